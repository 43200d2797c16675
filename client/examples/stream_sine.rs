//! Cyclic synchronous position from a program: streams θ(t) = θ₀ + A sin 2πft at a point
//! rate, paced by the axis's own clock ([`stepdrive_client::Stream::pace`]), and judges the
//! tracking against the sine's closed form at the stream time the axis plays: the peak and
//! the 99th percentile of |θ − θ_stream| over the statuses seen after the first 0.2 s.
//!
//! ```sh
//! cargo run --release -- serve &                        # a stack, its axis disabled
//! cargo run --release -p stepdrive-client --example stream_sine -- --seconds 5
//! ```
//!
//! Options: `--seconds S` (5), `--rate HZ` (1000), `--amplitude RAD` (2), `--frequency HZ`
//! (1), `--bound RAD` (1e-4: exit 1 above it), `--lead S` (the axis's), `--priority P` (SCHED_FIFO, 10; 0: ordinary,
//! see [`stepdrive_client::realtime_priority`] for why not), `--instance NAME` (stepdrive),
//! `--connect tcp/HOST:PORT` (through a `stepdrive gateway`, from another host: the status
//! comes at the gateway's rate, and the lead defaults to 0.5 s), `--trace 1` (print every judged status beyond the bound: its tick, the stream time, the
//! setpoint's and the rotor's distance from the sine, the warnings).
//! The axis is enabled if it is not; it is left holding at the end of the stream.

use std::f64::consts::TAU;
use std::process::ExitCode;
use stepdrive_client::{Axis, AxisState, AxisStatus, ClientError};

/// The first part of the stream, where the setpoint runs in from rest, is not judged.
const SETTLE_S: f64 = 0.2;

struct Options {
    seconds: f64,
    rate: f64,
    amplitude: f64,
    frequency: f64,
    bound: f64,
    priority: u8,
    lead: Option<f64>,
    instance: String,
    connect: Option<String>,
    trace: bool,
}

fn options() -> Result<Options, String> {
    let mut o = Options {
        seconds: 5.0,
        rate: 1000.0,
        amplitude: 2.0,
        frequency: 1.0,
        bound: 1e-4,
        priority: stepdrive_client::STREAM_PRIORITY,
        lead: None,
        instance: "stepdrive".to_string(),
        connect: None,
        trace: false,
    };
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        let value = args.next().ok_or_else(|| format!("{flag} needs a value"))?;
        let number = || {
            value
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(|| format!("{flag} {value}: a positive number expected"))
        };
        match flag.as_str() {
            "--seconds" => o.seconds = number()?,
            "--rate" => o.rate = number()?,
            "--amplitude" => o.amplitude = number()?,
            "--frequency" => o.frequency = number()?,
            "--bound" => o.bound = number()?,
            "--priority" => {
                o.priority = value
                    .parse::<u8>()
                    .ok()
                    .filter(|p| *p <= 99)
                    .ok_or_else(|| format!("--priority {value}: 0 (SCHED_OTHER) … 99"))?
            }
            "--lead" => o.lead = Some(number()?),
            "--instance" => o.instance = value,
            "--connect" => o.connect = Some(value),
            "--trace" => {
                o.trace = match value.as_str() {
                    "1" => true,
                    "0" => false,
                    _ => return Err(format!("--trace {value}: 0 or 1")),
                }
            }
            other => return Err(format!("unknown option {other}")),
        }
    }
    if !(100.0..=2000.0).contains(&o.rate) {
        return Err(format!("--rate {}: 100 … 2000 Hz", o.rate));
    }
    Ok(o)
}

fn main() -> ExitCode {
    let o = match options() {
        Ok(o) => o,
        Err(e) => {
            eprintln!("stream_sine: {e}\nusage: stream_sine [--seconds S] [--rate HZ] [--amplitude RAD] [--frequency HZ] [--bound RAD] [--lead S] [--priority P] [--instance NAME] [--trace 1]");
            return ExitCode::from(2);
        }
    };
    match run(&o) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("stream_sine stopped: {e}");
            ExitCode::FAILURE
        }
    }
}

/// |θ − θ_stream| of the statuses judged, and the statuses seen with a stream playing.
struct Tracking {
    errors: Vec<f64>,
    seen: usize,
    last_tick: Option<u64>,
    /// The least the stream was buffered ahead of the played time, s.
    least_ahead: f64,
}

impl Tracking {
    fn take(&mut self, s: &AxisStatus, path: impl Fn(f64) -> f64, o: &Options) {
        if self.last_tick == Some(s.tick) || !s.stream_time_s.is_finite() {
            return;
        }
        self.last_tick = Some(s.tick);
        self.seen += 1;
        if s.stream_time_s >= SETTLE_S {
            self.least_ahead = self.least_ahead.min(s.stream_ahead_s);
            let e = (s.theta_rad - path(s.stream_time_s)).abs();
            self.errors.push(e);
            if o.trace && e > o.bound {
                eprintln!(
                    "tick {} stream time {:.5} s, axis time {:.5} s, ahead {:.5} s: θ − θ_stream {:.3e}, θ_d − θ_stream {:.3e}, following error {:.3e} rad, warnings {:#x}",
                    s.tick,
                    s.stream_time_s,
                    s.t_s,
                    s.stream_ahead_s,
                    s.theta_rad - path(s.stream_time_s),
                    s.theta_d_rad - path(s.stream_time_s),
                    s.following_error_rad,
                    s.warning
                );
            }
        }
    }
}

fn run(o: &Options) -> Result<bool, ClientError> {
    stepdrive_client::realtime_priority(o.priority)?;
    let mut axis = match &o.connect {
        Some(endpoint) => Axis::connect_remote(endpoint, &o.instance, 0)?,
        None => Axis::connect(&o.instance, 0)?,
    };
    if axis.status()?.axis_state() != Some(AxisState::OperationEnabled) {
        axis.enable()?;
    }
    let theta0 = axis.status()?.theta_rad;
    let path = |t: f64| theta0 + o.amplitude * (TAU * o.frequency * t).sin();
    let points = (o.seconds * o.rate).round() as u64;
    let mut tracking = Tracking {
        errors: Vec::with_capacity(points as usize * 2),
        seen: 0,
        last_tick: None,
        least_ahead: f64::INFINITY,
    };
    let mut stream = axis.stream(o.lead)?;
    for k in 0..=points {
        let t = k as f64 / o.rate;
        stream.push_paced(t, path(t), None, None)?;
        if let Some(st) = stream.last_status() {
            tracking.take(st, path, o);
        }
    }
    stream.end()?;
    let mut e = tracking.errors;
    if e.is_empty() {
        eprintln!("no status of the stream was seen after {SETTLE_S} s");
        return Ok(false);
    }
    e.sort_by(f64::total_cmp);
    let peak = e[e.len() - 1];
    let p99 = e[(e.len() * 99 / 100).min(e.len() - 1)];
    println!(
        "{points} points at {} Hz: |θ − θ_stream| after {SETTLE_S} s over {} statuses: peak {peak:.3e} rad, p99 {p99:.3e} rad (bound {:.1e}); the stream buffered at least {:.2} ms ahead",
        o.rate,
        e.len(),
        o.bound,
        tracking.least_ahead * 1e3
    );
    Ok(peak <= o.bound)
}
