//! Several nodes, one scene: brickcast on NATS JetStream.
//!
//! `serve --nats URL` makes this node one of a cluster. Every node can serve every scene and
//! opens one when someone asks for it (`crate::served`); per scene one node is the **owner**,
//! chosen through a lease in a key-value bucket, and only it orders edits. Every node serving
//! the scene (the owner too) is a **replica**: it follows the scene's log stream in order,
//! applies each turn with the same code as recovery, and sends its own clients one delta per
//! turn, so fan-out spreads over the nodes.
//!
//! The cluster depends on the scene and never the reverse: the scene owner speaks to one
//! trait (`crate::scene::SceneLog`), which [`JetLog`] implements, and takes commands
//! (`Request`, `Apply`, `Lead`, `Follow`, `Fault`) that the tasks here send it. Everything
//! done with NATS goes through one trait too ([`Jet`]), so the simulation (`sim/`) runs this
//! same code over a simulated JetStream.
//!
//! * `jet.rs` — what the cluster needs of NATS; `nats.rs` — the real one ([`Cluster`]).
//! * `log.rs` — the log stream per scene (turn messages, fenced appends), loading a scene,
//!   [`JetLog`] (the owner's [`SceneLog`](crate::scene::SceneLog) in a cluster).
//! * `snapshot.rs` — snapshots in an object store: a whole base, then deltas of the bricks
//!   changed since.
//! * `lease.rs` — per scene on each node: the lease loop (claim, renew, lose, claim again),
//!   the intake of forwarded edits while leading, the log follower, and the reply publisher.
//! * `forward.rs` — sessions send edits to whichever node owns the scene.
//! * `name.rs` — a node's name, held while the process lives (and given up if another
//!   process took it).
//! * `catalog.rs` — the cluster's scene list; adding a scene.
//! * `repair.rs` — `cluster repair`: past a log message nobody can read, by an operator.
//! * `presence.rs` — people on different nodes see each other (core NATS, lossy, repaired by
//!   a full roster every second).
//! * `status.rs` — `brickcast-server cluster status` (and each node's answer to it).
//!
//! NATS layout (names in [`log`]; `<log>` is a scene's log key, see [`SceneEntry`]): key-value
//! buckets `brickcast_owners` (log key → owner node, entries expire after [`LEASE_TTL`]
//! without renewal), `brickcast_nodes` (node name → the running instance, expiring after
//! [`NODE_TTL`]), `brickcast_scenes` (scene → size and log key: the cluster's scene list);
//! object store `brickcast_snapshots` (`<log>` → base snapshot, `<log>+N` → its deltas); one
//! stream `BRICKCAST_LOG_<log>` per scene; core subjects `brickcast.edit.<log>.<node>` for
//! forwarded edits, `brickcast.presence.<scene>` for
//! presence and `brickcast.status.<node>` for `cluster status`.

pub mod catalog;
pub mod deleted;
mod entry;
pub mod forward;
pub mod jet;
pub mod kick;
mod lease;
pub mod log;
pub mod name;
pub mod nats;
pub mod presence;
pub mod repair;
pub mod signal;
#[cfg(test)]
mod sim;
pub mod snapshot;
pub mod status;

use std::time::Duration;

use serde::{Deserialize, Serialize};

pub use entry::SceneEntry;
pub use forward::SceneLink;
pub use jet::{Jet, PortError};
pub use lease::{open_scene, start_scene};
pub use log::{JetLog, LeaseClock};
pub use name::NodeName;
pub use nats::Cluster;

/// A scene's lease lives this long without renewal.
pub const LEASE_TTL: Duration = Duration::from_secs(3);
/// How often the owner renews its lease.
pub const RENEW_EVERY: Duration = Duration::from_millis(750);
/// How often a node without the lease tries to take it.
pub const CLAIM_POLL: Duration = Duration::from_millis(250);
/// How long a node without clients on a scene leaves a free lease to nodes with clients.
pub const CLAIM_GRACE: Duration = Duration::from_secs(1);
/// The owner stops appending this long before its lease could have run out.
pub const LEASE_MARGIN: Duration = Duration::from_millis(500);
/// A node's name is held this long without renewal.
pub const NODE_TTL: Duration = Duration::from_secs(5);

pub const OWNERS_BUCKET: &str = "brickcast_owners";
pub const NODES_BUCKET: &str = "brickcast_nodes";
pub const SCENES_BUCKET: &str = "brickcast_scenes";
pub const SNAPSHOT_BUCKET: &str = "brickcast_snapshots";
pub const HEADS_BUCKET: &str = "brickcast_snapshot_heads";

/// Why joining or asking the cluster failed.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    #[error("cannot reach NATS at {url}: {detail}")]
    Unreachable { url: String, detail: String },
    #[error(
        "the NATS server at {url} has no JetStream ({detail}); start it with JetStream on (`nats-server -js`)"
    )]
    NoJetStream { url: String, detail: String },
    #[error(
        "node name {0:?} is already in use by a running node; give this one another --node name"
    )]
    NodeInUse(String),
    #[error(
        "node name {0:?} is invalid: use 1-64 letters, digits, '-', '_' or '.', starting with a letter or digit"
    )]
    BadNodeName(String),
    #[error("scene {0} already exists in the cluster")]
    SceneExists(String),
    #[error("the cluster has no scene {0}")]
    UnknownScene(String),
    /// Another node changed what this change was about meanwhile; nothing was done.
    #[error("{0}")]
    Busy(String),
    #[error("cluster: {0}")]
    Nats(String),
}

impl From<PortError> for ClusterError {
    fn from(e: PortError) -> ClusterError {
        ClusterError::Nats(e.to_string())
    }
}

/// What `brickcast_nodes` says of a running node.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NodeEntry {
    pub instance: String,
    pub listen: String,
}
