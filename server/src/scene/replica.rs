//! The owner over a shared log: who may order edits, and how a replica keeps up.
//!
//! **Why the owner thread does this itself:** following the log, taking the scene over and
//! losing it all change the map, the sequence and the history, which only this thread
//! touches. Whoever runs the log around it (the cluster's lease and follower tasks) only feeds
//! it commands: [`Command::Request`], [`Command::Apply`], [`Command::Lead`],
//! [`Command::Follow`], [`Command::Fault`]. Everything here speaks to the [`SceneLog`] trait.
//!
//! * A request from another origin is applied like a local edit when this owner orders, and
//!   answered [`Outcome::NotOwner`] (nothing applied, the sender retries) otherwise; a request
//!   seen before is answered from the replies logged with it.
//! * A turn from the log is applied with [`LogRecord::replay`], the function recovery uses,
//!   unless this owner appended it. A turn after a gap (trimmed below a snapshot before this
//!   replica read it) reloads the scene from the log.
//! * Leading: apply every turn up to the log's end, then claim it (a marker); from then on the
//!   log's fence refuses any other owner's append.
//! * Losing the scene mid-turn (an append refused): nothing of the turn is acknowledged, the
//!   senders are told (they retry on the new owner), and the scene is loaded again from the
//!   log, so the map never holds an edit the log does not.
//! * A log this replica cannot follow (a message that does not decode, a gap): every session
//!   is told why, and the owner stops; the scene is served again only from a fresh load.
//!
//! [`SceneLog`]: super::log::SceneLog
//! [`Command::Request`]: super::Command::Request
//! [`Command::Apply`]: super::Command::Apply
//! [`Command::Lead`]: super::Command::Lead
//! [`Command::Follow`]: super::Command::Follow
//! [`Command::Fault`]: super::Command::Fault

use brickcast_protocol::wire::encode_server;
use tokio::sync::oneshot;

use super::answered::{AnsweredEntry, Lookup};
use super::cells::CellSet;
use super::history::History;
use super::log::{LogError, Turn};
use super::owner::{AckTo, Log, Owner, PendingAck, Remote};
use super::request::{Outcome, Request, RequestItem};
use crate::metrics::Metrics;
use crate::record::LogRecord;
use crate::store::Loaded;

/// How long a scene waits for its log to come back before it gives up on this replica.
const RELOAD_PATIENCE: std::time::Duration = std::time::Duration::from_secs(300);

impl Owner {
    /// Moves the replies to requests from other origins out of `acks`, encoded, onto their
    /// requests (in the order they were applied).
    pub(super) fn take_remote(&mut self, acks: &mut Vec<PendingAck>) {
        // One owner alone: every reply goes to a session (nothing to sort, on the hot path).
        if self.requests.is_empty() {
            return;
        }
        let mut rest = Vec::with_capacity(acks.len());
        for ack in acks.drain(..) {
            let AckTo::Remote(i) = ack.to else {
                rest.push(ack);
                continue;
            };
            match encode_server(&ack.msg) {
                Ok(bytes) => self.requests[i].replies.push(bytes),
                Err(e) => {
                    tracing::error!(scene = %self.name, error = %e, "cannot encode a reply to a request");
                    self.metrics.count_unencodable(ack.msg.kind());
                }
            }
        }
        *acks = rest;
    }

    /// This turn's requests and their replies, as the log records them.
    pub(super) fn answered_entries(&self) -> Vec<AnsweredEntry> {
        self.requests
            .iter()
            .map(|r| (r.origin.clone(), r.number, r.replies.clone()))
            .collect()
    }

    /// Records and sends the replies of a committed turn's requests.
    pub(super) fn answer_remote(&mut self) {
        for r in self.requests.drain(..) {
            self.answered.record(r.origin, r.number, r.replies.clone());
            if let Some(reply) = r.reply {
                let _ = reply.send(Outcome::Done(r.replies));
            }
        }
    }

    /// Whether a request was applied in this turn and is not committed yet (its retry must
    /// wait for the commit, then gets the recorded replies).
    pub(super) fn pending_request(&self, request: &Request) -> bool {
        self.answered.lookup(&request.origin, request.number) == Lookup::Pending
    }

