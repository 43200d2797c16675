//! The stack's processes: each sub-command builds its node and ports and hands them to the
//! runtime's one runner (`run_process`). They find each other by instance name, in any
//! order; `run` starts them with its scenario and deployment files.

use crate::commands::Exit;
use crate::options::{seconds, DeployOpt, PlacementArgs, ProcessArgs, ScenarioOpt};
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use std::path::PathBuf;
use stepdrive_bridge::link::{EncoderCalibration, HeldLoad};
use stepdrive_bridge::{BridgeNode, BridgePorts, BridgeSettings, DriveAddr};
use stepdrive_controller::current_loop_node::{CurrentLoopNode, CurrentLoopPorts};
use stepdrive_controller::position_loop_node::{PositionLoopNode, PositionLoopPorts};
use stepdrive_emulated_drive::{run_emulator, AlignFault, EmulatorOptions, FaultInjection};
use stepdrive_monitor::outcome::{fault_names, Outcome, LATCHED};
use stepdrive_monitor::pingpong::{PingPongOptions, Transport};
use stepdrive_plant::node::{PlantNode, PlantPorts, PlantSettings};
use stepdrive_runtime::deploy::{Deployment, Process};
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_runtime::process::{run_process, ProcessSpec};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::{Method, Scenario};

/// Realtime: the first deadline this long after the plant sees its peers, so that every
/// process is in its loop by then.
const PLANT_START_DELAY_NS: u64 = 20_000_000;

#[derive(Args, Debug)]
pub struct PlantArgs {
    #[command(flatten)]
    pub common: ProcessArgs,
    /// Realtime: after this many periods in a row without a command the outputs go off
    /// (zero volts) and a fault is latched (default 1000 = 50 ms at 20 kHz).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub watchdog_periods: Option<u32>,
    /// drive/state subscribers to wait for before the first sample: 2 = current and
    /// position loops; 3 adds a monitor.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub wait_subscribers: u32,
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

fn spec<'a>(
    a: &'a ProcessArgs,
    process: Process,
    node_name: &'a str,
    d: &'a Deployment,
    scenario: &'a Scenario,
) -> ProcessSpec<'a> {
    ProcessSpec {
        instance: &a.instance,
        mode: a.mode,
        process,
        node_name,
        deployment: d,
        scenario,
    }
}

pub fn plant(a: PlantArgs) -> Result<()> {
    let s = a.common.scenario.load()?;
    let mode = a.common.mode;
    let process = if mode == Mode::Hardware {
        Process::Bridge
    } else {
        Process::Plant
    };
    let mut d = a.common.deployment(process)?;
    a.drive.apply(&mut d);
    if let Some(n) = a.watchdog_periods {
        d.watchdog_periods = n;
    }
    d.validate().context("command-line options")?;
    let wait_subscribers = a.wait_subscribers as usize;
    if mode != Mode::Hardware {
        if a.drive.drive.is_some() {
            bail!(
                "--drive is for --mode hardware: in {} mode the plant is the motor model",
                mode.as_str()
            );
        }
        let settings = PlantSettings {
            mode,
            wait_subscribers,
            wait_position_loop: !a.no_position_loop,
            watchdog_periods: d.watchdog_periods,
            start_delay_ns: PLANT_START_DELAY_NS,
        };
        let finished = run_process(&spec(&a.common, process, "plant", &d, &s), |bus| {
            Ok((PlantNode::new(&s, settings), PlantPorts::open(bus, mode)?))
        })?;
        return ended_safe("plant", finished.node.latched_fault());
    }
    let drive: DriveAddr = d
        .drive
        .address
        .as_deref()
        .context("in hardware mode the plant is a bridge to a drive: give it with --drive HOST:PORT (or a serial device path)")?
        .parse()?;
    let wait = d.wait(Process::Bridge, mode);
    if wait == WaitStrategy::Event {
        bail!(
            "--wait event is for the current loop; the bridge waits for the drive's frames \
             with sleep, spin or hybrid:<µs>"
        );
    }
    let settings = BridgeSettings {
        drive,
        wait_subscribers,
        wait_position_loop: !a.no_position_loop,
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
    };
    let finished = run_process(&spec(&a.common, process, "plant", &d, &s), |bus| {
        let node = BridgeNode::new(&s, settings.clone())?;
        let ports = BridgePorts::open(bus, &settings.drive)?;
        Ok((node, ports))
    })?;
    ended_safe("bridge", finished.node.core().last_fault())
}

