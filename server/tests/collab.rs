//! Collaboration against a real server on loopback: per-user undo and redo (only what nobody
//! changed since goes back), history across reconnects and its bound, refusals that keep the
//! connection, and presence (who is here, where they look, who left).

mod common;

use std::time::Duration;

use brickcast_protocol::wire::{
    BrushMode, ClientMsg, Cursor, EditOp, Refusal, Role, Selection, ServerMsg, View,
};
use brickcast_protocol::{BrickMap, Colour};
use common::{Client, TestServer, colour, http_get};

const ALICE: u64 = 0xa11ce;
const BOB: u64 = 0xb0b;

fn set(pos: [u32; 3], c: u32) -> EditOp {
    EditOp::Set {
        pos,
        colour: colour(c),
    }
}

/// The undo reply's (seq is some, restored, kept, refused).
fn outcome(reply: &ServerMsg) -> (bool, u64, u64, Option<Refusal>) {
    match reply {
        ServerMsg::Undone {
            seq,
            restored,
            kept,
            refused,
            ..
        } => (seq.is_some(), *restored, *kept, refused.clone()),
        other => panic!("expected Undone, got {other:?}"),
    }
}

fn seq_of(ack: &ServerMsg) -> u64 {
    match ack {
        ServerMsg::Ack { seq: Some(s), .. } => *s,
        ServerMsg::Undone { seq: Some(s), .. } => *s,
        other => panic!("nothing applied: {other:?}"),
    }
}

/// A fresh client's copy: the server's scene as it is now.
async fn server_map(server: &TestServer) -> BrickMap {
    let mut fresh = Client::connect(&server.url("demo"), None).await.unwrap();
    fresh.sync().await;
    let map = fresh.map.clone();
    fresh.close().await;
    map
}

async fn caught_up(clients: &mut [&mut Client], seq: u64) {
    for c in clients {
        c.catch_up(seq).await;
    }
}

