//! The before-images of the bricks an edit changes, for undo: kept by the map while journaling
//! (see [`BrickMap::begin_journal`](crate::map::BrickMap::begin_journal)).
//!
//! Why its own buffers: the server journals every edit message, so this sits on the hot edit
//! path. A brick is copied once per message, on its first change, into buffers that are reused
//! from message to message (no allocation per brick), found again through a table keyed by a
//! cheap multiplicative hash of the cell (cells are trusted map indices, not peer input).

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use crate::brick::Mask;
use crate::colour::Colour;

/// A hasher for `u32` cell indices: one multiplication.
#[derive(Default)]
pub(crate) struct CellHasher(u64);

impl Hasher for CellHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 << 8 | u64::from(b)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }
    fn write_u32(&mut self, n: u32) {
        self.0 = u64::from(n).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

/// One journaled cell. A cell only single-voxel edits touched keeps the before-value of each
/// voxel they touched (`Journal::voxels`); any other change keeps the whole brick as it was
/// (`whole`: its mask here, its colours in `Journal::colours`).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Entry {
    pub(crate) cell: u32,
    pub(crate) whole: bool,
    /// The brick's mask before (empty when it had no brick); only when `whole`.
    pub(crate) mask: Mask,
    pub(crate) start: u32,
    pub(crate) len: u32,
    /// Voxels with a before-value in `Journal::voxels` (not `whole`).
    pub(crate) touched: Mask,
}

/// The journal's buffers.
#[derive(Default, Clone, Debug)]
pub(crate) struct Journal {
    pub(crate) on: bool,
    index: HashMap<u32, u32, BuildHasherDefault<CellHasher>>,
    pub(crate) entries: Vec<Entry>,
    pub(crate) colours: Vec<Colour>,
    /// (entry, voxel bit, before) of single voxels, in the order first touched.
    pub(crate) voxels: Vec<(u32, u16, Option<Colour>)>,
}

impl Journal {
    /// Empties the journal (keeping its buffers) and starts recording.
    pub(crate) fn begin(&mut self) {
        self.index.clear();
        self.entries.clear();
        self.colours.clear();
        self.voxels.clear();
        self.on = true;
    }

    /// The entry of `cell`, if journaled.
    pub(crate) fn entry(&self, cell: u32) -> Option<usize> {
        self.index.get(&cell).map(|&e| e as usize)
    }

    /// Records `cell`'s whole brick before its first change.
    pub(crate) fn record(&mut self, cell: u32, mask: Mask, colours: &[Colour]) {
        let start = self.colours.len() as u32;
        self.colours.extend_from_slice(colours);
        self.index.insert(cell, self.entries.len() as u32);
        self.entries.push(Entry {
            cell,
            whole: true,
            mask,
            start,
            len: colours.len() as u32,
            touched: [0; 8],
        });
    }

    /// Records one voxel's value before its first change (`cell` new to the journal or
    /// journaled voxel by voxel).
    pub(crate) fn record_voxel(&mut self, cell: u32, bit: u16, before: Option<Colour>) {
        let e = match self.entry(cell) {
            Some(e) => e,
            None => {
                self.index.insert(cell, self.entries.len() as u32);
                self.entries.push(Entry {
                    cell,
                    whole: false,
                    mask: [0; 8],
                    start: 0,
                    len: 0,
                    touched: [0; 8],
                });
                self.entries.len() - 1
            }
        };
        let entry = &mut self.entries[e];
        let (w, b) = (usize::from(bit / 64), bit % 64);
        if entry.whole || entry.touched[w] >> b & 1 == 1 {
            return;
        }
        entry.touched[w] |= 1 << b;
        self.voxels.push((e as u32, bit, before));
    }

    /// Turns a cell journaled voxel by voxel into a whole before-image, given the brick as it
    /// is now (`mask`, `colours`): the touched voxels go back to their recorded values.
    pub(crate) fn make_whole(&mut self, e: usize, mask: &Mask, colours: &[Colour]) {
        if self.entries[e].whole {
            return;
        }
        let mut values = [None; 512];
        let mut next = colours.iter();
        for (bit, value) in values.iter_mut().enumerate() {
            if mask[bit / 64] >> (bit % 64) & 1 == 1 {
                *value = next.next().copied();
            }
        }
        for v in self.voxels.iter_mut().filter(|v| v.0 == e as u32) {
            values[usize::from(v.1)] = v.2;
            v.0 = u32::MAX;
        }
        let mut before = [0u64; 8];
        let start = self.colours.len() as u32;
        for (bit, value) in values.iter().enumerate() {
            if let Some(c) = value {
                before[bit / 64] |= 1 << (bit % 64);
                self.colours.push(*c);
            }
        }
        let entry = &mut self.entries[e];
        entry.whole = true;
        entry.mask = before;
        entry.start = start;
        entry.len = self.colours.len() as u32 - start;
    }
}

/// Calls `f(bit, before, after)` for every voxel whose value differs between two bricks, in bit
/// order (`None`: empty). Words whose masks and colours are equal are skipped whole, so a brick
/// where one voxel changed costs eight mask compares and one short walk.
pub fn diff_bricks(
    before: (&Mask, &[Colour]),
    after: (&Mask, &[Colour]),
    mut f: impl FnMut(u16, Option<Colour>, Option<Colour>),
) {
    let (bm, bc) = before;
    let (am, ac) = after;
    let (mut bi, mut ai) = (0usize, 0usize);
    for w in 0..8 {
        let (b, a) = (bm[w], am[w]);
        let (bn, an) = (b.count_ones() as usize, a.count_ones() as usize);
        if b == a && bc.get(bi..bi + bn) == ac.get(ai..ai + an) {
            bi += bn;
            ai += an;
            continue;
        }
        let (mut bj, mut aj) = (bi, ai);
        let mut bits = b | a;
        while bits != 0 {
            let t = bits.trailing_zeros();
            bits &= bits - 1;
            let was = if b >> t & 1 == 1 {
                bj += 1;
                bc.get(bj - 1).copied()
            } else {
                None
            };
            let is = if a >> t & 1 == 1 {
                aj += 1;
                ac.get(aj - 1).copied()
            } else {
                None
            };
            if was != is {
                f((w * 64) as u16 + t as u16, was, is);
            }
        }
        bi += bn;
        ai += an;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn diff_finds_exactly_the_changed_voxels() {
        let c = |v: u16| Colour(v);
        let mut before = [0u64; 8];
        let mut after = [0u64; 8];
        before[0] = 0b1011;
        after[0] = 0b1110;
        before[7] = 1 << 63;
        after[7] = 1 << 63;
        let bc = [c(1), c(2), c(3), c(9)];
        let ac = [c(2), c(5), c(3), c(8)];
        let mut seen = Vec::new();
        diff_bricks((&before, &bc), (&after, &ac), |bit, b, a| {
            seen.push((bit, b, a))
        });
        assert_eq!(
            seen,
            [
                (0, Some(c(1)), None),
                (2, None, Some(c(5))),
                (511, Some(c(9)), Some(c(8)))
            ]
        );
        seen.clear();
        diff_bricks((&before, &bc), (&before, &bc), |bit, b, a| {
            seen.push((bit, b, a))
        });
        assert!(seen.is_empty());
    }
}
