//! `brickcast load`: many websocket clients editing one scene, to measure a server.
//!
//! The coordinator checks the options against the scene (one probe connection), starts one tokio
//! task per client ([`worker`]), waits until all have synced, lets editors edit for the
//! duration, waits for their acks, then fetches a fresh copy of the scene and has every client
//! compare its own copy with it. A run whose copies differ fails, however fast it was.
//!
//! Measured: acked ops/s; voxels changed/s (the server's own count from `/metrics`, or what one
//! client saw change in its copy when `/metrics` is unreachable); edit→visible latency (send
//! time of an edit batch to the arrival, at another client, of the delta containing its
//! sequence; see [`observe`]); ack latency; bytes per client; resyncs, rejected ops, errors.

pub mod copy;
pub mod fly;
pub mod histogram;
pub mod observe;
pub mod ops;
pub mod options;
pub mod scratch;
pub mod worker;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::IsTerminal;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use brickcast_protocol::wire::Role;
use serde::Serialize;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{mpsc, watch};

use self::histogram::Histogram;
pub use self::options::{LoadArgs, OpKind, OptionError, RegionSpec, VoxelBox};
use self::worker::{ClientPlan, EditorPlan, Event, Phase, Shared, Verdict};
use crate::link::{self, Link, LinkError};
use crate::replica::{Replica, ReplicaError};

/// Longest wait for every client to connect and sync.
const SETUP_TIMEOUT: Duration = Duration::from_secs(600);
/// Longest wait, after the edit phase, for the last acks.
const DRAIN_TIMEOUT: Duration = Duration::from_secs(30);
/// Longest wait for every copy to equal the fresh one.
const VERIFY_TIMEOUT: Duration = Duration::from_secs(30);

/// Why a run could not be made (as opposed to a run that was made and failed its checks).
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error(transparent)]
    Options(#[from] OptionError),
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error(
        "the server gives this connection the {0:?} role: load clients must edit (pass an editor --token)"
    )]
    NotEditor(Role),
    #[error(
        "scene {scene} holds {bricks} bricks and a load run's edits would stay in it, so the run edits a scratch scene it makes and deletes through the server's admin API, which refused: {why}. Give an admin --token (or run on the server's machine without --auth), or pass --in-place to edit {scene} itself"
    )]
    Scratch {
        scene: String,
        bricks: u32,
        why: String,
    },
    #[error("a load client could not connect and sync: {0}")]
    Setup(String),
    #[error("the clients did not all connect and sync within {0:?}")]
    SetupTimeout(Duration),
    #[error("fetching a fresh copy of the scene for the final check: {0}")]
    Fresh(LinkError),
    #[error("fetching a fresh copy of the scene for the final check: {0}")]
    FreshReplica(#[from] ReplicaError),
    #[error("could not start the async runtime: {0}")]
    Runtime(std::io::Error),
}

/// `latency_ms` in the JSON report.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct Percentiles {
    pub p50: f64,
    pub p95: f64,
    pub p99: f64,
    pub max: f64,
}

/// `ack_latency_ms` in the JSON report.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct AckPercentiles {
    pub p50: f64,
    pub p99: f64,
}

/// What `brickcast load --json` prints: exactly the fields issue #6 lists.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LoadReport {
    /// Editing clients (`--clients`).
    pub clients: u32,
    /// From the start of editing to the last ack (at least `--duration`).
    pub duration_s: f64,
    /// Ops the server applied and acknowledged (rejected ops not included).
    pub ops_acked: u64,
    pub ops_per_s: f64,
    /// Voxels changed per second: the server's count when `/metrics` answers, else the voxels
    /// one client saw change in its copy.
    pub voxels_per_s: f64,
    /// Edit→visible latency per edit batch.
    pub latency_ms: Percentiles,
    /// Send to Ack, per edit batch.
    pub ack_latency_ms: AckPercentiles,
    /// Websocket payload bytes received per connection (mean over editors and viewers, setup
    /// sync included).
    pub bytes_in: u64,
    /// Websocket payload bytes sent per connection (mean over editors and viewers).
    pub bytes_out: u64,
    pub resyncs: u64,
    pub rejected: u64,
    /// Only with `--undo-ratio` (so the fields issue #6 fixed stay the same without it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub undo: Option<UndoReport>,
    /// Only with `--presence-hz`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub presence: Option<PresenceReport>,
    /// Server CPU time over the edit window divided by its length (1.0 = one core), when the
    /// server's `/metrics` exports it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub server_cpu_cores: Option<f64>,
    /// Clients that failed (connection, protocol, unacknowledged batches) plus copies that did
    /// not match the server's: any error makes the run fail.
    pub errors: u64,
    /// Per server, when the run was given several (a cluster's nodes), in the order given.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub nodes: Vec<NodeReport>,
}

