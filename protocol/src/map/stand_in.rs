//! Coarse bricks standing in for regions a map does not hold at full resolution.
//!
//! A client that cannot hold a whole world holds level 0 near where it looks and coarser levels
//! of the pyramid ([`crate::lod`]) further away. Such a map keeps the one layout both tracers
//! read. A region's entry is one of:
//!
//! * empty (`>= EMPTY_REGION`, with its clearance),
//! * a cell block of level-0 bricks (`< STAND_IN`), as in every map,
//! * a **stand-in** (`STAND_IN | level << 27 | slot`): brick slot `slot` holds the level-`level`
//!   brick of the pyramid that covers the region (`level >= 2`, so a region lies inside one
//!   coarse brick: a level-k brick spans `8·2^k` voxels, a region 32). Its voxels are `2^k`
//!   voxels a side; the region shows the part of it that lies inside the region.
//!
//! Coarse bricks live in the same slot, mask and colour pools as level-0 bricks (so the GPU needs
//! no binding more), in slots marked [`COARSE`] that no cell points to. They are not bricks of the
//! scene: [`BrickMap::bricks`], the counters, versions and tombstones ignore them.
//!
//! What a map with stand-ins shows is exactly what the same map with every stand-in region
//! written out as level-0 voxels (each coarse voxel as a solid cube of `2^k` voxels, clipped to
//! the region) would show: the tracers, ambient occlusion and shadows agree with that "upsampled"
//! map bit for bit (tested in `protocol/tests/stand_ins.rs` and the GPU twin test). The server's
//! maps never hold stand-ins.

use super::{BrickMap, EMPTY_REGION, MapError, REGION_CELLS, REGION_EDGE, region_is_empty};
use crate::brick::{BRICK_EDGE, Mask, mask_get, mask_is_empty, popcount, voxel_bit};
use crate::colour::Colour;

/// Flag of a stand-in region entry.
pub const STAND_IN: u32 = 0x8000_0000;
/// Finest level a stand-in may have: a level-2 brick spans 32 voxels, one region.
pub const MIN_STAND_IN_LEVEL: u32 = 2;
/// Coarsest level a stand-in may have (a 16384-voxel world has levels up to 11); 15 would let an
/// entry reach the empty range.
pub const MAX_STAND_IN_LEVEL: u32 = 14;
/// Where the level sits in a stand-in entry; the slot takes the bits below.
const LEVEL_SHIFT: u32 = 27;
/// Slots a stand-in entry can name.
pub const MAX_STAND_IN_SLOTS: u32 = 1 << LEVEL_SHIFT;
/// `slot_cell` of a slot holding a coarse brick: no cell points to it.
pub(crate) const COARSE: u32 = 0xFFFF_FFFE;

/// The region entry of a stand-in. `level` and `slot` must be in range ([`BrickMap::set_stand_in`]
/// checks them).
#[inline(always)]
pub const fn stand_in_entry(level: u32, slot: u32) -> u32 {
    STAND_IN | (level << LEVEL_SHIFT) | slot
}

/// `(level, slot)` of a stand-in region entry; `None` for an empty or a cell-block entry.
#[inline(always)]
pub const fn region_stand_in(entry: u32) -> Option<(u32, u32)> {
    if entry & STAND_IN != 0 && !region_is_empty(entry) {
        Some((
            (entry >> LEVEL_SHIFT) & 0xF,
            entry & (MAX_STAND_IN_SLOTS - 1),
        ))
    } else {
        None
    }
}

/// The cell block of a region entry: `None` for an empty or a stand-in entry.
#[inline(always)]
pub const fn region_block(entry: u32) -> Option<u32> {
    // Empty entries lie above every stand-in: below the flag is a block.
    if entry < STAND_IN { Some(entry) } else { None }
}

/// The cell of the level-`level` brick that covers region `r` (`level >= 2`): such a brick
/// spans `2^(level-2)` regions a side.
#[inline(always)]
pub fn coarse_cell(r: [u32; 3], level: u32) -> [u32; 3] {
    r.map(|c| c >> (level - MIN_STAND_IN_LEVEL))
}

