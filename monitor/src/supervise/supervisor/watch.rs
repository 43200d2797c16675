//! The supervisor's part in keeping the motor safe when things end: the helpers beside the
//! stack (a dead gateway's remote motion quick-stopped, the gateway or the RT-throttling
//! guard restarted), and the stack's axes brought to a standstill before its processes go
//! (`crate::supervise::standstill`).

use super::{Ending, Supervisor, REALTIME_NAP};
use crate::report::outcome::{Outcome, LATCHED};
use crate::supervise::helpers::MAX_RESTARTS;
use crate::supervise::observer::{Observer, Stop};
use crate::supervise::standstill::{
    at_rest, in_motion, outputs_off, Phase, Stood, StopLimits, WoundDown, ALLOWANCE,
    STANDSTILL_RAD_S,
};
use std::time::{Duration, Instant};
use stepdrive_shared::axis::is_remote_client;
use stepdrive_shared::axis::{AxisMode, AxisState, AxisStatus, RequestKind};
use stepdrive_shared::messages::DriveState;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stack::Role;

/// How long a quick stop of a dead gateway's motion waits for its answer: the supervision
/// goes on after it.
const REMOTE_STOP_WAIT: Duration = Duration::from_millis(200);

impl Supervisor<'_, '_> {
    fn axis_count(&self) -> usize {
        1 + self.axes.len()
    }

