//! The editing tools against a real server on loopback (issue #34): flood fill, face extrude
//! and intrude, boxes and lines between two rays, each resolved on the server's copy and seen
//! by another editor; a fill too large for its limit is refused and changes nothing; two
//! people filling one region at once end with one colour on every copy; a tool's edit is one
//! undo step.

mod common;

use brickcast_protocol::wire::{BrushMode, EditOp, RayAction, Rejection, ServerMsg, Shape};
use brickcast_protocol::{BrickMap, Colour};
use common::admin_cli::{admin, ok};
use common::{Client, TestServer, colour};

const ALICE: u64 = 0xa11ce;
const BOB: u64 = 0xb0b;

/// A ray straight down onto column (x, z).
fn down(x: u32, z: u32) -> ([f32; 3], [f32; 3]) {
    ([x as f32 + 0.5, 63.5, z as f32 + 0.5], [0.0, -1.0, 0.0])
}

fn ray(x: u32, z: u32, action: RayAction) -> EditOp {
    let (origin, dir) = down(x, z);
    EditOp::Ray {
        origin,
        dir,
        action,
    }
}

fn span(a: [u32; 2], b: [u32; 2], shape: Shape, mode: BrushMode, c: Colour) -> EditOp {
    let (from, from_dir) = down(a[0], a[1]);
    let (to, to_dir) = down(b[0], b[1]);
    EditOp::Span {
        from,
        from_dir,
        to,
        to_dir,
        shape,
        mode,
        colour: c,
        extent: 64,
    }
}

fn seq_of(ack: &ServerMsg) -> u64 {
    match ack {
        ServerMsg::Ack {
            seq: Some(s),
            rejected,
            ..
        } if rejected.is_empty() => *s,
        ServerMsg::Undone { seq: Some(s), .. } => *s,
        other => panic!("not applied whole: {other:?}"),
    }
}

