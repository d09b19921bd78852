//! Getting a client's copy up to date: initial sync, resume, and resync after a client fell
//! behind, all streamed nearest-brick-first a few frames per turn so edits keep flowing while a
//! large scene goes out. Part of the owner (these are `impl Owner` methods), kept apart from
//! the edit path in `owner.rs`.

use brickcast_protocol::brick::popcount;
use brickcast_protocol::wire::{
    BlobEncoder, BrickBlob, MAX_REMOVED_PER_FRAME, PROTOCOL_VERSION, Role, ServerMsg, WireError,
    encode_server,
};
use brickcast_protocol::{BrickMap, Colour, palette};
use bytes::Bytes;

use super::owner::{Owner, ZSTD_LEVEL};
use super::{Outbox, SessionId, Subscriber};
use crate::metrics::Metrics;

/// Sync frames queued per subscriber per turn.
const FRAMES_PER_TURN: usize = 4;
/// How long one turn streams syncs and working sets before it lets the next turn take the
/// commands waiting (edits among them); the sessions not reached go first next turn.
const PUMP_TIME: std::time::Duration = std::time::Duration::from_millis(4);

/// A sync (initial, resume, resync) is queued at most this far ahead of its session's writer:
/// the next frames are encoded when the writer takes what was queued (it wakes the owner), not
/// all at once. A client that says Hello and never reads then holds about this much of its
/// sync in the server (plus what its writer and socket hold), not its whole scene: a thousand
/// of them held 0.7 MB each of the demo's 1.1 MB sync (BENCHMARKS.md, "Fair share").
pub(super) const SYNC_AHEAD: usize = 64 << 10;

/// Bytes one sync batch aims at: its bricks are this over the bytes a brick took in the
/// scene's last batch (Sibenik ~60 B, the demo's terrain ~110 B: 1,100 and 600 bricks).
/// Frames of fewer bricks compress worse (Sibenik's sync: +3.7% bytes at 1,024 bricks a frame,
/// +14% at 256, against 4,096), larger ones sit whole in a client that does not read.
pub(super) const SYNC_BATCH_BYTES: usize = 64 << 10;

/// Bricks in one sync batch, at least (noise, 1 KiB a brick: 256 KiB).
pub(super) const SYNC_BATCH_MIN_BRICKS: usize = 256;

/// What a joining session asks for: to resume from a sequence, a level of detail, a working
/// set within a GPU budget (`Command::Join`).
pub(super) struct Wants {
    pub(super) resume_from: Option<u64>,
    pub(super) level: u32,
    pub(super) budget: Option<brickcast_protocol::wire::Budget>,
}

