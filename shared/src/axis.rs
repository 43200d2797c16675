//! The axis: what programs command, as a CiA 402 drive is commanded. Its settings in the
//! scenario (`[axis]`, validated like every field), a program of timed commands
//! (`[[program]]`, for deterministic runs), the power state machine's states with their
//! CiA 402 names and status words, and the messages of the command service, the status
//! topic and the setpoint stream. Every message carries an axis index (one axis today).

use crate::scenario::{invalid, num, within, ScenarioError};
#[cfg(feature = "ipc")]
use iceoryx2::prelude::ZeroCopySend;
use serde::{Deserialize, Serialize};

/// `[axis]`: the axis's limits and defaults. Absent fields take these defaults (chosen for
/// the paper's motor: its back-EMF reaches the 24 V bus at 48 rad/s).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AxisParams {
    /// Soft position limits, rad: a target outside them is refused, a jog or a stream
    /// stops at them.
    pub position_min_rad: f64,
    pub position_max_rad: f64,
    /// The most any source may ask for: speed, acceleration, jerk.
    pub v_max_rad_s: f64,
    pub a_max_rad_s2: f64,
    pub j_max_rad_s3: f64,
    /// A move's limits when it gives none.
    pub move_v_rad_s: f64,
    pub move_a_rad_s2: f64,
    pub move_j_rad_s3: f64,
    /// The torque (12) may ask for, N·m (beyond it the torque is limited and a warning
    /// set).
    pub torque_max_nm: f64,
    /// Quick stop: its own deceleration to standstill (jerk: `j_max_rad_s3`).
    pub quick_stop_decel_rad_s2: f64,
    /// Following error window and time (CiA 402 0x6065/0x6066): |θ_d − θ| beyond the window
    /// for longer than the time faults the axis, outputs off. The default window is a little
    /// under one electrical period (2π/N_r = 0.126 rad for N_r = 50), where the rotor slips
    /// a pole.
    pub following_error_window_rad: f64,
    pub following_error_time_s: f64,
    /// Target reached: the trajectory at its target and |θ_target − θ| within this.
    pub target_window_rad: f64,
    /// A cyclic stream's lead (how far behind the newest point the axis plays it), s, and
    /// its watchdog: a stream silent this long is quick-stopped. The lead's default, 50 ms,
    /// is what a client at SCHED_FIFO 10 beside the realtime loops on two cores needs: it
    /// was held off up to 46 ms (docs/axis.md), and a 10 ms lead ran dry in 3 of 12 runs.
    pub stream_lead_s: f64,
    pub stream_timeout_s: f64,
    /// The current loop brings the motor to a stop on its own when the newest setpoint is
    /// older than this many position-loop periods (a silent position loop).
    pub setpoint_age_ticks: u32,
    /// The holding brake's release time, s (CiA 402's brake release delay): after an enable
    /// the axis holds its setpoint where the rotor stood this long, the current holding the
    /// rotor before the brake lets go, and then follows its commands. 0: released at once.
    pub brake_release_s: f64,
    /// A jog runs while the client that started it renews it: a jog that hears no command
    /// from its client for this long is quick-stopped (warning JOG_LOST), s. Any command
    /// renews it, a status request the cheapest. A client that dies, hangs or loses its
    /// link mid-jog so leaves the motor stopped (moteus's watchdog timeout plays this role).
    /// A scenario's `[[program]]` is the stack's own script and needs no renewal.
    pub jog_timeout_s: f64,
    /// The longest a move, a jog's change of speed or a stop may take at the limits it
    /// asks, s: a command whose planned trajectory is longer is refused (limits so low that
    /// the axis would not arrive in any useful time are a mistake, not a move).
    pub move_time_max_s: f64,
}

/// The least limit a command may ask, as a fraction of the axis's maximum (`v_max_rad_s`,
/// `a_max_rad_s2`, `j_max_rad_s3`; a jog's speed too): below it the trajectory generator
/// works with numbers it cannot resolve.
pub const LIMIT_FLOOR: f64 = 1e-6;

impl Default for AxisParams {
    fn default() -> Self {
        Self {
            position_min_rad: -1e4,
            position_max_rad: 1e4,
            v_max_rad_s: 30.0,
            a_max_rad_s2: 500.0,
            j_max_rad_s3: 50_000.0,
            move_v_rad_s: 13.13,
            move_a_rad_s2: 100.0,
            move_j_rad_s3: 5_000.0,
            torque_max_nm: 0.8,
            quick_stop_decel_rad_s2: 200.0,
            following_error_window_rad: 0.1,
            following_error_time_s: 0.02,
            target_window_rad: 1e-4,
            stream_lead_s: 0.05,
            stream_timeout_s: 0.05,
            setpoint_age_ticks: 20,
            brake_release_s: 0.02,
            jog_timeout_s: 0.5,
            move_time_max_s: 3600.0,
        }
    }
}

