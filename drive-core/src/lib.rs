//! The drive's side of the wire protocol (docs/drive-protocol.md, version 3.1) as a pure
//! state machine: handshake and CONFIG, alignment, ENABLE/DISABLE/RESET, the sequence and
//! timestamp rules, the watchdog, the voltage plan player, fault latching and FAULT_REPORT.
//! No clock reads, no I/O, no allocation, no `std`: frames in, frames out, over a
//! [`PowerStage`] (two bridge duties out; two phase currents, the encoder count and the bus
//! voltage in). The caller owns the sample clock: each period it sends
//! [`DriveCore::sample_frame`] and then calls [`DriveCore::run_period`]; every received
//! frame goes to [`DriveCore::on_frame_from`].
//!
//! The emulated drive (`stepdrive-emulated-drive`: this core, the motor model of
//! `stepdrive-motor` as its power stage, and fault injection) and drive firmware run this
//! one copy of the drive's rules.

#![no_std]

#[cfg(feature = "simulated-stage")]
pub mod simulated;

use stepdrive_drive_protocol::{
    decode_view, faults, is_newer, status, Action, Command, Config, DecodeError, FaultReport,
    Frame, Message, Plan, PlanView, Sample, MAX_PLAN_ENTRIES,
};

/// The bridges and the sensors: what the core drives and reads, in drive units.
pub trait PowerStage {
    /// Drives the two full bridges at these duties (±`MAX_DUTY` is the whole bus voltage;
    /// (0, 0) with the outputs off) from now until the next call: one sample period.
    fn drive(&mut self, duty: (i16, i16));
    /// The readings at this sample instant.
    fn measure(&mut self) -> Measurement;
}

/// One sample's readings, raw as a SAMPLE carries them (§3.2).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Measurement {
    pub encoder_counts: i32,
    /// Phase currents, offset binary (CONFIG's `current_zero_count` at 0 A).
    pub adc_a: u16,
    pub adc_b: u16,
    pub adc_bus: u16,
}

/// What the drive guards its bridges against, in ADC counts; `None` does not check.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Limits {
    /// |reading − zero| of either phase above this latches OVERCURRENT.
    pub overcurrent_counts: Option<u16>,
    /// A bus reading outside this range (inclusive) latches BUS_VOLTAGE.
    pub bus_counts: Option<(u16, u16)>,
}

