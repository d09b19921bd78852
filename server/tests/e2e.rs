//! End-to-end tests against a real server over real websockets.

mod common;

use std::time::Duration;

use brickcast_protocol::BrushMode;
use brickcast_protocol::wire::{
    ClientMsg, EditOp, ErrorCode, RayAction, Rejection, Role, ServerMsg, encode_client,
};
use brickcast_server::auth::Auth;
use brickcast_server::store::Store;
use common::{Client, Refused, TestServer, colour, http_get};

/// Seeded ChaCha8 (`rand_chacha`: the same numbers on every platform and rand release).
struct Rng(rand_chacha::ChaCha8Rng);
impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(rand::SeedableRng::seed_from_u64(seed))
    }
    fn below(&mut self, n: u32) -> u32 {
        rand::Rng::random_range(&mut self.0, 0..n)
    }
}

fn random_op(rng: &mut Rng, size: [u32; 3]) -> EditOp {
    let pos = [rng.below(size[0]), rng.below(size[1]), rng.below(size[2])];
    let c = colour(rng.below(1000));
    match rng.below(8) {
        0..=2 => EditOp::Set { pos, colour: c },
        3 => EditOp::Clear { pos },
        4 => EditOp::Paint { pos, colour: c },
        5 => EditOp::Sphere {
            centre: pos.map(|p| p as f32 + 0.5),
            radius: 1.0 + rng.below(6) as f32,
            mode: [BrushMode::Fill, BrushMode::Erase, BrushMode::Paint][rng.below(3) as usize],
            colour: c,
        },
        6 => EditOp::Box {
            min: pos,
            max: std::array::from_fn(|i| (pos[i] + rng.below(5)).min(size[i] - 1)),
            mode: [BrushMode::Fill, BrushMode::Erase][rng.below(2) as usize],
            colour: c,
        },
        _ => EditOp::Ray {
            origin: [
                rng.below(size[0]) as f32 + 0.5,
                size[1] as f32 + 10.0,
                rng.below(size[2]) as f32 + 0.5,
            ],
            dir: [0.1, -1.0, 0.05],
            action: if rng.below(2) == 0 {
                RayAction::Place { colour: c }
            } else {
                RayAction::Remove
            },
        },
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_editors_converge_and_survive_restart() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    let url = server.url("demo");
    let mut tasks = Vec::new();
    for id in 0..4u64 {
        let url = url.clone();
        tasks.push(tokio::spawn(async move {
            let mut c = Client::connect(&url, None).await.expect("joins");
            c.sync().await;
            let size = c.map.size();
            let mut rng = Rng::new(0x9E37_79B9 + id * 7919);
            let mut last_seq = 0;
            // Pipeline several batches before reading acks, as a real client would.
            for round in 0..12 {
                let mut sent = Vec::new();
                for _ in 0..5 {
                    let ops = (0..1 + rng.below(20))
                        .map(|_| random_op(&mut rng, size))
                        .collect();
                    sent.push(c.send_edit(ops).await);
                }
                for cs in sent {
                    if let ServerMsg::Ack { seq: Some(s), .. } = c.ack(cs).await {
                        assert!(s > last_seq, "sequence numbers grow (round {round})");
                        last_seq = s;
                    }
                }
            }
            (c, last_seq)
        }));
    }
    let mut clients = Vec::new();
    let mut final_seq = 0;
    for t in tasks {
        let (c, last) = t.await.unwrap();
        clients.push(c);
        final_seq = final_seq.max(last);
    }
    // Every edit is acknowledged, so the scene stands at the last acknowledged sequence (the
    // delta of the last turn may still be on its way to the clients).
    assert!(final_seq > 100, "edits were applied: {final_seq}");
    let (_, body) = http_get(server.addr, "/scenes").await;
    let scenes: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert!(scenes[0]["seq"].as_u64().unwrap() <= final_seq);
    for c in &mut clients {
        c.catch_up(final_seq).await;
    }
    let hash = clients[0].map.content_hash();
    for c in &clients {
        assert_eq!(
            c.map.content_hash(),
            hash,
            "every client holds the same scene"
        );
    }
    // A client joining now gets the same scene from a fresh sync.
    let mut late = Client::connect(&url, None).await.unwrap();
    late.catch_up(final_seq).await;
    assert_eq!(late.map.content_hash(), hash);
    let (status, metrics) = http_get(server.addr, "/metrics").await;
    assert_eq!(status, 200);
    assert!(
        metrics.contains("brickcast_connected_clients 5"),
        "{metrics}"
    );
    assert!(metrics.contains("brickcast_log_commit_seconds_count"));
    // Prometheus reads it: every family typed, the same sample names as before the crate.
    let families = common::openmetrics_families(&metrics);
    let kind_of = |name: &str| {
        families
            .iter()
            .find(|f| f.0 == name)
            .map(|f| (f.1.as_str(), f.2))
            .unwrap_or_else(|| panic!("{name} missing: {families:?}"))
    };
    assert!(families.iter().all(|f| f.1 != "unknown"), "{families:?}");
    assert_eq!(kind_of("brickcast_edits_applied"), ("counter", 1));
    assert_eq!(kind_of("brickcast_connected_clients"), ("gauge", 1));
    assert_eq!(kind_of("brickcast_scene_seq"), ("gauge", 1));
    assert_eq!(kind_of("brickcast_owner_seconds").0, "counter");
    assert_eq!(kind_of("brickcast_log_commit_seconds").0, "histogram");
    assert!(families.len() >= 50, "{families:?}");
    assert!(
        metrics.contains("\nbrickcast_scene_seq{scene=\"demo\"} "),
        "{metrics}"
    );
    assert!(
        metrics.contains("\nbrickcast_edits_applied_total "),
        "{metrics}"
    );
    assert!(metrics.ends_with("# EOF\n"));
    for c in clients {
        c.close().await;
    }
    late.close().await;
    server.shutdown().await.unwrap();
    // What the store recovers is what the clients saw.
    let store = Store::open(dir.path()).unwrap();
    let loaded = store.load_scene("demo").unwrap();
    assert_eq!(loaded.seq, final_seq);
    assert_eq!(loaded.map.content_hash(), hash);
}

#[tokio::test]
async fn roles_from_the_auth_file() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |c| {
        c.auth = Auth::parse("ed-token editor\nview-token viewer\n").unwrap();
    })
    .await;
    let url = server.url("demo");
    let mut viewer = Client::connect(&url, Some("view-token")).await.unwrap();
    assert_eq!(viewer.role, Role::Viewer);
    viewer.sync().await;
    let before = viewer.map.content_hash();
    match viewer
        .edit(vec![EditOp::Set {
            pos: [1, 60, 1],
            colour: colour(1),
        }])
        .await
    {
        ServerMsg::Ack {
            seq: None,
            applied: 0,
            rejected,
            ..
        } => {
            assert_eq!(rejected.len(), 1);
            assert_eq!(rejected[0].reason, Rejection::NotAllowed);
        }
        other => panic!("{other:?}"),
    }
    let mut anonymous = Client::connect(&url, None).await.unwrap();
    assert_eq!(anonymous.role, Role::Viewer, "no token: watch only");
    anonymous.sync().await;
    match Client::connect(&url, Some("wrong")).await {
        Err(Refused::Error(ErrorCode::Unauthorized, _)) => {}
        Err(other) => panic!("{other:?}"),
        Ok(_) => panic!("an unknown token was let in"),
    }
    let mut editor = Client::connect(&url, Some("ed-token")).await.unwrap();
    assert_eq!(editor.role, Role::Editor);
    editor.sync().await;
    let ServerMsg::Ack { seq: Some(seq), .. } = editor
        .edit(vec![EditOp::Set {
            pos: [1, 60, 1],
            colour: colour(1),
        }])
        .await
    else {
        panic!("editor edit applies")
    };
    // The viewer still watches: it receives the editor's change.
    viewer.catch_up(seq).await;
    assert_ne!(viewer.map.content_hash(), before);
    assert!(viewer.map.is_solid([1, 60, 1]));
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn bad_frames_close_only_their_connection() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |c| {
        c.owner.limits.max_frame_bytes = brickcast_protocol::wire::MIN_FRAME_BYTES;
    })
    .await;
    let url = server.url("demo");
    let mut good = Client::connect(&url, None).await.unwrap();
    good.sync().await;

    let mut garbage = Client::connect(&url, None).await.unwrap();
    garbage.send_raw(vec![0xFF, 0x13, 0x37, 0x00, 0x42]).await;
    let errors = garbage.until_closed().await;
    assert!(
        errors.iter().any(|(c, _)| *c == ErrorCode::MalformedFrame),
        "{errors:?}"
    );

    let mut big = Client::connect(&url, None).await.unwrap();
    // A well-formed edit whose frame (about 160 KB) exceeds the server's 64 KiB limit.
    let sphere = EditOp::Sphere {
        centre: [1.5, 2.5, 3.5],
        radius: 2.5,
        mode: BrushMode::Fill,
        colour: colour(5),
    };
    let ops = vec![sphere; 8000];
    big.send_raw(encode_client(&ClientMsg::Edit { client_seq: 1, ops }).unwrap())
        .await;
    let errors = big.until_closed().await;
    assert!(
        errors.iter().any(|(c, _)| *c == ErrorCode::FrameTooLarge),
        "{errors:?}"
    );

    // Wrong protocol version: a clear error, not a decode failure.
    let (mut ws, _) = tokio_tungstenite::connect_async(&url).await.unwrap();
    use futures_util::{SinkExt, StreamExt};
    let hello = ClientMsg::Hello {
        protocol: 99,
        name: "old".into(),
        token: None,
        resume_from: None,
        user: 0,
        budget: None,
    };
    ws.send(tokio_tungstenite::tungstenite::Message::Binary(
        encode_client(&hello).unwrap().into(),
    ))
    .await
    .unwrap();
    let reply = ws.next().await.unwrap().unwrap().into_data();
    match brickcast_protocol::wire::decode_server(&reply, &Default::default()).unwrap() {
        ServerMsg::Error {
            code: ErrorCode::VersionMismatch,
            message,
        } => assert!(message.contains("99"), "{message}"),
        other => panic!("{other:?}"),
    }

    // A client of protocol 1 (its Hello had no user id) learns the version, not "malformed".
    let (mut ws, _) = tokio_tungstenite::connect_async(&url).await.unwrap();
    let v1_hello = bincode::serde::encode_to_vec(
        (0u32, 1u32, "brickcast 0.1", None::<String>, None::<u64>),
        bincode::config::standard(),
    )
    .unwrap();
    ws.send(tokio_tungstenite::tungstenite::Message::Binary(
        v1_hello.into(),
    ))
    .await
    .unwrap();
    let reply = ws.next().await.unwrap().unwrap().into_data();
    match brickcast_protocol::wire::decode_server(&reply, &Default::default()).unwrap() {
        ServerMsg::Error {
            code: ErrorCode::VersionMismatch,
            message,
        } => assert!(
            message.contains(&format!(
                "protocol {}",
                brickcast_protocol::wire::PROTOCOL_VERSION
            )) && message.contains("client 1"),
            "{message}"
        ),
        other => panic!("{other:?}"),
    }

    // A frame that breaks the websocket protocol itself (a reserved bit set, no extension
    // agreed): a MalformedFrame error, not "too large".
    let mut broken = Client::connect(&url, None).await.unwrap();
    {
        use tokio::io::AsyncWriteExt;
        let tokio_tungstenite::MaybeTlsStream::Plain(tcp) = broken.ws_mut().get_mut() else {
            panic!("plain TCP");
        };
        // FIN + RSV1 + binary, masked, one byte of payload.
        let mask = [1u8, 2, 3, 4];
        tcp.write_all(&[
            0xC2,
            0x81,
            mask[0],
            mask[1],
            mask[2],
            mask[3],
            0x42 ^ mask[0],
        ])
        .await
        .unwrap();
    }
    let errors = broken.until_closed().await;
    assert!(
        errors
            .iter()
            .any(|(c, m)| *c == ErrorCode::MalformedFrame && m.contains("protocol")),
        "{errors:?}"
    );

    // The well-behaved client carries on.
    match good
        .edit(vec![EditOp::Set {
            pos: [2, 60, 2],
            colour: colour(2),
        }])
        .await
    {
        ServerMsg::Ack {
            seq: Some(_),
            applied: 1,
            ..
        } => {}
        other => panic!("{other:?}"),
    }
    let (_, metrics) = http_get(server.addr, "/metrics").await;
    assert!(
        metrics.contains("brickcast_rejected_frames_total 5"),
        "{metrics}"
    );
    for line in [
        "brickcast_read_errors_total{kind=\"too_large\"} 1",
        "brickcast_read_errors_total{kind=\"protocol\"} 1",
    ] {
        assert!(
            metrics.lines().any(|l| l == line),
            "{line} missing:\n{metrics}"
        );
    }
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn bad_ops_are_rejected_one_by_one() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    let mut c = Client::connect(&server.url("demo"), None).await.unwrap();
    c.sync().await;
    let ops = vec![
        EditOp::Set {
            pos: [3, 60, 3],
            colour: colour(3),
        },
        EditOp::Set {
            pos: [128, 0, 0],
            colour: colour(3),
        },
        EditOp::Sphere {
            centre: [f32::NAN, 1.0, 1.0],
            radius: 2.0,
            mode: BrushMode::Fill,
            colour: colour(3),
        },
        EditOp::Sphere {
            centre: [10.0, 10.0, 10.0],
            radius: 1000.0,
            mode: BrushMode::Fill,
            colour: colour(3),
        },
        EditOp::Ray {
            origin: [5.0, 100.0, 5.0],
            dir: [0.0, 1.0, 0.0],
            action: RayAction::Remove,
        },
        EditOp::Clear { pos: [3, 60, 4] },
    ];
    match c.edit(ops).await {
        ServerMsg::Ack {
            seq: Some(_),
            applied,
            rejected,
            ..
        } => {
            assert_eq!(applied, 2, "the set and the (no-op) clear");
            let reasons: Vec<_> = rejected
                .iter()
                .map(|r| (r.index, r.reason.clone()))
                .collect();
            assert_eq!(
                reasons,
                vec![
                    (1, Rejection::OutOfBounds),
                    (2, Rejection::InvalidNumber),
                    (3, Rejection::TooLarge),
                    (4, Rejection::RayMissed)
                ]
            );
        }
        other => panic!("{other:?}"),
    }
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn reconnect_resumes_with_only_what_changed() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    let url = server.url("demo");
    let mut a = Client::connect(&url, None).await.unwrap();
    a.sync().await;
    let full = a.sync_total;
    let seen = a.seq;
    let map = a.map.clone();
    a.close().await;

    let mut b = Client::connect(&url, None).await.unwrap();
    b.sync().await;
    let ServerMsg::Ack { seq: Some(seq), .. } = b
        .edit(vec![
            EditOp::Sphere {
                centre: [20.0, 30.0, 20.0],
                radius: 5.0,
                mode: BrushMode::Erase,
                colour: colour(0),
            },
            EditOp::Set {
                pos: [100, 62, 100],
                colour: colour(9),
            },
        ])
        .await
    else {
        panic!("edit applies")
    };

    let mut back = Client::resume(&url, None, Some(seen), Some(map))
        .await
        .unwrap();
    assert!(
        back.sync_total < full / 10,
        "resume sends {} bricks, a full sync {full}",
        back.sync_total
    );
    back.catch_up(seq).await;
    b.catch_up(seq).await;
    assert_eq!(back.map.content_hash(), b.map.content_hash());
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn a_client_that_never_reads_is_resynced_not_buffered() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |c| c.owner.max_queue_bytes = 64 << 10).await;
    let url = server.url("demo");
    // Joins, then reads nothing while another client edits heavily.
    let mut sleeper = Client::connect(&url, None).await.unwrap();
    let mut editor = Client::connect(&url, None).await.unwrap();
    editor.sync().await;
    // Random colours at random places: large deltas that barely compress, more than the
    // kernel's socket buffers can hide.
    let mut rng = Rng::new(42);
    let mut last = 0;
    for _ in 0..40 {
        let ops = (0..4000)
            .map(|_| EditOp::Set {
                pos: [rng.below(128), rng.below(64), rng.below(128)],
                colour: brickcast_protocol::Colour(rng.below(1 << 16) as u16),
            })
            .collect();
        if let ServerMsg::Ack { seq: Some(s), .. } = editor.edit(ops).await {
            last = s;
        }
    }
    let (_, metrics) = http_get(server.addr, "/metrics").await;
    let resyncs: u64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("brickcast_resyncs_total "))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    assert!(
        resyncs >= 1,
        "the sleeper overflowed its queue and was marked for resync"
    );
    // It wakes up, and converges anyway.
    sleeper.catch_up(last).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    editor.catch_up(last).await;
    assert_eq!(sleeper.map.content_hash(), editor.map.content_hash());
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn shutdown_acks_and_persists_queued_edits() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    let url = server.url("demo");
    let mut c = Client::connect(&url, None).await.unwrap();
    c.sync().await;
    let mut sent = Vec::new();
    for i in 0..20u32 {
        sent.push(
            c.send_edit(vec![EditOp::Set {
                pos: [i, 63, 7],
                colour: colour(i),
            }])
            .await,
        );
    }
    // Read one ack so the edits are surely in flight, then shut down without waiting for more.
    c.ack(sent[0]).await;
    let shutdown = tokio::spawn(server.shutdown());
    let mut acked = vec![0u32];
    while let Some(msg) = c.next().await {
        if let ServerMsg::Ack {
            client_seq,
            seq: Some(_),
            ..
        } = msg
        {
            acked.push(client_seq as u32 - 1);
        }
    }
    assert!(c.closed, "the server closed the socket");
    shutdown.await.unwrap().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let loaded = store.load_scene("demo").unwrap();
    assert_eq!(
        store.log_len("demo").unwrap(),
        0,
        "shutdown folded the log into a snapshot"
    );
    for i in acked {
        assert_eq!(
            loaded.map.get([i, 63, 7]),
            Some(colour(i)),
            "acknowledged edit {i} persisted"
        );
    }
}

