//! One websocket connection: handshake, then a reader that forwards edits to the scene owner and
//! a writer that drains the session's outgoing queue.
//!
//! The reader never blocks the owner: edits go through the owner's bounded channel (so a flood
//! slows only its sender), and everything the owner sends back goes through the session's
//! byte-counted [`Outbox`]. A frame that cannot be decoded or is too large earns one `Error`
//! frame and a close; the scene and the other sessions carry on.

use std::net::IpAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use crate::scene::rewind::MAX_PAST_BYTES;
use axum::extract::ws::{CloseFrame, Message, WebSocket};
use brickcast_protocol::rewind::PastBox;
use brickcast_protocol::wire::{
    ClientMsg, Cursor, EditOp, ErrorCode, Limits, OpRejection, PROTOCOL_VERSION, Peer, Refusal,
    Rejection, Role, Selection, ServerMsg, View, check_display_name, decode_client, hello_version,
};
use futures_util::{SinkExt, StreamExt};

use crate::App;
use crate::auth::Access;
use crate::bucket::Bucket;
use crate::cluster::{Cluster, SceneLink};
use crate::fair;
use crate::identity::{Identity, identify};
use crate::metrics::{Metrics, ReadError, SessionPhase};
use crate::scene::{
    Command, MAX_REPLY_BACKLOG, Outbox, OutboxReceiver, RequestItem, SceneHandle, SessionId,
};

/// Waits, without reading the client, while its replies are backlogged (over
/// [`MAX_REPLY_BACKLOG`]) or its queue holds more than twice `max_queue_bytes`, until both are
/// down to half. Deltas are bounded by resyncs and syncs by their lookahead, so what makes a
/// queue that large is replies to a client that writes without reading: it is not read again
/// until the writer catches up, and the writer cuts it off if it takes nothing for the stall
/// timeout. False when the session should end instead (closed, or the server shutting down).
async fn hold_while_backlogged(
    out: &Outbox,
    max_queue_bytes: usize,
    shutdown: &tokio_util::sync::CancellationToken,
    metrics: &Metrics,
) -> bool {
    if out.reply_backlog() <= MAX_REPLY_BACKLOG && out.queued() <= 2 * max_queue_bytes {
        return true;
    }
    Metrics::add(&metrics.reads_paused, 1);
    tokio::select! {
        _ = out.drained_to(MAX_REPLY_BACKLOG / 2, max_queue_bytes) => !out.is_closed(),
        () = shutdown.cancelled() => false,
    }
}

/// How long a closing connection keeps reading so its peer can receive the close.
const CLOSE_GRACE: Duration = Duration::from_secs(2);
/// Bytes of queued frames one flush may carry, so a long queue still goes out in bounded writes
/// and the byte count the owner reads keeps moving.
const MAX_WRITE_BATCH: usize = 64 << 10;
/// How long a new connection may take to say Hello.
const HELLO_TIMEOUT: Duration = Duration::from_secs(10);

/// Camera updates a session forwards to the owner, at most: the owner re-sorts the client's
/// pending sync on each, so a flood of them is cut to the latest one per interval.
const CAMERA_INTERVAL: Duration = Duration::from_millis(50);
/// Resumes re-stream what changed (up to the whole scene): each costs one token, refilled every
/// this long, with two of burst.
const RESUME_INTERVAL: Duration = Duration::from_secs(5);

