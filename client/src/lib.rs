//! Command a stepdrive axis from a program.
//!
//! A stack served with `stepdrive serve` has an axis that programs command as a CiA 402
//! drive is commanded: enable it, send it to a position along a time-optimal jerk-limited
//! trajectory (and change your mind mid-move), jog it, stream a path to it, stop it, and
//! read its status. Every command is answered: taken, or refused with the reason (a
//! non-finite target, a limit that is not positive or beyond the axis's, a target outside
//! the soft limits, a move while the axis is not enabled, ...); a refused command is never
//! applied, and nothing is clamped silently.
//!
//! ```no_run
//! use stepdrive_client::{Axis, Limits};
//! use std::time::Duration;
//!
//! # fn main() -> Result<(), stepdrive_client::ClientError> {
//! let mut axis = Axis::connect("stepdrive", 0)?;
//! axis.enable()?;
//! let mv = axis.move_to(6.28, Limits::default())?;
//! let done = axis.wait_target_reached(&mv, Duration::from_secs(5))?;
//! println!("at {:.6} rad, following error {:.2e} rad", done.theta_rad, done.following_error_rad);
//! axis.disable()?;
//! # Ok(())
//! # }
//! ```
//!
//! On the stack's host the axis talks through the stack's iceoryx2 services: the command
//! service (request-response, each command answered within the position loop's tick), the
//! status topic (every tick, 2 kHz by default) and the stream topic. From another host,
//! [`Axis::connect_remote`] talks to a `stepdrive gateway` over Zenoh with the same verbs
//! (the status at the gateway's rate, 100 Hz by default; docs/remote.md). See the README's
//! "Commanding the axis" and the CiA 402 table there. Several axes of a multi-axis stack
//! move together, leaving and arriving on one tick, through a [`Group`].

pub mod gateway;
pub mod group;
pub mod remote;

pub use group::{Group, GroupMove, GroupStream};

use std::time::{Duration, Instant};
use stepdrive_runtime::ipc::{CommandClient, IpcBus, IpcPublisher, IpcSubscriber};
use stepdrive_runtime::port::{PortError, Publish, Subscribe};
pub use stepdrive_shared::axis::{
    axis_faults, axis_warnings, AxisAck, AxisMode, AxisState, AxisStatus, Refusal, RequestKind,
};
use stepdrive_shared::axis::{request_flags, AxisRequest, AxisStreamPoint};
use stepdrive_shared::scenario::Mode;

