//! One scenario: motor parameters (Table I by default), load, supply, controller gains,
//! loop rates, trajectory and metric windows. Loads from TOML and validates itself; every
//! error names the offending field.

pub use crate::axis::{AxisParams, ProgramStep};
use crate::messages::MAX_PLAN;
pub use crate::plant::{Disturbance, PlantParams};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// Largest compute delay (in current-loop periods) the sampled current loop is designed for.
pub const MAX_COMPUTE_DELAY_PERIODS: u32 = 4;

#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    #[error("cannot read scenario file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("scenario file {path} is not valid: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("scenario field `{field}` {message}")]
    Invalid {
        field: &'static str,
        message: String,
    },
    #[error("cannot serialise scenario: {0}")]
    Serialise(String),
}

/// Two-phase PM stepper parameters of eq. (1). Defaults: Table I (Oriental Motor PK266-01B).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotorParams {
    /// Phase inductance L, H.
    pub inductance_h: f64,
    /// Phase resistance R, Ω.
    pub resistance_ohm: f64,
    /// Rotor inertia J, kg·m².
    pub inertia_kg_m2: f64,
    /// Torque constant K_m, N·m/A (also the back-EMF constant, V·s/rad).
    pub torque_constant_nm_per_a: f64,
    /// Number of rotor teeth N_r.
    pub rotor_teeth: u32,
    /// Viscous friction B, N·m·s/rad.
    pub viscous_friction_nm_s_per_rad: f64,
}

impl Default for MotorParams {
    fn default() -> Self {
        Self {
            inductance_h: 40e-3,
            resistance_ohm: 14.8,
            inertia_kg_m2: 8e-5,
            torque_constant_nm_per_a: 0.5,
            rotor_teeth: 50,
            viscous_friction_nm_s_per_rad: 5e-3,
        }
    }
}

impl MotorParams {
    pub fn n_r(&self) -> f64 {
        f64::from(self.rotor_teeth)
    }
}

impl From<&MotorParams> for stepdrive_motor::Motor {
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

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoadParams {
    /// Constant load torque τ_L opposing +θ, N·m. Known to the controller, as in the paper.
    pub torque_nm: f64,
}

impl Default for LoadParams {
    fn default() -> Self {
        Self { torque_nm: 0.01 }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DriveParams {
    /// Supply voltage; each phase voltage is limited to ±V_bus.
    pub bus_voltage_v: f64,
    /// Realtime: periods of voltage plan the current loop sends after its commands
    /// (0..=1024). A drive whose next command is late applies the plan's entry for that
    /// period instead of freezing the last voltage; 0 = freeze it. The default, 1000
    /// periods (50 ms at 20 kHz), matches the default watchdog: a host that holds the
    /// current loop's CPU for less than that costs no commutation.
    pub command_plan_periods: u32,
}

impl Default for DriveParams {
    fn default() -> Self {
        Self {
            bus_voltage_v: 24.0,
            command_plan_periods: 1000,
        }
    }
}

/// Controller gains, continuous-time as in Table I.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Gains {
    /// k_1 of eq. (12), 1/s.
    pub k1: f64,
    /// k_2 of eq. (12), N·m·s/rad.
    pub k2: f64,
    /// k_3 of eq. (22): designed current-error decay rate, 1/s.
    pub k3_per_s: f64,
    /// V_max of eqs. (2), (39): microstepping voltage amplitude, V.
    pub v_max_v: f64,
    /// ρ of eq. (39): the baseline's current-error decay rate, 1/s.
    pub rho_per_s: f64,
}

impl Default for Gains {
    fn default() -> Self {
        Self {
            k1: 0.01,
            k2: 0.01,
            k3_per_s: 30_000.0,
            v_max_v: 6.5,
            rho_per_s: 30_000.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Rates {
    /// Plant sample rate = current-loop rate, Hz.
    pub current_loop_hz: f64,
    /// Position/torque-loop rate, Hz; must divide `current_loop_hz`.
    pub position_loop_hz: f64,
    /// Periods between the sample a voltage is computed from and the period it is applied in
    /// (1 = a PWM drive: computed from sample k, applied over (t_{k+1}, t_{k+2}]).
    pub compute_delay_periods: u32,
    /// RK4 sub-steps per plant sample.
    pub plant_substeps: u32,
}

impl Default for Rates {
    fn default() -> Self {
        Self {
            current_loop_hz: 20_000.0,
            position_loop_hz: 2_000.0,
            compute_delay_periods: 1,
            plant_substeps: 4,
        }
    }
}

/// Trapezoidal velocity profile from rest at θ = 0: accelerate, cruise, decelerate, hold.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrajectoryParams {
    pub cruise_velocity_rad_s: f64,
    pub accel_s: f64,
    pub cruise_s: f64,
    pub decel_s: f64,
    pub hold_s: f64,
}

impl Default for TrajectoryParams {
    fn default() -> Self {
        Self {
            cruise_velocity_rad_s: 13.13,
            accel_s: 0.5,
            cruise_s: 1.0,
            decel_s: 0.5,
            hold_s: 0.5,
        }
    }
}

/// Windows the metrics are taken over.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetricWindows {
    /// Settled constant-velocity window [start, end], s.
    pub cruise_start_s: f64,
    pub cruise_end_s: f64,
    /// The final error is the mean of θ_d − θ over this last span of the run, s.
    pub final_window_s: f64,
}

impl Default for MetricWindows {
    fn default() -> Self {
        Self {
            cruise_start_s: 0.9,
            cruise_end_s: 1.5,
            final_window_s: 0.1,
        }
    }
}

/// Length of a run. By default one pass of the trajectory; a longer run repeats the move
/// back and forth (forward, back to θ = 0, forward, ...).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunParams {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub duration_s: Option<f64>,
    /// Runs until stopped (`stepdrive serve`): no last sample, `duration_s` ignored.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub until_stopped: bool,
}

/// Everything a run needs. `Scenario::default()` is the paper's Section V scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    pub motor: MotorParams,
    pub load: LoadParams,
    pub drive: DriveParams,
    pub gains: Gains,
    pub rates: Rates,
    pub trajectory: TrajectoryParams,
    pub metrics: MetricWindows,
    pub run: RunParams,
    /// How the simulated motor differs from `motor` and `load` (absent: it does not).
    #[serde(skip_serializing_if = "PlantParams::is_default")]
    pub plant: PlantParams,
    /// Load compensation of (12) and the industrial baseline's current loop.
    #[serde(skip_serializing_if = "ControlParams::is_default")]
    pub control: ControlParams,
    /// The axis's limits and defaults (absent: the defaults).
    #[serde(skip_serializing_if = "AxisParams::is_default")]
    pub axis: AxisParams,
    /// A multi-axis stack's axes as one machine (absent: the defaults).
    #[serde(skip_serializing_if = "GroupParams::is_default")]
    pub group: GroupParams,
    /// Timed commands (`[[program]]`): with a program the axis runs it instead of the
    /// scenario's trajectory, deterministically in lockstep.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub program: Vec<ProgramStep>,
    /// A multi-axis stack's axes (`[[axis]]` tables), each a whole scenario of its own;
    /// empty: one axis, the file's tables ([`Self::axis_count`], [`Self::for_axis`]).
    #[serde(skip)]
    pub axes: Vec<AxisOf>,
    /// One axis of a multi-axis program that has no step of its own: it waits disabled
    /// instead of running the trajectory.
    #[serde(skip)]
    pub held: bool,
}

/// A multi-axis stack's axes as one machine (`[group]`).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GroupParams {
    /// What a fault or a quick stop of one axis does to the others.
    pub stop: GroupStop,
}

