//! The run's figures of merit, computed from the plant's state stream alone (the truth), with
//! θ_d taken from the scenario's trajectory, so a controller cannot grade itself.

use crate::report::outcome::{
    fault_names, step_out_threshold_rad, FaultEvent, Outcome, LATCHED, MAX_UNSEEN_S,
    MIN_SEEN_FRACTION,
};
use crate::report::setpoints::SetpointHistory;
use serde::Serialize;
use std::collections::VecDeque;
use stepdrive_shared::axis::{axis_faults, request_flags, AxisAck, AxisStatus, RequestKind};
use stepdrive_shared::frames::dq_currents;
use stepdrive_shared::messages::{fault_bits, state_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::services::MONITOR_BUFFER;
use stepdrive_shared::trajectory::{Reference, Trapezoid};
use stepdrive_shared::{Method, Scenario};

/// One method's results: one object of the JSON `runs` array, one column of the table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunReport {
    pub method: String,
    pub mode: String,
    /// How the run ended (see [`crate::report::outcome`]).
    pub outcome: Outcome,
    /// False when the run stopped before its last sample: the figures cover what ran.
    pub complete: bool,
    /// Why it stopped early.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stopped_because: Option<String>,
    /// Why its recording is incomplete (the run went on without it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recording_error: Option<String>,
    /// A program's moves, one by one.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub moves: Vec<MoveReport>,
    /// The axis's first fault.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub axis_fault: Option<AxisFaultEvent>,
    /// When the position loop went silent and the current loop stopped the motor, s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub setpoint_stale_at_s: Option<f64>,
    /// When the first latched fault was cleared (a reset), s; absent: it stayed latched.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fault_cleared_at_s: Option<f64>,
    /// A multi-axis program's coordinated moves of this axis: the measured rotors' peak
    /// distance from the moves' straight lines (the contour error), rad.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub contour_peak_rad: Option<f64>,
    /// When |θ_d − θ| first passed the step-out threshold (one electrical period), s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stepped_out_at_s: Option<f64>,
    /// The time of the first sample the monitor missed (what an UNOBSERVED run lacks
    /// begins there), s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_missed_at_s: Option<f64>,
    /// The first latched fault.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fault: Option<FaultEvent>,
    /// max |θ_d − θ| over the cruise window, rad (null when the run never reached it).
    pub cruise_max_abs_error_rad: f64,
    /// max |θ_d − θ| over the whole run, rad (catches an excursion outside cruise).
    pub max_abs_error_rad: f64,
    /// mean θ_d − θ over the final window, rad.
    pub final_error_rad: f64,
    pub cruise_mean_id_a: f64,
    pub cruise_mean_iq_a: f64,
    /// K_m i_q averaged over the cruise window, N·m.
    pub cruise_mean_torque_nm: f64,
    /// R (i_a² + i_b²) averaged over the run, W.
    pub mean_copper_loss_w: f64,
    /// v_a i_a + v_b i_b averaged over the run, W.
    pub mean_input_power_w: f64,
    pub max_abs_voltage_v: f64,
    /// The largest phase voltage in the cruise window (what a disturbance at speed, e.g. a
    /// link dropout, does to the commands; the whole-run maximum is set by the start).
    pub cruise_max_abs_voltage_v: f64,
    /// R B ω_d / (K_m V_max N_r), rad.
    pub eq7_bound_rad: f64,
    pub sim_time_s: f64,
    pub wall_time_s: f64,
    /// Samples the monitor saw (the figures come from these alone).
    pub samples: u64,
    /// Samples seen that a commanded run's reader could not grade: sampled before the
    /// oldest setpoint it had (it attached before its controls' queues opened). They count
    /// for everything but |θ_d − θ|.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ungraded_samples: u64,
    /// Samples up to the last one seen that the monitor never saw (gaps in the index): lost
    /// on the wire, skipped by the bridge, or overwritten in the monitor's queue while it
    /// had no CPU.
    pub missed_samples: u64,
    /// Samples in the cruise window: seen, and missed.
    pub cruise_samples: u64,
    pub cruise_missed_samples: u64,
    /// The longest stretch of the run the monitor did not see, s.
    pub longest_gap_s: f64,
    /// Why the figures do not stand (outcome `unobserved`): which window was not seen.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unobserved: Option<String>,
    /// Samples during which the drive limited a phase voltage to ±V_bus.
    pub voltage_limited_samples: u64,
    /// Samples that carried a fault bit other than the bridge's DRIVE_SILENT.
    pub fault_samples: u64,
    /// Hardware: states the bridge published because the drive was silent (no valid
    /// SAMPLE for its silence window): the host heard nothing, the drive latched nothing.
    pub silent_samples: u64,
    /// Realtime only: loop timing, deadline misses, latencies.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timing: Option<crate::report::timing::TimingReport>,
    /// With a load step in `[plant.load]`: what the first one did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub load_step: Option<LoadStepReport>,
    /// Against an emulated drive: the same figures from the rotor's true state (the
    /// model's, from the electrical zero), where the ones above come from its sensors.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthReport>,
    /// A multi-axis stack's other axes (1, 2, ...), each judged by the same rules; the
    /// figures above are axis 0's.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub axes: Vec<AxisRun>,
}

/// One more axis of a multi-axis run: its own figures and outcome.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AxisRun {
    pub axis: usize,
    pub name: String,
    #[serde(flatten)]
    pub report: RunReport,
}

impl RunReport {
    /// How the run ended on its worst axis: what its exit code says.
    pub fn worst(&self) -> Outcome {
        self.axes
            .iter()
            .map(|a| a.report.outcome)
            .fold(self.outcome, Outcome::max)
    }
}

/// A run's figures from the true rotor state.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TruthReport {
    pub samples: u64,
    pub cruise_max_abs_error_rad: f64,
    pub max_abs_error_rad: f64,
    pub final_error_rad: f64,
}

/// The error after the plant's first load step, over [step, end of the cruise window] (or
/// the end of the run for a step after the cruise).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoadStepReport {
    pub at_s: f64,
    pub torque_nm: f64,
    /// max |θ_d − θ| from the step to the window's end, rad.
    pub peak_abs_error_rad: f64,
    /// From the step until |θ_d − θ| stays within [`RECOVERED_RAD`], s; null when it is
    /// not back by the window's end.
    pub back_within_1e4_rad_after_s: Option<f64>,
}

/// "Back" after a load step: within 1e-4 rad.
pub const RECOVERED_RAD: f64 = 1e-4;

#[derive(Debug, Clone, Copy)]
struct StepWatch {
    at: f64,
    torque: f64,
    until: f64,
    peak: f64,
    /// The last sample in the window above the threshold, and the last sample seen.
    last_above: Option<f64>,
    last_seen: Option<f64>,
}

