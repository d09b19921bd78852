//! A scene's log in the cluster: one JetStream stream per scene, and its snapshots in an
//! object store.
//!
//! **Why one stream per scene:** the owner fences its appends with the stream's expected last
//! sequence (`Nats-Expected-Last-Sequence`), which is the sequence of the stream's last
//! message; with one scene per stream, that is exactly "the last message of this scene", so a
//! deposed owner's append is refused the moment anyone else appended, and a scene's log can be
//! trimmed below its snapshot on its own.
//!
//! **A message is a turn** ([`Turn`]): the log records of one group commit (the same versioned
//! [`LogRecord`] bytes the redb store writes, replayed through the same
//! [`LogRecord::replay`]) and the turn's undo-history changes, zstd-compressed. One message per
//! turn makes the records and their history durable together, as one redb transaction does.
//! A turn larger than the server's `max_payload` is split between messages at record
//! boundaries (history in the last). A turn with no records is a lease marker: a new owner
//! appends one first, so an owner that lost its lease finds its next append refused.
//!
//! **Snapshots** (`snapshot.rs`): a whole base, then deltas of the bricks changed since, each
//! with the scene sequence and stream position it covers and the undo stacks. The owner thread
//! only copies what a snapshot holds; a task encodes and uploads it and only then purges the
//! stream below it.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use async_nats::jetstream::{self, object_store::ObjectStore, stream::Stream};
use brickcast_protocol::BrickMap;
use brickcast_protocol::wire::UserId;
use bytes::Bytes;
use serde::{Deserialize, Serialize};
use tokio::sync::mpsc;

use super::answered::{Answered, AnsweredEntry};
use super::forward::ForwardReply;
use super::snapshot;
use crate::record::LogRecord;
use crate::scene::history::{History, HistoryWrites, Stacks, StepMeta};
use crate::store::{Loaded, SceneMeta, StoreError};

/// First bytes of a turn message: a tag and the format version.
const TURN_MAGIC: [u8; 2] = [b'T', 1];
/// The most a turn or snapshot may decompress to: bounds what a corrupt message can allocate.
const MAX_RAW: usize = 4 << 30;
/// Room left in a message for headers and framing.
const HEADER_ROOM: usize = 4096;
/// How long an append keeps retrying a NATS server that does not answer (restarting, a
/// network blip) before the owner gives the scene up. The same message id is sent each time,
/// so JetStream's duplicate window keeps a retried append from landing twice.
const APPEND_PATIENCE: Duration = Duration::from_secs(20);

/// One group commit of a scene, as the log stream holds it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Turn {
    /// The node that appended it.
    pub node: String,
    /// Scene sequence → [`LogRecord`] bytes, in order.
    pub records: Vec<(u64, Vec<u8>)>,
    /// The turn's undo-history changes.
    pub history: HistoryWrites,
    /// The forwarded requests the turn applied, with the replies their senders got
    /// (`answered.rs`).
    pub requests: Vec<AnsweredEntry>,
}

impl Turn {
    /// A lease marker: what a new owner appends first (no records, no history, no requests).
    pub fn is_marker(&self) -> bool {
        self.records.is_empty() && self.history.is_empty() && self.requests.is_empty()
    }

    pub fn encode(&self) -> Result<Vec<u8>, String> {
        encode_as(TURN_MAGIC, self)
    }

    pub fn decode(bytes: &[u8]) -> Result<Turn, String> {
        decode_as(TURN_MAGIC, bytes, "turn")
    }
}

/// `value` in bincode, packed under `magic`.
pub(super) fn encode_as<T: Serialize>(magic: [u8; 2], value: &T) -> Result<Vec<u8>, String> {
    let raw = bincode::serde::encode_to_vec(value, bincode::config::standard())
        .map_err(|e| e.to_string())?;
    pack(magic, &raw)
}

/// What [`encode_as`] packed: the magic checked, nothing left over.
pub(super) fn decode_as<T: for<'de> Deserialize<'de>>(
    magic: [u8; 2],
    bytes: &[u8],
    what: &str,
) -> Result<T, String> {
    let raw = unpack(magic, bytes, what)?;
    let (value, read): (T, usize) =
        bincode::serde::decode_from_slice(&raw, bincode::config::standard())
            .map_err(|e| format!("{what}: {e}"))?;
    if read != raw.len() {
        return Err(format!("{what}: {} bytes after it", raw.len() - read));
    }
    Ok(value)
}

