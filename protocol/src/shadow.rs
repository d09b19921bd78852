//! Shadow rays that start with a table instead of a DDA.
//!
//! Why: a shadow ray starts at the centre of the empty voxel in front of a hit and goes towards
//! the sun, and most of its cost is the first few bricks, where it climbs out of the surface
//! voxel by voxel and changes levels often. Every shadow ray of a frame has the same direction
//! and starts at a voxel centre, so they all cross the *same* voxels relative to their start:
//! a plane time is `(plane − origin) · (1/d)`, and `plane − origin` is an integer plus one half,
//! exact in `f32` below 2^23, whatever the start voxel. So the flat DDA's walk from a voxel
//! centre is computed once per frame ([`SunPaths::new`]), for each of the 512 places a start can
//! have inside its brick, as a few (brick offset, 512-bit mask) pairs. A shadow ray then tests
//! those masks against the map's bricks, one `and` per brick, and only the rest of the ray
//! (past [`REACH`]) is traced, starting there ([`crate::trace::trace_from`]'s promise holds:
//! every voxel before it was tested). The answer is the plain trace's, bit for bit.

use std::sync::{Arc, Mutex};

use crate::brick::{BRICK_EDGE, EMPTY_MASK, Mask, mask_set, voxel_bit};
use crate::map::{BrickMap, REGION_CELLS};
use crate::trace::{Ray, TraceStats, trace_pending};

/// How far (in ray parameter, voxels for a unit direction) the table covers; the DDA takes over
/// past it. On the 1024³ demo scene, reaches of 24, 96 and 192 made shadow rays cost about
/// 0.75, 0.6 and 0.5 of a traced ray; the table is then about 0.7 MiB and takes about 1 ms
/// to build, once per sun direction ([`SunPaths::shared`]).
pub const REACH: f32 = 192.0;

/// Start voxels are placed this far inside the grid the walks are computed in, so a walk of
/// [`REACH`] never meets its edge.
const WALK_ORIGIN: i32 = 512;

/// The voxels a shadow ray towards one sun direction crosses, from every start place in a brick.
#[derive(Debug, Clone)]
pub struct SunPaths {
    dir: [f32; 3],
    /// For each start bit in its brick: the range of `bricks` its walk covers.
    ranges: Vec<(u32, u32)>,
    /// Brick offsets from the start voxel's brick, and the walk's voxels in that brick.
    bricks: Vec<([i32; 3], Mask)>,
}

impl SunPaths {
    /// The walks for rays with direction `dir` (the sun as [`crate::Lighting::sun`] has it).
    pub fn new(dir: [f32; 3]) -> SunPaths {
        let e = BRICK_EDGE as i32;
        // One walk serves every start: its voxels relative to the start voxel.
        let size = [(2 * WALK_ORIGIN) as u32; 3];
        let ray = Ray {
            origin: [WALK_ORIGIN as f32 + 0.5; 3],
            dir,
        };
        let mut walk = Vec::new();
        crate::trace::voxel_walk(size, &ray, REACH, |v, _| {
            walk.push(v.map(|c| c - WALK_ORIGIN))
        });
        let mut ranges = Vec::with_capacity(512);
        let mut bricks: Vec<([i32; 3], Mask)> = Vec::new();
        for bit in 0..512u32 {
            let local = crate::brick::bit_voxel(bit).map(|c| c as i32);
            let first = bricks.len();
            for step in &walk {
                // Where this voxel is relative to the start's brick, and its bit there. A walk
                // moves one way on each axis, so it never comes back to a brick it left.
                let rel: [i32; 3] = std::array::from_fn(|i| step[i] + local[i]);
                let brick = rel.map(|c| c.div_euclid(e));
                let l = rel.map(|c| c.rem_euclid(e) as u32);
                if bricks.len() == first || bricks[bricks.len() - 1].0 != brick {
                    bricks.push((brick, EMPTY_MASK));
                }
                let last = bricks.len() - 1;
                mask_set(&mut bricks[last].1, voxel_bit(l[0], l[1], l[2]), true);
            }
            ranges.push((first as u32, bricks.len() as u32));
        }
        SunPaths {
            dir,
            ranges,
            bricks,
        }
    }

    /// The table for `dir`, built once and shared while the sun does not move: a viewer asks
    /// for it every frame, and building it costs about as much as a few thousand shadow rays.
    pub fn shared(dir: [f32; 3]) -> Arc<SunPaths> {
        static LAST: Mutex<Option<Arc<SunPaths>>> = Mutex::new(None);
        let mut last = LAST.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        match &*last {
            Some(paths) if paths.dir == dir => paths.clone(),
            _ => {
                let paths = Arc::new(SunPaths::new(dir));
                *last = Some(paths.clone());
                paths
            }
        }
    }

    /// The direction these walks are for.
    pub fn dir(&self) -> [f32; 3] {
        self.dir
    }