    /// A request from another origin.
    pub(super) fn request(
        &mut self,
        reply: Option<oneshot::Sender<Outcome>>,
        request: Request,
        acks: &mut Vec<PendingAck>,
        log: &mut Log,
    ) {
        if !self.log.may_order() {
            if let Some(reply) = reply {
                let _ = reply.send(Outcome::NotOwner);
            }
            return;
        }
        let Request {
            origin,
            number,
            user,
            editor,
            items,
        } = request;
        let Some(reply) = reply else {
            // Nobody waits for an answer: only a history drop goes this way.
            for (_, kind) in items {
                if kind == RequestItem::Forget {
                    self.history.forget(user);
                    self.undo_budget.remove(&user);
                }
            }
            return;
        };
        match self.answered.lookup(&origin, number) {
            // A retry of a request already applied (here or by an earlier owner).
            Lookup::Done(replies) => {
                let _ = reply.send(Outcome::Done(replies));
                return;
            }
            // A copy its sender no longer waits for; or (cannot happen: the turn commits
            // before such a retry is taken) one still being committed.
            Lookup::Stale | Lookup::Pending => return,
            Lookup::New => self.answered.begin(&origin, number),
        }
        let to = AckTo::Remote(self.requests.len());
        self.requests.push(Remote {
            origin,
            number,
            reply: Some(reply),
            replies: Vec::new(),
        });
        for (client_seq, kind) in items {
            match kind {
                RequestItem::Edit(ops) => {
                    let ack = self.apply_batch(to, client_seq, ops, editor.then_some(user), log);
                    acks.push(ack);
                }
                RequestItem::Undo { redo } => {
                    // A request's undo is never planned across turns (`undo_job.rs`): its
                    // answer is logged with this turn.
                    acks.extend(self.undo(to, user, editor, client_seq, redo, log));
                }
                RequestItem::Forget => {
                    self.history.forget(user);
                    self.undo_budget.remove(&user);
                }
            }
        }
    }

    /// The turn of the log at position `pos`.
    pub(super) fn replicate(&mut self, pos: u64, turn: Turn) {
        if self.broken || !self.log.shared() || pos <= self.log.position() {
            return;
        }
        if self.log.may_order() {
            // Someone else appended: this owner's own appends all landed before it (the log is
            // one sequence), so the map is still the log's, up to here.
            tracing::warn!(scene = %self.name, pos, node = %turn.node, "another node appended to the scene's log; this node stops ordering edits");
            self.log.follow();
            Metrics::add(&self.metrics.stepdowns, 1);
        }
        if pos != self.log.position() + 1 {
            tracing::info!(scene = %self.name, pos, at = self.log.position(), "the log was trimmed past this replica; loading the newest snapshot");
            self.reload();
            return;
        }
        self.apply_turn(pos, turn);
    }

    /// The log now starts at `first`: when this replica has not read up to just before it,
    /// what it missed is only in the snapshot.
    pub(super) fn behind(&mut self, first: u64) {
        if self.broken || !self.log.shared() || first <= self.log.position() + 1 {
            return;
        }
        tracing::info!(scene = %self.name, first, at = self.log.position(), "the log was trimmed past this replica; loading the newest snapshot");
        self.reload();
    }

    /// Applies one turn another owner appended. False (and the scene stops here) when it does
    /// not fit: a gap in the scene's sequence, or a record that does not decode or apply.
    fn apply_turn(&mut self, pos: u64, turn: Turn) -> bool {
        let limits = LogRecord::replay_limits();
        for (s, bytes) in &turn.records {
            let fault = if *s != self.seq + 1 {
                Some(format!(
                    "log message {pos} holds sequence {s} after {}: the log has a gap or repeats",
                    self.seq
                ))
            } else {
                match LogRecord::decode(bytes) {
                    Err(e) => Some(format!("log entry {s} does not decode: {e}")),
                    Ok(record) => {
                        self.map.set_sequence(*s);
                        match record.replay(&mut self.map, &limits) {
                            Err(e) => Some(format!("log entry {s} does not apply: {e}")),
                            Ok(()) => {
                                self.seq = *s;
                                self.log_entries += 1;
                                self.log_ops += record.op_count() as u64;
                                None
                            }
                        }
                    }
                }
            };
            if let Some(fault) = fault {
                self.refuse_log(&fault);
                return false;
            }
        }
        self.history.apply_committed(&turn.history);
        self.log.applied(pos, &turn);
        for (origin, number, replies) in turn.requests {
            self.answered.record(origin, number, replies);
        }
        Metrics::add(&self.metrics.turns_replicated, 1);
        true
    }

    /// The log cannot be followed: say so loudly, and stop serving the scene from this
    /// replica (after this turn) rather than show, or order edits on, a scene that forked from
    /// it. It is served again only from a fresh load.
    pub(super) fn refuse_log(&mut self, fault: &str) {
        if self.broken {
            return;
        }
        self.broken = true;
        tracing::error!(scene = %self.name, fault, "the scene's log does not fit this replica; this node stops serving the scene (it loads it again when someone asks)");
        self.log.follow();
        self.fail_all(&format!("the scene's log is inconsistent: {fault}"));
    }

