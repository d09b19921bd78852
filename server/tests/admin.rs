//! The admin API and `brickcast-server admin` against a real server on loopback: scenes are
//! created, deleted (kept, restored), renamed and reset while users are connected, users are
//! disconnected and kept out, and everyone who is not an admin is refused.

mod common;

use std::net::SocketAddr;

use brickcast_protocol::Colour;
use brickcast_protocol::wire::{EditOp, ErrorCode, ServerMsg};
use brickcast_server::auth::Auth;
use common::admin_cli::{admin, ok, refused};
use common::{Client, Refused, TestServer, http_get};
use serde_json::Value;

fn scene<'a>(list: &'a Value, name: &str) -> Option<&'a Value> {
    list["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == name)
}

/// Reads until the server closes the session; returns the error it gave.
async fn closed_with(client: &mut Client) -> (ErrorCode, String) {
    let errors = client.until_closed().await;
    errors
        .last()
        .cloned()
        .expect("an error frame before the close")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_admin_manages_the_scenes_of_a_running_server() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |_| {}).await;
    let addr = server.addr;

    let mut alice = Client::as_user(&server.url("demo"), None, 5, "alice")
        .await
        .unwrap();
    let ack = alice
        .edit(vec![EditOp::Set {
            pos: [3, 40, 3],
            colour: Colour::from_rgb8(200, 10, 10),
        }])
        .await;
    assert!(matches!(ack, ServerMsg::Ack { .. }), "{ack:?}");

    let list = ok(&admin(addr, &["list"], None).await);
    let demo = scene(&list, "demo").expect("demo listed").clone();
    assert_eq!(demo["users"][0]["name"], "alice", "{demo}");
    assert!(demo["voxels"].as_u64().unwrap() > 0 && demo["seq"].as_u64().unwrap() >= 1);

    // Create: a generated world, served at once; its name now taken; bad input refused.
    let made = ok(&admin(
        addr,
        &[
            "create", "world", "--kind", "terrain", "--size", "64,32,64", "--seed", "3",
        ],
        None,
    )
    .await);
    assert!(made["voxels"].as_u64().unwrap() > 0, "{made}");
    let mut bob = Client::as_user(&server.url("world"), None, 6, "bob")
        .await
        .unwrap();
    let again = refused(&admin(addr, &["create", "world"], None).await);
    assert!(again.contains("already exists"), "{again}");
    let bad = refused(&admin(addr, &["create", "no~pe"], None).await);
    assert!(bad.contains("invalid"), "{bad}");
    let huge = refused(
        &admin(
            addr,
            &["create", "x", "--kind", "demo", "--size", "4096,64,64"],
            None,
        )
        .await,
    );
    assert!(huge.contains("at most 1024"), "{huge}");
    let odd = refused(&admin(addr, &["create", "x", "--size", "0,8,8"], None).await);
    assert!(odd.contains("not a number of voxels"), "{odd}");

    // Delete: refused unconfirmed; then alice is told and the scene is gone but kept.
    let unconfirmed = refused(&admin(addr, &["delete", "demo"], None).await);
    assert!(unconfirmed.contains("--yes"), "{unconfirmed}");
    let deleted = ok(&admin(addr, &["delete", "demo", "--yes", "--keep", "1h"], None).await);
    let (code, text) = closed_with(&mut alice).await;
    assert_eq!(code, ErrorCode::UnknownScene);
    assert!(text.contains("deleted by an administrator"), "{text}");
    assert_eq!(http_get(addr, "/scenes/demo/ws").await.0, 404);
    let list = ok(&admin(addr, &["list"], None).await);
    assert!(scene(&list, "demo").is_none());
    assert_eq!(list["deleted"][0]["name"], "demo", "{list}");
    let key = deleted["key"].as_str().unwrap().to_string();
    assert_eq!(list["deleted"][0]["key"], key.as_str());

    // Restore: the same scene, the acknowledged edit included.
    let back = ok(&admin(addr, &["restore", &key], None).await);
    assert_eq!(
        (&back["voxels"], &back["seq"]),
        (&demo["voxels"], &demo["seq"]),
        "{back}"
    );
    let again = refused(&admin(addr, &["restore", &key], None).await);
    assert!(again.contains("no deleted scene is kept as"), "{again}");
    let purge_gone = refused(&admin(addr, &["purge", &key, "--yes"], None).await);
    assert!(
        purge_gone.contains("no deleted scene is kept as"),
        "{purge_gone}"
    );

    // Rename, with its user told where it went.
    ok(&admin(addr, &["rename", "world", "terrain2"], None).await);
    let (_, text) = closed_with(&mut bob).await;
    assert!(text.contains("renamed to terrain2"), "{text}");
    Client::connect(&server.url("terrain2"), None)
        .await
        .unwrap();
    let taken = refused(&admin(addr, &["rename", "terrain2", "demo"], None).await);
    assert!(taken.contains("already exists"), "{taken}");

    // Reset: demo empty, the one before kept and restorable under another name.
    let reset = ok(&admin(addr, &["reset", "demo", "--yes"], None).await);
    assert_eq!(reset["voxels"], 0, "{reset}");
    let previous = reset["previous"]["key"].as_str().unwrap().to_string();
    let old = ok(&admin(addr, &["restore", &previous, "--as", "demo-old"], None).await);
    assert_eq!(old["voxels"], demo["voxels"]);

    // Kick: carol is disconnected and refused for a while; dave carries on.
    let mut carol = Client::as_user(&server.url("demo"), None, 7, "carol")
        .await
        .unwrap();
    let _dave = Client::as_user(&server.url("demo"), None, 8, "dave")
        .await
        .unwrap();
    let nobody = refused(&admin(addr, &["kick", "--name", "mallory"], None).await);
    assert!(nobody.contains("nobody like that"), "{nobody}");
    let kicked = ok(&admin(addr, &["kick", "--name", "carol", "--for", "10m"], None).await);
    assert_eq!(
        kicked["disconnected"].as_array().unwrap().len(),
        1,
        "{kicked}"
    );
    let (code, text) = closed_with(&mut carol).await;
    assert_eq!(code, ErrorCode::Unauthorized);
    assert!(text.contains("come back in 10 min"), "{text}");
    match Client::as_user(&server.url("demo"), None, 7, "carol").await {
        Err(Refused::Error(ErrorCode::Unauthorized, text)) => {
            assert!(text.contains("administrator"), "{text}")
        }
        Err(Refused::Error(code, text)) => panic!("refused with {code:?}: {text}"),
        Err(Refused::Closed) => panic!("closed without a reason"),
        Ok(_) => panic!("a kicked user came straight back"),
    }
    Client::as_user(&server.url("demo-old"), None, 9, "erin")
        .await
        .unwrap();

    // Backup and upload: a scene as a file and back; a .vox model; bad uploads change nothing.
    let files = tempfile::tempdir().unwrap();
    let backup = files.path().join("old.scene");
    let backup_arg = backup.display().to_string();
    ok(&admin(addr, &["backup", "demo-old", "--out", &backup_arg], None).await);
    let copy = ok(&admin(addr, &["upload", "copy", &backup_arg], None).await);
    assert_eq!(copy["voxels"], demo["voxels"], "{copy}");
    let taken = refused(&admin(addr, &["upload", "copy", &backup_arg], None).await);
    assert!(
        taken.contains("already exists") && taken.contains("--replace"),
        "{taken}"
    );
    let mut model = brickcast_protocol::BrickMap::new([40, 20, 30]).unwrap();
    model.fill_box(
        [0, 0, 0],
        [39, 4, 29],
        brickcast_protocol::BrushMode::Fill,
        Colour::from_rgb8(10, 200, 30),
    );
    let vox = files.path().join("model.vox");
    std::fs::write(&vox, brickcast_server::import::vox::export_vox(&model).0).unwrap();
    let vox_arg = vox.display().to_string();
    let replaced = ok(&admin(addr, &["upload", "copy", &vox_arg, "--replace"], None).await);
    assert_eq!(replaced["voxels"], model.solid_voxels(), "{replaced}");
    let replaced_key = replaced["previous"]["key"].as_str().unwrap().to_string();
    let purged = ok(&admin(addr, &["purge", &replaced_key, "--yes"], None).await);
    assert_eq!(purged["name"], "copy", "{purged}");
    let list = ok(&admin(addr, &["list"], None).await);
    assert!(
        !list["deleted"]
            .as_array()
            .unwrap()
            .iter()
            .any(|d| d["key"] == replaced_key.as_str()),
        "{list}"
    );
    // An .obj mesh is voxelized by the command (materials and textures read there) and
    // served as the offline import would make it.
    let obj = files.path().join("cube.obj");
    std::fs::write(
        &obj,
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
         f 1 2 3\nf 1 3 4\nf 5 7 6\nf 5 8 7\nf 1 5 6\nf 1 6 2\n\
         f 4 3 7\nf 4 7 8\nf 1 4 8\nf 1 8 5\nf 2 6 7\nf 2 7 3\n",
    )
    .unwrap();
    let options = brickcast_server::import::ImportOptions {
        resolution: 32,
        ..Default::default()
    };
    let offline = brickcast_server::import::import_file(
        &obj,
        &options,
        &brickcast_server::import::NoProgress,
    )
    .unwrap();
    let obj_arg = obj.display().to_string();
    let mesh = ok(&admin(
        addr,
        &["upload", "cube", &obj_arg, "--resolution", "32"],
        None,
    )
    .await);
    assert_eq!(mesh["voxels"], offline.map.solid_voxels(), "{mesh}");
    assert!(offline.map.solid_voxels() > 1000, "a hollow 32³ cube");
    let mut cube = Client::connect(&format!("ws://{addr}/scenes/cube/ws"), None)
        .await
        .unwrap();
    cube.sync().await;
    assert_eq!(cube.map.content_hash(), offline.map.content_hash());
    cube.close().await;
    let whole = std::fs::read(&backup).unwrap();
    let cut = files.path().join("cut.scene");
    std::fs::write(&cut, &whole[..whole.len() / 2]).unwrap();
    let cut_arg = cut.display().to_string();
    let damaged = refused(&admin(addr, &["upload", "copy", &cut_arg, "--replace"], None).await);
    assert!(damaged.contains("nothing changed"), "{damaged}");
    let junk = files.path().join("junk.bin");
    std::fs::write(&junk, b"hello").unwrap();
    let junk_arg = junk.display().to_string();
    let neither = refused(&admin(addr, &["upload", "copy", &junk_arg, "--replace"], None).await);
    assert!(
        neither.contains("neither a brickcast scene file"),
        "{neither}"
    );
    let (status, body) = half_upload(addr, "/admin/scenes/copy?replace=true", &whole).await;
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("did not arrive whole"), "{body}");
    let list = ok(&admin(addr, &["list"], None).await);
    assert_eq!(
        scene(&list, "copy").unwrap()["voxels"],
        model.solid_voxels()
    );
    server.shutdown().await.unwrap();
    let gone = refused(&admin(addr, &["list"], None).await);
    assert!(gone.contains("no server answers at"), "{gone}");

    // After a restart: the scenes as the admin left them.
    let server = TestServer::start(data.path(), |_| {}).await;
    let list = ok(&admin(server.addr, &["list"], None).await);
    let names: Vec<&str> = list["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["copy", "cube", "demo", "demo-old", "terrain2"]);
    server.shutdown().await.unwrap();
}