impl AxisParams {
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    pub fn validate(&self) -> Result<(), ScenarioError> {
        within(
            "axis.position_min_rad",
            self.position_min_rad,
            -1e9,
            1e9,
            "rad",
        )?;
        within(
            "axis.position_max_rad",
            self.position_max_rad,
            -1e9,
            1e9,
            "rad",
        )?;
        if self.position_min_rad >= self.position_max_rad {
            return Err(invalid(
                "axis.position_max_rad",
                format!(
                    "({} rad) must be above axis.position_min_rad ({} rad)",
                    num(self.position_max_rad),
                    num(self.position_min_rad)
                ),
            ));
        }
        within("axis.v_max_rad_s", self.v_max_rad_s, 1e-6, 1e5, "rad/s")?;
        within("axis.a_max_rad_s2", self.a_max_rad_s2, 1e-6, 1e8, "rad/s²")?;
        within("axis.j_max_rad_s3", self.j_max_rad_s3, 1e-6, 1e12, "rad/s³")?;
        let at_most = |field: &'static str, v: f64, max: f64, max_field: &str, unit: &str| {
            within(field, v, 1e-6, f64::MAX, unit)?;
            if v < max * LIMIT_FLOOR {
                return Err(invalid(
                    field,
                    format!(
                        "({} {unit}) is below a millionth of {max_field} ({} {unit}): the \
                         trajectory generator cannot resolve it",
                        num(v),
                        num(max)
                    ),
                ));
            }
            if v > max {
                return Err(invalid(
                    field,
                    format!(
                        "({} {unit}) exceeds {max_field} ({} {unit})",
                        num(v),
                        num(max)
                    ),
                ));
            }
            Ok(())
        };
        at_most(
            "axis.move_v_rad_s",
            self.move_v_rad_s,
            self.v_max_rad_s,
            "axis.v_max_rad_s",
            "rad/s",
        )?;
        at_most(
            "axis.move_a_rad_s2",
            self.move_a_rad_s2,
            self.a_max_rad_s2,
            "axis.a_max_rad_s2",
            "rad/s²",
        )?;
        at_most(
            "axis.move_j_rad_s3",
            self.move_j_rad_s3,
            self.j_max_rad_s3,
            "axis.j_max_rad_s3",
            "rad/s³",
        )?;
        at_most(
            "axis.quick_stop_decel_rad_s2",
            self.quick_stop_decel_rad_s2,
            self.a_max_rad_s2,
            "axis.a_max_rad_s2",
            "rad/s²",
        )?;
        within("axis.torque_max_nm", self.torque_max_nm, 1e-6, 1e4, "N·m")?;
        within(
            "axis.following_error_window_rad",
            self.following_error_window_rad,
            1e-9,
            1e3,
            "rad",
        )?;
        within(
            "axis.following_error_time_s",
            self.following_error_time_s,
            0.0,
            60.0,
            "s",
        )?;
        within(
            "axis.target_window_rad",
            self.target_window_rad,
            1e-12,
            1e3,
            "rad",
        )?;
        within("axis.stream_lead_s", self.stream_lead_s, 0.0, 10.0, "s")?;
        within("axis.brake_release_s", self.brake_release_s, 0.0, 1.0, "s")?;
        within(
            "axis.stream_timeout_s",
            self.stream_timeout_s,
            1e-3,
            60.0,
            "s",
        )?;
        within("axis.jog_timeout_s", self.jog_timeout_s, 0.01, 60.0, "s")?;
        within("axis.move_time_max_s", self.move_time_max_s, 1.0, 1e6, "s")?;
        if !(2..=100_000).contains(&self.setpoint_age_ticks) {
            return Err(invalid(
                "axis.setpoint_age_ticks",
                format!("must be 2..=100000 (got {})", self.setpoint_age_ticks),
            ));
        }
        Ok(())
    }
}

/// What a program step does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ProgramCommand {
    Enable,
    Disable,
    QuickStop,
    Reset,
    Move,
    Jog,
    Stop,
    Stream,
    SetPosition,
}

/// One timed command of a `[[program]]` (lockstep-deterministic: applied at the first
/// position-loop tick at or after `at_s`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProgramStep {
    pub at_s: f64,
    /// The axis it commands (a multi-axis scenario's `[[axis]]` index; 0 otherwise).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub axis: u32,
    pub command: ProgramCommand,
    /// move: the target (set-position: the new position), rad.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to: Option<f64>,
    /// move: `to` is relative to the preceding move's target, else to where the axis
    /// stands (see `request_flags::RELATIVE`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub relative: bool,
    /// move: wait for the current move to end instead of changing at once.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub after_current: bool,
    /// move (a multi-axis scenario's): part of a coordinated move with every other axis's
    /// coordinated move step at the same `at_s` (absolute targets, the axes' move limits).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub coordinated: bool,
    /// jog: the speed, rad/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub velocity: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vmax: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub amax: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jmax: Option<f64>,
    /// stream: a CSV file of `t, θ[, ω, τ_ff]` rows (relative to the working directory).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
    /// stream: its lead, s (absent: `[axis] stream_lead_s`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lead_s: Option<f64>,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

