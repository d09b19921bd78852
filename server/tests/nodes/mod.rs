//! The cluster harness the cluster tests share: a real `nats-server` with JetStream on a free
//! loopback port, `brickcast-server serve --nats` processes, and writers that remember what was
//! acknowledged.

#![allow(dead_code)]

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::time::{Duration, Instant};

use brickcast_protocol::Colour;
use brickcast_protocol::wire::{EditOp, ServerMsg};

use crate::common::{Client, colour, http_get};

pub fn free_port() -> u16 {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap().port()
}

/// Debian puts `nats-server` in /usr/sbin, which is not on every user's PATH.
pub fn nats_binary() -> PathBuf {
    for dir in std::env::var("PATH").unwrap_or_default().split(':') {
        let p = Path::new(dir).join("nats-server");
        if p.is_file() {
            return p;
        }
    }
    for p in ["/usr/sbin/nats-server", "/usr/local/bin/nats-server"] {
        if Path::new(p).is_file() {
            return p.into();
        }
    }
    panic!("nats-server is not installed (scripts/setup installs it)");
}

/// A `nats-server` with JetStream, killed on drop.
pub struct Nats {
    pub child: Option<Child>,
    pub port: u16,
    pub dir: tempfile::TempDir,
    pub jetstream: bool,
    /// A configuration file (`-c`), e.g. users and permissions.
    pub config: Option<PathBuf>,
    /// Whether it came up once (restarts keep the port).
    pub started: bool,
}

impl Nats {
    pub fn start(jetstream: bool) -> Nats {
        let mut nats = Nats {
            child: None,
            port: free_port(),
            dir: tempfile::tempdir().unwrap(),
            jetstream,
            config: None,
            started: false,
        };
        nats.spawn();
        nats
    }

    /// A `nats-server` with JetStream and the configuration `conf` (users, permissions).
    pub fn start_with_config(conf: &str) -> Nats {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nats.conf");
        std::fs::write(&path, conf).unwrap();
        let mut nats = Nats {
            child: None,
            port: free_port(),
            dir,
            jetstream: true,
            config: Some(path),
            started: false,
        };
        nats.spawn();
        nats
    }

    /// The URL with a user's credentials.
    pub fn url_as(&self, user: &str, password: &str) -> String {
        format!("nats://{user}:{password}@127.0.0.1:{}", self.port)
    }

    /// Starts (or restarts) the server. A free port can be taken by another test between
    /// `free_port` and the server's bind, so this checks that our own child answers with the
    /// NATS greeting; on a first start it tries again on another port, on a restart (the nodes
    /// know the URL) on the same one.
    pub fn spawn(&mut self) {
        let first_start = !self.started;
        for _ in 0..5 {
            if self.try_spawn() {
                self.started = true;
                return;
            }
            self.kill();
            if first_start {
                self.port = free_port();
            } else {
                std::thread::sleep(Duration::from_millis(500));
            }
        }
        panic!("nats-server did not come up on 127.0.0.1:{}", self.port);
    }

    /// One start; whether our child came up and greets on the port.
    fn try_spawn(&mut self) -> bool {
        use std::io::Read;
        let mut cmd = Command::new(nats_binary());
        if let Some(config) = &self.config {
            cmd.arg("-c").arg(config);
        }
        cmd.args(["-a", "127.0.0.1", "-p", &self.port.to_string()]);
        if self.jetstream {
            cmd.arg("-js").arg("-sd").arg(self.dir.path());
        }
        let child = cmd
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("nats-server starts");
        let child = self.child.insert(child);
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if !matches!(child.try_wait(), Ok(None)) {
                return false;
            }
            if let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", self.port)) {
                let _ = s.set_read_timeout(Some(Duration::from_secs(2)));
                let mut greeting = [0u8; 4];
                let ours = s.read_exact(&mut greeting).is_ok() && &greeting == b"INFO";
                return ours && matches!(child.try_wait(), Ok(None));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        false
    }

    pub fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }

    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.kill();
    }
}

/// One `brickcast-server serve --nats` process, killed on drop. Its log goes to a file.
pub struct Node {
    pub child: Option<Child>,
    pub addr: SocketAddr,
    pub name: String,
    pub log: PathBuf,
    pub _data: tempfile::TempDir,
}

pub fn signal(child: &Child, sig: i32) {
    // SAFETY: kill(2) on our own child's pid.
    unsafe {
        libc::kill(child.id() as i32, sig);
    }
}

impl Node {
    /// Starts a node, waits until it answers HTTP, and opens the demo scene on it the way
    /// people do (a client joins and leaves): nodes open scenes on demand.
    pub async fn start(nats: &str, name: &str, extra: &[&str]) -> Node {
        let node = Node::start_bare(nats, name, extra).await;
        let mut c = Client::connect(&node.url(), None)
            .await
            .unwrap_or_else(|e| panic!("node {name} serves no demo scene: {e:?}"));
        c.sync().await;
        c.close().await;
        node
    }