/// Voxels of `map` in the box `lo..=hi` that have colour `c`.
fn count(map: &BrickMap, lo: [u32; 3], hi: [u32; 3], c: Option<Colour>) -> usize {
    let mut n = 0;
    for z in lo[2]..=hi[2] {
        for y in lo[1]..=hi[1] {
            for x in lo[0]..=hi[0] {
                n += usize::from(map.get([x, y, z]) == c);
            }
        }
    }
    n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_tool_resolves_on_the_server_and_every_copy_agrees() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    ok(&admin(
        server.addr,
        &["create", "tools", "--size", "64,64,64"],
        None,
    )
    .await);
    let url = server.url("tools");
    let mut alice = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    let mut bob = Client::as_user(&url, None, BOB, "bob").await.unwrap();
    alice.sync().await;
    bob.sync().await;
    let (white, red, blue) = (colour(7), colour(1), colour(5));

    // A white floor with a red 4×4 patch.
    let floor = alice
        .edit(vec![
            EditOp::Box {
                min: [0, 0, 0],
                max: [63, 0, 63],
                mode: BrushMode::Fill,
                colour: white,
            },
            EditOp::Box {
                min: [10, 0, 10],
                max: [13, 0, 13],
                mode: BrushMode::Paint,
                colour: red,
            },
        ])
        .await;
    seq_of(&floor);

    // Fill: the patch turns blue on Bob's copy too; the floor around it stays white.
    let fill = alice
        .edit(vec![ray(
            11,
            11,
            RayAction::Fill {
                colour: blue,
                limit: 16,
            },
        )])
        .await;
    let filled = seq_of(&fill);
    bob.catch_up(filled).await;
    alice.catch_up(filled).await;
    assert_eq!(count(&bob.map, [10, 0, 10], [13, 0, 13], Some(blue)), 16);
    assert_eq!(bob.map.get([14, 0, 13]), Some(white));

    // A fill of the whole floor with a limit of 100 is refused and changes nothing.
    let before = alice.map.content_hash();
    let refused = alice
        .edit(vec![ray(
            40,
            40,
            RayAction::Fill {
                colour: red,
                limit: 100,
            },
        )])
        .await;
    let ServerMsg::Ack { seq, rejected, .. } = &refused else {
        panic!("{refused:?}")
    };
    assert_eq!(*seq, None, "{refused:?}");
    assert_eq!(rejected[0].reason, Rejection::TooLarge);
    assert_eq!(alice.map.content_hash(), before);

    // Extrude: the blue patch grows a blue layer; Bob sees it.
    let extrude = alice
        .edit(vec![ray(
            12,
            12,
            RayAction::Extrude {
                out: true,
                limit: 1000,
            },
        )])
        .await;
    bob.catch_up(seq_of(&extrude)).await;
    assert_eq!(count(&bob.map, [10, 1, 10], [13, 1, 13], Some(blue)), 16);

    // Bob drags a red box on the floor and erases a line through it.
    let boxed = bob
        .edit(vec![span(
            [30, 30],
            [34, 32],
            Shape::Box,
            BrushMode::Fill,
            red,
        )])
        .await;
    alice.catch_up(seq_of(&boxed)).await;
    assert_eq!(count(&alice.map, [30, 1, 30], [34, 1, 32], Some(red)), 15);
    let line = bob
        .edit(vec![span(
            [30, 30],
            [34, 30],
            Shape::Line,
            BrushMode::Erase,
            red,
        )])
        .await;
    alice.catch_up(seq_of(&line)).await;
    assert_eq!(count(&alice.map, [30, 1, 30], [34, 1, 30], None), 5);
    assert_eq!(count(&alice.map, [30, 1, 31], [34, 1, 32], Some(red)), 10);

    // Both fill Bob's box at once, in different colours: the fill ordered second recolours
    // the region as the first left it, so one colour wins on every copy.
    let (green, yellow) = (colour(2), colour(3));
    let a = alice
        .send_edit(vec![ray(
            32,
            31,
            RayAction::Fill {
                colour: green,
                limit: 100,
            },
        )])
        .await;
    let b = bob
        .send_edit(vec![ray(
            32,
            32,
            RayAction::Fill {
                colour: yellow,
                limit: 100,
            },
        )])
        .await;
    let (a, b) = (seq_of(&alice.ack(a).await), seq_of(&bob.ack(b).await));
    let last = a.max(b);
    alice.catch_up(last).await;
    bob.catch_up(last).await;
    assert_eq!(alice.map.content_hash(), bob.map.content_hash());
    let winner = if b > a { yellow } else { green };
    assert_eq!(count(&bob.map, [30, 1, 31], [34, 1, 32], Some(winner)), 10);

    // Each tool's edit is one undo step: Alice's first undo takes back her fill (what Bob's
    // fill changed since stays his), her second the whole extruded layer.
    let first = alice.undo(false).await;
    assert!(matches!(first, ServerMsg::Undone { .. }), "{first:?}");
    let second = seq_of(&alice.undo(false).await);
    bob.catch_up(second).await;
    assert_eq!(
        count(&bob.map, [10, 1, 10], [13, 1, 13], None),
        16,
        "the extruded layer is gone"
    );
    let mut fresh = Client::connect(&url, None).await.unwrap();
    fresh.sync().await;
    assert_eq!(fresh.map.content_hash(), bob.map.content_hash());
    server.shutdown().await.unwrap();
}

