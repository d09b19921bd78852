//! The scene owner: one thread per scene that alone touches its brick map.
//!
//! Sessions send it commands over a channel; it is the single place edits are ordered. Each turn
//! of its loop drains every queued command (group commit), applies the edits in arrival order and
//! gives each batch that changed something the next sequence number, appends the applied ops to
//! the log in one durable commit, and only then acknowledges them and broadcasts the delta. A
//! client therefore never sees an ack for an edit that a crash could lose.
//!
//! Deltas are coalesced: everything touched in a turn is sent once, in its latest state, encoded
//! and compressed once, and the same bytes are queued to every subscriber.
//!
//! Outgoing queues are bounded in bytes. A client whose queue overflows stops receiving deltas;
//! when it has drained, it gets a `Resync` from the last sequence fully queued to it, so a slow
//! client costs bounded memory and never delays the others.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::time::{Duration, Instant};

use brickcast_protocol::BrickMap;
use brickcast_protocol::apply::apply_op;
use brickcast_protocol::brick::popcount;
use brickcast_protocol::wire::{
    BlobEncoder, BrickBlob, EditOp, Limits, MAX_REMOVED_PER_FRAME, OpRejection, PROTOCOL_VERSION,
    Rejection, Role, ServerMsg, encode_server,
};
use bytes::Bytes;
use tokio::sync::{mpsc, oneshot};

use crate::metrics::{Metrics, OwnerPhase, PhaseClock};
use crate::store::Store;

/// Identifies a session within the server.
pub type SessionId = u64;

/// Most ops applied in one turn before committing: bounds the latency a huge backlog adds to the
/// first edit in it.
const MAX_OPS_PER_TURN: usize = 65_536;
/// Snapshot once replaying the log would cost about this many single-voxel ops (about a second
/// of recovery: 7.2 M logged voxel ops replayed in 2.0 s on the dev VM; see
/// [`Owner::replay_cost`]). A snapshot rewrites every brick touched since the
/// last one and stalls the owner meanwhile (about 1 µs per brick: a quarter of a second for a
/// scene whose every brick was edited), so it is sized by what recovery would replay, not by how
/// many edit messages carried it: counting messages made small batches snapshot the whole scene
/// every two seconds under load.
const SNAPSHOT_REPLAY_BUDGET: u64 = 4_000_000;
/// Voxels a sphere or box brush changes per single-voxel op of replay time (~10 ns per brushed
/// voxel against ~300 ns per op).
const VOXELS_PER_OP_COST: u64 = 32;
/// Single-voxel ops of replay time one log entry costs besides its ops (reading and decoding
/// the row).
const ENTRY_OP_COST: u64 = 4;
/// A snapshot is put off until this many times as long as the last one took has passed, so
/// snapshots take at most about a tenth of the owner's time: when every brick of a big scene is
/// being rewritten (sphere brushes everywhere), one snapshot takes seconds, and the replay
/// budget alone would have the owner snapshotting most of the time. Recovery then replays
/// more than the budget, in proportion.
const SNAPSHOT_SPACING: u32 = 10;
/// ...or after this long with any entries, so an idle server's log is short too.
const SNAPSHOT_EVERY: Duration = Duration::from_secs(60);
/// Keep tombstones for at least this many sequence numbers: a client that reconnects within that
/// window resumes with a delta instead of a full resync.
const TOMBSTONE_WINDOW: u64 = 1_000_000;
/// zstd level for deltas and sync batches: level 1 compresses at ~280 MiB/s raw on one core.
const ZSTD_LEVEL: i32 = 1;

/// A session's outgoing queue, as the owner sees it: frames plus a byte count shared with the
/// session's writer, which subtracts what it has sent.
#[derive(Clone)]
pub struct Outbox {
    tx: mpsc::UnboundedSender<Bytes>,
    queued: Arc<AtomicUsize>,
}

impl Outbox {
    pub fn new() -> (Outbox, mpsc::UnboundedReceiver<Bytes>, Arc<AtomicUsize>) {
        let (tx, rx) = mpsc::unbounded_channel();
        let queued = Arc::new(AtomicUsize::new(0));
        (
            Outbox {
                tx,
                queued: queued.clone(),
            },
            rx,
            queued,
        )
    }

