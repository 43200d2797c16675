//! The stack's processes: each sub-command builds its node and ports and hands them to the
//! runtime's one runner (`run_process`). They find each other by instance name, in any
//! order; `run` starts them with its scenario and deployment files.

use crate::commands::Exit;
use crate::options::{seconds, DeployOpt, PlacementArgs, ProcessArgs, ScenarioOpt};
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use std::path::PathBuf;
use stepdrive_control::identify::Bounds;
use stepdrive_emulated_drive::{run_emulator, AlignFault, EmulatorOptions, FaultInjection};
use stepdrive_monitor::assemble::{assemble, Assemble, Setup};
use stepdrive_monitor::latency::pingpong::{PingPongOptions, Transport};
use stepdrive_monitor::report::outcome::{fault_names, Outcome, LATCHED};
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::node::{Node, Role};
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_runtime::process::{Process, ProcessSpec};
use stepdrive_runtime::RunError;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stack::{stack, Purpose};
use stepdrive_shared::{Method, Scenario};

#[derive(Args, Debug)]
pub struct DeviceArgs {
    #[command(flatten)]
    pub common: ProcessArgs,
    /// Realtime: after this many periods in a row without a command the outputs go off
    /// (zero volts) and a fault is latched (default 1000 = 50 ms at 20 kHz).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub watchdog_periods: Option<u32>,
    /// drive/state subscribers to wait for before the first sample (default: the stack's
    /// own readers, the current and position loops; 3 adds a monitor).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub wait_subscribers: Option<u32>,
    /// Start without a position loop: a tool drives the plant alone (`stepdrive identify`).
    #[arg(long)]
    pub no_position_loop: bool,
    #[command(flatten)]
    pub drive: DriveLinkArgs,
}

/// Hardware mode: the plant process is a bridge to a drive speaking
/// docs/drive-protocol.md. These override the deployment's `[drive]`.
#[derive(Args, Debug)]
pub struct DriveLinkArgs {
    /// Hardware mode: the drive, host:port on UDP or a serial line's path (COBS framing).
    #[arg(long, value_name = "HOST:PORT|PATH")]
    pub drive: Option<String>,
    /// Bridge: periods without a valid sample before it publishes a fault and stops
    /// forwarding commands (default 200).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub silence_periods: Option<u32>,
    /// Bridge: send the current loop's voltage plan to the drive (if its CONFIG says it keeps
    /// one) whenever it is this many samples newer than the last sent (default 1: every plan
    /// the current loop publishes, i.e. every 10th command and after each lost sample).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub plan_every: Option<u32>,
    /// Bridge: encoder reading (counts) at θ = 0, for an absolute encoder; by default the
    /// first sample is θ = 0.
    #[arg(long, value_name = "COUNTS", allow_negative_numbers = true)]
    pub encoder_offset: Option<i64>,
    /// Bridge: counts increase for negative θ, whatever the drive's CONFIG says.
    #[arg(long)]
    pub reverse_encoder: bool,
    /// Bridge: bandwidth of the encoder velocity observer, Hz (default 400).
    #[arg(long, value_name = "HZ")]
    pub observer_hz: Option<f64>,
}

impl DriveLinkArgs {
    fn apply(&self, d: &mut Deployment) {
        let link = &mut d.drive;
        if self.drive.is_some() {
            link.address = self.drive.clone();
        }
        if let Some(n) = self.silence_periods {
            link.silence_periods = n;
        }
        if let Some(n) = self.plan_every {
            link.plan_every = n;
        }
        if self.encoder_offset.is_some() {
            link.encoder_offset_counts = self.encoder_offset;
        }
        link.reverse_encoder |= self.reverse_encoder;
        if let Some(hz) = self.observer_hz {
            link.observer_hz = hz;
        }
    }
}

/// One role's process: its node, built from the stack's declaration, on the runner.
struct RoleProcess<'a> {
    role: Role,
    args: &'a ProcessArgs,
    deployment: Deployment,
    scenario: Scenario,
}