impl StepWatch {
    fn new(s: &Scenario) -> Option<Self> {
        let step = s.plant.load.steps.first()?;
        let until = if step.at_s < s.metrics.cruise_end_s {
            s.metrics.cruise_end_s
        } else {
            s.duration_s()
        };
        Some(Self {
            at: step.at_s,
            torque: step.torque_nm,
            until,
            peak: 0.0,
            last_above: None,
            last_seen: None,
        })
    }

    fn push(&mut self, t: f64, abs_error: f64) {
        if t < self.at || t > self.until {
            return;
        }
        if abs_error.is_nan() || abs_error > self.peak {
            self.peak = abs_error;
        }
        if abs_error.is_nan() || abs_error > RECOVERED_RAD {
            self.last_above = Some(t);
        }
        self.last_seen = Some(t);
    }

    fn report(&self, period: f64) -> LoadStepReport {
        let back = match (self.last_above, self.last_seen) {
            (_, None) => None,
            (None, Some(_)) => Some(0.0),
            (Some(above), Some(seen)) if above < seen => Some(above + period - self.at),
            (Some(_), Some(_)) => None,
        };
        LoadStepReport {
            at_s: self.at,
            torque_nm: self.torque,
            peak_abs_error_rad: self.peak,
            back_within_1e4_rad_after_s: back,
        }
    }
}

/// Accumulates [`RunReport`] figures one state sample at a time; no allocation per sample.
#[derive(Debug, Clone)]
pub struct Metrics {
    trajectory: Trapezoid,
    cruise: (f64, f64),
    final_from: f64,
    r: f64,
    k_m: f64,
    n_r: f64,
    eq7: f64,
    cruise_max_abs_error: f64,
    max_abs_error: f64,
    cruise_sum_id: f64,
    cruise_sum_iq: f64,
    cruise_n: u64,
    final_sum_error: f64,
    final_n: u64,
    sum_copper: f64,
    sum_input: f64,
    intervals: u64,
    max_abs_voltage: f64,
    cruise_max_abs_voltage: f64,
    samples: u64,
    /// Samples with no setpoint known from before them (see [`RunReport::ungraded_samples`]).
    ungraded: u64,
    limited: u64,
    faults: u64,
    silent: u64,
    first_latched: Option<FaultEvent>,
    step_out_rad: f64,
    previous_i: Option<[f64; 2]>,
    last_time: f64,
    step: Option<StepWatch>,
    period: f64,
    sample_hz: f64,
    /// Samples in the run: a gap never counts past its end, whatever index a state carries.
    run_samples: u64,
    /// A served stack runs on before and after a reader attaches: the reader's window
    /// starts at the first sample it sees, not at sample 0.
    endless: bool,
    /// The index of the last sample pushed, and what the gaps before it held.
    last_seq: Option<u64>,
    missed: u64,
    cruise_missed: u64,
    final_missed: u64,
    longest_gap: u64,
    /// Where the longest gap began, and the first sample missed.
    longest_gap_from: u64,
    first_missed: Option<u64>,
    /// A commanded run (a program, a served stack): θ_d from the position loop's setpoints,
    /// the states waiting for the setpoint that covers them, and each move's figures.
    program: Option<ProgramReference>,
    /// The first state whose command came from a current loop stopping the motor on its
    /// own (the position loop went silent), and the axis's first fault.
    first_stale: Option<(u64, f64)>,
    /// The first sample after the first latched fault with none latched (a reset), s.
    cleared_at: Option<f64>,
    /// The first sample beyond the step-out threshold, s.
    stepped_out_at: Option<f64>,
    axis_fault: Option<AxisFaultEvent>,
    contour_peak: Option<f64>,
}

/// The axis faulted: when, and why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AxisFaultEvent {
    pub sim_time_s: f64,
    pub bits: u32,
    pub faults: Vec<&'static str>,
    /// θ_d − θ when it faulted, rad.
    pub following_error_rad: f64,
}

/// A commanded run's reference and moves, graded on the stack's timeline. The monitor takes
/// states, setpoints, answers and statuses from separate queues, in whatever order its
/// drains meet them; what a state is graded against, and which move its figures go to, must
/// not depend on that. So a state waits until every control up to its sample has come: the
/// position loop publishes a tick's answers and setpoint before that tick's status, and the
/// supervisor takes the statuses first ([`Metrics::controls_taken`] after them), so a status
/// of a tick at or after the state's sample says so. The answers and statuses are then
/// applied in their ticks' order between the states: a command taken at a tick after the
/// states before that tick's sample and before the state of that sample (whose setpoint
/// carries the command out).
#[derive(Debug, Clone)]
struct ProgramReference {
    setpoints: SetpointHistory,
    pending: VecDeque<DriveState>,
    /// Commands taken, and what the statuses told, not yet applied (in their ticks' order).
    commands: VecDeque<Taken>,
    told: VecDeque<Told>,
    /// The newest status's tick time, and the one of the last complete take of the
    /// controls: every control up to it has come.
    newest_status_s: f64,
    known_s: f64,
    moves: Vec<MoveWatch>,
    /// The move the samples' figures go to (playing, or settling after its end), and one
    /// queued "after the current move".
    current: Option<usize>,
    queued: Option<usize>,
}

/// Told each state as it is graded, with the θ_d, ω_d, α_d it was graded against (`None`:
/// no setpoint was known), in the states' order.
pub type Graded<'a> = dyn FnMut(&DriveState, Option<Reference>) + 'a;

/// States kept waiting for their tick's controls at most (then graded against the newest
/// known).
const PENDING_STATES: usize = 16_384;
/// Commands kept waiting to be applied at most (then applied at once).
const PENDING_COMMANDS: usize = 1024;
/// Statuses kept waiting at most: one a tick, over the states' queue and some.
const PENDING_STATUSES: usize = MONITOR_BUFFER + 64;

/// A command the axis took, as the moves need it.
#[derive(Debug, Clone, Copy)]
struct Taken {
    t: f64,
    kind: RequestKind,
    flags: u32,
    seq: u64,
    target: f64,
}

/// What a status told: at its tick, the axis's last command and target.
#[derive(Debug, Clone, Copy)]
struct Told {
    t: f64,
    last_kind: u32,
    last_seq: u64,
    target: f64,
}

impl ProgramReference {
    /// The move taking the samples is still under way (not at its target, not replaced).
    fn busy(&self) -> bool {
        self.current
            .and_then(|i| self.moves.get(i))
            .is_some_and(|m| m.end_s.is_none() && m.retargeted_s.is_none())
    }

