//! Launches a stack from its declaration (`stepdrive_shared::stack`): one child process per
//! node, each this same binary with its role's sub-command and the run's scenario and
//! deployment files, so a launched stack behaves like one started by hand with those
//! files; an emulated drive too in hardware mode without a drive. Then the one
//! [`Supervisor`] watches it, and what it gathered becomes the run's report.

use crate::record::recording::Recording;
use crate::report::metrics::{Metrics, RunReport, TruthReport};
use crate::report::outcome::{Exit, Outcome};
use crate::supervise::children::{
    free_loopback_ports, path_arg, spawn_emulated_drive, RunFiles, Supervised,
};
use crate::supervise::cpus;
use crate::supervise::helpers::Helpers;
use crate::supervise::observer::{Observer, Stop};
use crate::supervise::standstill::{AxisLine, StopLimits, Stopper, WoundDown};
use crate::supervise::supervisor::{AxisFeed, Controls, Ending, Feeds, Supervisor, Until};
use anyhow::{Context, Result};
use std::path::PathBuf;
use std::process::ExitStatus;
use stepdrive_emulated_drive::truth::TruthRow;
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::ipc::{cleanup_dead_nodes, live_nodes, IpcBus, Stamp};
use stepdrive_runtime::port::PortFactory;
use stepdrive_shared::messages::DriveState;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, MONITOR_BUFFER};
use stepdrive_shared::stack::{stack, NodeDecl, Purpose, Role, Stack};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::{Method, Scenario};

#[derive(Debug, Clone)]
pub struct LaunchOptions {
    pub instance: String,
    pub mode: Mode,
    /// How every process runs; in hardware mode without `drive.address` an emulated drive
    /// is started on loopback.
    pub deployment: Deployment,
    /// Hardware mode with a drive of its own that simulates its motor (the emulated
    /// firmware): the file it writes the true rotor state to, read at each method's end.
    pub drive_truth: Option<PathBuf>,
}

/// Child exit codes that are the child's own verdict on the run (a latched fault, a
/// step-out), not a failure of the process: the monitor judges the run from the state
/// stream itself.
const VERDICT_EXIT_CODES: [i32; 2] = [3, 4];

/// A stack's processes, started, and the monitor's view of them.
struct Launched {
    children: Vec<Supervised>,
    files: RunFiles,
    /// Hardware mode without a drive: the emulated drive is the first child, and it writes
    /// the true rotor state here.
    emulated: bool,
    truth: Option<PathBuf>,
    /// Taken by the supervisor.
    feeds: Option<Feeds>,
    /// On the wall clock, a stack with a position loop: the lines to its axes that stop
    /// them before its processes go. Taken by the supervisor.
    stopper: Option<Stopper>,
    /// The monitor's iceoryx2 node: its subscribers must outlive the run.
    _bus: IpcBus,
    /// Realtime and hardware: the CPUs of its loops, held for the run.
    _cpu_claim: Option<cpus::CpuClaim>,
    /// Lockstep: CPUs that poll instead of halting while the stack runs (its hand-offs are
    /// wake-ups of the other CPU).
    _wakeups: Option<stepdrive_runtime::wakeup::WakeupLatencyHold>,
    deployment: Deployment,
}

/// What a node's process is started with, beside the stack's common arguments.
fn role_args(node: &NodeDecl, stack: &Stack, extra: &[String]) -> Vec<String> {
    let mut args = Vec::new();
    if node.role == stack.device().role {
        // The device waits for every reader of the state, the monitor's too, and for the
        // position loop only in a stack that has one.
        let readers = stack.readers(Topic::State) + 1;
        args.extend(["--wait-subscribers".to_string(), readers.to_string()]);
        if !stack.has_writer(Topic::Setpoint) {
            args.push("--no-position-loop".to_string());
        }
    }
    args.extend(extra.iter().cloned());
    args
}