#[tokio::test]
async fn http_endpoints() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    assert_eq!(http_get(server.addr, "/healthz").await.0, 200);
    assert_eq!(http_get(server.addr, "/scenes/nope/ws").await.0, 404);
    let (status, body) = http_get(server.addr, "/scenes").await;
    assert_eq!(status, 200);
    let list: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(list[0]["name"], "demo");
    assert_eq!(list[0]["size"], serde_json::json!([128, 64, 128]));
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn edits_are_rate_limited_per_client() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |c| c.owner.limits.max_edits_per_second = 100).await;
    let mut c = Client::connect(&server.url("demo"), None).await.unwrap();
    c.sync().await;
    let ops = |n: u32| {
        (0..n)
            .map(|i| EditOp::Set {
                pos: [i, 62, 9],
                colour: colour(i),
            })
            .collect::<Vec<_>>()
    };
    assert!(matches!(
        c.edit(ops(80)).await,
        ServerMsg::Ack { applied: 80, .. }
    ));
    match c.edit(ops(80)).await {
        ServerMsg::Ack {
            applied: 0,
            rejected,
            ..
        } => {
            assert_eq!(rejected.len(), 80);
            assert!(rejected.iter().all(|r| r.reason == Rejection::RateLimited));
        }
        other => panic!("second burst should be rate limited: {other:?}"),
    }
    // Tokens come back with time.
    tokio::time::sleep(Duration::from_millis(900)).await;
    assert!(matches!(
        c.edit(ops(80)).await,
        ServerMsg::Ack { applied: 80, .. }
    ));
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_joining_during_heavy_editing_converges() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    let url = server.url("demo");
    let editor_url = url.clone();
    let editor = tokio::spawn(async move {
        let mut e = Client::connect(&editor_url, None).await.unwrap();
        let mut rng = Rng::new(7);
        let mut last = 0;
        for _ in 0..80 {
            let ops = (0..40)
                .map(|_| random_op(&mut rng, [128, 64, 128]))
                .collect();
            if let ServerMsg::Ack { seq: Some(s), .. } = e.edit(ops).await {
                last = s;
            }
        }
        (e, last)
    });
    tokio::time::sleep(Duration::from_millis(30)).await;
    let mut joiner = Client::connect(&url, None).await.unwrap();
    let (mut e, last) = editor.await.unwrap();
    joiner.catch_up(last).await;
    e.catch_up(last).await;
    assert_eq!(joiner.map.content_hash(), e.map.content_hash());
    server.shutdown().await.unwrap();
}

