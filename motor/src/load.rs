//! The load torque opposing +θ, unknown to the controller:
//!
//! ```text
//! τ(t, θ, ω) = τ_L + Σ steps (each from its instant on) + Σ ramps (linear between their
//!              start and end, held after) + τ_c tanh(ω/ω_c) + T_d sin(h N_r θ + φ)
//! ```
//!
//! Times are from the start of the run (the first sample; on a drive, from ENABLE). Steps
//! and ramps are held in place ([`MAX_STEPS`], [`MAX_RAMPS`]): a drive evaluates the load in
//! its sample interrupt, where nothing allocates.

use crate::math;

/// Steps, and ramps, a load holds at most.
pub const MAX_STEPS: usize = 16;
pub const MAX_RAMPS: usize = 16;

/// A change of the load torque at an instant, N·m added from `at_s` on.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(deny_unknown_fields)
)]
pub struct LoadStep {
    pub at_s: f64,
    pub torque_nm: f64,
}

/// A linear change of the load torque: `torque_nm` added gradually between `start_s` and
/// `end_s`, held after.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(deny_unknown_fields)
)]
pub struct LoadRamp {
    pub start_s: f64,
    pub end_s: f64,
    pub torque_nm: f64,
}

/// A load that has no room for another step or ramp.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Full;

/// What the mechanical equation needs of the plant's load.
#[derive(Debug, Clone, PartialEq)]
pub struct Disturbance {
    pub constant_nm: f64,
    steps: [LoadStep; MAX_STEPS],
    n_steps: usize,
    ramps: [LoadRamp; MAX_RAMPS],
    n_ramps: usize,
    pub coulomb_nm: f64,
    pub coulomb_smoothing_rad_s: f64,
    /// T_d, h N_r and φ.
    pub detent_nm: f64,
    pub detent_wavenumber: f64,
    pub detent_phase_rad: f64,
}

impl Disturbance {
    /// A constant load torque and nothing else: the paper's plant.
    pub fn constant(torque_nm: f64) -> Self {
        Self {
            constant_nm: torque_nm,
            steps: [LoadStep::default(); MAX_STEPS],
            n_steps: 0,
            ramps: [LoadRamp::default(); MAX_RAMPS],
            n_ramps: 0,
            coulomb_nm: 0.0,
            coulomb_smoothing_rad_s: 1.0,
            detent_nm: 0.0,
            detent_wavenumber: 0.0,
            detent_phase_rad: 0.0,
        }
    }

    /// Adds a step after those already there.
    pub fn add_step(&mut self, step: LoadStep) -> Result<(), Full> {
        let slot = self.steps.get_mut(self.n_steps).ok_or(Full)?;
        *slot = step;
        self.n_steps += 1;
        Ok(())
    }

    /// Adds a ramp after those already there.
    pub fn add_ramp(&mut self, ramp: LoadRamp) -> Result<(), Full> {
        let slot = self.ramps.get_mut(self.n_ramps).ok_or(Full)?;
        *slot = ramp;
        self.n_ramps += 1;
        Ok(())
    }

    pub fn steps(&self) -> &[LoadStep] {
        &self.steps[..self.n_steps]
    }

    pub fn ramps(&self) -> &[LoadRamp] {
        &self.ramps[..self.n_ramps]
    }

    /// The load torque opposing +θ at time `t` (from the run's start), angle θ, speed ω, N·m.
    /// With only a constant load it returns that constant exactly (the paper's figures stay
    /// bit for bit).
    pub fn torque(&self, t: f64, theta: f64, omega: f64) -> f64 {
        let mut tau = self.constant_nm;
        for s in self.steps() {
            if t >= s.at_s {
                tau += s.torque_nm;
            }
        }
        for r in self.ramps() {
            if t >= r.start_s {
                let share = ((t - r.start_s) / (r.end_s - r.start_s)).min(1.0);
                tau += share * r.torque_nm;
            }
        }
        if self.coulomb_nm != 0.0 {
            tau += self.coulomb_nm * math::tanh(omega / self.coulomb_smoothing_rad_s);
        }
        if self.detent_nm != 0.0 {
            tau +=
                self.detent_nm * math::sin(self.detent_wavenumber * theta + self.detent_phase_rad);
        }
        tau
    }

    /// True when the load depends on nothing but a constant.
    pub fn is_constant(&self) -> bool {
        self.n_steps == 0 && self.n_ramps == 0 && self.coulomb_nm == 0.0 && self.detent_nm == 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_constant_load_is_that_constant_exactly() {
        let d = Disturbance::constant(0.01);
        assert!(d.is_constant());
        assert_eq!(d.torque(1.0, 3.0, 13.0).to_bits(), 0.01f64.to_bits());
    }

    #[test]
    fn steps_ramps_friction_and_detent_add_up() {
        let mut d = Disturbance::constant(0.0);
        d.add_step(LoadStep {
            at_s: 1.0,
            torque_nm: 0.02,
        })
        .expect("room");
        d.add_ramp(LoadRamp {
            start_s: 2.0,
            end_s: 3.0,
            torque_nm: -0.01,
        })
        .expect("room");
        assert_eq!(d.torque(0.5, 0.0, 0.0), 0.0);
        assert!((d.torque(1.0, 0.0, 0.0) - 0.02).abs() < 1e-15);
        assert!((d.torque(2.5, 0.0, 0.0) - 0.015).abs() < 1e-15);
        assert!((d.torque(9.0, 0.0, 0.0) - 0.01).abs() < 1e-15);
        d.coulomb_nm = 0.002;
        d.coulomb_smoothing_rad_s = 0.1;
        // Friction opposes the motion and saturates at τ_c.
        assert!((d.torque(0.0, 0.0, 10.0) - 0.002).abs() < 1e-12);
        assert!((d.torque(0.0, 0.0, -10.0) + 0.002).abs() < 1e-12);
        d.coulomb_nm = 0.0;
        d.detent_nm = 0.04;
        d.detent_wavenumber = 200.0;
        // A quarter of the detent's period away from a stable point: the full T_d.
        let quarter = core::f64::consts::TAU / 200.0 / 4.0;
        assert!((d.torque(0.0, quarter, 0.0) - 0.04).abs() < 1e-12);
        assert!(!d.is_constant());
    }

    #[test]
    fn a_full_load_refuses_another_step_and_keeps_its_own() {
        let mut d = Disturbance::constant(0.0);
        for n in 0..MAX_STEPS {
            let at_s = n as f64;
            d.add_step(LoadStep {
                at_s,
                torque_nm: 1.0,
            })
            .expect("room");
        }
        let extra = LoadStep {
            at_s: 0.0,
            torque_nm: 100.0,
        };
        assert_eq!(d.add_step(extra), Err(Full));
        assert_eq!(d.steps().len(), MAX_STEPS);
        assert_eq!(d.torque(1e9, 0.0, 0.0), MAX_STEPS as f64);
    }
}
