//! The plant process in lockstep mode: the plant is the clock. It publishes sample k, waits
//! for exactly the command its delay line needs, integrates one period, and repeats.
//! Nothing is dropped and nothing depends on timing, so runs are bit-identical.

use crate::sim::{CommandSlot, PlantSim};
use std::time::Duration;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::DriveCommand;
use stepdrive_shared::pacer::{Pacer, WaitStrategy};
use stepdrive_shared::poll::termination_requested;
use stepdrive_shared::poll::{poll_until, WaitError};
use stepdrive_shared::rt::RtOptions;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{
    connect, drain, publish_stats, publisher, publisher_count, send, subscriber, subscriber_count,
    try_receive, IpcError, Topics, LOOP_BUFFER,
};
use stepdrive_shared::stats::{roles, CycleRecorder, StatsReport};
use stepdrive_shared::Scenario;

#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    #[error(transparent)]
    Ipc(#[from] IpcError),
    #[error("the stack did not come up within {0:?}: {1}")]
    Startup(Duration, String),
    #[error("no command for sample {seq} within {timeout:?}: is the current loop alive?")]
    CommandTimeout { seq: u64, timeout: Duration },
    #[error("protocol error: {0}")]
    Protocol(String),
    #[error("terminated by signal")]
    Terminated,
}

#[derive(Debug, Clone)]
pub struct PlantOptions {
    pub instance: String,
    pub scenario: Scenario,
    /// State subscribers to wait for before the first sample (current loop, position loop,
    /// and the monitor when one is attached).
    pub wait_subscribers: usize,
    pub startup_timeout: Duration,
    /// How long to wait for one command before declaring the current loop dead.
    pub peer_timeout: Duration,
}

#[derive(Debug, Clone, Copy)]
pub struct PlantSummary {
    pub samples: u64,
}

/// Commands may arrive ahead of the one the delay line needs; keep a few by sequence number.
const PENDING: usize = 8;

/// Waits until the current loop, the position loop and `wait_subscribers` state
/// subscribers are attached.
pub(crate) fn wait_for_stack(topics: &Topics, opts: &PlantOptions) -> Result<(), PlantError> {
    tracing::info!(
        instance = %opts.instance,
        waiting_for = opts.wait_subscribers,
        "plant up; waiting for the current loop, the position loop and subscribers"
    );
    poll_until(
        opts.startup_timeout,
        || -> Result<Option<()>, PlantError> {
            let ready = publisher_count(&topics.command) >= 1
                && publisher_count(&topics.setpoint) >= 1
                && subscriber_count(&topics.state) >= opts.wait_subscribers;
            Ok(ready.then_some(()))
        },
    )
    .map_err(|e| match e {
        WaitError::Timeout(t) => PlantError::Startup(
            t,
            format!(
                "command publishers {}, setpoint publishers {}, state subscribers {} of {}",
                publisher_count(&topics.command),
                publisher_count(&topics.setpoint),
                subscriber_count(&topics.state),
                opts.wait_subscribers
            ),
        ),
        WaitError::Terminated => PlantError::Terminated,
        WaitError::Source(e) => e,
    })?;
    Ok(())
}

pub fn run_lockstep(opts: &PlantOptions) -> Result<PlantSummary, PlantError> {
    let topics = Topics::open(&opts.instance, "plant", Mode::Lockstep)?;
    let commands = subscriber(&topics.command, "drive/command", LOOP_BUFFER)?;
    let states = publisher(&topics.state, "drive/state")?;

    wait_for_stack(&topics, opts)?;
    connect(&states)?;

    let mut sim = PlantSim::new(&opts.scenario);
    let n = opts.scenario.sample_count();
    let mut pending: [Option<DriveCommand>; PENDING] = [None; PENDING];
    tracing::info!(samples = n, "running lockstep");

    // `drain`: at the end, older commands (computed but never applied) are skipped.
    let mut wait_for = |seq: u64, drain: bool| -> Result<DriveCommand, PlantError> {
        let slot = (seq % PENDING as u64) as usize;
        poll_until(
            opts.peer_timeout,
            || -> Result<Option<DriveCommand>, PlantError> {
                if let Some(c) = pending[slot].filter(|c| c.answers_seq == seq) {
                    pending[slot] = None;
                    return Ok(Some(c));
                }
                while let Some(c) = try_receive(&commands)? {
                    if c.answers_seq == seq {
                        return Ok(Some(c));
                    }
                    if drain && c.answers_seq < seq {
                        continue;
                    }
                    if c.answers_seq < seq || c.answers_seq >= seq + PENDING as u64 {
                        return Err(PlantError::Protocol(format!(
                            "command for sample {} arrived while waiting for {seq}",
                            c.answers_seq
                        )));
                    }
                    pending[(c.answers_seq % PENDING as u64) as usize] = Some(c);
                }
                Ok(None)
            },
        )
        .map_err(|e| match e {
            WaitError::Timeout(timeout) => PlantError::CommandTimeout { seq, timeout },
            WaitError::Terminated => PlantError::Terminated,
            WaitError::Source(e) => e,
        })
    };

    for k in 0..n {
        let last = k + 1 == n;
        let mut state = sim.state(last);
        state.publish_time_ns = monotonic_ns();
        send(&states, state)?;
        if last {
            break;
        }
        let command = match sim.needed_command() {
            Some(seq) => Some(wait_for(seq, false)?),
            None => None,
        };
        sim.advance(command.as_ref());
    }
    // Let the current loop finish its last cycle before our subscriber goes away.
    wait_for(n - 1, true)?;
    tracing::info!(samples = n, "plant done");
    Ok(PlantSummary { samples: n })
}

