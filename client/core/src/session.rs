//! What a viewer knows about its connection, and how each server message changes it: the
//! replica, the status line, the roster, the outcome of edits and undos.
//!
//! Why here and not in a shell: the native viewer reads its socket on a tokio thread, the
//! browser page in WebSocket callbacks, but both must react to the server identically (the same
//! resume point, the same reset after a bad delta, the same words for a refusal). The shells own
//! the socket and the retry timer; [`Session`] owns everything the messages mean.

use std::time::Duration;

use brickcast_protocol::blocks::Quality;
use brickcast_protocol::replica::{Replica, ReplicaError};
use brickcast_protocol::roster::Roster;
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::{
    Budget, ClientMsg, EditOp, ErrorCode, Limits, PROTOCOL_VERSION, Peer, Role, ServerMsg, UserId,
};

/// First wait before reconnecting after a lost connection (see [`crate::backoff`]).
pub const BACKOFF_START: Duration = crate::backoff::START;
/// Longest wait before reconnecting.
pub const BACKOFF_MAX: Duration = crate::backoff::MAX;

/// Where the connection stands, for the status line.
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

/// What the server said about the scene and us.
#[derive(Debug, Clone)]
pub struct Welcome {
    pub server: String,
    pub scene: String,
    pub size: [u32; 3],
    pub seq: u64,
    pub role: Role,
    pub limits: Limits,
    pub total_bricks: u32,
    /// This connection as others see it.
    pub you: Peer,
    /// Everyone else present when we joined.
    pub peers: Vec<Peer>,
}

/// Why the first message from the server was not a Welcome.
#[derive(Debug, Clone, thiserror::Error)]
pub enum HandshakeError {
    #[error("the server refused the connection ({code:?}): {message}")]
    Refused { code: ErrorCode, message: String },
    #[error("the server sent {0} where a Welcome was expected")]
    Unexpected(&'static str),
}

/// The first message a client sends: who it is, where it can resume from, and the GPU memory
/// it gives the scene (`None`: the whole scene).
pub fn hello(
    name: &str,
    user: UserId,
    token: Option<&str>,
    resume_from: Option<u64>,
    budget: Option<Budget>,
) -> ClientMsg {
    ClientMsg::Hello {
        protocol: PROTOCOL_VERSION,
        name: name.to_string(),
        token: token.map(String::from),
        resume_from,
        user,
        budget,
    }
}

/// Reads the server's answer to the Hello.
pub fn welcome(first: ServerMsg) -> Result<Welcome, HandshakeError> {
    match first {
        ServerMsg::Welcome {
            server,
            scene,
            size,
            seq,
            role,
            limits,
            total_bricks,
            you,
            peers,
            ..
        } => Ok(Welcome {
            server,
            scene,
            size,
            seq,
            role,
            limits,
            total_bricks,
            you,
            peers,
        }),
        ServerMsg::Error { code, message } => Err(HandshakeError::Refused { code, message }),
        _ => Err(HandshakeError::Unexpected("another message")),
    }
}

/// An undo (or redo) request for this user's latest step.
pub fn undo_msg(client_seq: u64, redo: bool) -> ClientMsg {
    if redo {
        ClientMsg::Redo { client_seq }
    } else {
        ClientMsg::Undo { client_seq }
    }
}

/// Numbers a client's edit-like messages (edits, undos, redos), as acks refer to them.
#[derive(Debug)]
pub struct ClientSeq(u64);

impl Default for ClientSeq {
    fn default() -> Self {
        ClientSeq(1)
    }
}

impl ClientSeq {
    pub fn edit(&mut self, ops: Vec<EditOp>) -> ClientMsg {
        ClientMsg::Edit {
            client_seq: self.take(),
            ops,
        }
    }
    pub fn undo(&mut self, redo: bool) -> ClientMsg {
        undo_msg(self.take(), redo)
    }
    fn take(&mut self) -> u64 {
        self.0 += 1;
        self.0 - 1
    }
}

/// Everything a viewer knows from its connection.
pub struct Session {
    /// `None` until the first Welcome says how big the scene is.
    pub replica: Option<Replica>,
    pub status: Status,
    pub role: Option<Role>,
    /// Largest brush radius the server accepts.
    pub max_radius: f32,
    /// The limits the server announced (the tools size their edits by them).
    pub limits: Limits,
    /// Presence messages the server accepts per second.
    pub presence_hz: u32,
    /// Edit ops the server rejected, with the reason of the latest one.
    pub rejected: u64,
    pub last_rejection: Option<String>,
    /// Welcomes received: more than one means the connection was resumed.
    pub connects: u32,
    /// Who else is here, and who we are.
    pub roster: Roster,
    /// What the last undo or redo did, for the overlay.
    pub last_undo: Option<String>,
    /// The last refusal or error the server sent, for the status line.
    pub last_refusal: Option<String>,
    /// How exactly the copy keeps colours (`--colours`; bounded by default: a GPU copy).
    pub colours: Quality,
    /// GPU bytes the copy may take (`--gpu-budget`): the server streams a working set within
    /// them and follows the camera; `None`: the whole scene.
    pub budget: Option<u64>,
    /// Where our eye was when we last shared it, so a reconnect's working set starts there.
    pub eye: Option<[f32; 3]>,
}

impl Default for Session {
    fn default() -> Self {
        Session {
            replica: None,
            status: Status::Connecting,
            role: None,
            max_radius: 0.0,
            limits: Limits::default(),
            presence_hz: 1,
            rejected: 0,
            last_rejection: None,
            connects: 0,
            roster: Roster::default(),
            last_undo: None,
            last_refusal: None,
            colours: Quality::default(),
            budget: None,
            eye: None,
        }
    }
}

impl Session {
    /// The budget a `Hello` carries (with where the eye is), or `None` for the whole scene.
    pub fn hello_budget(&self) -> Option<Budget> {
        self.budget.map(|bytes| Budget {
            bytes,
            eye: self.eye,
        })
    }

