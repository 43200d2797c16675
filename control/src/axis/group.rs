//! Several axes commanded as one machine. Each is its own [`Axis`] (its state machine, its
//! sources, its envelope); the group adds what only a machine has:
//!
//! - **Coordinated moves**: a move of some or all axes in which every one leaves on the same
//!   tick and arrives on the same tick. The slowest axis (its own time-optimal move within
//!   its move limits) sets the duration, the others are stretched within theirs
//!   ([`super::coordinated`]); rest to rest the axes keep to the straight line between start
//!   and target, and the group reports how far the measured rotors strayed from it (the
//!   contour error).
//! - **A stop policy**: by default a fault or a quick stop of one axis quick-stops every
//!   other enabled axis on the same tick, each at its own quick-stop deceleration, none
//!   faulted ([`StopPolicy::All`]); [`StopPolicy::Own`] leaves each axis to its own faults
//!   and commands.
//!
//! Pure, like the axis: a multi-axis position loop feeds it each axis's measured state and
//! commands at every tick, and gives each axis's torque law its setpoint. Everything is
//! allocated in [`AxisGroup::new`]; a tick and a coordinated move's planning allocate
//! nothing.

use super::coordinated::{CoordinatedMove, MAX_AXES};
use super::otg::Limits;
use super::{move_limits, refuse, Axis, Measured, Refused, Setpoint};
use stepdrive_shared::axis::{
    AxisParams, AxisRequest, AxisState, AxisStatus, AxisStreamPoint, Refusal,
};
use stepdrive_shared::trajectory::Reference;

/// What one axis stopping does to the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StopPolicy {
    /// A fault or a quick stop on one axis quick-stops every enabled axis: axes that share
    /// a tool (a plotter, a mill) must not carry on without the one that stopped.
    #[default]
    All,
    /// Each axis stops on its own faults and commands only.
    Own,
}

/// A group that cannot be made, or a tick given the wrong number of axes.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GroupError {
    #[error("a group takes 1 … {MAX_AXES} axes, not {0}")]
    Axes(usize),
    #[error("the group has {axes} axes; the tick gave {measured} measured states and room for {setpoints} setpoints")]
    Lengths {
        axes: usize,
        measured: usize,
        setpoints: usize,
    },
}

/// The running coordinated move: which axes (in the move's order) and the straight line
/// each started on.
#[derive(Debug, Clone, Copy)]
struct Running {
    members: [usize; MAX_AXES],
    count: usize,
    from: [f64; MAX_AXES],
    to: [f64; MAX_AXES],
    /// The tick time the last state given was for: the move is stepped by the samples'
    /// time, as an axis's own trajectory is, not by ticks counted.
    given_for: f64,
}

/// A machine's axes by index, as the group's coordination reaches them: the group's own,
/// or the axes of a multi-axis position loop's lanes (each lane owning its axis).
pub trait Axes {
    fn count(&self) -> usize;
    fn axis_ref(&self, i: usize) -> &Axis;
    fn axis_mut(&mut self, i: usize) -> &mut Axis;
}

impl Axes for [Axis] {
    fn count(&self) -> usize {
        self.len()
    }
    fn axis_ref(&self, i: usize) -> &Axis {
        &self[i]
    }
    fn axis_mut(&mut self, i: usize) -> &mut Axis {
        &mut self[i]
    }
}

/// What only a machine has, over axes held elsewhere: the coordinated move, its contour
/// error, and the stop policy. Each tick: [`Self::before_tick`], every axis's own tick, then
/// [`Self::after_tick`]. [`AxisGroup`] is one with its axes.
#[derive(Debug)]
pub struct Coordinator {
    policy: StopPolicy,
    planner: CoordinatedMove,
    running: Option<Running>,
    /// The move's states of the next tick and their jerks, in the move's order.
    next: [Reference; MAX_AXES],
    jerks: [f64; MAX_AXES],
    /// Axes stopping (Fault, fault reaction, quick stop) after the last tick, bit per axis:
    /// the policy acts when an axis starts to stop, not while it stays stopped (an axis
    /// enabled again beside a faulted one is not stopped again).
    stopping: u32,
    /// The axis whose stop stopped the others last (the policy's cause).
    stopped_by: Option<usize>,
    /// The running (or last) move's peak contour error, rad.
    contour_peak: f64,
    /// The axes' samples are of one clock (one simulated plant), so that their times
    /// compare; drives each have their own ([`Self::separate_clocks`]).
    one_clock: bool,
}

impl Coordinator {
    /// For axes whose position loop ticks every `period_s`.
    pub fn new(period_s: f64, policy: StopPolicy) -> Self {
        Self {
            policy,
            planner: CoordinatedMove::new(period_s),
            running: None,
            next: [Reference::default(); MAX_AXES],
            jerks: [0.0; MAX_AXES],
            stopping: 0,
            stopped_by: None,
            contour_peak: 0.0,
            one_clock: true,
        }
    }

    /// Axes whose samples come from clocks of their own (a drive each): their times do not
    /// compare, so a coordinated move is stepped once a tick and each axis takes its state
    /// as it comes, and the contour error is of each axis's newest sample.
    pub fn separate_clocks(mut self) -> Self {
        self.one_clock = false;
        self
    }

