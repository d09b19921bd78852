//! Views of a scene's past (issue #34): `/scenes/NAME~S` is scene NAME as it was at sequence
//! S, read-only, streamed like any scene.
//!
//! **How:** the store rebuilds the scene at S (`store::past`), and an ordinary scene owner
//! serves that map over a log that takes no edits ([`PastLog`]): Welcome, sync, working sets,
//! levels of detail and presence are a live scene's, so every viewer (native, browser,
//! `render`) opens the past like the present. Its sessions are viewers. A view opens when its
//! first viewer comes and closes when its last one leaves; every viewer of the same S shares
//! one. Each open view holds its own copy of the scene, so a server opens at most
//! [`MAX_OPEN`] at once (more are refused, saying so).
//!
//! Only a single node keeps the past; a cluster node refuses views of it.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::scene::{
    Command, LogError, SceneHandle, SceneLog, SnapshotOf, TurnWrite, history::Stacks,
};
use crate::store::{Change, Loaded, SceneMeta, Span};
use crate::{App, scene};

/// Views of the past a server holds open at once.
pub const MAX_OPEN: usize = 4;

/// `NAME~S`: the scene and the sequence of a view of its past; `None` when the path names no
/// past (`Err` when it does, badly).
pub fn split_past(path: &str) -> Option<Result<(&str, u64), String>> {
    let (name, seq) = path.split_once('~')?;
    Some(match seq.parse::<u64>() {
        Ok(s) if seq.bytes().all(|b| b.is_ascii_digit()) => Ok((name, s)),
        _ => Err(format!(
            "{path:?}: a view of the past is NAME~SEQUENCE, a whole number (see the scene's history)"
        )),
    })
}

/// Rebuilds of a scene's past (`Store::scene_at`, `Store::timeline`) a server runs at once:
/// each reads a snapshot and replays up to a snapshot interval of log (seconds for the largest
/// scenes, on a blocking thread), so a flood of timeline requests, views and restores waits
/// its turn instead of taking every core.
pub const MAX_REBUILDS: usize = 2;

/// Views of the past one address may have open that it opened (joining one already open is
/// always allowed), so one client cannot take every view.
pub const MAX_PER_ADDRESS: usize = 2;

/// The views of the past open on this server.
pub struct PastViews {
    open: Arc<Mutex<Opened>>,
    /// Held while a view opens (rebuilding a scene is seconds for the largest).
    opening: tokio::sync::Mutex<()>,
    /// Turns at rebuilding the past ([`MAX_REBUILDS`]), each held by its rebuild until it ends.
    rebuilds: Arc<tokio::sync::Semaphore>,
    /// Each scene's generation: an admin command that changes a scene ([`PastViews::close_scene`])
    /// moves it on, so a view or timeline read from the scene before is not kept after.
    generations: Mutex<HashMap<String, u64>>,
    /// Each scene's last timeline, with the span it covers and the most changes it lists: a
    /// request for no more over the same span is answered from it.
    timelines: Mutex<HashMap<String, Timeline>>,
}

type Timeline = (Span, usize, Arc<Vec<Change>>);

impl Default for PastViews {
    fn default() -> Self {
        PastViews {
            open: Arc::default(),
            opening: tokio::sync::Mutex::default(),
            rebuilds: Arc::new(tokio::sync::Semaphore::new(MAX_REBUILDS)),
            generations: Mutex::default(),
            timelines: Mutex::default(),
        }
    }
}

#[derive(Default)]
struct Opened {
    views: HashMap<String, Open>,
    /// Views open now by the address that opened them.
    by_address: HashMap<IpAddr, usize>,
}

impl Opened {
    /// Takes view `key` out (its last viewer left, or its scene changed), giving its opener's
    /// count back.
    fn remove(&mut self, key: &str) -> Option<Open> {
        let gone = self.views.remove(key)?;
        if let Some(n) = self.by_address.get_mut(&gone.opener) {
            *n -= 1;
            if *n == 0 {
                self.by_address.remove(&gone.opener);
            }
        }
        Some(gone)
    }
}

struct Open {
    handle: SceneHandle,
    /// Its uses; a [`PastUse`] knows its view by this (not by name: a view that stopped and
    /// opened again under the same name is another view).
    uses: Arc<AtomicUsize>,
    /// The address that opened it (counted against [`MAX_PER_ADDRESS`] while it is open).
    opener: IpAddr,
}

/// One viewer of a view of the past: the view closes when the last one goes.
pub struct PastUse {
    key: String,
    uses: Arc<AtomicUsize>,
    open: Arc<Mutex<Opened>>,
}

impl Drop for PastUse {
    fn drop(&mut self) {
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        let last = self.uses.fetch_sub(1, Relaxed) == 1;
        let ours = open
            .views
            .get(&self.key)
            .is_some_and(|o| Arc::ptr_eq(&o.uses, &self.uses));
        if last
            && ours
            && let Some(gone) = open.remove(&self.key)
        {
            // The owner stops on Shutdown (its log writes nothing), or once the last handle
            // is gone.
            let _ = gone.handle.try_send(Command::Shutdown);
        }
    }
}

