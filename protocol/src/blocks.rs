//! Bounded-error colour blocks (issue #29): a brick's colours, in rank order, cut into groups
//! of 16; each group is two RGB565 end points and a 2- or 3-bit weight per voxel that picks
//! one of the 4 or 8 colours on the line between them (BC1's scheme, over the voxels' colour
//! sequence as Dolonius et al. 2017 do). 4 or 5 words per 16 voxels plus the block's header:
//! 4 or 5 bits per voxel for a full group, whatever the brick's colours.
//!
//! Lossy, so used only where asked ([`crate::BrickMap::set_colour_bound`]) and only where every
//! voxel of the brick stays within the bound (per channel, on the 0–255 scale) and the blocks
//! are smaller than the brick's exact coding; other bricks keep their exact coding.
//!
//! Layout after the header ([`crate::palette`], index width 14 for 2-bit weights, 13 for
//! 3-bit): per group, word 0 the end point at weight 0, word 1 the one at the top weight `m`
//! (3 or 7), then the weights, voxel `i` of the group at bit `bits·i` of those words read as
//! one little-endian number (a 3-bit weight may straddle two words). A weight `w` gives, per
//! RGB565 channel, `(a·(m − w) + b·w + m/2) / m` in integers: `shaders/trace.wgsl` computes
//! the same.

use crate::colour::Colour;

/// Voxels per group.
pub const GROUP: usize = 16;

/// Words per group with `bits`-bit weights: two end points and the weights.
pub const fn group_words(bits: u32) -> usize {
    2 + bits as usize
}

/// Words of a block of `voxels` colours with `bits`-bit weights (header included): the last
/// group, when short, has weight words for its own voxels only.
pub const fn words(bits: u32, voxels: usize) -> usize {
    let rest = voxels % GROUP;
    let last = if rest == 0 {
        0
    } else {
        2 + (bits as usize * rest).div_ceil(16)
    };
    1 + group_words(bits) * (voxels / GROUP) + last
}

/// The header of a block with `bits`-bit weights (2 or 3).
pub const fn header(bits: u32) -> u16 {
    16 - bits as u16
}

/// The weight width a header names, if it names blocks.
pub const fn bits_of_header(index_width: u16) -> Option<u32> {
    match index_width {
        14 => Some(2),
        13 => Some(3),
        _ => None,
    }
}

fn channels(c: Colour) -> [u32; 3] {
    [
        u32::from(c.0 >> 11),
        u32::from((c.0 >> 5) & 0x3F),
        u32::from(c.0 & 0x1F),
    ]
}

/// The colour of weight `w` (0 to `top`) between end points `a` and `b`.
pub fn mix(a: u16, b: u16, w: u32, top: u32) -> Colour {
    let (a, b) = (channels(Colour(a)), channels(Colour(b)));
    let c: [u32; 3] = std::array::from_fn(|i| (a[i] * (top - w) + b[i] * w + top / 2) / top);
    Colour(((c[0] << 11) | (c[1] << 5) | c[2]) as u16)
}

/// The largest per-channel difference between two colours on the 0–255 scale.
pub fn error(a: Colour, b: Colour) -> u32 {
    let (a, b) = (a.to_rgb8(), b.to_rgb8());
    (0..3)
        .map(|i| a[i].abs_diff(b[i]) as u32)
        .max()
        .unwrap_or(0)
}

/// A group's colours on the 0–255 scale.
type Rgb = [[i32; 3]; GROUP];

fn rgb_of(group: &[Colour]) -> Rgb {
    let mut rgb = [[0; 3]; GROUP];
    for (o, c) in rgb.iter_mut().zip(group) {
        *o = c.to_rgb8().map(i32::from);
    }
    rgb
}