/// One server's share of a run over several (`brickcast load URL URL …`): clients are dealt
/// to the servers in turn.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct NodeReport {
    pub url: String,
    /// Connections (editors and viewers) on this server.
    pub clients: u32,
    pub ops_acked: u64,
    /// Send to Ack, for this server's editors.
    pub ack_latency_ms: AckPercentiles,
    /// Edit→visible, as this server's clients saw other clients' edits.
    pub latency_ms: AckPercentiles,
    /// This server's CPU over the edit window (1.0 = one core), from its `/metrics`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub server_cpu_cores: Option<f64>,
    /// The sequence its fresh copy was at for the final check.
    pub final_seq: u64,
}

/// Undo and redo messages acknowledged (with `--undo-ratio`), those refused (nothing to undo),
/// and the voxels they put back.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct UndoReport {
    pub applied: u64,
    pub per_s: f64,
    pub refused: u64,
    pub voxels: u64,
}

/// Presence under load (`--presence-hz`): from a client sending to another seeing it, and what
/// the server sent.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PresenceReport {
    pub sent: u64,
    pub latency_ms: AckPercentiles,
    pub samples: u64,
    /// Presence frame bytes the server queued per client per second (from `/metrics`).
    pub bytes_per_client_s: Option<f64>,
}

/// Everything else the run learned, for the table.
#[derive(Debug, Clone)]
pub struct LoadDetails {
    pub url: String,
    pub scene: String,
    pub size: [u32; 3],
    pub viewers: u32,
    pub setup_s: f64,
    pub latency_samples: u64,
    /// Acked edits no delta showed (they changed nothing) or that arrived in a resync.
    pub unseen: u64,
    pub ack_mean_ms: f64,
    /// Voxels the server applied per second (its `/metrics` counter), if reachable.
    pub voxels_applied_per_s: Option<f64>,
    /// Voxels one client saw change in its copy, per second (net of edits that undid each
    /// other within one delta).
    pub voxels_seen_per_s: f64,
    pub editor_bytes: (u64, u64),
    pub viewer_bytes: (u64, u64),
    pub final_seq: u64,
    pub verified: usize,
    pub connections: usize,
    /// The server's own time accounting over the edit window, when `/metrics` answers.
    pub server: Option<ServerTimes>,
}

/// A finished run: the report, the details, and what failed (empty when the run passed).
#[derive(Debug, Clone)]
pub struct LoadOutcome {
    pub report: LoadReport,
    pub details: LoadDetails,
    pub failures: Vec<String>,
}

/// Runs a load test against the scene at `url` on a runtime of its own.
pub fn run_blocking(url: &str, args: &LoadArgs) -> Result<LoadOutcome, LoadError> {
    run_blocking_on(&[url.to_string()], args)
}

/// [`run_blocking`] over several servers of one scene (a cluster's nodes).
pub fn run_blocking_on(urls: &[String], args: &LoadArgs) -> Result<LoadOutcome, LoadError> {
    args.check()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(LoadError::Runtime)?;
    runtime.block_on(run_on(urls, args))
}

/// Runs a load test against the scene at `url`.
pub async fn run(url: &str, args: &LoadArgs) -> Result<LoadOutcome, LoadError> {
    run_on(&[url.to_string()], args).await
}

/// Runs a load test against one scene served at several addresses (a cluster's nodes):
/// client `i` connects to `urls[i % urls.len()]`; figures are reported per server too, and
/// every server's copy must end equal.
pub async fn run_on(urls: &[String], args: &LoadArgs) -> Result<LoadOutcome, LoadError> {
    args.check()?;
    let urls: Vec<String> = urls
        .iter()
        .map(|u| link::websocket_url(u))
        .collect::<Result<_, _>>()?;
    let Some(url) = urls.first().cloned() else {
        return Err(LoadError::Setup("no server address given".into()));
    };
    let welcome = probe(&urls, args).await?;
    if welcome.total_bricks == 0 || args.in_place {
        return edit(urls, args).await;
    }
    // On a cluster the scratch scene is made through the first node; every node serves it.
    let scratch = scratch::Scratch::create(&url, args.token.as_deref(), &welcome).await?;
    let outcome = edit(scratch.urls(&urls), args).await;
    scratch.delete().await;
    outcome
}

/// Checks the scene at every address: one scene, and this client may edit it.
async fn probe(urls: &[String], args: &LoadArgs) -> Result<link::Welcome, LoadError> {
    let url = &urls[0];
    let probe = Link::connect(url, "brickcast load probe", 0, args.token.as_deref(), None).await?;
    let welcome = probe.welcome.clone();
    probe.close().await;
    for other in &urls[1..] {
        let probe = Link::connect(
            other,
            "brickcast load probe",
            0,
            args.token.as_deref(),
            None,
        )
        .await?;
        let w = probe.welcome.clone();
        probe.close().await;
        if w.scene != welcome.scene || w.size != welcome.size {
            return Err(LoadError::Setup(format!(
                "{other} serves scene {} {:?}, {url} serves {} {:?}: give addresses of one scene",
                w.scene, w.size, welcome.scene, welcome.size
            )));
        }
    }
    if welcome.role != Role::Editor {
        return Err(LoadError::NotEditor(welcome.role));
    }
    Ok(welcome)
}