/// Serves one connection to `scene` until either side closes or the server shuts down.
/// `link`: in a cluster, how the session's edits reach the scene's owner (see
/// `crate::cluster::forward`); `None` on a single node, where they go to the owner thread.
/// `level`: the level of detail it views (`/scenes/NAME@K`, see `scene::levels`): above 0 the
/// session is a viewer of a coarser copy and takes no part in presence (its coordinates are not
/// the scene's). `past`: the scene is a view of a scene's past (`crate::past_views`), which
/// everyone views.
pub async fn run(
    socket: WebSocket,
    scene: SceneHandle,
    link: Option<SceneLink<Cluster>>,
    app: Arc<App>,
    from: IpAddr,
    level: u32,
    past: bool,
) {
    let id = app.next_session_id();
    app.metrics.connected_clients.fetch_add(1, Relaxed);
    let _guard = app.track_session();
    let (sink, mut stream) = socket.split();
    let (out, outbox) = Outbox::new(app.queued_total.clone());
    let writer = tokio::spawn(write_loop(
        sink,
        outbox,
        app.metrics.clone(),
        app.stall_timeout,
    ));

    // Set when the peer's input could not be read (a frame over the limit, a protocol error):
    // bytes it sent may still be unread when the connection closes.
    let unread = std::sync::atomic::AtomicBool::new(false);
    match handshake(&mut stream, &scene, &app, &out, id, from, &unread).await {
        Some((role, resume_from, budget, who)) => {
            let role = if level > 0 || past {
                Role::Viewer
            } else {
                role
            };
            let peer = Peer {
                id,
                user: who.user,
                name: who.name.clone(),
                colour: who.colour,
                role,
            };
            // Registered before the Welcome is built, so the roster it lists and the presence
            // frames after it leave nobody out.
            let (peer, roster) = if level == 0 {
                scene.presence.join(peer, out.clone())
            } else {
                (peer, Vec::new())
            };
            let (joined, welcomed) = tokio::sync::oneshot::channel();
            let sent = scene
                .send(Command::Join {
                    session: id,
                    out: out.clone(),
                    role,
                    resume_from,
                    level,
                    budget,
                    who: crate::scene::Joiner {
                        peer,
                        stable: who.stable,
                        roster,
                    },
                    joined,
                })
                .await;
            // Nothing goes out before the Welcome: the reader starts (and can queue pongs,
            // errors and refusals) only once the owner has queued it.
            if sent.is_ok() && welcomed.await.is_ok() {
                scene.presence.welcomed(id);
                let session = Session {
                    scene: &scene,
                    link: link.as_ref(),
                    app: &app,
                    out: &out,
                    id,
                    role,
                    who: &who,
                    from,
                    level,
                    unread: &unread,
                };
                read_loop(&mut stream, session).await;
                app.owner_config.pasts.forget(&scene.name, id);
                let _ = scene.send(Command::Leave { session: id }).await;
                if let Some(link) = &link
                    && !who.stable
                {
                    crate::cluster::forward::forget(link, who.user).await;
                }
            } else {
                out.close(ErrorCode::ShuttingDown, "the scene is shutting down");
            }
            scene.presence.leave(id);
        }
        None => tracing::debug!(session = id, "handshake failed"),
    }
    // The writer ends once every copy of the outbox is gone (ours now, the owner's on Leave),
    // after sending what was queued and a close frame. Meanwhile keep reading and discarding:
    // closing a socket with unread input makes the kernel reset the connection, and the peer
    // would lose the error frame that says why it was closed.
    drop(out);
    let drain = async {
        while let Some(Ok(msg)) = stream.next().await {
            if matches!(msg, Message::Close(_)) {
                return;
            }
        }
        // Input that could not be read cannot be drained either: closing now would reset the
        // connection, and a peer still reading the error frame would lose it. Linger for the
        // rest of the grace instead.
        if unread.load(Relaxed) {
            std::future::pending::<()>().await;
        }
    };
    let (_, _) = tokio::join!(writer, tokio::time::timeout(CLOSE_GRACE, drain));
    app.metrics.connected_clients.fetch_sub(1, Relaxed);
}

