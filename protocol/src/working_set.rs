//! Which level a client holds each region of a world at, within a budget in bytes (issue #30):
//! the rule the server and the client both run, so the server knows exactly what a client holds.
//!
//! **The rule** ([`Rule::level_of`]): with `d` the Chebyshev distance in regions (32 voxels)
//! between a region and the region the eye is in, a region is held at full resolution (level
//! 0) when `d <= near`, and otherwise at the finest level `k >= 2` with `d <= near · 2^k`,
//! capped at the pyramid's top. A level-k voxel is 2^k voxels wide, so at 2^k times the distance
//! it covers about as much of the screen as a level-0 voxel at the edge of the full-resolution
//! zone: detail falls off evenly with distance. Level 1 is skipped because a stand-in covers
//! whole regions (`map::stand_in`); the jump from 1 to 4 voxels happens at `4·near`.
//!
//! **The budget** ([`fit`]): the largest `near` whose working set fits the client's byte budget
//! (the map's arrays as the GPU holds them: regions, cell blocks, masks, colour bases and the
//! colour chunks), found by measuring candidates against the scene and its pyramid. The region
//! array is a fixed cost (4 bytes a region: 16 MiB for a 16384×512×16384 world).

use crate::lod::Pyramid;
use crate::map::{BrickMap, MIN_STAND_IN_LEVEL, MapError, box_points};

/// Bytes a brick slot takes besides its colours: a 64-byte mask and a 4-byte colour base.
const SLOT_BYTES: u64 = 64 + 4;
/// Bytes of a cell block (64 cells of 4 bytes).
const BLOCK_BYTES: u64 = 64 * 4;

/// The distance rule, for an eye in region `eye`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rule {
    /// The region the eye is in (clamped into the grid).
    pub eye: [u32; 3],
    /// Regions within this Chebyshev distance of `eye` are held at level 0.
    pub near: u32,
    /// The coarsest level held (the pyramid's top).
    pub top: u32,
}

impl Rule {
    /// The rule for an eye at voxel position `eye` (anywhere; clamped into `map`'s grid).
    pub fn new(map: &BrickMap, pyramid: &Pyramid, eye: [f32; 3], near: u32) -> Rule {
        Rule {
            eye: Rule::eye_region(map.region_dims(), eye),
            near,
            top: pyramid.level_count().max(MIN_STAND_IN_LEVEL),
        }
    }

    /// The region of a grid of `region_dims` regions an eye at voxel position `eye` is in
    /// (clamped into the grid).
    pub fn eye_region(region_dims: [u32; 3], eye: [f32; 3]) -> [u32; 3] {
        std::array::from_fn(|i| {
            let r = (eye[i].max(0.0) / crate::map::REGION_EDGE as f32) as u32;
            r.min(region_dims[i].saturating_sub(1))
        })
    }

    /// The box of regions held at level 0 in a grid of `region_dims` (`lo` inclusive, `hi`
    /// exclusive): those within `near` of the eye.
    pub fn level_0_box(&self, region_dims: [u32; 3]) -> ([u32; 3], [u32; 3]) {
        let lo = self.eye.map(|e| e.saturating_sub(self.near));
        let hi = std::array::from_fn(|i| {
            self.eye[i]
                .saturating_add(self.near)
                .saturating_add(1)
                .min(region_dims[i])
        });
        (lo, hi)
    }

    /// The level region `r` is held at.
    pub fn level_of(&self, r: [u32; 3]) -> u32 {
        let d = (0..3)
            .map(|i| r[i].abs_diff(self.eye[i]))
            .max()
            .unwrap_or(0);
        self.level_at(d)
    }

    /// The level of a region `d` regions (Chebyshev) from the eye's.
    fn level_at(&self, d: u32) -> u32 {
        if d <= self.near {
            return 0;
        }
        let near = u64::from(self.near.max(1));
        let mut k = MIN_STAND_IN_LEVEL;
        while k < self.top && u64::from(d) > near << k {
            k += 1;
        }
        k
    }

