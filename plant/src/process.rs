//! The plant process in lockstep mode: the plant is the clock. It publishes sample k, waits
//! for exactly the command its delay line needs, integrates one period, and repeats.
//! Nothing is dropped and nothing depends on timing, so runs are bit-identical.

use crate::sim::PlantSim;
use std::time::Duration;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::DriveCommand;
use stepdrive_shared::poll::{poll_until, WaitError};
use stepdrive_shared::services::{
    connect, publisher, publisher_count, send, subscriber, subscriber_count, try_receive, IpcError,
    Topics, LOOP_BUFFER,
};
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

pub fn run_lockstep(opts: &PlantOptions) -> Result<PlantSummary, PlantError> {
    let topics = Topics::open(&opts.instance, "plant")?;
    let commands = subscriber(&topics.command, "drive/command", LOOP_BUFFER)?;
    let states = publisher(&topics.state, "drive/state")?;

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
