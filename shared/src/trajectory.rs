//! Trapezoidal velocity profile of Section V: rest at θ = 0, constant acceleration to the
//! cruise velocity, cruise, constant deceleration to rest, hold. Past its end the move
//! repeats back and forth: odd passes run it mirrored, back to θ = 0.

use crate::scenario::TrajectoryParams;

/// Desired position, velocity and acceleration at one instant.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Reference {
    pub theta: f64,
    pub omega: f64,
    pub alpha: f64,
}

impl Reference {
    /// The state `dt` later at this acceleration.
    pub fn after(self, dt: f64) -> Reference {
        self.after_jerk(dt, 0.0)
    }

    /// The state `dt` later along a constant `jerk` (rad/s³): how a jerk-limited trajectory
    /// stepped on its own grid is told at a time between its steps.
    pub fn after_jerk(self, dt: f64, jerk: f64) -> Reference {
        if dt == 0.0 {
            return self;
        }
        Reference {
            theta: self.theta
                + self.omega * dt
                + 0.5 * self.alpha * dt * dt
                + jerk * dt * dt * dt / 6.0,
            omega: self.omega + self.alpha * dt + 0.5 * jerk * dt * dt,
            alpha: self.alpha + jerk * dt,
        }
    }
}

/// Evaluates the profile in closed form (no integration, so every process and every run
/// agrees on θ_d bit for bit).
#[derive(Debug, Clone, Copy)]
pub struct Trapezoid {
    w: f64,
    t1: f64,
    t2: f64,
    t3: f64,
    accel: f64,
    decel: f64,
    theta1: f64,
    theta2: f64,
    theta3: f64,
    period: f64,
}

impl Trapezoid {
    pub fn new(p: &TrajectoryParams) -> Self {
        let w = p.cruise_velocity_rad_s;
        let t1 = p.accel_s;
        let t2 = t1 + p.cruise_s;
        let t3 = t2 + p.decel_s;
        let accel = if p.accel_s > 0.0 { w / p.accel_s } else { 0.0 };
        let decel = if p.decel_s > 0.0 { w / p.decel_s } else { 0.0 };
        let theta1 = 0.5 * w * p.accel_s;
        let theta2 = theta1 + w * p.cruise_s;
        let theta3 = theta2 + 0.5 * w * p.decel_s;
        Self {
            w,
            t1,
            t2,
            t3,
            accel,
            decel,
            theta1,
            theta2,
            theta3,
            period: t3 + p.hold_s,
        }
    }

    /// Length of one pass, s.
    pub fn period(&self) -> f64 {
        self.period
    }

    /// Time within the current pass and whether that pass runs mirrored.
    pub fn phase(&self, t: f64) -> (f64, bool) {
        if t < self.period || self.period <= 0.0 {
            return (t, false);
        }
        let pass = (t / self.period).floor();
        (t - pass * self.period, pass as u64 % 2 == 1)
    }

    /// The reference at time `t`, repeating back and forth after the first pass.
    pub fn at(&self, t: f64) -> Reference {
        let (tau, mirrored) = self.phase(t);
        let r = self.one_pass(tau);
        if mirrored {
            Reference {
                theta: self.theta3 - r.theta,
                omega: -r.omega,
                alpha: -r.alpha,
            }
        } else {
            r
        }
    }

    /// Final position of the move, rad.
    pub fn final_position(&self) -> f64 {
        self.theta3
    }

    fn one_pass(&self, t: f64) -> Reference {
        if t <= 0.0 {
            Reference::default()
        } else if t < self.t1 {
            Reference {
                theta: 0.5 * self.accel * t * t,
                omega: self.accel * t,
                alpha: self.accel,
            }
        } else if t < self.t2 {
            Reference {
                theta: self.theta1 + self.w * (t - self.t1),
                omega: self.w,
                alpha: 0.0,
            }
        } else if t < self.t3 {
            let s = t - self.t2;
            Reference {
                theta: self.theta2 + self.w * s - 0.5 * self.decel * s * s,
                omega: self.w - self.decel * s,
                alpha: -self.decel,
            }
        } else {
            Reference {
                theta: self.theta3,
                omega: 0.0,
                alpha: 0.0,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profile_is_continuous_and_consistent() {
        let tr = Trapezoid::new(&TrajectoryParams::default());
        // Position is the integral of velocity: check by the trapezoid rule.
        let dt = 1e-5;
        let mut theta = 0.0;
        let mut prev = tr.at(0.0);
        let mut t = 0.0;
        while t < 2.5 {
            t += dt;
            let r = tr.at(t);
            theta += 0.5 * (prev.omega + r.omega) * dt;
            assert!(
                (r.theta - theta).abs() < 1e-6,
                "t={t}: {} vs {theta}",
                r.theta
            );
            prev = r;
        }
        // Area of the trapezoid: ω_c (0.25 + 1.0 + 0.25).
        assert!((tr.final_position() - 13.13 * 1.5).abs() < 1e-12);
        assert_eq!(tr.at(1.0).omega, 13.13);
        assert_eq!(tr.at(2.4).omega, 0.0);
        // Second pass runs back to zero; third starts again from zero.
        assert_eq!(tr.at(3.5).omega, -13.13);
        assert!((tr.at(5.0).theta).abs() < 1e-12);
        assert!((tr.at(6.0).omega - 13.13).abs() < 1e-12);
    }
}
