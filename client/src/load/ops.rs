//! Generating one client's edit ops.
//!
//! Ops are random but reproducible (each client's generator is seeded with its index), cheap to
//! make (the generator must not compete with the server for the CPU), and balanced where that is
//! possible: half of them add and half remove, so a long run does not just fill its region.

use brickcast_protocol::wire::{BrushMode, EditOp, RayAction};
use brickcast_protocol::{BrickMap, Colour};
use rand::{Rng as _, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::options::{OpKind, VoxelBox};

/// Most solid voxels a paint client remembers as targets.
const PAINT_TARGETS: usize = 65_536;

/// Seeded ChaCha8 (`rand_chacha`, documented to give the same numbers on every platform and
/// rand release: a recorded run's seed replays) at a few nanoseconds a draw.
#[derive(Clone)]
pub struct Rng(ChaCha8Rng);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(ChaCha8Rng::seed_from_u64(seed))
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }

    /// Uniform in `lo..=hi`.
    pub fn between(&mut self, lo: u32, hi: u32) -> u32 {
        self.0.random_range(lo..=hi)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f32 {
        self.0.random()
    }

    pub fn coin(&mut self) -> bool {
        self.0.random()
    }
}

/// Makes the ops of one editing client.
pub struct OpGen {
    kind: OpKind,
    area: VoxelBox,
    radius: f32,
    rng: Rng,
    /// Solid voxels of the area when the client synced (`--op paint`).
    targets: Vec<[u32; 3]>,
}

/// Why a client cannot generate its ops.
#[derive(Debug, thiserror::Error)]
#[error("--op paint: the region {min:?}..={max:?} holds no solid voxel to paint")]
pub struct NothingToPaint {
    min: [u32; 3],
    max: [u32; 3],
}

impl OpGen {
    /// A generator for ops of `kind` in `area`. Paint ops pick among the solid voxels of `map`
    /// (the client's synced copy) inside `area`.
    pub fn new(
        kind: OpKind,
        area: VoxelBox,
        radius: f32,
        seed: u64,
        map: &BrickMap,
    ) -> Result<OpGen, NothingToPaint> {
        let mut rng = Rng::new(seed);
        let targets = if kind == OpKind::Paint {
            let targets = solid_voxels_in(map, area, PAINT_TARGETS, &mut rng);
            if targets.is_empty() {
                return Err(NothingToPaint {
                    min: area.min,
                    max: area.max,
                });
            }
            targets
        } else {
            Vec::new()
        };
        Ok(OpGen {
            kind,
            area,
            radius,
            rng,
            targets,
        })
    }

    fn voxel(&mut self) -> [u32; 3] {
        let a = self.area;
        [0, 1, 2].map(|i| self.rng.between(a.min[i], a.max[i]))
    }

    fn colour(&mut self) -> Colour {
        Colour(self.rng.next_u64() as u16)
    }

    pub fn next_op(&mut self) -> EditOp {
        match self.kind {
            OpKind::Voxel => {
                let pos = self.voxel();
                if self.rng.coin() {
                    EditOp::Set {
                        pos,
                        colour: self.colour(),
                    }
                } else {
                    EditOp::Clear { pos }
                }
            }
            OpKind::Sphere => {
                let a = self.area;
                // Centres anywhere in the area's volume, not only on voxel centres.
                let centre = [0, 1, 2].map(|i| {
                    let span = (a.max[i] - a.min[i]) as f32;
                    a.min[i] as f32 + 0.5 + self.rng.unit() * span
                });
                let mode = if self.rng.coin() {
                    BrushMode::Fill
                } else {
                    BrushMode::Erase
                };
                EditOp::Sphere {
                    centre,
                    radius: self.radius,
                    mode,
                    colour: self.colour(),
                }
            }
            OpKind::Paint => {
                let i = self.rng.between(0, self.targets.len() as u32 - 1) as usize;
                EditOp::Paint {
                    pos: self.targets[i],
                    colour: self.colour(),
                }
            }
            OpKind::Ray => {
                let a = self.area;
                let [x, _, z] = self.voxel();
                // From just above the area, down with a slight random tilt so rays meet faces
                // from every side.
                let origin = [x as f32 + 0.5, a.max[1] as f32 + 1.0, z as f32 + 0.5];
                let tilt = |r: &mut Rng| (r.unit() - 0.5) * 0.6;
                let dir = [tilt(&mut self.rng), -1.0, tilt(&mut self.rng)];
                let action = if self.rng.coin() {
                    RayAction::Place {
                        colour: self.colour(),
                    }
                } else {
                    RayAction::Remove
                };
                EditOp::Ray {
                    origin,
                    dir,
                    action,
                }
            }
        }
    }
}

