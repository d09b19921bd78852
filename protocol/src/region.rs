//! The voxels a tool reaches from where a ray hit: a flood fill's region, a face extrude's
//! face, a line between two voxels. Resolved on the map being edited (`apply.rs`), so two
//! people using tools at once never disagree about what a tool covered.

use std::collections::{HashMap, VecDeque};

use crate::brick::{BRICK_EDGE, voxel_bit};
use crate::map::BrickMap;
use crate::wire::Rejection;

/// One step along each axis, both ways.
const NEIGHBOURS: [[i64; 3]; 6] = [
    [1, 0, 0],
    [-1, 0, 0],
    [0, 1, 0],
    [0, -1, 0],
    [0, 0, 1],
    [0, 0, -1],
];

/// `pos + step` when it is inside the map.
fn step(map: &BrickMap, pos: [u32; 3], step: [i64; 3]) -> Option<[u32; 3]> {
    let size = map.size();
    let mut out = [0u32; 3];
    for i in 0..3 {
        let p = i64::from(pos[i]) + step[i];
        if p < 0 || p >= i64::from(size[i]) {
            return None;
        }
        out[i] = p as u32;
    }
    Some(out)
}

/// Breadth-first from `start` through the neighbours `next` gives, keeping those `keep`
/// accepts; more than `limit` kept is [`Rejection::TooLarge`] (nothing is changed by a
/// refused tool). The order is the search's: the same on every copy of the same map.
fn search(
    map: &BrickMap,
    start: [u32; 3],
    steps: &[[i64; 3]],
    limit: u32,
    keep: impl Fn([u32; 3]) -> bool,
) -> Result<Vec<[u32; 3]>, Rejection> {
    let mut seen = Seen::default();
    let mut queue = VecDeque::new();
    let mut out = Vec::new();
    seen.insert(start);
    queue.push_back(start);
    while let Some(pos) = queue.pop_front() {
        out.push(pos);
        if out.len() > limit as usize {
            return Err(Rejection::TooLarge);
        }
        for &s in steps {
            if let Some(next) = step(map, pos, s)
                && !seen.contains(next)
                && keep(next)
            {
                seen.insert(next);
                queue.push_back(next);
            }
        }
    }
    Ok(out)
}

/// The voxels a search has seen: a 512-bit mask per brick, so a region of a million voxels
/// costs a few thousand hashed keys and about 64 bytes per brick, not a hashed key and ~40
/// bytes per voxel.
#[derive(Default)]
struct Seen {
    bricks: HashMap<[u32; 3], [u64; 8]>,
}

impl Seen {
    fn at(pos: [u32; 3]) -> ([u32; 3], usize) {
        let e = BRICK_EDGE;
        (
            pos.map(|p| p / e),
            voxel_bit(pos[0] % e, pos[1] % e, pos[2] % e) as usize,
        )
    }

    fn contains(&self, pos: [u32; 3]) -> bool {
        let (cell, bit) = Seen::at(pos);
        self.bricks
            .get(&cell)
            .is_some_and(|m| m[bit / 64] & (1 << (bit % 64)) != 0)
    }

    fn insert(&mut self, pos: [u32; 3]) {
        let (cell, bit) = Seen::at(pos);
        self.bricks.entry(cell).or_default()[bit / 64] |= 1 << (bit % 64);
    }
}

/// The solid voxels of `start`'s colour connected to it through faces (`start` first).
pub fn fill_region(
    map: &BrickMap,
    start: [u32; 3],
    limit: u32,
) -> Result<Vec<[u32; 3]>, Rejection> {
    let Some(colour) = map.get(start) else {
        return Ok(Vec::new());
    };
    search(map, start, &NEIGHBOURS, limit, |p| {
        map.get(p) == Some(colour)
    })
}

/// The face of `start` that looks along `normal` (one axis, ±1) and every face of the same
/// plane and colour connected to it (as MagicaVoxel's face mode takes them): voxels of
/// `start`'s colour side by side in that plane whose neighbour along `normal` is inside the
/// map and empty. `start` must be such a voxel.
pub fn face_region(
    map: &BrickMap,
    start: [u32; 3],
    normal: [i64; 3],
    limit: u32,
) -> Result<Vec<[u32; 3]>, Rejection> {
    let Some(colour) = map.get(start) else {
        return Ok(Vec::new());
    };
    let open = |p: [u32; 3]| {
        map.get(p) == Some(colour)
            && step(map, p, normal).is_some_and(|front| map.get(front).is_none())
    };
    if !open(start) {
        return Ok(Vec::new());
    }
    let in_plane: Vec<[i64; 3]> = NEIGHBOURS
        .iter()
        .copied()
        .filter(|s| (0..3).all(|i| s[i] == 0 || normal[i] == 0))
        .collect();
    search(map, start, &in_plane, limit, open)
}

