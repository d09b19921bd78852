//! Several nodes, one scene: brickcast on NATS JetStream.
//!
//! `serve --nats URL` makes this node one of a cluster. Every node can serve every scene and
//! opens one when someone asks for it (`crate::served`); per scene one node is the **owner**,
//! chosen through a lease in a key-value bucket, and only it orders edits. Every node serving
//! the scene (the owner too) is a **replica**: it follows the scene's log stream in order,
//! applies each turn with the same code as recovery, and sends its own clients one delta per
//! turn, so fan-out spreads over the nodes.
//!
//! * `log.rs` — the log stream per scene (turn messages, fenced appends), loading a scene,
//!   [`JetLog`] (the owner's store in a cluster).
//! * `snapshot.rs` — snapshots in an object store: a whole base, then deltas of the bricks
//!   changed since.
//! * `lease.rs` — per scene on each node: the lease loop (claim, renew, lose), the intake of
//!   forwarded edits while leading, the log follower, and the reply publisher.
//! * `forward.rs` — sessions send edits to whichever node owns the scene.
//! * `answered.rs` — which forwarded requests were answered, so a retry applies once.
//! * `presence.rs` — people on different nodes see each other (core NATS, lossy, repaired by
//!   a full roster every second).
//! * `status.rs` — `brickcast-server cluster status`.
//!
//! NATS layout (names in [`log`]): key-value buckets `brickcast_owners` (scene → owner node,
//! entries expire after [`LEASE_TTL`] without renewal), `brickcast_nodes` (node name → the
//! running instance, expiring after [`NODE_TTL`]), `brickcast_scenes` (scene → size: the
//! cluster's scene list); object store `brickcast_snapshots` (scene → base snapshot, `scene+N` → its deltas); one
//! stream `BRICKCAST_LOG_<scene>` per scene; core subjects `brickcast.edit.<scene>` for
//! forwarded edits and `brickcast.presence.<scene>` for presence.

mod answered;
pub mod forward;
mod lease;
pub mod log;
pub mod presence;
pub mod repair;
pub mod snapshot;
pub mod status;

use std::time::Duration;

use async_nats::jetstream::{self, kv, object_store::ObjectStore};
use brickcast_protocol::BrickMap;
use serde::{Deserialize, Serialize};

pub use answered::{Answered, Lookup};
pub use lease::start_scene;
pub use log::{JetLog, LeaseClock, LogHandles, Turn};

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

/// Why joining the cluster failed.
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
    #[error("cluster: {0}")]
    Nats(String),
}

fn nats(what: &str) -> impl Fn(&dyn std::fmt::Display) -> ClusterError + '_ {
    move |e| ClusterError::Nats(format!("{what}: {e}"))
}

/// What the scene list in `brickcast_scenes` says of a scene.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneEntry {
    pub size: [u32; 3],
}

/// What `brickcast_nodes` says of a running node.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NodeEntry {
    pub instance: String,
    pub listen: String,
}

/// A connection to the cluster's NATS server and its buckets.
#[derive(Clone)]
pub struct Cluster {
    pub url: String,
    pub client: async_nats::Client,
    pub js: jetstream::Context,
    pub owners: kv::Store,
    pub nodes: kv::Store,
    pub scenes: kv::Store,
    pub snapshots: ObjectStore,
    /// Copies of each stream this node creates (`--replicas`).
    pub replicas: usize,
}

/// A key-value bucket, created when missing. The bucket's stream is created here, with the
/// settings the client's own `create_key_value` uses: that call first reads the account's
/// info in a form NATS 2.9 (Debian's) does not send.
async fn bucket(
    js: &jetstream::Context,
    name: &str,
    max_age: Duration,
    replicas: usize,
) -> Result<kv::Store, ClusterError> {
    if let Ok(store) = js.get_key_value(name).await {
        return Ok(store);
    }
    js.create_stream(jetstream::stream::Config {
        name: format!("KV_{name}"),
        subjects: vec![format!("$KV.{name}.>")],
        max_messages_per_subject: 1,
        max_age,
        storage: jetstream::stream::StorageType::File,
        allow_rollup: true,
        deny_delete: true,
        allow_direct: true,
        num_replicas: replicas,
        discard: jetstream::stream::DiscardPolicy::New,
        ..Default::default()
    })
    .await
    .map_err(|e| nats(&format!("creating bucket {name}"))(&e))?;
    js.get_key_value(name)
        .await
        .map_err(|e| nats(&format!("opening bucket {name}"))(&e))
}

