//! The cluster, end to end: a real `nats-server` with JetStream on a free loopback port and
//! several `brickcast-server serve --nats` processes, driven by raw-protocol clients.
//!
//! * clients on three nodes edit one scene; every client's copy and every node's scene hash
//!   equal;
//! * SIGKILL of the owner under load: nothing acknowledged is lost, a new owner acknowledges
//!   within the failover target, every node converges;
//! * SIGSTOP of the owner past its lease, a takeover, SIGCONT: its append is refused, it steps
//!   down, no edit is applied twice or lost;
//! * SIGKILL and restart of `nats-server` under load: nothing acknowledged is lost;
//! * a node joining late syncs from the snapshot and the rest of the log;
//! * people on different nodes see each other (presence), and a dead node's people go;
//! * bad input: an unreachable NATS, one without JetStream, a node name in use, a corrupt log
//!   message.

mod common;
mod nodes;

use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::time::{Duration, Instant};

use brickcast_protocol::wire::{ClientMsg, Cursor, EditOp, ServerMsg, View};
use common::{Client, colour, http_get};
use nodes::*;

/// The first scene sequence a node other than `old` ordered: the first record after the
/// last lease marker (a turn without records) of another node, read from the log stream.
async fn first_seq_after_takeover(nats: &str, old: &str) -> u64 {
    let client = async_nats::connect(nats).await.unwrap();
    let js = async_nats::jetstream::new(client);
    let stream = js
        .get_stream(brickcast_server::cluster::log::stream_name("demo"))
        .await
        .unwrap();
    let info = stream.get_info().await.unwrap();
    let mut marker_seen = false;
    let mut first = None;
    for pos in info.state.first_sequence..=info.state.last_sequence {
        let msg = stream.get_raw_message(pos).await.unwrap();
        let turn = brickcast_server::cluster::log::decode_turn(&msg.payload).unwrap();
        if turn.is_marker() && turn.node != old {
            marker_seen = true;
            first = None;
        } else if marker_seen && first.is_none() && turn.node != old {
            first = turn.records.first().map(|r| r.0);
        }
    }
    first.expect("the new owner ordered edits")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn clients_on_three_nodes_edit_one_scene_and_every_copy_agrees() {
    let nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    let c = Node::start(&nats.url(), "c", &[]).await;
    let nodes = [&a, &b, &c];
    owner_of(&nodes, Duration::from_secs(20)).await;
    // Two writers per node, and a watcher per node that must end with the same scene.
    let mut watchers = Vec::new();
    for n in &nodes {
        let mut w = Client::connect(&n.url(), None).await.unwrap();
        w.sync().await;
        watchers.push(w);
    }
    let urls: Vec<String> = nodes.iter().flat_map(|n| [n.url(), n.url()]).collect();
    let acked = run_writers(&urls, Duration::from_secs(4)).await;
    assert!(acked.iter().all(|a| !a.closed && !a.voxels.is_empty()));
    let seq = last_seq(&acked);
    let mut hashes = Vec::new();
    for w in &mut watchers {
        w.catch_up(seq).await;
        assert_has_all(w, &acked, "watcher");
        hashes.push(w.map.content_hash());
    }
    assert!(hashes.windows(2).all(|h| h[0] == h[1]), "{hashes:?}");
    assert_converged(&nodes, &acked, "after editing on three nodes").await;
    // Every acked edit took its own sequence number: none was applied twice.
    let seqs: std::collections::BTreeSet<u64> = acked
        .iter()
        .flat_map(|a| a.voxels.values().map(|v| v.1))
        .collect();
    let count: usize = acked.iter().map(|a| a.voxels.len()).sum();
    assert_eq!(seqs.len(), count, "two acks named one sequence");
    // `cluster status` sees the three nodes and the owner.
    let out = Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
        .args(["cluster", "status", "--nats", &nats.url()])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("nodes (3)"), "{text}");
    assert!(
        text.lines()
            .any(|l| l.contains("demo")
                && (l.contains(" a ") || l.contains(" b ") || l.contains(" c "))),
        "{text}"
    );
    // ... and, asked with --json, where each node's copy stands: every node at the last
    // sequence with the watchers' hash, one of them the owner.
    let out = Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
        .args(["cluster", "status", "--json", "--nats", &nats.url()])
        .output()
        .unwrap();
    let status: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let replicas: Vec<&serde_json::Value> = status["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| {
            n["scenes"]
                .as_array()
                .and_then(|s| s.iter().find(|r| r["scene"] == "demo"))
                .unwrap_or_else(|| panic!("node {} did not describe demo: {status}", n["name"]))
        })
        .collect();
    assert_eq!(replicas.len(), 3, "{status}");
    for r in &replicas {
        assert_eq!(r["seq"], seq, "{status}");
        assert_eq!(r["hash"], hashes[0], "{status}");
    }
    assert_eq!(
        replicas.iter().filter(|r| r["leading"] == true).count(),
        1,
        "{status}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sigkill_of_the_owner_under_load_loses_no_acknowledged_edit() {
    let nats = Nats::start(true);
    let mut nodes = [
        Node::start(&nats.url(), "a", &[]).await,
        Node::start(&nats.url(), "b", &[]).await,
        Node::start(&nats.url(), "c", &[]).await,
    ];
    let owner = owner_of(&nodes.iter().collect::<Vec<_>>(), Duration::from_secs(20)).await;
    let others: Vec<usize> = (0..3).filter(|&i| i != owner).collect();
    // Writers on the two other nodes keep editing through the kill; one on the owner's node
    // loses its connection with it.
    let stop = Arc::new(AtomicBool::new(false));
    let mut tasks = Vec::new();
    for (w, i) in [others[0], others[1], owner].into_iter().enumerate() {
        tasks.push(tokio::spawn(writer(nodes[i].url(), w as u32, stop.clone())));
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    let killed_at = Instant::now();
    nodes[owner].kill();
    tokio::time::sleep(Duration::from_secs(8)).await;
    stop.store(true, Relaxed);
    let mut acked = Vec::new();
    for t in tasks {
        acked.push(t.await.unwrap());
    }
    assert!(acked[2].closed, "the owner's own client lost its node");
    assert!(
        !acked[0].closed && !acked[1].closed,
        "clients of the other nodes keep their connections"
    );
    // Failover: from the kill to the ack of the first edit the new owner ordered (the first
    // record after its lease marker in the log).
    let first = first_seq_after_takeover(&nats.url(), &nodes[owner].name).await;
    let acked_at = acked
        .iter()
        .flat_map(|a| a.ack_times.iter())
        .find(|(_, s)| *s == first)
        .map(|(t, _)| *t)
        .expect("the new owner's first edit was acknowledged to a writer");
    let failover = acked_at - killed_at;
    eprintln!("failover: {failover:?} (first sequence of the new owner: {first})");
    assert!(
        failover <= Duration::from_secs(5),
        "failover took {failover:?}"
    );
    let survivors: Vec<&Node> = others.iter().map(|&i| &nodes[i]).collect();
    assert!(
        survivors
            .iter()
            .any(|n| n.log_text().contains("this node owns the scene"))
    );
    assert_converged(&survivors, &acked, "after the owner was killed").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_owner_stopped_past_its_lease_is_fenced_and_steps_down() {
    let nats = Nats::start(true);
    let nodes = [
        Node::start(&nats.url(), "a", &[]).await,
        Node::start(&nats.url(), "b", &[]).await,
    ];
    let refs: Vec<&Node> = nodes.iter().collect();
    let owner = owner_of(&refs, Duration::from_secs(20)).await;
    let other = 1 - owner;
    // A client on each node; the one on the owner's node has an edit waiting when it stops.
    let mut on_owner = Client::connect(&nodes[owner].url(), None).await.unwrap();
    on_owner.sync().await;
    let mut on_other = Client::connect(&nodes[other].url(), None).await.unwrap();
    on_other.sync().await;
    let s1 = set(&mut on_other, spot(0, 0), 1).await;
    nodes[owner].stop();
    // The edit sits in the stopped node's socket buffer.
    let waiting = on_owner
        .send_edit(vec![EditOp::Set {
            pos: spot(1, 0),
            colour: colour(2),
        }])
        .await;
    // The other node takes the lease once it expires, and acknowledges edits.
    let deadline = Instant::now() + Duration::from_secs(20);
    while !nodes[other].owns().await {
        assert!(
            Instant::now() < deadline,
            "the other node did not take over"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let s2 = set(&mut on_other, spot(0, 1), 3).await;
    assert!(s2 > s1);
    nodes[owner].cont();
    // The woken node must not append: its edit is refused there and retried on the new
    // owner, which acknowledges it once.
    let ServerMsg::Ack { seq: Some(s3), .. } = on_owner.ack(waiting).await else {
        panic!("the waiting edit is acknowledged");
    };
    assert!(s3 > s2, "the waiting edit was ordered after the takeover");
    let deadline = Instant::now() + Duration::from_secs(10);
    while nodes[owner].owns().await {
        assert!(
            Instant::now() < deadline,
            "the woken node still claims the scene"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let text = nodes[owner].log_text();
    assert!(
        text.contains("no longer the scene's owner")
            || text.contains("no longer owns the scene")
            || text.contains("stops ordering edits"),
        "{text}"
    );
    let s4 = set(&mut on_other, spot(0, 2), 4).await;
    // Four edits, four sequence numbers: nothing applied twice, nothing lost.
    assert_eq!([s1, s2, s3, s4].len(), 4);
    assert_eq!(
        s4,
        s1 + 3,
        "sequences {s1} {s2} {s3} {s4}: an edit was applied twice or lost"
    );
    for n in &nodes {
        let c = copy_at(n, s4).await;
        for (pos, col) in [
            (spot(0, 0), 1),
            (spot(1, 0), 2),
            (spot(0, 1), 3),
            (spot(0, 2), 4),
        ] {
            assert_eq!(c.map.get(pos), Some(colour(col)), "node {}", n.name);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_nats_restart_under_load_loses_no_acknowledged_edit() {
    let mut nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    owner_of(&[&a, &b], Duration::from_secs(20)).await;
    let stop = Arc::new(AtomicBool::new(false));
    let tasks: Vec<_> = [a.url(), b.url()]
        .into_iter()
        .enumerate()
        .map(|(w, u)| tokio::spawn(writer(u, w as u32, stop.clone())))
        .collect();
    tokio::time::sleep(Duration::from_secs(2)).await;
    nats.kill();
    tokio::time::sleep(Duration::from_secs(1)).await;
    nats.spawn();
    tokio::time::sleep(Duration::from_secs(8)).await;
    stop.store(true, Relaxed);
    let mut acked = Vec::new();
    for t in tasks {
        acked.push(t.await.unwrap());
    }
    let after: usize = acked.iter().map(|a| a.voxels.len()).sum();
    assert!(after > 0);
    assert_converged(&[&a, &b], &acked, "after a NATS restart").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_node_joining_late_syncs_from_the_snapshot_and_the_log() {
    let nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &["--snapshot-every", "1"]).await;
    owner_of(&[&a], Duration::from_secs(20)).await;
    let first = run_writers(&[a.url()], Duration::from_secs(2)).await;
    // A snapshot trims the log below it.
    let deadline = Instant::now() + Duration::from_secs(20);
    while a.metric("snapshots_total").await == 0 {
        assert!(Instant::now() < deadline, "no snapshot");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut more = run_writers(&[a.url()], Duration::from_secs(1)).await;
    let late = Node::start(&nats.url(), "late", &[]).await;
    let text = late.log_text();
    assert!(text.contains("scene loaded from the cluster"), "{text}");
    let mut acked = first;
    acked.append(&mut more);
    assert_converged(&[&a, &late], &acked, "a late node").await;
}

/// The node exits with a failure, and its log says `why`.
fn assert_refused(node: &mut Node, why: &str) {
    let status = node.wait_exit(Duration::from_secs(30));
    assert!(status.is_some_and(|s| !s.success()), "{status:?}");
    let text = node.log_text();
    assert!(text.contains(why), "{text}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_clusters_are_clear_errors() {
    // Nobody listens.
    let mut n = Node::spawn(&format!("nats://127.0.0.1:{}", free_port()), "x", &[]);
    assert_refused(&mut n, "cannot reach NATS");
    // NATS without JetStream.
    let plain = Nats::start(false);
    let mut n = Node::spawn(&plain.url(), "x", &[]);
    assert_refused(&mut n, "has no JetStream");
    // A node name in use.
    let nats = Nats::start(true);
    let first = Node::start(&nats.url(), "same", &[]).await;
    let mut second = Node::spawn(&nats.url(), "same", &[]);
    assert_refused(&mut second, "already in use");
    // A corrupt message in the log: refused loudly, never applied.
    let client = async_nats::connect(nats.url()).await.unwrap();
    let js = async_nats::jetstream::new(client);
    js.publish("brickcast.log.demo", "not a turn".into())
        .await
        .unwrap()
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while !first.log_text().contains("cannot read") {
        assert!(Instant::now() < deadline, "{}", first.log_text());
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A scene imported with `import --nats` into a running cluster is served by every node,
/// voxel for voxel; a second import of the name is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_scene_imported_into_a_running_cluster_is_served_by_every_node() {
    use brickcast_protocol::{BrickMap, BrushMode};
    let nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    let models = tempfile::tempdir().unwrap();
    let mut map = BrickMap::new([40, 24, 40]).unwrap();
    map.fill_box([0, 0, 0], [39, 1, 39], BrushMode::Fill, colour(7));
    map.sphere([20.0, 10.0, 20.0], 6.0, BrushMode::Fill, colour(8));
    let (bytes, _) = brickcast_server::import::vox::export_vox(&map);
    let model = models.path().join("m.vox");
    // What the import makes of it: these voxels, and the model's colours as the palette.
    let want = brickcast_server::import::vox::import_vox(&bytes, &model).unwrap();
    assert_eq!(want.bricks().count(), map.bricks().count());
    std::fs::write(&model, bytes).unwrap();
    let import = |extra: &'static [&'static str]| {
        let model = model.clone();
        let url = nats.url();
        tokio::task::spawn_blocking(move || {
            Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
                .arg("import")
                .arg(&model)
                .args(["--scene", "imported.one", "--nats", &url, "--quiet"])
                .args(extra)
                .env("RUST_LOG", "warn")
                .output()
                .unwrap()
        })
    };
    let out = import(&[]).await.unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for n in [&a, &b] {
        let url = format!("ws://{}/scenes/imported.one/ws", n.addr);
        let deadline = Instant::now() + Duration::from_secs(20);
        while !http_get(n.addr, "/scenes").await.1.contains("imported.one") {
            assert!(
                Instant::now() < deadline,
                "node {} does not serve it",
                n.name
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let mut c = Client::connect(&url, None).await.unwrap();
        c.sync().await;
        assert_eq!(c.map.content_hash(), want.content_hash(), "node {}", n.name);
        assert_eq!(c.map.swatches().get(0), colour(7), "node {}", n.name);
    }
    let again = import(&[]).await.unwrap();
    assert!(!again.status.success());
    assert!(
        String::from_utf8_lossy(&again.stderr).contains("already exists"),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
}

/// A log with a gap (messages gone that no snapshot holds) is refused with an error naming
/// the missing messages: a node does not serve a scene that lost acknowledged edits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_log_with_a_gap_is_refused() {
    let nats = Nats::start(true);
    let mut first = Node::start(&nats.url(), "first", &[]).await;
    owner_of(&[&first], Duration::from_secs(20)).await;
    let mut c = Client::connect(&first.url(), None).await.unwrap();
    c.sync().await;
    for k in 0..3 {
        set(&mut c, spot(0, k), k).await;
    }
    first.kill();
    let client = async_nats::connect(nats.url()).await.unwrap();
    let js = async_nats::jetstream::new(client);
    let stream = js
        .get_stream(brickcast_server::cluster::log::stream_name("demo"))
        .await
        .unwrap();
    let last = stream.get_info().await.unwrap().state.last_sequence;
    // Drop everything before the last message: no snapshot covers it.
    stream.purge().sequence(last).await.unwrap();
    // The node runs, but does not serve the scene: a client is told why, and so is the log.
    let late = Node::start_bare(&nats.url(), "late", &[]).await;
    match tokio_tungstenite::connect_async(late.url()).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(response)) => {
            assert_eq!(response.status(), 503);
            let body = String::from_utf8_lossy(response.body().as_deref().unwrap_or_default());
            assert!(body.contains("are missing"), "{body}");
        }
        other => panic!(
            "a scene with a gap in its log was served: {:?}",
            other.map(|_| ())
        ),
    }
    let text = late.log_text();
    assert!(text.contains("are missing"), "{text}");
    assert!(!late.serves().await);
}

/// Undo and redo travel to the owner like edits, and the history moves with the scene: after
/// the owner is killed, the node that takes over undoes where the old owner left off.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn undo_goes_through_any_node_and_survives_a_failover() {
    let nats = Nats::start(true);
    let mut nodes = [
        Node::start(&nats.url(), "a", &[]).await,
        Node::start(&nats.url(), "b", &[]).await,
    ];
    let owner = owner_of(&nodes.iter().collect::<Vec<_>>(), Duration::from_secs(20)).await;
    let other = 1 - owner;
    let mut c = Client::as_user(&nodes[other].url(), None, 0x5eed, "sam")
        .await
        .unwrap();
    c.sync().await;
    for (k, col) in [(0, 1), (1, 2)] {
        set(&mut c, spot(0, k), col).await;
    }
    let undone = |reply: ServerMsg| match reply {
        ServerMsg::Undone {
            seq: Some(seq),
            restored: 1,
            refused: None,
            ..
        } => seq,
        other => panic!("{other:?}"),
    };
    // Undo the second edit through the node that does not own the scene.
    let s = undone(c.undo(false).await);
    c.catch_up(s).await;
    assert_eq!(c.map.get(spot(0, 1)), None);
    // A swatch of the shared palette set through the same node: no undo step, and it survives
    // the failover with the scene.
    let swatch = brickcast_protocol::wire::EditOp::Swatch {
        index: 7,
        colour: colour(3),
    };
    let set = match c.edit(vec![swatch]).await {
        ServerMsg::Ack { seq: Some(s), .. } => s,
        other => panic!("{other:?}"),
    };
    c.catch_up(set).await;
    assert_eq!(c.map.swatches().get(7), colour(3));
    nodes[owner].kill();
    // The client's node takes the scene over; the history came with the log.
    let s = undone(c.undo(false).await);
    c.catch_up(s).await;
    assert_eq!(c.map.get(spot(0, 0)), None, "the first edit is undone too");
    let s = undone(c.undo(true).await);
    c.catch_up(s).await;
    assert_eq!(c.map.get(spot(0, 0)), Some(colour(1)), "and redone");
    assert!(nodes[other].owns().await);
    let mut late = Client::connect(&nodes[other].url(), None).await.unwrap();
    late.sync().await;
    assert_eq!(
        late.map.swatches().get(7),
        colour(3),
        "the palette came with the log"
    );
}

/// Whether `c`'s roster shows someone named `name`.
fn sees(c: &Client, name: &str) -> bool {
    c.roster.others.values().any(|p| p.peer.name == name)
}

/// Reads `c` until `check` holds, within `within`.
async fn wait_for(c: &mut Client, within: Duration, check: impl Fn(&Client) -> bool) -> bool {
    if check(c) {
        return true;
    }
    tokio::time::timeout(within, c.until(|c, _| check(c)))
        .await
        .unwrap_or(false)
}

/// People connected to different nodes see each other: who is here, where they look and point,
/// renames and leaves. When a node dies, its people leave everyone else's roster.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn people_on_different_nodes_see_each_other() {
    let nats = Nats::start(true);
    let mut nodes = [
        Node::start(&nats.url(), "a", &[]).await,
        Node::start(&nats.url(), "b", &[]).await,
    ];
    let within = Duration::from_secs(15);
    let mut alice = Client::as_user(&nodes[0].url(), None, 0xa11ce, "alice")
        .await
        .unwrap();
    alice.sync().await;
    let mut bob = Client::as_user(&nodes[1].url(), None, 0xb0b, "bob")
        .await
        .unwrap();
    bob.sync().await;
    assert!(wait_for(&mut bob, within, |c| sees(c, "alice")).await);
    assert!(wait_for(&mut alice, within, |c| sees(c, "bob")).await);

    // A client arriving later is told about both in its Welcome.
    let mut dan = Client::as_user(&nodes[1].url(), None, 0xda, "dan")
        .await
        .unwrap();
    assert!(sees(&dan, "alice") && sees(&dan, "bob"), "{:?}", dan.roster);
    dan.sync().await;

    let view = View {
        eye: [64.0, 80.0, -20.0],
        forward: [0.0, -0.5, 1.0],
    };
    let cursor = Cursor {
        voxel: [64, 20, 64],
        radius: 3.0,
    };
    alice
        .send(&ClientMsg::Presence {
            view: Some(view),
            cursor: Some(cursor),
            selection: None,
        })
        .await;
    let looks = |c: &Client| {
        c.roster.others.values().any(|p| {
            p.peer.name == "alice" && p.state.view == Some(view) && p.state.cursor == Some(cursor)
        })
    };
    assert!(wait_for(&mut bob, within, looks).await, "{:?}", bob.roster);
    alice
        .send(&ClientMsg::Rename {
            name: "Alice".into(),
        })
        .await;
    assert!(wait_for(&mut bob, within, |c| sees(c, "Alice") && !sees(c, "alice")).await);
    // The scene list of a node shows people on the other nodes too.
    let (_, page) = http_get(nodes[1].addr, "/").await;
    assert!(page.contains("Alice"), "{page}");

    alice.close().await;
    assert!(wait_for(&mut bob, within, |c| !sees(c, "Alice")).await);

    // A node dies: its people go from the others' rosters once it has been silent a while.
    let mut carol = Client::as_user(&nodes[0].url(), None, 0xca201, "carol")
        .await
        .unwrap();
    carol.sync().await;
    assert!(wait_for(&mut bob, within, |c| sees(c, "carol")).await);
    nodes[0].kill();
    let killed = Instant::now();
    assert!(wait_for(&mut bob, within, |c| !sees(c, "carol")).await);
    let gone = killed.elapsed();
    assert!(gone < Duration::from_secs(8), "carol stayed {gone:?}");
    assert!(sees(&bob, "dan"), "people on the surviving node stay");
    let relayed = nodes[1].metric("cluster_presence_relayed_total").await;
    assert!(relayed > 0, "node b published no presence");
    assert_eq!(nodes[1].metric("cluster_presence_refused_total").await, 0);
}

/// Waits until `check` holds for `node`, or panics saying `what`.
async fn until_node(node: &Node, within: Duration, what: &str, check: impl AsyncFn(&Node) -> bool) {
    let deadline = Instant::now() + within;
    while !check(node).await {
        assert!(
            Instant::now() < deadline,
            "node {}: {what}\n{}",
            node.name,
            node.log_text()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A node serves a scene while people on it use it: it opens the scene for the first client,
/// closes it once nobody there used it for `--close-idle`, and a lease it held goes at once to
/// a node that still has people on the scene. Nothing edited is lost across closes and opens.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn scenes_open_where_people_are_and_close_behind_them() {
    let nats = Nats::start(true);
    let idle = ["--close-idle", "1"];
    let a = Node::start_bare(&nats.url(), "a", &idle).await;
    let b = Node::start_bare(&nats.url(), "b", &idle).await;
    // A third node serves the scene too, but without clients (it drew its picture).
    let c = Node::start_bare(&nats.url(), "c", &[]).await;
    let within = Duration::from_secs(20);
    // Listed, but served by nobody yet.
    for n in [&a, &b] {
        let entry = n.demo_entry().await;
        assert_eq!(entry["open"], false, "{entry}");
        assert_eq!(n.metric("scenes_open").await, 0);
    }
    let (status, _) = http_get(a.addr, "/scenes/nothing-here/ws").await;
    assert_eq!(status, 404);
    // The scene list and the viewer page know it without opening it.
    let (status, page) = http_get(a.addr, "/").await;
    assert_eq!(status, 200);
    assert!(page.contains("it opens when you join"), "{page}");
    assert_eq!(http_get(a.addr, "/scenes/demo").await.0, 200);
    assert_eq!(http_get(a.addr, "/scenes/nothing-here").await.0, 404);
    assert!(!a.serves().await);

    // The first client opens it on a, and a takes the lease.
    let mut on_a = Client::connect(&a.url(), None).await.unwrap();
    on_a.sync().await;
    until_node(&a, within, "a does not lead", async |n| n.owns().await).await;
    assert_eq!(http_get(c.addr, "/scenes/demo/thumb.png").await.0, 200);
    assert!(c.serves().await);
    assert!(!b.serves().await);
    let mut on_b = Client::connect(&b.url(), None).await.unwrap();
    on_b.sync().await;
    assert!(b.serves().await);
    let first = set(&mut on_b, spot(0, 0), 1).await;

    // a's client leaves: a closes the scene and b, where people are, leads it.
    on_a.close().await;
    until_node(&a, within, "a still serves the scene", async |n| {
        !n.serves().await
    })
    .await;
    until_node(&a, within, "a did not count the close", async |n| {
        n.metric("cluster_scene_closes_total").await == 1
    })
    .await;
    until_node(&b, within, "b did not take the lease over", async |n| {
        n.owns().await
    })
    .await;
    let second = set(&mut on_b, spot(0, 1), 2).await;
    assert!(second > first);
    // The node without clients left the lease to the ones with people.
    assert_eq!(c.metric("cluster_takeovers_total").await, 0);
    drop(c);
    // b keeps the scene while its client stays, idle or not.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    assert!(b.serves().await);

    // Everyone leaves: nobody serves it; the next client opens it again with every edit.
    on_b.close().await;
    until_node(&b, within, "b still serves the scene", async |n| {
        !n.serves().await
    })
    .await;
    let mut back = Client::connect(&a.url(), None).await.unwrap();
    back.sync().await;
    assert_eq!(back.map.get(spot(0, 0)), Some(colour(1)));
    assert_eq!(back.map.get(spot(0, 1)), Some(colour(2)));
    until_node(&a, within, "a does not lead again", async |n| {
        n.owns().await
    })
    .await;
    assert!(set(&mut back, spot(0, 2), 3).await > second);
    assert_eq!(a.metric("cluster_scene_opens_total").await, 2);
}

/// Snapshots after the first are deltas of the bricks and history changed since: a node that
/// loads the scene from a base, its deltas and the log has every voxel and every undo step.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_scene_loads_from_a_base_and_its_deltas_with_its_history() {
    let nats = Nats::start(true);
    let mut a = Node::start(&nats.url(), "a", &["--snapshot-every", "0.2"]).await;
    owner_of(&[&a], Duration::from_secs(20)).await;
    let mut c = Client::as_user(&a.url(), None, 0x5eed, "sam")
        .await
        .unwrap();
    c.sync().await;
    // After each change, wait for a snapshot holding it: a base, then deltas.
    let mut snapshots = a.metric("snapshots_total").await;
    let mut snapshot_after = async |a: &Node| {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let now = a.metric("snapshots_total").await;
            if now > snapshots {
                snapshots = now;
                return;
            }
            assert!(Instant::now() < deadline, "no snapshot");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    };
    set(&mut c, spot(0, 0), 1).await;
    snapshot_after(&a).await;
    set(&mut c, spot(0, 1), 2).await;
    snapshot_after(&a).await;
    match c.undo(false).await {
        ServerMsg::Undone { seq: Some(s), .. } => c.catch_up(s).await,
        other => panic!("{other:?}"),
    }
    snapshot_after(&a).await;
    c.close().await;
    let client = async_nats::connect(nats.url()).await.unwrap();
    let js = async_nats::jetstream::new(client);
    let store = js.get_object_store("brickcast_snapshots").await.unwrap();
    let heads = js.get_key_value("brickcast_snapshot_heads").await.unwrap();
    // The uploads finish after the counter moves; the head names the chain once they have.
    let deadline = Instant::now() + Duration::from_secs(20);
    let head = loop {
        let head: Option<serde_json::Value> = heads
            .get("demo")
            .await
            .unwrap()
            .map(|v| serde_json::from_slice(&v).unwrap());
        if let Some(head) = head.filter(|h| h["deltas"].as_u64() >= Some(2)) {
            break head;
        }
        assert!(Instant::now() < deadline, "no second delta was written");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let id = head["base"].as_u64().unwrap();
    use brickcast_server::cluster::snapshot::{base_name, delta_name};
    let base = store.info(base_name("demo", id)).await.unwrap().size;
    let delta = store.info(delta_name("demo", id, 1)).await.unwrap().size;
    assert!(
        delta * 10 < base,
        "a delta of {delta} bytes on a base of {base}"
    );
    // `cluster status` counts them.
    let out = Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
        .args(["cluster", "status", "--json", "--nats", &nats.url()])
        .output()
        .unwrap();
    let status: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let demo = &status["scenes"][0];
    assert_eq!(demo["name"], "demo");
    assert!(demo["snapshot_deltas"].as_u64() >= Some(2), "{status}");
    a.kill();

    // A new node loads base + deltas + log, takes the scene, and has sam's history.
    let b = Node::start(&nats.url(), "b", &[]).await;
    let mut c = Client::as_user(&b.url(), None, 0x5eed, "sam")
        .await
        .unwrap();
    c.sync().await;
    assert_eq!(c.map.get(spot(0, 0)), Some(colour(1)));
    assert_eq!(c.map.get(spot(0, 1)), None);
    for (redo, pos, expect) in [
        (false, spot(0, 0), None),
        (true, spot(0, 0), Some(colour(1))),
        (true, spot(0, 1), Some(colour(2))),
    ] {
        match c.undo(redo).await {
            ServerMsg::Undone {
                seq: Some(s),
                restored: 1,
                ..
            } => c.catch_up(s).await,
            other => panic!("redo {redo}: {other:?}"),
        }
        assert_eq!(c.map.get(pos), expect, "redo {redo} at {pos:?}");
    }
}

/// Two people who join two nodes at the same moment can be given one colour (each node picks
/// among the people it knows of). One of them picks again, and both end up seeing each other
/// in a colour unlike their own, the same colour the other sees for itself.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn people_joining_two_nodes_at_once_end_with_two_colours() {
    use brickcast_server::identity::{colour_of, looks_alike};
    let nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    // Two users whose own colour is the same.
    let first = 0x1000u64;
    let second = (first + 1..)
        .find(|&u| colour_of(u) == colour_of(first))
        .unwrap();
    let (url_a, url_b) = (a.url(), b.url());
    let (x, y) = tokio::join!(
        Client::as_user(&url_a, None, first, "x"),
        Client::as_user(&url_b, None, second, "y"),
    );
    let (mut x, mut y) = (x.unwrap(), y.unwrap());
    x.sync().await;
    y.sync().await;
    let within = Duration::from_secs(15);
    // Each sees the other in a colour unlike its own.
    let apart = |other: &'static str| {
        move |c: &Client| {
            let Some(me) = &c.roster.you else {
                return false;
            };
            c.roster
                .others
                .values()
                .find(|p| p.peer.name == other)
                .is_some_and(|p| !looks_alike(p.peer.colour, me.colour))
        }
    };
    assert!(wait_for(&mut x, within, apart("y")).await, "{:?}", x.roster);
    assert!(wait_for(&mut y, within, apart("x")).await, "{:?}", y.roster);
    // And what one sees of the other is what the other shows itself as.
    let shown = |c: &Client, name: &str| {
        c.roster
            .others
            .values()
            .find(|p| p.peer.name == name)
            .map(|p| p.peer.colour)
    };
    assert_eq!(shown(&x, "y"), y.roster.you.as_ref().map(|p| p.colour));
    assert_eq!(shown(&y, "x"), x.roster.you.as_ref().map(|p| p.colour));
}
