//! The brickcast scene server as a library: the binary is a thin CLI over [`Server`].
//!
//! * [`store`]: redb snapshot + edit log per scene, recovery.
//! * [`scene`]: one owner thread per scene: ordering, group commit, acks, deltas, syncs.
//! * [`session`]: one task pair per websocket: handshake, reader, writer.
//! * [`auth`], [`metrics`]: tokens → roles; Prometheus counters.
//! * [`import`]: OBJ/MTL meshes voxelized through an octree, MagicaVoxel `.vox` in and out.
//! * [`incoming`]: the spool through which a running server picks up newly imported scenes.
//!
//! Data flow of one edit: session reader → owner channel → `apply_op` on the map → durable log
//! commit → ack to the editor → one encoded delta → every session's outbox → websocket.

pub mod admin;
pub mod auth;
mod bucket;
pub mod cluster;
pub mod conns;
pub mod envelope;
pub mod exposition;
pub mod fair;
pub mod generate;
pub mod http;
pub mod identity;
pub mod ids;
pub mod import;
pub mod incoming;
pub mod metrics;
pub mod past_views;
pub mod presence;
pub mod record;
pub mod scene;
pub mod served;
pub mod session;
#[cfg(test)]
mod sim;
pub mod store;
mod store_rows;
pub mod web;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use axum::Router;
use axum::extract::{ConnectInfo, Path, State, WebSocketUpgrade};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio_util::sync::CancellationToken;
use tokio_util::task::{TaskTracker, task_tracker::TaskTrackerToken};

use crate::auth::Auth;
use crate::conns::{ConnectionLimits, Connections};
use crate::metrics::Metrics;
use crate::scene::{OwnerConfig, SceneHandle};
use crate::store::Store;

/// Size of the built-in demo scene created on an empty store.
pub const DEMO_SIZE: [u32; 3] = [512, 512, 512];

/// How often a running server looks in its spool for newly imported scenes.
pub const SPOOL_POLL: Duration = Duration::from_millis(300);
/// How often deleted scenes whose time is up are dropped from the store (`admin`).
const PURGE_EVERY: Duration = Duration::from_secs(60);
/// How often a cluster node looks for scenes added to the cluster.
pub const CLUSTER_POLL: Duration = Duration::from_secs(1);

/// Waits `period`; false once shutdown was requested (at once, not after the period). The
/// server's pollers (spool, cluster scene list) loop on it.
async fn wait_or_shutdown(shutdown: &CancellationToken, period: Duration) -> bool {
    tokio::select! {
        _ = tokio::time::sleep(period) => {}
        () = shutdown.cancelled() => {}
    }
    !shutdown.is_cancelled()
}

/// A node's name when `--node` is not given: the host's name and the listening port.
fn default_node_name(listen: SocketAddr) -> String {
    let host = std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|h| h.trim().to_string())
        .filter(|h| store::valid_scene_name(h))
        .unwrap_or_else(|| "node".to_string());
    format!("{host}-{}", listen.port())
}

/// Everything `serve` needs.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    pub listen: SocketAddr,
    pub data: PathBuf,
    pub auth: Auth,
    pub owner: OwnerConfig,
    /// Size of the demo scene created when the store holds no scene.
    pub demo_size: [u32; 3],
    /// Websocket connections taken, in all and per address.
    pub connections: ConnectionLimits,
    /// Lasting user ids clients of one address may choose (`ids`, `serve --ids-per-address`).
    pub ids_per_address: usize,
    /// A client that takes no data for this long while the server has data for it is cut off.
    pub stall_timeout: Duration,
    pub http: http::HttpConfig,
    /// Join a cluster instead of serving the redb store (`serve --nats`).
    pub cluster: Option<ClusterConfig>,
    /// Sequences of each scene's past the redb store keeps for its timeline and views of it
    /// (`serve --keep-history`, `store::past`; 0: none).
    pub keep_history: u64,
    /// Bytes of each scene's past kept at most (`serve --keep-history-bytes`).
    pub keep_history_bytes: u64,
}

/// `serve --nats URL [--node NAME]`.
#[derive(Clone, Debug)]
pub struct ClusterConfig {
    pub url: String,
    /// This node's name (unique in the cluster); default: host name and port.
    pub node: Option<String>,
    /// Copies JetStream keeps of the streams and buckets this node creates.
    pub replicas: usize,
    /// A scene nobody on this node used for this long is closed here (zero: never).
    pub close_idle: Duration,
}

