//! The CPU ray tracer: Amanatides–Woo DDA through regions, coarse cells and voxels.
//!
//! It follows the paper's appendix (AABB entry, start cell, step, tMax) with two changes that make
//! it exact and let the hierarchy agree with a flat voxel DDA on every ray, not just most:
//!
//! * **Boundary times are computed, never accumulated.** The time at which the ray crosses plane
//!   `p` on axis `i` is always `(p - o[i]) * inv[i]` in `f32`. Adding `tDelta` repeatedly drifts,
//!   and drifts differently depending on where a level started, which is how hierarchical DDAs
//!   end up disagreeing with themselves on grazing rays.
//! * **Events have one total order.** Crossings are ordered by time, ties broken by axis (x before
//!   y before z). Skipping an empty region or cell jumps straight to its exit event; the other
//!   axes are then settled to "every crossing ordered before that event has happened". Because
//!   coarse planes are a subset of voxel planes with the same times, the skip lands exactly where
//!   stepping voxel by voxel would have.
//!
//! The GPU tracer in `shaders/trace.wgsl` is a line-by-line twin of this file.

use crate::brick::{BRICK_EDGE, mask_get, rank, voxel_bit};
use crate::colour::Colour;
use crate::map::{
    BrickMap, CELLS_PER_BLOCK, REGION_CELLS, REGION_EDGE, cell_clearance, cell_is_empty,
    region_clearance, region_is_empty, region_stand_in,
};

/// Direction components smaller than this are treated as zero, so `1/d` stays finite (GPUs flush
/// subnormals, and the CPU must do the same thing).
pub const MIN_DIRECTION: f32 = 1e-30;

/// A ray in voxel units: the scene spans `0..size` on each axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: [f32; 3],
    /// Need not be normalised: hit distances are in units of its length.
    pub dir: [f32; 3],
}

/// Where a ray first meets a solid voxel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub voxel: [u32; 3],
    pub colour: Colour,
    /// Unit normal of the face the ray entered through, from the last step axis. Zero when the
    /// ray starts inside the voxel it hits.
    pub normal: [i32; 3],
    /// Ray parameter at which the ray enters the voxel (0 when it starts inside it).
    pub t: f32,
    /// The empty voxel the ray came from, where "place" puts a new voxel (paper 3.3). `None` when
    /// the ray starts inside the hit voxel or enters the grid straight into it.
    pub previous: Option<[u32; 3]>,
}

/// Counters for benchmarks and tests of empty-space skipping.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TraceStats {
    pub region_skips: u32,
    pub cell_skips: u32,
    pub voxel_steps: u32,
}

/// Per-ray constants and the DDA state.
struct Dda {
    o: [f32; 3],
    d: [f32; 3],
    inv: [f32; 3],
    step: [i32; 3],
    /// 1 on axes the ray moves up on, else 0: the exit plane of block `b` is `b + off` blocks up.
    off: [i32; 3],
    n: [i32; 3],
    /// Current voxel.
    v: [i32; 3],
    /// Time of the next voxel-plane crossing per axis (infinite on axes the ray does not move on).
    next: [f32; 3],
    /// Time and axis of the event that brought the ray into `v`, if any.
    t: f32,
    axis: Option<usize>,
}

/// `floor` as an `i32`, inline. Baseline x86-64 has no rounding instruction, so `f32::floor` is a
/// libm call that forces every float register to be spilled around it in the hot loop. Saturates
/// like `as` for values beyond `i32`.
#[inline(always)]
pub fn floor_i32(x: f32) -> i32 {
    let t = x as i32;
    t.saturating_sub(i32::from((t as f32) > x))
}

/// `ceil` as an `i32`, inline, saturating like [`floor_i32`].
#[inline(always)]
pub fn ceil_i32(x: f32) -> i32 {
    let t = x as i32;
    t.saturating_add(i32::from((t as f32) < x))
}

/// How far from a voxel plane (in voxels) a position must be for `floor` alone to settle it.
const SETTLE_MARGIN: f32 = 1.0 / 64.0;
/// Coordinates below which [`SETTLE_MARGIN`] covers every rounding error (see
/// [`clearly_inside_voxel`]).
const SETTLE_RANGE: f32 = 16384.0;

/// Whether `p = o + d·at` is so far inside voxel `guess` that every plane time below it is
/// before `at` and every one above after it, so that settling needs no plane times at all.
/// Why it holds: with `|o|, |p| < 16384` and planes at most 16384 (`map::MAX_SCENE_EDGE`), a
/// plane time's relative error (`(g − o)·(1/d)` in `f32`, about 1.8e-7) is at most 5.9e-3 voxels
/// as a position (`|g − o| < 32768`), and `p`'s own rounding at most 3e-3: 8.9e-3 in all, under
/// the 1/64 margin (1.56e-2). Beyond the range the exact path runs instead. Ties, which the event order
/// breaks by axis, need a position on a plane, so they never reach this shortcut.
#[inline(always)]
fn clearly_inside_voxel(o: f32, p: f32, guess: i32) -> bool {
    let frac = p - guess as f32;
    frac > SETTLE_MARGIN
        && frac < 1.0 - SETTLE_MARGIN
        && o.abs() < SETTLE_RANGE
        && p.abs() < SETTLE_RANGE
}

