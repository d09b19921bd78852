//! The beam pre-pass: one conservative march per tile of pixels that gives all of the tile's
//! primary rays a safe place to start (Laine & Karras' beam optimisation, on regions).
//!
//! Why: primary rays of neighbouring pixels cross the same empty space. Marching it once per
//! 8×8 tile instead of once per ray removes most region steps, and a tile that misses the
//! occupied box entirely costs no ray at all.
//!
//! How it stays exact: the rays of a tile are `eye + t·(F + R·u + U·v)` with `u`, `v` in the
//! tile's pixel ranges, so at parameter `t` they all lie in an axis-aligned box centred on the
//! tile's centre ray with half-size `t·ρ` (`ρ[i] = |R[i]|·hu + |U[i]|·hv`). The march only
//! advances `t` while that box, grown by [`MARGIN`] voxels for rounding, stays inside space known
//! to be empty: outside the map's occupied box, inside the cube of empty regions an empty
//! region's clearance vouches for, or, in an occupied region, inside the cube of empty cells an
//! empty cell's clearance vouches for. Every voxel any of the tile's rays meets before the returned
//! `t` is therefore empty, which is what [`crate::trace::trace_from`] needs to return exactly
//! the hit [`crate::trace::trace`] would. CPU only for now: in the shader, one invocation per
//! workgroup marching while the other 63 waited made lavapipe about 20% slower; a separate pass
//! writing one start per tile is the way to try it there.

use crate::brick::{BRICK_EDGE, Mask};
use crate::map::{
    BrickMap, CELLS_PER_BLOCK, REGION_EDGE, cell_clearance, cell_is_empty, region_clearance,
    region_is_empty, region_stand_in,
};
use crate::render::Projection;
use crate::trace::floor_i32;

/// Pixels along a tile's edge.
pub const TILE: u32 = 8;
/// Voxels added around the beam's box for rounding, while every coordinate involved is below
/// [`NEAR_RANGE`]: a ray's voxel path then strays at most about 7e-3 voxels from the exact line
/// (see `trace::clearly_inside_voxel`), and the beam's own arithmetic less.
pub const MARGIN: f32 = 1.0 / 32.0;
/// Beyond coordinates of this size the margin is a whole voxel.
pub const NEAR_RANGE: f32 = 16384.0;
/// Steps the march may take before it settles for what it has.
pub const MAX_STEPS: u32 = 48;

/// A tile's beam: centre direction and per-axis spread per unit of ray parameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Beam {
    pub eye: [f32; 3],
    pub centre: [f32; 3],
    pub spread: [f32; 3],
}

impl Beam {
    /// The beam holding the primary rays of pixels `x0..x1` × `y0..y1` (clipped to the image).
    pub fn tile(p: &Projection, x0: u32, y0: u32, x1: u32, y1: u32) -> Beam {
        let (x1, y1) = (x1.min(p.width).max(x0 + 1), y1.min(p.height).max(y0 + 1));
        let uc = (x0 + x1) as f32 * 0.5 - p.width as f32 * 0.5;
        let vc = p.height as f32 * 0.5 - (y0 + y1) as f32 * 0.5;
        let hu = (x1 - x0 - 1) as f32 * 0.5;
        let hv = (y1 - y0 - 1) as f32 * 0.5;
        Beam {
            eye: p.eye,
            centre: std::array::from_fn(|i| p.forward[i] + p.right[i] * uc + p.up[i] * vc),
            spread: std::array::from_fn(|i| p.right[i].abs() * hu + p.up[i].abs() * hv),
        }
    }

    /// Whether eye, centre and spread are all finite (a beam the marches can use).
    fn is_finite(&self) -> bool {
        self.eye
            .iter()
            .chain(&self.centre)
            .chain(&self.spread)
            .all(|c| c.is_finite())
    }

