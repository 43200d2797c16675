//! Figures from the stack's timeline (issue 44, "a figure reported with exit 0 must be
//! true"): what a report and a recording say of a run is what the stack did at each tick,
//! whatever order the monitor's drains met its messages in. Each test failed on the code
//! before its fix.

use crate::common::*;
use std::path::Path;

/// Item 10: on the wall clock a multi-axis position loop ticks on its own clock, so the
/// newest sample at a tick is 9, 11 or fewer samples after the last one's, and the group
/// stepped its coordinated move by that time rounded to ticks, only at axis 0's ticks. At
/// a tick it gave no state for (a step rounded to none, axis 0 without a new sample), an
/// axis stood on its last θ_d at a later time: the setpoint a tick behind (3.6e-3 rad on z
/// at 8 rad/s), the current loop pulling the rotor back, and the report's max |e| 3.0e-4,
/// 1.8e-3, 3.6e-3 rad where lockstep says 8e-8 … 1.7e-6. Each axis's recorded setpoints
/// are now one trajectory: between two of its ticks θ_d advances by the mean of their ω_d
/// times the time between them (to the jerk's term), however late the ticks came.
#[test]
fn a_realtime_coordinated_move_sends_each_axis_its_move_at_its_own_sample_time() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("rt-coordinated");
    let inst = instance("rt-coordinated");
    let json = dir.path("run.json");
    let mcap = dir.path("run.mcap");
    let scenario = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/three-axes.toml");
    let mut args = vec![
        "run",
        "--mode",
        "realtime",
        "--method",
        "proposed",
        "--scenario",
        scenario,
        "--instance",
        &inst,
        "--json",
        json.to_str().expect("a UTF-8 path"),
        "--record",
        mcap.to_str().expect("a UTF-8 path"),
    ];
    args.extend(ORDINARY_STACK);
    let out = stepdrive(&args);
    // Exit 0, or an ordinary-scheduling run the host starved (judged by its own report):
    // what is checked is what the position loop sent.
    assert!(
        out.status.code().is_some_and(|c| c == 0 || c == 6),
        "{}",
        text(&out)
    );
    let csv = dir.path("csv");
    export_csv(&mcap, &csv);
    // The axes' jerk limits (scenarios/three-axes.toml): the trapezoid rule's error over a
    // gap dt is at most j dt³ / 12.
    let mut report = Vec::new();
    for (axis, prefix, jerk) in [
        (0, "proposed", 2000.0),
        (1, "axis1_proposed", 5000.0),
        (2, "axis2_proposed", 1000.0),
    ] {
        let sp = Csv::read(&csv.join(format!("{prefix}_setpoint.csv")));
        let (t, theta, omega) = (sp.col("t ["), sp.col("theta_d"), sp.col("omega_d"));
        let rows: Vec<[f64; 3]> = sp
            .rows()
            .map(|r| [t, theta, omega].map(|c| r[c].parse::<f64>().expect("a number")))
            .collect();
        assert!(rows.len() > 2000, "axis {axis}: {} setpoints", rows.len());
        let (mut off, mut worst) = (0, 0.0f64);
        for w in rows.windows(2) {
            let dt = w[1][0] - w[0][0];
            if dt <= 0.0 {
                continue;
            }
            let e = (w[1][1] - w[0][1] - 0.5 * (w[0][2] + w[1][2]) * dt).abs();
            worst = worst.max(e);
            if e > 1e-6 + jerk * dt.powi(3) / 12.0 {
                off += 1;
            }
        }
        if off > 0 {
            report.push(format!(
                "axis {axis}: θ_d off its own time at {off} of {} ticks (up to {worst:.2e} rad)",
                rows.len()
            ));
        }
    }
    assert!(report.is_empty(), "{}\n{}", report.join("\n"), text(&out));
}

/// A program of two axes with what changes a move under way: re-targets ("change
/// immediately"), moves queued "after the current move" (each while the set-point buffer
/// is free), jogs, stops, a quick stop (which the group's policy takes to the other axis)
/// and an enable after it.
const PROGRAM: &str = r#"
name = "timeline"
[run]
duration_s = 1.3
[[program]]
at_s = 0.0
command = "enable"
[[program]]
at_s = 0.01
command = "move"
to = 1.0
[[program]]
at_s = 0.08
command = "move"
to = -0.5
[[program]]
at_s = 0.1
command = "move"
to = 0.5
after_current = true
[[program]]
at_s = 0.5
command = "jog"
velocity = 4.0
[[program]]
at_s = 0.6
command = "stop"
[[program]]
at_s = 0.7
command = "move"
to = 1.0
[[program]]
at_s = 0.72
command = "move"
to = 0.0
after_current = true
[[program]]
at_s = 0.95
command = "quick-stop"
[[program]]
at_s = 1.0
command = "enable"
[[program]]
at_s = 1.02
command = "move"
to = 0.3

