//! A cyclic synchronous position stream: timestamped points (θ, optional ω and τ
//! feed-forward) at 100 Hz–2 kHz, played a lead behind their arrival and interpolated to
//! the position loop's tick with continuous velocity and acceleration (quintic Hermite; ω
//! by central differences where a point carries none, α by second differences). A fixed
//! ring: nothing allocates after construction.
//!
//! Why quintic: the follower ([`crate::axis::track`]) feeds the stream's jerk forward and
//! corrects the rest at 100 rad/s. A cubic Hermite's acceleration jumps at every point
//! (its ω from differences is off by θ‴h²/6); each jump was a correction the follower
//! made over tens of ms, and a 1 kHz sine of 2 rad was followed 7.5e-5 rad off.

use stepdrive_shared::trajectory::Reference;

/// Points kept: 256 ms of a 1 kHz stream, twice the longest lead a stream should need.
pub const CAPACITY: usize = 256;

/// One point of a stream.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// Stream time, s.
    pub t: f64,
    pub theta: f64,
    pub omega: Option<f64>,
    pub torque_ff: Option<f64>,
}

/// Why a point was not taken.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PointError {
    #[error("stream point at t = {t} s is not finite")]
    NotFinite { t: f64 },
    #[error("stream time must increase: a point at t = {t} s came after one at {last} s")]
    Backwards { t: f64, last: f64 },
    #[error("the stream's buffer of {CAPACITY} points is full")]
    Full,
}

/// Where the played time stands against the points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Play {
    /// Before the first point: nothing to play yet.
    Waiting,
    /// Between two points: the interpolated state and feed-forward.
    At {
        reference: Reference,
        torque_ff: f64,
    },
    /// Past the last point: the stream ran dry (by this long, s); the last point's state.
    Dry { by_s: f64, last: Reference },
}

/// The points of one stream. See the module documentation.
#[derive(Debug, Clone)]
pub struct Stream {
    points: [Point; CAPACITY],
    /// Index of the oldest point and how many there are.
    head: usize,
    len: usize,
    last_t: Option<f64>,
}

impl Default for Stream {
    fn default() -> Self {
        Self {
            points: [Point {
                t: 0.0,
                theta: 0.0,
                omega: None,
                torque_ff: None,
            }; CAPACITY],
            head: 0,
            len: 0,
            last_t: None,
        }
    }
}

