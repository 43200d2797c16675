//! Loop statistics without allocation: a fixed-size log-linear ("HDR") histogram of
//! nanosecond values and the per-process stats message every loop publishes.

#[cfg(feature = "ipc")]
use iceoryx2::prelude::ZeroCopySend;

/// Values below this are counted exactly (one bucket per ns).
const LINEAR: u64 = 64;
/// Sub-buckets per power of two above `LINEAR`: relative resolution 1/64 ≈ 1.6 %.
const SUB_BITS: u32 = 6;
/// Powers of two covered above the linear range: up to 2^40 ns ≈ 18 min.
const OCTAVES: usize = 35;
pub const BUCKETS: usize = LINEAR as usize + OCTAVES * (1 << SUB_BITS);

/// Fixed-size histogram of non-negative nanosecond values with exact min, max, sum.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.Histogram.v1")
)]
#[repr(C)]
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
}
/// A loop's timing statistics, published at ~1 Hz and once more (`is_final`) at exit.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("stepdrive.StatsReport.v4")
)]
#[repr(C)]
pub struct StatsReport {
    /// The publisher's [`crate::stack::Role::code`].
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
    /// (`stepdrive_runtime::steal`): the plant missed their periods because the hypervisor held
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
    /// `stepdrive_runtime::steal::HOST_HOLD_MIN_NS`, and for how long.
    pub host_held: Histogram,
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
