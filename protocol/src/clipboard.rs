//! Copy and paste (issue #34): a box of a scene taken as a [`Clipboard`], and where its voxels
//! land when it is pasted turned and mirrored. One home for the rule: the server copies and
//! pastes with it, and a paste is logged as the voxels it changed, so replay needs no clipboard.
//!
//! **The transform.** A clipboard of size `s` pasted with `mirror` and `turns`: first x is
//! mirrored (`x → s.x − 1 − x`), then each quarter turn about the vertical axis takes
//! `(x, z)` to `(z, s.x − 1 − x)` in a box of size `(s.z, s.y, s.x)` (counter-clockwise seen
//! from above). The pasted box's lowest corner is `at`; its solid voxels replace what is there,
//! its empty ones leave the scene as it is; voxels past the scene are dropped.

use std::collections::HashMap;

use crate::BrickMap;
use crate::brick::{
    BRICK_EDGE, BrickData, EMPTY_MASK, bit_voxel, for_each_bit, mask_set, voxel_bit,
};
use crate::colour::Colour;

/// The size a box of `size` fills turned `turns` quarter turns about the vertical axis (what a
/// viewer states as a paste's size, and what the server checks it against).
pub fn turned(size: [u32; 3], turns: u8) -> [u32; 3] {
    let [x, y, z] = size;
    if turns % 2 == 1 { [z, y, x] } else { [x, y, z] }
}

/// The voxels a paste puts in one brick: (bit, colour).
type Pasted = Vec<(u32, Colour)>;

/// A copied box of voxels: its size and its solid voxels (position in the box, colour).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Clipboard {
    size: [u32; 3],
    /// `x + size.x · (y + size.y · z)` and the colour, in the order copied.
    voxels: Vec<(u32, Colour)>,
}

impl Clipboard {
    /// The voxels of `map` in the box `min..=max` (corners in order, inside the map: checked by
    /// the op that asks for it). A box of `n` voxels must fit a `u32` index (the ops' extent
    /// limit keeps it far below).
    pub fn copy(map: &BrickMap, min: [u32; 3], max: [u32; 3]) -> Clipboard {
        let size: [u32; 3] = std::array::from_fn(|i| max[i] - min[i] + 1);
        let mut voxels = Vec::new();
        let (lo, hi) = (min.map(|c| c / BRICK_EDGE), max.map(|c| c / BRICK_EDGE));
        for cz in lo[2]..=hi[2] {
            for cy in lo[1]..=hi[1] {
                for cx in lo[0]..=hi[0] {
                    let Some(brick) = map.brick([cx, cy, cz]) else {
                        continue;
                    };
                    let mut rank = 0;
                    for_each_bit(&brick.mask, |bit| {
                        let v = bit_voxel(bit);
                        let p = [
                            cx * BRICK_EDGE + v[0],
                            cy * BRICK_EDGE + v[1],
                            cz * BRICK_EDGE + v[2],
                        ];
                        if (0..3).all(|i| p[i] >= min[i] && p[i] <= max[i]) {
                            let r = [p[0] - min[0], p[1] - min[1], p[2] - min[2]];
                            let index = r[0] + size[0] * (r[1] + size[1] * r[2]);
                            voxels.push((index, brick.colours[rank]));
                        }
                        rank += 1;
                    });
                }
            }
        }
        // What it holds is what it weighs (a server bounds its clipboards by `bytes`).
        voxels.shrink_to_fit();
        Clipboard { size, voxels }
    }

    /// The copied box's size.
    pub fn size(&self) -> [u32; 3] {
        self.size
    }

    /// Solid voxels held.
    pub fn voxel_count(&self) -> usize {
        self.voxels.len()
    }

    /// Memory it holds, roughly (what a server's clipboards are bounded by).
    pub fn bytes(&self) -> usize {
        self.voxels.len() * std::mem::size_of::<(u32, Colour)>() + 64
    }

    /// The size of the box it fills when pasted with `turns` quarter turns.
    pub fn turned_size(&self, turns: u8) -> [u32; 3] {
        turned(self.size, turns)
    }

    /// Where voxel `p` of the clipboard lands in the pasted box (see the module doc).
    pub fn place(&self, p: [u32; 3], turns: u8, mirror: bool) -> [u32; 3] {
        let mut size = self.size;
        let mut p = p;
        if mirror {
            p[0] = size[0] - 1 - p[0];
        }
        for _ in 0..turns % 4 {
            p = [p[2], p[1], size[0] - 1 - p[0]];
            size = [size[2], size[1], size[0]];
        }
        p
    }