/// An axis number after every real axis: event `(t, AFTER_ALL)` is "once every crossing at or
/// before `t` has happened".
const AFTER_ALL: usize = 3;

/// Whether crossing `(t, axis)` comes before event `(at, at_axis)` in the total order.
#[inline(always)]
fn before(t: f32, axis: usize, at: f32, at_axis: usize) -> bool {
    t < at || (t == at && axis < at_axis)
}

impl Dda {
    #[inline(always)]
    fn plane_t(&self, i: usize, plane: i32) -> f32 {
        (plane as f32 - self.o[i]) * self.inv[i]
    }

    /// Time of the plane that the ray crosses when leaving voxel coordinate `v` on axis `i`.
    #[inline(always)]
    fn exit_t(&self, i: usize, v: i32) -> f32 {
        let t = self.plane_t(i, v + self.off[i]);
        if self.step[i] == 0 { f32::INFINITY } else { t }
    }

    /// The voxel coordinate on axis `i` once every crossing ordered before event `(at, k)` has
    /// happened, knowing it lies in `lo..=hi`.
    #[inline(always)]
    fn settle(&self, i: usize, lo: i32, hi: i32, at: f32, k: usize) -> i32 {
        self.settle_scaled(i, lo, hi, at, k, 1)
    }

    /// [`Dda::settle`] for blocks of `scale` voxels: the block coordinate on axis `i` after every
    /// crossing ordered before `(at, k)`, knowing it lies in `lo..=hi`. Block planes are voxel
    /// planes (`g · scale`), so this agrees with settling voxels and dividing.
    #[inline(always)]
    fn settle_scaled(&self, i: usize, lo: i32, hi: i32, at: f32, k: usize, scale: i32) -> i32 {
        if self.step[i] == 0 {
            return (floor_i32(self.o[i]) / scale).clamp(lo, hi);
        }
        let p = self.o[i] + self.d[i] * at;
        let guess = floor_i32(p);
        if clearly_inside_voxel(self.o[i], p, guess) {
            return guess.div_euclid(scale).clamp(lo, hi);
        }
        let mut g = guess.div_euclid(scale).clamp(lo, hi);
        if self.step[i] > 0 {
            while g < hi && before(self.plane_t(i, (g + 1) * scale), i, at, k) {
                g += 1;
            }
            while g > lo && !before(self.plane_t(i, g * scale), i, at, k) {
                g -= 1;
            }
        } else {
            while g > lo && before(self.plane_t(i, g * scale), i, at, k) {
                g -= 1;
            }
            while g < hi && !before(self.plane_t(i, (g + 1) * scale), i, at, k) {
                g += 1;
            }
        }
        g
    }

    /// Sets up the ray; `None` when it misses the grid or is not a usable ray.
    fn start(size: [u32; 3], ray: &Ray) -> Option<Dda> {
        let n = size.map(|s| s as i32);
        Dda::start_in(size, [0; 3], n, ray, 0.0)
    }

