//! Criterion benchmarks for the protocol crate; results and commands live in BENCHMARKS.md.
//!
//! `cargo bench -p brickcast-protocol --bench protocol`

use std::hint::black_box;
use std::time::Duration;

use brickcast_protocol::Colour;
use brickcast_protocol::Lighting;
use brickcast_protocol::demo::demo_scene;
use brickcast_protocol::map::{BrickMap, BrushMode};
use brickcast_protocol::render::{render, trace_frame};
use brickcast_protocol::wire::{
    BlobDecoder, BlobEncoder, BrickBlob, Limits, ServerMsg, decode_server, encode_server,
};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};

/// Seeded ChaCha8 (`rand_chacha`: the same numbers on every platform and rand release).
struct Rng(rand_chacha::ChaCha8Rng);
impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(rand::SeedableRng::seed_from_u64(seed))
    }
    fn next(&mut self) -> u64 {
        rand::RngCore::next_u64(&mut self.0)
    }
    fn below(&mut self, n: u32) -> u32 {
        rand::Rng::random_range(&mut self.0, 0..n)
    }
}

fn edits(c: &mut Criterion) {
    let mut group = c.benchmark_group("edit");
    group.measurement_time(Duration::from_secs(4));
    let base = demo_scene([512, 512, 512]).expect("demo scene");

    // Random single-voxel sets over the demo scene: a mix of recolouring existing voxels, growing
    // existing bricks and creating new ones, which is what people's clicks do.
    let mut map = base.clone();
    let mut rng = Rng::new(0x9E37_79B9_7F4A_7C15);
    group.throughput(Throughput::Elements(1));
    // A clear and a set at random places in a 64³ demo scene, which stays in the cache: the
    // single-voxel path's own work, without the misses that the 512³ runs below wait on.
    {
        let mut small = demo_scene([64, 64, 64]).expect("demo scene");
        let mut rng = Rng::new(7);
        group.bench_function("clear_and_set_in_cache", |b| {
            b.iter(|| {
                let p = [rng.below(64), rng.below(32), rng.below(64)];
                let _ = small.clear([rng.below(64), rng.below(32), rng.below(64)]);
                black_box(small.set(p, Colour(rng.next() as u16)))
            })
        });
    }
    group.bench_function("set_voxel", |b| {
        b.iter(|| {
            let p = [rng.below(512), rng.below(256), rng.below(512)];
            black_box(map.set(p, Colour(rng.next() as u16)))
        })
    });
    // The same sets in the eight colours of a viewer's palette: what clicks bring.
    let mut map = base.clone();
    let eight: Vec<Colour> = (0..8u16)
        .map(|i| Colour(0x1234u16.wrapping_mul(i + 1)))
        .collect();
    group.bench_function("set_voxel_8_colours", |b| {
        b.iter(|| {
            let p = [rng.below(512), rng.below(256), rng.below(512)];
            black_box(map.set(p, eight[rng.below(8) as usize]))
        })
    });
    let mut map = base.clone();
    group.bench_function("clear_voxel", |b| {
        b.iter(|| {
            let p = [rng.below(512), rng.below(96), rng.below(512)];
            black_box(map.clear(p))
        })
    });

    // Sphere brushes of radius 12 (about 7,200 voxels each), alternating fill and erase at random
    // places so the map neither fills up nor empties.
    let mut map = base.clone();
    let radius = 12.0f32;
    let per_sphere = (4.0 / 3.0 * std::f32::consts::PI * radius.powi(3)) as u64;
    group.throughput(Throughput::Elements(per_sphere));
    let mut flip = false;
    group.bench_function("sphere_brush_r12", |b| {
        b.iter(|| {
            flip = !flip;
            let c = [
                rng.below(480) as f32 + 16.0,
                rng.below(200) as f32 + 16.0,
                rng.below(480) as f32 + 16.0,
            ];
            let mode = if flip {
                BrushMode::Fill
            } else {
                BrushMode::Erase
            };
            black_box(map.sphere(c, radius, mode, Colour(0x7BEF)))
        })
    });
    group.finish();
}

/// The editing tools against the brush they are priced against (issue #34): a flood fill of
/// a 512×512 floor of one colour (262,144 voxels: finding the region, and the whole op as the
/// server applies it) next to painting the same voxels with a box brush.
fn tools(c: &mut Criterion) {
    use brickcast_protocol::apply::apply_op;
    use brickcast_protocol::region::fill_region;
    use brickcast_protocol::wire::{EditOp, RayAction};

    let mut group = c.benchmark_group("tools");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(6));
    let mut floor = BrickMap::new([512, 8, 512]).expect("a scene");
    let (a, b) = (Colour(0x7BEF), Colour(0x001F));
    floor.fill_box([0, 0, 0], [511, 0, 511], BrushMode::Fill, a);
    let voxels = 512 * 512;
    group.throughput(Throughput::Elements(voxels));
    group.bench_function("fill_region_262k", |bench| {
        bench.iter(|| black_box(fill_region(&floor, [3, 0, 7], 1 << 20).map(|r| r.len())))
    });
    let limits = Limits::default();
    let mut map = floor.clone();
    let mut now = a;
    group.bench_function("fill_op_262k", |bench| {
        bench.iter(|| {
            now = if now == a { b } else { a };
            let op = EditOp::Ray {
                origin: [3.5, 7.5, 7.5],
                dir: [0.0, -1.0, 0.0],
                action: RayAction::Fill {
                    colour: now,
                    limit: limits.max_tool_voxels,
                },
            };
            black_box(apply_op(&mut map, &op, &limits))
        })
    });
    let mut map = floor.clone();
    group.bench_function("paint_box_262k", |bench| {
        bench.iter(|| {
            now = if now == a { b } else { a };
            black_box(map.fill_box([0, 0, 0], [511, 0, 511], BrushMode::Paint, now))
        })
    });
    group.finish();
}

