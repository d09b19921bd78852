//! A brick's colours in fewer bits (issue #29, first step): one colour, a palette of up to 256
//! entries with 1-, 2-, 4- or 8-bit indices, or raw RGB565 — whichever is smallest, chosen per
//! brick when it is written. Lossless: a brick decodes to exactly the colours it was encoded
//! from.
//!
//! The colours are a brick's, one per solid voxel in bit order ([`crate::brick`]); the mask
//! says how many. A block is little-endian 16-bit words, so a reader of 32-bit words (a GPU
//! shader) can find any voxel's colour from its rank without decoding the rest:
//!
//! * word 0, the header: bits 0–3 the index width — 0 for one colour, 1, 2, 4 or 8 for a
//!   palette, 15 for raw — and for a palette, bits 4–11 its entries less one; other bits 0.
//! * one colour: the header, the colour (4 bytes for any number of voxels).
//! * palette: the header, the entries (ascending), then each voxel's index in rank order,
//!   packed from the low bits of each word up (a width divides 16, so none straddles words).
//! * raw: the header, every voxel's colour.
//!
//! A brush or a box paints a brick one colour; the demo's terrain has a few shades per brick;
//! a textured import has many. The redb store writes its bricks this way (`store_rows.rs` in
//! the server); the wire, the GPU pools and the tracers are the next steps of #29.

use crate::colour::Colour;

/// The header's index width for raw colours.
const RAW: u16 = 15;

/// Why a colour block does not decode.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PaletteError {
    #[error("a colour block is cut short: {need} bytes needed, {have} there")]
    Short { need: usize, have: usize },
    #[error("colour block header {0:#06x} names no encoding")]
    Header(u16),
    #[error("a palette index {index} is past its {entries} entries")]
    Index { index: usize, entries: usize },
    #[error("a palette of {entries} entries is not sorted and distinct")]
    Unsorted { entries: usize },
}

/// How a block encodes its colours.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coding {
    /// One colour for every voxel.
    One,
    /// `entries` distinct colours, each voxel an index of `bits` bits.
    Palette { bits: u32, entries: usize },
    /// Every voxel's colour.
    Raw,
}

impl Coding {
    fn of_header(header: u16) -> Result<Coding, PaletteError> {
        let bits = header & 0xf;
        let entries = usize::from((header >> 4) & 0xff) + 1;
        match (bits, header >> 12) {
            (0, 0) if entries == 1 => Ok(Coding::One),
            (1 | 2 | 4 | 8, 0) if entries <= 1 << bits && entries >= 2 => Ok(Coding::Palette {
                bits: u32::from(bits),
                entries,
            }),
            (RAW, 0) if entries == 1 => Ok(Coding::Raw),
            _ => Err(PaletteError::Header(header)),
        }
    }

    fn header(self) -> u16 {
        match self {
            Coding::One => 0,
            Coding::Palette { bits, entries } => bits as u16 | ((entries as u16 - 1) << 4),
            Coding::Raw => RAW,
        }
    }

    /// Bytes of a block of `voxels` colours in this coding.
    pub fn bytes(self, voxels: usize) -> usize {
        2 * match self {
            Coding::One => 2,
            Coding::Palette { bits, entries } => {
                1 + entries + (voxels * bits as usize).div_ceil(16)
            }
            Coding::Raw => 1 + voxels,
        }
    }
}

/// The smallest coding of `colours`, and the palette (ascending, distinct) it would use.
pub fn choose(colours: &[Colour]) -> (Coding, Vec<Colour>) {
    let mut distinct: Vec<Colour> = colours.to_vec();
    distinct.sort_unstable_by_key(|c| c.0);
    distinct.dedup();
    let coding = match distinct.len() {
        0 => Coding::Raw,
        1 => Coding::One,
        k if k <= 256 => {
            let bits = [1, 2, 4, 8]
                .into_iter()
                .find(|b| k <= 1 << b)
                .expect("256 entries fit 8 bits");
            let palette = Coding::Palette { bits, entries: k };
            if palette.bytes(colours.len()) < Coding::Raw.bytes(colours.len()) {
                palette
            } else {
                Coding::Raw
            }
        }
        _ => Coding::Raw,
    };
    (coding, distinct)
}

/// Appends the block of `colours` (one per solid voxel, in bit order) to `out`.
pub fn encode(colours: &[Colour], out: &mut Vec<u8>) {
    let (coding, palette) = choose(colours);
    let word = |out: &mut Vec<u8>, w: u16| out.extend_from_slice(&w.to_le_bytes());
    word(out, coding.header());
    match coding {
        Coding::One => word(out, palette[0].0),
        Coding::Raw => colours.iter().for_each(|c| word(out, c.0)),
        Coding::Palette { bits, .. } => {
            palette.iter().for_each(|c| word(out, c.0));
            let mut packed = vec![0u16; (colours.len() * bits as usize).div_ceil(16)];
            for (i, c) in colours.iter().enumerate() {
                let index = palette
                    .binary_search_by_key(&c.0, |p| p.0)
                    .expect("every colour is in its palette") as u16;
                let at = i * bits as usize;
                packed[at / 16] |= index << (at % 16);
            }
            packed.iter().for_each(|&w| word(out, w));
        }
    }
}

