//! Ports: how a node sends and receives, without knowing over what. [`crate::ipc`] implements
//! them on iceoryx2 shared memory between processes, [`crate::memory`] on in-process queues
//! for simulation and tests. A node holds its ports as trait objects, opened once at
//! start-up; sending and receiving never allocate.

use std::time::Duration;
use stepdrive_shared::services::{Message, Topic};

/// Why a port could not be opened or used.
#[derive(Debug, thiserror::Error)]
pub enum PortError {
    #[error(transparent)]
    BadInstance(#[from] stepdrive_shared::services::BadInstance),
    #[error("cannot create this process's iceoryx2 node `{node}`")]
    Node {
        node: String,
        #[source]
        source: BoxedError,
    },
    #[error("service `{service}` belongs to a stack with {theirs}; this process has {ours}: every process of an instance must run the same mode and scenario")]
    Mismatch {
        service: String,
        theirs: String,
        ours: String,
    },
    #[error("no stack runs on instance `{instance}` (no `{instance}/drive/state` service)")]
    NoStack { instance: String },
    #[error("cannot open service `{service}`")]
    Open {
        service: String,
        #[source]
        source: BoxedError,
    },
    #[error(
        "cannot create the {what} {port} of `{service}` (is another one running on this instance?)"
    )]
    Create {
        service: String,
        port: &'static str,
        what: &'static str,
        #[source]
        source: BoxedError,
    },
    #[error(transparent)]
    Doorbell(#[from] crate::doorbell::DoorbellError),
    #[error("{operation} on `{service}` failed")]
    Transfer {
        service: String,
        operation: &'static str,
        #[source]
        source: BoxedError,
    },
}

pub type BoxedError = Box<dyn std::error::Error + Send + Sync>;

/// Sends messages of one topic.
pub trait Publish<M> {
    /// Publishes a copy of `message` (the messages are small; a copy into the loaned
    /// shared-memory slot is what zero-copy means here).
    fn publish(&mut self, message: &M) -> Result<(), PortError>;
    /// Establishes the connections to the subscribers present now, so that the first real
    /// message does not pay for them.
    fn connect(&mut self) -> Result<(), PortError> {
        Ok(())
    }
}

/// Receives messages of one topic, oldest first.
pub trait Subscribe<M> {
    /// The next queued message, copied out.
    fn receive(&mut self) -> Result<Option<M>, PortError>;
    /// Hands every queued message to `f` in place (for large ones).
    fn drain(&mut self, f: &mut dyn FnMut(&M)) -> Result<(), PortError>;
    /// The newest queued message; older ones are dropped (stale for a realtime loop).
    fn newest(&mut self) -> Result<Option<M>, PortError> {
        let mut newest = None;
        while let Some(m) = self.receive()? {
            newest = Some(m);
        }
        Ok(newest)
    }
}

/// The server side of a request-response service: takes requests and answers each, never
/// waiting. Requests taken are held until answered, so that an answer can come after the
/// work it reports on (an axis command's, after the setpoint that carries it out).
pub trait Serve<Req, Resp> {
    /// Takes up to `out.len()` queued requests into `out`; returns how many.
    fn take(&mut self, out: &mut [Req]) -> Result<usize, PortError>;
    /// Whether a request is waiting (without taking it).
    fn pending(&self) -> bool {
        true
    }
    /// Answers the requests of the last [`Self::take`], in order (a deferred one's answer
    /// is skipped).
    fn answer(&mut self, answers: &[Resp]) -> Result<(), PortError>;
    /// Keeps the `index`-th request of the last [`Self::take`] unanswered past it, to be
    /// answered by [`Self::answer_deferred`] (an axis's part of a coordinated move waits
    /// for its partners). One at a time: false, and nothing kept, while one is kept.
    fn defer(&mut self, index: usize) -> bool;
    /// Answers the request kept by [`Self::defer`]; false if none is kept.
    fn answer_deferred(&mut self, answer: &Resp) -> Result<bool, PortError>;
}

/// Raises the "a state was published" event (hardware mode).
pub trait Notify {
    fn notify(&mut self) -> Result<(), PortError>;
}

/// Waits for that event.
pub trait Listen {
    /// Blocks until the event is raised or `timeout` passes, and consumes what is pending.
    /// A signal just ends the wait.
    fn wait(&mut self, timeout: Duration) -> Result<(), PortError>;
}

/// Who else is attached to the stack: a node that must not start before its peers asks.
pub trait Presence {
    fn publishers(&self, topic: Topic) -> usize;
    fn subscribers(&self, topic: Topic) -> usize;
    /// Removes the ports of peers that died without leaving (a SIGKILL), so that the counts
    /// above stop counting them. Not cheap: call it rarely.
    fn forget_dead(&self) {}
}

/// Opens ports: one implementation per transport, so a role's ports are built the same way
/// for a process and for a simulation.
pub trait PortFactory {
    /// The axis whose ports the next calls open (a multi-axis stack's topics are per axis:
    /// [`Topic::path_of`]); 0 until set.
    fn set_axis(&mut self, axis: u32);
    fn publisher<M: Message>(&mut self) -> Result<Box<dyn Publish<M>>, PortError>;
    /// `depth`: messages queued before the oldest is overwritten (realtime) or the
    /// publisher waits (lockstep).
    fn subscriber<M: Message>(&mut self, depth: usize) -> Result<Box<dyn Subscribe<M>>, PortError>;
    fn notifier(&mut self) -> Result<Box<dyn Notify>, PortError>;
    fn listener(&mut self) -> Result<Box<dyn Listen>, PortError>;
    fn presence(&mut self) -> Result<Box<dyn Presence>, PortError>;
    /// The axis command service's server (none in a simulation: its commands come from
    /// the scenario's program).
    fn command_server(&mut self) -> Result<Option<AxisServer>, PortError>;
}

/// The axis command service's server.
pub type AxisServer =
    Box<dyn Serve<stepdrive_shared::axis::AxisRequest, stepdrive_shared::axis::AxisAck>>;
