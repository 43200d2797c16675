//! The position/torque loop body: trajectory generation and torque modulation (12), one
//! tick per position-loop period. Pure: the process wrapper supplies state and time.

use crate::laws::load_observer::LoadObserver;
use crate::laws::torque_modulation::TorqueModulation;
use stepdrive_shared::messages::{DriveState, TorqueSetpoint};
use stepdrive_shared::scenario::LoadCompensation;
use stepdrive_shared::trajectory::Trapezoid;
use stepdrive_shared::Scenario;

#[derive(Debug, Clone)]
pub struct PositionLoop {
    law: TorqueModulation,
    /// With `load_compensation = "observer"`: what stands in for τ_L.
    observer: Option<LoadObserver>,
    trajectory: Trapezoid,
    ticks: u64,
}

impl PositionLoop {
    pub fn new(s: &Scenario) -> Self {
        let c = &s.control;
        let tau_l = match c.load_compensation {
            LoadCompensation::Known => s.load.torque_nm,
            LoadCompensation::Observer | LoadCompensation::None => 0.0,
        };
        // A command reaches the winding one compute delay after its sample and the current
        // follows it within about 1/k_3.
        let delay_s =
            s.sample_period_s() * f64::from(s.rates.compute_delay_periods) + 1.0 / s.gains.k3_per_s;
        let observer = (c.load_compensation == LoadCompensation::Observer).then(|| {
            LoadObserver::new(
                s.motor.inertia_kg_m2,
                s.motor.viscous_friction_nm_s_per_rad,
                delay_s,
                s.observer_bandwidth_rad_s(),
            )
            .starting_at(s.load.torque_nm)
        });
        Self {
            law: TorqueModulation {
                k1: s.gains.k1,
                k2: s.gains.k2,
                j: s.motor.inertia_kg_m2,
                b: s.motor.viscous_friction_nm_s_per_rad,
                tau_l,
            },
            observer,
            trajectory: Trapezoid::new(&s.trajectory),
            ticks: 0,
        }
    }

    /// One tick from the state sample `state`. `publish_time_ns` is left for the caller.
    pub fn on_tick(&mut self, state: &DriveState) -> TorqueSetpoint {
        let r = self.trajectory.at(state.sample_time_s);
        let (t, omega) = (state.sample_time_s, state.omega_rad_s);
        if let Some(obs) = self.observer.as_mut() {
            self.law.tau_l = obs.update(t, omega);
        }
        let torque = self.law.torque(&r, state.theta_rad, omega);
        if let Some(obs) = self.observer.as_mut() {
            obs.commanded(t, omega, torque);
        }
        let sp = TorqueSetpoint {
            seq: self.ticks,
            from_state_seq: state.seq,
            sample_time_s: state.sample_time_s,
            publish_time_ns: 0,
            theta_d_rad: r.theta,
            omega_d_rad_s: r.omega,
            alpha_d_rad_s2: r.alpha,
            torque_nm: torque,
            load_estimate_nm: self.law.tau_l,
        };
        self.ticks += 1;
        sp
    }
}
