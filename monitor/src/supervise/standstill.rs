//! What stops the motor before a launched stack's processes go. A served stack (and a run on
//! the wall clock) that is stopped brings every axis to a standstill first, as CiA 402's
//! shutdown option does: a quick stop at the axis's own deceleration, then, at rest, its
//! outputs off with the holding brake applied. The launcher commands the axis as a local
//! client does, through its own client of each axis's command service. When a process of
//! the stack dies, the survivors get the time their stand-in needs: the current loop
//! brakes for a silent position loop, the device's watchdog turns the outputs off for a
//! silent current loop.
//!
//! Every wait is bounded by what the stop should take — the quick stop from the axis's
//! speed at its deceleration and jerk, the watchdog's periods — plus [`ALLOWANCE`]; an axis
//! not at rest by then is said to be, and the stop fails (exit non-zero).

use std::time::{Duration, Instant};
use stepdrive_runtime::ipc::{CommandClient, PendingAnswer};
use stepdrive_runtime::port::Subscribe;
use stepdrive_shared::axis::{
    status_bits, AxisAck, AxisMode, AxisRequest, AxisState, AxisStatus, RequestKind,
};
use stepdrive_shared::messages::DriveState;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::Scenario;

/// Below this speed a rotor stands still, rad/s (CiA 402's velocity threshold, 0x606F): the
/// speed a stop's last transient leaves for a few ms, far below any motion commanded.
pub const STANDSTILL_RAD_S: f64 = 0.05;

/// Added to every bound: the command's way to the position loop and its answer (a tick,
/// 0.5 ms), the rotor settling once its setpoint is at rest (a few ms), the device's state
/// after the outputs went off (a sample or two), and a host that holds a process for tens
/// of ms now and then (docs/design.md, "When the host stalls the plant").
pub const ALLOWANCE: Duration = Duration::from_millis(250);

/// The client id in the stop's sequence numbers: the launcher's pid, as any local client's.
fn own_client() -> u32 {
    std::process::id()
}

/// The axis is in a motion that needs its client: a jog or a stream (open-ended), or a move
/// or a coordinated move still on its way.
pub fn in_motion(s: &AxisStatus) -> bool {
    if s.axis_state() != Some(AxisState::OperationEnabled) {
        return false;
    }
    match AxisMode::from_u32(s.mode) {
        Some(AxisMode::ProfileVelocity | AxisMode::CyclicPosition) => true,
        Some(AxisMode::Hold) => false,
        _ => s.omega_d_rad_s != 0.0 || !s.target_reached(),
    }
}

/// The brake bit of a status.
pub fn brake_applied(s: &AxisStatus) -> bool {
    s.statusword as u16 & status_bits::BRAKE_APPLIED != 0
}

/// What bounds an axis's stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StopLimits {
    /// The quick stop's deceleration and jerk.
    pub decel_rad_s2: f64,
    pub jerk_rad_s3: f64,
    /// How old the setpoint may grow before the current loop stops the motor on its own, s.
    pub setpoint_age_s: f64,
    /// The device's command watchdog, s.
    pub watchdog_s: f64,
    /// A simulated holding brake's deceleration of the rotor alone, rad/s² (`None`: no
    /// brake the axis applies: the paper's experiment has none, and on hardware the brake
    /// is the drive's, which the wire protocol does not carry).
    pub brake_decel_rad_s2: Option<f64>,
    /// Stack time from a setpoint to the device's state after it has been applied: the
    /// compute delay and two samples, s.
    pub device_delay_s: f64,
}

impl StopLimits {
    /// Axis `axis`'s limits in a stack of `s` in `mode`, whose device trips its watchdog
    /// after `watchdog_periods` current-loop periods without a command.
    pub fn of(s: &Scenario, axis: usize, mode: Mode, watchdog_periods: u32) -> Self {
        let own = s.for_axis(axis).unwrap_or(s);
        let brake = own.plant.brake.holding_torque_nm;
        Self {
            decel_rad_s2: own.axis.quick_stop_decel_rad_s2,
            jerk_rad_s3: own.axis.j_max_rad_s3,
            setpoint_age_s: f64::from(own.axis.setpoint_age_ticks) / own.rates.position_loop_hz,
            watchdog_s: f64::from(watchdog_periods) / own.rates.current_loop_hz,
            // The plant fits the brake to a commanded stack only (the paper's experiment
            // runs without one). A served stack's axes are commanded: `serve` marks the
            // whole scenario, after its axes' own were read.
            brake_decel_rad_s2: (mode == Mode::Realtime
                && !(s.runs_profile() && own.runs_profile())
                && brake > 0.0)
                .then(|| brake / own.motor.inertia_kg_m2),
            device_delay_s: f64::from(own.rates.compute_delay_periods + 2)
                / own.rates.current_loop_hz,
        }
    }