impl Limits {
    /// The fault bits `m` latches.
    pub fn check(&self, m: &Measurement, current_zero: u16) -> u16 {
        let mut bits = 0;
        if let Some(limit) = self.overcurrent_counts {
            let off = |adc: u16| adc.abs_diff(current_zero);
            if off(m.adc_a) > limit || off(m.adc_b) > limit {
                bits |= faults::OVERCURRENT;
            }
        }
        if let Some((low, high)) = self.bus_counts {
            if !(low..=high).contains(&m.adc_bus) {
                bits |= faults::BUS_VOLTAGE;
            }
        }
        bits
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DriveCounters {
    pub frames_ok: u64,
    pub bad_frames: u64,
    pub crc_errors: u64,
    pub stale_frames: u64,
    /// Frames from an address other than the session's host (UDP), a HELLO from one while
    /// the session is live (§4.6), and frames other than HELLO before there is a session.
    pub foreign_frames: u64,
    pub commands_applied: u64,
    /// COMMANDs discarded because their period had begun (they came too late).
    pub commands_late: u64,
    /// CONTROLs without effect in the state they came in (ENABLE or ALIGN while a fault is
    /// latched).
    pub ignored_controls: u64,
    /// Periods without their COMMAND (the watchdog's count), and of those, the ones that
    /// got a PLAN entry instead of the held duties.
    pub periods_held: u64,
    pub periods_planned: u64,
}

/// The drive's logic, without sockets, clocks or a motor: frames in, frames out, the
/// bridges' duties to the power stage and its measurements into each SAMPLE.
pub struct DriveCore {
    pub config: Config,
    limits: Limits,
    enabled: bool,
    latched: u16,
    /// Latched bits already sent in a FAULT_REPORT (one report each time new bits latch).
    reported: u16,
    /// A HELLO has been taken: before one, nothing but HELLO is acted on.
    session: bool,
    last_rx_seq: Option<u32>,
    pending: Option<Command>,
    pending_seq: u32,
    /// The PLAN with the newest `answers_sample` (its table written in place by each PLAN
    /// taken), and its frame's seq (`None`: no plan).
    plan: Plan,
    plan_seq: Option<u32>,
    planned: bool,
    /// The duties to hold when a period has no COMMAND, and the frame they came from.
    held_duty: (i16, i16),
    held_seq: u32,
    /// What the next SAMPLE reports of the period that ends at it (§4.1: duties, applied
    /// seq, COMMAND_HELD, COMMAND_PLANNED), fixed when that period started: a DISABLE,
    /// RESET or HELLO taken within it changes the state bits at once, not this.
    ended: EndedPeriod,
    since_command: u32,
    /// Periods since the last frame accepted from the session's host: a session whose host
    /// has been silent for the watchdog's periods is no longer live (§4.6).
    since_host: u32,
    /// The watchdog counts from the first COMMAND applied after ENABLE (§5).
    armed: bool,
    /// Periods of alignment left, and whether phase A still holds the rotor after it
    /// (until the first COMMAND after ENABLE).
    aligning: u32,
    holding: bool,
    align_duty: i16,
    /// The seq of the next SAMPLE (the sample index; CONFIG and FAULT_REPORT carry the
    /// last one sent).
    tx_seq: u32,
    /// The run's first sample (the first with ENABLED set and ALIGNING clear after an
    /// ENABLE that starts a run, §7 step 5). `run_pending`: such an ENABLE was taken and
    /// that sample has not been sent yet.
    run_start: Option<u32>,
    run_pending: bool,
    /// Fault injection: an alignment that never ends (§7).
    align_stuck: bool,
    pub counters: DriveCounters,
}

/// What a SAMPLE reports of the period that ended at it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct EndedPeriod {
    duty: (i16, i16),
    seq: u32,
    held: bool,
    planned: bool,
}

/// What the drive answers to a frame.
pub enum Reply {
    Config(Config),
}

impl DriveCore {
    /// A drive announcing `config` (its plan capacity at most [`MAX_PLAN_ENTRIES`]), whose
    /// ALIGN drives phase A at `align_duty`, guarding `limits`.
    pub fn new(mut config: Config, align_duty: i16, limits: Limits) -> Self {
        config.plan_capacity = config.plan_capacity.min(MAX_PLAN_ENTRIES as u16);
        Self {
            config,
            limits,
            enabled: false,
            latched: 0,
            reported: 0,
            session: false,
            last_rx_seq: None,
            pending: None,
            pending_seq: 0,
            plan: Plan::new(0, []),
            plan_seq: None,
            planned: false,
            held_duty: (0, 0),
            held_seq: 0,
            ended: EndedPeriod::default(),
            since_command: 0,
            since_host: 0,
            armed: false,
            aligning: 0,
            holding: false,
            align_duty,
            tx_seq: 1,
            run_start: None,
            run_pending: false,
            align_stuck: false,
            counters: DriveCounters::default(),
        }
    }

    /// The wire seq of the run's first SAMPLE, once a run has started.
    pub fn run_start(&self) -> Option<u32> {
        self.run_start
    }

    /// Whether the next SAMPLE is a run's first (§7 step 5): where its time counts from.
    pub fn run_starts_at_next_sample(&self) -> bool {
        self.run_pending && ((self.outputs_on() && self.aligning == 0) || self.latched != 0)
    }

    pub fn latched_faults(&self) -> u16 {
        self.latched
    }

    /// Whether a host has said HELLO (the drive has somewhere to send its samples).
    pub fn in_session(&self) -> bool {
        self.session
    }

    /// Whether a run is under way (from its first SAMPLE, §7 step 5, until a HELLO, ALIGN
    /// or DISABLE ends it): fault injection counts its time from there.
    pub fn in_run(&self) -> bool {
        self.run_start.is_some()
    }

    /// A session is live while its host is heard and the motor is energized (enabled,
    /// aligning or holding): then a HELLO from any other address is not taken (§4.6). A
    /// host silent for the watchdog's periods, or outputs off, leaves it to the next host.
    /// An armed watchdog ends a silent host's session itself, by tripping, so that the next
    /// host finds WATCHDOG latched (§2); the host's last frame comes a period or more
    /// before its last COMMAND is applied, so its silence alone ends the session sooner.
    fn live(&self) -> bool {
        let energized =
            self.outputs_on() || (self.latched == 0 && (self.aligning > 0 || self.holding));
        let heard = self.since_host < u32::from(self.config.watchdog_periods)
            || (self.armed && self.outputs_on());
        self.session && energized && heard
    }

