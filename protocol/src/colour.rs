//! Voxel colour: 16-bit RGB565.
//!
//! Colour is the largest part of a scene (one entry per solid voxel), so it is stored at 16 bits.
//! RGB565 is the precision of BC1 texture blocks and of the compressed RGB that van Wingerden's
//! brick maps use (the paper's reference point); it halves colour memory against RGBA8 and is what
//! gets a textured 2048³ scene under 100 MB. Conversions round to nearest and expand by bit
//! replication so that `from_rgb8(c.to_rgb8()) == c` for every colour.

use serde::{Deserialize, Serialize};

/// A voxel colour in RGB565 (red in the top 5 bits, blue in the bottom 5).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
#[serde(transparent)]
pub struct Colour(pub u16);

impl Colour {
    pub const WHITE: Colour = Colour(0xFFFF);
    pub const BLACK: Colour = Colour(0);

    /// Quantises 8-bit channels to 5/6/5 bits, rounding to nearest.
    pub const fn from_rgb8(r: u8, g: u8, b: u8) -> Colour {
        let r5 = (r as u32 * 31 + 127) / 255;
        let g6 = (g as u32 * 63 + 127) / 255;
        let b5 = (b as u32 * 31 + 127) / 255;
        Colour(((r5 << 11) | (g6 << 5) | b5) as u16)
    }

    /// Expands to 8-bit channels by bit replication (0 → 0, max → 255).
    pub const fn to_rgb8(self) -> [u8; 3] {
        let r5 = ((self.0 >> 11) & 0x1F) as u32;
        let g6 = ((self.0 >> 5) & 0x3F) as u32;
        let b5 = (self.0 & 0x1F) as u32;
        [
            ((r5 << 3) | (r5 >> 2)) as u8,
            ((g6 << 2) | (g6 >> 4)) as u8,
            ((b5 << 3) | (b5 >> 2)) as u8,
        ]
    }

    /// Channels as floats in 0..=1, the form the shader works in.
    pub fn to_f32(self) -> [f32; 3] {
        let r5 = ((self.0 >> 11) & 0x1F) as f32;
        let g6 = ((self.0 >> 5) & 0x3F) as f32;
        let b5 = (self.0 & 0x1F) as f32;
        [r5 / 31.0, g6 / 63.0, b5 / 31.0]
    }

    /// `#rrggbb` (8-bit channels, [`Colour::to_rgb8`]): what [`Colour::parse_hex`] reads back.
    pub fn to_hex(self) -> String {
        let [r, g, b] = self.to_rgb8();
        format!("#{r:02x}{g:02x}{b:02x}")
    }

    /// Parses `#rrggbb` or `rrggbb`.
    pub fn parse_hex(text: &str) -> Option<Colour> {
        let hex = text.strip_prefix('#').unwrap_or(text);
        if hex.len() != 6 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
            return None;
        }
        let value = u32::from_str_radix(hex, 16).ok()?;
        Some(Colour::from_rgb8(
            (value >> 16) as u8,
            (value >> 8) as u8,
            value as u8,
        ))
    }
}

impl std::fmt::Display for Colour {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [r, g, b] = self.to_rgb8();
        write!(f, "#{r:02x}{g:02x}{b:02x}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_colour_round_trips_through_rgb8() {
        for raw in 0..=u16::MAX {
            let c = Colour(raw);
            let [r, g, b] = c.to_rgb8();
            assert_eq!(Colour::from_rgb8(r, g, b), c, "{raw:#06x}");
        }
    }

    #[test]
    fn extremes_and_hex() {
        assert_eq!(Colour::from_rgb8(255, 255, 255), Colour::WHITE);
        assert_eq!(Colour::WHITE.to_rgb8(), [255, 255, 255]);
        assert_eq!(
            Colour::parse_hex("#ff0000").map(|c| c.to_rgb8()),
            Some([255, 0, 0])
        );
        assert_eq!(Colour::parse_hex("12345"), None);
        assert_eq!(Colour::parse_hex("zz0000"), None);
        assert_eq!(Colour::from_rgb8(255, 0, 0).to_string(), "#ff0000");
    }

    #[test]
    fn quantisation_error_is_at_most_half_a_step() {
        for v in 0..=255u8 {
            let [r, g, _] = Colour::from_rgb8(v, v, v).to_rgb8();
            assert!((r as i32 - v as i32).abs() <= 5, "red {v} -> {r}");
            assert!((g as i32 - v as i32).abs() <= 3, "green {v} -> {g}");
        }
    }
}
