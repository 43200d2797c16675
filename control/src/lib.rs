//! The controller's pure part: the paper's control laws ([`laws`]), the two loop bodies
//! built from them ([`position_loop`], [`current_loop`]), the axis a program commands
//! ([`axis`]: state machine, trajectory generation, safety envelope), and the
//! identification sequence with its fits ([`identify`]). Pure functions of state and parameters: no IPC, no clock,
//! no allocation in a cycle. This crate depends on neither iceoryx2 nor the runtime, so
//! drive firmware and tests can take the laws alone; the nodes that run the bodies in the
//! stack are `stepdrive-controller`'s.

pub mod axis;
pub mod current_loop;
pub mod identify;
pub mod laws;
pub mod position_loop;
pub mod stale;
