//! The contract between stepdrive's processes: message types and service names
//! ([`messages`], [`services`]), the scenario with motor parameters, gains, rates and
//! trajectory ([`scenario`], [`trajectory`]), and the small timing and waiting helpers every
//! loop uses ([`clock`], [`poll`]). No process logic lives here.

pub mod clock;
pub mod frames;
pub mod messages;
pub mod pacer;
pub mod poll;
pub mod rt;
pub mod scenario;
pub mod services;
pub mod stats;
pub mod steal;
pub mod trajectory;

pub use messages::{DriveCommand, DriveState, TorqueSetpoint};
pub use scenario::{Method, Scenario, ScenarioError};
