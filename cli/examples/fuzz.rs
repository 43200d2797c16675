//! Long-run fuzzing of everything that parses bytes from outside the stack, without the
//! stack: the frame decoder, the COBS deframer, the bridge's core (CONFIG, SAMPLE, fault
//! reports, ...) and the emulated drive (COMMAND, PLAN, CONTROL, HELLO), and the scenario
//! loader. Inputs come from a seeded RNG: random bytes, valid frames of every kind, and
//! valid frames changed with their CRC made to match (consistent liars); byte streams cut
//! into random chunks; the default scenario's TOML with lines dropped, repeated and given
//! extreme values.
//!
//! Checks, besides "no panic": an accepted frame re-encodes to exactly its bytes; the bridge
//! publishes indices only forwards and only finite states; the drive never applies the
//! out-of-range duty; an accepted scenario can run (finite, bounded in samples).
//!
//! ```sh
//! cargo run --release -p stepdrive --example fuzz -- --minutes 10 --seed 1
//! ```

use clap::Parser;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::{Duration, Instant};
use stepdrive_bridge::core::{BridgeCore, CoreSettings};
use stepdrive_bridge::link::EncoderCalibration;
use stepdrive_drive_protocol::transport::Deframer;
use stepdrive_drive_protocol::units::default_config;
use stepdrive_drive_protocol::{
    cobs_encode, decode, encode, reseal, Action, Command, Config, FaultReport, Frame, Message,
    Plan, Sample, MAX_FRAME, MAX_PLAN_ENTRIES,
};
use stepdrive_emulated_drive::emulated_drive;
use stepdrive_shared::scenario::MAX_SAMPLES;
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

#[derive(Parser)]
struct Args {
    /// How long to fuzz, minutes.
    #[arg(long, default_value_t = 1.0)]
    minutes: f64,
    /// RNG seed: the same seed gives the same inputs.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// SplitMix64: small, fast, and the same sequence everywhere for a seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
    fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.next() as u8).collect()
    }
    fn chance(&mut self, one_in: usize) -> bool {
        self.below(one_in) == 0
    }
}

fn random_message(r: &mut Rng) -> Message {
    match r.below(7) {
        0 => Message::Sample(Sample {
            encoder_counts: r.next() as i32,
            adc_a: r.next() as u16,
            adc_b: r.next() as u16,
            adc_bus: r.next() as u16,
            duty_a: r.next() as i16,
            duty_b: r.next() as i16,
            applied_command_seq: r.next() as u32,
            fault_bits: if r.chance(8) { r.next() as u16 } else { 0 },
            status: r.next() as u16,
        }),
        1 => Message::Command(Command {
            answers_sample: r.next() as u32 % 64,
            duty_a: r.next() as i16,
            duty_b: r.next() as i16,
        }),
        2 => Message::Control(match r.below(3) {
            0 => Action::Enable,
            1 => Action::Disable,
            _ => Action::Reset,
        }),
        3 => Message::FaultReport(FaultReport {
            fault_bits: r.next() as u16,
            at_sample: r.next() as u32,
        }),
        4 => Message::Config(if r.chance(2) {
            default_config(20_000.0, r.next() as u16, r.next() as u16 % 300)
        } else {
            Config {
                sample_rate_hz: r.next() as u32,
                counts_per_rev: r.next() as u32,
                current_ua_per_count: r.next() as u32,
                current_zero_count: r.next() as u16,
                bus_uv_per_count: r.next() as u32,
                watchdog_periods: r.next() as u16,
                encoder_direction: r.next() as i8,
                plan_capacity: r.next() as u16,
                align_current_ma: 1000,
                align_ms: 300,
                reserved: [0; 1],
            }
        }),
        5 => Message::Hello,
        _ => {
            let count = 1 + r.below(MAX_PLAN_ENTRIES);
            let mut duties = [[0i16; 2]; MAX_PLAN_ENTRIES];
            for d in duties.iter_mut().take(count) {
                *d = [r.next() as i16, r.next() as i16];
            }
            Message::Plan(Plan {
                answers_sample: r.next() as u32 % 64,
                count: count as u16,
                duties,
            })
        }
    }
}

