//! Durability: kill the server process with SIGKILL while clients edit, restart it, and check
//! that every acknowledged edit is there. Several rounds, each on the recovered store.

mod common;

use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use brickcast_protocol::wire::{EditOp, ServerMsg};
use common::{Client, colour, http_get};

fn free_port() -> SocketAddr {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap()
}

/// The server process; killed and reaped on drop, so a failing assertion leaves no orphan.
struct ServerProcess(Child);

impl ServerProcess {
    /// SIGKILL, and wait for the process to be gone.
    fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

// The child is returned inside `ServerProcess`, whose Drop waits for it.
#[allow(clippy::zombie_processes)]
async fn start(addr: SocketAddr, data: &std::path::Path) -> ServerProcess {
    let mut child = Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
        .args(["serve", "--listen", &addr.to_string(), "--data"])
        .arg(data)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .expect("server starts");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if tokio::net::TcpStream::connect(addr).await.is_ok()
            && http_get(addr, "/healthz").await.0 == 200
        {
            return ServerProcess(child);
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("server did not come up");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Unique voxel and colour of edit `i` of client `c` in round `r`: nothing else writes there.
fn op(r: u32, c: u32, i: u32) -> ([u32; 3], brickcast_protocol::Colour) {
    (
        [i % 128, 48 + r * 4 + i / 128, 100 + c],
        colour(r * 100_000 + c * 1000 + i),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acknowledged_edits_survive_sigkill() {
    let dir = tempfile::tempdir().unwrap();
    let addr = free_port();
    let mut acked: Vec<([u32; 3], brickcast_protocol::Colour)> = Vec::new();
    // Three rounds of edit-then-kill; a fourth start only checks the last kill's survivors.
    for round in 0..4u32 {
        let mut server = start(addr, dir.path()).await;
        // Everything acknowledged in earlier rounds survived the previous kill.
        let mut check = Client::connect(&format!("ws://{addr}/scenes/demo/ws"), None)
            .await
            .unwrap();
        check.sync().await;
        for (pos, c) in &acked {
            assert_eq!(
                check.map.get(*pos),
                Some(*c),
                "round {round}: acknowledged edit at {pos:?} lost"
            );
        }
        check.close().await;
        if round == 3 {
            break;
        }

        let progress = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let mut tasks = Vec::new();
        for client in 0..3u32 {
            let url = format!("ws://{addr}/scenes/demo/ws");
            let progress = progress.clone();
            tasks.push(tokio::spawn(async move {
                let mut c = Client::connect(&url, None).await.unwrap();
                let mut done = Vec::new();
                let mut i = 0;
                'outer: while i < 500 {
                    let batch: Vec<u32> = (i..(i + 10).min(500)).collect();
                    i += batch.len() as u32;
                    let ops = batch.iter().map(|&k| {
                        let (pos, colour) = op(round, client, k);
                        EditOp::Set { pos, colour }
                    });
                    let cs = c.send_edit(ops.collect()).await;
                    loop {
                        match c.next().await {
                            Some(ServerMsg::Ack {
                                client_seq,
                                seq: Some(_),
                                applied,
                                ..
                            }) if client_seq == cs => {
                                assert_eq!(applied as usize, batch.len());
                                done.extend(batch.iter().map(|&k| op(round, client, k)));
                                progress
                                    .fetch_add(batch.len(), std::sync::atomic::Ordering::Relaxed);
                                break;
                            }
                            Some(_) => {}
                            None => break 'outer,
                        }
                    }
                }
                done
            }));
        }
        // Kill mid-stream, at a different point each round: once this many edits are acknowledged.
        let kill_at = 60 + 150 * round as usize;
        let deadline = Instant::now() + Duration::from_secs(60);
        while progress.load(std::sync::atomic::Ordering::Relaxed) < kill_at {
            assert!(
                Instant::now() < deadline,
                "round {round}: clients made no progress"
            );
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        server.kill();
        let mut this_round = 0;
        for t in tasks {
            let done = t.await.unwrap();
            this_round += done.len();
            acked.extend(done);
        }
        eprintln!("round {round}: {this_round} of 1500 edits acknowledged before SIGKILL");
        assert!(
            this_round >= kill_at && this_round < 1500,
            "round {round}: the kill came mid-stream"
        );
    }
}
