//! `brickcast load` against a real in-process server: the JSON report of short runs of every op
//! kind, the server's own counters agreeing with it, refusals that say why, and a run whose
//! server goes away failing loudly.

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::time::Duration;

use brickcast_server::auth::Auth;
use brickcast_tests::{TestServer, fetch, http_get, run_brickcast};
use serde_json::Value;

const RUN_LIMIT: Duration = Duration::from_secs(180);

fn local() -> SocketAddr {
    "127.0.0.1:0".parse().expect("address")
}

/// Fields added since, each present only when it has something to say: the server's CPU (when
/// its `/metrics` exports it), undo and presence (with `--undo-ratio`, `--presence-hz`).
const LATER_FIELDS: [&str; 3] = ["server_cpu_cores", "undo", "presence"];

/// The fields issue #6 lists for `--json`, no more, no fewer (besides [`LATER_FIELDS`]).
const FIELDS: [&str; 12] = [
    "clients",
    "duration_s",
    "ops_acked",
    "ops_per_s",
    "voxels_per_s",
    "latency_ms",
    "ack_latency_ms",
    "bytes_in",
    "bytes_out",
    "resyncs",
    "rejected",
    "errors",
];

fn num(report: &Value, path: &[&str]) -> f64 {
    let mut v = report;
    for key in path {
        v = &v[*key];
    }
    v.as_f64()
        .unwrap_or_else(|| panic!("{path:?} is not a number in {report}"))
}

/// Runs `brickcast load URL ARGS --json`, demands success, and checks the report's shape.
fn load_ok(url: &str, args: &[&str]) -> (Value, String) {
    let all = [&["load", url][..], args, &["--in-place", "--json"][..]].concat();
    let (status, stdout, stderr) = run_brickcast(&all, &[], RUN_LIMIT).expect("brickcast load");
    assert!(status.success(), "{all:?} failed:\n{stderr}");
    let report: Value = serde_json::from_str(stdout.trim())
        .unwrap_or_else(|e| panic!("stdout is not one JSON object ({e}): {stdout}"));
    let keys: BTreeSet<&str> = report
        .as_object()
        .expect("an object")
        .keys()
        .map(String::as_str)
        .filter(|k| !LATER_FIELDS.contains(k))
        .collect();
    assert_eq!(keys, FIELDS.into_iter().collect(), "{report}");
    let latency: BTreeSet<&str> = report["latency_ms"]
        .as_object()
        .expect("latency_ms object")
        .keys()
        .map(String::as_str)
        .collect();
    assert_eq!(latency, ["max", "p50", "p95", "p99"].into_iter().collect());
    let ack: BTreeSet<&str> = report["ack_latency_ms"]
        .as_object()
        .expect("ack_latency_ms object")
        .keys()
        .map(String::as_str)
        .collect();
    assert_eq!(ack, ["p50", "p99"].into_iter().collect());
    for path in [
        &["latency_ms", "p50"][..],
        &["latency_ms", "p95"],
        &["latency_ms", "p99"],
        &["latency_ms", "max"],
    ]
    .windows(2)
    {
        assert!(
            num(&report, path[0]) <= num(&report, path[1]),
            "{:?} > {:?} in {report}",
            path[0],
            path[1]
        );
    }
    assert!(num(&report, &["ack_latency_ms", "p50"]) <= num(&report, &["ack_latency_ms", "p99"]));
    assert_eq!(num(&report, &["errors"]), 0.0, "{report}\n{stderr}");
    assert!(num(&report, &["ops_acked"]) > 0.0, "{report}");
    let ops_per_s = num(&report, &["ops_acked"]) / num(&report, &["duration_s"]);
    assert!((num(&report, &["ops_per_s"]) - ops_per_s).abs() <= 1e-6 * ops_per_s.max(1.0));
    (report, stderr)
}

/// The value of an unlabelled counter in the server's `/metrics`.
fn counter(addr: SocketAddr, name: &str) -> f64 {
    let text = http_get(addr, "/metrics").expect("/metrics");
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("{name} missing from /metrics:\n{text}"))
}

