//! Property tests of brick map edits against a plain hash-map model, plus the GPU change log.

use std::collections::HashMap;

use brickcast_protocol::brick::EMPTY;
use brickcast_protocol::map::{BrickMap, BrushMode, GpuChanges};
use brickcast_protocol::{BrickData, Colour};
use proptest::prelude::*;

const SIZE: [u32; 3] = [40, 24, 33];

#[derive(Debug, Clone)]
enum Op {
    Set([u32; 3], u16),
    Clear([u32; 3]),
    Paint([u32; 3], u16),
    Sphere([f32; 3], f32, BrushMode, u16),
    Box([u32; 3], [u32; 3], BrushMode, u16),
    Reinsert([u32; 3]),
    /// A whole brick of many colours (an 8-bit palette or raw), as an import writes one.
    Textured([u32; 3], u16),
}

fn pos() -> impl Strategy<Value = [u32; 3]> {
    (0..SIZE[0] + 3, 0..SIZE[1] + 3, 0..SIZE[2] + 3).prop_map(|(x, y, z)| [x, y, z])
}

fn mode() -> impl Strategy<Value = BrushMode> {
    prop_oneof![
        Just(BrushMode::Fill),
        Just(BrushMode::Erase),
        Just(BrushMode::Paint)
    ]
}

fn op() -> impl Strategy<Value = Op> {
    let colour = 0u16..6;
    prop_oneof![
        6 => (pos(), colour.clone()).prop_map(|(p, c)| Op::Set(p, c)),
        3 => pos().prop_map(Op::Clear),
        2 => (pos(), colour.clone()).prop_map(|(p, c)| Op::Paint(p, c)),
        2 => ((-2.0f32..42.0, -2.0f32..26.0, -2.0f32..35.0), 0.3f32..9.0, mode(), colour.clone())
            .prop_map(|((x, y, z), r, m, c)| Op::Sphere([x, y, z], r, m, c)),
        2 => (pos(), pos(), mode(), colour).prop_map(|(a, b, m, c)| {
            Op::Box(std::array::from_fn(|i| a[i].min(b[i])), std::array::from_fn(|i| a[i].max(b[i])), m, c)
        }),
        1 => pos().prop_map(Op::Reinsert),
        1 => (pos(), 0u16..3).prop_map(|(p, k)| Op::Textured(p, k)),
    ]
}

type Model = HashMap<[u32; 3], Colour>;

fn model_apply(model: &mut Model, p: [u32; 3], mode: BrushMode, colour: Colour) -> u64 {
    if (0..3).any(|i| p[i] >= SIZE[i]) {
        return 0;
    }
    let before = model.get(&p).copied();
    match mode {
        BrushMode::Fill => {
            model.insert(p, colour);
        }
        BrushMode::Erase => {
            model.remove(&p);
        }
        BrushMode::Paint => {
            if let Some(c) = model.get_mut(&p) {
                *c = colour;
            }
        }
    }
    u64::from(before != model.get(&p).copied())
}

fn all_voxels() -> impl Iterator<Item = [u32; 3]> {
    (0..SIZE[2]).flat_map(|z| (0..SIZE[1]).flat_map(move |y| (0..SIZE[0]).map(move |x| [x, y, z])))
}

/// The GPU's copy, kept up to date only from the change log, as the client's uploader does.
#[derive(Default)]
struct Mirror {
    regions: Vec<u32>,
    cells: Vec<u32>,
    masks: Vec<[u64; 8]>,
    bases: Vec<u32>,
    colours: Vec<u16>,
}

impl Mirror {
    fn apply(&mut self, map: &BrickMap, changes: &GpuChanges) {
        self.regions.resize(map.regions().len(), EMPTY);
        self.cells.resize(map.cells().len(), 0xDEAD_BEEF);
        self.masks.resize(map.masks().len(), [0xDEAD; 8]);
        self.bases.resize(map.colour_bases().len(), 0xDEAD_BEEF);
        self.colours.resize(map.colour_pool().len(), 0xDEAD);
        for &r in &changes.regions {
            self.regions[r as usize] = map.regions()[r as usize];
        }
        for &b in &changes.cell_blocks {
            let r = b as usize * 64..b as usize * 64 + 64;
            self.cells[r.clone()].copy_from_slice(&map.cells()[r]);
        }
        for &s in &changes.slots {
            self.masks[s as usize] = map.masks()[s as usize];
            self.bases[s as usize] = map.colour_bases()[s as usize];
        }
        for &(first, count) in &changes.colours {
            let r = first as usize..(first + count) as usize;
            self.colours[r.clone()].copy_from_slice(&map.colour_pool()[r]);
        }
    }

