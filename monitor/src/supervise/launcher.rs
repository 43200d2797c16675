//! Launches the plant, the position loop and the current loop as separate processes (this
//! same binary with a role sub-command), supervises them, and collects the plant's state
//! stream for the metrics. Every child reads the same scenario and deployment files, so a
//! launched stack behaves like one started by hand with those files. Every child is killed
//! and reaped on any exit path (drop guard), children die with us (PR_SET_PDEATHSIG), and
//! dead nodes' shared memory is removed.

use crate::record::recording::Recording;
use crate::report::metrics::{Metrics, RunReport, TruthReport};
use crate::report::outcome::Outcome;
use crate::report::timing::{rss_kib, Resources, Rss, TimingReport};
use anyhow::{Context, Result};
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use stepdrive_emulated_drive::truth::TruthRow;
use stepdrive_runtime::deploy::{Deployment, Process};
use stepdrive_runtime::ipc::{cleanup_dead_nodes, IpcBus, IpcSubscriber, Stamp};
use stepdrive_runtime::poll::termination_requested;
use stepdrive_runtime::port::Subscribe;
use stepdrive_shared::messages::{
    state_flags, DriveCommand, DrivePlan, DriveState, TorqueSetpoint,
};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{LOOP_BUFFER, MONITOR_BUFFER};
use stepdrive_shared::stats::{roles, StatsReport};
use stepdrive_shared::{Method, Scenario};

#[derive(Debug, Clone)]
pub struct LaunchOptions {
    pub instance: String,
    pub mode: Mode,
    /// How every process runs; in hardware mode without `drive.address` an emulated drive
    /// is started on loopback.
    pub deployment: Deployment,
}

/// A child process that is terminated and reaped when dropped.
pub(crate) struct Supervised {
    role: &'static str,
    child: Child,
    last_error: Arc<Mutex<Option<String>>>,
    status: Option<ExitStatus>,
    forwarder: Option<std::thread::JoinHandle<()>>,
}

impl Supervised {
    pub(crate) fn spawn(role: &'static str, args: &[String]) -> Result<Self> {
        let exe = std::env::current_exe().context("cannot locate the stepdrive executable")?;
        let mut cmd = Command::new(exe);
        cmd.arg(role)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        if std::env::var_os("RUST_LOG").is_none() {
            cmd.env("RUST_LOG", "warn");
        }
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            cmd.pre_exec(|| {
                // Die with the launcher even if it is SIGKILLed: no orphan loops.
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = cmd
            .spawn()
            .with_context(|| format!("cannot start the {role} process"))?;
        let last_error = Arc::new(Mutex::new(None));
        let forwarder = child.stderr.take().map(|stderr| {
            let last_error = Arc::clone(&last_error);
            std::thread::spawn(move || {
                for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                    eprintln!("[{role}] {line}");
                    if let Some(msg) = line.strip_prefix("error: ") {
                        if let Ok(mut slot) = last_error.lock() {
                            *slot = Some(msg.to_string());
                        }
                    }
                }
            })
        });
        tracing::debug!(role, pid = child.id(), "started");
        Ok(Self {
            role,
            child,
            last_error,
            status: None,
            forwarder,
        })
    }

    fn poll_exit(&mut self) -> Result<Option<ExitStatus>> {
        if self.status.is_none() {
            self.status = self
                .child
                .try_wait()
                .with_context(|| format!("cannot query the {role} process", role = self.role))?;
        }
        Ok(self.status)
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    pub(crate) fn role(&self) -> &'static str {
        self.role
    }

    pub(crate) fn signal(&self, sig: libc::c_int) {
        if self.status.is_none() {
            // SAFETY: plain kill(2) on our own, not yet reaped child.
            unsafe { libc::kill(self.child.id() as libc::pid_t, sig) };
        }
    }

    /// Waits up to `timeout` for a voluntary exit, then SIGTERM, then SIGKILL.
    pub(crate) fn finish(&mut self, timeout: Duration) -> ExitStatus {
        let exited = |c: &mut Child, within: Duration| -> Option<ExitStatus> {
            let deadline = Instant::now() + within;
            loop {
                match c.try_wait() {
                    Ok(Some(status)) => return Some(status),
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(2))
                    }
                    _ => return None,
                }
            }
        };
        if self.status.is_none() {
            self.status = exited(&mut self.child, timeout).or_else(|| {
                tracing::warn!(role = self.role, "did not exit in time; sending SIGTERM");
                self.signal(libc::SIGTERM);
                exited(&mut self.child, Duration::from_secs(1)).or_else(|| {
                    let _ = self.child.kill();
                    self.child.wait().ok()
                })
            });
        }
        if let Some(f) = self.forwarder.take() {
            let _ = f.join();
        }
        // Unknown only if the child could not be waited for: report failure, never guess success.
        self.status.unwrap_or_else(|| {
            use std::os::unix::process::ExitStatusExt;
            ExitStatus::from_raw(1 << 8)
        })
    }

    pub(crate) fn describe_failure(&self, status: ExitStatus) -> String {
        let detail = self
            .last_error
            .lock()
            .ok()
            .and_then(|e| e.clone())
            .unwrap_or_else(|| "no error message (see its log above)".to_string());
        format!("the {} process exited with {status}: {detail}", self.role)
    }
}