impl Owner {
    /// Subscribes a session: queues its Welcome and starts its sync. False when the session
    /// could not be welcomed (it is gone, or the Welcome could not be encoded).
    pub(super) fn join(
        &mut self,
        session: SessionId,
        out: Outbox,
        role: Role,
        wants: Wants,
        who: super::Joiner,
    ) -> bool {
        let Wants {
            resume_from,
            level,
            budget,
        } = wants;
        if level > brickcast_protocol::lod::level_count(self.map.size()) {
            // The session checked the level against the scene's size before it joined.
            out.close(
                brickcast_protocol::wire::ErrorCode::UnknownScene,
                format!("the scene has no level of detail {level}"),
            );
            return false;
        }
        // A budget the whole view fits with room to grow is served the whole view: a working
        // set is for what does not fit (every viewer states a budget by default).
        let budget = budget.filter(|b| !super::follow::fits_whole(&self.map, level, b.bytes));
        if level > 0 && budget.is_some() {
            out.close(
                brickcast_protocol::wire::ErrorCode::NotAllowed,
                "a working set (a GPU budget) is served at the scene's own level only, not at a level of detail",
            );
            return false;
        }
        if (level > 0 || budget.is_some())
            && let Err(e) = self.levels.start(&self.map, self.seq)
        {
            tracing::error!(scene = %self.name, error = %e, "could not build the levels of detail");
            out.close(
                brickcast_protocol::wire::ErrorCode::Internal,
                format!("the server could not build the scene's levels of detail: {e}"),
            );
            return false;
        }
        // While the levels are being built the session is welcomed now and synced later.
        let view = self.levels.map_at(&self.map, level);
        let size = brickcast_protocol::lod::level_size(self.map.size(), level);
        // No eye in the Hello. A working set starts at the eye of a viewer's first camera
        // (`Camera::overview`, the client core's `FirstView`; the page places its camera only
        // once the Welcome names the size), so that camera's first report is no jump that
        // starts the working set over. A whole scene streams from above its centre.
        let camera = match budget {
            Some(b) => b
                .eye
                .unwrap_or(brickcast_protocol::Camera::overview(size).eye),
            None => [size[0] as f32 * 0.5, size[1] as f32, size[2] as f32 * 0.5],
        };
        out.wake_owner_with(self.wake.clone());
        out.gate_with(self.durability.clone());
        out.set_following(budget.is_some());
        let mut sub = Subscriber {
            out,
            role,
            user: who.peer.user,
            stable: who.stable,
            camera,
            level,
            awaits_levels: None,
            delivered: self.seq,
            lagging: false,
            pending: Vec::new(),
            sync_total: 0,
            sync_sent: 0,
            syncing: false,
            follow: budget.map(|b| super::follow::Follow::new(b.bytes)),
        };
        // A resume is served as a resync from the client's sequence; anything else (or a
        // sequence from the future, i.e. another store) is a full sync.
        let (total, resume, everything) = match view {
            // A working set is counted in its `Follow`'s plan.
            _ if budget.is_some() => (0, None, None),
            None => (0, None, None),
            Some(map) => {
                let (total, resume) = match resume_from {
                    Some(since) if since <= self.seq => match map.changes_since(since) {
                        Some(c) => (c.changed.len() as u32, Some(since)),
                        None => (map.brick_count() as u32, None),
                    },
                    _ => (map.brick_count() as u32, None),
                };
                let everything = resume.is_none().then(|| all_cells(map, camera));
                (total, resume, everything)
            }
        };
        let welcome = ServerMsg::Welcome {
            protocol: PROTOCOL_VERSION,
            server: format!("brickcast-server {}", env!("CARGO_PKG_VERSION")),
            scene: self.name.clone(),
            size,
            seq: self.seq,
            role,
            limits: self.config.limits.clone(),
            total_bricks: total,
            you: who.peer,
            peers: who.roster,
        };
        let palette = ServerMsg::Palette {
            swatches: *self.map.swatches(),
        };
        if !sub.out.send(&welcome, &self.metrics) || !sub.out.send(&palette, &self.metrics) {
            return false;
        }
        if sub.follow.is_some() {
            // A client that resumed holds a copy of its own: it drops it.
            if self.levels.ready() {
                self.start_follow(&mut sub, resume_from.is_some());
            } else {
                sub.awaits_levels = Some(resume_from.is_some());
                sub.syncing = true;
                sub.out.set_syncing(true);
            }
            self.subs.insert(session, sub);
            return true;
        }
        match resume {
            _ if everything.is_none() && resume.is_none() => {
                sub.awaits_levels = Some(resume_from.is_some());
                sub.syncing = true;
                sub.out.set_syncing(true);
            }
            Some(since) => {
                sub.delivered = since;
                self.start_resync(&mut sub, false);
            }
            None => {
                // A client that asked to resume holds a copy we cannot patch: tell it to drop it.
                if resume_from.is_some() {
                    sub.out.send(&ServerMsg::Resync { since: 0 }, &self.metrics);
                }
                sub.pending = everything.unwrap_or_default();
                sub.sync_total = sub.pending.len() as u32;
                sub.syncing = true;
                sub.out.set_syncing(true);
            }
        }
        self.subs.insert(session, sub);
        true
    }

