//! Turning messages into frames and frames into messages.

use bincode::config::{Configuration, Limit, LittleEndian, Varint};
use bincode::enc::write::Writer;
use bincode::error::EncodeError;
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::{ClientMsg, Limits, MAX_FRAME_BYTES, ServerMsg, WireError};

type Config = Configuration<LittleEndian, Varint, Limit<MAX_FRAME_BYTES>>;

/// Standard bincode with the hard frame cap as its decode limit.
const CONFIG: Config = bincode::config::standard().with_limit::<MAX_FRAME_BYTES>();

/// A `Vec` writer that stops storing at the cap but keeps counting, so an oversized message is
/// refused with its exact size without ever holding more than the cap in memory.
struct CappedWriter<'a> {
    out: &'a mut Vec<u8>,
    len: usize,
}

impl Writer for CappedWriter<'_> {
    fn write(&mut self, bytes: &[u8]) -> Result<(), EncodeError> {
        self.len = self.len.saturating_add(bytes.len());
        if self.len <= MAX_FRAME_BYTES {
            self.out.extend_from_slice(bytes);
        }
        Ok(())
    }
}

fn encode_into<T: Serialize>(msg: &T, out: &mut Vec<u8>) -> Result<(), WireError> {
    out.clear();
    let mut writer = CappedWriter { out, len: 0 };
    bincode::serde::encode_into_writer(msg, &mut writer, CONFIG)?;
    let len = writer.len;
    if len > MAX_FRAME_BYTES {
        out.clear();
        return Err(WireError::FrameTooLarge {
            len,
            max: MAX_FRAME_BYTES,
        });
    }
    Ok(())
}

fn decode<T: DeserializeOwned>(bytes: &[u8], limits: &Limits) -> Result<T, WireError> {
    let max = limits.frame_cap();
    if bytes.len() > max {
        return Err(WireError::FrameTooLarge {
            len: bytes.len(),
            max,
        });
    }
    // The borrowing decoder lets strings and byte buffers be checked against their bounds while
    // still slices of `bytes`, before anything is copied (see `bounded`).
    let (msg, read) = bincode::serde::borrow_decode_from_slice::<T, _>(bytes, CONFIG)?;
    if read != bytes.len() {
        return Err(WireError::TrailingBytes {
            extra: bytes.len().saturating_sub(read),
        });
    }
    Ok(msg)
}

/// Encodes a client message into one frame, after checking it against the hard caps.
pub fn encode_client(msg: &ClientMsg) -> Result<Vec<u8>, WireError> {
    msg.validate(&Limits::hard_caps())?;
    let mut out = Vec::new();
    encode_into(msg, &mut out)?;
    Ok(out)
}

/// Encodes a server message into one frame, after checking it against the hard caps.
///
/// This does not know the limits of the client it goes to; the server sizes its batches by
/// the limits it announced itself.
pub fn encode_server(msg: &ServerMsg) -> Result<Vec<u8>, WireError> {
    let mut out = Vec::new();
    encode_server_into(msg, &mut out)?;
    Ok(out)
}

/// [`encode_server`] into a buffer the caller keeps, for the broadcast loop that encodes the
/// same kind of frame many times a second. `out` is cleared first; on error it is left empty.
pub fn encode_server_into(msg: &ServerMsg, out: &mut Vec<u8>) -> Result<(), WireError> {
    msg.validate(&Limits::hard_caps())?;
    encode_into(msg, out)
}

/// Decodes one frame from a client, refusing it if it is over `limits.max_frame_bytes`, has
/// bytes after the message, or breaks any of `limits`.
pub fn decode_client(bytes: &[u8], limits: &Limits) -> Result<ClientMsg, WireError> {
    let msg: ClientMsg = decode(bytes, limits)?;
    msg.validate(limits)?;
    Ok(msg)
}

/// Decodes one frame from the server, refusing it if it is over `limits.max_frame_bytes`, has
/// bytes after the message, or breaks any of `limits`. Brick blobs are checked for plausible
/// size here but decompressed only when the caller asks ([`BrickBlob::decode`]).
///
/// A client decodes `Welcome` with [`Limits::hard_caps`] (it does not know the server's limits
/// yet) and everything after with the limits that `Welcome` announced.
///
/// [`BrickBlob::decode`]: super::BrickBlob::decode
pub fn decode_server(bytes: &[u8], limits: &Limits) -> Result<ServerMsg, WireError> {
    let msg: ServerMsg = decode(bytes, limits)?;
    msg.validate(limits)?;
    Ok(msg)
}

/// The protocol version in a frame that starts like a `Hello`, even if the rest of it does not
/// parse as this version's `Hello`.
///
/// A server whose `decode_client` fails on a connection's first frame uses this to tell an
/// out-of-date client (answer [`ErrorCode::VersionMismatch`]) from garbage (answer
/// `MalformedFrame`). It relies on `Hello` being variant 0 with the version as its first field,
/// which every version of the protocol keeps.
///
/// [`ErrorCode::VersionMismatch`]: super::ErrorCode::VersionMismatch
pub fn hello_version(bytes: &[u8]) -> Option<u32> {
    // Reads only the two leading varints; whatever follows is ignored.
    match bincode::serde::decode_from_slice::<(u32, u32), _>(bytes, CONFIG) {
        Ok(((0, version), _)) => Some(version),
        _ => None,
    }
}
