//! A latency histogram with bounded relative error and fixed memory.
//!
//! A run at hundreds of thousands of acks per second for minutes would need gigabytes to keep
//! every sample; log-linear buckets (exact below 128 ns, then 64 buckets per power of two, so
//! within 1/64 ≈ 1.6% of the true value) keep percentiles honest in 30 KiB per histogram, and
//! histograms from many clients merge by adding counts.

use std::time::Duration;

/// Values below `2^SUB_BITS` get a bucket each; above, every power of two is cut into
/// `2^(SUB_BITS-1)` buckets.
const SUB_BITS: u32 = 7;
const EXACT: u64 = 1 << SUB_BITS;
const HALF: u64 = EXACT / 2;
const BUCKETS: usize = (EXACT + (64 - SUB_BITS as u64) * HALF) as usize;

/// Counts of durations in nanoseconds, plus the exact maximum and sum.
#[derive(Clone)]
pub struct Histogram {
    counts: Vec<u64>,
    count: u64,
    max: u64,
    sum: u128,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram {
            counts: vec![0; BUCKETS],
            count: 0,
            max: 0,
            sum: 0,
        }
    }
}

fn index(v: u64) -> usize {
    if v < EXACT {
        return v as usize;
    }
    let msb = 63 - v.leading_zeros();
    let shift = msb - (SUB_BITS - 1);
    (EXACT + u64::from(shift - 1) * HALF + ((v >> shift) - HALF)) as usize
}

/// The largest value that falls in bucket `i`.
fn upper(i: usize) -> u64 {
    let i = i as u64;
    if i < EXACT {
        return i;
    }
    let shift = (i - EXACT) / HALF + 1;
    let sub = (i - EXACT) % HALF + HALF;
    // The top bucket's bound is u64::MAX; the shifted form would overflow.
    ((sub + 1) << shift).wrapping_sub(1).max(sub << shift)
}

impl Histogram {
    pub fn record(&mut self, d: Duration) {
        self.record_ns(d.as_nanos().min(u128::from(u64::MAX)) as u64);
    }

    pub fn record_ns(&mut self, ns: u64) {
        self.counts[index(ns)] += 1;
        self.count += 1;
        self.max = self.max.max(ns);
        self.sum += u128::from(ns);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max_ns(&self) -> u64 {
        self.max
    }

    pub fn mean_ns(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum as f64 / self.count as f64
        }
    }

    pub fn merge(&mut self, other: &Histogram) {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        self.count += other.count;
        self.max = self.max.max(other.max);
        self.sum += other.sum;
    }

    /// The value at quantile `q` (0..=1): the smallest bucket bound at or above which lie at
    /// least `q` of the samples, never above the true maximum. 0 when empty. Monotone in `q`,
    /// so p50 ≤ p95 ≤ p99 ≤ max by construction.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.count == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return upper(i).min(self.max);
            }
        }
        self.max
    }

    /// [`Histogram::quantile_ns`] in milliseconds.
    pub fn quantile_ms(&self, q: f64) -> f64 {
        self.quantile_ns(q) as f64 / 1e6
    }

    pub fn max_ms(&self) -> f64 {
        self.max as f64 / 1e6
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn buckets_are_contiguous_and_ordered() {
        let mut last_upper = None;
        for i in 0..BUCKETS {
            let u = upper(i);
            if let Some(prev) = last_upper {
                assert!(u > prev, "bucket {i}");
            }
            assert_eq!(index(u), i, "bucket {i}'s upper bound {u} maps back");
            if i > 0 {
                assert_eq!(
                    index(upper(i - 1) + 1),
                    i,
                    "bucket {i} starts where {} ends",
                    i - 1
                );
            }
            last_upper = Some(u);
        }
        assert_eq!(upper(BUCKETS - 1), u64::MAX);
        assert_eq!(index(u64::MAX), BUCKETS - 1);
    }

    #[test]
    fn empty_and_single() {
        let mut h = Histogram::default();
        assert_eq!((h.quantile_ns(0.5), h.max_ns(), h.count()), (0, 0, 0));
        h.record(Duration::from_micros(1500));
        for q in [0.0, 0.5, 0.99, 1.0] {
            assert_eq!(h.quantile_ns(q), 1_500_000, "q={q}");
        }
        assert_eq!(h.max_ms(), 1.5);
    }

    #[test]
    fn percentiles_of_a_known_distribution() {
        // 1..=10_000 µs: p50 = 5000 µs, p95 = 9500 µs, p99 = 9900 µs.
        let mut h = Histogram::default();
        for us in 1..=10_000u64 {
            h.record_ns(us * 1000);
        }
        for (q, want) in [(0.5, 5_000_000.0), (0.95, 9_500_000.0), (0.99, 9_900_000.0)] {
            let got = h.quantile_ns(q) as f64;
            assert!(
                got >= want && got <= want * (1.0 + 1.0 / 64.0),
                "q={q}: {got} vs {want}"
            );
        }
        assert_eq!(h.quantile_ns(1.0), 10_000_000);
        assert_eq!(h.max_ns(), 10_000_000);
        assert!((h.mean_ns() - 5_000_500.0).abs() < 1.0);
    }

    proptest! {
        /// Against the exact order statistic: never below it, at most one bucket (1/64) above,
        /// ordered, and merging two halves gives the histogram of the whole.
        #[test]
        fn quantiles_match_sorted_samples(
            samples in proptest::collection::vec(0u64..50_000_000_000, 1..400),
            split in 0usize..400,
        ) {
            let mut sorted = samples.clone();
            sorted.sort_unstable();
            let split = split.min(samples.len());
            let (mut a, mut b, mut whole) =
                (Histogram::default(), Histogram::default(), Histogram::default());
            for (i, &s) in samples.iter().enumerate() {
                if i < split { a.record_ns(s) } else { b.record_ns(s) }
                whole.record_ns(s);
            }
            a.merge(&b);
            let mut last = 0;
            for q in [0.0, 0.1, 0.5, 0.9, 0.95, 0.99, 0.999, 1.0] {
                let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
                let exact = sorted[rank - 1];
                let got = whole.quantile_ns(q);
                prop_assert_eq!(got, a.quantile_ns(q));
                prop_assert!(got >= exact, "q={} got {} exact {}", q, got, exact);
                prop_assert!(got as f64 <= exact as f64 * (1.0 + 1.0 / 64.0) + 1.0,
                    "q={} got {} exact {}", q, got, exact);
                prop_assert!(got >= last);
                last = got;
            }
            prop_assert_eq!(whole.max_ns(), *sorted.last().unwrap());
            prop_assert_eq!(whole.quantile_ns(1.0), whole.max_ns());
        }
    }
}
