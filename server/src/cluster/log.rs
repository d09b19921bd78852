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
//! [`LogRecord::replay`]), the turn's undo-history changes and the requests it answered,
//! zstd-compressed. One message per turn makes them durable together, as one redb transaction
//! does. A turn larger than the server's `max_payload` is split between messages at record
//! boundaries (history in the last). A turn with none of them is a lease marker: a new owner
//! appends one first, so an owner that lost its lease finds its next append refused.
//!
//! **Snapshots** (`snapshot.rs`): a whole base, then deltas of the bricks changed since, each
//! with the scene sequence and stream position it covers and the undo stacks. The owner thread
//! only copies what a snapshot holds; a task encodes and uploads it and only then purges the
//! stream below it.
//!
//! [`JetLog`] is the owner's [`SceneLog`] in a cluster; [`load`] reads a scene (snapshot, then
//! the turns after it), and [`Replay`] is that reading's one replay loop, which `cluster
//! repair` shares.

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

use brickcast_protocol::BrickMap;
use brickcast_protocol::backoff::{self, Backoff};
use brickcast_protocol::wire::UserId;
use bytes::Bytes;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use super::ClusterError;
use super::jet::{Jet, LogStream, PortError};
use super::snapshot;
use crate::envelope::Format;
use crate::record::LogRecord;
use crate::scene::history::{HistoryWrites, Stacks, StepMeta};
use crate::scene::{Answered, LogError, SceneLog, SnapshotOf, Turn, TurnWrite};
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
/// How long a stopping owner waits for its last snapshot's upload.
const UPLOAD_PATIENCE: Duration = Duration::from_secs(20);
/// How long an owner waits before it tries an unreachable log again: the first wait, doubling
/// (with jitter, `brickcast_protocol::backoff`) to the longest while the log stays away.
const RELOAD_FIRST: Duration = Duration::from_millis(500);
const RELOAD_LONGEST: Duration = Duration::from_secs(8);
/// Waits between the attempts of one append.
const APPEND_FIRST: Duration = Duration::from_millis(200);
const APPEND_LONGEST: Duration = Duration::from_secs(2);
/// How many times a load starts over when the snapshot moved on while it was read.
const LOAD_ATTEMPTS: u32 = 5;

/// A turn as a log message.
pub fn encode_turn(turn: &Turn) -> Result<Vec<u8>, String> {
    encode_as(TURN_MAGIC, turn)
}

/// A log message as a turn: an error for anything that is not one.
pub fn decode_turn(bytes: &[u8]) -> Result<Turn, String> {
    decode_as(TURN_MAGIC, bytes, "turn")
}

/// The body of a packed message once unpacked: bincode, at most [`MAX_RAW`] bytes.
const PACKED: Format<MAX_RAW> = Format::new("cluster log message", b"");

/// `value` in bincode, packed under `magic`.
pub(super) fn encode_as<T: Serialize>(magic: [u8; 2], value: &T) -> Result<Vec<u8>, String> {
    let raw = PACKED.encode(value).map_err(|e| e.to_string())?;
    pack(magic, &raw)
}