/// Why a view of the past could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum PastError {
    #[error(
        "this server keeps no history of its scenes (a cluster node); views of the past need a single node"
    )]
    NoStore,
    #[error(
        "{0} views of the past are open on this server, the most it holds at once; try again when one closes"
    )]
    Busy(usize),
    #[error(
        "this address holds {0} views of the past already, the most one may open; close one first"
    )]
    BusyHere(usize),
    #[error("{0}")]
    Store(#[from] crate::store::StoreError),
    #[error("cannot serve the view: {0}")]
    Failed(String),
}

impl PastError {
    /// Whether the request named something that is not there (404) rather than a server
    /// that cannot serve it now (503).
    pub fn not_found(&self) -> bool {
        matches!(
            self,
            PastError::Store(
                crate::store::StoreError::NotKept { .. }
                    | crate::store::StoreError::UnknownScene(_)
            )
        )
    }
}

impl PastViews {
    fn lock(&self) -> std::sync::MutexGuard<'_, Opened> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The view of scene `name` at sequence `seq` for a viewer at `from`, opened if none is.
    pub async fn open(
        &self,
        app: &App,
        name: &str,
        seq: u64,
        from: IpAddr,
    ) -> Result<(SceneHandle, PastUse), PastError> {
        let store = app.store.clone().ok_or(PastError::NoStore)?;
        let key = format!("{name}~{seq}");
        if let Some(found) = self.take(&key) {
            return Ok(found);
        }
        let _opening = self.opening.lock().await;
        if let Some(found) = self.take(&key) {
            return Ok(found);
        }
        let generation = self.generation(name);
        {
            let open = self.lock();
            if open.views.len() >= MAX_OPEN {
                return Err(PastError::Busy(open.views.len()));
            }
            let here = open.by_address.get(&from).copied().unwrap_or(0);
            if here >= MAX_PER_ADDRESS {
                return Err(PastError::BusyHere(here));
            }
        }
        let scene = name.to_string();
        let map = self
            .rebuild(move || store.scene_at(&scene, seq))
            .await
            .map_err(PastError::Failed)??;
        let size = map.size();
        let loaded = Loaded {
            map,
            meta: SceneMeta {
                size,
                snapshot_seq: seq,
            },
            seq,
            replayed: 0,
            replay_touched: Vec::new(),
            history: Vec::<(u64, Stacks)>::new(),
            last_step_id: 0,
            answered: Vec::new(),
        };
        let (handle, _thread) = scene::spawn_with(
            key.clone(),
            loaded,
            Box::new(PastLog { key: key.clone() }),
            app.metrics.clone(),
            app.owner_config.clone(),
            tokio::runtime::Handle::current(),
        )
        .map_err(|e| PastError::Failed(e.to_string()))?;
        // Checked under the views' lock: `close_scene` moves the generation on before it takes
        // the scene's views out, so a view is either refused here or taken out there.
        let mut open = self.lock();
        if self.generation(name) != generation {
            // An administrator changed the scene while it was read: that past is not its own.
            let _ = handle.try_send(Command::Shutdown);
            return Err(PastError::Failed(format!(
                "scene {name} was changed by an administrator while its past was read; try again"
            )));
        }
        tracing::info!(scene = %name, seq, "opened a view of the past");
        let uses = Arc::new(AtomicUsize::new(1));
        open.views.insert(
            key.clone(),
            Open {
                handle: handle.clone(),
                uses: uses.clone(),
                opener: from,
            },
        );
        *open.by_address.entry(from).or_default() += 1;
        Ok((
            handle,
            PastUse {
                key,
                uses,
                open: self.open.clone(),
            },
        ))
    }

    /// Runs `work` (a rebuild of the past) on a blocking thread when its turn comes (at most
    /// [`MAX_REBUILDS`] at once). `Err`: it panicked, or the server is going away.
    pub async fn rebuild<T: Send + 'static>(
        &self,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T, String> {
        let turn = self
            .rebuilds
            .clone()
            .acquire_owned()
            .await
            .map_err(|e| format!("rebuilding the past: {e}"))?;
        // The turn goes with the work: a caller that stops waiting (its client left) does not
        // stop a blocking task, and the turn is not free until the task has ended.
        tokio::task::spawn_blocking(move || {
            let _turn = turn;
            work()
        })
        .await
        .map_err(|e| format!("rebuilding the past failed: {e}"))
    }

    /// Whether this server can show scene `name` at `seq` (it keeps that sequence).
    pub async fn check(&self, app: &App, name: &str, seq: u64) -> Result<(), PastError> {
        let store = app.store.clone().ok_or(PastError::NoStore)?;
        let scene = name.to_string();
        let span = tokio::task::spawn_blocking(move || store.past_span(&scene))
            .await
            .map_err(|e| PastError::Failed(e.to_string()))??;
        if seq < span.oldest || seq > span.newest {
            return Err(PastError::Store(crate::store::StoreError::NotKept {
                scene: name.into(),
                seq,
                oldest: span.oldest,
                newest: span.newest,
            }));
        }
        Ok(())
    }