/// A client that keeps writing but never reads is first no longer read (its replies stay
/// under a small backlog, so it costs its own socket, not the server's memory), then cut off
/// once its socket has taken nothing for the stall timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_writes_but_never_reads_is_paused_then_cut_off() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |c| {
        c.owner.max_queue_bytes = 64 << 10;
        c.stall_timeout = Duration::from_secs(1);
    })
    .await;
    let url = server.url("demo");
    let mut flooder = Client::connect(&url, None).await.unwrap();
    // Every op is out of bounds, so each batch earns an ack listing 4,000 rejections; the
    // client never reads them, and they pile up behind the kernel's socket buffers. Once the
    // server stops reading, the client's own sends wait (and fail once it is cut off).
    let ops: Vec<EditOp> = (0..4000)
        .map(|_| EditOp::Clear {
            pos: [100_000, 100_000, 100_000],
        })
        .collect();
    let sending = tokio::spawn(async move {
        // Far more replies than loopback's socket buffers hold (about 16 KB each); sends
        // after the cut-off fail at once.
        for _ in 0..5000 {
            flooder.send_edit(ops.clone()).await;
        }
        flooder
    });
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while common::metric(server.addr, "brickcast_stalled_disconnects_total").await < 1.0 {
        if std::time::Instant::now() > deadline {
            let (_, m) = http_get(server.addr, "/metrics").await;
            panic!("the flooder was never cut off: {m}");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(common::metric(server.addr, "brickcast_reads_paused_total").await >= 1.0);
    let mut flooder = sending.await.unwrap();
    flooder.until_closed().await;
    // Everyone else is unaffected.
    let mut other = Client::connect(&url, None).await.unwrap();
    other.sync().await;
    assert!(matches!(
        other
            .edit(vec![EditOp::Set {
                pos: [5, 61, 5],
                colour: colour(5)
            }])
            .await,
        ServerMsg::Ack { applied: 1, .. }
    ));
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn initial_sync_sends_nearest_bricks_first() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |c| c.owner.limits.max_bricks_per_frame = 32).await;
    let mut c = Client::connect(&server.url("demo"), None).await.unwrap();
    // Before any Camera message the server streams from above the scene's centre.
    let size = c.map.size();
    let eye = [size[0] as f32 * 0.5, size[1] as f32, size[2] as f32 * 0.5];
    let distance = |cell: [u32; 3]| -> f32 {
        (0..3)
            .map(|i| (cell[i] as f32 * 8.0 + 4.0 - eye[i]).powi(2))
            .sum()
    };
    let mut batches: Vec<(f32, f32)> = Vec::new();
    let mut decoder = brickcast_protocol::wire::BlobDecoder::new().unwrap();
    while !c.synced {
        if let Some(ServerMsg::SyncBatch { bricks, .. }) = c.next().await {
            let (mut lo, mut hi) = (f32::MAX, 0f32);
            decoder
                .for_each(&bricks, 64, |b| {
                    lo = lo.min(distance(b.cell));
                    hi = hi.max(distance(b.cell));
                })
                .unwrap();
            batches.push((lo, hi));
        }
    }
    assert!(batches.len() > 10, "small batches: {}", batches.len());
    for pair in batches.windows(2) {
        // Every brick of a batch is at most as far as every brick of the next (up to the
        // server's 1/16-voxel² sort granularity).
        assert!(pair[0].1 <= pair[1].0 + 1.0, "{pair:?}");
    }
    server.shutdown().await.unwrap();
}

