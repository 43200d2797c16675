//! Every way a run can go wrong, and what it must say: faults exit non-zero with a headline,
//! results survive a dead process or Ctrl-C, a restarted loop rejoins, mismatched processes
//! are refused, nothing is left behind, errors name the party at fault, and bad input is
//! refused before anything runs. Each test is one finding of the reliability issue; each
//! failed on the code before it.

use crate::common::*;
use serde_json::Value;
use std::process::Command;
use std::time::{Duration, Instant};

/// Finding 1: a realtime run whose current loop stops for 200 ms, four times the watchdog
/// (1000 periods, 50 ms; a host that also holds the plant pauses its time, so a stop of
/// barely more than the watchdog may not trip it),
/// loses the motor. It exits 3 with a FAULT headline naming the fault and when it latched,
/// and its results say so. (Before: exit 0.)
#[test]
fn a_run_whose_plant_latched_a_fault_exits_3_with_a_headline() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("fault");
    let scenario = dir.file("short.toml", SHORT);
    let json = dir.path("rt.json");
    let inst = instance("fault");
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "3.0"));
    args.extend(["--json", json.to_str().unwrap()]);
    let mut run = spawn_run(&args);
    wait_for_stack_time(&inst, &mut run, 1.0);
    let pid = pid_of_role(&inst, "current-loop").expect("current loop");
    signal(pid, libc::SIGSTOP);
    std::thread::sleep(Duration::from_millis(200));
    signal(pid, libc::SIGCONT);
    let status = wait_with_timeout(&mut run, Duration::from_secs(60));
    let (out, err) = (stdout_of(&mut run), stderr_of(&mut run));
    assert_eq!(status.code(), Some(3), "{out}\n{err}");
    assert!(
        out.contains("FAULT (exit 3)") && out.contains("COMMAND_TIMEOUT"),
        "{out}"
    );
    assert!(err.contains("FAULT (exit 3)"), "{err}");
    let doc = read_json(&json);
    assert_eq!(doc["outcome"], "fault");
    assert_eq!(doc["exit_code"], 3);
    let r = run_of(&doc, "proposed");
    assert_eq!(r["complete"], true);
    assert!(num(&r["fault"], "sim_time_s") > 0.5, "{r}");
    assert!(num(r, "fault_samples") > 0.0);
    assert!(processes_with(&inst).is_empty());
}

/// Finding 1, hardware: the drive latches an over-current: exit 3, the headline names the
/// drive and its fault. (Before: exit 0.)
#[test]
fn a_drive_fault_exits_3_naming_the_drive() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("drivefault");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("drivefault");
    let listen = format!("127.0.0.1:{}", free_udp_port());
    let mut drive = spawn_logged(
        &[
            &["emulate-drive", "--listen", &listen, "--scenario"][..],
            &[scenario.to_str().unwrap(), "--overcurrent-after", "0.6"][..],
            &ORDINARY_SCHEDULING[..],
        ]
        .concat(),
    );
    let out = hardware_run(&scenario, &inst, &json, &["--drive", &listen]);
    signal(drive.id(), libc::SIGTERM);
    let _ = wait_with_timeout(&mut drive, Duration::from_secs(10));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(3), "{stdout}");
    assert!(
        stdout.contains("the drive latched DRIVE_FAULT: OVERCURRENT"),
        "{stdout}"
    );
    assert_eq!(read_json(&json)["outcome"], "fault");
}