    /// Starts a node and waits until it answers HTTP.
    /// A node whose port another test took between `free_port` and its bind starts again on
    /// another port.
    pub async fn start_bare(nats: &str, name: &str, extra: &[&str]) -> Node {
        let mut node = Node::spawn(nats, name, extra);
        let mut tries = 0;
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if node.exited() && node.log_text().contains("in use") && tries < 5 {
                tries += 1;
                node = Node::spawn(nats, name, extra);
                continue;
            }
            if !node.exited()
                && tokio::net::TcpStream::connect(node.addr).await.is_ok()
                && http_get(node.addr, "/healthz").await.0 == 200
            {
                return node;
            }
            assert!(
                Instant::now() < deadline,
                "node {name} did not come up: {}",
                node.log_text()
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    pub fn spawn(nats: &str, name: &str, extra: &[&str]) -> Node {
        let data = tempfile::tempdir().unwrap();
        let addr: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
        let log = data.path().join("node.log");
        let file = std::fs::File::create(&log).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_brickcast-server"))
            .args(["serve", "--listen", &addr.to_string(), "--nats", nats])
            .args(["--node", name, "--data"])
            .arg(data.path())
            .args(extra)
            .env("RUST_LOG", "warn,brickcast_server=info")
            .env("NO_COLOR", "1")
            .stdout(file.try_clone().unwrap())
            .stderr(file)
            .spawn()
            .expect("node starts");
        Node {
            child: Some(child),
            addr,
            name: name.into(),
            log,
            _data: data,
        }
    }

    pub fn url(&self) -> String {
        format!("ws://{}/scenes/demo/ws", self.addr)
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Whether the process has exited.
    pub fn exited(&mut self) -> bool {
        self.child
            .as_mut()
            .is_none_or(|c| !matches!(c.try_wait(), Ok(None)))
    }

    /// Waits for the process to exit by itself; its status.
    pub fn wait_exit(&mut self, within: Duration) -> Option<std::process::ExitStatus> {
        let deadline = Instant::now() + within;
        let child = self.child.as_mut()?;
        loop {
            if let Ok(Some(status)) = child.try_wait() {
                return Some(status);
            }
            if Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGSTOP, and wait until the process is stopped (signals are delivered asynchronously:
    /// until then it may still read its sockets).
    pub fn stop(&self) {
        let child = self.child.as_ref().unwrap();
        signal(child, libc::SIGSTOP);
        let stat = format!("/proc/{}/stat", child.id());
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let state = std::fs::read_to_string(&stat).unwrap_or_default();
            // The state follows the command name in parentheses.
            if state
                .rsplit_once(") ")
                .is_some_and(|(_, rest)| rest.starts_with('T'))
            {
                return;
            }
            assert!(Instant::now() < deadline, "the node did not stop: {state}");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    pub fn cont(&self) {
        signal(self.child.as_ref().unwrap(), libc::SIGCONT);
    }

    /// Whether this node owns the demo scene now (from `/scenes`).
    pub async fn owns(&self) -> bool {
        self.demo_entry().await["owned_here"] == true
    }

    /// Whether this node serves the demo scene now (from `/scenes`).
    pub async fn serves(&self) -> bool {
        self.demo_entry().await["open"] == true
    }

    /// What `/scenes` says of the demo scene (null when it does not list it).
    pub async fn demo_entry(&self) -> serde_json::Value {
        let (status, body) = http_get(self.addr, "/scenes").await;
        if status != 200 {
            return serde_json::Value::Null;
        }
        let list: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        list.as_array()
            .into_iter()
            .flatten()
            .find(|s| s["name"] == "demo")
            .cloned()
            .unwrap_or_default()
    }

    /// A counter from `/metrics`.
    pub async fn metric(&self, name: &str) -> u64 {
        let (_, text) = http_get(self.addr, "/metrics").await;
        text.lines()
            .find_map(|l| l.strip_prefix(&format!("brickcast_{name} ")))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(0)
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        if let Some(c) = &self.child {
            signal(c, libc::SIGCONT);
        }
        self.kill();
    }
}

/// Waits until one of `nodes` owns the demo scene; its index.
pub async fn owner_of(nodes: &[&Node], within: Duration) -> usize {
    let deadline = Instant::now() + within;
    loop {
        for (i, n) in nodes.iter().enumerate() {
            if n.owns().await {
                return i;
            }
        }
        assert!(Instant::now() < deadline, "no node took the scene");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The voxel edit `k` of writer `w`: a spot of its own above the demo terrain.
pub fn spot(w: u32, k: u32) -> [u32; 3] {
    [8 + (k % 480), 440 + w, 8 + (k / 480) * 2]
}

/// What a writer had acknowledged: voxel → (colour, sequence), and when each ack came.
#[derive(Default, Debug)]
pub struct Acked {
    pub voxels: BTreeMap<[u32; 3], (Colour, u64)>,
    pub ack_times: Vec<(Instant, u64)>,
    pub closed: bool,
}

/// Writes one voxel per edit message, waiting for each ack, until `stop` (or its connection
/// closes, e.g. its node was killed). Edits that were not acknowledged are not counted.
pub async fn writer(url: String, w: u32, stop: Arc<AtomicBool>) -> Acked {
    let mut out = Acked::default();
    let mut c = match Client::connect(&url, None).await {
        Ok(c) => c,
        Err(_) => {
            out.closed = true;
            return out;
        }
    };
    c.sync().await;
    let mut k = 0;
    while !stop.load(Relaxed) {
        let pos = spot(w, k);
        let col = colour(w * 100_000 + k);
        let client_seq = c.send_edit(vec![EditOp::Set { pos, colour: col }]).await;
        loop {
            match c.next().await {
                Some(ServerMsg::Ack {
                    client_seq: s, seq, ..
                }) if s == client_seq => {
                    let seq = seq.expect("a Set above the terrain applies");
                    out.voxels.insert(pos, (col, seq));
                    out.ack_times.push((Instant::now(), seq));
                    break;
                }
                Some(_) => {}
                None => {
                    out.closed = true;
                    return out;
                }
            }
        }
        k += 1;
    }
    out
}

/// Sets one voxel and returns the sequence its ack names (the edit must apply).
pub async fn set(c: &mut Client, pos: [u32; 3], col: u32) -> u64 {
    match c
        .edit(vec![EditOp::Set {
            pos,
            colour: colour(col),
        }])
        .await
    {
        ServerMsg::Ack { seq: Some(seq), .. } => seq,
        other => panic!("setting {pos:?}: {other:?}"),
    }
}

/// A fresh client's copy of the scene from `node`, once it has caught up to `seq`.
pub async fn copy_at(node: &Node, seq: u64) -> Client {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let mut c = Client::connect(&node.url(), None).await.expect("connects");
        c.sync().await;
        if c.seq >= seq {
            return c;
        }
        // The node is still catching up with the log: read its deltas.
        while c.seq < seq && Instant::now() < deadline {
            if tokio::time::timeout(Duration::from_secs(1), c.next())
                .await
                .ok()
                .flatten()
                .is_none()
            {
                break;
            }
        }
        if c.seq >= seq {
            return c;
        }
        assert!(
            Instant::now() < deadline,
            "node {} did not reach sequence {seq} (at {})",
            node.name,
            c.seq
        );
    }
}

/// Every acknowledged voxel is in `client`'s copy with its colour.
pub fn assert_has_all(client: &Client, acked: &[Acked], what: &str) {
    let mut n = 0;
    for a in acked {
        for (pos, (col, seq)) in &a.voxels {
            assert_eq!(
                client.map.get(*pos),
                Some(*col),
                "{what}: the edit acknowledged at sequence {seq} ({pos:?}) is missing"
            );
            n += 1;
        }
    }
    assert!(n > 0, "{what}: nothing was acknowledged");
}

pub async fn run_writers(urls: &[String], for_how_long: Duration) -> Vec<Acked> {
    let stop = Arc::new(AtomicBool::new(false));
    let tasks: Vec<_> = urls
        .iter()
        .enumerate()
        .map(|(w, u)| tokio::spawn(writer(u.clone(), w as u32, stop.clone())))
        .collect();
    tokio::time::sleep(for_how_long).await;
    stop.store(true, Relaxed);
    let mut out = Vec::new();
    for t in tasks {
        out.push(t.await.unwrap());
    }
    out
}

pub fn last_seq(acked: &[Acked]) -> u64 {
    acked
        .iter()
        .flat_map(|a| a.voxels.values().map(|v| v.1))
        .max()
        .unwrap_or(0)
}

/// Every node's copy (through a fresh client) hashes the same and holds every acked edit.
pub async fn assert_converged(nodes: &[&Node], acked: &[Acked], what: &str) {
    let seq = last_seq(acked);
    let mut hashes = Vec::new();
    for n in nodes {
        let c = copy_at(n, seq).await;
        assert_has_all(&c, acked, &format!("{what}, node {}", n.name));
        hashes.push((n.name.clone(), c.seq, c.map.content_hash()));
    }
    // Copies taken at the same sequence must be equal.
    let top = hashes.iter().map(|h| h.1).max().unwrap();
    let at_top: Vec<_> = hashes.iter().filter(|h| h.1 == top).collect();
    assert!(
        at_top.windows(2).all(|w| w[0].2 == w[1].2),
        "{what}: nodes differ at sequence {top}: {hashes:?}"
    );
}
