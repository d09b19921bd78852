//! Restoring a box of a scene to how it was at an earlier sequence (issue #34,
//! [`crate::wire::EditOp::Restore`]). The server rebuilds the scene as it was (its store keeps
//! the past), takes the bricks over the box as a [`PastBox`], and the scene's owner writes,
//! in the scene's order, every voxel of the box as it was then: solid ones with their colour
//! then, empty ones emptied. Voxels outside the box stay as they are now.

use crate::brick::{BRICK_EDGE, BrickData, EMPTY_MASK, Mask, for_each_bit, mask_set};
use crate::colour::Colour;
use crate::map::BrickMap;

/// The bricks of a scene's past over a box that differ from the scene at sequence `against`
/// (`None`: every cell the box touches), with their brick then (`None`: empty then). Cells the
/// box touches that are not listed were the same then as at `against`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PastBox {
    pub min: [u32; 3],
    pub max: [u32; 3],
    against: Option<u64>,
    bricks: Vec<([u32; 3], Option<BrickData>)>,
}

/// Why a restore cannot be written as it was fetched.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Stale {
    #[error("the box changed while its past was being fetched; restore again")]
    Changed,
}

/// Brick coordinates of the cells of `map` that `min..=max` (voxels) touches, in cell order
/// (z, y, x): none past the map, whatever the box.
fn cells_of(map: &BrickMap, min: [u32; 3], max: [u32; 3]) -> impl Iterator<Item = [u32; 3]> {
    let dims = map.cell_dims();
    let lo = min.map(|c| c / BRICK_EDGE);
    let hi: [u32; 3] =
        std::array::from_fn(|i| (max[i] / BRICK_EDGE).min(dims[i].saturating_sub(1)));
    (lo[2]..=hi[2]).flat_map(move |z| {
        (lo[1]..=hi[1]).flat_map(move |y| (lo[0]..=hi[0]).map(move |x| [x, y, z]))
    })
}

/// Every voxel of a brick as its colour (`None`: empty).
fn voxels(brick: Option<&BrickData>) -> [Option<Colour>; 512] {
    let mut out = [None; 512];
    if let Some(brick) = brick {
        let mut rank = 0;
        for_each_bit(&brick.mask, |bit| {
            out[bit as usize] = Some(brick.colours[rank]);
            rank += 1;
        });
    }
    out
}

/// About what one listed cell weighs in memory.
fn brick_bytes(brick: Option<&BrickData>) -> usize {
    24 + brick.map_or(0, |b| 64 + 2 * b.colours.len())
}

impl PastBox {
    /// The box `min..=max` of `past` (corners in order, inside the map: the op's check), every
    /// cell it touches.
    pub fn take(past: &BrickMap, min: [u32; 3], max: [u32; 3]) -> PastBox {
        let bricks = cells_of(past, min, max)
            .map(|cell| (cell, past.brick(cell)))
            .collect();
        PastBox {
            min,
            max,
            against: None,
            bricks,
        }
    }

    /// The box of `past` where it differs from `now` (the same scene at a later sequence):
    /// what a restore writes, if the box does not change after `now` (see [`PastBox::check`]).
    /// `Err(bytes)` as soon as it would weigh more than `max_bytes` ([`PastBox::bytes`]).
    pub fn diff(
        past: &BrickMap,
        now: &BrickMap,
        min: [u32; 3],
        max: [u32; 3],
        max_bytes: usize,
    ) -> Result<PastBox, usize> {
        let mut bricks = Vec::new();
        let mut bytes = 0;
        for cell in cells_of(past, min, max) {
            let then = past.brick(cell);
            if then != now.brick(cell) {
                bytes += brick_bytes(then.as_ref());
                if bytes > max_bytes {
                    return Err(bytes);
                }
                bricks.push((cell, then));
            }
        }
        Ok(PastBox {
            min,
            max,
            against: Some(now.sequence()),
            bricks,
        })
    }

    /// Whether it still describes the box on `now`: no cell of the box it does not list changed
    /// after the sequence it was compared against.
    pub fn check(&self, now: &BrickMap) -> Result<(), Stale> {
        let Some(against) = self.against else {
            return Ok(());
        };
        let changes = now.changes_since(against).ok_or(Stale::Changed)?;
        let (lo, hi) = (
            self.min.map(|c| c / BRICK_EDGE),
            self.max.map(|c| c / BRICK_EDGE),
        );
        let listed: std::collections::HashSet<[u32; 3]> =
            self.bricks.iter().map(|(cell, _)| *cell).collect();
        let stale = changes
            .changed
            .iter()
            .chain(&changes.removed)
            .any(|c| (0..3).all(|i| lo[i] <= c[i] && c[i] <= hi[i]) && !listed.contains(c));
        if stale { Err(Stale::Changed) } else { Ok(()) }
    }

    /// Bricks it holds (solid ones).
    pub fn brick_count(&self) -> usize {
        self.bricks.iter().filter(|(_, b)| b.is_some()).count()
    }

    /// About what it weighs in memory.
    pub fn bytes(&self) -> usize {
        self.bricks
            .iter()
            .map(|(_, b)| brick_bytes(b.as_ref()))
            .sum()
    }

