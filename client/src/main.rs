//! `brickcast`: view a scene in a window, render one frame of it to a PNG, or load-test the
//! server that holds it.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use brickcast_client::gpu::BackendChoice;
use brickcast_client::headless::{self, RenderJob};
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "brickcast",
    version,
    about = "Thin client for brickcast scene servers"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Open a window on a scene: fly around, edit with the mouse.
    View {
        /// Scene address, e.g. ws://127.0.0.1:7878/scenes/demo; several addresses of one scene
        /// (a cluster's nodes) are tried in turn when a connection is lost.
        #[arg(required = true, num_args = 1..)]
        urls: Vec<String>,
        /// Access token (servers started with --auth).
        #[arg(long)]
        token: Option<String>,
        #[command(flatten)]
        view: brickcast_client::viewer::ViewArgs,
    },
    /// Sync a scene, render one frame and write it as a PNG.
    Render {
        /// Scene address, e.g. ws://127.0.0.1:7878/scenes/demo; with several (a cluster's
        /// nodes), the first that answers.
        #[arg(required = true, num_args = 1..)]
        urls: Vec<String>,
        #[arg(long)]
        token: Option<String>,
        /// Where to write the PNG (the name must end in .png).
        #[arg(long, value_parser = png_path)]
        out: PathBuf,
        #[arg(long, default_value_t = 640)]
        width: u32,
        #[arg(long, default_value_t = 360)]
        height: u32,
        /// The image's size as `view --size` takes it, e.g. 1280x720 (instead of --width and
        /// --height).
        #[arg(long, conflicts_with_all = ["width", "height"])]
        size: Option<String>,
        /// Camera position in voxels, "x,y,z" (default: the scene's first camera, see README).
        #[arg(long, value_parser = brickcast_client::light::parse_vec3, allow_hyphen_values = true)]
        eye: Option<[f32; 3]>,
        /// Point the camera looks at, "x,y,z".
        #[arg(long, value_parser = brickcast_client::light::parse_vec3, allow_hyphen_values = true)]
        target: Option<[f32; 3]>,
        /// Vertical field of view in degrees.
        #[arg(long, default_value_t = 60.0)]
        fov: f32,
        /// Trace on the CPU instead of the GPU.
        #[arg(long)]
        cpu: bool,
        /// Frames to time after a warm-up frame; trace_ms is their median.
        #[arg(long, default_value_t = 3)]
        frames: u32,
        /// Print a JSON report on stdout.
        #[arg(long)]
        json: bool,
        /// Only use Vulkan adapters (no fallback to other APIs).
        #[arg(long)]
        vulkan: bool,
        #[command(flatten)]
        light: brickcast_client::LightArgs,
        /// How exactly the copy keeps colours: `exact`, `bounded` or `bounded:N` (as `view`).
        #[arg(long, default_value_t = brickcast_protocol::blocks::Quality::default())]
        colours: brickcast_protocol::blocks::Quality,
        /// GPU memory for the scene: `unlimited` (every brick) or a size such as 256MiB. A
        /// scene that fits half of it is held whole; a larger world, the working set around
        /// --eye: full resolution near it, coarser further away.
        #[arg(long, default_value_t = brickcast_client_core::budget::GpuBudget(Some(brickcast_client_core::budget::NATIVE_DEFAULT)))]
        gpu_budget: brickcast_client_core::budget::GpuBudget,
    },
    /// Load-test a server: many clients edit one scene; report throughput and latency, and
    /// check that every client's copy ends equal to the server's (non-zero exit if not).
    Load {
        /// Scene address, e.g. ws://127.0.0.1:7878/scenes/demo; several addresses of one scene
        /// (a cluster's nodes) share the clients out in turn and are reported per server.
        #[arg(required = true, num_args = 1..)]
        urls: Vec<String>,
        #[command(flatten)]
        args: brickcast_client::load::LoadArgs,
    },
    /// Load-test streaming of large worlds: clients with a GPU budget fly straight paths
    /// through a scene; report time to first picture and to a complete working set, how often
    /// level 0 surrounds the eye, GPU bytes against the budget, bandwidth and server CPU.
    Fly {
        /// Scene address, e.g. ws://127.0.0.1:7878/scenes/world.
        #[arg(required = true, num_args = 1..)]
        urls: Vec<String>,
        #[command(flatten)]
        args: brickcast_client::load::fly::FlyArgs,
    },
}

/// `--out`: only PNG is written, so a name that promises another format is refused up front
/// (before a long sync), not silently written as PNG.
fn png_path(s: &str) -> Result<PathBuf, String> {
    let path = PathBuf::from(s);
    match path.extension().and_then(|e| e.to_str()) {
        Some(e) if e.eq_ignore_ascii_case("png") => Ok(path),
        _ => Err(format!(
            "{s:?}: only PNG images are written; give a name ending in .png"
        )),
    }
}

/// The token a pasted browser link carries (`#token=…`), when no `--token` is given.
fn token_of_links(urls: &[String]) -> Option<String> {
    urls.iter()
        .find_map(|u| brickcast_client::link::link_token(u))
}