    /// The bricks of `map` the clipboard pasted at `at` (turned, mirrored) changes, as they
    /// are after it, in cell order: what the server writes. Bricks the paste leaves as they
    /// were are not listed.
    pub fn paste(&self, map: &BrickMap, at: [u32; 3], turns: u8, mirror: bool) -> Vec<BrickData> {
        let scene = map.size();
        let [sx, sy, _] = self.size;
        // Voxels copied brick by brick land a few target bricks at a time: the last one is
        // looked up first, the table only when the voxel lands elsewhere.
        let mut cells: Vec<([u32; 3], Pasted)> = Vec::new();
        let mut index_of: HashMap<[u32; 3], usize> = HashMap::new();
        let mut last: Option<([u32; 3], usize)> = None;
        for &(index, colour) in &self.voxels {
            let p = [index % sx, (index / sx) % sy, index / (sx * sy)];
            let q = self.place(p, turns, mirror);
            let w: [u64; 3] = std::array::from_fn(|i| u64::from(at[i]) + u64::from(q[i]));
            if (0..3).any(|i| w[i] >= u64::from(scene[i])) {
                continue;
            }
            let w = w.map(|c| c as u32);
            let bit = voxel_bit(w[0] % BRICK_EDGE, w[1] % BRICK_EDGE, w[2] % BRICK_EDGE);
            let cell = w.map(|c| c / BRICK_EDGE);
            let slot = match last {
                Some((c, i)) if c == cell => i,
                _ => *index_of.entry(cell).or_insert_with(|| {
                    cells.push((cell, Vec::new()));
                    cells.len() - 1
                }),
            };
            last = Some((cell, slot));
            cells[slot].1.push((bit, colour));
        }
        cells.sort_unstable_by_key(|(cell, _)| [cell[2], cell[1], cell[0]]);
        let mut out = Vec::with_capacity(cells.len());
        for (cell, pasted) in cells {
            let old = map.brick(cell);
            let mut voxels: [Option<Colour>; 512] = [None; 512];
            if let Some(old) = &old {
                let mut rank = 0;
                for_each_bit(&old.mask, |bit| {
                    voxels[bit as usize] = Some(old.colours[rank]);
                    rank += 1;
                });
            }
            for (bit, colour) in pasted {
                voxels[bit as usize] = Some(colour);
            }
            let mut mask = EMPTY_MASK;
            let mut colours = Vec::new();
            for (bit, v) in voxels.iter().enumerate() {
                if let Some(c) = v {
                    mask_set(&mut mask, bit as u32, true);
                    colours.push(*c);
                }
            }
            let same = old
                .as_ref()
                .is_some_and(|o| o.mask == mask && o.colours == colours);
            if !same {
                out.push(BrickData {
                    cell,
                    mask,
                    colours,
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::BrushMode;

    fn scene() -> BrickMap {
        let mut map = BrickMap::new([64, 32, 64]).unwrap();
        // An L of three colours, 3 wide, 2 high, 4 deep, at (5..8, 2..4, 9..13).
        map.fill_box([5, 2, 9], [7, 2, 12], BrushMode::Fill, Colour(100));
        map.set([5, 3, 9], Colour(200));
        map.set([7, 3, 12], Colour(300));
        map
    }

    /// The ops' bounds: a box whose voxels would not number in a `u32` is too large whatever
    /// the server's box limit; a paste is charged for its whole box, a copy for the bricks it
    /// reads.
    #[test]
    fn copy_and_paste_ops_are_bounded_and_charged_for_what_they_do() {
        use crate::wire::{EditOp, Limits, Rejection};
        let open = Limits {
            max_box_extent: u32::MAX,
            ..Limits::default()
        };
        let world = [16384, 512, 16384];
        let copy = |min, max| EditOp::Copy { min, max };
        let paste = |at, size, turns| EditOp::Paste {
            at,
            size,
            turns,
            mirror: false,
        };
        let whole = copy([0, 0, 0], [16383, 511, 16383]);
        assert_eq!(whole.validate(world, &open), Err(Rejection::TooLarge));
        assert_eq!(
            paste([0, 0, 0], [4096, 4096, 4096], 0).validate(world, &open),
            Err(Rejection::TooLarge)
        );
        let limits = Limits::default();
        assert!(
            copy([0, 0, 0], [255, 255, 255])
                .validate(world, &limits)
                .is_ok()
        );
        assert_eq!(
            copy([0, 0, 0], [256, 0, 0]).validate(world, &limits),
            Err(Rejection::TooLarge)
        );
        assert_eq!(
            copy([5, 0, 0], [4, 0, 0]).validate(world, &limits),
            Err(Rejection::malformed("a copy's min is above its max"))
        );
        assert!(matches!(
            paste([0, 0, 0], [2, 2, 2], 4).validate(world, &limits),
            Err(Rejection::Malformed(_))
        ));
        assert!(matches!(
            paste([0, 0, 0], [0, 2, 2], 0).validate(world, &limits),
            Err(Rejection::Malformed(_))
        ));
        assert_eq!(
            paste([16384, 0, 0], [2, 2, 2], 0).validate(world, &limits),
            Err(Rejection::OutOfBounds)
        );
        // A 256³ paste into a 64³ scene is charged for all of it (every voxel is placed).
        assert_eq!(
            paste([0, 0, 0], [256, 256, 256], 0).work([64, 64, 64]),
            256 * 256 * 256
        );
        assert_eq!(
            copy([3, 3, 3], [3, 3, 3]).work(world),
            512,
            "one brick read"
        );
        assert_eq!(copy([7, 0, 0], [8, 0, 0]).work(world), 1024, "two bricks");
    }

    #[test]
    fn a_copy_pastes_back_where_it_came_from_unchanged() {
        let map = scene();
        let clip = Clipboard::copy(&map, [4, 1, 8], [8, 4, 13]);
        assert_eq!(clip.size(), [5, 4, 6]);
        assert_eq!(clip.voxel_count(), 14);
        // Back where it came from it changes nothing: no brick to write.
        assert!(clip.paste(&map, [4, 1, 8], 0, false).is_empty());
        let bricks = clip.paste(&map, [4, 1, 9], 0, false);
        assert!(!bricks.is_empty());
        let cells: Vec<[u32; 3]> = bricks.iter().map(|b| b.cell).collect();
        let mut sorted = cells.clone();
        sorted.sort_by_key(|c| [c[2], c[1], c[0]]);
        assert_eq!(cells, sorted, "in cell order");
    }

    #[test]
    fn a_paste_turns_and_mirrors_and_keeps_what_its_empty_voxels_cover() {
        let map = scene();
        let clip = Clipboard::copy(&map, [5, 2, 9], [7, 3, 12]);
        assert_eq!(clip.size(), [3, 2, 4]);
        assert_eq!(clip.turned_size(1), [4, 2, 3]);
        // One quarter turn: (x, z) → (z, 2 − x).
        assert_eq!(clip.place([0, 1, 0], 1, false), [0, 1, 2]);
        assert_eq!(clip.place([2, 1, 3], 1, false), [3, 1, 0]);
        // Four turns are none; mirroring twice is none.
        for p in [[0, 0, 0], [1, 1, 2], [2, 0, 3]] {
            assert_eq!(clip.place(p, 4, false), p);
            assert_eq!(clip.place(clip.place(p, 0, true), 0, true), p);
        }
        let mut map = map;
        map.set([30, 5, 30], Colour(998)); // where a solid voxel lands
        map.set([31, 6, 31], Colour(999)); // inside the pasted box, where the clipboard is empty
        for b in clip.paste(&map, [30, 5, 30], 1, false) {
            map.put_brick(&b).unwrap();
        }
        assert_eq!(map.get([30, 6, 32]), Some(Colour(200)), "(0,1,0) turned");
        assert_eq!(map.get([33, 6, 30]), Some(Colour(300)), "(2,1,3) turned");
        assert_eq!(
            map.get([30, 5, 30]),
            Some(Colour(100)),
            "a solid voxel replaces"
        );
        assert_eq!(
            map.get([31, 6, 31]),
            Some(Colour(999)),
            "an empty one keeps"
        );
        assert_eq!(map.get([31, 6, 30]), None);
        // Mirrored: (x, z) → (2 − x, z).
        let mirrored = clip.paste(&map, [40, 5, 40], 0, true);
        let mut m = map.clone();
        for b in &mirrored {
            m.put_brick(b).unwrap();
        }
        assert_eq!(m.get([42, 6, 40]), Some(Colour(200)));
        // Past the scene's edge: the rest is dropped, nothing panics.
        let edge = clip.paste(&map, [63, 31, 63], 3, true);
        let solid: u32 = edge
            .iter()
            .map(|b| b.mask.iter().map(|w| w.count_ones()).sum::<u32>())
            .sum();
        assert!(solid >= 1);
        assert!(clip.paste(&map, [u32::MAX, 0, 0], 0, false).is_empty());
    }
}
