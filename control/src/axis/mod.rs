//! The axis: what programs command, as a CiA 402 drive is commanded. A power state machine
//! with CiA 402's states and transitions; command sources — profile position (moves with
//! v/a/j limits, changed at once or after the current one), profile velocity (jog),
//! cyclic synchronous position (a stream), the scenario's own profile — turned into θ_d,
//! ω_d, α_d by the online trajectory generator ([`otg`]); and a safety envelope that holds
//! whatever the source: soft position limits, v/a/j limits, a following-error window and
//! time that fault the axis, a quick stop at its own deceleration, bumpless enable (the
//! setpoint starts where the rotor is, at rest), and commands refused with their reason,
//! never applied and never clamped silently.
//!
//! Pure: the position loop's node feeds it the measured state and the commands each tick,
//! and gives (12) the setpoint it returns. No IPC, no clock, no allocation in a tick.

pub mod coordinated;
pub mod gather;
pub mod group;
pub mod otg;
pub mod stream;
pub mod track;

use otg::{Goal, Limits, Otg, OtgError};
use stepdrive_shared::axis::{
    axis_faults, axis_warnings, request_flags, status_bits, AxisMode, AxisParams, AxisRequest,
    AxisState, AxisStatus, AxisStreamPoint, Refusal, RequestKind, LIMIT_FLOOR,
};
use stepdrive_shared::trajectory::{Reference, Trapezoid};
use stream::{Play, Point, PointError, Stream};

/// What the axis sees at a tick: the state sample's time and the measured rotor, and what
/// the device and the current loop report.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Measured {
    pub t: f64,
    pub theta: f64,
    pub omega: f64,
    /// The device's latched fault bits (zero: healthy).
    pub device_fault: u32,
    /// The current loop stopped the motor on its own (stale setpoints).
    pub setpoint_stale: bool,
}

/// What the axis asks of the torque law at a tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Setpoint {
    /// θ_d, ω_d, α_d at the tick's time.
    pub reference: Reference,
    /// The motor has torque; off, the current loop applies zero volts.
    pub outputs_on: bool,
    /// A stream's torque feed-forward, N·m.
    pub torque_ff: f64,
    /// The enable these setpoints belong to.
    pub epoch: u32,
    /// The acceleration is continuous (the trajectory generator's, jerk-limited; not the
    /// scenario's profile, whose acceleration steps at its corners).
    pub smooth: bool,
    /// The trajectory's jerk, rad/s³ (0 for the scenario's profile).
    pub jerk: f64,
    /// The holding brake may be released (outputs on, its release time past).
    pub brake_released: bool,
}

/// A command not taken: why, in words with the numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct Refused {
    pub refusal: Refusal,
    pub text: String,
}

/// `x` to four significant digits, trailing zeros left out (3e-5, not 2.9999999999999997e-5).
fn short(x: f64) -> String {
    let s = format!("{x:.3e}");
    match s.split_once('e') {
        Some((mantissa, exp)) if mantissa.contains('.') => {
            format!(
                "{}e{exp}",
                mantissa.trim_end_matches('0').trim_end_matches('.')
            )
        }
        _ => s,
    }
}

fn refuse(refusal: Refusal, text: impl Into<String>) -> Refused {
    Refused {
        refusal,
        text: text.into(),
    }
}

/// Who sent a command: a client (its jogs need renewing: [`AxisParams::jog_timeout_s`]) or
/// the scenario's program, the stack's own script, which lives and dies with the loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    Client,
    Program,
}

/// The axis. See the module documentation.
#[derive(Debug)]
pub struct Axis {
    p: AxisParams,
    period: f64,
    state: AxisState,
    mode: AxisMode,
    otg: Otg,
    /// The OTG's own time (a whole number of periods after its last restart).
    otg_t: f64,
    profile: Option<Trapezoid>,
    /// CiA 402's single set-point buffer: the move waiting for the current one to end
    /// (`after current`), its target and limits.
    queued: Option<(f64, Limits)>,
    /// Where the setpoint heads (a jog: the soft limit it runs to), for the status.
    target: f64,
    /// The target of the move in progress, or of the last one while nothing else has moved
    /// the axis since: what a relative move counts from. Never a jog's or a stop's.
    move_target: Option<f64>,
    /// The client whose jog runs (`None`: no jog, or the program's), and the axis time it
    /// last heard from that client.
    jog_client: Option<u32>,
    jog_renewed: f64,
    /// The axis time the running stream was started (its first point is due by a lead and
    /// a stream timeout after).
    stream_started: f64,
    move_id: u64,
    /// A stream: its id (its start's seq), its lead, the axis time its first point came
    /// and that point's stream time.
    stream: Stream,
    stream_id: Option<u64>,
    stream_lead: f64,
    stream_origin: Option<(f64, f64)>,
    /// A stream of several axes (a client's coordinated stream start): the origin is the
    /// group's to set, once every axis of it has its first point, whose time is kept here.
    origin_from_group: bool,
    stream_first: Option<f64>,
    /// The state a stream is followed from (at the trajectory's time).
    followed: Reference,
    /// The jerk of the period that led to `followed`, rad/s³: what (12)'s torque moves on
    /// at between ticks. The generator's own jerk is stale while a stream is followed.
    followed_jerk: f64,
    refused_points: u64,
    last_refusal: Refusal,
    fault: u32,
    warning: u32,
    following_since: Option<f64>,
    /// A fault reset waiting for the device's fault to clear.
    reset_pending: bool,
    last_kind: u32,
    last_seq: u64,
    epoch: u32,
    /// Axis position = measured θ + offset (set-position).
    offset: f64,
    /// When the outputs came on (the last enable from a powered-off state), s: the brake
    /// is released `brake_release_s` after.
    enabled_at: f64,
    /// The last setpoint, in axis coordinates, and the tick's time.
    reference: Reference,
    torque_ff: f64,
    t: f64,
    /// A coordinated move of its group runs: the group gives each tick's state.
    coordinated: bool,
    /// The group's state for the next tick, and the jerk that led to it.
    /// and the axis time the state is meant for.
    coordinated_next: Option<(Reference, f64, f64)>,
    coordinated_jerk: f64,
}

impl Axis {
    /// An axis standing disabled (Switch on disabled) at θ = 0; `period_s` is the position
    /// loop's.
    pub fn new(p: &AxisParams, period_s: f64) -> Self {
        let at = Reference::default();
        Self {
            otg: Otg::new(period_s, at, move_limits(p)),
            p: p.clone(),
            period: period_s,
            state: AxisState::SwitchOnDisabled,
            mode: AxisMode::Hold,
            otg_t: 0.0,
            profile: None,
            queued: None,
            target: 0.0,
            move_target: None,
            jog_client: None,
            jog_renewed: 0.0,
            stream_started: 0.0,
            move_id: 0,
            stream: Stream::default(),
            stream_id: None,
            stream_lead: p.stream_lead_s,
            stream_origin: None,
            origin_from_group: false,
            stream_first: None,
            followed: at,
            followed_jerk: 0.0,
            refused_points: 0,
            last_refusal: Refusal::None,
            fault: 0,
            warning: 0,
            following_since: None,
            reset_pending: false,
            last_kind: 0,
            last_seq: 0,
            epoch: 0,
            offset: 0.0,
            enabled_at: f64::NEG_INFINITY,
            reference: at,
            torque_ff: 0.0,
            t: 0.0,
            coordinated: false,
            coordinated_next: None,
            coordinated_jerk: 0.0,
        }
    }

    /// An axis enabled from the start, running the scenario's profile (`run` without a
    /// program: the paper's experiment).
    pub fn running_profile(p: &AxisParams, period_s: f64, profile: Trapezoid) -> Self {
        let mut a = Self::new(p, period_s);
        a.state = AxisState::OperationEnabled;
        a.mode = AxisMode::ScenarioProfile;
        a.profile = Some(profile);
        a.epoch = 1;
        a
    }

    pub fn state(&self) -> AxisState {
        self.state
    }

    pub fn mode(&self) -> AxisMode {
        self.mode
    }

    pub fn fault(&self) -> u32 {
        self.fault
    }

    /// A fault reset was asked while the device has a fault latched: its node asks the
    /// device to reset.
    pub fn device_reset_wanted(&self) -> bool {
        self.reset_pending
    }

    pub fn warning(&self) -> u32 {
        self.warning
    }

    pub fn epoch(&self) -> u32 {
        self.epoch
    }

    /// The measured position in axis coordinates.
    fn position(&self, m: &Measured) -> f64 {
        m.theta + self.offset
    }

    /// Restarts the trajectory at the measured position, at rest: a bumpless enable.
    fn restart_at(&mut self, m: &Measured) {
        let at = Reference {
            theta: self.position(m),
            omega: 0.0,
            alpha: 0.0,
        };
        self.otg.set_limits(move_limits(&self.p));
        self.otg.restart(at);
        self.otg_t = m.t;
        self.reference = at;
        self.target = at.theta;
        self.mode = AxisMode::Hold;
        self.profile = None;
        self.queued = None;
        self.move_target = None;
        self.jog_client = None;
        self.end_stream();
        self.end_coordinated();
        self.following_since = None;
        self.torque_ff = 0.0;
        self.epoch = self.epoch.wrapping_add(1);
        self.enabled_at = m.t;
    }

    /// The holding brake may be released: the outputs are on and its release time has
    /// passed since they came on.
    fn brake_released(&self, t: f64) -> bool {
        self.state.outputs_on() && t - self.enabled_at >= self.p.brake_release_s
    }

    /// Takes the trajectory from wherever the setpoint is now (a change of source while
    /// enabled keeps θ_d, ω_d, α_d continuous).
    fn take_over(&mut self, m: &Measured) {
        if matches!(
            self.mode,
            AxisMode::ScenarioProfile | AxisMode::CyclicPosition | AxisMode::Coordinated
        ) {
            self.otg.restart(self.reference);
            self.otg_t = m.t;
        }
        self.end_coordinated();
        self.profile = None;
        self.end_stream();
        self.torque_ff = 0.0;
        // Whatever takes over ends the move a relative move would count from, and a jog.
        self.move_target = None;
        self.jog_client = None;
    }

    /// The state a change of source starts from: the setpoint where the generator does not
    /// run the axis (the scenario's profile, a stream, the group's move), else the
    /// generator's own state.
    fn takeover_state(&self) -> Reference {
        match self.mode {
            AxisMode::ScenarioProfile | AxisMode::CyclicPosition | AxisMode::Coordinated => {
                self.reference
            }
            _ => self.otg.state(),
        }
    }

