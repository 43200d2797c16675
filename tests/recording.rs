//! Recording, plotting and exporting a run: the MCAP file read back with the `mcap` reader,
//! against the run's own JSON figures; a recording cut short by Ctrl-C or a dead child is
//! still a finished file; the plots and CSVs hold what the recording holds.

use crate::common::*;
use std::process::{Command, Stdio};
use std::time::Duration;
use stepdrive_monitor::record::recording::Recorded;

/// Every channel of the file has a schema, and the file has its summary (what a reader
/// such as PlotJuggler needs).
fn assert_finished(path: &std::path::Path) -> Vec<String> {
    let bytes = std::fs::read(path).expect("the recording exists");
    let summary = mcap::Summary::read(&bytes)
        .expect("a readable file")
        .expect("a summary section: the file was finished");
    let mut topics: Vec<String> = summary
        .channels
        .values()
        .map(|c| {
            let schema = c.schema.as_ref().expect("every channel has a schema");
            assert_eq!(schema.encoding, "jsonschema", "{}", c.topic);
            assert_eq!(c.message_encoding, "json", "{}", c.topic);
            c.topic.clone()
        })
        .collect();
    topics.sort();
    topics
}

#[test]
fn a_recorded_run_reads_back_with_every_sample_and_draws_and_exports() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("record");
    let scenario = dir.file("short.toml", SHORT);
    let json = dir.path("run.json");
    let mcap = dir.path("run.mcap");
    let figs = dir.path("figs");
    let inst = instance("record");
    let out = stepdrive(&[
        "run",
        "--instance",
        &inst,
        "--scenario",
        scenario.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
        "--record",
        mcap.to_str().unwrap(),
        "--plots",
        figs.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let topics = assert_finished(&mcap);
    let expected: Vec<String> = ["lyapunov", "proposed"]
        .iter()
        .flat_map(|m| {
            // The plan channel stays empty in lockstep; the axis's acknowledgements and
            // status are recorded beside the loops' topics.
            [
                "axis/ack",
                "axis/status",
                "command",
                "fault",
                "plan",
                "setpoint",
                "state",
                "stats",
            ]
            .map(|k| format!("/{m}/{k}"))
        })
        .collect();
    assert_eq!(topics, expected);
    let doc = read_json(&json);
    let rec = Recorded::read(&mcap).expect("read back");
    assert_eq!(
        rec.scenario().expect("the scenario is in the file").name,
        "short"
    );
    for (method, states) in &rec.runs {
        let run = run_of(&doc, method);
        assert_eq!(states.len() as f64, num(run, "samples"), "{method}");
        assert!(
            states.windows(2).all(|w| w[1].seq == w[0].seq + 1),
            "{method}"
        );
        // The figures the monitor computed, from the very samples in the file.
        let max = states.iter().map(|s| s.error.abs()).fold(0.0, f64::max);
        assert_eq!(max, num(run, "max_abs_error_rad"), "{method}");
        let last = states.last().expect("samples");
        assert!((last.theta_d - last.theta - last.error).abs() < 1e-15);
        let meta = &rec.metadata["recording"];
        assert_eq!(
            meta[&format!("{method}.samples_recorded")],
            states.len().to_string()
        );
        assert_eq!(meta[&format!("{method}.samples_lost")], "0");
        // Every position-loop tick's setpoint, with the load (12) used: the known 0.01 N·m.
        let (_, setpoints) = rec
            .setpoints
            .iter()
            .find(|(m, _)| m == method)
            .expect("setpoints");
        assert_eq!(setpoints.len(), (states.len() - 1) / 10 + 1, "{method}");
        assert!(setpoints.windows(2).all(|w| w[1].seq == w[0].seq + 1));
        assert!(setpoints.iter().all(|s| s.load_estimate == 0.01));
        // A command answering every sample (the last too), with its voltage the one the plant
        // reports applied over (t_{k+1}, t_{k+2}] (one period of compute delay).
        let (_, commands) = rec
            .commands
            .iter()
            .find(|(m, _)| m == method)
            .expect("commands");
        assert_eq!(commands.len(), states.len(), "{method}");
        for c in commands
            .iter()
            .step_by(97)
            .filter(|c| c.answers_seq + 2 < states.len() as u64)
        {
            let applied = &states[c.answers_seq as usize + 2];
            assert_eq!(
                (applied.v_a, applied.v_b),
                (c.v_a, c.v_b),
                "{method} {}",
                c.seq
            );
        }
    }
    // The plots: every figure as SVG and PNG, both methods named in the legend.
    for name in [
        "position",
        "error",
        "error_log",
        "currents",
        "currents_cruise",
        "dq_currents",
        "voltages",
        "torque",
    ] {
        let svg = std::fs::read_to_string(figs.join(format!("{name}.svg"))).expect(name);
        if name == "currents_cruise" {
            assert!(svg.contains("i_a reference"), "the references are drawn");
        }
        assert!(
            svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"),
            "{name}"
        );
        assert!(
            svg.contains("proposed") && svg.contains("lyapunov"),
            "{name}"
        );
        let png = std::fs::File::open(figs.join(format!("{name}.png"))).expect(name);
        let info = png::Decoder::new(png)
            .read_info()
            .expect("a PNG that decodes");
        let (w, h) = stepdrive_monitor::record::plot::PNG_SIZE;
        assert_eq!((info.info().width, info.info().height), (w, h), "{name}");
    }
    assert!(std::fs::read_to_string(figs.join("error.svg"))
        .expect("error.svg")
        .contains("eq. (7) bound"));
    // CSV: a header and one row per recorded sample.
    let csv = dir.path("csv");
    export_csv(&mcap, &csv);
    for (method, states) in &rec.runs {
        let text = std::fs::read_to_string(csv.join(format!("{method}_state.csv"))).expect("csv");
        let mut lines = text.lines();
        let header = lines.next().expect("header");
        assert!(header.starts_with("t [s],seq,theta [rad],theta_d [rad],error [rad]"));
        assert_eq!(header.split(',').count(), 17);
        assert_eq!(lines.count(), states.len(), "{method}");
    }
}

/// Starts a long lockstep run with a recording; returns it once samples are flowing.
fn start_recorded_run(dir: &TempDir, inst: &str, mcap: &std::path::Path) -> Launched {
    // 2 kHz with a 300 s hold: it runs for many seconds, and its file grows slowly.
    let long = slow_scenario().replace("hold_s = 0.15", "hold_s = 300.0");
    let scenario = dir.file("long.toml", &long);
    let child = spawn_run(&[
        "run",
        "--method",
        "proposed",
        "--instance",
        inst,
        "--scenario",
        scenario.to_str().unwrap(),
        "--record",
        mcap.to_str().unwrap(),
    ]);
    assert!(
        wait_until(Duration::from_secs(30), || {
            std::fs::metadata(mcap).is_ok_and(|m| m.len() > 1_000_000)
        }),
        "no samples recorded"
    );
    child
}

#[test]
fn a_recording_cut_short_by_ctrl_c_or_a_dead_child_is_finished() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("recordcut");
    for (case, victim) in [("ctrl-c", None), ("dead child", Some("current-loop"))] {
        let inst = instance(&format!("recordcut{}", victim.is_some()));
        let mcap = dir.path(&format!("{}.mcap", victim.is_some()));
        let mut run = start_recorded_run(&dir, &inst, &mcap);
        let target = match victim {
            None => run.id(),
            Some(role) => pid_of_role(&inst, role).expect("the current loop"),
        };
        signal(
            target,
            if victim.is_some() {
                libc::SIGKILL
            } else {
                libc::SIGINT
            },
        );
        let status = wait_with_timeout(&mut run, Duration::from_secs(30));
        assert_eq!(
            status.code(),
            Some(if victim.is_some() { 5 } else { 130 }),
            "{case}"
        );
        assert_finished(&mcap);
        let rec = Recorded::read(&mcap).expect(case);
        let states = &rec.runs[0].1;
        assert!(states.len() > 1000, "{case}: {} samples", states.len());
        assert_eq!(
            rec.metadata["recording"]["proposed.samples_recorded"],
            states.len().to_string(),
            "{case}"
        );
    }
}

