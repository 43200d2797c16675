//! Command-line options shared by several sub-commands, and how they turn into a scenario
//! and a deployment. Every deployment default lives in `stepdrive_runtime::deploy`; options
//! here only override it.

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use std::path::PathBuf;
use std::time::Duration;
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::node::Role;
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::DEFAULT_INSTANCE;
use stepdrive_shared::Scenario;

/// A number within `lo ..= hi` (`unit` names what it counts in the error), for
/// clap's `value_parser`. `lo` exclusive when `open_below` (a rate above 0).
pub fn number_within(
    s: &str,
    lo: f64,
    hi: f64,
    open_below: bool,
    unit: &str,
) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v <= hi && (v > lo || (!open_below && v == lo)) => Ok(v),
        _ => Err(format!(
            "must be {}{lo} … {hi} {unit} (got {s})",
            if open_below { "above " } else { "" }
        )),
    }
}

/// A run length or timeout: positive, finite, below 1e6 s.
pub fn seconds(v: f64) -> Result<Duration, String> {
    if v.is_finite() && v > 0.0 && v < 1e6 {
        Ok(Duration::from_secs_f64(v))
    } else {
        Err(format!(
            "must be a positive number of seconds below 1e6 (got {v})"
        ))
    }
}

pub fn parse_seconds(s: &str) -> Result<Duration, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("`{s}` is not a number of seconds"))?;
    seconds(v)
}

/// `N` or `none`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cpu(pub Option<usize>);

impl std::str::FromStr for Cpu {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "none" {
            return Ok(Cpu(None));
        }
        s.parse()
            .map(|c| Cpu(Some(c)))
            .map_err(|_| format!("`{s}` is not a CPU number (or `none`)"))
    }
}

/// `PLANT,CURRENT` or `none`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cpus(pub Option<(usize, usize)>);

impl std::str::FromStr for Cpus {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "none" {
            return Ok(Cpus(None));
        }
        let bad = || format!("`{s}` is not PLANT,CURRENT (two CPU numbers, e.g. 0,1) or none");
        let (a, b) = s.split_once(',').ok_or_else(bad)?;
        let a = a.trim().parse().map_err(|_| bad())?;
        let b = b.trim().parse().map_err(|_| bad())?;
        Ok(Cpus(Some((a, b))))
    }
}

/// `--cpus` of a helper (the gateway): a list of CPUs (`0`, `0,2-3`), or `any` (none
/// pinned). Each must exist on this machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CpuList(pub Vec<usize>);

impl std::str::FromStr for CpuList {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "any" {
            return Ok(CpuList(Vec::new()));
        }
        let bad = || format!("`{s}` is not a CPU list (e.g. 0 or 0,2-3) or any");
        let mut cpus = Vec::new();
        for part in s.split(',') {
            let (a, b) = part.split_once('-').unwrap_or((part, part));
            let a: usize = a.trim().parse().map_err(|_| bad())?;
            let b: usize = b.trim().parse().map_err(|_| bad())?;
            if a > b {
                return Err(bad());
            }
            stepdrive_runtime::rt::cpu_exists(b)?;
            cpus.extend(a..=b);
        }
        cpus.sort_unstable();
        cpus.dedup();
        Ok(CpuList(cpus))
    }
}

#[derive(Args, Debug, Clone)]
pub struct ScenarioOpt {
    /// Scenario TOML file (motor, load, drive, gains, rates, trajectory, metrics); absent
    /// fields take the paper's Section V defaults. `stepdrive scenario` prints them.
    #[arg(long, value_name = "FILE")]
    pub scenario: Option<PathBuf>,
}

impl ScenarioOpt {
    /// The scenario file given, if one was.
    pub fn given(&self) -> Result<Option<Scenario>> {
        match &self.scenario {
            Some(path) => Ok(Some(Scenario::from_toml_file(path)?)),
            None => Ok(None),
        }
    }

    pub fn load(&self) -> Result<Scenario> {
        match &self.scenario {
            Some(path) => Ok(Scenario::from_toml_file(path)?),
            None => Ok(Scenario::default()),
        }
    }

    /// [`Self::load`] for a command that runs one axis (`simulate`, `robustness`,
    /// `identify`): a scenario with `[[axis]]` tables is refused, naming `run`.
    pub fn load_one_axis(&self, command: &str) -> Result<Scenario> {
        let s = self.load()?;
        one_axis(&s, command)?;
        Ok(s)
    }
}

