//! A node's name (`--node`), held in `brickcast_nodes` while its process lives.
//!
//! **Why a process gives its name up:** forwarded edits go to the subject of the node the
//! lease names, and leases name nodes. Two processes of one name would both answer for it. A
//! process paused (or cut off from NATS) until its name expired may find, when it wakes, that
//! a new process took the name meanwhile: it stops, rather than run beside it.

use std::time::Duration;

use brickcast_protocol::backoff::{self, Backoff};
use bytes::Bytes;
use tokio::sync::oneshot;

use super::jet::{Bucket, Jet, PortError};
use super::{ClusterError, NODE_TTL, NodeEntry, signal};

/// This process's hold on its node name ([`register`]).
pub struct NodeName {
    release: std::sync::Mutex<Option<oneshot::Sender<()>>>,
    task: tokio::sync::Mutex<Option<tokio::task::JoinHandle<()>>>,
    /// Why this process must stop, once another process took its name.
    pub lost: signal::Receiver<Option<String>>,
}

impl NodeName {
    /// Gives the name back (a restarted node takes it at once). A name another process took
    /// meanwhile is left alone.
    pub async fn release(&self) {
        let release = self
            .release
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        if let Some(release) = release {
            let _ = release.send(());
        }
        if let Some(task) = self.task.lock().await.take() {
            let _ = tokio::time::timeout(Duration::from_secs(5), task).await;
        }
    }
}

/// This process, told apart from an earlier one of the same node name (a restarted node gets
/// another): in its name's entry, and the origin of its forwarded edits.
pub fn process_instance() -> String {
    static INSTANCE: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    INSTANCE
        .get_or_init(|| {
            let nanos = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos());
            format!("{}-{nanos:x}", std::process::id())
        })
        .clone()
}

/// How long a starting node waits for NATS to answer before it gives up.
pub const BOOT_UNAVAILABLE: Duration = Duration::from_secs(30);

/// Waits between registration attempts (`brickcast_protocol::backoff`, with jitter drawn from
/// the node's name, so a simulated run replays).
const RETRY_FIRST: Duration = Duration::from_millis(250);
const RETRY_LONGEST: Duration = Duration::from_secs(2);

/// Takes `name` for this process (instance `instance`, listening on `listen`) and keeps it
/// while the process lives. A name held by a node that just died frees itself within
/// [`NODE_TTL`], so a restarted node waits that long before it calls the name taken. NATS
/// not answering (restarting, a blip) is waited out for [`BOOT_UNAVAILABLE`]; a create that
/// landed with its answer lost is found again (the entry names this instance).
pub async fn register<J: Jet>(
    jet: &J,
    name: &str,
    instance: String,
    listen: &str,
) -> Result<NodeName, ClusterError> {
    if !crate::store::valid_scene_name(name) {
        return Err(ClusterError::BadNodeName(name.into()));
    }
    let entry = NodeEntry {
        instance,
        listen: listen.to_string(),
    };
    let value = Bytes::from(
        serde_json::to_vec(&entry).map_err(|e| ClusterError::Nats(format!("node entry: {e}")))?,
    );
    let start = tokio::time::Instant::now();
    // A name held by a dead process frees itself within NODE_TTL.
    let taken_until = start + NODE_TTL + Duration::from_secs(1);
    // NATS may be restarting or briefly out of reach as the node starts.
    let unreachable_until = start + BOOT_UNAVAILABLE;
    // Nodes restarted together (or waiting out one NATS restart) do not ask in lockstep.
    let mut backoff = Backoff::new(RETRY_FIRST, RETRY_LONGEST);
    let mut attempt = 0u64;
    let revision = loop {
        let error = match jet.kv_create(Bucket::Nodes, name, value.clone()).await {
            Ok(r) => break r,
            Err(e) => e,
        };
        match error {
            PortError::Conflict(_) => {
                // The create may have landed with its answer lost: then the entry is ours.
                match jet.kv_get(Bucket::Nodes, name).await {
                    Ok(Some(entry)) if entry.value == value => break entry.revision,
                    Ok(_) | Err(PortError::NotFound(_)) => {}
                    Err(PortError::Unavailable(_))
                        if tokio::time::Instant::now() < unreachable_until => {}
                    Err(e) => return Err(ClusterError::Nats(format!("registering the node: {e}"))),
                }
                if tokio::time::Instant::now() >= taken_until {
                    return Err(ClusterError::NodeInUse(name.into()));
                }
            }
            PortError::Unavailable(e) => {
                if tokio::time::Instant::now() >= unreachable_until {
                    return Err(ClusterError::Nats(format!(
                        "registering the node: {e} (tried for {BOOT_UNAVAILABLE:?})"
                    )));
                }
                tracing::warn!(node = name, error = %e, "NATS did not answer while registering; trying again");
            }
            e => return Err(ClusterError::Nats(format!("registering the node: {e}"))),
        }
        attempt += 1;
        let unit = backoff::spread(backoff::key_of(name), attempt);
        tokio::time::sleep(backoff.next_wait(unit)).await;
    };
    let (release, released) = oneshot::channel();
    let (lost_tx, lost) = signal::channel(None);
    let task = tokio::spawn(hold(
        jet.clone(),
        name.to_string(),
        value,
        revision,
        released,
        lost_tx,
    ));
    Ok(NodeName {
        release: std::sync::Mutex::new(Some(release)),
        task: tokio::sync::Mutex::new(Some(task)),
        lost,
    })
}

/// Renews the name every quarter of its life. When a renewal fails, the name is looked at:
/// gone (it expired while this process was paused or cut off) → taken again; another
/// process's → this process must stop ([`NodeName::lost`]).
async fn hold<J: Jet>(
    jet: J,
    name: String,
    value: Bytes,
    mut revision: u64,
    mut released: oneshot::Receiver<()>,
    lost: signal::Sender<Option<String>>,
) {
    loop {
        tokio::select! {
            biased;
            _ = &mut released => {
                let _ = jet.kv_delete(Bucket::Nodes, &name, Some(revision)).await;
                return;
            }
            _ = tokio::time::sleep(NODE_TTL / 4) => {}
        }
        let error = match jet
            .kv_update(Bucket::Nodes, &name, value.clone(), revision)
            .await
        {
            Ok(r) => {
                revision = r;
                continue;
            }
            Err(e) => e,
        };
        match jet.kv_get(Bucket::Nodes, &name).await {
            // Ours after all (the update's answer was lost).
            Ok(Some(entry)) if entry.value == value => revision = entry.revision,
            Ok(Some(entry)) => {
                let other = serde_json::from_slice::<NodeEntry>(&entry.value)
                    .map(|e| e.listen)
                    .unwrap_or_default();
                let why = format!(
                    "another process (listening on {other}) took this node's name {name:?} while this one could not renew it (it was paused or cut off from NATS for over {} s); this process stops",
                    NODE_TTL.as_secs()
                );
                tracing::error!("{why}");
                lost.send_replace(Some(why));
                return;
            }
            Ok(None) => {
                tracing::warn!(node = %name, error = %error, "the node's name expired; taking it again");
                match jet.kv_create(Bucket::Nodes, &name, value.clone()).await {
                    Ok(r) => revision = r,
                    Err(e) => {
                        tracing::warn!(node = %name, error = %e, "cannot take the node's name again yet")
                    }
                }
            }
            Err(e) => {
                tracing::warn!(node = %name, error = %e, "cannot renew the node's name; trying again");
            }
        }
    }
}
