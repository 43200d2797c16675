//! Histogram files: the cyclictest-compatible format (`-h` output) that `latency` writes and
//! reads back from cyclictest itself, and a sparse JSON form for passing a measurement
//! between processes (the ping-pong baselines).

use stepdrive_shared::stats::Histogram;

/// A cyclictest-compatible histogram file (`-h` output): `# Histogram`, one row per 1 µs
/// bin, then the `# Total / # Min / # Avg / # Max Latencies / # Histogram Overflows`
/// trailer (µs).
pub fn cyclictest_file(h: &Histogram, bins: usize) -> String {
    use std::fmt::Write;
    let (counts, overflow) = h.microsecond_bins(bins);
    let mut s = String::from("# Histogram\n");
    for (us, c) in counts.iter().enumerate() {
        let _ = writeln!(s, "{us:06} {c:06}");
    }
    let min_us = if h.count == 0 { 0 } else { h.min_ns / 1000 };
    let avg_us = if h.count == 0 {
        0
    } else {
        (h.mean_ns() / 1000.0).round() as u64
    };
    let _ = writeln!(s, "# Total: {:09}", h.count);
    let _ = writeln!(s, "# Min Latencies: {min_us:05}");
    let _ = writeln!(s, "# Avg Latencies: {avg_us:05}");
    let _ = writeln!(s, "# Max Latencies: {:05}", h.max_ns / 1000);
    let _ = writeln!(s, "# Histogram Overflows: {overflow:05}");
    s
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cyclictest_file_parses_back() {
        let mut h = Histogram::default();
        for (us, n) in [(3u64, 5u64), (7, 2), (25, 10), (300, 1), (5000, 2)] {
            for _ in 0..n {
                h.record(us * 1000 + 400);
            }
        }
        let text = cyclictest_file(&h, 1000);
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
