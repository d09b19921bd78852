//! One scene on one node of a cluster: the tasks around its owner.
//!
//! * **Lease:** without the lease, try to create the scene's key in `brickcast_owners` every
//!   [`CLAIM_POLL`]; with it, renew it (compare-and-set on its revision) every
//!   [`RENEW_EVERY`]. Taking it makes the owner catch up to the log's end and append a marker
//!   (`Command::Lead`); a failed renewal makes it stop appending (`Command::Follow`). A lease
//!   held while the owner does not order (its append was refused after a pause just under the
//!   lease's life) is used again: the owner is asked to lead once more. The lease only says
//!   who *tries*; the log's expected-sequence fence is what keeps two owners from both
//!   appending.
//! * **Intake:** while leading, forwarded edits on `brickcast.edit.<scene>.<node>` go to the
//!   owner in arrival order, and its answers go back in that order.
//! * **Follower:** the scene's stream, in order, to the owner (`Command::Apply`); the owner
//!   skips the turns it appended itself. A message that is not a turn stops the scene on this
//!   node (`Command::Fault`), saying how to repair it.
//! * **Closing** (the scene closing on this node, or the node shutting down): no more
//!   forwarded edits; a held lease is kept while the owner commits and writes its last
//!   snapshot, then handed over at once.
//!
//! Everything here runs on tokio's clock and reaches NATS through [`Jet`], so the cluster's
//! simulation runs these same tasks.

use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;

use bytes::Bytes;
use futures_util::StreamExt;
use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;

use super::forward::{SceneLink, decode_request, encode_outcome, owner_subject};
use super::jet::{Bucket, Jet, LogStream};
use super::log::{self as jetlog, ClusterLoaded, Exec, JetLog, LeaseClock, decode_turn};
use super::signal;
use super::{CLAIM_GRACE, CLAIM_POLL, Cluster, LEASE_MARGIN, LEASE_TTL, RENEW_EVERY};
use crate::metrics::Metrics;
use crate::scene::{self, Clock, Command, Outcome, OwnerConfig, SceneHandle};

/// A scene opened on a node: its owner (not yet running), the handle sessions reach it by,
/// the commands it is sent, and how sessions reach whichever node orders its edits. Its
/// lease and follower tasks run from the moment it is opened.
pub struct Opened<J: Jet> {
    pub owner: scene::Owner,
    pub handle: SceneHandle,
    pub commands: mpsc::Receiver<Command>,
    pub link: SceneLink<J>,
}

/// Opens scene `name`, whose log key is `log` ([`super::SceneEntry`]), loaded from the
/// cluster on node `node` (process `instance`): its owner over a [`JetLog`], following the log, and the lease and follower tasks, which end at `shutdown`
/// (the node's, or the scene's close on this node). Must run inside the runtime `exec` names.
#[allow(clippy::too_many_arguments)]
pub async fn open_scene<J: Jet>(
    jet: &J,
    exec: Exec,
    node: &str,
    instance: &str,
    name: String,
    log: &str,
    mut loaded: ClusterLoaded,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    clock: Clock,
    shutdown: signal::Receiver<bool>,
) -> anyhow::Result<Opened<J>> {
    let lease = Arc::new(LeaseClock::default());
    let start = loaded.pos + 1;
    let jet_log = JetLog::open(jet.clone(), exec, node, log, &mut loaded, lease.clone()).await?;
    let (owner, handle, commands) = scene::open(
        name.clone(),
        loaded.loaded,
        Box::new(jet_log),
        metrics.clone(),
        config,
        clock,
    )?;
    let (owner_tx, owner_rx) = signal::channel(None);
    let link = SceneLink {
        jet: jet.clone(),
        log: log.to_string(),
        subject: jetlog::edit_subject(log),
        owner: owner_rx,
        instance: instance.to_string(),
    };
    let stream = jet
        .stream(log, false)
        .await
        .map_err(|e| anyhow::anyhow!("scene {name}: opening the log stream: {e}"))?;
    tokio::spawn(follow(stream, start, handle.clone(), shutdown.clone()));
    tokio::spawn(hold_lease(LeaseTask {
        scene: handle.clone(),
        log: log.to_string(),
        jet: jet.clone(),
        node: node.to_string(),
        owner: owner_tx,
        clock: lease,
        metrics,
        shutdown,
    }));
    Ok(Opened {
        owner,
        handle,
        commands,
        link,
    })
}

