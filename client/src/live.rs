//! A replica kept live in the background: connects, syncs, applies deltas, sends edits, and
//! reconnects (resuming from its last complete sequence) when the connection drops.
//!
//! The network runs on its own thread so the render loop never waits on a socket; the two share
//! the replica behind a mutex, held by the network side only while applying one message and by
//! the render side only while copying changes into GPU upload buffers.

use brickcast_protocol::blocks::Quality;
use std::sync::{Arc, Mutex, MutexGuard};

pub use brickcast_client_core::session::Status;
use brickcast_client_core::session::{ClientSeq, Session};
use brickcast_protocol::wire::{ClientMsg, Cursor, EditOp, Selection, UserId, View};
use tokio::sync::mpsc;

use crate::link::{Link, LinkError};

/// What the render loop and the network thread share: the portable session state.
pub type LiveState = Session;

/// Handle to the background connection.
pub struct Live {
    state: Arc<Mutex<LiveState>>,
    outbox: mpsc::UnboundedSender<ClientMsg>,
    client_seq: ClientSeq,
}

impl Live {
    /// Starts connecting to the websocket address `url` in a background thread.
    pub fn start(
        url: String,
        name: String,
        user: UserId,
        token: Option<String>,
    ) -> std::io::Result<Live> {
        Live::start_any(vec![url], name, user, token, Quality::Exact, None)
    }

    /// [`Live::start`] with several addresses of one scene (a cluster's nodes): it connects to
    /// the first, and after losing a connection (or failing to make one) tries the next, in
    /// turn, resuming from what it had.
    pub fn start_any(
        urls: Vec<String>,
        name: String,
        user: UserId,
        token: Option<String>,
        colours: Quality,
        budget: Option<u64>,
    ) -> std::io::Result<Live> {
        let state = Arc::new(Mutex::new(Session {
            colours,
            budget,
            ..Session::default()
        }));
        let (outbox, inbox) = mpsc::unbounded_channel();
        let shared = state.clone();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        std::thread::Builder::new()
            .name("brickcast-net".into())
            .spawn(move || runtime.block_on(run(urls, name, user, token, shared, inbox)))?;
        Ok(Live {
            state,
            outbox,
            client_seq: ClientSeq::default(),
        })
    }

    /// Locks the shared state. A poisoned lock means the network thread panicked mid-update;
    /// the replica may be inconsistent, but showing it beats crashing the window.
    pub fn lock(&self) -> MutexGuard<'_, LiveState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues an edit batch; dropped if the connection is down when it is sent.
    pub fn edit(&mut self, ops: Vec<EditOp>) {
        let _ = self.outbox.send(self.client_seq.edit(ops));
    }

    /// Asks the server to undo (or redo) this user's latest step.
    pub fn undo(&mut self, redo: bool) {
        let _ = self.outbox.send(self.client_seq.undo(redo));
    }

    /// Shares where we look and point, and what we selected (the caller keeps to the server's
    /// rate).
    pub fn presence(
        &self,
        view: Option<View>,
        cursor: Option<Cursor>,
        selection: Option<Selection>,
    ) {
        if let Some(v) = &view {
            self.lock().eye = Some(v.eye);
        }
        let _ = self.outbox.send(ClientMsg::Presence {
            view,
            cursor,
            selection,
        });
    }
}

async fn run(
    urls: Vec<String>,
    name: String,
    user: UserId,
    token: Option<String>,
    state: Arc<Mutex<LiveState>>,
    mut inbox: mpsc::UnboundedReceiver<ClientMsg>,
) {
    let lock = || state.lock().unwrap_or_else(|e| e.into_inner());
    let mut backoff = brickcast_client_core::backoff::reconnect();
    let mut attempt = 0usize;
    loop {
        let url = &urls[attempt % urls.len().max(1)];
        attempt += 1;
        let (resume, budget) = {
            let s = lock();
            (s.resume_point(), s.hello_budget())
        };
        let connected =
            Link::connect_within(url, &name, user, token.as_deref(), resume, budget).await;
        let reason = match connected {
            Ok(mut link) => {
                backoff.reset();
                if lock().welcomed(&link.welcome).is_err() {
                    return;
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
        let wait = backoff.next_wait(rand::random());
        tracing::warn!("connection to {url} lost: {reason}; retrying in {wait:.1?}");
        lock().status = Status::Reconnecting(reason);
        // Edits made while disconnected are dropped rather than replayed against a scene that
        // moved on; the window shows the state, so the user knows.
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            msg = inbox.recv() => if msg.is_none() { return },
        }
        while inbox.try_recv().is_ok() {}
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
                // An error drops our copy (it can no longer be trusted): start over from scratch.
                state.lock().unwrap_or_else(|e| e.into_inner()).apply(&msg)?;
            }
            out = inbox.recv() => match out {
                Some(msg) => link.send(&msg).await?,
                None => return Ok(true),
            },
        }
    }
}
