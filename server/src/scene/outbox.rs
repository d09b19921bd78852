//! A session's outgoing queue, shared by the scene owner (which queues acks, deltas and syncs)
//! and the session (which queues pongs and errors and whose writer drains it).
//!
//! Why a queue of its own rather than a bounded channel: the owner must never wait on a slow
//! client, so the queue is unbounded and its bytes are counted instead; the owner reads the count
//! to decide when a client stops getting deltas and is resynced later.
//!
//! Every message goes in through [`Outbox::send`], which is where a message that cannot be
//! encoded is noticed: it is logged, counted, and the session is closed with an `Internal`
//! error, so the client learns that something is wrong instead of waiting for a reply forever.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering::Relaxed};

use brickcast_protocol::wire::{ErrorCode, ServerMsg, encode_server};
use bytes::Bytes;
use tokio::sync::{Notify, mpsc};

use crate::metrics::Metrics;

/// The owner's and the session's handle on one session's outgoing queue.
#[derive(Clone)]
pub struct Outbox {
    tx: mpsc::UnboundedSender<Bytes>,
    queued: Arc<AtomicUsize>,
    closing: Arc<Closing>,
}

/// Set once somebody decided the session must end (an unencodable reply, a peer that broke the
/// protocol); the session's reader waits on it.
#[derive(Default)]
struct Closing {
    closed: AtomicBool,
    notify: Notify,
}

/// The writer's end: frames in queue order and the shared byte count it decrements.
pub struct OutboxReceiver {
    pub rx: mpsc::UnboundedReceiver<Bytes>,
    pub queued: Arc<AtomicUsize>,
}

impl OutboxReceiver {
    /// Takes one queued frame without waiting, keeping the byte count true.
    pub fn try_take(&mut self) -> Option<Bytes> {
        let frame = self.rx.try_recv().ok()?;
        self.queued.fetch_sub(frame.len(), Relaxed);
        Some(frame)
    }
}

impl Outbox {
    pub fn new() -> (Outbox, OutboxReceiver) {
        let (tx, rx) = mpsc::unbounded_channel();
        let queued = Arc::new(AtomicUsize::new(0));
        (
            Outbox {
                tx,
                queued: queued.clone(),
                closing: Arc::default(),
            },
            OutboxReceiver { rx, queued },
        )
    }

    /// Queues an encoded frame; false when the session is gone.
    pub fn push(&self, frame: Bytes) -> bool {
        self.queued.fetch_add(frame.len(), Relaxed);
        self.tx.send(frame).is_ok()
    }

    /// Encodes and queues `msg`. A message that cannot be encoded is a server bug that would
    /// leave the client waiting (for its ack, its welcome, the end of its sync): it is logged
    /// and counted per message kind, and the session is closed with an `Internal` error.
    /// Returns whether the message was queued.
    pub fn send(&self, msg: &ServerMsg, metrics: &Metrics) -> bool {
        match encode_server(msg) {
            Ok(frame) => self.push(Bytes::from(frame)),
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

    /// Queues an `Error` frame and asks the session to end once it is written.
    pub fn close(&self, code: ErrorCode, text: impl Into<String>) {
        if !self.closing.closed.swap(true, Relaxed) {
            // `ServerMsg::error` cuts the text to the bound, so this always encodes.
            if let Ok(frame) = encode_server(&ServerMsg::error(code, text)) {
                self.push(Bytes::from(frame));
            }
        }
        self.closing.notify.notify_waiters();
    }

    /// Whether [`Outbox::close`] was called.
    pub fn is_closed(&self) -> bool {
        self.closing.closed.load(Relaxed)
    }

    /// Resolves once [`Outbox::close`] has been called (at once if it already was).
    pub async fn closed(&self) {
        loop {
            let notified = self.closing.notify.notified();
            if self.is_closed() {
                return;
            }
            notified.await;
        }
    }

    pub fn queued(&self) -> usize {
        self.queued.load(Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::wire::{Limits, decode_server};

    #[test]
    fn an_unencodable_message_is_counted_and_closes_the_session() {
        let metrics = Metrics::default();
        let (out, mut rx) = Outbox::new();
        assert!(out.send(&ServerMsg::Pong { nonce: 7 }, &metrics));
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
        assert_eq!(frames.len(), 2, "the pong, then one error saying why");
        assert!(matches!(
            &frames[1],
            ServerMsg::Error { code: ErrorCode::Internal, message } if message.contains("Error message")
        ));
        assert_eq!(out.queued(), 0);
        assert!(
            metrics
                .render()
                .contains("brickcast_frames_unencodable_total{message=\"Error\"} 1")
        );
        // Closing twice queues one error.
        out.close(ErrorCode::RateLimited, "again");
        assert!(rx.try_take().is_none());
    }

    #[tokio::test]
    async fn closed_resolves_after_close() {
        let (out, _rx) = Outbox::new();
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
