//! The figures of `stepdrive plot` as a control engineer reads them, checked in the SVGs
//! drawn from synthetic recordings (written through the `Recording` API, so every value is
//! known): a full run of phase currents or voltages is an envelope beside a zoomed window,
//! traces that lie on each other say so, every pass's cruise window is shaded, tick labels
//! read as numbers in one format per axis, legends stay off the data, and a latched fault
//! is marked with its name on every figure.
//!
//! These tests use only `Recording` and `plot_file`, so the same file runs against any
//! version of the figures.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use stepdrive_monitor::record::plot::plot_file;
use stepdrive_monitor::record::recording::{Chunks, Recording};
use stepdrive_shared::messages::fault_bits;
use stepdrive_shared::trajectory::Trapezoid;
use stepdrive_shared::{DriveState, Method, Scenario};

/// Every figure `plot_file` draws.
const FIGURES: [&str; 8] = [
    "position",
    "error",
    "error_log",
    "currents",
    "currents_cruise",
    "dq_currents",
    "voltages",
    "torque",
];

/// A directory of its own under the system's temporary directory, removed when dropped
/// unless `STEPDRIVE_KEEP_FIGURES` is set (to look at the figures: they are for eyes).
struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        let dir =
            std::env::temp_dir().join(format!("stepdrive-figures-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("a scratch directory");
        Self(dir)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::env::var_os("STEPDRIVE_KEEP_FIGURES").is_some() {
            eprintln!("figures kept in {}", self.0.display());
            return;
        }
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The default scenario at 10 kHz (half the samples: the recording stays small; enough
/// samples per electrical period, 96, that a peak sample is within 0.05 % of the peak).
fn scenario(duration_s: Option<f64>) -> Scenario {
    let mut s = Scenario {
        name: "synthetic".into(),
        ..Scenario::default()
    };
    s.rates.current_loop_hz = 10_000.0;
    s.run.duration_s = duration_s;
    s
}

/// A recording of both methods that follow θ_d to ±0.01 rad with the same phase currents
/// (0.3 A, commutated on θ, 1.2 rad ahead): θ, θ_d, i_q and the torque of both lie on each other at the
/// figures' scale. With `fault_at`, lyapunov latches COMMAND_TIMEOUT then: its outputs go
/// off, its currents decay, its rotor stops.
fn record(dir: &Path, s: &Scenario, fault_at: Option<f64>) -> PathBuf {
    let path = dir.join("run.mcap");
    let mut rec = Recording::create(&path, s, Chunks::Zstd).expect("a recording");
    let tr = Trapezoid::new(&s.trajectory);
    let n_r = s.motor.n_r();
    for method in [Method::Proposed, Method::Lyapunov] {
        rec.begin(method).expect("channels");
        let mut stopped: Option<f64> = None;
        for k in 0..s.sample_count() {
            let t = s.sample_time(k);
            let faulted = method == Method::Lyapunov && fault_at.is_some_and(|f| t >= f);
            let mut theta = tr.at(t).theta - 0.01 * (std::f64::consts::TAU * 3.0 * t).sin();
            if faulted {
                theta = *stopped.get_or_insert(theta);
            }
            let decay = match fault_at {
                Some(f) if faulted => (-(t - f) / 0.002).exp(),
                _ => 1.0,
            };
            // The current vector 1.2 rad ahead of the rotor: i_d = 0.11 A, i_q = 0.28 A.
            let phase = n_r * theta + 1.2;
            let st = DriveState {
                seq: k,
                sample_time_s: t,
                theta_rad: theta,
                i_a_a: 0.3 * phase.cos() * decay,
                i_b_a: 0.3 * phase.sin() * decay,
                v_a_v: if faulted {
                    0.0
                } else {
                    12.0 * (phase + 0.3).cos()
                },
                v_b_v: if faulted {
                    0.0
                } else {
                    12.0 * (phase + 0.3).sin()
                },
                bus_voltage_v: 24.0,
                fault: if faulted {
                    fault_bits::COMMAND_TIMEOUT
                } else {
                    0
                },
                ..DriveState::default()
            };
            rec.state(0, &st, None).expect("a sample");
        }
    }
    rec.finish().expect("a finished recording");
    path
}

/// One SVG element: its tag, attributes and text.
#[derive(Debug)]
struct Element {
    tag: String,
    attrs: BTreeMap<String, String>,
    text: String,
}

impl Element {
    fn num(&self, key: &str) -> f64 {
        self.attrs
            .get(key)
            .and_then(|v| v.parse().ok())
            .unwrap_or(f64::NAN)
    }

    fn points(&self) -> Vec<(f64, f64)> {
        self.attrs
            .get("points")
            .map(|p| {
                p.split_whitespace()
                    .filter_map(|xy| {
                        let (x, y) = xy.split_once(',')?;
                        Some((x.parse().ok()?, y.parse().ok()?))
                    })
                    .collect()
            })
            .unwrap_or_default()
    }
}

/// The elements of an SVG as plotters writes it (one element per tag, attributes quoted).
fn elements(svg: &str) -> Vec<Element> {
    let mut out = Vec::new();
    let mut rest = svg;
    while let Some(open) = rest.find('<') {
        rest = &rest[open + 1..];
        let Some(close) = rest.find('>') else { break };
        let inside = &rest[..close];
        rest = &rest[close + 1..];
        if inside.starts_with('/') || inside.starts_with('?') || inside.starts_with('!') {
            continue;
        }
        let tag: String = inside.chars().take_while(|c| !c.is_whitespace()).collect();
        let mut attrs = BTreeMap::new();
        let mut a = &inside[tag.len()..];
        while let Some(eq) = a.find("=\"") {
            let key = a[..eq].trim().to_string();
            let after = &a[eq + 2..];
            let Some(end) = after.find('"') else { break };
            attrs.insert(key, after[..end].to_string());
            a = &after[end + 1..];
        }
        let text = if inside.ends_with('/') {
            String::new()
        } else {
            rest[..rest.find('<').unwrap_or(rest.len())]
                .trim()
                .replace("&amp;", "&")
                .replace("&lt;", "<")
                .replace("&gt;", ">")
        };
        out.push(Element {
            tag: tag.trim_end_matches('/').to_string(),
            attrs,
            text,
        });
    }
    out
}

fn svg(dir: &Path, name: &str) -> Vec<Element> {
    let text = std::fs::read_to_string(dir.join(format!("{name}.svg"))).expect(name);
    elements(&text)
}

/// A tick label: its text, value and anchor point.
#[derive(Debug, Clone)]
struct Label {
    text: String,
    value: f64,
    x: f64,
    y: f64,
}

/// The tick labels of every axis: the numeric texts, x axes (centred under their ticks)
/// split where the value stops growing to the right, y axes (right-aligned beside theirs)
/// grouped by their x.
fn axes(els: &[Element]) -> (Vec<Vec<Label>>, Vec<Vec<Label>>) {
    let numeric = |anchor: &str| -> Vec<Label> {
        els.iter()
            .filter(|e| e.tag == "text" && e.attrs.get("text-anchor").is_some_and(|a| a == anchor))
            .filter(|e| !e.attrs.contains_key("transform"))
            .filter_map(|e| {
                Some(Label {
                    value: e.text.parse().ok()?,
                    text: e.text.clone(),
                    x: e.num("x"),
                    y: e.num("y"),
                })
            })
            .collect()
    };
    let mut xs = numeric("middle");
    xs.sort_by(|a, b| a.y.total_cmp(&b.y).then(a.x.total_cmp(&b.x)));
    let mut x_axes: Vec<Vec<Label>> = Vec::new();
    for l in xs {
        match x_axes.last_mut() {
            Some(axis) if axis.last().is_some_and(|p| p.y == l.y && p.value < l.value) => {
                axis.push(l)
            }
            _ => x_axes.push(vec![l]),
        }
    }
    let mut y_axes: BTreeMap<i64, Vec<Label>> = BTreeMap::new();
    for l in numeric("end") {
        y_axes.entry(l.x as i64).or_default().push(l);
    }
    (x_axes, y_axes.into_values().collect())
}

/// t → x pixel of the (first) time axis, from its tick labels.
fn time_to_px(els: &[Element]) -> impl Fn(f64) -> f64 {
    let (x_axes, _) = axes(els);
    let axis = x_axes
        .into_iter()
        .max_by_key(|a| a.len())
        .expect("a time axis");
    let (a, b) = (&axis[0], &axis[axis.len() - 1]);
    let scale = (b.x - a.x) / (b.value - a.value);
    let (x0, t0) = (a.x, a.value);
    move |t| x0 + (t - t0) * scale
}

/// How often a trace turns (up to down or back) per 100 px of its width: a trace that
/// turns every few pixels is a solid fill, not a line.
fn turns_per_100px(points: &[(f64, f64)]) -> f64 {
    let mut turns = 0;
    let mut last_dir = 0.0;
    for w in points.windows(2) {
        let d = w[1].1 - w[0].1;
        if d != 0.0 {
            if last_dir != 0.0 && d.signum() != last_dir {
                turns += 1;
            }
            last_dir = d.signum();
        }
    }
    let (lo, hi) = points.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
        (lo.min(p.0), hi.max(p.0))
    });
    100.0 * f64::from(turns) / (hi - lo).max(1.0)
}

#[test]
fn full_run_currents_and_voltages_are_an_envelope_beside_a_zoomed_window() {
    let dir = Scratch::new("envelope");
    let s = scenario(None);
    let figs = dir.0.join("figs");
    plot_file(&record(&dir.0, &s, None), &figs).expect("figures");
    for name in ["currents", "voltages"] {
        let els = svg(&figs, name);
        for e in els
            .iter()
            .filter(|e| e.tag == "polyline" || e.tag == "polygon")
        {
            let p = e.points();
            let (lo, hi) = p.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                (lo.min(p.0), hi.max(p.0))
            });
            // A trace across a stretch of the plot (a dash or a swatch is too short to
            // tell).
            if hi - lo < 100.0 {
                continue;
            }
            let turns = turns_per_100px(&p);
            assert!(
                turns <= 10.0,
                "{name}: a trace of {} points turns {turns:.0} times per 100 px (a solid fill)",
                p.len()
            );
        }
        let (x_axes, _) = axes(&els);
        assert!(
            x_axes.len() >= 2,
            "{name}: a zoomed time axis beside the full run: {x_axes:?}"
        );
    }
}

