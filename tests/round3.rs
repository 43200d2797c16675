//! Reliability, round 3: what a new user and a stranger's drive still broke. Each test is
//! one finding of that issue, and failed on the code before its fix.

mod common;

use common::*;
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
