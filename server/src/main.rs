//! `brickcast-server`: a thin command line over the `brickcast_server` library.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use brickcast_server::auth::Auth;
use brickcast_server::store::Store;
use brickcast_server::{Server, ServerConfig};
use clap::{Parser, Subcommand};

mod admin_cli;
mod generate_cli;
mod import_cli;

#[derive(Parser)]
#[command(
    name = "brickcast-server",
    version,
    about = "Authoritative brickcast voxel scene server"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Serve every scene in the store over websockets (creates the demo scene in an empty store).
    Serve(ServeArgs),
    /// List the scenes in the store.
    Scenes {
        #[arg(long, default_value = "./brickcast-data")]
        data: PathBuf,
    },
    /// Voxels, bricks and memory per component of one scene.
    Stats {
        #[arg(long)]
        scene: String,
        #[arg(long, default_value = "./brickcast-data")]
        data: PathBuf,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
        /// Also lay the scene out as a viewer with this colour quality holds it (`exact`,
        /// `bounded`, `bounded:N`) and report its memory and colour error.
        #[arg(long, default_value_t = brickcast_protocol::blocks::Quality::default())]
        colours: brickcast_protocol::blocks::Quality,
        /// Also build the scene's levels of detail (`protocol/src/lod.rs`) and report each
        /// level's bricks and memory and the build time.
        #[arg(long)]
        lod: bool,
    },
    /// Fold a scene's edit log into its snapshot (the server does this itself periodically).
    Snapshot {
        #[arg(long)]
        scene: String,
        #[arg(long, default_value = "./brickcast-data")]
        data: PathBuf,
        /// Also replay log entries at or below the snapshot's sequence: a store written by
        /// brickcast-server 0.1 can hold such entries after an edit whose every op was
        /// rejected, and the server refuses to serve the scene until they are folded in.
        #[arg(long)]
        repair: bool,
        /// Sequences of the scene's past to keep, as `serve --keep-history` (0: none).
        #[arg(long, default_value_t = brickcast_server::store::DEFAULT_KEEP)]
        keep_history: u64,
        /// Bytes of the scene's past kept at most, as `serve --keep-history-bytes`.
        #[arg(long, default_value_t = brickcast_server::store::DEFAULT_KEEP_BYTES)]
        keep_history_bytes: u64,
    },
    /// Import a mesh (OBJ with its MTL and textures) or a MagicaVoxel .vox as a new scene.
    ///
    /// With a server running on the same store, the scene is handed to it and served at once.
    Import(import_cli::Args),
    /// Make a procedural world into the store, tile by tile on every core (for worlds too large
    /// to build whole first).
    #[command(subcommand)]
    Generate(generate_cli::Kind),
    /// Administer a running server: list, create, delete, restore, rename and reset scenes,
    /// disconnect a user (the admin API; see README "Running a server without stopping it").
    Admin(admin_cli::Args),
    /// Ask a cluster what it holds.
    Cluster {
        #[command(subcommand)]
        command: ClusterCmd,
    },
    /// Export a scene as a MagicaVoxel .vox file (models of at most 256³, 255 colours).
    Export {
        #[arg(long)]
        scene: String,
        /// Output file.
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value = "./brickcast-data")]
        data: PathBuf,
        /// Print the summary as one JSON object.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum ClusterCmd {
    /// Nodes (with each scene's sequence and map hash as the node holds it), scenes, each
    /// scene's owner, log length and snapshot sequence.
    Status {
        /// The cluster's NATS URL.
        #[arg(long, value_name = "URL")]
        nats: String,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Drop the messages of a scene's log that no node can read (missing, not a turn, or not
    /// continuing the scene's sequence), rebuilding the scene from its newest snapshot and the
    /// rest of the log, and say what was dropped. Changes nothing when the log can be followed.
    Repair {
        /// The cluster's NATS URL.
        #[arg(long, value_name = "URL")]
        nats: String,
        #[arg(long)]
        scene: String,
        /// Print one JSON object instead of lines.
        #[arg(long)]
        json: bool,
    },
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

fn run() -> anyhow::Result<()> {
    // Logs go to stderr: stdout carries what a command prints (`--json` output included).
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Colour codes only for a person at a terminal, not in a log file or a pipe.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    match Cli::parse().command {
        Cmd::Serve(args) => serve(args),
        Cmd::Admin(args) => admin_cli::run(args),
        Cmd::Scenes { data } => {
            let store = open_store(&data)?;
            for (name, meta) in store.scenes()? {
                println!(
                    "{name}\t{}x{}x{}\tsnapshot at seq {}\t{} log entries after it",
                    meta.size[0],
                    meta.size[1],
                    meta.size[2],
                    meta.snapshot_seq,
                    store.log_len(&name)?
                );
            }
            Ok(())
        }
        Cmd::Stats {
            scene,
            data,
            json,
            colours,
            lod,
        } => {
            let store = open_store(&data)?;
            let loaded = store.load_scene(&scene)?;
            let lod = lod.then(|| lod_stats(&loaded.map)).transpose()?;
            let m = loaded.map.memory();
            let coded = brickcast_protocol::palette::Mix::of(&loaded.map);
            let viewer = viewer_copy(&loaded.map, colours)?;
            let viewer_memory = viewer.memory();
            let viewer_coded = match colours.bound() {
                Some(bound) => brickcast_protocol::palette::Mix::bounded(&loaded.map, bound),
                None => coded.clone(),
            };
            if json {
                let mut value = serde_json::to_value(m)?;
                value["scene"] = scene.into();
                value["seq"] = loaded.seq.into();
                value["coded_colours"] = serde_json::to_value(&coded)?;
                value["viewer"] = serde_json::json!({
                    "colours": colours.to_string(),
                    "memory": viewer_memory,
                    "coded_colours": viewer_coded,
                });
                if let Some(lod) = &lod {
                    value["lod"] = serde_json::to_value(lod)?;
                }
                println!("{value}");
            } else {
                println!(
                    "scene {scene}: {}x{}x{} voxels, sequence {}",
                    m.size[0], m.size[1], m.size[2], loaded.seq
                );
                print_memory(&m);
                print_coded(&coded);
                println!("as a viewer holds it with --colours {colours}:");
                print_memory(&viewer_memory);
                print_coded(&viewer_coded);
                if let Some(lod) = &lod {
                    print_lod(lod);
                }
            }
            Ok(())
        }
        Cmd::Snapshot {
            scene,
            data,
            repair,
            keep_history,
            keep_history_bytes,
        } => {
            let store = open_store(&data)?;
            store.set_keep_history(keep_history);
            store.set_keep_history_bytes(keep_history_bytes);
            let loaded = if repair {
                store.load_scene_repairing(&scene)?
            } else {
                store.load_scene(&scene)?
            };
            let mut map = loaded.map;
            map.set_sequence(loaded.seq);
            store.snapshot(&scene, &map, &loaded.replay_touched, loaded.seq)?;
            println!(
                "{scene}: snapshot at sequence {}, {} log entries folded in",
                loaded.seq, loaded.replayed
            );
            Ok(())
        }
        Cmd::Import(args) => import_cli::run(args),
        Cmd::Generate(kind) => generate_cli::run(kind),
        Cmd::Cluster {
            command: ClusterCmd::Status { nats, json },
        } => {
            let status = on_cluster(&nats, |cluster| async move {
                brickcast_server::cluster::status::status(&cluster).await
            })?;
            if json {
                println!("{}", serde_json::to_string(&status)?);
            } else {
                print!("{}", status.render());
            }
            Ok(())
        }
        Cmd::Cluster {
            command: ClusterCmd::Repair { nats, scene, json },
        } => {
            let repaired = on_cluster(&nats, |cluster| async move {
                brickcast_server::cluster::repair::repair(&cluster, &scene).await
            })?;
            if json {
                println!("{}", serde_json::to_string(&repaired)?);
            } else {
                print!("{}", repaired.render());
            }
            Ok(())
        }
        Cmd::Export {
            scene,
            out,
            data,
            json,
        } => import_cli::export(&scene, &out, &data, json),
    }
}

/// Connects to a cluster's NATS and runs `f` on it (`cluster` commands).
fn on_cluster<T, F>(
    nats: &str,
    f: impl FnOnce(brickcast_server::cluster::Cluster) -> F,
) -> anyhow::Result<T>
where
    F: std::future::Future<Output = Result<T, brickcast_server::cluster::ClusterError>>,
{
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let out = runtime.block_on(async {
        let cluster = brickcast_server::cluster::Cluster::connect(nats, 1).await?;
        f(cluster).await
    });
    runtime.shutdown_timeout(Duration::from_secs(2));
    Ok(out?)
}

/// Opens an existing store for the offline commands (`scenes`, `stats`, `snapshot`), explaining
/// the usual failure (a running server holds it); a folder without a store is an error, not a
/// new empty store.
fn open_store(data: &std::path::Path) -> anyhow::Result<Store> {
    if !data.join("brickcast.redb").is_file() {
        anyhow::bail!(
            "no store in {}: `serve`, `import` or `generate` create one (or give --data)",
            data.display()
        );
    }
    Store::open(data).map_err(|e| {
        if e.is_locked() {
            anyhow::anyhow!(
                "{e}: a running server holds the store: ask it instead (`brickcast-server admin list`, `admin backup`, ...: see `admin --help`), or stop it first"
            )
        } else {
            e.into()
        }
    })
}

/// The per-component memory table of `stats` and `import`.
fn print_memory(m: &brickcast_protocol::map::MemoryStats) {
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    println!("  solid voxels     {:>14}", m.solid_voxels);
    println!("  bricks           {:>14}", m.bricks);
    println!("  regions          {:>10.2} MiB", mib(m.region_bytes));
    println!(
        "  cell blocks      {:>10.2} MiB ({} blocks)",
        mib(m.cell_bytes),
        m.cell_blocks
    );
    println!(
        "  masks            {:>10.2} MiB ({:.2} bits per voxel)",
        mib(m.mask_bytes),
        m.mask_bits_per_voxel
    );
    println!("  colour bases     {:>10.2} MiB", mib(m.colour_base_bytes));
    println!(
        "  colours          {:>10.2} MiB ({:.2} MiB live; {:.2} bits per voxel)",
        mib(m.colour_bytes),
        mib(m.colour_used_bytes),
        m.colour_bits_per_voxel
    );
    println!("  total            {:>10.2} MiB", mib(m.total_bytes));
    println!(
        "  paper's formula  {:>10.2} MiB",
        mib(m.paper_formula_bytes)
    );
    println!("  bytes per voxel  {:>14.2}", m.bytes_per_solid_voxel);
}

/// The colours as the store codes them (`protocol::palette`), beside the GPU layout's RGB565.
fn print_coded(c: &brickcast_protocol::palette::Mix) {
    println!(
        "  colours coded    {:>10.2} MiB ({:.2} bits per voxel, without chunk slack)",
        c.bytes as f64 / (1 << 20) as f64,
        c.bits_per_voxel
    );
    println!(
        "    bricks of one colour {}, palettes of 1/2/4/8 bits {}/{}/{}/{}, raw {}, \
         blocks of 2/3-bit weights {}/{}",
        c.one,
        c.palette[0],
        c.palette[1],
        c.palette[2],
        c.palette[3],
        c.raw,
        c.blocks[0],
        c.blocks[1]
    );
    if let Some(h) = c.entropy_bits_per_voxel {
        println!(
            "    entropy of each brick's colours {h:.2} bits per voxel (no palette code goes below it)"
        );
    }
    if let Some(psnr) = c.psnr_db {
        println!(
            "    colour error: PSNR {psnr:.2} dB over every solid voxel, worst {} of 255",
            c.worst_error
        );
    }
}

/// The scene laid out as a viewer with colour quality `colours` holds it on its GPU: every
/// brick written once, as a sync writes it.
fn viewer_copy(
    map: &brickcast_protocol::BrickMap,
    colours: brickcast_protocol::blocks::Quality,
) -> anyhow::Result<brickcast_protocol::BrickMap> {
    let mut copy = brickcast_protocol::BrickMap::new(map.size())?;
    copy.set_colour_bound(colours.bound());
    copy.write_bricks(
        map.bricks()
            .map(|(b, _)| (b.cell, Some((b.mask, b.colours)))),
    )?;
    copy.rebuild_clearance();
    Ok(copy)
}

/// `serve`'s options: where, who may edit, and the limits that keep one client from costing the
/// server more than its share (README, "Running in public").
#[derive(clap::Args)]
struct ServeArgs {
    /// Address to listen on, HOST:PORT (a name such as localhost:7878 is looked up).
    #[arg(long, default_value = "127.0.0.1:7878", value_parser = listen_addr)]
    listen: SocketAddr,
    /// Folder holding the store (created if missing).
    #[arg(long, default_value = "./brickcast-data")]
    data: PathBuf,
    /// File of `TOKEN ROLE` lines (role: editor|viewer). Without it everyone may edit.
    #[arg(long)]
    auth: Option<PathBuf>,
    /// Snapshot a scene whose log has entries at least this often (seconds), besides the
    /// snapshots taken when replaying the log would take about a second.
    #[arg(long, default_value_t = 60.0, value_parser = positive_seconds)]
    snapshot_every: f64,
    /// Websocket connections open at once, in all.
    #[arg(long, default_value_t = 4096)]
    max_connections: usize,
    /// Websocket connections open at once from one IP address.
    #[arg(long, default_value_t = 64)]
    max_connections_per_ip: usize,
    /// User ids clients of one address may choose whose undo history outlives their
    /// connection (without --auth, ids come from clients); further ids from that address get
    /// a history that goes when they leave. IPv6 counts by /64.
    #[arg(long, default_value_t = brickcast_server::ids::PER_ADDRESS)]
    ids_per_address: usize,
    /// Cut off a client that takes no data for this many seconds while the server has data for
    /// it.
    #[arg(long, default_value_t = 30.0, value_parser = positive_seconds)]
    stall_timeout: f64,
    /// Most edit work one edit message may ask for, in voxels visited (a sphere costs its
    /// bounding box); a larger message is refused whole.
    #[arg(long, default_value_t = 1 << 25)]
    max_work_per_edit: u64,
    /// Edit work per second one connection may ask for, in voxels visited.
    #[arg(long, default_value_t = 1 << 26)]
    max_work_per_second: u64,
    /// Bytes of undo history a scene keeps over all its users; beyond it the oldest steps of
    /// the users idle longest go first (guests before users the auth file names).
    #[arg(long, default_value_t = 256 << 20)]
    max_history_bytes: u64,
    /// Sequences of each scene's past kept for its timeline and for views of it
    /// (`/scenes/NAME~SEQ`, restores), at least (older ones go at snapshots); 0 keeps none.
    #[arg(long, default_value_t = brickcast_server::store::DEFAULT_KEEP)]
    keep_history: u64,
    /// Bytes of each scene's past kept at most: beyond them its oldest goes first, whatever
    /// --keep-history says.
    #[arg(long, default_value_t = brickcast_server::store::DEFAULT_KEEP_BYTES)]
    keep_history_bytes: u64,
    /// Bytes queued to all clients together before slow clients stop getting deltas (they
    /// resync once they catch up) and syncs pause.
    #[arg(long, default_value_t = 1 << 30)]
    max_queued_bytes: usize,
    /// Join a cluster through this NATS server (JetStream on) instead of serving the redb
    /// store in --data: scenes, logs and snapshots live in NATS (README, "Running a cluster").
    #[arg(long, value_name = "URL")]
    nats: Option<String>,
    /// This node's name in the cluster (unique; default: host name and port).
    #[arg(long, requires = "nats")]
    node: Option<String>,
    /// Copies JetStream keeps of each scene log, snapshot store and bucket this node creates:
    /// 3 on a JetStream cluster of three servers (README, "Running a cluster").
    #[arg(long, default_value_t = 1, requires = "nats", value_parser = clap::value_parser!(u8).range(1..=5))]
    replicas: u8,
    /// Seconds a scene nobody on this node uses stays open here (0: never close). A cluster
    /// node opens a scene when someone asks for it and closes it after this; a lease it held
    /// goes at once to a node with people on the scene.
    #[arg(long, default_value_t = brickcast_server::CLOSE_IDLE.as_secs_f64(), requires = "nats", value_parser = zero_or_seconds)]
    close_idle: f64,
}

/// A clap parser for zero or a positive, finite number of seconds.
fn zero_or_seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(0.0) => Ok(0.0),
        _ => positive_seconds(text),
    }
}