/// The figures of a JSON document without what depends on the wall clock.
fn figures(doc: &serde_json::Value) -> serde_json::Value {
    let mut doc = doc.clone();
    for run in doc["runs"].as_array_mut().expect("runs") {
        let run = run.as_object_mut().expect("a run");
        run.remove("wall_time_s");
        run.remove("timing");
    }
    doc
}

/// The scope only reads: a lockstep run with a scope attached (in a pseudo-terminal, as a
/// user's) gives bit-identical results to one without, and the scope leaves when told.
#[test]
fn a_scope_attached_to_a_lockstep_run_changes_nothing() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("scope");
    // 2 kHz and a few seconds of hold: long enough to attach to, quick in lockstep.
    let long = slow_scenario().replace("hold_s = 0.15", "hold_s = 20.0");
    let scenario = dir.file("long.toml", &long);
    let sc = scenario.to_str().unwrap();
    let run = |inst: &str, json: &std::path::Path| {
        stepdrive(&[
            "run",
            "--method",
            "proposed",
            "--instance",
            inst,
            "--scenario",
            sc,
            "--json",
            json.to_str().unwrap(),
        ])
    };
    let plain = dir.path("plain.json");
    let out = run(&instance("scope-plain"), &plain);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The scope waits for the stack's services to appear, so it starts first.
    let inst = instance("scope");
    // A pseudo-terminal without a size has no cells to draw: give it one.
    let cmd = format!(
        "stty cols 120 rows 40; exec {} scope --instance {inst} --scenario {sc}",
        exe()
    );
    let mut scope = Command::new("script")
        .args(["-qfec", &cmd, "/dev/null"])
        .env("TERM", "xterm")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("script(1) runs the scope in a pseudo-terminal");
    std::thread::sleep(Duration::from_millis(300));
    let watched = dir.path("watched.json");
    let out = run(&inst, &watched);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        scope.try_wait().expect("wait").is_none(),
        "the scope is still up"
    );
    // Its screen shows the stack it watched.
    let pid = processes_with(&format!("scope --instance {inst}"))
        .into_iter()
        .find(|&p| {
            std::fs::read(format!("/proc/{p}/cmdline"))
                .is_ok_and(|c| c.starts_with(exe().as_bytes()))
        })
        .expect("the scope process");
    signal(pid, libc::SIGTERM);
    let status = wait_with_timeout(&mut scope, Duration::from_secs(10));
    let mut screen = String::new();
    use std::io::Read;
    if let Some(mut o) = scope.stdout.take() {
        let _ = o.read_to_string(&mut screen);
    }
    assert!(status.success(), "the scope left cleanly: {status:?}");
    assert!(screen.contains("stepdrive scope"), "{screen}");
    assert_eq!(figures(&read_json(&watched)), figures(&read_json(&plain)));
}

