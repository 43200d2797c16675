//! What the end-to-end tests share: running the real `stepdrive` binary, temporary files,
//! instance names, finding processes, reading results. Each test uses its own instance name,
//! so tests running in parallel never see each other's services.
#![allow(dead_code)]

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

/// The binary under test: this build's, or the one `STEPDRIVE_EXE` names (the same tests
/// against another build, e.g. one from before a fix).
pub fn exe() -> String {
    std::env::var("STEPDRIVE_EXE").unwrap_or_else(|_| env!("CARGO_BIN_EXE_stepdrive").into())
}

/// Tests that start a whole stack take turns: several stacks at once on two cores turn
/// scheduling noise into watchdog trips and lost samples, which is not what they test.
pub static STACK: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub fn one_stack_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    STACK
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A short version of the paper's scenario: 0.7 s, cruise window after the transients.
pub const SHORT: &str = r#"
name = "short"
[trajectory]
accel_s = 0.1
cruise_s = 0.35
decel_s = 0.1
hold_s = 0.15
[metrics]
cruise_start_s = 0.3
cruise_end_s = 0.45
final_window_s = 0.05
"#;

pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(test: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("stepdrive-e2e-{}-{test}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("create temp dir");
        Self(dir)
    }
    pub fn file(&self, name: &str, text: &str) -> PathBuf {
        let p = self.0.join(name);
        std::fs::write(&p, text).expect("write temp file");
        p
    }
    pub fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub fn instance(test: &str) -> String {
    format!("e2e-{}-{test}", std::process::id())
}

pub fn stepdrive(args: &[&str]) -> Output {
    Command::new(exe())
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("run stepdrive")
}

pub fn read_json(path: &Path) -> Value {
    let text = std::fs::read_to_string(path).expect("read JSON output");
    serde_json::from_str(&text).expect("valid JSON")
}

pub fn run_of<'a>(doc: &'a Value, method: &str) -> &'a Value {
    doc["runs"]
        .as_array()
        .expect("runs array")
        .iter()
        .find(|r| r["method"] == method)
        .unwrap_or_else(|| panic!("no {method} run in {doc}"))
}

pub fn num(run: &Value, key: &str) -> f64 {
    run[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} missing in {run}"))
}

/// PIDs of live processes whose command line contains `needle`.
pub fn processes_with(needle: &str) -> Vec<u32> {
    let mut found = Vec::new();
    let me = std::process::id();
    for entry in std::fs::read_dir("/proc").expect("read /proc").flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        if pid == me {
            continue;
        }
        let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) else {
            continue;
        };
        let cmdline = String::from_utf8_lossy(&cmdline).replace('\0', " ");
        // Zombies have an empty cmdline; only live processes count.
        if cmdline.contains(needle) {
            found.push(pid);
        }
    }
    found
}

