//! `stepdrive`: one binary, one sub-command per role. `run` launches the whole stack; `plant`,
//! `current-loop` and `position-loop` are the three processes (start them by hand in three
//! terminals and they find each other by instance name). This crate only parses the
//! command line and hands over: the processes are nodes of `stepdrive-runtime`'s runner.

mod axis;
mod commands;
mod options;
mod roles;

use clap::{Parser, Subcommand};
use std::process::ExitCode;
use stepdrive_monitor::report::outcome::Outcome;
use stepdrive_runtime::node::Role;
use stepdrive_runtime::poll::install_termination_handler;
use stepdrive_runtime::RunError;

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
    Run(commands::RunArgs),
    /// Bring plant (or bridge), position loop and current loop up and keep them up, the
    /// axis disabled, taking commands (`stepdrive axis ...`, the client crate) until Ctrl-C.
    Serve(commands::ServeArgs),
    /// Command a served stack's axis: status, enable, disable, quick-stop, reset, move, jog,
    /// stop, stream, set-position (`stepdrive axis --help`).
    Axis(crate::axis::AxisArgs),
    /// The axis on Zenoh for clients on other hosts: commands answered as the local command
    /// service answers them, the status at --status-rate, streams, and a lease per remote
    /// client (`serve --gateway` starts one; `stepdrive axis --connect` is its client).
    Gateway(commands::GatewayArgs),
    /// The same nodes in one process on virtual time, no IPC: the reference a `run` must
    /// reproduce exactly; with --stall, what a host stall of the current loop costs.
    Simulate(commands::SimulateArgs),
    /// Each method against plants that are not its model (R, L, K_m, J, B ±20 %, an unknown
    /// load, a load step, detent torque, all at once): lockstep, markdown tables, JSON.
    Robustness(commands::RobustnessArgs),
    /// Measure the motor's R, L, K_m, J, B and load through the stack with a bounded
    /// sequence (DC levels, steps, an open-loop spin) and write a scenario that uses them.
    Identify(commands::IdentifyArgs),
    /// The plant process: motor model eq. (1), publishes drive/state, applies drive/command;
    /// in hardware mode the bridge to a drive (as `bridge`).
    Plant(roles::DeviceArgs),
    /// The bridge process (hardware mode): the plant's contract toward the stack, the drive
    /// wire protocol (docs/drive-protocol.md) toward a drive.
    Bridge(roles::DeviceArgs),
    /// The current-loop process: commutation (17) + sampled current tracking (22), or a baseline.
    CurrentLoop(roles::CurrentLoopArgs),
    /// The position/torque-loop process: trajectory + torque modulation (12).
    PositionLoop(options::ProcessArgs),
    /// Clear the latched faults of a running stack's plant (or bridge and drive), once their
    /// cause is gone: e.g. after a dead current loop was restarted. Exit 0 when cleared.
    Reset(commands::ResetArgs),
    /// Attach to a running stack (one started by hand) and compute its run's figures from
    /// its state stream, as `run` does: table, JSON, exit code.
    Monitor(commands::MonitorArgs),
    /// Draw the paper's figures from a recording (run --record): position, tracking error
    /// (linear and log, eq. (7) bound), phase currents and voltages (full-run envelope beside
    /// a zoom), i_d/i_q, torque; every pass's cruise window and any fault marked; SVG and
    /// PNG, methods overlaid. A run with a `[[program]]` adds its moves: θ_d against θ, the
    /// following error, ω_d and ω, α_d, the axis state shaded (program_*.png).
    Plot(commands::PlotArgs),
    /// Write a recording's topics as CSV files, one per topic (time in s, SI columns).
    Export(commands::ExportArgs),
    /// A live terminal view of a running stack: rolling e, ω, i_d/i_q, v_a/v_b, each
    /// loop's timing, faults in red. Only reads: it never disturbs the loops.
    Scope(commands::ScopeArgs),
    /// Attach to a running stack (one started by hand too) and record it to an MCAP file
    /// until its last sample or Ctrl-C, then print its figures as `monitor` does.
    Record(commands::RecordArgs),
    /// Print the default scenario as TOML, or check a scenario file.
    Scenario(commands::CheckArgs),
    /// Print the default deployment (wait strategies, priorities, CPUs, timeouts, watchdog,
    /// drive link) as TOML, or check a deployment file.
    Deploy(commands::DeployArgs),

    /// Latency and jitter of the live stack in realtime mode, beside bare iceoryx2 and
    /// Unix-socket ping-pong and cyclictest: table, latency.json, cyclictest-compatible
    /// histograms and a log-y plot in --out DIR.
    Latency(commands::LatencyArgs),
    /// A stand-in driver board: the motor model behind the drive wire protocol
    /// (docs/drive-protocol.md) on UDP or a serial line, with its own sample clock and
    /// fault injection.
    EmulateDrive(roles::EmulateArgs),
    /// Transport baseline process used by `latency` (ping paced like the plant, pong waiting
    /// like the current loop).
    #[command(hide = true)]
    Pingpong(roles::PingpongArgs),
    /// The identification sequence as a process (`identify --mode realtime|hardware` starts
    /// one).
    #[command(hide = true)]
    IdentifyNode(roles::IdentifyNodeArgs),
    /// Lifts RT throttling and restores it when its stdin closes (`run` starts one).
    #[command(hide = true)]
    RtThrottlingGuard {
        /// Restore this value (a guard that takes over from one that died), not the one
        /// found.
        #[arg(long, value_name = "US", allow_negative_numbers = true)]
        restore: Option<i64>,
    },
}

