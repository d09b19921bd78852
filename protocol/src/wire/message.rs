//! The two message enums, one per direction, and the checks a received message must pass.

use serde::{Deserialize, Serialize};

use crate::swatches::Swatches;

use super::collab::{
    Cursor, MAX_PEERS_PER_FRAME, Peer, PeerId, PeerState, Refusal, Selection, UserId, View,
};
use super::{
    BrickBlob, EditOp, Limits, MAX_MESSAGE_BYTES, MAX_NAME_BYTES, MAX_OPS_PER_BATCH,
    MAX_REMOVED_PER_FRAME, MAX_SCENE_NAME_BYTES, MAX_TOKEN_BYTES, Rejection, WireError, bounded,
    truncate_utf8,
};

/// Everything a client can send to the server.
///
/// Variant order is the wire format: append only, and `Hello` stays first with the version as
/// its first field, so a server can always read the version of a client that is too old or too
/// new (the rest of `Hello` may change with the version).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ClientMsg {
    /// First message on a connection. `name` is the user's display name and `user` their stable
    /// id (`0`: none, the server picks one for this connection); with `--auth`, a token that
    /// names a user overrides both. `resume_from` is the last server sequence the client holds
    /// a picture of (from a previous connection), so a reconnect can skip full sync.
    Hello {
        protocol: u32,
        #[serde(deserialize_with = "bounded::string::<_, MAX_NAME_BYTES>")]
        name: String,
        #[serde(deserialize_with = "bounded::opt_string::<_, MAX_TOKEN_BYTES>")]
        token: Option<String>,
        resume_from: Option<u64>,
        user: UserId,
        /// The GPU memory the client gives the scene: the server streams it a working set
        /// within it (`working_set`, `held`) and follows its camera; `None`: the whole scene.
        budget: Option<Budget>,
    },
    /// A batch of edits, applied in order. `client_seq` comes back in the matching `Ack`.
    Edit {
        client_seq: u64,
        #[serde(deserialize_with = "bounded::vec::<_, _, { MAX_OPS_PER_BATCH as usize }>")]
        ops: Vec<EditOp>,
    },
    /// Where the viewer is looking, so the server streams the nearest visible bricks first.
    Camera { eye: [f32; 3], forward: [f32; 3] },
    /// Asks for every brick changed after server sequence `since`, for a client that detected a
    /// gap or dropped its own state.
    Resume { since: u64 },
    /// Keep-alive and latency probe; answered by `Pong` with the same nonce.
    Ping { nonce: u64 },
    /// Undo this user's most recent edit message (one message = one step): each voxel it
    /// changed goes back to its value before it, except where someone changed it since.
    /// Answered by `Undone`.
    Undo { client_seq: u64 },
    /// Re-apply the step most recently undone, the same way. A new edit clears what could be
    /// redone. Answered by `Undone`.
    Redo { client_seq: u64 },
    /// Where this peer looks and points, shared with everyone in the scene (latest wins, at most
    /// `Limits::presence_hz` a second). Also orders the peer's own sync, like `Camera`.
    /// Non-finite numbers earn a `Refused`, not a closed connection.
    Presence {
        view: Option<View>,
        cursor: Option<Cursor>,
        /// The box this peer has selected (the select tool), shown to everyone.
        selection: Option<Selection>,
    },
    /// A new display name. Parsed up to 1 KiB so that an over-long name earns a `Refused`
    /// (the limit is [`MAX_DISPLAY_NAME_BYTES`](super::MAX_DISPLAY_NAME_BYTES)).
    Rename {
        #[serde(deserialize_with = "bounded::string::<_, MAX_MESSAGE_BYTES>")]
        name: String,
    },
}

/// A client's GPU budget for the scene (`Hello.budget`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Budget {
    /// Bytes of GPU memory the client's copy may take.
    pub bytes: u64,
    /// Where its eye starts, in voxels (`None`: the server's default camera), so the first
    /// working set is fitted and sent for the right place.
    pub eye: Option<[f32; 3]>,
}

/// What a connected client may do, decided by the server from its token.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Role {
    /// May send `Edit`.
    Editor,
    /// Receives the scene, every edit op is rejected with `NotAllowed`.
    Viewer,
}

/// One refused op in an `Ack`, named by its index in the `Edit` batch.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct OpRejection {
    pub index: u32,
    pub reason: Rejection,
}

