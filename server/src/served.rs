//! Which scenes this server serves now.
//!
//! **Why scenes open on demand in a cluster:** a node that loaded every scene of the cluster
//! would hold every map in memory and follow every log, so adding nodes would add fan-out but
//! never room for more scenes. A cluster node opens a scene when someone asks for it (a
//! websocket, or the scene list's picture of it), and closes it again once nobody on this
//! node used it for `--close-idle`: its lease (handed over at once), log follower and presence
//! relay end, then its owner thread. A free lease goes to a node with people on the scene
//! first (`cluster::CLAIM_GRACE`): the scene's owner so follows its users.
//!
//! One node (redb) serves every scene of its store from start to shutdown; the same map holds
//! them and nothing closes.
//!
//! **Limits:** one scene opens at a time per node (a second waits for the first; loading is
//! a snapshot read and a log replay, seconds for the largest scenes), and a scene being closed
//! is reopened only once its owner thread stopped, so one node never runs two owners of a
//! scene.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

use crate::cluster::catalog::{scene_entry, scene_names};
use crate::cluster::{Cluster, SceneEntry, SceneLink, signal};
use crate::metrics::Metrics;
use crate::scene::{Command, SceneHandle};
use crate::{App, CLUSTER_POLL, wait_or_shutdown};

/// How long a closing scene's tasks get to end (lease handed over, relay's last roster sent).
const CLOSE_PATIENCE: Duration = Duration::from_secs(30);
/// How often a cluster node drops deleted scenes whose time is up (`cluster::deleted`).
const PURGE_EVERY: Duration = Duration::from_secs(60);

/// The scenes being served, and (cluster) the ones that could be.
#[derive(Default)]
pub struct Served {
    open: RwLock<BTreeMap<String, Entry>>,
    /// Cluster: the cluster's scene list (name → size and log key), refreshed every
    /// [`CLUSTER_POLL`].
    known: RwLock<BTreeMap<String, SceneEntry>>,
    /// Held while a scene opens or closes (see the module's limits), and by shutdown.
    pub(crate) opening: tokio::sync::Mutex<()>,
    /// Scenes whose owner thread did not stop within [`CLOSE_PATIENCE`]: not reopened here
    /// until it has.
    pub(crate) still_closing: Arc<Mutex<BTreeMap<String, SceneHandle>>>,
}

#[derive(Clone)]
pub(crate) struct Entry {
    handle: SceneHandle,
    /// Cluster: how sessions reach whichever node orders the scene's edits.
    link: Option<SceneLink<Cluster>>,
    uses: Arc<Uses>,
    /// Cluster: ends the scene's lease, follower and relay tasks.
    close: Option<Arc<signal::Sender<bool>>>,
}

impl Entry {
    pub(crate) fn handle(&self) -> &SceneHandle {
        &self.handle
    }
}

/// Who uses a scene on this node now, and since when nobody does.
struct Uses {
    count: AtomicUsize,
    idle_since: Mutex<Instant>,
}

/// One use of a served scene (a session, a thumbnail being drawn); the scene stays open while
/// any is alive. In a cluster it carries how the user's edits reach the scene's owner.
pub struct SceneUse {
    uses: Arc<Uses>,
    pub link: Option<SceneLink<Cluster>>,
}

impl Drop for SceneUse {
    fn drop(&mut self) {
        // The count and the time are read together only under the map's write lock, and a
        // use is only taken under its read lock: a scene with a use is never closed.
        *self
            .uses
            .idle_since
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = Instant::now();
        self.uses.count.fetch_sub(1, Relaxed);
    }
}

/// Why a cluster scene's copy served here is not the scene of its name any more.
enum Stale {
    /// Its name is not in the scene list (deleted, or renamed).
    Unlisted,
    /// Its name names another log now (reset, or replaced by an upload).
    OtherLog,
}

/// A scene in the scene list: served here (`handle`), or only known to the cluster.
pub struct Listed {
    pub name: String,
    pub size: [u32; 3],
    pub handle: Option<SceneHandle>,
}

