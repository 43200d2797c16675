//! Issue 44, items 4 and 5: a stack that stops, or loses a process, stops the motor first.
//! Ctrl-C of `serve` mid-move brings the axis to a standstill with its outputs off before
//! the processes go, and says where it stood; a killed loop's survivors are given the time
//! their stand-in needs (the current loop's own stop, the device's watchdog); a killed
//! gateway is logged at once, the motion its remote client started quick-stopped, and the
//! gateway restarted; a killed RT-throttling guard is replaced, so that throttling is still
//! restored when the launcher is killed.

use crate::common::*;
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use stepdrive_client::{Axis, Limits};

/// `stepdrive serve` on `inst` started as a shell starts a job: in a process group of its
/// own, so that a terminal's Ctrl-C is [`ctrl_c`] (SIGINT to the whole group). Its stderr is
/// followed line by line ([`Log`]); its stdout is piped.
fn serve_job(inst: &str, extra: &[&str]) -> (Launched, Log) {
    let mut child = Command::new(exe())
        .args(["serve", "--instance", inst])
        .args(ORDINARY_STACK)
        .args(extra)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0)
        .spawn()
        .expect("spawn stepdrive serve");
    let log = Log::follow(child.stderr.take().expect("stderr"));
    (Launched::new(child), log)
}

/// A terminal's Ctrl-C: SIGINT to the job's process group.
fn ctrl_c(job: &Launched) {
    // SAFETY: kill(2) of the process group this test started.
    unsafe { libc::kill(-(job.id() as libc::pid_t), libc::SIGINT) };
}

/// A process's stderr, each line with when it came.
#[derive(Clone)]
struct Log(Arc<Mutex<Vec<(Instant, String)>>>);

impl Log {
    fn follow(stderr: std::process::ChildStderr) -> Self {
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&lines);
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Ok(mut l) = sink.lock() {
                    l.push((Instant::now(), line));
                }
            }
        });
        Self(lines)
    }

    /// When the first line containing `needle` came.
    fn when(&self, needle: &str) -> Option<Instant> {
        let lines = self.0.lock().unwrap_or_else(|p| p.into_inner());
        lines
            .iter()
            .find(|(_, l)| l.contains(needle))
            .map(|(at, _)| *at)
    }

    fn text(&self) -> String {
        let lines = self.0.lock().unwrap_or_else(|p| p.into_inner());
        lines
            .iter()
            .map(|(_, l)| l.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    }
}

/// The axis of the stack on `inst` (started as `serve`), once its stack time has passed
/// 0.2 s.
fn axis_of(inst: &str, serve: &mut Launched) -> Axis {
    wait_for_stack_time(inst, serve, 0.2);
    Axis::connect(inst, 0).expect("connect to the served axis")
}

/// Enables `axis` and sends it towards 5000 rad at its move defaults (13.13 rad/s); returns
/// once it cruises.
fn cruise(axis: &mut Axis) {
    axis.enable().expect("enable");
    axis.move_to(5000.0, Limits::default())
        .expect("a long move");
    assert!(
        wait_until(Duration::from_secs(10), || axis
            .status()
            .is_ok_and(|s| s.omega_rad_s > 13.0)),
        "the axis never cruised: {:?}",
        axis.status()
    );
}

/// Every speed `ω <x> rad/s` a line names.
fn speeds(line: &str) -> Vec<f64> {
    line.split("ω ")
        .skip(1)
        .filter_map(|rest| rest.split_whitespace().next()?.parse().ok())
        .collect()
}

/// The `served ...` line of a served stack's stdout.
fn served_line(stdout: &str) -> String {
    stdout
        .lines()
        .find(|l| l.starts_with("served "))
        .unwrap_or_else(|| panic!("no `served` line in {stdout:?}"))
        .to_string()
}

/// The speed at which the line says the rotor stood still (its first) is a standstill's.
fn assert_stood_still(line: &str) {
    let w = speeds(line);
    assert!(
        w.first().is_some_and(|w| w.abs() <= 0.05),
        "{w:?} in {line}"
    );
}

/// Every speed the line names is a standstill's.
fn assert_still(line: &str) {
    let w = speeds(line);
    assert!(!w.is_empty(), "no speed in {line}");
    assert!(w.iter().all(|w| w.abs() <= 0.05), "{w:?} in {line}");
}

