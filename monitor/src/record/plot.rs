//! The paper's figures from a recording, as SVG and PNG: position, tracking error (linear
//! and log, with the eq. (7) bound), phase currents and phase voltages (each an envelope of
//! the full run beside a zoomed window), phase a's current against its reference, i_d and
//! i_q, torque. Several methods in one recording are overlaid.
//!
//! Made to be read by a control engineer: every pass's cruise window is shaded; a fault is
//! shaded from the sample it was set on, with its name above the plot; traces that lie on
//! each other at the figure's scale are dashed and say so in the legend; tick labels are
//! chosen here (one format per axis, zero written as 0); the legend sits below the plots,
//! never over the data. What goes where is computed by pure functions (envelopes, ticks,
//! windows, fault spans, overlaps, the legend's layout); plotters only draws it.

use crate::record::recording::{RecordError, Recorded, StateRecord, StatusRecord};
use crate::report::outcome::{fault_names, LATCHED};
use plotters::coord::ranged1d::{KeyPointHint, NoDefaultFormatting, Ranged, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::{Path, PathBuf};
use stepdrive_shared::axis::AxisState;
use stepdrive_shared::trajectory::Trapezoid;
use stepdrive_shared::Scenario;

#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error(transparent)]
    Recording(#[from] RecordError),
    #[error("{0} holds no state samples")]
    Empty(PathBuf),
    #[error("cannot draw {path}: {message}")]
    Draw { path: PathBuf, message: String },
    #[error("cannot create the plot directory {path}")]
    Dir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// The font of every label: embedded, so PNGs need no system fonts.
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

fn register_font() {
    use std::sync::Once;
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The embedded font is a valid TrueType file: registration cannot fail.
        let _ = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
    });
}

/// How a line is stroked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stroke {
    Solid,
    /// `on` pixels drawn, `off` left out, along the line.
    Dashed {
        on: u32,
        off: u32,
    },
}

/// The dashes of a method's second quantity (i_b beside i_a, i_d beside i_q, a reference).
const SECOND: Stroke = Stroke::Dashed { on: 6, off: 4 };

/// One line of a panel, or, with `lower`, a band: the area between `lower` and `points`.
#[derive(Debug, Clone)]
struct Series {
    name: String,
    /// In time order, every sample (decimated only when drawn).
    points: Vec<(f64, f64)>,
    lower: Option<Vec<(f64, f64)>>,
    color: RGBColor,
    stroke: Stroke,
    /// The run (method) it is of, which groups the legend; `None`: a reference (θ_d, the
    /// bound, the bus).
    run: Option<usize>,
}

impl Series {
    fn line(name: String, points: Vec<(f64, f64)>, color: RGBColor, stroke: Stroke) -> Self {
        Self {
            name,
            points,
            lower: None,
            color,
            stroke,
            run: None,
        }
    }
}

/// One plot: its series over time, against one y axis.
#[derive(Debug, Clone)]
struct Panel {
    /// Above the plot when the figure has two panels.
    title: Option<String>,
    y_label: String,
    series: Vec<Series>,
    /// The time shown, s.
    window: (f64, f64),
    /// A stretch of the run beside (or instead of) the whole: cruise windows are not
    /// shaded on it (its title says where it is).
    zoomed: bool,
    /// y holds log10 of the quantity: ticks at decades.
    log: bool,
}

/// What a stretch of time shaded on a panel is.
#[derive(Debug, Clone, PartialEq)]
enum SpanKind {
    /// A cruise window of the metrics (one per pass).
    Cruise,
    /// The stretch the zoomed panel beside shows.
    Zoom,
    /// A run's fault bits were set: the name to write above the plot, and the legend's text.
    Fault { label: String, legend: String },
    /// The axis was in this CiA 402 state (a program's figures; Operation enabled is not
    /// shaded).
    Axis(AxisState),
}

#[derive(Debug, Clone, PartialEq)]
struct Span {
    from: f64,
    to: f64,
    kind: SpanKind,
}

/// A figure: one file, one title, its panels side by side (the first the widest), the spans
/// shaded on them and one legend below.
#[derive(Debug, Clone)]
struct Figure {
    file: &'static str,
    title: String,
    panels: Vec<Panel>,
    spans: Vec<Span>,
}

/// The methods' colours: blue and orange first (told apart in colour-blind vision too); no
/// red, which marks faults.
const COLORS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
];
const FAULT: RGBColor = RGBColor(200, 0, 0);
const CRUISE_FILL: RGBColor = RGBColor(255, 205, 60);
const CRUISE_EDGE: RGBColor = RGBColor(190, 140, 0);
const ZOOM_FILL: RGBColor = RGBColor(90, 90, 90);
const BOUND: RGBColor = RGBColor(120, 120, 120);

/// The second quantity of a method (dashed): a lighter shade of its colour, so that the
/// legend tells the two apart.
fn light(c: RGBColor) -> RGBColor {
    let up = |v: u8| ((u16::from(v) + 255) / 2) as u8;
    RGBColor(up(c.0), up(c.1), up(c.2))
}

/// At most `2 × buckets` points: each bucket's minimum and maximum, in time order, so that
/// peaks survive (a 50 000-sample run would make a 10 MB SVG).
fn decimate(points: Vec<(f64, f64)>, buckets: usize) -> Vec<(f64, f64)> {
    if points.len() <= 2 * buckets {
        return points;
    }
    let per = points.len().div_ceil(buckets);
    let mut out = Vec::with_capacity(2 * buckets);
    for chunk in points.chunks(per) {
        let lo = chunk
            .iter()
            .copied()
            .fold(chunk[0], |a, p| if p.1 < a.1 { p } else { a });
        let hi = chunk
            .iter()
            .copied()
            .fold(chunk[0], |a, p| if p.1 > a.1 { p } else { a });
        if lo.0 <= hi.0 {
            out.extend([lo, hi]);
        } else {
            out.extend([hi, lo]);
        }
    }
    out
}

/// Points of a line, (t, value), in time order.
type Trace = Vec<(f64, f64)>;

/// The envelope of a waveform: its least and greatest value over each window of about
/// `window` of time, at the window's middle (lower edge, upper edge). A phase current or
/// voltage swings hundreds of electrical periods over a run, which a full-run line draws
/// as a solid fill; over windows of two electrical periods or more its envelope is its
/// amplitude. The windows divide the run evenly (a short last one would show a part of a
/// period as if it were the amplitude). `points` may hold several waveforms (both phases)
/// in time order.
fn envelope(points: &[(f64, f64)], window: f64) -> (Trace, Trace) {
    let (mut lower, mut upper) = (Vec::new(), Vec::new());
    let finite = points.iter().filter(|p| p.0.is_finite() && p.1.is_finite());
    let (Some(t0), Some(t1)) = (
        finite.clone().map(|p| p.0).reduce(f64::min),
        finite.clone().map(|p| p.0).reduce(f64::max),
    ) else {
        return (lower, upper);
    };
    let windows = if window > 0.0 {
        ((t1 - t0) / window).round().max(1.0)
    } else {
        1.0
    };
    let width = ((t1 - t0) / windows).max(f64::MIN_POSITIVE);
    let last = windows as i64 - 1;
    // (window, first t, last t, min, max)
    let mut open: Option<(i64, f64, f64, f64, f64)> = None;
    let mut close = |b: (i64, f64, f64, f64, f64)| {
        let mid = 0.5 * (b.1 + b.2);
        lower.push((mid, b.3));
        upper.push((mid, b.4));
    };
    for &(t, v) in finite {
        let k = (((t - t0) / width).floor() as i64).min(last);
        open = match open {
            Some(b) if b.0 == k => Some((k, b.1.min(t), b.2.max(t), b.3.min(v), b.4.max(v))),
            Some(b) => {
                close(b);
                Some((k, t, t, v, v))
            }
            None => Some((k, t, t, v, v)),
        };
    }
    if let Some(b) = open {
        close(b);
    }
    (lower, upper)
}

/// The ticks of one axis: where the labelled lines go, the light lines between them, and
/// how their labels are written (one format for the whole axis).
#[derive(Debug, Clone, PartialEq)]
struct Ticks {
    major: Vec<f64>,
    minor: Vec<f64>,
    format: TickFormat,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum TickFormat {
    /// `decimals` after the point: 0.005, 0.010, 0.015.
    Fixed(usize),
    /// One exponent for the axis: 0.5e-4, 1.0e-4.
    Scientific { exponent: i32, decimals: usize },
    /// The axis holds log10 of the quantity; a tick k is written 1e{k}.
    Decades,
}

/// An axis with the ticks chosen here, every label in the axis's one format (plotters's
/// own f64 axis puts ticks at sums that miss zero and formats each label on its own).
struct Axis {
    inner: RangedCoordf64,
    ticks: Ticks,
}

impl Axis {
    fn new(lo: f64, hi: f64, ticks: Ticks) -> Self {
        Self {
            inner: (lo..hi).into(),
            ticks,
        }
    }
}

impl Ranged for Axis {
    type FormatOption = NoDefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        self.inner.map(value, limit)
    }

    fn key_points<Hint: KeyPointHint>(&self, hint: Hint) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.ticks.minor.clone()
        } else {
            self.ticks.major.clone()
        }
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.inner.range()
    }
}

impl ValueFormatter<f64> for Axis {
    fn format_ext(&self, value: &f64) -> String {
        tick_label(*value, self.ticks.format)
    }
}

/// 1, 2 or 5 × 10^n: the least such step that puts at most `most` intervals in `span`.
fn nice_step(span: f64, most: usize) -> f64 {
    let raw = span / most.max(1) as f64;
    let magnitude = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * magnitude)
        .find(|s| *s >= raw * (1.0 - 1e-9))
        .unwrap_or(10.0 * magnitude)
}

