//! The current loop body, run once per plant sample: the selected method's desired currents
//! (commutation (17) with the fresh rotor angle, or the microstepping references), the
//! sampled current tracking law, the bus limit, and the voltage plan for the periods after.
//! Pure: no IPC, no clock, no allocation.

use crate::laws::commutation::commutate;
use crate::laws::current_tracking::SampledCurrentLaw;
use crate::laws::microstepping::{microstep_currents, microstep_voltages};
use crate::laws::phasor::{Complex, Rotating};
use crate::laws::pi_current::PiCurrent;
use stepdrive_shared::messages::{
    setpoint_flags, DriveCommand, DrivePlan, DriveState, TorqueSetpoint, MAX_PLAN,
};
use stepdrive_shared::scenario::MAX_COMPUTE_DELAY_PERIODS;
use stepdrive_shared::{Method, Scenario};

const MAX_DELAY: usize = MAX_COMPUTE_DELAY_PERIODS as usize;

#[derive(Debug, Clone)]
pub struct CurrentLoop {
    method: Method,
    law: SampledCurrentLaw,
    /// The industrial baseline's PI loops (its integrators are its only state).
    pi: PiCurrent,
    k_m: f64,
    n_r: f64,
    r: f64,
    v_max: f64,
    bus_v: f64,
    period: f64,
    delay: usize,
    plan_periods: usize,
    /// After answering sample m: the voltages of periods m+1 ..= m+d, oldest first (the
    /// last is the one just sent; the others were sent before).
    decided: [[f64; 2]; MAX_DELAY],
    /// The sample answered last, and that command's sequence number.
    answered: Option<(u64, u64)>,
    /// Where the plan for the last command starts (set by `on_sample`, used by `plan`),
    /// and the bus voltage its voltages are clamped to.
    seed: Option<(Seed, f64)>,
    /// The last plan, built in place (~8 KB); `len` 0 until one is made.
    plan: DrivePlan,
}

/// How the plan continues past the period just decided.
#[derive(Debug, Clone, Copy)]
enum Seed {
    /// Iterate the current law from the current `start` predicted at sample k+d+1, with the
    /// references and the back-EMF positioned there.
    Law {
        start: [f64; 2],
        references: Rotating,
        emf: Rotating,
    },
    /// Open loop: the voltages themselves.
    Voltages(Rotating),
}

impl CurrentLoop {
    /// Plans `drive.command_plan_periods` ahead; see [`Self::with_plan_periods`].
    pub fn new(s: &Scenario, method: Method) -> Self {
        let decay = match method {
            Method::Lyapunov => s.gains.rho_per_s,
            Method::Proposed | Method::OpenLoop | Method::Pi => s.gains.k3_per_s,
        };
        let m = &s.motor;
        Self {
            method,
            law: SampledCurrentLaw::new(
                m.resistance_ohm,
                m.inductance_h,
                m.torque_constant_nm_per_a,
                m.n_r(),
                s.sample_period_s(),
                decay,
            ),
            pi: PiCurrent::new(
                m.inductance_h,
                m.resistance_ohm,
                s.pi_bandwidth_rad_s(),
                s.sample_period_s(),
            ),
            k_m: m.torque_constant_nm_per_a,
            n_r: m.n_r(),
            r: m.resistance_ohm,
            v_max: s.gains.v_max_v,
            bus_v: s.drive.bus_voltage_v,
            period: s.sample_period_s(),
            // Validated ≤ MAX_COMPUTE_DELAY_PERIODS and ≤ MAX_PLAN by the scenario.
            delay: (s.rates.compute_delay_periods as usize).min(MAX_DELAY),
            plan_periods: (s.drive.command_plan_periods as usize).min(MAX_PLAN),
            decided: [[0.0; 2]; MAX_DELAY],
            answered: None,
            seed: None,
            plan: DrivePlan::default(),
        }
    }

    /// How many periods each plan covers (at most [`MAX_PLAN`]). Lockstep uses 0: its plant
    /// waits for every command, so it never needs a plan.
    pub fn with_plan_periods(mut self, periods: usize) -> Self {
        self.plan_periods = periods.min(MAX_PLAN);
        self
    }

    pub fn method(&self) -> Method {
        self.method
    }

