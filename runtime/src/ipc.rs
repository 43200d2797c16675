//! Ports on iceoryx2 shared memory: the transport between the stack's processes. Every
//! service is opened with the settings the contract gives its topic
//! (`stepdrive_shared::services::Topic::qos`), so every opener agrees, and carries the
//! stack's [`Stamp`] as service attributes: a process of another mode or scenario is refused
//! at once, with both named, instead of exchanging messages that mean something else.

use crate::doorbell::{Doorbells, Ringer};
use crate::port::{
    BoxedError, Listen, Notify, PortError, PortFactory, Presence, Publish, Serve, Subscribe,
};
use iceoryx2::port::listener::ListenerWaitError;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use iceoryx2::service::attribute::{
    AttributeKey, AttributeSpecifier, AttributeValue, AttributeVerifier,
};
use iceoryx2::service::builder::event::{EventOpenError, EventOpenOrCreateError};
use iceoryx2::service::builder::publish_subscribe::{
    PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::builder::request_response::{
    RequestResponseOpenError, RequestResponseOpenOrCreateError,
};
use iceoryx2::service::port_factory::PortFactory as _;
use std::time::{Duration, Instant};
use stepdrive_shared::axis::{AxisAck, AxisRequest};
use stepdrive_shared::messages::{ResetRequest, StackScenario};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::scenario::MAX_AXES;
use stepdrive_shared::services::{Message, ServiceNames, Topic};
use stepdrive_shared::stack::{Role, NODES};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::{DriveCommand, DriveState, Scenario, TorqueSetpoint};

type Ipc = ipc::Service;
type TopicFactory<M> = iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, M, ()>;
type EventFactory = iceoryx2::service::port_factory::event::PortFactory<Ipc>;

fn boxed<E: std::error::Error + Send + Sync + 'static>(e: E) -> BoxedError {
    Box::new(e)
}

/// iceoryx2 configuration built in code: without it iceoryx2 would silently read a
/// `config/iceoryx2.toml` from the working directory or the user's home.
pub fn iceoryx_config() -> Config {
    Config::default()
}

/// What every process of one stack must agree on: the timing mode (it sets the services'
/// settings) and the scenario (it sets what every message means).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stamp {
    pub mode: Mode,
    /// The scenario's name and fingerprint.
    pub scenario: String,
}

impl Stamp {
    pub fn new(mode: Mode, scenario: &Scenario) -> Self {
        // An attribute value holds 256 bytes: a long name is cut, the fingerprint kept.
        let name: String = scenario.name.chars().take(200).collect();
        Self {
            mode,
            scenario: format!("{name} ({})", scenario.fingerprint()),
        }
    }

    fn describe(mode: &str, scenario: &str) -> String {
        format!("mode {mode}, scenario {scenario}")
    }
}

const MODE_KEY: &str = "stepdrive.mode";
const SCENARIO_KEY: &str = "stepdrive.scenario";

/// An open that failed for good (other attributes), not because of a race.
trait OpenError: std::error::Error + Send + Sync + 'static {
    fn incompatible_attributes(&self) -> bool;
}

impl OpenError for PublishSubscribeOpenOrCreateError {
    fn incompatible_attributes(&self) -> bool {
        matches!(
            self,
            Self::PublishSubscribeOpenError(PublishSubscribeOpenError::IncompatibleAttributes)
        )
    }
}

impl OpenError for EventOpenOrCreateError {
    fn incompatible_attributes(&self) -> bool {
        matches!(
            self,
            Self::EventOpenError(EventOpenError::IncompatibleAttributes)
        )
    }
}

impl OpenError for RequestResponseOpenOrCreateError {
    fn incompatible_attributes(&self) -> bool {
        matches!(
            self,
            Self::RequestResponseOpenError(RequestResponseOpenError::IncompatibleAttributes)
        )
    }
}

/// One process's iceoryx2 node on one stack instance: opens the stack's ports.
pub struct IpcBus {
    node: Node<Ipc>,
    names: ServiceNames,
    stamp: Stamp,
    verifier: AttributeVerifier,
    /// Lockstep: the instance's doorbells, rung by every publisher.
    doorbells: Option<Doorbells>,
    /// The stack's node this process is, if it is one (its readers may relay rings).
    role: Option<Role>,
    /// The axis whose services the next ports are opened on ([`PortFactory::set_axis`]).
    axis: u32,
}

