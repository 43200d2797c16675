//! Loop statistics without allocation: a fixed-size log-linear ("HDR") histogram of
//! nanosecond values, the per-process stats message, percentiles, and the
//! cyclictest-compatible histogram file.

use iceoryx2::prelude::ZeroCopySend;

/// Values below this are counted exactly (one bucket per ns).
const LINEAR: u64 = 64;
/// Sub-buckets per power of two above `LINEAR`: relative resolution 1/64 ≈ 1.6 %.
const SUB_BITS: u32 = 6;
/// Powers of two covered above the linear range: up to 2^40 ns ≈ 18 min.
const OCTAVES: usize = 35;
pub const BUCKETS: usize = LINEAR as usize + OCTAVES * (1 << SUB_BITS);

/// Fixed-size histogram of non-negative nanosecond values with exact min, max, sum.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("stepdrive.Histogram.v1")]
pub struct Histogram {
    pub count: u64,
    pub sum_ns: u64,
    pub min_ns: u64,
    pub max_ns: u64,
    pub counts: [u64; BUCKETS],
}

impl Default for Histogram {
    fn default() -> Self {
        Self {
            count: 0,
            sum_ns: 0,
            min_ns: u64::MAX,
            max_ns: 0,
            counts: [0; BUCKETS],
        }
    }
}

fn bucket_of(v: u64) -> usize {
    if v < LINEAR {
        return v as usize;
    }
    let e = 63 - v.leading_zeros(); // floor(log2 v) ≥ SUB_BITS
    let sub = (v >> (e - SUB_BITS)) - (1 << SUB_BITS);
    let idx = LINEAR as usize + (e - SUB_BITS) as usize * (1 << SUB_BITS) + sub as usize;
    idx.min(BUCKETS - 1)
}

/// [low, high) of bucket `i`, ns.
fn bucket_range(i: usize) -> (u64, u64) {
    if (i as u64) < LINEAR {
        return (i as u64, i as u64 + 1);
    }
    let j = i - LINEAR as usize;
    let e = (j >> SUB_BITS) as u32 + SUB_BITS;
    let sub = (j & ((1 << SUB_BITS) - 1)) as u64;
    let width = 1u64 << (e - SUB_BITS);
    let low = (1u64 << e) + sub * width;
    (low, low + width)
}

impl Histogram {
    /// Records one value. O(1), no allocation.
    #[inline]
    pub fn record(&mut self, ns: u64) {
        self.counts[bucket_of(ns)] += 1;
        self.count += 1;
        self.sum_ns = self.sum_ns.saturating_add(ns);
        self.min_ns = self.min_ns.min(ns);
        self.max_ns = self.max_ns.max(ns);
    }

    pub fn merge(&mut self, other: &Histogram) {
        for (a, b) in self.counts.iter_mut().zip(other.counts.iter()) {
            *a += b;
        }
        self.count += other.count;
        self.sum_ns = self.sum_ns.saturating_add(other.sum_ns);
        self.min_ns = self.min_ns.min(other.min_ns);
        self.max_ns = self.max_ns.max(other.max_ns);
    }

    pub fn mean_ns(&self) -> f64 {
        if self.count == 0 {
            f64::NAN
        } else {
            self.sum_ns as f64 / self.count as f64
        }
    }

