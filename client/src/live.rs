//! A replica kept live in the background: connects, syncs, applies deltas, sends edits, and
//! reconnects (resuming from its last complete sequence) when the connection drops.
//!
//! The network runs on its own thread so the render loop never waits on a socket; the two share
//! the replica behind a mutex, held by the network side only while applying one message and by
//! the render side only while copying changes into GPU upload buffers.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use brickcast_protocol::roster::Roster;
use brickcast_protocol::wire::{ClientMsg, Cursor, EditOp, Role, ServerMsg, UserId, View};
use tokio::sync::mpsc;

use crate::link::{Link, LinkError};
use crate::replica::Replica;

/// Where the connection stands, for the window title.
#[derive(Debug, Clone, PartialEq)]
pub enum Status {
    Connecting,
    Syncing,
    Live,
    /// Lost the connection; trying again.
    Reconnecting(String),
    /// Gave up: the server refused us for a reason retrying cannot fix.
    Failed(String),
}

/// What the render loop and the network thread share.
pub struct LiveState {
    /// `None` until the first Welcome says how big the scene is.
    pub replica: Option<Replica>,
    pub status: Status,
    pub role: Option<Role>,
    /// Largest brush radius the server accepts.
    pub max_radius: f32,
    /// Presence messages the server accepts per second.
    pub presence_hz: u32,
    /// Edit ops the server rejected, with the reason of the latest one.
    pub rejected: u64,
    pub last_rejection: Option<String>,
    pub connects: u32,
    /// Who else is here, and who we are.
    pub roster: Roster,
    /// What the last undo or redo did, for the overlay.
    pub last_undo: Option<String>,
}

/// Handle to the background connection.
pub struct Live {
    state: Arc<Mutex<LiveState>>,
    outbox: mpsc::UnboundedSender<ClientMsg>,
    next_client_seq: u64,
}

const BACKOFF_START: Duration = Duration::from_millis(250);
const BACKOFF_MAX: Duration = Duration::from_secs(5);

impl Live {
    /// Starts connecting to the websocket address `url` in a background thread.
    pub fn start(
        url: String,
        name: String,
        user: UserId,
        token: Option<String>,
    ) -> std::io::Result<Live> {
        let state = Arc::new(Mutex::new(LiveState {
            replica: None,
            status: Status::Connecting,
            role: None,
            max_radius: 0.0,
            presence_hz: 1,
            rejected: 0,
            last_rejection: None,
            connects: 0,
            roster: Roster::default(),
            last_undo: None,
        }));
        let (outbox, inbox) = mpsc::unbounded_channel();
        let shared = state.clone();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        std::thread::Builder::new()
            .name("brickcast-net".into())
            .spawn(move || runtime.block_on(run(url, name, user, token, shared, inbox)))?;
        Ok(Live {
            state,
            outbox,
            next_client_seq: 1,
        })
    }

    /// Locks the shared state. A poisoned lock means the network thread panicked mid-update;
    /// the replica may be inconsistent, but showing it beats crashing the window.
    pub fn lock(&self) -> MutexGuard<'_, LiveState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues an edit batch; dropped if the connection is down when it is sent.
    pub fn edit(&mut self, ops: Vec<EditOp>) {
        let client_seq = self.next_client_seq;
        self.next_client_seq += 1;
        let _ = self.outbox.send(ClientMsg::Edit { client_seq, ops });
    }

    /// Asks the server to undo (or redo) this user's latest step.
    pub fn undo(&mut self, redo: bool) {
        let client_seq = self.next_client_seq;
        self.next_client_seq += 1;
        let msg = if redo {
            ClientMsg::Redo { client_seq }
        } else {
            ClientMsg::Undo { client_seq }
        };
        let _ = self.outbox.send(msg);
    }

    /// Shares where we look and point (the caller keeps to the server's rate).
    pub fn presence(&self, view: Option<View>, cursor: Option<Cursor>) {
        let _ = self.outbox.send(ClientMsg::Presence { view, cursor });
    }
}

