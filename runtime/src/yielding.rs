//! Lockstep: the position loop waits for its next tick by polling and yielding its CPU,
//! which it shares with the current loop ([`crate::doorbell::placement`]), instead of
//! sleeping on its doorbell, for as long as no other process takes that CPU.
//!
//! Why: at each tick the current loop waits for the tick's setpoint and yields
//! ([`crate::node::Awaits::Beside`]). A position loop that is runnable then runs at once: a
//! round trip of two yields costs ~3 µs on this VM. Woken from its doorbell instead, it ran
//! 5–16 µs later, and with the current loop spinning ~14 µs later (docs/measurements.md,
//! "The current loop yields to the position loop"). Beside a CPU hog it is the other way
//! round: a yield hands the hog a whole time slice (milliseconds), while a woken sleeper
//! preempts it. So a yield that comes back that late turns yielding off for a while.

/// A yield that comes back later than this found the CPU held by another process than the
/// current loop, which yields it back at its next tick (~20 µs apart in the default stack,
/// ~200 µs with a 200 Hz position loop): a CPU hog holds it for its time slice, milliseconds.
pub const HELD_NS: u64 = 300_000;
/// After a held yield the position loop sleeps on its doorbell for a while, then tries
/// again: first for this long (a process that ran once, the monitor, a kernel thread, costs
/// little)...
pub const BACK_OFF_MIN_NS: u64 = 2_000_000;
/// ... twice as long each time a yield is held again soon after, up to this (beside a CPU
/// hog, one slice lost every 200 ms).
pub const BACK_OFF_MAX_NS: u64 = 200_000_000;
/// A yield held within this long after the back-off ended is held again by the same taker.
pub const AGAIN_NS: u64 = 20_000_000;
/// Yield only this soon after the last input: a stack that is starting up or held up
/// sleeps instead of keeping a CPU busy.
pub const RECENT_NS: u64 = 200_000;

/// Whether the position loop yields or sleeps while it waits for its next tick.
#[derive(Debug, Clone)]
pub struct YieldPoll {
    off_until_ns: u64,
    back_off_ns: u64,
    held_ns: Option<u64>,
}

impl Default for YieldPoll {
    fn default() -> Self {
        Self {
            off_until_ns: 0,
            back_off_ns: BACK_OFF_MIN_NS,
            held_ns: None,
        }
    }
}

impl YieldPoll {
    /// Whether to yield now (else sleep on the doorbell), `last_input_ns` being when the
    /// node last took an input.
    pub fn yields(&self, now_ns: u64, last_input_ns: Option<u64>) -> bool {
        now_ns >= self.off_until_ns
            && last_input_ns.is_some_and(|t| now_ns.saturating_sub(t) < RECENT_NS)
    }

    /// Books a yield from `start_ns` that came back at `back_ns`.
    pub fn yielded(&mut self, start_ns: u64, back_ns: u64) {
        if back_ns.saturating_sub(start_ns) <= HELD_NS {
            return;
        }
        // Held again soon after the back-off: whoever holds the CPU is still there.
        let again = self
            .held_ns
            .is_some_and(|t| back_ns.saturating_sub(t) < self.back_off_ns + AGAIN_NS);
        self.back_off_ns = match again {
            true => (2 * self.back_off_ns).min(BACK_OFF_MAX_NS),
            false => BACK_OFF_MIN_NS,
        };
        self.held_ns = Some(back_ns);
        self.off_until_ns = back_ns.saturating_add(self.back_off_ns);
        tracing::debug!(
            held_us = back_ns.saturating_sub(start_ns) / 1000,
            back_off_ms = self.back_off_ns / 1_000_000,
            "a yield was held: sleeping between ticks for a while"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yields_while_inputs_come_and_no_one_holds_the_cpu() {
        let mut y = YieldPoll::default();
        let t = 1_000_000_000;
        assert!(y.yields(t, Some(t - 20_000)), "a tick 20 µs ago");
        assert!(!y.yields(t, None), "before the first input");
        assert!(!y.yields(t, Some(t - RECENT_NS)), "no input for 200 µs");
        // The current loop gives the CPU back within a tick: yielding stays on.
        y.yielded(t, t + 25_000);
        assert!(y.yields(t + 25_000, Some(t)));
    }

    #[test]
    fn a_yield_held_for_a_time_slice_turns_yielding_off_longer_each_time_it_recurs() {
        let mut y = YieldPoll::default();
        let mut t = 1_000_000_000;
        let mut back_offs = Vec::new();
        for _ in 0..10 {
            let back = t + 3_000_000;
            y.yielded(t, back);
            let off = y.off_until_ns - back;
            assert!(
                !y.yields(back + off - 1, Some(back + off - 2)),
                "within the back-off"
            );
            assert!(y.yields(back + off, Some(back + off - 1)), "after it");
            back_offs.push(off / 1_000_000);
            // Beside a hog the first yield after the back-off is held again.
            t = back + off;
        }
        assert_eq!(back_offs, [2, 4, 8, 16, 32, 64, 128, 200, 200, 200]);
        // A yield held once, long after: a passing process; the back-off starts over.
        let later = t + 10 * BACK_OFF_MAX_NS;
        y.yielded(later, later + HELD_NS + 1);
        assert_eq!(y.off_until_ns - (later + HELD_NS + 1), BACK_OFF_MIN_NS);
    }
}