    /// Whether the coarse brick `(level, cell)` is wanted: some region under it (inside a grid of
    /// `region_dims`) is held at `level`. Constant time: the distances of a box's regions take
    /// every value from the nearest to the farthest, and past level 0 the level grows with
    /// distance one level at a time, so the levels held under the box are exactly those from
    /// the nearest region's to the farthest's.
    pub fn holds(&self, region_dims: [u32; 3], level: u32, cell: [u32; 3]) -> bool {
        if !(MIN_STAND_IN_LEVEL..=self.top).contains(&level) {
            return false;
        }
        distances(region_dims, self.eye, level, cell)
            .is_some_and(|(dmin, dmax)| self.holds_between(level, dmin, dmax))
    }

    /// Whether a level-`level` brick whose regions lie from `dmin` to `dmax` regions from the
    /// eye is held ([`Rule::holds`], the level in range).
    fn holds_between(&self, level: u32, dmin: u32, dmax: u32) -> bool {
        self.level_at(dmin) <= level && level <= self.level_at(dmax)
    }
}

/// The nearest and farthest Chebyshev distance from region `eye` of the regions under the
/// coarse brick `(level, cell)` in a grid of `region_dims`; `None` when the cell lies outside.
fn distances(
    region_dims: [u32; 3],
    eye: [u32; 3],
    level: u32,
    cell: [u32; 3],
) -> Option<(u32, u32)> {
    let span = 1u64 << (level - MIN_STAND_IN_LEVEL);
    let (mut dmin, mut dmax) = (0u64, 0u64);
    for i in 0..3 {
        let lo = u64::from(cell[i]) * span;
        let dim = u64::from(region_dims[i]);
        if lo >= dim {
            return None;
        }
        let hi = (lo + span).min(dim) - 1;
        let e = u64::from(eye[i]);
        let nearest = if e < lo { lo - e } else { e.saturating_sub(hi) };
        dmin = dmin.max(nearest);
        dmax = dmax.max(e.abs_diff(lo).max(e.abs_diff(hi)));
    }
    let clamp = |d: u64| u32::try_from(d).unwrap_or(u32::MAX);
    Some((clamp(dmin), clamp(dmax)))
}

/// What a working set holds and what it costs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Cost {
    /// Bytes of the map's arrays as laid out for the GPU (colour chunks at their capacity).
    pub bytes: u64,
    /// Regions held at level 0, and their bricks.
    pub full_regions: u64,
    pub full_bricks: u64,
    /// Distinct coarse bricks standing in, and the regions they stand in for.
    pub coarse_bricks: u64,
    pub stand_ins: u64,
}

/// The cost of holding `base` (with its current `pyramid`) as `rule` says. Visits the regions
/// within `near` of the eye and each level's solid coarse bricks (and the regions under those
/// held), not every region of the world one by one.
pub fn cost(base: &BrickMap, pyramid: &Pyramid, rule: &Rule) -> Cost {
    let rd = base.region_dims();
    let mut c = Cost {
        bytes: rd.iter().map(|&d| u64::from(d)).product::<u64>() * 4,
        ..Cost::default()
    };
    let (lo, hi) = rule.level_0_box(rd);
    for r in box_points(lo, hi) {
        let bytes = region_bytes(base, r);
        if bytes > 0 {
            c.full_regions += 1;
            c.full_bricks += base
                .region_cells(r)
                .filter(|&cell| base.slot_of_cell(cell).is_some())
                .count() as u64;
            c.bytes += bytes;
        }
    }
    for k in MIN_STAND_IN_LEVEL..=rule.top {
        let Some(level) = pyramid.level(k) else {
            continue;
        };
        let span = 1u32 << (k - MIN_STAND_IN_LEVEL);
        for (cell, _) in level.brick_cells() {
            if !rule.holds(rd, k, cell) {
                continue;
            }
            c.coarse_bricks += 1;
            c.bytes += coarse_bytes(pyramid, k, cell);
            let lo = cell.map(|v| v.saturating_mul(span));
            let hi: [u32; 3] = std::array::from_fn(|i| lo[i].saturating_add(span).min(rd[i]));
            c.stand_ins += box_points(lo, hi)
                .filter(|&r| rule.level_of(r) == k)
                .count() as u64;
        }
    }
    c
}