    pub fn policy(&self) -> StopPolicy {
        self.policy
    }

    /// The axis whose fault or quick stop made the policy stop the others, last time it
    /// did.
    pub fn stopped_by(&self) -> Option<usize> {
        self.stopped_by
    }

    /// A coordinated move runs (some of its axes are still in it).
    pub fn coordinated_running(&self) -> bool {
        self.running.is_some()
    }

    /// The peak distance of the measured rotors from the running (or the last) coordinated
    /// move's straight line, rad: the contour error a plotter or a mill sees.
    pub fn contour_peak(&self) -> f64 {
        self.contour_peak
    }

    /// The coordinated move's duration, s (a whole number of ticks), while one runs.
    pub fn coordinated_duration_s(&self) -> Option<f64> {
        self.running.map(|_| self.planner.duration_s())
    }

    /// A coordinated move: each `(axis, target)` to rest at its target, within the axis's
    /// move limits (`[axis] move_*`), all leaving on the next tick and arriving on one
    /// tick. `m` is every axis's measured state at this tick. Refused, with nothing applied
    /// to any axis: an axis named twice or not in the group, no axis or more than
    /// [`MAX_AXES`], an axis not in Operation enabled or its brake still holding, a target
    /// not finite or outside its soft limits, a coordinated move already running (stop it,
    /// or let it arrive), or a move the generator cannot plan.
    pub fn move_together<A: Axes + ?Sized>(
        &mut self,
        axes: &mut A,
        targets: &[(usize, f64)],
        m: &[Measured],
    ) -> Result<(), Refused> {
        if targets.is_empty() || targets.len() > MAX_AXES {
            return Err(refuse(
                Refusal::UnknownAxis,
                format!(
                    "a coordinated move takes 1 … {MAX_AXES} axes, not {}",
                    targets.len()
                ),
            ));
        }
        if let Some(r) = &self.running {
            let axes: Vec<usize> = r.members[..r.count].to_vec();
            return Err(refuse(
                Refusal::Moving,
                format!("a coordinated move of axes {axes:?} is running: stop it or let it arrive"),
            ));
        }
        let period = self.planner.period_s();
        let mut run = Running {
            members: [0; MAX_AXES],
            count: targets.len(),
            from: [0.0; MAX_AXES],
            to: [0.0; MAX_AXES],
            given_for: 0.0,
        };
        let mut starts = [Reference::default(); MAX_AXES];
        let mut limits = [Limits {
            v: 1.0,
            a: 1.0,
            j: 1.0,
        }; MAX_AXES];
        for (j, &(i, target)) in targets.iter().enumerate() {
            if targets[..j].iter().any(|&(other, _)| other == i) {
                return Err(refuse(
                    Refusal::UnknownAxis,
                    format!("axis {i} is named twice"),
                ));
            }
            let Some(at) = m.get(i).filter(|_| i < axes.count()) else {
                return Err(unknown(i, axes.count()));
            };
            let axis = axes.axis_ref(i);
            let start = axis.coordinated_start(target).map_err(|e| Refused {
                refusal: e.refusal,
                text: format!("axis {i}: {}", e.text),
            })?;
            // The axes must leave on the same tick: no brake may still hold.
            if !axis.brake_released(at.t) {
                return Err(refuse(
                    Refusal::WrongState,
                    format!(
                        "axis {i}: its brake still holds (released {} s after the enable); \
                         the axes of a coordinated move leave together",
                        axis.p.brake_release_s
                    ),
                ));
            }
            run.members[j] = i;
            run.from[j] = start.theta;
            run.to[j] = target;
            starts[j] = start;
            limits[j] = move_limits(&axis.p);
        }
        let n = run.count;
        // The first state goes out at this tick (the newest of the axes' samples).
        run.given_for = newest_time(run.members[..n].iter().copied(), m) - period;
        self.planner
            .plan(&starts[..n], &run.to[..n], &limits[..n])
            .map_err(|e| refuse(Refusal::WrongState, e.to_string()))?;
        for j in 0..n {
            let i = run.members[j];
            axes.axis_mut(i).enter_coordinated(run.to[j], &m[i]);
        }
        self.running = Some(run);
        self.contour_peak = 0.0;
        Ok(())
    }

    /// Whether an enabled axis of `targets` still has its brake on at its measured time:
    /// a coordinated move asked now would be refused, and a client's, whose parts came
    /// together, waits for the release instead (at most `[axis] brake_release_s`).
    pub fn brakes_hold<A: Axes + ?Sized>(
        axes: &A,
        targets: &[(usize, f64)],
        m: &[Measured],
    ) -> bool {
        targets.iter().any(|&(i, _)| {
            i < axes.count()
                && m.get(i).is_some_and(|mi| {
                    let axis = axes.axis_ref(i);
                    axis.state() == AxisState::OperationEnabled && !axis.brake_released(mi.t)
                })
        })
    }