/// Starts serving a scene loaded from the cluster on this node: [`open_scene`], its owner on
/// a thread of its own, and presence across nodes.
#[allow(clippy::too_many_arguments)]
pub async fn start_scene(
    cluster: &Cluster,
    node: &str,
    name: String,
    log: &str,
    loaded: ClusterLoaded,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    shutdown: signal::Receiver<bool>,
) -> anyhow::Result<(SceneHandle, std::thread::JoinHandle<()>, SceneLink<Cluster>)> {
    let runtime = tokio::runtime::Handle::current();
    let opened = open_scene(
        cluster,
        Exec::Node(runtime.clone()),
        node,
        &super::name::process_instance(),
        name,
        log,
        loaded,
        metrics.clone(),
        config,
        Arc::new(std::time::Instant::now),
        shutdown.clone(),
    )
    .await?;
    let Opened {
        owner,
        handle,
        commands,
        link,
    } = opened;
    let thread = scene::run_thread(owner, commands, &handle, runtime)?;
    super::presence::start(
        cluster.client.clone(),
        node.to_string(),
        &handle,
        metrics,
        shutdown,
    );
    Ok((handle, thread, link))
}

/// How long the follower waits for a turn before it looks whether the log moved on without it.
const QUIET_CHECK: std::time::Duration = std::time::Duration::from_secs(2);