    /// A command taken at its tick: a move starts (or waits "after the current move"), and
    /// a move, a jog, a stop, a quick stop, a disable or a stream replaces the move under
    /// way and discards the queued one.
    fn apply(&mut self, c: &Taken) {
        let replaces = matches!(
            c.kind,
            RequestKind::Move
                | RequestKind::Jog
                | RequestKind::Stop
                | RequestKind::QuickStop
                | RequestKind::Shutdown
                | RequestKind::DisableVoltage
                | RequestKind::DisableOperation
                | RequestKind::StreamStart
        );
        if !replaces {
            return;
        }
        let busy = self.busy();
        let after =
            c.kind == RequestKind::Move && busy && c.flags & request_flags::AFTER_CURRENT != 0;
        if let Some(q) = self.queued.take() {
            self.moves[q].replaced(c.t, c.kind, true);
        }
        if !after {
            if let Some(m) = self.current.take().and_then(|i| self.moves.get_mut(i)) {
                if busy {
                    m.replaced(c.t, c.kind, false);
                }
            }
        }
        if c.kind != RequestKind::Move {
            return;
        }
        // The move's target until the axis's status tells it (a relative move counts from
        // the target before it, or from where the axis stands): the last move's plus the
        // step.
        let base = self.moves.last().map_or(0.0, |m| m.target);
        let target = if c.flags & request_flags::RELATIVE != 0 {
            base + c.target
        } else {
            c.target
        };
        let i = self.moves.len();
        self.moves.push(MoveWatch {
            start_s: c.t,
            target,
            seq: c.seq,
            // A queued move's target is its command's: the status names the axis's
            // target, the playing move's until the queued one starts.
            target_told: after,
            end_s: None,
            peak: 0.0,
            samples: 0,
            last_outside: None,
            last_seen: c.t,
            retargeted_s: None,
            replaced_by: None,
            discarded: false,
        });
        match after {
            true => self.queued = Some(i),
            false => self.current = Some(i),
        }
    }

    /// A status: the target of the move its tick took, if the move's command did not say.
    fn tell(&mut self, s: &Told) {
        if s.last_kind != RequestKind::Move as u32 {
            return;
        }
        if let Some(m) = self.moves.last_mut() {
            if !m.target_told && s.last_seq == m.seq {
                m.target = s.target;
                m.target_told = true;
            }
        }
    }

    /// Applies the commands and statuses of ticks up to `t` s (all: `None`), in their
    /// ticks' order (a tick's commands before its status).
    fn apply_until(&mut self, t: Option<f64>) {
        let due = |at: f64| t.is_none_or(|t| at <= t);
        loop {
            let command = self.commands.front().map(|c| c.t).filter(|&at| due(at));
            let status = self.told.front().map(|s| s.t).filter(|&at| due(at));
            match (command, status) {
                (Some(c), s) if s.is_none_or(|s| c <= s) => {
                    if let Some(c) = self.commands.pop_front() {
                        self.apply(&c);
                    }
                }
                (_, Some(_)) => {
                    if let Some(s) = self.told.pop_front() {
                        self.tell(&s);
                    }
                }
                _ => return,
            }
        }
    }

    /// A sample of the rotor at `t` graded against `r`: into the figures of the move under
    /// way (a queued move starts where the one before it reaches its target).
    fn grade(&mut self, t: f64, theta: f64, r: &Reference) {
        if let (Some(c), Some(q)) = (self.current, self.queued) {
            if let Some(end) = self.moves[c].end_s {
                self.moves[q].start_s = end;
                self.current = Some(q);
                self.queued = None;
            }
        }
        if let Some(m) = self
            .current
            .and_then(|i| self.moves.get_mut(i))
            .filter(|m| t >= m.start_s)
        {
            m.push(t, theta, r);
        }
    }
}

/// One move of a program: from the tick that took it to the next move or the run's end.
#[derive(Debug, Clone, Copy)]
struct MoveWatch {
    start_s: f64,
    target: f64,
    /// The move's command, and whether the axis's status has told its target yet.
    seq: u64,
    target_told: bool,
    /// The trajectory reached the target (θ_d on it, ω_d zero).
    end_s: Option<f64>,
    peak: f64,
    samples: u64,
    /// After the end: the last sample outside the settle window, and the last seen.
    last_outside: Option<f64>,
    last_seen: f64,
    /// Replaced by a later command (a "change immediately" move, a jog, a stop, ...) before
    /// it ended, at this time, and by which; discarded: queued, and replaced before it
    /// started.
    retargeted_s: Option<f64>,
    replaced_by: Option<RequestKind>,
    discarded: bool,
}

/// One move's figures.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MoveReport {
    pub start_s: f64,
    pub target_rad: f64,
    /// From the command (a queued move: from the end of the one before it) to the trajectory
    /// at its target, s (null: never got there).
    pub duration_s: Option<f64>,
    /// A later command replaced it before it got there, at this time, s (null: none did).
    pub retargeted_at_s: Option<f64>,
    /// That command: `move` (a "change immediately" move), `jog`, `stop`, `quick-stop`,
    /// `disable-voltage`, `stream-start`, ...
    #[serde(skip_serializing_if = "Option::is_none")]
    pub replaced_by: Option<&'static str>,
    /// Queued "after the current move", and replaced before it started: it never played.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub discarded: bool,
    /// max |θ_d − θ| over the move, rad (null: no sample of it was seen).
    pub peak_abs_error_rad: Option<f64>,
    /// From the trajectory's end until |target − θ| stays within [`RECOVERED_RAD`], s (null:
    /// not settled before the next move or the run's end).
    pub settle_s: Option<f64>,
}

impl MoveWatch {
    fn push(&mut self, t: f64, theta: f64, r: &Reference) {
        let e = (r.theta - theta).abs();
        if e.is_nan() || e > self.peak {
            self.peak = e;
        }
        self.samples += 1;
        if self.end_s.is_none() && r.theta == self.target && r.omega == 0.0 {
            self.end_s = Some(t);
        }
        if self.end_s.is_some() {
            let off = (self.target - theta).abs();
            if off.is_nan() || off > RECOVERED_RAD {
                self.last_outside = Some(t);
            }
        }
        self.last_seen = t;
    }

    /// Replaced at `t` by a command of `kind`; `discarded`: it waited queued.
    fn replaced(&mut self, t: f64, kind: RequestKind, discarded: bool) {
        self.retargeted_s = Some(t);
        self.replaced_by = Some(kind);
        self.discarded = discarded;
    }

    fn report(&self, period: f64) -> MoveReport {
        let settle_s = match (self.end_s, self.last_outside) {
            (None, _) => None,
            (Some(_), None) => Some(0.0),
            (Some(end), Some(out)) if out < self.last_seen => Some(out + period - end),
            (Some(_), Some(_)) => None,
        };
        MoveReport {
            start_s: self.start_s,
            target_rad: self.target,
            duration_s: self.end_s.map(|e| e - self.start_s),
            retargeted_at_s: self.retargeted_s,
            replaced_by: self.replaced_by.map(RequestKind::name),
            discarded: self.discarded,
            peak_abs_error_rad: (self.samples > 0).then_some(self.peak),
            settle_s,
        }
    }
}

