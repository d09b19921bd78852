//! The voxels a tool reaches from where a ray hit: a flood fill's region, a face extrude's
//! face, a line between two voxels. Resolved on the map being edited (`apply.rs`), so two
//! people using tools at once never disagree about what a tool covered.

use std::collections::{HashMap, VecDeque};

use crate::brick::{BRICK_EDGE, EMPTY_MASK, Mask, mask_get, mask_set, rank, voxel_bit};
use crate::colour::Colour;
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

/// Breadth-first from `start` through the neighbours `steps` give, keeping those `keep`
/// accepts (it reads voxels through the [`Local`] it is handed); more than `limit` kept is
/// [`Rejection::TooLarge`] (nothing is changed by a refused tool). The order is the search's:
/// the same on every copy of the same map.
fn search(
    local: &mut Local,
    start: [u32; 3],
    steps: &[[i64; 3]],
    limit: u32,
    keep: impl Fn(&mut Local, [u32; 3]) -> bool,
) -> Result<Vec<[u32; 3]>, Rejection> {
    let mut queue = VecDeque::new();
    let mut out = Vec::new();
    local.see(start);
    queue.push_back(start);
    while let Some(pos) = queue.pop_front() {
        out.push(pos);
        if out.len() > limit as usize {
            return Err(Rejection::TooLarge);
        }
        for &s in steps {
            if let Some(next) = step(local.map, pos, s)
                && !local.seen(next)
                && keep(local, next)
            {
                local.see(next);
                queue.push_back(next);
            }
        }
    }
    Ok(out)
}

/// The bricks a search reads, decoded once each (mask and colours), with a 512-bit mask per
/// brick of what it has seen, and the brick it read last at hand: most neighbours are in
/// the same brick, so most reads hash nothing. A region of a million voxels costs a few
/// thousand decoded bricks, not seven map lookups and a hashed key per voxel.
struct Local<'a> {
    map: &'a BrickMap,
    index: HashMap<[u32; 3], usize>,
    bricks: Vec<(Mask, Vec<Colour>, Mask)>,
    last: Option<([u32; 3], usize)>,
}

impl<'a> Local<'a> {
    fn new(map: &'a BrickMap) -> Local<'a> {
        Local {
            map,
            index: HashMap::new(),
            bricks: Vec::new(),
            last: None,
        }
    }

    /// The brick holding `pos` (decoded on first use), and `pos`'s bit in it.
    fn at(&mut self, pos: [u32; 3]) -> (usize, u32) {
        let e = BRICK_EDGE;
        let cell = pos.map(|p| p / e);
        let bit = voxel_bit(pos[0] % e, pos[1] % e, pos[2] % e);
        if let Some((c, i)) = self.last
            && c == cell
        {
            return (i, bit);
        }
        let (map, bricks) = (self.map, &mut self.bricks);
        let i = *self.index.entry(cell).or_insert_with(|| {
            let (mask, colours) = map
                .brick(cell)
                .map_or((EMPTY_MASK, Vec::new()), |b| (b.mask, b.colours));
            bricks.push((mask, colours, EMPTY_MASK));
            bricks.len() - 1
        });
        self.last = Some((cell, i));
        (i, bit)
    }

    fn get(&mut self, pos: [u32; 3]) -> Option<Colour> {
        let (i, bit) = self.at(pos);
        let (mask, colours, _) = &self.bricks[i];
        mask_get(mask, bit).then(|| colours[rank(mask, bit) as usize])
    }

    fn seen(&mut self, pos: [u32; 3]) -> bool {
        let (i, bit) = self.at(pos);
        mask_get(&self.bricks[i].2, bit)
    }

    fn see(&mut self, pos: [u32; 3]) {
        let (i, bit) = self.at(pos);
        mask_set(&mut self.bricks[i].2, bit, true);
    }
}

/// The solid voxels of `start`'s colour connected to it through faces (`start` first).
pub fn fill_region(
    map: &BrickMap,
    start: [u32; 3],
    limit: u32,
) -> Result<Vec<[u32; 3]>, Rejection> {
    let mut local = Local::new(map);
    let Some(colour) = local.get(start) else {
        return Ok(Vec::new());
    };
    search(&mut local, start, &NEIGHBOURS, limit, |l, p| {
        l.get(p) == Some(colour)
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
    let mut local = Local::new(map);
    let Some(colour) = local.get(start) else {
        return Ok(Vec::new());
    };
    let open = |l: &mut Local, p: [u32; 3]| {
        l.get(p) == Some(colour) && step(map, p, normal).is_some_and(|front| l.get(front).is_none())
    };
    if !open(&mut local, start) {
        return Ok(Vec::new());
    }
    let in_plane: Vec<[i64; 3]> = NEIGHBOURS
        .iter()
        .copied()
        .filter(|s| (0..3).all(|i| s[i] == 0 || normal[i] == 0))
        .collect();
    search(&mut local, start, &in_plane, limit, open)
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