    /// Refuses a command whose trajectory the generator cannot plan, or that would take
    /// longer than `[axis] move_time_max_s` (`what`: the command, for the text).
    fn plannable(
        &mut self,
        from: Reference,
        goal: Goal,
        limits: Limits,
        what: &str,
    ) -> Result<(), Refused> {
        let max = self.p.move_time_max_s;
        match self.otg.plan_duration(from, goal, limits) {
            Ok(d) if d <= max => Ok(()),
            Ok(d) => Err(refuse(
                Refusal::TooSlow,
                format!(
                    "{what} would take {} s at these limits, over the axis's {max} s",
                    short(d)
                ),
            )),
            Err(e) => Err(refuse(
                Refusal::TooSlow,
                format!("{what} cannot be planned at these limits: {}", e.why),
            )),
        }
    }

    /// What a relative move counts from: the preceding move's target, else where the axis
    /// stands (its position demand).
    fn relative_base(&self) -> f64 {
        self.move_target.unwrap_or(self.reference.theta)
    }

    /// Leaves the group's move: from here the generator holds or takes the axis on.
    fn end_coordinated(&mut self) {
        self.coordinated = false;
        self.coordinated_next = None;
    }

    fn end_stream(&mut self) {
        self.stream.clear();
        self.stream_id = None;
        self.stream_origin = None;
        self.origin_from_group = false;
        self.stream_first = None;
    }

    /// The running stream is one axis's of a multi-axis stream: its points are played from
    /// the origin [`Self::start_stream_at`] gives, not from its own first point's arrival
    /// (the axes' first points may arrive on different ticks).
    pub fn stream_in_group(&mut self) {
        self.origin_from_group = self.mode == AxisMode::CyclicPosition;
    }

    /// A multi-axis stream's axis waiting for its origin: its first point's stream time
    /// once one has come.
    pub fn stream_first_point(&self) -> Option<f64> {
        (self.origin_from_group && self.stream_origin.is_none())
            .then_some(self.stream_first)
            .flatten()
    }

    /// Whether the axis is still in a multi-axis stream whose origin is not yet set.
    pub fn stream_awaits_origin(&self) -> bool {
        self.origin_from_group
            && self.stream_origin.is_none()
            && self.mode == AxisMode::CyclicPosition
    }

    /// A multi-axis stream's axis whose group broke up before it began: it plays from its
    /// own first point (now, if one has come).
    pub fn stream_alone(&mut self) {
        if !self.stream_awaits_origin() {
            return;
        }
        self.origin_from_group = false;
        if let Some(first) = self.stream_first {
            self.stream_origin = Some((self.t, first));
        }
    }

    /// A multi-axis stream's origin: its stream time `first` is played a lead after axis
    /// time `t` (every axis of the stream is given the same two).
    pub fn start_stream_at(&mut self, t: f64, first: f64) {
        if self.stream_awaits_origin() {
            self.stream_origin = Some((t, first));
        }
    }

    fn power_off(&mut self, to: AxisState) {
        self.end_coordinated();
        self.state = to;
        self.mode = AxisMode::Hold;
        self.profile = None;
        self.queued = None;
        self.move_target = None;
        self.jog_client = None;
        self.end_stream();
        self.following_since = None;
    }

    fn enter_fault(&mut self, bits: u32) {
        self.fault |= bits;
        self.power_off(AxisState::Fault);
    }

    /// Quick stop: decelerate at its own rate to standstill, and hold there.
    fn quick_stop(&mut self, m: &Measured) {
        self.take_over(m);
        self.queued = None;
        self.otg.set_limits(Limits {
            v: self.p.v_max_rad_s,
            a: self.p.quick_stop_decel_rad_s2,
            j: self.p.j_max_rad_s3,
        });
        self.otg.set_goal(Goal::Velocity(0.0));
        self.state = AxisState::QuickStopActive;
        self.mode = AxisMode::QuickStop;
    }

    /// The limits a command asks for: its own (valid and within the axis's), or the move
    /// defaults.
    fn limits_of(&self, r: &AxisRequest) -> Result<Limits, Refused> {
        let defaults = move_limits(&self.p);
        let pick = |has: u32, v: f64, default: f64, max: f64, name: &str, unit: &str| {
            if r.flags & has == 0 {
                return Ok(default);
            }
            if !v.is_finite() {
                return Err(refuse(Refusal::NotFinite, format!("{name} is {v}")));
            }
            if v <= 0.0 {
                return Err(refuse(
                    Refusal::LimitNotPositive,
                    format!("{name} {v} {unit} is not positive"),
                ));
            }
            if v < max * LIMIT_FLOOR {
                return Err(refuse(
                    Refusal::TooSlow,
                    format!(
                        "{name} {} {unit} is below the axis's least, {} {unit}",
                        short(v),
                        short(max * LIMIT_FLOOR)
                    ),
                ));
            }
            if v > max {
                return Err(refuse(
                    Refusal::LimitAboveAxis,
                    format!("{name} {v} {unit} exceeds the axis's {max} {unit}"),
                ));
            }
            Ok(v)
        };
        Ok(Limits {
            v: pick(
                request_flags::HAS_V,
                r.v_max_rad_s,
                defaults.v,
                self.p.v_max_rad_s,
                "vmax",
                "rad/s",
            )?,
            a: pick(
                request_flags::HAS_A,
                r.a_max_rad_s2,
                defaults.a,
                self.p.a_max_rad_s2,
                "amax",
                "rad/s²",
            )?,
            j: pick(
                request_flags::HAS_J,
                r.j_max_rad_s3,
                defaults.j,
                self.p.j_max_rad_s3,
                "jmax",
                "rad/s³",
            )?,
        })
    }

    fn within_soft_limits(&self, theta: f64) -> Result<(), Refused> {
        let (lo, hi) = (self.p.position_min_rad, self.p.position_max_rad);
        if theta < lo || theta > hi {
            return Err(refuse(
                Refusal::OutsideSoftLimits,
                format!("{theta} rad is outside the soft limits [{lo}, {hi}] rad"),
            ));
        }
        Ok(())
    }

    /// Whether the axis takes stream start `r`, nothing applied: its lead if so (a stream
    /// of several axes starts on every axis or none, so each is asked first).
    pub fn stream_start(&self, r: &AxisRequest) -> Result<f64, Refused> {
        self.enabled("a stream")?;
        let lead = if r.flags & request_flags::HAS_LEAD != 0 {
            r.lead_s
        } else {
            self.p.stream_lead_s
        };
        if !(lead.is_finite() && (0.0..=10.0).contains(&lead)) {
            return Err(refuse(
                Refusal::NotFinite,
                format!("lead {lead} s must be within 0 … 10 s"),
            ));
        }
        Ok(lead)
    }

    fn enabled(&self, what: &str) -> Result<(), Refused> {
        if self.state != AxisState::OperationEnabled {
            return Err(refuse(
                Refusal::NotEnabled,
                format!(
                    "{what} needs Operation enabled; the axis is in {}",
                    self.state.name()
                ),
            ));
        }
        Ok(())
    }

    fn wrong_state(&self, kind: RequestKind) -> Refused {
        refuse(
            Refusal::WrongState,
            format!("no {} from {}", kind.name(), self.state.name()),
        )
    }

    /// A client's command, at the tick whose measured state is `m`: taken (applied from
    /// this tick on) or refused with its reason (nothing applied). Any command of the client
    /// whose jog runs renews the jog, taken or not (the client is alive).
    pub fn request(&mut self, r: &AxisRequest, m: &Measured) -> Result<(), Refused> {
        if self.jog_client == Some(r.client) {
            self.jog_renewed = m.t;
        }
        self.command(r, m, Source::Client)
    }

    /// A step of the scenario's program, as [`Self::request`] takes a client's command; a
    /// jog it starts needs no renewal (the program is the position loop's own).
    pub fn request_scripted(&mut self, r: &AxisRequest, m: &Measured) -> Result<(), Refused> {
        self.command(r, m, Source::Program)
    }

    fn command(&mut self, r: &AxisRequest, m: &Measured, source: Source) -> Result<(), Refused> {
        let Some(kind) = RequestKind::from_u32(r.kind) else {
            return Err(refuse(
                Refusal::UnknownCommand,
                format!("unknown command {}", r.kind),
            ));
        };
        self.apply(kind, r, m, source)?;
        // A status request reads: it is no command, and must not stand in the status as
        // the last one (a client waiting for its move, or a gateway judging whose motion
        // runs, would see another client's read as a new command).
        if kind != RequestKind::Status {
            self.last_kind = r.kind;
            self.last_seq = r.seq;
        }
        Ok(())
    }