/// What went wrong talking to an axis.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// No stack runs on the instance.
    #[error("no stack serves axis commands on instance `{instance}`: start one with `stepdrive serve --instance {instance}`")]
    NoStack {
        instance: String,
        #[source]
        source: PortError,
    },
    /// The stack runs in lockstep: its scenario's `[[program]]` is its only source of
    /// commands (its status can be read).
    #[error("the stack on instance `{instance}` runs in lockstep: it takes commands only from its scenario's [[program]]; to command an axis, start one with `stepdrive serve --instance {instance}`")]
    Lockstep { instance: String },
    /// The stack has no such axis.
    #[error("axis {axis}: the stack on instance `{instance}` has {axes} axis/axes (0 … {last})", last = axes - 1)]
    UnknownAxis {
        instance: String,
        axis: u32,
        axes: usize,
    },
    /// The axis did not take the command; nothing of it was applied.
    #[error("{kind} refused: {reason}")]
    Refused {
        kind: &'static str,
        refusal: Refusal,
        reason: String,
    },
    /// The axis is in Fault (or went there while waiting).
    #[error("the axis is in Fault ({faults}; following error {following_error:e} rad): reset it (`Axis::reset`) once the cause is gone")]
    Fault {
        faults: String,
        following_error: f64,
        status: Box<AxisStatus>,
    },
    /// What was waited for did not happen in time.
    #[error("{what} did not happen within {timeout:?}")]
    Timeout { what: String, timeout: Duration },
    /// Another command took over the move waited for.
    #[error("the move was superseded by another command (seq {by})")]
    Superseded { by: u64 },
    /// A stream point not after the one before, or not finite: refused here, never sent.
    #[error("stream point at t = {t} s: {why}")]
    BadPoint { t: f64, why: &'static str },
    /// The axis left the stream (a quick stop, a disable, another command took over).
    #[error("the axis left the stream: it is in {state}, mode {mode}")]
    StreamLeft {
        state: &'static str,
        mode: &'static str,
    },
    /// The system refused the scheduling asked for (see [`realtime_priority`]).
    #[error("{0}")]
    Scheduling(String),
    /// Not an instance name (see `stepdrive_shared::services::instance_name`).
    #[error("{0}")]
    BadInstance(String),
    #[error(transparent)]
    Port(#[from] PortError),
    /// The link to a gateway on another host failed (see [`Axis::connect_remote`]).
    #[error("gateway at {endpoint}: {message}")]
    Remote { endpoint: String, message: String },
    /// What only the stack's own host can do (a command flood of the local service).
    #[error("{0} works on the stack's host only, not through a gateway")]
    LocalOnly(&'static str),
    /// A group or a coordinated move that cannot be asked for (see [`Group`]).
    #[error("{0}")]
    BadGroup(String),
    /// SIGINT or SIGTERM came while waiting (the process installed
    /// `stepdrive_runtime::poll::install_termination_handler`): the wait ended, nothing was
    /// sent because of it.
    #[error("interrupted while waiting for {what}")]
    Interrupted { what: String },
    /// The axis refused points of the stream (counted in its status): it will not play the
    /// path that was sent.
    #[error("the axis refused {count} point(s) of the stream, the last: {}", refusal.name())]
    PointsRefused { count: u64, refusal: Refusal },
    /// The axis could not follow the stream within its v/a/j limits (warning
    /// STREAM_LIMITED): it followed as close as its limits allow, not the path sent.
    #[error("the axis could not follow the stream within its speed, acceleration and jerk limits at stream time {t:.4} s (warning STREAM_LIMITED); a stream must start where the axis stands, at its speed, and keep within [axis] v_max_rad_s, a_max_rad_s2, j_max_rad_s3")]
    StreamLimited { t: f64 },
}

/// Whether SIGINT or SIGTERM came (a process that installed the runtime's handler): a
/// wait ends with [`ClientError::Interrupted`].
fn interrupted(what: impl FnOnce() -> String) -> Result<(), ClientError> {
    if stepdrive_runtime::poll::termination_requested() {
        return Err(ClientError::Interrupted { what: what() });
    }
    Ok(())
}

/// How long a request waits for its answer.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(2);
/// How long [`Axis::connect`] waits for a stack just launched to answer.
const START_WAIT: Duration = Duration::from_secs(5);

/// The SCHED_FIFO priority a streaming client takes by default: below the stack's loops
/// (80 and 81), above everything at ordinary priority.
pub const STREAM_PRIORITY: u8 = 10;

/// Runs the calling process at SCHED_FIFO `priority` (1–99; 0 leaves it at SCHED_OTHER).
/// A client that streams needs it: on two cores the stack's loops run at SCHED_FIFO with
/// RT throttling lifted, and a client at ordinary priority was measured held off the CPU
/// for up to 84 ms, eight times the default stream lead, so its stream ran dry and the
/// axis quick-stopped. Refused loudly: a stream that cannot keep up is no stream.
pub fn realtime_priority(priority: u8) -> Result<(), ClientError> {
    if priority == 0 {
        return Ok(());
    }
    stepdrive_runtime::rt::RtOptions {
        priority: Some(priority),
        cpu: None,
        helper_cpus: Vec::new(),
        lock_memory: false,
        timer_slack_ns: None,
        nice: None,
        require: true,
    }
    .apply()
    .map(|_| ())
    .map_err(|e| ClientError::Scheduling(e.describe()))
}

/// A move's or a jog's limits; `None` takes the axis's move defaults (`[axis]` in the
/// scenario). Each given must be positive and within the axis's maximum.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Limits {
    /// Speed, rad/s.
    pub v: Option<f64>,
    /// Acceleration, rad/s².
    pub a: Option<f64>,
    /// Jerk, rad/s³.
    pub j: Option<f64>,
}

impl Limits {
    fn apply(&self, r: &mut AxisRequest) {
        for (value, flag, field) in [
            (self.v, request_flags::HAS_V, &mut r.v_max_rad_s),
            (self.a, request_flags::HAS_A, &mut r.a_max_rad_s2),
            (self.j, request_flags::HAS_J, &mut r.j_max_rad_s3),
        ] {
            if let Some(v) = value {
                *field = v;
                r.flags |= flag;
            }
        }
    }
}

/// A move that was taken: what to wait for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Move {
    /// The command's sequence number (in the status's `last_seq` while it is the newest).
    pub seq: u64,
    /// The axis's answer.
    pub ack: AxisAck,
}