impl IpcBus {
    /// Creates this process's node (named `role`) on `instance`; every port it opens uses the
    /// settings of the stamp's mode and requires the same stamp of every other process.
    pub fn open(instance: &str, role: &str, stamp: &Stamp) -> Result<Self, PortError> {
        let names = ServiceNames::new(instance)?;
        let node_name = names.node(role);
        let node_error = |source| PortError::Node {
            node: node_name.clone(),
            source,
        };
        let name: NodeName = node_name
            .as_str()
            .try_into()
            .map_err(|e| node_error(boxed(e)))?;
        let node = NodeBuilder::new()
            .name(&name)
            .config(&iceoryx_config())
            // We handle SIGINT/SIGTERM ourselves (`poll::install_termination_handler`).
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|e| node_error(boxed(e)))?;
        let attribute_error = |source: BoxedError| PortError::Node {
            node: node_name.clone(),
            source,
        };
        let mode_key = AttributeKey::try_from(MODE_KEY).map_err(|e| attribute_error(boxed(e)))?;
        let mode =
            AttributeValue::try_from(stamp.mode.as_str()).map_err(|e| attribute_error(boxed(e)))?;
        let scenario_key =
            AttributeKey::try_from(SCENARIO_KEY).map_err(|e| attribute_error(boxed(e)))?;
        let scenario = AttributeValue::try_from(stamp.scenario.as_str())
            .map_err(|e| attribute_error(boxed(e)))?;
        let verifier = AttributeVerifier::new()
            .require(&mode_key, &mode)
            .and_then(|v| v.require(&scenario_key, &scenario))
            .map_err(|e| attribute_error(boxed(e)))?;
        let doorbells = match stamp.mode {
            Mode::Lockstep => Some(Doorbells::open(instance)?),
            Mode::Realtime | Mode::Hardware => None,
        };
        Ok(Self {
            node,
            names,
            stamp: stamp.clone(),
            verifier,
            doorbells,
            role: NODES.iter().map(|n| n.role).find(|r| r.id() == role),
            axis: 0,
        })
    }

    /// Attaches a tool (a reset, a monitor) to the stack running on `instance`, waiting up
    /// to `wait` for it to appear: its stamp is read from the stack's own services, so the
    /// tool need not be told mode and scenario.
    pub fn attach(instance: &str, role: &str, wait: Duration) -> Result<Self, PortError> {
        let names = ServiceNames::new(instance)?;
        let state = names.topic(Topic::State);
        let no_stack = || PortError::NoStack {
            instance: instance.to_string(),
        };
        let service_name: ServiceName = state.as_str().try_into().map_err(|_| no_stack())?;
        let deadline = Instant::now() + wait;
        let details = loop {
            let details = ipc::Service::details(
                &service_name,
                &iceoryx_config(),
                MessagingPattern::PublishSubscribe,
            );
            match details {
                Ok(Some(d)) => break d,
                _ if Instant::now() < deadline && !crate::poll::termination_requested() => {
                    std::thread::sleep(Duration::from_millis(10));
                }
                _ => return Err(no_stack()),
            }
        };
        let attributes = details.static_details.attributes();
        let get = |k: &str| {
            AttributeKey::try_from(k)
                .ok()
                .and_then(|k| attributes.key_value(&k, 0).map(|v| v.to_string()))
        };
        let mode = get(MODE_KEY)
            .and_then(|m| m.parse::<Mode>().ok())
            .ok_or_else(no_stack)?;
        let scenario = get(SCENARIO_KEY).ok_or_else(no_stack)?;
        Self::open(instance, role, &Stamp { mode, scenario })
    }

    pub fn mode(&self) -> Mode {
        self.stamp.mode
    }

    pub fn stamp(&self) -> &Stamp {
        &self.stamp
    }

    /// Lockstep: the instance's doorbells (a runner waits on its role's).
    pub fn doorbells(&self) -> Option<&Doorbells> {
        self.doorbells.as_ref()
    }

    /// The stamp the service `name` was created with, as a sentence.
    fn stamp_of(&self, name: &ServiceName, pattern: MessagingPattern) -> String {
        let details = ipc::Service::details(name, &iceoryx_config(), pattern);
        let Ok(Some(details)) = details else {
            return "an unknown stamp".to_string();
        };
        let attributes = details.static_details.attributes();
        let get = |k: &str| {
            AttributeKey::try_from(k)
                .ok()
                .and_then(|k| attributes.key_value(&k, 0).map(|v| v.to_string()))
                .unwrap_or_else(|| "none".to_string())
        };
        Stamp::describe(&get(MODE_KEY), &get(SCENARIO_KEY))
    }

    /// Opens or creates a service with `open`. Two processes starting together may race to
    /// create a service; the loser sees a transient error and retries. One of another stack
    /// (other attributes) is refused at once.
    fn service<F, E: OpenError>(
        &self,
        name: &str,
        pattern: MessagingPattern,
        open: impl Fn(iceoryx2::service::builder::Builder<Ipc>, &AttributeVerifier) -> Result<F, E>,
    ) -> Result<F, PortError> {
        let error = |source| PortError::Open {
            service: name.to_string(),
            source,
        };
        let service_name: ServiceName = name.try_into().map_err(|e| error(boxed(e)))?;
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            match open(self.node.service_builder(&service_name), &self.verifier) {
                Ok(t) => return Ok(t),
                Err(e) if e.incompatible_attributes() => {
                    return Err(PortError::Mismatch {
                        service: name.to_string(),
                        theirs: self.stamp_of(&service_name, pattern),
                        ours: Stamp::describe(self.stamp.mode.as_str(), &self.stamp.scenario),
                    });
                }
                Err(e) if Instant::now() < deadline => {
                    tracing::debug!(service = name, error = ?e, "service not ready yet, retrying");
                    std::thread::sleep(Duration::from_millis(5));
                }
                Err(e) => return Err(error(boxed(e))),
            }
        }
    }

    fn topic<M: Message>(&self) -> Result<(String, TopicFactory<M>), PortError> {
        let name = self.names.topic_of(M::TOPIC, self.axis);
        let qos = M::TOPIC.qos(self.stamp.mode);
        let factory = self.service(
            &name,
            MessagingPattern::PublishSubscribe,
            |builder, stamp| {
                builder
                    .publish_subscribe::<M>()
                    .max_publishers(qos.max_publishers)
                    .max_subscribers(qos.max_subscribers)
                    .subscriber_max_buffer_size(qos.max_buffer)
                    .history_size(qos.history)
                    .enable_safe_overflow(qos.safe_overflow)
                    .open_or_create_with_attributes(stamp)
            },
        )?;
        Ok((name, factory))
    }

    /// One event for every axis (see [`ServiceNames::state_ready`]): a notifier per bridge
    /// lane, a listener per current-loop (or identification) lane.
    fn state_ready(&self) -> Result<(String, EventFactory), PortError> {
        let name = self.names.state_ready();
        let factory = self.service(&name, MessagingPattern::Event, |builder, stamp| {
            builder
                .event()
                .max_notifiers(MAX_AXES)
                .max_listeners(2 * MAX_AXES)
                .event_id_max_value(0)
                .open_or_create_with_attributes(stamp)
        })?;
        Ok((name, factory))
    }

    /// A subscriber with its concrete type, for the monitor (which is not a node).
    pub fn subscriber_of<M: Message>(&self, depth: usize) -> Result<IpcSubscriber<M>, PortError> {
        let (service, factory) = self.topic::<M>()?;
        let subscriber = factory
            .subscriber_builder()
            .buffer_size(depth)
            .create()
            .map_err(|e| PortError::Create {
                service: service.clone(),
                port: "subscriber",
                what: M::TOPIC.path(),
                source: boxed(e),
            })?;
        Ok(IpcSubscriber {
            subscriber,
            service,
            relay: self
                .doorbells
                .as_ref()
                .zip(self.role)
                .and_then(|(d, role)| d.relay(role, M::TOPIC)),
            _factory: factory,
        })
    }

    /// A publisher with its concrete type.
    pub fn publisher_of<M: Message>(&self) -> Result<IpcPublisher<M>, PortError> {
        let (service, factory) = self.topic::<M>()?;
        let publisher = factory
            .publisher_builder()
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .create()
            .map_err(|e| PortError::Create {
                service: service.clone(),
                port: "publisher",
                what: M::TOPIC.path(),
                source: boxed(e),
            })?;
        Ok(IpcPublisher {
            publisher,
            service,
            ringer: self.doorbells.as_ref().map(|d| d.ringer(M::TOPIC)),
            _factory: factory,
        })
    }
}