impl Metrics {
    pub fn new(s: &Scenario) -> Self {
        // The figures are the truth's: the plant's motor, not the controller's model.
        let plant = s.plant_motor();
        Self {
            trajectory: Trapezoid::new(&s.trajectory),
            // A commanded axis (a program, a served stack) has no cruise: its moves are its
            // own.
            cruise: match s.runs_profile() {
                true => (s.metrics.cruise_start_s, s.metrics.cruise_end_s),
                false => (f64::INFINITY, f64::NEG_INFINITY),
            },
            final_from: s.final_window_start_s(),
            r: plant.resistance_ohm,
            k_m: plant.torque_constant_nm_per_a,
            n_r: plant.n_r(),
            eq7: s.eq7_bound_rad(),
            cruise_max_abs_error: 0.0,
            max_abs_error: 0.0,
            cruise_sum_id: 0.0,
            cruise_sum_iq: 0.0,
            cruise_n: 0,
            final_sum_error: 0.0,
            final_n: 0,
            sum_copper: 0.0,
            sum_input: 0.0,
            intervals: 0,
            max_abs_voltage: 0.0,
            cruise_max_abs_voltage: 0.0,
            samples: 0,
            ungraded: 0,
            limited: 0,
            faults: 0,
            silent: 0,
            first_latched: None,
            step_out_rad: step_out_threshold_rad(s),
            previous_i: None,
            last_time: 0.0,
            step: StepWatch::new(s),
            period: s.sample_period_s(),
            sample_hz: s.rates.current_loop_hz,
            run_samples: s.sample_count(),
            endless: s.run.until_stopped,
            last_seq: None,
            missed: 0,
            cruise_missed: 0,
            final_missed: 0,
            longest_gap: 0,
            longest_gap_from: 0,
            first_missed: None,
            program: (!s.runs_profile()).then(|| ProgramReference {
                setpoints: SetpointHistory::for_scenario(s),
                pending: VecDeque::with_capacity(PENDING_STATES),
                commands: VecDeque::with_capacity(PENDING_COMMANDS),
                told: VecDeque::with_capacity(PENDING_STATUSES),
                newest_status_s: f64::NEG_INFINITY,
                known_s: f64::NEG_INFINITY,
                moves: Vec::with_capacity(s.program.len()),
                current: None,
                queued: None,
            }),
            first_stale: None,
            cleared_at: None,
            stepped_out_at: None,
            axis_fault: None,
            contour_peak: None,
        }
    }

    /// The samples `from..to` never arrived: count them, and those of them in the cruise and
    /// final windows (O(samples missed), only when some were).
    fn missed_between(&mut self, from: u64, to: u64) {
        let to = to.min(self.run_samples.max(from));
        self.missed += to - from;
        if to - from > self.longest_gap {
            self.longest_gap = to - from;
            self.longest_gap_from = from;
        }
        if to > from {
            self.first_missed.get_or_insert(from);
        }
        for k in from..to {
            let t = k as f64 / self.sample_hz;
            let (tau, _) = self.trajectory.phase(t);
            if tau >= self.cruise.0 && tau <= self.cruise.1 {
                self.cruise_missed += 1;
            }
            if t >= self.final_from {
                self.final_missed += 1;
            }
        }
    }

    /// [`Self::push_graded`], for the figures alone.
    pub fn push(&mut self, s: &DriveState) {
        self.push_graded(s, &mut |_, _| {});
    }

    /// One state sample: graded at once against the scenario's profile, or, in a commanded
    /// run, once the controls of its tick have come ([`ProgramReference`]). `graded` is told
    /// each state graded and its θ_d, ω_d, α_d (`None`: no setpoint known), in order.
    pub fn push_graded(&mut self, s: &DriveState, graded: &mut Graded) {
        let Some(p) = self.program.as_mut() else {
            let reference = self.trajectory.at(s.sample_time_s);
            self.account(s, Some(reference));
            graded(s, Some(reference));
            return;
        };
        if p.pending.len() == PENDING_STATES {
            self.grade_front(graded);
        }
        if let Some(p) = self.program.as_mut() {
            p.pending.push_back(*s);
        }
        self.grade_pending(false, graded);
    }

    /// A commanded run: the position loop's setpoint, the reference from its sample on.
    pub fn setpoint(&mut self, sp: &TorqueSetpoint) {
        if let Some(p) = self.program.as_mut() {
            p.setpoints.push(sp);
        }
    }

    /// The controls that had come have all been taken, the statuses first: every control
    /// up to the newest status's tick is in, and the states up to it are graded.
    pub fn controls_taken(&mut self, graded: &mut Graded) {
        if let Some(p) = self.program.as_mut() {
            p.known_s = p.newest_status_s;
        }
        self.grade_pending(false, graded);
    }

    /// Grades the oldest waiting state, after the controls of the ticks up to its sample.
    fn grade_front(&mut self, graded: &mut Graded) {
        let Some(p) = self.program.as_mut() else {
            return;
        };
        let Some(st) = p.pending.pop_front() else {
            return;
        };
        p.apply_until(Some(st.sample_time_s));
        let r = p.setpoints.at(st.sample_time_s);
        self.account(&st, r);
        graded(&st, r);
    }

    /// Grades the waiting states whose ticks' controls have all come (`all`: every one,
    /// and then every control left: the run is over), in order.
    fn grade_pending(&mut self, all: bool, graded: &mut Graded) {
        loop {
            let Some(p) = self.program.as_mut() else {
                return;
            };
            let known = p.known_s;
            let due = p
                .pending
                .front()
                .is_some_and(|st| all || st.sample_time_s <= known);
            if !due {
                if all {
                    p.apply_until(None);
                }
                return;
            }
            self.grade_front(graded);
        }
    }

    /// [`Self::flush_graded`], for the figures alone.
    pub fn flush(&mut self) {
        self.flush_graded(&mut |_, _| {});
    }

    /// Grades every state still waiting (the run is over, its controls all taken).
    pub fn flush_graded(&mut self, graded: &mut Graded) {
        self.grade_pending(true, graded);
    }

    /// A commanded run's answer to a command: a taken one is applied at its tick (a move
    /// starts its figures).
    pub fn ack(&mut self, ack: &AxisAck) {
        let Some(p) = self.program.as_mut() else {
            return;
        };
        let Some(kind) = RequestKind::from_u32(ack.request.kind).filter(|_| ack.taken()) else {
            return;
        };
        if p.commands.len() == PENDING_COMMANDS {
            if let Some(c) = p.commands.pop_front() {
                p.apply(&c);
            }
        }
        p.commands.push_back(Taken {
            t: ack.t_s,
            kind,
            flags: ack.request.flags,
            seq: ack.request.seq,
            target: ack.request.target_rad,
        });
    }

