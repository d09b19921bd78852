//! `brickcast-server cluster status`: what the cluster holds, from NATS, and where each node's
//! copy of each scene stands, from the nodes themselves.
//!
//! Each node answers on `brickcast.status.<node>` with, per scene it serves, the sequence, the
//! map's content hash, the log position and whether it orders the scene's edits: replicas at
//! one sequence must have one hash, so convergence can be checked without a client.

use std::fmt::Write;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use serde::{Deserialize, Serialize};
use tokio::sync::oneshot;

use super::catalog::scene_names;
use super::jet::{Bucket, Jet, LogStream, answer_requests};
use super::log::status_subject;
use super::{ClusterError, NodeEntry, SceneEntry};
use crate::scene::{Command, Described, SceneHandle};

/// How long `cluster status` waits for each node's answer.
const ANSWER_WAIT: Duration = Duration::from_secs(3);
/// How long a node waits for one scene's owner to describe it.
const DESCRIBE_WAIT: Duration = Duration::from_secs(2);

/// One scene's line.
#[derive(Debug, Clone, Serialize)]
pub struct SceneStatus {
    pub name: String,
    pub size: [u32; 3],
    /// The node holding the lease, if any.
    pub owner: Option<String>,
    /// Messages in the log stream (turns since the snapshot), and the stream's last position.
    pub log_messages: u64,
    pub log_last: u64,
    /// The newest snapshot's scene sequence and stream position, and how many deltas follow
    /// the base (`snapshot.rs`).
    pub snapshot_seq: Option<u64>,
    pub snapshot_pos: Option<u64>,
    pub snapshot_deltas: Option<u32>,
}

/// One scene as one node holds it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Replica {
    pub scene: String,
    #[serde(flatten)]
    pub described: Described,
}

/// One node: where it listens, and (when it answered) each scene it serves.
#[derive(Debug, Clone, Serialize)]
pub struct NodeStatus {
    pub name: String,
    pub listen: String,
    /// `None`: the node did not answer in time.
    pub scenes: Option<Vec<Replica>>,
}

/// Nodes and scenes.
#[derive(Debug, Clone, Serialize)]
pub struct Status {
    pub nodes: Vec<NodeStatus>,
    pub scenes: Vec<SceneStatus>,
}

pub async fn status(jet: &impl Jet) -> Result<Status, ClusterError> {
    let mut nodes = Vec::new();
    let mut names = jet.kv_keys(Bucket::Nodes).await.unwrap_or_default();
    names.sort();
    for name in names {
        let Ok(Some(entry)) = jet.kv_get(Bucket::Nodes, &name).await else {
            continue;
        };
        let listen = serde_json::from_slice::<NodeEntry>(&entry.value)
            .map(|e| e.listen)
            .unwrap_or_default();
        let scenes = match jet
            .request(status_subject(&name), Bytes::new(), ANSWER_WAIT)
            .await
        {
            Ok(answer) => serde_json::from_slice::<Vec<Replica>>(&answer).ok(),
            Err(_) => None,
        };
        nodes.push(NodeStatus {
            name,
            listen,
            scenes,
        });
    }
    let mut scenes = Vec::new();
    for name in scene_names(jet).await? {
        let entry = match jet.kv_get(Bucket::Scenes, &name).await {
            Ok(Some(v)) => serde_json::from_slice::<SceneEntry>(&v.value).ok(),
            Ok(None) => continue,
            Err(e) => return Err(ClusterError::Nats(format!("reading the scene list: {e}"))),
        };
        let size = entry.as_ref().map_or([0; 3], |e| e.size);
        let log = entry
            .as_ref()
            .map_or(name.as_str(), |e| e.log_key(&name))
            .to_string();
        let owner = jet
            .kv_get(Bucket::Owners, &log)
            .await
            .ok()
            .flatten()
            .map(|v| String::from_utf8_lossy(&v.value).into_owned());
        let (log_messages, log_last) = match jet.stream(&log, false).await {
            Ok(stream) => match stream.bounds().await {
                Ok((_, last, messages)) => (messages, last),
                Err(e) => return Err(ClusterError::Nats(format!("reading a log stream: {e}"))),
            },
            Err(_) => (0, 0),
        };
        let described = super::snapshot::newest(jet, &log).await;
        scenes.push(SceneStatus {
            name,
            size,
            owner,
            log_messages,
            log_last,
            snapshot_seq: described.map(|d| d.0),
            snapshot_pos: described.map(|d| d.1),
            snapshot_deltas: described.map(|d| d.2),
        });
    }
    Ok(Status { nodes, scenes })
}

impl Status {
    /// The table `cluster status` prints.
    pub fn render(&self) -> String {
        let mut out = String::new();
        let _ = writeln!(out, "nodes ({}):", self.nodes.len());
        for n in &self.nodes {
            let _ = writeln!(out, "  {:<20} {}", n.name, n.listen);
            match &n.scenes {
                None => {
                    let _ = writeln!(out, "    (did not answer)");
                }
                Some(scenes) => {
                    for r in scenes {
                        let d = &r.described;
                        let _ = writeln!(
                            out,
                            "    {:<18} seq {:>10}  hash {:016x}  log position {:>8}  {}{} clients",
                            r.scene,
                            d.seq,
                            d.hash,
                            d.position,
                            if d.leading { "owner  " } else { "" },
                            d.clients
                        );
                    }
                }
            }
        }
        let _ = writeln!(out, "scenes ({}):", self.scenes.len());
        let _ = writeln!(
            out,
            "  {:<20} {:<16} {:<20} {:>10} {:>10} {:>14} {:>7}",
            "scene", "size", "owner", "log msgs", "log last", "snapshot seq", "deltas"
        );
        for s in &self.scenes {
            let size = format!("{}x{}x{}", s.size[0], s.size[1], s.size[2]);
            let owner = s.owner.as_deref().unwrap_or("(none)");
            let snap = s
                .snapshot_seq
                .map_or_else(|| "-".to_string(), |v| v.to_string());
            let deltas = s
                .snapshot_deltas
                .map_or_else(|| "-".to_string(), |v| v.to_string());
            let _ = writeln!(
                out,
                "  {:<20} {:<16} {:<20} {:>10} {:>10} {:>14} {:>7}",
                s.name, size, owner, s.log_messages, s.log_last, snap, deltas
            );
        }
        out
    }
}

/// The scenes a node serves now.
pub type ScenesNow = Arc<dyn Fn() -> Vec<(String, SceneHandle)> + Send + Sync>;

/// A node's side of `cluster status`: answers on its status subject with where each scene it
/// serves stands, until `shutdown`.
pub async fn answer<J: Jet>(
    jet: J,
    node: String,
    scenes: ScenesNow,
    shutdown: tokio_util::sync::CancellationToken,
) {
    let subject = status_subject(&node);
    answer_requests(&jet, subject, "`cluster status`", &shutdown, |_| async {
        let mut replicas = Vec::new();
        for (name, handle) in scenes() {
            let (done, described) = oneshot::channel();
            if handle.send(Command::Describe { done }).await.is_err() {
                continue;
            }
            if let Ok(Ok(described)) = tokio::time::timeout(DESCRIBE_WAIT, described).await {
                replicas.push(Replica {
                    scene: name,
                    described,
                });
            }
        }
        match serde_json::to_vec(&replicas) {
            Ok(bytes) => Some(Bytes::from(bytes)),
            Err(e) => {
                tracing::error!(error = %e, "cannot encode a status answer");
                None
            }
        }
    })
    .await;
}