    /// Queues a frame; false when the session is gone.
    pub fn push(&self, frame: Bytes) -> bool {
        self.queued.fetch_add(frame.len(), Relaxed);
        self.tx.send(frame).is_ok()
    }

    pub fn queued(&self) -> usize {
        self.queued.load(Relaxed)
    }
}

/// What sessions ask of the owner.
pub enum Command {
    Join {
        session: SessionId,
        out: Outbox,
        role: Role,
        resume_from: Option<u64>,
    },
    Leave {
        session: SessionId,
    },
    Edit {
        session: SessionId,
        client_seq: u64,
        ops: Vec<EditOp>,
    },
    Camera {
        session: SessionId,
        eye: [f32; 3],
    },
    Resume {
        session: SessionId,
        since: u64,
    },
    /// Write a snapshot now (CLI, tests).
    Snapshot {
        done: oneshot::Sender<Result<(), String>>,
    },
    /// Apply what is queued, commit, snapshot, and stop.
    Shutdown,
}

/// Figures about a scene readable without asking the owner (for `/scenes` and `/metrics`).
#[derive(Default)]
pub struct SceneInfo {
    pub seq: AtomicU64,
    pub bricks: AtomicU64,
    pub voxels: AtomicU64,
    pub clients: AtomicU64,
    pub gpu_bytes: AtomicU64,
}

/// Knobs of a scene owner.
#[derive(Clone, Debug)]
pub struct OwnerConfig {
    pub limits: Limits,
    /// A session whose queue holds more than this many bytes is resynced instead of sent deltas.
    pub max_queue_bytes: usize,
}

impl Default for OwnerConfig {
    fn default() -> Self {
        OwnerConfig {
            limits: Limits::default(),
            max_queue_bytes: 32 << 20,
        }
    }
}

/// The handle sessions and the HTTP layer hold.
#[derive(Clone)]
pub struct SceneHandle {
    pub name: String,
    pub size: [u32; 3],
    pub limits: Limits,
    /// Queue bound of each session (see [`OwnerConfig::max_queue_bytes`]).
    pub max_queue_bytes: usize,
    pub info: Arc<SceneInfo>,
    tx: mpsc::Sender<Command>,
}

impl SceneHandle {
    /// Sends a command; fails only when the owner has stopped.
    pub async fn send(&self, cmd: Command) -> Result<(), SceneGone> {
        self.tx.send(cmd).await.map_err(|_| SceneGone)
    }

    pub fn try_send(&self, cmd: Command) -> Result<(), SceneGone> {
        self.tx.try_send(cmd).map_err(|_| SceneGone)
    }
}

/// A command sent to a scene whose owner thread has stopped (shutdown or a storage failure).
#[derive(Debug, thiserror::Error)]
#[error("the scene owner has stopped")]
pub struct SceneGone;

/// Per-session state the owner keeps.
struct Subscriber {
    out: Outbox,
    role: Role,
    camera: [f32; 3],
    /// Every change up to this sequence has been queued to the client.
    delivered: u64,
    /// Deltas stopped because the queue overflowed; resync from `delivered` once it drains.
    lagging: bool,
    /// Cells still to send in a sync, farthest first (the nearest is popped next).
    pending: Vec<u32>,
    sync_total: u32,
    sync_sent: u32,
    syncing: bool,
}

