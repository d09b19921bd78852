//! The first camera for a scene nobody has placed a camera in yet (no `--eye`).
//!
//! A fixed camera over the whole grid ([`Camera::overview`]) fails two kinds of scene: a small
//! model in a big grid is a speck in one corner, and a closed interior (a room, a cathedral) shows
//! nothing but its outer wall. [`find`] looks at the content first. The rule, exactly as
//! implemented:
//!
//! 1. **Occupied box.** The axis-aligned box of the solid voxels: the box of the non-empty 32³
//!    regions, each face then refined to voxels by reading the bricks of the regions on that face
//!    only. An empty map gets [`Camera::overview`] of the grid (outside).
//! 2. **Candidates.** A [`LATTICE`] of 6×4×6 voxel centres spread evenly over the occupied box
//!    (x, y, z; repeats on thin axes dropped); solid ones are skipped, the rest are *empty
//!    candidates*.
//! 3. **Probes.** From each empty candidate, [`PROBES`] = 32 rays along a fixed Fibonacci sphere
//!    of directions are traced with [`crate::trace::trace`]. A candidate is *enclosed* when at
//!    least [`ENCLOSED_HITS`] = 29 of them (≥ 90%) hit a solid voxel; probing stops at the 4th
//!    miss. An enclosed candidate also traces straight up and down, which gives the free vertical
//!    span of its column.
//! 4. **Inside or outside.** The scene is *inside* when at least one candidate is enclosed,
//!    enclosed candidates are at least [`ENCLOSED_SHARE`] = 1/2 of the empty candidates, and
//!    the enclosure holds something: at least [`INTERIOR_HITS`] = 8 of the enclosed candidates'
//!    probe hits are *interior* — past the solid the probe hit (stepped through in quarter
//!    voxels, at most [`WALL_DEPTH`] = 64 voxels) the same ray meets another solid before it
//!    leaves the grid. A closed model that is only a shell (an imported cube, a ball) has no
//!    interior hits: every probe from inside hits the shell and then escapes, so it is looked
//!    at from outside, like any object; a room with furniture, a cathedral with pillars and
//!    vaults, is looked at from inside.
//! 5. **Inside camera.** The enclosed candidate with the largest median probe distance (the 17th
//!    of its 32 sorted hit distances, a miss counting as infinitely far) wins; one in the upper
//!    half of its column's free span counts [`UPPER_HALF_WEIGHT`] = 0.9 of its median (ties: the
//!    first in z, y, x lattice order). The eye goes to the centre of the voxel in that column at
//!    [`EYE_HEIGHT`] = 40% of the free span above the solid below, then to the nearest voxel
//!    within [`NUDGE`] = 4 voxels (Chebyshev) whose neighbours up to [`CLEARANCE`] = 2 voxels away
//!    are all empty and inside the grid (failing that, 1 voxel away; failing both it stays). From
//!    there [`LOOK_DIRECTIONS`] = 16 horizontal rays, 22.5° apart starting at +x, are traced; the
//!    longest free one (a miss counts to the grid's edge; ties: the first) is the view direction.
//!    The eye then steps back against it by [`STEP_BACK`] = 0.5 of the free distance behind it, to
//!    the voxel there (nudged the same way), if that voxel is empty and the free distance ahead
//!    from it is longer than from where it was: the view takes in the room instead of standing in
//!    its middle. The target is along the view direction at half the free distance ahead (at
//!    least 1 voxel), tilted [`LOOK_DOWN_DEGREES`] = 5° down.
//! 6. **Outside camera.** The camera looks along −[`OUTSIDE_DIRECTION`] = −(−1, 0.75, −1), as
//!    [`Camera::overview`] does from above the −x −z corner, and frames the content's hull: per
//!    column of bricks (8×8 voxels across), the box from its lowest to its highest solid voxel,
//!    clipped to the occupied box (per column of regions instead when more than
//!    [`HULL_CELL_REGIONS`] regions are non-empty). The eye is the point from which every corner
//!    of those boxes lies within [`FRAME_FILL`] = 95% of the half-angle tangents of a
//!    [`FRAME_ASPECT`] = 16:9 frame of `fov_y`, as far forward as that allows and centred on them
//!    (the closed-form fit of a point set in a frustum of fixed orientation); the target is on the
//!    view axis at the depth of the occupied box's centre.
//!
//! Cost: at most 144 candidates × (32 + 2) probes, as many rays past the hits of enclosed
//! candidates (until [`INTERIOR_HITS`] are found), and 18 rays (≤ 9,522 rays); one pass over the
//! region array; the cells of each non-empty region (up to [`HULL_CELL_REGIONS`] of them) and the
//! bricks on the occupied box's faces; twice 13³ voxel reads. Deterministic: no randomness, no
//! clock. Nothing in the map can make it panic, and the camera it returns always projects
//! (`camera.project(w, h)` is `Some` for any non-zero `w`, `h`).

use crate::brick::{BRICK_EDGE, Mask};
use crate::map::{
    BrickMap, CELLS_PER_BLOCK, REGION_CELLS, REGION_EDGE, cell_is_empty, region_is_empty,
};
use crate::render::Camera;
use crate::trace::{Ray, trace};

