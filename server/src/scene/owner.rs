//! The scene owner's state and its turn: the only code that touches a scene's `BrickMap`.
//!
//! Why a plain state machine rather than the thread itself: the thread (in `mod.rs`) only waits
//! for commands and hands them over; everything that decides what is applied, logged,
//! acknowledged, snapshotted and sent lives here, takes its time from an injected clock, and
//! iterates sessions in a fixed order. The deterministic simulation test (`crate::sim`) drives
//! this same code turn by turn against a simulated disk, crashes it anywhere, and replays a
//! failing seed exactly.
//!
//! **The sequence.** The owner's `seq` is the one source of truth: the last sequence number
//! given to a batch that applied something. The map is stamped with `seq + 1` only once a batch
//! has an op that will apply (ops are resolved before anything changes), so the map's stamp
//! never runs ahead of the owner, and a snapshot records the owner's `seq` (the store refuses
//! one whose map stamp or log disagrees with it).

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use brickcast_protocol::BrickMap;
use brickcast_protocol::apply::{Resolved, apply_resolved, resolve};
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::{
    BlobEncoder, BrickBlob, EditOp, OpRejection, Refusal, Rejection, Role, ServerMsg, encode_server,
};
use bytes::Bytes;

use super::answered::Answered;
use super::cells::CellSet;
use super::durable::Durability;
use super::history::{Direction, History, Image, Step, plan_revert, write_planned};
use super::jobs::{Job, Jobs};
use super::log::{LogError, OwnedTurn, SceneLog, SnapshotOf};
use super::request::Outcome;
use super::undo_job::UndoJob;
use super::{Clock, Command, Described, OwnerConfig, SceneInfo, SessionId, Subscriber};
use crate::bucket::Bucket;
use crate::metrics::{Metrics, OwnerPhase, PhaseClock};
use crate::record::{LogRecord, REVERT_BRICK_OPS};
use crate::store::{Loaded, Store, StoreLog};

/// Voxels visited per single-voxel op of replay time (~10 ns per brushed voxel against ~300 ns
/// per op).
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
/// Keep tombstones for at least this many sequence numbers: a client that reconnects within that
/// window resumes with a delta instead of a full resync.
const TOMBSTONE_WINDOW: u64 = 1_000_000;
/// zstd level for deltas and sync batches: level 1 compresses at ~280 MiB/s raw on one core.
pub(super) const ZSTD_LEVEL: i32 = 1;
/// A queue this short keeps getting deltas even when the server as a whole holds too much:
/// clients that keep up are not punished for the ones that do not.
pub(super) const SHORT_QUEUE: usize = 256 << 10;

/// One scene's authoritative map, its subscribers, and the bookkeeping the next commit, delta
/// and snapshot need.
pub struct Owner {
    pub(super) name: String,
    pub(super) map: BrickMap,
    /// The last sequence number given to a batch that applied something.
    pub(super) seq: u64,
    /// Where turns are made durable: the only store the owner knows.
    pub(super) log: Box<dyn SceneLog>,
    pub(super) metrics: Arc<Metrics>,
    pub(super) info: Arc<SceneInfo>,
    pub(super) config: OwnerConfig,
    /// Sessions in id order, so every turn visits them in the same order.
    pub(super) subs: BTreeMap<SessionId, Subscriber>,
    pub(super) encoder: BlobEncoder,
    /// Encoders of the other threads a large delta is encoded on (`sync::encode_cells`).
    pub(super) spare_encoders: Vec<BlobEncoder>,
    /// Woken by a session's writer taking a frame while its sync streams (`sync.rs`: syncs
    /// are queued only [`super::sync::SYNC_AHEAD`] ahead of the writer).
    pub(super) wake: Arc<tokio::sync::Notify>,
    /// Bytes a brick took in the last sync batch: sizes the next (`sync.rs`).
    pub(super) sync_brick_bytes: usize,
    /// The sequence of the last delta broadcast (its successor's `from_seq`).
    pub(super) broadcast_seq: u64,
    /// The palette every session has heard (in its `Palette` after the `Welcome`, or since):
    /// a turn that leaves the map's palette otherwise sends it to everyone.
    pub(super) broadcast_swatches: Swatches,
    /// The last session whose sync got frames: the next turn serves those after it first.
    pub(super) sync_cursor: SessionId,
    /// Cells touched since the last snapshot.
    pub(super) unsnapshotted: CellSet,
    pub(super) log_entries: u64,
    /// Ops in the log since the snapshot, and the work replaying them costs (voxels visited,
    /// `EditOp::work`): what recovery would spend.
    pub(super) log_ops: u64,
    pub(super) log_work: u64,
    /// How long the last snapshot took (see [`SNAPSHOT_SPACING`]).
    last_snapshot_took: Duration,
    last_snapshot: Instant,
    pub(super) clock: Clock,
    /// Every user's undo and redo stacks.
    pub(super) history: History,
    /// Undo work each user may still ask for (voxels compared), and when it was counted: undo
    /// and redo are charged like edits, by what they cost, on the owner's clock.
    pub(super) undo_budget: HashMap<u64, Bucket>,
    /// Shutting down: a lost lease is not followed by a reload.
    pub(super) stopping: bool,
    /// Requests from other origins answered so far (a shared log: a retry is answered from
    /// here, not applied again).
    pub(super) answered: Answered,
    /// The requests from other origins applied in this turn, waiting for its commit.
    pub(super) requests: Vec<Remote>,
    /// The log cannot be followed (cluster): the owner stops after this turn, and the scene
    /// is served again only from a fresh load.
    pub(super) broken: bool,
    /// Large undos and redos and heavy edits being planned across turns, first one first
    /// (`jobs.rs`).
    pub(super) jobs: Jobs,
    /// Commands that waited behind a finished job: the next turn applies them first.
    pub(super) released: Vec<Command>,
    /// The levels of detail, once a session views one (`levels.rs`).
    pub(super) levels: super::levels::Levels,
    /// Which turns handed to the log are durable: every session's frames wait on it.
    pub(super) durability: Arc<Durability>,
    /// Commands wait behind this turn ([`Owner::set_backlog`]).
    backlog: bool,
}