    /// Before the axes' own ticks at their measured states `m`: the running move's axes
    /// take their states for this tick; a move none of whose axes is still in it (each was
    /// commanded elsewhere, quick-stopped or faulted) is over.
    ///
    /// The move is stepped to the newest sample's time, a period at a time (none if the
    /// samples' time stood still, two if one tick's sample was skipped), as an axis's own
    /// trajectory is: stepped once a tick instead, a tick whose sample stood still moved the
    /// plan on without the rotors, and axes of different inertia and load took that step
    /// differently.
    pub fn before_tick<A: Axes + ?Sized>(&mut self, axes: &mut A, m: &[Measured]) {
        let Some(mut run) = self.running else {
            return;
        };
        let members = &run.members[..run.count];
        if !members.iter().any(|&i| axes.axis_ref(i).in_coordinated()) {
            self.running = None;
            return;
        }
        let period = self.planner.period_s();
        let now = newest_time(members.iter().copied(), m);
        let steps = if self.one_clock {
            ((now - run.given_for) / period).round().clamp(0.0, 1000.0) as u64
        } else {
            1
        };
        if steps == 0 {
            return;
        }
        // The move goes on for the axes still in it: one taken out (a command of its own,
        // policy Own) does not stop the others' move short.
        let mut last = false;
        for _ in 0..steps {
            last = self.planner.step(&mut self.next, &mut self.jerks);
            run.given_for += period;
            if last {
                break;
            }
        }
        // Of separate clocks, each axis takes the state at its own sample, whatever its time.
        let for_t = if self.one_clock {
            run.given_for
        } else {
            f64::NAN
        };
        for (j, &i) in members.iter().enumerate() {
            let axis = axes.axis_mut(i);
            if axis.in_coordinated() {
                axis.follow_coordinated(self.next[j], self.jerks[j], last, for_t);
            }
        }
        self.running = (!last).then_some(run);
    }

    /// After the axes' own ticks at their measured states `m`: the contour error, and the
    /// stop policy (an axis that started to stop at this tick, or by a command since the
    /// last, quick-stops every other enabled axis from the next tick on).
    pub fn after_tick<A: Axes + ?Sized>(&mut self, axes: &mut A, m: &[Measured]) {
        self.watch_contour(axes, m);
        self.apply_policy(axes, m);
    }

    /// The distance of the measured point from the running move's straight line: of its
    /// axes, the measured positions' component across the line from start to target.
    fn watch_contour<A: Axes + ?Sized>(&mut self, axes: &A, m: &[Measured]) {
        let Some(run) = &self.running else {
            return;
        };
        let k = run.count;
        let mut p = [0.0; MAX_AXES];
        let mut d = [0.0; MAX_AXES];
        // On the wall clock the axes' newest states can be a sample apart (each axis's
        // loops take theirs as it comes): each position is brought to the newest one's time
        // at its measured speed, so that the contour is the rotors' at one instant.
        let now = newest_time(run.members[..k].iter().copied(), m);
        for j in 0..k {
            let i = run.members[j];
            d[j] = run.to[j] - run.from[j];
            let ahead = if self.one_clock {
                m[i].omega * (now - m[i].t)
            } else {
                0.0
            };
            p[j] = axes.axis_ref(i).position(&m[i]) + ahead - run.from[j];
        }
        let length2: f64 = d[..k].iter().map(|x| x * x).sum();
        let along: f64 = p[..k].iter().zip(&d[..k]).map(|(a, b)| a * b).sum();
        // The residual of p after its projection on d, summed axis by axis: the same as
        // |p|² − (p·d)²/|d|², without that difference's cancellation (1e-7 rad of noise on
        // a 12 rad move).
        let s = if length2 > 0.0 { along / length2 } else { 0.0 };
        let across2: f64 = p[..k]
            .iter()
            .zip(&d[..k])
            .map(|(a, b)| (a - s * b) * (a - s * b))
            .sum();
        self.contour_peak = self.contour_peak.max(across2.sqrt());
    }

    fn apply_policy<A: Axes + ?Sized>(&mut self, axes: &mut A, m: &[Measured]) {
        let mut now = 0u32;
        for i in 0..axes.count() {
            if matches!(
                axes.axis_ref(i).state(),
                AxisState::Fault | AxisState::FaultReactionActive | AxisState::QuickStopActive
            ) {
                now |= 1 << i;
            }
        }
        let started = now & !self.stopping;
        if self.policy == StopPolicy::All && started != 0 {
            self.stopped_by = Some(started.trailing_zeros() as usize);
            for (i, mi) in m.iter().enumerate().take(axes.count()) {
                if axes.axis_mut(i).quick_stop_if_enabled(mi) {
                    now |= 1 << i;
                }
            }
        }
        self.stopping = now;
    }
}

/// The newest of the `axes`' sample times (`m[i].t`): on the wall clock the axes' newest
/// samples can be one apart.
pub fn newest_time(axes: impl IntoIterator<Item = usize>, m: &[Measured]) -> f64 {
    axes.into_iter()
        .map(|i| m[i].t)
        .fold(f64::NEG_INFINITY, f64::max)
}

fn unknown(i: usize, count: usize) -> Refused {
    refuse(
        Refusal::UnknownAxis,
        format!("no axis {i}: the group has axes 0 … {}", count - 1),
    )
}