impl PortFactory for IpcBus {
    fn set_axis(&mut self, axis: u32) {
        self.axis = axis;
    }

    fn publisher<M: Message>(&mut self) -> Result<Box<dyn Publish<M>>, PortError> {
        Ok(Box::new(self.publisher_of::<M>()?))
    }

    fn subscriber<M: Message>(&mut self, depth: usize) -> Result<Box<dyn Subscribe<M>>, PortError> {
        Ok(Box::new(self.subscriber_of::<M>(depth)?))
    }

    fn notifier(&mut self) -> Result<Box<dyn Notify>, PortError> {
        let (service, factory) = self.state_ready()?;
        let notifier = factory
            .notifier_builder()
            .create()
            .map_err(|e| PortError::Create {
                service: service.clone(),
                port: "notifier",
                what: "state-ready",
                source: boxed(e),
            })?;
        Ok(Box::new(IpcNotifier {
            notifier,
            service,
            _factory: factory,
        }))
    }

    fn listener(&mut self) -> Result<Box<dyn Listen>, PortError> {
        let (service, factory) = self.state_ready()?;
        let listener = factory
            .listener_builder()
            .create()
            .map_err(|e| PortError::Create {
                service: service.clone(),
                port: "listener",
                what: "state-ready",
                source: boxed(e),
            })?;
        Ok(Box::new(IpcListener {
            listener,
            service,
            _factory: factory,
        }))
    }

    fn command_server(&mut self) -> Result<Option<crate::port::AxisServer>, PortError> {
        let (service, factory) = self.command_service()?;
        let server = factory
            .server_builder()
            .create()
            .map_err(|e| PortError::Create {
                service: service.clone(),
                port: "server",
                what: "axis commands",
                source: boxed(e),
            })?;
        Ok(Some(Box::new(IpcCommandServer {
            server,
            held: Vec::with_capacity(COMMANDS_PER_CYCLE),
            deferred: None,
            service,
            _factory: factory,
        })))
    }

