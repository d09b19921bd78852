//! How long a viewer waits before reconnecting: doubling from [`START`] to [`MAX`], and each
//! wait drawn between half and all of that ("equal jitter"). Without the draw every client
//! that lost a server at one moment (a restart) came back at the same moments, all of them at
//! once each time; with it they come back spread over the second half of each window.
//!
//! The draw is the caller's (`unit`, uniform in 0..1): `rand` natively, `Math.random` in a
//! browser, a fixed sequence in tests. The native viewer and the page share this one rule.

use std::time::Duration;

/// First wait before reconnecting after a lost connection.
pub const START: Duration = Duration::from_millis(250);
/// Longest wait.
pub const MAX: Duration = Duration::from_secs(5);

/// Where a client is in its waits.
#[derive(Clone, Debug, PartialEq)]
pub struct Backoff {
    window: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff { window: START }
    }
}

impl Backoff {
    /// A connection was welcomed: the next loss waits from [`START`] again.
    pub fn reset(&mut self) {
        self.window = START;
    }

    /// The next wait, for a draw `unit` in 0..1 (clamped), and the window doubles for the one
    /// after.
    pub fn next_wait(&mut self, unit: f64) -> Duration {
        let window = self.window;
        self.window = (window * 2).min(MAX);
        let half = window / 2;
        half + half.mul_f64(unit.clamp(0.0, 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn waits_double_to_the_cap_and_spread_over_each_windows_second_half() {
        let mut b = Backoff::default();
        let lows: Vec<u128> = (0..7).map(|_| b.next_wait(0.0).as_millis()).collect();
        assert_eq!(lows, [125, 250, 500, 1000, 2000, 2500, 2500]);
        let mut b = Backoff::default();
        let highs: Vec<u128> = (0..7).map(|_| b.next_wait(1.0).as_millis()).collect();
        assert_eq!(highs, [250, 500, 1000, 2000, 4000, 5000, 5000]);
        b.reset();
        assert_eq!(b.next_wait(0.5), Duration::from_micros(187_500));
        // A hundred clients that lost the server together: their first retries spread over
        // 125..250 ms, none closer to another than the draws are.
        let mut first: Vec<Duration> = (0..100)
            .map(|i| Backoff::default().next_wait(f64::from(i) / 100.0))
            .collect();
        first.sort();
        assert_eq!(first[0], Duration::from_millis(125));
        assert!(first[99] >= Duration::from_micros(248_000));
        assert!(first.windows(2).all(|w| w[1] > w[0]));
    }
}
