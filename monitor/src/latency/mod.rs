//! Latency and jitter: a measurement session of the live stack beside its baselines
//! ([`session`]), the transport ping-pongs ([`pingpong`]) and cyclictest-format histogram
//! files ([`histfile`]).

pub mod histfile;
pub mod pingpong;
pub mod session;
