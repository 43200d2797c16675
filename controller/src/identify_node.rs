//! The identification sequence as a node of the runner, in the current loop's place: it
//! answers every state with the sequence's voltages (lockstep), keeps the states for the
//! fits (pre-allocated for the whole sequence), and on a bound turns the outputs off for
//! the rest of the run.

use crate::current_loop_node::wait_state_ready;
use stepdrive_control::identify::{BoundHit, Bounds, Planner, Sequence};
use stepdrive_runtime::node::{Cx, Flow, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{Listen, PortError, PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{state_flags, DriveCommand, DrivePlan, DriveState, MAX_PLAN};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::Scenario;

/// Plan entries written after each command: ~4 µs of the 50 µs period (a whole 1000-entry
/// plan at once, ~40 µs, held the bridge off the shared CPU and made commands late).
const PLAN_PIECE: usize = 50;

pub struct IdentifyPorts {
    pub states: Box<dyn Subscribe<DriveState>>,
    pub commands: Box<dyn Publish<DriveCommand>>,
    /// Realtime: the sequence's voltages ahead, so that a drive or plant that misses a
    /// command applies what would have come (the current loop's plan, for the sequence).
    pub plans: Option<Box<dyn Publish<DrivePlan>>>,
    pub presence: Box<dyn Presence>,
    /// `event` wait (hardware mode): the bridge's state-ready event, as the current loop.
    pub state_ready: Option<Box<dyn Listen>>,
}

impl IdentifyPorts {
    pub fn open(f: &mut impl PortFactory, mode: Mode, event: bool) -> Result<Self, PortError> {
        Ok(Self {
            states: f.subscriber(LOOP_BUFFER)?,
            commands: f.publisher()?,
            plans: match mode {
                Mode::Lockstep => None,
                _ => Some(f.publisher()?),
            },
            presence: f.presence()?,
            state_ready: if event { Some(f.listener()?) } else { None },
        })
    }
}

pub struct IdentifyNode {
    sequence: Sequence,
    lockstep: bool,
    rate_hz: f64,
    period_ns: u64,
    /// Realtime: when the next state is due (the runner sleeps until just before it).
    due_ns: Option<u64>,
    state: Option<DriveState>,
    next_seq: u64,
    plan_periods: usize,
    /// The plan being written, a piece a cycle, and the command it continues (its seq, the
    /// sample it answers); whether the zeros after a stop went out.
    planner: Option<(Planner, (u64, u64))>,
    zeros_sent: bool,
    plan: Box<DrivePlan>,
    /// Every state of the run, in order.
    pub recorded: Vec<DriveState>,
    /// The bound that stopped the sequence, if one did.
    pub stopped: Option<BoundHit>,
}

impl IdentifyNode {
    /// `s`'s `[motor]` is the nominal model (it only sizes the levels); its run must last
    /// [`Sequence::duration_s`].
    pub fn new(s: &Scenario, bounds: Bounds, mode: Mode) -> Self {
        Self {
            sequence: Sequence::new(&s.motor, bounds, s.sample_period_s()),
            lockstep: mode == Mode::Lockstep,
            period_ns: s.sample_period_ns(),
            due_ns: None,
            rate_hz: s.rates.current_loop_hz,
            state: None,
            next_seq: 0,
            plan_periods: (s.drive.command_plan_periods as usize).min(MAX_PLAN),
            planner: None,
            zeros_sent: false,
            plan: Box::default(),
            recorded: Vec::with_capacity(s.sample_count() as usize),
            stopped: None,
        }
    }
}

impl IdentifyNode {
    /// A piece of the plan after each command ([`PLAN_PIECE`] entries), published when it is
    /// whole: it then continues a command up to `plan_periods / PLAN_PIECE` cycles old, as
    /// the current loop's plans do. Once a bound stopped the sequence, a plan of zeros goes
    /// out at once: the outputs stay off through a missed command too.
    fn write_plan(
        &mut self,
        state: &DriveState,
        command: &DriveCommand,
        cx: &mut Cx,
        plans: &mut dyn Publish<DrivePlan>,
    ) -> Result<(), RunError> {
        let n = self.plan_periods;
        if n == 0 || self.zeros_sent {
            return Ok(());
        }
        let continues = if self.stopped.is_some() {
            self.plan.v[..n].fill([0.0; 2]);
            self.zeros_sent = true;
            (command.seq, state.seq)
        } else {
            let (planner, continues) = self.planner.get_or_insert_with(|| {
                let planner = self.sequence.planner(state.sample_time_s);
                (planner, (command.seq, state.seq))
            });
            let from = planner.written();
            let to = (from + PLAN_PIECE).min(n);
            planner.fill(&mut self.plan.v[from..to]);
            if to < n {
                return Ok(());
            }
            let continues = *continues;
            self.planner = None;
            continues
        };
        (self.plan.command_seq, self.plan.answers_seq) = continues;
        self.plan.len = n as u32;
        self.plan.publish_time_ns = cx.now();
        plans.publish(&self.plan)?;
        Ok(())
    }
}

impl Node for IdentifyNode {
    type Ports = IdentifyPorts;

    fn role(&self) -> Role {
        Role::Tool("identify")
    }

    fn pace(&self) -> Pace {
        Pace::Input
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn awaiting(&self) -> String {
        "drive/state from the plant".to_string()
    }

    fn due_ns(&self) -> Option<u64> {
        self.due_ns
    }

    fn block(
        &mut self,
        ports: &mut IdentifyPorts,
        _now_ns: u64,
        _until_ns: u64,
    ) -> Result<bool, RunError> {
        wait_state_ready(&mut ports.state_ready)
    }

    fn start(&mut self, ports: &mut IdentifyPorts, _cx: &mut Cx) -> Result<Start, RunError> {
        let ready = ports.presence.subscribers(Topic::Command) >= 1;
        Ok(if ready { Start::NOW } else { Start::Waiting })
    }

    fn connect(&mut self, ports: &mut IdentifyPorts) -> Result<(), RunError> {
        ports.commands.connect()?;
        if let Some(plans) = &mut ports.plans {
            plans.connect()?;
        }
        Ok(())
    }

    fn poll(&mut self, ports: &mut IdentifyPorts, _cx: &mut Cx) -> Result<Poll, RunError> {
        if self.state.is_some() {
            return Ok(Poll::READY);
        }
        // Realtime: the newest state only (an older one is stale); the fits skip the gaps.
        let next = if self.lockstep {
            ports.states.receive()?
        } else {
            ports.states.newest()?
        };
        let Some(s) = next else {
            return Ok(Poll::Pending);
        };
        self.state = Some(s);
        Ok(Poll::READY)
    }

    fn step(&mut self, ports: &mut IdentifyPorts, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some(state) = self.state.take() else {
            return Ok(Flow::Continue);
        };
        if !self.lockstep {
            self.due_ns = Some(state.deadline_ns + self.period_ns);
        }
        if self.recorded.len() < self.recorded.capacity() {
            self.recorded.push(state);
        }
        let v = match self.stopped {
            Some(_) => [0.0, 0.0],
            None => match self.sequence.next(&state) {
                Ok(v) => v,
                Err(hit) => {
                    tracing::error!("identification stopped, outputs off: {hit}");
                    self.stopped = Some(hit);
                    [0.0, 0.0]
                }
            },
        };
        let command = DriveCommand {
            seq: self.next_seq,
            answers_seq: state.seq,
            sample_time_s: state.sample_time_s,
            state_publish_time_ns: state.publish_time_ns,
            publish_time_ns: cx.now(),
            v_a_v: v[0],
            v_b_v: v[1],
            ..Default::default()
        };
        self.next_seq += 1;
        ports.commands.publish(&command)?;
        if let Some(plans) = &mut ports.plans {
            self.write_plan(&state, &command, cx, plans.as_mut())?;
        }
        Ok(if state.flags & state_flags::LAST != 0 {
            Flow::Last
        } else {
            Flow::Continue
        })
    }
}
