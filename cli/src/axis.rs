//! `stepdrive axis`: command a served stack's axis from the command line, through the
//! client crate (`stepdrive-client`), as a program would.

use crate::commands::Exit;
use crate::options::parse_seconds;
use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use stepdrive_client::{
    Axis, AxisAck, AxisMode, AxisState, AxisStatus, ClientError, Group, Limits, RequestKind,
};
use stepdrive_monitor::report::outcome::Outcome;
use stepdrive_shared::axis::{
    parse_stream, parse_stream_of_axes, request_flags, status_bits, stream_theta_columns,
};
use stepdrive_shared::services::DEFAULT_INSTANCE;

#[derive(Args, Debug)]
pub struct AxisArgs {
    /// The served stack's instance name.
    #[arg(long, default_value = DEFAULT_INSTANCE, global = true, value_parser = stepdrive_shared::services::instance_name)]
    instance: String,
    /// The axis: 0, or in a multi-axis stack its `[[axis]]` index
    #[arg(long, default_value_t = 0, global = true)]
    axis: u32,
    /// Reach the stack through the `stepdrive gateway` at this Zenoh endpoint
    /// (tcp/HOST:PORT), from this host or another, instead of its services on this host.
    #[arg(long, value_name = "tcp/HOST:PORT", global = true)]
    connect: Option<String>,
    #[command(subcommand)]
    verb: Verb,
}

/// A move's or jog's limits (absent: the axis's move defaults, `[axis]`). Each must be
/// positive and finite here; the axis refuses one above its maximum, below a millionth of
/// it, or so low that the command would take longer than `[axis] move_time_max_s`.
#[derive(Args, Debug, Clone, Copy)]
struct LimitArgs {
    /// Speed limit, rad/s.
    #[arg(long, allow_negative_numbers = true, value_parser = positive)]
    vmax: Option<f64>,
    /// Acceleration limit, rad/s².
    #[arg(long, allow_negative_numbers = true, value_parser = positive)]
    amax: Option<f64>,
    /// Jerk limit, rad/s³.
    #[arg(long, allow_negative_numbers = true, value_parser = positive)]
    jmax: Option<f64>,
}

/// A limit: positive and finite.
fn positive(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("must be a positive finite number (got {s})")),
    }
}

/// A position or speed: finite.
fn finite(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("must be a finite number (got {s})")),
    }
}

/// A stream's lead, s.
fn lead(s: &str) -> Result<f64, String> {
    crate::options::number_within(s, 0.0, 10.0, false, "s")
}

impl LimitArgs {
    fn limits(&self) -> Limits {
        Limits {
            v: self.vmax,
            a: self.amax,
            j: self.jmax,
        }
    }
}

