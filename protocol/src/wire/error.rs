//! Everything that can go wrong turning messages into bytes and back.

use thiserror::Error;

/// Why a frame or a brick blob could not be encoded or decoded.
///
/// A receiver answers any of these by dropping the frame (and usually the connection, with
/// [`ErrorCode::MalformedFrame`](super::ErrorCode::MalformedFrame) or
/// [`ErrorCode::FrameTooLarge`](super::ErrorCode::FrameTooLarge)); a sender that gets one has a
/// bug or is about to send more than the peer accepts. The variants are precise so that logs say
/// which bound was hit without a packet capture.
#[derive(Debug, Error)]
pub enum WireError {
    /// Checked before parsing, so an oversized frame costs nothing to refuse.
    #[error("frame is {len} bytes, over the {max}-byte limit")]
    FrameTooLarge { len: usize, max: usize },

    /// A frame carries exactly one message; anything after it means the peers disagree on the
    /// format.
    #[error("frame has {extra} unexpected bytes after the message")]
    TrailingBytes { extra: usize },

    /// The bytes are not a message of this protocol (bad tag, truncated, invalid UTF-8, or a
    /// string or list longer than its hard cap).
    #[error("malformed frame: {0}")]
    Malformed(#[from] bincode::error::DecodeError),

    /// Serialisation itself failed; with these types that only happens on a bug.
    #[error("cannot encode message: {0}")]
    Encode(#[from] bincode::error::EncodeError),

    /// A list holds more entries than the receiver's limits allow.
    #[error("{what}: {len} entries, over the limit of {max}")]
    TooMany {
        what: &'static str,
        len: usize,
        max: usize,
    },

    /// A text is longer than its bound.
    #[error("{what}: {len} bytes, over the limit of {max}")]
    TooLong {
        what: &'static str,
        len: usize,
        max: usize,
    },

    /// A float that is used for ordering or geometry is NaN or infinite.
    #[error("{what} is not a finite number")]
    NotFinite { what: &'static str },

    /// A `Limits` value (announced in `Welcome` or configured on the server) is unusable.
    #[error("limit {field} = {value} is invalid: {reason}")]
    InvalidLimit {
        field: &'static str,
        value: f64,
        reason: &'static str,
    },

    /// A brick handed to [`BrickBlob::encode`](super::BrickBlob::encode) has an empty mask or
    /// a colour list that does not match its mask.
    #[error("brick {index} at cell {cell:?} is empty or its colours do not match its mask")]
    InconsistentBrick { index: usize, cell: [u32; 3] },

    /// The blob layout stores cells as 16-bit values.
    #[error("brick {index} has cell {cell:?}, beyond the 16-bit range the blob format stores")]
    CellOutOfRange { index: usize, cell: [u32; 3] },

    /// The header of a blob claims a size that no `count` bricks can have.
    #[error("brick blob of {count} bricks claims {raw_len} raw bytes, outside {min}..={max}")]
    BlobRawLen {
        count: u32,
        raw_len: u32,
        min: u64,
        max: u64,
    },

    /// A blob of zero bricks must carry no data; anything else is a confused sender.
    #[error("empty brick blob carries {len} bytes of data")]
    EmptyBlobData { len: usize },

    /// zstd refused the data, or it decompressed to more than the header announced.
    #[error("brick blob does not decompress: {0}")]
    Decompress(#[source] std::io::Error),

    /// zstd could not be set up or could not compress; only on resource exhaustion.
    #[error("brick blob compression failed: {0}")]
    Compress(#[source] std::io::Error),

    /// The data decompressed to fewer bytes than the header announced.
    #[error("brick blob decompressed to {actual} bytes, header says {expected}")]
    BlobLength { expected: usize, actual: usize },

    /// A brick inside a blob has no solid voxel; empty bricks travel as removals instead.
    #[error("brick {index} in blob has an empty mask")]
    EmptyMask { index: usize },

    /// The colour section does not hold exactly one colour block per brick: it ends inside a
    /// block (`needed`: where that block ends) or goes on past the last one.
    #[error(
        "brick blob's colour blocks take {needed} bytes, data holds {actual_bytes} colour bytes"
    )]
    ColourBytes { needed: u64, actual_bytes: usize },

    /// A brick's colour block names no coding or does not decode (an index past its palette,
    /// an unsorted palette: [`crate::palette`]).
    #[error("brick {index} in blob has a bad colour block: {source}")]
    ColourBlock {
        index: usize,
        #[source]
        source: crate::palette::PaletteError,
    },

    /// Lossy colour blocks ([`crate::blocks`]) never travel: the wire carries exact colours.
    #[error("brick {index} in blob has a lossy colour block; the wire carries exact colours")]
    LossyBlock { index: usize },
}
