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

use crate::brick::{BRICK_EDGE, EMPTY, mask_get, rank, voxel_bit};
use crate::colour::Colour;
use crate::map::{BrickMap, CELLS_PER_BLOCK, REGION_CELLS, REGION_EDGE};

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
    n: [i32; 3],
    /// Current voxel.
    v: [i32; 3],
    /// Time of the next voxel-plane crossing per axis (infinite on axes the ray does not move on).
    next: [f32; 3],
    /// Time and axis of the event that brought the ray into `v`, if any.
    t: f32,
    axis: Option<usize>,
}

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
        if self.step[i] == 0 {
            f32::INFINITY
        } else {
            self.plane_t(i, v + i32::from(self.step[i] > 0))
        }
    }

    /// The voxel coordinate on axis `i` once every crossing ordered before event `(at, k)` has
    /// happened, knowing it lies in `lo..=hi`.
    #[inline(always)]
    fn settle(&self, i: usize, lo: i32, hi: i32, at: f32, k: usize) -> i32 {
        if self.step[i] == 0 {
            return (self.o[i].floor() as i32).clamp(lo, hi);
        }
        let mut g = ((self.o[i] + self.d[i] * at).floor() as i32).clamp(lo, hi);
        if self.step[i] > 0 {
            while g < hi && before(self.plane_t(i, g + 1), i, at, k) {
                g += 1;
            }
            while g > lo && !before(self.plane_t(i, g), i, at, k) {
                g -= 1;
            }
        } else {
            while g > lo && before(self.plane_t(i, g), i, at, k) {
                g -= 1;
            }
            while g < hi && !before(self.plane_t(i, g + 1), i, at, k) {
                g += 1;
            }
        }
        g
    }

    /// Sets up the ray; `None` when it misses the grid or is not a usable ray.
    fn start(size: [u32; 3], ray: &Ray) -> Option<Dda> {
        if ray.origin.iter().chain(&ray.dir).any(|c| !c.is_finite()) {
            return None;
        }
        let n = size.map(|s| s as i32);
        let mut dda = Dda {
            o: ray.origin,
            d: ray.dir,
            inv: [0.0; 3],
            step: [0; 3],
            n,
            v: [0; 3],
            next: [f32::INFINITY; 3],
            t: 0.0,
            axis: None,
        };
        for i in 0..3 {
            if ray.dir[i].abs() >= MIN_DIRECTION {
                dda.step[i] = if ray.dir[i] > 0.0 { 1 } else { -1 };
                dda.inv[i] = 1.0 / ray.dir[i];
            }
        }
        if dda.step == [0; 3] {
            return None;
        }
        // The start voxel is the one the ray occupies just after t = 0: every crossing at t <= 0
        // has happened. On a plane that means floor() moving up and the voxel below moving down,
        // which keeps the start consistent with the event order that block skips rely on.
        let start: [i32; 3] = std::array::from_fn(|i| {
            if dda.step[i] < 0 {
                ray.origin[i].ceil() as i32 - 1
            } else {
                ray.origin[i].floor() as i32
            }
        });
        if (0..3).all(|i| start[i] >= 0 && start[i] < n[i]) {
            dda.v = start;
        } else {
            // Slab test with the same event order: the entry event is the last entry crossing
            // (ties to the later axis), the exit event the first exit crossing.
            let (mut near, mut near_axis) = (f32::NEG_INFINITY, 0usize);
            let (mut far, mut far_axis) = (f32::INFINITY, 0usize);
            for i in 0..3 {
                if dda.step[i] == 0 {
                    if ray.origin[i] < 0.0 || ray.origin[i] >= n[i] as f32 {
                        return None;
                    }
                    continue;
                }
                let (enter, leave) = if dda.step[i] > 0 {
                    (dda.plane_t(i, 0), dda.plane_t(i, n[i]))
                } else {
                    (dda.plane_t(i, n[i]), dda.plane_t(i, 0))
                };
                if !before(enter, i, near, near_axis) {
                    (near, near_axis) = (enter, i);
                }
                if before(leave, i, far, far_axis) {
                    (far, far_axis) = (leave, i);
                }
            }
            if !before(near, near_axis, far, far_axis) || near < 0.0 {
                return None;
            }
            let k = near_axis;
            for i in 0..3 {
                dda.v[i] = if i == k {
                    if dda.step[k] > 0 { 0 } else { n[k] - 1 }
                } else {
                    dda.settle(i, 0, n[i] - 1, near, k)
                };
            }
            dda.t = near;
            dda.axis = Some(k);
        }
        for i in 0..3 {
            dda.next[i] = dda.exit_t(i, dda.v[i]);
        }
        Some(dda)
    }

    /// Jumps to the exit event of the empty block `lo..=hi` (already clipped to the grid).
    /// Returns false when that exit leaves the grid.
    #[inline(always)]
    fn skip_block(&mut self, lo: [i32; 3], hi: [i32; 3]) -> bool {
        let mut k = 0usize;
        let mut at = f32::INFINITY;
        for i in 0..3 {
            if self.step[i] != 0 {
                let te = self.exit_t(i, if self.step[i] > 0 { hi[i] } else { lo[i] });
                if te < at {
                    at = te;
                    k = i;
                }
            }
        }
        for i in 0..3 {
            if i != k {
                self.v[i] = self.settle(i, lo[i], hi[i], at, k);
                self.next[i] = self.exit_t(i, self.v[i]);
            }
        }
        self.v[k] = if self.step[k] > 0 {
            hi[k] + 1
        } else {
            lo[k] - 1
        };
        self.next[k] = self.exit_t(k, self.v[k]);
        self.t = at;
        self.axis = Some(k);
        self.v[k] >= 0 && self.v[k] < self.n[k]
    }

    /// One voxel step along the earliest crossing. Returns false when it leaves the grid.
    #[inline(always)]
    fn step_voxel(&mut self) -> bool {
        let k = if self.next[0] <= self.next[1] {
            if self.next[0] <= self.next[2] { 0 } else { 2 }
        } else if self.next[1] <= self.next[2] {
            1
        } else {
            2
        };
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

/// [`trace`], counting the steps taken at each level.
pub fn trace_with_stats(map: &BrickMap, ray: &Ray, stats: &mut TraceStats) -> Option<Hit> {
    let size = map.size();
    let mut dda = Dda::start(size, ray)?;
    let n = dda.n;
    let region_edge = REGION_EDGE as i32;
    let brick_edge = BRICK_EDGE as i32;
    // Each iteration leaves a region, a cell or a voxel behind, so this bounds a looping bug
    // without ever cutting a real ray short.
    let mut budget = 4 * (n[0] + n[1] + n[2]) + 16;
    loop {
        budget -= 1;
        if budget < 0 {
            debug_assert!(false, "DDA did not terminate for {ray:?}");
            return None;
        }
        let v = dda.v;
        let region = v.map(|c| (c / region_edge) as u32);
        let block = map.regions[map.region_index(region)];
        if block == EMPTY {
            stats.region_skips += 1;
            let lo = region.map(|r| r as i32 * region_edge);
            let hi = std::array::from_fn(|i| (lo[i] + region_edge - 1).min(n[i] - 1));
            if !dda.skip_block(lo, hi) {
                return None;
            }
            continue;
        }
        let cell = v.map(|c| (c / brick_edge) as u32);
        let slot = map.cells[(block * CELLS_PER_BLOCK + BrickMap::cell_in_block(cell)) as usize];
        let lo = cell.map(|c| c as i32 * brick_edge);
        let hi: [i32; 3] = std::array::from_fn(|i| (lo[i] + brick_edge - 1).min(n[i] - 1));
        if slot == EMPTY {
            stats.cell_skips += 1;
            if !dda.skip_block(lo, hi) {
                return None;
            }
            continue;
        }
        let mask = &map.masks[slot as usize];
        // Step inside the brick until a solid voxel or until the ray leaves the brick.
        loop {
            let bit = voxel_bit(dda.v[0] as u32, dda.v[1] as u32, dda.v[2] as u32);
            if mask_get(mask, bit) {
                let colour =
                    map.colours[(map.colour_base[slot as usize] + rank(mask, bit)) as usize];
                return Some(dda.hit(colour));
            }
            stats.voxel_steps += 1;
            if !dda.step_voxel() {
                return None;
            }
            let k = dda.axis.unwrap_or(0);
            if dda.v[k] < lo[k] || dda.v[k] > hi[k] {
                break;
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
            stats.region_skips > 100 && stats.voxel_steps < 64,
            "{stats:?}"
        );
    }
}
