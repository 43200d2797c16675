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
//! - **start-up** (§7): HELLO until a CONFIG within the handshake time, then RESET and
//!   ALIGN, the held current and its scale, the phase-B step, ALIGN again; a drive that
//!   fails a step is refused ([`Refusal`]) and every exit path after a HELLO sends DISABLE
//!   ([`BridgeCore::farewell`]).

use crate::link::{ConfigChange, DriveLink, EncoderCalibration, Event, Hold};
use std::f64::consts::FRAC_PI_2;
use stepdrive_drive_protocol::{
    faults, status, Action, Config, ConfigError, DecodeError, Frame, MAX_DUTY, VERSION,
};
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
    /// What the host's model says of the motor, for the start-up checks (§7 step 4): its
    /// winding resistance (Ω) and its rotor teeth N_r.
    pub resistance_ohm: f64,
    pub rotor_teeth: f64,
}

/// What a frame from the drive was.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Received {
    /// A SAMPLE, kept as the newest until it is taken.
    Sample,
    Config(Config),
    /// A CONFIG the protocol does not allow (named field): the drive cannot be used.
    BadConfig(ConfigError),
    /// A CONFIG other than the one taken at the handshake: not applied; the session ends.
    ConfigChanged(ConfigChange),
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
    /// Where the start-up stands (§7), and whether a HELLO went out (from then on the drive
    /// may have a session with this host, and every exit path sends DISABLE).
    stage: Stage,
    hello_sent: bool,
}

/// How often HELLO is repeated until the drive's CONFIG arrives (§4.6).
pub const HELLO_EVERY_NS: u64 = 50_000_000;
/// The handshake time (§7 step 1): a drive whose CONFIG has not arrived this long after the
/// first HELLO (or after the last "port unreachable", while the drive was not up yet), with
/// at least [`HANDSHAKE_HELLOS`] HELLOs sent, is named with what did arrive. A drive on a
/// cable answers within a period; twenty HELLOs outlast any loss but a dead link.
pub const HANDSHAKE_NS: u64 = 1_000_000_000;
pub const HANDSHAKE_HELLOS: u32 = 20;
/// How much longer than its announced time a drive may take to report its alignment done
/// (and to report the hold after it, and the phase-B step), by its own timestamps.
pub const ALIGN_SLACK_MS: u64 = 1_000;
/// The same on the host's clock, which only bounds a drive that stops sending: a loaded
/// host reads SAMPLEs late (seen: a healthy drive's alignment judged 1.3 s long), and their
/// timestamps say how long the drive took.
pub const ALIGN_HOST_SLACK_MS: u64 = 5_000;

/// When a start-up step (an alignment, its hold, the phase-B step) began, on both clocks.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Since {
    host_ns: u64,
    /// On the drive's clock: the newest SAMPLE's timestamp when the step began (the first
    /// SAMPLE's, if none had come).
    drive_ns: Option<u64>,
}

impl Since {
    fn new(host_ns: u64, link: &DriveLink) -> Self {
        Self {
            host_ns,
            drive_ns: link.newest_sample_seq().map(|_| link.sample_timestamp_ns),
        }
    }

    /// How long the step has taken, ms: on the drive's clock (up to its newest SAMPLE) and
    /// on the host's.
    fn waited_ms(&mut self, link: &DriveLink, now: u64) -> (u64, u64) {
        let newest = link.sample_timestamp_ns;
        if link.newest_sample_seq().is_some() {
            self.drive_ns.get_or_insert(newest);
        }
        let drive = self.drive_ns.map_or(0, |d| newest.saturating_sub(d));
        (
            drive / 1_000_000,
            now.saturating_sub(self.host_ns) / 1_000_000,
        )
    }

    /// Past `announced_ms` and its slack on either clock: the one that is, and the wait.
    fn overdue(&mut self, link: &DriveLink, now: u64, announced_ms: u64) -> Option<(u64, bool)> {
        let (drive, host) = self.waited_ms(link, now);
        if drive > announced_ms + ALIGN_SLACK_MS {
            Some((drive, true))
        } else if host > announced_ms + ALIGN_HOST_SLACK_MS {
            Some((host, false))
        } else {
            None
        }
    }
}

/// Which clock a start-up step overran on, for its error.
fn clock_name(by_drive: bool) -> &'static str {
    if by_drive {
        "by its own timestamps"
    } else {
        "of the host's clock"
    }
}