/// Realtime settings of the plant.
#[derive(Debug, Clone)]
pub struct RealtimeOptions {
    pub wait: WaitStrategy,
    /// Misses in a row after which the outputs go off and a fault is latched.
    pub watchdog_periods: u32,
    pub rt: RtOptions,
}

/// Publishes stats about once a second (every this many samples at 20 kHz).
const STATS_EVERY: u64 = 20_000;

/// Realtime: the plant publishes sample k at its absolute deadline epoch + k·T and never
/// waits for anyone. The command for (t_k, t_{k+1}] is the one answering sample k − d; if
/// it has not arrived when the period starts, the previous voltage is held and a miss
/// counted; if it arrives later it is discarded. If the host freezes the plant for more than
/// a period, simulated time pauses (the schedule is re-anchored) and an overrun is counted.
pub fn run_realtime(opts: &PlantOptions, rto: &RealtimeOptions) -> Result<StatsReport, PlantError> {
    let topics = Topics::open(&opts.instance, "plant", Mode::Realtime)?;
    let commands = subscriber(&topics.command, "drive/command", LOOP_BUFFER)?;
    let plans = subscriber(&topics.plan, "drive/plan", LOOP_BUFFER)?;
    let states = publisher(&topics.state, "drive/state")?;
    let stats_pub = publisher(&topics.stats, "monitor/stats")?;
    rto.rt
        .apply()
        .map_err(|e| PlantError::Protocol(e.to_string()))?;
    wait_for_stack(&topics, opts)?;
    connect(&states)?;

    let s = &opts.scenario;
    let n = s.sample_count();
    let period_ns = s.sample_period_ns();
    let delay = u64::from(s.rates.compute_delay_periods);
    let mut sim = PlantSim::new(s);
    let mut slot = CommandSlot::new(delay);
    // Heap-allocated once: the report is ~90 KB.
    let mut stats = Box::new(StatsReport {
        role: roles::PLANT,
        ..Default::default()
    });
    // Start a little in the future so every process is in its loop at the first deadline.
    let epoch = monotonic_ns() + 20_000_000;
    let mut pacer = Pacer::new(epoch, period_ns, rto.wait);
    let mut recorder = CycleRecorder::new(period_ns);
    tracing::info!(samples = n, wait = %rto.wait, "running realtime");

    let mut paused_ns = 0u64;
    while sim.sample_index() < n {
        if termination_requested() {
            return Err(PlantError::Terminated);
        }
        let k = sim.sample_index();
        let tick = pacer.wait();
        let last = k + 1 == n;
        let mut state = sim.state(last);
        state.deadline_ns = tick.deadline_ns;
        state.publish_time_ns = monotonic_ns();
        send(&states, state)?;
        if last {
            break;
        }
        // Everything that arrived since the last period.
        let next_needed = k.saturating_sub(delay);
        while let Some(c) = try_receive(&commands)? {
            let now = monotonic_ns();
            stats.hop.record(now.saturating_sub(c.publish_time_ns));
            stats
                .sensor_to_actuator
                .record(c.publish_time_ns.saturating_sub(c.state_publish_time_ns));
            slot.offer(c, next_needed);
        }
        // In place: a plan is ~2 KB and only the freshest is kept.
        drain(&plans, |plan| slot.offer_plan(plan))?;
        if sim.advance_realtime(&mut slot, rto.watchdog_periods) {
            tracing::error!(
                periods = slot.runs.current,
                "no command for the watchdog's periods: outputs off, fault latched"
            );
        }
        // The next deadline already past means the host held us up for more than a period.
        // The simulated drive is hardware that does not stall, so its time pauses with us:
        // the schedule is re-anchored one period from now and an overrun is counted (the
        // stall stays visible in the wake-up and period figures). Catching up instead would
        // publish samples back to back and charge the current loop for periods it was
        // never given.
        if let Some(late) = pacer.pause_if_late(sim.sample_index(), monotonic_ns()) {
            stats.overruns += 1;
            paused_ns += late;
        }
        // The plant's misses are the commands it lacked (`slot`); its own lateness shows as
        // overruns, so the recorder's miss count is not used here.
        recorder.record(&mut stats, tick.deadline_ns, tick.woke_ns, monotonic_ns());
        if stats.cycles % STATS_EVERY == 0 {
            slot.copy_counters(&mut stats);
            publish_stats(&stats_pub, &mut stats, false)?;
        }
    }
    if stats.overruns > 0 {
        tracing::warn!(
            stalls = stats.overruns,
            paused_ms = paused_ns as f64 * 1e-6,
            "the host stalled the plant; simulated time paused through the stalls"
        );
    }
    slot.copy_counters(&mut stats);
    publish_stats(&stats_pub, &mut stats, true)?;
    tracing::info!(
        samples = n,
        misses = slot.misses,
        overruns = stats.overruns,
        miss_runs_1_2_4_8_16_32_64_128 = ?slot.runs.by_length,
        "plant done"
    );
    Ok(*stats)
}
