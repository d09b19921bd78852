//! The binary messages that travel over the websocket between the brickcast server and its
//! clients.
//!
//! Every websocket binary frame carries exactly one message, encoded with bincode 2 (standard
//! configuration: little-endian, variable-length integers). The order of enum variants and of
//! struct fields *is* the wire format, so new variants are only ever appended, and `Hello` and
//! `Welcome` keep their layout forever so that a peer speaking another version can still read the
//! version number and answer with a clean `VersionMismatch`.
//!
//! Bytes from the network are hostile until proven otherwise. Decoding therefore happens in three
//! fences, each cheaper than the next is expensive:
//!
//! 1. the frame length is checked against the receiver's [`Limits`] before any parsing;
//! 2. parsing itself refuses strings and lists longer than the hard caps below as soon as their
//!    length prefix is read, so a 10-byte frame cannot make the decoder allocate megabytes;
//! 3. the parsed message is checked against the (usually tighter) negotiated [`Limits`].
//!
//! Brick payloads are carried as a [`BrickBlob`]: compressed once by the server and the same
//! bytes fanned out to every client, and only decompressed by the client that needs them.
//!
//! Edit operations are *not* rejected at decode time: they depend on the scene size and the
//! server's brush limits, and a bad op should cost the client one [`OpRejection`] in its
//! [`ServerMsg::Ack`], not its connection. See [`EditOp::validate`].

mod blob;
mod bounded;
mod codec;
mod collab;
mod edit;
mod error;
mod limits;
mod message;
mod names;
mod zstd_frame;

pub use blob::{BlobDecoder, BlobEncoder, BrickBlob, BrickRef};
pub use codec::{
    decode_client, decode_server, encode_client, encode_server, encode_server_into, hello_version,
};
pub use collab::{
    Cursor, MAX_DISPLAY_NAME_BYTES, MAX_PEERS_PER_FRAME, Peer, PeerId, PeerState, Refusal,
    Selection, UserId, View,
};
pub use edit::{BrushMode, EditOp, RayAction, Rejection, Shape};
pub use error::WireError;
pub use limits::{Limits, MAX_PRESENCE_HZ};
pub use message::{Budget, ClientMsg, ErrorCode, OpRejection, Role, ServerMsg};
pub use names::{MAX_MARKS_PER_LETTER, check_display_name, clean_display_name};

/// Version of this wire format. A `Hello` carrying another number is answered with
/// [`ErrorCode::VersionMismatch`] rather than a decode failure, so that old clients learn why.
///
/// 2 added identity (`Hello.user`, `Welcome.you`/`peers`), presence, undo/redo and the history
/// and presence limits. 3 added `Refusal::NameTaken`. 4 sends each brick's colours as its
/// exact colour block ([`crate::palette`]) instead of every voxel's RGB565. 5 added working
/// sets: `Hello.budget`, `Follow`, `Regions` and `Coarse`. 6 added the editing tools: flood
/// fill and face extrude ([`RayAction::Fill`], [`RayAction::Extrude`]), boxes and lines
/// between two rays ([`EditOp::Span`]) and `Limits::max_tool_voxels`. 7 added the scene's
/// shared palette: [`EditOp::Swatch`] and `Palette` ([`crate::swatches`]), selections in
/// presence ([`Selection`]: `Presence.selection`, `PeerState.selection`) and copy and paste
/// ([`EditOp::Copy`], [`EditOp::Paste`]: [`crate::clipboard`]). 8 added the scene's history:
/// [`EditOp::Restore`] ([`crate::rewind`]).
pub const PROTOCOL_VERSION: u32 = 8;

/// Largest frame either side will ever encode or decode, whatever a server announces. It is also
/// bincode's decode limit, the ceiling on what a length prefix can make the decoder reserve.
pub const MAX_FRAME_BYTES: usize = 16 << 20;
/// Most bricks one [`BrickBlob`] may hold; bounds the decompressed size of a blob to about 9 MB.
pub const MAX_BRICKS_PER_FRAME: u32 = 8192;
/// Most edit operations in one `Edit` batch (and so rejections in one `Ack`).
pub const MAX_OPS_PER_BATCH: u32 = 8192;
/// Longest client or server name, in UTF-8 bytes.
pub const MAX_NAME_BYTES: usize = 64;
/// Longest authentication token, in bytes.
pub const MAX_TOKEN_BYTES: usize = 256;
/// Longest human-readable error text in [`ServerMsg::Error`], in bytes.
pub const MAX_MESSAGE_BYTES: usize = 1024;
/// Longest detail text in [`Rejection::Malformed`]; kept short because an `Ack` can carry one per
/// op, thousands of them.
pub const MAX_REASON_BYTES: usize = 128;
/// Most removed brick cells in one `Delta`. Removals are 12 bytes each and uncompressed, so this
/// is higher than the brick cap but still bounded.
pub const MAX_REMOVED_PER_FRAME: usize = 65536;
/// Longest scene name, in UTF-8 bytes.
pub const MAX_SCENE_NAME_BYTES: usize = 64;
/// Smallest `max_frame_bytes` a server may announce: any less and a full brick plus the message
/// around it might not fit in one frame, so initial sync could never make progress.
pub const MIN_FRAME_BYTES: u32 = 64 << 10;

/// Cuts `text` to at most `max` bytes on a character boundary, for texts that are built from
/// arbitrary input (error messages, rejection details) and must still fit their wire bound.
pub(crate) fn truncate_utf8(mut text: String, max: usize) -> String {
    if text.len() > max {
        let mut end = max;
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        text.truncate(end);
    }
    text
}