    /// Sets up the ray in the box `lo..hi` of voxels (planes, `0 <= lo < hi <= size`): it starts
    /// where it enters the box. Outside the box every voxel is empty, so the flat DDA would only
    /// cross empty voxels up to that entry event: the state there is the one it would have.
    /// With `t_min > 0` the caller vouches that every voxel the ray meets before `t_min` is empty
    /// (the beam pre-pass, [`crate::beam`]), and the ray starts there instead when that is later.
    fn start_in(size: [u32; 3], lo: [i32; 3], hi: [i32; 3], ray: &Ray, t_min: f32) -> Option<Dda> {
        if ray.origin.iter().chain(&ray.dir).any(|c| !c.is_finite()) {
            return None;
        }
        let n = size.map(|s| s as i32);
        let mut dda = Dda {
            o: ray.origin,
            d: ray.dir,
            inv: [0.0; 3],
            step: [0; 3],
            off: [0; 3],
            n,
            v: [0; 3],
            next: [f32::INFINITY; 3],
            t: 0.0,
            axis: None,
        };
        for i in 0..3 {
            if ray.dir[i].abs() >= MIN_DIRECTION {
                dda.step[i] = if ray.dir[i] > 0.0 { 1 } else { -1 };
                dda.off[i] = i32::from(ray.dir[i] > 0.0);
                dda.inv[i] = 1.0 / ray.dir[i];
            }
        }
        if dda.step == [0; 3] {
            return None;
        }
        // At `t_min` the ray is a whole voxel inside the box on every axis: it has entered the
        // box and not left it, whatever the rounding, so no slab test is needed. (The common
        // case after the beam pre-pass, so it is tested first.)
        let deep_inside_at_min = t_min > 0.0
            && (0..3).all(|i| {
                let p = ray.origin[i] + ray.dir[i] * t_min;
                p >= (lo[i] + 1) as f32
                    && p <= (hi[i] - 1) as f32
                    && ray.origin[i].abs() < SETTLE_RANGE
                    && p.abs() < SETTLE_RANGE
            });
        // The start voxel is the one the ray occupies just after t = 0: every crossing at t <= 0
        // has happened. On a plane that means floor() moving up and the voxel below moving down,
        // which keeps the start consistent with the event order that block skips rely on.
        // Not needed (and not computed) when the ray starts deep inside at `t_min`.
        let (start, inside) = if deep_inside_at_min {
            ([0; 3], false)
        } else {
            let start: [i32; 3] = std::array::from_fn(|i| {
                if dda.step[i] < 0 {
                    ceil_i32(ray.origin[i]).saturating_sub(1)
                } else {
                    floor_i32(ray.origin[i])
                }
            });
            (start, (0..3).all(|i| start[i] >= lo[i] && start[i] < hi[i]))
        };
        if inside && t_min <= 0.0 {
            dda.v = start;
        } else if deep_inside_at_min {
            for i in 0..3 {
                dda.v[i] = dda.settle(i, lo[i], hi[i] - 1, t_min, AFTER_ALL);
            }
            dda.t = t_min;
            dda.axis = None;
        } else {
            // Slab test with the same event order: the entry event is the last entry crossing
            // (ties to the later axis), the exit event the first exit crossing.
            let (mut near, mut near_axis) = (f32::NEG_INFINITY, 0usize);
            let (mut far, mut far_axis) = (f32::INFINITY, 0usize);
            for i in 0..3 {
                if dda.step[i] == 0 {
                    if ray.origin[i] < lo[i] as f32 || ray.origin[i] >= hi[i] as f32 {
                        return None;
                    }
                    continue;
                }
                let (enter, leave) = if dda.step[i] > 0 {
                    (dda.plane_t(i, lo[i]), dda.plane_t(i, hi[i]))
                } else {
                    (dda.plane_t(i, hi[i]), dda.plane_t(i, lo[i]))
                };
                if !before(enter, i, near, near_axis) {
                    (near, near_axis) = (enter, i);
                }
                if before(leave, i, far, far_axis) {
                    (far, far_axis) = (leave, i);
                }
            }
            if t_min > 0.0 && (inside || before(near, near_axis, t_min, AFTER_ALL)) {
                // Every voxel before `t_min` is empty (the caller knows it): the state there is
                // the one after every crossing at or before `t_min`, "event (t_min, after all
                // axes)". If the ray has left the box by then it meets nothing.
                if !before(t_min, AFTER_ALL, far, far_axis) {
                    return None;
                }
                for i in 0..3 {
                    dda.v[i] = dda.settle(i, lo[i], hi[i] - 1, t_min, AFTER_ALL);
                }
                dda.t = t_min;
                dda.axis = None;
            } else if inside {
                dda.v = start;
            } else {
                if !before(near, near_axis, far, far_axis) || near < 0.0 {
                    return None;
                }
                let k = near_axis;
                for i in 0..3 {
                    dda.v[i] = if i == k {
                        if dda.step[k] > 0 { lo[k] } else { hi[k] - 1 }
                    } else {
                        dda.settle(i, lo[i], hi[i] - 1, near, k)
                    };
                }
                dda.t = near;
                dda.axis = Some(k);
            }
        }
        for i in 0..3 {
            dda.next[i] = dda.exit_t(i, dda.v[i]);
        }
        Some(dda)
    }

    /// Time of the plane the ray crosses when leaving block `b` (of `scale` voxels) on axis
    /// `i`. The far plane is clipped to the grid, as partial blocks end where the scene ends.
    #[inline(always)]
    fn block_exit_t(&self, i: usize, b: i32, scale: i32) -> f32 {
        // A select, not branches: the same plane as `moving_exit_t`, infinite when not moving.
        let t = self.moving_exit_t(i, b, scale);
        if self.step[i] == 0 { f32::INFINITY } else { t }
    }

    /// [`Dda::block_exit_t`] for an axis the ray moves on, without branching on the direction
    /// (the stepping axis changes unpredictably, so a branch on its sign mispredicts).
    #[inline(always)]
    fn moving_exit_t(&self, i: usize, b: i32, scale: i32) -> f32 {
        self.plane_t(i, ((b + self.off[i]) * scale).min(self.n[i]))
    }

