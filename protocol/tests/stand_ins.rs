//! Maps whose regions are shown at mixed levels: level 0 near, coarse bricks of the pyramid
//! standing in further away (`map::stand_in`, issue #30). What such a map shows must be exactly
//! what the same map with every stand-in written out as level-0 voxels (each coarse voxel a
//! solid cube of 2^k voxels, clipped to its region) shows: hits, normals, colours, shading,
//! ambient occlusion and shadows, bit for bit.

use brickcast_protocol::brick::{BRICK_EDGE, Mask, bit_voxel, mask_get, mask_set, rank};
use brickcast_protocol::lod::Pyramid;
use brickcast_protocol::map::{
    BrickMap, BrushMode, GpuChanges, MapError, box_points, coarse_bit, region_stand_in,
};
use brickcast_protocol::render::{Camera, Lighting, render};
use brickcast_protocol::trace::{Ray, trace};
use brickcast_protocol::{BrickData, Colour};

/// Wide enough on x for level 6 (64-voxel voxels, 2×2×2 regions), with partial regions and
/// bricks at every far edge.
const SIZE: [u32; 3] = [300, 70, 141];

/// Seeded ChaCha8 (`rand_chacha`: the same numbers on every platform and rand release).
struct Rng(rand_chacha::ChaCha8Rng);

impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(rand::SeedableRng::seed_from_u64(seed))
    }
    fn below(&mut self, n: u32) -> u32 {
        rand::Rng::random_range(&mut self.0, 0..n)
    }
    fn unit(&mut self) -> f32 {
        rand::Rng::random(&mut self.0)
    }
}

/// Terrain, boxes, spheres, thin pillars and lone voxels of several colours: lone voxels and
/// thin walls become whole coarse voxels, the cases where levels differ most.
fn scene(seed: u64) -> BrickMap {
    let mut rng = Rng::new(seed);
    let mut map = BrickMap::new(SIZE).unwrap();
    for x in (0..SIZE[0]).step_by(20) {
        for z in (0..SIZE[2]).step_by(20) {
            let h = 3 + rng.below(12);
            let colour = Colour(0x2000 + rng.below(8) as u16 * 0x0841);
            map.fill_box(
                [x, 0, z],
                [(x + 19).min(SIZE[0] - 1), h, (z + 19).min(SIZE[2] - 1)],
                BrushMode::Fill,
                colour,
            );
        }
    }
    for _ in 0..10 {
        let c = [rng.below(SIZE[0]), 10 + rng.below(50), rng.below(SIZE[2])];
        let r = 2.0 + rng.below(12) as f32;
        map.sphere(
            c.map(|v| v as f32 + 0.5),
            r,
            BrushMode::Fill,
            Colour(rng.below(0xFFFF) as u16),
        );
    }
    for _ in 0..12 {
        let p = [rng.below(SIZE[0]), 0, rng.below(SIZE[2])];
        let top = rng.below(SIZE[1]);
        map.fill_box(p, [p[0], top, p[2]], BrushMode::Fill, Colour(0xF800));
    }
    for _ in 0..40 {
        let p = [rng.below(SIZE[0]), rng.below(SIZE[1]), rng.below(SIZE[2])];
        map.set(p, Colour(rng.below(0xFFFF) as u16));
    }
    map
}

/// The map with every stand-in written out as level-0 voxels.
fn written_out(mixed: &BrickMap) -> BrickMap {
    let mut out = BrickMap::new(mixed.size()).unwrap();
    for (brick, _) in mixed.bricks() {
        out.put_brick(&brick).unwrap();
    }
    let size = mixed.size();
    let mut scratch = [Colour::BLACK; 512];
    for r in box_points([0; 3], mixed.region_dims()) {
        let Some((level, slot)) = mixed.stand_in(r) else {
            continue;
        };
        let coarse_mask = mixed.masks()[slot as usize];
        let coarse = mixed.slot_colours(slot, &mut scratch).to_vec();
        for cell in mixed.region_cells(r) {
            let mut mask: Mask = [0; 8];
            let mut colours = Vec::new();
            for bit in 0..512 {
                let l = bit_voxel(bit);
                let p: [u32; 3] = std::array::from_fn(|i| cell[i] * BRICK_EDGE + l[i]);
                if (0..3).any(|i| p[i] >= size[i]) {
                    continue;
                }
                let cb = coarse_bit(p, level);
                if mask_get(&coarse_mask, cb) {
                    mask_set(&mut mask, bit, true);
                    colours.push(coarse[rank(&coarse_mask, cb) as usize]);
                }
            }
            if !colours.is_empty() {
                out.put_brick(&BrickData {
                    cell,
                    mask,
                    colours,
                })
                .unwrap();
            }
        }
    }
    out.rebuild_clearance();
    out
}