impl GroupParams {
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// [`GroupParams::stop`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GroupStop {
    /// Every other enabled axis quick-stops (axes sharing a tool must not carry on).
    #[default]
    All,
    /// Each axis stops on its own faults and commands only.
    Own,
}

/// The most axes one stack runs.
pub const MAX_AXES: usize = 8;

/// What an `[[axis]]` table may set: the axis's own tables, laid over the file's.
const AXIS_KEYS: [(&str, &str); 8] = [
    ("name", "name"),
    ("motor", "motor"),
    ("load", "load"),
    ("plant", "plant"),
    ("gains", "gains"),
    ("control", "control"),
    ("drive", "drive"),
    ("limits", "axis"),
];

/// One axis of a multi-axis scenario: its `[[axis]]` table as written, and the scenario
/// it makes (the file's tables with the axis's on top, its program steps only).
#[derive(Debug, Clone, PartialEq)]
pub struct AxisOf {
    pub name: String,
    pub table: toml::Table,
    pub scenario: Scenario,
}

impl Default for Scenario {
    fn default() -> Self {
        Self {
            name: "paper-section-v".to_string(),
            motor: MotorParams::default(),
            load: LoadParams::default(),
            drive: DriveParams::default(),
            gains: Gains::default(),
            rates: Rates::default(),
            trajectory: TrajectoryParams::default(),
            metrics: MetricWindows::default(),
            run: RunParams::default(),
            plant: PlantParams::default(),
            control: ControlParams::default(),
            axis: AxisParams::default(),
            group: GroupParams::default(),
            program: Vec::new(),
            axes: Vec::new(),
            held: false,
        }
    }
}

/// What (12) uses for τ_L.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LoadCompensation {
    /// `[load] torque_nm`, as the paper assumes.
    #[default]
    Known,
    /// The load-torque observer's estimate of the lumped disturbance.
    Observer,
    /// Nothing: the soft outer loop alone holds the load.
    None,
}

impl LoadCompensation {
    pub fn as_str(self) -> &'static str {
        match self {
            LoadCompensation::Known => "known",
            LoadCompensation::Observer => "observer",
            LoadCompensation::None => "none",
        }
    }
}

/// `[control]`: choices beyond the paper's gains.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControlParams {
    /// known | observer | none.
    pub load_compensation: LoadCompensation,
    /// Bandwidth λ of the load-torque observer, rad/s: its estimate of a step settles like
    /// 1 − e^{−λt} after one position-loop period of measurement delay. Absent: 2 ×
    /// `rates.position_loop_hz` (4000 rad/s at 2 kHz: pole e^{−2} per tick; see
    /// `control/src/laws/load_observer.rs` for why).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub observer_bandwidth_rad_s: Option<f64>,
    /// ω_c of the industrial baseline's PI current loops (`--method pi`), rad/s: K_p = ω_c L,
    /// K_i = ω_c R. Absent: 2π × `rates.current_loop_hz` / 20 (1 kHz at 20 kHz: 27° of
    /// phase lost to the 1.5 periods of compute delay and hold at crossover).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pi_bandwidth_rad_s: Option<f64>,
}