/// Default of [`ClusterConfig::close_idle`].
pub const CLOSE_IDLE: Duration = Duration::from_secs(60);

impl ServerConfig {
    pub fn new(listen: SocketAddr, data: PathBuf) -> ServerConfig {
        ServerConfig {
            listen,
            data,
            auth: Auth::open(),
            owner: OwnerConfig::default(),
            demo_size: DEMO_SIZE,
            connections: ConnectionLimits::default(),
            ids_per_address: ids::PER_ADDRESS,
            stall_timeout: Duration::from_secs(30),
            http: http::HttpConfig::default(),
            cluster: None,
            keep_history: store::DEFAULT_KEEP,
            keep_history_bytes: store::DEFAULT_KEEP_BYTES,
        }
    }
}

/// A cluster node's connection and name.
struct Node {
    cluster: cluster::Cluster,
    name: String,
    close_idle: Duration,
    /// This process's hold on its name (given back at shutdown; lost if another took it).
    registration: cluster::NodeName,
}

/// State shared by the HTTP handlers and sessions.
pub struct App {
    /// Served scenes: every scene of the store (one node), or those someone here uses
    /// (cluster, see `served`).
    scenes: served::Served,
    /// Owner threads, joined at shutdown (scenes added while running included).
    owners: Mutex<Vec<std::thread::JoinHandle<()>>>,
    /// The redb store (one node), or the cluster this node belongs to.
    store: Option<Arc<Store>>,
    node: Option<Node>,
    owner_config: OwnerConfig,
    data: PathBuf,
    pub metrics: Arc<Metrics>,
    pub auth: Auth,
    /// The server's one shutdown signal: cancelled once, when the server starts to stop; the
    /// scenes' own close signals follow it (`served::close_signal`).
    pub shutdown: CancellationToken,
    next_id: AtomicU64,
    /// Websocket sessions still running; shutdown waits for them to flush and close.
    sessions: TaskTracker,
    /// Bytes queued to every session together (see `scene::Outbox`).
    pub queued_total: Arc<std::sync::atomic::AtomicUsize>,
    pub stall_timeout: Duration,
    connections: Arc<Connections>,
    connection_limits: ConnectionLimits,
    /// Scene thumbnails for the scene list (see `web`).
    pub thumbnails: web::Thumbnails,
    /// Edit budgets shared by every connection of a user or of an address (see `fair`).
    pub shares: fair::Shares,
    /// The ids each address's clients chose (see `ids`).
    pub ids: ids::Ids,
    /// Users an administrator disconnected, refused for a while (see `admin`).
    pub bans: admin::Bans,
    /// Views of scenes' past open now (`past_views`).
    pub past: past_views::PastViews,
}

impl App {
    pub fn next_session_id(&self) -> u64 {
        self.next_id.fetch_add(1, Relaxed)
    }

    /// Held by a session while it runs, so shutdown can wait for sockets to flush and close.
    pub fn track_session(&self) -> TaskTrackerToken {
        self.sessions.token()
    }

    /// A scene served now (a cluster node may also serve it on demand: [`App::open_scene`]).
    pub fn scene(&self, name: &str) -> Option<SceneHandle> {
        self.scenes.get(name)
    }

    /// Every scene served now, by name.
    pub fn scene_list(&self) -> Vec<(String, SceneHandle)> {
        self.scenes.list()
    }

    /// Every scene served now or (cluster) known to the cluster, by name.
    pub fn catalog(&self) -> Vec<served::Listed> {
        self.scenes.catalog()
    }

    /// Whether there is such a scene, served or (cluster) in the cluster's scene list.
    pub async fn has_scene(&self, name: &str) -> bool {
        if self.scenes.knows(name) {
            return true;
        }
        match &self.node {
            Some(node) => matches!(
                cluster::catalog::scene_entry(&node.cluster, name).await,
                Ok(Some(_))
            ),
            None => false,
        }
    }

    /// Starts serving a recovered scene: spawns its owner and makes it reachable.
    fn add_scene(&self, name: String, loaded: store::Loaded) -> anyhow::Result<()> {
        let store = self
            .store
            .clone()
            .context("a scene from the redb store on a cluster node")?;
        let (handle, thread) = scene::spawn(
            name.clone(),
            loaded,
            store,
            self.metrics.clone(),
            self.owner_config.clone(),
            tokio::runtime::Handle::current(),
        )?;
        self.serve_scene(name, handle, thread, None, None);
        Ok(())
    }