/// Finding 1, the mechanism: a realtime run with real-time priorities lifts RT throttling
/// for the run and puts it back on every exit path, a SIGKILL of the launcher included.
/// (Before: throttling stayed on unless asked, and a killed launcher never restored it.)
#[test]
fn rt_throttling_is_lifted_for_the_run_and_restored_even_after_a_sigkill() {
    let read = rt_runtime_us;
    let Some(before) = rt_throttling_to_check() else {
        return;
    };
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("throttle");
    let scenario = dir.file("short.toml", SHORT);
    let inst = instance("throttle");
    // SCHED_FIFO 1, no spinning, no pinning: gentle on a shared CI machine.
    let mut run = spawn_run(&[
        "run",
        "--mode",
        "realtime",
        "--method",
        "proposed",
        "--duration",
        "30",
        "--scenario",
        scenario.to_str().unwrap(),
        "--instance",
        &inst,
        "--priority",
        "1",
        "--cpus",
        "none",
        "--plant-wait",
        "sleep",
        "--current-wait",
        "sleep",
    ]);
    let lifted = wait_until(Duration::from_secs(30), || read() == Some(-1));
    signal(run.id(), libc::SIGKILL);
    let _ = run.wait();
    assert!(lifted, "RT throttling was not lifted for the run");
    assert!(
        wait_until(Duration::from_secs(5), || read() == Some(before)),
        "RT throttling not restored after the launcher was killed: {:?}",
        read()
    );
    assert!(
        wait_until(Duration::from_secs(5), || processes_with(&inst).is_empty()),
        "orphans left: {:?}",
        processes_with(&inst)
    );

    // Round 3, finding 5: the guard itself killed. Before: throttling stayed lifted (-1)
    // after the run ended with exit 0, and nothing said so. Then the launcher restored it at
    // its end; now (issue 44, item 5) the death is logged at once and a new guard holds the
    // saved value, which it restores when the run is over.
    // On an instance of its own: the killed stack's services can outlive it for a moment,
    // and a plant that counts its dead position loop as a peer starts before the new one
    // (seen in CI: STEPPED OUT at 0.0406 s, the rotor unpowered until the loop came).
    let inst = instance("throttle-guard");
    let mut run = spawn_run(&[
        "run",
        "--mode",
        "realtime",
        "--method",
        "proposed",
        "--duration",
        "2",
        "--scenario",
        scenario.to_str().unwrap(),
        "--instance",
        &inst,
        "--priority",
        "1",
        "--cpus",
        "none",
        "--plant-wait",
        "sleep",
        "--current-wait",
        "sleep",
    ]);
    assert!(
        wait_until(Duration::from_secs(30), || read() == Some(-1)),
        "RT throttling was not lifted for the run"
    );
    let guard = std::process::Command::new("pgrep")
        .args(["-P", &run.id().to_string(), "-f", "rt-throttling-guard"])
        .output()
        .expect("pgrep");
    let pid: u32 = String::from_utf8_lossy(&guard.stdout)
        .trim()
        .parse()
        .expect("the guard's pid");
    signal(pid, libc::SIGKILL);
    let status = wait_with_timeout(&mut run, Duration::from_secs(60));
    let stderr = stderr_of(&mut run);
    assert!(status.success(), "{stderr}");
    assert_eq!(read(), Some(before), "{stderr}");
    assert!(
        stderr.contains("the RT-throttling guard exited with signal: 9"),
        "{stderr}"
    );
    assert!(
        stderr.contains("a new RT-throttling guard holds it"),
        "{stderr}"
    );
}

/// Finding 2: a child's death and Ctrl-C keep what was gathered: the table (marked
/// incomplete) and the JSON (complete: false) are written, with the exit code of the
/// cause. (Before: exit 1 or 130 and nothing but an error line.)
#[test]
fn a_dead_child_or_ctrl_c_keeps_the_results_gathered_so_far() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("partial");
    let scenario = dir.file("long.toml", LONG);
    for (victim, code) in [("current-loop", 5), ("launcher", 130)] {
        let inst = instance(&format!("partial-{code}"));
        let json = dir.path(&format!("{code}.json"));
        let mut run = spawn_run(&[
            "run",
            "--method",
            "proposed",
            "--instance",
            &inst,
            "--scenario",
            scenario.to_str().unwrap(),
            "--json",
            json.to_str().unwrap(),
        ]);
        // A tenth of a second of the stack's time: more than the 1000 samples asserted.
        wait_for_stack_time(&inst, &mut run, 0.1);
        match victim {
            "launcher" => signal(run.id(), libc::SIGINT),
            role => signal(pid_of_role(&inst, role).expect("victim"), libc::SIGKILL),
        }
        let status = wait_with_timeout(&mut run, Duration::from_secs(30));
        let out = stdout_of(&mut run);
        assert_eq!(status.code(), Some(code), "{out}");
        assert!(out.contains("incomplete"), "{out}");
        let doc = read_json(&json);
        assert_eq!(doc["complete"], false, "{doc}");
        assert_eq!(doc["exit_code"], code);
        let r = run_of(&doc, "proposed");
        assert!(num(r, "samples") > 1000.0, "{r}");
        assert!(r["stopped_because"].is_string(), "{r}");
        assert!(
            wait_until(Duration::from_secs(5), || processes_with(&inst).is_empty()),
            "orphans left"
        );
    }
}

/// A hand-started stack of `duration` seconds on the short scenario: the processes, the
/// common arguments.
fn by_hand<'a>(mode: &'a str, inst: &'a str, scenario: &'a str) -> Vec<&'a str> {
    let mut a = vec!["--mode", mode, "--instance", inst, "--scenario", scenario];
    a.extend(ORDINARY_SCHEDULING);
    a
}

