//! Following a stream within the axis's limits. A stream the limits allow is followed
//! exactly: each period takes the stream's own jerk, so a reference on the stream stays on
//! it. Off the stream — at its start, from rest, or after it asked for more than the
//! limits — a third-order correction of the state error (poles at −p) steers back onto it,
//! with |jerk| ≤ j, |α| ≤ a, and the speed bounded by braking the acceleration in time.
//! θ, ω and α stay continuous whatever the stream does.
//!
//! Why not the trajectory generator's own tracking: re-planned each period toward the
//! stream's present state, its time-optimal path to a target moving fast just ahead backs
//! off first (to have room to reach that speed there), and the rotor went backwards at a
//! stream's start.

use crate::axis::otg::Limits;
use stepdrive_shared::trajectory::Reference;

/// The correction's bandwidth, rad/s: back on a feasible stream within ~50 ms.
pub const DEFAULT_BANDWIDTH: f64 = 100.0;

/// One period of `period` s from `s`, following a stream whose state is `now` at the
/// period's start and `next` at its end. Returns the new state and the period's jerk.
pub fn follow(
    s: Reference,
    now: Reference,
    next: Reference,
    limits: Limits,
    bandwidth: f64,
    period: f64,
) -> (Reference, f64) {
    let p = bandwidth;
    // The stream's own jerk over the period, and the correction of where we are off it.
    let feedforward = (next.alpha - now.alpha) / period;
    let correction = 3.0 * p * (now.alpha - s.alpha)
        + 3.0 * p * p * (now.omega - s.omega)
        + p * p * p * (now.theta - s.theta);
    let mut jerk = (feedforward + correction).clamp(-limits.j, limits.j);
    // The acceleration stays within ±a at the period's end.
    let alpha_end = s.alpha + jerk * period;
    if alpha_end > limits.a {
        jerk = (limits.a - s.alpha) / period;
    } else if alpha_end < -limits.a {
        jerk = (-limits.a - s.alpha) / period;
    }
    // The speed stays within ±v: braking the acceleration at full jerk from the period's
    // end must not carry it past the limit.
    let peak = |jerk: f64| {
        let alpha = s.alpha + jerk * period;
        let omega = s.omega + s.alpha * period + 0.5 * jerk * period * period;
        omega + alpha * alpha.abs() / (2.0 * limits.j)
    };
    if peak(jerk) > limits.v {
        jerk = (-limits.j).max((-limits.a - s.alpha) / period);
    } else if peak(jerk) < -limits.v {
        jerk = limits.j.min((limits.a - s.alpha) / period);
    }
    let (t, t2, t3) = (period, period * period, period * period * period);
    let out = Reference {
        theta: s.theta + s.omega * t + 0.5 * s.alpha * t2 + jerk * t3 / 6.0,
        omega: (s.omega + s.alpha * t + 0.5 * jerk * t2).clamp(-limits.v, limits.v),
        alpha: s.alpha + jerk * t,
    };
    (out, jerk)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::TAU;

    const T: f64 = 500e-6;

    fn sine(t: f64) -> Reference {
        let w = TAU;
        Reference {
            theta: 2.0 * (w * t).sin(),
            omega: 2.0 * w * (w * t).cos(),
            alpha: -2.0 * w * w * (w * t).sin(),
        }
    }

    fn limits() -> Limits {
        Limits {
            v: 30.0,
            a: 500.0,
            j: 50_000.0,
        }
    }

    /// From rest onto 2 sin 2πt (which starts at 12.6 rad/s): within the limits all along,
    /// within 1e-6 rad of the stream after 0.2 s (the streaming acceptance asks 1e-4), and
    /// within 1e-7 after 0.5 s (what is left is a sine's fourth derivative, which a period of
    /// constant jerk cannot follow; a stream of cubic segments is followed exactly).
    #[test]
    fn from_rest_onto_a_sine_within_the_limits() {
        let l = limits();
        let mut s = Reference::default();
        let mut worst_late: f64 = 0.0;
        let mut worst_later: f64 = 0.0;
        for k in 0..4000 {
            let t = k as f64 * T;
            let (next, jerk) = follow(s, sine(t), sine(t + T), l, DEFAULT_BANDWIDTH, T);
            assert!(jerk.abs() <= l.j * (1.0 + 1e-9), "{t}: jerk {jerk}");
            assert!(next.alpha.abs() <= l.a * (1.0 + 1e-9), "{t}: {next:?}");
            assert!(next.omega.abs() <= l.v * (1.0 + 1e-9), "{t}: {next:?}");
            s = next;
            let off = (s.theta - sine(t + T).theta).abs();
            if t + T >= 0.2 {
                worst_late = worst_late.max(off);
            }
            if t + T >= 0.5 {
                worst_later = worst_later.max(off);
            }
        }
        assert!(worst_late < 1e-6, "{worst_late:e}");
        assert!(worst_later < 1e-7, "{worst_later:e}");
    }

    /// A stream beyond the limits (a step of 1 rad) is followed within them, and caught
    /// up with.
    #[test]
    fn a_step_is_followed_within_the_limits() {
        let l = limits();
        let mut s = Reference::default();
        let target = Reference {
            theta: 1.0,
            ..Default::default()
        };
        for _ in 0..4000 {
            let (next, jerk) = follow(s, target, target, l, DEFAULT_BANDWIDTH, T);
            assert!(jerk.abs() <= l.j * (1.0 + 1e-9));
            assert!(next.alpha.abs() <= l.a * (1.0 + 1e-9));
            assert!(next.omega.abs() <= l.v * (1.0 + 1e-9));
            s = next;
        }
        assert!((s.theta - 1.0).abs() < 1e-9, "{s:?}");
    }
}
