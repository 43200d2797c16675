//! The position/torque loop body: trajectory generation and torque modulation (12), one
//! tick per position-loop period. Pure: the process wrapper supplies state and time.

use crate::laws::torque_modulation::TorqueModulation;
use stepdrive_shared::messages::{DriveState, TorqueSetpoint};
use stepdrive_shared::trajectory::Trapezoid;
use stepdrive_shared::Scenario;

#[derive(Debug, Clone)]
pub struct PositionLoop {
    law: TorqueModulation,
    trajectory: Trapezoid,
    ticks: u64,
}

impl PositionLoop {
    pub fn new(s: &Scenario) -> Self {
        Self {
            law: TorqueModulation {
                k1: s.gains.k1,
                k2: s.gains.k2,
                j: s.motor.inertia_kg_m2,
                b: s.motor.viscous_friction_nm_s_per_rad,
                tau_l: s.load.torque_nm,
            },
            trajectory: Trapezoid::new(&s.trajectory),
            ticks: 0,
        }
    }

    /// One tick from the state sample `state`. `publish_time_ns` is left for the caller.
    pub fn on_tick(&mut self, state: &DriveState) -> TorqueSetpoint {
        let r = self.trajectory.at(state.sample_time_s);
        let torque = self.law.torque(&r, state.theta_rad, state.omega_rad_s);
        let sp = TorqueSetpoint {
            seq: self.ticks,
            from_state_seq: state.seq,
            sample_time_s: state.sample_time_s,
            publish_time_ns: 0,
            theta_d_rad: r.theta,
            omega_d_rad_s: r.omega,
            alpha_d_rad_s2: r.alpha,
            torque_nm: torque,
        };
        self.ticks += 1;
        sp
    }
}
