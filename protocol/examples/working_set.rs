//! A generated world held within a byte budget: level 0 near the eye, coarser levels standing in
//! further away (`working_set`, `map::stand_in`). Generates the world in memory, builds its
//! pyramid, fits the working set to the budget, builds the client's map, and renders the same
//! camera from the whole world and from the working set with the CPU tracer: times, bytes and how
//! far the two pictures differ.
//!
//! `cargo run --release -p brickcast-protocol --example working_set -- [--size X,Y,Z] [--seed S]
//!  [--budget-mib M] [--eye X,Y,Z] [--target X,Y,Z] [--image W,H] [--out budget.png]
//!  [--full-out full.png]`
//!
//! Defaults: BrickMap's 16384×512×16384 world (seed 3), 256 MiB, a camera over the middle.

use std::fs::File;
use std::io::BufWriter;
use std::time::Instant;

use brickcast_protocol::held;
use brickcast_protocol::lod::Pyramid;
use brickcast_protocol::render::{Camera, Frame, Lighting, MISS, render};
use brickcast_protocol::working_set;
use brickcast_protocol::world::World;

fn triple<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String> {
    let v: Vec<T> = s
        .split(',')
        .map(|p| p.trim().parse().map_err(|_| format!("bad number in {s:?}")))
        .collect::<Result<_, _>>()?;
    v.try_into()
        .map_err(|_| format!("{s:?}: three comma-separated numbers expected"))
}

fn write_png(path: &str, frame: &Frame) -> Result<(), Box<dyn std::error::Error>> {
    let mut encoder = png::Encoder::new(
        BufWriter::new(File::create(path)?),
        frame.width,
        frame.height,
    );
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()?
        .write_image_data(frame.pixels.as_flattened())?;
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut size = [16384u32, 512, 16384];
    let mut seed = 3u32;
    let mut budget_mib = 256u64;
    let mut eye = [8192.0f32, 400.0, 8192.0];
    let mut target = [8800.0f32, 150.0, 9400.0];
    let mut image = [640u32, 360];
    let mut out = "budget.png".to_string();
    let mut full_out = None;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        let mut value = || args.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--size" => size = triple(&value()?)?,
            "--seed" => seed = value()?.parse()?,
            "--budget-mib" => budget_mib = value()?.parse()?,
            "--eye" => eye = triple(&value()?)?,
            "--target" => target = triple(&value()?)?,
            "--image" => {
                let v = value()?;
                let (w, h) = v.split_once(',').ok_or("--image W,H")?;
                image = [w.parse()?, h.parse()?];
            }
            "--out" => out = value()?,
            "--full-out" => full_out = Some(value()?),
            other => return Err(format!("unknown argument {other:?}").into()),
        }
    }
    let mib = |b: u64| b as f64 / (1u64 << 20) as f64;

    let started = Instant::now();
    let base = World::new(size, seed)?.map()?;
    println!(
        "world {size:?} seed {seed}: {} bricks, {:.1} MiB, generated in {:.1?}",
        base.brick_count(),
        mib(base.memory().total_bytes),
        started.elapsed()
    );
    let started = Instant::now();
    let pyramid = Pyramid::build(&base)?;
    println!(
        "pyramid: {} levels, {} bricks, built in {:.1?}",
        pyramid.level_count(),
        pyramid.brick_count(),
        started.elapsed()
    );

    let budget = budget_mib << 20;
    let started = Instant::now();
    let (rule, cost) = working_set::fit(&base, &pyramid, eye, budget, 4096)?;
    let fitted = started.elapsed();
    let started = Instant::now();
    let map = working_set::build(&base, &pyramid, &rule)?;
    let built = started.elapsed();
    let memory = map.memory();
    println!(
        "budget {budget_mib} MiB: level 0 within {} regions ({} voxels) of the eye, {} regions / {} bricks at level 0, {} coarse bricks standing in for {} regions; {:.1} MiB (predicted {:.1} MiB); fitted in {fitted:.1?}, built in {built:.1?}",
        rule.near,
        rule.near * 32,
        cost.full_regions,
        cost.full_bricks,
        cost.coarse_bricks,
        cost.stand_ins,
        mib(memory.total_bytes),
        mib(cost.bytes),
    );
    assert!(
        memory.total_bytes <= budget,
        "the working set exceeds its budget"
    );

    // The eye moves one region (32 voxels) along x: what the server sends, and what deciding it
    // costs (`held::plan`, run by both sides once per region crossed).
    let mut moved_eye = eye;
    moved_eye[0] += 32.0;
    let moved = working_set::Rule::new(&base, &pyramid, moved_eye, rule.near);
    let started = Instant::now();
    let step = held::plan(base.region_dims(), Some(&rule), &moved);
    let planned = started.elapsed();
    let region_bricks: usize = step
        .regions
        .iter()
        .map(|&r| {
            base.region_cells(r)
                .filter(|&c| base.slot_of_cell(c).is_some())
                .count()
        })
        .sum();
    println!(
        "one region along x: {} regions at level 0 to send ({region_bricks} bricks), {} coarse bricks to send; planned in {planned:.1?}",
        step.regions.len(),
        step.coarse.len(),
    );

    let camera = Camera {
        eye,
        target,
        fov_y: 60.0,
    };
    let projection = camera
        .project(image[0], image[1])
        .ok_or("degenerate camera")?;
    let lighting = Lighting::default();
    let started = Instant::now();
    let frame = render(&map, &projection, &lighting, 0);
    println!("working set rendered in {:.2?}", started.elapsed());
    write_png(&out, &frame)?;
    let started = Instant::now();
    let full = render(&base, &projection, &lighting, 0);
    println!("whole world rendered in {:.2?}", started.elapsed());
    if let Some(path) = &full_out {
        write_png(path, &full)?;
    }
    // How far the working set's picture is from the whole world's.
    let (mut sq, mut within, mut same_hit) = (0f64, 0usize, 0usize);
    for i in 0..frame.pixels.len() {
        let (a, b) = (frame.pixels[i], full.pixels[i]);
        let worst = (0..3).map(|c| a[c].abs_diff(b[c])).max().unwrap_or(0);
        within += usize::from(worst <= 8);
        sq += (0..3)
            .map(|c| (f64::from(a[c]) - f64::from(b[c])).powi(2))
            .sum::<f64>();
        same_hit += usize::from(frame.hits[i] == full.hits[i] && full.hits[i] != MISS);
    }
    let n = frame.pixels.len() as f64;
    let psnr = 10.0 * (255.0f64.powi(2) / (sq / (3.0 * n)).max(1e-12)).log10();
    println!(
        "{out}: against the whole world PSNR {psnr:.2} dB, {:.2}% of pixels within 8/255, {:.2}% hit the same voxel",
        100.0 * within as f64 / n,
        100.0 * same_hit as f64 / n
    );
    Ok(())
}
