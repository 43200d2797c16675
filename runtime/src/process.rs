//! One role as one process: the real-time settings its deployment gives it, the stack's
//! iceoryx2 ports, its node, run to the end of the run by the [`Runner`]. Every role's
//! process goes through [`run_process`].

use crate::deploy::Deployment;
use crate::doorbell::Waiter;
use crate::error::RunError;
use crate::ipc::{IpcBus, ScenarioBoard, Stamp};
use crate::node::{Node, Role};
use crate::port::PortFactory;
use crate::runner::{Finished, Runner, Settings};
use std::time::Duration;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stack::Slot;
use stepdrive_shared::Scenario;

/// Which process of which stack this is.
#[derive(Debug, Clone)]
pub struct ProcessSpec<'a> {
    pub instance: &'a str,
    pub mode: Mode,
    /// Its place: its deployment's placement, its iceoryx2 node name under the instance
    /// (`Role::id`).
    pub role: Role,
    pub deployment: &'a Deployment,
    /// Every process of the stack must run this one (see [`Stamp`]).
    pub scenario: &'a Scenario,
}

/// How long the final statistics stay published before the ports go away, so that the
/// monitor (draining at ~1 kHz) takes them.
const STATS_LINGER: Duration = Duration::from_millis(200);

/// A role's process, set up: its real-time settings applied, its statistics port open.
/// Build the role's node on the bus [`Process::open`] returns, then [`Process::run`] it.
pub struct Process<'a> {
    spec: &'a ProcessSpec<'a>,
    stats: Option<Box<dyn crate::port::Publish<stepdrive_shared::stats::StatsReport>>>,
    /// Lockstep: the doorbell its node sleeps on; on the wall clock, the position loop's,
    /// rung by clients' commands.
    bell: Option<Waiter>,
    /// The device announces the stack's scenario to anyone attaching, for as long as it
    /// runs.
    _scenario: Option<ScenarioBoard>,
}

impl<'a> Process<'a> {
    /// Applies the real-time settings and opens the stack's ports: the process, and the bus
    /// its node's ports are opened on.
    pub fn open(spec: &'a ProcessSpec<'a>) -> Result<(Self, IpcBus), RunError> {
        // Before any port exists: mlockall then locks every segment as it is mapped, and a
        // peer that waits for this process's publishers sees them only once it is set up.
        spec.deployment.rt(spec.role, spec.mode).apply()?;
        if spec.mode == Mode::Lockstep {
            let allowed = crate::rt::allowed_cpus();
            if let Some(cpu) = crate::doorbell::placement(spec.role, spec.instance, &allowed) {
                if let Err(e) = crate::rt::pin_to_cpu(cpu) {
                    tracing::debug!(cpu, error = %e, "cannot take this process's lockstep CPU");
                }
            }
        }
        let stamp = Stamp::new(spec.mode, spec.scenario);
        let mut bus = IpcBus::open(spec.instance, spec.role.id(), &stamp)?;
        // Statistics are published in realtime and hardware modes.
        let stats = match spec.mode {
            Mode::Lockstep => None,
            _ => Some(bus.publisher()?),
        };
        let scenario = match spec.role.slot() {
            Some(Slot::Device) => Some(bus.announce_scenario(spec.scenario)?),
            _ => None,
        };
        Ok((
            Self {
                spec,
                stats,
                bell: match spec.mode {
                    Mode::Lockstep => bus.doorbells().map(|d| d.waiter(spec.role)),
                    // On the wall clock a client's command wakes the position loop between
                    // its ticks.
                    _ if spec.role == Role::PositionLoop => Some(
                        crate::doorbell::Doorbells::open(spec.instance)
                            .map_err(crate::port::PortError::from)?
                            .waiter(spec.role),
                    ),
                    _ => None,
                },
                _scenario: scenario,
            },
            bus,
        ))
    }

    /// Runs `node` to the end of the run. Returns it and its final statistics.
    pub fn run<N: Node>(&mut self, node: N, ports: N::Ports) -> Result<Finished<N>, RunError> {
        let spec = self.spec;
        let d = spec.deployment;
        let settings = Settings {
            // A process started by hand waits as the same process started by `run`.
            wait: d
                .clone()
                .for_axes(spec.scenario.axis_count())
                .wait(spec.role, spec.mode),
            startup_timeout: d.startup_timeout(),
            peer_timeout: d.peer_timeout(),
            // In hardware mode the loop sleeps on the bridge's event, whose length it does
            // not choose, so it cannot tell a hold from a wait.
            account_host_holds: spec.role == Role::CurrentLoop && spec.mode == Mode::Realtime,
            linger: STATS_LINGER,
            report_end: true,
        };
        tracing::info!(
            instance = spec.instance,
            mode = spec.mode.as_str(),
            wait = %settings.wait,
            "{} up",
            spec.role
        );
        Runner::new(node, ports, settings, self.stats.take())
            .with_doorbell(self.bell.take())
            .run()
    }
}

/// Applies the real-time settings, opens the ports, builds the node with `build`, and runs
/// it. Returns the node and its final statistics.
pub fn run_process<N: Node>(
    spec: &ProcessSpec,
    build: impl FnOnce(&mut IpcBus) -> Result<(N, N::Ports), RunError>,
) -> Result<Finished<N>, RunError> {
    let (mut process, mut bus) = Process::open(spec)?;
    let (node, ports) = build(&mut bus)?;
    process.run(node, ports)
}