impl<'a> RoleProcess<'a> {
    fn new(role: Role, args: &'a ProcessArgs, deployment: Deployment) -> Result<Self> {
        Ok(Self {
            role,
            args,
            deployment,
            scenario: args.scenario.load()?,
        })
    }

    fn spec(&self) -> ProcessSpec<'_> {
        ProcessSpec {
            instance: &self.args.instance,
            mode: self.args.mode,
            role: self.role,
            deployment: &self.deployment,
            scenario: &self.scenario,
        }
    }

    /// The setup of a stack for `purpose` started by hand: the device waits for the stack's
    /// own readers.
    fn setup(&self, purpose: Purpose) -> Setup<'_> {
        let stack = stack(self.args.mode, purpose);
        Setup::new(&self.scenario, &stack, &self.deployment, 0, true)
    }
}

/// Runs the node in this process and returns the faults it latched by the end of its run.
struct InProcess<'a>(Process<'a>);

impl Assemble for InProcess<'_> {
    type Out = u32;
    fn node<N: Node + 'static>(&mut self, node: N, ports: N::Ports) -> Result<u32, RunError> {
        Ok(self.0.run(node, ports)?.node.latched_fault())
    }
}

/// Builds `role`'s node from the declaration and runs it in this process; a device that
/// ends its run with a latched fault says so (exit 3).
fn run_role(p: &RoleProcess, setup: &Setup) -> Result<()> {
    let spec = p.spec();
    let (process, mut bus) = Process::open(&spec)?;
    let fault = assemble(p.role, setup, &mut bus, &mut InProcess(process))?;
    ended_safe(p.role, fault)
}

/// A plant or bridge that ends its run with a latched fault has lost the motor: it says so
/// and exits with the fault's code.
fn ended_safe(role: Role, fault: u32) -> Result<()> {
    if fault & LATCHED == 0 {
        return Ok(());
    }
    Err(Exit {
        code: Outcome::Fault.exit_code(),
        headline: format!(
            "FAULT (exit {}): the {role} ended its run with {} latched; the outputs are off. \
             See the log above for when and why; `stepdrive reset --instance NAME` clears it \
             once the cause is gone.",
            Outcome::Fault.exit_code(),
            fault_names(fault).join(" and ")
        ),
    }
    .into())
}

/// `stepdrive plant` (and `bridge`): the device. In hardware mode `plant` is the bridge.
pub fn device(a: DeviceArgs, asked: Role) -> Result<()> {
    let mode = a.common.mode;
    let role = match mode {
        Mode::Hardware => Role::Bridge,
        Mode::Lockstep | Mode::Realtime if asked == Role::Bridge => bail!(
            "the bridge talks to a drive: it runs in --mode hardware (in {} mode the device is \
             the plant: `stepdrive plant`)",
            mode.as_str()
        ),
        Mode::Lockstep | Mode::Realtime => Role::Plant,
    };
    let mut d = a.common.deployment(role)?;
    a.drive.apply(&mut d);
    if let Some(n) = a.watchdog_periods {
        d.watchdog_periods = n;
    }
    d.validate().context("command-line options")?;
    if role == Role::Plant && a.drive.drive.is_some() {
        bail!(
            "--drive is for --mode hardware: in {} mode the plant is the motor model",
            mode.as_str()
        );
    }
    let p = RoleProcess::new(role, &a.common, d)?;
    let purpose = match a.no_position_loop {
        true => Purpose::Identify,
        false => Purpose::Control,
    };
    let mut setup = p.setup(purpose);
    if let Some(n) = a.wait_subscribers {
        setup.state_readers = n as usize;
    }
    run_role(&p, &setup)
}
#[derive(Args, Debug)]
pub struct CurrentLoopArgs {
    #[command(flatten)]
    pub common: ProcessArgs,
    /// Control method: proposed (17)+(22), lyapunov (39), open_loop (2), pi.
    #[arg(long, value_enum, default_value_t = Method::Proposed)]
    pub method: Method,
}

pub fn current_loop(a: CurrentLoopArgs) -> Result<()> {
    let d = a.common.deployment(Role::CurrentLoop)?;
    let p = RoleProcess::new(Role::CurrentLoop, &a.common, d)?;
    let mut setup = p.setup(Purpose::Control);
    setup.method = a.method;
    run_role(&p, &setup)
}

