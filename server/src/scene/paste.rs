//! Copy and paste on the server (issue #34): each user's clipboard, kept by the node for every
//! scene it serves, and the owner's side of `EditOp::Copy` and `EditOp::Paste`.
//!
//! **Why the server holds clipboards:** a copy is taken in the scene's one order (what it
//! copies is what everyone's edits made it up to then, whatever a client's copy shows), a
//! paste never sends the voxels over the network twice, and a clipboard copied in one scene
//! pastes into any other scene of the node. A clipboard lives in memory only (a restart
//! forgets it, as a desktop's does); the node holds at most [`MAX_CLIPBOARD_BYTES`] of them,
//! forgetting the least recently used user's first, so made-up user ids cannot fill memory.
//! In a cluster a clipboard is on the node that owns the scene copied from; a paste into a
//! scene another node owns finds none (said so in its refusal).
//!
//! **A paste is one logged step:** the owner writes the bricks the clipboard changes
//! ([`Clipboard::paste`]) in one turn, journaled like any edit, so the step its user can undo
//! is the voxels it changed (others' later changes win, as for any undo), and the log holds
//! exactly that step (`LogRecord::Paste`, replayed by setting each voxel to its after-value):
//! replay needs no clipboard.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use brickcast_protocol::brick::BrickData;
use brickcast_protocol::clipboard::Clipboard;
use brickcast_protocol::wire::{EditOp, Rejection, UserId};

use super::owner::{AckTo, Log, Owner, PendingAck, ack, refuse_one};
use super::step::Step;
use crate::metrics::Metrics;
use crate::record::LogRecord;

/// Most bytes of clipboards one node keeps (a 256³ box of solid voxels is 128 MiB).
pub const MAX_CLIPBOARD_BYTES: usize = 512 << 20;

/// The clipboards of a node's users, shared by every scene owner of the node.
#[derive(Debug)]
pub struct Clipboards {
    inner: Mutex<Held>,
    /// Most bytes held ([`MAX_CLIPBOARD_BYTES`]).
    cap: usize,
}

impl Default for Clipboards {
    fn default() -> Self {
        Clipboards::with_cap(MAX_CLIPBOARD_BYTES)
    }
}

#[derive(Debug, Default)]
struct Held {
    /// User → clipboard and when it was last used.
    by_user: HashMap<UserId, (Arc<Clipboard>, u64)>,
    bytes: usize,
    clock: u64,
}

impl Clipboards {
    /// Clipboards holding at most `cap` bytes.
    pub fn with_cap(cap: usize) -> Clipboards {
        Clipboards {
            inner: Mutex::default(),
            cap,
        }
    }

    fn held(&self) -> std::sync::MutexGuard<'_, Held> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Puts `clipboard` as `user`'s, forgetting others' (least recently used first) to stay
    /// within the cap.
    pub fn put(&self, user: UserId, clipboard: Clipboard) {
        let mut held = self.held();
        held.clock += 1;
        let stamp = held.clock;
        let bytes = clipboard.bytes();
        if let Some((old, _)) = held.by_user.insert(user, (Arc::new(clipboard), stamp)) {
            held.bytes -= old.bytes();
        }
        held.bytes += bytes;
        while held.bytes > self.cap {
            let Some((&oldest, _)) = held
                .by_user
                .iter()
                .filter(|(u, _)| **u != user)
                .min_by_key(|(_, (_, used))| *used)
            else {
                break;
            };
            if let Some((gone, _)) = held.by_user.remove(&oldest) {
                held.bytes -= gone.bytes();
            }
        }
    }

    /// `user`'s clipboard, if any.
    pub fn get(&self, user: UserId) -> Option<Arc<Clipboard>> {
        let mut held = self.held();
        held.clock += 1;
        let stamp = held.clock;
        let (clipboard, used) = held.by_user.get_mut(&user)?;
        *used = stamp;
        Some(clipboard.clone())
    }

    /// Bytes held, over every user.
    pub fn bytes(&self) -> usize {
        self.held().bytes
    }
}

impl Owner {
    /// An applied `EditOp::Copy`: `user`'s clipboard becomes the box as the map holds it now.
    pub(super) fn copy_to_clipboard(&self, user: UserId, min: [u32; 3], max: [u32; 3]) {
        let clipboard = Clipboard::copy(&self.map, min, max);
        self.config.clipboards.put(user, clipboard);
    }

