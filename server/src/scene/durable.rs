//! Which of a scene's turns are durable, so the owner can go on with the next turn while one is
//! still being written (issue #31).
//!
//! **Why.** The rule is that nobody hears of an edit a crash could still lose: acks, deltas,
//! syncs and welcomes describe only what the log holds. The owner used to keep it by waiting
//! for each commit (an fsync) before queueing anything, so applying turn N+1 waited on the disk
//! for turn N. Now each turn the owner hands its log gets a **ticket** (1, 2, …), and every
//! frame the owner queues from then on is stamped with the latest ticket handed out
//! ([`Durability::stamp`]): whatever the frame says (an ack, a brick as the map holds it now)
//! is in that turn or an earlier one. A session's writer sends a stamped frame only once its
//! ticket is durable; until then it waits, and the frames behind it wait too, so a session's
//! frames keep their order. A log that commits before returning (a cluster's, the simulation's)
//! marks each ticket durable at once and nothing waits.
//!
//! If a commit fails, the tickets from it on never become durable: [`Durability::fail`] tells
//! the writers, which drop what waits for them (the scene stops and closes its sessions with a
//! frame that is not stamped).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use tokio::sync::watch;

/// A scene's tickets: handed out by its owner, made durable by its log.
#[derive(Debug)]
pub struct Durability {
    /// The last ticket handed out (0: none yet).
    handed: AtomicU64,
    /// The last ticket durable, for the writers to wait on.
    durable: watch::Sender<u64>,
    failed: AtomicBool,
}

impl Default for Durability {
    fn default() -> Self {
        Durability {
            handed: AtomicU64::new(0),
            durable: watch::Sender::new(0),
            failed: AtomicBool::new(false),
        }
    }
}

impl Durability {
    /// The next ticket, for a turn about to be handed to the log.
    pub fn next(&self) -> u64 {
        self.handed.fetch_add(1, Ordering::SeqCst) + 1
    }

    /// What a frame queued now is stamped with: the last ticket handed out.
    pub fn stamp(&self) -> u64 {
        self.handed.load(Ordering::SeqCst)
    }

    /// Every ticket up to `ticket` is durable.
    pub fn durable_to(&self, ticket: u64) {
        self.durable.send_if_modified(|d| {
            let moved = ticket > *d;
            *d = (*d).max(ticket);
            moved
        });
    }

    /// The last durable ticket.
    pub fn durable(&self) -> u64 {
        *self.durable.borrow()
    }

    /// Whether every ticket handed out is durable.
    pub fn settled(&self) -> bool {
        self.durable() >= self.stamp()
    }

    /// A commit failed: tickets not yet durable never will be.
    pub fn fail(&self) {
        self.failed.store(true, Ordering::SeqCst);
        self.durable.send_modify(|_| {});
    }

    pub fn has_failed(&self) -> bool {
        self.failed.load(Ordering::SeqCst)
    }

    /// Whether a frame stamped `ticket` may go: `Some(true)` now, `Some(false)` never (its
    /// commit failed), `None` not yet.
    pub fn may_send(&self, ticket: u64) -> Option<bool> {
        if ticket <= self.durable() {
            Some(true)
        } else if self.has_failed() {
            Some(false)
        } else {
            None
        }
    }

    /// Waits until a frame stamped `ticket` may go (true) or never will (false).
    pub async fn wait(&self, ticket: u64) -> bool {
        let mut rx = self.durable.subscribe();
        loop {
            if let Some(answer) = self.may_send(ticket) {
                return answer;
            }
            if rx.changed().await.is_err() {
                return false;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_ticket_waits_for_its_commit_and_a_failed_one_never_goes() {
        let d = std::sync::Arc::new(Durability::default());
        assert_eq!(
            d.may_send(0),
            Some(true),
            "nothing handed out: nothing to wait for"
        );
        let (one, two) = (d.next(), d.next());
        assert_eq!((one, two, d.stamp()), (1, 2, 2));
        assert_eq!(d.may_send(one), None);
        let waiting = tokio::spawn({
            let d = d.clone();
            async move { d.wait(two).await }
        });
        d.durable_to(one);
        assert_eq!(d.may_send(one), Some(true));
        assert!(!d.settled());
        d.durable_to(two);
        assert!(waiting.await.unwrap());
        assert!(d.settled());
        d.durable_to(one);
        assert_eq!(d.durable(), two, "never goes back");
        let three = d.next();
        let waiting = tokio::spawn({
            let d = d.clone();
            async move { d.wait(three).await }
        });
        d.fail();
        assert!(!waiting.await.unwrap());
        assert_eq!(d.may_send(two), Some(true), "what was durable still goes");
    }
}
