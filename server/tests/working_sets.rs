//! Working sets end to end (issue #30): a client that states a GPU budget is streamed the
//! working set around its camera by a real server on loopback, follows the camera, takes deltas
//! only for what it holds, resumes, and is refused clearly when its budget is too small. Its
//! copy is the protocol crate's `Replica`, the one every real client uses.

mod common;

use brickcast_protocol::lod::Pyramid;
use brickcast_protocol::map::REGION_CELLS;
use brickcast_protocol::replica::Replica;
use brickcast_protocol::wire::{
    BlobDecoder, Budget, ClientMsg, EditOp, ErrorCode, Limits, PROTOCOL_VERSION, ServerMsg,
    decode_server, encode_client,
};
use brickcast_protocol::working_set::{self, Rule};
use brickcast_protocol::{BrickMap, BrushMode, Colour};
use common::{Client, TestServer, colour};
use futures_util::{SinkExt, StreamExt};
use std::time::Duration;
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// The scene these tests serve: the demo terrain at 512×64×512 (16×2×16 regions).
const SIZE: [u32; 3] = [512, 64, 512];

/// A client holding a working set, counting the level-0 bricks it was sent per region.
struct Follower {
    ws: WebSocketStream<MaybeTlsStream<TcpStream>>,
    replica: Replica,
    decoder: BlobDecoder,
    /// Level-0 bricks received in deltas, by the region they lie in.
    delta_bricks: Vec<[u32; 3]>,
    errors: Vec<(ErrorCode, String)>,
    closed: bool,
}

impl Follower {
    async fn connect(
        url: &str,
        budget: u64,
        eye: Option<[f32; 3]>,
        resume: Option<(u64, Replica)>,
    ) -> Follower {
        let (mut ws, _) = tokio_tungstenite::connect_async(url).await.unwrap();
        let hello = ClientMsg::Hello {
            protocol: PROTOCOL_VERSION,
            name: "follower".into(),
            token: None,
            resume_from: resume.as_ref().map(|(seq, _)| *seq),
            user: 0,
            budget: Some(Budget { bytes: budget, eye }),
        };
        ws.send(Message::Binary(encode_client(&hello).unwrap().into()))
            .await
            .unwrap();
        let replica = match resume {
            Some((_, replica)) => replica,
            None => Replica::new("demo", SIZE).unwrap(),
        };
        Follower {
            ws,
            replica,
            decoder: BlobDecoder::new().unwrap(),
            delta_bricks: Vec::new(),
            errors: Vec::new(),
            closed: false,
        }
    }

    async fn camera(&mut self, eye: [f32; 3]) {
        let msg = ClientMsg::Camera {
            eye,
            forward: [0.0, 0.0, 1.0],
        };
        self.ws
            .send(Message::Binary(encode_client(&msg).unwrap().into()))
            .await
            .unwrap();
    }

    /// Reads and applies one message; `None` once the server closed.
    async fn next(&mut self) -> Option<ServerMsg> {
        loop {
            let frame = tokio::time::timeout(Duration::from_secs(30), self.ws.next())
                .await
                .expect("a message within 30 s");
            let bytes = match frame {
                Some(Ok(Message::Binary(b))) => b,
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => {
                    self.closed = true;
                    return None;
                }
                Some(Ok(_)) => continue,
            };
            let msg = decode_server(&bytes, &Limits::hard_caps()).unwrap();
            if let ServerMsg::Delta { bricks, .. } = &msg {
                let seen = &mut self.delta_bricks;
                self.decoder
                    .for_each(bricks, 8192, |b| {
                        seen.push(b.cell.map(|c| c / REGION_CELLS))
                    })
                    .unwrap();
            }
            if let ServerMsg::Error { code, message } = &msg {
                self.errors.push((*code, message.clone()));
            }
            self.replica.apply(&msg).expect("the replica takes it");
            return Some(msg);
        }
    }

    /// Reads until the working set for an eye at `eye` is complete and every change up to
    /// `seq` has arrived.
    async fn settle(&mut self, eye: [f32; 3], seq: u64) -> Rule {
        let want = Rule::eye_region(self.replica.map.region_dims(), eye);
        loop {
            let rule = self.replica.held().and_then(|h| h.rule()).copied();
            if self.replica.synced && self.replica.seq >= seq && rule.is_some_and(|r| r.eye == want)
            {
                return rule.unwrap();
            }
            if self.next().await.is_none() {
                panic!("closed while settling: {:?}", self.errors);
            }
        }
    }
}

