//! A paste and a restore of a million voxels, end to end (issue #34): a real server on
//! loopback and three clients. Alice fills a 100×60×168 box (1,008,000 voxels), copies it, and
//! then, five times: pastes it beside itself, undoes the paste, restores the pasted box to the
//! sequence after the paste (the restore rebuilds the past in the store), and undoes that.
//! Measured per action: the time to Alice's Ack, and until Bob (a full-scene client) has the
//! delta; meanwhile Carol sets one voxel every 5 ms, and her slowest Ack during each action is
//! what the action stalled others' edits (the owner applies a paste or a restore in one turn).
//!
//! `cargo bench -p brickcast-tests --bench paste`

use std::time::{Duration, Instant};

use brickcast_client::link::Link;
use brickcast_protocol::Colour;
use brickcast_protocol::wire::{BrushMode, ClientMsg, EditOp, ServerMsg};
use brickcast_server::{Server, ServerConfig};

const RUNS: usize = 5;
const BOX_MIN: [u32; 3] = [0, 64, 0];
const BOX_MAX: [u32; 3] = [99, 123, 167];
const SIZE: [u32; 3] = [100, 60, 168];
const PASTE_AT: [u32; 3] = [120, 64, 0];

/// Sends `msg` (carrying `client_seq`) from `from` and times its Ack there and the delta
/// holding its sequence at `to`: (ack, seen, the sequence).
async fn timed(from: &mut Link, to: &mut Link, client_seq: u64, msg: ClientMsg) -> (f64, f64, u64) {
    let start = Instant::now();
    from.send(&msg).await.expect("sent");
    let seq = loop {
        match from.next().await.expect("read").expect("open") {
            ServerMsg::Ack {
                client_seq: c,
                seq,
                rejected,
                ..
            } if c == client_seq => {
                assert!(rejected.is_empty(), "{rejected:?}");
                break seq.expect("applied");
            }
            ServerMsg::Undone {
                client_seq: c, seq, ..
            } if c == client_seq => {
                break seq.expect("undone");
            }
            _ => {}
        }
    };
    let ack = start.elapsed().as_secs_f64();
    loop {
        if let ServerMsg::Delta { to_seq, .. } = to.next().await.expect("read").expect("open")
            && to_seq >= seq
        {
            break;
        }
    }
    (ack, start.elapsed().as_secs_f64(), seq)
}

/// One action timed: to its Ack, until Bob has it (seconds), and when it started and ended.
type Run = (f64, f64, Instant, Instant);

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("a runtime");
    runtime.block_on(run());
}

