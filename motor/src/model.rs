//! Eq. (1): x = (θ, ω, i_a, i_b), inputs v_a, v_b, load torque τ_L opposing +θ: a
//! constant, or the plant's [`Disturbance`] (load profile, Coulomb friction, detent).

use crate::load::Disturbance;
use crate::math;
use nalgebra::Vector4;

pub type MotorState = Vector4<f64>;

pub const THETA: usize = 0;
pub const OMEGA: usize = 1;
pub const I_A: usize = 2;
pub const I_B: usize = 3;

/// The motor's parameters in the form the right-hand side uses.
#[derive(Debug, Clone, Copy)]
pub struct Motor {
    pub l: f64,
    pub r: f64,
    pub j: f64,
    pub k_m: f64,
    pub n_r: f64,
    pub b: f64,
}

impl Motor {
    /// The paper's Table I motor (a scenario's `[motor]` defaults; a firmware's simulated
    /// motor).
    pub const TABLE_I: Motor = Motor {
        l: 40e-3,
        r: 14.8,
        j: 8e-5,
        k_m: 0.5,
        n_r: 50.0,
        b: 5e-3,
    };

    /// ẋ of eq. (1) for phase voltages `v` and load torque `tau_l`.
    pub fn derivative(&self, x: &MotorState, v: [f64; 2], tau_l: f64) -> MotorState {
        let (s, c) = math::sin_cos(self.n_r * x[THETA]);
        let omega = x[OMEGA];
        let (i_a, i_b) = (x[I_A], x[I_B]);
        Vector4::new(
            omega,
            (-self.k_m * i_a * s + self.k_m * i_b * c - self.b * omega - tau_l) / self.j,
            (v[0] - self.r * i_a + self.k_m * omega * s) / self.l,
            (v[1] - self.r * i_b - self.k_m * omega * c) / self.l,
        )
    }

    /// One classical RK4 step of length `h` with the voltages held (zero-order hold).
    pub fn rk4_step(&self, x: &MotorState, v: [f64; 2], tau_l: f64, h: f64) -> MotorState {
        let k1 = self.derivative(x, v, tau_l);
        let k2 = self.derivative(&(x + k1 * (h / 2.0)), v, tau_l);
        let k3 = self.derivative(&(x + k2 * (h / 2.0)), v, tau_l);
        let k4 = self.derivative(&(x + k3 * h), v, tau_l);
        x + (k1 + k2 * 2.0 + k3 * 2.0 + k4) * (h / 6.0)
    }

    /// Integrates over `period` in `substeps` equal RK4 steps.
    pub fn integrate(
        &self,
        x: &MotorState,
        v: [f64; 2],
        tau_l: f64,
        period: f64,
        substeps: u32,
    ) -> MotorState {
        let h = period / f64::from(substeps);
        let mut y = *x;
        for _ in 0..substeps {
            y = self.rk4_step(&y, v, tau_l, h);
        }
        y
    }

    /// Integrates over (t0, t0 + period] with the load `load` evaluated at each RK4 stage.
    /// A constant load takes [`Self::integrate`]'s path, so the paper's plant stays bit for
    /// bit what it was.
    pub fn integrate_loaded(
        &self,
        x: &MotorState,
        v: [f64; 2],
        load: &Disturbance,
        t0: f64,
        period: f64,
        substeps: u32,
    ) -> MotorState {
        if load.is_constant() {
            return self.integrate(x, v, load.constant_nm, period, substeps);
        }
        let h = period / f64::from(substeps);
        let mut y = *x;
        for n in 0..substeps {
            y = self.rk4_loaded_step(&y, v, load, 0.0, t0 + h * f64::from(n), h);
        }
        y
    }

    /// One RK4 step from `t` with the load evaluated at each stage, plus a constant `extra`
    /// torque opposing +θ.
    fn rk4_loaded_step(
        &self,
        y: &MotorState,
        v: [f64; 2],
        load: &Disturbance,
        extra: f64,
        t: f64,
        h: f64,
    ) -> MotorState {
        let f = |t: f64, y: &MotorState| {
            self.derivative(y, v, load.torque(t, y[THETA], y[OMEGA]) + extra)
        };
        let k1 = f(t, y);
        let k2 = f(t + h / 2.0, &(y + k1 * (h / 2.0)));
        let k3 = f(t + h / 2.0, &(y + k2 * (h / 2.0)));
        let k4 = f(t + h, &(y + k3 * h));
        y + (k1 + k2 * 2.0 + k3 * 2.0 + k4) * (h / 6.0)
    }

