//! Renders the built-in demo scene with the CPU tracer and writes a PNG: a look at the scene and
//! the renderer without a server or a GPU.
//!
//! `cargo run --release -p brickcast-protocol --example cpu_render -- demo.png [width height [room]]`
//!
//! With `room`, renders the generated enclosed room (`demo::room_scene`) instead, from the first
//! camera `viewpoint::find` picks for it (inside).

use std::fs::File;
use std::io::BufWriter;
use std::time::Instant;

use brickcast_protocol::demo::{demo_scene, room_scene};
use brickcast_protocol::render::{Camera, Lighting, render};
use brickcast_protocol::viewpoint;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let out = args.next().unwrap_or_else(|| "demo.png".into());
    let width: u32 = args.next().map(|a| a.parse()).transpose()?.unwrap_or(960);
    let height: u32 = args.next().map(|a| a.parse()).transpose()?.unwrap_or(540);

    let started = Instant::now();
    let room = args.next().is_some_and(|a| a == "room");
    let map = if room {
        room_scene([160, 72, 128])?
    } else {
        demo_scene([512, 512, 512])?
    };
    let built = started.elapsed();
    let camera = if room {
        viewpoint::find(&map, 60.0).camera
    } else {
        Camera::overview(map.size())
    };
    let projection = camera.project(width, height).ok_or("degenerate camera")?;
    let started = Instant::now();
    let frame = render(&map, &projection, &Lighting::default(), 0);
    let traced = started.elapsed();

    let mut encoder = png::Encoder::new(BufWriter::new(File::create(&out)?), width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()?
        .write_image_data(frame.pixels.as_flattened())?;
    let memory = map.memory();
    println!(
        "{out}: {width}x{height}, scene built in {built:.2?}, rendered in {traced:.2?}; {} bricks, {} voxels, {:.1} MiB",
        memory.bricks,
        memory.solid_voxels,
        memory.total_bytes as f64 / (1 << 20) as f64
    );
    Ok(())
}