/// `magic`, raw length (u64 LE), zstd of `raw`.
fn pack(magic: [u8; 2], raw: &[u8]) -> Result<Vec<u8>, String> {
    let packed = zstd::bulk::compress(raw, 1).map_err(|e| e.to_string())?;
    let mut out = Vec::with_capacity(packed.len() + 10);
    out.extend_from_slice(&magic);
    out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    out.extend_from_slice(&packed);
    Ok(out)
}

fn unpack(magic: [u8; 2], bytes: &[u8], what: &str) -> Result<Vec<u8>, String> {
    if bytes.len() < 10 || bytes[..2] != magic {
        return Err(format!(
            "{what}: not a brickcast {what} (format {:?})",
            bytes.get(..2)
        ));
    }
    let len = u64::from_le_bytes(bytes[2..10].try_into().expect("8 bytes"));
    if len > MAX_RAW as u64 {
        return Err(format!("{what}: claims {len} bytes"));
    }
    let raw =
        zstd::bulk::decompress(&bytes[10..], len as usize).map_err(|e| format!("{what}: {e}"))?;
    if raw.len() as u64 != len {
        return Err(format!("{what}: {} bytes, {len} declared", raw.len()));
    }
    Ok(raw)
}

/// A turn cut into messages of at most `limit` bytes, at record boundaries (the history and
/// the requests go with the last part). A single record over the limit is an error.
fn split(turn: Turn, limit: usize, scene: &str) -> Result<Vec<Vec<u8>>, StoreError> {
    let whole = turn
        .encode()
        .map_err(|e| StoreError::Cluster(format!("encoding a turn: {e}")))?;
    if whole.len() <= limit {
        return Ok(vec![whole]);
    }
    if turn.records.len() <= 1 {
        return Err(StoreError::Cluster(format!(
            "scene {scene}: one log entry needs {} bytes compressed, over the NATS server's max_payload; raise max_payload (8MB is recommended)",
            whole.len(),
        )));
    }
    let mid = turn.records.len() / 2;
    let mut first = Turn {
        node: turn.node.clone(),
        records: turn.records,
        history: HistoryWrites::default(),
        requests: Vec::new(),
    };
    let rest = first.records.split_off(mid);
    let second = Turn {
        node: turn.node,
        records: rest,
        history: turn.history,
        requests: turn.requests,
    };
    let mut out = split(first, limit, scene)?;
    out.extend(split(second, limit, scene)?);
    Ok(out)
}

/// NATS names for a scene: streams allow letters, digits, `-` and `_`; scene names also allow
/// `.` (a subject separator). `_` → `__`, `.` → `_d`: one-to-one.
pub fn token(scene: &str) -> String {
    scene.replace('_', "__").replace('.', "_d")
}

pub fn stream_name(scene: &str) -> String {
    format!("BRICKCAST_LOG_{}", token(scene))
}

pub fn log_subject(scene: &str) -> String {
    format!("brickcast.log.{}", token(scene))
}

pub fn edit_subject(scene: &str) -> String {
    format!("brickcast.edit.{}", token(scene))
}

/// Until when this node may append: the lease task moves it on every renewal (the time the
/// renewal was *sent* plus the lease's life, less a margin), and revokes it when the lease is
/// lost. A node stopped past its lease (SIGSTOP, a long pause) reads a passed deadline when it
/// wakes and appends nothing, before JetStream's own fence is even needed.
#[derive(Debug)]
pub struct LeaseClock {
    base: Instant,
    deadline_ns: AtomicU64,
}

impl Default for LeaseClock {
    fn default() -> Self {
        LeaseClock {
            base: Instant::now(),
            deadline_ns: AtomicU64::new(0),
        }
    }
}

impl LeaseClock {
    pub fn extend_to(&self, until: Instant) {
        let ns = until.saturating_duration_since(self.base).as_nanos() as u64;
        self.deadline_ns.store(ns, Relaxed);
    }