/// A reply (`Ack` or `Undone`) waiting for the commit of what it reports.
pub(super) struct PendingAck {
    pub(super) to: AckTo,
    pub(super) msg: ServerMsg,
}

/// Who a reply goes to: a session of this owner, or a request from another origin (its index
/// in [`Owner::requests`]).
#[derive(Clone, Copy, Debug)]
pub(super) enum AckTo {
    Session(SessionId),
    Remote(usize),
}

/// A request from another origin waiting for its turn's commit: its origin and number (logged
/// with the turn, `answered.rs`), where its answer goes, and its replies so far.
#[derive(Debug)]
pub(super) struct Remote {
    pub(super) origin: String,
    pub(super) number: u64,
    pub(super) reply: Option<tokio::sync::oneshot::Sender<Outcome>>,
    pub(super) replies: Vec<Vec<u8>>,
}

/// Who asked for an undo (or redo), and how to answer them.
#[derive(Clone, Copy, Debug)]
pub(super) struct UndoAsk {
    pub(super) to: AckTo,
    pub(super) client_seq: u64,
    pub(super) redo: bool,
}

impl UndoAsk {
    /// The stack the step comes from.
    pub(super) fn direction(&self) -> Direction {
        if self.redo {
            Direction::Redo
        } else {
            Direction::Undo
        }
    }

    pub(super) fn reply(
        &self,
        seq: Option<u64>,
        restored: u64,
        kept: u64,
        refused: Option<Refusal>,
    ) -> PendingAck {
        PendingAck {
            to: self.to,
            msg: ServerMsg::Undone {
                client_seq: self.client_seq,
                redo: self.redo,
                seq,
                restored,
                kept,
                refused,
            },
        }
    }

    /// Refused for `reason` (counted).
    pub(super) fn refuse(&self, metrics: &Metrics, reason: Refusal) -> PendingAck {
        Metrics::add(&metrics.history_refused, 1);
        self.reply(None, 0, 0, Some(reason))
    }

    /// Refused: there is no step to undo (any more).
    pub(super) fn nothing(&self, metrics: &Metrics) -> PendingAck {
        let nothing = if self.redo {
            Refusal::NothingToRedo
        } else {
            Refusal::NothingToUndo
        };
        self.refuse(metrics, nothing)
    }
}

/// An undo or redo planned against the map and recorded, ready to apply.
pub(super) struct Reverted {
    pub(super) user: u64,
    pub(super) redo: bool,
    /// Cells whose brick changes, with the brick they get, frame by frame.
    pub(super) writes: Vec<Vec<(u32, Option<Image>)>>,
    /// The stored form of the undo's record, and its bricks.
    pub(super) record: Vec<u8>,
    pub(super) bricks: usize,
    pub(super) restored: u64,
    pub(super) kept: u64,
}

/// What this turn logs, in order.
pub(super) type Log = Vec<(u64, LogRecord)>;

pub(super) fn ack(
    to: AckTo,
    client_seq: u64,
    seq: Option<u64>,
    applied: u32,
    rejected: Vec<OpRejection>,
) -> PendingAck {
    PendingAck {
        to,
        msg: ServerMsg::Ack {
            client_seq,
            seq,
            applied,
            rejected,
        },
    }
}

/// The answer to a message of one op refused for `reason`, counted as a rejected op.
pub(super) fn refuse_one(
    metrics: &Metrics,
    to: AckTo,
    client_seq: u64,
    reason: Rejection,
) -> PendingAck {
    Metrics::add(&metrics.ops_rejected, 1);
    ack(
        to,
        client_seq,
        None,
        0,
        vec![OpRejection { index: 0, reason }],
    )
}

impl Owner {
    /// An owner for a scene recovered from the store. `clock` is where every decision that
    /// depends on time (when to snapshot) reads the time.
    pub fn new(
        name: String,
        loaded: Loaded,
        store: Arc<Store>,
        metrics: Arc<Metrics>,
        config: OwnerConfig,
        clock: Clock,
    ) -> std::io::Result<Owner> {
        let log = Box::new(StoreLog::new(store, name.clone()));
        Owner::with_log(name, loaded, log, metrics, config, clock)
    }