    /// The torque on the rotor but the brake's, N·m: the windings' less friction and load.
    fn torque_on_rotor(&self, y: &MotorState, load: &Disturbance, t: f64) -> f64 {
        let (s, c) = math::sin_cos(self.n_r * y[THETA]);
        self.k_m * (-y[I_A] * s + y[I_B] * c)
            - self.b * y[OMEGA]
            - load.torque(t, y[THETA], y[OMEGA])
    }

    /// As [`Self::integrate_loaded`] with a holding brake applied that holds up to
    /// `holding_nm` (Karnopp's stick-slip): a rotor at rest whose torque it can hold stays
    /// (only the windings' currents move on); otherwise the brake's torque opposes the
    /// motion (from rest, the torque that broke it loose), and a rotor that comes to rest
    /// within a step stays there.
    #[allow(clippy::too_many_arguments)]
    pub fn integrate_braked(
        &self,
        x: &MotorState,
        v: [f64; 2],
        load: &Disturbance,
        t0: f64,
        period: f64,
        substeps: u32,
        holding_nm: f64,
    ) -> MotorState {
        let h = period / f64::from(substeps);
        // J → ∞: ω' = 0 whatever the torque, and with ω = 0 the windings decouple.
        let locked = Motor {
            j: f64::INFINITY,
            ..*self
        };
        let mut y = *x;
        for n in 0..substeps {
            let t = t0 + h * f64::from(n);
            let torque = self.torque_on_rotor(&y, load, t);
            if y[OMEGA] == 0.0 && torque.abs() <= holding_nm {
                let theta = y[THETA];
                y = locked.rk4_step(&y, v, 0.0, h);
                y[THETA] = theta;
                y[OMEGA] = 0.0;
                continue;
            }
            // The brake's torque, opposing +θ as the load does, against the motion.
            let direction = match y[OMEGA] == 0.0 {
                true => torque.signum(),
                false => y[OMEGA].signum(),
            };
            y = self.rk4_loaded_step(&y, v, load, direction * holding_nm, t, h);
            if y[OMEGA] * direction <= 0.0 {
                y[OMEGA] = 0.0;
            }
        }
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table1() -> Motor {
        Motor::TABLE_I
    }

    /// Locked rotor (J → ∞ is emulated by holding θ, ω at zero: with ω = 0 the electrical
    /// equations decouple), current step: i(t) = V/R (1 − e^{−tR/L}).
    #[test]
    fn locked_rotor_current_step_matches_closed_form() {
        let m = Motor {
            j: f64::INFINITY,
            ..table1()
        };
        let v = 12.0;
        let dt = 50e-6;
        let mut x = MotorState::zeros();
        let mut t = 0.0;
        let mut worst: f64 = 0.0;
        for _ in 0..400 {
            x = m.integrate(&x, [v, -v], 0.0, dt, 4);
            t += dt;
            let expected = v / m.r * (1.0 - (-t * m.r / m.l).exp());
            worst = worst
                .max((x[I_A] - expected).abs())
                .max((x[I_B] + expected).abs());
            assert_eq!(x[OMEGA], 0.0);
        }
        // RK4 truncation at 12.5 µs sub-steps is ~1e-12 A here; a first-order method would be ~1e-6.
        assert!(worst < 1e-10, "locked-rotor current error {worst:e}");
        // 20 ms is 7.4 time constants: the current has settled at V/R.
        assert!((x[I_A] - v / m.r).abs() < 1e-3 * v / m.r);
    }

    /// With K_m = 0 and τ_L = 0 the rotor coasts: ω(t) = ω₀ e^{−tB/J}, θ(t) = ω₀ J/B (1 − e^{−tB/J}).
    #[test]
    fn coast_down_matches_closed_form() {
        let m = Motor {
            k_m: 0.0,
            ..table1()
        };
        let w0 = 20.0;
        let mut x = MotorState::new(0.0, w0, 0.0, 0.0);
        let dt = 50e-6;
        for k in 1..=20_000 {
            x = m.integrate(&x, [0.0, 0.0], 0.0, dt, 1);
            let t = f64::from(k) * dt;
            let decay = (-t * m.b / m.j).exp();
            assert!((x[OMEGA] - w0 * decay).abs() < 1e-9 * w0, "ω at t={t}");
            let theta = w0 * m.j / m.b * (1.0 - decay);
            assert!((x[THETA] - theta).abs() < 1e-9, "θ at t={t}");
        }
    }

    /// RK4's global error falls as h⁴: halving the sub-step divides it by about 16.
    #[test]
    fn rk4_converges_with_fourth_order() {
        let m = table1();
        let x0 = MotorState::new(0.01, 5.0, 0.1, -0.2);
        let v = [10.0, -3.0];
        // A 5 ms span with few steps so truncation dominates rounding.
        let span = 5e-3;
        let reference = m.integrate(&x0, v, 0.01, span, 8192);
        let err = |n: u32| (m.integrate(&x0, v, 0.01, span, n) - reference).norm();
        let (e1, e2, e3) = (err(16), err(32), err(64));
        let order1 = (e1 / e2).log2();
        let order2 = (e2 / e3).log2();
        assert!(
            (3.7..4.3).contains(&order1) && (3.7..4.3).contains(&order2),
            "observed orders {order1:.2}, {order2:.2} (errors {e1:e}, {e2:e}, {e3:e})"
        );
    }

    /// Detent alone, currents zero, no friction: a small swing about a stable point is
    /// harmonic with ω₀² = T_d h N_r / J, so the rotor is back where it started after one
    /// period 2π/ω₀ and at the far side after half of one.
    #[test]
    fn detent_swing_has_the_closed_form_period() {
        let m = Motor {
            k_m: 0.0,
            b: 0.0,
            ..table1()
        };
        let mut load = Disturbance::constant(0.0);
        load.detent_nm = 0.04;
        load.detent_wavenumber = 4.0 * m.n_r;
        let w0 = (load.detent_nm * load.detent_wavenumber / m.j).sqrt();
        let amplitude = 1e-6;
        let dt = 1e-6;
        let steps = |t: f64| (t / dt).round() as u64;
        let mut x = MotorState::new(amplitude, 0.0, 0.0, 0.0);
        let half = steps(std::f64::consts::PI / w0);
        for k in 0..half {
            x = m.integrate_loaded(&x, [0.0; 2], &load, k as f64 * dt, dt, 1);
        }
        assert!(
            (x[THETA] + amplitude).abs() < 1e-3 * amplitude,
            "θ(T/2) = {:e}",
            x[THETA]
        );
        for k in half..2 * half {
            x = m.integrate_loaded(&x, [0.0; 2], &load, k as f64 * dt, dt, 1);
        }
        assert!(
            (x[THETA] - amplitude).abs() < 1e-3 * amplitude,
            "θ(T) = {:e}",
            x[THETA]
        );
    }

    /// A load step at t_s while coasting with K_m = 0 and B = 0: ω falls with slope −τ/J
    /// from t_s on. A step inside an RK4 sub-step is felt by the stages after it, so ω is
    /// right to within what one sub-step of the step would change it.
    #[test]
    fn load_step_acts_from_its_instant() {
        let m = Motor {
            k_m: 0.0,
            b: 0.0,
            ..table1()
        };
        let (period, substeps) = (50e-6, 4);
        for at_s in [1.3e-4, 2.01e-4, 4.49e-4] {
            let mut load = Disturbance::constant(0.0);
            load.add_step(crate::LoadStep {
                at_s,
                torque_nm: 0.02,
            })
            .expect("room");
            let mut x = MotorState::new(0.0, 10.0, 0.0, 0.0);
            for k in 0..10 {
                x = m.integrate_loaded(
                    &x,
                    [0.0; 2],
                    &load,
                    f64::from(k) * period,
                    period,
                    substeps,
                );
            }
            let expected = 10.0 - 0.02 / m.j * (5e-4 - at_s);
            let one_substep = 0.02 / m.j * period / f64::from(substeps);
            assert!(
                (x[OMEGA] - expected).abs() < one_substep,
                "step at {at_s}: ω {} vs {expected}",
                x[OMEGA]
            );
        }
    }

    /// A constant load takes the paper's path bit for bit.
    #[test]
    fn constant_load_is_bit_identical_to_the_constant_path() {
        let m = table1();
        let x0 = MotorState::new(0.01, 5.0, 0.1, -0.2);
        let a = m.integrate(&x0, [3.0, 1.0], 0.01, 50e-6, 4);
        let b = m.integrate_loaded(&x0, [3.0, 1.0], &Disturbance::constant(0.01), 0.7, 50e-6, 4);
        assert_eq!(a, b);
    }

    /// Energy balance: input power = copper loss + friction loss + load work + d/dt(stored).
    #[test]
    fn power_balance_holds() {
        let m = table1();
        let x = MotorState::new(0.3, 7.0, 0.2, -0.1);
        let v = [5.0, 2.0];
        let tau_l = 0.01;
        let dx = m.derivative(&x, v, tau_l);
        let p_in = v[0] * x[I_A] + v[1] * x[I_B];
        let stored_rate = m.l * (x[I_A] * dx[I_A] + x[I_B] * dx[I_B]) + m.j * x[OMEGA] * dx[OMEGA];
        let losses =
            m.r * (x[I_A].powi(2) + x[I_B].powi(2)) + m.b * x[OMEGA].powi(2) + tau_l * x[OMEGA];
        assert!((p_in - stored_rate - losses).abs() < 1e-12);
    }

    /// A holding brake against a load it can hold: the rotor stays exactly where it stood
    /// while the windings' currents rise as for a locked rotor.
    #[test]
    fn an_applied_brake_holds_a_load_below_its_holding_torque() {
        let m = table1();
        let load = Disturbance::constant(0.01);
        let dt = 50e-6;
        // Where phase a's current makes no torque (sin N_r θ = 0): the load alone pulls.
        let theta = 3.0 * std::f64::consts::PI / m.n_r;
        let mut x = MotorState::new(theta, 0.0, 0.0, 0.0);
        let v = 2.0;
        for k in 1..=200 {
            x = m.integrate_braked(&x, [v, 0.0], &load, 0.0, dt, 4, 0.5);
            let t = f64::from(k) * dt;
            assert_eq!((x[THETA], x[OMEGA]), (theta, 0.0));
            let expected = v / m.r * (1.0 - (-t * m.r / m.l).exp());
            assert!((x[I_A] - expected).abs() < 1e-10, "{t}: {}", x[I_A]);
        }
    }

    /// A turning rotor, no load, no viscous friction, no coupling to the windings (whose
    /// back-EMF, shorted through 0 V, would brake it too): the brake decelerates it
    /// at τ_h/J to a standstill after ω₀J/τ_h, ω₀²J/(2τ_h) further on, and it stays there.
    #[test]
    fn an_applied_brake_stops_a_turning_rotor_at_its_holding_torque() {
        let m = Motor {
            b: 0.0,
            k_m: 0.0,
            ..table1()
        };
        let (omega0, holding, dt) = (5.0, 0.2, 50e-6);
        let load = Disturbance::constant(0.0);
        let mut x = MotorState::new(0.0, omega0, 0.0, 0.0);
        let stop_s = omega0 * m.j / holding;
        let mut stopped_at = None;
        for k in 1..=((2.0 * stop_s / dt) as u32) {
            x = m.integrate_braked(&x, [0.0; 2], &load, 0.0, dt, 4, holding);
            if x[OMEGA] == 0.0 && stopped_at.is_none() {
                stopped_at = Some(f64::from(k) * dt);
            }
        }
        let at = stopped_at.expect("it stops");
        assert!(
            (at - stop_s).abs() <= dt,
            "stopped at {at} s, expected {stop_s} s"
        );
        let travel = omega0 * omega0 * m.j / (2.0 * holding);
        assert!(
            (x[THETA] - travel).abs() < omega0 * dt,
            "{} against {travel}",
            x[THETA]
        );
        assert_eq!(x[OMEGA], 0.0);
    }

    /// A load beyond the holding torque drags the rotor along at (τ_L − τ_h)/J (no viscous
    /// friction, no coupling to the windings).
    #[test]
    fn a_load_beyond_the_holding_torque_slips_the_brake() {
        let m = Motor {
            b: 0.0,
            k_m: 0.0,
            ..table1()
        };
        let (tau_l, holding, dt) = (0.3, 0.2, 50e-6);
        let load = Disturbance::constant(tau_l);
        let mut x = MotorState::zeros();
        for _ in 0..100 {
            x = m.integrate_braked(&x, [0.0; 2], &load, 0.0, dt, 4, holding);
        }
        let expected = -(tau_l - holding) / m.j * 100.0 * dt;
        assert!(
            (x[OMEGA] - expected).abs() < 1e-9 * expected.abs(),
            "{}",
            x[OMEGA]
        );
    }
}
