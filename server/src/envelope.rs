//! One bounded envelope for every internal binary format: a tag (magic bytes, with the format's
//! version in them), a bincode body, a size limit, and typed errors.
//!
//! The server's own formats (log records, undo steps, store rows, the cluster's turns, presence
//! relays and forwarded requests, spooled scene files) each name a [`Format`]: what it is called
//! in errors, the bytes it starts with, and `LIMIT`, the most its body may be. Decoding checks
//! the tag, refuses a body over the limit before reading it, hands bincode the same limit (so a
//! length prefix in corrupt bytes cannot ask for more memory than that), and refuses bytes
//! after the value. Every decode site in the server goes through here, so what a peer, a file
//! or a NATS message controls is bounded and answered with an [`EnvelopeError`], never a panic.
//! The bytes each format writes are unchanged by this module (it frames them as before).

use serde::Serialize;
use serde::de::DeserializeOwned;

/// A binary format: its name in errors, its tag, and the most its body may hold (`LIMIT` bytes).
#[derive(Debug, Clone, Copy)]
pub struct Format<const LIMIT: usize> {
    pub what: &'static str,
    /// The bytes every value of the format starts with (empty for a format framed elsewhere,
    /// e.g. by its NATS subject).
    pub tag: &'static [u8],
}

/// Why bytes are not a value of a [`Format`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EnvelopeError {
    #[error("not a brickcast {what} ({len} bytes, starting {start})")]
    WrongTag {
        what: &'static str,
        len: usize,
        start: String,
    },
    #[error("a {what} of {len} bytes is over the limit of {limit}")]
    TooLarge {
        what: &'static str,
        len: usize,
        limit: usize,
    },
    #[error("a {what} that does not decode: {detail}")]
    Body { what: &'static str, detail: String },
    #[error("{extra} bytes after a {what}")]
    Trailing { what: &'static str, extra: usize },
    #[error("a {what} that cannot be encoded: {detail}")]
    Encode { what: &'static str, detail: String },
}

impl<const LIMIT: usize> Format<LIMIT> {
    /// A format called `what` whose values start with `tag`.
    pub const fn new(what: &'static str, tag: &'static [u8]) -> Self {
        Format { what, tag }
    }

    fn config(&self) -> impl bincode::config::Config {
        bincode::config::standard().with_limit::<LIMIT>()
    }

    /// The tag, then `value`.
    pub fn encode<T: Serialize + ?Sized>(&self, value: &T) -> Result<Vec<u8>, EnvelopeError> {
        let mut out = Vec::new();
        self.encode_into(value, &mut out)?;
        Ok(out)
    }

    /// Appends the tag, then `value`, to `out`.
    pub fn encode_into<T: Serialize + ?Sized>(
        &self,
        value: &T,
        out: &mut Vec<u8>,
    ) -> Result<(), EnvelopeError> {
        out.extend_from_slice(self.tag);
        self.append(value, out)
    }

    /// Appends `value` alone (a value inside a body whose tag was written already).
    pub fn append<T: Serialize + ?Sized>(
        &self,
        value: &T,
        out: &mut Vec<u8>,
    ) -> Result<(), EnvelopeError> {
        bincode::serde::encode_into_std_write(value, out, bincode::config::standard())
            .map(|_| ())
            .map_err(|e| EnvelopeError::Encode {
                what: self.what,
                detail: e.to_string(),
            })
    }

    /// The body after the tag: an error when `bytes` does not start with it or is over the limit.
    pub fn body<'a>(&self, bytes: &'a [u8]) -> Result<&'a [u8], EnvelopeError> {
        let Some(body) = bytes.strip_prefix(self.tag) else {
            let start: Vec<String> = bytes.iter().take(4).map(|b| format!("{b:02x}")).collect();
            return Err(EnvelopeError::WrongTag {
                what: self.what,
                len: bytes.len(),
                start: start.join(" "),
            });
        };
        self.check_len(body.len())?;
        Ok(body)
    }

    fn check_len(&self, len: usize) -> Result<(), EnvelopeError> {
        if len > LIMIT {
            return Err(EnvelopeError::TooLarge {
                what: self.what,
                len,
                limit: LIMIT,
            });
        }
        Ok(())
    }

    /// The one value `bytes` holds: its tag checked, nothing after it.
    pub fn decode<T: DeserializeOwned>(&self, bytes: &[u8]) -> Result<T, EnvelopeError> {
        let body = self.body(bytes)?;
        self.decode_body(body)
    }

    /// The one value a body (no tag) holds, nothing after it.
    pub fn decode_body<T: DeserializeOwned>(&self, body: &[u8]) -> Result<T, EnvelopeError> {
        let (value, read) = self.decode_prefix(body)?;
        if read != body.len() {
            return Err(EnvelopeError::Trailing {
                what: self.what,
                extra: body.len() - read,
            });
        }
        Ok(value)
    }

    /// The value at the start of `body` (no tag) and the bytes it took: for bodies that hold
    /// several values one after another.
    pub fn decode_prefix<T: DeserializeOwned>(
        &self,
        body: &[u8],
    ) -> Result<(T, usize), EnvelopeError> {
        self.check_len(body.len())?;
        bincode::serde::decode_from_slice(body, self.config()).map_err(|e| EnvelopeError::Body {
            what: self.what,
            detail: e.to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL: Format<64> = Format::new("test message", b"TM\x01");

    #[test]
    fn values_round_trip_and_bad_bytes_get_a_typed_error() {
        let bytes = SMALL.encode(&(7u32, "seven".to_string())).unwrap();
        assert_eq!(&bytes[..3], b"TM\x01");
        assert_eq!(
            SMALL.decode::<(u32, String)>(&bytes).unwrap(),
            (7, "seven".into())
        );
        // Another tag, a body over the limit, trailing bytes, a cut body.
        assert!(matches!(
            SMALL.decode::<u32>(b"XX\x01\x05"),
            Err(EnvelopeError::WrongTag { len: 4, .. })
        ));
        let mut big = b"TM\x01".to_vec();
        big.extend([0u8; 65]);
        assert!(matches!(
            SMALL.decode::<u32>(&big),
            Err(EnvelopeError::TooLarge {
                len: 65,
                limit: 64,
                ..
            })
        ));
        let mut extra = bytes.clone();
        extra.push(0);
        assert_eq!(
            SMALL.decode::<(u32, String)>(&extra),
            Err(EnvelopeError::Trailing {
                what: "test message",
                extra: 1
            })
        );
        assert!(matches!(
            SMALL.decode::<(u32, String)>(&bytes[..bytes.len() - 1]),
            Err(EnvelopeError::Body { .. })
        ));
    }

    /// A length prefix in corrupt bytes may claim any size: the limit stops the claim before
    /// anything is allocated for it.
    #[test]
    fn a_length_claim_past_the_limit_allocates_nothing() {
        // A Vec<u64> claiming 2^40 elements (bincode varint: 253 then a u64).
        let mut bytes = b"TM\x01\xfd".to_vec();
        bytes.extend((1u64 << 40).to_le_bytes());
        let e = SMALL.decode::<Vec<u64>>(&bytes).unwrap_err();
        assert!(matches!(e, EnvelopeError::Body { .. }), "{e}");
        assert!(
            e.to_string()
                .starts_with("a test message that does not decode")
        );
    }
}
