//! `stepdrive`: one binary, one sub-command per role. `run` launches the whole stack; `plant`,
//! `current-loop` and `position-loop` are the three processes (start them by hand in three
//! terminals and they find each other by instance name).

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;
use stepdrive_controller::process::{
    run_current_loop, run_current_loop_realtime, run_position_loop, run_position_loop_realtime,
    ControllerError, LoopOptions, RealtimeLoopOptions,
};
use stepdrive_monitor::latency::{run_latency, table as latency_table, LatencyOptions};
use stepdrive_monitor::launcher::{run_stack, Interrupted, LaunchOptions, RoleRt};
use stepdrive_monitor::metrics::RunReport;
use stepdrive_monitor::pingpong::PingPongOptions;
use stepdrive_monitor::report::{document, table};
use stepdrive_monitor::simulate::{simulate, simulate_stalls};
use stepdrive_plant::bridge::{
    default_wait as bridge_default_wait, run_bridge, BridgeOptions, DriveAddr, EncoderCalibration,
};
use stepdrive_plant::emulator::{run_emulator, EmulatorOptions, FaultInjection};
use stepdrive_plant::process::{PlantError, PlantOptions, RealtimeOptions};
use stepdrive_shared::pacer::WaitStrategy;
use stepdrive_shared::poll::install_termination_handler;
use stepdrive_shared::rt::{rt_runtime_us, RtOptions, RtThrottlingOff};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::DEFAULT_INSTANCE;
use stepdrive_shared::{Method, Scenario};

#[derive(Parser, Debug)]
#[command(
    name = "stepdrive",
    version,
    about = "Position control of two-phase PM stepper motors: plant, current loop and position loop as separate processes over iceoryx2",
    long_about = "Position control of two-phase PM stepper motors (Kim, Shin & Chung: microstepping with \
nonlinear torque modulation). The plant, the current loop and the position/torque loop run as \
separate processes that exchange state through iceoryx2 shared memory.\n\n\
`stepdrive run` launches all three, runs the scenario for each method and prints a table. \
Logs go to stderr (RUST_LOG=debug for more; IOX2_LOG_LEVEL for iceoryx2's own)."
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Launch plant, position loop and current loop as processes, run the scenario for each
    /// method, print the side-by-side table (and JSON with --json).
    Run(RunArgs),
    /// Same loop bodies in one process, no IPC: the reference a `run` must reproduce exactly.
    Simulate(SimulateArgs),
    /// The plant process: motor model eq. (1), publishes drive/state, applies drive/command.
    Plant(PlantArgs),
    /// The current-loop process: commutation (17) + sampled current tracking (22), or a baseline.
    CurrentLoop(CurrentLoopArgs),
    /// The position/torque-loop process: trajectory + torque modulation (12).
    PositionLoop(ProcessArgs),
    /// Print the default scenario as TOML, or check a scenario file.
    Scenario(ScenarioArgs),
    /// Latency and jitter of the live stack in realtime mode, beside bare iceoryx2 and
    /// Unix-socket ping-pong and cyclictest: table, latency.json, cyclictest-compatible
    /// histograms and a log-y plot in --out DIR.
    Latency(LatencyArgs),
    /// A stand-in driver board: the motor model behind the drive wire protocol
    /// (docs/drive-protocol.md) on UDP or a serial line, with its own sample clock and
    /// fault injection.
    EmulateDrive(EmulateArgs),
    /// Transport baseline process used by `latency` (ping paced like the plant, pong waiting
    /// like the current loop).
    #[command(hide = true)]
    Pingpong(PingpongArgs),
}

#[derive(Args, Debug)]
struct LatencyArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// Directory for latency.json, *.hist and latency.svg.
    #[arg(long, value_name = "DIR", default_value = "latency-report")]
    out: PathBuf,
    /// Length of each baseline (ping-pongs, cyclictest), seconds; default: the run's
    /// duration, at most 20.
    #[arg(long, value_name = "S")]
    baseline_duration: Option<f64>,
    /// Only measure the stack.
    #[arg(long)]
    skip_baselines: bool,
    #[command(flatten)]
    stack: StackArgs,
}

