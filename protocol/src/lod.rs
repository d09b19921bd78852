//! Levels of detail: a mip pyramid of the brick map, for clients that hold a world far larger
//! than their memory (issue #30).
//!
//! Level 0 is the scene itself. A level-k map is an ordinary [`BrickMap`] of `⌈size / 2^k⌉`
//! voxels a side, so its bricks have the same layout, coding, versions and wire form as level
//! 0's, and every tracer and sync path that reads a map reads a level; a level-k brick covers
//! `8·2^k` scene voxels a side with voxels `2^k` wide.
//!
//! **The rule** (one home, [`coarsen`]): a level-k voxel is solid when any of the 2×2×2 level-(k−1)
//! voxels it covers is solid, and its colour is the most frequent colour among those solid
//! children, the smallest RGB565 value on a tie. A mode, not a mean: a coarse brick holds only
//! colours of the scene (no new shades widen its palette, so coarse bricks code as small as
//! the fine ones), and a level is a pure function of the level below, so updating the bricks
//! an edit touched gives exactly what a rebuild gives (tested).
//!
//! **Incremental**: [`Pyramid::update`] takes the level-0 cells an edit batch touched, recomputes
//! only their parents, and climbs only where a parent changed; a paint that does not change a
//! mode stops at level 1. Bricks are stamped with the level-0 map's sequence, so a level's
//! `changes_since` works as level 0's does.

use crate::brick::{
    BRICK_EDGE, BRICK_VOXELS, BrickData, EMPTY_MASK, bit_voxel, for_each_bit, mask_get, mask_set,
    popcount, voxel_bit,
};
use crate::colour::Colour;
use std::collections::HashMap;

use crate::map::{BrickMap, MIN_STAND_IN_LEVEL, MapError, box_points, coarse_cell};

/// Levels above 0 for a scene of `size` voxels: until every axis of the top level fits one
/// brick (a 16384×512×16384 world has 11; a scene of at most 8 voxels a side has none).
pub fn level_count(size: [u32; 3]) -> u32 {
    let longest = size.into_iter().max().unwrap_or(1);
    let mut levels = 0;
    while longest.div_ceil(1 << levels) > BRICK_EDGE {
        levels += 1;
    }
    levels
}

/// Voxels a side of level `k` of a scene of `size` voxels.
pub fn level_size(size: [u32; 3], k: u32) -> [u32; 3] {
    size.map(|s| s.div_ceil(1 << k))
}

/// Room [`coarsen`] reuses between calls: each parent voxel's children's colours (at most
/// eight), gathered by position instead of sorted (a level of a 16k world gathers ~1.6 G voxels).
pub struct Scratch {
    children: Box<[[u16; 8]; BRICK_VOXELS as usize]>,
    counts: Box<[u8; BRICK_VOXELS as usize]>,
    colours: Box<[Colour; BRICK_VOXELS as usize]>,
}

impl Default for Scratch {
    fn default() -> Scratch {
        Scratch {
            children: Box::new([[0; 8]; BRICK_VOXELS as usize]),
            counts: Box::new([0; BRICK_VOXELS as usize]),
            colours: Box::new([Colour::BLACK; BRICK_VOXELS as usize]),
        }
    }
}

/// For each bit of a child brick, the bit of the parent voxel covering it when the child is
/// the parent's first (offset 0,0,0); another child adds its offset's [`child_base`].
const PARENT_BIT: [u16; BRICK_VOXELS as usize] = {
    let mut table = [0u16; BRICK_VOXELS as usize];
    let mut bit = 0;
    while bit < BRICK_VOXELS {
        let v = bit_voxel(bit);
        table[bit as usize] = voxel_bit(v[0] / 2, v[1] / 2, v[2] / 2) as u16;
        bit += 1;
    }
    table
};

/// The parent bit of a child's voxel 0 for the child at `offset` (each 0 or 1) of its parent.
const fn child_base(offset: [u32; 3]) -> u32 {
    voxel_bit(offset[0] * 4, offset[1] * 4, offset[2] * 4)
}

