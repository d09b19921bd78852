//! Durability: kill the server process with SIGKILL while clients edit, restart it, and check
//! that every acknowledged edit is there and that clients resuming across the kill end up with
//! the server's scene. Many rounds, each on the recovered store, with rejected batches and
//! snapshots mixed in; and the exact steps of the sequence bug (a fully rejected batch, then
//! the periodic snapshot, then an edit) as their own test.

mod common;

use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use brickcast_protocol::wire::{EditOp, RayAction, Rejection, ServerMsg};
use common::{Client, colour, http_get};

fn free_port() -> SocketAddr {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap()
}

/// The server process; killed and reaped on drop, so a failing assertion leaves no orphan.
struct ServerProcess(Child);

impl ServerProcess {
    /// SIGKILL, and wait for the process to be gone.
    fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

// The child is returned inside `ServerProcess`, whose Drop waits for it.
#[allow(clippy::zombie_processes)]
async fn start(addr: SocketAddr, data: &std::path::Path, extra: &[&str]) -> ServerProcess {
    let mut child = Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
        .args(["serve", "--listen", &addr.to_string(), "--data"])
        .arg(data)
        .args(extra)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .expect("server starts");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if tokio::net::TcpStream::connect(addr).await.is_ok()
            && http_get(addr, "/healthz").await.0 == 200
        {
            return ServerProcess(child);
        }
        if let Ok(Some(status)) = child.try_wait() {
            panic!("server exited at start: {status}");
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("server did not come up");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Snapshots the server has written since it started (from `/metrics`).
async fn snapshots(addr: SocketAddr) -> u64 {
    let (_, text) = http_get(addr, "/metrics").await;
    text.lines()
        .find_map(|l| l.strip_prefix("brickcast_snapshots_total "))
        .and_then(|v| v.trim().parse().ok())
        .expect("snapshot counter in /metrics")
}

/// A ray from high above the scene pointing up: it hits nothing, so the op is rejected.
fn sky_click() -> EditOp {
    EditOp::Ray {
        origin: [-10.0, 600.0, -10.0],
        dir: [0.0, 1.0, 0.0],
        action: RayAction::Remove,
    }
}

/// The steps that lost an acknowledged edit: a batch whose every op is rejected, then the
/// periodic snapshot, then an acknowledged edit, then SIGKILL. The edit must be there after the
/// restart, and a client that resumes from what it saw must agree with the server.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edit_after_a_rejected_batch_and_a_snapshot_survives_sigkill() {
    let dir = tempfile::tempdir().unwrap();
    let addr = free_port();
    let flags = ["--snapshot-every", "1"];
    let mut server = start(addr, dir.path(), &flags).await;
    let url = format!("ws://{addr}/scenes/demo/ws");
    let mut c = Client::connect(&url, None).await.unwrap();
    c.sync().await;
    let (a, x) = ([3, 500, 3], [4, 500, 4]);
    let Some(ServerMsg::Ack { seq: Some(1), .. }) = Some(
        c.edit(vec![EditOp::Set {
            pos: a,
            colour: colour(1),
        }])
        .await,
    ) else {
        panic!("the first edit is sequence 1");
    };
    match c.edit(vec![sky_click()]).await {
        ServerMsg::Ack {
            seq: None,
            applied: 0,
            rejected,
            ..
        } => assert_eq!(rejected[0].reason, Rejection::RayMissed),
        other => panic!("the sky click must be rejected: {other:?}"),
    }
    // The periodic snapshot (every second while the log has entries).
    let deadline = Instant::now() + Duration::from_secs(30);
    while snapshots(addr).await == 0 {
        assert!(Instant::now() < deadline, "no periodic snapshot");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let ServerMsg::Ack { seq: Some(seq), .. } = c
        .edit(vec![EditOp::Set {
            pos: x,
            colour: colour(2),
        }])
        .await
    else {
        panic!("the edit applies");
    };
    assert_eq!(seq, 2, "a rejected batch takes no sequence number");
    c.catch_up(seq).await;
    let (seen, copy) = (c.seq, c.map.clone());
    server.kill();

    let _server = start(addr, dir.path(), &flags).await;
    let mut fresh = Client::connect(&url, None).await.unwrap();
    fresh.sync().await;
    assert_eq!(
        fresh.map.get(x),
        Some(colour(2)),
        "the acknowledged edit survived"
    );
    assert_eq!(fresh.map.get(a), Some(colour(1)));
    assert_eq!(fresh.seq, 2);
    let mut back = Client::resume(&url, None, Some(seen), Some(copy))
        .await
        .unwrap();
    back.catch_up(fresh.seq).await;
    assert_eq!(back.map.content_hash(), fresh.map.content_hash());
}

/// Unique voxel and colour of edit `i` of client `c` in round `r`: nothing else writes there.
fn op(r: u32, c: u32, i: u32) -> ([u32; 3], brickcast_protocol::Colour) {
    (
        [i % 128, 48 + r * 4 + i / 128, 100 + c],
        colour(r * 100_000 + c * 1000 + i),
    )
}

/// A copy kept by a client that watches the scene until the server dies, to resume from.
struct Watcher {
    seq: u64,
    map: brickcast_protocol::BrickMap,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acknowledged_edits_survive_sigkill() {
    const ROUNDS: u32 = 12;
    const EDITS: u32 = 500;
    let dir = tempfile::tempdir().unwrap();
    let addr = free_port();
    let url = format!("ws://{addr}/scenes/demo/ws");
    // Snapshots every 50 ms while edits come in, so kills land before, during and after them.
    let flags = ["--snapshot-every", "0.05"];
    let mut acked: Vec<([u32; 3], brickcast_protocol::Colour)> = Vec::new();
    let mut watcher: Option<Watcher> = None;
    let mut snapshots_seen = 0;
    // Rounds of edit-then-kill; one more start only checks the last kill's survivors.
    for round in 0..=ROUNDS {
        let mut server = start(addr, dir.path(), &flags).await;
        // Everything acknowledged in earlier rounds survived the previous kill.
        let mut check = Client::connect(&url, None).await.unwrap();
        check.sync().await;
        for (pos, c) in &acked {
            assert_eq!(
                check.map.get(*pos),
                Some(*c),
                "round {round}: acknowledged edit at {pos:?} lost"
            );
        }
        // The copy that watched the last round resumes and converges on the server's scene.
        if let Some(w) = watcher.take() {
            assert!(
                w.seq <= check.seq,
                "round {round}: a client saw sequence {} but the server came back at {}",
                w.seq,
                check.seq
            );
            let mut back = Client::resume(&url, None, Some(w.seq), Some(w.map))
                .await
                .unwrap();
            back.catch_up(check.seq).await;
            assert_eq!(
                back.map.content_hash(),
                check.map.content_hash(),
                "round {round}: the resumed copy differs from the server's scene"
            );
            back.close().await;
        }
        check.close().await;
        if round == ROUNDS {
            break;
        }

        let progress = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        // The watcher syncs before anyone edits: a kill must not land mid-sync (syncs are
        // queued only a little ahead of the writer, so one takes a few owner turns).
        let (synced_tx, synced_rx) = tokio::sync::oneshot::channel();
        let watch = {
            let url = url.clone();
            tokio::spawn(async move {
                let mut w = Client::connect(&url, None).await.unwrap();
                w.sync().await;
                let _ = synced_tx.send(());
                let mut last = None;
                loop {
                    if w.synced {
                        last = Some(Watcher {
                            seq: w.seq,
                            map: w.map.clone(),
                        });
                    }
                    if w.next().await.is_none() {
                        return last;
                    }
                }
            })
        };
        synced_rx.await.expect("the watcher synced");
        let mut tasks = Vec::new();
        for client in 0..3u32 {
            let url = url.clone();
            let progress = progress.clone();
            tasks.push(tokio::spawn(async move {
                let mut c = Client::connect(&url, None).await.unwrap();
                let mut done = Vec::new();
                let mut i = 0;
                let mut batch_no = 0u32;
                'outer: while i < EDITS {
                    batch_no += 1;
                    // Every seventh batch is refused whole, every fifth partly.
                    let (ops, valid): (Vec<EditOp>, Vec<u32>) = if batch_no % 7 == 3 {
                        let oob = EditOp::Set {
                            pos: [9999, 0, 0],
                            colour: colour(0),
                        };
                        (vec![sky_click(), oob], Vec::new())
                    } else {
                        let batch: Vec<u32> = (i..(i + 10).min(EDITS)).collect();
                        i += batch.len() as u32;
                        let mut ops: Vec<EditOp> = batch
                            .iter()
                            .map(|&k| {
                                let (pos, colour) = op(round, client, k);
                                EditOp::Set { pos, colour }
                            })
                            .collect();
                        if batch_no % 5 == 1 {
                            ops.insert(ops.len() / 2, sky_click());
                        }
                        (ops, batch)
                    };
                    let cs = c.send_edit(ops).await;
                    loop {
                        match c.next().await {
                            Some(ServerMsg::Ack {
                                client_seq,
                                seq,
                                applied,
                                ..
                            }) if client_seq == cs => {
                                assert_eq!(applied as usize, valid.len());
                                assert_eq!(seq.is_some(), !valid.is_empty());
                                done.extend(valid.iter().map(|&k| op(round, client, k)));
                                progress
                                    .fetch_add(valid.len(), std::sync::atomic::Ordering::Relaxed);
                                break;
                            }
                            Some(_) => {}
                            None => break 'outer,
                        }
                    }
                }
                done
            }));
        }
        // Kill mid-stream, at a different point each round: once this many edits are
        // acknowledged.
        let kill_at = 40 + 97 * round as usize;
        let deadline = Instant::now() + Duration::from_secs(60);
        while progress.load(std::sync::atomic::Ordering::Relaxed) < kill_at {
            assert!(
                Instant::now() < deadline,
                "round {round}: clients made no progress"
            );
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        snapshots_seen += snapshots(addr).await;
        server.kill();
        let mut this_round = 0;
        for t in tasks {
            let done = t.await.unwrap();
            this_round += done.len();
            acked.extend(done);
        }
        watcher = watch.await.unwrap();
        assert!(watcher.is_some(), "round {round}: the watcher synced");
        eprintln!(
            "round {round}: {this_round} of {} edits acknowledged before SIGKILL",
            3 * EDITS
        );
        assert!(
            this_round >= kill_at && this_round < 3 * EDITS as usize,
            "round {round}: the kill came mid-stream"
        );
    }
    eprintln!("{snapshots_seen} snapshots were written during the rounds");
    assert!(snapshots_seen > 0, "snapshots were mixed in");
}

/// Undo history is as durable as the edits it undoes: steps made, undone and redone before a
/// SIGKILL are all still there after the restart, with snapshots taken in between (they never
/// trim history).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn undo_history_survives_sigkill() {
    let dir = tempfile::tempdir().unwrap();
    let addr = free_port();
    let url = format!("ws://{addr}/scenes/demo/ws");
    let flags = ["--snapshot-every", "0.05"];
    let alice = 0xa11ce;
    let undone = |reply: &ServerMsg| match reply {
        ServerMsg::Undone {
            seq: Some(seq),
            refused: None,
            restored,
            ..
        } => (*seq, *restored),
        other => panic!("the undo applies: {other:?}"),
    };

    let mut server = start(addr, dir.path(), &flags).await;
    let mut a = Client::as_user(&url, None, alice, "alice").await.unwrap();
    a.sync().await;
    let empty = a.map.content_hash();
    let mut hashes = vec![empty];
    for i in 0..4u32 {
        let ServerMsg::Ack { seq: Some(seq), .. } = a
            .edit(vec![EditOp::Sphere {
                centre: [20.0 + 25.0 * i as f32, 40.0, 64.0],
                radius: 9.0,
                mode: brickcast_protocol::BrushMode::Fill,
                colour: colour(i),
            }])
            .await
        else {
            panic!("the sphere applies");
        };
        a.catch_up(seq).await;
        hashes.push(a.map.content_hash());
    }
    // Undo the last step and let snapshots happen (every 50 ms while the log has entries), then
    // SIGKILL.
    let before = snapshots(addr).await;
    let (seq, _) = undone(&a.undo(false).await);
    a.catch_up(seq).await;
    assert_eq!(a.map.content_hash(), hashes[3]);
    // An idle owner looks at the snapshot clock at least once a second.
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let deadline = Instant::now() + Duration::from_secs(30);
    while snapshots(addr).await <= before {
        assert!(Instant::now() < deadline, "no snapshot around the undo");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    server.kill();

    let mut server = start(addr, dir.path(), &flags).await;
    let mut a = Client::as_user(&url, None, alice, "alice").await.unwrap();
    a.sync().await;
    assert_eq!(a.map.content_hash(), hashes[3], "the scene after the undo");
    // The redo stack survived: redo, then undo everything back to the empty scene.
    let (seq, restored) = undone(&a.undo(true).await);
    assert!(restored > 1000);
    a.catch_up(seq).await;
    assert_eq!(a.map.content_hash(), hashes[4]);
    server.kill();

    let _server = start(addr, dir.path(), &flags).await;
    let mut a = Client::as_user(&url, None, alice, "alice").await.unwrap();
    a.sync().await;
    assert_eq!(a.map.content_hash(), hashes[4]);
    for step in (0..4).rev() {
        let (seq, _) = undone(&a.undo(false).await);
        a.catch_up(seq).await;
        assert_eq!(
            a.map.content_hash(),
            hashes[step],
            "undo down to step {step}"
        );
    }
    match a.undo(false).await {
        ServerMsg::Undone {
            refused: Some(brickcast_protocol::wire::Refusal::NothingToUndo),
            ..
        } => {}
        other => panic!("{other:?}"),
    }
}
