//! How the redb store lays out a brick row, and which layouts a store file may hold.
//!
//! A row is 64 mask bytes, then the brick's colours. Stores before format 2 wrote every solid
//! voxel's colour (RGB565, little-endian: `64 + 2n` bytes, always an even length); format 2
//! writes a [`CODED`] tag byte and the colours as a [`brickcast_protocol::palette`] block (one
//! colour, a palette with 1–8-bit indices, or raw, whichever is smallest: `65 + 2w` bytes,
//! always odd), so both read back. A brush or a box fills bricks with one colour: their rows
//! are 69 bytes instead of 1,088, and a snapshot of 65,536 such bricks (two 256³ boxes)
//! writes 4.5 MB instead of 71 MB in the owner's turn.
//!
//! The store records the newest row layout it may hold ([`FORMAT`]); a store written by a
//! newer build is refused by name instead of failing on its first unknown row.

use brickcast_protocol::brick::{BrickData, Mask};
use brickcast_protocol::{Colour, palette};

use crate::store::decode_brick;

/// The store format this build writes and the newest it reads: 1 had raw rows only (and no
/// record of its format); 2 adds palette-coded rows; 3 adds log rows holding a turn's records
/// (`record.rs`) and history steps in packs with an index journal (`store/history_rows.rs`);
/// 4 adds the scene's palette (`palette/<scene>`, written by snapshots) and log records that
/// set a swatch (record version 7); 5 keeps each scene's past (`store/past.rs`: the tables a
/// build reading 4 would leave stale, trimming the log without keeping it) and log records of
/// version 9 (a restore).
pub const FORMAT: u32 = 5;

/// The byte after the mask of a palette-coded row.
const CODED: u8 = 2;

/// One brick's row, its colours palette-coded.
pub fn encode_row(mask: &Mask, colours: &[Colour], out: &mut Vec<u8>) {
    out.clear();
    for word in mask {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.push(CODED);
    palette::encode(colours, out);
}

/// A row back as a brick (either layout); `None` when it is neither, or its colours do not
/// fit its mask.
pub fn decode_row(cell: [u32; 3], bytes: &[u8]) -> Option<BrickData> {
    if bytes.len().is_multiple_of(2) {
        let brick = decode_brick(cell, bytes)?;
        return (brick.colours.len() == solid(&brick.mask)).then_some(brick);
    }
    if bytes.len() < 65 || bytes[64] != CODED {
        return None;
    }
    let mask = row_mask(bytes)?;
    let mut colours = Vec::new();
    let used = palette::decode(&bytes[65..], solid(&mask), &mut colours).ok()?;
    (used == bytes.len() - 65).then_some(BrickData {
        cell,
        mask,
        colours,
    })
}

/// A palette-coded row's mask and colour block, the block written to `words` as the map
/// stores it, so loading a scene need not choose and code every brick's colours again;
/// `None` for an older raw row or a row that is not a brick (read those with [`decode_row`]).
/// The block is not checked here: [`BrickMap::put_coded`](brickcast_protocol::BrickMap::put_coded)
/// takes it only with the colours it decodes to.
pub fn coded_row(bytes: &[u8], words: &mut Vec<u16>) -> Option<Mask> {
    if bytes.len() < 67 || bytes[64] != CODED || bytes.len().is_multiple_of(2) {
        return None;
    }
    let mask = row_mask(bytes)?;
    words.clear();
    words.extend(
        bytes[65..]
            .chunks_exact(2)
            .map(|pair| u16::from_le_bytes([pair[0], pair[1]])),
    );
    Some(mask)
}

/// The mask a row starts with (64 bytes, little-endian words).
fn row_mask(bytes: &[u8]) -> Option<Mask> {
    let mut mask = [0u64; 8];
    for (word, chunk) in mask.iter_mut().zip(bytes.get(..64)?.chunks_exact(8)) {
        *word = u64::from_le_bytes(chunk.try_into().ok()?);
    }
    Some(mask)
}

fn solid(mask: &Mask) -> usize {
    mask.iter().map(|w| w.count_ones() as usize).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::encode_brick;

    fn brick(solid: usize, colour: impl Fn(usize) -> u16) -> (Mask, Vec<Colour>) {
        let mut mask = [0u64; 8];
        for i in 0..solid {
            mask[i / 64] |= 1 << (i % 64);
        }
        (mask, (0..solid).map(|i| Colour(colour(i))).collect())
    }

    #[test]
    fn rows_of_either_format_come_back_whole() {
        let mut row = Vec::new();
        for (solid, colours, len) in [
            (512, 1, 69),
            (512, 2, 65 + 2 + 4 + 64),
            (512, 512, 65 + 2 + 1024),
            (1, 1, 69),
        ] {
            let (mask, colours) = brick(solid, |i| (i % colours) as u16 * 3);
            encode_row(&mask, &colours, &mut row);
            assert_eq!(row.len(), len, "{solid} voxels");
            let back = decode_row([1, 2, 3], &row).unwrap();
            assert_eq!(
                (back.cell, back.mask, back.colours.clone()),
                ([1, 2, 3], mask, colours.clone())
            );
            // Its block as the map stores it: the words the map would code.
            let mut words = Vec::new();
            assert_eq!(coded_row(&row, &mut words), Some(mask));
            let mut map = brickcast_protocol::BrickMap::new([64, 64, 64]).unwrap();
            map.put_brick(&back).unwrap();
            let slot = map.slot_of_cell([1, 2, 3]).unwrap();
            assert_eq!(&map.block(slot)[..words.len()], &words[..]);
            // The row a format-1 store holds.
            encode_brick(&mask, &colours, &mut row);
            assert_eq!(decode_row([1, 2, 3], &row).unwrap().colours, colours);
            assert_eq!(coded_row(&row, &mut words), None, "a raw row is read whole");
        }
    }

    #[test]
    fn rows_that_fit_no_layout_are_refused() {
        let (mask, colours) = brick(512, |i| (i % 2) as u16);
        let mut row = Vec::new();
        encode_row(&mask, &colours, &mut row);
        let mut tagged = row.clone();
        tagged[64] = 1;
        assert!(decode_row([0; 3], &tagged).is_none(), "unknown tag");
        let mut longer = row.clone();
        longer.extend_from_slice(&[0, 0]);
        assert!(
            decode_row([0; 3], &longer).is_none(),
            "bytes after the colours"
        );
        assert!(
            decode_row([0; 3], &row[..row.len() - 2]).is_none(),
            "cut short"
        );
        // A mask of fewer voxels than the block's colours: the raw row is refused.
        encode_brick(&mask, &colours, &mut row);
        row[0] = 0;
        assert!(
            decode_row([0; 3], &row).is_none(),
            "raw colours past the mask"
        );
        assert!(decode_row([0; 3], &[0; 63]).is_none());
    }
}