/// Item 4. Before: SIGINT during a 13.13 rad/s move ended `serve` in 0.74 s with exit 0, the
/// axis still in Operation enabled at 13.13 rad/s (a terminal's Ctrl-C stopped every loop at
/// once). Now the axis is quick-stopped, waited to rest within a bound from its speed and its
/// quick-stop deceleration, its outputs turned off with the brake applied, and the last
/// line says where it stood; exit 0 as before.
#[test]
fn ctrl_c_of_serve_stops_a_moving_axis_and_turns_its_outputs_off_before_the_stack_goes() {
    let _turn = one_stack_at_a_time();
    let inst = instance("ctrlc");
    let (mut serve, log) = serve_job(&inst, &[]);
    let mut axis = axis_of(&inst, &mut serve);
    cruise(&mut axis);
    ctrl_c(&serve);
    let status = wait_or_explain(&mut serve, Duration::from_secs(30), &inst);
    let stdout = stdout_of(&mut serve);
    assert_eq!(status.code(), Some(0), "{stdout}\n{}", log.text());
    let line = served_line(&stdout);
    for words in [
        "stopped (SIGINT/SIGTERM)",
        "stood still",
        "after its quick stop",
        "outputs off",
        "Switch on disabled",
        "brake applied",
    ] {
        assert!(line.contains(words), "{words:?} not in {line}");
    }
    assert_still(&line);
    assert!(processes_with(&inst).is_empty());
}

/// Item 4, a loop killed mid-move. Before: `serve` tore the rest down in 0.46 s and the
/// stand-ins never acted. Now a killed position loop leaves the current loop the time its
/// own stop needs (the rotor at rest, held), a killed current loop leaves the plant's
/// watchdog the time to turn the outputs off (and the brake to stop the rotor), and a
/// killed plant is said to leave nothing that can move the motor; exit 5, naming the dead
/// process and where the motor stood.
#[test]
fn a_killed_loop_leaves_its_survivors_the_time_to_stop_the_motor() {
    let _turn = one_stack_at_a_time();
    for (victim, said) in [
        ("position-loop", "held by the current loop"),
        (
            "current-loop",
            "had its outputs off by the plant's watchdog",
        ),
        ("plant", "nothing can move the motor"),
    ] {
        let inst = instance(&format!("stopkill-{victim}"));
        let (mut serve, log) = serve_job(&inst, &[]);
        let mut axis = axis_of(&inst, &mut serve);
        cruise(&mut axis);
        let pid = pid_of_role(&inst, victim).expect("the victim's pid");
        signal(pid, libc::SIGKILL);
        let status = wait_or_explain(&mut serve, Duration::from_secs(30), &inst);
        let stdout = stdout_of(&mut serve);
        assert_eq!(status.code(), Some(5), "{victim}: {stdout}\n{}", log.text());
        let line = served_line(&stdout);
        assert!(line.contains(victim), "{victim}: {line}");
        assert!(line.contains(said), "{victim}: {said:?} not in {line}");
        match victim {
            "position-loop" => assert_still(&line),
            "current-loop" => {
                assert!(line.contains("COMMAND_TIMEOUT"), "{line}");
                assert!(line.contains("at rest on its brake"), "{line}");
                assert_still(&line);
            }
            _ => {}
        }
        assert!(processes_with(&inst).is_empty());
    }
}

/// Item 4 in hardware mode (an emulated drive is started for it): Ctrl-C stops the axis as
/// in realtime (the drive's brake, if it has one, is its own: the line says the axis applies
/// none); a killed current loop leaves the drive's watchdog the time to turn the outputs
/// off.
#[test]
fn in_hardware_mode_ctrl_c_stops_the_axis_and_a_killed_current_loop_trips_the_drives_watchdog() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("hwstop");
    let scenario = dir.file("slow.toml", SLOW_RATES);
    let scenario = scenario.to_str().expect("a UTF-8 path");
    for (victim, code) in [(None, 0), (Some("current-loop"), 5)] {
        let inst = instance(&format!("hw-{code}"));
        let (mut serve, log) = serve_job(&inst, &["--mode", "hardware", "--scenario", scenario]);
        let mut axis = axis_of(&inst, &mut serve);
        cruise(&mut axis);
        match victim {
            None => ctrl_c(&serve),
            Some(v) => signal(
                pid_of_role(&inst, v).expect("the victim's pid"),
                libc::SIGKILL,
            ),
        }
        let status = wait_or_explain(&mut serve, Duration::from_secs(30), &inst);
        let stdout = stdout_of(&mut serve);
        assert_eq!(status.code(), Some(code), "{stdout}\n{}", log.text());
        let line = served_line(&stdout);
        match victim {
            None => {
                assert!(line.contains("stood still"), "{line}");
                assert!(line.contains("Switch on disabled"), "{line}");
                // The drive's brake is not the axis's (the wire protocol carries none): once
                // the outputs are off, the load may turn the rotor, and the line says so.
                assert!(line.contains("no holding brake"), "{line}");
                assert_stood_still(&line);
            }
            Some(_) => {
                assert!(
                    line.contains("had its outputs off by the drive's watchdog"),
                    "{line}"
                );
                assert!(line.contains("WATCHDOG"), "{line}");
            }
        }
        assert!(processes_with(&inst).is_empty());
    }
}

