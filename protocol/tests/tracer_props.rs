//! Property tests of the CPU tracer.
//!
//! Two oracles: (1) the same DDA over a flat voxel array, voxel by voxel, which the hierarchical
//! tracer must match exactly (same voxel, normal, previous cell and distance) on every ray; and
//! (2) brute-force slab intersection against every solid voxel, which checks the DDA itself
//! against geometry (the hit is where the ray first enters solid space, up to float tolerance).

use brickcast_protocol::Colour;
use brickcast_protocol::beam::{TILE, TileStarts};
use brickcast_protocol::map::{BrickMap, BrushMode};
use brickcast_protocol::render::Camera;
use brickcast_protocol::trace::{Ray, trace, trace_flat, trace_from};
use proptest::prelude::*;

#[derive(Debug, Clone)]
enum Shape {
    Voxel([u32; 3]),
    Box([u32; 3], [u32; 3]),
    Sphere([f32; 3], f32),
}

fn scene(size: [u32; 3], shapes: &[Shape]) -> BrickMap {
    let mut map = BrickMap::new(size).unwrap();
    for (i, shape) in shapes.iter().enumerate() {
        let colour = Colour(i as u16 * 97 + 1);
        match *shape {
            Shape::Voxel(p) => {
                map.set(p, colour);
            }
            Shape::Box(a, b) => {
                let lo = [a[0].min(b[0]), a[1].min(b[1]), a[2].min(b[2])];
                let hi = [a[0].max(b[0]), a[1].max(b[1]), a[2].max(b[2])];
                map.fill_box(lo, hi, BrushMode::Fill, colour);
            }
            Shape::Sphere(c, r) => {
                map.sphere(c, r, BrushMode::Fill, colour);
            }
        }
    }
    map
}

fn shape(size: [u32; 3]) -> impl Strategy<Value = Shape> {
    let p = (0..size[0], 0..size[1], 0..size[2]).prop_map(|(x, y, z)| [x, y, z]);
    let f = (
        0.0..size[0] as f32,
        0.0..size[1] as f32,
        0.0..size[2] as f32,
    )
        .prop_map(|(x, y, z)| [x, y, z]);
    prop_oneof![
        4 => p.clone().prop_map(Shape::Voxel),
        2 => (p.clone(), p).prop_map(|(a, b)| {
            // Keep boxes small so rays see structure, not one solid block.
            let b = std::array::from_fn(|i| a[i] + b[i] % 6);
            Shape::Box(a, b)
        }),
        1 => (f, 0.5f32..6.0).prop_map(|(c, r)| Shape::Sphere(c, r)),
    ]
}

/// Rays of every troublesome kind: random, axis-parallel, along exact voxel planes and edges,
/// through exact corners (integer origins, diagonal directions), from inside the grid.
fn ray(size: [u32; 3]) -> impl Strategy<Value = Ray> {
    let s = size.map(|c| c as f32);
    let anywhere = (-30.0..s[0] + 30.0, -30.0..s[1] + 30.0, -30.0..s[2] + 30.0)
        .prop_map(|(x, y, z)| [x, y, z]);
    let lattice = (
        -3i32..size[0] as i32 + 3,
        -3i32..size[1] as i32 + 3,
        -3i32..size[2] as i32 + 3,
        0u8..2,
    )
        .prop_map(|(x, y, z, half)| {
            let h = f32::from(half) * 0.5;
            [x as f32 + h, y as f32, z as f32 + h]
        });
    let random_dir = (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0).prop_map(|(x, y, z)| [x, y, z]);
    let lattice_dir =
        (-2i32..=2, -2i32..=2, -2i32..=2).prop_map(|(x, y, z)| [x as f32, y as f32, z as f32]);
    prop_oneof![
        3 => (anywhere.clone(), random_dir.clone()),
        2 => (lattice.clone(), lattice_dir.clone()),
        1 => (anywhere, lattice_dir),
        1 => (lattice, random_dir),
    ]
    .prop_map(|(origin, dir)| Ray { origin, dir })
}

