//! Latency histograms: `hdrhistogram` at 3 significant digits, plus the exact maximum and sum.
//!
//! A run at hundreds of thousands of acks per second for minutes would need gigabytes to keep
//! every sample; an HdrHistogram keeps every percentile within 0.1% of the true value in a few
//! tens of KiB, and the histograms of many clients merge by adding counts. This wrapper only adds
//! what the report prints exactly (maximum, mean) and the load tool's units.

use std::time::Duration;

/// Significant decimal digits every recorded value keeps (HdrHistogram's precision).
pub const SIGNIFICANT_DIGITS: u8 = 3;

/// Counts of durations in nanoseconds, plus the exact maximum and sum.
#[derive(Clone)]
pub struct Histogram {
    hdr: hdrhistogram::Histogram<u64>,
    max: u64,
    sum: u128,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram {
            // Auto-resizing from 1 ns: any u64 is recorded (3 digits are always valid).
            hdr: hdrhistogram::Histogram::new(SIGNIFICANT_DIGITS)
                .expect("3 significant digits are within HdrHistogram's 0..=5"),
            max: 0,
            sum: 0,
        }
    }
}

impl Histogram {
    pub fn record(&mut self, d: Duration) {
        self.record_ns(d.as_nanos().min(u128::from(u64::MAX)) as u64);
    }

    pub fn record_ns(&mut self, ns: u64) {
        // An auto-resizing histogram grows to take the value; one it cannot grow to (past
        // centuries) is counted at its top instead of lost.
        if self.hdr.record(ns).is_err() {
            self.hdr.saturating_record(ns);
        }
        self.max = self.max.max(ns);
        self.sum += u128::from(ns);
    }

    pub fn count(&self) -> u64 {
        self.hdr.len()
    }

    pub fn max_ns(&self) -> u64 {
        self.max
    }

    pub fn mean_ns(&self) -> f64 {
        match self.count() {
            0 => 0.0,
            n => self.sum as f64 / n as f64,
        }
    }

    pub fn merge(&mut self, other: &Histogram) {
        // Both auto-resize, so adding never runs out of range.
        if let Err(e) = self.hdr.add(&other.hdr) {
            tracing::warn!(error = %e, "a latency histogram could not be merged");
            return;
        }
        self.max = self.max.max(other.max);
        self.sum += other.sum;
    }

    /// The value at quantile `q` (0..=1): at or above which lie at least `q` of the samples,
    /// within 0.1% above the true order statistic and never above the true maximum. 0 when
    /// empty. Monotone in `q`, so p50 ≤ p95 ≤ p99 ≤ max.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.count() == 0 {
            return 0;
        }
        // The top of the sample's bucket: never below the true value, as the old histogram.
        let at = self.hdr.value_at_quantile(q.clamp(0.0, 1.0));
        self.hdr.highest_equivalent(at).min(self.max)
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
    fn empty_and_single() {
        let mut h = Histogram::default();
        assert_eq!((h.quantile_ns(0.5), h.max_ns(), h.count()), (0, 0, 0));
        h.record(Duration::from_micros(1500));
        for q in [0.0, 0.5, 0.99, 1.0] {
            assert_eq!(h.quantile_ns(q), 1_500_000, "q={q}");
        }
        assert_eq!(h.max_ms(), 1.5);
        h.record_ns(u64::MAX);
        assert_eq!((h.count(), h.max_ns()), (2, u64::MAX));
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
            assert!(got >= want && got <= want * 1.001, "q={q}: {got} vs {want}");
        }
        assert_eq!(h.quantile_ns(1.0), 10_000_000);
        assert_eq!(h.max_ns(), 10_000_000);
        assert!((h.mean_ns() - 5_000_500.0).abs() < 1.0);
    }

    /// Ack latencies shaped like BENCHMARKS.md's load runs (most acks in a few ms, a tail from
    /// slow commits) read the same percentiles as from the hand-made histogram this one
    /// replaced (46af7bb: log-linear buckets, at most 1/64 above the true value; its figures
    /// below come from its bucket rule), within that histogram's precision.
    #[test]
    fn percentiles_agree_with_the_replaced_histogram() {
        // (µs, samples), and what the replaced histogram gave for p50/p95/p99/p99.9 (ms).
        let run: &[(u64, u64)] = &[
            (850, 4_000),
            (1_900, 52_000),
            (3_100, 31_000),
            (5_800, 9_500),
            (12_400, 2_700),
            (48_000, 700),
            (210_000, 90),
            (460_000, 10),
        ];
        let replaced_ms = [
            (0.5, 1.900_543),
            (0.95, 5.832_703),
            (0.99, 12.451_839),
            (0.999, 48.234_495),
        ];
        let mut h = Histogram::default();
        for &(us, n) in run {
            for _ in 0..n {
                h.record_ns(us * 1000);
            }
        }
        for (q, old) in replaced_ms {
            let new = h.quantile_ms(q);
            assert!(
                (new - old).abs() <= old / 64.0,
                "p{}: {new} ms now, {old} ms before",
                q * 100.0
            );
        }
        // And this one is the closer: within 0.1% of the true values.
        for (q, true_ms) in [(0.5, 1.9), (0.95, 5.8), (0.99, 12.4), (0.999, 48.0)] {
            let new = h.quantile_ms(q);
            assert!(
                new >= true_ms && new <= true_ms * 1.001,
                "p{}: {new}",
                q * 100.0
            );
        }
    }

    proptest! {
        /// Against the exact order statistic: never below it, at most 0.1% above, ordered, and
        /// merging two halves gives the histogram of the whole.
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
                prop_assert!(got as f64 <= exact as f64 * 1.001 + 1.0,
                    "q={} got {} exact {}", q, got, exact);
                prop_assert!(got >= last);
                last = got;
            }
            prop_assert_eq!(whole.max_ns(), *sorted.last().unwrap());
            prop_assert_eq!(whole.quantile_ns(1.0), whole.max_ns());
            prop_assert_eq!(a.count(), whole.count());
        }
    }
}
