//! The contract between stepdrive's processes: the message types ([`messages`], [`stats`]),
//! the topics they travel on and the settings every opener uses ([`services`]), the scenario
//! with motor parameters, gains, rates and trajectory ([`scenario`], [`trajectory`]), and the
//! DQ frame the metrics and laws share ([`frames`]). No process logic lives here: timing,
//! ports and the runner are `stepdrive-runtime`'s.

pub mod axis;
pub mod frames;
pub mod messages;
pub mod plant;
pub mod scenario;
pub mod services;
pub mod stack;
pub mod stats;
pub mod trajectory;
pub mod wire;

pub use messages::{DriveCommand, DriveState, TorqueSetpoint};
pub use scenario::{Method, Mode, Scenario, ScenarioError};