/// Why a scene could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("the server is shutting down")]
    ShuttingDown,
    #[error("scene {0} is still closing on this server; try again in a few seconds")]
    StillClosing(String),
    #[error("cannot open scene {scene}: {detail}")]
    Failed { scene: String, detail: String },
}

impl Served {
    fn read(&self) -> std::sync::RwLockReadGuard<'_, BTreeMap<String, Entry>> {
        // Inserts and removals are one call each: a poisoned map is still a good map.
        self.open.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, BTreeMap<String, Entry>> {
        self.open.write().unwrap_or_else(|e| e.into_inner())
    }

    /// A served scene.
    pub fn get(&self, name: &str) -> Option<SceneHandle> {
        self.read().get(name).map(|e| e.handle.clone())
    }

    /// A served scene, kept open while the returned use lives.
    pub fn take(&self, name: &str) -> Option<(SceneHandle, SceneUse)> {
        let open = self.read();
        let entry = open.get(name)?;
        entry.uses.count.fetch_add(1, Relaxed);
        let using = SceneUse {
            uses: entry.uses.clone(),
            link: entry.link.clone(),
        };
        Some((entry.handle.clone(), using))
    }

    /// Every served scene, by name.
    pub fn list(&self) -> Vec<(String, SceneHandle)> {
        self.read()
            .iter()
            .map(|(n, e)| (n.clone(), e.handle.clone()))
            .collect()
    }

    pub fn insert(
        &self,
        name: String,
        handle: SceneHandle,
        link: Option<SceneLink<Cluster>>,
        close: Option<Arc<signal::Sender<bool>>>,
    ) {
        let uses = Arc::new(Uses {
            count: AtomicUsize::new(0),
            idle_since: Mutex::new(Instant::now()),
        });
        self.write().insert(
            name,
            Entry {
                handle,
                link,
                uses,
                close,
            },
        );
    }

    /// Cluster: the scene list as the cluster has it now.
    pub fn set_known(&self, known: BTreeMap<String, SceneEntry>) {
        *self.known.write().unwrap_or_else(|e| e.into_inner()) = known;
    }

    /// Cluster: the scenes served here over a log that the cluster's list (as of the last
    /// look) no longer gives their name: deleted, renamed or reset by an administrator on
    /// some node. With each, its log key.
    fn served_but_unlisted(&self) -> Vec<(String, String)> {
        let known = self.known.read().unwrap_or_else(|e| e.into_inner());
        self.read()
            .iter()
            .filter_map(|(name, e)| {
                let log = e.link.as_ref()?.log.clone();
                let listed = known.get(name).is_some_and(|k| k.log_key(name) == log);
                (e.close.is_some() && !listed).then(|| (name.clone(), log))
            })
            .collect()
    }

    /// Cluster: the scenes served here from the cluster; a fresh look at the list reads their
    /// entries again (one may now name another log).
    fn served_names(&self) -> Vec<String> {
        self.read()
            .iter()
            .filter(|(_, e)| e.link.is_some())
            .map(|(name, _)| name.clone())
            .collect()
    }

    /// Cluster: the log key of the copy of `name` served here.
    fn log_of(&self, name: &str) -> Option<String> {
        self.read().get(name)?.link.as_ref().map(|l| l.log.clone())
    }

    /// Cluster: the listed scene whose log key is `log` (a renamed scene's new name).
    fn named_for_log(&self, log: &str) -> Option<String> {
        let known = self.known.read().unwrap_or_else(|e| e.into_inner());
        known
            .iter()
            .find(|(name, e)| e.log_key(name) == log)
            .map(|(name, _)| name.clone())
    }

    /// Whether a scene is served or known to the cluster (as of the last look at its list).
    pub fn knows(&self, name: &str) -> bool {
        self.read().contains_key(name)
            || self
                .known
                .read()
                .unwrap_or_else(|e| e.into_inner())
                .contains_key(name)
    }

