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
//! a textured import has many. The brick map's colour pool (and so the GPU's), both tracers,
//! the redb store (`store_rows.rs` in the server) and the wire (`wire/blob.rs`) hold these
//! blocks; viewers may hold lossy ones ([`crate::blocks`]).

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
    /// Lossy groups of 16 voxels with `bits`-bit weights (2 or 3), within a stated error
    /// ([`crate::blocks`]).
    Blocks { bits: u32 },
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
            (13 | 14, 0) if entries == 1 => Ok(Coding::Blocks {
                bits: crate::blocks::bits_of_header(bits).unwrap_or(2),
            }),
            _ => Err(PaletteError::Header(header)),
        }
    }

    pub(crate) fn header(self) -> u16 {
        match self {
            Coding::One => 0,
            Coding::Palette { bits, entries } => bits as u16 | ((entries as u16 - 1) << 4),
            Coding::Raw => RAW,
            Coding::Blocks { bits } => crate::blocks::header(bits),
        }
    }

    /// Bytes of a block of `voxels` colours in this coding.
    pub fn bytes(self, voxels: usize) -> usize {
        2 * self.words(voxels)
    }

    /// 16-bit words of a block of `voxels` colours in this coding.
    pub fn words(self, voxels: usize) -> usize {
        match self {
            Coding::One => 2,
            Coding::Palette { bits, entries } => {
                1 + entries + (voxels * bits as usize).div_ceil(16)
            }
            Coding::Raw => 1 + voxels,
            Coding::Blocks { bits } => crate::blocks::words(bits, voxels),
        }
    }
}