impl ProgramStep {
    /// Checks the step on its own (whether the axis takes it is the axis's to say when it
    /// comes: a program can hold commands the axis refuses, and its report says so).
    pub fn validate(&self, index: usize) -> Result<(), ScenarioError> {
        let field = |name: &str| -> &'static str {
            // Field names in errors are static; a program's index is in the message.
            match name {
                "at_s" => "program.at_s",
                "to" => "program.to",
                "velocity" => "program.velocity",
                "file" => "program.file",
                _ => "program",
            }
        };
        if !(self.at_s.is_finite() && self.at_s >= 0.0) {
            return Err(invalid(
                field("at_s"),
                format!("(step {index}) must be a time ≥ 0 s (got {})", self.at_s),
            ));
        }
        let need = |what: &str, present: bool| {
            if present {
                Ok(())
            } else {
                Err(invalid(
                    field(what),
                    format!("(step {index}, {:?}) is required", self.command),
                ))
            }
        };
        if self.coordinated
            && (self.command != ProgramCommand::Move || self.relative || self.after_current)
        {
            return Err(invalid(
                field("coordinated"),
                format!(
                    "(step {index}, {:?}) coordinated is for an absolute move that changes at once",
                    self.command
                ),
            ));
        }
        match self.command {
            ProgramCommand::Move | ProgramCommand::SetPosition => need("to", self.to.is_some()),
            ProgramCommand::Jog => need("velocity", self.velocity.is_some()),
            ProgramCommand::Stream => need("file", self.file.is_some()),
            _ => Ok(()),
        }
    }
}

/// The CiA 402 power state machine's states (object 0x6041's state bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
#[repr(u32)]
pub enum AxisState {
    NotReadyToSwitchOn = 0,
    #[default]
    SwitchOnDisabled = 1,
    ReadyToSwitchOn = 2,
    SwitchedOn = 3,
    OperationEnabled = 4,
    QuickStopActive = 5,
    FaultReactionActive = 6,
    Fault = 7,
}

impl AxisState {
    pub const ALL: [AxisState; 8] = [
        AxisState::NotReadyToSwitchOn,
        AxisState::SwitchOnDisabled,
        AxisState::ReadyToSwitchOn,
        AxisState::SwitchedOn,
        AxisState::OperationEnabled,
        AxisState::QuickStopActive,
        AxisState::FaultReactionActive,
        AxisState::Fault,
    ];

    pub fn from_u32(v: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|s| *s as u32 == v)
    }

    /// Its CiA 402 name.
    pub fn name(self) -> &'static str {
        match self {
            AxisState::NotReadyToSwitchOn => "Not ready to switch on",
            AxisState::SwitchOnDisabled => "Switch on disabled",
            AxisState::ReadyToSwitchOn => "Ready to switch on",
            AxisState::SwitchedOn => "Switched on",
            AxisState::OperationEnabled => "Operation enabled",
            AxisState::QuickStopActive => "Quick stop active",
            AxisState::FaultReactionActive => "Fault reaction active",
            AxisState::Fault => "Fault",
        }
    }

    /// The state bits of the status word (0x6041): bit 0 ready to switch on, 1 switched
    /// on, 2 operation enabled, 3 fault, 4 voltage enabled, 5 quick stop (active low), 6
    /// switch on disabled.
    pub fn statusword(self) -> u16 {
        match self {
            AxisState::NotReadyToSwitchOn => 0x0000,
            AxisState::SwitchOnDisabled => 0x0040,
            AxisState::ReadyToSwitchOn => 0x0021,
            AxisState::SwitchedOn => 0x0023,
            AxisState::OperationEnabled => 0x0027,
            AxisState::QuickStopActive => 0x0007,
            AxisState::FaultReactionActive => 0x000F,
            AxisState::Fault => 0x0008,
        }
    }

    /// The motor has torque (the current loop follows the setpoints).
    pub fn outputs_on(self) -> bool {
        matches!(
            self,
            AxisState::OperationEnabled | AxisState::QuickStopActive
        )
    }
}

/// Status word bits beyond the state (0x6041): warning, target reached, set-point
/// acknowledge, following error, internal limit active, and in manufacturer-specific bit 14
/// the holding brake.
pub mod status_bits {
    pub const WARNING: u16 = 1 << 7;
    pub const TARGET_REACHED: u16 = 1 << 10;
    pub const INTERNAL_LIMIT: u16 = 1 << 11;
    /// Profile position (CiA 402's single set-point buffer): a move taken "after the
    /// current" waits in the buffer; another such move is refused until it is free.
    pub const SETPOINT_ACK: u16 = 1 << 12;
    pub const FOLLOWING_ERROR: u16 = 1 << 13;
    /// Manufacturer-specific: the axis applies the holding brake (outputs off, or its
    /// release time since the enable not yet past).
    pub const BRAKE_APPLIED: u16 = 1 << 14;
}

