//! Service names and the settings every process must open them with. iceoryx2 treats an
//! opener's settings as minimum requirements, so they are part of the contract: they live
//! here, once, and the port implementations (`stepdrive-runtime`) only read them.

use crate::axis::{AxisAck, AxisStatus, AxisStreamPoint};
use crate::messages::{DriveCommand, DrivePlan, DriveState, ResetRequest, TorqueSetpoint};
use crate::scenario::Mode;
use crate::stats::StatsReport;
#[cfg(feature = "ipc")]
use iceoryx2::prelude::ZeroCopySend;
use std::fmt::Debug;

pub const DEFAULT_INSTANCE: &str = "stepdrive";

/// The longest instance name (service names under it stay within iceoryx2's limit).
pub const INSTANCE_MAX_LEN: usize = 48;

/// Checks an instance name before anything uses it: it names shared-memory services and
/// the run's files in the temporary directory, so it is one path component of ASCII
/// letters, digits, `.`, `-` and `_` (at most [`INSTANCE_MAX_LEN`]; not starting with `-`,
/// not `.` or `..`).
/// Returns it, or why not (a clap `value_parser`).
pub fn instance_name(name: &str) -> Result<String, String> {
    let ok_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_');
    if name.is_empty() {
        return Err("an instance name cannot be empty".to_string());
    }
    if name.len() > INSTANCE_MAX_LEN {
        return Err(format!(
            "an instance name has at most {INSTANCE_MAX_LEN} characters ({} given)",
            name.len()
        ));
    }
    if let Some(c) = name.chars().find(|&c| !ok_char(c)) {
        return Err(format!(
            "{c:?} in instance name {name:?}: use ASCII letters, digits, '.', '-' and '_' \
             (it names shared-memory services and files, and is no path)"
        ));
    }
    if name.starts_with('-') {
        return Err(format!("instance name {name:?} starts with '-'"));
    }
    if name.chars().all(|c| c == '.') {
        return Err(format!("instance name {name:?} is a directory's name"));
    }
    Ok(name.to_string())
}

/// Subscriber queue depths. The monitor's is deep because in lockstep it must see every
/// sample (the publisher waits for it rather than drop one) while it drains at a low rate.
pub const MONITOR_BUFFER: usize = 8192;
pub const LOOP_BUFFER: usize = 16;

/// Why a name is no instance name ([`instance_name`]'s reason).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct BadInstance(pub String);

/// The publish-subscribe topics of one stack.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Topic {
    /// Plant → all, every sample.
    State,
    /// Current loop → plant, every sample.
    Command,
    /// Current loop → plant, after every tenth command and after a gap (realtime): the
    /// voltage plan.
    Plan,
    /// Position loop → current loop, every tick.
    Setpoint,
    /// Every loop → monitor: timing statistics, ~1 Hz and at exit.
    Stats,
    /// Anyone → plant or bridge: clear latched faults (`stepdrive reset`).
    Reset,
    /// Position loop → everyone, every tick: the axis's status.
    AxisStatus,
    /// A streaming client → position loop: cyclic synchronous position points.
    AxisStream,
    /// Clients → position loop: axis commands, each answered (request-response).
    AxisCommand,
    /// Position loop → recorders: every command's answer, with the command.
    AxisAcks,
}

