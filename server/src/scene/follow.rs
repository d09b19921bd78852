//! The owner in a cluster: who may order edits, and how a replica keeps up.
//!
//! **Why the owner thread does this itself:** following the log, taking the scene over and
//! losing it all change the map, the sequence and the history, which only this thread
//! touches. The tasks in `crate::cluster::lease` only feed it commands.
//!
//! * A forwarded edit is applied like a local one when this node leads, and answered "not the
//!   owner" (nothing applied, the sender retries) otherwise.
//! * A turn from the log is applied with [`LogRecord::replay`], the function recovery uses,
//!   unless this node appended it. A turn after a gap (trimmed below a snapshot before this
//!   node read it) reloads the scene from the snapshot.
//! * Taking over: apply every turn up to the log's end, then append a marker; from then on the
//!   log's expected-sequence fence refuses any other node's append.
//! * Losing the lease mid-turn (an append refused): nothing of the turn is acknowledged, the
//!   senders are told "not the owner" (they retry on the new owner), and the scene is loaded
//!   again from the log, so the map never holds an edit the log does not.

use brickcast_protocol::wire::encode_server;

use super::history::History;
use super::owner::{AckTo, Log, Owner, PendingAck, Remote};
use crate::cluster::forward::{ForwardKind, ForwardReply, Forwarded};
use crate::cluster::{Lookup, Turn};
use crate::metrics::Metrics;
use crate::record::LogRecord;
use crate::store::{Loaded, StoreError};

/// How long a scene waits for NATS to come back before it gives up on this node.
const RELOAD_PATIENCE: std::time::Duration = std::time::Duration::from_secs(300);

impl Owner {
    /// Takes the forwarded requests' replies out of `acks`, encoded, one entry per request
    /// in the order they were applied.
    pub(super) fn take_remote(&self, acks: &mut Vec<PendingAck>) -> Vec<(Remote, Vec<Vec<u8>>)> {
        let mut remote: Vec<(Remote, Vec<Vec<u8>>)> = Vec::new();
        // One node: every reply goes to a local session (nothing to sort, on the hot path).
        if !self.backend.clustered() {
            return remote;
        }
        let mut rest = Vec::with_capacity(acks.len());
        for ack in acks.drain(..) {
            let AckTo::Remote(to) = ack.to else {
                rest.push(ack);
                continue;
            };
            let bytes = match encode_server(&ack.msg) {
                Ok(bytes) => bytes,
                Err(e) => {
                    tracing::error!(scene = %self.name, error = %e, "cannot encode a reply to a forwarded edit");
                    self.metrics.count_unencodable(ack.msg.kind());
                    continue;
                }
            };
            match remote.last_mut() {
                Some((r, msgs)) if *r == to => msgs.push(bytes),
                _ => remote.push((to, vec![bytes])),
            }
        }
        *acks = rest;
        remote
    }

    /// Hands the turn's requests to the cluster's log, which writes them with the turn.
    pub(super) fn stage_remote(&mut self, remote: &[(Remote, Vec<Vec<u8>>)]) {
        if let Some(jet) = self.backend.jet() {
            jet.stage(
                remote
                    .iter()
                    .map(|(r, m)| (r.origin.clone(), r.number, m.clone()))
                    .collect(),
            );
        }
    }

    /// Records and sends the replies of a committed turn's requests.
    pub(super) fn answer_remote(&mut self, remote: Vec<(Remote, Vec<Vec<u8>>)>) {
        let Some(jet) = self.backend.jet() else {
            return;
        };
        for (to, msgs) in remote {
            jet.answered.record(to.origin, to.number, msgs.clone());
            jet.reply(to.subject, &ForwardReply::Done(msgs));
        }
    }

    /// Whether a forwarded request was applied in this turn and is not committed yet (its
    /// retry must wait for the commit, then gets the recorded replies).
    pub(super) fn pending_request(&self, request: &Forwarded) -> bool {
        self.backend
            .jet_ref()
            .is_some_and(|j| j.answered.lookup(&request.origin, request.number) == Lookup::Pending)
    }