/// Where the start-up sequence of §7 stands.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Stage {
    /// HELLO until CONFIG (step 1).
    Handshake {
        since_ns: Option<u64>,
        next_hello_ns: u64,
        hellos: u32,
    },
    /// Configured; waiting for the stack before touching the motor.
    Joining,
    /// RESET and ALIGN sent: waiting for the samples to show the alignment begin and end.
    Aligning {
        round: Round,
        since: Since,
        seen: bool,
    },
    /// Aligned: collecting the hold's figures ([`Hold`]).
    Holding { round: Round, since: Since },
    /// Enabled, phase B alone driven by the host's COMMANDs (step 4).
    Stepping(PhaseStep),
    /// Every check passed: the run may begin.
    Ready,
    /// The stream runs (after [`BridgeCore::begin`]).
    Running,
}

/// Which alignment: the first one, before the phase-B step, or the last one, which the run
/// starts from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Round {
    First,
    Last,
}

/// The phase-B step (§7 step 4): with the rotor held by phase A, the host drives phase B
/// alone at the hold's duty; a motor wired and sensed as the host assumes turns a quarter
/// electrical period towards +θ.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PhaseStep {
    since: Since,
    duty_b: i16,
    /// The hold before it.
    from: Hold,
    /// SAMPLEs the step lasts, the first ENABLED one's wire seq, the last one answered.
    periods: u32,
    first: Option<u32>,
    answered: Option<u32>,
    /// Means over its second half, when the rotor has settled.
    n: u32,
    theta_rad: f64,
    i_a_a: f64,
    i_b_a: f64,
}

/// What the host-driven start-up asks of the node after one look at the time and the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StartStep {
    /// Nothing to do until frames arrive or time passes.
    Wait,
    /// Nothing to do, but the drive's SAMPLEs must be answered as they come (the phase-B
    /// step: the drive's watchdog is armed): look again as soon as the wire is readable.
    Answer,
    /// Every check passed: drop the queued samples and [`BridgeCore::begin`].
    Ready,
}

/// Why the host will not run a drive: each names what it saw against the rule it broke
/// (docs/drive-protocol.md). Displayed after "the drive at ADDRESS ".
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Refusal {
    #[error("sent a CONFIG this host cannot use: {0}")]
    Config(ConfigError),
    #[error(
        "sent a CONFIG during its session that differs from the one of the handshake \
         ({} was {}, now {}): it was not applied, and the session ends, because the units \
         its SAMPLEs are read in cannot change under a running motor \
         (docs/drive-protocol.md §4.5, \"A CONFIG outside the handshake\")",
        .0.field, .0.was, .0.now
    )]
    ConfigChanged(ConfigChange),
    #[error("samples at {drive_hz} Hz, the scenario expects {scenario_hz} Hz")]
    SampleRate { drive_hz: u32, scenario_hz: f64 },
    #[error(
        "does not align (CONFIG align_ms 0) and no encoder offset is configured \
         ([drive] encoder_offset_counts or --encoder-offset): θ = 0 would be wherever the \
         rotor happens to rest, not an electrical zero, and every command would be \
         commutated at that angle's error (docs/drive-protocol.md §7)"
    )]
    NoElectricalZero,
    #[error("{0}")]
    Handshake(HandshakeReport),
    #[error(
        "did not finish its alignment ({align_ms} ms announced) within {waited_ms} ms {}: \
         no SAMPLE with ALIGNING set and then cleared (docs/drive-protocol.md §7)",
        clock_name(*by_drive)
    )]
    Align {
        align_ms: u16,
        waited_ms: u64,
        by_drive: bool,
    },
    #[error(
        "did not finish {during} within {waited_ms} ms {} (docs/drive-protocol.md §7)",
        clock_name(*by_drive)
    )]
    Stalled {
        during: &'static str,
        waited_ms: u64,
        by_drive: bool,
    },
    #[error(
        "latched {} (fault bits {bits:#06x}) during {during} (docs/drive-protocol.md §5); \
         the host does not start a run on it", faults::named(*bits)
    )]
    Fault { bits: u16, during: &'static str },
    #[error(
        "holding its rotor after its ALIGN, reports phase A at {i_a_a:+.3} A and phase B at \
         {i_b_a:+.3} A; it must drive phase A alone at its align current, {align_a:+.3} A \
         (docs/drive-protocol.md §7 step 4): a phase wired the other way round, or a current \
         sense of the wrong sign or scale (CONFIG current_zero_count, current_ua_per_count), \
         would commutate the motor wrongly"
    )]
    HeldCurrent {
        i_a_a: f64,
        i_b_a: f64,
        align_a: f64,
    },
    #[error(
        "holds phase A at {i_a_a:.3} A with a duty of {duty_pct:.1} % of its {bus_v:.2} V \
         bus, which drives {expected_a:.3} A through the model's {resistance_ohm} Ω: its \
         current sense reads {ratio:.2} × that, outside {min} … {max} (docs/drive-protocol.md \
         §7 step 4, \"The current scale\"): a wrong CONFIG current_ua_per_count, or a model \
         resistance ([motor] resistance_ohm) that is not this motor's",
        min = CURRENT_SCALE_MIN,
        max = CURRENT_SCALE_MAX
    )]
    CurrentScale {
        i_a_a: f64,
        duty_pct: f64,
        bus_v: f64,
        expected_a: f64,
        resistance_ohm: f64,
        ratio: f64,
    },
    #[error(
        "driven on phase B alone at a duty of {duty_b} after its alignment, reports phase A \
         at {i_a_a:+.3} A and phase B at {i_b_a:+.3} A; phase B must carry about the held \
         {held_a:+.3} A and phase A none (docs/drive-protocol.md §7 step 4): phase B's \
         current sense has the wrong sign or scale, or the phases are swapped"
    )]
    PhaseBCurrent {
        duty_b: i16,
        i_a_a: f64,
        i_b_a: f64,
        held_a: f64,
    },
    #[error(
        "turned its rotor {moved_rad:+.4} rad when phase B alone was driven at +{i_b_a:.3} A \
         after its alignment; a motor wired and sensed as this host assumes turns a quarter \
         electrical period towards +θ, {expected_rad:+.4} rad ({ratio:.2} × that, outside \
         {min} … {max}; docs/drive-protocol.md §7 step 4, \"The phase-B step\"): phase A's \
         or phase B's motor leads swapped, an encoder counting the other way (CONFIG \
         encoder_direction, --reverse-encoder), or a wrong counts_per_rev or N_r",
        min = STEP_MIN,
        max = STEP_MAX
    )]
    PhaseStep {
        moved_rad: f64,
        expected_rad: f64,
        ratio: f64,
        i_b_a: f64,
    },
}

