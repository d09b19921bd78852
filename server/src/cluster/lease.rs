//! One scene on one node of a cluster: the tasks around its owner thread.
//!
//! * **Lease:** without the lease, try to create the scene's key in `brickcast_owners` every
//!   [`CLAIM_POLL`]; with it, renew it (compare-and-set on its revision) every
//!   [`RENEW_EVERY`]. Taking it makes the owner thread catch up to the log's end and append a
//!   marker (`Command::TakeOver`); a failed renewal makes it stop appending
//!   (`Command::StepDown`). The lease only says who *tries*; the log's expected-sequence fence
//!   is what keeps two owners from both appending.
//! * **Intake:** while leading, forwarded edits on `brickcast.edit.<scene>` go to the owner
//!   thread in arrival order.
//! * **Follower:** an ordered consumer of the scene's stream hands every turn to the owner
//!   thread (`Command::Replicate`); the owner skips the ones it appended itself.
//! * **Replies:** the owner thread's answers to forwarded edits, published in order.

use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Instant;

use async_nats::jetstream::{self, consumer::pull, kv};
use futures_util::StreamExt;
use tokio::sync::{mpsc, oneshot, watch};

use super::forward::Forwarded;
use super::log::{self as jetlog, ClusterLoaded, JetLog, LeaseClock, Turn};
use super::{CLAIM_GRACE, CLAIM_POLL, Cluster, LEASE_MARGIN, LEASE_TTL, RENEW_EVERY};
use crate::metrics::Metrics;
use crate::scene::{self, Command, OwnerConfig, SceneCluster, SceneHandle};

/// Starts serving a scene loaded from the cluster: its owner thread (following the log) and
/// the lease, intake, follower and reply tasks, which end at `shutdown` (the server's, or the
/// scene's close on this node).
#[allow(clippy::too_many_arguments)]
pub async fn start_scene(
    cluster: &Cluster,
    node: &str,
    name: String,
    mut loaded: ClusterLoaded,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    shutdown: watch::Receiver<bool>,
) -> anyhow::Result<(SceneHandle, std::thread::JoinHandle<()>)> {
    let lease = Arc::new(LeaseClock::default());
    let (replies_tx, mut replies_rx) = mpsc::unbounded_channel::<(String, bytes::Bytes)>();
    let log = JetLog::open(
        cluster.handles(node),
        &name,
        &mut loaded,
        lease.clone(),
        replies_tx,
    )
    .await?;
    let broken = log.broken.clone();
    let start = loaded.pos + 1;
    let (owner_tx, owner_rx) = watch::channel(None);
    let link = SceneCluster {
        client: cluster.client.clone(),
        subject: jetlog::edit_subject(&name),
        owner: owner_rx,
    };
    let (handle, thread) = scene::spawn_with(
        name.clone(),
        loaded.loaded,
        scene::Backend::Jet(Box::new(log)),
        Some(link),
        metrics.clone(),
        config,
        tokio::runtime::Handle::current(),
    )?;

    let client = cluster.client.clone();
    tokio::spawn(async move {
        while let Some((subject, bytes)) = replies_rx.recv().await {
            if let Err(e) = client.publish(subject, bytes).await {
                tracing::warn!(error = %e, "cannot send a reply to a forwarded edit");
            }
        }
    });
    let stream = cluster
        .js
        .get_stream(jetlog::stream_name(&name))
        .await
        .map_err(|e| anyhow::anyhow!("scene {name}: opening the log stream: {e}"))?;
    tokio::spawn(follow(
        stream,
        start,
        handle.clone(),
        broken.clone(),
        shutdown.clone(),
    ));
    super::presence::start(
        cluster.client.clone(),
        node.to_string(),
        &handle,
        metrics.clone(),
        shutdown.clone(),
    );
    tokio::spawn(hold_lease(LeaseTask {
        scene: handle.clone(),
        owners: cluster.owners.clone(),
        client: cluster.client.clone(),
        node: node.to_string(),
        owner: owner_tx,
        clock: lease,
        broken,
        metrics,
        shutdown,
    }));
    Ok((handle, thread))
}