/// The scene's shared palette: a swatch Alice sets reaches Bob and every later client, is no
/// undo step (Alice's undo takes back her voxel, not the swatch), a swatch that does not exist
/// is refused, and the palette survives restarts (the store's own test replays it from the
/// log as well).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_palette_is_shared_kept_with_the_scene_and_no_undo_step() {
    use brickcast_protocol::swatches::{SWATCHES, Swatches};
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    ok(&admin(server.addr, &["create", "pal", "--size", "64,64,64"], None).await);
    let url = server.url("pal");
    let mut alice = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    let mut bob = Client::as_user(&url, None, BOB, "bob").await.unwrap();
    alice.sync().await;
    bob.sync().await;
    assert_eq!(bob.map.swatches(), &Swatches::default());
    let teal = Colour::from_rgb8(0, 128, 128);

    let voxel = alice
        .edit(vec![EditOp::Set {
            pos: [3, 3, 3],
            colour: teal,
        }])
        .await;
    seq_of(&voxel);
    let set = alice
        .edit(vec![EditOp::Swatch {
            index: 2,
            colour: teal,
        }])
        .await;
    let set = seq_of(&set);
    assert!(
        bob.until(|c, _| c.map.swatches().get(2) == teal).await,
        "bob hears the palette"
    );
    bob.catch_up(set).await;
    let refused = alice
        .edit(vec![EditOp::Swatch {
            index: SWATCHES as u8,
            colour: teal,
        }])
        .await;
    let ServerMsg::Ack { seq, rejected, .. } = &refused else {
        panic!("{refused:?}")
    };
    assert_eq!(*seq, None);
    assert!(
        matches!(rejected[0].reason, Rejection::Malformed(_)),
        "{refused:?}"
    );

    // Undo takes back the voxel (the step before the swatch), not the swatch.
    let undone = seq_of(&alice.undo(false).await);
    bob.catch_up(undone).await;
    assert_eq!(bob.map.get([3, 3, 3]), None);
    assert_eq!(bob.map.swatches().get(2), teal);
    let mut expected = Swatches::default();
    expected.set(2, teal);
    server.shutdown().await.unwrap();

    // Restarted (the shutdown snapshotted): a new client gets the palette after its Welcome.
    let server = TestServer::start(data.path(), |_| {}).await;
    let url = server.url("pal");
    let mut carol = Client::connect(&url, None).await.unwrap();
    carol.sync().await;
    assert_eq!(carol.map.swatches(), &expected);
    let red = Colour::from_rgb8(255, 0, 0);
    let last = carol
        .edit(vec![EditOp::Swatch {
            index: (SWATCHES - 1) as u8,
            colour: red,
        }])
        .await;
    seq_of(&last);
    expected.set(SWATCHES - 1, red);
    drop(carol);
    server.shutdown().await.unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let mut dave = Client::connect(&server.url("pal"), None).await.unwrap();
    dave.sync().await;
    assert_eq!(dave.map.swatches(), &expected);
    server.shutdown().await.unwrap();
}

