//! The one supervisor: what happens while a stack runs, whoever started it. `run`,
//! `latency`, `identify` and `serve` launch a stack and supervise it with its children;
//! `monitor` and `record` attach to one and supervise it without. Every message goes
//! through the [`Observer`]'s rules; around them the supervisor watches the children, the
//! termination flag and the stream's liveness, gathers every loop's statistics, and shows
//! progress.

use crate::report::metrics::AxisRun;
use crate::report::timing::{rss_kib, Resources, Rss, TimingReport};
use crate::supervise::children::{RunFiles, Supervised};
use crate::supervise::helpers::Helpers;
use crate::supervise::observer::{Observer, Stop};
use crate::supervise::standstill::Stopper;
use std::time::{Duration, Instant};
use stepdrive_runtime::poll::termination_requested;
use stepdrive_runtime::port::Subscribe;
use stepdrive_shared::axis::{AxisAck, AxisStatus};
use stepdrive_shared::messages::{DriveCommand, DrivePlan, DriveState, TorqueSetpoint};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stack::{Role, Slot};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

mod watch;

/// The supervisor's nap between drains, realtime: ~20 states at the default 20 kHz.
const REALTIME_NAP: Duration = Duration::from_millis(1);
/// Lockstep: ~900 states a drain at 22x real time, an eighth of the monitor's queue (a full
/// queue holds the plant, it never drops). Every wake-up of the monitor takes a CPU from the
/// plant or the loops, which hand off every sample: at 0.5 ms (1800 a second) the run took
/// 4 % longer (docs/measurements.md).
const LOCKSTEP_NAP: Duration = Duration::from_millis(2);

/// States taken between two drains of the controls: half a position-loop tick at the
/// default rates, so a recorded state's setpoint is at most a tick or two behind it.
const CONTROLS_EVERY: u32 = 5;

/// What the supervisor reads of a stack.
pub struct Feeds {
    pub states: Box<dyn Subscribe<DriveState>>,
    pub stats: Box<dyn Subscribe<StatsReport>>,
    /// What a recorder, or a program's figures, take besides: see [`Controls::open`].
    pub controls: Option<Controls>,
    /// A multi-axis stack's other axes (1, 2, ...).
    pub axes: Vec<AxisFeed>,
}

/// What the supervisor reads of another axis of a multi-axis stack: its states, and the
/// controls its figures need.
pub struct AxisFeed {
    pub axis: usize,
    pub states: Box<dyn Subscribe<DriveState>>,
    pub controls: Option<Controls>,
}

/// Another axis under watch: its feed, its own observer (the same rules as axis 0's),
/// and when a state of it last came.
struct AxisWatch<'r> {
    feed: AxisFeed,
    name: String,
    observer: Observer<'r>,
    heard: Option<Instant>,
}

/// The setpoints, commands, plans, and the axis's answers and status.
pub struct Controls {
    pub setpoints: Option<Box<dyn Subscribe<TorqueSetpoint>>>,
    pub commands: Option<Box<dyn Subscribe<DriveCommand>>>,
    /// The plan topic has room for the device and one reader: a second recorder goes
    /// without.
    pub plans: Option<Box<dyn Subscribe<DrivePlan>>>,
    pub acks: Option<Box<dyn Subscribe<AxisAck>>>,
    pub status: Option<Box<dyn Subscribe<AxisStatus>>>,
}

impl Controls {
    /// What to take of a stack in `mode`: everything when `recording` (the plans on the
    /// wall clock only: a lockstep plant never misses a command); for a commanded run's
    /// figures (`program`: a program or a served stack), the setpoints (its θ_d), the
    /// answers (its moves) and the status (the axis's faults). `None`: nothing beside the
    /// states.
    pub fn open(
        bus: &mut impl stepdrive_runtime::port::PortFactory,
        mode: Mode,
        recording: bool,
        program: bool,
    ) -> Result<Option<Self>, stepdrive_runtime::port::PortError> {
        if !recording && !program {
            return Ok(None);
        }
        let buffer = stepdrive_shared::services::MONITOR_BUFFER;
        Ok(Some(Self {
            setpoints: Some(bus.subscriber(buffer)?),
            commands: match recording {
                true => Some(bus.subscriber(buffer)?),
                false => None,
            },
            plans: match (recording, mode) {
                (true, Mode::Realtime | Mode::Hardware) => {
                    match bus.subscriber(stepdrive_shared::services::LOOP_BUFFER) {
                        Ok(p) => Some(p),
                        Err(e) => {
                            tracing::warn!("recording without the voltage plans: {e}");
                            None
                        }
                    }
                }
                _ => None,
            },
            acks: Some(bus.subscriber(buffer)?),
            status: Some(bus.subscriber(buffer)?),
        }))
    }
}

