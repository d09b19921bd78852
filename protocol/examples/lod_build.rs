//! How long the levels of detail of a generated world take to build, for BENCHMARKS.md (issue
//! #30): one shot (`Pyramid::build`, ROUNDS times), then level by level in parts of PART
//! (env, default 32,768) slots of the level below, as a server's owner builds them over its
//! turns (`Pyramid::fold`).
//! `cargo run --release -p brickcast-protocol --example lod_build -- [X,Y,Z] [SEED] [ROUNDS]`
//! (default 4096,512,4096, seed 3, 3 rounds; the world is generated once, in memory).

use std::time::Instant;

use brickcast_protocol::lod::Pyramid;
use brickcast_protocol::world::World;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let size = match args.first() {
        Some(s) => {
            let v: Vec<u32> = s.split(',').map(str::parse).collect::<Result<_, _>>()?;
            <[u32; 3]>::try_from(v).map_err(|_| "the size is X,Y,Z")?
        }
        None => [4096, 512, 4096],
    };
    let seed = args.get(1).map_or(Ok(3), |s| s.parse())?;
    let rounds: u32 = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let started = Instant::now();
    let base = World::new(size, seed)?.map()?;
    println!(
        "world {size:?} seed {seed}: {} bricks, {} voxels, generated in {:.1} s",
        base.brick_count(),
        base.solid_voxels(),
        started.elapsed().as_secs_f64()
    );
    let mut times = Vec::new();
    for _ in 0..rounds {
        let started = Instant::now();
        let pyramid = Pyramid::build(&base)?;
        times.push(started.elapsed().as_secs_f64());
        println!(
            "built {} levels, {} bricks in {:.2} s",
            pyramid.level_count(),
            pyramid.brick_count(),
            times[times.len() - 1]
        );
    }
    times.sort_by(f64::total_cmp);
    println!("median {:.2} s", times[times.len() / 2]);
    // Level by level in parts, as a server's owner builds them over its turns.
    let part: u32 = std::env::var("PART")
        .ok()
        .and_then(|p| p.parse().ok())
        .unwrap_or(32_768);
    let started = Instant::now();
    let mut pyramid = Pyramid::empty(base.size())?;
    let mut parts = 0;
    for k in 1..=pyramid.level_count() {
        let slots = if k == 1 {
            base.slot_count()
        } else {
            pyramid.level(k - 1).map_or(0, |l| l.slot_count())
        };
        let mut next = 0;
        while next < slots {
            let end = (next + part).min(slots);
            let below = if k == 1 {
                &base
            } else {
                pyramid.level(k - 1).ok_or("level")?
            };
            let cells: Vec<u32> = below.slot_cells(next..end).collect();
            pyramid.fold(&base, k, &cells)?;
            next = end;
            parts += 1;
        }
    }
    println!(
        "in {parts} parts of {part} slots: {} bricks in {:.2} s",
        pyramid.brick_count(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
