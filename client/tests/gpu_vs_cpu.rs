//! The GPU tracer against its CPU twin: same scene, same camera, same lighting; every pixel must
//! agree on hit/miss and on the voxel hit, and colours must be within a small tolerance. Only a
//! handful of pixels whose ray grazes an exact voxel edge or corner may differ (the shader's float
//! arithmetic may be fused or reordered by the driver).
//!
//! These tests need a Vulkan adapter and pin `Backends::VULKAN`: on a machine without a GPU that is
//! Mesa's lavapipe (`mesa-vulkan-drivers`). They fail rather than skip when there is none, so a
//! CI run can never pass without having traced a single pixel on the GPU.

use brickcast_client::gpu::{BackendChoice, GpuContext, GpuScene, Tracer};
use brickcast_client::replica::Replica;
use brickcast_protocol::demo::demo_scene;
use brickcast_protocol::map::BrushMode;
use brickcast_protocol::render::{
    Camera, Frame, Lighting, MISS, Projection, colour_distance, render,
};
use brickcast_protocol::wire::{BrickBlob, ServerMsg};
use brickcast_protocol::{BrickMap, Colour};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Largest colour difference (max over channels, 0..255) allowed where both tracers hit the same
/// voxel. Shading is a few multiply-adds on the same inputs; rounding differs by at most a step.
const COLOUR_TOLERANCE: u32 = 2;

fn gpu() -> GpuContext {
    GpuContext::headless(BackendChoice::Vulkan).unwrap_or_else(|e| {
        panic!("GPU tests need a Vulkan adapter (lavapipe: apt-get install mesa-vulkan-drivers libvulkan1): {e}")
    })
}

/// Pixels allowed to differ: a handful, scaling gently with the image.
fn edge_allowance(projection: &Projection) -> usize {
    3 + (projection.width * projection.height) as usize / 2000
}

struct Comparison {
    hit_pixels: usize,
    hit_mismatches: Vec<(u32, u32, u32, u32)>,
    colour_mismatches: Vec<(u32, u32, [u8; 4], [u8; 4])>,
}

fn compare(cpu: &Frame, gpu: &Frame) -> Comparison {
    assert_eq!((cpu.width, cpu.height), (gpu.width, gpu.height));
    let mut c = Comparison {
        hit_pixels: 0,
        hit_mismatches: Vec::new(),
        colour_mismatches: Vec::new(),
    };
    for i in 0..cpu.pixels.len() {
        let (x, y) = (i as u32 % cpu.width, i as u32 / cpu.width);
        if cpu.hits[i] != MISS {
            c.hit_pixels += 1;
        }
        if cpu.hits[i] != gpu.hits[i] {
            c.hit_mismatches.push((x, y, cpu.hits[i], gpu.hits[i]));
        } else if colour_distance(cpu.pixels[i], gpu.pixels[i]) > COLOUR_TOLERANCE {
            c.colour_mismatches
                .push((x, y, cpu.pixels[i], gpu.pixels[i]));
        }
    }
    c
}

/// Traces `map` both ways and asserts they agree. Returns the number of pixels that hit.
fn assert_twins(
    label: &str,
    ctx: &GpuContext,
    scene: &GpuScene,
    tracer: &mut Tracer,
    map: &BrickMap,
    projection: &Projection,
) -> usize {
    let lighting = Lighting::default();
    let cpu = render(map, projection, &lighting, 0);
    tracer
        .trace(ctx, scene, projection, &lighting)
        .expect("GPU trace");
    let gpu = tracer
        .read_back(ctx)
        .expect("read back")
        .to_frame(map.size());
    let c = compare(&cpu, &gpu);
    let allowed = edge_allowance(projection);
    assert!(
        c.hit_mismatches.len() <= allowed,
        "{label}: {} of {} pixels hit a different voxel (allowed {allowed}); first: {:?}",
        c.hit_mismatches.len(),
        cpu.pixels.len(),
        &c.hit_mismatches[..c.hit_mismatches.len().min(8)]
    );
    // A shadow ray that grazes an edge flips a pixel between lit and shadowed: same budget.
    assert!(
        c.colour_mismatches.len() <= allowed,
        "{label}: {} pixels differ in colour by more than {COLOUR_TOLERANCE} (allowed {allowed}); first: {:?}",
        c.colour_mismatches.len(),
        &c.colour_mismatches[..c.colour_mismatches.len().min(8)]
    );
    c.hit_pixels
}

