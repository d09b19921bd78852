//! `brickcast-server import` and `export`: progress bars, the summary, and where the scene goes
//! (straight into the store, or to a running server through its spool).

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use anyhow::Context;
use brickcast_server::import::{self, ImportOptions, Phase, Progress};
use brickcast_server::incoming;
use brickcast_server::store::{Store, valid_scene_name};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// How long `import` waits for a running server to take a spooled scene before saying it will
/// be taken when a server next runs.
const ADOPT_WAIT: Duration = Duration::from_secs(60);

#[derive(clap::Args)]
pub struct Args {
    /// Model file: `.obj` or `.vox`.
    model: PathBuf,
    /// Name of the new scene.
    #[arg(long)]
    scene: String,
    /// Voxels along the mesh's longest axis: a power of two, 8..=8192 (meshes only).
    #[arg(long)]
    resolution: Option<u32>,
    #[arg(long, default_value = "./brickcast-data")]
    data: PathBuf,
    /// Replace an existing scene of that name (only while no server runs on the store).
    #[arg(long)]
    replace: bool,
    /// Voxelizing threads (default: one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Let the model's MTL libraries and textures be read from outside its own folder (by
    /// default a model cannot reach other files on this machine).
    #[arg(long)]
    allow_outside_files: bool,
    /// Print the summary as one JSON object.
    #[arg(long)]
    json: bool,
    /// Import into a cluster (its NATS URL) instead of the redb store: every node serves it.
    #[arg(long, value_name = "URL")]
    nats: Option<String>,
    /// Copies JetStream keeps of the new scene's log and snapshot (with --nats).
    #[arg(long, default_value_t = 1, requires = "nats", value_parser = clap::value_parser!(u8).range(1..=5))]
    replicas: u8,
    /// No progress bars.
    #[arg(long)]
    quiet: bool,
}

/// One progress bar per phase on stderr (hidden when stderr is not a terminal or with --quiet).
pub(crate) struct Bars {
    hidden: bool,
    current: Mutex<Option<ProgressBar>>,
}

impl Bars {
    pub(crate) fn new(hidden: bool) -> Bars {
        Bars {
            hidden,
            current: Mutex::new(None),
        }
    }

    fn bar(&self) -> std::sync::MutexGuard<'_, Option<ProgressBar>> {
        self.current.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Progress for Bars {
    fn start(&self, phase: Phase, total: u64) {
        let bar = if total == 0 {
            ProgressBar::new_spinner()
        } else {
            ProgressBar::new(total)
        };
        if self.hidden {
            bar.set_draw_target(ProgressDrawTarget::hidden());
        }
        let template = if total == 0 {
            "{prefix:>11} {spinner} {elapsed}"
        } else {
            "{prefix:>11} [{bar:40}] {percent:>3}% {elapsed} (eta {eta})"
        };
        if let Ok(style) = ProgressStyle::with_template(template) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_prefix(phase.label());
        bar.enable_steady_tick(Duration::from_millis(120));
        if let Some(old) = self.bar().replace(bar) {
            old.finish();
        }
    }

    fn advance(&self, units: u64) {
        if let Some(bar) = self.bar().as_ref() {
            bar.inc(units);
        }
    }

    fn finish(&self) {
        if let Some(bar) = self.bar().take() {
            bar.finish();
        }
    }
}

/// Where the imported scene goes.
enum Destination {
    Store(Store),
    /// A cluster: the scene's log stream, first snapshot and scene-list entry go to NATS.
    Cluster(Box<(tokio::runtime::Runtime, brickcast_server::cluster::Cluster)>),
    /// A server holds the store: hand the scene over through its spool.
    RunningServer,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !valid_scene_name(&args.scene) {
        anyhow::bail!(
            "scene name {:?} is invalid: use 1-64 letters, digits, '-', '_' or '.'",
            args.scene
        );
    }
    let format = import::Format::of(&args.model)?;
    if format == import::Format::Vox && args.resolution.is_some() {
        eprintln!(
            "warning: --resolution applies to meshes; a .vox file is imported voxel for voxel"
        );
    }
    let options = ImportOptions {
        resolution: args
            .resolution
            .unwrap_or(ImportOptions::default().resolution),
        threads: args.threads,
        allow_outside_files: args.allow_outside_files,
    };
    options.check()?;
    // Check the destination before the expensive part, so a name clash fails in milliseconds.
    let destination = if let Some(url) = &args.nats {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?;
        let cluster = runtime.block_on(brickcast_server::cluster::Cluster::connect(
            url,
            usize::from(args.replicas),
        ))?;
        let exists = runtime
            .block_on(brickcast_server::cluster::catalog::scene_names(&cluster))?
            .contains(&args.scene);
        if exists && !args.replace {
            anyhow::bail!(
                "scene {} already exists in the cluster at {url}; pass --replace to overwrite it (and restart the nodes serving it)",
                args.scene
            );
        }
        Destination::Cluster(Box::new((runtime, cluster)))
    } else {
        match Store::open(&args.data) {
            Ok(store) => {
                let exists = store.scenes()?.iter().any(|(n, _)| *n == args.scene);
                if exists && !args.replace {
                    anyhow::bail!(
                        "scene {} already exists in {}; pass --replace to overwrite it",
                        args.scene,
                        args.data.display()
                    );
                }
                Destination::Store(store)
            }
            Err(e) if e.is_locked() => {
                if args.replace {
                    anyhow::bail!(
                        "a running server holds {}; --replace needs the server stopped (a live scene cannot be swapped under its viewers)",
                        args.data.display()
                    );
                }
                Destination::RunningServer
            }
            Err(e) => return Err(e.into()),
        }
    };

