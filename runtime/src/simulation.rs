//! Several runners stepped in one thread on virtual time, with in-memory ports
//! ([`crate::memory`]): the same nodes and the same runner as the processes, without
//! processes, clocks or waiting. Deterministic by construction.
//!
//! Each round gives every member, in order, one chance to start or to run a cycle at the
//! current virtual time. When a round and the one after it change nothing, time moves to
//! the earliest deadline of a clock-paced member; with none, the stack is stuck (a
//! deadlock is reported with what each member waits for). Order breaks ties: at the same
//! instant, earlier members run first.
//!
//! A member can be held for a span of virtual time ([`Hold`]), as the host holds a
//! process: it does nothing then, and finds its inputs piled up afterwards.

use crate::clock::{Clock, VirtualClock};
use crate::error::RunError;
use crate::node::{Node, Pace, Role};
use crate::runner::{Runner, Wake};
use std::ops::Range;
use stepdrive_shared::stats::StatsReport;

/// What the simulation needs of a runner; every [`Runner`] is one.
pub trait Member {
    fn role(&self) -> Role;
    /// Starts, or runs a cycle, if it can at `clock`'s time. True if it did.
    fn advance(&mut self, clock: &VirtualClock) -> Result<bool, RunError>;
    fn next_deadline(&self) -> Option<u64>;
    fn finished(&self) -> bool;
    fn awaiting(&self) -> String;
    /// Its statistics so far.
    fn stats(&self) -> &StatsReport;
    /// The run is over (every member done, or an error): stop the node.
    fn finish(&mut self, clock: &VirtualClock, completed: bool) -> Result<(), RunError>;
}

impl<N: Node> Member for Runner<N> {
    fn role(&self) -> Role {
        Runner::role(self)
    }

    fn advance(&mut self, clock: &VirtualClock) -> Result<bool, RunError> {
        if self.finished() {
            return Ok(false);
        }
        if self.next_deadline().is_none() && !self.try_start(clock)? {
            return Ok(false);
        }
        match self.node().pace() {
            Pace::Input => Ok(self.try_input_cycle(clock, Wake::default())?.is_some()),
            Pace::Clock { .. } => match self.next_deadline() {
                Some(deadline) if deadline <= clock.now_ns() => {
                    let tick = self.take_tick(clock.now_ns());
                    self.clock_cycle(clock, tick)?;
                    Ok(true)
                }
                _ => Ok(false),
            },
        }
    }

    fn next_deadline(&self) -> Option<u64> {
        Runner::next_deadline(self)
    }

    fn finished(&self) -> bool {
        Runner::finished(self)
    }

    fn awaiting(&self) -> String {
        Runner::awaiting(self)
    }

    fn stats(&self) -> &StatsReport {
        Runner::stats(self)
    }

    fn finish(&mut self, clock: &VirtualClock, completed: bool) -> Result<(), RunError> {
        Runner::finish(self, clock, completed)
    }
}

/// A member held (not stepped) over a span of virtual time, ns.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Hold {
    pub role: Role,
    pub during_ns: Range<u64>,
}

/// Runs `members` to the end of the run: until every one is finished. Every member is
/// stopped on every exit path.
pub fn run(members: &mut [&mut dyn Member], holds: &[Hold]) -> Result<(), RunError> {
    let clock = VirtualClock::default();
    let outcome = step_all(&clock, members, holds);
    let mut stopped = Ok(());
    for m in members.iter_mut() {
        let r = m.finish(&clock, outcome.is_ok());
        if stopped.is_ok() {
            stopped = r;
        }
    }
    outcome.and(stopped)
}

fn step_all(
    clock: &VirtualClock,
    members: &mut [&mut dyn Member],
    holds: &[Hold],
) -> Result<(), RunError> {
    let held = |role: Role, now: u64| {
        holds
            .iter()
            .any(|h| h.role == role && h.during_ns.contains(&now))
    };
    let mut idle_rounds = 0;
    loop {
        let now = clock.now_ns();
        let mut progress = false;
        for m in members.iter_mut() {
            if m.finished() || held(m.role(), now) {
                continue;
            }
            progress |= m.advance(clock)?;
        }
        if members.iter().all(|m| m.finished()) {
            return Ok(());
        }
        if progress {
            idle_rounds = 0;
            continue;
        }
        // A member may have published without running a cycle (a lockstep plant emits its
        // state, then waits): give everyone a second look before moving time.
        idle_rounds += 1;
        if idle_rounds < 2 {
            continue;
        }
        idle_rounds = 0;
        let next = members
            .iter()
            .filter(|m| !m.finished())
            .filter_map(|m| m.next_deadline())
            .filter(|&t| t > now)
            .min();
        match next {
            Some(t) => clock.set(t),
            None => {
                let waiting: Vec<String> = members
                    .iter()
                    .filter(|m| !m.finished())
                    .map(|m| format!("the {} waits for {}", m.role(), m.awaiting()))
                    .collect();
                return Err(RunError::Deadlock(waiting.join("; ")));
            }
        }
    }
}