/// The run itself, on the scene at `urls`.
async fn edit(urls: Vec<String>, args: &LoadArgs) -> Result<LoadOutcome, LoadError> {
    let url = urls[0].clone();
    let welcome = probe(&urls, args).await?;
    let areas = args.plan(welcome.size, &welcome.limits)?;
    if args.rate > f64::from(welcome.limits.max_edits_per_second) {
        tracing::warn!(
            "--rate {} is above the server's limit of {} ops per client per second: expect rejections",
            args.rate,
            welcome.limits.max_edits_per_second
        );
    }

    let editors = args.clients as usize;
    let connections = editors + args.viewers as usize;
    let shared = Arc::new(Shared::new(connections));
    let (control, control_rx) = watch::channel(Phase::Setup);
    let (events_tx, mut events) = mpsc::unbounded_channel();
    let pace = args.pace();
    let mut tasks = Vec::with_capacity(connections);
    for index in 0..connections {
        let editor = areas.get(index).map(|&area| EditorPlan {
            op: args.op,
            area,
            radius: args.radius,
            batch: args.batch,
            undo_ratio: args.undo_ratio,
            interval: pace.interval,
            observer: (connections > 1).then_some((index + 1) % connections),
        });
        let plan = ClientPlan {
            index,
            url: urls[index % urls.len()].clone(),
            token: args.token.clone(),
            editor,
            // The observer of editor 0 also counts the voxels it sees change.
            count_voxels: index == 1 % connections,
            presence_hz: args.presence_hz,
        };
        tasks.push(tokio::spawn(worker::client(
            plan,
            shared.clone(),
            control_rx.clone(),
            events_tx.clone(),
        )));
    }
    drop(events_tx);

    let progress = Progress::new();
    let setup_started = Instant::now();
    let setup_deadline = setup_started + SETUP_TIMEOUT;
    let mut ready = 0;
    let mut setup_error = None;
    // A line a second, however often clients report (a sleep restarted by every event
    // would never fire while they do).
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.reset();
    while ready < connections && setup_error.is_none() {
        tokio::select! {
            ev = events.recv() => match ev {
                Some(Event::Ready { result: Ok(()), .. }) => ready += 1,
                Some(Event::Ready { result: Err(e), .. }) => setup_error = Some(LoadError::Setup(e)),
                Some(Event::Drained { .. }) => {}
                None => setup_error = Some(LoadError::Setup("every client stopped".into())),
            },
            () = tokio::time::sleep_until(setup_deadline.into()) => {
                setup_error = Some(LoadError::SetupTimeout(SETUP_TIMEOUT));
            }
            _ = tick.tick() => {
                let live = &shared.live;
                progress.line(&format!(
                    "connecting and syncing: {ready}/{connections} clients ready, {}/{} bricks received",
                    live.sync_received.load(Relaxed),
                    live.sync_total.load(Relaxed),
                ));
            }
        }
    }
    if let Some(e) = setup_error {
        let _ = control.send(Phase::Abort);
        for t in tasks {
            let _ = t.await;
        }
        progress.done();
        return Err(e);
    }
    let setup_s = setup_started.elapsed().as_secs_f64();

    let mut metrics_before = Vec::with_capacity(urls.len());
    for u in &urls {
        metrics_before.push(server_metrics(u).await);
    }
    let start = Instant::now();
    let end = start + Duration::from_secs_f64(args.duration);
    let _ = control.send(Phase::Run { start, end });
    let mut drained = 0;
    let mut last_ack = None::<Instant>;
    let mut tick = tokio::time::interval_at(
        (start + Duration::from_secs(1)).into(),
        Duration::from_secs(1),
    );
    let mut last_ops = 0;
    let live = &shared.live;
    while drained < editors {
        tokio::select! {
            ev = events.recv() => match ev {
                Some(Event::Drained { last_ack: at, .. }) => {
                    drained += 1;
                    last_ack = last_ack.max(at);
                }
                Some(Event::Ready { .. }) => {}
                None => break,
            },
            now = tick.tick() => {
                if now.into_std() > end + DRAIN_TIMEOUT {
                    break;
                }
                let ops = live.ops_acked.load(Relaxed);
                let acks = live.acks.load(Relaxed).max(1);
                progress.line(&format!(
                    "{:>5.0}/{} s  {:>10} ops/s  {:>12} acked  ack mean {:.2} ms  resyncs {}  rejected {}  errors {}",
                    start.elapsed().as_secs_f64().min(args.duration),
                    args.duration,
                    ops - last_ops,
                    ops,
                    live.ack_ns.load(Relaxed) as f64 / acks as f64 / 1e6,
                    live.resyncs.load(Relaxed),
                    live.rejected.load(Relaxed),
                    live.errors.load(Relaxed),
                ));
                last_ops = ops;
            }
        }
    }
    let window_end = last_ack.map_or(end, |a| a.max(end));
    let duration_s = window_end.duration_since(start).as_secs_f64();
    let mut metrics_after = Vec::with_capacity(urls.len());
    for u in &urls {
        metrics_after.push(server_metrics(u).await);
    }
    progress.done();

    // Every acknowledged edit is in the server's scene now: that scene, fetched afresh, is what
    // every client's copy must equal.
    let fresh = fetch(&url, args.token.as_deref()).await;
    let (hash, final_seq) = match &fresh {
        Ok(replica) => (replica.map.content_hash(), replica.seq),
        Err(_) => (0, 0),
    };
    let _ = control.send(Phase::Verify {
        hash,
        deadline: Instant::now() + VERIFY_TIMEOUT,
    });
    if fresh.is_err() {
        let _ = control.send(Phase::Abort);
    }
    let mut reports = Vec::with_capacity(connections);
    for (index, t) in tasks.into_iter().enumerate() {
        reports.push(match t.await {
            Ok(r) => r,
            Err(e) => {
                let mut r = worker::ClientReport::new(index, index < editors);
                r.errors.push(format!("client {index}: its task died: {e}"));
                r
            }
        });
    }
    fresh?;

    let mut ack = Histogram::default();
    let mut latency = Histogram::default();
    let mut unseen = 0;
    let n = urls.len();
    let mut node_latency = vec![Histogram::default(); n];
    let mut node_ack = vec![Histogram::default(); n];
    let mut node_ops = vec![0u64; n];
    for i in 0..connections {
        let log = shared.observer(i);
        latency.merge(&log.latency);
        node_latency[i % n].merge(&log.latency);
        unseen += log.unseen + log.still_waiting() as u64;
    }
    for r in &reports {
        node_ack[r.index % n].merge(&r.ack_latency);
        node_ops[r.index % n] += r.ops_acked;
    }
    let mut failures = Vec::new();
    // Every other server's copy, once it has caught up, must be the same scene.
    let mut node_seqs = vec![final_seq; n];
    for (i, u) in urls.iter().enumerate().skip(1) {
        let deadline = Instant::now() + VERIFY_TIMEOUT;
        loop {
            match fetch(u, args.token.as_deref()).await {
                Ok(copy) if copy.seq >= final_seq || Instant::now() >= deadline => {
                    node_seqs[i] = copy.seq;
                    if copy.seq == final_seq && copy.map.content_hash() != hash {
                        failures.push(format!(
                            "{u}: its scene at seq {final_seq} (hash {:016x}) differs from {url}'s (hash {hash:016x})",
                            copy.map.content_hash()
                        ));
                    } else if copy.seq < final_seq {
                        failures.push(format!(
                            "{u}: still at seq {} after {VERIFY_TIMEOUT:?}, {url} is at {final_seq}",
                            copy.seq
                        ));
                    }
                    break;
                }
                Ok(_) => tokio::time::sleep(Duration::from_millis(200)).await,
                Err(e) => {
                    failures.push(format!("{u}: fetching its copy for the final check: {e}"));
                    break;
                }
            }
        }
    }
    let (mut ops_acked, mut rejected, mut resyncs, mut voxels_seen) = (0, 0, 0, 0);
    let (mut undos, mut undos_refused, mut undo_voxels) = (0, 0, 0);
    let mut presence_latency = Histogram::default();
    let mut presence_sent = 0;
    let (mut editor_bytes, mut viewer_bytes) = ((0, 0), (0, 0));
    let mut verified = 0;
    for r in &reports {
        ack.merge(&r.ack_latency);
        ops_acked += r.ops_acked;
        rejected += r.rejected;
        resyncs += r.resyncs;
        undos += r.undos;
        presence_latency.merge(&r.presence_latency);
        presence_sent += r.presence_sent;
        undos_refused += r.undos_refused;
        undo_voxels += r.undo_voxels;
        voxels_seen += r.voxels_seen;
        let bytes = if r.editor {
            &mut editor_bytes
        } else {
            &mut viewer_bytes
        };
        bytes.0 += r.bytes_in;
        bytes.1 += r.bytes_out;
        failures.extend(r.errors.iter().cloned());
        match r.verdict {
            Verdict::Match => verified += 1,
            Verdict::Mismatch { hash: h, seq } => failures.push(format!(
                "client {}: its copy (hash {h:016x}, seq {seq}) differs from the server's (hash {hash:016x}, seq {final_seq})",
                r.index
            )),
            Verdict::NotChecked if r.errors.is_empty() => failures.push(format!(
                "client {}: stopped before its copy could be checked",
                r.index
            )),
            Verdict::NotChecked => {}
        }
    }
    let per = |total: u64, n: usize| if n == 0 { 0 } else { total / n as u64 };
    let node_times: Vec<Option<ServerTimes>> = metrics_before
        .iter()
        .zip(&metrics_after)
        .map(|(a, b)| match (a, b) {
            (Some(a), Some(b)) => Some(ServerTimes::between(a, b)),
            _ => None,
        })
        .collect();
    let server = node_times
        .iter()
        .try_fold(ServerTimes::default(), |sum, t| Some(sum.plus(t.as_ref()?)));
    let nodes = if n > 1 {
        urls.iter()
            .enumerate()
            .map(|(i, u)| NodeReport {
                url: u.clone(),
                clients: (0..connections).filter(|c| c % n == i).count() as u32,
                ops_acked: node_ops[i],
                ack_latency_ms: AckPercentiles {
                    p50: node_ack[i].quantile_ms(0.50),
                    p99: node_ack[i].quantile_ms(0.99),
                },
                latency_ms: AckPercentiles {
                    p50: node_latency[i].quantile_ms(0.50),
                    p99: node_latency[i].quantile_ms(0.99),
                },
                server_cpu_cores: node_times[i]
                    .as_ref()
                    .and_then(|t| t.cpu_s)
                    .map(|c| c / duration_s),
                final_seq: node_seqs[i],
            })
            .collect()
    } else {
        Vec::new()
    };
    let voxels_applied_per_s = server.as_ref().map(|s| s.voxels_changed / duration_s);
    let voxels_seen_per_s = voxels_seen as f64 / duration_s;
    let report = LoadReport {
        clients: args.clients,
        duration_s,
        ops_acked,
        ops_per_s: ops_acked as f64 / duration_s,
        voxels_per_s: voxels_applied_per_s.unwrap_or(voxels_seen_per_s),
        latency_ms: Percentiles {
            p50: latency.quantile_ms(0.50),
            p95: latency.quantile_ms(0.95),
            p99: latency.quantile_ms(0.99),
            max: latency.max_ms(),
        },
        ack_latency_ms: AckPercentiles {
            p50: ack.quantile_ms(0.50),
            p99: ack.quantile_ms(0.99),
        },
        bytes_in: per(editor_bytes.0 + viewer_bytes.0, connections),
        bytes_out: per(editor_bytes.1 + viewer_bytes.1, connections),
        resyncs,
        rejected,
        undo: (args.undo_ratio > 0.0).then(|| UndoReport {
            applied: undos,
            per_s: undos as f64 / duration_s,
            refused: undos_refused,
            voxels: undo_voxels,
        }),
        presence: (args.presence_hz > 0.0).then(|| PresenceReport {
            sent: presence_sent,
            latency_ms: AckPercentiles {
                p50: presence_latency.quantile_ms(0.50),
                p99: presence_latency.quantile_ms(0.99),
            },
            samples: presence_latency.count(),
            bytes_per_client_s: server
                .as_ref()
                .map(|s| s.presence_bytes / connections.max(1) as f64 / duration_s),
        }),
        server_cpu_cores: server
            .as_ref()
            .and_then(|s| s.cpu_s)
            .map(|c| c / duration_s),
        errors: failures.len() as u64,
        nodes,
    };
    let details = LoadDetails {
        url,
        scene: welcome.scene,
        size: welcome.size,
        viewers: args.viewers,
        setup_s,
        latency_samples: latency.count(),
        unseen,
        ack_mean_ms: ack.mean_ns() / 1e6,
        voxels_applied_per_s,
        voxels_seen_per_s,
        editor_bytes: (per(editor_bytes.0, editors), per(editor_bytes.1, editors)),
        viewer_bytes: (
            per(viewer_bytes.0, connections - editors),
            per(viewer_bytes.1, connections - editors),
        ),
        final_seq,
        verified,
        connections,
        server,
    };
    Ok(LoadOutcome {
        report,
        details,
        failures,
    })
}

