//! The executor every stepdrive process and simulation runs on: a [`node::Node`] is one
//! role's logic (inputs in, outputs out, no clock, no transport); the [`runner`] steps it —
//! start-up, pacing, peer timeouts, the last-sample rule, statistics, shutdown — on the wall
//! clock in a process ([`process::run_process`]) or on virtual time with other nodes in one
//! thread ([`simulation`]). Ports are traits ([`port`]) with an iceoryx2 implementation
//! ([`ipc`]) and an in-memory one ([`memory`]).
//!
//! Around it: the clocks ([`clock`], [`pacer`]), waiting and termination ([`poll`], lockstep's [`doorbell`]), real-time
//! setup ([`rt`]), the per-cycle records ([`cycle`]), the host-hold accounting ([`steal`]), lockstep's wake-up latency request ([`wakeup`]) and yielding ([`yielding`]),
//! and the deployment settings every process reads ([`deploy`]).

pub mod clock;
pub mod cycle;
pub mod deploy;
pub mod doorbell;
pub mod error;
pub mod inbox;
pub mod ipc;
pub mod lanes;
pub mod memory;
pub mod node;
pub mod pacer;
pub mod poll;
pub mod port;
pub mod process;
pub mod rt;
pub mod runner;
pub mod simulation;
pub mod steal;
pub mod wakeup;
pub mod yielding;

pub use error::RunError;
pub use node::{Awaits, Cx, Flow, Late, Node, Pace, Poll, Role, Start};