/// Copy and paste through the server: Alice copies a box, pastes it turned elsewhere (Bob sees
/// it), Bob paints a pasted voxel, Alice's undo takes the paste back but leaves Bob's voxel;
/// her clipboard pastes into another scene of the server; a paste of the wrong size, one with
/// nothing copied and one not alone in its message are refused; a cut and a paste move a shape
/// and two undos put it back; the pasted scene survives a restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn copy_and_paste_within_a_scene_and_into_another() {
    use brickcast_protocol::clipboard::Clipboard;
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    for name in ["cp", "other"] {
        ok(&admin(server.addr, &["create", name, "--size", "64,64,64"], None).await);
    }
    let url = server.url("cp");
    let mut alice = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    let mut bob = Client::as_user(&url, None, BOB, "bob").await.unwrap();
    alice.sync().await;
    bob.sync().await;
    let (red, blue, green, yellow) = (colour(1), colour(5), colour(4), colour(3));
    let set = |pos, colour| EditOp::Set { pos, colour };
    let built = alice
        .edit(vec![
            set([10, 1, 10], red),
            set([11, 1, 10], red),
            set([10, 2, 10], blue),
            set([10, 1, 11], green),
        ])
        .await;
    seq_of(&built);
    let copied = alice
        .edit(vec![EditOp::Copy {
            min: [10, 1, 10],
            max: [11, 2, 11],
        }])
        .await;
    seq_of(&copied);
    let before = alice.map.clone();
    let clip = Clipboard::copy(&before, [10, 1, 10], [11, 2, 11]);
    let paste = |at, size, turns| EditOp::Paste {
        at,
        size,
        turns,
        mirror: false,
    };

    // Turned a quarter: (x, z) → (z, 1 − x) in the 2×2×2 box at (30, 1, 30).
    let pasted = seq_of(&alice.edit(vec![paste([30, 1, 30], [2, 2, 2], 1)]).await);
    bob.catch_up(pasted).await;
    let mut want = before.clone();
    for b in clip.paste(&before, [30, 1, 30], 1, false) {
        want.put_brick(&b).unwrap();
    }
    assert_eq!(bob.map.content_hash(), want.content_hash());
    assert_eq!(bob.map.get([30, 2, 31]), Some(blue), "(0,1,0) turned");
    assert_eq!(bob.map.get([30, 1, 30]), Some(red), "(1,0,0) turned");
    assert_eq!(bob.map.get([31, 1, 31]), Some(green), "(0,0,1) turned");

    // Bob paints a pasted voxel; Alice's undo takes her paste back, his voxel stays.
    let painted = seq_of(
        &bob.edit(vec![EditOp::Paint {
            pos: [30, 2, 31],
            colour: yellow,
        }])
        .await,
    );
    alice.catch_up(painted).await;
    let undone = seq_of(&alice.undo(false).await);
    bob.catch_up(undone).await;
    assert_eq!(bob.map.get([31, 1, 31]), None, "the paste is undone");
    assert_eq!(bob.map.get([30, 1, 30]), None);
    assert_eq!(
        bob.map.get([30, 2, 31]),
        Some(yellow),
        "bob's later change wins"
    );
    assert_eq!(
        bob.map.get([10, 2, 10]),
        Some(blue),
        "the copied voxels stay"
    );

    // Refused: the wrong size, nothing copied (Bob), a paste with another op.
    let refused = |reply: &ServerMsg| match reply {
        ServerMsg::Ack { rejected, .. } => rejected
            .iter()
            .any(|r| matches!(r.reason, Rejection::Malformed(_))),
        _ => false,
    };
    let wrong = alice.edit(vec![paste([30, 1, 30], [2, 2, 3], 1)]).await;
    assert!(refused(&wrong), "{wrong:?}");
    let none = bob.edit(vec![paste([30, 1, 30], [2, 2, 2], 0)]).await;
    assert!(refused(&none), "{none:?}");
    let mixed = alice
        .edit(vec![
            paste([40, 1, 40], [2, 2, 2], 0),
            set([50, 1, 50], red),
        ])
        .await;
    assert!(refused(&mixed), "{mixed:?}");
    let ServerMsg::Ack { applied, .. } = mixed else {
        unreachable!()
    };
    assert_eq!(applied, 1, "the other op applies");

    // Into another scene of the server, unturned.
    let mut there = Client::as_user(&server.url("other"), None, ALICE, "alice")
        .await
        .unwrap();
    there.sync().await;
    let into = seq_of(&there.edit(vec![paste([5, 1, 5], [2, 2, 2], 0)]).await);
    there.catch_up(into).await;
    assert_eq!(there.map.get([5, 2, 5]), Some(blue));
    assert_eq!(there.map.get([6, 1, 5]), Some(red));
    assert_eq!(there.map.get([5, 1, 6]), Some(green));

    // A cut (what Ctrl+X sends: the copy and the erase in one message) and a paste move the
    // shape; two undos put it back where it was.
    let cut = alice
        .edit(vec![
            EditOp::Copy {
                min: [10, 1, 10],
                max: [11, 2, 11],
            },
            EditOp::Box {
                min: [10, 1, 10],
                max: [11, 2, 11],
                mode: BrushMode::Erase,
                colour: red,
            },
        ])
        .await;
    seq_of(&cut);
    let moved = seq_of(&alice.edit(vec![paste([40, 1, 40], [2, 2, 2], 0)]).await);
    bob.catch_up(moved).await;
    assert_eq!(bob.map.get([10, 2, 10]), None, "cut");
    assert_eq!(bob.map.get([40, 2, 40]), Some(blue), "moved");
    alice.undo(false).await;
    let back = seq_of(&alice.undo(false).await);
    bob.catch_up(back).await;
    assert_eq!(bob.map.get([10, 2, 10]), Some(blue), "the cut is undone");
    assert_eq!(bob.map.get([40, 2, 40]), None, "the paste is undone");

    // Pasted again, then a restart: the scene comes back as it was.
    let again = seq_of(&alice.edit(vec![paste([20, 1, 20], [2, 2, 2], 2)]).await);
    bob.catch_up(again).await;
    let hash = bob.map.content_hash();
    drop((alice, bob, there));
    server.shutdown().await.unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let mut fresh = Client::connect(&server.url("cp"), None).await.unwrap();
    fresh.sync().await;
    assert_eq!(fresh.map.content_hash(), hash);
    server.shutdown().await.unwrap();
}

