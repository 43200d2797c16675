//! What the current loop does when the position loop goes quiet. Its setpoint segment
//! extrapolates θ_d, and (12)'s torque was computed for one tick: followed for long, a
//! stale setpoint steers the motor away (a 1 s stop of the position loop once left the
//! rotor 3.6 rad off). So the current loop bounds the setpoint's age: past
//! `[axis] setpoint_age_ticks` position-loop periods it brings the motor to a standstill on
//! its own — decelerating from the last setpoint's speed at the quick stop's rate, then
//! holding, torque by (12) at its own rate — and flags every command it sends so, until
//! setpoints of a later enable come (the axis, having seen the flag, faulted and was reset
//! and enabled again: its setpoints start where the rotor stands).
//!
//! A controlled stop rather than a fault: outputs off would let a loaded axis fall, and a
//! drive that loses its master stops and holds (CiA 402's abort connection option, quick
//! stop). The stop is the axis's own quick stop, so it is as gentle as a commanded one.

use crate::laws::torque_modulation::TorqueModulation;
use stepdrive_shared::messages::{setpoint_flags, DriveState, TorqueSetpoint};
use stepdrive_shared::trajectory::Reference;
use stepdrive_shared::Scenario;

/// The stop in progress: where it began (time, position, speed) and the enable it stopped.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Stop {
    t0: f64,
    theta0: f64,
    omega0: f64,
    epoch: u32,
    load_nm: f64,
}

/// See the module documentation.
#[derive(Debug, Clone)]
pub struct StaleGuard {
    /// The oldest a setpoint may be, s.
    limit_s: f64,
    decel: f64,
    law: TorqueModulation,
    stop: Option<Stop>,
}

impl StaleGuard {
    pub fn new(s: &Scenario) -> Self {
        Self {
            limit_s: f64::from(s.axis.setpoint_age_ticks) / s.rates.position_loop_hz,
            decel: s.axis.quick_stop_decel_rad_s2,
            law: TorqueModulation {
                k1: s.gains.k1,
                k2: s.gains.k2,
                j: s.motor.inertia_kg_m2,
                b: s.motor.viscous_friction_nm_s_per_rad,
                tau_l: 0.0,
            },
            stop: None,
        }
    }

    /// Stopping the motor on its own.
    pub fn active(&self) -> bool {
        self.stop.is_some()
    }

    /// The age bound, s.
    pub fn limit_s(&self) -> f64 {
        self.limit_s
    }

    /// The setpoint to follow at `state`: `sp` while it is fresh (or the axis has no
    /// torque), else the stop. Returns it and whether it is the stop's.
    pub fn guard(&mut self, state: &DriveState, sp: &TorqueSetpoint) -> (TorqueSetpoint, bool) {
        let t = state.sample_time_s;
        let fresh = t - sp.sample_time_s <= self.limit_s;
        if let Some(stop) = self.stop {
            if fresh && sp.epoch != stop.epoch {
                self.stop = None;
                return (*sp, false);
            }
            return (self.stopping(stop, state), true);
        }
        if fresh || sp.flags & setpoint_flags::OUTPUTS_ON == 0 {
            return (*sp, false);
        }
        let dt = t - sp.sample_time_s;
        let stop = Stop {
            t0: t,
            theta0: sp.theta_d_at(t),
            omega0: sp.omega_d_rad_s + sp.alpha_d_rad_s2 * dt,
            epoch: sp.epoch,
            load_nm: sp.load_estimate_nm,
        };
        self.stop = Some(stop);
        (self.stopping(stop, state), true)
    }