fn word(bytes: &[u8], at: usize) -> Result<u16, PaletteError> {
    match bytes.get(2 * at..2 * at + 2) {
        Some(w) => Ok(u16::from_le_bytes([w[0], w[1]])),
        None => Err(PaletteError::Short {
            need: 2 * at + 2,
            have: bytes.len(),
        }),
    }
}

/// The coding of the block at the start of `bytes` (its header, checked).
pub fn coding(bytes: &[u8]) -> Result<Coding, PaletteError> {
    Coding::of_header(word(bytes, 0)?)
}

/// Decodes the block of `voxels` colours at the start of `bytes` into `out` (cleared first);
/// returns the bytes it took. Every index is checked against its palette, and a palette must
/// be ascending and distinct (as [`encode`] writes it), so a block decodes one way only.
pub fn decode(bytes: &[u8], voxels: usize, out: &mut Vec<Colour>) -> Result<usize, PaletteError> {
    let coding = coding(bytes)?;
    let len = coding.bytes(voxels);
    if bytes.len() < len {
        return Err(PaletteError::Short {
            need: len,
            have: bytes.len(),
        });
    }
    out.clear();
    match coding {
        Coding::One => out.resize(voxels, Colour(word(bytes, 1)?)),
        Coding::Raw => {
            for i in 0..voxels {
                out.push(Colour(word(bytes, 1 + i)?));
            }
        }
        Coding::Palette { bits, entries } => {
            let palette = (0..entries)
                .map(|i| word(bytes, 1 + i))
                .collect::<Result<Vec<u16>, _>>()?;
            if palette.windows(2).any(|w| w[0] >= w[1]) {
                return Err(PaletteError::Unsorted { entries });
            }
            let mask = (1u16 << bits) - 1;
            for i in 0..voxels {
                let at = i * bits as usize;
                let index = usize::from((word(bytes, 1 + entries + at / 16)? >> (at % 16)) & mask);
                let colour = palette
                    .get(index)
                    .ok_or(PaletteError::Index { index, entries })?;
                out.push(Colour(*colour));
            }
        }
    }
    Ok(len)
}

/// The colour of the voxel of rank `rank` in the block at the start of `bytes`, without
/// decoding the rest (what a shader does); `None` where the block does not hold it.
pub fn colour_at(bytes: &[u8], rank: usize) -> Option<Colour> {
    let header = word(bytes, 0).ok()?;
    let w = match Coding::of_header(header).ok()? {
        Coding::One => word(bytes, 1),
        Coding::Raw => word(bytes, 1 + rank),
        Coding::Palette { bits, entries } => {
            let at = rank * bits as usize;
            let index = (word(bytes, 1 + entries + at / 16).ok()? >> (at % 16)) & ((1 << bits) - 1);
            if usize::from(index) >= entries {
                return None;
            }
            word(bytes, 1 + usize::from(index))
        }
    };
    w.ok().map(Colour)
}

/// How a scene's bricks would be coded: counts per coding and the bytes of their blocks
/// (`brickcast-server stats`).
#[derive(Debug, Default, Clone, PartialEq, serde::Serialize)]
pub struct Mix {
    pub bricks: u64,
    pub voxels: u64,
    /// Bricks of one colour.
    pub one: u64,
    /// Bricks with a palette of 1-, 2-, 4- and 8-bit indices.
    pub palette: [u64; 4],
    pub raw: u64,
    /// Bytes of every brick's block (headers and palettes included).
    pub bytes: u64,
    /// Bits per solid voxel the colours take coded.
    pub bits_per_voxel: f64,
}

impl Mix {
    /// Every brick of `map`.
    pub fn of(map: &crate::BrickMap) -> Mix {
        let mut mix = Mix::default();
        for (brick, _) in map.bricks() {
            mix.add(&brick.colours);
        }
        mix
    }

