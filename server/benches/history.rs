//! The scene's history (issue #34): opening the timeline and a view of an earlier sequence on
//! a scene with a million logged ops (`store/past.rs`).
//!
//! `cargo bench -p brickcast-server --bench history`
//!
//! A 256³ demo scene takes 1,000,000 one-voxel messages from eight users, written a thousand
//! to a turn, with a snapshot every 250,000 sequences (the points the past rebuilds from), the
//! last 250,000 left in the live log. Timed: the timeline of everything kept (the latest 1,000
//! changes), views of a sequence just after a kept point and just before the next (rebuilt
//! from the point plus 1 and 249,999 ops), and the present loaded the way a restart loads it,
//! for scale. Printed first: what each snapshot took, keeping the past and keeping none.

use std::hint::black_box;

use brickcast_protocol::wire::EditOp;
use brickcast_protocol::{BrickMap, Colour, demo};
use brickcast_server::record::LogRecord;
use brickcast_server::scene::history::HistoryWrites;
use brickcast_server::store::Store;
use criterion::{Criterion, criterion_group, criterion_main};

const OPS: u64 = 1_000_000;
const TURN: u64 = 1_000;
const SNAPSHOT_EVERY: u64 = 250_000;

fn op(seq: u64) -> EditOp {
    // A walk over the scene's top half: every message changes a voxel somewhere new.
    let h = seq.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let pos = [
        (h % 256) as u32,
        128 + ((h >> 8) % 128) as u32,
        ((h >> 16) % 256) as u32,
    ];
    EditOp::Set {
        pos,
        colour: Colour((h >> 32) as u16),
    }
}

/// Writes the million ops; what each snapshot took.
fn build(store: &Store) -> (BrickMap, Vec<f64>) {
    let mut snapshots = Vec::new();
    let mut map = demo::demo_scene([256; 3]).expect("the demo scene builds");
    store.create_scene("h", &map).expect("created");
    map.record_touched(true);
    let mut turn = Vec::with_capacity(TURN as usize);
    for seq in 1..=OPS {
        let op = op(seq);
        map.set_sequence(seq);
        brickcast_protocol::apply::apply_op(&mut map, &op, &Default::default()).expect("applies");
        turn.push((
            seq,
            LogRecord::Ops {
                user: seq % 8 + 1,
                ops: vec![op],
            },
        ));
        if seq % TURN == 0 {
            store
                .append("h", &turn, &HistoryWrites::default())
                .expect("appended");
            turn.clear();
        }
        if seq % SNAPSHOT_EVERY == 0 && seq < OPS {
            let cells = map.take_touched();
            let started = std::time::Instant::now();
            store.snapshot("h", &map, &cells, seq).expect("snapshot");
            snapshots.push(started.elapsed().as_secs_f64());
        }
    }
    (map, snapshots)
}

fn history(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("a temporary folder");
    let store = Store::open(dir.path()).expect("the store opens");
    // What keeping the past costs a snapshot: the same ops into a store that keeps none.
    let none = tempfile::tempdir().expect("a temporary folder");
    let bare = Store::open(none.path()).expect("the store opens");
    bare.set_keep_history(0);
    let (_, bare_snapshots) = build(&bare);
    drop(bare);
    let started = std::time::Instant::now();
    let (map, snapshots) = build(&store);
    let span = store.past_span("h").expect("a span");
    eprintln!(
        "{OPS} ops logged in {:.1} s; {} bricks; kept {}..={}",
        started.elapsed().as_secs_f64(),
        map.brick_count(),
        span.oldest,
        span.newest
    );
    let ms = |v: &[f64]| {
        v.iter()
            .map(|s| format!("{:.0}", s * 1e3))
            .collect::<Vec<_>>()
            .join(", ")
    };
    eprintln!(
        "snapshots (ms) keeping the past: {}; keeping none: {}",
        ms(&snapshots),
        ms(&bare_snapshots)
    );
    assert_eq!(
        store.scene_at("h", OPS).expect("now").content_hash(),
        map.content_hash()
    );
    let mut g = c.benchmark_group("history");
    g.sample_size(10);
    g.bench_function("timeline_1m", |b| {
        b.iter(|| black_box(store.timeline("h", 1000).expect("timeline").1.len()))
    });
    // Just after a kept point (one op to replay), and just before the next (a whole
    // interval of 249,999 ops).
    let view = |seq: u64| store.scene_at("h", seq).expect("past").brick_count();
    g.bench_function("view_after_a_point", |b| {
        b.iter(|| black_box(view(OPS / 2 + 1)))
    });
    g.bench_function("view_before_a_point", |b| {
        b.iter(|| black_box(view(OPS / 2 + SNAPSHOT_EVERY - 1)))
    });
    g.bench_function("load_now", |b| {
        b.iter(|| black_box(store.load_scene("h").expect("loads").seq))
    });
    g.finish();
}

criterion_group!(benches, history);
criterion_main!(benches);