/// Starts `stack`'s processes (each with `extra(role)` beside its own arguments) and
/// attaches the monitor to them; with `recording`, it takes the controls too.
fn launch(
    stack: &Stack,
    s: &Scenario,
    opts: &LaunchOptions,
    recording: bool,
    extra: &dyn Fn(Role) -> Vec<String>,
) -> Result<Launched> {
    let mode = opts.mode;
    let mut d = opts.deployment.clone();
    // At its own priority the monitor waits for the loops (see `deploy`).
    d.rt(Role::Monitor, mode).apply()?;
    let removed = cleanup_dead_nodes();
    if removed > 0 {
        tracing::warn!(
            removed,
            "removed resources of dead stepdrive/iceoryx2 nodes"
        );
    }
    // A second stack on a running stack's instance would read the first's samples as its
    // own (and its loops would answer them): refused before anything starts.
    let loops = [
        Role::Plant,
        Role::Bridge,
        Role::CurrentLoop,
        Role::PositionLoop,
    ];
    let busy = live_nodes(&opts.instance, &loops.map(|r| r.id()));
    if !busy.is_empty() {
        anyhow::bail!(
            "instance `{}` is in use by a running stack ({}): stop it, or give this one \
             another --instance",
            opts.instance,
            busy.join(", ")
        );
    }
    // Another realtime stack's loops on these CPUs: refused before anything starts.
    let cpu_claim = match mode {
        Mode::Lockstep => None,
        Mode::Realtime | Mode::Hardware => {
            let pinned: Option<Vec<usize>> =
                stack.nodes.iter().map(|n| d.rt(n.role, mode).cpu).collect();
            // A loop that floats may run on any CPU.
            let cpus = pinned.unwrap_or_else(|| {
                (0..std::thread::available_parallelism().map_or(1, |n| n.get())).collect()
            });
            let mut cpus = cpus;
            cpus.sort_unstable();
            cpus.dedup();
            Some(cpus::claim(&opts.instance, &cpus)?)
        }
    };
    let emulated = mode == Mode::Hardware && d.drive.address.is_none();
    if emulated {
        // A drive per axis, all in the one emulator process.
        let ports = free_loopback_ports(s.axis_count())?;
        let ports: Vec<String> = ports.iter().map(ToString::to_string).collect();
        d.drive.address = Some(ports.join(","));
    }
    let d = d.for_axes(s.axis_count());
    let files = RunFiles::write(s, &d.resolved(mode), &opts.instance)?;
    let common = files.process_args(mode, &opts.instance);

    // The monitor subscribes before the device may start: the device waits for it.
    let mut bus = IpcBus::open(&opts.instance, Role::Monitor.id(), &Stamp::new(mode, s))
        .context("cannot attach the monitor to the stack's services")?;
    let states = bus.subscriber::<DriveState>(MONITOR_BUFFER)?;
    let stats = bus.subscriber::<StatsReport>(4)?;
    // Recording (or a program's figures): the setpoints and the rest too, from the
    // first. The device still waits for the current loop's subscription before its first
    // sample, so the position loop (which starts once any setpoint subscriber is there) has
    // nothing to answer before.
    let controls = Controls::open(
        &mut bus,
        mode,
        recording,
        !s.for_axis(0).unwrap_or(s).runs_profile(),
    )?;
    // Every other axis is watched by the same rules: the devices wait for these too.
    let mut axes = Vec::with_capacity(s.axis_count() - 1);
    for axis in 1..s.axis_count() {
        let Some(own) = s.for_axis(axis) else {
            unreachable!("axis {axis} is below the axis count")
        };
        bus.set_axis(axis as u32);
        axes.push(AxisFeed {
            axis,
            states: bus.subscriber::<DriveState>(MONITOR_BUFFER)?,
            controls: Controls::open(&mut bus, mode, recording, !own.runs_profile())?,
        });
    }
    bus.set_axis(0);
    let stopper = match (mode, stack.node(Role::PositionLoop)) {
        (Mode::Realtime | Mode::Hardware, Some(_)) => {
            Some(open_stopper(&mut bus, s, mode, &d, &controls, &axes)?)
        }
        _ => None,
    };

    let mut children = Vec::with_capacity(stack.nodes.len() + 1);
    // Only an emulated drive knows where the rotor really is; it writes that beside the
    // run so that the report can set the truth against what the sensors said.
    let truth = match emulated {
        true => Some(std::env::temp_dir().join(format!(
            "{}{}-{}.csv",
            crate::supervise::children::TRUTH_PREFIX,
            std::process::id(),
            opts.instance
        ))),
        false => opts.drive_truth.clone(),
    };
    if let (true, Some(addr)) = (emulated, &d.drive.address) {
        children.push(spawn_emulated_drive(addr, &files, truth.as_deref())?);
    }
    for node in &stack.nodes {
        let mut args = common.to_vec();
        args.extend(role_args(node, stack, &extra(node.role)));
        children.push(Supervised::spawn(node.role, &args)?);
    }
    Ok(Launched {
        children,
        files,
        emulated,
        truth,
        feeds: Some(Feeds {
            states,
            stats,
            controls,
            axes,
        }),
        stopper,
        _bus: bus,
        _cpu_claim: cpu_claim,
        _wakeups: match mode {
            Mode::Lockstep => stepdrive_runtime::wakeup::hold_zero_wakeup_latency(),
            Mode::Realtime | Mode::Hardware => None,
        },
        deployment: d,
    })
}

