use std::sync::atomic::AtomicBool;

use stranger_drive::{serve, DriveOptions};

const HELP: &str =
    "stranger-drive: a simulated stepper drive speaking stepdrive's wire protocol v3.1 over UDP

options:
  --listen ADDR:PORT        (default 127.0.0.1:47701)
  --rate HZ                 sample rate (default 20000)
  --load NM                 constant load torque (default 0.01)
  --bus-v V                 bus voltage (default 24)
  --plan-capacity N         PLAN entries kept, 0..1024 (default 800 = the watchdog)
  --watchdog-periods N      (default 800)
  --align-ma MA             (default 800)
  --align-ms MS             (default 250; 0: no alignment)
  --counts-per-rev N        (default 400000)
  --reverse-encoder         announce direction -1 and count the other way
  --initial-angle RAD       where the rotor starts (default 0)
  --overcurrent-a A         phase current limit (default 4)
  --substeps N              RK4 sub-steps per period (default 4)
  --drop-pct P              drop P % of SAMPLEs of a run
  --corrupt-pct P           flip one bit of P % of SAMPLEs of a run
  --seed N                  PRNG seed
  --dropout-at N            do not send SAMPLEs N..N+M of the run
  --dropout-samples M
  --stop-after N            stop after N periods
  --spin-us US              spin this long before each deadline (default 60)
  --verbose                 print the rotor state once a second
  --swap-phase-a            fault injection: phase A's motor leads swapped";

fn parse<T: std::str::FromStr>(name: &str, v: Option<String>) -> Result<T, String> {
    let v = v.ok_or_else(|| format!("{name} needs a value"))?;
    v.parse::<T>()
        .map_err(|_| format!("{name}: cannot parse '{v}'"))
}

fn options() -> Result<DriveOptions, String> {
    let mut o = DriveOptions::default();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--listen" => o.listen = parse("--listen", args.next())?,
            "--rate" => o.rate_hz = parse("--rate", args.next())?,
            "--load" => o.load_nm = parse("--load", args.next())?,
            "--bus-v" => o.bus_v = parse("--bus-v", args.next())?,
            "--plan-capacity" => o.plan_capacity = parse("--plan-capacity", args.next())?,
            "--watchdog-periods" => o.watchdog_periods = parse("--watchdog-periods", args.next())?,
            "--align-ma" => o.align_ma = parse("--align-ma", args.next())?,
            "--align-ms" => o.align_ms = parse("--align-ms", args.next())?,
            "--counts-per-rev" => o.counts_per_rev = parse("--counts-per-rev", args.next())?,
            "--reverse-encoder" => o.reverse_encoder = true,
            "--initial-angle" => o.initial_angle = parse("--initial-angle", args.next())?,
            "--overcurrent-a" => o.overcurrent_a = parse("--overcurrent-a", args.next())?,
            "--substeps" => o.substeps = parse("--substeps", args.next())?,
            "--drop-pct" => o.drop_pct = parse("--drop-pct", args.next())?,
            "--corrupt-pct" => o.corrupt_pct = parse("--corrupt-pct", args.next())?,
            "--seed" => o.seed = parse("--seed", args.next())?,
            "--dropout-at" => o.dropout_at = Some(parse("--dropout-at", args.next())?),
            "--dropout-samples" => o.dropout_samples = parse("--dropout-samples", args.next())?,
            "--stop-after" => o.stop_after = Some(parse("--stop-after", args.next())?),
            "--spin-us" => o.spin_us = parse("--spin-us", args.next())?,
            "--verbose" => o.verbose = true,
            "--swap-phase-a" => o.swap_phase_a = true,
            "-h" | "--help" => {
                println!("{HELP}");
                std::process::exit(0);
            }
            other => return Err(format!("unknown option '{other}' (--help lists them)")),
        }
    }
    Ok(o)
}

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_sig: i32) {
    STOP.store(true, std::sync::atomic::Ordering::Relaxed);
}

/// SIGINT and SIGTERM set STOP (so the stats are printed), through libc's `signal`,
/// which std links anyway: no dependency.
#[cfg(unix)]
fn install_stop_handler() {
    extern "C" {
        fn signal(sig: i32, handler: extern "C" fn(i32)) -> usize;
    }
    // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
    unsafe {
        signal(2, on_signal);
        signal(15, on_signal);
    }
}

#[cfg(not(unix))]
fn install_stop_handler() {}

fn main() {
    let o = match options() {
        Ok(o) => o,
        Err(e) => {
            eprintln!("stranger-drive: {e}");
            std::process::exit(2);
        }
    };
    install_stop_handler();
    let stop = &STOP;
    eprintln!(
        "stranger-drive: listening on {} at {} Hz, {} counts/rev, plan {}, watchdog {}",
        o.listen, o.rate_hz, o.counts_per_rev, o.plan_capacity, o.watchdog_periods
    );
    match serve(&o, stop) {
        Ok(stats) => {
            println!("stranger-drive stats:\n{stats}");
        }
        Err(e) => {
            eprintln!("stranger-drive: {e}");
            std::process::exit(1);
        }
    }
}
