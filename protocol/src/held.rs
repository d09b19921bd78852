//! What a client holds of a world, and how it follows the eye (issue #30).
//!
//! [`Rule`] says at which level each region is *wanted*. [`Held`] is the client's side: its mixed
//! map (what both tracers read and the GPU mirrors), the level each region *shows*, and the
//! coarse bricks it holds. When the rule changes (the eye crossed into another region, or the
//! budget changed), [`Held::retarget`] at once switches every region whose wanted data is
//! already held and returns the [`Plan`]: what the server must send. [`plan`] gives the same
//! answer from the two rules alone, and [`Rule::holds`] says in constant time whether a coarse
//! brick is wanted, so the server knows what each client holds without a copy of it, and sends
//! a delta for a brick exactly when the client holds it.
//!
//! **Eviction is implied, and never leaves a hole while the eye flies**: a region keeps showing
//! what it shows until the data it now wants is in place; then its level-0 bricks are dropped
//! (or it stops pointing at a coarse brick), and a coarse brick no region shows or wants is
//! freed. After a *jump* (the eye moved more than [`SHELL_MOVE`] regions), level 0 no longer
//! wanted is dropped at once, so the copy does not hold two working sets' level 0 while the
//! new one streams in: those regions are empty until their coarse brick arrives. Data that
//! arrives for something no longer wanted is ignored.
//!
//! Messages are handled in the order the server sent them: region data is a region's whole
//! level 0 as it stands when sent; a coarse brick or a level-0 brick is the brick as it stands.
//! So a delta sent after the data it changes applies to it, and data sent after a delta already
//! includes it.

use std::collections::BTreeSet;

use crate::brick::{BrickData, Mask};
use crate::colour::Colour;
use crate::map::{BrickMap, MIN_STAND_IN_LEVEL, MapError, REGION_CELLS, box_points, coarse_cell};
use crate::wire::BrickRef;
use crate::working_set::Rule;

mod table;
use table::{Coarse, CoarseTable};

/// What the server must send when the rule changes: everything wanted that is not held.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Plan {
    /// Regions wanted at level 0 that were not: each region's level-0 bricks, all of them.
    pub regions: Vec<[u32; 3]>,
    /// Coarse bricks `(level, cell)` wanted that were not (each may turn out empty).
    pub coarse: Vec<(u32, [u32; 3])>,
}

impl Plan {
    pub fn is_empty(&self) -> bool {
        self.regions.is_empty() && self.coarse.is_empty()
    }
}

/// What a client must be sent when its rule changes from `old` (`None`: it holds nothing) to
/// `new`, for a grid of `region_dims` regions: the regions whose level changed to 0, nearest
/// first, and the coarse bricks regions changed to that the old rule did not hold. When the eye
/// moved a region or two under the same `near`, only the shells of regions around each level's
/// boundary distance are visited ([`each_candidate`]); otherwise every region.
pub fn plan(region_dims: [u32; 3], old: Option<&Rule>, new: &Rule) -> Plan {
    if !shells_apply(old, new) {
        return plan_whole(region_dims, old, new);
    }
    let mut regions = Vec::new();
    let mut coarse = BTreeSet::new();
    each_candidate(region_dims, old, new, |r| {
        let k = new.level_of(r);
        if old.is_some_and(|o| o.level_of(r) == k) {
            // Same level: held already (the old rule wanted this very region there).
            return;
        }
        if k == 0 {
            regions.push(r);
        } else if !old.is_some_and(|o| o.holds(region_dims, k, coarse_cell(r, k))) {
            coarse.insert((k, coarse_cell(r, k)));
        }
    });
    regions.sort_unstable_by_key(|&r| (chebyshev(r, new.eye), r[2], r[1], r[0]));
    Plan {
        regions,
        coarse: coarse.into_iter().collect(),
    }
}

