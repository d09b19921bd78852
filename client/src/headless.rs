//! `brickcast render`: fetch a scene, trace one frame (GPU or CPU), write a PNG, report.

use brickcast_protocol::blocks::Quality;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use brickcast_protocol::viewpoint;
use brickcast_protocol::working_set::Rule;
use brickcast_protocol::{BrickMap, Camera, Lighting, Projection};
use serde::Serialize;

use crate::gpu::{BackendChoice, GpuContext, GpuScene, Tracer};
use crate::link::{self, Link};
use crate::replica::Replica;

/// What `render --json` prints.
#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    pub width: u32,
    pub height: u32,
    pub bricks: u64,
    pub voxels: u64,
    /// Bytes of the scene's GPU buffers (0 with `--cpu`).
    pub gpu_bytes: u64,
    /// Connect to SyncDone.
    pub sync_ms: f64,
    /// Median of the timed frames, after one untimed warm-up frame.
    pub trace_ms: f64,
    pub adapter: String,
    pub scene: String,
    pub eye: [f32; 3],
    pub target: [f32; 3],
}

/// What of a scene to fetch: all of it (`budget: None`), or the working set a client with
/// `budget` GPU bytes holds when its eye is at `eye` (the server's default camera when `None`).
#[derive(Debug, Clone, Copy, Default)]
pub struct Within {
    pub budget: Option<u64>,
    pub eye: Option<[f32; 3]>,
}

/// [`fetch`] from the first of `urls` that answers.
pub async fn fetch_any(
    urls: &[String],
    token: Option<&str>,
    colours: Quality,
    within: Within,
) -> Result<(Replica, f64)> {
    let mut last = anyhow::anyhow!("no scene address given");
    for url in urls {
        match fetch(url, token, colours, within).await {
            Ok(done) => return Ok(done),
            Err(e) => {
                if urls.len() > 1 {
                    tracing::warn!("{url}: {e:#}; trying the next address");
                }
                last = e;
            }
        }
    }
    Err(last)
}

/// Connects to `url`, syncs the whole scene (or the working set `within` asks for) and
/// disconnects. Returns the replica and how long the sync took in milliseconds.
pub async fn fetch(
    url: &str,
    token: Option<&str>,
    colours: Quality,
    within: Within,
) -> Result<(Replica, f64)> {
    let url = link::websocket_url(url)?;
    let started = Instant::now();
    let budget = within.budget.map(|bytes| brickcast_protocol::wire::Budget {
        bytes,
        eye: within.eye,
    });
    let mut link = Link::connect_within(&url, "brickcast render", 0, token, None, budget)
        .await
        .with_context(|| format!("connecting to {url}"))?;
    let mut replica = Replica::new(&link.welcome.scene, link.welcome.size)?;
    replica.set_colour_bound(colours.bound());
    replica.set_budget(within.budget);
    replica.sync_total = link.welcome.total_bricks;
    let eye = within.budget.and(within.eye);
    let wanted = eye.map(|e| Rule::eye_region(replica.map.region_dims(), e));
    loop {
        link::sync(&mut link, &mut replica, |_| {})
            .await
            .context("syncing the scene")?;
        // Complete for the camera asked for (the server may have begun from its own).
        let at = replica.held().and_then(|h| h.rule()).map(|r| r.eye);
        // A budget the whole scene fits is served the whole scene: nothing held to check.
        if wanted.is_none() || replica.held().is_none() || at == wanted {
            break;
        }
        replica.synced = false;
    }
    let sync_ms = started.elapsed().as_secs_f64() * 1e3;
    link.close().await;
    Ok((replica, sync_ms))
}

/// The camera a user asked for. Without `--eye`, the first camera [`viewpoint::find`] picks
/// for the scene (outside framing the model, or inside an enclosed one); a `--target` given
/// alone replaces only its target. With `--eye` and no `--target`, it looks at the scene's
/// centre.
pub fn camera(map: &BrickMap, eye: Option<[f32; 3]>, target: Option<[f32; 3]>, fov: f32) -> Camera {
    match eye {
        None => {
            let found = viewpoint::find(map, fov).camera;
            Camera {
                target: target.unwrap_or(found.target),
                fov_y: fov,
                ..found
            }
        }
        Some(eye) => Camera {
            eye,
            target: target.unwrap_or(map.size().map(|s| s as f32 * 0.5)),
            fov_y: fov,
        },
    }
}

fn median(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples.get(samples.len() / 2).copied().unwrap_or(0.0)
}