/// Reads the Hello. On failure queues an error frame and returns `None`.
async fn handshake(
    stream: &mut futures_util::stream::SplitStream<WebSocket>,
    scene: &SceneHandle,
    app: &App,
    out: &Outbox,
    id: SessionId,
    from: IpAddr,
    unread: &std::sync::atomic::AtomicBool,
) -> Option<(
    Role,
    Option<u64>,
    Option<brickcast_protocol::wire::Budget>,
    Identity,
)> {
    let fail = |code: ErrorCode, text: String| {
        app.metrics.rejected_frames.fetch_add(1, Relaxed);
        out.close(code, text);
        None
    };
    let bytes = match tokio::time::timeout(HELLO_TIMEOUT, stream.next()).await {
        Ok(Some(Ok(Message::Binary(bytes)))) => bytes,
        Ok(Some(Ok(_))) => {
            return fail(
                ErrorCode::MalformedFrame,
                "expected a binary Hello frame".into(),
            );
        }
        Ok(Some(Err(e))) => {
            let (code, text) = read_error(e, &app.metrics)?;
            unread.store(true, Relaxed);
            return fail(code, text);
        }
        Ok(None) => return None,
        Err(_) => return fail(ErrorCode::MalformedFrame, "no Hello within 10 s".into()),
    };
    app.metrics.bytes_in.fetch_add(bytes.len() as u64, Relaxed);
    if let Some(v) = hello_version(&bytes)
        && v != PROTOCOL_VERSION
    {
        return fail(
            ErrorCode::VersionMismatch,
            format!("this server speaks protocol {PROTOCOL_VERSION}, the client {v}"),
        );
    }
    let limits = &scene.limits;
    match decode_client(&bytes, limits) {
        Ok(ClientMsg::Hello {
            token,
            resume_from,
            name,
            user,
            budget,
            ..
        }) => match app.auth.check(token.as_deref()) {
            Access::Granted(grant) => {
                let reserved = |n: &str| app.auth.reserves(n);
                let open = app.auth.is_open();
                let mut who = identify(open, grant.name.as_deref(), user, &name, id, reserved);
                // A chosen id over its address's allowance: served as if it sent none.
                if who.stable && !who.pinned && !app.ids.admit(from, who.user) {
                    app.metrics.ids_over_allowance.fetch_add(1, Relaxed);
                    tracing::info!(scene = %scene.name, %from, user = who.user, "user id over the address's allowance: history kept for this connection only");
                    who = identify(open, None, 0, &name, id, reserved);
                }
                if let Some(why) = app.bans.refusal(who.user, &who.name, &scene.name) {
                    return fail(ErrorCode::Unauthorized, why);
                }
                let role = grant.role;
                tracing::info!(scene = %scene.name, client = %who.name, user = who.user, ?role, ?resume_from, ?budget, "client joined");
                Some((role, resume_from, budget, who))
            }
            Access::Refused => fail(ErrorCode::Unauthorized, "unknown token".into()),
        },
        Ok(_) => fail(
            ErrorCode::MalformedFrame,
            "the first message must be Hello".into(),
        ),
        Err(e) => fail(frame_error_code(&e), format!("bad Hello: {e}")),
    }
}

fn frame_error_code(e: &brickcast_protocol::wire::WireError) -> ErrorCode {
    match e {
        brickcast_protocol::wire::WireError::FrameTooLarge { .. } => ErrorCode::FrameTooLarge,
        _ => ErrorCode::MalformedFrame,
    }
}

/// Sorts a failed websocket read by cause, counts it, and says what to tell the peer: `None`
/// when the connection itself is gone (nobody is left to tell).
fn read_error(e: axum::Error, metrics: &Metrics) -> Option<(ErrorCode, String)> {
    use tungstenite::error::{CapacityError, Error as WsError};
    let inner = e.into_inner();
    let (kind, code) = match inner.downcast_ref::<WsError>() {
        Some(WsError::Capacity(CapacityError::MessageTooLong { .. })) => {
            (ReadError::TooLarge, Some(ErrorCode::FrameTooLarge))
        }
        Some(WsError::Capacity(_)) => (ReadError::TooLarge, Some(ErrorCode::MalformedFrame)),
        Some(WsError::Protocol(_) | WsError::AttackAttempt) => {
            (ReadError::Protocol, Some(ErrorCode::MalformedFrame))
        }
        Some(WsError::Utf8(_)) => (ReadError::Utf8, Some(ErrorCode::MalformedFrame)),
        Some(WsError::Io(_) | WsError::ConnectionClosed | WsError::AlreadyClosed) => {
            (ReadError::Io, None)
        }
        _ => (ReadError::Other, Some(ErrorCode::MalformedFrame)),
    };
    metrics.count_read_error(kind);
    tracing::debug!(error = %inner, kind = kind.name(), "websocket read failed");
    code.map(|code| (code, format!("unreadable frame: {inner}")))
}

