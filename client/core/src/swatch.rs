//! The scene's shared palette in both viewers (issue #34, `brickcast_protocol::swatches`):
//! number keys 1–9 and 0 take swatches 1–10 to draw with; with Shift they set that swatch to
//! the colour drawn with now, for everyone in the scene (an `EditOp::Swatch`, ordered and kept
//! by the server like any edit). The page's swatch grid clicks the same way (Shift+click sets).

use brickcast_protocol::Colour;
use brickcast_protocol::swatches::{SWATCHES, Swatches};
use brickcast_protocol::wire::EditOp;

/// What a number key or a swatch click does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SwatchAction {
    /// Draw with swatch `index`'s colour from now on.
    Take { index: usize, colour: Colour },
    /// Ask the server to set swatch `index` to `colour` for everyone.
    Set { index: usize, op: EditOp },
}

impl SwatchAction {
    /// A line for the status bar.
    pub fn note(&self) -> String {
        match *self {
            SwatchAction::Take { index, colour } => {
                format!("swatch {}: {}", index + 1, colour.to_hex())
            }
            SwatchAction::Set { index, op } => match op {
                EditOp::Swatch { colour, .. } => {
                    format!(
                        "swatch {} set to {} for everyone",
                        index + 1,
                        colour.to_hex()
                    )
                }
                _ => String::new(),
            },
        }
    }
}

/// Swatch `index` clicked (or its key pressed): take its colour, or with `set` make it
/// `current`. `None` for an index past the palette.
pub fn swatch_action(
    index: usize,
    set: bool,
    swatches: &Swatches,
    current: Colour,
) -> Option<SwatchAction> {
    if index >= SWATCHES {
        return None;
    }
    Some(if set {
        SwatchAction::Set {
            index,
            op: EditOp::Swatch {
                index: index as u8,
                colour: current,
            },
        }
    } else {
        SwatchAction::Take {
            index,
            colour: swatches.get(index),
        }
    })
}

/// The key `code` (a `KeyboardEvent.code` / winit key name: `Digit1` … `Digit0`) with Shift
/// held or not; `None` when it is not a number key.
pub fn swatch_key(
    code: &str,
    shift: bool,
    swatches: &Swatches,
    current: Colour,
) -> Option<SwatchAction> {
    let digit: usize = code.strip_prefix("Digit")?.parse().ok()?;
    // 1–9 are swatches 0–8, 0 is swatch 9 (the keys' order on a keyboard).
    let index = match digit {
        1..=9 => digit - 1,
        0 => 9,
        _ => return None,
    };
    swatch_action(index, shift, swatches, current)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn number_keys_take_swatches_and_shift_sets_one_for_everyone() {
        let mut swatches = Swatches::default();
        let teal = Colour::from_rgb8(0, 128, 128);
        swatches.set(9, teal);
        let red = Colour::from_rgb8(255, 0, 0);
        assert_eq!(
            swatch_key("Digit1", false, &swatches, red),
            Some(SwatchAction::Take {
                index: 0,
                colour: swatches.get(0)
            })
        );
        assert_eq!(
            swatch_key("Digit0", false, &swatches, red),
            Some(SwatchAction::Take {
                index: 9,
                colour: teal
            })
        );
        let set = swatch_key("Digit3", true, &swatches, red).unwrap();
        assert_eq!(
            set,
            SwatchAction::Set {
                index: 2,
                op: EditOp::Swatch {
                    index: 2,
                    colour: red
                }
            }
        );
        assert_eq!(set.note(), "swatch 3 set to #ff0000 for everyone");
        for other in ["KeyD", "Digit", "Digit12", "Numpad1", ""] {
            assert_eq!(swatch_key(other, false, &swatches, red), None, "{other}");
        }
        assert_eq!(
            swatch_action(SWATCHES - 1, true, &swatches, red).map(|a| a.note()),
            Some(format!("swatch {SWATCHES} set to #ff0000 for everyone"))
        );
        assert_eq!(swatch_action(SWATCHES, false, &swatches, red), None);
    }
}