    fn presence(&mut self) -> Result<Box<dyn Presence>, PortError> {
        Ok(Box::new(IpcPresence {
            state: self.topic::<DriveState>()?.1,
            command: self.topic::<DriveCommand>()?.1,
            setpoint: self.topic::<TorqueSetpoint>()?.1,
            stats: self.topic::<StatsReport>()?.1,
            reset: self.topic::<ResetRequest>()?.1,
        }))
    }
}

/// A stack's announced scenario that cannot be read ([`IpcBus::announced_scenario`]).
#[derive(Debug, thiserror::Error)]
pub enum AnnouncedError {
    #[error(transparent)]
    Port(#[from] PortError),
    #[error("the stack's announced scenario is not text")]
    NotText,
    #[error("the stack's announced scenario")]
    Scenario(#[from] stepdrive_shared::scenario::ScenarioError),
}

/// Requests an axis's command server holds at most per cycle (more wait for the next).
pub const COMMANDS_PER_CYCLE: usize = 16;

type CommandFactory = iceoryx2::service::port_factory::request_response::PortFactory<
    Ipc,
    AxisRequest,
    (),
    AxisAck,
    (),
>;
type ActiveCommand = iceoryx2::active_request::ActiveRequest<Ipc, AxisRequest, (), AxisAck, ()>;

/// The axis command service's server side: requests taken are held until answered.
pub struct IpcCommandServer {
    server: iceoryx2::port::server::Server<Ipc, AxisRequest, (), AxisAck, ()>,
    /// The last take's requests; `None`: deferred.
    held: Vec<Option<ActiveCommand>>,
    deferred: Option<ActiveCommand>,
    service: String,
    _factory: CommandFactory,
}

impl Serve<AxisRequest, AxisAck> for IpcCommandServer {
    fn take(&mut self, out: &mut [AxisRequest]) -> Result<usize, PortError> {
        self.held.clear();
        let room = out.len().min(self.held.capacity());
        while self.held.len() < room {
            match self.server.receive() {
                Ok(Some(active)) => {
                    out[self.held.len()] = *active.payload();
                    self.held.push(Some(active));
                }
                Ok(None) => break,
                // A client that broke off mid-request, or one holding too many: its
                // requests wait for the next cycle (the loop never blocks on a client).
                Err(e) => {
                    tracing::debug!(service = %self.service, error = ?e, "command receive");
                    break;
                }
            }
        }
        Ok(self.held.len())
    }

    fn pending(&self) -> bool {
        // A connection it could not update is told at the next take.
        self.server.has_requests().unwrap_or(true)
    }

    fn answer(&mut self, answers: &[AxisAck]) -> Result<(), PortError> {
        for (active, ack) in self.held.drain(..).zip(answers) {
            if let Some(active) = active {
                send_answer(&self.service, active, ack);
            }
        }
        Ok(())
    }

    fn defer(&mut self, index: usize) -> bool {
        if self.deferred.is_some() {
            return false;
        }
        self.deferred = self.held.get_mut(index).and_then(Option::take);
        self.deferred.is_some()
    }

    fn answer_deferred(&mut self, answer: &AxisAck) -> Result<bool, PortError> {
        let Some(active) = self.deferred.take() else {
            return Ok(false);
        };
        send_answer(&self.service, active, answer);
        Ok(true)
    }
}

fn send_answer(service: &str, active: ActiveCommand, ack: &AxisAck) {
    // A client that is gone gets no answer; that is its business.
    if let Err(e) = active.send_copy(*ack) {
        tracing::debug!(service = %service, error = ?e, "command answer");
    }
}

/// A client of the axis command service (`stepdrive axis`, the client crate): each
/// request waits for its answer.
pub struct CommandClient {
    client: iceoryx2::port::client::Client<Ipc, AxisRequest, (), AxisAck, ()>,
    service: String,
    /// The position loop's doorbell, rung after each request (`None`: a stack that takes
    /// commands at its ticks only).
    wake: Option<Ringer>,
    _factory: CommandFactory,
}

/// A command the position loop did not answer in time (it is not running, or stalled).
#[derive(Debug, thiserror::Error)]
#[error("the axis did not answer {kind} within {timeout:?}: is the stack's position loop running?")]
pub struct NoAnswer {
    pub kind: &'static str,
    pub timeout: Duration,
}

impl CommandClient {
    /// Whether a server (the position loop) is on the service: a request sent before it
    /// came is never delivered.
    pub fn has_server(&self) -> bool {
        self._factory.dynamic_config().number_of_servers() > 0
    }

    /// Sends `request` and waits up to `timeout` for its answer.
    pub fn request(
        &mut self,
        request: &AxisRequest,
        timeout: Duration,
    ) -> Result<AxisAck, PortError> {
        self.send(request)?.wait(Instant::now() + timeout)
    }

    /// Sends `request` without waiting: its answer is the [`PendingAnswer`]'s to wait for
    /// (the parts of a coordinated move are all sent before any is answered).
    pub fn send(&mut self, request: &AxisRequest) -> Result<PendingAnswer, PortError> {
        let pending = self
            .client
            .send_copy(*request)
            .map_err(|e| PortError::Transfer {
                service: self.service.clone(),
                operation: "send",
                source: boxed(e),
            })?;
        if let Some(bell) = &self.wake {
            bell.ring(None);
        }
        Ok(PendingAnswer {
            pending,
            kind: request.kind,
            service: self.service.clone(),
        })
    }
}

/// A request sent and not yet answered ([`CommandClient::send`]).
pub struct PendingAnswer {
    pending: iceoryx2::pending_response::PendingResponse<Ipc, AxisRequest, (), AxisAck, ()>,
    kind: u32,
    service: String,
}

impl PendingAnswer {
    /// The answer, if it has come.
    pub fn answer(&self) -> Result<Option<AxisAck>, PortError> {
        match self.pending.receive() {
            Ok(answer) => Ok(answer.map(|a| *a.payload())),
            Err(e) => Err(PortError::Transfer {
                service: self.service.clone(),
                operation: "receive",
                source: boxed(e),
            }),
        }
    }

    /// Waits until `deadline` for the answer. Not cut short by SIGINT/SIGTERM: what a
    /// process sends as it stops (a halt after Ctrl-C, a quick stop at shutdown) must be
    /// answered, and the deadline bounds the wait.
    pub fn wait(self, deadline: Instant) -> Result<AxisAck, PortError> {
        let started = Instant::now();
        loop {
            if let Some(ack) = self.answer()? {
                return Ok(ack);
            }
            if Instant::now() >= deadline {
                return Err(self.unanswered(deadline.saturating_duration_since(started)));
            }
            std::thread::sleep(Duration::from_micros(50));
        }
    }

    /// The error of a request not answered within `timeout`.
    pub fn unanswered(&self, timeout: Duration) -> PortError {
        let kind = stepdrive_shared::axis::RequestKind::from_u32(self.kind)
            .map_or("a command", |k| k.name());
        PortError::Transfer {
            service: self.service.clone(),
            operation: "answer",
            source: Box::new(NoAnswer { kind, timeout }),
        }
    }
}

/// What a flood of requests came to ([`CommandClient::flood`]).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Flood {
    /// Requests the flood tried to send.
    pub tried: u64,
    /// Not sent: the service holds at most `max_active_requests_per_client` of a client's
    /// requests at once, and refuses the next one to the client itself.
    pub refused_by_service: u64,
    /// Answered: taken, or refused by the axis with a reason (`too_many` of them because
    /// more came in one tick than the position loop applies).
    pub taken: u64,
    pub refused: u64,
    pub too_many: u64,
    /// Sent and still unanswered when the flood ended (abandoned).
    pub unanswered: u64,
}

/// A flood that does not spin sleeps this long whenever it has sent what fell due: at
/// 100 kHz, bursts of ~10-20 requests (an ordinary task's sleep overshoots by its timer
/// slack).
pub const FLOOD_NAP: Duration = Duration::from_micros(100);

impl CommandClient {
    /// Sends copies of `template` (each with the seq `next_seq` gives) at `rate_hz` for
    /// `duration`, never waiting for an answer: what a runaway or hostile client does. The
    /// answers that come are counted; requests the service will not hold are counted as
    /// refused to the client. With `spin` it polls between sends, burning a CPU as a
    /// runaway client does; without, it naps [`FLOOD_NAP`] whenever it is on schedule and
    /// sends what fell due in a burst, so that what it measures is the command path and
    /// not its own CPU (docs/axis.md has both).
    pub fn flood(
        &mut self,
        template: &AxisRequest,
        mut next_seq: impl FnMut() -> u64,
        rate_hz: f64,
        duration: Duration,
        spin: bool,
    ) -> Result<Flood, PortError> {
        let mut counts = Flood::default();
        let mut pending = Vec::with_capacity(64);
        let started = Instant::now();
        let answers = |pending: &mut Vec<_>, counts: &mut Flood| -> Result<(), PortError> {
            let mut i = 0;
            while i < pending.len() {
                let p: &iceoryx2::pending_response::PendingResponse<
                    Ipc,
                    AxisRequest,
                    (),
                    AxisAck,
                    (),
                > = &pending[i];
                match p.receive() {
                    Ok(Some(answer)) => {
                        let ack: AxisAck = *answer.payload();
                        if ack.taken() {
                            counts.taken += 1;
                        } else {
                            counts.refused += 1;
                            if ack.refusal == stepdrive_shared::axis::Refusal::TooMany as u32 {
                                counts.too_many += 1;
                            }
                        }
                        pending.swap_remove(i);
                    }
                    Ok(None) => i += 1,
                    Err(e) => {
                        return Err(PortError::Transfer {
                            service: self.service.clone(),
                            operation: "receive",
                            source: boxed(e),
                        })
                    }
                }
            }
            Ok(())
        };
        loop {
            let elapsed = started.elapsed();
            if elapsed >= duration || crate::poll::termination_requested() {
                break;
            }
            let due = (elapsed.as_secs_f64() * rate_hz) as u64;
            while counts.tried < due {
                counts.tried += 1;
                let mut r = *template;
                r.seq = next_seq();
                r.publish_time_ns = crate::clock::monotonic_ns();
                match self.client.send_copy(r) {
                    Ok(p) => {
                        pending.push(p);
                        if let Some(bell) = &self.wake {
                            bell.ring(None);
                        }
                    }
                    Err(iceoryx2::port::client::RequestSendError::ExceedsMaxActiveRequests) => {
                        counts.refused_by_service += 1
                    }
                    Err(e) => {
                        return Err(PortError::Transfer {
                            service: self.service.clone(),
                            operation: "send",
                            source: boxed(e),
                        })
                    }
                }
            }
            answers(&mut pending, &mut counts)?;
            if spin {
                std::hint::spin_loop();
            } else {
                std::thread::sleep(FLOOD_NAP);
            }
        }
        // The last answers, for one position-loop period or two.
        let end = Instant::now() + Duration::from_millis(5);
        while !pending.is_empty() && Instant::now() < end {
            answers(&mut pending, &mut counts)?;
        }
        counts.unanswered = pending.len() as u64;
        Ok(counts)
    }
}

impl IpcBus {
    fn command_service(&self) -> Result<(String, CommandFactory), PortError> {
        let name = self.names.topic_of(Topic::AxisCommand, self.axis);
        let factory = self.service(
            &name,
            MessagingPattern::RequestResponse,
            |builder, stamp| {
                builder
                    .request_response::<AxisRequest, AxisAck>()
                    .max_servers(1)
                    .max_clients(8)
                    .max_active_requests_per_client(4)
                    .max_response_buffer_size(4)
                    .enable_safe_overflow_for_responses(true)
                    .open_or_create_with_attributes(stamp)
            },
        )?;
        Ok((name, factory))
    }

