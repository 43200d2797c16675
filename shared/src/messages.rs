//! Messages exchanged over iceoryx2. All are fixed-size `#[repr(C)]` plain data in SI units
//! (rad, rad/s, rad/s², A, V, N·m, s). iceoryx2 checks compatibility by type name, size and
//! alignment only, so every type carries a schema version in its name: bump it whenever a
//! field changes, even one that fits in padding.

#[cfg(feature = "ipc")]
use iceoryx2::prelude::ZeroCopySend;

/// Sequence value meaning "no such sample/command".
pub const NONE_SEQ: u64 = u64::MAX;

/// Bits of [`DriveState::flags`].
pub mod state_flags {
    /// Last sample of the run: loops that see it finish and exit.
    pub const LAST: u32 = 1 << 0;
    /// The applied voltage was clamped to ±V_bus on at least one phase.
    pub const VOLTAGE_LIMITED: u32 = 1 << 1;
    /// Realtime: the command for the last period was missing (a deadline miss). The voltage
    /// applied was the freshest plan's entry for that period ([`COMMAND_PLANNED`]) or,
    /// without one, the previous voltage held.
    pub const COMMAND_HELD: u32 = 1 << 2;
    /// With [`COMMAND_HELD`]: the voltage came from a [`DrivePlan`].
    pub const COMMAND_PLANNED: u32 = 1 << 3;
    /// The command applied came from a current loop that had stopped the motor on its own:
    /// the position loop's setpoints had grown stale ([`super::command_flags::SETPOINT_STALE`]).
    pub const SETPOINT_STALE: u32 = 1 << 4;
}

/// Bits of [`DriveCommand::flags`].
pub mod command_flags {
    /// The newest setpoint was older than `[axis] setpoint_age_ticks` position-loop periods:
    /// the current loop decelerates the motor to a standstill and holds it on its own.
    pub const SETPOINT_STALE: u32 = 1 << 0;
    /// The motor's holding brake may be released (without it, applied): the axis has its
    /// outputs on and its brake's release time has passed.
    pub const BRAKE_RELEASED: u32 = 1 << 1;
}

/// Bits of [`TorqueSetpoint::flags`].
pub mod setpoint_flags {
    /// The axis has torque: the current loop follows; without it it applies zero volts.
    pub const OUTPUTS_ON: u32 = 1 << 0;
    /// The acceleration is continuous (a jerk-limited trajectory): the current loop may
    /// predict the rotor's speed ahead with it.
    pub const ACCELERATION_AHEAD: u32 = 1 << 1;
    /// The holding brake may be released (as [`super::command_flags::BRAKE_RELEASED`]).
    pub const BRAKE_RELEASED: u32 = 1 << 2;
}

/// Bits of [`DriveState::fault`]. A fault is latched by the process that drives the motor.
pub mod fault_bits {
    /// A command arrived with a non-finite voltage; outputs are off.
    pub const BAD_COMMAND: u32 = 1 << 0;
    /// No command arrived for the watchdog's number of periods (realtime/hardware modes);
    /// outputs are off until reset.
    pub const COMMAND_TIMEOUT: u32 = 1 << 1;
    /// Hardware: the drive reported a latched fault (its bits are in the upper 16 bits).
    pub const DRIVE_FAULT: u32 = 1 << 2;
    /// Hardware: no valid sample from the drive for the bridge's watchdog periods; the
    /// bridge forwards no commands until the drive speaks again.
    pub const DRIVE_SILENT: u32 = 1 << 3;
}

/// Plant (or drive bridge) → everyone: the measured state at sample `seq`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.DriveState.v2")
)]
#[repr(C)]
pub struct DriveState {
    /// Sample index k (0, 1, 2, ... from the start of the run).
    pub seq: u64,
    /// Sample instant t_k in seconds since the start of the run (virtual time in lockstep).
    pub sample_time_s: f64,
    /// CLOCK_MONOTONIC at publication, nanoseconds.
    pub publish_time_ns: u64,
    /// Realtime: the absolute CLOCK_MONOTONIC deadline of this sample, ns (0 in lockstep).
    /// Every loop derives its deadline grid from it.
    pub deadline_ns: u64,
    /// Sequence number of the command whose voltage was applied over (t_{k-1}, t_k],
    /// or [`NONE_SEQ`] if none was (outputs off).
    pub applied_command_seq: u64,
    pub theta_rad: f64,
    pub omega_rad_s: f64,
    pub i_a_a: f64,
    pub i_b_a: f64,
    /// Phase voltages actually applied over (t_{k-1}, t_k], after the bus limit.
    pub v_a_v: f64,
    pub v_b_v: f64,
    pub bus_voltage_v: f64,
    /// [`state_flags`] bits.
    pub flags: u32,
    /// [`fault_bits`] bits; zero when healthy.
    pub fault: u32,
}

