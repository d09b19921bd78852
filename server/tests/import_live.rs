//! `brickcast-server import` against a running server: the scene is handed over through the
//! spool and served without a restart; a clash is refused with the reason and the scene kept;
//! offline import, `--replace` and `export` work on the stopped store.

mod common;

use std::path::Path;
use std::process::Output;

use brickcast_protocol::{BrickMap, BrushMode, Colour};
use brickcast_server::import::vox;
use brickcast_server::incoming;
use brickcast_server::store::Store;
use common::{Client, TestServer, http_get};

/// Runs the real CLI (blocking, so off the async workers).
async fn cli(args: Vec<String>) -> Output {
    tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
            .args(&args)
            .env("RUST_LOG", "warn")
            .output()
            .expect("the CLI runs")
    })
    .await
    .unwrap()
}

fn import_args(model: &Path, scene: &str, data: &Path, extra: &[&str]) -> Vec<String> {
    let mut args = vec![
        "import".to_string(),
        model.display().to_string(),
        "--scene".into(),
        scene.into(),
        "--data".into(),
        data.display().to_string(),
        "--json".into(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    args
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn json(out: &Output) -> serde_json::Value {
    assert!(out.status.success(), "CLI failed: {}", stderr(out));
    serde_json::from_slice(&out.stdout).expect("one JSON object")
}

/// A small scene with few colours, written as `.vox`, and the scene importing it makes.
fn write_model(dir: &Path) -> (std::path::PathBuf, BrickMap) {
    let mut map = BrickMap::new([70, 30, 50]).unwrap();
    map.fill_box(
        [0, 0, 0],
        [69, 2, 49],
        BrushMode::Fill,
        Colour::from_rgb8(90, 140, 60),
    );
    map.sphere(
        [35.0, 14.0, 25.0],
        10.0,
        BrushMode::Fill,
        Colour::from_rgb8(200, 60, 40),
    );
    let (bytes, _) = vox::export_vox(&map);
    let path = dir.join("model.vox");
    // What importing it makes: these voxels, with the model's colours as the scene's palette.
    let imported = vox::import_vox(&bytes, &path).unwrap();
    assert_eq!(imported.bricks().count(), map.bricks().count());
    assert_eq!(imported.swatches().get(0), Colour::from_rgb8(90, 140, 60));
    std::fs::write(&path, bytes).unwrap();
    (path, imported)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn running_server_serves_an_imported_scene_without_restart() {
    let data = tempfile::tempdir().unwrap();
    let models = tempfile::tempdir().unwrap();
    let (model, expected) = write_model(models.path());
    let server = TestServer::start(data.path(), |_| {}).await;

    let report = json(&cli(import_args(&model, "extra", data.path(), &[])).await);
    assert_eq!(report["destination"], "the running server");
    assert_eq!(report["voxels"], expected.solid_voxels());

    // Served at once: a client syncs the same scene, and the scene list shows it.
    let mut client = Client::connect(&server.url("extra"), None)
        .await
        .expect("the new scene accepts clients");
    client.sync().await;
    assert_eq!(client.map.size(), expected.size());
    assert_eq!(client.map.content_hash(), expected.content_hash());
    let (status, body) = http_get(server.addr, "/scenes").await;
    assert_eq!(status, 200);
    assert!(
        body.contains("\"extra\"") && body.contains("\"demo\""),
        "{body}"
    );
    // It takes edits like any scene.
    let ack = client
        .edit(vec![brickcast_protocol::wire::EditOp::Set {
            pos: [1, 20, 1],
            colour: Colour::WHITE,
        }])
        .await;
    assert!(
        matches!(
            ack,
            brickcast_protocol::wire::ServerMsg::Ack { seq: Some(1), .. }
        ),
        "{ack:?}"
    );
    client.close().await;

    // The same name again: refused by the server, reason reported, the scene kept in the spool.
    let out = cli(import_args(&model, "extra", data.path(), &[])).await;
    assert!(!out.status.success());
    assert!(stderr(&out).contains("already exists"), "{}", stderr(&out));
    let spooled = incoming::spool_dir(data.path()).join("extra.scene");
    assert!(spooled.exists() && incoming::error_path(&spooled).exists());
    // --replace cannot swap a live scene.
    let out = cli(import_args(&model, "other", data.path(), &["--replace"])).await;
    assert!(!out.status.success());
    assert!(stderr(&out).contains("server stopped"), "{}", stderr(&out));

    server.shutdown().await.unwrap();

    // The scene (with its edit) is in the store.
    {
        let store = Store::open(data.path()).unwrap();
        let loaded = store.load_scene("extra").unwrap();
        assert_eq!(loaded.map.get([1, 20, 1]), Some(Colour::WHITE));
    }
    // Offline: a clash fails before any work, --replace overwrites, export round-trips.
    let out = cli(import_args(&model, "extra", data.path(), &[])).await;
    assert!(!out.status.success());
    assert!(stderr(&out).contains("--replace"), "{}", stderr(&out));
    let report = json(&cli(import_args(&model, "extra", data.path(), &["--replace"])).await);
    assert_eq!(report["destination"], "the store");
    let exported = models.path().join("back.vox");
    let out = cli(vec![
        "export".into(),
        "--scene".into(),
        "extra".into(),
        "--out".into(),
        exported.display().to_string(),
        "--data".into(),
        data.path().display().to_string(),
        "--json".into(),
    ])
    .await;
    let report = json(&out);
    assert_eq!(report["colours"]["exact"], true);
    let back = vox::import_vox(&std::fs::read(&exported).unwrap(), &exported).unwrap();
    assert_eq!(back.content_hash(), expected.content_hash());

    // Bad input: unknown format, bad name, bad resolution — clear errors, nothing stored.
    for (args, says) in [
        (
            import_args(Path::new("model.stl"), "x", data.path(), &[]),
            "unknown model format",
        ),
        (import_args(&model, "bad/name", data.path(), &[]), "invalid"),
        (
            import_args(
                Path::new("m.obj"),
                "x",
                data.path(),
                &["--resolution", "1000"],
            ),
            "power of two",
        ),
    ] {
        let out = cli(args).await;
        assert!(!out.status.success());
        assert!(stderr(&out).contains(says), "{}", stderr(&out));
    }
    let store = Store::open(data.path()).unwrap();
    let names: Vec<String> = store
        .scenes()
        .unwrap()
        .into_iter()
        .map(|(n, _)| n)
        .collect();
    assert_eq!(names, vec!["demo".to_string(), "extra".to_string()]);
}
