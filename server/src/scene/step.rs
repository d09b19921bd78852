//! One step of undo history (what an edit message, an undo or a redo changed), how it is
//! stored, and how it is undone or replayed.
//!
//! **Columns, not voxels.** A step holds, per brick it changed, which voxels changed (a mask),
//! which of those were solid before and after (two masks) and their colours in bit order (two
//! lists): a brick a box filled is 200 bytes of masks and 1 KiB of one repeated colour, not 512
//! records of (bit, before, after). Two 256³ boxes (65,536 bricks, 33.5 M voxels) are ~80 MB in
//! memory and compress to a few hundred KB, where the voxel list was ~335 MB in memory and took
//! seconds to decode, plan and encode again in the owner's turn.
//!
//! **Frames.** A step is stored as frames of at most [`FRAME_BRICKS`] bricks, each compressed on
//! its own (zstd level 1, when that pays), so a large step can be read and planned a frame at a
//! time (the owner's sliced undo, `owner/undo.rs`) and a small step stays a few dozen bytes.
//!
//! Format 3 (this one): `[3][frames: u32]`, then per frame `[bricks: u32][raw: u32][stored: u32]`
//! and `stored` bytes (zstd when `stored < raw`). A frame's raw body is, per brick: the cell
//! (`u32`), a byte naming the words of the mask that are not zero, then for each such word the
//! changed, solid-before and solid-after words (`u64` each), then the before and the after
//! colours (`u16` each). Every integer is little-endian. Formats 1 and 2 (bincode of the voxel
//! list, raw or zstd) are still read.

use brickcast_protocol::BrickMap;
use brickcast_protocol::Colour;
use brickcast_protocol::brick::{BrickData, EMPTY_MASK, Mask, popcount};
use serde::{Deserialize, Serialize};

use crate::envelope::Format;

/// A brick's contents without its position.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Image {
    pub mask: Mask,
    pub colours: Vec<Colour>,
}

impl Image {
    fn from_voxels(voxels: &[Option<Colour>; 512]) -> Option<Image> {
        let mut mask = [0u64; 8];
        let mut colours = Vec::new();
        for (bit, voxel) in voxels.iter().enumerate() {
            if let Some(c) = voxel {
                mask[bit / 64] |= 1 << (bit % 64);
                colours.push(*c);
            }
        }
        (!colours.is_empty()).then_some(Image { mask, colours })
    }
}

/// One voxel a step changed: its bit in the brick (`brick::voxel_bit`), before and after.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VoxelChange {
    pub bit: u16,
    pub before: Option<Colour>,
    pub after: Option<Colour>,
}

/// One brick a step changed, column by column (see the module doc).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BrickChange {
    /// Linear cell index.
    pub cell: u32,
    /// The voxels the step changed.
    pub changed: Mask,
    /// Of the changed voxels, those solid before (after) the step.
    pub before_solid: Mask,
    pub after_solid: Mask,
    /// Colours of the changed voxels solid before (after), in bit order.
    pub before: Vec<Colour>,
    pub after: Vec<Colour>,
}

impl BrickChange {
    pub(super) fn empty(cell: u32) -> BrickChange {
        BrickChange {
            cell,
            changed: EMPTY_MASK,
            before_solid: EMPTY_MASK,
            after_solid: EMPTY_MASK,
            before: Vec::new(),
            after: Vec::new(),
        }
    }

    /// Adds one voxel's change; bits must come in increasing order.
    pub(super) fn push(&mut self, bit: u16, before: Option<Colour>, after: Option<Colour>) {
        let (w, b) = (usize::from(bit / 64) % 8, bit % 64);
        self.changed[w] |= 1 << b;
        if let Some(c) = before {
            self.before_solid[w] |= 1 << b;
            self.before.push(c);
        }
        if let Some(c) = after {
            self.after_solid[w] |= 1 << b;
            self.after.push(c);
        }
    }

