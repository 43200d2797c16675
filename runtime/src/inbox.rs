//! A node's input port with its input policy: how it takes a topic is the stack's
//! declaration's ([`stepdrive_shared::stack::Take`]) and the mode's, not the node's. In
//! lockstep every message is taken in order and a gap is the publisher's protocol error; in
//! realtime a reader takes every message that arrived (`Take::Every`) or only the newest
//! (`Take::Newest`), and what it never saw is counted (not by a newest-only reader whose
//! queue holds one: every message overwrites the one before). So a node's `poll` reads the
//! same in every mode.

use crate::error::RunError;
use crate::port::{PortError, PortFactory, Subscribe};
use stepdrive_shared::messages::{DriveCommand, DriveState, TorqueSetpoint};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::Message;
use stepdrive_shared::stack::{NodeDecl, Role, Take};

/// A message with a place in its stream, by which readers check the order.
pub trait Keyed {
    /// Its place: the sample a state is, or a command answers, or a setpoint was computed
    /// from.
    fn key(&self) -> u64;
    /// The stream's keys follow each other by one (states, commands), or only increase
    /// (setpoints: one every N-th sample).
    const CONSECUTIVE: bool;
}

impl Keyed for DriveState {
    fn key(&self) -> u64 {
        self.seq
    }
    const CONSECUTIVE: bool = true;
}

impl Keyed for DriveCommand {
    fn key(&self) -> u64 {
        self.answers_seq
    }
    const CONSECUTIVE: bool = true;
}

impl Keyed for TorqueSetpoint {
    fn key(&self) -> u64 {
        self.from_state_seq
    }
    const CONSECUTIVE: bool = false;
}

/// A message taken, and how many of its stream the reader never took before it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Taken<M> {
    pub message: M,
    pub skipped: u64,
}

/// A lockstep stream out of order: its publisher broke the protocol.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{topic}: expected {expected}, got {got} (lockstep delivers every message in order)")]
pub struct OutOfOrder {
    pub topic: &'static str,
    pub expected: String,
    pub got: u64,
}

/// An input port with its policy. See the module documentation.
pub struct Inbox<M> {
    port: Box<dyn Subscribe<M>>,
    /// The reader, named in an order error.
    reader: Role,
    take: Take,
    /// Lockstep: every message in order, nothing skipped.
    synchronous: bool,
    /// Realtime, newest only, from a queue of one: each message overwrites the one before,
    /// so what it never took it passed over, and nothing is counted.
    one_deep: bool,
    last: Option<u64>,
}

impl<M: Message + Keyed> Inbox<M> {
    /// `node`'s input of `M`'s topic, by its declaration, in `mode`.
    pub fn open(
        f: &mut impl PortFactory,
        node: &NodeDecl,
        mode: Mode,
        depth: usize,
    ) -> Result<Self, PortError> {
        // An undeclared input is taken as every message: the safe reading of a stream.
        let take = node.take(M::TOPIC).unwrap_or(Take::Every);
        let mut inbox = Self::new(f.subscriber(depth)?, node.role, take, mode);
        inbox.one_deep = depth == 1 && take == Take::Newest && !inbox.synchronous;
        Ok(inbox)
    }

    pub fn new(port: Box<dyn Subscribe<M>>, reader: Role, take: Take, mode: Mode) -> Self {
        Self {
            port,
            reader,
            take,
            synchronous: mode == Mode::Lockstep,
            one_deep: false,
            last: None,
        }
    }

    /// Lockstep: the reader must have the message it needs before its cycle runs; nothing
    /// is stale.
    pub fn synchronous(&self) -> bool {
        self.synchronous
    }

    /// The next message by the policy, with how many of its stream never reached the
    /// reader before it (realtime: overwritten or lost; those a `Newest` reader passed over
    /// on purpose are not counted), or an error if the stream is out of order (lockstep). The
    /// first message may be any: a reader that joins a running stack starts from the newest.
    pub fn take(&mut self) -> Result<Option<Taken<M>>, RunError> {
        let newest_only = !self.synchronous && self.take == Take::Newest;
        let Some(mut message) = self.port.receive()? else {
            return Ok(None);
        };
        let mut skipped = self.check(message.key())?;
        if newest_only {
            while let Some(newer) = self.port.receive()? {
                skipped += self.check(newer.key())?;
                message = newer;
            }
        }
        if self.one_deep {
            skipped = 0;
        }
        Ok(Some(Taken { message, skipped }))
    }

    /// Takes `key` as the stream's next: the messages missing before it (realtime), or an
    /// order error (lockstep).
    fn check(&mut self, key: u64) -> Result<u64, RunError> {
        let last = self.last.replace(key);
        let Some(last) = last else {
            return Ok(0);
        };
        if !self.synchronous {
            return Ok(if M::CONSECUTIVE {
                key.saturating_sub(last + 1)
            } else {
                0
            });
        }
        let in_order = if M::CONSECUTIVE {
            key == last + 1
        } else {
            key > last
        };
        if in_order {
            return Ok(0);
        }
        let e = OutOfOrder {
            topic: M::TOPIC.path(),
            expected: if M::CONSECUTIVE {
                format!("{}", last + 1)
            } else {
                format!("after {last}")
            },
            got: key,
        };
        Err(RunError::node(self.reader, e))
    }

