//! One voxel's edit made in its brick's colour block where it lies (issue #29): a single-voxel
//! set, paint or clear would otherwise decode and re-code the whole brick (about 1 µs for a few
//! hundred voxels, where the edit itself is 150 ns). Raw blocks shift their colours; palette
//! blocks whose palette already holds the colour write or shift indices. Anything else (a new
//! colour for a palette, a coding that should change) returns `None`, and the map re-codes the
//! brick. A block edited here may keep a palette entry no voxel uses any more, until the brick's
//! next re-coding: it still decodes to exactly the brick's colours.

use crate::colour::Colour;
use crate::palette::{Coding, coding_of_words};

/// What happens to the voxel of rank `r`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Edit {
    /// It is solid and takes this colour.
    Recolour(Colour),
    /// It becomes solid with this colour (ranks from `r` on move up one).
    Insert(Colour),
    /// It becomes empty (ranks after `r` move down one).
    Remove,
}

/// What an edit changed: words from `first` to the block's end (`words` after it, `before`
/// before it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Changed {
    pub first: usize,
    pub before: usize,
    pub words: usize,
}

/// Applies `edit` to the block at the start of `chunk` (its slot's whole chunk, so a block may
/// grow into the rest), which holds `n` voxels and is coded as `coding` (its header, read by
/// the caller). `None`: not done here; nothing was written.
pub(crate) fn edit_in_place(
    chunk: &mut [u16],
    mut coding: Coding,
    n: usize,
    r: usize,
    edit: Edit,
) -> Option<Changed> {
    debug_assert_eq!(coding_of_words(chunk).ok(), Some(coding));
    let before = coding.words(n);
    let mut first_palette_change = None;
    if let (Coding::Palette { bits, entries }, Edit::Recolour(c) | Edit::Insert(c)) = (coding, edit)
        && let Err(p) = chunk[1..=entries].binary_search(&c.0)
    {
        // A colour the palette lacks: one more entry, if the index width holds it and the chunk
        // has the room (its indices move one word up).
        let grown = Coding::Palette {
            bits,
            entries: entries + 1,
        };
        let voxels = if matches!(edit, Edit::Insert(_)) {
            n + 1
        } else {
            n
        };
        if entries + 1 > 1 << bits || grown.words(voxels) > chunk.len() || r > n {
            return None;
        }
        let packed_words = before - 1 - entries;
        chunk.copy_within(1 + entries..1 + entries + packed_words, 2 + entries);
        chunk.copy_within(1 + p..1 + entries, 2 + p);
        chunk[1 + p] = c.0;
        chunk[0] = grown.header();
        let (bits, mask) = (bits as usize, (1u16 << bits) - 1);
        let packed = &mut chunk[2 + entries..];
        for i in 0..n {
            let (w, sh) = (i * bits / 16, i * bits % 16);
            let v = (packed[w] >> sh) & mask;
            if usize::from(v) >= p {
                packed[w] = (packed[w] & !(mask << sh)) | ((v + 1) << sh);
            }
        }
        coding = grown;
        // The header names one more entry.
        first_palette_change = Some(0);
    }
    let after = coding.words(match edit {
        Edit::Insert(_) => n + 1,
        Edit::Remove => n.checked_sub(1)?,
        Edit::Recolour(_) => n,
    });
    if after > chunk.len() || r > n || (r == n && !matches!(edit, Edit::Insert(_))) {
        // A grown palette was checked for room before it grew.
        debug_assert!(first_palette_change.is_none());
        return None;
    }
    match coding {
        Coding::Raw => {
            let colours = &mut chunk[1..];
            match edit {
                Edit::Recolour(c) => colours[r] = c.0,
                Edit::Insert(c) => {
                    colours.copy_within(r..n, r + 1);
                    colours[r] = c.0;
                }
                Edit::Remove => colours.copy_within(r + 1..n, r),
            }
            Some(Changed {
                first: 1 + r,
                before,
                words: after,
            })
        }
        Coding::Palette { bits, entries } => {
            let (palette, packed) = chunk[1..].split_at_mut(entries);
            let index = match edit {
                Edit::Recolour(c) | Edit::Insert(c) => palette.binary_search(&c.0).ok()? as u16,
                Edit::Remove => 0,
            };
            let bits = bits as usize;
            let mask = (1u16 << bits) - 1;
            if matches!(edit, Edit::Insert(_)) && (n * bits).is_multiple_of(16) {
                // The new last index starts a word the block did not have.
                packed[n * bits / 16] = 0;
            }
            let mut put = |i: usize, v: u16| {
                let (w, sh) = (i * bits / 16, i * bits % 16);
                let old = (packed[w] >> sh) & mask;
                packed[w] = (packed[w] & !(mask << sh)) | (v << sh);
                old
            };
            match edit {
                Edit::Recolour(_) => {
                    put(r, index);
                }
                Edit::Insert(_) => {
                    let mut carry = index;
                    for i in r..=n {
                        carry = put(i, carry);
                    }
                }
                Edit::Remove => {
                    let mut carry = 0;
                    for i in (r..n).rev() {
                        carry = put(i, carry);
                    }
                }
            }
            Some(Changed {
                first: first_palette_change.unwrap_or(1 + entries + r * bits / 16),
                before,
                words: after,
            })
        }
        Coding::One | Coding::Blocks { .. } => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::palette::{choose, decode_words, encode_words};
    use proptest::prelude::*;

    fn block(colours: &[Colour], cap: usize) -> Vec<u16> {
        let (coding, palette) = choose(colours);
        let mut out = vec![0xBEEF; cap];
        encode_words(
            colours,
            coding,
            &palette,
            &mut out[..coding.words(colours.len())],
        );
        out
    }

    proptest! {
        /// Whatever it does, an edit in place decodes to the colours the edit asks for.
        #[test]
        fn an_edit_in_place_decodes_as_the_edited_colours(
            colours in prop::collection::vec((0u16..40).prop_map(|c| Colour(c * 977)), 1..300),
            shades in 1u16..40,
            at in any::<prop::sample::Index>(),
            what in 0u8..3,
            colour in 0u16..40,
        ) {
            let colours: Vec<Colour> = colours.iter().map(|c| Colour(c.0 % (shades * 977))).collect();
            let n = colours.len();
            let mut chunk = block(&colours, 1 + 2 * n + 8);
            let edit = match what {
                0 => Edit::Recolour(Colour(colour * 977)),
                1 => Edit::Insert(Colour(colour * 977)),
                _ => Edit::Remove,
            };
            let r = at.index(if what == 1 { n + 1 } else { n });
            let mut want = colours.clone();
            match edit {
                Edit::Recolour(c) => want[r] = c,
                Edit::Insert(c) => want.insert(r, c),
                Edit::Remove => { want.remove(r); }
            }
            let old = chunk.clone();
            let coding = coding_of_words(&chunk).unwrap();
            if let Some(changed) = edit_in_place(&mut chunk, coding, n, r, edit) {
                // Every word that changed is in the range handed to the GPU uploader.
                let end = changed.words.max(changed.before);
                for (i, (a, b)) in old.iter().zip(&chunk).enumerate() {
                    prop_assert!(a == b || (changed.first..end).contains(&i), "word {} changed outside {}..{}", i, changed.first, end);
                }
                let mut got = vec![Colour::BLACK; want.len()];
                let words = decode_words(&chunk, &mut got).unwrap();
                prop_assert_eq!(words, changed.words);
                prop_assert_eq!(got, want);
            } else {
                prop_assert_eq!(chunk, block(&colours, 1 + 2 * n + 8), "a refused edit wrote");
            }
        }
    }
}