/// The multiples of `step` in [lo, hi], each computed as k × step from an integer k (never
/// accumulated), zero exactly zero: a tick is never -2.8e-17.
fn multiples(lo: f64, hi: f64, step: f64) -> Vec<f64> {
    let first = (lo / step - 1e-9).ceil() as i64;
    let last = (hi / step + 1e-9).floor() as i64;
    (first..=last)
        .map(|k| if k == 0 { 0.0 } else { k as f64 * step })
        .collect()
}

/// Ticks of a linear axis over [lo, hi], at most `most` intervals between labels.
fn linear_ticks(lo: f64, hi: f64, most: usize) -> Ticks {
    let span = hi - lo;
    if !(span.is_finite() && span > 0.0) {
        return Ticks {
            major: vec![lo],
            minor: Vec::new(),
            format: TickFormat::Fixed(3),
        };
    }
    let step = nice_step(span, most);
    let lead = (step / 10f64.powf(step.log10().floor())).round();
    let minor_step = if lead == 2.0 { step / 4.0 } else { step / 5.0 };
    let major = multiples(lo, hi, step);
    let largest = major.iter().map(|v| v.abs()).fold(0.0, f64::max);
    let step_exp = step.log10().floor() as i32;
    // Plain decimals while they stay short; otherwise one exponent for the axis.
    let format = if step >= 1e-3 && largest < 1e5 {
        TickFormat::Fixed(usize::try_from(-step_exp).unwrap_or(0))
    } else {
        let exponent = if largest > 0.0 {
            largest.log10().floor() as i32
        } else {
            step_exp
        };
        TickFormat::Scientific {
            exponent,
            decimals: usize::try_from(exponent - step_exp).unwrap_or(0),
        }
    };
    Ticks {
        minor: multiples(lo, hi, minor_step),
        major,
        format,
    }
}

/// Ticks of an axis holding log10 of the quantity: whole decades, light lines at 2…9 × a
/// decade when one decade is labelled per step.
fn decade_ticks(lo: f64, hi: f64, most: usize) -> Ticks {
    let step = nice_step(hi - lo, most).max(1.0).round();
    let major = multiples(lo, hi, step);
    let minor = if step == 1.0 {
        let first = lo.floor() as i64;
        let last = hi.ceil() as i64;
        (first..=last)
            .flat_map(|k| (1..10).map(move |m| k as f64 + f64::from(m).log10()))
            .filter(|v| *v >= lo && *v <= hi)
            .collect()
    } else {
        multiples(lo, hi, 1.0)
    };
    Ticks {
        major,
        minor,
        format: TickFormat::Decades,
    }
}

/// A tick's label in its axis's format; zero is "0" in every format.
fn tick_label(v: f64, format: TickFormat) -> String {
    match format {
        TickFormat::Decades => format!("1e{}", v.round() as i64),
        _ if v == 0.0 => "0".to_string(),
        TickFormat::Fixed(decimals) => format!("{v:.decimals$}"),
        TickFormat::Scientific { exponent, decimals } => {
            format!("{:.decimals$}e{exponent}", v / 10f64.powi(exponent))
        }
    }
}

/// Every pass's cruise window within [0, end], s. The metrics take the window in every pass
/// of a repeating move (report/metrics.rs: the time within the pass), so each is marked;
/// the last one is cut at the end of the run. A run that did not run the profile (a
/// program, a served stack) has none: its cruise figures are n/a.
fn cruise_windows(s: &Scenario, end: f64) -> Vec<(f64, f64)> {
    if !s.runs_profile() {
        return Vec::new();
    }
    let (from, to) = (s.metrics.cruise_start_s, s.metrics.cruise_end_s);
    let period = Trapezoid::new(&s.trajectory).period();
    let mut out = Vec::new();
    // A bound on the passes drawn: a run of 10 000 passes is no figure anyway.
    for k in 0..10_000u32 {
        let offset = f64::from(k) * period;
        if from + offset >= end {
            break;
        }
        out.push((from + offset, (to + offset).min(end)));
        if period <= 0.0 {
            break;
        }
    }
    out
}

/// A stretch of a run with the same fault bits set: from the first sample that had them to
/// the first that had others (or the run's last sample, `to_end`).
#[derive(Debug, Clone, PartialEq)]
struct FaultSpan {
    from: f64,
    to: f64,
    bits: u32,
    to_end: bool,
}

fn fault_spans(states: &[StateRecord]) -> Vec<FaultSpan> {
    let mut out = Vec::new();
    let mut open: Option<(f64, u32)> = None;
    for s in states {
        if open.is_some_and(|(_, bits)| bits == s.fault) {
            continue;
        }
        if let Some((from, bits)) = open.take() {
            out.push(FaultSpan {
                from,
                to: s.t,
                bits,
                to_end: false,
            });
        }
        if s.fault != 0 {
            open = Some((s.t, s.fault));
        }
    }
    if let (Some((from, bits)), Some(last)) = (open, states.last()) {
        out.push(FaultSpan {
            from,
            to: last.t,
            bits,
            to_end: true,
        });
    }
    out
}

/// The fault bits by their short names, without the explanations `fault_names` adds in
/// parentheses (those are for the headline; a plot has room for the names).
fn short_fault_name(bits: u32) -> String {
    let names: Vec<String> = fault_names(bits)
        .iter()
        .map(|n| {
            let mut out = String::new();
            let mut depth = 0u32;
            for c in n.chars() {
                match c {
                    '(' => depth += 1,
                    ')' => depth = depth.saturating_sub(1),
                    _ if depth == 0 => out.push(c),
                    _ => {}
                }
            }
            out.split_whitespace()
                .collect::<Vec<_>>()
                .join(" ")
                .replace(" ,", ",")
        })
        .collect();
    if names.is_empty() {
        format!("fault {bits:#x}")
    } else {
        names.join(" + ")
    }
}

/// How much of `a` (its samples within `b`'s time span) lies within `tol` of `b`, the share
/// of `a`'s samples: 1.0 when `a` lies on `b` everywhere. `b` in time order.
fn share_on(a: &[(f64, f64)], b: &[(f64, f64)], tol: f64) -> f64 {
    let (Some(first), Some(last)) = (b.first(), b.last()) else {
        return 0.0;
    };
    let mut j = 0;
    let mut near = 0usize;
    for &(t, v) in a {
        if t < first.0 || t > last.0 {
            continue;
        }
        while j + 1 < b.len() && b[j + 1].0 < t {
            j += 1;
        }
        let (p, q) = (b[j], b[(j + 1).min(b.len() - 1)]);
        let at = if q.0 > p.0 && t >= p.0 {
            p.1 + (q.1 - p.1) * (t - p.0) / (q.0 - p.0)
        } else if t <= p.0 {
            p.1
        } else {
            q.1
        };
        if (v - at).abs() <= tol {
            near += 1;
        }
    }
    near as f64 / a.len().max(1) as f64
}

/// A series lies on another where they are within a few pixels on this share of its
/// samples or more (then the other is hidden where they meet: a method that follows θ_d
/// until a fault, say); on [`ALL_ALONG`] of them, it lies on it all along.
const PARTLY: f64 = 0.2;
const ALL_ALONG: f64 = 0.9;

/// Which earlier series each series lies on, at a tolerance of `tol` (a few pixels), and
/// on what share of its samples (at least [`PARTLY`]). A later series covers an earlier one
/// it lies on, so it is drawn dashed; a band lies on another as the lesser of its edges.
fn overlaps(series: &[Series], tol: f64) -> Vec<Vec<(usize, f64)>> {
    let on = |a: &Series, b: &Series| -> f64 {
        match (&a.lower, &b.lower) {
            (None, None) => share_on(&a.points, &b.points, tol),
            (Some(al), Some(bl)) => share_on(&a.points, &b.points, tol).min(share_on(al, bl, tol)),
            _ => 0.0,
        }
    };
    (0..series.len())
        .map(|i| {
            (0..i)
                .map(|j| (j, on(&series[i], &series[j])))
                .filter(|&(_, share)| share >= PARTLY)
                .collect()
        })
        .collect()
}

/// The extent of a panel's data (its window's, when it has one): x0, x1, y0, y1.
fn bounds(p: &Panel) -> Option<(f64, f64, f64, f64)> {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    let (a, b) = p.window;
    let inside = |x: f64| x >= a && x <= b;
    for s in &p.series {
        for &(x, y) in s.points.iter().chain(s.lower.iter().flatten()) {
            if x.is_finite() && y.is_finite() && inside(x) {
                x0 = x0.min(x);
                x1 = x1.max(x);
                y0 = y0.min(y);
                y1 = y1.max(y);
            }
        }
    }
    if x0 > x1 {
        return None;
    }
    Some((a.min(x0), b.max(x1), y0, y1))
}