/// What the host heard from a drive whose CONFIG never came within the handshake time.
#[derive(Debug, Clone, PartialEq)]
pub struct HandshakeReport {
    pub waited_ms: u64,
    pub hellos: u32,
    /// Datagrams read from the drive's address, and of those SAMPLEs before any CONFIG.
    pub frames: u64,
    pub samples: u64,
    /// Frames of another protocol version, and the last version seen.
    pub other_version: (u64, u8),
    /// Why the last frame that failed validation failed.
    pub last_rejection: Option<DecodeError>,
    /// Frames that came from another address or port of the drive's host instead (the node
    /// looks once the handshake failed with nothing heard: §2).
    pub elsewhere: Option<std::net::SocketAddr>,
}

impl std::fmt::Display for HandshakeReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "sent no usable CONFIG within {} ms ({} HELLOs, one every {} ms; \
             docs/drive-protocol.md §7 step 1): ",
            self.waited_ms,
            self.hellos,
            HELLO_EVERY_NS / 1_000_000
        )?;
        if self.frames == 0 {
            write!(f, "no frame came from that address and port")?;
            return match self.elsewhere {
                Some(from) => write!(
                    f,
                    "; frames came from {from} instead: a drive must send from the port it \
                     listens on (§2), and this host reads only the drive's address and port"
                ),
                None => write!(
                    f,
                    " (is it on, at that address, and does it answer HELLO from the port it \
                     listens on? §2)"
                ),
            };
        }
        write!(f, "{} frames came", self.frames)?;
        if self.other_version.0 > 0 {
            write!(
                f,
                ", {} of them of protocol version {} (this host speaks version {VERSION})",
                self.other_version.0, self.other_version.1
            )?;
        }
        if self.samples > 0 {
            write!(
                f,
                ", {} of them SAMPLEs before any CONFIG (a drive answers each HELLO with a \
                 CONFIG, §4.6)",
                self.samples
            )?;
        }
        if let Some(e) = &self.last_rejection {
            write!(f, "; the last frame dropped: ")?;
            match e {
                DecodeError::Reserved(5) => write!(
                    f,
                    "a CONFIG with its reserved byte (offset 27) set, which a receiver drops \
                     unread (§3, §4.5)"
                )?,
                DecodeError::Reserved(k) => write!(
                    f,
                    "a frame of kind {k} with a reserved byte set, which a receiver drops \
                     unread (§3)"
                )?,
                other => write!(f, "{other} (§3)")?,
            }
        }
        Ok(())
    }
}

