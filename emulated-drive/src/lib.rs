//! `stepdrive emulate-drive`: a stand-in driver board. The motor model of eq. (1) behind the
//! wire protocol of `docs/drive-protocol.md`, in drive units (encoder counts, ADC counts,
//! duties), with a command watchdog: the drive's logic without sockets or clocks
//! ([`DriveCore`]), run by the stack's runner on its own sample clock ([`node`]), with fault
//! injection for tests as a type of its own ([`inject`]).

pub mod inject;
pub mod node;
pub mod truth;

pub use inject::{AlignFault, FaultInjection, Injector};

use std::net::SocketAddr;
use std::time::Duration;
use stepdrive_drive_protocol::transport::Wire;
use stepdrive_drive_protocol::units::{default_config, volts_for, Scaling};
use stepdrive_drive_protocol::{
    decode, faults, is_newer, status, Action, Command, Config, DecodeError, FaultReport, Frame,
    Message, Plan, Sample, MAX_DUTY, MAX_PLAN_ENTRIES,
};
use stepdrive_plant::sim::PlantSim;
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_runtime::rt::RtOptions;
use stepdrive_runtime::runner::{Runner, Settings};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::DriveCommand;
use stepdrive_shared::Scenario;

/// Counters of what the drive received.
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

/// The drive's logic, without sockets or clocks: frames in, samples out.
pub struct DriveCore {
    pub config: Config,
    scaling: Scaling,
    sim: PlantSim,
    bus_v: f64,
    enabled: bool,
    latched: u16,
    /// Latched bits already sent in a FAULT_REPORT (one report each time new bits latch).
    reported: u16,
    /// A HELLO has been taken: before one, nothing but HELLO is acted on.
    session: bool,
    last_rx_seq: Option<u32>,
    pending: Option<Command>,
    pending_seq: u32,
    /// The PLAN with the newest `answers_sample`, and its frame's seq.
    plan: Option<(Plan, u32)>,
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
    /// ENABLE that starts a run, §7 step 5) and the electrical zero nearest to where the
    /// rotor was then: the truth's k and θ count from them. `run_pending`: such an ENABLE
    /// was taken and that sample has not been sent yet.
    run_start: Option<(u32, f64)>,
    run_pending: bool,
    align_fault: AlignFault,
    n_r: f64,
    period_s: f64,
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
    /// `plan_capacity`: PLAN entries kept (0: PLAN frames are not wanted, and dropped).
    pub fn new(s: &Scenario, watchdog_periods: u16, plan_capacity: u16) -> Self {
        let capacity = plan_capacity.min(MAX_PLAN_ENTRIES as u16);
        let config = default_config(s.rates.current_loop_hz, watchdog_periods, capacity);
        let align_duty = align_duty(s, config.align_current_ma);
        Self {
            scaling: Scaling::new(&config),
            config,
            sim: PlantSim::new(s),
            bus_v: s.drive.bus_voltage_v,
            enabled: false,
            latched: 0,
            reported: 0,
            session: false,
            last_rx_seq: None,
            pending: None,
            pending_seq: 0,
            plan: None,
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
            align_fault: AlignFault::None,
            n_r: s.motor.n_r(),
            period_s: s.sample_period_s(),
            counters: DriveCounters::default(),
        }
    }

