//! Identification of a motor's R, L, K_m, J, B and load from a scripted, bounded sequence
//! of phase voltages and the states it produces. Pure: the sequence maps a state to the
//! voltages for the next period; the fits map the recorded states to estimates.
//!
//! The sequence (docs/real-motors.md, "Identifying a motor"):
//! 1. **R and L, phase a**, rotor held by phase a's own field: four DC voltage levels, each
//!    held long enough to settle. R is the slope of V against I over the settled ends of
//!    the levels (an offset in either cancels); L is the time constant of the steps between
//!    them, from a least-squares fit of the exact sampled response i_k = a i_{k−1} + b v_k + c
//!    (a = e^{−RT/L}).
//! 2. **R and L, phase b**, the same (the rotor first turns a quarter electrical period to
//!    phase b's field; that part is skipped).
//! 3. **K_m, J, B, load**: open-loop microstepping along a speed profile (forward at two
//!    speeds, with accelerations, then backward). K_m from the back-EMF in each phase's
//!    sampled electrical equation with the R and L just found; J, B, the constant load and
//!    Coulomb friction from the torque balance K_m ∫ i_q dt = J Δω + B ∫ ω dt + τ_L Δt +
//!    τ_c ∫ sign ω dt over 10 ms windows.
//!
//! Every period is checked against the bounds (current, voltage, speed, travel): one
//! beyond them aborts with the outputs off.

use nalgebra::{DMatrix, DVector};
use stepdrive_shared::frames::dq_currents;
use stepdrive_shared::messages::DriveState;
use stepdrive_shared::scenario::MotorParams;

/// What the sequence may do to the motor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// |i_a|, |i_b| at most, A.
    pub current_a: f64,
    /// |v_a|, |v_b| the sequence commands at most, V.
    pub voltage_v: f64,
    /// |ω| at most, rad/s.
    pub speed_rad_s: f64,
    /// |θ − θ_start| at most, rad.
    pub travel_rad: f64,
}

impl Default for Bounds {
    fn default() -> Self {
        Self {
            current_a: 1.0,
            voltage_v: 20.0,
            speed_rad_s: 12.0,
            travel_rad: 30.0,
        }
    }
}

/// A bound the motor reached: the sequence stops with the outputs off.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum BoundHit {
    #[error("phase current {value:.3} A beyond the bound of {limit} A at t = {t:.4} s")]
    Current { value: f64, limit: f64, t: f64 },
    #[error("speed {value:.3} rad/s beyond the bound of {limit} rad/s at t = {t:.4} s")]
    Speed { value: f64, limit: f64, t: f64 },
    #[error("travel {value:.3} rad beyond the bound of {limit} rad at t = {t:.4} s")]
    Travel { value: f64, limit: f64, t: f64 },
    #[error("a non-finite measurement at t = {t:.4} s")]
    NotFinite { t: f64 },
}

impl BoundHit {
    /// When it was hit, s.
    pub fn time_s(&self) -> f64 {
        match *self {
            BoundHit::Current { t, .. }
            | BoundHit::Speed { t, .. }
            | BoundHit::Travel { t, .. }
            | BoundHit::NotFinite { t } => t,
        }
    }
}

/// Segment lengths, s.
const LEVEL_S: f64 = 0.08;
const LEVELS: usize = 4;
/// The rotor turning to phase b's field at the start of phase 2: not used for phase b.
const TURN_S: f64 = 0.1;
/// The speed profile of step 3: (duration, speed at its end as a share of the top speed);
/// speed ramps linearly within a segment.
const PROFILE: [(f64, f64); 9] = [
    (0.15, 0.5),
    (0.25, 0.5),
    (0.1, 1.0),
    (0.25, 1.0),
    (0.15, 0.2),
    (0.1, 0.2),
    (0.2, -0.6),
    (0.25, -0.6),
    (0.15, 0.0),
];

/// A plan being written: the sequence's voltages after a sample, entry by entry.
#[derive(Debug, Clone)]
pub struct Planner {
    ahead: Sequence,
    /// The sample the plan continues.
    t: f64,
    /// Entries written.
    j: usize,
}

impl Planner {
    /// Writes the next `out.len()` entries.
    pub fn fill(&mut self, out: &mut [[f32; 2]]) {
        for slot in out.iter_mut() {
            self.j += 1;
            let v = self
                .ahead
                .voltages(self.t + self.ahead.period * self.j as f64);
            *slot = v.map(|x| x as f32);
        }
    }

