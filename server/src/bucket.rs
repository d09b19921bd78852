//! Token buckets: how sessions say "too much, too fast" without timers.

use std::time::Instant;

/// A token bucket: `rate` units per second, refilled continuously, holding at most `burst`.
/// Sessions keep one per thing a client can ask too much of (ops, edit work, resumes).
pub struct Bucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    at: Instant,
}

impl Bucket {
    pub fn new(rate: f64, burst: f64) -> Bucket {
        Bucket {
            rate,
            burst,
            tokens: burst,
            at: Instant::now(),
        }
    }

    fn refill(&mut self) {
        let now = Instant::now();
        self.tokens =
            (self.tokens + now.duration_since(self.at).as_secs_f64() * self.rate).min(self.burst);
        self.at = now;
    }

    /// Whether the bucket holds `n` units now (nothing is taken).
    pub fn holds(&mut self, n: f64) -> bool {
        self.refill();
        self.tokens >= n
    }

    /// Takes `n` units if the bucket holds them.
    pub fn take(&mut self, n: f64) -> bool {
        self.refill();
        if self.tokens >= n {
            self.tokens -= n;
            true
        } else {
            false
        }
    }
}
