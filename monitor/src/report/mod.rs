//! What a run's figures are and how they are told: the metrics from the state stream
//! ([`metrics`]), the loops' timing ([`timing`]), how a run ended ([`outcome`]: exit codes
//! and headlines), and the table and JSON document ([`table`]).

pub mod metrics;
pub mod outcome;
pub mod table;
pub mod timing;