    /// A quick stop from `omega`: jerk-limited, so at most ω/a plus the time its
    /// deceleration takes to build up and die away (a/j), and the allowance.
    pub fn quick_stop(&self, omega: f64) -> Duration {
        seconds(omega.abs() / self.decel_rad_s2 + self.decel_rad_s2 / self.jerk_rad_s3)
    }

    /// The current loop's own stop for a silent position loop, from `omega`: it begins once
    /// the setpoint is too old and decelerates at the quick stop's rate.
    pub fn stand_in(&self, omega: f64) -> Duration {
        seconds(self.setpoint_age_s + omega.abs() / self.decel_rad_s2)
    }

    /// The motor has a holding brake the axis applies.
    pub fn brake(&self) -> bool {
        self.brake_decel_rad_s2.is_some()
    }

    /// The device's watchdog.
    pub fn watchdog(&self) -> Duration {
        seconds(self.watchdog_s)
    }

    /// The brake stopping a rotor at `omega` with the outputs off (zero without a brake:
    /// nothing to wait for).
    pub fn braking(&self, omega: f64) -> Option<Duration> {
        self.brake_decel_rad_s2.map(|a| seconds(omega.abs() / a))
    }
}

/// `s` seconds and the allowance.
fn seconds(s: f64) -> Duration {
    Duration::from_secs_f64(s.clamp(0.0, 3600.0)) + ALLOWANCE
}

/// One axis's line to the stack: its command service, and its status when the supervisor's
/// controls do not read it already.
pub struct AxisLine {
    pub commands: CommandClient,
    pub status: Option<Box<dyn Subscribe<AxisStatus>>>,
    pub newest: Option<AxisStatus>,
    pub limits: StopLimits,
}

/// The launcher's lines to every axis of its stack.
pub struct Stopper {
    pub axes: Vec<AxisLine>,
    next_seq: u64,
}

impl Stopper {
    pub fn new(axes: Vec<AxisLine>) -> Self {
        Self {
            axes,
            next_seq: u64::from(own_client()) << 32,
        }
    }

    /// Axis `axis`'s newest status from its own subscriber (none if it has none).
    pub fn own_status(&mut self, axis: usize) -> Option<AxisStatus> {
        let line = self.axes.get_mut(axis)?;
        if let Some(sub) = line.status.as_mut() {
            // A status lost to an error is read at the next look.
            if let Ok(Some(s)) = sub.newest() {
                line.newest = Some(s);
            }
        }
        line.newest
    }

    /// Sends `kind` to axis `axis`; its answer is the returned pending one's.
    pub fn send(&mut self, axis: usize, kind: RequestKind) -> Option<PendingAnswer> {
        self.next_seq += 1;
        let request = AxisRequest {
            axis: axis as u32,
            kind: kind as u32,
            seq: self.next_seq,
            client: own_client(),
            publish_time_ns: stepdrive_runtime::clock::monotonic_ns(),
            ..Default::default()
        };
        let line = self.axes.get_mut(axis)?;
        match line.commands.send(&request) {
            Ok(p) => Some(p),
            Err(e) => {
                tracing::error!("axis {axis}: cannot send {}: {e}", kind.name());
                None
            }
        }
    }

    /// Sends `kind` to axis `axis` and waits up to `wait` for its answer (not the
    /// termination flag: the stop goes on after Ctrl-C).
    pub fn ask(&mut self, axis: usize, kind: RequestKind, wait: Duration) -> Option<AxisAck> {
        let pending = self.send(axis, kind)?;
        answer_within(&pending, wait)
    }

    /// How many axes it reaches.
    pub fn count(&self) -> usize {
        self.axes.len()
    }

    pub fn limits(&self, axis: usize) -> Option<StopLimits> {
        self.axes.get(axis).map(|l| l.limits)
    }
}

/// `pending`'s answer if it comes within `wait`.
pub fn answer_within(pending: &PendingAnswer, wait: Duration) -> Option<AxisAck> {
    let deadline = Instant::now() + wait;
    loop {
        match pending.answer() {
            Ok(Some(ack)) => return Some(ack),
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_micros(100)),
            _ => return None,
        }
    }
}

/// Where one axis's motor stood once the stop was over.
#[derive(Debug, Clone, PartialEq)]
pub struct Stood {
    pub axis: usize,
    pub name: String,
    /// The rotor at the newest state seen (none: the device never published one).
    pub theta_rad: Option<f64>,
    pub omega_rad_s: Option<f64>,
    /// The axis's state and brake bit at its newest status (none: no status came).
    pub state: Option<AxisState>,
    pub brake: Option<bool>,
    /// The motor has no holding brake the axis applies.
    pub brakeless: bool,
    /// The device's fault bits at the newest state.
    pub device_fault: u32,
    /// What happened, in words ("at a standstill 0.071 s after the quick stop (bound
    /// 0.37 s), outputs off at 0.074 s").
    pub how: String,
    /// Whether the motor was stopped as it should be (false: not at rest in its bound).
    pub ok: bool,
}

