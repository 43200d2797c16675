//! The current-loop and position-loop processes in lockstep mode. Each answers every plant
//! sample it is due to answer, in order; the plant waits for them, so results do not depend
//! on timing.

use crate::current_loop::CurrentLoop;
use crate::position_loop::PositionLoop;
use std::fmt::Debug;
use std::time::Duration;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::{state_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::pacer::{await_message, Arrival, Pacer, WaitHooks, WaitStrategy};
use stepdrive_shared::poll::termination_requested;
use stepdrive_shared::poll::{poll_until, WaitError};
use stepdrive_shared::rt::RtOptions;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{
    connect, listener, publish_stats, publisher, send, subscriber, try_receive, wait_event,
    IpcError, Listener, Message, Sub, Topics, LOOP_BUFFER,
};
use stepdrive_shared::stats::{roles, CycleRecorder, StatsReport};
use stepdrive_shared::steal::{Slept, StealMeter, HOST_HOLD_MIN_NS};
use stepdrive_shared::{Method, Scenario};

#[derive(Debug, thiserror::Error)]
pub enum ControllerError {
    #[error(transparent)]
    Ipc(#[from] IpcError),
    #[error("nothing on {what} within {timeout:?}: is the {peer} alive?")]
    PeerTimeout {
        what: &'static str,
        peer: &'static str,
        timeout: Duration,
    },
    #[error("protocol error: {0}")]
    Protocol(String),
    #[error("terminated by signal")]
    Terminated,
}

#[derive(Debug, Clone)]
pub struct LoopOptions {
    pub instance: String,
    pub scenario: Scenario,
    /// Longest wait for the first sample (the stack is starting).
    pub startup_timeout: Duration,
    /// Longest wait for any later message before the peer is declared dead.
    pub peer_timeout: Duration,
}

fn receive_next<T: Debug + Copy + Message + 'static>(
    sub: &Sub<T>,
    timeout: Duration,
    what: &'static str,
    peer: &'static str,
) -> Result<T, ControllerError> {
    poll_until(timeout, || try_receive(sub)).map_err(|e| wait_error(e, what, peer))
}

fn wait_error(e: WaitError<IpcError>, what: &'static str, peer: &'static str) -> ControllerError {
    match e {
        WaitError::Timeout(timeout) => ControllerError::PeerTimeout {
            what,
            peer,
            timeout,
        },
        WaitError::Terminated => ControllerError::Terminated,
        WaitError::Source(e) => ControllerError::Ipc(e),
    }
}

/// Receives the next state and checks it is the one expected (no gaps in lockstep).
fn next_state(
    states: &Sub<DriveState>,
    expected: u64,
    opts: &LoopOptions,
) -> Result<DriveState, ControllerError> {
    let timeout = if expected == 0 {
        opts.startup_timeout
    } else {
        opts.peer_timeout
    };
    let state = receive_next(states, timeout, "drive/state", "plant")?;
    if state.seq != expected {
        return Err(ControllerError::Protocol(format!(
            "expected state sample {expected}, got {} (lockstep never skips)",
            state.seq
        )));
    }
    Ok(state)
}

#[derive(Debug, Clone, Copy)]
pub struct LoopSummary {
    pub cycles: u64,
}

pub fn run_current_loop(
    opts: &LoopOptions,
    method: Method,
) -> Result<LoopSummary, ControllerError> {
    let topics = Topics::open(&opts.instance, "current-loop", Mode::Lockstep)?;
    // Subscribers first: the plant starts once our command publisher exists.
    let states = subscriber(&topics.state, "drive/state", LOOP_BUFFER)?;
    let setpoints = subscriber(&topics.setpoint, "control/setpoint", LOOP_BUFFER)?;
    let commands = publisher(&topics.command, "drive/command")?;
    // The lockstep plant waits for every command, so it never needs a plan.
    let mut body = CurrentLoop::new(&opts.scenario, method).with_plan_periods(0);
    let ratio = opts.scenario.rate_ratio();
    let mut setpoint = TorqueSetpoint::default();
    tracing::info!(instance = %opts.instance, %method, "current loop up");
    let mut k = 0;
    loop {
        let state = next_state(&states, k, opts)?;
        if state.seq % ratio == 0 {
            setpoint = receive_next(
                &setpoints,
                opts.peer_timeout,
                "control/setpoint",
                "position loop",
            )?;
            if setpoint.from_state_seq != state.seq {
                return Err(ControllerError::Protocol(format!(
                    "setpoint computed from sample {} arrived for sample {}",
                    setpoint.from_state_seq, state.seq
                )));
            }
        }
        if k == 0 {
            connect(&commands)?;
        }
        let mut command = body.on_sample(&state, &setpoint);
        command.publish_time_ns = monotonic_ns();
        send(&commands, command)?;
        k += 1;
        if state.flags & state_flags::LAST != 0 {
            break;
        }
    }
    tracing::info!(cycles = k, "current loop done");
    Ok(LoopSummary { cycles: k })
}

pub fn run_position_loop(opts: &LoopOptions) -> Result<LoopSummary, ControllerError> {
    let topics = Topics::open(&opts.instance, "position-loop", Mode::Lockstep)?;
    let states = subscriber(&topics.state, "drive/state", LOOP_BUFFER)?;
    let setpoints = publisher(&topics.setpoint, "control/setpoint")?;
    let mut body = PositionLoop::new(&opts.scenario);
    let ratio = opts.scenario.rate_ratio();
    tracing::info!(instance = %opts.instance, ratio, "position loop up");
    let mut k = 0;
    let mut ticks = 0;
    loop {
        let state = next_state(&states, k, opts)?;
        if state.seq % ratio == 0 {
            if ticks == 0 {
                connect(&setpoints)?;
            }
            let mut sp = body.on_tick(&state);
            sp.publish_time_ns = monotonic_ns();
            send(&setpoints, sp)?;
            ticks += 1;
        }
        k += 1;
        if state.flags & state_flags::LAST != 0 {
            break;
        }
    }
    tracing::info!(ticks, "position loop done");
    Ok(LoopSummary { cycles: ticks })
}

/// Realtime settings of a control loop.
#[derive(Debug, Clone)]
pub struct RealtimeLoopOptions {
    pub wait: WaitStrategy,
    pub rt: RtOptions,
}

/// Waits (per `wait`, see [`await_message`]) for the next state and takes the newest one
/// queued: older ones are stale for a realtime loop and show up as lost by sequence gap.
fn await_newest<T: Debug + Copy + Message + 'static>(
    sub: &Sub<T>,
    wait: WaitStrategy,
    expected_ns: u64,
    timeout: Duration,
    hooks: &mut impl WaitHooks,
    peer: &'static str,
    what: &'static str,
) -> Result<Arrival<T>, ControllerError> {
    await_message(wait, expected_ns, timeout, hooks, || newest(sub))
        .map_err(|e| wait_error(e, what, peer))
}