    /// A client's camera moved: its pending sync is re-sorted nearest-first from there.
    pub(super) fn camera(&mut self, session: SessionId, eye: [f32; 3]) {
        let following = self.subs.get(&session).is_some_and(|s| s.follow.is_some());
        if following && let Some(mut sub) = self.subs.remove(&session) {
            sub.camera = eye;
            self.follow_camera(&mut sub);
            self.subs.insert(session, sub);
        } else if let Some(sub) = self.subs.get_mut(&session) {
            sub.camera = eye;
            // A session waiting for its level has nothing pending to sort.
            if let Some(map) = self.levels.map_at(&self.map, sub.level) {
                sort_far_to_near(map, &mut sub.pending, eye);
            }
        }
    }

    /// Queues what a client that has everything up to `sub.delivered` is missing: removals now,
    /// changed bricks through the sync pump; `announce` tells the client first with
    /// `Resync { since: delivered }`.
    ///
    /// `Resync { since: 0 }` means "drop your copy", so a client told that must be sent every
    /// brick: when tombstones that old are gone, and when an announced resync starts from 0
    /// (a client that fell behind during its first sync of a scene still at sequence 0, or that
    /// asked to resume from 0), where "changed after 0" would miss every brick the scene was
    /// created with.
    pub(super) fn start_resync(&self, sub: &mut Subscriber, announce: bool) {
        if sub.follow.is_some() {
            // A working set starts again from the camera: cheaper to reason about than a
            // resume, and what it holds is small.
            self.start_follow(sub, true);
            return;
        }
        // A level being built again: the session waits for it, then drops its copy.
        let Some(map) = self.levels.map_at(&self.map, sub.level) else {
            sub.awaits_levels = Some(true);
            sub.pending.clear();
            sub.lagging = false;
            return;
        };
        let changes = if announce && sub.delivered == 0 {
            None
        } else {
            map.changes_since(sub.delivered)
        };
        let full = changes.is_none();
        let (since, changes) = match changes {
            Some(c) => (sub.delivered, c),
            None => (
                0,
                brickcast_protocol::map::Changes {
                    changed: map.brick_cells().map(|(c, _)| c).collect(),
                    removed: Vec::new(),
                },
            ),
        };
        // A client that gets every brick must drop its copy first (bricks removed since it
        // last heard are not listed): say so. (A resume from 0 that tombstones still cover
        // keeps the copy the client has at 0 and gets what changed since.)
        if announce || full {
            sub.out.send(&ServerMsg::Resync { since }, &self.metrics);
        }
        for chunk in changes.removed.chunks(MAX_REMOVED_PER_FRAME) {
            let msg = ServerMsg::Delta {
                from_seq: since,
                to_seq: self.seq,
                bricks: BrickBlob::empty(),
                removed: chunk.to_vec(),
            };
            sub.out.send(&msg, &self.metrics);
        }
        // Keep what an interrupted sync had not sent yet: those bricks are still owed.
        let mut pending = std::mem::take(&mut sub.pending);
        pending.extend(changes.changed.iter().map(|&c| map.cell_index(c)));
        pending.sort_unstable();
        pending.dedup();
        sort_far_to_near(map, &mut pending, sub.camera);
        sub.begin_sync(pending, self.seq);
    }

    /// Starts the sync of a session that waited for the levels of detail to be built: every
    /// brick of its level, nearest first, after `Resync { since: 0 }` if it holds a copy.
    pub(super) fn start_level_sync(&self, sub: &mut Subscriber) {
        let drop_copy = sub.awaits_levels.take().unwrap_or(false);
        if sub.follow.is_some() {
            self.start_follow(sub, drop_copy);
            return;
        }
        let Some(map) = self.levels.map_at(&self.map, sub.level) else {
            return;
        };
        if drop_copy {
            sub.out.send(&ServerMsg::Resync { since: 0 }, &self.metrics);
        }
        sub.begin_sync(all_cells(map, sub.camera), self.seq);
    }

