//! The axis through processes: a served stack, commanded by `stepdrive axis` (the client
//! crate) from other processes, as a user does.

use crate::common::*;
use std::time::Duration;

/// `serve` keeps a stack up with its axis disabled; another process enables it, moves it
/// and waits for the target, has bad commands refused with their reason, quick-stops it;
/// Ctrl-C ends `serve` with exit 0.
#[test]
fn a_served_axis_is_commanded_from_other_processes() {
    let _turn = one_stack_at_a_time();
    let inst = instance("served");
    let mut serve = spawn_serve(&inst, &[]);
    let axis = |args: &[&str]| {
        let mut all = vec!["axis", "--instance", inst.as_str()];
        all.extend(args);
        stepdrive(&all)
    };
    assert!(
        wait_until(Duration::from_secs(30), || axis(&["status"])
            .status
            .success()),
        "the served stack did not answer"
    );
    let st = axis(&["status"]);
    assert!(text(&st).contains("Switch on disabled"), "{}", text(&st));
    // Disabled under the default 0.01 N·m load, the rotor stands on its holding brake
    // (without one it ran away at −0.46 rad/s).
    let theta = |o: &std::process::Output| -> f64 {
        let out = text(o);
        out.lines()
            .find_map(|l| l.strip_prefix("θ "))
            .and_then(|l| l.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no θ in {out}"))
    };
    std::thread::sleep(Duration::from_millis(500));
    let later = axis(&["status"]);
    assert_eq!(theta(&st), 0.0, "{}", text(&st));
    assert_eq!(theta(&later), 0.0, "{}", text(&later));

    // Refused, with the reason, nothing applied.
    let refused = axis(&["move", "--to", "1"]);
    assert_eq!(refused.status.code(), Some(1), "{}", text(&refused));
    assert!(
        text(&refused).contains("needs Operation enabled"),
        "{}",
        text(&refused)
    );
    let unknown = axis(&["--axis", "3", "status"]);
    assert_eq!(unknown.status.code(), Some(1), "{}", text(&unknown));
    assert!(text(&unknown).contains("axis 3"), "{}", text(&unknown));

    // A reader attached to the served stack grades it against its axis's setpoints (not
    // the scenario's trapezoid, which a served axis never runs) and ends in order with it;
    // its recording plots.
    let dir = TempDir::new("served-monitor");
    let json = dir.path("monitor.json");
    let mcap = dir.path("served.mcap");
    let mut monitor = spawn_logged(&[
        "record",
        mcap.to_str().expect("a UTF-8 path"),
        "--instance",
        inst.as_str(),
        "--json",
        json.to_str().expect("a UTF-8 path"),
    ]);

    let on = axis(&["enable"]);
    assert!(on.status.success(), "{}", text(&on));
    // A value that is no number the axis could take is a usage error (exit 2), never
    // sent; one the axis refuses comes back with its reason (exit 1).
    for (args, code, why) in [
        (&["move", "--to", "nan"][..], 2, "finite"),
        (&["move", "--to", "1", "--vmax", "0"][..], 2, "positive"),
        (&["move", "--to", "1e9"][..], 1, "outside the soft limits"),
        (
            &["move", "--to", "1", "--vmax", "1e6"][..],
            1,
            "exceeds the axis's",
        ),
    ] {
        let out = axis(args);
        assert_eq!(out.status.code(), Some(code), "{args:?}: {}", text(&out));
        assert!(text(&out).contains(why), "{args:?}: {}", text(&out));
    }

    // A move to 1 rad from where the rotor stands, waited for.
    let mv = axis(&MOVE_1_RAD_WAITED);
    assert_reached(&mv);
    // The stack's loops run at ordinary priority here: by default, so does the reader (at
    // SCHED_FIFO it would go before them).
    // SAFETY: sched_getscheduler only reads the policy of a process.
    let policy = unsafe { libc::sched_getscheduler(monitor.id() as libc::pid_t) };
    assert_eq!(policy, libc::SCHED_OTHER, "the reader's policy");

    let qs = axis(&["quick-stop"]);
    assert!(qs.status.success(), "{}", text(&qs));
    let st = axis(&["status"]);
    assert!(text(&st).contains("Quick stop active"), "{}", text(&st));

    signal(serve.id(), libc::SIGINT);
    let status = wait_or_explain(&mut serve, Duration::from_secs(30), &inst);
    let err = stderr_of(&mut serve);
    assert_eq!(status.code(), Some(0), "{err}");
    assert!(processes_with(&inst).is_empty());

    // The reader learnt of the stop from the loops' final statistics: no "process died".
    let read = wait_with_timeout(&mut monitor, Duration::from_secs(30));
    let report = stderr_of(&mut monitor);
    let doc = read_json(&json);
    let run = run_of(&doc, "proposed");
    assert_ne!(run["outcome"], "process_died", "{report}");
    assert!(
        matches!(read.code(), Some(0) | Some(6)),
        "{read:?}: {report}"
    );
    // Graded against the trapezoid (6.28 rad away at its end) it was several rad.
    assert!(num(run, "max_abs_error_rad") < 1e-3, "{report}");
    let moves = run["moves"].as_array().expect("a served run's moves");
    assert_eq!(moves.len(), 1, "{report}");
    assert!(num(&moves[0], "peak_abs_error_rad") < 1e-3, "{report}");
    // Its window starts where it attached: nothing before it counts as missed (the stack
    // had run > 0.5 s, 10 000 samples, by then). At ordinary priority on the CI machine's
    // two cores the reader may miss samples the host kept it from (1 417 of 9 037 seen,
    // none longer than 0.1 s in a row); one the host held past its queue says so and exits
    // 6, naming the stretch, which must not start before it attached either.
    if read.code() == Some(6) {
        let from: f64 = report
            .split("of the run in a row from t = ")
            .nth(1)
            .and_then(|r| r.split_whitespace().next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("no missed stretch named: {report}"));
        assert!(from > 0.3, "{report}");
    } else {
        assert!(num(run, "missed_samples") < 10_000.0, "{run}");
    }
    // A served run has no cruise window: the zoomed figures show where the move starts
    // (the cruise's figure had no point in a recording that starts where it attached).
    let plots = dir.path("plots");
    let plot = stepdrive(&[
        "plot",
        mcap.to_str().expect("a UTF-8 path"),
        "--out",
        plots.to_str().expect("a UTF-8 path"),
    ]);
    assert!(plot.status.success(), "{}", text(&plot));
    for figure in [
        "currents_cruise.svg",
        "voltages.svg",
        "program_position.svg",
    ] {
        assert!(plots.join(figure).exists(), "{figure}: {}", text(&plot));
    }
}

/// A load the motor cannot hold (2 N·m against a stall torque of 0.81 N·m, for 0.1 s) in a
/// lockstep program: the axis faults on its following error within the window's time,
/// outputs off, and the run exits 3 naming it; a reset and an enable later start where the
/// rotor was pushed to, and a relative move from there arrives on its target.
#[test]
fn a_following_error_faults_the_axis_and_a_reset_resumes_without_a_jump() {
    let dir = TempDir::new("following");
    let scenario = dir.file(
        "fe.toml",
        r#"name = "following-error"
[plant.load]
steps = [{ at_s = 0.2, torque_nm = 2.0 }, { at_s = 0.3, torque_nm = -2.0 }]
[[program]]
at_s = 0.0
command = "enable"
[[program]]
at_s = 0.6
command = "reset"
[[program]]
at_s = 0.65
command = "enable"
[[program]]
at_s = 0.7
command = "move"
to = 3.0
relative = true
"#,
    );
    let json = dir.path("fe.json");
    let inst = instance("following");
    let out = run_proposed(&inst, &scenario, &["--json", json.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(3), "{stdout}");
    assert!(
        stdout.contains("the axis went to Fault (FOLLOWING_ERROR)"),
        "{stdout}"
    );
    let doc = read_json(&json);
    let r = run_of(&doc, "proposed");
    assert_eq!(r["outcome"], "fault");
    let fault = &r["axis_fault"];
    // Beyond the 0.1 rad window a few ms after the step, then the 20 ms window time.
    let at = num(fault, "sim_time_s");
    assert!((0.22..0.23).contains(&at), "{fault}");
    let moves = r["moves"].as_array().expect("moves");
    assert_eq!(moves.len(), 1, "{r}");
    let mv = &moves[0];
    assert!(mv["duration_s"].is_number(), "the move never arrived: {mv}");
    assert!(num(mv, "peak_abs_error_rad") < 1e-3, "{mv}");
    assert!(num(r, "final_error_rad").abs() < 1e-9, "{r}");
}

/// Issue 21's move: the paper's motor, rest to rest over 20 rad along a jerk-limited
/// trajectory (v 13.13, a 50, j 2000) in lockstep. The move takes the closed-form optimum
/// d/v + v/a + a/j = 1.8108 s, the proposed method's peak following error over it is within
/// 2e-5 rad (7.75e-6 measured), the final error within 1e-9 rad; and the figures the
/// monitor reports are the ones the recording's samples give (the metrics once graded
/// states against setpoints newer than theirs, and reported 6.2e-5 for this move).
#[test]
fn a_jerk_limited_20_rad_move_is_tracked_within_2e_5_and_reported_as_recorded() {
    let dir = TempDir::new("move-20");
    let scenario = dir.file(
        "move.toml",
        r#"name = "move-20"
[[program]]
at_s = 0.0
command = "enable"
[[program]]
at_s = 0.05
command = "move"
to = 20.0
vmax = 13.13
amax = 50.0
jmax = 2000.0
"#,
    );
    let (json, recording) = (dir.path("move.json"), dir.path("move.mcap"));
    let inst = instance("move-20");
    let out = run_proposed(
        &inst,
        &scenario,
        &[
            "--json",
            json.to_str().unwrap(),
            "--record",
            recording.to_str().unwrap(),
        ],
    );
    assert!(out.status.success(), "{}", text(&out));
    let doc = read_json(&json);
    let run = run_of(&doc, "proposed");
    let moves = run["moves"].as_array().expect("moves");
    assert_eq!(moves.len(), 1, "{run}");
    let mv = &moves[0];
    let optimum = 20.0 / 13.13 + 13.13 / 50.0 + 50.0 / 2000.0;
    let duration = num(mv, "duration_s");
    assert!(
        (duration - optimum).abs() < 1e-3,
        "{duration} s against {optimum} s"
    );
    let peak = num(mv, "peak_abs_error_rad");
    assert!(
        peak <= 2e-5,
        "peak following error {peak:e} rad over the move"
    );
    assert!(num(run, "final_error_rad").abs() <= 1e-9, "{run}");

    let rec = stepdrive_monitor::record::recording::Recorded::read(&recording).expect("read");
    let (_, states) = rec.runs.first().expect("the run's states");
    let start = num(mv, "start_s");
    let recorded = |from: f64| {
        states
            .iter()
            .filter(|s| s.t >= from)
            .map(|s| s.error.abs())
            .fold(0.0, f64::max)
    };
    assert_eq!(
        peak,
        recorded(start),
        "the move's peak against the recording"
    );
    assert_eq!(
        num(run, "max_abs_error_rad"),
        recorded(0.0),
        "the run's peak"
    );
}

/// A lockstep program streams θ(t) = 2 sin 2πt at 1 kHz from a file; the recorded status
/// carries the stream time the axis played at every tick, one lead behind the point's
/// arrival and running with the stack's clock; after the first 0.2 s the rotor is within
/// 2e-5 rad of the sine at that time (9.3e-6 measured; 8.3e-5 with the cubic
/// interpolation the stream had before, whose acceleration jumped at every point).
#[test]
fn a_streamed_sine_is_tracked_at_the_stream_time_the_status_names() {
    let dir = TempDir::new("stream-sine");
    let rows: String = (0..=2000)
        .map(|k| {
            let t = f64::from(k) * 1e-3;
            format!("{t},{}\n", 2.0 * (std::f64::consts::TAU * t).sin())
        })
        .collect();
    let csv = dir.file("sine.csv", &rows);
    let scenario = dir.file(
        "stream.toml",
        &format!(
            r#"name = "stream-sine"
[[program]]
at_s = 0.0
command = "enable"
[[program]]
at_s = 0.05
command = "stream"
file = "{}"
"#,
            csv.display()
        ),
    );
    let recording = dir.path("stream.mcap");
    let inst = instance("stream-sine");
    let out = run_proposed(
        &inst,
        &scenario,
        &["--duration", "2.2", "--record", recording.to_str().unwrap()],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let csv_dir = dir.path("csv");
    export_csv(&recording, &csv_dir);
    let status = Csv::read(&csv_dir.join("proposed_axis_status.csv"));
    let (t_col, theta_col, played_col) = (
        status.col("t ["),
        status.col("theta ["),
        status.col("stream_time"),
    );
    let (mut judged, mut worst) = (0, 0.0f64);
    for f in status.rows() {
        let Ok(played) = f[played_col].parse::<f64>() else {
            continue;
        };
        let t: f64 = f[t_col].parse().expect("t");
        // The first point came at the program's 0.05 s; the default lead is 50 ms.
        assert!((played - (t - 0.1)).abs() < 1e-9, "t {t}: played {played}");
        if (0.2..=2.0).contains(&played) {
            let theta: f64 = f[theta_col].parse().expect("theta");
            worst = worst.max((theta - 2.0 * (std::f64::consts::TAU * played).sin()).abs());
            judged += 1;
        }
    }
    assert!(judged > 3500, "{judged} statuses judged");
    assert!(worst < 2e-5, "peak |θ − θ_stream| {worst:e} rad");

    // The state channel's θ_d and error are the axis's setpoint (the stream), not the
    // scenario's profile, which this run never ran.
    let state = Csv::read(&csv_dir.join("proposed_state.csv"));
    let (t_col, theta_d_col, error_col) = (
        state.col("t ["),
        state.col("theta_d ["),
        state.col("error ["),
    );
    let (mut judged, mut worst_d, mut worst_e) = (0, 0.0f64, 0.0f64);
    for f in state.rows() {
        let t: f64 = f[t_col].parse().expect("t");
        if (0.3..=2.0).contains(&t) {
            let stream = 2.0 * (std::f64::consts::TAU * (t - 0.1)).sin();
            let theta_d: f64 = f[theta_d_col].parse().expect("theta_d");
            let error: f64 = f[error_col].parse().expect("error");
            worst_d = worst_d.max((theta_d - stream).abs());
            worst_e = worst_e.max(error.abs());
            judged += 1;
        }
    }
    assert!(judged > 30_000, "{judged} state samples judged");
    assert!(
        worst_d < 2e-5,
        "recorded θ_d off the stream by {worst_d:e} rad"
    );
    assert!(worst_e < 2e-5, "recorded |θ_d − θ| up to {worst_e:e} rad");
}

/// A program's moves table: a move replaced mid-way ("change immediately") is reported as
/// re-targeted at the replacing move's tick, with no duration; a move queued "after the
/// current move" is timed from where the one before it arrives, and both of those arrive.
#[test]
fn retargeted_and_queued_moves_are_reported_as_such() {
    let dir = TempDir::new("retarget");
    let scenario = dir.file(
        "retarget.toml",
        r#"name = "retarget"
[[program]]
at_s = 0.0
command = "enable"
[[program]]
at_s = 0.05
command = "move"
to = 10.0
[[program]]
at_s = 0.3
command = "move"
to = 2.0
[[program]]
at_s = 0.35
command = "move"
to = 4.0
after_current = true
"#,
    );
    let json = dir.path("retarget.json");
    let inst = instance("retarget");
    let out = run_proposed(
        &inst,
        &scenario,
        &["--duration", "2.0", "--json", json.to_str().unwrap()],
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    assert!(stdout.contains("re-targeted 0.3000"), "{stdout}");
    let doc = read_json(&json);
    // A program has no cruise window: its cruise figures are not reached, not 0.
    let run = run_of(&doc, "proposed");
    assert!(run["cruise_max_abs_voltage_v"].is_null(), "{run}");
    assert!(run["cruise_mean_id_a"].is_null(), "{run}");
    let cruise_v = stdout.lines().find(|l| l.starts_with("cruise max |v|"));
    assert!(cruise_v.is_some_and(|l| l.ends_with("n/a")), "{stdout}");
    let moves = run_of(&doc, "proposed")["moves"]
        .as_array()
        .expect("moves")
        .clone();
    assert_eq!(moves.len(), 3, "{moves:?}");
    assert!(moves[0]["duration_s"].is_null(), "{}", moves[0]);
    assert!((num(&moves[0], "retargeted_at_s") - 0.3).abs() < 1e-9);
    let second_end = num(&moves[1], "start_s") + num(&moves[1], "duration_s");
    assert!(moves[1]["retargeted_at_s"].is_null(), "{}", moves[1]);
    // The queued move starts where the second arrives, not at its command's 0.35 s.
    assert!(
        (num(&moves[2], "start_s") - second_end).abs() < 1e-9,
        "{moves:?}"
    );
    assert!(num(&moves[2], "start_s") > 0.35, "{moves:?}");
    assert_eq!(num(&moves[2], "target_rad"), 4.0, "{}", moves[2]);
    assert!(num(&moves[2], "duration_s") > 0.1, "{}", moves[2]);
    assert!(num(&moves[2], "peak_abs_error_rad") < 1e-3, "{}", moves[2]);
}

/// A lockstep run takes commands only from its scenario's program: a client reads its
/// status (its stack time advancing) and is told why a command cannot be sent, naming
/// `serve`, instead of waiting for an answer that never comes.
#[test]
fn a_lockstep_stack_shows_its_status_and_refuses_commands_naming_serve() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("lockstep-client");
    let inst = instance("lockstep-client");
    let mut run = start_long_run(&dir, &inst);
    wait_for_stack_time(&inst, &mut run, 0.05);
    let first = stack_time(&inst).expect("a status");
    let enable = stepdrive(&["axis", "--instance", &inst, "enable"]);
    assert_eq!(enable.status.code(), Some(1), "{}", text(&enable));
    assert!(
        text(&enable).contains("runs in lockstep")
            && text(&enable).contains(&format!("stepdrive serve --instance {inst}")),
        "{}",
        text(&enable)
    );
    assert!(
        wait_until(Duration::from_secs(10), || stack_time(&inst)
            .is_some_and(|t| t > first)),
        "the stack's time did not advance past {first} s"
    );
    signal(run.id(), libc::SIGINT);
    wait_with_timeout(&mut run, Duration::from_secs(30));
    assert!(wait_until(Duration::from_secs(5), || processes_with(&inst).is_empty()));
}

/// A client started before the stack it asks for (a script that launches both): it waits
/// for the stack, then for its position loop to serve commands, and its first request is
/// answered once the loops tick, after the drive's handshake and alignments. (Before: the
/// request went out before the position loop served the service, was lost, and the client
/// failed after 2 s with "answer … failed".)
#[test]
fn a_client_started_before_a_hardware_stack_gets_its_status() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("early-client");
    let scenario = dir.file("slow.toml", &slow_scenario());
    let json = dir.path("hw.json");
    let inst = instance("early-client");
    let status = std::process::Command::new(exe())
        .args(["axis", "status", "--instance", &inst])
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn axis status");
    let mut args = hardware_args(&scenario, &inst, &json);
    args.extend(["--duration", "2.0"]);
    let mut run = spawn_run(&args);
    let out = status.wait_with_output().expect("axis status");
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("Operation enabled"), "{}", text(&out));
    let ended = wait_with_timeout(&mut run, Duration::from_secs(60));
    assert!(ended.success(), "{}", stderr_of(&mut run));
}

/// `[[program]]` steps: enable `axis` at 0 s, move it to `to` at 0.1 s (`extra`: more of
/// the move step's fields).
fn enable_then_move(axis: usize, to: f64, extra: &str) -> String {
    format!(
        "[[program]]\nat_s = 0.0\naxis = {axis}\ncommand = \"enable\"\n\
         [[program]]\nat_s = 0.1\naxis = {axis}\ncommand = \"move\"\nto = {to}\n{extra}"
    )
}

/// The short scenario's three axes: x as the file says, y without load, z with twice the
/// inertia.
fn three_axes(extra: &str) -> String {
    format!(
        "{SHORT}{extra}
[[axis]]
name = \"x\"
[[axis]]
name = \"y\"
[axis.load]
torque_nm = 0.0
[[axis]]
name = \"z\"
[axis.motor]
inertia_kg_m2 = 2.0e-5
"
    )
}

/// A stack of three axes is three loop processes, each serving every axis; each axis's
/// figures are bit for bit those of a one-axis stack of its own scenario (the axes share
/// the processes, nothing else).
#[test]
fn three_axes_in_one_stack_are_each_what_a_stack_of_their_own_gives() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("three-axes");
    let inst = instance("three-axes");
    let three = dir.file("three.toml", &three_axes(""));
    let json = dir.path("three.json");
    let out = run_proposed(&inst, &three, &["--json", json.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    let doc = read_json(&json);
    let run = run_of(&doc, "proposed");
    let axes = run["axes"].as_array().expect("the other axes' reports");
    assert_eq!(axes.len(), 2, "{run}");
    let own = [
        (None, run),
        (Some("[load]\ntorque_nm = 0.0\n"), &axes[0]),
        (Some("[motor]\ninertia_kg_m2 = 2.0e-5\n"), &axes[1]),
    ];
    for (n, (tables, in_three)) in own.into_iter().enumerate() {
        if n > 0 {
            assert_eq!(in_three["axis"], n, "{in_three}");
            assert_eq!(in_three["name"], ["x", "y", "z"][n], "{in_three}");
        }
        assert_eq!(in_three["outcome"], "ok", "axis {n}: {in_three}");
        let alone = dir.file(
            &format!("alone{n}.toml"),
            &format!("{SHORT}{}", tables.unwrap_or("")),
        );
        let alone_json = dir.path(&format!("alone{n}.json"));
        let out = run_proposed(
            &format!("{inst}-{n}"),
            &alone,
            &["--json", alone_json.to_str().unwrap()],
        );
        assert!(out.status.success(), "{}", text(&out));
        let doc = read_json(&alone_json);
        let alone = run_of(&doc, "proposed");
        for key in [
            "samples",
            "cruise_max_abs_error_rad",
            "max_abs_error_rad",
            "final_error_rad",
            "mean_copper_loss_w",
            "max_abs_voltage_v",
        ] {
            assert_eq!(
                in_three[key], alone[key],
                "axis {n}'s {key}: in the three-axis stack, then alone"
            );
        }
    }
    // The axes differ where their scenarios do: y carries no load.
    assert_ne!(
        num(run, "cruise_mean_torque_nm"),
        num(&axes[0], "cruise_mean_torque_nm")
    );
}

/// One axis of three faults (its following-error window is too tight for its move): the
/// run fails with the fault's exit code, and the headline names that axis. By default the
/// other two quick-stop on that tick, neither faulted ([group] stop = "all"); with
/// stop = "own" they finish their moves.
#[test]
fn a_fault_on_one_axis_of_three_stops_the_others_and_fails_the_run_naming_it() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("three-axes-fault");
    let inst = instance("three-axes-fault");
    let program: String = [(0, 1.0), (1, -2.0), (2, 3.0)]
        .into_iter()
        .map(|(axis, to)| enable_then_move(axis, to, ""))
        .collect();
    let text_of = three_axes(&program).replace(
        "[axis.motor]\ninertia_kg_m2 = 2.0e-5\n",
        "[axis.limits]\nfollowing_error_window_rad = 1e-6\nfollowing_error_time_s = 0.001\n",
    );
    for (policy, others_finish) in [("", false), ("[group]\nstop = \"own\"\n", true)] {
        let scenario = dir.file("fault.toml", &format!("{text_of}{policy}"));
        let json = dir.path("fault.json");
        let out = run_proposed(&inst, &scenario, &["--json", json.to_str().unwrap()]);
        assert_eq!(out.status.code(), Some(3), "{}", text(&out));
        let said = text(&out);
        assert!(
            said.contains("axis 2 (z): FAULT (exit 3)") && said.contains("FOLLOWING_ERROR"),
            "{said}"
        );
        let doc = read_json(&json);
        assert_eq!(doc["outcome"], "fault", "{doc}");
        let run = run_of(&doc, "proposed");
        let axes = run["axes"].as_array().expect("the other axes' reports");
        assert_eq!(axes[1]["outcome"], "fault");
        for (axis, target) in [(run, 1.0), (&axes[0], -2.0)] {
            // Healthy, whatever the policy: no fault, no step-out.
            assert_eq!(axis["outcome"], "ok", "policy {policy:?}: {axis}");
            assert!(axis["axis_fault"].is_null(), "{axis}");
            assert!(num(axis, "max_abs_error_rad") < 1e-4, "{axis}");
            let moves = axis["moves"].as_array().expect("moves");
            assert_eq!(moves.len(), 1, "{axis}");
            assert_eq!(num(&moves[0], "target_rad"), target);
            // Stopped short with the faulted axis, or on to its target.
            assert_eq!(
                moves[0]["duration_s"].as_f64().is_some(),
                others_finish,
                "policy {policy:?}: {axis}"
            );
        }
    }
}

/// A coordinated move of three axes over different distances, each within its own move
/// limits: all leave on one tick and arrive on one tick, the slowest setting the
/// duration; the contour error is reported.
#[test]
fn a_coordinated_move_of_three_axes_leaves_and_arrives_on_one_tick() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("coordinated");
    let inst = instance("coordinated");
    let mut text_of = String::from("name = \"coordinated\"\n");
    let axes = [
        (1.0, (5.0, 50.0, 2000.0)),
        (-6.0, (10.0, 100.0, 5000.0)),
        (12.0, (8.0, 40.0, 1000.0)),
    ];
    for (axis, (to, _)) in axes.iter().enumerate() {
        text_of += &enable_then_move(axis, *to, "coordinated = true\n");
    }
    for (_, (v, a, j)) in axes {
        text_of += &format!(
            "[[axis]]\n[axis.limits]\nmove_v_rad_s = {v}\nmove_a_rad_s2 = {a}\nmove_j_rad_s3 = {j}\n"
        );
    }
    let scenario = dir.file("coordinated.toml", &text_of);
    let json = dir.path("coordinated.json");
    let out = run_proposed(&inst, &scenario, &["--json", json.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("peak contour error"), "{}", text(&out));
    let doc = read_json(&json);
    let run = run_of(&doc, "proposed");
    let all: Vec<&serde_json::Value> = std::iter::once(run)
        .chain(run["axes"].as_array().expect("axes"))
        .collect();
    let mv = |a: &serde_json::Value| a["moves"][0].clone();
    // z's own optimum, d/v + v/a + a/j over 12 rad, is the longest: it sets the duration.
    let slowest = 12.0 / 8.0 + 8.0 / 40.0 + 40.0 / 1000.0;
    for (n, a) in all.iter().enumerate() {
        let m = mv(a);
        assert_eq!(num(&m, "target_rad"), axes[n].0, "{a}");
        assert_eq!(
            m["start_s"],
            mv(all[0])["start_s"],
            "axis {n} left on another tick"
        );
        assert_eq!(
            m["duration_s"],
            mv(all[0])["duration_s"],
            "axis {n} arrived on another tick"
        );
        assert!(num(&m, "peak_abs_error_rad") < 1e-5, "{a}");
        let contour = num(a, "contour_peak_rad");
        assert!((0.0..1e-5).contains(&contour), "{a}");
    }
    let duration = num(&mv(all[0]), "duration_s");
    assert!(
        (duration - slowest).abs() < 2e-3,
        "duration {duration} s, the slowest axis's optimum {slowest} s"
    );
}

/// `serve` of a three-axis scenario: each axis is commanded by its index (`--axis`), the
/// others stay as they were; an index the stack does not have is refused.
#[test]
fn each_axis_of_a_served_three_axis_stack_is_commanded_by_its_index() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("served-three");
    let inst = instance("served-three");
    let scenario = dir.file("three.toml", &three_axes(""));
    let mut serve = spawn_serve(&inst, &["--scenario", scenario.to_str().unwrap()]);
    let axis = |n: &str, args: &[&str]| {
        let mut all = vec!["axis", "--instance", inst.as_str(), "--axis", n];
        all.extend(args);
        stepdrive(&all)
    };
    assert!(
        wait_until(Duration::from_secs(30), || axis("2", &["status"])
            .status
            .success()),
        "the served stack did not answer"
    );
    axis_2_alone_and_no_axis_3(axis);

    // A reader attaches to one axis: one the stack lacks is refused, naming the count; axis
    // 2's recording holds axis 2's next move.
    let reader = stepdrive(&["monitor", "--instance", &inst, "--axis", "3"]);
    assert!(!reader.status.success(), "{}", text(&reader));
    assert!(text(&reader).contains("has 3 axis"), "{}", text(&reader));
    let mcap = dir.path("axis2.mcap");
    let mut recorder = spawn_run(&[
        "record",
        "--instance",
        &inst,
        "--axis",
        "2",
        mcap.to_str().unwrap(),
    ]);
    assert!(
        wait_until(Duration::from_secs(30), || mcap.is_file()),
        "the recorder did not attach"
    );
    assert_reached(&axis(
        "2",
        &["move", "--to", "-1", "--wait", "--timeout", "10"],
    ));
    std::thread::sleep(Duration::from_millis(300));
    signal(recorder.id(), libc::SIGINT);
    wait_with_timeout(&mut recorder, Duration::from_secs(30));
    let csv = dir.path("csv");
    export_csv(&mcap, &csv);
    let states = Csv::read(&csv.join("proposed_state.csv"));
    let theta = states.col("theta [");
    let last: f64 = states
        .rows()
        .last()
        .and_then(|r| r[theta].parse().ok())
        .expect("axis 2 recorded");
    assert!(
        (last + 1.0).abs() < 1e-4,
        "axis 2 recorded ending at {last} rad"
    );

    // A client's coordinated move: refused as a whole while one of its axes is disabled
    // (the enabled axes do not move); taken by every axis on one tick once all are enabled,
    // and every axis arrives.
    let together = |to: &str| {
        stepdrive(&[
            "axis",
            "--instance",
            &inst,
            "move-together",
            "--to",
            to,
            "--wait",
            "--timeout",
            "10",
        ])
    };
    assert!(axis("0", &["enable"]).status.success());
    let refused = together("0.5,-0.5,0");
    assert!(!refused.status.success(), "{}", text(&refused));
    assert!(
        text(&refused).contains("axis 1") && text(&refused).contains("Operation enabled"),
        "{}",
        text(&refused)
    );
    let theta_of = |n: &str| -> f64 {
        let st = axis(n, &["status"]);
        text(&st)
            .lines()
            .find_map(|l| l.strip_prefix("θ "))
            .and_then(|v| v.trim().trim_end_matches(" rad").parse().ok())
            .unwrap_or_else(|| panic!("axis {n}: no θ in {}", text(&st)))
    };
    assert!(
        (theta_of("2") + 1.0).abs() < 1e-4,
        "axis 2 moved on a refused coordinated move"
    );
    // Right after an enable: the parts wait for the brake's release, then leave together.
    assert!(axis("1", &["enable"]).status.success());
    assert_moved_together(&together("0.5,-0.5,0"), 3);
    for (n, target) in [("0", 0.5), ("1", -0.5), ("2", 0.0)] {
        let theta = theta_of(n);
        assert!(
            (theta - target).abs() < 1e-4,
            "axis {n} at {theta} rad, not {target}"
        );
    }

    // A stream of the three axes: one origin, so every axis's stack time less the stream
    // time it plays is one figure; each ends where its path does.
    let mut rows = String::from("t,x,y,z\n");
    for k in 0..=1000 {
        let t = k as f64 * 1e-3;
        // From rest to rest: 0 … 1 … 0.
        let s = 0.5 * (1.0 - (std::f64::consts::TAU * t).cos());
        rows += &format!("{t},{},{},{}\n", 0.5 + 0.2 * s, -0.5 - 0.3 * s, 0.1 * s);
    }
    let file = dir.file("xyz.csv", &rows);
    let streamed = stepdrive(&[
        "axis",
        "--instance",
        &inst,
        "stream-together",
        file.to_str().unwrap(),
        "--priority",
        "0",
    ]);
    let out = text(&streamed);
    assert!(streamed.status.success(), "{out}");
    // One origin: the same offset on every axis, to one plant sample. Each figure comes
    // from that axis's last status, and once CI's stack at ordinary priority read one axis's
    // a sample later than the others' (1.476700 against 1.476650 s).
    let offsets: Vec<f64> = after(&out, "stream time played ")
        .into_iter()
        .filter_map(|v| v.trim_end_matches(" s").parse().ok())
        .collect();
    assert_eq!(offsets.len(), 3, "{out}");
    let spread = offsets.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b))
        - offsets.iter().fold(f64::INFINITY, |a, &b| a.min(b));
    assert!(
        spread <= 60e-6,
        "the axes play different stream times: {out}"
    );
    std::thread::sleep(Duration::from_millis(300));
    for (n, end) in [("0", 0.5), ("1", -0.5), ("2", 0.0)] {
        let theta = theta_of(n);
        assert!(
            (theta - end).abs() < 1e-3,
            "axis {n} ended at {theta} rad, not {end}"
        );
    }

    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    assert!(status.success(), "{}", stderr_of(&mut serve));
}

