//! A simulated NATS server behind [`Jet`]: key-value buckets that expire on the simulation's
//! clock, one stream per scene with fenced appends and a duplicate window, an object store,
//! and core request/reply that can lose, delay and duplicate messages.
//!
//! All of it is one [`World`] behind a mutex that every simulated process reaches through its
//! own [`SimJet`] handle. Each process runs on a tokio runtime of its own with a paused clock
//! that the simulation moves; a call reads its caller's clock to learn what time it is in the
//! world (the world's clock is the latest any caller reached), so keys expire, outages end and
//! delayed messages arrive on one timeline. Randomness (latencies, losses) comes from the
//! world's seeded ChaCha generator, drawn in the order calls happen, which the simulation
//! keeps deterministic.

use std::collections::{BTreeMap, VecDeque};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Waker};
use std::time::Duration;

use bytes::Bytes;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::cluster::jet::{Bucket, Incoming, Jet, KvEntry, LogStream, PortError, PortResult};
use crate::cluster::{LEASE_TTL, NODE_TTL};

/// How long the server remembers an append's id (as the real streams are set up).
const DUPLICATE_WINDOW: Duration = Duration::from_secs(120);

/// What the network and the server do wrong now.
#[derive(Clone, Debug, Default)]
pub struct Faults {
    /// The server answers nothing until then.
    pub down_until: Duration,
    /// Chance that a core message (a forwarded edit, its answer) is lost.
    pub loss: f64,
    /// Chance that a core message arrives twice.
    pub duplicate: f64,
    /// Core messages arrive up to this late.
    pub delay: Duration,
    /// Chance that an append or a key's write lands but its answer is lost.
    pub lost_acks: f64,
}

struct Slot {
    value: Bytes,
    revision: u64,
    written: Duration,
}

/// One scene's stream.
#[derive(Default)]
pub struct SimStreamState {
    /// Position → message, from the first held.
    pub messages: BTreeMap<u64, Bytes>,
    pub last: u64,
    ids: BTreeMap<String, (u64, Duration)>,
    waiting: Vec<Waker>,
}

impl SimStreamState {
    pub fn first(&self) -> u64 {
        self.messages
            .keys()
            .next()
            .copied()
            .unwrap_or(self.last + 1)
    }

    fn wake(&mut self) {
        for w in self.waiting.drain(..) {
            w.wake();
        }
    }
}

struct Subscription {
    process: u64,
    subject: String,
    queue: VecDeque<Incoming>,
    waker: Option<Waker>,
}

struct Inbox {
    answer: Option<Bytes>,
    waker: Option<Waker>,
}

/// A core message on its way.
struct InFlight {
    at: Duration,
    subject: String,
    message: Incoming,
}

/// Every append that ever landed on a scene's stream, in order (purges do not touch it): what
/// the checks read the truth from.
#[derive(Default)]
pub struct History {
    pub appends: Vec<(u64, Bytes)>,
}

/// The simulated server.
pub struct World {
    pub now: Duration,
    pub rng: ChaCha8Rng,
    pub faults: Faults,
    kv: BTreeMap<(Bucket, String), Slot>,
    revision: u64,
    pub streams: BTreeMap<String, SimStreamState>,
    pub objects: BTreeMap<String, (Bytes, String)>,
    subs: BTreeMap<u64, Subscription>,
    inboxes: BTreeMap<u64, Inbox>,
    in_flight: Vec<InFlight>,
    next_id: u64,
    pub history: BTreeMap<String, History>,
    /// Processes that crashed: their subscriptions are gone.
    dead: std::collections::BTreeSet<u64>,
}

fn ttl(bucket: Bucket) -> Option<Duration> {
    match bucket {
        Bucket::Owners => Some(LEASE_TTL),
        Bucket::Nodes => Some(NODE_TTL),
        Bucket::Scenes | Bucket::Heads => None,
    }
}

impl World {
    pub fn new(rng: ChaCha8Rng) -> World {
        World {
            now: Duration::ZERO,
            rng,
            faults: Faults::default(),
            kv: BTreeMap::new(),
            revision: 0,
            streams: BTreeMap::new(),
            objects: BTreeMap::new(),
            subs: BTreeMap::new(),
            inboxes: BTreeMap::new(),
            in_flight: Vec::new(),
            next_id: 1,
            history: BTreeMap::new(),
            dead: Default::default(),
        }
    }

