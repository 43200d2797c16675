//! Tools that attach to a stack already running (one started by hand, or by `run` under
//! another name): its stamp (mode, scenario) is read from its own services.
//!
//! - [`reset`]: asks the plant (or bridge) to clear its latched faults, and reports whether
//!   they cleared.
//! - [`watch`]: computes a run's figures from the state stream, as `run` does for the stack
//!   it launches.

use crate::record::recording::Recording;
use crate::report::metrics::{Metrics, RunReport};
use crate::report::outcome::{fault_names, Outcome, LATCHED};
use anyhow::{bail, Result};
use std::time::{Duration, Instant};
use stepdrive_runtime::clock::monotonic_ns;
use stepdrive_runtime::ipc::{IpcBus, Stamp};
use stepdrive_runtime::poll::termination_requested;
use stepdrive_runtime::port::{PortFactory, Publish, Subscribe};
use stepdrive_shared::messages::{
    state_flags, DriveCommand, DrivePlan, DriveState, ResetRequest, TorqueSetpoint,
};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER, MONITOR_BUFFER};
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
/// sample, the stack going silent for `peer_timeout`, or Ctrl-C. `scenario` must be the
/// stack's (its fingerprint is checked); `method` labels the report. With `recording`,
/// every sample seen goes to the file, and those missed are counted.
/// What a recorder takes besides the states: setpoints, commands and (realtime) plans.
struct Controls {
    setpoints: Box<dyn Subscribe<TorqueSetpoint>>,
    commands: Box<dyn Subscribe<DriveCommand>>,
    plans: Option<Box<dyn Subscribe<DrivePlan>>>,
}

impl Controls {
    fn open(bus: &mut IpcBus, mode: Mode) -> Result<Self> {
        // The plan topic has room for the plant and one reader: a stack recorded by `run`
        // already has it, and is recorded here without its plans.
        let plans = match mode {
            Mode::Lockstep => None,
            _ => match bus.subscriber::<DrivePlan>(LOOP_BUFFER) {
                Ok(p) => Some(p),
                Err(e) => {
                    tracing::warn!("recording without the voltage plans: {e}");
                    None
                }
            },
        };
        Ok(Self {
            setpoints: bus.subscriber::<TorqueSetpoint>(MONITOR_BUFFER)?,
            commands: bus.subscriber::<DriveCommand>(MONITOR_BUFFER)?,
            plans,
        })
    }

    fn record(&mut self, r: &mut Recording) -> Result<()> {
        while let Some(sp) = self.setpoints.receive()? {
            r.setpoint(&sp)?;
        }
        while let Some(c) = self.commands.receive()? {
            r.command(&c)?;
        }
        if let Some(plans) = self.plans.as_mut() {
            while let Some(p) = plans.receive()? {
                r.plan(&p)?;
            }
        }
        Ok(())
    }
}

pub fn watch(
    instance: &str,
    scenario: &Scenario,
    method: Method,
    peer_timeout: Duration,
    mut recording: Option<&mut Recording>,
) -> Result<RunReport> {
    let mut bus = attach_reader(instance, "monitor", scenario)?;
    let mode = bus.mode();
    let mut states = bus.subscriber::<DriveState>(MONITOR_BUFFER)?;
    let mut metrics = Metrics::new(scenario);
    let mut controls = None;
    if let Some(r) = recording.as_deref_mut() {
        r.begin(method)?;
        controls = Some(Controls::open(&mut bus, mode)?);
    }
    let mut last_seq: Option<u64> = None;
    let mut last_heard = Instant::now();
    let (mut first_ns, mut last_ns) = (None, 0);
    let started = Instant::now();
    let outcome = loop {
        let mut last = false;
        while let Some(s) = states.receive()? {
            first_ns.get_or_insert(s.publish_time_ns);
            last_ns = s.publish_time_ns;
            metrics.push(&s);
            if let Some(r) = recording.as_deref_mut() {
                // Attached late or fallen behind: the samples never seen are counted.
                if let Some(gap) = last_seq.map(|q| s.seq.saturating_sub(q + 1)) {
                    r.lost(gap);
                }
                r.state(&s)?;
            }
            last_seq = Some(s.seq);
            last_heard = Instant::now();
            last |= s.flags & state_flags::LAST != 0;
        }
        if let (Some(c), Some(r)) = (controls.as_mut(), recording.as_deref_mut()) {
            c.record(r)?;
        }
        if last {
            // The answer to the last sample comes after it.
            std::thread::sleep(Duration::from_millis(50));
            if let (Some(c), Some(r)) = (controls.as_mut(), recording.as_deref_mut()) {
                c.record(r)?;
            }
            break None;
        }
        if termination_requested() {
            break Some((
                Outcome::Interrupted,
                "interrupted (SIGINT/SIGTERM)".to_string(),
            ));
        }
        let limit = if metrics.samples() == 0 {
            peer_timeout.max(Duration::from_secs(30))
        } else {
            peer_timeout
        };
        if last_heard.elapsed() > limit {
            break Some((
                Outcome::ProcessDied,
                format!(
                    "the plant of instance `{instance}` has been silent for {:.1} s",
                    last_heard.elapsed().as_secs_f64()
                ),
            ));
        }
        std::thread::sleep(Duration::from_micros(500));
    };
    let wall = first_ns.map_or(started.elapsed().as_secs_f64(), |f| {
        last_ns.saturating_sub(f) as f64 * 1e-9
    });
    Ok(match outcome {
        None => metrics.finish(method, mode.as_str(), wall),
        Some((outcome, because)) => {
            metrics.finish_early(method, mode.as_str(), wall, outcome, because)
        }
    })
}
