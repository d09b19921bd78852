//! How the redb store lays out a brick row, and which layouts a store file may hold.
//!
//! A row is 64 mask bytes then either every solid voxel's colour (RGB565, little-endian: `64 +
//! 2n` bytes, always an even length) or, when all of a brick's colours are the same and it has
//! more than one solid voxel, that colour once and a [`UNIFORM`] tag (67 bytes, the only odd
//! length). A brush or a box fills bricks with one colour, so most edited bricks are uniform:
//! their rows are 16× smaller, and a snapshot of 65,536 such bricks (two 256³ boxes) writes
//! 4.4 MB instead of 71 MB in the owner's turn.
//!
//! The store records the newest row layout it may hold ([`FORMAT`]); a store written by a
//! newer build is refused by name instead of failing on its first unknown row. Stores from
//! before the record (raw rows only) load as they are.

use brickcast_protocol::Colour;
use brickcast_protocol::brick::{BrickData, Mask};

use crate::store::{decode_brick, encode_brick};

/// The store format this build writes and the newest it reads: 1 had raw rows only (and no
/// record of its format); 2 adds uniform rows.
pub const FORMAT: u32 = 2;

/// The last byte of a uniform row.
const UNIFORM: u8 = 1;
/// A uniform row's length: mask, colour, tag.
const UNIFORM_LEN: usize = 64 + 2 + 1;

/// One brick's row: uniform when it can be, raw otherwise.
pub fn encode_row(mask: &Mask, colours: &[Colour], out: &mut Vec<u8>) {
    match colours.split_first() {
        Some((first, rest)) if !rest.is_empty() && rest.iter().all(|c| c == first) => {
            // A raw row of one voxel's colour, then the tag.
            encode_brick(mask, std::slice::from_ref(first), out);
            out.push(UNIFORM);
        }
        _ => encode_brick(mask, colours, out),
    }
}

/// A row back as a brick; `None` when it is neither layout or its colours do not fit its mask.
pub fn decode_row(cell: [u32; 3], bytes: &[u8]) -> Option<BrickData> {
    if bytes.len() == UNIFORM_LEN {
        if bytes[UNIFORM_LEN - 1] != UNIFORM {
            return None;
        }
        let mut brick = decode_brick(cell, &bytes[..UNIFORM_LEN - 1])?;
        let solid = solid(&brick.mask);
        if solid < 2 {
            return None;
        }
        brick.colours = vec![brick.colours[0]; solid];
        return Some(brick);
    }
    let brick = decode_brick(cell, bytes)?;
    (brick.colours.len() == solid(&brick.mask)).then_some(brick)
}

fn solid(mask: &Mask) -> usize {
    mask.iter().map(|w| w.count_ones() as usize).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brick(solid: usize, colour: impl Fn(usize) -> u16) -> (Mask, Vec<Colour>) {
        let mut mask = [0u64; 8];
        for i in 0..solid {
            mask[i / 64] |= 1 << (i % 64);
        }
        (mask, (0..solid).map(|i| Colour(colour(i))).collect())
    }

    #[test]
    fn one_colour_bricks_take_a_uniform_row_and_come_back_whole() {
        let mut row = Vec::new();
        for (solid, uniform) in [(512, true), (2, true), (1, false), (0, false)] {
            let (mask, colours) = brick(solid, |_| 0xbeef);
            encode_row(&mask, &colours, &mut row);
            assert_eq!(row.len() == UNIFORM_LEN, uniform, "{solid} solid voxels");
            let back = decode_row([1, 2, 3], &row).unwrap();
            assert_eq!(
                (back.cell, back.mask, back.colours),
                ([1, 2, 3], mask, colours)
            );
        }
        // Two colours: raw, and still exact.
        let (mask, colours) = brick(512, |i| (i % 2) as u16);
        encode_row(&mask, &colours, &mut row);
        assert_eq!(row.len(), 64 + 1024);
        assert_eq!(decode_row([0; 3], &row).unwrap().colours, colours);
    }

    #[test]
    fn rows_that_fit_no_layout_are_refused() {
        let (mask, colours) = brick(512, |_| 7);
        let mut row = Vec::new();
        encode_row(&mask, &colours, &mut row);
        let mut tagged = row.clone();
        tagged[UNIFORM_LEN - 1] = 2;
        assert!(decode_row([0; 3], &tagged).is_none(), "unknown tag");
        // A uniform row whose mask holds fewer than two voxels is never written.
        let mut thin = row.clone();
        thin[..64].fill(0);
        thin[0] = 1;
        assert!(decode_row([0; 3], &thin).is_none());
        assert!(decode_row([0; 3], &row[..66]).is_none(), "cut short");
        assert!(decode_row([0; 3], &[0; 65]).is_none(), "odd raw row");
    }
}