    /// The value at quantile `q` (0..=1): the upper edge of the bucket holding it, capped
    /// by the exact maximum, so a percentile is never under-reported by more than a bucket.
    pub fn quantile_ns(&self, q: f64) -> Option<u64> {
        if self.count == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                let (_, high) = bucket_range(i);
                return Some((high - 1).min(self.max_ns).max(self.min_ns));
            }
        }
        Some(self.max_ns)
    }

    /// Counts per 1 µs bin for bins 0..`bins` (cyclictest's layout) and the overflow count.
    /// Above 64 µs a bucket is wider than 1 µs; its count is spread evenly over the bins it
    /// covers (the remainder to the lowest), so totals are exact and no comb appears.
    pub fn microsecond_bins(&self, bins: usize) -> (Vec<u64>, u64) {
        let mut out = vec![0u64; bins];
        let mut overflow = 0;
        for (i, &c) in self.counts.iter().enumerate() {
            if c == 0 {
                continue;
            }
            let (low, high) = bucket_range(i);
            let first = (low / 1000) as usize;
            let last = ((high - 1) / 1000) as usize;
            let width = (last - first + 1) as u64;
            for (j, bin) in (first..=last).enumerate() {
                let share = c / width + u64::from((j as u64) < c % width);
                if bin < bins {
                    out[bin] += share;
                } else {
                    overflow += share;
                }
            }
        }
        (out, overflow)
    }

    /// A cyclictest-compatible histogram file (`-h` output): `# Histogram`, one row per 1 µs
    /// bin, then the `# Total / # Min / # Avg / # Max Latencies / # Histogram Overflows`
    /// trailer (µs).
    pub fn cyclictest_file(&self, bins: usize) -> String {
        use std::fmt::Write;
        let (counts, overflow) = self.microsecond_bins(bins);
        let mut s = String::from("# Histogram\n");
        for (us, c) in counts.iter().enumerate() {
            let _ = writeln!(s, "{us:06} {c:06}");
        }
        let min_us = if self.count == 0 {
            0
        } else {
            self.min_ns / 1000
        };
        let avg_us = if self.count == 0 {
            0
        } else {
            (self.mean_ns() / 1000.0).round() as u64
        };
        let _ = writeln!(s, "# Total: {:09}", self.count);
        let _ = writeln!(s, "# Min Latencies: {min_us:05}");
        let _ = writeln!(s, "# Avg Latencies: {avg_us:05}");
        let _ = writeln!(s, "# Max Latencies: {:05}", self.max_ns / 1000);
        let _ = writeln!(s, "# Histogram Overflows: {overflow:05}");
        s
    }
}

/// A cyclictest histogram file read back (first data column only).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CyclictestHistogram {
    pub bins: Vec<u64>,
    pub total: u64,
    pub min_us: u64,
    pub avg_us: u64,
    pub max_us: u64,
    pub overflows: u64,
}

impl CyclictestHistogram {
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut h = Self::default();
        let mut in_hist = false;
        let field = |line: &str| -> Result<u64, String> {
            line.split(':')
                .nth(1)
                .and_then(|v| v.split_whitespace().next())
                .ok_or_else(|| format!("no value in `{line}`"))?
                .parse()
                .map_err(|e| format!("bad number in `{line}`: {e}"))
        };
        for line in text.lines() {
            let line = line.trim();
            if line == "# Histogram" {
                in_hist = true;
            } else if let Some(rest) = line.strip_prefix("# ") {
                if rest.starts_with("Total:") {
                    h.total = field(line)?;
                } else if rest.starts_with("Min Latencies:") {
                    h.min_us = field(line)?;
                } else if rest.starts_with("Avg Latencies:") {
                    h.avg_us = field(line)?;
                } else if rest.starts_with("Max Latencies:") {
                    h.max_us = field(line)?;
                } else if rest.starts_with("Histogram Overflows:") {
                    h.overflows = field(line)?;
                }
            } else if in_hist && !line.is_empty() && !line.starts_with('#') {
                let mut cols = line.split_whitespace();
                let bin: usize = cols
                    .next()
                    .and_then(|b| b.parse().ok())
                    .ok_or_else(|| format!("bad histogram row `{line}`"))?;
                let count: u64 = cols
                    .next()
                    .and_then(|c| c.parse().ok())
                    .ok_or_else(|| format!("bad histogram row `{line}`"))?;
                if bin >= h.bins.len() {
                    h.bins.resize(bin + 1, 0);
                }
                h.bins[bin] = count;
            }
        }
        if !in_hist {
            return Err("no `# Histogram` section".into());
        }
        Ok(h)
    }

    /// Quantile in µs from the 1 µs bins (overflows count as beyond the last bin).
    pub fn quantile_us(&self, q: f64) -> Option<u64> {
        let n: u64 = self.bins.iter().sum::<u64>() + self.overflows;
        if n == 0 {
            return None;
        }
        let rank = ((q * n as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (us, c) in self.bins.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Some(us as u64);
            }
        }
        Some(self.max_us)
    }
}