    /// The axis command service's client.
    pub fn command_client(&self) -> Result<CommandClient, PortError> {
        let (service, factory) = self.command_service()?;
        let client = factory
            .client_builder()
            .create()
            .map_err(|e| PortError::Create {
                service: service.clone(),
                port: "client",
                what: "axis commands",
                source: boxed(e),
            })?;
        // A stack on the wall clock carries a command out as soon as its position loop is
        // woken for it (a lockstep stack's program is its only source of commands).
        let wake = match self.stamp.mode {
            Mode::Lockstep => None,
            Mode::Realtime | Mode::Hardware => Doorbells::open_existing(&self.names.instance)
                .unwrap_or_else(|e| {
                    tracing::debug!("commands wait for the position loop's tick: {e}");
                    None
                })
                .map(|d| d.ringer_of(Role::PositionLoop)),
        };
        Ok(CommandClient {
            client,
            service,
            wake,
            _factory: factory,
        })
    }
}

/// The blackboard on which the device announces the stack's scenario to anyone attaching;
/// it stands as long as this value lives.
pub struct ScenarioBoard {
    _board: iceoryx2::service::port_factory::blackboard::PortFactory<Ipc, u32>,
}

/// The blackboard's one key.
const BOARD_KEY: u32 = 0;

impl IpcBus {
    /// The stamp as the attributes of a service this process creates.
    fn specifier(&self) -> Result<AttributeSpecifier, BoxedError> {
        let mode_key = AttributeKey::try_from(MODE_KEY).map_err(boxed)?;
        let mode = AttributeValue::try_from(self.stamp.mode.as_str()).map_err(boxed)?;
        let scenario_key = AttributeKey::try_from(SCENARIO_KEY).map_err(boxed)?;
        let scenario = AttributeValue::try_from(self.stamp.scenario.as_str()).map_err(boxed)?;
        AttributeSpecifier::new()
            .define(&mode_key, &mode)
            .and_then(|s| s.define(&scenario_key, &scenario))
            .map_err(boxed)
    }

