//! The operator's console: launches and supervises the stack ([`launcher`]), computes the
//! metrics from the plant's state stream ([`metrics`]), runs the same nodes in one process as
//! a reference ([`simulate`]), reports ([`report`], [`timing`]), and measures latency against
//! baselines ([`latency`], [`pingpong`], [`histfile`]), and says how a run ended
//! ([`outcome`]: exit codes and headlines).

pub mod attach;
pub mod histfile;
pub mod identify;
pub mod latency;
pub mod launcher;
pub mod metrics;
pub mod outcome;
pub mod pingpong;
pub mod plot;
pub mod recording;
pub mod report;
pub mod robustness;
pub mod scope;
pub mod simulate;
pub mod throttling;
pub mod timing;