/// Waits for the next state by blocking on the producer's event (see [`WaitStrategy::Event`])
/// and takes the newest one queued.
fn await_event(
    sub: &Sub<DriveState>,
    ready: &Listener,
    timeout: Duration,
) -> Result<Arrival<DriveState>, ControllerError> {
    let start = monotonic_ns();
    loop {
        if let Some(message) = newest(sub)? {
            return Ok(Arrival {
                message,
                taken_ns: monotonic_ns(),
                timer_latency_ns: None,
                slept_after_wake: Slept::default(),
            });
        }
        if termination_requested() {
            return Err(ControllerError::Terminated);
        }
        if monotonic_ns() - start > timeout.as_nanos() as u64 {
            return Err(ControllerError::PeerTimeout {
                what: "drive/state",
                peer: "plant",
                timeout,
            });
        }
        wait_event(ready, Duration::from_millis(1))?;
    }
}

/// The newest queued message, if any (older ones are dropped).
fn newest<T: Debug + Copy + Message + 'static>(sub: &Sub<T>) -> Result<Option<T>, IpcError> {
    let mut newest = None;
    while let Some(m) = try_receive(sub)? {
        newest = Some(m);
    }
    Ok(newest)
}

/// The current loop's steal accounting around its wait (see [`StealMeter`]), booked into
/// its statistics: host holds, and the skipped states the host and guest queueing explain.
struct Accounting<'a> {
    meter: &'a mut StealMeter,
    stats: &'a mut StatsReport,
}

impl WaitHooks for Accounting<'_> {
    fn before_sleep(&mut self) {
        self.meter.before_sleep();
    }

    fn on_wake(&mut self, slept: Slept) {
        let Some(w) = self.meter.at_wake(slept) else {
            return;
        };
        if w.loss.held_ns >= HOST_HOLD_MIN_NS {
            self.stats.host_held.record(w.loss.held_ns);
        }
        self.stats.host_missed += w.by_host;
        self.stats.queued_missed += w.by_queue;
        if w.unseen > 0 {
            tracing::debug!(window = ?w, "states skipped");
        }
    }
}

