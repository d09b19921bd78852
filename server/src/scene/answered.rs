//! Which forwarded requests the scene has answered, so a retried request is applied once.
//!
//! **Why:** a node forwarding an edit cannot always learn whether it applied: the owner may
//! die (or lose its lease) after logging the turn and before the reply arrives. Each request
//! carries its origin (forwarding process and session) and a number that grows per origin;
//! the owner logs, with each turn, the replies it gave to the requests in it, and every replica
//! keeps the latest answered number and replies per origin (from the log, and in snapshots).
//! A retry of an answered request, on any owner, gets the recorded replies instead of being
//! applied again. So a forwarding session may retry anything (a timeout, an owner that
//! vanished) without ever applying an edit twice.

use std::collections::{HashMap, VecDeque};

/// Origins remembered at most (oldest forgotten first): far more sessions than one scene sees
/// at once, each entry a few dozen bytes.
const MAX_ORIGINS: usize = 65_536;

/// The encoded replies to one request's items.
pub type Replies = Vec<Vec<u8>>;

/// What a request's origin, number and replies look like in turns and snapshots.
pub type AnsweredEntry = (String, u64, Replies);

/// Where a request stands.
#[derive(Debug, PartialEq)]
pub enum Lookup {
    /// Not seen: apply it.
    New,
    /// Applied in this turn, not logged yet: commit first, then look again.
    Pending,
    /// Answered: these are its replies.
    Done(Replies),
    /// Older than the origin's latest: a copy nobody waits for any more.
    Stale,
}

#[derive(Default)]
pub struct Answered {
    /// Origin → (latest number, its replies; `None` while its turn is not logged).
    latest: HashMap<String, (u64, Option<Replies>)>,
    order: VecDeque<String>,
}

impl Answered {
    pub fn from_entries(entries: Vec<AnsweredEntry>) -> Answered {
        let mut a = Answered::default();
        for (origin, number, replies) in entries {
            a.record(origin, number, replies);
        }
        a
    }

    pub fn lookup(&self, origin: &str, number: u64) -> Lookup {
        match self.latest.get(origin) {
            None => Lookup::New,
            Some((n, _)) if number > *n => Lookup::New,
            Some((n, _)) if number < *n => Lookup::Stale,
            Some((_, None)) => Lookup::Pending,
            Some((_, Some(replies))) => Lookup::Done(replies.clone()),
        }
    }

    /// The request is being applied in the current turn.
    pub fn begin(&mut self, origin: &str, number: u64) {
        self.insert(origin.to_string(), number, None);
    }

    /// A request answered (by this owner after its turn, or by another one, from the log).
    pub fn record(&mut self, origin: String, number: u64, replies: Replies) {
        match self.latest.get(&origin) {
            Some((n, _)) if *n > number => {}
            _ => self.insert(origin, number, Some(replies)),
        }
    }

    fn insert(&mut self, origin: String, number: u64, replies: Option<Replies>) {
        if self
            .latest
            .insert(origin.clone(), (number, replies))
            .is_none()
        {
            self.order.push_back(origin);
            while self.order.len() > MAX_ORIGINS {
                if let Some(old) = self.order.pop_front() {
                    self.latest.remove(&old);
                }
            }
        }
    }

    /// Every answered request (for a snapshot).
    pub fn entries(&self) -> Vec<AnsweredEntry> {
        self.order
            .iter()
            .filter_map(|o| match self.latest.get(o) {
                Some((n, Some(r))) => Some((o.clone(), *n, r.clone())),
                _ => None,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_retried_request_gets_its_recorded_replies() {
        let mut a = Answered::default();
        assert_eq!(a.lookup("n/1", 1), Lookup::New);
        a.begin("n/1", 1);
        assert_eq!(a.lookup("n/1", 1), Lookup::Pending);
        a.record("n/1".into(), 1, vec![vec![7]]);
        assert_eq!(a.lookup("n/1", 1), Lookup::Done(vec![vec![7]]));
        assert_eq!(a.lookup("n/1", 2), Lookup::New);
        a.record("n/1".into(), 2, vec![]);
        assert_eq!(a.lookup("n/1", 1), Lookup::Stale);
        // An older record never replaces a newer one.
        a.record("n/1".into(), 1, vec![vec![9]]);
        assert_eq!(a.lookup("n/1", 2), Lookup::Done(vec![]));
        let b = Answered::from_entries(a.entries());
        assert_eq!(b.lookup("n/1", 2), Lookup::Done(vec![]));
        assert_eq!(b.lookup("n/2", 1), Lookup::New);
    }
}