    fn scenario_board_name(&self) -> Result<ServiceName, PortError> {
        let name = format!("{}/stack/scenario", self.names.instance);
        name.as_str().try_into().map_err(|e| PortError::Open {
            service: name.clone(),
            source: boxed(e),
        })
    }

    /// The device's announcement of `scenario` (its TOML as every process reads it).
    pub fn announce_scenario(&self, scenario: &Scenario) -> Result<ScenarioBoard, PortError> {
        let name = self.scenario_board_name()?;
        let error = |source: BoxedError| PortError::Create {
            service: name.to_string(),
            port: "blackboard",
            what: "stack/scenario",
            source,
        };
        let text = scenario.to_toml_string().map_err(|e| error(boxed(e)))?;
        let value = StackScenario::new(&text).map_err(|e| error(boxed(e)))?;
        let board = self
            .node
            .service_builder(&name)
            .blackboard_creator::<u32>()
            .max_readers(8)
            .add::<StackScenario>(BOARD_KEY, value)
            .create_with_attributes(&self.specifier().map_err(error)?)
            .map_err(|e| error(boxed(e)))?;
        Ok(ScenarioBoard { _board: board })
    }

    /// The scenario the stack on this instance announced, read: `Ok(None)` if it
    /// announces none (yet).
    pub fn announced_scenario(&self) -> Result<Option<Scenario>, AnnouncedError> {
        let Some(announced) = self.stack_scenario()? else {
            return Ok(None);
        };
        let text = announced.text().ok_or(AnnouncedError::NotText)?;
        Ok(Some(Scenario::from_toml_str(text)?))
    }

