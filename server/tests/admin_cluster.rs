//! The admin API against a three-node cluster (a real `nats-server`, three `serve --nats`
//! processes): a scene made through one node is served by the others; deleted through one,
//! every node closes it and tells its people; it is kept while a new scene takes its name, and
//! restored under another name through a third node with every acknowledged edit; renamed and
//! reset with people on it through other nodes (told why, nothing lost, the old one kept); an
//! uploaded model is served everywhere, and replaced by another; a node with an auth file
//! refuses whoever is not an admin, and a damaged upload changes nothing.

mod common;
mod nodes;

use std::time::Duration;

use brickcast_protocol::wire::{EditOp, ErrorCode, ServerMsg};
use common::admin_cli::{admin, ok, refused};
use common::{Client, colour};
use nodes::*;

fn url(node: &Node, scene: &str) -> String {
    format!("ws://{}/scenes/{scene}/ws", node.addr)
}

/// Sets one voxel through `client` and waits until its own copy holds it: a forwarded edit's
/// answer may come before this node's replica applied the turn. The edit's sequence.
async fn set_and_see(client: &mut Client, pos: [u32; 3], c: u32) -> u64 {
    let ack = client
        .edit(vec![EditOp::Set {
            pos,
            colour: colour(c),
        }])
        .await;
    let ServerMsg::Ack { seq: Some(seq), .. } = ack else {
        panic!("{ack:?}")
    };
    client.catch_up(seq).await;
    seq
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_admin_manages_the_scenes_of_a_cluster_through_any_node() {
    let nats = Nats::start(true);
    let a = Node::start(&nats.url(), "a", &[]).await;
    let b = Node::start(&nats.url(), "b", &[]).await;
    let c = Node::start(&nats.url(), "c", &[]).await;

    let made = ok(&admin(
        a.addr,
        &["create", "isle", "--kind", "terrain", "--size", "64,32,64"],
        None,
    )
    .await);
    assert!(made["voxels"].as_u64().unwrap() > 0, "{made}");
    let mut on_b = Client::connect(&url(&b, "isle"), None).await.unwrap();
    on_b.sync().await;
    // Both clients are waited for up to the edit's sequence (in the sync or after it).
    let seq = set_and_see(&mut on_b, [5, 30, 5], 3).await;
    let mut on_c = Client::connect(&url(&c, "isle"), None).await.unwrap();
    on_c.sync().await;
    on_c.catch_up(seq).await;
    assert_eq!(on_c.map.content_hash(), on_b.map.content_hash());
    let hash = on_b.map.content_hash();

    // Deleted through a: the people on b and c are told, by their own nodes.
    let deleted = ok(&admin(a.addr, &["delete", "isle", "--yes", "--keep", "1h"], None).await);
    let key = deleted["key"].as_str().unwrap().to_string();
    for client in [&mut on_b, &mut on_c] {
        let errors = tokio::time::timeout(Duration::from_secs(30), client.until_closed())
            .await
            .expect("closed within 30 s");
        let (code, text) = errors.last().cloned().expect("told why");
        assert_eq!(code, ErrorCode::UnknownScene);
        assert!(text.contains("deleted by an administrator"), "{text}");
    }
    let list = ok(&admin(c.addr, &["list"], None).await);
    assert!(
        !list["scenes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s["name"] == "isle"),
        "{list}"
    );
    assert_eq!(list["deleted"][0]["key"], key.as_str(), "{list}");
    // A new scene may take the kept one's name: it gets a log of its own.
    ok(&admin(b.addr, &["create", "isle", "--size", "16,16,16"], None).await);
    let mut new_isle = Client::connect(&url(&c, "isle"), None).await.unwrap();
    new_isle.sync().await;
    assert_eq!(new_isle.map.solid_voxels(), 0, "the new isle is empty");
    drop(new_isle);

    // The kept one comes back under another name, through c, with the edit acknowledged
    // before the delete.
    let taken = refused(&admin(c.addr, &["restore", &key], None).await);
    assert!(taken.contains("--as"), "{taken}");
    ok(&admin(c.addr, &["restore", &key, "--as", "isle2"], None).await);
    let mut back = Client::connect(&url(&a, "isle2"), None).await.unwrap();
    back.sync().await;
    assert_eq!(back.map.content_hash(), hash, "the scene as it was deleted");

    // Renamed through b while people are on it through a and c: each is told the new name,
    // which serves the same log (nothing copied, nothing lost).
    let mut on_c2 = Client::connect(&url(&c, "isle2"), None).await.unwrap();
    on_c2.sync().await;
    ok(&admin(b.addr, &["rename", "isle2", "islet"], None).await);
    for client in [&mut back, &mut on_c2] {
        let errors = tokio::time::timeout(Duration::from_secs(30), client.until_closed())
            .await
            .expect("closed within 30 s");
        let (_, text) = errors.last().cloned().expect("told why");
        assert!(text.contains("renamed to islet"), "{text}");
    }
    let mut renamed = Client::connect(&url(&c, "islet"), None).await.unwrap();
    renamed.sync().await;
    assert_eq!(
        renamed.map.content_hash(),
        hash,
        "renamed with its contents"
    );
    set_and_see(&mut renamed, [6, 30, 6], 4).await;
    let edited = renamed.map.content_hash();
    let taken = refused(&admin(a.addr, &["rename", "islet", "isle"], None).await);
    assert!(taken.contains("already exists"), "{taken}");
    let unknown = refused(&admin(a.addr, &["rename", "isle2", "x"], None).await);
    assert!(unknown.contains("no scene"), "{unknown}");

    // Reset through a while someone is on it through c: c closes its copy (the name now
    // names another log) and says why; the scene is empty; the one before is kept.
    let reset = ok(&admin(a.addr, &["reset", "islet", "--yes"], None).await);
    let previous = reset["previous"]["key"].as_str().unwrap().to_string();
    let errors = tokio::time::timeout(Duration::from_secs(30), renamed.until_closed())
        .await
        .expect("closed within 30 s");
    let (_, text) = errors.last().cloned().expect("told why");
    assert!(text.contains("reset"), "{text}");
    let mut empty = Client::connect(&url(&b, "islet"), None).await.unwrap();
    empty.sync().await;
    assert_eq!(empty.map.solid_voxels(), 0, "reset to an empty scene");
    ok(&admin(b.addr, &["restore", &previous, "--as", "islet-old"], None).await);
    let mut old = Client::connect(&url(&c, "islet-old"), None).await.unwrap();
    old.sync().await;
    assert_eq!(
        old.map.content_hash(),
        edited,
        "the reset scene, kept whole"
    );

    // Purged through b: its name is free at once (a second delete keeps it again first).
    ok(&admin(b.addr, &["create", "gone", "--size", "16,16,16"], None).await);
    let kept = ok(&admin(b.addr, &["delete", "gone", "--yes"], None).await);
    let kept_key = kept["key"].as_str().unwrap().to_string();
    let unsure = refused(&admin(a.addr, &["purge", &kept_key], None).await);
    assert!(unsure.contains("--yes"), "{unsure}");
    ok(&admin(a.addr, &["purge", &kept_key, "--yes"], None).await);
    ok(&admin(c.addr, &["create", "gone", "--size", "16,16,16"], None).await);

    // An uploaded model is served by every node.
    let mut model = brickcast_protocol::BrickMap::new([24, 16, 24]).unwrap();
    model.fill_box(
        [0, 0, 0],
        [23, 2, 23],
        brickcast_protocol::BrushMode::Fill,
        colour(5),
    );
    let files = tempfile::tempdir().unwrap();
    let vox = files.path().join("m.vox");
    std::fs::write(&vox, brickcast_server::import::vox::export_vox(&model).0).unwrap();
    let up = ok(&admin(
        b.addr,
        &["upload", "carved", &vox.display().to_string()],
        None,
    )
    .await);
    assert_eq!(up["voxels"], model.solid_voxels(), "{up}");
    let mut seen = Client::connect(&url(&c, "carved"), None).await.unwrap();
    seen.sync().await;
    assert_eq!(seen.map.solid_voxels(), model.solid_voxels());
    let twice = refused(
        &admin(
            a.addr,
            &["upload", "carved", &vox.display().to_string()],
            None,
        )
        .await,
    );
    assert!(twice.contains("--replace"), "{twice}");

    // A kick asked of one node reaches the user's connection to another, and every node
    // refuses them after; a kick of nobody refuses nobody.
    let nobody = refused(&admin(a.addr, &["kick", "--name", "nobody-here"], None).await);
    assert!(nobody.contains("nobody like that"), "{nobody}");
    let mut mallory = Client::as_user(&url(&c, "carved"), None, 77, "mallory")
        .await
        .unwrap();
    mallory.sync().await;
    let kicked = ok(&admin(a.addr, &["kick", "--name", "mallory", "--for", "10m"], None).await);
    assert_eq!(kicked["disconnected"][0]["node"], "c", "{kicked}");
    assert!(kicked.get("nodes_not_told").is_none(), "{kicked}");
    let errors = mallory.until_closed().await;
    let (code, text) = errors.last().cloned().expect("told why");
    assert_eq!(code, ErrorCode::Unauthorized);
    assert!(text.contains("come back in 10 min"), "{text}");
    for node in [&a, &b, &c] {
        match Client::as_user(&url(node, "carved"), None, 77, "mallory").await {
            Err(common::Refused::Error(ErrorCode::Unauthorized, text)) => {
                assert!(text.contains("administrator"), "{text}")
            }
            Err(e) => panic!("refused by {} otherwise: {e:?}", node.name),
            Ok(_) => panic!("a kicked user came straight back through {}", node.name),
        }
    }

    // A load run over two nodes leaves the real scene alone: it edits a scratch scene made
    // through the first node, served by both, and deleted after.
    let brickcast =
        std::path::Path::new(env!("CARGO_BIN_EXE_brickcast-server")).with_file_name("brickcast");
    assert!(
        brickcast.exists(),
        "{} is missing: `cargo build --workspace --bins` first (scripts/test does)",
        brickcast.display()
    );
    let run = tokio::task::spawn_blocking({
        let (to_a, to_b) = (url(&a, "carved"), url(&b, "carved"));
        move || {
            std::process::Command::new(brickcast)
                .args([
                    "load",
                    &to_a,
                    &to_b,
                    "--duration",
                    "1",
                    "--clients",
                    "2",
                    "--json",
                ])
                .env("NO_COLOR", "1")
                .output()
                .unwrap()
        }
    })
    .await
    .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        run.status.success(),
        "load over two nodes failed:\n{stderr}"
    );
    assert!(stderr.contains("scratch"), "{stderr}");
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert!(report["ops_acked"].as_u64().unwrap_or(0) > 0, "{report}");
    let mut fresh = Client::connect(&url(&a, "carved"), None).await.unwrap();
    fresh.sync().await;
    assert_eq!(
        fresh.map.content_hash(),
        seen.map.content_hash(),
        "the real scene was edited"
    );
    let after = ok(&admin(b.addr, &["list"], None).await);
    // Deleted at once; each node closes it at its next look at the scene list (every second).
    let served = |list: &serde_json::Value| {
        list["scenes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s["name"].as_str().is_some_and(|n| n.contains(".load-")))
    };
    assert!(
        after["deleted"].to_string().contains(".load-"),
        "the scratch scene was not deleted: {after}"
    );
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let mut last = after;
    while served(&last) {
        assert!(
            std::time::Instant::now() < deadline,
            "the scratch scene is still served: {last}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
        last = ok(&admin(b.addr, &["list"], None).await);
    }

    // Replaced by another upload through c: the name serves the new model, the old is kept.
    let mut other = brickcast_protocol::BrickMap::new([24, 16, 24]).unwrap();
    other.fill_box(
        [2, 0, 2],
        [9, 9, 9],
        brickcast_protocol::BrushMode::Fill,
        colour(6),
    );
    let vox2 = files.path().join("other.vox");
    std::fs::write(&vox2, brickcast_server::import::vox::export_vox(&other).0).unwrap();
    let replaced = ok(&admin(
        c.addr,
        &["upload", "carved", &vox2.display().to_string(), "--replace"],
        None,
    )
    .await);
    assert!(replaced["previous"]["key"].is_string(), "{replaced}");
    let errors = tokio::time::timeout(Duration::from_secs(30), seen.until_closed())
        .await
        .expect("closed within 30 s");
    let (_, text) = errors.last().cloned().expect("told why");
    assert!(text.contains("replaced"), "{text}");
    let mut now = Client::connect(&url(&b, "carved"), None).await.unwrap();
    now.sync().await;
    assert_eq!(now.map.solid_voxels(), other.solid_voxels());

    // A node with an auth file refuses whoever is not an admin; a damaged upload through it
    // is refused and changes nothing.
    let auth = files.path().join("auth");
    std::fs::write(&auth, "root-secret admin Ops\nalice-secret editor Alice\n").unwrap();
    let d = Node::start(&nats.url(), "d", &["--auth", &auth.display().to_string()]).await;
    let nobody = refused(&admin(d.addr, &["delete", "carved", "--yes"], None).await);
    assert!(nobody.contains("needs an admin token"), "{nobody}");
    let alice = refused(&admin(d.addr, &["rename", "carved", "x"], Some("alice-secret")).await);
    assert!(alice.contains("not an admin"), "{alice}");
    let backup = files.path().join("carved.scene");
    let backup_arg = backup.display().to_string();
    ok(&admin(
        d.addr,
        &["backup", "carved", "--out", &backup_arg],
        Some("root-secret"),
    )
    .await);
    let whole = std::fs::read(&backup).unwrap();
    std::fs::write(&backup, &whole[..whole.len() / 2]).unwrap();
    let damaged = refused(
        &admin(
            d.addr,
            &["upload", "carved", &backup_arg, "--replace"],
            Some("root-secret"),
        )
        .await,
    );
    assert!(damaged.contains("nothing changed"), "{damaged}");
    let mut still = Client::connect(&url(&a, "carved"), None).await.unwrap();
    still.sync().await;
    assert_eq!(still.map.content_hash(), now.map.content_hash());
}