/// Every loop's latest and final statistics, by its place in the stack.
#[derive(Default)]
pub struct Finals {
    latest: [Option<StatsReport>; 3],
    finals: [Option<StatsReport>; 3],
}

impl Finals {
    fn take(&mut self, r: &StatsReport) {
        let Some(slot) = Role::from_code(r.role).and_then(Role::slot) else {
            return;
        };
        let i = slot.index();
        if r.is_final != 0 {
            self.finals[i] = Some(*r);
        }
        self.latest[i] = Some(*r);
    }

    /// Every loop has sent its final statistics: the stack ended in order.
    fn all_final(&self) -> bool {
        self.finals.iter().all(Option::is_some)
    }

    /// The device's deadline misses so far.
    pub fn device_misses(&self) -> u64 {
        self.latest[Slot::Device.index()].map_or(0, |p| p.misses)
    }

    /// The timing report from each loop's final statistics (or its last, said once).
    pub fn timing(&self, s: &Scenario, monitor_lost: u64, mode: Mode) -> TimingReport {
        let missing: Vec<&str> = Slot::ALL
            .iter()
            .filter(|slot| self.finals[slot.index()].is_none())
            .map(|slot| match slot {
                Slot::Device => "device",
                Slot::Current => "current loop",
                Slot::Position => "position loop",
            })
            .collect();
        if !missing.is_empty() {
            tracing::warn!(
                ?missing,
                "no final statistics from some processes; using their last report"
            );
        }
        let pick = |slot: Slot| {
            let i = slot.index();
            self.finals[i].or(self.latest[i]).map(Box::new)
        };
        TimingReport::new(
            s,
            pick(Slot::Device),
            pick(Slot::Current),
            pick(Slot::Position),
            monitor_lost,
            // In hardware mode the loop sleeps on the bridge's event, whose length it does
            // not choose, so it cannot tell a hold from a wait.
            mode == Mode::Realtime,
        )
    }
}

/// When supervision ends by itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Until {
    /// At the run's last sample.
    LastSample,
    /// Never: a stack that serves until Ctrl-C (or until it breaks).
    Interrupted,
}

/// How supervision ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Ending {
    /// The last sample arrived.
    Last,
    /// The run stopped early, or was stopped.
    Stopped(Stop),
}

/// The children's resident memory at the first sample and at the last reading each
/// answered, and the device's misses minute by minute.
#[derive(Default)]
struct Resource {
    rss_start: Vec<(&'static str, u32, u64)>,
    rss_end: Vec<u64>,
    misses_per_minute: Vec<u64>,
}

impl Resource {
    fn start(&mut self, children: &[Supervised]) {
        let me = std::process::id();
        self.rss_start = children
            .iter()
            .map(|c| (c.role().id(), c.pid()))
            .chain([("monitor", me)])
            .map(|(role, pid)| (role, pid, rss_kib(pid).unwrap_or(0)))
            .collect();
    }

    fn read_end(&mut self) {
        self.rss_end.resize(self.rss_start.len(), 0);
        for (end, &(_, pid, _)) in self.rss_end.iter_mut().zip(&self.rss_start) {
            if let Some(kib) = rss_kib(pid) {
                *end = kib;
            }
        }
    }
}

/// One supervision: a stack, how it is watched, what was gathered.
pub struct Supervisor<'a, 'r> {
    s: &'a Scenario,
    mode: Mode,
    /// Names the run in progress lines ("proposed", "identify", ...).
    label: String,
    feeds: Feeds,
    pub observer: Observer<'r>,
    pub finals: Finals,
    /// The stack's processes, when this supervisor launched them.
    children: &'a mut [Supervised],
    /// Files the children read, removed once they all run.
    files: Option<&'a RunFiles>,
    startup_timeout: Duration,
    peer_timeout: Duration,
    resource: Resource,
    axes: Vec<AxisWatch<'r>>,
    /// A launched stack on the wall clock: its lines to the axes, to stop them before its
    /// processes go ([`Self::wind_down`]).
    stopper: Option<Stopper>,
    /// The processes beside the stack (the gateway, the RT-throttling guard), watched with
    /// it.
    helpers: Option<&'a mut Helpers>,
    /// The stack's process whose death ended the supervision.
    died: Option<stepdrive_shared::stack::Role>,
}

impl<'a, 'r> Supervisor<'a, 'r> {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        s: &'a Scenario,
        mode: Mode,
        label: impl Into<String>,
        feeds: Feeds,
        observer: Observer<'r>,
        children: &'a mut [Supervised],
        files: Option<&'a RunFiles>,
        timeouts: (Duration, Duration),
    ) -> Self {
        Self {
            s,
            mode,
            label: label.into(),
            feeds,
            observer,
            finals: Finals::default(),
            children,
            files,
            startup_timeout: timeouts.0,
            peer_timeout: timeouts.1,
            resource: Resource::default(),
            axes: Vec::new(),
            stopper: None,
            helpers: None,
            died: None,
        }
    }