/// Every turn of the scene's stream from `start`, in order, to the owner thread. An ordered
/// consumer is recreated from the next position after any error.
async fn follow(
    stream: jetstream::stream::Stream,
    mut next: u64,
    scene: SceneHandle,
    broken: Arc<std::sync::atomic::AtomicBool>,
    mut shutdown: watch::Receiver<bool>,
) {
    loop {
        if *shutdown.borrow() || broken.load(Relaxed) {
            return;
        }
        let consumer = stream
            .create_consumer(pull::OrderedConfig {
                deliver_policy: jetstream::consumer::DeliverPolicy::ByStartSequence {
                    start_sequence: next,
                },
                ..Default::default()
            })
            .await;
        let messages = match consumer {
            Ok(c) => c.messages().await,
            Err(e) => Err(async_nats::jetstream::consumer::StreamError::with_source(
                async_nats::jetstream::consumer::StreamErrorKind::Other,
                e,
            )),
        };
        match messages {
            Ok(mut messages) => loop {
                let item = tokio::select! {
                    item = messages.next() => item,
                    _ = shutdown.changed() => return,
                };
                let message = match item {
                    Some(Ok(m)) => m,
                    Some(Err(e)) => {
                        tracing::warn!(scene = %scene.name, error = %e, "following the log failed; following again");
                        break;
                    }
                    None => break,
                };
                let pos = match message.info() {
                    Ok(info) => info.stream_sequence,
                    Err(e) => {
                        tracing::warn!(scene = %scene.name, error = %e, "a log message without its position");
                        break;
                    }
                };
                match Turn::decode(&message.payload) {
                    Ok(turn) => {
                        let cmd = Command::Replicate {
                            pos,
                            turn: Box::new(turn),
                        };
                        if scene.send(cmd).await.is_err() {
                            return;
                        }
                    }
                    Err(e) => {
                        let why = format!(
                            "log message {pos} is corrupt ({e}); {}",
                            super::repair::hint(&scene.name)
                        );
                        tracing::error!(scene = %scene.name, pos, error = %e, "the scene's log holds a message this node cannot read");
                        broken.store(true, Relaxed);
                        let _ = scene.send(Command::LogFault { why }).await;
                        return;
                    }
                }
                next = pos + 1;
            },
            Err(e) => {
                tracing::warn!(scene = %scene.name, error = %e, "cannot follow the log; trying again");
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(CLAIM_POLL) => {}
            _ = shutdown.changed() => return,
        }
    }
}

struct LeaseTask {
    scene: SceneHandle,
    owners: kv::Store,
    client: async_nats::Client,
    node: String,
    /// Who the lease names, for this node's sessions (see `forward.rs`).
    owner: watch::Sender<Option<String>>,
    clock: Arc<LeaseClock>,
    broken: Arc<std::sync::atomic::AtomicBool>,
    metrics: Arc<Metrics>,
    shutdown: watch::Receiver<bool>,
}

impl LeaseTask {
    /// Renews a held lease; false when it is lost.
    async fn renew(&self, revision: &mut u64) -> bool {
        let sent = Instant::now();
        match self
            .owners
            .update(&self.scene.name, self.node.clone().into(), *revision)
            .await
        {
            Ok(r) => {
                *revision = r;
                self.clock.extend_to(sent + LEASE_TTL - LEASE_MARGIN);
                true
            }
            Err(e) => {
                tracing::warn!(scene = %self.scene.name, node = %self.node, error = %e, "lost the scene's lease");
                false
            }
        }
    }

    async fn lose(&self, intake: &mut Option<tokio::task::JoinHandle<()>>, why: String) {
        self.clock.revoke();
        self.owner.send_replace(None);
        if let Some(task) = intake.take() {
            task.abort();
        }
        let _ = self.scene.send(Command::StepDown { why }).await;
    }
}

impl LeaseTask {
    /// Hands a held lease back at once (delete with its revision: a key someone else took
    /// since is left alone).
    async fn release(&self, revision: u64) {
        let _ = self
            .owners
            .delete_expect_revision(&self.scene.name, Some(revision))
            .await;
    }

    /// With the lease held at `revision`: make the owner thread catch up and claim the log
    /// (`Command::TakeOver`), renewing meanwhile. The revision while the owner leads, `None`
    /// when it could not (the lease is then given back at once).
    async fn lead(
        &self,
        mut revision: u64,
        intake: &mut Option<tokio::task::JoinHandle<()>>,
    ) -> Option<u64> {
        if intake.is_none() {
            *intake = Some(tokio::spawn(take_edits(
                self.client.clone(),
                self.scene.clone(),
                self.node.clone(),
            )));
        }
        let (done, mut answer) = oneshot::channel();
        if self.scene.send(Command::TakeOver { done }).await.is_err() {
            // The owner thread is gone (the scene is closing): hand the key back now.
            if let Some(edits) = intake.take() {
                edits.abort();
            }
            self.release(revision).await;
            return None;
        }
        // Catching up can take a while: keep the lease meanwhile.
        let claimed = loop {
            tokio::select! {
                a = &mut answer => break a.unwrap_or(false),
                _ = tokio::time::sleep(RENEW_EVERY) => {
                    if !self.renew(&mut revision).await {
                        break false;
                    }
                }
            }
        };
        if claimed && self.clock.valid() {
            Metrics::add(&self.metrics.takeovers, 1);
            self.owner.send_replace(Some(self.node.clone()));
            return Some(revision);
        }
        self.lose(intake, "the log could not be claimed".into())
            .await;
        // Let another node have it now rather than when it expires.
        self.release(revision).await;
        None
    }

    /// The scene is closing on this node (or the node is shutting down): no more forwarded
    /// edits; a held lease is kept, renewed, while the owner thread commits what it has and
    /// writes its last snapshot, and handed over the moment it has stopped.
    async fn close(&self, held: Option<u64>, intake: &mut Option<tokio::task::JoinHandle<()>>) {
        if let Some(edits) = intake.take() {
            edits.abort();
        }
        if let Some(mut revision) = held {
            let kept = loop {
                tokio::select! {
                    () = self.scene.closed() => break true,
                    _ = tokio::time::sleep(RENEW_EVERY) => {
                        if !self.renew(&mut revision).await {
                            break false;
                        }
                    }
                }
            };
            if kept {
                self.release(revision).await;
            }
        }
        self.clock.revoke();
        self.owner.send_replace(None);
    }
}

async fn hold_lease(mut task: LeaseTask) {
    let mut held: Option<u64> = None;
    // Since when nobody holds the lease, while this node has no client on the scene.
    let mut free_since: Option<Instant> = None;
    let mut intake: Option<tokio::task::JoinHandle<()>> = None;
    loop {
        let wait = if held.is_some() {
            RENEW_EVERY
        } else {
            CLAIM_POLL
        };
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            _ = task.shutdown.changed() => {}
        }
        if *task.shutdown.borrow() {
            return task.close(held, &mut intake).await;
        }
        if let Some(mut revision) = held {
            if !task.renew(&mut revision).await {
                held = None;
                task.lose(&mut intake, "the lease could not be renewed".into())
                    .await;
                continue;
            }
            if task.broken.load(Relaxed) {
                // This node cannot follow the log: it must not keep the scene from the others.
                held = None;
                task.lose(
                    &mut intake,
                    "the scene's log cannot be followed here".into(),
                )
                .await;
                task.release(revision).await;
                continue;
            }
            held = if task.scene.info.leading.load(Relaxed) {
                Some(revision)
            } else {
                // The owner stopped ordering edits while the lease stayed ours (an append
                // refused after a pause just under the lease's life): claim the log again
                // rather than hold a lease nobody uses.
                tracing::info!(scene = %task.scene.name, "the owner stopped ordering edits under a held lease; claiming the log again");
                task.lead(revision, &mut intake).await
            };
            continue;
        }
        // Who holds it now (for this node's sessions); nobody: try to take it.
        match task.owners.get(&task.scene.name).await {
            Ok(Some(holder)) => {
                free_since = None;
                let holder = String::from_utf8_lossy(&holder).into_owned();
                task.owner.send_if_modified(|o| {
                    let changed = o.as_deref() != Some(holder.as_str());
                    *o = Some(holder);
                    changed
                });
                continue;
            }
            Ok(None) => {
                task.owner.send_if_modified(|o| o.take().is_some());
                // The lease goes to a node with people on the scene: one without (idle until
                // it closes the scene, or opened for a picture) claims only if none did.
                if task.scene.info.clients.load(Relaxed) == 0 {
                    if free_since.get_or_insert_with(Instant::now).elapsed() < CLAIM_GRACE {
                        continue;
                    }
                } else {
                    free_since = None;
                }
            }
            Err(_) => continue,
        }
        if task.broken.load(Relaxed) {
            continue;
        }
        let sent = Instant::now();
        let Ok(revision) = task
            .owners
            .create(&task.scene.name, task.node.clone().into())
            .await
        else {
            // Another node holds it (or NATS is away): look again later.
            continue;
        };
        task.clock.extend_to(sent + LEASE_TTL - LEASE_MARGIN);
        held = task.lead(revision, &mut intake).await;
        if held.is_none() && task.scene.is_closed() {
            return;
        }
    }
}

/// Forwarded edits for the scene, while this node leads it.
async fn take_edits(client: async_nats::Client, scene: SceneHandle, node: String) {
    let subject = super::forward::owner_subject(&jetlog::edit_subject(&scene.name), &node);
    let mut sub = match client.subscribe(subject).await {
        Ok(s) => s,
        Err(e) => {
            tracing::error!(scene = %scene.name, error = %e, "cannot take the scene's edits");
            return;
        }
    };
    while let Some(message) = sub.next().await {
        let reply = message.reply.map(|r| r.to_string());
        match Forwarded::decode(&message.payload) {
            Ok(request) => {
                if scene
                    .send(Command::Forwarded { reply, request })
                    .await
                    .is_err()
                {
                    return;
                }
            }
            Err(e) => {
                tracing::warn!(scene = %scene.name, error = %e, "a forwarded edit that does not decode");
            }
        }
    }
}