#[tokio::test]
async fn undo_reverts_only_what_nobody_changed_since_and_redo_puts_it_back() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let url = server.url("demo");
    let mut a = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    let mut b = Client::as_user(&url, None, BOB, "bob").await.unwrap();
    a.sync().await;
    b.sync().await;
    let before = server_map(&server).await;

    // Alice sets three voxels in one message; Bob repaints one of them and clears another.
    let (x, y, z) = ([10, 40, 10], [11, 40, 10], [100, 50, 100]);
    a.edit(vec![set(x, 1), set(y, 1), set(z, 1)]).await;
    let seq = seq_of(&b.edit(vec![set(y, 2), EditOp::Clear { pos: z }]).await);
    caught_up(&mut [&mut a, &mut b], seq).await;

    let undo = a.undo(false).await;
    assert_eq!(outcome(&undo), (true, 1, 2, None), "{undo:?}");
    let seq = seq_of(&undo);
    caught_up(&mut [&mut a, &mut b], seq).await;
    assert_eq!(a.map.get(x), before.get(x), "alice's voxel went back");
    assert_eq!(a.map.get(y), Some(colour(2)), "bob's paint stays");
    assert_eq!(a.map.get(z), None, "bob's clear stays");
    let server_now = server_map(&server).await;
    for map in [&a.map, &b.map] {
        assert_eq!(map.content_hash(), server_now.content_hash());
    }

    // Redo puts back what the undo restored.
    let redo = a.undo(true).await;
    assert_eq!(outcome(&redo), (true, 1, 0, None), "{redo:?}");
    caught_up(&mut [&mut a, &mut b], seq_of(&redo)).await;
    assert_eq!(b.map.get(x), Some(colour(1)));

    // Undo again, then a new edit clears the redo stack.
    seq_of(&a.undo(false).await);
    a.edit(vec![set([20, 40, 20], 3)]).await;
    let refused = a.undo(true).await;
    assert_eq!(outcome(&refused).3, Some(Refusal::NothingToRedo));

    // Bob's own history is his: his undo takes back his paint and clear only.
    let bob_undo = b.undo(false).await;
    assert_eq!(outcome(&bob_undo), (true, 2, 0, None), "{bob_undo:?}");
    caught_up(&mut [&mut a, &mut b], seq_of(&bob_undo)).await;
    assert_eq!(
        b.map.get(z),
        Some(colour(1)),
        "alice's voxel is back under bob's clear"
    );

    // Someone with no history.
    let mut c = Client::as_user(&url, None, 0xc, "carol").await.unwrap();
    assert_eq!(
        outcome(&c.undo(false).await).3,
        Some(Refusal::NothingToUndo)
    );
    assert_eq!(outcome(&c.undo(true).await).3, Some(Refusal::NothingToRedo));

    let server_now = server_map(&server).await;
    let last = server_now.sequence();
    caught_up(&mut [&mut a, &mut b, &mut c], last).await;
    for map in [&a.map, &b.map, &c.map] {
        assert_eq!(map.content_hash(), server_now.content_hash());
    }
    let (_, metrics) = http_get(server.addr, "/metrics").await;
    assert!(metrics.contains("brickcast_undos_total 3"), "{metrics}");
    assert!(metrics.contains("brickcast_redos_total 1"), "{metrics}");
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn a_sphere_of_radius_32_undoes_exactly_and_history_outlives_connections() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let url = server.url("demo");
    let mut a = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    a.sync().await;
    let before = a.map.content_hash();
    let brush = EditOp::Sphere {
        centre: [64.0, 32.0, 64.0],
        radius: 32.0,
        mode: BrushMode::Fill,
        colour: Colour::from_rgb8(200, 30, 30),
    };
    let seq = seq_of(&a.edit(vec![brush]).await);
    a.catch_up(seq).await;
    let filled = a.map.content_hash();
    assert_ne!(filled, before);
    a.close().await;

    // Reconnected (same user id): the history is still there.
    let mut a = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    a.sync().await;
    let undo = a.undo(false).await;
    let (changed, restored, kept, refused) = outcome(&undo);
    assert!(
        changed && restored > 100_000 && kept == 0 && refused.is_none(),
        "{undo:?}"
    );
    a.catch_up(seq_of(&undo)).await;
    assert_eq!(a.map.content_hash(), before);
    let redo = a.undo(true).await;
    a.catch_up(seq_of(&redo)).await;
    assert_eq!(a.map.content_hash(), filled);
    assert_eq!(server_map(&server).await.content_hash(), filled);

    // A clean restart keeps every user's history.
    a.close().await;
    server.shutdown().await.unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let mut a = Client::as_user(&server.url("demo"), None, ALICE, "alice")
        .await
        .unwrap();
    a.sync().await;
    let undo = a.undo(false).await;
    a.catch_up(seq_of(&undo)).await;
    assert_eq!(a.map.content_hash(), before);

    // A connection without a user id keeps its history only while it stays.
    let mut guest = Client::connect(&server.url("demo"), None).await.unwrap();
    guest.sync().await;
    guest.edit(vec![set([1, 60, 1], 5)]).await;
    guest.close().await;
    let mut guest = Client::connect(&server.url("demo"), None).await.unwrap();
    assert_eq!(
        outcome(&guest.undo(false).await).3,
        Some(Refusal::NothingToUndo)
    );

    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn the_history_bound_drops_the_oldest_step_and_viewers_cannot_undo() {
    let data = tempfile::tempdir().unwrap();
    let auth = data.path().join("auth");
    std::fs::write(&auth, "ed editor Alice Liddell\nlook viewer\n").unwrap();
    let server = TestServer::start(data.path(), |c| {
        c.owner.limits.max_undo_steps = 3;
        c.auth = brickcast_server::auth::Auth::from_file(&auth).unwrap();
    })
    .await;
    let url = server.url("demo");
    let mut a = Client::as_user(&url, Some("ed"), 42, "ignored")
        .await
        .unwrap();
    assert_eq!(a.roster.you.as_ref().unwrap().name, "Alice Liddell");
    a.sync().await;
    for i in 0..5 {
        a.edit(vec![set([30 + i, 45, 30], i)]).await;
    }
    for _ in 0..3 {
        assert_eq!(outcome(&a.undo(false).await).3, None);
    }
    assert_eq!(
        outcome(&a.undo(false).await).3,
        Some(Refusal::NothingToUndo)
    );
    let map = server_map(&server).await;
    assert_eq!(
        map.get([30, 45, 30]),
        Some(colour(0)),
        "the oldest steps stay applied"
    );
    assert_eq!(map.get([31, 45, 30]), Some(colour(1)));
    assert_eq!(map.get([32, 45, 30]), None);

    // A token names the user: the same person on another connection has the same history
    // (redo of what the first connection undid), whatever id the client sends.
    let mut again = Client::as_user(&url, Some("ed"), 7, "x").await.unwrap();
    assert_eq!(outcome(&again.undo(true).await), (true, 1, 0, None));

    let mut viewer = Client::as_user(&url, Some("look"), 42, "v").await.unwrap();
    assert_eq!(viewer.role, Role::Viewer);
    assert_eq!(
        outcome(&viewer.undo(false).await).3,
        Some(Refusal::NotAllowed)
    );
    // A client without a token cannot claim the token user's id.
    let mut claim = Client::as_user(&url, None, a.roster.you.as_ref().unwrap().user, "m")
        .await
        .unwrap();
    assert_ne!(
        claim.roster.you.as_ref().unwrap().user,
        a.roster.you.as_ref().unwrap().user
    );
    assert_eq!(
        outcome(&claim.undo(false).await).3,
        Some(Refusal::NotAllowed)
    );
    server.shutdown().await.unwrap();
}