    /// Stops the axes through `stopper` before the stack's processes go.
    pub fn stopping_with(mut self, stopper: Option<Stopper>) -> Self {
        self.stopper = stopper;
        self
    }

    /// Watches `helpers` with the stack.
    pub fn with_helpers(mut self, helpers: Option<&'a mut Helpers>) -> Self {
        self.helpers = helpers;
        self
    }

    /// Watches the feeds' other axes, each with its own observer (built from its axis's
    /// scenario): a fault, a step-out, a gap or a silence on any axis is the run's.
    pub fn watching_axes(mut self) -> Self {
        let s = self.s;
        let mode = self.mode;
        self.axes = std::mem::take(&mut self.feeds.axes)
            .into_iter()
            .map(|feed| AxisWatch {
                name: s.axis_name(feed.axis),
                observer: Observer::new(s.for_axis(feed.axis).unwrap_or(s), mode)
                    .on_axis(feed.axis as u32),
                feed,
                heard: None,
            })
            .collect();
        self
    }

    /// Every other axis's report, judged like axis 0's.
    pub fn axis_reports(&mut self, method: stepdrive_shared::Method, mode: &str) -> Vec<AxisRun> {
        self.axes
            .iter_mut()
            .map(|a| {
                let wall = a.observer.wall_s();
                // With the recording lent: its last states are graded (and recorded) now.
                let report = self
                    .observer
                    .lending(&mut a.observer, |o| o.report(method, mode, wall, None));
                AxisRun {
                    axis: a.feed.axis,
                    name: a.name.clone(),
                    report,
                }
            })
            .collect()
    }

    /// The devices' latched fault bits at their newest sample, every axis's together.
    pub fn last_faults(&self) -> u32 {
        self.axes.iter().fold(self.observer.last_fault(), |f, a| {
            f | a.observer.last_fault()
        })
    }

    /// Every axis has seen its last sample.
    fn all_last_seen(&self) -> bool {
        self.observer.last_seen() && self.axes.iter().all(|a| a.observer.last_seen())
    }

    /// Takes the other axes' controls and states; a stop names its axis.
    fn drain_axes(&mut self) -> Result<Result<bool, Stop>, stepdrive_runtime::port::PortError> {
        let mut got = false;
        for a in &mut self.axes {
            let mut states = 0u32;
            loop {
                if states.is_multiple_of(CONTROLS_EVERY) {
                    if let Some(c) = a.feed.controls.as_mut() {
                        self.observer
                            .lending(&mut a.observer, |o| take_controls(c, o))?;
                    }
                }
                if a.observer.last_seen() {
                    break;
                }
                let Some(st) = a.feed.states.receive()? else {
                    break;
                };
                states += 1;
                got = true;
                a.heard = Some(Instant::now());
                if let Err(mut stop) = self.observer.lending(&mut a.observer, |o| o.state(&st)) {
                    stop.because = format!("axis {} ({}): {}", a.feed.axis, a.name, stop.because);
                    return Ok(Err(stop));
                }
            }
        }
        Ok(Ok(got))
    }

    /// Another axis that has gone silent before its last sample.
    fn silent_axis(&self, started: Instant) -> Option<Stop> {
        self.axes.iter().find_map(|a| {
            let n = a.observer.metrics().samples();
            let limit = if n == 0 {
                self.startup_timeout
            } else {
                self.peer_timeout
            } + Duration::from_secs(1);
            let quiet = a.heard.unwrap_or(started).elapsed();
            (!a.observer.last_seen() && quiet > limit).then(|| {
                Stop::new(
                    crate::report::outcome::Outcome::ProcessDied,
                    format!(
                        "axis {} ({}): no state sample for {:.1} s (after {n} samples); the \
                         stack is stuck",
                        a.feed.axis,
                        a.name,
                        quiet.as_secs_f64()
                    ),
                )
            })
        })
    }

