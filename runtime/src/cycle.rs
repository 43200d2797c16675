//! The per-cycle bookkeeping every loop does, kept free of any clock so that it can be
//! driven with known timestamps in tests: wake-up, period and compute time of each cycle,
//! and runs of periods without their command.

use stepdrive_shared::stats::StatsReport;

/// Runs of consecutive periods without their command: the current one (the watchdog's
/// count), how many there were, the longest, and their lengths.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MissRuns {
    /// Misses in a row up to now.
    pub current: u32,
    pub runs: u64,
    pub longest: u32,
    /// Finished runs by length: 1, 2-3, 4-7, ..., 128 and more periods.
    pub by_length: [u64; 8],
}

impl MissRuns {
    /// One period: its command was `missed`, or not.
    pub fn record(&mut self, missed: bool) {
        if missed {
            self.current = self.current.saturating_add(1);
            self.runs += u64::from(self.current == 1);
            self.longest = self.longest.max(self.current);
        } else if self.current > 0 {
            let bucket = 31 - self.current.leading_zeros();
            self.by_length[(bucket as usize).min(7)] += 1;
            self.current = 0;
        }
    }

    /// Into a stats report's run counters.
    pub fn copy_to(&self, stats: &mut StatsReport) {
        stats.miss_runs = self.runs;
        stats.longest_miss_run = u64::from(self.longest);
    }
}

/// The per-cycle bookkeeping every periodic loop does, kept free of any clock so that it
/// can be driven with known timestamps in tests.
#[derive(Debug, Clone, Default)]
pub struct CycleRecorder {
    period_ns: u64,
    prev_woke: Option<u64>,
}

impl CycleRecorder {
    pub fn new(period_ns: u64) -> Self {
        Self {
            period_ns,
            prev_woke: None,
        }
    }

    /// Records one cycle that was due at `deadline_ns`, woke at `woke_ns` and finished at
    /// `done_ns`: wake-up latency, interval since the previous wake-up, compute time. A cycle
    /// that finishes after the next deadline is a miss (returns true).
    pub fn record(
        &mut self,
        r: &mut StatsReport,
        deadline_ns: u64,
        woke_ns: u64,
        done_ns: u64,
    ) -> bool {
        r.wakeup.record(woke_ns.saturating_sub(deadline_ns));
        if let Some(prev) = self.prev_woke {
            r.period.record(woke_ns.saturating_sub(prev));
        }
        self.prev_woke = Some(woke_ns);
        r.compute.record(done_ns.saturating_sub(woke_ns));
        r.cycles += 1;
        let missed = done_ns > deadline_ns + self.period_ns;
        if missed {
            r.misses += 1;
        }
        missed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_shared::stats::Histogram;

    /// A synthetic 1 kHz loop with injected delays: every cycle wakes 20 µs late, except
    /// every 100th which wakes 300 µs late; every 50th cycle computes 1.5 ms (a miss), the
    /// others 100 µs. The recorder must report exactly those percentiles and misses.
    #[test]
    fn synthetic_loop_with_injected_delays() {
        let period = 1_000_000u64;
        let mut rec = CycleRecorder::new(period);
        let mut r = Box::<StatsReport>::default();
        let n = 10_000u64;
        let mut misses = 0;
        for k in 0..n {
            let deadline = 5_000_000 + k * period;
            let late = if k % 100 == 99 { 300_000 } else { 20_000 };
            let compute = if k % 50 == 49 { 1_500_000 } else { 100_000 };
            let woke = deadline + late;
            if rec.record(&mut r, deadline, woke, woke + compute) {
                misses += 1;
            }
        }
        assert_eq!(r.cycles, n);
        assert_eq!(misses, n / 50);
        assert_eq!(r.misses, n / 50);
        // Wake-up: 99 % at 20 µs, 1 % at 300 µs.
        let q = |h: &Histogram, p: f64| h.quantile_ns(p).unwrap();
        let within = |v: u64, want: u64| v >= want && v as f64 <= want as f64 * 1.016;
        assert!(within(q(&r.wakeup, 0.5), 20_000));
        assert!(within(q(&r.wakeup, 0.99), 20_000));
        assert!(within(q(&r.wakeup, 0.995), 300_000));
        assert_eq!(r.wakeup.max_ns, 300_000);
        assert_eq!(r.wakeup.min_ns, 20_000);
        // Compute: 98 % at 100 µs, 2 % at 1.5 ms.
        assert!(within(q(&r.compute, 0.98), 100_000));
        assert!(within(q(&r.compute, 0.99), 1_500_000));
        // Period: one period, ± the 280 µs jitter around the late cycles.
        assert_eq!(r.period.count, n - 1);
        assert!(within(q(&r.period, 0.5), period));
        assert_eq!(r.period.max_ns, period + 280_000);
        assert_eq!(r.period.min_ns, period - 280_000);
    }
}
