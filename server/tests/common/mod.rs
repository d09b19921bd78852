//! A small brickcast client for tests: speaks the raw protocol over tokio-tungstenite and keeps
//! its own copy of the scene, so tests can compare what each client ends up with.

#![allow(dead_code)]

pub mod admin_cli;

use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

use brickcast_protocol::roster::Roster;
use brickcast_protocol::wire::{
    BlobDecoder, ClientMsg, EditOp, ErrorCode, Limits, PROTOCOL_VERSION, Role, ServerMsg,
    decode_server, encode_client,
};
use brickcast_protocol::{BrickMap, Colour};
use brickcast_server::{Server, ServerConfig};
use futures_util::{SinkExt, StreamExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

pub const TEST_SCENE: [u32; 3] = [128, 64, 128];
const READ_TIMEOUT: Duration = Duration::from_secs(20);

/// An in-process server on an ephemeral port, with a shutdown trigger.
pub struct TestServer {
    pub addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl TestServer {
    pub async fn start(data: &Path, tweak: impl FnOnce(&mut ServerConfig)) -> TestServer {
        let mut config = ServerConfig::new("127.0.0.1:0".parse().unwrap(), data.to_path_buf());
        config.demo_size = TEST_SCENE;
        tweak(&mut config);
        let server = Server::bind(config).await.expect("server binds");
        let addr = server.local_addr().unwrap();
        let (stop, stopped) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(server.run(async move {
            let _ = stopped.await;
        }));
        TestServer {
            addr,
            stop: Some(stop),
            task,
        }
    }

    pub fn url(&self, scene: &str) -> String {
        format!("ws://{}/scenes/{scene}/ws", self.addr)
    }

    /// Triggers a graceful shutdown and waits for it.
    pub async fn shutdown(mut self) -> anyhow::Result<()> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        tokio::time::timeout(Duration::from_secs(30), &mut self.task)
            .await
            .expect("shutdown finishes")?
    }
}

/// `/metrics` text as Prometheus' own OpenMetrics parser reads it (the official Python client's,
/// Debian's `python3-prometheus-client`, installed by `scripts/setup`): each family's name,
/// type and number of samples. Panics with the parser's complaint when it refuses the text.
#[allow(dead_code)]
pub fn openmetrics_families(text: &str) -> Vec<(String, String, usize)> {
    use std::io::Write;
    const PARSE: &str = "import sys\n\
from prometheus_client.openmetrics.parser import text_string_to_metric_families as parse\n\
for f in parse(sys.stdin.read()):\n    print(f.name, f.type, len(f.samples))\n";
    let mut child = std::process::Command::new("/usr/bin/python3")
        .args(["-c", PARSE])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("/usr/bin/python3 (scripts/setup installs python3-prometheus-client)");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(text.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "the OpenMetrics parser refused /metrics: {}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| {
            let mut w = l.split(' ');
            let (name, kind, n) = (w.next().unwrap(), w.next().unwrap(), w.next().unwrap());
            (name.to_string(), kind.to_string(), n.parse().unwrap())
        })
        .collect()
}

/// A figure from the server's `/metrics`.
#[allow(dead_code)]
pub async fn metric(addr: SocketAddr, name: &str) -> f64 {
    let (_, text) = http_get(addr, "/metrics").await;
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
        .unwrap_or_else(|| panic!("{name} is not in /metrics"))
}

/// A plain HTTP GET over a raw socket: status code and body.
pub async fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes())
        .await
        .unwrap();
    // Bodies that are not text (a PNG) read lossily: callers look at text and status.
    let mut bytes = Vec::new();
    s.read_to_end(&mut bytes).await.unwrap();
    let text = String::from_utf8_lossy(&bytes);
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

pub struct Client {
    ws: WebSocketStream<MaybeTlsStream<TcpStream>>,
    pub map: BrickMap,
    pub role: Role,
    pub limits: Limits,
    /// Highest sequence this client has seen applied (from deltas and SyncDone).
    pub seq: u64,
    pub synced: bool,
    pub sync_total: u32,
    pub resyncs: u32,
    pub errors: Vec<(ErrorCode, String)>,
    pub closed: bool,
    /// Who we are and who else is here, from the Welcome and presence frames.
    pub roster: Roster,
    decoder: BlobDecoder,
    next_client_seq: u64,
}