/// Up to `cap` solid voxels of `map` inside `area`, a uniform sample (reservoir sampling) when
/// there are more.
pub fn solid_voxels_in(map: &BrickMap, area: VoxelBox, cap: usize, rng: &mut Rng) -> Vec<[u32; 3]> {
    let mut out = Vec::new();
    let mut seen: u64 = 0;
    for (cell, _) in map.brick_cells() {
        let base = cell.map(|c| c * 8);
        let overlaps = (0..3).all(|i| base[i] <= area.max[i] && base[i] + 7 >= area.min[i]);
        if !overlaps {
            continue;
        }
        let Some(brick) = map.brick(cell) else {
            continue;
        };
        for (w, &word) in brick.mask.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let b = w as u32 * 64 + bits.trailing_zeros();
                bits &= bits - 1;
                let p = [base[0] + b % 8, base[1] + (b / 8) % 8, base[2] + b / 64];
                if !area.contains(p) {
                    continue;
                }
                seen += 1;
                if out.len() < cap {
                    out.push(p);
                } else {
                    let j = rng.next_u64() % seen;
                    if (j as usize) < cap {
                        out[j as usize] = p;
                    }
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::wire::Limits;

    fn ground() -> BrickMap {
        let mut map = BrickMap::new([64, 32, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 7, 63], BrushMode::Fill, Colour(7));
        map
    }

    #[test]
    fn ops_stay_in_their_area_and_apply() {
        let area = VoxelBox {
            min: [8, 0, 16],
            max: [23, 15, 31],
        };
        let limits = Limits::default();
        for kind in [OpKind::Voxel, OpKind::Sphere, OpKind::Paint, OpKind::Ray] {
            let mut map = ground();
            let mut g = OpGen::new(kind, area, 3.0, 1, &map).unwrap();
            let mut changed = 0;
            for _ in 0..500 {
                let op = g.next_op();
                match op {
                    EditOp::Set { pos, .. } | EditOp::Clear { pos } | EditOp::Paint { pos, .. } => {
                        assert!(area.contains(pos), "{kind:?} {op:?}")
                    }
                    EditOp::Sphere { centre, .. } => {
                        for (i, c) in centre.into_iter().enumerate() {
                            assert!(c >= area.min[i] as f32 && c <= area.max[i] as f32 + 1.0);
                        }
                    }
                    EditOp::Ray { origin, dir, .. } => {
                        assert!(origin[1] > area.max[1] as f32 && dir[1] < 0.0);
                        assert!(
                            origin[0] >= area.min[0] as f32
                                && origin[0] <= area.max[0] as f32 + 1.0
                        );
                    }
                    EditOp::Box { .. }
                    | EditOp::Span { .. }
                    | EditOp::Swatch { .. }
                    | EditOp::Copy { .. }
                    | EditOp::Paste { .. }
                    | EditOp::Restore { .. } => {
                        panic!("no box, span, swatch, copy, paste or restore ops are generated")
                    }
                }
                // Every generated op is valid; rays may miss only if the area were empty.
                changed += brickcast_protocol::apply::apply_op(&mut map, &op, &limits)
                    .unwrap_or_else(|e| panic!("{kind:?} {op:?}: {e}"));
            }
            assert!(changed > 100, "{kind:?} changed only {changed} voxels");
        }
    }

    #[test]
    fn paint_targets_are_solid_and_inside() {
        let map = ground();
        let area = VoxelBox {
            min: [5, 5, 5],
            max: [20, 20, 20],
        };
        let mut rng = Rng::new(3);
        let all = solid_voxels_in(&map, area, usize::MAX, &mut rng);
        // Solid layers y = 5..=7 of a 16×16 column.
        assert_eq!(all.len(), 3 * 16 * 16);
        assert!(all.iter().all(|&p| area.contains(p) && map.is_solid(p)));
        let some = solid_voxels_in(&map, area, 100, &mut rng);
        assert_eq!(some.len(), 100);
        assert!(some.iter().all(|&p| area.contains(p) && map.is_solid(p)));
        let sky = VoxelBox {
            min: [0, 8, 0],
            max: [63, 31, 63],
        };
        assert!(OpGen::new(OpKind::Paint, sky, 1.0, 0, &map).is_err());
    }

    #[test]
    fn rng_between_covers_the_range() {
        let mut rng = Rng::new(9);
        let mut hits = [0u32; 5];
        for _ in 0..5000 {
            hits[(rng.between(10, 14) - 10) as usize] += 1;
        }
        assert!(hits.iter().all(|&h| h > 800), "{hits:?}");
        assert_eq!(rng.between(7, 7), 7);
    }
}
