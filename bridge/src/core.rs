//! The bridge's rules, as a pure state machine: frames and messages in, frames and states
//! out, the time passed in. No socket, no clock, no IPC, so every rule is unit-tested here:
//!
//! - **samples**: of the SAMPLEs read in one go the newest is published; the others are
//!   counted as superseded, as is one whose index is not newer than the last published;
//!   the last sample of the run carries `LAST`.
//! - **silence**: no valid SAMPLE for `silence_periods` (measured at the last empty read of
//!   the socket, not whenever the bridge gets to check) publishes one fault state
//!   (`DRIVE_SILENT`, the next index) and stops forwarding. It is not latched: when the
//!   drive speaks again forwarding resumes, after the fault state's index (no index is
//!   published twice); the drive's own watchdog latch decides whether its outputs return.
//! - **forwarding**: every command is forwarded (unless silent, non-finite or beyond the
//!   measured bus); the newest plan goes out when it is `plan_every` samples newer than the
//!   last sent (default 1: each one), with as many entries as the drive keeps.
//! - **arrivals**: when the drive's next SAMPLE is due, from its own timestamps
//!   ([`ArrivalClock`]).

use crate::link::{DriveLink, EncoderCalibration, Event};
use stepdrive_drive_protocol::{Action, Config, ConfigError, Frame};
use stepdrive_shared::messages::{fault_bits, state_flags, DriveCommand, DrivePlan, DriveState};
use stepdrive_shared::stats::StatsReport;

/// When the drive's next sample is due, in host time. Every SAMPLE carries the drive's
/// timestamp, so the next one leaves one period after it (whatever the drive did before,
/// pauses included); it lands the transport delay later. That delay, which also absorbs the
/// offset between the two clocks, is the smallest seen: a sample can be held up on the way,
/// never sped up. The estimate may grow by `CREEP_NS` a period so that it follows a drive
/// clock running slow against the host's (up to 0.2 % at 20 kHz).
#[derive(Debug, Clone, Copy)]
pub struct ArrivalClock {
    period_ns: u64,
    /// Host time minus drive time of the fastest recent delivery, ns.
    delay_ns: Option<i64>,
}

/// How far a period the delay estimate may grow.
const CREEP_NS: i64 = 100;

impl ArrivalClock {
    pub fn new(period_ns: u64) -> Self {
        Self {
            period_ns,
            delay_ns: None,
        }
    }

    /// A sample stamped `drive_ns` by the drive arrived at host time `at`: returns when the
    /// next one is due.
    pub fn next_due(&mut self, drive_ns: u64, at: u64) -> u64 {
        let delay = at.wrapping_sub(drive_ns) as i64;
        let d = self.delay_ns.map_or(delay, |d| delay.min(d + CREEP_NS));
        self.delay_ns = Some(d);
        drive_ns.wrapping_add(self.period_ns).wrapping_add(d as u64)
    }
}

/// The bridge's settings beside the scenario.
#[derive(Debug, Clone, Copy)]
pub struct CoreSettings {
    pub sample_hz: f64,
    /// Samples in the run; the last carries `LAST`.
    pub samples: u64,
    pub silence_periods: u32,
    pub plan_every: u32,
    pub observer_hz: f64,
    pub calibration: EncoderCalibration,
}

/// What a frame from the drive was.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Received {
    /// A SAMPLE, kept as the newest until it is taken.
    Sample,
    Config(Config),
    /// A CONFIG the protocol does not allow (named field): the drive cannot be used.
    BadConfig(ConfigError),
    /// A latched fault the drive reports (also in its samples' fault bits).
    Fault {
        bits: u16,
        at_sample: u32,
    },
    /// Dropped and counted: bad CRC, malformed, duplicate, out of order or unexpected.
    Dropped,
}