/// Dashes every series that lies on an earlier one (all along or in part), with a longer gap the more traces lie
/// beneath it (so that each shows in the gaps of those above), and says so in its legend
/// entry. The tolerance is 1/200 of the panel's height: three pixels in a 600-pixel plot.
fn mark_overlaps(p: &mut Panel) {
    let Some((_, _, y0, y1)) = bounds(p) else {
        return;
    };
    let tol = (y1 - y0) / 200.0;
    let under = overlaps(&p.series, tol);
    let names: Vec<String> = p.series.iter().map(|s| s.name.clone()).collect();
    for (s, below) in p.series.iter_mut().zip(under) {
        if below.is_empty() {
            continue;
        }
        let layer = u32::try_from(below.len()).unwrap_or(u32::MAX).min(4);
        s.stroke = Stroke::Dashed {
            on: 10,
            off: 10 * layer,
        };
        let named = |all: bool| -> Vec<&str> {
            below
                .iter()
                .filter(|b| (b.1 >= ALL_ALONG) == all)
                .map(|b| names[b.0].as_str())
                .filter(|n| !n.is_empty())
                .collect()
        };
        let mut says = Vec::new();
        for (all, verb) in [(true, "lies on"), (false, "partly on")] {
            let others = named(all);
            if !others.is_empty() {
                says.push(format!("{verb} {}", others.join(" and ")));
            }
        }
        if !s.name.is_empty() && !says.is_empty() {
            s.name = format!("{}, dashed: {}", s.name, says.join(", "));
        }
    }
}

/// Where each legend entry goes: (column, row) in columns as wide as the widest entry, as
/// many as fit in `width` (at least one), filled top to bottom so that a method's entries
/// (which follow each other) stand in one column.
fn legend_layout(widths: &[u32], width: u32) -> (u32, Vec<(u32, u32)>) {
    let column = widths.iter().copied().max().unwrap_or(1).max(1);
    let n = u32::try_from(widths.len()).unwrap_or(u32::MAX);
    let columns = (width / column).clamp(1, n.max(1));
    let rows = n.div_ceil(columns);
    let cells = (0..n).map(|i| (i / rows, i % rows)).collect();
    (column, cells)
}

/// The rows the labels above a plot go in: each label (its x and width) on the first row
/// where it clears the labels already there.
fn label_rows(labels: &[(i32, u32)]) -> Vec<usize> {
    let mut rows: Vec<Vec<(i32, i32)>> = Vec::new();
    labels
        .iter()
        .map(|&(x, w)| {
            let end = x + i32::try_from(w).unwrap_or(i32::MAX / 2) + 8;
            let row = rows
                .iter()
                .position(|r| r.iter().all(|&(a, b)| end <= a || x >= b))
                .unwrap_or(rows.len());
            if row == rows.len() {
                rows.push(Vec::new());
            }
            rows[row].push((x, end));
            row
        })
        .collect()
}

/// The figures of a recording. `s` is the scenario it was made with, when it says.
fn figures(rec: &Recorded, s: Option<&Scenario>) -> Vec<Figure> {
    let runs = &rec.runs;
    let several = runs.len() > 1;
    let named = |label: &str, method: &str| {
        if several {
            format!("{label} ({method})")
        } else {
            label.to_string()
        }
    };
    let color = |i: usize| COLORS[i % COLORS.len()];
    let end = runs
        .iter()
        .filter_map(|(_, v)| v.last().map(|r| r.t))
        .fold(0.0, f64::max);
    let start = runs
        .iter()
        .filter_map(|(_, v)| v.first().map(|r| r.t))
        .fold(end, f64::min);
    let series = |i: usize, label: &str, f: &dyn Fn(&StateRecord) -> f64, c, stroke| {
        let (method, states) = &runs[i];
        Series {
            run: Some(i),
            ..Series::line(
                named(label, method),
                states.iter().map(|r| (r.t, f(r))).collect(),
                c,
                stroke,
            )
        }
    };

    // Faults, earliest first: the shaded stretch, the name above the plot, the legend's
    // words.
    let mut faults: Vec<Span> = Vec::new();
    for (method, states) in runs {
        for f in fault_spans(states) {
            let name = named(&short_fault_name(f.bits), method);
            let verb = if f.bits & LATCHED != 0 {
                "latched"
            } else {
                "set"
            };
            let until = if f.to_end {
                String::new()
            } else {
                format!(" until {:.3} s", f.to)
            };
            faults.push(Span {
                from: f.from,
                to: f.to,
                kind: SpanKind::Fault {
                    legend: format!("{name}: {verb} at {:.3} s{until}", f.from),
                    label: name,
                },
            });
        }
    }
    faults.sort_by(|a, b| a.from.total_cmp(&b.from));

    // The zoomed window: around the first fault, which is what a faulted run is read for;
    // otherwise the start of the cruise. Two electrical periods at the cruise velocity
    // (20 ms at least) show the waveform.
    // (An electrical period of 0: none known, a move without a cruise velocity.)
    let electrical = s
        .map(|s| std::f64::consts::TAU / (s.motor.n_r() * s.trajectory.cruise_velocity_rad_s.abs()))
        .filter(|e| e.is_finite())
        .unwrap_or(0.0);
    let zoom_len = (2.0 * electrical).max(0.02).min((end - start).max(1e-3));
    // A commanded run (a program, a served stack) has no cruise: the waveform is shown
    // where its first move starts (a served stack's recording starts where it attached).
    let first_move = rec
        .acks
        .iter()
        .flat_map(|(_, acks)| acks.iter())
        .find(|a| {
            a.kind == stepdrive_shared::axis::RequestKind::Move.name()
                && a.refusal == stepdrive_shared::axis::Refusal::None.name()
        })
        .map(|a| a.t);
    let (cruise_start, cruise_why) = match (s, first_move) {
        (Some(s), _) if s.runs_profile() => (s.metrics.cruise_start_s, "in cruise"),
        (_, Some(t)) => (t, "at the first move"),
        (Some(s), None) => (s.metrics.cruise_start_s, "in cruise"),
        (None, None) => (start, "at the start"),
    };
    let cruise_start = cruise_start.clamp(start, (end - zoom_len).max(start));
    let (zoom, zoom_why) = match faults.first() {
        Some(f) => {
            let from = (f.from - 0.25 * zoom_len).clamp(start, (end - zoom_len).max(start));
            ((from, from + zoom_len), "around the fault")
        }
        None => ((cruise_start, cruise_start + zoom_len), cruise_why),
    };
    let in_zoom = |t: f64| t >= zoom.0 && t <= zoom.1;
    let zoomed = |mut series: Series| {
        series.points.retain(|p| in_zoom(p.0));
        series
    };
    // Windows of the envelope: two electrical periods, and at least 1/300 of the run.
    let envelope_window = (2.0 * electrical).max((end - start) / 300.0);
    let band = |i: usize, label: &str, f: &dyn Fn(&StateRecord) -> [f64; 2]| {
        let (method, states) = &runs[i];
        let both: Vec<(f64, f64)> = states.iter().flat_map(|r| f(r).map(|v| (r.t, v))).collect();
        let (lower, upper) = envelope(&both, envelope_window);
        Series {
            name: named(label, method),
            points: upper,
            lower: Some(lower),
            color: color(i),
            stroke: Stroke::Solid,
            run: Some(i),
        }
    };

    let mut spans: Vec<Span> = s
        .map(|s| cruise_windows(s, end))
        .unwrap_or_default()
        .into_iter()
        .map(|(from, to)| Span {
            from,
            to,
            kind: SpanKind::Cruise,
        })
        .collect();
    spans.extend(faults.iter().cloned());
    let zoom_span = Span {
        from: zoom.0,
        to: zoom.1,
        kind: SpanKind::Zoom,
    };

    let panel = |y_label: &str, series: Vec<Series>| Panel {
        title: None,
        y_label: y_label.to_string(),
        series,
        window: (start, end),
        zoomed: false,
        log: false,
    };
    let figure = |file, title: &str, panels: Vec<Panel>, spans: Vec<Span>| {
        let mut f = Figure {
            file,
            title: title.to_string(),
            panels,
            spans,
        };
        for p in &mut f.panels {
            mark_overlaps(p);
        }
        f
    };
    // A full run beside its zoomed window.
    let pair = |full: Panel, zoom_series: Vec<Series>, what: &str| {
        let mut spans = spans.clone();
        spans.push(zoom_span.clone());
        let full = Panel {
            title: Some(format!(
                "full run: {what} envelope (least to greatest over each {:.0} ms)",
                envelope_window * 1e3
            )),
            ..full
        };
        let zoomed_panel = Panel {
            title: Some(format!("zoom {zoom_why}: {:.3}–{:.3} s", zoom.0, zoom.1)),
            window: zoom,
            zoomed: true,
            ..panel(&full.y_label, zoom_series)
        };
        (vec![full, zoomed_panel], spans)
    };

    // Position: θ_d solid black beneath; the methods' θ lie on it at this scale, and say
    // so (their difference is the error figure).
    let mut position = vec![series(0, "θ_d", &|r| r.theta_d, BLACK, Stroke::Solid)];
    position[0].name = "θ_d (desired)".into();
    position[0].run = None;
    for i in 0..runs.len() {
        position.push(series(i, "θ", &|r| r.theta, color(i), Stroke::Solid));
    }

    let mut error: Vec<Series> = (0..runs.len())
        .map(|i| series(i, "e = θ_d − θ", &|r| r.error, color(i), Stroke::Solid))
        .collect();
    let mut log_error: Vec<Series> = (0..runs.len())
        .map(|i| {
            series(
                i,
                "|e|",
                &|r| r.error.abs().max(1e-15).log10(),
                color(i),
                Stroke::Solid,
            )
        })
        .collect();
    if let Some(b) = s.map(|s| s.eq7_bound_rad()) {
        let span = |v: f64| vec![(0.0, v), (end, v)];
        let dashed = Stroke::Dashed { on: 6, off: 4 };
        error.push(Series::line(
            "±eq. (7) bound".into(),
            span(b),
            BOUND,
            dashed,
        ));
        error.push(Series::line(String::new(), span(-b), BOUND, dashed));
        log_error.push(Series::line(
            "eq. (7) bound".into(),
            span(b.log10()),
            BOUND,
            dashed,
        ));
    }

    // Phase currents: the envelope of both phases over the run, the waveforms zoomed.
    let current_bands: Vec<Series> = (0..runs.len())
        .map(|i| band(i, "i_a, i_b envelope", &|r| [r.i_a, r.i_b]))
        .collect();
    let current_lines: Vec<Series> = (0..runs.len())
        .flat_map(|i| {
            [
                zoomed(series(i, "i_a", &|r| r.i_a, color(i), Stroke::Solid)),
                zoomed(series(i, "i_b", &|r| r.i_b, light(color(i)), SECOND)),
            ]
        })
        .collect();
    let (current_panels, current_spans) = pair(
        panel("current [A]", current_bands),
        current_lines,
        "i_a and i_b",
    );

    // 20 ms of cruise (or two electrical periods), where the currents and their references
    // (from the commands, when the recording has them) can be told apart.
    let cruise_zoom = (cruise_start, cruise_start + zoom_len);
    let mut currents_zoom = Vec::new();
    for (i, (method, states)) in runs.iter().enumerate() {
        let inside = |t: f64| t >= cruise_zoom.0 && t <= cruise_zoom.1;
        currents_zoom.push(Series {
            run: Some(i),
            ..Series::line(
                named("i_a", method),
                states
                    .iter()
                    .filter(|r| inside(r.t))
                    .map(|r| (r.t, r.i_a))
                    .collect(),
                color(i),
                Stroke::Solid,
            )
        });
        if let Some((_, commands)) = rec.commands.iter().find(|(m, _)| m == method) {
            currents_zoom.push(Series {
                run: Some(i),
                ..Series::line(
                    named("i_a reference", method),
                    commands
                        .iter()
                        .filter(|c| inside(c.t_ref))
                        .map(|c| (c.t_ref, c.i_a_ref))
                        .collect(),
                    light(color(i)),
                    SECOND,
                )
            });
        }
    }

    let dq: Vec<Series> = (0..runs.len())
        .flat_map(|i| {
            [
                series(i, "i_d", &|r| r.i_d, light(color(i)), SECOND),
                series(i, "i_q", &|r| r.i_q, color(i), Stroke::Solid),
            ]
        })
        .collect();

    // Phase voltages against the bus, as the currents.
    let bus = |sign: f64, name: &str| {
        let mut s = series(0, "", &|r| sign * r.bus, BLACK, SECOND);
        s.name = name.to_string();
        s.run = None;
        s
    };
    let mut volt_bands: Vec<Series> = (0..runs.len())
        .map(|i| band(i, "v_a, v_b envelope", &|r| [r.v_a, r.v_b]))
        .collect();
    volt_bands.extend([bus(1.0, "±bus"), bus(-1.0, "")]);
    let mut volt_lines: Vec<Series> = (0..runs.len())
        .flat_map(|i| {
            [
                zoomed(series(i, "v_a", &|r| r.v_a, color(i), Stroke::Solid)),
                zoomed(series(i, "v_b", &|r| r.v_b, light(color(i)), SECOND)),
            ]
        })
        .collect();
    volt_lines.extend([zoomed(bus(1.0, "±bus")), zoomed(bus(-1.0, ""))]);
    let (volt_panels, volt_spans) =
        pair(panel("voltage [V]", volt_bands), volt_lines, "v_a and v_b");

    let torque: Vec<Series> = (0..runs.len())
        .map(|i| series(i, "τ = K_m i_q", &|r| r.torque, color(i), Stroke::Solid))
        .collect();

    let cruise_figure = Panel {
        window: cruise_zoom,
        zoomed: true,
        ..panel("current [A]", currents_zoom)
    };
    vec![
        figure(
            "position",
            "Desired and actual position (their difference: the error figure)",
            vec![panel("θ [rad]", position)],
            spans.clone(),
        ),
        figure(
            "error",
            "Tracking error and the eq. (7) bound",
            vec![panel("e [rad]", error)],
            spans.clone(),
        ),
        figure(
            "error_log",
            "Tracking error, log scale",
            vec![Panel {
                log: true,
                ..panel("|e| [rad]", log_error)
            }],
            spans.clone(),
        ),
        figure("currents", "Phase currents", current_panels, current_spans),
        figure(
            "currents_cruise",
            &format!(
                "Phase a current and its reference, {:.3}–{:.3} s",
                cruise_zoom.0, cruise_zoom.1
            ),
            vec![cruise_figure],
            spans.clone(),
        ),
        figure(
            "dq_currents",
            "i_d and i_q",
            vec![panel("current [A]", dq)],
            spans.clone(),
        ),
        figure(
            "voltages",
            "Phase voltages and the bus",
            volt_panels,
            volt_spans,
        ),
        figure(
            "torque",
            "Motor torque",
            vec![panel("τ [N·m]", torque)],
            spans,
        ),
    ]
}

