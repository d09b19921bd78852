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
//!
//! * `owner.rs`: the owner's state and turn (apply, commit, ack, delta, snapshot).
//! * `sync.rs`: joins, resumes and resyncs, streamed nearest-first.
//! * `outbox.rs`: a session's byte-counted outgoing queue.
//! * `durable.rs`: which turns are durable, so frames wait for their commit while the owner goes
//!   on (`Durability`).
//! * `cells.rs`: the set of bricks the next snapshot writes.
//! * `history.rs`: per-user undo and redo stacks and what undoing a step does.
//! * `log.rs`: the one interface to where turns are made durable ([`SceneLog`]: the redb
//!   store, or a cluster's JetStream stream), and its typed errors.
//! * `replica.rs`: the owner over a shared log: requests from other origins, following
//!   another owner's turns, claiming the scene and losing it.
//! * `request.rs`, `answered.rs`: requests from other origins, and which were answered (so a
//!   retry applies once).
//!
//! This file holds what sessions see (commands, the handle) and the thread that feeds commands
//! to the owner.

pub mod answered;
mod cells;
pub mod durable;
mod edit_job;
mod follow;
pub mod history;
mod jobs;
pub mod levels;
pub mod log;
mod outbox;
mod owner;
pub mod paste;
mod replica;
pub mod request;
pub mod rewind;
pub mod step;
mod sync;
mod undo_job;

use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::{Duration, Instant};

use brickcast_protocol::wire::{EditOp, Limits, Peer, Role};
use tokio::sync::{mpsc, oneshot};

use crate::metrics::{Metrics, OwnerPhase, PhaseClock};
use crate::store::{Store, StoreLog};

pub use answered::{Answered, AnsweredEntry, Lookup};
pub use durable::Durability;
/// Owners and sessions for unit tests of other modules (`jobs.rs`).
#[cfg(test)]
pub(crate) use jobs::testing;
pub use log::{LogError, OwnedTurn, SceneLog, SnapshotOf, Turn, TurnWrite};
pub use outbox::{MAX_REPLY_BACKLOG, Outbox, OutboxReceiver};
pub use owner::Owner;
pub use request::{Outcome, Request, RequestItem};

/// Identifies a session within the server.
pub type SessionId = u64;

/// Where the owner reads the time for its decisions (when to snapshot). The server uses
/// `Instant::now`; the simulation test a clock it advances itself.
pub type Clock = Arc<dyn Fn() -> Instant + Send + Sync>;

/// Most ops applied in one turn before committing: bounds the latency a huge backlog adds to the
/// first edit in it.
const MAX_OPS_PER_TURN: usize = 65_536;
/// Most edit work (voxels visited, `EditOp::work`) collected into one turn: big brushes from
/// several clients are spread over turns, each ending in a commit, its acks and its delta, so
/// no turn holds the others' edits for long (about 90 ms of brushing on the dev VM).
const MAX_WORK_PER_TURN: u64 = 1 << 25;