    /// Encodes the current state of `cells` as frames: bricks that exist go in blobs cut to
    /// fit the frame limit, empty cells are listed as removed. `make` builds the message around
    /// each blob. Many cells (a heavy edit's or an undo's last turn: 65,536 bricks, ~70 ms of
    /// compression on one core) are split into runs encoded on as many threads as the machine
    /// has, the frames kept in cell order; each frame stands alone either way.
    pub(super) fn encode_cells(
        &mut self,
        level: u32,
        cells: &[u32],
        make: impl Fn(BrickBlob, Vec<[u32; 3]>) -> ServerMsg + Sync,
    ) -> Result<Vec<Bytes>, WireError> {
        let limits = (
            (self.config.limits.max_frame_bytes as usize).saturating_sub(4096) / 2,
            self.config.limits.max_bricks_per_frame,
        );
        let parts = cells
            .len()
            .div_ceil(PARALLEL_CELLS)
            .min(encode_threads())
            .max(1);
        while self.spare_encoders.len() + 1 < parts {
            self.spare_encoders.push(BlobEncoder::new(ZSTD_LEVEL)?);
        }
        let runs: Vec<&[u32]> = cells.chunks(cells.len().div_ceil(parts).max(1)).collect();
        let Some(map) = self.levels.map_at(&self.map, level) else {
            // Callers encode only levels that are built (sessions waiting for one are skipped).
            tracing::error!(scene = %self.name, level, "asked to encode a level that is not built");
            return Ok(Vec::new());
        };
        let make = &make;
        let (first, rest) = match runs.split_first() {
            Some(split) => split,
            None => return Ok(Vec::new()),
        };
        let mut frames = std::thread::scope(|scope| {
            // A run whose thread could not be started is encoded here, after the first.
            let others: Vec<_> = rest
                .iter()
                .zip(self.spare_encoders.iter_mut())
                .map(|(run, encoder)| {
                    let thread = std::thread::Builder::new().name("encode".into());
                    let spawned = thread
                        .spawn_scoped(scope, move || encode_run(map, run, encoder, limits, make));
                    (run, spawned.ok())
                })
                .collect();
            let mut frames = encode_run(map, first, &mut self.encoder, limits, make)?;
            for (run, other) in others {
                let encoded = match other {
                    Some(thread) => match thread.join() {
                        Ok(encoded) => encoded,
                        Err(panic) => std::panic::resume_unwind(panic),
                    },
                    None => {
                        let mut encoder = BlobEncoder::new(ZSTD_LEVEL)?;
                        encode_run(map, run, &mut encoder, limits, make)
                    }
                };
                frames.extend(encoded?);
            }
            Ok::<_, WireError>(frames)
        })?;
        frames.shrink_to_fit();
        Ok(frames)
    }

    /// Whether a sync or resync can make progress now (its client's queue has room, and the
    /// server's queues together are within their bound).
    pub fn has_ready_work(&self) -> bool {
        let half = self.sync_ahead();
        let over_total = self
            .subs
            .values()
            .next()
            .is_some_and(|s| s.out.total_queued() > self.config.max_queued_total);
        self.levels.building()
            || !over_total
                && self.subs.values().any(|s| {
                    (s.syncing && s.awaits_levels.is_none() && s.out.queued() < half)
                        || (s.lagging && s.out.queued() < self.config.max_queue_bytes / 4)
                })
    }

    /// How far a sync is queued ahead of its writer: [`SYNC_AHEAD`], or half the queue bound
    /// when that is smaller.
    fn sync_ahead(&self) -> usize {
        SYNC_AHEAD.min(self.config.max_queue_bytes / 2)
    }

    /// The waker a session's writer rings when it takes a frame while its sync streams: the
    /// owner's loop waits on it besides its commands.
    pub fn waker(&self) -> std::sync::Arc<tokio::sync::Notify> {
        self.wake.clone()
    }

    /// Whether a sync or resync is waiting for its client's queue to drain.
    pub fn has_blocked_work(&self) -> bool {
        self.subs.values().any(|s| s.syncing || s.lagging)
    }