    /// One brick's colours.
    pub fn add(&mut self, colours: &[Colour]) {
        let (coding, _) = choose(colours);
        match coding {
            Coding::One => self.one += 1,
            Coding::Palette { bits, .. } => self.palette[bits.trailing_zeros() as usize] += 1,
            Coding::Raw => self.raw += 1,
        }
        self.bricks += 1;
        self.voxels += colours.len() as u64;
        self.bytes += coding.bytes(colours.len()) as u64;
        self.bits_per_voxel = if self.voxels == 0 {
            0.0
        } else {
            8.0 * self.bytes as f64 / self.voxels as f64
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn round_trip(colours: &[Colour]) -> (Coding, usize) {
        let mut block = Vec::new();
        encode(colours, &mut block);
        let (coding, _) = choose(colours);
        assert_eq!(block.len(), coding.bytes(colours.len()));
        let mut back = Vec::new();
        assert_eq!(decode(&block, colours.len(), &mut back), Ok(block.len()));
        assert_eq!(back, colours);
        for (rank, c) in colours.iter().enumerate() {
            assert_eq!(colour_at(&block, rank), Some(*c), "rank {rank}");
        }
        (coding, block.len())
    }

    #[test]
    fn each_brick_takes_its_smallest_coding() {
        let c = Colour;
        // A full brick of one colour: 4 bytes, not 1,024.
        assert_eq!(round_trip(&[c(7); 512]), (Coding::One, 4));
        // Two colours in a full brick: one bit each.
        let two: Vec<Colour> = (0..512)
            .map(|i| c(if i % 3 == 0 { 9 } else { 4 }))
            .collect();
        assert_eq!(
            round_trip(&two),
            (
                Coding::Palette {
                    bits: 1,
                    entries: 2
                },
                2 + 4 + 64
            )
        );
        // Sixteen shades: four bits.
        let shades: Vec<Colour> = (0..300).map(|i| c((i * 7 % 16) as u16 * 100)).collect();
        assert_eq!(
            round_trip(&shades).0,
            Coding::Palette {
                bits: 4,
                entries: 16
            }
        );
        // 257 colours, or a few voxels of distinct colours: raw is smaller.
        let many: Vec<Colour> = (0..512).map(|i| c((i % 257) as u16)).collect();
        assert_eq!(round_trip(&many).0, Coding::Raw);
        assert_eq!(round_trip(&[c(1), c(2), c(3)]).0, Coding::Raw);
        assert_eq!(round_trip(&[c(1)]), (Coding::One, 4));
        assert_eq!(round_trip(&[]).0, Coding::Raw);
    }

    #[test]
    fn broken_blocks_are_errors_not_colours() {
        let mut block = Vec::new();
        let two: Vec<Colour> = (0..100).map(|i| Colour(i % 2)).collect();
        encode(&two, &mut block);
        let mut out = Vec::new();
        assert!(matches!(
            decode(&block[..block.len() - 1], 100, &mut out),
            Err(PaletteError::Short { .. })
        ));
        assert!(matches!(
            decode(&[], 1, &mut out),
            Err(PaletteError::Short { .. })
        ));
        // Unknown widths, stray header bits, a palette too large for its width.
        for header in [3u16, 0x1000, 0x0021, 0x0010] {
            let mut bad = block.clone();
            bad[..2].copy_from_slice(&header.to_le_bytes());
            assert_eq!(
                decode(&bad, 100, &mut out),
                Err(PaletteError::Header(header)),
                "{header:#x}"
            );
        }
        // A palette out of order.
        let mut swapped = block.clone();
        swapped[2..6].copy_from_slice(&[1, 0, 0, 0]);
        assert_eq!(
            decode(&swapped, 100, &mut out),
            Err(PaletteError::Unsorted { entries: 2 })
        );
        // An index past a palette of three (two bits wide).
        let three: Vec<Colour> = (0..20).map(|i| Colour(i % 3)).collect();
        let mut block = Vec::new();
        encode(&three, &mut block);
        // Voxel 19's index: bits 38-39 of the indices, after the header and three entries.
        block[2 * (1 + 3) + 38 / 8] |= 0b11 << (38 % 8);
        assert!(matches!(
            decode(&block, 20, &mut out),
            Err(PaletteError::Index {
                index: 3,
                entries: 3
            })
        ));
        assert_eq!(colour_at(&block, 19), None);
    }

    #[test]
    fn a_mix_counts_each_coding_and_its_bytes() {
        let mut mix = Mix::default();
        mix.add(&[Colour(1); 512]);
        mix.add(&(0..512).map(|i| Colour(i % 4)).collect::<Vec<_>>());
        mix.add(&[Colour(1), Colour(2)]);
        assert_eq!(
            (mix.bricks, mix.voxels, mix.one, mix.palette, mix.raw),
            (3, 1026, 1, [0, 1, 0, 0], 1)
        );
        assert_eq!(mix.bytes, 4 + (2 + 8 + 128) + 6);
        assert!((mix.bits_per_voxel - 8.0 * 148.0 / 1026.0).abs() < 1e-9);
    }

    proptest! {
        #[test]
        fn any_colours_come_back_exactly(
            palette in proptest::collection::vec(any::<u16>(), 1..300),
            picks in proptest::collection::vec(any::<prop::sample::Index>(), 0..=512),
        ) {
            let colours: Vec<Colour> = picks.iter().map(|i| Colour(*i.get(&palette))).collect();
            let (coding, bytes) = round_trip(&colours);
            // Never larger than raw.
            prop_assert!(bytes <= Coding::Raw.bytes(colours.len()).max(4), "{coding:?}");
        }
    }
}
