//! The industrial baseline's current loop: one PI controller per phase, as most stepper
//! drives run it, with no back-EMF feed-forward and no model of the rotor.
//!
//! Design: the winding is 1/(L s + R). With K_p = ω_c L and K_i = ω_c R the PI zero cancels
//! the winding's pole and the loop gain is ω_c / s: the closed loop is first order with
//! bandwidth ω_c, whatever R/L is. The sampled loop adds one period of compute delay and
//! half a period of zero-order hold (1.5 T = 75 µs at 20 kHz), which costs ω_c · 1.5 T of
//! phase at crossover: 27° at ω_c = 2π·1 kHz, leaving 63° of margin. The integrator is
//! forward Euler and stops integrating while the output is at the bus limit (conditional
//! integration: no wind-up through a voltage-limited stretch).

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PiCurrent {
    kp: f64,
    /// K_i T.
    ki_t: f64,
    integral: [f64; 2],
}

impl PiCurrent {
    /// Gains for inductance `l`, resistance `r`, bandwidth `omega_c` (rad/s), sample period
    /// `period` (s).
    pub fn new(l: f64, r: f64, omega_c: f64, period: f64) -> Self {
        Self {
            kp: omega_c * l,
            ki_t: omega_c * r * period,
            integral: [0.0; 2],
        }
    }

    /// The phase voltages for the current error `reference − measured`, limited to ±`limit`.
    pub fn decide(&mut self, reference: [f64; 2], measured: [f64; 2], limit: f64) -> [f64; 2] {
        let mut v = [0.0; 2];
        for p in 0..2 {
            let e = reference[p] - measured[p];
            let raw = self.kp * e + self.integral[p];
            v[p] = raw.clamp(-limit, limit);
            let winding_up = (raw > limit && e > 0.0) || (raw < -limit && e < 0.0);
            if !winding_up {
                self.integral[p] = (self.integral[p] + self.ki_t * e).clamp(-limit, limit);
            }
        }
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const L: f64 = 40e-3;
    const R: f64 = 14.8;
    const T: f64 = 50e-6;

    /// Locked rotor, reference step of 0.04 A on phase a (small enough not to reach the
    /// bus: the linear design), the winding integrated exactly
    /// (zero-order hold) with one period of compute delay. The sampled loop behaves as the
    /// design says: 63 % of the step within one time constant 1/ω_c plus the 1.5 T of delay
    /// (±1 period), overshoot under the 10 % a 63° phase margin allows, and no steady error.
    #[test]
    fn sampled_step_response_is_the_designed_first_order_one() {
        let omega_c = 2000.0 * std::f64::consts::PI;
        let mut pi = PiCurrent::new(L, R, omega_c, T);
        let step = 0.04;
        let decay = (-R * T / L).exp();
        let (mut i, mut pending) = (0.0, 0.0);
        let mut samples = Vec::new();
        for _ in 0..400 {
            samples.push(i);
            let v = pi.decide([step, 0.0], [i, 0.0], 24.0)[0];
            assert!(v.abs() < 24.0, "linear");
            // The voltage decided at sample k is applied over the period after the next.
            let applied = std::mem::replace(&mut pending, v);
            i = i * decay + applied / R * (1.0 - decay);
        }
        let reach = samples
            .iter()
            .position(|&x| x >= 0.632 * step)
            .expect("rises");
        let designed = (1.0 / omega_c + 1.5 * T) / T;
        assert!(
            (reach as f64 - designed).abs() <= 1.5,
            "63 % after {reach} periods, designed {designed:.1}"
        );
        let peak = samples.iter().fold(0.0, |a: f64, &b| a.max(b));
        assert!(
            peak < 1.10 * step,
            "overshoot {:.1} %",
            100.0 * (peak / step - 1.0)
        );
        let steady = (samples[399] - step).abs() / step;
        assert!(steady < 1e-4, "steady error {steady:e} of the step");
    }

    /// A sinusoidal reference at the cruise's electrical frequency (656 rad/s) lags as the
    /// closed loop 1 / (1 + (s/ω_c) e^{sτ}) with τ = 1.5 T says: ~atan(ω/ω_c), the delay
    /// only adding at second order. Lag in the current is lag in the rotor: this is what
    /// the baseline's cruise error has on top of microstepping's.
    #[test]
    fn sinusoidal_tracking_lags_as_the_first_order_loop_does() {
        let omega_c = 2000.0 * std::f64::consts::PI;
        let w = 50.0 * 13.13;
        let mut pi = PiCurrent::new(L, R, omega_c, T);
        let decay = (-R * T / L).exp();
        let (mut i, mut pending) = (0.0, 0.0);
        let (mut re, mut im) = (0.0, 0.0);
        let n = 40_000;
        for k in 0..n {
            let t = f64::from(k) * T;
            let reference = (w * t).cos();
            if k >= n / 2 {
                re += i * (w * t).cos();
                im += i * (w * t).sin();
            }
            let v = pi.decide([reference, 0.0], [i, 0.0], 1e3)[0];
            let applied = std::mem::replace(&mut pending, v);
            i = i * decay + applied / R * (1.0 - decay);
        }
        let lag = im.atan2(re);
        let (x, wt) = (w / omega_c, w * 1.5 * T);
        let expected = (x * wt.cos()).atan2(1.0 - x * wt.sin());
        assert!(
            (lag - expected).abs() < 0.005,
            "lag {lag:.4} rad vs {expected:.4}"
        );
    }

    #[test]
    fn the_integrator_does_not_wind_up_at_the_limit() {
        let mut pi = PiCurrent::new(L, R, 6283.0, T);
        for _ in 0..10_000 {
            assert_eq!(pi.decide([10.0, -10.0], [0.0, 0.0], 24.0), [24.0, -24.0]);
        }
        // Reference reached: the output leaves the limit at once instead of unwinding.
        let v = pi.decide([0.0, 0.0], [0.0, 0.0], 24.0);
        assert!(v[0].abs() < 24.0 && v[1].abs() < 24.0, "{v:?}");
    }
}
