//! A node is one role's logic with a small step interface: it takes inputs from its ports,
//! computes, and publishes outputs. It never reads a clock (the time comes in its [`Cx`]),
//! never waits, and does not know its transport (the ports are injected). Everything around
//! it — start-up, pacing, peer timeouts, the last-sample rule, statistics, shutdown — is the
//! runner's ([`crate::runner`] in a process, [`crate::simulation`] in one thread), written
//! once for every role and every timing mode.

use crate::clock::Clock;
use crate::error::RunError;
pub use stepdrive_shared::stack::Role;
use stepdrive_shared::stats::StatsReport;

/// Lockstep: what a waiting node's next input depends on, so that the runner spins only
/// for an answer that comes within a hand-off.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Awaits {
    /// The peer's answer to what it just published: spin a little, then sleep.
    Next,
    /// Something a position-loop tick away: sleep at once, woken by any message (None) or
    /// from that state on (the position loop sleeps through the states between its ticks).
    Later { state: Option<u64> },
    /// The answer of a node that shares this one's CPU (the current loop waiting for its
    /// tick's setpoint): yield the CPU between polls, so that the other runs now.
    Beside,
}

/// What starts a node's cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pace {
    /// Its input: a cycle runs when [`Node::poll`] says the input is there (lockstep: the
    /// very next message it needs; realtime: a new one).
    Input,
    /// Its own clock: a cycle at each absolute deadline epoch + k·period, with whatever
    /// input is there.
    Clock { period_ns: u64, late: Late },
}

/// What a clock-paced node does when it wakes more than a period late.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Late {
    /// Skip the deadlines it missed (a controller: only the newest input matters).
    Skip,
    /// Pause its time with the stall: the schedule restarts one period after the cycle (a
    /// simulated device, which does not stall, so its time must not run while its process
    /// is held up; catching up would publish samples back to back).
    Pause,
}

/// Start-up: whether the node may begin its cycles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Start {
    /// Not yet: a peer, a drive or a first message is missing ([`Node::awaiting`] says which).
    Waiting,
    /// Go. A clock-paced node gives its first deadline.
    Ready { epoch_ns: Option<u64> },
}

impl Start {
    pub const NOW: Start = Start::Ready { epoch_ns: None };
}

/// What [`Node::poll`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Poll {
    /// The cycle's input is not there yet.
    Pending,
    /// Run the cycle. `fresh`: the peer the node listens to was heard (its liveness);
    /// `skipped`: input messages lost or passed over since the last cycle.
    Ready { fresh: bool, skipped: u64 },
    /// Nothing more to do: the run's last output is out, no cycle.
    Finished,
}

impl Poll {
    pub const READY: Poll = Poll::Ready {
        fresh: true,
        skipped: 0,
    };
}

/// How a cycle ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flow {
    Continue,
    /// The run's last sample has been handled.
    Last,
}

/// What a node sees of the world during one call: the time, its statistics, and when its
/// cycle was due and began.
pub struct Cx<'a> {
    pub(crate) clock: &'a dyn Clock,
    /// Role-specific figures (hops, counters); the runner records the generic ones.
    pub stats: &'a mut StatsReport,
    /// A clock-paced cycle's deadline; 0 for an input-paced one.
    pub deadline_ns: u64,
    /// When the cycle began (the wake-up, or the moment its input was taken).
    pub woke_ns: u64,
    pub(crate) taken_ns: Option<u64>,
    pub(crate) answered_ns: Option<u64>,
}

impl<'a> Cx<'a> {
    pub(crate) fn new(clock: &'a dyn Clock, stats: &'a mut StatsReport) -> Self {
        Self {
            clock,
            stats,
            deadline_ns: 0,
            woke_ns: 0,
            taken_ns: None,
            answered_ns: None,
        }
    }

    pub fn now(&self) -> u64 {
        self.clock.now_ns()
    }

    /// In `poll`: the input was taken at `ns` (when it is known more precisely than the
    /// return of `poll`, e.g. the moment a frame was read).
    pub fn taken_at(&mut self, ns: u64) {
        self.taken_ns = Some(ns);
    }