    /// The rotor's true state at the sample about to be sent with wire seq `seq`, once a
    /// run has started.
    pub fn truth(&self, seq: u32) -> Option<truth::TruthRow> {
        let (first, zero) = self.run_start?;
        let k = u64::from(seq.wrapping_sub(first));
        let x = self.sim.motor_state();
        Some(truth::TruthRow {
            k,
            t_s: k as f64 * self.period_s,
            theta_rad: x[0] - zero,
            omega_rad_s: x[1],
            i_a_a: x[2],
            i_b_a: x[3],
        })
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
    fn live(&self) -> bool {
        let energized =
            self.outputs_on() || (self.latched == 0 && (self.aligning > 0 || self.holding));
        self.session && energized && self.since_host < u32::from(self.config.watchdog_periods)
    }

    pub fn outputs_on(&self) -> bool {
        self.enabled && self.latched == 0
    }

    /// Its ALIGN: phase A at `current_ma` for `ms` (0: it does not align, as a drive with an
    /// absolute encoder may not), announced in CONFIG.
    pub fn set_alignment(&mut self, s: &Scenario, current_ma: u16, ms: u16) {
        self.config.align_current_ma = current_ma;
        self.config.align_ms = ms;
        self.align_duty = align_duty(s, current_ma);
    }

    /// Breaks its alignment as `fault` says (fault injection).
    pub fn set_align_fault(&mut self, fault: AlignFault) {
        self.align_fault = fault;
    }

    /// The seq a CONFIG or FAULT_REPORT carries: the last SAMPLE's (0 before the first).
    pub fn report_seq(&self) -> u32 {
        self.tx_seq.wrapping_sub(1)
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
        self.plan = None;
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

    /// Handles one received datagram; `from_host`: it came from the session's host's
    /// address (UDP), or there is no session yet. From any other address only a HELLO is
    /// read, and only while the session is not live.
    pub fn on_frame_from(&mut self, bytes: &[u8], from_host: bool) -> Option<Reply> {
        let frame = match decode(bytes) {
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
                if p.entries().iter().flatten().any(|&d| d == i16::MIN) {
                    self.latched |= faults::BAD_COMMAND;
                } else if p.count > self.config.plan_capacity {
                    // More than it announced it keeps: malformed for this drive.
                    self.counters.bad_frames += 1;
                } else if self
                    .plan
                    .is_none_or(|(old, _)| !is_newer(old.answers_sample, Some(p.answers_sample)))
                {
                    // Newer, or equal (a later frame for the same base replaces it).
                    self.plan = Some((p, frame.seq));
                }
                None
            }
            _ => None,
        }
    }

    /// The PLAN entry for the period starting at SAMPLE `sample_seq`, with its frame seq.
    fn planned_duty(&self, sample_seq: u32) -> Option<((i16, i16), u32)> {
        let (p, seq) = self.plan.as_ref()?;
        // Entry j is for the period starting at answers_sample + 2 + j.
        let j = sample_seq.wrapping_sub(p.answers_sample).wrapping_sub(2);
        let [a, b] = *p.entries().get(usize::try_from(j).ok()?)?;
        Some(((a, b), *seq))
    }

    /// Latches `bits` (e.g. an injected over-current).
    pub fn trip(&mut self, bits: u16) {
        self.latched |= bits;
    }

    /// The sample at the current instant, as a frame.
    pub fn sample_frame(&mut self, now_ns: u64) -> Frame {
        let starts_run = (self.outputs_on() && self.aligning == 0) || self.latched != 0;
        if self.run_pending && starts_run {
            // The plant's load profile and the truth count from the run's first SAMPLE.
            self.run_pending = false;
            self.sim.restart_load_clock();
            let pitch = std::f64::consts::TAU / self.n_r;
            let zero = (self.sim.motor_state()[0] / pitch).round() * pitch;
            self.run_start = Some((self.tx_seq, zero));
        }
        let st = self.sim.state(false);
        let counts = self.scaling.counts(st.theta_rad);
        // With phase A's leads swapped the shunt, on the drive's side of them, reads the
        // current the drive drives, the reverse of the winding's.
        let i_a = match self.align_fault {
            AlignFault::SwappedLeads => -st.i_a_a,
            _ => st.i_a_a,
        };
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
                encoder_counts: counts as i32,
                adc_a: self.scaling.adc(i_a),
                adc_b: self.scaling.adc(st.i_b_a),
                adc_bus: self.scaling.bus_adc(self.bus_v),
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

    /// Decides the duties for the period starting now and integrates the motor over it.
    /// The command must answer the previous sample (one period of compute delay); without
    /// one, the previous duties are held; after the watchdog's periods without one, the
    /// outputs go off and a fault latches. Returns a fault report if one just latched.
    pub fn run_period(&mut self, sample_seq: u32) -> Option<FaultReport> {
        self.planned = false;
        self.since_host = self.since_host.saturating_add(1);
        let wanted = sample_seq.wrapping_sub(1);
        if self.aligning > 0 && self.latched == 0 {
            if self.align_fault != AlignFault::Stuck {
                self.aligning -= 1;
            }
            self.pending = None;
            return self.apply(self.align_duty_now(), 0, sample_seq);
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
            return self.apply(self.align_duty_now(), 0, sample_seq);
        }
        if !self.outputs_on() {
            self.held_duty = (0, 0);
            self.held_seq = 0;
        }
        let (duty, seq) = (self.held_duty, self.held_seq);
        self.apply(duty, seq, sample_seq)
    }

    fn align_duty_now(&self) -> (i16, i16) {
        match self.align_fault {
            AlignFault::Reversed => (-self.align_duty, 0),
            _ => (self.align_duty, 0),
        }
    }

    /// Applies `duty` (reported in the next SAMPLE with `seq`) over the period and
    /// integrates the motor; a fault report if bits latched since the last one.
    fn apply(&mut self, duty: (i16, i16), seq: u32, sample_seq: u32) -> Option<FaultReport> {
        let duty = if self.latched == 0 { duty } else { (0, 0) };
        self.held_duty = duty;
        self.held_seq = if self.latched == 0 { seq } else { 0 };
        self.ended = EndedPeriod {
            duty,
            seq: self.held_seq,
            held: self.since_command > 0 && self.outputs_on(),
            planned: self.planned,
        };
        let v_a = match self.align_fault {
            AlignFault::SwappedLeads => -volts_for(duty.0, self.bus_v),
            _ => volts_for(duty.0, self.bus_v),
        };
        let v = DriveCommand {
            v_a_v: v_a,
            v_b_v: volts_for(duty.1, self.bus_v),
            ..Default::default()
        };
        self.sim.advance(Some(&v));
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

#[derive(Debug, Clone)]
pub struct EmulatorOptions {
    /// UDP address to listen on, one per axis of the scenario (a multi-axis scenario's
    /// drives are one process, a drive per address); ignored when `serial` is given.
    pub listen: Vec<SocketAddr>,
    /// The axis whose drive the fault injection acts on (the others run clean).
    pub inject_axis: usize,
    /// Serial line (UART or pseudo-terminal) to use instead of UDP.
    pub serial: Option<std::path::PathBuf>,
    pub scenario: Scenario,
    pub wait: WaitStrategy,
    pub rt: RtOptions,
    pub watchdog_periods: u16,
    /// PLAN entries the drive keeps (announced in CONFIG; 0: none).
    pub plan_capacity: u16,
    /// ALIGN current, mA, and time, ms (0 ms: no alignment).
    pub align_ma: u16,
    pub align_ms: u16,
    pub inject: FaultInjection,
    /// Stop after this long (None: until SIGTERM/SIGINT).
    pub duration: Option<Duration>,
    /// Write the rotor's true state of every sample of a run to this CSV file.
    pub truth: Option<std::path::PathBuf>,
}

#[derive(Debug, thiserror::Error)]
pub enum EmulatorError {
    #[error("cannot open the drive's {what}")]
    Open {
        what: String,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Rt(#[from] stepdrive_runtime::rt::RtError),
    #[error(transparent)]
    Run(stepdrive_runtime::RunError),
    #[error("the scenario has {axes} axes and {given} drive addresses were given (--listen A,B,...: one per axis{serial})")]
    Axes {
        axes: usize,
        given: usize,
        serial: &'static str,
    },
    #[error("cannot write the truth file {path}")]
    Truth {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Phase A's duty for `current_ma` in the steady state (R·I), within the bus.
fn align_duty(s: &Scenario, current_ma: u16) -> i16 {
    let v = s.motor.resistance_ohm * f64::from(current_ma) * 1e-3;
    (v / s.drive.bus_voltage_v * f64::from(MAX_DUTY))
        .round()
        .clamp(0.0, f64::from(MAX_DUTY)) as i16
}

pub fn run_emulator(o: &EmulatorOptions) -> Result<(), EmulatorError> {
    let axes = o.scenario.axis_count();
    if axes > 1 || o.listen.len() != 1 {
        return run_emulators(o);
    }
    let wire = match &o.serial {
        Some(path) => Wire::open_serial(path).map_err(|source| EmulatorError::Open {
            what: format!("serial line {}", path.display()),
            source,
        })?,
        None => Wire::bind_udp(o.listen[0]).map_err(|source| EmulatorError::Open {
            what: format!("UDP socket on {}", o.listen[0]),
            source,
        })?,
    };
    let truth = match &o.truth {
        Some(p) => Some(
            truth::TruthWriter::create(p).map_err(|source| EmulatorError::Truth {
                path: p.clone(),
                source,
            })?,
        ),
        None => None,
    };
    o.rt.apply()?;
    let mut core = DriveCore::new(&o.scenario, o.watchdog_periods, o.plan_capacity);
    core.set_alignment(&o.scenario, o.align_ma, o.align_ms);
    core.set_align_fault(o.inject.align);
    tracing::info!(listen = %o.listen[0], serial = ?o.serial, "emulated drive up; waiting for HELLO");
    let node = node::DriveNode::new(&o.scenario, core, Injector::new(o.inject.clone()), truth)
        .lasting(o.duration);
    run_drive(node, wire, o.wait)
}

/// A drive on the runner until it is switched off.
fn run_drive<N: stepdrive_runtime::Node>(
    node: N,
    ports: N::Ports,
    wait: WaitStrategy,
) -> Result<(), EmulatorError> {
    // A drive has no peer to time out: it waits for a host as long as it runs.
    let forever = Duration::from_secs(1_000_000_000);
    let settings = Settings {
        wait,
        startup_timeout: forever,
        peer_timeout: forever,
        account_host_holds: false,
        linger: Duration::ZERO,
        report_end: true,
    };
    match Runner::new(node, ports, settings, None).run() {
        // SIGINT/SIGTERM is how a drive is switched off.
        Ok(_) | Err(RunError::Terminated) => Ok(()),
        Err(e) => Err(EmulatorError::Run(e)),
    }
}

/// A multi-axis scenario's drives in one process: a drive per axis, each its own UDP
/// address, session, clock and motor (its axis's scenario), stepped on one deadline grid
/// (`stepdrive_runtime::lanes`); the truth is axis 0's, the fault injection
/// `inject_axis`'s.
fn run_emulators(o: &EmulatorOptions) -> Result<(), EmulatorError> {
    let axes = o.scenario.axis_count();
    if o.listen.len() != axes || o.serial.is_some() {
        return Err(EmulatorError::Axes {
            axes,
            given: if o.serial.is_some() {
                0
            } else {
                o.listen.len()
            },
            serial: if o.serial.is_some() {
                "; a serial line is one drive"
            } else {
                ""
            },
        });
    }
    o.rt.apply()?;
    let (mut nodes, mut wires) = (Vec::with_capacity(axes), Vec::with_capacity(axes));
    for (axis, &listen) in o.listen.iter().enumerate() {
        let Some(s) = o.scenario.for_axis(axis) else {
            unreachable!("axis {axis} is below the axis count")
        };
        wires.push(
            Wire::bind_udp(listen).map_err(|source| EmulatorError::Open {
                what: format!("UDP socket on {listen} (axis {axis})"),
                source,
            })?,
        );
        let truth = match (&o.truth, axis) {
            (Some(p), 0) => {
                Some(
                    truth::TruthWriter::create(p).map_err(|source| EmulatorError::Truth {
                        path: p.clone(),
                        source,
                    })?,
                )
            }
            _ => None,
        };
        let mut core = DriveCore::new(s, o.watchdog_periods, o.plan_capacity);
        core.set_alignment(s, o.align_ma, o.align_ms);
        let inject = if axis == o.inject_axis {
            core.set_align_fault(o.inject.align);
            o.inject.clone()
        } else {
            FaultInjection::default()
        };
        nodes.push(node::DriveNode::new(s, core, Injector::new(inject), truth).lasting(o.duration));
    }
    tracing::info!(listen = ?o.listen, "emulated drives up, one per axis; waiting for HELLO");
    run_drive(
        stepdrive_runtime::lanes::Lanes::new(nodes, false),
        wires,
        o.wait,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_protocol::frame_bytes;

    /// A drive a host has said HELLO to (frame seq 0).
    fn in_session(mut d: DriveCore) -> DriveCore {
        assert!(matches!(
            d.on_frame(&frame_bytes(0, Message::Hello)),
            Some(Reply::Config(_))
        ));
        d
    }

    fn cmd(answers: u32, d: i16) -> Message {
        Message::Command(Command {
            answers_sample: answers,
            duty_a: d,
            duty_b: d,
        })
    }

    #[test]
    fn corrupt_stale_and_late_frames_are_never_applied() {
        let mut d = DriveCore::new(&Scenario::default(), 20, 8);
        assert!(matches!(
            d.on_frame(&frame_bytes(1, Message::Hello)),
            Some(Reply::Config(_))
        ));
        d.on_frame(&frame_bytes(2, Message::Control(Action::Enable)));
        let _ = d.sample_frame(0);
        d.run_period(0);
        // A corrupted command: counted, not applied.
        let mut bad = frame_bytes(3, cmd(0, 1000));
        bad[20] ^= 1;
        assert!(d.on_frame(&bad).is_none());
        assert_eq!(d.counters.crc_errors, 1);
        d.run_period(1);
        assert_eq!(d.counters.commands_applied, 0);
        // A good one for sample 1, applied in the period after sample 2.
        d.on_frame(&frame_bytes(4, cmd(1, 2000)));
        // The same frame again (duplicate) and an older one (out of order): dropped.
        d.on_frame(&frame_bytes(4, cmd(1, 9000)));
        d.on_frame(&frame_bytes(3, cmd(1, 9000)));
        assert_eq!(d.counters.stale_frames, 2);
        d.run_period(2);
        assert_eq!(d.counters.commands_applied, 1);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!((s.duty_a, s.applied_command_seq), (2000, 4));
        // A command that answers an old sample arrives late: held, not applied.
        d.on_frame(&frame_bytes(5, cmd(1, 3000)));
        d.run_period(3);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!(s.duty_a, 2000);
        assert_ne!(s.status & status::COMMAND_HELD, 0);
    }

    fn plan(answers: u32, duties: &[i16]) -> Message {
        let mut d = [[0i16; 2]; MAX_PLAN_ENTRIES];
        for (slot, &x) in d.iter_mut().zip(duties) {
            *slot = [x, -x];
        }
        Message::Plan(Plan {
            answers_sample: answers,
            count: duties.len() as u16,
            duties: d,
        })
    }

    fn applied(d: &mut DriveCore) -> (i16, u32, u16) {
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        (s.duty_a, s.applied_command_seq, s.status)
    }

    /// A period without its COMMAND gets the freshest PLAN's entry for that very period
    /// (flagged, and still counted for the watchdog); past the plan the duty is held; an
    /// older PLAN never replaces a newer one; a PLAN longer than the announced capacity is
    /// dropped; one with a −32768 duty latches BAD_COMMAND like such a COMMAND.
    #[test]
    fn missing_commands_take_the_freshest_plan_entry_for_their_period() {
        let mut d = in_session(DriveCore::new(&Scenario::default(), 20, 8));
        assert_eq!(d.config.plan_capacity, 8);
        d.on_frame(&frame_bytes(1, Message::Control(Action::Enable)));
        d.run_period(0);
        // Sample 0 answered in time: applied over the period starting at sample 1. Its plan
        // covers the periods starting at samples 2, 3 and 4.
        d.on_frame(&frame_bytes(2, cmd(0, 1000)));
        d.on_frame(&frame_bytes(3, plan(0, &[2000, 3000, 4000])));
        d.run_period(1);
        assert_eq!(applied(&mut d), (1000, 2, status::ENABLED));
        let planned = status::ENABLED | status::COMMAND_HELD | status::COMMAND_PLANNED;
        d.run_period(2);
        assert_eq!(applied(&mut d), (2000, 3, planned));
        // A newer plan (continuing a command that never arrived) takes over; an older one
        // offered after it does not.
        d.on_frame(&frame_bytes(4, plan(1, &[5000, 6000])));
        d.on_frame(&frame_bytes(5, plan(0, &[7000, 7000, 7000])));
        d.run_period(3);
        assert_eq!(applied(&mut d), (5000, 4, planned));
        d.run_period(4);
        assert_eq!(applied(&mut d), (6000, 4, planned));
        // Past the plan: held, not planned.
        d.run_period(5);
        assert_eq!(
            applied(&mut d),
            (6000, 4, status::ENABLED | status::COMMAND_HELD)
        );
        // Held: period 0 (nothing can answer the sample before the first) and 2 to 5.
        assert_eq!(
            (d.counters.periods_held, d.counters.periods_planned),
            (5, 3)
        );
        // Longer than the capacity of 8: dropped, counted.
        d.on_frame(&frame_bytes(6, plan(5, &[1; 9])));
        assert_eq!(d.counters.bad_frames, 1);
        // A −32768 duty: rejected, fault latched, outputs off.
        d.on_frame(&frame_bytes(7, plan(6, &[1, i16::MIN])));
        d.run_period(6);
        assert_ne!(d.latched_faults() & faults::BAD_COMMAND, 0);
        assert_eq!(applied(&mut d).0, 0);
    }

    #[test]
    fn watchdog_turns_outputs_off_and_latches_until_reset() {
        let mut d = in_session(DriveCore::new(&Scenario::default(), 20, 8));
        d.on_frame(&frame_bytes(1, Message::Control(Action::Enable)));
        d.run_period(0);
        d.on_frame(&frame_bytes(2, cmd(0, 5000)));
        d.run_period(1);
        let mut report = None;
        for k in 2..=21 {
            report = report.or(d.run_period(k));
        }
        let r = report.expect("watchdog fault reported");
        assert_eq!(r.fault_bits & faults::WATCHDOG, faults::WATCHDOG);
        assert_eq!(r.at_sample, 21);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!((s.duty_a, s.duty_b), (0, 0));
        // A good command does not clear the latch; RESET + ENABLE does.
        d.on_frame(&frame_bytes(3, cmd(21, 5000)));
        d.run_period(22);
        assert!(!d.outputs_on());
        d.on_frame(&frame_bytes(4, Message::Control(Action::Reset)));
        assert!(!d.outputs_on(), "off until ENABLE");
        d.on_frame(&frame_bytes(5, Message::Control(Action::Enable)));
        d.on_frame(&frame_bytes(6, cmd(22, 5000)));
        d.run_period(23);
        assert!(d.outputs_on());
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!(s.duty_a, 5000);
    }

    /// A second host (a new run) says HELLO with its own frame numbers, lower than the
    /// first host's last: it gets its CONFIG and a new session, not a "stale frame".
    #[test]
    fn a_hello_starts_a_new_session() {
        let mut d = DriveCore::new(&Scenario::default(), 20, 8);
        assert!(matches!(
            d.on_frame(&frame_bytes(1, Message::Hello)),
            Some(Reply::Config(_))
        ));
        d.on_frame(&frame_bytes(2, Message::Control(Action::Enable)));
        for seq in 3..500 {
            d.on_frame(&frame_bytes(seq, cmd(seq, 100)));
        }
        assert!(d.outputs_on());
        // The next host.
        assert!(matches!(
            d.on_frame(&frame_bytes(1, Message::Hello)),
            Some(Reply::Config(_))
        ));
        assert!(!d.outputs_on(), "off until the new host enables them");
        d.on_frame(&frame_bytes(2, Message::Control(Action::Reset)));
        d.on_frame(&frame_bytes(3, Message::Control(Action::Enable)));
        assert!(d.outputs_on());
        assert_eq!(d.counters.stale_frames, 0);
    }

    /// ALIGN brings the rotor to an electrical zero, physically (phase A at the align
    /// current for align_ms, ALIGNING set meanwhile), whatever a previous session left it
    /// at; it rests there within the load's offset (0.01 N·m / 25 N·m/rad = 4e-4 rad).
    #[test]
    fn align_leaves_the_rotor_at_an_electrical_zero() {
        let mut d = in_session(DriveCore::new(&Scenario::default(), 2000, 8));
        d.on_frame(&frame_bytes(1, Message::Control(Action::Enable)));
        for k in 0..400u32 {
            d.on_frame(&frame_bytes(2 + k, cmd(k.wrapping_sub(1), 12_000)));
            d.run_period(k);
        }
        let theta = |d: &mut DriveCore| {
            let Message::Sample(s) = d.sample_frame(0).message else {
                panic!()
            };
            f64::from(s.encoder_counts) / f64::from(1u32 << 20) * std::f64::consts::TAU
        };
        let pitch = std::f64::consts::TAU / 50.0;
        let before = theta(&mut d);
        assert!(
            (before / pitch - (before / pitch).round()).abs() > 1e-3,
            "moved off a zero"
        );
        d.on_frame(&frame_bytes(500, Message::Control(Action::Align)));
        let periods = 300 * 20_000 / 1000;
        for k in 0..periods - 1 {
            d.run_period(400 + k);
            let Message::Sample(s) = d.sample_frame(0).message else {
                panic!()
            };
            assert_ne!(s.status & status::ALIGNING, 0, "aligning at {k}");
            assert_eq!((s.status & status::ENABLED, s.duty_b), (0, 0));
        }
        d.run_period(400 + periods - 1);
        let after = theta(&mut d);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!(s.status & status::ALIGNING, 0, "done");
        let off = (after / pitch - (after / pitch).round()) * pitch;
        assert!(off.abs() < 1e-3, "{off} rad from the nearest zero");
        assert!((after - before).abs() <= pitch / 2.0 + 1e-3);
    }

    /// Arbitrary frames, valid and corrupted with a matching CRC, at a drive between its
    /// periods: it never panics, and its outputs stay within the bus.
    #[test]
    fn arbitrary_frames_never_break_the_drive() {
        use proptest::prelude::*;
        let frame = (
            any::<u32>(),
            any::<u8>(),
            proptest::collection::vec(any::<u8>(), 0..64),
        );
        proptest!(|(frames in proptest::collection::vec(frame, 1..100))| {
            let mut d = DriveCore::new(&Scenario::default(), 20, 8);
            for (k, (seq, kind, payload)) in frames.into_iter().enumerate() {
                let bytes = stepdrive_drive_protocol::raw_frame(seq, kind % 9, &payload);
                d.on_frame(&bytes);
                d.run_period(k as u32);
                let Message::Sample(s) = d.sample_frame(0).message else {
                    panic!("a sample frame")
                };
                prop_assert!(s.duty_a != i16::MIN && s.duty_b != i16::MIN);
            }
        });
    }
}
