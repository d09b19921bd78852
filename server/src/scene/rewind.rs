//! Restoring a box to an earlier sequence (issue #34, `EditOp::Restore`): the owner's side.
//!
//! **Why the past is fetched before the owner sees the op:** rebuilding an earlier sequence
//! reads the store (a snapshot and up to a snapshot interval of log, `store::past`): seconds
//! for a large scene, which the owner thread must not spend while everyone's edits wait. The
//! session that receives the op rebuilds it off the owner (a blocking task), takes the box as a
//! [`PastBox`] of the bricks that differ between then and the scene as the store holds it now,
//! and leaves it here, keyed by scene, user and op, then sends the op on. What the box held at
//! sequence `to` never changes, so nothing is lost by fetching it early: the owner then writes
//! it in the scene's order, against the scene as it is in that turn, after checking that no
//! brick of the box it was not given changed since (else it refuses: restore again).
//!
//! **A restore is one logged step,** like a paste: the bricks it changes are written in one
//! turn, journaled, so its user can undo it (others' later changes win) and the log holds the
//! voxels it changed (`LogRecord::Rewind`): replay needs no past.
//!
//! Only a single node keeps the past (its redb store); a cluster's owner finds nothing here
//! and refuses, saying so.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use brickcast_protocol::rewind::PastBox;
use brickcast_protocol::wire::{EditOp, Rejection, UserId};

use super::SessionId;
use super::owner::{AckTo, Log, Owner, PendingAck, ack, refuse_one};
use crate::metrics::Metrics;
use crate::record::LogRecord;

/// Most bytes of the past one restore may bring (the bricks of its box that differ now from
/// then, as they were then): more is refused, saying to restore the box in parts. The owner
/// rewrites each in its turn (about as many bricks as a 256³ paste at most). The fetch stops
/// as soon as it passes this, so a huge difference costs no more memory than this.
pub const MAX_PAST_BYTES: usize = 64 << 20;

/// What a restore's box held then (or why it cannot be had), for the message `client_seq` of
/// a session, and the op it was fetched for.
type Prepared = (u64, EditOp, Result<Arc<PastBox>, String>);

/// Past boxes fetched by sessions for their restores, waiting for the scene's owner: at most
/// one per session (a session reads one message at a time, so a newer one replaces an older
/// one the owner never took), forgotten when the session ends.
#[derive(Debug, Default)]
pub struct Pasts {
    by: Mutex<HashMap<(String, SessionId), Prepared>>,
}

impl Pasts {
    fn held(&self) -> std::sync::MutexGuard<'_, HashMap<(String, SessionId), Prepared>> {
        self.by.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Leaves the past of message `client_seq` of `session` in `scene` (a restore, `op`), or
    /// why it cannot be had.
    pub fn put(
        &self,
        scene: &str,
        session: SessionId,
        client_seq: u64,
        op: EditOp,
        past: Result<PastBox, String>,
    ) {
        let past = past.map(Arc::new);
        self.held()
            .insert((scene.to_string(), session), (client_seq, op, past));
    }

    /// Forgets what `session` left in `scene` (it ended).
    pub fn forget(&self, scene: &str, session: SessionId) {
        self.held().remove(&(scene.to_string(), session));
    }

    /// Takes what was fetched for message `client_seq` (`op`) of `session` in `scene`: `None`
    /// when nothing was.
    fn take(
        &self,
        scene: &str,
        session: SessionId,
        client_seq: u64,
        op: &EditOp,
    ) -> Option<Result<Arc<PastBox>, String>> {
        let mut by = self.held();
        let key = (scene.to_string(), session);
        match by.get(&key) {
            Some((seq, asked, _)) if *seq == client_seq && asked == op => {
                by.remove(&key).map(|(_, _, past)| past)
            }
            _ => None,
        }
    }
}

impl Owner {
    /// A message of one `EditOp::Restore` from `user` (an editor): its past taken from what the
    /// session fetched, applied as one turn's brick writes, journaled as the user's step and
    /// logged as it.
    pub(super) fn apply_restore(
        &mut self,
        to_ack: AckTo,
        client_seq: u64,
        user: UserId,
        op: EditOp,
        log: &mut Log,
    ) -> PendingAck {
        let refuse =
            |metrics: &Metrics, reason: Rejection| refuse_one(metrics, to_ack, client_seq, reason);
        let EditOp::Restore { to, .. } = op else {
            return refuse(&self.metrics, Rejection::malformed("not a restore"));
        };
        if let Err(reason) = op.validate(self.map.size(), &self.config.limits) {
            return refuse(&self.metrics, reason);
        }
        let fetched = match to_ack {
            AckTo::Session(session) => self.config.pasts.take(&self.name, session, client_seq, &op),
            AckTo::Remote(_) => None,
        };
        let past = match fetched {
            Some(Ok(past)) => past,
            Some(Err(why)) => return refuse(&self.metrics, Rejection::malformed(why)),
            None => {
                return refuse(
                    &self.metrics,
                    Rejection::malformed(
                        "no past was fetched for this restore (a cluster keeps no history yet; on a single node, \
                         a later restore of yours took its place): restore again",
                    ),
                );
            }
        };
        if let Err(stale) = past.check(&self.map) {
            return refuse(&self.metrics, Rejection::malformed(stale.to_string()));
        }
        let bricks = past.restore(&self.map);
        let work = op.work(self.map.size());
        let seq = self.write_step(user, &bricks, work, log, |bricks, step| LogRecord::Rewind {
            user,
            to,
            bricks,
            step,
        });
        ack(to_ack, client_seq, Some(seq), 1, Vec::new())
    }
}