    let started = Instant::now();
    let bars = Bars::new(args.quiet || args.json);
    let imported = import::import_file(&args.model, &options, &bars)
        .with_context(|| format!("importing {}", args.model.display()))?;
    for warning in &imported.report.warnings {
        eprintln!("warning: {warning}");
    }
    let map = &imported.map;

    let store_started = Instant::now();
    let served_by = match destination {
        Destination::Store(store) => {
            if args.replace && store.delete_scene(&args.scene)? {
                eprintln!("replaced the earlier scene {}", args.scene);
            }
            bars.start(Phase::Storing, map.brick_count());
            store.create_scene_with_progress(&args.scene, map, &mut |n| bars.advance(n))?;
            bars.finish();
            "the store"
        }
        Destination::Cluster(cluster) => {
            let (runtime, cluster) = *cluster;
            bars.start(Phase::Storing, 0);
            runtime.block_on(brickcast_server::cluster::catalog::create_scene(
                &cluster,
                &args.scene,
                map,
                args.replace,
            ))?;
            bars.finish();
            "the cluster"
        }
        Destination::RunningServer => {
            bars.start(Phase::Storing, 0);
            let file = incoming::write(&args.data, &args.scene, map)?;
            let adopted = wait_for_server(&file)?;
            bars.finish();
            if adopted {
                "the running server"
            } else {
                eprintln!(
                    "note: a process holds the store but has not taken the scene in {}s; it waits in {} and the next server to start on {} will serve it",
                    ADOPT_WAIT.as_secs(),
                    file.display(),
                    args.data.display()
                );
                "the spool"
            }
        }
    };
    let store_seconds = store_started.elapsed().as_secs_f64();
    let memory = map.memory();
    let report = &imported.report;
    if args.json {
        let mut value = serde_json::to_value(report)?;
        value["scene"] = args.scene.clone().into();
        value["memory"] = serde_json::to_value(memory)?;
        value["store_seconds"] = store_seconds.into();
        value["total_seconds"] = started.elapsed().as_secs_f64().into();
        value["destination"] = served_by.into();
        println!("{value}");
    } else {
        println!(
            "imported {} as scene {}: {}x{}x{} voxels, into {served_by}",
            args.model.display(),
            args.scene,
            report.size[0],
            report.size[1],
            report.size[2]
        );
        if report.triangles > 0 {
            println!(
                "  triangles        {:>14} ({} without area skipped)",
                report.triangles, report.degenerate_triangles
            );
        }
        crate::print_memory(&memory);
        println!(
            "  seconds          {:>14.2} (parse {:.2}, voxelize {:.2}, store {:.2})",
            started.elapsed().as_secs_f64(),
            report.parse_seconds,
            report.voxelize_seconds,
            store_seconds
        );
    }
    Ok(())
}

/// Waits for the server to take (true) or refuse (error) a spooled scene; false on timeout.
fn wait_for_server(file: &Path) -> anyhow::Result<bool> {
    let deadline = Instant::now() + ADOPT_WAIT;
    while Instant::now() < deadline {
        let error_file = incoming::error_path(file);
        if let Ok(reason) = std::fs::read_to_string(&error_file) {
            anyhow::bail!(
                "the running server refused the scene: {} (the scene is kept in {}; delete it and {} when done)",
                reason.trim(),
                file.display(),
                error_file.display()
            );
        }
        if !file.exists() {
            return Ok(true);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(false)
}

pub fn export(scene: &str, out: &Path, data: &Path, json: bool) -> anyhow::Result<()> {
    let store = crate::open_store(data)?;
    let loaded = store.load_scene(scene)?;
    let (bytes, report) = import::vox::export_vox(&loaded.map);
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    if json {
        let mut value = serde_json::to_value(&report)?;
        value["scene"] = scene.into();
        value["out"] = out.display().to_string().into();
        value["bytes"] = bytes.len().into();
        println!("{value}");
    } else {
        let c = &report.colours;
        println!(
            "exported scene {scene} to {}: {} voxels in {} models, {} bytes",
            out.display(),
            report.voxels,
            report.models,
            bytes.len()
        );
        if c.exact {
            println!("  colours: {} distinct, kept exactly", c.distinct);
        } else {
            println!(
                "  colours: {} distinct quantised to {} (mean error {:.1}, worst {:.1} in RGB8 units)",
                c.distinct, c.palette, c.mean_error, c.max_error
            );
        }
    }
    Ok(())
}