/// Level K of a scene (`/scenes/NAME@K`) is served as a read-only scene of its own: what a
/// viewer of it holds is exactly level K of the pyramid of what an editor holds, after a sync,
/// after edits (deltas of the coarse bricks they changed) and after a resume.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn levels_of_detail_are_served_read_only_and_follow_edits() {
    use brickcast_protocol::lod::Pyramid;
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(dir.path(), |_| {}).await;
    let mut editor = Client::connect(&server.url("demo"), None).await.unwrap();
    editor.sync().await;
    let mut one = Client::connect(&server.url("demo@1"), None).await.unwrap();
    let mut three = Client::connect(&server.url("demo@3"), None).await.unwrap();
    assert_eq!(one.role, Role::Viewer, "a level view is read-only");
    assert_eq!(one.map.size(), [64, 32, 64]);
    assert_eq!(three.map.size(), [16, 8, 16]);
    one.sync().await;
    three.sync().await;
    let agree = |editor: &Client, views: &[(&Client, u32)]| {
        let pyramid = Pyramid::build(&editor.map).unwrap();
        for (view, k) in views {
            let want = pyramid.level(*k).unwrap();
            assert!(want.brick_count() > 0);
            assert_eq!(view.map.brick_count(), want.brick_count(), "level {k}");
            assert_eq!(view.map.content_hash(), want.content_hash(), "level {k}");
        }
    };
    agree(&editor, &[(&one, 1), (&three, 3)]);

    let mut rng = Rng::new(11);
    let mut last = 0;
    for _ in 0..6 {
        let ops = (0..24)
            .map(|_| random_op(&mut rng, common::TEST_SCENE))
            .collect();
        if let ServerMsg::Ack { seq: Some(seq), .. } = editor.edit(ops).await {
            last = seq;
        }
    }
    assert!(last > 0, "some edits applied");
    editor.catch_up(last).await;
    one.catch_up(last).await;
    three.catch_up(last).await;
    assert_eq!(one.resyncs + three.resyncs, 0, "deltas, not resyncs");
    agree(&editor, &[(&one, 1), (&three, 3)]);

    // A level view's edits are refused; it still follows the scene.
    match one
        .edit(vec![EditOp::Set {
            pos: [1, 30, 1],
            colour: colour(1),
        }])
        .await
    {
        ServerMsg::Ack {
            seq: None,
            rejected,
            ..
        } => assert_eq!(rejected[0].reason, Rejection::NotAllowed),
        other => panic!("{other:?}"),
    }

    // A level view that resumes gets what changed at its level, not the whole level.
    let (seen, copy) = (one.seq, one.map.clone());
    let full = one.map.brick_count() as u32;
    one.close().await;
    let ServerMsg::Ack { seq: Some(seq), .. } = editor
        .edit(vec![EditOp::Sphere {
            centre: [30.0, 40.0, 30.0],
            radius: 6.0,
            mode: BrushMode::Fill,
            colour: colour(3),
        }])
        .await
    else {
        panic!("the sphere applies")
    };
    let mut back = Client::resume(&server.url("demo@1"), None, Some(seen), Some(copy))
        .await
        .unwrap();
    assert!(back.sync_total < full / 4, "{} of {full}", back.sync_total);
    editor.catch_up(seq).await;
    back.catch_up(seq).await;
    three.catch_up(seq).await;
    agree(&editor, &[(&back, 1), (&three, 3)]);

    // Levels the scene does not have are refused before the upgrade, with the reason.
    for (path, says) in [("demo@5", "levels of detail 1 to 4"), ("demo@0", "from 1")] {
        match tokio_tungstenite::connect_async(server.url(path)).await {
            Err(tokio_tungstenite::tungstenite::Error::Http(response)) => {
                assert_eq!(response.status(), 404);
                let body =
                    String::from_utf8_lossy(response.body().as_deref().unwrap_or(&[])).to_string();
                assert!(body.contains(says), "{path}: {body}");
            }
            other => panic!("{path}: {other:?}"),
        }
    }
    server.shutdown().await.unwrap();
}

/// A port already in use fails the start before the store is touched: no folder, no demo scene
/// left behind by a server that never ran, and the error says what to do.
#[tokio::test]
async fn a_port_in_use_fails_before_the_store_is_created() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("store");
    let config = brickcast_server::ServerConfig::new(taken.local_addr().unwrap(), data.clone());
    let e = brickcast_server::Server::bind(config)
        .await
        .err()
        .map(|e| format!("{e:#}"))
        .unwrap_or_default();
    assert!(
        e.contains("cannot listen on") && e.contains("--listen"),
        "{e}"
    );
    assert!(!data.exists(), "the store folder was created");
}
