//! The motor the plant (or the emulated drive) simulates, when it is not the motor the
//! controller's model describes: `[plant.motor]` overrides fields of `[motor]`, `[plant.load]`
//! adds a load profile and Coulomb friction, `[plant.detent]` adds detent torque. Absent,
//! the plant is exactly the controller's model (eq. (1) with the constant τ_L of `[load]`).
//!
//! The plant's mechanical equation becomes
//!
//! ```text
//! J ω' = K_m i_q − B ω − τ_load(t) − τ_c tanh(ω/ω_c) − T_d sin(h N_r θ + φ)
//! ```
//!
//! with τ_load(t) = τ_L + Σ steps (each from its instant on) + Σ ramps (linear between
//! their start and end, held after). The electrical equations are unchanged.

use serde::{Deserialize, Serialize};

use crate::scenario::{invalid, within, MotorParams, ScenarioError};

/// Fields of `[motor]` the plant's motor has instead (the rotor's tooth count is not
/// uncertain, so it cannot differ).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotorOverride {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub inductance_h: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resistance_ohm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub inertia_kg_m2: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub torque_constant_nm_per_a: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub viscous_friction_nm_s_per_rad: Option<f64>,
}

impl MotorOverride {
    /// `model` with these fields replaced.
    pub fn apply(&self, model: &MotorParams) -> MotorParams {
        MotorParams {
            inductance_h: self.inductance_h.unwrap_or(model.inductance_h),
            resistance_ohm: self.resistance_ohm.unwrap_or(model.resistance_ohm),
            inertia_kg_m2: self.inertia_kg_m2.unwrap_or(model.inertia_kg_m2),
            torque_constant_nm_per_a: self
                .torque_constant_nm_per_a
                .unwrap_or(model.torque_constant_nm_per_a),
            rotor_teeth: model.rotor_teeth,
            viscous_friction_nm_s_per_rad: self
                .viscous_friction_nm_s_per_rad
                .unwrap_or(model.viscous_friction_nm_s_per_rad),
        }
    }
}

/// The motor model's load: the scenario's `[plant.load]` entries are its steps and ramps.
pub use stepdrive_motor::load::{MAX_RAMPS, MAX_STEPS};
pub use stepdrive_motor::{Disturbance, LoadRamp, LoadStep};

/// The plant's load, unknown to the controller. Times are from the start of the run (the
/// first sample; on a drive, from ENABLE).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlantLoad {
    /// Constant load torque opposing +θ, N·m; absent: `[load] torque_nm`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub torque_nm: Option<f64>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub steps: Vec<LoadStep>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ramps: Vec<LoadRamp>,
    /// Coulomb (dry) friction τ_c, N·m, opposing the motion.
    pub coulomb_nm: f64,
    /// ω_c of the smooth sign tanh(ω/ω_c), rad/s: friction reaches 76 % of τ_c at ω_c.
    pub coulomb_smoothing_rad_s: f64,
}

/// Detent (cogging) torque T_d sin(h N_r θ + φ), opposing the motion away from its stable
/// points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Detent {
    /// T_d, N·m (0 = none).
    pub amplitude_nm: f64,
    /// h: periods per electrical period; a hybrid stepper's detent is mostly the 4th.
    pub harmonic: u32,
    /// φ, rad.
    pub phase_rad: f64,
}

impl Default for Detent {
    fn default() -> Self {
        Self {
            amplitude_nm: 0.0,
            harmonic: 4,
            phase_rad: 0.0,
        }
    }
}

/// `[plant.brake]`: the motor's holding brake, spring-applied, released by the drive
/// (`[axis] brake_release_s` after it enables, applied again whenever its outputs go off).
/// Applied, it holds the rotor against up to `holding_torque_nm` and brakes a turning rotor
/// with that torque until it stands. A brake keeps a loaded rotor where it stood while the
/// axis is disabled, and at an enable until the current holds it. The simulated plant fits
/// it to commanded stacks (a program, `serve`); a run of the scenario's profile (the
/// paper's experiment) starts enabled, as it always did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Brake {
    /// The most torque it holds, N·m (0 = no brake).
    pub holding_torque_nm: f64,
}

impl Default for Brake {
    fn default() -> Self {
        Self {
            holding_torque_nm: 0.5,
        }
    }
}

