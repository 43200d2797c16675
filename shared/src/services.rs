//! Service names and the one place that opens them, so every process opens every service
//! with identical settings (iceoryx2 treats an opener's settings as minimum requirements).

use crate::messages::{DriveCommand, DrivePlan, DriveState, TorqueSetpoint};
use crate::scenario::Mode;
use crate::stats::StatsReport;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use iceoryx2::service::port_factory::PortFactory as _;
use std::fmt::Debug;
use std::time::{Duration, Instant};

pub use iceoryx2::prelude::ZeroCopySend as Message;

pub type Ipc = ipc::Service;
pub type Topic<T> = PortFactory<Ipc, T, ()>;
pub type Pub<T> = Publisher<Ipc, T, ()>;
pub type Sub<T> = Subscriber<Ipc, T, ()>;
pub type EventTopic = iceoryx2::service::port_factory::event::PortFactory<Ipc>;
pub type Notifier = iceoryx2::port::notifier::Notifier<Ipc>;
pub type Listener = iceoryx2::port::listener::Listener<Ipc>;

pub const DEFAULT_INSTANCE: &str = "stepdrive";

/// Subscriber queue depths. The monitor's is deep because in lockstep it must see every
/// sample (the publisher waits for it rather than drop one) while it drains at a low rate.
pub const MONITOR_BUFFER: usize = 8192;
pub const LOOP_BUFFER: usize = 16;

#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    #[error("invalid instance name `{0}`: use 1-48 characters from A-Z a-z 0-9 . _ -")]
    BadInstance(String),
    #[error("{context}: {message}")]
    Iceoryx { context: String, message: String },
}

fn ipc_err(context: impl Into<String>, e: impl Debug) -> IpcError {
    IpcError::Iceoryx {
        context: context.into(),
        message: format!("{e:?}"),
    }
}

/// Service names of one stack. Two stacks with different instance names never see each
/// other.
#[derive(Debug, Clone)]
pub struct ServiceNames {
    pub instance: String,
}

impl ServiceNames {
    pub fn new(instance: &str) -> Result<Self, IpcError> {
        let ok = !instance.is_empty()
            && instance.len() <= 48
            && instance
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
        if ok {
            Ok(Self {
                instance: instance.to_string(),
            })
        } else {
            Err(IpcError::BadInstance(instance.to_string()))
        }
    }
    /// Plant → all, every sample.
    pub fn drive_state(&self) -> String {
        format!("{}/drive/state", self.instance)
    }
    /// Current loop → plant, every sample.
    pub fn drive_command(&self) -> String {
        format!("{}/drive/command", self.instance)
    }
    /// Current loop → plant, after each command (realtime): the voltage plan.
    pub fn drive_plan(&self) -> String {
        format!("{}/drive/plan", self.instance)
    }
    /// Bridge → current loop (hardware): "a state was published".
    pub fn state_ready(&self) -> String {
        format!("{}/drive/state-ready", self.instance)
    }
    /// Position loop → current loop, every tick.
    pub fn torque_setpoint(&self) -> String {
        format!("{}/control/setpoint", self.instance)
    }
    /// Every loop → monitor: timing statistics, ~1 Hz and at exit.
    pub fn stats(&self) -> String {
        format!("{}/monitor/stats", self.instance)
    }
}

/// iceoryx2 configuration built in code: without it iceoryx2 would silently read a
/// `config/iceoryx2.toml` from the working directory or the user's home.
pub fn iceoryx_config() -> Config {
    Config::default()
}

/// A process's node and the three topics of the stack.
pub struct Topics {
    pub node: Node<Ipc>,
    pub names: ServiceNames,
    pub state: Topic<DriveState>,
    pub command: Topic<DriveCommand>,
    pub plan: Topic<DrivePlan>,
    pub setpoint: Topic<TorqueSetpoint>,
    pub stats: Topic<StatsReport>,
    pub mode: Mode,
}

/// Settings of one topic; the same for every opener.
struct Qos {
    max_publishers: usize,
    max_subscribers: usize,
    max_buffer: usize,
    /// Lockstep: false, a full queue makes the publisher wait and nothing is ever dropped.
    /// Realtime: true, the oldest queued sample is overwritten and nobody blocks the plant.
    safe_overflow: bool,
}

