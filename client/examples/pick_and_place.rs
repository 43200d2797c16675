//! A pick-and-place cycle: the axis moves between a pick and a place position with a dwell
//! at each, for a number of cycles, and prints each cycle's time and peak following error.
//!
//! ```sh
//! cargo run --release -- serve &                       # a stack, its axis disabled
//! cargo run --release -p stepdrive-client --example pick_and_place -- 5
//! ```
//!
//! Arguments: cycles (default 5), the instance (default `stepdrive`).

use std::process::ExitCode;
use std::time::{Duration, Instant};
use stepdrive_client::{Axis, AxisState, ClientError, Limits};

const PICK_RAD: f64 = 0.0;
const PLACE_RAD: f64 = std::f64::consts::TAU;
const DWELL: Duration = Duration::from_millis(100);

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let cycles = match args.next().map(|a| a.parse::<u32>()) {
        None => 5,
        Some(Ok(n)) if n > 0 => n,
        Some(_) => {
            eprintln!("usage: pick_and_place [CYCLES > 0] [INSTANCE]");
            return ExitCode::from(2);
        }
    };
    let instance = args.next().unwrap_or_else(|| "stepdrive".to_string());
    match run(&instance, cycles) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("pick-and-place stopped: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(instance: &str, cycles: u32) -> Result<(), ClientError> {
    let mut axis = Axis::connect(instance, 0)?;
    axis.enable()?;
    let limits = Limits {
        v: Some(13.13),
        a: Some(100.0),
        j: Some(5000.0),
    };
    println!("cycle  time [s]  peak following error [rad]");
    for cycle in 1..=cycles {
        let started = Instant::now();
        let mut peak: f64 = 0.0;
        for target in [PLACE_RAD, PICK_RAD] {
            peak = peak.max(move_and_watch(&mut axis, target, limits)?);
            std::thread::sleep(DWELL);
        }
        println!(
            "{cycle:>5}  {:>8.3}  {peak:.3e}",
            started.elapsed().as_secs_f64()
        );
    }
    axis.disable()?;
    Ok(())
}

/// Moves to `target` and waits there, watching the status: returns the peak |following
/// error| seen (the status topic at the position loop's rate, read as it comes).
fn move_and_watch(axis: &mut Axis, target: f64, limits: Limits) -> Result<f64, ClientError> {
    let mv = axis.move_to(target, limits)?;
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut peak: f64 = 0.0;
    loop {
        let s = axis.status()?;
        peak = peak.max(s.following_error_rad.abs());
        if s.axis_state() == Some(AxisState::Fault) {
            // The client's own wait names the fault.
            return axis.wait_target_reached(&mv, Duration::ZERO).map(|_| peak);
        }
        if s.last_seq == mv.seq && s.target_reached() {
            return Ok(peak);
        }
        if Instant::now() >= deadline {
            return Err(ClientError::Timeout {
                what: format!("the move to {target} rad"),
                timeout: Duration::from_secs(10),
            });
        }
        std::thread::sleep(Duration::from_micros(200));
    }
}