/// One client of each axis's command service, and the axis's status where the supervisor's
/// controls do not read it: what stops the axes before the stack's processes go. Held for
/// the stack's life (a client of the 8 the service takes, so that a stop never finds it
/// full).
fn open_stopper(
    bus: &mut IpcBus,
    s: &Scenario,
    mode: Mode,
    d: &Deployment,
    controls: &Option<Controls>,
    axes: &[AxisFeed],
) -> Result<Stopper> {
    let mut lines = Vec::with_capacity(s.axis_count());
    for axis in 0..s.axis_count() {
        bus.set_axis(axis as u32);
        let read = match axis {
            0 => controls.as_ref(),
            n => axes.get(n - 1).and_then(|a| a.controls.as_ref()),
        }
        .is_some_and(|c| c.status.is_some());
        lines.push(AxisLine {
            commands: bus
                .command_client()
                .context("the launcher's client of the axis command service")?,
            status: match read {
                true => None,
                false => Some(bus.subscriber(4)?),
            },
            newest: None,
            limits: StopLimits::of(s, axis, mode, d.watchdog_periods),
        });
    }
    bus.set_axis(0);
    Ok(Stopper::new(lines))
}

/// The stop's words after why supervision ended; a stop that failed makes the run's
/// outcome a dead (stuck) process.
fn amend(stop: &mut Stop, w: &WoundDown) {
    // The processes were stopped after the motor: said in that order.
    let (why, then) = match stop.because.strip_suffix(STOPPED_ALL) {
        Some(why) => (
            why.to_string(),
            "; then all stack processes were stopped".to_string(),
        ),
        None => (stop.because.clone(), String::new()),
    };
    if w.ok() {
        stop.because = format!("{why}; {}{then}", w.text());
    } else {
        stop.outcome = Outcome::ProcessDied;
        stop.because = format!(
            "{why}; the motor was NOT brought to a standstill: {}{then}",
            w.text()
        );
    }
}

/// How the supervisor's word on an interruption ends when it stops the processes.
const STOPPED_ALL: &str = "; all stack processes were stopped";

/// Supervises a launched stack to its last sample and stops its children; returns how it
/// ended and the children's failures. Ended early on the wall clock, the axes are brought to
/// a standstill (or a dead process's survivors stop them) first, and the ending says how.
fn supervise<'a, 'r>(
    l: &'a mut Launched,
    s: &'a Scenario,
    mode: Mode,
    label: &str,
    observer: Observer<'r>,
    helpers: Option<&'a mut Helpers>,
) -> Result<(Ending, Vec<String>, Supervisor<'a, 'r>)> {
    let timeouts = (l.deployment.startup_timeout(), l.deployment.peer_timeout());
    let feeds = l
        .feeds
        .take()
        .context("a launched stack is supervised once")?;
    let mut sup = Supervisor::new(
        s,
        mode,
        label,
        feeds,
        observer,
        &mut l.children,
        Some(&l.files),
        timeouts,
    )
    .watching_axes()
    .stopping_with(l.stopper.take())
    .with_helpers(helpers);
    let mut ending = sup.run(Until::LastSample)?;
    if let Some(w) = sup.wind_down(&ending)? {
        if let Ending::Stopped(stop) = &mut ending {
            amend(stop, &w);
        }
    }
    let mut failures = Vec::new();
    if ending == Ending::Last {
        failures = sup.stop_children(l.emulated)?;
    }
    sup.drain_stats()?;
    // The answer to the last sample comes after it: the loops have exited by now.
    sup.drain_controls()?;
    sup.close_controls();
    Ok((ending, failures, sup))
}

