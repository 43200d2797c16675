//! The plant: a sampled drive around the motor of eq. (1) (`stepdrive-motor`), with supply
//! limit, compute delay and the realtime command rules ([`sim`]), and the node that runs it
//! in the stack ([`node`]).

pub mod node;
pub mod sim;