#[test]
fn traces_that_lie_on_each_other_say_so_in_the_legend() {
    let dir = Scratch::new("coincide");
    let s = scenario(None);
    let figs = dir.0.join("figs");
    plot_file(&record(&dir.0, &s, None), &figs).expect("figures");
    for (name, entries) in [
        ("position", &["θ (proposed)", "θ (lyapunov)"][..]),
        ("dq_currents", &["i_q (lyapunov)"][..]),
        ("torque", &["(lyapunov)"][..]),
    ] {
        let els = svg(&figs, name);
        for entry in entries {
            assert!(
                els.iter().any(|e| e.tag == "text"
                    && e.text.contains(entry)
                    && e.text.contains("lies on")),
                "{name}: the legend says that {entry} lies on another trace"
            );
        }
    }
}

#[test]
fn every_pass_has_its_cruise_window_shaded() {
    let dir = Scratch::new("windows");
    // Three passes of 2.5 s: windows at 0.9–1.5, 3.4–4.0 and 5.9–6.0 (cut by the end).
    let s = scenario(Some(6.0));
    let figs = dir.0.join("figs");
    plot_file(&record(&dir.0, &s, None), &figs).expect("figures");
    for name in ["error", "position", "torque"] {
        let els = svg(&figs, name);
        let px = time_to_px(&els);
        for (from, to) in [(0.9, 1.5), (3.4, 4.0), (5.9, 6.0)] {
            let shaded = els.iter().any(|e| {
                e.tag == "rect"
                    && e.attrs.get("fill").is_some_and(|f| f != "none")
                    && (e.num("x") - px(from)).abs() <= 2.0
                    && (e.num("x") + e.num("width") - px(to)).abs() <= 2.0
            });
            assert!(shaded, "{name}: the cruise window {from}–{to} s is shaded");
        }
    }
}