    /// The largest ray parameter up to which every voxel the beam's rays meet is known to be
    /// empty: 0 when nothing is known, infinity when the beam never reaches an occupied region.
    pub fn safe_start(&self, map: &BrickMap) -> f32 {
        let Some((rlo, rhi)) = map.occupied_regions() else {
            return f32::INFINITY;
        };
        if !self.is_finite() {
            return 0.0;
        }
        let r = REGION_EDGE as f32;
        let size = map.size();
        let box_lo: [f32; 3] = rlo.map(|c| c as f32 * r);
        let box_hi: [f32; 3] =
            std::array::from_fn(|i| ((rhi[i] + 1) as f32 * r).min(size[i] as f32));
        let dims = map.region_dims();
        let regions = map.regions();
        let cells = map.cells();
        let b = BRICK_EDGE as f32;
        let (c, s) = (self.centre, self.spread);
        let mut t = 0.0f32;
        let eye_near = self.eye.iter().all(|c| c.abs() < NEAR_RANGE);
        for _ in 0..MAX_STEPS {
            let p: [f32; 3] = std::array::from_fn(|i| self.eye[i] + c[i] * t);
            let margin = if eye_near && p.iter().all(|c| c.abs() < NEAR_RANGE) {
                MARGIN
            } else {
                1.0
            };
            let half: [f32; 3] = std::array::from_fn(|i| s[i] * t + margin);
            let lo: [f32; 3] = std::array::from_fn(|i| p[i] - half[i]);
            let hi: [f32; 3] = std::array::from_fn(|i| p[i] + half[i]);
            // The empty box we may move in, per axis; infinite where it reaches past the
            // occupied box (beyond it everything is empty).
            let (elo, ehi) = if let Some(i) =
                (0..3).find(|&i| hi[i] < box_lo[i] || lo[i] > box_hi[i])
            {
                // Wholly outside the occupied box on axis i: the half-space beyond its face.
                let mut elo = [f32::NEG_INFINITY; 3];
                let mut ehi = [f32::INFINITY; 3];
                if hi[i] < box_lo[i] {
                    ehi[i] = box_lo[i];
                } else {
                    elo[i] = box_hi[i];
                }
                (elo, ehi)
            } else {
                // The region under the beam's centre (clamped into the occupied box) and the
                // cube of empty regions its clearance vouches for.
                let cell: [u32; 3] = std::array::from_fn(|i| {
                    let v = p[i].clamp(box_lo[i], box_hi[i] - 0.5);
                    ((v / r) as u32).clamp(rlo[i], rhi[i])
                });
                let entry = regions[(cell[0] + dims[0] * (cell[1] + dims[1] * cell[2])) as usize];
                // An occupied region: go down to its cell under the beam's centre, and the cube
                // of empty cells that cell's clearance vouches for.
                let (unit, at, clear) = if region_is_empty(entry) {
                    (r, cell, region_clearance(entry) as f32)
                } else if region_stand_in(entry).is_some() {
                    // A coarse brick stands in for the region: not empty at this grain.
                    return t;
                } else {
                    let c: [u32; 3] = std::array::from_fn(|i| {
                        let v = p[i].clamp(box_lo[i], box_hi[i] - 0.5);
                        ((v / b) as u32).clamp(cell[i] * 4, cell[i] * 4 + 3)
                    });
                    let local = (c[0] & 3) | ((c[1] & 3) << 2) | ((c[2] & 3) << 4);
                    let slot = cells[(entry * CELLS_PER_BLOCK + local) as usize];
                    if !cell_is_empty(slot) {
                        return t;
                    }
                    (b, c, cell_clearance(slot) as f32)
                };
                let mut elo = [0.0; 3];
                let mut ehi = [0.0; 3];
                for i in 0..3 {
                    elo[i] = (at[i] as f32 - clear) * unit;
                    ehi[i] = (at[i] as f32 + clear + 1.0) * unit;
                    if elo[i] <= box_lo[i] {
                        elo[i] = f32::NEG_INFINITY;
                    }
                    if ehi[i] >= box_hi[i] {
                        ehi[i] = f32::INFINITY;
                    }
                }
                (elo, ehi)
            };
            // How far the beam's box may grow and move before it leaves that empty box.
            let mut step = f32::INFINITY;
            for i in 0..3 {
                if ehi[i] < f32::INFINITY {
                    let room = ehi[i] - hi[i];
                    if room < 0.0 {
                        return t;
                    }
                    let rate = c[i] + s[i];
                    if rate > 0.0 {
                        step = step.min(room / rate);
                    }
                }
                if elo[i] > f32::NEG_INFINITY {
                    let room = lo[i] - elo[i];
                    if room < 0.0 {
                        return t;
                    }
                    let rate = s[i] - c[i];
                    if rate > 0.0 {
                        step = step.min(room / rate);
                    }
                }
            }
            if step == f32::INFINITY {
                return f32::INFINITY;
            }
            if step.is_nan() || step <= 0.0 {
                return t;
            }
            t += step;
        }
        t
    }
}