/// Current loop → plant: phase voltages computed from sample `answers_seq`, for period
/// answers_seq + d.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.DriveCommand.v2")
)]
#[repr(C)]
pub struct DriveCommand {
    /// Command sequence number; equals `answers_seq` in lockstep.
    pub seq: u64,
    /// The [`DriveState::seq`] this command was computed from.
    pub answers_seq: u64,
    /// Sample instant of that state, seconds.
    pub sample_time_s: f64,
    /// CLOCK_MONOTONIC when that state was published (copied), nanoseconds.
    pub state_publish_time_ns: u64,
    /// CLOCK_MONOTONIC at publication of this command, nanoseconds.
    pub publish_time_ns: u64,
    pub v_a_v: f64,
    pub v_b_v: f64,
    /// Reference currents the loop is steering to (for monitoring): those of sample
    /// `answers_seq` + compute delay + 1, the first the command's voltage can reach.
    pub i_a_ref_a: f64,
    pub i_b_ref_a: f64,
    /// [`command_flags`] bits.
    pub flags: u32,
    pub _reserved: u32,
}

/// Longest [`DrivePlan`]: 1024 periods, 51.2 ms at 20 kHz. The default plan (1000 periods)
/// is as long as the default watchdog, so a plan covers every period the watchdog waits
/// through and never outlives it.
pub const MAX_PLAN: usize = 1024;

/// Current loop → plant (realtime), after every few commands (`PLAN_EVERY` in the current
/// loop's node): the voltages the loop expects to send for the periods after that
/// command's, predicted with the same model and law (constant speed, the setpoint segment
/// unchanged). A plant whose next command is late
/// applies the freshest plan's entry for that period instead of freezing the last voltage:
/// at cruise the electrical angle turns ~0.03 rad per period, so a frozen voltage vector
/// loses torque within a millisecond while the plan keeps commutating. A miss is still a
/// miss (counted, and it feeds the watchdog). Published after the command so that planning
/// never delays it.
#[derive(Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.DrivePlan.v2")
)]
#[repr(C)]
pub struct DrivePlan {
    /// The [`DriveCommand::seq`] this plan continues.
    pub command_seq: u64,
    /// The sample that command answers; entry j is for period answers_seq + d + 1 + j.
    pub answers_seq: u64,
    /// CLOCK_MONOTONIC at publication, nanoseconds.
    pub publish_time_ns: u64,
    /// Valid entries, 0..=[`MAX_PLAN`].
    pub len: u32,
    pub _reserved: u32,
    /// (v_a, v_b), V.
    pub v: [[f32; 2]; MAX_PLAN],
}

impl Default for DrivePlan {
    fn default() -> Self {
        Self {
            command_seq: 0,
            answers_seq: 0,
            publish_time_ns: 0,
            len: 0,
            _reserved: 0,
            v: [[0.0; 2]; MAX_PLAN],
        }
    }
}

impl std::fmt::Debug for DrivePlan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let shown = (self.len as usize).min(3);
        f.debug_struct("DrivePlan")
            .field("command_seq", &self.command_seq)
            .field("answers_seq", &self.answers_seq)
            .field("len", &self.len)
            .field("first", &&self.v[..shown])
            .finish()
    }
}

impl DrivePlan {
    /// The planned voltage for `period` under compute delay `delay`, if the plan covers it.
    /// A plan claiming more than [`MAX_PLAN`] entries is malformed and covers nothing.
    pub fn voltage_for(&self, period: u64, delay: u64) -> Option<[f64; 2]> {
        let first = self.answers_seq.checked_add(delay)?.checked_add(1)?;
        let len = self.len as usize;
        let j = usize::try_from(period.checked_sub(first)?)
            .ok()
            .filter(|&j| j < len && len <= MAX_PLAN)?;
        Some(self.v[j].map(f64::from))
    }

    /// The entries in use.
    pub fn entries(&self) -> &[[f32; 2]] {
        &self.v[..(self.len as usize).min(MAX_PLAN)]
    }
}

