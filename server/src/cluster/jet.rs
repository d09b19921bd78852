//! What the cluster needs of NATS, as one trait: key-value buckets with compare-and-set and
//! expiry, a stream per scene with fenced appends, an object store, and core request/reply.
//!
//! **Why a trait:** the nodes run on a real nats-server (`nats.rs`, async-nats); the
//! cluster's simulation (`sim/`) runs the same lease, follower, log, repair and forwarding
//! code on a simulated JetStream that loses, delays and duplicates messages, expires keys on
//! a simulated clock and holds garbage on a log subject when told to (TigerBeetle's replica is
//! generic over its storage, network and time in the same way). Everything the cluster does
//! with NATS goes through here, so what the simulation checks is what the nodes run.
//!
//! Time is tokio's: the nodes' runtime reads the real clock, the simulation's runtimes a
//! paused one it moves itself.

use std::future::Future;
use std::time::Duration;

use bytes::Bytes;

/// Why a call to NATS failed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PortError {
    /// A compare-and-set lost: a key created that exists, a revision that is not the key's,
    /// an append whose expected last position is not the stream's. Nothing was written.
    #[error("conflict: {0}")]
    Conflict(String),
    /// A message, key or object that is not there (purged, deleted, expired).
    #[error("not found: {0}")]
    NotFound(String),
    /// A request nobody listens for.
    #[error("no responders")]
    NoResponders,
    /// The server did not answer (down, a network blip, a timeout): the call may or may not
    /// have taken effect.
    #[error("{0}")]
    Unavailable(String),
    /// The server refused the call (permissions, a bad request).
    #[error("refused: {0}")]
    Refused(String),
}

pub type PortResult<T> = Result<T, PortError>;

/// The cluster's key-value buckets (names in `mod.rs`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Bucket {
    /// Scene → the node holding its lease (expires [`super::LEASE_TTL`] after a write).
    Owners,
    /// Node name → the running process (expires [`super::NODE_TTL`] after a write).
    Nodes,
    /// Scene → its size: the cluster's scene list (never expires).
    Scenes,
    /// Scene → its newest snapshot (`snapshot.rs`; never expires).
    Heads,
}

/// A live key's value and revision.
#[derive(Clone, Debug, PartialEq)]
pub struct KvEntry {
    pub value: Bytes,
    pub revision: u64,
}

/// A core message taken from a subscription.
#[derive(Clone, Debug)]
pub struct Incoming {
    pub payload: Bytes,
    /// Where the sender waits for an answer.
    pub reply: Option<String>,
}

/// One scene's log stream.
pub trait LogStream: Clone + Send + Sync + 'static {
    /// The turns from position `from` on, in order, as they are appended: (position, bytes).
    /// Ends (or errs) when following breaks; the follower then follows again from where it was.
    type Follow: futures_util::Stream<Item = PortResult<(u64, Bytes)>> + Send + Unpin + 'static;

    /// Appends `payload` if the stream's last position is `expected_last` ([`PortError::Conflict`]
    /// otherwise): its position. `id` is unique per attempt series: the server drops a second
    /// copy of an append it already holds (a retry after a lost answer).
    fn append(
        &self,
        payload: Bytes,
        id: &str,
        expected_last: u64,
    ) -> impl Future<Output = PortResult<u64>> + Send;

    /// The first and last positions held (first = last + 1 when empty) and how many messages.
    fn bounds(&self) -> impl Future<Output = PortResult<(u64, u64, u64)>> + Send;

    /// The message at `pos` ([`PortError::NotFound`] when it is gone).
    fn get(&self, pos: u64) -> impl Future<Output = PortResult<Bytes>> + Send;

    /// Drops every message before `keep` (the last position stays counted).
    fn purge_before(&self, keep: u64) -> impl Future<Output = PortResult<()>> + Send;

    fn follow(&self, from: u64) -> impl Future<Output = PortResult<Self::Follow>> + Send;
}

