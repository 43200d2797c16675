//! Launching and supervising a stack: its processes ([`children`], started from the stack's
//! declaration by the [`launcher`]), the one [`supervisor`] and its per-message rules
//! ([`observer`]), tools that attach to a running stack ([`attach`]), and RT throttling
//! lifted for a run ([`throttling`]).

pub mod attach;
pub mod children;
pub mod launcher;
pub mod observer;
pub mod supervisor;
pub mod throttling;