/// The group: its axes and their coordination. See the module documentation.
#[derive(Debug)]
pub struct AxisGroup {
    axes: Vec<Axis>,
    coordinator: Coordinator,
}

impl std::ops::Deref for AxisGroup {
    type Target = Coordinator;
    fn deref(&self) -> &Coordinator {
        &self.coordinator
    }
}

impl AxisGroup {
    /// `params.len()` axes standing disabled, their position loop ticking every
    /// `period_s`.
    pub fn new(
        params: &[AxisParams],
        period_s: f64,
        policy: StopPolicy,
    ) -> Result<Self, GroupError> {
        if !(1..=MAX_AXES).contains(&params.len()) {
            return Err(GroupError::Axes(params.len()));
        }
        Ok(Self {
            axes: params.iter().map(|p| Axis::new(p, period_s)).collect(),
            coordinator: Coordinator::new(period_s, policy),
        })
    }

    pub fn len(&self) -> usize {
        self.axes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.axes.is_empty()
    }

    pub fn axis(&self, i: usize) -> Option<&Axis> {
        self.axes.get(i)
    }

    /// Axis `i`'s command, as [`Axis::request`] takes it.
    pub fn request(&mut self, i: usize, r: &AxisRequest, m: &Measured) -> Result<(), Refused> {
        let unknown = unknown(i, self.axes.len());
        self.axes.get_mut(i).ok_or(unknown)?.request(r, m)
    }

    /// A point of axis `i`'s stream, as [`Axis::stream_point`] takes it.
    pub fn stream_point(
        &mut self,
        i: usize,
        p: &AxisStreamPoint,
        m: &Measured,
    ) -> Result<(), Refused> {
        let unknown = unknown(i, self.axes.len());
        self.axes.get_mut(i).ok_or(unknown)?.stream_point(p, m)
    }

    /// [`Coordinator::move_together`] of this group's axes.
    pub fn move_together(
        &mut self,
        targets: &[(usize, f64)],
        m: &[Measured],
    ) -> Result<(), Refused> {
        self.coordinator
            .move_together(self.axes.as_mut_slice(), targets, m)
    }

    /// One tick of every axis at its measured state `m[i]`: the coordinated move's next
    /// states, each axis's own tick (its setpoint into `out[i]`), the contour error, and
    /// the stop policy.
    pub fn tick(&mut self, m: &[Measured], out: &mut [Setpoint]) -> Result<(), GroupError> {
        let n = self.axes.len();
        if m.len() != n || out.len() < n {
            return Err(GroupError::Lengths {
                axes: n,
                measured: m.len(),
                setpoints: out.len(),
            });
        }
        let axes = self.axes.as_mut_slice();
        self.coordinator.before_tick(axes, m);
        for (i, axis) in axes.iter_mut().enumerate() {
            out[i] = axis.tick(&m[i]);
        }
        self.coordinator.after_tick(axes, m);
        Ok(())
    }