    /// A brick change from voxel changes in any order (of two changes of one bit, the first counts);
    /// `None` when there are none.
    pub fn from_voxels(
        cell: u32,
        voxels: impl IntoIterator<Item = VoxelChange>,
    ) -> Option<BrickChange> {
        let mut all: Vec<VoxelChange> = voxels.into_iter().collect();
        all.sort_by_key(|v| v.bit % 512);
        all.dedup_by_key(|v| v.bit % 512);
        let mut change = BrickChange::empty(cell);
        for v in all {
            change.push(v.bit % 512, v.before, v.after);
        }
        (!change.is_empty()).then_some(change)
    }

    /// Voxels changed.
    pub fn len(&self) -> usize {
        popcount(&self.changed) as usize
    }

    pub fn is_empty(&self) -> bool {
        self.changed == EMPTY_MASK
    }

    /// Every voxel change, in bit order.
    pub fn voxels(&self) -> impl Iterator<Item = VoxelChange> + '_ {
        let (mut bi, mut ai) = (0, 0);
        bits(&self.changed).map(move |bit| {
            let (w, b) = (bit / 64, bit % 64);
            let before = (self.before_solid[w] >> b & 1 == 1).then(|| {
                bi += 1;
                self.before[bi - 1]
            });
            let after = (self.after_solid[w] >> b & 1 == 1).then(|| {
                ai += 1;
                self.after[ai - 1]
            });
            VoxelChange {
                bit: bit as u16,
                before,
                after,
            }
        })
    }

    /// Whether the columns agree with each other (decoded bytes are checked with this).
    fn is_consistent(&self) -> bool {
        (0..8).all(|w| {
            self.before_solid[w] & !self.changed[w] == 0
                && self.after_solid[w] & !self.changed[w] == 0
        }) && self.before.len() == popcount(&self.before_solid) as usize
            && self.after.len() == popcount(&self.after_solid) as usize
    }
}

/// The set bits of a mask, in increasing order.
fn bits(mask: &Mask) -> impl Iterator<Item = usize> + '_ {
    mask.iter().enumerate().flat_map(|(w, &word)| {
        let mut rest = word;
        std::iter::from_fn(move || {
            (rest != 0).then(|| {
                let t = rest.trailing_zeros() as usize;
                rest &= rest - 1;
                w * 64 + t
            })
        })
    })
}

/// Every voxel's colour of a brick (`None`: empty), in bit order.
fn brick_voxels(brick: Option<&BrickData>) -> [Option<Colour>; 512] {
    let mut out = [None; 512];
    if let Some(b) = brick {
        let mut next = b.colours.iter();
        for (bit, voxel) in out.iter_mut().enumerate() {
            if (b.mask[bit / 64] >> (bit % 64)) & 1 == 1 {
                *voxel = next.next().copied();
            }
        }
    }
    out
}

/// What one edit message, undo or redo changed.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Step {
    pub bricks: Vec<BrickChange>,
}

impl Step {
    /// The step an edit made, from the map's journal (see [`BrickMap::begin_journal`], which
    /// this ends): every voxel that differs between each journaled brick and that brick now.
    pub fn from_journal(map: &mut BrickMap) -> Step {
        let mut bricks: Vec<BrickChange> = Vec::new();
        map.end_journal(|cell, bit, b, a| {
            if bricks.last().is_none_or(|c| c.cell != cell) {
                bricks.push(BrickChange::empty(cell));
            }
            if let Some(change) = bricks.last_mut() {
                change.push(bit, b, a);
            }
        });
        bricks.sort_unstable_by_key(|b: &BrickChange| b.cell);
        Step { bricks }
    }

    /// Voxels the step changed.
    pub fn voxel_count(&self) -> u64 {
        self.bricks.iter().map(|b| b.len() as u64).sum()
    }

