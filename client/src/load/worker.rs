//! One load client: a tokio task with its own websocket and its own copy of the scene.
//!
//! Editors send edit batches (paced, or as fast as a bounded number of unacknowledged batches
//! allows) and time their acks; every client, editor or viewer, applies every delta to its copy
//! and logs when each delta arrived so the editor it observes can time edit→visible. At the end
//! each copy is hashed against a fresh copy of the server's scene.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use std::collections::HashMap;

use brickcast_protocol::wire::{ClientMsg, Cursor, ErrorCode, Role, ServerMsg, View};
use futures_util::FutureExt;
use tokio::sync::{mpsc, watch};

use super::copy::{DeltaCache, FLUSH_BYTES, LazyCopy};
use super::histogram::Histogram;
use super::observe::ObserverLog;
use super::ops::{NothingToPaint, OpGen};
use super::options::{OpKind, VoxelBox};
use crate::link::{self, Link, LinkError};
use crate::replica::{Replica, ReplicaError};

/// Work one client may have out unacknowledged, in single-voxel ops (a sphere counts for the
/// voxels it covers, see [`op_cost`]), rounded up to whole batches and at least
/// [`MIN_UNACKED_BATCHES`]. It bounds what a client queues in the server (so "as fast as acks
/// allow" measures the server, not an ever-growing backlog) and, with group commit, how much
/// one commit carries: about clients × this. Counted in work rather than messages so that the
/// offered load does not depend on `--batch`, and a sphere brush, a thousand times the work of a
/// voxel, does not pile up a thousand times the backlog.
pub const MAX_UNACKED_COST: f64 = 2048.0;
/// Fewest unacknowledged batches a client may have out, so large batches still overlap.
pub const MIN_UNACKED_BATCHES: usize = 2;
/// Messages handled in a row when they are already there, before the client looks at its
/// schedule again: replies to a burst of batches come in a burst, and answering each with its
/// own write would make the load generator pay a system call per ack.
const READ_BURST: usize = 256;

/// Roughly what one op costs the server, in single-voxel ops: a brush costs about a thirty-
/// second of a voxel op per voxel it covers (the server's own replay-cost estimate), a ray a few
/// (it is traced first).
pub fn op_cost(op: OpKind, radius: f32) -> f64 {
    match op {
        OpKind::Voxel | OpKind::Paint => 1.0,
        OpKind::Ray => 4.0,
        OpKind::Sphere => {
            let r = f64::from(radius.max(0.0));
            1.0 + 4.19 * r * r * r / 32.0
        }
    }
}

/// Unacknowledged batches a client of `batch` ops of `cost` each may have out.
pub fn max_unacked(batch: u32, cost: f64) -> usize {
    let per_batch = f64::from(batch.max(1)) * cost.max(1.0);
    ((MAX_UNACKED_COST / per_batch).ceil() as usize).max(MIN_UNACKED_BATCHES)
}

/// Where the whole run is; the coordinator moves it forward, every client follows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Phase {
    /// Clients connect and sync; nobody edits yet.
    Setup,
    /// Edit from `start` until `end`, then wait for the outstanding acks.
    Run { start: Instant, end: Instant },
    /// Editing is over: keep applying deltas until the copy hashes to `hash` or `deadline`.
    Verify { hash: u64, deadline: Instant },
    /// Something failed: stop now.
    Abort,
}

/// What clients tell the coordinator.
#[derive(Debug)]
pub enum Event {
    /// Connected and synced (or why not).
    Ready {
        index: usize,
        result: Result<(), String>,
    },
    /// An editor stopped sending and every batch it sent is acknowledged.
    Drained {
        index: usize,
        last_ack: Option<Instant>,
    },
}

/// Counters the progress line reads while the run goes.
#[derive(Default)]
pub struct Live {
    /// Bricks the connections' syncs will bring (their Welcomes' counts, summed) and have
    /// brought so far: the setup's progress.
    pub sync_total: AtomicU64,
    pub sync_received: AtomicU64,
    pub ops_acked: AtomicU64,
    pub acks: AtomicU64,
    pub ack_ns: AtomicU64,
    pub rejected: AtomicU64,
    pub resyncs: AtomicU64,
    pub errors: AtomicU64,
}