/// Starts the owner thread for a loaded scene.
pub fn spawn(
    name: String,
    loaded: crate::store::Loaded,
    store: Arc<Store>,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    runtime: tokio::runtime::Handle,
) -> std::io::Result<(SceneHandle, std::thread::JoinHandle<()>)> {
    let (tx, rx) = mpsc::channel(1024);
    let info = Arc::new(SceneInfo::default());
    let crate::store::Loaded {
        mut map,
        seq,
        replayed,
        replay_touched,
        ..
    } = loaded;
    map.set_sequence(seq);
    map.record_touched(true);
    let handle = SceneHandle {
        name: name.clone(),
        size: map.size(),
        limits: config.limits.clone(),
        max_queue_bytes: config.max_queue_bytes,
        info: info.clone(),
        tx,
    };
    let mut owner = Owner {
        name: name.clone(),
        map,
        seq,
        store,
        metrics,
        info,
        config,
        subs: HashMap::new(),
        encoder: BlobEncoder::new(ZSTD_LEVEL).map_err(std::io::Error::other)?,
        // Bricks the replayed log changed are not in the snapshot yet: the next snapshot must
        // write them before it trims the log that holds them.
        unsnapshotted: CellSet::from_cells(&replay_touched),
        log_entries: replayed,
        log_ops: 0,
        log_voxels: 0,
        last_snapshot_took: Duration::ZERO,
        last_snapshot: Instant::now(),
        rx,
        runtime,
    };
    owner.publish_info();
    let thread = std::thread::Builder::new().name(format!("scene-{name}")).spawn(move || {
        if let Err(e) = owner.run() {
            tracing::error!(scene = %owner.name, error = %e, "scene owner stopped on a storage error");
            owner.fail_all(&e.to_string());
        }
    })?;
    Ok((handle, thread))
}

/// One scene's owner thread: the authoritative map, its subscribers, and the bookkeeping the
/// next commit, delta and snapshot need.
struct Owner {
    name: String,
    map: BrickMap,
    seq: u64,
    store: Arc<Store>,
    metrics: Arc<Metrics>,
    info: Arc<SceneInfo>,
    config: OwnerConfig,
    subs: HashMap<SessionId, Subscriber>,
    encoder: BlobEncoder,
    /// Cells touched since the last snapshot (may repeat).
    unsnapshotted: CellSet,
    log_entries: u64,
    /// Ops and voxels changed in the log since the snapshot (replay cost).
    log_ops: u64,
    log_voxels: u64,
    /// How long the last snapshot took (see [`SNAPSHOT_SPACING`]).
    last_snapshot_took: Duration,
    last_snapshot: Instant,
    rx: mpsc::Receiver<Command>,
    runtime: tokio::runtime::Handle,
}

/// One edit batch waiting for its commit.
struct PendingAck {
    session: SessionId,
    client_seq: u64,
    seq: Option<u64>,
    applied: u32,
    rejected: Vec<OpRejection>,
}

impl Owner {
    fn run(&mut self) -> Result<(), crate::store::StoreError> {
        loop {
            // Wait briefly when a sync is waiting for a queue to drain, long when idle.
            let wait = if self.has_blocked_work() {
                Duration::from_millis(20)
            } else {
                Duration::from_secs(1)
            };
            let mut clock = PhaseClock::start();
            let first = if self.has_ready_work() {
                self.rx.try_recv().ok()
            } else {
                let runtime = self.runtime.clone();
                match runtime.block_on(async { tokio::time::timeout(wait, self.rx.recv()).await }) {
                    Ok(Some(cmd)) => Some(cmd),
                    Ok(None) => return self.stop(),
                    Err(_) => None,
                }
            };
            let mut commands: Vec<Command> = first.into_iter().collect();
            let mut ops = commands.iter().map(command_ops).sum::<usize>();
            while ops < MAX_OPS_PER_TURN {
                match self.rx.try_recv() {
                    Ok(cmd) => {
                        ops += command_ops(&cmd);
                        commands.push(cmd);
                    }
                    Err(_) => break,
                }
            }
            clock.mark(&self.metrics, OwnerPhase::Wait);
            let stop = self.turn(commands, &mut clock)?;
            self.pump_syncs();
            clock.mark(&self.metrics, OwnerPhase::Sync);
            self.maybe_snapshot(false)?;
            self.publish_info();
            clock.mark(&self.metrics, OwnerPhase::Snapshot);
            if stop {
                return self.stop();
            }
        }
    }