fn cameras(size: [u32; 3]) -> Vec<(&'static str, Camera)> {
    let s = size.map(|v| v as f32);
    vec![
        ("overview", Camera::overview(size)),
        (
            "inside, low and grazing",
            Camera {
                eye: [s[0] * 0.3, s[1] * 0.45, s[2] * 0.2],
                target: [s[0] * 0.8, s[1] * 0.2, s[2] * 0.9],
                fov_y: 70.0,
            },
        ),
        (
            "straight down an axis",
            Camera {
                eye: [s[0] * 0.5 + 0.25, s[1] * 2.0, s[2] * 0.5 + 0.25],
                target: [s[0] * 0.5, 0.0, s[2] * 0.5],
                fov_y: 40.0,
            },
        ),
        (
            "from below, outside the grid",
            Camera {
                eye: [-s[0] * 0.4, -s[1] * 0.8, s[2] * 1.3],
                target: [s[0] * 0.5, s[1] * 0.3, s[2] * 0.5],
                fov_y: 60.0,
            },
        ),
    ]
}

/// A scene of random boxes and spheres, sizes not multiples of a brick or a region.
fn scattered_scene(size: [u32; 3], seed: u64) -> BrickMap {
    let mut map = BrickMap::new(size).expect("scene size");
    // Seeded ChaCha8 (`rand_chacha`: the same scene on every platform and rand release).
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut next = move |n: u32| rng.random_range(0..n.max(1));
    for i in 0..40 {
        let colour = Colour::from_rgb8(next(256) as u8, next(256) as u8, next(256) as u8);
        if i % 2 == 0 {
            let min = [next(size[0]), next(size[1]), next(size[2])];
            let max = [
                (min[0] + next(24)).min(size[0] - 1),
                (min[1] + next(24)).min(size[1] - 1),
                (min[2] + next(24)).min(size[2] - 1),
            ];
            map.fill_box(min, max, BrushMode::Fill, colour);
        } else {
            let centre = [
                next(size[0]) as f32,
                next(size[1]) as f32,
                next(size[2]) as f32,
            ];
            map.sphere(centre, 2.0 + next(10) as f32, BrushMode::Fill, colour);
        }
    }
    // Bricks of noise from 3, 12, 200 and 4096 colours: every colour coding (2- to 8-bit
    // palettes and raw) on both tracers.
    for (k, shades) in [3u32, 12, 200, 4096].into_iter().enumerate() {
        let lo = [next(size[0] - 8), next(size[1] - 8), next(size[2] - 8)];
        let palette: Vec<Colour> = (0..shades)
            .map(|_| Colour::from_rgb8(next(256) as u8, next(256) as u8, 40 * k as u8))
            .collect();
        for z in 0..8 {
            for y in 0..8 {
                for x in 0..8 {
                    let c = palette[next(shades) as usize];
                    map.set([lo[0] + x, lo[1] + y, lo[2] + z], c);
                }
            }
        }
    }
    // Single voxels: the smallest thing a ray can hit.
    for _ in 0..200 {
        let p = [next(size[0]), next(size[1]), next(size[2])];
        map.set(p, Colour::from_rgb8(250, 240, 20));
    }
    map.rebuild_clearance();
    map
}

#[test]
fn demo_scene_matches_the_cpu_tracer_from_several_cameras() {
    let ctx = gpu();
    let mut map = demo_scene([192, 96, 160]).expect("demo scene");
    let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    for (label, camera) in cameras(map.size()) {
        let projection = camera.project(160, 96).expect("camera");
        assert_twins(label, &ctx, &scene, &mut tracer, &map, &projection);
    }
    // The overview must actually look at something, or the comparison proves little.
    let projection = Camera::overview(map.size())
        .project(160, 96)
        .expect("camera");
    let hits = assert_twins(
        "overview again",
        &ctx,
        &scene,
        &mut tracer,
        &map,
        &projection,
    );
    assert!(hits > 160 * 96 / 3, "overview hit only {hits} pixels");
}

