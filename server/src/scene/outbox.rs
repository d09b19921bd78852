//! A session's outgoing queue, shared by the scene owner (which queues acks, deltas and syncs)
//! and the session (which queues pongs and errors and whose writer drains it).
//!
//! Why a queue of its own rather than a bounded channel: the owner must never wait on a slow
//! client, so the queue is unbounded and its bytes are counted instead; the owner reads the count
//! to decide when a client stops getting deltas and is resynced later. The count is what a
//! queued frame really holds (its bytes plus [`FRAME_OVERHEAD`] for the buffer and the queue
//! slot), and every queue also adds to one server-wide total, so the owner can stop feeding
//! queues when the server as a whole holds too much (see `OwnerConfig::max_queued_total`).
//!
//! Pongs are coalesced: while one is waiting to be written, a later Ping only updates the nonce
//! it will carry, so a client that floods Pings and never reads costs one queued pong, not one
//! per Ping. `Refused` replies are coalesced the same way (the latest reason counts): they
//! answer no numbered request.
//!
//! Replies that answer a numbered request (`Ack`, `Undone`) are never dropped or merged: a
//! client keeps its own count of what is answered. Instead the queue keeps a **reply backlog**
//! (the bytes of replies not yet written, plus a charge per coalesced pong or refusal), and the
//! session stops reading its client while the backlog is over [`MAX_REPLY_BACKLOG`]: a client
//! that sends without reading gets TCP's flow control, not memory, and costs no CPU while it
//! waits (its writer cuts it off once it has taken nothing for the stall timeout). A client
//! that reads never meets the bound: replies queue only while its socket is full.
//!
//! **Durability.** Frames the owner queues are stamped with its latest turn handed to the log
//! (`durable.rs`); the writer takes a stamped frame only once that turn is durable, and the
//! frames behind it wait with it, so nothing leaves before the commit that holds what it says.
//!
//! Every message goes in through [`Outbox::send`], which is where a message that cannot be
//! encoded is noticed: it is logged, counted, and the session is closed with an `Internal`
//! error, so the client learns that something is wrong instead of waiting for a reply forever.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex};

use brickcast_protocol::wire::{ErrorCode, Refusal, ServerMsg, encode_server};
use bytes::Bytes;
use tokio::sync::{Notify, mpsc};

use super::durable::Durability;
use crate::metrics::Metrics;

/// What a queued frame costs besides its bytes: the `Bytes` header and allocation, and the
/// channel's slot (measured: a queued 3-byte pong cost about 90 bytes of heap).
pub const FRAME_OVERHEAD: usize = 96;

/// Bytes of unwritten replies (and coalesced ones, at [`COALESCED_COST`] each) past which the
/// session stops reading its client until the writer catches up: about 140 acks of a small
/// batch, far more than a client that reads ever has waiting. 4,096 connections at the bound
/// hold 64 MiB.
pub const MAX_REPLY_BACKLOG: usize = 16 << 10;

/// What a pong or refusal folded into one already waiting adds to the reply backlog, so that
/// a flood of Pings or refused requests also pauses reading (it costs CPU, not memory).
pub const COALESCED_COST: usize = 64;

/// One item in a session's queue.
pub enum Outgoing {
    /// An encoded frame; `reply` when it answers the client (it counts in the reply backlog);
    /// it may be written once turn `ticket` of its scene is durable (0: at once).
    Frame {
        frame: Bytes,
        reply: bool,
        ticket: u64,
    },
    /// A pong carrying the latest nonce at the time it is written.
    Pong,
    /// A `Refused` carrying the latest refusal at the time it is written.
    Refused,
}

/// The owner's and the session's handle on one session's outgoing queue.
#[derive(Clone)]
pub struct Outbox {
    tx: mpsc::UnboundedSender<Outgoing>,
    shared: Arc<Shared>,
}