/// The most frequent of `values` (one to eight), the smallest on a tie. Most coarse voxels'
/// children share one colour; the rest are counted pairwise (at most 64 comparisons, no sort).
fn mode(values: &[u16]) -> u16 {
    let first = values[0];
    if values.iter().all(|&v| v == first) {
        return first;
    }
    let (mut best, mut best_count) = (first, 0);
    for &v in values {
        let count = values.iter().filter(|&&w| w == v).count();
        if count > best_count || (count == best_count && v < best) {
            (best, best_count) = (v, count);
        }
    }
    best
}

/// The level-k brick at `cell`, made from `below` (level k−1) by the rule in the module doc;
/// `None` where all eight child bricks are empty. `scratch` is reused between calls.
pub fn coarsen(below: &BrickMap, cell: [u32; 3], scratch: &mut Scratch) -> Option<BrickData> {
    let Scratch {
        children,
        counts,
        colours,
    } = scratch;
    let mut mask = EMPTY_MASK;
    for o in 0..8u32 {
        let offset = [o & 1, (o >> 1) & 1, o >> 2];
        let child = std::array::from_fn(|a| cell[a] * 2 + offset[a]);
        let Some(slot) = below.slot_of_cell(child) else {
            continue;
        };
        let child_mask = below.masks()[slot as usize];
        let solid = below.slot_colours(slot, colours);
        let base = child_base(offset);
        let mut i = 0;
        for_each_bit(&child_mask, |bit| {
            let parent = (base + u32::from(PARENT_BIT[bit as usize])) as usize;
            let n = if mask_get(&mask, parent as u32) {
                counts[parent]
            } else {
                mask_set(&mut mask, parent as u32, true);
                0
            };
            children[parent][n as usize] = solid[i].0;
            counts[parent] = n + 1;
            i += 1;
        });
    }
    if mask == EMPTY_MASK {
        return None;
    }
    let mut brick = BrickData {
        cell,
        mask,
        colours: Vec::with_capacity(popcount(&mask) as usize),
    };
    for_each_bit(&mask, |parent| {
        let p = parent as usize;
        brick
            .colours
            .push(Colour(mode(&children[p][..counts[p] as usize])));
    });
    Some(brick)
}

/// Levels 1 and up of a scene, kept current by [`Pyramid::update`].
#[derive(Clone)]
pub struct Pyramid {
    /// `levels[k - 1]` is level k.
    levels: Vec<BrickMap>,
}

/// What one [`Pyramid::update`] changed: per level (index 0 is level 1), the linear cell indices
/// of that level's bricks that changed (written or removed), ascending. Empty levels above the
/// last change are left out.
pub type Changed = Vec<Vec<u32>>;

impl Pyramid {
    /// Every level of `base`, from scratch.
    pub fn build(base: &BrickMap) -> Result<Pyramid, MapError> {
        let mut pyramid = Pyramid::empty(base.size())?;
        let cells: Vec<u32> = base
            .brick_cells()
            .map(|(cell, _)| base.cell_index(cell))
            .collect();
        pyramid.update(base, &cells)?;
        Ok(pyramid)
    }

    /// A pyramid with empty levels for a scene of `size` voxels.
    pub fn empty(size: [u32; 3]) -> Result<Pyramid, MapError> {
        let levels = (1..=level_count(size))
            .map(|k| BrickMap::new(level_size(size, k)))
            .collect::<Result<_, _>>()?;
        Ok(Pyramid { levels })
    }

    fn take_palette(&mut self, base: &BrickMap) {
        for level in &mut self.levels {
            level.set_swatches(*base.swatches());
        }
    }

    /// Levels above 0.
    pub fn level_count(&self) -> u32 {
        self.levels.len() as u32
    }

    /// Level `k` (1 ..= [`Pyramid::level_count`]).
    pub fn level(&self, k: u32) -> Option<&BrickMap> {
        self.levels.get((k as usize).checked_sub(1)?)
    }

