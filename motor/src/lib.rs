//! The motor of eq. (1) and what acts on its rotor, as pure functions of state and
//! parameters: no clock, no I/O, no allocation, no `std` without the `std` feature. The
//! plant process, the emulated drive and the drive firmware's simulated power stage all
//! integrate this one model.
//!
//! - [`model`]: eq. (1), x = (θ, ω, i_a, i_b), integrated by RK4 with sub-steps; with the
//!   holding brake.
//! - [`load`]: the load torque opposing +θ: a constant, steps, ramps, Coulomb friction and
//!   detent ([`Disturbance`]).
//! - [`bus`]: phase voltages limited to ±V_bus.

#![cfg_attr(not(feature = "std"), no_std)]

pub mod bus;
pub mod load;
mod math;
pub mod model;

pub use load::{Disturbance, LoadRamp, LoadStep};
pub use model::{Motor, MotorState, I_A, I_B, OMEGA, THETA};