/// Per voxel the weight of the nearest of the `top + 1` colours from `a` to `b` (squared error
/// on the 0–255 scale; the candidates are the two levels around the voxel's projection on the
/// line and their neighbours). Returns the worst channel error and the sum of squared errors.
fn fit(rgb: &[[i32; 3]], a: Colour, b: Colour, top: u32, weights: &mut [u32; GROUP]) -> (u32, u64) {
    let mut levels = [[0i32; 3]; 8];
    for (w, l) in levels.iter_mut().enumerate().take(top as usize + 1) {
        *l = mix(a.0, b.0, w as u32, top).to_rgb8().map(i32::from);
    }
    let (la, lb) = (levels[0], levels[top as usize]);
    let axis: [i32; 3] = std::array::from_fn(|k| lb[k] - la[k]);
    let length2 = axis.iter().map(|v| v * v).sum::<i32>().max(1);
    let mut worst = 0;
    let mut squared = 0u64;
    for (i, x) in rgb.iter().enumerate() {
        let along: i32 = (0..3).map(|k| (x[k] - la[k]) * axis[k]).sum();
        let t = (along * top as i32 + length2 / 2)
            .div_euclid(length2)
            .clamp(0, top as i32);
        let (mut best, mut best_d2, mut best_max) = (0u32, u64::MAX, 0u32);
        for w in (t - 1).max(0)..=(t + 1).min(top as i32) {
            let l = levels[w as usize];
            let d: [i32; 3] = std::array::from_fn(|k| x[k] - l[k]);
            let d2 = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as u64;
            let max = d.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
            if (d2, max) < (best_d2, best_max) {
                (best, best_d2, best_max) = (w as u32, d2, max);
            }
        }
        weights[i] = best;
        worst = worst.max(best_max);
        squared += best_d2;
    }
    (worst, squared)
}

/// End points for a group: its two colours farthest apart along its principal axis (power
/// iteration on the covariance, on the 0–255 scale), so the line through them runs along the
/// group's spread.
fn end_points(group: &[Colour], rgb: &[[i32; 3]]) -> (Colour, Colour) {
    let n = rgb.len() as f32;
    let mean: [f32; 3] = std::array::from_fn(|k| rgb.iter().map(|c| c[k] as f32).sum::<f32>() / n);
    let mut cov = [[0f32; 3]; 3];
    for c in rgb {
        let d: [f32; 3] = std::array::from_fn(|k| c[k] as f32 - mean[k]);
        for (i, row) in cov.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += d[i] * d[j];
            }
        }
    }
    let mut axis = [1.0f32, 1.0, 1.0];
    for _ in 0..6 {
        let next: [f32; 3] = std::array::from_fn(|i| (0..3).map(|j| cov[i][j] * axis[j]).sum());
        let len = next.iter().map(|v| v * v).sum::<f32>().sqrt();
        if len < 1e-6 {
            break;
        }
        axis = next.map(|v| v / len);
    }
    let along = |c: &[i32; 3]| (0..3).map(|k| c[k] as f32 * axis[k]).sum::<f32>();
    let (mut lo, mut hi) = (0, 0);
    let (mut lo_t, mut hi_t) = (along(&rgb[0]), along(&rgb[0]));
    for (i, c) in rgb.iter().enumerate().skip(1) {
        let t = along(c);
        if t < lo_t {
            (lo, lo_t) = (i, t);
        }
        if t > hi_t {
            (hi, hi_t) = (i, t);
        }
    }
    (group[lo], group[hi])
}

/// The end points that best fit `rgb` with these weights (least squares per channel on the
/// 0–255 scale, rounded to RGB565); `None` when every weight is the same.
fn refit(rgb: &[[i32; 3]], weights: &[u32; GROUP], top: u32) -> Option<(Colour, Colour)> {
    let (mut aa, mut ab, mut bb) = (0f32, 0f32, 0f32);
    let (mut ax, mut bx) = ([0f32; 3], [0f32; 3]);
    for (c, &w) in rgb.iter().zip(weights) {
        let (alpha, beta) = ((top - w) as f32 / top as f32, w as f32 / top as f32);
        aa += alpha * alpha;
        ab += alpha * beta;
        bb += beta * beta;
        for k in 0..3 {
            ax[k] += alpha * c[k] as f32;
            bx[k] += beta * c[k] as f32;
        }
    }
    let det = aa * bb - ab * ab;
    if det.abs() < 1e-6 {
        return None;
    }
    let solve = |k: usize| {
        let a = (bb * ax[k] - ab * bx[k]) / det;
        let b = (aa * bx[k] - ab * ax[k]) / det;
        (
            a.clamp(0.0, 255.0).round() as u8,
            b.clamp(0.0, 255.0).round() as u8,
        )
    };
    let (r, g, bl) = (solve(0), solve(1), solve(2));
    Some((
        Colour::from_rgb8(r.0, g.0, bl.0),
        Colour::from_rgb8(r.1, g.1, bl.1),
    ))
}

/// What [`encode`] measured: the largest per-channel error of any voxel and the sum of squared
/// errors over all channels (0–255 scale).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Loss {
    pub worst: u32,
    pub squared: u64,
}

