//! Token buckets: how sessions and scene owners say "too much, too fast" without timers.
//!
//! A bucket reads no clock of its own: [`Bucket::holds_at`] and [`Bucket::take_at`] take the
//! time, so the scene owner charges undo steps on its own clock (the simulation's, in tests)
//! with the very same arithmetic sessions use on the wall clock ([`Bucket::take`]).

use std::time::Instant;

/// A token bucket: `rate` units per second, refilled continuously, holding at most `burst`.
/// Sessions keep one per thing a client can ask too much of (ops, edit work, resumes); the
/// scene owner one per user for undo work.
#[derive(Debug, Clone)]
pub struct Bucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    at: Instant,
}

impl Bucket {
    /// A full bucket, its clock starting now.
    pub fn new(rate: f64, burst: f64) -> Bucket {
        Bucket::new_at(rate, burst, Instant::now())
    }

    /// A full bucket whose clock starts at `now`.
    pub fn new_at(rate: f64, burst: f64, now: Instant) -> Bucket {
        Bucket {
            rate,
            burst,
            tokens: burst,
            at: now,
        }
    }

    /// The most the bucket ever holds.
    pub fn burst(&self) -> f64 {
        self.burst
    }

    fn refill(&mut self, now: Instant) {
        // A clock read before the last one (another thread's, or a test's) adds nothing.
        let gained = now.saturating_duration_since(self.at).as_secs_f64() * self.rate;
        self.tokens = (self.tokens + gained).min(self.burst);
        self.at = self.at.max(now);
    }

    /// Whether the bucket holds `n` units now (nothing is taken).
    pub fn holds(&mut self, n: f64) -> bool {
        self.holds_at(n, Instant::now())
    }

    /// Whether the bucket holds `n` units at `now` (nothing is taken).
    pub fn holds_at(&mut self, n: f64, now: Instant) -> bool {
        self.refill(now);
        self.tokens >= n
    }

    /// Takes `n` units if the bucket holds them.
    pub fn take(&mut self, n: f64) -> bool {
        self.take_at(n, Instant::now())
    }

    /// Takes `n` units if the bucket holds them at `now`.
    pub fn take_at(&mut self, n: f64, now: Instant) -> bool {
        self.refill(now);
        if self.tokens >= n {
            self.tokens -= n;
            true
        } else {
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_bucket_refills_on_the_clock_it_is_given() {
        let t0 = Instant::now();
        let mut b = Bucket::new_at(10.0, 20.0, t0);
        assert!(b.take_at(20.0, t0));
        assert!(!b.take_at(1.0, t0), "empty at the same instant");
        assert!(
            !b.holds_at(6.0, t0 + Duration::from_millis(500)),
            "5 units after 0.5 s"
        );
        assert!(b.take_at(5.0, t0 + Duration::from_millis(500)));
        // Never more than the burst, however long it waits.
        assert!(!b.holds_at(20.5, t0 + Duration::from_secs(3600)));
        assert!(b.take_at(20.0, t0 + Duration::from_secs(3600)));
        // A clock that goes back neither adds nor rewinds.
        assert!(!b.holds_at(1.0, t0));
        assert!(!b.holds_at(1.0, t0 + Duration::from_secs(3600)));
        assert!(b.holds_at(1.0, t0 + Duration::from_millis(3_600_100)));
    }
}
