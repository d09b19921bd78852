//! Large procedural worlds: terrain, water, trees and houses in the spirit of the demo scene,
//! generated tile by tile so a world far larger than memory is ever built whole.
//!
//! A world is cut into square **tiles** of [`TILE_EDGE`] voxels (full height). A tile's bricks
//! depend on the world's size, its seed and the tile alone, never on another tile: heights come
//! from noise over world coordinates (a brick column looks one voxel past its edges, as the
//! demo's does, so crusts meet without holes), and every tree or house lies inside one **site**
//! of [`SITE_EDGE`] voxels, which tiles never split. So tiles generate on any number of threads
//! in any order, and a caller streams each into a store as it comes
//! (`brickcast-server generate terrain`).
//!
//! Unlike the demo, whose noise scales with the scene (any size is one landscape), a world's
//! features have fixed sizes (hills of ~1,500 voxels, ridges of ~400, bumps of ~60), so a
//! larger world has more of them; the demo keeps its size and its voxels.

use crate::brick::BrickData;
use crate::demo::{Terrain, draw_house, draw_tree, lattice, relief};
use crate::map::{BrickMap, MapError};

/// Voxels along a tile's edge (32 brick columns).
pub const TILE_EDGE: u32 = 256;
/// Voxels along a site's edge: each holds at most one tree or house, inside it.
pub const SITE_EDGE: u32 = 64;
/// The size of the houses' and trees' parts (a house is 3 units wide).
const UNIT: u32 = 8;
/// Voxels between a site's edge and anything placed in it.
const SITE_MARGIN: u32 = 14;

/// A procedural world: its size and seed decide every voxel.
pub struct World {
    terrain: Terrain,
    seed: u32,
}

impl World {
    /// The world of `size` voxels from `seed`. Errors where a scene of that size could not be
    /// made ([`BrickMap::new`]).
    pub fn new(size: [u32; 3], seed: u32) -> Result<World, MapError> {
        BrickMap::check_size(size)?;
        let octave = |i: u32| seed.wrapping_mul(0x9E37_79B9).wrapping_add(101 + i);
        Ok(World {
            terrain: Terrain {
                size,
                water: relief(size) * 3 / 16,
                scales: [1536.0, 400.0, 60.0],
                seeds: [octave(0), octave(1), octave(2)],
            },
            seed,
        })
    }

    pub fn size(&self) -> [u32; 3] {
        self.terrain.size
    }

    /// Tiles along x and z.
    pub fn tiles(&self) -> [u32; 2] {
        let size = self.size();
        [size[0].div_ceil(TILE_EDGE), size[2].div_ceil(TILE_EDGE)]
    }

    /// The bricks of tile `[tx, tz]`, cells in world coordinates, each valid (as
    /// [`BrickMap::check_brick`] checks) and in no other tile. Empty past the world's tiles.
    pub fn tile(&self, [tx, tz]: [u32; 2]) -> Result<Vec<BrickData>, MapError> {
        let size = self.size();
        let origin = [tx * TILE_EDGE, tz * TILE_EDGE];
        if origin[0] >= size[0] || origin[1] >= size[2] {
            return Ok(Vec::new());
        }
        let extent = [
            (size[0] - origin[0]).min(TILE_EDGE),
            (size[2] - origin[1]).min(TILE_EDGE),
        ];
        // The tile as a small map in its own coordinates: the drawing primitives clip to it.
        let mut map = BrickMap::new([extent[0], size[1], extent[1]])?;
        let cells = map.cell_dims();
        let base = origin.map(|o| o / crate::brick::BRICK_EDGE);
        let mut heights = Vec::new();
        for cz in 0..cells[2] {
            for cx in 0..cells[0] {
                let mut result = Ok(());
                self.terrain
                    .crust(base[0] + cx, base[1] + cz, &mut heights, |mut brick| {
                        brick.cell = [
                            brick.cell[0] - base[0],
                            brick.cell[1],
                            brick.cell[2] - base[1],
                        ];
                        if result.is_ok() {
                            result = map.put_brick(&brick);
                        }
                    });
                result?;
            }
        }
        self.add_sites(&mut map, origin, extent);
        Ok(map
            .bricks()
            .map(|(mut brick, _)| {
                brick.cell = [
                    brick.cell[0] + base[0],
                    brick.cell[1],
                    brick.cell[2] + base[1],
                ];
                brick
            })
            .collect())
    }

    /// The whole world as one map: for tests and small worlds (a large one is streamed tile by
    /// tile instead).
    pub fn map(&self) -> Result<BrickMap, MapError> {
        let mut map = BrickMap::new(self.size())?;
        let [nx, nz] = self.tiles();
        for tz in 0..nz {
            for tx in 0..nx {
                for brick in self.tile([tx, tz])? {
                    map.put_brick(&brick)?;
                }
            }
        }
        map.rebuild_clearance();
        Ok(map)
    }