    /// An owner over any [`SceneLog`]: the redb store, or a cluster's JetStream stream.
    pub fn with_log(
        name: String,
        loaded: Loaded,
        log: Box<dyn SceneLog>,
        metrics: Arc<Metrics>,
        config: OwnerConfig,
        clock: Clock,
    ) -> std::io::Result<Owner> {
        let Loaded {
            mut map,
            seq,
            replayed,
            replay_touched,
            history,
            last_step_id,
            answered,
            ..
        } = loaded;
        let history = History::new(
            history,
            last_step_id,
            config.limits.max_undo_steps,
            config.limits.max_undo_bytes,
        )
        .with_scene_cap(config.max_history_bytes);
        map.set_sequence(seq);
        map.record_touched(true);
        let now = clock();
        let broadcast_swatches = *map.swatches();
        let mut owner = Owner {
            name,
            map,
            seq,
            log,
            metrics,
            info: Arc::new(SceneInfo::default()),
            config,
            subs: BTreeMap::new(),
            encoder: BlobEncoder::new(ZSTD_LEVEL).map_err(std::io::Error::other)?,
            spare_encoders: Vec::new(),
            wake: Arc::default(),
            sync_brick_bytes: 256,
            broadcast_seq: seq,
            broadcast_swatches,
            sync_cursor: 0,
            // Bricks the replayed log changed are not in the snapshot yet: the next snapshot
            // must write them before it trims the log that holds them.
            unsnapshotted: CellSet::from_cells(&replay_touched),
            log_entries: replayed,
            log_ops: 0,
            log_work: 0,
            last_snapshot_took: Duration::ZERO,
            last_snapshot: now,
            clock,
            history,
            undo_budget: HashMap::new(),
            stopping: false,
            answered: Answered::from_entries(answered),
            requests: Vec::new(),
            broken: false,
            jobs: Jobs::new(),
            released: Vec::new(),
            levels: super::levels::Levels::default(),
            durability: Arc::default(),
            backlog: false,
        };
        if owner.map.memory().total_bytes > owner.config.eager_levels_bytes {
            owner.start_levels_now();
        }
        owner.publish_info();
        Ok(owner)
    }

    /// Starts building the levels of detail before anyone asks (a scene too large for a
    /// viewer to hold whole); a failure is logged and the levels are tried again when asked.
    fn start_levels_now(&mut self) {
        match self.levels.start(&self.map, self.seq) {
            Ok(()) => tracing::info!(scene = %self.name, "building the levels of detail at load"),
            Err(e) => {
                tracing::error!(scene = %self.name, error = %e, "could not build the levels of detail");
                self.levels = super::levels::Levels::default();
            }
        }
    }

    /// The scene's sequence number (the last batch that applied something).
    pub fn seq(&self) -> u64 {
        self.seq
    }

    /// The position in its log of the last turn applied (a shared log; 0 otherwise).
    pub fn position(&self) -> u64 {
        self.log.position()
    }

    /// The authoritative map.
    pub fn map(&self) -> &BrickMap {
        &self.map
    }

    /// Every user's undo and redo stacks.
    /// The committed scene from its first camera (`viewpoint::find`, as a viewer opens it),
    /// traced on this thread (one core, a few milliseconds at thumbnail size; the scene list
    /// caches it per sequence number).
    pub fn history(&self) -> &History {
        &self.history
    }

    /// Figures readable without asking the owner.
    pub fn info(&self) -> Arc<SceneInfo> {
        self.info.clone()
    }

    /// One turn: processes `commands` in order (edits applied, logged in one durable commit,
    /// then acknowledged and broadcast as one delta), advances every sync, snapshots when due.
    /// `clock` is charged each phase's time. Returns true when a `Shutdown` was among the
    /// commands.
    pub fn step(
        &mut self,
        commands: Vec<Command>,
        clock: &mut PhaseClock,
    ) -> Result<bool, LogError> {
        let commands = if self.released.is_empty() {
            commands
        } else {
            // Commands that waited behind an undo arrived before these.
            let mut all = std::mem::take(&mut self.released);
            all.extend(commands);
            all
        };
        // A commit handed over in an earlier turn that failed stops the scene.
        if let Err(e) = self.log.failed() {
            self.durability.fail();
            return Err(e);
        }
        let stop = self.turn(commands, clock)? || self.broken;
        self.advance_levels();
        self.pump_syncs();
        clock.mark(&self.metrics, OwnerPhase::Sync);
        self.maybe_snapshot(false)?;
        self.publish_info();
        clock.mark(&self.metrics, OwnerPhase::Snapshot);
        Ok(stop)
    }

    /// Whether commands are waiting behind this turn (set by the owner thread before each
    /// step): then the turn's commit is handed over to run while the next turn applies;
    /// otherwise the owner commits it itself, as fast as a hand-over and with fewer threads
    /// between the fsync and the ack (on two shared cores, each hop is a scheduling delay).
    pub fn set_backlog(&mut self, backlog: bool) {
        self.backlog = backlog;
    }

