//! What the supervisor does with each message it takes from a stack: one rule set for every
//! way a stack is watched (launched by `run`, `identify` or `serve`; attached by `monitor` or
//! `record`; stepped in one thread by `simulate`).
//!
//! - A state published after a newer one, or repeated, breaks the device's contract: the run
//!   stops (process died).
//! - A gap: in lockstep queues never drop, so after the first state the monitor sees (which
//!   may be any: it may have attached late) a gap is the stack's protocol error and the run
//!   stops; on the wall clock the monitor is the one reader allowed to fall behind, and what
//!   it never saw is counted (and recorded as lost).
//! - Every state goes into the metrics and, when recording, to the file; setpoints,
//!   commands, plans and statistics go to the file as they come.
//! - A recording that fails is said once and given up; the run goes on (the motor comes
//!   first), and its report says the recording is incomplete.

use crate::record::recording::Recording;
use crate::report::metrics::{Graded, Metrics, RunReport};
use crate::report::outcome::Outcome;
use stepdrive_shared::axis::{AxisAck, AxisStatus};
use stepdrive_shared::messages::{
    state_flags, DriveCommand, DrivePlan, DriveState, TorqueSetpoint,
};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::trajectory::Reference;
use stepdrive_shared::{Method, Scenario};

/// Why watching a stack stopped before its last sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Stop {
    pub outcome: Outcome,
    pub because: String,
}

impl Stop {
    pub fn new(outcome: Outcome, because: impl Into<String>) -> Self {
        Self {
            outcome,
            because: because.into(),
        }
    }
}

/// The per-message rules, the metrics and the recording of one run. See the module
/// documentation.
pub struct Observer<'r> {
    metrics: Metrics,
    recording: Option<&'r mut Recording>,
    recording_failed: Option<String>,
    /// Lockstep: every state after the first must be the next.
    synchronous: bool,
    last_seq: Option<u64>,
    /// States the monitor never saw, after the first it saw.
    lost: u64,
    first_ns: Option<u64>,
    last_ns: u64,
    last_seen: bool,
    last_fault: u32,
    /// The axis it watches: the one whose channels it records on.
    axis: u32,
    /// The newest state and status taken, whatever is graded (a stop at the end reads them).
    newest_state: Option<DriveState>,
    newest_status: Option<AxisStatus>,
    /// The run is over and the stack is being stopped: what comes is recorded, not graded
    /// (an interrupted profile's quick stop is not the profile's following error).
    winding_down: bool,
}

impl<'r> Observer<'r> {
    /// Watches a run of `s` in `mode`.
    pub fn new(s: &Scenario, mode: Mode) -> Self {
        Self {
            metrics: Metrics::new(s),
            recording: None,
            recording_failed: None,
            synchronous: mode == Mode::Lockstep,
            last_seq: None,
            lost: 0,
            first_ns: None,
            last_ns: 0,
            last_seen: false,
            last_fault: 0,
            axis: 0,
            newest_state: None,
            newest_status: None,
            winding_down: false,
        }
    }

    /// From now on what comes is recorded (and checked) but no longer graded: the run is
    /// over and the stack is being brought to a standstill.
    pub fn wind_down(&mut self) {
        // The states waiting for their ticks' statuses are the run's: graded (and recorded)
        // with what has come, before what follows is only recorded.
        self.grading(|m, graded| m.flush_graded(graded));
        self.winding_down = true;
    }

    /// Watches axis `axis` of a multi-axis stack (`s` is that axis's scenario).
    pub fn on_axis(mut self, axis: u32) -> Self {
        self.axis = axis;
        self
    }