    pub fn outputs_on(&self) -> bool {
        self.enabled && self.latched == 0
    }

    /// Its ALIGN: phase A at `current_ma` for `ms` (0: it does not align, as a drive with an
    /// absolute encoder may not), announced in CONFIG, driven at `duty`.
    pub fn set_alignment(&mut self, current_ma: u16, ms: u16, duty: i16) {
        self.config.align_current_ma = current_ma;
        self.config.align_ms = ms;
        self.align_duty = duty;
    }

    /// Phase A's duty during an ALIGN.
    pub fn align_duty(&self) -> i16 {
        self.align_duty
    }

    /// Fault injection: an alignment that never ends (ALIGNING stays set).
    pub fn set_align_stuck(&mut self, stuck: bool) {
        self.align_stuck = stuck;
    }

    /// The seq a CONFIG or FAULT_REPORT carries: the last SAMPLE's (0 before the first).
    pub fn report_seq(&self) -> u32 {
        self.tx_seq.wrapping_sub(1)
    }

    /// A CONFIG or FAULT_REPORT as the frame the drive sends at `now_ns` (its seq
    /// [`report_seq`](Self::report_seq)).
    pub fn report_frame(&self, message: Message, now_ns: u64) -> Frame {
        Frame {
            seq: self.report_seq(),
            timestamp_ns: now_ns,
            message,
        }
    }

    fn end_run(&mut self) {
        self.run_start = None;
        self.run_pending = false;
    }

    fn stop_aligning(&mut self) {
        self.aligning = 0;
        self.holding = false;
    }

    /// Outputs off until the next ENABLE, the watchdog disarmed, the stored PLAN and any
    /// waiting COMMAND forgotten (§4.3: HELLO, ALIGN, DISABLE and RESET all do this).
    fn stand_down(&mut self) {
        self.enabled = false;
        self.armed = false;
        self.since_command = 0;
        self.pending = None;
        self.plan_seq = None;
        // Nothing to hold: the next ENABLE starts from duty 0 (§4.1).
        self.held_duty = (0, 0);
        self.held_seq = 0;
        self.stop_aligning();
    }

    /// Handles one received datagram from the session's host (or from the only host there
    /// is). Bad, duplicate and out-of-order frames are counted and dropped; nothing from
    /// them is applied.
    pub fn on_frame(&mut self, bytes: &[u8]) -> Option<Reply> {
        self.on_frame_from(bytes, true)
    }

    /// [`DriveCore::on_frame_from`] on a link whose frames come from addresses (UDP, §2):
    /// `host` is the session's host, the address whose HELLO was answered last (`None`
    /// before one). A HELLO answered makes `from` the host; its CONFIG, to send to `from`,
    /// is returned.
    pub fn on_datagram<A: PartialEq + Copy>(
        &mut self,
        bytes: &[u8],
        from: A,
        host: &mut Option<A>,
    ) -> Option<Config> {
        let from_host = host.is_none_or(|h| h == from);
        let Reply::Config(config) = self.on_frame_from(bytes, from_host)?;
        *host = Some(from);
        Some(config)
    }

