//! The position loop's recent setpoints, to tell θ_d at any state's sample time: the last
//! setpoint taken at or before it, carried on along its ω_d and α_d. The metrics grade a
//! program's run by it and the recorder writes its θ_d by it.
//!
//! Why a history and not the newest setpoint: a reader drains setpoints and states from
//! separate queues, so a state may arrive after setpoints computed from later samples; in
//! lockstep the states' queue lags by as much as it holds ([`MONITOR_BUFFER`] samples). A
//! state is graded (and recorded) once every control of its tick has come (see
//! `metrics::ProgramReference`), never against a setpoint that has not.

use stepdrive_shared::messages::TorqueSetpoint;
use stepdrive_shared::scenario::Scenario;
use stepdrive_shared::services::MONITOR_BUFFER;
use stepdrive_shared::trajectory::Reference;

/// A ring of the last setpoints (sample time, reference), allocated once.
#[derive(Debug, Clone)]
pub struct SetpointHistory {
    ring: Vec<(f64, Reference)>,
    /// Setpoints pushed; the newest is at `seen − 1` modulo the ring's length.
    seen: usize,
}

impl SetpointHistory {
    /// Room for the position loop's setpoints over the states' queue of `s`, and some: two
    /// a tick, as a command between ticks adds one ([`stepdrive_runtime`]'s
    /// `RINGS_PER_PERIOD`).
    pub fn for_scenario(s: &Scenario) -> Self {
        Self::with_capacity(2 * MONITOR_BUFFER / s.rate_ratio().max(1) as usize + 64)
    }

    pub fn with_capacity(capacity: usize) -> Self {
        Self {
            ring: vec![(f64::NAN, Reference::default()); capacity.max(1)],
            seen: 0,
        }
    }

    /// Forgets every setpoint (a new method's run).
    pub fn clear(&mut self) {
        self.seen = 0;
    }

    /// The position loop's next setpoint (their sample times increase).
    pub fn push(&mut self, sp: &TorqueSetpoint) {
        let len = self.ring.len();
        self.ring[self.seen % len] = (sp.sample_time_s, sp.reference());
        self.seen += 1;
    }

    /// θ_d, ω_d, α_d at `t`: the last setpoint at or before `t` carried on to it; `None`
    /// before the oldest kept. A setpoint is never carried back: θ_d before it is not told
    /// by its ω_d and α_d (a reader whose first setpoint is mid-move would name a θ_d the
    /// axis never had for the states before it, the rotor standing still).
    pub fn at(&self, t: f64) -> Option<Reference> {
        let len = self.ring.len();
        let kept = self.seen.min(len);
        if kept == 0 {
            return None;
        }
        let oldest = self.seen - kept;
        let at = |i: usize| self.ring[(oldest + i) % len];
        // Binary search for the first later than t: [lo, hi) holds it.
        let (mut lo, mut hi) = (0, kept);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if at(mid).0 <= t {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        let (t0, r) = at(lo.checked_sub(1)?);
        Some(r.after(t - t0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn moving(t: f64, theta: f64, omega: f64) -> TorqueSetpoint {
        TorqueSetpoint {
            sample_time_s: t,
            theta_d_rad: theta,
            omega_d_rad_s: omega,
            ..Default::default()
        }
    }

    #[test]
    fn a_time_is_told_by_the_last_setpoint_at_or_before_it_carried_on() {
        let mut h = SetpointHistory::with_capacity(4);
        assert!(h.at(1.0).is_none());
        for k in 0..10 {
            h.push(&moving(f64::from(k), f64::from(k) * 10.0, 1.0));
        }
        // Kept: 6, 7, 8, 9.
        assert_eq!(h.at(7.0).map(|r| r.theta), Some(70.0));
        assert_eq!(h.at(7.5).map(|r| r.theta), Some(70.5));
        assert_eq!(h.at(12.0).map(|r| r.theta), Some(93.0));
        // Older than any kept: unknown (carried back along ω_d it would be 59).
        assert!(h.at(5.0).is_none());
        assert!(h.at(5.999).is_none());
        h.clear();
        assert!(h.at(7.0).is_none());
    }
}
