//! Drive frames ↔ SI, without sockets or clocks: units and calibration live here and only
//! here, so the current loop, position loop and monitor see the same `DriveState` and
//! `DriveCommand` as with the simulated plant.

use crate::observer::VelocityObserver;
use stepdrive_drive_protocol::units::{duty_for, volts_for, Scaling};
use stepdrive_drive_protocol::{
    decode, is_newer, status, Action, Command, Config, ConfigError, DecodeError, FaultReport,
    Frame, Message, Plan, MAX_DUTY, MAX_PLAN_ENTRIES,
};
use stepdrive_runtime::cycle::MissRuns;
use stepdrive_shared::messages::{fault_bits, state_flags, DriveCommand, DrivePlan, DriveState};
use stepdrive_shared::stats::StatsReport;

/// What one received datagram turned into.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    State(DriveState),
    Config(Config),
    /// A CONFIG with a field the protocol does not allow: the drive cannot be used.
    BadConfig(ConfigError),
    /// A CONFIG that differs from the one taken at the handshake (§4.5, "A CONFIG outside
    /// the handshake"): never applied; the units the SAMPLEs are read in cannot change
    /// under a running motor, so the session must end.
    ConfigChanged(ConfigChange),
    Fault(FaultReport),
    /// Dropped: bad CRC, malformed, duplicate or out of order, stale, or unexpected.
    Dropped,
}

/// The first field in which a CONFIG differs from the one the host took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConfigChange {
    pub field: &'static str,
    pub was: i64,
    pub now: i64,
}

impl ConfigChange {
    /// The first field of §4.5's order in which `now` differs from `was`, if any.
    pub fn between(was: &Config, now: &Config) -> Option<Self> {
        let fields: [(&'static str, i64, i64); 11] = [
            (
                "sample_rate_hz",
                was.sample_rate_hz.into(),
                now.sample_rate_hz.into(),
            ),
            (
                "counts_per_rev",
                was.counts_per_rev.into(),
                now.counts_per_rev.into(),
            ),
            (
                "current_ua_per_count",
                was.current_ua_per_count.into(),
                now.current_ua_per_count.into(),
            ),
            (
                "current_zero_count",
                was.current_zero_count.into(),
                now.current_zero_count.into(),
            ),
            (
                "bus_uv_per_count",
                was.bus_uv_per_count.into(),
                now.bus_uv_per_count.into(),
            ),
            (
                "watchdog_periods",
                was.watchdog_periods.into(),
                now.watchdog_periods.into(),
            ),
            (
                "encoder_direction",
                was.encoder_direction.into(),
                now.encoder_direction.into(),
            ),
            (
                "plan_capacity",
                was.plan_capacity.into(),
                now.plan_capacity.into(),
            ),
            (
                "align_current_ma",
                was.align_current_ma.into(),
                now.align_current_ma.into(),
            ),
            ("align_ms", was.align_ms.into(), now.align_ms.into()),
            ("reserved", was.reserved[0].into(), now.reserved[0].into()),
        ];
        fields
            .into_iter()
            .find(|f| f.1 != f.2)
            .map(|(field, was, now)| Self { field, was, now })
    }
}

/// SAMPLEs with ALIGNING clear, after an alignment, that make up the held-current figure.
pub const HOLD_SAMPLES: u32 = 8;

/// What an aligned drive reports while phase A holds its rotor (§7 step 4): the mean of the
/// first [`HOLD_SAMPLES`] SAMPLEs with ALIGNING clear (not enabled, no fault) after the
/// last SAMPLE with ALIGNING set. One SAMPLE is one ADC reading; eight take most of its
/// noise out and last 4 ms at 2 kHz.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Hold {
    pub samples: u32,
    pub i_a_a: f64,
    pub i_b_a: f64,
    /// Phase A's duty as a fraction of the bus (−1 … 1), and the bus, V.
    pub duty_a: f64,
    pub bus_v: f64,
    /// θ as the link reads it before the run starts (from the first sample seen, or the
    /// encoder offset).
    pub theta_rad: f64,
}