    /// Processes one group of commands. Returns true on shutdown.
    ///
    /// Edits are applied in order and committed together; what a join or resume shows its
    /// client (the Welcome's sequence, removals, bricks) must already be durable, so one of
    /// those after uncommitted edits first commits and publishes them.
    fn turn(&mut self, commands: Vec<Command>, clock: &mut PhaseClock) -> Result<bool, LogError> {
        if !commands.is_empty() {
            Metrics::add(&self.metrics.owner_turns, 1);
        }
        let mut acks: Vec<PendingAck> = Vec::new();
        let mut log: Log = Vec::new();
        let mut stop = false;
        let mut snapshot_requests = Vec::new();
        let mut cameras = BTreeMap::new();
        for cmd in commands {
            match cmd {
                Command::Edit {
                    session,
                    client_seq,
                    ops,
                    admitted,
                } => {
                    let user = self.subs.get(&session).map(|s| s.user);
                    if let Some(waiting) = user.and_then(|u| self.waiting_behind(u)) {
                        // After the user's job that is still being planned.
                        waiting.push(Command::Edit {
                            session,
                            client_seq,
                            ops,
                            admitted,
                        });
                        continue;
                    }
                    let editor = self
                        .subs
                        .get(&session)
                        .filter(|s| s.role == Role::Editor)
                        .map(|s| s.user);
                    let to = AckTo::Session(session);
                    // A heavy edit is planned across turns and answered when applied.
                    if let Some((ops, admitted)) =
                        self.slice_edit(to, client_seq, ops, editor, admitted)
                    {
                        acks.push(self.apply_batch(to, client_seq, ops, editor, &mut log));
                        // Applied: the next heavy edit may queue.
                        drop(admitted);
                    }
                }
                Command::Undo {
                    session,
                    client_seq,
                    redo,
                } => {
                    if let Some(sub) = self.subs.get(&session) {
                        let (user, editor) = (sub.user, sub.role == Role::Editor);
                        if let Some(waiting) = self.waiting_behind(user) {
                            waiting.push(Command::Undo {
                                session,
                                client_seq,
                                redo,
                            });
                            continue;
                        }
                        let to = AckTo::Session(session);
                        acks.extend(self.undo(to, user, editor, client_seq, redo, &mut log));
                    }
                }
                Command::Request { request, reply } => {
                    if self.pending_request(&request) {
                        self.publish(&mut log, &mut acks, clock)?;
                    }
                    self.request(reply, request, &mut acks, &mut log);
                }
                Command::Apply { pos, turn } => {
                    // What is already applied was published; apply the rest in order.
                    self.publish(&mut log, &mut acks, clock)?;
                    self.replicate(pos, *turn);
                }
                Command::Lead { done } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    let _ = done.send(self.take_over());
                }
                Command::Follow { why } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    self.step_down(&why);
                }
                Command::Behind { first } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    self.behind(first);
                }
                Command::Fault { why } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    self.refuse_log(&why);
                }
                Command::Describe { done } => {
                    // Only what is committed is described.
                    self.publish(&mut log, &mut acks, clock)?;
                    self.log.flush()?;
                    let _ = done.send(Described {
                        seq: self.seq,
                        hash: self.map.content_hash(),
                        position: self.log.position(),
                        leading: self.log.shared() && self.log.may_order(),
                        clients: self.subs.len() as u64,
                    });
                }
                Command::Join {
                    session,
                    out,
                    role,
                    resume_from,
                    level,
                    budget,
                    who,
                    joined,
                } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    let wants = super::sync::Wants {
                        resume_from,
                        level,
                        budget,
                    };
                    if self.join(session, out, role, wants, who) {
                        let _ = joined.send(());
                    }
                }
                Command::Leave { session } => {
                    if let Some(sub) = self.subs.remove(&session) {
                        // In a cluster the session asks the owner to forget (forwarded).
                        if !sub.stable && !self.log.shared() {
                            self.history.forget(sub.user);
                        }
                        if !self.subs.values().any(|s| s.user == sub.user) {
                            self.undo_budget.remove(&sub.user);
                        }
                    }
                    cameras.remove(&session);
                }
                // Only the latest camera of a session counts: one re-sort per session and turn.
                Command::Camera { session, eye } => {
                    cameras.insert(session, eye);
                }
                Command::Resume { session, since } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    if let Some(sub) = self.subs.get_mut(&session) {
                        sub.delivered = since.min(self.seq);
                        sub.lagging = true;
                    }
                }
                Command::Snapshot { done } => snapshot_requests.push(done),
                Command::Thumbnail { done } => {
                    // Only what is committed is shown.
                    self.publish(&mut log, &mut acks, clock)?;
                    self.log.flush()?;
                    let _ = done.send((self.seq, Box::new(self.map.clone())));
                }
                Command::Shutdown => stop = true,
                Command::Farewell { code, text } => {
                    self.publish(&mut log, &mut acks, clock)?;
                    self.log.flush()?;
                    for sub in self.subs.values() {
                        sub.out.close(code, text.clone());
                    }
                }
            }
        }
        self.publish(&mut log, &mut acks, clock)?;
        if !self.jobs.is_empty() {
            // A frame of the first job, or its last turn (published on its own).
            let released = self.advance_jobs(&mut log, &mut acks, self.stopping);
            self.released.extend(released);
            self.publish(&mut log, &mut acks, clock)?;
        }
        clock.mark(&self.metrics, OwnerPhase::Snapshot);
        for (session, eye) in cameras {
            self.camera(session, eye);
        }
        clock.mark(&self.metrics, OwnerPhase::Follow);
        for done in snapshot_requests {
            let result = self.maybe_snapshot(true).map_err(|e| e.to_string());
            let _ = done.send(result);
        }
        clock.mark(&self.metrics, OwnerPhase::Snapshot);
        Ok(stop)
    }

    /// Makes the edits applied so far durable (one commit for all of them), then acknowledges
    /// them and shows everyone the delta, in that order: nobody hears of an edit a crash
    /// could still lose.
    fn publish(
        &mut self,
        log: &mut Log,
        acks: &mut Vec<PendingAck>,
        clock: &mut PhaseClock,
    ) -> Result<(), LogError> {
        clock.mark(&self.metrics, OwnerPhase::Apply);
        // Replies to requests from other origins, encoded now: a shared log records them with
        // the turn.
        self.take_remote(acks);
        let answered = self.answered_entries();
        if !log.is_empty() || self.history.has_writes() || !answered.is_empty() {
            let started = Instant::now();
            let entries = log.len() as u64;
            let turn = OwnedTurn {
                records: std::mem::take(log),
                history: self.history.take_writes(),
                answered,
            };
            // What is queued for sessions from here on waits for this turn's commit
            // (`durable.rs`), so the next turn need not.
            let ticket = self.durability.next();
            let handed = if self.backlog {
                self.log.submit(turn, ticket, &self.durability)
            } else {
                // In this thread (after what is still being committed).
                self.log.append(turn.as_write()).map(|()| {
                    self.durability.durable_to(ticket);
                    true
                })
            };
            match handed {
                Ok(committed) => {
                    if committed {
                        self.metrics.observe_commit(started.elapsed());
                    }
                }
                Err(e) if !self.log.shared() => {
                    self.durability.fail();
                    return Err(e);
                }
                Err(e) => {
                    // An owner that lost the scene: nothing of this turn is acknowledged (and
                    // nothing was queued under its ticket), and the map goes back to what the
                    // log holds.
                    self.durability.durable_to(ticket);
                    acks.clear();
                    self.lost_lead(&e);
                    return Ok(());
                }
            }
            self.log_entries += entries;
        }
        clock.mark(&self.metrics, OwnerPhase::Commit);
        for ack in acks.drain(..) {
            if let AckTo::Session(id) = ack.to
                && let Some(sub) = self.subs.get(&id)
            {
                sub.out.send(&ack.msg, &self.metrics);
            }
        }
        self.answer_remote();
        clock.mark(&self.metrics, OwnerPhase::Ack);
        self.broadcast_delta(clock);
        Ok(())
    }

    /// Applies one edit message. Every op is resolved (validated, ray traced) before it
    /// changes anything, so the map is stamped with the batch's sequence only once an op is
    /// certain to apply: a batch whose every op is rejected leaves the map and the sequence as
    /// they were.
    ///
    /// `editor` is the user whose history records the batch (`None`: the session may not edit).
    pub(super) fn apply_batch(
        &mut self,
        to: AckTo,
        client_seq: u64,
        ops: Vec<EditOp>,
        editor: Option<u64>,
        log: &mut Log,
    ) -> PendingAck {
        let mut rejected = Vec::new();
        let Some(user) = editor else {
            rejected = (0..ops.len() as u32)
                .map(|index| OpRejection {
                    index,
                    reason: Rejection::NotAllowed,
                })
                .collect();
            Metrics::add(&self.metrics.ops_rejected, ops.len() as u64);
            return ack(to, client_seq, None, 0, rejected);
        };
        if let [op @ EditOp::Paste { .. }] = ops[..] {
            return self.apply_paste(to, client_seq, user, op, log);
        }
        if let [op @ EditOp::Restore { .. }] = ops[..] {
            return self.apply_restore(to, client_seq, user, op, log);
        }
        let seq = self.seq + 1;
        self.map.begin_journal();
        let size = self.map.size();
        let mut applied = Vec::with_capacity(ops.len());
        let mut voxels = 0;
        let mut work = 0u64;
        for (index, op) in ops.into_iter().enumerate() {
            match resolve(&self.map, &op, &self.config.limits) {
                Ok(resolved) => {
                    if applied.is_empty() {
                        self.map.set_sequence(seq);
                    }
                    if let Resolved::Copy { min, max } = resolved {
                        self.copy_to_clipboard(user, min, max);
                    }
                    voxels += apply_resolved(&mut self.map, resolved);
                    work = work.saturating_add(op.work(size));
                    applied.push(op);
                }
                Err(reason) => rejected.push(OpRejection {
                    index: index as u32,
                    reason,
                }),
            }
        }
        let step = Step::from_journal(&mut self.map);
        Metrics::add(&self.metrics.ops_rejected, rejected.len() as u64);
        Metrics::add(&self.metrics.ops_applied, applied.len() as u64);
        Metrics::add(&self.metrics.voxels_changed, voxels);
        let count = applied.len() as u32;
        let seq = if applied.is_empty() {
            None
        } else {
            // Only batches that applied something take a sequence number and a log entry; ops
            // that changed no voxel are still logged so replay matches op for op. The message
            // is one step of its user's history, even if it changed nothing: one gesture, one
            // undo. A message that only set swatches or copied is none (it changed no voxel
            // and leaves what could be redone).
            if applied.iter().any(|op| !op.keeps_voxels()) {
                self.history.record_edit(user, &step);
            }
            self.seq = seq;
            self.log_ops += applied.len() as u64;
            self.log_work = self.log_work.saturating_add(work);
            Metrics::add(&self.metrics.edit_batches, 1);
            log.push((seq, LogRecord::Ops { user, ops: applied }));
            Some(seq)
        };
        ack(to, client_seq, seq, count, rejected)
    }

    /// Undoes (or redoes) the session's user's latest step: see `history.rs` for the rule. The
    /// bricks it writes take the next sequence number and are logged as a `Revert` record;
    /// the history change commits with them. `editor`: whether the user may edit. `None`: the
    /// undo is planned across turns (`undo_job.rs`) and answered when it is applied.
    pub(super) fn undo(
        &mut self,
        to: AckTo,
        user: u64,
        editor: bool,
        client_seq: u64,
        redo: bool,
        log: &mut Log,
    ) -> Option<PendingAck> {
        let ask = UndoAsk {
            to,
            client_seq,
            redo,
        };
        let direction = ask.direction();
        if !editor {
            return Some(ask.refuse(&self.metrics, Refusal::NotAllowed));
        }
        // Charged by the bricks the step changed (each compared voxel by voxel), against the
        // same per-second work budget as edits, refilled on the owner's clock.
        let Some(top) = self.history.peek(user, direction) else {
            return Some(ask.nothing(&self.metrics));
        };
        let cost = f64::from(top.bricks) * 512.0;
        let budget = &self.config.budget;
        let (rate, burst) = (
            budget.max_work_per_second as f64,
            budget.max_work_per_second.max(budget.max_work_per_edit) as f64,
        );
        let now = (self.clock)();
        let bucket = self
            .undo_budget
            .entry(user)
            .or_insert_with(|| Bucket::new_at(rate, burst, now));
        // A step bigger than the whole burst still goes when the bucket is full.
        if !bucket.take_at(cost.min(burst), now) {
            return Some(ask.refuse(&self.metrics, Refusal::RateLimited));
        }
        if self.may_slice(to) && top.bricks >= self.config.slice_bricks {
            // Planned across turns, answered when applied.
            self.jobs.push_back(Job::Undo(UndoJob::new(ask, user)));
            return None;
        }
        let store = &self.log;
        let popped = self.history.pop(user, direction, |id| {
            store.history_step(id).map_err(|e| e.to_string())
        });
        let step = match popped {
            Ok(Some(step)) => step,
            Ok(None) => return Some(ask.nothing(&self.metrics)),
            Err(e) => {
                // The step is gone from the stack either way; say so rather than stop the scene.
                tracing::error!(scene = %self.name, user, error = %e, "an undo step could not be read; it is dropped");
                return Some(ask.nothing(&self.metrics));
            }
        };
        let revert = plan_revert(&self.map, &step);
        let record = self.history.push_record(user, direction, &revert.record);
        let (restored, kept) = (revert.restored, revert.kept);
        let seq = self.apply_revert(
            Reverted {
                user,
                redo,
                bricks: revert.record.bricks.len(),
                writes: vec![revert.writes],
                record,
                restored,
                kept,
            },
            log,
        );
        Some(ask.reply(seq, restored, kept, None))
    }

    /// Applies a planned and recorded undo (or redo): writes its bricks, logs it as its record
    /// (when it changed anything: it then takes the next sequence) and counts it. Returns its
    /// sequence.
    pub(super) fn apply_revert(&mut self, r: Reverted, log: &mut Log) -> Option<u64> {
        let mut seq = None;
        if r.writes.iter().any(|w| !w.is_empty()) {
            let next = self.seq + 1;
            self.map.set_sequence(next);
            if let Err(e) = write_planned(&mut self.map, r.writes.into_iter().flatten()) {
                // Planned from this map's own bricks: cannot happen.
                tracing::error!(scene = %self.name, error = %e, "an undo wrote a brick the map refused");
            }
            self.seq = next;
            self.log_ops += r.bricks as u64 * REVERT_BRICK_OPS;
            log.push((
                next,
                LogRecord::Revert {
                    user: r.user,
                    redo: r.redo,
                    bricks: r.bricks.min(u32::MAX as usize) as u32,
                    step: r.record,
                },
            ));
            seq = Some(next);
        }
        let counter = if r.redo {
            &self.metrics.redos
        } else {
            &self.metrics.undos
        };
        Metrics::add(counter, 1);
        Metrics::add(&self.metrics.undo_voxels_restored, r.restored);
        Metrics::add(&self.metrics.undo_voxels_kept, r.kept);
        seq
    }

    /// Sends everything touched this turn to every subscriber that keeps up. A turn that
    /// moved the sequence without changing a voxel (ops that cleared air) still sends an empty
    /// delta: clients learn every sequence an ack can name, and resume from it.
    fn broadcast_delta(&mut self, clock: &mut PhaseClock) {
        let touched = self.map.take_touched();
        self.note_touched(&touched);
        let from = self.broadcast_seq;
        let to = self.seq;
        if touched.is_empty() && to == from {
            return;
        }
        self.broadcast_seq = to;
        // Before the turn's delta, so a copy that has the delta has the palette of its sequence.
        self.broadcast_palette();
        self.unsnapshotted.insert_all(&touched);
        // The levels of detail follow the map before anyone hears of the turn.
        let changed = match self.levels.update(&self.map, &touched) {
            Ok(changed) => changed,
            Err(e) => {
                tracing::error!(scene = %self.name, error = %e, "could not update the levels of detail; building them again");
                self.restart_levels();
                Default::default()
            }
        };
        clock.mark(&self.metrics, OwnerPhase::Apply);
        let mut viewed: Vec<u32> = self
            .subs
            .values()
            .filter(|s| s.awaits_levels.is_none() && s.follow.is_none())
            .map(|s| s.level)
            .collect();
        viewed.sort_unstable();
        viewed.dedup();
        if viewed.is_empty() && !self.subs.values().any(|s| s.follow.is_some()) {
            viewed.push(0);
        }
        for level in viewed {
            let cells = match level {
                0 => &touched[..],
                k => changed.get(k as usize - 1).map_or(&[][..], |c| &c[..]),
            };
            self.broadcast_level(level, cells, from, to, clock);
        }
        self.broadcast_follow(&touched, &changed, from, to);
        clock.mark(&self.metrics, OwnerPhase::Fanout);
    }

    /// Sends every session the palette when this turn (or a reload) changed it, queued with
    /// the turn's frames (so it waits for the same commit).
    pub(super) fn broadcast_palette(&mut self) {
        let swatches = *self.map.swatches();
        if swatches == self.broadcast_swatches {
            return;
        }
        self.broadcast_swatches = swatches;
        let msg = ServerMsg::Palette { swatches };
        for sub in self.subs.values_mut() {
            sub.out.send(&msg, &self.metrics);
        }
    }

    /// Sends the subscribers viewing `level` its cells that changed from sequence `from` to
    /// `to` (an empty delta when none did).
    fn broadcast_level(
        &mut self,
        level: u32,
        cells: &[u32],
        from: u64,
        to: u64,
        clock: &mut PhaseClock,
    ) {
        let make = |bricks, removed| ServerMsg::Delta {
            from_seq: from,
            to_seq: to,
            bricks,
            removed,
        };
        let encoded = if cells.is_empty() {
            encode_server(&make(BrickBlob::empty(), Vec::new())).map(|f| vec![Bytes::from(f)])
        } else {
            self.encode_cells(level, cells, make)
        };
        let frames = match encoded {
            Ok(frames) => frames,
            Err(e) => {
                // Nobody can be sent this turn's changes: every subscriber resyncs from what it
                // had, which re-encodes the bricks in smaller sync batches.
                tracing::error!(scene = %self.name, error = %e, level, "could not encode a delta; resyncing every client");
                self.metrics.count_unencodable("Delta");
                for sub in self
                    .subs
                    .values_mut()
                    .filter(|s| s.level == level && s.follow.is_none())
                {
                    if !sub.lagging {
                        sub.lagging = true;
                        Metrics::add(&self.metrics.resyncs, 1);
                    }
                }
                return;
            }
        };
        clock.mark(&self.metrics, OwnerPhase::Encode);
        let bytes: usize = frames.iter().map(|f| f.len()).sum();
        for sub in self
            .subs
            .values_mut()
            .filter(|s| s.level == level && s.follow.is_none())
        {
            if sub.lagging || sub.awaits_levels.is_some() {
                continue;
            }
            // Over its own bound, or the server holds too much and this queue is not short.
            let queued = sub.out.queued();
            if queued + bytes > self.config.max_queue_bytes
                || (queued > SHORT_QUEUE
                    && sub.out.total_queued() + bytes > self.config.max_queued_total)
            {
                sub.lagging = true;
                Metrics::add(&self.metrics.resyncs, 1);
                continue;
            }
            for frame in &frames {
                sub.out.push(frame.clone());
            }
            sub.delivered = to;
            Metrics::add(&self.metrics.deltas_sent, frames.len() as u64);
        }
        clock.mark(&self.metrics, OwnerPhase::Fanout);
    }

    /// One turn's part of building the levels of detail; once built, the sessions that waited
    /// for them start their syncs.
    fn advance_levels(&mut self) {
        match self.levels.advance(&self.map, self.seq, &self.name) {
            Ok(false) => {}
            Ok(true) => {
                let waiting: Vec<SessionId> = self
                    .subs
                    .iter()
                    .filter(|(_, s)| s.awaits_levels.is_some())
                    .map(|(&id, _)| id)
                    .collect();
                for id in waiting {
                    if let Some(mut sub) = self.subs.remove(&id) {
                        self.start_level_sync(&mut sub);
                        self.subs.insert(id, sub);
                    }
                }
            }
            Err(e) => {
                self.drop_levels(&e);
            }
        }
    }

    /// The levels of detail could not be built: they are dropped and every session viewing one
    /// is told why and closed.
    fn drop_levels(&mut self, e: &brickcast_protocol::map::MapError) {
        tracing::error!(scene = %self.name, error = %e, "could not build the levels of detail");
        self.levels = super::levels::Levels::default();
        for sub in self
            .subs
            .values()
            .filter(|s| s.level > 0 || s.follow.is_some())
        {
            sub.out.close(
                brickcast_protocol::wire::ErrorCode::Internal,
                format!("the server could not build the scene's levels of detail: {e}"),
            );
        }
    }

    /// Builds the levels of detail again from the map as it is now (after a reload, or an
    /// update that failed): every session viewing a level drops its copy and is synced again
    /// once they are built.
    pub(super) fn restart_levels(&mut self) {
        if let Err(e) = self.levels.reset(&self.map, self.seq) {
            self.drop_levels(&e);
            return;
        }
        for sub in self
            .subs
            .values_mut()
            .filter(|s| s.level > 0 || s.follow.is_some())
        {
            if sub.awaits_levels.is_none() {
                sub.awaits_levels = Some(true);
            }
            sub.pending.clear();
            sub.lagging = false;
            sub.syncing = true;
            sub.out.set_syncing(true);
        }
    }

    /// Snapshots when forced or due. Due means: replaying the log would cost more than the
    /// budget (and the last snapshot was long enough ago), or the log has entries and the last
    /// snapshot is older than `snapshot_every`.
    pub(super) fn maybe_snapshot(&mut self, force: bool) -> Result<(), LogError> {
        let now = (self.clock)();
        let since = now.saturating_duration_since(self.last_snapshot);
        let due = (self.replay_cost() >= self.config.snapshot_replay_budget
            && since >= self.last_snapshot_took * SNAPSHOT_SPACING)
            || (self.log_entries > 0 && since >= self.config.snapshot_every);
        // Over a shared log only the owner that orders snapshots.
        if !(force || due) || !self.log.may_order() {
            return Ok(());
        }
        let cells = self.unsnapshotted.take_sorted();
        // On the owner's clock: what the snapshot took decides when the next one is due.
        let started = (self.clock)();
        let at = SnapshotOf {
            map: &self.map,
            cells: &cells,
            seq: self.seq,
            history: &self.history,
            answered: &self.answered,
        };
        match self.log.snapshot(at) {
            Ok(true) => {}
            Ok(false) => {
                // Not this node's to write (a cluster replica), or one is still uploading.
                self.unsnapshotted.insert_all(&cells);
                return Ok(());
            }
            Err(e) => {
                // The cells are still unsnapshotted: a later snapshot must write them.
                self.unsnapshotted.insert_all(&cells);
                return Err(e);
            }
        }
        let took = (self.clock)().saturating_duration_since(started);
        tracing::debug!(scene = %self.name, seq = self.seq, entries = self.log_entries, bricks = cells.len(), ?took, "snapshot");
        self.log_entries = 0;
        self.log_ops = 0;
        self.log_work = 0;
        self.last_snapshot_took = took;
        self.last_snapshot = (self.clock)();
        Metrics::add(&self.metrics.snapshots, 1);
        if self.seq > TOMBSTONE_WINDOW {
            self.map.prune_tombstones(self.seq - TOMBSTONE_WINDOW);
            self.levels.prune_tombstones(self.seq - TOMBSTONE_WINDOW);
        }
        Ok(())
    }

    /// What replaying the log since the snapshot would cost, in single-voxel ops. Brushes
    /// count by the voxels they visit, not the ones they change: erasing air with a big sphere
    /// changes nothing and still costs its box to replay.
    fn replay_cost(&self) -> u64 {
        self.log_ops + self.log_work / VOXELS_PER_OP_COST + self.log_entries * ENTRY_OP_COST
    }

    pub(super) fn publish_info(&self) {
        self.info
            .history_users
            .store(self.history.user_count() as u64, Relaxed);
        self.info
            .history_bytes
            .store(self.history.total_bytes(), Relaxed);
        self.info.seq.store(self.seq, Relaxed);
        self.info
            .leading
            .store(self.log.shared() && self.log.may_order(), Relaxed);
        self.info.bricks.store(self.map.brick_count(), Relaxed);
        self.info.voxels.store(self.map.solid_voxels(), Relaxed);
        self.info.clients.store(self.subs.len() as u64, Relaxed);
        self.info
            .gpu_bytes
            .store(self.map.memory().total_bytes, Relaxed);
    }

    /// Applies and commits `rest` (what was still queued), then leaves a snapshot behind.
    pub fn stop(&mut self, rest: Vec<Command>) -> Result<(), LogError> {
        self.stopping = true;
        // What waited behind a job that finished in the last turn arrived before `rest`.
        let mut first = std::mem::take(&mut self.released);
        first.extend(rest);
        self.turn(first, &mut PhaseClock::start())?;
        // Undos still being planned are finished (a stopping turn plans them whole), and
        // what waited behind them applied.
        while !self.released.is_empty() || !self.jobs.is_empty() {
            let waited = std::mem::take(&mut self.released);
            self.turn(waited, &mut PhaseClock::start())?;
        }
        if self.log_entries > 0 && !self.broken {
            self.maybe_snapshot(true)?;
        }
        // A snapshot still being stored is waited for: the next owner reads it.
        self.log.close();
        tracing::info!(scene = %self.name, seq = self.seq, "scene owner stopped");
        Ok(())
    }

    /// Tells every session the scene is gone (after a storage failure) and closes it. Frames
    /// still waiting for a commit never go (that commit may not have happened); the closing
    /// error is not stamped, so it goes.
    pub fn fail_all(&mut self, reason: &str) {
        self.durability.fail();
        for sub in self.subs.values() {
            sub.out.close(
                brickcast_protocol::wire::ErrorCode::Internal,
                format!("scene stopped: {reason}"),
            );
        }
        self.subs.clear();
    }
}