    pub fn revoke(&self) {
        self.deadline_ns.store(0, Relaxed);
    }

    pub fn valid(&self) -> bool {
        (self.base.elapsed().as_nanos() as u64) < self.deadline_ns.load(Relaxed)
    }
}

/// What a node needs to reach a scene's log.
#[derive(Clone)]
pub struct LogHandles {
    pub js: jetstream::Context,
    pub snapshots: ObjectStore,
    pub rt: tokio::runtime::Handle,
    pub node: String,
    /// Copies of a new scene's stream (`--replicas`).
    pub replicas: usize,
}

/// A scene as loaded from the cluster: the map and history, plus where in the stream it is.
pub struct ClusterLoaded {
    pub loaded: Loaded,
    pub pos: u64,
    pub steps: HashMap<u64, Vec<u8>>,
    pub answered: Answered,
}

/// The stream and the snapshot object of a scene, created for a new scene.
pub async fn create(h: &LogHandles, scene: &str, map: &BrickMap) -> Result<(), StoreError> {
    let cluster = |e: String| StoreError::Cluster(format!("scene {scene}: {e}"));
    h.js.get_or_create_stream(jetstream::stream::Config {
        name: stream_name(scene),
        subjects: vec![log_subject(scene)],
        storage: jetstream::stream::StorageType::File,
        num_replicas: h.replicas,
        duplicate_window: Duration::from_secs(120),
        ..Default::default()
    })
    .await
    .map_err(|e| cluster(format!("creating the log stream: {e}")))?;
    let first = snapshot::first(map).encode(scene, None).map_err(cluster)?;
    snapshot::put(&h.snapshots, &first).await.map_err(cluster)
}

/// How many times a load starts over when the snapshot moved on while it was read.
const LOAD_ATTEMPTS: u32 = 5;

/// Loads a scene: its newest snapshot (base and deltas), then every turn after it, checked
/// for gaps. A gap right after the snapshot, with a newer snapshot in the store by then, means
/// the owner wrote one and trimmed the log while this node read: it reads again.
pub async fn load(h: &LogHandles, scene: &str) -> Result<ClusterLoaded, StoreError> {
    let mut attempt = 1;
    loop {
        let before = snapshot::newest(&h.snapshots, scene).await;
        match load_once(h, scene).await {
            Err(StoreError::Inconsistent { .. } | StoreError::Cluster(_))
                if attempt < LOAD_ATTEMPTS
                    && snapshot::newest(&h.snapshots, scene).await != before =>
            {
                tracing::info!(
                    scene,
                    attempt,
                    "the snapshot moved on while the scene loaded; reading it again"
                );
                attempt += 1;
            }
            other => return other,
        }
    }
}