#[test]
fn tick_labels_read_as_numbers_in_one_format_per_axis() {
    let dir = Scratch::new("ticks");
    let s = scenario(None);
    let figs = dir.0.join("figs");
    plot_file(&record(&dir.0, &s, None), &figs).expect("figures");
    // Every fault of every axis, then one assertion that lists them.
    let mut faults = Vec::new();
    for name in FIGURES {
        let (x_axes, y_axes) = axes(&svg(&figs, name));
        for axis in x_axes.iter().chain(&y_axes) {
            let texts: Vec<&str> = axis.iter().map(|l| l.text.as_str()).collect();
            let largest = axis.iter().map(|l| l.value.abs()).fold(0.0, f64::max);
            // Evenly spaced values: a linear axis, where a tick a billionth of the largest
            // is a zero missed by rounding (a log axis's 1e-14 is not).
            let steps: Vec<f64> = axis.windows(2).map(|w| w[1].value - w[0].value).collect();
            let linear = steps
                .iter()
                .all(|d| (d - steps[0]).abs() <= 1e-6 * steps[0].abs());
            for l in axis.iter().filter(|_| linear) {
                if l.value.abs() <= 1e-9 * largest
                    && (l.text.contains('e') || l.text.starts_with('-'))
                {
                    faults.push(format!("{name}: zero written as {} on {texts:?}", l.text));
                }
            }
            let not_zero: Vec<&str> = texts.iter().copied().filter(|t| *t != "0").collect();
            let sci = not_zero.iter().filter(|t| t.contains('e')).count();
            if sci != 0 && sci != not_zero.len() {
                faults.push(format!("{name}: one axis mixes notations: {texts:?}"));
            }
            let decimals = |t: &str| t.split_once('.').map_or(0, |(_, d)| d.len());
            if sci == 0
                && !not_zero
                    .iter()
                    .all(|t| decimals(t) == decimals(not_zero[0]))
            {
                faults.push(format!("{name}: one axis mixes decimals: {texts:?}"));
            }
            if texts.windows(2).any(|w| w[0] == w[1]) {
                faults.push(format!("{name}: two ticks read the same: {texts:?}"));
            }
        }
    }
    assert!(faults.is_empty(), "{}", faults.join("\n"));
}