/// Opens or creates service `name` with `open`. Two processes starting together may race
/// to create a service; the loser sees a transient error and retries.
fn open_service<F, E: Debug>(
    node: &Node<Ipc>,
    name: &str,
    open: impl Fn(iceoryx2::service::builder::Builder<Ipc>) -> Result<F, E>,
) -> Result<F, IpcError> {
    let service_name: ServiceName = name
        .try_into()
        .map_err(|e| ipc_err(format!("service name `{name}`"), e))?;
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        match open(node.service_builder(&service_name)) {
            Ok(t) => return Ok(t),
            Err(e) if Instant::now() < deadline => {
                tracing::debug!(service = name, error = ?e, "service not ready yet, retrying");
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) => return Err(ipc_err(format!("cannot open service `{name}`"), e)),
        }
    }
}

fn open_topic<T: Debug + ZeroCopySend + 'static>(
    node: &Node<Ipc>,
    name: &str,
    qos: &Qos,
) -> Result<Topic<T>, IpcError> {
    open_service(node, name, |builder| {
        builder
            .publish_subscribe::<T>()
            .max_publishers(qos.max_publishers)
            .max_subscribers(qos.max_subscribers)
            .subscriber_max_buffer_size(qos.max_buffer)
            .history_size(0)
            .enable_safe_overflow(qos.safe_overflow)
            .open_or_create()
    })
}

impl Topics {
    /// Creates this process's node (named `role`) and opens the stack's services with the
    /// settings of `mode` (all processes of a stack must run the same mode).
    pub fn open(instance: &str, role: &str, mode: Mode) -> Result<Self, IpcError> {
        let safe_overflow = mode != Mode::Lockstep;
        let names = ServiceNames::new(instance)?;
        let node_name: NodeName = format!("{instance}.{role}")
            .as_str()
            .try_into()
            .map_err(|e| ipc_err("node name", e))?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&iceoryx_config())
            // We handle SIGINT/SIGTERM ourselves (`poll::install_termination_handler`).
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|e| ipc_err("cannot create iceoryx2 node", e))?;
        // One writer per control topic; room for the loops, a monitor and a tool. Every
        // subscriber slot costs the publisher MONITOR_BUFFER samples of shared memory.
        let control = Qos {
            max_publishers: 1,
            max_subscribers: 4,
            max_buffer: MONITOR_BUFFER,
            safe_overflow,
        };
        let state = open_topic::<DriveState>(&node, &names.drive_state(), &control)?;
        let command = open_topic::<DriveCommand>(&node, &names.drive_command(), &control)?;
        let setpoint = open_topic::<TorqueSetpoint>(&node, &names.torque_setpoint(), &control)?;
        // Only the plant reads plans, and only the newest matters: a short queue keeps the
        // ~2 KB samples' shared memory small.
        let plan = open_topic::<DrivePlan>(
            &node,
            &names.drive_plan(),
            &Qos {
                max_publishers: 1,
                max_subscribers: 2,
                max_buffer: LOOP_BUFFER,
                safe_overflow: true,
            },
        )?;
        let stats = open_topic::<StatsReport>(
            &node,
            &names.stats(),
            // A report is ~90 KB: keep the queues short.
            &Qos {
                max_publishers: 4,
                max_subscribers: 2,
                max_buffer: 4,
                safe_overflow: true,
            },
        )?;
        Ok(Self {
            node,
            names,
            state,
            command,
            plan,
            setpoint,
            stats,
            mode,
        })
    }

    /// Hardware mode: the event the bridge raises after each state, so that the current
    /// loop sleeps until there is a sample to answer instead of spinning on the CPU the
    /// bridge needs (the bridge polls its drive socket there). Opened on demand.
    pub fn state_ready(&self) -> Result<EventTopic, IpcError> {
        open_service(&self.node, &self.names.state_ready(), |builder| {
            // One event id: each wait drains the whole id bitset with an atomic swap per
            // id, and the default 256 ids made that ~4.7 µs per wake-up (measured).
            builder
                .event()
                .max_notifiers(1)
                .max_listeners(2)
                .event_id_max_value(0)
                .open_or_create()
        })
    }
}

pub fn notifier(topic: &EventTopic) -> Result<Notifier, IpcError> {
    topic
        .notifier_builder()
        .create()
        .map_err(|e| ipc_err("cannot create state-ready notifier", e))
}

pub fn listener(topic: &EventTopic) -> Result<Listener, IpcError> {
    topic
        .listener_builder()
        .create()
        .map_err(|e| ipc_err("cannot create state-ready listener", e))
}

/// Raises the event (one `sendto` on a Unix socket).
pub fn notify(notifier: &Notifier) -> Result<(), IpcError> {
    notifier
        .notify()
        .map(|_| ())
        .map_err(|e| ipc_err("notify failed", e))
}