async fn load_once(h: &LogHandles, scene: &str) -> Result<ClusterLoaded, StoreError> {
    let corrupt = |detail: String| StoreError::Corrupt {
        scene: scene.into(),
        detail,
    };
    let inconsistent = |detail: String| StoreError::Inconsistent {
        scene: scene.into(),
        detail,
    };
    let cluster = |e: String| StoreError::Cluster(format!("scene {scene}: {e}"));
    let snapshot::Restored {
        mut map,
        size,
        seq: snapshot_seq,
        pos: snapshot_pos,
        mut rows,
        mut steps,
        mut last_step_id,
        answered,
        ..
    } = snapshot::read(&h.snapshots, scene).await?;
    let mut answered = Answered::from_entries(answered);

    // Every turn after the snapshot, in order.
    let stream =
        h.js.get_stream(stream_name(scene))
            .await
            .map_err(|e| cluster(format!("opening the log stream: {e}")))?;
    let info = stream
        .get_info()
        .await
        .map_err(|e| cluster(format!("reading the log stream: {e}")))?;
    let (first, last) = (info.state.first_sequence, info.state.last_sequence);
    let mut pos = snapshot_pos;
    let mut seq = snapshot_seq;
    let mut replayed = 0;
    if last > pos && first > pos + 1 {
        return Err(inconsistent(format!(
            "the snapshot holds the log up to message {pos} but the stream starts at {first}: messages {}..{first} are missing",
            pos + 1
        )));
    }
    let limits = LogRecord::replay_limits();
    map.record_touched(true);
    while pos < last {
        let next = pos + 1;
        let message = stream
            .get_raw_message(next)
            .await
            .map_err(|e| cluster(format!("reading log message {next}: {e}")))?;
        let turn = Turn::decode(&message.payload)
            .map_err(|e| corrupt(format!("log message {next}: {e}")))?;
        for (s, bytes) in &turn.records {
            if *s != seq + 1 {
                return Err(inconsistent(format!(
                    "log message {next} holds sequence {s} after {seq}: the log has a gap or repeats"
                )));
            }
            let record =
                LogRecord::decode(bytes).map_err(|e| corrupt(format!("log entry {s}: {e}")))?;
            map.set_sequence(*s);
            record
                .replay(&mut map, &limits)
                .map_err(|e| corrupt(format!("log entry {s} no longer applies: {e}")))?;
            seq = *s;
            replayed += 1;
        }
        for (id, user) in &turn.history.removed {
            if rows.get(id).is_some_and(|(u, _)| u == user) {
                rows.remove(id);
                steps.remove(id);
            }
        }
        for (id, (user, meta, body)) in &turn.history.steps {
            rows.insert(*id, (*user, *meta));
            steps.insert(*id, body.clone());
            last_step_id = last_step_id.max(*id);
        }
        for (origin, number, replies) in turn.requests {
            answered.record(origin, number, replies);
        }
        pos = next;
    }
    map.rebuild_clearance();
    let replay_touched = map.take_touched();
    map.record_touched(false);
    let mut by_user: BTreeMap<UserId, Vec<(u64, StepMeta)>> = BTreeMap::new();
    for (id, (user, meta)) in rows {
        by_user.entry(user).or_default().push((id, meta));
    }
    let history = by_user
        .into_iter()
        .map(|(u, rows)| (u, Stacks::from_rows(rows)))
        .collect();
    Ok(ClusterLoaded {
        loaded: Loaded {
            map,
            meta: SceneMeta { size, snapshot_seq },
            seq,
            replayed,
            replay_touched,
            history,
            last_step_id,
        },
        pos,
        steps,
        answered,
    })
}

/// A scene's log as its owner thread uses it: append while leading, follow otherwise.
///
/// Every call blocks the owner thread on the node's tokio runtime (the owner is a plain
/// thread, like the redb store's fsyncs block it).
pub struct JetLog {
    scene: String,
    h: LogHandles,
    stream: Stream,
    subject: String,
    max_payload: usize,
    /// The stream sequence of the last turn this replica holds.
    pos: u64,
    leading: bool,
    lease: Arc<LeaseClock>,
    /// Undo step bodies (the redb store's `history/` table).
    steps: HashMap<u64, Vec<u8>>,
    /// Forwarded requests answered, so a retry is not applied twice.
    pub answered: Answered,
    /// The requests (and replies) of the turn being appended.
    staged: Vec<AnsweredEntry>,
    /// Replies to forwarded edits, published in order by a task.
    replies: mpsc::UnboundedSender<(String, Bytes)>,
    /// Set when the log cannot be followed (corrupt, a gap): the node neither applies nor
    /// leads this scene until restarted.
    pub broken: Arc<std::sync::atomic::AtomicBool>,
    appends: u64,
    /// The snapshot being uploaded: one at a time, so an older one can never land after (and
    /// over) a newer one whose trim already happened.
    uploading: Option<tokio::task::JoinHandle<()>>,
    /// The snapshot chain this node wrote while leading without a break, so the next snapshot
    /// can be a delta on it (`snapshot.rs`), and which leadership it belongs to.
    chain: Arc<std::sync::Mutex<ChainState>>,
}