/// Which process a [`StatsReport`] comes from.
pub mod roles {
    pub const PLANT: u32 = 0;
    pub const CURRENT_LOOP: u32 = 1;
    pub const POSITION_LOOP: u32 = 2;
}

/// A loop's timing statistics, published at ~1 Hz and once more (`is_final`) at exit.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[repr(C)]
#[type_name("stepdrive.StatsReport.v4")]
pub struct StatsReport {
    pub role: u32,
    pub is_final: u32,
    pub seq: u64,
    pub publish_time_ns: u64,
    /// Loop cycles executed.
    pub cycles: u64,
    /// Deadline misses: plant — the command for a period was not there, the previous one
    /// was held; current loop — answer published after the next sample's deadline;
    /// position loop — tick computed more than one period late.
    pub misses: u64,
    /// Own wake-ups more than one period late (deadlines skipped).
    pub overruns: u64,
    /// Input messages lost or overwritten (sequence gaps).
    pub lost: u64,
    /// Plant: commands that arrived after their period and were discarded unapplied.
    pub late_discarded: u64,
    /// Plant: of the misses, periods that got the freshest command's plan entry (the rest
    /// held the previous voltage).
    pub planned: u64,
    /// Plant: runs of consecutive misses (how often the current loop was away), and the
    /// longest one.
    pub miss_runs: u64,
    pub longest_miss_run: u64,
    /// Bridge: frames from the drive dropped for a CRC mismatch.
    pub crc_errors: u64,
    /// Bridge: frames dropped as malformed, duplicate or out of order.
    pub bad_frames: u64,
    /// Bridge: commands not sent because they were non-finite or beyond the bus voltage.
    pub rejected_commands: u64,
    /// Bridge: samples received but superseded by a newer one before they were published
    /// (the bridge was held up); `lost` counts those that never arrived.
    pub superseded: u64,
    /// Current loop: of the states it never saw (`lost`), those its host holds explain
    /// (see [`crate::steal`]): the plant missed their periods because the hypervisor held
    /// the loop's vCPU, not because of anything in the guest.
    pub host_missed: u64,
    /// Current loop: of the rest, those explained by the loop waiting for its CPU behind
    /// another task of the guest (its run-queue delay).
    pub queued_missed: u64,
    /// Actual interval between successive cycles.
    pub period: Histogram,
    /// Wake-up latency against the absolute deadline.
    pub wakeup: Histogram,
    /// Compute time of one cycle.
    pub compute: Histogram,
    /// Publish → receive latency of the loop's main input topic.
    pub hop: Histogram,
    /// Plant only: sample publish → answering command published (sensor to actuator).
    pub sensor_to_actuator: Histogram,
    /// Bridge only: command frame sent → the drive reports it applied (bridge → drive →
    /// bridge round trip, including the wait for the drive's next period).
    pub round_trip: Histogram,
    /// Current loop: cycles in which the host held its vCPU at least
    /// [`crate::steal::HOST_HOLD_MIN_NS`], and for how long.
    pub host_held: Histogram,
}

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

    #[test]
    fn buckets_cover_values_with_bounded_relative_error() {
        for v in [
            0u64,
            1,
            63,
            64,
            65,
            100,
            1_000,
            25_000,
            1_234_567,
            10_000_000_000,
        ] {
            let (lo, hi) = bucket_range(bucket_of(v));
            assert!(lo <= v && v < hi, "{v} not in [{lo},{hi})");
            assert!(
                (hi - lo) as f64 <= (v as f64 / 64.0).max(1.0),
                "{v}: width {}",
                hi - lo
            );
        }
        // Contiguous.
        for i in 0..BUCKETS - 1 {
            assert_eq!(bucket_range(i).1, bucket_range(i + 1).0);
        }
    }

    #[test]
    fn percentiles_of_known_values() {
        let mut h = Histogram::default();
        // 1..=10000 µs in ns: quantile q is q·10000 µs.
        for us in 1..=10_000u64 {
            h.record(us * 1000);
        }
        for (q, want) in [(0.5, 5_000_000.0), (0.9, 9_000_000.0), (0.99, 9_900_000.0)] {
            let got = h.quantile_ns(q).unwrap() as f64;
            assert!(got >= want && got <= want * 1.016, "q{q}: {got} vs {want}");
        }
        assert_eq!(h.min_ns, 1000);
        assert_eq!(h.max_ns, 10_000_000);
        assert_eq!(h.quantile_ns(1.0), Some(10_000_000));
        assert!((h.mean_ns() - 5_000_500.0).abs() < 1e-6);
    }

    #[test]
    fn cyclictest_file_parses_back() {
        let mut h = Histogram::default();
        for (us, n) in [(3u64, 5u64), (7, 2), (25, 10), (300, 1), (5000, 2)] {
            for _ in 0..n {
                h.record(us * 1000 + 400);
            }
        }
        let text = h.cyclictest_file(1000);
        let back = CyclictestHistogram::parse(&text).expect("parse");
        assert_eq!(back.bins.len(), 1000);
        assert_eq!((back.bins[3], back.bins[7], back.bins[25]), (5, 2, 10));
        // Above 64 µs a bucket is 1/64 of the value wide: 300.4 µs lands within ±4 µs.
        assert_eq!(back.bins[296..=304].iter().sum::<u64>(), 1);
        assert_eq!(back.total, 20);
        assert_eq!(back.overflows, 2);
        assert_eq!(back.min_us, 3);
        assert_eq!(back.max_us, 5000);
        assert_eq!(back.quantile_us(0.5), Some(25));
    }

    #[test]
    fn parses_real_cyclictest_output_shape() {
        let text = "# /dev/cpu_dma_latency set to 0us\n# Histogram\n000000 000000\n000001 000004\n\
                    000002 000010\n# Total: 000000014\n# Min Latencies: 00001\n# Avg Latencies: 00002\n\
                    # Max Latencies: 00002\n# Histogram Overflows: 00000\n# Histogram Overflow at cycle number:\n# Thread 0:\n";
        let h = CyclictestHistogram::parse(text).unwrap();
        assert_eq!(h.bins, vec![0, 4, 10]);
        assert_eq!(h.quantile_us(0.99), Some(2));
    }
}

