//! The runner: everything around a [`Node`] that is the same for every role and timing
//! mode. [`Runner`] is a state machine that never waits — start-up, the cycle (poll, step,
//! bookkeeping), peer liveness, the last-sample rule, statistics and shutdown — driven by
//! [`Runner::run`] in a process (the wall clock, the wait strategies) or by
//! [`crate::simulation`] in one thread (virtual time).
//!
//! What it records for every node: cycles, the interval between cycles, the wake-up latency
//! (a clock-paced node's against its deadline, an input-paced node's timer when a `hybrid`
//! wait slept), the compute time (cycle start → [`Cx::answered`] or the end of the step),
//! inputs lost, and, for a clock-paced node, deadline misses and overruns. The node adds its
//! own figures (hops, counters).

use crate::clock::{monotonic_ns, Clock, Monotonic};
use crate::cycle::CycleRecorder;
use crate::doorbell::Waiter;
use crate::error::RunError;
use crate::node::{Awaits, Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use crate::pacer::{sleep_until, wait_until, Pacer, Tick, WaitStrategy};
use crate::poll::{termination_requested, Backoff};
use crate::port::Publish;
use crate::steal::{Slept, StealMeter, HOST_HOLD_MIN_NS};
use crate::yielding::YieldPoll;
use std::time::Duration;
use stepdrive_shared::stats::StatsReport;

/// How a runner runs its node.
#[derive(Debug, Clone)]
pub struct Settings {
    pub wait: WaitStrategy,
    /// Longest wait for the stack to come up (start-up and the first input).
    pub startup_timeout: Duration,
    /// Longest silence of a peer, once heard, before the node is stopped.
    pub peer_timeout: Duration,
    /// Account the host's holds of this thread's vCPU around each wait ([`crate::steal`]):
    /// the realtime current loop's deadline misses are split by them.
    pub account_host_holds: bool,
    /// After the final statistics, wait this long before the ports go away, so that a
    /// monitor draining at ~1 kHz takes them.
    pub linger: Duration,
    /// Log the node's end (cycles, misses) at info: a process started by hand says it is
    /// done; the dozens of stacks of an in-process study do not.
    pub report_end: bool,
}

impl Settings {
    /// Lockstep or simulation: no waiting strategy matters, no statistics linger.
    pub fn lockstep(startup_timeout: Duration, peer_timeout: Duration) -> Self {
        Self {
            wait: WaitStrategy::Sleep,
            startup_timeout,
            peer_timeout,
            account_host_holds: false,
            linger: Duration::ZERO,
            report_end: false,
        }
    }
}

/// A node's wake-up before a cycle, as the waiting driver saw it.
#[derive(Debug, Clone, Copy, Default)]
pub struct Wake {
    /// A timer's wake-up latency, when the wait slept on one.
    pub timer_latency_ns: Option<u64>,
    /// Sleeps asked for after the wake-up ([`crate::steal`]).
    pub slept: Slept,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    New,
    Starting { since_ns: u64 },
    Running,
    Done,
}

/// How long a waiting driver blocks on a node's input at most between checks of the time
/// and the termination flag.
const BLOCK_NS: u64 = 1_000_000;
/// `sleep` strategy: the nap between polls of an input-paced node with nothing to block on.
const NAP_NS: u64 = 10_000;
/// A clock-paced node acts on at most this many rings of its doorbell between two ticks: a
/// client flooding commands then costs the position loop one more tick a period at most
/// (with 2, a 100 kHz flood of moves had it taking 5-6 k a second).
pub const RINGS_PER_PERIOD: usize = 1;

/// Lockstep: empty polls before a node sleeps on its doorbell. A peer's answer on the other
/// core comes within ~1–3 µs, ~30–60 polls; a futex wake-up costs 3–8 µs on top.
const DOORBELL_SPIN_POLLS: u32 = 200;

/// A `hybrid` wait for an input due at `due_ns`, at `now_ns`: the time it sleeps to
/// (`now_ns` or before: it polls at once). It sleeps to `margin_ns` before the input; when
/// that is past, or so close that the sleep would end before the kernel switches away, it
/// rests for [`REST_SLEEP_NS`] after all, provided the rest ends [`REST_MARGIN_NS`] before
/// the input is due. An input already due is never slept for: a multi-axis node whose
/// other axes' inputs of this sample are still to come polls on.
///
/// Why the rest: a node that answers late in its period (a current loop of several axes
/// answers every axis first; the bridge forwards the answers) found its margin already past
/// and polled through to the next input without a break, every period. Beside an ordinary
/// task on its CPU (`taskset -c 1 yes`) the kernel's fair server then ran that task ahead
/// of SCHED_FIFO for ~50 ms at a time, past the plant's or drive's watchdog.
/// docs/design.md (wait strategies) and docs/measurements.md have the figures.
pub fn hybrid_sleep_target(now_ns: u64, due_ns: u64, margin_ns: u64) -> u64 {
    let ordinary = due_ns.saturating_sub(margin_ns);
    let rest = now_ns
        .saturating_add(REST_SLEEP_NS)
        .min(due_ns.saturating_sub(REST_MARGIN_NS));
    ordinary.max(rest)
}

/// The shortest sleep of a `hybrid` wait that gives the CPU away: the current loop's
/// ~7 µs sleeps of one axis do (an ordinary task on its CPU gets its share between
/// samples), ~2 µs ones return before the kernel switches.
pub const REST_SLEEP_NS: u64 = 7_000;
/// How long before its input is due a rest of a `hybrid` wait ends at the latest: the
/// timer's wake-up (p99 ~12 µs here) then still finds the input not yet published, or only
/// just (a plant publishes after its deadline, a drive's sample lands after it is sent).
pub const REST_MARGIN_NS: u64 = 10_000;

/// A node that ran to the end of its run, and its final statistics.
pub struct Finished<N> {
    pub node: N,
    pub stats: Box<StatsReport>,
}

/// One node, its ports and everything the runner keeps about it.
pub struct Runner<N: Node> {
    node: N,
    ports: N::Ports,
    settings: Settings,
    role: Role,
    pace: Pace,
    stats: Box<StatsReport>,
    stats_port: Option<Box<dyn Publish<StatsReport>>>,
    stats_every: u64,
    recorder: CycleRecorder,
    phase: Phase,
    pacer: Option<Pacer>,
    /// When the peer was last heard, and whether it has been at all.
    heard_ns: u64,
    heard_once: bool,
    last_taken_ns: Option<u64>,
    /// `Late::Pause`: time paused through stalls, ns.
    paused_ns: u64,
    steal: Option<StealMeter>,
    /// Lockstep: the doorbell this node sleeps on between inputs; clock-paced, the one that
    /// wakes it between ticks ([`Node::rung`]).
    bell: Option<Waiter>,
    /// Lockstep: whether the position loop yields or sleeps between its ticks.
    yield_poll: YieldPoll,
}

impl<N: Node> Runner<N> {
    /// `stats_port`: where statistics go (~1 Hz and at exit); `None` keeps them in the
    /// runner (lockstep, simulation).
    pub fn new(
        node: N,
        ports: N::Ports,
        settings: Settings,
        stats_port: Option<Box<dyn Publish<StatsReport>>>,
    ) -> Self {
        let role = node.role();
        let pace = node.pace();
        let period_ns = match pace {
            Pace::Clock { period_ns, .. } => period_ns,
            Pace::Input => (1e9 / node.rate_hz()).round() as u64,
        };
        // Heap-allocated once: the report is ~90 KB.
        let stats = Box::new(StatsReport {
            role: role.code(),
            ..Default::default()
        });
        let steal = (settings.account_host_holds && settings.wait != WaitStrategy::Event)
            .then(|| StealMeter::new(period_ns));
        if steal.as_ref().is_some_and(|m| !m.available()) {
            tracing::warn!(
                "no /proc/thread-self/schedstat: host holds of this loop's CPU are not measured"
            );
        }
        Self {
            stats_every: (node.rate_hz().round() as u64).max(1),
            node,
            ports,
            settings,
            role,
            pace,
            stats,
            stats_port,
            recorder: CycleRecorder::new(period_ns),
            phase: Phase::New,
            pacer: None,
            heard_ns: 0,
            heard_once: false,
            last_taken_ns: None,
            paused_ns: 0,
            steal,
            bell: None,
            yield_poll: YieldPoll::default(),
        }
    }

    /// Lockstep: sleep on `bell` between inputs instead of backing off.
    pub fn with_doorbell(mut self, bell: Option<Waiter>) -> Self {
        self.bell = bell;
        self
    }

    pub fn node(&self) -> &N {
        &self.node
    }

    pub fn role(&self) -> Role {
        self.role
    }

    pub fn stats(&self) -> &StatsReport {
        &self.stats
    }

    pub fn finished(&self) -> bool {
        self.phase == Phase::Done
    }

    /// What the node waits for, for a deadlock or timeout report.
    pub fn awaiting(&self) -> String {
        self.node.awaiting()
    }

    /// The next deadline of a started clock-paced node.
    pub fn next_deadline(&self) -> Option<u64> {
        match self.phase {
            Phase::Running => self.pacer.as_ref().map(Pacer::next_deadline),
            _ => None,
        }
    }

    /// A started clock-paced node's next tick, taken at `woke_ns` without waiting.
    pub fn take_tick(&mut self, woke_ns: u64) -> Tick {
        match &mut self.pacer {
            Some(p) => p.tick_at(woke_ns),
            None => unreachable!("take_tick before a clock-paced node started"),
        }
    }

    /// One start-up poll. True once the node runs.
    pub fn try_start(&mut self, clock: &dyn Clock) -> Result<bool, RunError> {
        let now = clock.now_ns();
        let since_ns = match self.phase {
            Phase::New => {
                self.phase = Phase::Starting { since_ns: now };
                now
            }
            Phase::Starting { since_ns } => since_ns,
            Phase::Running | Phase::Done => return Ok(true),
        };
        let mut cx = Cx::new(clock, &mut self.stats);
        match self.node.start(&mut self.ports, &mut cx)? {
            Start::Waiting => {
                if now.saturating_sub(since_ns) > self.settings.startup_timeout.as_nanos() as u64 {
                    return Err(RunError::Startup {
                        role: self.role,
                        awaiting: self.node.awaiting(),
                        timeout: self.settings.startup_timeout,
                    });
                }
                Ok(false)
            }
            Start::Ready { epoch_ns } => {
                self.node.connect(&mut self.ports)?;
                if let Pace::Clock { period_ns, .. } = self.pace {
                    let epoch = epoch_ns.unwrap_or(now);
                    self.pacer = Some(Pacer::new(epoch, period_ns, self.settings.wait));
                }
                self.heard_ns = now;
                self.phase = Phase::Running;
                tracing::debug!(role = %self.role, "started");
                Ok(true)
            }
        }
    }

    /// An input-paced node: polls once and runs the cycle if its input is there.
    pub fn try_input_cycle(
        &mut self,
        clock: &dyn Clock,
        wake: Wake,
    ) -> Result<Option<Flow>, RunError> {
        let mut cx = Cx::new(clock, &mut self.stats);
        let (fresh, skipped) = match self.node.poll(&mut self.ports, &mut cx)? {
            Poll::Pending => return Ok(None),
            Poll::Finished => {
                self.phase = Phase::Done;
                return Ok(Some(Flow::Last));
            }
            Poll::Ready { fresh, skipped } => (fresh, skipped),
        };
        let taken = cx.taken_ns.unwrap_or_else(|| clock.now_ns());
        cx.woke_ns = taken;
        let flow = self.node.step(&mut self.ports, &mut cx)?;
        let done = cx.answered_ns.unwrap_or_else(|| clock.now_ns());
        self.node.after_answers(&mut self.ports, &mut cx)?;
        let stats = &mut *self.stats;
        if let Some(prev) = self.last_taken_ns.replace(taken) {
            stats.period.record(taken.saturating_sub(prev));
        }
        if let Some(latency) = wake.timer_latency_ns {
            stats.wakeup.record(latency);
        }
        stats.compute.record(done.saturating_sub(taken));
        stats.cycles += 1;
        stats.lost += skipped;
        if let Some(meter) = &mut self.steal {
            meter.after_take(skipped, wake.slept);
        }
        if fresh {
            self.heard(taken);
        }
        self.after_cycle(clock, flow)?;
        Ok(Some(flow))
    }

    /// A clock-paced node: the cycle of deadline `tick`.
    pub fn clock_cycle(&mut self, clock: &dyn Clock, tick: Tick) -> Result<Flow, RunError> {
        let Pace::Clock { period_ns, late } = self.pace else {
            unreachable!("clock_cycle on an input-paced node")
        };
        if late == Late::Skip && tick.latency_ns() > period_ns {
            self.stats.overruns += 1;
            if let Some(p) = &mut self.pacer {
                p.skip_to(tick.woke_ns);
            }
        }
        let mut cx = Cx::new(clock, &mut self.stats);
        cx.deadline_ns = tick.deadline_ns;
        cx.woke_ns = tick.woke_ns;
        let (fresh, skipped) = match self.node.poll(&mut self.ports, &mut cx)? {
            Poll::Pending => (false, 0),
            Poll::Finished => {
                self.phase = Phase::Done;
                return Ok(Flow::Last);
            }
            Poll::Ready { fresh, skipped } => (fresh, skipped),
        };
        let flow = self.node.step(&mut self.ports, &mut cx)?;
        let done = cx.answered_ns.unwrap_or_else(|| clock.now_ns());
        self.node.after_answers(&mut self.ports, &mut cx)?;
        self.recorder
            .record(&mut self.stats, tick.deadline_ns, tick.woke_ns, done);
        self.stats.lost += skipped;
        let now = clock.now_ns();
        if fresh {
            self.heard(now);
        } else {
            self.check_alive(now)?;
        }
        if late == Late::Pause && flow == Flow::Continue {
            // The next deadline already past means the process was held up for more than
            // a period: the device's time pauses with it (see [`Late::Pause`]); the stall
            // stays visible in the wake-up and period figures.
            if let Some(p) = &mut self.pacer {
                if let Some(late_ns) = p.pause_if_late(tick.index + 1, now) {
                    self.stats.overruns += 1;
                    self.paused_ns += late_ns;
                }
            }
        }
        self.after_cycle(clock, flow)?;
        Ok(flow)
    }

    fn heard(&mut self, now: u64) {
        self.heard_ns = now;
        self.heard_once = true;
    }

    /// Fails once the peer has been silent for longer than the start-up timeout (before it
    /// was first heard) or the peer timeout.
    pub fn check_alive(&self, now: u64) -> Result<(), RunError> {
        let timeout = if self.heard_once && !self.node.awaiting_rejoin() {
            self.settings.peer_timeout
        } else {
            self.settings.startup_timeout
        };
        if now.saturating_sub(self.heard_ns) > timeout.as_nanos() as u64 {
            return Err(RunError::PeerSilent {
                role: self.role,
                awaiting: self.node.awaiting(),
                timeout,
            });
        }
        Ok(())
    }

    fn after_cycle(&mut self, clock: &dyn Clock, flow: Flow) -> Result<(), RunError> {
        match flow {
            Flow::Last => self.phase = Phase::Done,
            Flow::Continue => {
                if self.stats.cycles.is_multiple_of(self.stats_every) {
                    self.publish_stats(clock, false)?;
                }
            }
        }
        Ok(())
    }

    fn publish_stats(&mut self, clock: &dyn Clock, is_final: bool) -> Result<(), RunError> {
        self.node.report(&mut self.stats);
        let Some(port) = &mut self.stats_port else {
            return Ok(());
        };
        let stats = &mut *self.stats;
        stats.is_final = u32::from(is_final);
        stats.seq += 1;
        stats.publish_time_ns = clock.now_ns();
        port.publish(stats)?;
        Ok(())
    }

    /// Every exit path: the node stops (outputs safe); after a run that ended in order (its
    /// last cycle, or a termination signal) the final statistics go out.
    pub fn finish(&mut self, clock: &dyn Clock, completed: bool) -> Result<(), RunError> {
        let mut cx = Cx::new(clock, &mut self.stats);
        self.node.stop(&mut self.ports, &mut cx);
        self.phase = Phase::Done;
        if self.stats.overruns > 0
            && matches!(
                self.pace,
                Pace::Clock {
                    late: Late::Pause,
                    ..
                }
            )
        {
            tracing::warn!(
                role = %self.role,
                stalls = self.stats.overruns,
                paused_ms = self.paused_ns as f64 * 1e-6,
                "the host stalled this process; its simulated time paused through the stalls"
            );
        }
        if !completed {
            return Ok(());
        }
        self.publish_stats(clock, true)?;
        if self.stats_port.is_some() && !self.settings.linger.is_zero() {
            std::thread::sleep(self.settings.linger);
        }
        if self.settings.report_end {
            tracing::info!(
                role = %self.role,
                cycles = self.stats.cycles,
                misses = self.stats.misses,
                overruns = self.stats.overruns,
                "{} done",
                self.role
            );
        }
        Ok(())
    }

    /// Runs the node to the end of the run on the wall clock: waits for each cycle with the
    /// settings' strategy, stops on SIGINT/SIGTERM or a silent peer, and returns the node
    /// and its final statistics. The node's `stop` runs on every exit path.
    pub fn run(mut self) -> Result<Finished<N>, RunError> {
        let clock = Monotonic;
        let outcome = self.drive(&clock);
        // SIGINT/SIGTERM is how a served stack ends in order: its readers learn of it from
        // the final statistics (a loop that died sends none).
        let in_order = matches!(outcome, Ok(()) | Err(RunError::Terminated));
        let finished = self.finish(&clock, in_order);
        outcome.and(finished)?;
        Ok(Finished {
            node: self.node,
            stats: self.stats,
        })
    }

    fn drive(&mut self, clock: &Monotonic) -> Result<(), RunError> {
        let mut backoff = Backoff::default();
        while !self.try_start(clock)? {
            if termination_requested() {
                return Err(RunError::Terminated);
            }
            backoff.pause();
        }
        loop {
            if termination_requested() {
                return Err(RunError::Terminated);
            }
            let flow = match self.pace {
                Pace::Input => self.await_input_cycle(clock)?,
                Pace::Clock { .. } => {
                    let slept = self.take_rings(clock)?;
                    let Some(pacer) = &mut self.pacer else {
                        unreachable!("a started clock-paced node has a pacer")
                    };
                    let tick = match slept {
                        // The rest of a hybrid wait is its spin. A sleep that has nothing
                        // left to wait for must not be asked to: a `clock_nanosleep` to a
                        // time just past still waited for a timer interrupt, +25 µs here.
                        true => {
                            pacer.tick_at(wait_until(pacer.next_deadline(), WaitStrategy::Spin))
                        }
                        false => pacer.wait(),
                    };
                    self.clock_cycle(clock, tick)?
                }
            };
            if flow == Flow::Last {
                return Ok(());
            }
        }
    }

    /// A clock-paced node with a doorbell: sleeps on the doorbell until its next deadline
    /// (less its wait strategy's spin margin) instead of on the clock, and lets the node
    /// act on each ring, at most [`RINGS_PER_PERIOD`] times (a client flooding commands
    /// costs the loop that much and no more). True once it slept to that time (the rest of
    /// a hybrid wait is its spin); false when the pacer's own wait is to do it all (no
    /// doorbell, the rings used up, a spinning wait): without a ring the loop wakes once a
    /// period, as before.
    fn take_rings(&mut self, clock: &Monotonic) -> Result<bool, RunError> {
        let (Some(bell), Some(pacer)) = (&self.bell, &self.pacer) else {
            return Ok(false);
        };
        let until = match self.settings.wait {
            WaitStrategy::Sleep | WaitStrategy::Event => pacer.next_deadline(),
            WaitStrategy::Hybrid { margin_ns } => pacer.next_deadline().saturating_sub(margin_ns),
            WaitStrategy::Spin => return Ok(false),
        };
        for _ in 0..RINGS_PER_PERIOD {
            let armed = bell.arm(None);
            let now = clock.now_ns();
            if now >= until || termination_requested() {
                bell.disarm();
                return Ok(true);
            }
            bell.sleep_until(armed, until);
            let now = clock.now_ns();
            if now >= until {
                return Ok(true);
            }
            let mut cx = Cx::new(clock, &mut self.stats);
            cx.woke_ns = now;
            self.node.rung(&mut self.ports, &mut cx)?;
        }
        Ok(false)
    }

    /// Waits for an input-paced node's input and runs its cycle. `hybrid` sleeps until its
    /// margin before the input is due, then polls; `spin` polls throughout; `sleep` naps
    /// 10 µs between polls; a node with something to block on (a socket, an event) blocks
    /// there instead of napping; with no due time it backs off (spin, yield, sleep).
    fn await_input_cycle(&mut self, clock: &Monotonic) -> Result<Flow, RunError> {
        let wait = self.settings.wait;
        let due = self.node.due_ns();
        let mut wake = Wake::default();
        let mut hybrid_sleep = Slept::default();
        if let (WaitStrategy::Hybrid { margin_ns }, Some(due)) = (wait, due) {
            let now = monotonic_ns();
            let target = hybrid_sleep_target(now, due, margin_ns);
            if target > now {
                if let Some(m) = &mut self.steal {
                    m.before_sleep();
                }
                sleep_until(target);
                hybrid_sleep = Slept {
                    ns: target - now,
                    calls: 1,
                };
                wake.timer_latency_ns = Some(monotonic_ns().saturating_sub(target));
            }
        }
        self.account_wake(due.is_some(), hybrid_sleep);
        // Spinning (`spin`, `hybrid`) polls as fast as it can: the flags are checked every
        // 256 polls, and the clock read on each poll only when the spin has a budget
        // (`spin_past_due_ns`).
        let mut spinning =
            due.is_some() && matches!(wait, WaitStrategy::Spin | WaitStrategy::Hybrid { .. });
        let spin_until = match (due, self.node.spin_past_due_ns()) {
            (Some(d), Some(past)) => Some(d.saturating_add(past)),
            _ => None,
        };
        let mut backoff = Backoff::default();
        let mut polls: u32 = 0;
        // Lockstep: the poll at which the doorbell last woke the node.
        let mut rung_at: Option<u32> = None;
        loop {
            if let Some(flow) = self.try_input_cycle(clock, wake)? {
                return Ok(flow);
            }
            polls = polls.wrapping_add(1);
            if spinning {
                if polls.is_multiple_of(256) {
                    self.check_waiting(monotonic_ns())?;
                }
                if let Some(until) = spin_until {
                    spinning = monotonic_ns() <= until;
                }
                std::hint::spin_loop();
                continue;
            }
            // A node that awaits a state further off (the position loop between its ticks)
            // does not spin: on two cores its spin would take a core from the plant and the
            // current loop, which hand off every sample. It yields the CPU it shares with the
            // current loop while no one else takes it ([`YieldPoll`]), else sleeps at once.
            // Once rung it spins too: a relayed ring may come a moment before the message
            // reaches its queue. The current loop waiting for its tick's setpoint yields
            // between polls, so that the position loop beside it runs now.
            let awaits = match self.bell {
                Some(_) => self.node.awaits(),
                None => Awaits::Next,
            };
            let spin_until = match (awaits, rung_at) {
                (_, Some(at)) => at.saturating_add(DOORBELL_SPIN_POLLS),
                (Awaits::Next | Awaits::Beside, None) => DOORBELL_SPIN_POLLS,
                (Awaits::Later { .. }, None) => 0,
            };
            if self.bell.is_some() && polls < spin_until {
                match awaits {
                    Awaits::Beside => std::thread::yield_now(),
                    _ => std::hint::spin_loop(),
                }
                continue;
            }
            let now = monotonic_ns();
            if self.bell.is_some()
                && matches!(awaits, Awaits::Later { .. })
                && self.yield_poll.yields(now, self.last_taken_ns)
            {
                std::thread::yield_now();
                self.yield_poll.yielded(now, monotonic_ns());
                continue;
            }
            self.check_waiting(now)?;
            if let Some(bell) = self.bell.clone() {
                // Armed before the last poll: a message published after it rings the bell.
                let armed = bell.arm(match awaits {
                    Awaits::Later { state } => state,
                    Awaits::Next | Awaits::Beside => None,
                });
                if let Some(flow) = self.try_input_cycle(clock, wake)? {
                    bell.disarm();
                    return Ok(flow);
                }
                if bell.sleep(armed, Duration::from_nanos(BLOCK_NS)) {
                    rung_at = Some(polls);
                }
                continue;
            }
            if self.node.block(&mut self.ports, now, now + BLOCK_NS)? {
                continue;
            }
            if due.is_some() && wait == WaitStrategy::Sleep {
                sleep_until(now + NAP_NS);
                wake.slept.ns += NAP_NS;
                wake.slept.calls += 1;
            } else {
                backoff.pause();
            }
        }
    }

    fn check_waiting(&self, now: u64) -> Result<(), RunError> {
        if termination_requested() {
            return Err(RunError::Terminated);
        }
        self.check_alive(now)
    }

    /// Closes the steal meter's window at a wake-up and books the host holds it found.
    fn account_wake(&mut self, timed: bool, slept: Slept) {
        let Some(meter) = &mut self.steal else {
            return;
        };
        if !timed {
            // Before the first input there is no cycle to account for.
            meter.restart();
            return;
        }
        let Some(w) = meter.at_wake(slept) else {
            return;
        };
        let stats = &mut *self.stats;
        if w.loss.held_ns >= HOST_HOLD_MIN_NS {
            stats.host_held.record(w.loss.held_ns);
        }
        stats.host_missed += w.by_host;
        stats.queued_missed += w.by_queue;
        if w.unseen > 0 {
            tracing::debug!(window = ?w, "states skipped");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const US: u64 = 1_000;

    /// The current loop's `hybrid:35` at 20 kHz: its next sample is due 50 µs after this
    /// one's deadline (t = 0 here, so due at 50 µs).
    fn target(now_us: u64, due_us: u64) -> u64 {
        hybrid_sleep_target(now_us * US, due_us * US, 35 * US)
    }

    #[test]
    fn a_hybrid_wait_rests_when_its_margin_is_past_but_never_for_an_input_already_due() {
        // One axis, answered 8 µs into the period: 35 µs before the next sample, as before.
        assert_eq!(target(8, 50), 15 * US);
        // Answered 13 µs in, the 2 µs left to the margin would not switch: 7 µs instead.
        assert_eq!(target(13, 50), 20 * US);
        // Several axes, all answered 30 µs in: a rest of 7 µs, past the margin.
        assert_eq!(target(30, 50), 37 * US);
        // Answered 36 µs in: the rest ends 10 µs before the next sample.
        assert_eq!(target(36, 50), 40 * US);
        // 41 µs in, no time to rest: it polls at once.
        assert!(target(41, 50) <= 41 * US);
        // An axis of this sample still to answer (its input due at 0, now 20 µs in): the
        // other axes' answers come first, with no sleep between them.
        assert!(target(20, 0) <= 20 * US);
        assert!(target(5, 0) <= 5 * US);
    }
}