/// An untextured enclosed room seen from its first camera (inside): the sun reaches nothing, so
/// only the sky light, ambient occlusion and the headlight can tell faces apart. Both twins must
/// agree, and faces of the one grey that face different ways must differ visibly.
#[test]
fn enclosed_room_matches_and_shows_its_shape() {
    use brickcast_protocol::trace::trace;
    use brickcast_protocol::viewpoint::{Placement, find};
    let ctx = gpu();
    let mut map = brickcast_protocol::demo::room_scene([160, 72, 128]).expect("room");
    let found = find(&map, 60.0);
    assert!(matches!(found.placement, Placement::Inside), "{found:?}");
    let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    let projection = found.camera.project(192, 108).expect("camera");
    let hits = assert_twins("room", &ctx, &scene, &mut tracer, &map, &projection);
    assert_eq!(hits, 192 * 108, "an enclosed room: every pixel hits");

    // Group the CPU picture's pixels by the direction of the face they show.
    let frame = render(&map, &projection, &Lighting::default(), 0);
    let mut by_normal: std::collections::BTreeMap<[i32; 3], Vec<u8>> = Default::default();
    for y in 0..projection.height {
        for x in 0..projection.width {
            if let Some(hit) = trace(&map, &projection.ray(x, y)) {
                let grey = frame.pixels[(y * projection.width + x) as usize][0];
                by_normal.entry(hit.normal).or_default().push(grey);
            }
        }
    }
    let medians: Vec<([i32; 3], u8)> = by_normal
        .into_iter()
        .filter(|(_, v)| v.len() >= 100)
        .map(|(n, mut v)| {
            v.sort_unstable();
            (n, v[v.len() / 2])
        })
        .collect();
    assert!(
        medians.len() >= 4,
        "the view shows floor, walls and furniture sides: {medians:?}"
    );
    for (i, (na, a)) in medians.iter().enumerate() {
        for (nb, b) in &medians[i + 1..] {
            assert!(
                a.abs_diff(*b) >= 6,
                "faces facing {na:?} and {nb:?} look alike ({a} vs {b}): {medians:?}"
            );
        }
    }
    // The old lighting (a constant ambient, no sun indoors) painted all of them one grey.
    let flat = Lighting {
        sky: 0.0,
        headlight: 0.0,
        ao: false,
        ..Lighting::default()
    };
    let dark = render(&map, &projection, &flat, 0);
    assert!(
        dark.pixels.iter().all(|p| p[0] == dark.pixels[0][0]),
        "without sky light every face is alike"
    );
}

/// Scenes made by the mesh importer: surfaces at every angle, one voxel thick, textured.
#[test]
fn voxelized_mesh_matches_the_cpu_tracer() {
    use brickcast_server::import::mesh::Mesh;
    use brickcast_server::import::{ImportOptions, NoProgress, voxelize::voxelize};
    // A tilted box with a slanted roof: faces off the axes, shared edges, and an inside.
    let (s, c) = (0.5f32.sin(), 0.5f32.cos());
    let turn = |p: [f32; 3]| [c * p[0] - s * p[2], p[1], s * p[0] + c * p[2]];
    let corners: Vec<[f32; 3]> = [
        [0.0, 0.0, 0.0],
        [4.0, 0.0, 0.0],
        [4.0, 0.0, 3.0],
        [0.0, 0.0, 3.0],
        [0.0, 2.0, 0.0],
        [4.0, 2.0, 0.0],
        [4.0, 2.0, 3.0],
        [0.0, 2.0, 3.0],
        [0.0, 3.2, 1.5],
        [4.0, 3.2, 1.5],
    ]
    .into_iter()
    .map(turn)
    .collect();
    let faces = [
        [0, 1, 2],
        [0, 2, 3],
        [0, 4, 5],
        [0, 5, 1],
        [1, 5, 6],
        [1, 6, 2],
        [2, 6, 7],
        [2, 7, 3],
        [3, 7, 4],
        [3, 4, 0],
        [4, 8, 9],
        [4, 9, 5],
        [7, 6, 9],
        [7, 9, 8],
        [4, 7, 8],
        [5, 9, 6],
    ];
    let mut mesh = Mesh::new();
    for (i, f) in faces.iter().enumerate() {
        let material = mesh.add_material(brickcast_server::import::mesh::Material {
            name: format!("m{i}"),
            diffuse: [0.2 + 0.05 * i as f32, 0.5, 0.9 - 0.05 * i as f32],
            texture: None,
        });
        mesh.add_triangle(f.map(|k| corners[k]), None, material);
    }
    let options = ImportOptions {
        resolution: 128,
        threads: 2,
        ..ImportOptions::default()
    };
    let (mut map, _) = voxelize(&mesh, &options, &NoProgress).expect("voxelize");
    let ctx = gpu();
    let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    let mut hits = 0;
    for (label, camera) in cameras(map.size()) {
        let projection = camera.project(160, 96).expect("camera");
        hits += assert_twins(label, &ctx, &scene, &mut tracer, &map, &projection);
    }
    assert!(hits > 160 * 96, "the cameras hit only {hits} pixels in all");
}