#[derive(Subcommand, Debug)]
enum Verb {
    /// Print the axis's state (CiA 402), mode, position, speed, torque, following error,
    /// setpoint, target and faults.
    Status,
    /// Print a line of the axis's status (time, state, θ, ω, following error) every
    /// --every seconds until Ctrl-C.
    Watch {
        /// Seconds between lines.
        #[arg(long, default_value_t = 0.1, value_parser = watch_period)]
        every: f64,
    },
    /// Enable: shutdown, switch on, enable operation (the setpoint starts where the rotor
    /// stands, at rest).
    Enable,
    /// Disable voltage: no torque.
    Disable,
    /// Quick stop: decelerate at the axis's quick-stop rate to a standstill and hold.
    QuickStop,
    /// Fault reset (the drive's own fault too, once its cause is gone).
    Reset,
    /// Profile position: a jerk-limited move. With --wait, Ctrl-C halts the move (a stop at
    /// the axis's move limits, if no other command has taken the axis over since) and exits
    /// 130.
    Move {
        /// The target, rad.
        #[arg(long, allow_negative_numbers = true, value_parser = finite)]
        to: f64,
        /// `--to` is relative to the preceding move's target (the move in progress, or the
        /// last one if nothing has moved the axis since), else to where the axis stands
        /// (CiA 402's relative positioning): never to a jog's or a stop's.
        #[arg(long)]
        relative: bool,
        /// After the current move ends (otherwise the move in progress changes at once).
        #[arg(long)]
        after_current: bool,
        #[command(flatten)]
        limits: LimitArgs,
        /// Wait until the target is reached (exit 3 if the axis faults on the way).
        #[arg(long)]
        wait: bool,
        /// Longest wait with --wait, s.
        #[arg(long, default_value = "30", value_parser = parse_seconds)]
        timeout: Duration,
    },
    /// A coordinated move of several axes of a multi-axis stack: each to its target
    /// (absolute, at its `[axis]` move limits), all leaving on one tick and arriving on one
    /// tick; refused as a whole if any axis cannot take its part. (`--axis` is not used.)
    /// With --wait, Ctrl-C halts every axis the move still runs and exits 130.
    MoveTogether {
        /// The targets, rad, one per axis of --axes: `--to 1,-6,12`.
        #[arg(
            long,
            value_delimiter = ',',
            allow_negative_numbers = true,
            required = true,
            value_parser = finite
        )]
        to: Vec<f64>,
        /// The axes, in the order of --to (default: 0, 1, … one per target).
        #[arg(long, value_delimiter = ',')]
        axes: Option<Vec<u32>>,
        /// Wait until every axis has reached its target (exit 3 if one faults on the way).
        #[arg(long)]
        wait: bool,
        /// Longest wait with --wait, s.
        #[arg(long, default_value = "30", value_parser = parse_seconds)]
        timeout: Duration,
    },
    /// Profile velocity: run at a speed (stops at the soft position limit) while this
    /// command runs: it renews the jog every 0.1 s until Ctrl-C (or --for), then stops the
    /// axis at the jog's limits. The axis quick-stops a jog its client stops renewing
    /// (`[axis] jog_timeout_s`, 0.5 s), so a jog never outlives the command that runs it.
    Jog {
        /// Speed, rad/s.
        #[arg(long, allow_negative_numbers = true, value_parser = finite)]
        velocity: f64,
        #[command(flatten)]
        limits: LimitArgs,
        /// Stop after this long, s (default: at Ctrl-C).
        #[arg(long = "for", value_name = "S", value_parser = parse_seconds)]
        duration: Option<Duration>,
    },
    /// Halt: decelerate to a standstill and stay enabled.
    Stop {
        #[command(flatten)]
        limits: LimitArgs,
    },
    /// Cyclic synchronous position: stream a CSV file of `t, θ[, ω[, τ_ff]]` rows, each
    /// point sent when the axis is ready for it (paced by the stream time the axis plays,
    /// one lead ahead).
    Stream {
        file: PathBuf,
        /// How far behind its points the axis plays the stream, s (default: the axis's).
        #[arg(long, value_parser = lead)]
        lead: Option<f64>,
        /// SCHED_FIFO priority of this client, 0 for ordinary: the stack's loops run at
        /// SCHED_FIFO, and a client at ordinary priority was measured held off the CPU for
        /// 84 ms, far past the lead.
        #[arg(long, value_name = "P", default_value_t = stepdrive_client::STREAM_PRIORITY,
              value_parser = clap::value_parser!(u8).range(0..=99))]
        priority: u8,
    },
    /// Cyclic synchronous position on several axes of a multi-axis stack: stream a CSV file
    /// of `t, θ_0, θ_1, …` rows (one position per axis of --axes), every axis started on
    /// one tick and played from one origin, so that one stream time is one instant on every
    /// axis. Refused as a whole if any axis cannot stream. (`--axis` is not used.)
    StreamTogether {
        file: PathBuf,
        /// The axes, in the order of the file's θ columns (default: 0, 1, … one per column).
        #[arg(long, value_delimiter = ',')]
        axes: Option<Vec<u32>>,
        /// How far behind its points every axis plays the stream, s (default: each axis's).
        #[arg(long, value_parser = lead)]
        lead: Option<f64>,
        /// SCHED_FIFO priority of this client, 0 for ordinary (as `stream`'s).
        #[arg(long, value_name = "P", default_value_t = stepdrive_client::STREAM_PRIORITY,
              value_parser = clap::value_parser!(u8).range(0..=99))]
        priority: u8,
    },
    /// Flood the axis with commands, never waiting for answers (a measurement of what a
    /// runaway client costs the stack): status requests, or with --move relative moves of
    /// ±1 µrad (the axis enabled). Prints what became of them; compare the loops' deadline
    /// misses `serve` reports with and without it.
    Flood {
        /// Commands per second (1 … 1e6).
        #[arg(long, default_value_t = 100_000.0, value_parser = flood_rate)]
        rate: f64,
        /// How long, s.
        #[arg(long, default_value = "10", value_parser = crate::options::parse_seconds)]
        seconds: Duration,
        /// Relative moves of 1 µrad instead of status requests.
        #[arg(long = "move")]
        moves: bool,
        /// Poll between sends, burning a CPU as a runaway client does. Without it the flood
        /// naps 100 µs whenever it is on schedule and sends what fell due in a burst: its
        /// figures are then the command path's, not its own CPU's (an ordinary task that
        /// keeps a CPU busy costs the loops as much whatever it does).
        #[arg(long)]
        spin: bool,
    },
    /// Measure command latency: COUNT small relative moves (±1 µrad, the axis enabled), each
    /// timed from its publication to the first setpoint that carries it out (the
    /// acknowledgement's timestamp); prints p50/p99/max. With --connect, each command's
    /// round trip through the gateway on this host's clock. A measurement, not a test.
    Latency {
        #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
        count: u32,
        /// SCHED_FIFO priority of this client, 0 for ordinary (as a stream's): the command's
        /// timestamp is taken before it is sent, and a client at ordinary priority beside
        /// the stack's SCHED_FIFO loops is held off between the two.
        #[arg(long, value_name = "P", default_value_t = stepdrive_client::STREAM_PRIORITY,
              value_parser = clap::value_parser!(u8).range(0..=99))]
        priority: u8,
    },
    /// Declare the present position (at a standstill).
    SetPosition {
        #[arg(allow_negative_numbers = true, value_parser = finite)]
        position: f64,
    },
}

