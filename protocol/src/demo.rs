//! The built-in procedural demo scene: terrain, water, a village and trees.
//!
//! Deterministic (same size → same voxels), so the server's first start, the benchmarks and the
//! tests all see the same scene without shipping a file. Terrain is a crust a few voxels thick
//! rather than solid ground: people see and edit surfaces, and a solid 512² ground would spend
//! most of its memory on voxels no ray can reach.

use crate::brick::{BRICK_EDGE, BrickData, EMPTY_MASK, mask_set, voxel_bit};
use crate::colour::Colour;
use crate::map::{BrickMap, BrushMode, MapError};

/// Integer hash → 0..1, the lattice of the value noise.
pub(crate) fn lattice(x: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8DA6_B343)
        ^ (z as u32).wrapping_mul(0xD816_3841)
        ^ seed.wrapping_mul(0xCB1A_B31F);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5BD1_E995);
    h ^= h >> 15;
    (h & 0xFFFF) as f32 / 65535.0
}

/// Smoothly interpolated value noise at scale `cell` voxels.
pub(crate) fn value_noise(x: f32, z: f32, cell: f32, seed: u32) -> f32 {
    let (fx, fz) = (x / cell, z / cell);
    let (ix, iz) = (fx.floor() as i32, fz.floor() as i32);
    let (tx, tz) = (fx - ix as f32, fz - iz as f32);
    let (sx, sz) = (tx * tx * (3.0 - 2.0 * tx), tz * tz * (3.0 - 2.0 * tz));
    let a = lattice(ix, iz, seed) + (lattice(ix + 1, iz, seed) - lattice(ix, iz, seed)) * sx;
    let b = lattice(ix, iz + 1, seed)
        + (lattice(ix + 1, iz + 1, seed) - lattice(ix, iz + 1, seed)) * sx;
    a + (b - a) * sz
}

/// Terrain layout for a scene of a given size: heights from three octaves of value noise
/// (`scales` in voxels, `seeds` per octave, weights 0.55 / 0.3 / 0.15), water at `water`.
pub(crate) struct Terrain {
    pub size: [u32; 3],
    pub water: u32,
    pub scales: [f32; 3],
    pub seeds: [u32; 3],
}

/// Height scale of the terrain: half the horizontal extent, or the scene height if lower, so a
/// taller scene gets more sky rather than steeper mountains.
pub(crate) fn relief(size: [u32; 3]) -> u32 {
    size[1].min(size[0].max(size[2]) / 2).max(1)
}

impl Terrain {
    fn relief(&self) -> u32 {
        relief(self.size)
    }

    /// The demo's terrain: noise scales relative to the scene, so any size is one landscape.
    fn demo(size: [u32; 3]) -> Terrain {
        let s = size[0].max(size[2]) as f32;
        Terrain {
            size,
            water: relief(size) * 3 / 16,
            scales: [s / 4.0, s / 10.0, s / 32.0],
            seeds: [1, 2, 3],
        }
    }

    pub fn height(&self, x: u32, z: u32) -> u32 {
        let (x, z) = (x as f32, z as f32);
        let [a, b, c] = self.scales;
        let [sa, sb, sc] = self.seeds;
        let n = 0.55 * value_noise(x, z, a, sa)
            + 0.3 * value_noise(x, z, b, sb)
            + 0.15 * value_noise(x, z, c, sc);
        let top = self.relief() as f32;
        ((top * (0.12 + 0.5 * n * n)) as u32).clamp(1, self.size[1] - 1)
    }

    fn colour(&self, x: u32, y: u32, z: u32, surface: u32) -> Colour {
        let jitter = (lattice(x as i32 * 7 + y as i32, z as i32 * 13 - y as i32, 9) * 24.0) as u8;
        let depth = surface - y;
        let top = self.relief();
        if surface <= self.water + 1 {
            Colour::from_rgb8(214 - jitter / 2, 196 - jitter / 2, 140)
        } else if depth > 2 {
            Colour::from_rgb8(110 + jitter, 84 + jitter / 2, 60)
        } else if surface > top * 9 / 20 {
            Colour::from_rgb8(236 - jitter / 3, 240 - jitter / 3, 245)
        } else if surface > top * 7 / 20 {
            Colour::from_rgb8(120 + jitter, 118 + jitter, 112 + jitter)
        } else {
            Colour::from_rgb8(70 + jitter, 140 + jitter, 52 + jitter / 2)
        }
    }
}