/// Bytes region `r`'s level-0 bricks take in a working set: their slots and colours, and the
/// region's cell block (0 for an empty region).
pub fn region_bytes(base: &BrickMap, r: [u32; 3]) -> u64 {
    let bricks: u64 = base
        .region_cells(r)
        .filter_map(|cell| base.slot_of_cell(cell))
        .map(|slot| SLOT_BYTES + 2 * u64::from(base.fresh_chunk_words(slot)))
        .sum();
    if bricks > 0 { bricks + BLOCK_BYTES } else { 0 }
}

/// Bytes the coarse brick `(level, cell)` takes in a working set (0 when it is empty).
pub fn coarse_bytes(pyramid: &Pyramid, level: u32, cell: [u32; 3]) -> u64 {
    pyramid
        .level(level)
        .and_then(|l| {
            l.slot_of_cell(cell)
                .map(|slot| SLOT_BYTES + 2 * u64::from(l.fresh_chunk_words(slot)))
        })
        .unwrap_or(0)
}

/// [`region_bytes`] of every region, remembered: the cost of a move is mostly the regions of
/// its shells, measured again on every move otherwise (a pass over each region's bricks and
/// their colour blocks). Whoever changes the map forgets the regions of the cells it touched
/// ([`RegionCosts::forget_cells`]). Interior mutability (relaxed atomics), so a shared
/// reference to the owner's state can fill it.
pub struct RegionCosts {
    /// Per region (linear index): its bytes, or `UNKNOWN`.
    bytes: Vec<std::sync::atomic::AtomicU32>,
}

impl RegionCosts {
    const UNKNOWN: u32 = u32::MAX;

    /// Nothing known yet of a map of `region_dims` regions.
    pub fn new(region_dims: [u32; 3]) -> RegionCosts {
        let n = region_dims.iter().map(|&d| d as usize).product();
        RegionCosts {
            bytes: (0..n)
                .map(|_| std::sync::atomic::AtomicU32::new(Self::UNKNOWN))
                .collect(),
        }
    }

    /// [`region_bytes`] of region `r` of `base`.
    pub fn get(&self, base: &BrickMap, r: [u32; 3]) -> u64 {
        use std::sync::atomic::Ordering::Relaxed;
        let d = base.region_dims();
        let i = (r[0] + d[0] * (r[1] + d[1] * r[2])) as usize;
        let Some(slot) = self.bytes.get(i) else {
            return region_bytes(base, r);
        };
        match slot.load(Relaxed) {
            Self::UNKNOWN => {
                let bytes = region_bytes(base, r);
                // A region holds at most 64 bricks of a few KiB: always below the marker.
                slot.store(u32::try_from(bytes).unwrap_or(Self::UNKNOWN), Relaxed);
                bytes
            }
            known => u64::from(known),
        }
    }

    /// The regions of the level-0 cells `cells` (linear indices) changed.
    pub fn forget_cells(&self, base: &BrickMap, cells: &[u32]) {
        use std::sync::atomic::Ordering::Relaxed;
        let d = base.region_dims();
        for &c in cells {
            let r = base.cell_coords(c).map(|v| v / crate::map::REGION_CELLS);
            let i = (r[0] + d[0] * (r[1] + d[1] * r[2])) as usize;
            if let Some(slot) = self.bytes.get(i) {
                slot.store(Self::UNKNOWN, Relaxed);
            }
        }
    }
}

/// [`plan_bytes`] with the regions' bytes from `costs`.
pub fn plan_bytes_with(
    base: &BrickMap,
    pyramid: &Pyramid,
    plan: &crate::held::Plan,
    costs: &RegionCosts,
) -> u64 {
    plan_bytes_by(pyramid, plan, |r| costs.get(base, r))
}

/// Bytes of everything `plan` brings. The cost of a rule `new` is the cost of `old` plus the
/// bytes of `held::plan(old, new)` minus those of `held::plan(new, old)` (what `new` lets go
/// of): a move costs what its shells cost, not a pass over the world.
pub fn plan_bytes(base: &BrickMap, pyramid: &Pyramid, plan: &crate::held::Plan) -> u64 {
    plan_bytes_by(pyramid, plan, |r| region_bytes(base, r))
}