/// A command refused, or the axis in Fault, as the exit code and headline the user reads.
fn failed(e: ClientError) -> anyhow::Error {
    let code = match &e {
        ClientError::Fault { .. } => Outcome::Fault.exit_code(),
        ClientError::Interrupted { .. } => Outcome::Interrupted.exit_code(),
        _ => 1,
    };
    // The whole chain: "answer on … failed" alone does not say the position loop is silent.
    let mut headline = e.to_string();
    let mut source = std::error::Error::source(&e);
    while let Some(cause) = source {
        headline.push_str(": ");
        headline.push_str(&cause.to_string());
        source = cause.source();
    }
    Exit { code, headline }.into()
}

fn describe(s: &AxisStatus) -> String {
    let state = AxisState::from_u32(s.state).map_or("?", |x| x.name());
    let mode = AxisMode::from_u32(s.mode).map_or("?", |m| m.name());
    let word = s.statusword as u16;
    let mut flags = Vec::new();
    for (bit, name) in [
        (status_bits::TARGET_REACHED, "target reached"),
        (status_bits::WARNING, "warning"),
        (status_bits::INTERNAL_LIMIT, "internal limit"),
        (status_bits::FOLLOWING_ERROR, "following error"),
        (status_bits::BRAKE_APPLIED, "brake applied"),
    ] {
        if word & bit != 0 {
            flags.push(name);
        }
    }
    format!(
        "state        {state} (statusword {word:#06x}{})\nmode         {mode}\n\
         θ            {:.6} rad\nω            {:.4} rad/s\ntorque       {:.4} N·m\n\
         θ_d − θ      {:.3e} rad\nsetpoint     θ_d {:.6} rad, ω_d {:.4} rad/s, α_d {:.3} rad/s²\n\
         target       {:.6} rad\nfault        {:#x} (device {:#x}), warning {:#x}\n\
         time         t = {:.4} s (tick {})\nlast command seq {} (epoch {})",
        if flags.is_empty() {
            String::new()
        } else {
            format!(": {}", flags.join(", "))
        },
        s.theta_rad,
        s.omega_rad_s,
        s.torque_nm,
        s.following_error_rad,
        s.theta_d_rad,
        s.omega_d_rad_s,
        s.alpha_d_rad_s2,
        s.target_rad,
        s.fault,
        s.device_fault,
        s.warning,
        s.t_s,
        s.tick,
        s.last_seq,
        s.epoch,
    )
}

