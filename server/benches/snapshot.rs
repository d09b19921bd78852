//! Cluster snapshots: what the owner thread spends preparing a whole base against a delta of
//! the bricks changed since, and what encoding each costs off the thread (`cluster/snapshot.rs`).
//!
//! `cargo bench -p brickcast-server --bench snapshot`

use std::collections::HashMap;
use std::hint::black_box;

use brickcast_protocol::{BrushMode, Colour, demo};
use brickcast_server::cluster::snapshot::{self, Chain};
use brickcast_server::scene::history::History;
use criterion::{Criterion, criterion_group, criterion_main};

fn snapshots(c: &mut Criterion) {
    let size = 1024;
    let k = size as f32 / 512.0;
    let mut map = demo::demo_scene([size; 3]).expect("the demo scene builds");
    let history = History::new(Vec::new(), 0, 1, 0);
    let steps = HashMap::new();
    let base = snapshot::prepare(None, &map, &[], 1, 1, &history, &steps, Vec::new());
    let base = base.encode("demo", None).expect("the base encodes");
    let chain: Chain = base.chain.clone();
    // A minute of a few people editing: a hundred small spheres.
    map.record_touched(true);
    for i in 0..100u32 {
        let at = [
            (40 + i * 37 % 430) as f32 * k,
            (60 + i * 13 % 200) as f32 * k,
            (40 + i * 91 % 430) as f32 * k,
        ];
        map.set_sequence(u64::from(i) + 2);
        map.sphere(at, 4.0 * k, BrushMode::Fill, Colour::from_rgb8(200, 40, 40));
    }
    let changed = map.take_touched();
    map.record_touched(false);
    let seq = map.sequence();
    eprintln!(
        "{size}³ demo: {} bricks, {} changed; base {} bytes",
        map.brick_count(),
        changed.len(),
        base.bytes.len()
    );
    let prepare = |chain: Option<&Chain>| {
        snapshot::prepare(chain, &map, &changed, seq, 2, &history, &steps, Vec::new())
    };
    let delta = prepare(Some(&chain))
        .encode("demo", Some(chain.clone()))
        .expect("the delta encodes");
    eprintln!("delta {} bytes", delta.bytes.len());
    let mut g = c.benchmark_group("snapshot");
    g.sample_size(10);
    g.bench_function("prepare_base", |b| b.iter(|| black_box(prepare(None))));
    g.bench_function("prepare_delta", |b| {
        b.iter(|| black_box(prepare(Some(&chain))))
    });
    g.bench_function("encode_base", |b| {
        b.iter_batched(
            || prepare(None),
            |p| black_box(p.encode("demo", None).map(|e| e.bytes.len())),
            criterion::BatchSize::LargeInput,
        )
    });
    g.bench_function("encode_delta", |b| {
        b.iter_batched(
            || prepare(Some(&chain)),
            |p| black_box(p.encode("demo", Some(chain.clone())).map(|e| e.bytes.len())),
            criterion::BatchSize::SmallInput,
        )
    });
    g.finish();
}

criterion_group!(benches, snapshots);
criterion_main!(benches);