    /// Advances syncs (initial, resume, resync) by a bounded amount per turn, so edits keep
    /// flowing while a large scene streams out: at most `max_syncs_per_turn` sessions get
    /// frames, for at most [`PUMP_TIME`], in turn (the next turn starts after the last one
    /// served), and none while the
    /// server's queues together hold more than `max_queued_total`.
    pub(super) fn pump_syncs(&mut self) {
        let after = self.sync_cursor;
        let ids: Vec<SessionId> = self
            .subs
            .range(after.saturating_add(1)..)
            .chain(self.subs.range(..=after))
            .filter(|(_, s)| (s.syncing || s.lagging) && s.awaits_levels.is_none())
            .map(|(&id, _)| id)
            .collect();
        let mut served = 0;
        let started = (self.clock)();
        for id in ids {
            // Edits wait while a turn streams: a turn streams to a few sessions, for a few
            // milliseconds at most (the next turn goes on with the sessions after them).
            if served == self.config.max_syncs_per_turn
                || (self.clock)().saturating_duration_since(started) > PUMP_TIME
            {
                break;
            }
            let Some(mut sub) = self.subs.remove(&id) else {
                continue;
            };
            if sub.out.total_queued() > self.config.max_queued_total {
                self.subs.insert(id, sub);
                break;
            }
            let before = sub.out.queued();
            if sub.out.is_closed() {
                // Its session is ending: the Leave that follows removes it (and forgets a
                // guest's history), so it stays until then, with nothing more to stream.
                sub.syncing = false;
                sub.lagging = false;
                self.subs.insert(id, sub);
                continue;
            }
            if sub.lagging && sub.out.queued() < self.config.max_queue_bytes / 4 {
                self.start_resync(&mut sub, true);
            }
            let mut frames = 0;
            let ahead = self.sync_ahead();
            while sub.syncing && frames < FRAMES_PER_TURN && sub.out.queued() < ahead {
                if sub.follow.is_some() {
                    frames += self.follow_frames(&mut sub);
                    if sub.awaits_levels.is_some() || sub.out.is_closed() {
                        break;
                    }
                    continue;
                }
                let most = self.config.limits.max_bricks_per_frame as usize;
                let take = (SYNC_BATCH_BYTES / self.sync_brick_bytes.max(1))
                    .clamp(SYNC_BATCH_MIN_BRICKS.min(most), most)
                    .min(sub.pending.len());
                let batch: Vec<u32> = sub.pending.split_off(sub.pending.len() - take);
                // Cells emptied since the sync began were already announced by a delta.
                let Some(map) = self.levels.map_at(&self.map, sub.level) else {
                    // Its level is being built again: it waits, then starts over.
                    sub.awaits_levels = Some(true);
                    sub.pending.clear();
                    break;
                };
                let live: Vec<u32> = batch
                    .into_iter()
                    .filter(|&c| map.slot_of_cell(map.cell_coords(c)).is_some())
                    .collect();
                let sent_before = sub.sync_sent;
                let total = sub.sync_total;
                let count = live.len() as u32;
                match self.encode_cells(sub.level, &live, |bricks, _| ServerMsg::SyncBatch {
                    bricks,
                    sent: sent_before + count,
                    total,
                }) {
                    Ok(batch_frames) => {
                        let bytes: usize = batch_frames.iter().map(|f| f.len()).sum();
                        if count >= 64 {
                            self.sync_brick_bytes = bytes / count as usize;
                        }
                        for f in batch_frames {
                            Metrics::add(&self.metrics.sync_batches_sent, 1);
                            sub.out.push(f);
                            frames += 1;
                        }
                    }
                    Err(e) => {
                        // The client would finish its sync without these bricks: end the
                        // session instead of leaving it with a copy that silently differs.
                        tracing::error!(scene = %self.name, error = %e, "could not encode a sync batch; closing the session");
                        self.metrics.count_unencodable("SyncBatch");
                        sub.out.close(
                            brickcast_protocol::wire::ErrorCode::Internal,
                            format!("the server could not encode a sync batch: {e}"),
                        );
                        break;
                    }
                }
                sub.sync_sent += count;
                if sub.pending.is_empty() {
                    sub.syncing = false;
                    sub.out.set_syncing(false);
                    sub.out
                        .send(&ServerMsg::SyncDone { seq: self.seq }, &self.metrics);
                }
            }
            if sub.out.queued() != before {
                served += 1;
                self.sync_cursor = id;
            }
            self.subs.insert(id, sub);
        }
    }
}

