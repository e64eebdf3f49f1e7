//! Fixed-size latency histograms for the real-time loop: allocated once, `record` is O(1)
//! and allocation-free, percentiles are exact to the bucket width (1 µs).

use serde::{Deserialize, Serialize};

/// Bucket width, nanoseconds.
pub const BUCKET_NS: u64 = 1_000;

/// A histogram of durations with 1 µs buckets from 0 to `range_us` µs, plus an overflow
/// count and the exact maximum.
#[derive(Clone, Debug)]
pub struct Histogram {
    buckets: Box<[u32]>,
    overflow: u64,
    count: u64,
    max_ns: u64,
    sum_ns: u128,
}

/// Percentiles of a histogram, microseconds (bucket upper bounds; overflowed values report
/// the maximum).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Number of values.
    pub count: u64,
    /// Mean, microseconds.
    pub mean_us: f64,
    /// Median, microseconds.
    pub p50_us: f64,
    /// 99th percentile, microseconds.
    pub p99_us: f64,
    /// 99.9th percentile, microseconds.
    pub p999_us: f64,
    /// Maximum, microseconds (exact).
    pub max_us: f64,
}

impl Histogram {
    /// An empty histogram covering 0 ..= `range_us` microseconds in 1 µs buckets.
    pub fn new(range_us: usize) -> Self {
        Self { buckets: vec![0; range_us.max(1)].into_boxed_slice(), overflow: 0, count: 0, max_ns: 0, sum_ns: 0 }
    }

    /// Adds one duration, nanoseconds.
    ///
    /// **Real-time (1 kHz loop):** O(1), allocation-free.
    #[inline]
    pub fn record(&mut self, ns: u64) {
        let b = (ns / BUCKET_NS) as usize;
        match self.buckets.get_mut(b) {
            Some(c) => *c = c.saturating_add(1),
            None => self.overflow += 1,
        }
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
        self.sum_ns += u128::from(ns);
    }

    /// Number of values recorded.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The `q`-quantile (0 ..= 1), microseconds: the upper bound of the bucket holding it,
    /// capped by the maximum. 0 when empty.
    pub fn quantile_us(&self, q: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (i, c) in self.buckets.iter().enumerate() {
            seen += u64::from(*c);
            if seen >= rank {
                let upper_ns = (i as u64 + 1) * BUCKET_NS;
                return upper_ns.min(self.max_ns) as f64 / 1e3;
            }
        }
        self.max_ns as f64 / 1e3
    }

    /// Count, mean, p50, p99, p99.9 and max.
    pub fn summary(&self) -> Summary {
        Summary {
            count: self.count,
            mean_us: if self.count == 0 { 0.0 } else { self.sum_ns as f64 / self.count as f64 / 1e3 },
            p50_us: self.quantile_us(0.5),
            p99_us: self.quantile_us(0.99),
            p999_us: self.quantile_us(0.999),
            max_us: self.max_ns as f64 / 1e3,
        }
    }

    /// Non-empty buckets as (lower bound µs, count), for plots.
    pub fn buckets(&self) -> impl Iterator<Item = (u64, u32)> + '_ {
        self.buckets.iter().enumerate().filter(|(_, c)| **c > 0).map(|(i, c)| (i as u64, *c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_match_a_sorted_reference() {
        let mut h = Histogram::new(1000);
        let values: Vec<u64> = (0..10_000u64).map(|i| (i * 7919) % 500_000).collect();
        for v in &values {
            h.record(*v);
        }
        let mut sorted = values.clone();
        sorted.sort_unstable();
        for q in [0.5, 0.99, 0.999] {
            let exact = sorted[((q * sorted.len() as f64).ceil() as usize).max(1) - 1] as f64 / 1e3;
            let got = h.quantile_us(q);
            assert!(got >= exact && got - exact <= 1.0, "q {q}: {got} vs {exact}");
        }
        assert_eq!(h.summary().max_us, *sorted.last().unwrap() as f64 / 1e3);
    }

    #[test]
    fn overflow_reports_the_maximum() {
        let mut h = Histogram::new(10);
        h.record(1_000);
        h.record(5_000_000);
        assert_eq!(h.quantile_us(1.0), 5_000.0);
        assert_eq!(h.quantile_us(0.5), 2.0);
        assert_eq!(Histogram::new(10).summary(), Summary::default());
    }
}