/// Realtime recordings have the voltage plans too (a lockstep plant never needs one):
/// their first entries, one plan every 10th command at least.
#[test]
fn a_realtime_recording_has_the_commands_and_the_plans() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("recordrt");
    let scenario = dir.file("short.toml", SHORT);
    let mcap = dir.path("rt.mcap");
    let inst = instance("recordrt");
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "0.5"));
    args.extend(["--record", mcap.to_str().unwrap()]);
    let out = stepdrive(&args);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rec = Recorded::read(&mcap).expect("read back");
    let states = &rec.runs[0].1;
    let plans = &rec
        .plans
        .iter()
        .find(|(m, _)| m == "proposed")
        .expect("plans")
        .1;
    let commands = &rec
        .commands
        .iter()
        .find(|(m, _)| m == "proposed")
        .expect("commands")
        .1;
    // A loaded host's current loop misses periods (it sends fewer commands than the plant
    // samples), so the plans are counted against the commands that were sent.
    assert!(
        commands.len() > 100,
        "{} commands for {} states",
        commands.len(),
        states.len()
    );
    assert!(
        plans.len() * 10 >= commands.len(),
        "{} plans for {} commands",
        plans.len(),
        commands.len()
    );
    assert!(plans.iter().all(|p| p.len == 1000 && p.v_a_0.is_finite()));
}

