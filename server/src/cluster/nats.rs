//! The real NATS behind [`Jet`]: async-nats against a nats-server with JetStream.

use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use async_nats::jetstream::{self, consumer::pull, kv, object_store::ObjectStore};
use bytes::Bytes;
use futures_util::StreamExt;
use tokio::io::AsyncReadExt;

use super::jet::{Bucket, Incoming, Jet, KvEntry, LogStream, PortError, PortResult};
use super::log::{log_subject, stream_name};
use super::{
    ClusterError, HEADS_BUCKET, LEASE_TTL, NODE_TTL, NODES_BUCKET, OWNERS_BUCKET, SCENES_BUCKET,
    SNAPSHOT_BUCKET,
};

/// How long a scene's stream remembers an append's id (a retried append lands once).
const DUPLICATE_WINDOW: Duration = Duration::from_secs(120);

/// A connection to the cluster's NATS server and its buckets.
#[derive(Clone)]
pub struct Cluster {
    /// The server's URL, without a password (for messages).
    pub url: String,
    pub client: async_nats::Client,
    pub js: jetstream::Context,
    owners: kv::Store,
    nodes: kv::Store,
    scenes: kv::Store,
    heads: kv::Store,
    snapshots: ObjectStore,
    /// Copies of each stream this node creates (`--replicas`).
    pub replicas: usize,
}

/// `url` without what comes before an `@`, and that: a user and password
/// (`nats://user:password@host`), or a token (`nats://token@host`). async-nats does not read
/// them from the URL itself.
fn credentials(url: &str) -> (String, Option<(String, Option<String>)>) {
    let Some((scheme, rest)) = url.split_once("://") else {
        return (url.to_string(), None);
    };
    match rest.rsplit_once('@') {
        Some((userinfo, host)) => {
            let address = format!("{scheme}://{host}");
            match userinfo.split_once(':') {
                Some((user, password)) => (
                    address,
                    Some((user.to_string(), Some(password.to_string()))),
                ),
                None => (address, Some((userinfo.to_string(), None))),
            }
        }
        None => (url.to_string(), None),
    }
}

/// `url` without its password, for logs and errors.
pub fn redacted(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_string();
    };
    match rest.rsplit_once('@') {
        Some((userinfo, host)) => match userinfo.split_once(':') {
            Some((user, _)) => format!("{scheme}://{user}:***@{host}"),
            None => format!("{scheme}://***@{host}"),
        },
        None => url.to_string(),
    }
}

/// A key-value bucket, created when missing. The bucket's stream is created here, with the
/// settings the client's own `create_key_value` uses: that call first reads the account's
/// info in a form NATS 2.9 (Debian's) does not send.
async fn bucket(
    js: &jetstream::Context,
    name: &str,
    max_age: Duration,
    replicas: usize,
) -> Result<kv::Store, ClusterError> {
    if let Ok(store) = js.get_key_value(name).await {
        return Ok(store);
    }
    js.create_stream(jetstream::stream::Config {
        name: format!("KV_{name}"),
        subjects: vec![format!("$KV.{name}.>")],
        max_messages_per_subject: 1,
        max_age,
        storage: jetstream::stream::StorageType::File,
        allow_rollup: true,
        deny_delete: true,
        allow_direct: true,
        num_replicas: replicas,
        discard: jetstream::stream::DiscardPolicy::New,
        ..Default::default()
    })
    .await
    .map_err(|e| ClusterError::Nats(format!("creating bucket {name}: {e}")))?;
    js.get_key_value(name)
        .await
        .map_err(|e| ClusterError::Nats(format!("opening bucket {name}: {e}")))
}