/// The scene's history (issue #34, item 3): the timeline says who changed what where, across
/// a restart (whose snapshot keeps the past); a view of an earlier sequence (`NAME~S`) shows
/// the scene as it was and takes no edits; a restore of a box to that sequence writes it as
/// it was, leaves the rest of the scene, is one undo step that others' later edits win over,
/// orders with an edit Bob sends at the same time, and survives a restart. A sequence the
/// store does not keep is refused, saying what it keeps.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_past_is_listed_viewed_and_restored() {
    use common::http_get;
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    ok(&admin(server.addr, &["create", "h", "--size", "64,64,64"], None).await);
    let url = server.url("h");
    let mut alice = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    let mut bob = Client::as_user(&url, None, BOB, "bob").await.unwrap();
    alice.sync().await;
    bob.sync().await;
    let (red, blue, yellow) = (colour(1), colour(5), colour(3));
    let wall = EditOp::Box {
        min: [10, 1, 10],
        max: [20, 8, 11],
        mode: BrushMode::Fill,
        colour: red,
    };
    seq_of(&alice.edit(vec![wall]).await);
    let good = seq_of(
        &bob.edit(vec![EditOp::Paint {
            pos: [15, 8, 10],
            colour: blue,
        }])
        .await,
    );
    alice.catch_up(good).await;
    let then = alice.map.clone();
    drop((alice, bob));
    // A restart: the shutdown's snapshot keeps what it folds in.
    server.shutdown().await.unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let mut alice = Client::as_user(&server.url("h"), None, ALICE, "alice")
        .await
        .unwrap();
    let mut bob = Client::as_user(&server.url("h"), None, BOB, "bob")
        .await
        .unwrap();
    alice.sync().await;
    bob.sync().await;
    // Alice knocks a hole in the wall; Bob builds a post elsewhere.
    seq_of(
        &alice
            .edit(vec![EditOp::Box {
                min: [12, 3, 10],
                max: [17, 8, 11],
                mode: BrushMode::Erase,
                colour: red,
            }])
            .await,
    );
    let post = seq_of(
        &bob.edit(vec![EditOp::Box {
            min: [40, 1, 40],
            max: [40, 6, 40],
            mode: BrushMode::Fill,
            colour: yellow,
        }])
        .await,
    );
    alice.catch_up(post).await;

    // The timeline: the wall (Alice), the paint (Bob), the hole (Alice), the post (Bob).
    let (status, body) = http_get(server.addr, "/scenes/h/history").await;
    assert_eq!(status, 200, "{body}");
    let timeline: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(timeline["oldest"], 0, "{body}");
    assert_eq!(timeline["newest"], post, "{body}");
    let changes = timeline["changes"].as_array().unwrap();
    let who: Vec<(u64, u64)> = changes
        .iter()
        .map(|c| {
            let user = c["user"].as_str().unwrap().parse().unwrap();
            (c["first"].as_u64().unwrap(), user)
        })
        .collect();
    assert_eq!(
        who,
        vec![(1, ALICE), (2, BOB), (3, ALICE), (4, BOB)],
        "{body}"
    );
    assert_eq!(changes[3]["min"], serde_json::json!([40, 0, 40]), "{body}");
    assert!(changes.iter().all(|c| c["at_ms"].as_u64().is_some()));

    // The scene as it was at `good`: read-only.
    let mut past = Client::connect(&server.url(&format!("h~{good}")), None)
        .await
        .unwrap();
    past.sync().await;
    assert_eq!(past.map.content_hash(), then.content_hash());
    let refused = past.edit(vec![EditOp::Set {
        pos: [1, 1, 1],
        colour: red,
    }]);
    let ServerMsg::Ack {
        seq: None,
        rejected,
        ..
    } = refused.await
    else {
        panic!("a view of the past took an edit")
    };
    assert_eq!(rejected[0].reason, Rejection::NotAllowed);
    // Not kept: a 404 that says what is.
    let (status, body) = http_get(server.addr, "/scenes/h~999/ws").await;
    assert_eq!(status, 404);
    assert!(body.contains("from sequence 0 to 4"), "{body}");

    // Alice restores the wall's box to `good` while Bob paints inside it at the same time.
    let region = ([10, 0, 10], [20, 10, 11]);
    let restore = EditOp::Restore {
        to: good,
        min: region.0,
        max: region.1,
    };
    let now = alice.map.clone();
    let a = alice.send_edit(vec![restore]).await;
    let paint = [13, 5, 10];
    let b = bob
        .send_edit(vec![EditOp::Set {
            pos: paint,
            colour: yellow,
        }])
        .await;
    let restored = seq_of(&alice.ack(a).await);
    let painted = seq_of(&bob.ack(b).await);
    bob.catch_up(restored.max(painted)).await;
    let inside = |p: [u32; 3]| (0..3).all(|i| region.0[i] <= p[i] && p[i] <= region.1[i]);
    for p in near_the_wall() {
        // In the box: as it was, unless Bob's paint came after the restore.
        let want = if p == paint && painted > restored {
            Some(yellow)
        } else if inside(p) {
            then.get(p)
        } else {
            now.get(p)
        };
        assert_eq!(
            bob.map.get(p),
            want,
            "{p:?} (restored {restored}, painted {painted})"
        );
    }
    assert_eq!(
        bob.map.get([40, 6, 40]),
        Some(yellow),
        "outside the box: kept"
    );

    // Bob paints in the restored wall; Alice's undo takes the restore back, his paint stays.
    let later = seq_of(
        &bob.edit(vec![EditOp::Paint {
            pos: [12, 8, 11],
            colour: blue,
        }])
        .await,
    );
    alice.catch_up(later).await;
    let undone = seq_of(&alice.undo(false).await);
    bob.catch_up(undone).await;
    assert_eq!(bob.map.get([14, 6, 10]), None, "the hole is back");
    assert_eq!(
        bob.map.get([12, 8, 11]),
        Some(blue),
        "Bob's later paint wins"
    );
    let redone = seq_of(&alice.undo(true).await);
    bob.catch_up(redone).await;
    assert_eq!(bob.map.get([14, 6, 10]), Some(red), "redone");

    // A box past the scene is refused as such, at once (its past is never fetched).
    let huge = alice
        .edit(vec![EditOp::Restore {
            to: good,
            min: [0; 3],
            max: [u32::MAX; 3],
        }])
        .await;
    let ServerMsg::Ack {
        seq: None,
        rejected,
        ..
    } = &huge
    else {
        panic!("{huge:?}")
    };
    assert_eq!(rejected[0].reason, Rejection::OutOfBounds);
    // A sequence the store does not keep: refused, saying what it keeps.
    let far = alice
        .edit(vec![EditOp::Restore {
            to: 9_999,
            min: region.0,
            max: region.1,
        }])
        .await;
    let ServerMsg::Ack {
        seq: None,
        rejected,
        ..
    } = &far
    else {
        panic!("{far:?}")
    };
    assert!(
        matches!(&rejected[0].reason, Rejection::Malformed(m) if m.contains("keeps its history from sequence 0")),
        "{far:?}"
    );
    // The timeline names the restore; a restart keeps the restored scene.
    let (_, body) = http_get(server.addr, "/scenes/h/history").await;
    assert!(body.contains("\"restore\""), "{body}");
    let hash = bob.map.content_hash();
    drop((alice, bob, past));
    server.shutdown().await.unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let mut fresh = Client::connect(&server.url("h"), None).await.unwrap();
    fresh.sync().await;
    assert_eq!(fresh.map.content_hash(), hash);
    server.shutdown().await.unwrap();
}

/// The voxels around the wall of the history test.
fn near_the_wall() -> impl Iterator<Item = [u32; 3]> {
    (0..12).flat_map(|y| (8..24).flat_map(move |z| (8..24).map(move |x| [x, y, z])))
}
