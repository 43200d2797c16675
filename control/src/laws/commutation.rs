//! Eq. (17): the commutation scheme, i_a^d = −(τ/K_m) sin(N_r θ), i_b^d = (τ/K_m) cos(N_r θ).
//! It is field-oriented control with i_d = 0, i_q = τ/K_m, written in the phase frame.

/// Desired phase currents (i_a^d, i_b^d) for torque `tau` at rotor angle `theta`.
pub fn commutate(tau: f64, theta: f64, k_m: f64, n_r: f64) -> [f64; 2] {
    let (s, c) = (n_r * theta).sin_cos();
    let amplitude = tau / k_m;
    [-amplitude * s, amplitude * c]
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_shared::frames::dq_currents;

    /// Prop. 2: the commutated currents have zero direct current and i_q = τ/K_m.
    #[test]
    fn proposition2_zero_direct_current() {
        for i in 0..2000 {
            let theta = f64::from(i) * 0.0123 - 7.0;
            let tau = (f64::from(i) * 0.7).sin() * 0.3;
            let [ia, ib] = commutate(tau, theta, 0.5, 50.0);
            let (id, iq) = dq_currents(theta, 50.0, ia, ib);
            assert!(id.abs() < 1e-15, "i_d = {id}");
            assert!((iq - tau / 0.5).abs() < 1e-15, "i_q = {iq}");
        }
    }

    /// Eq. (18): the same currents are microstepping at N_r θ + π/2 with amplitude τ/K_m.
    #[test]
    fn equivalent_to_microstepping_with_phase_advance() {
        let (tau, theta, n_r) = (0.07, 0.123, 50.0);
        let [ia, ib] = commutate(tau, theta, 0.5, n_r);
        let advanced = n_r * theta + std::f64::consts::FRAC_PI_2;
        assert!((ia - tau / 0.5 * advanced.cos()).abs() < 1e-15);
        assert!((ib - tau / 0.5 * advanced.sin()).abs() < 1e-15);
    }
}