    /// Handles one received datagram; `from_host`: it came from the session's host's
    /// address (UDP), or there is no session yet. From any other address only a HELLO is
    /// read, and only while the session is not live.
    pub fn on_frame_from(&mut self, bytes: &[u8], from_host: bool) -> Option<Reply> {
        let frame = match decode_view(bytes) {
            Ok(f) => f,
            Err(DecodeError::BadCrc { .. }) => {
                self.counters.crc_errors += 1;
                return None;
            }
            Err(_) => {
                self.counters.bad_frames += 1;
                return None;
            }
        };
        // Only a host sends these; before a HELLO there is no host to act for (§2, §3.1).
        let host_kind = !matches!(
            frame.message,
            Message::Sample(_) | Message::Config(_) | Message::FaultReport(_)
        );
        if !host_kind {
            self.counters.bad_frames += 1;
            return None;
        }
        if !self.session && frame.message != Message::Hello {
            self.counters.foreign_frames += 1;
            return None;
        }
        // §2, §4.6: another address may take the drive over only once the session's host
        // has let go of the motor or gone silent for the watchdog's periods.
        if self.session && !from_host && (frame.message != Message::Hello || self.live()) {
            self.counters.foreign_frames += 1;
            return None;
        }
        // A HELLO starts a new session: a new host counts its frames from its own start,
        // so sequence tracking restarts with it, and the outputs stay off until it enables
        // them; the next ENABLE starts a run.
        if frame.message == Message::Hello {
            self.session = true;
            self.stand_down();
            self.end_run();
        } else if !is_newer(frame.seq, self.last_rx_seq) {
            self.counters.stale_frames += 1;
            return None;
        }
        self.last_rx_seq = Some(frame.seq);
        self.since_host = 0;
        self.counters.frames_ok += 1;
        match frame.message {
            Message::Command(c) => {
                // ±MAX_DUTY is the full range; i16::MIN is the one value beyond it.
                if c.duty_a == i16::MIN || c.duty_b == i16::MIN {
                    self.latched |= faults::BAD_COMMAND;
                } else {
                    self.pending = Some(c);
                    self.pending_seq = frame.seq;
                }
                None
            }
            Message::Control(Action::Enable | Action::Align) if self.latched != 0 => {
                // Only RESET clears a fault (§5); nothing is energized before it.
                self.counters.ignored_controls += 1;
                None
            }
            Message::Control(Action::Align) if self.config.align_ms == 0 => {
                // A drive that does not align (an absolute encoder) ignores ALIGN (§4.3).
                self.counters.ignored_controls += 1;
                None
            }
            Message::Control(Action::Enable) => {
                self.enabled = true;
                // A run starts with the first ENABLE after a HELLO, ALIGN or DISABLE (an
                // ENABLE after a RESET mid-run continues it), at its first SAMPLE with
                // ENABLED set and ALIGNING clear (§7 step 5: where the host's k = 0 is).
                if self.run_start.is_none() {
                    self.run_pending = true;
                }
                self.armed = false;
                self.since_command = 0;
                None
            }
            Message::Control(Action::Disable) => {
                self.stand_down();
                self.end_run();
                None
            }
            Message::Control(Action::Reset) => {
                // An ENABLE after it continues the run (`stepdrive reset`).
                self.latched = 0;
                self.reported = 0;
                self.stand_down();
                None
            }
            Message::Control(Action::Align) => {
                // With phase A energized the rotor settles at an electrical zero
                // (N_r θ ≡ 0 mod 2π), where the host's encoder zero then commutates right.
                self.stand_down();
                self.end_run();
                let periods =
                    u64::from(self.config.align_ms) * u64::from(self.config.sample_rate_hz) / 1000;
                self.aligning = u32::try_from(periods).unwrap_or(u32::MAX);
                self.holding = self.aligning > 0;
                None
            }
            Message::Hello => Some(Reply::Config(self.config)),
            Message::Plan(p) => {
                if p.entries().flatten().any(|d| d == i16::MIN) {
                    self.latched |= faults::BAD_COMMAND;
                } else if p.count > self.config.plan_capacity {
                    // More than it announced it keeps: malformed for this drive.
                    self.counters.bad_frames += 1;
                } else if self.plan_seq.is_none()
                    || !is_newer(self.plan.answers_sample, Some(p.answers_sample))
                {
                    // Newer, or equal (a later frame for the same base replaces it).
                    self.keep_plan(p, frame.seq);
                }
                None
            }
            _ => None,
        }
    }

    /// Takes `p` as the plan, into the table kept for it (no 4 KB value built and moved).
    fn keep_plan(&mut self, p: PlanView, seq: u32) {
        let kept = &mut self.plan;
        // Entries past `count` stay zero, as a Plan's are.
        let old = usize::from(kept.count);
        kept.duties[usize::from(p.count)..old.max(usize::from(p.count))].fill([0, 0]);
        for (slot, entry) in kept.duties.iter_mut().zip(p.entries()) {
            *slot = entry;
        }
        kept.answers_sample = p.answers_sample;
        kept.count = p.count;
        self.plan_seq = Some(seq);
    }

    /// The PLAN entry for the period starting at SAMPLE `sample_seq`, with its frame seq.
    fn planned_duty(&self, sample_seq: u32) -> Option<((i16, i16), u32)> {
        let (p, seq) = (&self.plan, self.plan_seq.as_ref()?);
        // Entry j is for the period starting at answers_sample + 2 + j.
        let j = sample_seq.wrapping_sub(p.answers_sample).wrapping_sub(2);
        let [a, b] = *p.entries().get(usize::try_from(j).ok()?)?;
        Some(((a, b), *seq))
    }