impl Hold {
    fn add(&mut self, i_a: f64, i_b: f64, duty_a: f64, bus_v: f64, theta: f64) {
        let n = f64::from(self.samples);
        let mean = |m: f64, x: f64| (m * n + x) / (n + 1.0);
        self.i_a_a = mean(self.i_a_a, i_a);
        self.i_b_a = mean(self.i_b_a, i_b);
        self.duty_a = mean(self.duty_a, duty_a);
        self.bus_v = mean(self.bus_v, bus_v);
        self.theta_rad = mean(self.theta_rad, theta);
        self.samples += 1;
    }

    pub fn complete(&self) -> bool {
        self.samples >= HOLD_SAMPLES
    }
}

/// Which of the last 64 SAMPLE sequence numbers arrived: a late one is told apart from a
/// duplicate, so that a reordered sample is counted once (out of order), not also as lost.
#[derive(Debug, Clone, Copy, Default)]
struct SeqWindow {
    last: Option<u32>,
    /// Bit i: sample `last − i` arrived.
    seen: u64,
}

enum Arrival {
    /// Newer than every sample so far, `gap` periods after the last (1: none lost).
    Next { gap: u32 },
    /// Older, never seen: it was counted lost when its successor came.
    Late,
    /// Seen before, or too old to tell.
    Duplicate,
}

impl SeqWindow {
    fn arrive(&mut self, seq: u32) -> Arrival {
        let Some(last) = self.last else {
            self.last = Some(seq);
            self.seen = 1;
            return Arrival::Next { gap: 1 };
        };
        if is_newer(seq, Some(last)) {
            let gap = seq.wrapping_sub(last);
            self.seen = if gap >= 64 { 0 } else { self.seen << gap };
            self.seen |= 1;
            self.last = Some(seq);
            return Arrival::Next { gap };
        }
        let age = last.wrapping_sub(seq);
        if age < 64 && self.seen & (1 << age) == 0 {
            self.seen |= 1 << age;
            Arrival::Late
        } else {
            Arrival::Duplicate
        }
    }
}

/// Host-side encoder calibration, over what the drive's CONFIG says.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EncoderCalibration {
    /// Encoder reading at θ = 0 (an absolute encoder's zero): a reading of the SAMPLE's
    /// 32-bit counter, so it is subtracted modulo 2^32 (§6); `None` zeroes at the first
    /// sample.
    pub offset_counts: Option<i64>,
    /// Counts increase for negative θ, whatever CONFIG's `encoder_direction` says (an
    /// encoder or motor wired the other way round).
    pub reverse: bool,
    /// The load the host's model says the rotor carries, N·m, with its K_m (N·m/A) and N_r:
    /// an aligned rotor rests short of the electrical zero by asin(τ_L / (K_m I_align)) / N_r,
    /// and the host puts θ = 0 at the electrical zero, not where the load left the rotor.
    pub held_load: Option<HeldLoad>,
}

/// What holds an aligned rotor away from its electrical zero (docs/drive-protocol.md §7).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldLoad {
    pub torque_nm: f64,
    pub torque_constant_nm_per_a: f64,
    pub rotor_teeth: f64,
}

impl HeldLoad {
    /// Where the load holds a rotor aligned at `align_current_a` against phase A, rad from
    /// the electrical zero (negative for a load opposing +θ).
    pub fn rest_angle_rad(&self, align_current_a: f64) -> f64 {
        let sin = self.torque_nm / (self.torque_constant_nm_per_a * align_current_a);
        -sin.clamp(-1.0, 1.0).asin() / self.rotor_teeth
    }
}

// A drive that keeps the protocol's most PLAN entries gets the current loop's whole plan.
const _: () = assert!(MAX_PLAN_ENTRIES == stepdrive_shared::messages::MAX_PLAN);