impl ControlParams {
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// A number as a person writes it: `1e-300`, not three hundred zeros.
pub fn num(v: f64) -> String {
    if v != 0.0 && v.is_finite() && (v.abs() < 1e-3 || v.abs() >= 1e6) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// `v` must be finite and within [lo, hi] (`unit` for the message).
pub(crate) fn within(
    field: &'static str,
    v: f64,
    lo: f64,
    hi: f64,
    unit: &str,
) -> Result<(), ScenarioError> {
    if v.is_finite() && v >= lo && v <= hi {
        return Ok(());
    }
    Err(invalid(
        field,
        format!(
            "must be between {} and {} {unit} (got {})",
            num(lo),
            num(hi),
            num(v)
        ),
    ))
}

/// Lays `value` over `into` in `table`: tables field by field, anything else replaced.
fn lay_over(table: &mut toml::Table, into: &str, value: &toml::Value) {
    match (table.get_mut(into), value) {
        (Some(toml::Value::Table(under)), toml::Value::Table(over)) => {
            for (key, v) in over {
                lay_over(under, key, v);
            }
        }
        _ => {
            table.insert(into.to_string(), value.clone());
        }
    }
}

/// A scenario text that is not valid TOML of a scenario (the file's path is put in by
/// [`Scenario::from_toml_file`]).
fn parse_error(message: String) -> ScenarioError {
    ScenarioError::Parse {
        path: PathBuf::from("<string>"),
        message,
    }
}

pub(crate) fn invalid(field: &'static str, message: String) -> ScenarioError {
    ScenarioError::Invalid { field, message }
}

/// Most samples a run may have (a 20 kHz run of 13.9 hours).
pub const MAX_SAMPLES: u64 = 1_000_000_000;

/// A program's run lasts this long past its last step unless `run.duration_s` says.
pub const PROGRAM_TAIL_S: f64 = 2.0;

impl Scenario {
    /// Reads and validates a TOML scenario. Absent fields take their defaults; unknown
    /// fields are errors (a typo must not silently fall back to a default).
    pub fn from_toml_file(path: &Path) -> Result<Self, ScenarioError> {
        let text = std::fs::read_to_string(path).map_err(|source| ScenarioError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml_str(&text).map_err(|e| match e {
            ScenarioError::Parse { message, .. } => ScenarioError::Parse {
                path: path.to_path_buf(),
                message,
            },
            other => other,
        })
    }

    pub fn from_toml_str(text: &str) -> Result<Self, ScenarioError> {
        let table: toml::Table = toml::from_str(text).map_err(|e| parse_error(e.to_string()))?;
        if matches!(table.get("axis"), Some(toml::Value::Array(_))) {
            return Self::with_axes(table);
        }
        // One axis: read straight from the text, whose errors point at their line.
        let scenario: Scenario = toml::from_str(text).map_err(|e| parse_error(e.to_string()))?;
        scenario.validate()?;
        if let Some((i, step)) = scenario
            .program
            .iter()
            .enumerate()
            .find(|(_, p)| p.axis != 0)
        {
            return Err(invalid(
                "program.axis",
                format!(
                    "(step {i}) names axis {}; without [[axis]] tables the scenario has axis 0 only",
                    step.axis
                ),
            ));
        }
        Ok(scenario)
    }

    /// A file with `[[axis]]` tables: the file's other tables are every axis's defaults, and
    /// each axis's tables lay its own values over them, field by field.
    fn with_axes(mut table: toml::Table) -> Result<Self, ScenarioError> {
        let Some(toml::Value::Array(entries)) = table.remove("axis") else {
            unreachable!("with_axes is called for an [[axis]] array")
        };
        if entries.is_empty() || entries.len() > MAX_AXES {
            return Err(invalid(
                "axis",
                format!(
                    "has {} [[axis]] tables; a stack runs 1..={MAX_AXES}",
                    entries.len()
                ),
            ));
        }
        let mut base: Scenario = toml::Value::Table(table.clone())
            .try_into()
            .map_err(|e: toml::de::Error| parse_error(e.to_string()))?;
        base.validate()?;
        let n = entries.len();
        if let Some((i, step)) = base
            .program
            .iter()
            .enumerate()
            .find(|(_, p)| p.axis as usize >= n)
        {
            return Err(invalid(
                "program.axis",
                format!(
                    "(step {i}) names axis {}; the scenario has axes 0..{}",
                    step.axis,
                    n - 1
                ),
            ));
        }
        let mut axes = Vec::with_capacity(n);
        for (i, entry) in entries.into_iter().enumerate() {
            let toml::Value::Table(entry) = entry else {
                return Err(invalid("axis", format!("(axis {i}) must be a table")));
            };
            let mut merged = table.clone();
            let mut name = format!("axis{i}");
            for (key, value) in &entry {
                let Some(&(_, into)) = AXIS_KEYS.iter().find(|(k, _)| k == key) else {
                    let keys: Vec<&str> = AXIS_KEYS.iter().map(|(k, _)| *k).collect();
                    return Err(invalid(
                        "axis",
                        format!(
                            "(axis {i}) has an unknown key `{key}`; an [[axis]] table takes {}",
                            keys.join(", ")
                        ),
                    ));
                };
                if key == "name" {
                    match value.as_str() {
                        Some(text) if !text.is_empty() => name = text.to_string(),
                        _ => {
                            return Err(invalid(
                                "axis.name",
                                format!("(axis {i}) must be a non-empty string"),
                            ))
                        }
                    }
                    continue;
                }
                lay_over(&mut merged, into, value);
            }
            if let Some(other) = axes.iter().position(|a: &AxisOf| a.name == name) {
                return Err(invalid(
                    "axis.name",
                    format!("(axis {i}) `{name}` is axis {other}'s name too"),
                ));
            }
            let mut scenario: Scenario = toml::Value::Table(merged)
                .try_into()
                .map_err(|e: toml::de::Error| parse_error(format!("axis {i} ({name}): {e}")))?;
            // Every axis runs as long as the whole program, on its own steps.
            if !scenario.run.until_stopped {
                scenario.run.duration_s = Some(base.duration_s());
            }
            scenario.held = !scenario.program.is_empty()
                && !scenario.program.iter().any(|p| p.axis as usize == i);
            scenario.program.retain(|p| p.axis as usize == i);
            // Within its own scenario an axis is the one axis; its loops know their index.
            for step in &mut scenario.program {
                step.axis = 0;
            }
            scenario.validate().map_err(|e| match e {
                ScenarioError::Invalid { field, message } => ScenarioError::Invalid {
                    field,
                    message: format!("(axis {i}, {name}) {message}"),
                },
                other => other,
            })?;
            axes.push(AxisOf {
                name,
                table: entry,
                scenario,
            });
        }
        base.axes = axes;
        Ok(base)
    }

    /// How many axes the stack runs (1 without `[[axis]]` tables).
    pub fn axis_count(&self) -> usize {
        self.axes.len().max(1)
    }

    /// Axis `n`'s own scenario: the scenario itself for a one-axis file; a multi-axis file's
    /// axis has its tables over the file's and only its program steps. `None` past the last.
    pub fn for_axis(&self, n: usize) -> Option<&Scenario> {
        if self.axes.is_empty() {
            return (n == 0).then_some(self);
        }
        self.axes.get(n).map(|a| &a.scenario)
    }

    /// Axis `n`'s name: its `[[axis]]` table's, or `axis<n>`.
    pub fn axis_name(&self, n: usize) -> String {
        self.axes
            .get(n)
            .map_or_else(|| format!("axis{n}"), |a| a.name.clone())
    }

    pub fn to_toml_string(&self) -> Result<String, ScenarioError> {
        let error = |e: toml::ser::Error| ScenarioError::Serialise(e.to_string());
        if self.axes.is_empty() {
            return toml::to_string(self).map_err(error);
        }
        let mut table = toml::Table::try_from(self).map_err(error)?;
        table.insert(
            "axis".to_string(),
            toml::Value::Array(
                self.axes
                    .iter()
                    .map(|a| toml::Value::Table(a.table.clone()))
                    .collect(),
            ),
        );
        toml::to_string(&table).map_err(error)
    }

    /// As [`Self::to_toml_string`], with the `[plant]`, `[control]` and `[axis]` tables
    /// written even at their defaults (which the compact form leaves out): every setting a
    /// user can change, with its value (`stepdrive scenario`).
    pub fn to_full_toml_string(&self) -> Result<String, ScenarioError> {
        #[derive(Serialize)]
        struct AtDefaults<'a> {
            plant: Option<&'a PlantParams>,
            control: Option<&'a ControlParams>,
            axis: Option<&'a AxisParams>,
        }
        let rest = AtDefaults {
            plant: self.plant.is_default().then_some(&self.plant),
            control: self.control.is_default().then_some(&self.control),
            // A multi-axis file's `axis` is its `[[axis]]` array.
            axis: (self.axis.is_default() && self.axes.is_empty()).then_some(&self.axis),
        };
        let rest = toml::to_string(&rest).map_err(|e| ScenarioError::Serialise(e.to_string()))?;
        Ok(format!("{}\n{rest}", self.to_toml_string()?))
    }

    /// Checks every field against what a real stepper stack can mean: finite, and within a
    /// plausible range (wide enough for any stepper, narrow enough to catch a typo or an
    /// exponent gone wrong), and against each other.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let m = &self.motor;
        within("motor.inductance_h", m.inductance_h, 1e-6, 10.0, "H")?;
        within("motor.resistance_ohm", m.resistance_ohm, 1e-4, 1e4, "Ω")?;
        within("motor.inertia_kg_m2", m.inertia_kg_m2, 1e-9, 10.0, "kg·m²")?;
        within(
            "motor.torque_constant_nm_per_a",
            m.torque_constant_nm_per_a,
            1e-4,
            100.0,
            "N·m/A",
        )?;
        if !(1..=1000).contains(&m.rotor_teeth) {
            return Err(invalid(
                "motor.rotor_teeth",
                format!("must be 1..=1000 (got {})", m.rotor_teeth),
            ));
        }
        within(
            "motor.viscous_friction_nm_s_per_rad",
            m.viscous_friction_nm_s_per_rad,
            0.0,
            100.0,
            "N·m·s/rad",
        )?;
        within("load.torque_nm", self.load.torque_nm, -1e3, 1e3, "N·m")?;
        within(
            "drive.bus_voltage_v",
            self.drive.bus_voltage_v,
            0.1,
            1e4,
            "V",
        )?;
        // The most torque the motor gives at standstill: the bus across one phase's R.
        let stall_nm = m.torque_constant_nm_per_a * self.drive.bus_voltage_v / m.resistance_ohm;
        if self.load.torque_nm.abs() >= stall_nm {
            return Err(invalid(
                "load.torque_nm",
                format!(
                    "{} N·m can never be held: the motor's most torque at standstill is \
                     K_m·V_bus/R = {stall_nm:.4} N·m",
                    self.load.torque_nm
                ),
            ));
        }
        if self.drive.command_plan_periods as usize > MAX_PLAN {
            return Err(invalid(
                "drive.command_plan_periods",
                format!(
                    "must be 0..={MAX_PLAN} (got {})",
                    self.drive.command_plan_periods
                ),
            ));
        }

        let g = &self.gains;
        within("gains.k1", g.k1, 1e-9, 1e6, "1/s")?;
        within("gains.k2", g.k2, 1e-9, 1e6, "N·m·s/rad")?;
        within("gains.k3_per_s", g.k3_per_s, 1e-3, 1e9, "1/s")?;
        within("gains.v_max_v", g.v_max_v, 1e-3, 1e4, "V")?;
        within("gains.rho_per_s", g.rho_per_s, 1e-3, 1e9, "1/s")?;
        if g.v_max_v > self.drive.bus_voltage_v {
            return Err(invalid(
                "gains.v_max_v",
                format!(
                    "({} V) exceeds drive.bus_voltage_v ({} V): the drive cannot apply it",
                    num(g.v_max_v),
                    num(self.drive.bus_voltage_v)
                ),
            ));
        }

        let r = &self.rates;
        within("rates.current_loop_hz", r.current_loop_hz, 10.0, 1e6, "Hz")?;
        within("rates.position_loop_hz", r.position_loop_hz, 1.0, 1e6, "Hz")?;
        if r.position_loop_hz > r.current_loop_hz {
            return Err(invalid(
                "rates.position_loop_hz",
                format!(
                    "({} Hz) must not exceed rates.current_loop_hz ({} Hz)",
                    num(r.position_loop_hz),
                    num(r.current_loop_hz)
                ),
            ));
        }
        let ratio = r.current_loop_hz / r.position_loop_hz;
        if (ratio - ratio.round()).abs() > 1e-9 * ratio {
            return Err(invalid(
                "rates.position_loop_hz",
                format!(
                    "must divide rates.current_loop_hz exactly (ratio {} / {} = {ratio} is not an integer)",
                    num(r.current_loop_hz),
                    num(r.position_loop_hz)
                ),
            ));
        }
        if r.compute_delay_periods > MAX_COMPUTE_DELAY_PERIODS {
            return Err(invalid(
                "rates.compute_delay_periods",
                format!(
                    "must be 0..={MAX_COMPUTE_DELAY_PERIODS} (got {})",
                    r.compute_delay_periods
                ),
            ));
        }
        if !(1..=1000).contains(&r.plant_substeps) {
            return Err(invalid(
                "rates.plant_substeps",
                format!("must be 1..=1000 (got {})", r.plant_substeps),
            ));
        }

        let t = &self.trajectory;
        // The sampled commutation needs the electrical angle to move less than an eighth of
        // a turn per current-loop period.
        let max_speed = std::f64::consts::FRAC_PI_4 * r.current_loop_hz / m.n_r();
        within(
            "trajectory.cruise_velocity_rad_s",
            t.cruise_velocity_rad_s,
            -max_speed,
            max_speed,
            "rad/s (the electrical angle may turn at most π/4 per current-loop period)",
        )?;
        for (field, v) in [
            ("trajectory.accel_s", t.accel_s),
            ("trajectory.cruise_s", t.cruise_s),
            ("trajectory.decel_s", t.decel_s),
            ("trajectory.hold_s", t.hold_s),
        ] {
            within(field, v, 0.0, 1e6, "s")?;
        }
        if self.profile_s() <= 0.0 {
            return Err(invalid(
                "trajectory",
                "phases must add up to a positive duration".into(),
            ));
        }
        let too_long = |field: &'static str, seconds: f64| {
            invalid(
                field,
                format!(
                    "({} s) gives more than {} samples at rates.current_loop_hz = {} Hz",
                    num(seconds),
                    num(MAX_SAMPLES as f64),
                    num(r.current_loop_hz)
                ),
            )
        };
        match self.run.duration_s {
            _ if self.run.until_stopped => {}
            Some(d) => {
                within("run.duration_s", d, 1e-6, 1e9, "s")?;
                if self.sample_count() > MAX_SAMPLES {
                    return Err(too_long("run.duration_s", d));
                }
            }
            None if self.sample_count() > MAX_SAMPLES => {
                return Err(too_long("trajectory", self.profile_s()))
            }
            None => {}
        }

        // Windows are within one pass of the trajectory (they apply to every pass of a longer
        // run); a shorter run reports what it reached, `n/a` for the rest.
        let w = &self.metrics;
        let pass = self.profile_s();
        within(
            "metrics.cruise_start_s",
            w.cruise_start_s,
            0.0,
            pass,
            "s (one pass of the trajectory)",
        )?;
        within(
            "metrics.cruise_end_s",
            w.cruise_end_s,
            0.0,
            pass,
            "s (one pass of the trajectory)",
        )?;
        if w.cruise_end_s <= w.cruise_start_s {
            return Err(invalid(
                "metrics.cruise_end_s",
                format!(
                    "({}) must be after metrics.cruise_start_s ({})",
                    num(w.cruise_end_s),
                    num(w.cruise_start_s)
                ),
            ));
        }
        within(
            "metrics.final_window_s",
            w.final_window_s,
            1e-9,
            pass,
            "s (one pass of the trajectory)",
        )?;
        self.plant.validate()?;
        self.axis.validate()?;
        for (i, step) in self.program.iter().enumerate() {
            step.validate(i)?;
        }
        let c = &self.control;
        // Past π f (half the sample rate) the estimate or the loop would be noise.
        if let Some(l) = c.observer_bandwidth_rad_s {
            within(
                "control.observer_bandwidth_rad_s",
                l,
                1.0,
                std::f64::consts::PI * r.position_loop_hz,
                "rad/s (at most π × rates.position_loop_hz)",
            )?;
        }
        if let Some(w) = c.pi_bandwidth_rad_s {
            within(
                "control.pi_bandwidth_rad_s",
                w,
                1.0,
                std::f64::consts::FRAC_PI_2 * r.current_loop_hz,
                "rad/s (at most π/2 × rates.current_loop_hz)",
            )?;
        }
        Ok(())
    }