    /// Latches `bits` (e.g. an injected over-current).
    pub fn trip(&mut self, bits: u16) {
        self.latched |= bits;
    }

    /// The sample at the current instant, as a frame: the stage's measurements, checked
    /// against the drive's limits (a reading beyond them latches its fault, and the period
    /// that starts at this sample has the outputs off).
    pub fn sample_frame(&mut self, now_ns: u64, stage: &mut impl PowerStage) -> Frame {
        if self.run_starts_at_next_sample() {
            self.run_pending = false;
            self.run_start = Some(self.tx_seq);
        }
        let m = stage.measure();
        self.latched |= self.limits.check(&m, self.config.current_zero_count);
        let mut status_bits = 0;
        if self.outputs_on() {
            status_bits |= status::ENABLED;
        }
        let ended = self.ended;
        if ended.held {
            status_bits |= status::COMMAND_HELD;
        }
        if ended.planned {
            status_bits |= status::COMMAND_PLANNED;
        }
        if self.aligning > 0 {
            status_bits |= status::ALIGNING;
        }
        let frame = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Sample(Sample {
                encoder_counts: m.encoder_counts,
                adc_a: m.adc_a,
                adc_b: m.adc_b,
                adc_bus: m.adc_bus,
                duty_a: ended.duty.0,
                duty_b: ended.duty.1,
                applied_command_seq: ended.seq,
                fault_bits: self.latched,
                status: status_bits,
            }),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        frame
    }

    /// Decides the duties for the period starting now and drives them into the stage.
    /// The command must answer the previous sample (one period of compute delay); without
    /// one, the previous duties are held; after the watchdog's periods without one, the
    /// outputs go off and a fault latches. Returns a fault report if one just latched.
    pub fn run_period(
        &mut self,
        sample_seq: u32,
        stage: &mut impl PowerStage,
    ) -> Option<FaultReport> {
        self.planned = false;
        self.since_host = self.since_host.saturating_add(1);
        let wanted = sample_seq.wrapping_sub(1);
        if self.aligning > 0 && self.latched == 0 {
            if !self.align_stuck {
                self.aligning -= 1;
            }
            self.pending = None;
            return self.apply((self.align_duty, 0), 0, sample_seq, stage);
        }
        match self.pending.take() {
            Some(c) if c.answers_sample == wanted && self.enabled => {
                self.held_duty = (c.duty_a, c.duty_b);
                self.held_seq = self.pending_seq;
                self.since_command = 0;
                self.armed = true;
                self.holding = false;
                self.counters.commands_applied += 1;
            }
            other => {
                // A command for a later sample waits for its period; older ones are dropped.
                match other {
                    Some(c) if is_newer(c.answers_sample, Some(wanted)) => self.pending = Some(c),
                    Some(_) => self.counters.commands_late += 1,
                    None => {}
                }
                // Holding the aligned rotor, no PLAN entry applies (§4.3): the watchdog is
                // not armed before the first COMMAND, and a plan alone would run the motor
                // on predictions with nothing to stop it.
                let hold = self.holding && !self.armed;
                if self.enabled {
                    self.since_command = self.since_command.saturating_add(1);
                    self.counters.periods_held += 1;
                    // The PLAN's duty for this period, if it has one; else the last is held.
                    if let Some((duty, seq)) = self.planned_duty(sample_seq).filter(|_| !hold) {
                        self.held_duty = duty;
                        self.held_seq = seq;
                        self.planned = true;
                        self.counters.periods_planned += 1;
                    }
                }
                // A latched fault has the outputs off already: the watchdog is disarmed.
                if self.armed
                    && self.latched == 0
                    && self.since_command >= u32::from(self.config.watchdog_periods)
                {
                    self.latched |= faults::WATCHDOG;
                }
            }
        }
        if self.holding && self.latched == 0 && !self.armed {
            // Aligned and not yet commanded: phase A keeps the rotor at its zero.
            return self.apply((self.align_duty, 0), 0, sample_seq, stage);
        }
        if !self.outputs_on() {
            self.held_duty = (0, 0);
            self.held_seq = 0;
        }
        let (duty, seq) = (self.held_duty, self.held_seq);
        self.apply(duty, seq, sample_seq, stage)
    }

