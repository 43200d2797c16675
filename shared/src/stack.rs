//! The stack, declared once: who its nodes are ([`Role`]), the topics each reads and writes
//! and how it takes what it reads ([`NodeDecl`]), and which nodes run for a purpose in a mode
//! ([`stack`]). The launcher, the role sub-commands, the in-process simulation, the ports'
//! input policies and the supervisor derive from this declaration; none of them lists the
//! stack again.
//!
//! Each node is one process today; each serves one axis. Several axes per process (one
//! process per rate, N axes inside) will add an axis count to the declaration, not more
//! nodes.

use crate::scenario::Mode;
use crate::services::Topic;

/// Who a node or process is. One spelling: [`Role::id`] names it to programs (its
/// sub-command, its iceoryx2 node, its deployment table, its JSON), [`Role::title`] to
/// people (logs, headlines).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// The simulated plant: the motor model behind the stack's contract.
    Plant,
    /// The plant's stand-in for real hardware: a bridge to a drive.
    Bridge,
    CurrentLoop,
    PositionLoop,
    /// A stand-in drive board (the motor model behind the wire protocol).
    EmulatedDrive,
    /// The identification sequence, in the current loop's place.
    Identify,
    /// The supervisor: metrics, recording, reports.
    Monitor,
    /// A measurement tool outside the stack (a transport baseline).
    Tool(&'static str),
}

/// The place a node takes in a stack: what its statistics stand for in a report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Slot {
    /// The plant or the bridge: the one that touches the motor and paces the samples.
    Device,
    /// The current loop, or the identification in its place.
    Current,
    Position,
}

impl Slot {
    pub const ALL: [Slot; 3] = [Slot::Device, Slot::Current, Slot::Position];

    pub fn index(self) -> usize {
        match self {
            Slot::Device => 0,
            Slot::Current => 1,
            Slot::Position => 2,
        }
    }
}

impl Role {
    /// The name programs use: `current-loop`.
    pub fn id(self) -> &'static str {
        match self {
            Role::Plant => "plant",
            Role::Bridge => "bridge",
            Role::CurrentLoop => "current-loop",
            Role::PositionLoop => "position-loop",
            Role::EmulatedDrive => "emulated-drive",
            Role::Identify => "identify",
            Role::Monitor => "monitor",
            Role::Tool(name) => name,
        }
    }

    /// The name people read: `current loop`.
    pub fn title(self) -> &'static str {
        match self {
            Role::Plant => "plant",
            Role::Bridge => "bridge",
            Role::CurrentLoop => "current loop",
            Role::PositionLoop => "position loop",
            Role::EmulatedDrive => "emulated drive",
            Role::Identify => "identification",
            Role::Monitor => "monitor",
            Role::Tool(name) => name,
        }
    }

    /// The `stepdrive` sub-command that runs it as a process, if one does.
    pub fn command(self) -> Option<&'static str> {
        match self {
            Role::Plant => Some("plant"),
            Role::Bridge => Some("bridge"),
            Role::CurrentLoop => Some("current-loop"),
            Role::PositionLoop => Some("position-loop"),
            Role::EmulatedDrive => Some("emulate-drive"),
            // `identify` is the user's command that launches it.
            Role::Identify => Some("identify-node"),
            // A tool outside the stack is its own sub-command.
            Role::Tool(name) => Some(name),
            Role::Monitor => None,
        }
    }

    /// The number its statistics reports carry (`StatsReport::role`).
    pub fn code(self) -> u32 {
        match self {
            Role::Plant => 0,
            Role::CurrentLoop => 1,
            Role::PositionLoop => 2,
            Role::Bridge => 3,
            Role::EmulatedDrive => 4,
            Role::Identify => 5,
            Role::Monitor => 6,
            Role::Tool(_) => 7,
        }
    }

    /// The role a statistics report names; tools share one code.
    pub fn from_code(code: u32) -> Option<Role> {
        [
            Role::Plant,
            Role::CurrentLoop,
            Role::PositionLoop,
            Role::Bridge,
            Role::EmulatedDrive,
            Role::Identify,
            Role::Monitor,
        ]
        .into_iter()
        .find(|r| r.code() == code)
    }

    /// Its place in a stack, if it takes one.
    pub fn slot(self) -> Option<Slot> {
        match self {
            Role::Plant | Role::Bridge => Some(Slot::Device),
            Role::CurrentLoop | Role::Identify => Some(Slot::Current),
            Role::PositionLoop => Some(Slot::Position),
            Role::EmulatedDrive | Role::Monitor | Role::Tool(_) => None,
        }
    }
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.title())
    }
}

