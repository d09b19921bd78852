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
//! | colours | `2 × Σ block words` | each brick's colour block ([`crate::palette`]), brick after brick |
//!
//! A colour block is the brick's exact coding — one colour, a palette of 1/2/4/8-bit indices,
//! or raw RGB565, as `u16` LE words — the same bytes the brick map's colour pool, the GPU copy
//! of an exact viewer and the redb store rows hold (protocol 4; protocol 3 sent every voxel's
//! RGB565). Lossy blocks ([`crate::blocks`]) never travel: a viewer that wants them codes the
//! exact colours itself, once. Each block says its own length (its header and the mask's
//! popcount), and the decoder decodes every block before it hands out any brick, so a bad index
//! or an unsorted palette refuses the whole blob.

use serde::{Deserialize, Serialize};

use super::zstd_frame::{Compressor, Decompressor};
use super::{MAX_BRICKS_PER_FRAME, WireError, bounded};
use crate::brick::{BRICK_VOXELS, BrickData, Mask, mask_is_empty, popcount};
use crate::colour::Colour;
use crate::palette::{self, Coding};

/// Raw bytes per brick for its cell.
const CELL_BYTES: usize = 6;
/// Raw bytes per brick for its mask.
const MASK_BYTES: usize = 64;
/// Raw bytes per brick before its colours.
const FIXED_BYTES: u64 = (CELL_BYTES + MASK_BYTES) as u64;
/// Bytes of the smallest colour block (one colour: header and colour).
const MIN_BLOCK_BYTES: u64 = 4;
/// Bytes of the largest exact colour block (raw: header and 512 colours).
const MAX_BLOCK_BYTES: u64 = 2 * (1 + BRICK_VOXELS as u64);

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
        let min = count * (FIXED_BYTES + MIN_BLOCK_BYTES);
        let max = count * (FIXED_BYTES + MAX_BLOCK_BYTES);
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
    /// One block's words while [`BlobEncoder::push`] codes it.
    scratch: Vec<u16>,
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
            scratch: vec![0; 1 + BRICK_VOXELS as usize],
            count: 0,
        })
    }

    /// Adds one brick, coding its colours exactly ([`palette::choose`]). On error nothing is
    /// added and the batch so far stays usable.
    pub fn push(
        &mut self,
        cell: [u32; 3],
        mask: &Mask,
        colours: &[Colour],
    ) -> Result<(), WireError> {
        let index = self.count as usize;
        if mask_is_empty(mask) || colours.len() != popcount(mask) as usize {
            return Err(WireError::InconsistentBrick { index, cell });
        }
        let (coding, entries) = palette::choose(colours);
        let words = &mut self.scratch[..coding.words(colours.len())];
        palette::encode_words(colours, coding, &entries, words);
        let block = std::mem::take(&mut self.scratch);
        let result = self.push_block(cell, mask, &block[..coding.words(colours.len())]);
        self.scratch = block;
        result
    }

    /// Adds one brick whose colours are already coded: `block` starts with an exact colour
    /// block of `popcount(mask)` colours (as [`crate::BrickMap::block`] hands out; words past
    /// the block's own length are ignored). Only the header and the length are checked here —
    /// the receiver decodes every block. On error nothing is added.
    pub fn push_block(
        &mut self,
        cell: [u32; 3],
        mask: &Mask,
        block: &[u16],
    ) -> Result<(), WireError> {
        let index = self.count as usize;
        if self.count >= MAX_BRICKS_PER_FRAME {
            return Err(WireError::TooMany {
                what: "bricks in blob",
                len: index + 1,
                max: MAX_BRICKS_PER_FRAME as usize,
            });
        }
        if mask_is_empty(mask) {
            return Err(WireError::InconsistentBrick { index, cell });
        }
        let voxels = popcount(mask) as usize;
        let len = match palette::coding_of_words(block) {
            Ok(Coding::Blocks { .. }) | Err(_) => {
                return Err(WireError::InconsistentBrick { index, cell });
            }
            Ok(coding) => coding.words(voxels),
        };
        if block.len() < len {
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
        self.colours.reserve(len * 2);
        for w in &block[..len] {
            self.colours.extend_from_slice(&w.to_le_bytes());
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
        // At most 8192 bricks of at most 1096 bytes: far inside u32.
        let raw_len = self.raw.len() as u32;
        Ok(BrickBlob {
            count,
            raw_len,
            data,
        })
    }
}

/// One brick inside a decompressed blob, borrowed from the decoder's buffers: its exact colour
/// block as it travelled, and its colours already decoded (the decoder decoded every block to
/// check the blob).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BrickRef<'a> {
    pub cell: [u32; 3],
    pub mask: Mask,
    block: &'a [u16],
    colours: &'a [Colour],
}