pub fn position_loop(a: ProcessArgs) -> Result<()> {
    let d = a.deployment(Role::PositionLoop)?;
    let p = RoleProcess::new(Role::PositionLoop, &a, d)?;
    run_role(&p, &p.setup(Purpose::Control))
}

#[derive(Args, Debug)]
pub struct EmulateArgs {
    /// UDP address to listen on for the bridge; a multi-axis scenario's drives, one
    /// address per axis (`A,B,...`), all in this process.
    #[arg(long, default_value = "127.0.0.1:7700", value_delimiter = ',')]
    pub listen: Vec<std::net::SocketAddr>,
    /// A multi-axis scenario's drives: the axis whose drive the injected faults (below)
    /// act on; the others run clean.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub inject_axis: usize,
    /// Speak on this serial line (UART or pseudo-terminal, COBS framing) instead of UDP.
    #[arg(long, value_name = "PATH")]
    pub serial: Option<PathBuf>,
    #[command(flatten)]
    pub scenario: ScenarioOpt,
    #[command(flatten)]
    pub deploy: DeployOpt,
    /// Periods without a valid command before outputs go off and a fault latches
    /// (default: the deployment's watchdog, 1000).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    pub watchdog_periods: Option<u16>,
    /// PLAN entries the drive keeps (announced in CONFIG): when a COMMAND is late it applies
    /// the plan's entry for that period instead of holding the last duty. 0: no plans
    /// (default 1000: as long as the default watchdog, so a late host is covered until the
    /// watchdog trips; a serial line needs fewer, see docs/drive-protocol.md §4.7).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(0..=1024))]
    pub plan_capacity: Option<u16>,
    /// ALIGN time, ms: phase A at --align-ma brings the rotor to an electrical zero before
    /// each run (docs/drive-protocol.md §7). 0: the drive does not align, as one with an
    /// absolute encoder may not (the host then needs --encoder-offset).
    #[arg(long, default_value_t = 300, value_name = "MS")]
    pub align_ms: u16,
    /// ALIGN current, mA (its voltage R·I is capped at the bus).
    #[arg(long, default_value_t = 1000, value_name = "MA", value_parser = clap::value_parser!(u16).range(1..))]
    pub align_ma: u16,
    /// Stop after this many seconds (default: run until SIGINT/SIGTERM).
    #[arg(long, value_name = "S")]
    pub duration: Option<f64>,
    /// Write the rotor's true state (the model's θ from the electrical zero, ω, i_a, i_b;
    /// not the sensors') of every sample of each run to FILE as CSV. Only an emulated
    /// drive knows it; `run --mode hardware` compares it with what the stack measured.
    #[arg(long, value_name = "FILE")]
    pub truth: Option<PathBuf>,
    #[command(flatten)]
    pub inject: InjectArgs,
    #[command(flatten)]
    pub placement: PlacementArgs,
}