/// How a connection attempt ended.
#[derive(Debug)]
pub enum Refused {
    Error(ErrorCode, String),
    Closed,
}

impl Client {
    pub async fn connect(url: &str, token: Option<&str>) -> Result<Client, Refused> {
        Self::resume(url, token, None, None).await
    }

    /// Connects, optionally resuming from `since` with an existing copy of the scene.
    pub async fn resume(
        url: &str,
        token: Option<&str>,
        since: Option<u64>,
        map: Option<BrickMap>,
    ) -> Result<Client, Refused> {
        Self::open(url, token, since, map, 0, "test").await
    }

    /// Connects as user `user` named `name`.
    pub async fn as_user(
        url: &str,
        token: Option<&str>,
        user: u64,
        name: &str,
    ) -> Result<Client, Refused> {
        Self::open(url, token, None, None, user, name).await
    }

    pub async fn open(
        url: &str,
        token: Option<&str>,
        since: Option<u64>,
        map: Option<BrickMap>,
        user: u64,
        name: &str,
    ) -> Result<Client, Refused> {
        let (mut ws, _) = tokio_tungstenite::connect_async(url)
            .await
            .expect("websocket connects");
        let hello = ClientMsg::Hello {
            protocol: PROTOCOL_VERSION,
            name: name.into(),
            token: token.map(String::from),
            resume_from: since,
            user,
            budget: None,
        };
        ws.send(Message::Binary(encode_client(&hello).unwrap().into()))
            .await
            .expect("hello sent");
        let limits = Limits::hard_caps();
        let first = tokio::time::timeout(READ_TIMEOUT, ws.next())
            .await
            .expect("welcome in time");
        let bytes = match first {
            Some(Ok(Message::Binary(b))) => b,
            _ => return Err(Refused::Closed),
        };
        let welcome = decode_server(&bytes, &limits).expect("server frames decode");
        let mut roster = Roster::default();
        roster.apply(&welcome);
        match welcome {
            ServerMsg::Welcome {
                size,
                role,
                limits,
                total_bricks,
                ..
            } => Ok(Client {
                roster,
                ws,
                map: map.unwrap_or_else(|| BrickMap::new(size).unwrap()),
                role,
                limits,
                seq: since.unwrap_or(0),
                synced: false,
                sync_total: total_bricks,
                resyncs: 0,
                errors: Vec::new(),
                closed: false,
                decoder: BlobDecoder::new().unwrap(),
                next_client_seq: 1,
            }),
            ServerMsg::Error { code, message } => Err(Refused::Error(code, message)),
            other => panic!("expected Welcome, got {other:?}"),
        }
    }

    /// The websocket underneath, for tests that write bytes no well-behaved client would.
    pub fn ws_mut(&mut self) -> &mut WebSocketStream<MaybeTlsStream<TcpStream>> {
        &mut self.ws
    }

    pub async fn send(&mut self, msg: &ClientMsg) {
        self.send_raw(encode_client(msg).unwrap()).await;
    }

    pub async fn send_raw(&mut self, bytes: Vec<u8>) {
        let _ = self.ws.send(Message::Binary(bytes.into())).await;
    }

    /// Sends an edit batch and returns its client sequence number.
    pub async fn send_edit(&mut self, ops: Vec<EditOp>) -> u64 {
        let client_seq = self.next_client_seq;
        self.next_client_seq += 1;
        self.send(&ClientMsg::Edit { client_seq, ops }).await;
        client_seq
    }

    /// Reads one message (applying it to the local copy); `None` once the server has closed.
    pub async fn next(&mut self) -> Option<ServerMsg> {
        loop {
            let frame = match tokio::time::timeout(READ_TIMEOUT, self.ws.next()).await {
                Ok(f) => f,
                Err(_) => panic!("no message from the server in {READ_TIMEOUT:?}"),
            };
            let bytes = match frame {
                Some(Ok(Message::Binary(b))) => b,
                Some(Ok(Message::Close(_))) | None => {
                    self.closed = true;
                    return None;
                }
                Some(Err(e)) => {
                    eprintln!("test client: websocket error: {e}");
                    self.closed = true;
                    return None;
                }
                Some(Ok(_)) => continue,
            };
            let msg = decode_server(&bytes, &Limits::hard_caps()).expect("server frames decode");
            self.apply(&msg);
            return Some(msg);
        }
    }