/// User ids come from clients (without `--auth`), so made-up ids must not grow a scene's
/// history past its cap: the longest idle users' steps go first, the newest stay undoable, and
/// the trimmed history is what a restart finds.
#[tokio::test]
async fn made_up_ids_cannot_grow_a_scenes_history_past_its_cap() {
    const CAP: u64 = 48 << 10;
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |c| c.owner.max_history_bytes = CAP).await;
    let url = server.url("demo");
    let sphere = |i: u32| EditOp::Sphere {
        centre: [
            8.0 + (i % 12) as f32 * 10.0,
            40.0,
            8.0 + (i / 12) as f32 * 10.0,
        ],
        radius: 6.0,
        mode: BrushMode::Fill,
        colour: colour(i),
    };
    let mut alice = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    let ack = alice.edit(vec![sphere(0)]).await;
    assert!(matches!(ack, ServerMsg::Ack { applied: 1, .. }), "{ack:?}");
    for i in 1..=60u32 {
        let mut c = Client::as_user(&url, None, 1000 + u64::from(i), "made up")
            .await
            .unwrap();
        c.edit(vec![sphere(i)]).await;
        c.close().await;
    }
    let bytes = common::metric(server.addr, "brickcast_scene_history_bytes{scene=\"demo\"}").await;
    let users = common::metric(server.addr, "brickcast_scene_history_users{scene=\"demo\"}").await;
    assert!(bytes as u64 <= CAP, "{bytes} bytes of history");
    assert!((2.0..61.0).contains(&users), "{users} users with history");
    // Alice was idle longest: her step went. The newest user's step stays.
    assert_eq!(
        outcome(&alice.undo(false).await).3,
        Some(Refusal::NothingToUndo)
    );
    alice.close().await;
    let mut last = Client::as_user(&url, None, 1060, "made up").await.unwrap();
    assert_eq!(outcome(&last.undo(false).await).3, None);
    last.close().await;
    server.shutdown().await.unwrap();

    let server = TestServer::start(data.path(), |c| c.owner.max_history_bytes = CAP).await;
    let mut c = Client::connect(&server.url("demo"), None).await.unwrap();
    c.sync().await;
    let after = common::metric(server.addr, "brickcast_scene_history_bytes{scene=\"demo\"}").await;
    // (The undo above pushed its record on the redo stack, so a few bytes more than before.)
    assert!(
        after as u64 <= CAP && after > 0.0,
        "{after} bytes of history after a restart, {bytes} before the last undo"
    );
    server.shutdown().await.unwrap();
}