/// The follower's map shows what a map built afresh for its rule from the scene shows: the
/// same level-0 bricks, and the same coarse brick in every region.
fn assert_holds_its_working_set(held: &BrickMap, scene: &BrickMap, rule: &Rule, what: &str) {
    let pyramid = Pyramid::build(scene).unwrap();
    let built = working_set::build(scene, &pyramid, rule).unwrap();
    held.check_invariants().unwrap();
    assert_eq!(held.brick_count(), built.brick_count(), "{what}: bricks");
    assert_eq!(held.content_hash(), built.content_hash(), "{what}: level 0");
    assert_eq!(
        held.stand_in_count(),
        built.stand_in_count(),
        "{what}: stand-ins"
    );
    let rd = built.region_dims();
    let (mut a, mut b) = ([Colour::BLACK; 512], [Colour::BLACK; 512]);
    for z in 0..rd[2] {
        for y in 0..rd[1] {
            for x in 0..rd[0] {
                let r = [x, y, z];
                match (held.stand_in(r), built.stand_in(r)) {
                    (None, None) => {}
                    (Some((ka, sa)), Some((kb, sb))) => {
                        assert_eq!(ka, kb, "{what}: region {r:?}");
                        assert_eq!(held.masks()[sa as usize], built.masks()[sb as usize]);
                        assert_eq!(
                            held.slot_colours(sa, &mut a),
                            built.slot_colours(sb, &mut b),
                            "{what}: region {r:?}"
                        );
                    }
                    other => panic!("{what}: region {r:?}: {other:?}"),
                }
            }
        }
    }
}

/// The bytes a working set with level 0 within `near` regions of `eye` takes.
fn cost_at(scene: &BrickMap, eye: [f32; 3], near: u32) -> u64 {
    let pyramid = Pyramid::build(scene).unwrap();
    working_set::cost(scene, &pyramid, &Rule::new(scene, &pyramid, eye, near)).bytes
}

async fn serve(dir: &std::path::Path) -> TestServer {
    TestServer::start(dir, |c| c.demo_size = SIZE).await
}

/// A client with a budget holds exactly its working set (level 0 near the eye, stand-ins
/// further away) within the budget; after edits near and far it still does, and the far edit
/// sent it no level-0 brick; after the camera moves it holds the working set there; after a
/// reconnect that resumes, it starts over and holds it again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_working_set_follows_the_camera_and_the_edits() {
    let dir = tempfile::tempdir().unwrap();
    let server = serve(dir.path()).await;
    let url = server.url("demo");
    let mut editor = Client::connect(&url, None).await.unwrap();
    editor.sync().await;

    // A budget that fits level 0 within 2 regions of the eye but not 3 (the server fits 7/8).
    let eye = [80.0, 40.0, 80.0];
    let (two, three) = (cost_at(&editor.map, eye, 2), cost_at(&editor.map, eye, 3));
    assert!(two < three, "{two} {three}");
    let budget = two * 8 / 7 + 8;
    assert!(budget * 7 / 8 < three);
    let mut follower = Follower::connect(&url, budget, Some(eye), None).await;
    let rule = follower.settle(eye, editor.seq).await;
    assert_eq!(rule.near, 2, "{rule:?}");
    assert_holds_its_working_set(&follower.replica.map, &editor.map, &rule, "first sync");
    assert!(
        follower.replica.map.stand_in_count() > 0,
        "far away is coarse"
    );
    assert!(follower.replica.map.memory().total_bytes <= budget);

    // An edit near the eye and one far away (a region held coarsely).
    let near = [90.0, 30.0, 90.0];
    let far = [460.0, 30.0, 470.0];
    let far_region = [14, 0, 14];
    assert_ne!(rule.level_of(far_region), 0);
    follower.delta_bricks.clear();
    let mut last = 0;
    for (i, centre) in [near, far].into_iter().enumerate() {
        let op = EditOp::Sphere {
            centre,
            radius: 6.0,
            mode: BrushMode::Fill,
            colour: colour(i as u32 + 7),
        };
        if let ServerMsg::Ack { seq: Some(seq), .. } = editor.edit(vec![op]).await {
            last = seq;
        }
    }
    editor.catch_up(last).await;
    follower.settle(eye, last).await;
    assert_holds_its_working_set(&follower.replica.map, &editor.map, &rule, "after edits");
    assert!(
        follower.delta_bricks.iter().any(|&r| rule.level_of(r) == 0),
        "the near edit came as level-0 bricks"
    );
    assert!(
        follower.delta_bricks.iter().all(|&r| rule.level_of(r) == 0),
        "no level-0 brick of a place held coarsely: {:?}",
        follower.delta_bricks
    );

    // The camera moves across the world.
    let there = [400.0, 40.0, 300.0];
    follower.camera(there).await;
    let moved = follower.settle(there, last).await;
    // Level 0 reaches as far as the budget allows there (no further than it was fitted).
    let fits = |near| cost_at(&editor.map, there, near) <= budget / 8 * 7;
    assert!(moved.near <= 2 && fits(moved.near), "{moved:?}");
    assert!(moved.near == 2 || !fits(moved.near + 1), "{moved:?}");
    assert_holds_its_working_set(&follower.replica.map, &editor.map, &moved, "after a move");
    let m = follower.replica.map.memory();
    let fresh = cost_at(&editor.map, there, 2);
    assert!(
        m.total_bytes <= budget,
        "{m:?} fresh {fresh} budget {budget}"
    );

    // A reconnect that resumes drops its copy and gets the working set again.
    let seq = follower.replica.seq;
    let _ = follower.ws.close(None).await;
    let replica = std::mem::replace(&mut follower.replica, Replica::new("x", [8, 8, 8]).unwrap());
    let mut back = Follower::connect(&url, budget, Some(there), Some((seq, replica))).await;
    let again = back.settle(there, seq).await;
    assert_holds_its_working_set(&back.replica.map, &editor.map, &again, "after a resume");
    server.shutdown().await.unwrap();
}