    fn apply(
        &mut self,
        kind: RequestKind,
        r: &AxisRequest,
        m: &Measured,
        source: Source,
    ) -> Result<(), Refused> {
        use AxisState as S;
        let s = self.state;
        match kind {
            RequestKind::Status => {}
            RequestKind::Shutdown => match s {
                S::SwitchOnDisabled | S::SwitchedOn | S::OperationEnabled => {
                    self.power_off(S::ReadyToSwitchOn)
                }
                S::ReadyToSwitchOn => {}
                _ => return Err(self.wrong_state(kind)),
            },
            RequestKind::SwitchOn => match s {
                S::ReadyToSwitchOn => self.state = S::SwitchedOn,
                S::SwitchedOn => {}
                S::OperationEnabled => self.power_off(S::SwitchedOn),
                _ => return Err(self.wrong_state(kind)),
            },
            RequestKind::EnableOperation => match s {
                S::SwitchedOn => {
                    self.restart_at(m);
                    self.state = S::OperationEnabled;
                }
                S::QuickStopActive => {
                    // Hold where the quick stop left it (or is leaving it: it brakes on).
                    self.otg.set_limits(move_limits(&self.p));
                    self.otg.hold();
                    self.mode = AxisMode::Hold;
                    self.state = S::OperationEnabled;
                }
                S::OperationEnabled => {}
                _ => return Err(self.wrong_state(kind)),
            },
            RequestKind::Enable => match s {
                S::SwitchOnDisabled | S::ReadyToSwitchOn | S::SwitchedOn => {
                    self.restart_at(m);
                    self.state = S::OperationEnabled;
                }
                S::QuickStopActive => {
                    self.otg.set_limits(move_limits(&self.p));
                    self.otg.hold();
                    self.mode = AxisMode::Hold;
                    self.state = S::OperationEnabled;
                }
                S::OperationEnabled => {}
                _ => {
                    return Err(refuse(
                        Refusal::WrongState,
                        format!("no enable from {}: reset the fault first", s.name()),
                    ))
                }
            },
            RequestKind::DisableOperation => match s {
                S::OperationEnabled => self.power_off(S::SwitchedOn),
                _ => return Err(self.wrong_state(kind)),
            },
            RequestKind::DisableVoltage => match s {
                S::Fault | S::FaultReactionActive | S::NotReadyToSwitchOn => {
                    return Err(self.wrong_state(kind))
                }
                _ => self.power_off(S::SwitchOnDisabled),
            },
            RequestKind::QuickStop => match s {
                S::OperationEnabled => self.quick_stop(m),
                S::QuickStopActive => {}
                S::ReadyToSwitchOn | S::SwitchedOn => self.power_off(S::SwitchOnDisabled),
                _ => return Err(self.wrong_state(kind)),
            },
            RequestKind::FaultReset => {
                if s == S::Fault || m.device_fault != 0 {
                    // The axis leaves Fault once the device's own fault is cleared too (its
                    // node asks the device to reset): at this tick, or when it clears.
                    self.reset_pending = true;
                }
            }
            RequestKind::Move => {
                self.enabled("a move")?;
                let limits = self.limits_of(r)?;
                if !r.target_rad.is_finite() {
                    return Err(refuse(
                        Refusal::NotFinite,
                        format!("target {}", r.target_rad),
                    ));
                }
                let target = if r.flags & request_flags::RELATIVE != 0 {
                    self.relative_base() + r.target_rad
                } else {
                    r.target_rad
                };
                if !target.is_finite() {
                    return Err(refuse(
                        Refusal::NotFinite,
                        format!(
                            "target {} relative to {}",
                            r.target_rad,
                            self.relative_base()
                        ),
                    ));
                }
                self.within_soft_limits(target)?;
                let busy = self.mode == AxisMode::ProfilePosition && !self.otg.done();
                if r.flags & request_flags::AFTER_CURRENT != 0 && busy {
                    // CiA 402's single set-point buffer: one move waits, a second is refused
                    // until it is free (status word bit 12 says so).
                    if let Some((queued, _)) = self.queued {
                        return Err(refuse(
                            Refusal::BufferFull,
                            format!(
                                "the set-point buffer holds the move to {queued} rad (status bit 12)"
                            ),
                        ));
                    }
                    // It starts at rest on the current move's target.
                    let from = Reference {
                        theta: self.target,
                        omega: 0.0,
                        alpha: 0.0,
                    };
                    self.plannable(from, Goal::Position(target), limits, "the move")?;
                    self.queued = Some((target, limits));
                } else {
                    let from = self.takeover_state();
                    self.plannable(from, Goal::Position(target), limits, "the move")?;
                    // Changed at once: a move waiting in the buffer is dropped with the one
                    // it waited for.
                    self.queued = None;
                    self.start_move(target, limits, m);
                }
            }
            RequestKind::Jog => {
                self.enabled("a jog")?;
                let v = r.velocity_rad_s;
                if !v.is_finite() {
                    return Err(refuse(Refusal::NotFinite, format!("velocity {v}")));
                }
                if v.abs() > self.p.v_max_rad_s {
                    return Err(refuse(
                        Refusal::LimitAboveAxis,
                        format!(
                            "jog at {v} rad/s exceeds the axis's {} rad/s",
                            self.p.v_max_rad_s
                        ),
                    ));
                }
                let floor = self.p.v_max_rad_s * LIMIT_FLOOR;
                if v != 0.0 && v.abs() < floor {
                    return Err(refuse(
                        Refusal::TooSlow,
                        format!(
                            "jog at {} rad/s is below the axis's least speed, {} rad/s",
                            short(v),
                            short(floor)
                        ),
                    ));
                }
                let mut limits = self.limits_of(r)?;
                let goal = Goal::Velocity(v);
                let speed = Limits {
                    v: if v == 0.0 { limits.v } else { v.abs() },
                    ..limits
                };
                let from = self.takeover_state();
                self.plannable(from, goal, speed, "the jog's change of speed")?;
                self.take_over(m);
                self.queued = None;
                if v == 0.0 {
                    self.otg.set_limits(limits);
                    self.otg.set_goal(Goal::Velocity(0.0));
                } else {
                    // A jog is a move to the soft limit at the jog's speed: it stops there.
                    limits.v = v.abs();
                    let edge = if v > 0.0 {
                        self.p.position_max_rad
                    } else {
                        self.p.position_min_rad
                    };
                    self.otg.set_limits(limits);
                    self.otg.set_goal(Goal::Position(edge));
                    self.target = edge;
                    // Open-ended: it runs while its client renews it (the program's needs
                    // none).
                    if source == Source::Client {
                        self.jog_client = Some(r.client);
                        self.jog_renewed = m.t;
                    }
                    self.warning &= !axis_warnings::JOG_LOST;
                }
                self.mode = AxisMode::ProfileVelocity;
            }
            RequestKind::Stop => {
                self.enabled("a stop")?;
                let limits = self.limits_of(r)?;
                let from = self.takeover_state();
                self.plannable(from, Goal::Velocity(0.0), limits, "the stop")?;
                self.take_over(m);
                self.queued = None;
                self.otg.set_limits(limits);
                self.otg.set_goal(Goal::Velocity(0.0));
                self.mode = AxisMode::Hold;
            }
            RequestKind::StreamStart => {
                let lead = self.stream_start(r)?;
                self.take_over(m);
                self.queued = None;
                // The stream's own limits: the axis's, the envelope around whatever it asks.
                self.otg.set_limits(axis_limits(&self.p));
                // Until the stream plays (its lead), a move or a jog it interrupts brakes to
                // a hold, and the stream is followed from wherever that has got to.
                self.otg.hold();
                self.stream_id = Some(r.seq);
                self.stream_lead = lead;
                self.stream_started = m.t;
                // The stream's warnings are this stream's.
                self.warning &= !(axis_warnings::STREAM_UNDERRUN
                    | axis_warnings::STREAM_LIMITED
                    | axis_warnings::STREAM_LOST);
                self.followed = self.otg.state();
                self.followed_jerk = self.otg.jerk();
                self.mode = AxisMode::CyclicPosition;
            }
            RequestKind::StreamEnd => {
                if self.mode != AxisMode::CyclicPosition {
                    return Err(refuse(Refusal::StreamNotStarted, "no stream is running"));
                }
                self.take_over(m);
                self.otg.set_limits(move_limits(&self.p));
                self.otg.hold();
                self.mode = AxisMode::Hold;
            }
            RequestKind::SetPosition => {
                let moving =
                    self.state.outputs_on() && (!self.otg.done() || self.reference.omega != 0.0);
                if moving {
                    return Err(refuse(
                        Refusal::Moving,
                        "set-position needs the axis at a standstill",
                    ));
                }
                if !r.target_rad.is_finite() {
                    return Err(refuse(
                        Refusal::NotFinite,
                        format!("position {}", r.target_rad),
                    ));
                }
                self.within_soft_limits(r.target_rad)?;
                let shift = r.target_rad - self.position(m);
                self.offset += shift;
                let at = Reference {
                    theta: self.reference.theta + shift,
                    omega: 0.0,
                    alpha: 0.0,
                };
                self.otg.restart(at);
                self.otg_t = m.t;
                self.reference = at;
                self.target += shift;
                self.move_target = self.move_target.map(|t| t + shift);
            }
        }
        Ok(())
    }

    fn start_move(&mut self, target: f64, limits: Limits, m: &Measured) {
        self.take_over(m);
        self.otg.set_limits(limits);
        self.otg.set_goal(Goal::Position(target));
        self.target = target;
        self.move_target = Some(target);
        self.mode = AxisMode::ProfilePosition;
        self.move_id += 1;
    }

    /// A point of the running stream (the stream of its `StreamStart`); one of another
    /// stream is not this axis's to take.
    pub fn stream_point(&mut self, p: &AxisStreamPoint, m: &Measured) -> Result<(), Refused> {
        if self.mode != AxisMode::CyclicPosition || self.stream_id != Some(p.stream) {
            return Err(self.point_refused(refuse(
                Refusal::StreamNotStarted,
                format!("point of stream {} while none of it runs", p.stream),
            )));
        }
        let point = Point {
            t: p.t_s,
            theta: p.theta_rad,
            omega: (p.flags & stepdrive_shared::axis::point_flags::HAS_OMEGA != 0)
                .then_some(p.omega_rad_s),
            torque_ff: (p.flags & stepdrive_shared::axis::point_flags::HAS_TORQUE != 0)
                .then_some(p.torque_ff_nm),
        };
        let (lo, hi) = (self.p.position_min_rad, self.p.position_max_rad);
        if !(lo..=hi).contains(&point.theta) && point.theta.is_finite() {
            // Refused like a move's target: the stream is never played out there.
            return Err(self.point_refused(refuse(
                Refusal::OutsideSoftLimits,
                format!(
                    "point at t = {} s: {} rad is outside the soft limits [{lo}, {hi}] rad",
                    point.t, point.theta
                ),
            )));
        }
        if self.stream_origin.is_none() && point.t.is_finite() {
            if !self.origin_from_group {
                self.stream_origin = Some((m.t, point.t));
            } else if self.stream_first.is_none() {
                self.stream_first = Some(point.t);
            }
        }
        self.stream.push(point).map_err(|e| {
            let refusal = match e {
                PointError::NotFinite { .. } => Refusal::NotFinite,
                PointError::Backwards { .. } => Refusal::StreamOutOfOrder,
                PointError::Full => Refusal::BufferFull,
            };
            self.point_refused(refuse(refusal, e.to_string()))
        })
    }

    fn point_refused(&mut self, r: Refused) -> Refused {
        self.refused_points += 1;
        self.last_refusal = r.refusal;
        r
    }

    /// Steps the trajectory generator to time `t` (whole periods), returns its state
    /// there.
    fn otg_to(&mut self, t: f64) -> Result<Reference, OtgError> {
        let n = ((t - self.otg_t) / self.period).round();
        let mut s = self.otg.state();
        if n >= 1.0 {
            for _ in 0..(n as u64).min(1000) {
                s = self.otg.step()?;
            }
            self.otg_t += n * self.period;
        }
        // A realtime tick's time is off the generator's grid by whole samples (its clock
        // is not the samples'): told with its jerk, α_d keeps to the trajectory there. Told
        // without it, α_d was j·dt off through every jerk phase, up to 0.5 rad/s² at
        // 2000 rad/s³, and the rotor rang to 3e-5 rad at a 20 rad move's corners.
        Ok(s.after_jerk(t - self.otg_t, self.otg.jerk()))
    }