/// A welcomed session, as its reader sees it.
struct Session<'a> {
    scene: &'a SceneHandle,
    link: Option<&'a SceneLink<Cluster>>,
    app: &'a App,
    out: &'a Outbox,
    id: SessionId,
    role: Role,
    who: &'a Identity,
    /// The address the connection comes from: edit work is budgeted per address too.
    from: IpAddr,
    /// The level of detail it views (0: the scene); above 0 it is not in presence.
    level: u32,
    /// Set when its input could not be read (see `run`).
    unread: &'a std::sync::atomic::AtomicBool,
}

/// Undo and redo messages one session may send per second, with this much burst: a guard
/// against a flood of messages. What each costs (the bricks its step changed) is charged by the
/// owner against the edit work budget.
const UNDOS_PER_SECOND: f64 = 1000.0;
const UNDO_BURST: f64 = 1000.0;
/// Renames per second, with this many of burst.
const RENAMES_PER_SECOND: f64 = 1.0;
const RENAME_BURST: f64 = 5.0;

impl Session<'_> {
    /// Checks a presence message: finite numbers, a direction with length, a cursor inside the
    /// scene with a radius the server allows.
    fn check_presence(
        &self,
        view: &Option<View>,
        cursor: &Option<Cursor>,
        selection: &Option<Selection>,
    ) -> Result<(), Refusal> {
        crate::presence::check(
            view,
            cursor,
            selection,
            self.scene.size,
            self.scene.limits.max_brush_radius,
        )
    }

    fn refuse(&self, reason: Refusal) {
        Metrics::add(&self.app.metrics.presence_refused, 1);
        self.out.refuse(reason);
    }
}

