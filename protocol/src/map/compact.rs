//! Compaction: the map's arrays packed again, without their free slots, blocks and chunks.
//!
//! The arrays only ever grow: a freed brick slot, cell block or colour chunk goes on a free list
//! that later allocations take from first. A map whose contents keep moving (a client's working
//! set following its eye) can so hold more array than it has live data: colour chunks freed in
//! one size class are not reused by bricks of another. [`BrickMap::compact`] writes every live
//! slot, block and chunk again from the start of its array, in order, so the arrays are exactly
//! as long as the live data; what the map shows is unchanged.

use super::stand_in::{region_stand_in, stand_in_entry};
use super::{BrickMap, CELLS_PER_BLOCK, GpuChanges, cell_is_empty, region_block};
use crate::brick::EMPTY;

/// What [`BrickMap::compact`] moved: the new slot of every old one (`None`: it was free).
/// Whoever keeps slots of the map (coarse bricks a client holds) maps them through it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Compacted {
    pub slots: Vec<Option<u32>>,
    /// Array bytes before and after ([`BrickMap::memory`]'s `total_bytes`).
    pub bytes_before: u64,
    pub bytes_after: u64,
}

impl Compacted {
    /// The new slot of `old` (`None` where `old` was free or out of range).
    pub fn slot(&self, old: u32) -> Option<u32> {
        self.slots.get(old as usize).copied().flatten()
    }
}

impl BrickMap {
    /// Array bytes free slots, blocks and chunks take (what [`BrickMap::compact`] would give
    /// back, slack inside live chunks aside).
    pub fn free_bytes(&self) -> u64 {
        let chunks: u64 = self
            .free_chunks
            .iter()
            .enumerate()
            .map(|(cap, list)| cap as u64 * list.len() as u64)
            .sum();
        self.free_slots.len() as u64 * (64 + 4)
            + self.free_blocks.len() as u64 * u64::from(CELLS_PER_BLOCK) * 4
            + chunks * 2
    }

    /// Packs every array: live slots, cell blocks and colour chunks move to the front in their
    /// order, the free lists empty, and the arrays shrink to the live data. Contents, versions,
    /// tombstones and what the map shows stay as they are. When recording GPU changes, every
    /// array is marked changed in full. Returns where each slot went.
    pub fn compact(&mut self) -> Compacted {
        let bytes_before = self.memory().total_bytes;
        // Slots, in order, with their colour blocks packed in the same order.
        let old_slots = self.masks.len();
        let mut slots = vec![None; old_slots];
        let mut masks = Vec::with_capacity(old_slots - self.free_slots.len());
        let mut colour_base = Vec::with_capacity(masks.capacity());
        let mut slot_cell = Vec::with_capacity(masks.capacity());
        let mut slot_version = Vec::with_capacity(masks.capacity());
        let mut slot_capacity = Vec::with_capacity(masks.capacity());
        let mut colours = Vec::new();
        for (s, new) in slots.iter_mut().enumerate() {
            if self.slot_cell[s] == EMPTY {
                continue;
            }
            *new = Some(masks.len() as u32);
            masks.push(self.masks[s]);
            slot_cell.push(self.slot_cell[s]);
            slot_version.push(self.slot_version[s]);
            slot_capacity.push(self.slot_capacity[s]);
            colour_base.push(colours.len() as u32);
            colours.extend_from_slice(self.block(s as u32));
        }
        // Cell blocks, in the order of the regions that point to them; cells name new slots.
        let mut cells = Vec::new();
        let mut block_cells = Vec::new();
        for i in 0..self.regions.len() {
            let entry = self.regions[i];
            if let Some(block) = region_block(entry) {
                let new = block_cells.len() as u32;
                let at = (block * CELLS_PER_BLOCK) as usize;
                cells.extend(
                    self.cells[at..at + CELLS_PER_BLOCK as usize]
                        .iter()
                        .map(|&c| {
                            if cell_is_empty(c) {
                                c
                            } else {
                                slots.get(c as usize).copied().flatten().unwrap_or(c)
                            }
                        }),
                );
                block_cells.push(self.block_cells[block as usize]);
                self.regions[i] = new;
            } else if let Some((level, slot)) = region_stand_in(entry)
                && let Some(new) = slots.get(slot as usize).copied().flatten()
            {
                self.regions[i] = stand_in_entry(level, new);
            }
        }
        self.masks = masks;
        self.colour_base = colour_base;
        self.slot_cell = slot_cell;
        self.slot_version = slot_version;
        self.slot_capacity = slot_capacity;
        self.colours = colours;
        self.cells = cells;
        self.block_cells = block_cells;
        self.free_slots.clear();
        self.free_blocks.clear();
        for list in &mut self.free_chunks {
            list.clear();
        }
        if self.gpu.is_some() {
            self.gpu = Some(GpuChanges {
                regions: (0..self.regions.len() as u32).collect(),
                cell_blocks: (0..self.block_cells.len() as u32).collect(),
                slots: (0..self.masks.len() as u32).collect(),
                colours: vec![(0, self.colours.len() as u32)],
            });
        }
        Compacted {
            slots,
            bytes_before,
            bytes_after: self.memory().total_bytes,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::colour::Colour;
    use crate::map::{BrickMap, BrushMode};

    /// Bricks of every colour count come and go, then the map is packed: it shows the same,
    /// its arrays are the live data alone, and allocation goes on from there.
    #[test]
    fn packing_keeps_what_the_map_shows_and_gives_back_the_free_room() {
        let mut map = BrickMap::new([128, 64, 128]).unwrap();
        map.record_gpu_changes(true);
        for i in 0..40u32 {
            let c = [(i * 37) % 128, (i * 11) % 64, (i * 53) % 128].map(|v| v as f32);
            let mode = if i % 3 == 2 {
                BrushMode::Erase
            } else {
                BrushMode::Fill
            };
            map.sphere(c, 3.0 + (i % 7) as f32, mode, Colour((i * 1999) as u16));
            // Single voxels of many colours give bricks of every coding and chunk class.
            map.set(c.map(|v| v as u32), Colour((i * 7919) as u16));
        }
        map.take_gpu_changes();
        let hash = map.content_hash();
        let free = map.free_bytes();
        assert!(free > 0, "the edits must leave free room to give back");
        let moved = map.compact();
        map.check_invariants().unwrap();
        assert_eq!(map.content_hash(), hash);
        assert_eq!(moved.bytes_after, moved.bytes_before - free);
        assert_eq!(map.free_bytes(), 0);
        let changes = map.take_gpu_changes();
        assert_eq!(changes.slots.len(), map.masks().len());
        assert_eq!(changes.colours, vec![(0, map.colour_pool().len() as u32)]);
        map.sphere([64.0, 32.0, 64.0], 9.0, BrushMode::Fill, Colour(4));
        map.sphere([20.0, 20.0, 20.0], 6.0, BrushMode::Erase, Colour(0));
        map.check_invariants().unwrap();
    }
}
