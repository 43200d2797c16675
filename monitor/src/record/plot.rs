//! The paper's figures from a recording, as SVG and PNG: position, tracking error (linear
//! and log, with the eq. (7) bound and the cruise window), phase currents, i_d and i_q,
//! phase voltages against the bus, torque. Several methods in one recording are overlaid.

use crate::record::recording::{RecordError, Recorded, StateRecord};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
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

/// One line of a chart.
struct Series {
    name: String,
    points: Vec<(f64, f64)>,
    color: RGBColor,
    dashed: bool,
}

/// A chart: its series, reference lines, and whether the y axis is log10.
struct Chart {
    file: &'static str,
    title: String,
    y_label: &'static str,
    series: Vec<Series>,
    /// Vertical lines (s): the cruise window.
    marks: Vec<f64>,
    log: bool,
}

const COLORS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// The second quantity of a method (dashed): a lighter shade of its colour, so that the
/// legend tells the two apart.
fn light(c: RGBColor) -> RGBColor {
    let up = |v: u8| ((u16::from(v) + 2 * 255) / 3) as u8;
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

fn line(
    runs: &[(String, Vec<StateRecord>)],
    run_index: usize,
    label: &str,
    f: impl Fn(&StateRecord) -> f64,
    color: RGBColor,
    dashed: bool,
) -> Series {
    let (method, states) = &runs[run_index];
    Series {
        name: if runs.len() > 1 {
            format!("{label} ({method})")
        } else {
            label.to_string()
        },
        points: decimate(states.iter().map(|s| (s.t, f(s))).collect(), 2000),
        color,
        dashed,
    }
}

fn charts(rec: &Recorded, s: Option<&Scenario>) -> Vec<Chart> {
    let runs = &rec.runs;
    let cruise = s
        .map(|s| vec![s.metrics.cruise_start_s, s.metrics.cruise_end_s])
        .unwrap_or_default();
    let bound = s.map(|s| s.eq7_bound_rad());
    let per_run = |f: &dyn Fn(usize, RGBColor) -> Vec<Series>| -> Vec<Series> {
        (0..runs.len())
            .flat_map(|i| f(i, COLORS[i % COLORS.len()]))
            .collect()
    };
    let mut position = vec![line(runs, 0, "θ_d", |r| r.theta_d, BLACK, true)];
    position[0].name = "θ_d (desired)".into();
    position.extend(per_run(&|i, c| {
        vec![line(runs, i, "θ", |r| r.theta, c, false)]
    }));
    let mut error = per_run(&|i, c| vec![line(runs, i, "e = θ_d − θ", |r| r.error, c, false)]);
    let mut log_error = per_run(&|i, c| {
        vec![line(
            runs,
            i,
            "|e|",
            |r| r.error.abs().max(1e-15).log10(),
            c,
            false,
        )]
    });
    if let (Some(b), Some(last)) = (bound, runs.first().and_then(|r| r.1.last())) {
        let span = [(0.0, 0.0), (last.t, 0.0)];
        for (sign, v) in [(1.0, b), (-1.0, -b)] {
            error.push(Series {
                name: if sign > 0.0 {
                    "±eq. (7) bound".into()
                } else {
                    String::new()
                },
                points: span.iter().map(|p| (p.0, v)).collect(),
                color: RGBColor(120, 120, 120),
                dashed: true,
            });
        }
        log_error.push(Series {
            name: "eq. (7) bound".into(),
            points: span.iter().map(|p| (p.0, b.log10())).collect(),
            color: RGBColor(120, 120, 120),
            dashed: true,
        });
    }
    let currents = per_run(&|i, c| {
        vec![
            line(runs, i, "i_a", |r| r.i_a, c, false),
            line(runs, i, "i_b", |r| r.i_b, light(c), true),
        ]
    });
    // 20 ms of cruise, where the currents and their references (from the commands, when
    // the recording has them) can be told apart: two electrical periods at 13 rad/s.
    let zoom_from = s.map_or(0.0, |s| s.metrics.cruise_start_s);
    let zoom = zoom_from..zoom_from + 0.02;
    let in_zoom = |t: f64| zoom.contains(&t);
    let currents_zoom = per_run(&|i, c| {
        let (method, states) = &runs[i];
        let named = |label: &str| {
            if runs.len() > 1 {
                format!("{label} ({method})")
            } else {
                label.to_string()
            }
        };
        let mut out = vec![Series {
            name: named("i_a"),
            points: states
                .iter()
                .filter(|r| in_zoom(r.t))
                .map(|r| (r.t, r.i_a))
                .collect(),
            color: c,
            dashed: false,
        }];
        if let Some((_, commands)) = rec.commands.iter().find(|(m, _)| m == method) {
            out.push(Series {
                name: named("i_a reference"),
                points: commands
                    .iter()
                    .filter(|c| in_zoom(c.t_ref))
                    .map(|c| (c.t_ref, c.i_a_ref))
                    .collect(),
                color: light(c),
                dashed: true,
            });
        }
        out
    });
    let dq = per_run(&|i, c| {
        vec![
            line(runs, i, "i_d", |r| r.i_d, light(c), true),
            line(runs, i, "i_q", |r| r.i_q, c, false),
        ]
    });
    let mut volts = per_run(&|i, c| {
        vec![
            line(runs, i, "v_a", |r| r.v_a, c, false),
            line(runs, i, "v_b", |r| r.v_b, light(c), true),
        ]
    });
    let mut plus = line(runs, 0, "+bus", |r| r.bus, BLACK, true);
    plus.name = "±bus".into();
    let mut minus = line(runs, 0, "−bus", |r| -r.bus, BLACK, true);
    minus.name = String::new();
    volts.extend([plus, minus]);
    let torque = per_run(&|i, c| vec![line(runs, i, "τ = K_m i_q", |r| r.torque, c, false)]);
    let chart = |file, title: &str, y_label, series, log| Chart {
        file,
        title: title.to_string(),
        y_label,
        series,
        marks: cruise.clone(),
        log,
    };
    vec![
        chart(
            "position",
            "Desired and actual position",
            "θ [rad]",
            position,
            false,
        ),
        chart(
            "error",
            "Tracking error (cruise window marked)",
            "e [rad]",
            error,
            false,
        ),
        chart(
            "error_log",
            "Tracking error, log scale",
            "log10 |e| [log10 rad]",
            log_error,
            true,
        ),
        chart("currents", "Phase currents", "current [A]", currents, false),
        Chart {
            file: "currents_cruise",
            title: format!(
                "Phase a current and its reference, {:.2}–{:.2} s",
                zoom_from,
                zoom_from + 0.02
            ),
            y_label: "current [A]",
            series: currents_zoom,
            marks: Vec::new(),
            log: false,
        },
        chart("dq_currents", "i_d and i_q", "current [A]", dq, false),
        chart(
            "voltages",
            "Phase voltages and the bus",
            "voltage [V]",
            volts,
            false,
        ),
        chart("torque", "Motor torque", "τ [N·m]", torque, false),
    ]
}

fn draw<DB: DrawingBackend>(area: DrawingArea<DB, Shift>, c: &Chart) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    area.fill(&WHITE).map_err(|e| e.to_string())?;
    let pts = c.series.iter().flat_map(|s| s.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        if x.is_finite() && y.is_finite() {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    if x0 > x1 {
        return Err("no finite point".into());
    }
    let pad = ((y1 - y0) * 0.05).max(1e-12);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let x1 = if x1 > x0 { x1 } else { x0 + 1.0 };
    let mut chart = ChartBuilder::on(&area)
        .caption(&c.title, (FAMILY, 22))
        .margin(12)
        .x_label_area_size(42)
        .y_label_area_size(78)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| e.to_string())?;
    chart
        .configure_mesh()
        .x_desc("t [s]")
        .y_desc(c.y_label)
        .label_style((FAMILY, 14))
        .y_label_formatter(&|v| {
            if c.log {
                format!("{v:.0}")
            } else if v.abs() >= 0.01 || *v == 0.0 {
                format!("{v:.3}")
            } else {
                format!("{v:.1e}")
            }
        })
        .draw()
        .map_err(|e| e.to_string())?;
    for &m in &c.marks {
        chart
            .draw_series(DashedLineSeries::new(
                [(m, y0), (m, y1)],
                4,
                4,
                RGBColor(170, 170, 170).stroke_width(1),
            ))
            .map_err(|e| e.to_string())?;
    }
    for s in &c.series {
        let style = s.color.stroke_width(2);
        let drawn = if s.dashed {
            chart.draw_series(DashedLineSeries::new(s.points.iter().copied(), 6, 4, style))
        } else {
            chart.draw_series(LineSeries::new(s.points.iter().copied(), style))
        }
        .map_err(|e| e.to_string())?;
        if !s.name.is_empty() {
            let color = s.color;
            drawn.label(s.name.clone()).legend(move |(x, y)| {
                PathElement::new([(x, y), (x + 18, y)], color.stroke_width(2))
            });
        }
    }
    chart
        .configure_series_labels()
        .label_font((FAMILY, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(|e| e.to_string())?;
    area.present().map_err(|e| e.to_string())
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
    for c in charts(&rec, scenario.as_ref()) {
        let failed = |path: &Path| {
            let path = path.to_path_buf();
            move |message| PlotError::Draw { path, message }
        };
        let svg = dir.join(format!("{}.svg", c.file));
        draw(SVGBackend::new(&svg, PNG_SIZE).into_drawing_area(), &c).map_err(failed(&svg))?;
        let png = dir.join(format!("{}.png", c.file));
        draw(BitMapBackend::new(&png, PNG_SIZE).into_drawing_area(), &c).map_err(failed(&png))?;
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
}
