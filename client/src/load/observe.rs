//! Edit→visible latency: matching an editor's acknowledged edit with the moment *another*
//! client receives the delta that shows it.
//!
//! The editor learns an edit's server sequence only from its Ack, and the server queues the Ack
//! and the delta in the same turn on different sockets, so the observer may see the delta before
//! the editor sees the Ack, or after. Each observing client therefore keeps a short log of the
//! delta ranges it received (with arrival times) and a list of acknowledged edits it has not seen
//! yet; whichever of the two events comes second produces the sample.

use std::collections::VecDeque;
use std::time::Instant;

use super::histogram::Histogram;

/// How many received delta ranges an observer remembers for acks that arrive late. An ack is
/// queued in the same server turn as its delta, so it trails by a few deltas at most.
const RECENT_RANGES: usize = 4096;

/// What one client has seen, for the editors whose edits it observes.
#[derive(Default)]
pub struct ObserverLog {
    /// Delta ranges `(from, to]` in arrival order, with when the first frame of each arrived.
    recent: VecDeque<(u64, u64, Instant)>,
    /// Everything up to this sequence has reached this client (deltas or a sync).
    seen_to: u64,
    /// Acknowledged edits not yet seen here: (sequence, when the editor sent it).
    waiting: Vec<(u64, Instant)>,
    /// Edit→visible latencies of the edits this client observed.
    pub latency: Histogram,
    /// Acknowledged edits no delta will show: they changed no voxel (the server sends no delta
    /// for a turn that touched no brick), or reached this client inside a resync.
    pub unseen: u64,
}

impl ObserverLog {
    /// An editor's edit with server sequence `seq`, sent at `sent`, was acknowledged.
    pub fn acked(&mut self, seq: u64, sent: Instant) {
        if seq > self.seen_to {
            self.waiting.push((seq, sent));
            return;
        }
        // Already here: find the delta that carried it. Ranges arrive in order, so walk back
        // from the newest until they end below `seq`.
        let found = self
            .recent
            .iter()
            .rev()
            .take_while(|&&(_, to, _)| to >= seq)
            .find(|&&(from, to, _)| from < seq && seq <= to);
        match found {
            Some(&(_, _, at)) => self.latency.record(at.saturating_duration_since(sent)),
            None => self.unseen += 1,
        }
    }

    /// This client received a delta covering sequences `(from, to]` at `at`.
    pub fn delta(&mut self, from: u64, to: u64, at: Instant) {
        // A delta too large for one frame comes as several frames with the same range: the
        // first one marks the arrival.
        if self
            .recent
            .back()
            .is_some_and(|&(f, t, _)| (f, t) == (from, to))
        {
            return;
        }
        if self.recent.len() == RECENT_RANGES {
            self.recent.pop_front();
        }
        self.recent.push_back((from, to, at));
        self.seen_to = self.seen_to.max(to);
        let (latency, unseen) = (&mut self.latency, &mut self.unseen);
        self.waiting.retain(|&(seq, sent)| {
            if seq > to {
                return true;
            }
            if seq > from {
                latency.record(at.saturating_duration_since(sent));
            } else {
                *unseen += 1;
            }
            false
        });
    }

    /// This client finished a (re)sync at sequence `seq`: edits up to it arrived as sync
    /// batches, which say nothing about delta latency.
    pub fn synced(&mut self, seq: u64) {
        self.seen_to = self.seen_to.max(seq);
        let before = self.waiting.len();
        self.waiting.retain(|&(s, _)| s > seq);
        self.unseen += (before - self.waiting.len()) as u64;
    }

    /// Edits still waiting (for the end-of-run report: they were never seen).
    pub fn still_waiting(&self) -> usize {
        self.waiting.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn ack_before_or_after_the_delta_gives_the_same_sample() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        let mut early = ObserverLog::default();
        early.synced(10);
        early.acked(12, t0);
        early.delta(10, 13, ms(4));
        let mut late = ObserverLog::default();
        late.synced(10);
        late.delta(10, 13, ms(4));
        late.acked(12, t0);
        for log in [&early, &late] {
            assert_eq!(log.latency.count(), 1);
            assert_eq!(log.latency.max_ns(), 4_000_000);
            assert_eq!((log.unseen, log.still_waiting()), (0, 0));
        }
    }

    #[test]
    fn edits_no_delta_shows_are_counted_not_timed() {
        let t0 = Instant::now();
        let mut log = ObserverLog::default();
        log.synced(5);
        // Sequence 6 changed nothing: the next delta starts after it.
        log.acked(6, t0);
        log.delta(6, 8, t0 + Duration::from_millis(1));
        assert_eq!((log.latency.count(), log.unseen), (0, 1));
        // Late ack for a sequence in a gap between two ranges.
        log.delta(9, 10, t0 + Duration::from_millis(2));
        log.acked(9, t0);
        assert_eq!((log.latency.count(), log.unseen), (0, 2));
        log.acked(10, t0);
        log.acked(8, t0);
        assert_eq!(log.latency.count(), 2);
        // Split frames of one delta keep the first arrival.
        log.acked(12, t0);
        log.delta(10, 12, t0 + Duration::from_millis(3));
        log.delta(10, 12, t0 + Duration::from_millis(9));
        assert_eq!(log.latency.max_ns(), 3_000_000);
        // A resync swallows what was waiting.
        log.acked(20, t0);
        log.synced(25);
        assert_eq!((log.unseen, log.still_waiting()), (3, 0));
    }
}