#[derive(Args, Debug)]
struct EmulateArgs {
    /// UDP address to listen on for the bridge.
    #[arg(long, default_value = "127.0.0.1:7700")]
    listen: std::net::SocketAddr,
    /// Speak on this serial line (UART or pseudo-terminal, COBS framing) instead of UDP.
    #[arg(long, value_name = "PATH")]
    serial: Option<PathBuf>,
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// How the drive's clock waits for its deadlines (see `run --help`).
    #[arg(long, default_value = "hybrid:25")]
    wait: WaitStrategy,
    /// Periods without a valid command before outputs go off and a fault latches.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u16).range(1..))]
    watchdog_periods: u16,
    /// PLAN entries the drive keeps (announced in CONFIG): when a COMMAND is late it applies
    /// the plan's entry for that period instead of holding the last duty. 0: no plans.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u16).range(0..=256))]
    plan_capacity: u16,
    /// Stop after this many seconds (default: run until SIGINT/SIGTERM).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Fault injection: drop every N-th sample frame.
    #[arg(long, default_value_t = 0, value_name = "N")]
    drop_every: u64,
    /// Fault injection: corrupt one bit of every N-th sample frame.
    #[arg(long, default_value_t = 0, value_name = "N")]
    corrupt_every: u64,
    /// Fault injection: send every N-th sample frame after the next one.
    #[arg(long, default_value_t = 0, value_name = "N")]
    reorder_every: u64,
    /// Fault injection: hold every N-th sample frame for --delay-us before sending it.
    #[arg(long, default_value_t = 0, value_name = "N")]
    delay_every: u64,
    /// Fault injection: how long --delay-every holds a frame, µs (longer than a period: it
    /// arrives after newer frames and is dropped as out of order).
    #[arg(long, default_value_t = 0, value_name = "US")]
    delay_us: u64,
    /// Fault injection: send every N-th sample frame twice.
    #[arg(long, default_value_t = 0, value_name = "N")]
    duplicate_every: u64,
    /// Fault injection: stop sending samples after S seconds of running.
    #[arg(long, value_name = "S")]
    stop_after: Option<f64>,
    /// Fault injection: freeze the drive once, after S seconds of running, for
    /// --freeze-ms (no frames, its clock paused: what a host stall does to it).
    #[arg(long, value_name = "S")]
    freeze_at: Option<f64>,
    #[arg(long, default_value_t = 0, value_name = "MS")]
    freeze_ms: u64,
    /// Fault injection: latch an over-current fault after S seconds of running.
    #[arg(long, value_name = "S")]
    overcurrent_after: Option<f64>,
    #[command(flatten)]
    rt: RtArgs,
}

#[derive(Args, Debug)]
struct PingpongArgs {
    #[arg(long)]
    transport: stepdrive_monitor::pingpong::Transport,
    /// ping or pong.
    #[arg(long, value_parser = ["ping", "pong"])]
    role: String,
    #[arg(long)]
    endpoint: String,
    #[arg(long, default_value_t = 50.0)]
    period_us: f64,
    #[arg(long, default_value_t = 10.0)]
    duration: f64,
    #[arg(long, default_value = "sleep")]
    wait: WaitStrategy,
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    rt: RtArgs,
}

/// A run length or timeout: positive, finite, below 1e6 s.
fn seconds(v: f64) -> Result<Duration, String> {
    if v.is_finite() && v > 0.0 && v < 1e6 {
        Ok(Duration::from_secs_f64(v))
    } else {
        Err(format!(
            "must be a positive number of seconds below 1e6 (got {v})"
        ))
    }
}

fn parse_seconds(s: &str) -> Result<Duration, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("`{s}` is not a number of seconds"))?;
    seconds(v)
}

#[derive(Args, Debug, Clone)]
struct ScenarioOpt {
    /// Scenario TOML file (motor, load, drive, gains, rates, trajectory, metrics); absent
    /// fields take the paper's Section V defaults. `stepdrive scenario` prints them.
    #[arg(long, value_name = "FILE")]
    scenario: Option<PathBuf>,
}

