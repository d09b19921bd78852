//! Edits travel to the scene's owner, wherever it runs.
//!
//! **Why every edit goes over NATS, even on the owner's own node:** the owner can change at
//! any moment (a lease lost, a node killed). A session that sent its edits straight to its
//! local scene thread would have to notice that and re-route, with edits in flight on both
//! paths. Instead each session forwards its edits as requests to the owner's own subject
//! (`brickcast.edit.<scene>.<node>`, the node the lease names), **one request at a time**, and
//! whatever queued up meanwhile goes in the next request together: a client's edits stay in
//! order and still reach the owner in batches, as they would its channel on one node.
//!
//! Only the named node listens on its subject. Any failure (no responders, "not the owner",
//! a timeout, an owner that lost the scene while logging) is retried with the same request,
//! on whichever node the lease names, for up to [`PATIENCE`]: the owner answers a request it
//! (or a previous owner) already applied with the replies it logged (`answered.rs`), so a
//! retry never applies an edit twice, and a failover costs the client a delay, not its
//! connection.
//!
//! The other nodes are trusted: the forwarding node has checked the client's role, rate and
//! edit budget; the owner applies what it is sent as that user.

use std::time::Duration;

use brickcast_protocol::backoff::{self, Backoff};
use brickcast_protocol::wire::{ErrorCode, UserId};
use bytes::Bytes;
use tokio::sync::mpsc;

use super::jet::Jet;
use crate::envelope::{EnvelopeError, Format};
use crate::metrics::Metrics;
use crate::scene::{Outbox, Outcome, Request, RequestItem};

/// How long a session keeps retrying an edit nobody owns (a failover in progress).
pub const PATIENCE: Duration = Duration::from_secs(15);
/// How long one attempt waits for its answer before the request is sent again (a slow owner
/// answers the copy from its record).
const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(3);
/// Edit messages a session may have queued for forwarding before its reader waits.
const QUEUE: usize = 256;
/// Ops one request carries at most (about 40 bytes each: well under NATS's 1 MB payload).
const MAX_OPS_PER_REQUEST: usize = 8192;
/// How long a request nobody took waits before it is tried again while the lease names
/// nobody new: the first wait, doubling (with jitter, `brickcast_protocol::backoff`) to the
/// longest, so the sessions of a node that lost its scene's owner do not ask in lockstep.
const RETRY_FIRST: Duration = Duration::from_millis(100);
const RETRY_LONGEST: Duration = Duration::from_secs(2);

/// How a session reaches a clustered scene's owner.
#[derive(Clone)]
pub struct SceneLink<J: Jet> {
    pub jet: J,
    /// The scene's log key ([`super::SceneEntry`]).
    pub log: String,
    /// The scene's edit subject; the owner listens on it plus `.<node>`.
    pub subject: String,
    /// The node the scene's lease names now (`None`: nobody holds it).
    pub owner: super::signal::Receiver<Option<String>>,
    /// This process, told apart from an earlier one of the same node name (session ids start
    /// again at 1 after a restart): the origin of its requests.
    pub instance: String,
}

/// Requests and answers between nodes: bincode alone (the NATS subject says which), at most
/// 64 MiB.
const REQUEST: Format<{ 64 << 20 }> = Format::new("forwarded request", b"");
const OUTCOME: Format<{ 64 << 20 }> = Format::new("forwarded answer", b"");

/// A request as it travels over NATS.
pub fn encode_request(request: &Request) -> Result<Vec<u8>, EnvelopeError> {
    REQUEST.encode(request)
}

pub fn decode_request(bytes: &[u8]) -> Result<Request, EnvelopeError> {
    REQUEST.decode(bytes)
}

/// An owner's answer as it travels over NATS.
pub fn encode_outcome(outcome: &Outcome) -> Result<Vec<u8>, EnvelopeError> {
    OUTCOME.encode(outcome)
}

pub fn decode_outcome(bytes: &[u8]) -> Result<Outcome, EnvelopeError> {
    OUTCOME.decode(bytes)
}

/// Why a forwarded edit got no answer.
#[derive(Debug, thiserror::Error)]
pub enum ForwardError {
    #[error("no node answered the scene's edits for {0:?}; they may or may not have applied")]
    NoOwner(Duration),
    #[error("cannot forward the edit: {0}")]
    Other(String),
    #[error("the scene is no longer served on this node; its edits may or may not have applied")]
    Closed,
}

/// The subject a scene's owner `node` takes edits on.
pub fn owner_subject(scene_subject: &str, node: &str) -> String {
    format!("{scene_subject}.{}", super::log::token(node))
}

