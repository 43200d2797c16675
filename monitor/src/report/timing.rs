//! Timing figures of a realtime run, from the processes' own fixed-size histograms.

use serde::Serialize;
use stepdrive_runtime::steal::HOST_HOLD_MIN_NS;
use stepdrive_shared::stats::{Histogram, StatsReport};
use stepdrive_shared::Scenario;

/// Summary of one histogram in µs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Percentiles {
    pub count: u64,
    pub min_us: f64,
    pub p50_us: f64,
    pub p90_us: f64,
    pub p99_us: f64,
    pub p99_9_us: f64,
    pub p99_99_us: f64,
    pub max_us: f64,
    pub mean_us: f64,
}

impl Percentiles {
    pub fn of(h: &Histogram) -> Self {
        let q = |p: f64| h.quantile_ns(p).map_or(f64::NAN, |v| v as f64 / 1000.0);
        Self {
            count: h.count,
            min_us: if h.count == 0 {
                f64::NAN
            } else {
                h.min_ns as f64 / 1000.0
            },
            p50_us: q(0.5),
            p90_us: q(0.9),
            p99_us: q(0.99),
            p99_9_us: q(0.999),
            p99_99_us: q(0.9999),
            max_us: if h.count == 0 {
                f64::NAN
            } else {
                h.max_ns as f64 / 1000.0
            },
            mean_us: h.mean_ns() / 1000.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopTiming {
    pub cycles: u64,
    pub misses: u64,
    pub miss_pct: f64,
    pub overruns: u64,
    pub lost: u64,
    pub period: Percentiles,
    pub wakeup_latency: Percentiles,
    pub compute: Percentiles,
    /// Publish → receive of the loop's main input (plant: commands, taken at its next
    /// period; current loop: states, while polling; position loop: newest state at its tick).
    pub input_hop: Percentiles,
}

impl LoopTiming {
    /// `deadlines`: deadlines a cycle has (a multi-axis plant: one per axis).
    fn of(r: &StatsReport, deadlines: u64) -> Self {
        Self {
            cycles: r.cycles,
            misses: r.misses,
            miss_pct: if r.cycles == 0 {
                f64::NAN
            } else {
                100.0 * r.misses as f64 / (r.cycles * deadlines) as f64
            },
            overruns: r.overruns,
            lost: r.lost,
            period: Percentiles::of(&r.period),
            wakeup_latency: Percentiles::of(&r.wakeup),
            compute: Percentiles::of(&r.compute),
            input_hop: Percentiles::of(&r.hop),
        }
    }
}

/// Cycles in which the hypervisor held the current loop's vCPU (wall time passed while the
/// loop neither ran, nor waited in the guest's run queue, nor slept: see
/// `stepdrive_runtime::steal`), and the deadline misses they explain.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HostHolds {
    /// Holds of at least [`HOST_HOLD_MIN_NS`] (20 µs).
    pub count: u64,
    pub total_ms: f64,
    pub longest_us: f64,
    /// Deadline misses whose states the loop never saw because of a hold.
    pub deadline_misses_in_holds: u64,
    /// Of the rest, misses while the loop waited for its CPU behind another guest task.
    pub deadline_misses_queued: u64,
    /// The rest: the misses the guest (scheduler, interrupts, the stack) is answerable for.
    pub deadline_misses_outside_holds: u64,
    pub deadline_miss_pct_outside_holds: f64,
}

impl HostHolds {
    /// One line for the tables.
    pub fn describe(&self) -> String {
        format!(
            "current loop's CPU held by the host {} times (≥ {} µs; {:.1} ms in all, longest {:.0} µs); deadline misses in those holds {}, outside them {} ({:.3} %; {} of them queued behind a guest task)",
            self.count,
            HOST_HOLD_MIN_NS / 1000,
            self.total_ms,
            self.longest_us,
            self.deadline_misses_in_holds,
            self.deadline_misses_outside_holds,
            self.deadline_miss_pct_outside_holds,
            self.deadline_misses_queued
        )
    }

    /// `axes`: a multi-axis plant's misses are its axes' (a period per axis).
    fn of(current: &StatsReport, plant: &StatsReport, axes: u64) -> Self {
        let h = &current.host_held;
        let outside = plant.misses.saturating_sub(current.host_missed);
        Self {
            count: h.count,
            total_ms: h.sum_ns as f64 * 1e-6,
            longest_us: h.max_ns as f64 * 1e-3,
            deadline_misses_in_holds: current.host_missed.min(plant.misses),
            deadline_misses_queued: current.queued_missed.min(outside),
            deadline_misses_outside_holds: outside,
            deadline_miss_pct_outside_holds: 100.0 * outside as f64
                / (plant.cycles * axes).max(1) as f64,
        }
    }
}

/// The timing section of a realtime run's report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TimingReport {
    pub current_loop_hz: f64,
    /// Periods in which the plant had no command and held the previous one: the current
    /// loop's deadline misses as the motor sees them.
    pub deadline_misses: u64,
    pub deadline_miss_pct: f64,
    /// Of the misses, periods the plant covered with the freshest command's voltage plan
    /// (the rest held the previous voltage).
    pub misses_planned: u64,
    /// Runs of consecutive misses (times the current loop was away) and the longest, periods.
    pub miss_runs: u64,
    pub longest_miss_run: u64,
    /// Commands that arrived after their period and were dropped unapplied.
    pub late_commands_discarded: u64,
    /// State sample published → answering command published.
    pub sensor_to_actuator: Option<Percentiles>,
    pub plant: Option<LoopTiming>,
    pub current_loop: Option<LoopTiming>,
    pub position_loop: Option<LoopTiming>,
    /// State samples the (low-rate) monitor did not see.
    pub monitor_lost_samples: u64,
    /// Hardware mode: frames from the drive dropped for a CRC mismatch / as malformed,
    /// duplicate or out of order; commands not sent (non-finite or beyond the bus).
    pub crc_errors: u64,
    pub bad_frames: u64,
    pub rejected_commands: u64,
    /// Hardware mode: samples that never arrived (gaps in the drive's frame sequence), and
    /// samples that arrived but were superseded before the bridge published them.
    pub frames_lost: u64,
    pub samples_superseded: u64,
    /// Hardware mode: command frame sent → reported applied by the drive.
    pub round_trip: Option<Percentiles>,
    /// Realtime mode: the current loop's account of its vCPU held by the host.
    pub host_holds: Option<HostHolds>,
    /// What the processes used: their memory at the start and end of the run, and the
    /// deadline misses of each minute (a long run's health at a glance).
    pub resources: Resources,
    #[serde(skip)]
    pub raw: [Option<Box<StatsReport>>; 3],
}

/// A process's resident memory at the start and the end of a run, KiB.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Rss {
    pub process: String,
    pub start_kib: u64,
    pub end_kib: u64,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Resources {
    pub rss: Vec<Rss>,
    /// The plant's deadline misses in each whole minute of the run.
    pub misses_per_minute: Vec<u64>,
}

impl Resources {
    /// One line for the tables.
    pub fn describe(&self) -> String {
        let rss: Vec<String> = self
            .rss
            .iter()
            .map(|r| {
                format!(
                    "{} {:.1}→{:.1}",
                    r.process,
                    r.start_kib as f64 / 1024.0,
                    r.end_kib as f64 / 1024.0
                )
            })
            .collect();
        let mut line = format!("RSS at start→end [MiB]: {}", rss.join(", "));
        if !self.misses_per_minute.is_empty() {
            line += &format!("; deadline misses per minute: {:?}", self.misses_per_minute);
        }
        line
    }
}

/// Resident memory of process `pid`, KiB (`VmRSS` in `/proc/<pid>/status`).
pub fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

impl TimingReport {
    pub fn new(
        s: &Scenario,
        plant: Option<Box<StatsReport>>,
        current: Option<Box<StatsReport>>,
        position: Option<Box<StatsReport>>,
        monitor_lost: u64,
        host_holds_measured: bool,
    ) -> Self {
        // A multi-axis plant misses per axis: a period of each axis is one deadline.
        let axes = s.axis_count() as u64;
        let (misses, pct) = plant.as_ref().map_or((0, f64::NAN), |p| {
            (
                p.misses,
                100.0 * p.misses as f64 / (p.cycles * axes).max(1) as f64,
            )
        });
        let counter = |f: fn(&StatsReport) -> u64| plant.as_deref().map_or(0, f);
        Self {
            current_loop_hz: s.rates.current_loop_hz,
            deadline_misses: misses,
            deadline_miss_pct: pct,
            misses_planned: counter(|p| p.planned),
            miss_runs: counter(|p| p.miss_runs),
            longest_miss_run: counter(|p| p.longest_miss_run),
            late_commands_discarded: counter(|p| p.late_discarded),
            sensor_to_actuator: plant
                .as_ref()
                .map(|p| Percentiles::of(&p.sensor_to_actuator)),
            plant: plant.as_deref().map(|p| LoopTiming::of(p, axes)),
            current_loop: current.as_deref().map(|c| LoopTiming::of(c, 1)),
            position_loop: position.as_deref().map(|q| LoopTiming::of(q, 1)),
            monitor_lost_samples: monitor_lost,
            crc_errors: counter(|p| p.crc_errors),
            bad_frames: counter(|p| p.bad_frames),
            rejected_commands: counter(|p| p.rejected_commands),
            frames_lost: counter(|p| p.lost),
            samples_superseded: counter(|p| p.superseded),
            round_trip: plant
                .as_ref()
                .filter(|p| p.round_trip.count > 0)
                .map(|p| Percentiles::of(&p.round_trip)),
            host_holds: match (&current, &plant) {
                (Some(c), Some(p)) if host_holds_measured => Some(HostHolds::of(c, p, axes)),
                _ => None,
            },
            resources: Resources::default(),
            raw: [plant, current, position],
        }
    }
}