fn init_logging() {
    use tracing_subscriber::EnvFilter;
    // iceoryx2's own log, errors only: its warnings are about its housekeeping (no config
    // file, leftovers of killed processes it cannot remove) and repeat in every process on
    // every start; ours carry what a failure means. IOX2_LOG_LEVEL=warn shows them.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    let filter =
        EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info,zenoh=warn"));
    // SAFETY: isatty only inspects a descriptor.
    let ansi = unsafe { libc::isatty(libc::STDERR_FILENO) } == 1;
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(ansi)
        .with_target(false)
        .init();
}

fn dispatch(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Cmd::Run(a) => commands::run(a),
        Cmd::Serve(a) => commands::serve(a),
        Cmd::Axis(a) => {
            // A client's output piped into `head` ends it quietly, as any Unix tool (Rust
            // ignores SIGPIPE and the print would panic). Not for the launchers: a stack's
            // supervisor must never die of its reader going away.
            // SAFETY: restoring a signal's default disposition has no preconditions.
            unsafe { libc::signal(libc::SIGPIPE, libc::SIG_DFL) };
            crate::axis::axis(a)
        }
        Cmd::Gateway(a) => commands::gateway(a),
        Cmd::Simulate(a) => commands::simulate(a),
        Cmd::Robustness(a) => commands::robustness(a),
        Cmd::Identify(a) => commands::identify(a),
        Cmd::IdentifyNode(a) => roles::identify_node(a),
        Cmd::Plant(a) => roles::device(a, Role::Plant),
        Cmd::Bridge(a) => roles::device(a, Role::Bridge),
        Cmd::CurrentLoop(a) => roles::current_loop(a),
        Cmd::PositionLoop(a) => roles::position_loop(a),
        Cmd::Scenario(a) => commands::scenario(a),
        Cmd::Plot(a) => commands::plot(a),
        Cmd::Record(a) => commands::record(a),
        Cmd::Scope(a) => commands::scope(a),
        Cmd::Export(a) => commands::export(a),
        Cmd::Reset(a) => commands::reset(a),
        Cmd::Monitor(a) => commands::monitor(a),
        Cmd::Deploy(a) => commands::deploy(a),
        Cmd::Latency(a) => commands::latency(a),
        Cmd::EmulateDrive(a) => roles::emulate_drive(a),
        Cmd::Pingpong(a) => roles::pingpong(a),
        Cmd::RtThrottlingGuard { restore } => {
            stepdrive_monitor::supervise::throttling::guard(restore)
        }
    }
}

fn main() -> ExitCode {
    // Before any thread exists, so that every thread inherits it (see the function).
    stepdrive_runtime::steal::notice_stops();
    let cli = Cli::parse();
    init_logging();
    install_termination_handler();
    match dispatch(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let stopped = e
                .chain()
                .any(|c| matches!(c.downcast_ref::<RunError>(), Some(RunError::Terminated)));
            if stopped && e.downcast_ref::<commands::Exit>().is_none() {
                // A stop asked for (the launcher's SIGTERM, Ctrl-C) is no error: the exit
                // code (130) says it; whoever asked reports the run.
                tracing::info!("stopped by SIGINT/SIGTERM");
                return ExitCode::from(Outcome::Interrupted.exit_code());
            }
            // One line, prefixed, so a launcher can pick it out of our stderr.
            eprintln!("error: {e:#}");
            if let Some(exit) = e.downcast_ref::<commands::Exit>() {
                return ExitCode::from(exit.code);
            }
            let run_error = e.chain().find_map(|c| c.downcast_ref::<RunError>());
            match run_error {
                Some(RunError::Terminated) => ExitCode::from(Outcome::Interrupted.exit_code()),
                // A peer died or went silent: this process stopped with it.
                Some(RunError::PeerSilent { .. }) => {
                    ExitCode::from(Outcome::ProcessDied.exit_code())
                }
                _ => ExitCode::FAILURE,
            }
        }
    }
}
