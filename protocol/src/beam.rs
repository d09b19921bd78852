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

use crate::brick::BRICK_EDGE;
use crate::map::{
    BrickMap, CELLS_PER_BLOCK, REGION_EDGE, cell_clearance, cell_is_empty, region_clearance,
    region_is_empty,
};
use crate::render::Projection;

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

    /// The largest ray parameter up to which every voxel the beam's rays meet is known to be
    /// empty: 0 when nothing is known, infinity when the beam never reaches an occupied region.
    pub fn safe_start(&self, map: &BrickMap) -> f32 {
        let Some((rlo, rhi)) = map.occupied_regions() else {
            return f32::INFINITY;
        };
        if self
            .eye
            .iter()
            .chain(&self.centre)
            .chain(&self.spread)
            .any(|c| !c.is_finite())
        {
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
