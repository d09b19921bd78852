//! A simulated disk under redb: what a process sees, what has reached the platter, and a crash
//! that keeps the second and loses (some of) the first.
//!
//! Writes land in `current` (what reads see, like the page cache) and are remembered as dirty
//! ranges; `sync_data` copies the dirty ranges to `durable`. A crash builds a new disk from
//! `durable` plus, when torn, a random subset of the unsynced 4 KiB pieces and possibly the
//! unsynced length: the kernel may have written back any dirty page before the power went,
//! in any order. A disk can also be armed to die after a number of I/O calls; from then on every
//! call fails, which is how the simulation stops a process in the middle of a commit or a
//! snapshot.

use std::sync::{Arc, Mutex, MutexGuard};

use rand::Rng;

/// Unsynced writes survive a torn crash in pieces of this size, each on its own.
const PIECE: u64 = 4096;

#[derive(Debug, Default)]
struct State {
    current: Vec<u8>,
    durable: Vec<u8>,
    /// Byte ranges written since the last sync, in write order.
    dirty: Vec<(u64, u64)>,
    /// I/O calls left before the disk dies (`None`: never).
    calls_left: Option<u64>,
    dead: bool,
    syncs: u64,
}

/// A shared handle on one simulated disk (redb owns one clone, the simulation another).
#[derive(Debug, Clone, Default)]
pub struct SimDisk(Arc<Mutex<State>>);

fn dead() -> std::io::Error {
    std::io::Error::other("simulated crash: the disk is gone")
}

impl SimDisk {
    pub fn new() -> SimDisk {
        SimDisk::default()
    }

    fn state(&self) -> MutexGuard<'_, State> {
        // A panic elsewhere cannot leave the state half-updated in a way that matters: the
        // simulation that panicked is over.
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Counts one I/O call against the arming; an error once the disk is dead.
    fn call(state: &mut State) -> std::io::Result<()> {
        if state.dead {
            return Err(dead());
        }
        if let Some(left) = &mut state.calls_left {
            if *left == 0 {
                state.dead = true;
                return Err(dead());
            }
            *left -= 1;
        }
        Ok(())
    }

    /// The disk dies after `calls` more I/O calls (reads, writes, syncs, resizes).
    pub fn die_after(&self, calls: u64) {
        self.state().calls_left = Some(calls);
    }

    /// Undoes [`SimDisk::die_after`] on a disk that is still alive.
    pub fn disarm(&self) {
        self.state().calls_left = None;
    }

    /// The disk dies now: every later call fails.
    pub fn kill(&self) {
        self.state().dead = true;
    }

    pub fn is_dead(&self) -> bool {
        self.state().dead
    }

    /// Syncs so far (each one a durable point).
    pub fn syncs(&self) -> u64 {
        self.state().syncs
    }

    /// The disk as it is found after a power cut now: everything synced, and with `torn` a
    /// random part of what was written since. The old disk must be dead (so nothing writes to
    /// it any more).
    pub fn crash(&self, rng: &mut impl Rng, torn: bool) -> SimDisk {
        let state = self.state();
        assert!(state.dead, "crash a disk only after killing it");
        let mut image = state.durable.clone();
        if torn {
            // The length may or may not have reached the disk.
            if state.current.len() != image.len() && rng.random_bool(0.5) {
                image.resize(state.current.len(), 0);
            }
            for &(start, end) in &state.dirty {
                let mut piece = start;
                while piece < end {
                    let stop = ((piece / PIECE + 1) * PIECE).min(end);
                    if rng.random_bool(0.5) {
                        let (a, b) = (piece as usize, stop as usize);
                        // What the page cache held at the crash, where it fits the image.
                        let b = b.min(image.len()).min(state.current.len());
                        if a < b {
                            image[a..b].copy_from_slice(&state.current[a..b]);
                        }
                    }
                    piece = stop;
                }
            }
        }
        SimDisk(Arc::new(Mutex::new(State {
            current: image.clone(),
            durable: image,
            ..State::default()
        })))
    }
}

