//! Tools that attach to a stack already running (one started by hand, or by `run` under
//! another name): its stamp (mode, scenario) is read from its own services.
//!
//! - [`reset`]: asks the plant (or bridge) to clear its latched faults, and reports whether
//!   they cleared.
//! - [`watch`]: computes a run's figures from the state stream, as `run` does for the stack
//!   it launches.

use crate::record::recording::Recording;
use crate::report::metrics::RunReport;
use crate::report::outcome::{fault_names, Outcome, LATCHED};
use crate::supervise::observer::Observer;
use crate::supervise::supervisor::{Controls, Ending, Feeds, Supervisor, Until};
use anyhow::{bail, Result};
use std::time::{Duration, Instant};
use stepdrive_runtime::clock::monotonic_ns;
use stepdrive_runtime::ipc::{IpcBus, Stamp};
use stepdrive_runtime::port::{PortFactory, Publish, Subscribe};
use stepdrive_shared::messages::{
    DriveCommand, DrivePlan, DriveState, ResetRequest, TorqueSetpoint,
};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER, MONITOR_BUFFER};
use stepdrive_shared::stack::Role;
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::{Method, Scenario};

/// What a reset achieved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ResetResult {
    /// The plant's states carry no latched fault any more.
    Cleared,
    /// There was nothing to clear.
    NothingLatched,
    /// Still latched after the wait: the plant refused (its log says why).
    StillLatched(u32),
}

/// Sends a reset request to the plant (or bridge) of `instance` and watches its states for
/// `wait` to see the faults clear.
pub fn reset(instance: &str, wait: Duration) -> Result<ResetResult> {
    let mut bus = IpcBus::attach(instance, "reset", Duration::ZERO)?;
    let presence = bus.presence()?;
    let mut states = bus.subscriber_of::<DriveState>(LOOP_BUFFER)?;
    let mut requests = bus.publisher_of::<ResetRequest>()?;
    let deadline = Instant::now() + wait;
    while presence.subscribers(Topic::Reset) == 0 {
        if Instant::now() > deadline {
            bail!("no plant or bridge on instance `{instance}` takes reset requests");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    requests.connect()?;
    let sent = monotonic_ns();
    let latched_before = states.newest()?.map_or(0, |s| s.fault & LATCHED);
    requests.publish(&ResetRequest {
        seq: 1,
        publish_time_ns: sent,
        pid: std::process::id(),
        _reserved: 0,
    })?;
    let mut latched = latched_before;
    while Instant::now() < deadline {
        if let Some(s) = states.newest()? {
            // Only states published after the request say what it did.
            if s.publish_time_ns > sent {
                latched = s.fault & LATCHED;
                if latched == 0 {
                    break;
                }
            }
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    Ok(match (latched_before, latched) {
        (0, 0) => ResetResult::NothingLatched,
        (_, 0) => ResetResult::Cleared,
        (_, bits) => ResetResult::StillLatched(bits),
    })
}

/// A reset's result, for the user.
pub fn describe(r: &ResetResult) -> String {
    match r {
        ResetResult::Cleared => "the latched faults are cleared; the outputs follow the commands again".into(),
        ResetResult::NothingLatched => "no fault was latched".into(),
        ResetResult::StillLatched(bits) => format!(
            "still latched: {} (the plant refuses while the cause remains, e.g. no command from the current loop; see its log)",
            fault_names(*bits).join(" and ")
        ),
    }
}

/// Attaches a reader (a monitor, a scope) to the stack on `instance`, waiting up to 30 s
/// for it to appear (a reader may be started before the stack), and checks that the stack
/// runs `scenario`: the reader's figures would mean nothing for another.
pub fn attach_reader(instance: &str, role: &str, scenario: &Scenario) -> Result<IpcBus> {
    let bus = IpcBus::attach(instance, role, Duration::from_secs(30))?;
    let ours = Stamp::new(bus.mode(), scenario);
    if bus.stamp() != &ours {
        bail!(
            "instance `{instance}` runs scenario {}; the scenario given is {}",
            bus.stamp().scenario,
            ours.scenario
        );
    }
    Ok(bus)
}

/// Computes the figures of the run on `instance` from its state stream, until its last
/// sample, the stack going silent for `peer_timeout`, or Ctrl-C: the one supervisor, with
/// no children of its own. `scenario` must be the stack's (its fingerprint is checked);
/// `method` labels the report. With `recording`, every sample seen goes to the file, with
/// the setpoints, commands and (realtime) plans, and those missed are counted.
pub fn watch(
    instance: &str,
    scenario: &Scenario,
    method: Method,
    peer_timeout: Duration,
    recording: Option<&mut Recording>,
) -> Result<RunReport> {
    let mut bus = attach_reader(instance, Role::Monitor.id(), scenario)?;
    let mode = bus.mode();
    let controls = match recording {
        Some(_) => Some(Controls {
            setpoints: bus.subscriber::<TorqueSetpoint>(MONITOR_BUFFER)?,
            commands: bus.subscriber::<DriveCommand>(MONITOR_BUFFER)?,
            // The plan topic has room for the device and one reader: a stack recorded by
            // `run` already has it, and is recorded here without its plans.
            plans: match mode {
                Mode::Lockstep => None,
                _ => match bus.subscriber::<DrivePlan>(LOOP_BUFFER) {
                    Ok(p) => Some(p),
                    Err(e) => {
                        tracing::warn!("recording without the voltage plans: {e}");
                        None
                    }
                },
            },
        }),
        None => None,
    };
    let feeds = Feeds {
        states: bus.subscriber::<DriveState>(MONITOR_BUFFER)?,
        stats: bus.subscriber::<StatsReport>(4)?,
        controls,
    };
    let observer = Observer::new(scenario, mode).recording(recording, method);
    // A reader may be started before the stack: it waits for the first sample as long as
    // for a silent peer, and at least 30 s.
    let timeouts = (peer_timeout.max(Duration::from_secs(30)), peer_timeout);
    let mut sup = Supervisor::new(
        scenario,
        mode,
        method.as_str(),
        feeds,
        observer,
        &mut [],
        None,
        timeouts,
    );
    let ending = sup.run(Until::LastSample)?;
    if ending == Ending::Last {
        // The answer to the last sample comes after it.
        std::thread::sleep(Duration::from_millis(50));
    }
    sup.drain_stats()?;
    sup.drain_controls()?;
    let stop = match ending {
        Ending::Last => None,
        Ending::Stopped(mut stop) => {
            if stop.outcome == Outcome::ProcessDied && sup.observer.metrics().samples() > 0 {
                stop.because = format!("instance `{instance}`: {}", stop.because);
            }
            Some(stop)
        }
    };
    let wall = sup.observer.wall_s();
    Ok(sup.observer.report(method, mode.as_str(), wall, stop))
}