/// The shade of an axis state on a program's figures: greys while the power is off, amber
/// in a quick stop, red in a fault; Operation enabled is not shaded.
fn axis_fill(state: AxisState) -> RGBColor {
    match state {
        AxisState::NotReadyToSwitchOn | AxisState::SwitchOnDisabled => RGBColor(150, 150, 150),
        AxisState::ReadyToSwitchOn | AxisState::SwitchedOn => RGBColor(120, 160, 210),
        AxisState::OperationEnabled => WHITE,
        AxisState::QuickStopActive => RGBColor(240, 170, 40),
        AxisState::FaultReactionActive | AxisState::Fault => FAULT,
    }
}

/// The stretches a run's axis spent in each state but Operation enabled, from its statuses.
fn axis_spans(statuses: &[StatusRecord]) -> Vec<Span> {
    let mut spans: Vec<Span> = Vec::new();
    for (i, r) in statuses.iter().enumerate() {
        let Some(state) = AxisState::from_u32(r.state_code) else {
            continue;
        };
        let to = statuses.get(i + 1).map_or(r.t, |n| n.t);
        match spans.last_mut() {
            Some(last) if last.kind == SpanKind::Axis(state) && last.to >= r.t => last.to = to,
            _ => spans.push(Span {
                from: r.t,
                to,
                kind: SpanKind::Axis(state),
            }),
        }
    }
    spans.retain(|s| s.kind != SpanKind::Axis(AxisState::OperationEnabled));
    spans
}

/// A program's figures (a run whose position loop published axis statuses): the setpoint
/// against the motor, the following error, ω_d and α_d of the trajectory generator, the
/// axis state shaded beneath. None for a run without statuses (the scenario's profile).
fn program_figures(rec: &Recorded) -> Vec<Figure> {
    let runs: Vec<(&str, &[StatusRecord])> = rec
        .statuses
        .iter()
        .filter(|(_, v)| !v.is_empty())
        .map(|(m, v)| (m.as_str(), v.as_slice()))
        .collect();
    let Some(&(_, first)) = runs.first() else {
        return Vec::new();
    };
    let several = runs.len() > 1;
    let named = |label: &str, method: &str| match several {
        true => format!("{label} ({method})"),
        false => label.to_string(),
    };
    let (start, end) = runs.iter().fold((f64::MAX, f64::MIN), |(a, b), (_, v)| {
        (
            a.min(v.first().map_or(a, |r| r.t)),
            b.max(v.last().map_or(b, |r| r.t)),
        )
    });
    let line = |i: usize, label: &str, f: &dyn Fn(&StatusRecord) -> f64, color, stroke| {
        let (method, statuses) = runs[i];
        Series {
            run: Some(i),
            ..Series::line(
                named(label, method),
                statuses.iter().map(|r| (r.t, f(r))).collect(),
                color,
                stroke,
            )
        }
    };
    let panel = |y_label: &str, series: Vec<Series>| Panel {
        title: None,
        y_label: y_label.to_string(),
        series,
        window: (start, end),
        zoomed: false,
        log: false,
    };
    // The first run's axis states (several runs of one program share them but for faults,
    // which each run's fault spans name).
    let mut spans = axis_spans(first);
    for (method, states) in &rec.runs {
        for f in fault_spans(states) {
            let name = named(&short_fault_name(f.bits), method);
            spans.push(Span {
                from: f.from,
                to: f.to,
                kind: SpanKind::Fault {
                    legend: format!("{name}: set at {:.3} s", f.from),
                    label: name,
                },
            });
        }
    }
    let color = |i: usize| COLORS[i % COLORS.len()];
    let per_run = |label: &str, f: &dyn Fn(&StatusRecord) -> f64, stroke| -> Vec<Series> {
        (0..runs.len())
            .map(|i| line(i, label, f, color(i), stroke))
            .collect()
    };
    let mut position = per_run("θ_d (setpoint)", &|r| r.theta_d, Stroke::Solid);
    position.extend(
        (0..runs.len()).map(|i| line(i, "θ (measured)", &|r| r.theta, light(color(i)), SECOND)),
    );
    let mut velocity = per_run("ω_d (setpoint)", &|r| r.omega_d, Stroke::Solid);
    velocity.extend(
        (0..runs.len()).map(|i| line(i, "ω (measured)", &|r| r.omega, light(color(i)), SECOND)),
    );
    let figure = |file, title: &str, panel: Panel| {
        let mut f = Figure {
            file,
            title: title.to_string(),
            panels: vec![panel],
            spans: spans.clone(),
        };
        for p in &mut f.panels {
            mark_overlaps(p);
        }
        f
    };
    vec![
        figure(
            "program_position",
            "Program: setpoint and measured position, the axis state shaded",
            panel("θ [rad]", position),
        ),
        figure(
            "program_following_error",
            "Program: following error θ_d − θ at each position-loop tick",
            panel(
                "θ_d − θ [rad]",
                per_run("following error", &|r| r.following_error, Stroke::Solid),
            ),
        ),
        figure(
            "program_velocity",
            "Program: the trajectory's velocity and the measured one",
            panel("ω [rad/s]", velocity),
        ),
        figure(
            "program_acceleration",
            "Program: the trajectory's acceleration (jerk-limited: ramps, no steps)",
            panel(
                "α_d [rad/s²]",
                per_run("α_d (setpoint)", &|r| r.alpha_d, Stroke::Solid),
            ),
        ),
    ]
}