impl Cluster {
    /// Connects and makes sure the buckets exist. A URL nobody answers at, or a server
    /// without JetStream, is a clear error. The URL may carry a user and password
    /// (`nats://user:password@host:4222`; see README, "Running a cluster").
    ///
    /// `replicas`: copies JetStream keeps of each stream and bucket this node creates (1 for a
    /// single nats-server; 3 for a JetStream cluster of three). Existing ones keep theirs.
    pub async fn connect(url: &str, replicas: usize) -> Result<Cluster, ClusterError> {
        let replicas = replicas.max(1);
        let shown = redacted(url);
        let (address, credentials) = credentials(url);
        let mut options = async_nats::ConnectOptions::new();
        match credentials {
            Some((user, Some(password))) => options = options.user_and_password(user, password),
            Some((token, None)) => options = options.token(token),
            None => {}
        }
        let client = options
            .name("brickcast")
            .connection_timeout(Duration::from_secs(5))
            .request_timeout(Some(Duration::from_secs(10)))
            .connect(address)
            .await
            .map_err(|e| ClusterError::Unreachable {
                url: shown.clone(),
                detail: e.to_string(),
            })?;
        let js = jetstream::new(client.clone());
        // The account's JetStream info, read raw: a server without JetStream has no responder
        // (or answers with an error), and the typed reply of this client expects 2.10's fields.
        let no_js = |detail: String| ClusterError::NoJetStream {
            url: shown.clone(),
            detail,
        };
        let info = tokio::time::timeout(
            Duration::from_secs(5),
            client.request("$JS.API.INFO", Bytes::new()),
        )
        .await
        .map_err(|_| no_js("no answer from $JS.API.INFO".into()))?
        .map_err(|e| no_js(e.to_string()))?;
        let info: serde_json::Value =
            serde_json::from_slice(&info.payload).map_err(|e| no_js(e.to_string()))?;
        if let Some(error) = info.get("error") {
            return Err(no_js(error.to_string()));
        }
        let owners = bucket(&js, OWNERS_BUCKET, LEASE_TTL, replicas).await?;
        let nodes = bucket(&js, NODES_BUCKET, NODE_TTL, replicas).await?;
        let scenes = bucket(&js, SCENES_BUCKET, Duration::ZERO, replicas).await?;
        let heads = bucket(&js, HEADS_BUCKET, Duration::ZERO, replicas).await?;
        let snapshots = match js.get_object_store(SNAPSHOT_BUCKET).await {
            Ok(s) => s,
            Err(_) => js
                .create_object_store(jetstream::object_store::Config {
                    bucket: SNAPSHOT_BUCKET.to_string(),
                    storage: jetstream::stream::StorageType::File,
                    num_replicas: replicas,
                    ..Default::default()
                })
                .await
                .map_err(|e| ClusterError::Nats(format!("creating the snapshot store: {e}")))?,
        };
        let max_payload = client.server_info().max_payload;
        if max_payload < 8 << 20 {
            tracing::info!(
                max_payload,
                "the NATS server's max_payload is under 8 MB: a turn too big for one message is split, but one undo of a very large brush may not fit (see README, Running a cluster)"
            );
        }
        Ok(Cluster {
            url: shown,
            client,
            js,
            owners,
            nodes,
            scenes,
            heads,
            snapshots,
            replicas,
        })
    }

    fn kv(&self, bucket: Bucket) -> &kv::Store {
        match bucket {
            Bucket::Owners => &self.owners,
            Bucket::Nodes => &self.nodes,
            Bucket::Scenes => &self.scenes,
            Bucket::Heads => &self.heads,
        }
    }
}

/// Anything async-nats reports, as an outcome-unknown failure.
fn unavailable(what: &str) -> impl Fn(&dyn std::fmt::Display) -> PortError + '_ {
    move |e| PortError::Unavailable(format!("{what}: {e}"))
}

impl Jet for Cluster {
    type Stream = NatsStream;
    type Subscription = NatsSubscription;

    async fn kv_get(&self, bucket: Bucket, key: &str) -> PortResult<Option<KvEntry>> {
        let entry = self
            .kv(bucket)
            .entry(key)
            .await
            .map_err(|e| unavailable("reading a key")(&e))?;
        Ok(entry
            .filter(|e| e.operation == kv::Operation::Put)
            .map(|e| KvEntry {
                value: e.value,
                revision: e.revision,
            }))
    }

    async fn kv_create(&self, bucket: Bucket, key: &str, value: Bytes) -> PortResult<u64> {
        self.kv(bucket)
            .create(key, value)
            .await
            .map_err(|e| match e.kind() {
                kv::CreateErrorKind::AlreadyExists => PortError::Conflict(format!("{key} exists")),
                _ => unavailable("creating a key")(&e),
            })
    }

    async fn kv_update(
        &self,
        bucket: Bucket,
        key: &str,
        value: Bytes,
        revision: u64,
    ) -> PortResult<u64> {
        self.kv(bucket)
            .update(key, value, revision)
            .await
            .map_err(|e| match e.kind() {
                kv::UpdateErrorKind::WrongLastRevision => {
                    PortError::Conflict(format!("{key} is not at revision {revision}"))
                }
                _ => unavailable("updating a key")(&e),
            })
    }

    async fn kv_delete(&self, bucket: Bucket, key: &str, revision: Option<u64>) -> PortResult<()> {
        let store = self.kv(bucket);
        let result = match revision {
            Some(r) => store.delete_expect_revision(key, Some(r)).await,
            None => store.purge(key).await,
        };
        result.map_err(|e| match e.kind() {
            kv::UpdateErrorKind::WrongLastRevision => {
                PortError::Conflict(format!("{key} is not at revision {revision:?}"))
            }
            _ => unavailable("deleting a key")(&e),
        })
    }