    /// Served and known scenes together, sorted by name.
    pub fn catalog(&self) -> Vec<Listed> {
        let mut all: BTreeMap<String, Listed> = self
            .known
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .map(|(name, entry)| {
                let listed = Listed {
                    name: name.clone(),
                    size: entry.size,
                    handle: None,
                };
                (name.clone(), listed)
            })
            .collect();
        for (name, handle) in self.list() {
            all.insert(
                name.clone(),
                Listed {
                    name,
                    size: handle.size,
                    handle: Some(handle),
                },
            );
        }
        all.into_values().collect()
    }

    /// Takes one scene out of service, whatever kind it is (the admin API deletes or renames
    /// it). A session that has it keeps its handle until the owner closes it.
    pub(crate) fn remove(&self, name: &str) -> Option<Entry> {
        self.write().remove(name)
    }

    /// Takes every scene out of service (shutdown).
    pub(crate) fn take_all(&self) -> Vec<(String, Entry)> {
        std::mem::take(&mut *self.write()).into_iter().collect()
    }

    /// Takes out of service the cluster scenes whose owner thread stopped by itself.
    fn take_stopped(&self) -> Vec<(String, Entry)> {
        self.take_where(|e| e.handle.is_closed())
    }

    /// Takes out of service the scenes nobody used for `idle`.
    fn take_idle(&self, idle: Duration) -> Vec<(String, Entry)> {
        self.take_where(|e| {
            e.uses.count.load(Relaxed) == 0
                && e.uses
                    .idle_since
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .elapsed()
                    >= idle
        })
    }

    /// Takes out of service the scenes that may close (cluster scenes) and match `which`.
    fn take_where(&self, which: impl Fn(&Entry) -> bool) -> Vec<(String, Entry)> {
        let mut open = self.write();
        let names: Vec<String> = open
            .iter()
            .filter(|(_, e)| e.close.is_some() && which(e))
            .map(|(n, _)| n.clone())
            .collect();
        names
            .into_iter()
            .filter_map(|n| open.remove(&n).map(|e| (n, e)))
            .collect()
    }
}

impl App {
    /// A scene for someone who wants to use it: served already, or (cluster) loaded from the
    /// cluster now. `Ok(None)`: no such scene.
    pub async fn open_scene(
        &self,
        name: &str,
    ) -> Result<Option<(SceneHandle, SceneUse)>, OpenError> {
        if let Some(found) = self.scenes.take(name) {
            match self.cluster_copy_stale(name).await {
                None => return Ok(Some(found)),
                Some(Stale::Unlisted) => return Ok(None),
                Some(Stale::OtherLog) => drop(found),
            }
        }
        let Some(node) = &self.node else {
            return Ok(None);
        };
        let failed = |detail: String| OpenError::Failed {
            scene: name.to_string(),
            detail,
        };
        match scene_entry(&node.cluster, name).await {
            Ok(Some(_)) => {}
            Ok(None) => return Ok(None),
            Err(e) => return Err(failed(e.to_string())),
        }
        let _opening = self.scenes.opening.lock().await;
        if let Some(found) = self.scenes.take(name) {
            return Ok(Some(found));
        }
        if self.shutdown.is_cancelled() {
            return Err(OpenError::ShuttingDown);
        }
        if self
            .scenes
            .still_closing
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains_key(name)
        {
            return Err(OpenError::StillClosing(name.to_string()));
        }
        self.add_cluster_scene(name.to_string()).await.map_err(|e| {
            let detail = format!("{e:#}");
            tracing::warn!(scene = %name, error = %detail, "cannot open a scene of the cluster");
            failed(detail)
        })?;
        Metrics::add(&self.metrics.scene_opens, 1);
        self.scenes
            .take(name)
            .map(Some)
            .ok_or_else(|| failed("it closed as it opened".into()))
    }

