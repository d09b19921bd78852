//! Deterministic simulation of a scene owner and its store, crashed at random points.
//!
//! Why: the promise everything else stands on is "an acknowledged edit is there after a crash",
//! and a scripted crash test only checks the scripts someone thought of. Here one seed drives a
//! random history (valid, partly and fully rejected edit batches, brushes, boxes, ray edits that
//! hit or miss, viewers that may not edit, joins, resumes, leaves, camera moves, forced and
//! periodic snapshots, clients that stop reading and fall behind) through the real [`Owner`]
//! and the real [`Store`] on a [`SimDisk`], and crashes at random: between turns, or in the
//! middle of a commit or a snapshot (the disk dies after a random number of I/O calls), keeping
//! either only what was synced or a torn mix of unsynced pages. After every crash the store is
//! reopened and the scene recovered, and the simulation checks:
//!
//! * every acknowledged batch is there, and the recovered scene is exactly the model's scene
//!   after some whole number of batches (nothing half-applied), no further than what was
//!   applied;
//! * no client holds a sequence the server came back without;
//! * every client that resumes (or syncs afresh) ends up hashing equal to the server.
//!
//! Between crashes every ack is checked against a model that applies the same ops to its own
//! map, and the owner's map must equal the model's after every turn.
//!
//! Everything is deterministic: time comes from a clock the simulation advances, sessions are
//! visited in id order, randomness comes from the seed. A failing seed is printed with the last
//! actions and the command that replays it: `BRICKCAST_SIM_SEED=N cargo test -p
//! brickcast-server sim::`. `BRICKCAST_SIM_SEEDS` sets how many seeds the test runs (2,000 by
//! default), `BRICKCAST_SIM_SECONDS` runs seeds for that long instead (a soak), and
//! `BRICKCAST_SIM_FIRST` the first seed.

pub(crate) mod disk;
mod model;
mod ops;
pub(crate) mod seeds;
#[cfg(test)]
mod tests;
mod undo;

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use brickcast_protocol::apply::apply_op;
use brickcast_protocol::replica::Replica;
use brickcast_protocol::wire::{EditOp, Limits, RayAction, Role, ServerMsg, decode_server};
use brickcast_protocol::{BrickMap, BrushMode, Colour};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::sync::oneshot;

pub use disk::SimDisk;
use model::{Expected, ExpectedUndone, Model};
use ops::{initial_scene, random_batch};
use undo::{describe, normal, server_history};

use crate::metrics::{Metrics, PhaseClock};
use crate::scene::{Command, Outbox, OutboxReceiver, Owner, OwnerConfig, SessionId};
use crate::store::Store;

const SCENE: &str = "sim";
/// Actions kept for the report of a failing seed.
const TRACE_LEN: usize = 80;

/// What one seed did, summed over seeds for the report.
#[derive(Debug, Default, Clone, Copy)]
pub struct SimStats {
    pub turns: u64,
    pub batches_applied: u64,
    pub batches_rejected: u64,
    pub acks: u64,
    pub crashes: u64,
    pub torn_crashes: u64,
    pub mid_io_crashes: u64,
    pub snapshots: u64,
    pub joins: u64,
    pub resumed_joins: u64,
    pub resyncs: u64,
    pub settles: u64,
    pub undos: u64,
    pub undos_refused: u64,
}

impl crate::sim::seeds::Tally for SimStats {
    fn add(&mut self, o: &SimStats) {
        self.turns += o.turns;
        self.batches_applied += o.batches_applied;
        self.batches_rejected += o.batches_rejected;
        self.acks += o.acks;
        self.crashes += o.crashes;
        self.torn_crashes += o.torn_crashes;
        self.mid_io_crashes += o.mid_io_crashes;
        self.snapshots += o.snapshots;
        self.joins += o.joins;
        self.resumed_joins += o.resumed_joins;
        self.resyncs += o.resyncs;
        self.settles += o.settles;
        self.undos += o.undos;
        self.undos_refused += o.undos_refused;
    }
}

/// One connection of a simulated client.
struct Conn {
    session: SessionId,
    rx: OutboxReceiver,
    /// Limits from the Welcome (hard caps until then).
    limits: Limits,
    welcomed: bool,
}