    /// λ of the load-torque observer, rad/s.
    pub fn observer_bandwidth_rad_s(&self) -> f64 {
        self.control
            .observer_bandwidth_rad_s
            .unwrap_or(2.0 * self.rates.position_loop_hz)
    }

    /// ω_c of the PI baseline's current loops, rad/s.
    pub fn pi_bandwidth_rad_s(&self) -> f64 {
        self.control
            .pi_bandwidth_rad_s
            .unwrap_or(std::f64::consts::TAU * self.rates.current_loop_hz / 20.0)
    }

    /// The motor the plant simulates: `[motor]` with `[plant.motor]`'s fields.
    pub fn plant_motor(&self) -> MotorParams {
        self.plant.motor.apply(&self.motor)
    }

    /// The plant's load: `[plant.load]` (its constant defaulting to `[load]`) and detent.
    pub fn disturbance(&self) -> Disturbance {
        let l = &self.plant.load;
        let d = &self.plant.detent;
        let mut load = Disturbance::constant(l.torque_nm.unwrap_or(self.load.torque_nm));
        // A valid scenario's steps and ramps fit (`PlantParams::validate`); a scenario built
        // in code with more keeps the first that do.
        for &s in &l.steps {
            let _ = load.add_step(s);
        }
        for &r in &l.ramps {
            let _ = load.add_ramp(r);
        }
        load.coulomb_nm = l.coulomb_nm;
        load.coulomb_smoothing_rad_s = l.coulomb_smoothing_rad_s;
        load.detent_nm = d.amplitude_nm;
        load.detent_wavenumber = f64::from(d.harmonic) * self.motor.n_r();
        load.detent_phase_rad = d.phase_rad;
        load
    }