    /// Leaves the cube of empty blocks `lo..=hi` (of `scale` voxels) in one event, the region
    /// and cell levels' clearance jump: the ray's event becomes the cube's exit, `b` the block
    /// after it (settled on the other axes, with their exit times in `bnext`). Returns the exit
    /// axis; `bnext` on it is left to the caller, which checks the block first.
    #[inline(always)]
    fn leave_cube(
        &mut self,
        b: &mut [i32; 3],
        bnext: &mut [f32; 3],
        lo: [i32; 3],
        hi: [i32; 3],
        scale: i32,
    ) -> usize {
        let exit: [f32; 3] = std::array::from_fn(|i| {
            self.block_exit_t(i, if self.step[i] > 0 { hi[i] } else { lo[i] }, scale)
        });
        let k = earliest(&exit);
        self.t = exit[k];
        self.axis = Some(k);
        for i in 0..3 {
            if i != k {
                b[i] = self.settle_scaled(i, lo[i], hi[i], self.t, k, scale);
                bnext[i] = self.block_exit_t(i, b[i], scale);
            }
        }
        b[k] = if self.step[k] > 0 {
            hi[k] + 1
        } else {
            lo[k] - 1
        };
        k
    }

    /// Voxel coordinates after the event that brought the ray into the block `lo..=hi`: the
    /// event's axis is on the entry face, the others settle.
    #[inline(always)]
    fn enter_block(&mut self, lo: [i32; 3], hi: [i32; 3]) {
        if let Some(k) = self.axis {
            for i in 0..3 {
                self.v[i] = if i == k {
                    if self.step[k] > 0 { lo[k] } else { hi[k] }
                } else {
                    self.settle(i, lo[i], hi[i], self.t, k)
                };
            }
        }
    }

    /// One voxel step along the earliest crossing. Returns false when it leaves the grid.
    #[inline(always)]
    fn step_voxel(&mut self) -> bool {
        let k = earliest(&self.next);
        self.t = self.next[k];
        self.axis = Some(k);
        self.v[k] += self.step[k];
        self.next[k] = self.exit_t(k, self.v[k]);
        self.v[k] >= 0 && self.v[k] < self.n[k]
    }

    fn hit(&self, colour: Colour) -> Hit {
        let voxel = self.v.map(|c| c as u32);
        let (normal, previous) = match self.axis {
            Some(k) => {
                let mut normal = [0; 3];
                normal[k] = -self.step[k];
                let mut prev = self.v;
                prev[k] -= self.step[k];
                let inside = prev[k] >= 0 && prev[k] < self.n[k];
                (normal, inside.then(|| prev.map(|c| c as u32)))
            }
            None => ([0; 3], None),
        };
        Hit {
            voxel,
            colour,
            normal,
            t: self.t,
            previous,
        }
    }
}

/// Traces a ray through the brick map; the first solid voxel it meets, if any.
pub fn trace(map: &BrickMap, ray: &Ray) -> Option<Hit> {
    trace_with_stats(map, ray, &mut TraceStats::default())
}

/// Earliest of three crossing times, ties to the lowest axis: the event order.
#[inline(always)]
fn earliest(next: &[f32; 3]) -> usize {
    // Written as selects rather than nested ifs: the axis changes unpredictably from step to
    // step, and a mispredicted branch costs more than the whole comparison.
    let a = usize::from(next[1] < next[0]);
    let m = if a == 1 { next[1] } else { next[0] };
    if next[2] < m { 2 } else { a }
}

/// [`trace`], counting the steps taken at each level.
///
/// One DDA per level, each stepping on its own planes (regions every 32 voxels, cells every 8,
/// voxels every 1), so crossing an empty region or cell costs one plane time. Coarse planes are
/// voxel planes with the same times, so each level visits exactly the blocks the flat DDA would.
/// Voxel coordinates are only needed inside bricks: descending after a coarse step settles them
/// at the entry event ([`Dda::settle`]); climbing back up needs nothing, as the brick's exit
/// event is a coarse crossing too.
pub fn trace_with_stats(map: &BrickMap, ray: &Ray, stats: &mut TraceStats) -> Option<Hit> {
    trace_from_with_stats(map, ray, 0.0, stats)
}

/// [`trace`] for a ray known to meet only empty voxels before parameter `t_min` (from
/// [`crate::beam`]): it starts there. The hit is the one [`trace`] finds, bit for bit, as long as
/// that promise holds; `t_min` of 0 (or less) is plain [`trace`], infinity a miss.
pub fn trace_from(map: &BrickMap, ray: &Ray, t_min: f32) -> Option<Hit> {
    trace_from_with_stats(map, ray, t_min, &mut TraceStats::default())
}

