//! The cluster simulation's test: thousands of seeds, from a random first seed each run.
//!
//! `BRICKCAST_CLUSTER_SIM_SEED=N` replays one seed (its trace on failure);
//! `BRICKCAST_CLUSTER_SIM_SEEDS` sets how many seeds run (2,000 by default);
//! `BRICKCAST_CLUSTER_SIM_FIRST` the first one (random by default, printed).

use std::io::Write;

use super::*;
use crate::sim::seeds::{SeedRun, run_seeds};

fn env_u64(name: &str) -> Option<u64> {
    std::env::var(name).ok().and_then(|v| v.parse().ok())
}

/// Written past the test harness's capture, so that a passing run says which seeds it ran.
fn say(what: &str) {
    let _ = writeln!(std::io::stderr(), "{what}");
}

#[test]
fn the_cluster_survives_random_faults() {
    if let Some(seed) = env_u64("BRICKCAST_CLUSTER_SIM_SEED") {
        match run_seed(seed) {
            Ok(stats) => say(&format!("cluster simulation seed {seed}: {stats:?}")),
            Err((e, trace)) => panic!("seed {seed} failed: {e}\nlast actions:\n{trace}"),
        }
        return;
    }
    let first = env_u64("BRICKCAST_CLUSTER_SIM_FIRST").unwrap_or_else(|| {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        (nanos % 1_000_000_000) * 1000
    });
    let seeds = env_u64("BRICKCAST_CLUSTER_SIM_SEEDS").unwrap_or(2_000);
    say(&format!(
        "cluster simulation: seeds {first}..{} (BRICKCAST_CLUSTER_SIM_FIRST={first} repeats this run)",
        first + seeds
    ));
    let SeedRun {
        ran,
        stats,
        threads,
        elapsed,
        failed,
    } = run_seeds(first, |seed, _| seed >= first + seeds, run_seed);
    say(&format!(
        "cluster simulation: {ran} seeds from {first} in {:.1} s on {threads} threads: {stats:?}",
        elapsed.as_secs_f64()
    ));
    if let Some((seed, e, trace)) = failed {
        panic!(
            "cluster simulation seed {seed} failed: {e}\nlast actions:\n{trace}\nreplay: BRICKCAST_CLUSTER_SIM_SEED={seed} cargo test -p brickcast-server cluster::sim"
        );
    }
    assert!(ran > 0, "no seed ran");
    assert!(
        stats.lease_window_pauses > 0
            && stats.kills > 0
            && stats.stops > 0
            && stats.name_takeovers > 0
            && stats.outages > 0
            && stats.network_faults > 0
            && stats.second_names > 0
            && stats.acks > ran,
        "the seeds must pause owners just under their lease, kill and stop nodes, take names, take NATS down, break the network, serve a scene under two names on a node and acknowledge edits: {stats:?}"
    );
    if seeds >= 200 {
        assert!(
            stats.garbage > 0 && stats.repairs > 0,
            "some seeds must put garbage on the log, and repair it: {stats:?}"
        );
    }
}

/// A simulated NATS server (its RNG from `seed`), a paused single-threaded runtime to call it
/// from, and that runtime's time at the start (a process clock's base).
fn simulated_jet(
    seed: u64,
) -> (
    Arc<Mutex<jet::World>>,
    tokio::runtime::Runtime,
    tokio::time::Instant,
) {
    let world = Arc::new(Mutex::new(jet::World::new(ChaCha8Rng::seed_from_u64(seed))));
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_time()
        .start_paused(true)
        .build()
        .unwrap();
    let base = rt.block_on(async { tokio::time::Instant::now() });
    (world, rt, base)
}

