//! Eq. (1): x = (θ, ω, i_a, i_b), inputs v_a, v_b, constant load torque τ_L opposing +θ.

use nalgebra::Vector4;
use stepdrive_shared::scenario::MotorParams;

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

impl From<&MotorParams> for Motor {
    fn from(p: &MotorParams) -> Self {
        Self {
            l: p.inductance_h,
            r: p.resistance_ohm,
            j: p.inertia_kg_m2,
            k_m: p.torque_constant_nm_per_a,
            n_r: p.n_r(),
            b: p.viscous_friction_nm_s_per_rad,
        }
    }
}

impl Motor {
    /// ẋ of eq. (1) for phase voltages `v` and load torque `tau_l`.
    pub fn derivative(&self, x: &MotorState, v: [f64; 2], tau_l: f64) -> MotorState {
        let (s, c) = (self.n_r * x[THETA]).sin_cos();
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
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table1() -> Motor {
        Motor::from(&MotorParams::default())
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
}