    /// Moves the world's clock on to `at` (never back) and delivers what has arrived by then.
    pub fn advance(&mut self, at: Duration) {
        if at > self.now {
            self.now = at;
        }
        let now = self.now;
        let (due, later): (Vec<_>, Vec<_>) = std::mem::take(&mut self.in_flight)
            .into_iter()
            .partition(|m| m.at <= now);
        self.in_flight = later;
        for m in due {
            self.deliver(m.subject, m.message);
        }
    }

    /// The answer to a write that landed: lost now and then, as an append's may be.
    fn answer<T>(&mut self, value: T) -> PortResult<T> {
        if self.rng.random_bool(self.faults.lost_acks) {
            return Err(PortError::Unavailable("the write's answer was lost".into()));
        }
        Ok(value)
    }

    pub fn down(&self) -> bool {
        self.now < self.faults.down_until
    }

    fn deliver(&mut self, subject: String, message: Incoming) {
        if let Some(id) = subject
            .strip_prefix("_INBOX.")
            .and_then(|i| i.parse::<u64>().ok())
        {
            if let Some(inbox) = self.inboxes.get_mut(&id)
                && inbox.answer.is_none()
            {
                inbox.answer = Some(message.payload);
                if let Some(w) = inbox.waker.take() {
                    w.wake();
                }
            }
            return;
        }
        for sub in self.subs.values_mut() {
            if sub.subject == subject && !self.dead.contains(&sub.process) {
                sub.queue.push_back(message.clone());
                if let Some(w) = sub.waker.take() {
                    w.wake();
                }
            }
        }
    }

    /// Sends a core message through the faulty network.
    fn send(&mut self, subject: String, message: Incoming) {
        if self.down() || self.rng.random_bool(self.faults.loss) {
            return;
        }
        let copies = if self.rng.random_bool(self.faults.duplicate) {
            2
        } else {
            1
        };
        for _ in 0..copies {
            let delay = if self.faults.delay.is_zero() {
                Duration::ZERO
            } else {
                self.faults.delay.mul_f64(self.rng.random::<f64>())
            };
            let at = self.now + delay;
            if delay.is_zero() {
                self.deliver(subject.clone(), message.clone());
            } else {
                self.in_flight.push(InFlight {
                    at,
                    subject: subject.clone(),
                    message: message.clone(),
                });
            }
        }
    }

    fn live(&mut self, bucket: Bucket, key: &str) -> Option<&Slot> {
        let k = (bucket, key.to_string());
        let expired = match (self.kv.get(&k), ttl(bucket)) {
            (Some(slot), Some(ttl)) => self.now >= slot.written + ttl,
            _ => false,
        };
        if expired {
            self.kv.remove(&k);
        }
        self.kv.get(&k)
    }

    fn write(&mut self, bucket: Bucket, key: &str, value: Bytes) -> u64 {
        self.revision += 1;
        let slot = Slot {
            value,
            revision: self.revision,
            written: self.now,
        };
        self.kv.insert((bucket, key.to_string()), slot);
        self.revision
    }

    /// A key's value now (the checks read the lease holder from here).
    #[allow(dead_code)]
    pub fn key(&mut self, bucket: Bucket, key: &str) -> Option<Bytes> {
        self.live(bucket, key).map(|s| s.value.clone())
    }

    /// Appends to a stream as whoever may publish on its subject does: no fence, no id.
    pub fn publish_unfenced(&mut self, scene: &str, payload: Bytes) -> u64 {
        let stream = self.streams.entry(scene.to_string()).or_default();
        stream.last += 1;
        let pos = stream.last;
        stream.messages.insert(pos, payload.clone());
        stream.wake();
        self.history
            .entry(scene.to_string())
            .or_default()
            .appends
            .push((pos, payload));
        pos
    }

    /// A crashed process's subscriptions and pending answers go.
    pub fn bury(&mut self, process: u64) {
        self.dead.insert(process);
        self.subs.retain(|_, s| s.process != process);
    }
}

/// Where a process's clock stands against the world's: world time = (now − base) × rate⁻¹.
#[derive(Debug)]
pub struct ProcessClock {
    pub base: tokio::time::Instant,
    pub rate: f64,
}

impl ProcessClock {
    /// The world time a process reads now (inside its runtime).
    pub fn world_now(&self) -> Duration {
        tokio::time::Instant::now()
            .saturating_duration_since(self.base)
            .div_f64(self.rate)
    }

    /// The process's clock reading at world time `at`.
    pub fn local(&self, at: Duration) -> tokio::time::Instant {
        self.base + at.mul_f64(self.rate)
    }
}