/// Drive frames ↔ SI, without sockets or clocks.
pub struct DriveLink {
    scaling: Option<Scaling>,
    /// The CONFIG taken at the handshake, as the drive sent it (before `reverse`).
    config: Option<Config>,
    calibration: EncoderCalibration,
    /// PLAN entries the drive keeps (from CONFIG; 0: send none).
    plan_capacity: u16,
    /// The PLAN frame, built in place: 4 KB that a frame returned by value copied twice
    /// more, every tenth period.
    plan_out: Frame,
    observer: VelocityObserver,
    observer_hz: f64,
    sample_hz: f64,
    window: SeqWindow,
    first_seq: Option<u32>,
    /// The unwrapped position, counts from θ = 0 (the first sample, or the offset).
    counts: i64,
    last_raw: Option<i32>,
    /// θ of the first sample when the encoder is zeroed there: where alignment left the
    /// rotor, relative to the electrical zero (0 without alignment or a known load).
    start_angle_rad: f64,
    /// An alignment was seen (a SAMPLE with ALIGNING set) since the last restart, and what
    /// the drive reported holding the rotor after it.
    aligning_seen: bool,
    hold: Hold,
    /// After [`Self::restart`]: samples the drive sent before it took the ENABLE (in
    /// flight when it was sent) are not the run's; k = 0 is the first with ENABLED set.
    awaiting_enable: bool,
    /// Samples dropped that way.
    pub before_enable: u64,
    tx_seq: u32,
    /// Every datagram read, valid or not (the handshake names what came, §7 step 1).
    pub frames_received: u64,
    pub crc_errors: u64,
    pub bad_frames: u64,
    /// Why the last frame that failed validation failed.
    pub last_rejection: Option<DecodeError>,
    /// SAMPLEs that came before any CONFIG (dropped: they cannot be read).
    pub samples_before_config: u64,
    pub rejected_commands: u64,
    /// Periods the drive reported without their COMMAND, and of those the ones it covered
    /// with a PLAN entry; runs of such periods.
    pub held_periods: u64,
    pub planned_periods: u64,
    pub held_runs: MissRuns,
    /// Samples that never arrived: gaps in the drive's sample sequence.
    pub lost_on_wire: u64,
    /// FAULT_REPORT and CONFIG frames older than the newest sample (§3.1): dropped, and
    /// counted with the bad frames of the report.
    pub stale_reports: u64,
    /// CONFIGs identical to the one taken, after it (a late answer to a repeated HELLO):
    /// dropped, and counted with the bad frames of the report.
    pub repeated_configs: u64,
    /// Frames of another protocol version, and the last such version.
    pub other_version: (u64, u8),
    /// The status and fault bits of the newest sample.
    pub last_status: u16,
    /// Every status bit any sample carried since [`Self::clear_status_seen`]: a host that
    /// reads its samples late (held up, or a multi-axis bridge busy with another drive's
    /// start-up) still learns that the drive went through a state it has left by now.
    pub status_seen: u16,
    pub last_fault_bits: u16,
    /// The drive's timestamp of the last accepted sample, ns on the drive's clock.
    pub sample_timestamp_ns: u64,
}

impl DriveLink {
    pub fn new(sample_hz: f64, observer_hz: f64, calibration: EncoderCalibration) -> Self {
        Self {
            scaling: None,
            config: None,
            calibration,
            plan_capacity: 0,
            plan_out: Frame {
                seq: 0,
                timestamp_ns: 0,
                message: Message::Plan(Plan {
                    answers_sample: 0,
                    count: 0,
                    duties: [[0; 2]; MAX_PLAN_ENTRIES],
                }),
            },
            observer: VelocityObserver::new(observer_hz, 1.0 / sample_hz),
            observer_hz,
            sample_hz,
            window: SeqWindow::default(),
            first_seq: None,
            counts: 0,
            last_raw: None,
            start_angle_rad: 0.0,
            aligning_seen: false,
            hold: Hold::default(),
            awaiting_enable: false,
            before_enable: 0,
            tx_seq: 1,
            frames_received: 0,
            crc_errors: 0,
            bad_frames: 0,
            last_rejection: None,
            samples_before_config: 0,
            rejected_commands: 0,
            held_periods: 0,
            planned_periods: 0,
            held_runs: MissRuns::default(),
            lost_on_wire: 0,
            stale_reports: 0,
            repeated_configs: 0,
            other_version: (0, 0),
            last_status: 0,
            status_seen: 0,
            last_fault_bits: 0,
            sample_timestamp_ns: 0,
        }
    }

    /// A FAULT_REPORT or CONFIG sent before the newest sample is stale (§3.1): dropped and
    /// counted, never acted upon.
    fn stale(&mut self, seq: u32, what: &'static str) -> bool {
        let last = self.window.last;
        let stale = last.is_some_and(|last| is_newer(last, Some(seq)));
        if stale {
            self.stale_reports += 1;
            tracing::debug!(
                what,
                seq,
                newest_sample = last,
                stale = self.stale_reports,
                "stale frame from the drive dropped"
            );
        }
        stale
    }

