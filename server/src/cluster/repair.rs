//! `brickcast-server cluster repair --scene NAME`: the operator's way past log messages no
//! node can read.
//!
//! **Why an explicit step:** a message in a scene's log that is not a turn (anyone who may
//! publish on the log's subject can put one there; README, "Running a cluster", says who
//! should) stops the scene on every node: skipping it silently would be skipping what might
//! have been acknowledged edits. The repair skips it on an operator's word and says what it
//! skipped:
//!
//! 1. take the scene's lease (waiting for the nodes to give it up: a node that cannot follow
//!    the log gives it up at once), so no node orders edits meanwhile;
//! 2. append a marker, fenced on the log's last position: an owner that still thinks it leads
//!    finds its next append refused;
//! 3. replay the newest snapshot and every message after it up to the marker with the nodes'
//!    own replay ([`Replay`]), dropping each message that is missing, does not decode, or
//!    does not continue the scene's sequence;
//! 4. store the result as a new base snapshot at the marker and trim the log below it, then
//!    give the lease back. Nodes load the scene from there when someone opens it.

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;

use super::catalog::scene_entry;
use super::jet::{Bucket, Jet, LogStream, PortError};
use super::log::{Replay, decode_turn, encode_turn, load};
use super::{ClusterError, RENEW_EVERY, snapshot};
use crate::scene::Turn;
use crate::scene::history::History;

/// The name the repair holds a scene's lease under.
const REPAIRER: &str = "cluster-repair";
/// How long the repair waits for the nodes to give the lease up.
const LEASE_WAIT: Duration = Duration::from_secs(10);

/// What a node says when a scene's log cannot be followed: how to repair it.
pub fn hint(scene: &str) -> String {
    format!(
        "an operator can drop what cannot be read with `brickcast-server cluster repair --scene {scene}`"
    )
}

/// A log message the repair dropped, and why.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Dropped {
    pub pos: u64,
    pub why: String,
}

/// What a repair did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Repaired {
    pub scene: String,
    /// Empty: the log could be followed as it was; nothing was changed.
    pub dropped: Vec<Dropped>,
    /// The scene's sequence and log position after the repair.
    pub seq: u64,
    pub pos: u64,
    /// The snapshot it started from, and the turns it kept after it.
    pub from_snapshot_seq: u64,
    pub turns_kept: u64,
}

impl Repaired {
    /// What `cluster repair` prints.
    pub fn render(&self) -> String {
        let mut out = String::new();
        if self.dropped.is_empty() {
            out.push_str(&format!(
                "scene {}: nothing to repair: its log can be followed (sequence {}, log message {})\n",
                self.scene, self.seq, self.pos
            ));
            return out;
        }
        for d in &self.dropped {
            out.push_str(&format!(
                "scene {}: dropped log message {} ({})\n",
                self.scene, d.pos, d.why
            ));
        }
        out.push_str(&format!(
            "scene {}: rebuilt at sequence {} (log message {}) from the snapshot at sequence {} and {} turns after it; nodes load it when someone opens the scene\n",
            self.scene, self.seq, self.pos, self.from_snapshot_seq, self.turns_kept
        ));
        out
    }
}

/// Repairs `scene` (see the module doc). Changes nothing when its log can be followed.
pub async fn repair<J: Jet>(jet: &J, scene: &str) -> Result<Repaired, ClusterError> {
    let Some(entry) = scene_entry(jet, scene).await? else {
        return Err(ClusterError::UnknownScene(scene.into()));
    };
    let mut repaired = repair_log(jet, entry.log_key(scene)).await?;
    repaired.scene = scene.into();
    Ok(repaired)
}

/// [`repair`] of the log whose key is `scene` (its name, unless it was renamed or reset).
async fn repair_log<J: Jet>(jet: &J, scene: &str) -> Result<Repaired, ClusterError> {
    match load(jet, scene).await {
        Ok(loaded) => {
            return Ok(Repaired {
                scene: scene.into(),
                dropped: Vec::new(),
                seq: loaded.loaded.seq,
                pos: loaded.pos,
                from_snapshot_seq: loaded.loaded.meta.snapshot_seq,
                turns_kept: loaded.loaded.replayed,
            });
        }
        Err(e) if !e.is_fault() => return Err(ClusterError::Nats(e.to_string())),
        Err(e) => tracing::info!(scene, error = %e, "repairing"),
    }
    let revision = take_lease(jet, scene).await?;
    let stop = Arc::new(tokio::sync::Notify::new());
    let renewing = tokio::spawn(keep_lease(
        jet.clone(),
        scene.to_string(),
        revision,
        stop.clone(),
    ));
    let result = rebuild(jet, scene).await;
    stop.notify_one();
    let revision = renewing.await.unwrap_or(None);
    if let Some(revision) = revision {
        let _ = jet.kv_delete(Bucket::Owners, scene, Some(revision)).await;
    }
    result
}

/// The scene's lease, for the repair: once the nodes gave it up.
async fn take_lease(jet: &impl Jet, scene: &str) -> Result<u64, ClusterError> {
    let deadline = tokio::time::Instant::now() + LEASE_WAIT;
    loop {
        match jet
            .kv_create(
                Bucket::Owners,
                scene,
                Bytes::from_static(REPAIRER.as_bytes()),
            )
            .await
        {
            Ok(revision) => return Ok(revision),
            Err(PortError::Conflict(_)) if tokio::time::Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
            Err(PortError::Conflict(_)) => {
                let holder = jet
                    .kv_get(Bucket::Owners, scene)
                    .await
                    .ok()
                    .flatten()
                    .map(|e| String::from_utf8_lossy(&e.value).into_owned())
                    .unwrap_or_default();
                return Err(ClusterError::Nats(format!(
                    "node {holder:?} holds scene {scene}'s lease and orders its edits: its log can be followed there; stop that node first if it cannot"
                )));
            }
            Err(e) => return Err(ClusterError::Nats(format!("taking the lease: {e}"))),
        }
    }
}

