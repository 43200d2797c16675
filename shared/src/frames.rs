//! Reference-frame helpers shared by the controller, the plant tests and the monitor.

/// DQ transform, eq. (26): (i_d, i_q) of phase currents at electrical angle N_r θ.
/// The motor torque is K_m i_q.
pub fn dq_currents(theta: f64, n_r: f64, i_a: f64, i_b: f64) -> (f64, f64) {
    let (s, c) = (n_r * theta).sin_cos();
    (c * i_a + s * i_b, -s * i_a + c * i_b)
}