/// What [`encode_as`] packed: the magic checked, nothing left over.
pub(super) fn decode_as<T: for<'de> Deserialize<'de>>(
    magic: [u8; 2],
    bytes: &[u8],
    what: &str,
) -> Result<T, String> {
    let raw = unpack(magic, bytes, what)?;
    PACKED.decode_body(&raw).map_err(|e| format!("{what}: {e}"))
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
        let start: Vec<String> = bytes.iter().take(4).map(|b| format!("{b:02x}")).collect();
        return Err(format!(
            "not a brickcast {what} ({} bytes, starting {})",
            bytes.len(),
            start.join(" ")
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
fn split(turn: Turn, limit: usize, scene: &str) -> Result<Vec<Vec<u8>>, LogError> {
    let whole = encode_turn(&turn).map_err(|e| LogError::Unsupported {
        scene: scene.into(),
        detail: format!("encoding a turn: {e}"),
    })?;
    if whole.len() <= limit {
        return Ok(vec![whole]);
    }
    if turn.records.len() <= 1 {
        return Err(LogError::Unsupported {
            scene: scene.into(),
            detail: format!(
                "one log entry needs {} bytes compressed, over the NATS server's max_payload; raise max_payload (8MB is recommended)",
                whole.len()
            ),
        });
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

/// NATS names for a scene's log key (or a node's name): streams allow letters, digits, `-`
/// and `_`; scene names also allow `.` (a subject separator), and log keys `=`.
/// `_` → `__`, `.` → `_d`, `=` → `_e`: one-to-one.
pub fn token(scene: &str) -> String {
    scene
        .replace('_', "__")
        .replace('.', "_d")
        .replace('=', "_e")
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

/// Where a node answers `cluster status`.
pub fn status_subject(node: &str) -> String {
    format!("brickcast.status.{}", token(node))
}

/// Until when this node may append: the lease task moves it on every renewal (the time the
/// renewal was *sent* plus the lease's life, less a margin), and revokes it when the lease is
/// lost. A node stopped past its lease (SIGSTOP, a long pause) reads a passed deadline when it
/// wakes and appends nothing, before JetStream's own fence is even needed. Read on tokio's
/// clock (inside the runtime: the simulation's clocks are its runtimes').
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

/// Where a log's async work runs: on a node, the node's runtime, which the owner thread (not
/// one of its own) blocks on; in the simulation, a runtime per node that the simulation drives.
#[derive(Clone)]
pub enum Exec {
    Node(tokio::runtime::Handle),
    #[cfg(test)]
    Own(Arc<tokio::runtime::Runtime>),
}

impl Exec {
    pub fn block_on<F: Future>(&self, future: F) -> F::Output {
        match self {
            Exec::Node(h) => h.block_on(future),
            #[cfg(test)]
            Exec::Own(rt) => rt.block_on(future),
        }
    }

    pub fn spawn<F>(&self, future: F) -> tokio::task::JoinHandle<F::Output>
    where
        F: Future + Send + 'static,
        F::Output: Send + 'static,
    {
        match self {
            Exec::Node(h) => h.spawn(future),
            #[cfg(test)]
            Exec::Own(rt) => rt.spawn(future),
        }
    }
}

/// A scene as loaded from the cluster: the map and history, plus where in the stream it is
/// and the undo step bodies (the redb store's `history/` table).
pub struct ClusterLoaded {
    pub loaded: Loaded,
    pub pos: u64,
    pub steps: HashMap<u64, Vec<u8>>,
}

/// The stream and the snapshot object of a scene, created for a new scene.
pub async fn create(jet: &impl Jet, scene: &str, map: &BrickMap) -> Result<(), ClusterError> {
    let failed = |e: String| ClusterError::Nats(format!("scene {scene}: {e}"));
    jet.stream(scene, true)
        .await
        .map_err(|e| failed(format!("creating the log stream: {e}")))?;
    let first = snapshot::first(map).encode(scene, None).map_err(failed)?;
    match snapshot::store(jet, &first).await {
        Ok(snapshot::Stored::Moved { .. }) => Ok(()),
        Ok(snapshot::Stored::Stale { head }) => Err(failed(format!(
            "the scene already has a snapshot (at log message {})",
            head.pos
        ))),
        Err(e) => Err(failed(format!("storing its first snapshot: {e}"))),
    }
}

/// A scene's snapshot with the turns after it replayed onto it, one at a time ([`load`]
/// refuses a turn that does not fit; `cluster repair` drops it and goes on).
pub struct Replay {
    scene: String,
    map: BrickMap,
    size: [u32; 3],
    snapshot_seq: u64,
    pub seq: u64,
    pub pos: u64,
    pub replayed: u64,
    rows: BTreeMap<u64, (UserId, StepMeta)>,
    steps: HashMap<u64, Vec<u8>>,
    last_step_id: u64,
    answered: Answered,
}

impl Replay {
    /// The newest snapshot of `scene`, to replay turns onto.
    pub async fn from_snapshot(jet: &impl Jet, scene: &str) -> Result<Replay, LogError> {
        let snapshot::Restored {
            mut map,
            size,
            seq,
            pos,
            rows,
            steps,
            last_step_id,
            answered,
            ..
        } = snapshot::read(jet, scene).await?;
        map.record_touched(true);
        Ok(Replay {
            scene: scene.into(),
            map,
            size,
            snapshot_seq: seq,
            seq,
            pos,
            replayed: 0,
            rows,
            steps,
            last_step_id,
            answered: Answered::from_entries(answered),
        })
    }

    /// The scene sequence and stream position of the snapshot this replay started from.
    pub fn snapshot_seq(&self) -> u64 {
        self.snapshot_seq
    }

    /// Why `turn` cannot follow what is replayed so far (checked before anything of it is
    /// applied): a record that does not decode, or a sequence that does not go on by one.
    pub fn check(&self, pos: u64, turn: &Turn) -> Result<Vec<(u64, LogRecord)>, String> {
        let mut records = Vec::with_capacity(turn.records.len());
        for (next, (s, bytes)) in (self.seq + 1..).zip(&turn.records) {
            if *s != next {
                return Err(format!(
                    "log message {pos} holds sequence {s} after {}: the log has a gap or repeats",
                    next - 1
                ));
            }
            let record = LogRecord::decode(bytes)
                .map_err(|e| format!("log entry {s} does not decode: {e}"))?;
            records.push((*s, record));
        }
        Ok(records)
    }

    /// Replays the turn at `pos` (its records as [`Replay::check`] returned them).
    pub fn apply(
        &mut self,
        pos: u64,
        turn: Turn,
        records: Vec<(u64, LogRecord)>,
    ) -> Result<(), String> {
        let limits = LogRecord::replay_limits();
        for (s, record) in records {
            self.map.set_sequence(s);
            record
                .replay(&mut self.map, &limits)
                .map_err(|e| format!("log entry {s} no longer applies: {e}"))?;
            self.seq = s;
            self.replayed += 1;
        }
        for (id, user) in &turn.history.removed {
            if self.rows.get(id).is_some_and(|(u, _)| u == user) {
                self.rows.remove(id);
                self.steps.remove(id);
            }
        }
        for (id, (user, meta, body)) in turn.history.steps {
            self.rows.insert(id, (user, meta));
            self.steps.insert(id, body);
            self.last_step_id = self.last_step_id.max(id);
        }
        for (origin, number, replies) in turn.requests {
            self.answered.record(origin, number, replies);
        }
        self.pos = pos;
        Ok(())
    }

    /// Skips the message at `pos` (`cluster repair`: it holds nothing that is kept).
    pub fn skip(&mut self, pos: u64) {
        self.pos = pos;
    }

    /// The scene as replayed.
    pub fn finish(self) -> ClusterLoaded {
        let Replay {
            mut map,
            size,
            snapshot_seq,
            seq,
            pos,
            replayed,
            rows,
            steps,
            last_step_id,
            answered,
            ..
        } = self;
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
        ClusterLoaded {
            loaded: Loaded {
                map,
                meta: SceneMeta { size, snapshot_seq },
                seq,
                replayed,
                replay_touched,
                history,
                last_step_id,
                answered: answered.entries(),
            },
            pos,
            steps,
        }
    }

    pub fn scene(&self) -> &str {
        &self.scene
    }
}

/// Loads a scene: its newest snapshot (base and deltas), then every turn after it, checked
/// for gaps. A gap right after the snapshot, with a newer snapshot in the store by then, means
/// the owner wrote one and trimmed the log while this node read: it reads again.
pub async fn load(jet: &impl Jet, scene: &str) -> Result<ClusterLoaded, LogError> {
    let mut attempt = 1;
    loop {
        let before = snapshot::newest(jet, scene).await;
        match load_once(jet, scene).await {
            Err(
                LogError::Store(StoreError::Inconsistent { .. }) | LogError::Unavailable { .. },
            ) if attempt < LOAD_ATTEMPTS && snapshot::newest(jet, scene).await != before => {
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

async fn load_once(jet: &impl Jet, scene: &str) -> Result<ClusterLoaded, LogError> {
    let corrupt = |detail: String| {
        LogError::from(StoreError::Corrupt {
            scene: scene.into(),
            detail: format!("{detail}; {}", super::repair::hint(scene)),
        })
    };
    let unavailable = |e: PortError| LogError::Unavailable {
        scene: scene.into(),
        detail: format!("reading the log stream: {e}"),
    };
    let mut replay = Replay::from_snapshot(jet, scene).await?;
    let stream = jet.stream(scene, false).await.map_err(unavailable)?;
    let (first, last, _) = stream.bounds().await.map_err(unavailable)?;
    let pos = replay.pos;
    if last > pos && first > pos + 1 {
        return Err(StoreError::Inconsistent {
            scene: scene.into(),
            detail: format!(
                "the snapshot holds the log up to message {pos} but the stream starts at {first}: messages {}..{first} are missing",
                pos + 1
            ),
        }
        .into());
    }
    while replay.pos < last {
        let next = replay.pos + 1;
        let bytes = match stream.get(next).await {
            Ok(bytes) => bytes,
            Err(PortError::NotFound(_)) => {
                return Err(corrupt(format!("log message {next} is missing (deleted)")));
            }
            Err(e) => return Err(unavailable(e)),
        };
        let turn = decode_turn(&bytes)
            .map_err(|e| corrupt(format!("log message {next} is corrupt ({e})")))?;
        let records = replay.check(next, &turn).map_err(|detail| {
            LogError::from(StoreError::Inconsistent {
                scene: scene.into(),
                detail,
            })
        })?;
        replay.apply(next, turn, records).map_err(corrupt)?;
    }
    Ok(replay.finish())
}

/// A scene's log as its owner thread uses it: append while leading, follow otherwise.
///
/// Every call blocks the owner thread on the node's runtime (the owner is a plain thread,
/// like the redb store's fsyncs block it).
pub struct JetLog<J: Jet> {
    scene: String,
    node: String,
    jet: J,
    stream: J::Stream,
    exec: Exec,
    max_payload: usize,
    /// The stream position of the last turn this replica holds.
    pos: u64,
    leading: bool,
    lease: Arc<LeaseClock>,
    /// Undo step bodies (the redb store's `history/` table).
    steps: HashMap<u64, Vec<u8>>,
    appends: u64,
    /// Waits between attempts to reload an unreachable log, and how many so far.
    reload_backoff: Backoff,
    pauses: u64,
    /// The snapshot being uploaded: one at a time, so an older one can never land after (and
    /// over) a newer one whose trim already happened.
    uploading: Option<tokio::task::JoinHandle<()>>,
    /// The snapshot chain this node wrote while leading without a break, so the next snapshot
    /// can be a delta on it (`snapshot.rs`), and which leadership it belongs to.
    chain: Arc<std::sync::Mutex<ChainState>>,
}

impl<J: Jet> JetLog<J> {
    /// The log of a loaded scene (taking its position and step bodies), for `node`.
    pub async fn open(
        jet: J,
        exec: Exec,
        node: &str,
        scene: &str,
        loaded: &mut ClusterLoaded,
        lease: Arc<LeaseClock>,
    ) -> Result<JetLog<J>, LogError> {
        let stream = jet
            .stream(scene, false)
            .await
            .map_err(|e| LogError::Unavailable {
                scene: scene.into(),
                detail: format!("opening the log stream: {e}"),
            })?;
        Ok(JetLog {
            scene: scene.to_string(),
            node: node.to_string(),
            max_payload: jet.max_payload(),
            jet,
            stream,
            exec,
            pos: loaded.pos,
            leading: false,
            lease,
            steps: std::mem::take(&mut loaded.steps),
            appends: 0,
            reload_backoff: Backoff::new(RELOAD_FIRST, RELOAD_LONGEST),
            pauses: 0,
            uploading: None,
            chain: Arc::default(),
        })
    }

    fn deposed(&self, detail: impl Into<String>) -> LogError {
        LogError::Deposed {
            scene: self.scene.clone(),
            detail: detail.into(),
        }
    }

    fn forget_chain(&self) {
        let mut state = self.chain.lock().unwrap_or_else(|e| e.into_inner());
        state.generation += 1;
        state.chain = None;
    }

    fn append_message(&mut self, bytes: Vec<u8>) -> Result<(), LogError> {
        if !self.leading {
            return Err(self.deposed("it does not hold the lease"));
        }
        let expected = self.pos;
        self.appends += 1;
        // Unique per node, scene position and attempt series: a retry after a lost ack is a
        // duplicate JetStream drops, never a second copy.
        let id = format!("{}:{}:{}", self.node, expected, self.appends);
        let payload = Bytes::from(bytes);
        let (stream, lease, scene) = (self.stream.clone(), self.lease.clone(), self.scene.clone());
        let result = self.exec.block_on(async move {
            let deposed = |detail: String| LogError::Deposed {
                scene: scene.clone(),
                detail,
            };
            // Read on waking, before anything is sent: a node stopped past its lease sees it.
            if !lease.valid() {
                return Err(deposed("its lease ran out before the append".into()));
            }
            let started = Instant::now();
            // Whether an attempt may have landed (its ack was lost): then a later refusal
            // does not mean "not appended".
            let mut maybe_landed = false;
            let mut backoff = Backoff::new(APPEND_FIRST, APPEND_LONGEST);
            let mut attempt = 0u64;
            loop {
                match stream.append(payload.clone(), &id, expected).await {
                    Ok(pos) => return Ok(pos),
                    Err(PortError::Conflict(_)) if !maybe_landed => {
                        return Err(deposed(format!(
                            "another node appended after message {expected}"
                        )));
                    }
                    Err(e) if started.elapsed() < APPEND_PATIENCE && lease.valid() => {
                        tracing::warn!(scene = %scene, error = %e, "log append failed; retrying");
                        maybe_landed = true;
                        attempt += 1;
                        // The draws depend on the message id only, so a simulated run replays.
                        let unit = backoff::spread(backoff::key_of(&id), attempt);
                        tokio::time::sleep(backoff.next_wait(unit)).await;
                    }
                    Err(e) if !maybe_landed => {
                        return Err(deposed(format!("the log append failed: {e}")));
                    }
                    Err(e) => {
                        return Err(LogError::Unknown {
                            scene: scene.clone(),
                            detail: format!("the log append failed ({e})"),
                        });
                    }
                }
            }
        });
        match result {
            Ok(pos) => {
                self.pos = pos;
                Ok(())
            }
            Err(e) => {
                self.leading = false;
                Err(e)
            }
        }
    }
}

impl<J: Jet> SceneLog for JetLog<J> {
    /// Appends a turn, fenced on this replica's position. Refused (`Deposed`) when the lease
    /// has run out or another node appended since.
    fn append(&mut self, turn: TurnWrite<'_>) -> Result<(), LogError> {
        let mut encoded = Vec::with_capacity(turn.records.len());
        let mut buf = Vec::new();
        for (seq, record) in turn.records {
            record.encode(&mut buf).map_err(|e| LogError::Unsupported {
                scene: self.scene.clone(),
                detail: format!("encoding log entry {seq}: {e}"),
            })?;
            encoded.push((*seq, buf.clone()));
        }
        let message = Turn {
            node: self.node.clone(),
            records: encoded,
            history: turn.history.clone(),
            requests: turn.answered.to_vec(),
        };
        let limit = self.max_payload.saturating_sub(HEADER_ROOM);
        for (i, part) in split(message, limit, &self.scene)?.into_iter().enumerate() {
            match self.append_message(part) {
                Ok(()) => {}
                // Part of the turn is in the log: its edits may replay; not "not applied".
                Err(LogError::Deposed { detail, .. }) if i > 0 => {
                    return Err(LogError::Unknown {
                        scene: self.scene.clone(),
                        detail: format!("a turn was logged in part ({detail})"),
                    });
                }
                Err(e) => return Err(e),
            }
        }
        for (id, (_, _, body)) in &turn.history.steps {
            self.steps.insert(*id, body.clone());
        }
        for id in turn.history.removed.keys() {
            self.steps.remove(id);
        }
        Ok(())
    }

    fn history_step(&self, id: u64) -> Result<Option<Vec<u8>>, LogError> {
        Ok(self.steps.get(&id).cloned())
    }

    /// Writes a snapshot at `seq` (this replica's position) in the background: a delta of
    /// the bricks changed since the last snapshot when this node wrote the chain it follows,
    /// else a base. The stream is trimmed below it once it is stored. Only the owner
    /// snapshots, one at a time: false when this call wrote nothing.
    fn snapshot(&mut self, at: SnapshotOf<'_>) -> Result<bool, LogError> {
        if !self.leading || self.uploading.as_ref().is_some_and(|t| !t.is_finished()) {
            return Ok(false);
        }
        if at.map.sequence() != at.seq {
            return Err(StoreError::Inconsistent {
                scene: self.scene.clone(),
                detail: format!(
                    "refusing a snapshot at sequence {} of a map stamped {}",
                    at.seq,
                    at.map.sequence()
                ),
            }
            .into());
        }
        let state = self.chain.clone();
        let (generation, before) = {
            let s = state.lock().unwrap_or_else(|e| e.into_inner());
            (s.generation, s.chain.clone())
        };
        let prepared = snapshot::prepare(
            before.as_ref(),
            at.map,
            at.cells,
            at.seq,
            self.pos,
            at.history,
            &self.steps,
            at.answered.entries(),
        );
        let jet = self.jet.clone();
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
        self.uploading = Some(self.exec.spawn(async move {
            let forget = || state.lock().unwrap_or_else(|e| e.into_inner()).chain = None;
            let name = scene.clone();
            let encoded = match jet.offload(move || prepared.encode(&name, before)).await {
                Some(Ok(encoded)) => encoded,
                Some(Err(e)) => {
                    forget();
                    tracing::error!(scene = %scene, error = %e, "cannot encode a snapshot; the log keeps everything");
                    return;
                }
                None => {
                    forget();
                    tracing::error!(scene = %scene, "encoding a snapshot failed; the log keeps everything");
                    return;
                }
            };
            if !current() {
                forget();
                tracing::info!(scene = %scene, "a snapshot not written: this node no longer leads the scene");
                return;
            }
            let before = match snapshot::store(&jet, &encoded).await {
                Ok(snapshot::Stored::Moved { before }) => before,
                Ok(snapshot::Stored::Stale { head }) => {
                    // It landed late: a newer snapshot (another owner's) is the scene's now.
                    forget();
                    tracing::info!(scene = %scene, pos = encoded.pos, newest = head.pos, "a snapshot landed after a newer one; it is dropped");
                    return;
                }
                Err(e) => {
                    forget();
                    tracing::warn!(scene = %scene, error = %e, "snapshot not written; the log keeps everything");
                    return;
                }
            };
            {
                let mut s = state.lock().unwrap_or_else(|e| e.into_inner());
                if s.generation == generation {
                    s.chain = Some(encoded.chain.clone());
                }
            }
            // Messages after the snapshot stay; the ones it holds go.
            let (seq, pos) = (encoded.seq, encoded.pos);
            match stream.purge_before(pos + 1).await {
                Ok(()) => tracing::debug!(scene = %scene, seq, pos, object = %encoded.name, bytes = encoded.bytes.len(), "snapshot written, log trimmed"),
                Err(e) => tracing::warn!(scene = %scene, error = %e, "snapshot written, log not trimmed"),
            }
            // The new base holds everything: the chain it replaced is leftovers.
            if let Some(old) = before.filter(|b| encoded.is_base && b.base != encoded.chain.base) {
                snapshot::delete_chain(&jet, &scene, old.base, old.deltas).await;
            }
        }));
        Ok(true)
    }

    fn may_order(&self) -> bool {
        self.leading
    }

    fn shared(&self) -> bool {
        true
    }

    fn position(&self) -> u64 {
        self.pos
    }

    /// The turns after this replica's position, up to the stream's end. `Err` when one is
    /// gone (trimmed below a snapshot): the owner reloads.
    fn tail(&mut self) -> Result<Vec<(u64, Turn)>, LogError> {
        let (stream, scene, from) = (self.stream.clone(), self.scene.clone(), self.pos + 1);
        self.exec.block_on(async move {
            let unavailable = |e: PortError| LogError::Unavailable {
                scene: scene.clone(),
                detail: format!("reading the log stream: {e}"),
            };
            let (_, last, _) = stream.bounds().await.map_err(unavailable)?;
            let mut out = Vec::new();
            for next in from..=last {
                let bytes = stream.get(next).await.map_err(unavailable)?;
                let turn = decode_turn(&bytes).map_err(|e| StoreError::Corrupt {
                    scene: scene.clone(),
                    detail: format!(
                        "log message {next} is corrupt ({e}); {}",
                        super::repair::hint(&scene)
                    ),
                })?;
                out.push((next, turn));
            }
            Ok(out)
        })
    }

    /// Appends the empty turn that claims the log for this node: after it, an owner that lost
    /// its lease finds its next append refused.
    fn claim(&mut self) -> Result<(), LogError> {
        self.leading = true;
        // What changed before this node led is not in the owner's changed-brick set.
        self.forget_chain();
        let marker = Turn {
            node: self.node.clone(),
            ..Default::default()
        };
        let bytes = encode_turn(&marker).map_err(|e| LogError::Unsupported {
            scene: self.scene.clone(),
            detail: format!("encoding a lease marker: {e}"),
        })?;
        if let Err(e) = self.append_message(bytes) {
            self.leading = false;
            return Err(e);
        }
        Ok(())
    }

    fn follow(&mut self) {
        self.leading = false;
        self.forget_chain();
    }

    fn applied(&mut self, pos: u64, turn: &Turn) {
        for id in turn.history.removed.keys() {
            self.steps.remove(id);
        }
        for (id, (_, _, body)) in &turn.history.steps {
            self.steps.insert(*id, body.clone());
        }
        self.pos = pos;
    }

    /// Loads the scene again from the cluster (after a gap, or an append that lost the lease).
    fn reload(&mut self) -> Result<Loaded, LogError> {
        self.forget_chain();
        self.leading = false;
        let (jet, scene) = (self.jet.clone(), self.scene.clone());
        let mut loaded = self
            .exec
            .block_on(async move { load(&jet, &scene).await })?;
        self.reload_backoff.reset();
        self.pos = loaded.pos;
        self.steps = std::mem::take(&mut loaded.steps);
        Ok(loaded.loaded)
    }

    fn pause(&mut self) {
        self.pauses += 1;
        let unit = backoff::spread(
            backoff::key_of(&self.node) ^ backoff::key_of(&self.scene),
            self.pauses,
        );
        let wait = self.reload_backoff.next_wait(unit);
        // The sleep is made inside the runtime: this thread is not one of its own.
        self.exec.block_on(async { tokio::time::sleep(wait).await });
    }

    /// A snapshot still uploading when the owner stops (the scene closing on this node, the
    /// server shutting down) is waited for: the next node to open the scene then reads it
    /// instead of replaying the log, and a process exiting does not cut the upload short.
    fn close(&mut self) {
        let Some(upload) = self.uploading.take() else {
            return;
        };
        // Only a thread outside the runtime may wait (blocking inside it would panic).
        if upload.is_finished() || tokio::runtime::Handle::try_current().is_ok() {
            return;
        }
        // The timeout is made inside the runtime: this thread is not one of its own.
        let waited = self
            .exec
            .block_on(async { tokio::time::timeout(UPLOAD_PATIENCE, upload).await });
        if waited.is_err() {
            tracing::warn!(scene = %self.scene, "the last snapshot's upload did not finish in time; the log keeps everything");
        }
    }
}

impl<J: Jet> Drop for JetLog<J> {
    fn drop(&mut self) {
        self.close();
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
        // A fresh log key never shares a stream with a scene name.
        assert_eq!(stream_name("x=12"), "BRICKCAST_LOG_x_e12");
        assert_ne!(token("a=1"), token("a_e1")); // "a_e1" vs "a__e1"
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
        let bytes = encode_turn(&turn).unwrap();
        assert_eq!(decode_turn(&bytes).unwrap(), turn);
        assert!(!turn.is_marker());
        assert!(Turn::default().is_marker());
        let garbage = decode_turn(b"not a turn").unwrap_err();
        assert!(garbage.contains("not a brickcast turn"), "{garbage}");
        // A length claim beyond the bound is refused before anything is allocated.
        let mut lying = bytes.clone();
        lying[2..10].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(decode_turn(&lying).unwrap_err().contains("claims"));
        let mut cut = bytes;
        cut.truncate(12);
        assert!(decode_turn(&cut).is_err());
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
        let turns: Vec<Turn> = parts.iter().map(|p| decode_turn(p).unwrap()).collect();
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
