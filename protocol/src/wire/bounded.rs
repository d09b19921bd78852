//! Serde helpers that enforce a length bound while parsing, not after.
//!
//! Plain `String` and `Vec` deserialisation trusts the length prefix: bincode reserves a string's
//! claimed length before checking that the bytes exist, and a list is fully built before anyone
//! can look at its length. These helpers read the prefix, refuse it if it is over the cap, and
//! only then copy bytes that are already known to be in the frame (strings and byte buffers are
//! borrowed from the input slice first), so what a frame can make us allocate is proportional to
//! the frame itself.

use std::fmt;
use std::marker::PhantomData;

use serde::Serializer;
use serde::de::{self, Deserialize, Deserializer, SeqAccess, Visitor};

/// How many list entries to reserve up front, whatever the prefix claims; the rest grows as
/// entries actually arrive, each of which costs the sender at least a byte.
const PREALLOC_ENTRIES: usize = 1024;

struct StrVisitor<const N: usize>;

impl<'de, const N: usize> Visitor<'de> for StrVisitor<N> {
    type Value = String;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "a string of at most {N} bytes")
    }

    fn visit_str<E: de::Error>(self, v: &str) -> Result<String, E> {
        if v.len() > N {
            return Err(E::custom(format_args!(
                "string is {} bytes, over the limit of {N}",
                v.len()
            )));
        }
        Ok(v.to_owned())
    }

    fn visit_string<E: de::Error>(self, v: String) -> Result<String, E> {
        if v.len() > N {
            return Err(E::custom(format_args!(
                "string is {} bytes, over the limit of {N}",
                v.len()
            )));
        }
        Ok(v)
    }
}

/// A `String` that refuses to be longer than `N` bytes while being parsed.
struct BoundedString<const N: usize>(String);

impl<'de, const N: usize> Deserialize<'de> for BoundedString<N> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        // `deserialize_str` lets bincode hand over a slice of the input (after checking the bytes
        // are there) instead of zero-filling a buffer of the claimed length.
        d.deserialize_str(StrVisitor::<N>).map(BoundedString)
    }
}

/// `deserialize_with` for a `String` of at most `N` bytes.
pub(crate) fn string<'de, D: Deserializer<'de>, const N: usize>(d: D) -> Result<String, D::Error> {
    BoundedString::<N>::deserialize(d).map(|s| s.0)
}

/// `deserialize_with` for an `Option<String>` of at most `N` bytes.
pub(crate) fn opt_string<'de, D: Deserializer<'de>, const N: usize>(
    d: D,
) -> Result<Option<String>, D::Error> {
    Option::<BoundedString<N>>::deserialize(d).map(|s| s.map(|s| s.0))
}

struct VecVisitor<T, const N: usize>(PhantomData<T>);

impl<'de, T: Deserialize<'de>, const N: usize> Visitor<'de> for VecVisitor<T, N> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "a list of at most {N} entries")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        let claimed = seq.size_hint().unwrap_or(0);
        if claimed > N {
            return Err(de::Error::custom(format_args!(
                "list has {claimed} entries, over the limit of {N}"
            )));
        }
        let mut out = Vec::with_capacity(claimed.min(PREALLOC_ENTRIES));
        while let Some(item) = seq.next_element()? {
            if out.len() == N {
                return Err(de::Error::custom(format_args!("list has over {N} entries")));
            }
            out.push(item);
        }
        Ok(out)
    }
}

/// `deserialize_with` for a `Vec<T>` of at most `N` entries.
pub(crate) fn vec<'de, D, T, const N: usize>(d: D) -> Result<Vec<T>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    d.deserialize_seq(VecVisitor::<T, N>(PhantomData))
}

/// `serde(with)` for a byte buffer: one length prefix and a block copy instead of a list of
/// single-byte elements (the same bytes on the wire with bincode, but megabytes of blob data go
/// through one `memcpy` instead of one visitor call per byte).
pub(crate) mod bytes {
    use super::*;

    /// The largest byte buffer any frame can carry.
    const MAX: usize = super::super::MAX_FRAME_BYTES;

    pub(crate) fn serialize<S: Serializer>(v: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(v)
    }

    struct BytesVisitor;

    impl<'de> Visitor<'de> for BytesVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            write!(f, "a byte buffer of at most {MAX} bytes")
        }

        fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<Vec<u8>, E> {
            if v.len() > MAX {
                return Err(E::invalid_length(v.len(), &self));
            }
            Ok(v.to_vec())
        }

        fn visit_byte_buf<E: de::Error>(self, v: Vec<u8>) -> Result<Vec<u8>, E> {
            if v.len() > MAX {
                return Err(E::invalid_length(v.len(), &self));
            }
            Ok(v)
        }

        // Self-describing formats (JSON in tools and tests) send bytes as a list of numbers.
        fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<Vec<u8>, A::Error> {
            VecVisitor::<u8, MAX>(PhantomData).visit_seq(seq)
        }
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        d.deserialize_bytes(BytesVisitor)
    }
}