/// `[plant]`: how the simulated motor differs from the controller's model.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlantParams {
    pub motor: MotorOverride,
    pub load: PlantLoad,
    pub detent: Detent,
    pub brake: Brake,
}

impl PlantParams {
    /// Absent from a scenario: the plant is the model.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    pub(crate) fn validate(&self) -> Result<(), ScenarioError> {
        let m = &self.motor;
        let optional = |field, v: Option<f64>, lo, hi, unit| match v {
            Some(v) => within(field, v, lo, hi, unit),
            None => Ok(()),
        };
        optional("plant.motor.inductance_h", m.inductance_h, 1e-6, 10.0, "H")?;
        optional(
            "plant.motor.resistance_ohm",
            m.resistance_ohm,
            1e-4,
            1e4,
            "Ω",
        )?;
        optional(
            "plant.motor.inertia_kg_m2",
            m.inertia_kg_m2,
            1e-9,
            10.0,
            "kg·m²",
        )?;
        optional(
            "plant.motor.torque_constant_nm_per_a",
            m.torque_constant_nm_per_a,
            1e-4,
            100.0,
            "N·m/A",
        )?;
        optional(
            "plant.motor.viscous_friction_nm_s_per_rad",
            m.viscous_friction_nm_s_per_rad,
            0.0,
            100.0,
            "N·m·s/rad",
        )?;
        let l = &self.load;
        optional("plant.load.torque_nm", l.torque_nm, -1e3, 1e3, "N·m")?;
        for (field, n, max) in [
            ("plant.load.steps", l.steps.len(), MAX_STEPS),
            ("plant.load.ramps", l.ramps.len(), MAX_RAMPS),
        ] {
            if n > max {
                return Err(invalid(
                    field,
                    format!("{n} entries; the plant's load holds at most {max}"),
                ));
            }
        }
        for (n, step) in l.steps.iter().enumerate() {
            within("plant.load.steps", step.at_s, 0.0, 1e9, "s (at_s)")
                .and_then(|()| within("plant.load.steps", step.torque_nm, -1e3, 1e3, "N·m"))
                .map_err(|e| entry(e, n))?;
        }
        for (n, ramp) in l.ramps.iter().enumerate() {
            within("plant.load.ramps", ramp.start_s, 0.0, 1e9, "s (start_s)")
                .and_then(|()| within("plant.load.ramps", ramp.end_s, 0.0, 1e9, "s (end_s)"))
                .and_then(|()| within("plant.load.ramps", ramp.torque_nm, -1e3, 1e3, "N·m"))
                .map_err(|e| entry(e, n))?;
            if ramp.end_s <= ramp.start_s {
                return Err(invalid(
                    "plant.load.ramps",
                    format!(
                        "entry {n}: end_s ({}) must be after start_s ({})",
                        ramp.end_s, ramp.start_s
                    ),
                ));
            }
        }
        within("plant.load.coulomb_nm", l.coulomb_nm, 0.0, 1e3, "N·m")?;
        if l.coulomb_nm > 0.0 {
            within(
                "plant.load.coulomb_smoothing_rad_s",
                l.coulomb_smoothing_rad_s,
                1e-6,
                1e3,
                "rad/s (the smooth sign needs a positive width)",
            )?;
        }
        within(
            "plant.brake.holding_torque_nm",
            self.brake.holding_torque_nm,
            0.0,
            1e3,
            "N·m",
        )?;
        let d = &self.detent;
        within("plant.detent.amplitude_nm", d.amplitude_nm, 0.0, 1e3, "N·m")?;
        if !(1..=64).contains(&d.harmonic) {
            return Err(invalid(
                "plant.detent.harmonic",
                format!("must be 1..=64 (got {})", d.harmonic),
            ));
        }
        within("plant.detent.phase_rad", d.phase_rad, -1e3, 1e3, "rad")?;
        Ok(())
    }
}