/// One process's connection to the simulated server.
#[derive(Clone)]
pub struct SimJet {
    pub world: Arc<Mutex<World>>,
    pub process: u64,
    pub clock: Arc<ProcessClock>,
}

impl SimJet {
    fn lock(&self) -> std::sync::MutexGuard<'_, World> {
        self.world.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Waits a random network latency, then enters the world at the caller's time: the server
    /// takes the call then (the caller locks the world right after). Out of reach (down), it
    /// waits as a client's timeout would and fails.
    async fn reach(&self) -> PortResult<()> {
        let latency = {
            let mut w = self.lock();
            w.advance(self.clock.world_now());
            if std::env::var_os("BRICKCAST_CLUSTER_SIM_OPS").is_some() {
                eprintln!(
                    "op p{} at {:?} (world {:?})",
                    self.process,
                    self.clock.world_now(),
                    w.now
                );
            }
            Duration::from_micros(w.rng.random_range(100..3000))
        };
        tokio::time::sleep(latency).await;
        let refused = {
            let mut w = self.lock();
            w.advance(self.clock.world_now());
            w.down() || w.dead.contains(&self.process)
        };
        if refused {
            tokio::time::sleep(Duration::from_millis(500)).await;
            return Err(PortError::Unavailable("the server does not answer".into()));
        }
        Ok(())
    }
}

impl Jet for SimJet {
    type Stream = SimStream;
    type Subscription = SimSubscription;

    async fn kv_get(&self, bucket: Bucket, key: &str) -> PortResult<Option<KvEntry>> {
        self.reach().await?;
        let mut w = self.lock();
        Ok(w.live(bucket, key).map(|s| KvEntry {
            value: s.value.clone(),
            revision: s.revision,
        }))
    }

    async fn kv_create(&self, bucket: Bucket, key: &str, value: Bytes) -> PortResult<u64> {
        self.reach().await?;
        let mut w = self.lock();
        if w.live(bucket, key).is_some() {
            return Err(PortError::Conflict(format!("{key} exists")));
        }
        let revision = w.write(bucket, key, value);
        w.answer(revision)
    }

    async fn kv_update(
        &self,
        bucket: Bucket,
        key: &str,
        value: Bytes,
        revision: u64,
    ) -> PortResult<u64> {
        self.reach().await?;
        let mut w = self.lock();
        if w.live(bucket, key).map(|s| s.revision) != Some(revision) {
            return Err(PortError::Conflict(format!("{key} is not at {revision}")));
        }
        let revision = w.write(bucket, key, value);
        w.answer(revision)
    }

    async fn kv_delete(&self, bucket: Bucket, key: &str, revision: Option<u64>) -> PortResult<()> {
        self.reach().await?;
        let mut w = self.lock();
        let current = w.live(bucket, key).map(|s| s.revision);
        if revision.is_some() && current != revision {
            return Err(PortError::Conflict(format!("{key} is not at {revision:?}")));
        }
        w.kv.remove(&(bucket, key.to_string()));
        w.answer(())
    }

    async fn kv_keys(&self, bucket: Bucket) -> PortResult<Vec<String>> {
        self.reach().await?;
        let mut w = self.lock();
        let keys: Vec<String> =
            w.kv.keys()
                .filter(|(b, _)| *b == bucket)
                .map(|(_, k)| k.clone())
                .collect();
        Ok(keys
            .into_iter()
            .filter(|k| w.live(bucket, k).is_some())
            .collect())
    }

    async fn stream(&self, scene: &str, create: bool) -> PortResult<SimStream> {
        self.reach().await?;
        let mut w = self.lock();
        if !w.streams.contains_key(scene) {
            if !create {
                return Err(PortError::NotFound(format!("stream of {scene}")));
            }
            w.streams
                .insert(scene.to_string(), SimStreamState::default());
        }
        Ok(SimStream {
            jet: self.clone(),
            scene: scene.to_string(),
        })
    }

    async fn delete_stream(&self, scene: &str) -> PortResult<()> {
        self.reach().await?;
        let mut w = self.lock();
        w.streams.remove(scene);
        Ok(())
    }

    async fn object_get(&self, name: &str) -> PortResult<Option<Bytes>> {
        self.reach().await?;
        let w = self.lock();
        Ok(w.objects.get(name).map(|(b, _)| b.clone()))
    }

