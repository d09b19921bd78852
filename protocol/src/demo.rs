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
fn lattice(x: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8DA6_B343)
        ^ (z as u32).wrapping_mul(0xD816_3841)
        ^ seed.wrapping_mul(0xCB1A_B31F);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5BD1_E995);
    h ^= h >> 15;
    (h & 0xFFFF) as f32 / 65535.0
}

/// Smoothly interpolated value noise at scale `cell` voxels.
fn value_noise(x: f32, z: f32, cell: f32, seed: u32) -> f32 {
    let (fx, fz) = (x / cell, z / cell);
    let (ix, iz) = (fx.floor() as i32, fz.floor() as i32);
    let (tx, tz) = (fx - ix as f32, fz - iz as f32);
    let (sx, sz) = (tx * tx * (3.0 - 2.0 * tx), tz * tz * (3.0 - 2.0 * tz));
    let a = lattice(ix, iz, seed) + (lattice(ix + 1, iz, seed) - lattice(ix, iz, seed)) * sx;
    let b = lattice(ix, iz + 1, seed)
        + (lattice(ix + 1, iz + 1, seed) - lattice(ix, iz + 1, seed)) * sx;
    a + (b - a) * sz
}

/// Terrain layout for a scene of a given size.
struct Terrain {
    size: [u32; 3],
    water: u32,
}

/// Height scale of the terrain: half the horizontal extent, or the scene height if lower, so a
/// taller scene gets more sky rather than steeper mountains.
fn relief(size: [u32; 3]) -> u32 {
    size[1].min(size[0].max(size[2]) / 2).max(1)
}

impl Terrain {
    fn relief(&self) -> u32 {
        relief(self.size)
    }

    fn height(&self, x: u32, z: u32) -> u32 {
        let s = self.size[0].max(self.size[2]) as f32;
        let (x, z) = (x as f32, z as f32);
        let n = 0.55 * value_noise(x, z, s / 4.0, 1)
            + 0.3 * value_noise(x, z, s / 10.0, 2)
            + 0.15 * value_noise(x, z, s / 32.0, 3);
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
    let terrain = Terrain {
        size,
        water: relief(size) * 3 / 16,
    };
    let cells = map.cell_dims();
    let mut heights = vec![0u32; 10 * 10];
    for cz in 0..cells[2] {
        for cx in 0..cells[0] {
            // Heights of this brick column's 8×8 voxel columns and one ring around it: the crust
            // reaches down to the lowest neighbour so steep slopes have no holes.
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
                continue;
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
                    map.put_brick(&brick)?;
                }
            }
        }
    }
    add_village(&mut map, &terrain);
    map.rebuild_clearance();
    Ok(map)
}

/// Houses and trees on dry, gentle ground, placed by the same deterministic hash.
fn add_village(map: &mut BrickMap, terrain: &Terrain) {
    let size = terrain.size;
    let unit = (size[0].min(size[2]) / 64).max(2);
    let wall = Colour::from_rgb8(226, 214, 190);
    let roof = Colour::from_rgb8(168, 60, 44);
    let glass = Colour::from_rgb8(60, 80, 110);
    let trunk = Colour::from_rgb8(96, 64, 36);
    let leaves = Colour::from_rgb8(46, 112, 40);
    let mut placed = 0;
    for i in 0..400u32 {
        if placed >= 24 {
            break;
        }
        let x = (lattice(i as i32, 1, 11) * (size[0] - 8 * unit) as f32) as u32 + 4 * unit;
        let z = (lattice(i as i32, 2, 11) * (size[2] - 8 * unit) as f32) as u32 + 4 * unit;
        let (w, d) = (3 * unit, 2 * unit + (i % 3) * unit / 2);
        let corners = [(x, z), (x + w, z), (x, z + d), (x + w, z + d)]
            .map(|(cx, cz)| terrain.height(cx.min(size[0] - 1), cz.min(size[2] - 1)));
        let (lo, hi) = (
            corners.iter().min().copied().unwrap_or(0),
            corners.iter().max().copied().unwrap_or(0),
        );
        if lo <= terrain.water + 2 || hi - lo > unit || hi + 4 * unit >= size[1] {
            continue;
        }
        placed += 1;
        if i % 3 == 2 {
            // A tree.
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
            continue;
        }
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
            if step * 2 > d || y >= size[1] {
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
}
