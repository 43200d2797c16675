//! Reliability, round 3: what a new user and a stranger's drive still broke. Each test is
//! one finding of that issue, and failed on the code before its fix.

use crate::common::*;
use std::time::Duration;

/// Finding 2: `monitor`, `record` and `scope` refused a stack started with `--duration` (the
/// README's own realtime command), because the scenario they were given was not the one
/// the stack ran, and the message did not say which field differed. A reader now takes the
/// scenario the stack announces; one given that differs is refused naming the field.
#[test]
fn attaching_readers_take_the_scenario_from_the_stack() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("attachscenario");
    let scenario = dir.file("short.toml", SHORT);
    let inst = instance("attachscenario");
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "2.0"));
    let mut run = spawn_run(&args);
    assert!(
        wait_until(Duration::from_secs(30), || pid_of_role(
            &inst,
            "current-loop"
        )
        .is_some()),
        "the stack did not come up"
    );
    // The file without the run's --duration is not the stack's scenario: refused, naming
    // the field that differs.
    let refused = stepdrive(&[
        "monitor",
        "--instance",
        &inst,
        "--scenario",
        scenario.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert_eq!(refused.status.code(), Some(1), "{err}");
    assert!(err.contains("run.duration_s"), "{err}");
    // Without --scenario: the stack's own, and the run's figures.
    let mcap = dir.path("attached.mcap");
    let json = dir.path("attached.json");
    let out = stepdrive(&[
        "record",
        mcap.to_str().unwrap(),
        "--instance",
        &inst,
        "--json",
        json.to_str().unwrap(),
    ]);
    let status = wait_with_timeout(&mut run, Duration::from_secs(60));
    assert!(status.success(), "{}", stdout_of(&mut run));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc = read_json(&json);
    assert_eq!(doc["scenario"]["run"]["duration_s"].as_f64(), Some(2.0));
    assert!(num(run_of(&doc, "proposed"), "samples") > 1000.0);
}

/// Finding 1: a position loop stopped for 1 s (SIGSTOP) in a realtime run. Before: the
/// current loop followed the last setpoint segment on, the rotor ended 3.6 rad away, exit 4
/// blaming the scenario. Now the current loop stops the motor at the quick-stop rate once
/// the newest setpoint is 10 ms old and holds it: the rotor stands where that stop puts
/// it, and the run ends with exit 5 naming the silent position loop.
#[test]
fn a_silent_position_loop_is_stood_in_for_by_a_controlled_stop() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("silentpos");
    // 13.13 rad/s reached in 0.1 s, 3 s of cruise, 0.1 s down, 0.5 s held.
    let scenario = dir.file(
        "cruise.toml",
        "name = \"cruise\"\n[trajectory]\naccel_s = 0.1\ncruise_s = 3.0\ndecel_s = 0.1\nhold_s = 0.5\n",
    );
    let inst = instance("silentpos");
    let json = dir.path("rt.json");
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "3.7"));
    args.extend(["--json", json.to_str().unwrap()]);
    let mut run = spawn_run(&args);
    wait_for_stack_time(&inst, &mut run, 1.0);
    let pid = pid_of_role(&inst, "position-loop").expect("position loop");
    signal(pid, libc::SIGSTOP);
    std::thread::sleep(Duration::from_secs(1));
    signal(pid, libc::SIGCONT);
    let status = wait_with_timeout(&mut run, Duration::from_secs(60));
    let stdout = stdout_of(&mut run);
    let stderr = stderr_of(&mut run);
    assert_eq!(status.code(), Some(5), "{stdout}\n{stderr}");
    assert!(stdout.contains("POSITION LOOP SILENT"), "{stdout}");
    assert!(stderr.contains("the position loop is silent"), "{stderr}");
    let doc = read_json(&json);
    let r = run_of(&doc, "proposed");
    let t = num(r, "setpoint_stale_at_s");
    // Where the stop leaves the rotor: θ_d and ω_d when it began, then ω²/(2 a_qs) on.
    let (a, v, qs) = (131.3, 13.13, 200.0);
    let theta_d = |t: f64| match t {
        t if t < 0.1 => 0.5 * a * t * t,
        t if t < 3.1 => 0.5 * a * 0.01 + v * (t - 0.1),
        t => 2.0 * 0.5 * a * 0.01 + v * 3.0 - 0.5 * a * (3.2 - t.min(3.2)).powi(2),
    };
    let omega_d = |t: f64| match t {
        t if t < 0.1 => a * t,
        t if t < 3.1 => v,
        t => a * (3.2 - t.min(3.2)),
    };
    let stood = theta_d(t) + omega_d(t).powi(2) / (2.0 * qs);
    let expected = theta_d(3.7) - stood;
    let final_error = num(r, "final_error_rad");
    // The report's stale time is the first state that carries the flag: a sample or more
    // after the current loop began its stop, never before. At ordinary priority on a busy
    // CI machine that was once 0.9 ms late, which at 13.13 rad/s cruise puts the expected
    // stop 12 mrad short. So the rotor may stand further from the end by up to 5 ms of
    // cruise (66 mrad), and no nearer; a stop from the wrong speed or at the wrong rate
    // moves it by tenths of a radian (v²/2a_qs = 0.43 rad), a missing stop by radians.
    let late = final_error - expected;
    assert!(
        (-1e-2..v * 5e-3).contains(&late),
        "stale at {t} s: the rotor stands {final_error} rad from the trajectory's end, the \
         stop puts it {expected} rad away ({late:+.4} rad)"
    );
}