/// What an [`AxisRequest`] asks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
pub enum RequestKind {
    /// CiA 402 transitions by command (the control word's).
    Shutdown = 1,
    SwitchOn = 2,
    EnableOperation = 3,
    DisableVoltage = 4,
    QuickStop = 5,
    DisableOperation = 6,
    FaultReset = 7,
    /// Shutdown, switch on and enable operation at once, from wherever that leads.
    Enable = 8,
    /// Profile position: to `target_rad` (relative with [`request_flags::RELATIVE`]).
    Move = 9,
    /// Profile velocity: at `velocity_rad_s`.
    Jog = 10,
    /// Halt: decelerate to standstill at the move's deceleration, stay enabled.
    Stop = 11,
    /// Cyclic synchronous position: points follow on the stream topic.
    StreamStart = 12,
    StreamEnd = 13,
    /// The present position is `target_rad` from now on (the axis standing still).
    SetPosition = 14,
    /// Nothing but an acknowledgement with the state (a status query through the service).
    Status = 15,
}

impl RequestKind {
    pub const ALL: [RequestKind; 15] = [
        RequestKind::Shutdown,
        RequestKind::SwitchOn,
        RequestKind::EnableOperation,
        RequestKind::DisableVoltage,
        RequestKind::QuickStop,
        RequestKind::DisableOperation,
        RequestKind::FaultReset,
        RequestKind::Enable,
        RequestKind::Move,
        RequestKind::Jog,
        RequestKind::Stop,
        RequestKind::StreamStart,
        RequestKind::StreamEnd,
        RequestKind::SetPosition,
        RequestKind::Status,
    ];

    pub fn from_u32(v: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|k| *k as u32 == v)
    }

    pub fn name(self) -> &'static str {
        match self {
            RequestKind::Shutdown => "shutdown",
            RequestKind::SwitchOn => "switch-on",
            RequestKind::EnableOperation => "enable-operation",
            RequestKind::DisableVoltage => "disable-voltage",
            RequestKind::QuickStop => "quick-stop",
            RequestKind::DisableOperation => "disable-operation",
            RequestKind::FaultReset => "fault-reset",
            RequestKind::Enable => "enable",
            RequestKind::Move => "move",
            RequestKind::Jog => "jog",
            RequestKind::Stop => "stop",
            RequestKind::StreamStart => "stream-start",
            RequestKind::StreamEnd => "stream-end",
            RequestKind::SetPosition => "set-position",
            RequestKind::Status => "status",
        }
    }
}

pub mod request_flags {
    /// Move: the target is relative to the preceding move's target (the move in progress,
    /// or the last one if nothing has moved the axis since), else to where the axis stands
    /// (its position demand, θ_d): never to a jog's or a stop's internal target.
    pub const RELATIVE: u32 = 1 << 0;
    /// Move: after the current move ends (otherwise it changes at once).
    pub const AFTER_CURRENT: u32 = 1 << 1;
    /// The limits given (otherwise the axis's move defaults).
    pub const HAS_V: u32 = 1 << 2;
    pub const HAS_A: u32 = 1 << 3;
    pub const HAS_J: u32 = 1 << 4;
    /// Stream start: `lead_s` given (otherwise `[axis] stream_lead_s`).
    pub const HAS_LEAD: u32 = 1 << 5;
    /// Move (a multi-axis program's): one axis's part of a coordinated move, which every
    /// axis with such a step at the same time starts on one tick and ends on one tick.
    pub const COORDINATED: u32 = 1 << 6;
    /// A client's coordinated part: bits 16-23 name every axis of its move (bit n: axis
    /// n), this one among them. The parts wait for each other (each answered when the move
    /// starts, or is refused, on one tick). A program's parts leave these bits 0: their
    /// partners are the parts due at the same time.
    pub const GROUP_SHIFT: u32 = 16;
    pub const GROUP_MASK: u32 = 0xff << GROUP_SHIFT;

    /// The axes of a coordinated part's move (bit n: axis n; 0: a program's part).
    pub fn group(flags: u32) -> u32 {
        (flags & GROUP_MASK) >> GROUP_SHIFT
    }

    /// `flags` with the coordinated bit and the group `axes` (bit per axis, 0 … 7).
    pub fn with_group(flags: u32, axes: u32) -> u32 {
        (flags & !GROUP_MASK) | COORDINATED | ((axes << GROUP_SHIFT) & GROUP_MASK)
    }
}

/// Whether `id` is a remote client's: odd and at or above 2³¹, so never a Linux pid (at
/// most 2²²), the id every local client uses. A remote client's commands carry it in the top
/// 32 bits of their sequence numbers too ([`AxisRequest::from_remote_client`]).
pub fn is_remote_client(id: u32) -> bool {
    id & 1 == 1 && id >= 1 << 31
}

/// Client → position loop, on the axis command service: one command, answered by an
/// [`AxisAck`] within the tick it is taken in.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.AxisRequest.v1")
)]
#[repr(C)]
pub struct AxisRequest {
    pub axis: u32,
    /// A [`RequestKind`].
    pub kind: u32,
    /// The client's own sequence number, echoed in the ack and the status.
    pub seq: u64,
    /// CLOCK_MONOTONIC at publication, nanoseconds.
    pub publish_time_ns: u64,
    /// The client (its pid), for logs.
    pub client: u32,
    /// [`request_flags`] bits.
    pub flags: u32,
    /// Move: the target; set-position: the new position, rad.
    pub target_rad: f64,
    /// Jog: the speed, rad/s.
    pub velocity_rad_s: f64,
    /// Limits with their `HAS_*` flag.
    pub v_max_rad_s: f64,
    pub a_max_rad_s2: f64,
    pub j_max_rad_s3: f64,
    /// Stream start: the lead, s.
    pub lead_s: f64,
}