    /// The final window within this run: its last `final_window_s`, or the whole of a
    /// shorter run.
    pub fn final_window_start_s(&self) -> f64 {
        (self.duration_s() - self.metrics.final_window_s).max(0.0)
    }

    /// A fingerprint of everything in the scenario (FNV-1a of its canonical TOML): two
    /// processes with the same fingerprint run the same scenario.
    pub fn fingerprint(&self) -> String {
        let text = self.to_toml_string().unwrap_or_default();
        format!("{:016x}", crate::fnv1a(text.as_bytes()))
    }

    /// One pass of the trajectory: its phases added up, s.
    pub fn profile_s(&self) -> f64 {
        let t = &self.trajectory;
        t.accel_s + t.cruise_s + t.decel_s + t.hold_s
    }

    /// The axis runs the scenario's profile from the first tick (the paper's experiment):
    /// no `[[program]]`, and not a stack served until stopped (whose axis waits for
    /// commands).
    pub fn runs_profile(&self) -> bool {
        self.program.is_empty() && !self.run.until_stopped && !self.held
    }

    /// Length of the run, s: `run.duration_s`, or one pass of the trajectory, or with a
    /// program its last step and [`PROGRAM_TAIL_S`] after it.
    pub fn duration_s(&self) -> f64 {
        self.run
            .duration_s
            .unwrap_or_else(|| match self.program_end_s() {
                Some(end) => end + PROGRAM_TAIL_S,
                None => self.profile_s(),
            })
    }

