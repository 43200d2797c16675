//! The stack's nodes built from its declaration (`stepdrive_shared::stack`): each role's
//! node and ports, built the same way for a process (`stepdrive plant`, `current-loop`, ...)
//! and for the in-process simulation. What differs is only what is done with them
//! ([`Assemble`]): run on the wall clock in a process, or stepped with the others on
//! virtual time.

use stepdrive_bridge::link::{EncoderCalibration, HeldLoad};
use stepdrive_bridge::node::{drive_addresses, StartGate};
use stepdrive_bridge::{BridgeNode, BridgePorts, BridgeSettings, DriveAddr};
use stepdrive_control::identify::Bounds;
use stepdrive_controller::current_loop_node::{CurrentLoopNode, CurrentLoopPorts};
use stepdrive_controller::identify_node::{IdentifyNode, IdentifyPorts};
use stepdrive_controller::position_loop_node::{PositionLoopNode, PositionLoopPorts};
use stepdrive_plant::node::{PlantNode, PlantPorts, PlantSettings};
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::lanes::Lanes;
use stepdrive_runtime::node::Node;
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_runtime::port::PortFactory;
use stepdrive_runtime::RunError;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::Topic;
use stepdrive_shared::stack::{Role, Stack};
use stepdrive_shared::{Method, Scenario};

/// Realtime: the plant's first deadline this long after it sees its peers, so that every
/// process is in its loop by then. A peer's ports exist before its loop runs; with 20 ms a
/// position loop on a loaded two-core machine (CI) came ~40 ms after the plant's start,
/// the current loop kept the outputs off until its first setpoint, and the loaded rotor
/// was pushed a period behind the profile by t = 0.0406 s (STEPPED OUT, four CI runs in
/// one day). 200 ms costs that much once per run.
const START_DELAY_NS: u64 = 200_000_000;

/// What building a stack's nodes needs beside the declaration.
#[derive(Debug, Clone)]
pub struct Setup<'a> {
    pub scenario: &'a Scenario,
    pub mode: Mode,
    pub deployment: &'a Deployment,
    /// The current loop's method.
    pub method: Method,
    /// State subscribers the device waits for before its first sample (the stack's readers,
    /// and a monitor).
    pub state_readers: usize,
    /// The device waits for a position loop too.
    pub position_loop: bool,
    /// Processes on the wall clock (a start-up delay, the position loop's ticks half a
    /// period after the samples, a watch on the setpoints' freshness), or one thread of a
    /// simulation.
    pub wall_clock: bool,
    /// The identification's bounds.
    pub bounds: Bounds,
}

impl<'a> Setup<'a> {
    /// The setup of `stack`'s nodes, the device waiting for `monitors` more state readers.
    pub fn new(
        scenario: &'a Scenario,
        stack: &Stack,
        deployment: &'a Deployment,
        monitors: usize,
        wall_clock: bool,
    ) -> Self {
        Self {
            scenario,
            mode: stack.mode,
            deployment,
            method: Method::Proposed,
            state_readers: stack.readers(Topic::State) + monitors,
            position_loop: stack.has_writer(Topic::Setpoint),
            wall_clock,
            bounds: Bounds::default(),
        }
    }

    /// Whether `role` waits on the bridge's state-ready event (`--wait event`), which only a
    /// bridge raises.
    fn waits_on_event(&self, role: Role) -> Result<bool, RunError> {
        let event = self.deployment.wait(role, self.mode) == WaitStrategy::Event;
        if event && self.mode != Mode::Hardware {
            return Err(RunError::node(role, NoEvent));
        }
        Ok(event)
    }
}

/// `--wait event` outside hardware mode.
#[derive(Debug, thiserror::Error)]
#[error(
    "--wait event needs a plant that raises state-ready: only the bridge does (--mode hardware)"
)]
pub struct NoEvent;