    /// A request another node (or a session on this one) forwarded.
    pub(super) fn forwarded(
        &mut self,
        reply: Option<String>,
        request: Forwarded,
        acks: &mut Vec<PendingAck>,
        log: &mut Log,
    ) {
        if !self.backend.leading() {
            if let (Some(subject), Some(jet)) = (reply, self.backend.jet_ref()) {
                jet.reply(subject, &ForwardReply::NotOwner);
            }
            return;
        }
        let Forwarded {
            origin,
            number,
            user,
            editor,
            items,
        } = request;
        let Some(subject) = reply else {
            // Nobody waits for an answer: only a history drop goes this way.
            for (_, kind) in items {
                if kind == ForwardKind::Forget {
                    self.history.forget(user);
                    self.undo_budget.remove(&user);
                }
            }
            return;
        };
        if let Some(jet) = self.backend.jet() {
            match jet.answered.lookup(&origin, number) {
                // A retry of a request already applied (here or by an earlier owner).
                Lookup::Done(replies) => return jet.reply(subject, &ForwardReply::Done(replies)),
                // A copy its sender no longer waits for; or (cannot happen: the turn commits
                // before such a retry is taken) one still being committed.
                Lookup::Stale | Lookup::Pending => return,
                Lookup::New => jet.answered.begin(&origin, number),
            }
        }
        let to = Remote {
            subject,
            origin,
            number,
        };
        for (client_seq, kind) in items {
            match kind {
                ForwardKind::Edit(ops) => {
                    let ack = self.apply_batch(
                        AckTo::Remote(to.clone()),
                        client_seq,
                        ops,
                        editor.then_some(user),
                        log,
                    );
                    acks.push(ack);
                }
                ForwardKind::Undo { redo } => {
                    let ack = self.undo(
                        AckTo::Remote(to.clone()),
                        user,
                        editor,
                        client_seq,
                        redo,
                        log,
                    );
                    acks.push(ack);
                }
                ForwardKind::Forget => {
                    self.history.forget(user);
                    self.undo_budget.remove(&user);
                }
            }
        }
    }

    /// A turn of the log at stream position `pos`.
    pub(super) fn replicate(&mut self, pos: u64, turn: Turn) {
        let Some(jet) = self.backend.jet() else {
            return;
        };
        if jet.broken.load(std::sync::atomic::Ordering::Relaxed) || pos <= jet.pos() {
            return;
        }
        if jet.leading() {
            // Someone else appended: this node's own appends all landed before it (the log is
            // one sequence), so the map is still the log's, up to here.
            tracing::warn!(scene = %self.name, pos, node = %turn.node, "another node appended to the scene's log; this node stops ordering edits");
            jet.follow();
            Metrics::add(&self.metrics.stepdowns, 1);
        }
        if pos != jet.pos() + 1 {
            tracing::info!(scene = %self.name, pos, at = jet.pos(), "the log was trimmed past this replica; loading the newest snapshot");
            self.reload();
            return;
        }
        self.apply_turn(pos, turn);
    }