/// Presence messages a client sent, for timing when the others see them: the message's number
/// and the sender's client index travel in its view (`eye[0]`, `eye[1]`), the send time stays
/// here. The index, not the server's peer id: in a cluster each node shows a peer under an id
/// of its own.
#[derive(Default)]
pub struct PresenceBoard {
    /// Per client: (message number, sent), the last few.
    sent: Vec<Mutex<VecDeque<(u32, Instant)>>>,
}

/// How many sends a client remembers: a presence older than this many messages is not timed.
const PRESENCE_REMEMBERED: usize = 64;

impl PresenceBoard {
    fn new(connections: usize) -> PresenceBoard {
        PresenceBoard {
            sent: (0..connections).map(|_| Mutex::default()).collect(),
        }
    }

    fn sent(&self, index: usize, number: u32, at: Instant) {
        let mut sent = self.sent[index].lock().unwrap_or_else(|e| e.into_inner());
        if sent.len() == PRESENCE_REMEMBERED {
            sent.pop_front();
        }
        sent.push_back((number, at));
    }

    /// Which client sent the presence `view`, its message number and when, if it is one of
    /// ours and remembered.
    fn sent_at(&self, view: &View) -> Option<(usize, u32, Instant)> {
        let [number, index, zero] = view.eye;
        let whole = |v: f32| v >= 0.0 && v.fract() == 0.0 && v < 16_777_216.0;
        if !(whole(number) && whole(index) && zero == 0.0) {
            return None;
        }
        let (number, index) = (number as u32, index as usize);
        let sent = self
            .sent
            .get(index)?
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        sent.iter()
            .find(|(n, _)| *n == number)
            .map(|&(_, at)| (index, number, at))
    }
}

/// State every client task shares.
pub struct Shared {
    /// One per connection: what that connection saw, for the editor it observes.
    pub observers: Vec<Mutex<ObserverLog>>,
    pub live: Live,
    pub cache: DeltaCache,
    pub presence: PresenceBoard,
    /// Clients connecting and syncing now are bounded by this (see [`SETUP_AT_ONCE`]).
    pub setup: tokio::sync::Semaphore,
}

/// Clients that connect and sync at the same time. Hundreds at once split the server's and
/// the generator's time so finely that one client can wait past its Welcome timeout although
/// the scene is fine; in waves, every client's sync is quick, and the whole setup takes about
/// as long (it is the same work).
pub const SETUP_AT_ONCE: usize = 64;

impl Shared {
    pub fn new(connections: usize) -> Shared {
        Shared {
            observers: (0..connections).map(|_| Mutex::default()).collect(),
            live: Live::default(),
            cache: DeltaCache::default(),
            presence: PresenceBoard::new(connections),
            setup: tokio::sync::Semaphore::new(SETUP_AT_ONCE),
        }
    }

    pub fn observer(&self, index: usize) -> MutexGuard<'_, ObserverLog> {
        // A panicking client task cannot leave a log half-updated in a way that matters more
        // than losing the whole run would.
        self.observers[index]
            .lock()
            .unwrap_or_else(|e| e.into_inner())
    }
}

/// What an editing client does.
#[derive(Clone, Debug)]
pub struct EditorPlan {
    pub op: OpKind,
    pub area: VoxelBox,
    pub radius: f32,
    pub batch: u32,
    /// Fraction of messages that are undos or redos instead of edits.
    pub undo_ratio: f64,
    /// Time between batches; `None`: as fast as [`max_unacked`] allows.
    pub interval: Option<Duration>,
    /// The connection whose arrivals time this editor's edits (`None` with nobody else).
    pub observer: Option<usize>,
}

/// One client of the run.
#[derive(Clone, Debug)]
pub struct ClientPlan {
    pub index: usize,
    pub url: String,
    pub token: Option<String>,
    /// `None`: a viewer.
    pub editor: Option<EditorPlan>,
    /// Whether this client also counts the voxels each delta changes in its copy (see
    /// [`LazyCopy`]).
    pub count_voxels: bool,
    /// Presence messages per second (0: none).
    pub presence_hz: f64,
}

/// The outcome of the end-of-run check.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// The client stopped before the check (see its errors).
    NotChecked,
    Match,
    /// The copy still differed from the fresh one at the deadline.
    Mismatch {
        hash: u64,
        seq: u64,
    },
}