/// The demo scene at `size` voxels (the server uses 512³).
pub fn demo_scene(size: [u32; 3]) -> Result<BrickMap, MapError> {
    let mut map = BrickMap::new(size)?;
    let terrain = Terrain::demo(size);
    let cells = map.cell_dims();
    let mut heights = Vec::new();
    for cz in 0..cells[2] {
        for cx in 0..cells[0] {
            let mut result = Ok(());
            terrain.crust(cx, cz, &mut heights, |brick| {
                if result.is_ok() {
                    result = map.put_brick(&brick);
                }
            });
            result?;
        }
    }
    add_village(&mut map, &terrain);
    map.rebuild_clearance();
    Ok(map)
}

impl Terrain {
    /// The bricks of the brick column `(cx, cz)` (scene cells), bottom up, handed to `out`:
    /// the ground's crust a few voxels thick and the water above low ground. `heights` is
    /// scratch space.
    pub fn crust(&self, cx: u32, cz: u32, heights: &mut Vec<u32>, mut out: impl FnMut(BrickData)) {
        let (size, terrain) = (self.size, self);
        // Heights of this brick column's 8×8 voxel columns and one ring around it: the crust
        // reaches down to the lowest neighbour so steep slopes have no holes.
        heights.clear();
        heights.resize(10 * 10, 0);
        for dz in 0..10u32 {
            for dx in 0..10u32 {
                let x = (cx * BRICK_EDGE + dx).saturating_sub(1).min(size[0] - 1);
                let z = (cz * BRICK_EDGE + dz).saturating_sub(1).min(size[2] - 1);
                heights[(dz * 10 + dx) as usize] = terrain.height(x, z);
            }
        }
        let column = |lx: u32, lz: u32| -> Option<(u32, u32)> {
            let (x, z) = (cx * BRICK_EDGE + lx, cz * BRICK_EDGE + lz);
            if x >= size[0] || z >= size[2] {
                return None;
            }
            let h = heights[((lz + 1) * 10 + lx + 1) as usize];
            let low = [(0, 1), (2, 1), (1, 0), (1, 2)]
                .iter()
                .map(|&(ox, oz)| heights[((lz + oz) * 10 + lx + ox) as usize])
                .min()
                .unwrap_or(h);
            let surface = h.max(terrain.water);
            Some((low.min(h).saturating_sub(3), surface))
        };
        let (mut lo, mut hi) = (u32::MAX, 0);
        for lz in 0..8 {
            for lx in 0..8 {
                if let Some((a, b)) = column(lx, lz) {
                    lo = lo.min(a);
                    hi = hi.max(b);
                }
            }
        }
        if lo > hi {
            return;
        }
        for cy in lo / BRICK_EDGE..=hi / BRICK_EDGE {
            let mut brick = BrickData {
                cell: [cx, cy, cz],
                mask: EMPTY_MASK,
                colours: Vec::new(),
            };
            // Bit order is x fastest, then y, then z: emit colours in that order.
            for lz in 0..8 {
                for ly in 0..8 {
                    for lx in 0..8 {
                        let Some((bottom, surface)) = column(lx, lz) else {
                            continue;
                        };
                        let y = cy * BRICK_EDGE + ly;
                        if y < bottom || y > surface || y >= size[1] {
                            continue;
                        }
                        let (x, z) = (cx * BRICK_EDGE + lx, cz * BRICK_EDGE + lz);
                        let ground = heights[((lz + 1) * 10 + lx + 1) as usize];
                        let colour = if y > ground {
                            let ripple = (lattice(x as i32, z as i32, 5) * 20.0) as u8;
                            Colour::from_rgb8(40, 90 + ripple, 170 + ripple)
                        } else {
                            terrain.colour(x, y, z, ground)
                        };
                        mask_set(&mut brick.mask, voxel_bit(lx, ly, lz), true);
                        brick.colours.push(colour);
                    }
                }
            }
            if !brick.colours.is_empty() {
                out(brick);
            }
        }
    }
}

/// Houses and trees on dry, gentle ground, placed by the same deterministic hash.
fn add_village(map: &mut BrickMap, terrain: &Terrain) {
    let size = terrain.size;
    let unit = (size[0].min(size[2]) / 64).max(2);
    let mut placed = 0;
    for i in 0..400u32 {
        if placed >= 24 {
            break;
        }
        let x = (lattice(i as i32, 1, 11) * (size[0] - 8 * unit) as f32) as u32 + 4 * unit;
        let z = (lattice(i as i32, 2, 11) * (size[2] - 8 * unit) as f32) as u32 + 4 * unit;
        let (w, d) = (3 * unit, 2 * unit + (i % 3) * unit / 2);
        let Some((lo, hi)) = terrain.building_ground(x, z, w, d, unit) else {
            continue;
        };
        placed += 1;
        if i % 3 == 2 {
            draw_tree(map, [x, z], [lo, hi], unit);
        } else {
            draw_house(map, [x, z], [w, d], [lo, hi], unit);
        }
    }
}