    pub fn configured(&self) -> bool {
        self.scaling.is_some()
    }

    /// The CONFIG taken at the handshake, as the drive sent it.
    pub fn config(&self) -> Option<&Config> {
        self.config.as_ref()
    }

    /// What the drive reported holding its rotor after the last alignment seen (§7 step 4).
    pub fn hold(&self) -> Hold {
        self.hold
    }

    /// The wire seq of the newest SAMPLE accepted.
    pub fn newest_sample_seq(&self) -> Option<u32> {
        self.window.last
    }

    /// Radians per encoder count (0 before a CONFIG).
    pub fn rad_per_count(&self) -> f64 {
        self.scaling.map_or(0.0, |s| s.theta(1).abs())
    }

    /// Forgets the sample stream (index, position, velocity, counters) so that run starts
    /// at k = 0 with the next sample; the configuration is kept. θ there is where the last
    /// alignment's hold left the rotor, from the held current the drive reported (§7,
    /// "Alignment under load"); without a hold seen, from the align current it announced.
    pub fn restart(&mut self) {
        let held_a = self.hold.complete().then_some(self.hold.i_a_a);
        let start_angle_rad = self.config.map_or(0.0, |c| self.start_angle(&c, held_a));
        *self = Self {
            scaling: self.scaling,
            config: self.config,
            plan_capacity: self.plan_capacity,
            start_angle_rad,
            hold: self.hold,
            awaiting_enable: true,
            other_version: self.other_version,
            tx_seq: self.tx_seq,
            ..Self::new(self.sample_hz, self.observer_hz, self.calibration)
        };
    }

    /// Where the aligned rotor rests from the electrical zero: an absolute zero is the
    /// electrical zero itself; an aligned one is where the load let the rotor rest against
    /// phase A's current (the one measured holding it, else the announced one).
    fn start_angle(&self, c: &Config, held_a: Option<f64>) -> f64 {
        match (self.calibration.held_load, self.calibration.offset_counts) {
            (Some(load), None) if c.align_ms > 0 && c.align_current_ma > 0 => {
                let announced = f64::from(c.align_current_ma) * 1e-3;
                // A current at or below zero is refused by the checks before any run; θ₀
                // from it would be meaningless.
                let i = held_a.filter(|&i| i > 0.0).unwrap_or(announced);
                load.rest_angle_rad(i)
            }
            _ => 0.0,
        }
    }

    /// Index k of the drive sample with wire sequence `seq` (k = 0 at the first sample).
    fn index_of(&self, seq: u32) -> u64 {
        u64::from(seq.wrapping_sub(self.first_seq.unwrap_or(seq)))
    }