async fn read_loop(
    stream: &mut futures_util::stream::SplitStream<WebSocket>,
    session: Session<'_>,
) {
    let Session {
        scene,
        link,
        app,
        out,
        id,
        role,
        ..
    } = session;
    let limits: &Limits = &scene.limits;
    let budget = &scene.budget;
    let mut ops_rate = Bucket::new(
        f64::from(limits.max_edits_per_second),
        f64::from(limits.max_edits_per_second),
    );
    // One second of burst, and always room for one message of the largest allowed size; the
    // same budget is shared by every connection of the user and of the address (`crate::fair`).
    let (work_per_second, work_burst) = (
        budget.max_work_per_second as f64,
        budget.max_work_per_second.max(budget.max_work_per_edit) as f64,
    );
    let mut work_rate = Bucket::new(work_per_second, work_burst);
    let shared_work = |owner| app.shares.get(owner, work_per_second, work_burst);
    let address_work = shared_work(fair::Owner::Address(session.from));
    let user_work = shared_work(fair::Owner::User(session.who.user));
    let mut resumes = Bucket::new(1.0 / RESUME_INTERVAL.as_secs_f64(), 2.0);
    let mut undos = Bucket::new(UNDOS_PER_SECOND, UNDO_BURST);
    let hz = f64::from(limits.presence_hz);
    let mut presences = Bucket::new(hz, hz);
    let mut renames = Bucket::new(RENAMES_PER_SECOND, RENAME_BURST);
    // The latest camera not yet forwarded, and when the next may go.
    let mut camera: Option<[f32; 3]> = None;
    let mut camera_at = tokio::time::Instant::now();
    let shutdown = app.shutdown.clone();
    // In a cluster, edits and undos go to the scene's owner over NATS, one at a time, in
    // order (`crate::cluster::forward`).
    let forwarder = link.map(|c| {
        crate::cluster::forward::SessionForwarder::start(
            c.clone(),
            id,
            session.who.user,
            role == Role::Editor,
            out.clone(),
            app.metrics.clone(),
        )
    });
    let reject = |code: ErrorCode, text: String| {
        app.metrics.rejected_frames.fetch_add(1, Relaxed);
        tracing::debug!(session = id, ?code, %text, "closing a session");
        out.close(code, text);
    };
    loop {
        // A client that sends faster than it reads its replies is not read until the writer
        // catches up (see `scene::outbox`): its requests wait in its own socket.
        if !hold_while_backlogged(out, scene.max_queue_bytes, &shutdown, &app.metrics).await {
            return;
        }
        let next = tokio::select! {
            next = stream.next() => next,
            () = shutdown.cancelled() => return,
            // The owner, the writer, or a reply that could not be encoded ended the session.
            _ = out.closed() => return,
            _ = tokio::time::sleep_until(camera_at), if camera.is_some() => {
                // Streaming order is a hint: drop it rather than wait when the owner is busy,
                // and do not wake the owner at all when no sync is going on.
                if let Some(eye) = camera.take()
                    && (out.is_syncing() || out.is_following())
                    && scene.try_send(Command::Camera { session: id, eye }).is_ok()
                {
                    Metrics::add(&app.metrics.camera_updates, 1);
                    camera_at = tokio::time::Instant::now() + CAMERA_INTERVAL;
                }
                continue;
            }
        };
        let bytes = match next {
            Some(Ok(Message::Binary(bytes))) => bytes,
            Some(Ok(Message::Close(_))) | None => return,
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
            Some(Ok(Message::Text(_))) => {
                return reject(
                    ErrorCode::MalformedFrame,
                    "only binary frames are spoken here".into(),
                );
            }
            Some(Err(e)) => {
                if let Some((code, text)) = read_error(e, &app.metrics) {
                    session.unread.store(true, Relaxed);
                    reject(code, text);
                }
                return;
            }
        };
        app.metrics.bytes_in.fetch_add(bytes.len() as u64, Relaxed);
        // The owner may have answered a run of requests since the check above (it answers a
        // turn's worth at once): hold this frame until they are written, so a client that
        // writes without reading meets the pause and then its writer's stall timeout, however
        // the owner's turns fall.
        if !hold_while_backlogged(out, scene.max_queue_bytes, &shutdown, &app.metrics).await {
            return;
        }
        let started = Instant::now();
        let decoded = decode_client(&bytes, limits);
        app.metrics
            .session_time(SessionPhase::Decode, started.elapsed());
        let msg = match decoded {
            Ok(msg) => msg,
            Err(e) => return reject(frame_error_code(&e), e.to_string()),
        };
        match msg {
            ClientMsg::Hello { .. } => {
                return reject(ErrorCode::MalformedFrame, "Hello sent twice".into());
            }
            ClientMsg::Edit { client_seq, ops } => {
                // Charged by the work the ops ask for (a sphere of radius 64 is two million
                // voxels), not only by how many there are.
                let work: u64 = ops
                    .iter()
                    .map(|op| op.work(scene.size))
                    .fold(0, u64::saturating_add);
                let refusal = if role != Role::Editor {
                    Some(Rejection::NotAllowed)
                } else if work > budget.max_work_per_edit {
                    Metrics::add(&app.metrics.edits_over_budget, 1);
                    Some(Rejection::TooLarge)
                } else if !ops_rate.take(ops.len() as f64)
                    || !fair::take_all(
                        &mut [
                            &mut work_rate,
                            &mut *address_work.lock().unwrap_or_else(|e| e.into_inner()),
                            &mut *user_work.lock().unwrap_or_else(|e| e.into_inner()),
                        ],
                        work as f64,
                    )
                {
                    Some(Rejection::RateLimited)
                } else {
                    None
                };
                if let Some(reason) = refusal {
                    Metrics::add(&app.metrics.ops_rejected, ops.len() as u64);
                    let rejected = (0..ops.len() as u32)
                        .map(|index| OpRejection {
                            index,
                            reason: reason.clone(),
                        })
                        .collect();
                    out.send(
                        &ServerMsg::Ack {
                            client_seq,
                            seq: None,
                            applied: 0,
                            rejected,
                        },
                        &app.metrics,
                    );
                    continue;
                }
                // A restore's past is rebuilt here, off the owner (`scene::rewind`), for a box
                // the op's own check accepts (else the owner refuses it, saying why).
                if let (None, Some(store), [op @ EditOp::Restore { to, min, max }]) =
                    (&forwarder, &app.store, &ops[..])
                    && op.validate(scene.size, limits).is_ok()
                {
                    let (store, name, (to, min, max)) =
                        (store.clone(), scene.name.clone(), (*to, *min, *max));
                    // The box then against the scene as the store holds it now: only the
                    // bricks that differ go to the owner.
                    let fetch = app.past.rebuild(move || {
                        let (then, now) = store.then_and_now(&name, to).map_err(|e| e.to_string())?;
                        PastBox::diff(&then, &now, min, max, MAX_PAST_BYTES).map_err(|bytes| {
                            format!(
                                "the box differs from then in more than {} MiB of bricks ({} MiB so far), more than one restore takes: restore it in parts",
                                MAX_PAST_BYTES >> 20,
                                bytes >> 20
                            )
                        })
                    });
                    let past = tokio::select! {
                        fetched = fetch => fetched.and_then(|f| f),
                        () = shutdown.cancelled() => return,
                        _ = out.closed() => return,
                    };
                    app.owner_config
                        .pasts
                        .put(&scene.name, id, client_seq, *op, past);
                }
                // (Fetched before: a restore does not hold the gate while it waits for a turn
                // at rebuilding.) A heavy edit waits for its turn at the scene, its socket unread meanwhile.
                let admitted = tokio::select! {
                    admitted = scene.heavy.admit(work) => admitted,
                    () = shutdown.cancelled() => return,
                    _ = out.closed() => return,
                };
                let sent = match &forwarder {
                    // The turn is held while the forwarder takes it; the owner node's own
                    // sessions take turns there (a cluster shares one gate per node).
                    Some(f) => f.send(client_seq, RequestItem::Edit(ops)).await,
                    None => scene
                        .send(Command::Edit {
                            session: id,
                            client_seq,
                            ops,
                            admitted,
                        })
                        .await
                        .is_ok(),
                };
                if !sent {
                    return reject(ErrorCode::ShuttingDown, "the scene is shutting down".into());
                }
            }
            ClientMsg::Camera { eye, .. } => {
                // Latest wins: forwarded at most once per interval.
                camera = Some(eye);
            }
            ClientMsg::Resume { since } => {
                if !resumes.take(1.0) {
                    return reject(
                        ErrorCode::RateLimited,
                        format!(
                            "too many Resume requests: each re-sends what changed, at most one per {} s",
                            RESUME_INTERVAL.as_secs()
                        ),
                    );
                }
                if scene
                    .send(Command::Resume { session: id, since })
                    .await
                    .is_err()
                {
                    return;
                }
            }
            ClientMsg::Ping { nonce } => out.pong(nonce),
            ClientMsg::Undo { client_seq } | ClientMsg::Redo { client_seq } => {
                let redo = matches!(msg, ClientMsg::Redo { .. });
                let refused = if role != Role::Editor {
                    Some(Refusal::NotAllowed)
                } else if !undos.take(1.0) {
                    Some(Refusal::RateLimited)
                } else {
                    None
                };
                if let Some(reason) = refused {
                    Metrics::add(&app.metrics.history_refused, 1);
                    out.send(
                        &ServerMsg::Undone {
                            client_seq,
                            redo,
                            seq: None,
                            restored: 0,
                            kept: 0,
                            refused: Some(reason),
                        },
                        &app.metrics,
                    );
                    continue;
                }
                let sent = match &forwarder {
                    Some(f) => f.send(client_seq, RequestItem::Undo { redo }).await,
                    None => {
                        let cmd = Command::Undo {
                            session: id,
                            client_seq,
                            redo,
                        };
                        scene.send(cmd).await.is_ok()
                    }
                };
                if !sent {
                    return reject(ErrorCode::ShuttingDown, "the scene is shutting down".into());
                }
            }
            ClientMsg::Presence {
                view,
                cursor,
                selection,
            } => {
                if !presences.take(1.0) {
                    session.refuse(Refusal::RateLimited);
                } else if let Err(reason) = session.check_presence(&view, &cursor, &selection) {
                    session.refuse(reason);
                } else {
                    Metrics::add(&app.metrics.presence_updates, 1);
                    if session.level == 0 {
                        scene.presence.update(id, view, cursor, selection);
                    }
                    if let Some(view) = view {
                        camera = Some(view.eye);
                    }
                }
            }
            ClientMsg::Rename { name } => {
                if !renames.take(1.0) {
                    session.refuse(Refusal::RateLimited);
                } else if let Err(reason) = check_display_name(&name) {
                    session.refuse(reason);
                } else if session.who.pinned {
                    // A name from the auth file is the user's name.
                    session.refuse(Refusal::NotAllowed);
                } else if app.auth.reserves(&name) {
                    session.refuse(Refusal::NameTaken);
                } else if let Err(reason) = scene.presence.rename(id, name) {
                    session.refuse(reason);
                }
            }
        }
    }
}