/// Runs one method of one scenario on the stack's processes and returns its report:
/// complete, or with what ran before it stopped (a child died, the stack hung, Ctrl-C), its
/// outcome saying which. An error only when the stack could not be started at all.
///
/// With `recording`, every state sample the monitor sees and every statistics report go to
/// the file too (on channels of their own for this method). `helpers` (the RT-throttling
/// guard) are watched with the stack.
pub fn run_stack(
    s: &Scenario,
    method: Method,
    opts: &LaunchOptions,
    recording: Option<&mut Recording>,
    helpers: Option<&mut Helpers>,
) -> Result<RunReport> {
    let mode = opts.mode;
    let stack = stack(mode, Purpose::Control);
    let method_arg = |role: Role| match role {
        Role::CurrentLoop => vec!["--method".to_string(), method.as_str().to_string()],
        _ => Vec::new(),
    };
    // The recording's channels first: opening them waits for its writer to catch up with
    // the method before, which a stack already launched would wait out as a dead monitor.
    let recording_on = recording.is_some();
    let observer = Observer::new(s.for_axis(0).unwrap_or(s), mode).recording(recording, method);
    let mut l = launch(&stack, s, opts, recording_on, &method_arg)?;
    let (truth, emulated) = (l.truth.clone(), l.emulated);
    let (ending, failures, mut sup) =
        supervise(&mut l, s, mode, method.as_str(), observer, helpers)?;
    let wall = sup.observer.wall_s();
    let stop = match ending {
        Ending::Last => None,
        Ending::Stopped(stop) => Some(stop),
    };
    let mut report = sup.observer.report(method, mode.as_str(), wall, stop);
    report.axes = sup.axis_reports(method, mode.as_str());
    if !failures.is_empty() && report.complete {
        report.outcome = report.outcome.max(Outcome::ProcessDied);
        report.stopped_because = Some(failures.join("; "));
    }
    let timing = (mode != Mode::Lockstep).then(|| {
        let mut t = sup.finals.timing(s, sup.observer.lost(), mode);
        t.resources = sup.resources();
        t
    });
    let Supervisor { observer, .. } = sup;
    let mut observer = observer;
    if let Some(path) = truth {
        let rows = read_truth(&path);
        // The emulated drive's file is the run's; a drive's own is not ours to remove.
        if emulated {
            let _ = std::fs::remove_file(&path);
        }
        report.truth = truth_report(s, method, &rows);
        if !rows.is_empty() {
            observer.truth(&rows);
        }
    }
    report.timing = timing;
    drop(observer);
    drop(l);
    cleanup_dead_nodes();
    Ok(report)
}

/// How a served stack ended.
#[derive(Debug, Clone, PartialEq)]
pub struct ServeReport {
    pub outcome: Outcome,
    /// In words: how it ended, with the run's time.
    pub because: String,
    /// Served for, s of the stack's time; samples seen and the device's misses.
    pub served_s: f64,
    pub samples: u64,
    pub misses: u64,
    /// The device's faults latched at the end (zero: none).
    pub latched: u32,
}

/// `stepdrive serve`: brings the stack up (the axis disabled, waiting for commands) and
/// keeps it up, supervised like any run, until Ctrl-C or until it breaks (a process dies
/// or goes silent). Ctrl-C is how a served stack is meant to end: every axis is brought to
/// a standstill with its outputs off before the processes go, and the outcome is ok unless
/// the device has a fault latched at that moment or an axis could not be stopped. A
/// process that died leaves its survivors the time to stop the motor. `helpers` (the
/// gateway, the RT-throttling guard) are watched with the stack. With `live` (a live view),
/// what the stack does goes to it as to a recording, on the proposed method's channels.
pub fn serve_stack(
    s: &Scenario,
    opts: &LaunchOptions,
    live: Option<&mut Recording>,
    helpers: Option<&mut Helpers>,
) -> Result<ServeReport> {
    let mode = opts.mode;
    let stack = stack(mode, Purpose::Control);
    let mut l = launch(&stack, s, opts, live.is_some(), &|_| Vec::new())?;
    let timeouts = (l.deployment.startup_timeout(), l.deployment.peer_timeout());
    let feeds = l
        .feeds
        .take()
        .context("a launched stack is supervised once")?;
    let mut sup = Supervisor::new(
        s,
        mode,
        "serve",
        feeds,
        Observer::new(s.for_axis(0).unwrap_or(s), mode).recording(live, Method::Proposed),
        &mut l.children,
        Some(&l.files),
        timeouts,
    )
    .watching_axes()
    .stopping_with(l.stopper.take())
    .with_helpers(helpers);
    let ending = sup.run(Until::Interrupted)?;
    // Any axis's device with a fault latched at the end makes the served stack's verdict.
    let latched = sup.last_faults() & crate::report::outcome::LATCHED;
    let served_s = sup.observer.metrics().sim_time_s();
    let samples = sup.observer.metrics().samples();
    let misses = sup.finals.device_misses();
    let (outcome, because) = match ending.clone() {
        Ending::Stopped(stop) if stop.outcome == Outcome::Interrupted => match latched {
            0 => (Outcome::Ok, "stopped (SIGINT/SIGTERM)".to_string()),
            bits => (
                Outcome::Fault,
                format!(
                    "stopped (SIGINT/SIGTERM) with {} latched in the device",
                    crate::report::outcome::fault_names(bits).join(" and ")
                ),
            ),
        },
        Ending::Stopped(stop) => (stop.outcome, stop.because),
        Ending::Last => (Outcome::Ok, "the stack ended its run".to_string()),
    };
    let mut stop = Stop::new(outcome, because);
    if let Some(w) = sup.wind_down(&ending)? {
        amend(&mut stop, &w);
    }
    drop(sup);
    drop(l);
    cleanup_dead_nodes();
    let Stop { outcome, because } = stop;
    Ok(ServeReport {
        outcome,
        because,
        served_s,
        samples,
        misses,
        latched,
    })
}

