//! The plant: the two-phase PM stepper of eq. (1) ([`model`]), a sampled drive around it with
//! supply limit, compute delay and the realtime command rules ([`sim`]), and the node that
//! runs it in the stack ([`node`]).

pub mod model;
pub mod node;
pub mod sim;