/// Pixels along a quarter tile's edge: the second level of beams.
pub const SUBTILE: u32 = TILE / 2;
/// Largest step of [`Beam::advance`], in voxels moved by the box's fastest face: a larger hull
/// costs more to test than it usually saves.
const MAX_STEP: f32 = 16.0;

/// The safe starts of one tile's rays, from two levels of beams: the tile's (its march over
/// regions and cells, [`Beam::safe_start`], then [`Beam::advance`] down to the bricks) and then
/// each quarter's, narrower, from there.
///
/// Why two levels: a tile's box is about twice as wide as a quarter's, so it touches the surface
/// sooner; measured on the 1024³ demo cameras, quarters cut the rays' own work by a further
/// 15–25% for a few percent more beam work, and a third level (2×2 pixels) cost more beam work
/// than it saved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileStarts {
    x0: u32,
    y0: u32,
    quarters: [f32; 4],
}

impl TileStarts {
    /// The starts for the tile whose top-left pixel is `(x0, y0)`.
    pub fn new(p: &Projection, map: &BrickMap, x0: u32, y0: u32) -> TileStarts {
        let tile = Beam::tile(p, x0, y0, x0 + TILE, y0 + TILE);
        let t = tile.safe_start(map);
        let t = tile.advance(map, t, 8.0, 4.0);
        let quarters = std::array::from_fn(|q| {
            let (x, y) = (
                x0 + SUBTILE * (q as u32 & 1),
                y0 + SUBTILE * (q as u32 >> 1),
            );
            if x >= p.width || y >= p.height {
                return t;
            }
            Beam::tile(p, x, y, x + SUBTILE, y + SUBTILE).advance(map, t, 2.0, 0.75)
        });
        TileStarts { x0, y0, quarters }
    }

    /// The start for pixel `(x, y)` of the tile.
    #[inline]
    pub fn at(&self, x: u32, y: u32) -> f32 {
        let qx = usize::from(x.wrapping_sub(self.x0) >= SUBTILE);
        let qy = usize::from(y.wrapping_sub(self.y0) >= SUBTILE);
        self.quarters[qx + 2 * qy]
    }
}

impl Beam {
    /// The box holding every ray of the beam at parameter `t`, grown by `margin` voxels.
    #[inline]
    fn bounds(&self, t: f32, margin: f32) -> ([f32; 3], [f32; 3]) {
        let p: [f32; 3] = std::array::from_fn(|i| self.eye[i] + self.centre[i] * t);
        let half: [f32; 3] = std::array::from_fn(|i| self.spread[i] * t + margin);
        (
            std::array::from_fn(|i| p[i] - half[i]),
            std::array::from_fn(|i| p[i] + half[i]),
        )
    }

    /// Whether the beam's centre at `t` (and the eye) are within [`NEAR_RANGE`], where
    /// [`MARGIN`] covers the rays' rounding.
    #[inline]
    fn near(&self, t: f32) -> bool {
        (0..3).all(|i| {
            self.eye[i].abs() < NEAR_RANGE && (self.eye[i] + self.centre[i] * t).abs() < NEAR_RANGE
        })
    }