impl AxisRequest {
    /// Whether it comes from a remote client as a gateway must see it: a remote client's id
    /// ([`is_remote_client`]), which the top 32 bits of its sequence number repeat.
    pub fn from_remote_client(&self) -> bool {
        is_remote_client(self.client) && (self.seq >> 32) as u32 == self.client
    }
}

/// Why a command was refused (0: taken).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
pub enum Refusal {
    None = 0,
    UnknownAxis = 1,
    UnknownCommand = 2,
    NotFinite = 3,
    LimitNotPositive = 4,
    LimitAboveAxis = 5,
    OutsideSoftLimits = 6,
    NotEnabled = 7,
    WrongState = 8,
    Moving = 9,
    StreamNotStarted = 10,
    StreamOutOfOrder = 11,
    TooMany = 12,
    BufferFull = 13,
    /// A coordinated part whose partners did not all come in time.
    GroupIncomplete = 14,
    /// Limits below the axis's least ([`LIMIT_FLOOR`] of its maximum), or so low that the
    /// command would take longer than `[axis] move_time_max_s`.
    TooSlow = 15,
    /// Through a gateway: a request whose client id is not a remote client's (odd, at least
    /// 2³¹) or differs from the top 32 bits of its sequence number.
    BadClient = 16,
}

impl Refusal {
    pub const ALL: [Refusal; 17] = [
        Refusal::None,
        Refusal::UnknownAxis,
        Refusal::UnknownCommand,
        Refusal::NotFinite,
        Refusal::LimitNotPositive,
        Refusal::LimitAboveAxis,
        Refusal::OutsideSoftLimits,
        Refusal::NotEnabled,
        Refusal::WrongState,
        Refusal::Moving,
        Refusal::StreamNotStarted,
        Refusal::StreamOutOfOrder,
        Refusal::TooMany,
        Refusal::BufferFull,
        Refusal::GroupIncomplete,
        Refusal::TooSlow,
        Refusal::BadClient,
    ];

    pub fn from_u32(v: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|r| *r as u32 == v)
    }

    pub fn name(self) -> &'static str {
        match self {
            Refusal::None => "taken",
            Refusal::UnknownAxis => "unknown axis",
            Refusal::UnknownCommand => "unknown command",
            Refusal::NotFinite => "a value is not finite",
            Refusal::LimitNotPositive => "a limit is not positive",
            Refusal::LimitAboveAxis => "a limit exceeds the axis's",
            Refusal::OutsideSoftLimits => "outside the soft position limits",
            Refusal::NotEnabled => "the axis is not in Operation enabled",
            Refusal::WrongState => "not a transition from the axis's state",
            Refusal::Moving => "the axis is moving",
            Refusal::StreamNotStarted => "no stream is running",
            Refusal::StreamOutOfOrder => "stream time must increase",
            Refusal::TooMany => "too many commands in one tick",
            Refusal::BufferFull => "a buffer is full (the stream's, or the set-point buffer)",
            Refusal::GroupIncomplete => "the coordinated move's other parts did not come",
            Refusal::TooSlow => "limits too low for the axis to carry the command out",
            Refusal::BadClient => "not a remote client's id",
        }
    }
}

/// Length of an ack's reason text.
pub const ACK_TEXT: usize = 120;

/// Position loop → the client that asked: whether its command was taken, and if not why.
/// Published on the acks topic too, for recorders.
#[derive(Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.AxisAck.v1")
)]
#[repr(C)]
pub struct AxisAck {
    /// The request answered, as it came.
    pub request: AxisRequest,
    /// A [`Refusal`]; 0 (`None`): taken.
    pub refusal: u32,
    /// The axis's [`AxisState`] after the command.
    pub state: u32,
    /// The position-loop tick that took it, and its time, s.
    pub tick: u64,
    pub t_s: f64,
    /// CLOCK_MONOTONIC when the tick's setpoint went out (the first to carry the command
    /// out), nanoseconds.
    pub publish_time_ns: u64,
    /// Bytes of `text` in use: the reason in words, with the numbers.
    pub text_len: u32,
    pub _reserved: u32,
    pub text: [u8; ACK_TEXT],
}

impl Default for AxisAck {
    fn default() -> Self {
        Self {
            request: AxisRequest::default(),
            refusal: 0,
            state: 0,
            tick: 0,
            t_s: 0.0,
            publish_time_ns: 0,
            text_len: 0,
            _reserved: 0,
            text: [0; ACK_TEXT],
        }
    }
}

impl std::fmt::Debug for AxisAck {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AxisAck")
            .field("axis", &self.request.axis)
            .field("kind", &self.request.kind)
            .field("seq", &self.request.seq)
            .field("refusal", &self.refusal)
            .field("text", &self.text())
            .finish()
    }
}

impl AxisAck {
    /// Writes `text` (cut at [`ACK_TEXT`] bytes, on a character boundary).
    pub fn set_text(&mut self, text: &str) {
        let mut n = text.len().min(ACK_TEXT);
        while !text.is_char_boundary(n) {
            n -= 1;
        }
        self.text[..n].copy_from_slice(&text.as_bytes()[..n]);
        self.text_len = n as u32;
    }