/// [`plan`] for a jump, a first rule or a new `near`, without visiting every region: level 0 is
/// the box of regions within `near` of the eye, and a coarse brick is wanted now and was not
/// exactly when the new rule [`Rule::holds`] it and the old one does not (a region under it at
/// that level whose old level was the same would have made the old rule hold it), so each
/// level's cells are checked in constant time each.
fn plan_whole(dims: [u32; 3], old: Option<&Rule>, new: &Rule) -> Plan {
    let (lo, hi) = new.level_0_box(dims);
    let mut regions: Vec<[u32; 3]> = box_points(lo, hi)
        .filter(|&r| old.is_none_or(|o| o.level_of(r) != 0))
        .collect();
    regions.sort_unstable_by_key(|&r| (chebyshev(r, new.eye), r[2], r[1], r[0]));
    // Visited in the order the plan lists them, (level, x, y, z) ascending, so nothing is
    // sorted afterwards (a first rule on a 16k world lists about a million coarse cells).
    let mut coarse = Vec::new();
    for k in MIN_STAND_IN_LEVEL..=new.top {
        let span = 1u32 << (k - MIN_STAND_IN_LEVEL);
        let cells = dims.map(|d| d.div_ceil(span));
        for x in 0..cells[0] {
            for y in 0..cells[1] {
                for z in 0..cells[2] {
                    let cell = [x, y, z];
                    if new.holds(dims, k, cell) && !old.is_some_and(|o| o.holds(dims, k, cell)) {
                        coarse.push((k, cell));
                    }
                }
            }
        }
    }
    debug_assert!(coarse.is_sorted());
    Plan { regions, coarse }
}

/// Whether a move from `old` to `new` can be planned from the shells around level boundaries:
/// the same `near` and top, and an eye that moved at most [`SHELL_MOVE`] regions.
fn shells_apply(old: Option<&Rule>, new: &Rule) -> bool {
    old.is_some_and(|o| {
        o.near == new.near && o.top == new.top && chebyshev(o.eye, new.eye) <= SHELL_MOVE
    })
}

/// Chebyshev distance between two regions.
fn chebyshev(a: [u32; 3], b: [u32; 3]) -> u32 {
    (0..3).map(|i| a[i].abs_diff(b[i])).max().unwrap_or(0)
}

/// Eye moves of at most this many regions (Chebyshev) under the same `near` visit only shells.
const SHELL_MOVE: u32 = 2;

/// Calls `f` once for each region whose level may differ between `old` and `new` (a superset of
/// those whose level does). A region's distance to the eye changes by at most the eye's move
/// `m`, so under the same `near` its level can change only if its new distance lies within `m`
/// of a level's boundary distance: those shells are visited. Anything else visits every region.
fn each_candidate(dims: [u32; 3], old: Option<&Rule>, new: &Rule, mut f: impl FnMut([u32; 3])) {
    let m = old.map(|o| chebyshev(o.eye, new.eye));
    if !shells_apply(old, new) {
        box_points([0; 3], dims).for_each(f);
        return;
    }
    let m = m.unwrap_or(0);
    if m == 0 {
        return;
    }
    // Boundary distances: level 0 up to `near`, level k up to near·2^k below the top.
    let n = new.near.max(1);
    let mut bounds = vec![new.near];
    bounds.extend((MIN_STAND_IN_LEVEL..new.top).map(|k| n.saturating_mul(1 << k)));
    let reach = dims.iter().max().copied().unwrap_or(0);
    let mut ranges: Vec<(u32, u32)> = bounds
        .into_iter()
        .map(|t| ((t + 1).saturating_sub(m), t.saturating_add(m)))
        .filter(|&(a, _)| a <= reach)
        .collect();
    ranges.sort_unstable();
    // Merge overlapping ranges so no region is visited twice.
    let mut merged: Vec<(u32, u32)> = Vec::new();
    for (a, b) in ranges {
        match merged.last_mut() {
            Some(last) if a <= last.1.saturating_add(1) => last.1 = last.1.max(b),
            _ => merged.push((a, b)),
        }
    }
    for (a, b) in merged {
        each_in_shell(dims, new.eye, a, b, &mut f);
    }
}

/// Calls `f` for each region of the grid whose Chebyshev distance from `e` is in `a..=b`.
pub(crate) fn each_in_shell(
    dims: [u32; 3],
    e: [u32; 3],
    a: u32,
    b: u32,
    f: &mut impl FnMut([u32; 3]),
) {
    let lo = |i: usize| e[i].saturating_sub(b);
    let hi = |i: usize| e[i].saturating_add(b).min(dims[i] - 1);
    for z in lo(2)..=hi(2) {
        for y in lo(1)..=hi(1) {
            if z.abs_diff(e[2]).max(y.abs_diff(e[1])) >= a {
                for x in lo(0)..=hi(0) {
                    f([x, y, z]);
                }
            } else {
                // Only |dx| in a..=b: a segment on each side.
                if e[0] >= a {
                    for x in lo(0)..=e[0] - a {
                        f([x, y, z]);
                    }
                }
                let start = e[0].saturating_add(a);
                if start <= hi(0) {
                    for x in start..=hi(0) {
                        f([x, y, z]);
                    }
                }
            }
        }
    }
}