/// A simulated user: a copy of the scene that outlives its connections.
struct Client {
    role: Role,
    replica: Replica,
    conn: Option<Conn>,
    next_client_seq: u64,
    /// How likely the client is to read its queue when the simulation offers it a read.
    reads: f64,
}

/// Why a seed failed.
pub type Failure = String;

macro_rules! check {
    ($cond:expr, $($fmt:tt)+) => {
        if !$cond {
            return Err(format!($($fmt)+));
        }
    };
}

/// One simulated world: a store on a simulated disk, the owner of one scene, its clients, and
/// the model they are checked against.
pub struct Sim {
    rng: ChaCha8Rng,
    now: Arc<Mutex<Instant>>,
    disk: SimDisk,
    store: Arc<Store>,
    owner: Owner,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    clients: Vec<Client>,
    queue: Vec<Command>,
    /// Queues of clients that left, kept until the turn that processes their Leave.
    departed: Vec<OutboxReceiver>,
    snapshot_replies: Vec<oneshot::Receiver<Result<(), String>>>,
    model: Model,
    next_session: SessionId,
    /// Bytes queued to every simulated session (the server-wide figure).
    queued_total: Arc<std::sync::atomic::AtomicUsize>,
    trace: VecDeque<String>,
    pub stats: SimStats,
}