/// What a legend entry's swatch shows.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Swatch {
    Line(RGBColor, Stroke),
    Band(RGBColor),
    /// A shaded stretch: its fill and its edge.
    Shade(RGBColor, RGBColor),
    Fault,
}

/// The legend of a figure: its series (once each, by name), then its shaded spans.
fn legend(f: &Figure) -> Vec<(Swatch, String)> {
    let mut out: Vec<(Swatch, String)> = Vec::new();
    let mut add = |swatch, text: String| {
        if !text.is_empty() && !out.iter().any(|(_, t)| *t == text) {
            out.push((swatch, text));
        }
    };
    // Each run's series together, then the references (θ_d, the bound, the bus).
    let mut runs: Vec<Option<usize>> = f
        .panels
        .iter()
        .flat_map(|p| p.series.iter().map(|s| s.run))
        .collect();
    runs.sort_by_key(|r| r.unwrap_or(usize::MAX));
    runs.dedup();
    for run in runs {
        for s in f
            .panels
            .iter()
            .flat_map(|p| &p.series)
            .filter(|s| s.run == run)
        {
            let swatch = if s.lower.is_some() {
                Swatch::Band(s.color)
            } else {
                Swatch::Line(s.color, s.stroke)
            };
            add(swatch, s.name.clone());
        }
    }
    // What the panels show of time: a fault outside it is named all the same.
    let shown = f
        .panels
        .iter()
        .map(|p| p.window)
        .reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)));
    // Cruise windows and the zoomed stretch are shaded on whole-run panels only.
    let whole = f.panels.iter().any(|p| !p.zoomed);
    for sp in &f.spans {
        match &sp.kind {
            SpanKind::Cruise | SpanKind::Zoom if !whole => {}
            SpanKind::Cruise => add(
                Swatch::Shade(CRUISE_FILL, CRUISE_EDGE),
                "cruise window of the metrics (every pass)".into(),
            ),
            SpanKind::Zoom => add(
                Swatch::Shade(ZOOM_FILL, ZOOM_FILL),
                format!("zoomed at right: {:.3}–{:.3} s", sp.from, sp.to),
            ),
            SpanKind::Axis(state) => {
                let fill = axis_fill(*state);
                add(Swatch::Shade(fill, fill), format!("axis {}", state.name()));
            }
            SpanKind::Fault { legend, .. } => {
                let outside = match shown {
                    Some((_, b)) if sp.from > b => " (after this window)",
                    Some((a, _)) if sp.to < a => " (before this window)",
                    _ => "",
                };
                add(Swatch::Fault, format!("{legend}{outside}"));
            }
        }
    }
    out
}

type Drawn = Result<(), String>;

fn err(e: impl std::fmt::Display) -> String {
    e.to_string()
}

/// A line's points on a chart: finite ones, decimated to what a plot can show.
fn drawable(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    decimate(
        points
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect(),
        2000,
    )
}

/// Where to cut a line drawn through the pixels `px` so that no piece turns back by more
/// than 120°: (first, last) indices of each piece, a piece ending where the next begins.
/// plotters's bitmap backend draws a wide line as a polygon whose corner at a turn is where
/// the offsets of the two segments cross; at a near-reversal that is far off, a spike out
/// to the image's edge (|e| on a log axis plunges to 1e-15 and back within a pixel). A
/// piece that ends at the turn has no such corner.
fn pieces(px: &[(i32, i32)]) -> Vec<(usize, usize)> {
    if px.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::new();
    let (mut start, mut last) = (0, 0);
    let mut heading: Option<(f64, f64)> = None;
    for (i, p) in px.iter().enumerate().skip(1) {
        let d = (f64::from(p.0 - px[last].0), f64::from(p.1 - px[last].1));
        if d == (0.0, 0.0) {
            continue;
        }
        if let Some(h) = heading {
            let cos = (h.0 * d.0 + h.1 * d.1) / (h.0.hypot(h.1) * d.0.hypot(d.1));
            if cos < -0.5 {
                out.push((start, last));
                start = last;
            }
        }
        heading = Some(d);
        last = i;
    }
    out.push((start, px.len() - 1));
    out
}

/// A line of a chart, in pieces that never turn back sharply (see [`pieces`]).
fn draw_line<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<Axis, Axis>>,
    points: &[(f64, f64)],
    stroke: Stroke,
    style: ShapeStyle,
) -> Drawn
where
    DB::ErrorType: 'static,
{
    let px: Vec<(i32, i32)> = points.iter().map(|p| chart.backend_coord(p)).collect();
    for (a, b) in pieces(&px) {
        let piece = points[a..=b].iter().copied();
        match stroke {
            Stroke::Solid => chart.draw_series(LineSeries::new(piece, style)),
            Stroke::Dashed { on, off } => {
                chart.draw_series(DashedLineSeries::new(piece, on, off, style))
            }
        }
        .map_err(err)?;
    }
    Ok(())
}

/// The height of the strip above each plot where fault names go, per row.
const STRIP_ROW: u32 = 18;

fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    p: &Panel,
    spans: &[Span],
    strip_rows: u32,
) -> Drawn
where
    DB::ErrorType: 'static,
{
    // A window the recording has no sample in (a reader that missed that stretch) is drawn
    // empty and says so, rather than costing the other figures.
    let empty = bounds(p).is_none();
    let Some((x0, x1, y0, y1)) = bounds(p).or_else(|| {
        let (a, b) = p.window;
        (a.is_finite() && b.is_finite() && a < b).then_some((a, b, -1.0, 1.0))
    }) else {
        return Err("no finite point".into());
    };
    // 5 % of room above and below; a constant gets ±5 % of itself, a constant 0 ±1.
    let pad = if y1 - y0 > 1e-12 * y0.abs().max(y1.abs()) {
        (y1 - y0) * 0.05
    } else if y0 != 0.0 {
        y0.abs() * 0.05
    } else {
        1.0
    };
    let (y0, y1) = (y0 - pad, y1 + pad);
    let x1 = if x1 > x0 { x1 } else { x0 + 1.0 };
    let (width, _) = area.dim_in_pixel();
    // About one label per 110 pixels of width; up to 8 intervals on y (~70 pixels each).
    let xt = linear_ticks(x0, x1, (width / 110).max(3) as usize);
    let yt = if p.log {
        decade_ticks(y0, y1, 8)
    } else {
        linear_ticks(y0, y1, 8)
    };
    // The panel's title above the strip for fault names (a caption of the chart builder
    // would sit between the strip and the plot).
    let titled;
    let area = match &p.title {
        Some(title) => {
            titled = area.titled(title, (FAMILY, 15)).map_err(err)?;
            &titled
        }
        None => area,
    };
    let mut chart = ChartBuilder::on(area)
        .margin(10)
        // Room for a tick label centred on the right end.
        .margin_right(26)
        // The strip above the plot where fault names go.
        .margin_top(6 + STRIP_ROW * strip_rows)
        .x_label_area_size(42)
        .y_label_area_size(78)
        .build_cartesian_2d(Axis::new(x0, x1, xt), Axis::new(y0, y1, yt))
        .map_err(err)?;
    // (from, to) within the plot, the kind, and whether it begins on it.
    let visible: Vec<(f64, f64, &SpanKind, bool)> = spans
        .iter()
        .filter(|s| match s.kind {
            // The zoomed panel shows one stretch: only a fault is marked on it.
            SpanKind::Cruise | SpanKind::Zoom => !p.zoomed,
            SpanKind::Fault { .. } | SpanKind::Axis(_) => true,
        })
        .filter(|s| s.from <= x1 && s.to >= x0)
        .map(|s| (s.from.max(x0), s.to.min(x1), &s.kind, s.from >= x0))
        .collect();
    // Shading beneath the grid and the data.
    for &(a, b, kind, _) in &visible {
        let fill = match kind {
            SpanKind::Cruise => CRUISE_FILL.mix(0.22),
            SpanKind::Zoom => ZOOM_FILL.mix(0.22),
            SpanKind::Fault { .. } => FAULT.mix(0.10),
            SpanKind::Axis(state) => axis_fill(*state).mix(0.30),
        };
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(a, y0), (b, y1)],
                fill.filled(),
            )))
            .map_err(err)?;
    }
    chart
        .configure_mesh()
        .x_desc("t [s]")
        .y_desc(p.y_label.as_str())
        .label_style((FAMILY, 14))
        .axis_desc_style((FAMILY, 14))
        .bold_line_style(RGBColor(205, 205, 205))
        .light_line_style(RGBColor(238, 238, 238))
        .draw()
        .map_err(err)?;
    if empty {
        chart
            .draw_series(std::iter::once(Text::new(
                "no sample recorded in this window",
                (0.5 * (x0 + x1), 0.0),
                TextStyle::from((FAMILY, 15).into_font()).pos(Pos::new(HPos::Center, VPos::Center)),
            )))
            .map_err(err)?;
    }
    // A cruise window's edges over the grid, so that an edge on a grid line still shows.
    for &(a, b, kind, _) in &visible {
        if *kind == SpanKind::Cruise {
            for x in [a, b] {
                chart
                    .draw_series(LineSeries::new(
                        [(x, y0), (x, y1)],
                        CRUISE_EDGE.stroke_width(1),
                    ))
                    .map_err(err)?;
            }
        }
    }
    for s in &p.series {
        let style = s.color.stroke_width(2);
        if let Some(lower) = &s.lower {
            let (up, low) = (drawable(&s.points), drawable(lower));
            let outline: Vec<(f64, f64)> = up.iter().chain(low.iter().rev()).copied().collect();
            chart
                .draw_series(std::iter::once(Polygon::new(
                    outline,
                    s.color.mix(0.12).filled(),
                )))
                .map_err(err)?;
            for edge in [up, low] {
                draw_line(&mut chart, &edge, s.stroke, style)?;
            }
            continue;
        }
        draw_line(&mut chart, &drawable(&s.points), s.stroke, style)?;
    }
    // Faults over the data: a line at the sample the bits were set on, the name above the
    // plot (in the strip kept for it, never over the data); a fault set before a zoomed
    // window is named at its left end.
    let font = (FAMILY, 13).into_font().color(&FAULT);
    let base = area.get_base_pixel();
    let mut labels = Vec::new();
    for &(a, _, kind, begins) in &visible {
        let SpanKind::Fault { label, .. } = kind else {
            continue;
        };
        if begins {
            chart
                .draw_series(LineSeries::new([(a, y0), (a, y1)], FAULT.stroke_width(2)))
                .map_err(err)?;
        }
        let at = chart.backend_coord(&(a, y1));
        let w = area.estimate_text_size(label, &font).map_or(0, |s| s.0);
        let x = at.0 - base.0;
        // Right of the line, or left of it where the plot ends.
        let right_end = chart.backend_coord(&(x1, y1)).0 - base.0;
        let left = x + 4 + i32::try_from(w).unwrap_or(0) > right_end;
        let x = if left { x - 4 - w as i32 } else { x + 4 };
        labels.push((x, w, label, at.1 - base.1));
    }
    let rows = label_rows(&labels.iter().map(|l| (l.0, l.1)).collect::<Vec<_>>());
    for ((x, _, label, top), row) in labels.into_iter().zip(rows) {
        // More crowded than the strip: the last row holds the rest (over the title else).
        let row = row.min(strip_rows.saturating_sub(1) as usize);
        let y = top - 3 - (STRIP_ROW as i32) * row as i32;
        let style = font.pos(Pos::new(HPos::Left, VPos::Bottom));
        area.draw_text(label, &style, (x, y)).map_err(err)?;
    }
    Ok(())
}

