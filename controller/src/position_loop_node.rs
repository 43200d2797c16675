//! The position loop as a node of the runner: trajectory and torque modulation (12) from
//! the newest state, a setpoint per tick. Its ports take the states by the stack's policy
//! (in lockstep every one in order); its ticks come from its input (every N-th state) or
//! from its own clock at the position rate, on the plant's deadline grid (it does not chase
//! the plant's re-anchoring: it only needs the newest state).

use stepdrive_control::position_loop::PositionLoop;
use stepdrive_runtime::inbox::Inbox;
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{PortError, PortFactory, Presence, Publish};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{state_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::stack::POSITION_LOOP;
use stepdrive_shared::Scenario;

/// What the position loop reads and writes.
pub struct PositionLoopPorts {
    pub states: Inbox<DriveState>,
    pub setpoints: Box<dyn Publish<TorqueSetpoint>>,
    pub presence: Box<dyn Presence>,
}

impl PositionLoopPorts {
    pub fn open(f: &mut impl PortFactory, mode: Mode) -> Result<Self, PortError> {
        Ok(Self {
            states: Inbox::open(f, &POSITION_LOOP, mode, LOOP_BUFFER)?,
            setpoints: f.publisher()?,
            presence: f.presence()?,
        })
    }
}

pub struct PositionLoopNode {
    body: PositionLoop,
    pace: Pace,
    ratio: u64,
    period_ns: u64,
    phase_ns: u64,
    rate_hz: f64,
    /// The newest state taken, whether it is news, and the sample the last tick used.
    latest: Option<DriveState>,
    fresh: bool,
    last_used: Option<u64>,
    setpoint_subscribers: usize,
}

impl PositionLoopNode {
    /// In lockstep a tick is every N-th state, taken in order; otherwise its own clock at
    /// the position rate, on the plant's deadline grid shifted by `phase_ns` (processes use
    /// half a current period, so that the sample is out when the tick reads it; a
    /// simulation, 0: same instant, the plant first).
    pub fn new(s: &Scenario, mode: Mode, phase_ns: u64) -> Self {
        let period_ns = s.sample_period_ns();
        let ratio = s.rate_ratio();
        Self {
            body: PositionLoop::new(s),
            pace: match mode {
                Mode::Lockstep => Pace::Input,
                _ => Pace::Clock {
                    period_ns: period_ns * ratio,
                    late: Late::Skip,
                },
            },
            ratio,
            period_ns,
            phase_ns,
            rate_hz: s.rates.position_loop_hz,
            latest: None,
            fresh: false,
            last_used: None,
            setpoint_subscribers: 0,
        }
    }

    /// Whether `state` starts a tick: on the clock, any state the last tick did not use;
    /// paced by its input, every N-th.
    fn ticks_on(&self, state: &DriveState) -> bool {
        match self.pace {
            Pace::Input => state.seq % self.ratio == 0,
            Pace::Clock { .. } => self.last_used != Some(state.seq),
        }
    }
}

impl Node for PositionLoopNode {
    type Ports = PositionLoopPorts;

    fn role(&self) -> Role {
        Role::PositionLoop
    }

    fn pace(&self) -> Pace {
        self.pace
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn awaiting(&self) -> String {
        if self.pace == Pace::Input && self.latest.is_none() {
            "a current loop subscribed to control/setpoint".to_string()
        } else {
            "drive/state from the plant".to_string()
        }
    }

    fn start(&mut self, ports: &mut PositionLoopPorts, _cx: &mut Cx) -> Result<Start, RunError> {
        if self.pace == Pace::Input {
            let ready = ports.presence.subscribers(Topic::Setpoint) >= 1;
            return Ok(if ready { Start::NOW } else { Start::Waiting });
        }
        // On its own clock: the first state tells where the plant's deadline grid is.
        let Some(first) = ports.states.take()? else {
            return Ok(Start::Waiting);
        };
        let first = first.message;
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
        let fresh = std::mem::take(&mut self.fresh);
        let Some(taken) = ports.states.take()? else {
            if self.pace == Pace::Input {
                // A current loop that rejoins gets the newest setpoint from the topic's
                // history, delivered when the publisher updates its connections.
                let subscribers = ports.presence.subscribers(Topic::Setpoint);
                if subscribers != self.setpoint_subscribers {
                    self.setpoint_subscribers = subscribers;
                    ports.setpoints.connect()?;
                }
                return Ok(Poll::Pending);
            }
            return Ok(Poll::Ready { fresh, skipped: 0 });
        };
        cx.stats
            .hop
            .record(cx.now().saturating_sub(taken.message.publish_time_ns));
        self.latest = Some(taken.message);
        Ok(Poll::Ready {
            fresh: true,
            skipped: taken.skipped,
        })
    }

    fn step(&mut self, ports: &mut PositionLoopPorts, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some(state) = self.latest else {
            return Ok(Flow::Continue);
        };
        if self.ticks_on(&state) {
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