/// `stepdrive record --instance` attached to a running realtime stack records what
/// `run --record` does: states, setpoints, commands and the plans.
#[test]
fn record_attached_to_a_running_stack_takes_every_topic() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("recordattach");
    // The run's length in the file, so that the recorder's scenario is the stack's.
    let scenario = dir.file("short.toml", &format!("{SHORT}\n[run]\nduration_s = 3.0\n"));
    let mcap = dir.path("attached.mcap");
    let inst = instance("recordattach");
    let mut args = vec!["run", "--mode", "realtime", "--method", "proposed"];
    args.extend(realtime_test_args(&scenario, &inst, "3.0"));
    let mut run = spawn_run(&args);
    assert!(
        wait_until(Duration::from_secs(30), || pid_of_role(
            &inst,
            "current-loop"
        )
        .is_some()),
        "the stack did not come up"
    );
    let out = stepdrive(&[
        "record",
        mcap.to_str().unwrap(),
        "--instance",
        &inst,
        "--scenario",
        scenario.to_str().unwrap(),
    ]);
    let status = wait_with_timeout(&mut run, Duration::from_secs(60));
    assert!(status.success(), "{}", stdout_of(&mut run));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rec = Recorded::read(&mcap).expect("read back");
    let sizes = |name: &str, n: usize| (name.to_string(), n);
    let got = [
        sizes("states", rec.runs.iter().map(|r| r.1.len()).sum()),
        sizes("setpoints", rec.setpoints.iter().map(|r| r.1.len()).sum()),
        sizes("commands", rec.commands.iter().map(|r| r.1.len()).sum()),
        sizes("plans", rec.plans.iter().map(|r| r.1.len()).sum()),
    ];
    assert!(got.iter().all(|(_, n)| *n > 100), "{got:?}");
}

/// The messages of a recording by topic, each as (log time, data) in file order (how the
/// monitor interleaves its topics depends on when it reads them, the order within one does
/// not).
type Messages = std::collections::BTreeMap<String, Vec<(u64, Vec<u8>)>>;

fn messages(path: &std::path::Path) -> Messages {
    let bytes = std::fs::read(path).expect("the recording exists");
    let mut by_topic = Messages::new();
    for m in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let m = m.expect("a message that decodes");
        by_topic
            .entry(m.channel.topic.clone())
            .or_default()
            .push((m.log_time, m.data.into_owned()));
    }
    by_topic
}

/// The compression named by every chunk of the file's summary.
fn chunk_compressions(path: &std::path::Path) -> Vec<String> {
    let bytes = std::fs::read(path).expect("the recording exists");
    let summary = mcap::Summary::read(&bytes)
        .expect("a readable file")
        .expect("a summary");
    summary
        .chunk_indexes
        .iter()
        .map(|c| c.compression.clone())
        .collect()
}

/// A recording's chunks are zstd by default and as they are with `--uncompressed`; the two
/// files of one lockstep run hold the same messages byte for byte, and the compressed one is
/// under a third of the other's size (3.55× smaller on this short scenario).
#[test]
fn recordings_are_zstd_compressed_unless_asked_and_hold_the_same_messages() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("zstd");
    let scenario = dir.file("short.toml", SHORT);
    let inst = instance("zstd");
    let record = |file: &str, extra: &[&str]| {
        let path = dir.path(file);
        let mut args = vec!["--record", path.to_str().unwrap()];
        args.extend_from_slice(extra);
        let out = run_proposed(&inst, &scenario, &args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert_finished(&path);
        path
    };
    let packed = record("zstd.mcap", &[]);
    let plain = record("plain.mcap", &["--uncompressed"]);
    let (zstd_chunks, plain_chunks) = (chunk_compressions(&packed), chunk_compressions(&plain));
    assert!(!zstd_chunks.is_empty() && zstd_chunks.iter().all(|c| c == "zstd"));
    assert!(!plain_chunks.is_empty() && plain_chunks.iter().all(|c| c.is_empty()));
    let (a, b) = (messages(&packed), messages(&plain));
    assert!(a["/proposed/state"].len() > 10_000, "{:?}", a.keys());
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (topic, messages) in &a {
        assert!(
            messages == &b[topic],
            "{topic} differs between the two recordings"
        );
    }
    let size = |p: &std::path::Path| std::fs::metadata(p).expect("size").len();
    assert!(
        size(&packed) * 3 < size(&plain),
        "zstd {} B, uncompressed {} B",
        size(&packed),
        size(&plain)
    );
}