/// Finding 3, realtime: in a stack started by hand, a killed current loop trips the plant's
/// watchdog; a new one attaches; `stepdrive reset` clears the fault; control resumes and the
/// run ends as a clean one does (final error), the plant healthy (exit 0). Without the
/// restart, the plant ends faulted and says so (exit 3). (Before: no reset existed, the
/// plant stayed faulted to the end and exited 0.)
#[test]
fn a_restarted_current_loop_rejoins_and_a_reset_clears_the_fault() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("rejoin");
    // Six whole passes: the run ends in the hold, where a clean run's final error is ~0.
    let scenario = dir.file("short.toml", &format!("{SHORT}\n[run]\nduration_s = 4.2\n"));
    let sc = scenario.to_str().unwrap();
    for restart in [true, false] {
        let inst = instance(&format!("rejoin-{restart}"));
        let json = dir.path(&format!("{restart}.json"));
        let common = by_hand("realtime", &inst, sc);
        // A 100 ms watchdog: scheduling noise on a shared CI machine must not trip it.
        let mut plant = spawn_logged(
            &[
                &[
                    "plant",
                    "--wait-subscribers",
                    "3",
                    "--watchdog-periods",
                    "2000",
                ][..],
                &common,
            ]
            .concat(),
        );
        let mut monitor = spawn_run(&[
            "monitor",
            "--instance",
            &inst,
            "--scenario",
            sc,
            "--json",
            json.to_str().unwrap(),
        ]);
        let mut position = spawn_logged(&[&["position-loop"][..], &common].concat());
        let mut current = spawn_logged(&[&["current-loop"][..], &common].concat());
        wait_for_stack_time(&inst, &mut plant, 0.8);
        signal(current.id(), libc::SIGKILL);
        let _ = current.wait();
        // Past the watchdog: outputs off, fault latched.
        std::thread::sleep(Duration::from_millis(300));
        let mut restarted = None;
        if restart {
            restarted = Some(spawn_logged(&[&["current-loop"][..], &common].concat()));
            std::thread::sleep(Duration::from_millis(300));
            // Refused while the new loop sends no command yet (on a loaded machine its
            // start-up can outlast the sleep), or unanswered when the tool's subscriber got
            // no state in its wait (seen beside two CPU hogs, right after the kill): a user
            // asks again, and so does the test.
            let asked = Instant::now();
            loop {
                let out = Command::new(exe())
                    .args(["reset", "--instance", &inst])
                    .output()
                    .expect("reset");
                let said = format!(
                    "{}{}",
                    String::from_utf8_lossy(&out.stdout),
                    String::from_utf8_lossy(&out.stderr)
                );
                if out.status.success() && said.contains("cleared") {
                    break;
                }
                let refused = (out.status.code() == Some(3) && said.contains("still latched"))
                    || said.contains("no state from the plant");
                if !refused || asked.elapsed() > Duration::from_secs(5) {
                    // The plant's own account of the reset, before the stack is torn down.
                    signal(plant.id(), libc::SIGTERM);
                    let _ = wait_with_timeout(&mut plant, Duration::from_secs(10));
                    panic!(
                        "reset said: {said}\nthe plant's log:\n{}",
                        stderr_of(&mut plant)
                    );
                }
            }
        }
        let plant_status = wait_with_timeout(&mut plant, Duration::from_secs(30));
        let plant_log = stderr_of(&mut plant);
        let _ = wait_with_timeout(&mut position, Duration::from_secs(30));
        if let Some(mut c) = restarted {
            assert!(wait_with_timeout(&mut c, Duration::from_secs(30)).success());
        }
        let _ = wait_with_timeout(&mut monitor, Duration::from_secs(30));
        assert!(
            plant_log.contains("the current loop is silent"),
            "{plant_log}"
        );
        let doc = read_json(&json);
        let r = run_of(&doc, "proposed");
        assert_eq!(r["outcome"], "fault", "the fault happened: {r}");
        if restart {
            assert!(plant_status.success(), "{plant_log}");
            assert!(
                num(r, "final_error_rad").abs() < 1e-4,
                "control did not resume: {r}"
            );
            // Round 3, finding 10: the report says the reset cleared it (its headline said
            // "its outputs were off from then on" after a reset).
            assert!(
                num(r, "fault_cleared_at_s") > num(&r["fault"], "sim_time_s"),
                "{r}"
            );
        } else {
            assert!(r.get("fault_cleared_at_s").is_none(), "{r}");
            assert_eq!(plant_status.code(), Some(3), "{plant_log}");
            assert!(plant_log.contains("FAULT (exit 3)"), "{plant_log}");
            assert!(num(r, "final_error_rad").abs() > 1e-3, "{r}");
        }
    }
}