/// Candidate eye points per axis (x, y, z) over the occupied box.
pub const LATTICE: [u32; 3] = [6, 4, 6];
/// Probe rays per candidate.
pub const PROBES: usize = 32;
/// Probes that must hit for a candidate to count as enclosed (29 of 32: ≥ 90%).
pub const ENCLOSED_HITS: usize = 29;
/// Share of empty candidates that must be enclosed for the scene to be viewed from inside.
pub const ENCLOSED_SHARE: f32 = 0.5;
/// Probe hits on something inside an enclosure (not its shell) it takes to view it from inside.
pub const INTERIOR_HITS: u32 = 8;
/// Deepest solid a probe steps through, in voxels, to see whether something lies beyond it.
pub const WALL_DEPTH: f32 = 64.0;
/// Weight of a candidate in the upper half of its column's free span, against 1 below.
pub const UPPER_HALF_WEIGHT: f32 = 0.9;
/// Eye height inside, as a fraction of the free vertical span above the solid below.
pub const EYE_HEIGHT: f32 = 0.4;
/// Voxels the inside eye may move to gain clearance.
pub const NUDGE: i32 = 4;
/// Empty voxels wanted around the inside eye (Chebyshev distance).
pub const CLEARANCE: i32 = 2;
/// Horizontal directions tried for the inside view.
pub const LOOK_DIRECTIONS: usize = 16;
/// Fraction of the free distance behind the inside eye that it steps back, against the view.
pub const STEP_BACK: f32 = 0.5;
/// Downward tilt of the inside view.
pub const LOOK_DOWN_DEGREES: f32 = 5.0;
/// From the content towards the outside eye: above the −x −z corner, like [`Camera::overview`].
pub const OUTSIDE_DIRECTION: [f32; 3] = [-1.0, 0.75, -1.0];
/// Frame aspect (width / height) the outside view is fitted to.
pub const FRAME_ASPECT: f32 = 16.0 / 9.0;
/// Fraction of the frame's half-angle tangents the content may span, leaving a margin.
pub const FRAME_FILL: f32 = 0.95;
/// Field of view used when the caller's is not a usable angle.
pub const FALLBACK_FOV: f32 = 55.0;

/// Whether the first view looks at the scene from outside or stands inside it. Inside exists
/// because an enclosed scene seen from outside is only its outer wall.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    Outside,
    Inside,
}

/// The chosen camera and why: the diagnostics let a log line or a test say what [`find`] saw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Viewpoint {
    pub camera: Camera,
    pub placement: Placement,
    /// Occupied voxel box as `[min, max)`; `None` for an empty map.
    pub occupied: Option<[[u32; 3]; 2]>,
    /// Candidates that were empty and probed.
    pub candidates: u32,
    /// Of those, the enclosed ones.
    pub enclosed: u32,
    /// `enclosed / candidates` (0 when there were none).
    pub enclosed_fraction: f32,
    /// Enclosed candidates' probe hits with more solid beyond them, counted up to
    /// [`INTERIOR_HITS`]: fewer means the enclosure is an empty shell.
    pub interior: u32,
    /// Rays traced in all.
    pub rays: u32,
}

/// Chooses the first camera for `map` with vertical field of view `fov_y` degrees (an unusable
/// angle is clamped to 1..=170, or [`FALLBACK_FOV`] when not finite). See the module docs for
/// the rule.
pub fn find(map: &BrickMap, fov_y: f32) -> Viewpoint {
    let fov_y = if fov_y.is_finite() {
        fov_y.clamp(1.0, 170.0)
    } else {
        FALLBACK_FOV
    };
    let size = map.size();
    let Some(occupancy) = Occupancy::of(map) else {
        let mut camera = Camera::overview(size);
        camera.fov_y = fov_y;
        return Viewpoint {
            camera,
            placement: Placement::Outside,
            occupied: None,
            candidates: 0,
            enclosed: 0,
            enclosed_fraction: 0.0,
            interior: 0,
            rays: 0,
        };
    };
    let (lo, hi) = (occupancy.lo, occupancy.hi);
    let survey = survey(map, lo, hi);
    let mut rays = survey.rays;
    let inside = survey.enclosed > 0
        && survey.enclosed as f32 >= ENCLOSED_SHARE * survey.candidates as f32
        && survey.interior >= INTERIOR_HITS;
    let (camera, placement) = match survey.best.filter(|_| inside) {
        Some(best) => (
            inside_camera(map, &best, fov_y, &mut rays),
            Placement::Inside,
        ),
        None => (
            outside_camera(&occupancy, fov_y).unwrap_or_else(|| {
                let mut camera = Camera::overview(size);
                camera.fov_y = fov_y;
                camera
            }),
            Placement::Outside,
        ),
    };
    Viewpoint {
        camera,
        placement,
        occupied: Some([lo, hi]),
        candidates: survey.candidates,
        enclosed: survey.enclosed,
        enclosed_fraction: if survey.candidates == 0 {
            0.0
        } else {
            survey.enclosed as f32 / survey.candidates as f32
        },
        interior: survey.interior,
        rays,
    }
}

// ---- occupied box -------------------------------------------------------------------------------

