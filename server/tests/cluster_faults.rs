//! The cluster's failures found from outside, each as an end-to-end test against a real
//! `nats-server` and real node processes:
//!
//! * an owner paused just under its lease (its own deadline passed, the lease's key not yet
//!   expired) gives the scene back to edits: it is not wedged;
//! * SIGTERM (and an idle close) of a node that owns a scene stops it cleanly, with a
//!   snapshot of its last edit;
//! * a garbage message on a scene's log: every node says so at once and stops serving the
//!   scene, `cluster repair` drops it (reporting what it dropped), and the scene serves again
//!   with every acknowledged edit; with the README's NATS permissions a stranger cannot
//!   publish one at all;
//! * a node paused until its name expired, and a new node of the same name: the old one stops
//!   when it wakes.

mod common;
mod nodes;

use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::time::{Duration, Instant};

use common::Client;
use nodes::*;

/// `brickcast-server cluster ARGS --nats URL`: its exit status, stdout and stderr.
async fn cluster_cli(nats: &str, args: &[&str]) -> (bool, String, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_brickcast-server"));
    cmd.arg("cluster")
        .args(args)
        .args(["--nats", nats])
        .env("RUST_LOG", "warn")
        .env("NO_COLOR", "1");
    let out = tokio::task::spawn_blocking(move || cmd.output().unwrap())
        .await
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// What `cluster status --json` says of the demo scene.
async fn demo_status(nats: &str) -> serde_json::Value {
    let (ok, out, err) = cluster_cli(nats, &["status", "--json"]).await;
    assert!(ok, "cluster status failed: {err}");
    let status: serde_json::Value = serde_json::from_str(&out).unwrap();
    status["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "demo")
        .cloned()
        .unwrap_or_default()
}

/// Waits until the newest snapshot of the demo scene is at `seq`.
async fn until_snapshot_at(nats: &str, seq: u64, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let s = demo_status(nats).await;
        if s["snapshot_seq"] == seq {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: the newest snapshot is not at sequence {seq}: {s}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// An edit through a fresh client on `node` is acknowledged within `within`; its sequence.
async fn edit_within(node: &Node, within: Duration, pos: [u32; 3], col: u32) -> u64 {
    let attempt = async {
        let mut c = Client::connect(&node.url(), None).await.ok()?;
        c.sync().await;
        Some(set(&mut c, pos, col).await)
    };
    match tokio::time::timeout(within, attempt).await {
        Ok(Some(seq)) => seq,
        other => panic!(
            "node {}: no edit acknowledged within {within:?} ({other:?})\n{}",
            node.name,
            node.log_text()
        ),
    }
}

/// An owner stopped for a little less than the lease's life finds, when it wakes, that its own
/// deadline passed (its append is refused) while its lease key still lives. It must not keep
/// renewing a lease it no longer uses: edits are acknowledged again within seconds.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_owner_paused_just_under_its_lease_gives_the_scene_back() {
    let nats = Nats::start(true);
    let nodes = [
        Node::start(&nats.url(), "a", &[]).await,
        Node::start(&nats.url(), "b", &[]).await,
    ];
    let refs: Vec<&Node> = nodes.iter().collect();
    // Load on both nodes, so an edit waits at the owner whenever it wakes.
    let stop = Arc::new(AtomicBool::new(false));
    let writers: Vec<_> = nodes
        .iter()
        .enumerate()
        .map(|(w, n)| tokio::spawn(writer(n.url(), w as u32, stop.clone())))
        .collect();
    // The key lives 3 s after the owner's last renewal (every 0.75 s); the owner stops
    // appending 2.5 s after it. Several pauses in that window, so that some wake with the
    // key alive whatever the phase of the renewals.
    for (round, pause_ms) in [2600u64, 2750, 2900, 2650].into_iter().enumerate() {
        let owner = owner_of(&refs, Duration::from_secs(20)).await;
        tokio::time::sleep(Duration::from_millis(300 + 170 * round as u64)).await;
        nodes[owner].stop();
        tokio::time::sleep(Duration::from_millis(pause_ms)).await;
        nodes[owner].cont();
        for (i, n) in nodes.iter().enumerate() {
            let pos = spot(4 + round as u32, i as u32);
            edit_within(n, Duration::from_secs(10), pos, 7).await;
        }
    }
    stop.store(true, Relaxed);
    let mut acked = Vec::new();
    for w in writers {
        acked.push(w.await.unwrap());
    }
    assert_converged(&refs, &acked, "after the pauses").await;
}

/// SIGTERM of the node that owns a scene: it commits what it has, writes a snapshot of its
/// last edit, hands the scene over and exits 0. Closing an idle scene on a node takes the same
/// path.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sigterm_and_idle_close_of_the_owner_stop_cleanly_with_a_snapshot() {
    let nats = Nats::start(true);
    let mut a = Node::start(&nats.url(), "a", &["--close-idle", "1"]).await;
    owner_of(&[&a], Duration::from_secs(20)).await;
    let mut c = Client::connect(&a.url(), None).await.unwrap();
    c.sync().await;
    let mut last = 0;
    for k in 0..3 {
        last = set(&mut c, spot(0, k), k + 1).await;
    }
    c.close().await;
    // Nobody uses the scene on a: it closes there, with a snapshot.
    let deadline = Instant::now() + Duration::from_secs(20);
    while a.serves().await {
        assert!(Instant::now() < deadline, "the idle scene did not close");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    until_snapshot_at(&nats.url(), last, "after an idle close").await;
    assert!(!a.log_text().contains("panicked"), "{}", a.log_text());

    // Open it again on a (a owns it again), start b, edit through b, SIGTERM a.
    let mut c = Client::connect(&a.url(), None).await.unwrap();
    c.sync().await;
    owner_of(&[&a], Duration::from_secs(20)).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    let mut on_b = Client::connect(&b.url(), None).await.unwrap();
    on_b.sync().await;
    for k in 3..6 {
        last = set(&mut on_b, spot(0, k), k + 1).await;
    }
    signal(a.child.as_ref().unwrap(), libc::SIGTERM);
    let status = a.wait_exit(Duration::from_secs(30));
    let text = a.log_text();
    assert!(status.is_some_and(|s| s.success()), "{status:?}\n{text}");
    assert!(!text.contains("panicked"), "{text}");
    assert!(text.contains("shut down cleanly"), "{text}");
    until_snapshot_at(&nats.url(), last, "after SIGTERM").await;
    // b carries on with every edit.
    let next = edit_within(&b, Duration::from_secs(10), spot(1, 0), 9).await;
    assert_eq!(next, last + 1);
    let copy = copy_at(&b, next).await;
    for k in 0..6 {
        assert_eq!(copy.map.get(spot(0, k)), Some(common::colour(k + 1)));
    }
}

/// A node paused until its name expired comes back beside a new process that took the name:
/// the old one stops (it may not serve as a second node of that name), the new one keeps the
/// name and serves.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_node_whose_name_was_taken_while_it_was_paused_stops_when_it_wakes() {
    let nats = Nats::start(true);
    let mut old = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    old.stop();
    let client = async_nats::connect(nats.url()).await.unwrap();
    let names = async_nats::jetstream::new(client)
        .get_key_value("brickcast_nodes")
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while names.get("a").await.unwrap().is_some() {
        assert!(
            Instant::now() < deadline,
            "the paused node's name never expired"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let new = Node::start(&nats.url(), "a", &[]).await;
    old.cont();
    let status = old.wait_exit(Duration::from_secs(20));
    let text = old.log_text();
    assert!(status.is_some_and(|s| !s.success()), "{status:?}\n{text}");
    assert!(text.contains("took this node's name"), "{text}");
    // The name is the new process's, and stays so.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let entry: serde_json::Value =
        serde_json::from_slice(&names.get("a").await.unwrap().expect("the name is held")).unwrap();
    assert_eq!(entry["listen"], new.addr.to_string());
    edit_within(&new, Duration::from_secs(10), spot(0, 0), 3).await;
    edit_within(&b, Duration::from_secs(10), spot(0, 1), 4).await;
}
/// A message that is not a turn lands in a scene's log (anyone who may publish to NATS can do
/// this). Every node stops serving the scene at once and says why, naming the repair; the
/// repair drops the message, says so, and the scene serves again with every edit.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_garbage_log_message_is_repaired_by_an_operator_never_silently() {
    let nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    let mut on_b = Client::connect(&b.url(), None).await.unwrap();
    on_b.sync().await;
    let mut last = 0;
    for k in 0..3 {
        last = set(&mut on_b, spot(0, k), k + 1).await;
    }
    let (ok, out, err) = cluster_cli(&nats.url(), &["repair", "--scene", "demo"]).await;
    assert!(ok, "{err}");
    assert!(out.contains("nothing to repair"), "{out}");

    let client = async_nats::connect(nats.url()).await.unwrap();
    let js = async_nats::jetstream::new(client);
    let garbage = js
        .publish("brickcast.log.demo", "not a turn".into())
        .await
        .unwrap()
        .await
        .unwrap()
        .sequence;
    // The client is told at once, not after the edit patience.
    let told = tokio::time::timeout(Duration::from_secs(8), on_b.until_closed())
        .await
        .expect("the client was not told");
    assert!(
        told.iter()
            .any(|(_, text)| text.contains(&format!("message {garbage}"))
                && text.contains("cluster repair")),
        "{told:?}"
    );
    // Neither node serves the scene now; opening it says why.
    for n in [&a, &b] {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            match tokio_tungstenite::connect_async(n.url()).await {
                Err(tokio_tungstenite::tungstenite::Error::Http(response)) => {
                    assert_eq!(response.status(), 503);
                    let body =
                        String::from_utf8_lossy(response.body().as_deref().unwrap_or_default());
                    assert!(body.contains("cluster repair"), "{body}");
                    break;
                }
                other => {
                    assert!(
                        Instant::now() < deadline,
                        "node {} still serves a scene with a corrupt log: {:?}",
                        n.name,
                        other.map(|_| ())
                    );
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
            }
        }
        assert!(n.log_text().contains("cluster repair"), "{}", n.log_text());
    }

    let (ok, out, err) = cluster_cli(&nats.url(), &["repair", "--scene", "demo"]).await;
    assert!(ok, "{err}");
    assert!(
        out.contains(&format!("dropped log message {garbage}")),
        "{out}"
    );
    // Every node serves the scene again, with every edit, and takes new ones.
    for (i, n) in [&a, &b].into_iter().enumerate() {
        let seq = edit_within(n, Duration::from_secs(15), spot(1, i as u32), 5).await;
        assert!(seq > last);
        let copy = copy_at(n, seq).await;
        for k in 0..3 {
            assert_eq!(copy.map.get(spot(0, k)), Some(common::colour(k + 1)));
        }
    }
}

/// With the NATS permissions the README gives, only the nodes' user may publish to the
/// cluster's subjects: a stranger's garbage never reaches the log.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn with_the_readme_permissions_a_stranger_cannot_touch_the_log() {
    let nats = Nats::start_with_config(include_str!("../../docs/nats-permissions.conf"));
    let url = nats.url_as("brickcast", "node-secret");
    let a = Node::start(&url, "a", &[]).await;
    let mut c = Client::connect(&a.url(), None).await.unwrap();
    c.sync().await;
    set(&mut c, spot(0, 0), 1).await;
    // The node's log shows no password.
    assert!(!a.log_text().contains("node-secret"), "{}", a.log_text());

    let stranger =
        async_nats::ConnectOptions::with_user_and_password("viewer".into(), "viewer-secret".into())
            .connect(nats.url())
            .await
            .unwrap();
    let js = async_nats::jetstream::new(stranger.clone());
    let publish = js.publish("brickcast.log.demo", "not a turn".into()).await;
    let landed = match publish {
        Ok(ack) => tokio::time::timeout(Duration::from_secs(3), ack)
            .await
            .is_ok_and(|a| a.is_ok()),
        Err(_) => false,
    };
    assert!(!landed, "a stranger's message landed in the log");
    // Forged edits on the edit subject are refused too.
    let _ = stranger
        .publish("brickcast.edit.demo.a", "forged".into())
        .await;
    let _ = stranger.flush().await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let seq = edit_within(&a, Duration::from_secs(10), spot(0, 1), 2).await;
    assert_eq!(seq, 2, "the log holds the two edits and nothing else");
    assert!(!a.log_text().contains("cannot read"), "{}", a.log_text());
}