impl Stood {
    /// The axis's newest state and status, with `how` it got there.
    /// `brake`: the motor has a holding brake the axis applies (a simulated one: on
    /// hardware the drive's brake is not the axis's, and the paper's experiment has none).
    pub fn at(
        axis: usize,
        name: &str,
        state: Option<&DriveState>,
        status: Option<&AxisStatus>,
        brake: bool,
        how: String,
        ok: bool,
    ) -> Self {
        Self {
            axis,
            name: name.to_string(),
            theta_rad: status.map(|s| s.theta_rad).or(state.map(|s| s.theta_rad)),
            omega_rad_s: state.map(|s| s.omega_rad_s),
            state: status.and_then(AxisStatus::axis_state),
            brake: status.filter(|_| brake).map(brake_applied),
            brakeless: !brake,
            device_fault: state.map_or(0, |s| s.fault),
            how,
            ok,
        }
    }

    /// `axis 0 (x) <how>: θ 14.2131 rad, ω 0.0000 rad/s, Switch on disabled, brake
    /// applied` (no name for the one axis of a stack).
    pub fn line(&self) -> String {
        let mut at = Vec::new();
        if let Some(t) = self.theta_rad {
            at.push(format!("θ {t:.4} rad"));
        }
        if let Some(w) = self.omega_rad_s {
            at.push(format!("ω {w:.4} rad/s"));
        }
        if let Some(s) = self.state {
            at.push(s.name().to_string());
        }
        match (self.brake, self.brakeless) {
            (_, true) => at.push("no holding brake".to_string()),
            (Some(true), false) => at.push("brake applied".to_string()),
            (Some(false), false) => at.push("brake released".to_string()),
            (None, false) => {}
        }
        if self.device_fault != 0 {
            at.push(format!(
                "device fault {}",
                crate::report::outcome::fault_names(self.device_fault).join(", ")
            ));
        }
        let at = match at.is_empty() {
            true => "never seen".to_string(),
            false => at.join(", "),
        };
        match self.name.is_empty() {
            true => format!("axis {} {}: {at}", self.axis, self.how),
            false => format!("axis {} ({}) {}: {at}", self.axis, self.name, self.how),
        }
    }
}

/// How the stack's axes stood when it was wound down.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct WoundDown {
    /// What the stack did first, if a process died ("the current loop braked for it").
    pub cause: Option<String>,
    pub axes: Vec<Stood>,
    /// How long the stop took, wall clock.
    pub took: Duration,
}

impl WoundDown {
    /// Every axis stopped as it should be.
    pub fn ok(&self) -> bool {
        self.axes.iter().all(|a| a.ok)
    }

    /// The headline's words: every axis's line.
    pub fn text(&self) -> String {
        let lines: Vec<String> = self.axes.iter().map(Stood::line).collect();
        let mut text = lines.join("; ");
        if let Some(c) = &self.cause {
            text = format!("{c}; {text}");
        }
        format!("{text} (the stop took {:.3} s)", self.took.as_secs_f64())
    }
}

/// One axis's way to a standstill: quick stop, at rest, outputs off.
pub(crate) enum Phase {
    /// Waiting for a status to tell where the axis is.
    Look,
    /// The quick stop asked (its answer pending) or running; the time it was asked, and
    /// whether it was this stop's (not a quick stop already running).
    Braking {
        sent: bool,
        pending: Option<PendingAnswer>,
        after_t: f64,
        asked: Instant,
        deadline: Instant,
        bound: Duration,
    },
    /// At rest: outputs off asked; the time the axis stood still, since the stop began.
    Disabling {
        sent: bool,
        /// The rotor's speed when it was found at rest.
        rest_omega: f64,
        pending: Option<PendingAnswer>,
        after_t: f64,
        asked: Instant,
        rest_s: f64,
        bound: Duration,
        deadline: Instant,
        /// The status that said the outputs are off, waiting for the device to take it.
        off_at: Option<f64>,
    },
    Done(Stood),
}

/// Whether a quick stop has left the axis at rest: Quick stop active, the setpoint at rest
/// (target reached), and the rotor below [`STANDSTILL_RAD_S`].
pub(crate) fn at_rest(status: &AxisStatus, state: Option<&DriveState>) -> bool {
    status.axis_state() == Some(AxisState::QuickStopActive)
        && status.target_reached()
        && state.is_some_and(|s| s.omega_rad_s.abs() <= STANDSTILL_RAD_S)
}