/// A histogram as JSON (sparse buckets), for passing a measurement between processes.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SparseHistogram {
    pub count: u64,
    pub sum_ns: u64,
    pub min_ns: u64,
    pub max_ns: u64,
    /// (bucket index, count) for non-empty buckets.
    pub buckets: Vec<(usize, u64)>,
}

impl From<&Histogram> for SparseHistogram {
    fn from(h: &Histogram) -> Self {
        Self {
            count: h.count,
            sum_ns: h.sum_ns,
            min_ns: h.min_ns,
            max_ns: h.max_ns,
            buckets: h
                .counts
                .iter()
                .enumerate()
                .filter(|(_, c)| **c > 0)
                .map(|(i, c)| (i, *c))
                .collect(),
        }
    }
}

impl SparseHistogram {
    pub fn to_histogram(&self) -> Result<Histogram, String> {
        let mut h = Histogram {
            count: self.count,
            sum_ns: self.sum_ns,
            min_ns: self.min_ns,
            max_ns: self.max_ns,
            ..Default::default()
        };
        for &(i, c) in &self.buckets {
            *h.counts
                .get_mut(i)
                .ok_or_else(|| format!("bucket {i} out of range"))? = c;
        }
        if h.counts.iter().sum::<u64>() != h.count {
            return Err("bucket counts do not add up to the total".into());
        }
        Ok(h)
    }
}
