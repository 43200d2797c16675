//! Online trajectory generation: time-optimal, jerk-limited, from any state (θ, ω, α) to a
//! position or a velocity, re-targetable at every tick with continuous acceleration; and
//! tracking of a moving target (a stream) within the same limits. A thin layer over
//! `rsruckig` (a port of Ruckig) that makes its inputs valid before every call — on its
//! error path the crate allocates and leaves its output stale — clamps a jog's speed (its
//! velocity interface does not), and puts a finished move exactly on its target (the crate
//! extrapolates its numerically computed end state, which creeps ~1e-10 rad/s).
//!
//! Construction allocates (a few small buffers); a step does not.

use rsruckig::prelude::*;
use stepdrive_shared::trajectory::Reference;

/// Speed, acceleration and jerk bounds, all positive.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    pub v: f64,
    pub a: f64,
    pub j: f64,
}

impl Limits {
    /// Finite and positive.
    pub fn valid(&self) -> bool {
        [self.v, self.a, self.j]
            .iter()
            .all(|x| x.is_finite() && *x > 0.0)
    }
}

/// Where the generator heads.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Goal {
    /// Stand still at this position.
    Position(f64),
    /// Run at this speed.
    Velocity(f64),
}

/// The generator could not continue from its state (only states far outside the limits:
/// a speed hundreds of times the limit with no room to brake).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("the trajectory generator cannot continue from θ {theta} rad, ω {omega} rad/s, α {alpha} rad/s²: {why}")]
pub struct OtgError {
    pub theta: f64,
    pub omega: f64,
    pub alpha: f64,
    pub why: String,
}

/// The generator. See the module documentation.
pub struct Otg {
    ruckig: Ruckig<1, ThrowErrorHandler>,
    tracker: Trackig<1, ThrowErrorHandler>,
    input: InputParameter<1>,
    output: OutputParameter<1>,
    target: TargetState<1>,
    goal: Goal,
    /// Finished: at its position goal, or at its speed.
    done: bool,
    period_s: f64,
    /// The jerk of the trajectory at its current state, rad/s³.
    jerk: f64,
    /// A second generator that plans what a command would do, to judge it before it is
    /// taken ([`Otg::plan_duration`]); allocated here, not when a command comes.
    planner: Ruckig<1, ThrowErrorHandler>,
    plan_input: InputParameter<1>,
    plan: Trajectory<1>,
}

impl std::fmt::Debug for Otg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Otg")
            .field("state", &self.state())
            .field("goal", &self.goal)
            .field("done", &self.done)
            .finish()
    }
}

impl Otg {
    /// A generator stepping `period_s` at a time, standing at `at` with `limits`.
    pub fn new(period_s: f64, at: Reference, limits: Limits) -> Self {
        let mut g = Self {
            ruckig: Ruckig::new(None, period_s),
            tracker: Trackig::new(None, period_s),
            input: InputParameter::new(None),
            output: OutputParameter::new(None),
            target: TargetState::new(None),
            goal: Goal::Position(at.theta),
            done: true,
            period_s,
            jerk: 0.0,
            planner: Ruckig::new(None, period_s),
            plan_input: InputParameter::new(None),
            plan: Trajectory::new(None),
        };
        // Each DoF its own profile toward a moving target: what tracking wants.
        g.input.synchronization = Synchronization::None;
        g.set_limits(limits);
        g.restart(at);
        g.input.target_position[0] = at.theta;
        g
    }

    /// The state it stands at now.
    pub fn state(&self) -> Reference {
        Reference {
            theta: self.input.current_position[0],
            omega: self.input.current_velocity[0],
            alpha: self.input.current_acceleration[0],
        }
    }

    pub fn goal(&self) -> Goal {
        self.goal
    }

    /// The trajectory's jerk where it stands, rad/s³ (0 at rest or at speed).
    pub fn jerk(&self) -> f64 {
        self.jerk
    }

    /// At its goal: standing at the position, or running at the speed.
    pub fn done(&self) -> bool {
        self.done
    }

    pub fn limits(&self) -> Limits {
        Limits {
            v: self.input.max_velocity[0],
            a: self.input.max_acceleration[0],
            j: self.input.max_jerk[0],
        }
    }

