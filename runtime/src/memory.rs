//! Ports on in-process queues: the transport of a simulation, where every node runs in one
//! thread ([`crate::simulation`]). Each subscriber has its own queue; a publisher appends to
//! all of them. In lockstep a queue never drops (nobody can wait in one thread, so it grows
//! instead); in realtime it keeps its depth by dropping the oldest, as iceoryx2's safe
//! overflow does.

use crate::port::{Listen, Notify, PortError, PortFactory, Presence, Publish, Subscribe};
use std::any::Any;
use std::cell::RefCell;
use std::collections::{HashMap, VecDeque};
use std::rc::Rc;
use std::time::Duration;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Message, Topic};

struct Queue<M> {
    items: VecDeque<M>,
    /// Most entries kept; `None`: unbounded.
    depth: Option<usize>,
}

type Queues<M> = Rc<RefCell<Vec<Rc<RefCell<Queue<M>>>>>>;

/// A topic of one axis (the statistics: axis 0, one per process).
type Key = (Topic, u32);

#[derive(Default)]
struct Counts {
    publishers: HashMap<Key, usize>,
    subscribers: HashMap<Key, usize>,
}

/// The ports of one simulated stack.
pub struct MemoryBus {
    mode: Mode,
    axis: u32,
    topics: HashMap<Key, Box<dyn Any>>,
    counts: Rc<RefCell<Counts>>,
}

impl MemoryBus {
    pub fn new(mode: Mode) -> Self {
        Self {
            mode,
            axis: 0,
            topics: HashMap::new(),
            counts: Rc::default(),
        }
    }

    fn key(&self, topic: Topic) -> Key {
        (topic, if topic.per_axis() { self.axis } else { 0 })
    }

    fn queues<M: Message>(&mut self) -> Queues<M> {
        let entry = self
            .topics
            .entry(self.key(M::TOPIC))
            .or_insert_with(|| Box::new(Queues::<M>::default()));
        // One message type per topic (the contract's `Message::TOPIC`), so this always holds.
        match entry.downcast_ref::<Queues<M>>() {
            Some(q) => Rc::clone(q),
            None => unreachable!("topic {:?} carries one message type", M::TOPIC),
        }
    }
}

impl PortFactory for MemoryBus {
    fn set_axis(&mut self, axis: u32) {
        self.axis = axis;
    }

    fn publisher<M: Message>(&mut self) -> Result<Box<dyn Publish<M>>, PortError> {
        let key = self.key(M::TOPIC);
        *self.counts.borrow_mut().publishers.entry(key).or_default() += 1;
        Ok(Box::new(MemoryPublisher {
            queues: self.queues::<M>(),
        }))
    }

    fn subscriber<M: Message>(&mut self, depth: usize) -> Result<Box<dyn Subscribe<M>>, PortError> {
        let key = self.key(M::TOPIC);
        *self.counts.borrow_mut().subscribers.entry(key).or_default() += 1;
        let overwrite = M::TOPIC.qos(self.mode).safe_overflow;
        let queue = Rc::new(RefCell::new(Queue {
            items: VecDeque::with_capacity(depth),
            depth: overwrite.then_some(depth.max(1)),
        }));
        self.queues::<M>().borrow_mut().push(Rc::clone(&queue));
        Ok(Box::new(MemorySubscriber { queue }))
    }

    fn notifier(&mut self) -> Result<Box<dyn Notify>, PortError> {
        Ok(Box::new(Nothing))
    }

    fn listener(&mut self) -> Result<Box<dyn Listen>, PortError> {
        Ok(Box::new(Nothing))
    }

    fn command_server(&mut self) -> Result<Option<crate::port::AxisServer>, PortError> {
        Ok(None)
    }

    fn presence(&mut self) -> Result<Box<dyn Presence>, PortError> {
        Ok(Box::new(MemoryPresence {
            counts: Rc::clone(&self.counts),
            axis: self.axis,
        }))
    }
}

struct MemoryPublisher<M> {
    queues: Queues<M>,
}

impl<M: Message> Publish<M> for MemoryPublisher<M> {
    fn publish(&mut self, message: &M) -> Result<(), PortError> {
        for queue in self.queues.borrow().iter() {
            let mut q = queue.borrow_mut();
            if q.depth.is_some_and(|d| q.items.len() >= d) {
                q.items.pop_front();
            }
            q.items.push_back(*message);
        }
        Ok(())
    }
}

struct MemorySubscriber<M> {
    queue: Rc<RefCell<Queue<M>>>,
}

impl<M: Message> Subscribe<M> for MemorySubscriber<M> {
    fn receive(&mut self) -> Result<Option<M>, PortError> {
        Ok(self.queue.borrow_mut().items.pop_front())
    }

    fn drain(&mut self, f: &mut dyn FnMut(&M)) -> Result<(), PortError> {
        while let Some(m) = self.receive()? {
            f(&m);
        }
        Ok(())
    }
}

/// Events need no transport in one thread: whoever waits is polled anyway.
struct Nothing;

impl Notify for Nothing {
    fn notify(&mut self) -> Result<(), PortError> {
        Ok(())
    }
}

impl Listen for Nothing {
    fn wait(&mut self, _timeout: Duration) -> Result<(), PortError> {
        Ok(())
    }
}

struct MemoryPresence {
    counts: Rc<RefCell<Counts>>,
    axis: u32,
}

impl MemoryPresence {
    fn key(&self, topic: Topic) -> Key {
        (topic, if topic.per_axis() { self.axis } else { 0 })
    }
}

impl Presence for MemoryPresence {
    fn publishers(&self, topic: Topic) -> usize {
        let key = self.key(topic);
        self.counts
            .borrow()
            .publishers
            .get(&key)
            .copied()
            .unwrap_or(0)
    }
    fn subscribers(&self, topic: Topic) -> usize {
        let key = self.key(topic);
        self.counts
            .borrow()
            .subscribers
            .get(&key)
            .copied()
            .unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_shared::DriveState;

    fn state(seq: u64) -> DriveState {
        DriveState {
            seq,
            ..Default::default()
        }
    }

    #[test]
    fn every_subscriber_gets_every_message_in_order_and_lockstep_never_drops() {
        let mut bus = MemoryBus::new(Mode::Lockstep);
        let mut a = bus.subscriber::<DriveState>(2).unwrap();
        let mut tx = bus.publisher::<DriveState>().unwrap();
        let mut b = bus.subscriber::<DriveState>(2).unwrap();
        for k in 0..5 {
            tx.publish(&state(k)).unwrap();
        }
        for sub in [&mut a, &mut b] {
            let mut seen = Vec::new();
            sub.drain(&mut |s| seen.push(s.seq)).unwrap();
            assert_eq!(seen, [0, 1, 2, 3, 4]);
        }
        let p = bus.presence().unwrap();
        assert_eq!(
            (p.publishers(Topic::State), p.subscribers(Topic::State)),
            (1, 2)
        );
        assert_eq!(p.publishers(Topic::Command), 0);
    }

    #[test]
    fn realtime_queues_keep_their_depth_by_dropping_the_oldest() {
        let mut bus = MemoryBus::new(Mode::Realtime);
        let mut rx = bus.subscriber::<DriveState>(3).unwrap();
        let mut tx = bus.publisher::<DriveState>().unwrap();
        for k in 0..10 {
            tx.publish(&state(k)).unwrap();
        }
        assert_eq!(rx.receive().unwrap().map(|s| s.seq), Some(7));
        assert_eq!(rx.newest().unwrap().map(|s| s.seq), Some(9));
        assert_eq!(rx.receive().unwrap(), None);
    }
}