pub fn wait_with_timeout(child: &mut Child, timeout: Duration) -> std::process::ExitStatus {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("process did not exit within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// [`wait_with_timeout`] for a stack's launcher: if it does not exit in time, the panic
/// says what was still running (each process of `inst`, its state and where it waits) and
/// what the launcher had written, so that a hang is diagnosable from a CI log.
pub fn wait_or_explain(
    child: &mut Child,
    timeout: Duration,
    inst: &str,
) -> std::process::ExitStatus {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            return status;
        }
        if Instant::now() > deadline {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut left = String::new();
    for pid in processes_with(inst) {
        let read =
            |f: &str| std::fs::read_to_string(format!("/proc/{pid}/{f}")).unwrap_or_default();
        let cmdline = read("cmdline").replace('\0', " ");
        let state = read("stat")
            .split(") ")
            .nth(1)
            .unwrap_or("")
            .chars()
            .next()
            .unwrap_or('?');
        left.push_str(&format!(
            "  pid {pid} [{state}] waits in {:?}: {cmdline}\n",
            read("wchan")
        ));
    }
    let _ = child.kill();
    let _ = child.wait();
    panic!(
        "the launcher did not exit within {timeout:?}; still running:\n{left}its stderr:\n{}",
        stderr_of(child)
    );
}

/// A launcher a failing test does not leave behind: dropped while still running (a test
/// that panicked before it waited), it is interrupted like Ctrl-C, which stops its loops,
/// and killed if it has not ended 20 s later. A stack left running holds its CPUs and its
/// instance, and every later test that starts a realtime stack would fail on it.
pub struct Launched(Child);

impl Launched {
    /// A launcher started some other way (e.g. in a network namespace).
    pub fn new(child: Child) -> Self {
        Self(child)
    }
}

impl std::ops::Deref for Launched {
    type Target = Child;
    fn deref(&self) -> &Child {
        &self.0
    }
}

impl std::ops::DerefMut for Launched {
    fn deref_mut(&mut self) -> &mut Child {
        &mut self.0
    }
}

impl Drop for Launched {
    fn drop(&mut self) {
        if !matches!(self.0.try_wait(), Ok(None)) {
            return;
        }
        signal(self.0.id(), libc::SIGINT);
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if !matches!(self.0.try_wait(), Ok(None)) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub fn wait_until(timeout: Duration, mut cond: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if cond() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    cond()
}

/// A long run the supervision tests can interrupt.
pub const LONG: &str = "[trajectory]\nhold_s = 300.0\n";

pub fn start_long_run(dir: &TempDir, inst: &str) -> Launched {
    let scenario = dir.file("long.toml", LONG);
    let child = spawn_logged(&[
        "run",
        "--method",
        "proposed",
        "--instance",
        inst,
        "--scenario",
        scenario.to_str().expect("a UTF-8 path"),
    ]);
    // Wait until all three stack processes are up.
    assert!(
        wait_until(Duration::from_secs(30), || {
            ["plant", "current-loop", "position-loop"]
                .iter()
                .all(|role| pid_of_role(inst, role).is_some())
        }),
        "stack did not come up"
    );
    std::thread::sleep(Duration::from_millis(500));
    child
}

pub fn stderr_of(child: &mut Child) -> String {
    let mut s = String::new();
    use std::io::Read;
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_string(&mut s);
    }
    s
}

pub fn stdout_of(child: &mut Child) -> String {
    let mut s = String::new();
    use std::io::Read;
    if let Some(mut o) = child.stdout.take() {
        let _ = o.read_to_string(&mut s);
    }
    s
}

/// `stepdrive ARGS` started in the background, its output piped.
pub fn spawn_run(args: &[&str]) -> Launched {
    spawn_with(args, Stdio::piped())
}

/// `stepdrive ARGS` in the background, its stderr piped, its stdout to `stdout`.
fn spawn_with(args: &[&str], stdout: Stdio) -> Launched {
    Launched(
        Command::new(exe())
            .args(args)
            .env("RUST_LOG", "warn")
            .stdout(stdout)
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn stepdrive"),
    )
}

/// The process of `role` (plant, current-loop, ...) in the stack on `inst`.
pub fn pid_of_role(inst: &str, role: &str) -> Option<u32> {
    let needle = format!("\0{role}\0");
    processes_with(inst).into_iter().find(|pid| {
        std::fs::read(format!("/proc/{pid}/cmdline"))
            .map(|c| String::from_utf8_lossy(&c).contains(&needle))
            .unwrap_or(false)
    })
}

pub fn signal(pid: u32, sig: libc::c_int) {
    // SAFETY: plain kill(2) on a process this test started.
    unsafe { libc::kill(pid as libc::pid_t, sig) };
}

/// RT throttling's budget (`/proc/sys/kernel/sched_rt_runtime_us`; −1: lifted).
pub fn rt_runtime_us() -> Option<i64> {
    std::fs::read_to_string("/proc/sys/kernel/sched_rt_runtime_us")
        .ok()
        .and_then(|s| s.trim().parse::<i64>().ok())
}

/// RT throttling's budget as it is, if a test of lifting and restoring it can run here:
/// throttling on, and this process root (probed by writing the same value back).
pub fn rt_throttling_to_check() -> Option<i64> {
    let Some(before) = rt_runtime_us().filter(|&v| v != -1) else {
        eprintln!("RT throttling already off or unreadable here: nothing to check");
        return None;
    };
    if std::fs::write("/proc/sys/kernel/sched_rt_runtime_us", before.to_string()).is_err() {
        eprintln!("not root: nothing to check");
        return None;
    }
    Some(before)
}

/// Puts RT throttling's budget back (a test that found the stack had not).
pub fn restore_rt_runtime_us(value: i64) {
    let _ = std::fs::write("/proc/sys/kernel/sched_rt_runtime_us", value.to_string());
}

/// A process started by hand without real-time settings: the deployment's defaults
/// (SCHED_FIFO, pinned) are for a machine the run has to itself, not for tests that share
/// the CI machine's two cores.
pub const ORDINARY_SCHEDULING: [&str; 4] = ["--priority", "0", "--cpu", "none"];

/// The same for a launcher of a whole stack (`run`, `serve`): its loops' options.
pub const ORDINARY_STACK: [&str; 4] = ["--priority", "0", "--cpus", "none"];

/// A realtime stack of `duration` seconds on the short scenario, with ordinary scheduling
/// and no pinning: tests run in parallel on two cores.
pub fn realtime_test_args<'a>(
    scenario: &'a Path,
    inst: &'a str,
    duration: &'a str,
) -> Vec<&'a str> {
    let mut args = vec![
        "--scenario",
        scenario.to_str().unwrap(),
        "--duration",
        duration,
        "--instance",
        inst,
    ];
    args.extend(ORDINARY_STACK);
    args
}

/// The stack time of `inst`'s axis 0 as its status reports it (what `stepdrive axis
/// status` prints on its `time` line), if the stack is up and publishing.
pub fn stack_time(inst: &str) -> Option<f64> {
    let out = stepdrive(&["axis", "status", "--instance", inst]);
    if !out.status.success() {
        return None;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().find(|l| l.starts_with("time"))?;
    let t = line.split("t = ").nth(1)?.split_whitespace().next()?;
    t.parse().ok()
}

/// Waits until the stack on `inst` (started as `child`) has run `t_s` seconds of its own
/// time. A fixed delay after the processes appear is not enough on a loaded machine: their
/// start (a drive's handshake and alignment included) has been seen to outlast 1.2 s. One
/// client, connected once, reads the status: a new `stepdrive axis status` each time costs
/// a connection (a request the position loop answers) that a loaded host makes slow.
pub fn wait_for_stack_time(inst: &str, child: &mut Child, t_s: f64) {
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut axis = None;
    loop {
        if axis.is_none() {
            axis = stepdrive_client::Axis::connect(inst, 0).ok();
        }
        if let Some(a) = axis.as_mut() {
            if a.status().is_ok_and(|s| s.t_s >= t_s) {
                return;
            }
        }
        if let Ok(Some(status)) = child.try_wait() {
            panic!(
                "the stack ended ({status}) before t = {t_s} s: {}",
                stderr_of(child)
            );
        }
        assert!(
            Instant::now() < deadline,
            "the stack on {inst} did not reach t = {t_s} s in 60 s"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Runs `stepdrive` with `args` (a run with `--json`), freezes its current-loop process
/// with SIGSTOP for `freeze` once the stack's own time has reached `at_s`, and returns the
/// run's JSON document.
pub fn run_with_frozen_current_loop(
    args: &[&str],
    inst: &str,
    json: &Path,
    at_s: f64,
    freeze: Duration,
) -> Value {
    let mut child = spawn_logged(args);
    wait_for_stack_time(inst, &mut child, at_s);
    let pid = pid_of_role(inst, "current-loop").expect("current loop");
    signal(pid, libc::SIGSTOP);
    std::thread::sleep(freeze);
    signal(pid, libc::SIGCONT);
    let status = wait_with_timeout(&mut child, Duration::from_secs(60));
    assert!(status.success(), "run failed: {}", stderr_of(&mut child));
    assert!(processes_with(inst).is_empty());
    read_json(json)
}

/// Hardware-mode tests run the short scenario at 2 kHz / 200 Hz: they run without
/// real-time priorities (tests share the CI machine's two cores), and there five processes
/// plus loopback UDP at 20 kHz would measure the machine's scheduler, not the stack.
pub fn slow_scenario() -> String {
    format!("{SHORT}\n{SLOW_RATES}")
}

/// The rates of [`slow_scenario`], for a scenario with another trajectory.
pub const SLOW_RATES: &str = "[rates]\ncurrent_loop_hz = 2000.0\nposition_loop_hz = 200.0\n";

pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("free port")
        .port()
}

/// A TCP port free on 127.0.0.1 at the time of asking.
pub fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port")
        .port()
}

/// `stepdrive serve` on `inst` in the background, ordinary scheduling and no pinning (tests
/// share two cores), with `extra` options.
pub fn spawn_serve(inst: &str, extra: &[&str]) -> Launched {
    let mut args = vec!["serve", "--instance", inst];
    args.extend(ORDINARY_STACK);
    args.extend_from_slice(extra);
    spawn_run(&args)
}

/// `stepdrive run` of the proposed method alone on `inst`, lockstep, with `scenario` and
/// `extra` options.
pub fn run_proposed(inst: &str, scenario: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "run",
        "--instance",
        inst,
        "--method",
        "proposed",
        "--scenario",
        scenario.to_str().expect("a UTF-8 path"),
    ];
    args.extend_from_slice(extra);
    stepdrive(&args)
}

/// `stepdrive ARGS` in the background, its stdout dropped and its stderr (the log) piped.
pub fn spawn_logged(args: &[&str]) -> Launched {
    spawn_with(args, Stdio::null())
}

/// A hardware-mode run of the proposed method, without real-time settings.
pub fn hardware_args<'a>(scenario: &'a Path, inst: &'a str, json: &'a Path) -> Vec<&'a str> {
    hardware_args_with(scenario, inst, json, "proposed")
}