/// Finding 3, lockstep: a killed current loop is noticed, a new one rejoins from the newest
/// sample, and the run finishes. (Before: the new loop never rejoined; 30 s timeout.)
#[test]
fn a_restarted_current_loop_rejoins_a_lockstep_stack() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("lockrejoin");
    let scenario = dir.file("long.toml", "[trajectory]\nhold_s = 20.0\n");
    let inst = instance("lockrejoin");
    let common = by_hand("lockstep", &inst, scenario.to_str().unwrap());
    let mut plant = spawn_logged(&[&["plant"][..], &common].concat());
    let mut position = spawn_logged(&[&["position-loop"][..], &common].concat());
    let mut current = spawn_logged(&[&["current-loop"][..], &common].concat());
    std::thread::sleep(Duration::from_millis(300));
    signal(current.id(), libc::SIGKILL);
    let _ = current.wait();
    std::thread::sleep(Duration::from_millis(500));
    let mut again = spawn_logged(&[&["current-loop"][..], &common].concat());
    for (name, p) in [
        ("plant", &mut plant),
        ("position loop", &mut position),
        ("new current loop", &mut again),
    ] {
        let status = wait_with_timeout(p, Duration::from_secs(60));
        assert!(status.success(), "{name}: {}", stderr_of(p));
    }
}

/// Finding 4: a process with another scenario or another mode than the stack's is refused
/// at once, both named. (Before: it ran along undetected, or failed after 10 s with an
/// iceoryx2 error.)
#[test]
fn a_process_of_another_scenario_or_mode_is_refused_at_once() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("handshake");
    let other = dir.file(
        "other.toml",
        "name = \"other\"\n[motor]\nresistance_ohm = 30.0\n",
    );
    let inst = instance("handshake");
    let mut plant = spawn_logged(
        &[
            &["plant", "--mode", "realtime", "--instance", &inst][..],
            &ORDINARY_SCHEDULING,
        ]
        .concat(),
    );
    std::thread::sleep(Duration::from_millis(500));
    for (args, theirs, ours) in [
        (
            vec![
                "current-loop",
                "--mode",
                "realtime",
                "--scenario",
                other.to_str().unwrap(),
            ],
            "scenario paper-section-v (",
            "scenario other (",
        ),
        (
            vec!["position-loop", "--mode", "lockstep"],
            "mode realtime",
            "mode lockstep",
        ),
    ] {
        let started = Instant::now();
        let out = Command::new(exe())
            .args(&args)
            .args(["--instance", &inst])
            .args(ORDINARY_SCHEDULING)
            .output()
            .expect("run");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success());
        assert!(
            started.elapsed() < Duration::from_secs(3),
            "took {:?}",
            started.elapsed()
        );
        assert!(err.contains(theirs) && err.contains(ours), "{err}");
    }
    signal(plant.id(), libc::SIGTERM);
    let _ = wait_with_timeout(&mut plant, Duration::from_secs(10));
}

/// Finding 5: a launcher killed outright leaves no file behind. (Before: its
/// `/tmp/stepdrive-<pid>-<instance>.toml` stayed.)
#[test]
fn a_killed_launcher_leaves_no_files() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("files");
    let scenario = dir.file("long.toml", LONG);
    let inst = instance("files");
    // A results file of an earlier run, and a temporary of a launcher long dead.
    let json = dir.file("results.json", "{\"from\": \"an earlier run\"}");
    let stale_temp = dir.file(".results.json.999999999.tmp", "");
    let mut run = spawn_run(&[
        "run",
        "--method",
        "proposed",
        "--instance",
        &inst,
        "--scenario",
        scenario.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(
        wait_until(Duration::from_secs(30), || pid_of_role(
            &inst,
            "current-loop"
        )
        .is_some()),
        "stack did not come up"
    );
    std::thread::sleep(Duration::from_millis(800));
    let launcher = run.id();
    signal(launcher, libc::SIGKILL);
    let _ = run.wait();
    let prefix = format!("stepdrive-{launcher}-");
    let left: Vec<String> = std::fs::read_dir(std::env::temp_dir())
        .expect("temp dir")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&prefix))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    // Round 3, finding 8: no results file (before: one of 0 bytes), not the earlier run's
    // either, and the dead launcher's temporary is gone.
    assert!(
        !json.exists(),
        "a results file stayed after the launcher was killed"
    );
    assert!(!stale_temp.exists(), "a dead launcher's temporary stayed");
    assert!(
        wait_until(Duration::from_secs(5), || processes_with(&inst).is_empty()),
        "orphans left"
    );
}