    async fn kv_keys(&self, bucket: Bucket) -> PortResult<Vec<String>> {
        let mut keys = self
            .kv(bucket)
            .keys()
            .await
            .map_err(|e| unavailable("listing keys")(&e))?;
        let mut out = Vec::new();
        while let Some(key) = keys.next().await {
            out.push(key.map_err(|e| unavailable("listing keys")(&e))?);
        }
        Ok(out)
    }

    async fn stream(&self, scene: &str, create: bool) -> PortResult<NatsStream> {
        let stream = if create {
            self.js
                .get_or_create_stream(jetstream::stream::Config {
                    name: stream_name(scene),
                    subjects: vec![log_subject(scene)],
                    storage: jetstream::stream::StorageType::File,
                    num_replicas: self.replicas,
                    duplicate_window: DUPLICATE_WINDOW,
                    ..Default::default()
                })
                .await
                .map_err(|e| unavailable("creating the log stream")(&e))?
        } else {
            self.js
                .get_stream(stream_name(scene))
                .await
                .map_err(|e| unavailable("opening the log stream")(&e))?
        };
        Ok(NatsStream {
            js: self.js.clone(),
            stream,
            subject: log_subject(scene),
        })
    }

    async fn delete_stream(&self, scene: &str) -> PortResult<()> {
        self.js
            .delete_stream(stream_name(scene))
            .await
            .map(|_| ())
            .map_err(|e| unavailable("deleting the log stream")(&e))
    }

    async fn object_get(&self, name: &str) -> PortResult<Option<Bytes>> {
        let mut object = match self.snapshots.get(name).await {
            Ok(o) => o,
            Err(e) if matches!(e.kind(), jetstream::object_store::GetErrorKind::NotFound) => {
                return Ok(None);
            }
            Err(e) => return Err(unavailable(&format!("reading object {name}"))(&e)),
        };
        let mut bytes = Vec::new();
        object
            .read_to_end(&mut bytes)
            .await
            .map_err(|e| unavailable(&format!("reading object {name}"))(&e))?;
        Ok(Some(bytes.into()))
    }

    async fn object_put(&self, name: &str, description: &str, bytes: Bytes) -> PortResult<()> {
        let meta = jetstream::object_store::ObjectMetadata {
            name: name.to_string(),
            description: Some(description.to_string()),
            ..Default::default()
        };
        self.snapshots
            .put(meta, &mut bytes.as_ref())
            .await
            .map(|_| ())
            .map_err(|e| unavailable(&format!("writing object {name}"))(&e))
    }

    async fn object_delete(&self, name: &str) -> PortResult<()> {
        self.snapshots
            .delete(name)
            .await
            .map_err(|e| match e.kind() {
                jetstream::object_store::DeleteErrorKind::NotFound => {
                    PortError::NotFound(name.into())
                }
                _ => unavailable(&format!("deleting object {name}"))(&e),
            })
    }

    async fn object_description(&self, name: &str) -> PortResult<Option<String>> {
        match self.snapshots.info(name).await {
            Ok(info) => Ok(Some(info.description.unwrap_or_default())),
            Err(e) if matches!(e.kind(), jetstream::object_store::InfoErrorKind::NotFound) => {
                Ok(None)
            }
            Err(e) => Err(unavailable(&format!("reading object {name}"))(&e)),
        }
    }

    async fn request(
        &self,
        subject: String,
        payload: Bytes,
        timeout: Duration,
    ) -> PortResult<Bytes> {
        match tokio::time::timeout(timeout, self.client.request(subject, payload)).await {
            Err(_) => Err(PortError::Unavailable("no answer in time".into())),
            Ok(Ok(message)) => Ok(message.payload),
            Ok(Err(e)) => Err(match e.kind() {
                async_nats::RequestErrorKind::NoResponders => PortError::NoResponders,
                _ => unavailable("a request")(&e),
            }),
        }
    }

    async fn publish(&self, subject: String, payload: Bytes) -> PortResult<()> {
        self.client
            .publish(subject, payload)
            .await
            .map_err(|e| unavailable("publishing")(&e))
    }

    async fn subscribe(&self, subject: String) -> PortResult<NatsSubscription> {
        self.client
            .subscribe(subject)
            .await
            .map(NatsSubscription)
            .map_err(|e| unavailable("subscribing")(&e))
    }