    /// Axis `i`'s status at the tick just run, with its index.
    pub fn status(&mut self, i: usize, m: &Measured, torque: f64) -> Option<AxisStatus> {
        let axis = self.axes.get_mut(i)?;
        let mut s = axis.status(m, torque);
        s.axis = i as u32;
        Some(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_shared::axis::{AxisMode, RequestKind};

    const T: f64 = 500e-6;

    fn request(kind: RequestKind) -> AxisRequest {
        AxisRequest {
            kind: kind as u32,
            ..Default::default()
        }
    }

    /// Axes with these move limits (v, a, j), no brake delay.
    fn with_move_limits(limits: [(f64, f64, f64); 3]) -> Vec<AxisParams> {
        let mut params = vec![AxisParams::default(); 3];
        for (p, (v, a, j)) in params.iter_mut().zip(limits) {
            p.brake_release_s = 0.0;
            p.move_v_rad_s = v;
            p.move_a_rad_s2 = a;
            p.move_j_rad_s3 = j;
        }
        params
    }

    /// Three axes with their own move limits, no brake delay, enabled at t = 0 where their
    /// rotors stand (`at`).
    fn three(policy: StopPolicy, at: [f64; 3]) -> (AxisGroup, Vec<AxisParams>, [Measured; 3]) {
        let params = with_move_limits([
            (5.0, 50.0, 2000.0),
            (10.0, 100.0, 5000.0),
            (3.0, 20.0, 500.0),
        ]);
        let mut g = AxisGroup::new(&params, T, policy).expect("three axes");
        let m = at.map(|theta| Measured {
            theta,
            ..Default::default()
        });
        for (i, mi) in m.iter().enumerate() {
            g.request(i, &request(RequestKind::Enable), mi)
                .expect("enable");
        }
        (g, params, m)
    }

    /// [`three`] after its first tick (t = 0), the rotors where it put them: the setpoints'
    /// buffer is returned with them.
    fn three_ticked(
        policy: StopPolicy,
        at: [f64; 3],
    ) -> (AxisGroup, Vec<AxisParams>, [Measured; 3], [Setpoint; 3]) {
        let (mut g, params, mut m) = three(policy, at);
        let mut out = [idle_setpoint(); 3];
        g.tick(&m, &mut out).expect("tick");
        follow(&mut m, &out, 0);
        (g, params, m, out)
    }

    /// The rotors on their setpoints (a perfect plant) at the tick after `k`.
    fn follow(m: &mut [Measured; 3], out: &[Setpoint], k: u64) {
        for (mi, sp) in m.iter_mut().zip(out) {
            mi.t = (k + 1) as f64 * T;
            mi.theta = sp.reference.theta;
            mi.omega = sp.reference.omega;
        }
    }

    fn idle_setpoint() -> Setpoint {
        Setpoint {
            reference: Reference::default(),
            outputs_on: false,
            torque_ff: 0.0,
            epoch: 0,
            smooth: true,
            jerk: 0.0,
            brake_released: false,
        }
    }

    /// Three axes over 1, −6 and 12 rad with their own limits: every axis leaves on the
    /// tick after the command and stands on its target, target reached, on one tick; no
    /// axis passes its speed, acceleration or jerk limit; the setpoints stay on the straight
    /// line (phase synchronisation, rest to rest) and so does a perfect plant, whose contour
    /// error the group reports; the slowest axis's own optimum sets the duration.
    #[test]
    fn a_coordinated_move_leaves_and_arrives_on_one_tick_within_every_limit() {
        let start = [0.5, 2.0, -1.0];
        let goal = [1.5, -4.0, 11.0];
        let (mut g, params, mut m, mut out) = three_ticked(StopPolicy::All, start);
        let targets: Vec<(usize, f64)> = goal.iter().copied().enumerate().collect();
        g.move_together(&targets, &m).expect("planned");
        let duration = g.coordinated_duration_s().expect("running");
        let mut left = [None; 3];
        let mut arrived = [None; 3];
        let mut prev = out;
        let mut worst_line: f64 = 0.0;
        for k in 1..20_000u64 {
            g.tick(&m, &mut out).expect("tick");
            for i in 0..3 {
                let r = out[i].reference;
                let p = &params[i];
                assert!(
                    r.omega.abs() <= p.move_v_rad_s * (1.0 + 1e-9),
                    "axis {i} ω {}",
                    r.omega
                );
                assert!(
                    r.alpha.abs() <= p.move_a_rad_s2 * (1.0 + 1e-9),
                    "axis {i} α {}",
                    r.alpha
                );
                let jerk = (r.alpha - prev[i].reference.alpha) / T;
                assert!(
                    jerk.abs() <= p.move_j_rad_s3 * (1.0 + 1e-6),
                    "axis {i} j {jerk}"
                );
                if left[i].is_none() && r.theta != start[i] {
                    left[i] = Some(k);
                }
                let status = g.status(i, &m[i], 0.0).expect("status");
                assert_eq!(status.axis, i as u32);
                let reached = status.statusword
                    & u32::from(stepdrive_shared::axis::status_bits::TARGET_REACHED)
                    != 0;
                if arrived[i].is_none() && r.theta == goal[i] && reached {
                    arrived[i] = Some(k);
                }
            }
            // The setpoint's distance from the straight line, as a fraction of the path.
            let s = (out[0].reference.theta - start[0]) / (goal[0] - start[0]);
            for i in 1..3 {
                let on_line = start[i] + s * (goal[i] - start[i]);
                worst_line = worst_line.max((out[i].reference.theta - on_line).abs());
            }
            prev = out;
            follow(&mut m, &out, k);
            if arrived.iter().all(Option::is_some) && k > arrived[0].unwrap_or(0) + 10 {
                break;
            }
        }
        assert_eq!(left, [Some(1); 3], "left on ticks {left:?}");
        let ticks = (duration / T).round() as u64;
        assert_eq!(arrived, [Some(ticks); 3], "arrived on ticks {arrived:?}");
        assert!(worst_line < 1e-9, "off the line by {worst_line} rad");
        assert!(g.contour_peak() < 1e-9, "contour {}", g.contour_peak());
        assert!(!g.coordinated_running());
        for i in 0..3 {
            assert_eq!(g.axis(i).map(Axis::mode), Some(AxisMode::Coordinated));
        }
        // Axis 2 (12 rad at 3 rad/s) is the slowest; its own optimum is the move's length.
        let slowest = (0..3)
            .map(|i| g.planner.independent_duration_s(i))
            .fold(0.0, f64::max);
        assert!(
            (duration - slowest).abs() <= T,
            "{duration} s against {slowest} s"
        );
    }

    /// The contour error is the measured point's distance from the move's straight line:
    /// from (0, 0, 0) towards (3, 4, 0), a rotor set at (3, 0, 0) is 12/5 = 2.4 rad off it
    /// (|p × d| / |d|), and one on the line is not off at all.
    #[test]
    fn the_contour_error_is_the_distance_from_the_straight_line() {
        let (mut g, _, mut m, mut out) = three_ticked(StopPolicy::Own, [0.0; 3]);
        g.move_together(&[(0, 3.0), (1, 4.0), (2, 0.0)], &m)
            .expect("planned");
        m[0].theta = 1.5;
        m[1].theta = 2.0;
        g.tick(&m, &mut out).expect("tick");
        assert!(g.contour_peak() < 1e-15, "{}", g.contour_peak());
        m[0].theta = 3.0;
        m[1].theta = 0.0;
        g.tick(&m, &mut out).expect("tick");
        assert!(
            (g.contour_peak() - 2.4).abs() < 1e-12,
            "{}",
            g.contour_peak()
        );
    }

    /// A fault on one axis in the middle of a coordinated move (its drive latched one):
    /// that axis is in Fault, and on the same tick the other two are quick-stopped, brake
    /// to a standstill at their quick-stop deceleration and hold there, not faulted.
    #[test]
    fn a_faulted_axis_quick_stops_the_others_and_none_of_them_faults() {
        let (mut g, params, mut m, mut out) = three_ticked(StopPolicy::All, [0.0; 3]);
        g.move_together(&[(0, 3.0), (1, 8.0), (2, 10.0)], &m)
            .expect("planned");
        let mut fault_at = None;
        for k in 1..20_000u64 {
            if k == 800 {
                m[1].device_fault = 1;
            }
            g.tick(&m, &mut out).expect("tick");
            if k == 800 {
                fault_at = Some(k);
                assert_eq!(g.axis(1).map(Axis::state), Some(AxisState::Fault));
                for i in [0, 2] {
                    assert_eq!(
                        g.axis(i).map(Axis::state),
                        Some(AxisState::QuickStopActive),
                        "axis {i}"
                    );
                }
                assert_eq!(g.stopped_by(), Some(1));
            }
            if k > 800 {
                for i in [0, 2] {
                    let a = out[i].reference.alpha.abs();
                    assert!(
                        a <= params[i].quick_stop_decel_rad_s2 * (1.0 + 1e-9),
                        "axis {i} α {a}"
                    );
                }
            }
            follow(&mut m, &out, k);
            if k > 800 && [0, 2].iter().all(|&i| out[i].reference.omega == 0.0) {
                break;
            }
        }
        assert_eq!(fault_at, Some(800));
        for i in [0, 2] {
            assert_eq!(g.axis(i).map(Axis::state), Some(AxisState::QuickStopActive));
            assert_eq!(g.axis(i).map(Axis::fault), Some(0), "axis {i}");
            assert_eq!(out[i].reference.omega, 0.0, "axis {i} stands");
        }
        assert!(!g.coordinated_running());
        // The faulted axis stays in Fault; the others, enabled again, are not stopped again
        // by it.
        g.request(0, &request(RequestKind::Enable), &m[0])
            .expect("enable again");
        g.tick(&m, &mut out).expect("tick");
        assert_eq!(
            g.axis(0).map(Axis::state),
            Some(AxisState::OperationEnabled)
        );
    }

    /// Two axes of a coordinated move, axis 1's samples stamped `offset` s behind axis 0's
    /// (drives each with its own clock, or one simulated plant's samples one apart): axis
    /// 1's references over the whole move.
    fn coordinated_references(group: Coordinator, offset: f64) -> Vec<Reference> {
        let p = AxisParams {
            brake_release_s: 0.0,
            ..Default::default()
        };
        let mut axes = vec![Axis::new(&p, T), Axis::new(&p, T)];
        let mut group = group;
        let mut m = [Measured::default(); 2];
        let at = |k: u64, m: &mut [Measured; 2]| {
            m[0].t = 0.01 + k as f64 * T;
            m[1].t = m[0].t - offset;
        };
        at(0, &mut m);
        for (axis, mi) in axes.iter_mut().zip(&m) {
            axis.request(&request(RequestKind::Enable), mi)
                .expect("enable");
        }
        let mut out = Vec::new();
        for k in 0..2000u64 {
            at(k, &mut m);
            if k == 1 {
                group
                    .move_together(axes.as_mut_slice(), &[(0, 2.0), (1, -3.0)], &m)
                    .expect("planned");
            }
            group.before_tick(axes.as_mut_slice(), &m);
            let sp: Vec<Setpoint> = axes.iter_mut().zip(&m).map(|(a, mi)| a.tick(mi)).collect();
            group.after_tick(axes.as_mut_slice(), &m);
            for (mi, s) in m.iter_mut().zip(&sp) {
                mi.theta = s.reference.theta;
                mi.omega = s.reference.omega;
            }
            out.push(sp[1].reference);
        }
        out
    }

    /// Of one clock, an axis whose sample is 50 µs behind takes the move 50 µs back (the
    /// rotors at one instant on the line); of separate clocks, whose times do not compare,
    /// an axis takes the move as it comes, whatever its clock says (a drive that started
    /// 5 ms later moves exactly as one that did not).
    #[test]
    fn an_axis_takes_the_move_at_its_own_sample_only_when_the_clocks_are_one() {
        let new = || Coordinator::new(T, StopPolicy::All);
        let aligned = coordinated_references(new(), 0.0);
        assert_eq!(
            coordinated_references(new().separate_clocks(), 5e-3),
            aligned
        );
        let behind = coordinated_references(new(), 50e-6);
        let k = aligned
            .iter()
            .position(|r| r.omega.abs() > 1.0)
            .expect("the move runs");
        let back = aligned[k].theta - behind[k].theta;
        let d = 50e-6;
        let expected = aligned[k].omega * d - 0.5 * aligned[k].alpha * d * d;
        assert!(
            (back - expected).abs() < 1e-3 * expected.abs(),
            "50 µs behind: {back} rad back, ωd − αd²/2 = {expected} rad"
        );
    }

    /// The timeline of a realtime run of `scenarios/three-axes.toml`: the position loop's
    /// ticks are on its own clock, so the newest sample at a tick is 10 samples after the
    /// last one's, or 9, 11, or fewer when a tick came late; each lane ticks on its own
    /// newest sample, and the group steps its move only at the ticks of axis 0 (the lanes'
    /// `before_lanes`). Whatever the timeline, each axis takes the move where it is at its
    /// own sample's time: between two of its ticks θ_d advances by the mean of their ω_d
    /// times the time between them. Before, a tick at which the group gave no state (its
    /// samples 0.45 ms on: the move's step rounded to none; or axis 0 had no new sample)
    /// stood on the last one's θ_d, at a later time: 3.6e-3 rad behind the rotor at 8 rad/s,
    /// and the current loop pulled the rotor back for a tick.
    #[test]
    fn on_a_realtime_timeline_each_axis_takes_the_move_at_its_own_sample_time() {
        const SAMPLE: f64 = 50e-6;
        // Samples between the newest states of consecutive ticks, as recorded.
        const GAPS: [u64; 36] = [
            10, 10, 9, 9, 10, 10, 9, 6, 11, 1, 9, 5, 8, 1, 10, 7, 4, 9, 1, 9, 10, 4, 9, 9, 3, 1, 1,
            1, 9, 9, 9, 9, 9, 9, 7, 3,
        ];
        let params = with_move_limits([
            (5.0, 50.0, 2000.0),
            (10.0, 100.0, 5000.0),
            (8.0, 40.0, 1000.0),
        ]);
        let mut axes: Vec<Axis> = params.iter().map(|p| Axis::new(p, T)).collect();
        let mut group = Coordinator::new(T, StopPolicy::All);
        let mut m = [Measured::default(); 3];
        for (axis, mi) in axes.iter_mut().zip(&m) {
            axis.request(&request(RequestKind::Enable), mi)
                .expect("enable");
        }
        // A lane's newest sample lags the newest of all by 0 or 1 (each is published as it
        // is computed), and axis 0's sometimes has not come at all (pseudo-random, fixed).
        let mut lcg = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = || {
            lcg = lcg
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            lcg >> 33
        };
        let mut newest = 0u64;
        let mut used = [None::<u64>; 3];
        let mut last: [Option<(f64, Reference)>; 3] = [None; 3];
        let mut worst: f64 = 0.0;
        let mut stood = 0;
        let mut moving = false;
        for cycle in 0..6000usize {
            newest += GAPS[cycle % GAPS.len()];
            let mut seq = [newest; 3];
            for (i, s) in seq.iter_mut().enumerate() {
                *s -= next() % 2;
                if i == 0 && next() % 8 == 0 {
                    *s = used[0].unwrap_or(*s);
                }
            }
            let ticks: Vec<bool> = (0..3).map(|i| used[i] != Some(seq[i])).collect();
            for i in 0..3 {
                m[i].t = seq[i] as f64 * SAMPLE;
                // The rotor on its setpoint, carried on by the current loop.
                if let Some((t, r)) = last[i] {
                    m[i].theta = r.after(m[i].t - t).theta;
                    m[i].omega = r.after(m[i].t - t).omega;
                }
            }
            if ticks[0] {
                if cycle == 20 {
                    group
                        .move_together(axes.as_mut_slice(), &[(0, 1.0), (1, -6.0), (2, 12.0)], &m)
                        .expect("planned");
                    moving = true;
                }
                group.before_tick(axes.as_mut_slice(), &m);
            }
            for i in (0..3).filter(|&i| ticks[i]) {
                let r = axes[i].tick(&m[i]).reference;
                if let (Some((t0, r0)), true) = (last[i], moving) {
                    let dt = m[i].t - t0;
                    let expected = 0.5 * (r0.omega + r.omega) * dt;
                    worst = worst.max((r.theta - r0.theta - expected).abs());
                    if r.theta == r0.theta && r.omega != 0.0 && dt > 0.0 {
                        stood += 1;
                    }
                }
                last[i] = Some((m[i].t, r));
                used[i] = Some(seq[i]);
            }
            if ticks[0] {
                group.after_tick(axes.as_mut_slice(), &m);
            }
        }
        assert!(
            moving && !group.coordinated_running(),
            "the move ran to its end"
        );
        for (i, axis) in axes.iter().enumerate() {
            assert_eq!(axis.state(), AxisState::OperationEnabled, "axis {i}");
        }
        assert_eq!(stood, 0, "ticks at which a moving θ_d stood still");
        assert!(worst < 1e-6, "θ_d off its own time by up to {worst:e} rad");
    }

    /// With each axis to its own (policy Own), a quick stop of one axis stops that axis only:
    /// the others finish the coordinated move on its tick.
    #[test]
    fn with_policy_own_the_others_finish_the_move() {
        let (mut g, _, mut m, mut out) = three_ticked(StopPolicy::Own, [0.0; 3]);
        g.move_together(&[(0, 2.0), (1, 4.0), (2, 6.0)], &m)
            .expect("planned");
        let ticks = (g.coordinated_duration_s().expect("running") / T).round() as u64;
        for k in 1..=ticks {
            if k == 100 {
                g.request(1, &request(RequestKind::QuickStop), &m[1])
                    .expect("quick stop");
            }
            g.tick(&m, &mut out).expect("tick");
            follow(&mut m, &out, k);
        }
        assert_eq!(g.axis(1).map(Axis::state), Some(AxisState::QuickStopActive));
        assert_eq!(out[0].reference.theta, 2.0);
        assert_eq!(out[2].reference.theta, 6.0);
        assert!(out[1].reference.theta < 4.0);
        assert!(!g.coordinated_running());
    }

    /// A coordinated move that cannot be taken is refused naming the axis and why, and
    /// leaves every axis as it was.
    #[test]
    fn a_coordinated_move_that_cannot_be_taken_says_why_and_moves_nothing() {
        let (mut g, _, m, mut out) = three_ticked(StopPolicy::All, [0.0; 3]);
        let limit = g.axis(2).map(|a| a.p.position_max_rad).unwrap_or(f64::NAN);
        type Case<'a> = (&'a [(usize, f64)], Refusal, &'a str);
        let cases: [Case; 6] = [
            (&[], Refusal::UnknownAxis, "1 … 8 axes"),
            (
                &[(0, 1.0), (0, 2.0)],
                Refusal::UnknownAxis,
                "axis 0 is named twice",
            ),
            (&[(0, 1.0), (3, 2.0)], Refusal::UnknownAxis, "no axis 3"),
            (&[(1, f64::NAN)], Refusal::NotFinite, "axis 1: target NaN"),
            (
                &[(0, 1.0), (2, limit + 1.0)],
                Refusal::OutsideSoftLimits,
                "axis 2: ",
            ),
            (
                &[(0, 1.0)],
                Refusal::NotEnabled,
                "axis 0: a coordinated move needs Operation enabled",
            ),
        ];
        for (j, (targets, refusal, says)) in cases.iter().enumerate() {
            if j == cases.len() - 1 {
                g.request(0, &request(RequestKind::DisableOperation), &m[0])
                    .expect("disable");
            }
            let e = g.move_together(targets, &m).expect_err("refused");
            assert_eq!(e.refusal, *refusal, "{}", e.text);
            assert!(e.text.contains(says), "{}", e.text);
            assert!(!g.coordinated_running());
            for i in 0..3 {
                assert_ne!(g.axis(i).map(Axis::mode), Some(AxisMode::Coordinated));
            }
        }
        // One at a time: a second coordinated move while one runs is refused.
        g.move_together(&[(1, 1.0), (2, 1.0)], &m).expect("planned");
        let e = g.move_together(&[(1, 2.0)], &m).expect_err("refused");
        assert_eq!(e.refusal, Refusal::Moving, "{}", e.text);
        // The tick's lengths are checked, not trusted.
        assert_eq!(
            g.tick(&m[..2], &mut out),
            Err(GroupError::Lengths {
                axes: 3,
                measured: 2,
                setpoints: 3
            })
        );
        assert_eq!(
            AxisGroup::new(&[], T, StopPolicy::All).err(),
            Some(GroupError::Axes(0))
        );
    }

    /// An axis taken into a coordinated move while it jogs keeps θ_d, ω_d and α_d
    /// continuous: the move starts from its setpoint, moving.
    #[test]
    fn a_coordinated_move_takes_a_jogging_axis_on_without_a_jump() {
        let (mut g, params, mut m) = three(StopPolicy::All, [0.0; 3]);
        let mut out = [idle_setpoint(); 3];
        let jog = AxisRequest {
            kind: RequestKind::Jog as u32,
            velocity_rad_s: 2.0,
            ..Default::default()
        };
        g.request(0, &jog, &m[0]).expect("jog");
        let mut prev = out;
        for k in 0..2000u64 {
            if k == 1000 {
                g.move_together(&[(0, 0.5), (1, 3.0)], &m).expect("planned");
            }
            g.tick(&m, &mut out).expect("tick");
            if k > 0 {
                let (a, b) = (prev[0].reference, out[0].reference);
                assert!(
                    (b.alpha - a.alpha).abs() <= params[0].j_max_rad_s3 * T * (1.0 + 1e-6),
                    "k {k}: α {} → {}",
                    a.alpha,
                    b.alpha
                );
                assert!(
                    (b.omega - a.omega).abs() <= params[0].a_max_rad_s2 * T * 1.01,
                    "k {k}: ω {} → {}",
                    a.omega,
                    b.omega
                );
            }
            prev = out;
            follow(&mut m, &out, k);
        }
    }
}