/// A full copy of the scene as a new client gets it.
async fn fetch(url: &str, token: Option<&str>) -> Result<Replica, LoadError> {
    let mut link = Link::connect(url, "brickcast load check", 0, token, None)
        .await
        .map_err(LoadError::Fresh)?;
    let mut replica = Replica::new(&link.welcome.scene, link.welcome.size)?;
    replica.record_gpu_changes(false);
    link::sync(&mut link, &mut replica, |_| {})
        .await
        .map_err(LoadError::Fresh)?;
    link.close().await;
    Ok(replica)
}

/// The server's counters, read from `/metrics` on the scene's host: series (labels included) →
/// value. `None` when that does not answer (a proxy may expose only the websocket).
pub(crate) async fn server_metrics(ws_url: &str) -> Option<BTreeMap<String, f64>> {
    parse_metrics(&http_get(ws_url, "/metrics").await?)
}

/// The whole HTTP response to `GET path` on the host of a `ws://` scene address (at most 4
/// MiB, within 5 s); `None` when it does not answer.
pub(crate) async fn http_get(ws_url: &str, path: &str) -> Option<String> {
    let host = ws_url.strip_prefix("ws://")?.split('/').next()?.to_string();
    let get = async {
        let mut stream = tokio::net::TcpStream::connect(&host).await.ok()?;
        let request = format!("GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n");
        stream.write_all(request.as_bytes()).await.ok()?;
        let mut body = Vec::new();
        stream.take(4 << 20).read_to_end(&mut body).await.ok()?;
        Some(String::from_utf8_lossy(&body).into_owned())
    };
    tokio::time::timeout(Duration::from_secs(5), get)
        .await
        .ok()
        .flatten()
}

