//! The coarse bricks a working set holds, found by level and cell.
//!
//! A dense index per level (a `u32` per coarse cell of the scene, made at the level's first
//! brick) into a list of entries. A first working set on the 16k world stores about a million
//! coarse cells in a row, each looked up two or three times: in a hash table that was an eighth
//! of the browser page's time (a cache miss or two per lookup, on cores the page shares with
//! the server and the GPU process); here it is one read of an index near the last one. The
//! index costs 4 bytes per level-2 cell (one per region: as much again as the map's region
//! array, 16 MiB on the 16k world) and an eighth of that for each level above; a hash table of
//! the same million entries took more (about 58 MiB at its load factor).

use crate::map::{MAX_STAND_IN_LEVEL, MIN_STAND_IN_LEVEL};

/// A coarse brick the client holds: its slot (`None`: the brick is empty) and how many regions
/// show it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Coarse {
    pub(super) slot: Option<u32>,
    pub(super) shown_by: u32,
}

/// Coarse bricks by `(level, cell)`. Keys outside the scene's grid at their level are never
/// held.
#[derive(Debug, Clone)]
pub(super) struct CoarseTable {
    region_dims: [u32; 3],
    /// Per level from [`MIN_STAND_IN_LEVEL`]: each cell's entry + 1 (0: none held); empty until
    /// the level's first brick.
    index: Vec<Vec<u32>>,
    entries: Vec<Coarse>,
    /// Entries freed for reuse (reset to the default: no slot, shown by none).
    free: Vec<u32>,
}

impl CoarseTable {
    pub(super) fn new(region_dims: [u32; 3]) -> CoarseTable {
        CoarseTable {
            region_dims,
            index: vec![Vec::new(); (MAX_STAND_IN_LEVEL - MIN_STAND_IN_LEVEL + 1) as usize],
            entries: Vec::new(),
            free: Vec::new(),
        }
    }