/// What one client measured.
pub struct ClientReport {
    pub index: usize,
    pub editor: bool,
    pub bytes_in: u64,
    pub bytes_out: u64,
    pub ops_acked: u64,
    pub rejected: u64,
    pub resyncs: u64,
    pub undos: u64,
    pub undos_refused: u64,
    pub undo_voxels: u64,
    pub ack_latency: Histogram,
    /// From another client sending a presence to this one seeing it.
    pub presence_latency: Histogram,
    pub presence_sent: u64,
    pub last_ack: Option<Instant>,
    /// Voxels the received deltas changed in this copy (only with `count_voxels`).
    pub voxels_seen: u64,
    pub errors: Vec<String>,
    pub verdict: Verdict,
}

impl ClientReport {
    /// Nothing measured yet.
    pub fn new(index: usize, editor: bool) -> ClientReport {
        ClientReport {
            index,
            editor,
            bytes_in: 0,
            bytes_out: 0,
            ops_acked: 0,
            rejected: 0,
            resyncs: 0,
            undos: 0,
            undos_refused: 0,
            undo_voxels: 0,
            ack_latency: Histogram::default(),
            presence_latency: Histogram::default(),
            presence_sent: 0,
            last_ack: None,
            voxels_seen: 0,
            errors: Vec::new(),
            verdict: Verdict::NotChecked,
        }
    }
}

/// Why a client stopped early.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error("its copy of the scene broke: {0}")]
    Replica(#[from] ReplicaError),
    #[error("the server said {code:?}: {message}")]
    Server { code: ErrorCode, message: String },
    #[error("the server gave it the {0:?} role, which may not edit (pass an editor --token)")]
    NotEditor(Role),
    #[error("the server closed the connection")]
    Closed,
    #[error(
        "the server acknowledged batch {0}, which this client never sent or was already acknowledged"
    )]
    UnknownAck(u64),
    #[error(transparent)]
    Paint(#[from] NothingToPaint),
    #[error("stopped: another client failed")]
    Aborted,
}

/// Runs one client to the end of the run. Always answers `Ready` (and, for editors, `Drained`)
/// so the coordinator never waits on a client that failed.
pub async fn client(
    plan: ClientPlan,
    shared: Arc<Shared>,
    control: watch::Receiver<Phase>,
    events: mpsc::UnboundedSender<Event>,
) -> ClientReport {
    let mut c = Client {
        plan,
        shared,
        control,
        events,
        ready_sent: false,
        drained_sent: false,
        inflight: VecDeque::new(),
        user: crate::identity::random_id(),
        undo_credit: 0.0,
        undone: 0,
        presence_seen: HashMap::new(),
    };
    let mut report = ClientReport::new(c.plan.index, c.plan.editor.is_some());
    let mut link = None;
    let result = c.run(&mut link, &mut report).await;
    if let Some(link) = link {
        report.bytes_in = link.bytes_in;
        report.bytes_out = link.bytes_out;
        link.close().await;
    }
    if let Err(e) = result {
        c.shared.live.errors.fetch_add(1, Relaxed);
        let text = format!("client {}: {e}", c.plan.index);
        if !c.ready_sent {
            let _ = c.events.send(Event::Ready {
                index: c.plan.index,
                result: Err(text.clone()),
            });
            c.ready_sent = true;
        }
        report.errors.push(text);
    }
    if c.plan.editor.is_some() && !c.drained_sent {
        let _ = c.events.send(Event::Drained {
            index: c.plan.index,
            last_ack: report.last_ack,
        });
    }
    report
}

/// One client task's state between awaits: what it was asked to do, where it shares results,
/// and the batches it is still waiting to hear about.
struct Client {
    plan: ClientPlan,
    shared: Arc<Shared>,
    control: watch::Receiver<Phase>,
    events: mpsc::UnboundedSender<Event>,
    ready_sent: bool,
    drained_sent: bool,
    /// Sent, unacknowledged batches: (client_seq, when sent).
    inflight: VecDeque<(u64, Instant)>,
    /// This client's user id: its undo history.
    user: u64,
    /// `--undo-ratio` bookkeeping: owed history messages, and steps undone since the last edit
    /// (a redo is sent while there are some).
    undo_credit: f64,
    undone: u32,
    /// The highest presence number seen from each other client (older ones are not timed).
    presence_seen: HashMap<usize, u32>,
}