/// The series of an HTTP response carrying Prometheus text.
fn parse_metrics(response: &str) -> Option<BTreeMap<String, f64>> {
    let (head, body) = response.split_once("\r\n\r\n")?;
    if !head.starts_with("HTTP/1.1 200") {
        return None;
    }
    let series: BTreeMap<String, f64> = body
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (name, value) = l.rsplit_once(' ')?;
            Some((name.to_string(), value.trim().parse().ok()?))
        })
        .collect();
    (!series.is_empty()).then_some(series)
}

/// What the server's own accounting says about the run: counter increases between two scrapes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ServerTimes {
    pub voxels_changed: f64,
    /// Server process CPU seconds (absent from servers that do not export it).
    pub cpu_s: Option<f64>,
    pub presence_bytes: f64,
    pub turns: f64,
    /// (phase, seconds) of the scene owners' wall time.
    pub owner: Vec<(String, f64)>,
    /// (phase, seconds) of the sessions' time.
    pub session: Vec<(String, f64)>,
}

impl ServerTimes {
    /// Two servers' figures together (phases added by name).
    fn plus(mut self, other: &ServerTimes) -> ServerTimes {
        self.voxels_changed += other.voxels_changed;
        self.cpu_s = match (self.cpu_s, other.cpu_s) {
            (Some(a), Some(b)) => Some(a + b),
            (a, b) => a.or(b),
        };
        self.presence_bytes += other.presence_bytes;
        self.turns += other.turns;
        for (list, more) in [
            (&mut self.owner, &other.owner),
            (&mut self.session, &other.session),
        ] {
            for (phase, secs) in more {
                match list.iter_mut().find(|(p, _)| p == phase) {
                    Some((_, s)) => *s += secs,
                    None => list.push((phase.clone(), *secs)),
                }
            }
        }
        self
    }