/// A mixed map of `scene(seed)`: each region at a random one of 0, 2, 3, 4, 5, 6, except that
/// with `near` the regions within 2 of it are level 0 (a client's working set has that shape).
fn mixed(seed: u64, near: Option<[u32; 3]>) -> (BrickMap, BrickMap) {
    let base = scene(seed);
    let pyramid = Pyramid::build(&base).unwrap();
    assert!(
        pyramid.level_count() >= 6,
        "the scene is meant to have level 6"
    );
    let mut rng = Rng::new(seed ^ 0xABCD);
    let map = pyramid
        .mixed(&base, |r| {
            if near.is_some_and(|n| (0..3).all(|i| r[i].abs_diff(n[i]) <= 2)) {
                return 0;
            }
            [0, 2, 3, 4, 5, 6][rng.below(6) as usize]
        })
        .unwrap();
    map.check_invariants().unwrap();
    assert!(map.stand_in_count() > 0 && map.brick_count() > 0);
    let out = written_out(&map);
    out.check_invariants().unwrap();
    (map, out)
}

fn random_ray(rng: &mut Rng) -> Ray {
    let origin: [f32; 3] = std::array::from_fn(|i| {
        let span = SIZE[i] as f32 + 60.0;
        let v = rng.unit() * span - 30.0;
        // Every fourth coordinate on a voxel plane: the ties the event order decides.
        if rng.below(4) == 0 { v.floor() } else { v }
    });
    let mut dir: [f32; 3] = std::array::from_fn(|_| rng.unit() * 2.0 - 1.0);
    // Some rays parallel to an axis plane, some along an axis.
    match rng.below(6) {
        0 => dir[rng.below(3) as usize] = 0.0,
        1 => {
            let keep = rng.below(3) as usize;
            for (i, d) in dir.iter_mut().enumerate() {
                if i != keep {
                    *d = 0.0;
                }
            }
        }
        2 => {
            // Exact diagonals cross several planes at once.
            dir = dir.map(|d| if d < 0.0 { -1.0 } else { 1.0 });
        }
        _ => {}
    }
    Ray { origin, dir }
}

#[test]
fn stand_ins_trace_like_their_voxels_written_out() {
    for seed in 0..4u64 {
        let (map, out) = mixed(seed, None);
        let mut rng = Rng::new(seed + 100);
        let mut hits = 0;
        for i in 0..4000 {
            let ray = random_ray(&mut rng);
            let (a, b) = (trace(&map, &ray), trace(&out, &ray));
            assert_eq!(a, b, "seed {seed}, ray {i}: {ray:?}");
            hits += usize::from(a.is_some());
        }
        assert!(
            hits > 1000,
            "seed {seed}: only {hits} rays hit: the test would prove little"
        );
    }
}

#[test]
fn frames_with_stand_ins_render_like_their_voxels_written_out() {
    // A camera in a level-0 neighbourhood looking out over coarser regions, and one far above.
    let (map, out) = mixed(7, Some([4, 1, 2]));
    let cameras = [
        Camera {
            eye: [150.0, 30.0, 70.0],
            target: [290.0, 5.0, 120.0],
            fov_y: 70.0,
        },
        Camera {
            eye: [-60.0, 140.0, -50.0],
            target: [150.0, 10.0, 70.0],
            fov_y: 50.0,
        },
    ];
    let lighting = Lighting::default();
    assert!(lighting.shadows && lighting.ao);
    for (i, camera) in cameras.iter().enumerate() {
        let projection = camera.project(120, 80).unwrap();
        let a = render(&map, &projection, &lighting, 1);
        let b = render(&out, &projection, &lighting, 1);
        let differ = a
            .pixels
            .iter()
            .zip(&b.pixels)
            .filter(|(p, q)| p != q)
            .count();
        assert_eq!(differ, 0, "camera {i}: {differ} pixels differ");
        assert_eq!(a.hits, b.hits, "camera {i}");
        // Sky and scene both in view, or the comparison says little.
        let misses = a.hits.iter().filter(|&&h| h == u32::MAX).count();
        assert!(misses < a.hits.len() * 9 / 10, "camera {i}: mostly sky");
    }
}

