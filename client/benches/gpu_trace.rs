//! GPU tracer throughput, in rays per second, on the same 1024³ demo scene and cameras as the CPU
//! tracer's benchmark (`protocol/benches/protocol.rs`), so the two can be read side by side.
//!
//! `primary`: shadows off, one ray per pixel (comparable to the CPU's `trace_frame`);
//! `shaded`: what the viewer draws, a primary ray plus a shadow ray from every hit.
//! Each iteration is one dispatch and a wait for it. The adapter is printed first: on a machine
//! without a GPU it is lavapipe (Mesa's CPU Vulkan), and the figures say nothing about GPUs.
//!
//! `cargo bench -p brickcast-client --bench gpu_trace`

use std::time::Duration;

use brickcast_client::gpu::{BackendChoice, GpuContext, GpuScene, Tracer};
use brickcast_protocol::Lighting;
use brickcast_protocol::demo::demo_scene;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};

fn gpu_trace(c: &mut Criterion) {
    let ctx = match GpuContext::headless(BackendChoice::Vulkan) {
        Ok(ctx) => ctx,
        Err(e) => panic!("the GPU benchmark needs a Vulkan adapter: {e}"),
    };
    eprintln!("gpu_trace: adapter = {}", ctx.adapter_name);
    let mut map = demo_scene([1024, 1024, 1024]).expect("demo scene");
    let scene = GpuScene::new(&ctx, &mut map, None).expect("upload");
    eprintln!("gpu_trace: scene buffers = {} bytes", scene.gpu_bytes());
    let mut tracer = Tracer::new(&ctx).expect("tracer");
    let cameras = brickcast_protocol::demo::benchmark_cameras_1024();
    let (w, h) = (640, 360);
    let mut group = c.benchmark_group("gpu_trace");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(10));
    group.throughput(Throughput::Elements(u64::from(w * h)));
    for (name, camera) in cameras {
        let projection = camera.project(w, h).expect("camera");
        // "primary": one ray per pixel and the shading arithmetic; "sun": plus the shadow ray
        // where a face turns to the sun; "shaded": plus ambient occlusion (the viewer's default).
        for (variant, shadows, ao) in [
            ("primary", false, false),
            ("sun", true, false),
            ("shaded", true, true),
        ] {
            let lighting = Lighting {
                shadows,
                ao,
                ..Lighting::default()
            };
            // Warm-up: pipeline compilation and first-touch of the buffers.
            tracer
                .trace(&ctx, &scene, &projection, &lighting)
                .expect("trace");
            group.bench_function(format!("{name}_640x360_{variant}"), |b| {
                b.iter(|| {
                    tracer
                        .trace(&ctx, &scene, &projection, &lighting)
                        .expect("trace")
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, gpu_trace);
criterion_main!(benches);