/// What sessions ask of the owner.
pub enum Command {
    Join {
        session: SessionId,
        out: Outbox,
        role: Role,
        resume_from: Option<u64>,
        /// Which level of detail the session views: 0 is the scene, K > 0 its level K
        /// (`levels.rs`; such a session is a viewer).
        level: u32,
        /// GPU bytes the client gives the scene: it is streamed a working set within them and
        /// followed (`follow.rs`); `None`: the whole scene.
        budget: Option<brickcast_protocol::wire::Budget>,
        /// Who joins, and who it saw present (for the Welcome).
        who: Joiner,
        /// Fired once the Welcome is queued: the session sends nothing before it.
        joined: oneshot::Sender<()>,
    },
    Leave {
        session: SessionId,
    },
    Edit {
        session: SessionId,
        client_seq: u64,
        ops: Vec<EditOp>,
        /// A heavy edit's turn at the scene (`crate::fair`), given back once it is applied.
        admitted: Option<crate::fair::Admitted>,
    },
    Camera {
        session: SessionId,
        eye: [f32; 3],
    },
    Resume {
        session: SessionId,
        since: u64,
    },
    /// Undo (or redo) the session's user's latest step.
    Undo {
        session: SessionId,
        client_seq: u64,
        redo: bool,
    },
    /// Write a snapshot now (CLI, tests).
    Snapshot {
        done: oneshot::Sender<Result<(), String>>,
    },
    /// A copy of the committed scene and its sequence, for a thumbnail: `crate::web` draws it
    /// off the owner thread (copying is a memory copy; tracing it would hold the scene for
    /// tens of milliseconds) and caches the picture per sequence number.
    Thumbnail {
        done: oneshot::Sender<(u64, Box<brickcast_protocol::BrickMap>)>,
    },
    /// Apply what is queued, commit, snapshot, and stop.
    Shutdown,
    /// Commit what is applied, then close every session with this error (the scene is being
    /// deleted or renamed: `crate::admin`). The scene goes on until [`Command::Shutdown`].
    Farewell {
        code: brickcast_protocol::wire::ErrorCode,
        text: String,
    },
    /// A request from another origin (in a cluster: a session of any node, forwarded), answered
    /// on `reply` after the commit, or at once with [`Outcome::NotOwner`] when this owner does
    /// not order edits. `reply: None`: nobody waits for an answer (a history drop).
    Request {
        request: Request,
        reply: Option<oneshot::Sender<Outcome>>,
    },
    /// Shared log: the turn at position `pos`, appended by whichever owner ordered it.
    Apply {
        pos: u64,
        turn: Box<Turn>,
    },
    /// Shared log: this owner may order edits (it holds the lease): catch up to the log's end
    /// and claim it. Answers whether this owner now orders edits.
    Lead {
        done: oneshot::Sender<bool>,
    },
    /// Shared log: stop ordering edits (the lease is gone).
    Follow {
        why: String,
    },
    /// Shared log: it now starts at position `first`. What this replica had not read yet
    /// below that was trimmed (a snapshot holds it): load the scene again.
    Behind {
        first: u64,
    },
    /// Shared log: it holds something this replica cannot follow (a message that does not
    /// decode): stop serving the scene here, telling every session why.
    Fault {
        why: String,
    },
    /// Where the scene stands here (for `cluster status`: checking that replicas agree
    /// without a client). Hashes the whole map: a few milliseconds per 100k bricks.
    Describe {
        done: oneshot::Sender<Described>,
    },
}

/// Where one replica of a scene stands ([`Command::Describe`]).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Described {
    pub seq: u64,
    /// `BrickMap::content_hash` of the committed map.
    pub hash: u64,
    /// The position in the log of the last turn applied.
    pub position: u64,
    /// Whether this owner orders the scene's edits.
    pub leading: bool,
    pub clients: u64,
}

/// Who a joining session is.
#[derive(Clone, Debug)]
pub struct Joiner {
    /// The session as others see it (`peer.user` keys its history).
    pub peer: Peer,
    /// False for a user without a stable id: its history is dropped when it leaves.
    pub stable: bool,
    /// Everyone else present when it joined (from the presence hub), for the Welcome.
    pub roster: Vec<Peer>,
}

impl Joiner {
    /// An editor or viewer with a stable id and nobody else around (tests, the simulation).
    pub fn solo(session: SessionId, user: u64, role: Role) -> Joiner {
        Joiner {
            peer: Peer {
                id: session,
                user,
                name: format!("user-{user}"),
                colour: crate::identity::colour_of(user),
                role,
            },
            stable: true,
            roster: Vec::new(),
        }
    }
}

/// Figures about a scene readable without asking the owner (for `/scenes` and `/metrics`).
#[derive(Default)]
pub struct SceneInfo {
    pub seq: AtomicU64,
    pub bricks: AtomicU64,
    pub voxels: AtomicU64,
    pub clients: AtomicU64,
    pub gpu_bytes: AtomicU64,
    /// Users with undo history, and the bytes of their stored steps.
    pub history_users: AtomicU64,
    pub history_bytes: AtomicU64,
    /// In a cluster: whether this node owns the scene now.
    pub leading: std::sync::atomic::AtomicBool,
}

