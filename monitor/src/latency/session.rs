//! `stepdrive latency`: the measurement session. Runs the live stack in realtime mode, then
//! the baselines at the same interval, priority and CPU (bare iceoryx2 and Unix-socket
//! ping-pong with the current loop's wait strategy, and cyclictest when installed), prints
//! one table, and writes latency.json, cyclictest-compatible histograms and a log-y plot.

use crate::latency::histfile::{cyclictest_file, CyclictestHistogram, SparseHistogram};
use crate::latency::pingpong::Transport;
use crate::report::metrics::RunReport;
use crate::report::timing::Percentiles;
use crate::supervise::children::Supervised;
use crate::supervise::launcher::{run_stack, LaunchOptions};
use anyhow::{bail, Context, Result};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use stepdrive_shared::stack::Role;
use stepdrive_shared::stats::Histogram;
use stepdrive_shared::{Method, Scenario};

#[derive(Debug, Clone)]
pub struct LatencyOptions {
    pub out: PathBuf,
    pub baseline_duration: Duration,
    pub launch: LaunchOptions,
    pub skip_baselines: bool,
}

/// One measured distribution.
#[derive(Debug, Clone, Serialize)]
pub struct Metric {
    pub name: String,
    pub what: String,
    pub file: String,
    #[serde(flatten)]
    pub percentiles: Percentiles,
    #[serde(skip)]
    pub histogram: Box<Histogram>,
}

#[derive(Debug, Serialize)]
pub struct Ratios {
    pub current_loop_wakeup_p50_vs_cyclictest: Option<f64>,
    pub current_loop_wakeup_p99_vs_cyclictest: Option<f64>,
    pub state_hop_p50_vs_iceoryx2_pingpong: Option<f64>,
    pub state_hop_p50_vs_uds_pingpong: Option<f64>,
}

#[derive(Debug, Serialize)]
pub struct LatencyReport {
    pub interval_us: f64,
    pub run: RunReport,
    pub metrics: Vec<Metric>,
    pub ratios: Ratios,
    pub notes: Vec<String>,
}

fn metric(name: &str, what: &str, h: &Histogram) -> Metric {
    Metric {
        name: name.to_string(),
        what: what.to_string(),
        file: format!("{name}.hist"),
        percentiles: Percentiles::of(h),
        histogram: Box::new(*h),
    }
}

fn find(metrics: &[Metric], name: &str) -> Option<Percentiles> {
    metrics
        .iter()
        .find(|m| m.name == name)
        .map(|m| m.percentiles)
}

fn ratio(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b > 0.0 && a.is_finite() => Some(a / b),
        _ => None,
    }
}

/// Runs a ping-pong baseline over `transport` and returns the pong side's one-way latency.
/// The pong side is placed and waits like the current loop, the ping side is placed like
/// the plant (the deployment file the run used).
fn pingpong(
    transport: Transport,
    o: &LatencyOptions,
    period_ns: u64,
    out_dir: &Path,
) -> Result<Histogram> {
    let transport_name = transport.as_str();
    let endpoint = format!("{}-pp-{transport_name}", o.launch.instance);
    let file = out_dir.join(format!(".pong-{transport_name}.json"));
    let deploy = out_dir.join(".deploy.toml");
    std::fs::write(&deploy, o.launch.deployment.to_toml_string())
        .with_context(|| format!("cannot write {}", deploy.display()))?;
    let common = |role: &str| {
        vec![
            "--transport".to_string(),
            transport_name.to_string(),
            "--role".to_string(),
            role.to_string(),
            "--endpoint".to_string(),
            endpoint.clone(),
            "--period-us".to_string(),
            (period_ns as f64 / 1000.0).to_string(),
            "--duration".to_string(),
            o.baseline_duration.as_secs_f64().to_string(),
            "--deploy".to_string(),
            deploy.display().to_string(),
        ]
    };
    let mut pong_args = common("pong");
    pong_args.extend(["--out".to_string(), file.display().to_string()]);
    let mut pong = Supervised::spawn(Role::Tool("pingpong"), &pong_args)?;
    let mut ping = Supervised::spawn(Role::Tool("pingpong"), &common("ping"))?;
    let limit = o.baseline_duration + Duration::from_secs(40);
    let ps = ping.finish(limit);
    let qs = pong.finish(Duration::from_secs(10));
    let _ = std::fs::remove_file(&deploy);
    if !ps.success() {
        bail!("{transport_name} ping-pong: {}", ping.describe_failure(ps));
    }
    if !qs.success() {
        bail!("{transport_name} ping-pong: {}", pong.describe_failure(qs));
    }
    let text = std::fs::read_to_string(&file)
        .with_context(|| format!("no result from the {transport_name} pong side"))?;
    let _ = std::fs::remove_file(&file);
    let sparse: SparseHistogram = serde_json::from_str(&text)?;
    sparse.to_histogram().map_err(anyhow::Error::msg)
}