    /// Applies one turn another node appended. False (and the scene stops here) when it does
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
        if let Some(jet) = self.backend.jet() {
            jet.apply_committed(&turn.history);
            for (origin, number, replies) in turn.requests {
                jet.answered.record(origin, number, replies);
            }
            jet.set_pos(pos);
        }
        Metrics::add(&self.metrics.turns_replicated, 1);
        true
    }

    /// The log cannot be followed: say so loudly, stop serving the scene from this node
    /// rather than show (or order edits on) a scene that forked from it.
    pub(super) fn refuse_log(&mut self, fault: &str) {
        if self.broken {
            return;
        }
        self.broken = true;
        tracing::error!(scene = %self.name, fault, "the scene's log does not fit this replica; this node stops serving the scene (it loads it again when someone asks)");
        if let Some(jet) = self.backend.jet() {
            jet.broken.store(true, std::sync::atomic::Ordering::Relaxed);
            jet.follow();
        }
        self.fail_all(&format!("the scene's log is inconsistent: {fault}"));
    }

    /// This node took the lease: catch up to the log's end, then claim it.
    pub(super) fn take_over(&mut self) -> bool {
        // Asked again while it leads (the lease task saw it before this turn published it).
        if self.backend.jet_ref().is_some_and(|j| j.leading()) {
            return true;
        }
        for attempt in 0..2 {
            let Some(jet) = self.backend.jet() else {
                return false;
            };
            if jet.broken.load(std::sync::atomic::Ordering::Relaxed) {
                return false;
            }
            match jet.tail() {
                Ok(turns) => {
                    for (pos, turn) in turns {
                        if !self.apply_turn(pos, turn) {
                            return false;
                        }
                    }
                    break;
                }
                Err(e) if attempt == 0 => {
                    tracing::info!(scene = %self.name, error = %e, "catching up by loading the newest snapshot");
                    self.reload();
                }
                Err(e) => {
                    tracing::warn!(scene = %self.name, error = %e, "cannot catch up with the log; not taking the scene");
                    return false;
                }
            }
        }
        let Some(jet) = self.backend.jet() else {
            return false;
        };
        match jet.claim() {
            Ok(()) => {
                tracing::info!(scene = %self.name, node = %jet.node(), seq = self.seq, pos = jet.pos(), "this node owns the scene");
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
        if let Some(jet) = self.backend.jet()
            && jet.leading()
        {
            jet.follow();
            Metrics::add(&self.metrics.stepdowns, 1);
            tracing::warn!(scene = %self.name, why, "this node no longer owns the scene");
        }
    }

    /// An append failed: this turn's edits are not durable. Their senders hear "not the
    /// owner" (nothing applied) or "unknown" (an append may have landed); either way they
    /// retry, and the owner then answers from the log. The map is loaded again from the log.
    pub(super) fn lost_lead(&mut self, remote: &[(Remote, Vec<Vec<u8>>)], error: &StoreError) {
        tracing::warn!(scene = %self.name, %error, "a turn could not be logged; its edits are dropped and the scene is reloaded from the log");
        Metrics::add(&self.metrics.stepdowns, 1);
        let answer = if matches!(error, StoreError::Deposed { .. }) {
            ForwardReply::NotOwner
        } else {
            ForwardReply::Unknown
        };
        if let Some(jet) = self.backend.jet_ref() {
            for (to, _) in remote {
                jet.reply(to.subject.clone(), &answer);
            }
        }
        if !self.stopping {
            self.reload();
        }
    }

    /// Replaces the map, sequence and history with the log's (snapshot + turns). Sessions
    /// resync from what they were last sent.
    ///
    /// NATS being away (restarting, a network blip) is waited out, blocking this scene's
    /// thread: nothing can be ordered or made durable meanwhile anyway. A log that does not
    /// fit its snapshot stops the scene on this node.
    pub(super) fn reload(&mut self) {
        let started = std::time::Instant::now();
        loop {
            let Some(jet) = self.backend.jet() else {
                return;
            };
            let fault = match jet.reload() {
                Ok(loaded) => return self.reset_from(loaded),
                Err(
                    e @ (StoreError::Corrupt { .. }
                    | StoreError::Inconsistent { .. }
                    | StoreError::UnknownScene(_)),
                ) => e,
                Err(e) if started.elapsed() < RELOAD_PATIENCE => {
                    tracing::warn!(scene = %self.name, error = %e, "cannot load the scene from the cluster yet; trying again");
                    std::thread::sleep(std::time::Duration::from_millis(500));
                    continue;
                }
                Err(e) => e,
            };
            let fault = format!("the scene could not be loaded from the cluster: {fault}");
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
        );
        self.unsnapshotted = super::cells::CellSet::from_cells(&replay_touched);
        for sub in self.subs.values_mut() {
            sub.delivered = sub.delivered.min(seq);
            sub.lagging = true;
        }
    }
}