/// Machine-readable reason for a `ServerMsg::Error`, so a client can react (retry later,
/// prompt for a token, upgrade) without parsing the text.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ErrorCode {
    /// The client's `Hello` carried another `PROTOCOL_VERSION`.
    VersionMismatch,
    /// Missing or wrong token.
    Unauthorized,
    /// The role does not allow this message.
    NotAllowed,
    /// A frame failed to decode or broke a limit.
    MalformedFrame,
    /// A frame was over `max_frame_bytes`.
    FrameTooLarge,
    /// The client sent too much, too fast.
    RateLimited,
    /// The requested scene does not exist on this server.
    UnknownScene,
    /// The server is stopping; reconnecting later may work.
    ShuttingDown,
    /// A server bug; the text may say more.
    Internal,
}

/// Everything the server can send to a client.
///
/// Variant order is the wire format: append only, and `Welcome` keeps its place (a client of
/// another version never sees one: the server answers its `Hello` with `VersionMismatch`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ServerMsg {
    /// Answer to `Hello`: who the server is, the scene's size, the sequence number the scene is
    /// at, and the limits this connection will be held to. `total_bricks` lets the client show
    /// sync progress and size its GPU buffers before the first brick arrives. `you` is this
    /// connection as others see it; `peers` everyone else present when it joined (presence
    /// frames keep the list current from there).
    Welcome {
        protocol: u32,
        #[serde(deserialize_with = "bounded::string::<_, MAX_NAME_BYTES>")]
        server: String,
        #[serde(deserialize_with = "bounded::string::<_, MAX_SCENE_NAME_BYTES>")]
        scene: String,
        size: [u32; 3],
        seq: u64,
        role: Role,
        limits: Limits,
        total_bricks: u32,
        you: Peer,
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_PEERS_PER_FRAME>")]
        peers: Vec<Peer>,
    },
    /// Part of the initial (or re-) sync; progress is `sent / total` bricks.
    SyncBatch {
        bricks: BrickBlob,
        sent: u32,
        total: u32,
    },
    /// Sync is complete: the client's picture now equals the scene at server sequence `seq`,
    /// and deltas from `seq` on follow.
    SyncDone { seq: u64 },
    /// Changes between server sequences `from_seq` (exclusive) and `to_seq` (inclusive):
    /// bricks that changed (whole bricks, replacing the client's copy) and cells whose brick
    /// became empty.
    Delta {
        from_seq: u64,
        to_seq: u64,
        bricks: BrickBlob,
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_REMOVED_PER_FRAME>")]
        removed: Vec<[u32; 3]>,
    },
    /// The client fell too far behind and its queued deltas were dropped; every brick with a
    /// version above `since` follows as `SyncBatch`es and a `SyncDone`.
    Resync { since: u64 },
    /// Outcome of one `Edit` batch. `seq` is the server sequence that contains the applied ops
    /// (so the client knows which `Delta` shows them), `None` when nothing applied.
    Ack {
        client_seq: u64,
        seq: Option<u64>,
        applied: u32,
        #[serde(deserialize_with = "bounded::vec::<_, _, { MAX_OPS_PER_BATCH as usize }>")]
        rejected: Vec<OpRejection>,
    },
    /// Something went wrong at the connection level; usually followed by closing it.
    Error {
        code: ErrorCode,
        #[serde(deserialize_with = "bounded::string::<_, MAX_MESSAGE_BYTES>")]
        message: String,
    },
    /// Answer to `Ping`.
    Pong { nonce: u64 },
    /// Who else is here and what they look at, at most `Limits::presence_hz` times a second:
    /// peers that joined or were renamed (replace by id), peers that left, and the latest state
    /// of each peer whose state changed. `full` means the lists are the whole roster and every
    /// state: forget peers not in it (sent to a peer that skipped frames while its queue was
    /// long, so it never has to catch up on old ones).
    Presence {
        full: bool,
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_PEERS_PER_FRAME>")]
        joined: Vec<Peer>,
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_PEERS_PER_FRAME>")]
        left: Vec<PeerId>,
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_PEERS_PER_FRAME>")]
        states: Vec<PeerState>,
    },
    /// Outcome of `Undo` (`redo: false`) or `Redo`: `seq` is the server sequence holding the
    /// change (`None` when no voxel changed), `restored` how many voxels went back, `kept` how
    /// many stayed because someone else changed them since. `refused` says why nothing
    /// happened (nothing to undo, a viewer, too fast).
    Undone {
        client_seq: u64,
        redo: bool,
        seq: Option<u64>,
        restored: u64,
        kept: u64,
        refused: Option<Refusal>,
    },
    /// A `Presence` or `Rename` was refused; nothing changed and the connection stays.
    Refused { reason: Refusal },
    /// To a client with a budget: from here on it holds the working set of this rule
    /// ([`crate::working_set::Rule`], adopted with [`crate::held::Held::retarget`]). What it
    /// lacks follows as `Regions` and `Coarse` frames, then a `SyncDone`.
    Follow { eye: [u32; 3], near: u32, top: u32 },
    /// The whole level 0 of each listed region (32 voxels a side), as it stands: a listed
    /// region's bricks not in the blob are empty.
    Regions {
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_REMOVED_PER_FRAME>")]
        regions: Vec<[u32; 3]>,
        bricks: BrickBlob,
    },
    /// Bricks of level `level` of the scene's pyramid (`lod`), as they stand, their cells in
    /// that level's grid; `empty`: cells of that level whose brick is empty. Sent for what a
    /// following client's rule wants, and again when an edit changes it.
    Coarse {
        level: u32,
        bricks: BrickBlob,
        #[serde(deserialize_with = "bounded::vec::<_, _, MAX_REMOVED_PER_FRAME>")]
        empty: Vec<[u32; 3]>,
    },
    /// The scene's shared palette ([`crate::swatches`]) as of the frames before it: sent after
    /// every `Welcome` and after a turn that changed it.
    Palette { swatches: Swatches },
}

