//! Current tracking: the paper's continuous law, eq. (22), and the sampled law the current
//! loop actually runs.
//!
//! # Why not just sample (22)
//! With T_s = 50 µs and k_3 = 30000 1/s, k_3 T_s = 1.5. Euler-sampling (22) and applying the
//! voltage one period late (as a PWM drive does) gives e[k+1] = e[k] − k_3 T_s e[k−1], which is
//! unstable for k_3 T_s > 1. The sampled law below keeps the design intent of (22), current
//! errors decaying like exp(−k_3 t), for the real sampling period and compute delay.
//!
//! # The sampled design
//! Over one period with the voltage held, each phase of (19) is a first-order system driven
//! by the voltage and the back-EMF. Its exact solution over one period is
//!
//! ```text
//! i[k+1] = a i[k] + b v[k] + Δ[k],   a = exp(−R T/L),   b = (1 − a)/R,
//! Δ[k]   = (1/L) ∫₀ᵀ exp(−R(T−s)/L) · emf(s) ds,
//! ```
//!
//! with emf = (+K_m ω sin N_rθ, −K_m ω cos N_rθ). For constant ω over the period
//! (θ(s) = θ_k + ω s) the integral has a closed form: with β = R/L, Ω = N_r ω,
//! φ = N_r θ_k, Z = e^{jφ}(e^{jΩT} − e^{−βT})/(β + jΩ), Δ = (K_m ω/L)(Im Z, −Re Z).
//! The prediction is therefore exact for constant speed, with no averaging approximation.
//!
//! At sample k the voltages of the next d periods are already decided (compute delay d).
//! The law predicts î[k+d] by running the model through them, then chooses the voltage for
//! period k+d so that
//!
//! ```text
//! i[k+d+1] = i^d[k+d+1] − λ (i^d[k+d] − î[k+d]),   λ = exp(−k_3 T),
//! ```
//!
//! i.e. e[k+d+1] = λ e[k+d]: the continuous design's exp(−k_3 t) decay, sampled exactly.
//! With d = 0 and T → 0 this is (22) term for term (see the test
//! `tends_to_eq22_as_the_period_shrinks`). Future rotor angles for the reference are
//! predicted at constant ω (N_r ω T ≈ 0.03 rad per period at cruise).

use crate::laws::phasor::{Complex, Rotating};

/// The paper's continuous law, eq. (22) (also (39) with ρ for k_3): phase voltages that make
/// ė = −k e. `i_ref_dot` is the reference's time derivative.
#[allow(clippy::too_many_arguments)]
pub fn continuous_voltage(
    i: [f64; 2],
    i_ref: [f64; 2],
    i_ref_dot: [f64; 2],
    theta: f64,
    omega: f64,
    r: f64,
    l: f64,
    k_m: f64,
    n_r: f64,
    k: f64,
) -> [f64; 2] {
    let (s, c) = (n_r * theta).sin_cos();
    [
        r * i[0] - k_m * omega * s + l * (i_ref_dot[0] + k * (i_ref[0] - i[0])),
        r * i[1] + k_m * omega * c + l * (i_ref_dot[1] + k * (i_ref[1] - i[1])),
    ]
}

/// The sampled current tracking law for period T, compute delay d and decay rate k.
#[derive(Debug, Clone, Copy)]
pub struct SampledCurrentLaw {
    a: f64,
    b: f64,
    beta: f64,
    l: f64,
    lambda: f64,
    k_m: f64,
    n_r: f64,
    period: f64,
}

impl SampledCurrentLaw {
    /// `decay_rate`: k_3 for the proposed method, ρ for the Lyapunov baseline, 1/s.
    pub fn new(r: f64, l: f64, k_m: f64, n_r: f64, period: f64, decay_rate: f64) -> Self {
        let a = (-r * period / l).exp();
        Self {
            a,
            // (1 − a)/R without cancellation: −expm1(−RT/L)/R.
            b: -(-r * period / l).exp_m1() / r,
            beta: r / l,
            l,
            lambda: (-decay_rate * period).exp(),
            k_m,
            n_r,
            period,
        }
    }

    /// Error contraction per period, exp(−k T).
    pub fn lambda(&self) -> f64 {
        self.lambda
    }