    /// A use of the open view `key`.
    fn take(&self, key: &str) -> Option<(SceneHandle, PastUse)> {
        let open = self.lock();
        let found = open.views.get(key).filter(|o| !o.handle.is_closed())?;
        found.uses.fetch_add(1, Relaxed);
        Some((
            found.handle.clone(),
            PastUse {
                key: key.to_string(),
                uses: found.uses.clone(),
                open: self.open.clone(),
            },
        ))
    }

    /// Scene `name`'s generation (see [`PastViews::close_scene`]).
    fn generation(&self, name: &str) -> u64 {
        let generations = self.generations.lock().unwrap_or_else(|e| e.into_inner());
        generations.get(name).copied().unwrap_or(0)
    }

    /// The latest `limit` changes of scene `name`'s timeline, and the span they cover: read
    /// again only when the scene's kept span moved (an edit, a snapshot) or more are asked for.
    pub async fn timeline(
        &self,
        app: &App,
        name: &str,
        limit: usize,
    ) -> Result<(Span, Vec<Change>), PastError> {
        let store = app.store.clone().ok_or(PastError::NoStore)?;
        let (scene, reader) = (name.to_string(), store.clone());
        let span = tokio::task::spawn_blocking(move || reader.past_span(&scene))
            .await
            .map_err(|e| PastError::Failed(e.to_string()))??;
        let cached = |timelines: &HashMap<String, Timeline>| {
            let (at, most, changes) = timelines.get(name)?;
            (*at == span && *most >= limit).then(|| {
                let from = changes.len().saturating_sub(limit);
                (span, changes[from..].to_vec())
            })
        };
        if let Some(hit) = cached(&self.timelines.lock().unwrap_or_else(|e| e.into_inner())) {
            return Ok(hit);
        }
        let scene = name.to_string();
        let generation = self.generation(name);
        let (span, changes) = self
            .rebuild(move || store.timeline(&scene, limit))
            .await
            .map_err(PastError::Failed)??;
        let mut timelines = self.timelines.lock().unwrap_or_else(|e| e.into_inner());
        if self.generation(name) != generation {
            return Err(PastError::Failed(format!(
                "scene {name} was changed by an administrator while its history was read; try again"
            )));
        }
        timelines.insert(name.to_string(), (span, limit, Arc::new(changes.clone())));
        Ok((span, changes))
    }

    /// Closes the views of scene `name` (deleted, renamed, reset or replaced: its past is
    /// another scene's now), telling their viewers `why`.
    pub async fn close_scene(&self, name: &str, why: &str) {
        {
            // Under the cache's lock: a timeline read before the change is not cached after it.
            let mut timelines = self.timelines.lock().unwrap_or_else(|e| e.into_inner());
            *self
                .generations
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .entry(name.to_string())
                .or_default() += 1;
            timelines.remove(name);
        }
        let prefix = format!("{name}~");
        let gone: Vec<Open> = {
            let mut open = self.lock();
            let keys: Vec<String> = open
                .views
                .keys()
                .filter(|k| k.starts_with(&prefix))
                .cloned()
                .collect();
            keys.iter().filter_map(|k| open.remove(k)).collect()
        };
        for view in gone {
            let farewell = Command::Farewell {
                code: brickcast_protocol::wire::ErrorCode::UnknownScene,
                text: why.to_string(),
            };
            let _ = view.handle.send(farewell).await;
            let _ = view.handle.send(Command::Shutdown).await;
        }
    }

    /// Closes every view (shutdown), waiting a little for their owners.
    pub async fn close_all(&self) {
        let all: Vec<Open> = {
            let mut open = self.lock();
            open.by_address.clear();
            open.views.drain().map(|(_, o)| o).collect()
        };
        for view in all {
            let _ = view.handle.send(Command::Shutdown).await;
            let _ = tokio::time::timeout(Duration::from_secs(10), view.handle.closed()).await;
        }
    }
}

/// The log of a view of the past: it takes no edits (its sessions are viewers, so nothing is
/// ever appended) and keeps nothing.
struct PastLog {
    key: String,
}

impl PastLog {
    fn unsupported(&self, what: &str) -> LogError {
        LogError::Unsupported {
            scene: self.key.clone(),
            detail: format!("a view of the past {what}"),
        }
    }
}

impl SceneLog for PastLog {
    fn append(&mut self, turn: TurnWrite<'_>) -> Result<(), LogError> {
        if turn.records.is_empty() && turn.history.is_empty() {
            return Ok(());
        }
        Err(self.unsupported("takes no edits"))
    }

    fn history_step(&self, _id: u64) -> Result<Option<Vec<u8>>, LogError> {
        Ok(None)
    }

    fn snapshot(&mut self, _at: SnapshotOf<'_>) -> Result<bool, LogError> {
        Ok(false)
    }

    fn may_order(&self) -> bool {
        true
    }

    fn reload(&mut self) -> Result<Loaded, LogError> {
        Err(self.unsupported("does not reload"))
    }
}