    /// The voltages the drive applies over periods k .. k+d−1, as far as this loop knows:
    /// what it sent for them, or, for periods whose own command it never sent (it skipped
    /// samples), the entry of its last plan that the drive falls back on.
    fn decided_before(&self, k: u64) -> [[f64; 2]; MAX_DELAY] {
        let d = self.delay as u64;
        let Some((m, _)) = self.answered.filter(|&(m, _)| m + 1 < k) else {
            return self.decided;
        };
        let mut out = [[0.0; 2]; MAX_DELAY];
        for (p, slot) in (k..k + d).zip(out.iter_mut()) {
            *slot = if p <= m + d {
                self.decided[(p - m - 1) as usize]
            } else {
                self.planned(p, m)
            };
        }
        out
    }

    /// What the drive applies in period `p`, after the periods of the last command (which
    /// answered sample `m`): the entry for `p` of the last plan this loop made (the plant's
    /// freshest; it may continue an earlier command than the last); past that plan's end,
    /// the voltage held from the period before: the plan's last entry, or, for a plan that
    /// ends before the last command's periods do, that command's voltage.
    fn planned(&self, p: u64, m: u64) -> [f64; 2] {
        let d = self.delay as u64;
        let held = self.decided[self.delay - 1];
        if self.plan.len == 0 || self.plan.answers_seq > m {
            return held;
        }
        let last = self.plan.answers_seq + d + u64::from(self.plan.len);
        if last <= m + d {
            return held;
        }
        self.plan.voltage_for(p.min(last), d).unwrap_or(held)
    }