/// A traced image and how long tracing took.
pub struct Rendered {
    pub pixels: Vec<[u8; 4]>,
    pub trace_ms: f64,
    pub gpu_bytes: u64,
    pub adapter: String,
}

/// Traces `replica` on the GPU: one warm-up frame (pipeline compilation), then `timed` frames.
pub fn render_gpu(
    ctx: &GpuContext,
    replica: &mut Replica,
    projection: &Projection,
    lighting: &Lighting,
    timed: u32,
) -> Result<Rendered> {
    let budget = replica.budget();
    let scene = GpuScene::within(ctx, &mut replica.map, None, budget)?;
    let mut tracer = Tracer::new(ctx)?;
    tracer.trace(ctx, &scene, projection, lighting)?;
    let mut samples = Vec::new();
    for _ in 0..timed.max(1) {
        let started = Instant::now();
        tracer.trace(ctx, &scene, projection, lighting)?;
        samples.push(started.elapsed().as_secs_f64() * 1e3);
    }
    let frame = tracer.read_back(ctx)?;
    Ok(Rendered {
        pixels: frame.pixels,
        trace_ms: median(samples),
        gpu_bytes: scene.gpu_bytes(),
        adapter: ctx.adapter_name.clone(),
    })
}

/// Traces `replica` with the CPU tracer on every core.
pub fn render_cpu(
    replica: &Replica,
    projection: &Projection,
    lighting: &Lighting,
    timed: u32,
) -> Rendered {
    let mut samples = Vec::new();
    let mut pixels = Vec::new();
    for _ in 0..timed.max(1) {
        let started = Instant::now();
        pixels = brickcast_protocol::render::render(&replica.map, projection, lighting, 0).pixels;
        samples.push(started.elapsed().as_secs_f64() * 1e3);
    }
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    Rendered {
        pixels,
        trace_ms: median(samples),
        gpu_bytes: 0,
        adapter: format!("cpu ({threads} threads)"),
    }
}

/// Writes RGBA8 pixels as a PNG.
pub fn write_png(path: &Path, width: u32, height: u32, pixels: &[[u8; 4]]) -> Result<()> {
    let image = image::RgbaImage::from_raw(width, height, pixels.as_flattened().to_vec())
        .context("pixel count does not match the image size")?;
    image
        .save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("writing {}", path.display()))
}

/// Everything `brickcast render` does after parsing its arguments.
pub struct RenderJob<'a> {
    /// Addresses of the scene (several: a cluster's nodes, tried in turn until one syncs).
    pub urls: &'a [String],
    pub token: Option<&'a str>,
    pub out: &'a Path,
    pub width: u32,
    pub height: u32,
    pub eye: Option<[f32; 3]>,
    pub target: Option<[f32; 3]>,
    pub fov: f32,
    pub cpu: bool,
    pub backends: BackendChoice,
    pub timed_frames: u32,
    pub lighting: Lighting,
    /// How exactly the copy keeps colours.
    pub colours: Quality,
    /// GPU bytes for the scene: `None` fetches every brick, a budget the working set at `eye`.
    pub budget: Option<u64>,
}

pub fn run(job: &RenderJob<'_>) -> Result<RenderReport> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let (mut replica, sync_ms) = runtime.block_on(fetch_any(
        job.urls,
        job.token,
        job.colours,
        Within {
            budget: job.budget,
            eye: job.eye,
        },
    ))?;
    let camera = camera(&replica.map, job.eye, job.target, job.fov);
    let projection = camera.project(job.width, job.height).with_context(|| {
        format!(
            "the camera is degenerate (eye {:?}, target {:?}, fov {}, {}×{})",
            camera.eye, camera.target, camera.fov_y, job.width, job.height
        )
    })?;
    let lighting = job.lighting;
    let rendered = if job.cpu {
        render_cpu(&replica, &projection, &lighting, job.timed_frames)
    } else {
        let ctx = GpuContext::headless(job.backends)?;
        render_gpu(&ctx, &mut replica, &projection, &lighting, job.timed_frames)?
    };
    write_png(job.out, job.width, job.height, &rendered.pixels)?;
    Ok(RenderReport {
        width: job.width,
        height: job.height,
        bricks: replica.map.brick_count(),
        voxels: replica.map.solid_voxels(),
        gpu_bytes: rendered.gpu_bytes,
        sync_ms,
        trace_ms: rendered.trace_ms,
        adapter: rendered.adapter,
        scene: replica.scene.clone(),
        eye: camera.eye,
        target: camera.target,
    })
}