impl ScenarioOpt {
    fn load(&self) -> Result<Scenario> {
        match &self.scenario {
            Some(path) => Ok(Scenario::from_toml_file(path)?),
            None => Ok(Scenario::default()),
        }
    }
}

#[derive(Args, Debug, Clone)]
struct Timeouts {
    /// Longest wait for the other processes to come up, seconds.
    #[arg(long, value_name = "S", default_value = "30", value_parser = parse_seconds)]
    startup_timeout_s: Duration,
    /// Longest wait for a peer's next message before declaring it dead, seconds.
    #[arg(long, value_name = "S", default_value = "5", value_parser = parse_seconds)]
    peer_timeout_s: Duration,
}

#[derive(Args, Debug, Clone)]
struct ProcessArgs {
    /// Instance namespace of the services; stacks with different instances never interact.
    #[arg(long, default_value = DEFAULT_INSTANCE)]
    instance: String,
    #[command(flatten)]
    scenario: ScenarioOpt,
    #[command(flatten)]
    timeouts: Timeouts,
    /// Timing mode: lockstep (virtual time) or realtime (wall clock). All processes of a
    /// stack must use the same.
    #[arg(long, default_value = "lockstep")]
    mode: Mode,
    /// Realtime: how this process waits: sleep (clock_nanosleep), spin, hybrid[:µs] (sleep
    /// to that margin before the deadline, then spin), or event (current loop, hardware
    /// mode: sleep until the bridge raises state-ready). Defaults: current loop spin
    /// (hardware: event); bridge hybrid:30 with --priority, else sleep; others sleep.
    #[arg(long)]
    wait: Option<WaitStrategy>,
    #[command(flatten)]
    rt: RtArgs,
}

/// Real-time settings of one process, as cyclictest's -p, -a, -m.
#[derive(Args, Debug, Clone)]
struct RtArgs {
    /// SCHED_FIFO priority (1-99); without it the process stays SCHED_OTHER.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=99))]
    priority: Option<u8>,
    /// Pin to this CPU.
    #[arg(long)]
    cpu: Option<usize>,
    /// mlockall and prefault the stack.
    #[arg(long)]
    mlock: bool,
    /// Timer slack in ns (kernel default 50000, a whole 20 kHz period).
    #[arg(long, value_name = "NS")]
    timer_slack_ns: Option<u64>,
    /// Fail if the system refuses a real-time setting instead of warning and going on.
    #[arg(long)]
    require_rt: bool,
}

impl RtArgs {
    fn options(&self) -> RtOptions {
        RtOptions {
            priority: self.priority,
            cpu: self.cpu,
            lock_memory: self.mlock,
            timer_slack_ns: self.timer_slack_ns,
            require: self.require_rt,
        }
    }
}

impl ProcessArgs {
    fn loop_options(&self) -> Result<LoopOptions> {
        Ok(LoopOptions {
            instance: self.instance.clone(),
            scenario: self.scenario.load()?,
            startup_timeout: self.timeouts.startup_timeout_s,
            peer_timeout: self.timeouts.peer_timeout_s,
        })
    }
}

#[derive(Args, Debug)]
struct PlantArgs {
    #[command(flatten)]
    common: ProcessArgs,
    /// Realtime watchdog: after this many periods in a row without a command the outputs
    /// go off (zero volts) and a fault is latched (200 = 10 ms at 20 kHz).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..))]
    watchdog_periods: u32,
    /// sim: the motor model. udp / serial: a bridge to a drive speaking
    /// docs/drive-protocol.md at --drive ADDR:PORT / on --port PATH (hardware mode).
    #[arg(long, default_value = "sim", value_parser = ["sim", "udp", "serial"])]
    backend: String,
    /// The drive's UDP address (backend udp).
    #[arg(long, value_name = "ADDR:PORT")]
    drive: Option<std::net::SocketAddr>,
    /// The drive's serial line, e.g. /dev/ttyACM0 (backend serial; COBS framing).
    #[arg(long, value_name = "PATH")]
    port: Option<PathBuf>,
    /// Bridge: periods without a valid sample before it publishes a fault and stops
    /// forwarding commands.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..))]
    silence_periods: u32,
    /// Bridge: send the current loop's voltage plan to the drive (if its CONFIG says it keeps
    /// one) whenever it is this many samples newer than the last sent. A full PLAN is ~830
    /// bytes: every period at 20 kHz would be 17 MB/s.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..))]
    plan_every: u32,
    /// Bridge: encoder reading (counts) at θ = 0, for an absolute encoder; by default the
    /// first sample is θ = 0.
    #[arg(long, value_name = "COUNTS", allow_negative_numbers = true)]
    encoder_offset: Option<i64>,
    /// Bridge: counts increase for negative θ, whatever the drive's CONFIG says (an encoder
    /// or motor wired the other way round).
    #[arg(long)]
    reverse_encoder: bool,
    /// Bridge: bandwidth of the encoder velocity observer, Hz.
    #[arg(long, default_value_t = 400.0)]
    observer_hz: f64,
    /// drive/state subscribers to wait for before the first sample: 2 = current and
    /// position loops; 3 adds a monitor.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    wait_subscribers: u32,
}