/// A clap parser for a positive, finite number of seconds.
fn positive_seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && s > 0.0 && s <= 1e9 => Ok(s),
        _ => Err(format!("{text:?} is not a positive number of seconds")),
    }
}

/// `--listen`: an address, or a host name and port (`localhost:7878`), looked up; the first
/// address it names is the one bound.
fn listen_addr(text: &str) -> Result<SocketAddr, String> {
    use std::net::ToSocketAddrs;
    let why = |e: &dyn std::fmt::Display| {
        format!(
            "{text:?} is not an address to listen on (HOST:PORT, e.g. 127.0.0.1:7878 or localhost:7878): {e}"
        )
    };
    text.to_socket_addrs()
        .map_err(|e| why(&e))?
        .next()
        .ok_or_else(|| why(&"it names no address"))
}

fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting tokio")?;
    let served = runtime.block_on(async move {
        let mut config = ServerConfig::new(args.listen, args.data);
        config.owner.snapshot_every = Duration::from_secs_f64(args.snapshot_every);
        config.owner.budget.max_work_per_edit = args.max_work_per_edit;
        config.owner.budget.max_work_per_second = args.max_work_per_second;
        config.owner.max_queued_total = args.max_queued_bytes;
        config.owner.max_history_bytes = args.max_history_bytes;
        config.keep_history = args.keep_history;
        config.keep_history_bytes = args.keep_history_bytes;
        config.connections.max_total = args.max_connections;
        config.connections.max_per_ip = args.max_connections_per_ip;
        config.ids_per_address = args.ids_per_address;
        config.stall_timeout = Duration::from_secs_f64(args.stall_timeout);
        config.cluster = args.nats.map(|url| brickcast_server::ClusterConfig {
            url,
            node: args.node,
            replicas: usize::from(args.replicas),
            close_idle: Duration::from_secs_f64(args.close_idle),
        });
        if let Some(path) = args.auth {
            config.auth = Auth::from_file(&path)?;
        }
        let server = Server::bind(config).await?;
        let addr = server.local_addr()?;
        tracing::info!("listening on http://{addr}");
        match brickcast_server::web::unbuilt_reason() {
            None => tracing::info!("browser viewer: open http://{addr}/ in a WebGPU browser"),
            Some(why) => tracing::warn!("no browser viewer in this build: {}", why.trim()),
        }
        server.run(shutdown_signal()).await
    });
    // Whatever a task still waits on (a NATS connection that is gone), the process ends.
    runtime.shutdown_timeout(Duration::from_secs(5));
    served
}