impl JetLog {
    pub async fn open(
        h: LogHandles,
        scene: &str,
        loaded: &mut ClusterLoaded,
        lease: Arc<LeaseClock>,
        replies: mpsc::UnboundedSender<(String, Bytes)>,
    ) -> Result<JetLog, StoreError> {
        let stream = h.js.get_stream(stream_name(scene)).await.map_err(|e| {
            StoreError::Cluster(format!("scene {scene}: opening the log stream: {e}"))
        })?;
        let max_payload = h.js.client().server_info().max_payload;
        Ok(JetLog {
            scene: scene.to_string(),
            stream,
            subject: log_subject(scene),
            max_payload,
            pos: loaded.pos,
            leading: false,
            lease,
            steps: std::mem::take(&mut loaded.steps),
            answered: std::mem::take(&mut loaded.answered),
            staged: Vec::new(),
            replies,
            broken: Arc::default(),
            appends: 0,
            uploading: None,
            chain: Arc::default(),
            h,
        })
    }

    pub fn scene(&self) -> &str {
        &self.scene
    }

    pub fn node(&self) -> &str {
        &self.h.node
    }

    pub fn pos(&self) -> u64 {
        self.pos
    }

    pub fn set_pos(&mut self, pos: u64) {
        self.pos = pos;
    }

    pub fn leading(&self) -> bool {
        self.leading
    }

    /// Stops appending (the lease is gone, or another node appended).
    pub fn follow(&mut self) {
        self.leading = false;
        self.forget_chain();
    }

    pub fn history_step(&self, id: u64) -> Option<Vec<u8>> {
        self.steps.get(&id).cloned()
    }

    /// Keeps the step bodies of a turn another node committed.
    pub fn apply_committed(&mut self, writes: &HistoryWrites) {
        for id in writes.removed.keys() {
            self.steps.remove(id);
        }
        for (id, (_, _, body)) in &writes.steps {
            self.steps.insert(*id, body.clone());
        }
    }

    /// The requests (with their replies) the next append logs.
    pub fn stage(&mut self, requests: Vec<AnsweredEntry>) {
        self.staged = requests;
    }

    /// Queues a reply to a forwarded edit.
    pub fn reply(&self, subject: String, reply: &ForwardReply) {
        match reply.encode() {
            Ok(bytes) => {
                let _ = self.replies.send((subject, Bytes::from(bytes)));
            }
            Err(e) => {
                tracing::error!(scene = %self.scene, error = %e, "cannot encode a reply to a forwarded edit")
            }
        }
    }

    /// Appends a turn, fenced on this replica's position. Refused (`Deposed`) when the lease
    /// has run out or another node appended since.
    pub fn append(
        &mut self,
        records: &[(u64, LogRecord)],
        history: &HistoryWrites,
    ) -> Result<(), StoreError> {
        let mut encoded = Vec::with_capacity(records.len());
        let mut buf = Vec::new();
        for (seq, record) in records {
            record
                .encode(&mut buf)
                .map_err(|e| StoreError::Cluster(format!("encoding log entry {seq}: {e}")))?;
            encoded.push((*seq, buf.clone()));
        }
        let turn = Turn {
            node: self.h.node.clone(),
            records: encoded,
            history: history.clone(),
            requests: std::mem::take(&mut self.staged),
        };
        let limit = self.max_payload.saturating_sub(HEADER_ROOM);
        for (i, part) in split(turn, limit, &self.scene)?.into_iter().enumerate() {
            match self.append_message(part) {
                Ok(()) => {}
                // Part of the turn is in the log: its edits may replay; not "not applied".
                Err(StoreError::Deposed { detail, .. }) if i > 0 => {
                    return Err(StoreError::Cluster(format!(
                        "scene {}: a turn was logged in part ({detail}); its outcome is unknown",
                        self.scene
                    )));
                }
                Err(e) => return Err(e),
            }
        }
        for (id, (_, _, body)) in &history.steps {
            self.steps.insert(*id, body.clone());
        }
        for id in history.removed.keys() {
            self.steps.remove(id);
        }
        Ok(())
    }

    /// Appends the empty turn that claims the log for this node: after it, an owner that lost
    /// its lease finds its next append refused.
    pub fn claim(&mut self) -> Result<(), StoreError> {
        self.leading = true;
        // What changed before this node led is not in the owner's changed-brick set.
        self.forget_chain();
        let marker = Turn {
            node: self.h.node.clone(),
            ..Default::default()
        };
        let bytes = marker
            .encode()
            .map_err(|e| StoreError::Cluster(format!("encoding a lease marker: {e}")))?;
        if let Err(e) = self.append_message(bytes) {
            self.leading = false;
            return Err(e);
        }
        Ok(())
    }