/// See the module documentation.
pub struct BridgeCore {
    link: DriveLink,
    settings: CoreSettings,
    period_ns: u64,
    silence_ns: u64,
    arrivals: ArrivalClock,
    due_ns: Option<u64>,
    /// The newest SAMPLE read and not yet taken, and when it was read.
    newest: Option<(DriveState, u64)>,
    /// The last state published (a sample or the silence fault state), and when the last
    /// sample was read.
    last_state: Option<DriveState>,
    last_rx_ns: u64,
    silent: bool,
    /// The measured bus voltage of the last sample (volts → duty).
    bus_v: f64,
    /// (frame seq, send time) of recent COMMAND frames, for the round trip.
    sent_at: [(u32, u64); 64],
    /// The newest sample a command has answered.
    answered: Option<u64>,
    /// The newest plan received (~8 KB, kept in place), and the sample the last PLAN sent
    /// continued from.
    plan: Box<DrivePlan>,
    plan_sent: Option<u64>,
}

impl BridgeCore {
    pub fn new(settings: CoreSettings) -> Self {
        let period_ns = (1e9 / settings.sample_hz).round() as u64;
        Self {
            link: DriveLink::new(
                settings.sample_hz,
                settings.observer_hz,
                settings.calibration,
            ),
            period_ns,
            silence_ns: u64::from(settings.silence_periods) * period_ns,
            arrivals: ArrivalClock::new(period_ns),
            due_ns: None,
            newest: None,
            last_state: None,
            last_rx_ns: 0,
            silent: false,
            bus_v: 0.0,
            sent_at: [(0, 0); 64],
            answered: None,
            plan: Box::default(),
            plan_sent: None,
            settings,
        }
    }

    pub fn configured(&self) -> bool {
        self.link.configured()
    }

    pub fn silent(&self) -> bool {
        self.silent
    }

    /// When the drive's next SAMPLE is due (host time), once one has been published.
    pub fn due_ns(&self) -> Option<u64> {
        self.due_ns
    }

    /// The HELLO that asks the drive for its CONFIG.
    pub fn hello(&mut self, now: u64) -> Frame {
        self.link.hello_frame(now)
    }

    /// Before the stream: the RESET that clears what a previous session latched, and the
    /// ALIGN that brings the rotor to an electrical zero (§7).
    pub fn prepare(&mut self, now: u64) -> [Frame; 2] {
        [
            self.link.control_frame(Action::Reset, now),
            self.link.control_frame(Action::Align, now),
        ]
    }

    /// The stream starts: samples read so far are stale (the stack was coming up, the rotor
    /// aligning), the next one is k = 0 and its position θ = 0. Returns the ENABLE to send.
    pub fn begin(&mut self, now: u64) -> Frame {
        self.link.restart();
        self.newest = None;
        self.last_rx_ns = now;
        self.link.control_frame(Action::Enable, now)
    }

    /// The RESET and ENABLE to send when a reset is requested: the drive clears its
    /// latched faults (and aligns) and takes commands again.
    pub fn reset(&mut self, now: u64) -> [Frame; 2] {
        [
            self.link.control_frame(Action::Reset, now),
            self.link.control_frame(Action::Enable, now),
        ]
    }

    /// The DISABLE to send when the bridge stops.
    pub fn disable(&mut self, now: u64) -> Frame {
        self.link.control_frame(Action::Disable, now)
    }

    /// A frame from the drive, read at `now`.
    pub fn on_frame(&mut self, bytes: &[u8], now: u64, stats: &mut StatsReport) -> Received {
        match self.link.on_frame(bytes, now) {
            Event::State(st) => {
                // The emulated drive shares this host's clock; for a real drive only the
                // round trip is meaningful.
                stats
                    .hop
                    .record(now.saturating_sub(self.link.sample_timestamp_ns));
                self.round_trip(st.applied_command_seq as u32, now, stats);
                stats.superseded += u64::from(self.newest.is_some());
                self.newest = Some((st, now));
                Received::Sample
            }
            Event::Config(c) => Received::Config(c),
            Event::BadConfig(e) => Received::BadConfig(e),
            Event::Fault(f) => {
                tracing::error!(
                    faults = f.fault_bits,
                    at = f.at_sample,
                    "drive reports a latched fault"
                );
                Received::Fault {
                    bits: f.fault_bits,
                    at_sample: f.at_sample,
                }
            }
            Event::Dropped => Received::Dropped,
        }
    }

