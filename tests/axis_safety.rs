//! Issue 44's findings on a served axis, as a new user met them: commands that must never
//! move the motor unasked (a relative move counting from a jog's soft limit, options read
//! after the move went out, limits the axis cannot carry out, a second queued move), and a
//! motor that must stop when its client does (Ctrl-C during a wait, a jogging client killed,
//! a stream the axis cannot follow).

use crate::common::*;
use std::process::Output;
use std::time::{Duration, Instant};

/// A served stack on its own instance, and `stepdrive axis` against it.
struct Served {
    inst: String,
    serve: Launched,
}

impl Served {
    fn start(name: &str) -> Self {
        let inst = instance(name);
        let serve = spawn_serve(&inst, &[]);
        let this = Self { inst, serve };
        assert!(
            wait_until(Duration::from_secs(30), || this
                .axis(&["status"])
                .status
                .success()),
            "the served stack did not answer"
        );
        this
    }

    /// [`Self::start`], then `axis enable`.
    fn enabled(name: &str) -> Self {
        let this = Self::start(name);
        let on = this.axis(&["enable"]);
        assert!(on.status.success(), "{}", text(&on));
        this
    }

    fn args<'a>(&'a self, args: &[&'a str]) -> Vec<&'a str> {
        let mut all = vec!["axis", "--instance", self.inst.as_str()];
        all.extend(args);
        all
    }

    fn axis(&self, args: &[&str]) -> Output {
        stepdrive(&self.args(args))
    }

    /// `axis ARGS` in the background.
    fn spawn(&self, args: &[&str]) -> Launched {
        spawn_run(&self.args(args))
    }

    fn status(&self) -> String {
        text(&self.axis(&["status"]))
    }

    /// A number after `label` in `axis status` (`θ            1.000000 rad`).
    fn field(&self, label: &str) -> f64 {
        let st = self.status();
        st.lines()
            .find_map(|l| l.strip_prefix(label))
            .and_then(|l| l.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no {label:?} in {st}"))
    }

    /// Waits until the setpoint and the rotor stand still; the status then.
    fn standstill(&self, within: Duration) -> String {
        let mut last = String::new();
        let at_rest = wait_until(within, || {
            last = self.status();
            let st = &last;
            let speed = |label: &str| {
                st.lines()
                    .find_map(|l| l.strip_prefix(label))
                    .and_then(|l| l.split_whitespace().next())
                    .and_then(|v| v.parse::<f64>().ok())
            };
            let omega_d = st
                .lines()
                .find_map(|l| l.split("ω_d ").nth(1))
                .and_then(|l| l.split_whitespace().next())
                .and_then(|v| v.trim_end_matches(',').parse::<f64>().ok());
            omega_d == Some(0.0) && speed("ω ").is_some_and(|w| w.abs() < 0.05)
        });
        assert!(at_rest, "no standstill within {within:?}: {last}");
        last
    }

    fn stop(mut self) {
        signal(self.serve.id(), libc::SIGINT);
        let _ = wait_or_explain(&mut self.serve, Duration::from_secs(30), &self.inst);
        assert!(processes_with(&self.inst).is_empty());
    }
}

/// Item 2 of issue 44: options are read before anything is sent (a bad `--timeout` went
/// out with the move, which ran, and failed after), and limits the axis cannot carry out are
/// refused (1e-300 faulted the axis, 1e-6 never arrived): the axis neither moves nor
/// faults.
#[test]
fn bad_options_and_limits_are_refused_before_anything_moves() {
    let _turn = one_stack_at_a_time();
    let s = Served::enabled("refused-first");
    let theta0 = s.field("θ ");
    for bad in ["nan", "inf", "0", "1e20", "-1"] {
        let out = s.axis(&["move", "--to", "0.25", "--wait", "--timeout", bad]);
        assert_eq!(
            out.status.code(),
            Some(2),
            "--timeout {bad}: {}",
            text(&out)
        );
        assert!(!text(&out).contains("move taken"), "{}", text(&out));
    }
    for args in [
        &["move", "--to", "0.25", "--vmax", "1e-300"][..],
        &["move", "--to", "0.25", "--vmax", "1e-6"],
        &["move", "--to", "0.25", "--amax", "1e-300"],
        &["move", "--to", "0.25", "--jmax", "1e-300"],
        &["move", "--to", "5", "--vmax", "1e-3"],
        &["jog", "--velocity", "1e-300"],
    ] {
        let out = s.axis(args);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {}", text(&out));
        assert!(text(&out).contains("refused"), "{args:?}: {}", text(&out));
    }
    std::thread::sleep(Duration::from_millis(200));
    let st = s.status();
    assert!(st.contains("state        Operation enabled"), "{st}");
    assert!(st.contains("fault        0x0 "), "{st}");
    assert!(
        (s.field("θ ") - theta0).abs() < 1e-3,
        "the axis moved: {st}"
    );
    s.stop();
}

/// Item 1 of issue 44: after a jog and a stop, a relative move counted from the jog's
/// target, the soft limit (9999 rad): it counts from where the axis stands; after a quick
/// stop and an enable too.
#[test]
fn a_relative_move_after_a_jog_and_a_stop_counts_from_where_the_axis_stands() {
    let _turn = one_stack_at_a_time();
    let s = Served::enabled("relative");
    let mut jog = s.spawn(&["jog", "--velocity", "2"]);
    assert!(
        wait_until(Duration::from_secs(10), || (s.field("ω ") - 2.0).abs()
            < 0.05),
        "no jog: {}",
        s.status()
    );
    // Ctrl-C ends a held jog with a stop (a jog command that returned at once left the
    // jog running to the next command).
    signal(jog.id(), libc::SIGINT);
    let _ = wait_with_timeout(&mut jog, Duration::from_secs(10));
    assert!(s.axis(&["stop"]).status.success());
    s.standstill(Duration::from_secs(5));
    let stood = s.field("θ ");
    let mv = s.axis(&[
        "move",
        "--relative",
        "--to",
        "-1",
        "--wait",
        "--timeout",
        "5",
    ]);
    assert_reached(&mv);
    let target = s.field("target ");
    assert!(
        (target - (stood - 1.0)).abs() < 1e-3,
        "target {target} rad, stood at {stood}"
    );
    assert!(s.axis(&["quick-stop"]).status.success());
    assert!(s.axis(&["enable"]).status.success());
    let stood = s.field("θ ");
    let mv = s.axis(&[
        "move",
        "--relative",
        "--to",
        "0.5",
        "--wait",
        "--timeout",
        "3",
    ]);
    assert_reached(&mv);
    assert!(
        (s.field("target ") - (stood + 0.5)).abs() < 1e-3,
        "{}",
        s.status()
    );
    s.stop();
}

/// Item 3 of issue 44: Ctrl-C during `move --wait` was ignored until the target; it ends
/// the wait, halts the move this command started and exits 130.
#[test]
fn ctrl_c_during_a_waited_move_halts_it_and_exits_130() {
    let _turn = one_stack_at_a_time();
    let s = Served::enabled("interrupted");
    let from = s.field("θ ");
    let far = format!("{}", from + 30.0);
    let mut waiting = s.spawn(&["move", "--to", &far, "--wait"]);
    assert!(
        wait_until(Duration::from_secs(10), || s.field("ω ") > 5.0),
        "the move did not start: {}",
        s.status()
    );
    let interrupted = Instant::now();
    signal(waiting.id(), libc::SIGINT);
    let code = wait_with_timeout(&mut waiting, Duration::from_secs(10));
    let said = stderr_of(&mut waiting);
    assert_eq!(code.code(), Some(130), "{said}");
    assert!(
        interrupted.elapsed() < Duration::from_secs(3),
        "exit {:?} after Ctrl-C",
        interrupted.elapsed()
    );
    assert!(said.contains("halted"), "{said}");
    let st = s.standstill(Duration::from_secs(5));
    assert!(s.field("θ ") < from + 25.0, "the move went on: {st}");
    s.stop();
}

/// Item 8 of issue 44: CiA 402's set-point buffer holds one move: a second "after the
/// current" was taken and silently replaced the first; it is refused. A move that changes
/// at once drops the one waiting (it played after it).
#[test]
fn the_set_point_buffer_holds_one_move_and_a_change_at_once_drops_it() {
    let _turn = one_stack_at_a_time();
    let s = Served::enabled("buffer");
    let at = s.field("θ ");
    let to = |d: f64| format!("{}", at + d);
    let (t20, t21, t22, t2) = (to(20.0), to(21.0), to(22.0), to(2.0));
    assert!(s.axis(&["move", "--to", &t20]).status.success());
    let queued = s.axis(&["move", "--after-current", "--to", &t21]);
    assert!(queued.status.success(), "{}", text(&queued));
    let full = s.axis(&["move", "--after-current", "--to", &t22]);
    assert_eq!(full.status.code(), Some(1), "{}", text(&full));
    assert!(text(&full).contains("set-point buffer"), "{}", text(&full));
    let now = s.axis(&["move", "--to", &t2, "--wait", "--timeout", "10"]);
    assert_reached(&now);
    std::thread::sleep(Duration::from_millis(1500));
    let st = s.standstill(Duration::from_secs(5));
    assert!(
        (s.field("θ ") - (at + 2.0)).abs() < 1e-3,
        "the queued move played after the one that changed at once: {st}"
    );
    s.stop();
}

/// Item 6 of issue 44, on the stack's host: a jogging client killed left the jog running
/// (to the soft limit, 13 min away at 13 rad/s): the axis quick-stops a jog its client
/// stops renewing.
#[test]
fn a_killed_jogging_client_leaves_the_motor_stopped() {
    let _turn = one_stack_at_a_time();
    let s = Served::enabled("jog-killed");
    let mut jog = s.spawn(&["jog", "--velocity", "3"]);
    assert!(
        wait_until(Duration::from_secs(10), || (s.field("ω ") - 3.0).abs()
            < 0.05),
        "no jog: {}",
        s.status()
    );
    let killed = Instant::now();
    signal(jog.id(), libc::SIGKILL);
    let _ = jog.wait();
    // The jog timeout (0.5 s) plus 3 rad/s at the quick-stop rate (15 ms), and the status
    // polls' slack on a shared machine.
    let st = s.standstill(Duration::from_secs(4));
    let took = killed.elapsed();
    assert!(st.contains("Quick stop active"), "{st}");
    assert!(st.contains("warning 0x20"), "JOG_LOST: {st}");
    assert!(
        took < Duration::from_secs(3),
        "standstill {took:?} after the kill"
    );
    println!("jogging client killed → standstill in {took:?}");
    s.stop();
}

/// Item 7 of issue 44: a stream with points beyond the soft limits, or one the axis can
/// only follow within its limits (a 1000 rad step), reported "N points streamed" and exit
/// 0; each ends non-zero with the reason, and the axis does not run on.
#[test]
fn a_stream_the_axis_cannot_follow_ends_non_zero_with_the_reason() {
    let _turn = one_stack_at_a_time();
    let s = Served::enabled("stream-refused");
    let theta0 = s.field("θ ");
    let dir = TempDir::new("stream-refused");
    // From where the axis stands, at rest, then points beyond the soft limits (1e4 rad).
    let beyond: String = (0..=300)
        .map(|k| {
            let t = k as f64 * 0.01;
            let theta = if k < 10 { theta0 } else { 20_000.0 };
            format!("{t},{theta}\n")
        })
        .collect();
    let file = dir.file("beyond.csv", &beyond);
    let out = s.axis(&["stream", file.to_str().expect("UTF-8"), "--priority", "0"]);
    assert_ne!(out.status.code(), Some(0), "{}", text(&out));
    assert!(text(&out).contains("soft"), "{}", text(&out));
    let st = s.standstill(Duration::from_secs(5));
    assert!(s.field("θ ") < theta0 + 50.0, "the axis ran on: {st}");

    // A step of 1000 rad, within the soft limits: followed only at the axis's limits.
    assert!(s.axis(&["enable"]).status.success());
    let theta0 = s.field("θ ");
    let step: String = (0..=100)
        .map(|k| {
            let t = k as f64 * 0.01;
            let theta = if k < 20 { theta0 } else { theta0 + 1000.0 };
            format!("{t},{theta}\n")
        })
        .collect();
    let file = dir.file("step.csv", &step);
    let out = s.axis(&["stream", file.to_str().expect("UTF-8"), "--priority", "0"]);
    assert_ne!(out.status.code(), Some(0), "{}", text(&out));
    assert!(text(&out).contains("could not follow"), "{}", text(&out));
    let st = s.standstill(Duration::from_secs(10));
    assert!(s.field("θ ") < theta0 + 100.0, "the axis ran on: {st}");
    s.stop();
}