/// Refuses a multi-axis scenario for `what`, which runs one axis.
pub fn one_axis(s: &Scenario, what: &str) -> Result<()> {
    if s.axis_count() > 1 {
        anyhow::bail!(
            "scenario {} has {} axes ([[axis]] tables); {what} runs one axis: run them with \
             `stepdrive run` (lockstep or realtime), or give it one axis's scenario",
            s.name,
            s.axis_count()
        );
    }
    Ok(())
}

#[derive(Args, Debug, Clone)]
pub struct DeployOpt {
    /// Deployment TOML file: wait strategies, priorities, CPUs, timeouts, watchdog, drive
    /// link (`stepdrive deploy` prints the defaults; `run` writes one for its children).
    /// Options given on the command line override it.
    #[arg(long = "deploy", value_name = "FILE")]
    pub file: Option<PathBuf>,
}

impl DeployOpt {
    pub fn load(&self) -> Result<Deployment> {
        match &self.file {
            Some(path) => Ok(Deployment::from_toml_file(path)?),
            None => Ok(Deployment::default()),
        }
    }
}

#[derive(Args, Debug, Clone)]
pub struct Timeouts {
    /// Longest wait for the other processes to come up, seconds (default 30).
    #[arg(long, value_name = "S", value_parser = parse_seconds)]
    pub startup_timeout_s: Option<Duration>,
    /// Longest silence of a peer before a process stops, seconds (default 5).
    #[arg(long, value_name = "S", value_parser = parse_seconds)]
    pub peer_timeout_s: Option<Duration>,
}

impl Timeouts {
    pub fn apply(&self, d: &mut Deployment) {
        if let Some(t) = self.startup_timeout_s {
            d.startup_timeout_s = t.as_secs_f64();
        }
        if let Some(t) = self.peer_timeout_s {
            d.peer_timeout_s = t.as_secs_f64();
        }
    }
}

/// Real-time settings of one process, as cyclictest's -p, -a, -m; override its deployment.
#[derive(Args, Debug, Clone)]
pub struct PlacementArgs {
    /// Realtime: how this process waits: sleep (clock_nanosleep), spin, hybrid:<µs> (sleep to
    /// that margin before the deadline, then spin), or event (current loop, hardware mode:
    /// sleep until the bridge raises state-ready). Defaults (`stepdrive deploy`): plant and
    /// emulated drive hybrid:25, current loop hybrid:35 (hardware: event), position loop
    /// sleep, bridge hybrid:30 with a priority, else sleep.
    #[arg(long, value_name = "STRATEGY")]
    pub wait: Option<WaitStrategy>,
    /// Realtime: SCHED_FIFO priority 1-99, 0 for SCHED_OTHER (default: the deployment's).
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=99))]
    pub priority: Option<u8>,
    /// Realtime: pin to this CPU, or `none`.
    #[arg(long, value_name = "N|none")]
    pub cpu: Option<Cpu>,
    #[command(flatten)]
    pub rt: RtArgs,
}

/// Real-time settings every process of a stack shares.
#[derive(Args, Debug, Clone)]
pub struct RtArgs {
    /// Realtime: do not mlockall.
    #[arg(long)]
    pub no_mlock: bool,
    /// Realtime: timer slack in ns (default 1000; the kernel's, 50000, is a whole 20 kHz
    /// period).
    #[arg(long, value_name = "NS")]
    pub timer_slack_ns: Option<u64>,
    /// Fail if the system refuses a real-time setting instead of warning and going on.
    #[arg(long)]
    pub require_rt: bool,
    /// Nice value of every process of the stack at ordinary scheduling (all of them in
    /// lockstep; in realtime those given priority 0), -20..=19: default -10, so that their
    /// hand-offs are not queued behind ordinary tasks on a busy machine (needs root, else
    /// the inherited one stays); 0 keeps the inherited value
    #[arg(long, value_name = "N", allow_negative_numbers = true,
          value_parser = clap::value_parser!(i32).range(-20..=19))]
    pub nice: Option<i32>,
}