/// Copy and paste (issue #34) of a 1 M-voxel selection (a 100³ box of solid voxels in eight
/// colours): taking it into a clipboard, and pasting it turned a quarter into the same scene as
/// the owner does it in one turn (the bricks it changes, computed and written) — the owner's
/// stall for such a paste.
fn clipboard(c: &mut Criterion) {
    use brickcast_protocol::clipboard::Clipboard;

    let mut group = c.benchmark_group("clipboard");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(8));
    let mut map = BrickMap::new([512, 128, 512]).expect("a scene");
    for (i, x) in (0..100).step_by(13).enumerate() {
        let colour = Colour(0x1111 * (i as u16 + 1));
        map.fill_box(
            [x, 0, 0],
            [(x + 12).min(99), 99, 99],
            BrushMode::Fill,
            colour,
        );
    }
    let voxels = 100 * 100 * 100;
    group.throughput(Throughput::Elements(voxels));
    group.bench_function("copy_1m", |bench| {
        bench.iter(|| black_box(Clipboard::copy(&map, [0, 0, 0], [99, 99, 99]).voxel_count()))
    });
    let clip = Clipboard::copy(&map, [0, 0, 0], [99, 99, 99]);
    group.bench_function("paste_bricks_1m", |bench| {
        bench.iter(|| black_box(clip.paste(&map, [200, 0, 200], 1, false).len()))
    });
    let mut target = map.clone();
    let mut turns = 1;
    group.bench_function("paste_and_write_1m", |bench| {
        bench.iter(|| {
            // A quarter one way, then the other: every paste changes every brick it covers.
            turns = 4 - turns;
            for b in clip.paste(&target, [300, 0, 300], turns, false) {
                target.put_brick(&b).expect("a pasted brick");
            }
        })
    });
    group.finish();
}

fn tracer(c: &mut Criterion) {
    let mut group = c.benchmark_group("trace");
    group.sample_size(20);
    group.measurement_time(Duration::from_secs(8));
    let map: BrickMap = demo_scene([1024, 1024, 1024]).expect("demo scene");
    let cameras = brickcast_protocol::demo::benchmark_cameras_1024();
    let (w, h) = (640, 360);
    group.throughput(Throughput::Elements(u64::from(w * h)));
    for (name, camera) in cameras {
        let projection = camera.project(w, h).expect("camera");
        for threads in [1usize, 2] {
            group.bench_function(format!("{name}_640x360_{threads}t"), |b| {
                b.iter(|| black_box(trace_frame(&map, &projection, threads)))
            });
        }
    }
    group.finish();

    // The shaded frame against primary rays alone: "flat" is the renderer with shadows and AO
    // off (primary rays plus the shading arithmetic), "sun" adds the shadow ray where a face
    // turns to the sun, "shaded" adds ambient occlusion (the default lighting).
    let mut group = c.benchmark_group("render");
    group.sample_size(20);
    group.measurement_time(Duration::from_secs(8));
    group.throughput(Throughput::Elements(u64::from(w * h)));
    for (name, camera) in cameras {
        let projection = camera.project(w, h).expect("camera");
        for (variant, shadows, ao) in [
            ("flat", false, false),
            ("sun", true, false),
            ("shaded", true, true),
        ] {
            let lighting = Lighting {
                shadows,
                ao,
                ..Lighting::default()
            };
            group.bench_function(format!("{name}_640x360_{variant}_2t"), |b| {
                b.iter(|| black_box(render(&map, &projection, &lighting, 2)))
            });
        }
    }
    group.finish();
}

/// Brick payload encoding: what the server pays once per delta or sync batch, and what every
/// client pays per frame. Throughput is in raw (uncompressed) bytes.
fn wire(c: &mut Criterion) {
    let mut group = c.benchmark_group("wire");
    group.measurement_time(Duration::from_secs(5));
    let map = demo_scene([512, 512, 512]).expect("demo scene");
    let bricks: Vec<_> = map.bricks().map(|(b, _)| b).take(4096).collect();
    for level in [1, 3] {
        let mut encoder = BlobEncoder::new(level).expect("zstd");
        let blob = BrickBlob::encode(&bricks, level).expect("encode");
        group.throughput(Throughput::Bytes(u64::from(blob.raw_len)));
        group.bench_function(format!("encode_4096_bricks_zstd{level}"), |b| {
            b.iter(|| {
                for brick in &bricks {
                    encoder.push_brick(brick).expect("push");
                }
                black_box(encoder.finish().expect("finish"))
            })
        });
        let mut decoder = BlobDecoder::new().expect("zstd");
        group.bench_function(format!("decode_4096_bricks_zstd{level}"), |b| {
            b.iter(|| {
                let mut voxels = 0usize;
                decoder
                    .for_each(&blob, 8192, |brick| voxels += brick.colour_count())
                    .expect("decode");
                black_box(voxels)
            })
        });
        // A whole delta frame as a client receives it: bincode, header checks, decompression.
        let frame = encode_server(&ServerMsg::Delta {
            from_seq: 1,
            to_seq: 2,
            bricks: blob.clone(),
            removed: Vec::new(),
        })
        .expect("frame");
        let limits = Limits::default();
        group.bench_function(format!("decode_delta_frame_zstd{level}"), |b| {
            b.iter(|| match decode_server(&frame, &limits).expect("frame") {
                ServerMsg::Delta { bricks, .. } => {
                    black_box(decoder.decode(&bricks, 8192).expect("blob").len())
                }
                _ => unreachable!("encoded a delta"),
            })
        });
    }
    group.finish();
}

criterion_group!(benches, edits, tools, clipboard, tracer, wire);
criterion_main!(benches);