/// Where the content is: the voxel box, and the boxes whose hull the outside view frames.
struct Occupancy {
    lo: [u32; 3],
    /// Exclusive.
    hi: [u32; 3],
    /// Per column of bricks (or of regions, for maps with more than [`HULL_CELL_REGIONS`]
    /// non-empty regions): the box from its lowest to its highest non-empty brick (region), as
    /// voxel `[min, max)`, not yet clipped to `lo..hi`.
    columns: Vec<[[u32; 3]; 2]>,
}

/// Most non-empty regions whose bricks are read to build the outside hull per brick column;
/// beyond it the hull is per region column, which bounds the cost on huge dense maps.
pub const HULL_CELL_REGIONS: usize = 1 << 16;

impl Occupancy {
    fn of(map: &BrickMap) -> Option<Occupancy> {
        let rd = map.region_dims();
        let regions = map.regions();
        let mut region_span: Vec<Option<(u32, u32)>> = vec![None; (rd[0] * rd[2]) as usize];
        let (mut rlo, mut rhi) = ([u32::MAX; 3], [0u32; 3]);
        let mut occupied = 0usize;
        for (i, &entry) in regions.iter().enumerate() {
            if region_is_empty(entry) {
                continue;
            }
            occupied += 1;
            let i = i as u32;
            let r = [i % rd[0], i / rd[0] % rd[1], i / rd[0] / rd[1]];
            for a in 0..3 {
                rlo[a] = rlo[a].min(r[a]);
                rhi[a] = rhi[a].max(r[a]);
            }
            if let Some(span) = region_span.get_mut((r[0] + rd[0] * r[2]) as usize) {
                *span = Some(widen(*span, r[1]));
            }
        }
        if rlo[0] > rhi[0] {
            return None;
        }
        let size = map.size();
        // Region-accurate, then each face refined to voxels from the bricks on it.
        let mut lo: [u32; 3] = std::array::from_fn(|a| rlo[a] * REGION_EDGE);
        let mut hi: [u32; 3] = std::array::from_fn(|a| ((rhi[a] + 1) * REGION_EDGE).min(size[a]));
        for axis in 0..3 {
            for high in [false, true] {
                if let Some(v) = refine_face(map, rlo, rhi, axis, high) {
                    if high {
                        hi[axis] = v + 1;
                    } else {
                        lo[axis] = v;
                    }
                }
            }
        }
        let hi = std::array::from_fn(|a| hi[a].clamp(lo[a] + 1, size[a].max(lo[a] + 1)));
        let columns = if occupied <= HULL_CELL_REGIONS {
            brick_columns(map, rlo, rhi)
        } else {
            region_span
                .iter()
                .enumerate()
                .filter_map(|(i, span)| {
                    let (y0, y1) = (*span)?;
                    let (rx, rz) = (i as u32 % rd[0], i as u32 / rd[0]);
                    Some([
                        [rx, y0, rz].map(|c| c * REGION_EDGE),
                        [rx + 1, y1 + 1, rz + 1].map(|c| c * REGION_EDGE),
                    ])
                })
                .collect()
        };
        Some(Occupancy { lo, hi, columns })
    }
}

/// The bricks of region `r` (region coordinates): each one's cell inside the region and its
/// slot. Nothing for an empty region or one outside the grid.
fn region_bricks(map: &BrickMap, r: [u32; 3]) -> impl Iterator<Item = ([u32; 3], u32)> + '_ {
    let rd = map.region_dims();
    let inside = (0..3).all(|i| r[i] < rd[i]);
    let index = (r[0] + rd[0] * (r[1] + rd[1] * r[2])) as usize;
    let block = map
        .regions()
        .get(index)
        .copied()
        .filter(|_| inside)
        .and_then(crate::map::region_block);
    block.into_iter().flat_map(move |block| {
        (0..CELLS_PER_BLOCK).filter_map(move |local| {
            let slot = *map
                .cells()
                .get((block * CELLS_PER_BLOCK + local) as usize)?;
            (!cell_is_empty(slot))
                .then_some(([local & 3, (local >> 2) & 3, (local >> 4) & 3], slot))
        })
    })
}

/// `span` grown to include `y`.
fn widen(span: Option<(u32, u32)>, y: u32) -> (u32, u32) {
    match span {
        Some((a, b)) => (a.min(y), b.max(y)),
        None => (y, y),
    }
}