    fn serve_scene(
        &self,
        name: String,
        handle: SceneHandle,
        thread: std::thread::JoinHandle<()>,
        link: Option<cluster::SceneLink<cluster::Cluster>>,
        close: Option<Arc<cluster::signal::Sender<bool>>>,
    ) {
        self.scenes.insert(name, handle, link, close);
        self.owners
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(thread);
    }

    /// Cluster: loads a scene from the cluster and serves it (following its log; the lease
    /// decides whether this node orders its edits) until it closes (see `served`).
    async fn add_cluster_scene(&self, name: String) -> anyhow::Result<()> {
        let node = self.node.as_ref().context("not a cluster node")?;
        let entry = cluster::catalog::scene_entry(&node.cluster, &name)
            .await?
            .with_context(|| format!("the cluster has no scene {name}"))?;
        let log = entry.log_key(&name).to_string();
        let loaded = cluster::log::load(&node.cluster, &log)
            .await
            .with_context(|| format!("loading scene {name} from the cluster"))?;
        tracing::info!(scene = %name, seq = loaded.loaded.seq, replayed = loaded.loaded.replayed, pos = loaded.pos, "scene loaded from the cluster");
        let (close, closed) = served::close_signal(&self.shutdown);
        let (handle, thread, link) = cluster::start_scene(
            &node.cluster,
            &node.name,
            name.clone(),
            &log,
            loaded,
            self.metrics.clone(),
            self.owner_config.clone(),
            closed,
        )
        .await?;
        self.serve_scene(name, handle, thread, Some(link), Some(close));
        Ok(())
    }

    /// This node's name in a cluster.
    pub fn node_name(&self) -> Option<&str> {
        self.node.as_ref().map(|n| n.name.as_str())
    }

    /// Takes one spooled scene: store it, serve it, remove the file. On failure the file stays
    /// with a `.error` beside it saying why.
    async fn adopt_spooled(self: &Arc<Self>, file: PathBuf) {
        let app = self.clone();
        let file2 = file.clone();
        let outcome = tokio::task::spawn_blocking(move || -> anyhow::Result<(String, store::Loaded)> {
            let (name, map) = incoming::read(&file2)?;
            if app.scene(&name).is_some() {
                anyhow::bail!("scene {name} already exists on this server: import under another name, or stop the server and import with --replace");
            }
            let store = app.store.clone().context("no redb store on a cluster node")?;
            store.create_scene(&name, &map)?;
            let loaded = store.load_scene(&name)?;
            Ok((name, loaded))
        })
        .await;
        let outcome = match outcome {
            Ok(Ok((name, loaded))) => self.add_scene(name.clone(), loaded).map(|()| name),
            Ok(Err(e)) => Err(e),
            Err(e) => Err(anyhow::anyhow!("import task failed: {e}")),
        };
        match outcome {
            Ok(name) => {
                tracing::info!(scene = %name, "serving newly imported scene");
                if let Err(e) = std::fs::remove_file(&file) {
                    tracing::warn!(file = %file.display(), error = %e, "cannot remove the spool file of an adopted scene");
                }
            }
            Err(e) => {
                tracing::warn!(file = %file.display(), error = %format!("{e:#}"), "refused a spooled scene");
                if let Err(e) = incoming::write_error(&file, &format!("{e:#}\n")) {
                    tracing::error!(file = %file.display(), error = %e, "cannot write the spool error file");
                }
            }
        }
    }

    /// Polls the spool until shutdown; drops deleted scenes whose time is up (`admin`) at
    /// start and every [`PURGE_EVERY`].
    async fn watch_spool(self: Arc<Self>) {
        let shutdown = self.shutdown.clone();
        let mut purged: Option<std::time::Instant> = None;
        while wait_or_shutdown(&shutdown, SPOOL_POLL).await {
            if let Some(store) = &self.store
                && purged.is_none_or(|at| at.elapsed() >= PURGE_EVERY)
            {
                purged = Some(std::time::Instant::now());
                let store = store.clone();
                let dropped = tokio::task::spawn_blocking(move || {
                    store.purge_deleted(store::Store::unix_seconds())
                })
                .await;
                match dropped {
                    Ok(Ok(dropped)) => {
                        for d in dropped {
                            tracing::info!(scene = %d.name, key = %d.key, "dropped a deleted scene whose time was up");
                        }
                    }
                    Ok(Err(e)) => tracing::warn!(error = %e, "cannot drop deleted scenes"),
                    Err(e) => tracing::warn!(error = %e, "dropping deleted scenes failed"),
                }
            }
            let data = self.data.clone();
            let files = tokio::task::spawn_blocking(move || incoming::pending(&data))
                .await
                .unwrap_or_default();
            for file in files {
                self.adopt_spooled(file).await;
            }
        }
    }
}