impl Topic {
    /// The name under the instance, as in `<instance>/drive/state`.
    pub fn path(self) -> &'static str {
        match self {
            Topic::State => "drive/state",
            Topic::Command => "drive/command",
            Topic::Plan => "drive/plan",
            Topic::Setpoint => "control/setpoint",
            Topic::Stats => "monitor/stats",
            Topic::Reset => "control/reset",
            Topic::AxisStatus => "axis/0/status",
            Topic::AxisStream => "axis/0/stream",
            Topic::AxisCommand => "axis/0/command",
            Topic::AxisAcks => "axis/0/acks",
        }
    }

    /// Whether each axis of a multi-axis stack has its own (every topic but the statistics,
    /// which are one per process).
    pub fn per_axis(self) -> bool {
        self != Topic::Stats
    }

    /// The name under the instance for `axis`: axis 0's is [`Self::path`] (a one-axis
    /// stack's names are unchanged); another axis's loop topics are under `axis/<n>/`
    /// (`axis/2/drive/state`) and its axis topics name it (`axis/2/status`).
    pub fn path_of(self, axis: u32) -> std::borrow::Cow<'static, str> {
        let path = self.path();
        if axis == 0 || !self.per_axis() {
            return path.into();
        }
        match path.strip_prefix("axis/0/") {
            Some(rest) => format!("axis/{axis}/{rest}").into(),
            None => format!("axis/{axis}/{path}").into(),
        }
    }

    /// The settings of this topic in `mode`; the same for every opener.
    pub fn qos(self, mode: Mode) -> Qos {
        // Lockstep: a full queue makes the publisher wait and nothing is ever dropped.
        // Realtime: the oldest queued sample is overwritten and nobody blocks the plant.
        let safe_overflow = mode != Mode::Lockstep;
        match self {
            // One writer per control topic; room for the loops, a monitor and two tools. Every
            // subscriber slot costs the publisher MONITOR_BUFFER samples of shared memory.
            Topic::State | Topic::Command | Topic::Setpoint => Qos {
                max_publishers: 1,
                max_subscribers: 5,
                max_buffer: MONITOR_BUFFER,
                history: usize::from(self != Topic::Command),
                safe_overflow,
            },
            // Only the plant reads plans, and only the newest matters: a short queue keeps
            // the ~8 KB samples' shared memory small.
            Topic::Plan => Qos {
                max_publishers: 1,
                max_subscribers: 2,
                max_buffer: LOOP_BUFFER,
                history: 0,
                safe_overflow: true,
            },
            // A report is ~90 KB: keep the queues short.
            Topic::Stats => Qos {
                max_publishers: 4,
                max_subscribers: 2,
                max_buffer: 4,
                history: 0,
                safe_overflow: true,
            },
            // Every tick; readers want the newest (a late joiner gets it at once). The acks
            // are rare, but a recorder must see each.
            Topic::AxisStatus | Topic::AxisAcks => Qos {
                max_publishers: 1,
                max_subscribers: 8,
                max_buffer: MONITOR_BUFFER,
                history: 1,
                safe_overflow: true,
            },
            // Up to 2 kHz from a client; the position loop takes them every tick. A client
            // that writes faster than that loses its oldest points (the axis counts the gap
            // in time as an underrun).
            Topic::AxisStream => Qos {
                max_publishers: 4,
                max_subscribers: 2,
                max_buffer: 256,
                history: 0,
                safe_overflow: true,
            },
            // Rare, small, from any tool; the plant takes them at its pace. (The command
            // service's settings are the request-response builder's: `IpcBus::command_*`.)
            Topic::Reset | Topic::AxisCommand => Qos {
                max_publishers: 4,
                max_subscribers: 2,
                max_buffer: LOOP_BUFFER,
                history: 0,
                safe_overflow: true,
            },
        }
    }
}

/// Settings of one topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub max_publishers: usize,
    pub max_subscribers: usize,
    pub max_buffer: usize,
    /// Messages a subscriber that attaches late receives at once: the newest state and
    /// setpoint let a restarted loop rejoin a running stack.
    pub history: usize,
    /// False: a full queue makes the publisher wait. True: the oldest entry is overwritten.
    pub safe_overflow: bool,
}

/// The event the bridge raises after each state (hardware mode), so that the current loop
/// sleeps until there is a sample to answer instead of spinning on the CPU the bridge
/// needs. One event id: each wait drains the whole id bitset with an atomic swap per id,
/// and the default 256 ids made that ~4.7 µs per wake-up (measured).
pub const STATE_READY: &str = "drive/state-ready";

/// A message type of the stack and the one topic it travels on.
#[cfg(feature = "ipc")]
pub trait Message: Copy + Debug + ZeroCopySend + 'static {
    const TOPIC: Topic;
    /// Its place in its stream when a lockstep reader may sleep until a given one: a
    /// state's sequence number (the position loop sleeps through the states between its
    /// ticks). None: every message of the topic is worth a wake-up.
    fn stream_key(&self) -> Option<u64> {
        None
    }
}