/// A child that exited with its verdict on the run (a latched fault: 3) carries that exit
/// code; any other failure is the process's own (exit 5).
fn child_failed(child: &Supervised, status: ExitStatus) -> anyhow::Error {
    let code = match status.code() {
        Some(c) if VERDICT_EXIT_CODES.contains(&c) => c as u8,
        _ => Outcome::ProcessDied.exit_code(),
    };
    Exit {
        code,
        headline: child.describe_failure(status),
    }
    .into()
}

/// `stepdrive identify` through the stack's processes in `opts.mode`: the plant (or the
/// bridge, and an emulated drive when no drive is given) and the identification process in
/// the current loop's place, supervised like any stack. `s` must last the sequence. Returns
/// what the identification process found.
pub fn run_identify(
    s: &Scenario,
    bounds: &stepdrive_control::identify::Bounds,
    opts: &LaunchOptions,
) -> Result<crate::studies::identify::NodeResult> {
    let mode = opts.mode;
    let stack = stack(mode, Purpose::Identify);
    let result = std::env::temp_dir().join(format!(
        "stepdrive-identify-{}-{}.json",
        std::process::id(),
        opts.instance
    ));
    let extra = |role: Role| match role {
        Role::Identify => vec![
            "--max-current".to_string(),
            bounds.current_a.to_string(),
            "--max-voltage".to_string(),
            bounds.voltage_v.to_string(),
            "--max-speed".to_string(),
            bounds.speed_rad_s.to_string(),
            "--max-travel".to_string(),
            bounds.travel_rad.to_string(),
            "--result".to_string(),
            path_arg(&result),
        ],
        _ => Vec::new(),
    };
    let mut l = launch(&stack, s, opts, false, &extra)?;
    let (ending, _, mut sup) =
        supervise(&mut l, s, mode, "identify", Observer::new(s, mode), None)?;
    if let Ending::Stopped(stop) = ending {
        // A child that died says why, with its own verdict (a drive's fault: exit 3).
        for child in sup.children_mut() {
            if let Some(status) = child.poll_exit()?.filter(|s| !s.success()) {
                return Err(child_failed(child, status));
            }
        }
        return Err(Exit {
            code: stop.outcome.exit_code(),
            headline: stop.because,
        }
        .into());
    }
    for child in sup.children_mut() {
        if let Some(status) = child.poll_exit()?.filter(|s| !s.success()) {
            return Err(child_failed(child, status));
        }
    }
    drop(sup);
    drop(l);
    cleanup_dead_nodes();
    let text = std::fs::read_to_string(&result)
        .with_context(|| format!("the identification left no result in {}", result.display()))?;
    let _ = std::fs::remove_file(&result);
    serde_json::from_str(&text).context("the identification's result is not readable")
}

/// The emulated drive's true rotor state over the run (none, said once, when the drive
/// left no usable file: the run's own figures stand).
fn read_truth(path: &std::path::Path) -> Vec<TruthRow> {
    stepdrive_emulated_drive::truth::read(path).unwrap_or_else(|e| {
        tracing::warn!("no true rotor state from the emulated drive: {e}");
        Vec::new()
    })
}

/// The run's figures from the true rotor state.
fn truth_report(s: &Scenario, method: Method, rows: &[TruthRow]) -> Option<TruthReport> {
    if rows.is_empty() {
        return None;
    }
    let mut m = Metrics::new(s);
    for r in rows {
        m.push(&DriveState {
            seq: r.k,
            sample_time_s: r.t_s,
            theta_rad: r.theta_rad,
            omega_rad_s: r.omega_rad_s,
            i_a_a: r.i_a_a,
            i_b_a: r.i_b_a,
            ..Default::default()
        });
    }
    let t = m.finish(method, "truth", 0.0);
    Some(TruthReport {
        samples: t.samples,
        cruise_max_abs_error_rad: t.cruise_max_abs_error_rad,
        max_abs_error_rad: t.max_abs_error_rad,
        final_error_rad: t.final_error_rad,
    })
}
