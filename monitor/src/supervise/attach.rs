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
use stepdrive_shared::messages::{DriveState, ResetRequest};
use stepdrive_shared::services::{Topic, LOOP_BUFFER, MONITOR_BUFFER};
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
    // What was latched before the request, from a state that has come: a subscriber gets
    // the newest state only once the device publishes again, and reading none as "nothing
    // latched" reported a reset that cleared a fault as "no fault was latched".
    let latched_before = loop {
        if let Some(s) = states.newest()? {
            break s.fault & LATCHED;
        }
        if Instant::now() > deadline {
            bail!(
                "no state from the plant or bridge of instance `{instance}` within {:.1} s: \
                 cannot tell what a reset would clear",
                wait.as_secs_f64()
            );
        }
        std::thread::sleep(Duration::from_millis(1));
    };
    let sent = monotonic_ns();
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

/// Attaches a reader (a monitor, a recorder, a scope) to the stack on `instance`, waiting
/// up to 30 s for it to appear (a reader may be started before the stack). The scenario is
/// the stack's to say: without `given` it is the one the stack announces; with it, it must
/// be the stack's (the reader's figures would mean nothing for another), and the fields
/// that differ are named.
/// A reader attached to a stack: its bus, the stack's scenario, and the state subscriber
/// it opened first.
pub struct Attached {
    pub bus: IpcBus,
    pub scenario: Scenario,
    pub states: Box<dyn Subscribe<DriveState>>,
}

/// `axis`: the axis of a multi-axis stack it reads (0 for a one-axis stack): its states, and
/// its own scenario in [`Attached::scenario`]; an index the stack lacks is refused, naming
/// its axis count. The bus is left on that axis's services.
pub fn attach_reader(
    instance: &str,
    role: &str,
    given: Option<&Scenario>,
    axis: u32,
) -> Result<Attached> {
    let wait = Duration::from_secs(30);
    let deadline = Instant::now() + wait;
    tracing::info!(
        "attaching to the stack on instance `{instance}` (waiting up to 30 s for it; Ctrl-C stops)"
    );
    let mut bus = IpcBus::attach(instance, role, wait)?;
    // Subscribed at once, before waiting for the device: a realtime device publishes from
    // its first period, and every sample before this subscription is one the reader missed.
    bus.set_axis(axis);
    let states = bus.subscriber::<DriveState>(MONITOR_BUFFER)?;
    bus.set_axis(0);
    // The device announces before it publishes its first state (a launcher's monitor may
    // have created the stack's services before the device came up).
    let presence = bus.presence()?;
    while presence.publishers(Topic::State) == 0 && Instant::now() < deadline {
        if stepdrive_runtime::poll::termination_requested() {
            bail!("interrupted while waiting for the stack on instance `{instance}`");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let announced = bus.announced_scenario()?;
    let attached = |mut bus: IpcBus, scenario: Scenario| {
        let count = scenario.axis_count();
        let Some(own) = scenario.for_axis(axis as usize) else {
            bail!(
                "the stack on instance `{instance}` has {count} axis(es), 0..={}: there is no axis {axis}",
                count - 1
            );
        };
        bus.set_axis(axis);
        Ok(Attached {
            bus,
            scenario: own.clone(),
            states,
        })
    };
    match (given, announced) {
        (None, Some(theirs)) => attached(bus, theirs),
        (None, None) => bail!(
            "the stack on instance `{instance}` ({}) does not announce its scenario (a stack \
             of an older stepdrive): give it with --scenario",
            bus.stamp().scenario
        ),
        (Some(ours), theirs) => {
            if bus.stamp() == &Stamp::new(bus.mode(), ours) {
                return attached(bus, ours.clone());
            }
            let differ = match &theirs {
                Some(t) => differing_fields(t, ours)
                    .unwrap_or_else(|e| vec![format!("(cannot compare: {e})")])
                    .join("; "),
                None => "the stack does not say which fields".to_string(),
            };
            bail!(
                "instance `{instance}` runs scenario {}; the scenario given is {}: {differ}. \
                 Leave out --scenario to take the stack's",
                bus.stamp().scenario,
                Stamp::new(bus.mode(), ours).scenario
            )
        }
    }
}

/// The dotted names of the fields in which two scenarios differ, with both values
/// (`run.duration_s: the stack's 60, the one given none`).
pub fn differing_fields(stack: &Scenario, given: &Scenario) -> Result<Vec<String>> {
    fn walk(path: &str, a: Option<&toml::Value>, b: Option<&toml::Value>, out: &mut Vec<String>) {
        match (a, b) {
            (Some(toml::Value::Table(ta)), Some(toml::Value::Table(tb))) => {
                let mut keys: Vec<&String> = ta.keys().chain(tb.keys()).collect();
                keys.sort();
                keys.dedup();
                for k in keys {
                    let p = if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    };
                    walk(&p, ta.get(k), tb.get(k), out);
                }
            }
            (a, b) if a != b => {
                let show =
                    |v: Option<&toml::Value>| v.map_or("none".to_string(), |v| v.to_string());
                out.push(format!(
                    "{path}: the stack's {}, the one given {}",
                    show(a),
                    show(b)
                ));
            }
            _ => {}
        }
    }
    let a: toml::Value = toml::from_str(&stack.to_toml_string()?)?;
    let b: toml::Value = toml::from_str(&given.to_toml_string()?)?;
    let mut out = Vec::new();
    walk("", Some(&a), Some(&b), &mut out);
    Ok(out)
}

/// Computes the figures of the run on `instance` (attached as `bus`, running `scenario`:
/// [`attach_reader`]) from its state stream, until its last sample, the stack going silent
/// for `peer_timeout`, or Ctrl-C: the one supervisor, with no children of its own. `method`
/// labels the report. With `recording`, every sample seen goes to the file, with
/// the setpoints, commands and (realtime) plans, and those missed are counted.
pub fn watch(
    attached: Attached,
    instance: &str,
    method: Method,
    peer_timeout: Duration,
    recording: Option<&mut Recording>,
) -> Result<RunReport> {
    let Attached {
        mut bus,
        scenario,
        states,
    } = attached;
    let scenario = &scenario;
    let mode = bus.mode();
    let controls = Controls::open(
        &mut bus,
        mode,
        recording.is_some(),
        !scenario.runs_profile(),
    )?;
    // The loops' statistics are per process, on axis 0's services (the controls above are
    // the attached axis's).
    bus.set_axis(0);
    let feeds = Feeds {
        states,
        stats: bus.subscriber::<StatsReport>(4)?,
        controls,
        axes: Vec::new(),
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
