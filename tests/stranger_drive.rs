//! The stack against a drive it did not write: `tests/stranger-drive/` was written from
//! `docs/drive-protocol.md`, the README and the paper's notes (now `docs/paper.md`) alone
//! (no line of the host, the codec or the emulated drive read), with its own codec, CRC,
//! calibration (400 000 counts per revolution, 153 µA per count about 31 744, 7 mV per bus
//! count), alignment and motor model. Its questions about the spec are in its
//! SPEC-QUESTIONS.md. If these runs pass, a stranger could build the other side from the
//! document.

use crate::common::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use stranger_drive::{serve, DriveOptions, DriveStats};

/// Runs the stranger drive at 2 kHz on a free loopback port while `run` uses it; returns
/// what `run` returned and the drive's counters.
fn against_the_stranger<T>(options: DriveOptions, run: impl FnOnce(&str) -> T) -> (T, DriveStats) {
    let listen = format!("127.0.0.1:{}", free_udp_port());
    let options = DriveOptions {
        listen: listen.clone(),
        rate_hz: 2000,
        ..options
    };
    let stop = Arc::new(AtomicBool::new(false));
    let drive = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || serve(&options, &stop))
    };
    // The socket is bound within a moment; the host retries its HELLO meanwhile.
    std::thread::sleep(Duration::from_millis(50));
    let out = run(&listen);
    stop.store(true, Ordering::Relaxed);
    let stats = drive
        .join()
        .expect("the stranger drive's thread")
        .expect("the stranger drive ran");
    (out, stats)
}

fn methods_run(
    scenario: &std::path::Path,
    inst: &str,
    json: &std::path::Path,
    drive: &str,
    methods: &str,
) -> std::process::Output {
    let mut args = hardware_args_with(scenario, inst, json, methods);
    args.extend(["--drive", drive]);
    stepdrive(&args)
}

/// Both methods back to back against one stranger-drive process (two sessions, each
/// aligned by the drive), at their figures: the baseline at its microstepping error, the
/// proposed method far below it.
#[test]
fn both_methods_run_against_a_drive_written_from_the_spec_alone() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("stranger");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("stranger");
    let (out, stats) = against_the_stranger(DriveOptions::default(), |drive| {
        methods_run(&scenario, &inst, &json, drive, "proposed,lyapunov")
    });
    assert!(
        out.status.success(),
        "{}\n{}\ndrive: {stats:?}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let doc = read_json(&json);
    let expected = num(&doc, "microstepping_expected_cruise_error_rad");
    let lyapunov = run_of(&doc, "lyapunov");
    let cruise = num(lyapunov, "cruise_max_abs_error_rad");
    assert!(
        cruise > 0.8 * expected && cruise < 1.5 * expected,
        "{lyapunov}"
    );
    let proposed = run_of(&doc, "proposed");
    assert!(
        num(proposed, "cruise_max_abs_error_rad") < 0.2 * expected,
        "{proposed}"
    );
    for run in [proposed, lyapunov] {
        assert_eq!(num(run, "fault_samples"), 0.0, "{run}");
        assert_eq!(run["timing"]["crc_errors"].as_u64(), Some(0), "{run}");
    }
    assert!(processes_with(&inst).is_empty());
}

/// 1 % of the stranger's SAMPLEs dropped at random: counted lost by the host, and the
/// proposed method's cruise error within 2× of the loss-free run's.
#[test]
fn a_lossy_link_to_the_stranger_drive_costs_nothing() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("strangerlossy");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let mut cruise = Vec::new();
    for (name, drop_pct) in [("clean", 0.0), ("lossy", 1.0)] {
        let json = dir.path(&format!("{name}.json"));
        let inst = instance(&format!("stranger{name}"));
        let options = DriveOptions {
            drop_pct,
            ..DriveOptions::default()
        };
        let (out, stats) = against_the_stranger(options, |drive| {
            methods_run(&scenario, &inst, &json, drive, "proposed")
        });
        assert!(
            out.status.success(),
            "{name}: {}\ndrive: {stats:?}",
            String::from_utf8_lossy(&out.stderr)
        );
        let doc = read_json(&json);
        let run = run_of(&doc, "proposed");
        let lost = run["timing"]["frames_lost"].as_u64().expect("frames_lost");
        if drop_pct > 0.0 {
            assert!(lost > 0, "{name}: nothing lost: {run}");
        }
        cruise.push(num(run, "cruise_max_abs_error_rad"));
    }
    // 1.5× at 20 kHz with real-time priorities (README); 2× here, where the test shares the
    // CI machine without them (before the sequence-gap observer: 15×).
    assert!(cruise[1] < 2.0 * cruise[0], "clean → lossy: {cruise:?}");
}

/// Issue 24: the stranger drive with phase A's motor leads swapped. Its shunt reads +I
/// holding, so the held-current check passes; the phase-B step (docs/drive-protocol.md §7
/// step 4) sees the rotor turn a quarter electrical period the wrong way and refuses the
/// drive before the run, exit 5. (Before: both methods ran away, STEPPED OUT, exit 4.)
#[test]
fn a_stranger_drive_with_phase_a_swapped_is_refused_before_the_run() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("strangerswapped");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("strangerswapped");
    let options = DriveOptions {
        swap_phase_a: true,
        ..DriveOptions::default()
    };
    let (out, stats) = against_the_stranger(options, |drive| {
        methods_run(&scenario, &inst, &json, drive, "proposed")
    });
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(5), "{err}\ndrive: {stats:?}");
    assert!(err.contains("turned its rotor -0.03"), "{err}");
    assert!(processes_with(&inst).is_empty());
}