fn check_len(what: &'static str, len: usize, max: usize) -> Result<(), WireError> {
    if len > max {
        Err(WireError::TooLong { what, len, max })
    } else {
        Ok(())
    }
}

fn check_count(what: &'static str, len: usize, max: usize) -> Result<(), WireError> {
    if len > max {
        Err(WireError::TooMany { what, len, max })
    } else {
        Ok(())
    }
}

fn check_finite(what: &'static str, v: &[f32]) -> Result<(), WireError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(WireError::NotFinite { what })
    }
}

fn check_peers<'a>(peers: impl IntoIterator<Item = &'a Peer>) -> Result<(), WireError> {
    peers
        .into_iter()
        .try_for_each(|p| check_len("peer name", p.name.len(), MAX_NAME_BYTES))
}

impl ClientMsg {
    /// Checks the message against `limits` and the protocol's hard caps. Decoding runs this on
    /// every frame; encoding runs it against [`Limits::hard_caps`] so a client notices its own
    /// oversize message before the server drops the connection over it.
    ///
    /// Edit ops are not validated here (see [`EditOp::validate`]).
    pub fn validate(&self, limits: &Limits) -> Result<(), WireError> {
        match self {
            ClientMsg::Hello {
                name,
                token,
                budget,
                ..
            } => {
                check_len("client name", name.len(), MAX_NAME_BYTES)?;
                if let Some(Budget { eye: Some(eye), .. }) = budget {
                    check_finite("budget eye", eye)?;
                }
                match token {
                    Some(token) => check_len("token", token.len(), MAX_TOKEN_BYTES),
                    None => Ok(()),
                }
            }
            ClientMsg::Edit { ops, .. } => {
                check_count("edit batch", ops.len(), limits.ops_cap() as usize)
            }
            // Non-finite camera values would poison the server's distance ordering.
            ClientMsg::Camera { eye, forward } => {
                check_finite("camera eye", eye)?;
                check_finite("camera forward", forward)
            }
            // Presence and names are checked by the server, which refuses a bad one without
            // closing the connection.
            ClientMsg::Resume { .. }
            | ClientMsg::Ping { .. }
            | ClientMsg::Undo { .. }
            | ClientMsg::Redo { .. }
            | ClientMsg::Presence { .. } => Ok(()),
            ClientMsg::Rename { name } => check_len("name", name.len(), MAX_MESSAGE_BYTES),
        }
    }
}