/// A client that states a budget but no eye (the page: it places its camera only once the
/// Welcome names the scene's size) is streamed first the working set around the eye a
/// viewer's first camera has (`Camera::overview`), so that camera's first report is no jump
/// that starts the sync over (on a 16k world the page waited 3.5 s for its first bytes).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_working_set_without_an_eye_starts_where_a_viewer_first_looks() {
    let dir = tempfile::tempdir().unwrap();
    let server = serve(dir.path()).await;
    let url = server.url("demo");
    let mut editor = Client::connect(&url, None).await.unwrap();
    editor.sync().await;
    let first = brickcast_protocol::Camera::overview(SIZE).eye;
    let budget = cost_at(&editor.map, first, 2) * 8 / 7 + 8;
    let mut follower = Follower::connect(&url, budget, None, None).await;
    let rule = loop {
        let msg = follower.next().await.expect("a working set");
        if matches!(msg, ServerMsg::Follow { .. }) {
            break follower.replica.held().and_then(|h| h.rule()).copied();
        }
    }
    .expect("a rule");
    let dims = follower.replica.map.region_dims();
    assert_eq!(rule.eye, Rule::eye_region(dims, first), "{rule:?}");
    // Its first camera report moves nothing: the working set completes where it started.
    follower.camera(first).await;
    let settled = follower.settle(first, editor.seq).await;
    assert_eq!(settled, rule);
    assert_holds_its_working_set(&follower.replica.map, &editor.map, &rule, "first sync");
    server.shutdown().await.unwrap();
}

/// A budget too small for any working set is refused with the bytes it would need, and a
/// budget at a level of detail is refused: both say why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn budgets_that_cannot_be_served_are_refused_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let server = serve(dir.path()).await;
    let mut tiny = Follower::connect(&server.url("demo"), 1000, None, None).await;
    while tiny.next().await.is_some() {}
    let (code, text) = tiny.errors.first().cloned().expect("an error");
    assert_eq!(code, ErrorCode::NotAllowed);
    assert!(text.contains("GPU budget of 1000 bytes"), "{text}");
    // A level of detail too large for the budget to hold whole: level views are served whole.
    let mut level = Follower::connect(&server.url("demo@2"), 1000, None, None).await;
    while level.next().await.is_some() {}
    let (code, text) = level.errors.first().cloned().expect("an error");
    assert_eq!(code, ErrorCode::NotAllowed);
    assert!(text.contains("level of detail"), "{text}");
    server.shutdown().await.unwrap();
}

/// A budget the whole scene fits with room to spare (every viewer states one by default) is
/// served the whole scene, as a client without a budget is: no working set, every brick, and
/// a level view likewise.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_budget_the_scene_fits_gets_the_whole_scene() {
    let dir = tempfile::tempdir().unwrap();
    let server = serve(dir.path()).await;
    let mut whole = Follower::connect(&server.url("demo"), 1 << 30, None, None).await;
    while !whole.replica.synced {
        let msg = whole.next().await.expect("the sync");
        assert!(!matches!(msg, ServerMsg::Follow { .. }), "a working set");
    }
    assert!(whole.replica.held().is_none());
    let bricks = whole.replica.map.brick_count();
    assert!(bricks > 0);
    let mut level = Follower::connect(&server.url("demo@2"), 1 << 30, None, None).await;
    while !level.replica.synced {
        assert!(level.next().await.is_some(), "{:?}", level.errors);
    }
    assert!(level.replica.held().is_none() && level.replica.map.brick_count() > 0);
    assert!(level.replica.map.brick_count() < bricks);
    server.shutdown().await.unwrap();
}