    /// One cycle: the command answering `state`, given the position loop's latest setpoint.
    /// `publish_time_ns` is left for the caller. Keeps what [`Self::plan`] needs.
    pub fn on_sample(&mut self, state: &DriveState, setpoint: &TorqueSetpoint) -> DriveCommand {
        let (theta, omega) = (state.theta_rad, state.omega_rad_s);
        let i = [state.i_a_a, state.i_b_a];
        let t = state.sample_time_s;
        let d = self.delay;
        let all_decided = self.decided_before(state.seq);
        let decided = &all_decided[..d];
        // The drive cannot apply more than its measured bus (a bridge refuses to send it).
        let measured = state.bus_voltage_v;
        let bus_v = if measured.is_finite() && measured > 0.0 {
            measured.min(self.bus_v)
        } else {
            self.bus_v
        };
        let (k_m, n_r, period) = (self.k_m, self.n_r, self.period);
        let planning = self.plan_periods > 0;
        // The first planned period starts at sample k+d+1.
        let t_plan = t + period * (d + 1) as f64;
        let clamp = |v: [f64; 2]| v.map(|x| x.clamp(-bus_v, bus_v));
        let law = self.law;
        // A jerk-limited setpoint's acceleration is continuous: the rotor's speed over the
        // periods ahead is predicted with it. The scenario's profile (the paper's experiment,
        // its acceleration a step at each corner) runs the sampled law as designed, at
        // constant speed.
        let alpha = match setpoint.flags & setpoint_flags::ACCELERATION_AHEAD != 0 {
            true => setpoint.alpha_d_rad_s2,
            false => 0.0,
        };
        let ahead = |j: usize| {
            let tj = period * j as f64;
            theta + omega * tj + 0.5 * alpha * tj * tj
        };
        // The current at k+d+1 once `v` has been applied from `predicted` at k+d, and the
        // back-EMF from there on: at the rotor's speed, or accelerating as the law decided
        // (a plan at constant speed through a deceleration fed the back-EMF of a rotor too
        // fast: a 2 ms hold of the loop left the rotor 0.015 rad/s ahead, 8e-5 rad off).
        let seed_law = |predicted: [f64; 2], v: [f64; 2], references: Rotating| {
            let speed = |j: usize| omega + alpha * period * j as f64;
            let mid = speed(d) + 0.5 * alpha * period;
            let (start, emf) = match alpha == 0.0 {
                true => {
                    let theta_d = theta + omega * period * d as f64;
                    (
                        law.predict(predicted, v, theta_d, omega),
                        law.back_emf_sequence(theta_d + omega * period, omega),
                    )
                }
                false => (
                    law.predict(predicted, v, ahead(d), mid),
                    law.back_emf_sequence_accelerating(ahead(d + 1), speed(d + 1), alpha),
                ),
            };
            Seed::Law {
                start,
                references,
                emf,
            }
        };
        let decide = |reference: &dyn Fn(usize) -> [f64; 2]| match alpha == 0.0 {
            true => law.decide(i, theta, omega, decided, reference),
            false => law.decide_accelerating(i, theta, omega, alpha, decided, reference),
        };
        let (v, i_ref, seed) = match self.method {
            Method::Proposed => {
                let tau = setpoint.torque_nm;
                // Along a smooth segment the torque moves on between ticks.
                let tau_at = |j: usize| {
                    tau + setpoint.torque_rate_nm_s
                        * (t + period * j as f64 - setpoint.sample_time_s)
                };
                let reference = |j: usize| match alpha == 0.0 {
                    true => commutate(tau, theta + omega * period * j as f64, k_m, n_r),
                    false => commutate(tau_at(j), ahead(j), k_m, n_r),
                };
                let (v, predicted) = decide(&reference);
                let v = clamp(v);
                // (17) as a phasor: i^d = j(τ/K_m) e^{jN_rθ}, turning with the rotor.
                let seed = planning.then(|| {
                    let references = match alpha == 0.0 {
                        true => Rotating::new(
                            Complex::new(0.0, tau / k_m),
                            n_r * (theta + omega * (t_plan - t)),
                            n_r * omega * period,
                            0.0,
                        ),
                        // (17) along the accelerating angle, its torque ramping as
                        // `reference` has it.
                        false => Rotating::ramped(
                            Complex::new(0.0, tau_at(d + 1) / k_m),
                            Complex::new(0.0, setpoint.torque_rate_nm_s * period / k_m),
                            Complex::new(0.0, 0.0),
                            n_r * ahead(d + 1),
                            n_r * (ahead(d + 2) - ahead(d + 1)),
                            n_r * alpha * period * period,
                        ),
                    };
                    seed_law(predicted, v, references)
                });
                (v, reference(d + 1), seed)
            }
            Method::Lyapunov => {
                let (v_max, r) = (self.v_max, self.r);
                let reference = |j: usize| {
                    microstep_currents(setpoint.theta_d_at(t + period * j as f64), v_max, r, n_r)
                };
                let (v, predicted) = decide(&reference);
                let v = clamp(v);
                let seed = planning.then(|| {
                    let amplitude = Complex::new(v_max / r, 0.0);
                    let references = microstep_sequence(setpoint, t_plan, period, n_r, amplitude);
                    seed_law(predicted, v, references)
                });
                (v, reference(d + 1), seed)
            }
            Method::OpenLoop => {
                // Eq. (2) evaluated mid-way through the period the voltage will be applied in.
                let half = 0.5 * period;
                let t_mid = t + period * d as f64 + half;
                let v = clamp(microstep_voltages(
                    setpoint.theta_d_at(t_mid),
                    self.v_max,
                    n_r,
                ));
                let seed = planning.then(|| {
                    Seed::Voltages(microstep_sequence(
                        setpoint,
                        t_plan + half,
                        period,
                        n_r,
                        Complex::new(self.v_max, 0.0),
                    ))
                });
                (v, [v[0] / self.r, v[1] / self.r], seed)
            }
            Method::Pi => {
                // What a drive does: the reference at the sample, no prediction, no model.
                let reference = microstep_currents(setpoint.theta_d_at(t), self.v_max, self.r, n_r);
                let v = self.pi.decide(reference, i, bus_v);
                // The plan turns the last voltage with θ_d: a PI loop's steady state.
                let seed = planning.then(|| {
                    let half = 0.5 * period;
                    let t_mid = t + period * d as f64 + half;
                    let relative =
                        Complex::from_pair(v) / Complex::unit(n_r * setpoint.theta_d_at(t_mid));
                    Seed::Voltages(microstep_sequence(
                        setpoint,
                        t_plan + half,
                        period,
                        n_r,
                        relative,
                    ))
                });
                // Reported for the first sample this voltage reaches, as the others do.
                let ahead = setpoint.theta_d_at(t + period * (d + 1) as f64);
                let reported = microstep_currents(ahead, self.v_max, self.r, n_r);
                (v, reported, seed)
            }
        };
        self.answer(state, v, i_ref, seed.map(|seed| (seed, bus_v)))
    }

    /// Keeps what the drive will apply, for the next cycle's prediction, and makes the
    /// command.
    fn answer(
        &mut self,
        state: &DriveState,
        v: [f64; 2],
        i_ref: [f64; 2],
        seed: Option<(Seed, f64)>,
    ) -> DriveCommand {
        let d = self.delay;
        self.decided = self.decided_before(state.seq);
        if d > 0 {
            self.decided.copy_within(1..d, 0);
            self.decided[d - 1] = v;
        }
        let seq = self.answered.map_or(0, |(_, seq)| seq + 1);
        self.answered = Some((state.seq, seq));
        self.seed = seed;
        DriveCommand {
            seq,
            answers_seq: state.seq,
            sample_time_s: state.sample_time_s,
            state_publish_time_ns: state.publish_time_ns,
            publish_time_ns: 0,
            v_a_v: v[0],
            v_b_v: v[1],
            i_a_ref_a: i_ref[0],
            i_b_ref_a: i_ref[1],
            flags: 0,
            _reserved: 0,
        }
    }