    fn between(before: &BTreeMap<String, f64>, after: &BTreeMap<String, f64>) -> ServerTimes {
        let delta = |name: &str| after.get(name).unwrap_or(&0.0) - before.get(name).unwrap_or(&0.0);
        let phases = |family: &str| -> Vec<(String, f64)> {
            let prefix = format!("{family}{{phase=\"");
            after
                .keys()
                .filter_map(|k| {
                    let phase = k.strip_prefix(&prefix)?.strip_suffix("\"}")?;
                    Some((phase.to_string(), delta(k)))
                })
                .collect()
        };
        let cpu = "brickcast_process_cpu_seconds_total";
        ServerTimes {
            voxels_changed: delta("brickcast_voxels_changed_total"),
            cpu_s: (before.contains_key(cpu) && after.contains_key(cpu)).then(|| delta(cpu)),
            presence_bytes: delta("brickcast_presence_bytes_total"),
            turns: delta("brickcast_owner_turns_total"),
            owner: phases("brickcast_owner_seconds_total"),
            session: phases("brickcast_session_seconds_total"),
        }
    }
}

/// The progress line on stderr: rewritten in place on a terminal, one line per second otherwise.
struct Progress {
    terminal: bool,
}

impl Progress {
    fn new() -> Progress {
        Progress {
            terminal: std::io::stderr().is_terminal(),
        }
    }

    fn line(&self, text: &str) {
        if self.terminal {
            eprint!("\r\x1b[2K{text}");
        } else {
            eprintln!("{text}");
        }
    }

    fn done(&self) {
        if self.terminal {
            eprintln!();
        }
    }
}

