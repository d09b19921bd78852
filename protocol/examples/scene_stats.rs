//! Memory per component and wire size of the demo scene at a few sizes: the figures behind the
//! memory and compression rows of BENCHMARKS.md.
//!
//! `cargo run --release -p brickcast-protocol --example scene_stats`

use brickcast_protocol::demo::demo_scene;
use brickcast_protocol::wire::BlobEncoder;

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1 << 20) as f64
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!(
        "| scene | bricks | solid voxels | regions | cells | masks | colour bases | colours | total | paper formula | bytes/voxel |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for size in [[512, 512, 512], [1024, 1024, 1024]] {
        let map = demo_scene(size)?;
        let m = map.memory();
        println!(
            "| demo {}×{}×{} | {} | {} | {:.2} MiB | {:.2} MiB | {:.2} MiB | {:.2} MiB | {:.2} MiB | **{:.2} MiB** | {:.1} MiB | {:.2} |",
            size[0],
            size[1],
            size[2],
            m.bricks,
            m.solid_voxels,
            mib(m.region_bytes),
            mib(m.cell_bytes),
            mib(m.mask_bytes),
            mib(m.colour_base_bytes),
            mib(m.colour_bytes),
            mib(m.total_bytes),
            mib(m.paper_formula_bytes),
            m.bytes_per_solid_voxel
        );
    }
    println!();
    println!("| scene | zstd level | raw bytes/brick | compressed bytes/brick | ratio |");
    println!("|---|---|---|---|---|");
    let map = demo_scene([512, 512, 512])?;
    let bricks: Vec<_> = map.bricks().map(|(b, _)| b).collect();
    for level in [1, 3, 9] {
        let mut encoder = BlobEncoder::new(level)?;
        let (mut raw, mut packed) = (0u64, 0u64);
        for chunk in bricks.chunks(4096) {
            for brick in chunk {
                encoder.push_brick(brick)?;
            }
            let blob = encoder.finish()?;
            raw += u64::from(blob.raw_len);
            packed += blob.data.len() as u64;
        }
        let n = bricks.len() as f64;
        println!(
            "| demo 512³ ({} bricks) | {level} | {:.1} | {:.1} | {:.2} |",
            bricks.len(),
            raw as f64 / n,
            packed as f64 / n,
            raw as f64 / packed as f64
        );
    }
    Ok(())
}