#[test]
fn a_short_run_reports_sane_json_and_every_copy_matches_the_server() {
    let data = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(data.path(), local()).expect("server");
    let url = server.url("demo");
    let before = fetch(&url).expect("fresh copy").map.content_hash();

    let (report, stderr) = load_ok(
        &url,
        &[
            "--clients",
            "3",
            "--viewers",
            "2",
            "--duration",
            "2",
            "--batch",
            "8",
            "--region",
            "0,0,0,127,31,127",
        ],
    );
    assert_eq!(num(&report, &["clients"]), 3.0);
    let duration = num(&report, &["duration_s"]);
    assert!((2.0..30.0).contains(&duration), "duration_s {duration}");
    assert!(num(&report, &["latency_ms", "p50"]) > 0.0, "{report}");
    assert!(num(&report, &["ack_latency_ms", "p50"]) > 0.0, "{report}");
    assert!(num(&report, &["voxels_per_s"]) > 0.0, "{report}");
    // Every connection synced the whole scene: at least its compressed bricks came in.
    assert!(num(&report, &["bytes_in"]) > 100_000.0, "{report}");
    assert!(num(&report, &["bytes_out"]) > 0.0, "{report}");
    assert_eq!(num(&report, &["rejected"]), 0.0, "{report}");
    // The only editors were the load clients: the server applied exactly what they were acked.
    assert_eq!(
        counter(server.addr, "brickcast_edits_applied_total"),
        num(&report, &["ops_acked"]),
        "server and tool disagree on ops applied"
    );
    assert!(
        stderr.contains("5/5 copies equal the server's scene"),
        "table on stderr:\n{stderr}"
    );
    let after = fetch(&url).expect("fresh copy").map.content_hash();
    assert_ne!(before, after, "the run changed nothing");
    server.stop().expect("clean shutdown");
}

/// A run on a scene that holds voxels, without `--in-place`, edits a scratch scene of the same
/// size that it makes and deletes through the admin API: the scene named is left as it was.
#[test]
fn a_run_on_a_scene_with_voxels_edits_a_scratch_scene_and_leaves_it_alone() {
    let data = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(data.path(), local()).expect("server");
    let url = server.url("demo");
    let before = fetch(&url).expect("fresh copy").map.content_hash();
    let args = [
        "load",
        &url,
        "--clients",
        "2",
        "--duration",
        "0.5",
        "--json",
    ];
    let (status, stdout, stderr) = run_brickcast(&args, &[], RUN_LIMIT).expect("brickcast");
    assert!(status.success(), "{stderr}");
    let report: Value = serde_json::from_str(&stdout).expect("one JSON report");
    assert!(num(&report, &["ops_acked"]) > 0.0, "{report}");
    assert!(stderr.contains("scratch"), "{stderr}");
    assert_eq!(fetch(&url).expect("fresh copy").map.content_hash(), before);
    let list: Value = serde_json::from_str(&http_get(server.addr, "/scenes").unwrap()).unwrap();
    let names: Vec<&str> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["demo"], "the scratch scene is gone");
    server.stop().expect("clean shutdown");
}

#[test]
fn every_op_kind_paced_and_disjoint() {
    let data = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(data.path(), local()).expect("server");
    let url = server.url("demo");
    let (clients, rate, batch, duration) = (2.0, 200.0, 4.0, 1.5);
    for (op, region) in [
        ("sphere", "disjoint:0,0,0,127,40,127"),
        ("paint", "0,0,0,127,40,127"),
        ("ray", "disjoint"),
        ("voxel", "disjoint:16,0,16,111,30,111"),
    ] {
        let (report, stderr) = load_ok(
            &url,
            &[
                "--op",
                op,
                "--radius",
                "3",
                "--region",
                region,
                "--clients",
                "2",
                "--viewers",
                "1",
                "--rate",
                "200",
                "--batch",
                "4",
                "--duration",
                "1.5",
            ],
        );
        // Paced: each client sends at most one batch per batch/rate seconds (plus the first).
        let acked = num(&report, &["ops_acked"]) + num(&report, &["rejected"]);
        let most = clients * (rate * duration + batch);
        assert!(
            acked <= most && acked >= most / 3.0,
            "{op}: {acked} ops at {rate}/s per client for {duration} s:\n{stderr}"
        );
        assert!(num(&report, &["voxels_per_s"]) > 0.0, "{op}: {report}");
        assert!(stderr.contains("3/3 copies equal"), "{op}:\n{stderr}");
    }
    server.stop().expect("clean shutdown");
}

