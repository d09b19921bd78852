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
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::scene::{
    Command, LogError, SceneHandle, SceneLog, SnapshotOf, TurnWrite, history::Stacks,
};
use crate::store::{Loaded, SceneMeta};
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

/// The views of the past open on this server.
#[derive(Default)]
pub struct PastViews {
    open: Arc<Mutex<HashMap<String, Open>>>,
    /// Held while a view opens (rebuilding a scene is seconds for the largest).
    opening: tokio::sync::Mutex<()>,
}

struct Open {
    handle: SceneHandle,
    uses: Arc<AtomicUsize>,
}

/// One viewer of a view of the past: the view closes when the last one goes.
pub struct PastUse {
    key: String,
    open: Arc<Mutex<HashMap<String, Open>>>,
}

impl Drop for PastUse {
    fn drop(&mut self) {
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        let last = open
            .get(&self.key)
            .is_some_and(|o| o.uses.fetch_sub(1, Relaxed) == 1);
        if last && let Some(gone) = open.remove(&self.key) {
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
    /// The view of scene `name` at sequence `seq`, opened if none is.
    pub async fn open(
        &self,
        app: &App,
        name: &str,
        seq: u64,
    ) -> Result<(SceneHandle, PastUse), PastError> {
        let store = app.store.clone().ok_or(PastError::NoStore)?;
        let key = format!("{name}~{seq}");
        let _opening = self.opening.lock().await;
        if let Some(found) = self.take(&key) {
            return Ok(found);
        }
        let count = self.open.lock().unwrap_or_else(|e| e.into_inner()).len();
        if count >= MAX_OPEN {
            return Err(PastError::Busy(count));
        }
        let scene = name.to_string();
        let map = tokio::task::spawn_blocking(move || store.scene_at(&scene, seq))
            .await
            .map_err(|e| PastError::Failed(e.to_string()))??;
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
        tracing::info!(scene = %name, seq, "opened a view of the past");
        self.open.lock().unwrap_or_else(|e| e.into_inner()).insert(
            key.clone(),
            Open {
                handle,
                uses: Arc::default(),
            },
        );
        self.take(&key)
            .ok_or_else(|| PastError::Failed("it closed as it opened".into()))
    }

    /// Whether this server can show scene `name` at `seq` (it keeps that sequence).
    pub fn check(&self, app: &App, name: &str, seq: u64) -> Result<(), PastError> {
        let store = app.store.as_ref().ok_or(PastError::NoStore)?;
        let span = store.past_span(name)?;
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
        let open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        let found = open.get(key).filter(|o| !o.handle.is_closed())?;
        found.uses.fetch_add(1, Relaxed);
        Some((
            found.handle.clone(),
            PastUse {
                key: key.to_string(),
                open: self.open.clone(),
            },
        ))
    }

    /// Views open now (tests, metrics).
    pub fn count(&self) -> usize {
        self.open.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// Closes every view (shutdown), waiting a little for their owners.
    pub async fn close_all(&self) {
        let all: Vec<Open> = {
            let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
            open.drain().map(|(_, o)| o).collect()
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