/// Runs the command; errors are printed for people (the cause chain on one line, no backtrace
/// even with `RUST_BACKTRACE` set) with a failing exit status.
fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("Error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> Result<()> {
    use std::io::IsTerminal;
    let cli = Cli::parse();
    // Mesa's device-select layer looks for a display to order GPUs by, and with no Wayland
    // runtime directory prints "XDG_RUNTIME_DIR is invalid or not set" twice: a headless
    // render has no display to ask (wgpu picks the adapter itself). Unless the user set it.
    if matches!(cli.command, Command::Render { .. })
        && std::env::var_os("NODEVICE_SELECT").is_none()
    {
        // SAFETY: nothing else runs yet: no thread has been started and no variable read.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,wgpu_core=warn,wgpu_hal=warn,naga=warn".into()),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a person at a terminal, not in a log file or a pipe.
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    match cli.command {
        Command::Load { urls, args } => {
            let outcome = brickcast_client::load::run_blocking_on(&urls, &args)?;
            let table = outcome.table();
            if args.json {
                eprint!("{table}");
                println!(
                    "{}",
                    serde_json::to_string(&outcome.report).context("encoding the report")?
                );
            } else {
                print!("{table}");
            }
            if !outcome.failures.is_empty() {
                bail!(
                    "the run failed its checks ({} problems, listed above)",
                    outcome.failures.len()
                );
            }
            Ok(())
        }
        Command::Fly { urls, args } => {
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()?;
            let report = runtime.block_on(brickcast_client::load::fly::run(&urls, &args))?;
            let table = brickcast_client::load::fly::table(&report);
            if args.json {
                eprint!("{table}");
                println!(
                    "{}",
                    serde_json::to_string(&report).context("encoding the report")?
                );
            } else {
                print!("{table}");
            }
            Ok(())
        }
        Command::View { urls, token, view } => {
            let token = token.or_else(|| token_of_links(&urls));
            brickcast_client::viewer::run(&urls, token, view)
        }
        Command::Render {
            urls,
            token,
            out,
            width,
            height,
            size,
            eye,
            target,
            fov,
            cpu,
            frames,
            json,
            vulkan,
            light,
            colours,
            gpu_budget,
        } => {
            let (width, height) = match size {
                Some(size) => brickcast_client::viewer::parse_size(&size)?,
                None => (width, height),
            };
            if width == 0 || height == 0 || width > 16384 || height > 16384 {
                bail!("image size {width}×{height} is out of range (1..=16384 per side)");
            }
            let token = token.or_else(|| token_of_links(&urls));
            let report = headless::run(&RenderJob {
                urls: &urls,
                token: token.as_deref(),
                out: &out,
                width,
                height,
                eye,
                target,
                fov,
                cpu,
                backends: if vulkan {
                    BackendChoice::Vulkan
                } else {
                    BackendChoice::Primary
                },
                timed_frames: frames,
                lighting: light.lighting()?,
                colours,
                budget: gpu_budget.0,
            })?;
            if json {
                println!(
                    "{}",
                    serde_json::to_string(&report).context("encoding the report")?
                );
            } else {
                eprintln!(
                    "{}: {}×{} of {} ({} bricks, {} voxels) on {}: sync {:.0} ms, trace {:.2} ms",
                    out.display(),
                    report.width,
                    report.height,
                    report.scene,
                    report.bricks,
                    report.voxels,
                    report.adapter,
                    report.sync_ms,
                    report.trace_ms
                );
            }
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("brickcast").chain(args.iter().copied()))
    }

    #[test]
    fn render_takes_negative_coordinates_and_only_png_names() {
        let cli = parse(&[
            "render",
            "ws://127.0.0.1:7878/scenes/demo",
            "--out",
            "a.PNG",
            "--eye",
            "-100,180,-100",
            "--target",
            "-1.5,0,-2",
        ])
        .expect("negative coordinates parse");
        let Command::Render { eye, target, .. } = cli.command else {
            panic!("not a render command");
        };
        assert_eq!(eye, Some([-100.0, 180.0, -100.0]));
        assert_eq!(target, Some([-1.5, 0.0, -2.0]));
        let cli = parse(&[
            "render",
            "ws://h:1/scenes/demo",
            "--out",
            "a.png",
            "--size",
            "320x200",
        ])
        .expect("--size parses");
        let Command::Render { size, .. } = cli.command else {
            panic!("not a render command");
        };
        assert_eq!(size.as_deref(), Some("320x200"));
        assert_eq!(
            brickcast_client::viewer::parse_size("320x200").unwrap(),
            (320, 200)
        );
        let both = parse(&[
            "render",
            "ws://h:1/scenes/demo",
            "--out",
            "a.png",
            "--size",
            "3x2",
            "--width",
            "9",
        ]);
        assert!(both.is_err(), "--size with --width is refused");
        for bad in ["x.jpg", "x", "x.png.tmp"] {
            let e = parse(&["render", "ws://h:1/scenes/demo", "--out", bad]).err();
            let e = e.map(|e| e.to_string()).unwrap_or_default();
            assert!(e.contains("only PNG"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_pasted_browser_link_brings_its_token() {
        let links = ["http://127.0.0.1:7878/scenes/demo#token=t0k".to_string()];
        assert_eq!(token_of_links(&links).as_deref(), Some("t0k"));
        assert_eq!(token_of_links(&["ws://h:1/scenes/demo".to_string()]), None);
    }
}