/// Sibenik at 1024³ (the importer's output for a real textured mesh), from inside the nave and
/// from above.
#[test]
#[ignore = "needs the shared scenes: set BRICKCAST_SCENES"]
fn sibenik_matches_the_cpu_tracer() {
    use brickcast_server::import::{ImportOptions, NoProgress, import_file};
    let scenes = std::env::var("BRICKCAST_SCENES").expect("BRICKCAST_SCENES");
    let options = ImportOptions {
        resolution: 1024,
        threads: 0,
        ..ImportOptions::default()
    };
    let obj = std::path::Path::new(&scenes).join("sibenik/sibenik.obj");
    let mut map = import_file(&obj, &options, &NoProgress)
        .expect("import")
        .map;
    let ctx = gpu();
    let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    let nave = Camera {
        eye: [75.0, 260.0, 216.0],
        target: [950.0, 190.0, 216.0],
        fov_y: 70.0,
    };
    for (label, camera) in [("nave", nave), ("overview", Camera::overview(map.size()))] {
        let projection = camera.project(240, 135).expect("camera");
        let hits = assert_twins(label, &ctx, &scene, &mut tracer, &map, &projection);
        assert!(hits > 240 * 135 / 2, "{label}: only {hits} pixels hit");
    }
}

#[test]
fn scattered_scene_with_odd_sizes_matches_the_cpu_tracer() {
    let ctx = gpu();
    for (seed, size) in [(1u64, [100u32, 70, 90]), (2, [37, 129, 61])] {
        let mut map = scattered_scene(size, seed);
        let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
        let mut tracer = Tracer::new(&ctx).expect("tracer");
        let mut total_hits = 0;
        for (label, camera) in cameras(size) {
            let projection = camera.project(128, 80).expect("camera");
            total_hits += assert_twins(label, &ctx, &scene, &mut tracer, &map, &projection);
        }
        assert!(
            total_hits > 1000,
            "seed {seed}: the cameras saw almost nothing"
        );
    }
}

/// A copy whose bricks may be coded lossily (`--colours bounded`, both weight widths): the
/// shader decodes the same blocks as the CPU tracer, and every voxel stays within the bound.
#[test]
fn bounded_colour_blocks_match_the_cpu_tracer() {
    let ctx = gpu();
    let size = [100u32, 70, 90];
    let mut exact = scattered_scene(size, 3);
    // A textured slab: smooth gradients with a little grain, as an imported texture is.
    for z in 40..72u32 {
        for y in 20..28u32 {
            for x in 30..62u32 {
                let grain = ((x * 7 + y * 13 + z * 5) % 6) as u8;
                let c = Colour::from_rgb8(
                    (x * 4) as u8 + grain,
                    (z * 3) as u8 + grain,
                    (120 + y * 4) as u8,
                );
                exact.set([x, y, z], c);
            }
        }
    }
    exact.rebuild_clearance();
    let mut widths = [false; 2];
    for bound in [4, brickcast_protocol::blocks::DEFAULT_BOUND, 40] {
        let mut map = BrickMap::new(size).expect("scene size");
        map.set_colour_bound(Some(bound));
        for (brick, _) in exact.bricks() {
            map.put_brick(&brick).expect("brick");
        }
        map.rebuild_clearance();
        let mix = brickcast_protocol::palette::Mix::of(&map);
        assert!(
            bound < 12 || mix.blocks[0] + mix.blocks[1] > 0,
            "bound {bound}: {mix:?}"
        );
        widths[0] |= mix.blocks[0] > 0;
        widths[1] |= mix.blocks[1] > 0;
        for (brick, _) in exact.bricks() {
            for (i, &c) in brick.colours.iter().enumerate() {
                let got = map.brick(brick.cell).expect("brick").colours[i];
                assert!(brickcast_protocol::blocks::error(got, c) <= bound);
            }
        }
        let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
        let mut tracer = Tracer::new(&ctx).expect("tracer");
        for (label, camera) in cameras(size) {
            let projection = camera.project(128, 80).expect("camera");
            assert_twins(label, &ctx, &scene, &mut tracer, &map, &projection);
        }
    }
    assert_eq!(widths, [true, true], "both weight widths traced");
}