    /// Current change over one period caused by the back-EMF of (19), starting at `theta`
    /// with constant `omega` (exact; see the module documentation).
    pub fn back_emf_step(&self, theta: f64, omega: f64) -> [f64; 2] {
        let beta = self.beta;
        let big_omega = self.n_r * omega;
        let phi = self.n_r * theta;
        let decay = self.a;
        let (s1, c1) = (phi + big_omega * self.period).sin_cos();
        let (s0, c0) = phi.sin_cos();
        let (nr, ni) = (c1 - decay * c0, s1 - decay * s0);
        let denom = beta * beta + big_omega * big_omega;
        let z_re = (nr * beta + ni * big_omega) / denom;
        let z_im = (ni * beta - nr * big_omega) / denom;
        let gain = self.k_m * omega / self.l;
        [gain * z_im, -gain * z_re]
    }

    /// One period of the phase-current model with voltage `v` held.
    pub fn predict(&self, i: [f64; 2], v: [f64; 2], theta: f64, omega: f64) -> [f64; 2] {
        let e = self.back_emf_step(theta, omega);
        [
            self.a * i[0] + self.b * v[0] + e[0],
            self.a * i[1] + self.b * v[1] + e[1],
        ]
    }

    /// The voltage for period k+d, given the measured currents `i`, angle and velocity at
    /// sample k, the voltages already decided for periods k .. k+d−1 (`decided`, oldest
    /// first, d = `decided.len()`), and the desired currents: `reference(j)` is i^d at sample
    /// k+j, evaluated at the rotor angle predicted for that instant. Also returns the current
    /// it predicted at sample k+d, where that voltage starts (from which [`Self::plan`]
    /// continues).
    pub fn decide(
        &self,
        i: [f64; 2],
        theta: f64,
        omega: f64,
        decided: &[[f64; 2]],
        reference: impl Fn(usize) -> [f64; 2],
    ) -> ([f64; 2], [f64; 2]) {
        let d = decided.len();
        let mut predicted = i;
        for (j, v) in decided.iter().enumerate() {
            let theta_j = theta + omega * self.period * j as f64;
            predicted = self.predict(predicted, *v, theta_j, omega);
        }
        let r_now = reference(d);
        let r_next = reference(d + 1);
        let theta_d = theta + omega * self.period * d as f64;
        let e = self.back_emf_step(theta_d, omega);
        let mut v = [0.0; 2];
        for p in 0..2 {
            let target = r_next[p] - self.lambda * (r_now[p] - predicted[p]);
            v[p] = (target - self.a * predicted[p] - e[p]) / self.b;
        }
        (v, predicted)
    }

    /// [`Self::decide`] for a rotor accelerating at `alpha` (rad/s²): the speed over the
    /// periods ahead is ω + α t, and each period's back-EMF is taken at its mid-period speed
    /// (second-order accurate). At constant speed the prediction lags an accelerating rotor's
    /// back-EMF by K_m α (d + ½) T, and the current, hence the torque, falls short by a
    /// constant amount while it accelerates. `reference` is evaluated by the caller at the
    /// angles it predicts the same way.
    pub fn decide_accelerating(
        &self,
        i: [f64; 2],
        theta: f64,
        omega: f64,
        alpha: f64,
        decided: &[[f64; 2]],
        reference: impl Fn(usize) -> [f64; 2],
    ) -> ([f64; 2], [f64; 2]) {
        let d = decided.len();
        let t = |j: f64| self.period * j;
        let angle = |j: f64| theta + omega * t(j) + 0.5 * alpha * t(j) * t(j);
        let mid_speed = |j: f64| omega + alpha * t(j + 0.5);
        let mut predicted = i;
        for (j, v) in decided.iter().enumerate() {
            let j = j as f64;
            predicted = self.predict(predicted, *v, angle(j), mid_speed(j));
        }
        let r_now = reference(d);
        let r_next = reference(d + 1);
        let e = self.back_emf_step(angle(d as f64), mid_speed(d as f64));
        let mut v = [0.0; 2];
        for p in 0..2 {
            let target = r_next[p] - self.lambda * (r_now[p] - predicted[p]);
            v[p] = (target - self.a * predicted[p] - e[p]) / self.b;
        }
        (v, predicted)
    }