/// Anyone → the plant (or bridge): clear the latched faults once their cause is gone
/// (`stepdrive reset`). The plant refuses while the cause remains (no commands coming).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.ResetRequest.v1")
)]
#[repr(C)]
pub struct ResetRequest {
    pub seq: u64,
    /// CLOCK_MONOTONIC at publication, nanoseconds.
    pub publish_time_ns: u64,
    /// The requesting process, for the log.
    pub pid: u32,
    pub _reserved: u32,
}

/// Position/torque loop → current loop: torque demand and the trajectory segment that
/// holds until the next tick.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.TorqueSetpoint.v3")
)]
#[repr(C)]
pub struct TorqueSetpoint {
    /// Tick counter of the position loop.
    pub seq: u64,
    /// The [`DriveState::seq`] this setpoint was computed from.
    pub from_state_seq: u64,
    /// Sample instant of that state (the segment's origin), seconds.
    pub sample_time_s: f64,
    /// CLOCK_MONOTONIC at publication, nanoseconds.
    pub publish_time_ns: u64,
    /// Desired position, velocity, acceleration at `sample_time_s`; the current loop
    /// extrapolates θ_d between ticks with them (the baselines need θ_d at 20 kHz).
    pub theta_d_rad: f64,
    pub omega_d_rad_s: f64,
    pub alpha_d_rad_s2: f64,
    /// Torque demand of eq. (12), N·m (unused by the baselines).
    pub torque_nm: f64,
    /// The load torque (12) used for τ_L: `[load]`'s when known, the observer's estimate
    /// of the lumped disturbance, or 0, N·m.
    pub load_estimate_nm: f64,
    /// With [`setpoint_flags::ACCELERATION_AHEAD`]: how fast the torque changes along the
    /// segment (B α_d + J jerk_d, while the rotor tracks), N·m/s: the current loop follows
    /// τ + τ̇ (t − t_0) between ticks instead of holding τ.
    pub torque_rate_nm_s: f64,
    /// The axis it is for.
    pub axis: u32,
    /// [`setpoint_flags`] bits.
    pub flags: u32,
    /// The axis's enable these setpoints belong to: a current loop that stopped the motor
    /// on its own follows setpoints again only from a later one.
    pub epoch: u32,
    pub _reserved: u32,
}

impl TorqueSetpoint {
    /// Desired position at time `t_s`, extrapolated along this segment.
    pub fn theta_d_at(&self, t_s: f64) -> f64 {
        let dt = t_s - self.sample_time_s;
        self.theta_d_rad + self.omega_d_rad_s * dt + 0.5 * self.alpha_d_rad_s2 * dt * dt
    }

    /// θ_d, ω_d, α_d at the sample this setpoint was computed from.
    pub fn reference(&self) -> crate::trajectory::Reference {
        crate::trajectory::Reference {
            theta: self.theta_d_rad,
            omega: self.omega_d_rad_s,
            alpha: self.alpha_d_rad_s2,
        }
    }
}

/// The longest scenario TOML a stack can announce, bytes.
pub const SCENARIO_BYTES: usize = 16 * 1024;

/// The device → anyone attaching (a monitor, a recorder, a scope): the scenario the stack
/// runs, as its TOML, so that a reader takes it from the stack instead of being told it.
#[derive(Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.StackScenario.v1")
)]
#[repr(C)]
pub struct StackScenario {
    /// Bytes of `toml` in use.
    pub len: u32,
    pub _reserved: u32,
    pub toml: [u8; SCENARIO_BYTES],
}

impl std::fmt::Debug for StackScenario {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StackScenario")
            .field("len", &self.len)
            .finish()
    }
}

/// A scenario whose TOML does not fit a [`StackScenario`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("the scenario's TOML is {0} bytes; a stack announces at most {SCENARIO_BYTES}")]
pub struct ScenarioTooLong(pub usize);

impl StackScenario {
    pub fn new(toml: &str) -> Result<Self, ScenarioTooLong> {
        let bytes = toml.as_bytes();
        if bytes.len() > SCENARIO_BYTES {
            return Err(ScenarioTooLong(bytes.len()));
        }
        let mut out = Self {
            len: bytes.len() as u32,
            _reserved: 0,
            toml: [0; SCENARIO_BYTES],
        };
        out.toml[..bytes.len()].copy_from_slice(bytes);
        Ok(out)
    }

    /// The TOML, if it is text.
    pub fn text(&self) -> Option<&str> {
        let len = (self.len as usize).min(SCENARIO_BYTES);
        std::str::from_utf8(&self.toml[..len]).ok()
    }
}