    /// Runs `f` on `other` (another axis's observer) with this observer's recording lent to
    /// it, so that what `other` takes is recorded on its axis's channels of the one file.
    /// A recording `other` gives up is given up here too.
    pub fn lending<T>(
        &mut self,
        other: &mut Observer<'r>,
        f: impl FnOnce(&mut Observer<'r>) -> T,
    ) -> T {
        other.recording = self.recording.take();
        let out = f(other);
        self.recording = other.recording.take();
        if let Some(why) = other.recording_failed.take() {
            self.recording = None;
            self.recording_failed.get_or_insert(why);
        }
        out
    }

    /// Records what it takes into `recording`, on the channels of `method`, which begin now.
    pub fn recording(mut self, recording: Option<&'r mut Recording>, method: Method) -> Self {
        if let Some(r) = recording {
            r.set_lossless(self.synchronous);
            match r.begin(method) {
                Ok(()) => self.recording = Some(r),
                Err(e) => self.give_up_recording(e.to_string()),
            }
        }
        self
    }

    fn give_up_recording(&mut self, why: String) {
        tracing::error!("{why}; the rest of the run goes unrecorded");
        self.recording = None;
        self.recording_failed.get_or_insert(why);
    }

    /// Runs `f` on the recording, giving it up if it fails.
    fn record(
        &mut self,
        f: impl FnOnce(&mut Recording) -> Result<(), crate::record::recording::RecordError>,
    ) {
        if let Some(r) = self.recording.as_deref_mut() {
            if let Err(e) = f(r) {
                self.give_up_recording(e.to_string());
            }
        }
    }

    /// One state, by the rules. Stops the run if the stream broke its contract.
    pub fn state(&mut self, st: &DriveState) -> Result<(), Stop> {
        if let Some(last) = self.last_seq {
            if st.seq <= last {
                return Err(Stop::new(
                    Outcome::ProcessDied,
                    format!("the plant published sample {} after sample {last}", st.seq),
                ));
            }
            let gap = st.seq - last - 1;
            if gap > 0 {
                if self.synchronous {
                    return Err(Stop::new(
                        Outcome::ProcessDied,
                        format!(
                            "monitor expected sample {}, got {}: samples were lost",
                            last + 1,
                            st.seq
                        ),
                    ));
                }
                self.lost += gap;
                let axis = self.axis;
                self.record(|r| {
                    r.lost(axis, gap);
                    Ok(())
                });
            }
        }
        self.last_seq = Some(st.seq);
        self.first_ns.get_or_insert(st.publish_time_ns);
        self.last_ns = st.publish_time_ns;
        self.newest_state = Some(*st);
        if self.winding_down {
            // The stop at the end is recorded, not graded (an interrupted profile's quick
            // stop is no following error).
            let axis = self.axis;
            self.record(|r| r.state(axis, st, None));
        } else {
            self.grading(|m, graded| m.push_graded(st, graded));
        }
        self.last_seen |= st.flags & state_flags::LAST != 0;
        self.last_fault = st.fault;
        Ok(())
    }

    /// Runs `f` on the metrics, recording each state it grades with the θ_d it was graded
    /// against (so the file's θ_d is the figures', whatever order the drains met the
    /// states and setpoints in).
    fn grading(&mut self, f: impl FnOnce(&mut Metrics, &mut Graded)) {
        let axis = self.axis;
        let mut failed = None;
        let recording = &mut self.recording;
        let mut record = |st: &DriveState, r: Option<Reference>| {
            if let (None, Some(rec)) = (&failed, recording.as_deref_mut()) {
                failed = rec.state(axis, st, r).err();
            }
        };
        f(&mut self.metrics, &mut record);
        if let Some(e) = failed {
            self.give_up_recording(e.to_string());
        }
    }

    /// Every control that had come has been taken, the statuses first: the states their
    /// ticks cover are graded (and recorded).
    pub fn controls_taken(&mut self) {
        self.grading(|m, graded| m.controls_taken(graded));
    }

    pub fn setpoint(&mut self, sp: &TorqueSetpoint) {
        if !self.winding_down {
            self.metrics.setpoint(sp);
        }
        let axis = self.axis;
        self.record(|r| r.setpoint(axis, sp));
    }

    /// An axis command's answer (a program's move starts its figures).
    pub fn ack(&mut self, ack: &AxisAck) {
        if !self.winding_down {
            self.metrics.ack(ack);
        }
        let axis = self.axis;
        self.record(|r| r.ack(axis, ack));
    }

    /// The axis's status (its first fault is the run's).
    pub fn status(&mut self, st: &AxisStatus) {
        self.newest_status = Some(*st);
        if !self.winding_down {
            self.metrics.status(st);
        }
        let axis = self.axis;
        self.record(|r| r.status(axis, st));
    }

    pub fn command(&mut self, c: &DriveCommand) {
        let axis = self.axis;
        self.record(|r| r.command(axis, c));
    }

    pub fn plan(&mut self, p: &DrivePlan) {
        let axis = self.axis;
        self.record(|r| r.plan(axis, p));
    }

    pub fn stats(&mut self, report: &StatsReport) {
        self.record(|r| r.stats(report));
    }

    /// The emulated drive's true rotor state, recorded after the run.
    pub fn truth(&mut self, rows: &[stepdrive_emulated_drive::truth::TruthRow]) {
        self.record(|r| r.truth(rows));
    }

    /// The fault bits of the newest state seen.
    pub fn last_fault(&self) -> u32 {
        self.last_fault
    }

    /// The newest state taken.
    pub fn newest_state(&self) -> Option<&DriveState> {
        self.newest_state.as_ref()
    }

    /// The newest axis status taken (none when the controls are not read).
    pub fn newest_status(&self) -> Option<&AxisStatus> {
        self.newest_status.as_ref()
    }

    /// The run's last state has been seen.
    pub fn last_seen(&self) -> bool {
        self.last_seen
    }

    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// The index of the newest state seen, if any.
    pub fn last_seq(&self) -> Option<u64> {
        self.last_seq
    }

    /// States never seen after the first.
    pub fn lost(&self) -> u64 {
        self.lost
    }

    /// Wall time between the first and the last state seen, s.
    pub fn wall_s(&self) -> f64 {
        self.first_ns
            .map_or(0.0, |f| self.last_ns.saturating_sub(f) as f64 * 1e-9)
    }

    /// Why the recording is incomplete, if it is.
    pub fn recording_failed(&self) -> Option<&str> {
        self.recording_failed.as_deref()
    }

    /// The run's report: complete, or stopped by `stop` with what ran before.
    pub fn report(
        &mut self,
        method: Method,
        mode: &str,
        wall_s: f64,
        stop: Option<Stop>,
    ) -> RunReport {
        self.grading(|m, graded| m.flush_graded(graded));
        let mut report = match stop {
            None => self.metrics.finish(method, mode, wall_s),
            Some(s) => self
                .metrics
                .finish_early(method, mode, wall_s, s.outcome, s.because),
        };
        report.recording_error = self.recording_failed.clone();
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(seq: u64) -> DriveState {
        DriveState {
            seq,
            sample_time_s: seq as f64 * 50e-6,
            ..Default::default()
        }
    }

    #[test]
    fn a_sample_after_a_newer_one_stops_the_run_in_every_mode() {
        for mode in [Mode::Lockstep, Mode::Realtime] {
            let s = Scenario::default();
            let mut o = Observer::new(&s, mode);
            o.state(&state(5)).expect("the first may be any");
            o.state(&state(6)).expect("the next");
            let stop = o.state(&state(6)).expect_err("repeated");
            assert_eq!(stop.outcome, Outcome::ProcessDied);
            assert!(stop.because.contains("sample 6 after sample 6"), "{stop:?}");
        }
    }

    #[test]
    fn a_gap_stops_lockstep_and_is_counted_on_the_wall_clock() {
        let s = Scenario::default();
        let mut o = Observer::new(&s, Mode::Lockstep);
        o.state(&state(0)).expect("first");
        let stop = o.state(&state(3)).expect_err("a gap in lockstep");
        assert!(
            stop.because.contains("expected sample 1, got 3"),
            "{stop:?}"
        );

        let mut o = Observer::new(&s, Mode::Realtime);
        o.state(&state(10)).expect("first");
        o.state(&state(13)).expect("a gap is counted");
        o.state(&state(20)).expect("a gap is counted");
        assert_eq!(o.lost(), 8);
        assert_eq!(o.last_seq(), Some(20));
    }
}
