//! One zstd frame per brick blob, with the implementation the target can build.
//!
//! Why two: the C library (`zstd`) is the fast one and what the server and native clients use;
//! it does not build for `wasm32-unknown-unknown`, where the browser viewer runs, so there a
//! pure-Rust implementation (`ruzstd`) reads (and, for completeness, writes) the same frames.
//! Both read any valid zstd frame, so a blob written by either decodes with either.

use std::io;

/// Compresses blobs, keeping one context between them where the implementation has one.
pub(crate) struct Compressor {
    #[cfg(not(target_arch = "wasm32"))]
    inner: zstd::bulk::Compressor<'static>,
}

impl Compressor {
    /// `level` as zstd counts (3 is its default, negative is faster). The pure-Rust encoder
    /// has only its fastest level, which is the one the server uses for streaming anyway.
    pub(crate) fn new(level: i32) -> io::Result<Compressor> {
        #[cfg(not(target_arch = "wasm32"))]
        {
            Ok(Compressor {
                inner: zstd::bulk::Compressor::new(level)?,
            })
        }
        #[cfg(target_arch = "wasm32")]
        {
            let _ = level;
            Ok(Compressor {})
        }
    }

    pub(crate) fn compress(&mut self, raw: &[u8]) -> io::Result<Vec<u8>> {
        #[cfg(not(target_arch = "wasm32"))]
        {
            self.inner.compress(raw)
        }
        #[cfg(target_arch = "wasm32")]
        {
            Ok(ruzstd::encoding::compress_to_vec(
                raw,
                ruzstd::encoding::CompressionLevel::Fastest,
            ))
        }
    }
}

/// Decompresses blobs into a caller's buffer of exactly the announced size.
pub(crate) struct Decompressor {
    #[cfg(not(target_arch = "wasm32"))]
    inner: zstd::bulk::Decompressor<'static>,
}

impl Decompressor {
    pub(crate) fn new() -> io::Result<Decompressor> {
        #[cfg(not(target_arch = "wasm32"))]
        {
            Ok(Decompressor {
                inner: zstd::bulk::Decompressor::new()?,
            })
        }
        #[cfg(target_arch = "wasm32")]
        {
            Ok(Decompressor {})
        }
    }

    /// Decompresses `data` into `out` and returns how many bytes it produced. A frame that
    /// holds more than `out` has room for is an error, not a bigger allocation: the header's
    /// size is also the memory bound.
    pub(crate) fn decompress_to_buffer(
        &mut self,
        data: &[u8],
        out: &mut [u8],
    ) -> io::Result<usize> {
        #[cfg(not(target_arch = "wasm32"))]
        {
            self.inner.decompress_to_buffer(data, out)
        }
        #[cfg(target_arch = "wasm32")]
        {
            use std::io::Read;
            let mut source = data;
            let mut decoder = ruzstd::decoding::StreamingDecoder::new(&mut source)
                .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e.to_string()))?;
            let mut filled = 0;
            while filled < out.len() {
                match decoder.read(&mut out[filled..])? {
                    0 => return Ok(filled),
                    n => filled += n,
                }
            }
            let mut extra = [0u8; 1];
            if decoder.read(&mut extra)? != 0 {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    "the frame holds more than its header announced",
                ));
            }
            Ok(filled)
        }
    }
}
