//! The sub-commands that are not a process of the stack: launching and simulating runs,
//! measuring latency, printing and checking configuration.

use crate::options::{
    check_drive_count, parse_seconds, seconds, LiveArgs, ScenarioOpt, StackArgs, Throttling,
};
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::time::Duration;
use stepdrive_monitor::latency::session::{run_latency, table as latency_table, LatencyOptions};
use stepdrive_monitor::record::recording::{Chunks, Recording};
use stepdrive_monitor::report::metrics::RunReport;
use stepdrive_monitor::report::outcome::Outcome;
use stepdrive_monitor::report::table::{document, headlines, overall, table};
use stepdrive_monitor::studies::simulate::{simulate as simulate_run, simulate_stalls};
use stepdrive_monitor::supervise::attach::{attach_reader, watch, ResetResult};
use stepdrive_monitor::supervise::helpers::{Helper, Helpers};
use stepdrive_monitor::supervise::launcher::{run_stack, LaunchOptions};
use stepdrive_monitor::supervise::throttling::ThrottlingLifted;
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::rt::rt_runtime_us;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::DEFAULT_INSTANCE;
use stepdrive_shared::stack::Role;
use stepdrive_shared::{Method, Scenario};

/// What a run or simulation computes and where its results go.
#[derive(Args, Debug)]
pub struct Selection {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// Methods to run, in order (comma-separated or repeated): proposed, lyapunov, open_loop,
    /// pi (the industrial baseline: constant-amplitude microstepping currents, PI per phase).
    #[arg(long = "method", value_enum, value_delimiter = ',', default_values = ["proposed", "lyapunov"])]
    methods: Vec<Method>,
    /// Also write the results as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct RunArgs {
    #[command(flatten)]
    select: Selection,
    /// lockstep: virtual time, bit-identical, as fast as possible. realtime: wall clock,
    /// 20 kHz on absolute deadlines, late commands are held and counted. hardware: the
    /// plant is a bridge to a drive (--drive, or an emulated one started for the run).
    #[arg(long, value_enum, default_value_t = Mode::Lockstep)]
    mode: Mode,
    /// Record every state sample, each loop's statistics and the faults to FILE (MCAP, JSON
    /// messages with schemas: opens in Foxglove, Lichtblick and PlotJuggler). The file is
    /// finished on every exit the run controls, Ctrl-C and a dead child included.
    #[arg(long, value_name = "FILE")]
    record: Option<PathBuf>,
    /// Write the recording's chunks uncompressed (default: zstd, ~4× smaller), for tools
    /// that read MCAP without its compression.
    #[arg(long)]
    uncompressed: bool,
    /// Draw the paper's figures of the run into DIR (SVG and PNG). Without --record the
    /// recording they are drawn from is kept as DIR/run.mcap.
    #[arg(long, value_name = "DIR")]
    plots: Option<PathBuf>,
    #[command(flatten)]
    live: LiveArgs,
    #[command(flatten)]
    stack: StackArgs,
}

#[derive(Args, Debug)]
pub struct ServeArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// realtime: the simulated motor on the wall clock. hardware: the plant is a bridge to a
    /// drive (--drive, or an emulated one started for it). A served stack runs on the wall
    /// clock: commands come when they come.
    #[arg(long, value_enum, default_value_t = ServeMode::Realtime)]
    mode: ServeMode,
    #[command(flatten)]
    live: LiveArgs,
    /// Start a `stepdrive gateway` listening on this Zenoh endpoint (e.g.
    /// tcp/0.0.0.0:7447), so clients on other hosts command the axis
    /// (`stepdrive axis --connect tcp/HOST:7447 ...`).
    #[arg(long, value_name = "tcp/HOST:PORT")]
    gateway: Option<String>,
    #[command(flatten)]
    stack: StackArgs,
}

#[derive(Args, Debug)]
pub struct GatewayArgs {
    /// The served stack's instance name.
    #[arg(long, default_value = stepdrive_shared::services::DEFAULT_INSTANCE, value_parser = stepdrive_shared::services::instance_name)]
    instance: String,
    /// Listen for clients on this Zenoh endpoint (default tcp/0.0.0.0:7447).
    #[arg(long, value_name = "tcp/HOST:PORT", conflicts_with = "connect")]
    listen: Option<String>,
    /// Connect to this Zenoh endpoint instead (a router, or a peer that listens).
    #[arg(long, value_name = "tcp/HOST:PORT")]
    connect: Option<String>,
    /// Status messages per second on Zenoh.
    #[arg(long, value_name = "HZ", default_value_t = 100.0, value_parser = positive_rate)]
    status_rate: f64,
    /// Commands per second one remote client may send; more are refused (too many)
    /// without reaching the axis.
    #[arg(long, value_name = "HZ", default_value_t = 500.0, value_parser = positive_rate)]
    max_command_rate: f64,
    /// How long to wait for the stack to come up, s.
    #[arg(long, value_name = "S", default_value = "30", value_parser = crate::options::parse_seconds)]
    wait: Duration,
    /// SCHED_FIFO priority of the gateway and Zenoh's threads, 0 for ordinary: below the
    /// stack's loops, above everything at ordinary priority (on two cores the loops leave
    /// an ordinary process waiting: docs/remote.md has the round trips either way).
    #[arg(long, value_name = "P", default_value_t = stepdrive_client::STREAM_PRIORITY,
          value_parser = clap::value_parser!(u8).range(0..=99))]
    priority: u8,
    /// CPUs the gateway and Zenoh's threads run on, e.g. 0 or 0,2-3; `any` leaves them to
    /// the scheduler. Default: the CPUs the stack's loops leave by the default deployment
    /// (on two cores the plant's, never the current loop's: there the gateway's threads and
    /// the network traffic they handle took the current loop's CPU from it two to four times
    /// as often; docs/remote.md).
    #[arg(long, value_name = "LIST|any")]
    cpus: Option<crate::options::CpuList>,
}