/// Realtime current loop: woken by each state sample (by polling, see `await_newest`),
/// it answers the newest one with the latest setpoint. Its deadline for sample k is the
/// plant's deadline k + d (the period the answer is applied in).
pub fn run_current_loop_realtime(
    opts: &LoopOptions,
    method: Method,
    rto: &RealtimeLoopOptions,
) -> Result<StatsReport, ControllerError> {
    let topics = Topics::open(&opts.instance, "current-loop", Mode::Realtime)?;
    let states = subscriber(&topics.state, "drive/state", LOOP_BUFFER)?;
    let setpoints = subscriber(&topics.setpoint, "control/setpoint", LOOP_BUFFER)?;
    let stats_pub = publisher(&topics.stats, "monitor/stats")?;
    // Real-time setup (mlockall faults in every mapped segment) before the command
    // publisher exists: the plant starts its clock once it sees that publisher.
    rto.rt
        .apply()
        .map_err(|e| ControllerError::Protocol(e.to_string()))?;
    let commands = publisher(&topics.command, "drive/command")?;
    let plans = publisher(&topics.plan, "drive/plan")?;
    // `event`: woken by the bridge's state-ready event (hardware mode) instead of a clock.
    let ready = match rto.wait {
        WaitStrategy::Event => Some(listener(&topics.state_ready()?)?),
        _ => None,
    };
    let s = &opts.scenario;
    let period_ns = s.sample_period_ns();
    let answer_budget_ns = period_ns * u64::from(s.rates.compute_delay_periods.max(1));
    let mut body = CurrentLoop::new(s, method);
    let mut setpoint = TorqueSetpoint::default();
    let mut stats = Box::new(StatsReport {
        role: roles::CURRENT_LOOP,
        ..Default::default()
    });
    tracing::info!(instance = %opts.instance, %method, wait = %rto.wait, "current loop up (realtime)");
    let mut steal = StealMeter::new(period_ns);
    if !steal.available() {
        tracing::warn!(
            "no /proc/thread-self/schedstat: host holds of this loop's CPU are not measured"
        );
    }
    let mut expected_ns = 0;
    let mut last_seq: Option<u64> = None;
    let mut prev_start = 0;
    loop {
        let timeout = if last_seq.is_none() {
            opts.startup_timeout
        } else {
            opts.peer_timeout
        };
        let arrival = if last_seq.is_none() {
            // Before the first sample there is no deadline to time against: a back-off
            // poll, not a spin that would hold this CPU from processes starting on it.
            let first = poll_until(timeout, || newest(&states))
                .map_err(|e| wait_error(e, "drive/state", "plant"))?;
            steal.restart();
            Arrival {
                message: first,
                taken_ns: monotonic_ns(),
                timer_latency_ns: None,
                slept_after_wake: Slept::default(),
            }
        } else if let Some(ready) = &ready {
            steal.restart();
            await_event(&states, ready, timeout)?
        } else {
            await_newest(
                &states,
                rto.wait,
                expected_ns,
                timeout,
                &mut Accounting {
                    meter: &mut steal,
                    stats: &mut stats,
                },
                "plant",
                "drive/state",
            )?
        };
        let (state, start) = (arrival.message, arrival.taken_ns);
        if let Some(prev) = last_seq {
            let unseen = state.seq.saturating_sub(prev + 1);
            stats.lost += unseen;
            steal.after_take(unseen, arrival.slept_after_wake);
            stats.period.record(start - prev_start);
        } else {
            connect(&commands)?;
            connect(&plans)?;
        }
        last_seq = Some(state.seq);
        prev_start = start;
        // Wake-up latency is the timer's (comparable with cyclictest); a spinning loop has none.
        if let Some(l) = arrival.timer_latency_ns {
            stats.wakeup.record(l);
        }
        stats
            .hop
            .record(start.saturating_sub(state.publish_time_ns));
        while let Some(sp) = try_receive(&setpoints)? {
            setpoint = sp;
        }
        let mut command = body.on_sample(&state, &setpoint);
        command.publish_time_ns = monotonic_ns();
        send(&commands, command)?;
        let done = monotonic_ns();
        stats.compute.record(done - start);
        if done > state.deadline_ns + answer_budget_ns {
            stats.misses += 1;
        }
        // After the command, so that planning never delays it.
        let mut plan = *body.plan();
        if plan.len > 0 {
            plan.publish_time_ns = monotonic_ns();
            send(&plans, plan)?;
        }
        stats.cycles += 1;
        expected_ns = state.deadline_ns + period_ns;
        if state.flags & state_flags::LAST != 0 {
            break;
        }
        if stats.cycles % 20_000 == 0 {
            publish_stats(&stats_pub, &mut stats, false)?;
        }
    }
    publish_stats(&stats_pub, &mut stats, true)?;
    tracing::info!(
        cycles = stats.cycles,
        misses = stats.misses,
        "current loop done"
    );
    Ok(*stats)
}