#[derive(Args, Debug)]
pub struct InjectArgs {
    /// Fault injection: drop every N-th sample frame.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub drop_every: u64,
    /// Fault injection: corrupt one bit of every N-th sample frame.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub corrupt_every: u64,
    /// Fault injection: send every N-th sample frame after the next one.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub reorder_every: u64,
    /// Fault injection: hold every N-th sample frame for --delay-us before sending it.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub delay_every: u64,
    /// Fault injection: how long --delay-every holds a frame, µs (longer than a period: it
    /// arrives after newer frames and is dropped as out of order).
    #[arg(long, default_value_t = 0, value_name = "US")]
    pub delay_us: u64,
    /// Fault injection: send every N-th sample frame twice.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub duplicate_every: u64,
    /// Fault injection: stop sending samples after S seconds of running (from the ENABLE).
    #[arg(long, value_name = "S")]
    pub stop_after: Option<f64>,
    /// Fault injection: freeze the drive once, after S seconds of running, for --freeze-ms (no
    /// frames, its clock paused: what a host stall does to it). Seconds count from a run's
    /// first SAMPLE (docs/drive-protocol.md §7 step 5); the host's phase-B step (--align-ms
    /// long) is a run to the drive, so pick S past it to hit the host's run.
    #[arg(long, value_name = "S")]
    pub freeze_at: Option<f64>,
    #[arg(long, default_value_t = 0, value_name = "MS")]
    pub freeze_ms: u64,
    /// Fault injection: latch an over-current fault after S seconds of running (counted as
    /// for --freeze-at: pick S past the phase-B step to hit the host's run).
    #[arg(long, value_name = "S")]
    pub overcurrent_after: Option<f64>,
    /// Fault injection: drop each sample frame with probability P % (seeded: the same
    /// frames every run).
    #[arg(long, default_value_t = 0.0, value_name = "P", value_parser = percent)]
    pub drop_pct: f64,
    /// Fault injection: corrupt one bit of each sample frame with probability P %.
    #[arg(long, default_value_t = 0.0, value_name = "P", value_parser = percent)]
    pub corrupt_pct: f64,
    /// Fault injection: after S seconds of running (from the ENABLE), drop --dropout-samples samples in a row
    /// (the drive keeps running: a link outage, not a drive stall).
    #[arg(long, value_name = "S")]
    pub dropout_at: Option<f64>,
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub dropout_samples: u64,
    /// Fault injection: break the ALIGN (§7). stuck: ALIGNING never clears; reversed:
    /// phase A is energized the wrong way, leaving the rotor half an electrical period off;
    /// swapped-leads: phase A's motor leads swapped (the drive's shunt still reads +I).
    #[arg(long, value_enum, default_value_t = AlignInjection::None)]
    pub align_fault: AlignInjection,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum AlignInjection {
    None,
    Stuck,
    Reversed,
    SwappedLeads,
}

fn percent(s: &str) -> Result<f64, String> {
    let p: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if (0.0..=100.0).contains(&p) {
        Ok(p)
    } else {
        Err(format!("{s} is not a percentage (0 … 100)"))
    }
}

pub fn emulate_drive(a: EmulateArgs) -> Result<()> {
    let scenario = a.scenario.load()?;
    let mut d = a.deploy.load()?;
    a.placement.apply(&mut d, Role::EmulatedDrive);
    d.validate().context("command-line options")?;
    let watchdog_periods = match a.watchdog_periods {
        Some(n) => n,
        None => u16::try_from(d.watchdog_periods).map_err(|_| {
            anyhow::anyhow!(
                "watchdog_periods {} is more than a drive's CONFIG can carry (65535)",
                d.watchdog_periods
            )
        })?,
    };
    let duration = match a.duration {
        Some(s) => Some(
            seconds(s)
                .map_err(anyhow::Error::msg)
                .context("--duration")?,
        ),
        None => None,
    };
    let i = &a.inject;
    run_emulator(&EmulatorOptions {
        listen: a.listen,
        inject_axis: a.inject_axis,
        serial: a.serial,
        scenario,
        // The drive stands for hardware: it always runs on the wall clock.
        wait: d.wait(Role::EmulatedDrive, Mode::Realtime),
        rt: d.rt(Role::EmulatedDrive, Mode::Realtime),
        watchdog_periods,
        plan_capacity: a.plan_capacity.unwrap_or(d.drive.emulated_plan_capacity),
        align_ma: a.align_ma,
        align_ms: a.align_ms,
        inject: FaultInjection {
            drop_every: i.drop_every,
            corrupt_every: i.corrupt_every,
            reorder_every: i.reorder_every,
            delay_every: i.delay_every,
            delay_ns: i.delay_us.saturating_mul(1000),
            duplicate_every: i.duplicate_every,
            stop_after_s: i.stop_after,
            overcurrent_after_s: i.overcurrent_after,
            freeze_at_s: i.freeze_at,
            freeze_ns: i.freeze_ms.saturating_mul(1_000_000),
            drop_fraction: i.drop_pct / 100.0,
            corrupt_fraction: i.corrupt_pct / 100.0,
            dropout_at_s: i.dropout_at,
            dropout_samples: i.dropout_samples,
            align: match i.align_fault {
                AlignInjection::None => AlignFault::None,
                AlignInjection::Stuck => AlignFault::Stuck,
                AlignInjection::Reversed => AlignFault::Reversed,
                AlignInjection::SwappedLeads => AlignFault::SwappedLeads,
            },
        },
        duration,
        truth: a.truth,
    })
    .context("emulated drive")?;
    Ok(())
}

/// Which side of the ping-pong this process is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PingPongRole {
    Ping,
    Pong,
}

