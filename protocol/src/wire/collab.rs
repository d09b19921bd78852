//! What collaborators learn about each other: who is here (identity), where they look and point
//! (presence), and the outcome of an undo or redo.
//!
//! Identity is per *user* (a stable id the client keeps across runs, or one pinned by an auth
//! token); presence is per *peer* (one connection: a user with two windows is two peers with one
//! name and colour). History (undo/redo) belongs to the user, so it survives reconnecting.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::{MAX_NAME_BYTES, Role, bounded};
use crate::colour::Colour;

/// A connection within one server (the server's session id), named in presence frames.
pub type PeerId = u64;

/// A user's stable id: chosen by the client and kept across runs (the viewer keeps it in a file
/// under the user's config directory), or derived from the auth token's name. `0` means "none":
/// the server then picks one for the connection, and its history ends with it.
pub type UserId = u64;

/// Longest display name, in UTF-8 bytes (the same cap as `Hello`'s name).
pub const MAX_DISPLAY_NAME_BYTES: usize = MAX_NAME_BYTES;

/// Most peers one `Welcome` or presence frame may list.
pub const MAX_PEERS_PER_FRAME: usize = 65_536;

/// Where a peer's camera is and where it points.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct View {
    pub eye: [f32; 3],
    /// Need not be normalised; never zero-length when the server forwards it.
    pub forward: [f32; 3],
}

/// What a peer points at: the voxel under its pointer and the radius of its brush (0 for a
/// single voxel).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cursor {
    pub voxel: [u32; 3],
    pub radius: f32,
}

/// A connected peer as everyone else sees it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Peer {
    pub id: PeerId,
    pub user: UserId,
    #[serde(deserialize_with = "bounded::string::<_, MAX_DISPLAY_NAME_BYTES>")]
    pub name: String,
    /// Given by the server from the user id, so a user keeps a colour across reconnects.
    pub colour: Colour,
    pub role: Role,
}

/// A box of voxels a peer has selected (the select tool), both corners inclusive: shown to
/// everyone in the scene, the region its next copy or move acts on (issue #34).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Selection {
    pub min: [u32; 3],
    pub max: [u32; 3],
}

impl Selection {
    /// The box with `a` and `b` as opposite corners.
    pub fn between(a: [u32; 3], b: [u32; 3]) -> Selection {
        Selection {
            min: std::array::from_fn(|i| a[i].min(b[i])),
            max: std::array::from_fn(|i| a[i].max(b[i])),
        }
    }

    /// `min` at or below `max` on every axis, and inside a scene of `size` voxels.
    pub fn is_within(&self, size: [u32; 3]) -> bool {
        (0..3).all(|i| self.min[i] <= self.max[i] && self.max[i] < size[i])
    }

    /// Voxels along each axis.
    pub fn extent(&self) -> [u32; 3] {
        std::array::from_fn(|i| self.max[i].saturating_sub(self.min[i]).saturating_add(1))
    }
}

/// One peer's latest presence. `None` fields mean "not shared" (a headless client), "pointing
/// at nothing" (the pointer is on the sky or outside the window) or "nothing selected".
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PeerState {
    pub id: PeerId,
    pub view: Option<View>,
    pub cursor: Option<Cursor>,
    pub selection: Option<Selection>,
}

/// Why a request that is not an edit op was refused. The connection stays open: each of these
/// is the client's mistake or impatience, not a broken peer.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Error)]
pub enum Refusal {
    #[error("there is nothing of yours to undo")]
    NothingToUndo,
    #[error("there is nothing of yours to redo (a new edit clears what could be redone)")]
    NothingToRedo,
    #[error("this connection may watch but not edit")]
    NotAllowed,
    #[error("too many requests; slow down")]
    RateLimited,
    #[error("a position or direction is not a finite number, or a direction has no length")]
    NotFinite,
    #[error("a name must be 1 to {max} bytes of printable text")]
    BadName { max: u32 },
    #[error("the cursor is outside the scene or its radius is out of range")]
    OutOfRange,
    /// The name is someone else's: it looks like (UTS #39 confusable with) the name of another
    /// user present, or of a user the server's auth file names.
    #[error("that name is taken: it looks like the name of someone else here")]
    NameTaken,
}

impl View {
    /// Finite numbers and a direction with length.
    pub fn is_valid(&self) -> bool {
        let finite = self.eye.iter().chain(&self.forward).all(|v| v.is_finite());
        let len2: f32 = self.forward.iter().map(|v| v * v).sum();
        finite && len2.is_finite() && len2 > 1e-12
    }
}
