//! The load clients' copies of the scene, kept cheaply enough that the load generator does not
//! starve the server it measures when both share a machine.
//!
//! Every client receives the same delta bytes, so a delta is decompressed once for all of them
//! (a client whose bytes differ from the cached ones by even one byte decodes its own). Each
//! client then only notes, per brick cell, the latest version it received; the notes are applied
//! to its map before anything else touches the map (a sync message) and before the map is
//! hashed. A delta replaces whole bricks and lists removed cells, so applying the last version of
//! each cell gives exactly the map that applying every delta in order would: the end-of-run check
//! compares the same thing, for a fraction of the work.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use brickcast_protocol::brick::popcount;
use brickcast_protocol::wire::{BlobDecoder, BrickBlob, Limits, ServerMsg};
use brickcast_protocol::{BrickData, Colour, Mask};

use crate::replica::{Replica, ReplicaError};

/// Decoded deltas kept for clients that have not read them yet, up to this many raw bytes:
/// clients within that much of each other share a decode; one further behind decodes for
/// itself.
const CACHED_BYTES: usize = 128 << 20;

/// One decoded delta frame, with the compressed bytes it came from.
struct Decoded {
    from: u64,
    to: u64,
    count: u32,
    raw_len: u32,
    data: Vec<u8>,
    bricks: Vec<Arc<BrickData>>,
}

/// Deltas decoded by one client for the others.
#[derive(Default)]
pub struct DeltaCache {
    recent: Mutex<Recent>,
}

/// The cached deltas, oldest first, and their raw size.
#[derive(Default)]
struct Recent {
    deltas: VecDeque<Arc<Decoded>>,
    bytes: usize,
}