/// Finding 6: one emulated drive serves one run after another: two methods back to back
/// against it, both complete and at their figures (its RESET aligns the rotor for each).
/// (Before: the second run hung 30 s on "no CONFIG" and the first one's results were lost.)
#[test]
fn an_emulated_drive_serves_runs_back_to_back() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("sessions");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("sessions");
    let port = free_udp_port();
    let listen = format!("127.0.0.1:{port}");
    let mut drive = spawn_logged(
        &[
            &[
                "emulate-drive",
                "--listen",
                &listen,
                "--scenario",
                scenario.to_str().unwrap(),
            ][..],
            &ORDINARY_SCHEDULING[..],
        ]
        .concat(),
    );
    // A host name, not only an address.
    let by_name = format!("localhost:{port}");
    let mut args = hardware_args_with(&scenario, &inst, &json, "proposed,lyapunov");
    args.extend(["--drive", &by_name]);
    let out = stepdrive(&args);
    signal(drive.id(), libc::SIGTERM);
    let _ = wait_with_timeout(&mut drive, Duration::from_secs(10));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc = read_json(&json);
    let expected = num(&doc, "microstepping_expected_cruise_error_rad");
    let lyapunov = run_of(&doc, "lyapunov");
    // Below the figure would mean the baseline is not microstepping as designed; a host
    // busy with other tests may hold the (unprivileged) stack and raise the maximum a little.
    let cruise = num(lyapunov, "cruise_max_abs_error_rad");
    assert!(
        cruise > 0.8 * expected && cruise < 1.5 * expected,
        "{lyapunov}"
    );
    assert!(num(run_of(&doc, "proposed"), "max_abs_error_rad") < 0.05);
}

/// Finding 7: errors name the party at fault, at once: a drive address where nothing
/// listens names the drive within seconds; CPUs that do not exist name the option before
/// anything starts. (Before: "is the plant alive?" after 30 s; "protocol error ... CPU
/// affinity" and "no error message".)
#[test]
fn errors_name_the_party_at_fault() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("blame");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("blame");
    let nowhere = format!("127.0.0.1:{}", free_udp_port());
    let started = Instant::now();
    let out = hardware_run(&scenario, &inst, &json, &["--drive", &nowhere]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        started.elapsed() < Duration::from_secs(15),
        "took {:?}",
        started.elapsed()
    );
    assert!(
        err.contains(&nowhere) && err.contains("nothing listens there"),
        "{err}"
    );

    let started = Instant::now();
    let out = stepdrive(&["run", "--mode", "realtime", "--cpus", "7,9", "--require-rt"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(started.elapsed() < Duration::from_secs(3));
    assert!(err.contains("--cpus: CPU 7 does not exist"), "{err}");
}

/// Finding 8: bad input is refused before anything runs, naming what is wrong in a short
/// message; a short run is allowed and reports what it reached. (Before: 1e300 accepted,
/// 300 zeros printed, the wrong field blamed, short runs refused, --drive in lockstep
/// ignored, an unwritable JSON path found only after the run.)
#[test]
fn bad_input_is_refused_at_once_naming_it() {
    let dir = TempDir::new("holes");
    for (text, field, shown) in [
        (
            "[trajectory]\ncruise_velocity_rad_s = 1e300\n",
            "trajectory.cruise_velocity_rad_s",
            "1e300",
        ),
        (
            "[drive]\nbus_voltage_v = 1e-300\n",
            "drive.bus_voltage_v",
            "1e-300",
        ),
    ] {
        let path = dir.file("bad.toml", text);
        let out = stepdrive(&["scenario", "--check", path.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains(field) && err.contains(shown), "{err}");
        assert!(err.len() < 400, "{} bytes: {err}", err.len());
    }
    let out = stepdrive(&["run", "--duration", "1e12"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1));
    assert!(err.contains("run.duration_s"), "{err}");

    let out = stepdrive(&["run", "--drive", "127.0.0.1:7700"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1));
    assert!(err.contains("--mode hardware"), "{err}");

    // Round 3, finding 10: a drive address that names no drive is bad input (exit 1), said
    // before anything starts; before, the bridge died on it: exit 5, PROCESS DIED and a
    // table of NaN.
    for (drive, said) in [
        (
            ["--drive", "nosuchhost.invalid:9"],
            "is not a drive address",
        ),
        (
            ["--drive-port", "/dev/stepdrive-no-such-line"],
            "no serial line at",
        ),
    ] {
        let mut args = vec!["run", "--mode", "hardware", "--method", "proposed"];
        args.extend(drive);
        let out = stepdrive(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains(said) && !err.contains("PROCESS DIED"), "{err}");
    }

    let started = Instant::now();
    let out = stepdrive(&["run", "--json", "/nonexistent/dir/results.json"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1));
    assert!(err.contains("/nonexistent/dir/results.json"), "{err}");
    assert!(
        started.elapsed() < Duration::from_secs(2),
        "the run ran first"
    );
}

/// Finding 8: a run shorter than the profile runs, and reports `n/a` for the windows it
/// did not reach.
#[test]
fn a_run_shorter_than_the_profile_reports_what_it_reached() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("shortrun");
    let json = dir.path("short.json");
    let inst = instance("shortrun");
    let out = stepdrive(&[
        "run",
        "--duration",
        "0.2",
        "--method",
        "proposed",
        "--instance",
        &inst,
        "--json",
        json.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("n/a"), "{stdout}");
    let doc = read_json(&json);
    let r = run_of(&doc, "proposed");
    assert_eq!(r["cruise_max_abs_error_rad"], Value::Null, "{r}");
    assert_eq!(num(r, "samples"), 4001.0);
}

/// A drive whose ALIGN is broken (docs/drive-protocol.md §7) never gives a run that
/// reports success: one that never finishes aligning is named by the bridge and the run
/// exits 5; one that aligned the wrong way (phase A reversed: the rotor half an electrical
/// period from the zero the host assumes, which used to commutate backwards and run away)
/// is refused before it is enabled, its held current named, exit 5; one whose phase A leads
/// are swapped is refused by the phase-B step (§7 step 4), exit 5.
#[test]
fn a_broken_alignment_is_loud() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("hwalign");
    let scenario = dir.file("slow.toml", &slow_scenario());
    for (fault, code, says) in [
        ("stuck", 5, "did not finish its alignment"),
        ("reversed", 5, "reports phase A at -1.0"),
        // Issue 24: phase A's leads swapped passes the held-current check (the drive's
        // shunt reads +1 A); the phase-B step turns the rotor the wrong way, refused before
        // the run. (Before: both methods ran away, STEPPED OUT, exit 4.)
        ("swapped-leads", 5, "turned its rotor -0.03"),
    ] {
        let json = dir.path(&format!("{fault}.json"));
        let inst = instance(&format!("hwalign{fault}"));
        let listen = format!("127.0.0.1:{}", free_udp_port());
        let mut drive = spawn_logged(
            &[
                &[
                    "emulate-drive",
                    "--listen",
                    &listen,
                    "--scenario",
                    scenario.to_str().unwrap(),
                    "--align-fault",
                    fault,
                ][..],
                &ORDINARY_SCHEDULING[..],
            ]
            .concat(),
        );
        let out = hardware_run(&scenario, &inst, &json, &["--drive", &listen]);
        signal(drive.id(), libc::SIGTERM);
        let _ = wait_with_timeout(&mut drive, Duration::from_secs(10));
        let all = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        assert_eq!(out.status.code(), Some(code), "{fault}: {all}");
        assert!(all.contains(says), "{fault}: {all}");
        assert!(processes_with(&inst).is_empty());
    }
}

/// How the [`FakeDrive`] answers a HELLO.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Answer {
    /// A valid CONFIG and then SAMPLEs, every one from a second socket (another port than
    /// the one the HELLO went to).
    FromAnotherPort,
    /// A CONFIG with its reserved byte set.
    ReservedByte,
    /// A CONFIG with an invalid field (encoder_direction 0).
    InvalidConfig,
}

