//! Requests from another origin: edits, undos and history drops that reach the owner from
//! outside its own sessions (in a cluster: the sessions of every node, forwarded over NATS).
//!
//! **Why an origin and a number:** whoever sends a request may not learn whether it applied
//! (the owner can lose the scene between logging a turn and answering), so it sends it again,
//! to whichever owner there is by then. Each request names its origin (the sending process and
//! session) and a number that grows per origin; the owner logs the replies it gave with the
//! turn (`answered.rs`), and a request seen before is answered from that record, never applied
//! twice.

use brickcast_protocol::wire::{EditOp, UserId};
use serde::{Deserialize, Serialize};

/// Queued edits and undos of one session, sent together.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Request {
    /// The sending process and session, and this request's number among its requests.
    pub origin: String,
    pub number: u64,
    pub user: UserId,
    /// Whether the user may edit (the owner checks it again, as for its own sessions).
    pub editor: bool,
    /// In the order the client sent them: client sequence, what to do.
    pub items: Vec<(u64, RequestItem)>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum RequestItem {
    Edit(Vec<EditOp>),
    Undo {
        redo: bool,
    },
    /// A user without a stable id left: its history goes (no reply is expected).
    Forget,
}

/// The owner's answer to a request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Outcome {
    /// One encoded `ServerMsg` (`Ack` or `Undone`) per edit or undo, sent after the commit.
    Done(Vec<Vec<u8>>),
    /// This owner does not order edits (any more): nothing was applied.
    NotOwner,
    /// The owner lost the scene while logging the request: it may or may not have applied.
    Unknown,
}