    fn append_message(&mut self, bytes: Vec<u8>) -> Result<(), StoreError> {
        let deposed = |detail: String| StoreError::Deposed {
            scene: self.scene.clone(),
            detail,
        };
        if !self.leading {
            return Err(deposed("it does not hold the lease".into()));
        }
        if !self.lease.valid() {
            self.leading = false;
            return Err(deposed("its lease ran out before the append".into()));
        }
        let expected = self.pos;
        self.appends += 1;
        // Unique per node, scene position and attempt series: a retry after a lost ack is a
        // duplicate JetStream drops, never a second copy.
        let id = format!("{}:{}:{}", self.h.node, expected, self.appends);
        let payload = Bytes::from(bytes);
        let started = Instant::now();
        let result = self.h.rt.clone().block_on(async {
            // Whether an attempt may have landed (its ack was lost): then a later refusal
            // does not mean "not appended".
            let mut maybe_landed = false;
            loop {
                let publish = jetstream::message::PublishMessage::build()
                    .payload(payload.clone())
                    .message_id(id.clone())
                    .expected_last_sequence(expected);
                let sent = self
                    .h
                    .js
                    .send_publish(self.subject.clone(), publish)
                    .await;
                let outcome = match sent {
                    Ok(ack) => ack.await,
                    Err(e) => Err(e),
                };
                match outcome {
                    Ok(ack) => return Ok(ack.sequence),
                    Err(e)
                        if !maybe_landed
                            && matches!(
                                e.kind(),
                                jetstream::context::PublishErrorKind::WrongLastSequence
                            ) =>
                    {
                        return Err(deposed(format!(
                            "another node appended after message {expected}"
                        )));
                    }
                    Err(e) if started.elapsed() < APPEND_PATIENCE && self.lease.valid() => {
                        tracing::warn!(scene = %self.scene, error = %e, "log append failed; retrying");
                        maybe_landed = true;
                        tokio::time::sleep(Duration::from_millis(200)).await;
                    }
                    Err(e) if !maybe_landed => {
                        return Err(deposed(format!("the log append failed: {e}")));
                    }
                    Err(e) => {
                        return Err(StoreError::Cluster(format!(
                            "scene {}: the log append's outcome is unknown: {e}",
                            self.scene
                        )));
                    }
                }
            }
        });
        match result {
            Ok(seq) => {
                self.pos = seq;
                Ok(())
            }
            Err(e) => {
                self.leading = false;
                Err(e)
            }
        }
    }

    /// The turns after this replica's position, up to the stream's end (a new owner catches
    /// up before it claims the log). `Err` when one is gone (trimmed below a snapshot): the
    /// caller reloads.
    pub fn tail(&self) -> Result<Vec<(u64, Turn)>, StoreError> {
        let cluster = |e: String| StoreError::Cluster(format!("scene {}: {e}", self.scene));
        self.h.rt.clone().block_on(async {
            let info = self
                .stream
                .get_info()
                .await
                .map_err(|e| cluster(format!("reading the log stream: {e}")))?;
            let mut out = Vec::new();
            for next in self.pos + 1..=info.state.last_sequence {
                let message = self
                    .stream
                    .get_raw_message(next)
                    .await
                    .map_err(|e| cluster(format!("reading log message {next}: {e}")))?;
                let turn = Turn::decode(&message.payload).map_err(|e| StoreError::Corrupt {
                    scene: self.scene.clone(),
                    detail: format!("log message {next}: {e}"),
                })?;
                out.push((next, turn));
            }
            Ok(out)
        })
    }

    /// Loads the scene again from the cluster (after a gap, or an append that lost the lease).
    fn forget_chain(&self) {
        let mut state = self.chain.lock().unwrap_or_else(|e| e.into_inner());
        state.generation += 1;
        state.chain = None;
    }