    async fn object_put(&self, name: &str, description: &str, bytes: Bytes) -> PortResult<()> {
        // An object is uploaded in chunks: it takes a while, longer for a bigger one.
        let upload = {
            let mut w = self.lock();
            Duration::from_millis(w.rng.random_range(1..200))
        };
        tokio::time::sleep(upload).await;
        self.reach().await?;
        let mut w = self.lock();
        if std::env::var_os("BRICKCAST_CLUSTER_SIM_OPS").is_some() {
            eprintln!("put p{} {name} {description} at {:?}", self.process, w.now);
        }
        w.objects
            .insert(name.to_string(), (bytes, description.to_string()));
        Ok(())
    }

    async fn object_delete(&self, name: &str) -> PortResult<()> {
        self.reach().await?;
        let mut w = self.lock();
        if std::env::var_os("BRICKCAST_CLUSTER_SIM_OPS").is_some() && w.objects.contains_key(name) {
            eprintln!("delete p{} {name} at {:?}", self.process, w.now);
        }
        match w.objects.remove(name) {
            Some(_) => Ok(()),
            None => Err(PortError::NotFound(name.into())),
        }
    }

    async fn object_description(&self, name: &str) -> PortResult<Option<String>> {
        self.reach().await?;
        let w = self.lock();
        Ok(w.objects.get(name).map(|(_, d)| d.clone()))
    }

    async fn request(
        &self,
        subject: String,
        payload: Bytes,
        timeout: Duration,
    ) -> PortResult<Bytes> {
        let inbox = {
            self.reach().await?;
            let mut w = self.lock();
            let listening = w
                .subs
                .values()
                .any(|s| s.subject == subject && !w.dead.contains(&s.process));
            if !listening {
                return Err(PortError::NoResponders);
            }
            let id = w.next_id;
            w.next_id += 1;
            w.inboxes.insert(
                id,
                Inbox {
                    answer: None,
                    waker: None,
                },
            );
            let message = Incoming {
                payload,
                reply: Some(format!("_INBOX.{id}")),
            };
            w.send(subject, message);
            id
        };
        let answer = tokio::time::timeout(
            timeout,
            Answer {
                jet: self.clone(),
                inbox,
            },
        )
        .await;
        self.lock().inboxes.remove(&inbox);
        answer.map_err(|_| PortError::Unavailable("no answer in time".into()))
    }

    async fn publish(&self, subject: String, payload: Bytes) -> PortResult<()> {
        self.reach().await?;
        let mut w = self.lock();
        w.send(
            subject,
            Incoming {
                payload,
                reply: None,
            },
        );
        Ok(())
    }

    async fn subscribe(&self, subject: String) -> PortResult<SimSubscription> {
        self.reach().await?;
        let mut w = self.lock();
        let id = w.next_id;
        w.next_id += 1;
        w.subs.insert(
            id,
            Subscription {
                process: self.process,
                subject,
                queue: VecDeque::new(),
                waker: None,
            },
        );
        Ok(SimSubscription {
            jet: self.clone(),
            id,
        })
    }

    fn max_payload(&self) -> usize {
        1 << 20
    }

    async fn offload<R: Send + 'static>(
        &self,
        work: impl FnOnce() -> R + Send + 'static,
    ) -> Option<R> {
        Some(work())
    }
}

/// Waits for a request's answer in its inbox.
struct Answer {
    jet: SimJet,
    inbox: u64,
}

impl std::future::Future for Answer {
    type Output = Bytes;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Bytes> {
        let mut w = self.jet.lock();
        let Some(inbox) = w.inboxes.get_mut(&self.inbox) else {
            return Poll::Pending;
        };
        match inbox.answer.take() {
            Some(answer) => Poll::Ready(answer),
            None => {
                inbox.waker = Some(cx.waker().clone());
                Poll::Pending
            }
        }
    }
}

/// A subscription's messages.
pub struct SimSubscription {
    jet: SimJet,
    id: u64,
}

impl futures_util::Stream for SimSubscription {
    type Item = Incoming;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Incoming>> {
        let mut w = self.jet.lock();
        let Some(sub) = w.subs.get_mut(&self.id) else {
            return Poll::Ready(None);
        };
        match sub.queue.pop_front() {
            Some(m) => Poll::Ready(Some(m)),
            None => {
                sub.waker = Some(cx.waker().clone());
                Poll::Pending
            }
        }
    }
}

impl Drop for SimSubscription {
    fn drop(&mut self) {
        self.jet.lock().subs.remove(&self.id);
    }
}

/// A scene's stream, reached through one process's connection.
#[derive(Clone)]
pub struct SimStream {
    jet: SimJet,
    scene: String,
}