/// A role without a node that can be built here.
#[derive(Debug, thiserror::Error)]
pub enum AssembleError {
    #[error("the {0} is not a node of the stack")]
    NotANode(Role),
    #[error("in hardware mode the plant is a bridge to a drive: give it with --drive HOST:PORT (or a serial device path)")]
    NoDrive,
    #[error(transparent)]
    BadDrive(#[from] stepdrive_bridge::node::BadDriveAddr),
    #[error("{axes} axes need {axes} drive addresses (--drive A,B,...: one per axis, in axis order); {given} given")]
    DriveAddresses { axes: usize, given: usize },
    #[error("the {role} serves one axis; this scenario has {axes} ([[axis]] tables): a multi-axis stack runs in lockstep or realtime with the simulated plant")]
    OneAxisOnly { role: Role, axes: usize },
    #[error("--wait event is for the current loop; the bridge waits for the drive's frames with sleep, spin or hybrid:<µs>")]
    BridgeEvent,
}

/// What is done with each node once built.
pub trait Assemble {
    type Out;
    fn node<N: Node + 'static>(&mut self, node: N, ports: N::Ports) -> Result<Self::Out, RunError>;
}

/// Builds `role`'s node and ports on `bus` and hands them to `a`.
pub fn assemble<A: Assemble>(
    role: Role,
    setup: &Setup,
    bus: &mut impl PortFactory,
    a: &mut A,
) -> Result<A::Out, RunError> {
    if setup.scenario.axis_count() > 1 {
        return assemble_axes(role, setup, bus, a);
    }
    match role {
        Role::Plant => {
            let (n, p) = plant(setup, bus)?;
            a.node(n, p)
        }
        Role::Bridge => {
            let (n, p) = bridge(setup, bus)?;
            a.node(n, p)
        }
        Role::CurrentLoop => {
            let (n, p) = current_loop(setup, bus)?;
            a.node(n, p)
        }
        Role::PositionLoop => {
            let (n, p) = position_loop(setup, bus, 0)?;
            a.node(n, p)
        }
        Role::Identify => {
            let (n, p) = identify(setup, bus)?;
            a.node(n, p)
        }
        Role::EmulatedDrive | Role::Monitor | Role::Tool(_) => {
            Err(RunError::node(role, AssembleError::NotANode(role)))
        }
    }
}

/// A multi-axis stack's `role`: one node per axis, each built from its axis's scenario on
/// its axis's ports, stepped as one ([`Lanes`]).
fn assemble_axes<A: Assemble, B: PortFactory>(
    role: Role,
    setup: &Setup,
    bus: &mut B,
    a: &mut A,
) -> Result<A::Out, RunError> {
    match role {
        Role::Plant => {
            let (n, p) = lanes_of(setup, bus, |s, b, _| plant(s, b))?;
            a.node(n, p)
        }
        Role::CurrentLoop => {
            let (n, p) = lanes_of(setup, bus, |s, b, axis| {
                current_loop(s, b).map(|(n, p)| (n.for_axis(axis), p))
            })?;
            a.node(n, p)
        }
        Role::PositionLoop => {
            let axes = setup.scenario.axis_count();
            let (n, p) = lanes_of(setup, bus, |lane, bus, axis| {
                let (node, ports) = position_loop(lane, bus, axis)?;
                Ok((node.in_stack_of(axes), ports))
            })?;
            a.node(n, p)
        }
        Role::Bridge => {
            let axes = setup.scenario.axis_count();
            let given = setup
                .deployment
                .drive
                .address
                .as_deref()
                .map_or(0, |a| drive_addresses(a).len());
            if given != axes {
                return Err(RunError::node(
                    role,
                    AssembleError::DriveAddresses { axes, given },
                ));
            }
            // The drives are enabled together, once every one has aligned.
            let gate = StartGate::new(axes);
            let (n, p) = lanes_of(setup, bus, |lane, bus, axis| {
                let (node, ports) = bridge_of(lane, bus, axis)?;
                Ok((node.with_start_gate(gate.clone()), ports))
            })?;
            a.node(n, p)
        }
        Role::Identify => Err(RunError::node(
            role,
            AssembleError::OneAxisOnly {
                role,
                axes: setup.scenario.axis_count(),
            },
        )),
        Role::EmulatedDrive | Role::Monitor | Role::Tool(_) => {
            Err(RunError::node(role, AssembleError::NotANode(role)))
        }
    }
}

/// Every axis's node of one role, built by `build` from the axis's setup on its ports.
fn lanes_of<N: Node, B: PortFactory>(
    setup: &Setup,
    bus: &mut B,
    build: impl Fn(&Setup, &mut B, u32) -> Result<(N, N::Ports), RunError>,
) -> Result<(Lanes<N>, Vec<N::Ports>), RunError> {
    let axes = setup.scenario.axis_count();
    let (mut nodes, mut ports) = (Vec::with_capacity(axes), Vec::with_capacity(axes));
    for axis in 0..axes {
        let Some(scenario) = setup.scenario.for_axis(axis) else {
            unreachable!("axis {axis} is below the axis count {axes}")
        };
        bus.set_axis(axis as u32);
        let lane = Setup {
            scenario,
            ..setup.clone()
        };
        let (n, p) = build(&lane, bus, axis as u32)?;
        nodes.push(n);
        ports.push(p);
    }
    bus.set_axis(0);
    Ok((Lanes::new(nodes, setup.mode == Mode::Lockstep), ports))
}

/// The simulated plant.
pub fn plant(
    setup: &Setup,
    bus: &mut impl PortFactory,
) -> Result<(PlantNode, PlantPorts), RunError> {
    let settings = PlantSettings {
        mode: setup.mode,
        wait_subscribers: setup.state_readers,
        wait_position_loop: setup.position_loop,
        watchdog_periods: setup.deployment.watchdog_periods,
        start_delay_ns: if setup.wall_clock { START_DELAY_NS } else { 0 },
    };
    Ok((
        PlantNode::new(setup.scenario, settings),
        PlantPorts::open(bus, setup.mode)?,
    ))
}

/// The bridge to the deployment's drive.
pub fn bridge(
    setup: &Setup,
    bus: &mut impl PortFactory,
) -> Result<(BridgeNode, BridgePorts), RunError> {
    bridge_of(setup, bus, 0)
}

/// The bridge to `axis`'s drive: the deployment's drive address of that axis (a
/// multi-axis stack's `--drive A,B,...`, one per axis).
fn bridge_of(
    setup: &Setup,
    bus: &mut impl PortFactory,
    axis: u32,
) -> Result<(BridgeNode, BridgePorts), RunError> {
    let settings = bridge_settings(setup, axis as usize)?;
    let node = BridgeNode::new(setup.scenario, settings.clone())?;
    let ports = BridgePorts::open(bus, &settings.drive)?;
    Ok((node, ports))
}

/// The current loop with the setup's method.
pub fn current_loop(
    setup: &Setup,
    bus: &mut impl PortFactory,
) -> Result<(CurrentLoopNode, CurrentLoopPorts), RunError> {
    let event = setup.waits_on_event(Role::CurrentLoop)?;
    let mut node = CurrentLoopNode::new(setup.scenario, setup.method, setup.mode);
    if setup.wall_clock {
        node = node.watching_setpoints(setup.deployment.peer_timeout());
    }
    Ok((node, CurrentLoopPorts::open(bus, setup.mode, event)?))
}

/// The position loop.
pub fn position_loop(
    setup: &Setup,
    bus: &mut impl PortFactory,
    axis: u32,
) -> Result<(PositionLoopNode, PositionLoopPorts), RunError> {
    // Half a current period after the plant's samples: each tick finds its sample out. In
    // one thread the plant simply goes first.
    let s = setup.scenario;
    let phase_ns = if setup.wall_clock {
        s.sample_period_ns() / 2
    } else {
        0
    };
    Ok((
        PositionLoopNode::new(s, axis, setup.mode, phase_ns)?,
        PositionLoopPorts::open(bus, setup.mode)?,
    ))
}

/// The identification sequence, in the current loop's place.
pub fn identify(
    setup: &Setup,
    bus: &mut impl PortFactory,
) -> Result<(IdentifyNode, IdentifyPorts), RunError> {
    let event = setup.waits_on_event(Role::Identify)?;
    Ok((
        IdentifyNode::new(setup.scenario, setup.bounds, setup.mode),
        IdentifyPorts::open(bus, setup.mode, event)?,
    ))
}

/// The bridge's settings: the deployment's drive link, the scenario's load for the
/// alignment's rest angle.
fn bridge_settings(setup: &Setup, axis: usize) -> Result<BridgeSettings, RunError> {
    let d = setup.deployment;
    let s = setup.scenario;
    let bad = |e: AssembleError| RunError::node(Role::Bridge, e);
    let addresses = d
        .drive
        .address
        .as_deref()
        .ok_or(AssembleError::NoDrive)
        .map_err(bad)?;
    // One drive per axis, in axis order ([`assemble_axes`] checks their count).
    let list = drive_addresses(addresses);
    let drive: DriveAddr = list
        .get(axis)
        .ok_or(AssembleError::DriveAddresses {
            axes: axis + 1,
            given: list.len(),
        })
        .map_err(bad)?
        .parse()
        .map_err(|e| bad(AssembleError::BadDrive(e)))?;
    let wait = d.wait(Role::Bridge, setup.mode);
    if wait == WaitStrategy::Event {
        return Err(bad(AssembleError::BridgeEvent));
    }
    Ok(BridgeSettings {
        drive,
        wait_subscribers: setup.state_readers,
        wait_position_loop: setup.position_loop,
        silence_periods: d.drive.silence_periods,
        plan_every: d.drive.plan_every,
        observer_hz: d.drive.observer_hz,
        calibration: EncoderCalibration {
            offset_counts: d.drive.encoder_offset_counts,
            reverse: d.drive.reverse_encoder,
            held_load: Some(HeldLoad {
                torque_nm: s.load.torque_nm,
                torque_constant_nm_per_a: s.motor.torque_constant_nm_per_a,
                rotor_teeth: s.motor.n_r(),
            }),
        },
        look_for_answers: wait == WaitStrategy::Sleep,
    })
}