/// What runs one axis refuses a multi-axis scenario before anything starts, naming `run`.
#[test]
fn commands_that_run_one_axis_refuse_a_multi_axis_scenario() {
    let dir = TempDir::new("one-axis-only");
    let three = dir.file("three.toml", &three_axes(""));
    let three = three.to_str().unwrap();
    for args in [
        vec!["simulate", "--scenario", three],
        vec!["robustness", "--scenario", three, "--json", "/dev/null"],
    ] {
        let out = stepdrive(&args);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {}", text(&out));
        assert!(
            text(&out).contains("has 3 axes ([[axis]] tables)")
                && text(&out).contains("stepdrive run"),
            "{args:?}: {}",
            text(&out)
        );
    }
}

/// Hardware mode with two axes: `run` starts one emulator process serving a drive per axis
/// (each its own UDP address, session and alignment), one bridge talks to both, and each
/// axis's samples reach the supervisor on its own services. (Two emulated drives at 20 kHz
/// beside the whole stack overload two cores, so the run's verdict is not asserted here:
/// docs/axes.md has the figures.)
#[test]
fn a_two_axis_hardware_stack_runs_a_drive_per_axis() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("two-drives");
    let inst = instance("two-drives");
    let scenario = dir.file(
        "two.toml",
        "name = \"two-drives\"\n[run]\nduration_s = 0.3\n[[axis]]\nname = \"left\"\n[[axis]]\nname = \"right\"\n",
    );
    let json = dir.path("two.json");
    let out = hardware_run(&scenario, &inst, &json, &[]);
    let said = text(&out);
    assert!(
        !said.contains("NO DRIVE RUN") && !said.contains("alignment"),
        "{said}"
    );
    // Both drives aligned and streamed: each axis's samples came on its own services.
    let doc = read_json(&json);
    let left = run_of(&doc, "proposed");
    let right = &left["axes"][0];
    assert_eq!(right["name"], "right", "{left}");
    for axis in [left, right] {
        assert!(num(axis, "samples") > 0.0, "{axis}");
    }
}