impl Stream {
    pub fn clear(&mut self) {
        self.head = 0;
        self.len = 0;
        self.last_t = None;
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn at(&self, i: usize) -> &Point {
        &self.points[(self.head + i) % CAPACITY]
    }

    /// The first point's time, if any came.
    pub fn first_t(&self) -> Option<f64> {
        (self.len > 0).then(|| self.at(0).t)
    }

    /// The newest point's time.
    pub fn last_t(&self) -> Option<f64> {
        self.last_t
    }

    /// Takes a point; refuses a non-finite one, one not after the last, or one the full
    /// buffer has no room for.
    pub fn push(&mut self, p: Point) -> Result<(), PointError> {
        let finite = p.t.is_finite()
            && p.theta.is_finite()
            && p.omega.is_none_or(f64::is_finite)
            && p.torque_ff.is_none_or(f64::is_finite);
        if !finite {
            return Err(PointError::NotFinite { t: p.t });
        }
        if let Some(last) = self.last_t.filter(|&l| p.t <= l) {
            return Err(PointError::Backwards { t: p.t, last });
        }
        if self.len == CAPACITY {
            return Err(PointError::Full);
        }
        self.points[(self.head + self.len) % CAPACITY] = p;
        self.len += 1;
        self.last_t = Some(p.t);
        Ok(())
    }

    /// The velocity at point `i`: its own, or by differences with its neighbours.
    fn omega(&self, i: usize) -> f64 {
        let p = self.at(i);
        if let Some(w) = p.omega {
            return w;
        }
        let prev = (i > 0).then(|| self.at(i - 1));
        let next = (i + 1 < self.len).then(|| self.at(i + 1));
        match (prev, next) {
            (Some(a), Some(b)) => (b.theta - a.theta) / (b.t - a.t),
            (None, Some(b)) => (b.theta - p.theta) / (b.t - p.t),
            (Some(a), None) => (p.theta - a.theta) / (p.t - a.t),
            (None, None) => 0.0,
        }
    }

    /// The acceleration at point `i`: the second divided difference with its neighbours (0
    /// at the stream's ends, where a stream starts or stops).
    fn alpha(&self, i: usize) -> f64 {
        if i == 0 || i + 1 >= self.len {
            return 0.0;
        }
        let (a, p, b) = (self.at(i - 1), self.at(i), self.at(i + 1));
        let slope = |x: &Point, y: &Point| (y.theta - x.theta) / (y.t - x.t);
        2.0 * (slope(p, b) - slope(a, p)) / (b.t - a.t)
    }

    /// The stream at time `t`, dropping the points it no longer needs (all but the one
    /// before `t`, and its predecessor for the differences).
    pub fn play(&mut self, t: f64) -> Play {
        if self.len == 0 || t < self.at(0).t {
            return Play::Waiting;
        }
        while self.len > 2 && self.at(2).t <= t {
            self.head = (self.head + 1) % CAPACITY;
            self.len -= 1;
        }
        let i = match (0..self.len.saturating_sub(1)).find(|&i| self.at(i + 1).t > t) {
            Some(i) => i,
            None => {
                let last = self.at(self.len - 1);
                if t == last.t {
                    return Play::At {
                        reference: Reference {
                            theta: last.theta,
                            omega: self.omega(self.len - 1),
                            alpha: 0.0,
                        },
                        torque_ff: last.torque_ff.unwrap_or(0.0),
                    };
                }
                return Play::Dry {
                    by_s: t - last.t,
                    last: Reference {
                        theta: last.theta,
                        omega: self.omega(self.len - 1),
                        alpha: 0.0,
                    },
                };
            }
        };
        let (a, b) = (*self.at(i), *self.at(i + 1));
        let h = b.t - a.t;
        // Quintic Hermite on [a, b] in s = (t − a.t)/h: θ(s) = Σ c_k s^k matching θ, ω, α
        // at both ends.
        let (dv0, dv1) = (h * self.omega(i), h * self.omega(i + 1));
        let (da0, da1) = (h * h * self.alpha(i), h * h * self.alpha(i + 1));
        let dp = b.theta - a.theta;
        let c = [
            a.theta,
            dv0,
            0.5 * da0,
            10.0 * dp - 6.0 * dv0 - 4.0 * dv1 - 1.5 * da0 + 0.5 * da1,
            -15.0 * dp + 8.0 * dv0 + 7.0 * dv1 + 1.5 * da0 - da1,
            6.0 * dp - 3.0 * dv0 - 3.0 * dv1 - 0.5 * da0 + 0.5 * da1,
        ];
        let s = (t - a.t) / h;
        let theta = c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * c[5]))));
        let omega =
            (c[1] + s * (2.0 * c[2] + s * (3.0 * c[3] + s * (4.0 * c[4] + s * 5.0 * c[5])))) / h;
        let alpha = (2.0 * c[2] + s * (6.0 * c[3] + s * (12.0 * c[4] + s * 20.0 * c[5]))) / (h * h);
        let torque_ff = match (a.torque_ff, b.torque_ff) {
            (Some(x), Some(y)) => x + (y - x) * s,
            (Some(x), None) | (None, Some(x)) => x,
            (None, None) => 0.0,
        };
        Play::At {
            reference: Reference {
                theta,
                omega,
                alpha,
            },
            torque_ff,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sine(t: f64) -> Point {
        let w = std::f64::consts::TAU;
        Point {
            t,
            theta: 2.0 * (w * t).sin(),
            omega: None,
            torque_ff: None,
        }
    }

    /// θ(t) = 2 sin 2πt at 1 kHz, played at 2 kHz: within 1e-6 rad of the sine (the
    /// Hermite's error with difference velocities: ~h²·θ''''/... at h = 1 ms), velocity
    /// continuous across points.
    #[test]
    fn a_sine_at_1_khz_plays_back_at_2_khz() {
        let mut s = Stream::default();
        let mut k = 0;
        let mut worst: f64 = 0.0;
        let mut prev_omega: Option<f64> = None;
        for tick in 0..4000 {
            let t = tick as f64 * 500e-6;
            // Points arrive 10 ms ahead of play.
            while (k as f64) * 1e-3 <= t + 0.01 {
                s.push(sine(k as f64 * 1e-3)).expect("in order");
                k += 1;
            }
            match s.play(t) {
                Play::At { reference, .. } => {
                    worst = worst.max((reference.theta - sine(t).theta).abs());
                    if let Some(w) = prev_omega {
                        // Continuous: a tick's change of ω is α·T at most (α ≤ 8π²).
                        assert!((reference.omega - w).abs() < 80.0 * 500e-6 * 1.5);
                    }
                    prev_omega = Some(reference.omega);
                }
                other => panic!("tick {tick}: {other:?}"),
            }
        }
        assert!(worst < 1e-6, "{worst:e}");
    }

    #[test]
    fn time_must_increase_and_a_dry_stream_says_by_how_much() {
        let mut s = Stream::default();
        s.push(sine(0.0)).expect("first");
        s.push(sine(0.001)).expect("second");
        assert_eq!(
            s.push(sine(0.001)),
            Err(PointError::Backwards {
                t: 0.001,
                last: 0.001
            })
        );
        let mut nan = sine(0.002);
        nan.theta = f64::NAN;
        assert!(matches!(s.push(nan), Err(PointError::NotFinite { .. })));
        assert_eq!(s.play(-0.1), Play::Waiting);
        match s.play(0.003) {
            Play::Dry { by_s, .. } => assert!((by_s - 0.002).abs() < 1e-12),
            other => panic!("{other:?}"),
        }
    }
}