/// A rate in Hz: finite, positive, at most 10 kHz.
fn positive_rate(s: &str) -> Result<f64, String> {
    crate::options::number_within(s, 0.0, 10_000.0, true, "Hz")
}

/// The modes a stack can be served in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ServeMode {
    Realtime,
    Hardware,
}

#[derive(Args, Debug)]
pub struct SimulateArgs {
    #[command(flatten)]
    select: Selection,
    /// Stall the current loop for PERIODS samples from AT seconds on (repeatable), with
    /// the realtime plant's rules: each missing command is a miss, covered by the freshest
    /// voltage plan (`drive.command_plan_periods`; 0 in the scenario holds the voltage
    /// instead). Shows what a host stall of that length costs, without a clock.
    #[arg(long = "stall", value_name = "AT:PERIODS", value_parser = parse_stall)]
    stalls: Vec<(f64, u64)>,
    /// With --stall: misses in a row before the plant's outputs go off.
    #[arg(long, default_value_t = Deployment::default().watchdog_periods, value_parser = clap::value_parser!(u32).range(1..))]
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
pub struct LatencyArgs {
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
pub struct ResetArgs {
    /// The stack's instance name.
    #[arg(long, default_value = DEFAULT_INSTANCE, value_parser = stepdrive_shared::services::instance_name)]
    instance: String,
    /// How long to wait for the faults to clear, seconds.
    #[arg(long, value_name = "S", default_value = "2", value_parser = parse_seconds)]
    wait_s: std::time::Duration,
}

#[derive(Args, Debug)]
pub struct MonitorArgs {
    /// The stack's instance name.
    #[arg(long, default_value = DEFAULT_INSTANCE, value_parser = stepdrive_shared::services::instance_name)]
    instance: String,
    /// The stack's scenario (default: the one the stack announces; given, it must be the
    /// stack's, and the fields that differ are named).
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// The method the stack's current loop runs (a label for the report).
    #[arg(long, value_enum, default_value_t = Method::Proposed)]
    method: Method,
    /// Also write the results as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Silence of the plant after which the run is declared stuck, seconds.
    #[arg(long, value_name = "S", default_value = "5", value_parser = parse_seconds)]
    peer_timeout_s: std::time::Duration,
    /// Read at SCHED_FIFO priority P (1-99; root), 0 for ordinary priority. By default 1
    /// beside a realtime or hardware stack whose loops run at SCHED_FIFO (as `run`'s own
    /// monitor; warned and ordinary where the system refuses it), ordinary beside one whose
    /// loops run at ordinary priority and beside a lockstep one. Beside loops that
    /// spin at SCHED_FIFO a reader at ordinary priority gets too little CPU to keep up (its
    /// misses end the report UNOBSERVED), and the kernel's fair server runs it ahead of
    /// them. Below the loops' priorities, so it never delays them.
    #[arg(long, value_name = "P", value_parser = clap::value_parser!(u8).range(0..=99))]
    priority: Option<u8>,
    /// The axis of a multi-axis stack to read (its index, 0 first): its states, setpoints
    /// and status, judged and recorded as a one-axis run.
    #[arg(long, value_name = "N", default_value_t = 0)]
    axis: u32,
}

/// An attached reader's SCHED_FIFO priority beside a realtime stack: the deployment's own
/// monitor's.
const READER_PRIORITY: u8 = 1;

impl MonitorArgs {
    /// The reader's scheduling beside a stack in `mode`: a priority asked for and refused
    /// fails loudly (a reader asked to keep up that cannot is no reader); the default is
    /// only warned about.
    fn apply_priority(&self, mode: Mode) -> Result<()> {
        let (p, require) = match (self.priority, mode) {
            (Some(0), _) | (None, Mode::Lockstep) => return Ok(()),
            (Some(p), _) => (p, true),
            (None, Mode::Realtime | Mode::Hardware) => {
                // Above loops at ordinary priority (a stack started with `--priority 0`),
                // a FIFO reader would take their CPU: it runs as they do.
                if !loops_run_realtime(&self.instance) {
                    tracing::info!(
                        "the stack's loops run at ordinary priority: so does this reader"
                    );
                    return Ok(());
                }
                (READER_PRIORITY, false)
            }
        };
        stepdrive_runtime::rt::RtOptions {
            priority: Some(p),
            cpu: None,
            // Off the current loop's CPU, as `run`'s own monitor (the default deployment's).
            helper_cpus: Deployment::default().helper_cpus(),
            lock_memory: false,
            timer_slack_ns: None,
            nice: None,
            require,
        }
        .apply()
        .map_err(|e| anyhow::anyhow!("--priority {p}: {}", e.describe()))?;
        Ok(())
    }
}

/// Whether a loop of the stack on `instance` runs at a real-time policy (SCHED_FIFO/RR).
fn loops_run_realtime(instance: &str) -> bool {
    let loops = [
        Role::Plant.id(),
        Role::Bridge.id(),
        Role::CurrentLoop.id(),
        Role::PositionLoop.id(),
    ];
    stepdrive_runtime::ipc::live_nodes_with_pids(instance, &loops)
        .iter()
        .any(|&(_, pid)| {
            // SAFETY: sched_getscheduler only reads the policy of a process (-1 if gone).
            let policy = unsafe { libc::sched_getscheduler(pid) };
            policy == libc::SCHED_FIFO || policy == libc::SCHED_RR
        })
}

#[derive(Args, Debug)]
pub struct CheckArgs {
    /// Validate this file instead of printing the defaults.
    #[arg(long, value_name = "FILE")]
    check: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct DeployArgs {
    #[command(flatten)]
    check: CheckArgs,
    /// The mode whose wait strategies the printed defaults spell out (the current loop's
    /// differs in hardware mode), and that `--check` checks the file for.
    #[arg(long, value_enum, default_value_t = Mode::Realtime)]
    mode: Mode,
}

/// The JSON results file, opened before anything runs so that a path that cannot be
/// written fails at once, not after the run.
/// The results file: written whole at the end or not at all. It is written to a hidden
/// temporary beside it (created at the start, so that an unwritable path fails before the
/// run) and renamed over it; a results file of an earlier run is removed at the start, so a
/// launcher killed mid-run leaves no file, rather than an empty or a stale one.
pub struct JsonOut {
    path: PathBuf,
    temp: PathBuf,
    file: std::fs::File,
}

impl JsonOut {
    pub fn create(path: Option<&PathBuf>) -> Result<Option<Self>> {
        let Some(path) = path else {
            return Ok(None);
        };
        let name = path
            .file_name()
            .with_context(|| format!("the results file {} names no file", path.display()))?
            .to_string_lossy()
            .into_owned();
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
        let dir = dir.unwrap_or(std::path::Path::new("."));
        remove_stale_temps(dir, &name);
        let temp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
        let file = std::fs::File::create(&temp)
            .with_context(|| format!("cannot write the results file {}", path.display()))?;
        match std::fs::remove_file(path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                let _ = std::fs::remove_file(&temp);
                return Err(e).with_context(|| {
                    format!("cannot replace the results file {}", path.display())
                });
            }
        }
        Ok(Some(Self {
            path: path.clone(),
            temp,
            file,
        }))
    }