/// What the queue's two ends share.
struct Shared {
    /// Bytes this queue holds (frames plus overhead).
    queued: AtomicUsize,
    /// Bytes every queue of the server holds.
    total: Arc<AtomicUsize>,
    /// Set once somebody decided the session must end (an unencodable reply, a peer that broke
    /// the protocol, a writer that stalled); the session's reader waits on it.
    closed: AtomicBool,
    notify: Notify,
    pong_queued: AtomicBool,
    pong_nonce: AtomicU64,
    refusal_queued: AtomicBool,
    refusal: Mutex<Option<Refusal>>,
    /// Bytes of replies queued (frames plus overhead; a waiting pong or refusal counts its
    /// overhead).
    replies: AtomicUsize,
    /// Pongs and refusals folded into the one waiting since it was queued.
    pongs_folded: AtomicUsize,
    refusals_folded: AtomicUsize,
    /// Woken when the writer takes a reply.
    drained: Notify,
    /// The owner is streaming this session a sync: its camera decides what goes next.
    syncing: AtomicBool,
    /// The session holds a working set that follows its camera (set by the owner).
    following: AtomicBool,
    /// Woken when the writer takes a frame while the owner streams a sync: the owner queues
    /// a sync only a little ahead of the writer ([`Outbox::wake_owner_with`]).
    owner: std::sync::OnceLock<Arc<Notify>>,
    /// The scene's turns made durable (set by the owner at join): frames are stamped with it.
    gate: std::sync::OnceLock<Arc<Durability>>,
}

impl Shared {
    fn add(&self, n: usize) {
        self.queued.fetch_add(n, Relaxed);
        self.total.fetch_add(n, Relaxed);
    }

    fn sub(&self, n: usize) {
        self.queued.fetch_sub(n, Relaxed);
        self.total.fetch_sub(n, Relaxed);
    }
}

/// The writer's end: items in queue order.
pub struct OutboxReceiver {
    rx: mpsc::UnboundedReceiver<Outgoing>,
    shared: Arc<Shared>,
    /// The next item, taken from the queue but waiting for its turn to be durable.
    held: Option<Outgoing>,
}

impl OutboxReceiver {
    /// Waits for the next frame that may be written (a pong is encoded here, with the latest
    /// nonce); `None` once every [`Outbox`] is gone and the queue is empty.
    pub async fn next(&mut self) -> Option<Bytes> {
        loop {
            let item = match self.held.take() {
                Some(item) => item,
                None => self.rx.recv().await?,
            };
            match self.may_send(&item) {
                Some(true) => return Some(self.take(item)),
                Some(false) => drop(self.take(item)),
                None => {
                    let (Outgoing::Frame { ticket, .. }, Some(gate)) = (&item, self.gate()) else {
                        return Some(self.take(item));
                    };
                    if gate.wait(*ticket).await {
                        return Some(self.take(item));
                    }
                    drop(self.take(item));
                }
            }
        }
    }

    /// The next frame that may be written, without waiting.
    pub fn try_take(&mut self) -> Option<Bytes> {
        loop {
            let item = match self.held.take() {
                Some(item) => item,
                None => self.rx.try_recv().ok()?,
            };
            match self.may_send(&item) {
                Some(true) => return Some(self.take(item)),
                // Its turn's commit failed: it never goes.
                Some(false) => drop(self.take(item)),
                None => {
                    self.held = Some(item);
                    return None;
                }
            }
        }
    }

    fn gate(&self) -> Option<Arc<Durability>> {
        self.shared.gate.get().cloned()
    }

    /// Whether `item` may be written now (`Some(true)`), never (`Some(false)`) or later.
    fn may_send(&self, item: &Outgoing) -> Option<bool> {
        match (item, self.shared.gate.get()) {
            (Outgoing::Frame { ticket, .. }, Some(gate)) if *ticket > 0 => gate.may_send(*ticket),
            _ => Some(true),
        }
    }

    /// Everything queued, dropped and uncounted, whether it could be written or not.
    fn discard_all(&mut self) {
        if let Some(item) = self.held.take() {
            drop(self.take(item));
        }
        while let Ok(item) = self.rx.try_recv() {
            drop(self.take(item));
        }
    }