/// The map's GPU arrays as a client mirrors them from the change log alone.
#[derive(Default)]
struct Mirror {
    regions: Vec<u32>,
    masks: Vec<Mask>,
}

impl Mirror {
    fn apply(&mut self, map: &BrickMap, changes: &GpuChanges) {
        self.regions.resize(map.regions().len(), 0xDEAD_BEEF);
        self.masks.resize(map.masks().len(), [0xDEAD; 8]);
        for &r in &changes.regions {
            self.regions[r as usize] = map.regions()[r as usize];
        }
        for &s in &changes.slots {
            self.masks[s as usize] = map.masks()[s as usize];
        }
    }
}

#[test]
fn stand_ins_refuse_bad_requests_and_give_way_to_level_0() {
    let mut map = BrickMap::new([100, 70, 70]).unwrap();
    map.record_gpu_changes(true);
    let mut mirror = Mirror::default();
    map.set([3, 3, 3], Colour(9));
    let mut mask: Mask = [0; 8];
    mask_set(&mut mask, 0, true);
    mask_set(&mut mask, 9, true);
    let slot = map.add_coarse(mask, &[Colour(1), Colour(2)]).unwrap();
    let level0_slot = map.slot_of_cell([0, 0, 0]).unwrap();

    // Refusals change nothing.
    let before = map.content_hash();
    let refused = [
        map.set_stand_in([0, 0, 0], Some((2, slot))),
        map.set_stand_in([1, 0, 0], Some((1, slot))),
        map.set_stand_in([1, 0, 0], Some((15, slot))),
        map.set_stand_in([1, 0, 0], Some((3, level0_slot))),
        map.set_stand_in([1, 0, 0], Some((3, 999))),
        map.set_stand_in([4, 0, 0], Some((3, slot))),
        map.remove_coarse(level0_slot).map(|_| ()),
        map.add_coarse([0; 8], &[]).map(|_| ()),
        map.add_coarse(mask, &[Colour(1)]).map(|_| ()),
    ];
    assert!(matches!(
        refused[0],
        Err(MapError::RegionHoldsBricks([0, 0, 0]))
    ));
    assert!(refused.iter().all(Result::is_err), "{refused:?}");
    assert_eq!(map.stand_in_count(), 0);
    assert_eq!(map.content_hash(), before);
    map.check_invariants().unwrap();

    // A stand-in shows its coarse voxels; the coarse brick is no brick of the scene.
    map.set_stand_in([1, 0, 0], Some((3, slot))).unwrap();
    map.set_stand_in([2, 1, 1], Some((3, slot))).unwrap();
    map.check_invariants().unwrap();
    assert_eq!(map.stand_in_count(), 2);
    assert_eq!(map.brick_count(), 1);
    assert_eq!(map.bricks().count(), 1);
    assert_eq!(map.content_hash(), before);
    // Region [1, 0, 0] shows level-3 voxels x 4..8 of the brick: its solid ones (x 0, 1) are
    // outside it.
    assert!(!map.looks_solid([40, 0, 0]));
    let mut low: Mask = [0; 8];
    mask_set(&mut low, 0, true);
    let low_slot = map.add_coarse(low, &[Colour(5)]).unwrap();
    map.set_stand_in([0, 1, 0], Some((2, low_slot))).unwrap();
    // Level 2: voxel (0, 0, 0) of the brick is voxels 0..4 of region (0, 1, 0) (y 32..36).
    assert!(map.looks_solid([0, 32, 0]) && map.looks_solid([3, 35, 3]));
    assert!(!map.looks_solid([4, 32, 0]) && !map.is_solid([0, 32, 0]));
    let up = Ray {
        origin: [1.5, 20.5, 1.5],
        dir: [0.0, 1.0, 0.0],
    };
    let hit = trace(&map, &up).unwrap();
    assert_eq!(
        (hit.voxel, hit.colour, hit.normal),
        ([1, 32, 1], Colour(5), [0, -1, 0])
    );
    map.check_invariants().unwrap();

    // A level-0 brick written there replaces the stand-in.
    map.set([1, 40, 1], Colour(7));
    assert_eq!(map.stand_in([0, 1, 0]), None);
    assert_eq!(map.stand_in_count(), 2);
    assert!(!map.looks_solid([0, 32, 0]));
    assert_eq!(trace(&map, &up).unwrap().voxel, [1, 40, 1]);
    map.check_invariants().unwrap();

    // Cleared and freed; the slot is reused by the next brick.
    map.set_stand_in([1, 0, 0], None).unwrap();
    map.set_stand_in([2, 1, 1], None).unwrap();
    map.set_stand_in([2, 1, 1], None).unwrap();
    assert_eq!(map.stand_in_count(), 0);
    map.remove_coarse(slot).unwrap();
    assert!(map.remove_coarse(slot).is_err());
    map.remove_coarse(low_slot).unwrap();
    map.check_invariants().unwrap();
    map.set([90, 30, 60], Colour(3));
    assert!(
        [slot, low_slot].contains(&map.slot_of_cell([11, 3, 7]).unwrap()),
        "a freed coarse slot is reused"
    );
    map.check_invariants().unwrap();

    // The client's mirror, fed only the change log, holds the same regions and masks.
    let changes = map.take_gpu_changes();
    mirror.apply(&map, &changes);
    assert_eq!(mirror.regions, map.regions());
    for s in 0..map.masks().len() {
        let live = map
            .bricks()
            .any(|(b, _)| map.slot_of_cell(b.cell) == Some(s as u32));
        if live {
            assert_eq!(mirror.masks[s], map.masks()[s], "slot {s}");
        }
    }
    assert!(map.regions().iter().all(|&e| region_stand_in(e).is_none()));
}

