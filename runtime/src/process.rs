//! One role as one process: the real-time settings its deployment gives it, the stack's
//! iceoryx2 ports, its node, run to the end of the run by the [`Runner`]. Every role's
//! process goes through [`run_process`].

use crate::deploy::{Deployment, Process};
use crate::error::RunError;
use crate::ipc::{IpcBus, Stamp};
use crate::node::Node;
use crate::port::PortFactory;
use crate::runner::{Finished, Runner, Settings};
use std::time::Duration;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::Scenario;

/// Which process of which stack this is.
#[derive(Debug, Clone)]
pub struct ProcessSpec<'a> {
    pub instance: &'a str,
    pub mode: Mode,
    pub process: Process,
    /// The iceoryx2 node name under the instance ("plant", "current-loop", ...).
    pub node_name: &'a str,
    pub deployment: &'a Deployment,
    /// Every process of the stack must run this one (see [`Stamp`]).
    pub scenario: &'a Scenario,
}

/// How long the final statistics stay published before the ports go away, so that the
/// monitor (draining at ~1 kHz) takes them.
const STATS_LINGER: Duration = Duration::from_millis(200);

/// Applies the real-time settings, opens the ports, builds the node with `build`, and runs
/// it. Statistics are published in realtime and hardware modes. Returns the node and its
/// final statistics.
pub fn run_process<N: Node>(
    spec: &ProcessSpec,
    build: impl FnOnce(&mut IpcBus) -> Result<(N, N::Ports), RunError>,
) -> Result<Finished<N>, RunError> {
    let d = spec.deployment;
    // Before any port exists: mlockall then locks every segment as it is mapped, and a
    // peer that waits for this process's publishers sees them only once it is set up.
    d.rt(spec.process, spec.mode).apply()?;
    let stamp = Stamp::new(spec.mode, spec.scenario);
    let mut bus = IpcBus::open(spec.instance, spec.node_name, &stamp)?;
    let (node, ports) = build(&mut bus)?;
    let realtime = spec.mode != Mode::Lockstep;
    let stats_port = if realtime {
        Some(bus.publisher()?)
    } else {
        None
    };
    let settings = Settings {
        wait: d.wait(spec.process, spec.mode),
        startup_timeout: d.startup_timeout(),
        peer_timeout: d.peer_timeout(),
        // In hardware mode the loop sleeps on the bridge's event, whose length it does not
        // choose, so it cannot tell a hold from a wait.
        account_host_holds: spec.process == Process::CurrentLoop && spec.mode == Mode::Realtime,
        linger: STATS_LINGER,
    };
    tracing::info!(
        instance = spec.instance,
        mode = spec.mode.as_str(),
        wait = %settings.wait,
        "{} up",
        spec.node_name
    );
    Runner::new(node, ports, settings, stats_port).run()
}