/// What one connection may ask of the owner in edit work (voxels visited, `EditOp::work`):
/// the owner is one thread per scene, so a message is charged by what it costs, not by how many
/// ops it holds.
#[derive(Clone, Debug)]
pub struct EditBudget {
    /// A message asking for more is refused whole (`TooLarge` on every op). 2^25 voxels: two
    /// boxes of 256³, about 90 ms of brushing on the dev VM.
    pub max_work_per_edit: u64,
    /// Work per second one connection may ask for, refilled continuously with one second of
    /// burst (and always room for one message of `max_work_per_edit`); beyond it, `RateLimited`.
    pub max_work_per_second: u64,
}

impl Default for EditBudget {
    fn default() -> Self {
        EditBudget {
            max_work_per_edit: 1 << 25,
            max_work_per_second: 1 << 26,
        }
    }
}

/// Knobs of a scene owner.
#[derive(Clone, Debug)]
pub struct OwnerConfig {
    pub limits: Limits,
    pub budget: EditBudget,
    /// A session whose queue holds more than this many bytes is resynced instead of sent deltas.
    pub max_queue_bytes: usize,
    /// When every session's queue together holds more than this, sessions with more than a
    /// little queued stop getting deltas (and resync later) and syncs pause: a thousand slow
    /// clients cannot hold a thousand times `max_queue_bytes`.
    pub max_queued_total: usize,
    /// Sessions whose sync (or resync) advances in one turn, in turn: a thousand clients joining
    /// at once cost the owner a bounded amount per turn, and edits keep flowing.
    pub max_syncs_per_turn: usize,
    /// Snapshot once replaying the log would cost about this many single-voxel ops (about a
    /// second of recovery: 7.2 M logged voxel ops replayed in 2.0 s on the dev VM). A
    /// snapshot rewrites every brick touched since the last one and stalls the owner meanwhile
    /// (about 1 µs per brick), so it is sized by what recovery would replay, not by how many
    /// edit messages carried it: counting messages made small batches snapshot the whole scene
    /// every two seconds under load.
    pub snapshot_replay_budget: u64,
    /// ...or once the last snapshot is this old and the log has entries, so an idle server's
    /// log is short too (`serve --snapshot-every`).
    pub snapshot_every: Duration,
    /// Bytes of stored undo history over every user of the scene (`serve --max-history-bytes`;
    /// the oldest steps of idle guests go first, see `history`).
    pub max_history_bytes: u64,
    /// An undo or redo of a step of at least this many bricks, and an edit message of at
    /// least this many bricks' work (512 voxels each), is planned a frame per turn and applied
    /// in one (`jobs.rs`), so others' edits go on meanwhile.
    pub slice_bricks: u32,
    /// A scene laid out larger than this gets its levels of detail built as soon as it loads
    /// (`levels.rs`, [`levels::EAGER_ABOVE_BYTES`] by default), so the first viewer that needs
    /// a working set does not wait for them.
    pub eager_levels_bytes: u64,
    /// The node's users' clipboards (`paste.rs`): one for every scene of the node (the
    /// config is cloned per scene, the clipboards shared).
    pub clipboards: std::sync::Arc<paste::Clipboards>,
    /// Past boxes fetched for restores, waiting for their scene's owner (`rewind.rs`): one
    /// for every scene of the node.
    pub pasts: std::sync::Arc<rewind::Pasts>,
}

impl Default for OwnerConfig {
    fn default() -> Self {
        OwnerConfig {
            limits: Limits::default(),
            budget: EditBudget::default(),
            max_queue_bytes: 32 << 20,
            max_queued_total: 1 << 30,
            max_syncs_per_turn: 8,
            snapshot_replay_budget: 4_000_000,
            snapshot_every: Duration::from_secs(60),
            max_history_bytes: 256 << 20,
            // 1 M voxels compared: as heavy as a heavy edit (`fair::HEAVY_WORK`).
            slice_bricks: 2048,
            eager_levels_bytes: levels::EAGER_ABOVE_BYTES,
            clipboards: Default::default(),
            pasts: Default::default(),
        }
    }
}

