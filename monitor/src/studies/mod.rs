//! Studies run in one process on virtual time: the stack simulated with in-memory ports
//! ([`simulate`]), the robustness table ([`robustness`]) and the identification of a
//! motor ([`identify`]).

pub mod identify;
pub mod robustness;
pub mod simulate;
