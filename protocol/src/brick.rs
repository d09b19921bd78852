//! The 8×8×8 brick and its compact form.
//!
//! A brick is a 512-bit solid mask plus the colours of its solid voxels only, in bit order: the
//! colour of voxel `b` is entry `rank(mask, b)` (the number of solid voxels before it). Keeping the
//! mask apart from the colours lets a ray step through bricks reading 64 bytes each (paper 3.1),
//! and storing colours only for solid voxels is what makes surface scenes small.
//!
//! Bit order: voxel `(x, y, z)` inside a brick is bit `x + 8·y + 64·z`, so one `u64` word is one
//! z-slice and one byte is one row. Read as little-endian `u32`s (as the GPU does) it is the same
//! bit order: bit `b` lives in `u32` word `b / 32`.

use serde::{Deserialize, Serialize};

use crate::colour::Colour;

/// Voxels along one edge of a brick.
pub const BRICK_EDGE: u32 = 8;
/// Voxels in one brick.
pub const BRICK_VOXELS: u32 = 512;
/// Marks an empty coarse-grid cell or an unallocated region (paper 3.1).
pub const EMPTY: u32 = 0xFFFF_FFFF;

/// The solid-voxel mask of one brick.
pub type Mask = [u64; 8];

/// A mask with no solid voxel.
pub const EMPTY_MASK: Mask = [0; 8];
/// A mask with every voxel solid.
pub const FULL_MASK: Mask = [u64::MAX; 8];

/// Bit index of a voxel inside its brick; each coordinate is taken modulo 8.
#[inline]
pub const fn voxel_bit(x: u32, y: u32, z: u32) -> u32 {
    (x & 7) | ((y & 7) << 3) | ((z & 7) << 6)
}

/// Local coordinates of a bit index.
#[inline]
pub const fn bit_voxel(bit: u32) -> [u32; 3] {
    [bit & 7, (bit >> 3) & 7, (bit >> 6) & 7]
}

#[inline]
pub fn mask_get(mask: &Mask, bit: u32) -> bool {
    (mask[(bit >> 6) as usize] >> (bit & 63)) & 1 == 1
}

#[inline]
pub fn mask_set(mask: &mut Mask, bit: u32, solid: bool) {
    let word = &mut mask[(bit >> 6) as usize];
    if solid {
        *word |= 1 << (bit & 63);
    } else {
        *word &= !(1 << (bit & 63));
    }
}

/// Number of solid voxels.
#[inline]
pub fn popcount(mask: &Mask) -> u32 {
    mask.iter().map(|w| w.count_ones()).sum()
}

/// [`rank`] and [`popcount`] in one pass over the mask: (solid voxels below `bit`, solid
/// voxels in all).
#[inline]
pub fn rank_and_count(mask: &Mask, bit: u32) -> (u32, u32) {
    let word = (bit >> 6) as usize;
    let counts: [u32; 8] = std::array::from_fn(|i| mask[i].count_ones());
    let below =
        counts[..word].iter().sum::<u32>() + (mask[word] & ((1u64 << (bit & 63)) - 1)).count_ones();
    (below, counts.iter().sum())
}

/// Number of solid voxels with a bit index below `bit`: the colour slot of voxel `bit`.
#[inline]
pub fn rank(mask: &Mask, bit: u32) -> u32 {
    let word = (bit >> 6) as usize;
    let below: u32 = mask[..word].iter().map(|w| w.count_ones()).sum();
    let partial = mask[word] & ((1u64 << (bit & 63)) - 1);
    below + partial.count_ones()
}

#[inline]
pub fn mask_is_empty(mask: &Mask) -> bool {
    mask.iter().all(|&w| w == 0)
}

/// Calls `f` with each solid bit index in increasing order.
#[inline]
pub fn for_each_bit(mask: &Mask, mut f: impl FnMut(u32)) {
    for (w, &word) in mask.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            let b = bits.trailing_zeros();
            f(((w as u32) << 6) | b);
            bits &= bits - 1;
        }
    }
}

/// One brick in compact form, as it travels on the wire and sits in snapshots.
///
/// `cell` is the brick's coarse-grid coordinate (voxel coordinate / 8). An empty mask never
/// appears: a brick that loses its last voxel is removed, not sent empty.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BrickData {
    pub cell: [u32; 3],
    pub mask: Mask,
    /// Colours of the solid voxels in bit order; `colours.len() == popcount(mask)`.
    pub colours: Vec<Colour>,
}

impl BrickData {
    /// Whether the colour list matches the mask and the brick is not empty.
    pub fn is_consistent(&self) -> bool {
        !mask_is_empty(&self.mask) && self.colours.len() == popcount(&self.mask) as usize
    }

    /// Colour of a voxel given by its bit index, `None` where it is empty.
    pub fn colour_at(&self, bit: u32) -> Option<Colour> {
        mask_get(&self.mask, bit).then(|| self.colours[rank(&self.mask, bit) as usize])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_layout_matches_u32_view() {
        let mut mask = EMPTY_MASK;
        mask_set(&mut mask, voxel_bit(3, 5, 6), true);
        let bit = voxel_bit(3, 5, 6);
        assert_eq!(bit, 3 + 8 * 5 + 64 * 6);
        assert_eq!(bit_voxel(bit), [3, 5, 6]);
        // The GPU reads the mask as sixteen little-endian u32 words.
        let words: Vec<u32> = mask
            .iter()
            .flat_map(|w| [*w as u32, (*w >> 32) as u32])
            .collect();
        assert_eq!((words[(bit / 32) as usize] >> (bit % 32)) & 1, 1);
    }

    #[test]
    fn rank_counts_bits_below() {
        let mut mask = EMPTY_MASK;
        for b in [0, 5, 63, 64, 200, 511] {
            mask_set(&mut mask, b, true);
        }
        assert_eq!(rank(&mask, 0), 0);
        assert_eq!(rank(&mask, 5), 1);
        assert_eq!(rank(&mask, 64), 3);
        assert_eq!(rank(&mask, 511), 5);
        assert_eq!(popcount(&mask), 6);
        let mut seen = vec![];
        for_each_bit(&mask, |b| seen.push(b));
        assert_eq!(seen, vec![0, 5, 63, 64, 200, 511]);
        assert_eq!(rank(&FULL_MASK, 511), 511);
        for b in [0, 5, 6, 63, 64, 65, 200, 511] {
            assert_eq!(rank_and_count(&mask, b), (rank(&mask, b), 6), "bit {b}");
        }
        assert_eq!(rank_and_count(&FULL_MASK, 511), (511, 512));
        assert_eq!(rank_and_count(&EMPTY_MASK, 300), (0, 0));
    }
}