/// Per brick column, the box from its lowest to its highest solid voxel, in voxels `[min, max)`
/// (brick-accurate across, voxel-accurate up). Reads the cells of every non-empty region in the
/// region box `rlo..=rhi`, one slab of regions (4 brick rows along z) at a time.
fn brick_columns(map: &BrickMap, rlo: [u32; 3], rhi: [u32; 3]) -> Vec<[[u32; 3]; 2]> {
    /// Lowest and highest brick of a column: (brick row, slot) each.
    type Span = ((u32, u32), (u32, u32));
    let masks = map.masks();
    let width = (rhi[0] - rlo[0] + 1) * REGION_CELLS;
    let mut out = Vec::new();
    let mut spans: Vec<Option<Span>> = vec![None; (width * REGION_CELLS) as usize];
    for rz in rlo[2]..=rhi[2] {
        spans.fill(None);
        for ry in rlo[1]..=rhi[1] {
            for rx in rlo[0]..=rhi[0] {
                for (l, slot) in region_bricks(map, [rx, ry, rz]) {
                    let column = (rx - rlo[0]) * REGION_CELLS + l[0] + width * l[2];
                    let here = (ry * REGION_CELLS + l[1], slot);
                    if let Some(span) = spans.get_mut(column as usize) {
                        *span = Some(match *span {
                            Some((low, high)) => (
                                if here.0 < low.0 { here } else { low },
                                if here.0 > high.0 { here } else { high },
                            ),
                            None => (here, here),
                        });
                    }
                }
            }
        }
        for (i, span) in spans.iter().enumerate() {
            let Some(((y0, slot0), (y1, slot1))) = *span else {
                continue;
            };
            let extent = |slot: u32| {
                masks
                    .get(slot as usize)
                    .and_then(|m| mask_extent(m, 1))
                    .unwrap_or((0, BRICK_EDGE - 1))
            };
            let (cx, cz) = (
                rlo[0] * REGION_CELLS + i as u32 % width,
                rz * REGION_CELLS + i as u32 / width,
            );
            out.push([
                [
                    cx * BRICK_EDGE,
                    y0 * BRICK_EDGE + extent(slot0).0,
                    cz * BRICK_EDGE,
                ],
                [
                    (cx + 1) * BRICK_EDGE,
                    y1 * BRICK_EDGE + extent(slot1).1 + 1,
                    (cz + 1) * BRICK_EDGE,
                ],
            ]);
        }
    }
    out
}

/// The extreme solid voxel coordinate on `axis` (lowest, or highest when `high`) among the
/// regions on that face of the region box `rlo..=rhi`.
fn refine_face(
    map: &BrickMap,
    rlo: [u32; 3],
    rhi: [u32; 3],
    axis: usize,
    high: bool,
) -> Option<u32> {
    let masks = map.masks();
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let mut best: Option<u32> = None;
    for ru in rlo[u]..=rhi[u] {
        for rv in rlo[v]..=rhi[v] {
            let mut r = [0u32; 3];
            r[axis] = if high { rhi[axis] } else { rlo[axis] };
            r[u] = ru;
            r[v] = rv;
            for (l, slot) in region_bricks(map, r) {
                let cell = r[axis] * REGION_CELLS + l[axis];
                // Skip bricks that cannot beat the best so far.
                let base = cell * BRICK_EDGE;
                match best {
                    Some(b) if high && base + BRICK_EDGE - 1 <= b => continue,
                    Some(b) if !high && base >= b => continue,
                    _ => {}
                }
                let Some(mask) = masks.get(slot as usize) else {
                    continue;
                };
                let Some((min, max)) = mask_extent(mask, axis) else {
                    continue;
                };
                let voxel = base + if high { max } else { min };
                best = Some(match best {
                    Some(b) if high => b.max(voxel),
                    Some(b) => b.min(voxel),
                    None => voxel,
                });
            }
        }
    }
    best
}

/// The lowest and highest solid local coordinate of a brick mask along `axis`.
fn mask_extent(mask: &Mask, axis: usize) -> Option<(u32, u32)> {
    let all = mask.iter().fold(0u64, |a, &w| a | w);
    if all == 0 {
        return None;
    }
    Some(match axis {
        0 => {
            let row = (0..8).fold(0u8, |a, y| a | (all >> (8 * y)) as u8);
            (row.trailing_zeros(), 7 - row.leading_zeros())
        }
        1 => (all.trailing_zeros() / 8, (63 - all.leading_zeros()) / 8),
        _ => {
            let first = mask.iter().position(|&w| w != 0).unwrap_or(0) as u32;
            let last = mask.iter().rposition(|&w| w != 0).unwrap_or(7) as u32;
            (first, last)
        }
    })
}

// ---- probing ------------------------------------------------------------------------------------

/// An enclosed candidate and what its probes found.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    voxel: [u32; 3],
    score: f32,
    /// The solid voxel row below and above (y), or -1 / the grid height where there is none.
    floor: i64,
    ceiling: i64,
}

/// What probing the lattice found.
struct Survey {
    candidates: u32,
    enclosed: u32,
    /// Interior hits found, up to [`INTERIOR_HITS`].
    interior: u32,
    rays: u32,
    best: Option<Candidate>,
}

/// The fixed probe directions: a Fibonacci sphere, unit length.
fn probe_directions() -> [[f32; 3]; PROBES] {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    std::array::from_fn(|i| {
        let y = 1.0 - (i as f64 + 0.5) * 2.0 / PROBES as f64;
        let r = (1.0 - y * y).max(0.0).sqrt();
        let phi = golden * i as f64;
        [(r * phi.cos()) as f32, y as f32, (r * phi.sin()) as f32]
    })
}

/// Evenly spread voxel coordinates over `lo..hi`, `n` of them, repeats dropped.
fn spread(lo: u32, hi: u32, n: u32) -> Vec<u32> {
    let extent = u64::from(hi.saturating_sub(lo).max(1));
    let mut out: Vec<u32> = (0..u64::from(n))
        .map(|k| lo + ((2 * k + 1) * extent / (2 * u64::from(n))) as u32)
        .collect();
    out.dedup();
    out
}