impl Terrain {
    /// The lowest and highest ground under the corners of a `w`×`d` footprint at `(x, z)`,
    /// where something `unit`-sized may stand there: dry, gentle ground with room above.
    pub fn building_ground(&self, x: u32, z: u32, w: u32, d: u32, unit: u32) -> Option<(u32, u32)> {
        let size = self.size;
        let corners = [(x, z), (x + w, z), (x, z + d), (x + w, z + d)]
            .map(|(cx, cz)| self.height(cx.min(size[0] - 1), cz.min(size[2] - 1)));
        let lo = corners.iter().min().copied().unwrap_or(0);
        let hi = corners.iter().max().copied().unwrap_or(0);
        (lo > self.water + 2 && hi - lo <= unit && hi + 4 * unit < size[1]).then_some((lo, hi))
    }
}

/// A tree on ground between `ground[0]` and `ground[1]` at `(x, z)` of `map`: a trunk
/// `unit / 2` wide and `3·unit` above the ground, a crown of radius `1.4·unit`.
pub(crate) fn draw_tree(map: &mut BrickMap, [x, z]: [u32; 2], [lo, hi]: [u32; 2], unit: u32) {
    let trunk = Colour::from_rgb8(96, 64, 36);
    let leaves = Colour::from_rgb8(46, 112, 40);
    let h = 3 * unit;
    map.fill_box(
        [x, lo, z],
        [x + unit / 2, hi + h, z + unit / 2],
        BrushMode::Fill,
        trunk,
    );
    let centre = [
        x as f32 + unit as f32 * 0.25,
        (hi + h) as f32,
        z as f32 + unit as f32 * 0.25,
    ];
    map.sphere(centre, unit as f32 * 1.4, BrushMode::Fill, leaves);
}

/// A house of `w`×`d` voxels at `(x, z)` of `map` on ground between `ground[0]` and
/// `ground[1]`: hollow walls `2·unit` above the ground, windows along the long walls, a
/// stepped roof.
pub(crate) fn draw_house(
    map: &mut BrickMap,
    [x, z]: [u32; 2],
    [w, d]: [u32; 2],
    [lo, hi]: [u32; 2],
    unit: u32,
) {
    let wall = Colour::from_rgb8(226, 214, 190);
    let roof = Colour::from_rgb8(168, 60, 44);
    let glass = Colour::from_rgb8(60, 80, 110);
    let top = hi + 2 * unit;
    map.fill_box([x, lo, z], [x + w, top, z + d], BrushMode::Fill, wall);
    map.fill_box(
        [x + 1, hi + 1, z + 1],
        [x + w - 1, top - 1, z + d - 1],
        BrushMode::Erase,
        wall,
    );
    // Windows along the long walls.
    let win = (unit / 2).max(1);
    let mut wx = x + unit / 2;
    while wx + win < x + w {
        map.fill_box(
            [wx, hi + unit / 2, z],
            [wx + win, hi + unit / 2 + win, z + d],
            BrushMode::Paint,
            glass,
        );
        wx += unit;
    }
    // A stepped roof.
    for step in 0..=unit {
        let y = top + 1 + step;
        if step * 2 > d || y >= map.size()[1] {
            break;
        }
        map.fill_box(
            [x, y, z + step],
            [x + w, y, z + d - step],
            BrushMode::Fill,
            roof,
        );
    }
}