/// Names the list entry an error came from.
fn entry(e: ScenarioError, n: usize) -> ScenarioError {
    match e {
        ScenarioError::Invalid { field, message } => ScenarioError::Invalid {
            field,
            message: format!("entry {n}: {message}"),
        },
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use crate::Scenario;

    #[test]
    fn absent_plant_section_is_the_model() {
        let s = Scenario::default();
        assert!(s.plant.is_default());
        assert_eq!(s.plant_motor(), s.motor);
        let d = s.disturbance();
        assert!(d.is_constant());
        assert_eq!(d.torque(1.0, 3.0, 13.0).to_bits(), 0.01f64.to_bits());
    }

    #[test]
    fn overrides_steps_ramps_friction_and_detent_add_up() {
        let s = Scenario::from_toml_str(
            "[plant.motor]\nresistance_ohm = 17.76\n\
             [plant.load]\ntorque_nm = 0.0\ncoulomb_nm = 0.002\ncoulomb_smoothing_rad_s = 0.1\n\
             steps = [{ at_s = 1.0, torque_nm = 0.02 }]\n\
             ramps = [{ start_s = 2.0, end_s = 3.0, torque_nm = -0.01 }]\n\
             [plant.detent]\namplitude_nm = 0.04\n",
        )
        .expect("valid");
        let m = s.plant_motor();
        assert_eq!(m.resistance_ohm, 17.76);
        assert_eq!(m.inductance_h, s.motor.inductance_h);
        let d = s.disturbance();
        // At rest at a detent's stable point, before the step: nothing.
        assert_eq!(d.torque(0.5, 0.0, 0.0), 0.0);
        assert!((d.torque(1.0, 0.0, 0.0) - 0.02).abs() < 1e-15);
        assert!((d.torque(2.5, 0.0, 0.0) - 0.015).abs() < 1e-15);
        assert!((d.torque(9.0, 0.0, 0.0) - 0.01).abs() < 1e-15);
        // Friction opposes the motion and saturates at τ_c.
        assert!((d.torque(0.0, 0.0, 10.0) - 0.002).abs() < 1e-12);
        assert!((d.torque(0.0, 0.0, -10.0) + 0.002).abs() < 1e-12);
        // Detent: period 2π/(4 N_r); a quarter of it away from a stable point, the full T_d.
        let quarter = std::f64::consts::TAU / (4.0 * 50.0) / 4.0;
        assert!((d.torque(0.0, quarter, 0.0) - 0.04).abs() < 1e-12);
    }

    #[test]
    fn bad_plant_values_are_refused_by_name() {
        let err = |t: &str| Scenario::from_toml_str(t).expect_err(t).to_string();
        assert!(err("[plant.motor]\ninertia_kg_m2 = -1.0").contains("plant.motor.inertia_kg_m2"));
        assert!(err("[plant.motor]\nrotor_teeth = 49").contains("rotor_teeth"));
        assert!(
            err("[plant.load]\nramps = [{ start_s = 2.0, end_s = 1.0, torque_nm = 0.1 }]")
                .contains("entry 0: end_s")
        );
        assert!(
            err("[plant.load]\nsteps = [{ at_s = nan, torque_nm = 0.1 }]")
                .contains("plant.load.steps")
        );
        assert!(
            err("[plant.load]\ncoulomb_nm = 0.01\ncoulomb_smoothing_rad_s = 0.0")
                .contains("coulomb_smoothing_rad_s")
        );
        assert!(err("[plant.detent]\nharmonic = 0").contains("plant.detent.harmonic"));
        // The motor model holds its load in place (a drive allocates nothing): one more step
        // than it holds is refused, not dropped.
        let steps = |n: usize| {
            let one = "{ at_s = 1.0, torque_nm = 0.001 }";
            format!("[plant.load]\nsteps = [{}]", vec![one; n].join(", "))
        };
        assert!(Scenario::from_toml_str(&steps(super::MAX_STEPS)).is_ok());
        assert!(err(&steps(super::MAX_STEPS + 1)).contains("plant.load.steps"));
        assert!(err("[control]\nobserver_bandwidth_rad_s = 7000.0").contains("at most π × rates"));
        assert!(err("[control]\nload_compensation = \"guess\"").contains("load_compensation"));
        // The defaults follow the rates, so a slow stack is valid as it is.
        let slow = Scenario::from_toml_str(
            "[rates]\ncurrent_loop_hz = 2000.0\nposition_loop_hz = 200.0\n\
             [control]\nload_compensation = \"observer\"",
        )
        .expect("valid");
        assert_eq!(slow.observer_bandwidth_rad_s(), 400.0);
        assert!((slow.pi_bandwidth_rad_s() - 628.3185307179587).abs() < 1e-9);
    }
}