    /// The axis has no torque: zero volts, and a plan of zeros (a drive that misses the next
    /// commands keeps the outputs at zero too). `publish_time_ns` is left for the caller.
    pub fn off(&mut self, state: &DriveState) -> DriveCommand {
        let zero = Rotating::new(Complex::new(0.0, 0.0), 0.0, 0.0, 0.0);
        let planning = self.plan_periods > 0;
        let seed = planning.then_some((Seed::Voltages(zero), self.bus_v));
        self.answer(state, [0.0; 2], [0.0; 2], seed)
    }

    /// The plan continuing the command just returned by [`Self::on_sample`]: the voltages
    /// the law would choose for the next periods if its model held (see
    /// [`SampledCurrentLaw::plan`]). Built in place; `publish_time_ns` is left for the
    /// caller. Empty when planning is off.
    pub fn plan(&mut self) -> &DrivePlan {
        let (Some((answers, seq)), Some((seed, bus_v))) = (self.answered, self.seed.take()) else {
            self.plan.len = 0;
            return &self.plan;
        };
        let n = self.plan_periods;
        let out = &mut self.plan.v[..n];
        match seed {
            Seed::Law {
                start,
                references,
                emf,
            } => self.law.plan(start, references, emf, bus_v, out),
            Seed::Voltages(mut voltages) => {
                for slot in out.iter_mut() {
                    *slot = voltages
                        .value()
                        .pair()
                        .map(|x| x.clamp(-bus_v, bus_v) as f32);
                    voltages.advance();
                }
            }
        }
        self.plan.command_seq = seq;
        self.plan.answers_seq = answers;
        self.plan.publish_time_ns = 0;
        self.plan.len = n as u32;
        &self.plan
    }
}