/// Sends one request to whichever node owns the scene, waiting for one while nobody does.
pub async fn request<J: Jet>(
    link: &SceneLink<J>,
    request: &Request,
) -> Result<Vec<Vec<u8>>, ForwardError> {
    let payload =
        Bytes::from(encode_request(request).map_err(|e| ForwardError::Other(e.to_string()))?);
    let started = tokio::time::Instant::now();
    let deadline = started + PATIENCE;
    let mut owner = link.owner.clone();
    let mut backoff = Backoff::new(RETRY_FIRST, RETRY_LONGEST);
    // The draws depend on the request only, so a simulated run replays.
    let key = backoff::key_of(&request.origin) ^ request.number;
    let mut attempt = 0u64;
    loop {
        let current = owner.get_and_update();
        if let Some(node) = current {
            let subject = owner_subject(&link.subject, &node);
            // Until the answer, a timeout, or the lease naming another node (the one asked
            // died or lost the scene: ask the new one at once).
            let moved = async {
                let mut watch = link.owner.clone();
                loop {
                    if watch.changed().await.is_err() {
                        return std::future::pending().await;
                    }
                    if watch.get().as_deref().is_some_and(|n| n != node) {
                        return;
                    }
                }
            };
            let sent = tokio::select! {
                biased;
                sent = link.jet.request(subject, payload.clone(), ATTEMPT_TIMEOUT) => Some(sent),
                () = moved => None,
            };
            // Anything but an answer is retried: see the module doc.
            if let Some(Ok(answer)) = sent {
                match decode_outcome(&answer) {
                    Ok(Outcome::Done(msgs)) => return Ok(msgs),
                    Ok(Outcome::NotOwner | Outcome::Unknown) => {}
                    Err(e) => return Err(ForwardError::Other(format!("a bad reply: {e}"))),
                }
            }
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(ForwardError::NoOwner(PATIENCE));
        }
        // Wait for the lease to name someone (else) or a short while, then try again.
        attempt += 1;
        let wait = backoff.next_wait(backoff::spread(key, attempt));
        let waited = tokio::time::timeout_at(
            (tokio::time::Instant::now() + wait).min(deadline),
            owner.changed(),
        )
        .await;
        if let Ok(Err(_)) = waited {
            // Nobody will name an owner any more: the scene closed on this node.
            return Err(ForwardError::Closed);
        }
    }
}

/// A session's edits on their way to the owner: a queue, and the task that sends what is
/// queued as one request, waits for its answer, and queues the replies to the client.
pub struct SessionForwarder {
    tx: mpsc::Sender<(u64, RequestItem)>,
}

impl SessionForwarder {
    pub fn start<J: Jet>(
        link: SceneLink<J>,
        session: u64,
        user: UserId,
        editor: bool,
        out: Outbox,
        metrics: std::sync::Arc<Metrics>,
    ) -> SessionForwarder {
        let (tx, mut rx) = mpsc::channel::<(u64, RequestItem)>(QUEUE);
        let origin = format!("{}/{session}", link.instance);
        tokio::spawn(async move {
            let mut number = 0;
            while let Some(first) = rx.recv().await {
                number += 1;
                let mut ops = item_ops(&first.1);
                let mut items = vec![first];
                while ops < MAX_OPS_PER_REQUEST {
                    match rx.try_recv() {
                        Ok(item) => {
                            ops += item_ops(&item.1);
                            items.push(item);
                        }
                        Err(_) => break,
                    }
                }
                let req = Request {
                    origin: origin.clone(),
                    number,
                    user,
                    editor,
                    items,
                };
                match request(&link, &req).await {
                    Ok(replies) => {
                        Metrics::add(&metrics.edits_forwarded, req.items.len() as u64);
                        for reply in replies {
                            out.push(Bytes::from(reply));
                        }
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "closing a session whose edits were not answered");
                        out.close(
                            ErrorCode::ShuttingDown,
                            format!("{e}; reconnect to continue"),
                        );
                        return;
                    }
                }
            }
        });
        SessionForwarder { tx }
    }

    /// Queues an edit or undo; false when the forwarding task is gone (the session closed).
    pub async fn send(&self, client_seq: u64, kind: RequestItem) -> bool {
        self.tx.send((client_seq, kind)).await.is_ok()
    }
}

fn item_ops(kind: &RequestItem) -> usize {
    match kind {
        RequestItem::Edit(ops) => ops.len().max(1),
        _ => 1,
    }
}

/// Asks the owner to drop the history of a user without a stable id, who left. Nobody waits
/// for it: lost in a failover, the history stays until the owner's bounds drop it.
pub async fn forget<J: Jet>(link: &SceneLink<J>, user: UserId) {
    let request = Request {
        origin: format!("{}/forget", link.instance),
        number: 0,
        user,
        editor: false,
        items: vec![(0, RequestItem::Forget)],
    };
    let Some(node) = link.owner.get() else {
        return;
    };
    if let Ok(bytes) = encode_request(&request)
        && let Err(e) = link
            .jet
            .publish(owner_subject(&link.subject, &node), bytes.into())
            .await
    {
        tracing::debug!(error = %e, "a history could not be dropped");
    }
}