    /// Processes one group of commands, charging each phase's time to `clock`. Returns true on
    /// shutdown.
    fn turn(
        &mut self,
        commands: Vec<Command>,
        clock: &mut PhaseClock,
    ) -> Result<bool, crate::store::StoreError> {
        if !commands.is_empty() {
            Metrics::add(&self.metrics.owner_turns, 1);
        }
        let mut acks: Vec<PendingAck> = Vec::new();
        let mut log: Vec<(u64, Vec<EditOp>)> = Vec::new();
        let mut stop = false;
        let mut snapshot_requests = Vec::new();
        for cmd in commands {
            match cmd {
                Command::Edit {
                    session,
                    client_seq,
                    ops,
                } => {
                    let allowed = self
                        .subs
                        .get(&session)
                        .is_some_and(|s| s.role == Role::Editor);
                    acks.push(self.apply_batch(session, client_seq, ops, allowed, &mut log));
                }
                Command::Join {
                    session,
                    out,
                    role,
                    resume_from,
                } => self.join(session, out, role, resume_from),
                Command::Leave { session } => {
                    self.subs.remove(&session);
                }
                Command::Camera { session, eye } => {
                    if let Some(sub) = self.subs.get_mut(&session) {
                        sub.camera = eye;
                        let map = &self.map;
                        sort_far_to_near(map, &mut sub.pending, eye);
                    }
                }
                Command::Resume { session, since } => {
                    if let Some(sub) = self.subs.get_mut(&session) {
                        sub.delivered = since.min(self.seq);
                        sub.lagging = true;
                    }
                }
                Command::Snapshot { done } => snapshot_requests.push(done),
                Command::Shutdown => stop = true,
            }
        }
        clock.mark(&self.metrics, OwnerPhase::Apply);
        if !log.is_empty() {
            let started = Instant::now();
            let batches: Vec<(u64, &[EditOp])> =
                log.iter().map(|(s, ops)| (*s, ops.as_slice())).collect();
            self.store.append(&self.name, &batches)?;
            self.metrics.observe_commit(started.elapsed());
            self.log_entries += log.len() as u64;
        }
        clock.mark(&self.metrics, OwnerPhase::Commit);
        // Durable: acknowledge, then show everyone.
        for ack in acks {
            if let Some(sub) = self.subs.get(&ack.session) {
                let msg = ServerMsg::Ack {
                    client_seq: ack.client_seq,
                    seq: ack.seq,
                    applied: ack.applied,
                    rejected: ack.rejected,
                };
                if let Ok(frame) = encode_server(&msg) {
                    sub.out.push(Bytes::from(frame));
                }
            }
        }
        clock.mark(&self.metrics, OwnerPhase::Ack);
        self.broadcast_delta(clock);
        for done in snapshot_requests {
            let result = self.maybe_snapshot(true).map_err(|e| e.to_string());
            let _ = done.send(result);
        }
        clock.mark(&self.metrics, OwnerPhase::Snapshot);
        Ok(stop)
    }

    fn apply_batch(
        &mut self,
        session: SessionId,
        client_seq: u64,
        ops: Vec<EditOp>,
        allowed: bool,
        log: &mut Vec<(u64, Vec<EditOp>)>,
    ) -> PendingAck {
        let mut rejected = Vec::new();
        if !allowed {
            rejected = (0..ops.len() as u32)
                .map(|index| OpRejection {
                    index,
                    reason: Rejection::NotAllowed,
                })
                .collect();
            Metrics::add(&self.metrics.ops_rejected, ops.len() as u64);
            return PendingAck {
                session,
                client_seq,
                seq: None,
                applied: 0,
                rejected,
            };
        }
        let seq = self.seq + 1;
        self.map.set_sequence(seq);
        let mut applied = Vec::with_capacity(ops.len());
        let mut voxels = 0;
        for (index, op) in ops.into_iter().enumerate() {
            match apply_op(&mut self.map, &op, &self.config.limits) {
                Ok(n) => {
                    voxels += n;
                    applied.push(op);
                }
                Err(reason) => rejected.push(OpRejection {
                    index: index as u32,
                    reason,
                }),
            }
        }
        Metrics::add(&self.metrics.ops_rejected, rejected.len() as u64);
        Metrics::add(&self.metrics.ops_applied, applied.len() as u64);
        Metrics::add(&self.metrics.voxels_changed, voxels);
        let count = applied.len() as u32;
        let seq = if applied.is_empty() {
            None
        } else {
            // Only batches that applied something take a sequence number and a log entry; ops
            // that changed no voxel are still logged so replay matches op for op.
            self.seq = seq;
            self.log_ops += applied.len() as u64;
            self.log_voxels += voxels;
            Metrics::add(&self.metrics.edit_batches, 1);
            log.push((seq, applied));
            Some(seq)
        };
        PendingAck {
            session,
            client_seq,
            seq,
            applied: count,
            rejected,
        }
    }