/// Not a drive: a UDP socket on a free loopback port that answers each HELLO as told and
/// keeps every host frame it receives, for the host's side of the handshake.
struct FakeDrive {
    addr: String,
    other: std::net::SocketAddr,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: std::thread::JoinHandle<Vec<stepdrive_drive_protocol::Message>>,
}

impl FakeDrive {
    fn start(answer: Answer, rate_hz: f64) -> Self {
        use std::sync::atomic::Ordering;
        use stepdrive_drive_protocol::units::default_config;
        use stepdrive_drive_protocol::{decode, frame_bytes, reseal, status, Message, Sample};
        let sock = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let other = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        sock.set_read_timeout(Some(Duration::from_millis(1)))
            .expect("timeout");
        let addr = sock.local_addr().expect("addr").to_string();
        let other_addr = other.local_addr().expect("addr");
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let stopped = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut got = Vec::new();
            let mut host = None;
            let mut seq = 0u32;
            let mut buf = [0u8; 8192];
            let mut config = default_config(rate_hz, 1000, 0);
            if answer == Answer::InvalidConfig {
                config.encoder_direction = 0;
            }
            while !stopped.load(Ordering::Relaxed) {
                if let Ok((n, from)) = sock.recv_from(&mut buf) {
                    if let Ok(f) = decode(&buf[..n]) {
                        if f.message == Message::Hello {
                            host = Some(from);
                            let mut reply = frame_bytes(seq, Message::Config(config));
                            if answer == Answer::ReservedByte {
                                reply[18 + 27] = 1;
                                reseal(&mut reply);
                            }
                            let out = if answer == Answer::FromAnotherPort {
                                &other
                            } else {
                                &sock
                            };
                            let _ = out.send_to(&reply, from);
                        }
                        got.push(f.message);
                    }
                }
                if let (Some(to), Answer::FromAnotherPort) = (host, answer) {
                    seq += 1;
                    let s = Sample {
                        encoder_counts: 0,
                        adc_a: 32768,
                        adc_b: 32768,
                        adc_bus: 2400,
                        duty_a: 0,
                        duty_b: 0,
                        applied_command_seq: 0,
                        fault_bits: 0,
                        status: status::ENABLED,
                    };
                    let _ = other.send_to(&frame_bytes(seq, Message::Sample(s)), to);
                }
            }
            got
        });
        Self {
            addr,
            other: other_addr,
            stop,
            thread,
        }
    }

    /// Stops it; the host frames it received.
    fn stop(self) -> Vec<stepdrive_drive_protocol::Message> {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        self.thread.join().expect("fake drive thread")
    }
}