/// A recording of a multi-axis run holds every axis on its own channels (axis n's under
/// `/<method>/axis/<n>/`): exported, each axis's states end at its own target and its
/// answers name its own move; plotted, each axis has its figures.
#[test]
fn a_three_axis_recording_holds_every_axis_and_exports_and_plots_each() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("three-axes-recorded");
    let inst = instance("three-axes-recorded");
    let targets = [0.5, -0.5, 1.0];
    let program: String = targets
        .iter()
        .enumerate()
        .map(|(axis, to)| enable_then_move(axis, *to, ""))
        .collect();
    let scenario = dir.file("three.toml", &three_axes(&program));
    let mcap = dir.path("three.mcap");
    let json = dir.path("three.json");
    let out = run_proposed(
        &inst,
        &scenario,
        &[
            "--record",
            mcap.to_str().unwrap(),
            "--json",
            json.to_str().unwrap(),
        ],
    );
    assert!(out.status.success(), "{}", text(&out));
    let doc = read_json(&json);
    let samples = num(run_of(&doc, "proposed"), "samples");

    let csv = dir.path("csv");
    export_csv(&mcap, &csv);
    for (n, target) in targets.iter().enumerate() {
        let prefix = if n == 0 {
            String::new()
        } else {
            format!("axis{n}_")
        };
        let states = Csv::read(&csv.join(format!("{prefix}proposed_state.csv")));
        let theta = states.col("theta [");
        let rows: Vec<Vec<&str>> = states.rows().collect();
        assert_eq!(
            rows.len() as f64,
            samples,
            "axis {n}: every sample recorded"
        );
        let last: f64 = rows
            .last()
            .and_then(|r| r[theta].parse().ok())
            .expect("a last sample");
        assert!(
            (last - target).abs() < 1e-4,
            "axis {n} ends at {last} rad, its target is {target}"
        );
        let acks = Csv::read(&csv.join(format!("{prefix}proposed_axis_ack.csv")));
        let (kind, to) = (acks.col("kind"), acks.col("target"));
        assert!(
            acks.rows()
                .any(|f| f[kind] == "move" && f[to].parse::<f64>().ok() == Some(*target)),
            "axis {n}'s answers name its own move to {target}"
        );
    }

    let plots = dir.path("plots");
    let drawn = stepdrive(&[
        "plot",
        "--out",
        plots.to_str().unwrap(),
        mcap.to_str().unwrap(),
    ]);
    assert!(drawn.status.success(), "{}", text(&drawn));
    for file in ["position.png", "position-axis1.png", "position-axis2.png"] {
        assert!(plots.join(file).is_file(), "{file} drawn");
    }
}