    /// Moves a safe start `t` (every voxel the beam's rays meet before it is empty) further, up
    /// to where the beam's box first touches a solid voxel, give or take a step.
    ///
    /// Why: [`Beam::safe_start`] moves only through whole empty regions and cells, so it stops
    /// at the first cell holding a brick near the beam, often far from where the rays hit (on
    /// terrain seen at a grazing angle, several bricks of empty air above the surface). Here the
    /// beam moves in steps, and a step is taken only when the hull of the beam's boxes at its
    /// start and end (which holds every box in between, as each face moves linearly in `t`)
    /// holds no solid voxel, tested on the brick masks themselves. Steps are measured in voxels
    /// moved by the box's fastest face: the first is `first`, they double after a success (up
    /// to 16 voxels) and halve after a failure, and the march ends when a step would be
    /// shorter than `min`.
    pub fn advance(&self, map: &BrickMap, t: f32, first: f32, min: f32) -> f32 {
        if t.is_nan() || t < 0.0 || t == f32::INFINITY || min.is_nan() || min <= 0.0 {
            return t;
        }
        let Some((rlo, rhi)) = map.occupied_regions() else {
            return f32::INFINITY;
        };
        if !self.is_finite() {
            return t;
        }
        // Voxels outside the occupied regions' box are all empty.
        let r = REGION_EDGE as i32;
        let size = map.size().map(|s| s as i32);
        let vmin: [i32; 3] = rlo.map(|c| c as i32 * r);
        let vmax: [i32; 3] = std::array::from_fn(|i| ((rhi[i] as i32 + 1) * r).min(size[i]) - 1);
        let rate = (0..3)
            .map(|i| self.centre[i].abs() + self.spread[i])
            .fold(0.0f32, f32::max);
        if rate.is_nan() || rate <= 0.0 {
            return t;
        }
        let (mut t, mut d) = (t, first.min(MAX_STEP));
        while d >= min {
            let next = t + d / rate;
            if !next.is_finite() || next <= t {
                break;
            }
            // One margin for both ends: the centre moves on a line, so when both ends are near
            // every point between is, and every box between is inside the hull.
            let margin = if self.near(t) && self.near(next) {
                MARGIN
            } else {
                1.0
            };
            let (lo0, hi0) = self.bounds(t, margin);
            let (lo1, hi1) = self.bounds(next, margin);
            if lo1.iter().chain(&hi1).any(|c| !c.is_finite()) {
                break;
            }
            let mut vlo = [0i32; 3];
            let mut vhi = [0i32; 3];
            let mut outside = false;
            for i in 0..3 {
                // Voxel `v` meets the hull when its cube does: v from floor(lo) to floor(hi).
                let lo = lo0[i].min(lo1[i]).max(vmin[i] as f32 - 1.0);
                let hi = hi0[i].max(hi1[i]).min(vmax[i] as f32 + 1.0);
                vlo[i] = floor_i32(lo).max(vmin[i]);
                vhi[i] = floor_i32(hi).min(vmax[i]);
                outside |= vlo[i] > vhi[i];
            }
            if outside || voxels_empty(map, vlo, vhi) {
                t = next;
                if outside
                    && (0..3).any(|i| {
                        // Leaving the box for good: past its far side on an axis it moves away on.
                        (lo1[i] > vmax[i] as f32 + 1.0 && self.centre[i] - self.spread[i] >= 0.0)
                            || (hi1[i] < vmin[i] as f32 && self.centre[i] + self.spread[i] <= 0.0)
                    })
                {
                    return f32::INFINITY;
                }
                d = (d * 2.0).min(MAX_STEP);
            } else {
                d *= 0.5;
            }
        }
        t
    }
}

/// Whether every voxel in `lo..=hi` (inside the grid) is empty: an empty region in one lookup,
/// the cells of an occupied one in one `and` with its block's occupied-cell bits, and the bricks
/// that remain by their masks.
fn voxels_empty(map: &BrickMap, lo: [i32; 3], hi: [i32; 3]) -> bool {
    let (r, b) = (REGION_EDGE as i32, BRICK_EDGE as i32);
    let dims = map.region_dims().map(|d| d as i32);
    let (regions, cells, masks) = (map.regions(), map.cells(), map.masks());
    let block_cells = map.block_cells();
    let (clo, chi) = (lo.map(|v| v / b), hi.map(|v| v / b));
    for rz in lo[2] / r..=hi[2] / r {
        for ry in lo[1] / r..=hi[1] / r {
            for rx in lo[0] / r..=hi[0] / r {
                let entry = regions[(rx + dims[0] * (ry + dims[1] * rz)) as usize];
                if region_is_empty(entry) {
                    continue;
                }
                if region_stand_in(entry).is_some() {
                    // A coarse brick's voxels: not looked into, so not known to be empty.
                    return false;
                }
                let reg = [rx, ry, rz];
                // The box's cells inside this region, in the region's local cell coordinates.
                let a: [i32; 3] = std::array::from_fn(|i| (clo[i] - reg[i] * 4).max(0));
                let z: [i32; 3] = std::array::from_fn(|i| (chi[i] - reg[i] * 4).min(3));
                let mut hits = block_cells[entry as usize] & cell_box_bits(a, z);
                while hits != 0 {
                    let local = hits.trailing_zeros();
                    hits &= hits - 1;
                    let slot = cells[(entry * CELLS_PER_BLOCK + local) as usize];
                    let c = [
                        reg[0] * 4 + (local & 3) as i32,
                        reg[1] * 4 + ((local >> 2) & 3) as i32,
                        reg[2] * 4 + ((local >> 4) & 3) as i32,
                    ];
                    let va: [i32; 3] = std::array::from_fn(|i| (lo[i] - c[i] * b).max(0));
                    let vz: [i32; 3] = std::array::from_fn(|i| (hi[i] - c[i] * b).min(b - 1));
                    if brick_box_solid(&masks[slot as usize], va, vz) {
                        return false;
                    }
                }
            }
        }
    }
    true
}