/// A plant or bridge that ends its run with a latched fault has lost the motor: it says so
/// and exits with the fault's code.
fn ended_safe(who: &str, fault: u32) -> Result<()> {
    if fault & LATCHED == 0 {
        return Ok(());
    }
    Err(Exit {
        code: Outcome::Fault.exit_code(),
        headline: format!(
            "FAULT (exit {}): the {who} ended its run with {} latched; the outputs are off. \
             See the log above for when and why; `stepdrive reset --instance NAME` clears it \
             once the cause is gone.",
            Outcome::Fault.exit_code(),
            fault_names(fault).join(" and ")
        ),
    }
    .into())
}

#[derive(Args, Debug)]
pub struct CurrentLoopArgs {
    #[command(flatten)]
    pub common: ProcessArgs,
    /// Control method: proposed (17)+(22), lyapunov (39), open_loop (2).
    #[arg(long, value_enum, default_value_t = Method::Proposed)]
    pub method: Method,
}

/// Whether the current loop's process sleeps on the bridge's state-ready event (`--wait
/// event`), which only a bridge raises.
fn waits_on_event(d: &Deployment, mode: Mode) -> Result<bool> {
    let event = d.wait(Process::CurrentLoop, mode) == WaitStrategy::Event;
    if event && mode != Mode::Hardware {
        bail!(
            "--wait event needs a plant that raises state-ready: only the bridge does \
             (--mode hardware)"
        );
    }
    Ok(event)
}

pub fn current_loop(a: CurrentLoopArgs) -> Result<()> {
    let s = a.common.scenario.load()?;
    let d = a.common.deployment(Process::CurrentLoop)?;
    let mode = a.common.mode;
    let event = waits_on_event(&d, mode)?;
    run_process(
        &spec(&a.common, Process::CurrentLoop, "current-loop", &d, &s),
        |bus| {
            Ok((
                CurrentLoopNode::new(&s, a.method, mode).watching_setpoints(d.peer_timeout()),
                CurrentLoopPorts::open(bus, mode, event)?,
            ))
        },
    )?;
    Ok(())
}

pub fn position_loop(a: ProcessArgs) -> Result<()> {
    let s = a.scenario.load()?;
    let d = a.deployment(Process::PositionLoop)?;
    // Half a current period after the plant's samples: each tick finds its sample out.
    let phase_ns = s.sample_period_ns() / 2;
    run_process(
        &spec(&a, Process::PositionLoop, "position-loop", &d, &s),
        |bus| {
            Ok((
                PositionLoopNode::new(&s, a.mode, phase_ns),
                PositionLoopPorts::open(bus)?,
            ))
        },
    )?;
    Ok(())
}

#[derive(Args, Debug)]
pub struct EmulateArgs {
    /// UDP address to listen on for the bridge.
    #[arg(long, default_value = "127.0.0.1:7700")]
    pub listen: std::net::SocketAddr,
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
    /// Fault injection: freeze the drive once, after S seconds of running (from the ENABLE), for
    /// --freeze-ms (no frames, its clock paused: what a host stall does to it).
    #[arg(long, value_name = "S")]
    pub freeze_at: Option<f64>,
    #[arg(long, default_value_t = 0, value_name = "MS")]
    pub freeze_ms: u64,
    /// Fault injection: latch an over-current fault after S seconds of running (from the ENABLE).
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
    a.placement.apply(&mut d, Process::EmulatedDrive);
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
        serial: a.serial,
        scenario,
        // The drive stands for hardware: it always runs on the wall clock.
        wait: d.wait(Process::EmulatedDrive, Mode::Realtime),
        rt: d.rt(Process::EmulatedDrive, Mode::Realtime),
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
        (Process::Plant, WaitStrategy::Sleep)
    } else {
        (
            Process::CurrentLoop,
            d.wait(Process::CurrentLoop, Mode::Realtime),
        )
    };
    stepdrive_monitor::pingpong::run(&PingPongOptions {
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
    use stepdrive_controller::identify::Bounds;
    use stepdrive_controller::identify_node::{IdentifyNode, IdentifyPorts};
    use stepdrive_monitor::identify::{conclude, IdentifyError, NodeResult};
    let s = a.common.scenario.load()?;
    let d = a.common.deployment(Process::CurrentLoop)?;
    let mode = a.common.mode;
    let event = waits_on_event(&d, mode)?;
    let bounds = Bounds {
        current_a: a.max_current,
        voltage_v: a.max_voltage,
        speed_rad_s: a.max_speed,
        travel_rad: a.max_travel,
    };
    let finished = run_process(
        &spec(&a.common, Process::CurrentLoop, "current-loop", &d, &s),
        |bus| {
            Ok((
                IdentifyNode::new(&s, bounds, mode),
                IdentifyPorts::open(bus, mode, event)?,
            ))
        },
    )?;
    let result = match conclude(&s, &finished.node, s.sample_period_s()) {
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