impl LoadOutcome {
    /// The human-readable summary.
    pub fn table(&self) -> String {
        let r = &self.report;
        let d = &self.details;
        let mut t = String::new();
        let mut row = |k: &str, v: String| {
            let _ = writeln!(t, "  {k:<28} {v}");
        };
        row("scene", format!("{} {:?} at {}", d.scene, d.size, d.url));
        for node in &r.nodes {
            row(
                "  server",
                format!(
                    "{}: {} clients, {} ops acked, ack p50 {:.2} p99 {:.2} ms, visible p50 {:.2} p99 {:.2} ms{}",
                    node.url,
                    node.clients,
                    node.ops_acked,
                    node.ack_latency_ms.p50,
                    node.ack_latency_ms.p99,
                    node.latency_ms.p50,
                    node.latency_ms.p99,
                    node.server_cpu_cores
                        .map(|c| format!(", cpu {:.0}% of one core", c * 100.0))
                        .unwrap_or_default()
                ),
            );
        }
        row(
            "clients",
            format!("{} editing + {} viewers", r.clients, d.viewers),
        );
        row("connect + sync", format!("{:.2} s", d.setup_s));
        row("edit window", format!("{:.2} s", r.duration_s));
        row(
            "ops acked",
            format!("{} ({:.0} ops/s)", r.ops_acked, r.ops_per_s),
        );
        row(
            "voxels changed/s",
            match d.voxels_applied_per_s {
                Some(v) => format!(
                    "{v:.0} by the server's count (every scene it serves); one client's deltas showed {:.0}",
                    d.voxels_seen_per_s
                ),
                None => format!(
                    "{:.0} seen by one client (server /metrics unreachable)",
                    d.voxels_seen_per_s
                ),
            },
        );
        let l = &r.latency_ms;
        row(
            "edit→visible ms",
            format!(
                "p50 {:.2}  p95 {:.2}  p99 {:.2}  max {:.2}  ({} samples, {} edits changed nothing visible)",
                l.p50, l.p95, l.p99, l.max, d.latency_samples, d.unseen
            ),
        );
        row(
            "ack ms",
            format!(
                "p50 {:.2}  p99 {:.2}  mean {:.2}",
                r.ack_latency_ms.p50, r.ack_latency_ms.p99, d.ack_mean_ms
            ),
        );
        row(
            "bytes per editor",
            format!(
                "{} in, {} out",
                human_bytes(d.editor_bytes.0),
                human_bytes(d.editor_bytes.1)
            ),
        );
        if d.viewers > 0 {
            row(
                "bytes per viewer",
                format!(
                    "{} in, {} out",
                    human_bytes(d.viewer_bytes.0),
                    human_bytes(d.viewer_bytes.1)
                ),
            );
        }
        // A server without phase accounting (older builds) exports none: say nothing then.
        if let Some(server) = d.server.as_ref().filter(|s| !s.owner.is_empty()) {
            let list = |phases: &[(String, f64)]| {
                phases
                    .iter()
                    .map(|(p, secs)| format!("{p} {secs:.2}"))
                    .collect::<Vec<_>>()
                    .join("  ")
            };
            row(
                "server owner s (all scenes)",
                format!(
                    "{}  ({:.0} turns, {:.0} ops/turn)",
                    list(&server.owner),
                    server.turns,
                    r.ops_acked as f64 / server.turns.max(1.0)
                ),
            );
            row("server sessions s (all)", list(&server.session));
            // Per acknowledged op, and how much of the window the owners were busy (not
            // waiting for commands): the largest phase is where the next gain is, and a busy
            // share well under 100% says the owner is not what limits the run.
            let busy: f64 = server
                .owner
                .iter()
                .filter(|(p, _)| p != "wait")
                .map(|(_, s)| s)
                .sum();
            if r.ops_acked > 0 && busy > 0.0 {
                let ops = r.ops_acked as f64;
                let per_op = server
                    .owner
                    .iter()
                    .filter(|(p, _)| p != "wait")
                    .map(|(p, s)| format!("{p} {:.2}", s * 1e6 / ops))
                    .collect::<Vec<_>>()
                    .join("  ");
                row(
                    "server owner µs/op (all)",
                    format!(
                        "{per_op}  (busy {busy:.2} s of {:.2} s: ~{:.0} ops/s if always busy)",
                        r.duration_s,
                        ops / busy
                    ),
                );
            }
        }
        if let Some(p) = &r.presence {
            row(
                "presence",
                format!(
                    "{} sent, seen by others p50 {:.1} ms p99 {:.1} ms ({} samples){}",
                    p.sent,
                    p.latency_ms.p50,
                    p.latency_ms.p99,
                    p.samples,
                    p.bytes_per_client_s
                        .map(|b| format!(", {} per client per s", human_bytes(b as u64)))
                        .unwrap_or_default()
                ),
            );
        }
        if let Some(cpu) = r.server_cpu_cores {
            row("server cpu", format!("{:.0}% of one core", cpu * 100.0));
        }
        if let Some(u) = &r.undo {
            row(
                "undo / redo",
                format!(
                    "{} applied ({:.0}/s), {} refused, {} voxels put back",
                    u.applied, u.per_s, u.refused, u.voxels
                ),
            );
        }
        row(
            "resyncs / rejected / errors",
            format!("{} / {} / {}", r.resyncs, r.rejected, r.errors),
        );
        row(
            "check",
            format!(
                "{}/{} copies equal the server's scene at seq {}",
                d.verified, d.connections, d.final_seq
            ),
        );
        for f in &self.failures {
            let _ = writeln!(t, "  FAILED: {f}");
        }
        t
    }
}