/// A bound, ready server. `run` serves until the shutdown future resolves.
pub struct Server {
    listener: tokio::net::TcpListener,
    app: Arc<App>,
    shutdown: CancellationToken,
    http: http::HttpConfig,
}

impl Server {
    /// Binds the listener, opens the store (creating the demo scene if it holds none), recovers
    /// every scene and starts their owners. With `config.cluster`, joins the cluster instead:
    /// scenes open when someone asks for them (see `served`).
    pub async fn bind(config: ServerConfig) -> anyhow::Result<Server> {
        if config.cluster.is_some() {
            return Server::bind_cluster(config).await;
        }
        // The port first: a port in use must fail before anything is written to the store
        // (an empty folder would otherwise get a demo scene nobody asked for).
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .with_context(|| {
                format!(
                    "cannot listen on {} (is another server running there? choose another address with --listen)",
                    config.listen
                )
            })?;
        let store = Arc::new(Store::open(&config.data)?);
        store.set_keep_history(config.keep_history);
        store.set_keep_history_bytes(config.keep_history_bytes);
        let demo_size = config.demo_size;
        let store2 = store.clone();
        let loaded = tokio::task::spawn_blocking(move || -> anyhow::Result<Vec<(String, store::Loaded)>> {
            // Not when scenes were deleted and are still kept: the operator emptied it.
            if store2.scenes()?.is_empty() && store2.deleted()?.is_empty() {
                let map = brickcast_protocol::demo::demo_scene(demo_size)?;
                store2.create_scene("demo", &map)?;
                tracing::info!(bricks = map.brick_count(), voxels = map.solid_voxels(), "created the built-in demo scene");
            }
            let mut loaded = Vec::new();
            for (name, _) in store2.scenes()? {
                let scene = store2.load_scene(&name).with_context(|| format!("recovering scene {name}"))?;
                tracing::info!(scene = %name, seq = scene.seq, replayed = scene.replayed, bricks = scene.map.brick_count(), "scene recovered");
                loaded.push((name, scene));
            }
            Ok(loaded)
        })
        .await??;
        let server = Server::new(listener, config, Some(store), None);
        for (name, scene) in loaded {
            server.app.add_scene(name, scene)?;
        }
        Ok(server)
    }

    /// The server around a bound listener: the shared state sessions and handlers see.
    fn new(
        listener: tokio::net::TcpListener,
        config: ServerConfig,
        store: Option<Arc<Store>>,
        node: Option<Node>,
    ) -> Server {
        let shutdown = CancellationToken::new();
        let app = Arc::new(App {
            scenes: served::Served::default(),
            owners: Mutex::new(Vec::new()),
            store,
            node,
            owner_config: config.owner,
            data: config.data,
            metrics: Arc::new(Metrics::default()),
            auth: config.auth,
            shutdown: shutdown.clone(),
            next_id: AtomicU64::new(1),
            sessions: TaskTracker::new(),
            queued_total: Arc::default(),
            stall_timeout: config.stall_timeout,
            connections: Arc::default(),
            connection_limits: config.connections,
            thumbnails: web::Thumbnails::default(),
            shares: fair::Shares::default(),
            ids: ids::Ids::new(config.ids_per_address),
            bans: admin::Bans::default(),
            past: past_views::PastViews::default(),
        });
        Server {
            listener,
            app,
            shutdown,
            http: config.http,
        }
    }