/// A hardware-mode run of `methods` (e.g. "proposed,lyapunov"), without real-time settings.
pub fn hardware_args_with<'a>(
    scenario: &'a Path,
    inst: &'a str,
    json: &'a Path,
    methods: &'a str,
) -> Vec<&'a str> {
    let mut args = vec![
        "run",
        "--mode",
        "hardware",
        "--method",
        methods,
        "--scenario",
        scenario.to_str().unwrap(),
        "--instance",
        inst,
        "--json",
        json.to_str().unwrap(),
    ];
    args.extend(ORDINARY_STACK);
    args
}

pub fn hardware_run(scenario: &Path, inst: &str, json: &Path, extra: &[&str]) -> Output {
    let mut args = hardware_args(scenario, inst, json);
    args.extend(extra);
    stepdrive(&args)
}

/// A hardware run against an emulated drive started with `injection` (fault-injection
/// options) on a free loopback port; returns the run's output and the drive's log. Fails
/// the test if the run failed.
pub fn hardware_run_against(
    scenario: &Path,
    inst: &str,
    json: &Path,
    injection: &[&str],
) -> (Output, String) {
    let listen = format!("127.0.0.1:{}", free_udp_port());
    let mut args = vec!["emulate-drive", "--listen", &listen];
    args.extend(ORDINARY_SCHEDULING);
    args.push("--scenario");
    args.push(scenario.to_str().unwrap());
    args.extend(injection);
    let mut drive = spawn_logged(&args);
    let out = hardware_run(scenario, inst, json, &["--drive", &listen]);
    signal(drive.id(), libc::SIGTERM);
    let _ = wait_with_timeout(&mut drive, Duration::from_secs(10));
    let drive_log = stderr_of(&mut drive);
    assert!(
        out.status.success(),
        "{}\ndrive: {drive_log}",
        String::from_utf8_lossy(&out.stderr)
    );
    (out, drive_log)
}