    /// The time of a program's last step, if there is a program.
    pub fn program_end_s(&self) -> Option<f64> {
        self.program.iter().map(|p| p.at_s).reduce(f64::max)
    }

    /// Current-loop sample period T_s, s.
    pub fn sample_period_s(&self) -> f64 {
        1.0 / self.rates.current_loop_hz
    }

    /// Current-loop sample period in whole nanoseconds, for deadline arithmetic.
    pub fn sample_period_ns(&self) -> u64 {
        (1e9 / self.rates.current_loop_hz).round() as u64
    }

    /// Current-loop samples per position-loop tick.
    pub fn rate_ratio(&self) -> u64 {
        (self.rates.current_loop_hz / self.rates.position_loop_hz).round() as u64
    }

    /// Samples in the run, k = 0 ..= duration / T_s.
    pub fn sample_count(&self) -> u64 {
        if self.run.until_stopped {
            return u64::MAX;
        }
        (self.duration_s() * self.rates.current_loop_hz).round() as u64 + 1
    }

    /// Sample instant t_k. Computed as k·T_s from the integer k, never accumulated, so every
    /// process agrees on it bit for bit.
    pub fn sample_time(&self, k: u64) -> f64 {
        k as f64 / self.rates.current_loop_hz
    }

    /// Eq. (7): the least steady error of microstepping at the cruise velocity, rad.
    pub fn eq7_bound_rad(&self) -> f64 {
        let m = &self.motor;
        (m.resistance_ohm * m.viscous_friction_nm_s_per_rad * self.trajectory.cruise_velocity_rad_s
            / (m.torque_constant_nm_per_a * self.gains.v_max_v * m.n_r()))
        .abs()
    }

    /// The load's share of the microstepping steady error, R τ_L / (K_m V_max N_r), rad.
    pub fn load_offset_rad(&self) -> f64 {
        let m = &self.motor;
        m.resistance_ohm * self.load.torque_nm
            / (m.torque_constant_nm_per_a * self.gains.v_max_v * m.n_r())
    }
}

/// Which control method the current loop runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(
    feature = "clap",
    derive(clap::ValueEnum),
    value(rename_all = "snake_case")
)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Torque modulation (12) + commutation (17) + current tracking (22).
    Proposed,
    /// Lyapunov-based microstepping, eq. (39).
    Lyapunov,
    /// Open-loop microstepping voltages, eq. (2).
    #[cfg_attr(feature = "clap", value(alias = "open-loop"))]
    OpenLoop,
    /// The industrial baseline: microstepping currents of constant amplitude (V_max/R)
    /// tracked by a PI loop per phase, no back-EMF feed-forward.
    Pi,
}

impl Method {
    pub const ALL: [Method; 4] = [
        Method::Proposed,
        Method::Lyapunov,
        Method::OpenLoop,
        Method::Pi,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            Method::Proposed => "proposed",
            Method::Lyapunov => "lyapunov",
            Method::OpenLoop => "open_loop",
            Method::Pi => "pi",
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "proposed" => Ok(Method::Proposed),
            "lyapunov" => Ok(Method::Lyapunov),
            "open_loop" | "open-loop" => Ok(Method::OpenLoop),
            "pi" => Ok(Method::Pi),
            other => Err(format!(
                "unknown method `{other}` (expected proposed, lyapunov, open_loop or pi)"
            )),
        }
    }
}