    /// The axis's status: its first fault is the run's; its tick's controls have all been
    /// published (see [`ProgramReference`]).
    pub fn status(&mut self, st: &AxisStatus) {
        if let Some(p) = self.program.as_mut() {
            if p.told.len() == PENDING_STATUSES {
                if let Some(s) = p.told.pop_front() {
                    p.tell(&s);
                }
            }
            p.told.push_back(Told {
                t: st.t_s,
                last_kind: st.last_kind,
                last_seq: st.last_seq,
                target: st.target_rad,
            });
            p.newest_status_s = p.newest_status_s.max(st.t_s);
        }
        if st.contour_rad.is_finite() {
            self.contour_peak = Some(
                self.contour_peak
                    .map_or(st.contour_rad, |c| c.max(st.contour_rad)),
            );
        }
        if st.fault != 0 && self.axis_fault.is_none() {
            self.axis_fault = Some(AxisFaultEvent {
                sim_time_s: st.t_s,
                bits: st.fault,
                faults: axis_fault_names(st.fault),
                following_error_rad: st.following_error_rad,
            });
        }
    }

    /// One state into the figures. `reference`: θ_d, ω_d, α_d at its sample; `None` in a
    /// commanded run when the reader has no setpoint from before it (it attached, or its
    /// controls' queues opened, after the state's): then the sample counts for everything
    /// but the following error, which nobody can tell.
    fn account(&mut self, s: &DriveState, reference: Option<Reference>) {
        let expected = match self.last_seq {
            Some(q) => q + 1,
            None if self.endless => s.seq,
            None => 0,
        };
        if s.seq > expected {
            self.missed_between(expected, s.seq);
            // The interval ending here did not start at the last sample seen.
            self.previous_i = None;
        }
        self.last_seq = Some(self.last_seq.map_or(s.seq, |q| q.max(s.seq)));
        let t = s.sample_time_s;
        let error = reference.map(|r| r.theta - s.theta_rad);
        let i = [s.i_a_a, s.i_b_a];
        // The cruise window applies to every pass of a repeating move; on the way back the
        // torque and i_q are negative, so they are taken along the direction of motion.
        let (tau, mirrored) = self.trajectory.phase(t);
        let direction = if mirrored { -1.0 } else { 1.0 };
        let cruise = tau >= self.cruise.0 && tau <= self.cruise.1;
        if let (Some(error), Some(reference)) = (error, reference.as_ref()) {
            // NaN-safe: a NaN error must show up, not be skipped by `max`.
            let abs = error.abs();
            if abs.is_nan() || abs > self.max_abs_error {
                self.max_abs_error = abs;
            }
            if self.stepped_out_at.is_none() && (abs.is_nan() || abs > self.step_out_rad) {
                self.stepped_out_at = Some(t);
            }
            if cruise && (abs.is_nan() || abs > self.cruise_max_abs_error) {
                self.cruise_max_abs_error = abs;
            }
            if let Some(w) = self.step.as_mut() {
                w.push(t, abs);
            }
            if let Some(p) = self.program.as_mut() {
                p.grade(t, s.theta_rad, reference);
            }
            if t >= self.final_from {
                self.final_sum_error += error;
                self.final_n += 1;
            }
        } else {
            self.ungraded += 1;
        }
        if cruise {
            let (id, iq) = dq_currents(s.theta_rad, self.n_r, i[0], i[1]);
            self.cruise_sum_id += id;
            self.cruise_sum_iq += direction * iq;
            self.cruise_n += 1;
            self.cruise_max_abs_voltage = self
                .cruise_max_abs_voltage
                .max(s.v_a_v.abs())
                .max(s.v_b_v.abs());
        }
        if s.flags & state_flags::SETPOINT_STALE != 0 && self.first_stale.is_none() {
            self.first_stale = Some((s.seq, t));
        }
        // The voltage in this sample was applied over the interval that ends here: average
        // power over the interval by the trapezoid rule on the currents at its ends.
        if let Some(p) = self.previous_i {
            let copper = 0.5 * self.r * (p[0] * p[0] + p[1] * p[1] + i[0] * i[0] + i[1] * i[1]);
            let input = 0.5 * (s.v_a_v * (p[0] + i[0]) + s.v_b_v * (p[1] + i[1]));
            self.sum_copper += copper;
            self.sum_input += input;
            self.intervals += 1;
        }
        self.previous_i = Some(i);
        self.max_abs_voltage = self.max_abs_voltage.max(s.v_a_v.abs()).max(s.v_b_v.abs());
        self.samples += 1;
        if s.flags & state_flags::VOLTAGE_LIMITED != 0 {
            self.limited += 1;
        }
        self.silent += u64::from(s.fault & fault_bits::DRIVE_SILENT != 0);
        if s.fault & !fault_bits::DRIVE_SILENT != 0 {
            self.faults += 1;
        }
        if self.first_latched.is_some() && s.fault & LATCHED == 0 && self.cleared_at.is_none() {
            self.cleared_at = Some(t);
        }
        if s.fault & LATCHED != 0 && self.first_latched.is_none() {
            let seen_unix_s = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            self.first_latched = Some(FaultEvent {
                sample: s.seq,
                sim_time_s: t,
                seen_unix_s,
                bits: s.fault,
                faults: fault_names(s.fault),
            });
        }
        self.last_time = t;
    }

    /// Samples with a fault bit so far, the bridge's DRIVE_SILENT aside.
    pub fn faulted_samples(&self) -> u64 {
        self.faults
    }

    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// The newest sample's time, s.
    pub fn sim_time_s(&self) -> f64 {
        self.last_time
    }

    /// How a run that reached its end went: a latched fault, then a step-out, then whether
    /// the monitor saw enough of it, decide.
    pub fn outcome(&self) -> Outcome {
        if self.first_latched.is_some() || self.axis_fault.is_some() {
            Outcome::Fault
        } else if self.first_stale.is_some() {
            Outcome::ProcessDied
        } else if self.max_abs_error.is_nan() || self.max_abs_error > self.step_out_rad {
            Outcome::SteppedOut
        } else if self.unobserved().is_some() {
            Outcome::Unobserved
        } else {
            Outcome::Ok
        }
    }