/// One frame's bytes: valid, or valid then changed (CRC matched or not), or random.
fn random_frame_bytes(r: &mut Rng, seq: u32) -> Vec<u8> {
    if r.chance(8) {
        let n = r.below(MAX_FRAME + 8);
        return r.bytes(n);
    }
    let frame = Frame {
        seq,
        timestamp_ns: r.next(),
        message: random_message(r),
    };
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(&frame, &mut buf);
    let mut bytes = buf[..n].to_vec();
    if r.chance(3) {
        for _ in 0..1 + r.below(4) {
            let at = r.below(bytes.len());
            bytes[at] = r.next() as u8;
        }
        if r.chance(4) {
            let cut = r.below(bytes.len() + 1);
            bytes.truncate(cut);
        }
        if r.chance(2) {
            reseal(&mut bytes);
        }
    }
    bytes
}

#[derive(Default)]
struct Tally {
    inputs: u64,
    accepted: u64,
}

fn check(cond: bool, what: &str) {
    if !cond {
        panic!("{what}");
    }
}

fn fuzz_decoder(r: &mut Rng, t: &mut Tally) {
    let seq = r.next() as u32;
    let bytes = random_frame_bytes(r, seq);
    t.inputs += 1;
    if let Ok(f) = decode(&bytes) {
        t.accepted += 1;
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(&f, &mut buf);
        check(
            buf[..n] == bytes[..],
            "an accepted frame re-encodes differently",
        );
    }
}

fn fuzz_deframer(r: &mut Rng, t: &mut Tally) {
    let mut stream = Vec::new();
    for _ in 0..1 + r.below(8) {
        if r.chance(5) {
            let n = r.below(300);
            stream.extend(r.bytes(n));
        } else {
            let raw = random_frame_bytes(r, 1);
            let mut enc = vec![0u8; 2 * raw.len() + 2];
            let n = cobs_encode(&raw, &mut enc);
            stream.extend_from_slice(&enc[..n]);
        }
    }
    let mut d = Deframer::default();
    let mut out = [0u8; MAX_FRAME];
    let mut at = 0;
    while at < stream.len() {
        let end = (at + 1 + r.below(400)).min(stream.len());
        d.push(&stream[at..end]);
        at = end;
        while let Some(n) = d.next_frame(&mut out) {
            t.inputs += 1;
            t.accepted += u64::from(decode(&out[..n]).is_ok());
        }
    }
}

fn fuzz_bridge(r: &mut Rng, t: &mut Tally) {
    let mut core = BridgeCore::new(CoreSettings {
        sample_hz: 20_000.0,
        samples: 1_000,
        silence_periods: 1 + r.below(50) as u32,
        plan_every: 1 + r.below(20) as u32,
        observer_hz: 400.0,
        calibration: EncoderCalibration::default(),
        resistance_ohm: 14.8,
        rotor_teeth: 50.0,
    });
    let mut stats = StatsReport::default();
    let mut last: Option<u64> = None;
    for k in 0..1 + r.below(300) as u64 {
        let bytes = random_frame_bytes(r, k as u32 + 1);
        let now = (k + 1) * 50_000;
        t.inputs += 1;
        core.on_frame(&bytes, now, &mut stats);
        // The start-up's checks read the same frames: a refusal is an answer, never a panic.
        let _ = core.startup(now, r.chance(2), &mut |_| {});
        if r.chance(10) {
            core.on_quiet(now, now);
        }
        if let Some((st, rx)) = core.take_sample(&mut stats) {
            t.accepted += 1;
            let st = core.publish(st, rx);
            check(
                last.is_none_or(|l| st.seq > l),
                "an index published twice or backwards",
            );
            last = Some(st.seq);
            check(
                [
                    st.theta_rad,
                    st.omega_rad_s,
                    st.i_a_a,
                    st.i_b_a,
                    st.bus_voltage_v,
                ]
                .iter()
                .all(|v| v.is_finite()),
                "a non-finite state",
            );
        }
    }
}

