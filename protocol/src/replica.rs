//! A client's copy of a scene: server messages in, a `BrickMap` (and its GPU change log) out.
//!
//! Kept apart from the socket so that the viewer, the headless renderer and the tests apply
//! messages the same way, and so a reconnect can hand the same replica to a new connection.

use crate::BrickMap;
use crate::map::MapError;
use crate::wire::{BlobDecoder, Limits, ServerMsg, WireError};

/// Why the client stopped trusting what the server sent.
#[derive(Debug, thiserror::Error)]
pub enum ReplicaError {
    #[error("server sent an undecodable brick batch: {0}")]
    Wire(#[from] WireError),
    #[error("server sent a brick that does not fit the scene: {0}")]
    Brick(#[from] MapError),
    #[error("server sent {0} before its Welcome")]
    NotWelcomed(&'static str),
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
        })
    }

    /// Lets this copy code bricks in lossy blocks within `bound` per channel (0–255 scale)
    /// from now on and after every reset ([`BrickMap::set_colour_bound`]); `None`: exact. Set
    /// it before the sync: bricks already held keep their coding. Every brick arrives whole
    /// and exact from the server, so errors never compound.
    pub fn set_colour_bound(&mut self, bound: Option<u32>) {
        self.colour_bound = bound;
        self.map.set_colour_bound(bound);
    }

    /// Turns the map's GPU change log on or off, now and after every reset.
    pub fn record_gpu_changes(&mut self, on: bool) {
        self.gpu_log = on;
        self.map.record_gpu_changes(on);
    }

    /// Where a reconnect can resume from: the sequence of a complete copy, if there is one.
    pub fn resume_point(&self) -> Option<u64> {
        self.synced.then_some(self.seq)
    }

    /// Whether the map was replaced since the last call (the GPU copy must start over).
    pub fn take_reset(&mut self) -> bool {
        std::mem::take(&mut self.reset)
    }

    /// Called with a connection's Welcome. A copy from another scene, or from a server whose
    /// history is shorter than ours (a different store), is dropped. So is an incomplete copy
    /// (a sync cut short): the connection did not resume from it (see
    /// [`Replica::resume_point`]), so the server sends every brick but not the removals, and
    /// bricks removed meanwhile would stay in the copy forever.
    pub fn welcome(
        &mut self,
        scene: &str,
        size: [u32; 3],
        server_seq: u64,
    ) -> Result<(), ReplicaError> {
        let foreign =
            scene != self.scene || size != self.map.size() || server_seq < self.seq || !self.synced;
        if foreign {
            self.clear(scene, size)?;
        }
        self.synced = false;
        self.sync_sent = 0;
        Ok(())
    }

    fn clear(&mut self, scene: &str, size: [u32; 3]) -> Result<(), ReplicaError> {
        self.map = BrickMap::new(size)?;
        self.map.record_gpu_changes(self.gpu_log);
        self.map.set_colour_bound(self.colour_bound);
        self.scene = scene.to_string();
        self.seq = 0;
        self.reset = true;
        Ok(())
    }

    /// Applies one server message to the copy.
    pub fn apply(&mut self, msg: &ServerMsg) -> Result<(), ReplicaError> {
        match msg {
            ServerMsg::Welcome {
                scene, size, seq, ..
            } => self.welcome(scene, *size, *seq)?,
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
                self.map.rebuild_clearance();
                self.deltas_since_rebuild = 0;
            }
            ServerMsg::Delta {
                to_seq,
                bricks,
                removed,
                ..
            } => {
                self.put_bricks(bricks)?;
                for &cell in removed {
                    self.map.remove_brick(cell);
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
            ServerMsg::Ack { .. }
            | ServerMsg::Error { .. }
            | ServerMsg::Pong { .. }
            | ServerMsg::Presence { .. }
            | ServerMsg::Undone { .. }
            | ServerMsg::Refused { .. } => {}
        }
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
}