/// A brick as [`Held`] receives it: owned ([`BrickData`]), or straight from a wire blob
/// ([`BrickRef`]: stored with the colour block it travelled in, not coded again).
pub trait Incoming {
    fn cell(&self) -> [u32; 3];
    fn mask(&self) -> &Mask;
    fn colours(&self) -> &[Colour];
    /// Whether `map` can take it (inside the scene, consistent).
    fn check(&self, map: &BrickMap) -> Result<(), MapError>;
    /// Stores it as a level-0 brick of `map`.
    fn put(&self, map: &mut BrickMap) -> Result<(), MapError>;
    /// Stores it as a coarse brick of `map` ([`BrickMap::add_coarse`]); returns its slot.
    fn add_coarse(&self, map: &mut BrickMap) -> Result<u32, MapError>;
}

impl Incoming for BrickData {
    fn cell(&self) -> [u32; 3] {
        self.cell
    }
    fn mask(&self) -> &Mask {
        &self.mask
    }
    fn colours(&self) -> &[Colour] {
        &self.colours
    }
    fn check(&self, map: &BrickMap) -> Result<(), MapError> {
        map.check_brick(self)
    }
    fn put(&self, map: &mut BrickMap) -> Result<(), MapError> {
        map.put_brick(self)
    }
    fn add_coarse(&self, map: &mut BrickMap) -> Result<u32, MapError> {
        map.add_coarse(self.mask, &self.colours)
    }
}

impl Incoming for BrickRef<'_> {
    fn cell(&self) -> [u32; 3] {
        self.cell
    }
    fn mask(&self) -> &Mask {
        &self.mask
    }
    fn colours(&self) -> &[Colour] {
        BrickRef::colours(self)
    }
    fn check(&self, map: &BrickMap) -> Result<(), MapError> {
        map.check_parts(self.cell, &self.mask, BrickRef::colours(self))
    }
    fn put(&self, map: &mut BrickMap) -> Result<(), MapError> {
        map.put_coded(self.cell, self.mask, BrickRef::colours(self), self.block())
    }
    fn add_coarse(&self, map: &mut BrickMap) -> Result<u32, MapError> {
        map.add_coarse_coded(self.mask, BrickRef::colours(self), self.block())
    }
}

/// A region that shows nothing yet.
const NOTHING: u8 = u8::MAX;

/// The client's working set: what it shows where, kept beside the map it fills (the
/// replica's), which every method takes.
#[derive(Debug, Clone)]
pub struct Held {
    rule: Option<Rule>,
    region_dims: [u32; 3],
    /// Per region (linear index): the level it shows, or [`NOTHING`].
    shown: Vec<u8>,
    coarse: CoarseTable,
    /// Regions a coarse brick is about to be shown in (kept to save an allocation per brick).
    scratch: Vec<[u32; 3]>,
}

impl Held {
    /// Nothing held yet of the scene `map` (an empty map) will hold.
    pub fn new(map: &BrickMap) -> Held {
        let region_dims = map.region_dims();
        let regions = region_dims.iter().map(|&d| d as usize).product();
        Held {
            rule: None,
            region_dims,
            shown: vec![NOTHING; regions],
            coarse: CoarseTable::new(region_dims),
            scratch: Vec::new(),
        }
    }

    pub fn rule(&self) -> Option<&Rule> {
        self.rule.as_ref()
    }

    /// The level region `r` shows; `None` while it shows nothing yet (or outside the grid).
    pub fn shown_level(&self, r: [u32; 3]) -> Option<u32> {
        let i = self.index(r)?;
        (self.shown[i] != NOTHING).then(|| u32::from(self.shown[i]))
    }

    /// Whether moving to `rule` is a jump (or the first rule): most of what the copy shows
    /// changes, and much of it is new.
    pub fn is_jump(&self, rule: &Rule) -> bool {
        self.rule
            .is_none_or(|o| chebyshev(o.eye, rule.eye) > SHELL_MOVE)
    }

    /// Coarse bricks held (empty ones included).
    pub fn coarse_count(&self) -> usize {
        self.coarse.len()
    }