#[test]
fn tokens_bad_addresses_and_bad_options_are_refused_with_reasons() {
    let data = tempfile::tempdir().expect("tempdir");
    let auth = Auth::parse("ed editor\nlook viewer\n").expect("auth file");
    let server =
        TestServer::start_with(data.path(), local(), |config| config.auth = auth).expect("server");
    let url = format!("ws://{}/scenes/demo", server.addr);
    let short = ["--duration", "0.5", "--clients", "1", "--in-place"];
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["--token", "look"], "editor --token"),
        (vec![], "editor --token"),
        (vec!["--token", "nope"], "unknown token"),
        (vec!["--token", "ed", "--batch", "5000"], "--batch"),
        (
            vec!["--token", "ed", "--region", "0,0,0,999,10,10"],
            "outside the scene",
        ),
        (vec!["--token", "ed", "--region", "0,0,0"], "--region"),
        (
            vec!["--token", "ed", "--op", "sphere", "--radius", "65"],
            "--radius",
        ),
        (
            vec![
                "--token",
                "ed",
                "--op",
                "paint",
                "--region",
                "0,60,0,127,63,127",
            ],
            "no solid voxel",
        ),
        (vec!["--token", "ed", "--clients", "0"], "--clients"),
    ];
    // Without --in-place a run on a scene that holds voxels edits a scratch scene through the
    // admin API: an editor token is refused that, with the ways around it, before any edit.
    let seq = || brickcast_tests::scene_info(server.addr, "demo").expect("/scenes")["seq"].clone();
    let before = seq();
    let (status, _, stderr) = run_brickcast(
        &["load", &url, "--token", "ed", "--duration", "0.5"],
        &[],
        RUN_LIMIT,
    )
    .expect("brickcast");
    assert!(!status.success(), "an editor cannot make a scratch scene");
    assert!(
        stderr.contains("not an admin") && stderr.contains("--in-place"),
        "{stderr}"
    );
    assert_eq!(seq(), before, "nothing was written");
    for (extra, expect) in cases {
        let args = [&["load", &url][..], &short[..], &extra[..]].concat();
        let (status, stdout, stderr) = run_brickcast(&args, &[], RUN_LIMIT).expect("brickcast");
        assert!(!status.success(), "{args:?} should fail");
        assert!(
            stderr.contains(expect),
            "{args:?}: the error should mention {expect:?}:\n{stderr}"
        );
        assert!(!stderr.contains("panicked"), "{args:?} panicked:\n{stderr}");
        assert!(
            stdout.trim().is_empty(),
            "{args:?} printed a report: {stdout}"
        );
    }
    for (bad, expect) in [
        (
            "wss://example.invalid/scenes/demo",
            "ws://HOST:PORT/scenes/NAME",
        ),
        ("ws://127.0.0.1:1/scenes/demo", "could not connect"),
    ] {
        let (status, _, stderr) =
            run_brickcast(&["load", bad, "--duration", "0.5"], &[], RUN_LIMIT).expect("brickcast");
        assert!(!status.success(), "{bad} should fail");
        assert!(stderr.contains(expect), "{bad}: {stderr}");
    }
    // The editor token works.
    let (report, _) = load_ok(
        &url,
        &["--token", "ed", "--clients", "2", "--duration", "0.5"],
    );
    assert!(num(&report, &["ops_acked"]) > 0.0);
}

#[test]
fn a_run_whose_server_goes_away_fails_loudly() {
    let data = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start(data.path(), local()).expect("server");
    let url = server.url("demo");
    let mut child = brickcast_tests::spawn_brickcast(
        &[
            "load",
            &url,
            "--clients",
            "2",
            "--duration",
            "5",
            "--in-place",
        ],
        &[],
    )
    .expect("brickcast load");
    std::thread::sleep(Duration::from_millis(1500));
    server.stop().expect("server stop");
    let status = child
        .wait_exit(Duration::from_secs(60))
        .expect("wait")
        .expect("brickcast load should end once its server is gone");
    assert!(
        !status.success(),
        "a run that lost its server must not pass"
    );
}

/// `brickcast fly`: clients with a GPU budget get a complete working set, fly with level 0
/// around the eye in most frames, and never hold more than their budget.
#[test]
fn fly_streams_working_sets_within_the_budget() {
    let dir = tempfile::tempdir().expect("tempdir");
    let server = TestServer::start_with(dir.path(), local(), |c| c.demo_size = [512, 64, 512])
        .expect("server starts");
    let url = server.url("demo");
    let budget = 200 * 1024;
    let args = [
        "fly",
        &url,
        "--clients",
        "2",
        "--gpu-budget",
        "200KiB",
        "--duration",
        "3",
        "--speed",
        "4",
        "--full-within",
        "32",
        "--json",
    ];
    let (status, stdout, stderr) = run_brickcast(&args, &[], RUN_LIMIT).expect("brickcast fly");
    assert!(status.success(), "{args:?} failed:\n{stderr}");
    let report: Value = serde_json::from_str(stdout.trim())
        .unwrap_or_else(|e| panic!("stdout is not one JSON object ({e}): {stdout}"));
    assert_eq!(num(&report, &["budget_bytes"]), f64::from(budget));
    assert!(num(&report, &["complete_ms_max"]) > 0.0, "{report}");
    assert!(
        num(&report, &["first_picture_ms_max"]) <= num(&report, &["complete_ms_max"]),
        "{report}"
    );
    // The copy never takes more than its budget: after a move the coarse bricks that let old
    // level 0 go arrive before the new level 0, and arrays that free room takes past the
    // budget are packed.
    eprintln!("{report}");
    assert!(
        num(&report, &["peak_gpu_bytes_max"]) <= f64::from(budget),
        "over the budget: {report}"
    );
    assert!(num(&report, &["sharp_share_all"]) > 0.5, "{report}");
    for flight in report["flights"].as_array().expect("flights") {
        assert!(num(flight, &["frames"]) >= 30.0, "{flight}");
    }
    let (status, _, stderr) =
        run_brickcast(&["fly", &url, "--gpu-budget", "unlimited"], &[], RUN_LIMIT)
            .expect("brickcast fly");
    assert!(!status.success());
    assert!(stderr.contains("limited --gpu-budget"), "{stderr}");
    server.stop().expect("server stops");
}