    fn apply(&mut self, msg: &ServerMsg) {
        match msg {
            ServerMsg::SyncBatch { bricks, .. } => {
                let map = &mut self.map;
                self.decoder
                    .for_each(bricks, 8192, |b| {
                        map.put_brick(&b.to_brick()).expect("valid brick")
                    })
                    .unwrap();
            }
            ServerMsg::Delta {
                to_seq,
                bricks,
                removed,
                ..
            } => {
                let map = &mut self.map;
                self.decoder
                    .for_each(bricks, 8192, |b| {
                        map.put_brick(&b.to_brick()).expect("valid brick")
                    })
                    .unwrap();
                for &cell in removed {
                    map.remove_brick(cell);
                }
                self.seq = self.seq.max(*to_seq);
            }
            ServerMsg::SyncDone { seq } => {
                self.synced = true;
                self.seq = self.seq.max(*seq);
            }
            ServerMsg::Resync { since } => {
                self.resyncs += 1;
                self.synced = false;
                if *since == 0 {
                    let swatches = *self.map.swatches();
                    self.map = BrickMap::new(self.map.size()).unwrap();
                    self.map.set_swatches(swatches);
                }
            }
            ServerMsg::Error { code, message } => self.errors.push((*code, message.clone())),
            ServerMsg::Presence { .. } => {
                self.roster.apply(msg);
            }
            ServerMsg::Palette { swatches } => self.map.set_swatches(*swatches),
            _ => {}
        }
    }

    /// Sends Undo (or Redo) and returns the `Undone` that answers it.
    pub async fn undo(&mut self, redo: bool) -> ServerMsg {
        let client_seq = self.next_client_seq;
        self.next_client_seq += 1;
        let msg = if redo {
            ClientMsg::Redo { client_seq }
        } else {
            ClientMsg::Undo { client_seq }
        };
        self.send(&msg).await;
        loop {
            match self.next().await {
                Some(reply @ ServerMsg::Undone { client_seq: c, .. }) if c == client_seq => {
                    return reply;
                }
                Some(_) => {}
                None => panic!("closed before the undo reply: {:?}", self.errors),
            }
        }
    }

    /// Reads until `check` holds for a message (or the roster after it); false if the server
    /// closes first.
    pub async fn until(&mut self, mut check: impl FnMut(&Client, &ServerMsg) -> bool) -> bool {
        while let Some(msg) = self.next().await {
            if check(self, &msg) {
                return true;
            }
        }
        false
    }

    /// Reads until the initial sync (or a resync) is complete.
    pub async fn sync(&mut self) {
        while !self.synced {
            if self.next().await.is_none() {
                panic!("closed during sync: {:?}", self.errors);
            }
        }
    }

    /// Reads until an Ack for `client_seq` arrives and returns it.
    pub async fn ack(&mut self, client_seq: u64) -> ServerMsg {
        loop {
            match self.next().await {
                Some(ack @ ServerMsg::Ack { client_seq: c, .. }) if c == client_seq => return ack,
                Some(_) => {}
                None => panic!("closed before ack {client_seq}: {:?}", self.errors),
            }
        }
    }

    pub async fn edit(&mut self, ops: Vec<EditOp>) -> ServerMsg {
        let c = self.send_edit(ops).await;
        self.ack(c).await
    }

    /// Reads until synced and every change up to `seq` has arrived.
    pub async fn catch_up(&mut self, seq: u64) {
        while !self.synced || self.seq < seq {
            if self.next().await.is_none() {
                panic!(
                    "closed while catching up to {seq} (at {}): {:?}",
                    self.seq, self.errors
                );
            }
        }
    }

    /// Reads until the server closes the connection; returns the errors it sent.
    pub async fn until_closed(&mut self) -> Vec<(ErrorCode, String)> {
        while self.next().await.is_some() {}
        self.errors.clone()
    }

    pub async fn close(mut self) {
        let _ = self.ws.close(None).await;
    }
}

/// A colour from an integer, for telling edits apart.
pub fn colour(i: u32) -> Colour {
    Colour((i.wrapping_mul(2654435761) >> 16) as u16 | 1)
}