/// A swatch in the legend, 26 × 12 pixels from (x, y) (its left end, middle).
fn draw_swatch<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    swatch: Swatch,
    (x, y): (i32, i32),
) -> Drawn {
    // The pieces of a line at height y: one, or its dashes (shortened to fit the swatch).
    let line = |c: RGBColor, stroke: Stroke, y: i32| -> Vec<PathElement<(i32, i32)>> {
        let style = c.stroke_width(2);
        match stroke {
            Stroke::Solid => vec![PathElement::new(vec![(x, y), (x + 26, y)], style)],
            Stroke::Dashed { on, off } => {
                let (on, off) = (on.min(10) as i32, (off.min(10) as i32).max(3));
                (0..)
                    .map(|k| x + k * (on + off))
                    .take_while(|a| *a < x + 26)
                    .map(|a| PathElement::new(vec![(a, y), ((a + on).min(x + 26), y)], style))
                    .collect()
            }
        }
    };
    match swatch {
        Swatch::Line(c, stroke) => {
            for e in line(c, stroke, y) {
                area.draw(&e).map_err(err)?;
            }
        }
        Swatch::Band(c) => {
            area.draw(&Rectangle::new(
                [(x, y - 6), (x + 26, y + 6)],
                c.mix(0.12).filled(),
            ))
            .map_err(err)?;
            for e in line(c, Stroke::Solid, y - 6)
                .into_iter()
                .chain(line(c, Stroke::Solid, y + 6))
            {
                area.draw(&e).map_err(err)?;
            }
        }
        Swatch::Shade(c, edge) => {
            area.draw(&Rectangle::new(
                [(x, y - 6), (x + 26, y + 6)],
                c.mix(0.35).filled(),
            ))
            .map_err(err)?;
            area.draw(&Rectangle::new(
                [(x, y - 6), (x + 26, y + 6)],
                edge.stroke_width(1),
            ))
            .map_err(err)?;
        }
        Swatch::Fault => {
            area.draw(&Rectangle::new(
                [(x, y - 6), (x + 26, y + 6)],
                FAULT.mix(0.10).filled(),
            ))
            .map_err(err)?;
            area.draw(&PathElement::new(
                vec![(x, y - 6), (x, y + 6)],
                FAULT.stroke_width(2),
            ))
            .map_err(err)?;
        }
    }
    Ok(())
}

/// Pixels of a legend row, of its swatch with the gap after it, and of space after a text.
const LEGEND_ROW: u32 = 20;
const SWATCH: u32 = 34;
const AFTER_TEXT: u32 = 24;

fn draw_figure<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, f: &Figure) -> Drawn
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(err)?;
    let (w, h) = root.dim_in_pixel();
    let font = TextStyle::from((FAMILY, 14).into_font());
    let entries = legend(f);
    let widths: Vec<u32> = entries
        .iter()
        .map(|(_, text)| {
            let text_w = root
                .estimate_text_size(text, &font)
                .map_or(8 * text.len() as u32, |s| s.0);
            SWATCH + text_w + AFTER_TEXT
        })
        .collect();
    let margin = 16;
    let (column, cells) = legend_layout(&widths, w.saturating_sub(2 * margin));
    let rows = cells.iter().map(|c| c.1 + 1).max().unwrap_or(0);
    let legend_h = rows * LEGEND_ROW + 10;
    let (body, legend_area) = root.split_vertically(h.saturating_sub(legend_h));
    let body = body.titled(&f.title, (FAMILY, 20)).map_err(err)?;
    // Rows of fault names above the plots: one a fault (up to three), so that names that
    // would overlap stand one above the other.
    let faults = f
        .spans
        .iter()
        .filter(|s| matches!(s.kind, SpanKind::Fault { .. }))
        .count();
    let strip_rows = u32::try_from(faults).unwrap_or(1).clamp(1, 3);
    let areas = if f.panels.len() > 1 {
        let (full, zoom) = body.split_horizontally(w * 62 / 100);
        vec![full, zoom]
    } else {
        vec![body]
    };
    for (area, p) in areas.iter().zip(&f.panels) {
        draw_panel(area, p, &f.spans, strip_rows)?;
    }
    let text_style = font.pos(Pos::new(HPos::Left, VPos::Center));
    for ((swatch, text), (col, row)) in entries.iter().zip(cells) {
        let x = (margin + col * column) as i32;
        let y = (row * LEGEND_ROW + LEGEND_ROW / 2 + 2) as i32;
        draw_swatch(&legend_area, *swatch, (x, y))?;
        legend_area
            .draw_text(text, &text_style, (x + SWATCH as i32, y))
            .map_err(err)?;
    }
    root.present().map_err(err)
}

/// PNG size, pixels.
pub const PNG_SIZE: (u32, u32) = (1200, 700);