    /// Drives `duty` (reported in the next SAMPLE with `seq`) over the period; a fault
    /// report if bits latched since the last one.
    fn apply(
        &mut self,
        duty: (i16, i16),
        seq: u32,
        sample_seq: u32,
        stage: &mut impl PowerStage,
    ) -> Option<FaultReport> {
        let duty = if self.latched == 0 { duty } else { (0, 0) };
        self.held_duty = duty;
        self.held_seq = if self.latched == 0 { seq } else { 0 };
        self.ended = EndedPeriod {
            duty,
            seq: self.held_seq,
            held: self.since_command > 0 && self.outputs_on(),
            planned: self.planned,
        };
        stage.drive(duty);
        // Bits latched since the last report, whether by a frame before this period's
        // sample, by the sample's own values or by the watchdog at this period's start:
        // period `sample_seq` is the first with the outputs off (§5).
        if self.latched & !self.reported == 0 {
            return None;
        }
        self.reported = self.latched;
        Some(FaultReport {
            fault_bits: self.latched,
            at_sample: sample_seq,
        })
    }
}

#[cfg(test)]
mod tests {
    //! The core against a stage that only records: what it drives and what it reports,
    //! without a motor.
    use super::*;
    use stepdrive_drive_protocol::{encode, MAX_FRAME};

    /// Drives nothing; reads what the test sets.
    #[derive(Default)]
    struct Bench {
        driven: Option<(i16, i16)>,
        reading: Measurement,
    }

    impl PowerStage for Bench {
        fn drive(&mut self, duty: (i16, i16)) {
            self.driven = Some(duty);
        }
        fn measure(&mut self) -> Measurement {
            self.reading
        }
    }

    const ZERO: u16 = 32768;

    fn config() -> Config {
        Config {
            sample_rate_hz: 2000,
            counts_per_rev: 1 << 20,
            current_ua_per_count: 100,
            current_zero_count: ZERO,
            bus_uv_per_count: 1000,
            watchdog_periods: 4,
            encoder_direction: 1,
            plan_capacity: 8,
            align_current_ma: 0,
            align_ms: 0,
            reserved: [0],
        }
    }

    fn send(d: &mut DriveCore, seq: u32, message: Message) -> Option<Reply> {
        let mut b = [0u8; MAX_FRAME];
        let n = encode(
            &Frame {
                seq,
                timestamp_ns: 0,
                message,
            },
            &mut b,
        );
        d.on_frame(&b[..n])
    }

    /// A drive in session and enabled, with `limits`, on a bench reading `reading`.
    fn enabled(limits: Limits, reading: Measurement) -> (DriveCore, Bench) {
        let mut d = DriveCore::new(config(), 0, limits);
        assert!(matches!(
            send(&mut d, 0, Message::Hello),
            Some(Reply::Config(_))
        ));
        send(&mut d, 1, Message::Control(Action::Enable));
        let bench = Bench {
            driven: None,
            reading,
        };
        (d, bench)
    }

    /// One period: the SAMPLE sent, then the COMMAND answering it (when `duty`), then the
    /// period driven. Returns the sample and the fault report.
    fn period(
        d: &mut DriveCore,
        b: &mut Bench,
        rx_seq: &mut u32,
        duty: Option<i16>,
    ) -> (u32, Sample, Option<FaultReport>) {
        let f = d.sample_frame(0, b);
        let Message::Sample(s) = f.message else {
            panic!("a sample frame");
        };
        if let Some(duty) = duty {
            *rx_seq += 1;
            send(
                d,
                *rx_seq,
                Message::Command(Command {
                    answers_sample: f.seq,
                    duty_a: duty,
                    duty_b: -duty,
                }),
            );
        }
        let report = d.run_period(f.seq.wrapping_add(1), b);
        (f.seq, s, report)
    }

    fn quiet() -> Measurement {
        Measurement {
            encoder_counts: 7,
            adc_a: ZERO,
            adc_b: ZERO,
            adc_bus: 24_000,
        }
    }

    /// The stage's readings go out in the SAMPLE as they are; the COMMAND's duties reach the
    /// bridges in the period after the sample it answers.
    #[test]
    fn readings_go_out_and_commands_reach_the_bridges() {
        let (mut d, mut b) = enabled(Limits::default(), quiet());
        let mut rx = 1;
        let (_, s, _) = period(&mut d, &mut b, &mut rx, Some(1000));
        assert_eq!(
            (s.encoder_counts, s.adc_a, s.adc_b, s.adc_bus),
            (7, ZERO, ZERO, 24_000)
        );
        // The first COMMAND answers the sample just sent: the period after it drives it.
        let (_, _, _) = period(&mut d, &mut b, &mut rx, Some(2000));
        assert_eq!(b.driven, Some((2000, -2000)));
        let (_, s, _) = period(&mut d, &mut b, &mut rx, Some(3000));
        assert_eq!((s.duty_a, s.duty_b), (2000, -2000));
        assert_eq!(s.status & status::ENABLED, status::ENABLED);
    }