/// Renews the repair's lease until told to stop; its revision then (`None`: lost).
async fn keep_lease<J: Jet>(
    jet: J,
    scene: String,
    mut revision: u64,
    stop: Arc<tokio::sync::Notify>,
) -> Option<u64> {
    loop {
        tokio::select! {
            biased;
            () = stop.notified() => return Some(revision),
            _ = tokio::time::sleep(RENEW_EVERY) => {}
        }
        let value = Bytes::from_static(REPAIRER.as_bytes());
        match jet.kv_update(Bucket::Owners, &scene, value, revision).await {
            Ok(r) => revision = r,
            Err(e) => {
                tracing::warn!(scene, error = %e, "the repair lost the scene's lease");
                stop.notified().await;
                return None;
            }
        }
    }
}

/// Steps 2-4 of the module doc, with the lease held.
async fn rebuild<J: Jet>(jet: &J, scene: &str) -> Result<Repaired, ClusterError> {
    let failed = |what: &str, e: &dyn std::fmt::Display| {
        ClusterError::Nats(format!("scene {scene}: {what}: {e}"))
    };
    let stream = jet
        .stream(scene, false)
        .await
        .map_err(|e| failed("opening the log stream", &e))?;
    // Fence: any append after this marker's position is refused.
    let marker = encode_turn(&Turn {
        node: REPAIRER.into(),
        ..Default::default()
    })
    .map_err(|e| failed("encoding a marker", &e))?;
    let mut fenced = None;
    for attempt in 0..5 {
        let (_, last, _) = stream
            .bounds()
            .await
            .map_err(|e| failed("reading the log stream", &e))?;
        let id = format!("{REPAIRER}:{last}:{attempt}");
        match stream.append(Bytes::from(marker.clone()), &id, last).await {
            Ok(pos) => {
                fenced = Some(pos);
                break;
            }
            Err(PortError::Conflict(_)) => continue,
            Err(e) => return Err(failed("fencing the log", &e)),
        }
    }
    let fence = fenced.ok_or_else(|| {
        ClusterError::Nats(format!(
            "scene {scene}: its log kept moving under the repair; try again"
        ))
    })?;
    let mut replay = Replay::from_snapshot(jet, scene)
        .await
        .map_err(|e| failed("reading the newest snapshot", &e))?;
    let from_snapshot_seq = replay.snapshot_seq();
    let mut dropped = Vec::new();
    let mut kept = 0;
    let (first, _, _) = stream
        .bounds()
        .await
        .map_err(|e| failed("reading the log stream", &e))?;
    if first > replay.pos + 1 {
        dropped.push(Dropped {
            pos: replay.pos + 1,
            why: format!(
                "messages {}..{first} are missing: trimmed, but no snapshot holds them",
                replay.pos + 1
            ),
        });
        replay.skip(first - 1);
    }
    while replay.pos < fence {
        let pos = replay.pos + 1;
        let turn = match stream.get(pos).await {
            Ok(bytes) => decode_turn(&bytes),
            Err(PortError::NotFound(_)) => Err("it is missing (deleted)".to_string()),
            Err(e) => return Err(failed("reading the log", &e)),
        };
        let checked = turn.and_then(|t| replay.check(pos, &t).map(|r| (t, r)));
        match checked {
            Ok((turn, records)) => {
                let marker = turn.is_marker();
                replay.apply(pos, turn, records).map_err(|e| {
                    failed(
                        "replaying the log (it cannot be repaired by dropping messages)",
                        &e,
                    )
                })?;
                if !marker {
                    kept += 1;
                }
            }
            Err(why) => {
                tracing::warn!(scene, pos, why, "dropping a log message");
                dropped.push(Dropped { pos, why });
                replay.skip(pos);
            }
        }
    }
    let loaded = replay.finish();
    let (seq, pos) = (loaded.loaded.seq, loaded.pos);
    let limits = brickcast_protocol::wire::Limits::default();
    let history = History::new(
        loaded.loaded.history,
        loaded.loaded.last_step_id,
        limits.max_undo_steps,
        limits.max_undo_bytes,
    );
    let mut map = loaded.loaded.map;
    map.set_sequence(seq);
    let base = snapshot::prepare(
        None,
        &map,
        &[],
        seq,
        pos,
        &history,
        &loaded.steps,
        loaded.loaded.answered,
    )
    .encode(scene, None)
    .map_err(|e| failed("encoding the new snapshot", &e))?;
    let before = match snapshot::store(jet, &base)
        .await
        .map_err(|e| failed("storing the new snapshot", &e))?
    {
        snapshot::Stored::Moved { before } => before,
        snapshot::Stored::Stale { head } => {
            return Err(ClusterError::Nats(format!(
                "scene {scene}: a snapshot at log message {} appeared while the repair ran; try again",
                head.pos
            )));
        }
    };
    if let Some(old) = before {
        snapshot::delete_chain(jet, scene, old.base, old.deltas).await;
    }
    // A chain written before heads existed is not read any more.
    let _ = jet.object_delete(scene).await;
    stream
        .purge_before(pos + 1)
        .await
        .map_err(|e| failed("trimming the log", &e))?;
    tracing::info!(scene, seq, pos, dropped = dropped.len(), "repaired");
    Ok(Repaired {
        scene: scene.into(),
        dropped,
        seq,
        pos,
        from_snapshot_seq,
        turns_kept: kept,
    })
}