/// The smallest coding of `colours`, and the palette (ascending, distinct) it would use.
pub fn choose(colours: &[Colour]) -> (Coding, Vec<Colour>) {
    let distinct = distinct(colours);
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

/// The distinct colours, ascending. Bricks mostly hold a few colours in runs: those are found
/// by a scan; only a brick of more than 16 sorts a copy.
fn distinct(colours: &[Colour]) -> Vec<Colour> {
    let mut few: Vec<Colour> = Vec::with_capacity(16);
    let mut last = None;
    for &c in colours {
        if last == Some(c) {
            continue;
        }
        last = Some(c);
        if !few.contains(&c) {
            if few.len() == 16 {
                let mut all = colours.to_vec();
                all.sort_unstable();
                all.dedup();
                return all;
            }
            few.push(c);
        }
    }
    few.sort_unstable();
    few
}

/// Appends the block of `colours` (one per solid voxel, in bit order) to `out`.
pub fn encode(colours: &[Colour], out: &mut Vec<u8>) {
    let (coding, palette) = choose(colours);
    let mut words = vec![0u16; coding.words(colours.len())];
    encode_words(colours, coding, &palette, &mut words);
    out.extend(words.iter().flat_map(|w| w.to_le_bytes()));
}

/// Writes the block of `colours` in `coding` with `palette` (both from [`choose`]) to
/// `out[..coding.words(colours.len())]`: the brick map's colour pool is such blocks. Exact
/// codings only: [`crate::blocks::encode`] writes lossy ones.
pub fn encode_words(colours: &[Colour], coding: Coding, palette: &[Colour], out: &mut [u16]) {
    out[0] = coding.header();
    match coding {
        Coding::Blocks { .. } => unreachable!("choose picks exact codings only"),
        Coding::One => out[1] = palette[0].0,
        Coding::Raw => {
            for (o, c) in out[1..=colours.len()].iter_mut().zip(colours) {
                *o = c.0;
            }
        }
        Coding::Palette { bits, entries } => {
            for (o, c) in out[1..=entries].iter_mut().zip(palette) {
                *o = c.0;
            }
            let packed = &mut out[1 + entries..coding.words(colours.len())];
            packed.fill(0);
            let mut last = (palette[0], 0u16);
            for (i, &c) in colours.iter().enumerate() {
                if c != last.0 {
                    let index = palette
                        .binary_search(&c)
                        .expect("every colour is in its palette");
                    last = (c, index as u16);
                }
                let at = i * bits as usize;
                packed[at / 16] |= last.1 << (at % 16);
            }
        }
    }
}

fn short(need_words: usize, have_words: usize) -> PaletteError {
    PaletteError::Short {
        need: 2 * need_words,
        have: 2 * have_words,
    }
}

/// Little-endian bytes as 16-bit words (a trailing odd byte is dropped).
pub fn words_of(bytes: &[u8]) -> Vec<u16> {
    bytes
        .chunks_exact(2)
        .map(|w| u16::from_le_bytes([w[0], w[1]]))
        .collect()
}

/// The coding of the block at the start of `bytes` (its header, checked).
pub fn coding(bytes: &[u8]) -> Result<Coding, PaletteError> {
    match bytes.get(..2) {
        Some(w) => Coding::of_header(u16::from_le_bytes([w[0], w[1]])),
        None => Err(PaletteError::Short {
            need: 2,
            have: bytes.len(),
        }),
    }
}

/// The coding of the block at the start of `words` (its header, checked).
pub fn coding_of_words(words: &[u16]) -> Result<Coding, PaletteError> {
    Coding::of_header(*words.first().ok_or(short(1, 0))?)
}

/// Decodes the block of `voxels` colours at the start of `bytes` into `out` (cleared first);
/// returns the bytes it took. Every index is checked against its palette, and a palette must
/// be ascending and distinct (as [`encode`] writes it), so a block decodes one way only.
pub fn decode(bytes: &[u8], voxels: usize, out: &mut Vec<Colour>) -> Result<usize, PaletteError> {
    // Only the block's own words: a reader of a longer record must not pay for the rest.
    let len = coding(bytes)?.bytes(voxels).min(bytes.len() & !1);
    out.clear();
    out.resize(voxels, Colour::BLACK);
    let result = decode_words(&words_of(&bytes[..len]), out);
    if result.is_err() {
        out.clear();
    }
    result.map(|words| 2 * words)
}

/// Decodes the block of `out.len()` colours at the start of `words` into `out`; returns the
/// words it took. Checked as [`decode`] checks.
pub fn decode_words(words: &[u16], out: &mut [Colour]) -> Result<usize, PaletteError> {
    let voxels = out.len();
    let coding = coding_of_words(words)?;
    let len = coding.words(voxels);
    if words.len() < len {
        return Err(short(len, words.len()));
    }
    match coding {
        Coding::Blocks { bits } => {
            for (rank, o) in out.iter_mut().enumerate() {
                *o = crate::blocks::colour_at(&words[1..len], bits, rank).unwrap_or(Colour::BLACK);
            }
        }
        Coding::One => out.fill(Colour(words[1])),
        Coding::Raw => {
            for (o, &w) in out.iter_mut().zip(&words[1..len]) {
                *o = Colour(w);
            }
        }
        Coding::Palette { bits, entries } => {
            let palette = &words[1..=entries];
            if palette.windows(2).any(|w| w[0] >= w[1]) {
                return Err(PaletteError::Unsorted { entries });
            }
            let packed = &words[1 + entries..len];
            let mask = (1u16 << bits) - 1;
            for (i, o) in out.iter_mut().enumerate() {
                let at = i * bits as usize;
                let index = usize::from((packed[at / 16] >> (at % 16)) & mask);
                *o = Colour(
                    *palette
                        .get(index)
                        .ok_or(PaletteError::Index { index, entries })?,
                );
            }
        }
    }
    Ok(len)
}

/// The colour of the voxel of rank `rank` in the block at the start of `bytes`, without
/// decoding the rest (what a shader does); `None` where the block does not hold it.
pub fn colour_at(bytes: &[u8], rank: usize) -> Option<Colour> {
    colour_at_words(&words_of(bytes), rank)
}

/// [`colour_at`] over 16-bit words: the CPU tracer's read of the colour pool, the same steps
/// as `brick_colour` in `shaders/trace.wgsl`.
pub fn colour_at_words(words: &[u16], rank: usize) -> Option<Colour> {
    Coding::of_header(*words.first()?)
        .ok()?
        .colour_at(words, rank)
}

impl Coding {
    /// The colour of the voxel of rank `rank` in `words`, a block coded this way (its header
    /// read already); `None` where the block is cut short or an index is past its palette.
    #[inline]
    pub fn colour_at(self, words: &[u16], rank: usize) -> Option<Colour> {
        let w = match self {
            Coding::Blocks { bits } => {
                return crate::blocks::colour_at(words.get(1..)?, bits, rank);
            }
            Coding::One => words.get(1),
            Coding::Raw => words.get(1 + rank),
            Coding::Palette { bits, entries } => {
                let at = rank * bits as usize;
                let index = (words.get(1 + entries + at / 16)? >> (at % 16)) & ((1 << bits) - 1);
                if usize::from(index) >= entries {
                    return None;
                }
                words.get(1 + usize::from(index))
            }
        };
        w.copied().map(Colour)
    }
}

/// Codes `colours` in bounded-error blocks into `out` (cleared first) where that is smaller
/// than their exact coding `exact` and every voxel stays within `bound`: 2-bit weights if they
/// hold the bound and a mean squared error per channel of at most
/// [`crate::blocks::MEAN_SQUARED_2BIT`], else 3-bit ones. Returns the weights' width and what was lost; `None` (and
/// `out` empty): keep the exact coding.
pub fn lossy(
    colours: &[Colour],
    exact: Coding,
    bound: u32,
    out: &mut Vec<u16>,
) -> Option<(u32, crate::blocks::Loss)> {
    out.clear();
    let n = colours.len();
    [2, 3]
        .into_iter()
        .filter(|&bits| Coding::Blocks { bits }.words(n) < exact.words(n))
        .find_map(|bits| {
            // Four levels that hold the bound only loosely give way to eight.
            let max_squared = match bits {
                2 => crate::blocks::MEAN_SQUARED_2BIT * 3 * n as u64,
                _ => u64::MAX,
            };
            crate::blocks::encode(colours, bits, bound, max_squared, out).map(|l| (bits, l))
        })
}

/// [`lossy`] for many bricks (each its colours and its exact coding) on up to `threads`
/// threads: each brick's lossy block, or an empty block where its exact coding stays. A
/// viewer syncing a textured scene codes hundreds of thousands of bricks this way (about 9 µs
/// each on one core). Where threads cannot start (the browser) the work is done on this one.
pub fn lossy_many(bricks: &[(&[Colour], Coding)], bound: u32, threads: usize) -> Vec<Vec<u16>> {
    let code = |part: &[(&[Colour], Coding)]| -> Vec<Vec<u16>> {
        part.iter()
            .map(|&(colours, exact)| {
                let mut out = Vec::new();
                lossy(colours, exact, bound, &mut out);
                out
            })
            .collect()
    };
    let voxels: usize = bricks.iter().map(|(c, _)| c.len()).sum();
    // Below ~64 full bricks a thread costs more than it saves.
    let threads = threads.clamp(1, 16).min(voxels / (64 * 512) + 1);
    if threads == 1 {
        return code(bricks);
    }
    let per = bricks.len().div_ceil(threads);
    std::thread::scope(|scope| {
        let parts: Vec<_> = bricks
            .chunks(per)
            .map(|part| {
                let handle = std::thread::Builder::new()
                    .name("lossy".into())
                    .spawn_scoped(scope, move || code(part));
                (part, handle)
            })
            .collect();
        parts
            .into_iter()
            .flat_map(|(part, handle)| match handle.map(|h| h.join()) {
                Ok(Ok(blocks)) => blocks,
                // No thread (or it died): code this part here.
                _ => code(part),
            })
            .collect()
    })
}

/// The order-0 entropy of `colours` in bits, all of them together: Σ −log2(count/n) over the
/// voxels, `n` times the entropy of the brick's colour histogram. `scratch` is reused.
pub fn entropy_bits(colours: &[Colour], scratch: &mut Vec<u16>) -> f64 {
    let n = colours.len() as f64;
    scratch.clear();
    scratch.extend(colours.iter().map(|c| c.0));
    scratch.sort_unstable();
    scratch
        .chunk_by(|a, b| a == b)
        .map(|run| {
            let k = run.len() as f64;
            k * (n / k).log2()
        })
        .sum()
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
    /// Bricks in bounded-error blocks of 2- and 3-bit weights ([`crate::blocks`]).
    pub blocks: [u64; 2],
    /// Bytes of every brick's block (headers and palettes included).
    pub bytes: u64,
    /// Bits per solid voxel the colours take coded.
    pub bits_per_voxel: f64,
    /// The order-0 entropy of each brick's exact colours, in bits per solid voxel over the
    /// scene: what any code of a brick that spends a fixed number of bits on each of its
    /// colours (a palette, whatever its indices) cannot go below, before the palette itself is
    /// paid for (of the exact colours, also in a bounded mix). `None` where the mix was counted
    /// without the colours (`add_coded` alone).
    pub entropy_bits_per_voxel: Option<f64>,
    /// The bound blocks were allowed (largest error per channel, 0–255 scale); `None`: exact.
    pub bound: Option<u32>,
    /// The largest error of any voxel per channel (0–255 scale), against the exact colours.
    pub worst_error: u32,
    /// Sum of squared channel errors over every solid voxel (0–255 scale).
    pub squared_error: u64,
    /// Peak signal-to-noise ratio of every solid voxel's colour against the exact colours
    /// (channels on the 0–255 scale); `None` when nothing was lost.
    pub psnr_db: Option<f64>,
}

impl Mix {
    /// How `map`'s bricks are coded in its colour pool.
    pub fn of(map: &crate::BrickMap) -> Mix {
        let mut mix = Mix::default();
        for (coding, voxels) in map.codings() {
            mix.add_coded(coding, voxels);
        }
        let mut scratch = Vec::new();
        let bits: f64 = map
            .bricks()
            .map(|(brick, _)| entropy_bits(&brick.colours, &mut scratch))
            .sum();
        mix.entropy_bits_per_voxel = Some(if mix.voxels == 0 {
            0.0
        } else {
            bits / mix.voxels as f64
        });
        mix
    }

    /// How `map`'s bricks would be coded in a map whose bricks may be lossy within `bound`
    /// ([`crate::BrickMap::set_colour_bound`]), and what that loses against their exact colours.
    pub fn bounded(map: &crate::BrickMap, bound: u32) -> Mix {
        let mut mix = Mix {
            bound: Some(bound),
            ..Mix::default()
        };
        let (mut scratch, mut sorted, mut entropy) = (Vec::new(), Vec::new(), 0.0);
        for (brick, _) in map.bricks() {
            let (coding, _) = choose(&brick.colours);
            let n = brick.colours.len();
            entropy += entropy_bits(&brick.colours, &mut sorted);
            match lossy(&brick.colours, coding, bound, &mut scratch) {
                Some((bits, loss)) => {
                    mix.worst_error = mix.worst_error.max(loss.worst);
                    mix.squared_error += loss.squared;
                    mix.add_coded(Coding::Blocks { bits }, n);
                }
                None => mix.add_coded(coding, n),
            }
        }
        mix.entropy_bits_per_voxel = Some(if mix.voxels == 0 {
            0.0
        } else {
            entropy / mix.voxels as f64
        });
        mix.psnr_db = (mix.squared_error > 0).then(|| {
            let mse = mix.squared_error as f64 / (3.0 * mix.voxels as f64);
            10.0 * (255.0f64 * 255.0 / mse).log10()
        });
        mix
    }

    /// One brick's colours, coded exactly.
    pub fn add(&mut self, colours: &[Colour]) {
        self.add_coded(choose(colours).0, colours.len());
    }

    /// One brick of `voxels` colours in `coding`.
    pub fn add_coded(&mut self, coding: Coding, voxels: usize) {
        match coding {
            Coding::One => self.one += 1,
            Coding::Palette { bits, .. } => self.palette[bits.trailing_zeros() as usize] += 1,
            Coding::Raw => self.raw += 1,
            Coding::Blocks { bits } => self.blocks[bits as usize - 2] += 1,
        }
        self.bricks += 1;
        self.voxels += voxels as u64;
        self.bytes += coding.bytes(voxels) as u64;
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

    #[test]
    fn entropy_counts_bits_of_each_colours_share() {
        let mut scratch = Vec::new();
        let c = |v: u16| Colour(v);
        assert_eq!(entropy_bits(&[], &mut scratch), 0.0);
        assert_eq!(entropy_bits(&[c(7); 9], &mut scratch), 0.0);
        // Two colours half each: one bit a voxel.
        assert_eq!(entropy_bits(&[c(1), c(2), c(2), c(1)], &mut scratch), 4.0);
        // Eight colours, equally often: three bits a voxel, in any order.
        let eight: Vec<Colour> = (0..64).map(|i| c((i * 5 % 8) as u16)).collect();
        assert!((entropy_bits(&eight, &mut scratch) - 192.0).abs() < 1e-9);
        // 3:1 — 0.811 bits a voxel.
        let skew = [c(1), c(1), c(1), c(2)];
        let h = -(0.75f64 * 0.75f64.log2() + 0.25 * 0.25f64.log2());
        assert!((entropy_bits(&skew, &mut scratch) - 4.0 * h).abs() < 1e-9);
    }

    #[test]
    fn lossy_many_codes_as_one_brick_at_a_time_does() {
        // 300 bricks of textured shades: enough for several threads.
        let mut seed = 11u32;
        let bricks: Vec<Vec<Colour>> = (0..300)
            .map(|i| {
                (0..512)
                    .map(|_| {
                        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                        let k = (seed >> 24) as u8 % (1 + i as u8 % 64);
                        Colour::from_rgb8(90 + k, 70 + k / 2, 50 + k / 3)
                    })
                    .collect()
            })
            .collect();
        let exact: Vec<_> = bricks.iter().map(|c| (c.as_slice(), choose(c).0)).collect();
        let one_by_one: Vec<Vec<u16>> = exact
            .iter()
            .map(|&(c, coding)| {
                let mut out = Vec::new();
                lossy(c, coding, crate::blocks::DEFAULT_BOUND, &mut out);
                out
            })
            .collect();
        assert!(one_by_one.iter().any(|b| b.is_empty()));
        assert!(one_by_one.iter().any(|b| !b.is_empty()));
        for threads in [1, 3, 8] {
            assert_eq!(
                lossy_many(&exact, crate::blocks::DEFAULT_BOUND, threads),
                one_by_one,
                "{threads} threads"
            );
        }
    }

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