fn human_bytes(n: u64) -> String {
    match n {
        n if n >= 10 << 30 => format!("{:.1} GiB", n as f64 / (1u64 << 30) as f64),
        n if n >= 10 << 20 => format!("{:.1} MiB", n as f64 / (1u64 << 20) as f64),
        n if n >= 10 << 10 => format!("{:.1} KiB", n as f64 / 1024.0),
        n => format!("{n} B"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn server_counters_are_read_from_an_http_answer() {
        let scrape = |voxels: u64, apply: f64, turns: u64| {
            format!(
                "HTTP/1.1 200 OK\r\ncontent-type: text/plain\r\n\r\n\
                 # HELP brickcast_voxels_changed_total x\n\
                 # TYPE brickcast_voxels_changed_total counter\n\
                 brickcast_voxels_changed_total {voxels}\n\
                 brickcast_owner_turns_total {turns}\n\
                 brickcast_owner_seconds_total{{phase=\"apply\"}} {apply}\n\
                 brickcast_owner_seconds_total{{phase=\"commit\"}} 2\n\
                 brickcast_session_seconds_total{{phase=\"decode\"}} 0.5\n\
                 brickcast_scene_seq{{scene=\"demo\"}} 7\n"
            )
        };
        let before = parse_metrics(&scrape(100, 1.5, 10)).unwrap();
        assert_eq!(before["brickcast_voxels_changed_total"], 100.0);
        assert_eq!(before["brickcast_scene_seq{scene=\"demo\"}"], 7.0);
        let after = parse_metrics(&scrape(12_345, 4.0, 30)).unwrap();
        assert_eq!(
            ServerTimes::between(&before, &after),
            ServerTimes {
                voxels_changed: 12_245.0,
                cpu_s: None,
                presence_bytes: 0.0,
                turns: 20.0,
                owner: vec![("apply".into(), 2.5), ("commit".into(), 0.0)],
                session: vec![("decode".into(), 0.0)],
            }
        );
        assert_eq!(
            parse_metrics("HTTP/1.1 404 Not Found\r\n\r\nbrickcast_voxels_changed_total 1\n"),
            None
        );
        assert_eq!(parse_metrics("HTTP/1.1 200 OK\r\n\r\n# nothing\n"), None);
        assert_eq!(parse_metrics("garbage"), None);
    }

    #[test]
    fn bad_urls_are_refused_before_connecting() {
        let args = LoadArgs {
            clients: 1,
            duration: 1.0,
            rate: 0.0,
            batch: 1,
            op: OpKind::Voxel,
            radius: 1.0,
            region: RegionSpec::default(),
            undo_ratio: 0.0,
            presence_hz: 0.0,
            viewers: 0,
            token: None,
            in_place: false,
            json: false,
        };
        for url in [
            "wss://example.com/scenes/demo",
            "ws://127.0.0.1:1/demo",
            "nonsense",
        ] {
            let err = run_blocking(url, &args).expect_err(url);
            assert!(
                matches!(err, LoadError::Link(LinkError::BadUrl(_))),
                "{url}: {err}"
            );
            assert!(
                err.to_string()
                    .contains("expected ws://HOST:PORT/scenes/NAME"),
                "{err}"
            );
        }
        // A well-formed address where nothing listens: a connect error that names it.
        let err = run_blocking("ws://127.0.0.1:9/scenes/demo", &args).expect_err("port 9");
        assert!(
            matches!(err, LoadError::Link(LinkError::Connect { .. })),
            "{err}"
        );
        assert!(err.to_string().contains("127.0.0.1:9"), "{err}");
        // Options are checked before the URL is even looked at.
        let err = run_blocking(
            "ws://127.0.0.1:9/scenes/demo",
            &LoadArgs { clients: 0, ..args },
        )
        .expect_err("no clients");
        assert!(matches!(err, LoadError::Options(OptionError::NoClients)));
    }

    #[test]
    fn sizes_read_well() {
        assert_eq!(human_bytes(999), "999 B");
        assert_eq!(human_bytes(20 << 10), "20.0 KiB");
        assert_eq!(human_bytes(15 << 20), "15.0 MiB");
    }
}