    fn take(&self, item: Outgoing) -> Bytes {
        let shared = &self.shared;
        if shared.syncing.load(Relaxed)
            && let Some(owner) = shared.owner.get()
        {
            owner.notify_one();
        }
        let frame = match item {
            Outgoing::Frame { frame, reply, .. } => {
                let cost = frame.len() + FRAME_OVERHEAD;
                shared.sub(cost);
                if !reply {
                    return frame;
                }
                shared.replies.fetch_sub(cost, Relaxed);
                frame
            }
            Outgoing::Pong => {
                shared.sub(FRAME_OVERHEAD);
                shared.replies.fetch_sub(FRAME_OVERHEAD, Relaxed);
                // Cleared before reading the nonce: a Ping arriving now queues another pong.
                shared.pong_queued.store(false, Relaxed);
                shared.pongs_folded.store(0, Relaxed);
                let nonce = shared.pong_nonce.load(Relaxed);
                Bytes::from(encode_server(&ServerMsg::Pong { nonce }).unwrap_or_default())
            }
            Outgoing::Refused => {
                shared.sub(FRAME_OVERHEAD);
                shared.replies.fetch_sub(FRAME_OVERHEAD, Relaxed);
                let reason = {
                    let mut latest = shared.refusal.lock().unwrap_or_else(|e| e.into_inner());
                    // Cleared under the lock: a refusal arriving now queues another.
                    shared.refusal_queued.store(false, Relaxed);
                    shared.refusals_folded.store(0, Relaxed);
                    latest.take()
                };
                let reason = reason.unwrap_or(Refusal::RateLimited);
                Bytes::from(encode_server(&ServerMsg::Refused { reason }).unwrap_or_default())
            }
        };
        shared.drained.notify_waiters();
        frame
    }

    /// Ends the session from the writer's side (its peer stopped taking data): later pushes
    /// are refused, what is queued is dropped and uncounted, and the reader is told to stop.
    pub fn abort(&mut self) {
        self.rx.close();
        self.discard_all();
        self.shared.closed.store(true, Relaxed);
        self.shared.notify.notify_waiters();
    }
}

impl Drop for OutboxReceiver {
    /// Whatever is still queued is dropped with the queue: it no longer counts.
    fn drop(&mut self) {
        self.rx.close();
        self.discard_all();
    }
}

impl Outbox {
    /// A queue whose bytes also count towards `total`, the server-wide figure.
    pub fn new(total: Arc<AtomicUsize>) -> (Outbox, OutboxReceiver) {
        let (tx, rx) = mpsc::unbounded_channel();
        let shared = Arc::new(Shared {
            queued: AtomicUsize::new(0),
            total,
            closed: AtomicBool::new(false),
            notify: Notify::new(),
            pong_queued: AtomicBool::new(false),
            pong_nonce: AtomicU64::new(0),
            refusal_queued: AtomicBool::new(false),
            refusal: Mutex::new(None),
            replies: AtomicUsize::new(0),
            pongs_folded: AtomicUsize::new(0),
            refusals_folded: AtomicUsize::new(0),
            drained: Notify::new(),
            syncing: AtomicBool::new(false),
            following: AtomicBool::new(false),
            owner: std::sync::OnceLock::new(),
            gate: std::sync::OnceLock::new(),
        });
        (
            Outbox {
                tx,
                shared: shared.clone(),
            },
            OutboxReceiver {
                rx,
                shared,
                held: None,
            },
        )
    }

    /// Queues an encoded frame (a delta or sync: not a reply); false when the session is gone
    /// (then nothing is counted).
    pub fn push(&self, frame: Bytes) -> bool {
        self.enqueue(frame, false)
    }

    /// Queues a frame stamped with the scene's latest turn handed to its log.
    fn enqueue(&self, frame: Bytes, reply: bool) -> bool {
        let ticket = self.shared.gate.get().map_or(0, |g| g.stamp());
        self.enqueue_at(frame, reply, ticket)
    }

    fn enqueue_at(&self, frame: Bytes, reply: bool, ticket: u64) -> bool {
        let cost = frame.len() + FRAME_OVERHEAD;
        self.shared.add(cost);
        if reply {
            self.shared.replies.fetch_add(cost, Relaxed);
        }
        let item = Outgoing::Frame {
            frame,
            reply,
            ticket,
        };
        if self.tx.send(item).is_err() {
            self.shared.sub(cost);
            if reply {
                self.shared.replies.fetch_sub(cost, Relaxed);
            }
            return false;
        }
        true
    }

    /// Queues a coalesced item (a pong or a refusal) unless one is already waiting: then the
    /// waiting one carries the latest value and `folded` counts one more.
    fn coalesce(&self, queued: &AtomicBool, folded: &AtomicUsize, item: Outgoing) {
        if queued.swap(true, Relaxed) {
            folded.fetch_add(1, Relaxed);
            return;
        }
        self.shared.add(FRAME_OVERHEAD);
        self.shared.replies.fetch_add(FRAME_OVERHEAD, Relaxed);
        if self.tx.send(item).is_err() {
            self.shared.sub(FRAME_OVERHEAD);
            self.shared.replies.fetch_sub(FRAME_OVERHEAD, Relaxed);
        }
    }

