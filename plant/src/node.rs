//! The simulated plant as a node of the runner. Each cycle publishes the state at sample k,
//! takes the commands, and integrates one period by one set of rules ([`CommandSlot`]): the
//! command for (t_k, t_{k+1}] is the one answering sample k − d; one not there is a miss,
//! covered by the freshest plan or the held voltage, and a watchdog's worth in a row turns
//! the outputs off. Paced by its input (lockstep) the plant is the clock: it waits until
//! the command its period needs is there, so there are no misses and runs are
//! bit-identical. On its own clock (realtime) it waits for nobody; when the host holds the
//! process past a period, its simulated time pauses ([`Late::Pause`]).
//!
//! A latched fault stays until a reset request (`stepdrive reset`) arrives while its cause
//! is gone. A current loop that dies and is restarted rejoins: on the clock its commands
//! are simply taken again; paced by its input the plant waits for a new one (within the
//! start-up timeout), which starts from the newest state, and the periods whose commands
//! died with the old one are misses.

use crate::sim::{CommandSlot, PlantSim};
use stepdrive_runtime::inbox::Inbox;
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{PortError, PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{fault_bits, DriveCommand, DrivePlan, DriveState, ResetRequest};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};
use stepdrive_shared::stack::PLANT;
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

/// Lockstep: after this long without the awaited command, and then at most this often, the
/// plant looks for dead peers.
const LOOK_FOR_THE_DEAD_NS: u64 = 200_000_000;
/// Lockstep: after this long without the awaited command the plant watches the current loop
/// leave and another attach.
const WATCH_AFTER_NS: u64 = 100_000;

/// What the plant reads and writes.
pub struct PlantPorts {
    pub states: Box<dyn Publish<DriveState>>,
    pub commands: Inbox<DriveCommand>,
    /// Realtime: the current loop's voltage plans (a lockstep plant waits for every command).
    pub plans: Option<Box<dyn Subscribe<DrivePlan>>>,
    pub resets: Box<dyn Subscribe<ResetRequest>>,
    pub presence: Box<dyn Presence>,
}