    /// This owner may lead: catch up to the log's end, then claim it.
    pub(super) fn take_over(&mut self) -> bool {
        if self.broken || !self.log.shared() {
            return false;
        }
        // Asked again while it leads (the lease task saw it before this turn published it).
        if self.log.may_order() {
            return true;
        }
        for attempt in 0..2 {
            match self.log.tail() {
                Ok(turns) => {
                    for (pos, turn) in turns {
                        if !self.apply_turn(pos, turn) {
                            return false;
                        }
                    }
                    break;
                }
                Err(e) if e.is_fault() => {
                    self.refuse_log(&e.to_string());
                    return false;
                }
                Err(e) if attempt == 0 => {
                    tracing::info!(scene = %self.name, error = %e, "catching up by loading the newest snapshot");
                    self.reload();
                    if self.broken {
                        return false;
                    }
                }
                Err(e) => {
                    tracing::warn!(scene = %self.name, error = %e, "cannot catch up with the log; not taking the scene");
                    return false;
                }
            }
        }
        match self.log.claim() {
            Ok(()) => {
                tracing::info!(scene = %self.name, seq = self.seq, pos = self.log.position(), "this node owns the scene");
                true
            }
            Err(e) => {
                tracing::info!(scene = %self.name, error = %e, "another node claimed the scene first");
                false
            }
        }
    }

    /// The lease is gone: stop ordering edits (the map is the log's: every append landed).
    pub(super) fn step_down(&mut self, why: &str) {
        if self.log.shared() && self.log.may_order() {
            self.log.follow();
            Metrics::add(&self.metrics.stepdowns, 1);
            tracing::warn!(scene = %self.name, why, "this node no longer owns the scene");
        }
    }

    /// An append failed: this turn's edits are not durable. Their senders hear "not the
    /// owner" (nothing applied) or "unknown" (an append may have landed); either way they
    /// retry, and the owner then answers from the log. The map is loaded again from the log.
    pub(super) fn lost_lead(&mut self, error: &LogError) {
        tracing::warn!(scene = %self.name, %error, "a turn could not be logged; its edits are dropped and the scene is reloaded from the log");
        Metrics::add(&self.metrics.stepdowns, 1);
        let answer = if matches!(error, LogError::Deposed { .. }) {
            Outcome::NotOwner
        } else {
            Outcome::Unknown
        };
        for r in self.requests.drain(..) {
            if let Some(reply) = r.reply {
                let _ = reply.send(answer.clone());
            }
        }
        self.log.follow();
        if !self.stopping {
            self.reload();
        }
    }

    /// Replaces the map, sequence and history with the log's (snapshot + turns). Sessions
    /// resync from what they were last sent.
    ///
    /// A log out of reach (NATS restarting, a network blip) is waited out, blocking this
    /// scene's thread: nothing can be ordered or made durable meanwhile anyway. A log that
    /// does not fit its snapshot stops the scene on this replica.
    pub(super) fn reload(&mut self) {
        let started = (self.clock)();
        loop {
            let fault = match self.log.reload() {
                Ok(loaded) => return self.reset_from(loaded),
                Err(e) if e.is_fault() => e,
                Err(e) if (self.clock)().saturating_duration_since(started) < RELOAD_PATIENCE => {
                    tracing::warn!(scene = %self.name, error = %e, "cannot load the scene from its log yet; trying again");
                    self.log.pause();
                    continue;
                }
                Err(e) => e,
            };
            let fault = format!("the scene could not be loaded from its log: {fault}");
            return self.refuse_log(&fault);
        }
    }

    fn reset_from(&mut self, loaded: Loaded) {
        let Loaded {
            mut map,
            seq,
            replay_touched,
            history,
            last_step_id,
            answered,
            ..
        } = loaded;
        map.set_sequence(seq);
        map.record_touched(true);
        self.map = map;
        self.seq = seq;
        self.broadcast_seq = seq;
        self.history = History::new(
            history,
            last_step_id,
            self.config.limits.max_undo_steps,
            self.config.limits.max_undo_bytes,
        )
        .with_scene_cap(self.config.max_history_bytes);
        self.answered = super::answered::Answered::from_entries(answered);
        self.unsnapshotted = CellSet::from_cells(&replay_touched);
        for sub in self.subs.values_mut() {
            sub.delivered = sub.delivered.min(seq);
            sub.lagging = true;
        }
        // The reloaded palette may be newer than what the sessions heard, and the resyncs
        // carry only bricks.
        self.broadcast_palette();
        self.restart_levels();
    }
}