    /// Answers a Ping: queues a pong unless one is already waiting, which then carries this
    /// nonce instead.
    pub fn pong(&self, nonce: u64) {
        self.shared.pong_nonce.store(nonce, Relaxed);
        let shared = &self.shared;
        self.coalesce(&shared.pong_queued, &shared.pongs_folded, Outgoing::Pong);
    }

    /// Tells the client a request was refused: queues a `Refused` unless one is already
    /// waiting, which then carries this reason instead.
    pub fn refuse(&self, reason: Refusal) {
        let shared = &self.shared;
        {
            let mut latest = shared.refusal.lock().unwrap_or_else(|e| e.into_inner());
            *latest = Some(reason);
            // Under the lock, so the writer cannot take the slot between the two.
            self.coalesce(
                &shared.refusal_queued,
                &shared.refusals_folded,
                Outgoing::Refused,
            );
        }
    }

    /// The reply backlog: bytes of replies not yet written, plus [`COALESCED_COST`] for each
    /// pong or refusal folded into a waiting one.
    pub fn reply_backlog(&self) -> usize {
        let s = &self.shared;
        let folded = s.pongs_folded.load(Relaxed) + s.refusals_folded.load(Relaxed);
        s.replies.load(Relaxed) + folded.saturating_mul(COALESCED_COST)
    }

    /// Resolves once the reply backlog is at most `replies` and the queue holds at most
    /// `queued` bytes, or the session is closed.
    pub async fn drained_to(&self, replies: usize, queued: usize) {
        loop {
            let drained = self.shared.drained.notified();
            let closed = self.shared.notify.notified();
            if (self.reply_backlog() <= replies && self.queued() <= queued) || self.is_closed() {
                return;
            }
            tokio::select! {
                _ = drained => {}
                _ = closed => {}
            }
        }
    }

    /// Encodes and queues `msg`. A message that cannot be encoded is a server bug that would
    /// leave the client waiting (for its ack, its welcome, the end of its sync): it is logged
    /// and counted per message kind, and the session is closed with an `Internal` error.
    /// Returns whether the message was queued.
    pub fn send(&self, msg: &ServerMsg, metrics: &Metrics) -> bool {
        let reply = matches!(
            msg,
            ServerMsg::Ack { .. }
                | ServerMsg::Undone { .. }
                | ServerMsg::Refused { .. }
                | ServerMsg::Pong { .. }
                | ServerMsg::Error { .. }
        );
        match encode_server(msg) {
            Ok(frame) => self.enqueue(Bytes::from(frame), reply),
            Err(e) => {
                let kind = msg.kind();
                tracing::error!(message = kind, error = %e, "cannot encode a reply; closing the session");
                metrics.count_unencodable(kind);
                self.close(
                    ErrorCode::Internal,
                    format!(
                        "the server could not encode a {kind} message for this connection: {e}"
                    ),
                );
                false
            }
        }
    }

    /// Queues an `Error` frame and asks the session to end once it is written. The frame is not
    /// stamped: it says nothing about the scene, and must reach the client even when the
    /// scene stopped because a commit failed.
    pub fn close(&self, code: ErrorCode, text: impl Into<String>) {
        if !self.shared.closed.swap(true, Relaxed) {
            // `ServerMsg::error` cuts the text to the bound, so this always encodes.
            if let Ok(frame) = encode_server(&ServerMsg::error(code, text)) {
                self.enqueue_at(Bytes::from(frame), false, 0);
            }
        }
        self.shared.notify.notify_waiters();
    }

    /// Whether [`Outbox::close`] (or the writer's abort) happened.
    pub fn is_closed(&self) -> bool {
        self.shared.closed.load(Relaxed)
    }

    /// Resolves once the session has been closed (at once if it already was).
    pub async fn closed(&self) {
        loop {
            let notified = self.shared.notify.notified();
            if self.is_closed() {
                return;
            }
            notified.await;
        }
    }

    /// Has the writer wake `owner` each time it takes a frame while a sync streams (set by
    /// the owner at join; the first one set stays).
    pub fn wake_owner_with(&self, owner: Arc<Notify>) {
        let _ = self.shared.owner.set(owner);
    }