impl Subscriber {
    /// Starts streaming `pending` (sorted farthest first) as the state at `seq`.
    fn begin_sync(&mut self, pending: Vec<u32>, seq: u64) {
        self.pending = pending;
        self.sync_total = self.pending.len() as u32;
        self.sync_sent = 0;
        self.syncing = true;
        self.out.set_syncing(true);
        self.lagging = false;
        self.delivered = seq;
    }
}

/// Every brick's linear cell index in `map`, sorted to be sent nearest `eye` first.
pub(super) fn all_cells(map: &BrickMap, eye: [f32; 3]) -> Vec<u32> {
    let mut cells: Vec<u32> = map.brick_cells().map(|(c, _)| map.cell_index(c)).collect();
    sort_far_to_near(map, &mut cells, eye);
    cells
}

/// Sorts linear cell indices by distance to `eye`, farthest first, so `pop` yields the nearest.
pub(super) fn sort_far_to_near(map: &BrickMap, cells: &mut [u32], eye: [f32; 3]) {
    let key = |&c: &u32| {
        let p = map.cell_coords(c);
        let d: f32 = (0..3)
            .map(|i| (p[i] as f32 * 8.0 + 4.0 - eye[i]).powi(2))
            .sum();
        std::cmp::Reverse((d * 16.0) as u64)
    };
    cells.sort_unstable_by_key(key);
}

/// Cells above this many are encoded on more than one thread (one run per this many, at
/// most one per core).
const PARALLEL_CELLS: usize = 8192;

/// Threads a large delta is encoded on.
fn encode_threads() -> usize {
    static THREADS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *THREADS.get_or_init(|| {
        std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .min(8)
    })
}

