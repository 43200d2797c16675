//! The current loop as a node of the runner: woken by each state sample, it answers with
//! the command computed by [`CurrentLoop`] from that state and the position loop's latest
//! setpoint, then publishes the voltage plan (realtime). In lockstep it answers every sample
//! in order and waits for the setpoint of each position-loop tick; in realtime it answers
//! the newest sample and uses the newest setpoint. Its deadline for sample k is the plant's
//! deadline k + d, the period the answer is applied in.

use stepdrive_control::current_loop::CurrentLoop;
use stepdrive_control::stale::StaleGuard;
use stepdrive_runtime::inbox::Inbox;
use stepdrive_runtime::node::{Awaits, Cx, Flow, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{Listen, PortError, PortFactory, Presence, Publish};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{
    command_flags, setpoint_flags, state_flags, DriveCommand, DrivePlan, DriveState, TorqueSetpoint,
};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::stack::CURRENT_LOOP;
use stepdrive_shared::{Method, Scenario};

/// A plan goes out with every tenth command: 1000 periods of plan cost ~9 µs to compute,
/// which with every command would be a fifth of the 50 µs period; a plan ten periods old
/// still covers the 990 after the newest command. The loop predicts with the plan it last
/// sent, which is the plant's freshest.
pub(crate) const PLAN_EVERY: u64 = 10;

/// Whether the command answering `seq` is followed by a plan: every [`PLAN_EVERY`]-th,
/// `phase` samples after axis 0's, and the first after a gap (`last`: the sample answered
/// before), the newest state being news, unless the last plan (answering `planned`) is
/// younger than half [`PLAN_EVERY`]. Why the limit: on a host that loses samples because
/// it is busy, a plan after every gap made more work (each plan ~9 µs here, and 4 KB the
/// bridge encodes and the drive decodes) and so lost more samples: beside an ordinary task
/// on CPU 1 the loops then left it less than the kernel's fair server guarantees, which
/// took CPU 1 from them for tens of milliseconds at once.
pub(crate) fn plans_after(seq: u64, last: Option<u64>, planned: Option<u64>, phase: u64) -> bool {
    let gap = last.is_none_or(|l| seq != l + 1);
    let stale = planned.is_none_or(|p| seq >= p + PLAN_EVERY / 2);
    (gap && stale) || (seq + phase).is_multiple_of(PLAN_EVERY)
}

/// What the current loop reads and writes.
pub struct CurrentLoopPorts {
    pub states: Inbox<DriveState>,
    pub setpoints: Inbox<TorqueSetpoint>,
    pub commands: Box<dyn Publish<DriveCommand>>,
    /// Realtime: the voltage plan, after every `PLAN_EVERY`-th command.
    pub plans: Option<Box<dyn Publish<DrivePlan>>>,
    /// `event` wait (hardware mode): the bridge's state-ready event.
    pub state_ready: Option<Box<dyn Listen>>,
    pub presence: Box<dyn Presence>,
}

impl CurrentLoopPorts {
    pub fn open(f: &mut impl PortFactory, mode: Mode, event: bool) -> Result<Self, PortError> {
        // Setpoints first: the plant starts once the states have their subscribers, and
        // the first setpoint must find this loop listening.
        Ok(Self {
            setpoints: Inbox::open(f, &CURRENT_LOOP, mode, LOOP_BUFFER)?,
            states: Inbox::open(f, &CURRENT_LOOP, mode, LOOP_BUFFER)?,
            commands: f.publisher()?,
            // A lockstep plant waits for every command: it never needs a plan.
            plans: match mode {
                Mode::Lockstep => None,
                _ => Some(f.publisher()?),
            },
            state_ready: if event { Some(f.listener()?) } else { None },
            presence: f.presence()?,
        })
    }
}

/// A lockstep setpoint for another sample than the tick's: the position loop broke the
/// protocol.
#[derive(Debug, thiserror::Error)]
#[error("a setpoint computed from sample {got} arrived for sample {expected}")]
pub struct WrongSetpoint {
    pub expected: u64,
    pub got: u64,
}

pub struct CurrentLoopNode {
    body: CurrentLoop,
    ratio: u64,
    period_ns: u64,
    answer_budget_ns: u64,
    rate_hz: f64,
    setpoint: TorqueSetpoint,
    /// The state taken for the coming cycle, and the states skipped before it.
    state: Option<DriveState>,
    skipped: u64,
    last_seq: Option<u64>,
    /// The sample the last plan's command answered.
    planned_seq: Option<u64>,
    due_ns: Option<u64>,
    /// A plan follows this cycle's command ([`Node::after_answers`]).
    plan_due: bool,
    /// Samples by which its plans follow axis 0's ([`Self::for_axis`]).
    plan_phase: u64,
    started: bool,
    /// When the last setpoint came, and how long it may be stale before this loop stops.
    setpoint_seen_ns: Option<u64>,
    setpoint_timeout: Option<std::time::Duration>,
    /// A setpoint came at all; the guard against stale ones, and whether it was acting.
    setpoint_seen: bool,
    guard: StaleGuard,
    was_stale: bool,
    /// The last command had the outputs on.
    outputs_on: bool,
}

impl CurrentLoopNode {
    /// Plans as `s` says, except in lockstep (see [`CurrentLoopPorts::plans`]).
    pub fn new(s: &Scenario, method: Method, mode: Mode) -> Self {
        let body = CurrentLoop::new(s, method);
        let period_ns = s.sample_period_ns();
        Self {
            body: match mode {
                Mode::Lockstep => body.with_plan_periods(0),
                _ => body,
            },
            ratio: s.rate_ratio(),
            period_ns,
            answer_budget_ns: period_ns * u64::from(s.rates.compute_delay_periods.max(1)),
            rate_hz: s.rates.current_loop_hz,
            setpoint: TorqueSetpoint::default(),
            state: None,
            skipped: 0,
            last_seq: None,
            planned_seq: None,
            due_ns: None,
            plan_due: false,
            plan_phase: 0,
            started: false,
            setpoint_seen_ns: None,
            setpoint_timeout: None,
            setpoint_seen: false,
            guard: StaleGuard::new(s),
            was_stale: false,
            outputs_on: false,
        }
    }

    /// Axis `axis` of a multi-axis loop plans `axis` samples after axis 0: a plan takes
    /// ~10 µs, and the axes' plans in one period left the next sample's answers late.
    pub fn for_axis(mut self, axis: u32) -> Self {
        self.plan_phase = u64::from(axis) % PLAN_EVERY;
        self
    }

    /// Stop (a silent peer) when no setpoint came for `timeout`.
    pub fn watching_setpoints(mut self, timeout: std::time::Duration) -> Self {
        self.setpoint_timeout = Some(timeout);
        self
    }

    /// Takes the setpoints that arrived: the one of `state`'s tick, which a synchronous
    /// (lockstep) stack must have before answering; otherwise the newest. False while the
    /// one needed is not there.
    fn take_setpoints(
        &mut self,
        ports: &mut CurrentLoopPorts,
        state: &DriveState,
        now: u64,
    ) -> Result<bool, RunError> {
        let tick = state.seq - state.seq % self.ratio;
        let synchronous = ports.setpoints.synchronous();
        if synchronous && ports.setpoints.last_key() == Some(tick) {
            return Ok(true);
        }
        let Some(sp) = ports.setpoints.take()? else {
            return Ok(!synchronous);
        };
        if synchronous && sp.message.from_state_seq != tick {
            let e = WrongSetpoint {
                expected: tick,
                got: sp.message.from_state_seq,
            };
            return Err(RunError::node(Role::CurrentLoop, e));
        }
        self.setpoint = sp.message;
        self.setpoint_seen_ns = Some(now);
        self.setpoint_seen = true;
        Ok(true)
    }
}

/// Each axis's current loop is on its own in a multi-axis stack, and every lane's
/// state-ready listener wakes on any drive's state (the event is one for all axes), so
/// lanes waiting together block on it. Lanes that could not block (a bridge of two drives)
/// kept the loop spinning and yielding at SCHED_FIFO for 2 ms at a time on the bridge's
/// CPU, where a yield gives the lower-priority bridge nothing: it fell behind, and both
/// axes' commands with it.
impl stepdrive_runtime::lanes::Together for CurrentLoopNode {
    const BLOCKS_FOR_ALL: bool = true;
}

impl Node for CurrentLoopNode {
    type Ports = CurrentLoopPorts;

    fn role(&self) -> Role {
        Role::CurrentLoop
    }

    fn pace(&self) -> Pace {
        Pace::Input
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    /// Lockstep: a state in hand waits for its tick's setpoint, from the position loop on
    /// this loop's CPU.
    fn awaits(&self) -> Awaits {
        match self.state {
            Some(_) => Awaits::Beside,
            None => Awaits::Next,
        }
    }

    fn awaiting(&self) -> String {
        match self.state {
            _ if !self.started => "a plant subscribed to drive/command".to_string(),
            Some(s) => format!("the setpoint for sample {} from the position loop", s.seq),
            None => "drive/state from the plant".to_string(),
        }
    }

    fn start(&mut self, ports: &mut CurrentLoopPorts, _cx: &mut Cx) -> Result<Start, RunError> {
        self.started = ports.presence.subscribers(Topic::Command) >= 1;
        Ok(if self.started {
            Start::NOW
        } else {
            Start::Waiting
        })
    }

    fn connect(&mut self, ports: &mut CurrentLoopPorts) -> Result<(), RunError> {
        ports.commands.connect()?;
        if let Some(plans) = &mut ports.plans {
            plans.connect()?;
        }
        Ok(())
    }

    fn poll(&mut self, ports: &mut CurrentLoopPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        let state = match self.state {
            Some(s) => s,
            None => {
                let Some(t) = ports.states.take()? else {
                    return Ok(Poll::Pending);
                };
                // The state hop ends here, before the setpoints are read.
                cx.taken_at(cx.now());
                // Every state asks for an answer: one passed over is skipped.
                self.skipped = self
                    .last_seq
                    .map_or(0, |prev| t.message.seq.saturating_sub(prev + 1));
                self.state = Some(t.message);
                t.message
            }
        };
        let now = cx.now();
        if !self.take_setpoints(ports, &state, now)? {
            return Ok(Poll::Pending);
        }
        // A stale setpoint segment keeps extrapolating θ_d: a position loop that went quiet
        // must stop this loop, not steer the motor on.
        if let (Some(seen), Some(timeout)) = (self.setpoint_seen_ns, self.setpoint_timeout) {
            if now.saturating_sub(seen) > timeout.as_nanos() as u64 {
                return Err(RunError::PeerSilent {
                    role: Role::CurrentLoop,
                    awaiting: "control/setpoint from the position loop".to_string(),
                    timeout,
                });
            }
        }
        Ok(Poll::Ready {
            fresh: true,
            skipped: std::mem::take(&mut self.skipped),
        })
    }

    fn step(&mut self, ports: &mut CurrentLoopPorts, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some(state) = self.state.take() else {
            return Ok(Flow::Continue);
        };
        cx.stats
            .hop
            .record(cx.woke_ns.saturating_sub(state.publish_time_ns));
        // A stale setpoint is not followed: the guard stops the motor on its own.
        let (sp, stale) = match self.setpoint_seen {
            true => self.guard.guard(&state, &self.setpoint),
            false => (self.setpoint, false),
        };
        if stale != self.was_stale {
            self.was_stale = stale;
            if stale {
                tracing::error!(
                    age_ms = (state.sample_time_s - self.setpoint.sample_time_s) * 1e3,
                    limit_ms = self.guard.limit_s() * 1e3,
                    "the position loop is silent (its newest setpoint is too old): this loop \
                     brings the motor to a standstill and holds it until setpoints of a new \
                     enable come"
                );
            } else {
                tracing::warn!("setpoints of a new enable: the position loop has the motor again");
            }
        }
        let on = sp.flags & setpoint_flags::OUTPUTS_ON != 0;
        let mut command = if on {
            self.body.on_sample(&state, &sp)
        } else {
            self.body.off(&state)
        };
        if stale {
            command.flags |= command_flags::SETPOINT_STALE;
        }
        if on && sp.flags & setpoint_flags::BRAKE_RELEASED != 0 {
            command.flags |= command_flags::BRAKE_RELEASED;
        }
        // Outputs switched: the plant's freshest plan must say so at once.
        let switched = on != self.outputs_on;
        self.outputs_on = on;
        command.publish_time_ns = cx.now();
        ports.commands.publish(&command)?;
        let done = cx.answered();
        // A state with a deadline (on the wall clock) must be answered by its period's.
        if state.deadline_ns > 0 && done > state.deadline_ns + self.answer_budget_ns {
            cx.stats.misses += 1;
        }
        // After the command (every axis's, in a multi-axis loop), so that planning never
        // delays one; after a gap at once, the newest state being news.
        self.plan_due = ports.plans.is_some()
            && (switched
                || plans_after(state.seq, self.last_seq, self.planned_seq, self.plan_phase));
        if self.plan_due {
            self.planned_seq = Some(state.seq);
        }
        self.last_seq = Some(state.seq);
        self.due_ns = (state.deadline_ns > 0).then(|| state.deadline_ns + self.period_ns);
        Ok(if state.flags & state_flags::LAST != 0 {
            Flow::Last
        } else {
            Flow::Continue
        })
    }

    fn after_answers(&mut self, ports: &mut CurrentLoopPorts, cx: &mut Cx) -> Result<(), RunError> {
        if let Some(plans) = ports.plans.as_mut().filter(|_| self.plan_due) {
            self.plan_due = false;
            let mut plan = *self.body.plan();
            if plan.len > 0 {
                plan.publish_time_ns = cx.now();
                plans.publish(&plan)?;
            }
        }
        Ok(())
    }

    fn due_ns(&self) -> Option<u64> {
        self.due_ns
    }

    /// `event` wait: asleep until the bridge raises state-ready (its 1 ms timeout is
    /// jiffy-grained here, the wake-up on the event is not).
    fn block(
        &mut self,
        ports: &mut CurrentLoopPorts,
        _now_ns: u64,
        _until_ns: u64,
    ) -> Result<bool, RunError> {
        wait_state_ready(&mut ports.state_ready)
    }
}

/// `event` wait: asleep on the bridge's state-ready event for at most 1 ms; false without
/// one (the runner then sleeps). The current loop and the identification share it.
pub(crate) fn wait_state_ready(ready: &mut Option<Box<dyn Listen>>) -> Result<bool, RunError> {
    let Some(ready) = ready else {
        return Ok(false);
    };
    ready.wait(std::time::Duration::from_millis(1))?;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;
    use stepdrive_runtime::clock::VirtualClock;
    use stepdrive_runtime::memory::MemoryBus;
    use stepdrive_runtime::runner::{Runner, Settings, Wake};

    /// Lockstep: a state in hand without its tick's setpoint is waited on beside the
    /// position loop (the runner yields the CPU they share); without a state, the plant's
    /// next one is a hand-off away.
    #[test]
    fn a_lockstep_current_loop_waits_beside_the_position_loop_only_for_a_tick_setpoint() {
        let s = Scenario::default();
        let mut bus = MemoryBus::new(Mode::Lockstep);
        let ports = CurrentLoopPorts::open(&mut bus, Mode::Lockstep, false).expect("ports");
        let mut states = bus.publisher::<DriveState>().expect("states");
        let mut setpoints = bus.publisher::<TorqueSetpoint>().expect("setpoints");
        let mut commands = bus.subscriber::<DriveCommand>(16).expect("commands");
        let node = CurrentLoopNode::new(&s, Method::Proposed, Mode::Lockstep);
        let timeout = Duration::from_secs(1);
        let mut runner = Runner::new(node, ports, Settings::lockstep(timeout, timeout), None);
        let clock = VirtualClock::default();
        assert!(runner.try_start(&clock).expect("start"));
        let state = |seq| DriveState {
            seq,
            ..DriveState::default()
        };
        let setpoint = |tick| TorqueSetpoint {
            from_state_seq: tick,
            ..TorqueSetpoint::default()
        };
        assert_eq!(runner.node().awaits(), Awaits::Next);
        states.publish(&state(0)).expect("publish");
        assert!(
            !runner_cycle(&mut runner, &clock),
            "no setpoint for tick 0 yet"
        );
        assert_eq!(runner.node().awaits(), Awaits::Beside);
        setpoints.publish(&setpoint(0)).expect("publish");
        assert!(
            runner_cycle(&mut runner, &clock),
            "answered with tick 0's setpoint"
        );
        assert_eq!(runner.node().awaits(), Awaits::Next);
        // The samples of a tick after its first are answered with its setpoint.
        let ratio = (s.rates.current_loop_hz / s.rates.position_loop_hz).round() as u64;
        for seq in 1..ratio {
            states.publish(&state(seq)).expect("publish");
            assert!(runner_cycle(&mut runner, &clock), "sample {seq}");
            assert_eq!(runner.node().awaits(), Awaits::Next);
        }
        states.publish(&state(ratio)).expect("publish");
        assert!(
            !runner_cycle(&mut runner, &clock),
            "the next tick's setpoint"
        );
        assert_eq!(runner.node().awaits(), Awaits::Beside);
        let mut answered = Vec::new();
        commands
            .drain(&mut |c| answered.push(c.seq))
            .expect("commands");
        assert_eq!(answered, (0..ratio).collect::<Vec<_>>());
    }

    /// One poll of the runner: true if the node ran a cycle.
    fn runner_cycle(runner: &mut Runner<CurrentLoopNode>, clock: &VirtualClock) -> bool {
        runner
            .try_input_cycle(clock, Wake::default())
            .expect("cycle")
            .is_some()
    }

    #[test]
    fn each_axis_plans_every_tenth_sample_and_no_two_axes_plan_after_one_sample() {
        for axes in [2u64, 4, 8] {
            let mut last = vec![Some(99u64); axes as usize];
            let mut plans = 0;
            for seq in 100..200 {
                let planning: Vec<u64> = (0..axes)
                    .filter(|&a| {
                        let p = plans_after(seq, last[a as usize], Some(seq - 5), a);
                        last[a as usize] = Some(seq);
                        p
                    })
                    .collect();
                assert!(planning.len() <= 1, "sample {seq}: axes {planning:?} plan");
                plans += planning.len() as u64;
                if let [a] = planning[..] {
                    assert_eq!((seq + a) % PLAN_EVERY, 0);
                }
            }
            assert_eq!(plans, axes * 100 / PLAN_EVERY);
        }
        // After a gap every axis plans at once (the newest state is news), unless its last
        // plan is younger than half the interval: a host losing sample after sample must
        // not plan after each.
        assert!((0..4).all(|a| plans_after(205, Some(200), Some(199), a)));
        assert!(plans_after(0, None, None, 3));
        assert!(!plans_after(203, Some(201), Some(200), 0));
        assert!(plans_after(205, Some(203), Some(200), 1));
        let (mut last, mut planned, mut plans) = (None, None, 0);
        for seq in (0..1000).step_by(2) {
            if plans_after(seq, last, planned, 0) {
                planned = Some(seq);
                plans += 1;
            }
            last = Some(seq);
        }
        assert_eq!(
            plans, 200,
            "every other sample lost: a plan every fifth sample"
        );
    }
}
