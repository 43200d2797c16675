//! The simulated plant as a node of the runner. Each cycle publishes the state at sample k,
//! takes the commands, and integrates one period. In lockstep the plant is the clock: it
//! waits for exactly the command its delay line needs, so runs are bit-identical. In
//! realtime it runs on absolute deadlines and never waits for anyone: the command for
//! (t_k, t_{k+1}] is the one answering sample k − d; one not there when the period starts
//! is a deadline miss, covered by the freshest plan ([`CommandSlot`]); and when the host
//! holds the process past a period, its simulated time pauses ([`Late::Pause`]).
//!
//! A latched fault stays until a reset request (`stepdrive reset`) arrives while its cause
//! is gone. A current loop that dies and is restarted rejoins: in realtime its commands are
//! simply taken again; in lockstep the plant waits for a new one (within the start-up
//! timeout), which starts from the newest state, and the periods whose commands died with
//! the old one get no voltage.

use crate::sim::{CommandSlot, PlantSim};
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{PortError, PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{fault_bits, DriveCommand, DrivePlan, DriveState, ResetRequest};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

/// Lockstep: commands may arrive ahead of the one the delay line needs; a few are kept.
const PENDING: usize = 8;
/// Lockstep: after this long without the awaited command, and then at most this often, the
/// plant looks for dead peers.
const LOOK_FOR_THE_DEAD_NS: u64 = 200_000_000;

/// What the plant reads and writes.
pub struct PlantPorts {
    pub states: Box<dyn Publish<DriveState>>,
    pub commands: Box<dyn Subscribe<DriveCommand>>,
    /// Realtime: the current loop's voltage plans.
    pub plans: Option<Box<dyn Subscribe<DrivePlan>>>,
    pub resets: Box<dyn Subscribe<ResetRequest>>,
    pub presence: Box<dyn Presence>,
}

impl PlantPorts {
    pub fn open(f: &mut impl PortFactory, mode: Mode) -> Result<Self, PortError> {
        Ok(Self {
            commands: f.subscriber(LOOP_BUFFER)?,
            plans: match mode {
                Mode::Lockstep => None,
                _ => Some(f.subscriber(LOOP_BUFFER)?),
            },
            resets: f.subscriber(LOOP_BUFFER)?,
            states: f.publisher()?,
            presence: f.presence()?,
        })
    }
}

/// How the plant runs, beside its scenario.
#[derive(Debug, Clone)]
pub struct PlantSettings {
    pub mode: Mode,
    /// State subscribers to wait for before the first sample: the current and position
    /// loops, and the monitor when one is attached.
    pub wait_subscribers: usize,
    /// Wait for a position loop (a setpoint publisher) too; false for a tool that drives the
    /// plant alone (the identification sequence).
    pub wait_position_loop: bool,
    /// Realtime: misses in a row after which the outputs go off and a fault latches.
    pub watchdog_periods: u32,
    /// Realtime: the first deadline this long after start-up, so every process is in its
    /// loop by then.
    pub start_delay_ns: u64,
}

/// Counts of the peers the plant waits for at start-up, as last seen.
#[derive(Debug, Clone, Copy, Default)]
struct Peers {
    command_publishers: usize,
    setpoint_publishers: usize,
    state_subscribers: usize,
}

pub struct PlantNode {
    sim: PlantSim,
    settings: PlantSettings,
    samples: u64,
    delay: u64,
    period_ns: u64,
    rate_hz: f64,
    /// Start-up: the peers as last counted; `started` once they were all there.
    peers: Option<Peers>,
    started: bool,
    /// Lockstep: whether the current sample's state is out, commands received ahead of
    /// their turn, and the command the next period takes.
    emitted: bool,
    pending: [Option<DriveCommand>; PENDING],
    next: Option<DriveCommand>,
    /// Realtime: the command rules.
    slot: CommandSlot,
    /// A reset request waiting for the next period (the requester's pid).
    reset_requested: Option<u32>,
    /// Lockstep: the current loop left (its publisher is gone), and, once another has
    /// attached, the stream is resynchronised on its first command.
    current_loop_gone: bool,
    resync: bool,
    /// Lockstep: since when the awaited command has been awaited, and when dead peers were
    /// last looked for.
    waiting_since_ns: Option<u64>,
    dead_checked_ns: u64,
    state_subscribers: usize,
}

/// A lockstep command that cannot be the one awaited: the current loop broke the protocol.
#[derive(Debug, thiserror::Error)]
#[error("a command for sample {got} arrived while waiting for the one for sample {expected}")]
pub struct OutOfOrderCommand {
    pub got: u64,
    pub expected: u64,
}

impl PlantNode {
    pub fn new(scenario: &Scenario, settings: PlantSettings) -> Self {
        let delay = u64::from(scenario.rates.compute_delay_periods);
        Self {
            sim: PlantSim::new(scenario),
            samples: scenario.sample_count(),
            delay,
            period_ns: scenario.sample_period_ns(),
            rate_hz: scenario.rates.current_loop_hz,
            settings,
            peers: None,
            started: false,
            emitted: false,
            pending: [None; PENDING],
            next: None,
            slot: CommandSlot::new(delay),
            reset_requested: None,
            current_loop_gone: false,
            resync: false,
            waiting_since_ns: None,
            dead_checked_ns: 0,
            state_subscribers: 0,
        }
    }

    /// The realtime command rules' counters (misses, plan coverage, runs).
    pub fn slot(&self) -> &CommandSlot {
        &self.slot
    }

    /// The faults latched at the end of the run (zero: healthy).
    pub fn latched_fault(&self) -> u32 {
        self.sim.fault()
    }

    fn publish_state(
        &mut self,
        ports: &mut PlantPorts,
        cx: &Cx,
        last: bool,
    ) -> Result<(), RunError> {
        let mut state = self.sim.state(last);
        state.deadline_ns = cx.deadline_ns;
        state.publish_time_ns = cx.now();
        ports.states.publish(&state)?;
        Ok(())
    }

    /// The command lockstep waits for before integrating the period after sample k: the
    /// one the delay line needs, or at the last sample the answer to it (so the current
    /// loop finishes before our subscriber goes away; older ones are skipped then).
    fn awaited(&self) -> Option<(u64, bool)> {
        let k = self.sim.sample_index();
        if k + 1 == self.samples {
            Some((k, true))
        } else {
            self.sim.needed_command().map(|seq| (seq, false))
        }
    }

    /// Takes the reset requests that arrived; one is acted on at the next period.
    fn take_resets(&mut self, ports: &mut PlantPorts) -> Result<(), RunError> {
        while let Some(r) = ports.resets.receive()? {
            self.reset_requested = Some(r.pid);
        }
        Ok(())
    }

    /// Clears the latched faults if a reset was requested and their cause is gone: a
    /// command timeout is cleared only once commands arrive again (the silence is shorter
    /// than the watchdog's).
    fn apply_reset(&mut self) {
        let Some(pid) = self.reset_requested.take() else {
            return;
        };
        let fault = self.sim.fault();
        if fault == 0 {
            tracing::info!(pid, "reset requested: no fault latched");
            return;
        }
        let silent = self.slot.runs.current;
        if fault & fault_bits::COMMAND_TIMEOUT != 0
            && self.settings.mode != Mode::Lockstep
            && silent >= self.settings.watchdog_periods
        {
            tracing::warn!(
                pid,
                periods = silent,
                "reset refused: the current loop still sends no command"
            );
            return;
        }
        self.sim.clear_faults();
        tracing::warn!(
            pid,
            faults = fault,
            "reset: latched faults cleared, outputs follow the commands again"
        );
    }

    /// Lockstep: watches the current loop leave and another attach. Its history brings the
    /// newcomer the newest state at once. A loop killed outright still counts until its
    /// ports are removed, so after a while without its command the plant looks for dead
    /// peers.
    fn watch_current_loop(&mut self, ports: &mut PlantPorts, now: u64) -> Result<(), RunError> {
        let since = *self.waiting_since_ns.get_or_insert(now);
        if now.saturating_sub(since) > LOOK_FOR_THE_DEAD_NS
            && now.saturating_sub(self.dead_checked_ns) > LOOK_FOR_THE_DEAD_NS
        {
            self.dead_checked_ns = now;
            ports.presence.forget_dead();
        }
        let subscribers = ports.presence.subscribers(Topic::State);
        if subscribers != self.state_subscribers {
            // A newcomer gets the newest state from the topic's history.
            self.state_subscribers = subscribers;
            ports.states.connect()?;
        }
        let present = ports.presence.publishers(Topic::Command) > 0;
        if !present && !self.current_loop_gone {
            self.current_loop_gone = true;
            tracing::error!(
                "the current loop is gone; waiting for another to attach (start-up timeout)"
            );
        } else if present && self.current_loop_gone {
            self.current_loop_gone = false;
            self.resync = true;
            tracing::warn!("a current loop attached; resuming from the newest sample");
        }
        Ok(())
    }

    fn poll_lockstep(&mut self, ports: &mut PlantPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        let k = self.sim.sample_index();
        if !self.emitted {
            self.publish_state(ports, cx, k + 1 == self.samples)?;
            self.emitted = true;
        }
        self.take_resets(ports)?;
        let Some((seq, drain)) = self.awaited() else {
            return Ok(Poll::READY);
        };
        let slot = (seq % PENDING as u64) as usize;
        if let Some(c) = self.pending[slot].filter(|c| c.answers_seq == seq) {
            self.pending[slot] = None;
            return Ok(self.take(Some(c)));
        }
        while let Some(c) = ports.commands.receive()? {
            if c.answers_seq == seq {
                return Ok(self.take(Some(c)));
            }
            if drain && c.answers_seq < seq {
                continue;
            }
            if self.resync && c.answers_seq > seq && c.answers_seq < seq + PENDING as u64 {
                // The command awaited died with the old current loop; the new one starts
                // after it: this period gets no voltage, the next takes the new command.
                self.pending[(c.answers_seq % PENDING as u64) as usize] = Some(c);
                return Ok(self.take(None));
            }
            if c.answers_seq < seq || c.answers_seq >= seq + PENDING as u64 {
                return Err(RunError::node(
                    Role::Plant,
                    OutOfOrderCommand {
                        got: c.answers_seq,
                        expected: seq,
                    },
                ));
            }
            self.pending[(c.answers_seq % PENDING as u64) as usize] = Some(c);
        }
        self.watch_current_loop(ports, cx.now())?;
        Ok(Poll::Pending)
    }

    /// Lockstep: the command for the coming period is decided (`None`: none will come).
    fn take(&mut self, command: Option<DriveCommand>) -> Poll {
        self.resync &= command.is_none();
        self.next = command;
        self.waiting_since_ns = None;
        Poll::READY
    }

    fn poll_realtime(&mut self, ports: &mut PlantPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        let k = self.sim.sample_index();
        let last = k + 1 == self.samples;
        self.publish_state(ports, cx, last)?;
        if last {
            return Ok(Poll::Finished);
        }
        self.take_resets(ports)?;
        // Everything that arrived since the last period.
        let next_needed = k.saturating_sub(self.delay);
        while let Some(c) = ports.commands.receive()? {
            let now = cx.now();
            cx.stats.hop.record(now.saturating_sub(c.publish_time_ns));
            cx.stats
                .sensor_to_actuator
                .record(c.publish_time_ns.saturating_sub(c.state_publish_time_ns));
            self.slot.offer(c, next_needed);
        }
        if let Some(plans) = &mut ports.plans {
            // In place: a plan is ~2 KB and only the freshest is kept.
            let slot = &mut self.slot;
            plans.drain(&mut |plan| slot.offer_plan(plan))?;
        }
        Ok(Poll::READY)
    }
}

impl Node for PlantNode {
    type Ports = PlantPorts;

    fn role(&self) -> Role {
        Role::Plant
    }

    fn pace(&self) -> Pace {
        match self.settings.mode {
            Mode::Lockstep => Pace::Input,
            _ => Pace::Clock {
                period_ns: self.period_ns,
                late: Late::Pause,
            },
        }
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn awaiting(&self) -> String {
        match (self.peers, self.awaited()) {
            (Some(p), _) if !self.started => format!(
                "the current loop, the position loop and {} state subscribers (command publishers {}, setpoint publishers {}, state subscribers {})",
                self.settings.wait_subscribers,
                p.command_publishers,
                p.setpoint_publishers,
                p.state_subscribers
            ),
            (_, Some((seq, _))) if self.settings.mode == Mode::Lockstep => {
                format!("the command for sample {seq} from the current loop")
            }
            _ => "the current loop".to_string(),
        }
    }

    fn start(&mut self, ports: &mut PlantPorts, cx: &mut Cx) -> Result<Start, RunError> {
        let p = &ports.presence;
        let peers = Peers {
            command_publishers: p.publishers(Topic::Command),
            setpoint_publishers: p.publishers(Topic::Setpoint),
            state_subscribers: p.subscribers(Topic::State),
        };
        if self.peers.is_none() {
            tracing::info!(
                waiting_for = self.settings.wait_subscribers,
                "plant up; waiting for the current loop, the position loop and subscribers"
            );
        }
        self.peers = Some(peers);
        let ready = peers.command_publishers >= 1
            && (peers.setpoint_publishers >= 1 || !self.settings.wait_position_loop)
            && peers.state_subscribers >= self.settings.wait_subscribers;
        self.started = ready;
        Ok(match (ready, self.settings.mode) {
            (false, _) => Start::Waiting,
            (true, Mode::Lockstep) => Start::NOW,
            (true, _) => Start::Ready {
                epoch_ns: Some(cx.now() + self.settings.start_delay_ns),
            },
        })
    }

    fn connect(&mut self, ports: &mut PlantPorts) -> Result<(), RunError> {
        ports.states.connect()?;
        Ok(())
    }

    fn poll(&mut self, ports: &mut PlantPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        match self.settings.mode {
            Mode::Lockstep => self.poll_lockstep(ports, cx),
            _ => self.poll_realtime(ports, cx),
        }
    }

    fn step(&mut self, _ports: &mut PlantPorts, _cx: &mut Cx) -> Result<Flow, RunError> {
        self.apply_reset();
        if self.settings.mode == Mode::Lockstep {
            if self.sim.sample_index() + 1 == self.samples {
                return Ok(Flow::Last);
            }
            self.sim.advance(self.next.take().as_ref());
            self.emitted = false;
        } else if self
            .sim
            .advance_realtime(&mut self.slot, self.settings.watchdog_periods)
        {
            tracing::error!(
                periods = self.slot.runs.current,
                at_s = self.sim.sample_index() as f64 / self.rate_hz,
                "the current loop is silent: no command for the watchdog's periods; outputs \
                 off, fault latched until `stepdrive reset` (once commands come again)"
            );
        }
        Ok(Flow::Continue)
    }

    fn awaiting_rejoin(&self) -> bool {
        self.current_loop_gone
    }

    fn report(&self, stats: &mut StatsReport) {
        if self.settings.mode != Mode::Lockstep {
            // The plant's misses are the commands it lacked; its own lateness shows as
            // overruns.
            self.slot.copy_counters(stats);
        }
    }

    fn stop(&mut self, _ports: &mut PlantPorts, _cx: &mut Cx) {
        if self.settings.mode != Mode::Lockstep {
            tracing::debug!(
                misses = self.slot.misses,
                miss_runs_1_2_4_8_16_32_64_128 = ?self.slot.runs.by_length,
                "plant's command record"
            );
        }
    }
}