    pub fn text(&self) -> &str {
        let n = (self.text_len as usize).min(ACK_TEXT);
        std::str::from_utf8(&self.text[..n]).unwrap_or("")
    }

    pub fn taken(&self) -> bool {
        self.refusal == Refusal::None as u32
    }
}

/// What moves the axis's setpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
pub enum AxisMode {
    /// Holding where it is (or nothing: outputs off).
    #[default]
    Hold = 0,
    ProfilePosition = 1,
    ProfileVelocity = 2,
    CyclicPosition = 3,
    /// The scenario's own profile (the paper's trapezoid).
    ScenarioProfile = 4,
    QuickStop = 5,
    /// A move of several axes together, planned for all of them at once: every axis leaves
    /// on the same tick and arrives on the same tick (CiA 402's interpolated position mode
    /// plays that role for a multi-axis controller).
    Coordinated = 6,
}

impl AxisMode {
    pub fn from_u32(v: u32) -> Option<Self> {
        [
            AxisMode::Hold,
            AxisMode::ProfilePosition,
            AxisMode::ProfileVelocity,
            AxisMode::CyclicPosition,
            AxisMode::ScenarioProfile,
            AxisMode::QuickStop,
            AxisMode::Coordinated,
        ]
        .into_iter()
        .find(|m| *m as u32 == v)
    }

    pub fn name(self) -> &'static str {
        match self {
            AxisMode::Hold => "hold",
            AxisMode::ProfilePosition => "profile position",
            AxisMode::ProfileVelocity => "profile velocity",
            AxisMode::CyclicPosition => "cyclic synchronous position",
            AxisMode::ScenarioProfile => "scenario profile",
            AxisMode::QuickStop => "quick stop",
            AxisMode::Coordinated => "coordinated move",
        }
    }
}

/// Why the axis is in Fault (0: it is not).
pub mod axis_faults {
    /// |θ_d − θ| beyond the following error window for longer than its time.
    pub const FOLLOWING_ERROR: u32 = 1 << 0;
    /// The plant or the drive latched a fault (its bits are in the state).
    pub const DRIVE: u32 = 1 << 1;
    /// The current loop stopped the motor on its own: the setpoints grew stale.
    pub const SETPOINT_STALE: u32 = 1 << 2;
    /// The trajectory generator could not reach a state from where the axis stood.
    pub const TRAJECTORY: u32 = 1 << 3;
}

/// Warnings: the axis goes on, but not as asked.
pub mod axis_warnings {
    /// The torque (12) asked for more than `[axis] torque_max_nm`.
    pub const TORQUE_LIMITED: u32 = 1 << 0;
    /// A jog or a stream was stopped at a soft position limit.
    pub const SOFT_LIMIT: u32 = 1 << 1;
    /// A stream point came late or was past its time; the stream's last state was held.
    pub const STREAM_UNDERRUN: u32 = 1 << 2;
    /// A stream asked beyond the axis's limits; the envelope limited it (the setpoint left
    /// the stream by more than `target_window_rad`).
    pub const STREAM_LIMITED: u32 = 1 << 3;
    /// A stream stopped coming, or never began (its watchdog): the axis quick-stopped.
    pub const STREAM_LOST: u32 = 1 << 4;
    /// A jog's client stopped renewing it (`[axis] jog_timeout_s`): the axis quick-stopped.
    pub const JOG_LOST: u32 = 1 << 5;
}

/// Position loop → everyone, every position-loop tick: the axis as it stands.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.AxisStatus.v3")
)]
#[repr(C)]
pub struct AxisStatus {
    pub axis: u32,
    /// An [`AxisState`].
    pub state: u32,
    /// The position-loop tick, its time (the state sample's), s.
    pub tick: u64,
    pub t_s: f64,
    pub publish_time_ns: u64,
    /// The CiA 402 status word (0x6041) and mode ([`AxisMode`]).
    pub statusword: u32,
    pub mode: u32,
    /// Measured: θ, ω; the torque (12) asked for; θ_d − θ.
    pub theta_rad: f64,
    pub omega_rad_s: f64,
    pub torque_nm: f64,
    pub following_error_rad: f64,
    /// The setpoint: θ_d, ω_d, α_d, and the target it heads for.
    pub theta_d_rad: f64,
    pub omega_d_rad_s: f64,
    pub alpha_d_rad_s2: f64,
    pub target_rad: f64,
    /// [`axis_faults`] and [`axis_warnings`] bits; the device's latched fault bits.
    pub fault: u32,
    pub warning: u32,
    pub device_fault: u32,
    /// The last command taken: its kind and the client's seq.
    pub last_kind: u32,
    pub last_seq: u64,
    /// Profile position: the move in progress (counts every move taken).
    pub move_id: u64,
    /// Stream points refused (not finite, out of order, buffer full) and the last
    /// refusal ([`Refusal`]).
    pub refused_points: u64,
    pub last_refusal: u32,
    /// Counts every (re-)enable: the setpoints of one enable carry it.
    pub epoch: u32,
    /// Cyclic synchronous position: the stream time played at this tick (the axis's clock
    /// since the first point came, less the lead, from that point's time), s; NaN when no
    /// stream plays. A client paces its points by it (the drive's clock, not its own) and
    /// judges tracking against its path at this time.
    pub stream_time_s: f64,
    /// The newest point's stream time less `stream_time_s`: how far ahead the stream is
    /// buffered, s; and the stream's lead, s (NaN when no stream plays). A client that
    /// sends the point at stream time t once `stream_time_s + stream_lead_s ≥ t` keeps the
    /// buffer one lead deep whatever the two clocks do.
    pub stream_ahead_s: f64,
    pub stream_lead_s: f64,
    /// A multi-axis stack's running (or last) coordinated move of this axis: the measured
    /// rotors' peak distance from the move's straight line, rad (NaN: none yet).
    pub contour_rad: f64,
}