    /// The stream starts again (its publisher was replaced): the next message may be any.
    pub fn rejoin(&mut self) {
        self.last = None;
    }

    /// The key of the last message taken.
    pub fn last_key(&self) -> Option<u64> {
        self.last
    }

    /// Every message queued, in place, without order checks (large ones: plans).
    pub fn drain(&mut self, f: &mut dyn FnMut(&M)) -> Result<(), PortError> {
        self.port.drain(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::memory::MemoryBus;
    use crate::port::Publish;
    use stepdrive_shared::stack::{CURRENT_LOOP, POSITION_LOOP};

    fn state(seq: u64) -> DriveState {
        DriveState {
            seq,
            ..Default::default()
        }
    }

    fn pair(mode: Mode, take: Take) -> (Box<dyn Publish<DriveState>>, Inbox<DriveState>) {
        let mut bus = MemoryBus::new(mode);
        let sub = bus.subscriber::<DriveState>(4).expect("subscriber");
        let publisher = bus.publisher::<DriveState>().expect("publisher");
        (publisher, Inbox::new(sub, Role::CurrentLoop, take, mode))
    }

    #[test]
    fn lockstep_takes_every_message_in_order_and_refuses_a_gap() {
        let (mut tx, mut rx) = pair(Mode::Lockstep, Take::Newest);
        for k in [7, 8] {
            tx.publish(&state(k)).expect("publish");
        }
        // The first may be any (a reader joining late); then one by one, newest or not.
        assert_eq!(rx.take().expect("ok").map(|t| t.message.seq), Some(7));
        assert_eq!(rx.take().expect("ok").map(|t| t.message.seq), Some(8));
        tx.publish(&state(10)).expect("publish");
        let err = rx.take().expect_err("a gap");
        let cause = std::error::Error::source(&err).map(|e| e.to_string());
        assert!(
            cause.is_some_and(|c| c.contains("expected 9, got 10")),
            "{err:?}"
        );
        rx.rejoin();
        tx.publish(&state(20)).expect("publish");
        assert_eq!(rx.take().expect("ok").map(|t| t.message.seq), Some(20));
    }

    #[test]
    fn realtime_takes_the_newest_or_every_one_and_counts_what_it_skipped() {
        let (mut tx, mut rx) = pair(Mode::Realtime, Take::Newest);
        for k in 0..3 {
            tx.publish(&state(k)).expect("publish");
        }
        let t = rx.take().expect("ok").expect("a state");
        assert_eq!((t.message.seq, t.skipped), (2, 0));
        for k in 3..6 {
            tx.publish(&state(k)).expect("publish");
        }
        // Passed over on purpose: not counted; never arrived: counted.
        let t = rx.take().expect("ok").expect("a state");
        assert_eq!((t.message.seq, t.skipped), (5, 0));
        tx.publish(&state(9)).expect("publish");
        let t = rx.take().expect("ok").expect("a state");
        assert_eq!((t.message.seq, t.skipped), (9, 3));
        assert!(rx.take().expect("ok").is_none());

        let (mut tx, mut rx) = pair(Mode::Realtime, Take::Every);
        for k in [0, 1, 4] {
            tx.publish(&state(k)).expect("publish");
        }
        let seen: Vec<(u64, u64)> = std::iter::from_fn(|| rx.take().expect("ok"))
            .map(|t| (t.message.seq, t.skipped))
            .collect();
        assert_eq!(seen, [(0, 0), (1, 0), (4, 2)]);
    }

    #[test]
    fn the_policy_comes_from_the_declaration() {
        let mut bus = MemoryBus::new(Mode::Realtime);
        let rx = Inbox::<DriveState>::open(&mut bus, &CURRENT_LOOP, Mode::Realtime, 4);
        assert_eq!(rx.expect("open").take, Take::Newest);
    }

    #[test]
    fn a_newest_reader_with_a_queue_of_one_counts_nothing_it_passed_over() {
        let mut bus = MemoryBus::new(Mode::Realtime);
        let mut rx =
            Inbox::<DriveState>::open(&mut bus, &POSITION_LOOP, Mode::Realtime, 1).expect("open");
        let mut tx = bus.publisher::<DriveState>().expect("publisher");
        for k in 0..10 {
            tx.publish(&state(k)).expect("publish");
        }
        let t = rx.take().expect("ok").expect("a state");
        assert_eq!((t.message.seq, t.skipped), (9, 0));
        assert!(rx.take().expect("ok").is_none(), "the queue held one");
        for k in 10..20 {
            tx.publish(&state(k)).expect("publish");
        }
        let t = rx.take().expect("ok").expect("a state");
        assert_eq!((t.message.seq, t.skipped), (19, 0));
        // In lockstep the same reader still takes every message in order.
        let mut bus = MemoryBus::new(Mode::Lockstep);
        let mut rx =
            Inbox::<DriveState>::open(&mut bus, &POSITION_LOOP, Mode::Lockstep, 4).expect("open");
        let mut tx = bus.publisher::<DriveState>().expect("publisher");
        for k in [3, 4] {
            tx.publish(&state(k)).expect("publish");
        }
        assert_eq!(rx.take().expect("ok").map(|t| t.message.seq), Some(3));
    }
}