impl PlantPorts {
    pub fn open(f: &mut impl PortFactory, mode: Mode) -> Result<Self, PortError> {
        Ok(Self {
            commands: Inbox::open(f, &PLANT, mode, LOOP_BUFFER)?,
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
    /// Misses in a row after which the outputs go off and a fault latches.
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

/// A plant paced by its input (lockstep) waits for the current loop's command; while it
/// waits, it watches the current loop leave and another attach (a restarted process).
#[derive(Debug, Clone, Copy, Default)]
struct Rejoin {
    /// The current loop left (its publisher is gone).
    gone: bool,
    /// Since when the awaited command has been awaited, and when dead peers were last
    /// looked for.
    waiting_since_ns: Option<u64>,
    dead_checked_ns: u64,
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
    /// The current sample's state is out.
    emitted: bool,
    /// The command rules: which command, plan entry or held voltage each period gets.
    slot: CommandSlot,
    /// A reset request waiting for the next period (the requester's pid).
    reset_requested: Option<u32>,
    rejoin: Rejoin,
}

impl PlantNode {
    pub fn new(scenario: &Scenario, settings: PlantSettings) -> Self {
        let delay = u64::from(scenario.rates.compute_delay_periods);
        let mut sim = PlantSim::new(scenario);
        // A commanded stack starts disabled, its rotor on the brake; the paper's experiment
        // starts enabled, with none.
        if !scenario.runs_profile() {
            sim.fit_brake(scenario.plant.brake.holding_torque_nm);
        }
        Self {
            sim,
            samples: scenario.sample_count(),
            delay,
            period_ns: scenario.sample_period_ns(),
            rate_hz: scenario.rates.current_loop_hz,
            settings,
            peers: None,
            started: false,
            emitted: false,
            slot: CommandSlot::new(delay),
            reset_requested: None,
            rejoin: Rejoin::default(),
        }
    }

    /// The command rules' counters (misses, plan coverage, runs).
    pub fn slot(&self) -> &CommandSlot {
        &self.slot
    }

    fn is_last(&self) -> bool {
        self.sim.sample_index() + 1 == self.samples
    }

    fn publish_state(&mut self, ports: &mut PlantPorts, cx: &Cx) -> Result<(), RunError> {
        let mut state = self.sim.state(self.is_last());
        state.deadline_ns = cx.deadline_ns;
        state.publish_time_ns = cx.now();
        ports.states.publish(&state)?;
        Ok(())
    }

    /// The command the period after sample k waits for: the one its delay line needs, or
    /// at the last sample the answer to it (so the current loop finishes before our
    /// subscriber goes away). `None` while the delay line fills.
    fn awaited(&self) -> Option<u64> {
        match self.is_last() {
            true => Some(self.sim.sample_index()),
            false => self.sim.needed_command(),
        }
    }

    /// Whether the awaited command is decided: here, or never to come (a newer one is here:
    /// the current loop that would have sent it was replaced).
    fn decided(&self) -> bool {
        self.awaited()
            .is_none_or(|seq| self.slot.newest().is_some_and(|newest| newest >= seq))
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
        if fault & fault_bits::COMMAND_TIMEOUT != 0 && silent >= self.settings.watchdog_periods {
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

    /// Paced by its input: watches the current loop leave and another attach. Its history
    /// brings the newcomer the newest state at once, and its stream starts where it
    /// joined. A loop killed outright still counts until its ports are removed, so after a
    /// while without its command the plant looks for dead peers.
    fn watch_current_loop(&mut self, ports: &mut PlantPorts, now: u64) -> Result<(), RunError> {
        let r = &mut self.rejoin;
        let since = *r.waiting_since_ns.get_or_insert(now);
        // Counting the peers walks iceoryx2's port tables: not on every poll of a hand-off
        // that takes a few µs.
        if now.saturating_sub(since) < WATCH_AFTER_NS {
            return Ok(());
        }
        if now.saturating_sub(since) > LOOK_FOR_THE_DEAD_NS
            && now.saturating_sub(r.dead_checked_ns) > LOOK_FOR_THE_DEAD_NS
        {
            r.dead_checked_ns = now;
            ports.presence.forget_dead();
        }
        let subscribers = ports.presence.subscribers(Topic::State);
        if subscribers != r.state_subscribers {
            r.state_subscribers = subscribers;
            ports.states.connect()?;
        }
        let present = ports.presence.publishers(Topic::Command) > 0;
        if !present && !r.gone {
            r.gone = true;
            tracing::error!(
                "the current loop is gone; waiting for another to attach (start-up timeout)"
            );
        } else if present && r.gone {
            r.gone = false;
            ports.commands.rejoin();
            tracing::warn!("a current loop attached; resuming from the newest sample");
        }
        Ok(())
    }
}

/// Each axis's plant is on its own in a multi-axis stack.
impl stepdrive_runtime::lanes::Together for PlantNode {}

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
            (_, Some(seq)) if self.pace() == Pace::Input => {
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
            tracing::debug!(
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

    /// Publishes the sample's state (once), takes what arrived: resets, every command, the
    /// freshest plan. Ready when the command the coming period waits for is decided; on
    /// its own clock the period comes anyway, and a command not there is a miss.
    fn poll(&mut self, ports: &mut PlantPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        if !self.emitted {
            self.publish_state(ports, cx)?;
            self.emitted = true;
            // Once a sample on the clock; in lockstep every 16th: polling an empty queue
            // costs a hand-off its latency.
            if self.pace() != Pace::Input || self.sim.sample_index().is_multiple_of(16) {
                self.take_resets(ports)?;
            }
        }
        let next_needed = self.sim.sample_index().saturating_sub(self.delay);
        while let Some(t) = ports.commands.take()? {
            let c = t.message;
            let now = cx.now();
            cx.stats.hop.record(now.saturating_sub(c.publish_time_ns));
            cx.stats
                .sensor_to_actuator
                .record(c.publish_time_ns.saturating_sub(c.state_publish_time_ns));
            self.slot.offer(c, next_needed);
        }
        if let Some(plans) = &mut ports.plans {
            // In place: a plan is ~8 KB and only the freshest is kept.
            let slot = &mut self.slot;
            plans.drain(&mut |plan| slot.offer_plan(plan))?;
        }
        let clocked = self.pace() != Pace::Input;
        if self.is_last() && (clocked || self.decided()) {
            // The run ends at its last sample: on the clock at once, paced by its input once
            // the answer to it is in (the current loop then finishes before this plant goes).
            return Ok(Poll::Finished);
        }
        if self.decided() {
            self.rejoin.waiting_since_ns = None;
            return Ok(Poll::READY);
        }
        if !clocked {
            self.watch_current_loop(ports, cx.now())?;
        }
        Ok(Poll::Pending)
    }

    /// The period after the sample: the command the delay line needs, or (missing) the
    /// freshest plan's entry or the held voltage; a watchdog's worth of misses in a row
    /// turns the outputs off.
    fn step(&mut self, _ports: &mut PlantPorts, _cx: &mut Cx) -> Result<Flow, RunError> {
        self.apply_reset();
        if self
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
        self.emitted = false;
        Ok(Flow::Continue)
    }

    fn awaiting_rejoin(&self) -> bool {
        self.rejoin.gone
    }

    fn latched_fault(&self) -> u32 {
        self.sim.fault()
    }

    fn report(&self, stats: &mut StatsReport) {
        // The plant's misses are the commands it lacked; its own lateness shows as overruns.
        self.slot.copy_counters(stats);
    }

    fn stop(&mut self, _ports: &mut PlantPorts, _cx: &mut Cx) {
        tracing::debug!(
            misses = self.slot.misses,
            miss_runs_1_2_4_8_16_32_64_128 = ?self.slot.runs.by_length,
            "plant's command record"
        );
    }
}
