//! The position loop as a node of the runner: trajectory and torque modulation (12) from
//! the newest state, a setpoint per tick. In lockstep it reads every state in order and
//! ticks on every N-th; in realtime it has its own clock at the position rate, on the
//! plant's deadline grid shifted by `phase_ns`, and takes the newest state at each tick
//! (it does not chase the plant's re-anchoring: it only needs the newest state).

use stepdrive_control::position_loop::PositionLoop;
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{PortError, PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{state_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::Scenario;

/// What the position loop reads and writes.
pub struct PositionLoopPorts {
    pub states: Box<dyn Subscribe<DriveState>>,
    pub setpoints: Box<dyn Publish<TorqueSetpoint>>,
    pub presence: Box<dyn Presence>,
}

impl PositionLoopPorts {
    pub fn open(f: &mut impl PortFactory) -> Result<Self, PortError> {
        Ok(Self {
            states: f.subscriber(LOOP_BUFFER)?,
            setpoints: f.publisher()?,
            presence: f.presence()?,
        })
    }
}

/// A lockstep state stream with a gap: the plant broke the protocol.
#[derive(Debug, thiserror::Error)]
#[error("expected state sample {expected}, got {got} (lockstep never skips)")]
pub struct SkippedState {
    pub expected: u64,
    pub got: u64,
}

pub struct PositionLoopNode {
    body: PositionLoop,
    lockstep: bool,
    ratio: u64,
    period_ns: u64,
    phase_ns: u64,
    rate_hz: f64,
    /// The newest state taken, and the one the last tick used.
    latest: Option<DriveState>,
    fresh: bool,
    last_used: Option<u64>,
    setpoint_subscribers: usize,
}

impl PositionLoopNode {
    /// `phase_ns`: realtime, where its ticks fall after the plant's samples (processes use
    /// half a current period, so that the sample is out when the tick reads it; a
    /// simulation, 0: same instant, the plant first).
    pub fn new(s: &Scenario, mode: Mode, phase_ns: u64) -> Self {
        Self {
            body: PositionLoop::new(s),
            lockstep: mode == Mode::Lockstep,
            ratio: s.rate_ratio(),
            period_ns: s.sample_period_ns(),
            phase_ns,
            rate_hz: s.rates.position_loop_hz,
            latest: None,
            fresh: false,
            last_used: None,
            setpoint_subscribers: 0,
        }
    }
}

impl Node for PositionLoopNode {
    type Ports = PositionLoopPorts;

    fn role(&self) -> Role {
        Role::PositionLoop
    }

    fn pace(&self) -> Pace {
        if self.lockstep {
            Pace::Input
        } else {
            Pace::Clock {
                period_ns: self.period_ns * self.ratio,
                late: Late::Skip,
            }
        }
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn awaiting(&self) -> String {
        if self.lockstep && self.latest.is_none() && self.last_used.is_none() {
            "a current loop subscribed to control/setpoint".to_string()
        } else {
            "drive/state from the plant".to_string()
        }
    }

    fn start(&mut self, ports: &mut PositionLoopPorts, _cx: &mut Cx) -> Result<Start, RunError> {
        if self.lockstep {
            let ready = ports.presence.subscribers(Topic::Setpoint) >= 1;
            return Ok(if ready { Start::NOW } else { Start::Waiting });
        }
        // The first state tells where the plant's deadline grid is.
        let Some(first) = ports.states.newest()? else {
            return Ok(Start::Waiting);
        };
        self.latest = Some(first);
        self.fresh = true;
        let epoch = (first.deadline_ns + self.phase_ns).saturating_sub(first.seq * self.period_ns);
        Ok(Start::Ready {
            epoch_ns: Some(epoch),
        })
    }

    fn connect(&mut self, ports: &mut PositionLoopPorts) -> Result<(), RunError> {
        ports.setpoints.connect()?;
        Ok(())
    }

    fn poll(&mut self, ports: &mut PositionLoopPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        if self.lockstep {
            let Some(s) = ports.states.receive()? else {
                // A current loop that rejoins gets the newest setpoint from the topic's
                // history, delivered when the publisher updates its connections.
                let subscribers = ports.presence.subscribers(Topic::Setpoint);
                if subscribers != self.setpoint_subscribers {
                    self.setpoint_subscribers = subscribers;
                    ports.setpoints.connect()?;
                }
                return Ok(Poll::Pending);
            };
            // The first may be any: a loop that rejoins starts from the newest sample.
            if let Some(expected) = self.latest.map(|l| l.seq + 1) {
                if s.seq != expected {
                    let e = SkippedState {
                        expected,
                        got: s.seq,
                    };
                    return Err(RunError::node(Role::PositionLoop, e));
                }
            }
            self.latest = Some(s);
            return Ok(Poll::READY);
        }
        let mut skipped = 0;
        let fresh = std::mem::take(&mut self.fresh);
        let mut got = false;
        while let Some(s) = ports.states.receive()? {
            if let Some(prev) = self.latest {
                skipped += s.seq.saturating_sub(prev.seq + 1);
            }
            self.latest = Some(s);
            got = true;
        }
        if let Some(l) = self.latest.filter(|_| got) {
            cx.stats
                .hop
                .record(cx.now().saturating_sub(l.publish_time_ns));
        }
        Ok(Poll::Ready {
            fresh: fresh || got,
            skipped,
        })
    }

    fn step(&mut self, ports: &mut PositionLoopPorts, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some(state) = self.latest else {
            return Ok(Flow::Continue);
        };
        let due = if self.lockstep {
            state.seq % self.ratio == 0
        } else {
            self.last_used != Some(state.seq)
        };
        if due {
            let mut sp = self.body.on_tick(&state);
            sp.publish_time_ns = cx.now();
            ports.setpoints.publish(&sp)?;
            self.last_used = Some(state.seq);
        }
        Ok(if state.flags & state_flags::LAST != 0 {
            Flow::Last
        } else {
            Flow::Continue
        })
    }
}