/// The handle sessions and the HTTP layer hold.
#[derive(Clone)]
pub struct SceneHandle {
    pub name: String,
    pub size: [u32; 3],
    pub limits: Limits,
    pub budget: EditBudget,
    /// Queue bound of each session (see [`OwnerConfig::max_queue_bytes`]).
    pub max_queue_bytes: usize,
    pub info: Arc<SceneInfo>,
    /// Who is here and what they look at (lives beside the owner, see `crate::presence`).
    pub presence: Arc<crate::presence::Hub>,
    /// Heavy edits enter the owner's queue one budget at a time (see `crate::fair`).
    pub heavy: crate::fair::HeavyGate,
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

    /// Resolves once the owner thread has stopped taking commands (it stopped, or crashed).
    pub async fn closed(&self) {
        self.tx.closed().await
    }

    /// Whether the owner thread has stopped taking commands.
    pub fn is_closed(&self) -> bool {
        self.tx.is_closed()
    }
}

/// A command sent to a scene whose owner thread has stopped (shutdown or a storage failure).
#[derive(Debug, thiserror::Error)]
#[error("the scene owner has stopped")]
pub struct SceneGone;

/// Per-session state the owner keeps.
pub(crate) struct Subscriber {
    out: Outbox,
    role: Role,
    /// Whose history this session's edits go to.
    user: u64,
    /// Forget the user's history when this session leaves.
    stable: bool,
    camera: [f32; 3],
    /// The level of detail it views (0: the scene itself), in whose coordinates `camera` is.
    level: u32,
    /// Waiting for the levels of detail to be built before its sync starts (`levels.rs`); true:
    /// it holds a copy it must drop first (it resumed, or the levels were rebuilt).
    awaits_levels: Option<bool>,
    /// Every change up to this sequence has been queued to the client.
    delivered: u64,
    /// Deltas stopped because the queue overflowed; resync from `delivered` once it drains.
    lagging: bool,
    /// Cells still to send in a sync, farthest first (the nearest is popped next).
    pending: Vec<u32>,
    sync_total: u32,
    sync_sent: u32,
    syncing: bool,
    /// Its working set, when it gave a budget (`follow.rs`).
    follow: Option<follow::Follow>,
}

/// Starts the owner thread for a scene loaded from the redb store.
pub fn spawn(
    name: String,
    loaded: crate::store::Loaded,
    store: Arc<Store>,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    runtime: tokio::runtime::Handle,
) -> std::io::Result<(SceneHandle, std::thread::JoinHandle<()>)> {
    let log = Box::new(StoreLog::pipelined(store, name.clone(), metrics.clone())?);
    spawn_with(name, loaded, log, metrics, config, runtime)
}

/// Starts the owner thread for a loaded scene over any [`SceneLog`].
pub fn spawn_with(
    name: String,
    loaded: crate::store::Loaded,
    log: Box<dyn SceneLog>,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    runtime: tokio::runtime::Handle,
) -> std::io::Result<(SceneHandle, std::thread::JoinHandle<()>)> {
    let (owner, handle, rx) = open(name, loaded, log, metrics, config, Arc::new(Instant::now))?;
    let thread = run_thread(owner, rx, &handle, runtime)?;
    Ok((handle, thread))
}

/// Runs an opened owner on a thread of its own (and its presence hub on `runtime`) until
/// shutdown, a storage failure, or every handle gone.
pub fn run_thread(
    mut owner: Owner,
    mut rx: mpsc::Receiver<Command>,
    handle: &SceneHandle,
    runtime: tokio::runtime::Handle,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    runtime.spawn(crate::presence::run(
        handle.presence.clone(),
        owner.metrics.clone(),
    ));
    let presence = handle.presence.clone();
    let name = handle.name.clone();
    std::thread::Builder::new()
        .name(format!("scene-{name}"))
        .spawn(move || {
            if let Err(e) = run(&mut owner, &mut rx, &runtime) {
                tracing::error!(scene = %name, error = %e, "scene owner stopped on a storage error");
                owner.fail_all(&e.to_string());
            }
            presence.close();
            // The owner first (its log waits for a snapshot still being stored), so the
            // handle reads as closed only once it is gone.
            drop(owner);
        })
}

