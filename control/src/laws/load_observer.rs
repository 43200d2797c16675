//! A load-torque (disturbance) observer for the position/torque loop: estimates the lumped
//! disturbance d in J ω' = τ − B ω − d (the load, friction, detent and every model error
//! between the torque command and the shaft) so that (12) can use d̂ in place of τ_L.
//!
//! Design, for the sampled loop as it is:
//! - Input: the torque the loop *commanded*, not K_m i_q from the measured currents.
//!   What lies between the command and the shaft (the current loop's tracking error with a
//!   wrong R, L or K_m, ~2–7e-4 N·m at cruise for ±20 %) is then part of d and is
//!   compensated; an observer fed with measured currents would leave it uncompensated and,
//!   through the outer loop's stiffness of ~1 N·m/rad, cost as many rad.
//! - Measurement: ω at each tick (the plant's, or the bridge's velocity estimate).
//! - Model: the mechanical equation integrated exactly over the interval between two ticks,
//!   with the torque of the previous command for the first `delay_s` of it (the command
//!   reaches the winding one compute delay later and the current follows within ~1/k_3)
//!   and the new one after. Inverting it gives d over each interval exactly when d is
//!   constant; a first-order filter with pole e^{−λT} smooths it. A step in d is therefore
//!   seen one tick late and then settles like 1 − e^{−λt}.
//! - Bandwidth: the outer loop of (12) is slow (ω_n = 112 rad/s, ζ = 0.56 with Table I's
//!   k_1 = k_2 = 0.01, decay rate 62.5 1/s), so what a load step leaves in the error is
//!   mostly the impulse ∫(d − d̂) dt that reaches the mechanics before d̂ catches up. For
//!   a +0.02 N·m step to be back within 1e-4 rad in 50 ms that impulse must stay under
//!   ~1.7e-5 N·m·s: one tick (0.5 ms) plus 1/λ of lag needs λ ≳ 2500 rad/s. Measured on the
//!   default scenario (lockstep / hardware mode through the emulated drive's 20-bit encoder
//!   and 16-bit ADCs): λ = 3000 is back in 48.5 / 47.3 ms, 4000 in 45.5 / 29.4 ms, 5000 in
//!   29.7 / 29.2 ms; the cruise error in hardware mode, where the estimate sees the
//!   quantised sensors, is 5.7e-6, 9.2e-6 and 2.6e-5 rad. The default, 2 f_pos = 4000 rad/s at
//!   2 kHz (pole e^{−2} = 0.135 per tick), meets the 50 ms in both modes for a third of 5000's noise. The
//!   validator caps λ at π f_pos, past which the filter would pass tick-to-tick noise
//!   straight into the torque.

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadObserver {
    /// J, kg·m², and B, N·m·s/rad, of the controller's model.
    j: f64,
    b: f64,
    /// How long after a tick the previous command still acts, s.
    delay_s: f64,
    /// λ, rad/s.
    bandwidth: f64,
    estimate: f64,
    last: Option<Tick>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Tick {
    time_s: f64,
    omega: f64,
    /// The command in effect when this tick's sample was taken, and the one it issued.
    torque_before: f64,
    torque: f64,
}

impl LoadObserver {
    pub fn new(j: f64, b: f64, delay_s: f64, bandwidth_rad_s: f64) -> Self {
        Self {
            j,
            b,
            delay_s,
            bandwidth: bandwidth_rad_s,
            estimate: 0.0,
            last: None,
        }
    }

    /// Starts from `prior` (the model's load, N·m) instead of 0: the first ticks, before
    /// the estimate has anything to go on, then cost nothing when the model is right.
    pub fn starting_at(mut self, prior: f64) -> Self {
        self.estimate = prior;
        self
    }

    /// The newest estimate d̂, N·m.
    pub fn estimate(&self) -> f64 {
        self.estimate
    }

    /// A new tick at `time_s` with speed `omega`: updates d̂ from the interval since the
    /// last tick and returns it.
    pub fn update(&mut self, time_s: f64, omega: f64) -> f64 {
        let Some(last) = self.last else {
            return self.estimate;
        };
        let dt = time_s - last.time_s;
        if dt.is_nan() || dt <= 0.0 || !omega.is_finite() {
            return self.estimate;
        }
        let delay = self.delay_s.min(dt);
        // ω(t+s) = e^{−βs} ω(t) + g(s) (τ − d) with β = B/J and g(s) = (1 − e^{−βs})/B.
        let beta = self.b / self.j;
        let gain = |s: f64| {
            if beta * s < 1e-12 {
                s / self.j
            } else {
                -(-beta * s).exp_m1() / self.b
            }
        };
        let early = (-beta * (dt - delay)).exp() * gain(delay);
        let late = gain(dt - delay);
        let free = (-beta * dt).exp() * last.omega;
        let measured =
            (free + early * last.torque_before + late * last.torque - omega) / (early + late);
        let pole = (-self.bandwidth * dt).exp();
        self.estimate = pole * self.estimate + (1.0 - pole) * measured;
        self.estimate
    }

    /// The torque the loop commanded at the tick just updated (time `time_s`, speed `omega`).
    pub fn commanded(&mut self, time_s: f64, omega: f64, torque: f64) {
        let torque_before = self.last.map_or(0.0, |l| l.torque);
        self.last = Some(Tick {
            time_s,
            omega,
            torque_before,
            torque,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const J: f64 = 8e-5;
    const B: f64 = 5e-3;
    const T: f64 = 5e-4;
    const DELAY: f64 = 8.3e-5;

    /// The mechanics with the command delayed as the observer assumes, integrated finely.
    struct Shaft {
        omega: f64,
    }

    impl Shaft {
        fn run(&mut self, before: f64, torque: f64, d: f64) {
            let n = 5000;
            let h = T / f64::from(n);
            for i in 0..n {
                let tau = if f64::from(i) * h < DELAY {
                    before
                } else {
                    torque
                };
                // Exact over each sub-step.
                let a = (-B / J * h).exp();
                self.omega = a * self.omega + (1.0 - a) / B * (tau - d);
            }
        }
    }

    /// A step of the disturbance at a tick: the estimate is seen one tick late and then
    /// follows 1 − e^{−λt}, the designed time constant, to rounding.
    #[test]
    fn step_disturbance_is_estimated_with_the_designed_time_constant() {
        let lambda = 3000.0;
        let mut obs = LoadObserver::new(J, B, DELAY, lambda);
        let mut shaft = Shaft { omega: 5.0 };
        let mut torque = 0.0;
        let d_step = 0.02;
        let pole = (-lambda * T).exp();
        for k in 0..40 {
            let t = f64::from(k) * T;
            let estimate = obs.update(t, shaft.omega);
            // d steps at tick 10; the interval from tick 10 on carries it.
            let expected = if k <= 10 {
                0.0
            } else {
                d_step * (1.0 - pole.powi(k - 10))
            };
            assert!(
                (estimate - expected).abs() < 1e-9,
                "tick {k}: {estimate:e} vs {expected:e}"
            );
            // Any torque program: here a ramp, so the delayed command matters.
            let before = torque;
            torque = 0.03 + 1e-3 * f64::from(k);
            obs.commanded(t, shaft.omega, torque);
            shaft.run(before, torque, if k >= 10 { d_step } else { 0.0 });
        }
    }

    /// At constant speed under τ = B ω + τ_L, the estimate is τ_L: the viscous term is the
    /// model's, not the load's, and nothing is left over.
    #[test]
    fn no_bias_at_constant_speed() {
        let mut obs = LoadObserver::new(J, B, DELAY, 3000.0);
        let (omega, tau_l) = (13.13, 0.01);
        let torque = B * omega + tau_l;
        let mut shaft = Shaft { omega };
        for k in 0..200 {
            let t = f64::from(k) * T;
            obs.update(t, shaft.omega);
            obs.commanded(t, shaft.omega, torque);
            shaft.run(torque, torque, tau_l);
        }
        assert!(
            (shaft.omega - omega).abs() < 1e-9,
            "the shaft stayed at speed"
        );
        assert!(
            (obs.estimate() - tau_l).abs() < 1e-9,
            "d̂ = {:e}",
            obs.estimate()
        );
    }

    /// A skipped tick (a realtime loop that slept through one) is an interval twice as
    /// long, not a wrong estimate.
    #[test]
    fn a_longer_interval_is_integrated_as_such() {
        let mut obs = LoadObserver::new(J, B, DELAY, 3000.0);
        let mut shaft = Shaft { omega: 2.0 };
        obs.update(0.0, shaft.omega);
        obs.commanded(0.0, shaft.omega, 0.05);
        shaft.run(0.0, 0.05, 0.01);
        shaft.run(0.05, 0.05, 0.01);
        let e = obs.update(2.0 * T, shaft.omega);
        let expected = 0.01 * (1.0 - (-3000.0 * 2.0 * T).exp());
        assert!((e - expected).abs() < 1e-9, "{e:e} vs {expected:e}");
    }
}