    /// The newest sample read since the last take, with when it was read, if it may be
    /// published (its index is newer than the last published: the silence fault state
    /// took an index, and a drive that resumes continues after it).
    pub fn take_sample(&mut self, stats: &mut StatsReport) -> Option<(DriveState, u64)> {
        let (st, rx_at) = self.newest.take()?;
        if self.last_state.is_some_and(|prev| st.seq <= prev.seq) {
            stats.superseded += 1;
            return None;
        }
        Some((st, rx_at))
    }

    /// The state to publish for a taken sample (`publish_time_ns` is the caller's). Ends a
    /// silence, marks the run's last sample, and moves the due time on.
    pub fn publish(&mut self, mut st: DriveState, rx_at: u64) -> DriveState {
        if self.silent {
            // Forwarding resumes: the drive's own watchdog decides whether its outputs come
            // back (one that missed its commands has latched a fault until RESET, and
            // reports it in every sample). A drive stalled by its host (an emulated one)
            // pauses its time with it: nothing was missed.

            self.silent = false;
            tracing::warn!(
                silent_ms = rx_at.saturating_sub(self.last_rx_ns) as f64 * 1e-6,
                drive_faults = st.fault >> 16,
                "the drive speaks again; forwarding commands again"
            );
        }
        if self.is_last(&st) {
            st.flags |= state_flags::LAST;
        }
        self.bus_v = st.bus_voltage_v;
        self.last_rx_ns = rx_at;
        self.last_state = Some(st);
        self.due_ns = Some(self.arrivals.next_due(self.link.sample_timestamp_ns, rx_at));
        st
    }

    /// The fault bits of the last state published (the drive's latched faults in the upper
    /// 16 bits).
    pub fn last_fault(&self) -> u32 {
        self.last_state.map_or(0, |st| st.fault)
    }

    pub fn is_last(&self, st: &DriveState) -> bool {
        st.seq + 1 >= self.settings.samples
    }

    /// Nothing was read at `looked_at` (taken before the read: if the socket held nothing,
    /// nothing arrived up to then, even if the bridge is held up before it checks). After
    /// the silence periods, once: the fault state to publish (the last state, its index
    /// moved on, `DRIVE_SILENT` set), and forwarding stops.
    pub fn on_quiet(&mut self, looked_at: u64, now: u64) -> Option<DriveState> {
        if self.silent || looked_at.saturating_sub(self.last_rx_ns) <= self.silence_ns {
            return None;
        }
        self.silent = true;
        tracing::error!(
            periods = self.settings.silence_periods,
            "no valid sample from the drive: fault published, no commands forwarded until it speaks again"
        );
        let mut st = self.last_state?;
        st.seq += 1;
        st.fault |= fault_bits::DRIVE_SILENT;
        st.publish_time_ns = now;
        st.deadline_ns = now;
        self.last_state = Some(st);
        Some(st)
    }

    /// A command from the current loop: the frame to send, or `None` (while silent, or
    /// refused: non-finite or beyond the measured bus, counted). Say when it went out with
    /// [`Self::sent`].
    pub fn command(
        &mut self,
        c: &DriveCommand,
        now: u64,
        stats: &mut StatsReport,
    ) -> Option<Frame> {
        stats
            .sensor_to_actuator
            .record(c.publish_time_ns.saturating_sub(c.state_publish_time_ns));
        self.answered = self.answered.max(Some(c.answers_seq));
        if self.silent {
            return None;
        }
        self.link.command_frame(c, self.bus_v, now)
    }

    /// COMMAND frame `seq` left at `at`: the round trip starts there.
    pub fn sent(&mut self, seq: u32, at: u64) {
        self.sent_at[(seq % 64) as usize] = (seq, at);
    }

    /// A plan from the current loop; the one continuing the newest command is kept.
    pub fn offer_plan(&mut self, p: &DrivePlan) {
        if p.len > 0 && (self.plan.len == 0 || p.answers_seq > self.plan.answers_seq) {
            *self.plan = *p;
        }
    }

    /// The PLAN frame to send now, if the newest plan is `plan_every` samples newer than
    /// the last one sent (none while silent, or when the drive keeps no plans).
    pub fn plan_frame(&mut self, now: u64) -> Option<Frame> {
        let every = u64::from(self.settings.plan_every.max(1));
        let due = self
            .plan_sent
            .is_none_or(|sent| self.plan.answers_seq >= sent + every);
        if self.plan.len == 0 || !due || self.silent {
            return None;
        }
        self.plan_sent = Some(self.plan.answers_seq);
        self.link.plan_frame(&self.plan, self.bus_v, now)
    }