/// Whether the ray from `origin` along `dir` (unit), which first meets a solid at `t`, meets
/// another solid past it: it steps through the solid in quarter voxels (at most
/// [`WALL_DEPTH`]; a thicker solid counts as the shell) and traces on from the first empty
/// voxel. Leaving the grid first means nothing is beyond.
fn solid_beyond(map: &BrickMap, origin: [f32; 3], dir: [f32; 3], t: f32) -> bool {
    let size = map.size();
    let mut d = t;
    while d < t + WALL_DEPTH {
        d += 0.25;
        let p: [f32; 3] = std::array::from_fn(|a| origin[a] + dir[a] * d);
        if (0..3).any(|a| !(p[a] >= 0.0 && p[a] < size[a] as f32)) {
            return false;
        }
        if !map.is_solid(p.map(|c| c as u32)) {
            return trace(map, &Ray { origin: p, dir }).is_some();
        }
    }
    false
}

fn centre(v: [u32; 3]) -> [f32; 3] {
    v.map(|c| c as f32 + 0.5)
}

/// Probes every lattice candidate in the occupied box `lo..hi`.
fn survey(map: &BrickMap, lo: [u32; 3], hi: [u32; 3]) -> Survey {
    let dirs = probe_directions();
    let axes: [Vec<u32>; 3] = std::array::from_fn(|a| spread(lo[a], hi[a], LATTICE[a]));
    let mut s = Survey {
        candidates: 0,
        enclosed: 0,
        interior: 0,
        rays: 0,
        best: None,
    };
    let mut distances = Vec::with_capacity(PROBES);
    for &z in &axes[2] {
        for &y in &axes[1] {
            for &x in &axes[0] {
                let voxel = [x, y, z];
                if map.is_solid(voxel) {
                    continue;
                }
                s.candidates += 1;
                let origin = centre(voxel);
                distances.clear();
                let mut misses = 0;
                for dir in &dirs {
                    s.rays += 1;
                    match trace(map, &Ray { origin, dir: *dir }) {
                        Some(hit) => distances.push(hit.t),
                        None => {
                            misses += 1;
                            if misses > PROBES - ENCLOSED_HITS {
                                break;
                            }
                            distances.push(f32::INFINITY);
                        }
                    }
                }
                if misses > PROBES - ENCLOSED_HITS {
                    continue;
                }
                s.enclosed += 1;
                for (dir, &t) in dirs.iter().zip(&distances) {
                    if s.interior >= INTERIOR_HITS {
                        break;
                    }
                    if t.is_finite() {
                        s.rays += 1;
                        s.interior += u32::from(solid_beyond(map, origin, *dir, t));
                    }
                }
                distances.sort_by(f32::total_cmp);
                let median = distances[PROBES / 2];
                let vertical = |dy: f32| {
                    trace(
                        map,
                        &Ray {
                            origin,
                            dir: [0.0, dy, 0.0],
                        },
                    )
                    .map(|h| i64::from(h.voxel[1]))
                };
                s.rays += 2;
                let floor = vertical(-1.0).unwrap_or(-1);
                let ceiling = vertical(1.0).unwrap_or(i64::from(map.size()[1]));
                let rel = (i64::from(y) - floor) as f32 / (ceiling - floor).max(1) as f32;
                let score = if rel > 0.5 {
                    median * UPPER_HALF_WEIGHT
                } else {
                    median
                };
                if s.best.is_none_or(|b| score > b.score) {
                    s.best = Some(Candidate {
                        voxel,
                        score,
                        floor,
                        ceiling,
                    });
                }
            }
        }
    }
    s
}

// ---- inside -------------------------------------------------------------------------------------

/// The inside camera from the best enclosed candidate (module docs, step 5).
fn inside_camera(map: &BrickMap, best: &Candidate, fov_y: f32, rays: &mut u32) -> Camera {
    let size = map.size();
    let mut eye = best.voxel;
    // Free voxels of the column are floor+1 ..= ceiling-1; the candidate is one of them.
    let (free_lo, free_hi) = (best.floor + 1, best.ceiling - 1);
    if free_hi >= free_lo {
        let y = free_lo + (EYE_HEIGHT * (free_hi - free_lo) as f32) as i64;
        eye[1] = y.clamp(free_lo, free_hi) as u32;
    }
    let eye = nudge(map, eye);
    let mut free_along = |eye: [u32; 3], dir: [f32; 3]| {
        *rays += 1;
        let origin = centre(eye);
        match trace(map, &Ray { origin, dir }) {
            Some(hit) => hit.t,
            None => exit_distance(size, origin, dir),
        }
    };
    let mut best_dir = ([1.0f32, 0.0, 0.0], 0.0f32);
    for k in 0..LOOK_DIRECTIONS {
        let angle = k as f64 * std::f64::consts::TAU / LOOK_DIRECTIONS as f64;
        let snap = |c: f64| if c.abs() < 1e-6 { 0.0 } else { c as f32 };
        let dir = [snap(angle.cos()), 0.0, snap(angle.sin())];
        let free = free_along(eye, dir);
        if free > best_dir.1 {
            best_dir = (dir, free);
        }
    }
    let (dir, mut free) = best_dir;
    // Step back against the view, so the view takes in the room rather than the middle of it.
    let back = free_along(eye, dir.map(|c| -c)) * STEP_BACK;
    let moved: [i64; 3] = std::array::from_fn(|i| {
        let c = f64::from(centre(eye)[i]) - f64::from(dir[i]) * f64::from(back);
        (c.floor() as i64).clamp(0, i64::from(size[i]) - 1)
    });
    let moved = moved.map(|c| c as u32);
    let mut eye = eye;
    if moved != eye && !map.is_solid(moved) {
        let moved = nudge(map, moved);
        let ahead = free_along(moved, dir);
        if ahead > free {
            (eye, free) = (moved, ahead);
        }
    }
    let origin = centre(eye);
    let reach = (free * 0.5).max(1.0);
    let (sin, cos) = LOOK_DOWN_DEGREES.to_radians().sin_cos();
    let target = [
        origin[0] + dir[0] * cos * reach,
        origin[1] - sin * reach,
        origin[2] + dir[2] * cos * reach,
    ];
    Camera {
        eye: origin,
        target,
        fov_y,
    }
}