    /// Stored form (format 3, see the module doc).
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(None)
    }

    /// [`Step::encode`] with a compressor kept from step to step (creating one per step cost
    /// as much as compressing a small step).
    pub fn encode_with(&self, compressor: Option<&mut zstd::bulk::Compressor<'static>>) -> Vec<u8> {
        encode_frames(&self.bricks, compressor)
    }

    /// A stored step, whole (formats 1 to 3).
    pub fn decode(bytes: &[u8]) -> Result<Step, String> {
        match bytes.first() {
            Some(&STEP_FRAMES) => {
                let mut frames = Frames::new(bytes)?;
                let mut bricks = Vec::new();
                while let Some(frame) = frames.next_frame()? {
                    bricks.extend(frame);
                }
                Ok(Step { bricks })
            }
            _ => decode_legacy(bytes),
        }
    }
}

/// The stored form of a step of `bricks` (format 3).
pub fn encode_frames(
    bricks: &[BrickChange],
    compressor: Option<&mut zstd::bulk::Compressor<'static>>,
) -> Vec<u8> {
    let mut frames = EncodedFrames::default();
    frames.push(bricks, compressor);
    frames.finish()
}

/// Frames of a step encoded a few at a time (a sliced undo encodes its record as it plans
/// it), then put together.
#[derive(Clone, Debug, Default)]
pub struct EncodedFrames {
    count: u32,
    bytes: Vec<u8>,
}

impl EncodedFrames {
    /// Encodes `bricks` as the next frames.
    pub fn push(
        &mut self,
        bricks: &[BrickChange],
        mut compressor: Option<&mut zstd::bulk::Compressor<'static>>,
    ) {
        let mut raw = Vec::new();
        for frame in bricks.chunks(FRAME_BRICKS) {
            raw.clear();
            for change in frame {
                encode_brick(change, &mut raw);
            }
            let packed = if raw.len() > COMPRESS_ABOVE {
                match compressor.as_deref_mut() {
                    Some(c) => c.compress(&raw).ok(),
                    None => zstd::bulk::compress(&raw, 1).ok(),
                }
            } else {
                None
            };
            let stored = packed.as_deref().filter(|p| p.len() < raw.len());
            let body = stored.unwrap_or(&raw);
            self.bytes.reserve(12 + body.len());
            self.bytes
                .extend_from_slice(&(frame.len() as u32).to_le_bytes());
            self.bytes
                .extend_from_slice(&(raw.len() as u32).to_le_bytes());
            self.bytes
                .extend_from_slice(&(body.len() as u32).to_le_bytes());
            self.bytes.extend_from_slice(body);
            self.count += 1;
        }
    }

    /// Appends frames encoded elsewhere, after these.
    pub fn append(&mut self, other: &EncodedFrames) {
        self.count += other.count;
        self.bytes.extend_from_slice(&other.bytes);
    }

    /// The stored step (format 3).
    pub fn finish(self) -> Vec<u8> {
        let mut out = Vec::with_capacity(5 + self.bytes.len());
        out.push(STEP_FRAMES);
        out.extend_from_slice(&self.count.to_le_bytes());
        out.extend_from_slice(&self.bytes);
        out
    }
}

/// A stored step read a frame at a time (format 3; older formats come as one frame).
pub struct Frames<'a> {
    rest: &'a [u8],
    left: u32,
    /// An older format, decoded whole.
    legacy: Option<Vec<BrickChange>>,
}