    /// A map showing each region of `base` (32³ voxels) at the level `level_of(region)` picks:
    /// 0 holds the region's level-0 bricks, `2..=`[`Pyramid::level_count`] shows the part of
    /// that level's brick covering it as a stand-in ([`crate::map::stand_in`]); one coarse brick
    /// serves every region it covers. What a client holding a working set of mixed levels holds.
    /// `self` must be `base`'s pyramid, current. Level 1 and levels past the top are refused.
    pub fn mixed(
        &self,
        base: &BrickMap,
        mut level_of: impl FnMut([u32; 3]) -> u32,
    ) -> Result<BrickMap, MapError> {
        let mut map = BrickMap::new(base.size())?;
        map.set_swatches(*base.swatches());
        let mut coarse: HashMap<(u32, [u32; 3]), Option<u32>> = HashMap::new();
        for r in box_points([0; 3], base.region_dims()) {
            let k = level_of(r);
            if k == 0 {
                for cell in base.region_cells(r) {
                    if let (Some(slot), Some(b)) = (base.slot_of_cell(cell), base.brick(cell)) {
                        // Coded as the base has it, as the wire carries it.
                        map.put_coded(cell, b.mask, &b.colours, base.block(slot))?;
                    }
                }
                continue;
            }
            let level = self
                .level(k)
                .filter(|_| k >= MIN_STAND_IN_LEVEL)
                .ok_or(MapError::BadCoarseBrick("no such level for a stand-in"))?;
            let cell = coarse_cell(r, k);
            let slot = match coarse.get(&(k, cell)) {
                Some(&slot) => slot,
                None => {
                    let slot = match level.brick(cell) {
                        Some(b) => Some(map.add_coarse(b.mask, &b.colours)?),
                        None => None,
                    };
                    coarse.insert((k, cell), slot);
                    slot
                }
            };
            if let Some(slot) = slot {
                map.set_stand_in(r, Some((k, slot)))?;
            }
        }
        map.rebuild_clearance();
        Ok(map)
    }

    /// Brings every level up to date after the level-0 cells `touched` (linear indices in
    /// `base`, as [`BrickMap::take_touched`] gives them, in any order, repeats allowed) changed.
    /// Each level is stamped with `base`'s sequence and takes its palette (scene state every
    /// view of the scene shows). Returns what changed, level by level.
    pub fn update(&mut self, base: &BrickMap, touched: &[u32]) -> Result<Changed, MapError> {
        self.take_palette(base);
        let mut changed = Changed::new();
        let mut below_cells: Vec<[u32; 3]> = touched.iter().map(|&i| base.cell_coords(i)).collect();
        for k in 1..=self.level_count() {
            if below_cells.is_empty() {
                break;
            }
            let (level_changed, cells) = self.refresh(base, k, &below_cells)?;
            below_cells = cells;
            changed.push(level_changed);
        }
        Ok(changed)
    }

    /// Recomputes the level-`k` parents of the level-(k−1) cells `below` (linear indices in
    /// level k−1, `base` for k = 1) from level k−1 as it is, without climbing further: one
    /// part of a build level by level, each level from the finished one below (what a build
    /// spread over an owner's turns does, so upper levels are not recomputed once per part).
    /// Stamped with `base`'s sequence.
    pub fn fold(&mut self, base: &BrickMap, k: u32, below: &[u32]) -> Result<(), MapError> {
        if k == 0 || k > self.level_count() {
            return Ok(());
        }
        self.take_palette(base);
        let below_map = if k == 1 {
            base
        } else {
            &self.levels[k as usize - 2]
        };
        let cells: Vec<[u32; 3]> = below.iter().map(|&i| below_map.cell_coords(i)).collect();
        self.refresh(base, k, &cells).map(|_| ())
    }