    /// A voxel read through the mirrored arrays with the same addressing the shader uses.
    fn get(&self, map: &BrickMap, p: [u32; 3]) -> Option<Colour> {
        let cell = p.map(|c| c / 8);
        let rd = map.region_dims();
        let r = cell.map(|c| c / 4);
        let block = self.regions[(r[0] + rd[0] * (r[1] + rd[1] * r[2])) as usize];
        if brickcast_protocol::map::region_is_empty(block) {
            return None;
        }
        let local = (cell[0] & 3) | ((cell[1] & 3) << 2) | ((cell[2] & 3) << 4);
        let slot = self.cells[(block * 64 + local) as usize];
        if brickcast_protocol::map::cell_is_empty(slot) {
            return None;
        }
        let mask = &self.masks[slot as usize];
        let bit = brickcast_protocol::brick::voxel_bit(p[0], p[1], p[2]);
        if !brickcast_protocol::brick::mask_get(mask, bit) {
            return None;
        }
        // The block at the slot's base, read as the shader reads it.
        brickcast_protocol::palette::colour_at_words(
            &self.colours[self.bases[slot as usize] as usize..],
            brickcast_protocol::brick::rank(mask, bit) as usize,
        )
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn edits_match_model_and_gpu_mirror(ops in prop::collection::vec(op(), 1..60)) {
        let mut map = BrickMap::new(SIZE).unwrap();
        map.record_gpu_changes(true);
        let mut mirror = Mirror::default();
        let mut model = Model::new();
        for op in &ops {
            let colour = |c: u16| Colour(c * 0x1111 + 7);
            let (got, want) = match *op {
                Op::Set(p, c) => (u64::from(map.set(p, colour(c))), model_apply(&mut model, p, BrushMode::Fill, colour(c))),
                Op::Clear(p) => (u64::from(map.clear(p)), model_apply(&mut model, p, BrushMode::Erase, Colour(0))),
                Op::Paint(p, c) => (u64::from(map.paint(p, colour(c))), model_apply(&mut model, p, BrushMode::Paint, colour(c))),
                Op::Sphere(centre, r, m, c) => {
                    let got = map.sphere(centre, r, m, colour(c));
                    let mut want = 0;
                    for v in all_voxels() {
                        let d2: f32 = (0..3).map(|i| { let d = v[i] as f32 + 0.5 - centre[i]; d * d }).sum();
                        if d2 <= r * r {
                            want += model_apply(&mut model, v, m, colour(c));
                        }
                    }
                    // The brush evaluates rows with a square root; voxels within an ulp of the
                    // surface may land either side. Resync the model from the map for those.
                    if got != want {
                        for v in all_voxels() {
                            let d2: f32 = (0..3).map(|i| { let d = v[i] as f32 + 0.5 - centre[i]; d * d }).sum();
                            prop_assert!((d2 - r * r).abs() < 1e-2 || map.get(v) == model.get(&v).copied());
                            match map.get(v) { Some(c) => { model.insert(v, c); } None => { model.remove(&v); } }
                        }
                    }
                    (got, got)
                }
                Op::Box(lo, hi, m, c) => {
                    let got = map.fill_box(lo, hi, m, colour(c));
                    let mut want = 0;
                    for v in all_voxels() {
                        if (0..3).all(|i| v[i] >= lo[i] && v[i] <= hi[i]) {
                            want += model_apply(&mut model, v, m, colour(c));
                        }
                    }
                    (got, want)
                }
                Op::Textured(p, k) => {
                    let cell = p.map(|c| c / 8);
                    if (0..3).any(|i| cell[i] * 8 >= SIZE[i]) {
                        (0, 0)
                    } else {
                        let mut brick = BrickData { cell, mask: [0; 8], colours: Vec::new() };
                        let distinct = [20u32, 200, 512][usize::from(k)];
                        let mut changed = 0;
                        for z in 0..8 {
                            for y in 0..8 {
                                for x in 0..8 {
                                    let v = [cell[0] * 8 + x, cell[1] * 8 + y, cell[2] * 8 + z];
                                    if (0..3).all(|i| v[i] < SIZE[i]) {
                                        let bit = x + 8 * y + 64 * z;
                                        let c = Colour((bit % distinct * 97 + 5) as u16);
                                        brick.mask[(bit / 64) as usize] |= 1 << (bit % 64);
                                        brick.colours.push(c);
                                        changed += model_apply(&mut model, v, BrushMode::Fill, c);
                                    }
                                }
                            }
                        }
                        map.put_brick(&brick).unwrap();
                        (changed, changed)
                    }
                }
                Op::Reinsert(p) => {
                    // Round-trip one brick through its compact form.
                    let cell = p.map(|c| c / 8);
                    if let Some(b) = map.brick(cell) {
                        prop_assert!(map.remove_brick(cell));
                        map.put_brick(&b).unwrap();
                    }
                    (0, 0)
                }
            };
            prop_assert_eq!(got, want, "changed-voxel count for {:?}", op);
            map.check_invariants().map_err(TestCaseError::fail)?;
            let changes = map.take_gpu_changes();
            mirror.apply(&map, &changes);
        }
        for v in all_voxels() {
            prop_assert_eq!(map.get(v), model.get(&v).copied(), "voxel {:?}", v);
            prop_assert_eq!(mirror.get(&map, v), model.get(&v).copied(), "GPU mirror at {:?}", v);
        }
        prop_assert_eq!(map.solid_voxels(), model.len() as u64);
        // Rebuilding from compact bricks gives the same scene.
        let mut copy = BrickMap::new(SIZE).unwrap();
        for (b, _) in map.bricks() {
            copy.put_brick(&b).unwrap();
        }
        prop_assert_eq!(copy.content_hash(), map.content_hash());
    }
}

#[test]
fn compact_brick_rejects_foreign_sizes() {
    let map = BrickMap::new(SIZE).unwrap();
    let mut mask = [0u64; 8];
    mask[7] = 1 << 63; // voxel (7,7,7) of cell (4,2,4) = (39,23,39): z 39 >= 33
    let b = BrickData {
        cell: [4, 2, 4],
        mask,
        colours: vec![Colour(1)],
    };
    assert!(map.check_brick(&b).is_err());
}