impl AxisStatus {
    pub fn axis_state(&self) -> Option<AxisState> {
        AxisState::from_u32(self.state)
    }

    pub fn target_reached(&self) -> bool {
        self.statusword as u16 & status_bits::TARGET_REACHED != 0
    }
}

pub mod point_flags {
    /// ω given (otherwise interpolated).
    pub const HAS_OMEGA: u32 = 1 << 0;
    /// τ feed-forward given.
    pub const HAS_TORQUE: u32 = 1 << 1;
}

/// Client → position loop, on the stream topic: one point of a cyclic synchronous
/// position stream (after a taken `StreamStart`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.AxisStreamPoint.v1")
)]
#[repr(C)]
pub struct AxisStreamPoint {
    pub axis: u32,
    /// [`point_flags`] bits.
    pub flags: u32,
    /// The stream: the seq of its `StreamStart` request.
    pub stream: u64,
    /// Point number in the stream, from 0.
    pub seq: u64,
    /// Stream time, s (the first point's is the stream's origin).
    pub t_s: f64,
    pub theta_rad: f64,
    pub omega_rad_s: f64,
    pub torque_ff_nm: f64,
    pub publish_time_ns: u64,
}

/// One row of a stream file: `t, θ[, ω[, τ_ff]]` (s, rad, rad/s, N·m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamRow {
    pub t_s: f64,
    pub theta_rad: f64,
    pub omega_rad_s: Option<f64>,
    pub torque_ff_nm: Option<f64>,
}

/// A stream file that cannot be streamed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StreamFileError {
    #[error("line {line}: {message}")]
    Line { line: usize, message: String },
    #[error("no points")]
    Empty,
}

/// Parses a stream file: CSV rows of `t, θ[, ω[, τ_ff]]`, blank lines and `#` comments
/// skipped, and a first line that is not numbers taken as a header. Time must increase and
/// every value be finite: a file that breaks that is refused whole, naming the line.
pub fn parse_stream(text: &str) -> Result<Vec<StreamRow>, StreamFileError> {
    let rows = numeric_rows(text, 2..=4, "a row is t, θ[, ω[, τ_ff]]")?;
    Ok(rows
        .iter()
        .map(|values| StreamRow {
            t_s: values[0],
            theta_rad: values[1],
            omega_rad_s: values.get(2).copied(),
            torque_ff_nm: values.get(3).copied(),
        })
        .collect())
}

/// Parses a stream file of several axes: CSV rows of `t, θ_0, θ_1, …`, one position per
/// axis (rad), under the rules of [`parse_stream`]. Each row: its time, then its positions.
pub fn parse_stream_of_axes(text: &str, axes: usize) -> Result<Vec<Vec<f64>>, StreamFileError> {
    let shape = format!("a row is t and one θ for each of the {axes} axes");
    numeric_rows(text, axes + 1..=axes + 1, &shape)
}

/// The θ columns of a stream file of several axes: its first row of numbers' fields less
/// the time (0 if it has none; [`parse_stream_of_axes`] then says what is wrong).
pub fn stream_theta_columns(text: &str) -> usize {
    text.lines()
        .filter_map(numbers_of)
        .find_map(|(_, values)| values.ok())
        .map_or(0, |values| values.len().saturating_sub(1))
}

/// A stream file's line, its `#` comment left out, and it as numbers; `None` if nothing is
/// left.
fn numbers_of(raw: &str) -> Option<(&str, Result<Vec<f64>, std::num::ParseFloatError>)> {
    let content = raw.split('#').next().unwrap_or("").trim();
    (!content.is_empty()).then(|| {
        let values = content
            .split(',')
            .map(|f| f.trim().parse::<f64>())
            .collect();
        (content, values)
    })
}