/// The voxels of a line from `a` to `b`, both included, one voxel thick (each step moves one
/// voxel along the longest axis; the others follow by rounding, as Bresenham's line does).
pub fn line(a: [u32; 3], b: [u32; 3]) -> Vec<[u32; 3]> {
    let d: [i64; 3] = std::array::from_fn(|i| i64::from(b[i]) - i64::from(a[i]));
    let n = d.iter().map(|v| v.abs()).max().unwrap_or(0);
    if n == 0 {
        return vec![a];
    }
    (0..=n)
        .map(|k| {
            std::array::from_fn(|i| {
                // Rounded half away from zero, in integers: a + round(d·k/n).
                let num = d[i] * k;
                let q = (2 * num.abs() + n) / (2 * n);
                (i64::from(a[i]) + num.signum() * q) as u32
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::map::BrushMode;

    fn scene() -> BrickMap {
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        // A white floor, a red patch on it, a red block standing on the patch.
        map.fill_box([0, 0, 0], [31, 0, 31], BrushMode::Fill, Colour::WHITE);
        let red = Colour::from_rgb8(255, 0, 0);
        map.fill_box([4, 0, 4], [7, 0, 7], BrushMode::Paint, red);
        map.fill_box([5, 1, 5], [6, 2, 6], BrushMode::Fill, red);
        map
    }

    #[test]
    fn a_fill_takes_the_connected_voxels_of_one_colour() {
        let map = scene();
        let red = fill_region(&map, [4, 0, 4], 1000).unwrap();
        assert_eq!(red.len(), 16 + 8, "the patch and the block on it");
        assert_eq!(red[0], [4, 0, 4]);
        let white = fill_region(&map, [0, 0, 0], 10_000).unwrap();
        assert_eq!(white.len(), 32 * 32 - 16);
        assert_eq!(fill_region(&map, [0, 0, 0], 100), Err(Rejection::TooLarge));
        assert!(fill_region(&map, [0, 5, 0], 100).unwrap().is_empty(), "air");
    }

    #[test]
    fn a_face_is_the_open_voxels_of_one_plane_and_colour() {
        let map = scene();
        // The floor's top face: every white floor voxel (the red patch is another colour).
        let top = face_region(&map, [0, 0, 0], [0, 1, 0], 10_000).unwrap();
        assert_eq!(top.len(), 32 * 32 - 16);
        // The patch's: its open voxels, around the block standing on it.
        let patch = face_region(&map, [4, 0, 4], [0, 1, 0], 100).unwrap();
        assert_eq!(patch.len(), 16 - 4);
        // The block's top.
        let block = face_region(&map, [5, 2, 5], [0, 1, 0], 100).unwrap();
        assert_eq!(block.len(), 4);
        // The block's side facing -x: two high, two deep.
        let side = face_region(&map, [5, 1, 5], [-1, 0, 0], 100).unwrap();
        assert_eq!(side.len(), 4);
        // The floor's underside is the scene's edge: nothing in front to grow into.
        assert!(
            face_region(&map, [0, 0, 0], [0, -1, 0], 100)
                .unwrap()
                .is_empty()
        );
        assert_eq!(
            face_region(&map, [0, 0, 0], [0, 1, 0], 10),
            Err(Rejection::TooLarge)
        );
    }

    #[test]
    fn lines_are_one_voxel_thick_and_end_where_they_are_drawn() {
        assert_eq!(line([3, 3, 3], [3, 3, 3]), vec![[3, 3, 3]]);
        let l = line([0, 0, 0], [10, 4, 0]);
        assert_eq!(l.len(), 11);
        assert_eq!((l[0], l[10]), ([0, 0, 0], [10, 4, 0]));
        for w in l.windows(2) {
            let step: u32 = (0..3).map(|i| w[0][i].abs_diff(w[1][i])).max().unwrap();
            assert_eq!(step, 1, "{w:?}");
        }
        let back = line([10, 4, 0], [0, 0, 0]);
        assert_eq!(back.len(), 11);
        assert_eq!(back[10], [0, 0, 0]);
        let diagonal = line([2, 9, 5], [7, 4, 0]);
        assert_eq!(
            diagonal,
            (0..6).map(|k| [2 + k, 9 - k, 5 - k]).collect::<Vec<_>>()
        );
    }
}
