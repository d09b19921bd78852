//! `brickcast fly`: the load tool for large worlds (issue #30). Each client states a GPU budget
//! and flies a straight path through the scene at a fixed speed and frame rate (bouncing off
//! the edges, each from its own seeded start and heading), sending its camera every frame the
//! way a viewer does. Reported per client and in aggregate:
//! - **first picture**: connect → the first working-set data applied (something to draw);
//! - **complete**: connect → every brick of the first working set present (`SyncDone` for the
//!   rule of the starting eye);
//! - **full resolution near the eye**: the share of frames in which every region within
//!   `--full-within` voxels of the eye shows level 0;
//! - the most GPU bytes its copy took (the map's arrays as uploaded, after every message),
//!   against the budget, and how often it packed its arrays to stay within it;
//! - bytes received per second in flight, and the server's CPU per client (from `/metrics`).

use std::time::{Duration, Instant};

use brickcast_protocol::map::REGION_EDGE;
use brickcast_protocol::replica::Replica;
use brickcast_protocol::wire::{Budget, ClientMsg, ServerMsg};
use brickcast_protocol::working_set::Rule;
use serde::Serialize;

use crate::link::{self, Link, LinkError};

/// What `brickcast fly` is asked to do.
#[derive(Debug, Clone, clap::Args)]
pub struct FlyArgs {
    /// Flying clients (one websocket and one task each).
    #[arg(long, default_value_t = 1)]
    pub clients: u32,
    /// GPU memory each client gives the scene (e.g. 256MiB).
    #[arg(long, default_value = "256MiB")]
    pub gpu_budget: brickcast_client_core::budget::GpuBudget,
    /// Voxels the eye moves per frame.
    #[arg(long, default_value_t = 16.0)]
    pub speed: f32,
    /// Frames per second (camera updates and samples).
    #[arg(long, default_value_t = 30.0)]
    pub fps: f32,
    /// Seconds of flight after the first working set is complete.
    #[arg(long, default_value_t = 60.0)]
    pub duration: f64,
    /// Height of the paths in voxels (default: 3/4 of the scene's height).
    #[arg(long)]
    pub height: Option<f32>,
    /// A frame counts as sharp when every region within this many voxels of the eye shows
    /// level 0.
    #[arg(long, default_value_t = 256.0)]
    pub full_within: f32,
    /// Seed of the paths' starts and headings.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long)]
    pub token: Option<String>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// One client's flight.
#[derive(Debug, Clone, Serialize)]
pub struct Flight {
    pub first_picture_ms: f64,
    pub complete_ms: f64,
    pub frames: u64,
    /// Frames with level 0 everywhere within `--full-within` of the eye.
    pub sharp_frames: u64,
    /// The most bytes the copy's arrays took (after every message the copy applied).
    pub peak_gpu_bytes: u64,
    /// Times the copy packed its arrays to stay within the budget.
    pub compactions: u64,
    /// Bytes received per second during the flight.
    pub bytes_per_s: f64,
    /// Level-0 reach the server fitted (regions), at the start and at the end.
    pub near_start: u32,
    pub near_end: u32,
}

/// What `brickcast fly --json` prints.
#[derive(Debug, Clone, Serialize)]
pub struct FlyReport {
    pub clients: u32,
    pub budget_bytes: u64,
    pub speed: f32,
    pub fps: f32,
    pub first_picture_ms_median: f64,
    pub first_picture_ms_max: f64,
    pub complete_ms_median: f64,
    pub complete_ms_max: f64,
    /// Sharp frames over all frames, the worst client's share.
    pub sharp_share_min: f64,
    pub sharp_share_all: f64,
    pub peak_gpu_bytes_max: u64,
    /// Times the copies packed their arrays to stay within the budget, all clients together.
    pub compactions: u64,
    pub bytes_per_s_median: f64,
    /// Server CPU over the flight per client (1.0 = one core), when `/metrics` answers.
    pub server_cpu_per_client: Option<f64>,
    pub flights: Vec<Flight>,
}

/// Runs the flights against the first of `urls` and reports.
pub async fn run(urls: &[String], args: &FlyArgs) -> anyhow::Result<FlyReport> {
    let budget = args
        .gpu_budget
        .0
        .ok_or_else(|| anyhow::anyhow!("fly needs a limited --gpu-budget (e.g. 256MiB)"))?;
    if !(args.speed.is_finite() && args.speed > 0.0 && args.fps.is_finite() && args.fps > 0.0) {
        anyhow::bail!("--speed and --fps must be positive numbers");
    }
    let url = link::websocket_url(urls.first().map_or("", String::as_str))?;
    let before = super::server_metrics(&url).await;
    let started = Instant::now();
    let tasks: Vec<_> = (0..args.clients)
        .map(|i| {
            let (url, args) = (url.clone(), args.clone());
            tokio::spawn(async move { fly_one(&url, &args, budget, i).await })
        })
        .collect();
    let mut flights = Vec::new();
    for task in tasks {
        flights.push(task.await??);
    }
    let wall = started.elapsed().as_secs_f64();
    let after = super::server_metrics(&url).await;
    let cpu = |m: &Option<std::collections::BTreeMap<String, f64>>| {
        m.as_ref()
            .and_then(|m| m.get("brickcast_process_cpu_seconds_total").copied())
    };
    let server_cpu_per_client = match (cpu(&before), cpu(&after)) {
        (Some(a), Some(b)) if wall > 0.0 => Some((b - a) / wall / f64::from(args.clients.max(1))),
        _ => None,
    };
    let stat = |f: fn(&Flight) -> f64| {
        let mut v: Vec<f64> = flights.iter().map(f).collect();
        v.sort_by(f64::total_cmp);
        (
            v.get(v.len() / 2).copied().unwrap_or(0.0),
            v.last().copied().unwrap_or(0.0),
        )
    };
    let (fp_med, fp_max) = stat(|f| f.first_picture_ms);
    let (c_med, c_max) = stat(|f| f.complete_ms);
    let (bps_med, _) = stat(|f| f.bytes_per_s);
    let share = |f: &Flight| f.sharp_frames as f64 / f.frames.max(1) as f64;
    let frames: u64 = flights.iter().map(|f| f.frames).sum();
    let sharp: u64 = flights.iter().map(|f| f.sharp_frames).sum();
    Ok(FlyReport {
        clients: args.clients,
        budget_bytes: budget,
        speed: args.speed,
        fps: args.fps,
        first_picture_ms_median: fp_med,
        first_picture_ms_max: fp_max,
        complete_ms_median: c_med,
        complete_ms_max: c_max,
        sharp_share_min: flights.iter().map(share).fold(1.0, f64::min),
        sharp_share_all: sharp as f64 / frames.max(1) as f64,
        peak_gpu_bytes_max: flights.iter().map(|f| f.peak_gpu_bytes).max().unwrap_or(0),
        compactions: flights.iter().map(|f| f.compactions).sum(),
        bytes_per_s_median: bps_med,
        server_cpu_per_client,
        flights,
    })
}

/// A small deterministic generator for the paths (SplitMix64).
fn mix(seed: u64) -> u64 {
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A straight path that bounces off the scene's edges.
struct Path {
    eye: [f32; 3],
    step: [f32; 3],
    size: [f32; 3],
}

impl Path {
    fn new(size: [u32; 3], height: Option<f32>, speed: f32, seed: u64) -> Path {
        let unit = |k: u64| {
            (mix(seed.wrapping_mul(31).wrapping_add(k)) >> 11) as f32 / (1u64 << 53) as f32
        };
        let size = size.map(|s| s as f32);
        let y = height.unwrap_or(size[1] * 0.75).clamp(0.0, size[1]);
        let angle = unit(3) * std::f32::consts::TAU;
        Path {
            eye: [unit(1) * size[0], y, unit(2) * size[2]],
            step: [angle.cos() * speed, 0.0, angle.sin() * speed],
            size,
        }
    }

    fn advance(&mut self) {
        for i in [0, 2] {
            self.eye[i] += self.step[i];
            if self.eye[i] < 0.0 || self.eye[i] > self.size[i] {
                self.step[i] = -self.step[i];
                self.eye[i] = self.eye[i].clamp(0.0, self.size[i]);
            }
        }
    }
}

/// Whether every region within `reach` regions of the eye's region shows level 0.
fn sharp(replica: &Replica, eye: [f32; 3], reach: u32) -> bool {
    let Some(held) = replica.held() else {
        return true;
    };
    let dims = replica.map.region_dims();
    let e = Rule::eye_region(dims, eye);
    let lo = e.map(|v| v.saturating_sub(reach));
    let hi: [u32; 3] = std::array::from_fn(|i| e[i].saturating_add(reach + 1).min(dims[i]));
    brickcast_protocol::map::box_points(lo, hi).all(|r| held.shown_level(r) == Some(0))
}

/// The scene's size from the server's `/scenes` list, so a path can start before connecting.
async fn scene_size(ws_url: &str) -> Option<[u32; 3]> {
    let name = ws_url.split("/scenes/").nth(1)?.split('/').next()?;
    let response = super::http_get(ws_url, "/scenes").await?;
    let (_, body) = response.split_once("\r\n\r\n")?;
    let list: serde_json::Value = serde_json::from_str(body).ok()?;
    let scene = list.as_array()?.iter().find(|s| s["name"] == name)?;
    let size: Vec<u32> = scene["size"]
        .as_array()?
        .iter()
        .filter_map(|v| v.as_u64().and_then(|v| u32::try_from(v).ok()))
        .collect();
    size.try_into().ok()
}

async fn fly_one(url: &str, args: &FlyArgs, budget: u64, i: u32) -> anyhow::Result<Flight> {
    // Where the path starts goes in the Hello, so the first working set is the one at the eye
    // (a server whose `/scenes` does not answer starts it at its default camera instead).
    let seed = args.seed.wrapping_add(u64::from(i));
    let planned = scene_size(url)
        .await
        .map(|size| Path::new(size, args.height, args.speed, seed));
    let started = Instant::now();
    let mut link = Link::connect_within(
        url,
        &format!("brickcast fly {i}"),
        0,
        args.token.as_deref(),
        None,
        Some(Budget {
            bytes: budget,
            eye: planned.as_ref().map(|p| p.eye),
        }),
    )
    .await?;
    let size = link.welcome.size;
    let mut path = match planned {
        Some(p) if p.size == size.map(|s| s as f32) => p,
        _ => Path::new(size, args.height, args.speed, seed),
    };
    let mut replica = Replica::new(&link.welcome.scene, size)?;
    replica.record_gpu_changes(false);
    replica.set_budget(Some(budget));
    let camera = |eye| ClientMsg::Camera {
        eye,
        forward: [1.0, 0.0, 0.0],
    };
    link.send(&camera(path.eye)).await?;
    let want = Rule::eye_region(replica.map.region_dims(), path.eye);
    let mut first_picture = None;
    let mut peak = 0;
    let complete = loop {
        let msg = next(&mut link).await?;
        replica.apply(&msg)?;
        peak = peak.max(replica.map.memory().total_bytes);
        if first_picture.is_none()
            && matches!(msg, ServerMsg::Regions { .. } | ServerMsg::Coarse { .. })
        {
            first_picture = Some(started.elapsed());
        }
        let at = replica.held().and_then(|h| h.rule()).map(|r| r.eye);
        // A budget the whole scene fits is served the whole scene.
        if replica.synced && (replica.held().is_none() || at == Some(want)) {
            break started.elapsed();
        }
    };
    let near_start = replica.held().and_then(|h| h.rule()).map_or(0, |r| r.near);
    let reach = (args.full_within / REGION_EDGE as f32).ceil() as u32;
    let frame = Duration::from_secs_f64(1.0 / f64::from(args.fps));
    let mut tick = tokio::time::interval(frame);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let flight_start = Instant::now();
    let bytes_before = link.bytes_in;
    let (mut frames, mut sharp_frames) = (0u64, 0u64);
    while flight_start.elapsed().as_secs_f64() < args.duration {
        tokio::select! {
            _ = tick.tick() => {
                frames += 1;
                if sharp(&replica, path.eye, reach) {
                    sharp_frames += 1;
                }
                path.advance();
                link.send(&camera(path.eye)).await?;
            }
            msg = next(&mut link) => {
                replica.apply(&msg?)?;
                peak = peak.max(replica.map.memory().total_bytes);
            }
        }
    }
    let flown = flight_start.elapsed().as_secs_f64();
    let bytes_per_s = (link.bytes_in - bytes_before) as f64 / flown.max(1e-9);
    let near_end = replica.held().and_then(|h| h.rule()).map_or(0, |r| r.near);
    link.close().await;
    Ok(Flight {
        first_picture_ms: first_picture.unwrap_or(complete).as_secs_f64() * 1e3,
        complete_ms: complete.as_secs_f64() * 1e3,
        frames,
        sharp_frames,
        peak_gpu_bytes: peak,
        compactions: replica.compactions,
        bytes_per_s,
        near_start,
        near_end,
    })
}

/// The next message; errors and a closed connection end the flight.
async fn next(link: &mut Link) -> anyhow::Result<ServerMsg> {
    match link.next().await? {
        Some(ServerMsg::Error { code, message }) => {
            Err(LinkError::Refused { code, message }.into())
        }
        Some(msg) => Ok(msg),
        None => Err(LinkError::Closed.into()),
    }
}

/// The report as a table, for people.
pub fn table(r: &FlyReport) -> String {
    let mib = |b: f64| b / f64::from(1u32 << 20);
    let mut s = format!(
        "{} clients, {:.0} MiB each, {} voxels/frame at {} fps\n",
        r.clients,
        mib(r.budget_bytes as f64),
        r.speed,
        r.fps
    );
    s += &format!(
        "first picture   median {:.0} ms, max {:.0} ms\ncomplete        median {:.0} ms, max {:.0} ms\n",
        r.first_picture_ms_median, r.first_picture_ms_max, r.complete_ms_median, r.complete_ms_max
    );
    s += &format!(
        "sharp frames    {:.1}% of all, worst client {:.1}%\npeak GPU copy   {:.1} MiB (budget {:.1} MiB), packed {} times\nreceived        median {:.1} KiB/s per client\n",
        100.0 * r.sharp_share_all,
        100.0 * r.sharp_share_min,
        mib(r.peak_gpu_bytes_max as f64),
        mib(r.budget_bytes as f64),
        r.compactions,
        r.bytes_per_s_median / 1024.0
    );
    if let Some(cpu) = r.server_cpu_per_client {
        s += &format!("server CPU      {:.3} cores per client\n", cpu);
    }
    s
}