    /// Which window of the run (up to its last sample seen) the monitor saw less than
    /// [`MIN_SEEN_FRACTION`] of, if any. A window the run never reached (a `--duration`
    /// shorter than the profile) has nothing to see and is not one.
    pub fn unobserved(&self) -> Option<String> {
        let windows = [
            ("the run", self.samples, self.missed),
            ("the cruise window", self.cruise_n, self.cruise_missed),
            ("the final window", self.final_n, self.final_missed),
        ];
        let gap_s = self.longest_gap as f64 / self.sample_hz;
        if gap_s > MAX_UNSEEN_S {
            return Some(format!(
                "the monitor missed {:.3} s of the run in a row from t = {:.4} s (at most \
                 {MAX_UNSEEN_S} s allowed)",
                gap_s,
                self.longest_gap_from as f64 / self.sample_hz
            ));
        }
        // A following error told by fewer than half the samples seen is not the run's.
        let graded = self.samples.saturating_sub(self.ungraded);
        if self.ungraded > 0 && (graded as f64) < MIN_SEEN_FRACTION * self.samples as f64 {
            return Some(format!(
                "the reader could grade {graded} of the {} samples it saw: it had no setpoint \
                 from before the others (at least {:.0} % needed)",
                self.samples,
                100.0 * MIN_SEEN_FRACTION
            ));
        }
        let first = self.first_missed_s().unwrap_or(f64::NAN);
        windows
            .into_iter()
            .find(|&(_, seen, missed)| {
                missed > 0 && (seen as f64) < MIN_SEEN_FRACTION * (seen + missed) as f64
            })
            .map(|(name, seen, missed)| {
                format!(
                    "the monitor saw {seen} of the {} samples of {name} ({:.1} %; at least {:.0} % \
                     needed; the first it missed at t = {first:.4} s)",
                    seen + missed,
                    100.0 * seen as f64 / (seen + missed) as f64,
                    100.0 * MIN_SEEN_FRACTION
                )
            })
    }

    /// The time of the first sample the monitor missed, s.
    pub fn first_missed_s(&self) -> Option<f64> {
        self.first_missed.map(|k| k as f64 / self.sample_hz)
    }

    /// The report of a run that reached its last sample.
    pub fn finish(&self, method: Method, mode: &str, wall_time_s: f64) -> RunReport {
        self.report(method, mode, wall_time_s, self.outcome(), None)
    }

    /// The report of a run that stopped early, with what it gathered.
    pub fn finish_early(
        &self,
        method: Method,
        mode: &str,
        wall_time_s: f64,
        outcome: Outcome,
        because: String,
    ) -> RunReport {
        let outcome = outcome.max(self.outcome());
        self.report(method, mode, wall_time_s, outcome, Some(because))
    }

    fn report(
        &self,
        method: Method,
        mode: &str,
        wall_time_s: f64,
        outcome: Outcome,
        stopped_because: Option<String>,
    ) -> RunReport {
        let mean = |sum: f64, n: u64| if n == 0 { f64::NAN } else { sum / n as f64 };
        let cruise_mean_iq = mean(self.cruise_sum_iq, self.cruise_n);
        RunReport {
            method: method.as_str().to_string(),
            mode: mode.to_string(),
            outcome,
            complete: stopped_because.is_none(),
            stopped_because,
            recording_error: None,
            fault: self.first_latched.clone(),
            cruise_max_abs_error_rad: if self.cruise_n == 0 {
                f64::NAN
            } else {
                self.cruise_max_abs_error
            },
            max_abs_error_rad: self.max_abs_error,
            final_error_rad: mean(self.final_sum_error, self.final_n),
            cruise_mean_id_a: mean(self.cruise_sum_id, self.cruise_n),
            cruise_mean_iq_a: cruise_mean_iq,
            cruise_mean_torque_nm: self.k_m * cruise_mean_iq,
            mean_copper_loss_w: mean(self.sum_copper, self.intervals),
            mean_input_power_w: mean(self.sum_input, self.intervals),
            max_abs_voltage_v: self.max_abs_voltage,
            // A run that never reached the cruise window has no cruise voltage (not 0 V).
            cruise_max_abs_voltage_v: if self.cruise_n == 0 {
                f64::NAN
            } else {
                self.cruise_max_abs_voltage
            },
            eq7_bound_rad: self.eq7,
            sim_time_s: self.last_time,
            wall_time_s,
            samples: self.samples,
            ungraded_samples: self.ungraded,
            missed_samples: self.missed,
            cruise_samples: self.cruise_n,
            cruise_missed_samples: self.cruise_missed,
            longest_gap_s: self.longest_gap as f64 / self.sample_hz,
            unobserved: self.unobserved(),
            first_missed_at_s: self.first_missed_s(),
            voltage_limited_samples: self.limited,
            fault_samples: self.faults,
            silent_samples: self.silent,
            timing: None,
            load_step: self.step.map(|w| w.report(self.period)),
            truth: None,
            moves: self
                .program
                .as_ref()
                .map(|p| p.moves.iter().map(|m| m.report(self.period)).collect())
                .unwrap_or_default(),
            axis_fault: self.axis_fault.clone(),
            setpoint_stale_at_s: self.first_stale.map(|(_, t)| t),
            stepped_out_at_s: self.stepped_out_at,
            fault_cleared_at_s: self.cleared_at,
            contour_peak_rad: self.contour_peak,
            axes: Vec::new(),
        }
    }
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

/// The axis's fault bits by name.
pub fn axis_fault_names(bits: u32) -> Vec<&'static str> {
    [
        (axis_faults::FOLLOWING_ERROR, "FOLLOWING_ERROR"),
        (axis_faults::DRIVE, "DRIVE"),
        (axis_faults::SETPOINT_STALE, "SETPOINT_STALE"),
        (axis_faults::TRAJECTORY, "TRAJECTORY"),
    ]
    .into_iter()
    .filter(|(b, _)| bits & b != 0)
    .map(|(_, n)| n)
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_shared::axis::AxisRequest;

    fn state(s: &Scenario, k: u64) -> DriveState {
        let t = k as f64 / s.rates.current_loop_hz;
        DriveState {
            seq: k,
            sample_time_s: t,
            // On the trajectory: the motor follows.
            theta_rad: Trapezoid::new(&s.trajectory).at(t).theta,
            ..Default::default()
        }
    }

    /// A commanded run's stream as the stack publishes it, tick by tick (ratio 10): the
    /// states of the tick's samples, then its answers, setpoint and status. The setpoints
    /// ramp θ_d from 0 to 1 rad from tick 2 to tick 12 and stand at 1 rad after; the rotor
    /// 1e-6 rad behind. A move to 1 at tick 2, one to 2 queued after it at
    /// tick 5, a jog at tick 8 (replacing the first, discarding the queued one), a move to
    /// 1 at tick 20 that gets there at once.
    struct Stream {
        ticks: Vec<(Vec<DriveState>, Vec<AxisAck>, TorqueSetpoint, AxisStatus)>,
    }

