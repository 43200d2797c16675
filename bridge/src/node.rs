//! The bridge as a node of the runner: the plant's place in the stack taken by a drive
//! speaking `docs/drive-protocol.md` over UDP or a serial line. The drive's sample clock
//! paces it: a cycle runs when a SAMPLE arrives (due from the drive's own timestamps);
//! while it waits it forwards the current loop's commands and plans, and watches for
//! silence. The rules are [`BridgeCore`]'s; this module moves bytes.

use crate::core::{BridgeCore, CoreSettings, Received, Refusal, StartStep};
use crate::link::EncoderCalibration;
use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;
use stepdrive_drive_protocol::transport::{Wire, WireError};
use stepdrive_drive_protocol::{encode, Frame, MAX_FRAME, VERSION};
use stepdrive_runtime::node::{Cx, Flow, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::poll::termination_requested;
use stepdrive_runtime::port::{Notify, PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{DriveCommand, DrivePlan, DriveState, ResetRequest};
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

/// Where the drive is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DriveAddr {
    Udp(SocketAddr),
    /// A serial line: a UART (`/dev/ttyACM0`) or a pseudo-terminal.
    Serial(PathBuf),
}

impl std::fmt::Display for DriveAddr {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DriveAddr::Udp(a) => write!(f, "udp://{a}"),
            DriveAddr::Serial(p) => write!(f, "serial:{}", p.display()),
        }
    }
}

/// A drive address that does not name a drive.
#[derive(Debug, thiserror::Error)]
#[error("`{text}` is not a drive address (host:port or udp://host:port for UDP, a device path or serial:PATH for a serial line)")]
pub struct BadDriveAddr {
    pub text: String,
    #[source]
    pub source: Option<std::io::Error>,
}

impl std::str::FromStr for DriveAddr {
    type Err = BadDriveAddr;

    /// `udp://host:port`, `host:port` (a name is resolved), `serial:PATH`, or a path.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if let Some(path) = text.strip_prefix("serial:") {
            return Ok(DriveAddr::Serial(PathBuf::from(path)));
        }
        if text.starts_with('/') {
            return Ok(DriveAddr::Serial(PathBuf::from(text)));
        }
        let host_port = text.strip_prefix("udp://").unwrap_or(text);
        let bad = |source| BadDriveAddr {
            text: text.to_string(),
            source,
        };
        let mut addrs = host_port.to_socket_addrs().map_err(|e| bad(Some(e)))?;
        addrs.next().map(DriveAddr::Udp).ok_or_else(|| bad(None))
    }
}

/// The drives a drive-address text names, one per axis in axis order: a comma-separated
/// list of UDP addresses (`127.0.0.1:7700,127.0.0.1:7701`); a serial line's path is one
/// drive, whatever it holds.
pub fn drive_addresses(text: &str) -> Vec<&str> {
    if text.starts_with("serial:") || text.starts_with('/') {
        return vec![text];
    }
    text.split(',').map(str::trim).collect()
}

/// What can go wrong between the bridge and its drive, naming the drive.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("cannot open the drive at {drive}")]
    Open {
        drive: DriveAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("the drive at {drive} is gone")]
    Gone {
        drive: DriveAddr,
        #[source]
        source: WireError,
    },
    #[error(
        "a drive applies each COMMAND one period after its sample (docs/drive-protocol.md); the \
         scenario's rates.compute_delay_periods is {0}, so the current loop would be designed \
         for another drive"
    )]
    ComputeDelay(u32),
    #[error(
        "the encoder offset {0} is not a reading of a drive's 32-bit encoder count \
         (−2147483648 … 2147483647, docs/drive-protocol.md §6)"
    )]
    EncoderOffset(i64),
    /// The drive failed a step of the start-up (§7) or broke a rule of the session.
    #[error("the drive at {drive} {reason}")]
    Refused { drive: DriveAddr, reason: Refusal },
}

/// The bridge's settings beside the scenario.
#[derive(Debug, Clone)]
pub struct BridgeSettings {
    pub drive: DriveAddr,
    /// State subscribers to wait for before enabling the drive (the loops, a monitor).
    pub wait_subscribers: usize,
    /// Wait for a position loop (a setpoint publisher) too; false for a tool that drives
    /// the motor alone.
    pub wait_position_loop: bool,
    pub silence_periods: u32,
    pub plan_every: u32,
    pub observer_hz: f64,
    pub calibration: EncoderCalibration,
    /// Without real-time priorities (`sleep` wait) nothing orders the current loop's answer
    /// before the bridge's next wake-up: look for it every 20 µs while it is pending.
    pub look_for_answers: bool,
}