    pub fn on_frame(&mut self, bytes: &[u8], now_ns: u64) -> Event {
        self.frames_received += 1;
        let frame = match decode(bytes) {
            Ok(f) => f,
            Err(e) => {
                match e {
                    DecodeError::BadCrc { .. } => self.crc_errors += 1,
                    DecodeError::BadVersion(v) => {
                        self.bad_frames += 1;
                        self.other_version = (self.other_version.0 + 1, v);
                    }
                    _ => self.bad_frames += 1,
                }
                self.last_rejection = Some(e);
                return Event::Dropped;
            }
        };
        match frame.message {
            Message::Config(c) => {
                if self.stale(frame.seq, "CONFIG") {
                    return Event::Dropped;
                }
                if let Some(taken) = &self.config {
                    // Only the handshake's CONFIG is read (§4.5): a later identical one is
                    // a late answer to a repeated HELLO; a different one would change the
                    // units of every SAMPLE under a running motor.
                    return match ConfigChange::between(taken, &c) {
                        None => {
                            self.repeated_configs += 1;
                            tracing::debug!(
                                repeated = self.repeated_configs,
                                "a CONFIG identical to the one taken: dropped"
                            );
                            Event::Dropped
                        }
                        Some(change) => Event::ConfigChanged(change),
                    };
                }
                if let Err(e) = c.check() {
                    return Event::BadConfig(e);
                }
                self.config = Some(c);
                let mut c = c;
                if self.calibration.reverse {
                    c.encoder_direction = if c.encoder_direction < 0 { 1 } else { -1 };
                }
                self.scaling = Some(Scaling::new(&c));
                self.start_angle_rad = self.start_angle(&c, None);
                self.plan_capacity = c.plan_capacity.min(MAX_PLAN_ENTRIES as u16);
                Event::Config(c)
            }
            Message::FaultReport(f) => {
                if self.stale(frame.seq, "FAULT_REPORT") {
                    return Event::Dropped;
                }
                Event::Fault(f)
            }
            Message::Sample(s) => {
                let Some(scaling) = self.scaling else {
                    self.bad_frames += 1;
                    self.samples_before_config += 1;
                    return Event::Dropped;
                };
                // A faulted drive reports ENABLED clear too: that sample starts the run, so
                // that its fault is seen.
                // An ENABLE taken during an ALIGN shows ENABLED beside ALIGNING: the run starts
                // when the alignment ends (§7 step 5).
                let running = s.status & (status::ENABLED | status::ALIGNING) == status::ENABLED;
                if self.awaiting_enable && !running && s.fault_bits == 0 {
                    self.before_enable += 1;
                    return Event::Dropped;
                }
                self.awaiting_enable = false;
                let gap = match self.window.arrive(frame.seq) {
                    Arrival::Next { gap } => gap,
                    Arrival::Late => {
                        // Counted lost when its successor came; it did arrive, too late.
                        self.lost_on_wire = self.lost_on_wire.saturating_sub(1);
                        self.bad_frames += 1;
                        return Event::Dropped;
                    }
                    Arrival::Duplicate => {
                        self.bad_frames += 1;
                        return Event::Dropped;
                    }
                };
                self.lost_on_wire += u64::from(gap - 1);
                self.last_status = s.status;
                self.status_seen |= s.status;
                self.last_fault_bits = s.fault_bits;
                self.sample_timestamp_ns = frame.timestamp_ns;
                self.first_seq.get_or_insert(frame.seq);
                // Unwrap the 32-bit counter into a 64-bit position by differences, the
                // first one against the configured offset: that too is a reading of the
                // 32-bit counter, so it is taken modulo 2^32 (§6) like every other
                // difference (a reading across the ±2^31 wrap from the offset is a few
                // counts away, not 2^32).
                let step = match (self.last_raw, self.calibration.offset_counts) {
                    (Some(prev), _) => s.encoder_counts.wrapping_sub(prev),
                    (None, Some(offset)) => s.encoder_counts.wrapping_sub(offset as i32),
                    (None, None) => 0,
                };
                self.last_raw = Some(s.encoder_counts);
                self.counts += i64::from(step);
                let theta = scaling.theta(self.counts) + self.start_angle_rad;
                let omega = self.observer.update(theta, gap);
                let bus = scaling.bus_volts(s.adc_bus);
                let k = self.index_of(frame.seq);
                let mut fault = 0;
                if s.fault_bits != 0 {
                    fault = fault_bits::DRIVE_FAULT | (u32::from(s.fault_bits) << 16);
                }
                let mut flags = 0;
                let held = s.status & status::COMMAND_HELD != 0;
                self.held_runs.record(held);
                if held {
                    flags |= state_flags::COMMAND_HELD;
                    self.held_periods += 1;
                    if s.status & status::COMMAND_PLANNED != 0 {
                        flags |= state_flags::COMMAND_PLANNED;
                        self.planned_periods += 1;
                    }
                }
                let (i_a, i_b) = (scaling.amps(s.adc_a), scaling.amps(s.adc_b));
                if s.status & status::ALIGNING != 0 {
                    // A new alignment: the hold after it is measured afresh.
                    self.aligning_seen = true;
                    self.hold = Hold::default();
                } else if self.aligning_seen
                    && s.status & status::ENABLED == 0
                    && s.fault_bits == 0
                    && !self.hold.complete()
                {
                    let duty = f64::from(s.duty_a.clamp(-MAX_DUTY, MAX_DUTY)) / f64::from(MAX_DUTY);
                    self.hold.add(i_a, i_b, duty, bus, theta);
                }
                Event::State(DriveState {
                    seq: k,
                    sample_time_s: k as f64 / self.sample_hz,
                    publish_time_ns: 0,
                    deadline_ns: now_ns,
                    applied_command_seq: u64::from(s.applied_command_seq),
                    theta_rad: theta,
                    omega_rad_s: omega,
                    i_a_a: i_a,
                    i_b_a: i_b,
                    v_a_v: volts_for(s.duty_a, bus),
                    v_b_v: volts_for(s.duty_b, bus),
                    bus_voltage_v: bus,
                    flags,
                    fault,
                })
            }
            _ => {
                self.bad_frames += 1;
                Event::Dropped
            }
        }
    }