    pub(super) fn len(&self) -> usize {
        self.entries.len() - self.free.len()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Room for `n` more entries.
    pub(super) fn reserve(&mut self, n: usize) {
        self.entries.reserve(n.saturating_sub(self.free.len()));
    }

    /// The level's grid of cells and the cell's place in it; `None` outside it.
    fn place(&self, (level, cell): (u32, [u32; 3])) -> Option<(usize, usize)> {
        if !(MIN_STAND_IN_LEVEL..=MAX_STAND_IN_LEVEL).contains(&level) {
            return None;
        }
        let span = 1u32 << (level - MIN_STAND_IN_LEVEL);
        let cells = self.region_dims.map(|d| d.div_ceil(span));
        if (0..3).any(|i| cell[i] >= cells[i]) {
            return None;
        }
        let at = (cell[2] as usize * cells[1] as usize + cell[1] as usize) * cells[0] as usize
            + cell[0] as usize;
        Some(((level - MIN_STAND_IN_LEVEL) as usize, at))
    }

    fn entry_of(&self, key: (u32, [u32; 3])) -> Option<usize> {
        let (level, at) = self.place(key)?;
        let e = *self.index[level].get(at)?;
        (e != 0).then(|| e as usize - 1)
    }

    pub(super) fn get(&self, key: &(u32, [u32; 3])) -> Option<&Coarse> {
        self.entry_of(*key).map(|e| &self.entries[e])
    }

    pub(super) fn get_mut(&mut self, key: &(u32, [u32; 3])) -> Option<&mut Coarse> {
        self.entry_of(*key).map(|e| &mut self.entries[e])
    }

    pub(super) fn contains_key(&self, key: &(u32, [u32; 3])) -> bool {
        self.entry_of(*key).is_some()
    }

    /// Holds `value` for `key` (replacing what it held). A key outside the grid is not held:
    /// returns false.
    pub(super) fn insert(&mut self, key: (u32, [u32; 3]), value: Coarse) -> bool {
        let Some((level, at)) = self.place(key) else {
            return false;
        };
        if self.index[level].is_empty() {
            // `level` counts from the finest stand-in level, as a cell's span does.
            let span = 1u32 << level;
            let cells: usize = self
                .region_dims
                .iter()
                .map(|&d| d.div_ceil(span) as usize)
                .product();
            self.index[level] = vec![0; cells];
        }
        match self.index[level][at] {
            0 => {
                let e = match self.free.pop() {
                    Some(e) => {
                        self.entries[e as usize] = value;
                        e
                    }
                    None => {
                        self.entries.push(value);
                        (self.entries.len() - 1) as u32
                    }
                };
                self.index[level][at] = e + 1;
            }
            e => self.entries[e as usize - 1] = value,
        }
        true
    }

    pub(super) fn remove(&mut self, key: &(u32, [u32; 3])) -> Option<Coarse> {
        let (level, at) = self.place(*key)?;
        let e = std::mem::take(self.index[level].get_mut(at)?);
        if e == 0 {
            return None;
        }
        let e = e - 1;
        self.free.push(e);
        Some(std::mem::take(&mut self.entries[e as usize]))
    }

    /// Every key held, with its entry (level by level, x fastest; for tests).
    #[cfg(test)]
    pub(super) fn iter(&self) -> impl Iterator<Item = ((u32, [u32; 3]), &Coarse)> {
        self.index.iter().enumerate().flat_map(move |(l, index)| {
            let cells = self.region_dims.map(|d| d.div_ceil(1 << l) as usize);
            index
                .iter()
                .enumerate()
                .filter(|(_, e)| **e != 0)
                .map(move |(at, &e)| {
                    let cell = [
                        at % cells[0],
                        at / cells[0] % cells[1],
                        at / (cells[0] * cells[1]),
                    ];
                    let key = (l as u32 + MIN_STAND_IN_LEVEL, cell.map(|c| c as u32));
                    (key, &self.entries[e as usize - 1])
                })
        })
    }

    /// Every entry held (and freed ones, which hold no slot).
    pub(super) fn values_mut(&mut self) -> impl Iterator<Item = &mut Coarse> {
        self.entries.iter_mut()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    /// Random inserts, removes and lookups agree with a hash map, keys outside the grid
    /// included.
    #[test]
    fn agrees_with_a_hash_map() {
        let dims = [13, 3, 9];
        let mut table = CoarseTable::new(dims);
        let mut model: HashMap<(u32, [u32; 3]), Coarse> = HashMap::new();
        let mut s = 7u64;
        let mut next = |n: u32| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) % u64::from(n)) as u32
        };
        for step in 0..20_000u32 {
            let level = MIN_STAND_IN_LEVEL + next(5);
            let span = 1u32 << (level - MIN_STAND_IN_LEVEL);
            // Up to one cell past the grid on each axis.
            let cell = dims.map(|d| next(d.div_ceil(span) + 1));
            let inside = (0..3).all(|i| cell[i] < dims[i].div_ceil(span));
            let key = (level, cell);
            match next(3) {
                0 => {
                    let value = Coarse {
                        slot: (step % 3 != 0).then_some(step),
                        shown_by: step % 5,
                    };
                    assert_eq!(table.insert(key, value), inside, "{key:?}");
                    if inside {
                        model.insert(key, value);
                    }
                }
                1 => assert_eq!(table.remove(&key), model.remove(&key), "{key:?}"),
                _ => {
                    assert_eq!(table.get(&key), model.get(&key), "{key:?}");
                    if let (Some(t), Some(m)) = (table.get_mut(&key), model.get_mut(&key)) {
                        t.shown_by += 1;
                        m.shown_by += 1;
                    }
                }
            }
            assert_eq!(table.len(), model.len());
        }
        let listed: HashMap<_, _> = table.iter().map(|(k, c)| (k, *c)).collect();
        assert_eq!(listed, model, "iter lists what is held");
        let mut slots: Vec<u32> = table.values_mut().filter_map(|c| c.slot).collect();
        let mut want: Vec<u32> = model.values().filter_map(|c| c.slot).collect();
        slots.sort_unstable();
        want.sort_unstable();
        assert_eq!(slots, want, "freed entries hold no slot");
    }
}
