//! The admin API against a three-node cluster (a real `nats-server`, three `serve --nats`
//! processes): a scene made through one node is served by the others; deleted through one,
//! every node closes it and tells its people; it is kept, refused as a new scene's name, and
//! restored through a third node with every acknowledged edit; an uploaded model is served
//! everywhere; what a cluster cannot do yet is refused with the reason.

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
    let ack = on_b
        .edit(vec![EditOp::Set {
            pos: [5, 30, 5],
            colour: colour(3),
        }])
        .await;
    assert!(matches!(ack, ServerMsg::Ack { .. }), "{ack:?}");
    let mut on_c = Client::connect(&url(&c, "isle"), None).await.unwrap();
    on_c.sync().await;
    // The edit is in c's sync or comes after it as a delta: `until` looks only at messages
    // still to come, so it is asked only when the sync did not already hold the edit.
    if on_c.map.content_hash() != on_b.map.content_hash() {
        assert!(
            on_c.until(|cl, _| cl.map.content_hash() == on_b.map.content_hash())
                .await,
            "c closed before it held b's edit"
        );
    }
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
    let reuse = refused(&admin(b.addr, &["create", "isle"], None).await);
    assert!(
        reuse.contains("deleted scene named isle is kept"),
        "{reuse}"
    );
    let rename = refused(&admin(b.addr, &["rename", "demo", "other"], None).await);
    assert!(
        rename.contains("not available on a cluster node"),
        "{rename}"
    );
    let elsewhere = refused(&admin(c.addr, &["restore", &key, "--as", "isle2"], None).await);
    assert!(elsewhere.contains("its own name"), "{elsewhere}");

    // Purged through b: its name is free at once (a second delete keeps it again first).
    ok(&admin(b.addr, &["create", "gone", "--size", "16,16,16"], None).await);
    let kept = ok(&admin(b.addr, &["delete", "gone", "--yes"], None).await);
    let kept_key = kept["key"].as_str().unwrap().to_string();
    let unsure = refused(&admin(a.addr, &["purge", &kept_key], None).await);
    assert!(unsure.contains("--yes"), "{unsure}");
    ok(&admin(a.addr, &["purge", &kept_key, "--yes"], None).await);
    ok(&admin(c.addr, &["create", "gone", "--size", "16,16,16"], None).await);

    // Restored through c: served again with the edit acknowledged before the delete.
    ok(&admin(c.addr, &["restore", &key], None).await);
    let mut back = Client::connect(&url(&a, "isle"), None).await.unwrap();
    back.sync().await;
    assert_eq!(back.map.content_hash(), hash, "the scene as it was deleted");

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
}