    /// The stop's setpoint at `state`: decelerating at the quick stop's rate, then holding.
    fn stopping(&self, stop: Stop, state: &DriveState) -> TorqueSetpoint {
        let t = state.sample_time_s;
        let r = stop_reference(stop.theta0, stop.omega0, self.decel, t - stop.t0);
        let law = TorqueModulation {
            tau_l: stop.load_nm,
            ..self.law
        };
        TorqueSetpoint {
            seq: 0,
            from_state_seq: state.seq,
            sample_time_s: t,
            publish_time_ns: 0,
            theta_d_rad: r.theta,
            omega_d_rad_s: r.omega,
            alpha_d_rad_s2: r.alpha,
            torque_nm: law.torque(&r, state.theta_rad, state.omega_rad_s),
            load_estimate_nm: stop.load_nm,
            torque_rate_nm_s: 0.0,
            axis: 0,
            // The current loop holds the rotor with torque; the brake stays off it.
            flags: setpoint_flags::OUTPUTS_ON | setpoint_flags::BRAKE_RELEASED,
            epoch: stop.epoch,
            _reserved: 0,
        }
    }
}

/// From θ0 at speed ω0, decelerating at `decel` to a standstill and holding there: the
/// state `tau` later.
pub fn stop_reference(theta0: f64, omega0: f64, decel: f64, tau: f64) -> Reference {
    let t_stop = omega0.abs() / decel;
    let a = -omega0.signum() * decel;
    if tau < t_stop {
        Reference {
            theta: theta0 + omega0 * tau + 0.5 * a * tau * tau,
            omega: omega0 + a * tau,
            alpha: a,
        }
    } else {
        Reference {
            theta: theta0 + omega0 * t_stop + 0.5 * a * t_stop * t_stop,
            omega: 0.0,
            alpha: 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(t: f64) -> DriveState {
        DriveState {
            seq: (t * 20_000.0).round() as u64,
            sample_time_s: t,
            theta_rad: 13.13 * t,
            omega_rad_s: 13.13,
            ..Default::default()
        }
    }

    fn cruising(t: f64, epoch: u32) -> TorqueSetpoint {
        TorqueSetpoint {
            sample_time_s: t,
            theta_d_rad: 13.13 * t,
            omega_d_rad_s: 13.13,
            torque_nm: 0.0757,
            flags: setpoint_flags::OUTPUTS_ON,
            epoch,
            ..Default::default()
        }
    }

    /// A fresh setpoint passes; one older than the bound starts a stop from its speed,
    /// which ends at rest after ω/a and holds; the same enable's setpoints do not end it,
    /// a later enable's do.
    #[test]
    fn a_stale_setpoint_brings_the_motor_to_rest_until_a_new_enable() {
        let s = Scenario::default();
        let mut g = StaleGuard::new(&s);
        assert!((g.limit_s() - 0.01).abs() < 1e-12);
        let sp = cruising(1.0, 1);
        let (out, stale) = g.guard(&state(1.009), &sp);
        assert!(!stale);
        assert_eq!(out, sp);
        let (out, stale) = g.guard(&state(1.011), &sp);
        assert!(stale && g.active());
        assert!((out.omega_d_rad_s - 13.13).abs() < 1e-9, "{out:?}");
        let stop_s = 13.13 / s.axis.quick_stop_decel_rad_s2;
        let (held, _) = g.guard(&state(1.011 + stop_s + 0.1), &sp);
        assert_eq!(held.omega_d_rad_s, 0.0);
        let expected = 13.13 * 1.011 + 13.13 * stop_s / 2.0;
        assert!((held.theta_d_rad - expected).abs() < 1e-9, "{held:?}");
        // The same enable coming back does not take the motor over.
        let t = 1.2;
        let (_, stale) = g.guard(&state(t), &cruising(t, 1));
        assert!(stale);
        let (out, stale) = g.guard(&state(t), &cruising(t, 2));
        assert!(!stale && !g.active());
        assert_eq!(out.epoch, 2);
    }

    /// Without torque there is nothing to stop.
    #[test]
    fn a_disabled_axis_is_not_stopped() {
        let mut g = StaleGuard::new(&Scenario::default());
        let mut sp = cruising(0.0, 1);
        sp.flags = 0;
        let (out, stale) = g.guard(&state(5.0), &sp);
        assert!(!stale);
        assert_eq!(out, sp);
    }
}