#[derive(Args, Debug)]
pub struct PingpongArgs {
    #[arg(long, value_enum)]
    pub transport: Transport,
    #[arg(long, value_enum)]
    pub role: PingPongRole,
    #[arg(long)]
    pub endpoint: String,
    #[arg(long, default_value_t = 50.0)]
    pub period_us: f64,
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
    /// The ping side is placed like the plant, the pong side like the current loop (and
    /// waits like it).
    #[command(flatten)]
    pub deploy: DeployOpt,
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn pingpong(a: PingpongArgs) -> Result<()> {
    if !(a.period_us.is_finite() && a.period_us >= 1.0) {
        bail!("--period-us must be ≥ 1");
    }
    let duration = seconds(a.duration).map_err(anyhow::Error::msg)?;
    let d = a.deploy.load()?;
    let ping = a.role == PingPongRole::Ping;
    let (process, wait) = if ping {
        // Paced like the plant, on a plain sleep.
        (Role::Plant, WaitStrategy::Sleep)
    } else {
        (Role::CurrentLoop, d.wait(Role::CurrentLoop, Mode::Realtime))
    };
    stepdrive_monitor::latency::pingpong::run(&PingPongOptions {
        transport: a.transport,
        endpoint: a.endpoint,
        ping,
        period_ns: (a.period_us * 1000.0).round() as u64,
        duration,
        wait,
        rt: d.rt(process, Mode::Realtime),
        out: a.out,
    })
}

/// `stepdrive identify`'s sequence as a process of the stack, in the current loop's place.
#[derive(Args, Debug)]
pub struct IdentifyNodeArgs {
    #[command(flatten)]
    pub common: ProcessArgs,
    #[arg(long, value_name = "A")]
    pub max_current: f64,
    #[arg(long, value_name = "V")]
    pub max_voltage: f64,
    #[arg(long, value_name = "RAD_S")]
    pub max_speed: f64,
    #[arg(long, value_name = "RAD")]
    pub max_travel: f64,
    /// Where the estimates (or why there are none) go, as JSON.
    #[arg(long, value_name = "FILE")]
    pub result: PathBuf,
}

pub fn identify_node(a: IdentifyNodeArgs) -> Result<()> {
    use stepdrive_monitor::studies::identify::{conclude, IdentifyError, NodeResult};
    let d = a.common.deployment(Role::Identify)?;
    let p = RoleProcess::new(Role::Identify, &a.common, d)?;
    let mut setup = p.setup(Purpose::Identify);
    setup.bounds = Bounds {
        current_a: a.max_current,
        voltage_v: a.max_voltage,
        speed_rad_s: a.max_speed,
        travel_rad: a.max_travel,
    };
    // Built as `assemble` builds it, but kept: its fits need what it recorded.
    let spec = p.spec();
    let (mut process, mut bus) = Process::open(&spec)?;
    let (node, ports) = stepdrive_monitor::assemble::identify(&setup, &mut bus)?;
    let finished = process.run(node, ports)?;
    let s = &p.scenario;
    let result = match conclude(s, &finished.node, s.sample_period_s()) {
        Ok(found) => NodeResult::Estimates(found.estimates),
        Err(IdentifyError::Bound {
            hit,
            applied_after_v,
        }) => NodeResult::Stopped {
            hit: hit.to_string(),
            applied_after_v,
        },
        Err(e) => NodeResult::Failed(e.to_string()),
    };
    std::fs::write(&a.result, serde_json::to_string(&result)?)
        .with_context(|| format!("cannot write {}", a.result.display()))?;
    Ok(())
}