/// A POST with a bearer token over a raw socket: the status and body.
async fn post(addr: SocketAddr, path: &str, token: Option<&str>, body: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    let request = format!(
        "POST {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    s.write_all(request.as_bytes()).await.unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).await.unwrap();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text.split_once("\r\n\r\n").map(|(_, b)| b.to_string());
    (status, body.unwrap_or_default())
}

/// A PUT that sends half its body and then stops (the sender's side closed): status and body.
async fn half_upload(addr: SocketAddr, path: &str, body: &[u8]) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "PUT {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).await.unwrap();
    s.write_all(&body[..body.len() / 2]).await.unwrap();
    s.shutdown().await.unwrap();
    let mut text = Vec::new();
    let _ = s.read_to_end(&mut text).await;
    let text = String::from_utf8_lossy(&text).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    (status, text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_an_admin_may_use_the_admin_api() {
    let data = tempfile::tempdir().unwrap();
    let server = TestServer::start(data.path(), |c| {
        c.auth = Auth::parse("root-secret admin Ops\nalice-secret editor Alice\n").unwrap();
    })
    .await;
    let addr = server.addr;
    let path = "/admin/scenes/new";
    let (status, body) = post(addr, path, None, "{}").await;
    assert_eq!(status, 403, "{body}");
    assert!(body.contains("needs an admin token"), "{body}");
    let (status, body) = post(addr, path, Some("alice-secret"), "{}").await;
    assert_eq!(status, 403, "{body}");
    assert!(body.contains("not an admin"), "{body}");
    let (status, body) = post(addr, path, Some("root-secret"), "{\"kind\": \"lava\"}").await;
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("the request's JSON"), "{body}");
    let (status, body) = post(
        addr,
        "/admin/scenes/demo/rename",
        Some("root-secret"),
        "not json",
    )
    .await;
    assert_eq!(status, 400, "{body}");
    let (status, body) = post(addr, path, Some("root-secret"), "{\"size\": [32, 16, 32]}").await;
    assert_eq!(status, 201, "{body}");

    // The command line: the token from BRICKCAST_TOKEN; without it, a clear refusal.
    let without = refused(&admin(addr, &["list"], None).await);
    assert!(without.contains("needs an admin token"), "{without}");
    let wrong = refused(&admin(addr, &["list"], Some("alice-secret")).await);
    assert!(wrong.contains("not an admin"), "{wrong}");
    let list = ok(&admin(addr, &["list"], Some("root-secret")).await);
    assert!(scene(&list, "new").is_some(), "{list}");
    let gone = refused(&admin(addr, &["delete", "nope", "--yes"], Some("root-secret")).await);
    assert!(gone.contains("no scene named \"nope\""), "{gone}");
    server.shutdown().await.unwrap();
}