/// Runs `simulate` on `scenario` for `methods` and asserts that a multi-process run's JSON
/// document `ipc` equals it bit for bit, all figures but wall time.
pub fn assert_reproduces_the_simulation(
    ipc: &serde_json::Value,
    scenario: &str,
    methods: &str,
    sim_json: &Path,
) {
    let out = stepdrive(&[
        "simulate",
        "--scenario",
        scenario,
        "--method",
        methods,
        "--json",
        sim_json.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut sim = read_json(sim_json);
    let mut ipc = ipc.clone();
    for d in [&mut sim, &mut ipc] {
        for r in d["runs"].as_array_mut().unwrap() {
            r["wall_time_s"] = serde_json::Value::Null;
        }
    }
    assert_eq!(
        ipc, sim,
        "multi-process run differs from the in-process reference"
    );
}

/// A command's stdout and stderr, for assertions and their messages.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// `axis move` by 1 rad from where the rotor stands, waited for (10 s at most).
pub const MOVE_1_RAD_WAITED: [&str; 7] = [
    "move",
    "--to",
    "1",
    "--relative",
    "--wait",
    "--timeout",
    "10",
];

/// A waited `axis move` that exited 0 saying its target was reached.
pub fn assert_reached(mv: &Output) {
    assert!(mv.status.success(), "{}", text(mv));
    assert!(text(mv).contains("reached"), "{}", text(mv));
}

/// `stepdrive export --csv DIR RECORDING`: every topic of `recording` as CSV files in `dir`.
/// Fails the test if the export fails.
pub fn export_csv(recording: &Path, dir: &Path) {
    let out = stepdrive(&[
        "export",
        "--csv",
        dir.to_str().expect("a UTF-8 path"),
        recording.to_str().expect("a UTF-8 path"),
    ]);
    assert!(out.status.success(), "{}", text(&out));
}

/// An exported CSV file (`stepdrive export --csv`): its header and its rows' fields.
pub struct Csv {
    header: Vec<String>,
    text: String,
}

impl Csv {
    pub fn read(path: &Path) -> Self {
        let text =
            std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let header = text
            .lines()
            .next()
            .unwrap_or_else(|| panic!("{}: no header", path.display()))
            .split(',')
            .map(str::to_string)
            .collect();
        Self { header, text }
    }

    /// The column whose header starts with `name` (`"t ["` for `t [s]`).
    pub fn col(&self, name: &str) -> usize {
        self.header
            .iter()
            .position(|h| h.starts_with(name))
            .unwrap_or_else(|| panic!("no column {name} in {:?}", self.header))
    }

    /// Each row after the header, split into its fields.
    pub fn rows(&self) -> impl Iterator<Item = Vec<&str>> {
        self.text.lines().skip(1).map(|l| l.split(',').collect())
    }
}

/// What follows `marker` on each line of `out` that holds it.
pub fn after<'a>(out: &'a str, marker: &str) -> Vec<&'a str> {
    out.lines().filter_map(|l| l.split(marker).nth(1)).collect()
}