/// A scene's owner, the handle sessions reach it by and the channel its commands arrive on,
/// without a thread: [`spawn_with`] runs the owner on one, the cluster's simulation steps it
/// itself. `clock` is where the owner reads the time.
pub fn open(
    name: String,
    loaded: crate::store::Loaded,
    log: Box<dyn SceneLog>,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    clock: Clock,
) -> std::io::Result<(Owner, SceneHandle, mpsc::Receiver<Command>)> {
    let (tx, rx) = mpsc::channel(1024);
    let limits = config.limits.clone();
    let budget = config.budget.clone();
    let max_queue_bytes = config.max_queue_bytes;
    let heavy = crate::fair::HeavyGate::new(budget.max_work_per_edit);
    let owner = Owner::with_log(name.clone(), loaded, log, metrics, config, clock)?;
    let handle = SceneHandle {
        name,
        size: owner.map().size(),
        presence: Arc::new(crate::presence::Hub::new(limits.presence_hz)),
        limits,
        budget,
        max_queue_bytes,
        info: owner.info(),
        heavy,
        tx,
    };
    Ok((owner, handle, rx))
}

/// The owner thread: wait for commands, hand each group to the owner, stop on shutdown or when
/// every handle is gone.
fn run(
    owner: &mut Owner,
    rx: &mut mpsc::Receiver<Command>,
    runtime: &tokio::runtime::Handle,
) -> Result<(), LogError> {
    let metrics = owner.metrics.clone();
    let size = owner.map().size();
    loop {
        // Wait briefly when a sync is waiting for a queue to drain, long when idle.
        let wait = if owner.has_blocked_work() {
            Duration::from_millis(20)
        } else {
            Duration::from_secs(1)
        };
        let mut clock = PhaseClock::start();
        let first = if owner.has_ready_work() || owner.has_jobs() {
            rx.try_recv().ok()
        } else {
            // A writer that took a sync frame wakes the owner to queue the next ones.
            let wake = owner.waker();
            let next = async {
                tokio::select! {
                    biased;
                    cmd = rx.recv() => Some(cmd),
                    _ = wake.notified() => None,
                }
            };
            match runtime.block_on(async { tokio::time::timeout(wait, next).await }) {
                Ok(Some(Some(cmd))) => Some(cmd),
                Ok(Some(None)) => return owner.stop(drain(rx)),
                Ok(None) | Err(_) => None,
            }
        };
        let mut commands: Vec<Command> = first.into_iter().collect();
        let (mut ops, mut work) = commands
            .iter()
            .map(|c| command_cost(c, size))
            .fold((0, 0), |(o, w), (co, cw)| (o + co, w + cw));
        while ops < MAX_OPS_PER_TURN && work < MAX_WORK_PER_TURN {
            match rx.try_recv() {
                Ok(cmd) => {
                    let (co, cw) = command_cost(&cmd, size);
                    ops += co;
                    work = work.saturating_add(cw);
                    commands.push(cmd);
                }
                Err(_) => break,
            }
        }
        clock.mark(&metrics, OwnerPhase::Wait);
        let busy = !commands.is_empty() || owner.has_jobs() || owner.has_ready_work();
        let started = Instant::now();
        // Commands still queued: this turn's commit may run while the next turn applies.
        owner.set_backlog(!rx.is_empty());
        let stop = owner.step(commands, &mut clock)?;
        if busy {
            metrics.turns.observe(started.elapsed());
        }
        if stop {
            return owner.stop(drain(rx));
        }
    }
}

/// Every command still queued.
fn drain(rx: &mut mpsc::Receiver<Command>) -> Vec<Command> {
    std::iter::from_fn(|| rx.try_recv().ok()).collect()
}

/// Ops and edit work a command brings into a turn.
fn command_cost(cmd: &Command, size: [u32; 3]) -> (usize, u64) {
    match cmd {
        Command::Edit { ops, .. } => (
            ops.len().max(1),
            ops.iter()
                .map(|op| op.work(size))
                .fold(0, u64::saturating_add),
        ),
        _ => (1, 0),
    }
}