impl RtArgs {
    pub fn apply(&self, d: &mut Deployment) {
        if self.no_mlock {
            d.lock_memory = false;
        }
        if let Some(ns) = self.timer_slack_ns {
            d.timer_slack_ns = ns;
        }
        d.require_rt |= self.require_rt;
        if let Some(n) = self.nice {
            d.nice = n;
        }
    }
}

impl PlacementArgs {
    pub fn apply(&self, d: &mut Deployment, process: Role) {
        if let Some(p) = d.placement_mut(process) {
            if self.wait.is_some() {
                p.wait = self.wait;
            }
            if let Some(prio) = self.priority {
                p.priority = (prio > 0).then_some(prio);
            }
            if let Some(Cpu(cpu)) = self.cpu {
                p.cpu = cpu;
            }
        }
        self.rt.apply(d);
    }
}

/// What every process of the stack takes.
#[derive(Args, Debug, Clone)]
pub struct ProcessArgs {
    /// Instance namespace of the services; stacks with different instances never interact.
    #[arg(long, default_value = DEFAULT_INSTANCE, value_parser = stepdrive_shared::services::instance_name)]
    pub instance: String,
    #[command(flatten)]
    pub scenario: ScenarioOpt,
    /// Timing mode: lockstep (virtual time), realtime (wall clock) or hardware (the plant is
    /// a bridge to a drive). All processes of a stack must use the same.
    #[arg(long, value_enum, default_value_t = Mode::Lockstep)]
    pub mode: Mode,
    #[command(flatten)]
    pub deploy: DeployOpt,
    #[command(flatten)]
    pub timeouts: Timeouts,
    #[command(flatten)]
    pub placement: PlacementArgs,
}

impl ProcessArgs {
    /// The deployment file (or the defaults) with this command line's overrides for
    /// `process`.
    pub fn deployment(&self, process: Role) -> Result<Deployment> {
        let mut d = self.deploy.load()?;
        self.timeouts.apply(&mut d);
        self.placement.apply(&mut d, process);
        d.validate().context("command-line options")?;
        Ok(d)
    }
}

/// `--rt-throttling`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Throttling {
    On,
    Off,
}

/// Options of a launched stack.
#[derive(Args, Debug)]
pub struct StackArgs {
    /// Instance namespace of the services.
    #[arg(long, default_value = DEFAULT_INSTANCE, value_parser = stepdrive_shared::services::instance_name)]
    pub instance: String,
    #[command(flatten)]
    pub deploy: DeployOpt,
    #[command(flatten)]
    pub timeouts: Timeouts,
    /// Run length in seconds; past one pass of the trajectory the move repeats back and forth.
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub duration: Option<f64>,
    /// Realtime: SCHED_FIFO priority of plant and current loop (position loop: one more;
    /// bridge: one less than the current loop); 0 keeps everything SCHED_OTHER. Default 80.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=99))]
    pub priority: Option<u8>,
    /// Realtime: SCHED_FIFO priority of the current loop alone (default: --priority);
    /// 0 runs it SCHED_OTHER, which RT throttling does not touch.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=99))]
    pub current_priority: Option<u8>,
    /// Realtime: CPUs as PLANT,CURRENT: the plant and position loop (hardware: the drive) are
    /// pinned to the first, the current loop (and the bridge) to the second. `none` disables
    /// pinning. Default 0,1.
    #[arg(long, value_name = "A,B|none")]
    pub cpus: Option<Cpus>,
    #[command(flatten)]
    pub rt: RtArgs,
    /// Realtime: wait strategy of the plant (default hybrid:25: sleeps to 25 µs before each
    /// deadline and spins the rest, so samples leave on time although a timer wake-up here
    /// takes ~25 µs; from 3 axes, sleep: the spin would leave the other loops too little
    /// of the plant's CPU).
    #[arg(long, value_name = "STRATEGY")]
    pub plant_wait: Option<WaitStrategy>,
    /// Realtime: wait strategy of the current loop (default hybrid:35: sleep to 35 µs
    /// before the next sample's deadline, then poll; hardware mode: event). A larger margin
    /// leaves sleeps too short to give the CPU away, and an ordinary task on the current
    /// loop's CPU is then run by the kernel's fair server for ~50 ms at a time, past the
    /// watchdog.
    #[arg(long, value_name = "STRATEGY")]
    pub current_wait: Option<WaitStrategy>,
    /// Realtime: wait strategy of the position loop (default sleep).
    #[arg(long, value_name = "STRATEGY")]
    pub position_wait: Option<WaitStrategy>,
    /// Realtime: `off` (the default) sets sched_rt_runtime_us to -1 for a run with real-time
    /// priorities and restores it on every exit path, a SIGKILL of this launcher included
    /// (root; otherwise a warning). With throttling `on`, SCHED_FIFO tasks lose their CPU up
    /// to 50 ms a second whenever ordinary tasks want it: five times the watchdog.
    #[arg(long, value_enum, default_value_t = Throttling::Off)]
    pub rt_throttling: Throttling,
    /// Hardware mode: the drive's address, host:port on UDP (a name is resolved); without
    /// it (or --drive-port) an emulated drive is started on loopback.
    #[arg(long, value_name = "HOST:PORT")]
    pub drive: Option<String>,
    /// Hardware mode: the drive's serial line (an MCU board, COBS framing), e.g.
    /// /dev/ttyACM0, instead of UDP.
    #[arg(long, value_name = "PATH", conflicts_with = "drive")]
    pub drive_port: Option<PathBuf>,
    /// Hardware mode with --drive or --drive-port: the true rotor state a simulated drive
    /// writes (CSV `k,t_s,theta_rad,omega_rad_s,i_a_a,i_b_a`, k from each run's first
    /// sample; the emulated firmware's UART2, firmware/qemu-mps2/run): each method's true
    /// figures are read from it at the method's end, beside what the sensors said.
    #[arg(long, value_name = "FILE")]
    pub drive_truth: Option<PathBuf>,
    /// Realtime: periods without a command before the plant (or drive) turns its outputs off
    /// and latches a fault (default 1000 = 50 ms at 20 kHz).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub watchdog_periods: Option<u32>,
}