fn dims() -> impl Strategy<Value = [u32; 3]> {
    prop_oneof![
        3 => (1u32..48, 1u32..48, 1u32..48).prop_map(|(x, y, z)| [x, y, z]),
        1 => (60u32..140, 1u32..20, 60u32..140).prop_map(|(x, y, z)| [x, y, z]),
        // Large and sparse: empty regions with wide clearance, so rays take the long jumps.
        1 => (150u32..420, 8u32..100, 150u32..420).prop_map(|(x, y, z)| [x, y, z]),
    ]
}

fn case() -> impl Strategy<Value = ([u32; 3], Vec<Shape>, Vec<Ray>)> {
    dims().prop_flat_map(|size| {
        (
            Just(size),
            prop::collection::vec(shape(size), 0..24),
            prop::collection::vec(ray(size), 1..48),
        )
    })
}

/// An independent flat copy of the voxels (index `x + sx·(y + sy·z)`), so a reference tracer
/// does not read the brick map.
fn flat_copy(map: &BrickMap) -> Vec<Option<Colour>> {
    let size = map.size();
    let mut flat = vec![None; (size[0] * size[1] * size[2]) as usize];
    for (brick, _) in map.bricks() {
        for b in 0..512u32 {
            if let Some(c) = brick.colour_at(b) {
                let l = brickcast_protocol::brick::bit_voxel(b);
                let v: [u32; 3] = std::array::from_fn(|i| brick.cell[i] * 8 + l[i]);
                flat[(v[0] + size[0] * (v[1] + size[1] * v[2])) as usize] = Some(c);
            }
        }
    }
    flat
}

