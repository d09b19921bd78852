//! Compressed batches of bricks.
//!
//! Raw (uncompressed) layout of `count` bricks, column by column because like values side by
//! side compress better (cells of neighbouring bricks differ in their low bytes only, masks of
//! surface bricks repeat, colours of one material repeat):
//!
//! | section | size | content |
//! | --- | --- | --- |
//! | cells | `count × 6` | `[x, y, z]` as `u16` LE each |
//! | masks | `count × 64` | 8 × `u64` LE each, bit order as in [`crate::brick`] |
//! | colours | `2 × Σ popcount` | `u16` LE RGB565, brick after brick, bit order within a brick |
//!
//! The colour section is the GPU's upload format already, which is why [`BrickRef`] hands it out
//! as bytes.

use serde::{Deserialize, Serialize};

use super::zstd_frame::{Compressor, Decompressor};
use super::{MAX_BRICKS_PER_FRAME, WireError, bounded};
use crate::brick::{BRICK_VOXELS, BrickData, Mask, mask_is_empty, popcount};
use crate::colour::Colour;

/// Raw bytes per brick for its cell.
const CELL_BYTES: usize = 6;
/// Raw bytes per brick for its mask.
const MASK_BYTES: usize = 64;
/// Raw bytes per brick before its colours.
const FIXED_BYTES: u64 = (CELL_BYTES + MASK_BYTES) as u64;

/// A batch of bricks, zstd-compressed.
///
/// The server compresses a batch once and sends the same bytes to every client that needs it,
/// so compression cost does not grow with the audience; a client only pays for decompression.
/// `count` and `raw_len` travel in the clear so a receiver can refuse an implausible blob (too
/// many bricks, a decompressed size no `count` bricks can have) before spending a byte of memory
/// on decompression.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BrickBlob {
    /// Number of bricks inside.
    pub count: u32,
    /// Exact size of the decompressed data.
    pub raw_len: u32,
    /// One zstd frame; empty when `count` is 0.
    #[serde(with = "bounded::bytes")]
    pub data: Vec<u8>,
}

