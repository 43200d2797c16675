//! The baselines' references: microstepping voltages, eq. (2), and the desired currents of
//! the Lyapunov microstepping controller, eq. (39) (read as i^d = v^d / R; see docs/paper.md).

/// Eq. (2): v_a = V_max cos(N_r θ_d), v_b = V_max sin(N_r θ_d).
pub fn microstep_voltages(theta_d: f64, v_max: f64, n_r: f64) -> [f64; 2] {
    let (s, c) = (n_r * theta_d).sin_cos();
    [v_max * c, v_max * s]
}

/// Desired currents of eq. (39): the microstepping voltages divided by R.
pub fn microstep_currents(theta_d: f64, v_max: f64, r: f64, n_r: f64) -> [f64; 2] {
    let [va, vb] = microstep_voltages(theta_d, v_max, n_r);
    [va / r, vb / r]
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_shared::frames::dq_currents;

    /// Eq. (27): in the DQ frame, i_d = (V_max/R) cos(N_r(θ_d − θ)) > 0 while the electrical
    /// lag stays under π/2, so the baseline always spends current on i_d.
    #[test]
    fn direct_current_is_positive_for_small_lag() {
        let (v_max, r, n_r) = (6.5, 14.8, 50.0);
        for i in 0..100 {
            let theta = f64::from(i) * 0.01;
            let lag = 0.007;
            let [ia, ib] = microstep_currents(theta + lag, v_max, r, n_r);
            let (id, iq) = dq_currents(theta, n_r, ia, ib);
            assert!((id - v_max / r * (n_r * lag).cos()).abs() < 1e-12);
            assert!((iq - v_max / r * (n_r * lag).sin()).abs() < 1e-12);
            assert!(id > 0.0);
        }
    }
}