    pub fn reload(&mut self) -> Result<Loaded, StoreError> {
        self.forget_chain();
        let mut loaded = self.h.rt.clone().block_on(load(&self.h, &self.scene))?;
        self.pos = loaded.pos;
        self.steps = std::mem::take(&mut loaded.steps);
        self.answered = std::mem::take(&mut loaded.answered);
        self.staged.clear();
        self.leading = false;
        Ok(loaded.loaded)
    }

    /// Writes a snapshot at `seq` (this replica's position) in the background: a delta of
    /// the bricks at `changed` (linear cells changed since the last snapshot) when this node
    /// wrote the chain it follows, else a base. The stream is trimmed below it once it is
    /// stored. Only the owner snapshots, one at a time: false when this call wrote nothing.
    pub fn snapshot(
        &mut self,
        map: &BrickMap,
        changed: &[u32],
        seq: u64,
        history: &History,
    ) -> Result<bool, StoreError> {
        if !self.leading || self.uploading.as_ref().is_some_and(|t| !t.is_finished()) {
            return Ok(false);
        }
        if map.sequence() != seq {
            return Err(StoreError::Inconsistent {
                scene: self.scene.clone(),
                detail: format!(
                    "refusing a snapshot at sequence {seq} of a map stamped {}",
                    map.sequence()
                ),
            });
        }
        let state = self.chain.clone();
        let (generation, before) = {
            let s = state.lock().unwrap_or_else(|e| e.into_inner());
            (s.generation, s.chain.clone())
        };
        let prepared = snapshot::prepare(
            before.as_ref(),
            map,
            changed,
            seq,
            self.pos,
            history,
            &self.steps,
            self.answered.entries(),
        );
        let store = self.h.snapshots.clone();
        let stream = self.stream.clone();
        let scene = self.scene.clone();
        let lease = self.lease.clone();
        // Still the leadership that prepared the snapshot, with the lease held: a deposed
        // owner's late upload must not replace a newer owner's snapshot.
        let current = {
            let state = state.clone();
            move || {
                lease.valid()
                    && state.lock().unwrap_or_else(|e| e.into_inner()).generation == generation
            }
        };
        // The owner thread only copies the bricks; encoding and compressing (the larger part:
        // seconds for a big scene's base) runs off it, so edits keep flowing.
        self.uploading = Some(self.h.rt.spawn(async move {
            let forget = || state.lock().unwrap_or_else(|e| e.into_inner()).chain = None;
            let name = scene.clone();
            let encoded =
                tokio::task::spawn_blocking(move || prepared.encode(&name, before)).await;
            let encoded = match encoded {
                Ok(Ok(encoded)) => encoded,
                Ok(Err(e)) => {
                    forget();
                    tracing::error!(scene = %scene, error = %e, "cannot encode a snapshot; the log keeps everything");
                    return;
                }
                Err(e) => {
                    forget();
                    tracing::error!(scene = %scene, error = %e, "encoding a snapshot failed; the log keeps everything");
                    return;
                }
            };
            if !current() {
                forget();
                tracing::info!(scene = %scene, "a snapshot not written: this node no longer leads the scene");
                return;
            }
            if let Err(e) = snapshot::put(&store, &encoded).await {
                forget();
                tracing::warn!(scene = %scene, error = %e, "snapshot not written; the log keeps everything");
                return;
            }
            {
                let mut s = state.lock().unwrap_or_else(|e| e.into_inner());
                if s.generation != generation {
                    return;
                }
                s.chain = Some(encoded.chain.clone());
            }
            // Messages after the snapshot stay; the ones it holds go.
            let (seq, pos) = (encoded.seq, encoded.pos);
            match stream.purge().sequence(pos + 1).await {
                Ok(_) => tracing::debug!(scene = %scene, seq, pos, object = %encoded.name, bytes = encoded.bytes.len(), "snapshot written, log trimmed"),
                Err(e) => tracing::warn!(scene = %scene, error = %e, "snapshot written, log not trimmed"),
            }
            if encoded.is_base {
                // The new base holds everything: the old chain's deltas are leftovers.
                snapshot::delete_deltas(&store, &scene).await;
            }
        }));
        Ok(true)
    }
}