/// A plan's bytes with each region's from `region`.
fn plan_bytes_by(
    pyramid: &Pyramid,
    plan: &crate::held::Plan,
    region: impl Fn([u32; 3]) -> u64,
) -> u64 {
    let regions: u64 = plan.regions.iter().map(|&r| region(r)).sum();
    let coarse: u64 = plan
        .coarse
        .iter()
        .map(|&(k, cell)| coarse_bytes(pyramid, k, cell))
        .sum();
    regions + coarse
}

/// Why no working set fits.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BudgetError {
    #[error(
        "a budget of {budget} bytes is too small for this scene: the coarsest working set (level 0 only in the eye's region) takes {needed} bytes"
    )]
    TooSmall { budget: u64, needed: u64 },
    #[error(transparent)]
    Map(#[from] MapError),
}

/// The rule with the largest `near` (at most `max_near`) whose working set fits `budget` bytes,
/// and its cost. Cost grows with `near`: `near` doubles until the set no longer fits, then a
/// binary search between the last two. Each probe's level 0 is the sum of the regions' bytes
/// in the rings of regions around the eye (each ring measured once, as far out as the largest
/// probe), its coarse part a walk over the pyramid's bricks; the full [`Cost`] is measured
/// once, for the answer.
pub fn fit(
    base: &BrickMap,
    pyramid: &Pyramid,
    eye: [f32; 3],
    budget: u64,
    max_near: u32,
) -> Result<(Rule, Cost), BudgetError> {
    let rd = base.region_dims();
    let fixed = rd.iter().map(|&d| u64::from(d)).product::<u64>() * 4;
    let groups = coarse_groups(pyramid, rd, Rule::new(base, pyramid, eye, 0));
    // Bytes of level 0 in the ring of regions at each distance from the eye.
    let mut rings: Vec<u64> = Vec::new();
    let mut bytes_at = |near: u32| {
        let rule = Rule::new(base, pyramid, eye, near);
        while rings.len() <= near as usize {
            let d = rings.len() as u32;
            let mut ring = 0;
            crate::held::each_in_shell(rd, rule.eye, d, d, &mut |r| {
                ring += region_bytes(base, r);
            });
            rings.push(ring);
        }
        let level0: u64 = rings[..=near as usize].iter().sum();
        let coarse: u64 = groups
            .iter()
            .filter(|g| rule.holds_between(g.level, g.dmin, g.dmax))
            .map(|g| g.bytes)
            .sum();
        (rule, fixed + level0 + coarse)
    };
    let (rule, bytes) = bytes_at(0);
    if bytes > budget {
        return Err(BudgetError::TooSmall {
            budget,
            needed: bytes,
        });
    }
    let reach = rd.iter().max().copied().unwrap_or(0).min(max_near);
    let (mut lo, mut best) = (0u32, rule);
    let mut hi = reach;
    let mut step = 1u32;
    while step <= reach {
        let (rule, bytes) = bytes_at(step);
        if bytes > budget {
            hi = step - 1;
            break;
        }
        (lo, best) = (step, rule);
        step = step.saturating_mul(2);
    }
    while lo < hi {
        let mid = lo + (hi - lo).div_ceil(2);
        let (rule, bytes) = bytes_at(mid);
        if bytes <= budget {
            (lo, best) = (mid, rule);
        } else {
            hi = mid - 1;
        }
    }
    Ok((best, cost(base, pyramid, &best)))
}

/// Coarse bytes of one level whose bricks' regions lie from `dmin` to `dmax` regions from the
/// eye: whether a rule holds them depends on its `near` and on nothing else of the brick.
#[derive(Debug, Clone, Copy)]
struct Group {
    level: u32,
    dmin: u32,
    dmax: u32,
    bytes: u64,
}

/// The coarse bricks of every level up to `rule`'s top in [`Group`]s around its eye: one pass
/// over them, where each probe of [`fit`] walked every coarse brick again (about 2.6 million
/// on the 16k world, 13 probes: most of a join's fit).
fn coarse_groups(pyramid: &Pyramid, rd: [u32; 3], rule: Rule) -> Vec<Group> {
    let mut sums: rustc_hash::FxHashMap<(u32, u32, u32), u64> = Default::default();
    for k in MIN_STAND_IN_LEVEL..=rule.top {
        let Some(level) = pyramid.level(k) else {
            continue;
        };
        for (cell, _) in level.brick_cells() {
            if let Some((dmin, dmax)) = distances(rd, rule.eye, k, cell) {
                *sums.entry((k, dmin, dmax)).or_default() += coarse_bytes(pyramid, k, cell);
            }
        }
    }
    sums.into_iter()
        .map(|((level, dmin, dmax), bytes)| Group {
            level,
            dmin,
            dmax,
            bytes,
        })
        .collect()
}