    /// In `step`: the answer is out now; the cycle's compute time ends here (what follows,
    /// like planning after a command, is not on the critical path). Returns the time.
    pub fn answered(&mut self) -> u64 {
        let now = self.now();
        self.answered_ns = Some(now);
        now
    }
}

/// One role's logic. See the module documentation.
pub trait Node {
    /// The ports it reads and writes, opened before the runner starts.
    type Ports;

    fn role(&self) -> Role;

    fn pace(&self) -> Pace;

    /// Its cycles per second at the nominal rate: statistics go out once per second's worth.
    fn rate_hz(&self) -> f64;

    /// What it is waiting for now, naming the peer ("drive/state from the plant"): the text
    /// of a start-up or peer timeout.
    fn awaiting(&self) -> String;

    /// Polled (without waiting) until it returns `Ready`, within the start-up timeout.
    fn start(&mut self, _ports: &mut Self::Ports, _cx: &mut Cx) -> Result<Start, RunError> {
        Ok(Start::NOW)
    }

    /// Once started: connect the publishers to the subscribers present now, so that the
    /// first real message does not pay for it.
    fn connect(&mut self, _ports: &mut Self::Ports) -> Result<(), RunError> {
        Ok(())
    }

    /// Takes input. Input-paced: `Ready` once the next cycle's input is there. Clock-paced:
    /// called at each deadline; takes what is there and is always `Ready`.
    fn poll(&mut self, ports: &mut Self::Ports, cx: &mut Cx) -> Result<Poll, RunError>;

    /// The cycle: compute and publish.
    fn step(&mut self, ports: &mut Self::Ports, cx: &mut Cx) -> Result<Flow, RunError>;

    /// After the cycle's answers: work that may wait until every axis of a multi-axis
    /// process has sent its own (the current loop's voltage plans, ~8 KB each: stepped
    /// after each axis's command, three axes' plans held the fourth's command 30 µs).
    fn after_answers(&mut self, _ports: &mut Self::Ports, _cx: &mut Cx) -> Result<(), RunError> {
        Ok(())
    }

    /// Input-paced, realtime: when the next input is expected (a `hybrid` wait sleeps until
    /// its margin before it). `None`: unknown, the runner backs off instead.
    fn due_ns(&self) -> Option<u64> {
        None
    }

    /// How long past `due_ns` a spinning wait keeps spinning before it blocks (`None`: until
    /// the input comes).
    fn spin_past_due_ns(&self) -> Option<u64> {
        None
    }

    /// Lockstep: how it waits on its doorbell ([`crate::doorbell`]) for its next input.
    fn awaits(&self) -> Awaits {
        Awaits::Next
    }

    /// Blocks until input may have arrived, or `until_ns` (it is `now_ns`), on whatever the
    /// node can block on (a socket, an event). False if it has nothing to block on: the
    /// runner sleeps.
    fn block(
        &mut self,
        _ports: &mut Self::Ports,
        _now_ns: u64,
        _until_ns: u64,
    ) -> Result<bool, RunError> {
        Ok(false)
    }

    /// Clock-paced, given a doorbell: woken between its ticks by a ring (a client's
    /// command), it may act at once instead of at its next deadline. The runner allows
    /// [`crate::runner::RINGS_PER_PERIOD`] rings a period; the rest wait for the tick.
    fn rung(&mut self, _ports: &mut Self::Ports, _cx: &mut Cx) -> Result<(), RunError> {
        Ok(())
    }

    /// True while it waits for a peer that left to be replaced (a restarted process): the
    /// runner then allows the start-up timeout instead of the peer timeout.
    fn awaiting_rejoin(&self) -> bool {
        false
    }

    /// The faults latched at the end of its run (a device's: the plant's, the bridge's);
    /// zero when healthy or not a device.
    fn latched_fault(&self) -> u32 {
        0
    }

    /// Copies its counters into the statistics before they are published.
    fn report(&self, _stats: &mut StatsReport) {}

    /// On every exit path, success or not: make outputs safe, say goodbye.
    fn stop(&mut self, _ports: &mut Self::Ports, _cx: &mut Cx) {}
}
