//! Colour quantisation for formats with a small palette (MagicaVoxel: 255 colours).
//!
//! A scene's colours are RGB565, so a histogram over all 65,536 values is exact and small. When
//! a scene has no more distinct colours than the palette holds, the palette *is* those colours
//! and nothing is lost (565 → RGB8 → 565 is exact). Otherwise median cut over the
//! voxel-weighted histogram picks the palette and each colour maps to its nearest entry; the
//! error is reported, not hidden.

use brickcast_protocol::Colour;

/// A palette and the map from every RGB565 colour in use to its entry.
pub struct Palette {
    pub colours: Vec<[u8; 3]>,
    /// RGB565 value → palette index (only meaningful for colours in the histogram).
    lookup: Vec<u8>,
}

/// How faithful a palette is to the colours it replaced.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct QuantizeReport {
    /// Distinct RGB565 colours in the scene.
    pub distinct: usize,
    pub palette: usize,
    /// True when every colour is in the palette unchanged.
    pub exact: bool,
    /// Voxel-weighted mean and worst Euclidean RGB8 distance from a colour to its entry.
    pub mean_error: f64,
    pub max_error: f64,
}

impl Palette {
    pub fn index(&self, colour: Colour) -> u8 {
        self.lookup[colour.0 as usize]
    }
}

fn distance(a: [u8; 3], b: [u8; 3]) -> f64 {
    let d: i32 = (0..3).map(|i| (a[i] as i32 - b[i] as i32).pow(2)).sum();
    (d as f64).sqrt()
}

/// Builds a palette of at most `max` entries (≥ 1) from a histogram indexed by RGB565 value.
pub fn quantize(histogram: &[u64], max: usize) -> (Palette, QuantizeReport) {
    let max = max.max(1);
    let used: Vec<(Colour, u64)> = histogram
        .iter()
        .enumerate()
        .filter(|(_, n)| **n > 0)
        .map(|(c, n)| (Colour(c as u16), *n))
        .collect();
    let mut lookup = vec![0u8; 1 << 16];
    if used.len() <= max {
        let colours = used.iter().map(|(c, _)| c.to_rgb8()).collect();
        for (i, (c, _)) in used.iter().enumerate() {
            lookup[c.0 as usize] = i as u8;
        }
        let report = QuantizeReport {
            distinct: used.len(),
            palette: used.len(),
            exact: true,
            mean_error: 0.0,
            max_error: 0.0,
        };
        return (Palette { colours, lookup }, report);
    }

    // Median cut: split the box with the widest channel range (weighted by how many voxels it
    // holds) at the voxel-weighted median of that channel.
    let mut boxes: Vec<Vec<([u8; 3], u64)>> =
        vec![used.iter().map(|(c, n)| (c.to_rgb8(), *n)).collect()];
    while boxes.len() < max {
        let score = |b: &Vec<([u8; 3], u64)>| -> (u64, usize) {
            if b.len() < 2 {
                return (0, 0);
            }
            let (channel, range) = (0..3)
                .map(|ch| {
                    let lo = b.iter().map(|(c, _)| c[ch]).min().unwrap_or(0);
                    let hi = b.iter().map(|(c, _)| c[ch]).max().unwrap_or(0);
                    (ch, (hi - lo) as u64)
                })
                .max_by_key(|&(_, r)| r)
                .unwrap_or((0, 0));
            let weight: u64 = b.iter().map(|(_, n)| n).sum();
            (range * range * weight.max(1), channel)
        };
        let Some((widest, (s, channel))) = boxes
            .iter()
            .map(score)
            .enumerate()
            .max_by_key(|(_, (s, _))| *s)
        else {
            break;
        };
        if s == 0 {
            break;
        }
        let mut b = boxes.swap_remove(widest);
        b.sort_unstable_by_key(|(c, _)| c[channel]);
        let total: u64 = b.iter().map(|(_, n)| n).sum();
        let mut seen = 0;
        let mut cut = 1;
        for (i, (_, n)) in b.iter().enumerate() {
            seen += n;
            if seen * 2 >= total {
                cut = (i + 1).clamp(1, b.len() - 1);
                break;
            }
        }
        let upper = b.split_off(cut);
        boxes.push(b);
        boxes.push(upper);
    }
    let colours: Vec<[u8; 3]> = boxes
        .iter()
        .map(|b| {
            let weight: u64 = b.iter().map(|(_, n)| n).sum::<u64>().max(1);
            std::array::from_fn(|ch| {
                let sum: u64 = b.iter().map(|(c, n)| c[ch] as u64 * n).sum();
                ((sum + weight / 2) / weight) as u8
            })
        })
        .collect();
    let (mut error_sum, mut max_error, mut voxels) = (0.0, 0.0f64, 0u64);
    for (c, n) in &used {
        let rgb = c.to_rgb8();
        let (index, err) = colours
            .iter()
            .enumerate()
            .map(|(i, p)| (i, distance(rgb, *p)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, 0.0));
        lookup[c.0 as usize] = index as u8;
        error_sum += err * *n as f64;
        max_error = max_error.max(err);
        voxels += n;
    }
    let report = QuantizeReport {
        distinct: used.len(),
        palette: colours.len(),
        exact: false,
        mean_error: error_sum / voxels.max(1) as f64,
        max_error,
    };
    (Palette { colours, lookup }, report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn few_colours_are_kept_exactly() {
        let mut h = vec![0u64; 1 << 16];
        let colours = [
            Colour::from_rgb8(255, 0, 0),
            Colour::from_rgb8(10, 200, 30),
            Colour::WHITE,
        ];
        for (i, c) in colours.iter().enumerate() {
            h[c.0 as usize] = 10 + i as u64;
        }
        let (p, r) = quantize(&h, 255);
        assert!(r.exact);
        assert_eq!((r.distinct, r.palette), (3, 3));
        for c in colours {
            assert_eq!(p.colours[p.index(c) as usize], c.to_rgb8());
        }
    }

    #[test]
    fn many_colours_are_cut_to_the_limit_with_bounded_error() {
        // A smooth gradient of 4,096 colours into 255 entries: neighbours share entries, and
        // no colour lands far from its own.
        let mut h = vec![0u64; 1 << 16];
        for r in 0..64u32 {
            for g in 0..64u32 {
                h[Colour::from_rgb8((r * 4) as u8, (g * 4) as u8, 128).0 as usize] += 1;
            }
        }
        let (p, r) = quantize(&h, 255);
        assert!(!r.exact);
        assert_eq!(r.palette, 255);
        assert!(r.distinct >= 2000, "{r:?}");
        assert!(r.mean_error < 12.0 && r.max_error < 30.0, "{r:?}");
        assert!(p.colours.len() == 255);
    }
}