    /// The stream's target at played time `played`: its interpolated state (within the
    /// soft limits), or, run dry, its last state carried on at its speed.
    fn stream_target(&mut self, played: f64) -> Option<Reference> {
        let target = match self.stream.play(played) {
            Play::Waiting => return None,
            Play::At {
                reference,
                torque_ff,
            } => {
                self.torque_ff = torque_ff;
                reference
            }
            Play::Dry { by_s, last } => {
                self.warning |= axis_warnings::STREAM_UNDERRUN;
                Reference {
                    theta: last.theta + last.omega * by_s,
                    omega: last.omega,
                    alpha: 0.0,
                }
            }
        };
        let (lo, hi) = (self.p.position_min_rad, self.p.position_max_rad);
        if target.theta < lo || target.theta > hi {
            self.warning |= axis_warnings::SOFT_LIMIT;
            return Some(Reference {
                theta: target.theta.clamp(lo, hi),
                omega: 0.0,
                alpha: 0.0,
            });
        }
        Some(target)
    }

    /// The stream time played at axis time `t`: the lead behind the first point's arrival
    /// (at axis time `origin`, stream time `first`).
    fn played(&self, t: f64, origin: f64, first: f64) -> f64 {
        t - origin - self.stream_lead + first
    }

    /// The stream followed to time `t` within the axis's limits ([`track`]); a stream dry
    /// past its watchdog is quick-stopped.
    fn stream_to(&mut self, m: &Measured) -> Result<Reference, OtgError> {
        let Some((origin, first)) = self.stream_origin else {
            // A stream whose first point does not come is lost as one that stops coming
            // (its client died or never sent one): quick-stopped a lead and a timeout after
            // its start, or after the brake let go.
            let since = self
                .stream_started
                .max(self.enabled_at + self.p.brake_release_s);
            if m.t - since > self.stream_lead + self.p.stream_timeout_s {
                self.warning |= axis_warnings::STREAM_LOST;
                self.quick_stop(m);
                return self.otg_to(m.t);
            }
            // No point yet: the trajectory the stream found runs on (a move or a jog it
            // interrupted brakes to a hold), and the stream is followed from where it is.
            let r = self.otg_to(m.t)?;
            self.followed = self.otg.state();
            self.followed_jerk = self.otg.jerk();
            return Ok(r);
        };
        let n = ((m.t - self.otg_t) / self.period).round();
        let limits = axis_limits(&self.p);
        let mut s = self.followed;
        let mut jerk = self.followed_jerk;
        for _ in 0..(n.max(0.0) as u64).min(1000) {
            // Each period from where the stream is at its start to where it is at its end.
            let played = self.played(self.otg_t, origin, first);
            let (Some(now), Some(next)) = (
                self.stream_target(played),
                self.stream_target(played + self.period),
            ) else {
                // Not played yet (its lead): as before the first point.
                s = self.otg.step()?;
                jerk = self.otg.jerk();
                self.otg_t += self.period;
                continue;
            };
            let (after, j) =
                track::follow(s, now, next, limits, track::DEFAULT_BANDWIDTH, self.period);
            // Off the stream by more than the target window: not a rounding, nor the few
            // µrad between where a path starts and where the setpoint stood.
            if (after.theta - next.theta).abs() > self.p.target_window_rad {
                self.warning |= axis_warnings::STREAM_LIMITED;
            }
            s = after;
            jerk = j;
            self.otg_t += self.period;
        }
        self.followed = s;
        self.followed_jerk = jerk;
        let last = self.stream.last_t().unwrap_or(first);
        let played = self.played(m.t, origin, first);
        if played - last > self.p.stream_timeout_s {
            self.warning |= axis_warnings::STREAM_LOST;
            // The quick stop starts from where the stream left the setpoint.
            self.reference = s.after_jerk(m.t - self.otg_t, jerk);
            self.quick_stop(m);
            return self.otg_to(m.t);
        }
        Ok(s.after_jerk(m.t - self.otg_t, jerk))
    }

    /// A coordinated move's target checked as a move's is (enabled, finite, within the
    /// soft limits), nothing applied: the state the group plans from (the last tick's
    /// setpoint, in axis coordinates; the move's first step is the next tick's).
    fn coordinated_start(&self, target: f64) -> Result<Reference, Refused> {
        self.enabled("a coordinated move")?;
        if !target.is_finite() {
            return Err(refuse(Refusal::NotFinite, format!("target {target}")));
        }
        self.within_soft_limits(target)?;
        Ok(self.reference)
    }

    /// The group's move takes the axis towards `target` (checked by
    /// [`Self::coordinated_start`]) from the next tick on.
    /// A coordinated move's part, started by the group: the last command in the status
    /// (a client waits for its move by its sequence number).
    pub fn took_part(&mut self, r: &AxisRequest) {
        self.last_kind = r.kind;
        self.last_seq = r.seq;
    }

    fn enter_coordinated(&mut self, target: f64, m: &Measured) {
        self.take_over(m);
        self.queued = None;
        self.target = target;
        self.move_target = Some(target);
        self.mode = AxisMode::Coordinated;
        self.coordinated = true;
        self.move_id += 1;
    }

    /// Still in the group's move (no command, quick stop or fault took it out).
    fn in_coordinated(&self) -> bool {
        self.coordinated && self.mode == AxisMode::Coordinated && self.state.outputs_on()
    }

    /// The group's state for the next tick and the jerk that led to it; `last`: the move
    /// ends there, at rest on its target, and the generator holds it from then on.
    /// `for_t`: the tick time the state is meant for (an axis whose sample is of another
    /// instant takes the state there, along the same jerk; NaN: at its own sample, its
    /// clock not the group's).
    fn follow_coordinated(&mut self, at: Reference, jerk: f64, last: bool, for_t: f64) {
        self.coordinated_next = Some((at, jerk, for_t));
        if last {
            self.otg.set_limits(move_limits(&self.p));
            self.otg.restart(at);
            self.coordinated = false;
        }
    }

    /// Quick stop from Operation enabled (the group's stop policy); false if the axis was
    /// not enabled.
    fn quick_stop_if_enabled(&mut self, m: &Measured) -> bool {
        if self.state != AxisState::OperationEnabled {
            return false;
        }
        self.quick_stop(m);
        true
    }

    /// One tick at the measured state `m`: the device's faults, the source's setpoint, the
    /// envelope's checks. Returns what the torque law is to follow.
    pub fn tick(&mut self, m: &Measured) -> Setpoint {
        self.t = m.t;
        // The scenario's profile is the paper's experiment, judged by the monitor (step-out,
        // the device's faults), as it always was: the envelope watches the commanded
        // sources.
        let experiment = self.mode == AxisMode::ScenarioProfile;
        if !experiment {
            if m.device_fault != 0 && self.state != AxisState::Fault {
                self.enter_fault(axis_faults::DRIVE);
            }
            if m.setpoint_stale && self.state.outputs_on() {
                self.enter_fault(axis_faults::SETPOINT_STALE);
            }
        }
        if self.jog_client.is_some()
            && self.mode == AxisMode::ProfileVelocity
            && self.state == AxisState::OperationEnabled
            && m.t - self.jog_renewed > self.p.jog_timeout_s
        {
            // The jog's client went silent (died, hung, lost its link): stop, whatever it
            // declared.
            self.warning |= axis_warnings::JOG_LOST;
            self.quick_stop(m);
        }
        if self.reset_pending && m.device_fault == 0 {
            self.reset_pending = false;
            self.fault = 0;
            self.warning = 0;
            self.power_off(AxisState::SwitchOnDisabled);
        }
        let reference = match self.mode {
            AxisMode::ScenarioProfile => match &self.profile {
                Some(p) => p.at(m.t),
                None => self.reference,
            },
            _ if !self.state.outputs_on() => {
                // Outputs off: the setpoint follows the rotor, so that an enable starts
                // where it stands.
                let at = Reference {
                    theta: self.position(m),
                    omega: 0.0,
                    alpha: 0.0,
                };
                self.otg.restart(at);
                self.otg_t = m.t;
                at
            }
            _ if !self.brake_released(m.t) => {
                // The brake still holds the rotor: the setpoint stays where the enable put
                // it, and what was commanded meanwhile starts when the brake has let go.
                self.otg_t = m.t;
                self.reference
            }
            AxisMode::CyclicPosition => match self.stream_to(m) {
                Ok(r) => r,
                Err(e) => self.trajectory_failed(e),
            },
            AxisMode::Coordinated if self.coordinated || self.coordinated_next.is_some() => {
                // A tick the group gave no state for (on the wall clock: its step rounded to
                // none, or axis 0 had no new sample) carries the last one on to this
                // sample's time: standing on it, θ_d fell a tick behind the rotor.
                let (at, jerk, for_t) = self.coordinated_next.take().unwrap_or((
                    self.reference,
                    self.coordinated_jerk,
                    self.otg_t,
                ));
                // On the wall clock the axes' newest samples can be one apart: each takes
                // the move where it is at its own sample's time.
                let skew = m.t - for_t;
                let at = if skew.abs() > 1e-9 {
                    at.after_jerk(skew, jerk)
                } else {
                    at
                };
                self.otg_t = m.t;
                self.coordinated_jerk = jerk;
                at
            }
            _ => match self.otg_to(m.t) {
                Ok(r) => r,
                Err(e) => self.trajectory_failed(e),
            },
        };
        self.reference = reference;
        if self.mode == AxisMode::ProfilePosition && self.otg.done() {
            if let Some((target, limits)) = self.queued.take() {
                self.start_move(target, limits, m);
            }
        }
        if self.mode == AxisMode::ProfileVelocity && self.otg.done() && self.reference.omega == 0.0
        {
            // A jog that reached its soft limit stands there.
            if self.target == self.p.position_max_rad || self.target == self.p.position_min_rad {
                self.warning |= axis_warnings::SOFT_LIMIT;
            }
        }
        if !experiment {
            self.watch_following(m);
        }
        Setpoint {
            reference: Reference {
                theta: reference.theta - self.offset,
                ..reference
            },
            outputs_on: self.state.outputs_on(),
            torque_ff: if self.mode == AxisMode::CyclicPosition {
                self.torque_ff
            } else {
                0.0
            },
            epoch: self.epoch,
            smooth: self.mode != AxisMode::ScenarioProfile,
            jerk: match self.mode {
                AxisMode::ScenarioProfile => 0.0,
                _ if !self.state.outputs_on() => 0.0,
                AxisMode::CyclicPosition => self.followed_jerk,
                AxisMode::Coordinated if self.coordinated => self.coordinated_jerk,
                _ => self.otg.jerk(),
            },
            brake_released: self.brake_released(m.t),
        }
    }