    fn max_payload(&self) -> usize {
        self.client.server_info().max_payload
    }

    async fn offload<R: Send + 'static>(
        &self,
        work: impl FnOnce() -> R + Send + 'static,
    ) -> Option<R> {
        tokio::task::spawn_blocking(work).await.ok()
    }
}

/// A scene's log stream on the server.
#[derive(Clone)]
pub struct NatsStream {
    js: jetstream::Context,
    stream: jetstream::stream::Stream,
    subject: String,
}

type MessageStream =
    Pin<Box<dyn futures_util::Stream<Item = PortResult<(u64, Bytes)>> + Send + 'static>>;

impl LogStream for NatsStream {
    type Follow = MessageStream;

    async fn append(&self, payload: Bytes, id: &str, expected_last: u64) -> PortResult<u64> {
        let publish = jetstream::message::PublishMessage::build()
            .payload(payload)
            .message_id(id)
            .expected_last_sequence(expected_last);
        let sent = self.js.send_publish(self.subject.clone(), publish).await;
        let acked = match sent {
            Ok(ack) => ack.await,
            Err(e) => Err(e),
        };
        acked.map(|ack| ack.sequence).map_err(|e| match e.kind() {
            jetstream::context::PublishErrorKind::WrongLastSequence => {
                PortError::Conflict(format!("the log is not at message {expected_last}"))
            }
            _ => unavailable("appending to the log")(&e),
        })
    }

    async fn bounds(&self) -> PortResult<(u64, u64, u64)> {
        let mut stream = self.stream.clone();
        let info = stream
            .info()
            .await
            .map_err(|e| unavailable("reading the log stream")(&e))?;
        Ok((
            info.state.first_sequence,
            info.state.last_sequence,
            info.state.messages,
        ))
    }

    async fn get(&self, pos: u64) -> PortResult<Bytes> {
        match self.stream.get_raw_message(pos).await {
            Ok(message) => Ok(message.payload),
            Err(e)
                if matches!(
                    e.kind(),
                    jetstream::stream::LastRawMessageErrorKind::NoMessageFound
                ) =>
            {
                Err(PortError::NotFound(format!("log message {pos}")))
            }
            Err(e) => Err(unavailable(&format!("reading log message {pos}"))(&e)),
        }
    }

    async fn purge_before(&self, keep: u64) -> PortResult<()> {
        self.stream
            .purge()
            .sequence(keep)
            .await
            .map(|_| ())
            .map_err(|e| unavailable("trimming the log")(&e))
    }

    async fn follow(&self, from: u64) -> PortResult<MessageStream> {
        let consumer = self
            .stream
            .create_consumer(pull::OrderedConfig {
                deliver_policy: jetstream::consumer::DeliverPolicy::ByStartSequence {
                    start_sequence: from,
                },
                ..Default::default()
            })
            .await
            .map_err(|e| unavailable("following the log")(&e))?;
        let messages = consumer
            .messages()
            .await
            .map_err(|e| unavailable("following the log")(&e))?;
        Ok(Box::pin(messages.map(|item| {
            let message = item.map_err(|e| unavailable("following the log")(&e))?;
            let pos = message
                .info()
                .map_err(|e| unavailable("a log message without its position")(&e))?
                .stream_sequence;
            Ok((pos, message.payload.clone()))
        })))
    }
}

/// A core subscription on the server.
pub struct NatsSubscription(async_nats::Subscriber);

impl futures_util::Stream for NatsSubscription {
    type Item = Incoming;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Incoming>> {
        self.0.poll_next_unpin(cx).map(|m| {
            m.map(|m| Incoming {
                payload: m.payload,
                reply: m.reply.map(|r| r.to_string()),
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::redacted;

    #[test]
    fn passwords_stay_out_of_messages() {
        assert_eq!(
            redacted("nats://node:secret@127.0.0.1:4222"),
            "nats://node:***@127.0.0.1:4222"
        );
        assert_eq!(redacted("nats://127.0.0.1:4222"), "nats://127.0.0.1:4222");
        assert_eq!(redacted("nats://tok@h:1"), "nats://***@h:1");
        assert_eq!(
            super::credentials("nats://node:se:cret@h:1"),
            (
                "nats://h:1".to_string(),
                Some(("node".to_string(), Some("se:cret".to_string())))
            )
        );
        assert_eq!(
            super::credentials("nats://tok@h:1"),
            ("nats://h:1".to_string(), Some(("tok".to_string(), None)))
        );
        assert_eq!(
            super::credentials("nats://h:1"),
            ("nats://h:1".to_string(), None)
        );
    }
}