    /// Entries written so far.
    pub fn written(&self) -> usize {
        self.j
    }
}

/// Which part of the sequence a sample belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    PhaseA,
    Turn,
    PhaseB,
    Spin,
    Done,
}

/// The script: the voltages for each period, from the nominal model (only to choose the
/// levels: more current than the bound allows is never asked for).
#[derive(Debug, Clone)]
pub struct Sequence {
    bounds: Bounds,
    period: f64,
    n_r: f64,
    /// Phase voltage of the top DC level, V.
    dc_v: f64,
    /// Microstepping: nominal R, K_m, the current amplitude and the top speed.
    r: f64,
    k_m: f64,
    spin_a: f64,
    top_speed: f64,
    start_theta: Option<f64>,
    /// Spin: the field angle so far (integrated, so the profile's speed is exact).
    field: f64,
    /// The sample the last voltages answered: a realtime caller that skipped samples (the
    /// host stalled it) must find the field where the profile has it by now, not behind.
    last_t: Option<f64>,
}

impl Sequence {
    pub fn new(nominal: &MotorParams, bounds: Bounds, period_s: f64) -> Self {
        let r = nominal.resistance_ohm;
        // 60 % of the current bound at the top level, on the nominal R.
        let dc_v = (0.6 * bounds.current_a * r).min(bounds.voltage_v);
        Self {
            bounds,
            period: period_s,
            n_r: nominal.n_r(),
            dc_v,
            r,
            k_m: nominal.torque_constant_nm_per_a,
            spin_a: 0.5 * bounds.current_a,
            // Two thirds: an open-loop rotor overshoots its field's speed (by 25 % seen through a
            // drive's velocity observer), and the bound is on what is measured.
            top_speed: bounds.speed_rad_s / 1.5,
            start_theta: None,
            field: std::f64::consts::FRAC_PI_2,
            last_t: None,
        }
    }

    /// The sequence's length, s.
    pub fn duration_s() -> f64 {
        2.0 * LEVELS as f64 * LEVEL_S + TURN_S + PROFILE.iter().map(|p| p.0).sum::<f64>()
    }

    /// Where time `t` falls.
    pub fn part(t: f64) -> Part {
        let dc = LEVELS as f64 * LEVEL_S;
        if t < dc {
            Part::PhaseA
        } else if t < dc + TURN_S {
            Part::Turn
        } else if t < 2.0 * dc + TURN_S {
            Part::PhaseB
        } else if t < Self::duration_s() {
            Part::Spin
        } else {
            Part::Done
        }
    }

    /// The DC level at time `t` within a phase's part (1..=LEVELS of the top level).
    fn level(&self, t_in: f64) -> f64 {
        let n = ((t_in / LEVEL_S).floor() as usize).min(LEVELS - 1) + 1;
        self.dc_v * n as f64 / LEVELS as f64
    }

    /// The profile's speed at `t_in` into the spin, rad/s.
    fn speed(&self, t_in: f64) -> f64 {
        let (mut t0, mut w0) = (0.0, 0.0);
        for (d, share) in PROFILE {
            let w1 = share * self.top_speed;
            if t_in < t0 + d {
                return w0 + (w1 - w0) * (t_in - t0) / d;
            }
            t0 += d;
            w0 = w1;
        }
        0.0
    }

    /// The voltages for the period after `state`'s (the bounds checked first).
    pub fn next(&mut self, state: &DriveState) -> Result<[f64; 2], BoundHit> {
        self.check(state)?;
        Ok(self.voltages(state.sample_time_s))
    }

    /// What [`Self::next`] will answer to the `out.len()` samples after the one at `t`,
    /// if their states stay within the bounds (a plan cannot check states not yet seen;
    /// the next state checks them): the voltage plan for a drive that misses commands.
    pub fn plan(&self, t: f64, out: &mut [[f32; 2]]) {
        let mut ahead = self.planner(t);
        ahead.fill(out);
    }

    /// The sequence continued from the sample at `t`, to write a plan piece by piece
    /// ([`Planner::fill`]): a whole plan at once would take tens of µs from the loop.
    pub fn planner(&self, t: f64) -> Planner {
        Planner {
            ahead: self.clone(),
            t,
            j: 0,
        }
    }

