//! A client's copy of a scene: server messages in, a `BrickMap` (and its GPU change log) out.
//!
//! Kept apart from the socket so that the viewer, the headless renderer and the tests apply
//! messages the same way, and so a reconnect can hand the same replica to a new connection.

use crate::BrickMap;
use crate::held::Held;
use crate::map::{MAX_STAND_IN_LEVEL, MIN_STAND_IN_LEVEL, MapError, REGION_CELLS};
use crate::wire::{BlobDecoder, BrickRef, Limits, ServerMsg, WireError};
use crate::working_set::Rule;

/// Why the client stopped trusting what the server sent.
#[derive(Debug, thiserror::Error)]
pub enum ReplicaError {
    #[error("server sent an undecodable brick batch: {0}")]
    Wire(#[from] WireError),
    #[error("server sent a brick that does not fit the scene: {0}")]
    Brick(#[from] MapError),
    #[error("server sent {0} before its Welcome")]
    NotWelcomed(&'static str),
    #[error("server sent {0}")]
    Unexpected(&'static str),
    #[error("server sent a working-set rule that does not fit the scene: {0:?}")]
    BadRule(Rule),
}

/// The local copy of one scene and how far it has caught up with the server.
pub struct Replica {
    pub map: BrickMap,
    /// Scene name from the Welcome.
    pub scene: String,
    /// Highest server sequence whose changes are all in `map` (valid once `synced`).
    pub seq: u64,
    /// Whether `map` equals the server's scene at `seq`.
    pub synced: bool,
    /// Bricks received and expected in the current (re)sync.
    pub sync_sent: u32,
    pub sync_total: u32,
    /// Bricks received over the replica's life (syncs and deltas): shows whether a reconnect
    /// resumed or had to fetch the whole scene again.
    pub bricks_received: u64,
    /// Set when the map was replaced wholesale (new scene, resync from zero): the GPU copy must
    /// be rebuilt rather than patched.
    reset: bool,
    /// Deltas since the last clearance rebuild: edits only lower empty-space clearance, so it is
    /// raised back now and then.
    deltas_since_rebuild: u32,
    decoder: BlobDecoder,
    max_bricks: u32,
    /// Whether the map keeps a GPU change log; off for copies no GPU drains (the load
    /// generator), whose log would otherwise grow with every delta.
    gpu_log: bool,
    /// How far bricks may stray from their colours in this copy ([`BrickMap::set_colour_bound`]).
    colour_bound: Option<u32>,
    /// What a client with a budget holds of the scene (issue #30), from the server's first
    /// `Follow` until the copy is dropped; `None`: the whole scene.
    held: Option<Held>,
    /// GPU bytes this copy may take (the budget its `Hello` states): a working set whose
    /// arrays outgrow it is packed ([`Held::compact`]). `None`: no limit.
    budget: Option<u64>,
    /// Times the arrays were packed to stay within the budget.
    pub compactions: u64,
    /// The working set's clearance was rebuilt at a `SyncDone` since it started.
    held_clearance_built: bool,
}

/// How many deltas between clearance rebuilds. A rebuild is a few passes over the region grid
/// (a few hundred KiB for 2048³), so this keeps its cost negligible.
const CLEARANCE_REBUILD_DELTAS: u32 = 256;

impl Replica {
    /// An empty replica of a scene of `size`, waiting for its sync.
    pub fn new(scene: &str, size: [u32; 3]) -> Result<Replica, ReplicaError> {
        let mut map = BrickMap::new(size)?;
        map.record_gpu_changes(true);
        Ok(Replica {
            map,
            scene: scene.to_string(),
            seq: 0,
            synced: false,
            sync_sent: 0,
            sync_total: 0,
            bricks_received: 0,
            reset: true,
            deltas_since_rebuild: 0,
            decoder: BlobDecoder::new()?,
            max_bricks: Limits::hard_caps().max_bricks_per_frame,
            gpu_log: true,
            colour_bound: None,
            held: None,
            budget: None,
            compactions: 0,
            held_clearance_built: false,
        })
    }

    /// Lets this copy code bricks in lossy blocks within `bound` per channel (0–255 scale)
    /// from now on and after every reset ([`BrickMap::set_colour_bound`]); `None`: exact. Set
    /// it before the sync: bricks already held keep their coding. Every brick arrives whole
    /// and exact from the server, so errors never compound. A copy that follows a working set
    /// holds it exact whatever the bound: the server plans it in exact bytes.
    pub fn set_colour_bound(&mut self, bound: Option<u32>) {
        self.colour_bound = bound;
        self.map.set_colour_bound(bound);
    }

    /// The GPU bytes this copy may take ([`Replica::budget`]); set it with the budget the
    /// `Hello` states.
    pub fn set_budget(&mut self, budget: Option<u64>) {
        self.budget = budget;
    }

    /// The GPU bytes this copy may take: a working set's arrays are packed when free room in
    /// them would take it past this, and the GPU copy keeps its buffers within it.
    pub fn budget(&self) -> Option<u64> {
        self.budget
    }

    /// Keeps a working set's arrays within the budget: when freed slots, blocks and colour
    /// chunks take them past it, they are packed. What the copy shows does not change; the
    /// GPU copy is rewritten in full (every array is marked changed).
    fn keep_within_budget(&mut self) {
        let (Some(budget), Some(held)) = (self.budget, &mut self.held) else {
            return;
        };
        if self.map.memory().total_bytes > budget && self.map.free_bytes() > 0 {
            held.compact(&mut self.map);
            self.compactions += 1;
        }
    }

    /// Turns the map's GPU change log on or off, now and after every reset.
    pub fn record_gpu_changes(&mut self, on: bool) {
        self.gpu_log = on;
        self.map.record_gpu_changes(on);
    }

    /// Where a reconnect can resume from: the sequence of a complete copy of the whole scene,
    /// if there is one. A working set does not resume: the server starts it again from the
    /// camera, and the next connection may be served the whole scene instead.
    pub fn resume_point(&self) -> Option<u64> {
        (self.synced && self.held.is_none()).then_some(self.seq)
    }

    /// Whether the map was replaced since the last call (the GPU copy must start over).
    pub fn take_reset(&mut self) -> bool {
        std::mem::take(&mut self.reset)
    }

    /// Called with a connection's Welcome. A copy from another scene, or from a server whose
    /// history is shorter than ours (a different store), is dropped. So is an incomplete copy
    /// (a sync cut short): the connection did not resume from it (see
    /// [`Replica::resume_point`]), so the server sends every brick but not the removals, and
    /// bricks removed meanwhile would stay in the copy forever. So is a working set: the server
    /// starts one again from the camera (a `Follow`), or serves this connection the whole
    /// scene, which a copy still holding coarse stand-ins would refuse.
    pub fn welcome(
        &mut self,
        scene: &str,
        size: [u32; 3],
        server_seq: u64,
    ) -> Result<(), ReplicaError> {
        let foreign = scene != self.scene
            || size != self.map.size()
            || server_seq < self.seq
            || !self.synced
            || self.held.is_some();
        if foreign {
            self.clear(scene, size)?;
        }
        self.synced = false;
        self.sync_sent = 0;
        Ok(())
    }

    fn clear(&mut self, scene: &str, size: [u32; 3]) -> Result<(), ReplicaError> {
        // The palette is not part of what a resync sends again: it stays until a `Palette`.
        let swatches = *self.map.swatches();
        self.map = BrickMap::new(size)?;
        self.map.set_swatches(swatches);
        self.map.record_gpu_changes(self.gpu_log);
        self.map.set_colour_bound(self.colour_bound);
        self.scene = scene.to_string();
        self.seq = 0;
        self.reset = true;
        self.held = None;
        self.held_clearance_built = false;
        Ok(())
    }

    /// What this copy holds of the scene when it follows a working set (`None`: all of it).
    pub fn held(&self) -> Option<&Held> {
        self.held.as_ref()
    }

    /// Applies one server message to the copy.
    pub fn apply(&mut self, msg: &ServerMsg) -> Result<(), ReplicaError> {
        match msg {
            ServerMsg::Welcome {
                scene, size, seq, ..
            } => self.welcome(scene, *size, *seq)?,
            ServerMsg::SyncBatch { .. } if self.held.is_some() => {
                return Err(ReplicaError::Unexpected(
                    "a whole-scene sync to a working set",
                ));
            }
            ServerMsg::SyncBatch {
                bricks,
                sent,
                total,
            } => {
                self.put_bricks(bricks)?;
                self.sync_sent = *sent;
                self.sync_total = *total;
            }
            ServerMsg::SyncDone { seq } => {
                self.seq = self.seq.max(*seq);
                self.synced = true;
                self.sync_sent = self.sync_total;
                // A working set's SyncDone follows every move of its eye: its clearance is
                // rebuilt after its first sync, then like a delta's, every so many messages
                // (a rebuild is a pass over the whole region grid).
                let settled = self.held.is_some()
                    && self.held_clearance_built
                    && self.deltas_since_rebuild < CLEARANCE_REBUILD_DELTAS;
                if !settled {
                    self.map.rebuild_clearance();
                    self.deltas_since_rebuild = 0;
                    self.held_clearance_built = self.held.is_some();
                }
            }
            ServerMsg::Delta {
                to_seq,
                bricks,
                removed,
                ..
            } => {
                match &mut self.held {
                    // Only what the working set shows at full resolution takes a delta.
                    Some(held) => {
                        let mut got = Vec::new();
                        self.decoder
                            .for_each(bricks, self.max_bricks, |b| got.push(b))?;
                        self.bricks_received += got.len() as u64;
                        for b in &got {
                            held.receive_brick(&mut self.map, b.cell, Some(b))?;
                        }
                        for &cell in removed {
                            held.receive_brick::<BrickRef>(&mut self.map, cell, None)?;
                        }
                    }
                    None => {
                        self.put_bricks(bricks)?;
                        for &cell in removed {
                            self.map.remove_brick(cell);
                        }
                    }
                }
                self.seq = self.seq.max(*to_seq);
                self.deltas_since_rebuild += 1;
                if self.deltas_since_rebuild >= CLEARANCE_REBUILD_DELTAS {
                    self.map.rebuild_clearance();
                    self.deltas_since_rebuild = 0;
                }
            }
            ServerMsg::Resync { since } => {
                self.synced = false;
                self.sync_sent = 0;
                if *since == 0 {
                    let (scene, size) = (self.scene.clone(), self.map.size());
                    self.clear(&scene, size)?;
                }
            }
            ServerMsg::Palette { swatches } => self.map.set_swatches(*swatches),
            &ServerMsg::Follow { eye, near, top } => {
                self.follow(Rule { eye, near, top })?;
                self.deltas_since_rebuild += 1;
            }
            ServerMsg::Regions { regions, bricks } => {
                self.receive_regions(regions, bricks)?;
                self.deltas_since_rebuild += 1;
            }
            ServerMsg::Coarse {
                level,
                bricks,
                empty,
            } => {
                let Some(held) = &mut self.held else {
                    return Err(ReplicaError::Unexpected("coarse bricks before a Follow"));
                };
                let mut got = Vec::new();
                self.decoder
                    .for_each(bricks, self.max_bricks, |b| got.push(b))?;
                self.bricks_received += got.len() as u64;
                for b in &got {
                    held.receive_coarse(&mut self.map, *level, b.cell, Some(b))?;
                }
                for &cell in empty {
                    held.receive_coarse::<BrickRef>(&mut self.map, *level, cell, None)?;
                }
                self.sync_sent = self
                    .sync_sent
                    .saturating_add((got.len() + empty.len()) as u32);
                self.deltas_since_rebuild += 1;
            }
            ServerMsg::Ack { .. }
            | ServerMsg::Error { .. }
            | ServerMsg::Pong { .. }
            | ServerMsg::Presence { .. }
            | ServerMsg::Undone { .. }
            | ServerMsg::Refused { .. } => {}
        }
        self.keep_within_budget();
        Ok(())
    }

    /// The server's rule for this copy's working set: adopted at once where the data is held
    /// ([`Held::retarget`]); what it lacks follows, then a `SyncDone`. A copy that held the
    /// whole scene (or nothing) starts from nothing.
    fn follow(&mut self, rule: Rule) -> Result<(), ReplicaError> {
        let dims = self.map.region_dims();
        let sane = (0..3).all(|i| rule.eye[i] < dims[i])
            && (MIN_STAND_IN_LEVEL..=MAX_STAND_IN_LEVEL).contains(&rule.top)
            && rule.near <= dims.iter().max().copied().unwrap_or(0);
        if !sane {
            return Err(ReplicaError::BadRule(rule));
        }
        if self.held.is_none() {
            let (scene, size) = (self.scene.clone(), self.map.size());
            self.clear(&scene, size)?;
            // The server plans a working set in the bytes of exact blocks
            // (`working_set::region_bytes`), so lossy blocks would only leave part of the
            // budget unused; coding them was most of what a page spent taking a working set
            // in. Held exact (the next `clear`, for a whole scene, brings the bound back).
            self.map.set_colour_bound(None);
            self.held = Some(Held::new(&self.map));
        }
        let Some(held) = &mut self.held else {
            return Ok(());
        };
        if held.is_jump(&rule) {
            // Most of what arrives next occupies regions that were empty, and lowering the
            // clearance around each new region visits (2·cap+1)³ others where the world is a
            // surface: claim none anywhere until the next SyncDone rebuilds it (the copy is
            // traced meanwhile, correct and a little slower).
            self.map.zero_region_clearance();
            self.held_clearance_built = false;
        }
        let plan = held.retarget(&mut self.map, rule)?;
        self.synced = false;
        self.sync_sent = 0;
        self.sync_total = (plan.regions.len() + plan.coarse.len()) as u32;
        Ok(())
    }

    /// Whole regions at level 0: each listed region takes the blob's bricks inside it.
    fn receive_regions(
        &mut self,
        regions: &[[u32; 3]],
        blob: &crate::wire::BrickBlob,
    ) -> Result<(), ReplicaError> {
        let Some(held) = &mut self.held else {
            return Err(ReplicaError::Unexpected("regions before a Follow"));
        };
        let mut bricks = Vec::with_capacity(blob.count as usize);
        self.decoder
            .for_each(blob, self.max_bricks, |brick| bricks.push(brick))?;
        self.bricks_received += bricks.len() as u64;
        let region_of = |b: &BrickRef| b.cell.map(|c| c / REGION_CELLS);
        bricks.sort_by_key(|b| {
            let r = region_of(b);
            (r[2], r[1], r[0])
        });
        let mut used = 0;
        for &r in regions {
            let start = bricks.partition_point(|b| {
                let q = region_of(b);
                (q[2], q[1], q[0]) < (r[2], r[1], r[0])
            });
            let end = start + bricks[start..].partition_point(|b| region_of(b) == r);
            used += end - start;
            held.receive_region(&mut self.map, r, &bricks[start..end])?;
        }
        if used != bricks.len() {
            return Err(ReplicaError::Unexpected(
                "bricks outside the regions they came with",
            ));
        }
        self.sync_sent = self.sync_sent.saturating_add(regions.len() as u32);
        Ok(())
    }

    fn put_bricks(&mut self, blob: &crate::wire::BrickBlob) -> Result<(), ReplicaError> {
        let mut bricks = Vec::with_capacity(blob.count as usize);
        self.decoder
            .for_each(blob, self.max_bricks, |brick| bricks.push(brick))?;
        self.bricks_received += bricks.len() as u64;
        // A copy that keeps colours within a bound codes the blob's bricks lossy on every core
        // first (most of what a textured sync costs), then stores them one by one.
        let lossy = match self.map.colour_bound() {
            Some(bound) => {
                let exact: Vec<_> = bricks
                    .iter()
                    .map(|b| {
                        let coding = crate::palette::coding_of_words(b.block())
                            .unwrap_or(crate::palette::Coding::Raw);
                        (b.colours(), coding)
                    })
                    .collect();
                let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
                crate::palette::lossy_many(&exact, bound, threads)
            }
            None => Vec::new(),
        };
        for (i, brick) in bricks.iter().enumerate() {
            let block = match lossy.get(i) {
                Some(l) if !l.is_empty() => l.as_slice(),
                _ => brick.block(),
            };
            self.map
                .put_coded(brick.cell, brick.mask, brick.colours(), block)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::BrickBlob;
    use crate::{BrickData, Colour};

    fn blob(bricks: &[BrickData]) -> BrickBlob {
        let mut enc = crate::wire::BlobEncoder::new(1).unwrap();
        for b in bricks {
            enc.push_brick(b).unwrap();
        }
        enc.finish().unwrap()
    }

    fn brick_at(cell: [u32; 3], colour: Colour) -> BrickData {
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.set(cell.map(|c| c * 8 + 1), colour);
        map.brick(cell).unwrap()
    }

    #[test]
    fn sync_delta_and_resync_from_zero() {
        let mut r = Replica::new("demo", [64, 64, 64]).unwrap();
        assert!(r.take_reset());
        let a = brick_at([1, 1, 1], Colour(5));
        r.apply(&ServerMsg::SyncBatch {
            bricks: blob(std::slice::from_ref(&a)),
            sent: 1,
            total: 1,
        })
        .unwrap();
        r.apply(&ServerMsg::SyncDone { seq: 7 }).unwrap();
        assert_eq!((r.synced, r.seq, r.resume_point()), (true, 7, Some(7)));
        assert_eq!(r.map.get([9, 9, 9]), Some(Colour(5)));
        r.apply(&ServerMsg::Delta {
            from_seq: 7,
            to_seq: 9,
            bricks: BrickBlob::empty(),
            removed: vec![[1, 1, 1]],
        })
        .unwrap();
        assert_eq!((r.seq, r.map.brick_count()), (9, 0));
        assert!(!r.take_reset());
        r.apply(&ServerMsg::SyncBatch {
            bricks: blob(&[a]),
            sent: 1,
            total: 1,
        })
        .unwrap();
        r.apply(&ServerMsg::Resync { since: 0 }).unwrap();
        assert_eq!((r.synced, r.map.brick_count()), (false, 0));
        assert!(r.take_reset());
    }

    #[test]
    fn welcome_from_a_shorter_history_drops_the_copy() {
        let mut r = Replica::new("demo", [64, 64, 64]).unwrap();
        r.map.set([1, 2, 3], Colour(1));
        r.apply(&ServerMsg::SyncDone { seq: 50 }).unwrap();
        r.take_reset();
        r.welcome("demo", [64, 64, 64], 60).unwrap();
        assert_eq!(r.map.brick_count(), 1, "same store, later: keep and resume");
        assert!(!r.take_reset());
        r.apply(&ServerMsg::SyncDone { seq: 60 }).unwrap();
        r.welcome("demo", [64, 64, 64], 10).unwrap();
        assert_eq!(r.map.brick_count(), 0, "server is behind us: another store");
        assert!(r.take_reset());
    }

    #[test]
    fn an_incomplete_copy_is_dropped_at_the_next_welcome() {
        let mut r = Replica::new("demo", [64, 64, 64]).unwrap();
        r.apply(&ServerMsg::SyncBatch {
            bricks: blob(&[brick_at([1, 1, 1], Colour(5))]),
            sent: 1,
            total: 2,
        })
        .unwrap();
        r.take_reset();
        // The connection broke before SyncDone: no resume point, and the next server may
        // have removed that brick meanwhile without saying so.
        assert_eq!(r.resume_point(), None);
        r.welcome("demo", [64, 64, 64], 3).unwrap();
        assert_eq!(r.map.brick_count(), 0);
        assert!(r.take_reset());
    }

    #[test]
    fn bad_bricks_are_errors_not_panics() {
        let mut r = Replica::new("demo", [16, 16, 16]).unwrap();
        let outside = brick_at([5, 5, 5], Colour(1));
        let err = r
            .apply(&ServerMsg::SyncBatch {
                bricks: blob(&[outside]),
                sent: 1,
                total: 1,
            })
            .unwrap_err();
        assert!(matches!(err, ReplicaError::Brick(_)), "{err}");
        let garbage = BrickBlob {
            count: 3,
            raw_len: 100,
            data: vec![1, 2, 3],
        };
        assert!(
            r.apply(&ServerMsg::SyncBatch {
                bricks: garbage,
                sent: 3,
                total: 3
            })
            .is_err()
        );
    }

    /// A copy that keeps colours within a bound still holds a working set exact: the server
    /// plans it in exact bytes, so lossy blocks would buy nothing the budget uses (and were most
    /// of a page's work taking a 16k world in). A whole scene after it is bounded again.
    #[test]
    fn a_working_set_is_held_exact_whatever_the_colour_bound() {
        let mut r = Replica::new("demo", [512, 64, 512]).unwrap();
        r.set_colour_bound(Some(12));
        let rule = Rule {
            eye: [0, 0, 0],
            near: 1,
            top: 4,
        };
        r.apply(&ServerMsg::Follow {
            eye: rule.eye,
            near: rule.near,
            top: rule.top,
        })
        .unwrap();
        let dims = r.map.region_dims();
        let cells = r.map.cell_dims();
        let (level, cell) = (MIN_STAND_IN_LEVEL..=rule.top)
            .flat_map(|l| {
                let [x, y, z] = cells.map(|c| c.div_ceil(1 << l));
                (0..z).flat_map(move |k| {
                    (0..y).flat_map(move |j| (0..x).map(move |i| (l, [i, j, k])))
                })
            })
            .find(|&(l, c)| rule.holds(dims, l, c))
            .expect("a coarse brick the rule holds");
        // 512 voxels on a smooth ramp: every colour distinct (raw exact), and what a bound of
        // 12 codes in lossy blocks.
        let ramp = BrickData {
            cell,
            mask: crate::brick::FULL_MASK,
            colours: (0..512u16)
                .map(|i| Colour(((i / 16) << 11) | ((i % 64) << 5)))
                .collect(),
        };
        r.apply(&ServerMsg::Coarse {
            level,
            bricks: blob(std::slice::from_ref(&ramp)),
            empty: vec![],
        })
        .unwrap();
        let codings: Vec<_> = (0..r.map.slot_count())
            .filter(|&s| r.map.masks()[s as usize] != crate::brick::EMPTY_MASK)
            .map(|s| crate::palette::coding_of_words(r.map.block(s)).unwrap())
            .collect();
        assert_eq!(codings, vec![crate::palette::Coding::Raw], "held exact");
        // Another scene, held whole: bounded as asked.
        r.welcome("other", [64, 64, 64], 0).unwrap();
        assert_eq!(r.map.colour_bound(), Some(12));
    }

    /// A copy that held a working set and connects again may be served the whole scene (its
    /// budget now holds it whole): the Welcome drops the working set, and the whole-scene sync
    /// is taken, not refused. Nor does a working set claim a resume.
    #[test]
    fn a_working_set_reconnected_to_a_whole_scene_is_dropped_at_the_welcome() {
        let mut r = Replica::new("demo", [128, 64, 128]).unwrap();
        r.set_colour_bound(Some(12));
        r.apply(&ServerMsg::Follow {
            eye: [0, 0, 0],
            near: 3,
            top: 4,
        })
        .unwrap();
        let near = brick_at([1, 1, 1], Colour(5));
        r.apply(&ServerMsg::Regions {
            regions: vec![[0, 0, 0]],
            bricks: blob(std::slice::from_ref(&near)),
        })
        .unwrap();
        r.apply(&ServerMsg::SyncDone { seq: 4 }).unwrap();
        assert!(r.synced && r.held().is_some());
        assert_eq!(r.resume_point(), None, "a working set does not resume");
        r.welcome("demo", [128, 64, 128], 4).unwrap();
        assert!(r.held().is_none(), "the working set is dropped");
        let far = brick_at([7, 1, 7], Colour(9));
        r.apply(&ServerMsg::SyncBatch {
            bricks: blob(&[near, far]),
            sent: 2,
            total: 2,
        })
        .expect("the whole scene's sync is taken");
        r.apply(&ServerMsg::SyncDone { seq: 4 }).unwrap();
        assert_eq!(r.map.brick_count(), 2);
        assert_eq!(r.map.colour_bound(), Some(12));
        assert_eq!(r.resume_point(), Some(4));
    }

    /// What a hostile or confused server sends a working set is an error, never a panic, and
    /// leaves the copy as it was: a rule outside the grid or with absurd levels, regions or
    /// coarse bricks before any rule, bricks outside the regions they came with.
    #[test]
    fn bad_working_set_messages_are_errors_not_panics() {
        let mut r = Replica::new("demo", [128, 64, 128]).unwrap();
        let before = r.map.content_hash();
        for (eye, near, top) in [
            ([9, 0, 0], 1, 4),
            ([0, 0, 0], 1, 40),
            ([0, 0, 0], 1, 0),
            ([0, 0, 0], u32::MAX, 4),
        ] {
            let err = r.apply(&ServerMsg::Follow { eye, near, top }).unwrap_err();
            assert!(matches!(err, ReplicaError::BadRule(_)), "{err}");
        }
        let brick = brick_at([1, 1, 1], Colour(5));
        let regions = ServerMsg::Regions {
            regions: vec![[0, 0, 0]],
            bricks: blob(std::slice::from_ref(&brick)),
        };
        assert!(matches!(
            r.apply(&regions),
            Err(ReplicaError::Unexpected(_))
        ));
        let coarse = ServerMsg::Coarse {
            level: 2,
            bricks: BrickBlob::empty(),
            empty: vec![[0, 0, 0]],
        };
        assert!(matches!(r.apply(&coarse), Err(ReplicaError::Unexpected(_))));
        assert_eq!(r.map.content_hash(), before);
        // With a rule: a brick of region [0, 0, 0] listed under region [1, 0, 0] is refused.
        r.apply(&ServerMsg::Follow {
            eye: [0, 0, 0],
            near: 3,
            top: 4,
        })
        .unwrap();
        let stray = ServerMsg::Regions {
            regions: vec![[1, 0, 0]],
            bricks: blob(&[brick]),
        };
        assert!(r.apply(&stray).is_err());
        assert_eq!(r.map.brick_count(), 0);
        // Coarse data at levels that are no stand-in level, or past the rule's top, or for
        // cells far outside the grid: ignored, at once (a level below 2 made the client count
        // regions with an overflowed span: a panic, or in a release build a walk over the
        // whole grid for each of up to 65,536 listed cells).
        let before = r.map.content_hash();
        for level in [0, 1, 5, 14, 15, 40, u32::MAX] {
            let coarse = ServerMsg::Coarse {
                level,
                bricks: BrickBlob::empty(),
                empty: vec![[0, 0, 0]; 65_536],
            };
            assert!(r.apply(&coarse).is_ok(), "level {level}");
        }
        let far = ServerMsg::Coarse {
            level: 2,
            bricks: BrickBlob::empty(),
            empty: vec![[u32::MAX, 0, u32::MAX]; 65_536],
        };
        assert!(r.apply(&far).is_ok());
        assert_eq!(r.map.content_hash(), before);
        r.map.check_invariants().unwrap();
    }
}