    /// [`Self::back_emf_step`] from rotor angle θ_0 + ωTm, as a sequence over m: at constant
    /// speed it is a fixed complex amplitude turning with the electrical angle,
    /// Δ_m = −j (K_m ω/L) C e^{jN_rθ_m}, C = (e^{jΩT} − a)/(β + jΩ).
    pub fn back_emf_sequence(&self, theta0: f64, omega: f64) -> Rotating {
        let big_omega = self.n_r * omega;
        Rotating::new(
            self.back_emf_amplitude(omega),
            self.n_r * theta0,
            big_omega * self.period,
            0.0,
        )
    }

    /// −j (K_m ω/L) C of [`Self::back_emf_sequence`].
    fn back_emf_amplitude(&self, omega: f64) -> Complex {
        let big_omega = self.n_r * omega;
        let c = (Complex::unit(big_omega * self.period) - Complex::new(self.a, 0.0))
            / Complex::new(self.beta, big_omega);
        let g = self.k_m * omega / self.l;
        Complex::new(g * c.im, -g * c.re)
    }

    /// [`Self::back_emf_sequence`] for a rotor accelerating at `alpha` from angle `theta0`
    /// and speed `omega0`, as [`Self::decide_accelerating`] sees each period (its
    /// mid-period speed held through it): the phase quadratic, the amplitude quadratic in
    /// the period through its values at the first three (its curvature in ω is taken, its
    /// third derivative neglected).
    pub fn back_emf_sequence_accelerating(&self, theta0: f64, omega0: f64, alpha: f64) -> Rotating {
        let t = self.period;
        let mid = omega0 + 0.5 * alpha * t;
        let a = [0.0, 1.0, 2.0].map(|m| self.back_emf_amplitude(mid + alpha * t * m));
        Rotating::ramped(
            a[0],
            a[1] - a[0],
            (a[2] - a[1]) - (a[1] - a[0]),
            self.n_r * theta0,
            self.n_r * mid * t,
            self.n_r * alpha * t * t,
        )
    }