impl Drop for Supervised {
    fn drop(&mut self) {
        if self.status.is_none() {
            self.signal(libc::SIGTERM);
            let deadline = Instant::now() + Duration::from_secs(2);
            while Instant::now() < deadline {
                if let Ok(Some(_)) = self.child.try_wait() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The scenario and deployment as the children read them: a private directory, removed as
/// soon as every child has read it (when the first sample arrives) and when dropped. A
/// launcher killed before then leaves it; the next launch removes such leftovers.
struct RunFiles {
    dir: PathBuf,
}

/// The prefix of a run's directory: `stepdrive-<launcher pid>-<instance>`.
const RUN_DIR_PREFIX: &str = "stepdrive-";

impl RunFiles {
    fn write(s: &Scenario, d: &Deployment, instance: &str) -> Result<Self> {
        Self::remove_leftovers();
        let dir =
            std::env::temp_dir().join(format!("{RUN_DIR_PREFIX}{}-{instance}", std::process::id()));
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let files = Self { dir };
        let write = |path: PathBuf, text: String| {
            std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))
        };
        write(files.scenario(), s.to_toml_string()?)?;
        write(files.deployment(), d.to_toml_string())?;
        Ok(files)
    }

    fn scenario(&self) -> PathBuf {
        self.dir.join("scenario.toml")
    }

    /// What every process of the stack is started with: mode, instance and these files.
    fn process_args(&self, mode: Mode, instance: &str) -> [String; 8] {
        [
            "--mode".to_string(),
            mode.as_str().to_string(),
            "--instance".to_string(),
            instance.to_string(),
            "--scenario".to_string(),
            path_arg(&self.scenario()),
            "--deploy".to_string(),
            path_arg(&self.deployment()),
        ]
    }

    fn deployment(&self) -> PathBuf {
        self.dir.join("deploy.toml")
    }

    /// Every child has read its files: they can go.
    fn remove(&self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }

    /// Removes the directories of launchers that no longer run.
    fn remove_leftovers() {
        let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let pid = name
                .to_str()
                .and_then(|n| n.strip_prefix(RUN_DIR_PREFIX))
                .and_then(|rest| rest.split('-').next())
                .and_then(|pid| pid.parse::<u32>().ok());
            let Some(pid) = pid else { continue };
            let alive = Path::new(&format!("/proc/{pid}")).exists();
            if !alive && entry.path().join("deploy.toml").exists() {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
    }
}

impl Drop for RunFiles {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// An emulated drive on `addr` for a run's files. It stands for separate hardware: it
/// keeps the plant's CPU; the bridge shares the current loop's, one priority below it (see
/// the README's hardware section). With `truth`, it writes the true rotor state there.
fn spawn_emulated_drive(addr: &str, files: &RunFiles, truth: Option<&Path>) -> Result<Supervised> {
    let mut args = vec![
        "--listen".to_string(),
        addr.to_string(),
        "--scenario".to_string(),
        path_arg(&files.scenario()),
        "--deploy".to_string(),
        path_arg(&files.deployment()),
    ];
    if let Some(p) = truth {
        args.extend(["--truth".to_string(), path_arg(p)]);
    }
    Supervised::spawn("emulate-drive", &args)
}

fn path_arg(p: &Path) -> String {
    p.display().to_string()
}

/// Child exit codes that are the child's own verdict on the run (a latched fault, a
/// step-out), not a failure of the process: the monitor judges the run from the state
/// stream itself.
const VERDICT_EXIT_CODES: [i32; 2] = [3, 4];

/// How the supervision of a run ended.
enum Ending {
    /// The last sample arrived.
    Last,
    /// The run stopped early.
    Stopped(Outcome, String),
}

/// Runs one method of one scenario on three processes and returns its report: complete, or
/// with what ran before it stopped (a child died, the stack hung, Ctrl-C), its outcome
/// saying which. An error only when the stack could not be started at all.
///
/// With `recording`, every state sample the monitor sees and every statistics report go to
/// the file too (on channels of their own for this method).
pub fn run_stack(
    s: &Scenario,
    method: Method,
    opts: &LaunchOptions,
    recording: Option<&mut Recording>,
) -> Result<RunReport> {
    let mode = opts.mode;
    let realtime = mode != Mode::Lockstep;
    let hardware = mode == Mode::Hardware;
    let mut d = opts.deployment.clone();
    // At its own priority the monitor waits for the loops (see `deploy`).
    d.rt(Process::Monitor, mode).apply()?;
    let removed = cleanup_dead_nodes();
    if removed > 0 {
        tracing::warn!(
            removed,
            "removed resources of dead stepdrive/iceoryx2 nodes"
        );
    }
    let emulated = hardware && d.drive.address.is_none();
    if emulated {
        d.drive.address = Some(free_loopback_port()?.to_string());
    }
    let files = RunFiles::write(s, &d.resolved(mode), &opts.instance)?;
    let common = files.process_args(mode, &opts.instance);

    // The monitor subscribes before the plant may start: the plant waits for 3 subscribers.
    let bus = IpcBus::open(&opts.instance, "monitor", &Stamp::new(mode, s))
        .context("cannot attach the monitor to the stack's services")?;
    let mut states = bus.subscriber_of::<DriveState>(MONITOR_BUFFER)?;
    let mut stats_sub = bus.subscriber_of::<StatsReport>(4)?;
    // Recording: the setpoints too, from the first. The plant still waits for the current
    // loop's subscription before its first sample, so the position loop (which starts
    // once any setpoint subscriber is there) has nothing to answer before it.
    let (setpoints, commands) = match recording {
        Some(_) => (
            Some(bus.subscriber_of::<TorqueSetpoint>(MONITOR_BUFFER)?),
            Some(bus.subscriber_of::<DriveCommand>(MONITOR_BUFFER)?),
        ),
        None => (None, None),
    };
    // Plans exist in realtime and hardware only (a lockstep plant never misses a command).
    let plans = match (&recording, realtime) {
        (Some(_), true) => Some(bus.subscriber_of::<DrivePlan>(LOOP_BUFFER)?),
        _ => None,
    };

    let mut children = Vec::with_capacity(4);
    // Only an emulated drive knows where the rotor really is; it writes that beside the
    // run so that the report can set the truth against what the sensors said.
    let truth_path = emulated.then(|| {
        std::env::temp_dir().join(format!(
            "stepdrive-truth-{}-{}.csv",
            std::process::id(),
            opts.instance
        ))
    });
    if let (true, Some(addr)) = (emulated, &d.drive.address) {
        children.push(spawn_emulated_drive(addr, &files, truth_path.as_deref())?);
    }
    let with = |extra: &[&str]| -> Vec<String> {
        common
            .iter()
            .cloned()
            .chain(extra.iter().map(|a| a.to_string()))
            .collect()
    };
    children.push(Supervised::spawn(
        "plant",
        &with(&["--wait-subscribers", "3"]),
    )?);
    children.push(Supervised::spawn("position-loop", &with(&[]))?);
    children.push(Supervised::spawn(
        "current-loop",
        &with(&["--method", method.as_str()]),
    )?);
    let mut stats = Finals::default();
    let recording = match recording {
        Some(r) => match r.begin(method) {
            Ok(()) => Some(r),
            Err(e) => {
                tracing::error!("{e:#}; the run goes on unrecorded");
                None
            }
        },
        None => None,
    };
    let mut watch = Watch {
        recording,
        setpoints,
        commands,
        plans,
        metrics: Metrics::new(s),
        rss_start: Vec::new(),
        rss_end: Vec::new(),
        misses_per_minute: Vec::new(),
        last_seq: None,
        monitor_lost: 0,
        first_ns: None,
        last_ns: 0,
    };
    let ending = supervise(
        s,
        method,
        &d,
        realtime,
        &mut states,
        &mut stats_sub,
        &mut stats,
        &mut children,
        &mut watch,
        &files,
    )?;

    watch.read_rss_end();
    let mut failures = Vec::new();
    if let Ending::Last = ending {
        if emulated {
            // The emulated drive runs until told to stop; the bridge has disabled it.
            children[0].signal(libc::SIGTERM);
        }
        for child in children.iter_mut() {
            let status = child.finish(Duration::from_secs(10));
            stats.drain(&mut stats_sub, watch.recording.as_deref_mut())?;
            let verdict = status
                .code()
                .is_some_and(|c| VERDICT_EXIT_CODES.contains(&c));
            if !status.success() && !verdict {
                failures.push(child.describe_failure(status));
            }
        }
    }
    stats.drain(&mut stats_sub, watch.recording.as_deref_mut())?;
    // The answer to the last sample comes after it: the loops have exited by now.
    watch.record_controls()?;
    if let Some(r) = watch.recording.as_deref_mut() {
        r.lost(watch.monitor_lost);
    }
    watch.setpoints = None;
    watch.commands = None;
    watch.plans = None;
    drop(stats_sub);
    drop(children);
    drop(states);
    drop(bus);
    cleanup_dead_nodes();
    let wall = watch
        .first_ns
        .map(|f| watch.last_ns.saturating_sub(f) as f64 * 1e-9)
        .unwrap_or(0.0);
    let metrics = &watch.metrics;
    let mut report = match ending {
        Ending::Last if failures.is_empty() => metrics.finish(method, mode.as_str(), wall),
        Ending::Last => {
            let mut r = metrics.finish(method, mode.as_str(), wall);
            r.outcome = r.outcome.max(Outcome::ProcessDied);
            r.stopped_because = Some(failures.join("; "));
            r
        }
        Ending::Stopped(outcome, because) => {
            metrics.finish_early(method, mode.as_str(), wall, outcome, because)
        }
    };
    if let Some(path) = truth_path {
        let rows = read_truth(&path);
        let _ = std::fs::remove_file(&path);
        report.truth = truth_report(s, method, &rows);
        if let (Some(r), false) = (watch.recording.as_deref_mut(), rows.is_empty()) {
            if let Err(e) = r.truth(&rows) {
                tracing::error!("{e:#}; the true rotor state goes unrecorded");
            }
        }
    }
    if realtime {
        let mut timing = stats.timing(s, watch.monitor_lost, mode);
        timing.resources = Resources {
            rss: watch
                .rss_start
                .iter()
                .zip(&watch.rss_end)
                .map(|(&(process, _, start_kib), &end_kib)| Rss {
                    process: process.to_string(),
                    start_kib,
                    end_kib,
                })
                .collect(),
            misses_per_minute: watch.misses_per_minute.clone(),
        };
        report.timing = Some(timing);
    }
    Ok(report)
}

/// The emulated drive's true rotor state over the run (none, said once, when the drive
/// left no usable file: the run's own figures stand).
fn read_truth(path: &std::path::Path) -> Vec<TruthRow> {
    stepdrive_emulated_drive::truth::read(path).unwrap_or_else(|e| {
        tracing::warn!("no true rotor state from the emulated drive: {e}");
        Vec::new()
    })
}

/// The run's figures from the true rotor state.
fn truth_report(s: &Scenario, method: Method, rows: &[TruthRow]) -> Option<TruthReport> {
    if rows.is_empty() {
        return None;
    }
    let mut m = Metrics::new(s);
    for r in rows {
        m.push(&DriveState {
            seq: r.k,
            sample_time_s: r.t_s,
            theta_rad: r.theta_rad,
            omega_rad_s: r.omega_rad_s,
            i_a_a: r.i_a_a,
            i_b_a: r.i_b_a,
            ..Default::default()
        });
    }
    let t = m.finish(method, "truth", 0.0);
    Some(TruthReport {
        samples: t.samples,
        cruise_max_abs_error_rad: t.cruise_max_abs_error_rad,
        max_abs_error_rad: t.max_abs_error_rad,
        final_error_rad: t.final_error_rad,
    })
}

/// What the monitor gathers from the state stream, and the processes' resources.
struct Watch<'r> {
    /// Where every sample and report also goes, if the run is recorded.
    recording: Option<&'r mut Recording>,
    /// Recording: the position loop's setpoints (torque, load estimate) and the current
    /// loop's commands (voltages, current references).
    setpoints: Option<IpcSubscriber<TorqueSetpoint>>,
    commands: Option<IpcSubscriber<DriveCommand>>,
    /// Realtime and hardware: the voltage plans (their first entries); the topic keeps a
    /// short queue, so a monitor that falls behind loses some (they are not counted).
    plans: Option<IpcSubscriber<DrivePlan>>,
    metrics: Metrics,
    /// (process, pid, RSS at the first sample in KiB) of every child and the monitor.
    rss_start: Vec<(&'static str, u32, u64)>,
    /// RSS at the last reading each process answered.
    rss_end: Vec<u64>,
    misses_per_minute: Vec<u64>,
    last_seq: Option<u64>,
    /// Realtime: samples the monitor (the one loop allowed to fall behind) did not see.
    monitor_lost: u64,
    first_ns: Option<u64>,
    last_ns: u64,
}

impl Watch<'_> {
    /// Records a sample; a recording that fails is given up (the run goes on), once said.
    fn record(&mut self, st: &DriveState) {
        if let Some(r) = self.recording.as_deref_mut() {
            if let Err(e) = r.state(st) {
                tracing::error!("{e:#}; the rest of the run goes unrecorded");
                self.recording = None;
            }
        }
    }

    /// Records the setpoints and commands that arrived; a recording that fails is given up.
    fn record_controls(&mut self) -> Result<(), stepdrive_runtime::port::PortError> {
        let Some(r) = self.recording.as_deref_mut() else {
            return Ok(());
        };
        let mut failed = None;
        if let Some(sub) = self.setpoints.as_mut() {
            while let Some(sp) = sub.receive()? {
                if let Err(e) = r.setpoint(&sp) {
                    failed = Some(e);
                    break;
                }
            }
        }
        if let (Some(sub), None) = (self.commands.as_mut(), &failed) {
            while let Some(c) = sub.receive()? {
                if let Err(e) = r.command(&c) {
                    failed = Some(e);
                    break;
                }
            }
        }
        if let (Some(sub), None) = (self.plans.as_mut(), &failed) {
            while let Some(p) = sub.receive()? {
                if let Err(e) = r.plan(&p) {
                    failed = Some(e);
                    break;
                }
            }
        }
        if let Some(e) = failed {
            tracing::error!("{e:#}; the rest of the run goes unrecorded");
            self.recording = None;
        }
        Ok(())
    }

    fn read_rss_end(&mut self) {
        self.rss_end.resize(self.rss_start.len(), 0);
        for (end, &(_, pid, _)) in self.rss_end.iter_mut().zip(&self.rss_start) {
            if let Some(kib) = rss_kib(pid) {
                *end = kib;
            }
        }
    }
}

/// Every process's latest and final statistics.
#[derive(Default)]
struct Finals {
    latest: [Option<StatsReport>; 3],
    finals: [Option<StatsReport>; 3],
}

impl Finals {
    fn drain(
        &mut self,
        sub: &mut IpcSubscriber<StatsReport>,
        mut recording: Option<&mut Recording>,
    ) -> Result<()> {
        while let Some(r) = sub.receive()? {
            if let Some(rec) = recording.as_deref_mut() {
                if let Err(e) = rec.stats(&r) {
                    tracing::error!("{e:#}");
                    recording = None;
                }
            }
            let i = r.role as usize;
            if i < 3 {
                if r.is_final != 0 {
                    self.finals[i] = Some(r);
                }
                self.latest[i] = Some(r);
            }
        }
        Ok(())
    }

    fn timing(&self, s: &Scenario, monitor_lost: u64, mode: Mode) -> TimingReport {
        let missing: Vec<&str> = ["plant", "current-loop", "position-loop"]
            .iter()
            .zip(self.finals.iter())
            .filter(|(_, f)| f.is_none())
            .map(|(n, _)| *n)
            .collect();
        if !missing.is_empty() {
            tracing::warn!(
                ?missing,
                "no final statistics from some processes; using their last report"
            );
        }
        let pick = |i: usize| self.finals[i].or(self.latest[i]).map(Box::new);
        TimingReport::new(
            s,
            pick(0),
            pick(1),
            pick(2),
            monitor_lost,
            // In hardware mode the loop sleeps on the bridge's event, whose length it
            // does not choose, so it cannot tell a hold from a wait.
            mode == Mode::Realtime,
        )
    }
}

/// Takes the state stream into the metrics until the last sample, watching the children,
/// the termination flag and the stream's liveness; says how it ended.
#[allow(clippy::too_many_arguments)]
fn supervise(
    s: &Scenario,
    method: Method,
    d: &Deployment,
    realtime: bool,
    states: &mut IpcSubscriber<DriveState>,
    stats_sub: &mut IpcSubscriber<StatsReport>,
    stats: &mut Finals,
    children: &mut [Supervised],
    w: &mut Watch<'_>,
    files: &RunFiles,
) -> Result<Ending> {
    let total = s.sample_count();
    let duration = s.duration_s();
    let started = Instant::now();
    let mut last_sample_at = Instant::now();
    let mut next_progress = Instant::now() + Duration::from_secs(1);
    let mut files_removed = false;
    let mut next_minute = Instant::now() + Duration::from_secs(60);
    let mut misses_at_minute = 0;
    // On a terminal a bar with the simulated time, misses and faults so far; otherwise (a
    // log, CI) the plain progress lines below.
    let bar = std::io::IsTerminal::is_terminal(&std::io::stderr()).then(|| {
        let bar = indicatif::ProgressBar::new(total);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{prefix} [{bar:30}] {percent:>3} % {msg} ({elapsed})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        bar.set_prefix(method.to_string());
        bar
    });
    let mut next_bar = Instant::now();
    let ending = (|| -> Result<Ending> {
        loop {
            let mut got = false;
            stats.drain(stats_sub, w.recording.as_deref_mut())?;
            while let Some(state) = states.receive()? {
                got = true;
                let expected = w.last_seq.map_or(0, |q| q + 1);
                w.last_seq = Some(state.seq);
                if state.seq < expected {
                    // A sample repeated or published after a newer one: whatever the mode, the
                    // plant (or bridge) broke its contract.
                    return Ok(Ending::Stopped(
                        Outcome::ProcessDied,
                        format!(
                            "the plant published sample {} after sample {}",
                            state.seq,
                            expected - 1
                        ),
                    ));
                }
                if state.seq != expected {
                    if !realtime {
                        return Ok(Ending::Stopped(
                            Outcome::ProcessDied,
                            format!(
                                "monitor expected sample {expected}, got {}: samples were lost",
                                state.seq
                            ),
                        ));
                    }
                    w.monitor_lost += state.seq - expected;
                }
                w.first_ns.get_or_insert(state.publish_time_ns);
                w.last_ns = state.publish_time_ns;
                w.metrics.push(&state);
                w.record(&state);
                if state.flags & state_flags::LAST != 0 {
                    w.record_controls()?;
                    return Ok(Ending::Last);
                }
            }
            w.record_controls()?;
            if got {
                if !files_removed {
                    // A sample means every child is up, with its files read.
                    files.remove();
                    files_removed = true;

                    let me = std::process::id();
                    w.rss_start = children
                        .iter()
                        .map(|c| (c.role(), c.pid()))
                        .chain([("monitor", me)])
                        .map(|(role, pid)| (role, pid, rss_kib(pid).unwrap_or(0)))
                        .collect();
                }
                last_sample_at = Instant::now();
            }
            for child in children.iter_mut() {
                if let Some(status) = child.poll_exit()? {
                    return Ok(Ending::Stopped(
                        Outcome::ProcessDied,
                        child.describe_failure(status),
                    ));
                }
            }
            if termination_requested() {
                return Ok(Ending::Stopped(
                    Outcome::Interrupted,
                    "interrupted (SIGINT/SIGTERM); all stack processes were stopped".to_string(),
                ));
            }
            let limit = if w.metrics.samples() == 0 {
                d.startup_timeout()
            } else {
                d.peer_timeout()
            } + Duration::from_secs(1);
            if last_sample_at.elapsed() > limit {
                return Ok(Ending::Stopped(
                    Outcome::ProcessDied,
                    format!(
                        "no state sample for {:.1} s (after {} of {total}); the stack is stuck",
                        last_sample_at.elapsed().as_secs_f64(),
                        w.metrics.samples()
                    ),
                ));
            }
            if realtime && Instant::now() >= next_minute {
                let misses = stats.latest[roles::PLANT as usize].map_or(0, |p| p.misses);
                w.misses_per_minute
                    .push(misses.saturating_sub(misses_at_minute));
                misses_at_minute = misses;
                next_minute += Duration::from_secs(60);
            }
            if let Some(bar) = bar.as_ref().filter(|_| Instant::now() >= next_bar) {
                let k = w.last_seq.map_or(0, |q| q + 1);
                let misses = stats.latest[roles::PLANT as usize].map_or(0, |p| p.misses);
                let mut msg = format!(
                    "{:.2} of {duration:.2} s",
                    k as f64 / s.rates.current_loop_hz
                );
                if realtime {
                    msg += &format!(", {misses} misses");
                }
                msg += &format!(", {} faulted samples", w.metrics.faulted_samples());
                bar.set_position(k);
                bar.set_message(msg);
                next_bar = Instant::now() + Duration::from_millis(200);
            }
            if Instant::now() >= next_progress {
                let k = w.last_seq.map_or(0, |q| q + 1);
                let done_s = k as f64 / s.rates.current_loop_hz;
                let misses = stats.latest[roles::PLANT as usize].map_or(0, |p| p.misses);
                if bar.is_none() {
                    tracing::info!(
                        "{method}: {done_s:.2} of {duration:.2} s ({:.0} %), {:.1} s elapsed{}",
                        100.0 * k as f64 / total as f64,
                        started.elapsed().as_secs_f64(),
                        if realtime {
                            format!(", {misses} deadline misses so far")
                        } else {
                            String::new()
                        }
                    );
                }
                next_progress += Duration::from_secs(if realtime { 5 } else { 1 });
                // The last reading while every child lives: one that has exited has none.
                w.read_rss_end();
            }
            std::thread::sleep(Duration::from_micros(if realtime { 1000 } else { 500 }));
        }
    })();
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    ending
}

/// A child that exited with its verdict on the run (a latched fault: 3) carries that exit
/// code; any other failure is the process's own (exit 5).
fn child_failed(child: &Supervised, status: ExitStatus) -> anyhow::Error {
    let code = match status.code() {
        Some(c) if VERDICT_EXIT_CODES.contains(&c) => c as u8,
        _ => Outcome::ProcessDied.exit_code(),
    };
    crate::report::outcome::Exit {
        code,
        headline: child.describe_failure(status),
    }
    .into()
}

/// A loopback UDP address no one is using right now, for the emulated drive.
fn free_loopback_port() -> Result<std::net::SocketAddr> {
    let probe = std::net::UdpSocket::bind("127.0.0.1:0").context("cannot find a free UDP port")?;
    Ok(probe.local_addr()?)
}

/// `stepdrive identify` through the stack's processes in `opts.mode`: the plant (or the
/// bridge, and an emulated drive when no drive is given) and the identification process in
/// the current loop's place; no position loop, no monitor. `s` must last the sequence.
/// Returns what the identification process found.
pub fn run_identify(
    s: &Scenario,
    bounds: &stepdrive_control::identify::Bounds,
    opts: &LaunchOptions,
) -> Result<crate::studies::identify::NodeResult> {
    let mode = opts.mode;
    let mut d = opts.deployment.clone();
    cleanup_dead_nodes();
    let emulated = mode == Mode::Hardware && d.drive.address.is_none();
    if emulated {
        d.drive.address = Some(free_loopback_port()?.to_string());
    }
    let files = RunFiles::write(s, &d.resolved(mode), &opts.instance)?;
    let result = files.dir.join("identify.json");
    let common = files.process_args(mode, &opts.instance);
    let mut drive = None;
    if let (true, Some(addr)) = (emulated, &d.drive.address) {
        drive = Some(spawn_emulated_drive(addr, &files, None)?);
    }
    let with = |extra: &[String]| -> Vec<String> { common.iter().chain(extra).cloned().collect() };
    let mut plant = Supervised::spawn(
        "plant",
        &with(&["--wait-subscribers", "1", "--no-position-loop"].map(String::from)),
    )?;
    let extra = [
        "--max-current".to_string(),
        bounds.current_a.to_string(),
        "--max-voltage".to_string(),
        bounds.voltage_v.to_string(),
        "--max-speed".to_string(),
        bounds.speed_rad_s.to_string(),
        "--max-travel".to_string(),
        bounds.travel_rad.to_string(),
        "--result".to_string(),
        path_arg(&result),
    ];
    let mut node = Supervised::spawn("identify-node", &with(&extra))?;
    let limit =
        d.startup_timeout() + Duration::from_secs_f64(s.duration_s()) + Duration::from_secs(10);
    let started = Instant::now();
    let status = loop {
        if let Some(status) = node.poll_exit()? {
            break status;
        }
        if let Some(status) = plant.poll_exit()? {
            if !status.success() {
                return Err(child_failed(&plant, status));
            }
        }
        if termination_requested() {
            anyhow::bail!("interrupted (SIGINT/SIGTERM); all processes were stopped");
        }
        if started.elapsed() > limit {
            anyhow::bail!(
                "the identification did not finish within {:.0} s",
                limit.as_secs_f64()
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let plant_status = plant.finish(Duration::from_secs(10));
    if let Some(mut drive) = drive {
        drive.signal(libc::SIGTERM);
        drive.finish(Duration::from_secs(5));
    }
    if !status.success() {
        return Err(child_failed(&node, status));
    }
    if !plant_status.success() {
        return Err(child_failed(&plant, plant_status));
    }
    let text = std::fs::read_to_string(&result)
        .with_context(|| format!("the identification left no result in {}", result.display()))?;
    serde_json::from_str(&text).context("the identification's result is not readable")
}