    /// Cluster: whether the copy of `name` served here is no longer the cluster's scene of
    /// that name (deleted, renamed, reset or replaced since this node's last look at the
    /// list). A copy over another log is taken out of service now, so the caller opens the
    /// new one; an unlisted one is left to [`App::tend_cluster_scenes`] to close and say why.
    /// `None` (serve it) also when the list cannot be read.
    async fn cluster_copy_stale(&self, name: &str) -> Option<Stale> {
        let node = self.node.as_ref()?;
        let log = self.scenes.log_of(name)?;
        let entry = scene_entry(&node.cluster, name).await.ok()?;
        let Some(entry) = entry else {
            return Some(Stale::Unlisted);
        };
        if entry.log_key(name) == log {
            return None;
        }
        let _opening = self.scenes.opening.lock().await;
        if self.scenes.log_of(name).as_deref() == Some(log.as_str()) {
            let why = format!(
                "scene {name} was reset or replaced by an administrator: reconnect to see it"
            );
            let _ = crate::admin::take_out(self, name, why).await;
        }
        Some(Stale::OtherLog)
    }

    /// Cluster: reads the cluster's scene list (an entry only for names not seen before).
    pub(crate) async fn refresh_known(
        &self,
        cluster: &crate::cluster::Cluster,
    ) -> Result<(), crate::cluster::ClusterError> {
        let before = self
            .scenes
            .known
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        // A served scene's entry is read every time: a reset keeps its name, not its log.
        let served = self.scenes.served_names();
        let mut known = BTreeMap::new();
        for name in scene_names(cluster).await? {
            let entry = match before.get(&name) {
                Some(entry) if !served.contains(&name) => Some(entry.clone()),
                // One bad entry does not hide the others.
                _ => match scene_entry(cluster, &name).await {
                    Ok(entry) => entry,
                    Err(e) => {
                        tracing::warn!(scene = %name, error = %e, "skipping a scene of the cluster's list");
                        None
                    }
                },
            };
            if let Some(entry) = entry {
                known.insert(name, entry);
            }
        }
        self.scenes.set_known(known);
        Ok(())
    }

    /// Cluster: keeps the scene list fresh, takes scenes whose owner stopped by itself out of
    /// service, and closes scenes nobody here used for `close_idle` (never when it is zero),
    /// until shutdown.
    pub(crate) async fn tend_cluster_scenes(self: Arc<Self>, close_idle: Duration) {
        let shutdown = self.shutdown.clone();
        let mut purged: Option<Instant> = None;
        while wait_or_shutdown(&shutdown, CLUSTER_POLL).await {
            let Some(node) = &self.node else { return };
            let listed = match self.refresh_known(&node.cluster).await {
                Ok(()) => true,
                Err(e) => {
                    tracing::warn!(error = %e, "cannot list the cluster's scenes");
                    false
                }
            };
            if purged.is_none_or(|at| at.elapsed() >= PURGE_EVERY) {
                purged = Some(Instant::now());
                let now = crate::store::Store::unix_seconds();
                match crate::cluster::deleted::purge(&node.cluster, now).await {
                    Ok(dropped) => {
                        for d in dropped {
                            tracing::info!(scene = %d.name, key = %d.key, "dropped a deleted scene whose time was up");
                        }
                    }
                    Err(e) => tracing::warn!(error = %e, "cannot drop deleted scenes"),
                }
            }
            let _closing = self.scenes.opening.lock().await;
            if self.shutdown.is_cancelled() {
                return;
            }
            let mut closed = 0;
            // Deleted on another node (or here, by the admin API, which closed it already).
            let unlisted = if listed {
                self.scenes.served_but_unlisted()
            } else {
                Vec::new()
            };
            for (name, log) in unlisted {
                // Listed again since the list was read (a restore), or unreadable: left.
                let why = match scene_entry(&node.cluster, &name).await {
                    Ok(Some(e)) if e.log_key(&name) == log => continue,
                    Ok(Some(_)) => {
                        format!(
                            "scene {name} was reset or replaced by an administrator: reconnect to see it"
                        )
                    }
                    Ok(None) => match self.scenes.named_for_log(&log) {
                        Some(to) => format!(
                            "scene {name} was renamed to {to} by an administrator: open /scenes/{to}"
                        ),
                        None => format!("scene {name} was deleted by an administrator"),
                    },
                    Err(_) => continue,
                };
                if crate::admin::take_out(&self, &name, why).await.is_ok() {
                    closed += 1;
                }
            }
            for (name, entry) in self.scenes.take_stopped() {
                close(&name, entry, Closing::Stopped, &self.scenes.still_closing).await;
                closed += 1;
            }
            let idle = if close_idle.is_zero() {
                Vec::new()
            } else {
                self.scenes.take_idle(close_idle)
            };
            for (name, entry) in idle {
                let why = Closing::Idle(close_idle);
                close(&name, entry, why, &self.scenes.still_closing).await;
                Metrics::add(&self.metrics.scene_closes, 1);
                closed += 1;
            }
            self.owners
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .retain(|t| !t.is_finished());
            if closed > 0 {
                let _ = tokio::task::spawn_blocking(give_back_memory).await;
            }
        }
    }
}