    fn join(&mut self, session: SessionId, out: Outbox, role: Role, resume_from: Option<u64>) {
        let size = self.map.size();
        let camera = [size[0] as f32 * 0.5, size[1] as f32, size[2] as f32 * 0.5];
        let mut sub = Subscriber {
            out,
            role,
            camera,
            delivered: self.seq,
            lagging: false,
            pending: Vec::new(),
            sync_total: 0,
            sync_sent: 0,
            syncing: false,
        };
        // A resume is served as a resync from the client's sequence; anything else (or a
        // sequence from the future, i.e. another store) is a full sync.
        let (total, resume) = match resume_from {
            Some(since) if since <= self.seq => match self.map.changes_since(since) {
                Some(c) => (c.changed.len() as u32, Some(since)),
                None => (self.map.brick_count() as u32, None),
            },
            _ => (self.map.brick_count() as u32, None),
        };
        let welcome = ServerMsg::Welcome {
            protocol: PROTOCOL_VERSION,
            server: format!("brickcast-server {}", env!("CARGO_PKG_VERSION")),
            scene: self.name.clone(),
            size,
            seq: self.seq,
            role,
            limits: self.config.limits.clone(),
            total_bricks: total,
        };
        if let Ok(frame) = encode_server(&welcome) {
            sub.out.push(Bytes::from(frame));
        }
        match resume {
            Some(since) => {
                sub.delivered = since;
                self.start_resync(&mut sub, false);
            }
            None => {
                // A client that asked to resume holds a copy we cannot patch: tell it to drop it.
                if resume_from.is_some()
                    && let Ok(frame) = encode_server(&ServerMsg::Resync { since: 0 })
                {
                    sub.out.push(Bytes::from(frame));
                }
                sub.pending = self
                    .map
                    .brick_cells()
                    .map(|(c, _)| self.map.cell_index(c))
                    .collect();
                sort_far_to_near(&self.map, &mut sub.pending, sub.camera);
                sub.sync_total = sub.pending.len() as u32;
                sub.syncing = true;
            }
        }
        self.subs.insert(session, sub);
    }

    /// Queues what a client that has everything up to `sub.delivered` is missing: removals now,
    /// changed bricks through the sync pump.
    fn start_resync(&self, sub: &mut Subscriber, announce: bool) {
        let (since, changes) = match self.map.changes_since(sub.delivered) {
            Some(c) => (sub.delivered, c),
            None => (
                0,
                brickcast_protocol::map::Changes {
                    changed: self.map.brick_cells().map(|(c, _)| c).collect(),
                    removed: Vec::new(),
                },
            ),
        };
        // A client resuming from before the tombstone horizon must drop its copy: say so.
        let restart = since == 0 && sub.delivered != 0;
        if (announce || restart)
            && let Ok(frame) = encode_server(&ServerMsg::Resync { since })
        {
            sub.out.push(Bytes::from(frame));
        }
        for chunk in changes.removed.chunks(MAX_REMOVED_PER_FRAME) {
            let msg = ServerMsg::Delta {
                from_seq: since,
                to_seq: self.seq,
                bricks: BrickBlob::empty(),
                removed: chunk.to_vec(),
            };
            if let Ok(frame) = encode_server(&msg) {
                sub.out.push(Bytes::from(frame));
            }
        }
        // Keep what an interrupted sync had not sent yet: those bricks are still owed.
        let mut pending = std::mem::take(&mut sub.pending);
        pending.extend(changes.changed.iter().map(|&c| self.map.cell_index(c)));
        pending.sort_unstable();
        pending.dedup();
        sort_far_to_near(&self.map, &mut pending, sub.camera);
        sub.pending = pending;
        sub.sync_total = sub.pending.len() as u32;
        sub.sync_sent = 0;
        sub.syncing = true;
        sub.lagging = false;
        sub.delivered = self.seq;
    }