/// Appends the blocks of `colours` with `bits`-bit weights (2 or 3; header included) to `out`
/// if every voxel stays within `bound` per channel and the sum of squared errors within
/// `max_squared`; otherwise leaves `out` as it was and returns `None`.
pub fn encode(
    colours: &[Colour],
    bits: u32,
    bound: u32,
    max_squared: u64,
    out: &mut Vec<u16>,
) -> Option<Loss> {
    let start = out.len();
    let top = (1 << bits) - 1;
    out.push(header(bits));
    let mut loss = Loss::default();
    let mut weights = [0u32; GROUP];
    for group in colours.chunks(GROUP) {
        let rgb = &rgb_of(group)[..group.len()];
        let (mut a, mut b) = end_points(group, rgb);
        let (mut worst, mut squared) = fit(rgb, a, b, top, &mut weights);
        // Least-squares end points for the weights found, kept while they lower the squared
        // error within the bound (or the worst error while it is past the bound).
        for _ in 0..3 {
            if squared == 0 {
                break;
            }
            let Some((a2, b2)) = refit(rgb, &weights, top) else {
                break;
            };
            let mut w2 = [0u32; GROUP];
            let (worst2, squared2) = fit(rgb, a2, b2, top, &mut w2);
            let better = if worst > bound {
                (worst2, squared2) < (worst, squared)
            } else {
                worst2 <= bound && squared2 < squared
            };
            if !better {
                break;
            }
            (a, b, worst, squared, weights) = (a2, b2, worst2, squared2, w2);
        }
        loss.worst = loss.worst.max(worst);
        loss.squared += squared;
        if worst > bound || loss.squared > max_squared {
            out.truncate(start);
            return None;
        }
        let mut packed = 0u64;
        for (i, &w) in weights[..group.len()].iter().enumerate() {
            packed |= u64::from(w) << (bits as usize * i);
        }
        out.extend_from_slice(&[a.0, b.0]);
        let weight_words = (bits as usize * group.len()).div_ceil(16);
        out.extend((0..weight_words).map(|k| (packed >> (16 * k)) as u16));
    }
    Some(loss)
}

/// The error a viewer allows by default: 12 steps of 255 per channel, at most (see
/// BENCHMARKS.md, "Colours in fewer bits", for what it costs and keeps on Sibenik).
pub const DEFAULT_BOUND: u32 = 12;
/// A brick keeps 2-bit weights only while its mean squared error per channel (0–255 scale)
/// is at most this (RMSE 2.8, about 39 dB); noisier bricks take 3-bit weights. Chosen on
/// Sibenik: it holds the scene's colour PSNR above 40 dB for 0.9 MiB more than 2-bit alone.
pub const MEAN_SQUARED_2BIT: u64 = 8;
/// The largest bound one may ask for.
pub const MAX_BOUND: u32 = 64;

/// How exactly a copy of a scene keeps its colours: `--colours exact|bounded|bounded:N`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quality {
    /// Every colour as the server holds it (palettes or raw).
    Exact,
    /// Bricks may be coded in blocks where every voxel stays within this error per channel
    /// (0–255 scale).
    Bounded(u32),
}

impl Default for Quality {
    fn default() -> Quality {
        Quality::Bounded(DEFAULT_BOUND)
    }
}

impl Quality {
    /// The bound for [`crate::BrickMap::set_colour_bound`].
    pub fn bound(self) -> Option<u32> {
        match self {
            Quality::Exact => None,
            Quality::Bounded(b) => Some(b),
        }
    }
}

impl std::fmt::Display for Quality {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Quality::Exact => write!(f, "exact"),
            Quality::Bounded(b) => write!(f, "bounded:{b}"),
        }
    }
}

impl std::str::FromStr for Quality {
    type Err = String;

    fn from_str(s: &str) -> Result<Quality, String> {
        let bad = || {
            format!(
                "colours must be `exact`, `bounded` (within {DEFAULT_BOUND} of 255 per channel) \
                 or `bounded:N` with N from 1 to {MAX_BOUND}, not {s:?}"
            )
        };
        match s {
            "exact" => Ok(Quality::Exact),
            "bounded" => Ok(Quality::default()),
            _ => match s.strip_prefix("bounded:").map(str::parse::<u32>) {
                Some(Ok(n)) if (1..=MAX_BOUND).contains(&n) => Ok(Quality::Bounded(n)),
                _ => Err(bad()),
            },
        }
    }
}