    /// Without real-time priorities nothing orders the current loop's answer before the
    /// bridge's next wake-up: while the last published sample is unanswered and most of its
    /// period is left, the bridge should look for the answer often.
    pub fn awaiting_answer(&self, now: u64) -> bool {
        let Some(last) = self.last_state else {
            return false;
        };
        let until = self.last_rx_ns + self.period_ns * 8 / 10;
        now < until && self.answered.is_none_or(|a| a < last.seq)
    }

    /// A sample reported command frame `seq` applied: records the round trip once.
    fn round_trip(&mut self, seq: u32, now: u64, stats: &mut StatsReport) {
        let slot = &mut self.sent_at[(seq % 64) as usize];
        if slot.0 == seq && slot.1 != 0 {
            stats.round_trip.record(now - slot.1);
            slot.1 = 0;
        }
    }

    /// The link's counters into a stats report (drive-held periods are its misses).
    pub fn report(&self, stats: &mut StatsReport) {
        self.link.copy_counters(stats);
    }

    pub fn link(&self) -> &DriveLink {
        &self.link
    }

    /// The newest sample read and not yet taken.
    pub fn newest(&self) -> Option<&DriveState> {
        self.newest.as_ref().map(|(st, _)| st)
    }
}

/// After its ALIGN a drive holds phase A alone at `align_current_ma` (§7). Outside these
/// bounds the currents it reports are not that: a phase wired the other way round, or a
/// current sense of the wrong sign or scale. Either commutates the motor wrongly from the
/// first command, so the host refuses the drive instead. The low bound leaves room for a
/// voltage-mode drive whose winding is hotter (more resistive) than its align duty assumed.
pub const HELD_CURRENT_MIN: f64 = 0.5;
pub const HELD_CURRENT_MAX: f64 = 1.5;
/// Phase B's current while phase A holds, at most, as a fraction of the align current.
pub const HELD_CROSS_MAX: f64 = 0.25;