/// Distance along a unit `dir` from `origin` (inside the grid) to the grid's edge.
fn exit_distance(size: [u32; 3], origin: [f32; 3], dir: [f32; 3]) -> f32 {
    (0..3)
        .filter(|&i| dir[i] != 0.0)
        .map(|i| {
            let plane = if dir[i] > 0.0 { size[i] as f32 } else { 0.0 };
            (plane - origin[i]) / dir[i]
        })
        .fold(f32::INFINITY, f32::min)
        .max(0.0)
}

/// The nearest empty voxel within [`NUDGE`] of `eye` with [`CLEARANCE`] (then 1) empty voxels
/// all round, inside the grid; `eye` itself when there is none.
fn nudge(map: &BrickMap, eye: [u32; 3]) -> [u32; 3] {
    const R: i32 = NUDGE + CLEARANCE;
    const W: i32 = 2 * R + 1;
    let size = map.size();
    // Solid or outside the grid, for the (2R+1)³ voxels around the eye.
    let mut blocked = vec![true; (W * W * W) as usize];
    let at = |d: [i32; 3]| ((d[0] + R) + W * ((d[1] + R) + W * (d[2] + R))) as usize;
    for dz in -R..=R {
        for dy in -R..=R {
            for dx in -R..=R {
                let d = [dx, dy, dz];
                let v: [i64; 3] = std::array::from_fn(|i| i64::from(eye[i]) + i64::from(d[i]));
                if (0..3).all(|i| v[i] >= 0 && v[i] < i64::from(size[i])) {
                    let v = v.map(|c| c as u32);
                    blocked[at(d)] = map.is_solid(v);
                }
            }
        }
    }
    for clearance in [CLEARANCE, 1] {
        let mut found: Option<([i32; 3], i32)> = None;
        for dz in -NUDGE..=NUDGE {
            for dy in -NUDGE..=NUDGE {
                for dx in -NUDGE..=NUDGE {
                    let d2 = dx * dx + dy * dy + dz * dz;
                    if found.is_some_and(|(_, best)| best <= d2) {
                        continue;
                    }
                    let clear = (-clearance..=clearance).all(|ez| {
                        (-clearance..=clearance).all(|ey| {
                            (-clearance..=clearance)
                                .all(|ex| !blocked[at([dx + ex, dy + ey, dz + ez])])
                        })
                    });
                    if clear {
                        found = Some(([dx, dy, dz], d2));
                    }
                }
            }
        }
        if let Some((d, _)) = found {
            return std::array::from_fn(|i| (i64::from(eye[i]) + i64::from(d[i])) as u32);
        }
    }
    eye
}

// ---- outside ------------------------------------------------------------------------------------

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn unit(a: [f32; 3]) -> Option<[f32; 3]> {
    let len = dot(a, a).sqrt();
    (len > 1e-12 && len.is_finite()).then(|| a.map(|c| c / len))
}