    /// Starts over from `at` (an enable: the measured position at rest); the goal becomes
    /// to stand there.
    pub fn restart(&mut self, at: Reference) {
        self.input.current_position[0] = at.theta;
        self.input.current_velocity[0] = at.omega;
        self.input.current_acceleration[0] = at.alpha;
        self.jerk = 0.0;
        self.tracker.reset();
        self.hold();
    }

    /// Stand where the trajectory ends: at once if standing still, else braking.
    pub fn hold(&mut self) {
        let s = self.state();
        if s.omega == 0.0 && s.alpha == 0.0 {
            self.set_goal(Goal::Position(s.theta));
        } else {
            self.set_goal(Goal::Velocity(0.0));
        }
    }

    /// New limits, from the next step (they must be [`Limits::valid`]; invalid ones are the
    /// caller's bug and keep the old).
    pub fn set_limits(&mut self, limits: Limits) {
        if !limits.valid() {
            return;
        }
        self.input.max_velocity[0] = limits.v;
        self.input.max_acceleration[0] = limits.a;
        self.input.max_jerk[0] = limits.j;
        if let Goal::Velocity(v) = self.goal {
            self.input.target_velocity[0] = v.clamp(-limits.v, limits.v);
        }
        self.done = false;
    }

    /// Heads for `goal` from the current state (re-targeting mid-move keeps θ, ω and α
    /// continuous). A non-finite goal is ignored (the caller refuses those).
    pub fn set_goal(&mut self, goal: Goal) {
        let i = &mut self.input;
        match goal {
            Goal::Position(p) if p.is_finite() => {
                i.control_interface = ControlInterface::Position;
                i.target_position[0] = p;
                i.target_velocity[0] = 0.0;
                i.target_acceleration[0] = 0.0;
            }
            Goal::Velocity(v) if v.is_finite() => {
                // Its velocity interface does not bound the target speed.
                let vmax = i.max_velocity[0];
                i.control_interface = ControlInterface::Velocity;
                i.target_velocity[0] = v.clamp(-vmax, vmax);
                i.target_acceleration[0] = 0.0;
            }
            _ => return,
        }
        self.goal = goal;
        self.done = false;
    }

    fn error(&self, e: RuckigError) -> OtgError {
        let s = self.state();
        OtgError {
            theta: s.theta,
            omega: s.omega,
            alpha: s.alpha,
            why: e.to_string(),
        }
    }

    /// One period along the trajectory toward the goal; returns the new state.
    pub fn step(&mut self) -> Result<Reference, OtgError> {
        if self.done {
            self.jerk = 0.0;
            if let Goal::Velocity(_) = self.goal {
                // At its speed: the position runs on.
                self.input.current_position[0] += self.input.current_velocity[0] * self.period_s;
            }
            return Ok(self.state());
        }
        let result = self
            .ruckig
            .update(&self.input, &mut self.output)
            .map_err(|e| self.error(e))?;
        self.output.pass_to_input(&mut self.input);
        self.jerk = self.output.new_jerk[0];
        if result == RuckigResult::Finished {
            self.done = true;
            self.jerk = 0.0;
            match self.goal {
                Goal::Position(p) => {
                    // Exactly on the target, at rest: nothing left to creep.
                    self.input.current_position[0] = p;
                    self.input.current_velocity[0] = 0.0;
                    self.input.current_acceleration[0] = 0.0;
                }
                Goal::Velocity(_) => {
                    self.input.current_velocity[0] = self.input.target_velocity[0];
                    self.input.current_acceleration[0] = 0.0;
                }
            }
        }
        Ok(self.state())
    }

    /// One period following a moving `target` as closely as the limits allow (exactly,
    /// once caught up, when the target itself keeps within them); returns the new state.
    pub fn track(&mut self, target: Reference) -> Result<Reference, OtgError> {
        let vmax = self.input.max_velocity[0];
        let amax = self.input.max_acceleration[0];
        self.target.position[0] = target.theta;
        self.target.velocity[0] = target.omega.clamp(-vmax, vmax);
        self.target.acceleration[0] = target.alpha.clamp(-amax, amax);
        self.input.control_interface = ControlInterface::Position;
        self.tracker
            .update(&self.target, &self.input, &mut self.output)
            .map_err(|e| self.error(e))?;
        self.output.pass_to_input(&mut self.input);
        self.jerk = self.output.new_jerk[0];
        self.goal = Goal::Position(target.theta);
        self.done = false;
        Ok(self.state())
    }