/// Sends the queue's frames until every [`Outbox`] is gone, then a close frame. A peer that
/// takes nothing for `stall` (its socket stays full) is cut off: its queue is dropped and the
/// reader told to stop, so a client that stops reading holds no memory past the deadline.
async fn write_loop(
    mut sink: futures_util::stream::SplitSink<WebSocket, Message>,
    mut outbox: OutboxReceiver,
    metrics: Arc<Metrics>,
    stall: Duration,
) {
    while let Some(frame) = outbox.next().await {
        let started = Instant::now();
        // Everything already queued goes out with one flush: an ack and the delta of the same
        // turn, or a burst of deltas, leave in one write instead of one small segment each.
        // Separate small writes also meet Nagle's algorithm, which holds a segment back until the
        // previous one is acknowledged, and a client's delayed ACK can put that off until it
        // next sends: the ack of one edit arrived only after the client's following edit.
        let write = async {
            let mut len = frame.len();
            sink.feed(Message::Binary(frame)).await?;
            while len < MAX_WRITE_BATCH {
                let Some(frame) = outbox.try_take() else {
                    break;
                };
                len += frame.len();
                sink.feed(Message::Binary(frame)).await?;
            }
            sink.flush().await?;
            Ok::<usize, axum::Error>(len)
        };
        let sent = tokio::time::timeout(stall, write).await;
        metrics.session_time(SessionPhase::Send, started.elapsed());
        match sent {
            Ok(Ok(len)) => {
                metrics.bytes_out.fetch_add(len as u64, Relaxed);
            }
            Ok(Err(_)) => {
                // The peer is gone.
                outbox.abort();
                return;
            }
            Err(_) => {
                tracing::info!(stalled = ?stall, "disconnecting a client that stopped reading");
                Metrics::add(&metrics.stalled_disconnects, 1);
                outbox.abort();
                // Its socket is full, so a close frame may not get through; try briefly.
                let close = Message::Close(Some(CloseFrame {
                    code: axum::extract::ws::close_code::POLICY,
                    reason: "stalled: the client stopped reading".into(),
                }));
                let _ = tokio::time::timeout(Duration::from_secs(1), sink.send(close)).await;
                return;
            }
        }
    }
    let _ = sink
        .send(Message::Close(Some(CloseFrame {
            code: axum::extract::ws::close_code::NORMAL,
            reason: "bye".into(),
        })))
        .await;
    let _ = sink.close().await;
}