/// Realtime position loop: its own clock at the position rate, started on the plant's
/// deadline grid shifted by half a current period, reading the newest state at each tick.
/// It does not chase the plant's re-anchoring: it only needs the newest state.
pub fn run_position_loop_realtime(
    opts: &LoopOptions,
    rto: &RealtimeLoopOptions,
) -> Result<StatsReport, ControllerError> {
    let topics = Topics::open(&opts.instance, "position-loop", Mode::Realtime)?;
    let states = subscriber(&topics.state, "drive/state", LOOP_BUFFER)?;
    let stats_pub = publisher(&topics.stats, "monitor/stats")?;
    // As in the current loop: set up before the publisher the plant waits for.
    rto.rt
        .apply()
        .map_err(|e| ControllerError::Protocol(e.to_string()))?;
    let setpoints = publisher(&topics.setpoint, "control/setpoint")?;
    let s = &opts.scenario;
    let period_ns = s.sample_period_ns();
    let tick_ns = period_ns * s.rate_ratio();
    let mut body = PositionLoop::new(s);
    let mut stats = Box::new(StatsReport {
        role: roles::POSITION_LOOP,
        ..Default::default()
    });
    // The first state tells where the plant's deadline grid is (a cheap back-off poll:
    // at this priority a 10 µs sleep loop would crowd the plant's CPU while it starts).
    let first = receive_next(&states, opts.startup_timeout, "drive/state", "plant")?;
    connect(&setpoints)?;
    let epoch = first.deadline_ns - first.seq * period_ns + period_ns / 2;
    let mut pacer = Pacer::new(epoch, tick_ns, rto.wait);
    pacer.skip_to(monotonic_ns());
    tracing::info!(instance = %opts.instance, wait = %rto.wait, "position loop up (realtime)");
    let mut latest = first;
    let mut last_used: Option<u64> = None;
    let mut recorder = CycleRecorder::new(tick_ns);
    let mut last_seen_at = monotonic_ns();
    loop {
        if termination_requested() {
            return Err(ControllerError::Terminated);
        }
        let tick = pacer.wait();
        if tick.latency_ns() > tick_ns {
            stats.overruns += 1;
            pacer.skip_to(tick.woke_ns);
        }
        let mut fresh = false;
        while let Some(st) = try_receive(&states)? {
            stats.lost += st.seq.saturating_sub(latest.seq + 1);
            latest = st;
            fresh = true;
        }

        let now = monotonic_ns();
        if fresh {
            last_seen_at = now;
            stats.hop.record(now.saturating_sub(latest.publish_time_ns));
        } else if now - last_seen_at > opts.peer_timeout.as_nanos() as u64 {
            return Err(ControllerError::PeerTimeout {
                what: "drive/state",
                peer: "plant",
                timeout: opts.peer_timeout,
            });
        }
        if last_used != Some(latest.seq) {
            let mut sp = body.on_tick(&latest);
            sp.publish_time_ns = monotonic_ns();
            send(&setpoints, sp)?;
            last_used = Some(latest.seq);
        }
        // A miss: the tick finished after the next tick was due.
        recorder.record(&mut stats, tick.deadline_ns, tick.woke_ns, monotonic_ns());
        if latest.flags & state_flags::LAST != 0 {
            break;
        }
        if stats.cycles % 2_000 == 0 {
            publish_stats(&stats_pub, &mut stats, false)?;
        }
    }
    publish_stats(&stats_pub, &mut stats, true)?;
    tracing::info!(ticks = stats.cycles, "position loop done");
    Ok(*stats)
}