/// A working set of mixed levels (`map::stand_in`): level 0 around one place, coarse bricks of
/// levels 2 to 6 standing in elsewhere. The shader descends to whatever each region holds, its
/// ambient occlusion and shadows read coarse voxels as the CPU's do; then regions change level
/// (level 0 gives way to a stand-in and back) through the incremental upload alone.
#[test]
fn mixed_levels_match_the_cpu_tracer() {
    let ctx = gpu();
    let size = [300u32, 70, 141];
    let mut base = scattered_scene(size, 11);
    // Ground everywhere, so every region of the bottom row shows something at every level.
    base.fill_box(
        [0, 0, 0],
        [299, 2, 140],
        BrushMode::Fill,
        Colour::from_rgb8(90, 140, 60),
    );
    let pyramid = brickcast_protocol::lod::Pyramid::build(&base).expect("pyramid");
    assert!(pyramid.level_count() >= 6);
    let levels = [0u32, 2, 3, 4, 5, 6];
    let pick = |r: [u32; 3]| {
        if r[0].abs_diff(3) <= 1 && r[2].abs_diff(2) <= 1 {
            0
        } else {
            levels[((r[0] * 7 + r[1] * 3 + r[2] * 5) % 6) as usize]
        }
    };
    let mut map = pyramid.mixed(&base, pick).expect("mixed map");
    assert!(map.stand_in_count() > 20 && map.brick_count() > 0);
    let mut scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    let mut hits = 0;
    let check = |label: &str, scene: &GpuScene, tracer: &mut Tracer, map: &BrickMap| {
        let mut hits = 0;
        for (name, camera) in cameras(size) {
            let projection = camera.project(128, 80).expect("camera");
            hits += assert_twins(
                &format!("{label}, {name}"),
                &ctx,
                scene,
                tracer,
                map,
                &projection,
            );
        }
        hits
    };
    hits += check("mixed", &scene, &mut tracer, &map);
    // Region (3, 0, 2) from level 0 to its level-3 brick, and (8, 1, 3) from its level to 0.
    let coarse = pyramid.level(3).expect("level 3");
    let cell = [3u32 >> 1, 0, 2 >> 1];
    for c in 0..64u32 {
        let cell0 = [12 + (c & 3), c >> 2 & 3, 8 + (c >> 4)];
        map.remove_brick(cell0);
    }
    let brick = coarse.brick(cell).expect("a level-3 brick there");
    let slot = map.add_coarse(brick.mask, &brick.colours).expect("coarse");
    map.set_stand_in([3, 0, 2], Some((3, slot)))
        .expect("stand in");
    map.set_stand_in([8, 1, 3], None).expect("clear");
    for c in 0..64u32 {
        let cell0 = [32 + (c & 3), 4 + (c >> 2 & 3), 12 + (c >> 4)];
        if let Some(b) = base.brick(cell0) {
            map.put_brick(&b).expect("level 0");
        }
    }
    map.check_invariants().expect("invariants");
    scene.update(&ctx, &mut map).expect("update");
    hits += check("levels changed", &scene, &mut tracer, &map);
    // Packed (a copy that outgrew its budget does this), then held to a budget its buffers
    // were over: they shrink to fit, and the picture stays the same.
    assert!(map.free_bytes() > 0, "the level changes freed room");
    let packed = map.compact();
    map.check_invariants().expect("invariants after packing");
    let budget = packed.bytes_after + packed.bytes_after / 16;
    assert!(
        scene.gpu_bytes() > budget,
        "the buffers must start over this budget"
    );
    scene.set_budget(Some(budget));
    let stats = scene.update(&ctx, &mut map).expect("update");
    assert!(stats.reallocations > 0, "{stats:?}");
    assert!(
        scene.gpu_bytes() <= budget,
        "{} GPU bytes for a budget of {budget}",
        scene.gpu_bytes()
    );
    hits += check("packed, within a budget", &scene, &mut tracer, &map);
    // Growing again within the budget: headroom is cut to what the budget leaves.
    assert_eq!(map.stand_in([2, 0, 1]), None, "a region held at level 0");
    map.fill_box(
        [66, 3, 34],
        [90, 20, 60],
        BrushMode::Fill,
        Colour::from_rgb8(9, 9, 200),
    );
    scene.update(&ctx, &mut map).expect("update");
    let need = map.memory().total_bytes;
    assert!(
        scene.gpu_bytes() <= budget.max(need + 64 * 4 * 5),
        "{} GPU bytes for a budget of {budget} ({need} needed)",
        scene.gpu_bytes()
    );
    hits += check("grown within a budget", &scene, &mut tracer, &map);
    assert!(hits > 2000, "the cameras saw almost nothing: {hits}");
}