/// What the bridge reads and writes: the drive's wire and the stack's ports.
pub struct BridgePorts {
    pub wire: Wire,
    pub states: Box<dyn Publish<DriveState>>,
    pub state_ready: Box<dyn Notify>,
    pub commands: Box<dyn Subscribe<DriveCommand>>,
    pub plans: Box<dyn Subscribe<DrivePlan>>,
    pub resets: Box<dyn Subscribe<ResetRequest>>,
    pub presence: Box<dyn Presence>,
}

impl BridgePorts {
    /// Opens the drive's wire and the stack's ports.
    pub fn open(f: &mut impl PortFactory, drive: &DriveAddr) -> Result<Self, RunError> {
        let wire = match drive {
            DriveAddr::Udp(addr) => Wire::connect_udp(*addr),
            DriveAddr::Serial(path) => Wire::open_serial(path),
        }
        .map_err(|source| {
            RunError::node(
                Role::Bridge,
                BridgeError::Open {
                    drive: drive.clone(),
                    source,
                },
            )
        })?;
        Ok(Self {
            wire,
            commands: f.subscriber(LOOP_BUFFER)?,
            plans: f.subscriber(LOOP_BUFFER)?,
            resets: f.subscriber(LOOP_BUFFER)?,
            state_ready: f.notifier()?,
            states: f.publisher()?,
            presence: f.presence()?,
        })
    }
}

/// How often a bridge without real-time priority looks for the current loop's answer.
const ANSWER_CHECK_NS: u64 = 20_000;
/// A drive whose host answers "port unreachable" this long is not coming (it is not
/// started, or the address is wrong): fail instead of waiting out the handshake.
const REFUSED_FOR_NS: u64 = 3_000_000_000;
/// The longest the bridge polls its socket past a frame's due time before it blocks.
const MAX_SPIN_PAST_DUE_NS: u64 = 100_000;
/// While the start-up answers the drive itself (the phase-B step), the longest it blocks on
/// the wire between looks at the time and the termination flag.
const STEP_WAIT_NS: u64 = 1_000_000;
/// After a handshake with nothing heard, how long the bridge listens for the drive's frames
/// from another port (§2), ms.
const ELSEWHERE_LISTEN_MS: i32 = 100;

pub struct BridgeNode {
    core: BridgeCore,
    settings: BridgeSettings,
    sample_hz: f64,
    period_ns: u64,
    running: bool,
    refused_since_ns: Option<u64>,
    /// A sample taken by `poll` for the coming cycle.
    taken: Option<(DriveState, u64)>,
    rx: [u8; 2048],
    /// A bridge of several drives: its drive has aligned (and stepped phase B) and waits
    /// for the others' before it is enabled ([`StartGate`]).
    gate: Option<StartGate>,
    prepared: bool,
}

/// The drives of a multi-axis bridge are enabled together: each lane's start-up (HELLO,
/// CONFIG, ALIGN, the phase-B step) runs on its own, and a lane ready before the others
/// waits, its drive idle, until every lane is. Enabled one by one instead, the first
/// drive streamed through the second's 300 ms alignment while its lane took no samples:
/// the stack lost axis 0's first 0.3 s and the monitor called the run unobserved.
#[derive(Clone, Debug)]
pub struct StartGate {
    ready: std::rc::Rc<std::cell::Cell<usize>>,
    lanes: usize,
}

impl StartGate {
    /// A gate for `lanes` drives.
    pub fn new(lanes: usize) -> Self {
        Self {
            ready: std::rc::Rc::default(),
            lanes,
        }
    }

    fn arrive(&self) {
        self.ready.set(self.ready.get() + 1);
    }

    fn open(&self) -> bool {
        self.ready.get() >= self.lanes
    }
}