    /// The scenario the stack on this instance announced, if its device announces one.
    pub fn stack_scenario(&self) -> Result<Option<StackScenario>, PortError> {
        let name = self.scenario_board_name()?;
        let error = |source: BoxedError| PortError::Open {
            service: name.to_string(),
            source,
        };
        let board = match self
            .node
            .service_builder(&name)
            .blackboard_opener::<u32>()
            .open_with_attributes(&self.verifier)
        {
            Ok(b) => b,
            Err(e) => {
                tracing::debug!(error = ?e, "no scenario announced");
                return Ok(None);
            }
        };
        let reader = board
            .reader_builder()
            .create()
            .map_err(|e| error(boxed(e)))?;
        let entry = reader
            .entry::<StackScenario>(&BOARD_KEY)
            .map_err(|e| error(boxed(e)))?;
        Ok(Some(*entry.get()))
    }
}

pub struct IpcPublisher<M: Message> {
    publisher: iceoryx2::port::publisher::Publisher<Ipc, M, ()>,
    service: String,
    /// Lockstep: wakes the readers that sleep for what was published.
    ringer: Option<Ringer>,
    _factory: TopicFactory<M>,
}

impl<M: Message> Publish<M> for IpcPublisher<M> {
    fn publish(&mut self, message: &M) -> Result<(), PortError> {
        self.publisher
            .send_copy(*message)
            .map_err(|e| PortError::Transfer {
                service: self.service.clone(),
                operation: "send",
                source: boxed(e),
            })?;
        if let Some(ringer) = &self.ringer {
            ringer.ring(message.stream_key());
        }
        Ok(())
    }

    fn connect(&mut self) -> Result<(), PortError> {
        self.publisher
            .update_connections()
            .map_err(|e| PortError::Transfer {
                service: self.service.clone(),
                operation: "connect",
                source: boxed(e),
            })
    }
}

pub struct IpcSubscriber<M: Message> {
    subscriber: iceoryx2::port::subscriber::Subscriber<Ipc, M, ()>,
    service: String,
    /// Lockstep: wakes the readers this one wakes for each message it takes
    /// ([`Doorbells::relay`]).
    relay: Option<Ringer>,
    _factory: TopicFactory<M>,
}

impl<M: Message> IpcSubscriber<M> {
    /// Wakes the readers this one wakes for `message` (lockstep).
    fn relay(&self, message: &M) {
        if let Some(relay) = &self.relay {
            relay.ring(message.stream_key());
        }
    }

    fn receive_error(&self, e: iceoryx2::port::ReceiveError) -> PortError {
        PortError::Transfer {
            service: self.service.clone(),
            operation: "receive",
            source: boxed(e),
        }
    }
}

impl<M: Message> Subscribe<M> for IpcSubscriber<M> {
    fn receive(&mut self) -> Result<Option<M>, PortError> {
        match self.subscriber.receive() {
            Ok(Some(sample)) => {
                self.relay(sample.payload());
                Ok(Some(*sample.payload()))
            }
            Ok(None) => Ok(None),
            Err(e) => Err(self.receive_error(e)),
        }
    }

    fn drain(&mut self, f: &mut dyn FnMut(&M)) -> Result<(), PortError> {
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => {
                    self.relay(sample.payload());
                    f(sample.payload())
                }
                Ok(None) => return Ok(()),
                Err(e) => return Err(self.receive_error(e)),
            }
        }
    }
}

struct IpcNotifier {
    notifier: iceoryx2::port::notifier::Notifier<Ipc>,
    service: String,
    _factory: EventFactory,
}

impl Notify for IpcNotifier {
    /// One `sendto` on a Unix socket.
    fn notify(&mut self) -> Result<(), PortError> {
        self.notifier
            .notify()
            .map(|_| ())
            .map_err(|e| PortError::Transfer {
                service: self.service.clone(),
                operation: "notify",
                source: boxed(e),
            })
    }
}

struct IpcListener {
    listener: iceoryx2::port::listener::Listener<Ipc>,
    service: String,
    _factory: EventFactory,
}

impl Listen for IpcListener {
    /// The timeout is jiffy-grained here, the wake-up on an event is not. A signal (SIGCONT
    /// after a stop, SIGTERM) just ends the wait: the caller re-checks its flags.
    fn wait(&mut self, timeout: Duration) -> Result<(), PortError> {
        match self.listener.timed_wait(|_| {}, timeout) {
            Ok(_) | Err(ListenerWaitError::InterruptSignal) => Ok(()),
            Err(e) => Err(PortError::Transfer {
                service: self.service.clone(),
                operation: "event wait",
                source: boxed(e),
            }),
        }
    }
}