    /// Level `k` (1 ..= count) brought up to date for the level-(k−1) cells `below_cells`:
    /// the linear cells of level k that changed, ascending, and their coordinates.
    fn refresh(
        &mut self,
        base: &BrickMap,
        k: u32,
        below_cells: &[[u32; 3]],
    ) -> Result<(Vec<u32>, Vec<[u32; 3]>), MapError> {
        let (done, rest) = self.levels.split_at_mut(k as usize - 1);
        let below = done.last().unwrap_or(base);
        let level = &mut rest[0];
        level.set_sequence(base.sequence().max(level.sequence()));
        let mut parents: Vec<u32> = below_cells
            .iter()
            .map(|c| level.cell_index(c.map(|v| v / 2)))
            .collect();
        parents.sort_unstable();
        parents.dedup();
        let (mut level_changed, mut cells) = (Vec::new(), Vec::new());
        // In windows, so a rebuild holds a window's new bricks at a time, not a level's.
        for window in parents.chunks(WINDOW) {
            let computed = recompute(below, level, window);
            for (&index, new) in window.iter().zip(computed) {
                let Some(new) = new else {
                    continue;
                };
                let cell = level.cell_coords(index);
                match new {
                    Some(brick) => level.put_brick(&brick)?,
                    None => {
                        level.remove_brick(cell);
                    }
                }
                level_changed.push(index);
                cells.push(cell);
            }
        }
        Ok((level_changed, cells))
    }

    /// Drops every level's tombstones at or below `sequence` ([`BrickMap::prune_tombstones`]).
    pub fn prune_tombstones(&mut self, sequence: u64) {
        for level in &mut self.levels {
            level.prune_tombstones(sequence);
        }
    }

    /// Bricks in all levels above 0.
    pub fn brick_count(&self) -> u64 {
        self.levels.iter().map(BrickMap::brick_count).sum()
    }
}

/// Parents recomputed before their bricks are written.
const WINDOW: usize = 1 << 16;

/// Parents per thread below which [`recompute`] stays on the calling thread (a thousand
/// parents are a few milliseconds of work; a build part of 32,768 slots has ~7,000).
const PARALLEL_PARENTS: usize = 1024;