    /// The voltages of the period after the sample at `t`.
    fn voltages(&mut self, t: f64) -> [f64; 2] {
        let dc = LEVELS as f64 * LEVEL_S;
        let periods = match self.last_t {
            Some(last) => ((t - last) / self.period).round().max(0.0),
            None => 1.0,
        };
        self.last_t = Some(t);
        let v = match Self::part(t) {
            Part::PhaseA => [self.level(t), 0.0],
            Part::Turn => [0.0, self.dc_v * 0.5],
            Part::PhaseB => [0.0, self.level(t - dc - TURN_S)],
            Part::Spin => {
                let w = self.speed(t - 2.0 * dc - TURN_S);
                self.field += self.n_r * w * self.period * periods;
                // Eq. (2) with the nominal back-EMF added, so the current stays near its
                // amplitude at every speed.
                let amplitude = self.r * self.spin_a + self.k_m * w.abs();
                let (s, c) = self.field.sin_cos();
                [amplitude * c, amplitude * s]
            }
            Part::Done => [0.0, 0.0],
        };
        let lim = self.bounds.voltage_v;
        v.map(|x| x.clamp(-lim, lim))
    }

    fn check(&mut self, s: &DriveState) -> Result<(), BoundHit> {
        let t = s.sample_time_s;
        let values = [s.theta_rad, s.omega_rad_s, s.i_a_a, s.i_b_a];
        if !values.iter().all(|v| v.is_finite()) {
            return Err(BoundHit::NotFinite { t });
        }
        let b = self.bounds;
        let i = s.i_a_a.abs().max(s.i_b_a.abs());
        if i > b.current_a {
            return Err(BoundHit::Current {
                value: i,
                limit: b.current_a,
                t,
            });
        }
        if s.omega_rad_s.abs() > b.speed_rad_s {
            return Err(BoundHit::Speed {
                value: s.omega_rad_s,
                limit: b.speed_rad_s,
                t,
            });
        }
        let start = *self.start_theta.get_or_insert(s.theta_rad);
        let travel = (s.theta_rad - start).abs();
        if travel > b.travel_rad {
            return Err(BoundHit::Travel {
                value: travel,
                limit: b.travel_rad,
                t,
            });
        }
        Ok(())
    }
}

/// One estimate with its standard error (from the fit's residuals).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Estimate {
    pub value: f64,
    pub std_error: f64,
}