pub fn axis(a: AxisArgs) -> Result<()> {
    if let Verb::MoveTogether {
        to,
        axes,
        wait,
        timeout,
    } = &a.verb
    {
        let axes = axes
            .clone()
            .unwrap_or_else(|| (0..to.len() as u32).collect());
        let timeout = wait.then_some(*timeout);
        let group = match &a.connect {
            Some(endpoint) => Group::connect_remote(endpoint, &a.instance, &axes),
            None => Group::connect(&a.instance, &axes),
        }
        .map_err(failed)?;
        return move_together(group, &axes, to, timeout);
    }
    if let Verb::StreamTogether {
        file,
        axes,
        lead,
        priority,
    } = &a.verb
    {
        let text = std::fs::read_to_string(file)
            .with_context(|| format!("cannot read the stream file {}", file.display()))?;
        let axes = match axes {
            Some(a) => a.clone(),
            None => (0..stream_theta_columns(&text) as u32).collect(),
        };
        let rows = parse_stream_of_axes(&text, axes.len())
            .with_context(|| format!("{}", file.display()))?;
        stepdrive_client::realtime_priority(*priority).map_err(failed)?;
        let group = match &a.connect {
            Some(endpoint) => Group::connect_remote(endpoint, &a.instance, &axes),
            None => Group::connect(&a.instance, &axes),
        }
        .map_err(failed)?;
        return stream_together(group, &rows, *lead);
    }
    let mut axis = match &a.connect {
        Some(endpoint) => Axis::connect_remote(endpoint, &a.instance, a.axis),
        None => Axis::connect(&a.instance, a.axis),
    }
    .map_err(failed)?;
    match a.verb {
        Verb::Status => {
            let s = axis.status().map_err(failed)?;
            println!("{}", describe(&s));
        }
        Verb::Watch { every } => {
            while !stepdrive_runtime::poll::termination_requested() {
                let s = axis.status().map_err(failed)?;
                println!(
                    "t {:.4} s  {}  θ {:.6} rad  ω {:.4} rad/s  θ_d − θ {:.2e} rad",
                    s.t_s,
                    AxisState::from_u32(s.state).map_or("?", |x| x.name()),
                    s.theta_rad,
                    s.omega_rad_s,
                    s.following_error_rad
                );
                std::thread::sleep(Duration::from_secs_f64(every));
            }
        }
        Verb::Enable => {
            axis.enable().map_err(failed)?;
            println!("enabled: Operation enabled");
        }
        Verb::Disable => {
            axis.disable().map_err(failed)?;
            println!("disabled: Switch on disabled");
        }
        Verb::QuickStop => {
            axis.quick_stop().map_err(failed)?;
            println!("quick stop: Quick stop active");
        }
        Verb::Reset => {
            let ack = axis.reset().map_err(failed)?;
            let state = AxisState::from_u32(ack.state).map_or("?", |s| s.name());
            println!("fault reset: {state}");
        }
        Verb::Move {
            to,
            relative,
            after_current,
            limits,
            wait,
            timeout,
        } => {
            let mut flags = 0;
            if relative {
                flags |= request_flags::RELATIVE;
            }
            if after_current {
                flags |= request_flags::AFTER_CURRENT;
            }
            let mv = axis.move_with(to, limits.limits(), flags).map_err(failed)?;
            println!("move taken (seq {})", mv.seq);
            if wait {
                let started = Instant::now();
                let s = match axis.wait_target_reached(&mv, timeout) {
                    Err(ClientError::Interrupted { .. }) => {
                        return Err(halted(&mut [(&mut axis, a.axis)], mv.seq))
                    }
                    r => r.map_err(failed)?,
                };
                println!(
                    "target {:.6} rad reached in {:.3} s: θ {:.6} rad, θ_d − θ {:.2e} rad",
                    s.target_rad,
                    started.elapsed().as_secs_f64(),
                    s.theta_rad,
                    s.following_error_rad
                );
            }
        }
        Verb::MoveTogether { .. } | Verb::StreamTogether { .. } => {
            unreachable!("handled before an axis is connected")
        }
        Verb::Jog {
            velocity,
            limits,
            duration,
        } => {
            let taken = axis.jog(velocity, limits.limits()).map_err(failed)?;
            println!("jogging at {velocity} rad/s");
            hold_jog(&mut axis, &taken, limits.limits(), duration)?;
        }
        Verb::Stop { limits } => {
            axis.stop(limits.limits()).map_err(failed)?;
            println!("stopping");
        }
        Verb::Latency { count, priority } => {
            stepdrive_client::realtime_priority(priority).map_err(failed)?;
            command_latency(&mut axis, count)?
        }
        Verb::Flood {
            rate,
            seconds,
            moves,
            spin,
        } => {
            let kind = if moves {
                RequestKind::Move
            } else {
                RequestKind::Status
            };
            let f = axis
                .flood(kind, 1e-6, rate, seconds, spin)
                .map_err(failed)?;
            println!(
                "{} {} commands tried in {:.1} s ({rate} /s): {} taken, {} refused by the axis ({} of them more than one tick applies), {} refused to this client by the service (it holds 4 of a client's requests), {} unanswered at the end",
                f.tried,
                kind.name(),
                seconds.as_secs_f64(),
                f.taken,
                f.refused,
                f.too_many,
                f.refused_by_service,
                f.unanswered
            );
        }
        Verb::SetPosition { position } => {
            axis.set_position(position).map_err(failed)?;
            println!("the present position is {position} rad");
        }
        Verb::Stream {
            file,
            lead,
            priority,
        } => {
            stepdrive_client::realtime_priority(priority).map_err(failed)?;
            let text = std::fs::read_to_string(&file)
                .with_context(|| format!("cannot read the stream file {}", file.display()))?;
            let rows = parse_stream(&text).with_context(|| format!("{}", file.display()))?;
            stream_rows(&mut axis, &rows, lead)?;
        }
    }
    Ok(())
}