/// Everything a node reaches on NATS.
pub trait Jet: Clone + Send + Sync + 'static {
    type Stream: LogStream;
    type Subscription: futures_util::Stream<Item = Incoming> + Send + Unpin + 'static;

    fn kv_get(
        &self,
        bucket: Bucket,
        key: &str,
    ) -> impl Future<Output = PortResult<Option<KvEntry>>> + Send;
    /// Writes a key that is not there: its revision ([`PortError::Conflict`] when it is).
    fn kv_create(
        &self,
        bucket: Bucket,
        key: &str,
        value: Bytes,
    ) -> impl Future<Output = PortResult<u64>> + Send;
    /// Writes a key whose revision is `revision`: the new one.
    fn kv_update(
        &self,
        bucket: Bucket,
        key: &str,
        value: Bytes,
        revision: u64,
    ) -> impl Future<Output = PortResult<u64>> + Send;
    /// Deletes a key (only at `revision`, when given).
    fn kv_delete(
        &self,
        bucket: Bucket,
        key: &str,
        revision: Option<u64>,
    ) -> impl Future<Output = PortResult<()>> + Send;
    fn kv_keys(&self, bucket: Bucket) -> impl Future<Output = PortResult<Vec<String>>> + Send;

    /// A scene's log stream, created when `create` and missing.
    fn stream(
        &self,
        scene: &str,
        create: bool,
    ) -> impl Future<Output = PortResult<Self::Stream>> + Send;
    fn delete_stream(&self, scene: &str) -> impl Future<Output = PortResult<()>> + Send;

    /// Snapshot objects (`snapshot.rs`): bytes, and a one-line description read alone.
    fn object_get(&self, name: &str) -> impl Future<Output = PortResult<Option<Bytes>>> + Send;
    fn object_put(
        &self,
        name: &str,
        description: &str,
        bytes: Bytes,
    ) -> impl Future<Output = PortResult<()>> + Send;
    fn object_delete(&self, name: &str) -> impl Future<Output = PortResult<()>> + Send;
    fn object_description(
        &self,
        name: &str,
    ) -> impl Future<Output = PortResult<Option<String>>> + Send;

    /// A core request: the first answer within `timeout`.
    fn request(
        &self,
        subject: String,
        payload: Bytes,
        timeout: Duration,
    ) -> impl Future<Output = PortResult<Bytes>> + Send;
    fn publish(
        &self,
        subject: String,
        payload: Bytes,
    ) -> impl Future<Output = PortResult<()>> + Send;
    fn subscribe(
        &self,
        subject: String,
    ) -> impl Future<Output = PortResult<Self::Subscription>> + Send;

    /// The largest message the server takes.
    fn max_payload(&self) -> usize;

    /// Runs CPU-heavy work (encoding a snapshot) off the async threads: a blocking thread on a
    /// node, in place in the simulation (which must not depend on another thread's timing).
    fn offload<R: Send + 'static>(
        &self,
        work: impl FnOnce() -> R + Send + 'static,
    ) -> impl Future<Output = Option<R>> + Send;
}

/// Answers the requests on `subject` with `handle` (`None`: no answer) until `shutdown` or the
/// subscription ends: the loop of every node-side request handler (`cluster status`, kicks).
pub async fn answer_requests<J, F, Fut>(
    jet: &J,
    subject: String,
    what: &str,
    shutdown: &tokio_util::sync::CancellationToken,
    mut handle: F,
) where
    J: Jet,
    F: FnMut(Bytes) -> Fut,
    Fut: Future<Output = Option<Bytes>>,
{
    let mut asks = match jet.subscribe(subject).await {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!(error = %e, "cannot answer {what}");
            return;
        }
    };
    loop {
        let ask = tokio::select! {
            biased;
            () = shutdown.cancelled() => return,
            ask = futures_util::StreamExt::next(&mut asks) => ask,
        };
        let Some(ask) = ask else { return };
        let Some(to) = ask.reply else { continue };
        if let Some(answer) = handle(ask.payload).await {
            let _ = jet.publish(to, answer).await;
        }
    }
}