impl Cluster {
    /// Connects and makes sure the buckets exist. A URL nobody answers at, or a server
    /// without JetStream, is a clear error.
    ///
    /// `replicas`: copies JetStream keeps of each stream and bucket this node creates (1 for a
    /// single nats-server; 3 for a JetStream cluster of three). Existing ones keep theirs.
    pub async fn connect(url: &str, replicas: usize) -> Result<Cluster, ClusterError> {
        let replicas = replicas.max(1);
        let client = async_nats::ConnectOptions::new()
            .name("brickcast")
            .connection_timeout(Duration::from_secs(5))
            .request_timeout(Some(Duration::from_secs(10)))
            .connect(url)
            .await
            .map_err(|e| ClusterError::Unreachable {
                url: url.to_string(),
                detail: e.to_string(),
            })?;
        let js = jetstream::new(client.clone());
        // The account's JetStream info, read raw: a server without JetStream has no responder
        // (or answers with an error), and the typed reply of this client expects 2.10's fields.
        let no_js = |detail: String| ClusterError::NoJetStream {
            url: url.to_string(),
            detail,
        };
        let info = tokio::time::timeout(
            Duration::from_secs(5),
            client.request("$JS.API.INFO", bytes::Bytes::new()),
        )
        .await
        .map_err(|_| no_js("no answer from $JS.API.INFO".into()))?
        .map_err(|e| no_js(e.to_string()))?;
        let info: serde_json::Value =
            serde_json::from_slice(&info.payload).map_err(|e| no_js(e.to_string()))?;
        if let Some(error) = info.get("error") {
            return Err(no_js(error.to_string()));
        }
        let owners = bucket(&js, OWNERS_BUCKET, LEASE_TTL, replicas).await?;
        let nodes = bucket(&js, NODES_BUCKET, NODE_TTL, replicas).await?;
        let scenes = bucket(&js, SCENES_BUCKET, Duration::ZERO, replicas).await?;
        let snapshots = match js.get_object_store(SNAPSHOT_BUCKET).await {
            Ok(s) => s,
            Err(_) => js
                .create_object_store(jetstream::object_store::Config {
                    bucket: SNAPSHOT_BUCKET.to_string(),
                    storage: jetstream::stream::StorageType::File,
                    num_replicas: replicas,
                    ..Default::default()
                })
                .await
                .map_err(|e| nats("creating the snapshot store")(&e))?,
        };
        let max_payload = client.server_info().max_payload;
        if max_payload < 8 << 20 {
            tracing::info!(
                max_payload,
                "the NATS server's max_payload is under 8 MB: a turn too big for one message is split, but one undo of a very large brush may not fit (see README, Running a cluster)"
            );
        }
        Ok(Cluster {
            url: url.to_string(),
            client,
            js,
            owners,
            nodes,
            scenes,
            snapshots,
            replicas,
        })
    }