/// Finding 6: `--instance` was used as a path before it was checked (`a/b` and
/// `../../x/escape` created directories outside the prefix). Now a name that is not one
/// plain path component is refused by the argument parser, before anything runs.
#[test]
fn an_instance_name_that_is_a_path_is_refused_at_once() {
    for name in ["a/b", "../../x/escape", "", "two words"] {
        let out = stepdrive(&["run", "--instance", name]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name:?}: {err}");
        assert!(err.contains("instance name"), "{name:?}: {err}");
    }
}

/// Finding 7 and finding 11, the smaller ones. A second stack on a running stack's
/// instance is refused naming it. A negative `--duration` is refused naming the field (was:
/// "unexpected argument '-1'"); a load no motor torque can hold is refused by `--check`
/// (was: accepted); a served stack stopped by Ctrl-C exits 0 without a child printing
/// "error: terminated by signal" (was: one such line per process on every normal stop).
#[test]
fn small_input_and_exit_findings() {
    let out = stepdrive(&["run", "--duration", "-1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("run.duration_s"), "{err}");

    let dir = TempDir::new("smallfindings");
    let heavy = dir.file(
        "heavy.toml",
        "name = \"heavy\"\n[load]\ntorque_nm = 1000.0\n",
    );
    let out = stepdrive(&["scenario", "--check", heavy.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("can never be held"), "{err}");

    let _turn = one_stack_at_a_time();
    let inst = instance("sigstop");
    let mut serve = spawn_serve(&inst, &[]);
    assert!(
        wait_until(Duration::from_secs(30), || pid_of_role(
            &inst,
            "current-loop"
        )
        .is_some()),
        "the stack did not come up"
    );
    std::thread::sleep(Duration::from_millis(500));
    // Finding 7: a second stack on a running stack's instance is refused before it starts
    // (before: it read the first stack's samples as its own).
    let second = stepdrive(&["run", "--instance", &inst, "--method", "proposed"]);
    let err = String::from_utf8_lossy(&second.stderr);
    assert_eq!(second.status.code(), Some(1), "{err}");
    assert!(err.contains("in use by a running stack"), "{err}");
    // Finding 7, another instance: a realtime stack whose loops would share the running
    // one's CPUs is refused at once, naming it (before: both ran, both ended UNOBSERVED with
    // 25 % and 36 % misses). A lockstep stack beside it is not refused.
    let other = instance("sigstop-other");
    let t0 = std::time::Instant::now();
    let rt = stepdrive(&[
        "run",
        "--mode",
        "realtime",
        "--duration",
        "5",
        "--instance",
        &other,
        "--method",
        "proposed",
    ]);
    let err = String::from_utf8_lossy(&rt.stderr);
    assert_eq!(rt.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!("is taken by the stack of instance `{inst}`")),
        "{err}"
    );
    assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
    assert!(processes_with(&other).is_empty());
    let short = dir.file("short.toml", SHORT);
    let lockstep = stepdrive(&[
        "run",
        "--instance",
        &other,
        "--method",
        "proposed",
        "--scenario",
        short.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&lockstep.stderr);
    assert_eq!(lockstep.status.code(), Some(0), "{err}");
    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    let err = stderr_of(&mut serve);
    assert_eq!(status.code(), Some(0), "{err}");
    assert!(!err.contains("terminated by signal"), "{err}");
    assert!(processes_with(&inst).is_empty());
}

/// Finding 9: `record` started before a realtime stack missed its first 0.16-0.18 s (3300-
/// 3600 samples) and ended UNOBSERVED (exit 6): it subscribed to the states only after the
/// device had announced itself and started publishing. It now subscribes as soon as the
/// stack's services exist, and sees every sample.
///
/// A recorder that encoded each message itself between drains fell behind its queue on a
/// loaded host and lost up to 13 % of the samples (0.04 s in a row, two runs of three beside
/// a busy loop on each core); its file is now written on a thread of its own.
///
/// The run here is all ordinary scheduling on the CI machine's two cores; when the host
/// held the run's own monitor past its queue (the run ends UNOBSERVED, exit 6: the host
/// could not vouch for it), it is tried once more. The bug this guards against left the
/// run `ok` and the recorder short, so a retry cannot hide it.
#[test]
fn a_recorder_started_before_the_stack_sees_every_sample() {
    let _turn = one_stack_at_a_time();
    for attempt in 1..=2 {
        match record_a_run_from_its_start(attempt) {
            Ok(()) => return,
            Err(unobserved) if attempt == 1 => eprintln!("retrying once: {unobserved}"),
            Err(unobserved) => panic!("unobserved twice: {unobserved}"),
        }
    }
}

/// Records a 2 s realtime run with `record` started first, and asserts it saw all of it;
/// `Err` (the run's report) when the run itself ended UNOBSERVED.
fn record_a_run_from_its_start(attempt: u32) -> Result<(), String> {
    let dir = TempDir::new(&format!("firstrecord{attempt}"));
    let scenario = dir.file("short.toml", &format!("{SHORT}\n[run]\nduration_s = 2.0\n"));
    let inst = instance(&format!("firstrecord{attempt}"));
    let mcap = dir.path("first.mcap");
    let json = dir.path("first.json");
    let mut record = spawn_run(&[
        "record",
        mcap.to_str().unwrap(),
        "--instance",
        &inst,
        "--json",
        json.to_str().unwrap(),
    ]);
    std::thread::sleep(Duration::from_millis(300));
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "2.0"));
    let run = stepdrive(&args);
    let report = String::from_utf8_lossy(&run.stdout).into_owned();
    let status = wait_with_timeout(&mut record, Duration::from_secs(30));
    let out = stdout_of(&mut record);
    if run.status.code() == Some(6) {
        return Err(report);
    }
    assert!(run.status.success(), "{report}");
    assert!(status.success(), "{out}");
    let r = run_of(&read_json(&json), "proposed").clone();
    assert_eq!(num(&r, "missed_samples"), 0.0, "{r}");
    assert_eq!(num(&r, "samples"), 40_001.0, "{r}");
    // And the file has them: its writer, behind the reader, dropped none.
    let file = stepdrive_monitor::record::recording::Recorded::read(&mcap).expect("read back");
    let meta = &file.metadata["recording"];
    assert_eq!(meta["proposed.samples_recorded"], "40001", "{meta:?}");
    assert_eq!(meta["proposed.messages_dropped"], "0", "{meta:?}");
    assert_eq!(file.runs[0].1.len(), 40_001);
    Ok(())
}