    /// Stamps every frame queued from now on with the scene's latest turn handed to its log,
    /// and holds it until that turn is durable (set by the owner at join; the first one set
    /// stays).
    pub fn gate_with(&self, durability: Arc<Durability>) {
        let _ = self.shared.gate.set(durability);
    }

    /// Marks whether the owner is streaming this session a sync (set by the owner).
    pub fn set_syncing(&self, on: bool) {
        self.shared.syncing.store(on, Relaxed);
    }

    /// Whether a camera update would change anything: only a sync is ordered by it, so a
    /// session forwards cameras to the owner only then, and a synced viewer moving at 20 Hz
    /// costs the owner nothing.
    pub fn is_syncing(&self) -> bool {
        self.shared.syncing.load(Relaxed)
    }

    /// Marks whether the session holds a working set that follows its camera (set by the
    /// owner when it joins: a budget the whole scene fits is served the whole scene).
    pub fn set_following(&self, on: bool) {
        self.shared.following.store(on, Relaxed);
    }

    /// Whether every camera update matters (a working set follows it), not only during a sync.
    pub fn is_following(&self) -> bool {
        self.shared.following.load(Relaxed)
    }

    /// Bytes this session's queue holds.
    pub fn queued(&self) -> usize {
        self.shared.queued.load(Relaxed)
    }

