//! Prints where a frame's rays spend their steps (regions, cells, voxels): a guide for tuning
//! empty-space skipping. `cargo run --release -p brickcast-protocol --example trace_stats`
use brickcast_protocol::beam::{TILE, TileStarts};
use brickcast_protocol::demo::demo_scene;
use brickcast_protocol::render::trace_frame;
use brickcast_protocol::trace::{TraceStats, trace_from_with_stats};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let map = demo_scene([1024, 1024, 1024])?;
    let m = map.memory();
    println!(
        "1024³ demo: {} bricks, {} voxels, {} MiB",
        m.bricks,
        m.solid_voxels,
        m.total_bytes >> 20
    );
    let cameras = brickcast_protocol::demo::benchmark_cameras_1024();
    for (name, camera) in cameras {
        let p = camera.project(640, 360).ok_or("camera")?;
        let mut total = TraceStats::default();
        let mut hits = 0u64;
        let mut skipped_tiles = 0u32;
        let mut tiles = 0u32;
        for y in 0..360 {
            for x in 0..640 {
                let (tx, ty) = (x / TILE * TILE, y / TILE * TILE);
                let t0 = TileStarts::new(&p, &map, tx, ty).at(x, y);
                if x % TILE == 0 && y % TILE == 0 {
                    tiles += 1;
                    skipped_tiles += u32::from(t0 > 0.0);
                }
                let mut s = TraceStats::default();
                hits += u64::from(trace_from_with_stats(&map, &p.ray(x, y), t0, &mut s).is_some());
                total.region_skips += s.region_skips;
                total.cell_skips += s.cell_skips;
                total.voxel_steps += s.voxel_steps;
            }
        }
        println!("{name}: the beam pre-pass moved the start of {skipped_tiles} of {tiles} tiles");
        let n = 640.0 * 360.0;
        let started = std::time::Instant::now();
        let frames = 5;
        for _ in 0..frames {
            std::hint::black_box(trace_frame(&map, &p, 2));
        }
        let secs = started.elapsed().as_secs_f64() / f64::from(frames);
        println!(
            "{name}: {:.2} Mrays/s on 2 threads (rough; criterion has the real figure)",
            n / secs / 1e6
        );
        println!(
            "{name}: hit {:.0}%, per ray: {:.1} region skips, {:.1} cell skips, {:.1} voxel steps",
            hits as f64 / n * 100.0,
            f64::from(total.region_skips) / n,
            f64::from(total.cell_skips) / n,
            f64::from(total.voxel_steps) / n
        );
    }
    Ok(())
}