    /// Trees and houses of the sites inside the tile at `origin` (world x, z) of `extent`
    /// voxels, drawn into `map` (the tile's own coordinates). A site that would not fit inside
    /// the world is left empty.
    fn add_sites(&self, map: &mut BrickMap, origin: [u32; 2], extent: [u32; 2]) {
        let size = self.size();
        let seed = self.seed.wrapping_mul(0x85EB_CA6B) ^ 0x5EED;
        for sz in 0..extent[1].div_ceil(SITE_EDGE) {
            for sx in 0..extent[0].div_ceil(SITE_EDGE) {
                let (wx, wz) = (origin[0] + sx * SITE_EDGE, origin[1] + sz * SITE_EDGE);
                let (ix, iz) = ((wx / SITE_EDGE) as i32, (wz / SITE_EDGE) as i32);
                let kind = lattice(ix, iz, seed);
                // Forests where a slow noise says so, houses in clearings between them.
                let forest = crate::demo::value_noise(wx as f32, wz as f32, 900.0, seed ^ 7);
                let tree = kind < 0.15 + 0.55 * forest;
                let house = !tree && kind > 0.93;
                if !tree && !house {
                    continue;
                }
                let (w, d) = if tree {
                    (UNIT / 2, UNIT / 2)
                } else {
                    (
                        3 * UNIT,
                        2 * UNIT + (lattice(ix, iz, seed ^ 3) * 3.0) as u32 * UNIT / 2,
                    )
                };
                let room = SITE_EDGE - 2 * SITE_MARGIN;
                let jx = (lattice(ix, iz, seed ^ 1) * (room - w) as f32) as u32;
                let jz = (lattice(ix, iz, seed ^ 2) * (room - d.min(room)) as f32) as u32;
                let (x, z) = (wx + SITE_MARGIN + jx, wz + SITE_MARGIN + jz);
                if x + w + SITE_MARGIN > size[0] || z + d + SITE_MARGIN > size[2] {
                    continue;
                }
                let Some(ground) = self.terrain.building_ground(x, z, w, d, UNIT) else {
                    continue;
                };
                let local = [x - origin[0], z - origin[1]];
                if tree {
                    draw_tree(map, local, [ground.0, ground.1], UNIT);
                } else {
                    draw_house(map, local, [w, d], [ground.0, ground.1], UNIT);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_meet_without_holes_and_repeat_exactly() {
        // Three tiles by two, the last ones cut by the world's edge (seed 3: dry land there).
        let world = World::new([600, 128, 300], 3).unwrap();
        assert_eq!(world.tiles(), [3, 2]);
        let map = world.map().unwrap();
        map.check_invariants().unwrap();
        assert_eq!(map.content_hash(), world.map().unwrap().content_hash());
        assert_ne!(
            map.content_hash(),
            World::new([600, 128, 300], 4)
                .unwrap()
                .map()
                .unwrap()
                .content_hash(),
            "another seed, another world"
        );
        // Every voxel column has ground (or water) under the sky, across tile edges too.
        for x in 0..600 {
            for z in 0..300 {
                assert!(
                    (0..128).any(|y| map.is_solid([x, y, z])),
                    "a hole at ({x}, {z})"
                );
            }
        }
        // Something stands on the ground: more than the crust and water alone.
        let bare = Terrain {
            ..World::new([600, 128, 300], 3).unwrap().terrain
        };
        let mut crust = 0u64;
        let mut heights = Vec::new();
        for cz in 0..300u32.div_ceil(8) {
            for cx in 0..600u32.div_ceil(8) {
                bare.crust(cx, cz, &mut heights, |b| crust += b.colours.len() as u64);
            }
        }
        assert!(
            map.solid_voxels() > crust,
            "{} vs {crust}",
            map.solid_voxels()
        );
    }

    #[test]
    fn a_tile_is_the_same_alone_and_in_any_order() {
        let world = World::new([512, 96, 512], 3).unwrap();
        let a = world.tile([1, 0]).unwrap();
        let _ = world.tile([0, 1]).unwrap();
        assert_eq!(a, world.tile([1, 0]).unwrap());
        assert!(
            a.iter()
                .all(|b| (32..64).contains(&b.cell[0]) && b.cell[2] < 32)
        );
        assert!(world.tile([2, 0]).unwrap().is_empty(), "past the world");
    }

    #[test]
    fn sizes_past_the_limit_are_refused() {
        assert!(World::new([0, 64, 64], 1).is_err());
        assert!(World::new([crate::map::MAX_SCENE_EDGE + 8, 64, 64], 1).is_err());
        assert!(World::new([16384; 3], 1).is_err(), "too many regions");
    }

    #[test]
    fn brickmaps_world_size_generates_to_its_far_corner() {
        let world = World::new([16384, 512, 16384], 7).unwrap();
        assert_eq!(world.tiles(), [64, 64]);
        let corner = world.tile([63, 63]).unwrap();
        assert!(!corner.is_empty());
        let mut map = BrickMap::new(world.size()).unwrap();
        for brick in &corner {
            map.check_brick(brick).unwrap();
            assert!(brick.cell[0] >= 63 * 32 && brick.cell[2] >= 63 * 32);
        }
        for brick in corner {
            map.put_brick(&brick).unwrap();
        }
        assert!(map.brick_count() > 0);
    }
}