/// Asserts that `out` has `count` lines holding `marker` and that what follows the marker
/// is the same on each (`what`: the property that says, for the message).
pub fn assert_same_after(out: &str, marker: &str, count: usize, what: &str) {
    let after = after(out, marker);
    assert_eq!(after.len(), count, "{out}");
    assert!(after.iter().all(|a| *a == after[0]), "{what}: {out}");
}

/// Axis 2 of a served three-axis stack enabled and moved by 1 rad through `axis` (a verb
/// runner for axis n, on this host or through a gateway), axes 0 and 1 left disabled; the
/// status of axis 3, which the stack lacks, refused (its output returned).
pub fn axis_2_alone_and_no_axis_3(axis: impl Fn(&str, &[&str]) -> Output) -> Output {
    let enabled = axis("2", &["enable"]);
    assert!(enabled.status.success(), "{}", text(&enabled));
    assert_reached(&axis("2", &MOVE_1_RAD_WAITED));
    for (n, state) in [
        ("2", "Operation enabled"),
        ("0", "Switch on disabled"),
        ("1", "Switch on disabled"),
    ] {
        let st = axis(n, &["status"]);
        assert!(text(&st).contains(state), "axis {n}: {}", text(&st));
    }
    let unknown = axis("3", &["status"]);
    assert!(!unknown.status.success(), "{}", text(&unknown));
    unknown
}

/// `axis move-together --wait` of `axes` axes: every part taken with one sequence number
/// at one time, and every axis at its target.
pub fn assert_moved_together(moved: &Output, axes: usize) {
    let out = text(moved);
    assert!(moved.status.success(), "{out}");
    assert_same_after(
        &out,
        "taken (seq",
        axes,
        "the parts left on different ticks",
    );
    assert!(
        out.contains(&format!("all {axes} axes reached their targets")),
        "{out}"
    );
}