impl<'a> Frames<'a> {
    pub fn new(bytes: &'a [u8]) -> Result<Frames<'a>, String> {
        match bytes.split_first() {
            Some((&STEP_FRAMES, rest)) => {
                let (count, rest) = take_u32(rest)?;
                Ok(Frames {
                    rest,
                    left: count,
                    legacy: None,
                })
            }
            _ => Ok(Frames {
                rest: &[],
                left: 0,
                legacy: Some(decode_legacy(bytes)?.bricks),
            }),
        }
    }

    /// Reading `bytes` again from where [`Frames::position`] said an earlier reading stopped.
    pub fn resume(bytes: &'a [u8], offset: usize, left: u32) -> Result<Frames<'a>, String> {
        if offset == 0 {
            return Frames::new(bytes);
        }
        match bytes.get(offset..) {
            Some(rest) => Ok(Frames {
                rest,
                left,
                legacy: None,
            }),
            None => Err("a step reading resumed past its end".into()),
        }
    }

    /// Where the next frame starts in `bytes` (the slice this reading was made from), and how
    /// many frames are left.
    pub fn position(&self, bytes: &[u8]) -> (usize, u32) {
        (bytes.len() - self.rest.len(), self.left)
    }

    /// The next frame's bricks; `None` after the last.
    pub fn next_frame(&mut self) -> Result<Option<Vec<BrickChange>>, String> {
        if let Some(all) = self.legacy.take() {
            return Ok(Some(all));
        }
        if self.left == 0 {
            return if self.rest.is_empty() {
                Ok(None)
            } else {
                Err(format!("{} bytes after the step's frames", self.rest.len()))
            };
        }
        self.left -= 1;
        let (bricks, rest) = take_u32(self.rest)?;
        let (raw_len, rest) = take_u32(rest)?;
        let (stored_len, rest) = take_u32(rest)?;
        let (bricks, raw_len, stored_len) =
            (bricks as usize, raw_len as usize, stored_len as usize);
        if stored_len > rest.len() || stored_len > raw_len || raw_len > MAX_FRAME_BYTES {
            return Err(format!(
                "a step frame of {stored_len} stored / {raw_len} raw bytes does not fit"
            ));
        }
        if bricks > FRAME_BRICKS {
            return Err(format!("a step frame of {bricks} bricks"));
        }
        let (stored, rest) = rest.split_at(stored_len);
        self.rest = rest;
        let unpacked;
        let raw = if stored_len < raw_len {
            unpacked = zstd::bulk::decompress(stored, raw_len).map_err(|e| e.to_string())?;
            if unpacked.len() != raw_len {
                return Err("a step frame decompressed to the wrong size".into());
            }
            &unpacked[..]
        } else {
            stored
        };
        let mut body = raw;
        let mut out = Vec::with_capacity(bricks);
        for _ in 0..bricks {
            let (change, rest) = decode_brick(body)?;
            out.push(change);
            body = rest;
        }
        if !body.is_empty() {
            return Err(format!("{} bytes after a step frame's bricks", body.len()));
        }
        Ok(Some(out))
    }
}

fn encode_brick(change: &BrickChange, out: &mut Vec<u8>) {
    out.extend_from_slice(&change.cell.to_le_bytes());
    let words = (0..8).fold(0u8, |acc, w| acc | u8::from(change.changed[w] != 0) << w);
    out.push(words);
    for w in (0..8).filter(|w| words >> w & 1 == 1) {
        out.extend_from_slice(&change.changed[w].to_le_bytes());
        out.extend_from_slice(&change.before_solid[w].to_le_bytes());
        out.extend_from_slice(&change.after_solid[w].to_le_bytes());
    }
    out.reserve(2 * (change.before.len() + change.after.len()));
    for c in change.before.iter().chain(&change.after) {
        out.extend_from_slice(&c.0.to_le_bytes());
    }
}

fn decode_brick(bytes: &[u8]) -> Result<(BrickChange, &[u8]), String> {
    let (cell, rest) = take_u32(bytes)?;
    let (&words, mut rest) = rest.split_first().ok_or("a step brick is cut short")?;
    let mut change = BrickChange::empty(cell);
    for w in (0..8).filter(|w| words >> w & 1 == 1) {
        let (c, r) = take_u64(rest)?;
        let (b, r) = take_u64(r)?;
        let (a, r) = take_u64(r)?;
        (
            change.changed[w],
            change.before_solid[w],
            change.after_solid[w],
        ) = (c, b, a);
        rest = r;
    }
    let colours = |n: u32, rest: &[u8]| -> Result<(Vec<Colour>, usize), String> {
        let n = n as usize;
        let bytes = rest
            .get(..2 * n)
            .ok_or("a step brick's colours are cut short")?;
        let list = bytes
            .chunks_exact(2)
            .map(|c| Colour(u16::from_le_bytes([c[0], c[1]])))
            .collect();
        Ok((list, 2 * n))
    };
    let (before, used) = colours(popcount(&change.before_solid), rest)?;
    rest = &rest[used..];
    let (after, used) = colours(popcount(&change.after_solid), rest)?;
    rest = &rest[used..];
    (change.before, change.after) = (before, after);
    if change.is_empty() || !change.is_consistent() {
        return Err(format!("a step brick of cell {cell} is not consistent"));
    }
    Ok((change, rest))
}

fn take_u32(bytes: &[u8]) -> Result<(u32, &[u8]), String> {
    match bytes.split_first_chunk::<4>() {
        Some((n, rest)) => Ok((u32::from_le_bytes(*n), rest)),
        None => Err("a step is cut short".into()),
    }
}

fn take_u64(bytes: &[u8]) -> Result<(u64, &[u8]), String> {
    match bytes.split_first_chunk::<8>() {
        Some((n, rest)) => Ok((u64::from_le_bytes(*n), rest)),
        None => Err("a step is cut short".into()),
    }
}

/// Formats 1 and 2: bincode of the voxel list, raw or zstd.
fn decode_legacy(bytes: &[u8]) -> Result<Step, String> {
    #[derive(Deserialize)]
    struct LegacyBrick {
        cell: u32,
        voxels: Vec<VoxelChange>,
    }
    #[derive(Deserialize)]
    struct LegacyStep {
        bricks: Vec<LegacyBrick>,
    }
    let raw;
    let body = match bytes.split_first() {
        Some((&STEP_RAW, body)) => body,
        Some((&STEP_ZSTD, rest)) if rest.len() >= 4 => {
            let len = u32::from_le_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
            if len > MAX_LEGACY_BYTES {
                return Err(format!("a step of {len} bytes is over {MAX_LEGACY_BYTES}"));
            }
            raw = zstd::bulk::decompress(&rest[4..], len).map_err(|e| e.to_string())?;
            &raw
        }
        _ => return Err("unknown step format".into()),
    };
    let (step, _): (LegacyStep, usize) =
        LEGACY_STEP.decode_prefix(body).map_err(|e| e.to_string())?;
    Ok(Step {
        bricks: step
            .bricks
            .into_iter()
            .filter_map(|b| BrickChange::from_voxels(b.cell, b.voxels))
            .collect(),
    })
}

/// Frames above this many raw bytes are stored zstd-compressed (level 1): a brush's step
/// shrinks several times, which the commit and the disk gain back.
const COMPRESS_ABOVE: usize = 4 << 10;
/// Bricks per frame: ~600 KiB raw for bricks changed whole, planned in well under 10 ms.
pub const FRAME_BRICKS: usize = 512;
const STEP_RAW: u8 = 1;
const STEP_ZSTD: u8 = 2;
const STEP_FRAMES: u8 = 3;
/// Largest raw frame: every voxel of every brick of a frame changed, with colours both sides.
const MAX_FRAME_BYTES: usize = FRAME_BRICKS * (5 + 8 * 24 + 2 * 2 * 512);
/// Largest decoded step of the old formats.
const MAX_LEGACY_BYTES: usize = 1 << 30;
/// A step of the old formats once unpacked.
const LEGACY_STEP: Format<MAX_LEGACY_BYTES> = Format::new("undo step (old format)", b"");

/// What undoing a step would do to the map now.
pub struct Revert {
    /// Cells whose brick changes, with the brick they get (`None`: the cell empties), and the
    /// record of the change (for the opposite stack).
    pub writes: Vec<(u32, Option<Image>)>,
    pub record: Step,
    /// Voxels that go back to the step's before-value.
    pub restored: u64,
    /// Voxels the step changed that someone changed again since: left as they are.
    pub kept: u64,
}

impl Revert {
    pub fn new() -> Revert {
        Revert {
            writes: Vec::new(),
            record: Step::default(),
            restored: 0,
            kept: 0,
        }
    }
}

impl Default for Revert {
    fn default() -> Self {
        Revert::new()
    }
}

/// Plans undoing `step` against the map as it is: every voxel the step changed goes back to its
/// before-value where it still holds the after-value. Changes nothing.
pub fn plan_revert(map: &BrickMap, step: &Step) -> Revert {
    let mut revert = Revert::new();
    plan_revert_into(map, &step.bricks, &mut revert);
    revert
}

/// [`plan_revert`] of some of a step's bricks, added to `revert`.
pub fn plan_revert_into(map: &BrickMap, bricks: &[BrickChange], revert: &mut Revert) {
    let cells = map.cell_dims();
    let count = u64::from(cells[0]) * u64::from(cells[1]) * u64::from(cells[2]);
    for change in bricks {
        if u64::from(change.cell) >= count {
            continue; // Not this scene's step: nothing of it can be restored.
        }
        let coords = map.cell_coords(change.cell);
        let mut voxels = brick_voxels(map.brick(coords).as_ref());
        let mut undone = BrickChange::empty(change.cell);
        for v in change.voxels() {
            let i = usize::from(v.bit) % 512;
            if voxels[i] == v.after {
                voxels[i] = v.before;
                undone.push(v.bit, v.after, v.before);
            } else {
                revert.kept += 1;
            }
        }
        if !undone.is_empty() {
            revert.restored += undone.len() as u64;
            revert
                .writes
                .push((change.cell, Image::from_voxels(&voxels)));
            revert.record.bricks.push(undone);
        }
    }
}

/// Writes whole bricks (a logged revert of an older store being replayed).
pub fn write_bricks(map: &mut BrickMap, writes: &[(u32, Option<Image>)]) -> Result<(), String> {
    for (cell, image) in writes {
        write_brick(
            map,
            *cell,
            image.as_ref().map(|i| (i.mask, i.colours.clone())),
        )?;
    }
    Ok(())
}

/// Writes a planned revert's bricks, giving them up (no copy of their colours).
pub fn write_planned(
    map: &mut BrickMap,
    writes: impl IntoIterator<Item = (u32, Option<Image>)>,
) -> Result<(), String> {
    let cells = map.cell_dims();
    let count = u64::from(cells[0]) * u64::from(cells[1]) * u64::from(cells[2]);
    let mut outside = None;
    let bricks = writes.into_iter().map_while(|(cell, image)| {
        if u64::from(cell) >= count {
            outside = Some(cell);
            return None;
        }
        let (x, rest) = (cell % cells[0], cell / cells[0]);
        let coords = [x, rest % cells[1], rest / cells[1]];
        Some((coords, image.map(|i| (i.mask, i.colours))))
    });
    map.write_bricks(bricks).map_err(|e| e.to_string())?;
    match outside {
        Some(cell) => Err(format!("cell {cell} is outside the scene")),
        None => Ok(()),
    }
}

fn write_brick(
    map: &mut BrickMap,
    cell: u32,
    brick: Option<(Mask, Vec<Colour>)>,
) -> Result<(), String> {
    let cells = map.cell_dims();
    if u64::from(cell) >= u64::from(cells[0]) * u64::from(cells[1]) * u64::from(cells[2]) {
        return Err(format!("cell {cell} is outside the scene"));
    }
    let coords = map.cell_coords(cell);
    match brick {
        Some((mask, colours)) => map
            .put_brick(&BrickData {
                cell: coords,
                mask,
                colours,
            })
            .map_err(|e| e.to_string()),
        None => {
            map.remove_brick(coords);
            Ok(())
        }
    }
}

/// Sets every voxel a step changed to its after-value: replays a logged undo or redo, whose
/// record says exactly what it changed (a log record of it is its encoded record). Works a
/// mask word at a time: recovery replays every brick of a large undo this way.
pub fn apply_after(map: &mut BrickMap, step: &Step) -> Result<(), String> {
    let cells = map.cell_dims();
    let count = u64::from(cells[0]) * u64::from(cells[1]) * u64::from(cells[2]);
    for change in &step.bricks {
        if u64::from(change.cell) >= count {
            return Err(format!("cell {} is outside the scene", change.cell));
        }
        let coords = map.cell_coords(change.cell);
        let (old_mask, old) = match map.brick(coords) {
            Some(b) => (b.mask, b.colours),
            None => (EMPTY_MASK, Vec::new()),
        };
        let mut mask = EMPTY_MASK;
        let mut colours = Vec::with_capacity(old.len() + change.after.len());
        let (mut oi, mut ai) = (0, 0);
        for w in 0..8 {
            let (was, changed, after) = (old_mask[w], change.changed[w], change.after_solid[w]);
            mask[w] = (was & !changed) | after;
            let mut bits = was | after;
            while bits != 0 {
                let t = bits.trailing_zeros();
                bits &= bits - 1;
                let colour = if was >> t & 1 == 1 {
                    oi += 1;
                    old.get(oi - 1).copied()
                } else {
                    None
                };
                if changed >> t & 1 == 1 {
                    if after >> t & 1 == 1 {
                        ai += 1;
                        colours.extend(change.after.get(ai - 1).copied());
                    }
                } else {
                    colours.extend(colour);
                }
            }
        }
        if mask == EMPTY_MASK {
            map.remove_brick(coords);
        } else {
            map.put_brick(&BrickData {
                cell: coords,
                mask,
                colours,
            })
            .map_err(|e| e.to_string())?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn colour(n: u16) -> Colour {
        Colour(n)
    }

    fn change(cell: u32, voxels: &[(u16, Option<u16>, Option<u16>)]) -> BrickChange {
        BrickChange::from_voxels(
            cell,
            voxels.iter().map(|&(bit, b, a)| VoxelChange {
                bit,
                before: b.map(colour),
                after: a.map(colour),
            }),
        )
        .unwrap()
    }

    #[test]
    fn steps_round_trip_in_frames_and_small_steps_stay_small() {
        let one = Step {
            bricks: vec![change(5, &[(3, None, Some(7))])],
        };
        let bytes = one.encode();
        assert!(
            bytes.len() <= 48,
            "a one-voxel step is {} bytes",
            bytes.len()
        );
        assert_eq!(Step::decode(&bytes).unwrap(), one);
        // More bricks than a frame holds, every voxel changed: several frames, compressed.
        let full: Vec<(u16, Option<u16>, Option<u16>)> = (0..512)
            .map(|b| (b, (b % 3 == 0).then_some(b), Some(9)))
            .collect();
        let big = Step {
            bricks: (0..(2 * FRAME_BRICKS as u32 + 3))
                .map(|c| change(c, &full))
                .collect(),
        };
        let bytes = big.encode();
        assert!(bytes.len() < 300 << 10, "{} bytes", bytes.len());
        let mut frames = Frames::new(&bytes).unwrap();
        let mut sizes = Vec::new();
        while let Some(f) = frames.next_frame().unwrap() {
            sizes.push(f.len());
        }
        assert_eq!(sizes, [FRAME_BRICKS, FRAME_BRICKS, 3]);
        assert_eq!(Step::decode(&bytes).unwrap(), big);
        // The voxel view gives back what went in.
        let v: Vec<VoxelChange> = big.bricks[0].voxels().collect();
        assert_eq!(v.len(), 512);
        assert_eq!(v[3].before, Some(colour(3)));
        assert_eq!(v[4].before, None);
        assert_eq!(v[4].after, Some(colour(9)));
    }

    #[test]
    fn steps_of_the_old_formats_still_read() {
        #[derive(Serialize)]
        struct LegacyBrick {
            cell: u32,
            voxels: Vec<VoxelChange>,
        }
        #[derive(Serialize)]
        struct LegacyStep {
            bricks: Vec<LegacyBrick>,
        }
        let voxels = vec![
            VoxelChange {
                bit: 9,
                before: None,
                after: Some(colour(4)),
            },
            VoxelChange {
                bit: 2,
                before: Some(colour(1)),
                after: None,
            },
        ];
        let old = LegacyStep {
            bricks: vec![LegacyBrick { cell: 11, voxels }],
        };
        let raw = bincode::serde::encode_to_vec(&old, bincode::config::standard()).unwrap();
        let expected = Step {
            bricks: vec![change(11, &[(2, Some(1), None), (9, None, Some(4))])],
        };
        let mut format1 = vec![STEP_RAW];
        format1.extend_from_slice(&raw);
        assert_eq!(Step::decode(&format1).unwrap(), expected);
        let mut format2 = vec![STEP_ZSTD];
        format2.extend_from_slice(&(raw.len() as u32).to_le_bytes());
        format2.extend_from_slice(&zstd::bulk::compress(&raw, 1).unwrap());
        assert_eq!(Step::decode(&format2).unwrap(), expected);
    }

    #[test]
    fn garbage_steps_are_errors_never_panics() {
        let good = Step {
            bricks: vec![change(5, &[(3, None, Some(7)), (400, Some(2), None)])],
        }
        .encode();
        for cut in 0..good.len() {
            assert!(Step::decode(&good[..cut]).is_err(), "cut at {cut}");
        }
        let mut extra = good.clone();
        extra.push(0);
        assert!(Step::decode(&extra).is_err());
        // A solid-after bit outside the changed mask.
        let mut bad = good.clone();
        let at = 5 + 12 + 4 + 1 + 16;
        bad[at] ^= 0x80;
        assert!(Step::decode(&bad).is_err());
        for bytes in [
            &[][..],
            &[9, 1, 2],
            &[2, 255, 255, 255, 255, 0],
            &[1, 200],
            &[3, 1, 0, 0, 0, 255, 255, 255, 255, 0, 0, 0, 0, 0, 0, 0, 0],
        ] {
            assert!(Step::decode(bytes).is_err());
        }
    }

    /// The step from the journal is exactly the voxels that differ between the map before and
    /// after a message, whatever mix of single voxels (the same voxel twice, set then cleared
    /// back) and whole-brick changes it held.
    #[test]
    fn a_journaled_step_is_exactly_what_changed() {
        use brickcast_protocol::BrushMode;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(31);
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        map.fill_box([0, 0, 0], [31, 6, 31], BrushMode::Fill, colour(7));
        for _ in 0..300 {
            let before = map.clone();
            map.begin_journal();
            for _ in 0..rng.random_range(1..12) {
                // A small corner, so ops meet in the same bricks and voxels.
                let p = [0, 1, 2].map(|_| rng.random_range(0..12u32));
                let c = colour(rng.random_range(1..6));
                match rng.random_range(0..10) {
                    0..=3 => drop(map.set(p, c)),
                    4..=5 => drop(map.clear(p)),
                    6 => drop(map.paint(p, c)),
                    7 => drop(map.fill_box(p, p.map(|v| v + 3), BrushMode::Fill, c)),
                    8 => drop(map.sphere(p.map(|v| v as f32), 2.5, BrushMode::Erase, c)),
                    _ => drop(map.remove_brick(p.map(|v| v / 8))),
                }
            }
            let step = Step::from_journal(&mut map);
            let mut want = Vec::new();
            for coords in brickcast_protocol::map::box_points([0; 3], [4; 3]) {
                let cell = map.cell_index(coords);
                let (b, a) = (before.brick(coords), map.brick(coords));
                let none = ([0u64; 8], Vec::new());
                let b = b.map_or(none.clone(), |b| (b.mask, b.colours));
                let a = a.map_or(none, |a| (a.mask, a.colours));
                let mut change = BrickChange::empty(cell);
                brickcast_protocol::journal::diff_bricks(
                    (&b.0, &b.1),
                    (&a.0, &a.1),
                    |bit, x, y| change.push(bit, x, y),
                );
                if !change.is_empty() {
                    want.push(change);
                }
            }
            want.sort_unstable_by_key(|c| c.cell);
            assert_eq!(step.bricks, want);
        }
    }
}