/// The snapshot chain and the leadership it belongs to. `chain: None`: the next snapshot is
/// a base. An upload sets the chain once its snapshot is stored, but only in the leadership
/// that started it: claim, step-down and reload start a new one (and clear the chain), so an
/// upload finishing after a change of leadership cannot bring an old chain back.
#[derive(Default)]
struct ChainState {
    generation: u64,
    chain: Option<snapshot::Chain>,
}

/// How long a stopping owner waits for its last snapshot's upload.
const UPLOAD_PATIENCE: Duration = Duration::from_secs(20);

impl Drop for JetLog {
    /// A snapshot still uploading when the owner stops (the scene closing on this node, the
    /// server shutting down) is waited for: the next node to open the scene then reads it
    /// instead of replaying the log, and a process exiting does not cut the upload short.
    fn drop(&mut self) {
        let Some(upload) = self.uploading.take() else {
            return;
        };
        // Only the owner thread may wait (blocking inside the runtime would panic).
        if upload.is_finished() || tokio::runtime::Handle::try_current().is_ok() {
            return;
        }
        // The timeout is made inside the runtime: this thread is not one of its own.
        let waited = self
            .h
            .rt
            .block_on(async { tokio::time::timeout(UPLOAD_PATIENCE, upload).await });
        if waited.is_err() {
            tracing::warn!(scene = %self.scene, "the last snapshot's upload did not finish in time; the log keeps everything");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_escape_one_to_one() {
        assert_eq!(token("demo"), "demo");
        assert_eq!(token("a.b_c"), "a_db__c");
        // Distinct scene names never share a stream.
        assert_ne!(token("a_d"), token("a.")); // "a__d" vs "a_d"
        assert_eq!(stream_name("x.y"), "BRICKCAST_LOG_x_dy");
        assert_eq!(log_subject("x.y"), "brickcast.log.x_dy");
    }

    #[test]
    fn turns_round_trip_and_garbage_is_refused() {
        let mut history = HistoryWrites::default();
        history.removed.insert(3, 9);
        let turn = Turn {
            node: "a".into(),
            records: vec![(7, vec![0, 2, 1]), (8, vec![4])],
            history,
            requests: vec![("p/1".into(), 2, vec![vec![1, 2]])],
        };
        let bytes = turn.encode().unwrap();
        assert_eq!(Turn::decode(&bytes).unwrap(), turn);
        assert!(!turn.is_marker());
        assert!(Turn::default().is_marker());
        assert!(Turn::decode(b"not a turn").is_err());
        // A length claim beyond the bound is refused before anything is allocated.
        let mut lying = bytes.clone();
        lying[2..10].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(Turn::decode(&lying).unwrap_err().contains("claims"));
        let mut cut = bytes;
        cut.truncate(12);
        assert!(Turn::decode(&cut).is_err());
    }

    #[test]
    fn big_turns_split_at_record_boundaries() {
        // Incompressible records of 3000 bytes each, eight of them, under a 7000-byte limit.
        let mut x = 1u32;
        let mut noise = || {
            (0..3000)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    x as u8
                })
                .collect::<Vec<u8>>()
        };
        let turn = Turn {
            node: "a".into(),
            records: (1..=8).map(|s| (s, noise())).collect(),
            history: HistoryWrites::default(),
            requests: vec![("p/1".into(), 1, vec![vec![1]])],
        };
        let parts = split(turn.clone(), 7000, "s").unwrap();
        assert!(parts.len() >= 4, "{} parts", parts.len());
        let turns: Vec<Turn> = parts.iter().map(|p| Turn::decode(p).unwrap()).collect();
        assert!(parts.iter().all(|p| p.len() <= 7000));
        let records: Vec<_> = turns.iter().flat_map(|t| t.records.clone()).collect();
        assert_eq!(records, turn.records, "every record once, in order");
        assert_eq!(turns.last().unwrap().requests, turn.requests);
        assert!(
            turns[..turns.len() - 1]
                .iter()
                .all(|t| t.requests.is_empty())
        );
        // One record over the limit cannot be split.
        let err = split(turn, 2000, "s").unwrap_err().to_string();
        assert!(err.contains("max_payload"), "{err}");
    }
}