/// amplitude · e^{jN_rθ_d(t)} at t = t_0, t_0 + T, ...: the microstepping references of
/// (2) and (39) along the setpoint's segment (quadratic θ_d, so a chirp).
fn microstep_sequence(
    sp: &TorqueSetpoint,
    t0: f64,
    period: f64,
    n_r: f64,
    amplitude: Complex,
) -> Rotating {
    let phase = n_r * sp.theta_d_at(t0);
    let step = n_r * (sp.theta_d_at(t0 + period) - sp.theta_d_at(t0));
    let step_change = n_r * sp.alpha_d_rad_s2 * period * period;
    Rotating::new(amplitude, phase, step, step_change)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::laws::commutation::commutate;
    use stepdrive_motor::{Motor, MotorState, I_A, I_B, OMEGA, THETA};

    const T: f64 = 50e-6;

    /// What a run of the loop against the motor produced.
    struct Trace {
        /// The plan sent with the answer to sample k0.
        plan: Vec<[f32; 2]>,
        /// The voltage applied over each period k.
        applied: Vec<[f64; 2]>,
        /// |i − (17)| at each sample, A (the proposed method's tracking error).
        current_error: Vec<f64>,
        /// At each first sample after a gap: how far the loop's idea of the voltage the
        /// drive applied in that period was from the voltage applied, V.
        resume_mismatch: Vec<f64>,
    }

    /// Runs the loop (compute delay 1) against the motor at constant speed (J → ∞, the
    /// plan's own assumption), skipping the samples in `skipped` as a stalled loop does,
    /// with the drive applying the freshest plan's entry for each period without its
    /// command, or past the plan the voltage it applied last. A plan goes out with every
    /// command, or with every `plan_every`-th and the first after a gap (as the node does).
    fn run(
        method: Method,
        sp: &TorqueSetpoint,
        skipped: std::ops::Range<u64>,
        k0: u64,
        n: u64,
    ) -> Trace {
        run_planning_every(method, sp, skipped, k0, n, 1)
    }

    fn run_planning_every(
        method: Method,
        sp: &TorqueSetpoint,
        skipped: std::ops::Range<u64>,
        k0: u64,
        n: u64,
        plan_every: u64,
    ) -> Trace {
        run_with(method, sp, skipped, k0, n, plan_every, 0.0)
    }

    /// `alpha` ≠ 0: the rotor is driven at that acceleration (a rotor whose speed the
    /// windings do not change, as with J → ∞, each period at its mid-period speed, as the
    /// law's accelerating model has it).
    fn run_with(
        method: Method,
        sp: &TorqueSetpoint,
        skipped: std::ops::Range<u64>,
        k0: u64,
        n: u64,
        plan_every: u64,
        alpha: f64,
    ) -> Trace {
        let s = Scenario::default();
        let m = Motor {
            j: f64::INFINITY,
            ..Motor::from(&s.motor)
        };
        let mut cl = CurrentLoop::new(&s, method).with_plan_periods(120);
        let omega0 = 13.13;
        let mut x = MotorState::new(0.2, omega0, 0.0, 0.0);
        let mut last: Option<(DriveCommand, DrivePlan)> = None;
        let mut sent = DrivePlan::default();
        let mut applied = [0.0; 2];
        let mut trace = Trace {
            plan: Vec::new(),
            applied: Vec::new(),
            current_error: Vec::new(),
            resume_mismatch: Vec::new(),
        };
        for k in 0..n {
            let i_ref = commutate(sp.torque_nm, x[THETA], m.k_m, m.n_r);
            trace
                .current_error
                .push((x[I_A] - i_ref[0]).hypot(x[I_B] - i_ref[1]));
            // Period k belongs to the answer to k − 1, or else to the freshest plan.
            let v = match &last {
                Some((c, _)) if c.answers_seq + 1 == k => [c.v_a_v, c.v_b_v],
                Some((_, plan)) => plan.voltage_for(k, 1).unwrap_or(applied),
                None => [0.0; 2],
            };
            applied = v;
            trace.applied.push(v);
            let resumed = k > 0 && skipped.contains(&(k - 1)) && !skipped.contains(&k);
            if resumed {
                let believed = cl.decided_before(k)[0];
                trace
                    .resume_mismatch
                    .push((believed[0] - v[0]).abs().max((believed[1] - v[1]).abs()));
            }
            if !skipped.contains(&k) {
                let state = DriveState {
                    seq: k,
                    sample_time_s: k as f64 * T,
                    theta_rad: x[THETA],
                    omega_rad_s: x[OMEGA],
                    i_a_a: x[I_A],
                    i_b_a: x[I_B],
                    ..Default::default()
                };
                let c = cl.on_sample(&state, sp);
                if resumed || k % plan_every == 0 {
                    sent = *cl.plan();
                }
                if k == k0 {
                    trace.plan = sent.entries().to_vec();
                }
                last = Some((c, sent));
            }
            if alpha != 0.0 {
                x[OMEGA] = omega0 + alpha * (k as f64 + 0.5) * T;
            }
            x = m.integrate(&x, v, 0.0, T, 8);
            if alpha != 0.0 {
                x[OMEGA] = omega0 + alpha * (k + 1) as f64 * T;
            }
        }
        trace
    }

    const CRUISE_TORQUE: TorqueSetpoint = TorqueSetpoint {
        seq: 0,
        from_state_seq: 0,
        sample_time_s: 0.0,
        publish_time_ns: 0,
        theta_d_rad: 0.0,
        omega_d_rad_s: 0.0,
        alpha_d_rad_s2: 0.0,
        torque_nm: 0.0757,
        load_estimate_nm: 0.0,
        torque_rate_nm_s: 0.0,
        axis: 0,
        flags: stepdrive_shared::messages::setpoint_flags::OUTPUTS_ON,
        epoch: 1,
        _reserved: 0,
    };

    /// The largest difference, V, between a plan's entries and the voltages applied in the
    /// periods they are for.
    fn plan_gap(plan: &[[f32; 2]], later: &[[f64; 2]]) -> f64 {
        plan.iter()
            .zip(later)
            .map(|(p, a)| {
                (f64::from(p[0]) - a[0])
                    .abs()
                    .max((f64::from(p[1]) - a[1]).abs())
            })
            .fold(0.0, f64::max)
    }

    /// The plan is the law's own future: on the model it assumes (constant speed, same
    /// setpoint segment), the voltages the loop goes on to send equal the plan sent at k0,
    /// period by period, to f32 rounding; for each method, and for the baselines along an
    /// accelerating θ_d (the chirp).
    #[test]
    fn the_plan_is_what_the_law_goes_on_to_send() {
        let accelerating = TorqueSetpoint {
            theta_d_rad: 0.2,
            omega_d_rad_s: 13.0,
            alpha_d_rad_s2: 26.26,
            ..Default::default()
        };
        for (method, sp) in [
            (Method::Proposed, CRUISE_TORQUE),
            (Method::Lyapunov, accelerating),
            (Method::OpenLoop, accelerating),
        ] {
            let k0 = 30;
            let t = run(method, &sp, 0..0, k0, k0 + 130);
            assert_eq!(t.plan.len(), 120);
            // Entry j is for period k0 + d + 1 + j.
            let later = &t.applied[k0 as usize + 2..];
            let gap = plan_gap(&t.plan, later);
            assert!(
                gap < 1e-5,
                "{method}: plan and later commands differ by {gap} V"
            );
            // Not equal by accident: the voltage turns through ~4 rad over the plan.
            let (a, b) = (later[0], later[100]);
            assert!(
                (a[0] - b[0]).abs() + (a[1] - b[1]).abs() > 1.0,
                "{method}: {a:?} {b:?}"
            );
        }
    }

    /// Along a jerk-limited move the plan assumes the rotor accelerates as the setpoint
    /// says, and its torque ramps: on that model (a rotor driven at 50 rad/s² from
    /// 13.13 rad/s, braking), the loop's later voltages equal the plan sent at k0 over its
    /// 120 periods, to 1e-5 V. The plan at constant speed it replaced was 0.84 V off by its
    /// end (6 ms, the rotor 0.3 rad/s slower than it assumed).
    #[test]
    fn along_an_acceleration_the_plan_is_what_the_law_goes_on_to_send() {
        use stepdrive_shared::messages::setpoint_flags;
        let alpha = -50.0;
        let braking = TorqueSetpoint {
            torque_nm: 0.05,
            torque_rate_nm_s: -0.4,
            alpha_d_rad_s2: alpha,
            flags: setpoint_flags::OUTPUTS_ON | setpoint_flags::ACCELERATION_AHEAD,
            ..CRUISE_TORQUE
        };
        for method in [Method::Proposed, Method::Lyapunov] {
            let k0 = 30;
            let t = run_with(method, &braking, 0..0, k0, k0 + 130, 1, alpha);
            assert_eq!(t.plan.len(), 120);
            let later = &t.applied[k0 as usize + 2..];
            let gap = plan_gap(&t.plan, later);
            assert!(
                gap < 1e-5,
                "{method}: plan and later commands differ by {gap} V"
            );
        }
    }

    /// A loop that skipped samples predicts with the plan entries the drive applied in the
    /// meantime, so tracking resumes without a transient: the current error stays at its
    /// settled level through a 60-period gap and after it.
    #[test]
    fn after_a_gap_the_loop_predicts_with_the_applied_plan() {
        let t = run(Method::Proposed, &CRUISE_TORQUE, 100..160, 0, 260);
        let settled = t.current_error[60..100]
            .iter()
            .fold(0.0, |a: f64, &b| a.max(b));
        let after = t.current_error[100..]
            .iter()
            .fold(0.0, |a: f64, &b| a.max(b));
        assert!(settled < 1e-6, "settled error {settled} A");
        assert!(after < 1e-6, "error through and after the gap {after} A");
        assert_eq!(t.resume_mismatch, [0.0]);
    }

    /// The same with a plan every tenth command, as the node sends them: the drive's
    /// freshest plan may continue a command up to nine periods older than the last, and the
    /// loop predicts with that one. Through a gap the plan covers, tracking is unchanged;
    /// through one that outlasts it (the drive holding the plan's last entry), the loop
    /// still knows exactly what was applied.
    #[test]
    fn with_a_plan_every_tenth_command_the_loop_predicts_with_the_plan_the_drive_has() {
        let t = run_planning_every(Method::Proposed, &CRUISE_TORQUE, 103..163, 0, 260, 10);
        let after = t.current_error[100..]
            .iter()
            .fold(0.0, |a: f64, &b| a.max(b));
        assert!(after < 1e-6, "error through and after the gap {after} A");
        assert_eq!(t.resume_mismatch, [0.0]);
        // A 200-period gap past the 120-period plan of the command answering 100: its
        // entries are for periods 102..=221, the last command's (answering 102) for 103.
        let t = run_planning_every(Method::Proposed, &CRUISE_TORQUE, 103..303, 0, 400, 10);
        assert_eq!(t.resume_mismatch, [0.0]);
        let held = &t.applied[221..=303];
        assert!(held.iter().all(|v| v == &held[0]), "held past the plan");
        assert_ne!(t.applied[220], t.applied[221], "planned up to its end");
    }
}
