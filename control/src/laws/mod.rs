//! Control laws of Kim, Shin and Chung, as pure functions of state and parameters: no IPC,
//! no clock, no allocation.
//!
//! - [`torque_modulation`]: nonlinear torque modulation, eq. (12).
//! - [`commutation`]: desired phase currents from the torque, eq. (17).
//! - [`current_tracking`]: the nonlinear current tracking law, eq. (22), and its sampled
//!   design for a 50 µs period with compute delay.
//! - [`load_observer`]: a disturbance observer that stands in for the known τ_L of (12).
//! - [`microstepping`]: the baselines' references, eqs. (2) and (39).
//! - [`pi_current`]: the industrial baseline's PI current loop per phase.
//! - [`phasor`]: sinusoids stepped by complex multiplication, for the voltage plan.

pub mod commutation;
pub mod current_tracking;
pub mod load_observer;
pub mod microstepping;
pub mod phasor;
pub mod pi_current;
pub mod torque_modulation;