impl BrickBlob {
    /// A blob of no bricks, for a `Delta` that only removes.
    pub fn empty() -> Self {
        BrickBlob {
            count: 0,
            raw_len: 0,
            data: Vec::new(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Compresses `bricks` at zstd `level`. Refuses more than [`MAX_BRICKS_PER_FRAME`] bricks,
    /// bricks that are empty or whose colours do not match their mask, and cells beyond `u16`.
    ///
    /// Sets up a zstd context per call; a server encoding many blobs keeps a [`BlobEncoder`].
    pub fn encode(bricks: &[BrickData], level: i32) -> Result<BrickBlob, WireError> {
        check_count(bricks.len(), MAX_BRICKS_PER_FRAME)?;
        if bricks.is_empty() {
            return Ok(BrickBlob::empty());
        }
        let mut encoder = BlobEncoder::new(level)?;
        for brick in bricks {
            encoder.push_brick(brick)?;
        }
        encoder.finish()
    }

    /// Decompresses and checks the blob: at most `max_bricks` (and the hard cap), every mask
    /// non-empty, exactly one colour per solid voxel. Nothing is returned unless all of it is
    /// valid.
    ///
    /// Sets up a zstd context per call; a client decoding many blobs keeps a [`BlobDecoder`].
    pub fn decode(&self, max_bricks: u32) -> Result<Vec<BrickData>, WireError> {
        self.validate_header(max_bricks)?;
        if self.count == 0 {
            return Ok(Vec::new());
        }
        BlobDecoder::new()?.decode(self, max_bricks)
    }

    /// The checks that need no decompression: brick count within `max_bricks` and the hard cap,
    /// `raw_len` possible for `count` bricks, no data for an empty blob. Run on every received
    /// frame by `decode_server`.
    pub fn validate_header(&self, max_bricks: u32) -> Result<(), WireError> {
        check_count(self.count as usize, max_bricks.min(MAX_BRICKS_PER_FRAME))?;
        let count = u64::from(self.count);
        let min = count * (FIXED_BYTES + 2);
        let max = count * (FIXED_BYTES + 2 * u64::from(BRICK_VOXELS));
        let raw_len = u64::from(self.raw_len);
        if raw_len < min || raw_len > max {
            return Err(WireError::BlobRawLen {
                count: self.count,
                raw_len: self.raw_len,
                min,
                max,
            });
        }
        if self.count == 0 && !self.data.is_empty() {
            return Err(WireError::EmptyBlobData {
                len: self.data.len(),
            });
        }
        Ok(())
    }
}

fn check_count(len: usize, max: u32) -> Result<(), WireError> {
    let max = max as usize;
    if len > max {
        Err(WireError::TooMany {
            what: "bricks in blob",
            len,
            max,
        })
    } else {
        Ok(())
    }
}

/// Builds blobs brick by brick into buffers that are kept between blobs, with one zstd context.
///
/// This is the server's fast path: bricks can be pushed straight from wherever the server keeps
/// them (no `BrickData` needed), nothing is allocated per brick, and after the first few blobs
/// nothing is allocated per blob except the compressed output itself. [`raw_len`] tells how big
/// the batch has grown so the caller can cut batches to fit its frame limit.
///
/// [`raw_len`]: BlobEncoder::raw_len
pub struct BlobEncoder {
    compressor: Compressor,
    cells: Vec<u8>,
    masks: Vec<u8>,
    colours: Vec<u8>,
    raw: Vec<u8>,
    count: u32,
}

impl BlobEncoder {
    /// A new encoder compressing at zstd `level` (3 is zstd's default, negative is faster).
    pub fn new(level: i32) -> Result<Self, WireError> {
        Ok(BlobEncoder {
            compressor: Compressor::new(level).map_err(WireError::Compress)?,
            cells: Vec::new(),
            masks: Vec::new(),
            colours: Vec::new(),
            raw: Vec::new(),
            count: 0,
        })
    }

    /// Adds one brick. On error nothing is added and the batch so far stays usable.
    pub fn push(
        &mut self,
        cell: [u32; 3],
        mask: &Mask,
        colours: &[Colour],
    ) -> Result<(), WireError> {
        let index = self.count as usize;
        if self.count >= MAX_BRICKS_PER_FRAME {
            return Err(WireError::TooMany {
                what: "bricks in blob",
                len: index + 1,
                max: MAX_BRICKS_PER_FRAME as usize,
            });
        }
        if mask_is_empty(mask) || colours.len() != popcount(mask) as usize {
            return Err(WireError::InconsistentBrick { index, cell });
        }
        let mut short = [0u16; 3];
        for (s, &c) in short.iter_mut().zip(&cell) {
            *s = u16::try_from(c).map_err(|_| WireError::CellOutOfRange { index, cell })?;
        }
        for s in short {
            self.cells.extend_from_slice(&s.to_le_bytes());
        }
        for word in mask {
            self.masks.extend_from_slice(&word.to_le_bytes());
        }
        self.colours.reserve(colours.len() * 2);
        for c in colours {
            self.colours.extend_from_slice(&c.0.to_le_bytes());
        }
        self.count += 1;
        Ok(())
    }

    /// [`push`](Self::push) for a brick already in compact form.
    pub fn push_brick(&mut self, brick: &BrickData) -> Result<(), WireError> {
        self.push(brick.cell, &brick.mask, &brick.colours)
    }

    /// Bricks pushed since the last `finish` or `clear`.
    pub fn len(&self) -> u32 {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Uncompressed size of the batch so far; the compressed blob is never much larger.
    pub fn raw_len(&self) -> usize {
        self.cells.len() + self.masks.len() + self.colours.len()
    }

    /// Drops the bricks pushed so far, keeping the buffers.
    pub fn clear(&mut self) {
        self.cells.clear();
        self.masks.clear();
        self.colours.clear();
        self.count = 0;
    }

    /// Compresses the batch into a blob and starts a new, empty batch.
    pub fn finish(&mut self) -> Result<BrickBlob, WireError> {
        if self.count == 0 {
            return Ok(BrickBlob::empty());
        }
        self.raw.clear();
        self.raw.reserve(self.raw_len());
        self.raw.extend_from_slice(&self.cells);
        self.raw.extend_from_slice(&self.masks);
        self.raw.extend_from_slice(&self.colours);
        let count = self.count;
        self.clear();
        let data = self
            .compressor
            .compress(&self.raw)
            .map_err(WireError::Compress)?;
        // At most 8192 bricks of at most 1094 bytes: far inside u32.
        let raw_len = self.raw.len() as u32;
        Ok(BrickBlob {
            count,
            raw_len,
            data,
        })
    }
}

/// One brick inside a decompressed blob, borrowed from the decoder's buffer.
///
/// Lets a client copy colours straight into its GPU upload buffer (they are already `u16` LE)
/// without building a `Vec<Colour>` per brick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BrickRef<'a> {
    pub cell: [u32; 3],
    pub mask: Mask,
    colour_bytes: &'a [u8],
}

impl<'a> BrickRef<'a> {
    /// The colours as `u16` little-endian, in bit order; `2 × popcount(mask)` bytes.
    pub fn colour_bytes(&self) -> &'a [u8] {
        self.colour_bytes
    }

    /// Number of solid voxels (and colours).
    pub fn colour_count(&self) -> usize {
        self.colour_bytes.len() / 2
    }

    /// The colours in bit order.
    pub fn colours(&self) -> impl ExactSizeIterator<Item = Colour> + 'a {
        let (pairs, _) = self.colour_bytes.as_chunks::<2>();
        pairs.iter().map(|p| Colour(u16::from_le_bytes(*p)))
    }

    /// An owned copy.
    pub fn to_brick(&self) -> BrickData {
        BrickData {
            cell: self.cell,
            mask: self.mask,
            colours: self.colours().collect(),
        }
    }
}

/// Decompresses blobs with one zstd context and one buffer kept between blobs; the client's
/// counterpart of [`BlobEncoder`].
pub struct BlobDecoder {
    decompressor: Decompressor,
    raw: Vec<u8>,
}

impl BlobDecoder {
    pub fn new() -> Result<Self, WireError> {
        Ok(BlobDecoder {
            decompressor: Decompressor::new().map_err(WireError::Decompress)?,
            raw: Vec::new(),
        })
    }