/// [`trace_from`], counting the steps taken at each level.
pub fn trace_from_with_stats(
    map: &BrickMap,
    ray: &Ray,
    t_min: f32,
    stats: &mut TraceStats,
) -> Option<Hit> {
    trace_pending(map, ray, t_min, stats).map(|hit| hit.resolve(map))
}

/// Whether a ray meets any solid voxel: [`trace`] without reading the colour (shadow rays).
pub fn blocked(map: &BrickMap, ray: &Ray) -> bool {
    trace_pending(map, ray, 0.0, &mut TraceStats::default()).is_some()
}

/// A hit whose colour has not been read yet: the brick slot and bit to read it from.
///
/// Why: the colour is the one read of a hit that usually misses every cache (the colour pool is
/// the largest array). Tracing a tile's rays first and reading their colours afterwards, in a
/// row of independent loads, lets those misses overlap instead of stalling each ray in turn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PendingHit {
    hit: Hit,
    slot: u32,
    bit: u32,
}

impl PendingHit {
    /// The hit with its colour, read from `map` (the map it was traced on).
    #[inline]
    pub fn resolve(self, map: &BrickMap) -> Hit {
        let mask = &map.masks[self.slot as usize];
        let colour =
            crate::palette::colour_at_words(map.block(self.slot), rank(mask, self.bit) as usize)
                .unwrap_or(Colour::BLACK);
        Hit { colour, ..self.hit }
    }
}