/// Blocks until the event is raised or `timeout` passes (the timeout is jiffy-grained
/// here, the wake-up on an event is not), and consumes what is pending. A signal (SIGCONT
/// after a stop, SIGTERM) just ends the wait: the caller re-checks its flags.
pub fn wait_event(listener: &Listener, timeout: Duration) -> Result<(), IpcError> {
    use iceoryx2::port::listener::ListenerWaitError;
    match listener.timed_wait(|_| {}, timeout) {
        Ok(_) | Err(ListenerWaitError::InterruptSignal) => Ok(()),
        Err(e) => Err(ipc_err("event wait failed", e)),
    }
}

pub fn publisher<T: Debug + ZeroCopySend + 'static>(
    topic: &Topic<T>,
    what: &str,
) -> Result<Pub<T>, IpcError> {
    topic
        .publisher_builder()
        .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
        .create()
        .map_err(|e| {
            ipc_err(
                format!(
                    "cannot create {what} publisher (is another one running on this instance?)"
                ),
                e,
            )
        })
}

pub fn subscriber<T: Debug + ZeroCopySend + 'static>(
    topic: &Topic<T>,
    what: &str,
    buffer: usize,
) -> Result<Sub<T>, IpcError> {
    topic
        .subscriber_builder()
        .buffer_size(buffer)
        .create()
        .map_err(|e| ipc_err(format!("cannot create {what} subscriber"), e))
}

/// Publishes a copy of `value` (the messages are a few dozen bytes; a copy into the loaned
/// shared-memory slot is what zero-copy means here).
pub fn send<T: Debug + ZeroCopySend + Copy + 'static>(
    publisher: &Pub<T>,
    value: T,
) -> Result<(), IpcError> {
    publisher
        .send_copy(value)
        .map(|_| ())
        .map_err(|e| ipc_err("send failed", e))
}

/// Non-blocking receive of the next queued sample, copied out.
pub fn try_receive<T: Debug + ZeroCopySend + Copy + 'static>(
    subscriber: &Sub<T>,
) -> Result<Option<T>, IpcError> {
    match subscriber.receive() {
        Ok(Some(sample)) => Ok(Some(*sample.payload())),
        Ok(None) => Ok(None),
        Err(e) => Err(ipc_err("receive failed", e)),
    }
}

/// Hands every queued sample to `f` in place, without copying it out (for large ones).
pub fn drain<T: Debug + ZeroCopySend + 'static>(
    subscriber: &Sub<T>,
    mut f: impl FnMut(&T),
) -> Result<(), IpcError> {
    while let Some(sample) = subscriber
        .receive()
        .map_err(|e| ipc_err("receive failed", e))?
    {
        f(sample.payload());
    }
    Ok(())
}

/// Removes what crashed processes left behind (nodes, ports, shared memory). Call it
/// before starting a stack and after its processes have been reaped.
pub fn cleanup_dead_nodes() -> usize {
    let config = iceoryx_config();
    let mut removed = 0;
    let result = Node::<Ipc>::list(&config, |state| {
        if let NodeState::Dead(view) = state {
            match view.try_remove_stale_resources() {
                Ok(()) => removed += 1,
                Err(e) => tracing::warn!(error = ?e, "could not remove a dead node's resources"),
            }
        }
        CallbackProgression::Continue
    });
    if let Err(e) = result {
        tracing::warn!(error = ?e, "could not list iceoryx2 nodes");
    }
    removed
}

/// Establishes a publisher's connections to the subscribers present now, so the first
/// real sample does not pay for `shm_open`/`mmap`.
pub fn connect<T: Debug + ZeroCopySend + 'static>(publisher: &Pub<T>) -> Result<(), IpcError> {
    use iceoryx2::port::update_connections::UpdateConnections;
    publisher
        .update_connections()
        .map_err(|e| ipc_err("cannot connect publisher", e))
}

/// Publishers currently attached to a topic.
pub fn publisher_count<T: Debug + ZeroCopySend + 'static>(topic: &Topic<T>) -> usize {
    topic.dynamic_config().number_of_publishers()
}

/// Subscribers currently attached to a topic.
pub fn subscriber_count<T: Debug + ZeroCopySend + 'static>(topic: &Topic<T>) -> usize {
    topic.dynamic_config().number_of_subscribers()
}

/// Publishes a loop's statistics. The final report is followed by a short linger so the
/// monitor (draining at ~1 kHz) takes it before this process's publisher goes away.
pub fn publish_stats(
    publisher: &Pub<StatsReport>,
    stats: &mut StatsReport,
    is_final: bool,
) -> Result<(), IpcError> {
    stats.is_final = u32::from(is_final);
    stats.seq += 1;
    stats.publish_time_ns = crate::clock::monotonic_ns();
    send(publisher, *stats)?;
    if is_final {
        std::thread::sleep(Duration::from_millis(200));
    }
    Ok(())
}