impl ServerMsg {
    /// The name of every variant, in wire order (for logs and per-kind metrics).
    pub const KINDS: [&'static str; 15] = [
        "Welcome",
        "SyncBatch",
        "SyncDone",
        "Delta",
        "Resync",
        "Ack",
        "Error",
        "Pong",
        "Presence",
        "Undone",
        "Refused",
        "Follow",
        "Regions",
        "Coarse",
        "Palette",
    ];

    /// The variant's name, one of [`ServerMsg::KINDS`].
    pub fn kind(&self) -> &'static str {
        Self::KINDS[match self {
            ServerMsg::Welcome { .. } => 0,
            ServerMsg::SyncBatch { .. } => 1,
            ServerMsg::SyncDone { .. } => 2,
            ServerMsg::Delta { .. } => 3,
            ServerMsg::Resync { .. } => 4,
            ServerMsg::Ack { .. } => 5,
            ServerMsg::Error { .. } => 6,
            ServerMsg::Pong { .. } => 7,
            ServerMsg::Presence { .. } => 8,
            ServerMsg::Undone { .. } => 9,
            ServerMsg::Refused { .. } => 10,
            ServerMsg::Follow { .. } => 11,
            ServerMsg::Regions { .. } => 12,
            ServerMsg::Coarse { .. } => 13,
            ServerMsg::Palette { .. } => 14,
        }]
    }

    /// An `Error` whose text is cut to [`MAX_MESSAGE_BYTES`], so that an error built from
    /// arbitrary detail can always be sent.
    pub fn error(code: ErrorCode, message: impl Into<String>) -> Self {
        ServerMsg::Error {
            code,
            message: truncate_utf8(message.into(), MAX_MESSAGE_BYTES),
        }
    }

    /// Checks the message against `limits` and the protocol's hard caps, including the
    /// header of any brick blob (count and size, not its compressed contents). Decoding runs
    /// this on every frame; encoding runs it against [`Limits::hard_caps`].
    pub fn validate(&self, limits: &Limits) -> Result<(), WireError> {
        match self {
            ServerMsg::Welcome {
                server,
                scene,
                limits: announced,
                you,
                peers,
                ..
            } => {
                check_len("server name", server.len(), MAX_NAME_BYTES)?;
                check_len("scene name", scene.len(), MAX_SCENE_NAME_BYTES)?;
                check_peers(std::iter::once(you).chain(peers))?;
                check_count("peers", peers.len(), MAX_PEERS_PER_FRAME)?;
                announced.validate()
            }
            ServerMsg::Presence {
                joined,
                left,
                states,
                ..
            } => {
                check_count("joined peers", joined.len(), MAX_PEERS_PER_FRAME)?;
                check_count("left peers", left.len(), MAX_PEERS_PER_FRAME)?;
                check_count("peer states", states.len(), MAX_PEERS_PER_FRAME)?;
                check_peers(joined)
            }
            ServerMsg::Undone { .. }
            | ServerMsg::Refused { .. }
            | ServerMsg::Follow { .. }
            | ServerMsg::Palette { .. } => Ok(()),
            ServerMsg::Regions { regions, bricks } => {
                check_count("regions", regions.len(), MAX_REMOVED_PER_FRAME)?;
                bricks.validate_header(limits.brick_cap())
            }
            ServerMsg::Coarse { bricks, empty, .. } => {
                check_count("empty coarse bricks", empty.len(), MAX_REMOVED_PER_FRAME)?;
                bricks.validate_header(limits.brick_cap())
            }
            ServerMsg::SyncBatch { bricks, .. } => bricks.validate_header(limits.brick_cap()),
            ServerMsg::Delta {
                bricks, removed, ..
            } => {
                check_count("removed bricks", removed.len(), MAX_REMOVED_PER_FRAME)?;
                bricks.validate_header(limits.brick_cap())
            }
            ServerMsg::Ack { rejected, .. } => {
                check_count("ack rejections", rejected.len(), limits.ops_cap() as usize)?;
                rejected.iter().try_for_each(|r| match &r.reason {
                    Rejection::Malformed(text) => {
                        check_len("rejection reason", text.len(), super::MAX_REASON_BYTES)
                    }
                    _ => Ok(()),
                })
            }
            ServerMsg::Error { message, .. } => {
                check_len("error message", message.len(), MAX_MESSAGE_BYTES)
            }
            ServerMsg::SyncDone { .. } | ServerMsg::Resync { .. } | ServerMsg::Pong { .. } => {
                Ok(())
            }
        }
    }
}
