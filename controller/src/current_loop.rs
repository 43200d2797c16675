//! The current loop body, run once per plant sample: the selected method's desired currents
//! (commutation (17) with the fresh rotor angle, or the microstepping references), the
//! sampled current tracking law, and the bus limit. Pure: no IPC, no clock, no allocation.

use crate::laws::commutation::commutate;
use crate::laws::current_tracking::SampledCurrentLaw;
use crate::laws::microstepping::{microstep_currents, microstep_voltages};
use stepdrive_shared::messages::{DriveCommand, DriveState, TorqueSetpoint};
use stepdrive_shared::scenario::MAX_COMPUTE_DELAY_PERIODS;
use stepdrive_shared::{Method, Scenario};

const MAX_DELAY: usize = MAX_COMPUTE_DELAY_PERIODS as usize;

#[derive(Debug, Clone)]
pub struct CurrentLoop {
    method: Method,
    law: SampledCurrentLaw,
    k_m: f64,
    n_r: f64,
    r: f64,
    v_max: f64,
    bus_v: f64,
    period: f64,
    delay: usize,
    /// Voltages already sent for the next `delay` periods, oldest first.
    decided: [[f64; 2]; MAX_DELAY],
    commands: u64,
}

impl CurrentLoop {
    pub fn new(s: &Scenario, method: Method) -> Self {
        let decay = match method {
            Method::Lyapunov => s.gains.rho_per_s,
            Method::Proposed | Method::OpenLoop => s.gains.k3_per_s,
        };
        let m = &s.motor;
        Self {
            method,
            law: SampledCurrentLaw::new(
                m.resistance_ohm,
                m.inductance_h,
                m.torque_constant_nm_per_a,
                m.n_r(),
                s.sample_period_s(),
                decay,
            ),
            k_m: m.torque_constant_nm_per_a,
            n_r: m.n_r(),
            r: m.resistance_ohm,
            v_max: s.gains.v_max_v,
            bus_v: s.drive.bus_voltage_v,
            period: s.sample_period_s(),
            // Validated ≤ MAX_COMPUTE_DELAY_PERIODS by the scenario.
            delay: (s.rates.compute_delay_periods as usize).min(MAX_DELAY),
            decided: [[0.0; 2]; MAX_DELAY],
            commands: 0,
        }
    }

    pub fn method(&self) -> Method {
        self.method
    }

    /// One cycle: the command answering `state`, given the position loop's latest setpoint.
    /// `publish_time_ns` is left for the caller.
    pub fn on_sample(&mut self, state: &DriveState, setpoint: &TorqueSetpoint) -> DriveCommand {
        let (theta, omega) = (state.theta_rad, state.omega_rad_s);
        let i = [state.i_a_a, state.i_b_a];
        let t = state.sample_time_s;
        let decided = &self.decided[..self.delay];
        let (v, i_ref) = match self.method {
            Method::Proposed => {
                let tau = setpoint.torque_nm;
                let (k_m, n_r, period) = (self.k_m, self.n_r, self.period);
                let reference =
                    |j: usize| commutate(tau, theta + omega * period * j as f64, k_m, n_r);
                (
                    self.law.voltage(i, theta, omega, decided, reference),
                    reference(self.delay + 1),
                )
            }
            Method::Lyapunov => {
                let (v_max, r, n_r, period) = (self.v_max, self.r, self.n_r, self.period);
                let reference = |j: usize| {
                    microstep_currents(setpoint.theta_d_at(t + period * j as f64), v_max, r, n_r)
                };
                (
                    self.law.voltage(i, theta, omega, decided, reference),
                    reference(self.delay + 1),
                )
            }
            Method::OpenLoop => {
                // Eq. (2) evaluated mid-way through the period the voltage will be applied in.
                let t_mid = t + self.period * (self.delay as f64 + 0.5);
                let v = microstep_voltages(setpoint.theta_d_at(t_mid), self.v_max, self.n_r);
                (v, [v[0] / self.r, v[1] / self.r])
            }
        };
        // Clamp here too, so the loop's own prediction uses what the drive will really apply.
        let v = v.map(|x| x.clamp(-self.bus_v, self.bus_v));
        if self.delay > 0 {
            self.decided.copy_within(1..self.delay, 0);
            self.decided[self.delay - 1] = v;
        }
        let command = DriveCommand {
            seq: self.commands,
            answers_seq: state.seq,
            sample_time_s: t,
            state_publish_time_ns: state.publish_time_ns,
            publish_time_ns: 0,
            v_a_v: v[0],
            v_b_v: v[1],
            i_a_ref_a: i_ref[0],
            i_b_ref_a: i_ref[1],
        };
        self.commands += 1;
        command
    }
}