/// Whether phase currents `(i_a, i_b)` are what a drive holding phase A at `align_a` (A)
/// reports.
pub fn holds_phase_a(i_a: f64, i_b: f64, align_a: f64) -> bool {
    (HELD_CURRENT_MIN * align_a..=HELD_CURRENT_MAX * align_a).contains(&i_a)
        && i_b.abs() <= HELD_CROSS_MAX * align_a
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_protocol::units::default_config;
    use stepdrive_drive_protocol::{frame_bytes, status, Message, Sample};

    const PERIOD: u64 = 50_000;

    fn core(samples: u64) -> BridgeCore {
        let mut c = BridgeCore::new(CoreSettings {
            sample_hz: 20_000.0,
            samples,
            silence_periods: 4,
            plan_every: 3,
            observer_hz: 400.0,
            calibration: EncoderCalibration {
                offset_counts: Some(0),
                reverse: false,
                held_load: None,
            },
        });
        let mut stats = StatsReport::default();
        let config = frame_bytes(0, Message::Config(default_config(20_000.0, 200, 8)));
        assert!(matches!(
            c.on_frame(&config, 0, &mut stats),
            Received::Config(_)
        ));
        c.begin(0);
        c
    }

    /// A SAMPLE frame of an enabled drive: wire seq `seq` (the drive's first is 100),
    /// reporting command frame `applied` applied.
    fn sample(seq: u32, applied: u32) -> Vec<u8> {
        sample_with(seq, applied, status::ENABLED)
    }

    fn sample_with(seq: u32, applied: u32, status: u16) -> Vec<u8> {
        frame_bytes(
            seq,
            Message::Sample(Sample {
                encoder_counts: 0,
                adc_a: 32768,
                adc_b: 32768,
                adc_bus: 2400,
                duty_a: 0,
                duty_b: 0,
                applied_command_seq: applied,
                fault_bits: 0,
                status,
            }),
        )
    }

    /// §7 step 5: samples the drive sent before it took the ENABLE (still in flight when
    /// the stream started) are dropped and counted; k = 0 is the first with ENABLED set.
    #[test]
    fn the_run_starts_at_the_first_enabled_sample() {
        let mut c = core(10);
        let mut stats = StatsReport::default();
        let aligning = [100, 101].map(|seq| sample_with(seq, 0, status::ALIGNING));
        assert!(cycle(&mut c, &aligning, PERIOD, &mut stats).is_none());
        assert_eq!(c.link().before_enable, 2);
        let st = cycle(&mut c, &[sample(102, 0)], 2 * PERIOD, &mut stats).expect("a sample");
        assert_eq!(st.seq, 0, "k = 0 is the first enabled sample");
        assert_eq!(
            c.link().lost_on_wire,
            0,
            "the dropped ones are not lost samples"
        );
    }

    /// §7 step 4: after an ALIGN at 1 A the drive holds phase A alone at about 1 A; a
    /// reversed phase, a wrong-signed sense or one scaled 2× off is refused.
    #[test]
    fn an_aligned_drive_holds_phase_a_alone() {
        assert!(holds_phase_a(1.0, 0.0, 1.0));
        assert!(holds_phase_a(0.74, 0.02, 1.0), "a 35 % hotter winding");
        assert!(!holds_phase_a(-1.0, 0.0, 1.0), "phase A reversed");
        assert!(!holds_phase_a(2.0, 0.0, 1.0), "current sense 2× off");
        assert!(!holds_phase_a(0.0, 1.0, 1.0), "phases swapped");
        assert!(!holds_phase_a(0.0, 0.0, 1.0), "nothing energized");
    }

    fn command(answers: u64, v: f64) -> DriveCommand {
        DriveCommand {
            seq: answers,
            answers_seq: answers,
            v_a_v: v,
            v_b_v: -v,
            ..Default::default()
        }
    }

    /// Reads `frames` at `at`, takes and publishes the newest, as the node does.
    fn cycle(
        c: &mut BridgeCore,
        frames: &[Vec<u8>],
        at: u64,
        stats: &mut StatsReport,
    ) -> Option<DriveState> {
        for f in frames {
            c.on_frame(f, at, stats);
        }
        let (st, rx) = c.take_sample(stats)?;
        Some(c.publish(st, rx))
    }

    #[test]
    fn the_newest_sample_is_published_older_ones_are_superseded_and_the_last_is_marked() {
        let mut c = core(3);
        let mut stats = StatsReport::default();
        let st = cycle(&mut c, &[sample(100, 0)], PERIOD, &mut stats).expect("a sample");
        assert_eq!((st.seq, st.flags & state_flags::LAST), (0, 0));
        // Two arrive in one read (the bridge was held up): the newer one is published.
        let st = cycle(
            &mut c,
            &[sample(101, 0), sample(102, 0)],
            3 * PERIOD,
            &mut stats,
        )
        .expect("a sample");
        assert_eq!(st.seq, 2);
        assert_eq!(stats.superseded, 1);
        assert_ne!(st.flags & state_flags::LAST, 0, "sample 2 of 3 is the last");
        assert!((st.bus_voltage_v - 24.0).abs() < 1e-9);
        // Nothing new: nothing to take.
        assert_eq!(c.take_sample(&mut stats), None);
    }

    #[test]
    fn silence_publishes_one_fault_state_stops_forwarding_and_a_sample_resumes_it() {
        let mut c = core(1000);
        let mut stats = StatsReport::default();
        let t0 = PERIOD;
        let st = cycle(&mut c, &[sample(100, 0)], t0, &mut stats).expect("a sample");
        assert!(c.command(&command(0, 1.0), t0, &mut stats).is_some());
        // Within the silence periods (4): quiet, and measured when the socket was read, not
        // when the bridge gets to check.
        assert_eq!(c.on_quiet(t0 + 4 * PERIOD, t0 + 100 * PERIOD), None);
        let fault = c
            .on_quiet(t0 + 4 * PERIOD + 1, t0 + 5 * PERIOD)
            .expect("a fault state");
        assert_eq!(
            fault.seq,
            st.seq + 1,
            "the fault state takes the next index"
        );
        assert_ne!(fault.fault & fault_bits::DRIVE_SILENT, 0);
        assert_eq!(fault.publish_time_ns, t0 + 5 * PERIOD);
        assert!(c.silent());
        assert_eq!(c.on_quiet(t0 + 50 * PERIOD, t0 + 50 * PERIOD), None, "once");
        // Silent: commands and plans are not forwarded, but answers are still noted.
        assert_eq!(c.command(&command(1, 1.0), t0, &mut stats), None);
        let mut plan = DrivePlan {
            command_seq: 1,
            answers_seq: 1,
            len: 4,
            ..Default::default()
        };
        plan.v[..4].copy_from_slice(&[[1.0, -1.0]; 4]);
        c.offer_plan(&plan);
        assert_eq!(c.plan_frame(t0), None);
        // The drive speaks again with the index the fault state took: superseded, still
        // silent. The next one resumes forwarding, with no fault of the bridge's own.
        assert_eq!(
            cycle(&mut c, &[sample(101, 0)], t0 + 60 * PERIOD, &mut stats),
            None
        );
        assert!(c.silent());
        let st = cycle(&mut c, &[sample(102, 0)], t0 + 61 * PERIOD, &mut stats).expect("resumed");
        assert_eq!((st.seq, st.fault), (2, 0));
        assert!(!c.silent());
        assert!(c.command(&command(2, 1.0), t0, &mut stats).is_some());
        assert!(
            c.plan_frame(t0).is_some(),
            "the plan kept while silent goes out"
        );
    }

    #[test]
    fn commands_are_forwarded_refused_when_bad_and_timed_to_their_sample() {
        let mut c = core(1000);
        let mut stats = StatsReport::default();
        cycle(&mut c, &[sample(100, 0)], PERIOD, &mut stats).expect("a sample");
        assert!(c.awaiting_answer(PERIOD), "sample 0 unanswered");
        let f = c
            .command(&command(0, 12.0), PERIOD + 4_000, &mut stats)
            .expect("forwarded");
        c.sent(f.seq, PERIOD + 5_000);
        let Message::Command(cmd) = f.message else {
            panic!("{f:?}")
        };
        assert_eq!((cmd.answers_sample, cmd.duty_a), (100, 16384));
        assert!(!c.awaiting_answer(PERIOD + 6_000));
        // Non-finite, beyond the bus: refused, counted.
        assert_eq!(c.command(&command(1, f64::NAN), PERIOD, &mut stats), None);
        assert_eq!(c.command(&command(1, 30.0), PERIOD, &mut stats), None);
        assert_eq!(c.link().rejected_commands, 2);
        assert_eq!(stats.sensor_to_actuator.count, 3);
        // The drive reports that frame applied: one round trip, from the moment it was sent.
        cycle(&mut c, &[sample(101, f.seq)], PERIOD + 80_000, &mut stats).expect("a sample");
        assert_eq!(stats.round_trip.count, 1);
        assert_eq!(stats.round_trip.max_ns, 75_000);
    }

    #[test]
    fn the_newest_plan_goes_out_every_plan_every_samples_with_the_drives_capacity() {
        let mut c = core(1000);
        let mut stats = StatsReport::default();
        cycle(&mut c, &[sample(100, 0)], PERIOD, &mut stats).expect("a sample");
        let plan = |answers: u64| {
            let mut p = DrivePlan {
                command_seq: answers,
                answers_seq: answers,
                len: 20,
                ..Default::default()
            };
            p.v[..20].copy_from_slice(&[[2.0, -2.0]; 20]);
            p
        };
        let sent = |c: &mut BridgeCore, answers: u64| {
            c.offer_plan(&plan(answers));
            c.plan_frame(0).map(|f| match f.message {
                Message::Plan(p) => (p.answers_sample, usize::from(p.count)),
                other => panic!("{other:?}"),
            })
        };
        // The drive keeps 8 entries (its CONFIG), so 8 of the 20 go out.
        assert_eq!(sent(&mut c, 0), Some((100, 8)));
        assert_eq!(sent(&mut c, 1), None);
        assert_eq!(sent(&mut c, 2), None);
        assert_eq!(sent(&mut c, 3), Some((103, 8)), "plan_every = 3");
        // An older plan never replaces a newer one.
        c.offer_plan(&plan(2));
        assert_eq!(c.plan_frame(0), None);
    }

    /// By default every plan the current loop publishes reaches the drive, the one it
    /// makes after a lost sample too: the loop predicts its next duties with the plan it
    /// last published, so the drive must hold that very plan. (With plans thinned to every
    /// 10 samples, the plan made after a lost sample stayed home, and 1 % of samples lost
    /// at random raised the cruise error 10-25×.)
    #[test]
    fn by_default_every_plan_the_loop_publishes_reaches_the_drive() {
        let every = stepdrive_runtime::deploy::DriveLink::default().plan_every;
        let mut c = core(1000);
        c.settings.plan_every = every;
        let mut stats = StatsReport::default();
        cycle(&mut c, &[sample(100, 0)], PERIOD, &mut stats).expect("a sample");
        for answers in [10, 13, 20, 21] {
            let mut p = DrivePlan {
                command_seq: answers,
                answers_seq: answers,
                len: 4,
                ..Default::default()
            };
            p.v[..4].copy_from_slice(&[[1.0, -1.0]; 4]);
            c.offer_plan(&p);
            let sent = c.plan_frame(0).map(|f| match f.message {
                Message::Plan(p) => p.answers_sample,
                other => panic!("{other:?}"),
            });
            assert_eq!(sent, Some(100 + answers as u32), "plan {answers}");
        }
    }

    /// The due time follows the drive's own timestamps (a pause of the drive moves it at
    /// once), plus the fastest delivery seen; a slower delivery does not move it, a steadily
    /// growing delay (a slow drive clock) is followed at CREEP_NS a period.
    #[test]
    fn arrival_clock_follows_the_drive_timestamps() {
        let mut c = ArrivalClock::new(50_000);
        // Drive clock 7 ms behind the host's, 3 µs on the way.
        let host = |drive: u64, on_the_way: u64| drive + 7_000_000 + on_the_way;
        assert_eq!(
            c.next_due(1_000_000, host(1_000_000, 3_000)),
            host(1_050_000, 3_000)
        );
        // Held up 20 µs on the way: the next is still due 3 µs after it leaves.
        assert_eq!(
            c.next_due(1_050_000, host(1_050_000, 23_000)),
            host(1_100_000, 3_000 + CREEP_NS as u64)
        );
        // The drive paused 400 µs: its timestamp says so.
        assert_eq!(
            c.next_due(1_500_000, host(1_500_000, 3_000)),
            host(1_550_000, 3_000)
        );
        // A drive clock 1 µs a period slower than the host's: the delay estimate follows.
        let mut due = 0;
        for k in 0..200u64 {
            let sent = 2_000_000 + k * 50_000;
            due = c.next_due(sent, host(sent, 3_000 + k * 1_000));
        }
        assert!(due >= host(2_000_000 + 200 * 50_000, 3_000 + 199 * CREEP_NS as u64 - 1));
    }

    /// Frames of every kind with arbitrary fields (CONFIGs included), some corrupted with
    /// a matching CRC: the core never panics and never publishes an index twice or
    /// backwards, and every state it takes is finite.
    #[test]
    fn arbitrary_frames_never_break_the_core() {
        use proptest::prelude::*;
        let frame = (
            any::<u32>(),
            any::<u8>(),
            proptest::collection::vec(any::<u8>(), 0..64),
        );
        proptest!(|(frames in proptest::collection::vec(frame, 1..200))| {
            let mut c = core(100);
            let mut stats = StatsReport::default();
            let mut last: Option<u64> = None;
            for (i, (seq, kind, payload)) in frames.into_iter().enumerate() {
                let bytes = stepdrive_drive_protocol::raw_frame(seq, kind % 9, &payload);
                let now = (i as u64 + 1) * PERIOD;
                c.on_frame(&bytes, now, &mut stats);
                if let Some((st, rx)) = c.take_sample(&mut stats) {
                    let st = c.publish(st, rx);
                    prop_assert!(last.is_none_or(|l| st.seq > l), "{:?} after {:?}", st.seq, last);
                    last = Some(st.seq);
                    for v in [st.theta_rad, st.omega_rad_s, st.i_a_a, st.i_b_a, st.bus_voltage_v] {
                        prop_assert!(v.is_finite(), "{st:?}");
                    }
                }
            }
        });
    }
}