/// Clearance stays conservative (no empty region claims past an occupied one) however regions
/// come and go: level-0 bricks and stand-ins set one by one (lowered shell by shell, stopping
/// where nothing needs it) and boxes of stand-ins set under a deferral (lowered once around
/// their box), scattered through a sparse grid where clearance matters, with removals between.
#[test]
fn clearance_stays_conservative_as_regions_come_and_go() {
    let mut map = BrickMap::new([1024, 128, 1024]).unwrap();
    let dims = map.region_dims();
    let mut rng = Rng::new(5);
    let mut mask: Mask = [0; 8];
    mask_set(&mut mask, 0, true);
    let slot = map.add_coarse(mask, &[Colour(3)]).unwrap();
    let mut stand_ins = Vec::new();
    for step in 0..300 {
        let r = [rng.below(dims[0]), rng.below(dims[1]), rng.below(dims[2])];
        match rng.below(5) {
            0 | 1 => {
                if map.stand_in(r).is_none() {
                    map.set(r.map(|v| v * 32 + 5), Colour(7));
                }
            }
            2 => {
                if map.set_stand_in(r, Some((2, slot))).is_ok() {
                    stand_ins.push(r);
                }
            }
            3 => {
                // A coarse brick's worth of regions at once, some of it already held.
                let hi: [u32; 3] =
                    std::array::from_fn(|i| (r[i] + 1 + rng.below(4)).min(dims[i] - 1));
                map.defer_region_clearance();
                for q in box_points(r, hi.map(|v| v + 1)) {
                    if rng.below(4) != 0 && map.set_stand_in(q, Some((4, slot))).is_ok() {
                        stand_ins.push(q);
                    }
                }
                map.lower_deferred_region_clearance();
            }
            _ => {
                if let Some(q) = stand_ins.pop() {
                    map.set_stand_in(q, None).unwrap();
                }
                map.clear(r.map(|v| v * 32 + 5));
            }
        }
        if let Err(e) = map.check_invariants() {
            panic!("step {step}: {e}");
        }
        if step % 50 == 49 {
            map.rebuild_clearance();
        }
    }
}