struct IpcPresence {
    state: TopicFactory<DriveState>,
    command: TopicFactory<DriveCommand>,
    setpoint: TopicFactory<TorqueSetpoint>,
    stats: TopicFactory<StatsReport>,
    reset: TopicFactory<ResetRequest>,
}

impl IpcPresence {
    fn counts(&self, topic: Topic) -> (usize, usize) {
        fn of<M: Message>(f: &TopicFactory<M>) -> (usize, usize) {
            let c = f.dynamic_config();
            (c.number_of_publishers(), c.number_of_subscribers())
        }
        match topic {
            Topic::State => of(&self.state),
            Topic::Command => of(&self.command),
            Topic::Setpoint => of(&self.setpoint),
            Topic::Stats => of(&self.stats),
            Topic::Reset => of(&self.reset),
            // Nobody waits for these peers.
            Topic::Plan
            | Topic::AxisStatus
            | Topic::AxisStream
            | Topic::AxisCommand
            | Topic::AxisAcks => (0, 0),
        }
    }
}

impl Presence for IpcPresence {
    fn publishers(&self, topic: Topic) -> usize {
        self.counts(topic).0
    }
    fn subscribers(&self, topic: Topic) -> usize {
        self.counts(topic).1
    }
    fn forget_dead(&self) {
        cleanup_dead_nodes();
    }
}

/// Every live iceoryx2 node on this host: its name and its process.
fn alive_nodes() -> Vec<(String, i32)> {
    let mut found = Vec::new();
    let result = Node::<Ipc>::list(&iceoryx_config(), |state| {
        if let NodeState::Alive(view) = state {
            if let Some(details) = iceoryx2::node::NodeView::details(&view) {
                let pid = details.process_id().value();
                found.push((details.name().as_str().to_string(), pid));
            }
        }
        CallbackProgression::Continue
    });
    if let Err(e) = result {
        tracing::warn!(error = ?e, "could not list iceoryx2 nodes");
    }
    found
}

/// The instances that have a live iceoryx2 node of this project (`<instance>.<role>`).
pub fn live_instances() -> std::collections::BTreeSet<String> {
    alive_nodes()
        .into_iter()
        // Role names have no '.'; instance names may.
        .filter_map(|(name, _)| {
            name.rsplit_once('.')
                .map(|(instance, _)| instance.to_string())
        })
        .collect()
}

/// The live iceoryx2 nodes of `instance` whose role is one of `roles` (node names are
/// `<instance>.<role>`), with their processes: a stack's loops, found before another stack
/// is started on the same instance, or to see how they are scheduled.
pub fn live_nodes_with_pids(instance: &str, roles: &[&str]) -> Vec<(String, i32)> {
    let mut found: Vec<(String, i32)> = alive_nodes()
        .into_iter()
        .filter(|(name, _)| {
            name.strip_prefix(instance)
                .and_then(|rest| rest.strip_prefix('.'))
                .is_some_and(|r| roles.contains(&r))
        })
        .collect();
    found.sort();
    found
}

/// [`live_nodes_with_pids`], the names alone.
pub fn live_nodes(instance: &str, roles: &[&str]) -> Vec<String> {
    live_nodes_with_pids(instance, roles)
        .into_iter()
        .map(|(name, _)| name)
        .collect()
}

/// Removes what crashed processes left behind (nodes, ports, shared memory). Call it
/// before starting a stack and after its processes have been reaped.
pub fn cleanup_dead_nodes() -> usize {
    use iceoryx2::node::NodeView;
    use std::sync::atomic::{AtomicBool, Ordering};
    // Every start and every presence check cleans up: the same leftovers would be reported
    // on each, so a process says it once.
    static REPORTED: AtomicBool = AtomicBool::new(false);
    let config = iceoryx_config();
    let (mut removed, mut failed, mut unreadable) = (0, 0, 0);
    let mut last_error = None;
    let result = Node::<Ipc>::list(&config, |state| {
        if let NodeState::Dead(view) = state {
            if view.details().is_none() {
                // Killed while being created or removed: its config is unknown, iceoryx2
                // would guess it (warning that it does), and the removal fails.
                unreadable += 1;
            } else {
                match view.try_remove_stale_resources() {
                    Ok(()) => removed += 1,
                    Err(e) => {
                        failed += 1;
                        last_error = Some(e);
                    }
                }
            }
        }
        CallbackProgression::Continue
    });
    if let Err(e) = result {
        tracing::warn!(error = ?e, "could not list iceoryx2 nodes");
    }
    if failed + unreadable > 0 && !REPORTED.swap(true, Ordering::Relaxed) {
        tracing::debug!(
            failed,
            unreadable,
            error = ?last_error,
            "dead iceoryx2 nodes left by killed processes could not be removed; with no \
             stack running, `rm -rf /tmp/iceoryx2 /dev/shm/iox2_*` clears them"
        );
    }
    removed
}