#[derive(Args, Debug)]
struct CurrentLoopArgs {
    #[command(flatten)]
    common: ProcessArgs,
    /// Control method: proposed (17)+(22), lyapunov (39), open_loop (2).
    #[arg(long, default_value = "proposed")]
    method: Method,
}

#[derive(Args, Debug)]
struct RunArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// Methods to run, in order (comma-separated or repeated): proposed, lyapunov, open_loop.
    #[arg(long = "method", value_delimiter = ',', default_values = ["proposed", "lyapunov"])]
    methods: Vec<Method>,
    /// Also write the results as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// lockstep: virtual time, bit-identical, as fast as possible. realtime: wall clock,
    /// 20 kHz on absolute deadlines, late commands are held and counted. hardware: the
    /// plant is a bridge to a drive (--drive, or an emulated one started for the run).
    #[arg(long, default_value = "lockstep")]
    mode: Mode,
    #[command(flatten)]
    stack: StackArgs,
}

/// Options of a launched stack.
#[derive(Args, Debug)]
struct StackArgs {
    /// Instance namespace of the services.
    #[arg(long, default_value = DEFAULT_INSTANCE)]
    instance: String,
    #[command(flatten)]
    timeouts: Timeouts,
    /// Run length in seconds; past one pass of the trajectory the move repeats back and forth.
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Realtime: SCHED_FIFO priority of plant and current loop (position loop: one more);
    /// 0 keeps everything SCHED_OTHER.
    #[arg(long, default_value_t = 80, value_parser = clap::value_parser!(u8).range(0..=99))]
    priority: u8,
    /// Realtime: SCHED_FIFO priority of the current loop alone (default: --priority);
    /// 0 runs it SCHED_OTHER, which RT throttling does not touch.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=99))]
    current_priority: Option<u8>,
    /// Realtime: CPUs as PLANT,CURRENT: the plant and position loop (hardware: the drive and
    /// the bridge) are pinned to the first, the current loop to the second. `none` disables
    /// pinning.
    #[arg(long, default_value = "0,1")]
    cpus: String,
    /// Realtime: do not mlockall.
    #[arg(long)]
    no_mlock: bool,
    /// Realtime: timer slack of every loop, ns.
    #[arg(long, default_value_t = 1000, value_name = "NS")]
    timer_slack_ns: u64,
    /// Fail if the system refuses a real-time setting.
    #[arg(long)]
    require_rt: bool,
    /// Realtime: wait strategy of the plant. hybrid:25 sleeps to 25 µs before each deadline
    /// and spins the rest, so samples leave on time although a timer wake-up here takes
    /// ~25 µs (measured: wake-up p50 31 µs with sleep, 3-5 µs with hybrid:25).
    #[arg(long, default_value = "hybrid:25")]
    plant_wait: WaitStrategy,
    /// Realtime: wait strategy of the current loop. Default: hybrid:40 (sleep to 40 µs
    /// before the next sample's deadline, then poll; a pure spin would hold a whole CPU);
    /// in hardware mode `event` (sleep until the bridge raises state-ready).
    #[arg(long)]
    current_wait: Option<WaitStrategy>,
    /// Realtime: wait strategy of the position loop.
    #[arg(long, default_value = "sleep")]
    position_wait: WaitStrategy,
    /// Realtime: `off` sets sched_rt_runtime_us to -1 for the run and restores it after
    /// (root). With throttling on, SCHED_FIFO tasks lose their CPU up to 50 ms a second
    /// whenever ordinary tasks want it; see the README's latency section.
    #[arg(long, default_value = "on", value_parser = ["on", "off"])]
    rt_throttling: String,
    /// Hardware mode: the drive's UDP address; without it (or --drive-port) an emulated
    /// drive is started on loopback.
    #[arg(long, value_name = "ADDR:PORT")]
    drive: Option<std::net::SocketAddr>,
    /// Hardware mode: the drive's serial line (an MCU board, COBS framing), e.g.
    /// /dev/ttyACM0, instead of UDP.
    #[arg(long, value_name = "PATH", conflicts_with = "drive")]
    drive_port: Option<PathBuf>,
    /// Realtime: plant watchdog periods (see `stepdrive plant --help`).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..))]
    watchdog_periods: u32,
}

