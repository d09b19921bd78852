//! Display names as people see them on each other's screens: what a name may hold, and how a
//! name sent with characters it may not hold is made fit to show.
//!
//! A name is drawn beside a cursor and in the roster, so it must not hide or reorder what is
//! around it or pretend to be something it is not. Removed: control and format characters
//! (bidirectional overrides such as U+202E, zero-width spaces and joiners, U+2060, the BOM),
//! line and paragraph separators, private-use, surrogate and unassigned code points, enclosing
//! marks, the invisible Hangul fillers, and combining marks past [`MAX_MARKS_PER_LETTER`] on
//! one letter (stacked marks draw over the names above and below). Any space becomes one
//! ASCII space, runs of them one, and the name is trimmed. Names are compared in Unicode NFC.
//! Which names look like each other (confusables, UTS #39) is the server's business: it knows
//! who is present.

use unicode_normalization::UnicodeNormalization;
use unicode_properties::{GeneralCategory, UnicodeGeneralCategory};

use super::collab::{MAX_DISPLAY_NAME_BYTES, Refusal};

/// Combining marks kept on one letter: enough for every script's ordinary writing (a
/// Vietnamese vowel carries two), not for a tower of them.
pub const MAX_MARKS_PER_LETTER: usize = 2;

/// Letters that are blank in every font (Hangul fillers, the Mongolian vowel separator).
fn is_invisible_letter(c: char) -> bool {
    matches!(
        c,
        '\u{115F}' | '\u{1160}' | '\u{3164}' | '\u{FFA0}' | '\u{180E}' | '\u{2800}'
    )
}

/// `raw` made fit to show (see the module doc); empty when nothing printable is left. The
/// result is at most [`MAX_DISPLAY_NAME_BYTES`] long (cut at a character).
pub fn clean_display_name(raw: &str) -> String {
    let mut out = String::with_capacity(raw.len().min(MAX_DISPLAY_NAME_BYTES));
    let mut marks = 0;
    let mut space = false;
    for c in raw.nfc() {
        let keep = match c.general_category() {
            GeneralCategory::Control
            | GeneralCategory::Format
            | GeneralCategory::LineSeparator
            | GeneralCategory::ParagraphSeparator
            | GeneralCategory::Surrogate
            | GeneralCategory::PrivateUse
            | GeneralCategory::Unassigned
            | GeneralCategory::EnclosingMark => None,
            GeneralCategory::SpaceSeparator => Some(' '),
            GeneralCategory::NonspacingMark | GeneralCategory::SpacingMark => {
                // A mark needs a letter to sit on.
                marks += 1;
                (marks <= MAX_MARKS_PER_LETTER && !out.is_empty() && !space).then_some(c)
            }
            _ if is_invisible_letter(c) => None,
            _ => Some(c),
        };
        let Some(c) = keep else { continue };
        if c == ' ' {
            space = !out.is_empty();
            continue;
        }
        if !matches!(
            c.general_category(),
            GeneralCategory::NonspacingMark | GeneralCategory::SpacingMark
        ) {
            marks = 0;
        }
        let pending = usize::from(space);
        if out.len() + pending + c.len_utf8() > MAX_DISPLAY_NAME_BYTES {
            break;
        }
        if space {
            out.push(' ');
            space = false;
        }
        out.push(c);
    }
    out
}

/// Why a display name is refused: empty, too long, or not as [`clean_display_name`] would
/// make it (control or format characters, stacked marks, odd spaces, not NFC).
pub fn check_display_name(name: &str) -> Result<(), Refusal> {
    if name.is_empty() || name.len() > MAX_DISPLAY_NAME_BYTES || clean_display_name(name) != name {
        return Err(Refusal::BadName {
            max: MAX_DISPLAY_NAME_BYTES as u32,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_and_control_characters_are_removed() {
        for (raw, clean) in [
            ("Al\u{200B}ice", "Alice"),
            ("\u{202E}ecilA", "ecilA"),
            ("\u{FEFF}Alice", "Alice"),
            ("Ali\u{2060}ce", "Alice"),
            ("Al\u{200D}ice\u{7}", "Alice"),
            ("A\u{2028}lice", "Alice"),
            ("\u{3164}\u{3164}", ""),
            ("\u{E000}Alice", "Alice"),
            ("  Alice \u{3000}  Smith ", "Alice Smith"),
            ("Alice\tSmith", "AliceSmith"),
        ] {
            assert_eq!(clean_display_name(raw), clean, "{raw:?}");
            assert!(
                check_display_name(raw).is_err(),
                "{raw:?} is refused as sent"
            );
        }
    }

    #[test]
    fn marks_stay_on_letters_but_do_not_stack() {
        // Decomposed é is the same name as the composed one.
        assert_eq!(clean_display_name("Rene\u{301}"), "René");
        assert!(check_display_name("René").is_ok());
        // Vietnamese keeps its two marks on one vowel; a tower of them is cut.
        assert_eq!(clean_display_name("Nguyê\u{303}n"), "Nguyễn");
        let zalgo = format!("A{}lice", "\u{300}\u{301}\u{302}\u{303}\u{304}".repeat(4));
        let clean = clean_display_name(&zalgo);
        assert_eq!(
            clean.chars().count(),
            "Alice".chars().count() + 2,
            "{clean:?}"
        );
        // A mark with no letter under it, and enclosing marks, go.
        assert_eq!(clean_display_name("\u{301}Bob"), "Bob");
        assert_eq!(clean_display_name("Bob\u{20DD}"), "Bob");
        // Scripts that write with marks keep them.
        assert!(check_display_name("हिन्दी").is_ok());
        assert!(check_display_name("日本語 名前").is_ok());
        assert!(check_display_name("🦊 fox").is_ok());
    }

    #[test]
    fn names_are_cut_to_the_bound_at_a_character() {
        let long = "é".repeat(MAX_DISPLAY_NAME_BYTES);
        let clean = clean_display_name(&long);
        assert!(clean.len() <= MAX_DISPLAY_NAME_BYTES && clean.len() >= MAX_DISPLAY_NAME_BYTES - 1);
        assert!(check_display_name(&long).is_err());
        assert!(check_display_name("").is_err());
    }
}