/// What the identification found.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Estimates {
    pub resistance_ohm: Estimate,
    pub inductance_h: Estimate,
    pub torque_constant_nm_per_a: Estimate,
    pub inertia_kg_m2: Estimate,
    pub viscous_friction_nm_s_per_rad: Estimate,
    pub load_nm: Estimate,
    pub coulomb_nm: Estimate,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    #[error("the {what} fit is singular: the sequence did not excite it (too few samples?)")]
    Singular { what: &'static str },
    #[error("the {what} fit gave a non-physical value {value:e}")]
    NonPhysical { what: &'static str, value: f64 },
}

/// Least squares y ≈ X β: β and the standard error of each coefficient.
fn least_squares(
    what: &'static str,
    rows: &[Vec<f64>],
    y: &[f64],
) -> Result<(Vec<f64>, Vec<f64>), FitError> {
    let n = rows.len();
    let p = rows.first().map_or(0, Vec::len);
    if n <= p || p == 0 {
        return Err(FitError::Singular { what });
    }
    let x = DMatrix::from_fn(n, p, |i, j| rows[i][j]);
    let yv = DVector::from_column_slice(y);
    let xtx = x.transpose() * &x;
    let inv = xtx.try_inverse().ok_or(FitError::Singular { what })?;
    let beta = &inv * x.transpose() * &yv;
    let residual = &yv - &x * &beta;
    let sigma2 = residual.norm_squared() / (n - p) as f64;
    let se = (0..p)
        .map(|j| (sigma2 * inv[(j, j)]).max(0.0).sqrt())
        .collect();
    Ok((beta.iter().copied().collect(), se))
}

/// The means of `f` over the settled second half of each DC level of the part starting at
/// `start`, s.
fn settled_means(
    states: &[DriveState],
    start: f64,
    what: &'static str,
    f: impl Fn(&DriveState) -> [f64; 2],
) -> Result<Vec<[f64; 2]>, FitError> {
    (0..LEVELS)
        .map(|n| {
            let from = start + (n as f64 + 0.5) * LEVEL_S;
            let to = start + (n as f64 + 1.0) * LEVEL_S;
            let (mut sum, mut m) = ([0.0; 2], 0.0);
            for s in states
                .iter()
                .filter(|s| s.sample_time_s >= from && s.sample_time_s < to)
            {
                let v = f(s);
                sum = [sum[0] + v[0], sum[1] + v[1]];
                m += 1.0;
            }
            if m == 0.0 {
                return Err(FitError::Singular { what });
            }
            Ok([sum[0] / m, sum[1] / m])
        })
        .collect()
}

/// The back-EMF's shape in each phase's equation, ω sin(N_r θ) and −ω cos(N_r θ) (times
/// K_m it is the voltage the rotor induces, eq. (1)).
fn back_emf(s: &DriveState, n_r: f64) -> [f64; 2] {
    let (sn, cs) = (n_r * s.theta_rad).sin_cos();
    [s.omega_rad_s * sn, -s.omega_rad_s * cs]
}

/// R and L of one phase (`phase` 0 = a, 1 = b) from the samples of its DC part.
fn resistance_and_inductance(
    states: &[DriveState],
    phase: usize,
    start: f64,
    period: f64,
    n_r: f64,
) -> Result<(Estimate, Estimate), FitError> {
    let i_of = |s: &DriveState| if phase == 0 { s.i_a_a } else { s.i_b_a };
    let v_of = |s: &DriveState| if phase == 0 { s.v_a_v } else { s.v_b_v };
    // R: the settled second half of each level, V against I.
    let means = settled_means(states, start, "resistance", |s| [i_of(s), v_of(s)])?;
    let rows: Vec<Vec<f64>> = means.iter().map(|&[i, _]| vec![i, 1.0]).collect();
    let y: Vec<f64> = means.iter().map(|&[_, v]| v).collect();
    let (beta, se) = least_squares("resistance", &rows, &y)?;
    let r = Estimate {
        value: beta[0],
        std_error: se[0],
    };
    if r.value.is_nan() || r.value <= 0.0 {
        return Err(FitError::NonPhysical {
            what: "resistance",
            value: r.value,
        });
    }
    // L: i_k = a i_{k−1} + b v_k + g ē_k + c over the whole part (the steps excite it).
    // ē is the interval's mean of ω sin(N_r θ) (−ω cos for b): a load holds the rotor
    // off the phase's axis, so each current step swings it and its back-EMF would
    // otherwise bias a (by 0.2 % in L with a 0.012 N·m load at 0.1 A).
    let part: Vec<&DriveState> = states
        .iter()
        .filter(|s| s.sample_time_s >= start && s.sample_time_s < start + LEVELS as f64 * LEVEL_S)
        .collect();
    let emf = |s: &DriveState| back_emf(s, n_r)[phase];
    let (mut rows, mut y) = (Vec::new(), Vec::new());
    for w in part.windows(2) {
        if w[1].seq != w[0].seq + 1 {
            continue;
        }
        let e = 0.5 * (emf(w[0]) + emf(w[1]));
        rows.push(vec![i_of(w[0]), v_of(w[1]), e, 1.0]);
        y.push(i_of(w[1]));
    }
    let (beta, se) = least_squares("inductance", &rows, &y)?;
    let a = beta[0];
    if a.is_nan() || a <= 0.0 || a >= 1.0 {
        return Err(FitError::NonPhysical {
            what: "inductance",
            value: a,
        });
    }
    // τ = −T / ln a, L = R τ; the error of a carried through d(τ)/da = T / (a ln² a).
    let tau = -period / a.ln();
    let l = r.value * tau;
    let l_se = l
        * ((se[0] * period / (a * a.ln().powi(2)) / tau).powi(2) + (r.std_error / r.value).powi(2))
            .sqrt();
    Ok((
        r,
        Estimate {
            value: l,
            std_error: l_se,
        },
    ))
}

/// How far the measured θ is from the electrical zero, rad (add it to θ). A drive zeroes
/// its encoder where alignment left the rotor, which a load holds short of the zero by an
/// angle that depends on the load, K_m and the align current (docs/drive-protocol.md §7);
/// a host corrects it with its model, and the model is what is being identified. The DC
/// levels of phase a show it: at each, the rotor rests where K_m I_n sin(N_r θ) = −τ_L, so
/// θ_n = −asin(x / I_n) / N_r − offset with x = τ_L / K_m: two unknowns, four levels, a few
/// Gauss-Newton steps from the small-angle solution. Left alone, 8e-5 rad of it (a bench
/// motor's align current 15 % below the model's) biased the load by −7 % through a drive.
fn zero_offset(states: &[DriveState], n_r: f64) -> Result<f64, FitError> {
    let levels: Vec<(f64, f64)> =
        settled_means(states, 0.0, "electrical zero", |s| [s.i_a_a, s.theta_rad])?
            .into_iter()
            .map(|[i, theta]| (i, theta))
            .collect();
    // Small angles: θ_n = −(x / N_r) / I_n − offset, linear in 1/I_n.
    let rows: Vec<Vec<f64>> = levels.iter().map(|&(i, _)| vec![1.0 / i, 1.0]).collect();
    let y: Vec<f64> = levels.iter().map(|&(_, th)| th).collect();
    let (beta, _) = least_squares("electrical zero", &rows, &y)?;
    let (mut x, mut offset) = (-beta[0] * n_r, -beta[1]);
    for _ in 0..8 {
        let mut rows = Vec::with_capacity(LEVELS);
        let mut r = Vec::with_capacity(LEVELS);
        for &(i, th) in &levels {
            let u = x / i;
            if u.abs() >= 1.0 {
                return Err(FitError::NonPhysical {
                    what: "load against the DC levels",
                    value: u,
                });
            }
            rows.push(vec![1.0 / (n_r * i * (1.0 - u * u).sqrt()), -1.0]);
            r.push(-(th + offset + u.asin() / n_r));
        }
        let (step, _) = least_squares("electrical zero", &rows, &r)?;
        x += step[0];
        offset -= step[1];
    }
    Ok(offset)
}

/// Everything from the states of one run of the sequence (sample k at k·`period_s`).
pub fn fit(states: &[DriveState], n_r: f64, period_s: f64) -> Result<Estimates, FitError> {
    let dc = LEVELS as f64 * LEVEL_S;
    // Every fit that turns currents into torque needs the electrical angle exactly: move θ
    // to the electrical zero the DC levels show.
    let offset = zero_offset(states, n_r)?;
    let corrected: Vec<DriveState> = states
        .iter()
        .map(|s| DriveState {
            theta_rad: s.theta_rad + offset,
            ..*s
        })
        .collect();
    let states = &corrected[..];
    let (r_a, l_a) = resistance_and_inductance(states, 0, 0.0, period_s, n_r)?;
    let (r_b, l_b) = resistance_and_inductance(states, 1, dc + TURN_S, period_s, n_r)?;
    let mean = |x: Estimate, y: Estimate| Estimate {
        value: 0.5 * (x.value + y.value),
        std_error: 0.5 * x.std_error.hypot(y.std_error),
    };
    let (r, l) = (mean(r_a, r_b), mean(l_a, l_b));

    // K_m: i_k − a i_{k−1} − b v_k = b K_m ē, ē the mean of ω sin(N_r θ) (phase a, −ω cos
    // for b) over the interval, with each phase's own a and b.
    let spin_from = 2.0 * dc + TURN_S;
    let spin: Vec<&DriveState> = states
        .iter()
        .filter(|s| s.sample_time_s >= spin_from)
        .collect();
    let coefficients = |rr: f64, ll: f64| {
        let a = (-rr * period_s / ll).exp();
        (a, (1.0 - a) / rr)
    };
    let phases = [
        coefficients(r_a.value, l_a.value),
        coefficients(r_b.value, l_b.value),
    ];
    let (mut rows, mut y) = (Vec::new(), Vec::new());
    for w in spin.windows(2) {
        let (p, q) = (w[0], w[1]);
        if q.seq != p.seq + 1 || p.omega_rad_s.abs() < 0.5 {
            continue;
        }
        let (ep, eq) = (back_emf(p, n_r), back_emf(q, n_r));
        for (ph, &(a, b)) in phases.iter().enumerate() {
            let (i0, i1, v) = match ph {
                0 => (p.i_a_a, q.i_a_a, q.v_a_v),
                _ => (p.i_b_a, q.i_b_a, q.v_b_v),
            };
            rows.push(vec![b * 0.5 * (ep[ph] + eq[ph])]);
            y.push(i1 - a * i0 - b * v);
        }
    }
    let (beta, se) = least_squares("torque constant", &rows, &y)?;
    let k_m = Estimate {
        value: beta[0],
        std_error: se[0],
    };
    if k_m.value.is_nan() || k_m.value <= 0.0 {
        return Err(FitError::NonPhysical {
            what: "torque constant",
            value: k_m.value,
        });
    }

    // J, B, τ_L, τ_c: the torque balance integrated over 10 ms windows. Speed comes from
    // the encoder, not from the velocity estimate (a drive's observer lags): ∫ω dt is
    // the change of θ, and ω at a window's ends a central difference over ±M samples.
    const M: usize = 4;
    let window = (0.01 / period_s).round().max(2.0) as usize;
    let consecutive =
        |from: usize, to: usize| spin[from..=to].windows(2).all(|w| w[1].seq == w[0].seq + 1);
    let speed_at = |k: usize| {
        let (a, b) = (spin[k - M], spin[k + M]);
        (b.theta_rad - a.theta_rad) / (b.sample_time_s - a.sample_time_s)
    };
    let (mut rows, mut y) = (Vec::new(), Vec::new());
    let mut start = M;
    while start + window + M < spin.len() {
        let end = start + window;
        let first = start;
        start = end;
        if !consecutive(first - M, end + M) {
            continue;
        }
        let chunk = &spin[first..=end];
        let (mut torque, mut sign, mut dt) = (0.0, 0.0, 0.0);
        for w in chunk.windows(2) {
            let iq = |s: &DriveState| dq_currents(s.theta_rad, n_r, s.i_a_a, s.i_b_a).1;
            let h = w[1].sample_time_s - w[0].sample_time_s;
            torque += 0.5 * h * k_m.value * (iq(w[0]) + iq(w[1]));
            sign += 0.5 * h * (smooth_sign(w[0].omega_rad_s) + smooth_sign(w[1].omega_rad_s));
            dt += h;
        }
        let travel = spin[end].theta_rad - spin[first].theta_rad;
        let dw = speed_at(end) - speed_at(first);
        rows.push(vec![dw, travel, dt, sign]);
        y.push(torque);
    }
    let (beta, se) = least_squares("inertia and friction", &rows, &y)?;
    let est = |n: usize| Estimate {
        value: beta[n],
        std_error: se[n],
    };
    if beta[0].is_nan() || beta[0] <= 0.0 {
        return Err(FitError::NonPhysical {
            what: "inertia",
            value: beta[0],
        });
    }
    Ok(Estimates {
        resistance_ohm: r,
        inductance_h: l,
        torque_constant_nm_per_a: k_m,
        inertia_kg_m2: est(0),
        viscous_friction_nm_s_per_rad: est(1),
        load_nm: est(2),
        coulomb_nm: est(3),
    })
}

/// The sign of ω, smoothed over ±0.05 rad/s (a rotor at rest has no friction direction).
fn smooth_sign(omega: f64) -> f64 {
    (omega / 0.05).tanh()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each part takes its time and the voltages stay within the bound.
    #[test]
    fn the_sequence_is_bounded_in_voltage_and_ends_with_outputs_off() {
        let bounds = Bounds::default();
        let mut seq = Sequence::new(&MotorParams::default(), bounds, 50e-6);
        let end = Sequence::duration_s();
        assert!((2.0..4.0).contains(&end), "{end} s");
        let mut k = 0u64;
        loop {
            let t = k as f64 * 50e-6;
            let state = DriveState {
                seq: k,
                sample_time_s: t,
                ..Default::default()
            };
            let v = seq.next(&state).expect("within bounds");
            assert!(v.iter().all(|x| x.abs() <= bounds.voltage_v));
            if t > end {
                assert_eq!(v, [0.0, 0.0]);
                break;
            }
            k += 1;
        }
    }

    /// The plan is what the sequence goes on to answer, entry for entry (to f32), in every
    /// part: a drive that misses commands applies the voltages that would have come.
    #[test]
    fn the_plan_is_what_the_sequence_answers_next() {
        let period = 50e-6;
        let mut seq = Sequence::new(&MotorParams::default(), Bounds::default(), period);
        let state = |k: u64| DriveState {
            seq: k,
            sample_time_s: k as f64 * period,
            ..Default::default()
        };
        let end = (Sequence::duration_s() / period) as u64;
        let mut plan = [[0.0f32; 2]; 500];
        let mut planned_at = None;
        let mut checked = 0;
        for k in 0..end + 10 {
            let v = seq.next(&state(k)).expect("within bounds");
            if let Some(p) = planned_at.filter(|&p| k > p && k - p <= plan.len() as u64) {
                let want = plan[(k - p - 1) as usize];
                assert_eq!(v.map(|x| x as f32), want, "sample {k} planned at {p}");
                checked += 1;
            }
            // A fresh plan every 300 samples, so every part's stretch is covered.
            if k % 300 == 0 {
                seq.plan(state(k).sample_time_s, &mut plan);
                planned_at = Some(k);
            }
        }
        assert!(checked as u64 > end / 2, "{checked}");
    }

    /// A realtime caller the host stalled sees only the newest state: after skipped
    /// samples the field is where the profile has it by now, as for a caller that saw every
    /// sample (the field once lagged one period per skipped sample, a jolt to an open-loop
    /// rotor at speed).
    #[test]
    fn skipped_samples_leave_the_field_where_the_profile_has_it() {
        let period = 50e-6;
        let bounds = Bounds::default();
        let mut every = Sequence::new(&MotorParams::default(), bounds, period);
        let mut skipping = Sequence::new(&MotorParams::default(), bounds, period);
        let state = |k: u64| DriveState {
            seq: k,
            sample_time_s: k as f64 * period,
            ..Default::default()
        };
        let end = (Sequence::duration_s() / period) as u64;
        let mut compared = 0;
        for k in 0..end {
            let v = every.next(&state(k)).expect("within bounds");
            // Within the spin, a stall of 40 samples every 1000.
            let spin = Sequence::part(state(k).sample_time_s) == Part::Spin;
            if spin && k % 1000 < 40 {
                continue;
            }
            let w = skipping.next(&state(k)).expect("within bounds");
            if spin {
                let angle = |v: [f64; 2]| v[1].atan2(v[0]);
                let diff = (angle(v) - angle(w) + std::f64::consts::PI)
                    .rem_euclid(std::f64::consts::TAU)
                    - std::f64::consts::PI;
                // One period of the top speed's field: the skip uses the speed at its end.
                assert!(diff.abs() < 0.05, "sample {k}: field {diff:e} rad apart");
                compared += 1;
            }
        }
        assert!(compared > 10_000, "{compared}");
    }

    /// The rotor resting under load at each DC level gives the electrical zero: a measured θ
    /// shifted by 8e-5 rad is put back exactly, whatever the load.
    #[test]
    fn the_dc_levels_give_the_electrical_zero() {
        let (n_r, period) = (50.0, 50e-6);
        for (load_over_km, shift) in [(0.012 / 0.59, 8e-5), (0.0, -3e-5), (0.03, 0.0)] {
            let states: Vec<DriveState> = (0..(LEVELS as f64 * LEVEL_S / period) as u64)
                .map(|k| {
                    let t = k as f64 * period;
                    let level = ((t / LEVEL_S).floor() as usize).min(LEVELS - 1) + 1;
                    let i = 0.5 * level as f64 / LEVELS as f64;
                    let theta = -(load_over_km / i).asin() / n_r;
                    DriveState {
                        seq: k,
                        sample_time_s: t,
                        theta_rad: theta - shift,
                        i_a_a: i,
                        ..Default::default()
                    }
                })
                .collect();
            let offset = zero_offset(&states, n_r).expect("found");
            assert!((offset - shift).abs() < 1e-12, "{offset:e} vs {shift:e}");
        }
    }

    #[test]
    fn a_current_beyond_the_bound_stops_the_sequence() {
        let mut seq = Sequence::new(&MotorParams::default(), Bounds::default(), 50e-6);
        let state = DriveState {
            i_a_a: 1.2,
            ..Default::default()
        };
        assert!(matches!(seq.next(&state), Err(BoundHit::Current { .. })));
    }
}
