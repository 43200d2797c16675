//! Deployment: where and how each process of a stack runs — its wait strategy, SCHED_FIFO
//! priority, CPU, memory locking, timer slack — and the stack's timeouts, watchdog and drive
//! link. One home for these settings and their defaults: `stepdrive run` writes them to a
//! TOML file that every child reads (`--deploy FILE`), and a process started by hand gets
//! the same defaults, so the two behave the same. `stepdrive deploy` prints them.
//!
//! The defaults are this project's measured choice for two cores (see docs/design.md's
//! realtime section): the plant and position loop (or the emulated drive) share CPU 0, the
//! current loop (and in hardware mode the bridge, one priority below it) has CPU 1.

use crate::pacer::WaitStrategy;
use crate::rt::RtOptions;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Duration;
use stepdrive_shared::messages::MAX_PLAN;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stack::Role;

/// Where and how one process runs. Absent fields take the process's default.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Placement {
    /// `sleep`, `spin`, `hybrid:<µs>` or `event` (see docs/design.md's wait strategies).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wait: Option<WaitStrategy>,
    /// SCHED_FIFO priority 1-99; 0: SCHED_OTHER.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub priority: Option<u8>,
    /// Pin to this CPU.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cpu: Option<usize>,
}

/// The link to a drive (hardware mode).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DriveLink {
    /// The drive: `host:port` on UDP, or a serial line (`/dev/ttyACM0`). Absent: `run`
    /// starts an emulated drive on loopback.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,
    /// Periods without a valid sample before the bridge publishes a fault state and stops
    /// forwarding commands until the drive speaks again.
    pub silence_periods: u32,
    /// Forward the current loop's voltage plan when it is this many samples newer than the
    /// last one sent. 1: every plan the loop publishes (it publishes one every 10th command
    /// and after every lost sample, ~8 MB/s of 1000-entry PLANs at 20 kHz), so the drive
    /// holds the very plan the loop predicts with; a larger value spares a slow link, and
    /// after a lost sample the drive may then hold an older plan than the loop assumes.
    pub plan_every: u32,
    /// Bandwidth of the bridge's encoder velocity observer, Hz.
    pub observer_hz: f64,
    /// Encoder reading at θ = 0 (an absolute encoder); absent: the first sample is θ = 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub encoder_offset_counts: Option<i64>,
    /// Counts increase for negative θ, whatever the drive's CONFIG says.
    pub reverse_encoder: bool,
    /// The emulated drive: PLAN entries it keeps (0: none).
    pub emulated_plan_capacity: u16,
}

impl Default for DriveLink {
    fn default() -> Self {
        Self {
            address: None,
            silence_periods: 200,
            plan_every: 1,
            observer_hz: 400.0,
            encoder_offset_counts: None,
            reverse_encoder: false,
            emulated_plan_capacity: 1000,
        }
    }
}

/// Everything about how a stack is deployed. See the module documentation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Deployment {
    /// Longest wait for the rest of the stack to come up, s.
    pub startup_timeout_s: f64,
    /// Longest silence of a peer, once heard, before a process stops, s.
    pub peer_timeout_s: f64,
    /// Realtime: periods in a row without a command after which the plant (or the drive)
    /// turns its outputs off and latches a fault (1000 = 50 ms at 20 kHz: this VM's
    /// hypervisor has held a vCPU for 20 ms, and a 10 ms watchdog lost the motor 11 minutes
    /// into a 30-minute run).
    pub watchdog_periods: u32,
    /// mlockall and prefault the stack in every realtime process.
    pub lock_memory: bool,
    /// Timer slack of every realtime process, ns (the kernel's default, 50 µs, is a whole
    /// 20 kHz period).
    pub timer_slack_ns: u64,
    /// Fail when the system refuses a real-time setting, instead of warning and going on.
    pub require_rt: bool,
    /// The nice value of every process of the stack that runs at ordinary scheduling (all of
    /// them in lockstep; in realtime those without a SCHED_FIFO priority), -20..=19, 0 to
    /// leave it. A lockstep stack hands off ~44 000 times a simulated second, and a hand-off
    /// whose peer has to get its CPU back from an ordinary task waits for a scheduler slice:
    /// beside two CPU hogs a run was 2-3× slower at nice 0 (docs/measurements.md). Negative
    /// values need root or CAP_SYS_NICE; without them a process keeps its inherited nice.
    pub nice: i32,
    pub plant: Placement,
    pub current_loop: Placement,
    pub position_loop: Placement,
    pub bridge: Placement,
    pub emulated_drive: Placement,
    pub monitor: Placement,
    pub drive: DriveLink,
}