    /// Sends everything touched this turn to every subscriber that keeps up.
    fn broadcast_delta(&mut self, clock: &mut PhaseClock) {
        let touched = self.map.take_touched();
        if touched.is_empty() {
            return;
        }
        self.unsnapshotted.insert_all(&touched);
        let from = self.info.seq.load(Relaxed);
        let to = self.seq;
        let frames = match self.encode_cells(&touched, |bricks, removed| ServerMsg::Delta {
            from_seq: from,
            to_seq: to,
            bricks,
            removed,
        }) {
            Ok(frames) => frames,
            Err(e) => {
                tracing::error!(scene = %self.name, error = %e, "could not encode a delta");
                return;
            }
        };
        clock.mark(&self.metrics, OwnerPhase::Encode);
        let seq = self.seq;
        let bytes: usize = frames.iter().map(|f| f.len()).sum();
        for sub in self.subs.values_mut() {
            if sub.lagging {
                continue;
            }
            if sub.out.queued() + bytes > self.config.max_queue_bytes {
                sub.lagging = true;
                Metrics::add(&self.metrics.resyncs, 1);
                continue;
            }
            for frame in &frames {
                sub.out.push(frame.clone());
            }
            sub.delivered = seq;
            Metrics::add(&self.metrics.deltas_sent, frames.len() as u64);
        }
        clock.mark(&self.metrics, OwnerPhase::Fanout);
    }

    /// Encodes the current state of `cells` as frames: bricks that exist go in blobs cut to
    /// fit the frame limit, empty cells are listed as removed. `make` builds the message around
    /// each blob.
    fn encode_cells(
        &mut self,
        cells: &[u32],
        make: impl Fn(BrickBlob, Vec<[u32; 3]>) -> ServerMsg,
    ) -> Result<Vec<Bytes>, brickcast_protocol::wire::WireError> {
        let max_raw = (self.config.limits.max_frame_bytes as usize).saturating_sub(4096) / 2;
        let max_bricks = self.config.limits.max_bricks_per_frame;
        let mut frames = Vec::new();
        let mut removed = Vec::new();
        self.encoder.clear();
        let finish =
            |encoder: &mut BlobEncoder, removed: &mut Vec<[u32; 3]>, frames: &mut Vec<Bytes>| {
                let blob = encoder.finish()?;
                let msg = make(blob, std::mem::take(removed));
                frames.push(Bytes::from(encode_server(&msg)?));
                Ok::<(), brickcast_protocol::wire::WireError>(())
            };
        let map = &self.map;
        for &cell in cells {
            let coords = map.cell_coords(cell);
            match map.slot_of_cell(coords) {
                Some(slot) => {
                    // Straight from the map's arrays: a delta re-sends every brick it touched,
                    // and copying each into a `BrickData` first cost as much as compressing it.
                    let s = slot as usize;
                    let mask = &map.masks()[s];
                    let base = map.colour_bases()[s] as usize;
                    let colours = &map.colour_pool()[base..base + popcount(mask) as usize];
                    // Brick rows compress ~3x but may not; budget raw bytes against half the frame.
                    if self.encoder.len() >= max_bricks
                        || self.encoder.raw_len() + 70 + 2 * colours.len() > max_raw
                    {
                        finish(&mut self.encoder, &mut removed, &mut frames)?;
                    }
                    self.encoder.push(coords, mask, colours)?;
                }
                None => {
                    if removed.len() >= MAX_REMOVED_PER_FRAME {
                        finish(&mut self.encoder, &mut removed, &mut frames)?;
                    }
                    removed.push(coords);
                }
            }
        }
        if !self.encoder.is_empty() || !removed.is_empty() {
            finish(&mut self.encoder, &mut removed, &mut frames)?;
        }
        Ok(frames)
    }