impl BridgeNode {
    /// §7 up to ENABLE: the handshake, the alignment and the checks. True once the drive
    /// may be enabled. Between looks it returns to the runner (false), except during the
    /// phase-B step, when the drive's armed watchdog needs every SAMPLE answered as it
    /// comes.
    fn prepare(&mut self, ports: &mut BridgePorts, cx: &mut Cx) -> Result<bool, RunError> {
        loop {
            self.read_frames(ports, cx)?;
            // Asked only while it matters: the phase-B step answers within a period.
            let p = &ports.presence;
            let stack_ready = self.core.awaiting_stack()
                && p.publishers(Topic::Command) >= 1
                && (p.publishers(Topic::Setpoint) >= 1 || !self.settings.wait_position_loop)
                && p.subscribers(Topic::State) >= self.settings.wait_subscribers;
            let now = cx.now();
            let wire = &mut ports.wire;
            let step = self
                .core
                .startup(now, stack_ready, &mut |f| send_on(wire, f));
            match step {
                Err(reason) => return Err(self.refused(ports, reason, now)),
                Ok(StartStep::Wait) => return Ok(false),
                Ok(StartStep::Answer) => {
                    if termination_requested() {
                        return Ok(false);
                    }
                    wait_readable(ports.wire.raw_fd(), STEP_WAIT_NS);
                }
                Ok(StartStep::Ready) => return Ok(true),
            }
        }
    }

    pub fn new(s: &Scenario, settings: BridgeSettings) -> Result<Self, RunError> {
        if s.rates.compute_delay_periods != 1 {
            return Err(RunError::node(
                Role::Bridge,
                BridgeError::ComputeDelay(s.rates.compute_delay_periods),
            ));
        }
        if let Some(offset) = settings.calibration.offset_counts {
            if i32::try_from(offset).is_err() {
                return Err(RunError::node(
                    Role::Bridge,
                    BridgeError::EncoderOffset(offset),
                ));
            }
        }
        Ok(Self {
            core: BridgeCore::new(CoreSettings {
                sample_hz: s.rates.current_loop_hz,
                samples: s.sample_count(),
                silence_periods: settings.silence_periods,
                plan_every: settings.plan_every,
                observer_hz: settings.observer_hz,
                calibration: settings.calibration,
                resistance_ohm: s.motor.resistance_ohm,
                rotor_teeth: s.motor.n_r(),
            }),
            sample_hz: s.rates.current_loop_hz,
            period_ns: s.sample_period_ns(),
            settings,
            running: false,
            refused_since_ns: None,
            taken: None,
            rx: [0; 2048],
            gate: None,
            prepared: false,
        })
    }

    /// One drive of several, enabled with the others through `gate`.
    pub fn with_start_gate(mut self, gate: StartGate) -> Self {
        self.gate = Some(gate);
        self
    }

    pub fn core(&self) -> &BridgeCore {
        &self.core
    }

    fn gone(&self, source: WireError) -> RunError {
        RunError::node(
            Role::Bridge,
            BridgeError::Gone {
                drive: self.settings.drive.clone(),
                source,
            },
        )
    }

    /// The drive refused for `reason`, with what the wire can add to it: a handshake that
    /// heard nothing listens once for the drive's frames from another port (§2).
    fn refused(&mut self, ports: &mut BridgePorts, mut reason: Refusal, now: u64) -> RunError {
        if let (Refusal::Handshake(report), DriveAddr::Udp(addr)) =
            (&mut reason, &self.settings.drive)
        {
            if report.frames == 0 {
                let mut buf = [0u8; MAX_FRAME];
                let n = encode(&self.core.hello(now), &mut buf);
                report.elsewhere =
                    ports
                        .wire
                        .listen_elsewhere(*addr, &buf[..n], ELSEWHERE_LISTEN_MS);
            }
        }
        RunError::node(
            Role::Bridge,
            BridgeError::Refused {
                drive: self.settings.drive.clone(),
                reason,
            },
        )
    }

    /// Reads every frame queued. A refusal (nothing listens yet) is tolerated during the
    /// handshake for a while, since the drive may be starting; a hang-up never is. A CONFIG
    /// that cannot be used, or one that differs from the handshake's, ends the session.
    fn read_frames(&mut self, ports: &mut BridgePorts, cx: &mut Cx) -> Result<(), RunError> {
        loop {
            match ports.wire.recv(&mut self.rx, 0) {
                Ok(Some((len, _))) => {
                    self.refused_since_ns = None;
                    let now = cx.now();
                    let reason = match self.core.on_frame(&self.rx[..len], now, cx.stats) {
                        Received::BadConfig(e) => Refusal::Config(e),
                        Received::ConfigChanged(c) => Refusal::ConfigChanged(c),
                        _ => continue,
                    };
                    return Err(self.refused(ports, reason, now));
                }
                Ok(None) => return Ok(()),
                Err(WireError::Refused) if !self.core.configured() => {
                    let now = cx.now();
                    self.core.refused(now);
                    let since = *self.refused_since_ns.get_or_insert(now);
                    if now.saturating_sub(since) > REFUSED_FOR_NS {
                        return Err(self.gone(WireError::Refused));
                    }
                    return Ok(());
                }
                Err(e) => return Err(self.gone(e)),
            }
        }
    }