/// Item 4 for `run`: a realtime run interrupted mid-cruise (13.13 rad/s) stops the motor as
/// `serve` does before its processes go, and says so; exit 130 as before.
#[test]
fn ctrl_c_of_a_realtime_run_stops_the_motor_first() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("runstop");
    let scenario = dir.file(
        "cruise.toml",
        "name = \"cruise\"\n[trajectory]\naccel_s = 0.1\ncruise_s = 30.0\ndecel_s = 0.1\nhold_s = 0.5\n",
    );
    let inst = instance("runstop");
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "30"));
    let mut run = Launched::new(
        Command::new(exe())
            .args(&args)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .process_group(0)
            .spawn()
            .expect("spawn stepdrive run"),
    );
    wait_for_stack_time(&inst, &mut run, 1.0);
    ctrl_c(&run);
    let status = wait_or_explain(&mut run, Duration::from_secs(30), &inst);
    let stdout = stdout_of(&mut run);
    assert_eq!(
        status.code(),
        Some(130),
        "{stdout}\n{}",
        stderr_of(&mut run)
    );
    let line = stdout
        .lines()
        .find(|l| l.contains("stood still"))
        .unwrap_or_else(|| panic!("no standstill said in {stdout}"));
    assert!(line.contains("outputs off"), "{line}");
    // The paper's experiment runs without a holding brake.
    assert!(line.contains("no holding brake"), "{line}");
    assert_stood_still(line);
    assert!(processes_with(&inst).is_empty());
}

/// Item 5. Before: `kill -9` of the gateway `serve --gateway` started logged nothing until
/// the end, the motion its remote client had started ran on, and `serve` ended 0. Now its
/// death is logged at once, the remote client's move is quick-stopped, and the gateway is
/// restarted (a new client connects through it); the last line says it was.
#[test]
fn a_killed_gateway_is_logged_at_once_its_remote_motion_stopped_and_it_is_restarted() {
    let _turn = one_stack_at_a_time();
    let inst = instance("gwkill");
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let (mut serve, log) = serve_job(&inst, &["--gateway", &endpoint]);
    wait_for_stack_time(&inst, &mut serve, 0.2);
    let mut remote = Axis::connect_remote(&endpoint, &inst, 0).expect("a remote client");
    cruise(&mut remote);
    let gateway = pid_of_role(&inst, "gateway").expect("the gateway's pid");
    let killed = Instant::now();
    signal(gateway, libc::SIGKILL);
    let mut local = Axis::connect(&inst, 0).expect("a local client");
    assert!(
        wait_until(Duration::from_secs(3), || local.status().is_ok_and(|s| {
            s.axis_state() == Some(stepdrive_shared::axis::AxisState::QuickStopActive)
                && s.omega_rad_s.abs() < 0.05
        })),
        "the remote client's move was not quick-stopped: {:?}\n{}",
        local.status(),
        log.text()
    );
    let said = log
        .when("the gateway (pid")
        .unwrap_or_else(|| panic!("the gateway's death was not logged:\n{}", log.text()));
    assert!(
        said.duration_since(killed) < Duration::from_secs(1),
        "logged {:?} after the kill",
        said.duration_since(killed)
    );
    assert!(log.text().contains("signal: 9"), "{}", log.text());
    assert!(log.text().contains("quick-stopped"), "{}", log.text());
    // Restarted: a client connects through it again.
    assert!(
        wait_until(Duration::from_secs(10), || {
            pid_of_role(&inst, "gateway").is_some_and(|p| p != gateway)
                && Axis::connect_remote(&endpoint, &inst, 0).is_ok()
        }),
        "no gateway answers after the restart:\n{}",
        log.text()
    );
    drop(remote);
    ctrl_c(&serve);
    let status = wait_or_explain(&mut serve, Duration::from_secs(30), &inst);
    let stdout = stdout_of(&mut serve);
    assert_eq!(status.code(), Some(0), "{stdout}\n{}", log.text());
    assert!(
        served_line(&stdout).contains("the gateway was restarted"),
        "{stdout}"
    );
    assert!(processes_with(&inst).is_empty());
}