/// Every turn of the scene's stream from `next` on, in order, to the owner. Following again
/// from the next position after any error; when nothing comes for a while, it looks whether
/// the log was trimmed past this replica (`Command::Behind`) or holds turns it was not given.
async fn follow<S: LogStream>(
    stream: S,
    mut next: u64,
    scene: SceneHandle,
    mut shutdown: signal::Receiver<bool>,
) {
    loop {
        if shutdown.get() || scene.is_closed() {
            return;
        }
        match stream.follow(next).await {
            Ok(mut messages) => loop {
                let item = tokio::select! {
                    biased;
                    _ = shutdown.changed() => return,
                    item = messages.next() => Some(item),
                    _ = tokio::time::sleep(QUIET_CHECK) => None,
                };
                let (pos, bytes) = match item {
                    Some(Some(Ok(m))) => m,
                    Some(Some(Err(e))) => {
                        tracing::warn!(scene = %scene.name, error = %e, "following the log failed; following again");
                        break;
                    }
                    Some(None) => break,
                    None => {
                        // Quiet: has the log moved on without this replica (trimmed past it
                        // while it was paused, or a stalled consumer)?
                        match stream.bounds().await {
                            Ok((first, _, _)) if first > next => {
                                if scene.send(Command::Behind { first }).await.is_err() {
                                    return;
                                }
                                next = first;
                            }
                            Ok((_, last, _)) if last >= next => break,
                            _ => {}
                        }
                        continue;
                    }
                };
                match decode_turn(&bytes) {
                    Ok(turn) => {
                        let cmd = Command::Apply {
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
                        let _ = scene.send(Command::Fault { why }).await;
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
            biased;
            _ = shutdown.changed() => return,
            _ = tokio::time::sleep(CLAIM_POLL) => {}
        }
    }
}

struct LeaseTask<J: Jet> {
    scene: SceneHandle,
    /// The scene's log key: the lease's key in `brickcast_owners`.
    log: String,
    jet: J,
    node: String,
    /// Who the lease names, for this node's sessions (see `forward.rs`).
    owner: signal::Sender<Option<String>>,
    clock: Arc<LeaseClock>,
    metrics: Arc<Metrics>,
    shutdown: signal::Receiver<bool>,
}

type Intake = Option<tokio::task::JoinHandle<()>>;

impl<J: Jet> LeaseTask<J> {
    /// Renews a held lease; false when it is lost.
    async fn renew(&self, revision: &mut u64) -> bool {
        let sent = Instant::now();
        let node = Bytes::from(self.node.clone());
        match self
            .jet
            .kv_update(Bucket::Owners, &self.log, node, *revision)
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

    async fn lose(&self, intake: &mut Intake, why: String) {
        self.clock.revoke();
        self.owner.send_replace(None);
        if let Some(task) = intake.take() {
            task.abort();
        }
        let _ = self.scene.send(Command::Follow { why }).await;
    }

    /// Hands a held lease back at once (delete with its revision: a key someone else took
    /// since is left alone).
    async fn release(&self, revision: u64) {
        let _ = self
            .jet
            .kv_delete(Bucket::Owners, &self.log, Some(revision))
            .await;
    }

    /// With the lease held at `revision`: make the owner catch up and claim the log
    /// (`Command::Lead`), renewing meanwhile. The revision while the owner leads, `None` when
    /// it could not (the lease is then given back at once).
    async fn lead(&self, mut revision: u64, intake: &mut Intake) -> Option<u64> {
        if intake.is_none() {
            *intake = Some(tokio::spawn(take_edits(
                self.jet.clone(),
                self.scene.clone(),
                self.node.clone(),
                self.log.clone(),
            )));
        }
        let (done, mut answer) = oneshot::channel();
        if self.scene.send(Command::Lead { done }).await.is_err() {
            // The owner is gone (the scene is closing): hand the key back now.
            if let Some(edits) = intake.take() {
                edits.abort();
            }
            self.release(revision).await;
            return None;
        }
        // Catching up can take a while: keep the lease meanwhile.
        let claimed = loop {
            tokio::select! {
                biased;
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
    /// edits; a held lease is kept, renewed, while the owner commits what it has and writes
    /// its last snapshot, and handed over the moment it has stopped.
    async fn close(&self, held: Option<u64>, intake: &mut Intake) {
        if let Some(edits) = intake.take() {
            edits.abort();
        }
        if let Some(mut revision) = held {
            let kept = loop {
                tokio::select! {
                    biased;
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

async fn hold_lease<J: Jet>(mut task: LeaseTask<J>) {
    let mut held: Option<u64> = None;
    // Since when nobody holds the lease, while this node has no client on the scene.
    let mut free_since: Option<Instant> = None;
    let mut intake: Intake = None;
    loop {
        let wait = if held.is_some() {
            RENEW_EVERY
        } else {
            CLAIM_POLL
        };
        tokio::select! {
            biased;
            _ = task.shutdown.changed() => {}
            _ = tokio::time::sleep(wait) => {}
        }
        if task.shutdown.get() {
            return task.close(held, &mut intake).await;
        }
        if let Some(mut revision) = held {
            if !task.renew(&mut revision).await {
                held = None;
                task.lose(&mut intake, "the lease could not be renewed".into())
                    .await;
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
            if held.is_none() && task.scene.is_closed() {
                return;
            }
            continue;
        }
        // Who holds it now (for this node's sessions); nobody: try to take it.
        match task.jet.kv_get(Bucket::Owners, &task.log).await {
            Ok(Some(holder)) => {
                free_since = None;
                let holder = String::from_utf8_lossy(&holder.value).into_owned();
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
        if task.scene.is_closed() {
            return;
        }
        let sent = Instant::now();
        let node = Bytes::from(task.node.clone());
        let Ok(revision) = task.jet.kv_create(Bucket::Owners, &task.log, node).await else {
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

/// Forwarded edits for the scene, while this node leads it, in arrival order; each answer is
/// published once the owner gives it, in the same order.
async fn take_edits<J: Jet>(jet: J, scene: SceneHandle, node: String, log: String) {
    let subject = owner_subject(&jetlog::edit_subject(&log), &node);
    let mut sub = match jet.subscribe(subject).await {
        Ok(s) => s,
        Err(e) => {
            tracing::error!(scene = %scene.name, error = %e, "cannot take the scene's edits");
            return;
        }
    };
    let (answers, waiting) = mpsc::unbounded_channel();
    tokio::spawn(publish_answers(jet, waiting));
    while let Some(message) = sub.next().await {
        let request = match decode_request(&message.payload) {
            Ok(request) => request,
            Err(e) => {
                tracing::warn!(scene = %scene.name, error = %e, "a forwarded edit that does not decode");
                continue;
            }
        };
        let (reply, answer) = match message.reply {
            Some(to) => {
                let (tx, rx) = oneshot::channel();
                (Some(tx), Some((to, rx)))
            }
            None => (None, None),
        };
        if scene
            .send(Command::Request { request, reply })
            .await
            .is_err()
        {
            return;
        }
        if let Some(answer) = answer {
            let _ = answers.send(answer);
        }
    }
}

/// Publishes the owner's answers to forwarded edits, in the order the edits came.
async fn publish_answers<J: Jet>(
    jet: J,
    mut waiting: mpsc::UnboundedReceiver<(String, oneshot::Receiver<Outcome>)>,
) {
    while let Some((to, answer)) = waiting.recv().await {
        // No answer (a copy its sender no longer waits for): the sender's retry gets one.
        let Ok(outcome) = answer.await else { continue };
        match encode_outcome(&outcome) {
            Ok(bytes) => {
                if let Err(e) = jet.publish(to, Bytes::from(bytes)).await {
                    tracing::warn!(error = %e, "cannot send a reply to a forwarded edit");
                }
            }
            Err(e) => tracing::error!(error = %e, "cannot encode a reply to a forwarded edit"),
        }
    }
}