/// [`trace_from_with_stats`] up to the hit, leaving its colour to [`PendingHit::resolve`].
pub fn trace_pending(
    map: &BrickMap,
    ray: &Ray,
    t_min: f32,
    stats: &mut TraceStats,
) -> Option<PendingHit> {
    if t_min == f32::INFINITY {
        return None;
    }
    let t_min = if t_min.is_nan() { 0.0 } else { t_min };
    const R: i32 = REGION_EDGE as i32;
    const C: i32 = BRICK_EDGE as i32;
    // Only the occupied regions' box is traced (none: nothing to hit).
    let (rlo, rhi) = map.occupied_regions()?;
    let (rlo, rhi) = (rlo.map(|r| r as i32), rhi.map(|r| r as i32));
    let size = map.size();
    let n = size.map(|s| s as i32);
    let mut dda = Dda::start_in(
        size,
        rlo.map(|r| r * R),
        std::array::from_fn(|i| ((rhi[i] + 1) * R).min(n[i])),
        ray,
        t_min,
    )?;
    let cdims = map.cell_dims().map(|d| d as i32);
    let rdims = map.region_dims().map(|d| d as i32);
    let step = dda.step;
    // Whether `dda.v` holds the voxel at the last event; false after a coarse step.
    let mut v_valid = true;
    let mut r = dda.v.map(|c| c / R);
    let mut rnext: [f32; 3] = std::array::from_fn(|i| dda.block_exit_t(i, r[i], R));
    loop {
        // Region level.
        let block = loop {
            let entry = map.regions[(r[0] + rdims[0] * (r[1] + rdims[1] * r[2])) as usize];
            if !region_is_empty(entry) {
                break entry;
            }
            stats.region_skips += 1;
            v_valid = false;
            let clear = region_clearance(entry) as i32;
            if clear >= 2 {
                // Leave the whole empty cube of regions r ± clear in one event. Worth a settle
                // only when it replaces several single steps.
                let lo: [i32; 3] = std::array::from_fn(|i| (r[i] - clear).max(rlo[i]));
                let hi: [i32; 3] = std::array::from_fn(|i| (r[i] + clear).min(rhi[i]));
                dda.leave_cube(&mut r, &mut rnext, lo, hi, R);
            } else {
                let k = earliest(&rnext);
                dda.t = rnext[k];
                dda.axis = Some(k);
                r[k] += step[k];
            }
            let k = dda.axis.unwrap_or(0);
            if r[k] < rlo[k] || r[k] > rhi[k] {
                return None;
            }
            rnext[k] = dda.moving_exit_t(k, r[k], R);
        };
        if !v_valid {
            let lo = r.map(|c| c * R);
            dda.enter_block(lo, std::array::from_fn(|i| (lo[i] + R - 1).min(n[i] - 1)));
            v_valid = true;
        }
        if let Some((level, slot)) = region_stand_in(block) {
            // A coarse brick stands in for this region (`map::stand_in`): its voxels are blocks
            // of 2^level voxels (the whole region from level 5 on), stepped like cells. A solid
            // block is hit where the ray enters it, the voxel the flat DDA over the block's
            // voxels would stop at; leaving the last block is a region crossing.
            let scale = 1i32 << level.min(5);
            let lo = r.map(|c| c * R);
            let hi: [i32; 3] = std::array::from_fn(|i| (lo[i] + R).min(n[i]) - 1);
            let (blo, bhi) = (lo.map(|c| c / scale), hi.map(|c| c / scale));
            let mask = &map.masks[slot as usize];
            let mut b = dda.v.map(|c| c / scale);
            let mut bnext: [f32; 3] = std::array::from_fn(|i| dda.block_exit_t(i, b[i], scale));
            loop {
                let bit = crate::map::coarse_bit(b.map(|c| (c * scale) as u32), level);
                if mask_get(mask, bit) {
                    if !v_valid {
                        let at = b.map(|c| c * scale);
                        dda.enter_block(
                            at,
                            std::array::from_fn(|i| (at[i] + scale - 1).min(hi[i])),
                        );
                    }
                    return Some(PendingHit {
                        hit: dda.hit(Colour(0)),
                        slot,
                        bit,
                    });
                }
                stats.cell_skips += 1;
                v_valid = false;
                let k = earliest(&bnext);
                dda.t = bnext[k];
                dda.axis = Some(k);
                b[k] += step[k];
                if b[k] < blo[k] || b[k] > bhi[k] {
                    r[k] += step[k];
                    if r[k] < rlo[k] || r[k] > rhi[k] {
                        return None;
                    }
                    rnext[k] = dda.moving_exit_t(k, r[k], R);
                    break;
                }
                bnext[k] = dda.moving_exit_t(k, b[k], scale);
            }
            continue;
        }
        // Cell level, inside this region: cells `clo..=chi` (the grid ends inside the box's
        // last regions, so leaving the region covers leaving the grid).
        let clo = r.map(|r| r * REGION_CELLS as i32);
        let chi: [i32; 3] =
            std::array::from_fn(|i| (clo[i] + REGION_CELLS as i32 - 1).min(cdims[i] - 1));
        let mut c = dda.v.map(|v| v / C);
        let mut cnext: [f32; 3] = std::array::from_fn(|i| dda.block_exit_t(i, c[i], C));
        'cells: loop {
            let local = ((c[0] & 3) | ((c[1] & 3) << 2) | ((c[2] & 3) << 4)) as u32;
            let slot = map.cells[(block * CELLS_PER_BLOCK + local) as usize];
            let k = if cell_is_empty(slot) {
                stats.cell_skips += 1;
                v_valid = false;
                let clear = cell_clearance(slot) as i32;
                if clear >= 1 {
                    // Leave the cube of empty cells c ± clear (within this region) in one event,
                    // as the region level does.
                    let lo: [i32; 3] = std::array::from_fn(|i| (c[i] - clear).max(clo[i]));
                    let hi: [i32; 3] = std::array::from_fn(|i| (c[i] + clear).min(chi[i]));
                    let k = dda.leave_cube(&mut c, &mut cnext, lo, hi, C);
                    cnext[k] = dda.moving_exit_t(k, c[k], C);
                    k
                } else {
                    let k = earliest(&cnext);
                    dda.t = cnext[k];
                    dda.axis = Some(k);
                    c[k] += step[k];
                    cnext[k] = dda.moving_exit_t(k, c[k], C);
                    k
                }
            } else {
                let lo = c.map(|v| v * C);
                let hi: [i32; 3] = std::array::from_fn(|i| (lo[i] + C - 1).min(n[i] - 1));
                if !v_valid {
                    dda.enter_block(lo, hi);
                    v_valid = true;
                }
                let mask = &map.masks[slot as usize];
                // Voxel level, inside this brick. The state lives in scalars and every axis is
                // updated with selects rather than an index: the stepping axis changes
                // unpredictably, and a branch or a memory round trip per step costs more than
                // computing all three candidates. Plane times are the same expressions as
                // `Dda::exit_t`, so the times are bit for bit those of the flat DDA.
                let [ox, oy, oz] = dda.o;
                let [ix, iy, iz] = dda.inv;
                let [sx, sy, sz] = step;
                let off = step.map(|s| i32::from(s > 0));
                let plane = |v: i32, off: i32, o: f32, inv: f32| ((v + off) as f32 - o) * inv;
                let [mut vx, mut vy, mut vz] = dda.v;
                let mut nx = dda.exit_t(0, vx);
                let mut ny = dda.exit_t(1, vy);
                let mut nz = dda.exit_t(2, vz);
                let mut t = dda.t;
                let mut axis = dda.axis;
                let k = loop {
                    let bit = voxel_bit(vx as u32, vy as u32, vz as u32);
                    if mask_get(mask, bit) {
                        dda.v = [vx, vy, vz];
                        dda.t = t;
                        dda.axis = axis;
                        return Some(PendingHit {
                            hit: dda.hit(Colour(0)),
                            slot,
                            bit,
                        });
                    }
                    stats.voxel_steps += 1;
                    let k = earliest(&[nx, ny, nz]);
                    let (x, y, z) = (k == 0, k == 1, k == 2);
                    t = if x {
                        nx
                    } else if y {
                        ny
                    } else {
                        nz
                    };
                    vx += if x { sx } else { 0 };
                    vy += if y { sy } else { 0 };
                    vz += if z { sz } else { 0 };
                    nx = if x { plane(vx, off[0], ox, ix) } else { nx };
                    ny = if y { plane(vy, off[1], oy, iy) } else { ny };
                    nz = if z { plane(vz, off[2], oz, iz) } else { nz };
                    axis = Some(k);
                    let out = (vx < lo[0] || vx > hi[0])
                        | (vy < lo[1] || vy > hi[1])
                        | (vz < lo[2] || vz > hi[2]);
                    if out {
                        break k;
                    }
                };
                // Left the brick: that crossing is a cell plane as well.
                dda.v = [vx, vy, vz];
                dda.t = t;
                dda.axis = axis;
                c[k] += step[k];
                cnext[k] = dda.moving_exit_t(k, c[k], C);
                k
            };
            if c[k] < clo[k] || c[k] > chi[k] {
                // Left the region: that crossing is a region plane as well (or the grid's edge,
                // which lies outside the occupied box).
                r[k] += step[k];
                if r[k] < rlo[k] || r[k] > rhi[k] {
                    return None;
                }
                rnext[k] = dda.moving_exit_t(k, r[k], R);
                break 'cells;
            }
        }
    }
}