/// A node starting while NATS does not answer waits for it; a create that landed with its
/// answer lost is found again, not taken for another process's name. (Before, the first
/// unanswered request ended the start.)
#[test]
fn a_starting_node_waits_for_nats_and_finds_its_own_name() {
    use crate::cluster::jet::{Bucket, Jet};
    use crate::cluster::name;

    let (world, rt, base) = simulated_jet(2);
    let jet = |process| jet::SimJet {
        world: world.clone(),
        process,
        clock: Arc::new(jet::ProcessClock { base, rate: 1.0 }),
    };
    // NATS is down for the first 3 s of the node's life.
    world.lock().unwrap().faults.down_until = Duration::from_secs(3);
    let first = jet(1);
    let name = rt
        .block_on(name::register(&first, "n0", "n0#1".into(), "sim"))
        .expect("the node waits for NATS");
    assert!(world.lock().unwrap().now >= Duration::from_secs(3));
    rt.block_on(name.release());
    // Every write's answer is lost: the create lands, the node does not hear so.
    world.lock().unwrap().faults.lost_acks = 1.0;
    let second = jet(2);
    let started = rt.block_on(async { tokio::time::Instant::now() });
    let name = rt
        .block_on(name::register(&second, "n1", "n1#2".into(), "sim"))
        .expect("the node finds its own entry");
    let waited = rt.block_on(async { started.elapsed() });
    assert!(waited < Duration::from_secs(2), "{waited:?}");
    let entry = rt
        .block_on(second.kv_get(Bucket::Nodes, "n1"))
        .unwrap()
        .expect("the name is held");
    assert!(String::from_utf8_lossy(&entry.value).contains("n1#2"));
    assert!(name.lost.get().is_none());
    // NATS that never answers ends the start, with why.
    world.lock().unwrap().faults = jet::Faults {
        down_until: Duration::from_secs(3600),
        ..Default::default()
    };
    let err = rt
        .block_on(name::register(&jet(3), "n2", "n2#3".into(), "sim"))
        .err()
        .expect("NATS never answered");
    assert!(err.to_string().contains("tried for"), "{err}");
}

/// A scene written before snapshot heads existed (base `<scene>`, deltas `<scene>+N`) loads
/// as it was; its next snapshot starts a head, which a load then follows.
#[test]
fn a_scene_from_before_heads_loads_and_its_next_snapshot_starts_one() {
    use crate::cluster::jet::{Jet, LogStream};
    use crate::cluster::log::{encode_turn, load};
    use crate::record::LogRecord;
    use crate::scene::Turn;
    use crate::scene::history::History;

    let (world, rt, base) = simulated_jet(1);
    let jet = jet::SimJet {
        world,
        process: 1,
        clock: Arc::new(jet::ProcessClock { base, rate: 1.0 }),
    };
    let map = initial_scene();
    rt.block_on(async {
        // As an older brickcast left it: the base under the scene's own name, one turn after.
        let old = snapshot::first(&map).encode(SCENE, None).unwrap();
        jet.object_put(SCENE, &old.description, old.bytes.clone())
            .await
            .unwrap();
        let stream = jet.stream(SCENE, true).await.unwrap();
        let mut bytes = Vec::new();
        LogRecord::Ops {
            user: 3,
            ops: vec![EditKey { user: 3, k: 0 }.op()],
        }
        .encode(&mut bytes)
        .unwrap();
        let turn = Turn {
            node: "old".into(),
            records: vec![(1, bytes)],
            ..Default::default()
        };
        let payload = Bytes::from(encode_turn(&turn).unwrap());
        stream.append(payload, "t1", 0).await.unwrap();

        let loaded = load(&jet, SCENE).await.unwrap();
        assert_eq!((loaded.loaded.seq, loaded.pos), (1, 1));
        assert_eq!(snapshot::newest(&jet, SCENE).await, Some((0, 0, 0)));
        let mut scene = loaded.loaded.map;
        scene.set_sequence(1);
        let history = History::new(Vec::new(), 0, 4, 1 << 20);
        let snapshot_at = |map: &BrickMap, at: u64| {
            snapshot::prepare(
                None,
                map,
                &[],
                at,
                at,
                &history,
                &Default::default(),
                Vec::new(),
            )
            .encode(SCENE, None)
            .unwrap()
        };
        let next = snapshot_at(&scene, 1);
        assert!(matches!(
            snapshot::store(&jet, &next).await.unwrap(),
            snapshot::Stored::Moved { before: None }
        ));
        assert_eq!(snapshot::newest(&jet, SCENE).await, Some((1, 1, 0)));
        let again = load(&jet, SCENE).await.unwrap();
        assert_eq!((again.loaded.seq, again.pos), (1, 1));
        assert_eq!(again.loaded.map.content_hash(), scene.content_hash());
        // A late snapshot (further back in the log) does not move the head, and leaves no
        // object behind.
        let late = snapshot_at(&map, 0);
        assert!(matches!(
            snapshot::store(&jet, &late).await.unwrap(),
            snapshot::Stored::Stale { .. }
        ));
        assert_eq!(jet.object_get(&late.name).await.unwrap(), None);
        assert_eq!(snapshot::newest(&jet, SCENE).await, Some((1, 1, 0)));
    });
}