    /// The scene's shared palette as this copy last heard it (the default before any).
    pub fn swatches(&self) -> Swatches {
        self.replica
            .as_ref()
            .map_or_else(Swatches::default, |r| *r.map.swatches())
    }

    /// Where a new connection can resume from: the last sequence our copy holds completely.
    pub fn resume_point(&self) -> Option<u64> {
        self.replica.as_ref().and_then(Replica::resume_point)
    }

    /// A Welcome arrived on a new connection. On error (a Welcome for another scene than the
    /// one we hold) the session has failed: retrying would only repeat it.
    pub fn welcomed(&mut self, w: &Welcome) -> Result<(), ReplicaError> {
        let welcomed = match &mut self.replica {
            Some(r) => r.welcome(&w.scene, w.size, w.seq),
            None => Replica::new(&w.scene, w.size).map(|mut r| {
                r.set_colour_bound(self.colours.bound());
                r.set_budget(self.budget);
                self.replica = Some(r);
            }),
        };
        if let Err(e) = welcomed {
            self.status = Status::Failed(e.to_string());
            return Err(e);
        }
        if let Some(r) = &mut self.replica {
            r.sync_total = w.total_bricks;
        }
        self.status = Status::Syncing;
        self.role = Some(w.role);
        self.max_radius = w.limits.max_brush_radius;
        self.limits = w.limits.clone();
        self.presence_hz = w.limits.presence_hz;
        self.connects += 1;
        self.roster.welcome(w.you.clone(), &w.peers);
        Ok(())
    }

    /// Applies one message from the server. An error means our copy can no longer be trusted:
    /// it has been dropped, and the caller should reconnect (which syncs from scratch).
    pub fn apply(&mut self, msg: &ServerMsg) -> Result<(), ReplicaError> {
        match msg {
            ServerMsg::Error { code, message } => {
                tracing::warn!("server error {code:?}: {message}");
                self.last_refusal = Some(message.clone());
            }
            ServerMsg::Ack { rejected, .. } if !rejected.is_empty() => {
                self.rejected += rejected.len() as u64;
                self.last_rejection = rejected.last().map(|r| format!("{:?}", r.reason));
            }
            ServerMsg::Undone {
                redo,
                restored,
                kept,
                refused,
                ..
            } => {
                let what = if *redo { "redo" } else { "undo" };
                self.last_undo = Some(match refused {
                    Some(reason) => format!("{what}: {reason}"),
                    None if *kept > 0 => format!(
                        "{what}: {restored} voxels back, {kept} kept (changed by others since)"
                    ),
                    None => format!("{what}: {restored} voxels back"),
                });
            }
            ServerMsg::Presence { .. } => {
                self.roster.apply(msg);
            }
            ServerMsg::Refused { reason } => {
                tracing::warn!("the server refused a request: {reason}");
                self.last_refusal = Some(reason.to_string());
            }
            _ => {}
        }
        if let Some(r) = &mut self.replica {
            if let Err(e) = r.apply(msg) {
                self.replica = None;
                return Err(e);
            }
            self.status = if r.synced {
                Status::Live
            } else {
                Status::Syncing
            };
        }
        Ok(())
    }

    /// Bricks received and expected during the current sync.
    pub fn progress(&self) -> (u32, u32) {
        self.replica
            .as_ref()
            .map_or((0, 0), |r| (r.sync_sent, r.sync_total))
    }

    /// The status as the status line shows it.
    pub fn status_text(&self) -> String {
        let (sent, total) = self.progress();
        match &self.status {
            Status::Connecting => "connecting".to_string(),
            Status::Syncing => format!("syncing {sent}/{total} bricks"),
            Status::Live => "live".to_string(),
            Status::Reconnecting(why) => format!("reconnecting ({why})"),
            Status::Failed(why) => format!("failed: {why}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_seqs_count_from_one_across_edits_and_undos() {
        let mut seq = ClientSeq::default();
        assert!(matches!(
            seq.edit(vec![]),
            ClientMsg::Edit { client_seq: 1, .. }
        ));
        assert!(matches!(seq.undo(false), ClientMsg::Undo { client_seq: 2 }));
        assert!(matches!(seq.undo(true), ClientMsg::Redo { client_seq: 3 }));
    }

    #[test]
    fn a_refusal_instead_of_a_welcome_keeps_its_words() {
        let err = welcome(ServerMsg::error(ErrorCode::Unauthorized, "bad token")).unwrap_err();
        assert!(err.to_string().contains("bad token"), "{err}");
    }
}
