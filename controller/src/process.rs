//! The current-loop and position-loop processes in lockstep mode. Each answers every plant
//! sample it is due to answer, in order; the plant waits for them, so results do not depend
//! on timing.

use crate::current_loop::CurrentLoop;
use crate::position_loop::PositionLoop;
use std::fmt::Debug;
use std::time::Duration;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::{state_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::poll::{poll_until, WaitError};
use stepdrive_shared::services::{
    connect, publisher, send, subscriber, try_receive, IpcError, Message, Sub, Topics, LOOP_BUFFER,
};
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
    poll_until(timeout, || try_receive(sub)).map_err(|e| match e {
        WaitError::Timeout(timeout) => ControllerError::PeerTimeout {
            what,
            peer,
            timeout,
        },
        WaitError::Terminated => ControllerError::Terminated,
        WaitError::Source(e) => ControllerError::Ipc(e),
    })
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
    let topics = Topics::open(&opts.instance, "current-loop")?;
    // Subscribers first: the plant starts once our command publisher exists.
    let states = subscriber(&topics.state, "drive/state", LOOP_BUFFER)?;
    let setpoints = subscriber(&topics.setpoint, "control/setpoint", LOOP_BUFFER)?;
    let commands = publisher(&topics.command, "drive/command")?;
    let mut body = CurrentLoop::new(&opts.scenario, method);
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
    let topics = Topics::open(&opts.instance, "position-loop")?;
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