/// `serve --foxglove ADDR --foxglove-rate 50`: a Foxglove WebSocket client (written from the
/// protocol: subprotocol `foxglove.sdk.v1`, JSON `advertise` and `subscribe`, binary
/// message data = opcode 1, subscription id u32, log time u64, payload) finds the state
/// channel with its JSON Schema, subscribes, and gets JSON states 20 ms of stack time apart;
/// Ctrl-C still ends `serve` with exit 0.
#[test]
fn a_live_view_serves_the_state_channel_decimated_to_its_rate() {
    use tungstenite::{client::IntoClientRequest, Message};
    let _turn = one_stack_at_a_time();
    let inst = instance("live");
    let addr = format!("127.0.0.1:{}", free_tcp_port());
    let mut serve = spawn_serve(&inst, &["--foxglove", &addr, "--foxglove-rate", "50"]);
    let mut socket = None;
    assert!(
        wait_until(Duration::from_secs(30), || {
            let Ok(tcp) = std::net::TcpStream::connect(&addr) else {
                return false;
            };
            let mut req = format!("ws://{addr}")
                .into_client_request()
                .expect("a request");
            req.headers_mut().insert(
                "sec-websocket-protocol",
                "foxglove.sdk.v1".parse().expect("a header"),
            );
            match tungstenite::client(req, tcp) {
                Ok((ws, _)) => {
                    socket = Some(ws);
                    true
                }
                Err(_) => false,
            }
        }),
        "no live view on {addr}"
    );
    let mut ws = socket.expect("connected");
    // The server is up before the stack starts: the messages are awaited once the stack
    // runs. (In one CI run none came for 10 s after the subscription; if that recurs, the
    // panic below says where the stack's time was.)
    wait_for_stack_time(&inst, &mut serve, 0.05);
    ws.get_mut()
        .set_read_timeout(Some(Duration::from_secs(10)))
        .expect("a timeout");
    // The advertisements: the state channel, JSON with its schema.
    let mut state_channel = None;
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while state_channel.is_none() && std::time::Instant::now() < deadline {
        let Message::Text(text) = ws.read().expect("a message") else {
            continue;
        };
        let v: serde_json::Value = serde_json::from_str(&text).expect("JSON");
        if v["op"] != "advertise" {
            continue;
        }
        for c in v["channels"].as_array().expect("channels") {
            if c["topic"] == "/proposed/state" {
                assert_eq!(c["encoding"], "json", "{c}");
                assert_eq!(c["schemaEncoding"], "jsonschema", "{c}");
                assert!(c["schema"]
                    .as_str()
                    .expect("a schema")
                    .contains("\"theta\""));
                state_channel = c["id"].as_u64();
            }
        }
    }
    let channel = state_channel.expect("the state channel advertised");
    let subscribe = serde_json::json!({
        "op": "subscribe",
        "subscriptions": [{"id": 7, "channelId": channel}],
    });
    ws.send(Message::text(subscribe.to_string()))
        .expect("subscribed");
    let mut times = Vec::new();
    let start = std::time::Instant::now();
    while start.elapsed() < Duration::from_secs(3) {
        let message = ws.read().unwrap_or_else(|e| {
            panic!(
                "no message after {} states in {:.1} s ({e}); the stack's time is {:?}",
                times.len(),
                start.elapsed().as_secs_f64(),
                stack_time(&inst)
            )
        });
        let Message::Binary(b) = message else {
            continue;
        };
        assert_eq!(b[0], 1, "message data");
        assert_eq!(u32::from_le_bytes(b[1..5].try_into().unwrap()), 7);
        let log_ns = u64::from_le_bytes(b[5..13].try_into().unwrap());
        let state: serde_json::Value = serde_json::from_slice(&b[13..]).expect("a JSON state");
        let t = state["t"].as_f64().expect("t");
        assert!(
            state["theta"].is_number() && state["error"].is_number(),
            "{state}"
        );
        assert_eq!(log_ns, (t * 1e9).round() as u64);
        times.push(t);
    }
    signal(serve.id(), libc::SIGINT);
    let status = wait_with_timeout(&mut serve, Duration::from_secs(30));
    assert!(status.success(), "{}", stderr_of(&mut serve));
    assert!(times.len() >= 50, "{} states in 3 s", times.len());
    // One a 20 ms of stack time: never closer, and no more than a sample (50 µs) later
    // unless the monitor missed samples there.
    let gaps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    assert!(gaps.iter().all(|g| *g >= 0.02 - 1e-9), "{gaps:?}");
    let mut sorted = gaps.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    assert!(
        (median - 0.02).abs() <= 50e-6 + 1e-9,
        "median gap {median} s"
    );
}