/// A message type of the stack and the one topic it travels on (without iceoryx2: the
/// laws and drive firmware use the types, not the transport).
#[cfg(not(feature = "ipc"))]
pub trait Message: Copy + Debug + 'static {
    const TOPIC: Topic;
    /// Its place in its stream when a lockstep reader may sleep until a given one: a
    /// state's sequence number (the position loop sleeps through the states between its
    /// ticks). None: every message of the topic is worth a wake-up.
    fn stream_key(&self) -> Option<u64> {
        None
    }
}

impl Message for DriveState {
    const TOPIC: Topic = Topic::State;
    /// The last state wakes every reader: it may fall between a reader's ticks.
    fn stream_key(&self) -> Option<u64> {
        if self.flags & crate::messages::state_flags::LAST != 0 {
            return Some(u64::MAX);
        }
        Some(self.seq)
    }
}
impl Message for DriveCommand {
    const TOPIC: Topic = Topic::Command;
}
impl Message for DrivePlan {
    const TOPIC: Topic = Topic::Plan;
}
impl Message for TorqueSetpoint {
    const TOPIC: Topic = Topic::Setpoint;
}
impl Message for StatsReport {
    const TOPIC: Topic = Topic::Stats;
}
impl Message for ResetRequest {
    const TOPIC: Topic = Topic::Reset;
}
impl Message for AxisStatus {
    const TOPIC: Topic = Topic::AxisStatus;
}
impl Message for AxisStreamPoint {
    const TOPIC: Topic = Topic::AxisStream;
}
impl Message for AxisAck {
    const TOPIC: Topic = Topic::AxisAcks;
}

/// Service names of one stack. Two stacks with different instance names never see each
/// other.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceNames {
    pub instance: String,
}

impl ServiceNames {
    pub fn new(instance: &str) -> Result<Self, BadInstance> {
        let instance = instance_name(instance).map_err(BadInstance)?;
        Ok(Self { instance })
    }

    pub fn topic(&self, topic: Topic) -> String {
        format!("{}/{}", self.instance, topic.path())
    }

    /// `topic`'s service for `axis` ([`Topic::path_of`]).
    pub fn topic_of(&self, topic: Topic, axis: u32) -> String {
        format!("{}/{}", self.instance, topic.path_of(axis))
    }

    /// The bridge's state-ready event: one for every axis, so that a current loop serving
    /// several drives sleeps on one event whichever drive's state comes first.
    pub fn state_ready(&self) -> String {
        format!("{}/{STATE_READY}", self.instance)
    }