    /// Writes `text` and puts the file in its place.
    fn commit(mut self, text: &str) -> Result<()> {
        use std::io::Write;
        self.file
            .write_all(text.as_bytes())
            .and_then(|()| self.file.sync_all())
            .with_context(|| format!("cannot write {}", self.path.display()))?;
        std::fs::rename(&self.temp, &self.path)
            .with_context(|| format!("cannot write {}", self.path.display()))
    }
}

impl Drop for JsonOut {
    fn drop(&mut self) {
        // Renamed already, or the run ended before its results: nothing stays behind.
        let _ = std::fs::remove_file(&self.temp);
    }
}

/// Whether a file can be written at `path` (its directory takes a new file), without
/// leaving one: for outputs written only after a long run.
fn writable(path: &std::path::Path) -> std::io::Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
    let dir = dir.unwrap_or(std::path::Path::new("."));
    let probe = dir.join(format!(".stepdrive-probe.{}", std::process::id()));
    std::fs::File::create(&probe)?;
    std::fs::remove_file(&probe)
}

/// Temporaries of `name` left by launchers that were killed (their pid is gone).
fn remove_stale_temps(dir: &std::path::Path, name: &str) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let prefix = format!(".{name}.");
    for entry in entries.flatten() {
        let file = entry.file_name();
        let Some(pid) = file
            .to_str()
            .and_then(|f| f.strip_prefix(&prefix))
            .and_then(|rest| rest.strip_suffix(".tmp"))
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if !std::path::Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Prints the table of `runs` and writes the JSON, complete or not, then says how the runs
/// ended: a headline per run that did not go well, and an error carrying the exit code of
/// the most severe.
fn conclude(s: &Scenario, runs: &[RunReport], json: Option<JsonOut>) -> Result<()> {
    println!("scenario: {}", s.name);
    print!("{}", table(s, runs));
    if let Some(out) = json {
        let text = serde_json::to_string_pretty(&document(s, runs))?;
        let path = out.path.clone();
        out.commit(&(text + "\n"))?;
        println!("results written to {}", path.display());
    }
    let headlines: Vec<String> = runs.iter().flat_map(|r| headlines(s, r)).collect();
    for h in &headlines {
        println!("\n{h}");
    }
    let outcome = overall(runs);
    if outcome == Outcome::Ok {
        return Ok(());
    }
    Err(Exit {
        code: outcome.exit_code(),
        headline: headlines.join("\n"),
    }
    .into())
}

pub use stepdrive_monitor::report::outcome::Exit;

/// Lifts RT throttling for the life of the returned guard (`--rt-throttling off`, the
/// default), when the run has real-time priorities to protect.
fn throttling_guard(a: &StackArgs, d: &Deployment, mode: Mode) -> Result<Option<ThrottlingLifted>> {
    lift_throttling(a.rt_throttling, d, mode)
}

/// [`throttling_guard`] for a command without the stack's options (`identify`).
fn lift_throttling(
    throttling: Throttling,
    d: &Deployment,
    mode: Mode,
) -> Result<Option<ThrottlingLifted>> {
    if mode == Mode::Lockstep || !d.has_priorities() {
        return Ok(None);
    }
    if throttling == Throttling::Off {
        match ThrottlingLifted::engage() {
            Ok(g) => return Ok(g),
            Err(e) if d.require_rt => return Err(e),
            Err(e) => tracing::warn!("{e:#}; continuing with RT throttling on"),
        }
    }
    // RT throttling takes a spinning SCHED_FIFO task off its CPU for up to 50 ms a second
    // when ordinary tasks want that CPU; say so once.
    if let Some(us) = rt_runtime_us().filter(|&us| us != -1) {
        tracing::info!(
            "RT throttling is on (sched_rt_runtime_us = {us}): SCHED_FIFO tasks may lose their CPU \
             for {} ms a second when ordinary tasks need it (--rt-throttling off disables it for \
             the run; see the README)",
            (1_000_000 - us) / 1000
        );
    }
    Ok(None)
}

/// The recording's chunks as `--uncompressed` says.
fn chunks(uncompressed: bool) -> Chunks {
    if uncompressed {
        Chunks::Uncompressed
    } else {
        Chunks::Zstd
    }
}

pub fn run(a: RunArgs) -> Result<()> {
    let mut s = a.select.scenario.load()?;
    a.stack.apply_duration(&mut s)?;
    let deployment = a.stack.deployment(a.mode)?;
    check_drive_count(&s, &deployment)?;
    let json = JsonOut::create(a.select.json.as_ref())?;
    let record_path = match (&a.record, &a.plots) {
        (Some(p), _) => Some(p.clone()),
        (None, Some(dir)) => Some(dir.join("run.mcap")),
        (None, None) => None,
    };
    if let Some(dir) = &a.plots {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the plot directory {}", dir.display()))?;
    }
    let live = a.live.start()?;
    let mut recording = match (&record_path, live) {
        (Some(p), live) => {
            let file = Recording::create(p, &s, chunks(a.uncompressed))?;
            Some(match live {
                Some(view) => file.with_live(view),
                None => file,
            })
        }
        (None, Some(view)) => Some(Recording::live_only(view, &s)),
        (None, None) => None,
    };
    // The guard is watched with each method's stack (restarted if it dies), and restores
    // throttling when the last one is over.
    let mut helpers = Helpers {
        guard: throttling_guard(&a.stack, &deployment, a.mode)?,
        ..Helpers::default()
    };
    let opts = LaunchOptions {
        instance: a.stack.instance.clone(),
        mode: a.mode,
        deployment,
        drive_truth: a.stack.drive_truth.clone(),
    };
    let mut runs = Vec::new();
    for method in &a.select.methods {
        tracing::info!(
            "{method}: launching plant, position loop and current loop ({}, {:.1} s)",
            a.mode.as_str(),
            s.duration_s()
        );
        let report = match run_stack(&s, *method, &opts, recording.as_mut(), Some(&mut helpers)) {
            Ok(report) => report,
            Err(e) => {
                // The stack could not start: keep what the earlier methods gathered.
                close_recording(recording.take(), a.plots.as_deref());
                if !runs.is_empty() {
                    conclude(&s, &runs, json).ok();
                }
                return Err(e.context(format!("the {method} run could not start")));
            }
        };
        let stop = report.worst() >= Outcome::ProcessDied;
        runs.push(report);
        if stop {
            break;
        }
    }
    close_recording(recording, a.plots.as_deref());
    conclude(&s, &runs, json)
}

/// `stepdrive serve`: the stack up, the axis disabled, until Ctrl-C.
pub fn gateway(a: GatewayArgs) -> Result<()> {
    use stepdrive_client::remote::Side;
    let (endpoint, side) = match (a.listen, a.connect) {
        (_, Some(c)) => (c, Side::Connect),
        (Some(l), None) => (l, Side::Listen),
        (None, None) => (
            format!(
                "tcp/0.0.0.0:{}",
                stepdrive_shared::services::remote::DEFAULT_PORT
            ),
            Side::Listen,
        ),
    };
    // Before the session opens: Zenoh's threads inherit both.
    let cpus = a
        .cpus
        .map_or_else(|| Deployment::default().helper_cpus(), |c| c.0);
    stepdrive_runtime::rt::RtOptions {
        priority: (a.priority > 0).then_some(a.priority),
        cpu: None,
        helper_cpus: cpus,
        lock_memory: false,
        timer_slack_ns: None,
        nice: None,
        require: true,
    }
    .apply()
    .map_err(|e| anyhow::anyhow!("--priority/--cpus: {}", e.describe()))?;
    let o = stepdrive_client::gateway::GatewayOptions {
        instance: a.instance,
        endpoint,
        side,
        status_hz: a.status_rate,
        max_commands_hz: a.max_command_rate,
        attach_timeout: a.wait,
    };
    let sum = stepdrive_client::gateway::run(&o).context("gateway")?;
    println!(
        "gateway stopped: {} commands forwarded, {} refused over the rate limit, {} malformed \
         messages, {} statuses and {} stream points carried, {} leases lost, {} quick stops",
        sum.commands,
        sum.rate_limited,
        sum.malformed,
        sum.statuses,
        sum.points,
        sum.leases_lost,
        sum.quick_stops
    );
    Ok(())
}

/// `serve --gateway`: the gateway as a child process, started beside the stack (it waits
/// for the stack's services), watched with it (a death is logged at once, the motion of its
/// remote clients quick-stopped and the gateway restarted: `Helpers`) and stopped with it.
/// `priority`: the gateway's SCHED_FIFO priority; 0 when the stack's loops run at ordinary
/// priority, so that the gateway never goes before them. `cpus`: the stack's helper CPUs
/// (empty: any).
fn start_gateway(endpoint: &str, instance: &str, priority: u8, cpus: &[usize]) -> Result<Helper> {
    if !endpoint.starts_with("tcp/") {
        anyhow::bail!("--gateway {endpoint}: give tcp/HOST:PORT");
    }
    // A busy or foreign address is refused before the stack starts.
    let addr = &endpoint["tcp/".len()..];
    std::net::TcpListener::bind(addr)
        .with_context(|| format!("--gateway {endpoint}: cannot listen there"))?;
    let cpus = match cpus {
        [] => "any".to_string(),
        cpus => stepdrive_runtime::rt::cpu_list(cpus),
    };
    let args = ["gateway", "--instance", instance, "--listen", endpoint]
        .into_iter()
        .map(String::from)
        .chain(["--priority".to_string(), priority.to_string()])
        .chain(["--cpus".to_string(), cpus])
        .collect();
    let mut gateway = Helper::spawn("gateway", args).context("starting the gateway")?;
    // What fails at once (a priority refused, a bad option) fails `serve` at once.
    std::thread::sleep(std::time::Duration::from_millis(300));
    if let Some(status) = gateway.poll_exit()? {
        anyhow::bail!("--gateway: the gateway exited at once ({status}); its error is above");
    }
    Ok(gateway)
}

pub fn serve(a: ServeArgs) -> Result<()> {
    let mut s = a.scenario.load()?;
    if !s.program.is_empty() {
        anyhow::bail!(
            "scenario {} has a [[program]]: a served stack takes its commands from clients \
             (`stepdrive axis`); run a program with `stepdrive run`",
            s.name
        );
    }
    if a.stack.duration.is_some() {
        anyhow::bail!("--duration is for `run`: a served stack runs until Ctrl-C");
    }
    s.run.until_stopped = true;
    let mode = match a.mode {
        ServeMode::Realtime => Mode::Realtime,
        ServeMode::Hardware => Mode::Hardware,
    };
    let deployment = a.stack.deployment(mode)?;
    let mut live = a.live.start()?.map(|view| Recording::live_only(view, &s));
    let gateway = a
        .gateway
        .as_deref()
        .map(|endpoint| {
            let priority = match a.stack.priority {
                Some(0) => 0,
                _ => stepdrive_client::STREAM_PRIORITY,
            };
            start_gateway(
                endpoint,
                &a.stack.instance,
                priority,
                &deployment.helper_cpus(),
            )
        })
        .transpose()?;
    check_drive_count(&s, &deployment)?;
    let mut helpers = Helpers {
        gateway,
        guard: throttling_guard(&a.stack, &deployment, mode)?,
        ..Helpers::default()
    };
    let opts = LaunchOptions {
        instance: a.stack.instance.clone(),
        mode,
        deployment,
        drive_truth: a.stack.drive_truth.clone(),
    };
    tracing::info!(
        "serving instance `{}` ({}): the axis is disabled; command it with `stepdrive axis \
         --instance {} ...`; Ctrl-C stops the stack",
        opts.instance,
        mode.as_str(),
        opts.instance
    );
    let r = stepdrive_monitor::supervise::launcher::serve_stack(
        &s,
        &opts,
        live.as_mut(),
        Some(&mut helpers),
    )?;
    drop(live);
    let events = std::mem::take(&mut helpers.events);
    // The gateway stopped, then throttling restored, before the last line.
    drop(helpers);
    let because = match events.is_empty() {
        true => r.because.clone(),
        false => format!("{}; {}", r.because, events.join("; ")),
    };
    println!(
        "served {:.1} s ({} samples, {} deadline misses): {because}",
        r.served_s, r.samples, r.misses
    );
    if r.outcome == Outcome::Ok {
        return Ok(());
    }
    Err(Exit {
        code: r.outcome.exit_code(),
        headline: format!(
            "{} (exit {}): the served stack {because}",
            r.outcome.title(),
            r.outcome.exit_code(),
        ),
    }
    .into())
}

/// Finishes the recording (its summary makes it complete) and draws its plots; a failure
/// here is said, and never hides the run's own outcome.
fn close_recording(recording: Option<Recording>, plots: Option<&std::path::Path>) {
    let Some(r) = recording.filter(Recording::has_file) else {
        return;
    };
    let path = r.path().to_path_buf();
    match r.finish() {
        Ok(()) => println!("recording written to {}", path.display()),
        Err(e) => {
            tracing::error!("{e:#}");
            return;
        }
    }
    if let Some(dir) = plots {
        match stepdrive_monitor::record::plot::plot_file(&path, dir) {
            Ok(files) => println!("{} plots written to {}", files.len(), dir.display()),
            Err(e) => tracing::error!("cannot draw the plots: {e:#}"),
        }
    }
}

pub fn simulate(a: SimulateArgs) -> Result<()> {
    let s = a.select.scenario.load_one_axis("`simulate`")?;
    let json = JsonOut::create(a.select.json.as_ref())?;
    let mut runs = Vec::with_capacity(a.select.methods.len());
    if a.stalls.is_empty() {
        for m in &a.select.methods {
            runs.push(simulate_run(&s, *m).with_context(|| format!("the {m} simulation failed"))?);
        }
        return conclude(&s, &runs, json);
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
    for m in &a.select.methods {
        let (report, record) = simulate_stalls(&s, *m, &stalls, a.watchdog_periods)
            .with_context(|| format!("the {m} simulation failed"))?;
        println!(
            "{m}: {} periods without their command, {} of them covered by a plan, longest run {}",
            record.misses, record.planned, record.longest_run
        );
        runs.push(report);
    }
    conclude(&s, &runs, json)
}

pub fn latency(a: LatencyArgs) -> Result<()> {
    let mut s = a.scenario.load()?;
    if a.stack.duration.is_none() {
        s.run.duration_s = Some(60.0);
    }
    a.stack.apply_duration(&mut s)?;
    let deployment = a.stack.deployment(Mode::Realtime)?;
    let _throttling = throttling_guard(&a.stack, &deployment, Mode::Realtime)?;
    let baseline = a.baseline_duration.unwrap_or(s.duration_s().min(20.0));
    let baseline_duration = seconds(baseline)
        .map_err(anyhow::Error::msg)
        .context("--baseline-duration")?;
    let opts = LatencyOptions {
        out: a.out.clone(),
        baseline_duration,
        launch: LaunchOptions {
            instance: a.stack.instance.clone(),
            mode: Mode::Realtime,
            deployment,
            drive_truth: None,
        },
        skip_baselines: a.skip_baselines,
    };
    let report = run_latency(&s, &opts)?;
    println!("{}", latency_table(&report));
    println!(
        "written: {}/latency.json, latency.svg, *.hist",
        a.out.display()
    );
    conclude(&s, std::slice::from_ref(&report.run), None)
}

pub fn reset(a: ResetArgs) -> Result<()> {
    let result = stepdrive_monitor::supervise::attach::reset(&a.instance, a.wait_s)?;
    let text = stepdrive_monitor::supervise::attach::describe(&result);
    if let ResetResult::StillLatched(_) = result {
        return Err(Exit {
            code: Outcome::Fault.exit_code(),
            headline: format!("FAULT (exit 3): reset of instance `{}`: {text}", a.instance),
        }
        .into());
    }
    println!("reset of instance `{}`: {text}", a.instance);
    Ok(())
}

pub fn monitor(a: MonitorArgs) -> Result<()> {
    let given = a.scenario.given()?;
    let json = JsonOut::create(a.json.as_ref())?;
    let attached = attach_reader(&a.instance, Role::Monitor.id(), given.as_ref(), a.axis)?;
    a.apply_priority(attached.bus.mode())?;
    let s = attached.scenario.clone();
    let report = watch(attached, &a.instance, a.method, a.peer_timeout_s, None)?;
    conclude(&s, &[report], json)
}

#[derive(Args, Debug)]
pub struct RecordArgs {
    /// The recording to write (MCAP; see `run --record`).
    file: PathBuf,
    /// Write its chunks uncompressed (default: zstd, ~4× smaller).
    #[arg(long)]
    uncompressed: bool,
    #[command(flatten)]
    watch: MonitorArgs,
}

/// `monitor` with a recording: attaches to a running stack (one started by hand too) and
/// records until its last sample, Ctrl-C, or its silence; the file is finished on each.
pub fn record(a: RecordArgs) -> Result<()> {
    let w = a.watch;
    let given = w.scenario.given()?;
    let json = JsonOut::create(w.json.as_ref())?;
    let attached = attach_reader(&w.instance, Role::Monitor.id(), given.as_ref(), w.axis)?;
    w.apply_priority(attached.bus.mode())?;
    let s = attached.scenario.clone();
    let mut recording = Recording::create(&a.file, &s, chunks(a.uncompressed))?;
    let report = watch(
        attached,
        &w.instance,
        w.method,
        w.peer_timeout_s,
        Some(&mut recording),
    );
    close_recording(Some(recording), None);
    conclude(&s, &[report?], json)
}

pub fn scenario(a: CheckArgs) -> Result<()> {
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
        None => print!("{}", Scenario::default().to_full_toml_string()?),
    }
    Ok(())
}

pub fn deploy(a: DeployArgs) -> Result<()> {
    match a.check.check {
        Some(path) => {
            Deployment::from_toml_file(&path)?
                .validate_for(a.mode)
                .with_context(|| format!("{} for --mode {}", path.display(), a.mode.as_str()))?;
            println!("{}: valid for --mode {}", path.display(), a.mode.as_str());
        }
        None => print!(
            "{}",
            Deployment::default().resolved(a.mode).to_toml_string()
        ),
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct PlotArgs {
    /// The recording (MCAP) to draw.
    file: PathBuf,
    /// Directory for the figures (created if missing).
    #[arg(long, value_name = "DIR", default_value = "plots")]
    out: PathBuf,
}

pub fn plot(a: PlotArgs) -> Result<()> {
    let files = stepdrive_monitor::record::plot::plot_file(&a.file, &a.out)?;
    for f in &files {
        println!("{}", f.display());
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// The recording (MCAP) to export.
    file: PathBuf,
    /// Directory for the CSV files (created if missing): <method>_state.csv,
    /// <method>_stats.csv, <method>_fault.csv.
    #[arg(long, value_name = "DIR")]
    csv: PathBuf,
}

pub fn export(a: ExportArgs) -> Result<()> {
    let files = stepdrive_monitor::record::recording::export_csv(&a.file, &a.csv)?;
    for (f, rows) in &files {
        println!("{} ({rows} rows)", f.display());
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct ScopeArgs {
    /// The stack's instance name.
    #[arg(long, default_value = DEFAULT_INSTANCE, value_parser = stepdrive_shared::services::instance_name)]
    instance: String,
    /// The stack's scenario (default: the one the stack announces).
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// The axis of a multi-axis stack to show (its index, 0 first).
    #[arg(long, value_name = "N", default_value_t = 0)]
    axis: u32,
}

pub fn scope(a: ScopeArgs) -> Result<()> {
    let given = a.scenario.given()?;
    stepdrive_monitor::record::scope::run_scope(&a.instance, given.as_ref(), a.axis)
}

#[derive(Args, Debug)]
pub struct RobustnessArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// Write every cell's full results as JSON to FILE.
    #[arg(long, value_name = "FILE", default_value = "robustness.json")]
    json: PathBuf,
    /// Simulations run side by side (default: the CPUs available).
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=64))]
    threads: Option<u16>,
}

/// Every case of the robustness table with every controller, in lockstep: markdown tables
/// on stdout, the full results in JSON. Step-outs and faults are results here, named in
/// the table and summed up at the end, not errors of the command.
pub fn robustness(a: RobustnessArgs) -> Result<()> {
    use stepdrive_monitor::studies::robustness::{run_table, tables, RobustnessDocument};
    let s = a.scenario.load_one_axis("`robustness`")?;
    let threads = a.threads.map_or_else(
        || std::thread::available_parallelism().map_or(1, |n| n.get()),
        usize::from,
    );
    let json = JsonOut::create(Some(&a.json))?;
    let started = std::time::Instant::now();
    let bar = indicatif::ProgressBar::new(0);
    let cells = run_table(&s, threads, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .context("a robustness simulation failed")?;
    bar.finish_and_clear();
    println!(
        "robustness of scenario {}: {} cases × 4 controllers, lockstep, {:.1} s",
        s.name,
        cells.len() / 4,
        started.elapsed().as_secs_f64()
    );
    print!("{}", tables(&cells));
    if let Some(out) = json {
        let doc = RobustnessDocument {
            stepdrive_version: env!("CARGO_PKG_VERSION"),
            scenario: &s,
            cells: &cells,
        };
        let text = serde_json::to_string_pretty(&doc)?;
        let path = out.path.clone();
        out.commit(&(text + "\n"))?;
        println!("\nresults written to {}", path.display());
    }
    let lost: Vec<String> = cells
        .iter()
        .filter(|c| c.report.outcome != Outcome::Ok)
        .map(|c| {
            format!(
                "{} with {}: {}",
                c.case,
                c.controller,
                c.report.outcome.title()
            )
        })
        .collect();
    if !lost.is_empty() {
        println!("\n{} of {} cells lost the motor:", lost.len(), cells.len());
        for l in &lost {
            println!("  {l}");
        }
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct IdentifyArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    /// Write the scenario with the identified [motor] and [load] to FILE (the rest, its
    /// [plant] section included, as given): `run --scenario FILE` then uses them.
    #[arg(long, value_name = "FILE", default_value = "motor.toml")]
    out: PathBuf,
    /// Also write the estimates as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Phase current the sequence must never exceed, A (it asks for 60 % of it).
    #[arg(long, value_name = "A", default_value_t = 1.0, value_parser = positive)]
    max_current: f64,
    /// Phase voltage the sequence never commands beyond, V.
    #[arg(long, value_name = "V", default_value_t = 20.0, value_parser = positive)]
    max_voltage: f64,
    /// Speed the sequence must never exceed, rad/s (it spins at up to two thirds of it; default
    /// 1.5 × the scenario's cruise speed, so B and the load are measured at the speeds the
    /// motor will run at).
    #[arg(long, value_name = "RAD_S", value_parser = positive)]
    max_speed: Option<f64>,
    /// Travel from the start the sequence must never exceed, rad.
    #[arg(long, value_name = "RAD", default_value_t = 30.0, value_parser = positive)]
    max_travel: f64,
    /// lockstep: in one process on virtual time, deterministic. realtime: the plant and the
    /// sequence as processes on the wall clock. hardware: against a drive (--drive, or an
    /// emulated one started for it), through the bridge.
    #[arg(long, value_enum, default_value_t = Mode::Lockstep)]
    mode: Mode,
    /// Hardware mode: the drive, host:port on UDP or a serial line's path.
    #[arg(long, value_name = "HOST:PORT|PATH")]
    drive: Option<String>,
    /// The stack's instance name (realtime and hardware).
    #[arg(long, default_value = "identify", value_parser = stepdrive_shared::services::instance_name)]
    instance: String,
    /// Realtime and hardware: RT throttling, as `run --rt-throttling` (lifted by default).
    #[arg(long, value_enum, default_value_t = Throttling::Off)]
    rt_throttling: Throttling,
}

fn positive(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && *v > 0.0)
        .ok_or_else(|| format!("`{s}` must be a positive number"))
}

/// The identification sequence against the simulated plant (lockstep): table, scenario
/// file, JSON. A bound hit stops it with the outputs off and exits 3.
pub fn identify(a: IdentifyArgs) -> Result<()> {
    use stepdrive_control::identify::Bounds;
    use stepdrive_monitor::studies::identify::{default_max_speed, identified_scenario, table};
    let s = a.scenario.load_one_axis("`identify`")?;
    writable(&a.out).with_context(|| {
        format!(
            "cannot write the identified scenario to {} (checked before the sequence runs)",
            a.out.display()
        )
    })?;
    if a.max_voltage > s.drive.bus_voltage_v {
        anyhow::bail!(
            "--max-voltage {} V exceeds the bus ({} V): the drive cannot apply it",
            a.max_voltage,
            s.drive.bus_voltage_v
        );
    }
    let bounds = Bounds {
        current_a: a.max_current,
        voltage_v: a.max_voltage,
        speed_rad_s: a.max_speed.unwrap_or_else(|| default_max_speed(&s)),
        travel_rad: a.max_travel,
    };
    let stopped = |hit: String| -> anyhow::Error {
        Exit {
            code: Outcome::Fault.exit_code(),
            headline: format!(
                "IDENTIFICATION STOPPED (exit {}): {hit}; the outputs were turned off and nothing was written",
                Outcome::Fault.exit_code()
            ),
        }
        .into()
    };
    let found = if a.mode == Mode::Lockstep {
        identify_lockstep(&s, bounds, &stopped)?
    } else {
        let mut run = s.clone();
        run.run.duration_s = Some(stepdrive_control::identify::Sequence::duration_s());
        let mut deployment = Deployment::default();
        if let Some(addr) = &a.drive {
            deployment.drive.address = Some(addr.clone());
        }
        // As for `run`: with throttling on, the kernel takes the SCHED_FIFO sequence off its
        // CPU for up to 50 ms a second, as long as the drive's watchdog.
        let _throttling = lift_throttling(a.rt_throttling, &deployment, a.mode)?;
        let opts = stepdrive_monitor::supervise::launcher::LaunchOptions {
            instance: a.instance.clone(),
            mode: a.mode,
            deployment,
            drive_truth: None,
        };
        use stepdrive_monitor::studies::identify::{identified, NodeResult};
        match stepdrive_monitor::supervise::launcher::run_identify(&run, &bounds, &opts)? {
            NodeResult::Estimates(e) => identified(&s, e),
            NodeResult::Stopped { hit, .. } => return Err(stopped(hit)),
            NodeResult::Failed(why) => anyhow::bail!("identification failed: {why}"),
        }
    };
    println!(
        "identified on scenario {} ({} mode)",
        s.name,
        a.mode.as_str()
    );
    print!("{}", table(&found.rows));
    let out = identified_scenario(&s, &found.estimates);
    std::fs::write(&a.out, out.to_toml_string()?)
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    println!(
        "scenario written to {} (run --scenario {} uses it)",
        a.out.display(),
        a.out.display()
    );
    if let Some(path) = &a.json {
        std::fs::write(path, serde_json::to_string_pretty(&found)? + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
        println!("estimates written to {}", path.display());
    }
    Ok(())
}

fn identify_lockstep(
    s: &Scenario,
    bounds: stepdrive_control::identify::Bounds,
    stopped: &dyn Fn(String) -> anyhow::Error,
) -> Result<stepdrive_monitor::studies::identify::Identified> {
    use stepdrive_monitor::studies::identify::{identify_simulated, IdentifyError};
    match identify_simulated(s, bounds) {
        Ok(f) => Ok(f),
        Err(IdentifyError::Bound { hit, .. }) => Err(stopped(hit.to_string())),
        Err(e) => Err(e).context("identification failed"),
    }
}