    fn send(ports: &mut BridgePorts, frame: &Frame) {
        send_on(&mut ports.wire, frame);
    }

    /// Forwards every command queued, then the newest plan if it is due.
    fn forward(&mut self, ports: &mut BridgePorts, cx: &mut Cx) -> Result<(), RunError> {
        while let Some(c) = ports.commands.receive()? {
            if let Some(f) = self.core.command(&c, cx.now(), cx.stats) {
                Self::send(ports, &f);
                self.core.sent(f.seq, cx.now());
            }
        }
        let core = &mut self.core;
        ports.plans.drain(&mut |p| core.offer_plan(p))?;
        if let Some(f) = self.core.plan_frame(cx.now()) {
            Self::send(ports, f);
        }
        Ok(())
    }
}

fn send_on(wire: &mut Wire, frame: &Frame) {
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(frame, &mut buf);
    wire.send(&buf[..n]);
}

/// Each axis's drive is on its own in a multi-axis bridge.
impl stepdrive_runtime::lanes::Together for BridgeNode {}

impl Node for BridgeNode {
    type Ports = BridgePorts;

    fn role(&self) -> Role {
        Role::Bridge
    }

    fn latched_fault(&self) -> u32 {
        self.core.last_fault()
    }

    fn pace(&self) -> Pace {
        Pace::Input
    }

    fn rate_hz(&self) -> f64 {
        self.sample_hz
    }

    fn awaiting(&self) -> String {
        let drive = &self.settings.drive;
        if self.core.awaiting_stack() {
            return format!(
                "the current loop, the position loop and {} state subscribers",
                self.settings.wait_subscribers
            );
        }
        if self.core.configured() {
            return format!("{} from the drive at {drive}", self.core.awaiting());
        }
        if self.refused_since_ns.is_some() {
            return format!("a CONFIG from the drive at {drive} (nothing listens there yet)");
        }
        match self.core.link().other_version {
            (0, _) => format!("a CONFIG from the drive at {drive}"),
            (n, v) => format!(
                "a CONFIG from the drive at {drive}: it sent {n} frames of protocol \
                 version {v}, this host speaks version {VERSION} (docs/drive-protocol.md)"
            ),
        }
    }

    /// §7: [`Self::prepare`], then (with the other drives, see [`StartGate`]) ENABLE.
    fn start(&mut self, ports: &mut BridgePorts, cx: &mut Cx) -> Result<Start, RunError> {
        if !self.prepared {
            if !self.prepare(ports, cx)? {
                return Ok(Start::Waiting);
            }
            self.prepared = true;
            if let Some(g) = &self.gate {
                g.arrive();
            }
        }
        if self.gate.as_ref().is_some_and(|g| !g.open()) {
            // Its drive idles, aligned, until the others are.
            self.read_frames(ports, cx)?;
            return Ok(Start::Waiting);
        }
        // Samples queued meanwhile are stale: drop them and start the stream (k = 0) with
        // the next one, then enable the drive.
        while let Ok(Some(_)) = ports.wire.recv(&mut self.rx, 0) {}
        let enable = self.core.begin(cx.now());
        Self::send(ports, &enable);
        self.running = true;
        tracing::info!(drive = %self.settings.drive, "bridge running");
        Ok(Start::NOW)
    }

    fn connect(&mut self, ports: &mut BridgePorts) -> Result<(), RunError> {
        ports.states.connect()?;
        Ok(())
    }