/// Scattered single voxels: one brick each, so masks and the coarse grid dominate.
fn dust_scene(size: [u32; 3], voxels: u32) -> BrickMap {
    let mut map = BrickMap::new(size).expect("scene size");
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for i in 0..voxels {
        let p = size.map(|n| rng.random_range(0..n));
        map.set(p, Colour::from_rgb8((i % 200) as u8 + 50, 120, 200));
    }
    map.rebuild_clearance();
    map
}

#[test]
fn paged_pools_trace_like_a_single_binding() {
    let ctx = gpu();
    let scenes = [
        (
            "demo (colours dominate)",
            demo_scene([192, 96, 160]).expect("demo scene"),
        ),
        (
            "dust (masks and cells dominate)",
            dust_scene([512, 64, 512], 3000),
        ),
    ];
    let mut paged_at_least_once = std::collections::BTreeSet::new();
    for (label, mut map) in scenes {
        let biggest_pool = [
            map.cells().len() as u64 * 4,
            map.masks().len() as u64 * 64,
            map.colour_pool().len().div_ceil(2) as u64 * 4,
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        // The biggest pool spans two pages (the most that are bound).
        let page = biggest_pool.div_ceil(2).next_power_of_two();
        let paged = GpuScene::new(&ctx, &mut map, Some(page)).expect("paged upload");
        for (array, pages) in paged.page_counts() {
            if pages > 1 {
                paged_at_least_once.insert(array);
            }
        }
        let mut tracer = Tracer::new(&ctx).expect("tracer");
        for (camera_label, camera) in cameras(map.size()) {
            let projection = camera.project(128, 72).expect("camera");
            let what = format!("{label}, {camera_label}");
            assert_twins(&what, &ctx, &paged, &mut tracer, &map, &projection);
        }
    }
    assert_eq!(
        paged_at_least_once.into_iter().collect::<Vec<_>>(),
        ["cells", "colours", "masks"],
        "every paged pool must have been split across bindings by one of the scenes"
    );
}

/// The server side of the delta test: an authoritative map and what a client has seen of it.
struct Authority {
    map: BrickMap,
    sent_seq: u64,
}

impl Authority {
    /// Everything that changed since the last call, as the server would send it.
    fn delta(&mut self) -> ServerMsg {
        let changes = self.map.changes_since(self.sent_seq).expect("history kept");
        let bricks: Vec<_> = changes
            .changed
            .iter()
            .filter_map(|&cell| self.map.brick(cell))
            .collect();
        let msg = ServerMsg::Delta {
            from_seq: self.sent_seq,
            to_seq: self.map.sequence(),
            bricks: BrickBlob::encode(&bricks, 1).expect("encode"),
            removed: changes.removed,
        };
        self.sent_seq = self.map.sequence();
        msg
    }
}

/// One step of the delta test: an edit made on the server's map.
type Edit = Box<dyn Fn(&mut BrickMap)>;

#[test]
fn deltas_update_the_gpu_copy_incrementally_and_it_still_matches() {
    let ctx = gpu();
    let size = [160, 80, 144];
    let mut authority = Authority {
        map: demo_scene(size).expect("demo scene"),
        sent_seq: 0,
    };
    authority.map.record_touched(false);
    // Initial sync: the whole scene as one batch.
    let mut replica = Replica::new("demo", size).expect("replica");
    let everything: Vec<_> = authority.map.bricks().map(|(b, _)| b).collect();
    let total = everything.len() as u32;
    replica
        .apply(&ServerMsg::SyncBatch {
            bricks: BrickBlob::encode(&everything, 1).expect("encode"),
            sent: total,
            total,
        })
        .expect("sync");
    authority.sent_seq = authority.map.sequence();
    replica
        .apply(&ServerMsg::SyncDone {
            seq: authority.sent_seq,
        })
        .expect("sync done");
    assert!(replica.take_reset());
    let mut scene = GpuScene::new(&ctx, &mut replica.map, None).expect("upload");
    let full_upload = scene.uploaded.bytes;
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    let projection = Camera::overview(size).project(128, 72).expect("camera");
    let close = Camera {
        eye: [40.0, 60.0, 30.0],
        target: [80.0, 20.0, 72.0],
        fov_y: 65.0,
    }
    .project(128, 72)
    .expect("camera");

    let s = size.map(|v| v as f32);
    let steps: Vec<(&str, Edit)> = vec![
        (
            "carve a crater",
            Box::new(move |m| {
                m.sphere(
                    [s[0] * 0.5, s[1] * 0.3, s[2] * 0.5],
                    14.0,
                    BrushMode::Erase,
                    Colour(0),
                );
            }),
        ),
        (
            "build a tower into empty sky (new bricks)",
            Box::new(|m| {
                m.fill_box(
                    [70, 20, 60],
                    [85, 79, 75],
                    BrushMode::Fill,
                    Colour::from_rgb8(200, 30, 30),
                );
            }),
        ),
        (
            "repaint a hillside",
            Box::new(move |m| {
                m.sphere(
                    [s[0] * 0.25, s[1] * 0.25, s[2] * 0.7],
                    20.0,
                    BrushMode::Paint,
                    Colour::from_rgb8(20, 20, 220),
                );
            }),
        ),
        (
            "single voxels",
            Box::new(|m| {
                for i in 0..30u32 {
                    m.set([10 + i * 4, 70, 10 + i * 3], Colour::from_rgb8(255, 255, 0));
                }
                m.clear([80, 79, 67]);
            }),
        ),
        (
            "remove whole bricks",
            Box::new(|m| {
                m.fill_box([0, 0, 0], [47, 79, 31], BrushMode::Erase, Colour(0));
            }),
        ),
        (
            "grow the pools past their slack (reallocation)",
            Box::new(|m| {
                m.fill_box(
                    [0, 40, 0],
                    [159, 47, 143],
                    BrushMode::Fill,
                    Colour::from_rgb8(90, 90, 90),
                );
            }),
        ),
    ];
    for (label, edit) in steps {
        let next = authority.map.sequence() + 1;
        authority.map.set_sequence(next);
        edit(&mut authority.map);
        let delta = authority.delta();
        replica.apply(&delta).expect("delta");
        assert!(
            !replica.take_reset(),
            "{label}: a delta must not reset the copy"
        );
        assert_eq!(
            replica.map.content_hash(),
            authority.map.content_hash(),
            "{label}: replica diverged"
        );
        let stats = scene.update(&ctx, &mut replica.map).expect("update");
        assert!(stats.bytes > 0, "{label}: nothing uploaded");
        if stats.reallocations == 0 {
            assert!(
                stats.bytes * 4 < full_upload,
                "{label}: uploaded {} bytes, the whole scene is {full_upload}",
                stats.bytes
            );
        } else {
            // A pool that grew takes its old contents over on the GPU: only what changed and
            // the new room are written (writing grown pools whole again was 87 KB of the
            // 252 KB copy in the last step; now 56 KB).
            assert!(
                stats.bytes * 3 < scene.gpu_bytes(),
                "{label}: uploaded {} bytes after {} reallocations, the copy is {}",
                stats.bytes,
                stats.reallocations,
                scene.gpu_bytes()
            );
        }
        assert_twins(label, &ctx, &scene, &mut tracer, &replica.map, &projection);
        assert_twins(label, &ctx, &scene, &mut tracer, &replica.map, &close);
    }
    assert!(
        scene.uploaded.reallocations > 0,
        "the last step was meant to outgrow the pools"
    );
}