impl redb::StorageBackend for SimDisk {
    fn len(&self) -> std::io::Result<u64> {
        let mut state = self.state();
        Self::call(&mut state)?;
        Ok(state.current.len() as u64)
    }

    fn read(&self, offset: u64, out: &mut [u8]) -> std::io::Result<()> {
        let mut state = self.state();
        Self::call(&mut state)?;
        let start = usize::try_from(offset).map_err(std::io::Error::other)?;
        let end = start
            .checked_add(out.len())
            .filter(|&e| e <= state.current.len())
            .ok_or_else(|| std::io::Error::other("read past the end of the simulated disk"))?;
        out.copy_from_slice(&state.current[start..end]);
        Ok(())
    }

    fn set_len(&self, len: u64) -> std::io::Result<()> {
        let mut state = self.state();
        Self::call(&mut state)?;
        let len = usize::try_from(len).map_err(std::io::Error::other)?;
        let old = state.current.len();
        state.current.resize(len, 0);
        if len > old {
            // New bytes are zeros in `current`; the durable copy grows at the next sync.
            state.dirty.push((old as u64, len as u64));
        }
        Ok(())
    }

    fn sync_data(&self) -> std::io::Result<()> {
        let mut state = self.state();
        Self::call(&mut state)?;
        let State {
            current,
            durable,
            dirty,
            ..
        } = &mut *state;
        durable.resize(current.len(), 0);
        for (start, end) in dirty.drain(..) {
            let (a, b) = (start as usize, (end as usize).min(current.len()));
            if a < b {
                durable[a..b].copy_from_slice(&current[a..b]);
            }
        }
        state.syncs += 1;
        Ok(())
    }

    fn write(&self, offset: u64, data: &[u8]) -> std::io::Result<()> {
        let mut state = self.state();
        Self::call(&mut state)?;
        let start = usize::try_from(offset).map_err(std::io::Error::other)?;
        let end = start
            .checked_add(data.len())
            .filter(|&e| e <= state.current.len())
            .ok_or_else(|| std::io::Error::other("write past the end of the simulated disk"))?;
        state.current[start..end].copy_from_slice(data);
        state.dirty.push((start as u64, end as u64));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use redb::StorageBackend;

    #[test]
    fn a_crash_keeps_what_was_synced() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let disk = SimDisk::new();
        disk.set_len(3 * PIECE).unwrap();
        disk.write(0, &[1; 10]).unwrap();
        disk.sync_data().unwrap();
        disk.write(0, &[2; 10]).unwrap();
        disk.write(2 * PIECE, &[3; 10]).unwrap();
        disk.kill();
        assert!(disk.write(0, &[4]).is_err(), "a dead disk takes nothing");
        let clean = disk.crash(&mut rng, false);
        let mut out = [0u8; 10];
        clean.read(0, &mut out).unwrap();
        assert_eq!(out, [1; 10], "unsynced writes are lost");
        // Torn: each unsynced piece survives on its own; over many crashes both outcomes occur.
        let mut seen = std::collections::BTreeSet::new();
        for _ in 0..64 {
            let torn = disk.crash(&mut rng, true);
            let (mut a, mut b) = ([0u8; 1], [0u8; 1]);
            torn.read(0, &mut a).unwrap();
            torn.read(2 * PIECE, &mut b).unwrap();
            seen.insert((a[0], b[0]));
        }
        assert_eq!(seen.len(), 4, "{seen:?}");
    }

    #[test]
    fn an_armed_disk_dies_after_so_many_calls() {
        let disk = SimDisk::new();
        disk.die_after(2);
        disk.set_len(10).unwrap();
        disk.write(0, &[1]).unwrap();
        assert!(disk.sync_data().is_err());
        assert!(disk.is_dead());
        assert_eq!(disk.syncs(), 0);
    }
}