/// The defaults' priorities: the plant's and current loop's. The position loop runs one
/// above the plant (below it, it would only get the gaps between the plant's spins); the
/// bridge one below the current loop, which preempts it to answer; the monitor at 1 (an
/// ordinary task waking at 1 kHz is run ahead of SCHED_FIFO tasks by the kernel's fair
/// server, and delays them). docs/design.md has the measurements.
pub const DEFAULT_PRIORITY: u8 = 80;

/// The default nice value of a stack's processes at ordinary scheduling ([`Deployment::nice`]).
pub const DEFAULT_NICE: i32 = -10;

/// The most axes whose plant spins before its deadlines by default ([`Deployment::for_axes`]).
pub const PLANT_SPINS_UP_TO_AXES: usize = 2;

/// The current loop's default hybrid margin: it sleeps to this long before the next sample
/// and polls the rest. Why not 40 µs (the default until 2026-11-27): a 20 kHz loop done
/// ~8 µs after its sample then asked for sleeps of ~2 µs, which return before the kernel
/// switches away, so it held CPU 1 without a break; an ordinary task runnable there (a
/// flooding client, `taskset -c 1 yes`) was starved until the kernel's fair server ran it
/// ahead of SCHED_FIFO for ~50 ms, and the plant's watchdog latched COMMAND_TIMEOUT (8 runs
/// of 9). At 35 µs the sleeps yield, ordinary tasks get their share between samples, and
/// the same runs ended ok (12 of 12). docs/measurements.md has the figures; the ignored test
/// `an_ordinary_task_busy_on_the_current_loops_cpu_does_not_trip_the_watchdog` repeats it.
pub const CURRENT_LOOP_MARGIN_NS: u64 = 35_000;

impl Default for Deployment {
    fn default() -> Self {
        let mut d = Self {
            startup_timeout_s: 30.0,
            peer_timeout_s: 5.0,
            watchdog_periods: 1000,
            lock_memory: true,
            timer_slack_ns: 1000,
            require_rt: false,
            nice: DEFAULT_NICE,
            plant: Placement::default(),
            current_loop: Placement::default(),
            position_loop: Placement::default(),
            bridge: Placement::default(),
            emulated_drive: Placement::default(),
            monitor: Placement::default(),
            drive: DriveLink::default(),
        };
        d.set_priorities(DEFAULT_PRIORITY, DEFAULT_PRIORITY);
        d.set_cpus(Some((0, 1)));
        d
    }
}

/// A setting that cannot work, named.
#[derive(Debug, thiserror::Error)]
pub enum DeployError {
    #[error("cannot read deployment file {path}")]
    Read {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("deployment file {path} is not valid: {message}")]
    Parse {
        path: std::path::PathBuf,
        message: String,
    },
    #[error("deployment setting `{field}` {message}")]
    Invalid {
        field: &'static str,
        message: String,
    },
}

fn invalid(field: &'static str, message: impl Into<String>) -> DeployError {
    DeployError::Invalid {
        field,
        message: message.into(),
    }
}

