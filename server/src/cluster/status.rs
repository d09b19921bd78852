//! `brickcast-server cluster status`: what the cluster holds, read from NATS alone.

use std::fmt::Write;

use futures_util::StreamExt;

use super::log::stream_name;
use super::{Cluster, ClusterError, NodeEntry, SceneEntry};

/// One scene's line.
#[derive(Debug, Clone, serde::Serialize)]
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

/// Nodes and scenes.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Status {
    pub nodes: Vec<(String, String)>,
    pub scenes: Vec<SceneStatus>,
}

pub async fn status(cluster: &Cluster) -> Result<Status, ClusterError> {
    let err = |what: &str, e: &dyn std::fmt::Display| ClusterError::Nats(format!("{what}: {e}"));
    let mut nodes = Vec::new();
    if let Ok(mut keys) = cluster.nodes.keys().await {
        while let Some(Ok(key)) = keys.next().await {
            let listen = match cluster.nodes.get(&key).await {
                Ok(Some(v)) => serde_json::from_slice::<NodeEntry>(&v)
                    .map(|e| e.listen)
                    .unwrap_or_default(),
                _ => continue,
            };
            nodes.push((key, listen));
        }
    }
    nodes.sort();
    let mut scenes = Vec::new();
    for name in cluster.scene_names().await? {
        let size = match cluster.scenes.get(&name).await {
            Ok(Some(v)) => serde_json::from_slice::<SceneEntry>(&v)
                .map(|e| e.size)
                .unwrap_or([0; 3]),
            Ok(None) => continue,
            Err(e) => return Err(err("reading the scene list", &e)),
        };
        let owner = cluster
            .owners
            .get(&name)
            .await
            .ok()
            .flatten()
            .map(|v| String::from_utf8_lossy(&v).into_owned());
        let (log_messages, log_last) = match cluster.js.get_stream(stream_name(&name)).await {
            Ok(stream) => match stream.get_info().await {
                Ok(info) => (info.state.messages, info.state.last_sequence),
                Err(e) => return Err(err("reading a log stream", &e)),
            },
            Err(_) => (0, 0),
        };
        let described = super::snapshot::newest(&cluster.snapshots, &name).await;
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
        for (name, listen) in &self.nodes {
            let _ = writeln!(out, "  {name:<20} {listen}");
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
