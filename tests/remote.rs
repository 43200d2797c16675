//! The axis from another host: `serve --gateway` in one network namespace, `stepdrive axis
//! --connect` in another, joined by a veth pair the test makes (nothing leaves the machine).
//! Needs root and iproute2's `ip` (the CI machine has both).

use crate::common::*;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Two network namespaces joined by a veth pair, removed when dropped.
struct Link {
    stack: String,
    remote: String,
    remote_end: String,
    /// The stack's address on the link.
    stack_ip: String,
}

fn ip(args: &[&str]) {
    let out = Command::new("ip")
        .args(args)
        .output()
        .expect("iproute2's `ip` (the tests make network namespaces; run them as root)");
    assert!(
        out.status.success(),
        "ip {}: {} (the tests make network namespaces: run them as root)",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

impl Link {
    fn new() -> Self {
        let id = std::process::id();
        let (stack, remote) = (format!("sd{id}s"), format!("sd{id}r"));
        let (stack_end, remote_end) = (format!("sdv{id}s"), format!("sdv{id}r"));
        let net = format!("10.231.{}", id % 250);
        ip(&["netns", "add", &stack]);
        ip(&["netns", "add", &remote]);
        ip(&[
            "link",
            "add",
            &stack_end,
            "type",
            "veth",
            "peer",
            "name",
            &remote_end,
        ]);
        ip(&["link", "set", &stack_end, "netns", &stack]);
        ip(&["link", "set", &remote_end, "netns", &remote]);
        for (ns, end, host) in [(&stack, &stack_end, 1), (&remote, &remote_end, 2)] {
            ip(&[
                "-n",
                ns,
                "addr",
                "add",
                &format!("{net}.{host}/24"),
                "dev",
                end,
            ]);
            ip(&["-n", ns, "link", "set", end, "up"]);
            ip(&["-n", ns, "link", "set", "lo", "up"]);
        }
        Self {
            stack,
            remote,
            remote_end,
            stack_ip: format!("{net}.1"),
        }
    }

    /// `stepdrive ARGS` in namespace `ns`.
    fn command(ns: &str, args: &[&str]) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", ns, &exe()])
            .args(args)
            .env("RUST_LOG", "warn");
        c
    }

    /// The link cut: the remote end down (the stack's end loses its carrier).
    fn cut(&self) {
        ip(&["-n", &self.remote, "link", "set", &self.remote_end, "down"]);
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        // Deleting a namespace deletes the veth end in it, and with it the pair.
        for ns in [&self.stack, &self.remote] {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// The warning bits in `axis status`'s text (`warning 0x30`), 0 if none.
fn warnings(status: &str) -> u32 {
    status
        .split("warning 0x")
        .nth(1)
        .and_then(|w| w.split_whitespace().next())
        .and_then(|w| u32::from_str_radix(w, 16).ok())
        .unwrap_or(0)
}

/// A value after `label` in `axis status`'s text (`ω            -0.4581 rad/s`).
fn field(status: &str, label: &str) -> Option<f64> {
    status
        .lines()
        .find(|l| l.starts_with(label))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// The setpoint's θ_d in `axis status`'s text (`setpoint     θ_d 1.000000 rad, ω_d …`):
/// where a stream's follower starts.
fn setpoint(status: &str) -> Option<f64> {
    status
        .lines()
        .find(|l| l.starts_with("setpoint"))?
        .split_whitespace()
        .nth(2)?
        .parse()
        .ok()
}

/// Remote `axis status`, `enable`, `move --wait`, a refused command, command latency and a
/// stream, through the gateway across the veth; then a remote jog whose link is cut: its
/// client's renewals stop and the axis quick-stops the jog itself (`[axis] jog_timeout_s`,
/// long before the link's lease of 3 s expires), standing still in Quick stop active within
/// the timeout plus the deceleration, with no fault.
#[test]
fn a_client_in_another_network_namespace_commands_the_axis_and_a_cut_link_quick_stops_it() {
    let _turn = one_stack_at_a_time();
    let link = Link::new();
    let inst = instance("remote");
    let endpoint = format!("tcp/{}:7447", link.stack_ip);
    let mut serve_args = vec!["serve", "--instance", &inst, "--gateway", &endpoint];
    serve_args.extend(ORDINARY_STACK);
    let serve = Link::command(&link.stack, &serve_args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn serve");
    let mut serve = Launched::new(serve);
    let remote = |args: &[&str]| {
        let mut all = vec!["axis", "--instance", &inst, "--connect", &endpoint];
        all.extend(args);
        Link::command(&link.remote, &all)
            .output()
            .expect("run stepdrive axis")
    };
    let local_status = || {
        let out = Link::command(&link.stack, &["axis", "--instance", &inst, "status"])
            .output()
            .expect("run stepdrive axis");
        text(&out)
    };

    if !wait_until(Duration::from_secs(30), || {
        remote(&["status"]).status.success()
    }) {
        let last = text(&remote(&["status"]));
        signal(serve.id(), libc::SIGINT);
        let _ = wait_with_timeout(&mut serve, Duration::from_secs(30));
        panic!(
            "no answer through the gateway: {last}\nserve said: {}",
            stderr_of(&mut serve)
        );
    }
    let st = remote(&["status"]);
    assert!(text(&st).contains("Switch on disabled"), "{}", text(&st));
    // The same validation as on the stack's host: refused with the reason.
    let refused = remote(&["move", "--to", "1"]);
    assert_eq!(refused.status.code(), Some(1), "{}", text(&refused));
    assert!(text(&refused).contains("needs Operation enabled"));

    let on = remote(&["enable"]);
    assert!(on.status.success(), "{}", text(&on));
    let far = remote(&["move", "--to", "1e9"]);
    assert_eq!(far.status.code(), Some(1), "{}", text(&far));
    assert!(
        text(&far).contains("outside the soft limits"),
        "{}",
        text(&far)
    );
    let mv = remote(&MOVE_1_RAD_WAITED);
    assert_reached(&mv);
    let lat = remote(&["latency", "--count", "100"]);
    assert!(lat.status.success(), "{}", text(&lat));
    assert!(text(&lat).contains("round trip"), "{}", text(&lat));
    println!("{}", text(&lat).trim());

    // A 100 Hz stream of 2 s from a file, paced by the status the gateway relays: from
    // where the axis's setpoint stands, at rest, and back (one it cannot follow ends
    // non-zero).
    let dir = TempDir::new("remote");
    let before = local_status();
    let theta0 = setpoint(&before).expect("θ_d in the status");
    let rows: String = (0..=200)
        .map(|k| {
            let t = k as f64 * 0.01;
            let s = 0.5 * (1.0 - (std::f64::consts::PI * t).cos());
            format!("{t},{}\n", theta0 + 0.5 * s)
        })
        .collect();
    let csv = dir.path("sine.csv");
    std::fs::write(&csv, rows).expect("write the stream");
    let streamed = remote(&["stream", csv.to_str().expect("UTF-8"), "--priority", "0"]);
    assert!(
        streamed.status.success(),
        "{}\nthe axis before the stream:\n{before}\nand after:\n{}",
        text(&streamed),
        local_status()
    );
    assert!(
        text(&streamed).contains("201 points streamed"),
        "{}",
        text(&streamed)
    );
    let st = local_status();
    assert!(st.contains("Operation enabled"), "{st}");

    // A remote jog lasts while its command runs and renews it; the link cut, the renewals
    // stop and the axis quick-stops the jog itself.
    let mut jog = Link::command(
        &link.remote,
        &[
            "axis",
            "--instance",
            &inst,
            "--connect",
            &endpoint,
            "jog",
            "--velocity",
            "1",
        ],
    )
    .stdout(Stdio::piped())
    .stderr(Stdio::piped())
    .spawn()
    .expect("spawn the jog");
    if !wait_until(Duration::from_secs(10), || {
        field(&local_status(), "ω").is_some_and(|w| (w - 1.0).abs() < 0.05)
    }) {
        let st = local_status();
        signal(serve.id(), libc::SIGINT);
        let _ = wait_with_timeout(&mut serve, Duration::from_secs(30));
        let _ = jog.kill();
        let jogged = jog.wait_with_output().expect("the jog's output");
        panic!(
            "the jog did not reach 1 rad/s: {st}\nthe jog said: {}\nserve said: {}",
            text(&jogged),
            stderr_of(&mut serve)
        );
    }
    let cut = Instant::now();
    link.cut();
    let mut stopped = None;
    let bound = Duration::from_millis(500) + Duration::from_secs(2);
    while cut.elapsed() < bound + Duration::from_secs(5) {
        let st = local_status();
        assert!(!st.contains("state        Fault"), "{st}");
        let still = field(&st, "ω").is_some_and(|w| w.abs() < 1e-3);
        if st.contains("Quick stop active") && still {
            stopped = Some(cut.elapsed());
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    signal(jog.id(), libc::SIGKILL);
    let _ = jog.wait();
    let stopped = stopped.unwrap_or_else(|| panic!("no quick stop: {}", local_status()));
    // The jog timeout (0.5 s) plus 1 rad/s at the quick-stop rate, and the status polls'
    // slack (the lease alone took 3.06-3.76 s).
    assert!(stopped < bound, "standstill {stopped:?} after the cut");
    assert!(
        warnings(&local_status()) & 0x20 != 0,
        "JOG_LOST: {}",
        local_status()
    );
    println!("link cut → standstill in Quick stop active after {stopped:?}");

    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    let err = stderr_of(&mut serve);
    assert_eq!(status.code(), Some(0), "{err}");
    assert!(processes_with(&inst).is_empty());
}

/// A remote client that does only what docs/remote.md requires, written here with Zenoh
/// alone and the request's bytes laid out from the document's table (not with our client
/// library): Zenoh's default client settings, no liveliness token. It cannot leave the motor
/// running: its jog, never renewed, is quick-stopped by the axis; a stream it starts and
/// never sends a point to is quick-stopped a remote lead (which the gateway gives it) and a
/// stream timeout later; a request carrying a local client's id is refused.
#[test]
fn a_client_that_does_the_minimum_cannot_leave_the_motor_running() {
    use zenoh::Wait;
    let _turn = one_stack_at_a_time();
    let inst = instance("minimal");
    let port = free_tcp_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut args = vec!["serve", "--instance", &inst, "--gateway", &endpoint];
    args.extend(ORDINARY_STACK);
    let mut serve = spawn_run(&args);
    let local_status = || text(&stepdrive(&["axis", "--instance", &inst, "status"]));
    assert!(
        wait_until(Duration::from_secs(30), || local_status()
            .contains("Switch on")),
        "the stack did not come up: {}",
        local_status()
    );

    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"client\"").expect("mode");
    config
        .insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]"))
        .expect("endpoint");
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .expect("scouting");
    let session = zenoh::open(config)
        .wait()
        .expect("a session with the gateway");
    let key = format!("stepdrive/{inst}/axis/0/command");
    // An odd id above 2^31, the top of every sequence number (docs/remote.md).
    let id: u32 = 0x8000_0001 | (std::process::id() << 1);
    let mut seq = u64::from(id) << 32;
    // AxisRequest, 80 bytes little-endian: axis u32 @0, kind u32 @4, seq u64 @8,
    // publish_time_ns u64 @16, client u32 @24, flags u32 @28, target_rad f64 @32,
    // velocity_rad_s f64 @40, v/a/j limits f64 @48/@56/@64, lead_s f64 @72.
    let mut ask = |kind: u32, client: u32, velocity: f64| -> (u32, String) {
        seq += 1;
        let mut b = [0u8; 80];
        b[4..8].copy_from_slice(&kind.to_le_bytes());
        b[8..16].copy_from_slice(&seq.to_le_bytes());
        b[24..28].copy_from_slice(&client.to_le_bytes());
        b[40..48].copy_from_slice(&velocity.to_le_bytes());
        let replies = session.get(&key).payload(b.to_vec()).wait().expect("query");
        let reply = replies
            .recv_timeout(Duration::from_secs(5))
            .expect("an answer")
            .expect("an answer in time");
        let sample = reply.into_result().expect("an ack");
        let ack = sample.payload().to_bytes();
        // AxisAck, 240 bytes: the request, refusal u32 @80, …, text_len u32 @112, text @120.
        assert_eq!(ack.len(), 240);
        let refusal = u32::from_le_bytes(ack[80..84].try_into().expect("4 bytes"));
        let len = u32::from_le_bytes(ack[112..116].try_into().expect("4 bytes")) as usize;
        (
            refusal,
            String::from_utf8_lossy(&ack[120..120 + len.min(120)]).into_owned(),
        )
    };
    let (enable, jog, stream_start) = (8, 10, 12);

    // A local client's id (a pid) is refused by the gateway (16: not a remote client's).
    let (refusal, why) = ask(enable, std::process::id(), 0.0);
    assert_eq!(refusal, 16, "{why}");
    assert_eq!(ask(enable, id, 0.0).0, 0);
    assert_eq!(ask(jog, id, 2.0).0, 0);
    // How long after `since` the axis stood in Quick stop active with warning `bit` set.
    let quick_stopped = |since: Instant, bit: u32| {
        while since.elapsed() < Duration::from_secs(8) {
            let st = local_status();
            if st.contains("Quick stop active") && warnings(&st) & bit != 0 {
                return Some(since.elapsed());
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        None
    };
    // Silent from here on, its session open: no token ever said it was there.
    let stopped = quick_stopped(Instant::now(), 0x20)
        .unwrap_or_else(|| panic!("the jog ran on: {}", local_status()));
    assert!(
        stopped < Duration::from_secs(3),
        "stopped {stopped:?} after the jog"
    );
    println!("a silent remote client's jog stopped after {stopped:?}");

    // A stream started and never fed: stopped after the remote lead (0.5 s) and the stream
    // timeout, not the local lead (0.05 s) the client's default would have given it.
    assert_eq!(ask(enable, id, 0.0).0, 0);
    assert_eq!(ask(stream_start, id, 0.0).0, 0);
    let lost = quick_stopped(Instant::now(), 0x10)
        .unwrap_or_else(|| panic!("the stream was never stopped: {}", local_status()));
    assert!(
        lost > Duration::from_millis(450) && lost < Duration::from_secs(3),
        "the pointless stream stopped after {lost:?}"
    );
    println!("a stream with no point stopped after {lost:?}");
    drop(session);

    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    assert!(status.success(), "{}", stderr_of(&mut serve));
}

/// A multi-axis stack is served whole by its gateway (on loopback here): a remote client
/// commands each axis by its index, each axis's status comes on its own key, and an index
/// the stack lacks is refused by the gateway, naming the axis count.
#[test]
fn a_gateway_serves_every_axis_of_a_multi_axis_stack() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("remote-axes");
    let inst = instance("remote-axes");
    let scenario = dir.file(
        "three.toml",
        "name = \"three\"\n[[axis]]\nname = \"x\"\n[[axis]]\nname = \"y\"\n[[axis]]\nname = \"z\"\n",
    );
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let mut args = vec![
        "serve",
        "--instance",
        &inst,
        "--scenario",
        scenario.to_str().unwrap(),
        "--gateway",
        &endpoint,
    ];
    args.extend(ORDINARY_STACK);
    let mut serve = spawn_run(&args);
    let remote = |axis: &str, verb: &[&str]| {
        let mut all = vec![
            "axis",
            "--instance",
            &inst,
            "--connect",
            &endpoint,
            "--axis",
            axis,
        ];
        all.extend(verb);
        stepdrive(&all)
    };
    if !wait_until(Duration::from_secs(30), || {
        remote("2", &["status"]).status.success()
    }) {
        let last = text(&remote("2", &["status"]));
        signal(serve.id(), libc::SIGINT);
        let _ = wait_with_timeout(&mut serve, Duration::from_secs(30));
        panic!(
            "axis 2 did not answer through the gateway: {last}\nserve: {}",
            stderr_of(&mut serve)
        );
    }
    let unknown = axis_2_alone_and_no_axis_3(remote);
    assert!(text(&unknown).contains("no axis 3"), "{}", text(&unknown));

    // A coordinated move through the gateway: its parts are forwarded without waiting for
    // each other's answers, and leave on one tick.
    for axis in ["0", "1"] {
        assert!(remote(axis, &["enable"]).status.success());
    }
    let together = remote(
        "0",
        &[
            "move-together",
            "--to",
            "0.5,-0.5,0",
            "--wait",
            "--timeout",
            "10",
        ],
    );
    assert_moved_together(&together, 3);

    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    assert!(status.success(), "{}", stderr_of(&mut serve));
}

/// The CPUs every thread of process `pid` may run on (`Cpus_allowed_list`), one string per
/// thread, or none once it is gone.
fn threads_cpus(pid: u32) -> Vec<String> {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return Vec::new();
    };
    tasks
        .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("status")).ok())
        .filter_map(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
                .map(|v| v.trim().to_string())
        })
        .collect()
}

/// The stack's helpers keep off the current loop's CPU (docs/design.md's deployment): with
/// the loops pinned as by default (plant 0, current loop 1), every thread of `serve` (its
/// monitor and the live view's) and of the gateway it starts (Zenoh's too) runs on the CPUs
/// the loops leave, on two cores CPU 0 alone. Loops at ordinary priority: tests share the
/// machine.
#[test]
fn the_gateway_and_the_live_view_keep_off_the_current_loops_cpu() {
    // SAFETY: sysconf only reads a system constant.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) }.max(1) as usize;
    if n < 2 {
        eprintln!("one CPU: nothing to keep off");
        return;
    }
    let expected = match n {
        2 => "0".to_string(),
        3 => "2".to_string(),
        _ => format!("2-{}", n - 1),
    };
    let _turn = one_stack_at_a_time();
    let inst = instance("helpers");
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let mut serve = spawn_run(&[
        "serve",
        "--instance",
        &inst,
        "--gateway",
        &endpoint,
        "--foxglove",
        "127.0.0.1:0",
        "--priority",
        "0",
        "--cpus",
        "0,1",
    ]);
    let answered = wait_until(Duration::from_secs(30), || {
        stepdrive(&[
            "axis",
            "--instance",
            &inst,
            "--connect",
            &endpoint,
            "status",
        ])
        .status
        .success()
    });
    let gateway = std::fs::read_dir("/proc")
        .expect("/proc")
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .find(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline")).is_ok_and(|c| {
                let c = String::from_utf8_lossy(&c).replace('\0', " ");
                c.contains(" gateway ") && c.contains(&format!("--instance {inst} "))
            })
        });
    let serve_threads = threads_cpus(serve.id());
    let gateway_threads = gateway.map(threads_cpus).unwrap_or_default();
    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    let err = stderr_of(&mut serve);
    assert!(answered, "no answer through the gateway\nserve: {err}");
    assert!(status.success(), "{err}");
    // The monitor's thread and the live view's at least; Zenoh's several.
    assert!(
        serve_threads.len() >= 2,
        "serve's threads: {serve_threads:?}"
    );
    assert!(gateway_threads.len() >= 3, "gateway: {gateway_threads:?}");
    for (who, cpus) in [("serve", &serve_threads), ("the gateway", &gateway_threads)] {
        assert!(
            cpus.iter().all(|c| *c == expected),
            "{who}'s threads may run on {cpus:?}, expected {expected} on {n} CPUs"
        );
    }
}
