//! The operator's console: launches and supervises the stack ([`launcher`]), computes the
//! metrics from the plant's state stream ([`metrics`]), runs the same loop bodies in one
//! process as a reference ([`simulate`]), and reports ([`report`]).

pub mod latency;
pub mod launcher;
pub mod metrics;
pub mod pingpong;
pub mod report;
pub mod simulate;
pub mod timing;