/// Ctrl-C or SIGTERM.
async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for Ctrl-C");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = term => {}
    }
    tracing::info!("shutdown requested");
}

/// A scene's levels of detail as `stats --lod` reports them.
#[derive(serde::Serialize)]
struct LodStats {
    seconds: f64,
    levels: Vec<brickcast_protocol::map::MemoryStats>,
}

fn lod_stats(map: &brickcast_protocol::BrickMap) -> anyhow::Result<LodStats> {
    let started = std::time::Instant::now();
    let pyramid = brickcast_protocol::lod::Pyramid::build(map)?;
    let seconds = started.elapsed().as_secs_f64();
    let levels = (1..=pyramid.level_count())
        .filter_map(|k| pyramid.level(k).map(|l| l.memory()))
        .collect();
    Ok(LodStats { seconds, levels })
}

fn print_lod(lod: &LodStats) {
    let total: u64 = lod.levels.iter().map(|l| l.total_bytes).sum();
    println!(
        "levels of detail: {} above level 0, {:.2} MiB in all, built in {:.2} s",
        lod.levels.len(),
        total as f64 / (1 << 20) as f64,
        lod.seconds
    );
    for (k, level) in lod.levels.iter().enumerate() {
        println!(
            "  level {:>2} {:>5}x{}x{} {:>10} bricks {:>10.2} MiB",
            k + 1,
            level.size[0],
            level.size[1],
            level.size[2],
            level.bricks,
            level.total_bytes as f64 / (1 << 20) as f64
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offline_commands_do_not_create_a_store() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nothing-here");
        let e = open_store(&missing)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("no store in"), "{e}");
        assert!(!missing.exists(), "the folder was created");
    }

    #[test]
    fn listen_takes_addresses_and_host_names() {
        assert_eq!(
            listen_addr("127.0.0.1:7878"),
            Ok("127.0.0.1:7878".parse().unwrap())
        );
        let local = listen_addr("localhost:7878").expect("localhost resolves");
        assert!(local.ip().is_loopback() && local.port() == 7878, "{local}");
        for bad in ["localhost", "127.0.0.1:99999", ""] {
            let e = listen_addr(bad).unwrap_err();
            assert!(e.contains("HOST:PORT"), "{bad}: {e}");
        }
    }
}