/// The bit of coarse voxel covering level-0 voxel `p` in a level-`level` brick's mask.
#[inline(always)]
pub fn coarse_bit(p: [u32; 3], level: u32) -> u32 {
    let g = p.map(|c| (c >> level) & (BRICK_EDGE - 1));
    voxel_bit(g[0], g[1], g[2])
}

impl BrickMap {
    /// Stores a coarse brick (mask and colours in bit order, as a level's brick has them) in a
    /// slot of its own for [`BrickMap::set_stand_in`] to point regions at. Returns the slot.
    pub fn add_coarse(&mut self, mask: Mask, colours: &[Colour]) -> Result<u32, MapError> {
        self.add_coarse_as(mask, colours, super::Exact::Smallest)
    }

    /// [`BrickMap::add_coarse`] for a coarse brick whose colour block is at hand (a received
    /// blob hands it out): the block is stored as it is, as [`BrickMap::put_coded`] stores a
    /// level-0 brick's, without choosing and coding a palette again. `block` must decode to
    /// `colours`; a block that names no coding or another length is refused.
    pub fn add_coarse_coded(
        &mut self,
        mask: Mask,
        colours: &[Colour],
        block: &[u16],
    ) -> Result<u32, MapError> {
        match self.given_block(&mask, colours.len(), block) {
            Some(block) => self.add_coarse_as(mask, colours, super::Exact::Given(block)),
            None => Err(MapError::BadCoarseBrick(
                "a coarse brick's colour block does not code its colours",
            )),
        }
    }

    fn add_coarse_as(
        &mut self,
        mask: Mask,
        colours: &[Colour],
        how: super::Exact,
    ) -> Result<u32, MapError> {
        if mask_is_empty(&mask) || popcount(&mask) as usize != colours.len() {
            return Err(MapError::BadCoarseBrick(
                "a coarse brick needs a solid voxel and one colour per solid voxel",
            ));
        }
        if self.free_slots.is_empty() && self.masks.len() as u64 >= u64::from(MAX_STAND_IN_SLOTS) {
            return Err(MapError::BadCoarseBrick(
                "the map has as many brick slots as a stand-in can name",
            ));
        }
        let slot = self.alloc_slot();
        let s = slot as usize;
        self.masks[s] = mask;
        self.slot_capacity[s] = 0;
        self.store_colours_as(slot, colours, how);
        self.slot_cell[s] = COARSE;
        self.slot_version[s] = 0;
        self.mark_slot(slot);
        Ok(slot)
    }

    /// Frees a coarse brick's slot. The caller points no region at it any more (a region that
    /// still did would show whatever the slot holds next).
    pub fn remove_coarse(&mut self, slot: u32) -> Result<(), MapError> {
        if self.slot_cell.get(slot as usize) != Some(&COARSE) {
            return Err(MapError::BadCoarseBrick("no coarse brick in that slot"));
        }
        let s = slot as usize;
        self.coded_words -= self.block_words(slot) as u64;
        self.free_chunk(self.colour_base[s], u32::from(self.slot_capacity[s]));
        self.masks[s] = crate::brick::EMPTY_MASK;
        self.slot_cell[s] = crate::brick::EMPTY;
        self.slot_capacity[s] = 0;
        self.free_slots.push(slot);
        self.mark_slot(slot);
        Ok(())
    }