fn fuzz_drive(r: &mut Rng, t: &mut Tally, s: &Scenario) {
    let mut d = emulated_drive(s, 1 + r.below(200) as u16, r.below(257) as u16);
    for k in 0..1 + r.below(200) as u32 {
        for _ in 0..r.below(3) {
            let bytes = random_frame_bytes(r, k + 1);
            t.inputs += 1;
            t.accepted += u64::from(d.on_frame(&bytes).is_some());
        }
        d.run_period(k);
        if let Message::Sample(sample) = d.sample_frame(0).message {
            check(
                sample.duty_a != i16::MIN && sample.duty_b != i16::MIN,
                "the drive applied the out-of-range duty",
            );
        }
    }
}

const EXTREMES: [&str; 10] = [
    "1e300",
    "-1e300",
    "1e-300",
    "nan",
    "inf",
    "-0.0",
    "0",
    "18446744073709551615",
    "\"x\"",
    "[]",
];

fn fuzz_scenario(r: &mut Rng, t: &mut Tally, base: &str) {
    let mut lines: Vec<String> = base.lines().map(str::to_string).collect();
    for _ in 0..1 + r.below(4) {
        let i = r.below(lines.len());
        match r.below(4) {
            0 => {
                lines.remove(i);
            }
            1 => {
                let copy = lines[i].clone();
                lines.insert(i, copy);
            }
            2 => {
                if let Some((key, _)) = lines[i].split_once(" = ") {
                    lines[i] = format!("{key} = {}", EXTREMES[r.below(EXTREMES.len())]);
                }
            }
            _ => {
                if let Some((key, _)) = lines[i].split_once(" = ") {
                    lines[i] = format!("{key} = {}", f64::from_bits(r.next()));
                }
            }
        }
    }
    t.inputs += 1;
    if let Ok(s) = Scenario::from_toml_str(&lines.join("\n")) {
        t.accepted += 1;
        check(
            s.sample_count() <= MAX_SAMPLES,
            "an accepted scenario too long to run",
        );
        check(
            s.duration_s().is_finite() && s.sample_period_ns() > 0,
            "an accepted scenario that cannot run",
        );
    }
}

fn main() {
    let args = Args::parse();
    let mut rng = Rng(args.seed);
    let budget = Duration::from_secs_f64(args.minutes.max(0.0) * 60.0);
    let started = Instant::now();
    let scenario = Scenario::default();
    let base = scenario.to_toml_string().unwrap_or_default();
    let names = [
        "decoder",
        "deframer",
        "bridge core",
        "emulated drive",
        "scenario loader",
    ];
    let mut tallies: [Tally; 5] = Default::default();
    let mut rounds: u64 = 0;
    // The hook would print every caught panic; we report the first one ourselves.
    std::panic::set_hook(Box::new(|_| {}));
    while started.elapsed() < budget {
        let target = (rounds % 5) as usize;
        let state = rng.0;
        let t = &mut tallies[target];
        let outcome = catch_unwind(AssertUnwindSafe(|| match target {
            0 => fuzz_decoder(&mut rng, t),
            1 => fuzz_deframer(&mut rng, t),
            2 => fuzz_bridge(&mut rng, t),
            3 => fuzz_drive(&mut rng, t, &scenario),
            _ => fuzz_scenario(&mut rng, t, &base),
        }));
        if let Err(panic) = outcome {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic".to_string());
            eprintln!(
                "FAILED: {} after {rounds} rounds: {what} (rerun: --seed {}, round state {state:#x})",
                names[target], args.seed
            );
            std::process::exit(1);
        }
        rounds += 1;
    }
    let secs = started.elapsed().as_secs_f64();
    println!(
        "fuzzed {secs:.0} s, seed {}, {rounds} rounds, no panic, every check held:",
        args.seed
    );
    for (name, t) in names.iter().zip(&tallies) {
        println!(
            "  {name:<16} {:>12} inputs ({:.0}/s), {:>10} accepted",
            t.inputs,
            t.inputs as f64 / secs,
            t.accepted
        );
    }
}