/// Issue 24, defect 5 (the reliability issue's finding 4): a drive whose frames never
/// arrive is named, with what was missing, within the handshake time (1 s of HELLOs): one
/// that answers from another port than it listens on, and one whose CONFIG has its
/// reserved byte set; DISABLE follows. (Before: after 30 s, "the position loop could not
/// start within 30s: still waiting for drive/state from the plant", exit 5.)
#[test]
fn a_drive_never_heard_is_named_within_the_handshake_time() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("handshake");
    let scenario = dir.file("slow.toml", &slow_scenario());
    for answer in [Answer::FromAnotherPort, Answer::ReservedByte] {
        let json = dir.path("hw.json");
        let inst = instance(&format!("handshake{answer:?}"));
        let fake = FakeDrive::start(answer, 2000.0);
        let (addr, other) = (fake.addr.clone(), fake.other);
        let started = Instant::now();
        let out = hardware_run(&scenario, &inst, &json, &["--drive", &addr]);
        let took = started.elapsed();
        let received = fake.stop();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(5), "{answer:?}: {err}");
        assert!(took < Duration::from_secs(10), "{answer:?}: took {took:?}");
        let named = format!("the drive at udp://{addr} sent no usable CONFIG within");
        assert!(err.contains(&named), "{answer:?}: {err}");
        let says = match answer {
            Answer::FromAnotherPort => format!("frames came from {other} instead"),
            _ => "a CONFIG with its reserved byte (offset 27) set".to_string(),
        };
        assert!(err.contains(&says), "{answer:?}: {err}");
        assert!(
            received.contains(&stepdrive_drive_protocol::Message::Control(
                stepdrive_drive_protocol::Action::Disable
            )),
            "{answer:?}: no DISABLE in {received:?}"
        );
        assert!(processes_with(&inst).is_empty());
    }
}

/// Issue 24, defect 4: a drive whose CONFIG is refused gets DISABLE on the way out (§7 step
/// 7: every exit path). (Before: the refusal named the field, and no DISABLE went out.)
#[test]
fn a_refused_config_is_followed_by_disable() {
    use stepdrive_drive_protocol::{Action, Message};
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("refusedconfig");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("refusedconfig");
    let fake = FakeDrive::start(Answer::InvalidConfig, 2000.0);
    let addr = fake.addr.clone();
    let out = hardware_run(&scenario, &inst, &json, &["--drive", &addr]);
    let received = fake.stop();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(5), "{err}");
    assert!(
        err.contains("CONFIG field encoder_direction = 0 is invalid"),
        "{err}"
    );
    let hello = received.iter().position(|m| *m == Message::Hello);
    let disable = received
        .iter()
        .rposition(|m| *m == Message::Control(Action::Disable));
    assert!(
        matches!((hello, disable), (Some(h), Some(d)) if d > h),
        "HELLO then DISABLE: {received:?}"
    );
    assert!(processes_with(&inst).is_empty());
}

/// A busy ordinary task on the current loop's CPU must not lose the motor. With the current
/// loop's old `hybrid:40` wait, `taskset -c 1 yes` tripped the plant's watchdog ~1 s into a
/// realtime run (8 runs of 9): the loop's ~2 µs sleeps never gave CPU 1 away, and the
/// kernel's fair server ran the starved task ahead of the loop for ~50 ms. This needs the
/// default deployment (SCHED_FIFO, CPUs 0 and 1) and a machine otherwise idle, so it is
/// ignored in CI: `cargo test --release --test stack reliability:: -- --ignored`.
#[test]
#[ignore = "timing: the default realtime deployment beside a CPU hog on the current loop's CPU"]
fn an_ordinary_task_busy_on_the_current_loops_cpu_does_not_trip_the_watchdog() {
    let _turn = one_stack_at_a_time();
    beside_a_hog_on_cpu_1("hog", "", &["--mode", "realtime"]);
}

