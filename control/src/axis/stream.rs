//! A cyclic synchronous position stream: timestamped points (θ, optional ω and τ
//! feed-forward) at 100 Hz–2 kHz, played a lead behind their arrival and interpolated to
//! the position loop's tick with continuous velocity (cubic Hermite; ω by central
//! differences where a point carries none). A fixed ring: nothing allocates after
//! construction.

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
        let (wa, wb) = (self.omega(i), self.omega(i + 1));
        let h = b.t - a.t;
        let s = (t - a.t) / h;
        // Cubic Hermite on [a, b]: θ(s), and its derivatives in time.
        let (s2, s3) = (s * s, s * s * s);
        let theta = (2.0 * s3 - 3.0 * s2 + 1.0) * a.theta
            + (s3 - 2.0 * s2 + s) * h * wa
            + (-2.0 * s3 + 3.0 * s2) * b.theta
            + (s3 - s2) * h * wb;
        let omega = ((6.0 * s2 - 6.0 * s) * a.theta
            + (3.0 * s2 - 4.0 * s + 1.0) * h * wa
            + (-6.0 * s2 + 6.0 * s) * b.theta
            + (3.0 * s2 - 2.0 * s) * h * wb)
            / h;
        let alpha = ((12.0 * s - 6.0) * a.theta
            + (6.0 * s - 4.0) * h * wa
            + (-12.0 * s + 6.0) * b.theta
            + (6.0 * s - 2.0) * h * wb)
            / (h * h);
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