    /// The iceoryx2 node name of `role` in this instance.
    pub fn node(&self, role: &str) -> String {
        format!("{}.{role}", self.instance)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Axis 0 keeps a one-axis stack's names; every other axis has its own, except the
    /// statistics (one report per process).
    #[test]
    fn each_axis_has_its_own_services_and_axis_0_keeps_todays() {
        let names = ServiceNames::new("cell").unwrap();
        assert_eq!(names.topic_of(Topic::State, 0), "cell/drive/state");
        assert_eq!(names.topic_of(Topic::State, 2), "cell/axis/2/drive/state");
        assert_eq!(
            names.topic_of(Topic::Setpoint, 1),
            "cell/axis/1/control/setpoint"
        );
        assert_eq!(names.topic_of(Topic::AxisStatus, 0), "cell/axis/0/status");
        assert_eq!(names.topic_of(Topic::AxisStatus, 3), "cell/axis/3/status");
        assert_eq!(names.topic_of(Topic::AxisCommand, 7), "cell/axis/7/command");
        assert_eq!(names.topic_of(Topic::Stats, 5), "cell/monitor/stats");
        let all = [
            Topic::State,
            Topic::Command,
            Topic::Plan,
            Topic::Setpoint,
            Topic::Reset,
            Topic::AxisStatus,
            Topic::AxisStream,
            Topic::AxisCommand,
            Topic::AxisAcks,
        ];
        let mut seen = std::collections::BTreeSet::new();
        for axis in 0..8 {
            for t in all {
                assert!(seen.insert(names.topic_of(t, axis)), "{t:?} of axis {axis}");
            }
        }
    }

    /// An instance name is one harmless path component: a slash, `..`, a space or an
    /// empty name is refused before anything touches the filesystem.
    #[test]
    fn instance_names_are_one_plain_path_component() {
        for ok in ["stepdrive", "axis_2", "cell-7", "A"] {
            assert_eq!(instance_name(ok).as_deref(), Ok(ok));
        }
        for bad in [
            "a/b",
            "../../x/escape",
            "..",
            "",
            "a b",
            "-x",
            "é",
            &"x".repeat(65),
        ] {
            assert!(instance_name(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn instance_names_are_checked_and_topics_named_under_them() {
        let n = ServiceNames::new("bench-1.a_b").expect("valid");
        assert_eq!(n.topic(Topic::State), "bench-1.a_b/drive/state");
        assert_eq!(n.topic(Topic::Setpoint), "bench-1.a_b/control/setpoint");
        assert_eq!(n.state_ready(), "bench-1.a_b/drive/state-ready");
        for bad in ["", "a/b", "x y", &"n".repeat(49)] {
            assert!(ServiceNames::new(bad).is_err(), "{bad:?} accepted");
        }
    }

    #[test]
    fn lockstep_never_drops_and_realtime_never_blocks() {
        for t in [Topic::State, Topic::Command, Topic::Setpoint] {
            assert!(!t.qos(Mode::Lockstep).safe_overflow);
            assert!(t.qos(Mode::Realtime).safe_overflow);
            assert!(t.qos(Mode::Hardware).safe_overflow);
        }
    }
}

/// Zenoh key expressions of the gateway (`stepdrive gateway`, docs/remote.md): what
/// crosses hosts, under `stepdrive/<instance>/`.
pub mod remote {
    /// Queryable: an [`AxisRequest`](crate::axis::AxisRequest) in, its
    /// [`AxisAck`](crate::axis::AxisAck) out.
    pub const COMMAND: &str = "command";
    /// The axis's [`AxisStatus`](crate::axis::AxisStatus), at the gateway's rate.
    pub const STATUS: &str = "status";
    /// [`AxisStreamPoint`](crate::axis::AxisStreamPoint)s of a stream a remote client
    /// started.
    pub const STREAM: &str = "stream";

    /// The port a gateway listens on when none is named (Zenoh's own default).
    pub const DEFAULT_PORT: u16 = 7447;

    /// `stepdrive/<instance>/axis/<axis>/<leaf>`.
    pub fn axis_key(instance: &str, axis: u32, leaf: &str) -> String {
        format!("stepdrive/{instance}/axis/{axis}/{leaf}")
    }

    /// `stepdrive/<instance>/axis/*/<leaf>`: the leaf of every axis (what a gateway
    /// serves).
    pub fn any_axis_key(instance: &str, leaf: &str) -> String {
        format!("stepdrive/{instance}/axis/*/{leaf}")
    }

    /// The axis a key of [`axis_key`]'s form names.
    pub fn axis_of_key(key: &str) -> Option<u32> {
        let mut parts = key.rsplit('/');
        let _leaf = parts.next()?;
        let axis = parts.next()?.parse().ok()?;
        (parts.next()? == "axis").then_some(axis)
    }

    /// A remote client's liveliness token: `stepdrive/<instance>/client/<id>`, the id the
    /// top 32 bits of its commands' sequence numbers.
    pub fn client_token(instance: &str, client: u32) -> String {
        format!("stepdrive/{instance}/client/{client}")
    }

    /// Every client token of an instance.
    pub fn client_tokens(instance: &str) -> String {
        format!("stepdrive/{instance}/client/*")
    }

    /// The client id in a token's key.
    pub fn client_of_token(key: &str) -> Option<u32> {
        key.rsplit('/').next()?.parse().ok()
    }
}