/// The current-scale check (§7 step 4): the held current against what the hold's duty
/// drives through the model's resistance. A winding warms from the model's temperature by
/// up to ~110 K in use (copper +0.39 %/K: R × 1.43) and a motor's R is within ±10 % of its
/// datasheet, so a sense that reads right gives 1/(1.43 × 1.1) = 0.64 … 1/(0.88 × 0.9) =
/// 1.26 × (0.88: a winding 30 K colder than the model's): the band is that, rounded out.
/// A 1.4× scale error at a cold start reads 1.4 and is refused; in a hot winding it can
/// hide (the document says so).
pub const CURRENT_SCALE_MIN: f64 = 0.6;
pub const CURRENT_SCALE_MAX: f64 = 1.3;
/// The phase-B step (§7 step 4) must turn the rotor 0.5 … 1.5 × a quarter electrical
/// period towards +θ: the sign tells a wiring or encoder-direction error; the magnitude a
/// counts_per_rev or N_r twice or half what it is. Detent torque and friction move the
/// two rest positions by a few % of it, not by half.
pub const STEP_MIN: f64 = 0.5;
pub const STEP_MAX: f64 = 1.5;
/// A quarter electrical period of fewer encoder counts than this cannot be judged.
pub const STEP_MIN_COUNTS: f64 = 4.0;

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
            stage: Stage::Handshake {
                since_ns: None,
                next_hello_ns: 0,
                hellos: 0,
            },
            hello_sent: false,
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
        self.hello_sent = true;
        self.link.hello_frame(now)
    }

    /// The node saw "port unreachable" from the drive's address: nothing listens there yet
    /// (a drive starting up). The handshake time counts from the last such answer; the node
    /// gives up on a drive that keeps answering it.
    pub fn refused(&mut self, now: u64) {
        if let Stage::Handshake { since_ns, .. } = &mut self.stage {
            *since_ns = Some(now);
        }
    }

    /// The start-up of §7, one look at a time: sends (through `send`) the frames due now,
    /// and says what the node should do next. `stack_ready`: the loops the run needs are
    /// there (the motor is not touched before).
    pub fn startup(
        &mut self,
        now: u64,
        stack_ready: bool,
        send: &mut dyn FnMut(&Frame),
    ) -> Result<StartStep, Refusal> {
        loop {
            match self.stage {
                Stage::Handshake {
                    since_ns,
                    next_hello_ns,
                    hellos,
                } => {
                    if self.link.configured() {
                        self.accept_config()?;
                        self.stage = Stage::Joining;
                        continue;
                    }
                    let since = since_ns.unwrap_or(now);
                    let waited = now.saturating_sub(since);
                    if waited >= HANDSHAKE_NS && hellos >= HANDSHAKE_HELLOS {
                        let l = &self.link;
                        return Err(Refusal::Handshake(HandshakeReport {
                            waited_ms: waited / 1_000_000,
                            hellos,
                            frames: l.frames_received,
                            samples: l.samples_before_config,
                            other_version: l.other_version,
                            last_rejection: l.last_rejection.clone(),
                            elsewhere: None,
                        }));
                    }
                    let mut next = next_hello_ns;
                    let mut sent = hellos;
                    if now >= next_hello_ns {
                        send(&self.hello(now));
                        sent += 1;
                        next = now + HELLO_EVERY_NS;
                    }
                    self.stage = Stage::Handshake {
                        since_ns: Some(since),
                        next_hello_ns: next,
                        hellos: sent,
                    };
                    return Ok(StartStep::Wait);
                }
                Stage::Joining => {
                    if !stack_ready {
                        return Ok(StartStep::Wait);
                    }
                    // A fresh start: nothing a previous session latched, the rotor at an
                    // electrical zero (a drive that does not align has an absolute encoder
                    // whose offset the host was given: accept_config).
                    send(&self.link.control_frame(Action::Reset, now));
                    if self.align_ms() == 0 {
                        self.stage = Stage::Ready;
                        continue;
                    }
                    send(&self.link.control_frame(Action::Align, now));
                    self.link.status_seen = 0;
                    self.stage = Stage::Aligning {
                        round: Round::First,
                        since: Since::new(now, &self.link),
                        seen: false,
                    };
                    return Ok(StartStep::Wait);
                }
                Stage::Aligning {
                    round,
                    mut since,
                    seen,
                } => {
                    let aligning = self.link.last_status & status::ALIGNING != 0;
                    // An alignment begun and ended between two readings still counts.
                    let seen = seen || self.link.status_seen & status::ALIGNING != 0;
                    // Samples sent before the drive took the RESET may still carry a fault
                    // of a previous session; from the ALIGN's first SAMPLE on, one is new.
                    if seen || aligning {
                        self.fault_check(alignment_name(round))?;
                    }
                    if seen && !aligning {
                        self.stage = Stage::Holding { round, since };
                        continue;
                    }
                    self.align_deadline(&mut since, now)?;
                    self.stage = Stage::Aligning {
                        round,
                        since,
                        seen: seen || aligning,
                    };
                    return Ok(StartStep::Wait);
                }
                Stage::Holding { round, mut since } => {
                    self.fault_check(alignment_name(round))?;
                    let hold = self.link.hold();
                    if !hold.complete() {
                        self.align_deadline(&mut since, now)?;
                        self.stage = Stage::Holding { round, since };
                        return Ok(StartStep::Wait);
                    }
                    self.check_hold(&hold)?;
                    if round == Round::Last {
                        self.stage = Stage::Ready;
                        continue;
                    }
                    let Some(step) = self.phase_step(&hold, now) else {
                        self.stage = Stage::Ready;
                        continue;
                    };
                    send(&self.link.control_frame(Action::Enable, now));
                    self.stage = Stage::Stepping(step);
                    return Ok(StartStep::Answer);
                }
                Stage::Stepping(mut step) => {
                    self.fault_check("the phase-B step")?;
                    let announced = u64::from(self.align_ms());
                    if let Some((waited_ms, by_drive)) =
                        step.since.overdue(&self.link, now, announced)
                    {
                        return Err(Refusal::Stalled {
                            during: "the phase-B step",
                            waited_ms,
                            by_drive,
                        });
                    }
                    if let (Some(first), Some(newest)) = (step.first, self.link.newest_sample_seq())
                    {
                        if newest.wrapping_sub(first) >= step.periods {
                            judge_phase_step(&step, self.settings.rotor_teeth)?;
                            send(&self.link.control_frame(Action::Align, now));
                            self.link.status_seen = 0;
                            self.stage = Stage::Aligning {
                                round: Round::Last,
                                since: Since::new(now, &self.link),
                                seen: false,
                            };
                            return Ok(StartStep::Wait);
                        }
                        if step.answered != Some(newest) {
                            send(&self.link.duty_command_frame(newest, 0, step.duty_b, now));
                            step.answered = Some(newest);
                        }
                    }
                    self.stage = Stage::Stepping(step);
                    return Ok(StartStep::Answer);
                }
                Stage::Ready => return Ok(StartStep::Ready),
                Stage::Running => return Ok(StartStep::Ready),
            }
        }
    }

    /// What the start-up waits for from the drive, for a timeout report.
    pub fn awaiting(&self) -> &'static str {
        match self.stage {
            Stage::Handshake { .. } | Stage::Joining => "a CONFIG",
            Stage::Aligning { .. } | Stage::Holding { .. } => "the alignment",
            Stage::Stepping(_) => "the phase-B step",
            Stage::Ready | Stage::Running => "SAMPLE frames",
        }
    }

    /// Whether the start-up waits for the stack's loops (configured, motor untouched).
    pub fn awaiting_stack(&self) -> bool {
        self.stage == Stage::Joining
    }

    fn align_ms(&self) -> u16 {
        self.link.config().map_or(0, |c| c.align_ms)
    }

    /// §4.5 and §7 step 2: the drive's CONFIG against the scenario and the calibration.
    fn accept_config(&mut self) -> Result<(), Refusal> {
        let Some(c) = self.link.config().copied() else {
            return Ok(());
        };
        tracing::info!(?c, "drive configuration");
        if f64::from(c.sample_rate_hz) != self.settings.sample_hz.round() {
            return Err(Refusal::SampleRate {
                drive_hz: c.sample_rate_hz,
                scenario_hz: self.settings.sample_hz,
            });
        }
        if c.align_ms == 0 && self.settings.calibration.offset_counts.is_none() {
            return Err(Refusal::NoElectricalZero);
        }
        Ok(())
    }

    fn align_deadline(&self, since: &mut Since, now: u64) -> Result<(), Refusal> {
        let align_ms = self.align_ms();
        match since.overdue(&self.link, now, u64::from(align_ms)) {
            Some((waited_ms, by_drive)) => Err(Refusal::Align {
                align_ms,
                waited_ms,
                by_drive,
            }),
            None => Ok(()),
        }
    }

    /// A fault latched during the checks ends the start-up: the drive named it.
    fn fault_check(&self, during: &'static str) -> Result<(), Refusal> {
        let bits = self.link.last_fault_bits;
        if bits != 0 {
            return Err(Refusal::Fault { bits, during });
        }
        Ok(())
    }

    /// §7 step 4: phase A alone at the align current, read at the scale its duty implies.
    fn check_hold(&self, hold: &Hold) -> Result<(), Refusal> {
        let align_a = self
            .link
            .config()
            .map_or(0.0, |c| f64::from(c.align_current_ma) * 1e-3);
        if !holds_phase_a(hold.i_a_a, hold.i_b_a, align_a) {
            return Err(Refusal::HeldCurrent {
                i_a_a: hold.i_a_a,
                i_b_a: hold.i_b_a,
                align_a,
            });
        }
        let expected_a = hold.duty_a * hold.bus_v / self.settings.resistance_ohm;
        let ratio = hold.i_a_a / expected_a;
        // A duty that drives no current cannot hold +I: refused as off scale too.
        let in_scale = expected_a > 0.0 && (CURRENT_SCALE_MIN..=CURRENT_SCALE_MAX).contains(&ratio);
        if !in_scale {
            return Err(Refusal::CurrentScale {
                i_a_a: hold.i_a_a,
                duty_pct: hold.duty_a * 100.0,
                bus_v: hold.bus_v,
                expected_a,
                resistance_ohm: self.settings.resistance_ohm,
                ratio,
            });
        }
        Ok(())
    }

    /// The phase-B step after the first hold, or `None` (said once) when the encoder is too
    /// coarse to see a quarter electrical period.
    fn phase_step(&self, hold: &Hold, now: u64) -> Option<PhaseStep> {
        let quarter = FRAC_PI_2 / self.settings.rotor_teeth;
        let counts = quarter / self.link.rad_per_count();
        if counts.is_nan() || counts < STEP_MIN_COUNTS {
            tracing::warn!(
                counts,
                "a quarter electrical period is under {STEP_MIN_COUNTS} encoder counts: the \
                 phase-B step cannot tell a swapped phase; the run starts unchecked"
            );
            return None;
        }
        // The hold's own duty: the same voltage drives the same current through phase B.
        let duty_b = (hold.duty_a * f64::from(MAX_DUTY))
            .round()
            .clamp(1.0, f64::from(MAX_DUTY)) as i16;
        let config = self.link.config()?;
        let periods = (u64::from(config.align_ms) * u64::from(config.sample_rate_hz) / 1000).max(2);
        Some(PhaseStep {
            since: Since::new(now, &self.link),
            duty_b,
            from: *hold,
            periods: u32::try_from(periods).unwrap_or(u32::MAX),
            first: None,
            answered: None,
            n: 0,
            theta_rad: 0.0,
            i_a_a: 0.0,
            i_b_a: 0.0,
        })
    }

    /// A SAMPLE during the phase-B step: its second half makes the step's figures.
    fn observe_step(&mut self, st: &DriveState) {
        let (Stage::Stepping(step), Some(seq)) = (&mut self.stage, self.link.newest_sample_seq())
        else {
            return;
        };
        if self.link.last_status & (status::ENABLED | status::ALIGNING) != status::ENABLED {
            return;
        }
        let first = *step.first.get_or_insert(seq);
        if seq.wrapping_sub(first) < step.periods / 2 {
            return;
        }
        let n = f64::from(step.n);
        let mean = |m: f64, x: f64| (m * n + x) / (n + 1.0);
        step.theta_rad = mean(step.theta_rad, st.theta_rad);
        step.i_a_a = mean(step.i_a_a, st.i_a_a);
        step.i_b_a = mean(step.i_b_a, st.i_b_a);
        step.n += 1;
    }

    /// The stream starts: samples read so far are stale (the stack was coming up, the rotor
    /// aligning), the next one is k = 0 and its position θ = 0 at the electrical zero (θ₀
    /// from the last hold's current). Returns the ENABLE to send.
    pub fn begin(&mut self, now: u64) -> Frame {
        self.link.restart();
        self.newest = None;
        self.last_rx_ns = now;
        self.stage = Stage::Running;
        self.link.control_frame(Action::Enable, now)
    }

    /// The DISABLE to send on any exit path, once a HELLO went out (§7 step 7): the drive
    /// may have a session with this host, and its outputs may be on (aligning, holding,
    /// running) or about to be. `None` before any HELLO: there is nobody to tell.
    pub fn farewell(&mut self, now: u64) -> Option<Frame> {
        self.hello_sent
            .then(|| self.link.control_frame(Action::Disable, now))
    }

    /// The RESET and ENABLE to send when a reset is requested: the drive clears its
    /// latched faults (and aligns) and takes commands again.
    pub fn reset(&mut self, now: u64) -> [Frame; 2] {
        [
            self.link.control_frame(Action::Reset, now),
            self.link.control_frame(Action::Enable, now),
        ]
    }

    /// A frame from the drive, read at `now`.
    pub fn on_frame(&mut self, bytes: &[u8], now: u64, stats: &mut StatsReport) -> Received {
        match self.link.on_frame(bytes, now) {
            Event::State(st) => {
                if self.stage != Stage::Running {
                    // The start-up reads samples for its checks; none is for the stack, so
                    // none is counted as superseded or timed.
                    self.observe_step(&st);
                    self.newest = Some((st, now));
                    return Received::Sample;
                }
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
            Event::ConfigChanged(c) => Received::ConfigChanged(c),
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
    pub fn plan_frame(&mut self, now: u64) -> Option<&Frame> {
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

fn alignment_name(round: Round) -> &'static str {
    match round {
        Round::First => "its alignment",
        Round::Last => "its second alignment (after the phase-B step)",
    }
}

/// §7 step 4, the phase-B step: phase B carries about the held current and phase A none,
/// and the rotor turned a quarter electrical period towards +θ.
fn judge_phase_step(step: &PhaseStep, rotor_teeth: f64) -> Result<(), Refusal> {
    let held_a = step.from.i_a_a;
    if !holds_phase_a(step.i_b_a, step.i_a_a, held_a) {
        return Err(Refusal::PhaseBCurrent {
            duty_b: step.duty_b,
            i_a_a: step.i_a_a,
            i_b_a: step.i_b_a,
            held_a,
        });
    }
    let expected_rad = FRAC_PI_2 / rotor_teeth;
    let moved_rad = step.theta_rad - step.from.theta_rad;
    let ratio = moved_rad / expected_rad;
    if !(STEP_MIN..=STEP_MAX).contains(&ratio) {
        return Err(Refusal::PhaseStep {
            moved_rad,
            expected_rad,
            ratio,
            i_b_a: step.i_b_a,
        });
    }
    tracing::info!(
        moved_rad,
        ratio,
        i_b_a = step.i_b_a,
        "phase-B step: the rotor turned towards +θ as wired"
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_protocol::units::default_config;
    use stepdrive_drive_protocol::{frame_bytes, status, Message, Sample};

    const PERIOD: u64 = 50_000;

    /// A core that has taken the drive's CONFIG (default, 20 kHz), not yet begun.
    fn configured(samples: u64) -> BridgeCore {
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
            resistance_ohm: 14.8,
            rotor_teeth: 50.0,
        });
        let mut stats = StatsReport::default();
        let config = frame_bytes(0, Message::Config(default_config(20_000.0, 200, 8)));
        assert!(matches!(
            c.on_frame(&config, 0, &mut stats),
            Received::Config(_)
        ));
        c
    }

    fn core(samples: u64) -> BridgeCore {
        let mut c = configured(samples);
        c.begin(0);
        c
    }

    /// A SAMPLE frame of an enabled drive: wire seq `seq` (the drive's first is 100),
    /// reporting command frame `applied` applied.
    fn sample(seq: u32, applied: u32) -> Vec<u8> {
        sample_with(seq, applied, status::ENABLED)
    }

    fn sample_with(seq: u32, applied: u32, status: u16) -> Vec<u8> {
        frame_bytes(seq, Message::Sample(still_sample(applied, status)))
    }

    fn still_sample(applied: u32, status: u16) -> Sample {
        Sample {
            encoder_counts: 0,
            adc_a: 32768,
            adc_b: 32768,
            adc_bus: 2400,
            duty_a: 0,
            duty_b: 0,
            applied_command_seq: applied,
            fault_bits: 0,
            status,
        }
    }

    /// A SAMPLE stamped `at_ns` on the drive's clock.
    fn timed_sample(seq: u32, at_ns: u64, status: u16) -> Vec<u8> {
        let mut b = [0u8; stepdrive_drive_protocol::MAX_FRAME];
        let frame = stepdrive_drive_protocol::Frame {
            seq,
            timestamp_ns: at_ns,
            message: Message::Sample(still_sample(0, status)),
        };
        let n = stepdrive_drive_protocol::encode(&frame, &mut b);
        b[..n].to_vec()
    }

    /// §7 step 4: how long a drive takes to align is read on its own clock (its SAMPLEs'
    /// timestamps); the host's clock only bounds a drive that stops sending. The default
    /// CONFIG announces 300 ms.
    #[test]
    fn the_alignment_is_timed_on_the_drives_clock() {
        const MS: u64 = 1_000_000;
        // Configured, the stack ready: RESET and ALIGN go out at host time 0.
        let aligning = || {
            let mut c = configured(10);
            let mut stats = StatsReport::default();
            // A configured drive streams SAMPLEs, disabled, before it is told to align.
            c.on_frame(&timed_sample(99, 0, 0), 0, &mut stats);
            let mut sent = 0;
            assert_eq!(c.startup(0, true, &mut |_| sent += 1), Ok(StartStep::Wait));
            assert_eq!(sent, 2, "RESET and ALIGN");
            (c, stats)
        };
        let at = |c: &mut BridgeCore, now: u64| c.startup(now, true, &mut |_| {});

        // A host held up for 3 s reads a healthy drive's SAMPLEs late: 300 ms of aligning
        // by their timestamps, accepted (before: refused, "within 3000 ms").
        let (mut c, mut stats) = aligning();
        c.on_frame(
            &timed_sample(100, MS, status::ALIGNING),
            3000 * MS,
            &mut stats,
        );
        assert_eq!(at(&mut c, 3000 * MS), Ok(StartStep::Wait));
        c.on_frame(&timed_sample(101, 301 * MS, 0), 3001 * MS, &mut stats);
        assert_eq!(at(&mut c, 3001 * MS), Ok(StartStep::Wait), "holding");
        assert_eq!(c.awaiting(), "the alignment");

        // Still aligning 1.3 s later by its own clock: refused, naming that clock.
        let (mut c, mut stats) = aligning();
        for (i, t) in [1, 700, 1302].into_iter().enumerate() {
            c.on_frame(
                &timed_sample(100 + i as u32, t * MS, status::ALIGNING),
                t * MS,
                &mut stats,
            );
        }
        match at(&mut c, 1302 * MS) {
            Err(
                e @ Refusal::Align {
                    by_drive: true,
                    waited_ms: 1302,
                    ..
                },
            ) => {
                assert!(e.to_string().contains("by its own timestamps"), "{e}");
            }
            other => panic!("{other:?}"),
        }

        // Silent after the ALIGN: waited for on the host's clock, then refused.
        let (mut c, _) = aligning();
        assert_eq!(at(&mut c, 2000 * MS), Ok(StartStep::Wait));
        match at(&mut c, 5301 * MS) {
            Err(
                e @ Refusal::Align {
                    by_drive: false, ..
                },
            ) => {
                assert!(e.to_string().contains("of the host's clock"), "{e}");
            }
            other => panic!("{other:?}"),
        }
    }

    /// An alignment begun and ended between two readings (a host busy elsewhere for longer
    /// than the alignment: a multi-axis bridge starting another drive) still counts: the
    /// newest SAMPLE no longer says ALIGNING, an earlier one of the batch did. Before, the
    /// bridge waited for an ALIGNING it had missed and refused the drive 1.3 s later.
    #[test]
    fn an_alignment_seen_only_in_a_late_batch_still_counts() {
        const MS: u64 = 1_000_000;
        let mut c = configured(10);
        let mut stats = StatsReport::default();
        c.on_frame(&timed_sample(99, 0, 0), 0, &mut stats);
        assert_eq!(c.startup(0, true, &mut |_| {}), Ok(StartStep::Wait));
        // Read in one go, 400 ms later: aligning, then done and holding still.
        let batch = [(1, status::ALIGNING), (300, status::ALIGNING)]
            .into_iter()
            .chain((301..312).map(|t| (t, 0)));
        for (i, (t, st)) in batch.enumerate() {
            c.on_frame(
                &timed_sample(100 + i as u32, t * MS, st),
                400 * MS,
                &mut stats,
            );
        }
        // Past the alignment to judging its hold (these still samples carry no current in
        // phase A, so it is refused for that), not waiting to see an ALIGNING that is gone.
        match c.startup(400 * MS, true, &mut |_| {}) {
            Err(Refusal::Align { .. }) | Ok(StartStep::Wait) => {
                panic!("still waiting for the alignment it has seen")
            }
            _ => {}
        }
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
            let mut fresh = BridgeCore::new(c.settings);
            let mut stats = StatsReport::default();
            let mut last: Option<u64> = None;
            for (i, (seq, kind, payload)) in frames.into_iter().enumerate() {
                let bytes = stepdrive_drive_protocol::raw_frame(seq, kind % 9, &payload);
                let now = (i as u64 + 1) * PERIOD;
                c.on_frame(&bytes, now, &mut stats);
                // A fresh core in its start-up reads the same frames: refusals, no panic.
                fresh.on_frame(&bytes, now, &mut stats);
                let _ = fresh.startup(now, i % 2 == 0, &mut |_| {});
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
