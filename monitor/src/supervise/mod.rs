//! Launching and supervising a stack: its processes ([`children`], started from the stack's
//! declaration by the [`launcher`]), the one [`supervisor`] and its per-message rules
//! ([`observer`]), tools that attach to a running stack ([`attach`]), RT throttling lifted
//! for a run ([`throttling`]) and the CPUs a realtime stack claims ([`cpus`]).

pub mod attach;
pub mod children;
pub mod cpus;
pub mod helpers;
pub mod launcher;
pub mod observer;
pub mod standstill;
pub mod supervisor;
pub mod throttling;