    fn has_ready_work(&self) -> bool {
        let half = self.config.max_queue_bytes / 2;
        self.subs.values().any(|s| {
            (s.syncing && s.out.queued() < half)
                || (s.lagging && s.out.queued() < self.config.max_queue_bytes / 4)
        })
    }

    fn has_blocked_work(&self) -> bool {
        self.subs.values().any(|s| s.syncing || s.lagging)
    }

    /// Advances every sync (initial, resume, resync) by a bounded amount per turn, so edits keep
    /// flowing while a large scene streams out.
    fn pump_syncs(&mut self) {
        const FRAMES_PER_TURN: usize = 4;
        let ids: Vec<SessionId> = self.subs.keys().copied().collect();
        for id in ids {
            let Some(mut sub) = self.subs.remove(&id) else {
                continue;
            };
            if sub.lagging && sub.out.queued() < self.config.max_queue_bytes / 4 {
                self.start_resync(&mut sub, true);
            }
            let mut frames = 0;
            while sub.syncing
                && frames < FRAMES_PER_TURN
                && sub.out.queued() < self.config.max_queue_bytes / 2
            {
                let take =
                    (self.config.limits.max_bricks_per_frame as usize).min(sub.pending.len());
                let batch: Vec<u32> = sub.pending.split_off(sub.pending.len() - take);
                // Cells emptied since the sync began were already announced by a delta.
                let live: Vec<u32> = batch
                    .into_iter()
                    .filter(|&c| self.map.slot_of_cell(self.map.cell_coords(c)).is_some())
                    .collect();
                let sent_before = sub.sync_sent;
                let total = sub.sync_total;
                let count = live.len() as u32;
                match self.encode_cells(&live, |bricks, _| ServerMsg::SyncBatch {
                    bricks,
                    sent: sent_before + count,
                    total,
                }) {
                    Ok(batch_frames) => {
                        for f in batch_frames {
                            Metrics::add(&self.metrics.sync_batches_sent, 1);
                            sub.out.push(f);
                            frames += 1;
                        }
                    }
                    Err(e) => {
                        tracing::error!(scene = %self.name, error = %e, "could not encode a sync batch")
                    }
                }
                sub.sync_sent += count;
                if sub.pending.is_empty() {
                    sub.syncing = false;
                    if let Ok(frame) = encode_server(&ServerMsg::SyncDone { seq: self.seq }) {
                        sub.out.push(Bytes::from(frame));
                    }
                }
            }
            self.subs.insert(id, sub);
        }
    }

    fn maybe_snapshot(&mut self, force: bool) -> Result<(), crate::store::StoreError> {
        let since = self.last_snapshot.elapsed();
        let due = (self.replay_cost() >= SNAPSHOT_REPLAY_BUDGET
            && since >= self.last_snapshot_took * SNAPSHOT_SPACING)
            || (self.log_entries > 0 && since >= SNAPSHOT_EVERY);
        if !(force || due) {
            return Ok(());
        }
        let started = Instant::now();
        let cells = self.unsnapshotted.take_sorted();
        self.store.snapshot(&self.name, &self.map, &cells)?;
        tracing::debug!(scene = %self.name, seq = self.seq, entries = self.log_entries, bricks = cells.len(), took = ?started.elapsed(), "snapshot");
        self.log_entries = 0;
        self.log_ops = 0;
        self.log_voxels = 0;
        self.last_snapshot_took = started.elapsed();
        self.last_snapshot = Instant::now();
        Metrics::add(&self.metrics.snapshots, 1);
        if self.seq > TOMBSTONE_WINDOW {
            self.map.prune_tombstones(self.seq - TOMBSTONE_WINDOW);
        }
        Ok(())
    }