impl StackArgs {
    /// The stack's deployment: the file (or the defaults), then this command line.
    pub fn deployment(&self, mode: Mode) -> Result<Deployment> {
        let mut d = self.deploy.load()?;
        self.timeouts.apply(&mut d);
        if self.priority.is_some() || self.current_priority.is_some() {
            let plant = self.priority.or(d.plant.priority).unwrap_or(0);
            let current = self.current_priority.or(self.priority).unwrap_or(plant);
            d.set_priorities(plant, current);
        }
        if let Some(Cpus(cpus)) = self.cpus {
            if let Some((a, b)) = cpus {
                for cpu in [a, b] {
                    stepdrive_runtime::rt::cpu_exists(cpu)
                        .map_err(|e| anyhow::anyhow!("--cpus: {e}"))?;
                }
            }
            d.set_cpus(cpus);
        }
        self.rt.apply(&mut d);
        for (wait, process) in [
            (self.plant_wait, Role::Plant),
            (self.current_wait, Role::CurrentLoop),
            (self.position_wait, Role::PositionLoop),
        ] {
            if wait.is_some() {
                if let Some(p) = d.placement_mut(process) {
                    p.wait = wait;
                }
            }
        }
        if let Some(n) = self.watchdog_periods {
            d.watchdog_periods = n;
        }
        let drive = match (&self.drive, &self.drive_port) {
            (Some(addr), _) => Some(addr.clone()),
            (None, Some(path)) => Some(format!("serial:{}", path.display())),
            (None, None) => None,
        };
        if drive.is_some() && mode != Mode::Hardware {
            anyhow::bail!(
                "--drive and --drive-port are for --mode hardware (this run is {})",
                mode.as_str()
            );
        }
        if self.drive_truth.is_some() && drive.is_none() {
            anyhow::bail!(
                "--drive-truth is for a drive of --drive or --drive-port (an emulated drive started for the run writes its own)"
            );
        }
        if drive.is_some() {
            d.drive.address = drive;
        }
        if let (Mode::Hardware, Some(addr)) = (mode, &d.drive.address) {
            check_drive_address(addr)?;
        }
        d.validate_for(mode).context("command-line options")?;
        Ok(d)
    }

    pub fn apply_duration(&self, s: &mut Scenario) -> Result<()> {
        if let Some(d) = self.duration {
            s.run.duration_s = Some(d);
            s.validate().context("--duration")?;
        }
        Ok(())
    }
}