/// How a node takes the messages of a topic it reads. In lockstep every reader takes every
/// message in order (queues never drop; a gap is the publisher's protocol error); the policy
/// says what it takes in realtime.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Take {
    /// Every message that arrived, oldest first; one that never arrived is counted lost.
    Every,
    /// The newest; older ones are stale for a loop on the wall clock, and counted skipped.
    Newest,
}

/// One topic a node reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Input {
    pub topic: Topic,
    pub take: Take,
}

const fn every(topic: Topic) -> Input {
    Input {
        topic,
        take: Take::Every,
    }
}

const fn newest(topic: Topic) -> Input {
    Input {
        topic,
        take: Take::Newest,
    }
}

/// One node: who it is, what it reads (and how), what it writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NodeDecl {
    pub role: Role,
    pub reads: &'static [Input],
    pub writes: &'static [Topic],
}

impl NodeDecl {
    /// How this node takes `topic`.
    pub fn take(&self, topic: Topic) -> Option<Take> {
        self.reads.iter().find(|i| i.topic == topic).map(|i| i.take)
    }

    pub fn reads(&self, topic: Topic) -> bool {
        self.take(topic).is_some()
    }

    pub fn writes(&self, topic: Topic) -> bool {
        self.writes.contains(&topic)
    }
}

/// The simulated plant: publishes the state at each sample, applies every command in its
/// period (a late one is discarded), keeps the freshest plan, takes reset requests.
pub const PLANT: NodeDecl = NodeDecl {
    role: Role::Plant,
    reads: &[
        every(Topic::Command),
        every(Topic::Plan),
        every(Topic::Reset),
    ],
    writes: &[Topic::State, Topic::Stats],
};

/// The bridge: the plant's contract toward the stack, a drive's wire protocol toward the
/// drive (it raises the state-ready event after each state, too).
pub const BRIDGE: NodeDecl = NodeDecl {
    role: Role::Bridge,
    reads: PLANT.reads,
    writes: PLANT.writes,
};

/// The current loop: answers the newest state with the newest setpoint.
pub const CURRENT_LOOP: NodeDecl = NodeDecl {
    role: Role::CurrentLoop,
    reads: &[newest(Topic::State), newest(Topic::Setpoint)],
    writes: &[Topic::Command, Topic::Plan, Topic::Stats],
};

/// The position loop: a tick on its own clock with the newest state.
pub const POSITION_LOOP: NodeDecl = NodeDecl {
    role: Role::PositionLoop,
    reads: &[newest(Topic::State)],
    writes: &[Topic::Setpoint, Topic::Stats],
};

/// The identification sequence, in the current loop's place (no position loop).
pub const IDENTIFY: NodeDecl = NodeDecl {
    role: Role::Identify,
    reads: &[newest(Topic::State)],
    writes: &[Topic::Command, Topic::Plan, Topic::Stats],
};

/// Lockstep: who wakes `reader` for a message of `topic` it sleeps for, when not the
/// message's publisher. The position loop sleeps from tick to tick; the current loop takes
/// every state as it comes, so it wakes the position loop for its tick's, on its own CPU
/// (the two share one: `stepdrive_runtime::doorbell::placement`). The plant ringing it
/// instead woke it on the plant's CPU or another busy one, where a wake-up costs ~17 µs
/// here against ~4 µs on the waker's own, and at every tick the current loop waits for
/// that setpoint.
pub fn woken_by(reader: Role, topic: Topic) -> Option<Role> {
    match (reader, topic) {
        (Role::PositionLoop, Topic::State) => Some(Role::CurrentLoop),
        _ => None,
    }
}

/// Lockstep: whether `role` wakes another reader or is woken by one ([`woken_by`]).
pub fn wakes_or_is_woken(role: Role) -> bool {
    NODES.iter().any(|n| {
        n.reads.iter().any(|i| match woken_by(n.role, i.topic) {
            Some(waker) => waker == role || n.role == role,
            None => false,
        })
    })
}

/// Every node a stack's processes can run (the monitor is not one: it never blocks a
/// peer).
pub const NODES: [NodeDecl; 5] = [PLANT, BRIDGE, CURRENT_LOOP, POSITION_LOOP, IDENTIFY];

/// The supervisor: every state (it may fall behind in realtime: what it missed is counted),
/// and, when it records, every setpoint, command and plan.
pub const MONITOR: NodeDecl = NodeDecl {
    role: Role::Monitor,
    reads: &[
        every(Topic::State),
        every(Topic::Stats),
        every(Topic::Setpoint),
        every(Topic::Command),
        every(Topic::Plan),
    ],
    writes: &[],
};

/// What a stack is started for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Purpose {
    /// The position and current loops control the motor.
    Control,
    /// The identification sequence drives the motor alone.
    Identify,
}

