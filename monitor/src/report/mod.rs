//! What a run's figures are and how they are told: the metrics from the state stream
//! ([`metrics`]), the loops' timing ([`timing`]), how a run ended ([`outcome`]: exit codes
//! and headlines), the table and JSON document ([`table`]), and θ_d from the position
//! loop's setpoints ([`setpoints`]).

pub mod metrics;
pub mod outcome;
pub mod setpoints;
pub mod table;
pub mod timing;
