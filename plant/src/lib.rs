//! The plant: the two-phase PM stepper of eq. (1) ([`model`]), a sampled drive around it with
//! supply limit and compute delay ([`sim`]), and the process that serves it over iceoryx2
//! ([`process`]).

pub mod bridge;
pub mod drive_protocol;
pub mod drive_units;
pub mod emulator;
pub mod model;
pub mod process;
pub mod sim;
pub mod wire;
