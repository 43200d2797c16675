//! `stepdrive scope`: a live terminal view of a running stack. Rolling traces of the
//! tracking error, the speed, i_d/i_q and the phase voltages; each loop's timing (misses,
//! wake-up p99, sensor-to-actuator p99); faults in red.
//!
//! It only reads: one more subscriber of the state and statistics topics, which in realtime
//! may fall behind (samples it misses are counted, never waited for), so starting, stopping
//! or killing it never touches the loops. What it draws is a pure function of [`View`]
//! ([`render`]), tested on ratatui's `TestBackend`.

use crate::report::outcome::fault_names;
use crate::report::setpoints::SetpointHistory;
use anyhow::Result;
use ratatui::layout::{Constraint, Layout};
use ratatui::style::{Color, Modifier, Style};
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::{Axis, Block, Chart, Dataset, GraphType, Paragraph};
use ratatui::Frame;
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use stepdrive_runtime::port::PortFactory;
use stepdrive_shared::frames::dq_currents;
use stepdrive_shared::messages::{state_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::stack::{Role, Slot};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::trajectory::Trapezoid;
use stepdrive_shared::Scenario;

/// Time spans the view can show, s (`+`/`-` step through them).
pub const SPANS: [f64; 6] = [0.1, 0.25, 0.5, 1.0, 2.5, 10.0];
/// Points kept per span and trace: the terminal has far fewer columns.
const POINTS: usize = 600;

/// The signals, in panel order (`1`–`4` toggle them).
pub const PANELS: [&str; 4] = [
    "e = θ_d − θ [rad]",
    "ω [rad/s]",
    "i_d, i_q [A]",
    "v_a, v_b [V]",
];

/// One decimated sample: t, e, ω, i_d, i_q, v_a, v_b.
type Point = [f64; 7];

/// A trace of a panel: its name, points (t, value) and colour.
type Trace = (&'static str, Vec<(f64, f64)>, Color);

/// Where θ_d comes from: the scenario's profile, or a commanded axis's setpoints (a
/// program, a served stack), which the scope takes from the position loop.
enum Desired {
    Profile(Trapezoid),
    Setpoints(SetpointHistory),
}

/// What the scope shows; fed by samples and reports, drawn by [`render`].
pub struct View {
    pub instance: String,
    pub mode: String,
    desired: Desired,
    n_r: f64,
    points: VecDeque<Point>,
    span_index: usize,
    pub paused: bool,
    pub shown: [bool; 4],
    /// The latest report of each loop (plant, current loop, position loop).
    stats: [Option<StatsReport>; 3],
    pub fault: u32,
    pub samples: u64,
    pub missed: u64,
    last_seq: Option<u64>,
    /// Keep one sample in `every`.
    every: u64,
    /// The stack's last sample came (its LAST flag), or it went silent: what is shown is
    /// where it ended.
    pub ended: Option<&'static str>,
}

impl View {
    pub fn new(s: &Scenario, instance: &str, mode: &str) -> Self {
        let mut v = Self {
            instance: instance.to_string(),
            mode: mode.to_string(),
            desired: match s.runs_profile() {
                true => Desired::Profile(Trapezoid::new(&s.trajectory)),
                false => Desired::Setpoints(SetpointHistory::for_scenario(s)),
            },
            n_r: f64::from(s.motor.rotor_teeth),
            points: VecDeque::with_capacity(2 * POINTS),
            span_index: 3,
            paused: false,
            shown: [true; 4],
            stats: [None; 3],
            fault: 0,
            samples: 0,
            missed: 0,
            last_seq: None,
            every: 1,
            ended: None,
        };
        v.set_span(3, s.rates.current_loop_hz);
        v
    }

    pub fn span_s(&self) -> f64 {
        SPANS[self.span_index]
    }

    fn set_span(&mut self, index: usize, rate_hz: f64) {
        self.span_index = index.min(SPANS.len() - 1);
        self.every = ((self.span_s() * rate_hz / POINTS as f64).round() as u64).max(1);
    }

    /// A wider (`+1`) or narrower (`-1`) span.
    pub fn zoom(&mut self, step: i32, rate_hz: f64) {
        let i = (self.span_index as i32 + step).clamp(0, SPANS.len() as i32 - 1) as usize;
        self.set_span(i, rate_hz);
    }

    pub fn push_state(&mut self, st: &DriveState) {
        if let Some(q) = self.last_seq {
            self.missed += st.seq.saturating_sub(q + 1);
        }
        self.last_seq = Some(st.seq);
        self.samples += 1;
        self.fault = st.fault;
        self.ended = (st.flags & state_flags::LAST != 0).then_some("ENDED (its last sample)");
        if self.paused || !st.seq.is_multiple_of(self.every) {
            return;
        }
        let t = st.sample_time_s;
        // NaN before the first setpoint: not drawn.
        let theta_d = match &self.desired {
            Desired::Profile(trajectory) => trajectory.at(t).theta,
            Desired::Setpoints(h) => h.at(t).map_or(f64::NAN, |r| r.theta),
        };
        let e = theta_d - st.theta_rad;
        let (i_d, i_q) = dq_currents(st.theta_rad, self.n_r, st.i_a_a, st.i_b_a);
        self.points
            .push_back([t, e, st.omega_rad_s, i_d, i_q, st.v_a_v, st.v_b_v]);
        let from = t - self.span_s();
        while self.points.front().is_some_and(|p| p[0] < from) || self.points.len() > 4 * POINTS {
            self.points.pop_front();
        }
    }

    /// The position loop's setpoint: a commanded axis's θ_d from its sample on.
    pub fn push_setpoint(&mut self, sp: &TorqueSetpoint) {
        if let Desired::Setpoints(h) = &mut self.desired {
            h.push(sp);
        }
    }

    /// Whether θ_d comes from the position loop's setpoints.
    pub fn wants_setpoints(&self) -> bool {
        matches!(self.desired, Desired::Setpoints(_))
    }

    pub fn push_stats(&mut self, r: &StatsReport) {
        let slot = Role::from_code(r.role).and_then(Role::slot);
        if let Some(slot) = slot {
            self.stats[slot.index()] = Some(*r);
        }
    }
}

fn us(h: &stepdrive_shared::stats::Histogram, q: f64) -> String {
    h.quantile_ns(q).map_or("—".to_string(), |ns| {
        format!("{:.1} µs", ns as f64 * 1e-3)
    })
}

/// The header: what is shown, each loop's timing, and the faults, in red when latched.
fn header(v: &View) -> Vec<Line<'static>> {
    let mut lines = vec![Line::from(vec![
        Span::styled(
            format!("stepdrive scope — {} ({})", v.instance, v.mode),
            Style::new().add_modifier(Modifier::BOLD),
        ),
        Span::raw(format!(
            "   span {:.2} s   samples {}   missed by the scope {}{}",
            v.span_s(),
            v.samples,
            v.missed,
            if v.paused { "   PAUSED" } else { "" }
        )),
    ])];
    if let Some(why) = v.ended {
        lines[0].spans.push(Span::styled(
            format!("   STACK {why}"),
            Style::new().add_modifier(Modifier::BOLD | Modifier::REVERSED),
        ));
    }
    let mut timing = Vec::new();
    for slot in Slot::ALL {
        let Some(r) = v.stats[slot.index()] else {
            continue;
        };
        let name = Role::from_code(r.role).map_or("?", Role::title);
        let pct = if r.cycles > 0 {
            100.0 * r.misses as f64 / r.cycles as f64
        } else {
            0.0
        };
        let mut text = format!("{name}: misses {} ({pct:.3} %)", r.misses);
        if r.wakeup.count > 0 {
            text += &format!(", wake-up p99 {}", us(&r.wakeup, 0.99));
        }
        if slot == Slot::Device && r.sensor_to_actuator.count > 0 {
            text += &format!(", s2a p99 {}", us(&r.sensor_to_actuator, 0.99));
        }
        timing.push(text);
    }
    if timing.is_empty() {
        timing.push("timing: no report yet".to_string());
    }
    // One line a loop: side by side they overflow an 80- or 130-column terminal.
    lines.extend(timing.into_iter().map(Line::from));
    lines.push(if v.fault != 0 {
        Line::from(Span::styled(
            format!("FAULT: {}", fault_names(v.fault).join(", ")),
            Style::new()
                .fg(Color::White)
                .bg(Color::Red)
                .add_modifier(Modifier::BOLD),
        ))
    } else {
        Line::from(Span::styled("no fault", Style::new().fg(Color::Green)))
    });
    lines.push(Line::from(
        "keys: q quit   p pause   + / - span   1-4 show/hide e, ω, i_dq, v",
    ));
    lines
}

fn bounds(data: &[&[(f64, f64)]]) -> [f64; 2] {
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    for d in data {
        for &(_, y) in d.iter() {
            if y.is_finite() {
                lo = lo.min(y);
                hi = hi.max(y);
            }
        }
    }
    if lo > hi {
        return [-1.0, 1.0];
    }
    let pad = ((hi - lo) * 0.1).max(1e-9);
    [lo - pad, hi + pad]
}

fn fmt(v: f64) -> String {
    if v == 0.0 || (1e-2..1e4).contains(&v.abs()) {
        format!("{v:.3}")
    } else {
        format!("{v:.2e}")
    }
}

/// Draws the view: the header, then one chart per shown signal.
pub fn render(f: &mut Frame, v: &View) {
    let head = header(v);
    let shown: Vec<usize> = (0..4).filter(|&i| v.shown[i]).collect();
    let mut constraints = vec![Constraint::Length(head.len() as u16)];
    constraints.extend(shown.iter().map(|_| Constraint::Fill(1)));
    let areas = Layout::vertical(constraints).split(f.area());
    f.render_widget(Paragraph::new(head), areas[0]);
    let t1 = v.points.back().map_or(v.span_s(), |p| p[0]);
    let t0 = t1 - v.span_s();
    let col = |k: usize| -> Vec<(f64, f64)> {
        v.points
            .iter()
            .filter(|p| p[k].is_finite())
            .map(|p| (p[0], p[k]))
            .collect()
    };
    for (slot, &panel) in shown.iter().enumerate() {
        let series: Vec<Trace> = match panel {
            0 => vec![("e", col(1), Color::Cyan)],
            1 => vec![("ω", col(2), Color::Yellow)],
            2 => vec![
                ("i_d", col(3), Color::Magenta),
                ("i_q", col(4), Color::Green),
            ],
            _ => vec![
                ("v_a", col(5), Color::Cyan),
                ("v_b", col(6), Color::LightRed),
            ],
        };
        let y = bounds(&series.iter().map(|s| s.1.as_slice()).collect::<Vec<_>>());
        let datasets: Vec<Dataset> = series
            .iter()
            .map(|(name, data, color)| {
                Dataset::default()
                    .name(*name)
                    .marker(Marker::Braille)
                    .graph_type(GraphType::Line)
                    .style(Style::new().fg(*color))
                    .data(data)
            })
            .collect();
        let chart = Chart::new(datasets)
            .block(Block::bordered().title(PANELS[panel]))
            .x_axis(
                Axis::default()
                    .bounds([t0, t1])
                    .labels([format!("{t0:.2} s"), format!("{t1:.2} s")]),
            )
            .y_axis(Axis::default().bounds(y).labels([fmt(y[0]), fmt(y[1])]));
        f.render_widget(chart, areas[slot + 1]);
    }
}

/// A stack this long without a sample is shown as ended.
const SILENT: Duration = Duration::from_secs(2);

/// Attaches to `instance` (running `given`, or the scenario it announces) and shows it until
/// `q`, Ctrl-C, or the stack's end.
/// `axis`: the axis of a multi-axis stack it shows.
pub fn run_scope(instance: &str, given: Option<&Scenario>, axis: u32) -> Result<()> {
    use ratatui::crossterm::event::{self, Event, KeyCode, KeyEventKind, KeyModifiers};
    let crate::supervise::attach::Attached {
        mut bus,
        scenario,
        mut states,
    } = crate::supervise::attach::attach_reader(instance, "scope", given, axis)?;
    let s = &scenario;
    // The loops' statistics are per process, on axis 0's services.
    bus.set_axis(0);
    let mut stats = bus.subscriber::<StatsReport>(4)?;
    bus.set_axis(axis);
    let rate = s.rates.current_loop_hz;
    let label = match axis {
        0 => instance.to_string(),
        n => format!("{instance}, axis {n}"),
    };
    let mut view = View::new(s, &label, bus.mode().as_str());
    let mut setpoints = match view.wants_setpoints() {
        true => Some(bus.subscriber::<TorqueSetpoint>(stepdrive_shared::services::MONITOR_BUFFER)?),
        false => None,
    };
    // A commanded axis's states wait for the setpoint that covers them (one from a later
    // sample): graded at once, those newer than the last setpoint taken were drawn against
    // the one before, and a move's start showed a spike of several mrad the rotor never had.
    let mut waiting: VecDeque<DriveState> =
        VecDeque::with_capacity(stepdrive_shared::services::MONITOR_BUFFER);
    let mut newest_setpoint = f64::NEG_INFINITY;
    let mut terminal = ratatui::init();
    let outcome = (|| -> Result<()> {
        let mut next_frame = Instant::now();
        let mut heard = Instant::now();
        loop {
            // The setpoints first: a state's θ_d is the setpoint in force at its sample.
            if let Some(sub) = setpoints.as_mut() {
                while let Some(sp) = sub.receive()? {
                    newest_setpoint = newest_setpoint.max(sp.sample_time_s);
                    view.push_setpoint(&sp);
                }
            }
            while let Some(st) = states.receive()? {
                heard = Instant::now();
                match setpoints.is_some() {
                    true => {
                        if waiting.len() == waiting.capacity() {
                            if let Some(old) = waiting.pop_front() {
                                view.push_state(&old);
                            }
                        }
                        waiting.push_back(st);
                    }
                    false => view.push_state(&st),
                }
            }
            // A silent position loop sends no setpoint: what waits is drawn once the stack
            // is silent too.
            let flush = heard.elapsed() > SILENT;
            while let Some(st) = waiting.front() {
                if !flush && st.sample_time_s >= newest_setpoint {
                    break;
                }
                if let Some(st) = waiting.pop_front() {
                    view.push_state(&st);
                }
            }
            if view.ended.is_none() && view.samples > 0 && heard.elapsed() > SILENT {
                view.ended = Some("SILENT (no sample for 2 s)");
            }
            // In place: a report is ~90 KB (see `Supervisor::take_stats`).
            stats.drain(&mut |r| view.push_stats(r))?;
            if Instant::now() >= next_frame {
                terminal.draw(|f| render(f, &view))?;
                next_frame = Instant::now() + Duration::from_millis(50);
            }
            if stepdrive_runtime::poll::termination_requested() {
                return Ok(());
            }
            if event::poll(Duration::from_millis(5))? {
                if let Event::Key(k) = event::read()? {
                    if k.kind != KeyEventKind::Press {
                        continue;
                    }
                    match k.code {
                        KeyCode::Char('q') | KeyCode::Esc => return Ok(()),
                        // Raw mode turns Ctrl-C into a key.
                        KeyCode::Char('c') if k.modifiers.contains(KeyModifiers::CONTROL) => {
                            return Ok(())
                        }
                        KeyCode::Char('p') | KeyCode::Char(' ') => view.paused = !view.paused,
                        KeyCode::Char('+') | KeyCode::Char('=') => view.zoom(1, rate),
                        KeyCode::Char('-') => view.zoom(-1, rate),
                        KeyCode::Char(c @ '1'..='4') => {
                            let i = c as usize - '1' as usize;
                            view.shown[i] = !view.shown[i];
                        }
                        _ => {}
                    }
                }
            }
        }
    })();
    ratatui::restore();
    outcome
}

#[cfg(test)]
mod tests {
    use super::*;
    use ratatui::backend::TestBackend;
    use ratatui::Terminal;
    use stepdrive_shared::messages::fault_bits;

    fn text(t: &Terminal<TestBackend>) -> String {
        let b = t.backend().buffer();
        let mut s = String::new();
        for y in 0..b.area.height {
            for x in 0..b.area.width {
                s.push_str(b[(x, y)].symbol());
            }
            s.push('\n');
        }
        s
    }

    fn feed(v: &mut View, s: &Scenario, from: u64, to: u64, fault: u32) {
        let rate = s.rates.current_loop_hz;
        for k in from..to {
            let t = k as f64 / rate;
            let r = Trapezoid::new(&s.trajectory).at(t);
            v.push_state(&DriveState {
                seq: k,
                sample_time_s: t,
                theta_rad: r.theta - 1e-5,
                omega_rad_s: r.omega,
                i_a_a: 0.1,
                v_a_v: 3.0,
                fault,
                ..Default::default()
            });
        }
    }

    /// A synthetic feed drawn into a test terminal: the titles, the loops' timing, the
    /// span; then a latched fault shown by name; a skipped sample counted as missed.
    #[test]
    fn the_view_shows_signals_timing_and_faults() {
        let s = Scenario::default();
        let mut v = View::new(&s, "bench", "realtime");
        feed(&mut v, &s, 0, 20_000, 0);
        let mut plant = StatsReport {
            role: Role::Plant.code(),
            cycles: 20_000,
            misses: 20,
            ..Default::default()
        };
        plant.sensor_to_actuator.record(7_000);
        v.push_stats(&plant);
        let mut t = Terminal::new(TestBackend::new(120, 40)).expect("terminal");
        t.draw(|f| render(f, &v)).expect("draw");
        let screen = text(&t);
        for want in [
            "stepdrive scope — bench (realtime)",
            "e = θ_d − θ [rad]",
            "ω [rad/s]",
            "i_d, i_q [A]",
            "v_a, v_b [V]",
            "plant: misses 20 (0.100 %)",
            "s2a p99",
            "span 1.00 s",
            "no fault",
        ] {
            assert!(screen.contains(want), "{want:?} missing from\n{screen}");
        }
        // Hide two panels, pause, and a fault latches (two samples lost on the way).
        v.shown[1] = false;
        v.shown[3] = false;
        feed(&mut v, &s, 20_002, 20_010, fault_bits::COMMAND_TIMEOUT);
        assert_eq!(v.missed, 2);
        t.draw(|f| render(f, &v)).expect("draw");
        let screen = text(&t);
        assert!(screen.contains("FAULT: COMMAND_TIMEOUT"), "{screen}");
        assert!(!screen.contains("ω [rad/s]") && screen.contains("i_d, i_q [A]"));
        assert_eq!(
            t.backend().buffer()[(0, 2)].bg,
            Color::Red,
            "the fault line is red"
        );
        // The stack's last sample: the view says it ended (round 3, finding 11: it kept
        // its last frame with no mark).
        assert!(!screen.contains("STACK ENDED"));
        v.push_state(&DriveState {
            seq: 20_010,
            sample_time_s: 20_010.0 / s.rates.current_loop_hz,
            flags: stepdrive_shared::messages::state_flags::LAST,
            ..Default::default()
        });
        t.draw(|f| render(f, &v)).expect("draw");
        let screen = text(&t);
        assert!(screen.contains("STACK ENDED (its last sample)"), "{screen}");
    }

    /// A served stack (or a program) is drawn against its axis's setpoints: a rotor 1e-5
    /// rad behind a setpoint at 3 rad shows e = 1e-5, where the scenario's trapezoid (which
    /// it never runs) showed several rad; before the first setpoint nothing is drawn.
    #[test]
    fn a_commanded_axis_is_drawn_against_its_setpoints() {
        let mut s = Scenario::default();
        s.run.until_stopped = true;
        let mut v = View::new(&s, "served", "realtime");
        assert!(v.wants_setpoints());
        let rate = s.rates.current_loop_hz;
        let state = |k: u64| DriveState {
            seq: k,
            sample_time_s: k as f64 / rate,
            theta_rad: 3.0 - 1e-5,
            ..Default::default()
        };
        // Samples a multiple of the 1 s span's decimation (33) are drawn.
        let first = 33 * 1212;
        v.push_state(&state(first));
        v.push_setpoint(&TorqueSetpoint {
            sample_time_s: (first + 1) as f64 / rate,
            theta_d_rad: 3.0,
            ..Default::default()
        });
        for k in first + 1..first + 100 {
            v.push_state(&state(k));
        }
        let e: Vec<f64> = v.points.iter().map(|p| p[1]).collect();
        assert!(e[0].is_nan(), "before any setpoint: {}", e[0]);
        assert!(
            e[1..].iter().all(|e| (e - 1e-5).abs() < 1e-12),
            "{:?}",
            &e[..4]
        );
    }

    #[test]
    fn the_span_keeps_a_bounded_window() {
        let s = Scenario::default();
        let mut v = View::new(&s, "x", "lockstep");
        v.zoom(-10, s.rates.current_loop_hz);
        assert_eq!(v.span_s(), SPANS[0]);
        feed(&mut v, &s, 0, 40_000, 0);
        let t_last = v.points.back().expect("points")[0];
        assert!(v.points.front().expect("points")[0] >= t_last - SPANS[0]);
        assert!(v.points.len() <= 4 * POINTS);
    }
}