/// `axis move-together`: the group's parts, each answered on the tick the move left.
/// `timeout`: wait that long for every axis to arrive (`None`: do not wait).
fn move_together(
    mut group: Group,
    axes: &[u32],
    targets: &[f64],
    timeout: Option<Duration>,
) -> Result<()> {
    let mv = group.move_together(targets).map_err(failed)?;
    for (axis, ack) in axes.iter().zip(&mv.acks) {
        println!(
            "axis {axis}: coordinated move to {:.6} rad taken (seq {}) at t = {:.4} s",
            ack.request.target_rad, mv.seq, ack.t_s
        );
    }
    let Some(timeout) = timeout else {
        return Ok(());
    };
    let started = Instant::now();
    let arrived = match group.wait_arrived(&mv, timeout) {
        Err(ClientError::Interrupted { .. }) => {
            let mut each: Vec<(&mut Axis, u32)> = group
                .axes_mut()
                .iter_mut()
                .zip(axes.iter().copied())
                .collect();
            return Err(halted(&mut each, mv.seq));
        }
        r => r.map_err(failed)?,
    };
    for (axis, s) in axes.iter().zip(&arrived) {
        println!(
            "axis {axis}: target {:.6} rad reached: θ {:.6} rad, θ_d − θ {:.2e} rad, contour error peak {:.2e} rad",
            s.target_rad, s.theta_rad, s.following_error_rad, s.contour_rad
        );
    }
    println!(
        "all {} axes reached their targets within {:.3} s",
        axes.len(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Ctrl-C during a wait: each axis whose newest command is still `seq` (the motion this
/// command started) is halted at its move limits; the exit is 130, and the headline says
/// where each stood.
fn halted(axes: &mut [(&mut Axis, u32)], seq: u64) -> anyhow::Error {
    let mut halting = Vec::new();
    let mut said = Vec::new();
    for (k, (axis, index)) in axes.iter_mut().enumerate() {
        match axis.halt_if_still(seq) {
            Ok(Some(_)) => halting.push(k),
            Ok(None) => said.push(format!(
                "axis {index}: another command had taken it over, left alone"
            )),
            Err(e) => said.push(format!("axis {index}: could not halt it: {e}")),
        }
    }
    // Where each halted axis came to rest: its setpoint at rest, within a bound far above
    // any stop at the move limits.
    let deadline = Instant::now() + Duration::from_secs(5);
    for k in halting {
        let (axis, index) = &mut axes[k];
        let mut last = None;
        while Instant::now() < deadline {
            match axis.status() {
                Ok(s) if s.omega_d_rad_s == 0.0 => {
                    last = Some((s, true));
                    break;
                }
                Ok(s) => last = Some((s, false)),
                Err(_) => break,
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        said.push(match last {
            Some((s, true)) => format!(
                "axis {index} halted, at rest at θ {:.6} rad (a stop at its move limits)",
                s.theta_rad
            ),
            Some((s, false)) => format!(
                "axis {index} halting, still at ω {:.4} rad/s at θ {:.6} rad after 5 s",
                s.omega_rad_s, s.theta_rad
            ),
            None => format!("axis {index} halting; no status since"),
        });
    }
    Exit {
        code: Outcome::Interrupted.exit_code(),
        headline: format!("interrupted: {}", said.join("; ")),
    }
    .into()
}

/// How often a held jog is renewed: well inside the axis's `jog_timeout_s` (0.5 s by
/// default), so that a client held off the CPU for a while keeps its jog.
const RENEW_EVERY: Duration = Duration::from_millis(100);

/// A jog lasts while its command runs: the axis quick-stops a jog whose client stops
/// renewing it, so this holds the jog (renewing it) until Ctrl-C or `duration`, then stops
/// the axis (a deceleration at the jog's limits). Exit 3 if the axis faults. The jog has
/// ended only by a status of a tick after the jog's (`taken`'s): a remote status is
/// relayed at the gateway's rate and one from before the jog still says "hold".
fn hold_jog(
    axis: &mut Axis,
    taken: &AxisAck,
    limits: Limits,
    duration: Option<Duration>,
) -> Result<()> {
    println!("the jog lasts while this command runs; Ctrl-C stops it");
    let started = Instant::now();
    while !stepdrive_runtime::poll::termination_requested()
        && duration.is_none_or(|d| started.elapsed() < d)
    {
        let ack = axis.renew().map_err(failed)?;
        let s = axis.status().map_err(failed)?;
        stepdrive_client::faulted(&s).map_err(failed)?;
        if s.tick > taken.tick && AxisMode::from_u32(s.mode) != Some(AxisMode::ProfileVelocity) {
            // Stopped by another command, a quick stop or its soft limit: nothing to hold.
            let state = AxisState::from_u32(ack.state).map_or("?", |x| x.name());
            anyhow::bail!(
                "the jog ended: the axis is in {state}, mode {}",
                AxisMode::from_u32(s.mode).map_or("?", |m| m.name())
            );
        }
        std::thread::sleep(RENEW_EVERY);
    }
    axis.stop(limits).map_err(failed)?;
    println!("stopping");
    Ok(())
}

/// Sends each row when the axis is ready for it (paced by the axis's stream time, one
/// lead ahead: [`stepdrive_client::Stream::pace`]), then ends the stream.
fn stream_rows(
    axis: &mut Axis,
    rows: &[stepdrive_shared::axis::StreamRow],
    lead: Option<f64>,
) -> Result<()> {
    let mut stream = axis.stream(lead).map_err(failed)?;
    let started = Instant::now();
    let played = (|| {
        for row in rows {
            stream.pace(row.t_s)?;
            stream.followed()?;
            stream.push(row.t_s, row.theta_rad, row.omega_rad_s, row.torque_ff_nm)?;
        }
        stream.played_out()?;
        stream.followed()
    })();
    let sent = stream.sent();
    let dry = stream.ran_dry();
    if let Err(e) = played {
        // The stream this command started ends here: the axis brakes to a hold (a stream
        // left to run dry would be quick-stopped by its watchdog).
        let ended = stream.end();
        return Err(stream_failed(e, sent, dry, ended.err()));
    }
    stream.end().map_err(failed)?;
    println!(
        "{sent} points streamed in {:.3} s",
        started.elapsed().as_secs_f64()
    );
    if dry {
        println!("warning: the stream ran dry at times (STREAM_UNDERRUN): the axis carried its last point on at its speed until the next came");
    }
    Ok(())
}

/// A stream that failed after `sent` points, ended (or not: `end_failed`) by this command;
/// `dry`: it ran dry on the way (its points came later than its lead: the likelier cause of
/// a path the axis could not follow than the path itself).
fn stream_failed(
    e: ClientError,
    sent: u64,
    dry: bool,
    end_failed: Option<ClientError>,
) -> anyhow::Error {
    let ended = match end_failed {
        None => "the stream was ended: the axis brakes to a hold".to_string(),
        Some(f) => format!(
            "the stream could not be ended ({f}): the axis's stream watchdog quick-stops it"
        ),
    };
    let e = failed(e);
    let (code, headline) = match e.downcast_ref::<Exit>() {
        Some(x) => (x.code, x.headline.clone()),
        None => (1, e.to_string()),
    };
    let dry = if dry {
        "; it ran dry on the way (STREAM_UNDERRUN: points came later than the stream's lead, --lead)"
    } else {
        ""
    };
    Exit {
        code,
        headline: format!("{headline} (after {sent} points{dry}; {ended})"),
    }
    .into()
}

/// `axis stream-together`: every row's positions, paced as one stream; then each axis's
/// stream clock (its time less the stream time it plays: one origin, one figure).
fn stream_together(mut group: Group, rows: &[Vec<f64>], lead: Option<f64>) -> Result<()> {
    let indices = group.indices().to_vec();
    let mut stream = group.stream(lead).map_err(failed)?;
    let started = Instant::now();
    let mut sent = 0;
    let played = (|| {
        for row in rows {
            stream.pace(row[0])?;
            stream.followed()?;
            stream.push(row[0], &row[1..])?;
            sent += 1;
        }
        stream.played_out()?;
        stream.followed()
    })();
    let dry = stream.ran_dry();
    if let Err(e) = played {
        let ended = stream.end();
        return Err(stream_failed(e, sent, dry, ended.err()));
    }
    let offsets: Vec<Option<f64>> = stream
        .last_statuses()
        .iter()
        .map(|s| s.map(|s| s.t_s - s.stream_time_s))
        .collect();
    stream.end().map_err(failed)?;
    println!(
        "{} points on {} axes streamed in {:.3} s",
        rows.len(),
        indices.len(),
        started.elapsed().as_secs_f64()
    );
    for (axis, offset) in indices.iter().zip(offsets) {
        match offset {
            Some(o) => println!("axis {axis}: stack time − stream time played {o:.6} s"),
            None => println!("axis {axis}: no status read while streaming"),
        }
    }
    if dry {
        println!("warning: the stream ran dry at times (STREAM_UNDERRUN) on an axis: it carried its last point on at its speed until the next came");
    }
    Ok(())
}

/// `watch --every`: 1 ms … 1 h.
fn watch_period(s: &str) -> Result<f64, String> {
    crate::options::number_within(s, 1e-3, 3600.0, false, "seconds")
}

/// A flood's rate, commands/s.
fn flood_rate(s: &str) -> Result<f64, String> {
    crate::options::number_within(s, 1.0, 1e6, false, "commands per second")
}

/// See [`Verb::Latency`].
fn command_latency(axis: &mut Axis, count: u32) -> Result<()> {
    let s = axis.status().map_err(failed)?;
    if s.axis_state() != Some(AxisState::OperationEnabled) {
        anyhow::bail!("the latency measurement moves the axis by ±1 µrad: enable it first");
    }
    // Through a gateway the two ends' clocks are different hosts' (or at least the
    // acknowledgement's timestamp is the stack's): the round trip is timed here instead.
    let remote = axis.endpoint().is_some();
    let mut us = Vec::with_capacity(count as usize);
    for i in 0..count {
        if stepdrive_runtime::poll::termination_requested() {
            break;
        }
        let delta = if i % 2 == 0 { 1e-6 } else { -1e-6 };
        let sent = Instant::now();
        let mv = axis
            .move_with(delta, Limits::default(), request_flags::RELATIVE)
            .map_err(failed)?;
        let ns = if remote {
            sent.elapsed().as_nanos() as u64
        } else {
            mv.ack
                .publish_time_ns
                .saturating_sub(mv.ack.request.publish_time_ns)
        };
        us.push(ns as f64 * 1e-3);
        // Commands a little over a tick apart: each meets a position loop waiting for its
        // next tick at a different phase.
        std::thread::sleep(Duration::from_micros(700));
    }
    if us.is_empty() {
        anyhow::bail!("interrupted before the first command");
    }
    us.sort_by(f64::total_cmp);
    let at = |q: f64| us[((us.len() - 1) as f64 * q).round() as usize];
    let what = if remote {
        "command sent → its acknowledgement back through the gateway (round trip)"
    } else {
        "command published → first setpoint carrying it"
    };
    println!(
        "{what}, {} commands: p50 {:.1} µs, p90 {:.1} µs, p99 {:.1} µs, max {:.1} µs",
        us.len(),
        at(0.5),
        at(0.9),
        at(0.99),
        at(1.0)
    );
    Ok(())
}