/// Runs cyclictest at the current loop's interval, priority and CPU, if it is installed.
fn cyclictest(o: &LatencyOptions, period_ns: u64, out_dir: &Path) -> Result<Option<Histogram>> {
    let found = std::process::Command::new("cyclictest")
        .arg("--help")
        .output()
        .is_ok();
    if !found {
        return Ok(None);
    }
    let hist_file = out_dir.join("cyclictest.raw");
    let mut cmd = std::process::Command::new("cyclictest");
    cmd.args(["-q", "-m", "-h", "2000"])
        .arg(format!("-i{}", (period_ns / 1000).max(1)))
        .arg(format!("-D{}s", o.baseline_duration.as_secs().max(1)))
        .arg(format!("--histfile={}", hist_file.display()));
    let current = &o.launch.deployment.current_loop;
    if let Some(p) = current.priority.filter(|&p| p > 0) {
        cmd.arg(format!("-p{p}"));
    }
    if let Some(c) = current.cpu {
        cmd.arg(format!("-a{c}"));
    }
    let out = cmd.output().context("cannot run cyclictest")?;
    if !out.status.success() {
        bail!(
            "cyclictest failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let text = std::fs::read_to_string(&hist_file)
        .with_context(|| format!("cyclictest wrote no {}", hist_file.display()))?;
    let _ = std::fs::remove_file(&hist_file);
    let parsed = CyclictestHistogram::parse(&text).map_err(anyhow::Error::msg)?;
    // Rebuild a histogram from its 1 µs bins (values at bin centres) so it sits in the same
    // table and plot as ours.
    let mut h = Histogram::default();
    for (us, &c) in parsed.bins.iter().enumerate() {
        for _ in 0..c {
            h.record(us as u64 * 1000 + 500);
        }
    }
    for _ in 0..parsed.overflows {
        h.record(parsed.max_us * 1000);
    }
    h.min_ns = parsed.min_us * 1000;
    h.max_ns = parsed.max_us * 1000;
    Ok(Some(h))
}

pub fn run_latency(s: &Scenario, o: &LatencyOptions) -> Result<LatencyReport> {
    std::fs::create_dir_all(&o.out)
        .with_context(|| format!("cannot create {}", o.out.display()))?;
    let period_ns = s.sample_period_ns();
    let mut notes = Vec::new();
    tracing::info!(
        "latency session: {:.0} s realtime stack run, then baselines of {:.0} s each",
        s.duration_s(),
        o.baseline_duration.as_secs_f64()
    );
    let started = Instant::now();
    let run =
        run_stack(s, Method::Proposed, &o.launch, None, None).context("the stack run failed")?;
    let timing = run
        .timing
        .as_ref()
        .context("the realtime run returned no timing")?;
    let mut metrics = Vec::new();
    if let Some(p) = timing.raw[0].as_deref() {
        metrics.push(metric(
            "plant_wakeup",
            "plant: wake-up latency against its absolute deadline",
            &p.wakeup,
        ));
        metrics.push(metric(
            "plant_period",
            "plant: actual sample interval",
            &p.period,
        ));
        metrics.push(metric(
            "sensor_to_actuator",
            "sample published → answering command published",
            &p.sensor_to_actuator,
        ));
        metrics.push(metric(
            "command_hop",
            "command published → taken by the plant at its next period",
            &p.hop,
        ));
    }
    if let Some(c) = timing.raw[1].as_deref() {
        metrics.push(metric(
            "current_loop_wakeup",
            "current loop: timer wake-up latency (hybrid sleep)",
            &c.wakeup,
        ));
        metrics.push(metric(
            "current_loop_compute",
            "current loop: state taken → command published",
            &c.compute,
        ));
        metrics.push(metric(
            "state_hop",
            "state published → taken by the current loop (iceoryx2 hop)",
            &c.hop,
        ));
    }
    if let Some(p) = timing.raw[2].as_deref() {
        metrics.push(metric(
            "position_loop_wakeup",
            "position loop: wake-up latency (2 kHz clock)",
            &p.wakeup,
        ));
    }
    if o.skip_baselines {
        notes.push("baselines skipped (--skip-baselines)".into());
    } else {
        for transport in [Transport::Iceoryx2, Transport::Uds] {
            let name = transport.as_str();
            tracing::info!("baseline: {name} ping-pong");
            match pingpong(transport, o, period_ns, &o.out) {
                Ok(h) => metrics.push(metric(
                    &format!("pingpong_{name}"),
                    &format!(
                        "bare {name} ping-pong: one-way latency, same payload and wait strategy"
                    ),
                    &h,
                )),
                Err(e) => notes.push(format!("{name} ping-pong failed: {e:#}")),
            }
        }
        tracing::info!("baseline: cyclictest");
        match cyclictest(o, period_ns, &o.out) {
            Ok(Some(h)) => metrics.push(metric(
                "cyclictest",
                "cyclictest: timer wake-up latency, same interval, priority and CPU",
                &h,
            )),
            Ok(None) => notes.push(
                "cyclictest not installed (Debian: apt-get install rt-tests); baseline skipped"
                    .into(),
            ),
            Err(e) => notes.push(format!("cyclictest: {e:#}")),
        }
    }
    let p50 = |n: &str| find(&metrics, n).map(|p| p.p50_us);
    let p99 = |n: &str| find(&metrics, n).map(|p| p.p99_us);
    let ratios = Ratios {
        current_loop_wakeup_p50_vs_cyclictest: ratio(p50("current_loop_wakeup"), p50("cyclictest")),
        current_loop_wakeup_p99_vs_cyclictest: ratio(p99("current_loop_wakeup"), p99("cyclictest")),
        state_hop_p50_vs_iceoryx2_pingpong: ratio(p50("state_hop"), p50("pingpong_iceoryx2")),
        state_hop_p50_vs_uds_pingpong: ratio(p50("state_hop"), p50("pingpong_uds")),
    };
    let report = LatencyReport {
        interval_us: period_ns as f64 / 1000.0,
        run,
        metrics,
        ratios,
        notes,
    };
    write_files(&report, &o.out)?;
    tracing::info!(
        "latency session took {:.0} s",
        started.elapsed().as_secs_f64()
    );
    Ok(report)
}

fn write_files(r: &LatencyReport, dir: &Path) -> Result<()> {
    for m in &r.metrics {
        std::fs::write(dir.join(&m.file), cyclictest_file(&m.histogram, 2000))?;
    }
    std::fs::write(
        dir.join("latency.json"),
        serde_json::to_string_pretty(r)? + "\n",
    )?;
    std::fs::write(dir.join("latency.svg"), svg_plot(r))?;
    Ok(())
}

pub fn table(r: &LatencyReport) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<22}{:>9}{:>9}{:>9}{:>9}{:>9}{:>10}{:>10}{:>11}",
        "latency [µs]", "min", "p50", "p90", "p99", "p99.9", "p99.99", "max", "count"
    );
    for m in &r.metrics {
        let p = &m.percentiles;
        let _ = writeln!(
            out,
            "{:<22}{:>9.1}{:>9.1}{:>9.1}{:>9.1}{:>9.1}{:>10.1}{:>10.1}{:>11}",
            m.name,
            p.min_us,
            p.p50_us,
            p.p90_us,
            p.p99_us,
            p.p99_9_us,
            p.p99_99_us,
            p.max_us,
            p.count
        );
    }
    if let Some(t) = &r.run.timing {
        let _ = writeln!(
            out,
            "\ndeadline misses (command not there for its period): {} of {} ({:.3} %; {} covered by a plan; {} runs, longest {} periods), late commands discarded {}",
            t.deadline_misses,
            t.plant.as_ref().map_or(0, |p| p.cycles),
            t.deadline_miss_pct,
            t.misses_planned,
            t.miss_runs,
            t.longest_miss_run,
            t.late_commands_discarded
        );
        if let Some(p) = &t.plant {
            let _ = writeln!(
                out,
                "plant overruns (host held the plant past a period; its time paused): {}",
                p.overruns
            );
        }
        if let Some(c) = &t.current_loop {
            let _ = writeln!(
                out,
                "current loop: answers after the nominal deadline {} ({:.3} %), states not seen {}",
                c.misses, c.miss_pct, c.lost
            );
        }
        if let Some(h) = &t.host_holds {
            let _ = writeln!(out, "{}", h.describe());
        }
    }
    let rr = &r.ratios;
    let f = |x: Option<f64>| x.map_or("n/a".to_string(), |v| format!("{v:.2}×"));
    let _ = writeln!(
        out,
        "ratios: current-loop wake-up vs cyclictest p50 {}, p99 {}; state hop p50 vs iceoryx2 ping-pong {}, vs UDS ping-pong {}",
        f(rr.current_loop_wakeup_p50_vs_cyclictest),
        f(rr.current_loop_wakeup_p99_vs_cyclictest),
        f(rr.state_hop_p50_vs_iceoryx2_pingpong),
        f(rr.state_hop_p50_vs_uds_pingpong)
    );
    for n in &r.notes {
        let _ = writeln!(out, "note: {n}");
    }
    out
}