/// Bytes of the coarse bricks `rule` holds, brick by brick ([`coarse_groups`] sums them once
/// for every `near`).
#[cfg(test)]
fn coarse_part(pyramid: &Pyramid, rd: [u32; 3], rule: &Rule) -> u64 {
    let mut bytes = 0;
    for k in MIN_STAND_IN_LEVEL..=rule.top {
        let Some(level) = pyramid.level(k) else {
            continue;
        };
        for (cell, _) in level.brick_cells() {
            if rule.holds(rd, k, cell) {
                bytes += coarse_bytes(pyramid, k, cell);
            }
        }
    }
    bytes
}

/// The map a client holding `rule`'s working set holds.
pub fn build(base: &BrickMap, pyramid: &Pyramid, rule: &Rule) -> Result<BrickMap, MapError> {
    pyramid.mixed(base, |r| rule.level_of(r))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::map::BrushMode;

    /// Ground and spheres of many colours in 13×2×10 regions (also `held`'s tests).
    pub(crate) fn scene() -> BrickMap {
        let mut map = BrickMap::new([400, 64, 300]).unwrap();
        map.fill_box([0, 0, 0], [399, 5, 299], BrushMode::Fill, Colour(0x4A69));
        for i in 0..30u32 {
            let c = [(i * 97) % 400, 6 + (i * 13) % 50, (i * 61) % 300];
            map.sphere(
                c.map(|v| v as f32),
                4.0 + (i % 7) as f32,
                BrushMode::Fill,
                Colour(i as u16 * 999),
            );
        }
        map
    }

    #[test]
    fn levels_grow_with_distance_and_stop_at_the_top() {
        let rule = Rule {
            eye: [10, 0, 10],
            near: 2,
            top: 6,
        };
        assert_eq!(rule.level_of([10, 0, 10]), 0);
        assert_eq!(rule.level_of([12, 1, 8]), 0);
        assert_eq!(rule.level_of([13, 0, 10]), 2);
        assert_eq!(rule.level_of([18, 0, 10]), 2); // 8 = 2·4
        assert_eq!(rule.level_of([19, 0, 10]), 3);
        assert_eq!(rule.level_of([10, 0, 42]), 4); // 32 = 2·16
        assert_eq!(rule.level_of([10, 0, 43]), 5);
        assert_eq!(rule.level_of([1000, 0, 10]), 6);
        let none = Rule { near: 0, ..rule };
        assert_eq!(none.level_of([11, 0, 10]), 2);
        assert_eq!(none.level_of([10, 0, 10]), 0);
    }

    /// The cost is what the built map takes (colour chunks as the map sizes them), and the fitted
    /// working set is the largest within the budget.
    #[test]
    fn grouped_coarse_bytes_equal_the_brick_by_brick_sum() {
        let base = scene();
        let pyramid = Pyramid::build(&base).unwrap();
        let rd = base.region_dims();
        for eye in [[0.0, 0.0, 0.0], [200.0, 10.0, 150.0], [399.0, 63.0, 10.0]] {
            let groups = coarse_groups(&pyramid, rd, Rule::new(&base, &pyramid, eye, 0));
            for near in [0, 1, 2, 3, 5, 8, 13, 100] {
                let rule = Rule::new(&base, &pyramid, eye, near);
                let grouped: u64 = groups
                    .iter()
                    .filter(|g| rule.holds_between(g.level, g.dmin, g.dmax))
                    .map(|g| g.bytes)
                    .sum();
                assert_eq!(
                    grouped,
                    coarse_part(&pyramid, rd, &rule),
                    "{eye:?} near {near}"
                );
            }
        }
    }

    #[test]
    fn cost_is_the_built_maps_size_and_fit_keeps_within_the_budget() {
        let base = scene();
        let pyramid = Pyramid::build(&base).unwrap();
        for near in [0, 1, 3, 20] {
            let rule = Rule::new(&base, &pyramid, [100.0, 30.0, 80.0], near);
            let c = cost(&base, &pyramid, &rule);
            let map = build(&base, &pyramid, &rule).unwrap();
            map.check_invariants().unwrap();
            assert_eq!(c.bytes, map.memory().total_bytes, "near {near}: {c:?}");
            assert_eq!(c.full_bricks, map.brick_count());
            assert_eq!(c.stand_ins, map.stand_in_count());
        }
        let whole = cost(&base, &pyramid, &Rule::new(&base, &pyramid, [0.0; 3], 100));
        let budget = whole.bytes / 3;
        let (rule, c) = fit(&base, &pyramid, [200.0, 10.0, 150.0], budget, 100).unwrap();
        assert!(c.bytes <= budget && rule.near < 100, "{rule:?} {c:?}");
        let next = cost(
            &base,
            &pyramid,
            &Rule {
                near: rule.near + 1,
                ..rule
            },
        );
        assert!(next.bytes > budget, "near {} would fit too", rule.near + 1);
        let small = fit(&base, &pyramid, [200.0, 10.0, 150.0], 1000, 100);
        assert!(matches!(
            small,
            Err(BudgetError::TooSmall { budget: 1000, .. })
        ));
    }

    /// Remembered region costs equal measured ones after edits, once the edited cells'
    /// regions are forgotten; a stale entry is what forgetting prevents.
    #[test]
    fn remembered_region_costs_follow_the_edits() {
        let mut base = scene();
        base.record_touched(true);
        base.take_touched();
        let costs = RegionCosts::new(base.region_dims());
        let d = base.region_dims();
        let every = || box_points([0, 0, 0], d);
        for r in every() {
            assert_eq!(costs.get(&base, r), region_bytes(&base, r));
        }
        base.sphere([100.0, 20.0, 100.0], 14.0, BrushMode::Fill, Colour(0x1234));
        base.sphere([300.0, 3.0, 200.0], 9.0, BrushMode::Erase, Colour(0));
        let touched = base.take_touched();
        let stale = every().filter(|&r| costs.get(&base, r) != region_bytes(&base, r));
        assert!(stale.count() > 0, "the edits change some regions' cost");
        costs.forget_cells(&base, &touched);
        for r in every() {
            assert_eq!(costs.get(&base, r), region_bytes(&base, r), "{r:?}");
        }
    }

    /// A rule's cost follows from the previous rule's and the two plans between them, for moves
    /// of the eye (shells) and changes of `near` (full passes) alike.
    #[test]
    fn costs_follow_moves_through_the_plans() {
        let base = scene();
        let pyramid = Pyramid::build(&base).unwrap();
        let rd = base.region_dims();
        let mut rule = Rule::new(&base, &pyramid, [30.0, 20.0, 40.0], 1);
        let mut bytes = cost(&base, &pyramid, &rule).bytes;
        let mut x: u32 = 7;
        for step in 0..60 {
            x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
            let eye = [(x >> 8) % 420, (x >> 4) % 70, (x >> 16) % 320];
            let near = if step % 9 == 0 {
                (x >> 20) % 4
            } else {
                rule.near
            };
            let next = if step % 3 == 0 {
                Rule::new(&base, &pyramid, eye.map(|v| v as f32), near)
            } else {
                // A step of a region or two.
                let e: [u32; 3] = std::array::from_fn(|i| {
                    (rule.eye[i] + (x >> (3 * i)) % 5)
                        .saturating_sub(2)
                        .min(rd[i] - 1)
                });
                Rule {
                    eye: e,
                    near,
                    ..rule
                }
            };
            let gained = plan_bytes(&base, &pyramid, &crate::held::plan(rd, Some(&rule), &next));
            let lost = plan_bytes(&base, &pyramid, &crate::held::plan(rd, Some(&next), &rule));
            bytes = bytes + gained - lost;
            rule = next;
            assert_eq!(
                bytes,
                cost(&base, &pyramid, &rule).bytes,
                "step {step}: {rule:?}"
            );
        }
    }
}