/// Slab interval `(enter, exit)` of a ray against one voxel, in f64.
fn slab(ray: &Ray, v: [u32; 3]) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    for ((&o, &d), &corner) in ray.origin.iter().zip(&ray.dir).zip(&v) {
        let (o, d) = (f64::from(o), f64::from(d));
        let (lo, hi) = (f64::from(corner), f64::from(corner) + 1.0);
        if d.abs() < 1e-30 {
            if o < lo || o >= hi {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo - o) / d, (hi - o) / d);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t1 >= t0.max(0.0)).then_some((t0.max(0.0), t1))
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn hierarchy_matches_flat_grid_exactly((size, shapes, rays) in case()) {
        let map = scene(size, &shapes);
        let flat = flat_copy(&map);
        let lookup = |v: [u32; 3]| flat[(v[0] + size[0] * (v[1] + size[1] * v[2])) as usize];
        // As edited (clearances only ever lowered) and with every clearance rebuilt to its
        // largest (so rays take the long jumps over empty regions and cells).
        let mut rebuilt = map.clone();
        rebuilt.rebuild_clearance();
        rebuilt.check_invariants().map_err(TestCaseError::fail)?;
        for ray in &rays {
            let reference = trace_flat(size, lookup, ray);
            prop_assert_eq!(trace(&map, ray), reference, "ray {:?}", ray);
            prop_assert_eq!(trace(&rebuilt, ray), reference, "ray {:?}, rebuilt", ray);
        }
        // Random rays rarely find small shapes in a big grid: also aim at solid voxels, from the
        // grid's corners and centre, across the empty cells and regions around them.
        let s = size.map(|c| c as f32);
        let origins = [
            [-3.0, -3.0, -3.0],
            [s[0] + 3.0, s[1] * 0.5, -2.0],
            [s[0] * 0.5 + 0.25, s[1] + 4.0, s[2] * 0.5 + 0.75],
            [-2.5, s[1] + 2.0, s[2] + 3.0],
            [s[0] * 0.37, s[1] * 0.61, s[2] * 0.29],
        ];
        let targets = (0..size[2]).flat_map(|z| (0..size[1]).flat_map(move |y| (0..size[0]).map(move |x| [x, y, z])))
            .filter(|&v| lookup(v).is_some())
            .step_by(7)
            .take(12);
        for target in targets {
            for origin in origins {
                let aim = [target[0] as f32 + 0.3, target[1] as f32 + 0.6, target[2] as f32 + 0.45];
                let ray = Ray { origin, dir: std::array::from_fn(|i| aim[i] - origin[i]) };
                let reference = trace_flat(size, lookup, &ray);
                prop_assert_eq!(trace(&rebuilt, &ray), reference, "aimed ray {:?}, rebuilt", ray);
                prop_assert_eq!(trace(&map, &ray), reference, "aimed ray {:?}", ray);
            }
        }
    }

    /// Starting later (what the beam pre-pass does) changes nothing as long as every voxel
    /// before the start is empty: any start before the hit's entry time, any start at all for
    /// a ray that misses. Checked against the flat DDA. This also covers the shortcut that settles a coordinate by `floor`
    /// alone when it is clearly inside a voxel.
    #[test]
    fn starting_later_on_empty_space_changes_nothing(
        (size, shapes, rays) in case(),
        fractions in prop::collection::vec(0.0f32..0.999, 48),
    ) {
        let mut map = scene(size, &shapes);
        map.rebuild_clearance();
        let flat = flat_copy(&map);
        let lookup = |v: [u32; 3]| flat[(v[0] + size[0] * (v[1] + size[1] * v[2])) as usize];
        for (ray, fraction) in rays.iter().zip(&fractions) {
            let full = trace_flat(size, lookup, ray);
            let t_min = match full {
                Some(hit) => hit.t * fraction,
                None => 1.0 + 400.0 * fraction,
            };
            if full.is_some_and(|hit| t_min >= hit.t || t_min.is_nan()) {
                continue;
            }
            prop_assert_eq!(trace_from(&map, ray, t_min), full, "ray {:?} from t = {}", ray, t_min);
        }
    }

    /// The beam pre-pass ([`TileStarts`]: the tile's march, its advance on the brick masks, the
    /// quarters' advances) gives every pixel a start after which its ray finds exactly the hit a
    /// plain trace finds: from cameras outside and inside the grid, near and far (beyond the
    /// range where the rounding margin is a fraction of a voxel), on maps as edited and with
    /// clearances rebuilt.
    #[test]
    fn beam_starts_change_no_pixel(
        (size, shapes, _) in case(),
        eye in (-1.5f32..2.5, -0.5f32..3.0, -1.5f32..2.5),
        target in (0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0),
        far in prop_oneof![4 => Just(1.0f32), 1 => Just(40.0f32)],
        fov in 5.0f32..120.0,
    ) {
        let mut map = scene(size, &shapes);
        let s = size.map(|c| c as f32);
        let camera = Camera {
            eye: [eye.0 * s[0] * far, eye.1 * s[1] * far, eye.2 * s[2] * far],
            target: [target.0 * s[0], target.1 * s[1], target.2 * s[2]],
            fov_y: fov,
        };
        let Some(p) = camera.project(40, 24) else { return Ok(()); };
        for rebuilt in [false, true] {
            if rebuilt {
                map.rebuild_clearance();
            }
            for ty in (0..p.height).step_by(TILE as usize) {
                for tx in (0..p.width).step_by(TILE as usize) {
                    let starts = TileStarts::new(&p, &map, tx, ty);
                    for y in ty..(ty + TILE).min(p.height) {
                        for x in tx..(tx + TILE).min(p.width) {
                            let ray = p.ray(x, y);
                            prop_assert_eq!(
                                trace_from(&map, &ray, starts.at(x, y)),
                                trace(&map, &ray),
                                "{:?} pixel ({}, {}) from t = {}, rebuilt: {}",
                                camera, x, y, starts.at(x, y), rebuilt
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn hits_agree_with_brute_force_geometry((size, shapes, rays) in case()) {
        let map = scene(size, &shapes);
        let solids: Vec<[u32; 3]> = map
            .bricks()
            .flat_map(|(b, _)| {
                (0..512u32).filter(move |&bit| brickcast_protocol::brick::mask_get(&b.mask, bit)).map(move |bit| {
                    let l = brickcast_protocol::brick::bit_voxel(bit);
                    std::array::from_fn(|i| b.cell[i] * 8 + l[i])
                })
            })
            .collect();
        for ray in &rays {
            let hit = trace(&map, ray);
            if ray.dir.iter().all(|c| c.abs() < 1e-30) {
                prop_assert_eq!(hit, None, "a zero direction is not a ray");
                continue;
            }
            // Brute force: the earliest entry into a voxel the ray really passes through (not
            // one it only touches at an edge or corner, where either answer is right).
            let len = f64::from(ray.dir.iter().map(|c| c * c).sum::<f32>().sqrt());
            let eps = 1e-3 / len.max(1e-6);
            let mut best: Option<(f64, [u32; 3])> = None;
            for &v in &solids {
                if let Some((t0, t1)) = slab(ray, v)
                    && t1 - t0 > eps
                    && best.is_none_or(|(b, _)| t0 < b)
                {
                    best = Some((t0, v));
                }
            }
            let tol = eps + 1e-4 * best.map_or(0.0, |b| b.0);
            match (hit, best) {
                (Some(h), best) => {
                    let (enter, exit) = slab(ray, h.voxel).unwrap_or((f64::NAN, f64::NAN));
                    let t = f64::from(h.t);
                    prop_assert!(
                        enter <= t + tol && t <= exit + tol && best.is_none_or(|(b, _)| t <= b + tol),
                        "ray {:?}: hit {:?} at {} (slab {}..{}), brute force enters solid at {:?}",
                        ray, h.voxel, h.t, enter, exit, best
                    );
                    prop_assert!(map.is_solid(h.voxel));
                    if let Some(p) = h.previous {
                        prop_assert!(!map.is_solid(p), "previous cell must be empty");
                        let d: i32 = (0..3).map(|i| (p[i] as i32 - h.voxel[i] as i32).abs()).sum();
                        prop_assert_eq!(d, 1, "previous is a face neighbour");
                    }
                }
                (None, Some((t0, v))) => {
                    prop_assert!(false, "ray {:?} missed voxel {:?} entered at {}", ray, v, t0);
                }
                (None, None) => {}
            }
        }
    }
}

/// A finite coordinate of any magnitude, from inside the scene out to `f32::MAX`, either sign.
fn wild_coordinate() -> impl Strategy<Value = f32> {
    prop_oneof![
        -100.0f32..200.0,
        (0.0f32..38.0, any::<bool>()).prop_map(|(e, neg)| {
            let v = 10f32.powf(e).min(f32::MAX);
            if neg { -v } else { v }
        }),
        Just(f32::MAX),
        Just(f32::MIN),
        Just(-2.2e9),
        Just(2.2e9),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Ray origins and directions are what a peer sends (ray edits): no finite value may
    /// overflow the tracer's integer arithmetic (tests run with overflow checks on), and a ray
    /// the hierarchy traces agrees with the flat DDA.
    #[test]
    fn rays_from_anywhere_never_overflow(
        origin in prop::array::uniform3(wild_coordinate()),
        dir in prop::array::uniform3(wild_coordinate()),
    ) {
        let map = scene([40, 24, 40], &[Shape::Box([0, 0, 0], [39, 3, 39]), Shape::Sphere([20.0, 8.0, 20.0], 5.0)]);
        let ray = Ray { origin, dir };
        let hit = trace(&map, &ray);
        let flat = trace_flat(map.size(), |p| map.get(p), &ray);
        prop_assert_eq!(hit.map(|h| h.voxel), flat.map(|h| h.voxel));
        let mut edited = map.clone();
        let op = brickcast_protocol::wire::EditOp::Ray {
            origin,
            dir,
            action: brickcast_protocol::wire::RayAction::Remove,
        };
        let _ = brickcast_protocol::apply::apply_op(&mut edited, &op, &Default::default());
    }
}