impl StackArgs {
    /// Applies `--rt-throttling` for the life of the returned guard.
    fn throttling_guard(&self, mode: Mode) -> Result<Option<RtThrottlingOff>> {
        if mode == Mode::Lockstep {
            return Ok(None);
        }
        if self.rt_throttling == "off" {
            match RtThrottlingOff::engage() {
                Ok(g) => return Ok(g),
                Err(e) if self.require_rt => return Err(e.into()),
                Err(e) => tracing::warn!("{e}; continuing with RT throttling on"),
            }
        }
        warn_rt_throttling();
        Ok(None)
    }

    fn apply_duration(&self, s: &mut Scenario) -> Result<()> {
        if let Some(d) = self.duration {
            s.run.duration_s = Some(d);
            s.validate().context("--duration")?;
        }
        Ok(())
    }

    fn launch_options(&self, mode: Mode) -> Result<LaunchOptions> {
        let cpus: Option<(usize, usize)> = if self.cpus == "none" {
            None
        } else {
            let parts: Vec<&str> = self.cpus.split(',').collect();
            match parts.as_slice() {
                [a, b] => Some((
                    a.trim().parse().context("--cpus: first CPU")?,
                    b.trim().parse().context("--cpus: second CPU")?,
                )),
                _ => anyhow::bail!("--cpus must be PLANT,CURRENT (e.g. 0,1) or none"),
            }
        };
        let rt = |prio: u8, cpu: Option<usize>| RtOptions {
            priority: (prio > 0).then_some(prio),
            cpu,
            lock_memory: !self.no_mlock,
            timer_slack_ns: Some(self.timer_slack_ns),
            require: self.require_rt,
        };
        Ok(LaunchOptions {
            instance: self.instance.clone(),
            startup_timeout: self.timeouts.startup_timeout_s,
            peer_timeout: self.timeouts.peer_timeout_s,
            mode,
            plant: RoleRt {
                wait: self.plant_wait,
                rt: rt(self.priority, cpus.map(|c| c.0)),
            },
            current: RoleRt {
                wait: self.current_wait.unwrap_or(match mode {
                    Mode::Hardware => WaitStrategy::Event,
                    _ => WaitStrategy::Hybrid { margin_ns: 40_000 },
                }),
                rt: rt(
                    self.current_priority.unwrap_or(self.priority),
                    cpus.map(|c| c.1),
                ),
            },
            position: RoleRt {
                wait: self.position_wait,
                // One above the plant: the plant busy-waits the last part of each period, so
                // below it the 2 kHz loop would wait for those gaps (measured: wake-up p50
                // 112 µs, p99 3.7 ms). Its ~5 µs of work delays the plant at most that much.
                rt: rt(
                    if self.priority > 0 {
                        self.priority.saturating_add(1).min(99)
                    } else {
                        0
                    },
                    cpus.map(|c| c.0),
                ),
            },
            watchdog_periods: self.watchdog_periods,
            drive: match (&self.drive, &self.drive_port) {
                (Some(addr), _) => Some(DriveAddr::Udp(*addr)),
                (None, Some(path)) => Some(DriveAddr::Serial(path.clone())),
                (None, None) => None,
            },
        })
    }
}