/// The reference the tracer is tested against: the same DDA over a flat voxel grid, one voxel
/// at a time, with no hierarchy. Slow; for tests and for checking the GPU twin.
pub fn trace_flat(
    size: [u32; 3],
    solid: impl Fn([u32; 3]) -> Option<Colour>,
    ray: &Ray,
) -> Option<Hit> {
    let mut dda = Dda::start(size, ray)?;
    loop {
        let voxel = dda.v.map(|c| c as u32);
        if let Some(colour) = solid(voxel) {
            return Some(dda.hit(colour));
        }
        if !dda.step_voxel() {
            return None;
        }
    }
}

/// Calls `f(voxel, entry)` for each voxel the flat DDA visits in a grid of `size`, in order,
/// with the ray parameter at which the ray enters it (0 for the start voxel), while that is at
/// most `t_end`. Nothing for a ray that misses the grid or is not usable.
pub(crate) fn voxel_walk(size: [u32; 3], ray: &Ray, t_end: f32, mut f: impl FnMut([i32; 3], f32)) {
    let Some(mut dda) = Dda::start(size, ray) else {
        return;
    };
    while dda.t <= t_end {
        f(dda.v, dda.t);
        if !dda.step_voxel() {
            return;
        }
    }
}

// Keep the region constant visible to readers of the hierarchy above.
const _: () = assert!(REGION_EDGE == REGION_CELLS * BRICK_EDGE);

#[cfg(test)]
mod tests {
    use super::*;

    fn scene() -> BrickMap {
        let mut map = BrickMap::new([100, 70, 90]).unwrap();
        map.fill_box(
            [40, 0, 40],
            [59, 19, 59],
            crate::map::BrushMode::Fill,
            Colour::WHITE,
        );
        map.set([10, 60, 80], Colour(7));
        map
    }

    fn flat(map: &BrickMap, ray: &Ray) -> Option<Hit> {
        trace_flat(map.size(), |v| map.get(v), ray)
    }

    #[test]
    fn hits_box_from_outside_with_normal_and_previous() {
        let map = scene();
        let ray = Ray {
            origin: [50.5, 10.5, -30.0],
            dir: [0.0, 0.0, 1.0],
        };
        let hit = trace(&map, &ray).unwrap();
        assert_eq!(hit.voxel, [50, 10, 40]);
        assert_eq!(hit.normal, [0, 0, -1]);
        assert_eq!(hit.previous, Some([50, 10, 39]));
        assert!((hit.t - 70.0).abs() < 1e-4);
        assert_eq!(Some(hit), flat(&map, &ray));
    }

    #[test]
    fn origin_inside_solid_voxel_hits_at_zero() {
        let map = scene();
        let ray = Ray {
            origin: [45.2, 5.5, 45.5],
            dir: [1.0, 0.3, 0.0],
        };
        let hit = trace(&map, &ray).unwrap();
        assert_eq!(hit.voxel, [45, 5, 45]);
        assert_eq!(hit.t, 0.0);
        assert_eq!(hit.normal, [0, 0, 0]);
        assert_eq!(hit.previous, None);
    }

    #[test]
    fn entering_grid_straight_into_a_voxel_has_no_previous() {
        let map = scene();
        let ray = Ray {
            origin: [50.5, -5.0, 50.5],
            dir: [0.0, 1.0, 0.0],
        };
        let hit = trace(&map, &ray).unwrap();
        assert_eq!(hit.voxel, [50, 0, 50]);
        assert_eq!(hit.normal, [0, -1, 0]);
        assert_eq!(hit.previous, None);
    }

