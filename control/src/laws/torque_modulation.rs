//! Eq. (12): nonlinear torque modulation for the mechanical error dynamics (11).

use stepdrive_shared::trajectory::Reference;

#[derive(Debug, Clone, Copy)]
pub struct TorqueModulation {
    /// k_1, 1/s.
    pub k1: f64,
    /// k_2, N·m·s/rad.
    pub k2: f64,
    /// J, kg·m².
    pub j: f64,
    /// B, N·m·s/rad.
    pub b: f64,
    /// Known load torque τ_L, N·m (the paper assumes it known).
    pub tau_l: f64,
}

impl TorqueModulation {
    /// τ = k_2 (ω* − ω) + e_θ + B ω + J ω̇* + τ_L with ω* = ω_d + k_1 e_θ and
    /// ω̇* = ω̇_d + k_1 (ω_d − ω).
    pub fn torque(&self, r: &Reference, theta: f64, omega: f64) -> f64 {
        let e_theta = r.theta - theta;
        let omega_star = r.omega + self.k1 * e_theta;
        let omega_star_dot = r.alpha + self.k1 * (r.omega - omega);
        self.k2 * (omega_star - omega)
            + e_theta
            + self.b * omega
            + self.j * omega_star_dot
            + self.tau_l
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lemma 1: along (11) with τ from (12), V̇₁ = −k₁ e_θ² − k₂ e_ω² < 0.
    #[test]
    fn lemma1_lyapunov_derivative_is_negative() {
        let law = TorqueModulation {
            k1: 0.01,
            k2: 0.01,
            j: 8e-5,
            b: 5e-3,
            tau_l: 0.01,
        };
        // A deterministic spread of states and references (no RNG dependency needed).
        let mut checked = 0;
        for i in 0..40 {
            for jx in 0..40 {
                let f = f64::from(i) * 0.37 + f64::from(jx) * 1.91;
                let r = Reference {
                    theta: 3.0 * f.sin(),
                    omega: 20.0 * (1.3 * f).cos(),
                    alpha: 50.0 * (0.7 * f).sin(),
                };
                let theta = r.theta + 0.05 * (2.1 * f).cos() * f64::from(i % 7);
                let omega = r.omega + 2.0 * (3.3 * f).sin() * f64::from(jx % 5);
                let tau = law.torque(&r, theta, omega);
                // Tracking errors (10) and their dynamics (11) with τ as the input.
                let e_theta = r.theta - theta;
                let omega_star = r.omega + law.k1 * e_theta;
                let e_omega = omega_star - omega;
                let omega_dot = (tau - law.b * omega - law.tau_l) / law.j;
                let omega_star_dot = r.alpha + law.k1 * (r.omega - omega);
                let e_theta_dot = r.omega - omega;
                let e_omega_dot = omega_star_dot - omega_dot;
                let v1_dot = e_theta * e_theta_dot + law.j * e_omega * e_omega_dot;
                let expected = -law.k1 * e_theta * e_theta - law.k2 * e_omega * e_omega;
                assert!(
                    (v1_dot - expected).abs() <= 1e-9 * (1.0 + expected.abs()),
                    "V̇₁ {v1_dot} vs {expected}"
                );
                if e_theta != 0.0 || e_omega != 0.0 {
                    assert!(v1_dot < 0.0);
                    checked += 1;
                }
            }
        }
        assert!(checked > 1000);
    }

    /// Prop. 3: at cruise with zero errors, τ = B ω_d + τ_L (0.0757 N·m for Table I).
    #[test]
    fn cruise_torque_matches_proposition3() {
        let law = TorqueModulation {
            k1: 0.01,
            k2: 0.01,
            j: 8e-5,
            b: 5e-3,
            tau_l: 0.01,
        };
        let r = Reference {
            theta: 5.0,
            omega: 13.13,
            alpha: 0.0,
        };
        let tau = law.torque(&r, 5.0, 13.13);
        assert!((tau - (5e-3 * 13.13 + 0.01)).abs() < 1e-15);
        assert!((tau - 0.0757).abs() < 1e-4);
    }
}