/// An axis of a served stack. See the crate documentation.
pub struct Axis {
    instance: String,
    axis: u32,
    link: Link,
    next_seq: u64,
    /// How long a command waits for its answer.
    pub timeout: Duration,
}

/// How an axis is reached: the stack's services on this host, or a gateway.
enum Link {
    Local(Box<LocalLink>),
    Remote(Box<remote::RemoteLink>),
}

struct LocalLink {
    bus: IpcBus,
    /// None for a lockstep stack, which takes no commands.
    commands: Option<CommandClient>,
    instance: String,
    status: IpcSubscriber<AxisStatus>,
    stream: Option<IpcPublisher<AxisStreamPoint>>,
}

impl LocalLink {
    fn commands(&mut self) -> Result<&mut CommandClient, ClientError> {
        self.commands.as_mut().ok_or_else(|| ClientError::Lockstep {
            instance: self.instance.clone(),
        })
    }

    /// Waits up to `timeout` for the position loop to serve the command service.
    fn wait_for_server(&mut self, timeout: Duration) -> Result<(), ClientError> {
        let deadline = Instant::now() + timeout;
        let commands = self.commands()?;
        while !commands.has_server() {
            if Instant::now() >= deadline {
                return Err(ClientError::Timeout {
                    what: "the stack's position loop serving commands".to_string(),
                    timeout,
                });
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        Ok(())
    }
}

impl Link {
    /// A lockstep stack's axis: its status can be read, nothing sent.
    fn status_only(&self) -> bool {
        matches!(self, Link::Local(l) if l.commands.is_none())
    }

    fn request(&mut self, r: &AxisRequest, timeout: Duration) -> Result<AxisAck, ClientError> {
        self.send(r)?.wait(Instant::now() + timeout)
    }

    /// Sends `r` without waiting for its answer.
    fn send(&mut self, r: &AxisRequest) -> Result<Pending, ClientError> {
        Ok(match self {
            Link::Local(l) => Pending::Local(l.commands()?.send(r)?),
            Link::Remote(l) => Pending::Remote(l.send(r)?),
        })
    }

    fn newest_status(&mut self) -> Result<Option<AxisStatus>, ClientError> {
        match self {
            Link::Local(l) => Ok(l.status.newest()?),
            Link::Remote(l) => l.newest_status(),
        }
    }

    fn open_stream(&mut self) -> Result<(), ClientError> {
        if let Link::Local(l) = self {
            if l.stream.is_none() {
                l.stream = Some(l.bus.publisher_of::<AxisStreamPoint>()?);
            }
        }
        Ok(())
    }

    fn publish_point(&mut self, p: &AxisStreamPoint) -> Result<(), ClientError> {
        match self {
            Link::Local(l) => {
                if let Some(publisher) = l.stream.as_mut() {
                    publisher.publish(p)?;
                }
                Ok(())
            }
            Link::Remote(l) => l.publish_point(p),
        }
    }
}

/// A request sent and not yet answered.
enum Pending {
    Local(stepdrive_runtime::ipc::PendingAnswer),
    Remote(remote::RemotePending),
}

impl Pending {
    fn wait(self, deadline: Instant) -> Result<AxisAck, ClientError> {
        match self {
            Pending::Local(p) => Ok(p.wait(deadline)?),
            Pending::Remote(p) => p.wait(deadline),
        }
    }
}

/// The faults' names.
fn fault_names(bits: u32) -> String {
    let names: Vec<&str> = [
        (axis_faults::FOLLOWING_ERROR, "following error"),
        (axis_faults::DRIVE, "the drive's fault"),
        (axis_faults::SETPOINT_STALE, "stale setpoints"),
        (axis_faults::TRAJECTORY, "trajectory"),
    ]
    .into_iter()
    .filter(|(b, _)| bits & b != 0)
    .map(|(_, n)| n)
    .collect();
    if names.is_empty() {
        "no fault bits".to_string()
    } else {
        names.join(", ")
    }
}

/// An axis in Fault is an error ([`ClientError::Fault`]), naming the faults; any other
/// status is `Ok`.
pub fn faulted(s: &AxisStatus) -> Result<(), ClientError> {
    if s.axis_state() == Some(AxisState::Fault) {
        return Err(ClientError::Fault {
            faults: fault_names(s.fault),
            following_error: s.following_error_rad,
            status: Box::new(*s),
        });
    }
    Ok(())
}

impl Axis {
    /// Connects to axis `axis` of the stack on `instance`, waiting up to 5 s for it to
    /// come up and up to 5 s more for its position loop to answer (a hardware stack's loops
    /// tick once its drive has aligned).
    pub fn connect(instance: &str, axis: u32) -> Result<Self, ClientError> {
        let no_stack = |source| ClientError::NoStack {
            instance: instance.to_string(),
            source,
        };
        stepdrive_shared::services::instance_name(instance).map_err(ClientError::BadInstance)?;
        let role = format!("client-{}", std::process::id());
        let mut bus = IpcBus::attach(instance, &role, Duration::from_secs(5)).map_err(no_stack)?;
        // Each axis of a multi-axis stack has its own services; an axis the stack's
        // scenario does not have is refused at once (not after a wait for its server).
        let axes = bus
            .announced_scenario()
            .ok()
            .flatten()
            .map(|s| s.axis_count());
        if let Some(axes) = axes.filter(|&n| axis as usize >= n) {
            return Err(ClientError::UnknownAxis {
                instance: instance.to_string(),
                axis,
                axes,
            });
        }
        stepdrive_runtime::port::PortFactory::set_axis(&mut bus, axis);
        let commands = match bus.mode() {
            Mode::Lockstep => None,
            Mode::Realtime | Mode::Hardware => Some(bus.command_client().map_err(no_stack)?),
        };
        let status = bus.subscriber_of::<AxisStatus>(16)?;
        let link = Link::Local(Box::new(LocalLink {
            bus,
            commands,
            instance: instance.to_string(),
            status,
            stream: None,
        }));
        // Sequence numbers of different clients do not collide: the pid is their top.
        Self::checked(instance, axis, link, std::process::id())
    }

    /// Connects to axis `axis` of the stack on `instance` through the `stepdrive gateway`
    /// at `endpoint` (`tcp/HOST:PORT`), from this host or another: the same verbs as
    /// [`Axis::connect`]. The status comes at the gateway's rate (100 Hz by default), a
    /// stream's default lead is [`remote::REMOTE_STREAM_LEAD_S`], and while this value
    /// lives it holds a lease at the gateway: if this process ends or its link is silent
    /// for [`remote::LEASE`], a stream or jog it started is quick-stopped at once. (The axis
    /// stops a jog that is not renewed, and a stream whose points stop, on its own and
    /// sooner: the lease is the fast path for a client that ends, not the safety.)
    pub fn connect_remote(endpoint: &str, instance: &str, axis: u32) -> Result<Self, ClientError> {
        stepdrive_shared::services::instance_name(instance).map_err(ClientError::BadInstance)?;
        let client = remote_client_id();
        let link = remote::RemoteLink::open(endpoint, instance, axis, client)?;
        Self::checked(instance, axis, Link::Remote(Box::new(link)), client)
    }

    fn checked(instance: &str, axis: u32, link: Link, client: u32) -> Result<Self, ClientError> {
        let mut this = Self {
            instance: instance.to_string(),
            axis,
            link,
            next_seq: u64::from(client) << 32,
            timeout: REQUEST_TIMEOUT,
        };
        // A status request answers whether the stack has this axis (an unknown index is
        // refused by the stack, naming it), before anything is read or sent for it. A
        // lockstep stack answers nothing: its status shows which axes it has.
        if !this.link.status_only() {
            // A stack just launched: its position loop may not serve commands yet (a request
            // sent before it does is lost), and a hardware stack's loops tick only once the
            // drive has aligned (about a second after launch).
            if let Link::Local(l) = &mut this.link {
                l.wait_for_server(START_WAIT)?;
            }
            this.timeout = START_WAIT;
            let checked = this.simple(RequestKind::Status);
            this.timeout = REQUEST_TIMEOUT;
            checked?;
        }
        Ok(this)
    }

    /// The gateway's endpoint, for an axis reached through one.
    pub fn endpoint(&self) -> Option<&str> {
        match &self.link {
            Link::Local(_) => None,
            Link::Remote(l) => Some(l.endpoint()),
        }
    }

    pub fn instance(&self) -> &str {
        &self.instance
    }

    fn request(&mut self, kind: RequestKind) -> AxisRequest {
        self.next_seq += 1;
        AxisRequest {
            axis: self.axis,
            kind: kind as u32,
            seq: self.next_seq,
            client: (self.next_seq >> 32) as u32,
            ..Default::default()
        }
    }

    /// Sends `r` and waits for its answer; a refusal is an error (nothing was applied).
    pub fn send(&mut self, mut r: AxisRequest) -> Result<AxisAck, ClientError> {
        r.publish_time_ns = stepdrive_runtime::clock::monotonic_ns();
        let ack = self.link.request(&r, self.timeout)?;
        if ack.taken() {
            return Ok(ack);
        }
        let kind = RequestKind::from_u32(r.kind).map_or("a command", |k| k.name());
        Err(ClientError::Refused {
            kind,
            refusal: Refusal::from_u32(ack.refusal).unwrap_or(Refusal::UnknownCommand),
            reason: ack.text().to_string(),
        })
    }

    fn simple(&mut self, kind: RequestKind) -> Result<AxisAck, ClientError> {
        let r = self.request(kind);
        self.send(r)
    }

    /// The axis's newest status (waiting up to `timeout` for one).
    pub fn status(&mut self) -> Result<AxisStatus, ClientError> {
        let deadline = Instant::now() + self.timeout;
        loop {
            if let Some(s) = self.link.newest_status()? {
                if s.axis == self.axis {
                    return Ok(s);
                }
            }
            if Instant::now() >= deadline {
                return Err(ClientError::Timeout {
                    what: "a status from the axis".to_string(),
                    timeout: self.timeout,
                });
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Enables the axis (shutdown, switch on, enable operation): Operation enabled, the
    /// setpoint where the rotor stands, at rest.
    pub fn enable(&mut self) -> Result<AxisAck, ClientError> {
        self.simple(RequestKind::Enable)
    }

    /// Renews the jog this client runs (any command does; this one changes nothing): a jog
    /// that hears nothing from its client for `[axis] jog_timeout_s` (0.5 s by default) is
    /// quick-stopped. Send it at least every 0.1 s while jogging. Answers with the state.
    pub fn renew(&mut self) -> Result<AxisAck, ClientError> {
        self.simple(RequestKind::Status)
    }

    /// Disables the axis (disable voltage): no torque.
    pub fn disable(&mut self) -> Result<AxisAck, ClientError> {
        self.simple(RequestKind::DisableVoltage)
    }

    /// Quick stop: decelerates at the axis's quick-stop rate to a standstill and holds
    /// (Quick stop active, until `enable`).
    pub fn quick_stop(&mut self) -> Result<AxisAck, ClientError> {
        self.simple(RequestKind::QuickStop)
    }

    /// Fault reset: from Fault to Switch on disabled, once the cause is gone (the drive's
    /// own fault is reset with it).
    pub fn reset(&mut self) -> Result<AxisAck, ClientError> {
        self.simple(RequestKind::FaultReset)
    }

    /// Halts: decelerates to a standstill at the move's limits and stays enabled.
    pub fn stop(&mut self, limits: Limits) -> Result<AxisAck, ClientError> {
        let mut r = self.request(RequestKind::Stop);
        limits.apply(&mut r);
        self.send(r)
    }

    /// Profile position: to `target` rad, changing any move in progress at once.
    pub fn move_to(&mut self, target: f64, limits: Limits) -> Result<Move, ClientError> {
        self.move_with(target, limits, 0)
    }

    /// Profile position: by `delta` rad from the current target.
    pub fn move_by(&mut self, delta: f64, limits: Limits) -> Result<Move, ClientError> {
        self.move_with(delta, limits, request_flags::RELATIVE)
    }

    /// A move with [`request_flags`] (relative, after the current move).
    pub fn move_with(
        &mut self,
        target: f64,
        limits: Limits,
        flags: u32,
    ) -> Result<Move, ClientError> {
        let mut r = self.request(RequestKind::Move);
        r.target_rad = target;
        r.flags |= flags;
        limits.apply(&mut r);
        let seq = r.seq;
        let ack = self.send(r)?;
        Ok(Move { seq, ack })
    }

    /// Waits until the move's target is reached (the trajectory at its target and the
    /// rotor within the target window); fails if the axis faults or another command takes
    /// over, and ends with [`ClientError::Interrupted`] on SIGINT/SIGTERM (the move goes
    /// on: halt it with [`Axis::halt_if_still`]).
    pub fn wait_target_reached(
        &mut self,
        mv: &Move,
        timeout: Duration,
    ) -> Result<AxisStatus, ClientError> {
        let deadline = Instant::now() + timeout;
        loop {
            let s = self.status()?;
            faulted(&s)?;
            // After the tick that took the move, any other last command took over (whatever
            // its client: sequence numbers of different clients do not compare).
            if s.tick > mv.ack.tick && s.last_seq != mv.seq {
                return Err(ClientError::Superseded { by: s.last_seq });
            }
            if s.last_seq == mv.seq && s.target_reached() {
                return Ok(s);
            }
            interrupted(|| format!("the move to {} rad", s.target_rad))?;
            if Instant::now() >= deadline {
                return Err(ClientError::Timeout {
                    what: format!("the move to {} rad", s.target_rad),
                    timeout,
                });
            }
            std::thread::sleep(Duration::from_micros(500));
        }
    }

    /// Halts the axis (a stop at its move limits) if the newest command is still the one
    /// of sequence number `seq`, i.e. the motion it started is this client's to end (a
    /// command of another client since has taken the axis over: it is left alone). The
    /// status after, or `None` if the axis was left alone.
    pub fn halt_if_still(&mut self, seq: u64) -> Result<Option<AxisStatus>, ClientError> {
        let s = self.status()?;
        if s.last_seq != seq || !s.axis_state().is_some_and(AxisState::outputs_on) {
            return Ok(None);
        }
        self.stop(Limits::default())?;
        self.status().map(Some)
    }

    /// Profile velocity: runs at `velocity` rad/s (stops at the soft position limit) while
    /// this client renews it ([`Axis::renew`], or any command, at least every 0.1 s): the
    /// axis quick-stops a jog that hears nothing from its client for `[axis] jog_timeout_s`.
    pub fn jog(&mut self, velocity: f64, limits: Limits) -> Result<AxisAck, ClientError> {
        let mut r = self.request(RequestKind::Jog);
        r.velocity_rad_s = velocity;
        limits.apply(&mut r);
        self.send(r)
    }

    /// Floods the axis with `request`-kind commands (status requests, or relative moves of
    /// `move_rad`) at `rate_hz` for `duration`, never waiting for answers: a measurement of
    /// what a runaway client costs the stack, not a way to command it. Each request sent
    /// is answered (taken, or refused with a reason: more than the position loop applies
    /// in one tick) or refused to this client by the service (it holds a few of a
    /// client's requests at once). `spin`: poll between sends, as a runaway client
    /// burning a CPU does; otherwise nap between bursts, and measure the command path alone.
    pub fn flood(
        &mut self,
        kind: RequestKind,
        move_rad: f64,
        rate_hz: f64,
        duration: Duration,
        spin: bool,
    ) -> Result<stepdrive_runtime::ipc::Flood, ClientError> {
        let Link::Local(local) = &mut self.link else {
            return Err(ClientError::LocalOnly("a command flood"));
        };
        let mut template = AxisRequest {
            axis: self.axis,
            kind: kind as u32,
            seq: self.next_seq + 1,
            client: (self.next_seq >> 32) as u32,
            ..Default::default()
        };
        template.target_rad = move_rad;
        template.flags |= request_flags::RELATIVE;
        let mut seq = template.seq;
        let counts = local.commands()?.flood(
            &template,
            || {
                seq += 1;
                seq
            },
            rate_hz,
            duration,
            spin,
        );
        self.next_seq = seq;
        Ok(counts?)
    }

    /// The axis's present position is `position` rad from now on (at a standstill).
    pub fn set_position(&mut self, position: f64) -> Result<AxisAck, ClientError> {
        let mut r = self.request(RequestKind::SetPosition);
        r.target_rad = position;
        self.send(r)
    }

    /// Starts a cyclic synchronous position stream, played `lead` s behind its points'
    /// arrival (`None`: the axis's default). Push points with [`Stream::push`] at 100 Hz to
    /// 2 kHz; a stream that stops coming, or whose first point does not come, is
    /// quick-stopped by the axis.
    pub fn stream(&mut self, lead: Option<f64>) -> Result<Stream<'_>, ClientError> {
        self.link.open_stream()?;
        // Points refused before this stream are not this stream's.
        let refused_before = self.status()?.refused_points;
        let mut r = self.request(RequestKind::StreamStart);
        let lead = match (&self.link, lead) {
            (Link::Remote(_), None) => Some(remote::REMOTE_STREAM_LEAD_S),
            (_, lead) => lead,
        };
        if let Some(l) = lead {
            r.lead_s = l;
            r.flags |= request_flags::HAS_LEAD;
        }
        let id = r.seq;
        let ack = self.send(r)?;
        Ok(Stream::new(self, id, ack.tick, refused_before))
    }
}

/// A stream in progress (see [`Axis::stream`]).
pub struct Stream<'a> {
    axis: &'a mut Axis,
    id: u64,
    /// The position-loop tick that took the stream's start.
    start_tick: u64,
    next: u64,
    last_t: Option<f64>,
    seen: Option<AxisStatus>,
    /// The axis's count of refused points when the stream started.
    refused_before: u64,
    /// The stream time of the first status that carried STREAM_LIMITED, and whether one
    /// carried STREAM_UNDERRUN.
    limited_at: Option<f64>,
    underrun: bool,
}

impl<'a> Stream<'a> {
    pub(crate) fn new(axis: &'a mut Axis, id: u64, start_tick: u64, refused_before: u64) -> Self {
        Self {
            axis,
            id,
            start_tick,
            next: 0,
            last_t: None,
            seen: None,
            refused_before,
            limited_at: None,
            underrun: false,
        }
    }

    /// The stream time at which the axis first said it could not follow the stream within
    /// its limits (warning STREAM_LIMITED), from the statuses read while pacing; `None` if
    /// it followed it all so far.
    pub fn limited_at(&self) -> Option<f64> {
        self.limited_at
    }

    /// Whether the stream ran dry at some status read (warning STREAM_UNDERRUN: the axis
    /// carried the last point on at its speed until points came again).
    pub fn ran_dry(&self) -> bool {
        self.underrun
    }

    /// Fails with [`ClientError::StreamLimited`] if the axis could not follow the stream
    /// within its limits so far.
    pub fn followed(&self) -> Result<(), ClientError> {
        match self.limited_at {
            Some(t) => Err(ClientError::StreamLimited { t }),
            None => Ok(()),
        }
    }

    /// Sends the point at stream time `t` s: θ rad, and optionally ω rad/s and a torque
    /// feed-forward N·m. Time must increase; a point that breaks that, or is not finite,
    /// is refused here and never sent.
    pub fn push(
        &mut self,
        t: f64,
        theta: f64,
        omega: Option<f64>,
        torque_ff: Option<f64>,
    ) -> Result<(), ClientError> {
        let finite = t.is_finite()
            && theta.is_finite()
            && omega.is_none_or(f64::is_finite)
            && torque_ff.is_none_or(f64::is_finite);
        if !finite {
            return Err(ClientError::BadPoint {
                t,
                why: "not finite",
            });
        }
        if self.last_t.is_some_and(|l| t <= l) {
            return Err(ClientError::BadPoint {
                t,
                why: "stream time must increase",
            });
        }
        let row = stepdrive_shared::axis::StreamRow {
            t_s: t,
            theta_rad: theta,
            omega_rad_s: omega,
            torque_ff_nm: torque_ff,
        };
        let mut p = row.point(self.axis.axis, self.id, self.next);
        p.publish_time_ns = stepdrive_runtime::clock::monotonic_ns();
        self.axis.link.publish_point(&p)?;
        self.next += 1;
        self.last_t = Some(t);
        Ok(())
    }

    /// Waits until the axis is ready for the point at stream time `t`: the first point at
    /// once, each later one when the stream time the axis plays (its status's
    /// `stream_time_s`, on the stack's clock) is within the stream's lead of `t`. Paced so,
    /// the axis holds one lead of points whatever the two clocks do: a simulated plant's
    /// time pauses while its process is held up, and a wall-clock sender would run ahead
    /// of it. Fails if the axis faults, leaves the stream or refuses a point (one beyond
    /// the soft limits, say), its stream time stands still for the client's timeout, or on
    /// SIGINT/SIGTERM.
    pub fn pace(&mut self, t: f64) -> Result<(), ClientError> {
        if self.next == 0 {
            return Ok(());
        }
        self.wait_until(t, |s| t <= s.stream_time_s + s.stream_lead_s)
    }

    /// Waits until the axis has played every point sent (its stream time past the last
    /// point's): a stream ended before that is cut a lead short of its end.
    pub fn played_out(&mut self) -> Result<(), ClientError> {
        let Some(last) = self.last_t else {
            return Ok(());
        };
        self.wait_until(last, |s| s.stream_time_s >= last)
    }

    /// Waits until the stream's newest status is `ready`: fails if the axis faults or
    /// leaves the stream, or its stream time stands still for the client's timeout (`t`:
    /// the stream time waited for, for the message).
    fn wait_until(
        &mut self,
        t: f64,
        ready: impl Fn(&AxisStatus) -> bool,
    ) -> Result<(), ClientError> {
        let mut moved = (f64::NAN, Instant::now());
        loop {
            interrupted(|| format!("the axis's stream time to reach {t} s"))?;
            // Statuses of ticks before the stream's start say nothing of it.
            let start = self.start_tick;
            let axis = self.axis.axis;
            if let Some(s) = self
                .axis
                .link
                .newest_status()?
                .filter(|s| s.axis == axis && s.tick >= start)
            {
                self.seen = Some(s);
            }
            if let Some(s) = self.seen {
                faulted(&s)?;
                if s.refused_points > self.refused_before {
                    return Err(ClientError::PointsRefused {
                        count: s.refused_points - self.refused_before,
                        refusal: Refusal::from_u32(s.last_refusal)
                            .unwrap_or(Refusal::UnknownCommand),
                    });
                }
                if s.warning & axis_warnings::STREAM_LIMITED != 0 && self.limited_at.is_none() {
                    self.limited_at = Some(s.stream_time_s);
                }
                self.underrun |= s.warning & axis_warnings::STREAM_UNDERRUN != 0;
                if AxisMode::from_u32(s.mode) != Some(AxisMode::CyclicPosition) {
                    return Err(ClientError::StreamLeft {
                        state: s.axis_state().map_or("?", |x| x.name()),
                        mode: AxisMode::from_u32(s.mode).map_or("?", |m| m.name()),
                    });
                }
                if ready(&s) {
                    return Ok(());
                }
                if s.stream_time_s.is_finite() && s.stream_time_s != moved.0 {
                    moved = (s.stream_time_s, Instant::now());
                }
            }
            if moved.1.elapsed() >= self.axis.timeout {
                return Err(ClientError::Timeout {
                    what: format!("the axis's stream time to reach {t} s"),
                    timeout: self.axis.timeout,
                });
            }
            std::thread::sleep(Duration::from_micros(100));
        }
    }

    /// The newest status [`Stream::pace`] read (none before the first wait): a streaming
    /// program judges its tracking by it without a wait of its own.
    pub fn last_status(&self) -> Option<&AxisStatus> {
        self.seen.as_ref()
    }

    /// [`Stream::pace`], then [`Stream::push`].
    pub fn push_paced(
        &mut self,
        t: f64,
        theta: f64,
        omega: Option<f64>,
        torque_ff: Option<f64>,
    ) -> Result<(), ClientError> {
        self.pace(t)?;
        self.push(t, theta, omega, torque_ff)
    }

    /// Points sent so far.
    pub fn sent(&self) -> u64 {
        self.next
    }

    /// Ends the stream: the axis decelerates to rest and holds.
    pub fn end(self) -> Result<AxisAck, ClientError> {
        self.axis.simple(RequestKind::StreamEnd)
    }
}

/// A remote client's id (the top of its commands' sequence numbers and its lease's name):
/// the pid alone may repeat across hosts, so the clock's nanoseconds are mixed in.
fn remote_client_id() -> u32 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    // Odd ids beyond 2^22 never equal a Linux pid (at most 2^22), so a remote client never
    // shares a local one's sequence numbers.
    (std::process::id() ^ nanos.rotate_left(11)) | (1 << 31) | 1
}