impl Sim {
    /// A world for `seed`: a random scene in a fresh store, `clients` users (some viewers).
    pub fn new(seed: u64) -> Result<Sim, Failure> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let size = [
            rng.random_range(16..72),
            rng.random_range(16..56),
            rng.random_range(16..72),
        ];
        let map = initial_scene(&mut rng, size);
        let disk = SimDisk::new();
        let store = Arc::new(Store::with_backend(disk.clone()).map_err(|e| e.to_string())?);
        store.create_scene(SCENE, &map).map_err(|e| e.to_string())?;
        let limits = Limits {
            max_undo_steps: [2, 4, 16][rng.random_range(0..3)],
            ..Limits::default()
        };
        let config = OwnerConfig {
            limits,
            max_queue_bytes: [4 << 10, 64 << 10, 32 << 20][rng.random_range(0..3)],
            max_queued_total: [16 << 10, 1 << 30][rng.random_range(0..2)],
            max_syncs_per_turn: rng.random_range(1..4),
            snapshot_replay_budget: [300, 20_000, 4_000_000][rng.random_range(0..3)],
            snapshot_every: Duration::from_secs(60),
            // The model applies an undo in the turn it arrives; an undo planned across turns
            // has a test of its own (`scene::undo_job`), against the undo of one turn.
            slice_bricks: u32::MAX,
            // Levels of detail built from the start (over turns, beside the edits) or when a
            // working set or level view first asks.
            eager_levels_bytes: [0, u64::MAX][rng.random_range(0..2)],
            ..OwnerConfig::default()
        };
        let now = Arc::new(Mutex::new(Instant::now()));
        let metrics = Arc::new(Metrics::default());
        let owner = open_owner(&store, &metrics, &config, &now)?;
        let limits = config.limits.clone();
        let clients = (0..rng.random_range(1..5))
            .map(|i| Client {
                role: if i > 0 && rng.random_bool(0.3) {
                    Role::Viewer
                } else {
                    Role::Editor
                },
                replica: Replica::new(SCENE, size).expect("valid size"),
                conn: None,
                next_client_seq: 1,
                reads: [1.0, 0.7, 0.2][rng.random_range(0..3)],
            })
            .collect();
        let hash = map.content_hash();
        Ok(Sim {
            rng,
            now,
            disk,
            store,
            owner,
            metrics,
            config,
            clients,
            queue: Vec::new(),
            departed: Vec::new(),
            snapshot_replies: Vec::new(),
            model: Model {
                base: (0, map.clone()),
                map,
                seq: 0,
                hashes: vec![hash],
                batches: Vec::new(),
                acked: 0,
                subscribed: BTreeMap::new(),
                expected: BTreeMap::new(),
                expected_undone: BTreeMap::new(),
                limits,
                users: BTreeMap::new(),
                history: BTreeMap::new(),
                committed: vec![(0, BTreeMap::new())],
            },
            next_session: 1,
            queued_total: Arc::default(),
            trace: VecDeque::new(),
            stats: SimStats::default(),
        })
    }

    fn note(&mut self, action: String) {
        if self.trace.len() == TRACE_LEN {
            self.trace.pop_front();
        }
        self.trace.push_back(action);
    }

    /// The last actions, oldest first.
    pub fn trace(&self) -> String {
        self.trace.iter().cloned().collect::<Vec<_>>().join("\n  ")
    }

    /// Client `c` connects, resuming from its copy if it has a complete one.
    pub fn join(&mut self, c: usize) {
        if self.clients[c].conn.is_some() {
            return;
        }
        let session = self.next_session;
        self.next_session += 1;
        let (out, rx) = Outbox::new(self.queued_total.clone());
        let client = &mut self.clients[c];
        let resume_from = client.replica.resume_point();
        client.conn = Some(Conn {
            session,
            rx,
            limits: Limits::hard_caps(),
            welcomed: false,
        });
        let role = client.role;
        let (joined, _) = oneshot::channel();
        self.queue.push(Command::Join {
            session,
            out,
            role,
            resume_from,
            level: 0,
            budget: None,
            who: crate::scene::Joiner::solo(session, c as u64 + 1, role),
            joined,
        });
        self.stats.joins += 1;
        if resume_from.is_some() {
            self.stats.resumed_joins += 1;
        }
        self.note(format!(
            "client {c} joins as session {session} ({role:?}), resume from {resume_from:?}"
        ));
    }

    /// Client `c` disconnects; whatever it had in flight is lost to it.
    pub fn leave(&mut self, c: usize) {
        if let Some(conn) = self.clients[c].conn.take() {
            self.queue.push(Command::Leave {
                session: conn.session,
            });
            // As with a real session, the queue lives until the owner has seen the Leave.
            self.departed.push(conn.rx);
            self.note(format!("client {c} leaves (session {})", conn.session));
        }
    }

    /// Client `c` sends an edit message.
    pub fn edit(&mut self, c: usize, ops: Vec<EditOp>) {
        let client = &mut self.clients[c];
        let Some(conn) = &client.conn else { return };
        let client_seq = client.next_client_seq;
        client.next_client_seq += 1;
        let session = conn.session;
        self.note(format!("client {c} edits #{client_seq}: {ops:?}"));
        self.queue.push(Command::Edit {
            session,
            client_seq,
            ops,
            admitted: None,
        });
    }

    /// Client `c` asks to undo (or redo) its user's latest step.
    pub fn undo(&mut self, c: usize, redo: bool) {
        let client = &mut self.clients[c];
        let Some(conn) = &client.conn else { return };
        let client_seq = client.next_client_seq;
        client.next_client_seq += 1;
        let session = conn.session;
        self.note(format!(
            "client {c} {} #{client_seq}",
            if redo { "redoes" } else { "undoes" }
        ));
        self.queue.push(Command::Undo {
            session,
            client_seq,
            redo,
        });
    }

    /// The server's history (every step read back from the store) against the model's.
    fn check_history(&self, what: &str) -> Result<(), Failure> {
        let server = server_history(
            &self.store,
            SCENE,
            self.owner.map(),
            self.owner.history().users(),
        )?;
        let model = normal(&self.model.history);
        check!(
            server == model,
            "{what}: the undo history differs from the model's: {}",
            describe(&server, &model)
        );
        Ok(())
    }

    fn camera(&mut self, c: usize, eye: [f32; 3]) {
        if let Some(conn) = &self.clients[c].conn {
            let session = conn.session;
            self.queue.push(Command::Camera { session, eye });
            self.note(format!("client {c} moves its camera to {eye:?}"));
        }
    }

    /// Client `c` asks for everything after `since` again (as after a detected gap).
    fn resume(&mut self, c: usize, since: u64) {
        let client = &self.clients[c];
        // A client asks once it has been welcomed and holds a complete copy; the Resync that
        // answers makes the copy incomplete until SyncDone.
        if let Some(conn) = &client.conn
            && conn.welcomed
            && client.replica.synced
        {
            let session = conn.session;
            self.queue.push(Command::Resume { session, since });
            self.note(format!("client {c} asks to resume from {since}"));
        }
    }

    /// A snapshot forced through the command channel (as the CLI and tests do).
    pub fn force_snapshot(&mut self) {
        let (done, reply) = oneshot::channel();
        self.queue.push(Command::Snapshot { done });
        self.snapshot_replies.push(reply);
        self.note("forced snapshot".into());
    }

    /// Moves the owner's clock on (periodic snapshots are due after 60 s with any log).
    pub fn advance(&mut self, by: Duration) {
        *self.now.lock().unwrap_or_else(|e| e.into_inner()) += by;
        self.note(format!("clock +{by:?}"));
    }

    /// Runs one owner turn with everything queued. A storage failure must come from a dead
    /// disk; then the world crashes. Returns whether it crashed.
    pub fn turn(&mut self) -> Result<bool, Failure> {
        let commands = std::mem::take(&mut self.queue);
        self.note(format!("turn with {} commands", commands.len()));
        self.model.turn(&commands);
        self.stats.turns += 1;
        let result = self.owner.step(commands, &mut PhaseClock::start());
        self.departed.clear();
        self.note(format!(
            "  -> {}, sequence {}, disk {} after {} syncs",
            if result.is_ok() {
                "ok"
            } else {
                "storage error"
            },
            self.owner.seq(),
            if self.disk.is_dead() { "dead" } else { "alive" },
            self.disk.syncs()
        ));
        for reply in std::mem::take(&mut self.snapshot_replies) {
            match reply.blocking_recv() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => check!(self.disk.is_dead(), "forced snapshot failed: {e}"),
                Err(_) => check!(self.disk.is_dead(), "forced snapshot was never answered"),
            }
        }
        match result {
            Ok(_) if !self.disk.is_dead() => {
                if self.owner.seq() != self.model.seq {
                    // The acks say which batch went differently.
                    self.read_all()?;
                }
                check!(
                    self.owner.seq() == self.model.seq,
                    "owner is at sequence {}, the model at {}",
                    self.owner.seq(),
                    self.model.seq
                );
                check!(
                    self.owner.map().content_hash() == self.model.map.content_hash(),
                    "owner's map differs from the model's at sequence {}",
                    self.model.seq
                );
                Ok(false)
            }
            Ok(_) => {
                self.crash(false)?;
                Ok(true)
            }
            Err(e) => {
                check!(self.disk.is_dead(), "storage error without a crash: {e}");
                self.crash(false)?;
                Ok(true)
            }
        }
    }

    /// Client `c` reads everything queued to it and applies it to its copy.
    fn read(&mut self, c: usize) -> Result<(), Failure> {
        let owner_seq = self.owner.seq();
        let client = &mut self.clients[c];
        let Some(conn) = &mut client.conn else {
            return Ok(());
        };
        while let Some(frame) = conn.rx.try_take() {
            let msg = decode_server(&frame, &conn.limits)
                .map_err(|e| format!("client {c} cannot decode a frame: {e}"))?;
            match &msg {
                ServerMsg::Welcome { seq, limits, .. } => {
                    check!(!conn.welcomed, "client {c} was welcomed twice");
                    check!(
                        *seq >= client.replica.seq,
                        "client {c} holds sequence {} but the server came back at {seq}: acknowledged edits were lost",
                        client.replica.seq
                    );
                    conn.welcomed = true;
                    conn.limits = limits.clone();
                }
                ServerMsg::Ack {
                    client_seq,
                    seq,
                    applied,
                    rejected,
                } => {
                    let want = self
                        .model
                        .expected
                        .remove(&(conn.session, *client_seq))
                        .ok_or_else(|| {
                            format!("client {c} got an ack for #{client_seq} nobody expected")
                        })?;
                    let got = Expected {
                        seq: *seq,
                        applied: *applied,
                        rejected: rejected.clone(),
                    };
                    check!(
                        got == want,
                        "client {c} edit #{client_seq}: ack {got:?}, the model expected {want:?}"
                    );
                    if let Some(s) = seq {
                        self.model.acked = self.model.acked.max(*s);
                    }
                    self.stats.acks += 1;
                    if seq.is_some() {
                        self.stats.batches_applied += 1;
                    } else {
                        self.stats.batches_rejected += 1;
                    }
                }
                ServerMsg::Undone {
                    client_seq,
                    seq,
                    restored,
                    kept,
                    refused,
                    ..
                } => {
                    let want = self
                        .model
                        .expected_undone
                        .remove(&(conn.session, *client_seq))
                        .ok_or_else(|| {
                            format!(
                                "client {c} got an undo reply for #{client_seq} nobody expected"
                            )
                        })?;
                    let got = ExpectedUndone {
                        seq: *seq,
                        restored: *restored,
                        kept: *kept,
                        refused: refused.clone(),
                    };
                    check!(
                        got == want,
                        "client {c} undo #{client_seq}: reply {got:?}, the model expected {want:?}"
                    );
                    if let Some(s) = seq {
                        self.model.acked = self.model.acked.max(*s);
                    }
                    if refused.is_some() {
                        self.stats.undos_refused += 1;
                    } else {
                        self.stats.undos += 1;
                    }
                }
                ServerMsg::Error { code, message } => {
                    return Err(format!("client {c} got an error: {code:?} {message}"));
                }
                ServerMsg::Delta { to_seq, .. } => {
                    check!(
                        *to_seq <= owner_seq,
                        "client {c} got a delta to {to_seq} from an owner at {owner_seq}"
                    );
                }
                ServerMsg::Resync { .. } => self.stats.resyncs += 1,
                _ => {}
            }
            check!(
                conn.welcomed,
                "client {c} got {} before its Welcome",
                msg.kind()
            );
            client
                .replica
                .apply(&msg)
                .map_err(|e| format!("client {c} cannot apply {}: {e}", msg.kind()))?;
            // A complete copy, just moved to sequence s, is the scene at s.
            let r = &client.replica;
            if r.synced && matches!(msg, ServerMsg::SyncDone { .. } | ServerMsg::Delta { .. }) {
                let want = self.model.hashes.get(r.seq as usize).copied();
                if want != Some(r.map.content_hash()) {
                    return Err(format!(
                        "client {c}'s copy after {} differs from the scene at sequence {}: {}",
                        msg.kind(),
                        r.seq,
                        match self.model.state_at(r.seq) {
                            Some(scene) => first_difference(&r.map, &scene),
                            None => "(the scene at that sequence is not known)".into(),
                        }
                    ));
                }
            }
        }
        Ok(())
    }

    fn read_all(&mut self) -> Result<(), Failure> {
        for c in 0..self.clients.len() {
            self.read(c)?;
        }
        Ok(())
    }

    /// Lets every connected client read until the owner has nothing left to send, then checks
    /// that each one's copy equals the server's scene. Returns false if it crashed meanwhile.
    pub fn settle(&mut self) -> Result<bool, Failure> {
        self.stats.settles += 1;
        self.note("settle".into());
        if !self.queue.is_empty() && self.turn()? {
            return Ok(false);
        }
        for _ in 0..100_000 {
            self.read_all()?;
            if !self.owner.has_blocked_work() {
                break;
            }
            if self.turn()? {
                return Ok(false);
            }
        }
        self.read_all()?;
        check!(!self.owner.has_blocked_work(), "syncs never finished");
        self.check_history(&format!("settled at sequence {}", self.model.seq))?;
        let hash = self.owner.map().content_hash();
        for (c, client) in self.clients.iter().enumerate() {
            if client.conn.is_none() {
                continue;
            }
            let r = &client.replica;
            check!(
                r.synced && r.seq == self.owner.seq(),
                "client {c} is not caught up: synced {}, at {} of {}",
                r.synced,
                r.seq,
                self.owner.seq()
            );
            check!(
                r.map.content_hash() == hash,
                "client {c}'s copy differs from the server's scene at sequence {}",
                r.seq
            );
        }
        Ok(true)
    }

    /// Arms the disk to die after `calls` more I/O calls: the next commit or snapshot that
    /// reaches that point fails half-way, and the world crashes.
    pub fn arm(&mut self, calls: u64) {
        self.disk.die_after(calls);
        self.note(format!("disk dies after {calls} more I/O calls"));
    }

    /// Power cut: the disk dies, the process is gone (the owner and the store are dropped
    /// without a word), the store is reopened on what the disk kept, and the scene recovered.
    pub fn crash(&mut self, torn: bool) -> Result<(), Failure> {
        let torn = torn || self.rng.random_bool(0.5);
        let mid_io = self.disk.is_dead();
        self.note(format!("crash (torn: {torn}, mid-I/O: {mid_io})"));
        self.disk.kill();
        // What the writers had already put on the wire still reaches the clients.
        self.read_all()?;
        self.stats.snapshots += snapshot_count(&self.metrics);
        self.stats.crashes += 1;
        self.stats.torn_crashes += u64::from(torn);
        self.stats.mid_io_crashes += u64::from(mid_io);
        self.queue.clear();
        self.departed.clear();
        self.snapshot_replies.clear();
        for client in &mut self.clients {
            client.conn = None;
        }
        self.model.subscribed.clear();
        self.model.users.clear();
        self.model.expected.clear();
        self.model.expected_undone.clear();
        let disk = self.disk.crash(&mut self.rng, torn);
        self.disk = disk.clone();
        // A new process: new metrics, a store opened on what the disk kept, the scene
        // recovered from it. (The old owner and store hold the dead disk until replaced.)
        self.metrics = Arc::new(Metrics::default());
        let store = Arc::new(
            Store::with_backend(disk).map_err(|e| format!("the store does not reopen: {e}"))?,
        );
        self.owner = open_owner(&store, &self.metrics, &self.config, &self.now)?;
        self.store = store;
        let r = self.owner.seq();
        check!(
            r >= self.model.acked,
            "recovered to sequence {r}, but {} was acknowledged",
            self.model.acked
        );
        check!(
            r <= self.model.seq,
            "recovered to sequence {r}, beyond the {} batches applied",
            self.model.seq
        );
        check!(
            self.owner.map().content_hash() == self.model.hashes[r as usize],
            "the scene recovered at sequence {r} is not the scene acknowledged at {r}"
        );
        for (c, client) in self.clients.iter().enumerate() {
            check!(
                client.replica.seq <= r,
                "client {c} saw sequence {} but the server recovered only to {r}",
                client.replica.seq
            );
        }
        // The history came back as it was at one of the owner's commits at sequence r.
        let server = server_history(
            &self.store,
            SCENE,
            self.owner.map(),
            self.owner.history().users(),
        )?;
        let candidates: Vec<_> = self
            .model
            .committed
            .iter()
            .filter(|(seq, _)| *seq == r)
            .map(|(_, h)| h.clone())
            .collect();
        let Some(history) = candidates.into_iter().find(|h| normal(h) == server) else {
            return Err(format!(
                "the undo history recovered at sequence {r} is none the owner committed at {r}: {}",
                describe(&server, &normal(&self.model.history))
            ));
        };
        self.model.history = history.clone();
        self.model.committed = vec![(r, history)];
        // Batches after r were never acknowledged and are gone: the model forgets them too.
        self.model.seq = r;
        self.model.hashes.truncate(r as usize + 1);
        self.model.map = self.owner.map().clone();
        self.model.base = (r, self.model.map.clone());
        self.model.batches.clear();
        self.note(format!("recovered at sequence {r}"));
        Ok(())
    }

    /// A clean stop (queued commands applied, final snapshot), then the store reopened: the
    /// scene must come back exactly.
    pub fn stop_and_reopen(&mut self) -> Result<(), Failure> {
        let rest = std::mem::take(&mut self.queue);
        self.model.turn(&rest);
        self.owner
            .stop(rest)
            .map_err(|e| format!("clean stop failed: {e}"))?;
        self.read_all()?;
        let (seq, hash) = (self.owner.seq(), self.owner.map().content_hash());
        check!(
            seq == self.model.seq,
            "stopped at {seq}, model at {}",
            self.model.seq
        );
        let store = self.store.clone();
        let loaded = store
            .load_scene(SCENE)
            .map_err(|e| format!("reload after a clean stop: {e}"))?;
        check!(
            loaded.seq == seq && loaded.replayed == 0,
            "a clean stop left sequence {} with {} log entries (want {seq}, 0)",
            loaded.seq,
            loaded.replayed
        );
        check!(
            loaded.map.content_hash() == hash,
            "the snapshot of a clean stop differs from the scene"
        );
        let stored = server_history(&store, SCENE, &loaded.map, loaded.history.into_iter())?;
        let model = normal(&self.model.history);
        check!(
            stored == model,
            "the history a clean stop left differs from the model's: {}",
            describe(&stored, &model)
        );
        Ok(())
    }

    /// One random action.
    fn random_action(&mut self) -> Result<(), Failure> {
        let n = self.clients.len();
        let c = self.rng.random_range(0..n);
        match self.rng.random_range(0..100) {
            0..=34 => {
                if self.clients[c].conn.is_none() {
                    self.join(c);
                } else if self.rng.random_bool(0.2) {
                    let redo = self.rng.random_bool(0.4);
                    self.undo(c, redo);
                } else {
                    let ops = random_batch(&mut self.rng, self.owner.map().size());
                    self.edit(c, ops);
                }
            }
            35..=59 => {
                self.turn()?;
            }
            60..=69 => {
                for c in 0..n {
                    if self.rng.random_bool(self.clients[c].reads) {
                        self.read(c)?;
                    }
                }
            }
            70..=74 => self.join(c),
            75..=77 => self.leave(c),
            78..=80 => {
                let s = self.owner.map().size();
                let eye = std::array::from_fn(|i| self.rng.random_range(-20.0..s[i] as f32 + 20.0));
                self.camera(c, eye);
            }
            81..=82 => {
                let since = self.rng.random_range(0..=self.clients[c].replica.seq);
                self.resume(c, since);
            }
            83..=85 => self.force_snapshot(),
            86..=89 => {
                let secs = self.rng.random_range(0..=90);
                self.advance(Duration::from_secs(secs));
            }
            90..=93 => {
                self.settle()?;
            }
            94..=96 => {
                if !self.disk.is_dead() {
                    let calls = self.rng.random_range(0..80);
                    self.arm(calls);
                }
            }
            _ => self.crash(false)?,
        }
        Ok(())
    }
}