    /// Takes what arrived: statistics, the controls when recording, and states (by the
    /// observer's rules). True if a state came. The controls first, and again every
    /// [`CONTROLS_EVERY`] states while states keep coming: a state's recorded θ_d is the
    /// setpoint in force at its sample, which must have been taken by then.
    fn drain(&mut self) -> Result<Result<bool, Stop>, stepdrive_runtime::port::PortError> {
        self.take_stats()?;
        let mut got = false;
        let mut states = 0u32;
        loop {
            if states.is_multiple_of(CONTROLS_EVERY) {
                self.drain_controls()?;
            }
            let Some(st) = self.feeds.states.receive()? else {
                break;
            };
            states += 1;
            got = true;
            if let Err(stop) = self.observer.state(&st) {
                return Ok(Err(stop));
            }
            if self.observer.last_seen() {
                break;
            }
        }
        match self.drain_axes()? {
            Ok(axes) => Ok(Ok(got || axes)),
            Err(stop) => Ok(Err(stop)),
        }
    }

    /// Takes the setpoints, commands, plans, answers and statuses that arrived (of every
    /// axis).
    pub fn drain_controls(&mut self) -> Result<(), stepdrive_runtime::port::PortError> {
        for a in &mut self.axes {
            if let Some(c) = a.feed.controls.as_mut() {
                self.observer
                    .lending(&mut a.observer, |o| take_controls(c, o))?;
            }
        }
        match self.feeds.controls.as_mut() {
            Some(c) => take_controls(c, &mut self.observer),
            None => Ok(()),
        }
    }

    /// The statistics that arrived since (the final ones, after the children exit).
    pub fn drain_stats(&mut self) -> Result<(), stepdrive_runtime::port::PortError> {
        self.take_stats()
    }

    /// In place: a report is ~90 KB, and taking it by value (`receive`) copied that much at
    /// every drain, 2000 a second, whether one had come or not (14 % of the lockstep
    /// monitor's time was that copy).
    fn take_stats(&mut self) -> Result<(), stepdrive_runtime::port::PortError> {
        let (finals, observer) = (&mut self.finals, &mut self.observer);
        self.feeds.stats.drain(&mut |r| {
            finals.take(r);
            observer.stats(r);
        })
    }