impl LogStream for SimStream {
    type Follow = SimFollow;

    async fn append(&self, payload: Bytes, id: &str, expected_last: u64) -> PortResult<u64> {
        self.jet.reach().await?;
        let mut w = self.jet.lock();
        let now = w.now;
        let lost_acks = w.faults.lost_acks;
        let lost_ack = w.rng.random_bool(lost_acks);
        let stream = w
            .streams
            .get_mut(&self.scene)
            .ok_or_else(|| PortError::NotFound(format!("stream of {}", self.scene)))?;
        stream
            .ids
            .retain(|_, (_, at)| now.saturating_sub(*at) < DUPLICATE_WINDOW);
        // A second copy of an append the stream holds: its position, nothing written.
        if let Some((pos, _)) = stream.ids.get(id) {
            return Ok(*pos);
        }
        if stream.last != expected_last {
            return Err(PortError::Conflict(format!(
                "the log is not at message {expected_last}"
            )));
        }
        stream.last += 1;
        let pos = stream.last;
        stream.messages.insert(pos, payload.clone());
        stream.ids.insert(id.to_string(), (pos, now));
        stream.wake();
        w.history
            .entry(self.scene.clone())
            .or_default()
            .appends
            .push((pos, payload));
        if lost_ack {
            return Err(PortError::Unavailable(
                "the append's answer was lost".into(),
            ));
        }
        Ok(pos)
    }

    async fn bounds(&self) -> PortResult<(u64, u64, u64)> {
        self.jet.reach().await?;
        let w = self.jet.lock();
        let stream = w
            .streams
            .get(&self.scene)
            .ok_or_else(|| PortError::NotFound(format!("stream of {}", self.scene)))?;
        Ok((stream.first(), stream.last, stream.messages.len() as u64))
    }

    async fn get(&self, pos: u64) -> PortResult<Bytes> {
        self.jet.reach().await?;
        let w = self.jet.lock();
        w.streams
            .get(&self.scene)
            .and_then(|s| s.messages.get(&pos).cloned())
            .ok_or_else(|| PortError::NotFound(format!("log message {pos}")))
    }

    async fn purge_before(&self, keep: u64) -> PortResult<()> {
        self.jet.reach().await?;
        let mut w = self.jet.lock();
        if std::env::var_os("BRICKCAST_CLUSTER_SIM_OPS").is_some() {
            eprintln!("purge p{} before {keep} at {:?}", self.jet.process, w.now);
        }
        if let Some(stream) = w.streams.get_mut(&self.scene) {
            stream.messages = stream.messages.split_off(&keep);
        }
        Ok(())
    }

    async fn follow(&self, from: u64) -> PortResult<SimFollow> {
        self.jet.reach().await?;
        Ok(SimFollow {
            jet: self.jet.clone(),
            scene: self.scene.clone(),
            next: from,
            failed: false,
        })
    }
}

/// A stream followed from a position: the server's ordered consumer. It breaks (an error)
/// while the server is down, as a consumer does when its connection goes.
pub struct SimFollow {
    jet: SimJet,
    scene: String,
    next: u64,
    failed: bool,
}

impl futures_util::Stream for SimFollow {
    type Item = PortResult<(u64, Bytes)>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.failed {
            return Poll::Ready(None);
        }
        let jet = self.jet.clone();
        let mut w = jet.lock();
        w.advance(jet.clock.world_now());
        if w.down() || w.dead.contains(&jet.process) {
            self.failed = true;
            return Poll::Ready(Some(Err(PortError::Unavailable(
                "the server does not answer".into(),
            ))));
        }
        let Some(stream) = w.streams.get_mut(&self.scene) else {
            self.failed = true;
            return Poll::Ready(Some(Err(PortError::NotFound("the stream".into()))));
        };
        // Messages trimmed before this consumer read them: it goes on from the first held.
        let next = self.next.max(stream.first());
        if std::env::var_os("BRICKCAST_CLUSTER_SIM_OPS").is_some() {
            eprintln!(
                "follow p{} next {next} first {} last {}",
                jet.process,
                stream.first(),
                stream.last
            );
        }
        match stream.messages.get(&next) {
            Some(bytes) => {
                let item = (next, bytes.clone());
                self.next = next + 1;
                Poll::Ready(Some(Ok(item)))
            }
            None => {
                stream.waiting.push(cx.waker().clone());
                Poll::Pending
            }
        }
    }
}