    fn observer_of(&self, axis: usize) -> &Observer<'_> {
        match axis {
            0 => &self.observer,
            n => &self.axes[n - 1].observer,
        }
    }

    /// The axis's name as a multi-axis stack's scenario gives it (none for one axis).
    fn axis_label(&self, axis: usize) -> String {
        match self.axes.is_empty() {
            true => String::new(),
            false => self.s.axis_name(axis),
        }
    }

    fn newest_state(&self, axis: usize) -> Option<DriveState> {
        self.observer_of(axis).newest_state().copied()
    }

    /// The axis's newest status: from the controls the supervisor reads, or from the
    /// stopper's own subscriber where it reads none.
    fn newest_status(&mut self, axis: usize) -> Option<AxisStatus> {
        let own = self
            .stopper
            .as_ref()
            .and_then(|s| s.axes.get(axis))
            .is_some_and(|l| l.status.is_some());
        match own {
            true => self.stopper.as_mut().and_then(|s| s.own_status(axis)),
            false => self.observer_of(axis).newest_status().copied(),
        }
    }

    fn send(
        &mut self,
        axis: usize,
        kind: RequestKind,
    ) -> Option<stepdrive_runtime::ipc::PendingAnswer> {
        self.stopper.as_mut().and_then(|s| s.send(axis, kind))
    }

    fn limits(&self, axis: usize) -> Option<StopLimits> {
        self.stopper.as_ref().and_then(|s| s.limits(axis))
    }

    /// Takes what arrived, recorded and not graded (the run is over); a broken contract is
    /// not news now.
    fn take_quietly(&mut self) -> anyhow::Result<()> {
        self.take_stats()?;
        let _ = self.drain()?;
        self.drain_controls()?;
        Ok(())
    }

    /// A process of the stack that died and is not among `known`: its role and why.
    fn newly_dead(&mut self, known: &[Role]) -> anyhow::Result<Option<(Role, String)>> {
        for child in self.children.iter_mut() {
            if known.contains(&child.role()) {
                continue;
            }
            if let Some(status) = child.poll_exit()? {
                return Ok(Some((child.role(), child.describe_failure(status))));
            }
        }
        Ok(None)
    }

    /// The helpers beside the stack: a death is logged at once and answered. The gateway's
    /// remote clients lose their link, so every axis in a motion a remote client started is
    /// quick-stopped, then the gateway is started again. The guard is replaced by one that
    /// holds the value it saved, so that throttling is restored however the launcher ends.
    /// A helper that cannot be restarted, or dies once more than [`MAX_RESTARTS`] times,
    /// stops the stack (`Some`).
    pub(super) fn watch_helpers(&mut self) -> anyhow::Result<Option<Stop>> {
        let gateway = match self.helpers.as_deref_mut() {
            Some(h) => h.gateway_died()?,
            None => return Ok(None),
        };
        if let Some(status) = gateway {
            let stopped = self.stop_remote_motion()?;
            let Some(h) = self.helpers.as_deref_mut() else {
                return Ok(None);
            };
            let Some(g) = h.gateway.as_mut() else {
                return Ok(None);
            };
            let what = format!(
                "the gateway (pid {}) exited with {status}: its remote clients lost their link; {stopped}",
                g.pid()
            );
            tracing::error!("{what}");
            if g.restarts() >= MAX_RESTARTS {
                return Ok(Some(Stop::new(
                    Outcome::ProcessDied,
                    format!("{what}; it had been restarted {MAX_RESTARTS} times already"),
                )));
            }
            match g.restart() {
                Ok(n) => {
                    tracing::warn!(
                        "gateway restarted (pid {}, restart {n} of {MAX_RESTARTS}); remote clients \
                         connect again and enable the axes they drove",
                        g.pid()
                    );
                    h.events.push(format!(
                        "the gateway was restarted after it exited with {status}"
                    ));
                }
                Err(e) => {
                    return Ok(Some(Stop::new(
                        Outcome::ProcessDied,
                        format!("{what}; it could not be restarted: {e:#}"),
                    )))
                }
            }
        }
        let Some(h) = self.helpers.as_deref_mut() else {
            return Ok(None);
        };
        let Some(status) = h.guard_died() else {
            return Ok(None);
        };
        let Some(guard) = h.guard.as_mut() else {
            return Ok(None);
        };
        let previous = guard.previous();
        tracing::error!(
            "the RT-throttling guard exited with {status}: nothing would restore \
             sched_rt_runtime_us = {previous} if this launcher were killed now"
        );
        let restarted = match h.guard_restarts < MAX_RESTARTS {
            true => guard.restart().map_err(|e| format!("{e:#}")),
            false => Err(format!(
                "it had been restarted {MAX_RESTARTS} times already"
            )),
        };
        match restarted {
            Ok(()) => {
                h.guard_restarts += 1;
                tracing::warn!(
                    "a new RT-throttling guard holds it (restart {} of {MAX_RESTARTS}): \
                     throttling stays lifted for the stack and goes back to {previous} however \
                     this launcher ends",
                    h.guard_restarts
                );
                h.events.push(format!(
                    "the RT-throttling guard was restarted after it exited with {status}"
                ));
                Ok(None)
            }
            Err(why) => {
                // Nobody would restore it: restored now, and a realtime stack is not left
                // running with the throttling that takes its CPUs for 50 ms at a time.
                guard.restore_now();
                Ok(Some(Stop::new(
                    Outcome::ProcessDied,
                    format!(
                        "the RT-throttling guard exited with {status} and no other could hold \
                         it ({why}): throttling was restored to {previous} and the stack stopped"
                    ),
                )))
            }
        }
    }

    /// Quick-stops every axis in a motion a remote client started (its last command's):
    /// with the gateway gone nothing can stop it on that client's behalf. Says what it did.
    fn stop_remote_motion(&mut self) -> anyhow::Result<String> {
        self.drain_controls()?;
        let mut said = Vec::new();
        for axis in 0..self.axis_count() {
            let Some(st) = self.newest_status(axis) else {
                continue;
            };
            let client = (st.last_seq >> 32) as u32;
            if !is_remote_client(client) || !in_motion(&st) {
                continue;
            }
            let mode = AxisMode::from_u32(st.mode).map_or("motion", |m| m.name());
            let answer = self
                .stopper
                .as_mut()
                .and_then(|s| s.ask(axis, RequestKind::QuickStop, REMOTE_STOP_WAIT));
            said.push(match answer {
                Some(a) if a.taken() => {
                    format!("axis {axis}'s {mode} (remote client {client:#x}) quick-stopped")
                }
                Some(a) => format!(
                    "axis {axis}'s {mode} (remote client {client:#x}): quick stop refused: {}",
                    a.text()
                ),
                None => format!(
                    "axis {axis}'s {mode} (remote client {client:#x}): quick stop not answered"
                ),
            });
        }
        Ok(match said.is_empty() {
            true => "no axis was in a motion a remote client started".to_string(),
            false => said.join(", "),
        })
    }

    /// Once supervision has ended early (Ctrl-C, a dead process, a stuck stack), before the
    /// stack's processes go: every axis brought to a standstill and its outputs off, or, if
    /// a process died, the survivors given the time their stand-in needs. `None` when there
    /// is nothing to stop: a reader, a lockstep stack (it takes no commands and moves no
    /// real motor), a run that ended at its last sample, or a stack that never ran.
    pub fn wind_down(&mut self, ending: &Ending) -> anyhow::Result<Option<WoundDown>> {
        if self.stopper.is_none() || matches!(ending, Ending::Last) {
            return Ok(None);
        }
        // A stack that never published a state never moved: nothing to stop, and its own
        // headline (it did not start) says enough.
        if (0..self.axis_count()).all(|a| self.newest_state(a).is_none()) {
            return Ok(None);
        }
        self.observer.wind_down();
        for a in &mut self.axes {
            a.observer.wind_down();
        }
        let began = Instant::now();
        let mut w = match self.died {
            Some(role) => self.survivors(role, &[role], began)?,
            None => self.standstill(began)?,
        };
        w.took = began.elapsed();
        for a in w.axes.iter().filter(|a| !a.ok) {
            tracing::error!("{}", a.line());
        }
        Ok(Some(w))
    }

    /// Quick stop, rest, outputs off, on every axis at once, each within its bound.
    fn standstill(&mut self, began: Instant) -> anyhow::Result<WoundDown> {
        let n = self.axis_count();
        let mut phases: Vec<Phase> = (0..n).map(|_| Phase::Look).collect();
        loop {
            self.take_quietly()?;
            if let Some((role, why)) = self.newly_dead(&[])? {
                // The survivors finish the stop; it did not go as it should.
                tracing::error!("{why}, while the axes were being stopped");
                self.died = Some(role);
                let mut w = self.survivors(role, &[role], began)?;
                w.cause = Some(format!(
                    "{why}, while the axes were being stopped{}",
                    w.cause.map_or(String::new(), |c| format!("; {c}"))
                ));
                for a in &mut w.axes {
                    a.ok = false;
                }
                return Ok(w);
            }
            let now = Instant::now();
            let mut done = true;
            for (axis, slot) in phases.iter_mut().enumerate() {
                let phase = std::mem::replace(slot, Phase::Look);
                *slot = self.step(axis, phase, began, now);
                done &= matches!(slot, Phase::Done(_));
            }
            if done {
                break;
            }
            std::thread::sleep(REALTIME_NAP);
        }
        let axes = phases
            .into_iter()
            .filter_map(|p| match p {
                Phase::Done(stood) => Some(stood),
                _ => None,
            })
            .collect();
        Ok(WoundDown {
            cause: None,
            axes,
            took: Duration::ZERO,
        })
    }

    fn stood(&mut self, axis: usize, how: String, ok: bool) -> Stood {
        let state = self.newest_state(axis);
        let status = self.newest_status(axis);
        let brake = self.limits(axis).is_some_and(|l| l.brake());
        Stood::at(
            axis,
            &self.axis_label(axis),
            state.as_ref(),
            status.as_ref(),
            brake,
            how,
            ok,
        )
    }

    /// One axis's next step towards its standstill.
    fn step(&mut self, axis: usize, phase: Phase, began: Instant, now: Instant) -> Phase {
        let state = self.newest_state(axis);
        let status = self.newest_status(axis);
        let Some(limits) = self.limits(axis) else {
            return Phase::Done(self.stood(axis, "has no line to it".to_string(), false));
        };
        match phase {
            Phase::Look => {
                let Some(st) = status else {
                    if now < began + ALLOWANCE {
                        return Phase::Look;
                    }
                    let resting = state
                        .as_ref()
                        .is_none_or(|s| s.omega_rad_s.abs() <= STANDSTILL_RAD_S);
                    let how = match state {
                        None => "was never started (no state, no status)",
                        Some(_) if resting => {
                            "gave no status (its position loop is silent), at rest"
                        }
                        Some(_) => "gave no status (its position loop is silent): NOT stopped",
                    };
                    return Phase::Done(self.stood(axis, how.to_string(), resting));
                };
                match st.axis_state() {
                    Some(AxisState::OperationEnabled | AxisState::QuickStopActive) => {
                        let omega = state
                            .map_or(0.0, |s| s.omega_rad_s.abs())
                            .max(st.omega_d_rad_s.abs());
                        let bound = limits.quick_stop(omega);
                        let sent = st.axis_state() == Some(AxisState::OperationEnabled);
                        let pending = match sent {
                            true => self.send(axis, RequestKind::QuickStop),
                            false => None,
                        };
                        Phase::Braking {
                            sent,
                            pending,
                            after_t: st.t_s,
                            asked: now,
                            deadline: now + bound,
                            bound,
                        }
                    }
                    Some(s) => Phase::Done(self.stood(
                        axis,
                        format!("had its outputs off already ({})", s.name()),
                        true,
                    )),
                    None => Phase::Done(self.stood(
                        axis,
                        format!("is in an unknown state {}", st.state),
                        false,
                    )),
                }
            }
            Phase::Braking {
                sent,
                mut pending,
                mut after_t,
                asked,
                deadline,
                bound,
            } => {
                if let Some(ack) = pending.as_ref().and_then(|p| p.answer().ok().flatten()) {
                    pending = None;
                    if !ack.taken() {
                        tracing::warn!("axis {axis}: quick stop refused: {}", ack.text());
                    }
                    after_t = ack.t_s;
                }
                let seen = status.filter(|s| pending.is_none() && s.t_s >= after_t);
                if let Some(st) = seen {
                    match st.axis_state() {
                        Some(AxisState::QuickStopActive) if at_rest(&st, state.as_ref()) => {
                            return Phase::Disabling {
                                sent,
                                rest_omega: state.map_or(0.0, |s| s.omega_rad_s),
                                pending: self.send(axis, RequestKind::DisableVoltage),
                                after_t: st.t_s,
                                asked: now,
                                rest_s: now.duration_since(asked).as_secs_f64(),
                                bound,
                                deadline: now + ALLOWANCE,
                                off_at: None,
                            };
                        }
                        Some(AxisState::QuickStopActive) => {}
                        Some(AxisState::OperationEnabled) => {
                            // Enabled again (a client) while it stopped: stopped again, within
                            // the same bound.
                            pending = self.send(axis, RequestKind::QuickStop);
                            after_t = st.t_s;
                        }
                        Some(s) => {
                            return Phase::Done(self.stood(
                                axis,
                                format!(
                                    "went to {} during its quick stop ({:.3} s after it)",
                                    s.name(),
                                    now.duration_since(asked).as_secs_f64()
                                ),
                                s != AxisState::Fault,
                            ))
                        }
                        None => {}
                    }
                }
                if now >= deadline {
                    let why = match pending {
                        Some(_) => " (the quick stop was not answered: the position loop is stuck)",
                        None => "",
                    };
                    return Phase::Done(self.stood(
                        axis,
                        format!(
                            "was NOT at a standstill within its bound of {:.3} s after the quick \
                             stop{why}",
                            bound.as_secs_f64()
                        ),
                        false,
                    ));
                }
                Phase::Braking {
                    sent,
                    pending,
                    after_t,
                    asked,
                    deadline,
                    bound,
                }
            }
            Phase::Disabling {
                sent,
                rest_omega,
                mut pending,
                mut after_t,
                asked,
                rest_s,
                bound,
                deadline,
                mut off_at,
            } => {
                if let Some(ack) = pending.as_ref().and_then(|p| p.answer().ok().flatten()) {
                    pending = None;
                    if !ack.taken() {
                        tracing::warn!("axis {axis}: disable refused: {}", ack.text());
                    }
                    after_t = ack.t_s;
                }
                let seen = status.filter(|s| pending.is_none() && s.t_s >= after_t);
                if let (Some(st), None) = (seen, off_at) {
                    if outputs_off(&st) {
                        off_at = Some(st.t_s);
                    } else if st.axis_state().is_some_and(AxisState::outputs_on) {
                        // Enabled again meanwhile: outputs off again.
                        pending = self.send(axis, RequestKind::DisableVoltage);
                        after_t = st.t_s;
                    }
                }
                // The device has taken the outputs off once a state sampled after it came.
                let applied = off_at.is_some_and(|t| {
                    state.is_some_and(|s| s.sample_time_s >= t + limits.device_delay_s)
                });
                if applied {
                    let stop = match sent {
                        true => "its quick stop",
                        false => "the stop began (it was in Quick stop active)",
                    };
                    let how = format!(
                        "stood still at ω {rest_omega:.4} rad/s {rest_s:.3} s after {stop} \
                         (bound {:.3} s), outputs off {:.3} s later",
                        bound.as_secs_f64(),
                        now.duration_since(asked).as_secs_f64()
                    );
                    return Phase::Done(self.stood(axis, how, true));
                }
                if now >= deadline {
                    let how = format!(
                        "stood still at ω {rest_omega:.4} rad/s {rest_s:.3} s after its quick \
                         stop but its outputs were NOT off {:.3} s later",
                        ALLOWANCE.as_secs_f64()
                    );
                    return Phase::Done(self.stood(axis, how, false));
                }
                Phase::Disabling {
                    sent,
                    rest_omega,
                    pending,
                    after_t,
                    asked,
                    rest_s,
                    bound,
                    deadline,
                    off_at,
                }
            }
            Phase::Done(stood) => Phase::Done(stood),
        }
    }

    /// `role`'s process died (and those in `dead`): the survivors stop the motor before they
    /// are torn down. A silent position loop: the current loop brakes at the quick stop's
    /// rate, and the rotor is given until it is at rest. A silent current loop: the
    /// device's watchdog turns the outputs off (the brake applied), and the rotor is given
    /// until its brake stops it. A dead device: nothing can move the motor (the plant or
    /// the emulated drive is the motor; a bridge's drive is left to its own watchdog).
    fn survivors(
        &mut self,
        role: Role,
        dead: &[Role],
        began: Instant,
    ) -> anyhow::Result<WoundDown> {
        let n = self.axis_count();
        let device = match self.mode {
            Mode::Hardware => "the drive",
            _ => "the plant",
        };
        let mut w = WoundDown::default();
        match role {
            Role::PositionLoop => {
                w.cause = Some(
                    "the current loop stood in for it (its own quick stop once the setpoint \
                     grew too old)"
                        .to_string(),
                );
                let omegas: Vec<f64> = (0..n)
                    .map(|a| self.newest_state(a).map_or(0.0, |s| s.omega_rad_s.abs()))
                    .collect();
                let bounds: Vec<Duration> = (0..n)
                    .map(|a| self.limits(a).map_or(ALLOWANCE, |l| l.stand_in(omegas[a])))
                    .collect();
                let rest = self.wait_per_axis(&bounds, began, dead, |_, s| {
                    s.is_some_and(|s| s.omega_rad_s.abs() <= STANDSTILL_RAD_S)
                })?;
                for (axis, r) in rest.iter().enumerate() {
                    // Its status is the dead loop's last: the state alone says where it is.
                    let state = self.newest_state(axis);
                    let how = match r {
                        Ok(t) => format!(
                            "came to rest {t:.3} s after the position loop was found dead \
                             (bound {:.3} s), held by the current loop",
                            bounds[axis].as_secs_f64()
                        ),
                        Err(why) => format!(
                            "was NOT at rest within its bound of {:.3} s{why}",
                            bounds[axis].as_secs_f64()
                        ),
                    };
                    let label = self.axis_label(axis);
                    let brake = self.limits(axis).is_some_and(|l| l.brake());
                    let stood =
                        Stood::at(axis, &label, state.as_ref(), None, brake, how, r.is_ok());
                    w.axes.push(stood);
                }
            }
            Role::CurrentLoop | Role::Identify => {
                w.cause = Some(format!("{device}'s watchdog stood in for it"));
                let bounds: Vec<Duration> = (0..n)
                    .map(|a| self.limits(a).map_or(ALLOWANCE, |l| l.watchdog()))
                    .collect();
                let tripped = self.wait_per_axis(&bounds, began, dead, |_, s| {
                    s.is_some_and(|s| s.fault & LATCHED != 0)
                })?;
                // With the outputs off, a simulated brake stops the rotor.
                let after = Instant::now();
                let braking: Vec<Duration> = (0..n)
                    .map(|a| {
                        let omega = self.newest_state(a).map_or(0.0, |s| s.omega_rad_s);
                        self.limits(a)
                            .and_then(|l| l.braking(omega))
                            .filter(|_| tripped[a].is_ok())
                            .unwrap_or(Duration::ZERO)
                    })
                    .collect();
                let rest = match braking.iter().any(|b| !b.is_zero()) {
                    true => self.wait_per_axis(&braking, after, dead, |_, s| {
                        s.is_some_and(|s| s.omega_rad_s.abs() <= STANDSTILL_RAD_S)
                    })?,
                    false => vec![Err(String::new()); n],
                };
                for axis in 0..n {
                    let (how, ok) = match &tripped[axis] {
                        Ok(t) => {
                            let mut how = format!(
                                "had its outputs off by {device}'s watchdog {t:.3} s after the \
                                 current loop was found dead (bound {:.3} s)",
                                bounds[axis].as_secs_f64()
                            );
                            match (&rest[axis], braking[axis].is_zero()) {
                                (Ok(r), false) => {
                                    how += &format!(", at rest on its brake {r:.3} s later")
                                }
                                (Err(_), false) => {
                                    how += &format!(
                                        ", still turning on its brake {:.3} s later",
                                        braking[axis].as_secs_f64()
                                    )
                                }
                                (_, true) => {
                                    let omega =
                                        self.newest_state(axis).map_or(0.0, |s| s.omega_rad_s);
                                    if omega.abs() > STANDSTILL_RAD_S {
                                        how += ", the rotor turning on freely (no holding brake)";
                                    }
                                }
                            }
                            (how, true)
                        }
                        Err(why) => (
                            format!(
                                "did NOT have its outputs off by {device}'s watchdog within its \
                                 bound of {:.3} s{why}",
                                bounds[axis].as_secs_f64()
                            ),
                            false,
                        ),
                    };
                    let stood = self.stood(axis, how, ok);
                    w.axes.push(stood);
                }
            }
            Role::Bridge => {
                // Nothing reads the drive now; its own watchdog turns its outputs off that
                // long after the last command. An emulated drive is kept up for it.
                let watchdog = (0..n)
                    .filter_map(|a| self.limits(a).map(|l| l.watchdog()))
                    .max()
                    .unwrap_or(ALLOWANCE);
                let emulated = self
                    .children
                    .iter()
                    .any(|c| c.role() == Role::EmulatedDrive);
                std::thread::sleep(watchdog.saturating_sub(began.elapsed()));
                w.cause = Some(format!(
                    "nothing reads the drive now: its own watchdog turns its outputs off {:.3} s \
                     after its last command at most{}",
                    watchdog.as_secs_f64(),
                    match emulated {
                        true => " (the emulated drive was kept up that long)",
                        false => "",
                    }
                ));
                for axis in 0..n {
                    let stood = self.stood(axis, "was last seen".to_string(), true);
                    w.axes.push(stood);
                }
            }
            Role::Plant | Role::EmulatedDrive => {
                w.cause = Some(format!(
                    "{} is the motor: with it gone nothing can move the motor",
                    match role {
                        Role::Plant => "the plant (a simulated motor)",
                        _ => "the emulated drive (a simulated drive and motor)",
                    }
                ));
                for axis in 0..n {
                    let stood = self.stood(axis, "was last seen".to_string(), true);
                    w.axes.push(stood);
                }
            }
            _ => {
                for axis in 0..n {
                    let stood = self.stood(axis, "was last seen".to_string(), true);
                    w.axes.push(stood);
                }
            }
        }
        Ok(w)
    }

    /// Waits until `done(axis, newest state)` holds for every axis, each within its bound
    /// from `from`; per axis the time it took, s, or why it did not (a survivor that died
    /// too ends the wait).
    fn wait_per_axis(
        &mut self,
        bounds: &[Duration],
        from: Instant,
        dead: &[Role],
        done: impl Fn(usize, Option<&DriveState>) -> bool,
    ) -> anyhow::Result<Vec<Result<f64, String>>> {
        let n = bounds.len();
        let mut result: Vec<Option<Result<f64, String>>> = vec![None; n];
        loop {
            self.take_quietly()?;
            let now = Instant::now();
            let gone = self.newly_dead(dead)?;
            for (axis, r) in result.iter_mut().enumerate() {
                if r.is_some() {
                    continue;
                }
                let state = self.observer_of(axis).newest_state();
                if done(axis, state) {
                    *r = Some(Ok(now.duration_since(from).as_secs_f64()));
                } else if let Some((_, why)) = &gone {
                    *r = Some(Err(format!(" ({why})")));
                } else if now >= from + bounds[axis] {
                    *r = Some(Err(String::new()));
                }
            }
            if result.iter().all(Option::is_some) {
                return Ok(result.into_iter().flatten().collect());
            }
            std::thread::sleep(REALTIME_NAP);
        }
    }
}