    /// Supervises until `until`, a child's death, Ctrl-C, or the stack's silence.
    pub fn run(&mut self, until: Until) -> anyhow::Result<Ending> {
        let total = self.s.sample_count();
        let duration = self.s.duration_s();
        let realtime = self.mode != Mode::Lockstep;
        let started = Instant::now();
        let mut last_sample_at = Instant::now();
        let mut next_progress = Instant::now() + Duration::from_secs(1);
        let mut next_minute = Instant::now() + Duration::from_secs(60);
        let mut misses_at_minute = 0;
        let mut running = false;
        // A served stack has no end to count towards.
        let endless = self.s.run.until_stopped;
        let progress = Progress::new(&self.label, total, endless);
        let ending = loop {
            // Before the drain: a plant that ended in order exits after its last sample,
            // which a multi-axis drain (the axes in turn) may not have taken yet; what a
            // child published before it exited is drained below, and its exit counts only
            // if the run is not complete.
            let died = self.dead_child()?;
            let got = match self.drain()? {
                Ok(got) => got,
                Err(stop) => break Ending::Stopped(stop),
            };
            if until == Until::LastSample && self.all_last_seen() {
                break Ending::Last;
            }
            // A reader of a served stack: the stack ends when its owner stops it, and every
            // loop says so with its final statistics (a loop that died sends none, and its
            // silence ends the reading as a death below). The states drained above came
            // before those statistics.
            if endless && self.children.is_empty() && self.finals.all_final() {
                break Ending::Last;
            }
            if got {
                if !running {
                    // A sample means every child is up, with its files read.
                    running = true;
                    if let Some(files) = self.files {
                        files.remove();
                    }
                    self.resource.start(self.children);
                }
                last_sample_at = Instant::now();
            }
            if let Some(stop) = died {
                break Ending::Stopped(stop);
            }
            if termination_requested() {
                // An attached reader has no children: the stack it read runs on.
                let what = if self.children.is_empty() {
                    "interrupted (SIGINT/SIGTERM); this reader stopped, the stack runs on"
                } else {
                    "interrupted (SIGINT/SIGTERM); all stack processes were stopped"
                };
                break Ending::Stopped(Stop::new(
                    crate::report::outcome::Outcome::Interrupted,
                    what,
                ));
            }
            if let Some(stop) = self.watch_helpers()? {
                break Ending::Stopped(stop);
            }
            let limit = if self.observer.metrics().samples() == 0 {
                self.startup_timeout
            } else {
                self.peer_timeout
            } + Duration::from_secs(1);
            if let Some(stop) = self.silent_axis(started) {
                break Ending::Stopped(stop);
            }
            if !self.observer.last_seen() && last_sample_at.elapsed() > limit {
                break Ending::Stopped(Stop::new(
                    crate::report::outcome::Outcome::ProcessDied,
                    format!(
                        "no state sample for {:.1} s (after {} samples); the stack is stuck",
                        last_sample_at.elapsed().as_secs_f64(),
                        self.observer.metrics().samples()
                    ),
                ));
            }
            let now = Instant::now();
            if realtime && now >= next_minute {
                let misses = self.finals.device_misses();
                self.resource
                    .misses_per_minute
                    .push(misses.saturating_sub(misses_at_minute));
                misses_at_minute = misses;
                next_minute += Duration::from_secs(60);
            }
            let k = self.observer.last_seq().map_or(0, |q| q + 1);
            let misses = realtime.then(|| self.finals.device_misses());
            let faulted = self.observer.metrics().faulted_samples();
            progress.show(
                k,
                k as f64 / self.s.rates.current_loop_hz,
                duration,
                misses,
                faulted,
            );
            if now >= next_progress {
                progress.line(
                    k,
                    total,
                    duration,
                    self.s.rates.current_loop_hz,
                    started.elapsed(),
                    misses,
                );
                next_progress += Duration::from_secs(match (endless, realtime) {
                    (true, _) => 60,
                    (false, true) => 5,
                    (false, false) => 1,
                });
                // The last reading while every child lives: one that has exited has none.
                self.resource.read_end();
            }
            std::thread::sleep(match realtime {
                true => REALTIME_NAP,
                false => LOCKSTEP_NAP,
            });
        };
        progress.finish();
        self.resource.read_end();
        Ok(ending)
    }

    /// A child that exited before the run's end: the run stops, naming it.
    fn dead_child(&mut self) -> anyhow::Result<Option<Stop>> {
        for child in self.children.iter_mut() {
            if let Some(status) = child.poll_exit()? {
                self.died = Some(child.role());
                return Ok(Some(Stop::new(
                    crate::report::outcome::Outcome::ProcessDied,
                    child.describe_failure(status),
                )));
            }
        }
        Ok(None)
    }

    /// The processes' memory and the misses per minute, for the timing report.
    pub fn resources(&self) -> Resources {
        let r = &self.resource;
        Resources {
            rss: r
                .rss_start
                .iter()
                .zip(&r.rss_end)
                .map(|(&(process, _, start_kib), &end_kib)| Rss {
                    process: process.to_string(),
                    start_kib,
                    end_kib,
                })
                .collect(),
            misses_per_minute: r.misses_per_minute.clone(),
        }
    }

    /// After the last sample: every child exits by itself (the emulated drive, which runs
    /// until told, is told first); returns the failures of those whose exit was not a
    /// verdict on the run (a latched fault or a step-out is judged from the stream).
    pub fn stop_children(&mut self, drive_first: bool) -> anyhow::Result<Vec<String>> {
        if drive_first {
            if let Some(drive) = self.children.first() {
                drive.signal(libc::SIGTERM);
            }
        }
        let mut failures = Vec::new();
        for i in 0..self.children.len() {
            let status = self.children[i].finish(Duration::from_secs(10));
            self.drain_stats()?;
            let verdict = status.code().is_some_and(|c| [3, 4].contains(&c));
            if !status.success() && !verdict {
                failures.push(self.children[i].describe_failure(status));
            }
        }
        Ok(failures)
    }

    pub fn children_mut(&mut self) -> &mut [Supervised] {
        self.children
    }

    /// Stops reading the controls (their publishers are about to go).
    pub fn close_controls(&mut self) {
        self.feeds.controls = None;
    }
}