/// A stack: its nodes, one process each, in the order they are started (the device first:
/// it waits for its peers).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stack {
    pub mode: Mode,
    pub purpose: Purpose,
    pub nodes: Vec<NodeDecl>,
}

/// The stack for `purpose` in `mode`: the plant (the bridge in hardware mode), then the
/// position loop and the current loop, or the identification alone.
pub fn stack(mode: Mode, purpose: Purpose) -> Stack {
    let device = match mode {
        Mode::Hardware => BRIDGE,
        Mode::Lockstep | Mode::Realtime => PLANT,
    };
    let nodes = match purpose {
        Purpose::Control => vec![device, POSITION_LOOP, CURRENT_LOOP],
        Purpose::Identify => vec![device, IDENTIFY],
    };
    Stack {
        mode,
        purpose,
        nodes,
    }
}

impl Stack {
    /// The node in `role`'s place.
    pub fn node(&self, role: Role) -> Option<&NodeDecl> {
        self.nodes.iter().find(|n| n.role == role)
    }

    /// The node in `slot`.
    pub fn in_slot(&self, slot: Slot) -> Option<&NodeDecl> {
        self.nodes.iter().find(|n| n.role.slot() == Some(slot))
    }

    /// The device: the plant or the bridge.
    pub fn device(&self) -> &NodeDecl {
        match self.in_slot(Slot::Device) {
            Some(d) => d,
            None => unreachable!("every stack has a device"),
        }
    }

    /// How many of its nodes read `topic` (the device waits for them before its first
    /// sample), a monitor not counted.
    pub fn readers(&self, topic: Topic) -> usize {
        self.nodes.iter().filter(|n| n.reads(topic)).count()
    }

    /// Whether one of its nodes publishes `topic`.
    pub fn has_writer(&self, topic: Topic) -> bool {
        self.nodes.iter().any(|n| n.writes(topic))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_role_has_one_code_and_names_it_back() {
        let roles = [
            Role::Plant,
            Role::Bridge,
            Role::CurrentLoop,
            Role::PositionLoop,
            Role::EmulatedDrive,
            Role::Identify,
            Role::Monitor,
        ];
        for r in roles {
            assert_eq!(Role::from_code(r.code()), Some(r));
            assert!(!r.id().contains(' '), "{}", r.id());
        }
        let mut codes: Vec<u32> = roles.iter().map(|r| r.code()).collect();
        codes.dedup();
        assert_eq!(codes.len(), roles.len());
    }

    /// Every topic a node reads has a writer in the stack (the monitor's and the reset's
    /// come from outside), and every slot is taken once.
    #[test]
    fn every_stack_is_closed_and_fills_its_slots() {
        for mode in [Mode::Lockstep, Mode::Realtime, Mode::Hardware] {
            for purpose in [Purpose::Control, Purpose::Identify] {
                let s = stack(mode, purpose);
                for n in &s.nodes {
                    for i in n.reads {
                        let outside = matches!(i.topic, Topic::Reset | Topic::Plan);
                        assert!(
                            outside || s.has_writer(i.topic),
                            "{mode:?} {purpose:?}: nobody writes {:?} for the {}",
                            i.topic,
                            n.role
                        );
                    }
                }
                assert_eq!(s.device().role == Role::Bridge, mode == Mode::Hardware);
                assert!(s.in_slot(Slot::Current).is_some());
                let position = s.in_slot(Slot::Position).is_some();
                assert_eq!(position, purpose == Purpose::Control);
                assert_eq!(s.readers(Topic::State), s.nodes.len() - 1);
            }
        }
    }

    /// A reader woken by another is woken by one that reads the same topic in the same
    /// stack (else nobody would ever ring it); the position loop is the one, for states.
    #[test]
    fn a_reader_woken_by_another_shares_its_stack_and_topic() {
        let mut relayed = Vec::new();
        for n in NODES {
            for i in n.reads {
                let Some(waker) = woken_by(n.role, i.topic) else {
                    continue;
                };
                relayed.push((n.role, i.topic, waker));
                let s = stack(Mode::Lockstep, Purpose::Control);
                let w = s
                    .node(waker)
                    .expect("the waker runs where the woken one does");
                assert!(
                    w.reads(i.topic),
                    "the {waker} wakes the {} for {:?} it never takes",
                    n.role,
                    i.topic
                );
                assert_ne!(waker, n.role);
            }
        }
        assert_eq!(
            relayed,
            [(Role::PositionLoop, Topic::State, Role::CurrentLoop)]
        );
        assert!(wakes_or_is_woken(Role::CurrentLoop) && wakes_or_is_woken(Role::PositionLoop));
        assert!(!wakes_or_is_woken(Role::Plant) && !wakes_or_is_woken(Role::Identify));
    }
}