/// Encodes one run of cells as frames (see [`Owner::encode_cells`]); `limits`: the raw bytes
/// and bricks one frame may hold.
fn encode_run(
    map: &BrickMap,
    cells: &[u32],
    encoder: &mut BlobEncoder,
    limits: (usize, u32),
    make: &(impl Fn(BrickBlob, Vec<[u32; 3]>) -> ServerMsg + Sync),
) -> Result<Vec<Bytes>, WireError> {
    let (max_raw, max_bricks) = limits;
    let mut frames = Vec::new();
    let mut removed = Vec::new();
    let mut scratch = [Colour::BLACK; 512];
    encoder.clear();
    let finish =
        |encoder: &mut BlobEncoder, removed: &mut Vec<[u32; 3]>, frames: &mut Vec<Bytes>| {
            let blob = encoder.finish()?;
            let msg = make(blob, std::mem::take(removed));
            frames.push(Bytes::from(encode_server(&msg)?));
            Ok::<(), WireError>(())
        };
    for &cell in cells {
        let coords = map.cell_coords(cell);
        match map.slot_of_cell(coords) {
            Some(slot) => {
                // Straight from the map's arrays: a delta re-sends every brick it touched, and
                // copying each into a `BrickData` first cost as much as compressing it. The
                // server's map is exact, so its colour blocks are what the wire carries.
                let mask = &map.masks()[slot as usize];
                let block = map.block(slot);
                let words = palette::coding_of_words(block)
                    .map_or(block.len(), |c| c.words(popcount(mask) as usize));
                // Brick rows usually compress but may not; budget raw bytes against half the frame.
                if encoder.len() >= max_bricks || encoder.raw_len() + 70 + 2 * words > max_raw {
                    finish(encoder, &mut removed, &mut frames)?;
                }
                if encoder.push_block(coords, mask, block).is_err() {
                    // A lossy block (a map with a colour bound): send its colours exactly as
                    // it holds them.
                    let colours = map.slot_colours(slot, &mut scratch);
                    encoder.push(coords, mask, colours)?;
                }
            }
            None => {
                if removed.len() >= MAX_REMOVED_PER_FRAME {
                    finish(encoder, &mut removed, &mut frames)?;
                }
                removed.push(coords);
            }
        }
    }
    if !encoder.is_empty() || !removed.is_empty() {
        finish(encoder, &mut removed, &mut frames)?;
    }
    Ok(frames)
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use brickcast_protocol::wire::{BrickBlob, Limits, ServerMsg, decode_server};
    use brickcast_protocol::{BrickMap, BrushMode, Colour};

    use crate::metrics::Metrics;
    use crate::scene::jobs::testing::open;
    use crate::store::Store;

    /// Cells enough to be encoded on several threads come out as frames holding every brick
    /// and every removed cell exactly once, in the order asked, each frame within its limits.
    #[test]
    fn many_cells_encode_on_several_threads_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let store = Arc::new(Store::open(dir.path()).unwrap());
        let mut map = BrickMap::new([512, 64, 512]).unwrap();
        // 64 × 4 × 64 = 16,384 bricks, some of two colours.
        map.fill_box([0, 0, 0], [511, 31, 511], BrushMode::Fill, Colour::WHITE);
        map.sphere([100.0, 20.0, 300.0], 40.0, BrushMode::Paint, Colour::BLACK);
        store.create_scene("s", &map).unwrap();
        let mut owner = open(&store, &Arc::new(Metrics::default()), 64);
        // Every cell of the lower half: bricks, then as many empty cells.
        let dims = map.cell_dims();
        let cells: Vec<u32> = (0..dims[0] * 8 * dims[2])
            .map(|i| {
                let (x, rest) = (i % dims[0], i / dims[0]);
                map.cell_index([x, rest % 8, rest / 8])
            })
            .collect();
        assert!(cells.len() > 3 * super::PARALLEL_CELLS);
        let frames = owner
            .encode_cells(0, &cells, |bricks, removed| ServerMsg::Delta {
                from_seq: 0,
                to_seq: 1,
                bricks,
                removed,
            })
            .unwrap();
        let limits = Limits::default();
        let mut seen = Vec::new();
        for frame in &frames {
            assert!(frame.len() <= limits.max_frame_bytes as usize);
            let ServerMsg::Delta {
                bricks, removed, ..
            } = decode_server(frame, &limits).unwrap()
            else {
                panic!("not a delta");
            };
            let bricks: Vec<_> = BrickBlob::decode(&bricks, limits.max_bricks_per_frame).unwrap();
            for brick in bricks {
                assert_eq!(Some(&brick), map.brick(brick.cell).as_ref());
                seen.push(map.cell_index(brick.cell));
            }
            seen.extend(removed.iter().map(|&c| map.cell_index(c)));
        }
        // Each frame lists its bricks, then its removed cells: compare as sets per frame run.
        let mut sorted = seen.clone();
        sorted.sort_unstable();
        let mut expected = cells.clone();
        expected.sort_unstable();
        assert_eq!(sorted, expected, "every cell once");
        let bricks_in_order: Vec<u32> = seen
            .iter()
            .copied()
            .filter(|&c| map.brick(map.cell_coords(c)).is_some())
            .collect();
        let expected_order: Vec<u32> = cells
            .iter()
            .copied()
            .filter(|&c| map.brick(map.cell_coords(c)).is_some())
            .collect();
        assert_eq!(bricks_in_order, expected_order, "bricks in the order asked");
    }

    /// A client that takes nothing has about [`super::SYNC_AHEAD`] of its sync queued, however
    /// large the scene; each frame its writer takes wakes the owner, which queues the next, to
    /// the end of the sync.
    #[test]
    fn a_sync_is_queued_only_a_little_ahead_of_its_writer() {
        use futures_util::FutureExt;

        use crate::metrics::PhaseClock;
        use crate::scene::jobs::testing::{A, Scene, join};

        // 1,024 bricks of noise: about 1 MB of sync, eight times what may be queued ahead.
        let mut map = BrickMap::new([128, 32, 128]).unwrap();
        let mut x: u32 = 1;
        for p in 0..128 * 32 * 128u32 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            map.set([p % 128, p / 128 % 32, p / 4096], Colour(x as u16 | 1));
        }
        assert_eq!(map.brick_count(), 1024);
        let scene = Scene::new(&map);
        let mut owner = scene.owner(u32::MAX);
        let wake = owner.waker();
        let mut rx = join(&mut owner, 1, A);
        let limits = Limits::default();
        let (mut bricks, mut done, mut most) = (0, false, 0);
        for round in 0..1000 {
            for _ in 0..20 {
                owner.step(Vec::new(), &mut PhaseClock::start()).unwrap();
            }
            let mut queued = 0;
            while let Some(frame) = rx.try_take() {
                queued += frame.len();
                match decode_server(&frame, &limits).unwrap() {
                    ServerMsg::SyncBatch { bricks: blob, .. } => {
                        bricks += BrickBlob::decode(&blob, limits.max_bricks_per_frame)
                            .unwrap()
                            .len();
                    }
                    ServerMsg::SyncDone { .. } => done = true,
                    _ => {}
                }
            }
            if queued > 0 && !done {
                assert!(
                    wake.notified().now_or_never().is_some(),
                    "taking sync frames wakes the owner (round {round}, {queued} bytes)"
                );
            }
            most = most.max(queued);
            if done {
                assert!(round >= 3, "the sync went out in {round} rounds");
                break;
            }
        }
        assert!(done, "the sync finished");
        assert_eq!(bricks, 1024);
        assert!(
            most <= super::SYNC_AHEAD + super::SYNC_BATCH_MIN_BRICKS * 1100,
            "{most} bytes queued ahead of the writer"
        );
    }

    /// A guest whose connection broke while its sync streamed is forgotten when it leaves:
    /// its history goes with it (the sync used to drop the session first, so its Leave found
    /// nobody and the guest's steps stayed in the scene's history for good).
    #[test]
    fn a_guest_cut_off_during_its_sync_leaves_no_history() {
        use crate::metrics::PhaseClock;
        use crate::scene::jobs::testing::{Scene, edit};
        use crate::scene::{Command, Joiner, Outbox};
        use brickcast_protocol::wire::{EditOp, Role};

        let mut map = BrickMap::new([256, 32, 256]).unwrap();
        map.fill_box([0, 0, 0], [255, 15, 255], BrushMode::Fill, Colour::WHITE);
        let scene = Scene::new(&map);
        let mut owner = scene.owner(u32::MAX);
        let (out, mut rx) = Outbox::new(Arc::default());
        let mut guest = Joiner::solo(7, 0x77, Role::Editor);
        guest.stable = false;
        let (joined, _) = tokio::sync::oneshot::channel();
        let join = Command::Join {
            session: 7,
            out,
            role: Role::Editor,
            resume_from: None,
            level: 0,
            budget: None,
            who: guest,
            joined,
        };
        let set = EditOp::Set {
            pos: [1, 20, 1],
            colour: Colour::BLACK,
        };
        let turn = |owner: &mut super::Owner, commands| {
            owner.step(commands, &mut PhaseClock::start()).unwrap();
        };
        turn(&mut owner, vec![join, edit(7, 1, vec![set])]);
        assert_eq!(owner.history.user_count(), 1);
        // The writer finds the peer gone mid-sync; a few turns pass before the Leave.
        rx.abort();
        for _ in 0..3 {
            turn(&mut owner, Vec::new());
        }
        turn(&mut owner, vec![Command::Leave { session: 7 }]);
        assert_eq!(owner.history.user_count(), 0, "the guest's history went");
    }
}