    fn trajectory_failed(&mut self, e: OtgError) -> Reference {
        let _ = e;
        self.enter_fault(axis_faults::TRAJECTORY);
        self.reference
    }

    /// The following-error window and time: beyond the window for longer than the time,
    /// the axis faults with its outputs off.
    fn watch_following(&mut self, m: &Measured) {
        if !self.state.outputs_on() {
            self.following_since = None;
            return;
        }
        let e = self.reference.theta - self.position(m);
        if e.abs() <= self.p.following_error_window_rad {
            self.following_since = None;
            return;
        }
        let since = *self.following_since.get_or_insert(m.t);
        if m.t - since >= self.p.following_error_time_s {
            self.enter_fault(axis_faults::FOLLOWING_ERROR);
        }
    }

    /// Notes that the torque asked was limited (a warning, not silent).
    pub fn torque_limited(&mut self, limited: bool) {
        if limited {
            self.warning |= axis_warnings::TORQUE_LIMITED;
        }
    }

    /// The torque limit of the envelope, N·m.
    pub fn torque_max(&self) -> f64 {
        self.p.torque_max_nm
    }

    /// The status at the tick just run (`m` its measured state, `torque` what (12) asked).
    pub fn status(&mut self, m: &Measured, torque: f64) -> AxisStatus {
        let theta = self.position(m);
        let e = self.reference.theta - theta;
        let standing = self.otg.done();
        let played = self
            .stream_origin
            .filter(|_| self.mode == AxisMode::CyclicPosition)
            .map(|(origin, first)| self.played(m.t, origin, first));
        let reached = match self.mode {
            AxisMode::ProfilePosition => {
                standing && (self.target - theta).abs() <= self.p.target_window_rad
            }
            AxisMode::ProfileVelocity => standing,
            AxisMode::QuickStop => standing && self.reference.omega == 0.0,
            AxisMode::Hold => e.abs() <= self.p.target_window_rad,
            AxisMode::Coordinated => {
                // The group's last step puts the setpoint on the target at rest.
                !self.coordinated
                    && self.reference.omega == 0.0
                    && (self.target - theta).abs() <= self.p.target_window_rad
            }
            AxisMode::CyclicPosition | AxisMode::ScenarioProfile => false,
        };
        let mut word = self.state.statusword();
        if reached {
            word |= status_bits::TARGET_REACHED;
        }
        if self.queued.is_some() {
            word |= status_bits::SETPOINT_ACK;
        }
        if self.warning != 0 {
            word |= status_bits::WARNING;
        }
        if self.fault & axis_faults::FOLLOWING_ERROR != 0 {
            word |= status_bits::FOLLOWING_ERROR;
        }
        if self.warning & (axis_warnings::TORQUE_LIMITED | axis_warnings::SOFT_LIMIT) != 0 {
            word |= status_bits::INTERNAL_LIMIT;
        }
        if !self.brake_released(m.t) {
            word |= status_bits::BRAKE_APPLIED;
        }
        AxisStatus {
            axis: 0,
            state: self.state as u32,
            tick: 0,
            t_s: m.t,
            publish_time_ns: 0,
            statusword: u32::from(word),
            mode: self.mode as u32,
            theta_rad: theta,
            omega_rad_s: m.omega,
            torque_nm: torque,
            following_error_rad: e,
            theta_d_rad: self.reference.theta,
            omega_d_rad_s: self.reference.omega,
            alpha_d_rad_s2: self.reference.alpha,
            target_rad: self.target,
            fault: self.fault,
            warning: self.warning,
            device_fault: m.device_fault,
            last_kind: self.last_kind,
            last_seq: self.last_seq,
            move_id: self.move_id,
            refused_points: self.refused_points,
            last_refusal: self.last_refusal as u32,
            epoch: self.epoch,
            stream_time_s: played.unwrap_or(f64::NAN),
            stream_ahead_s: played
                .zip(self.stream.last_t())
                .map_or(f64::NAN, |(p, last)| last - p),
            stream_lead_s: if self.mode == AxisMode::CyclicPosition {
                self.stream_lead
            } else {
                f64::NAN
            },
            contour_rad: f64::NAN,
        }
    }
}

/// A move's limits when it gives none.
pub fn move_limits(p: &AxisParams) -> Limits {
    Limits {
        v: p.move_v_rad_s,
        a: p.move_a_rad_s2,
        j: p.move_j_rad_s3,
    }
}