/// Hardware mode, a drive per axis: one axis's drive latches a fault mid-move; the other
/// axis quick-stops ([group] stop = "all"), neither faulted nor stepped out, and the run
/// fails naming the faulted axis. (Ordinary scheduling, as every test stack here: the
/// drives' plans carry the periods the host misses.)
///
/// Ignored in CI: at ordinary priority on a busy two-core machine the host's first
/// commands can come later than the drives' 50 ms watchdog (a fresh-clone CI run latched
/// WATCHDOG on one drive at 0.07 s), which is the drive doing its job, not the stop policy
/// failing. Run it with `cargo test --release --test stack axis:: -- --ignored`.
#[test]
#[ignore = "timing: at ordinary priority the drives' watchdogs can trip at start-up"]
fn a_drive_fault_on_one_axis_quick_stops_the_other_in_hardware_mode() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("two-drives-fault");
    let inst = instance("two-drives-fault");
    let program: String = [0, 1]
        .into_iter()
        .map(|axis| enable_then_move(axis, 20.0, ""))
        .collect();
    let scenario = dir.file(
        "two.toml",
        &format!(
            "name = \"two-drives-fault\"\n[run]\nduration_s = 3.0\n{program}\
             [[axis]]\nname = \"left\"\n[[axis]]\nname = \"right\"\n"
        ),
    );
    let (a, b) = (free_udp_port(), free_udp_port());
    let listen = format!("127.0.0.1:{a},127.0.0.1:{b}");
    let mut args = vec!["emulate-drive", "--listen", &listen];
    args.extend(ORDINARY_SCHEDULING);
    args.extend([
        "--scenario",
        scenario.to_str().unwrap(),
        "--inject-axis",
        "1",
        // Counted from the drive's first SAMPLE (its phase-B step), before the host's run
        // starts: on a busy machine the start-up took 0.95 s of a 1.0 s count, and the
        // fault came before the moves. 2 s leaves the moves a second at least.
        "--overcurrent-after",
        "2.0",
    ]);
    let mut drives = spawn_logged(&args);
    let json = dir.path("two.json");
    let out = hardware_run(&scenario, &inst, &json, &["--drive", &listen]);
    signal(drives.id(), libc::SIGTERM);
    let _ = wait_with_timeout(&mut drives, Duration::from_secs(10));
    let said = text(&out);
    assert_eq!(out.status.code(), Some(3), "{said}");
    assert!(
        said.contains("axis 1 (right): FAULT (exit 3)") && said.contains("OVERCURRENT"),
        "{said}"
    );
    assert!(
        said.contains("every other enabled axis quick-stops"),
        "the stop policy acted: {said}"
    );
    let doc = read_json(&json);
    let left = run_of(&doc, "proposed");
    assert_eq!(left["outcome"], "ok", "{left}");
    assert_eq!(num(left, "fault_samples"), 0.0, "{left}");
    assert!(num(left, "max_abs_error_rad") < 1e-2, "no step-out: {left}");
    assert!(
        left["moves"][0]["start_s"]
            .as_f64()
            .is_some_and(|t| t < 0.11),
        "both drives were enabled together: the left axis's move started on time: {left}"
    );
    assert_eq!(left["axes"][0]["outcome"], "fault", "{left}");
}
