//! The side-by-side table and the JSON document of a set of runs.

use crate::report::metrics::RunReport;
use crate::report::outcome::{step_out_threshold_rad, utc_time_of_day, Outcome};
use serde::Serialize;
use std::fmt::Write as _;
use stepdrive_shared::Scenario;

#[derive(Debug, Serialize)]
pub struct Document<'a> {
    pub stepdrive_version: &'static str,
    /// The most severe outcome of the runs, and the exit code it gave.
    pub outcome: Outcome,
    pub exit_code: u8,
    /// False when a run stopped early (its figures cover what ran).
    pub complete: bool,
    pub scenario: &'a Scenario,
    /// Expected steady error of microstepping at cruise, eq. (7) plus the load term, rad.
    pub microstepping_expected_cruise_error_rad: f64,
    /// R τ_L / (K_m V_max N_r): microstepping's final offset under load, rad.
    pub microstepping_expected_final_error_rad: f64,
    pub runs: &'a [RunReport],
}

/// The most severe outcome of a set of runs.
pub fn overall(runs: &[RunReport]) -> Outcome {
    runs.iter()
        .map(RunReport::worst)
        .max()
        .unwrap_or(Outcome::Ok)
}

/// [`headline`] of a run and of each of its other axes that did not go well.
pub fn headlines(s: &Scenario, r: &RunReport) -> Vec<String> {
    let own = headline(s.for_axis(0).unwrap_or(s), r);
    let axes = r.axes.iter().filter_map(|a| {
        let h = headline(s.for_axis(a.axis)?, &a.report)?;
        Some(format!("axis {} ({}): {h}", a.axis, a.name))
    });
    own.into_iter().chain(axes).collect()
}

pub fn document<'a>(s: &'a Scenario, runs: &'a [RunReport]) -> Document<'a> {
    let outcome = overall(runs);
    Document {
        stepdrive_version: env!("CARGO_PKG_VERSION"),
        outcome,
        exit_code: outcome.exit_code(),
        complete: runs.iter().all(|r| r.complete),
        scenario: s,
        microstepping_expected_cruise_error_rad: expected_microstepping_cruise_error(s),
        microstepping_expected_final_error_rad: s.load_offset_rad(),
        runs,
    }
}

/// Steady lag of microstepping with ideal current tracking at cruise: the electrical angle
/// lag δ where (K_m V_max / R) sin δ = B ω_d + τ_L, i.e. (7) plus the load, without the
/// small-angle approximation.
pub fn expected_microstepping_cruise_error(s: &Scenario) -> f64 {
    let m = &s.motor;
    let needed =
        m.viscous_friction_nm_s_per_rad * s.trajectory.cruise_velocity_rad_s + s.load.torque_nm;
    let available = m.torque_constant_nm_per_a * s.gains.v_max_v / m.resistance_ohm;
    (needed / available).clamp(-1.0, 1.0).asin() / m.n_r()
}

/// `{:.3e}`, or `n/a` for a figure the run never reached.
fn sci(v: f64) -> String {
    if v.is_nan() {
        "n/a".to_string()
    } else {
        format!("{v:.3e}")
    }
}

/// What replaced a move before it got there, in the moves table: a move re-targets it.
fn replaced_word(kind: Option<&str>) -> &str {
    match kind {
        Some("move") | None => "re-targeted",
        Some("stop") => "stopped",
        Some("quick-stop") => "quick stop",
        Some("shutdown" | "disable-voltage" | "disable-operation") => "disabled",
        Some("stream-start") => "stream",
        Some(other) => other,
    }
}

/// `v` to `digits` decimals, or `n/a` for a figure the run never reached (a run with a
/// program has no cruise window).
fn fixed(v: f64, digits: usize) -> String {
    if v.is_nan() {
        "n/a".to_string()
    } else {
        format!("{v:.digits$}")
    }
}