/// Whether the axis has its outputs off with the brake applied.
pub(crate) fn outputs_off(status: &AxisStatus) -> bool {
    status.axis_state().is_some_and(|s| !s.outputs_on()) && brake_applied(status)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(state: AxisState, word: u16, mode: AxisMode) -> AxisStatus {
        AxisStatus {
            state: state as u32,
            statusword: u32::from(word),
            mode: mode as u32,
            ..Default::default()
        }
    }

    /// A jog or a stream is motion whatever its speed; a move until it has arrived; an
    /// axis that holds, or is not enabled, is not.
    #[test]
    fn motion_is_what_needs_its_client() {
        let reached = status_bits::TARGET_REACHED;
        let on = AxisState::OperationEnabled;
        assert!(in_motion(&status(on, reached, AxisMode::ProfileVelocity)));
        assert!(in_motion(&status(on, reached, AxisMode::CyclicPosition)));
        assert!(in_motion(&status(on, 0, AxisMode::ProfilePosition)));
        assert!(!in_motion(&status(on, reached, AxisMode::ProfilePosition)));
        assert!(!in_motion(&status(on, reached, AxisMode::Hold)));
        assert!(
            !in_motion(&status(on, 0, AxisMode::Hold)),
            "held off its target by a load"
        );
        let mut moving = status(on, reached, AxisMode::Coordinated);
        moving.omega_d_rad_s = 1.0;
        assert!(in_motion(&moving));
        let qs = AxisState::QuickStopActive;
        assert!(!in_motion(&status(qs, 0, AxisMode::QuickStop)));
    }

    /// The bounds follow the speed: a quick stop from 13.13 rad/s at 200 rad/s² and
    /// 50 000 rad/s³ takes 65.65 + 4 ms, the current loop's own stop 10 ms more before it
    /// begins; each with the allowance.
    #[test]
    fn bounds_follow_the_speed_and_the_deceleration() {
        let s = Scenario::default();
        let l = StopLimits::of(&s, 0, Mode::Realtime, 1000);
        let ms = |d: Duration| (d - ALLOWANCE).as_secs_f64() * 1e3;
        assert!((ms(l.quick_stop(13.13)) - 69.65).abs() < 1e-6);
        assert!((ms(l.quick_stop(-13.13)) - 69.65).abs() < 1e-6);
        assert!((ms(l.stand_in(13.13)) - 75.65).abs() < 1e-6);
        assert!((ms(l.watchdog()) - 50.0).abs() < 1e-6);
        assert!(l.quick_stop(30.0) > l.quick_stop(1.0));
        // The paper's experiment has no brake; a served axis has the default one.
        assert_eq!(l.braking(10.0), None);
        let mut served = Scenario::default();
        served.run.until_stopped = true;
        let l = StopLimits::of(&served, 0, Mode::Realtime, 1000);
        let braking = l.braking(12.5).expect("a brake");
        assert!((ms(braking) - 12.5 / (0.5 / 8e-5) * 1e3).abs() < 1e-6);
        assert_eq!(
            StopLimits::of(&served, 0, Mode::Hardware, 1000).braking(1.0),
            None
        );
        // Each axis of a served stack has the brake, though its own scenario was read
        // before `serve` marked the whole one.
        let two = "[[axis]]\nname = \"x\"\n[[axis]]\nname = \"y\"\n";
        let mut two = Scenario::from_toml_str(two).expect("two axes");
        assert!(!StopLimits::of(&two, 1, Mode::Realtime, 1000).brake());
        two.run.until_stopped = true;
        assert!(StopLimits::of(&two, 1, Mode::Realtime, 1000).brake());
    }

    #[test]
    fn rest_is_the_quick_stop_done_and_the_rotor_still() {
        let qs = status(
            AxisState::QuickStopActive,
            status_bits::TARGET_REACHED,
            AxisMode::QuickStop,
        );
        let still = DriveState {
            omega_rad_s: 0.01,
            ..Default::default()
        };
        let turning = DriveState {
            omega_rad_s: 0.2,
            ..Default::default()
        };
        assert!(at_rest(&qs, Some(&still)));
        assert!(!at_rest(&qs, Some(&turning)));
        assert!(!at_rest(&qs, None));
        let braking = status(AxisState::QuickStopActive, 0, AxisMode::QuickStop);
        assert!(!at_rest(&braking, Some(&still)));
        let off = status(
            AxisState::SwitchOnDisabled,
            status_bits::BRAKE_APPLIED,
            AxisMode::Hold,
        );
        assert!(outputs_off(&off));
        assert!(!outputs_off(&qs));
    }
}