    /// Makes region `region` show the level-`level` coarse brick in `slot` (`Some((level,
    /// slot))`), or nothing (`None`). The region must hold no level-0 brick: a map holds a region
    /// at one level. Refused (nothing changed) for a region outside the grid, a level outside
    /// [`MIN_STAND_IN_LEVEL`]`..=`[`MAX_STAND_IN_LEVEL`] or a slot without a coarse brick.
    pub fn set_stand_in(
        &mut self,
        region: [u32; 3],
        stand_in: Option<(u32, u32)>,
    ) -> Result<(), MapError> {
        if (0..3).any(|i| region[i] >= self.region_dims[i]) {
            return Err(MapError::BadCoarseBrick("region outside the grid"));
        }
        if let Some((level, slot)) = stand_in {
            if !(MIN_STAND_IN_LEVEL..=MAX_STAND_IN_LEVEL).contains(&level) {
                return Err(MapError::BadCoarseBrick("stand-in level out of range"));
            }
            if self.slot_cell.get(slot as usize) != Some(&COARSE) {
                return Err(MapError::BadCoarseBrick("no coarse brick in that slot"));
            }
        }
        let index = self.region_index(region);
        let old = self.regions[index];
        if region_block(old).is_some() {
            return Err(MapError::RegionHoldsBricks(region));
        }
        let was = region_stand_in(old).is_some();
        match stand_in {
            Some((level, slot)) => {
                self.regions[index] = stand_in_entry(level, slot);
                if !was {
                    self.stand_ins += 1;
                    self.occupy_region(region);
                    self.lower_clearance_for(region);
                }
            }
            None => {
                if !was {
                    return Ok(());
                }
                // Clearance 0 is always safe; neighbours keep theirs (still conservative).
                self.regions[index] = EMPTY_REGION;
                self.stand_ins -= 1;
            }
        }
        if let Some(g) = &mut self.gpu {
            g.regions.push(index as u32);
        }
        // Cell clearance of the level-0 regions around counts a stand-in's cells as occupied.
        self.rebuild_cell_clearance_around(region);
        Ok(())
    }

    /// The stand-in of a region, `(level, slot)`; `None` for a region outside the grid or not
    /// standing in.
    pub fn stand_in(&self, region: [u32; 3]) -> Option<(u32, u32)> {
        if (0..3).any(|i| region[i] >= self.region_dims[i]) {
            return None;
        }
        region_stand_in(self.regions[self.region_index(region)])
    }

    /// Regions shown by a stand-in.
    pub fn stand_in_count(&self) -> u64 {
        self.stand_ins
    }

    /// Whether a voxel looks solid: its level-0 brick's bit, or in a stand-in region the bit of
    /// the coarse voxel covering it. False outside the grid. On a map without stand-ins, the same
    /// as [`BrickMap::is_solid`].
    pub fn looks_solid(&self, pos: [i32; 3]) -> bool {
        if (0..3).any(|i| pos[i] < 0 || pos[i] as u32 >= self.size[i]) {
            return false;
        }
        let p = pos.map(|c| c as u32);
        let entry = self.regions[self.region_index(p.map(|c| c / REGION_EDGE))];
        if let Some((level, slot)) = region_stand_in(entry) {
            return mask_get(&self.masks[slot as usize], coarse_bit(p, level));
        }
        self.is_solid(p)
    }

    /// Grows the occupied box by `region`.
    pub(super) fn occupy_region(&mut self, r: [u32; 3]) {
        self.occupied = Some(match self.occupied {
            None => (r, r),
            Some((lo, hi)) => (
                std::array::from_fn(|i| lo[i].min(r[i])),
                std::array::from_fn(|i| hi[i].max(r[i])),
            ),
        });
    }

    /// Recomputes the cell clearance of the level-0 regions next to `region` (and its own).
    fn rebuild_cell_clearance_around(&mut self, region: [u32; 3]) {
        let r = region.map(i64::from);
        let dims = self.region_dims.map(i64::from);
        let mut around = Vec::with_capacity(27);
        for z in (r[2] - 1).max(0)..=(r[2] + 1).min(dims[2] - 1) {
            for y in (r[1] - 1).max(0)..=(r[1] + 1).min(dims[1] - 1) {
                for x in (r[0] - 1).max(0)..=(r[0] + 1).min(dims[0] - 1) {
                    around.push(self.region_index([x as u32, y as u32, z as u32]));
                }
            }
        }
        self.rebuild_cell_clearance_in(around);
    }
}

// A stand-in's cells, as the cell level sees them: all occupied.
const _: () = assert!(REGION_CELLS == 4 && REGION_EDGE == 32);
