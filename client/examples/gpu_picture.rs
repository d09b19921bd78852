//! Traces a generated scene on the GPU (the client's compute shader) from its first camera and
//! writes a PNG: the README's pictures, without a server.
//!
//! `cargo run --release -p brickcast-client --example gpu_picture -- demo|room out.png [width height]`

use anyhow::{Context, Result, bail};
use brickcast_client::gpu::{BackendChoice, GpuContext};
use brickcast_client::headless::{render_gpu, write_png};
use brickcast_client::replica::Replica;
use brickcast_protocol::{Lighting, demo, viewpoint};

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let which = args.next().unwrap_or_else(|| "demo".into());
    let out = args.next().unwrap_or_else(|| format!("{which}.png"));
    let width: u32 = args.next().map(|a| a.parse()).transpose()?.unwrap_or(960);
    let height: u32 = args.next().map(|a| a.parse()).transpose()?.unwrap_or(540);
    let map = match which.as_str() {
        "demo" => demo::demo_scene([512, 512, 512])?,
        "room" => demo::room_scene([160, 72, 128])?,
        other => bail!("unknown scene {other:?} (demo or room)"),
    };
    let mut replica = Replica::new(&which, map.size())?;
    replica.map = map;
    replica.map.rebuild_clearance();
    let camera = viewpoint::find(&replica.map, 60.0).camera;
    let projection = camera.project(width, height).context("camera")?;
    let ctx = GpuContext::headless(BackendChoice::Vulkan)?;
    let frame = render_gpu(&ctx, &mut replica, &projection, &Lighting::default(), 1)?;
    write_png(out.as_ref(), width, height, &frame.pixels)?;
    println!(
        "{out}: {width}x{height} on {}, {:.1} ms, eye {:?} target {:?}",
        frame.adapter, frame.trace_ms, camera.eye, camera.target
    );
    Ok(())
}