    /// Takes `name` for this process and keeps it while the process lives. A name held by a
    /// node that just died frees itself within [`NODE_TTL`], so a restarted node waits that
    /// long before it calls the name taken.
    pub async fn register_node(&self, name: &str, listen: &str) -> Result<NodeName, ClusterError> {
        if !crate::store::valid_scene_name(name) {
            return Err(ClusterError::BadNodeName(name.into()));
        }
        let entry = NodeEntry {
            instance: format!(
                "{}-{}",
                std::process::id(),
                std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos())
            ),
            listen: listen.to_string(),
        };
        let value =
            bytes::Bytes::from(serde_json::to_vec(&entry).map_err(|e| nats("node entry")(&e))?);
        let deadline = tokio::time::Instant::now() + NODE_TTL + Duration::from_secs(1);
        let revision = loop {
            match self.nodes.create(name, value.clone()).await {
                Ok(r) => break r,
                Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => {
                    if tokio::time::Instant::now() >= deadline {
                        return Err(ClusterError::NodeInUse(name.into()));
                    }
                    tokio::time::sleep(Duration::from_millis(250)).await;
                }
                Err(e) => return Err(nats("registering the node")(&e)),
            }
        };
        let (release, released) = tokio::sync::oneshot::channel();
        let (lost_tx, lost) = tokio::sync::watch::channel(None);
        let task = tokio::spawn(hold_name(
            self.nodes.clone(),
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

    /// The cluster's scenes, sorted.
    pub async fn scene_names(&self) -> Result<Vec<String>, ClusterError> {
        use futures_util::StreamExt;
        let mut keys = self
            .scenes
            .keys()
            .await
            .map_err(|e| nats("listing scenes")(&e))?;
        let mut names = Vec::new();
        while let Some(key) = keys.next().await {
            names.push(key.map_err(|e| nats("listing scenes")(&e))?);
        }
        names.sort();
        Ok(names)
    }

    /// What the scene list says of one scene; `None` when the cluster has no such scene.
    pub async fn scene_entry(&self, name: &str) -> Result<Option<SceneEntry>, ClusterError> {
        if !crate::store::valid_scene_name(name) {
            return Ok(None);
        }
        let Some(value) = self
            .scenes
            .get(name)
            .await
            .map_err(|e| nats("reading the scene list")(&e))?
        else {
            return Ok(None);
        };
        serde_json::from_slice(&value)
            .map(Some)
            .map_err(|e| ClusterError::Nats(format!("the scene list's entry for {name}: {e}")))
    }

    pub fn handles(&self, node: &str) -> LogHandles {
        LogHandles {
            js: self.js.clone(),
            snapshots: self.snapshots.clone(),
            rt: tokio::runtime::Handle::current(),
            node: node.to_string(),
            replicas: self.replicas,
        }
    }

    /// Adds a scene to the cluster: its stream, a first snapshot, then its entry in the scene
    /// list (last, so no node opens a scene that is not complete). `replace` first deletes a
    /// scene of that name: its log and snapshot (nodes serving it must be restarted).
    pub async fn create_scene(
        &self,
        name: &str,
        map: &BrickMap,
        replace: bool,
    ) -> Result<(), ClusterError> {
        if !crate::store::valid_scene_name(name) {
            return Err(ClusterError::Nats(format!(
                "scene name {name:?} is invalid"
            )));
        }
        let exists = self
            .scenes
            .get(name)
            .await
            .map_err(|e| nats("reading the scene list")(&e))?
            .is_some();
        if exists && !replace {
            return Err(ClusterError::SceneExists(name.into()));
        }
        if exists {
            self.scenes
                .purge(name)
                .await
                .map_err(|e| nats("removing the old scene")(&e))?;
            let _ = self.js.delete_stream(log::stream_name(name)).await;
            let _ = self.snapshots.delete(name).await;
            snapshot::delete_deltas(&self.snapshots, name).await;
        }
        let h = self.handles("import");
        log::create(&h, name, map)
            .await
            .map_err(|e| ClusterError::Nats(e.to_string()))?;
        let entry = SceneEntry { size: map.size() };
        let value = serde_json::to_vec(&entry).map_err(|e| nats("scene entry")(&e))?;
        match self.scenes.create(name, value.into()).await {
            Ok(_) => Ok(()),
            Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => {
                Err(ClusterError::SceneExists(name.into()))
            }
            Err(e) => Err(nats("adding the scene to the list")(&e)),
        }
    }
}

/// This process's hold on its node name (`register_node`).
pub struct NodeName {
    release: std::sync::Mutex<Option<tokio::sync::oneshot::Sender<()>>>,
    task: tokio::sync::Mutex<Option<tokio::task::JoinHandle<()>>>,
    /// Why this process must stop, once another process took its name.
    pub lost: tokio::sync::watch::Receiver<Option<String>>,
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

/// Renews the name every quarter of its life. When a renewal fails, the name is looked at:
/// gone (it expired while this process was paused or cut off) → taken again; another
/// process's → this process must stop (`NodeName::lost`): two processes of one name would both
/// answer for it.
async fn hold_name(
    nodes: kv::Store,
    name: String,
    value: bytes::Bytes,
    mut revision: u64,
    mut released: tokio::sync::oneshot::Receiver<()>,
    lost: tokio::sync::watch::Sender<Option<String>>,
) {
    loop {
        tokio::select! {
            biased;
            _ = &mut released => {
                let _ = nodes.delete_expect_revision(&name, Some(revision)).await;
                return;
            }
            _ = tokio::time::sleep(NODE_TTL / 4) => {}
        }
        let error = match nodes.update(&name, value.clone(), revision).await {
            Ok(r) => {
                revision = r;
                continue;
            }
            Err(e) => e,
        };
        match nodes.entry(&name).await {
            Ok(Some(entry)) if entry.operation == kv::Operation::Put && entry.value == value => {
                // Ours after all (the update's answer was lost).
                revision = entry.revision;
            }
            Ok(Some(entry)) if entry.operation == kv::Operation::Put => {
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
            Ok(_) => {
                tracing::warn!(node = %name, error = %error, "the node's name expired; taking it again");
                match nodes.create(&name, value.clone()).await {
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