    /// The bricks of `now` the restore changes, as they are after it, in cell order: what the
    /// server writes (a brick with no voxel left is to be removed). Bricks it leaves as they
    /// are not listed.
    pub fn restore(&self, now: &BrickMap) -> Vec<BrickData> {
        let mut out = Vec::new();
        for (cell, then) in &self.bricks {
            let old = now.brick(*cell);
            let mut after = voxels(old.as_ref());
            let before = voxels(then.as_ref());
            // The part of the box inside this brick, in the brick's own coordinates.
            let lo: [u32; 3] = std::array::from_fn(|i| {
                self.min[i].max(cell[i] * BRICK_EDGE) - cell[i] * BRICK_EDGE
            });
            let hi: [u32; 3] = std::array::from_fn(|i| {
                self.max[i].min(cell[i] * BRICK_EDGE + BRICK_EDGE - 1) - cell[i] * BRICK_EDGE
            });
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let bit = crate::brick::voxel_bit(x, y, z) as usize;
                        after[bit] = before[bit];
                    }
                }
            }
            let mut mask: Mask = EMPTY_MASK;
            let mut colours = Vec::new();
            for (bit, v) in after.iter().enumerate() {
                if let Some(c) = v {
                    mask_set(&mut mask, bit as u32, true);
                    colours.push(*c);
                }
            }
            let same = match &old {
                Some(o) => o.mask == mask && o.colours == colours,
                None => colours.is_empty(),
            };
            if !same {
                out.push(BrickData {
                    cell: *cell,
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

    /// A restore writes the box as it was, solid and empty alike, and nothing outside it.
    #[test]
    fn a_restore_writes_the_box_as_it_was_and_nothing_else() {
        let mut then = BrickMap::new([32, 16, 32]).unwrap();
        then.fill_box([0, 0, 0], [31, 1, 31], BrushMode::Fill, Colour(10));
        then.set([4, 5, 4], Colour(20));
        let mut now = then.clone();
        // Since then: the floor dug out in one place, a voxel painted, a tower added.
        now.fill_box([2, 0, 2], [9, 1, 9], BrushMode::Erase, Colour(0));
        now.set([4, 5, 4], Colour(30));
        now.fill_box([20, 2, 20], [21, 12, 21], BrushMode::Fill, Colour(40));
        let past = PastBox::take(&then, [0, 0, 0], [12, 15, 12]);
        let bricks = past.restore(&now);
        let mut restored = now.clone();
        for b in &bricks {
            if b.colours.is_empty() {
                restored.remove_brick(b.cell);
            } else {
                restored.put_brick(b).unwrap();
            }
        }
        for z in 0..32 {
            for y in 0..16 {
                for x in 0..32 {
                    let inside = x <= 12 && z <= 12;
                    let want = if inside {
                        then.get([x, y, z])
                    } else {
                        now.get([x, y, z])
                    };
                    assert_eq!(restored.get([x, y, z]), want, "{x},{y},{z}");
                }
            }
        }
        // Compared against the present, it lists only the bricks that differ, and writes the
        // same; a change inside the box after the present makes it stale, one outside not.
        now.set_sequence(5);
        let diff = PastBox::diff(&then, &now, [0, 0, 0], [12, 15, 12], usize::MAX).unwrap();
        // Bounded: past the bound it stops, saying how far it got.
        assert!(PastBox::diff(&then, &now, [0, 0, 0], [12, 15, 12], 100).is_err());
        // A box past the scene touches only the scene's cells.
        let huge = PastBox::take(&then, [0, 0, 0], [u32::MAX; 3]);
        assert_eq!(huge.bricks.len(), 4 * 2 * 4);
        assert!(diff.bricks.len() < past.bricks.len());
        assert_eq!(diff.restore(&now), bricks);
        assert_eq!(diff.check(&now), Ok(()));
        let mut later = now.clone();
        later.set_sequence(6);
        later.set([30, 2, 30], Colour(50));
        assert_eq!(diff.check(&later), Ok(()), "outside the box");
        later.set_sequence(7);
        later.set([12, 9, 12], Colour(50));
        assert_eq!(
            diff.check(&later),
            Err(Stale::Changed),
            "an unlisted brick of the box"
        );
        // The tower, outside the box, stays; restoring again changes nothing.
        assert_eq!(restored.get([20, 12, 20]), Some(Colour(40)));
        assert!(past.restore(&restored).is_empty());
        // A box over a place emptied since: its bricks come back; over one filled since: go.
        let mut empty = BrickMap::new([32, 16, 32]).unwrap();
        let back = PastBox::take(&then, [0, 0, 0], [31, 15, 31]).restore(&empty);
        assert_eq!(back.len(), 16);
        for b in &back {
            empty.put_brick(b).unwrap();
        }
        assert_eq!(empty.content_hash(), then.content_hash());
        let gone = PastBox::take(
            &BrickMap::new([32, 16, 32]).unwrap(),
            [0, 0, 0],
            [31, 15, 31],
        )
        .restore(&then);
        assert!(gone.iter().all(|b| b.colours.is_empty()) && gone.len() == 16);
    }
}