/// The fixed cameras of the tracer benchmarks (CPU and GPU) and of `trace_stats`, on the 1024³
/// demo scene: one above a corner looking across, one low over the terrain. Kept in one place so
/// the CPU and GPU figures in BENCHMARKS.md are of the same rays.
pub fn benchmark_cameras_1024() -> [(&'static str, crate::Camera); 2] {
    [
        (
            "1024_overview",
            crate::Camera {
                eye: [-80.0, 700.0, -80.0],
                target: [512.0, 200.0, 512.0],
                fov_y: 60.0,
            },
        ),
        (
            "1024_ground",
            crate::Camera {
                eye: [300.0, 420.0, 200.0],
                target: [700.0, 260.0, 800.0],
                fov_y: 70.0,
            },
        ),
    ]
}

/// The one colour of [`room_scene`]: a light grey, so only shading tells its faces apart.
pub const ROOM_GREY: Colour = Colour::from_rgb8(200, 200, 200);

/// Thickness of the room's floor, ceiling and walls, in voxels.
pub const ROOM_WALL: u32 = 3;

/// Smallest room [`room_scene`] builds: smaller requested axes are raised to these, so the
/// furniture keeps legs, seat and shelves that are distinct voxels. The returned map's `size()`
/// is what was built.
pub const ROOM_MIN: [u32; 3] = [32, 24, 32];

/// A closed, untextured room: floor, ceiling and four walls [`ROOM_WALL`] voxels thick, with a
/// table (top and four legs), a chair (seat, back, legs), a bookcase against the back wall and a
/// crate in a corner, all in [`ROOM_GREY`].
///
/// Why it exists: it is the indoor counterpart of [`demo_scene`], for tests and README pictures.
/// The sun never reaches inside and every face has the same colour, so what a renderer shows
/// here comes from shading alone (which faces it can still tell apart), and a first-camera rule
/// must find a place inside rather than a view of the outer box.
///
/// Furniture is placed at fixed fractions of the interior (heights of its height, footprints of
/// its width and depth), so any size works, multiples of 8 or not; axes below [`ROOM_MIN`] are
/// raised to it (see there). Deterministic. Errors only where [`BrickMap::new`] does (an axis
/// above the largest scene edge).
pub fn room_scene(size: [u32; 3]) -> Result<BrickMap, MapError> {
    let size: [u32; 3] = std::array::from_fn(|i| size[i].max(ROOM_MIN[i]));
    let mut map = BrickMap::new(size)?;
    let [sx, sy, sz] = size;
    let w = ROOM_WALL;
    let mut put = |min: [u32; 3], max: [u32; 3]| {
        // Inclusive boxes; a degenerate one (max below min on an axis) still covers one voxel.
        let max = std::array::from_fn(|i| max[i].max(min[i]));
        map.fill_box(min, max, BrushMode::Fill, ROOM_GREY);
    };
    // The shell as six slabs, so a large room never allocates its interior.
    put([0, 0, 0], [sx - 1, w - 1, sz - 1]);
    put([0, sy - w, 0], [sx - 1, sy - 1, sz - 1]);
    put([0, 0, 0], [w - 1, sy - 1, sz - 1]);
    put([sx - w, 0, 0], [sx - 1, sy - 1, sz - 1]);
    put([0, 0, 0], [sx - 1, sy - 1, w - 1]);
    put([0, 0, sz - w], [sx - 1, sy - 1, sz - 1]);

    // Interior: voxels w..s-w on each axis.
    let inner = size.map(|s| s - 2 * w);
    let at = |axis: usize, frac: f32| w + (frac * inner[axis] as f32) as u32;
    let up = |frac: f32| w + ((frac * inner[1] as f32).round() as u32).max(1);
    let t = (inner[0].min(inner[2]) / 40).max(1);
    let floor = w;
    let last = size.map(|s| s - w - 1);

    // Table: a top slab and four legs.
    let (tx0, tx1) = (at(0, 0.50), at(0, 0.78));
    let (tz0, tz1) = (at(2, 0.45), at(2, 0.72));
    let table_top = up(0.30);
    put([tx0, table_top - t, tz0], [tx1, table_top - 1, tz1]);
    for (lx, lz) in [
        (tx0, tz0),
        (tx1 + 1 - t, tz0),
        (tx0, tz1 + 1 - t),
        (tx1 + 1 - t, tz1 + 1 - t),
    ] {
        put([lx, floor, lz], [lx + t - 1, table_top - t - 1, lz + t - 1]);
    }

    // Chair facing the table (+x): seat, four legs, a back on its -x side.
    let (cx0, cx1) = (at(0, 0.36), at(0, 0.46));
    let (cz0, cz1) = (at(2, 0.50), at(2, 0.64));
    let seat = up(0.17);
    put([cx0, seat - t, cz0], [cx1, seat - 1, cz1]);
    for (lx, lz) in [
        (cx0, cz0),
        (cx1 + 1 - t, cz0),
        (cx0, cz1 + 1 - t),
        (cx1 + 1 - t, cz1 + 1 - t),
    ] {
        put([lx, floor, lz], [lx + t - 1, seat - t - 1, lz + t - 1]);
    }
    put([cx0, seat, cz0], [cx0 + t - 1, up(0.45), cz1]);

    // Bookcase against the back (+z) wall: sides, back panel, top and boards.
    let (bx0, bx1) = (at(0, 0.10), at(0, 0.40));
    let bz0 = at(2, 0.88);
    let shelf_top = up(0.60);
    put([bx0, floor, bz0], [bx0 + t - 1, shelf_top, last[2]]);
    put([bx1 + 1 - t, floor, bz0], [bx1, shelf_top, last[2]]);
    put([bx0, floor, last[2] + 1 - t], [bx1, shelf_top, last[2]]);
    for frac in [0.0, 0.15, 0.30, 0.45] {
        let y = floor + (frac * inner[1] as f32) as u32;
        put([bx0, y, bz0], [bx1, y + t - 1, last[2]]);
    }
    put([bx0, shelf_top + 1 - t, bz0], [bx1, shelf_top, last[2]]);

    // A crate in the front (-z) corner on the +x side.
    put(
        [at(0, 0.86), floor, floor],
        [last[0], up(0.20), at(2, 0.14)],
    );

    map.rebuild_clearance();
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn demo_scene_is_deterministic_and_valid() {
        let a = demo_scene([128, 64, 128]).unwrap();
        let b = demo_scene([128, 64, 128]).unwrap();
        assert_eq!(a.content_hash(), b.content_hash());
        assert!(a.solid_voxels() > 128 * 128, "a crust covers the ground");
        a.check_invariants().unwrap();
        for (brick, _) in a.bricks() {
            a.check_brick(&brick).unwrap();
        }
        let distinct: std::collections::HashSet<_> = a
            .bricks()
            .flat_map(|(b, _)| b.colours.into_iter())
            .collect();
        assert!(distinct.len() > 20, "colour variety: {}", distinct.len());
    }

    #[test]
    fn odd_sizes_work() {
        let map = demo_scene([37, 21, 45]).unwrap();
        map.check_invariants().unwrap();
    }

    /// Whether every interior voxel is sealed off: a flood fill from an interior air voxel never
    /// reaches the grid's outer layer.
    fn sealed(map: &BrickMap, from: [u32; 3]) -> (bool, u64) {
        let s = map.size();
        let index = |v: [u32; 3]| (v[0] + s[0] * (v[1] + s[1] * v[2])) as usize;
        let mut seen = vec![false; (s[0] * s[1] * s[2]) as usize];
        let mut stack = vec![from];
        seen[index(from)] = true;
        let mut air = 0;
        while let Some(v) = stack.pop() {
            air += 1;
            if (0..3).any(|i| v[i] == 0 || v[i] == s[i] - 1) {
                return (false, air);
            }
            for (axis, delta) in [(0, -1), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1)] {
                let mut n = v;
                n[axis] = (n[axis] as i64 + delta) as u32;
                if !seen[index(n)] && !map.is_solid(n) {
                    seen[index(n)] = true;
                    stack.push(n);
                }
            }
        }
        (true, air)
    }

    #[test]
    fn room_is_closed_grey_and_furnished() {
        let size = [160, 72, 128];
        let a = room_scene(size).unwrap();
        let b = room_scene(size).unwrap();
        assert_eq!(a.size(), size);
        assert_eq!(a.content_hash(), b.content_hash(), "deterministic");
        a.check_invariants().unwrap();
        assert!(
            a.bricks()
                .all(|(brick, _)| brick.colours.iter().all(|&c| c == ROOM_GREY)),
            "one colour"
        );
        let centre = [80, 40, 40];
        assert!(!a.is_solid(centre));
        let (closed, air) = sealed(&a, centre);
        assert!(closed, "the air inside never reaches the outside");
        let interior: u64 = (160 - 6) * (72 - 6) * (128 - 6);
        assert!(
            air < interior && air > interior / 2,
            "furniture takes some room, not most: {air} of {interior}"
        );
        // Furniture stands on the floor: a column under the table top reaches it from the floor.
        let floor_contacts = (3..157)
            .flat_map(|x| (3..125).map(move |z| [x, 3, z]))
            .filter(|&v| a.is_solid(v))
            .count();
        assert!(floor_contacts > 20, "legs and bases: {floor_contacts}");
    }

    #[test]
    fn small_and_odd_rooms_are_closed() {
        for size in [
            [1, 1, 1],
            [20, 50, 10],
            [32, 24, 32],
            [37, 29, 45],
            [61, 33, 200],
        ] {
            let map = room_scene(size).unwrap();
            let built = map.size();
            assert!(
                (0..3).all(|i| built[i] == size[i].max(ROOM_MIN[i])),
                "{size:?}"
            );
            map.check_invariants().unwrap();
            let from = [built[0] / 2, built[1] - ROOM_WALL - 2, built[2] / 2];
            assert!(!map.is_solid(from), "{size:?}: air under the ceiling");
            assert!(sealed(&map, from).0, "{size:?}");
        }
        assert!(
            room_scene([crate::map::MAX_SCENE_EDGE + 1, 64, 64]).is_err(),
            "too large is the map's error"
        );
    }
}