    /// Whether the ray from the centre of voxel `from` along the sun direction meets a solid
    /// voxel: exactly `crate::trace::blocked` of that ray.
    pub fn blocked(&self, map: &BrickMap, from: [i32; 3]) -> bool {
        let ray = Ray {
            origin: from.map(|c| c as f32 + 0.5),
            dir: self.dir,
        };
        let size = map.size();
        let inside = (0..3).all(|i| from[i] >= 0 && (from[i] as u32) < size[i]);
        // The table reads level-0 bricks only: where coarse bricks stand in for regions, the
        // plain trace answers (the same answer).
        if !inside || map.stand_in_count() > 0 {
            // A start outside the grid (a hit on the grid's face): the plain trace.
            return crate::trace::blocked(map, &ray);
        }
        let e = BRICK_EDGE as i32;
        let local = from.map(|c| (c % e) as u32);
        let (first, end) = self.ranges[voxel_bit(local[0], local[1], local[2]) as usize];
        let home = from.map(|c| c / e);
        let masks = map.masks();
        // Cells outside the occupied regions' box hold nothing: skipped without a lookup.
        let Some((rlo, rhi)) = map.occupied_regions() else {
            return false;
        };
        let rc = REGION_CELLS as i32;
        let clo = rlo.map(|r| r as i32 * rc);
        let chi = rhi.map(|r| r as i32 * rc + rc - 1);
        for (offset, path) in &self.bricks[first as usize..end as usize] {
            let cell: [i32; 3] = std::array::from_fn(|i| home[i] + offset[i]);
            if (0..3).any(|i| cell[i] < clo[i] || cell[i] > chi[i]) {
                // Past the box on an axis the walk does not come back on: nothing is left.
                if (0..3).any(|i| {
                    (cell[i] > chi[i] && self.dir[i] >= 0.0)
                        || (cell[i] < clo[i] && self.dir[i] <= 0.0)
                }) {
                    return false;
                }
                continue;
            }
            // Inside the occupied box means inside the grid. Voxels past the grid's edge are
            // never solid (no brick holds them), so the walk may run past it where the DDA
            // would have stopped.
            let Some(slot) = map.slot_of_cell(cell.map(|c| c as u32)) else {
                continue;
            };
            let mask = &masks[slot as usize];
            if (0..8).any(|w| mask[w] & path[w] != 0) {
                return true;
            }
        }
        trace_pending(map, &ray, REACH, &mut TraceStats::default()).is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::map::BrushMode;

    /// The table's answer is the plain trace's for starts everywhere in a scene with surfaces
    /// at every distance, for sun directions of every kind (axis-parallel, diagonal, low, with
    /// negative components), including starts next to the grid's faces.
    #[test]
    fn table_agrees_with_tracing() {
        let mut map = BrickMap::new([70, 60, 66]).unwrap();
        map.fill_box([0, 0, 0], [69, 4, 65], BrushMode::Fill, Colour::WHITE);
        map.sphere([30.0, 20.0, 30.0], 9.0, BrushMode::Fill, Colour(5));
        map.fill_box([50, 5, 10], [52, 40, 12], BrushMode::Fill, Colour(9));
        map.fill_box([5, 30, 40], [25, 31, 60], BrushMode::Fill, Colour(9));
        for v in [[12, 9, 9], [40, 50, 50], [64, 20, 3], [1, 58, 64]] {
            map.set(v, Colour(3));
        }
        let dirs = [
            [0.5f32, 0.8, 0.25],
            [0.0, 1.0, 0.0],
            [1.0, 1.0, 1.0],
            [-0.3, 0.9, 0.1],
            [0.9, 0.1, -0.4],
            [-0.5, 0.5, -0.5],
            [0.2, -0.1, 0.97],
        ];
        let mut blocked = 0;
        let mut checked = 0;
        for dir in dirs {
            let paths = SunPaths::new(dir);
            for z in (-1..67).step_by(3) {
                for y in (-1..61).step_by(2) {
                    for x in (-1..71).step_by(3) {
                        let from = [x, y, z];
                        let ray = Ray {
                            origin: from.map(|c| c as f32 + 0.5),
                            dir,
                        };
                        let expected = crate::trace::blocked(&map, &ray);
                        assert_eq!(paths.blocked(&map, from), expected, "{dir:?} from {from:?}");
                        blocked += usize::from(expected);
                        checked += 1;
                    }
                }
            }
        }
        assert!(
            blocked > checked / 10 && blocked < checked * 9 / 10,
            "{blocked} of {checked}"
        );
    }

    /// In a large grid whose occupied regions fill only a corner, walks leave the occupied box
    /// (and the grid) early, in every direction: still the plain trace's answers.
    #[test]
    fn walks_leaving_the_occupied_box() {
        let mut map = BrickMap::new([300, 200, 260]).unwrap();
        map.fill_box([40, 40, 40], [80, 44, 90], BrushMode::Fill, Colour::WHITE);
        map.sphere([60.0, 60.0, 60.0], 8.0, BrushMode::Fill, Colour(5));
        map.set([299, 199, 259], Colour(3));
        map.set([0, 0, 0], Colour(3));
        let mut blocked = 0;
        for dir in [
            [0.5f32, 0.8, 0.25],
            [-0.6, 0.3, -0.2],
            [0.0, -1.0, 0.0],
            [0.7, 0.0, 0.7],
        ] {
            let paths = SunPaths::new(dir);
            for z in (30..110).step_by(4) {
                for y in (30..80).step_by(3) {
                    for x in (20..110).step_by(4) {
                        let ray = Ray {
                            origin: [x as f32 + 0.5, y as f32 + 0.5, z as f32 + 0.5],
                            dir,
                        };
                        let expected = crate::trace::blocked(&map, &ray);
                        assert_eq!(
                            paths.blocked(&map, [x, y, z]),
                            expected,
                            "{dir:?} {x} {y} {z}"
                        );
                        blocked += usize::from(expected);
                    }
                }
            }
        }
        assert!(blocked > 100, "{blocked}");
        // (Other tests render with the default sun at the same time, so the one shared table
        // may change hands between two calls: only its direction is checked.)
        assert_eq!(SunPaths::shared([0.5, 0.8, 0.25]).dir(), [0.5, 0.8, 0.25]);
    }
}