    fn poll(&mut self, ports: &mut BridgePorts, cx: &mut Cx) -> Result<Poll, RunError> {
        while let Some(r) = ports.resets.receive()? {
            tracing::warn!(
                pid = r.pid,
                drive_faults = self.core.last_fault() >> 16,
                "reset requested: RESET and ENABLE sent to the drive"
            );
            for f in self.core.reset(cx.now()) {
                Self::send(ports, &f);
            }
        }
        self.forward(ports, cx)?;
        // Taken before the socket is read: if it holds nothing, nothing arrived up to here.
        let looked_at = cx.now();
        self.read_frames(ports, cx)?;
        if let Some((st, rx_at)) = self.core.take_sample(cx.stats) {
            self.taken = Some((st, rx_at));
            cx.taken_at(rx_at);
            return Ok(Poll::READY);
        }
        if let Some(fault_state) = self.core.on_quiet(looked_at, cx.now()) {
            ports.states.publish(&fault_state)?;
            ports.state_ready.notify()?;
        }
        Ok(Poll::Pending)
    }

    fn step(&mut self, ports: &mut BridgePorts, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some((st, rx_at)) = self.taken.take() else {
            return Ok(Flow::Continue);
        };
        let mut st = self.core.publish(st, rx_at);
        st.publish_time_ns = cx.now();
        ports.states.publish(&st)?;
        // With real-time priorities the current loop, one above on this CPU, preempts us
        // here and has answered when notify returns.
        ports.state_ready.notify()?;
        cx.answered();
        self.forward(ports, cx)?;
        Ok(if self.core.is_last(&st) {
            Flow::Last
        } else {
            Flow::Continue
        })
    }

    /// Asleep until the wait strategy's margin before the next frame is due, then polling:
    /// a wake-up by the kernel would cost ~15 µs here (softirq, IPI, preemption). Without a
    /// due time, or well past it (drive late or silent), it blocks in `poll()`.
    fn due_ns(&self) -> Option<u64> {
        self.core.due_ns()
    }

    fn spin_past_due_ns(&self) -> Option<u64> {
        // A frame this late means the drive or the host was held up: stop spinning.
        Some((2 * self.period_ns).min(MAX_SPIN_PAST_DUE_NS))
    }

    fn block(
        &mut self,
        ports: &mut BridgePorts,
        now: u64,
        until_ns: u64,
    ) -> Result<bool, RunError> {
        let mut until = until_ns;
        if self.settings.look_for_answers && self.core.awaiting_answer(now) {
            until = until.min(now + ANSWER_CHECK_NS);
        }
        wait_readable(ports.wire.raw_fd(), until.saturating_sub(now));
        Ok(true)
    }

    fn report(&self, stats: &mut StatsReport) {
        self.core.report(stats);
    }

    /// Every exit path after a HELLO, a refusal included: the drive's outputs off (§7 step 7).
    fn stop(&mut self, ports: &mut BridgePorts, cx: &mut Cx) {
        if let Some(f) = self.core.farewell(cx.now()) {
            Self::send(ports, &f);
        }
        let l = self.core.link();
        tracing::info!(
            crc_errors = l.crc_errors,
            bad_frames = l.bad_frames,
            stale = l.stale_reports,
            repeated_configs = l.repeated_configs,
            rejected = l.rejected_commands,
            lost = l.lost_on_wire,
            running = self.running,
            "bridge stopped"
        );
    }
}

/// Sleeps until `fd` is readable or `timeout_ns` passes (EINTR too).
fn wait_readable(fd: std::os::fd::RawFd, timeout_ns: u64) -> bool {
    let mut pfd = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: (timeout_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (timeout_ns % 1_000_000_000) as libc::c_long,
    };
    // SAFETY: one valid pollfd and timespec; no signal mask change.
    unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) > 0 }
}

#[cfg(test)]
mod tests {
    use super::drive_addresses;

    /// One rule for a drive-address text, wherever it is read: a list of UDP addresses is
    /// a drive per axis; a serial line's path is one drive even with a comma in it.
    #[test]
    fn a_drive_address_text_names_a_drive_per_axis() {
        assert_eq!(drive_addresses("127.0.0.1:7700"), ["127.0.0.1:7700"]);
        assert_eq!(
            drive_addresses("127.0.0.1:7700, 127.0.0.1:7701"),
            ["127.0.0.1:7700", "127.0.0.1:7701"]
        );
        assert_eq!(drive_addresses("/dev/ttyACM0"), ["/dev/ttyACM0"]);
        assert_eq!(drive_addresses("serial:/tmp/a,b"), ["serial:/tmp/a,b"]);
    }
}
