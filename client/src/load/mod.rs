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
pub mod histogram;
pub mod observe;
pub mod ops;
pub mod options;
pub mod worker;

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
    /// Clients that failed (connection, protocol, unacknowledged batches) plus copies that did
    /// not match the server's: any error makes the run fail.
    pub errors: u64,
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
    args.check()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(LoadError::Runtime)?;
    runtime.block_on(run(url, args))
}

/// Runs a load test against the scene at `url`.
pub async fn run(url: &str, args: &LoadArgs) -> Result<LoadOutcome, LoadError> {
    args.check()?;
    let url = link::websocket_url(url)?;
    let probe = Link::connect(&url, "brickcast load probe", args.token.as_deref(), None).await?;
    let welcome = probe.welcome.clone();
    probe.close().await;
    if welcome.role != Role::Editor {
        return Err(LoadError::NotEditor(welcome.role));
    }
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
            interval: pace.interval,
            observer: (connections > 1).then_some((index + 1) % connections),
        });
        let plan = ClientPlan {
            index,
            url: url.clone(),
            token: args.token.clone(),
            editor,
            // The observer of editor 0 also counts the voxels it sees change.
            count_voxels: index == 1 % connections,
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
            () = tokio::time::sleep(Duration::from_secs(1)) => {
                progress.line(&format!("connecting and syncing: {ready}/{connections} clients ready"));
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

    let voxels_before = server_voxels_changed(&url).await;
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
    let voxels_after = server_voxels_changed(&url).await;
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
    for i in 0..connections {
        let log = shared.observer(i);
        latency.merge(&log.latency);
        unseen += log.unseen + log.still_waiting() as u64;
    }
    let mut failures = Vec::new();
    let (mut ops_acked, mut rejected, mut resyncs, mut voxels_seen) = (0, 0, 0, 0);
    let (mut editor_bytes, mut viewer_bytes) = ((0, 0), (0, 0));
    let mut verified = 0;
    for r in &reports {
        ack.merge(&r.ack_latency);
        ops_acked += r.ops_acked;
        rejected += r.rejected;
        resyncs += r.resyncs;
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
    let voxels_applied_per_s = match (voxels_before, voxels_after) {
        (Some(a), Some(b)) => Some(b.saturating_sub(a) as f64 / duration_s),
        _ => None,
    };
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
        errors: failures.len() as u64,
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
    };
    Ok(LoadOutcome {
        report,
        details,
        failures,
    })
}

/// A full copy of the scene as a new client gets it.
async fn fetch(url: &str, token: Option<&str>) -> Result<Replica, LoadError> {
    let mut link = Link::connect(url, "brickcast load check", token, None)
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

/// The server's `brickcast_voxels_changed_total`, read from `/metrics` on the scene's host;
/// `None` when that does not answer (a proxy may expose only the websocket).
async fn server_voxels_changed(ws_url: &str) -> Option<u64> {
    let host = ws_url.strip_prefix("ws://")?.split('/').next()?.to_string();
    let get = async {
        let mut stream = tokio::net::TcpStream::connect(&host).await.ok()?;
        let request = format!("GET /metrics HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n");
        stream.write_all(request.as_bytes()).await.ok()?;
        let mut body = Vec::new();
        stream.take(4 << 20).read_to_end(&mut body).await.ok()?;
        parse_voxels_changed(&String::from_utf8_lossy(&body))
    };
    tokio::time::timeout(Duration::from_secs(5), get)
        .await
        .ok()
        .flatten()
}

/// The counter's value in an HTTP response carrying Prometheus text.
fn parse_voxels_changed(response: &str) -> Option<u64> {
    let (head, body) = response.split_once("\r\n\r\n")?;
    if !head.starts_with("HTTP/1.1 200") {
        return None;
    }
    body.lines()
        .find_map(|l| l.strip_prefix("brickcast_voxels_changed_total "))
        .and_then(|v| v.trim().parse().ok())
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
                    "{v:.0} applied by the server, {:.0} seen by one client",
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
    fn metrics_counter_is_read_from_an_http_answer() {
        let ok = "HTTP/1.1 200 OK\r\ncontent-type: text/plain\r\n\r\n# HELP brickcast_voxels_changed_total x\n# TYPE brickcast_voxels_changed_total counter\nbrickcast_voxels_changed_total 12345\nbrickcast_deltas_sent_total 9\n";
        assert_eq!(parse_voxels_changed(ok), Some(12345));
        assert_eq!(
            parse_voxels_changed(
                "HTTP/1.1 404 Not Found\r\n\r\nbrickcast_voxels_changed_total 1\n"
            ),
            None
        );
        assert_eq!(
            parse_voxels_changed("HTTP/1.1 200 OK\r\n\r\nnothing\n"),
            None
        );
        assert_eq!(parse_voxels_changed("garbage"), None);
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
            viewers: 0,
            token: None,
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