async fn run() {
    let data = tempfile::tempdir().expect("a folder");
    let mut config = ServerConfig::new("127.0.0.1:0".parse().unwrap(), data.path().into());
    config.demo_size = [256, 128, 256];
    let server = Server::bind(config).await.expect("binds");
    let addr = server.local_addr().expect("an address");
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let served = tokio::spawn(server.run(async move {
        let _ = stopped.await;
    }));
    let url = format!("ws://{addr}/scenes/demo/ws");
    let mut alice = Link::connect(&url, "alice", 1, None, None)
        .await
        .expect("alice");
    let mut bob = Link::connect(&url, "bob", 2, None, None)
        .await
        .expect("bob");
    let mut carol = Link::connect(&url, "carol", 3, None, None)
        .await
        .expect("carol");
    let mut client_seq = 0;
    let mut next = || {
        client_seq += 1;
        client_seq
    };
    let edit = |client_seq, ops| ClientMsg::Edit { client_seq, ops };
    let c = next();
    let fill = EditOp::Box {
        min: BOX_MIN,
        max: BOX_MAX,
        mode: BrushMode::Fill,
        colour: Colour::from_rgb8(200, 60, 60),
    };
    timed(&mut alice, &mut bob, c, edit(c, vec![fill])).await;
    let c = next();
    let copy = EditOp::Copy {
        min: BOX_MIN,
        max: BOX_MAX,
    };
    alice.send(&edit(c, vec![copy])).await.expect("copy");

    // Carol's steady one-voxel edits, each Ack timed, until told to stop.
    let (carol_stop, mut carol_stopped) = tokio::sync::watch::channel(false);
    let carol_task = tokio::spawn(async move {
        let mut latencies: Vec<(Instant, f64)> = Vec::new();
        let mut n = 0u64;
        let mut tick = tokio::time::interval(Duration::from_millis(5));
        while !*carol_stopped.borrow() {
            tokio::select! {
                _ = tick.tick() => {}
                _ = carol_stopped.changed() => break,
            }
            n += 1;
            let msg = ClientMsg::Edit {
                client_seq: n,
                ops: vec![EditOp::Set {
                    pos: [250, 100 + (n % 20) as u32, 250],
                    colour: Colour::from_rgb8(0, 0, (n % 255) as u8),
                }],
            };
            let sent = Instant::now();
            carol.send(&msg).await.expect("carol sends");
            loop {
                match carol.next().await.expect("carol reads").expect("open") {
                    ServerMsg::Ack { client_seq, .. } if client_seq == n => break,
                    _ => {}
                }
            }
            latencies.push((sent, sent.elapsed().as_secs_f64()));
        }
        latencies
    });

    let mut rows: Vec<(&str, Vec<Run>)> = vec![
        ("paste", Vec::new()),
        ("undo the paste", Vec::new()),
        ("restore", Vec::new()),
        ("undo the restore", Vec::new()),
    ];
    for _ in 0..RUNS {
        let c = next();
        let t0 = Instant::now();
        let paste = EditOp::Paste {
            at: PASTE_AT,
            size: SIZE,
            turns: 0,
            mirror: false,
        };
        let (ack, seen, pasted) = timed(&mut alice, &mut bob, c, edit(c, vec![paste])).await;
        rows[0].1.push((ack, seen, t0, Instant::now()));
        let c = next();
        let t0 = Instant::now();
        let (ack, seen, _) =
            timed(&mut alice, &mut bob, c, ClientMsg::Undo { client_seq: c }).await;
        rows[1].1.push((ack, seen, t0, Instant::now()));
        let c = next();
        let t0 = Instant::now();
        let restore = EditOp::Restore {
            to: pasted,
            min: PASTE_AT,
            max: std::array::from_fn(|i| PASTE_AT[i] + SIZE[i] - 1),
        };
        let (ack, seen, _) = timed(&mut alice, &mut bob, c, edit(c, vec![restore])).await;
        rows[2].1.push((ack, seen, t0, Instant::now()));
        let c = next();
        let t0 = Instant::now();
        let (ack, seen, _) =
            timed(&mut alice, &mut bob, c, ClientMsg::Undo { client_seq: c }).await;
        rows[3].1.push((ack, seen, t0, Instant::now()));
    }
    let _ = carol_stop.send(true);
    let carol = carol_task.await.expect("carol");
    println!(
        "| action (1,008,000 voxels) | to Ack (median of {RUNS}) | until Bob has it | Carol's slowest Ack meanwhile (median) |"
    );
    println!("|---|---|---|---|");
    for (name, runs) in &rows {
        let stall: Vec<f64> = runs
            .iter()
            .map(|&(_, _, from, to)| {
                carol
                    .iter()
                    .filter(|(sent, _)| *sent >= from && *sent <= to)
                    .map(|&(_, l)| l)
                    .fold(0.0, f64::max)
            })
            .collect();
        println!(
            "| {name} | {:.1} ms | {:.1} ms | {:.1} ms |",
            1e3 * median(runs.iter().map(|r| r.0).collect()),
            1e3 * median(runs.iter().map(|r| r.1).collect()),
            1e3 * median(stall),
        );
    }
    let all: Vec<f64> = carol.iter().map(|&(_, l)| l).collect();
    println!(
        "Carol: {} one-voxel edits, median Ack {:.2} ms",
        all.len(),
        1e3 * median(all)
    );
    let _ = stop.send(());
    served.await.expect("served").expect("stopped cleanly");
}