[[program]]
at_s = 0.0
axis = 1
command = "enable"
[[program]]
at_s = 0.02
axis = 1
command = "move"
to = -2.0
[[program]]
at_s = 0.06
axis = 1
command = "move"
to = 1.0
[[program]]
at_s = 0.4
axis = 1
command = "jog"
velocity = -3.0
[[program]]
at_s = 0.5
axis = 1
command = "stop"
[[program]]
at_s = 0.7
axis = 1
command = "move"
to = 0.5
[[program]]
at_s = 0.72
axis = 1
command = "move"
to = -0.5
after_current = true

[[axis]]
name = "x"
[[axis]]
name = "y"
"#;

/// A run's JSON document without the wall clock's fields (its wall time, when a fault was
/// seen), as text.
fn without_wall_times(path: &Path) -> String {
    fn strip(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::Object(map) => {
                map.remove("wall_time_s");
                map.remove("seen_unix_s");
                map.values_mut().for_each(strip);
            }
            serde_json::Value::Array(items) => items.iter_mut().for_each(strip),
            _ => {}
        }
    }
    let mut doc = read_json(path);
    strip(&mut doc);
    serde_json::to_string_pretty(&doc).expect("JSON")
}

/// Every exported topic of a recording but the loops' statistics (counted on the wall
/// clock), by file name.
fn recorded_topics(dir: &Path) -> Vec<(String, String)> {
    let mut files: Vec<(String, String)> = std::fs::read_dir(dir)
        .expect("the export's directory")
        .map(|e| e.expect("an entry").path())
        .filter(|p| !p.to_string_lossy().ends_with("_stats.csv"))
        .map(|p| {
            let name = p.file_name().map(|n| n.to_string_lossy().into_owned());
            (
                name.unwrap_or_default(),
                std::fs::read_to_string(&p).expect("a CSV file"),
            )
        })
        .collect();
    files.sort();
    files
}

/// Where two texts first differ, by line.
fn first_difference(a: &str, b: &str) -> String {
    a.lines()
        .zip(b.lines())
        .enumerate()
        .find(|(_, (x, y))| x != y)
        .map_or_else(
            || format!("{} lines against {}", a.lines().count(), b.lines().count()),
            |(i, (x, y))| format!("line {}: {x} | {y}", i + 1),
        )
}

/// Item 11: the monitor graded a program's moves in the order the acknowledgements reached
/// it, and recorded each state's θ_d from the setpoints that had reached it: between
/// identical lockstep runs moves were reported `re-targeted` with no duration, with peaks of
/// 0, and the recorded θ_d differed at a few samples a run. Graded on the stack's timeline,
/// ten runs of one program give one JSON document (wall times aside) and one recording.
#[test]
fn lockstep_runs_of_one_program_report_and_record_the_same() {
    let _turn = one_stack_at_a_time();
    let dir = TempDir::new("same-runs");
    let inst = instance("same-runs");
    let scenario = dir.file("program.toml", PROGRAM);
    let mut first: Option<(String, Vec<(String, String)>)> = None;
    let mut differ = Vec::new();
    for run in 0..10 {
        let json = dir.path(&format!("run{run}.json"));
        let mcap = dir.path(&format!("run{run}.mcap"));
        let out = run_proposed(
            &inst,
            &scenario,
            &[
                "--json",
                json.to_str().expect("a UTF-8 path"),
                "--record",
                mcap.to_str().expect("a UTF-8 path"),
            ],
        );
        assert!(out.status.success(), "run {run}: {}", text(&out));
        let csv = dir.path(&format!("csv{run}"));
        export_csv(&mcap, &csv);
        let doc = without_wall_times(&json);
        let topics = recorded_topics(&csv);
        let Some((doc0, topics0)) = &first else {
            // The runs compared are the ones meant: every move of each axis reported, some
            // of them replaced before they got there.
            let report = read_json(&json);
            let run = run_of(&report, "proposed");
            let moves = |r: &serde_json::Value| r["moves"].as_array().map_or(0, Vec::len);
            assert_eq!(moves(run), 6, "{}", text(&out));
            assert_eq!(moves(&run["axes"][0]), 4, "{}", text(&out));
            assert!(
                run["moves"]
                    .as_array()
                    .is_some_and(|m| m.iter().any(|m| m["retargeted_at_s"].is_number())),
                "{}",
                text(&out)
            );
            assert!(
                topics.iter().any(|(n, _)| n == "axis1_proposed_state.csv"),
                "{topics:?}"
            );
            first = Some((doc, topics));
            continue;
        };
        if doc != *doc0 {
            differ.push(format!("run {run}: JSON {}", first_difference(doc0, &doc)));
        }
        let names = |t: &[(String, String)]| t.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
        assert_eq!(names(topics0), names(&topics), "run {run}'s topics");
        for ((name, a), (_, b)) in topics0.iter().zip(&topics) {
            if a != b {
                differ.push(format!("run {run}: {name} {}", first_difference(a, b)));
            }
        }
    }
    assert!(
        differ.is_empty(),
        "{} differences from run 0:\n{}",
        differ.len(),
        differ.join("\n")
    );
}