    fn index(&self, r: [u32; 3]) -> Option<usize> {
        let d = self.region_dims;
        (0..3)
            .all(|i| r[i] < d[i])
            .then(|| (r[0] + d[0] * (r[1] + d[1] * r[2])) as usize)
    }

    /// Adopts `rule`: regions whose wanted data is held switch now (a coarse brick they let go
    /// of is freed once nothing shows or wants it). Returns what the server must send
    /// ([`plan`]).
    pub fn retarget(&mut self, map: &mut BrickMap, rule: Rule) -> Result<Plan, MapError> {
        let plan = plan(self.region_dims, self.rule.as_ref(), &rule);
        // Room for what comes at once (a first rule brings hundreds of thousands: growing the
        // table step by step rehashed it again and again).
        self.coarse.reserve(plan.coarse.len());
        let jump = self.is_jump(&rule);
        let old = self.rule.replace(rule);
        // Only regions whose level changed can switch now; the others wait for their data.
        let mut switch = Vec::new();
        let mut release = Vec::new();
        each_candidate(self.region_dims, old.as_ref(), &rule, |r| {
            let k = rule.level_of(r);
            let shown = self.shown_level(r);
            if k != 0
                && shown != Some(k)
                && !self.coarse.is_empty()
                && self.coarse.contains_key(&(k, coarse_cell(r, k)))
            {
                switch.push((r, k));
            } else if jump && k != 0 && shown == Some(0) {
                release.push(r);
            }
        });
        for (r, k) in switch {
            self.show_coarse(map, r, k)?;
        }
        // After a jump most of level 0 is let go of: it goes now, so the new level 0 reuses
        // its room and the copy never holds two working sets' worth of it.
        for r in release {
            self.detach(map, r)?;
        }
        map.prune_tombstones(u64::MAX);
        Ok(plan)
    }

    /// Region `r`'s level-0 bricks, all of them (none: the region is empty at level 0). Ignored
    /// unless the rule wants `r` at level 0. Bricks outside `r` are refused.
    pub fn receive_region<B: Incoming>(
        &mut self,
        map: &mut BrickMap,
        r: [u32; 3],
        bricks: &[B],
    ) -> Result<(), MapError> {
        let Some(rule) = self.rule else { return Ok(()) };
        if self.index(r).is_none() || rule.level_of(r) != 0 {
            return Ok(());
        }
        if let Some(b) = bricks
            .iter()
            .find(|b| (0..3).any(|i| b.cell()[i] / REGION_CELLS != r[i]))
        {
            return Err(MapError::OutsideRegion {
                cell: b.cell(),
                region: r,
            });
        }
        for b in bricks {
            b.check(map)?;
        }
        self.detach(map, r)?;
        for b in bricks {
            b.put(map)?;
        }
        let i = self.index(r).unwrap_or(0);
        self.shown[i] = 0;
        Ok(())
    }

    /// A coarse brick, as it stands (`None`: empty). Stored when the rule wants it or regions
    /// still show an older copy of it; the regions that want it switch to it.
    pub fn receive_coarse<B: Incoming>(
        &mut self,
        map: &mut BrickMap,
        level: u32,
        cell: [u32; 3],
        brick: Option<&B>,
    ) -> Result<(), MapError> {
        let Some(rule) = self.rule else { return Ok(()) };
        let key = (level, cell);
        let wanted = rule.holds(self.region_dims, level, cell);
        // Neither wanted nor held: ignored before anything is counted (a level outside the
        // stand-in levels, or a cell far outside the grid, names no regions to visit).
        if !wanted && !self.coarse.contains_key(&key) {
            return Ok(());
        }
        let add = |map: &mut BrickMap| match brick {
            Some(b) => b.add_coarse(map).map(Some),
            None => Ok(None),
        };
        let (lo, hi) = self.regions_under(level, cell);
        // A brick not held yet (most of a first working set: about a million coarse cells on
        // the 16k world) is stored with the count of regions about to show it, which are
        // listed once.
        let mut to_show = std::mem::take(&mut self.scratch);
        to_show.clear();
        to_show.extend(
            box_points(lo, hi)
                .filter(|&r| rule.level_of(r) == level && self.shown_level(r) != Some(level)),
        );
        let count = to_show.len() as u32;
        let (slot, held) = match self.coarse.get_mut(&key) {
            Some(entry) => {
                // A newer copy: the regions showing the old one show the new one.
                let slot = add(map)?;
                let old = std::mem::replace(&mut entry.slot, slot);
                for r in box_points(lo, hi) {
                    if self.shown_level(r) == Some(level) {
                        map.set_stand_in(r, slot.map(|s| (level, s)))?;
                    }
                }
                if let Some(old) = old {
                    map.remove_coarse(old)?;
                }
                (slot, true)
            }
            // Wanted (neither wanted nor held returned above).
            None => {
                let slot = add(map)?;
                self.coarse.insert(
                    key,
                    Coarse {
                        slot,
                        shown_by: count,
                    },
                );
                (slot, false)
            }
        };
        // Clearance is lowered once around the brick's regions, not around each of them.
        map.defer_region_clearance();
        let (mut shown, mut result) = (0, Ok(()));
        for &r in &to_show {
            result = self.show_slot(map, r, level, slot);
            if result.is_err() {
                break;
            }
            shown += 1;
        }
        self.scratch = to_show;
        // A brick stored just now was counted then: only a failure changes its count.
        let unused = if held || shown != count {
            self.coarse.get_mut(&key).is_some_and(|c| {
                c.shown_by = if held { c.shown_by + shown } else { shown };
                held && c.shown_by == 0
            })
        } else {
            false
        };
        map.lower_deferred_region_clearance();
        result?;
        if !wanted && unused {
            self.free_coarse(map, key)?;
        }
        Ok(())
    }