/// The scene list under changes through two nodes at once (issue #32): a rename whose source
/// was reset meanwhile is undone, not left pointing two names at logs; a kept scene is only
/// purged with the log another kept or live scene uses left alone; a restore of a kept scene
/// purged meanwhile puts nothing back; `import --replace` gives the name a new log key, so
/// the nodes serving the old scene see it replaced.
#[test]
fn the_scene_list_refuses_changes_that_crossed() {
    use crate::cluster::jet::{Bucket, Jet};
    use crate::cluster::{catalog, deleted};

    let (world, rt, base) = simulated_jet(3);
    let jet = jet::SimJet {
        world: world.clone(),
        process: 1,
        clock: Arc::new(jet::ProcessClock { base, rate: 1.0 }),
    };
    let map = initial_scene();
    rt.block_on(async {
        catalog::create_scene(&jet, "a", &map, false).await.unwrap();
        // A rename that read `a` before it was reset through another node: its delete at the
        // revision read fails, and the new name is taken back.
        let (entry, old) = catalog::scene_entry_at(&jet, "a").await.unwrap().unwrap();
        let replaced = crate::cluster::SceneEntry::new("a", entry.size, "a=99");
        let value = bytes::Bytes::from(serde_json::to_vec(&replaced).unwrap());
        jet.kv_update(Bucket::Scenes, "a", value, old)
            .await
            .unwrap();
        let moved = crate::cluster::SceneEntry::new("b", entry.size, "a");
        catalog::put_new(&jet, "b", &moved).await.unwrap();
        let crossed = jet.kv_delete(Bucket::Scenes, "a", Some(old)).await;
        assert!(crossed.is_err(), "a stale revision deletes nothing");
        let back = catalog::scene_entry(&jet, "a").await.unwrap().unwrap();
        assert_eq!(back.log_key("a"), "a=99", "the reset stands");
        // Through the function itself: `a` is renamed at the revision it reads.
        jet.kv_delete(Bucket::Scenes, "b", None).await.unwrap();
        let renamed = catalog::rename_scene(&jet, "a", "b").await.unwrap();
        assert_eq!(renamed.log_key("b"), "a=99");
        assert!(catalog::scene_entry(&jet, "a").await.unwrap().is_none());

        // `import --replace` gives the name a new log key, never the one it replaces (here
        // the name itself, which the old log no longer holds once it is dropped).
        catalog::create_scene(&jet, "d", &map, false).await.unwrap();
        catalog::create_scene(&jet, "d", &map, true).await.unwrap();
        let d = catalog::scene_entry(&jet, "d").await.unwrap().unwrap();
        assert_ne!(
            d.log_key("d"),
            "d",
            "nodes serving the old d must see another log"
        );
        catalog::create_scene(&jet, "b", &map, true).await.unwrap();
        let now = catalog::scene_entry(&jet, "b").await.unwrap().unwrap();
        assert_ne!(now.log_key("b"), "a=99");

        // Two kept scenes of one log (a delete that crossed a restore): purging one leaves
        // the log the other still needs.
        let kept = deleted::delete_keeping(&jet, "b", 1_000, 60).await.unwrap();
        let key = now.log_key("b").to_string();
        let twin = deleted::Deleted {
            key: "deleted=2000=b".into(),
            deleted_at: 2,
            ..kept.clone()
        };
        let value = bytes::Bytes::from(serde_json::to_vec(&twin).unwrap());
        jet.kv_create(Bucket::Scenes, &twin.key, value)
            .await
            .unwrap();
        deleted::purge_key(&jet, &kept.key).await.unwrap();
        assert!(
            crate::cluster::log::load(&jet, &key).await.is_ok(),
            "the log the other kept scene uses is still there"
        );
        // A restore of a kept scene purged meanwhile: nothing put back.
        deleted::purge_key(&jet, &twin.key).await.unwrap();
        let gone = deleted::restore(&jet, &twin.key, Some("c")).await;
        assert!(gone.is_err());
        assert!(catalog::scene_entry(&jet, "c").await.unwrap().is_none());
    });
}