/// Draws every figure of the recording at `path` into `dir` as `<name>.svg` and
/// `<name>.png`; returns the files written.
pub fn plot_file(path: &Path, dir: &Path) -> Result<Vec<PathBuf>, PlotError> {
    let rec = Recorded::read(path)?;
    if rec.runs.iter().all(|(_, v)| v.is_empty()) {
        return Err(PlotError::Empty(path.to_path_buf()));
    }
    std::fs::create_dir_all(dir).map_err(|source| PlotError::Dir {
        path: dir.to_path_buf(),
        source,
    })?;
    register_font();
    let scenario = rec.scenario();
    let mut written = Vec::new();
    // A multi-axis recording: every axis's figures, axis n's files named `<figure>-axis<n>`
    // and every title naming its axis.
    let several = !rec.axes.is_empty();
    let axes = std::iter::once((0, &rec)).chain(rec.axes.iter().map(|(n, r)| (*n, r)));
    let mut all = Vec::new();
    for (n, axis) in axes {
        let own = scenario
            .as_ref()
            .map(|s| s.for_axis(n as usize).unwrap_or(s));
        let mut figs = figures(axis, own);
        figs.extend(program_figures(axis));
        for mut f in figs {
            let file = match n {
                0 => f.file.to_string(),
                n => format!("{}-axis{n}", f.file),
            };
            if several {
                let name = scenario
                    .as_ref()
                    .map_or_else(String::new, |s| format!(" ({})", s.axis_name(n as usize)));
                f.title = format!("{} — axis {n}{name}", f.title);
            }
            all.push((file, f));
        }
    }
    for (file, f) in all {
        let failed = |path: &Path| {
            let path = path.to_path_buf();
            move |message| PlotError::Draw { path, message }
        };
        let svg = dir.join(format!("{file}.svg"));
        draw_figure(SVGBackend::new(&svg, PNG_SIZE).into_drawing_area(), &f)
            .map_err(failed(&svg))?;
        let png = dir.join(format!("{file}.png"));
        draw_figure(BitMapBackend::new(&png, PNG_SIZE).into_drawing_area(), &f)
            .map_err(failed(&png))?;
        written.extend([svg, png]);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimation_keeps_the_peaks_and_time_order() {
        let pts: Vec<(f64, f64)> = (0..10_000)
            .map(|k| {
                (
                    f64::from(k),
                    if k == 4321 {
                        9.0
                    } else {
                        (f64::from(k) * 0.01).sin()
                    },
                )
            })
            .collect();
        let d = decimate(pts, 100);
        assert!(d.len() <= 200);
        assert!(d.iter().any(|p| p.1 == 9.0), "the spike survives");
        assert!(d.windows(2).all(|w| w[0].0 <= w[1].0), "in time order");
    }

    #[test]
    fn the_envelope_of_both_phases_is_their_amplitude() {
        // 100 Hz at 20 kHz, amplitude rising 0.1 → 0.5 A over 1 s.
        let amplitude = |t: f64| 0.1 + 0.4 * t;
        let w = std::f64::consts::TAU * 100.0;
        let points: Vec<(f64, f64)> = (0..=20_000)
            .flat_map(|k| {
                let t = f64::from(k) / 20_000.0;
                [
                    (t, amplitude(t) * (w * t).cos()),
                    (t, amplitude(t) * (w * t).sin()),
                ]
            })
            .collect();
        let (lower, upper) = envelope(&points, 0.02);
        assert_eq!(lower.len(), 50, "one point per 20 ms window");
        for (lo, hi) in lower.iter().zip(&upper) {
            assert_eq!(lo.0, hi.0);
            // Within the window's own rise (0.4 A/s × 20 ms) of the amplitude at its middle.
            let a = amplitude(hi.0);
            assert!((hi.1 - a).abs() <= 0.0081, "{hi:?} against {a}");
            assert!((lo.1 + a).abs() <= 0.0081, "{lo:?} against {a}");
        }
        assert!(upper.windows(2).all(|w| w[0].0 < w[1].0), "in time order");
        assert_eq!(envelope(&[], 0.02), (Vec::new(), Vec::new()));
    }

    fn labels(t: &Ticks) -> Vec<String> {
        t.major.iter().map(|v| tick_label(*v, t.format)).collect()
    }

    #[test]
    fn tick_labels_share_one_format_and_zero_is_zero() {
        // The tracking error of both methods: ±1.05e-2 (before: -1.0e-2 beside 0.010, and
        // a zero of -2.8e-17 where ticks were summed).
        let t = linear_ticks(-0.0105, 0.0105, 8);
        assert_eq!(
            labels(&t),
            ["-0.010", "-0.005", "0", "0.005", "0.010"],
            "{t:?}"
        );
        assert!(t.major.contains(&0.0));
        // Steps of 0.1 from a start that is no multiple: 0.30000000000000004 reads 0.3.
        let t = linear_ticks(-0.33, 0.71, 12);
        assert_eq!(
            labels(&t),
            ["-0.3", "-0.2", "-0.1", "0", "0.1", "0.2", "0.3", "0.4", "0.5", "0.6", "0.7"]
        );
        // The proposed method's error alone: one exponent on the whole axis.
        let t = linear_ticks(-3.2e-5, 1.1e-4, 8);
        assert_eq!(
            labels(&t),
            ["-0.2e-4", "0", "0.2e-4", "0.4e-4", "0.6e-4", "0.8e-4", "1.0e-4"]
        );
        // Time: whole seconds and halves.
        assert_eq!(
            labels(&linear_ticks(0.0, 2.5, 10)),
            ["0", "0.5", "1.0", "1.5", "2.0", "2.5"]
        );
        // A zoomed window of 20 ms.
        assert_eq!(
            labels(&linear_ticks(0.9, 0.92, 5)),
            ["0.900", "0.905", "0.910", "0.915", "0.920"]
        );
        // Light lines between the labelled ones.
        let t = linear_ticks(0.0, 1.0, 5);
        assert_eq!(t.major, [0.0, 0.2, 0.4, 0.6000000000000001, 0.8, 1.0]);
        assert_eq!(t.minor.len(), 21);
        // Large values.
        assert_eq!(
            labels(&linear_ticks(0.0, 4e5, 4)),
            ["0", "1e5", "2e5", "3e5", "4e5"]
        );
        // A log axis: decades, written as such.
        let t = decade_ticks(-15.3, -1.7, 8);
        assert_eq!(
            labels(&t),
            ["1e-14", "1e-12", "1e-10", "1e-8", "1e-6", "1e-4", "1e-2"]
        );
        assert!(t.minor.iter().all(|v| (-15.3..=-1.7).contains(v)));
        let t = decade_ticks(-6.2, -2.1, 8);
        assert_eq!(labels(&t), ["1e-6", "1e-5", "1e-4", "1e-3"]);
        assert_eq!(t.minor.len(), 4 * 9 + 1, "2…9 × each decade: {:?}", t.minor);
        // No span: one tick, no panic.
        assert_eq!(linear_ticks(1.0, 1.0, 8).major, [1.0]);
    }

    #[test]
    fn every_pass_has_its_cruise_window() {
        let mut s = Scenario::default();
        // One pass: 0.5 + 1.0 + 0.5 + 0.5 = 2.5 s; the window 0.9–1.5 s in each.
        assert_eq!(cruise_windows(&s, 2.5), [(0.9, 1.5)]);
        let w = cruise_windows(&s, 6.0);
        assert_eq!(w.len(), 3, "{w:?}");
        for (got, want) in w.iter().zip([(0.9, 1.5), (3.4, 4.0), (5.9, 6.0)]) {
            assert!(
                (got.0 - want.0).abs() < 1e-12 && (got.1 - want.1).abs() < 1e-12,
                "{w:?}"
            );
        }
        // A run that ends before the window: none.
        assert!(cruise_windows(&s, 0.5).is_empty());
        // A served stack's axis never runs the profile: none.
        let mut served = s.clone();
        served.run.until_stopped = true;
        assert!(cruise_windows(&served, 6.0).is_empty());
        // A profile of no length does not loop.
        s.trajectory = stepdrive_shared::scenario::TrajectoryParams {
            cruise_velocity_rad_s: 1.0,
            accel_s: 0.0,
            cruise_s: 0.0,
            decel_s: 0.0,
            hold_s: 0.0,
        };
        assert_eq!(cruise_windows(&s, 100.0).len(), 1);
    }

    fn state(t: f64, fault: u32) -> StateRecord {
        StateRecord {
            t,
            seq: 0,
            theta: 0.0,
            theta_d: 0.0,
            error: 0.0,
            omega: 0.0,
            omega_d: 0.0,
            i_a: 0.0,
            i_b: 0.0,
            i_d: 0.0,
            i_q: 0.0,
            v_a: 0.0,
            v_b: 0.0,
            bus: 0.0,
            torque: 0.0,
            flags: 0,
            fault,
        }
    }

    #[test]
    fn fault_spans_run_from_the_sample_that_set_the_bits() {
        use stepdrive_shared::messages::fault_bits::{COMMAND_TIMEOUT, DRIVE_SILENT};
        let states: Vec<StateRecord> = [0, 0, DRIVE_SILENT, DRIVE_SILENT, 0, COMMAND_TIMEOUT]
            .iter()
            .zip(0..)
            .map(|(f, k)| state(f64::from(k) * 0.5, *f))
            .chain([state(3.0, COMMAND_TIMEOUT)])
            .collect();
        assert_eq!(
            fault_spans(&states),
            [
                FaultSpan {
                    from: 1.0,
                    to: 2.0,
                    bits: DRIVE_SILENT,
                    to_end: false
                },
                FaultSpan {
                    from: 2.5,
                    to: 3.0,
                    bits: COMMAND_TIMEOUT,
                    to_end: true
                },
            ]
        );
        assert!(fault_spans(&[state(0.0, 0), state(1.0, 0)]).is_empty());
        assert!(fault_spans(&[]).is_empty());
        // Latched on the last sample: a span of no length, still marked.
        let last = fault_spans(&[state(0.0, 0), state(1.0, COMMAND_TIMEOUT)]);
        assert_eq!((last[0].from, last[0].to, last[0].to_end), (1.0, 1.0, true));
    }

    #[test]
    fn fault_names_on_a_plot_are_short() {
        use stepdrive_shared::messages::fault_bits::{BAD_COMMAND, COMMAND_TIMEOUT, DRIVE_FAULT};
        assert_eq!(short_fault_name(COMMAND_TIMEOUT), "COMMAND_TIMEOUT");
        assert_eq!(
            short_fault_name(COMMAND_TIMEOUT | BAD_COMMAND),
            "COMMAND_TIMEOUT + BAD_COMMAND"
        );
        // The drive's own bits: watchdog and over-current.
        assert_eq!(
            short_fault_name(DRIVE_FAULT | (0b11 << 16)),
            "DRIVE_FAULT: WATCHDOG, OVERCURRENT"
        );
        assert_eq!(short_fault_name(1 << 7), "fault 0x80");
    }

    fn line(name: &str, points: Vec<(f64, f64)>) -> Series {
        Series::line(name.into(), points, BLACK, Stroke::Solid)
    }

    #[test]
    fn a_trace_that_lies_on_another_is_dashed_and_says_so() {
        let ramp: Vec<(f64, f64)> = (0..=1000).map(|k| (f64::from(k), f64::from(k))).collect();
        // 0.2 off a ramp of height 1000 (tolerance 5): on it; 50 off: not.
        let near: Vec<(f64, f64)> = ramp.iter().map(|p| (p.0, p.1 + 0.2)).collect();
        let off: Vec<(f64, f64)> = ramp.iter().map(|p| (p.0, p.1 - 50.0)).collect();
        let mut p = Panel {
            title: None,
            y_label: String::new(),
            series: vec![
                line("θ_d", ramp.clone()),
                line("θ (proposed)", near.clone()),
                line("θ (lyapunov)", ramp),
                line("away", off),
            ],
            window: (0.0, 1000.0),
            zoomed: false,
            log: false,
        };
        mark_overlaps(&mut p);
        let strokes: Vec<Stroke> = p.series.iter().map(|s| s.stroke).collect();
        assert_eq!(
            strokes,
            [
                Stroke::Solid,
                Stroke::Dashed { on: 10, off: 10 },
                // Over two: a longer gap, so that both beneath show.
                Stroke::Dashed { on: 10, off: 20 },
                Stroke::Solid,
            ]
        );
        assert_eq!(p.series[1].name, "θ (proposed), dashed: lies on θ_d");
        assert_eq!(
            p.series[2].name,
            "θ (lyapunov), dashed: lies on θ_d and θ (proposed)"
        );
        assert_eq!(p.series[3].name, "away");
        // On it until it parts (a method until its fault): dashed, partly on it.
        let a = line(
            "a",
            (0..=1000).map(|k| (f64::from(k), f64::from(k))).collect(),
        );
        let mut parting = near.clone();
        for q in parting.iter_mut().skip(480) {
            q.1 += 100.0;
        }
        let mut p = Panel {
            series: vec![a.clone(), line("b", parting)],
            ..p
        };
        mark_overlaps(&mut p);
        assert_eq!(p.series[1].name, "b, dashed: partly on a");
        assert_eq!(p.series[1].stroke, Stroke::Dashed { on: 10, off: 10 });
        // Meeting it on a tenth of its samples, or crossing it: not on it.
        let mut brief = near;
        for q in brief.iter_mut().skip(100) {
            q.1 += 100.0;
        }
        assert!(share_on(&brief, &a.points, 5.0) < PARTLY);
        let crossing: Vec<(f64, f64)> = (0..=1000)
            .map(|k| (f64::from(k), 1000.0 - f64::from(k)))
            .collect();
        assert!(overlaps(&[a.clone(), line("b", brief)], 5.0)[1].is_empty());
        assert!(overlaps(&[a, line("c", crossing)], 5.0)[1].is_empty());
    }

    #[test]
    fn the_legend_stands_in_columns_a_method_to_a_column() {
        // Eight entries of up to 300 px in 1168 px: three columns of three rows.
        let (column, cells) = legend_layout(&[300, 200, 200, 300, 200, 200, 250, 250], 1168);
        assert_eq!(column, 300);
        assert_eq!(
            cells,
            [
                (0, 0),
                (0, 1),
                (0, 2),
                (1, 0),
                (1, 1),
                (1, 2),
                (2, 0),
                (2, 1)
            ]
        );
        // Wider than the figure: one column.
        let (_, cells) = legend_layout(&[2000, 10], 1168);
        assert_eq!(cells, [(0, 0), (0, 1)]);
        assert!(legend_layout(&[], 1168).1.is_empty());
    }

    #[test]
    fn a_line_is_cut_where_it_turns_back() {
        // Down 500 pixels and back up one pixel over: cut at the bottom.
        assert_eq!(pieces(&[(10, 10), (10, 510), (11, 10)]), [(0, 1), (1, 2)]);
        // A right angle, and repeated pixels (many samples in one): not cut.
        assert_eq!(pieces(&[(0, 0), (5, 0), (5, 0), (5, 5), (9, 5)]), [(0, 4)]);
        // A zig-zag: cut at every turn back.
        assert_eq!(
            pieces(&[(0, 0), (0, 9), (1, 0), (1, 9)]),
            [(0, 1), (1, 2), (2, 3)]
        );
        assert_eq!(pieces(&[(3, 3)]), [(0, 0)]);
        assert!(pieces(&[]).is_empty());
    }

    #[test]
    fn fault_names_above_a_plot_do_not_overlap() {
        // The second starts inside the first: a row of its own; the third clears both.
        assert_eq!(label_rows(&[(100, 150), (200, 100), (400, 80)]), [0, 1, 0]);
        assert_eq!(label_rows(&[(100, 50), (100, 50), (100, 50)]), [0, 1, 2]);
    }

    fn figure(panels: Vec<Panel>, spans: Vec<Span>) -> Figure {
        Figure {
            file: "test",
            title: String::new(),
            panels,
            spans,
        }
    }

    #[test]
    fn the_legend_names_a_fault_outside_the_window_too() {
        let zoom = Panel {
            title: None,
            y_label: String::new(),
            series: vec![line("i_a", vec![(0.9, 0.0), (0.92, 1.0)])],
            window: (0.9, 0.92),
            zoomed: true,
            log: false,
        };
        let fault = |from: f64| Span {
            from,
            to: 2.0,
            kind: SpanKind::Fault {
                label: "COMMAND_TIMEOUT".into(),
                legend: format!("COMMAND_TIMEOUT: latched at {from:.3} s"),
            },
        };
        let cruise = Span {
            from: 0.9,
            to: 1.5,
            kind: SpanKind::Cruise,
        };
        let texts = |f: &Figure| legend(f).into_iter().map(|e| e.1).collect::<Vec<_>>();
        // A zoomed panel alone: no cruise shading to explain; the fault after it named.
        assert_eq!(
            texts(&figure(
                vec![zoom.clone()],
                vec![cruise.clone(), fault(1.2)]
            )),
            [
                "i_a",
                "COMMAND_TIMEOUT: latched at 1.200 s (after this window)"
            ]
        );
        assert_eq!(
            texts(&figure(vec![zoom.clone()], vec![fault(0.91)])),
            ["i_a", "COMMAND_TIMEOUT: latched at 0.910 s"]
        );
        let whole = Panel {
            window: (0.0, 2.0),
            zoomed: false,
            ..zoom
        };
        assert_eq!(
            texts(&figure(vec![whole], vec![cruise, fault(1.2)])),
            [
                "i_a",
                "cruise window of the metrics (every pass)",
                "COMMAND_TIMEOUT: latched at 1.200 s"
            ]
        );
    }

    #[test]
    fn a_program_is_drawn_with_its_axis_states_and_a_profile_run_is_not() {
        use stepdrive_shared::axis::AxisState as S;
        // 1 kHz statuses: disabled to 0.1 s, enabled to 0.5 s, quick stop to 0.7 s, enabled.
        let state_at = |t: f64| match t {
            t if t < 0.1 => S::SwitchOnDisabled,
            t if t < 0.5 => S::OperationEnabled,
            t if t < 0.7 => S::QuickStopActive,
            _ => S::OperationEnabled,
        };
        let statuses: Vec<StatusRecord> = (0..1000)
            .map(|k| {
                let t = f64::from(k) * 1e-3;
                StatusRecord {
                    t,
                    state_code: state_at(t) as u32,
                    theta_d: t * t,
                    theta: t * t - 1e-6,
                    following_error: 1e-6,
                    omega_d: 2.0 * t,
                    alpha_d: 2.0,
                    ..Default::default()
                }
            })
            .collect();
        let mut rec = Recorded::default();
        rec.runs.push(("proposed".into(), Vec::new()));
        assert!(
            program_figures(&rec).is_empty(),
            "no statuses: no program figures"
        );
        rec.statuses.push(("proposed".into(), statuses));
        let figures = program_figures(&rec);
        let files: Vec<&str> = figures.iter().map(|f| f.file).collect();
        assert_eq!(
            files,
            [
                "program_position",
                "program_following_error",
                "program_velocity",
                "program_acceleration"
            ]
        );
        // Shaded: the disabled start and the quick stop, each once, at their times;
        // Operation enabled is not.
        let spans: Vec<(S, f64, f64)> = figures[0]
            .spans
            .iter()
            .filter_map(|s| match s.kind {
                SpanKind::Axis(state) => Some((state, s.from, s.to)),
                _ => None,
            })
            .collect();
        assert_eq!(spans.len(), 2, "{spans:?}");
        assert_eq!(spans[0].0, S::SwitchOnDisabled);
        assert!(spans[0].1 == 0.0 && (spans[0].2 - 0.1).abs() < 1.5e-3);
        assert_eq!(spans[1].0, S::QuickStopActive);
        assert!((spans[1].1 - 0.5).abs() < 1.5e-3 && (spans[1].2 - 0.7).abs() < 1.5e-3);
        // The legend names both states once.
        let legend: Vec<String> = legend(&figures[0]).into_iter().map(|(_, t)| t).collect();
        assert!(
            legend.contains(&"axis Switch on disabled".to_string()),
            "{legend:?}"
        );
        assert!(
            legend.contains(&"axis Quick stop active".to_string()),
            "{legend:?}"
        );
        // θ_d and the measured θ are both drawn, the latter dashed.
        let position = &figures[0].panels[0].series;
        assert_eq!(position.len(), 2);
        assert!(matches!(position[1].stroke, Stroke::Dashed { .. }));
    }
}

#[cfg(test)]
mod empty_window {
    use super::*;

    /// A zoomed window the recording has no sample in (a reader that missed that stretch)
    /// is drawn empty and says so: it used to fail the whole `plot` ("no finite point").
    #[test]
    fn a_window_without_samples_is_drawn_empty_and_says_so() {
        let p = Panel {
            title: None,
            y_label: "current [A]".into(),
            series: Vec::new(),
            window: (0.2, 0.22),
            zoomed: true,
            log: false,
        };
        let mut svg = String::new();
        {
            let area = SVGBackend::with_string(&mut svg, (640, 360)).into_drawing_area();
            draw_panel(&area, &p, &[], 1).expect("an empty window is drawn");
        }
        assert!(svg.contains("no sample recorded in this window"), "{svg}");
        let nothing = Panel {
            window: (f64::NAN, f64::NAN),
            ..p
        };
        let area = SVGBackend::with_string(&mut svg, (640, 360)).into_drawing_area();
        assert!(draw_panel(&area, &nothing, &[], 1).is_err());
    }
}