    #[test]
    fn axis_parallel_and_grazing_rays() {
        let map = scene();
        // Along the box's top face plane y = 20: the voxels below are solid, the plane itself is
        // the boundary, so the ray runs in the empty row y = 20 and misses.
        let graze = Ray {
            origin: [0.0, 20.0, 50.5],
            dir: [1.0, 0.0, 0.0],
        };
        assert_eq!(trace(&map, &graze), None);
        assert_eq!(flat(&map, &graze), None);
        // Just below it hits the box side.
        let below = Ray {
            origin: [0.0, 19.999, 50.5],
            dir: [1.0, 0.0, 0.0],
        };
        assert_eq!(trace(&map, &below).map(|h| h.voxel), Some([40, 19, 50]));
        // Exactly through the box's corner edge, diagonally.
        let corner = Ray {
            origin: [30.0, 10.5, 30.0],
            dir: [1.0, 0.0, 1.0],
        };
        assert_eq!(trace(&map, &corner), flat(&map, &corner));
        assert!(trace(&map, &corner).is_some());
    }

    #[test]
    fn misses_and_degenerate_rays() {
        let map = scene();
        assert_eq!(
            trace(
                &map,
                &Ray {
                    origin: [-5.0, -5.0, -5.0],
                    dir: [-1.0, 0.0, 0.0]
                }
            ),
            None
        );
        assert_eq!(
            trace(
                &map,
                &Ray {
                    origin: [5.0, 5.0, 5.0],
                    dir: [0.0, 0.0, 0.0]
                }
            ),
            None
        );
        assert_eq!(
            trace(
                &map,
                &Ray {
                    origin: [f32::NAN, 5.0, 5.0],
                    dir: [1.0, 0.0, 0.0]
                }
            ),
            None
        );
        assert_eq!(
            trace(
                &map,
                &Ray {
                    origin: [5.0, 5.0, 5.0],
                    dir: [f32::INFINITY, 0.0, 0.0]
                }
            ),
            None
        );
        // Parallel to an axis but outside the slab on it.
        assert_eq!(
            trace(
                &map,
                &Ray {
                    origin: [50.0, 80.0, -1.0],
                    dir: [0.0, 0.0, 1.0]
                }
            ),
            None
        );
        // Behind the grid.
        assert_eq!(
            trace(
                &map,
                &Ray {
                    origin: [50.5, 10.5, -30.0],
                    dir: [0.0, 0.0, -1.0]
                }
            ),
            None
        );
    }

    #[test]
    fn huge_and_tiny_grids() {
        let mut tiny = BrickMap::new([1, 1, 1]).unwrap();
        tiny.set([0, 0, 0], Colour(3));
        let hit = trace(
            &tiny,
            &Ray {
                origin: [-2.0, 0.5, 0.5],
                dir: [1.0, 0.0, 0.0],
            },
        )
        .unwrap();
        assert_eq!((hit.voxel, hit.normal), ([0, 0, 0], [-1, 0, 0]));
        let mut huge = BrickMap::new([4096, 4096, 4096]).unwrap();
        huge.set([4095, 4095, 4095], Colour(9));
        huge.set([0, 0, 0], Colour(8));
        let diag = Ray {
            origin: [-100.0, -100.0, -100.0],
            dir: [1.0, 1.0, 1.0],
        };
        let mut stats = TraceStats::default();
        let hit = trace_with_stats(&huge, &diag, &mut stats).unwrap();
        assert_eq!(hit.voxel, [0, 0, 0]);
        let back = Ray {
            origin: [4095.5, 4095.5, 4095.5],
            dir: [-1.0, -0.999, -1.001],
        };
        let mut stats = TraceStats::default();
        let hit = trace_with_stats(&huge, &back, &mut stats).unwrap();
        assert_eq!(hit.voxel, [4095, 4095, 4095], "starts inside it");
        // The exact diagonal crosses every voxel corner: all three crossings tie at each one.
        let across = Ray {
            origin: [4094.5, 4094.5, 4094.5],
            dir: [-1.0, -1.0, -1.0],
        };
        let mut stats = TraceStats::default();
        let hit = trace_with_stats(&huge, &across, &mut stats);
        assert_eq!(hit.map(|h| h.voxel), Some([0, 0, 0]));
        assert_eq!(hit, trace_flat(huge.size(), |v| huge.get(v), &across));
        assert!(
            // 128 regions lie on the diagonal; clearance jumps cross them in far fewer steps.
            stats.region_skips < 48 && stats.voxel_steps < 64,
            "{stats:?}"
        );
    }
}