    /// The frame carrying `c`, or `None` (counted) if it must not reach the drive: a
    /// non-finite voltage or one beyond the measured bus voltage.
    pub fn command_frame(&mut self, c: &DriveCommand, bus_v: f64, now_ns: u64) -> Option<Frame> {
        let (Some(a), Some(b)) = (duty_for(c.v_a_v, bus_v), duty_for(c.v_b_v, bus_v)) else {
            self.rejected_commands += 1;
            return None;
        };
        let first = self.first_seq?;
        let frame = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Command(Command {
                answers_sample: first.wrapping_add(c.answers_seq as u32),
                duty_a: a,
                duty_b: b,
            }),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        Some(frame)
    }

    /// A COMMAND with these duties answering the SAMPLE with wire seq `answers_sample`: the
    /// host's own, before the run (the phase check of §7 step 4).
    pub fn duty_command_frame(
        &mut self,
        answers_sample: u32,
        duty_a: i16,
        duty_b: i16,
        now_ns: u64,
    ) -> Frame {
        let frame = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Command(Command {
                answers_sample,
                duty_a,
                duty_b,
            }),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        frame
    }

    /// The PLAN frame carrying `plan` (as many entries as the drive keeps), or `None` if the
    /// drive keeps none or any entry must not reach it (non-finite or beyond the measured
    /// bus: the whole plan is refused and counted with the rejected commands).
    pub fn plan_frame(&mut self, plan: &DrivePlan, bus_v: f64, now_ns: u64) -> Option<&Frame> {
        let first = self.first_seq?;
        let count = plan.entries().len().min(usize::from(self.plan_capacity));
        if count == 0 {
            return None;
        }
        let Message::Plan(out) = &mut self.plan_out.message else {
            unreachable!("plan_out is built as a PLAN and only ever refilled");
        };
        for (d, v) in out.duties.iter_mut().zip(&plan.entries()[..count]) {
            let (Some(a), Some(b)) = (
                duty_for(f64::from(v[0]), bus_v),
                duty_for(f64::from(v[1]), bus_v),
            ) else {
                self.rejected_commands += 1;
                return None;
            };
            *d = [a, b];
        }
        out.answers_sample = first.wrapping_add(plan.answers_seq as u32);
        out.count = count as u16;
        self.plan_out.seq = self.tx_seq;
        self.plan_out.timestamp_ns = now_ns;
        self.tx_seq = self.tx_seq.wrapping_add(1);
        Some(&self.plan_out)
    }

    /// Puts the link's counters into a stats report (drive-held periods are its misses).
    pub fn copy_counters(&self, stats: &mut StatsReport) {
        stats.lost = self.lost_on_wire;
        stats.crc_errors = self.crc_errors;
        // Stale reports and repeated CONFIGs are dropped frames like any other (§3.1).
        stats.bad_frames = self.bad_frames + self.stale_reports + self.repeated_configs;
        stats.rejected_commands = self.rejected_commands;
        stats.misses = self.held_periods;
        stats.planned = self.planned_periods;
        self.held_runs.copy_to(stats);
    }

    pub fn control_frame(&mut self, action: Action, now_ns: u64) -> Frame {
        let f = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Control(action),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        f
    }

