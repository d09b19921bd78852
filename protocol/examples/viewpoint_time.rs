//! Times [`viewpoint::find`] on the demo scene and the room, and optionally writes what the chosen
//! camera sees: the cost check of the first-camera rule and a look at its choice.
//!
//! `cargo run --release -p brickcast-protocol --example viewpoint_time -- [demo edge] [png prefix]`
//! (edge defaults to 1024; with a prefix, writes `<prefix>_demo.png` and `<prefix>_room.png`).

use std::fs::File;
use std::io::BufWriter;
use std::time::{Duration, Instant};

use brickcast_protocol::BrickMap;
use brickcast_protocol::demo::{demo_scene, room_scene};
use brickcast_protocol::render::{Lighting, render};
use brickcast_protocol::viewpoint::{self, Viewpoint};

/// Runs `find` a few times; the fastest and slowest run and the result.
fn time(map: &BrickMap) -> (Duration, Duration, Viewpoint) {
    let mut runs = Vec::new();
    let mut view = viewpoint::find(map, 60.0);
    for _ in 0..7 {
        let started = Instant::now();
        view = std::hint::black_box(viewpoint::find(map, 60.0));
        runs.push(started.elapsed());
    }
    runs.sort();
    (runs[0], runs[runs.len() - 1], view)
}

fn write_png(
    map: &BrickMap,
    view: &Viewpoint,
    path: &str,
) -> Result<(), Box<dyn std::error::Error>> {
    let (w, h) = (960, 540);
    let projection = view.camera.project(w, h).ok_or("degenerate camera")?;
    let frame = render(map, &projection, &Lighting::default(), 0);
    let mut encoder = png::Encoder::new(BufWriter::new(File::create(path)?), w, h);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()?
        .write_image_data(frame.pixels.as_flattened())?;
    println!("  wrote {path}");
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let edge: u32 = args.next().map(|a| a.parse()).transpose()?.unwrap_or(1024);
    let png = args.next();
    let scenes = [
        ("demo", [edge; 3]),
        ("room", [160, 72, 128]),
        ("big_room", [edge, edge / 4, edge]),
    ];
    for (name, size) in scenes {
        let started = Instant::now();
        let map = if name == "demo" {
            demo_scene(size)?
        } else {
            room_scene(size)?
        };
        let built = started.elapsed();
        let (fastest, slowest, view) = time(&map);
        println!(
            "{name} {size:?} (built in {built:.2?}): find {fastest:.2?} (slowest of 7: {slowest:.2?}), {:?}, {} rays, {}/{} candidates enclosed, occupied {:?}\n  {:?}",
            view.placement, view.rays, view.enclosed, view.candidates, view.occupied, view.camera
        );
        if let Some(prefix) = &png {
            write_png(&map, &view, &format!("{prefix}_{name}.png"))?;
        }
    }
    Ok(())
}