/// Timing mode of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Virtual time: the plant waits for each command; bit-identical results.
    Lockstep,
    /// Wall clock: the plant publishes on absolute deadlines and never waits.
    Realtime,
    /// Realtime with the plant replaced by a bridge to a drive; the drive's clock paces.
    Hardware,
}

impl Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Lockstep => "lockstep",
            Mode::Realtime => "realtime",
            Mode::Hardware => "hardware",
        }
    }
}

impl FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "lockstep" => Ok(Mode::Lockstep),
            "realtime" => Ok(Mode::Realtime),
            "hardware" => Ok(Mode::Hardware),
            other => Err(format!(
                "unknown mode `{other}` (expected lockstep, realtime or hardware)"
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scenario's default motor is the one the firmware simulates (`Motor::TABLE_I`).
    #[test]
    fn the_default_motor_is_table_i() {
        let m = stepdrive_motor::Motor::from(&MotorParams::default());
        let t = stepdrive_motor::Motor::TABLE_I;
        assert_eq!(
            [m.l, m.r, m.j, m.k_m, m.n_r, m.b].map(f64::to_bits),
            [t.l, t.r, t.j, t.k_m, t.n_r, t.b].map(f64::to_bits)
        );
    }

    #[test]
    fn default_scenario_is_valid_and_round_trips_through_toml() {
        let s = Scenario::default();
        s.validate().expect("defaults valid");
        let text = s.to_toml_string().expect("serialise");
        assert_eq!(Scenario::from_toml_str(&text).expect("parse"), s);
        let full = s.to_full_toml_string().expect("serialise");
        assert!(
            full.contains("[axis]") && full.contains("[plant.brake]"),
            "{full}"
        );
        assert_eq!(Scenario::from_toml_str(&full).expect("parse"), s);
        assert_eq!(s.sample_count(), 50_001);
        assert_eq!(s.rate_ratio(), 10);
    }

    #[test]
    fn eq7_numbers_match_the_notes() {
        let s = Scenario::default();
        assert!((s.eq7_bound_rad() - 5.98e-3).abs() < 0.01e-3);
        assert!((s.load_offset_rad() - 0.91e-3).abs() < 0.01e-3);
    }

    fn err_of(text: &str) -> String {
        Scenario::from_toml_str(text)
            .expect_err("must be rejected")
            .to_string()
    }

    #[test]
    fn bad_fields_are_named() {
        assert!(err_of("[motor]\nresistance_ohm = -1.0").contains("motor.resistance_ohm"));
        assert!(err_of("[motor]\ninductance_h = 0.0").contains("motor.inductance_h"));
        assert!(err_of("[motor]\ninertia_kg_m2 = nan").contains("motor.inertia_kg_m2"));
        assert!(err_of("[motor]\ntorque_constant_nm_per_a = inf")
            .contains("motor.torque_constant_nm_per_a"));
        assert!(err_of("[rates]\nposition_loop_hz = 3000.0").contains("rates.position_loop_hz"));
        assert!(err_of("[rates]\ncompute_delay_periods = 9").contains("compute_delay_periods"));
        assert!(err_of("[load]\ntorque_nm = nan").contains("load.torque_nm"));
        // Beyond the stall torque K_m·V_bus/R (0.5 · 24 / 14.8 = 0.81 N·m here).
        let too_much = err_of("[load]\ntorque_nm = 1000.0");
        assert!(too_much.contains("can never be held"), "{too_much}");
        assert!(err_of("[drive]\ncommand_plan_periods = 1025").contains("command_plan_periods"));
        assert!(err_of("[metrics]\ncruise_end_s = 9.0").contains("metrics.cruise_end_s"));
        // A typo is an error naming the unknown key, not a silent default.
        assert!(err_of("[motor]\nresistanse_ohm = 1.0").contains("resistanse_ohm"));
        // A wrong type is reported with its key.
        assert!(err_of("[gains]\nk1 = \"fast\"").contains("k1"));
    }

    #[test]
    fn method_names_parse() {
        for m in Method::ALL {
            assert_eq!(m.as_str().parse::<Method>(), Ok(m));
        }
        assert!("pid".parse::<Method>().is_err());
    }

    /// Scenario files made of known keys with arbitrary values, extremes included: loading
    /// never panics, and what is accepted can be run (finite, bounded in samples).
    #[test]
    fn arbitrary_scenario_files_never_panic_and_accepted_ones_can_run() {
        use proptest::prelude::*;
        const KEYS: [(&str, &str); 12] = [
            ("motor", "inductance_h"),
            ("motor", "resistance_ohm"),
            ("motor", "rotor_teeth"),
            ("load", "torque_nm"),
            ("drive", "bus_voltage_v"),
            ("gains", "v_max_v"),
            ("rates", "current_loop_hz"),
            ("rates", "position_loop_hz"),
            ("trajectory", "cruise_velocity_rad_s"),
            ("trajectory", "hold_s"),
            ("metrics", "cruise_end_s"),
            ("run", "duration_s"),
        ];
        let value = prop_oneof![
            any::<f64>().prop_map(|v| format!("{v:?}")),
            any::<i64>().prop_map(|v| v.to_string()),
            Just("nan".to_string()),
            Just("-inf".to_string()),
            Just("1e308".to_string()),
            Just("\"x\"".to_string()),
            Just("true".to_string()),
        ];
        let line = (0..KEYS.len(), value);
        proptest!(|(lines in proptest::collection::vec(line, 0..8))| {
            // Each table once, each key once: valid TOML, so the values are what is tested.
            let mut tables: std::collections::BTreeMap<&str, std::collections::BTreeMap<&str, String>> =
                Default::default();
            for (key, value) in lines {
                let (table, field) = KEYS[key];
                tables.entry(table).or_default().insert(field, value);
            }
            let mut text = String::new();
            for (table, fields) in tables {
                text.push_str(&format!("[{table}]\n"));
                for (field, value) in fields {
                    text.push_str(&format!("{field} = {value}\n"));
                }
            }
            if let Ok(s) = Scenario::from_toml_str(&text) {
                prop_assert!(s.sample_count() <= MAX_SAMPLES);
                prop_assert!(s.duration_s().is_finite() && s.duration_s() > 0.0);
                prop_assert!(s.sample_period_ns() > 0);
                prop_assert!(s.eq7_bound_rad().is_finite());
            }
        });
    }
}

#[cfg(test)]
mod axes_tests {
    use super::*;

    const THREE: &str = r#"
name = "three"
[motor]
inertia_kg_m2 = 2.0e-5

[[program]]
at_s = 0.0
command = "enable"
[[program]]
at_s = 0.1
axis = 2
command = "enable"
[[program]]
at_s = 0.5
axis = 2
command = "move"
to = 3.0

[[axis]]
name = "x"

[[axis]]
name = "y"
[axis.motor]
resistance_ohm = 1.2
[axis.limits]
v_max_rad_s = 20.0

[[axis]]
[axis.load]
torque_nm = 0.0
"#;

    /// Each axis is the file's tables with its own laid over them field by field, and runs
    /// its own steps, renumbered to its own axis 0, for as long as the whole program.
    #[test]
    fn axis_tables_lay_their_fields_over_the_files() {
        let s = Scenario::from_toml_str(THREE).unwrap();
        assert_eq!(s.axis_count(), 3);
        let (x, y, z) = (
            s.for_axis(0).unwrap(),
            s.for_axis(1).unwrap(),
            s.for_axis(2).unwrap(),
        );
        assert!(s.for_axis(3).is_none());
        assert_eq!(s.axis_name(1), "y");
        assert_eq!(s.axis_name(2), "axis2");
        // The file's motor under every axis, y's resistance over it.
        for a in [x, y, z] {
            assert_eq!(a.motor.inertia_kg_m2, 2.0e-5);
        }
        assert_eq!(y.motor.resistance_ohm, 1.2);
        assert_eq!(
            x.motor.resistance_ohm,
            MotorParams::default().resistance_ohm
        );
        assert_eq!(y.axis.v_max_rad_s, 20.0);
        assert_eq!(y.axis.a_max_rad_s2, AxisParams::default().a_max_rad_s2);
        assert_eq!(x.axis, AxisParams::default());
        assert_eq!(z.load.torque_nm, 0.0);
        assert_eq!(x.load.torque_nm, LoadParams::default().torque_nm);
        // Steps: x one, y none (it waits disabled), z two, all as axis 0 of their own.
        assert_eq!(x.program.len(), 1);
        assert!(y.program.is_empty() && y.held && !y.runs_profile());
        assert_eq!(z.program.len(), 2);
        assert!(z.program.iter().all(|p| p.axis == 0));
        assert_eq!(z.program[1].to, Some(3.0));
        for a in [x, y, z] {
            assert_eq!(a.duration_s(), 0.5 + PROGRAM_TAIL_S);
            assert_eq!(a.sample_count(), s.sample_count());
        }
    }

    /// What the stack announces reads back as the same scenario.
    #[test]
    fn a_multi_axis_scenario_reads_back_from_its_own_text() {
        let s = Scenario::from_toml_str(THREE).unwrap();
        let text = s.to_toml_string().unwrap();
        assert_eq!(Scenario::from_toml_str(&text).unwrap(), s);
        assert!(s.to_full_toml_string().is_ok());
    }

    /// A file without `[[axis]]` is its own one axis, unchanged.
    #[test]
    fn a_file_without_axis_tables_is_one_axis() {
        let s = Scenario::from_toml_str("[axis]\nv_max_rad_s = 20.0\n").unwrap();
        assert_eq!(s.axis_count(), 1);
        assert_eq!(s.for_axis(0), Some(&s));
        assert!(s.for_axis(1).is_none());
        assert!(s.axes.is_empty() && !s.held);
    }

    /// Bad axis tables are refused naming the axis and what is wrong.
    #[test]
    fn bad_axis_tables_are_refused_with_the_axis_named() {
        let cases: [(String, &str); 6] = [
            ("[[axis]]\nspeed = 3\n".into(), "unknown key `speed`"),
            (
                "[[axis]]\n[[axis]]\n[axis.motor]\nresistance_ohm = -1.0\n".into(),
                "(axis 1, axis1)",
            ),
            (
                "[[axis]]\nname = \"a\"\n[[axis]]\nname = \"a\"\n".into(),
                "axis 0's name too",
            ),
            ("[[axis]]\n".repeat(9), "a stack runs 1..=8"),
            (
                "[[program]]\nat_s = 0.0\naxis = 1\ncommand = \"enable\"\n[[axis]]\n".into(),
                "names axis 1",
            ),
            (
                "[[program]]\nat_s = 0.0\naxis = 1\ncommand = \"enable\"\n".into(),
                "axis 0 only",
            ),
        ];
        for (text, expected) in cases {
            let e = Scenario::from_toml_str(&text).unwrap_err().to_string();
            assert!(
                e.contains(expected),
                "{text}\n→ {e}\n(expected `{expected}`)"
            );
        }
    }
}