    /// A message of one `EditOp::Paste` from `user` (an editor): checked, applied as one turn's
    /// brick writes, journaled as the user's step and logged as it.
    pub(super) fn apply_paste(
        &mut self,
        to: AckTo,
        client_seq: u64,
        user: UserId,
        op: EditOp,
        log: &mut Log,
    ) -> PendingAck {
        let refuse =
            |metrics: &Metrics, reason: Rejection| refuse_one(metrics, to, client_seq, reason);
        let EditOp::Paste {
            at,
            size,
            turns,
            mirror,
        } = op
        else {
            return refuse(&self.metrics, Rejection::malformed("not a paste"));
        };
        if let Err(reason) = op.validate(self.map.size(), &self.config.limits) {
            return refuse(&self.metrics, reason);
        }
        let Some(clipboard) = self.config.clipboards.get(user) else {
            return refuse(
                &self.metrics,
                Rejection::malformed(
                    "nothing copied to paste (on this server: a clipboard stays on the node that copied it)",
                ),
            );
        };
        let turned = clipboard.turned_size(turns);
        if turned != size {
            return refuse(
                &self.metrics,
                Rejection::malformed(format!(
                    "the clipboard holds a {turned:?} box, not {size:?}"
                )),
            );
        }
        let bricks = clipboard.paste(&self.map, at, turns, mirror);
        let work = op.work(self.map.size());
        let seq = self.write_step(user, &bricks, work, log, |bricks, step| LogRecord::Paste {
            user,
            bricks,
            step,
        });
        ack(to, client_seq, Some(seq), 1, Vec::new())
    }

    /// Writes whole bricks (made from the map's own and a paste's or a past's voxels, inside
    /// the scene; one with no voxel left is removed) as one turn's message of `user`: the
    /// sequence it takes, journaled as the user's step, logged as `record(bricks, step)`.
    pub(super) fn write_step(
        &mut self,
        user: UserId,
        bricks: &[BrickData],
        work: u64,
        log: &mut Log,
        record: impl FnOnce(u32, Vec<u8>) -> LogRecord,
    ) -> u64 {
        let seq = self.seq + 1;
        self.map.begin_journal();
        self.map.set_sequence(seq);
        for brick in bricks {
            if brick.colours.is_empty() {
                self.map.remove_brick(brick.cell);
            } else if let Err(e) = self.map.put_brick(brick) {
                tracing::error!(scene = %self.name, error = %e, cell = ?brick.cell, "a written brick does not fit");
            }
        }
        let step = Step::from_journal(&mut self.map);
        let voxels = step.voxel_count();
        self.history.record_edit(user, &step);
        self.seq = seq;
        self.log_ops += 1;
        self.log_work = self.log_work.saturating_add(work);
        Metrics::add(&self.metrics.ops_applied, 1);
        Metrics::add(&self.metrics.voxels_changed, voxels);
        Metrics::add(&self.metrics.edit_batches, 1);
        log.push((seq, record(step.bricks.len() as u32, step.encode())));
        seq
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::{BrickMap, BrushMode, Colour};

    #[test]
    fn clipboards_stay_within_their_bound_forgetting_the_least_recently_used() {
        let mut map = BrickMap::new([16, 16, 16]).unwrap();
        map.fill_box([0, 0, 0], [15, 15, 15], BrushMode::Fill, Colour::WHITE);
        let whole = || Clipboard::copy(&map, [0, 0, 0], [15, 15, 15]);
        // Room for four: a fifth pushes the least recently used out.
        let clipboards = Clipboards::with_cap(4 * whole().bytes());
        for user in 1..=4 {
            clipboards.put(user, whole());
        }
        assert!(clipboards.get(1).is_some(), "user 1 used last now");
        clipboards.put(5, whole());
        assert!(clipboards.bytes() <= 4 * whole().bytes());
        assert!(clipboards.get(2).is_none(), "the least recently used went");
        for user in [1, 3, 4, 5] {
            assert!(clipboards.get(user).is_some(), "{user}");
        }
        // Replacing one's own clipboard counts its bytes once.
        let before = clipboards.bytes();
        clipboards.put(5, whole());
        assert_eq!(clipboards.bytes(), before);
    }
}