/// One address may bring only so many lasting ids (`--ids-per-address`): a further id's steps
/// are undoable while it is connected and go when it leaves; ids it brought before keep theirs.
#[tokio::test]
async fn ids_over_an_addresss_allowance_keep_their_history_only_while_connected() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |c| c.ids_per_address = 2).await;
    let url = server.url("demo");
    for user in 1..=3u32 {
        let mut c = Client::as_user(&url, None, u64::from(user), "someone")
            .await
            .unwrap();
        let ack = c.edit(vec![set([user, 60, 3], user)]).await;
        assert!(matches!(ack, ServerMsg::Ack { applied: 1, .. }), "{ack:?}");
        if user == 3 {
            // Over the allowance, yet its step is undoable while it stays.
            assert_eq!(outcome(&c.undo(false).await).3, None);
            assert_eq!(outcome(&c.undo(true).await).3, None);
        }
        c.close().await;
    }
    let over = common::metric(server.addr, "brickcast_ids_over_allowance_total").await;
    assert_eq!(over, 1.0);
    // The owner forgets user 3's history once it handles its Leave.
    let users = "brickcast_scene_history_users{scene=\"demo\"}";
    let mut left = common::metric(server.addr, users).await;
    for _ in 0..500 {
        if left == 2.0 {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        left = common::metric(server.addr, users).await;
    }
    assert_eq!(left, 2.0, "users with history");
    // User 3's history went with its connection; users 1 and 2 keep theirs.
    let mut third = Client::as_user(&url, None, 3, "someone").await.unwrap();
    assert_eq!(
        outcome(&third.undo(false).await).3,
        Some(Refusal::NothingToUndo)
    );
    third.close().await;
    let mut first = Client::as_user(&url, None, 1, "someone").await.unwrap();
    assert_eq!(outcome(&first.undo(false).await).3, None);
    first.close().await;
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn presence_shows_who_is_here_where_they_look_and_who_left() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let url = server.url("demo");
    let mut a = Client::as_user(&url, None, ALICE, "alice").await.unwrap();
    a.sync().await;
    let mut b = Client::as_user(&url, None, BOB, "bob").await.unwrap();
    let alice = a.roster.you.clone().unwrap();
    assert!(
        b.roster.others.contains_key(&alice.id),
        "bob's Welcome lists alice"
    );
    b.sync().await;

    let view = View {
        eye: [64.0, 80.0, -20.0],
        forward: [0.0, -0.5, 1.0],
    };
    let cursor = Cursor {
        voxel: [64, 20, 64],
        radius: 3.0,
    };
    let selection = Selection::between([70, 20, 60], [60, 24, 66]);
    a.send(&ClientMsg::Presence {
        view: Some(view),
        cursor: Some(cursor),
        selection: Some(selection),
    })
    .await;
    let seen = tokio::time::timeout(
        Duration::from_secs(20),
        b.until(|b, _| {
            b.roster.others.get(&alice.id).is_some_and(|p| {
                p.state.view == Some(view)
                    && p.state.cursor == Some(cursor)
                    && p.state.selection == Some(selection)
            })
        }),
    )
    .await;
    assert_eq!(
        seen,
        Ok(true),
        "bob never saw alice's view, cursor and selection"
    );
    assert_eq!(b.roster.others[&alice.id].peer.name, "alice");

    // A rename reaches the others; a bad one is refused and the connection stays.
    a.send(&ClientMsg::Rename {
        name: "Alice".into(),
    })
    .await;
    assert!(
        b.until(|b, _| b.roster.others[&alice.id].peer.name == "Alice")
            .await
    );
    for (msg, want) in [
        (
            ClientMsg::Rename {
                name: "x".repeat(65),
            },
            Refusal::BadName { max: 64 },
        ),
        (
            ClientMsg::Rename {
                name: "tab\there".into(),
            },
            Refusal::BadName { max: 64 },
        ),
        (
            ClientMsg::Presence {
                view: Some(View {
                    eye: [f32::NAN, 0.0, 0.0],
                    forward: [0.0, 0.0, 1.0],
                }),
                cursor: None,
                selection: None,
            },
            Refusal::NotFinite,
        ),
        (
            ClientMsg::Presence {
                view: None,
                cursor: Some(Cursor {
                    voxel: [9999, 0, 0],
                    radius: 1.0,
                }),
                selection: None,
            },
            Refusal::OutOfRange,
        ),
        // A selection past the scene, or with its corners the wrong way round.
        (
            ClientMsg::Presence {
                view: None,
                cursor: None,
                selection: Some(Selection {
                    min: [0, 0, 0],
                    max: [9999, 1, 1],
                }),
            },
            Refusal::OutOfRange,
        ),
        (
            ClientMsg::Presence {
                view: None,
                cursor: None,
                selection: Some(Selection {
                    min: [5, 5, 5],
                    max: [4, 5, 5],
                }),
            },
            Refusal::OutOfRange,
        ),
    ] {
        a.send(&msg).await;
        let got = a
            .until(|_, m| matches!(m, ServerMsg::Refused { reason } if *reason == want))
            .await;
        assert!(got, "no {want:?} for {msg:?}");
    }
    // Too fast: more than presence_hz in a burst.
    for i in 0..60 {
        a.send(&ClientMsg::Presence {
            view: None,
            cursor: Some(Cursor {
                voxel: [i, 0, 0],
                radius: 0.0,
            }),
            selection: None,
        })
        .await;
    }
    assert!(
        a.until(|_, m| matches!(
            m,
            ServerMsg::Refused {
                reason: Refusal::RateLimited
            }
        ))
        .await
    );
    a.send(&ClientMsg::Ping { nonce: 77 }).await;
    assert!(
        a.until(|_, m| matches!(m, ServerMsg::Pong { nonce: 77 }))
            .await
    );
    assert!(a.errors.is_empty(), "{:?}", a.errors);

    // Alice leaves: bob's roster drops her.
    a.close().await;
    assert!(
        b.until(|b, _| !b.roster.others.contains_key(&alice.id))
            .await
    );
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn a_client_that_never_reads_does_not_queue_presence() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let url = server.url("demo");
    // Says hello and then never reads a byte.
    let silent = Client::as_user(&url, None, 5, "silent").await.unwrap();
    let mut movers = Vec::new();
    for i in 0..4 {
        let mut c = Client::as_user(&url, None, 100 + i, &format!("m{i}"))
            .await
            .unwrap();
        c.sync().await;
        movers.push(c);
    }
    // Four peers move at 20 Hz for 4 seconds.
    for step in 0..80 {
        for (i, c) in movers.iter_mut().enumerate() {
            c.send(&ClientMsg::Presence {
                view: Some(View {
                    eye: [step as f32, i as f32, 1.0],
                    forward: [0.0, 0.0, 1.0],
                }),
                cursor: None,
                selection: None,
            })
            .await;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        // The movers read what comes, like a viewer does.
        for c in movers.iter_mut() {
            while let Ok(Some(_)) = tokio::time::timeout(Duration::from_millis(1), c.next()).await {
            }
        }
    }
    let (_, metrics) = http_get(server.addr, "/metrics").await;
    let value = |name: &str| -> f64 {
        metrics
            .lines()
            .find(|l| l.starts_with(name) && l[name.len()..].starts_with(' '))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{name} missing:\n{metrics}"))
    };
    let queued = value("brickcast_queued_bytes");
    // The silent client holds its sync (bounded by the queue limits) and at most one presence
    // frame past the presence bound, not 80 ticks of them.
    // (Loopback socket buffers can absorb all of it; `presence::tests` fills a queue past the
    // bound directly.)
    let frames = value("brickcast_presence_frames_total");
    assert!(frames > 100.0, "presence frames sent: {frames}");
    assert!(queued < (1 << 20) as f64, "queued {queued} bytes");
    drop(silent);
    server.shutdown().await.unwrap();
}

/// Before: names kept format characters (`Al\u{200b}ice`), a stranger could show as a name the
/// auth file gives someone ("Alice Liddell", or a look-alike), and could choose an id whose
/// colour is hers so that she got another. Now names are cleaned, the auth file's names and
/// their look-alikes are the named users' only, and a named user keeps her colour.
#[tokio::test]
async fn a_name_the_auth_file_gives_cannot_be_shown_by_anyone_else() {
    use brickcast_server::identity::{colour_of, identify, looks_alike};
    let data = tempfile::tempdir().unwrap();
    let auth = data.path().join("auth");
    std::fs::write(&auth, "ed editor Alice Liddell\nmal editor\n").unwrap();
    let server = TestServer::start(data.path(), |c| {
        c.auth = brickcast_server::auth::Auth::from_file(&auth).unwrap();
    })
    .await;
    let url = server.url("demo");
    // Mallory picks an id that lands on Alice's colour and a name like hers, and comes first.
    let alice_user = identify(false, Some("Alice Liddell"), 0, "", 0, |_| false).user;
    let hers = colour_of(alice_user);
    let id = (1..100_000u64).find(|&u| colour_of(u) == hers).unwrap();
    let mut mallory = Client::as_user(&url, Some("mal"), id, "AIice LiddeII")
        .await
        .unwrap();
    let shown = mallory.roster.you.clone().unwrap();
    assert!(shown.name.starts_with("guest-"), "{}", shown.name);
    assert_eq!(shown.colour, hers, "the colour was free");
    mallory.sync().await;
    let mut alice = Client::as_user(&url, Some("ed"), 0, "x").await.unwrap();
    let me = alice.roster.you.clone().unwrap();
    assert_eq!((me.name.as_str(), me.colour), ("Alice Liddell", hers));
    // Mallory now shows another colour, as Alice sees her.
    assert!(
        alice
            .until(|a, _| a
                .roster
                .others
                .get(&shown.id)
                .is_some_and(|p| !looks_alike(p.peer.colour, hers)))
            .await
    );
    // Renames to her name, a look-alike of it, or with invisible characters are refused.
    for name in ["Alice Liddell", "ALICE LIDDELL", "\u{410}lice Liddell"] {
        mallory.send(&ClientMsg::Rename { name: name.into() }).await;
        assert!(
            mallory
                .until(|_, m| matches!(
                    m,
                    ServerMsg::Refused {
                        reason: Refusal::NameTaken
                    }
                ))
                .await,
            "{name:?} was not refused"
        );
    }
    mallory
        .send(&ClientMsg::Rename {
            name: "Mal\u{200B}lory".into(),
        })
        .await;
    assert!(
        mallory
            .until(|_, m| matches!(
                m,
                ServerMsg::Refused {
                    reason: Refusal::BadName { .. }
                }
            ))
            .await
    );
    // A name sent in Hello with format characters is shown cleaned.
    let bob = Client::as_user(&url, Some("mal"), 0, "B\u{202E}o\u{200B}b")
        .await
        .unwrap();
    assert_eq!(bob.roster.you.as_ref().unwrap().name, "Bob");
    assert!(alice.errors.is_empty() && mallory.errors.is_empty());
    server.shutdown().await.unwrap();
}
