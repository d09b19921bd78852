//! A scene's shared palette (issue #34): [`SWATCHES`] colours everyone in the scene picks from,
//! kept with the scene (its snapshots and log) and changed by anyone who may edit, with
//! [`crate::wire::EditOp::Swatch`] — an op like any other, so it is ordered, acknowledged,
//! logged and replayed with the voxels, and every copy of a scene holds the same palette at the
//! same sequence. Clients hear the palette as [`crate::wire::ServerMsg::Palette`] after their
//! `Welcome` and whenever a turn changed it.
//!
//! A swatch change is not an undo step (it changes no voxel): setting the swatch back is.

use serde::{Deserialize, Serialize};

use crate::Colour;

/// Swatches in a scene's palette (serde writes arrays up to 32 long without help).
pub const SWATCHES: usize = 32;

/// A scene's palette: [`SWATCHES`] colours in the order people see them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Swatches(pub [Colour; SWATCHES]);

/// What a scene starts with: the eight colours keys 1–8 always gave first, then a row of greys
/// and earth tones and a row of the brighter and paler hues of the first eight.
const DEFAULT: [(u8, u8, u8); SWATCHES] = [
    (0xd9, 0x3b, 0x3b),
    (0xf2, 0x9e, 0x38),
    (0xf2, 0xd8, 0x4b),
    (0x5f, 0xb0, 0x4a),
    (0x3b, 0x8e, 0xd9),
    (0x8a, 0x5c, 0xc7),
    (0xf0, 0xf0, 0xf0),
    (0x50, 0x48, 0x40),
    (0x00, 0x00, 0x00),
    (0x30, 0x30, 0x30),
    (0x60, 0x60, 0x60),
    (0x90, 0x90, 0x90),
    (0xc0, 0xc0, 0xc0),
    (0xff, 0xff, 0xff),
    (0x7a, 0x52, 0x30),
    (0xa8, 0x7d, 0x50),
    (0xc9, 0xb0, 0x82),
    (0x4e, 0x6b, 0x2f),
    (0x2e, 0x4a, 0x2a),
    (0x8f, 0x8a, 0x7e),
    (0x9c, 0x4a, 0x2e),
    (0x3a, 0x5f, 0x7a),
    (0x6b, 0x3d, 0x5c),
    (0xd8, 0xc8, 0xa8),
    (0xff, 0x6f, 0x6f),
    (0xff, 0xc2, 0x7a),
    (0xff, 0xf0, 0x9a),
    (0xa6, 0xe8, 0x8c),
    (0x8c, 0xc8, 0xff),
    (0xc9, 0xa6, 0xf2),
    (0xf2, 0xa6, 0xc9),
    (0x6f, 0xe0, 0xd6),
];

impl Default for Swatches {
    fn default() -> Self {
        Swatches(DEFAULT.map(|(r, g, b)| Colour::from_rgb8(r, g, b)))
    }
}

impl Swatches {
    /// Swatch `index` (wrapping, so any key or click lands on one).
    pub fn get(&self, index: usize) -> Colour {
        self.0[index % SWATCHES]
    }

    /// Sets swatch `index`; `false` (and nothing changed) when there is no such swatch.
    pub fn set(&mut self, index: usize, colour: Colour) -> bool {
        match self.0.get_mut(index) {
            Some(c) => {
                *c = colour;
                true
            }
            None => false,
        }
    }

    /// 64 bytes, little-endian RGB565 in swatch order: how stores and snapshots keep it.
    pub fn to_bytes(&self) -> Vec<u8> {
        self.0.iter().flat_map(|c| c.0.to_le_bytes()).collect()
    }

    /// The inverse of [`Swatches::to_bytes`]; `None` for any other length.
    pub fn from_bytes(bytes: &[u8]) -> Option<Swatches> {
        if bytes.len() != 2 * SWATCHES {
            return None;
        }
        let mut out = [Colour::BLACK; SWATCHES];
        for (c, pair) in out.iter_mut().zip(bytes.chunks_exact(2)) {
            *c = Colour(u16::from_le_bytes([pair[0], pair[1]]));
        }
        Some(Swatches(out))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_eight_are_the_old_number_keys() {
        // What keys 1–8 drew with before scenes had palettes (as the page's buttons wrote them).
        let old = "#d93b3b #f29e38 #f2d84b #5fb04a #3b8ed9 #8a5cc7 #f0f0f0 #504840";
        let s = Swatches::default();
        for (i, hex) in old.split(' ').enumerate() {
            assert_eq!(Some(s.get(i)), Colour::parse_hex(hex), "{hex}");
        }
        assert_eq!(s.get(SWATCHES + 1), s.get(1), "wraps");
    }

    #[test]
    fn bytes_round_trip_and_other_lengths_are_refused() {
        let mut s = Swatches::default();
        assert!(s.set(31, Colour(0x1234)));
        assert!(!s.set(32, Colour(0x1234)), "no swatch 32");
        let bytes = s.to_bytes();
        assert_eq!(bytes.len(), 64);
        assert_eq!(Swatches::from_bytes(&bytes), Some(s));
        assert_eq!(Swatches::from_bytes(&bytes[1..]), None);
        assert_eq!(Swatches::from_bytes(&[]), None);
    }
}