    /// Bytes every session's queue holds together.
    pub fn total_queued(&self) -> usize {
        self.shared.total.load(Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::wire::{Limits, decode_server};

    fn outbox() -> (Outbox, OutboxReceiver, Arc<AtomicUsize>) {
        let total = Arc::new(AtomicUsize::new(0));
        let (out, rx) = Outbox::new(total.clone());
        (out, rx, total)
    }

    #[test]
    fn an_unencodable_message_is_counted_and_closes_the_session() {
        let metrics = Metrics::default();
        let (out, mut rx, total) = outbox();
        assert!(out.send(&ServerMsg::Resync { since: 7 }, &metrics));
        // Built by hand past the bound that `ServerMsg::error` would have enforced.
        let too_long = ServerMsg::Error {
            code: ErrorCode::Internal,
            message: "x".repeat(10_000),
        };
        assert!(!out.send(&too_long, &metrics));
        assert!(out.is_closed());
        let frames: Vec<ServerMsg> = std::iter::from_fn(|| rx.try_take())
            .map(|f| decode_server(&f, &Limits::hard_caps()).unwrap())
            .collect();
        assert_eq!(frames.len(), 2, "the resync, then one error saying why");
        assert!(matches!(
            &frames[1],
            ServerMsg::Error { code: ErrorCode::Internal, message } if message.contains("Error message")
        ));
        assert_eq!((out.queued(), total.load(Relaxed)), (0, 0));
        assert!(
            metrics
                .render()
                .contains("brickcast_frames_unencodable_total{message=\"Error\"} 1")
        );
        // Closing twice queues one error.
        out.close(ErrorCode::RateLimited, "again");
        assert!(rx.try_take().is_none());
    }

    /// Frames queued after a turn was handed to the log wait for its commit, in order, and are
    /// dropped (and uncounted) if it fails; the closing error still goes.
    #[tokio::test]
    async fn frames_wait_for_their_turn_to_be_durable() {
        let (out, mut rx, total) = outbox();
        let gate = Arc::new(Durability::default());
        assert!(out.push(Bytes::from_static(b"before")), "not stamped yet");
        out.gate_with(gate.clone());
        let one = gate.next();
        assert!(out.push(Bytes::from_static(b"one")));
        out.pong(7);
        assert_eq!(rx.try_take().unwrap().as_ref(), b"before");
        assert!(rx.try_take().is_none(), "turn one is not durable");
        assert!(rx.try_take().is_none(), "the pong waits behind it");
        let writer = tokio::spawn(async move {
            let first = rx.next().await.unwrap();
            (first, rx)
        });
        tokio::task::yield_now().await;
        gate.durable_to(one);
        let (first, mut rx) = writer.await.unwrap();
        assert_eq!(first.as_ref(), b"one");
        assert!(rx.try_take().is_some(), "then the pong");
        let two = gate.next();
        assert!(out.push(Bytes::from_static(b"two")));
        assert!(rx.try_take().is_none());
        gate.fail();
        out.close(ErrorCode::Internal, "scene stopped");
        let frames: Vec<Bytes> = std::iter::from_fn(|| rx.try_take()).collect();
        assert_eq!(frames.len(), 1, "turn two never goes; the error does");
        assert!(gate.may_send(two) == Some(false));
        assert_eq!((out.queued(), total.load(Relaxed)), (0, 0));
    }

    #[test]
    fn pongs_are_coalesced_and_counted_with_their_overhead() {
        let (out, mut rx, total) = outbox();
        for nonce in 1..=10_000 {
            out.pong(nonce);
        }
        assert_eq!(
            out.queued(),
            FRAME_OVERHEAD,
            "one pong waits, whatever the pings"
        );
        assert!(out.push(Bytes::from_static(b"abc")));
        assert_eq!(total.load(Relaxed), 2 * FRAME_OVERHEAD + 3);
        let pong = decode_server(&rx.try_take().unwrap(), &Limits::hard_caps()).unwrap();
        assert_eq!(pong, ServerMsg::Pong { nonce: 10_000 }, "the latest nonce");
        out.pong(10_001);
        assert_eq!(rx.try_take().unwrap().as_ref(), b"abc");
        assert!(matches!(
            decode_server(&rx.try_take().unwrap(), &Limits::hard_caps()).unwrap(),
            ServerMsg::Pong { nonce: 10_001 }
        ));
        assert_eq!(total.load(Relaxed), 0);
    }

    #[tokio::test]
    async fn refusals_coalesce_and_replies_make_the_backlog() {
        let metrics = Metrics::default();
        let (out, mut rx, total) = outbox();
        for i in 0..10_000 {
            out.refuse(if i % 2 == 0 {
                Refusal::RateLimited
            } else {
                Refusal::NotAllowed
            });
        }
        assert_eq!(out.queued(), FRAME_OVERHEAD, "one refusal waits");
        assert_eq!(out.reply_backlog(), FRAME_OVERHEAD + 9_999 * COALESCED_COST);
        // Deltas are not replies; acks are.
        assert!(out.push(Bytes::from_static(b"delta")));
        let ack = ServerMsg::Ack {
            client_seq: 1,
            seq: None,
            applied: 0,
            rejected: Vec::new(),
        };
        assert!(out.send(&ack, &metrics));
        let ack_len = encode_server(&ack).unwrap().len();
        assert_eq!(
            out.reply_backlog(),
            2 * FRAME_OVERHEAD + ack_len + 9_999 * COALESCED_COST
        );
        let waiter = tokio::spawn({
            let out = out.clone();
            async move { out.drained_to(0, usize::MAX).await }
        });
        tokio::task::yield_now().await;
        assert!(!waiter.is_finished());
        let refused = decode_server(&rx.try_take().unwrap(), &Limits::hard_caps()).unwrap();
        assert_eq!(
            refused,
            ServerMsg::Refused {
                reason: Refusal::NotAllowed
            },
            "the latest reason"
        );
        assert_eq!(out.reply_backlog(), FRAME_OVERHEAD + ack_len);
        assert_eq!(rx.try_take().unwrap().as_ref(), b"delta");
        assert_eq!(
            decode_server(&rx.try_take().unwrap(), &Limits::hard_caps()).unwrap(),
            ack
        );
        tokio::time::timeout(std::time::Duration::from_secs(5), waiter)
            .await
            .unwrap()
            .unwrap();
        assert_eq!((out.reply_backlog(), total.load(Relaxed)), (0, 0));
        // A refusal after the last was written queues again.
        out.refuse(Refusal::RateLimited);
        assert!(rx.try_take().is_some());
    }

    #[tokio::test]
    async fn an_aborted_queue_refuses_and_uncounts_everything() {
        let (out, mut rx, total) = outbox();
        out.push(Bytes::from_static(b"queued"));
        rx.abort();
        assert!(out.is_closed());
        assert!(!out.push(Bytes::from_static(b"later")));
        assert_eq!(total.load(Relaxed), 0);
        tokio::time::timeout(std::time::Duration::from_secs(5), out.closed())
            .await
            .unwrap();
    }

    #[tokio::test]
    async fn closed_resolves_after_close() {
        let (out, _rx, _) = outbox();
        let waiter = tokio::spawn({
            let out = out.clone();
            async move { out.closed().await }
        });
        tokio::task::yield_now().await;
        assert!(!waiter.is_finished());
        out.close(ErrorCode::Internal, "bye");
        tokio::time::timeout(std::time::Duration::from_secs(5), waiter)
            .await
            .unwrap()
            .unwrap();
        out.closed().await;
    }
}