/// Item 5, bounded: a gateway that keeps dying is restarted three times, and its fourth
/// death stops the stack as Ctrl-C does (the axes brought to a standstill), exit 5 naming
/// it.
#[test]
fn a_gateway_that_keeps_dying_is_restarted_three_times_then_the_stack_stops() {
    let _turn = one_stack_at_a_time();
    let inst = instance("gwagain");
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let (mut serve, log) = serve_job(&inst, &["--gateway", &endpoint]);
    let mut axis = axis_of(&inst, &mut serve);
    cruise(&mut axis);
    let mut killed = Vec::new();
    for death in 1..=4 {
        let pid = wait_until(Duration::from_secs(10), || {
            pid_of_role(&inst, "gateway").is_some_and(|p| !killed.contains(&p))
        })
        .then(|| pid_of_role(&inst, "gateway"))
        .flatten()
        .unwrap_or_else(|| panic!("no gateway to kill for death {death}:\n{}", log.text()));
        killed.push(pid);
        signal(pid, libc::SIGKILL);
    }
    let status = wait_or_explain(&mut serve, Duration::from_secs(30), &inst);
    let stdout = stdout_of(&mut serve);
    assert_eq!(status.code(), Some(5), "{stdout}\n{}", log.text());
    let line = served_line(&stdout);
    assert!(line.contains("restarted 3 times already"), "{line}");
    assert!(line.contains("stood still"), "{line}");
    assert!(line.contains("Switch on disabled"), "{line}");
    assert_still(&line);
    assert!(processes_with(&inst).is_empty());
}

/// Item 5, the RT-throttling guard (root only: it writes sched_rt_runtime_us). Before:
/// killed, nothing was logged, and a launcher killed afterwards left throttling lifted for
/// good. Now its death is logged at once and a new guard holds the saved value: throttling
/// stays lifted for the stack and is restored when the launcher is killed.
#[test]
fn a_killed_rt_throttling_guard_is_replaced_and_throttling_is_still_restored() {
    let read = rt_runtime_us;
    let Some(before) = rt_throttling_to_check() else {
        return;
    };
    let _turn = one_stack_at_a_time();
    let inst = instance("guardkill");
    // SCHED_FIFO 1 without spinning or pinning: gentle on a shared machine; a stack with
    // priorities is what lifts throttling.
    let mut child = Command::new(exe())
        .args([
            "serve",
            "--instance",
            &inst,
            "--priority",
            "1",
            "--cpus",
            "none",
        ])
        .args(["--plant-wait", "sleep", "--current-wait", "sleep"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn stepdrive serve");
    let log = Log::follow(child.stderr.take().expect("stderr"));
    let mut serve = Launched::new(child);
    let guard_of = |parent: u32| -> Option<u32> {
        let out = Command::new("pgrep")
            .args(["-P", &parent.to_string(), "-f", "rt-throttling-guard"])
            .output()
            .ok()?;
        String::from_utf8_lossy(&out.stdout).trim().parse().ok()
    };
    let lifted = wait_until(Duration::from_secs(30), || {
        read() == Some(-1) && guard_of(serve.id()).is_some()
    });
    let first = guard_of(serve.id());
    if let Some(pid) = first.filter(|_| lifted) {
        let killed = Instant::now();
        signal(pid, libc::SIGKILL);
        let replaced = wait_until(Duration::from_secs(5), || {
            guard_of(serve.id()).is_some_and(|p| p != pid)
        });
        let said = log.when("RT-throttling guard exited");
        signal(serve.id(), libc::SIGKILL);
        let _ = serve.wait();
        let restored = wait_until(Duration::from_secs(5), || read() == Some(before));
        let now = read();
        // Whatever happened, the machine keeps its setting.
        restore_rt_runtime_us(before);
        assert!(replaced, "no new guard:\n{}", log.text());
        let said = said.unwrap_or_else(|| panic!("the guard's death not logged:\n{}", log.text()));
        assert!(
            said.duration_since(killed) < Duration::from_secs(1),
            "logged {:?} after the kill",
            said.duration_since(killed)
        );
        assert!(
            restored,
            "RT throttling not restored after the launcher was killed: {now:?}\n{}",
            log.text()
        );
    } else {
        restore_rt_runtime_us(before);
        panic!(
            "RT throttling was not lifted for the stack:\n{}",
            log.text()
        );
    }
    assert!(
        wait_until(Duration::from_secs(5), || processes_with(&inst).is_empty()),
        "orphans left: {:?}",
        processes_with(&inst)
    );
}