/// The progress bar on the terminal now, if any: a child's log line printed under it
/// would leave the bar's last frame standing (at 97 %, say) when it is cleared.
static SHOWN_BAR: std::sync::Mutex<Option<indicatif::ProgressBar>> = std::sync::Mutex::new(None);

/// Prints `line` on stderr, with the progress bar (if one is shown) out of its way.
pub fn print_beside_progress(line: &str) {
    let bar = SHOWN_BAR.lock().ok().and_then(|b| b.clone());
    match bar {
        Some(bar) => bar.suspend(|| eprintln!("{line}")),
        None => eprintln!("{line}"),
    }
}

/// Progress of a run: a bar on a terminal (simulated time, misses, faults), plain lines
/// otherwise (a log, CI).
struct Progress {
    label: String,
    bar: Option<indicatif::ProgressBar>,
    next_bar: std::cell::Cell<Instant>,
}

impl Progress {
    fn new(label: &str, total: u64, endless: bool) -> Self {
        let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr()) && !endless;
        let bar = terminal.then(|| {
            let bar = indicatif::ProgressBar::new(total);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "{prefix} [{bar:30}] {percent:>3} % {msg} ({elapsed})",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            bar.set_prefix(label.to_string());
            bar
        });
        if let (Some(bar), Ok(mut shown)) = (&bar, SHOWN_BAR.lock()) {
            *shown = Some(bar.clone());
        }
        Self {
            label: label.to_string(),
            bar,
            next_bar: std::cell::Cell::new(Instant::now()),
        }
    }

    fn show(&self, k: u64, done_s: f64, duration: f64, misses: Option<u64>, faulted: u64) {
        let Some(bar) = &self.bar else { return };
        if Instant::now() < self.next_bar.get() {
            return;
        }
        let mut msg = format!("{done_s:.2} of {duration:.2} s");
        if let Some(m) = misses {
            msg += &format!(", {m} misses");
        }
        msg += &format!(", {faulted} faulted samples");
        bar.set_position(k);
        bar.set_message(msg);
        self.next_bar
            .set(Instant::now() + Duration::from_millis(200));
    }

    fn line(
        &self,
        k: u64,
        total: u64,
        duration: f64,
        rate_hz: f64,
        elapsed: Duration,
        misses: Option<u64>,
    ) {
        if self.bar.is_some() {
            return;
        }
        if total == u64::MAX {
            tracing::info!(
                "{}: up {:.0} s (stack time {:.1} s){}",
                self.label,
                elapsed.as_secs_f64(),
                k as f64 / rate_hz,
                misses.map_or(String::new(), |m| format!(", {m} deadline misses so far"))
            );
            return;
        }
        tracing::info!(
            "{}: {:.2} of {duration:.2} s ({:.0} %), {:.1} s elapsed{}",
            self.label,
            k as f64 / rate_hz,
            100.0 * k as f64 / total.max(1) as f64,
            elapsed.as_secs_f64(),
            misses.map_or(String::new(), |m| format!(", {m} deadline misses so far"))
        );
    }

    fn finish(&self) {
        if let Some(bar) = &self.bar {
            if let Ok(mut shown) = SHOWN_BAR.lock() {
                *shown = None;
            }
            bar.finish_and_clear();
        }
    }
}

/// Takes the statuses, answers, setpoints, commands and plans that arrived into `o`. The
/// statuses first: the position loop publishes a tick's answers and setpoint before its
/// status, so every control up to the newest status taken is in when the rest have been
/// taken after it, and the states up to that tick can be graded (`Observer::controls_taken`).
fn take_controls(
    c: &mut Controls,
    o: &mut Observer,
) -> Result<(), stepdrive_runtime::port::PortError> {
    if let Some(sub) = c.status.as_mut() {
        while let Some(st) = sub.receive()? {
            o.status(&st);
        }
    }
    if let Some(sub) = c.acks.as_mut() {
        while let Some(a) = sub.receive()? {
            o.ack(&a);
        }
    }
    if let Some(sub) = c.setpoints.as_mut() {
        while let Some(sp) = sub.receive()? {
            o.setpoint(&sp);
        }
    }
    if let Some(sub) = c.commands.as_mut() {
        while let Some(cmd) = sub.receive()? {
            o.command(&cmd);
        }
    }
    if let Some(sub) = c.plans.as_mut() {
        while let Some(p) = sub.receive()? {
            o.plan(&p);
        }
    }
    o.controls_taken();
    Ok(())
}