/// Distributions drawn in the plot: the latencies that share one scale (periods, the
/// plant's command pick-up and the 2 kHz loop are in the table and files, not the plot).
const PLOTTED: [&str; 7] = [
    "cyclictest",
    "current_loop_wakeup",
    "plant_wakeup",
    "sensor_to_actuator",
    "state_hop",
    "pingpong_iceoryx2",
    "pingpong_uds",
];

/// Log-y latency histogram in the OSADL style: x = latency (µs, 1 µs bins), y = samples.
fn svg_plot(r: &LatencyReport) -> String {
    let plotted: Vec<&Metric> = PLOTTED
        .iter()
        .filter_map(|n| r.metrics.iter().find(|m| m.name == *n))
        .collect();
    let (w, h, left, bottom, top, right) = (900.0, 520.0, 70.0, 50.0, 30.0, 260.0);
    let plot_w = w - left - right;
    let plot_h = h - top - bottom;
    let x_max = plotted
        .iter()
        .map(|m| m.percentiles.p99_9_us)
        .filter(|v| v.is_finite())
        .fold(50.0f64, f64::max)
        .min(1000.0)
        .ceil();
    let bins = x_max as usize + 1;
    let y_max = plotted
        .iter()
        .flat_map(|m| m.histogram.microsecond_bins(bins).0)
        .max()
        .unwrap_or(1)
        .max(10) as f64;
    let decades = y_max.log10().ceil();
    let colors = [
        "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
        "#17becf", "#bcbd22",
    ];
    let x_of = |us: f64| left + plot_w * us / x_max;
    let y_of = |c: f64| top + plot_h * (1.0 - (c.max(1.0).log10() / decades));
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        s,
        r#"<text x="{}" y="18" font-size="14">stepdrive latency, {:.0} µs interval (log scale)</text>"#,
        left, r.interval_us
    );
    for d in 0..=decades as i32 {
        let y = y_of(10f64.powi(d));
        let _ = writeln!(
            s,
            r##"<line x1="{left}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" text-anchor="end">1e{d}</text>"##,
            left + plot_w,
            left - 6.0,
            y + 4.0
        );
    }
    let step = [10.0, 20.0, 50.0, 100.0, 200.0, 500.0]
        .into_iter()
        .find(|st| x_max / st <= 10.0)
        .unwrap_or(500.0);
    let mut x = 0.0;
    while x <= x_max {
        let px = x_of(x);
        let _ = writeln!(
            s,
            r##"<line x1="{px:.1}" y1="{top}" x2="{px:.1}" y2="{:.1}" stroke="#eee"/><text x="{px:.1}" y="{:.1}" text-anchor="middle">{x:.0}</text>"##,
            top + plot_h,
            top + plot_h + 16.0
        );
        x += step;
    }
    let _ = writeln!(
        s,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">latency [µs]</text>"#,
        left + plot_w / 2.0,
        h - 10.0
    );
    let _ = writeln!(
        s,
        r#"<text transform="translate(16,{:.1}) rotate(-90)" text-anchor="middle">samples</text>"#,
        top + plot_h / 2.0
    );
    let _ = writeln!(
        s,
        r##"<rect x="{left}" y="{top}" width="{plot_w}" height="{plot_h}" fill="none" stroke="#333"/>"##
    );
    for (i, m) in plotted.iter().enumerate() {
        let color = colors[i % colors.len()];
        let (counts, _) = m.histogram.microsecond_bins(bins);
        let mut pts = String::new();
        for (us, &c) in counts.iter().enumerate() {
            let y = if c == 0 { top + plot_h } else { y_of(c as f64) };
            let _ = write!(
                pts,
                "{:.1},{:.1} {:.1},{:.1} ",
                x_of(us as f64),
                y,
                x_of(us as f64 + 1.0).min(left + plot_w),
                y
            );
        }
        let _ = writeln!(
            s,
            r#"<polyline points="{pts}" fill="none" stroke="{color}" stroke-width="1.2"/>"#
        );
        let ly = top + 14.0 + 18.0 * i as f64;
        let _ = writeln!(
            s,
            r#"<line x1="{:.1}" y1="{ly:.1}" x2="{:.1}" y2="{ly:.1}" stroke="{color}" stroke-width="3"/><text x="{:.1}" y="{:.1}">{} (p99 {:.1})</text>"#,
            w - right + 10.0,
            w - right + 30.0,
            w - right + 36.0,
            ly + 4.0,
            m.name,
            m.percentiles.p99_us
        );
    }
    s.push_str("</svg>\n");
    s
}
