//! Launching and supervising a stack: its processes ([`launcher`]), tools that attach to a
//! running one ([`attach`]), and RT throttling lifted for a run ([`throttling`]).

pub mod attach;
pub mod launcher;
pub mod throttling;