impl<'a> BrickRef<'a> {
    /// The brick's colour block ([`crate::palette`]), exactly its own words.
    pub fn block(&self) -> &'a [u16] {
        self.block
    }

    /// Number of solid voxels (and colours).
    pub fn colour_count(&self) -> usize {
        self.colours.len()
    }

    /// The colours in bit order.
    pub fn colours(&self) -> &'a [Colour] {
        self.colours
    }

    /// An owned copy.
    pub fn to_brick(&self) -> BrickData {
        BrickData {
            cell: self.cell,
            mask: self.mask,
            colours: self.colours.to_vec(),
        }
    }
}

/// Decompresses blobs with one zstd context and buffers kept between blobs; the client's
/// counterpart of [`BlobEncoder`].
pub struct BlobDecoder {
    decompressor: Decompressor,
    raw: Vec<u8>,
    /// The colour section as words.
    words: Vec<u16>,
    /// Every brick's colours, decoded, brick after brick.
    colours: Vec<Colour>,
    /// Where each brick's block starts in `words`.
    starts: Vec<u32>,
}

impl BlobDecoder {
    pub fn new() -> Result<Self, WireError> {
        Ok(BlobDecoder {
            decompressor: Decompressor::new().map_err(WireError::Decompress)?,
            raw: Vec::new(),
            words: Vec::new(),
            colours: Vec::new(),
            starts: Vec::new(),
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
    /// ever applying half a bad blob. Returns the number of bricks. The bricks borrow the
    /// decoder until its next blob, so a caller may also keep them to work on all at once.
    pub fn for_each<'a>(
        &'a mut self,
        blob: &BrickBlob,
        max_bricks: u32,
        mut f: impl FnMut(BrickRef<'a>),
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
        let (_, rest) = self
            .raw
            .split_at_checked(count * CELL_BYTES)
            .ok_or_else(length_error)?;
        let (masks, colours) = rest
            .split_at_checked(count * MASK_BYTES)
            .ok_or_else(length_error)?;
        let (masks, _) = masks.as_chunks::<MASK_BYTES>();
        let (pairs, odd) = colours.as_chunks::<2>();
        if !odd.is_empty() {
            return Err(WireError::ColourBytes {
                needed: colours.len() as u64 + 1,
                actual_bytes: colours.len(),
            });
        }
        self.words.clear();
        self.words
            .extend(pairs.iter().map(|p| u16::from_le_bytes(*p)));

        // First pass: every mask non-empty, every block exact and decodable, the colour
        // section exactly the blocks.
        self.colours.clear();
        self.starts.clear();
        let mut at = 0usize;
        for (index, m) in masks.iter().enumerate() {
            let mask = read_mask(m);
            if mask_is_empty(&mask) {
                return Err(WireError::EmptyMask { index });
            }
            let voxels = popcount(&mask) as usize;
            let rest = &self.words[at..];
            let len = match palette::coding_of_words(rest) {
                Ok(Coding::Blocks { .. }) => return Err(WireError::LossyBlock { index }),
                Ok(coding) => coding.words(voxels),
                Err(_) if rest.is_empty() => {
                    return Err(WireError::ColourBytes {
                        needed: 2 * (at as u64 + 1),
                        actual_bytes: colours.len(),
                    });
                }
                Err(source) => return Err(WireError::ColourBlock { index, source }),
            };
            if rest.len() < len {
                return Err(WireError::ColourBytes {
                    needed: 2 * (at + len) as u64,
                    actual_bytes: colours.len(),
                });
            }
            let from = self.colours.len();
            self.colours.resize(from + voxels, Colour::BLACK);
            palette::decode_words(&rest[..len], &mut self.colours[from..])
                .map_err(|source| WireError::ColourBlock { index, source })?;
            self.starts.push(at as u32);
            at += len;
        }
        if at != self.words.len() {
            return Err(WireError::ColourBytes {
                needed: 2 * at as u64,
                actual_bytes: colours.len(),
            });
        }

        // Second pass: hand out the bricks; the slicing cannot fail after the first pass.
        let this: &'a BlobDecoder = self;
        let cells = &this.raw[..count * CELL_BYTES];
        let masks = &this.raw[count * CELL_BYTES..count * (CELL_BYTES + MASK_BYTES)];
        let (cells, _) = cells.as_chunks::<CELL_BYTES>();
        let (masks, _) = masks.as_chunks::<MASK_BYTES>();
        let mut from = 0usize;
        for (i, (c, m)) in cells.iter().zip(masks).enumerate() {
            let mask = read_mask(m);
            let voxels = popcount(&mask) as usize;
            let start = self.starts[i] as usize;
            let end = self
                .starts
                .get(i + 1)
                .map_or(self.words.len(), |&e| e as usize);
            let cell = [
                u32::from(u16::from_le_bytes([c[0], c[1]])),
                u32::from(u16::from_le_bytes([c[2], c[3]])),
                u32::from(u16::from_le_bytes([c[4], c[5]])),
            ];
            f(BrickRef {
                cell,
                mask,
                block: &this.words[start..end],
                colours: &this.colours[from..from + voxels],
            });
            from += voxels;
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