    fn program_stream() -> (Scenario, Stream) {
        let s = Scenario::from_toml_str(
            "[[program]]\nat_s = 0.0\ncommand = \"enable\"\n[run]\nduration_s = 0.0149",
        )
        .expect("a program");
        let period = s.sample_period_s();
        let ratio = 10u64;
        let tick_s = period * ratio as f64;
        let theta_d = |t: f64| (t / tick_s - 2.0).clamp(0.0, 10.0) / 10.0;
        let omega_d = |t: f64| match (2.0..12.0).contains(&(t / tick_s)) {
            true => 0.1 / tick_s,
            false => 0.0,
        };
        let command = |tick: u64, kind: RequestKind, flags: u32, target: f64| AxisAck {
            request: AxisRequest {
                kind: kind as u32,
                seq: tick,
                flags,
                target_rad: target,
                ..Default::default()
            },
            tick,
            t_s: tick as f64 * tick_s,
            ..Default::default()
        };
        let ticks = (0..=s.sample_count() / ratio)
            .map(|tick| {
                let t = tick as f64 * tick_s;
                let states = (tick * ratio..((tick + 1) * ratio).min(s.sample_count()))
                    .map(|k| {
                        let ts = k as f64 * period;
                        DriveState {
                            seq: k,
                            sample_time_s: ts,
                            theta_rad: theta_d(ts) - 1e-6,
                            ..Default::default()
                        }
                    })
                    .collect();
                let acks = match tick {
                    2 => vec![command(2, RequestKind::Move, 0, 1.0)],
                    5 => vec![command(
                        5,
                        RequestKind::Move,
                        request_flags::AFTER_CURRENT,
                        2.0,
                    )],
                    8 => vec![command(8, RequestKind::Jog, 0, 0.0)],
                    20 => vec![command(20, RequestKind::Move, 0, 1.0)],
                    _ => Vec::new(),
                };
                let setpoint = TorqueSetpoint {
                    seq: tick,
                    sample_time_s: t,
                    theta_d_rad: theta_d(t),
                    omega_d_rad_s: omega_d(t),
                    ..Default::default()
                };
                let status = AxisStatus {
                    tick,
                    t_s: t,
                    last_kind: acks.last().map_or(0, |a| a.request.kind),
                    last_seq: tick,
                    target_rad: 1.0,
                    ..Default::default()
                };
                (states, acks, setpoint, status)
            })
            .collect();
        (s, Stream { ticks })
    }

    /// Feeds `stream` as a monitor whose states lag the controls by `lag` ticks takes it:
    /// at each drain the statuses, then the answers and setpoints, then the states.
    fn drained(s: &Scenario, stream: &Stream, lag: usize) -> Vec<MoveReport> {
        let mut m = Metrics::new(s);
        let n = stream.ticks.len();
        for i in 0..n + lag {
            if let Some((_, acks, sp, st)) = stream.ticks.get(i) {
                m.status(st);
                acks.iter().for_each(|a| m.ack(a));
                m.setpoint(sp);
                m.controls_taken(&mut |_, _| {});
            }
            if let Some((states, ..)) = i.checked_sub(lag).and_then(|j| stream.ticks.get(j)) {
                states.iter().for_each(|st| m.push(st));
            }
        }
        m.flush();
        m.finish(Method::Proposed, "lockstep", 0.0).moves
    }

    /// A program's moves are graded on the stack's timeline: the states before a command's
    /// tick go to the move before it, whether the monitor took the command before or after
    /// those states (before, a move replaced a tick later than it was, or not at all, by
    /// how the drains fell). A jog replaces the move under way and discards the one queued
    /// after it, which never played.
    #[test]
    fn a_programs_moves_are_the_same_whatever_order_the_drains_take_them_in() {
        let (s, stream) = program_stream();
        let prompt = drained(&s, &stream, 0);
        for lag in [1, 2, 7, 40] {
            assert_eq!(
                drained(&s, &stream, lag),
                prompt,
                "states {lag} ticks behind"
            );
        }
        let tick = 10.0 * s.sample_period_s();
        assert_eq!(prompt.len(), 3, "{prompt:?}");
        let (first, queued, last) = (&prompt[0], &prompt[1], &prompt[2]);
        assert_eq!(first.retargeted_at_s, Some(8.0 * tick), "{first:?}");
        assert_eq!(first.replaced_by, Some("jog"));
        assert!(!first.discarded && first.duration_s.is_none(), "{first:?}");
        // The samples of ticks 2 … 7: the rotor 1e-6 behind.
        assert!(
            first
                .peak_abs_error_rad
                .is_some_and(|p| (p - 1e-6).abs() < 1e-9),
            "{first:?}"
        );
        assert!(queued.discarded, "{queued:?}");
        assert_eq!(queued.retargeted_at_s, Some(8.0 * tick));
        assert_eq!(
            queued.peak_abs_error_rad, None,
            "it never played: {queued:?}"
        );
        assert_eq!(last.duration_s, Some(0.0), "{last:?}");
    }