/// The bits of the cells `a..=z` (coordinates 0..4) in a block's 64-bit cell set.
#[inline]
fn cell_box_bits(a: [i32; 3], z: [i32; 3]) -> u64 {
    let xbits = (0xFu64 >> (3 - z[0])) & (0xFu64 << a[0]);
    let rows = (0xFFFFu64 >> (4 * (3 - z[1]))) & (0xFFFFu64 << (4 * a[1]));
    let slices = (u64::MAX >> (16 * (3 - z[2]))) & (u64::MAX << (16 * a[2]));
    slices & (rows & xbits.wrapping_mul(0x1111)).wrapping_mul(0x0001_0001_0001_0001)
}

/// Whether a brick has a solid voxel in the local box `a..=z` (coordinates 0..8).
#[inline]
fn brick_box_solid(mask: &Mask, a: [i32; 3], z: [i32; 3]) -> bool {
    let xbits = (0xFFu64 >> (7 - z[0])) & (0xFFu64 << a[0]);
    let rows = (u64::MAX >> (8 * (7 - z[1]))) & (u64::MAX << (8 * a[1]));
    let box_bits = rows & xbits.wrapping_mul(0x0101_0101_0101_0101);
    (a[2]..=z[2]).any(|w| mask[w as usize] & box_bits != 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::map::BrushMode;
    use crate::render::Camera;
    use crate::trace::{trace, trace_from};

    /// Every ray of every tile hits exactly what a plain trace hits, and the march skips
    /// something: the start is past the eye for tiles that look across empty space.
    #[test]
    fn tile_starts_are_safe_and_useful() {
        let mut map = BrickMap::new([400, 200, 400]).unwrap();
        map.fill_box([0, 0, 0], [399, 20, 399], BrushMode::Fill, Colour(0x7BEF));
        map.sphere([300.0, 60.0, 300.0], 30.0, BrushMode::Fill, Colour::WHITE);
        map.set([50, 150, 350], Colour(7));
        map.rebuild_clearance();
        for camera in [
            Camera::overview(map.size()),
            Camera {
                eye: [20.0, 40.0, 20.0],
                target: [300.0, 60.0, 300.0],
                fov_y: 70.0,
            },
            Camera {
                eye: [-900.0, 1500.0, 200.0],
                target: [200.0, 0.0, 200.0],
                fov_y: 20.0,
            },
        ] {
            let p = camera.project(96, 54).unwrap();
            let mut skipped = 0;
            for ty in (0..p.height).step_by(TILE as usize) {
                for tx in (0..p.width).step_by(TILE as usize) {
                    let t0 = Beam::tile(&p, tx, ty, tx + TILE, ty + TILE).safe_start(&map);
                    skipped += usize::from(t0 > 0.0);
                    for y in ty..(ty + TILE).min(p.height) {
                        for x in tx..(tx + TILE).min(p.width) {
                            let ray = p.ray(x, y);
                            assert_eq!(
                                trace_from(&map, &ray, t0),
                                trace(&map, &ray),
                                "{camera:?} ({x}, {y}) t0 {t0}"
                            );
                        }
                    }
                }
            }
            assert!(skipped > 0, "{camera:?}: no tile skipped anything");
        }
    }

    /// The two-level starts are safe on every pixel, and the advance on brick masks gets
    /// further than the march over regions and cells alone: here the camera looks across a
    /// terrain-like floor at a grazing angle, where cells above the surface hold bricks.
    #[test]
    fn quarter_starts_are_safe_and_get_further() {
        let mut map = BrickMap::new([256, 96, 256]).unwrap();
        for z in 0..256u32 {
            for x in 0..256u32 {
                let h = 10 + (x / 9 + z / 13) % 5;
                map.fill_box([x, h - 2, z], [x, h, z], BrushMode::Fill, Colour(0x7BEF));
            }
        }
        map.sphere([180.0, 30.0, 200.0], 12.0, BrushMode::Fill, Colour::WHITE);
        map.rebuild_clearance();
        let camera = Camera {
            eye: [20.0, 24.0, 10.0],
            target: [200.0, 12.0, 230.0],
            fov_y: 60.0,
        };
        let p = camera.project(64, 40).unwrap();
        let (mut further, mut hits) = (0, 0);
        for ty in (0..p.height).step_by(TILE as usize) {
            for tx in (0..p.width).step_by(TILE as usize) {
                let coarse = Beam::tile(&p, tx, ty, tx + TILE, ty + TILE).safe_start(&map);
                let starts = TileStarts::new(&p, &map, tx, ty);
                for y in ty..(ty + TILE).min(p.height) {
                    for x in tx..(tx + TILE).min(p.width) {
                        let ray = p.ray(x, y);
                        let t = starts.at(x, y);
                        let hit = trace(&map, &ray);
                        assert_eq!(trace_from(&map, &ray, t), hit, "({x}, {y}) from {t}");
                        assert!(t >= coarse, "({x}, {y}): {t} < {coarse}");
                        if let Some(hit) = hit {
                            hits += 1;
                            assert!(t <= hit.t, "({x}, {y}): start {t} past the hit {}", hit.t);
                            further += usize::from(t > coarse + 8.0);
                        }
                    }
                }
            }
        }
        assert!(hits > 1000, "{hits}");
        assert!(
            further * 2 > hits,
            "only {further} of {hits} hits start 8 further"
        );
    }

    /// The box test on the map agrees with looking at every voxel, for boxes of every shape
    /// placed anywhere (across region, cell and brick boundaries).
    #[test]
    fn voxel_box_test_matches_brute_force() {
        let mut map = BrickMap::new([80, 70, 90]).unwrap();
        let mut seed = 12345u32;
        let mut next = |n: u32| {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) % n
        };
        for _ in 0..60 {
            let v = [next(80), next(70), next(90)];
            map.set(v, Colour::WHITE);
        }
        map.fill_box([40, 30, 40], [45, 33, 41], BrushMode::Fill, Colour(3));
        for _ in 0..4000 {
            let lo = [next(80), next(70), next(90)];
            let hi: [u32; 3] = std::array::from_fn(|i| (lo[i] + next(20)).min(map.size()[i] - 1));
            let mut solid = false;
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        solid |= map.is_solid([x, y, z]);
                    }
                }
            }
            let (l, h) = (lo.map(|c| c as i32), hi.map(|c| c as i32));
            assert_eq!(voxels_empty(&map, l, h), !solid, "{lo:?}..={hi:?}");
        }
    }

    #[test]
    fn empty_map_and_eye_inside_an_occupied_region() {
        let map = BrickMap::new([64, 64, 64]).unwrap();
        let p = Camera::overview(map.size()).project(16, 16).unwrap();
        assert_eq!(Beam::tile(&p, 0, 0, 8, 8).safe_start(&map), f32::INFINITY);
        let mut map = map;
        map.set([10, 10, 10], Colour::WHITE);
        let inside = Camera {
            eye: [12.5, 12.5, 12.5],
            target: [40.0, 12.0, 40.0],
            fov_y: 60.0,
        }
        .project(16, 16)
        .unwrap();
        assert_eq!(Beam::tile(&inside, 0, 0, 8, 8).safe_start(&map), 0.0);
    }
}