    /// The law's own future: the voltages it would choose for the periods after the one it
    /// just decided if its model held (the speed, or the acceleration, it assumed; the
    /// reference trajectory unchanged).
    /// `i` is the current predicted at the first planned sample, `reference` and `emf` are
    /// positioned there and step one period per entry. Each voltage is clamped to ±`bus_v`
    /// as the drive will clamp it, and the prediction uses the clamped value.
    pub fn plan(
        &self,
        i: [f64; 2],
        mut reference: Rotating,
        mut emf: Rotating,
        bus_v: f64,
        out: &mut [[f32; 2]],
    ) {
        let mut i = Complex::from_pair(i);
        for slot in out.iter_mut() {
            let r_now = reference.value();
            reference.advance();
            let r_next = reference.value();
            let e = emf.value();
            emf.advance();
            let target = r_next - (r_now - i) * self.lambda;
            let v = (target - i * self.a - e) * (1.0 / self.b);
            let v = Complex::new(v.re.clamp(-bus_v, bus_v), v.im.clamp(-bus_v, bus_v));
            i = i * self.a + v * self.b + e;
            *slot = [v.re as f32, v.im as f32];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_motor::{Motor, MotorState, I_A, I_B, OMEGA, THETA};
    use stepdrive_shared::scenario::MotorParams;

    const T: f64 = 50e-6;

    fn motor() -> Motor {
        Motor::from(&MotorParams::default())
    }

    fn law(m: &Motor, period: f64, k: f64) -> SampledCurrentLaw {
        SampledCurrentLaw::new(m.r, m.l, m.k_m, m.n_r, period, k)
    }

    #[test]
    fn tends_to_eq22_as_the_period_shrinks() {
        let m = motor();
        let (theta, omega) = (0.37, 11.0);
        let i = [0.1, -0.05];
        // A rotating reference and its derivative.
        let amp = 0.3;
        let w_e = m.n_r * omega;
        let r_at = |t: f64| {
            [
                amp * (m.n_r * theta + w_e * t).cos(),
                amp * (m.n_r * theta + w_e * t).sin(),
            ]
        };
        let r_dot = [
            -amp * w_e * (m.n_r * theta).sin(),
            amp * w_e * (m.n_r * theta).cos(),
        ];
        let v22 = continuous_voltage(
            i,
            r_at(0.0),
            r_dot,
            theta,
            omega,
            m.r,
            m.l,
            m.k_m,
            m.n_r,
            30_000.0,
        );
        let mut prev_gap = f64::INFINITY;
        for period in [1e-5, 1e-6, 1e-7, 1e-8] {
            let lw = law(&m, period, 30_000.0);
            let (v, _) = lw.decide(i, theta, omega, &[], |j| r_at(j as f64 * period));
            let gap = (v[0] - v22[0]).abs().max((v[1] - v22[1]).abs());
            assert!(gap < prev_gap / 5.0, "T={period}: gap {gap} vs {prev_gap}");
            prev_gap = gap;
        }
        assert!(
            prev_gap < 0.05,
            "at T = 10 ns the laws differ by {prev_gap} V"
        );
    }

    /// Runs the law against the plant model with compute delay `d` for `n` periods and
    /// returns the phase-a current error at every sample.
    fn closed_loop_errors(d: usize, omega: f64, n: usize, k: f64) -> Vec<f64> {
        // Rotor held at constant speed (J → ∞) so the current dynamics are isolated.
        let m = Motor {
            j: f64::INFINITY,
            ..motor()
        };
        let lw = law(&m, T, k);
        let amp = 0.05;
        let reference = |theta: f64| [-amp * (m.n_r * theta).sin(), amp * (m.n_r * theta).cos()];
        let mut x = MotorState::new(0.2, omega, 0.0, 0.0);
        let mut queue: Vec<[f64; 2]> = vec![[0.0; 2]; d];
        let mut errors = Vec::new();
        for _ in 0..n {
            let (theta, w) = (x[THETA], x[OMEGA]);
            errors.push(reference(theta)[0] - x[I_A]);
            let (v, _) = lw.decide([x[I_A], x[I_B]], theta, w, &queue, |j| {
                reference(theta + w * T * j as f64)
            });
            queue.push(v);
            let applied = queue.remove(0);
            x = m.integrate(&x, applied, 0.0, T, 8);
        }
        errors
    }

    /// The sampled loop's error decays at the designed rate: e[k+1] = exp(−k_3 T) e[k] once
    /// the delay line has filled, on the plant model itself.
    #[test]
    fn error_decays_at_the_designed_rate_on_the_plant_model() {
        for (d, omega) in [(1usize, 0.0), (1, 13.13), (2, 13.13), (0, 13.13)] {
            let errors = closed_loop_errors(d, omega, 14, 30_000.0);
            let lambda = (-30_000.0 * T).exp();
            let start = d + 1;
            // Eight periods: the error falls by λ⁸ ≈ 6e-6, still far above rounding.
            for k in start..start + 8 {
                let ratio = errors[k + 1] / errors[k];
                assert!(
                    (ratio - lambda).abs() < 1e-6,
                    "d={d} ω={omega}: e[{}]/e[{k}] = {ratio}, designed {lambda}",
                    k + 1
                );
            }
        }
    }

    /// The reason for the sampled design: Euler-sampled (22) with one period of delay
    /// diverges on the same plant (docs/paper.md).
    #[test]
    fn euler_sampled_eq22_with_delay_is_unstable() {
        let m = Motor {
            j: f64::INFINITY,
            ..motor()
        };
        let mut x = MotorState::new(0.0, 0.0, 0.0, 0.0);
        let mut queued = [0.0; 2];
        let target = 0.05;
        let mut worst: f64 = 0.0;
        for _ in 0..200 {
            let v = continuous_voltage(
                [x[I_A], x[I_B]],
                [target, 0.0],
                [0.0, 0.0],
                x[THETA],
                x[OMEGA],
                m.r,
                m.l,
                m.k_m,
                m.n_r,
                30_000.0,
            );
            x = m.integrate(&x, queued, 0.0, T, 4);
            queued = v;
            worst = worst.max((x[I_A] - target).abs());
        }
        assert!(
            worst > 10.0 * target,
            "expected divergence, worst error {worst}"
        );
        // The sampled design on the same plant settles.
        let errors = closed_loop_errors(1, 0.0, 60, 30_000.0);
        assert!(
            errors[59].abs() < 1e-12,
            "sampled design error {}",
            errors[59]
        );
    }
}