    /// A level-0 brick as it stands, or `None` for a cell whose brick went: applied where the
    /// client shows and wants the cell's region at level 0, ignored elsewhere.
    pub fn receive_brick<B: Incoming>(
        &mut self,
        map: &mut BrickMap,
        cell: [u32; 3],
        brick: Option<&B>,
    ) -> Result<(), MapError> {
        let Some(rule) = self.rule else { return Ok(()) };
        let r = cell.map(|c| c / REGION_CELLS);
        if self.shown_level(r) != Some(0) || rule.level_of(r) != 0 {
            return Ok(());
        }
        match brick {
            Some(b) if b.cell() == cell => b.put(map),
            Some(b) => Err(MapError::OutsideRegion {
                cell: b.cell(),
                region: r,
            }),
            None => {
                map.remove_brick(cell);
                Ok(())
            }
        }
    }

    /// Regions under a level-`level` coarse cell, inside the grid.
    fn regions_under(&self, level: u32, cell: [u32; 3]) -> ([u32; 3], [u32; 3]) {
        let span = 1u32 << (level - MIN_STAND_IN_LEVEL);
        let d = self.region_dims;
        let lo = cell.map(|c| c.saturating_mul(span));
        let hi: [u32; 3] = std::array::from_fn(|i| lo[i].saturating_add(span).min(d[i]));
        (lo, hi)
    }

    /// Region `r` shows the held coarse brick of level `level` over it.
    fn show_coarse(&mut self, map: &mut BrickMap, r: [u32; 3], level: u32) -> Result<(), MapError> {
        let key = (level, coarse_cell(r, level));
        let Some(slot) = self.coarse.get(&key).map(|c| c.slot) else {
            return Ok(());
        };
        self.show_slot(map, r, level, slot)?;
        if let Some(c) = self.coarse.get_mut(&key) {
            c.shown_by += 1;
        }
        Ok(())
    }

    /// Region `r` shows the held level-`level` brick over it, in `slot` (`None`: empty); the
    /// caller counts it in the brick's `shown_by`. `r` must not show that brick already.
    fn show_slot(
        &mut self,
        map: &mut BrickMap,
        r: [u32; 3],
        level: u32,
        slot: Option<u32>,
    ) -> Result<(), MapError> {
        self.detach(map, r)?;
        if let Some(slot) = slot {
            map.set_stand_in(r, Some((level, slot)))?;
        }
        let i = self.index(r).unwrap_or(0);
        self.shown[i] = level as u8;
        Ok(())
    }

    /// Region `r` stops showing what it shows: its level-0 bricks go, or it lets go of its
    /// coarse brick (freed when nothing shows or wants it).
    fn detach(&mut self, map: &mut BrickMap, r: [u32; 3]) -> Result<(), MapError> {
        let Some(i) = self.index(r) else {
            return Ok(());
        };
        match self.shown[i] {
            NOTHING => {}
            0 => {
                for cell in map.region_cells(r) {
                    map.remove_brick(cell);
                }
            }
            level => {
                let level = u32::from(level);
                map.set_stand_in(r, None)?;
                let key = (level, coarse_cell(r, level));
                let mut unused = false;
                if let Some(c) = self.coarse.get_mut(&key) {
                    c.shown_by = c.shown_by.saturating_sub(1);
                    unused = c.shown_by == 0;
                }
                let wanted = self
                    .rule
                    .is_some_and(|rule| rule.holds(self.region_dims, key.0, key.1));
                if unused && !wanted {
                    self.free_coarse(map, key)?;
                }
            }
        }
        self.shown[i] = NOTHING;
        Ok(())
    }