/// For each of `parents` (linear cells of `level`): `None` where [`coarsen`] gives what `level`
/// holds, else `Some(the new brick or None for empty)`. Read-only, so large sets are cut into
/// runs computed on one thread per core, results kept in order.
fn recompute(
    below: &BrickMap,
    level: &BrickMap,
    parents: &[u32],
) -> Vec<Option<Option<BrickData>>> {
    let run = |cells: &[u32]| {
        let mut scratch = Scratch::default();
        cells
            .iter()
            .map(|&index| {
                let cell = level.cell_coords(index);
                let new = coarsen(below, cell, &mut scratch);
                let same = match (&new, level.brick(cell)) {
                    (Some(new), Some(old)) => new.mask == old.mask && new.colours == old.colours,
                    (None, None) => true,
                    _ => false,
                };
                (!same).then_some(new)
            })
            .collect::<Vec<_>>()
    };
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(parents.len() / PARALLEL_PARENTS)
        .max(1);
    if threads == 1 {
        return run(parents);
    }
    let run = &run;
    std::thread::scope(|scope| {
        let handles: Vec<_> = parents
            .chunks(parents.len().div_ceil(threads))
            .map(|chunk| {
                (
                    chunk,
                    std::thread::Builder::new()
                        .spawn_scoped(scope, move || run(chunk))
                        .ok(),
                )
            })
            .collect();
        let mut out = Vec::with_capacity(parents.len());
        for (chunk, handle) in handles {
            match handle.map(|h| h.join()) {
                Some(Ok(part)) => out.extend(part),
                Some(Err(panic)) => std::panic::resume_unwind(panic),
                // A thread that could not start: its run is done here.
                None => out.extend(run(chunk)),
            }
        }
        out
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_counts_reach_one_brick() {
        assert_eq!(level_count([8, 8, 8]), 0);
        assert_eq!(level_count([9, 1, 1]), 1);
        assert_eq!(level_count([64, 64, 64]), 3);
        assert_eq!(level_count([16384, 512, 16384]), 11);
        assert_eq!(level_size([100, 3, 64], 2), [25, 1, 16]);
    }

    #[test]
    fn a_coarse_voxel_is_solid_if_any_child_is_and_takes_the_mode() {
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        // Coarse voxel (0,0,0) of level 1 covers (0..2)³: three red, two blue, one green.
        let (red, blue, green) = (Colour(0xF800), Colour(0x001F), Colour(0x07E0));
        for (p, c) in [
            ([0, 0, 0], blue),
            ([1, 0, 0], red),
            ([0, 1, 0], red),
            ([1, 1, 0], blue),
            ([0, 0, 1], green),
            ([1, 1, 1], red),
        ] {
            map.set(p, c);
        }
        // A tie (one each) takes the smaller value; a lone voxel far away makes its own voxel.
        map.set([16, 16, 16], red);
        map.set([17, 16, 16], blue);
        map.set([31, 31, 31], green);
        let pyramid = Pyramid::build(&map).unwrap();
        let one = pyramid.level(1).unwrap();
        assert_eq!(one.size(), [16, 16, 16]);
        assert_eq!(one.get([0, 0, 0]), Some(red));
        assert_eq!(one.get([8, 8, 8]), Some(blue));
        assert_eq!(one.get([15, 15, 15]), Some(green));
        assert_eq!(one.solid_voxels(), 3);
        let two = pyramid.level(2).unwrap();
        assert_eq!(two.get([0, 0, 0]), Some(red));
        assert_eq!(two.solid_voxels(), 3);
        assert!(pyramid.level(3).is_none() && pyramid.level(0).is_none());
        assert_eq!(pyramid.level_count(), 2);
    }

    #[test]
    fn parents_computed_on_several_threads_come_back_in_order() {
        // 65,536 bricks under 16,384 level-1 parents: enough for one run per core.
        let mut map = BrickMap::new([2048, 8, 2048]).unwrap();
        let mut rng = Lcg(9);
        for z in 0..256 {
            for x in 0..256 {
                let mut mask = EMPTY_MASK;
                for _ in 0..1 + rng.next(40) {
                    mask_set(&mut mask, rng.next(512), true);
                }
                let colours = (0..popcount(&mask))
                    .map(|_| Colour(rng.next(6) as u16 * 0x0841))
                    .collect();
                let brick = BrickData {
                    cell: [x, 0, z],
                    mask,
                    colours,
                };
                map.put_brick(&brick).unwrap();
            }
        }
        let level = BrickMap::new(level_size(map.size(), 1)).unwrap();
        let parents: Vec<u32> = (0..128 * 128).collect();
        let mut scratch = Scratch::default();
        let one_by_one: Vec<_> = parents
            .iter()
            .map(|&i| Some(coarsen(&map, level.cell_coords(i), &mut scratch)))
            .collect();
        assert!(one_by_one.iter().all(|b| matches!(b, Some(Some(_)))));
        assert_eq!(recompute(&map, &level, &parents), one_by_one);
    }

    #[test]
    fn odd_sizes_keep_every_coarse_voxel_inside_its_level() {
        let mut map = BrickMap::new([37, 9, 21]).unwrap();
        for p in [[36, 8, 20], [0, 0, 0], [35, 1, 19]] {
            map.set(p, Colour::WHITE);
        }
        let pyramid = Pyramid::build(&map).unwrap();
        for k in 1..=pyramid.level_count() {
            let level = pyramid.level(k).unwrap();
            level.check_invariants().unwrap();
            let top = level_size([37, 9, 21], k).map(|s| s - 1);
            assert!(level.is_solid(top), "level {k}: {top:?}");
        }
    }

    /// A small deterministic generator: the property test below needs no crate.
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self, n: u32) -> u32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 33) % u64::from(n)) as u32
        }
    }

    fn same_bricks(a: &BrickMap, b: &BrickMap) -> Result<(), String> {
        let sorted = |m: &BrickMap| {
            let mut v: Vec<_> = m.bricks().map(|(b, _)| b).collect();
            v.sort_by_key(|b| m.cell_index(b.cell));
            v
        };
        let (x, y) = (sorted(a), sorted(b));
        if x.len() != y.len() {
            return Err(format!("{} bricks vs {}", x.len(), y.len()));
        }
        for (p, q) in x.iter().zip(&y) {
            if p != q {
                return Err(format!("brick {:?} differs from {:?}", p.cell, q.cell));
            }
        }
        Ok(())
    }

    #[test]
    fn updating_after_random_edits_equals_a_rebuild() {
        for seed in 0..24u64 {
            let mut rng = Lcg(seed);
            let size = [40 + rng.next(60), 8 + rng.next(40), 40 + rng.next(60)];
            let mut map = BrickMap::new(size).unwrap();
            map.record_touched(true);
            let palette = [0xF800, 0x07E0, 0x001F, 0xFFFF, 0x1234].map(Colour);
            let mut pyramid = Pyramid::empty(size).unwrap();
            for round in 0..12u64 {
                map.set_sequence(round + 1);
                for _ in 0..1 + rng.next(6) {
                    let centre = size.map(|s| rng.next(s) as f32);
                    let radius = 1.0 + rng.next(6) as f32;
                    let colour = palette[rng.next(5) as usize];
                    match rng.next(4) {
                        0 => {
                            map.sphere(centre, radius, crate::map::BrushMode::Erase, colour);
                        }
                        1 => {
                            map.sphere(centre, radius, crate::map::BrushMode::Paint, colour);
                        }
                        2 => {
                            map.set(centre.map(|c| c as u32), colour);
                        }
                        _ => {
                            map.sphere(centre, radius, crate::map::BrushMode::Fill, colour);
                        }
                    }
                }
                let touched = map.take_touched();
                let changed = pyramid.update(&map, &touched).unwrap();
                let fresh = Pyramid::build(&map).unwrap();
                assert_eq!(pyramid.level_count(), fresh.level_count());
                for k in 1..=fresh.level_count() {
                    let (kept, built) = (pyramid.level(k).unwrap(), fresh.level(k).unwrap());
                    if let Err(e) = same_bricks(kept, built) {
                        panic!("seed {seed} round {round} level {k}: {e}");
                    }
                    kept.check_invariants().unwrap();
                    // Whatever changed carries this round's stamp; nothing else does.
                    for &index in changed.get(k as usize - 1).into_iter().flatten() {
                        let cell = kept.cell_coords(index);
                        if let Some(v) = kept.brick_version(cell) {
                            assert_eq!(v, round + 1);
                        }
                    }
                }
                // Level 1 agrees with the rule applied voxel by voxel: solid if any child is,
                // the most frequent child colour, the smallest on a tie (counted, not sorted).
                let one = pyramid.level(1).unwrap();
                for (brick, _) in one.bricks() {
                    for bit in 0..512 {
                        let v = bit_voxel(bit);
                        let p: [u32; 3] = std::array::from_fn(|a| (brick.cell[a] * 8 + v[a]) * 2);
                        let children: Vec<Colour> = (0..8u32)
                            .filter_map(|o| {
                                map.get([p[0] + (o & 1), p[1] + ((o >> 1) & 1), p[2] + (o >> 2)])
                            })
                            .collect();
                        assert_eq!(mask_get(&brick.mask, bit), !children.is_empty());
                        let count = |c: &Colour| children.iter().filter(|&d| d == c).count();
                        let want = children
                            .iter()
                            .copied()
                            .max_by(|a, b| count(a).cmp(&count(b)).then(b.0.cmp(&a.0)));
                        let got = one.get(std::array::from_fn(|a| brick.cell[a] * 8 + v[a]));
                        assert_eq!(
                            got, want,
                            "seed {seed} round {round} voxel {bit} of {:?}",
                            brick.cell
                        );
                    }
                    assert_eq!(brick.colours.len(), popcount(&brick.mask) as usize);
                }
            }
        }
    }
}