/// The outside camera framing the content's hull (module docs, step 6); `None` only if the
/// arithmetic degenerates, which the caller answers with the overview.
fn outside_camera(occupancy: &Occupancy, fov_y: f32) -> Option<Camera> {
    let (lo, hi) = (
        occupancy.lo.map(|c| c as f32),
        occupancy.hi.map(|c| c as f32),
    );
    let forward = unit(OUTSIDE_DIRECTION.map(|c| -c))?;
    // The same basis Camera::project builds, so the fit holds for the frame it renders.
    let right = unit([-forward[2], 0.0, forward[0]])?;
    let up = [
        right[1] * forward[2] - right[2] * forward[1],
        right[2] * forward[0] - right[0] * forward[2],
        right[0] * forward[1] - right[1] * forward[0],
    ];
    let tv = (fov_y.to_radians() * 0.5).tan() * FRAME_FILL;
    let th = tv * FRAME_ASPECT;
    // Bounds of x − th·z, x + th·z, y − tv·z, y + tv·z over all hull corners.
    let (mut a, mut b, mut c, mut d) = (
        f32::NEG_INFINITY,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::INFINITY,
    );
    for [cmin, cmax] in &occupancy.columns {
        let bmin: [f32; 3] = std::array::from_fn(|i| (cmin[i] as f32).clamp(lo[i], hi[i]));
        let bmax: [f32; 3] = std::array::from_fn(|i| (cmax[i] as f32).clamp(lo[i], hi[i]));
        for corner in 0..8 {
            let p: [f32; 3] = std::array::from_fn(|i| {
                if corner >> i & 1 == 0 {
                    bmin[i]
                } else {
                    bmax[i]
                }
            });
            let (px, py, pz) = (dot(p, right), dot(p, up), dot(p, forward));
            a = a.max(px - th * pz);
            b = b.min(px + th * pz);
            c = c.max(py - tv * pz);
            d = d.min(py + tv * pz);
        }
    }
    let ez = ((b - a) / (2.0 * th)).min((d - c) / (2.0 * tv));
    let (ex, ey) = ((a + b) * 0.5, (c + d) * 0.5);
    let eye: [f32; 3] = std::array::from_fn(|i| right[i] * ex + up[i] * ey + forward[i] * ez);
    let middle: [f32; 3] = std::array::from_fn(|i| (lo[i] + hi[i]) * 0.5);
    let depth = (dot(middle, forward) - ez).max(1.0);
    let target: [f32; 3] = std::array::from_fn(|i| eye[i] + forward[i] * depth);
    let camera = Camera { eye, target, fov_y };
    (eye.iter().chain(&target).all(|v| v.is_finite()) && camera.project(16, 9).is_some())
        .then_some(camera)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colour::Colour;
    use crate::demo::{ROOM_WALL, demo_scene, room_scene};
    use crate::map::BrushMode;

    /// Traces a 64×36 frame: how many pixels hit, and the hit distances.
    fn look(map: &BrickMap, camera: &Camera) -> (usize, Vec<f32>) {
        let projection = camera.project(64, 36).expect("a usable camera");
        let mut distances = Vec::new();
        for y in 0..36 {
            for x in 0..64 {
                let ray = projection.ray(x, y);
                if let Some(hit) = trace(map, &ray) {
                    distances.push(hit.t * dot(ray.dir, ray.dir).sqrt());
                }
            }
        }
        (distances.len(), distances)
    }

    #[test]
    fn room_is_viewed_from_inside_along_its_length() {
        let size = [160, 72, 128];
        let map = room_scene(size).unwrap();
        let view = find(&map, 60.0);
        assert_eq!(view.placement, Placement::Inside, "{view:?}");
        assert_eq!(view.occupied, Some([[0, 0, 0], size]));
        assert!(view.rays <= 10_000, "{}", view.rays);
        let eye = view.camera.eye;
        let voxel = eye.map(|c| c.floor() as u32);
        assert!(!map.is_solid(voxel), "eye in an empty voxel: {eye:?}");
        for i in 0..3 {
            assert!(
                voxel[i] >= ROOM_WALL && voxel[i] < size[i] - ROOM_WALL,
                "eye inside the walls: {eye:?}"
            );
        }
        let (hits, mut distances) = look(&map, &view.camera);
        assert_eq!(hits, 64 * 36, "every ray meets the room");
        distances.sort_by(f32::total_cmp);
        let median = distances[distances.len() / 2];
        assert!(
            median > size[0] as f32 / 4.0,
            "looks along the room, not at a wall: median {median} from {view:?}"
        );
        let down = view.camera.target[1] - eye[1];
        assert!(down < 0.0, "tilted down: {view:?}");
        assert_eq!(find(&map, 60.0), view, "deterministic");
    }

    #[test]
    fn inside_eye_keeps_clear_of_solids() {
        let map = room_scene([160, 72, 128]).unwrap();
        let eye = find(&map, 60.0).camera.eye.map(|c| c.floor() as i64);
        for dz in -CLEARANCE..=CLEARANCE {
            for dy in -CLEARANCE..=CLEARANCE {
                for dx in -CLEARANCE..=CLEARANCE {
                    let v = [eye[0] + dx as i64, eye[1] + dy as i64, eye[2] + dz as i64];
                    assert!(!map.is_solid(v.map(|c| c as u32)), "solid at {v:?}");
                }
            }
        }
    }

    #[test]
    fn terrain_is_viewed_from_outside() {
        let map = demo_scene([128, 128, 128]).unwrap();
        let view = find(&map, 55.0);
        assert_eq!(view.placement, Placement::Outside, "{view:?}");
        assert!(view.enclosed_fraction < ENCLOSED_SHARE);
        let (hits, _) = look(&map, &view.camera);
        assert!(hits * 10 >= 64 * 36 * 4, "{hits} of {} pixels hit", 64 * 36);
        // The terrain spans the grid, so the view is much like the overview's.
        let overview = Camera::overview(map.size());
        let along = |c: &Camera| unit(std::array::from_fn(|i| c.target[i] - c.eye[i]));
        let cos = dot(along(&view.camera).unwrap(), along(&overview).unwrap());
        assert!(
            cos > 12f32.to_radians().cos(),
            "view direction off by {}°",
            cos.acos().to_degrees()
        );
        let [lo, hi] = view.occupied.unwrap();
        let middle: [f32; 3] = std::array::from_fn(|i| (lo[i] + hi[i]) as f32 * 0.5);
        let away = |c: &Camera| {
            let d: [f32; 3] = std::array::from_fn(|i| c.eye[i] - middle[i]);
            dot(d, d).sqrt()
        };
        let ratio = away(&view.camera) / away(&overview);
        assert!(
            (0.6..1.5).contains(&ratio),
            "distance {ratio}× the overview's"
        );
    }

    #[test]
    fn small_object_in_a_big_grid_fills_the_frame() {
        let mut map = BrickMap::new([512, 512, 512]).unwrap();
        map.fill_box([490, 3, 12], [499, 12, 21], BrushMode::Fill, Colour::WHITE);
        let view = find(&map, 55.0);
        assert_eq!(view.placement, Placement::Outside);
        assert_eq!(
            view.occupied,
            Some([[490, 3, 12], [500, 13, 22]]),
            "voxel-accurate"
        );
        let (hits, _) = look(&map, &view.camera);
        assert!(hits * 100 >= 64 * 36 * 15, "{hits} pixels hit");
        let (overview_hits, _) = look(&map, &Camera::overview(map.size()));
        assert!(
            overview_hits * 10 < hits,
            "overview: {overview_hits}, framed: {hits}"
        );
    }

    #[test]
    fn occupied_box_is_voxel_accurate_on_every_face() {
        let mut map = BrickMap::new([200, 90, 70]).unwrap();
        map.set([37, 50, 11], Colour::WHITE);
        map.set([150, 5, 64], Colour::WHITE);
        map.set([90, 88, 40], Colour::WHITE);
        let occupancy = Occupancy::of(&map).expect("not empty");
        assert_eq!((occupancy.lo, occupancy.hi), ([37, 5, 11], [151, 89, 65]));
    }

    #[test]
    fn degenerate_maps_get_usable_cameras() {
        let check = |map: &BrickMap, what: &str| {
            for fov in [55.0, 0.0, -3.0, 200.0, f32::NAN, f32::INFINITY] {
                let view = find(map, fov);
                assert!(
                    view.camera.project(64, 36).is_some(),
                    "{what}, fov {fov}: {view:?}"
                );
            }
        };
        check(&BrickMap::new([1, 1, 1]).unwrap(), "empty 1³");
        check(&BrickMap::new([300, 40, 9]).unwrap(), "empty");
        let empty = find(&BrickMap::new([64, 64, 64]).unwrap(), 55.0);
        assert_eq!(empty.camera, Camera::overview([64, 64, 64]));
        assert_eq!(empty.placement, Placement::Outside);
        let mut one = BrickMap::new([1, 1, 1]).unwrap();
        one.set([0, 0, 0], Colour::WHITE);
        check(&one, "solid 1³");
        let mut full = BrickMap::new([20, 12, 9]).unwrap();
        full.fill_box([0, 0, 0], [19, 11, 8], BrushMode::Fill, Colour::WHITE);
        check(&full, "all solid");
        assert_eq!(find(&full, 55.0).placement, Placement::Outside);
        let mut flat = BrickMap::new([64, 1, 64]).unwrap();
        flat.fill_box([0, 0, 0], [63, 0, 63], BrushMode::Fill, Colour::WHITE);
        check(&flat, "one-voxel slab");
        let (hits, _) = look(&flat, &find(&flat, 55.0).camera);
        assert!(hits > 0, "the slab is in view");
    }

    #[test]
    fn a_furnished_box_is_seen_from_inside_an_empty_shell_or_an_open_one_from_outside() {
        let mut map = BrickMap::new([64, 48, 64]).unwrap();
        let grey = Colour::from_rgb8(200, 200, 200);
        map.fill_box([4, 4, 4], [59, 43, 59], BrushMode::Fill, grey);
        map.fill_box([6, 6, 6], [57, 41, 57], BrushMode::Erase, grey);
        // A closed, empty shell (an imported cube): an object, seen from outside, whole.
        let view = find(&map, 60.0);
        assert_eq!(view.placement, Placement::Outside, "{view:?}");
        assert_eq!(view.interior, 0);
        assert!(view.enclosed_fraction >= ENCLOSED_SHARE, "{view:?}");
        let (hits, _) = look(&map, &view.camera);
        assert!(hits > 0, "the shell is in view");
        assert!(
            map.size()
                .iter()
                .zip(view.camera.eye)
                .any(|(&s, e)| e < 4.0 || e > s as f32 - 4.0),
            "the eye is outside the shell: {view:?}"
        );
        // Something inside (two pillars and a table): a room, seen from inside.
        map.fill_box([20, 6, 20], [23, 41, 23], BrushMode::Fill, grey);
        map.fill_box([40, 6, 40], [43, 41, 43], BrushMode::Fill, grey);
        map.fill_box([26, 14, 34], [44, 15, 48], BrushMode::Fill, grey);
        let view = find(&map, 60.0);
        assert_eq!(view.placement, Placement::Inside, "{view:?}");
        assert_eq!(view.interior, INTERIOR_HITS);
        // The same box with its lid off: its candidates see the sky.
        map.fill_box([6, 42, 6], [57, 43, 57], BrushMode::Erase, grey);
        assert_eq!(find(&map, 60.0).placement, Placement::Outside);
    }
}
