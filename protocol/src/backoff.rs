//! Waits between retries: doubling from a first wait to a longest, each wait drawn between
//! half and all of its window ("equal jitter"). Every loop in brickcast that tries something
//! again after a failure waits by this one rule: viewers reconnecting to a server, sessions
//! forwarding edits through a failover, owners appending to or reloading a cluster log.
//!
//! Without the draw, everyone who lost a server at one moment (a restart, a failover) came back
//! at the same moments, all at once each time; with it they spread over the second half of each
//! window. The draw is the caller's (`unit`, uniform in 0..1): `rand` in the native viewer,
//! `Math.random` in a browser, [`spread`] where a run must replay exactly (the server's loops
//! under the cluster simulation), a fixed sequence in tests.

use std::time::Duration;

/// Where a retry loop is in its waits.
#[derive(Clone, Debug, PartialEq)]
pub struct Backoff {
    first: Duration,
    longest: Duration,
    window: Duration,
}

impl Backoff {
    /// Waits from `first` (drawn within `first/2..=first`) doubling up to `longest`.
    pub const fn new(first: Duration, longest: Duration) -> Backoff {
        Backoff {
            first,
            longest,
            window: first,
        }
    }

    /// It worked: the next failure waits from the first window again.
    pub fn reset(&mut self) {
        self.window = self.first;
    }

    /// The next wait, for a draw `unit` in 0..1 (clamped; NaN counts as 0), and the window
    /// doubles for the one after.
    pub fn next_wait(&mut self, unit: f64) -> Duration {
        let window = self.window;
        self.window = window.saturating_mul(2).min(self.longest);
        let half = window / 2;
        let unit = if unit.is_nan() {
            0.0
        } else {
            unit.clamp(0.0, 1.0)
        };
        half + half.mul_f64(unit)
    }
}

/// A draw in 0..1 that depends only on `key` and `attempt`: the same pair always gives the same
/// draw (a simulation replays), different keys (nodes, sessions) spread over the window.
pub fn spread(key: u64, attempt: u64) -> f64 {
    // SplitMix64's finaliser over the two words: every input bit moves every output bit.
    let mut z = key ^ attempt.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// A stable 64-bit key for a name (FNV-1a): the same on every platform and every build, unlike
/// the standard library's hasher, so [`spread`] over it replays.
pub fn key_of(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const START: Duration = Duration::from_millis(250);
    const MAX: Duration = Duration::from_secs(5);

    #[test]
    fn waits_double_to_the_cap_and_spread_over_each_windows_second_half() {
        let mut b = Backoff::new(START, MAX);
        let lows: Vec<u128> = (0..7).map(|_| b.next_wait(0.0).as_millis()).collect();
        assert_eq!(lows, [125, 250, 500, 1000, 2000, 2500, 2500]);
        let mut b = Backoff::new(START, MAX);
        let highs: Vec<u128> = (0..7).map(|_| b.next_wait(1.0).as_millis()).collect();
        assert_eq!(highs, [250, 500, 1000, 2000, 4000, 5000, 5000]);
        b.reset();
        assert_eq!(b.next_wait(0.5), Duration::from_micros(187_500));
        assert_eq!(b.next_wait(f64::NAN), Duration::from_millis(250));
        // A hundred clients that lost the server together: their first retries spread over
        // 125..250 ms, none closer to another than the draws are.
        let mut first: Vec<Duration> = (0..100)
            .map(|i| Backoff::new(START, MAX).next_wait(f64::from(i) / 100.0))
            .collect();
        first.sort();
        assert_eq!(first[0], Duration::from_millis(125));
        assert!(first[99] >= Duration::from_micros(248_000));
        assert!(first.windows(2).all(|w| w[1] > w[0]));
    }

    #[test]
    fn spread_replays_and_spreads_names_over_the_unit_interval() {
        assert_eq!(spread(key_of("node-a"), 3), spread(key_of("node-a"), 3));
        assert_ne!(spread(key_of("node-a"), 3), spread(key_of("node-b"), 3));
        assert_ne!(spread(key_of("node-a"), 3), spread(key_of("node-a"), 4));
        // Fixed values: a change of the rule would change every simulated history.
        assert_eq!(key_of(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(key_of("a"), 0xaf63_dc4c_8601_ec8c);
        // 1,000 sessions' first draws fill each tenth of 0..1 roughly evenly.
        let mut tenths = [0u32; 10];
        for i in 0..1000u64 {
            let u = spread(key_of(&format!("session-{i}")), 0);
            assert!((0.0..1.0).contains(&u));
            tenths[(u * 10.0) as usize] += 1;
        }
        assert!(
            tenths.iter().all(|&n| (60..=140).contains(&n)),
            "{tenths:?}"
        );
    }
}