    /// A reader attached to a served stack takes the states from its attach on, but its
    /// setpoints, answers and statuses only from when those queues opened: here 0.05 s
    /// into a move, the setpoint then at ω_d 5 rad/s and α_d 100 rad/s². The rotor follows
    /// θ_d exactly. The states before the first setpoint have no θ_d the reader can tell:
    /// they are counted, not graded. Before, they were graded against that setpoint
    /// carried back along its ω_d and α_d (0.5 rad at the attach, where θ_d was 0) and the
    /// reader reported STEPPED OUT for a move the axis made to 2.2e-6 rad.
    #[test]
    fn states_from_before_a_readers_first_setpoint_are_not_graded_against_it_carried_back() {
        let s = Scenario::from_toml_str(
            "[[program]]\nat_s = 0.0\ncommand = \"enable\"\n[run]\nduration_s = 0.2",
        )
        .expect("a program");
        let period = s.sample_period_s();
        let ratio = 10u64;
        let tick_s = period * ratio as f64;
        // The move from 0.1 s on, accelerating at 100 rad/s².
        let (start, alpha) = (0.1, 100.0);
        let reference = |t: f64| {
            let dt = (t - start).max(0.0);
            let a = if t >= start { alpha } else { 0.0 };
            Reference {
                theta: 0.5 * alpha * dt * dt,
                omega: alpha * dt,
                alpha: a,
            }
        };
        let (setpoints_from, statuses_from) = (0.15, 0.16);
        let mut m = Metrics::new(&s);
        // The move's answer is the acks' history: the newest when that queue opened.
        let mut ack_pending = true;
        for tick in 0..s.sample_count() / ratio {
            let t = tick as f64 * tick_s;
            if t >= statuses_from {
                m.status(&AxisStatus {
                    tick,
                    t_s: t,
                    last_kind: RequestKind::Move as u32,
                    last_seq: 7,
                    target_rad: 1.0,
                    ..Default::default()
                });
            }
            if t >= setpoints_from {
                if std::mem::take(&mut ack_pending) {
                    m.ack(&AxisAck {
                        request: AxisRequest {
                            kind: RequestKind::Move as u32,
                            seq: 7,
                            target_rad: 1.0,
                            ..Default::default()
                        },
                        tick: (start / tick_s).round() as u64,
                        t_s: start,
                        ..Default::default()
                    });
                }
                let r = reference(t);
                m.setpoint(&TorqueSetpoint {
                    seq: tick,
                    sample_time_s: t,
                    theta_d_rad: r.theta,
                    omega_d_rad_s: r.omega,
                    alpha_d_rad_s2: r.alpha,
                    ..Default::default()
                });
            }
            m.controls_taken(&mut |_, _| {});
            for k in tick * ratio..(tick + 1) * ratio {
                let ts = k as f64 * period;
                m.push(&DriveState {
                    seq: k,
                    sample_time_s: ts,
                    theta_rad: reference(ts).theta,
                    ..Default::default()
                });
            }
        }
        m.flush();
        let report = m.finish(Method::Proposed, "realtime", 0.0);
        assert_eq!(report.stepped_out_at_s, None, "{report:?}");
        assert!(report.max_abs_error_rad < 1e-9, "{report:?}");
        // Three quarters of it ungraded: no following error stands for the run.
        assert_eq!(report.outcome, Outcome::Unobserved, "{report:?}");
        assert!(
            report
                .unobserved
                .as_deref()
                .is_some_and(|u| u.contains("could grade 1000 of the 4000")),
            "{report:?}"
        );
        let before = (setpoints_from / period).round() as u64;
        assert_eq!(report.ungraded_samples, before, "{report:?}");
        assert_eq!(
            report.samples,
            s.sample_count() / ratio * ratio,
            "{report:?}"
        );
        // The move's figures come from the states it has a θ_d for.
        assert_eq!(report.moves.len(), 1, "{report:?}");
        assert!(
            report.moves[0].peak_abs_error_rad.is_some_and(|p| p < 1e-9),
            "{report:?}"
        );
    }

    /// A rotor that really slipped is still caught by a reader with a late first setpoint:
    /// the states it can grade carry the error.
    #[test]
    fn a_readers_late_first_setpoint_still_catches_a_slipped_rotor() {
        let s = Scenario::from_toml_str(
            "[[program]]\nat_s = 0.0\ncommand = \"enable\"\n[run]\nduration_s = 0.1",
        )
        .expect("a program");
        let period = s.sample_period_s();
        let mut m = Metrics::new(&s);
        for k in 0..s.sample_count() {
            let t = k as f64 * period;
            if k % 10 == 0 && k >= 1000 {
                m.status(&AxisStatus {
                    tick: k / 10,
                    t_s: t,
                    ..Default::default()
                });
                m.setpoint(&TorqueSetpoint {
                    seq: k / 10,
                    sample_time_s: t,
                    theta_d_rad: 1.0,
                    ..Default::default()
                });
                m.controls_taken(&mut |_, _| {});
            }
            // The rotor slipped a quarter turn behind θ_d = 1 before the reader's first
            // setpoint and stays there.
            m.push(&DriveState {
                seq: k,
                sample_time_s: t,
                theta_rad: 0.75 - 1.0,
                ..Default::default()
            });
        }
        m.flush();
        let report = m.finish(Method::Proposed, "realtime", 0.0);
        assert_eq!(report.outcome, Outcome::SteppedOut, "{report:?}");
        assert_eq!(report.stepped_out_at_s, Some(1000.0 * period), "{report:?}");
    }

    #[test]
    fn a_run_whose_cruise_the_monitor_never_saw_does_not_pass() {
        let s = Scenario::default();
        let total = s.sample_count();
        let mut m = Metrics::new(&s);
        // What a starved monitor sees: the start, then the newest 8192 samples of its queue.
        for k in (0..17_245).chain(total - 8192..total) {
            m.push(&state(&s, k));
        }
        assert_eq!(m.outcome(), Outcome::Unobserved);
        let r = m.finish(Method::Proposed, "hardware", 2.5);
        assert!(r.cruise_max_abs_error_rad.is_nan());
        assert_eq!(
            (r.cruise_samples, r.missed_samples),
            (0, total - 17_245 - 8192)
        );
        assert!(r.cruise_missed_samples > 11_000, "{r:?}");
        assert!(
            r.unobserved.as_deref().unwrap().contains("of the run"),
            "{r:?}"
        );
        // When: the first sample missed, in the words and in the JSON.
        let first = 17_245.0 / s.rates.current_loop_hz;
        assert_eq!(r.first_missed_at_s, Some(first));
        assert!(
            r.unobserved
                .as_deref()
                .unwrap()
                .contains(&format!("from t = {first:.4} s")),
            "{r:?}"
        );
    }

    #[test]
    fn a_gap_too_long_is_named_with_where_it_began() {
        let s = Scenario::default();
        let total = s.sample_count();
        let mut m = Metrics::new(&s);
        // Every sample but 0.3 s from t = 1.0 s: 88 % seen, one gap too long.
        let hz = s.rates.current_loop_hz;
        let (from, to) = ((1.0 * hz) as u64, (1.3 * hz) as u64);
        for k in (0..from).chain(to..total) {
            m.push(&state(&s, k));
        }
        assert_eq!(m.outcome(), Outcome::Unobserved);
        let r = m.finish(Method::Proposed, "realtime", 2.5);
        let why = r.unobserved.as_deref().unwrap_or_default();
        assert!(
            why.contains("missed 0.300 s of the run in a row from t = 1.0000 s"),
            "{why}"
        );
        assert_eq!(r.first_missed_at_s, Some(1.0));
    }

    #[test]
    fn a_lossy_link_and_a_short_run_still_pass() {
        let s = Scenario::default();
        let mut m = Metrics::new(&s);
        // One sample in ten lost on the wire.
        for k in (0..s.sample_count()).filter(|k| k % 10 != 3) {
            m.push(&state(&s, k));
        }
        assert_eq!(m.outcome(), Outcome::Ok, "{:?}", m.unobserved());
        // A run shorter than the profile never reaches the cruise: n/a, and ok.
        let mut short = s.clone();
        short.run.duration_s = Some(0.2);
        let mut m = Metrics::new(&short);
        for k in 0..short.sample_count() {
            m.push(&state(&short, k));
        }
        let r = m.finish(Method::Proposed, "lockstep", 0.1);
        assert_eq!(r.outcome, Outcome::Ok);
        assert!(r.cruise_max_abs_error_rad.is_nan());
        assert_eq!((r.samples, r.missed_samples), (4001, 0));
    }
}