#[test]
fn legends_leave_the_data_alone() {
    let dir = Scratch::new("legend");
    let s = scenario(None);
    let figs = dir.0.join("figs");
    plot_file(&record(&dir.0, &s, None), &figs).expect("figures");
    for name in FIGURES {
        let els = svg(&figs, name);
        // Vertices of the data: lines of three points or more (a legend's swatch has two)
        // and filled bands.
        let data: Vec<(f64, f64)> = els
            .iter()
            .filter(|e| e.tag == "polygon" || (e.tag == "polyline" && e.points().len() >= 3))
            .flat_map(Element::points)
            .collect();
        for e in els.iter().filter(|e| {
            e.tag == "text"
                && (e.text.contains("(proposed)") || e.text.contains("(lyapunov)"))
                && e.attrs.get("text-anchor").is_some_and(|a| a == "start")
        }) {
            let size = e.num("font-size") * 1.24;
            let (x0, x1) = (
                e.num("x"),
                e.num("x") + 0.6 * size * e.text.chars().count() as f64,
            );
            let (y0, y1) = (e.num("y") - size, e.num("y") + size);
            let under = data
                .iter()
                .filter(|p| p.0 >= x0 && p.0 <= x1 && p.1 >= y0 && p.1 <= y1)
                .count();
            assert_eq!(
                under, 0,
                "{name}: the legend entry {:?} lies over the data",
                e.text
            );
        }
    }
}

#[test]
fn a_latched_fault_is_marked_with_its_name_on_every_figure() {
    let dir = Scratch::new("fault");
    let s = scenario(None);
    let figs = dir.0.join("figs");
    plot_file(&record(&dir.0, &s, Some(1.2)), &figs).expect("figures");
    for name in FIGURES {
        let els = svg(&figs, name);
        let marks: Vec<&Element> = els
            .iter()
            .filter(|e| e.tag == "text" && e.text.contains("COMMAND_TIMEOUT"))
            .collect();
        assert!(!marks.is_empty(), "{name}: the fault is named");
        if name == "error" {
            let px = time_to_px(&els);
            assert!(
                marks.iter().any(|e| (e.num("x") - px(1.2)).abs() <= 8.0),
                "{name}: the name is written at the instant the fault latched ({:.0} px): {marks:?}",
                px(1.2)
            );
        }
    }
}