impl Client {
    async fn run(
        &mut self,
        slot: &mut Option<Link>,
        report: &mut ClientReport,
    ) -> Result<(), ClientError> {
        let index = self.plan.index;
        let name = match self.plan.editor {
            Some(_) => format!("brickcast load editor {index}"),
            None => format!("brickcast load viewer {index}"),
        };
        // Connect and sync, unless the run is aborted meanwhile.
        let mut abort = self.control.clone();
        let setup = async {
            // Never closed: `acquire` cannot fail.
            let _turn = self.shared.setup.acquire().await.ok();
            let mut link = Link::connect(
                &self.plan.url,
                &name,
                self.user,
                self.plan.token.as_deref(),
                None,
            )
            .await?;
            let welcome = link.welcome.clone();
            if self.plan.editor.is_some() && welcome.role != Role::Editor {
                return Err(ClientError::NotEditor(welcome.role));
            }
            let mut replica = Replica::new(&welcome.scene, welcome.size)?;
            replica.record_gpu_changes(false);
            replica.sync_total = welcome.total_bricks;
            let live = &self.shared.live;
            live.sync_total
                .fetch_add(u64::from(welcome.total_bricks), Relaxed);
            let mut counted = 0;
            link::sync(&mut link, &mut replica, |r| {
                live.sync_received
                    .fetch_add(r.bricks_received - counted, Relaxed);
                counted = r.bricks_received;
            })
            .await?;
            Ok::<_, ClientError>((link, replica))
        };
        let (link, replica) = tokio::select! {
            done = setup => done?,
            _ = abort.wait_for(|p| *p == Phase::Abort) => return Err(ClientError::Aborted),
        };
        let link = slot.insert(link);
        self.shared.observer(index).synced(replica.seq);
        let ops = match &self.plan.editor {
            Some(e) => Some(OpGen::new(
                e.op,
                e.area,
                e.radius,
                index as u64,
                &replica.map,
            )?),
            None => None,
        };
        let flush_at = FLUSH_BYTES / 2 + FLUSH_BYTES / 2 * index / self.shared.observers.len();
        let mut copy = LazyCopy::new(replica, self.plan.count_voxels, flush_at)?;
        let _ = self.events.send(Event::Ready {
            index,
            result: Ok(()),
        });
        self.ready_sent = true;
        let result = self.edit_and_check(link, &mut copy, ops, report).await;
        report.voxels_seen = copy.voxels_seen;
        result
    }