/// A drive address that cannot name a drive is bad input, said before anything starts (a
/// bridge failing on it would be reported as a dead process): a UDP address must resolve,
/// a serial line must exist.
fn check_drive_address(addrs: &str) -> Result<()> {
    use stepdrive_bridge::node::{drive_addresses, DriveAddr};
    // A multi-axis stack's drives, one address per axis.
    for addr in drive_addresses(addrs) {
        match addr.parse::<DriveAddr>() {
            Err(e) => {
                return Err(
                    anyhow::Error::new(e).context("the drive's address (--drive, [drive] address)")
                )
            }
            Ok(DriveAddr::Serial(path)) if !path.exists() => anyhow::bail!(
                "no serial line at {} (--drive-port, [drive] address): is the drive connected?",
                path.display()
            ),
            Ok(_) => {}
        }
    }
    Ok(())
}

/// The live view in Foxglove or Lichtblick.
#[derive(Args, Debug)]
pub struct LiveArgs {
    /// Serve a live view of the stack on ADDR (e.g. 127.0.0.1:8765; port 0: a free one,
    /// logged) over the Foxglove WebSocket protocol: the recording's channels, each with its
    /// JSON Schema. In Foxglove (or Lichtblick): Open connection → Foxglove WebSocket →
    /// ws://ADDR, then a Plot panel of e.g. /proposed/state.error.
    #[arg(long, value_name = "ADDR")]
    pub foxglove: Option<std::net::SocketAddr>,
    /// The live view's rate for the streams (state, setpoints, commands, axis status), Hz,
    /// by the stack's time; the events (faults, axis acknowledgements, loop statistics) go
    /// out as they come.
    #[arg(long, value_name = "HZ", requires = "foxglove", default_value_t = stepdrive_monitor::record::live::DEFAULT_RATE_HZ)]
    pub foxglove_rate: f64,
}

impl LiveArgs {
    /// The live view, started, if one was asked for.
    pub fn start(&self) -> Result<Option<stepdrive_monitor::record::live::LiveView>> {
        let Some(addr) = self.foxglove else {
            return Ok(None);
        };
        let view = stepdrive_monitor::record::live::LiveView::start(addr, self.foxglove_rate)
            .context("--foxglove")?;
        tracing::info!(
            "live view on ws://{} (Foxglove WebSocket, streams at {} Hz)",
            view.addr(),
            self.foxglove_rate
        );
        Ok(Some(view))
    }
}

/// A hardware stack's drive addresses against its scenario's axes: one per axis.
pub fn check_drive_count(s: &Scenario, d: &Deployment) -> Result<()> {
    let Some(addr) = d.drive.address.as_deref() else {
        return Ok(());
    };
    let given = stepdrive_bridge::node::drive_addresses(addr).len();
    if given != s.axis_count() {
        anyhow::bail!(
            "scenario {} has {} axes and {given} drive addresses were given (--drive A,B,...: \
             one per axis, in axis order)",
            s.name,
            s.axis_count()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{number_within, CpuList};

    #[test]
    fn a_cpu_list_is_cpus_and_ranges_that_exist_or_any() {
        let list = |s: &str| s.parse::<CpuList>().map(|c| c.0);
        assert_eq!(list("0"), Ok(vec![0]));
        assert_eq!(list("any"), Ok(vec![]));
        let n = stepdrive_runtime::rt::configured_cpus();
        if n >= 2 {
            assert_eq!(list("1,0-1"), Ok(vec![0, 1]));
        }
        let e = list(&n.to_string()).expect_err("a CPU past the last");
        assert!(e.contains("does not exist"), "{e}");
        for bad in ["", "x", "1-0", "0,", "-1", "0-"] {
            let e = list(bad).expect_err(bad);
            assert!(e.contains("is not a CPU list"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_number_outside_its_range_or_not_a_number_is_refused_naming_the_range() {
        let rate = |s| number_within(s, 0.0, 10_000.0, true, "Hz");
        assert_eq!(rate("100"), Ok(100.0));
        assert_eq!(rate("10000"), Ok(10_000.0));
        for bad in ["0", "-1", "10000.5", "nan", "inf", "fast"] {
            let e = rate(bad).expect_err(bad);
            assert!(e.contains("above 0 … 10000 Hz") && e.contains(bad), "{e}");
        }
        let period = |s| number_within(s, 1e-3, 3600.0, false, "seconds");
        assert_eq!(period("0.001"), Ok(1e-3));
        assert!(period("0.0009").is_err());
    }
}