#[derive(Args, Debug)]
struct SimulateArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// Methods to run, in order (comma-separated or repeated).
    #[arg(long = "method", value_delimiter = ',', default_values = ["proposed", "lyapunov"])]
    methods: Vec<Method>,
    /// Also write the results as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Stall the current loop for PERIODS samples from AT seconds on (repeatable), with
    /// the realtime plant's rules: each missing command is a miss, covered by the freshest
    /// voltage plan (`drive.command_plan_periods`; 0 in the scenario holds the voltage
    /// instead). Shows what a host stall of that length costs, without a clock.
    #[arg(long = "stall", value_name = "AT:PERIODS", value_parser = parse_stall)]
    stalls: Vec<(f64, u64)>,
    /// With --stall: misses in a row before the plant's outputs go off.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..))]
    watchdog_periods: u32,
}

/// `AT:PERIODS`, e.g. `1.2:33`.
fn parse_stall(s: &str) -> Result<(f64, u64), String> {
    let (at, periods) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}` is not AT:PERIODS (seconds:samples, e.g. 1.2:33)"))?;
    let at: f64 = at
        .parse()
        .ok()
        .filter(|t: &f64| t.is_finite() && *t >= 0.0)
        .ok_or_else(|| format!("stall start `{at}` must be seconds ≥ 0"))?;
    let periods: u64 = periods
        .parse()
        .ok()
        .filter(|&p| p > 0)
        .ok_or_else(|| format!("stall length `{periods}` must be a number of samples ≥ 1"))?;
    Ok((at, periods))
}

#[derive(Args, Debug)]
struct ScenarioArgs {
    /// Validate this scenario file instead of printing the defaults.
    #[arg(long, value_name = "FILE")]
    check: Option<PathBuf>,
}

fn init_logging() {
    use tracing_subscriber::EnvFilter;
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Warn);
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let ansi = unsafe { libc::isatty(libc::STDERR_FILENO) } == 1;
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(ansi)
        .with_target(false)
        .init();
}

fn write_outputs(s: &Scenario, runs: &[RunReport], json: Option<&PathBuf>) -> Result<()> {
    println!("scenario: {}", s.name);
    print!("{}", table(s, runs));
    if let Some(path) = json {
        let text = serde_json::to_string_pretty(&document(s, runs))?;
        std::fs::write(path, text + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
        println!("results written to {}", path.display());
    }
    Ok(())
}

fn real_main(cli: Cli) -> Result<()> {
    match cli.command {
        Cmd::Run(a) => {
            let mut s = a.scenario.load()?;
            a.stack.apply_duration(&mut s)?;
            let opts = a.stack.launch_options(a.mode)?;
            let _throttling = a.stack.throttling_guard(a.mode)?;
            let mut runs = Vec::new();
            for method in &a.methods {
                tracing::info!(
                    "{method}: launching plant, position loop and current loop ({}, {:.1} s)",
                    a.mode.as_str(),
                    s.duration_s()
                );
                let report = run_stack(&s, *method, &opts)
                    .with_context(|| format!("the {method} run failed"))?;
                runs.push(report);
            }
            write_outputs(&s, &runs, a.json.as_ref())
        }
        Cmd::Simulate(a) => {
            let s = a.scenario.load()?;
            if a.stalls.is_empty() {
                let runs: Vec<RunReport> = a.methods.iter().map(|m| simulate(&s, *m)).collect();
                return write_outputs(&s, &runs, a.json.as_ref());
            }
            let duration = s.duration_s();
            let mut stalls = Vec::with_capacity(a.stalls.len());
            for &(at, periods) in &a.stalls {
                if at >= duration {
                    anyhow::bail!("--stall {at}:{periods} starts after the run ({duration} s)");
                }
                let start = (at * s.rates.current_loop_hz).round() as u64;
                stalls.push(start..start + periods);
            }
            let mut runs = Vec::with_capacity(a.methods.len());
            for m in &a.methods {
                let (report, slot) = simulate_stalls(&s, *m, &stalls, a.watchdog_periods);
                println!(
                    "{m}: {} periods without their command, {} of them covered by a plan, longest run {}",
                    slot.misses, slot.planned, slot.runs.longest
                );
                runs.push(report);
            }
            write_outputs(&s, &runs, a.json.as_ref())
        }
        Cmd::Plant(a) => {
            let lo = a.common.loop_options()?;
            let opts = PlantOptions {
                instance: lo.instance,
                scenario: lo.scenario,
                wait_subscribers: a.wait_subscribers as usize,
                startup_timeout: lo.startup_timeout,
                peer_timeout: lo.peer_timeout,
            };
            if a.backend != "sim" {
                let drive = if a.backend == "udp" {
                    DriveAddr::Udp(a.drive.context("--backend udp needs --drive ADDR:PORT")?)
                } else {
                    DriveAddr::Serial(
                        a.port
                            .clone()
                            .context("--backend serial needs --port PATH")?,
                    )
                };
                if !(a.observer_hz.is_finite() && a.observer_hz > 0.0) {
                    anyhow::bail!("--observer-hz must be a positive number");
                }
                if a.common.wait == Some(WaitStrategy::Event) {
                    anyhow::bail!(
                        "--wait event is for the current loop; the bridge waits for the drive's \
                         frames with sleep, spin or hybrid:<µs>"
                    );
                }
                let b = BridgeOptions {
                    drive,
                    rt: a.common.rt.options(),
                    wait: a
                        .common
                        .wait
                        .unwrap_or(bridge_default_wait(a.common.rt.priority.is_some())),
                    plan_every: a.plan_every,
                    silence_periods: a.silence_periods,
                    observer_hz: a.observer_hz,
                    calibration: EncoderCalibration {
                        offset_counts: a.encoder_offset,
                        reverse: a.reverse_encoder,
                    },
                };
                run_bridge(&opts, &b)?;
                return Ok(());
            }
            match a.common.mode {
                Mode::Lockstep => {
                    stepdrive_plant::process::run_lockstep(&opts)?;
                }
                Mode::Hardware => {
                    anyhow::bail!("the plant in hardware mode is a bridge: add --backend udp --drive ADDR:PORT");
                }
                Mode::Realtime => {
                    let rto = RealtimeOptions {
                        wait: a.common.wait.unwrap_or(WaitStrategy::Sleep),
                        watchdog_periods: a.watchdog_periods,
                        rt: a.common.rt.options(),
                    };
                    stepdrive_plant::process::run_realtime(&opts, &rto)?;
                }
            }
            Ok(())
        }
        Cmd::CurrentLoop(a) => {
            let lo = a.common.loop_options()?;
            match a.common.mode {
                Mode::Lockstep => {
                    run_current_loop(&lo, a.method)?;
                }
                mode @ (Mode::Realtime | Mode::Hardware) => {
                    let wait = a.common.wait.unwrap_or(match mode {
                        Mode::Hardware => WaitStrategy::Event,
                        _ => WaitStrategy::Spin,
                    });
                    if wait == WaitStrategy::Event && mode != Mode::Hardware {
                        anyhow::bail!(
                            "--wait event needs a plant that raises state-ready: only the \
                             bridge does (--mode hardware)"
                        );
                    }
                    let rto = RealtimeLoopOptions {
                        wait,
                        rt: a.common.rt.options(),
                    };
                    run_current_loop_realtime(&lo, a.method, &rto)?;
                }
            }
            Ok(())
        }
        Cmd::PositionLoop(a) => {
            let lo = a.loop_options()?;
            match a.mode {
                Mode::Lockstep => {
                    run_position_loop(&lo)?;
                }
                Mode::Realtime | Mode::Hardware => {
                    let rto = RealtimeLoopOptions {
                        wait: a.wait.unwrap_or(WaitStrategy::Sleep),
                        rt: a.rt.options(),
                    };
                    run_position_loop_realtime(&lo, &rto)?;
                }
            }
            Ok(())
        }
        Cmd::Latency(a) => {
            let mut s = a.scenario.load()?;
            if a.stack.duration.is_none() {
                s.run.duration_s = Some(60.0);
            }
            a.stack.apply_duration(&mut s)?;
            let launch = a.stack.launch_options(Mode::Realtime)?;
            let _throttling = a.stack.throttling_guard(Mode::Realtime)?;
            let baseline = a.baseline_duration.unwrap_or(s.duration_s().min(20.0));
            let baseline_duration = seconds(baseline)
                .map_err(anyhow::Error::msg)
                .context("--baseline-duration")?;
            let opts = LatencyOptions {
                out: a.out.clone(),
                baseline_duration,
                launch,
                skip_baselines: a.skip_baselines,
            };
            let report = run_latency(&s, &opts)?;
            write_outputs(&s, std::slice::from_ref(&report.run), None)?;
            println!();
            print!("{}", latency_table(&report));
            println!(
                "written: {}/latency.json, latency.svg, *.hist",
                a.out.display()
            );
            Ok(())
        }
        Cmd::EmulateDrive(a) => {
            let scenario = a.scenario.load()?;
            let duration = match a.duration {
                Some(d) => Some(seconds(d).map_err(anyhow::Error::msg)?),
                None => None,
            };
            run_emulator(&EmulatorOptions {
                listen: a.listen,
                serial: a.serial,
                scenario,
                wait: a.wait,
                rt: a.rt.options(),
                watchdog_periods: a.watchdog_periods,
                plan_capacity: a.plan_capacity,
                inject: FaultInjection {
                    drop_every: a.drop_every,
                    corrupt_every: a.corrupt_every,
                    reorder_every: a.reorder_every,
                    delay_every: a.delay_every,
                    delay_ns: a.delay_us.saturating_mul(1000),
                    duplicate_every: a.duplicate_every,
                    stop_after_s: a.stop_after,
                    overcurrent_after_s: a.overcurrent_after,
                    freeze_at_s: a.freeze_at,
                    freeze_ns: a.freeze_ms.saturating_mul(1_000_000),
                },
                duration,
            })
            .context("emulated drive")?;
            Ok(())
        }
        Cmd::Pingpong(a) => {
            if !(a.period_us.is_finite() && a.period_us >= 1.0) {
                anyhow::bail!("--period-us must be ≥ 1");
            }
            let duration = seconds(a.duration).map_err(anyhow::Error::msg)?;
            stepdrive_monitor::pingpong::run(&PingPongOptions {
                transport: a.transport,
                endpoint: a.endpoint,
                ping: a.role == "ping",
                period_ns: (a.period_us * 1000.0).round() as u64,
                duration,
                wait: a.wait,
                rt: a.rt.options(),
                out: a.out,
            })
        }
        Cmd::Scenario(a) => {
            match a.check {
                Some(path) => {
                    let s = Scenario::from_toml_file(&path)?;
                    println!(
                        "{}: valid ({} s, {} samples, {} Hz / {} Hz)",
                        path.display(),
                        s.duration_s(),
                        s.sample_count(),
                        s.rates.current_loop_hz,
                        s.rates.position_loop_hz
                    );
                }
                None => print!("{}", Scenario::default().to_toml_string()?),
            }
            Ok(())
        }
    }
}

/// RT throttling takes a spinning SCHED_FIFO task off its CPU for up to 50 ms a second
/// when ordinary tasks want that CPU; say so once.
fn warn_rt_throttling() {
    match rt_runtime_us() {
        Some(-1) => {}
        Some(us) => tracing::info!(
            "RT throttling is on (sched_rt_runtime_us = {us}): SCHED_FIFO tasks may lose their CPU \
             for {} ms a second when ordinary tasks need it (--rt-throttling off disables it for \
             the run; see the README)",
            (1_000_000 - us) / 1000
        ),
        None => {}
    }
}

fn interrupted(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.is::<Interrupted>()
            || matches!(c.downcast_ref::<PlantError>(), Some(PlantError::Terminated))
            || matches!(
                c.downcast_ref::<ControllerError>(),
                Some(ControllerError::Terminated)
            )
    })
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logging();
    install_termination_handler();
    match real_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line, prefixed, so a launcher can pick it out of our stderr.
            eprintln!("error: {e:#}");
            if interrupted(&e) {
                ExitCode::from(130)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}