    /// How long the generator would take from `from` to `goal` with `limits`, s: to stand
    /// at a position goal, or to reach a speed goal (then it runs on). Nothing of the
    /// generator's own trajectory changes. An error if it cannot plan it (limits it cannot
    /// resolve, a state far outside them).
    pub fn plan_duration(
        &mut self,
        from: Reference,
        goal: Goal,
        limits: Limits,
    ) -> Result<f64, OtgError> {
        let fail = |why: String| OtgError {
            theta: from.theta,
            omega: from.omega,
            alpha: from.alpha,
            why,
        };
        if !limits.valid() {
            return Err(fail(format!("limits {limits:?}")));
        }
        let i = &mut self.plan_input;
        i.current_position[0] = from.theta;
        i.current_velocity[0] = from.omega;
        i.current_acceleration[0] = from.alpha;
        i.max_velocity[0] = limits.v;
        i.max_acceleration[0] = limits.a;
        i.max_jerk[0] = limits.j;
        i.target_acceleration[0] = 0.0;
        match goal {
            Goal::Position(p) if p.is_finite() => {
                i.control_interface = ControlInterface::Position;
                i.target_position[0] = p;
                i.target_velocity[0] = 0.0;
            }
            Goal::Velocity(v) if v.is_finite() => {
                i.control_interface = ControlInterface::Velocity;
                i.target_velocity[0] = v.clamp(-limits.v, limits.v);
            }
            _ => return Err(fail(format!("goal {goal:?}"))),
        }
        self.planner
            .calculate(&self.plan_input, &mut self.plan)
            .map_err(|e| fail(e.to_string()))?;
        let d = self.plan.get_duration();
        if !(d.is_finite() && d >= 0.0) {
            return Err(fail(format!("a duration of {d} s")));
        }
        Ok(d)
    }

    /// How long a rest-to-rest move over `distance` takes with `limits`, s (what the
    /// generator plans; for the time-optimality checks).
    pub fn duration(distance: f64, limits: Limits, period_s: f64) -> Option<f64> {
        let mut ruckig = Ruckig::<1, ThrowErrorHandler>::new(None, period_s);
        let mut input = InputParameter::<1>::new(None);
        input.target_position[0] = distance;
        input.max_velocity[0] = limits.v;
        input.max_acceleration[0] = limits.a;
        input.max_jerk[0] = limits.j;
        let mut trajectory = Trajectory::<1>::new(None);
        ruckig.calculate(&input, &mut trajectory).ok()?;
        Some(trajectory.get_duration())
    }
}