    /// Like [`BrickBlob::decode`].
    pub fn decode(
        &mut self,
        blob: &BrickBlob,
        max_bricks: u32,
    ) -> Result<Vec<BrickData>, WireError> {
        // The header check bounds `count` before it sizes an allocation.
        blob.validate_header(max_bricks)?;
        let mut out = Vec::with_capacity(blob.count as usize);
        self.for_each(blob, max_bricks, |brick| out.push(brick.to_brick()))?;
        Ok(out)
    }

    /// Checks the whole blob, then calls `f` for each brick in order. `f` is not called at all
    /// unless the blob is entirely valid, so a caller can apply bricks as they come without
    /// ever applying half a bad blob. Returns the number of bricks.
    pub fn for_each(
        &mut self,
        blob: &BrickBlob,
        max_bricks: u32,
        mut f: impl FnMut(BrickRef<'_>),
    ) -> Result<u32, WireError> {
        blob.validate_header(max_bricks)?;
        if blob.count == 0 {
            return Ok(0);
        }
        let expected = blob.raw_len as usize;
        // Exactly `raw_len` bytes of room: a blob that decompresses to more fails inside zstd
        // instead of growing the buffer, so the header bound is also the memory bound.
        self.raw.clear();
        self.raw.resize(expected, 0);
        let actual = self
            .decompressor
            .decompress_to_buffer(&blob.data, self.raw.as_mut_slice())
            .map_err(WireError::Decompress)?;
        if actual != expected {
            return Err(WireError::BlobLength { expected, actual });
        }

        let count = blob.count as usize;
        let length_error = || WireError::BlobLength { expected, actual };
        let (cells, rest) = self
            .raw
            .split_at_checked(count * CELL_BYTES)
            .ok_or_else(length_error)?;
        let (masks, colours) = rest
            .split_at_checked(count * MASK_BYTES)
            .ok_or_else(length_error)?;
        let (cells, _) = cells.as_chunks::<CELL_BYTES>();
        let (masks, _) = masks.as_chunks::<MASK_BYTES>();

        // First pass: every mask non-empty and the colour section exactly the right size.
        let mut solid = 0u64;
        for (index, m) in masks.iter().enumerate() {
            let mask = read_mask(m);
            if mask_is_empty(&mask) {
                return Err(WireError::EmptyMask { index });
            }
            solid += u64::from(popcount(&mask));
        }
        if colours.len() as u64 != solid * 2 {
            return Err(WireError::ColourCount {
                expected: solid,
                actual_bytes: colours.len(),
            });
        }

        // Second pass: hand out the bricks; the slicing cannot fail after the first pass.
        let mut rest = colours;
        for (c, m) in cells.iter().zip(masks) {
            let mask = read_mask(m);
            let n = popcount(&mask) as usize * 2;
            let (mine, tail) = rest.split_at_checked(n).unwrap_or((rest, &[]));
            rest = tail;
            let cell = [
                u32::from(u16::from_le_bytes([c[0], c[1]])),
                u32::from(u16::from_le_bytes([c[2], c[3]])),
                u32::from(u16::from_le_bytes([c[4], c[5]])),
            ];
            f(BrickRef {
                cell,
                mask,
                colour_bytes: mine,
            });
        }
        Ok(blob.count)
    }
}

fn read_mask(bytes: &[u8; MASK_BYTES]) -> Mask {
    let (words, _) = bytes.as_chunks::<8>();
    let mut mask = [0u64; 8];
    for (m, w) in mask.iter_mut().zip(words) {
        *m = u64::from_le_bytes(*w);
    }
    mask
}