async fn run(
    url: String,
    name: String,
    user: UserId,
    token: Option<String>,
    state: Arc<Mutex<LiveState>>,
    mut inbox: mpsc::UnboundedReceiver<ClientMsg>,
) {
    let lock = || state.lock().unwrap_or_else(|e| e.into_inner());
    let mut backoff = BACKOFF_START;
    loop {
        let resume = lock().replica.as_ref().and_then(Replica::resume_point);
        let reason = match Link::connect(&url, &name, user, token.as_deref(), resume).await {
            Ok(mut link) => {
                backoff = BACKOFF_START;
                {
                    let mut s = lock();
                    let w = &link.welcome;
                    let welcomed = match &mut s.replica {
                        Some(r) => r.welcome(&w.scene, w.size, w.seq),
                        None => Replica::new(&w.scene, w.size).map(|r| {
                            s.replica = Some(r);
                        }),
                    };
                    if let Err(e) = welcomed {
                        s.status = Status::Failed(e.to_string());
                        return;
                    }
                    if let Some(r) = &mut s.replica {
                        r.sync_total = w.total_bricks;
                    }
                    s.status = Status::Syncing;
                    s.role = Some(w.role);
                    s.max_radius = w.limits.max_brush_radius;
                    s.presence_hz = w.limits.presence_hz;
                    s.connects += 1;
                    s.roster.welcome(w.you.clone(), &w.peers);
                }
                match pump(&mut link, &state, &mut inbox).await {
                    Ok(true) => {
                        link.close().await;
                        return;
                    }
                    Ok(false) => "the server closed the connection".to_string(),
                    Err(e) => e.to_string(),
                }
            }
            Err(e) if !e.is_retryable() => {
                lock().status = Status::Failed(e.to_string());
                return;
            }
            Err(e) => e.to_string(),
        };
        tracing::warn!("connection lost: {reason}; retrying in {backoff:?}");
        lock().status = Status::Reconnecting(reason);
        // Edits made while disconnected are dropped rather than replayed against a scene that
        // moved on; the window shows the state, so the user knows.
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            msg = inbox.recv() => if msg.is_none() { return },
        }
        while inbox.try_recv().is_ok() {}
        backoff = (backoff * 2).min(BACKOFF_MAX);
    }
}

/// Moves messages both ways until the connection ends. `Ok(true)`: the window went away.
async fn pump(
    link: &mut Link,
    state: &Arc<Mutex<LiveState>>,
    inbox: &mut mpsc::UnboundedReceiver<ClientMsg>,
) -> Result<bool, LinkError> {
    loop {
        tokio::select! {
            msg = link.next() => {
                let Some(msg) = msg? else { return Ok(false) };
                let mut s = state.lock().unwrap_or_else(|e| e.into_inner());
                match &msg {
                    ServerMsg::Error { code, message } => {
                        tracing::warn!("server error {code:?}: {message}");
                    }
                    ServerMsg::Ack { rejected, .. } if !rejected.is_empty() => {
                        s.rejected += rejected.len() as u64;
                        s.last_rejection = rejected.last().map(|r| format!("{:?}", r.reason));
                    }
                    ServerMsg::Undone { redo, restored, kept, refused, .. } => {
                        let what = if *redo { "redo" } else { "undo" };
                        s.last_undo = Some(match refused {
                            Some(reason) => format!("{what}: {reason}"),
                            None if *kept > 0 => format!(
                                "{what}: {restored} voxels back, {kept} kept (changed by others since)"
                            ),
                            None => format!("{what}: {restored} voxels back"),
                        });
                    }
                    ServerMsg::Presence { .. } => {
                        s.roster.apply(&msg);
                    }
                    ServerMsg::Refused { reason } => {
                        tracing::warn!("the server refused a request: {reason}");
                    }
                    _ => {}
                }
                if let Some(r) = &mut s.replica {
                    if let Err(e) = r.apply(&msg) {
                        // Our copy can no longer be trusted: start over from scratch.
                        s.replica = None;
                        return Err(e.into());
                    }
                    s.status = if r.synced { Status::Live } else { Status::Syncing };
                }
            }
            out = inbox.recv() => match out {
                Some(msg) => link.send(&msg).await?,
                None => return Ok(true),
            },
        }
    }
}
