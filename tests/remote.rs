//! The axis from another host: `serve --gateway` in one network namespace, `stepdrive axis
//! --connect` in another, joined by a veth pair the test makes (nothing leaves the machine).
//! Needs root and iproute2's `ip` (the CI machine has both).

mod common;

use common::*;
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

/// Remote `axis status`, `enable`, `move --wait`, a refused command, command latency and a
/// stream, through the gateway across the veth; then a remote jog whose link is cut: the
/// gateway's lease on the client expires and it quick-stops the axis, which stands still in
/// Quick stop active within the lease plus the deceleration, with no fault.
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
    let nan = remote(&["move", "--to", "nan"]);
    assert_eq!(nan.status.code(), Some(1), "{}", text(&nan));
    assert!(text(&nan).contains("target NaN"), "{}", text(&nan));
    let mv = remote(&MOVE_1_RAD_WAITED);
    assert_reached(&mv);
    let lat = remote(&["latency", "--count", "100"]);
    assert!(lat.status.success(), "{}", text(&lat));
    assert!(text(&lat).contains("round trip"), "{}", text(&lat));
    println!("{}", text(&lat).trim());

    // A 100 Hz stream of 2 s from a file, paced by the status the gateway relays.
    let dir = TempDir::new("remote");
    let theta0 = field(&local_status(), "θ ").expect("θ in the status");
    let rows: String = (0..=200)
        .map(|k| {
            let t = k as f64 * 0.01;
            format!("{t},{}\n", theta0 + 0.5 * (std::f64::consts::TAU * t).sin())
        })
        .collect();
    let csv = dir.path("sine.csv");
    std::fs::write(&csv, rows).expect("write the stream");
    let streamed = remote(&["stream", csv.to_str().expect("UTF-8"), "--priority", "0"]);
    assert!(streamed.status.success(), "{}", text(&streamed));
    assert!(
        text(&streamed).contains("201 points streamed"),
        "{}",
        text(&streamed)
    );
    let st = local_status();
    assert!(st.contains("Operation enabled"), "{st}");

    // A remote jog holds its lease while its command runs; the link cut, the lease expires.
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
    assert!(
        wait_until(Duration::from_secs(10), || field(&local_status(), "ω")
            .is_some_and(|w| (w - 1.0).abs() < 0.05)),
        "the jog did not reach 1 rad/s: {}",
        local_status()
    );
    let cut = Instant::now();
    link.cut();
    let mut stopped = None;
    let bound = Duration::from_secs(3) + Duration::from_secs(2);
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
    // The lease (3 s) plus 1 rad/s at the quick-stop rate, and the status polls' slack.
    assert!(stopped < bound, "standstill {stopped:?} after the cut");
    println!("link cut → standstill in Quick stop active after {stopped:?}");

    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    let err = stderr_of(&mut serve);
    assert_eq!(status.code(), Some(0), "{err}");
    assert!(
        err.contains("went away") && err.contains("quick stop taken"),
        "the gateway did not say why it stopped the axis: {err}"
    );
    assert!(processes_with(&inst).is_empty());
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