    async fn bind_cluster(config: ServerConfig) -> anyhow::Result<Server> {
        let cc = config.cluster.clone().context("no cluster configured")?;
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("listening on {}", config.listen))?;
        let listen = listener.local_addr()?;
        let cluster = cluster::Cluster::connect(&cc.url, cc.replicas).await?;
        let name = cc.node.unwrap_or_else(|| default_node_name(listen));
        let registration = cluster::name::register(
            &cluster,
            &name,
            cluster::name::process_instance(),
            &listen.to_string(),
        )
        .await?;
        tracing::info!(node = %name, nats = %cluster.url, "joined the cluster");
        if cluster::catalog::scene_names(&cluster).await?.is_empty() {
            let demo_size = config.demo_size;
            let map = tokio::task::spawn_blocking(move || {
                brickcast_protocol::demo::demo_scene(demo_size)
            })
            .await??;
            match cluster::catalog::create_scene(&cluster, "demo", &map, false).await {
                Ok(()) => tracing::info!(
                    bricks = map.brick_count(),
                    "created the built-in demo scene in the cluster"
                ),
                // Another node created it first.
                Err(cluster::ClusterError::SceneExists(_)) => {}
                Err(e) => return Err(e.into()),
            }
        }
        let node = Node {
            cluster: cluster.clone(),
            name,
            close_idle: cc.close_idle,
            registration,
        };
        // Scenes open when someone asks for them (see `served`).
        let server = Server::new(listener, config, None, Some(node));
        server.app.refresh_known(&cluster).await?;
        Ok(server)
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// Serves until `signal` resolves, then: stop accepting, stop reading edits, let every scene
    /// owner apply and commit what it has queued and write a snapshot, and let sessions flush and
    /// close their sockets with a close frame.
    pub async fn run(
        self,
        signal: impl Future<Output = ()> + Send + 'static,
    ) -> anyhow::Result<()> {
        let Server {
            listener,
            app,
            shutdown,
            http: http_config,
        } = self;
        let spool = if let Some(node) = &app.node {
            // `cluster status` asks every node where its scenes stand.
            let scenes = app.clone();
            tokio::spawn(cluster::status::answer(
                node.cluster.clone(),
                node.name.clone(),
                Arc::new(move || scenes.scene_list()),
                app.shutdown.clone(),
            ));
            // An administrator's kick asked of any node reaches this one's connections too.
            let kicks = app.clone();
            tokio::spawn(cluster::kick::answer(
                node.cluster.clone(),
                node.name.clone(),
                Arc::new(move |order| admin::handle_kick_order(&kicks, order)),
                app.shutdown.clone(),
            ));
            tokio::spawn(app.clone().tend_cluster_scenes(node.close_idle))
        } else {
            tokio::spawn(app.clone().watch_spool())
        };
        let router = router(app.clone());
        let stop = shutdown.clone();
        // A cluster node whose name another process took stops as if told to.
        let mut lost = app.node.as_ref().map(|n| n.registration.lost.clone());
        // TCP_NODELAY, the header timeout and ConnectInfo: see `http`. Waits out requests in
        // flight; upgraded websockets end through `app.shutdown`.
        http::serve(listener, router, http_config, async move {
            let name_lost = async {
                match &mut lost {
                    Some(lost) => {
                        let _ = lost.wait_for(|why| why.is_some()).await;
                    }
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                () = signal => {}
                () = name_lost => {}
            }
            stop.cancel();
        })
        .await;
        tracing::info!("shutting down: flushing scenes");
        // No scene may be added after the owners were told to stop: the spool and the
        // scene tender have ended, and an open still loading finishes before this lock is
        // had (any later one sees the shutdown).
        let _ = spool.await;
        let _opening = app.scenes.opening.lock().await;
        // Every scene takes the one closing path (`served::close`): in a cluster a lease is
        // kept until its owner has committed and snapshotted, then handed over at once.
        let still_closing = app.scenes.still_closing.clone();
        futures_util::future::join_all(app.scenes.take_all().into_iter().map(|(name, entry)| {
            let still_closing = still_closing.clone();
            async move {
                served::close(&name, entry, served::Closing::Shutdown, &still_closing).await;
            }
        }))
        .await;
        app.past.close_all().await;
        let owners = std::mem::take(&mut *app.owners.lock().unwrap_or_else(|e| e.into_inner()));
        let crashed = tokio::task::spawn_blocking(move || {
            owners.into_iter().filter_map(|o| o.join().err()).count()
        })
        .await?;
        // Owners have dropped their outboxes: writers send what is left and close.
        app.sessions.close();
        let _ = tokio::time::timeout(Duration::from_secs(5), app.sessions.wait()).await;
        let mut name_lost = None;
        if let Some(node) = &app.node {
            name_lost = node.registration.lost.get();
            // Free the name for a restart (unless another process holds it now).
            node.registration.release().await;
            let _ = node.cluster.client.flush().await;
        }
        if crashed > 0 {
            anyhow::bail!(
                "{crashed} scene owner(s) crashed; their last acknowledged edits are in the log"
            );
        }
        if let Some(why) = name_lost {
            anyhow::bail!("{why}");
        }
        tracing::info!("shut down cleanly");
        Ok(())
    }
}

/// A scene path `NAME` or `NAME@K` (level K ≥ 1 of its levels of detail) split into the
/// scene's name and the level (0 for the scene itself); an error says what is wrong with `K`.
pub fn split_level(path: &str) -> Result<(&str, u32), String> {
    let Some((name, level)) = path.split_once('@') else {
        return Ok((path, 0));
    };
    match level.parse::<u32>() {
        Ok(k) if k >= 1 && level.bytes().all(|b| b.is_ascii_digit()) => Ok((name, k)),
        _ => Err(format!(
            "{path:?}: a level of detail is a whole number from 1 (NAME@1, NAME@2, ...)"
        )),
    }
}

/// The HTTP surface.
pub fn router(app: Arc<App>) -> Router {
    Router::new()
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/metrics", get(metrics_text))
        .route("/scenes", get(scene_list))
        .route("/scenes/{name}/ws", get(websocket))
        .route("/scenes/{name}/history", get(history))
        .merge(web::routes())
        .merge(admin::routes())
        .with_state(app)
}

/// `?limit=N` of `/scenes/NAME/history`.
#[derive(serde::Deserialize)]
struct HistoryQuery {
    limit: Option<usize>,
}

/// Most changes one timeline answer lists.
const MAX_TIMELINE: usize = 100_000;

/// `/scenes/NAME/history`: the scene's timeline (who changed what region when, from the log
/// the store keeps, `store::past`), the latest `limit` changes (1,000 unless asked), and the
/// sequences a view of its past (`/scenes/NAME~S`) can show.
async fn history(
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
    axum::extract::Query(query): axum::extract::Query<HistoryQuery>,
) -> Response {
    if app.store.is_none() {
        return (
            StatusCode::NOT_IMPLEMENTED,
            "this server keeps no history of its scenes (a cluster node): a single node does\n",
        )
            .into_response();
    }
    if app.scene(&name).is_none() {
        return (StatusCode::NOT_FOUND, format!("no scene named {name:?}\n")).into_response();
    }
    let limit = query.limit.unwrap_or(1000).clamp(1, MAX_TIMELINE);
    match app.past.timeline(&app, &name, limit).await {
        Ok((span, changes)) => axum::Json(serde_json::json!({
            "scene": name,
            "oldest": span.oldest,
            "newest": span.newest,
            "changes": changes,
        }))
        .into_response(),
        Err(e) if e.not_found() => (StatusCode::NOT_FOUND, format!("{e}\n")).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")).into_response(),
    }
}

async fn metrics_text(State(app): State<Arc<App>>) -> Response {
    use exposition::Value;
    let mut x = exposition::Exposition::default();
    app.metrics.expose(&mut x);
    x.one(
        "queued_bytes",
        "Bytes queued to all clients together (frames plus per-frame overhead).",
        Value::gauge(app.queued_total.load(Relaxed) as u64),
    );
    x.one(
        "open_connections",
        "Websocket connections admitted and not yet closed.",
        Value::gauge(app.connections.open() as u64),
    );
    let scenes = app.scene_list();
    x.one(
        "scenes_open",
        "Scenes this server serves now (a cluster node: those someone here used lately).",
        Value::gauge(scenes.len() as u64),
    );
    if let Some(rss) = metrics::resident_bytes() {
        x.one(
            "process_resident_bytes",
            "Resident memory of the server process.",
            Value::gauge(rss),
        );
    }
    if let Some(cpu) = metrics::cpu_seconds() {
        x.one(
            "process_cpu_seconds",
            "CPU time (user and system) of the server process.",
            Value::Seconds(cpu),
        );
    }
    // One family per scene figure, a series per scene.
    type Read = fn(&SceneHandle) -> u64;
    let per_scene: [(&str, &str, Read); 9] = [
        ("scene_seq", "The scene's last applied sequence.", |s| {
            s.info.seq.load(Relaxed)
        }),
        ("scene_bricks", "Bricks the scene holds.", |s| {
            s.info.bricks.load(Relaxed)
        }),
        ("scene_voxels", "Solid voxels the scene holds.", |s| {
            s.info.voxels.load(Relaxed)
        }),
        ("scene_clients", "Websocket sessions on the scene.", |s| {
            s.info.clients.load(Relaxed)
        }),
        (
            "scene_gpu_bytes",
            "Bytes the scene takes as laid out for the GPU.",
            |s| s.info.gpu_bytes.load(Relaxed),
        ),
        (
            "scene_history_users",
            "Users with undo history in the scene.",
            |s| s.info.history_users.load(Relaxed),
        ),
        (
            "scene_history_bytes",
            "Bytes of undo history the scene keeps.",
            |s| s.info.history_bytes.load(Relaxed),
        ),
        (
            "scene_present",
            "People present in the scene (all nodes).",
            |s| s.presence.len() as u64,
        ),
        (
            "scene_owned_here",
            "1 where this node orders the scene's edits, else 0.",
            |s| u64::from(s.info.leading.load(Relaxed)),
        ),
    ];
    for (name, help, read) in per_scene {
        x.labelled(
            name,
            help,
            "scene",
            scenes
                .iter()
                .map(|(scene, handle)| (scene.clone(), Value::gauge(read(handle)))),
        );
    }
    (
        [(header::CONTENT_TYPE, exposition::CONTENT_TYPE)],
        x.encode(),
    )
        .into_response()
}

async fn scene_list(State(app): State<Arc<App>>) -> Response {
    let list: Vec<_> = app
        .catalog()
        .into_iter()
        .map(|listed| match listed.handle {
            Some(s) => {
                let mut value = open_scene_json(&listed.name, &s);
                value["node"] = app.node_name().into();
                value["owned_here"] = s.info.leading.load(Relaxed).into();
                value
            }
            // Cluster: a scene nobody uses on this node (it opens when someone does).
            None => serde_json::json!({
                "name": listed.name,
                "size": listed.size,
                "open": false,
                "node": app.node_name(),
                "owned_here": false,
            }),
        })
        .collect();
    axum::Json(list).into_response()
}

/// What the scene lists (`/scenes`, `/admin/scenes`) say of a scene served here.
pub(crate) fn open_scene_json(name: &str, s: &SceneHandle) -> serde_json::Value {
    serde_json::json!({
        "name": name,
        "size": s.size,
        "open": true,
        "seq": s.info.seq.load(Relaxed),
        "bricks": s.info.bricks.load(Relaxed),
        "voxels": s.info.voxels.load(Relaxed),
        "clients": s.info.clients.load(Relaxed),
        "gpu_bytes": s.info.gpu_bytes.load(Relaxed),
    })
}

async fn websocket(
    Path(path_name): Path<String>,
    State(app): State<Arc<App>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    ws: Result<WebSocketUpgrade, axum::extract::ws::rejection::WebSocketUpgradeRejection>,
) -> Response {
    // `NAME~S` views the scene as it was at sequence S (`past_views`).
    if let Some(past) = past_views::split_past(&path_name) {
        return past_websocket(past, app, peer, ws).await;
    }
    // `NAME@K` views level K of the scene's levels of detail (`scene::levels`).
    let (name, level) = match split_level(&path_name) {
        Ok(split) => split,
        Err(why) => return (StatusCode::NOT_FOUND, format!("{why}\n")).into_response(),
    };
    let name = name.to_string();
    // Unknown scenes are a 404 whether or not the request is a websocket upgrade.
    if !app.has_scene(&name).await {
        return (StatusCode::NOT_FOUND, format!("no scene named {name:?}\n")).into_response();
    }
    let (ws, admitted) = match admit(&app, peer, ws) {
        Ok(admitted) => admitted,
        Err(refused) => return *refused,
    };
    // Only an admitted websocket opens a scene a cluster node does not serve yet.
    let (scene, using) = match app.open_scene(&name).await {
        Ok(Some(found)) => found,
        Ok(None) => {
            return (StatusCode::NOT_FOUND, format!("no scene named {name:?}\n")).into_response();
        }
        Err(e) => return (StatusCode::SERVICE_UNAVAILABLE, format!("{e}\n")).into_response(),
    };
    let levels = scene::levels::levels_of(scene.size);
    if level > levels {
        return (
            StatusCode::NOT_FOUND,
            format!(
                "scene {name:?} has levels of detail 1 to {levels} ({}x{}x{} voxels), not {level}\n",
                scene.size[0], scene.size[1], scene.size[2]
            ),
        )
            .into_response();
    }
    sized(ws, &scene).on_upgrade(move |socket| async move {
        let link = using.link.clone();
        session::run(socket, scene, link, app, peer.ip(), level, false).await;
        drop((admitted, using));
    })
}

/// A websocket request for a scene that exists: upgraded if it is one, the server is not
/// stopping and the connection limits take it (its place held while the session runs).
fn admit(
    app: &App,
    peer: SocketAddr,
    ws: Result<WebSocketUpgrade, axum::extract::ws::rejection::WebSocketUpgradeRejection>,
) -> Result<(WebSocketUpgrade, conns::Admitted), Box<Response>> {
    let ws = ws.map_err(|rejection| Box::new(rejection.into_response()))?;
    if app.shutdown.is_cancelled() {
        return Err(Box::new(
            (StatusCode::SERVICE_UNAVAILABLE, "shutting down\n").into_response(),
        ));
    }
    match app.connections.admit(peer.ip(), &app.connection_limits) {
        Ok(admitted) => Ok((ws, admitted)),
        Err(refusal) => {
            Metrics::add(&app.metrics.refused_connections, 1);
            tracing::debug!(%peer, %refusal, "refused a connection");
            Err(Box::new(
                (StatusCode::SERVICE_UNAVAILABLE, format!("{refusal}\n")).into_response(),
            ))
        }
    }
}

/// The upgrade sized for `scene`'s frames.
fn sized(ws: WebSocketUpgrade, scene: &SceneHandle) -> WebSocketUpgrade {
    // Accept frames a little over the limit so the session can answer them with a clean
    // FrameTooLarge error instead of a dropped connection.
    let max = scene.limits.max_frame_bytes as usize + (64 << 10);
    // Reads start in a 16 KiB buffer (a client's frames are small; a larger one grows it)
    // rather than tungstenite's 128 KiB: a crowd of idle connections holds less.
    ws.max_message_size(max)
        .max_frame_size(max)
        .read_buffer_size(16 << 10)
}

/// A websocket to a view of a scene's past (`NAME~S`, `past_views`): its sessions view.
async fn past_websocket(
    past: Result<(&str, u64), String>,
    app: Arc<App>,
    peer: SocketAddr,
    ws: Result<WebSocketUpgrade, axum::extract::ws::rejection::WebSocketUpgradeRejection>,
) -> Response {
    let (name, seq) = match past {
        Ok(split) => split,
        Err(why) => return (StatusCode::NOT_FOUND, format!("{why}\n")).into_response(),
    };
    if !app.has_scene(name).await {
        return (StatusCode::NOT_FOUND, format!("no scene named {name:?}\n")).into_response();
    }
    // A sequence the store does not keep is a 404 whether or not the request is a websocket.
    if let Err(e) = app.past.check(&app, name, seq).await {
        let status = if e.not_found() {
            StatusCode::NOT_FOUND
        } else {
            StatusCode::SERVICE_UNAVAILABLE
        };
        return (status, format!("{e}\n")).into_response();
    }
    let (ws, admitted) = match admit(&app, peer, ws) {
        Ok(admitted) => admitted,
        Err(refused) => return *refused,
    };
    let (scene, using) = match app.past.open(&app, name, seq, peer.ip()).await {
        Ok(found) => found,
        Err(e) if e.not_found() => {
            return (StatusCode::NOT_FOUND, format!("{e}\n")).into_response();
        }
        Err(e) => return (StatusCode::SERVICE_UNAVAILABLE, format!("{e}\n")).into_response(),
    };
    sized(ws, &scene).on_upgrade(move |socket| async move {
        session::run(socket, scene, None, app, peer.ip(), 0, true).await;
        drop((admitted, using));
    })
}

#[cfg(test)]
mod tests {
    use super::split_level;

    #[test]
    fn scene_paths_name_a_level_of_detail_after_an_at() {
        assert_eq!(split_level("demo"), Ok(("demo", 0)));
        assert_eq!(split_level("w16@3"), Ok(("w16", 3)));
        for bad in [
            "demo@",
            "demo@0",
            "demo@-1",
            "demo@+2",
            "demo@x",
            "demo@1@2",
            "demo@99999999999",
        ] {
            let err = split_level(bad).unwrap_err();
            assert!(err.contains("whole number from 1"), "{bad}: {err}");
        }
    }
}