/// The first cell whose brick differs between two maps, for a failure report.
fn first_difference(a: &BrickMap, b: &BrickMap) -> String {
    let bricks = |m: &BrickMap| -> BTreeMap<[u32; 3], (u64, u64)> {
        m.bricks()
            .map(|(brick, version)| {
                let hash = brickcast_protocol::map::brick_hash(0, &brick.mask, &brick.colours);
                (brick.cell, (hash, version))
            })
            .collect()
    };
    let (a, b) = (bricks(a), bricks(b));
    for (cell, (hash, version)) in &a {
        match b.get(cell) {
            None => {
                return format!("the copy has brick {cell:?} (version {version}), the server none");
            }
            Some((h, v)) if h != hash => {
                return format!("brick {cell:?}: copy version {version}, server version {v}");
            }
            _ => {}
        }
    }
    for (cell, (_, v)) in &b {
        if !a.contains_key(cell) {
            return format!("the copy lacks brick {cell:?} (server version {v})");
        }
    }
    "no brick differs".into()
}

fn snapshot_count(metrics: &Metrics) -> u64 {
    metrics.snapshots.load(std::sync::atomic::Ordering::Relaxed)
}

/// Recovers the scene from `store` and starts an owner on the simulation's clock.
fn open_owner(
    store: &Arc<Store>,
    metrics: &Arc<Metrics>,
    config: &OwnerConfig,
    now: &Arc<Mutex<Instant>>,
) -> Result<Owner, Failure> {
    let loaded = store
        .load_scene(SCENE)
        .map_err(|e| format!("recovery failed: {e}"))?;
    let now = now.clone();
    Owner::new(
        SCENE.into(),
        loaded,
        store.clone(),
        metrics.clone(),
        config.clone(),
        Arc::new(move || *now.lock().unwrap_or_else(|e| e.into_inner())),
    )
    .map_err(|e| e.to_string())
}

/// Runs one seed: a random history of `actions` actions with crashes, a final settle and a
/// clean stop.
pub fn run_seed(seed: u64, actions: usize) -> Result<SimStats, (Failure, String)> {
    let mut sim = Sim::new(seed).map_err(|e| (e, String::new()))?;
    let result = (|| {
        for _ in 0..actions {
            sim.random_action()?;
        }
        // However it ended, everyone catches up and agrees, and a clean stop keeps it all.
        if sim.disk.is_dead() {
            sim.crash(false)?;
        }
        sim.disk.disarm();
        for c in 0..sim.clients.len() {
            sim.join(c);
        }
        if sim.settle()? {
            sim.stop_and_reopen()?;
        }
        Ok::<(), Failure>(())
    })();
    sim.stats.snapshots += snapshot_count(&sim.metrics);
    match result {
        Ok(()) => Ok(sim.stats),
        Err(e) => Err((e, sim.trace())),
    }
}