/// Stops a scene taken out of service: the one path of an idle close and of a shutdown. Its
/// cluster tasks are told first: the lease task stops taking forwarded edits (their senders
/// retry until the lease names another node) but keeps the lease while the owner thread
/// commits what it has and writes its last snapshot, then hands it over at once. An owner
/// that does not stop in time stays listed as closing, and the scene is not reopened here
/// until it has stopped: one node never runs two owners of a scene.
pub(crate) async fn close(
    name: &str,
    entry: Entry,
    why: Closing,
    still_closing: &Arc<Mutex<BTreeMap<String, SceneHandle>>>,
) {
    if let Some(close) = &entry.close {
        close.send_replace(true);
    }
    let _ = entry.handle.send(Command::Shutdown).await;
    let stopped = tokio::time::timeout(CLOSE_PATIENCE, entry.handle.closed()).await;
    if let Some(close) = &entry.close {
        let _ = tokio::time::timeout(CLOSE_PATIENCE, close.closed()).await;
    }
    if stopped.is_err() {
        tracing::warn!(scene = %name, "a closing scene's owner did not stop in time; the scene reopens here once it has");
        still_closing
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(name.to_string(), entry.handle.clone());
        let (still_closing, name) = (still_closing.clone(), name.to_string());
        tokio::spawn(async move {
            entry.handle.closed().await;
            still_closing
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .remove(&name);
        });
        return;
    }
    match why {
        Closing::Idle(idle) => {
            tracing::info!(scene = %name, idle_s = idle.as_secs_f64(), "closed a scene nobody on this node used")
        }
        Closing::Stopped => {
            tracing::info!(scene = %name, "took a scene whose owner stopped out of service; it opens again (from the cluster) when someone asks")
        }
        Closing::Shutdown => tracing::debug!(scene = %name, "closed a scene for the shutdown"),
        Closing::Admin => tracing::info!(scene = %name, "closed a scene for an administrator"),
    }
}

/// Why a scene is taken out of service.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Closing {
    /// Nobody on this node used it for this long.
    Idle(Duration),
    /// Its owner thread stopped by itself (in a cluster: its log cannot be followed).
    Stopped,
    /// The server is shutting down.
    Shutdown,
    /// An administrator deletes, renames or resets it (`crate::admin`).
    Admin,
}

/// Returns freed memory (of closed scenes, of a crowd that left: `conns.rs`) to the system.
/// glibc's allocator keeps freed pages for reuse, so without this a node's resident memory
/// would not go down when a scene closes (measured: BENCHMARKS.md, "Several nodes").
pub(crate) fn give_back_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free heap pages; it touches no live allocation.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// A per-scene stop signal that also fires at the server's shutdown: the cluster's own signal
/// (the simulation drives it without a runtime of tokio's), set when `shutdown` is cancelled
/// unless the scene was closed first.
pub fn close_signal(
    shutdown: &CancellationToken,
) -> (Arc<signal::Sender<bool>>, signal::Receiver<bool>) {
    let (tx, rx) = signal::channel(false);
    let tx = Arc::new(tx);
    let global = shutdown.clone();
    let forward = tx.clone();
    tokio::spawn(async move {
        tokio::select! {
            () = global.cancelled() => { forward.send_replace(true); }
            _ = forward.closed() => {}
        }
    });
    (tx, rx)
}