    /// The run after setup: edit (editors), follow the scene, and finally check the copy.
    async fn edit_and_check(
        &mut self,
        link: &mut Link,
        copy: &mut LazyCopy,
        mut ops: Option<OpGen>,
        report: &mut ClientReport,
    ) -> Result<(), ClientError> {
        let index = self.plan.index;
        let mut next_client_seq = 1u64;
        let mut due: Option<Instant> = None;
        let presence_every = (self.plan.presence_hz > 0.0)
            .then(|| Duration::from_secs_f64(1.0 / self.plan.presence_hz));
        let mut presence_due: Option<Instant> = None;
        let mut presence_number = 0u32;
        // Whether the copy changed since it was last hashed.
        let mut dirty = true;
        loop {
            let phase = *self.control.borrow_and_update();
            let mut wake = None;
            match phase {
                Phase::Abort => return Err(ClientError::Aborted),
                Phase::Setup => {}
                Phase::Run { start, end } => {
                    if let Some(every) = presence_every
                        && Instant::now() < end
                    {
                        // Spread over one interval, like the edits.
                        let due = presence_due.get_or_insert_with(|| {
                            start + every.mul_f64(index as f64 / self.shared.observers.len() as f64)
                        });
                        let now = Instant::now();
                        if now >= *due {
                            presence_number += 1;
                            let msg = ClientMsg::Presence {
                                view: Some(View {
                                    eye: [presence_number as f32, index as f32, 0.0],
                                    forward: [0.0, 0.0, 1.0],
                                }),
                                cursor: Some(Cursor {
                                    voxel: [0, 0, 0],
                                    radius: (presence_number % 8) as f32,
                                }),
                                selection: None,
                            };
                            self.shared.presence.sent(index, presence_number, now);
                            link.send(&msg).await?;
                            report.presence_sent += 1;
                            while *due <= now {
                                *due += every;
                            }
                        }
                        wake = Some(*due);
                    }
                    if let (Some(plan), Some(ops)) = (&self.plan.editor, &mut ops) {
                        let now = Instant::now();
                        if now < end {
                            // Spread the clients' first batches over one interval so paced
                            // clients do not send in lockstep.
                            let due = due.get_or_insert_with(|| match plan.interval {
                                Some(iv) => start + iv.mul_f64(index as f64 / (index as f64 + 1.0)),
                                None => start,
                            });
                            let mut fed = false;
                            let window = max_unacked(plan.batch, op_cost(plan.op, plan.radius));
                            while self.inflight.len() < window && now >= *due {
                                let client_seq = next_client_seq;
                                self.undo_credit += plan.undo_ratio;
                                let msg = if self.undo_credit >= 1.0 {
                                    self.undo_credit -= 1.0;
                                    if self.undone > 0 {
                                        self.undone -= 1;
                                        ClientMsg::Redo { client_seq }
                                    } else {
                                        self.undone += 1;
                                        ClientMsg::Undo { client_seq }
                                    }
                                } else {
                                    self.undone = 0;
                                    let ops = (0..plan.batch).map(|_| ops.next_op()).collect();
                                    ClientMsg::Edit { client_seq, ops }
                                };
                                let sent = Instant::now();
                                link.feed(&msg).await?;
                                self.inflight.push_back((next_client_seq, sent));
                                next_client_seq += 1;
                                fed = true;
                                if let Some(iv) = plan.interval {
                                    *due += iv;
                                }
                            }
                            if fed {
                                link.flush().await?;
                            }
                            let edits_wake = match plan.interval {
                                Some(_) if self.inflight.len() < window => (*due).min(end),
                                _ => end,
                            };
                            wake = Some(wake.map_or(edits_wake, |w: Instant| w.min(edits_wake)));
                        } else if self.inflight.is_empty() && !self.drained_sent {
                            let _ = self.events.send(Event::Drained {
                                index,
                                last_ack: report.last_ack,
                            });
                            self.drained_sent = true;
                        }
                    }
                }
                Phase::Verify { hash, deadline } => {
                    if !self.inflight.is_empty() {
                        report.errors.push(format!(
                            "client {index}: {} batches were never acknowledged",
                            self.inflight.len()
                        ));
                        self.shared.live.errors.fetch_add(1, Relaxed);
                        self.inflight.clear();
                    }
                    if dirty {
                        dirty = false;
                        let replica = copy.current()?;
                        if replica.synced && replica.map.content_hash() == hash {
                            report.verdict = Verdict::Match;
                            return Ok(());
                        }
                    }
                    if Instant::now() >= deadline {
                        let replica = copy.current()?;
                        report.verdict = Verdict::Mismatch {
                            hash: replica.map.content_hash(),
                            seq: replica.seq,
                        };
                        return Ok(());
                    }
                    wake = Some(deadline);
                }
            }
            let sleep = async {
                match wake {
                    Some(at) => tokio::time::sleep_until(at.into()).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                biased;
                changed = self.control.changed() => {
                    if changed.is_err() {
                        return Err(ClientError::Aborted);
                    }
                }
                msg = link.next() => {
                    let at = Instant::now();
                    let msg = msg?.ok_or(ClientError::Closed)?;
                    self.handle(&msg, at, copy, report)?;
                    dirty = true;
                    // Reading a websocket message is cancel-safe: a message not ready yet
                    // stays in the socket for the next round.
                    for _ in 1..READ_BURST {
                        let Some(next) = link.next().now_or_never() else {
                            break;
                        };
                        let msg = next?.ok_or(ClientError::Closed)?;
                        self.handle(&msg, Instant::now(), copy, report)?;
                    }
                }
                () = sleep => {}
            }
        }
    }

    /// An edit or undo was answered: it leaves the in-flight list, its latency is recorded, and
    /// the observing client learns which sequence shows it.
    fn answered(
        &mut self,
        client_seq: u64,
        seq: Option<u64>,
        at: Instant,
        report: &mut ClientReport,
    ) -> Result<(), ClientError> {
        let i = self
            .inflight
            .iter()
            .position(|&(c, _)| c == client_seq)
            .ok_or(ClientError::UnknownAck(client_seq))?;
        let (_, sent) = self
            .inflight
            .remove(i)
            .ok_or(ClientError::UnknownAck(client_seq))?;
        let took = at.saturating_duration_since(sent);
        report.ack_latency.record(took);
        report.last_ack = Some(at);
        let live = &self.shared.live;
        live.acks.fetch_add(1, Relaxed);
        live.ack_ns
            .fetch_add(took.as_nanos().min(u128::from(u64::MAX)) as u64, Relaxed);
        if let (Some(seq), Some(observer)) =
            (seq, self.plan.editor.as_ref().and_then(|e| e.observer))
        {
            self.shared.observer(observer).acked(seq, sent);
        }
        Ok(())
    }

    fn handle(
        &mut self,
        msg: &ServerMsg,
        at: Instant,
        copy: &mut LazyCopy,
        report: &mut ClientReport,
    ) -> Result<(), ClientError> {
        match msg {
            ServerMsg::Ack {
                client_seq,
                seq,
                applied,
                rejected,
            } => {
                self.answered(*client_seq, *seq, at, report)?;
                report.ops_acked += u64::from(*applied);
                report.rejected += rejected.len() as u64;
                let live = &self.shared.live;
                live.ops_acked.fetch_add(u64::from(*applied), Relaxed);
                live.rejected.fetch_add(rejected.len() as u64, Relaxed);
            }
            ServerMsg::Undone {
                client_seq,
                seq,
                restored,
                refused,
                ..
            } => {
                self.answered(*client_seq, *seq, at, report)?;
                if refused.is_some() {
                    report.undos_refused += 1;
                } else {
                    report.undos += 1;
                    report.undo_voxels += restored;
                }
            }
            ServerMsg::Error { code, message } => {
                return Err(ClientError::Server {
                    code: *code,
                    message: message.clone(),
                });
            }
            ServerMsg::Resync { .. } => {
                report.resyncs += 1;
                self.shared.live.resyncs.fetch_add(1, Relaxed);
            }
            ServerMsg::Presence { states, .. } => {
                for state in states {
                    let Some(view) = state.view else { continue };
                    let Some((from, number, sent)) = self.shared.presence.sent_at(&view) else {
                        continue;
                    };
                    if from == self.plan.index {
                        continue;
                    }
                    let seen = self.presence_seen.entry(from).or_insert(0);
                    if number > *seen {
                        *seen = number;
                        report
                            .presence_latency
                            .record(at.saturating_duration_since(sent));
                    }
                }
            }
            _ => {}
        }
        copy.apply(msg, &self.shared.cache)?;
        match msg {
            ServerMsg::Delta {
                from_seq, to_seq, ..
            } => self
                .shared
                .observer(self.plan.index)
                .delta(*from_seq, *to_seq, at),
            ServerMsg::SyncDone { seq } => self.shared.observer(self.plan.index).synced(*seq),
            _ => {}
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_unacked_window_is_counted_in_work() {
        let voxel = op_cost(OpKind::Voxel, 4.0);
        assert_eq!(max_unacked(1, voxel), 2048);
        assert_eq!(max_unacked(64, voxel), 32);
        assert_eq!(max_unacked(100, voxel), 21);
        assert_eq!(max_unacked(4096, voxel), MIN_UNACKED_BATCHES);
        assert_eq!(max_unacked(0, voxel), 2048);
        // A radius-8 sphere covers ~2,145 voxels: ~68 voxel ops of work.
        let sphere = op_cost(OpKind::Sphere, 8.0);
        assert!((sphere - 68.0).abs() < 1.0, "{sphere}");
        assert_eq!(max_unacked(1, sphere), 31);
        assert_eq!(max_unacked(4, sphere), 8);
        assert_eq!(
            max_unacked(1, op_cost(OpKind::Sphere, 64.0)),
            MIN_UNACKED_BATCHES
        );
    }
}