    /// Packs `map`'s arrays ([`BrickMap::compact`]) and follows its coarse bricks to their
    /// new slots.
    pub fn compact(&mut self, map: &mut BrickMap) -> crate::map::Compacted {
        let moved = map.compact();
        for c in self.coarse.values_mut() {
            c.slot = c.slot.and_then(|s| moved.slot(s));
        }
        moved
    }

    fn free_coarse(&mut self, map: &mut BrickMap, key: (u32, [u32; 3])) -> Result<(), MapError> {
        if let Some(Coarse {
            slot: Some(slot), ..
        }) = self.coarse.remove(&key)
        {
            map.remove_coarse(slot)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::lod::Pyramid;
    use crate::map::BrushMode;
    use crate::working_set;

    use crate::working_set::tests::scene;

    struct Rng(u64);
    impl Rng {
        fn below(&mut self, n: u32) -> u32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 33) % u64::from(n)) as u32
        }
    }

    /// Sends what `plan` asks for, from the server's map and pyramid.
    fn fulfil(
        held: &mut Held,
        map: &mut BrickMap,
        plan: &Plan,
        base: &BrickMap,
        pyramid: &Pyramid,
    ) {
        for &r in &plan.regions {
            let bricks: Vec<_> = base.region_cells(r).filter_map(|c| base.brick(c)).collect();
            held.receive_region(map, r, &bricks).unwrap();
        }
        for &(k, cell) in &plan.coarse {
            let brick = pyramid.level(k).unwrap().brick(cell);
            held.receive_coarse(map, k, cell, brick.as_ref()).unwrap();
        }
    }

    /// The held map shows what a map built afresh for the rule shows, region by region.
    fn assert_same(map: &BrickMap, built: &BrickMap, step: usize) {
        map.check_invariants().unwrap();
        assert_eq!(map.brick_count(), built.brick_count(), "step {step}");
        assert_eq!(map.stand_in_count(), built.stand_in_count(), "step {step}");
        for (brick, _) in built.bricks() {
            assert_eq!(map.brick(brick.cell), Some(brick.clone()), "step {step}");
        }
        let rd = built.region_dims();
        let mut scratch_a = [Colour::BLACK; 512];
        let mut scratch_b = [Colour::BLACK; 512];
        for z in 0..rd[2] {
            for y in 0..rd[1] {
                for x in 0..rd[0] {
                    let r = [x, y, z];
                    match (map.stand_in(r), built.stand_in(r)) {
                        (None, None) => {}
                        (Some((ka, sa)), Some((kb, sb))) => {
                            assert_eq!(ka, kb, "step {step}, region {r:?}");
                            assert_eq!(map.masks()[sa as usize], built.masks()[sb as usize]);
                            assert_eq!(
                                map.slot_colours(sa, &mut scratch_a),
                                built.slot_colours(sb, &mut scratch_b),
                                "step {step}, region {r:?}"
                            );
                        }
                        other => panic!("step {step}, region {r:?}: {other:?}"),
                    }
                }
            }
        }
    }

    #[test]
    fn holds_is_whether_a_region_under_the_cell_wants_that_level() {
        let base = scene();
        let pyramid = Pyramid::build(&base).unwrap();
        let rd = base.region_dims();
        let mut rng = Rng(5);
        for _ in 0..30 {
            let eye = [
                rng.below(500) as f32 - 50.0,
                30.0,
                rng.below(400) as f32 - 50.0,
            ];
            let rule = Rule::new(&base, &pyramid, eye, rng.below(4));
            for k in 2..=rule.top {
                let cells = crate::lod::level_size(base.size(), k).map(|s| s.div_ceil(8));
                for cz in 0..cells[2] {
                    for cy in 0..cells[1] {
                        for cx in 0..cells[0] {
                            let cell = [cx, cy, cz];
                            let span = 1 << (k - 2);
                            let mut any = false;
                            for z in cz * span..((cz + 1) * span).min(rd[2]) {
                                for y in cy * span..((cy + 1) * span).min(rd[1]) {
                                    for x in cx * span..((cx + 1) * span).min(rd[0]) {
                                        any |= rule.level_of([x, y, z]) == k;
                                    }
                                }
                            }
                            assert_eq!(rule.holds(rd, k, cell), any, "{rule:?} {k} {cell:?}");
                        }
                    }
                }
            }
        }
    }

    /// A client following a wandering eye while people edit: after each move (and the data its
    /// plan asked for) and after each edit (and the deltas for what it holds), its map is the
    /// map built afresh for its rule; while data is in flight no region goes blank; a repeated
    /// rule asks for nothing; coarse bricks nothing wants are freed; packing the arrays on the
    /// way changes nothing it shows.
    #[test]
    fn following_the_eye_and_the_edits_keeps_the_map_equal_to_a_fresh_build() {
        let mut base = scene();
        base.record_touched(true);
        base.take_touched();
        let mut pyramid = Pyramid::build(&base).unwrap();
        let mut map = BrickMap::new(base.size()).unwrap();
        let mut held = Held::new(&map);
        let rd = base.region_dims();
        let mut rng = Rng(11);
        let mut eye = [200.0f32, 40.0, 150.0];
        for step in 0..16 {
            // Move: mostly a region or two, sometimes a jump; the budget changes now and then.
            if step % 5 == 4 {
                eye = [rng.below(400) as f32, 40.0, rng.below(300) as f32];
            } else {
                eye[0] = (eye[0] + rng.below(90) as f32 - 45.0).clamp(0.0, 399.0);
                eye[2] = (eye[2] + rng.below(90) as f32 - 45.0).clamp(0.0, 299.0);
            }
            let near = if step % 3 == 0 {
                rng.below(4)
            } else {
                held.rule().map_or(1, |r| r.near)
            };
            let rule = Rule::new(&base, &pyramid, eye, near);
            let showing = |held: &Held| {
                (0..rd[0] * rd[1] * rd[2])
                    .filter(|&i| {
                        let r = [i % rd[0], i / rd[0] % rd[1], i / rd[0] / rd[1]];
                        held.shown_level(r).is_some()
                    })
                    .count()
            };
            let before = showing(&held);
            let flight = held
                .rule()
                .is_some_and(|o| chebyshev(o.eye, rule.eye) <= SHELL_MOVE);
            let plan = held.retarget(&mut map, rule).unwrap();
            if flight {
                assert!(showing(&held) >= before, "step {step}: a region went blank");
            }
            fulfil(&mut held, &mut map, &plan, &base, &pyramid);
            if step % 2 == 1 {
                // Packed now and then: it gives back exactly the free room, and everything
                // after (more moves, deltas, freed coarse bricks) goes on from the new slots.
                let free = map.free_bytes();
                let moved = held.compact(&mut map);
                assert_eq!(moved.bytes_after, moved.bytes_before - free, "step {step}");
                assert_eq!(map.free_bytes(), 0, "step {step}");
            }
            assert!(
                held.retarget(&mut map, rule).unwrap().is_empty(),
                "step {step}"
            );
            let built = working_set::build(&base, &pyramid, &rule).unwrap();
            assert_same(&map, &built, step);
            // Every coarse brick held is wanted, and the solid ones are those a build holds.
            let cost = working_set::cost(&base, &pyramid, &rule);
            assert!(
                held.coarse
                    .iter()
                    .all(|((k, cell), _)| rule.holds(rd, k, cell)),
                "step {step}: coarse bricks held that nothing wants"
            );
            let solid = held.coarse.iter().filter(|(_, c)| c.slot.is_some()).count();
            assert_eq!(solid as u64, cost.coarse_bricks, "step {step}");

            // Someone edits: a sphere anywhere; deltas for what the client holds.
            let c = [rng.below(400), rng.below(60), rng.below(300)];
            let mode = if rng.below(2) == 0 {
                BrushMode::Fill
            } else {
                BrushMode::Erase
            };
            base.sphere(
                c.map(|v| v as f32),
                2.0 + rng.below(10) as f32,
                mode,
                Colour(rng.below(60000) as u16),
            );
            let touched = base.take_touched();
            let changed = pyramid.update(&base, &touched).unwrap();
            for &i in &touched {
                let cell = base.cell_coords(i);
                held.receive_brick(&mut map, cell, base.brick(cell).as_ref())
                    .unwrap();
            }
            for (k0, cells) in changed.iter().enumerate() {
                let k = k0 as u32 + 1;
                let Some(level) = pyramid.level(k) else {
                    continue;
                };
                for &i in cells {
                    let cell = level.cell_coords(i);
                    if k >= 2 && rule.holds(rd, k, cell) {
                        held.receive_coarse(&mut map, k, cell, level.brick(cell).as_ref())
                            .unwrap();
                    }
                }
            }
            let built = working_set::build(&base, &pyramid, &rule).unwrap();
            assert_same(&map, &built, step);
        }
    }

    /// The plan from a full pass over every region, the reference for the shells.
    fn plan_everywhere(dims: [u32; 3], old: Option<&Rule>, new: &Rule) -> Plan {
        let mut regions = Vec::new();
        let mut coarse = BTreeSet::new();
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let r = [x, y, z];
                    let k = new.level_of(r);
                    if k == 0 {
                        if old.is_none_or(|o| o.level_of(r) != 0) {
                            regions.push(r);
                        }
                    } else if !old.is_some_and(|o| o.holds(dims, k, coarse_cell(r, k))) {
                        coarse.insert((k, coarse_cell(r, k)));
                    }
                }
            }
        }
        regions.sort_unstable_by_key(|&r| (chebyshev(r, new.eye), r[2], r[1], r[0]));
        Plan {
            regions,
            coarse: coarse.into_iter().collect(),
        }
    }

    #[test]
    fn plans_from_shells_equal_plans_from_every_region() {
        let mut rng = Rng(3);
        for case in 0..400 {
            let dims = [1 + rng.below(40), 1 + rng.below(6), 1 + rng.below(40)];
            let top = 2 + rng.below(6);
            let near = rng.below(6);
            let old = Rule {
                eye: [rng.below(dims[0]), rng.below(dims[1]), rng.below(dims[2])],
                near,
                top,
            };
            let step = |rng: &mut Rng, c: u32, d: u32| {
                (c + rng.below(2 * SHELL_MOVE + 1))
                    .saturating_sub(SHELL_MOVE)
                    .min(d - 1)
            };
            let new = Rule {
                eye: [
                    step(&mut rng, old.eye[0], dims[0]),
                    step(&mut rng, old.eye[1], dims[1]),
                    step(&mut rng, old.eye[2], dims[2]),
                ],
                near: if case % 7 == 0 { rng.below(6) } else { near },
                top,
            };
            assert_eq!(
                plan(dims, Some(&old), &new),
                plan_everywhere(dims, Some(&old), &new),
                "case {case}: {old:?} → {new:?} in {dims:?}"
            );
            // A jump anywhere, and a first rule.
            let far = Rule {
                eye: [rng.below(dims[0]), rng.below(dims[1]), rng.below(dims[2])],
                ..new
            };
            assert_eq!(
                plan(dims, Some(&old), &far),
                plan_everywhere(dims, Some(&old), &far),
                "case {case}: {old:?} → {far:?} in {dims:?}"
            );
            assert_eq!(plan(dims, None, &far), plan_everywhere(dims, None, &far));
        }
    }

    #[test]
    fn data_for_what_is_not_wanted_is_ignored_and_bad_data_refused() {
        let base = scene();
        let pyramid = Pyramid::build(&base).unwrap();
        let mut map = BrickMap::new(base.size()).unwrap();
        let mut held = Held::new(&map);
        let brick = base.bricks().next().unwrap().0;
        // Before any rule: nothing is wanted.
        held.receive_brick(&mut map, brick.cell, Some(&brick))
            .unwrap();
        assert_eq!(map.brick_count(), 0);
        let rule = Rule::new(&base, &pyramid, [10.0, 10.0, 10.0], 0);
        held.retarget(&mut map, rule).unwrap();
        // A region far away is not wanted at level 0.
        let far = [12, 0, 9];
        assert_ne!(rule.level_of(far), 0);
        held.receive_region::<BrickData>(&mut map, far, &[])
            .unwrap();
        assert_eq!(held.shown_level(far), None);
        // Bricks of another region are refused.
        let r = [0, 0, 0];
        assert_eq!(rule.level_of(r), 0);
        let stranger = BrickData {
            cell: [5, 0, 0],
            ..brick.clone()
        };
        assert!(held.receive_region(&mut map, r, &[stranger]).is_err());
        assert_eq!(held.shown_level(r), None);
        map.check_invariants().unwrap();
    }
}