/// The most the axis allows.
pub fn axis_limits(p: &AxisParams) -> Limits {
    Limits {
        v: p.v_max_rad_s,
        a: p.a_max_rad_s2,
        j: p.j_max_rad_s3,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const T: f64 = 500e-6;

    fn request(kind: RequestKind, seq: u64) -> AxisRequest {
        AxisRequest {
            kind: kind as u32,
            seq,
            ..Default::default()
        }
    }

    /// The rotor exactly where the setpoint says (a perfect plant), at time `t`.
    fn on(t: f64, r: &Reference) -> Measured {
        Measured {
            t,
            theta: r.theta,
            omega: r.omega,
            ..Default::default()
        }
    }

    /// Two axes of one stream whose first points come 5 ms apart play one stream time at
    /// every tick once the group gives them one origin; on its own the early one would play
    /// 5 ms ahead.
    #[test]
    fn the_axes_of_a_stream_of_several_play_one_stream_time() {
        let p = AxisParams::default();
        let mut a = Axis::new(&p, T);
        let mut b = Axis::new(&p, T);
        let r = Reference::default();
        for axis in [&mut a, &mut b] {
            axis.request(&request(RequestKind::Enable, 1), &on(0.0, &r))
                .expect("enable");
            axis.request(&request(RequestKind::StreamStart, 2), &on(0.0, &r))
                .expect("stream");
            axis.stream_in_group();
            assert!(axis.stream_awaits_origin());
        }
        let point = |k: u64| AxisStreamPoint {
            stream: 2,
            seq: k,
            t_s: k as f64 * 1e-3,
            theta_rad: 1e-3 * k as f64,
            ..Default::default()
        };
        let mut played = (Vec::new(), Vec::new());
        // Each rotor exactly on its setpoint.
        let (mut ra, mut rb) = (r, r);
        for tick in 0..400u64 {
            let t = tick as f64 * T;
            let (ma, mb) = (on(t, &ra), on(t, &rb));
            // a's points from tick 0, b's from tick 10 (5 ms), each at 1 kHz from t_s = 0.
            if tick % 2 == 0 {
                a.stream_point(&point(tick / 2), &ma).expect("a's point");
            }
            if tick >= 10 && tick % 2 == 0 {
                b.stream_point(&point((tick - 10) / 2), &mb)
                    .expect("b's point");
            }
            if tick == 11 {
                assert_eq!(a.stream_first_point(), Some(0.0));
                assert_eq!(b.stream_first_point(), Some(0.0));
                a.start_stream_at(t, 0.0);
                b.start_stream_at(t, 0.0);
            }
            if tick < 11 {
                assert_eq!(b.stream_first_point(), (tick >= 10).then_some(0.0));
            }
            ra = a.tick(&ma).reference;
            rb = b.tick(&mb).reference;
            played.0.push(a.status(&ma, 0.0).stream_time_s);
            played.1.push(b.status(&mb, 0.0).stream_time_s);
        }
        let lead_ticks = (p.stream_lead_s / T).round() as usize;
        let from = 11 + lead_ticks;
        assert!(
            played.0[..11].iter().all(|x| x.is_nan()),
            "a played before its origin"
        );
        assert!(played.0[from..].iter().all(|x| x.is_finite()));
        assert_eq!(played.0[from..], played.1[from..]);
    }

    /// A stream of 2 sin 2πt at 1 kHz, each point sent at its time: after 0.2 s the setpoint
    /// is on the stream (played its lead behind) within 5e-6 rad, within the limits all the
    /// way.
    #[test]
    fn a_sine_stream_is_followed_within_the_limits() {
        let p = AxisParams::default();
        let mut axis = Axis::new(&p, T);
        let mut r = Reference::default();
        axis.request(&request(RequestKind::Enable, 1), &on(0.0, &r))
            .expect("enable");
        axis.request(&request(RequestKind::StreamStart, 2), &on(0.0, &r))
            .expect("stream");
        let sine = |t: f64| 2.0 * (std::f64::consts::TAU * t).sin();
        let mut sent = 0u64;
        let mut worst: f64 = 0.0;
        let mut prev = r;
        for k in 0..6000u64 {
            let t = k as f64 * T;
            while (sent as f64) * 1e-3 <= t && sent <= 4000 {
                let ts = sent as f64 * 1e-3;
                let point = AxisStreamPoint {
                    stream: 2,
                    seq: sent,
                    t_s: ts,
                    theta_rad: sine(ts),
                    flags: 0,
                    ..Default::default()
                };
                axis.stream_point(&point, &on(t, &r)).expect("in order");
                sent += 1;
            }
            let sp = axis.tick(&on(t, &r));
            assert_eq!(
                axis.state(),
                AxisState::OperationEnabled,
                "t {t}: {:#x}",
                axis.warning()
            );
            r = sp.reference;
            assert!(r.omega.abs() <= p.v_max_rad_s * (1.0 + 1e-9));
            assert!(r.alpha.abs() <= p.a_max_rad_s2 * (1.0 + 1e-9));
            if k > 0 {
                let jerk = (r.alpha - prev.alpha) / T;
                assert!(
                    jerk.abs() <= p.j_max_rad_s3 * (1.0 + 1e-9),
                    "t {t}: jerk {jerk}"
                );
            }
            prev = r;
            let played = t - p.stream_lead_s;
            if (0.2..=2.5).contains(&played) {
                worst = worst.max((r.theta - sine(played)).abs());
            }
        }
        // 3.9e-7 measured; a cubic Hermite's acceleration jumps put it at 7.5e-5.
        assert!(worst < 5e-6, "{worst:e}");
    }

    /// The holding brake: applied while the axis is disabled; after an enable the setpoint
    /// stays where the rotor stood, outputs on, for the brake's release time; a move asked
    /// meanwhile starts once it has let go; a disable applies it again at once.
    #[test]
    fn an_enable_holds_the_setpoint_until_the_brake_has_released() {
        let p = AxisParams::default();
        let mut axis = Axis::new(&p, T);
        let at = |t: f64| Measured {
            t,
            theta: 0.4,
            ..Default::default()
        };
        let sp = axis.tick(&at(0.0));
        assert!(!sp.outputs_on && !sp.brake_released);
        axis.request(&request(RequestKind::Enable, 1), &at(0.0))
            .expect("enable");
        let to = AxisRequest {
            target_rad: 1.4,
            ..request(RequestKind::Move, 2)
        };
        axis.request(&to, &at(0.0))
            .expect("a move while the brake opens");
        let held = Reference {
            theta: 0.4,
            omega: 0.0,
            alpha: 0.0,
        };
        let mut k = 0u32;
        let released_at = loop {
            let t = f64::from(k) * T;
            let sp = axis.tick(&at(t));
            assert!(sp.outputs_on);
            let word = axis.status(&at(t), 0.0).statusword as u16;
            assert_eq!(
                word & status_bits::BRAKE_APPLIED == 0,
                sp.brake_released,
                "t {t}"
            );
            if sp.brake_released {
                break t;
            }
            assert_eq!(sp.reference, held, "t {t}");
            k += 1;
            assert!(k < 1000, "the brake never released");
        };
        assert!(
            (p.brake_release_s..p.brake_release_s + T).contains(&released_at),
            "released at {released_at} s"
        );
        let sp = axis.tick(&at(released_at + 10.0 * T));
        assert!(sp.reference.theta > 0.4 && sp.reference.omega > 0.0);
        axis.request(
            &request(RequestKind::DisableVoltage, 3),
            &at(released_at + 11.0 * T),
        )
        .expect("disable");
        let sp = axis.tick(&at(released_at + 11.0 * T));
        assert!(!sp.outputs_on && !sp.brake_released);
    }

    /// Ticks off the trajectory's grid (a realtime position loop's clock is not the
    /// samples'): 0.2 ms after each step, the setpoint is the trajectory at the tick's own
    /// time. In a move's first jerk phase from rest that is α = j t, ω = j t²/2,
    /// θ = j t³/6 (told without the jerk, α_d was j × 0.2 ms = 1 rad/s² behind).
    #[test]
    fn ticks_off_the_grid_are_told_the_trajectory_at_their_own_time() {
        let p = AxisParams {
            brake_release_s: 0.0,
            ..AxisParams::default()
        };
        let mut axis = Axis::new(&p, T);
        let rest = Measured::default();
        axis.request(&request(RequestKind::Enable, 1), &rest)
            .expect("enable");
        let to = AxisRequest {
            target_rad: 10.0,
            ..request(RequestKind::Move, 2)
        };
        axis.request(&to, &rest).expect("move");
        axis.tick(&rest);
        let (j, off) = (p.move_j_rad_s3, 0.2e-3);
        let first_phase = p.move_a_rad_s2 / j;
        let mut judged = 0;
        for n in 1..100u32 {
            let t = f64::from(n) * T + off;
            if t >= first_phase {
                break;
            }
            let r = axis.tick(&Measured { t, ..rest }).reference;
            assert!((r.alpha - j * t).abs() < 1e-9, "t {t}: α_d {}", r.alpha);
            assert!((r.omega - j * t * t / 2.0).abs() < 1e-12, "t {t}");
            assert!((r.theta - j * t * t * t / 6.0).abs() < 1e-14, "t {t}");
            judged += 1;
        }
        assert!(judged > 30, "{judged}");
    }

    fn enabled_axis() -> (Axis, AxisParams) {
        let p = AxisParams::default();
        let mut axis = Axis::new(&p, T);
        axis.request(
            &request(RequestKind::Enable, 1),
            &on(0.0, &Reference::default()),
        )
        .expect("enable");
        (axis, p)
    }

    /// An enabled axis told at t = 0, at rest, to jog at 13 rad/s.
    fn jogging_axis() -> (Axis, AxisParams) {
        let (mut axis, p) = enabled_axis();
        let jog = AxisRequest {
            velocity_rad_s: 13.0,
            ..request(RequestKind::Jog, 2)
        };
        axis.request(&jog, &on(0.0, &Reference::default()))
            .expect("jog");
        (axis, p)
    }

    fn move_to(target: f64, seq: u64) -> AxisRequest {
        AxisRequest {
            target_rad: target,
            ..request(RequestKind::Move, seq)
        }
    }

    /// The control word's transitions walk CiA 402's states, the status word mirrors each,
    /// and a transition the state machine does not have is refused by name.
    #[test]
    fn the_power_state_machine_follows_cia_402() {
        let p = AxisParams::default();
        let mut axis = Axis::new(&p, T);
        let m = on(0.0, &Reference::default());
        let word = |a: &mut Axis| a.status(&m, 0.0).statusword as u16 & 0x6F;
        assert_eq!(axis.state(), AxisState::SwitchOnDisabled);
        assert_eq!(word(&mut axis) & 0x4F, 0x40);
        let e = axis
            .request(&request(RequestKind::EnableOperation, 1), &m)
            .expect_err("no enable operation from Switch on disabled");
        assert_eq!(e.refusal, Refusal::WrongState);
        assert_eq!(axis.state(), AxisState::SwitchOnDisabled);
        let walk = [
            (RequestKind::Shutdown, AxisState::ReadyToSwitchOn, 0x21),
            (RequestKind::SwitchOn, AxisState::SwitchedOn, 0x23),
            (
                RequestKind::EnableOperation,
                AxisState::OperationEnabled,
                0x27,
            ),
            (RequestKind::QuickStop, AxisState::QuickStopActive, 0x07),
            (
                RequestKind::EnableOperation,
                AxisState::OperationEnabled,
                0x27,
            ),
            (RequestKind::DisableOperation, AxisState::SwitchedOn, 0x23),
            (
                RequestKind::DisableVoltage,
                AxisState::SwitchOnDisabled,
                0x40,
            ),
        ];
        for (i, (kind, to, sw)) in walk.into_iter().enumerate() {
            axis.request(&request(kind, i as u64 + 2), &m)
                .unwrap_or_else(|e| panic!("{kind:?}: {}", e.text));
            axis.tick(&m);
            assert_eq!(axis.state(), to, "{kind:?}");
            assert_eq!(word(&mut axis), sw, "{kind:?}");
        }
    }

    /// Bad commands are refused with their reason and change nothing: the target, the
    /// mode and the setpoint stay as they were.
    #[test]
    fn bad_commands_are_refused_and_nothing_is_applied() {
        let p = AxisParams::default();
        let m = on(0.0, &Reference::default());
        let mut disabled = Axis::new(&p, T);
        let e = disabled
            .request(&move_to(1.0, 1), &m)
            .expect_err("disabled");
        assert_eq!(e.refusal, Refusal::NotEnabled);
        assert!(e.text.contains("Switch on disabled"), "{}", e.text);

        let (mut axis, p) = enabled_axis();
        let before = axis.tick(&m);
        let cases: [(AxisRequest, Refusal); 7] = [
            (move_to(f64::NAN, 2), Refusal::NotFinite),
            (
                move_to(p.position_max_rad + 1.0, 3),
                Refusal::OutsideSoftLimits,
            ),
            (
                AxisRequest {
                    flags: request_flags::HAS_V,
                    v_max_rad_s: 0.0,
                    ..move_to(1.0, 4)
                },
                Refusal::LimitNotPositive,
            ),
            (
                AxisRequest {
                    flags: request_flags::HAS_A,
                    a_max_rad_s2: -5.0,
                    ..move_to(1.0, 5)
                },
                Refusal::LimitNotPositive,
            ),
            (
                AxisRequest {
                    flags: request_flags::HAS_J,
                    j_max_rad_s3: p.j_max_rad_s3 * 2.0,
                    ..move_to(1.0, 6)
                },
                Refusal::LimitAboveAxis,
            ),
            (
                AxisRequest {
                    velocity_rad_s: f64::INFINITY,
                    ..request(RequestKind::Jog, 7)
                },
                Refusal::NotFinite,
            ),
            (
                AxisRequest {
                    kind: 99,
                    ..request(RequestKind::Move, 8)
                },
                Refusal::UnknownCommand,
            ),
        ];
        for (r, why) in cases {
            let e = axis.request(&r, &m).expect_err("refused");
            assert_eq!(e.refusal, why, "{}", e.text);
            assert!(!e.text.is_empty());
        }
        let after = axis.tick(&on(T, &before.reference));
        assert_eq!(axis.mode(), AxisMode::Hold);
        assert_eq!(after.reference, before.reference);
        assert_eq!(
            axis.status(&m, 0.0).last_seq,
            1,
            "only the enable was taken"
        );
        // A status request is answered but is no command: the enable stays the last.
        axis.request(&request(RequestKind::Status, 77), &m)
            .expect("a status request is taken");
        assert_eq!(axis.status(&m, 0.0).last_seq, 1);

        // A stream whose time goes backwards: the point is refused and counted.
        axis.request(&request(RequestKind::StreamStart, 9), &m)
            .expect("stream");
        let point = |seq: u64, t_s: f64| AxisStreamPoint {
            stream: 9,
            seq,
            t_s,
            theta_rad: 0.0,
            ..Default::default()
        };
        axis.stream_point(&point(0, 1.0), &m).expect("first");
        let e = axis
            .stream_point(&point(1, 0.5), &m)
            .expect_err("backwards");
        assert_eq!(e.refusal, Refusal::StreamOutOfOrder);
        assert_eq!(axis.status(&m, 0.0).refused_points, 1);
    }

    /// A rotor that cannot follow (held where it stands while a move runs) faults the axis
    /// once the following error has been beyond the window for the window's time, outputs
    /// off; a reset and an enable start the setpoint where the rotor stands, at rest.
    #[test]
    fn a_following_error_faults_and_a_reset_enables_without_a_jump() {
        let (mut axis, p) = enabled_axis();
        let stuck = on(0.0, &Reference::default());
        axis.request(&move_to(20.0, 2), &stuck).expect("move");
        let mut beyond = None;
        let mut k = 0u64;
        while axis.state() == AxisState::OperationEnabled {
            let t = k as f64 * T;
            let m = Measured { t, ..stuck };
            let sp = axis.tick(&m);
            if beyond.is_none() && sp.reference.theta > p.following_error_window_rad {
                beyond = Some(t);
            }
            k += 1;
            assert!(k < 100_000, "never faulted");
        }
        let faulted_at = k as f64 * T - T;
        let since = beyond.expect("the error grew beyond the window");
        assert_eq!(axis.state(), AxisState::Fault);
        assert_ne!(axis.fault() & axis_faults::FOLLOWING_ERROR, 0);
        let late = faulted_at - since - p.following_error_time_s;
        assert!((0.0..=2.0 * T).contains(&late), "{late}");
        let m = on(faulted_at, &Reference::default());
        let st = axis.status(&m, 0.0);
        assert_ne!(st.statusword as u16 & status_bits::FOLLOWING_ERROR, 0);
        assert!(!axis.tick(&m).outputs_on);
        let e = axis
            .request(&request(RequestKind::Enable, 3), &m)
            .expect_err("enable from Fault");
        assert_eq!(e.refusal, Refusal::WrongState);

        // The rotor has been pushed to 0.37 rad meanwhile: the enable starts there.
        let moved = Measured {
            t: faulted_at + 0.1,
            theta: 0.37,
            ..Default::default()
        };
        axis.request(&request(RequestKind::FaultReset, 4), &moved)
            .expect("reset");
        axis.tick(&moved);
        assert_eq!(axis.state(), AxisState::SwitchOnDisabled);
        axis.request(&request(RequestKind::Enable, 5), &moved)
            .expect("enable");
        let sp = axis.tick(&moved);
        assert!(sp.outputs_on);
        assert_eq!(sp.reference.theta, 0.37);
        assert_eq!((sp.reference.omega, sp.reference.alpha), (0.0, 0.0));
    }

    /// A stream that interrupts a jog mid-ramp: during its lead the jog brakes, the setpoint
    /// moving on as its speed says (no jump when the stream takes over), and once it plays
    /// the setpoint's jerk is the followed path's own, the one (12)'s torque moves on at
    /// between ticks (a jerk left from the jog made the realtime rotor sit 1.57e-3 rad off a
    /// 100 Hz stream: 4 N·m/s of torque rate at 50 000 rad/s³).
    #[test]
    fn a_stream_that_interrupts_a_jog_takes_over_smoothly_with_its_own_jerk() {
        let (mut axis, p) = jogging_axis();
        let mut k = 0u64;
        let mut sp = axis.tick(&on(0.0, &Reference::default()));
        // Mid-ramp: the jog's acceleration still rising.
        while sp.jerk == 0.0 || k < 5 {
            k += 1;
            sp = axis.tick(&on(k as f64 * T, &sp.reference));
            assert!(k < 100, "the jog never ramped");
        }
        let mut r = sp.reference;
        let t0 = k as f64 * T;
        axis.request(&request(RequestKind::StreamStart, 3), &on(t0, &r))
            .expect("stream");
        let hold_at = r.theta + 0.05;
        let mut sent = 0u64;
        let mut prev = r;
        for _ in 0..2000 {
            k += 1;
            let t = k as f64 * T;
            while t0 + sent as f64 * 1e-3 <= t {
                let point = AxisStreamPoint {
                    stream: 3,
                    seq: sent,
                    t_s: sent as f64 * 1e-3,
                    theta_rad: hold_at,
                    ..Default::default()
                };
                axis.stream_point(&point, &on(t, &r)).expect("in order");
                sent += 1;
            }
            let sp = axis.tick(&on(t, &r));
            r = sp.reference;
            // One period on from the last state, within what the jerk limit can change.
            let theta = prev.theta + prev.omega * T + 0.5 * prev.alpha * T * T;
            assert!(
                (r.theta - theta).abs() <= p.j_max_rad_s3 * T * T * T / 6.0 + 1e-12,
                "t {t}: θ_d {} where {theta} was due",
                r.theta
            );
            if t - t0 > p.stream_lead_s + 2.0 * T {
                let jerk = (r.alpha - prev.alpha) / T;
                assert!(
                    (sp.jerk - jerk).abs() <= 1e-6 * p.j_max_rad_s3,
                    "t {t}: the setpoint's jerk {} on a path whose is {jerk}",
                    sp.jerk
                );
            }
            prev = r;
        }
        assert_eq!(axis.state(), AxisState::OperationEnabled);
        assert!(
            (r.theta - hold_at).abs() < 1e-6,
            "θ_d {} ≠ {hold_at}",
            r.theta
        );
    }

    /// A quick stop from full jog speed brakes at its own rate (jerk-limited) and holds
    /// in Quick stop active within ω/a_qs plus the jerk's ramp.
    #[test]
    fn a_quick_stop_brakes_at_its_own_rate_and_holds() {
        let (mut axis, p) = jogging_axis();
        let mut r = Reference::default();
        let mut k = 0u64;
        while r.omega < 13.0 - 1e-9 {
            r = axis.tick(&on(k as f64 * T, &r)).reference;
            k += 1;
        }
        let t0 = k as f64 * T;
        axis.request(&request(RequestKind::QuickStop, 3), &on(t0, &r))
            .expect("quick stop");
        let mut stopped_at = None;
        for _ in 0..4000 {
            let t = k as f64 * T;
            r = axis.tick(&on(t, &r)).reference;
            assert!(r.alpha >= -p.quick_stop_decel_rad_s2 * (1.0 + 1e-9));
            if stopped_at.is_none() && r.omega == 0.0 && r.alpha == 0.0 {
                stopped_at = Some(t);
            }
            k += 1;
        }
        let took = stopped_at.expect("stopped") - t0;
        let bound = 13.0 / p.quick_stop_decel_rad_s2 + p.quick_stop_decel_rad_s2 / p.j_max_rad_s3;
        assert!(took <= bound + 2.0 * T, "{took} s > {bound} s");
        assert_eq!(axis.state(), AxisState::QuickStopActive);
        let st = axis.status(&on(k as f64 * T, &r), 0.0);
        assert_ne!(st.statusword as u16 & status_bits::TARGET_REACHED, 0);
    }

    /// "After the current move": the second move waits for the first to arrive, then
    /// runs; "change immediately" re-targets on the tick it comes.
    #[test]
    fn a_move_after_the_current_waits_and_one_at_once_retargets() {
        let (mut axis, _) = enabled_axis();
        let mut r = Reference::default();
        axis.request(&move_to(1.0, 2), &on(0.0, &r)).expect("first");
        let queued = AxisRequest {
            flags: request_flags::AFTER_CURRENT,
            ..move_to(2.0, 3)
        };
        axis.request(&queued, &on(0.0, &r)).expect("queued");
        let mut reached_one = false;
        let mut k = 0u64;
        while k < 20_000 && !(r.theta == 2.0 && r.omega == 0.0) {
            r = axis.tick(&on(k as f64 * T, &r)).reference;
            reached_one |= r.theta == 1.0 && r.omega == 0.0;
            assert!(r.theta <= 2.0 + 1e-12);
            k += 1;
        }
        assert!(
            reached_one,
            "the first move ended at its target before the second"
        );
        assert_eq!(r.theta, 2.0);
        // At once: mid-move to 5, a move to 0 turns the setpoint back without a step (its
        // speed changes by no more than the acceleration limit allows in a tick).
        axis.request(&move_to(5.0, 4), &on(k as f64 * T, &r))
            .expect("move");
        for _ in 0..400 {
            r = axis.tick(&on(k as f64 * T, &r)).reference;
            k += 1;
        }
        let prev = r;
        axis.request(&move_to(0.0, 5), &on(k as f64 * T, &r))
            .expect("re-target");
        let next = axis.tick(&on(k as f64 * T, &r)).reference;
        let (_, p) = enabled_axis();
        assert!(prev.omega > 1.0, "mid-move: {prev:?}");
        assert!((next.omega - prev.omega).abs() <= p.move_a_rad_s2 * T * (1.0 + 1e-9));
        assert!(next.theta > prev.theta);
    }

    /// Ticks the axis from tick `k` for `n` ticks on a perfect plant; returns the last
    /// setpoint and the next tick.
    fn run(axis: &mut Axis, r: &mut Reference, k: &mut u64, n: u64) {
        for _ in 0..n {
            *r = axis.tick(&on(*k as f64 * T, r)).reference;
            *k += 1;
        }
    }

    fn relative(delta: f64, seq: u64) -> AxisRequest {
        AxisRequest {
            flags: request_flags::RELATIVE,
            ..move_to(delta, seq)
        }
    }

    /// Issue 44, 1: a relative move counts from the preceding move's target, else from
    /// where the axis stands; a jog's target (the soft limit) and a stop never leak into it.
    #[test]
    fn a_relative_move_counts_from_the_last_move_or_where_the_axis_stands() {
        let (mut axis, p) = jogging_axis();
        let (mut r, mut k) = (Reference::default(), 0);
        // Jog, renewed, then a stop: the axis stands somewhere short of the soft limit.
        for _ in 0..4 {
            run(&mut axis, &mut r, &mut k, 200);
            axis.request(&request(RequestKind::Status, 9), &on(k as f64 * T, &r))
                .expect("renew");
        }
        axis.request(&request(RequestKind::Stop, 10), &on(k as f64 * T, &r))
            .expect("stop");
        run(&mut axis, &mut r, &mut k, 2000);
        assert_eq!(r.omega, 0.0);
        let stood = r.theta;
        assert!(stood > 1.0 && stood < 100.0, "{stood}");
        axis.request(&relative(-1.0, 11), &on(k as f64 * T, &r))
            .expect("relative after a stop");
        let s = axis.status(&on(k as f64 * T, &r), 0.0);
        assert_eq!(
            s.target_rad,
            stood - 1.0,
            "not {}",
            p.position_max_rad - 1.0
        );
        run(&mut axis, &mut r, &mut k, 4000);
        assert_eq!(r.theta, stood - 1.0);
        // A second relative move counts from the first's target, mid-move or after.
        axis.request(&relative(2.0, 12), &on(k as f64 * T, &r))
            .expect("relative after a move");
        run(&mut axis, &mut r, &mut k, 50);
        axis.request(&relative(0.5, 13), &on(k as f64 * T, &r))
            .expect("relative mid-move");
        run(&mut axis, &mut r, &mut k, 6000);
        assert_eq!(r.theta, stood + 1.5);
        // A quick stop mid-move, then enable: from where the axis stands, not the target.
        axis.request(&move_to(40.0, 14), &on(k as f64 * T, &r))
            .expect("move");
        run(&mut axis, &mut r, &mut k, 600);
        axis.request(&request(RequestKind::QuickStop, 15), &on(k as f64 * T, &r))
            .expect("quick stop");
        run(&mut axis, &mut r, &mut k, 2000);
        axis.request(&request(RequestKind::Enable, 16), &on(k as f64 * T, &r))
            .expect("enable");
        let stood = r.theta;
        assert!(stood < 39.0, "{stood}");
        axis.request(&relative(0.5, 17), &on(k as f64 * T, &r))
            .expect("relative after a quick stop");
        assert_eq!(
            axis.status(&on(k as f64 * T, &r), 0.0).target_rad,
            stood + 0.5
        );
    }

    /// Issue 44, 8: CiA 402's single set-point buffer: a second move "after the current"
    /// is refused while one waits (status bit 12 set), taken once it is free; a move that
    /// changes at once drops the one waiting.
    #[test]
    fn the_set_point_buffer_holds_one_move_and_a_change_at_once_empties_it() {
        let (mut axis, _) = enabled_axis();
        let (mut r, mut k) = (Reference::default(), 0);
        let after = |target: f64, seq: u64| AxisRequest {
            flags: request_flags::AFTER_CURRENT,
            ..move_to(target, seq)
        };
        let bit12 = |a: &mut Axis, k: u64, r: &Reference| {
            a.status(&on(k as f64 * T, r), 0.0).statusword as u16 & status_bits::SETPOINT_ACK != 0
        };
        axis.request(&move_to(1.0, 2), &on(0.0, &r)).expect("first");
        assert!(!bit12(&mut axis, k, &r));
        axis.request(&after(2.0, 3), &on(0.0, &r)).expect("queued");
        assert!(bit12(&mut axis, k, &r));
        let e = axis
            .request(&after(3.0, 4), &on(0.0, &r))
            .expect_err("the buffer is full");
        assert_eq!(e.refusal, Refusal::BufferFull);
        // The first move arrives, the queued one starts: the buffer is free again.
        while r.theta <= 1.0 {
            run(&mut axis, &mut r, &mut k, 1);
            assert!(k < 20_000);
        }
        assert!(!bit12(&mut axis, k, &r));
        axis.request(&after(3.0, 5), &on(k as f64 * T, &r))
            .expect("queued again");
        // Changed at once: the move waiting is dropped and never plays.
        axis.request(&move_to(-1.0, 6), &on(k as f64 * T, &r))
            .expect("at once");
        assert!(!bit12(&mut axis, k, &r));
        run(&mut axis, &mut r, &mut k, 20_000);
        assert_eq!((r.theta, r.omega), (-1.0, 0.0));
    }

    /// Issue 44, 2: limits the axis cannot carry out are refused before anything moves:
    /// below the floor (the generator failed on 1e-300 and faulted the axis), or so low
    /// that the move would outlast `move_time_max_s` (1e-6 rad/s never arrived); the same
    /// for a jog's speed and a stop's deceleration. Limits low but workable are taken.
    #[test]
    fn limits_the_axis_cannot_carry_out_are_refused_before_anything_moves() {
        let (mut axis, p) = enabled_axis();
        let r = Reference::default();
        let m = on(0.0, &r);
        let with = |v: Option<f64>, a: Option<f64>, j: Option<f64>, base: AxisRequest| {
            let mut q = base;
            for (value, flag, field) in [
                (v, request_flags::HAS_V, &mut q.v_max_rad_s),
                (a, request_flags::HAS_A, &mut q.a_max_rad_s2),
                (j, request_flags::HAS_J, &mut q.j_max_rad_s3),
            ] {
                if let Some(x) = value {
                    *field = x;
                    q.flags |= flag;
                }
            }
            q
        };
        for (v, a, j) in [
            (Some(1e-300), None, None),
            (Some(1e-6), None, None),
            (None, Some(1e-300), None),
            (None, None, Some(1e-300)),
        ] {
            let e = axis
                .request(&with(v, a, j, move_to(0.25, 2)), &m)
                .expect_err("refused");
            assert_eq!(e.refusal, Refusal::TooSlow, "{e:?}");
        }
        let jog = |v: f64| AxisRequest {
            velocity_rad_s: v,
            ..request(RequestKind::Jog, 3)
        };
        assert_eq!(
            axis.request(&jog(1e-300), &m).expect_err("jog").refusal,
            Refusal::TooSlow
        );
        assert_eq!(axis.state(), AxisState::OperationEnabled);
        assert_eq!(axis.mode(), AxisMode::Hold);
        // Moving at 13 rad/s, a stop that would brake at 1e-4 rad/s² takes 1.3e5 s.
        axis.request(&jog(13.0), &m).expect("jog");
        let (mut r, mut k) = (r, 0);
        for _ in 0..5 {
            run(&mut axis, &mut r, &mut k, 100);
            axis.request(&request(RequestKind::Status, 4), &on(k as f64 * T, &r))
                .expect("renew");
        }
        let e = axis
            .request(
                &with(None, Some(1e-4), None, request(RequestKind::Stop, 5)),
                &on(k as f64 * T, &r),
            )
            .expect_err("a stop that never stops");
        assert_eq!(e.refusal, Refusal::TooSlow, "{e:?}");
        // Workable low limits: 1 mrad at 1e-3 rad/s, 1e-2 rad/s², 1 rad/s³ arrives.
        axis.request(&request(RequestKind::Stop, 6), &on(k as f64 * T, &r))
            .expect("stop");
        run(&mut axis, &mut r, &mut k, 4000);
        let goal = r.theta + 1e-3;
        axis.request(
            &with(Some(1e-3), Some(1e-2), Some(1.0), move_to(goal, 7)),
            &on(k as f64 * T, &r),
        )
        .expect("slow but workable");
        run(&mut axis, &mut r, &mut k, (2.5 / T) as u64);
        assert_eq!(r.theta, goal);
        assert_eq!(axis.fault(), 0);
        let _ = p;
    }

    /// Issue 44, 6: a client's jog runs while that client renews it; one it stops renewing
    /// (died, hung, lost its link) is quick-stopped after `jog_timeout_s`, with JOG_LOST.
    /// Another client's commands do not renew it; the program's jog needs no renewal.
    #[test]
    fn a_jog_its_client_stops_renewing_is_quick_stopped() {
        let (mut axis, p) = jogging_axis();
        let (mut r, mut k) = (Reference::default(), 0);
        let renew_every = (0.1 / T) as u64;
        // Renewed by its client for 2 s: still jogging.
        for _ in 0..20 {
            run(&mut axis, &mut r, &mut k, renew_every);
            let status = AxisRequest {
                client: 0,
                ..request(RequestKind::Status, 20)
            };
            axis.request(&status, &on(k as f64 * T, &r)).expect("renew");
        }
        assert_eq!(axis.mode(), AxisMode::ProfileVelocity);
        assert!(r.omega > 12.9);
        // Only another client speaks from now on: stopped after the timeout.
        let silent_from = k;
        loop {
            run(&mut axis, &mut r, &mut k, 1);
            let other = AxisRequest {
                client: 4242,
                ..request(RequestKind::Status, 30)
            };
            axis.request(&other, &on(k as f64 * T, &r)).expect("status");
            if axis.state() == AxisState::QuickStopActive {
                break;
            }
            assert!(k < silent_from + 10_000, "never stopped");
        }
        let after = (k - silent_from) as f64 * T;
        assert!(
            after > p.jog_timeout_s && after <= p.jog_timeout_s + 2.0 * T,
            "stopped {after} s after the last renewal"
        );
        assert!(axis.warning() & axis_warnings::JOG_LOST != 0);
        run(&mut axis, &mut r, &mut k, 4000);
        assert_eq!(r.omega, 0.0);
        // The program's jog runs on unrenewed.
        let (mut axis, _) = enabled_axis();
        let jog = AxisRequest {
            velocity_rad_s: 5.0,
            ..request(RequestKind::Jog, 2)
        };
        axis.request_scripted(&jog, &on(0.0, &Reference::default()))
            .expect("jog");
        let (mut r, mut k) = (Reference::default(), 0);
        run(&mut axis, &mut r, &mut k, (3.0 / T) as u64);
        assert_eq!(axis.mode(), AxisMode::ProfileVelocity);
        assert_eq!(r.omega, 5.0);
    }

    /// Issue 44, 6: a stream started with no point is lost a lead and a stream timeout
    /// after it began (it was never stopped).
    #[test]
    fn a_stream_whose_first_point_never_comes_is_quick_stopped() {
        let (mut axis, p) = enabled_axis();
        let (mut r, mut k) = (Reference::default(), 0);
        run(
            &mut axis,
            &mut r,
            &mut k,
            (p.brake_release_s / T) as u64 + 1,
        );
        let started = k;
        axis.request(&request(RequestKind::StreamStart, 3), &on(k as f64 * T, &r))
            .expect("stream");
        while axis.state() == AxisState::OperationEnabled {
            run(&mut axis, &mut r, &mut k, 1);
            assert!(k < started + 10_000, "never stopped");
        }
        let after = (k - started) as f64 * T;
        let bound = p.stream_lead_s + p.stream_timeout_s;
        assert!(after > bound && after <= bound + 2.0 * T, "{after} s");
        assert_eq!(axis.state(), AxisState::QuickStopActive);
        assert!(axis.warning() & axis_warnings::STREAM_LOST != 0);
    }

    /// Issue 44, 7: a stream point beyond the soft limits is refused like a move's target
    /// (counted in the status), never played.
    #[test]
    fn a_stream_point_beyond_the_soft_limits_is_refused() {
        let (mut axis, p) = enabled_axis();
        let r = Reference::default();
        axis.request(&request(RequestKind::StreamStart, 3), &on(0.0, &r))
            .expect("stream");
        let point = |k: u64, theta: f64| AxisStreamPoint {
            stream: 3,
            seq: k,
            t_s: k as f64 * 1e-3,
            theta_rad: theta,
            ..Default::default()
        };
        axis.stream_point(&point(0, 0.0), &on(0.0, &r))
            .expect("inside");
        let e = axis
            .stream_point(&point(1, 2.0 * p.position_max_rad), &on(0.0, &r))
            .expect_err("outside");
        assert_eq!(e.refusal, Refusal::OutsideSoftLimits);
        let s = axis.status(&on(0.0, &r), 0.0);
        assert_eq!(s.refused_points, 1);
        assert_eq!(s.last_refusal, Refusal::OutsideSoftLimits as u32);
    }
}