pub fn table(s: &Scenario, runs: &[RunReport]) -> String {
    // A table of n/a and NaN says nothing: say that nothing ran (the headline says why).
    if !runs.is_empty() && runs.iter().all(|r| r.samples == 0 && !r.complete) {
        return "no figures: no sample ran (the headline below says why)\n".to_string();
    }
    type Row = (&'static str, fn(&RunReport) -> String);
    let rows: [Row; 18] = [
        ("mode", |r| r.mode.clone()),
        ("outcome", |r| {
            let title = r.outcome.title().to_lowercase();
            if r.complete {
                title
            } else {
                format!("{title}, incomplete")
            }
        }),
        ("cruise max |e| [rad]", |r| sci(r.cruise_max_abs_error_rad)),
        ("max |e|, whole run [rad]", |r| sci(r.max_abs_error_rad)),
        ("final error [rad]", |r| sci(r.final_error_rad)),
        ("cruise mean i_d [A]", |r| fixed(r.cruise_mean_id_a, 4)),
        ("cruise mean i_q [A]", |r| fixed(r.cruise_mean_iq_a, 4)),
        ("cruise mean torque [N·m]", |r| {
            fixed(r.cruise_mean_torque_nm, 4)
        }),
        ("mean copper loss [W]", |r| fixed(r.mean_copper_loss_w, 4)),
        ("mean input power [W]", |r| fixed(r.mean_input_power_w, 4)),
        ("max |v| [V]", |r| fixed(r.max_abs_voltage_v, 2)),
        ("cruise max |v| [V]", |r| {
            fixed(r.cruise_max_abs_voltage_v, 2)
        }),
        ("eq. (7) bound [rad]", |r| sci(r.eq7_bound_rad)),
        ("sim time [s]", |r| format!("{:.3}", r.sim_time_s)),
        ("wall time [s]", |r| format!("{:.3}", r.wall_time_s)),
        ("samples", |r| r.samples.to_string()),
        ("samples missed", |r| r.missed_samples.to_string()),
        ("limited / faulted / silent samples", |r| {
            format!(
                "{} / {} / {}",
                r.voltage_limited_samples, r.fault_samples, r.silent_samples
            )
        }),
    ];
    let step_rows: [Row; 2] = [
        ("load step: peak |e| [rad]", |r| {
            r.load_step
                .as_ref()
                .map_or("n/a".into(), |l| sci(l.peak_abs_error_rad))
        }),
        ("back within 1e-4 rad [ms]", |r| {
            match r.load_step.as_ref() {
                None => "n/a".into(),
                Some(l) => l
                    .back_within_1e4_rad_after_s
                    .map_or("not back".into(), |b| format!("{:.1}", b * 1e3)),
            }
        }),
    ];
    let truth_rows: [Row; 3] = [
        ("true cruise max |e| [rad]", |r| {
            r.truth
                .as_ref()
                .map_or("n/a".into(), |t| sci(t.cruise_max_abs_error_rad))
        }),
        ("true max |e|, whole run [rad]", |r| {
            r.truth
                .as_ref()
                .map_or("n/a".into(), |t| sci(t.max_abs_error_rad))
        }),
        ("true final error [rad]", |r| {
            r.truth
                .as_ref()
                .map_or("n/a".into(), |t| sci(t.final_error_rad))
        }),
    ];
    let mut rows = rows.to_vec();
    if runs.iter().any(|r| r.load_step.is_some()) {
        rows.splice(5..5, step_rows);
    }
    if runs.iter().any(|r| r.truth.is_some()) {
        rows.splice(5..5, truth_rows);
    }
    let label_w = rows
        .iter()
        .map(|(l, _)| l.chars().count())
        .max()
        .unwrap_or(0)
        + 2;
    let col_w = 14;
    let mut out = String::new();
    let _ = write!(out, "{:label_w$}", "");
    for r in runs {
        let _ = write!(out, "{:>col_w$}", r.method);
    }
    out.push('\n');
    for (label, f) in rows.iter() {
        let pad = label_w - label.chars().count();
        let _ = write!(out, "{label}{:pad$}", "");
        for r in runs {
            let _ = write!(out, "{:>col_w$}", f(r));
        }
        out.push('\n');
    }
    for r in runs.iter().filter(|r| !r.axes.is_empty()) {
        // The columns above are axis 0's; each other axis gets a line of its own.
        let _ = writeln!(
            out,
            "\n{} axes (above: axis 0, {}):\n  {:>4} {:<10} {:>22} {:>14} {:>14} {:>14} {:>9} {:>8}",
            r.method,
            s.axis_name(0),
            "axis",
            "name",
            "outcome",
            "cruise max |e|",
            "max |e|",
            "final error",
            "samples",
            "faulted"
        );
        for a in &r.axes {
            let o = &a.report;
            let outcome = o.outcome.title().to_lowercase();
            let _ = writeln!(
                out,
                "  {:>4} {:<10} {:>22} {:>14} {:>14} {:>14} {:>9} {:>8}",
                a.axis,
                a.name,
                if o.complete {
                    outcome
                } else {
                    format!("{outcome}, incomplete")
                },
                sci(o.cruise_max_abs_error_rad),
                sci(o.max_abs_error_rad),
                sci(o.final_error_rad),
                o.samples,
                o.fault_samples
            );
        }
        let contour = std::iter::once(r.contour_peak_rad)
            .chain(r.axes.iter().map(|a| a.report.contour_peak_rad))
            .flatten()
            .reduce(f64::max);
        if let Some(c) = contour {
            let _ = writeln!(
                out,
                "  coordinated moves: peak contour error {} rad (the rotors' distance from \
                 the moves' straight lines)",
                sci(c)
            );
        }
    }
    for r in runs {
        // Every axis's moves; a multi-axis run's lines name their axis.
        let several = !r.axes.is_empty();
        let moves: Vec<_> = r
            .moves
            .iter()
            .map(|m| (0, m))
            .chain(
                r.axes
                    .iter()
                    .flat_map(|a| a.report.moves.iter().map(move |m| (a.axis, m))),
            )
            .collect();
        if moves.is_empty() {
            continue;
        }
        let _ = writeln!(
            out,
            "\n{} moves:\n  {}{:>3} {:>10} {:>14} {:>20} {:>16} {:>20}",
            r.method,
            if several { " axis " } else { "" },
            "#",
            "start [s]",
            "target [rad]",
            "duration [s]",
            "peak |e| [rad]",
            "settled 1e-4 [ms]"
        );
        let or_na = |v: Option<f64>, f: &dyn Fn(f64) -> String| v.map_or("n/a".into(), f);
        let mut number = 0;
        let mut last_axis = 0;
        for (axis, m) in moves {
            number = if axis == last_axis { number + 1 } else { 1 };
            last_axis = axis;
            let _ = writeln!(
                out,
                "  {}{:>3} {:>10.4} {:>14.6} {:>20} {:>16} {:>20}",
                if several {
                    format!("{axis:>5} ")
                } else {
                    String::new()
                },
                number,
                m.start_s,
                m.target_rad,
                match (m.retargeted_at_s, m.discarded) {
                    (Some(t), true) => format!("discarded {t:.4}"),
                    (Some(t), false) => format!("{} {t:.4}", replaced_word(m.replaced_by)),
                    (None, _) => or_na(m.duration_s, &|d| format!("{d:.4}")),
                },
                m.peak_abs_error_rad.map_or("n/a".into(), sci),
                or_na(m.settle_s, &|d| format!("{:.1}", d * 1e3)),
            );
        }
    }
    for r in runs {
        let Some(t) = &r.timing else { continue };
        let _ = writeln!(
            out,
            "\n{} realtime timing: deadline misses {} ({:.3} %; {} covered by a plan; {} runs, longest {} periods), late commands discarded {}, plant overruns {}",
            r.method,
            t.deadline_misses,
            t.deadline_miss_pct,
            t.misses_planned,
            t.miss_runs,
            t.longest_miss_run,
            // A drive discards late commands itself and tells no one: its own count says.
            if r.mode == "hardware" {
                "n/a (the drive counts them)".to_string()
            } else {
                t.late_commands_discarded.to_string()
            },
            t.plant.as_ref().map_or(0, |p| p.overruns)
        );
        if let Some(h) = &t.host_holds {
            let _ = writeln!(out, "  {}", h.describe());
        }
        if !t.resources.rss.is_empty() {
            let _ = writeln!(out, "  {}", t.resources.describe());
        }
        let line = |name: &str, p: Option<&crate::report::timing::Percentiles>| match p {
            Some(p) if p.count > 0 => format!(
                "  {name:<34} p50 {:>7.1} µs  p99 {:>7.1} µs  p99.9 {:>8.1} µs  max {:>9.1} µs\n",
                p.p50_us, p.p99_us, p.p99_9_us, p.max_us
            ),
            _ => String::new(),
        };
        if r.mode == "hardware" {
            let _ = writeln!(
                out,
                "  drive link: CRC errors {}, bad/duplicate/out-of-order frames {}, rejected commands {}, frames lost on the wire {}, samples superseded in the bridge {}",
                t.crc_errors,
                t.bad_frames,
                t.rejected_commands,
                t.frames_lost,
                t.samples_superseded
            );
            out += &line("round trip bridge → drive → bridge", t.round_trip.as_ref());
        }
        out += &line("sensor → actuator", t.sensor_to_actuator.as_ref());
        out += &line(
            "plant wake-up latency",
            t.plant.as_ref().map(|p| &p.wakeup_latency),
        );
        out += &line(
            "current-loop timer wake-up latency",
            t.current_loop.as_ref().map(|c| &c.wakeup_latency),
        );
        out += &line(
            "state hop (iceoryx2)",
            t.current_loop.as_ref().map(|c| &c.input_hop),
        );
        out += &line(
            "position-loop wake-up latency",
            t.position_loop.as_ref().map(|p| &p.wakeup_latency),
        );
    }
    if let Some(r) = runs
        .iter()
        .find(|r| r.wall_time_s > 0.0 && r.timing.is_none())
    {
        let _ = writeln!(
            out,
            "\nreal-time factor ({}): {:.1}× faster than real time",
            r.method,
            r.sim_time_s / r.wall_time_s
        );
    }
    // The paper's closed forms are about its experiment, the profile; a program's moves
    // are judged per move above.
    if s.runs_profile() {
        let _ = writeln!(
            out,
            "microstepping with ideal current tracking: cruise error ≈ {:.3e} rad (eq. 7 {:.3e} + load), final offset {:.3e} rad",
            expected_microstepping_cruise_error(s),
            s.eq7_bound_rad(),
            s.load_offset_rad()
        );
    }
    out
}

/// What a user must read first when a run did not go well: what happened, when, where, and
/// what to do. `None` for a run that went well.
pub fn headline(s: &Scenario, r: &RunReport) -> Option<String> {
    let code = r.outcome.exit_code();
    let stale = r.outcome == Outcome::ProcessDied
        && r.setpoint_stale_at_s.is_some()
        && r.stopped_because.is_none();
    // Nothing ran: no sample came (a drive that never answered or was refused, a process
    // that failed at start). Nothing died mid-run, and there are no figures.
    let never_ran = r.outcome == Outcome::ProcessDied && r.samples == 0;
    // No process died: one stopped answering and the current loop stood in for it.
    let title = if stale {
        "POSITION LOOP SILENT"
    } else if never_ran && r.mode == "hardware" {
        "NO DRIVE RUN"
    } else if never_ran {
        "DID NOT START"
    } else {
        r.outcome.title()
    };
    let method = &r.method;
    let what = match r.outcome {
        Outcome::Ok => return None,
        Outcome::Fault if r.fault.is_none() => {
            // The axis's own fault (the device is healthy): the envelope stopped it.
            let f = r.axis_fault.as_ref()?;
            format!(
                "the axis went to Fault ({}) at t = {:.4} s, following error {} rad; its \
                 outputs were off until a fault reset. What to do: a following error means \
                 the motor could not follow (a load beyond its torque, a move beyond its \
                 limits); see [axis] following_error_window_rad and following_error_time_s.",
                f.faults.join(", "),
                f.sim_time_s,
                sci(f.following_error_rad),
            )
        }
        Outcome::Fault => {
            let f = r.fault.as_ref()?;
            let off = match r.fault_cleared_at_s {
                Some(t) => format!(
                    "its outputs were off until a reset cleared it at t = {t:.4} s ({} faulted \
                     samples in the run)",
                    r.fault_samples
                ),
                None => format!(
                    "its outputs were off from then on ({} faulted samples)",
                    r.fault_samples
                ),
            };
            format!(
                "{} latched {} at t = {:.4} s (sample {}, seen {}); {off}. What to do: {}.",
                f.latched_by(&r.mode),
                f.faults.join(" and "),
                f.sim_time_s,
                f.sample,
                utc_time_of_day(f.seen_unix_s),
                f.advice()
            )
        }
        Outcome::SteppedOut => format!(
            "|θ_d − θ| passed one electrical period ({:.3e} rad) at t = {} s and reached {} \
             rad: the rotor slipped. What to do: check the scenario's speed, load and V_max \
             against the method (open-loop microstepping cannot follow once the back-EMF \
             K_m ω exceeds V_max).",
            step_out_threshold_rad(s),
            r.stepped_out_at_s
                .map_or("?".to_string(), |t| format!("{t:.4}")),
            sci(r.max_abs_error_rad),
        ),
        Outcome::Unobserved => {
            let seen = r
                .unobserved
                .as_deref()
                .unwrap_or("the monitor saw too little of the run");
            // Only a hardware run has a wire and a bridge to blame.
            let (lost, cause) = if r.mode == "hardware" {
                let wire = r.timing.as_ref().map_or(0, |t| t.frames_lost);
                (
                    format!(
                        "{wire} were lost on the wire; the rest the bridge skipped or the \
                         monitor's queue overwrote while the monitor had no CPU"
                    ),
                    "a drive process spinning at SCHED_FIFO on the plant's CPU leaves it none",
                )
            } else {
                (
                    "they came before this reader subscribed, or its queue overwrote them \
                     while it had no CPU"
                        .to_string(),
                    "the stack's loops at SCHED_FIFO leave an ordinary-priority reader little; \
                     an attached `record` or `monitor` takes --priority (below the loops') for \
                     that",
                )
            };
            format!(
                "{seen}: the figures above do not stand for the run. Of the {} samples it \
                 missed (the longest stretch {:.3} s), {lost}. What to do: leave the monitor CPU \
                 time ({cause}; see the deployment's CPUs), then run again.",
                r.missed_samples, r.longest_gap_s
            )
        }
        Outcome::ProcessDied if stale => {
            format!(
                "the position loop went silent at t = {:.3} s: no setpoint for more than {:.1} \
                 ms ([axis] setpoint_age_ticks {} of its {} Hz periods). The current loop \
                 brought the motor to a standstill at the quick-stop rate ({} rad/s²) and held \
                 it while the trajectory went on ({} rad from it at the end: the motor held, \
                 not a step-out). What to do: find what stopped the position loop (a stop \
                 signal, a debugger, a host that starved it).",
                r.setpoint_stale_at_s.unwrap_or(f64::NAN),
                f64::from(s.axis.setpoint_age_ticks) / s.rates.position_loop_hz * 1e3,
                s.axis.setpoint_age_ticks,
                s.rates.position_loop_hz,
                s.axis.quick_stop_decel_rad_s2,
                sci(r.final_error_rad),
            )
        }
        Outcome::ProcessDied if never_ran => format!(
            "{}; no sample ran, so there are no figures.",
            r.stopped_because
                .as_deref()
                .unwrap_or("stopped before its first sample"),
        ),
        Outcome::ProcessDied | Outcome::Interrupted => format!(
            "{} after {:.3} s{} simulated. The figures above cover what ran (marked \
             incomplete).",
            r.stopped_because.as_deref().unwrap_or("stopped"),
            r.sim_time_s,
            // A served stack runs until stopped: there is no length to compare with.
            if s.run.until_stopped {
                String::new()
            } else {
                format!(" of {:.3} s", s.duration_s())
            }
        ),
    };
    Some(format!("{title} (exit {code}) in the {method} run: {what}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::metrics::Metrics;
    use stepdrive_shared::messages::DriveState;

    /// Issue 22, finding 10: a drive that never answered gave "PROCESS DIED" and a table of
    /// n/a and NaN. A run that never produced a sample says so, and draws no table.
    #[test]
    fn a_run_that_never_started_says_so_and_draws_no_table_of_nans() {
        let s = Scenario::default();
        let why = "the bridge failed: the drive at udp://127.0.0.1:9 sent no usable CONFIG";
        let never = Metrics::new(&s).finish_early(
            stepdrive_shared::Method::Proposed,
            "hardware",
            0.0,
            Outcome::ProcessDied,
            why.to_string(),
        );
        let h = headline(&s, &never).expect("a headline");
        assert!(
            h.starts_with("NO DRIVE RUN (exit 5) in the proposed run: "),
            "{h}"
        );
        assert!(h.contains(why) && h.contains("no sample ran"), "{h}");
        assert!(table(&s, std::slice::from_ref(&never)).starts_with("no figures: no sample ran"));
        // A process that died mid-run is still PROCESS DIED, with its figures.
        let mut m = Metrics::new(&s);
        for k in 0..100 {
            m.push(&DriveState {
                seq: k,
                sample_time_s: k as f64 / s.rates.current_loop_hz,
                ..Default::default()
            });
        }
        let died = m.finish_early(
            stepdrive_shared::Method::Proposed,
            "realtime",
            0.1,
            Outcome::ProcessDied,
            "the current loop process exited".to_string(),
        );
        let h = headline(&s, &died).expect("a headline");
        assert!(h.starts_with("PROCESS DIED (exit 5)"), "{h}");
        assert!(table(&s, &[never, died]).contains("max |e|, whole run"));
    }
}
