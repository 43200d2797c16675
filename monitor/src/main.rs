//! `stepdrive`: one binary, one sub-command per role. `run` launches the whole stack; `plant`,
//! `current-loop` and `position-loop` are the three processes (start them by hand in three
//! terminals and they find each other by instance name).

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;
use stepdrive_controller::process::{
    run_current_loop, run_position_loop, ControllerError, LoopOptions,
};
use stepdrive_monitor::launcher::{run_lockstep, Interrupted, LaunchOptions};
use stepdrive_monitor::metrics::RunReport;
use stepdrive_monitor::report::{document, table};
use stepdrive_monitor::simulate::simulate;
use stepdrive_plant::process::{PlantError, PlantOptions};
use stepdrive_shared::poll::install_termination_handler;
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
}

fn parse_seconds(s: &str) -> Result<Duration, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("`{s}` is not a number of seconds"))?;
    if v.is_finite() && v > 0.0 && v < 1e6 {
        Ok(Duration::from_secs_f64(v))
    } else {
        Err(format!(
            "must be a positive number of seconds below 1e6 (got {s})"
        ))
    }
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
    /// Timing mode. Only `lockstep` (virtual time, plant waits for each command) exists yet.
    #[arg(long, default_value = "lockstep")]
    mode: Mode,
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
    /// Timing mode. Only `lockstep` (virtual time, bit-identical results) exists yet.
    #[arg(long, default_value = "lockstep")]
    mode: Mode,
    /// Instance namespace of the services.
    #[arg(long, default_value = DEFAULT_INSTANCE)]
    instance: String,
    #[command(flatten)]
    timeouts: Timeouts,
}

#[derive(Args, Debug)]
struct SimulateArgs {
    #[command(flatten)]
    scenario: ScenarioOpt,
    #[arg(long = "method", value_delimiter = ',', default_values = ["proposed", "lyapunov"])]
    methods: Vec<Method>,
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
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
            let s = a.scenario.load()?;
            let Mode::Lockstep = a.mode;
            let opts = LaunchOptions {
                instance: a.instance.clone(),
                startup_timeout: a.timeouts.startup_timeout_s,
                peer_timeout: a.timeouts.peer_timeout_s,
            };
            let mut runs = Vec::new();
            for method in &a.methods {
                tracing::info!(
                    "{method}: launching plant, position loop and current loop (lockstep)"
                );
                let report = run_lockstep(&s, *method, &opts)
                    .with_context(|| format!("the {method} run failed"))?;
                runs.push(report);
            }
            write_outputs(&s, &runs, a.json.as_ref())
        }
        Cmd::Simulate(a) => {
            let s = a.scenario.load()?;
            let runs: Vec<RunReport> = a.methods.iter().map(|m| simulate(&s, *m)).collect();
            write_outputs(&s, &runs, a.json.as_ref())
        }
        Cmd::Plant(a) => {
            let lo = a.common.loop_options()?;
            let Mode::Lockstep = a.mode;
            let opts = PlantOptions {
                instance: lo.instance,
                scenario: lo.scenario,
                wait_subscribers: a.wait_subscribers as usize,
                startup_timeout: lo.startup_timeout,
                peer_timeout: lo.peer_timeout,
            };
            stepdrive_plant::process::run_lockstep(&opts)?;
            Ok(())
        }
        Cmd::CurrentLoop(a) => {
            run_current_loop(&a.common.loop_options()?, a.method)?;
            Ok(())
        }
        Cmd::PositionLoop(a) => {
            run_position_loop(&a.loop_options()?)?;
            Ok(())
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