/// The same with several axes: their current loop answers every axis before it waits, so
/// the margin before the next sample was already past and it polled without a break (4 axes:
/// 7 sleeps in 408 769 cycles); beside `taskset -c 1 yes` 2 axes latched COMMAND_TIMEOUT in
/// 1 run of 2, 4 axes in 2 of 2. A `hybrid` wait now rests ~7 µs when all its axes are
/// answered and the next sample is still ≥ 17 µs off (`runner::hybrid_sleep_target`).
#[test]
#[ignore = "timing: the default realtime deployment beside a CPU hog on the current loop's CPU"]
fn an_ordinary_task_busy_on_the_current_loops_cpu_does_not_trip_the_watchdog_of_several_axes() {
    let _turn = one_stack_at_a_time();
    for axes in [2, 4] {
        let scenario: String = (0..axes)
            .map(|n| format!("[[axis]]\nname = \"a{n}\"\n"))
            .collect();
        beside_a_hog_on_cpu_1(&format!("hog{axes}"), &scenario, &["--mode", "realtime"]);
    }
}

/// Hardware mode: the bridge shares CPU 1 with the current loop and polls its socket from
/// 30 µs before each frame; it answered late in the period too, so the same hog tripped the
/// emulated drive's watchdog at t = 0.99 s. It rests as the current loop does.
#[test]
#[ignore = "timing: the default hardware deployment beside a CPU hog on the bridge's CPU"]
fn an_ordinary_task_busy_on_the_bridges_cpu_does_not_trip_the_drives_watchdog() {
    let _turn = one_stack_at_a_time();
    beside_a_hog_on_cpu_1("hoghw", "", &["--mode", "hardware"]);
}

/// `stepdrive deploy` prints the realtime waits; given to a hardware run, its current loop
/// would poll CPU 1 above the bridge it waits for and the stack stalled at its first sample
/// (and its launcher, reaping the killed bridge at SCHED_FIFO, spun in the kernel for
/// minutes). Refused before anything starts, naming the setting; the hardware file passes.
#[test]
fn a_hardware_run_refuses_a_deployment_whose_current_loop_would_starve_the_bridge() {
    let dir = TempDir::new("starve");
    let printed = stepdrive(&["deploy", "--mode", "realtime"]);
    assert!(printed.status.success(), "{}", text(&printed));
    let file = dir.file("realtime.toml", &String::from_utf8_lossy(&printed.stdout));
    let file = file.to_str().expect("utf-8 path");
    let inst = instance("starve");
    let started = Instant::now();
    let out = stepdrive(&[
        "run",
        "--mode",
        "hardware",
        "--deploy",
        file,
        "--instance",
        &inst,
        "--duration",
        "1",
    ]);
    let said = text(&out);
    assert!(!out.status.success(), "taken: {said}");
    assert!(said.contains("current_loop.wait"), "{said}");
    assert!(
        processes_with(&inst).is_empty() && started.elapsed() < Duration::from_secs(10),
        "something started: {said}"
    );
    let checked = stepdrive(&["deploy", "--check", file, "--mode", "hardware"]);
    assert!(!checked.status.success(), "{}", text(&checked));
    let hardware = stepdrive(&["deploy", "--mode", "hardware"]);
    let hw_file = dir.file("hardware.toml", &String::from_utf8_lossy(&hardware.stdout));
    let checked = stepdrive(&[
        "deploy",
        "--check",
        hw_file.to_str().expect("utf-8 path"),
        "--mode",
        "hardware",
    ]);
    assert!(checked.status.success(), "{}", text(&checked));
}

/// Runs the proposed method for 5 s with the default deployment on `scenario`, a thread
/// pinned to CPU 1 spinning beside it, and asserts the run ended ok with no faulted sample
/// on any axis.
fn beside_a_hog_on_cpu_1(name: &str, scenario: &str, mode: &[&str]) {
    let dir = TempDir::new(name);
    let json = dir.path("rt.json");
    let inst = instance(name);
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let hog = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let pinned = stepdrive_runtime::rt::pin_to_cpu(1).is_ok();
            let mut spins = 0u64;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                spins = std::hint::black_box(spins.wrapping_add(1));
            }
            pinned
        })
    };
    let scenario = dir.file("scenario.toml", scenario);
    let json_path = json.to_str().unwrap();
    let mut args = mode.to_vec();
    args.extend(["--duration", "5", "--json", json_path]);
    let out = run_proposed(&inst, &scenario, &args);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    assert!(
        hog.join().expect("the hog"),
        "could not pin the hog to CPU 1"
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{name}: {text}\n{err}");
    let doc = read_json(&json);
    assert_eq!(doc["outcome"], "ok", "{name}: {text}");
    let run = run_of(&doc, "proposed");
    assert_eq!(num(run, "fault_samples"), 0.0, "{name}");
    for axis in run["axes"].as_array().into_iter().flatten() {
        assert_eq!(num(axis, "fault_samples"), 0.0, "{name}: axis {axis}");
    }
}