    pub fn hello_frame(&mut self, now_ns: u64) -> Frame {
        let f = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Hello,
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_protocol::units::default_config;
    use stepdrive_drive_protocol::{frame_bytes as bytes, Sample};

    fn sample(counts: i32) -> Message {
        Message::Sample(Sample {
            encoder_counts: counts,
            adc_a: 32768 + 1510,
            adc_b: 32768,
            adc_bus: 2400,
            duty_a: 16384,
            duty_b: 0,
            applied_command_seq: 0,
            fault_bits: 0,
            status: 0,
        })
    }

    #[test]
    fn samples_become_si_states_and_bad_frames_are_dropped() {
        let mut l = DriveLink::new(20_000.0, 400.0, zero_offset());
        assert_eq!(
            l.on_frame(&bytes(9, sample(5)), 0),
            Event::Dropped,
            "no CONFIG yet"
        );
        let cfg = default_config(20_000.0, 200, 200);
        assert!(matches!(
            l.on_frame(&bytes(0, Message::Config(cfg)), 0),
            Event::Config(_)
        ));
        let Event::State(st) = l.on_frame(&bytes(100, sample(1 << 18)), 7) else {
            panic!()
        };
        assert_eq!(st.seq, 0);
        assert!((st.theta_rad - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((st.i_a_a - 0.151).abs() < 1e-9);
        assert!((st.bus_voltage_v - 24.0).abs() < 1e-9);
        assert!((st.v_a_v - 12.0).abs() < 1e-3);
        assert_eq!(st.deadline_ns, 7);
        // Corrupted: counted, no state.
        let mut bad = bytes(101, sample(0));
        bad[25] ^= 4;
        assert_eq!(l.on_frame(&bad, 0), Event::Dropped);
        assert_eq!(l.crc_errors, 1);
        // Duplicate and out of order: counted, no state.
        assert_eq!(l.on_frame(&bytes(100, sample(0)), 0), Event::Dropped);
        assert_eq!(l.on_frame(&bytes(99, sample(0)), 0), Event::Dropped);
        assert_eq!(l.bad_frames, 3);
        // A gap is visible in the index; counter wrap-around unwraps.
        let Event::State(st) = l.on_frame(&bytes(103, sample(i32::MAX)), 0) else {
            panic!()
        };
        assert_eq!(st.seq, 3);
        let Event::State(st2) = l.on_frame(&bytes(104, sample(i32::MIN)), 0) else {
            panic!()
        };
        assert!(st2.theta_rad > st.theta_rad);
    }

    fn zero_offset() -> EncoderCalibration {
        EncoderCalibration {
            offset_counts: Some(0),
            reverse: false,
            held_load: None,
        }
    }

    /// A configured offset is θ = 0 and `reverse` flips CONFIG's direction; without an
    /// offset the first sample is θ = 0.
    #[test]
    fn encoder_calibration_overrides() {
        let quarter: i32 = 1 << 18; // a quarter turn of the 20-bit encoder
        let theta_of = |cal: EncoderCalibration, counts: &[i32]| {
            let mut l = DriveLink::new(20_000.0, 400.0, cal);
            l.on_frame(
                &bytes(0, Message::Config(default_config(20_000.0, 200, 0))),
                0,
            );
            let mut theta = f64::NAN;
            for (i, &c) in counts.iter().enumerate() {
                if let Event::State(st) = l.on_frame(&bytes(10 + i as u32, sample(c)), 0) {
                    theta = st.theta_rad;
                }
            }
            theta
        };
        let half_pi = std::f64::consts::FRAC_PI_2;
        let offset = |o: i64, reverse| EncoderCalibration {
            offset_counts: Some(o),
            reverse,
            held_load: None,
        };
        let q = i64::from(quarter);
        assert!((theta_of(offset(q, false), &[2 * quarter]) - half_pi).abs() < 1e-12);
        assert!((theta_of(offset(q, true), &[2 * quarter]) + half_pi).abs() < 1e-12);
        let first = EncoderCalibration::default();
        assert!((theta_of(first, &[quarter, 2 * quarter]) - half_pi).abs() < 1e-12);
    }

    #[test]
    fn bad_commands_are_never_sent() {
        let mut l = DriveLink::new(20_000.0, 400.0, zero_offset());
        l.on_frame(
            &bytes(0, Message::Config(default_config(20_000.0, 200, 200))),
            0,
        );
        l.on_frame(&bytes(50, sample(0)), 0);
        let c = |va: f64| DriveCommand {
            answers_seq: 0,
            v_a_v: va,
            v_b_v: 0.0,
            ..Default::default()
        };
        assert!(l.command_frame(&c(f64::NAN), 24.0, 0).is_none());
        assert!(l.command_frame(&c(f64::INFINITY), 24.0, 0).is_none());
        assert!(l.command_frame(&c(30.0), 24.0, 0).is_none());
        assert_eq!(l.rejected_commands, 3);
        let f = l.command_frame(&c(-12.0), 24.0, 0).expect("valid");
        let Message::Command(cmd) = f.message else {
            panic!()
        };
        assert_eq!((cmd.answers_sample, cmd.duty_a), (50, -16384));
    }
}