impl DeltaCache {
    /// The bricks of `blob` (from a delta covering `(from, to]`), decoded by whoever received the
    /// same bytes first.
    fn bricks(
        &self,
        from: u64,
        to: u64,
        blob: &BrickBlob,
        decoder: &mut BlobDecoder,
    ) -> Result<Arc<Decoded>, ReplicaError> {
        let same_header = |d: &&Arc<Decoded>| {
            (d.from, d.to, d.count, d.raw_len, d.data.len())
                == (from, to, blob.count, blob.raw_len, blob.data.len())
        };
        let candidates: Vec<Arc<Decoded>> = self
            .lock()
            .deltas
            .iter()
            .rev()
            .filter(same_header)
            .cloned()
            .collect();
        // Compared outside the lock: a few hundred KiB at memory speed.
        if let Some(hit) = candidates.into_iter().find(|d| d.data == blob.data) {
            return Ok(hit);
        }
        let mut bricks = Vec::with_capacity(blob.count as usize);
        decoder.for_each(blob, Limits::hard_caps().max_bricks_per_frame, |b| {
            bricks.push(Arc::new(b.to_brick()));
        })?;
        let decoded = Arc::new(Decoded {
            from,
            to,
            count: blob.count,
            raw_len: blob.raw_len,
            data: blob.data.clone(),
            bricks,
        });
        let mut recent = self.lock();
        recent.bytes += decoded.raw_len as usize;
        recent.deltas.push_back(decoded.clone());
        while recent.bytes > CACHED_BYTES {
            match recent.deltas.pop_front() {
                Some(old) => recent.bytes -= old.raw_len as usize,
                None => break,
            }
        }
        Ok(decoded)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Recent> {
        // A panic mid-update can at worst leave the byte count off, which only moves eviction.
        self.recent.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Raw bytes of held deltas after which a copy writes them into its map. Writing bricks into a
/// map is most of what a load client costs, and on a machine shared with the server every
/// cycle spent there is taken from the server being measured: holding deltas until the
/// end-of-run check (where nothing is measured any more) halved the tool's CPU time in a
/// 16-client run (8.7 s instead of 15 s for 10 s of max-rate edits) and doubled the throughput
/// it measured. The held deltas are shared between clients that received the same bytes, so
/// this bounds the tool's memory to about this much (1-2 GiB in practice), not this much per
/// client. Each copy flushes somewhere between half and all of it (see [`LazyCopy::new`]).
pub const FLUSH_BYTES: usize = 512 << 20;

/// One received delta frame, not yet written into the map.
struct Held {
    decoded: Arc<Decoded>,
    removed: Vec<[u32; 3]>,
}

/// One client's copy: a replica plus the delta frames not yet written into it.
pub struct LazyCopy {
    replica: Replica,
    /// Delta frames received since the last flush, in arrival order.
    held: Vec<Held>,
    held_bytes: usize,
    /// `held_bytes` that trigger a flush.
    flush_at: usize,
    /// Highest delta sequence in `held`.
    held_to: u64,
    /// One bit per cell of the grid, set for cells already written in the current flush.
    written: Vec<u64>,
    decoder: BlobDecoder,
    /// Apply every delta at once and count the voxels it changes (one client does, so the run
    /// reports voxels broadcast even without the server's metrics).
    count_voxels: bool,
    pub voxels_seen: u64,
}

impl LazyCopy {
    /// A copy that flushes after `flush_at` raw bytes of deltas. Clients receive the same
    /// stream, so with one threshold they would all flush at the same moment and stall the
    /// load generator (and its latency samples) for seconds with 200 clients: give each client
    /// its own, between `FLUSH_BYTES / 2` and `FLUSH_BYTES`.
    pub fn new(
        replica: Replica,
        count_voxels: bool,
        flush_at: usize,
    ) -> Result<LazyCopy, ReplicaError> {
        Ok(LazyCopy {
            replica,
            held: Vec::new(),
            held_bytes: 0,
            flush_at,
            held_to: 0,
            written: Vec::new(),
            decoder: BlobDecoder::new()?,
            count_voxels,
            voxels_seen: 0,
        })
    }

    /// Takes in one server message.
    pub fn apply(&mut self, msg: &ServerMsg, cache: &DeltaCache) -> Result<(), ReplicaError> {
        let ServerMsg::Delta {
            from_seq,
            to_seq,
            bricks,
            removed,
        } = msg
        else {
            if matches!(
                msg,
                ServerMsg::SyncBatch { .. }
                    | ServerMsg::SyncDone { .. }
                    | ServerMsg::Resync { .. }
                    | ServerMsg::Welcome { .. }
            ) {
                // These act on the map as it stands: bring it up to date first.
                self.flush()?;
            }
            return self.replica.apply(msg);
        };
        let decoded = cache.bricks(*from_seq, *to_seq, bricks, &mut self.decoder)?;
        if self.count_voxels {
            let map = &mut self.replica.map;
            let mut scratch = [Colour::BLACK; 512];
            for brick in &decoded.bricks {
                self.voxels_seen += match map.slot_of_cell(brick.cell) {
                    Some(slot) => {
                        let colours = map.slot_colours(slot, &mut scratch);
                        let mask = &map.masks()[slot as usize];
                        brick_difference(mask, colours, &brick.mask, &brick.colours)
                    }
                    None => brick.colours.len() as u64,
                };
                map.put_brick(brick)?;
            }
            for &cell in removed {
                if let Some(slot) = map.slot_of_cell(cell) {
                    self.voxels_seen += u64::from(popcount(&map.masks()[slot as usize]));
                    map.remove_brick(cell);
                }
            }
            self.replica.seq = self.replica.seq.max(*to_seq);
            return Ok(());
        }
        self.held_bytes += decoded.raw_len as usize + removed.len() * 12;
        self.held.push(Held {
            decoded,
            removed: removed.clone(),
        });
        self.held_to = self.held_to.max(*to_seq);
        if self.held_bytes > self.flush_at {
            self.flush()?;
        }
        Ok(())
    }

    /// Writes the held deltas into the map: newest first, each cell once (its latest version).
    ///
    /// A flush is milliseconds of work. On a multi-threaded runtime it runs with
    /// `block_in_place`, so the other clients' tasks queued behind it move to another worker
    /// instead of waiting, and their latency samples measure the server, not this flush.
    pub fn flush(&mut self) -> Result<(), ReplicaError> {
        if self.held.is_empty() {
            return Ok(());
        }
        let multi_thread = tokio::runtime::Handle::try_current()
            .is_ok_and(|h| h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread);
        if multi_thread {
            tokio::task::block_in_place(|| self.write_held())
        } else {
            self.write_held()
        }
    }

    fn write_held(&mut self) -> Result<(), ReplicaError> {
        let map = &mut self.replica.map;
        let dims = map.cell_dims();
        let cells: usize = dims.iter().map(|&d| d as usize).product();
        self.written.resize(cells.div_ceil(64), 0);
        let written = &mut self.written;
        // Whether `cell` is inside the grid and still to be written (then marks it written).
        let mut first = |cell: [u32; 3]| {
            if (0..3).any(|i| cell[i] >= dims[i]) {
                return None;
            }
            let i = map_index(dims, cell);
            let (word, bit) = (i / 64, 1u64 << (i % 64));
            let fresh = written[word] & bit == 0;
            written[word] |= bit;
            Some(fresh)
        };
        for held in self.held.iter().rev() {
            for brick in &held.decoded.bricks {
                match first(brick.cell) {
                    Some(false) => {}
                    // Outside the grid: `put_brick` says why it does not fit.
                    Some(true) | None => map.put_brick(brick)?,
                }
            }
            for &cell in &held.removed {
                if first(cell) == Some(true) {
                    map.remove_brick(cell);
                }
            }
        }
        self.written.iter_mut().for_each(|w| *w = 0);
        self.held.clear();
        self.held_bytes = 0;
        self.replica.seq = self.replica.seq.max(self.held_to);
        Ok(())
    }

    /// The copy, up to date (flushes first).
    pub fn current(&mut self) -> Result<&Replica, ReplicaError> {
        self.flush()?;
        Ok(&self.replica)
    }
}

/// Linear index of an in-grid cell (x fastest), for the written-cells bitset.
fn map_index(dims: [u32; 3], cell: [u32; 3]) -> usize {
    (cell[0] as usize) + dims[0] as usize * (cell[1] as usize + dims[1] as usize * cell[2] as usize)
}

/// Voxels whose solidity or colour differs between two versions of a brick.
pub fn brick_difference(
    old_mask: &Mask,
    old_colours: &[Colour],
    new_mask: &Mask,
    new_colours: &[Colour],
) -> u64 {
    if old_mask == new_mask {
        return old_colours
            .iter()
            .zip(new_colours)
            .filter(|(a, b)| a != b)
            .count() as u64;
    }
    let mut changed = 0u64;
    let (mut i, mut j) = (0usize, 0usize);
    for (&a, &b) in old_mask.iter().zip(new_mask) {
        changed += u64::from((a ^ b).count_ones());
        let mut any = a | b;
        while any != 0 {
            let bit = 1u64 << any.trailing_zeros();
            any &= any - 1;
            match (a & bit != 0, b & bit != 0) {
                (true, true) => {
                    changed += u64::from(old_colours.get(i) != new_colours.get(j));
                    i += 1;
                    j += 1;
                }
                (true, false) => i += 1,
                (false, true) => j += 1,
                (false, false) => {}
            }
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::wire::BlobEncoder;
    use brickcast_protocol::{BrickMap, BrushMode, Colour};

    fn brick(voxels: &[(u32, u16)]) -> BrickData {
        let mut mask = [0u64; 8];
        let mut sorted = voxels.to_vec();
        sorted.sort_unstable();
        for &(b, _) in &sorted {
            mask[(b / 64) as usize] |= 1 << (b % 64);
        }
        BrickData {
            cell: [0, 0, 0],
            mask,
            colours: sorted.iter().map(|&(_, c)| Colour(c)).collect(),
        }
    }

    #[test]
    fn brick_difference_counts_solidity_and_colour_changes() {
        let diff = |a: &BrickData, b: &BrickData| {
            brick_difference(&a.mask, &a.colours, &b.mask, &b.colours)
        };
        let a = brick(&[(0, 1), (5, 2), (64, 3), (511, 4)]);
        assert_eq!(diff(&a, &a), 0);
        // Recolour one voxel, same mask.
        let b = brick(&[(0, 1), (5, 9), (64, 3), (511, 4)]);
        assert_eq!(diff(&a, &b), 1);
        // Remove voxel 5, add voxel 6, recolour 511: the colour lists shift against each other.
        let c = brick(&[(0, 1), (6, 2), (64, 3), (511, 7)]);
        assert_eq!(diff(&a, &c), 3);
        assert_eq!(diff(&c, &a), 3);
    }

    /// A delta carrying the current state of `cells` of `map`, as the server builds one.
    fn delta(map: &BrickMap, cells: &[[u32; 3]], from: u64, to: u64) -> ServerMsg {
        let mut enc = BlobEncoder::new(1).unwrap();
        let mut removed = Vec::new();
        for &c in cells {
            match map.brick(c) {
                Some(b) => enc.push_brick(&b).unwrap(),
                None => removed.push(c),
            }
        }
        ServerMsg::Delta {
            from_seq: from,
            to_seq: to,
            bricks: enc.finish().unwrap(),
            removed,
        }
    }

    #[test]
    fn lazy_copies_end_equal_to_applying_every_delta_in_order() {
        let size = [64, 32, 64];
        let mut server = BrickMap::new(size).unwrap();
        server.fill_box([0, 0, 0], [63, 5, 63], BrushMode::Fill, Colour(3));
        let mut eager = Replica::new("t", size).unwrap();
        for (b, _) in server.bricks() {
            eager.map.put_brick(&b).unwrap();
        }
        eager.apply(&ServerMsg::SyncDone { seq: 0 }).unwrap();
        let start = || {
            let mut r = Replica::new("t", size).unwrap();
            for (b, _) in server.bricks() {
                r.map.put_brick(&b).unwrap();
            }
            r.apply(&ServerMsg::SyncDone { seq: 0 }).unwrap();
            r
        };
        let cache = DeltaCache::default();
        let mut lazy = LazyCopy::new(start(), false, FLUSH_BYTES).unwrap();
        // A tiny threshold: flushes after every delta, the other extreme.
        let mut lazy2 = LazyCopy::new(start(), false, 1).unwrap();
        let mut counting = LazyCopy::new(start(), true, FLUSH_BYTES).unwrap();
        let mut changed = 0;
        // Spheres that grow, erase and repaint the same bricks over and over, so later deltas
        // supersede earlier ones and some bricks vanish and come back.
        for step in 0..40u64 {
            server.record_touched(true);
            let x = (step * 7 % 48) as f32 + 8.0;
            let mode = match step % 3 {
                0 => BrushMode::Fill,
                1 => BrushMode::Erase,
                _ => BrushMode::Paint,
            };
            changed += server.sphere([x, 5.0, 20.0], 6.0, mode, Colour(step as u16));
            let touched = server.take_touched();
            let cells: Vec<[u32; 3]> = touched.iter().map(|&c| server.cell_coords(c)).collect();
            let msg = delta(&server, &cells, step, step + 1);
            eager.apply(&msg).unwrap();
            lazy.apply(&msg, &cache).unwrap();
            lazy2.apply(&msg, &cache).unwrap();
            counting.apply(&msg, &cache).unwrap();
        }
        let want = server.content_hash();
        assert_eq!(eager.map.content_hash(), want);
        for copy in [&mut lazy, &mut lazy2, &mut counting] {
            let r = copy.current().unwrap();
            assert_eq!((r.map.content_hash(), r.seq), (want, 40));
        }
        // Net voxels changed per delta equal the brushes' own counts here (each delta is one
        // brush, and a brush reports exactly the voxels it changed).
        assert_eq!(counting.voxels_seen, changed);
        // Three copies, one decode per delta.
        assert_eq!(cache.lock().deltas.len(), 40);
    }

    #[test]
    fn a_sync_message_applies_pending_deltas_first() {
        let size = [32, 32, 32];
        let mut server = BrickMap::new(size).unwrap();
        server.set([1, 1, 1], Colour(9));
        let mut copy = LazyCopy::new(Replica::new("t", size).unwrap(), false, FLUSH_BYTES).unwrap();
        let cache = DeltaCache::default();
        copy.apply(&delta(&server, &[[0, 0, 0]], 0, 1), &cache)
            .unwrap();
        // A resync from zero drops the copy: the pending brick must not reappear after it.
        copy.apply(&ServerMsg::Resync { since: 0 }, &cache).unwrap();
        let r = copy.current().unwrap();
        assert_eq!(r.map.brick_count(), 0);
        // A frame with the same range but other bytes is decoded on its own, not taken from the
        // cache.
        server.paint([1, 1, 1], Colour(10));
        copy.apply(&delta(&server, &[[0, 0, 0]], 0, 1), &cache)
            .unwrap();
        assert_eq!(copy.current().unwrap().map.get([1, 1, 1]), Some(Colour(10)));
        // A removal outside the grid changes nothing, as it would in an eager replica.
        let outside = ServerMsg::Delta {
            from_seq: 1,
            to_seq: 2,
            bricks: BrickBlob::empty(),
            removed: vec![[1 << 20, 0, 0], [0, 0, 4]],
        };
        copy.apply(&outside, &cache).unwrap();
        let r = copy.current().unwrap();
        assert_eq!((r.map.brick_count(), r.seq), (1, 2));
    }
}