    /// A phase current beyond the limit latches OVERCURRENT at that sample: the period that
    /// starts there has the outputs off, a FAULT_REPORT names the sample, and nothing but a
    /// RESET lets the bridges be driven again.
    #[test]
    fn an_overcurrent_reading_turns_the_outputs_off_until_reset() {
        let limits = Limits {
            overcurrent_counts: Some(1000),
            bus_counts: None,
        };
        let (mut d, mut b) = enabled(limits, quiet());
        let mut rx = 1;
        for _ in 0..3 {
            period(&mut d, &mut b, &mut rx, Some(1000));
        }
        assert_eq!(b.driven, Some((1000, -1000)));
        // Exactly at the limit is within it.
        b.reading.adc_b = ZERO - 1000;
        let (_, s, report) = period(&mut d, &mut b, &mut rx, Some(1000));
        assert_eq!((s.fault_bits, report), (0, None));
        b.reading.adc_b = ZERO - 1001;
        let (seq, s, report) = period(&mut d, &mut b, &mut rx, Some(1000));
        assert_eq!(s.fault_bits, faults::OVERCURRENT);
        assert_eq!(s.status & status::ENABLED, 0);
        assert_eq!(
            report,
            Some(FaultReport {
                fault_bits: faults::OVERCURRENT,
                at_sample: seq.wrapping_add(1),
            })
        );
        assert_eq!(b.driven, Some((0, 0)));
        // The reading back to normal does not clear it; commands are not driven.
        b.reading = quiet();
        for _ in 0..3 {
            let (_, s, report) = period(&mut d, &mut b, &mut rx, Some(1000));
            assert_eq!(
                (s.fault_bits, report, b.driven),
                (faults::OVERCURRENT, None, Some((0, 0)))
            );
        }
        rx += 1;
        send(&mut d, rx, Message::Control(Action::Reset));
        rx += 1;
        send(&mut d, rx, Message::Control(Action::Enable));
        period(&mut d, &mut b, &mut rx, Some(500));
        period(&mut d, &mut b, &mut rx, Some(500));
        assert_eq!(b.driven, Some((500, -500)));
    }

    /// A bus reading outside the range latches BUS_VOLTAGE, below it as above it.
    #[test]
    fn a_bus_outside_its_range_latches_bus_voltage() {
        for bus in [9_999, 40_001] {
            let limits = Limits {
                overcurrent_counts: None,
                bus_counts: Some((10_000, 40_000)),
            };
            let (mut d, mut b) = enabled(limits, quiet());
            let mut rx = 1;
            period(&mut d, &mut b, &mut rx, Some(1000));
            b.reading.adc_bus = bus;
            let (_, s, report) = period(&mut d, &mut b, &mut rx, Some(1000));
            assert_eq!(s.fault_bits, faults::BUS_VOLTAGE, "bus {bus}");
            assert!(report.is_some());
            assert_eq!(b.driven, Some((0, 0)));
        }
    }

    /// Silence after the first COMMAND: the duties are held for the watchdog's periods,
    /// then the outputs go off with WATCHDOG latched.
    #[test]
    fn a_silent_host_trips_the_watchdog() {
        let (mut d, mut b) = enabled(Limits::default(), quiet());
        let mut rx = 1;
        period(&mut d, &mut b, &mut rx, Some(1000));
        period(&mut d, &mut b, &mut rx, None);
        assert_eq!(b.driven, Some((1000, -1000)));
        let mut tripped = None;
        for n in 0..10 {
            let (_, _, report) = period(&mut d, &mut b, &mut rx, None);
            if report.is_some() {
                tripped = Some(n);
                break;
            }
            assert_eq!(b.driven, Some((1000, -1000)));
        }
        assert_eq!(tripped, Some(2), "the 4th period without a COMMAND");
        assert_eq!(d.latched_faults(), faults::WATCHDOG);
        assert_eq!(b.driven, Some((0, 0)));
    }
}