/// CSV rows of numbers, `fields` of them each, the first a time that increases.
fn numeric_rows(
    text: &str,
    fields: std::ops::RangeInclusive<usize>,
    shape: &str,
) -> Result<Vec<Vec<f64>>, StreamFileError> {
    let mut rows: Vec<Vec<f64>> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let Some((content, values)) = numbers_of(raw) else {
            continue;
        };
        let values = match values {
            Ok(v) => v,
            Err(_) if rows.is_empty() && line == 1 => continue,
            Err(e) => {
                return Err(StreamFileError::Line {
                    line,
                    message: format!("`{content}` is not numbers: {e}"),
                })
            }
        };
        if !fields.contains(&values.len()) {
            return Err(StreamFileError::Line {
                line,
                message: format!("{} fields; {shape}", values.len()),
            });
        }
        if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
            return Err(StreamFileError::Line {
                line,
                message: format!("{bad} is not finite"),
            });
        }
        if let Some(last) = rows.last().filter(|l| values[0] <= l[0]) {
            return Err(StreamFileError::Line {
                line,
                message: format!("time must increase: {} s after {} s", values[0], last[0]),
            });
        }
        rows.push(values);
    }
    if rows.is_empty() {
        return Err(StreamFileError::Empty);
    }
    Ok(rows)
}

impl StreamRow {
    /// As the stream topic's point number `seq` of stream `stream` on `axis`.
    pub fn point(&self, axis: u32, stream: u64, seq: u64) -> AxisStreamPoint {
        let mut flags = 0;
        if self.omega_rad_s.is_some() {
            flags |= point_flags::HAS_OMEGA;
        }
        if self.torque_ff_nm.is_some() {
            flags |= point_flags::HAS_TORQUE;
        }
        AxisStreamPoint {
            axis,
            flags,
            stream,
            seq,
            t_s: self.t_s,
            theta_rad: self.theta_rad,
            omega_rad_s: self.omega_rad_s.unwrap_or(0.0),
            torque_ff_nm: self.torque_ff_nm.unwrap_or(0.0),
            publish_time_ns: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn remote_ids_are_odd_and_above_any_pid() {
        assert!(is_remote_client(0x8000_0001));
        assert!(is_remote_client(u32::MAX));
        assert!(!is_remote_client(0x8000_0000), "even");
        assert!(!is_remote_client(0xfffe_0000), "the gateway's own");
        assert!(!is_remote_client(4_194_303), "a pid");
    }

    /// A gateway takes a remote client's request only when its sequence number carries the
    /// same id.
    #[test]
    fn a_remote_request_repeats_its_id_in_its_sequence_number() {
        let id = 0x8000_0003u32;
        let request = |client: u32, seq: u64| AxisRequest {
            client,
            seq,
            ..Default::default()
        };
        assert!(request(id, u64::from(id) << 32 | 7).from_remote_client());
        assert!(
            !request(id, 7).from_remote_client(),
            "a local sequence number"
        );
        assert!(
            !request(id, u64::from(id + 2) << 32).from_remote_client(),
            "another id"
        );
        let pid = 4242;
        assert!(
            !request(pid, u64::from(pid) << 32).from_remote_client(),
            "a pid"
        );
    }

    #[test]
    fn a_stream_file_with_a_header_comments_and_optional_columns_parses() {
        let rows =
            parse_stream("t,theta,omega\n0, 0, 1 # start\n\n0.001, 0.001\n").expect("parses");
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].omega_rad_s, Some(1.0));
        assert_eq!(rows[1].omega_rad_s, None);
    }

    #[test]
    fn a_stream_going_backwards_or_not_finite_is_refused_naming_the_line() {
        let e = parse_stream("0,0\n0.002,1\n0.001,2\n").expect_err("backwards");
        assert!(
            e.to_string().contains("line 3") && e.to_string().contains("increase"),
            "{e}"
        );
        let e = parse_stream("0,0\n0.001,NaN\n").expect_err("not finite");
        assert!(e.to_string().contains("line 2"), "{e}");
        assert_eq!(parse_stream("# nothing\n"), Err(StreamFileError::Empty));
    }

    #[test]
    fn a_stream_of_several_axes_has_one_position_per_axis() {
        let rows =
            parse_stream_of_axes("t,x,y,z\n0, 0, 1, 2\n0.001, 0.1, 1.1, 2.1\n", 3).expect("parses");
        assert_eq!(
            rows,
            vec![vec![0.0, 0.0, 1.0, 2.0], vec![0.001, 0.1, 1.1, 2.1]]
        );
        assert_eq!(stream_theta_columns("t,x,y,z\n# c\n0, 0, 1, 2 # x\n"), 3);
        assert_eq!(stream_theta_columns("t,x\n"), 0);
        let e = parse_stream_of_axes("0, 0, 1\n", 3).expect_err("a column short");
        assert!(
            e.to_string().contains("line 1") && e.to_string().contains("3 axes"),
            "{e}"
        );
    }

    #[test]
    fn statuswords_follow_cia_402() {
        // 0x6041 bits: xxxx xxxx x00x 0000 switch on disabled = 0x40 with bit 6, ...
        assert_eq!(AxisState::OperationEnabled.statusword() & 0x6F, 0x27);
        assert_eq!(AxisState::SwitchOnDisabled.statusword() & 0x4F, 0x40);
        assert_eq!(AxisState::QuickStopActive.statusword() & 0x6F, 0x07);
        assert_eq!(AxisState::Fault.statusword() & 0x4F, 0x08);
        for s in AxisState::ALL {
            assert_eq!(AxisState::from_u32(s as u32), Some(s));
        }
    }
}