/// The colour of the voxel of rank `rank` in blocks of `bits`-bit weights (after the header:
/// `words` starts at group 0).
pub fn colour_at(words: &[u16], bits: u32, rank: usize) -> Option<Colour> {
    let size = group_words(bits);
    let g = words.get(size * (rank / GROUP)..)?;
    let at = bits as usize * (rank % GROUP);
    let low = u32::from(*g.get(2 + at / 16)?);
    // A weight that straddles two words takes the next one's low bits.
    let high = if at % 16 + bits as usize > 16 {
        u32::from(*g.get(3 + at / 16)?) << 16
    } else {
        0
    };
    let w = ((low | high) >> (at % 16)) & ((1 << bits) - 1);
    Some(mix(g[0], g[1], w, (1 << bits) - 1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn the_four_levels_are_the_end_points_and_their_thirds() {
        let (a, b) = (Colour::from_rgb8(0, 0, 0), Colour::from_rgb8(255, 255, 255));
        assert_eq!(mix(a.0, b.0, 0, 3), a);
        assert_eq!(mix(a.0, b.0, 3, 3), b);
        assert_eq!(channels(mix(a.0, b.0, 1, 3)), [10, 21, 10]);
        assert_eq!(channels(mix(a.0, b.0, 2, 3)), [21, 42, 21]);
        assert_eq!(mix(a.0, b.0, 7, 7), b);
        assert_eq!(channels(mix(a.0, b.0, 1, 7)), [4, 9, 4]);
    }

    #[test]
    fn a_gradient_is_kept_within_the_bound_and_noise_is_refused() {
        let ramp: Vec<Colour> = (0..40)
            .map(|i| Colour::from_rgb8(100 + i, 50, 20 + i))
            .collect();
        for bits in [2, 3] {
            let mut out = Vec::new();
            let loss =
                encode(&ramp, bits, 8, u64::MAX, &mut out).expect("a ramp fits four levels per 16");
            assert_eq!(out.len(), words(bits, ramp.len()));
            assert!(loss.worst <= 8);
            for (rank, &c) in ramp.iter().enumerate() {
                assert!(error(colour_at(&out[1..], bits, rank).unwrap(), c) <= 8);
            }
        }
        let noise: Vec<Colour> = (0..32u32)
            .map(|i| Colour((i.wrapping_mul(2_654_435_761) >> 16) as u16))
            .collect();
        let mut out = vec![7];
        assert_eq!(encode(&noise, 3, 8, u64::MAX, &mut out), None);
        assert_eq!(out, vec![7], "a refused brick writes nothing");
    }

    #[test]
    fn quality_reads_exact_bounded_and_a_bound() {
        assert_eq!("exact".parse(), Ok(Quality::Exact));
        assert_eq!("bounded".parse(), Ok(Quality::Bounded(DEFAULT_BOUND)));
        assert_eq!("bounded:4".parse(), Ok(Quality::Bounded(4)));
        for bad in [
            "",
            "lossy",
            "bounded:0",
            "bounded:65",
            "bounded:x",
            "bounded:-1",
        ] {
            let e = bad.parse::<Quality>().unwrap_err();
            assert!(
                e.contains("exact") && e.contains(&format!("{bad:?}")),
                "{e}"
            );
        }
        assert_eq!(
            Quality::Bounded(7).to_string().parse(),
            Ok(Quality::Bounded(7))
        );
    }

    proptest! {
        #[test]
        fn every_voxel_decodes_within_the_bound(
            colours in prop::collection::vec(any::<u16>().prop_map(Colour), 1..512),
            bound in 0u32..64,
            bits in 2u32..4,
        ) {
            let mut out = Vec::new();
            if let Some(loss) = encode(&colours, bits, bound, u64::MAX, &mut out) {
                prop_assert_eq!(out.len(), words(bits, colours.len()));
                let mut squared = 0u64;
                for (rank, &c) in colours.iter().enumerate() {
                    let got = colour_at(&out[1..], bits, rank).unwrap();
                    prop_assert!(error(got, c) <= bound);
                    let (x, y) = (got.to_rgb8(), c.to_rgb8());
                    squared += (0..3).map(|k| (i64::from(x[k]) - i64::from(y[k])).pow(2) as u64).sum::<u64>();
                }
                prop_assert_eq!(squared, loss.squared);
            }
        }
    }
}