impl Deployment {
    /// Reads and validates a deployment file; absent fields keep their defaults.
    pub fn from_toml_file(path: &Path) -> Result<Self, DeployError> {
        let text = std::fs::read_to_string(path).map_err(|source| DeployError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let d: Deployment = toml::from_str(&text).map_err(|e| DeployError::Parse {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        d.validate()?;
        Ok(d)
    }

    pub fn to_toml_string(&self) -> String {
        // Every field is plain data (strings, numbers, tables): serialising cannot fail.
        toml::to_string(self).unwrap_or_default()
    }

    pub fn validate(&self) -> Result<(), DeployError> {
        let seconds = |field, v: f64| {
            if v.is_finite() && v > 0.0 && v < 1e6 {
                Ok(())
            } else {
                Err(invalid(
                    field,
                    format!("must be seconds in (0, 1e6) (got {v})"),
                ))
            }
        };
        seconds("startup_timeout_s", self.startup_timeout_s)?;
        seconds("peer_timeout_s", self.peer_timeout_s)?;
        if self.watchdog_periods == 0 {
            return Err(invalid("watchdog_periods", "must be at least 1"));
        }
        if !(-20..=19).contains(&self.nice) {
            return Err(invalid(
                "nice",
                format!("must be a nice value in -20..=19 (got {})", self.nice),
            ));
        }
        let link = &self.drive;
        if link.silence_periods == 0 {
            return Err(invalid("drive.silence_periods", "must be at least 1"));
        }
        if link.plan_every == 0 {
            return Err(invalid("drive.plan_every", "must be at least 1"));
        }
        if !(link.observer_hz.is_finite() && link.observer_hz > 0.0) {
            return Err(invalid(
                "drive.observer_hz",
                format!("must be a positive number of Hz (got {})", link.observer_hz),
            ));
        }
        if usize::from(link.emulated_plan_capacity) > MAX_PLAN {
            return Err(invalid(
                "drive.emulated_plan_capacity",
                format!(
                    "must be 0..={MAX_PLAN} (got {})",
                    link.emulated_plan_capacity
                ),
            ));
        }
        for (field, p) in [
            ("plant.priority", &self.plant),
            ("current_loop.priority", &self.current_loop),
            ("position_loop.priority", &self.position_loop),
            ("bridge.priority", &self.bridge),
            ("emulated_drive.priority", &self.emulated_drive),
            ("monitor.priority", &self.monitor),
        ] {
            if p.priority.is_some_and(|v| v > 99) {
                return Err(invalid(field, "must be 0-99 (0: SCHED_OTHER)"));
            }
        }
        Ok(())
    }

    /// [`Self::validate`], and what only `mode` rules out. Hardware mode: a current loop that
    /// polls (`spin`, `hybrid`) on the bridge's CPU at a higher priority holds the CPU the
    /// bridge needs to bring it its state; the bridge runs only when the loop gives up
    /// polling. Beside an ordinary task on CPU 1 the stack stalled at its first sample (the
    /// current loop at 94 % of CPU 1, the bridge at 0; three runs of three), and the file
    /// that did it was `stepdrive deploy`'s output, which spells out the realtime wait.
    pub fn validate_for(&self, mode: Mode) -> Result<(), DeployError> {
        self.validate()?;
        let (cl, bridge) = (&self.current_loop, &self.bridge);
        let same_cpu = cl.cpu.is_some() && cl.cpu == bridge.cpu;
        let above = cl.priority.unwrap_or(0) > bridge.priority.unwrap_or(0);
        let polls = matches!(
            self.wait(Role::CurrentLoop, mode),
            WaitStrategy::Spin | WaitStrategy::Hybrid { .. }
        );
        if mode == Mode::Hardware && same_cpu && above && polls {
            return Err(invalid(
                "current_loop.wait",
                format!(
                    "{} in hardware mode: the current loop would poll CPU {} at priority {} \
                     above the bridge it waits for (priority {}), which then runs only when \
                     the loop gives up polling; use `event` (the hardware default) or put \
                     them on different CPUs",
                    self.wait(Role::CurrentLoop, mode),
                    cl.cpu.unwrap_or_default(),
                    cl.priority.unwrap_or(0),
                    bridge.priority.unwrap_or(0),
                ),
            ));
        }
        Ok(())
    }

    /// SCHED_FIFO priorities by the project's policy (see [`DEFAULT_PRIORITY`]): `plant`
    /// for the plant, emulated drive and (one above) the position loop; `current` for the
    /// current loop and (one below) the bridge. 0 keeps that side SCHED_OTHER.
    pub fn set_priorities(&mut self, plant: u8, current: u8) {
        let fifo = |p: u8| (p > 0).then_some(p.min(99));
        self.plant.priority = fifo(plant);
        self.emulated_drive.priority = fifo(plant);
        self.position_loop.priority = fifo(plant).map(|p| p.saturating_add(1).min(99));
        self.current_loop.priority = fifo(current);
        self.bridge.priority = fifo(current).map(|p| p.saturating_sub(1).max(1));
        self.monitor.priority = fifo(plant).map(|_| 1);
    }

    /// CPUs by the project's policy: the plant, position loop and emulated drive on the
    /// first, the current loop and bridge on the second; `None` pins nothing.
    pub fn set_cpus(&mut self, cpus: Option<(usize, usize)>) {
        let (a, b) = cpus.unzip();
        for p in [
            &mut self.plant,
            &mut self.position_loop,
            &mut self.emulated_drive,
        ] {
            p.cpu = a;
        }
        for p in [&mut self.current_loop, &mut self.bridge] {
            p.cpu = b;
        }
    }

    /// Whether any process runs at a SCHED_FIFO priority.
    pub fn has_priorities(&self) -> bool {
        [
            &self.plant,
            &self.current_loop,
            &self.position_loop,
            &self.bridge,
            &self.emulated_drive,
        ]
        .iter()
        .any(|p| p.priority.is_some_and(|v| v > 0))
    }

    pub fn startup_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.startup_timeout_s)
    }

    pub fn peer_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.peer_timeout_s)
    }

    /// Where `role` runs. The identification runs in the current loop's place; a tool
    /// outside the stack has no placement.
    fn placement(&self, role: Role) -> &Placement {
        const UNPLACED: Placement = Placement {
            wait: None,
            priority: None,
            cpu: None,
        };
        match role {
            Role::Plant => &self.plant,
            Role::CurrentLoop | Role::Identify => &self.current_loop,
            Role::PositionLoop => &self.position_loop,
            Role::Bridge => &self.bridge,
            Role::EmulatedDrive => &self.emulated_drive,
            Role::Monitor => &self.monitor,
            Role::Tool(_) => &UNPLACED,
        }
    }

    /// `role`'s placement, to change it; none for a tool.
    pub fn placement_mut(&mut self, role: Role) -> Option<&mut Placement> {
        Some(match role {
            Role::Plant => &mut self.plant,
            Role::CurrentLoop | Role::Identify => &mut self.current_loop,
            Role::PositionLoop => &mut self.position_loop,
            Role::Bridge => &mut self.bridge,
            Role::EmulatedDrive => &mut self.emulated_drive,
            Role::Monitor => &mut self.monitor,
            Role::Tool(_) => return None,
        })
    }

    /// How `process` waits in `mode`: its placement's strategy, or its default. The
    /// defaults: the plant and emulated drive `hybrid:25` (a timer wake-up can take most of
    /// a 50 µs period, so they sleep to 25 µs before it and spin the rest; a plant of three
    /// or more axes sleeps, see [`Self::for_axes`]); the current loop
    /// `hybrid:35` against the next sample (see [`CURRENT_LOOP_MARGIN_NS`]),
    /// `event` in hardware mode (asleep until the bridge raises state-ready); the position
    /// loop `sleep`; the bridge `hybrid:30` with a real-time priority (asleep until 30 µs
    /// before the drive's frame is due, then polling its socket), `sleep` without (polling
    /// would only take the CPU from the processes it waits for).
    pub fn wait(&self, process: Role, mode: Mode) -> WaitStrategy {
        if let Some(w) = self.placement(process).wait {
            return w;
        }
        match process {
            Role::Plant | Role::EmulatedDrive => WaitStrategy::Hybrid { margin_ns: 25_000 },
            Role::CurrentLoop | Role::Identify if mode == Mode::Hardware => WaitStrategy::Event,
            Role::CurrentLoop | Role::Identify => WaitStrategy::Hybrid {
                margin_ns: CURRENT_LOOP_MARGIN_NS,
            },
            Role::PositionLoop | Role::Monitor | Role::Tool(_) => WaitStrategy::Sleep,
            Role::Bridge if self.bridge.priority.is_some() => {
                WaitStrategy::Hybrid { margin_ns: 30_000 }
            }
            Role::Bridge => WaitStrategy::Sleep,
        }
    }

    /// This deployment for a stack of `axes`: above [`PLANT_SPINS_UP_TO_AXES`] the plant
    /// sleeps to each deadline instead of spinning its last 25 µs, unless told otherwise.
    /// Its compute grows ~2.4 µs an axis, and with the spin CPU 0 had too little left for
    /// the position loop's ticks and the monitor: 8 axes ended UNOBSERVED or "stuck" with
    /// 2-8 % of commands missed, and at 3 and 4 axes, in interleaved 20 s pairs, asleep
    /// missed 2-8 times fewer (4 axes: 0.04-0.19 % against 0.15-0.50 %). At 1 and 2 axes the
    /// spin still wins (0.01-0.02 % against 0.01-0.06 %), and the samples leave on time
    /// instead of a timer wake-up late (p50 16 µs here). docs/axes.md has the figures.
    pub fn for_axes(mut self, axes: usize) -> Self {
        if axes > PLANT_SPINS_UP_TO_AXES && self.plant.wait.is_none() {
            self.plant.wait = Some(WaitStrategy::Sleep);
        }
        self
    }

    /// This deployment with every process's wait strategy written out as `mode` resolves
    /// it: what a file written for a run, or printed for a user, should say.
    pub fn resolved(&self, mode: Mode) -> Deployment {
        let mut d = self.clone();
        for process in [
            Role::Plant,
            Role::CurrentLoop,
            Role::PositionLoop,
            Role::Bridge,
            Role::EmulatedDrive,
        ] {
            let wait = self.wait(process, mode);
            if let Some(p) = d.placement_mut(process) {
                p.wait = Some(wait);
            }
        }
        d
    }

    /// The CPUs the stack's helpers run on (the monitor with its live view, the gateway, an
    /// attached reader): of those this process may use, the ones no loop is pinned to, or
    /// where the loops take them all (two cores), all but the current loop's and the
    /// bridge's. Empty when no loop is pinned. Why: beside everything attached (the gateway,
    /// a remote watcher, the live view and its client), helpers left to the scheduler ran
    /// their socket calls on the current loop's CPU in its sleeps (this kernel does not
    /// preempt a system call: preempt=none), and the loop's CPU was taken from it for
    /// ≥ 20 µs 687-1090 times in 10 s against 260-505 alone; kept off it, 165-459 against
    /// 155-505 (docs/remote.md).
    pub fn helper_cpus(&self) -> Vec<usize> {
        self.helper_cpus_among(&crate::rt::allowed_cpus())
    }

    fn helper_cpus_among(&self, allowed: &[usize]) -> Vec<usize> {
        let loops = [
            &self.plant,
            &self.current_loop,
            &self.position_loop,
            &self.bridge,
            &self.emulated_drive,
        ];
        if loops.iter().all(|p| p.cpu.is_none()) {
            return Vec::new();
        }
        let off = |taken: &[&Placement]| -> Vec<usize> {
            allowed
                .iter()
                .copied()
                .filter(|&c| !taken.iter().any(|p| p.cpu == Some(c)))
                .collect()
        };
        let free = off(&loops);
        if free.is_empty() {
            off(&[&self.current_loop, &self.bridge])
        } else {
            free
        }
    }

    /// The real-time settings `process` applies to itself in `mode` (in lockstep only the
    /// stack's nice value, which a realtime process without a priority takes too).
    pub fn rt(&self, process: Role, mode: Mode) -> RtOptions {
        if mode == Mode::Lockstep {
            return RtOptions {
                nice: self.nice_value(),
                ..RtOptions::default()
            };
        }
        let p = self.placement(process);
        let priority = p.priority.filter(|&v| v > 0);
        let helper_cpus = if process == Role::Monitor && p.cpu.is_none() {
            self.helper_cpus()
        } else {
            Vec::new()
        };
        RtOptions {
            priority,
            cpu: p.cpu,
            helper_cpus,
            // The monitor only wants its priority: it allocates as it records.
            lock_memory: self.lock_memory && process != Role::Monitor,
            timer_slack_ns: (process != Role::Monitor).then_some(self.timer_slack_ns),
            nice: priority.map_or_else(|| self.nice_value(), |_| None),
            require: self.require_rt,
        }
    }

    fn nice_value(&self) -> Option<i32> {
        (self.nice != 0).then_some(self.nice)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_follow_the_placement_policy_and_round_trip() {
        let d = Deployment::default();
        assert_eq!(d.plant.priority, Some(80));
        assert_eq!(d.position_loop.priority, Some(81));
        assert_eq!(d.bridge.priority, Some(79));
        assert_eq!(
            (d.plant.cpu, d.current_loop.cpu, d.bridge.cpu),
            (Some(0), Some(1), Some(1))
        );
        assert_eq!(
            d.wait(Role::CurrentLoop, Mode::Realtime),
            WaitStrategy::Hybrid { margin_ns: 35_000 }
        );
        assert_eq!(
            d.wait(Role::CurrentLoop, Mode::Hardware),
            WaitStrategy::Event
        );
        assert_eq!(
            d.wait(Role::Bridge, Mode::Hardware),
            WaitStrategy::Hybrid { margin_ns: 30_000 }
        );
        // Lockstep: no priority, CPU or locking; the whole stack at one nice value, which
        // in realtime only a process at ordinary scheduling takes.
        for p in [
            Role::Plant,
            Role::CurrentLoop,
            Role::PositionLoop,
            Role::Monitor,
        ] {
            assert_eq!(
                d.rt(p, Mode::Lockstep),
                RtOptions {
                    nice: Some(DEFAULT_NICE),
                    ..RtOptions::default()
                }
            );
            assert_eq!(d.rt(p, Mode::Realtime).nice, None, "{p:?} has a priority");
        }
        let mut ordinary = Deployment::default();
        ordinary.set_priorities(0, 0);
        let rt = ordinary.rt(Role::CurrentLoop, Mode::Realtime);
        assert_eq!((rt.priority, rt.nice), (None, Some(DEFAULT_NICE)));
        let polite = Deployment {
            nice: 0,
            ..Deployment::default()
        };
        assert_eq!(polite.rt(Role::Plant, Mode::Lockstep), RtOptions::default());
        let back: Deployment = toml::from_str(&d.to_toml_string()).expect("parses");
        assert_eq!(back, d);
        // Written out for a mode, every wait strategy is spelled out and reads back the same.
        let hardware = d.resolved(Mode::Hardware);
        assert_eq!(hardware.current_loop.wait, Some(WaitStrategy::Event));
        assert_eq!(
            hardware.plant.wait,
            Some(WaitStrategy::Hybrid { margin_ns: 25_000 })
        );
        let back: Deployment = toml::from_str(&hardware.to_toml_string()).expect("parses");
        assert_eq!(
            back.wait(Role::CurrentLoop, Mode::Hardware),
            WaitStrategy::Event
        );
        // A file may give only what differs.
        let partial: Deployment =
            toml::from_str("[current_loop]\nwait = \"spin\"\n").expect("parses");
        assert_eq!(
            partial.wait(Role::CurrentLoop, Mode::Realtime),
            WaitStrategy::Spin
        );
        assert_eq!(partial.plant, d.plant);
    }

    /// The defaults pass in every mode; a hardware-mode current loop that would poll above
    /// the bridge on its CPU is refused, naming the field; on its own CPU, or below the
    /// bridge, or waiting on its event, it is not.
    #[test]
    fn a_current_loop_polling_above_its_bridge_is_refused_in_hardware_mode() {
        let d = Deployment::default();
        for mode in [Mode::Lockstep, Mode::Realtime, Mode::Hardware] {
            assert!(d.validate_for(mode).is_ok(), "{mode:?}");
        }
        // What `stepdrive deploy` prints: every field, the realtime wait spelled out.
        let printed = d.resolved(Mode::Realtime).to_toml_string();
        let polling: Deployment = toml::from_str(&printed).expect("parses");
        assert!(polling.validate_for(Mode::Realtime).is_ok());
        match polling.validate_for(Mode::Hardware) {
            Err(DeployError::Invalid { field, message }) => {
                assert_eq!(field, "current_loop.wait");
                assert!(message.contains("hybrid:35"), "{message}");
            }
            other => panic!("taken: {other:?}"),
        }
        let mut elsewhere = polling.clone();
        elsewhere.current_loop.cpu = Some(0);
        assert!(elsewhere.validate_for(Mode::Hardware).is_ok());
        let mut below = polling.clone();
        below.current_loop.priority = Some(78);
        assert!(below.validate_for(Mode::Hardware).is_ok());
    }

    #[test]
    fn helpers_keep_off_the_loops_cpus_and_always_off_the_current_loops() {
        let d = Deployment::default();
        // Two cores: the loops take both; helpers share the plant's, never the current loop's.
        assert_eq!(d.helper_cpus_among(&[0, 1]), vec![0]);
        // More cores: the ones no loop uses.
        assert_eq!(d.helper_cpus_among(&[0, 1, 2, 3]), vec![2, 3]);
        // A process confined (taskset) to the current loop's CPU has nowhere to go.
        assert!(d.helper_cpus_among(&[1]).is_empty());
        let mut moved = d.clone();
        moved.set_cpus(Some((2, 3)));
        assert_eq!(moved.helper_cpus_among(&[0, 1, 2, 3]), vec![0, 1]);
        assert_eq!(moved.helper_cpus_among(&[2, 3]), vec![2]);
        // Nothing pinned: nothing to keep off.
        let mut free = d.clone();
        free.set_cpus(None);
        assert!(free.helper_cpus_among(&[0, 1]).is_empty());
        assert!(free
            .rt(Role::Monitor, Mode::Realtime)
            .helper_cpus
            .is_empty());
        // Only the monitor is a helper, and only outside lockstep.
        assert!(d.rt(Role::Plant, Mode::Realtime).helper_cpus.is_empty());
        assert!(d.rt(Role::Monitor, Mode::Lockstep).helper_cpus.is_empty());
        let mut placed = d.clone();
        placed.monitor.cpu = Some(1);
        let rt = placed.rt(Role::Monitor, Mode::Realtime);
        assert_eq!((rt.cpu, rt.helper_cpus.is_empty()), (Some(1), true));
    }

    #[test]
    fn priority_zero_means_ordinary_scheduling_everywhere_it_applies() {
        let mut d = Deployment::default();
        d.set_priorities(0, 0);
        d.set_cpus(None);
        for p in [Role::Plant, Role::CurrentLoop, Role::Bridge, Role::Monitor] {
            let rt = d.rt(p, Mode::Realtime);
            assert_eq!((rt.priority, rt.cpu), (None, None), "{p:?}");
        }
        // Without a priority the bridge blocks on its socket instead of polling it.
        assert_eq!(d.wait(Role::Bridge, Mode::Hardware), WaitStrategy::Sleep);
    }

    #[test]
    fn bad_settings_are_named() {
        let bad = |text: &str| {
            toml::from_str::<Deployment>(text)
                .map_err(|e| e.to_string())
                .and_then(|d| d.validate().map_err(|e| e.to_string()))
                .expect_err("must be rejected")
        };
        assert!(bad("watchdog_periods = 0").contains("watchdog_periods"));
        assert!(bad("nice = -21").contains("nice"));
        assert!(bad("nice = 20").contains("-20..=19"));
        assert!(bad("peer_timeout_s = -1.0").contains("peer_timeout_s"));
        assert!(bad("[drive]\nobserver_hz = nan").contains("drive.observer_hz"));
        assert!(bad("[plant]\nwait = \"nap\"").contains("nap"));
        assert!(bad("[plant]\nprioritty = 3").contains("prioritty"));
    }

    #[test]
    fn a_stack_of_more_than_two_axes_has_a_plant_that_sleeps_unless_told_otherwise() {
        let spin = WaitStrategy::Hybrid { margin_ns: 25_000 };
        let d = Deployment::default();
        assert_eq!(
            d.clone().for_axes(2).wait(Role::Plant, Mode::Realtime),
            spin
        );
        let three = d.clone().for_axes(3);
        assert_eq!(three.wait(Role::Plant, Mode::Realtime), WaitStrategy::Sleep);
        assert_eq!(
            three.resolved(Mode::Realtime).plant.wait,
            Some(WaitStrategy::Sleep)
        );
        // Only the plant: the emulated drive stands for hardware of its own.
        assert_eq!(three.wait(Role::EmulatedDrive, Mode::Hardware), spin);
        let mut told = d;
        told.plant.wait = Some(WaitStrategy::Spin);
        assert_eq!(
            told.for_axes(8).wait(Role::Plant, Mode::Realtime),
            WaitStrategy::Spin
        );
    }
}