    /// What replaying the log since the snapshot would cost, in single-voxel ops.
    fn replay_cost(&self) -> u64 {
        self.log_ops + self.log_voxels / VOXELS_PER_OP_COST + self.log_entries * ENTRY_OP_COST
    }

    fn publish_info(&self) {
        self.info.seq.store(self.seq, Relaxed);
        self.info.bricks.store(self.map.brick_count(), Relaxed);
        self.info.voxels.store(self.map.solid_voxels(), Relaxed);
        self.info.clients.store(self.subs.len() as u64, Relaxed);
        self.info
            .gpu_bytes
            .store(self.map.memory().total_bytes, Relaxed);
    }

    fn stop(&mut self) -> Result<(), crate::store::StoreError> {
        // Apply and commit whatever is still queued, then leave a snapshot behind.
        let mut rest = Vec::new();
        while let Ok(cmd) = self.rx.try_recv() {
            rest.push(cmd);
        }
        self.turn(rest, &mut PhaseClock::start())?;
        if self.log_entries > 0 {
            self.maybe_snapshot(true)?;
        }
        tracing::info!(scene = %self.name, seq = self.seq, "scene owner stopped");
        Ok(())
    }

    /// Tells every session the scene is gone (after a storage failure).
    fn fail_all(&mut self, reason: &str) {
        let msg = ServerMsg::error(
            brickcast_protocol::wire::ErrorCode::Internal,
            format!("scene stopped: {reason}"),
        );
        if let Ok(frame) = encode_server(&msg) {
            let frame = Bytes::from(frame);
            for sub in self.subs.values() {
                sub.out.push(frame.clone());
            }
        }
        self.subs.clear();
    }
}

/// Linear cell indices, each once: the bricks a snapshot must rewrite. A bitset rather than a
/// list because under load the same cells are touched turn after turn between snapshots.
#[derive(Default)]
struct CellSet {
    bits: Vec<u64>,
    len: usize,
}

impl CellSet {
    fn from_cells(cells: &[u32]) -> CellSet {
        let mut set = CellSet::default();
        set.insert_all(cells);
        set
    }

    fn insert_all(&mut self, cells: &[u32]) {
        for &c in cells {
            let (word, bit) = ((c / 64) as usize, 1u64 << (c % 64));
            if word >= self.bits.len() {
                self.bits.resize(word + 1, 0);
            }
            if self.bits[word] & bit == 0 {
                self.bits[word] |= bit;
                self.len += 1;
            }
        }
    }

    /// The cells in ascending order; the set is left empty.
    fn take_sorted(&mut self) -> Vec<u32> {
        let mut out = Vec::with_capacity(self.len);
        for (w, word) in self.bits.iter_mut().enumerate() {
            let mut bits = std::mem::take(word);
            while bits != 0 {
                out.push(w as u32 * 64 + bits.trailing_zeros());
                bits &= bits - 1;
            }
        }
        self.len = 0;
        out
    }
}

fn command_ops(cmd: &Command) -> usize {
    match cmd {
        Command::Edit { ops, .. } => ops.len().max(1),
        _ => 1,
    }
}

/// Sorts linear cell indices by distance to `eye`, farthest first, so `pop` yields the nearest.
fn sort_far_to_near(map: &BrickMap, cells: &mut [u32], eye: [f32; 3]) {
    let key = |&c: &u32| {
        let p = map.cell_coords(c);
        let d: f32 = (0..3)
            .map(|i| (p[i] as f32 * 8.0 + 4.0 - eye[i]).powi(2))
            .sum();
        std::cmp::Reverse((d * 16.0) as u64)
    };
    cells.sort_unstable_by_key(key);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cell_set_keeps_each_cell_once_in_order() {
        let mut set = CellSet::from_cells(&[70, 3, 3, 200_000]);
        set.insert_all(&[64, 70, 0]);
        assert_eq!(set.len, 5);
        assert_eq!(set.take_sorted(), vec![0, 3, 64, 70, 200_000]);
        assert!(set.take_sorted().is_empty());
        set.insert_all(&[5]);
        assert_eq!(set.take_sorted(), vec![5]);
    }
}