/// The closed-form duration of the time-optimal jerk-limited rest-to-rest move over
/// `distance` (the classic 7-segment profile: each of v, a reached or not), s.
pub fn optimal_duration(distance: f64, l: Limits) -> f64 {
    let d = distance.abs();
    if d == 0.0 {
        return 0.0;
    }
    let (v, a, j) = (l.v, l.a, l.j);
    // Acceleration phase to speed w: with a reached if w ≥ a²/j.
    let accel_time = |w: f64| -> f64 {
        if w * j >= a * a {
            w / a + a / j
        } else {
            2.0 * (w / j).sqrt()
        }
    };
    // Distance covered accelerating from rest to w (and braking back): w · accel_time(w).
    let ramp_distance = |w: f64| w * accel_time(w);
    if ramp_distance(v) <= d {
        // v reached: cruise the rest.
        return 2.0 * accel_time(v) + (d - ramp_distance(v)) / v;
    }
    // v not reached: find the peak speed w with ramp_distance(w) = d (monotonic).
    let (mut lo, mut hi) = (0.0, v);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if ramp_distance(mid) < d {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    2.0 * accel_time(0.5 * (lo + hi))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const T: f64 = 500e-6;

    fn rest(theta: f64) -> Reference {
        Reference {
            theta,
            omega: 0.0,
            alpha: 0.0,
        }
    }

    /// Rest-to-rest durations against the closed form: 5 distances × 3 limit sets, to 1e-9
    /// relative (the generator's own plan; its sampled run ends on the tick after).
    #[test]
    fn rest_to_rest_moves_take_the_closed_form_time() {
        let sets = [
            Limits {
                v: 13.13,
                a: 50.0,
                j: 2000.0,
            },
            Limits {
                v: 5.0,
                a: 100.0,
                j: 5000.0,
            },
            Limits {
                v: 30.0,
                a: 500.0,
                j: 50_000.0,
            },
        ];
        for l in sets {
            for d in [1e-3, 0.1, 1.0, 5.0, 20.0] {
                let planned = Otg::duration(d, l, T).expect("plans");
                let optimal = optimal_duration(d, l);
                assert!(
                    (planned - optimal).abs() <= 1e-9 * optimal,
                    "{d} rad with {l:?}: {planned} s planned, {optimal} s optimal"
                );
            }
        }
    }

    /// A finished move stands exactly on its target, and stays there.
    #[test]
    fn a_move_ends_exactly_on_its_target_and_holds() {
        let l = Limits {
            v: 13.13,
            a: 50.0,
            j: 2000.0,
        };
        let mut g = Otg::new(T, rest(0.0), l);
        g.set_goal(Goal::Position(20.0));
        let mut ticks = 0;
        while !g.done() {
            g.step().expect("steps");
            ticks += 1;
            assert!(ticks < 100_000);
        }
        let planned = optimal_duration(20.0, l);
        assert!((ticks as f64 * T - planned).abs() <= T, "{ticks} ticks");
        for _ in 0..1000 {
            assert_eq!(g.step().expect("holds"), rest(20.0));
        }
    }

    /// A jog's speed is bounded by the limit, whatever is asked (the caller refuses more;
    /// the generator must not exceed it either way).
    #[test]
    fn a_jog_never_exceeds_the_speed_limit() {
        let l = Limits {
            v: 2.0,
            a: 50.0,
            j: 2000.0,
        };
        let mut g = Otg::new(T, rest(0.0), l);
        g.set_goal(Goal::Velocity(5.0));
        for _ in 0..2000 {
            let s = g.step().expect("steps");
            assert!(s.omega.abs() <= 2.0 * (1.0 + 1e-9), "{s:?}");
        }
        assert!((g.state().omega - 2.0).abs() < 1e-9);
    }

    fn limits() -> impl Strategy<Value = Limits> {
        (0.5f64..50.0, 1.0f64..500.0, 10.0f64..1e5).prop_map(|(v, a, j)| Limits { v, a, j })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// Random targets and limits, re-targeted every few ticks: |ω| ≤ v, |α| ≤ a, |jerk|
        /// ≤ j to 1e-9 relative, θ, ω, α continuous across every re-target (a jump would
        /// show as a jerk beyond the limit, or a θ/ω step the previous state cannot reach in
        /// one period), and the last target reached and held.
        #[test]
        fn limits_hold_across_re_targets(
            l in limits(),
            targets in proptest::collection::vec((-100.0f64..100.0, 1u32..20, any::<bool>()), 1..12),
        ) {
            let mut g = Otg::new(T, rest(0.0), l);
            let mut prev = g.state();
            let tol = 1.0 + 1e-9;
            let check = |prev: Reference, s: Reference| -> Result<(), TestCaseError> {
                prop_assert!(s.omega.abs() <= l.v * tol, "ω {} > {}", s.omega, l.v);
                prop_assert!(s.alpha.abs() <= l.a * tol, "α {} > {}", s.alpha, l.a);
                let jerk = (s.alpha - prev.alpha) / T;
                prop_assert!(jerk.abs() <= l.j * tol, "jerk {jerk} > {}", l.j);
                // θ and ω follow from the previous state with a bounded jerk.
                let omega_bound = prev.omega + prev.alpha * T;
                prop_assert!((s.omega - omega_bound).abs() <= 0.5 * l.j * T * T * tol + 1e-12);
                let theta_bound = prev.theta + prev.omega * T + 0.5 * prev.alpha * T * T;
                prop_assert!((s.theta - theta_bound).abs() <= l.j * T * T * T / 6.0 * tol + 1e-12);
                Ok(())
            };
            for (target, ticks, jog) in targets {
                let goal = if jog { Goal::Velocity(target / 10.0) } else { Goal::Position(target) };
                g.set_goal(goal);
                for _ in 0..ticks {
                    let s = g.step().expect("steps");
                    check(prev, s)?;
                    prev = s;
                }
            }
            g.set_goal(Goal::Position(1.0));
            let mut n = 0;
            while !g.done() {
                let s = g.step().expect("steps");
                check(prev, s)?;
                prev = s;
                n += 1;
                prop_assert!(n < 10_000_000);
            }
            for _ in 0..100 {
                prop_assert_eq!(g.step().expect("holds"), rest(1.0));
            }
        }
    }
}
