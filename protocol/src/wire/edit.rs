//! Edit operations a client asks for, and why the server may refuse one.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::{Limits, MAX_REASON_BYTES, bounded, truncate_utf8};
use crate::colour::Colour;

pub use crate::map::BrushMode;

/// What to do where a ray first hits a solid voxel.
///
/// Clicks are sent as rays rather than resolved voxel positions because the client's picture may
/// be a few deltas behind: the server traces against the authoritative map, so two clients
/// clicking the same spot cannot place two voxels in one cell or dig into a voxel that is gone.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum RayAction {
    /// Empty the voxel that was hit.
    Remove,
    /// Fill the empty cell in front of the hit face (the last empty cell the ray crossed).
    Place { colour: Colour },
    /// Recolour the voxel that was hit.
    Paint { colour: Colour },
    /// Apply a sphere brush centred on the hit voxel.
    Sphere {
        mode: BrushMode,
        radius: f32,
        colour: Colour,
    },
    /// Flood fill: recolour the hit voxel and every voxel of its colour connected to it
    /// through faces. Refused ([`Rejection::TooLarge`]) when that region holds more than
    /// `limit` voxels (at most [`Limits::max_tool_voxels`]), so a fill never runs away.
    Fill { colour: Colour, limit: u32 },
    /// Face extrude (`out`) or intrude: the face under the ray and every face of the same
    /// plane and colour connected to it (voxels side by side whose neighbour in front is
    /// empty) grow by one layer of that colour, or lose that layer. At most `limit` voxels.
    Extrude { out: bool, limit: u32 },
}

/// What a two-point edit ([`EditOp::Span`]) draws between its two points.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Shape {
    /// The box with the two points as opposite corners.
    Box,
    /// A line one voxel thick from one point to the other.
    Line,
}

/// One requested change to the scene, in voxel coordinates.
///
/// Ops are small and self-contained so that a batch can be applied partially: each op either
/// applies or earns an [`OpRejection`](super::OpRejection) with its index, and the client can
/// tell the user which of its edits did not land.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum EditOp {
    /// Make one voxel solid with a colour.
    Set { pos: [u32; 3], colour: Colour },
    /// Make one voxel empty.
    Clear { pos: [u32; 3] },
    /// Recolour one voxel if it is solid.
    Paint { pos: [u32; 3], colour: Colour },
    /// A sphere brush; the centre may be fractional so brushes follow the cursor smoothly.
    Sphere {
        centre: [f32; 3],
        radius: f32,
        mode: BrushMode,
        colour: Colour,
    },
    /// A box brush; `min` and `max` are both inclusive.
    Box {
        min: [u32; 3],
        max: [u32; 3],
        mode: BrushMode,
        colour: Colour,
    },
    /// Resolved by the server's own tracer, see [`RayAction`]. `dir` need not be normalised.
    Ray {
        origin: [f32; 3],
        dir: [f32; 3],
        action: RayAction,
    },
    /// A box or a line between the voxels two rays hit (a drag from one to the other), both
    /// resolved by the server's tracer like [`EditOp::Ray`]: filling starts from the empty
    /// cells in front of the hits, erasing and painting from the voxels hit. `extent` is the
    /// most voxels the shape may span along an axis (at most [`Limits::max_box_extent`]): the
    /// server charges for that much and refuses a larger one.
    Span {
        from: [f32; 3],
        from_dir: [f32; 3],
        to: [f32; 3],
        to_dir: [f32; 3],
        shape: Shape,
        mode: BrushMode,
        colour: Colour,
        extent: u32,
    },
    /// Sets swatch `index` of the scene's shared palette ([`crate::swatches`]) to `colour`.
    /// Changes no voxel (and so is no undo step); every client hears the new palette.
    Swatch { index: u8, colour: Colour },
    /// Copies the box `min..=max` (inclusive) of the scene, as this op finds it in the scene's
    /// order, into the editing user's clipboard on the server ([`crate::clipboard`]), replacing
    /// what it held; any scene on that server may paste it. Changes no voxel; no undo step. At
    /// most [`Limits::max_box_extent`] along each axis.
    Copy { min: [u32; 3], max: [u32; 3] },
    /// Pastes the user's clipboard with its lowest corner at `at`, mirrored along x if
    /// `mirror`, then turned `turns` quarter turns about the vertical axis
    /// ([`crate::clipboard`]): its solid voxels replace what is there, its empty ones leave it,
    /// voxels past the scene are dropped. `size` is the pasted box's size as the client
    /// believes it (the copied box, turned): the server charges for it and refuses a paste
    /// whose clipboard is another size. Alone in its message; one undo step; logged as the
    /// voxels it changed.
    Paste {
        at: [u32; 3],
        size: [u32; 3],
        turns: u8,
        mirror: bool,
    },
    /// Restores the box `min..=max` (inclusive) to how it was at sequence `to` of the scene
    /// ([`crate::rewind`]): every voxel of the box as it was then, solid or empty; nothing
    /// outside it. Only a server that keeps the scene's past serves it (refused otherwise,
    /// saying which sequences it keeps). Alone in its message; one undo step, which others'
    /// later edits win over like any other; logged as the voxels it changed.
    Restore {
        to: u64,
        min: [u32; 3],
        max: [u32; 3],
    },
}

impl EditOp {
    /// Checks what can be checked without looking at the scene's contents: coordinates inside a
    /// scene of `scene_size` voxels, finite numbers, and brush sizes within `limits`.
    ///
    /// Ray ops pass here even if they will miss; the tracer decides [`Rejection::RayMissed`] and
    /// [`Rejection::NothingToPlace`]. Ray origins may lie outside the scene (a camera usually
    /// does); the tracer clips the ray to the scene box.
    pub fn validate(&self, scene_size: [u32; 3], limits: &Limits) -> Result<(), Rejection> {
        match *self {
            EditOp::Set { pos, .. } | EditOp::Clear { pos } | EditOp::Paint { pos, .. } => {
                if per_axis(pos, scene_size, |p, s| p < s) {
                    Ok(())
                } else {
                    Err(Rejection::OutOfBounds)
                }
            }
            EditOp::Sphere { centre, radius, .. } => {
                if !centre.iter().all(|c| c.is_finite()) {
                    return Err(Rejection::InvalidNumber);
                }
                if !per_axis(centre, scene_size, |c, s| c >= 0.0 && c <= s as f32) {
                    return Err(Rejection::OutOfBounds);
                }
                check_radius(radius, limits)
            }
            EditOp::Box { min, max, .. } => {
                if !per_axis(min, max, |lo, hi| lo <= hi) {
                    return Err(Rejection::malformed("box min is above max"));
                }
                if !per_axis(max, scene_size, |hi, s| hi < s) {
                    return Err(Rejection::OutOfBounds);
                }
                // `max - min + 1 <= extent`, without the `+ 1` overflowing at u32::MAX.
                let extent_ok = per_axis(min, max, |lo, hi| {
                    hi.saturating_sub(lo) < limits.max_box_extent
                });
                if extent_ok {
                    Ok(())
                } else {
                    Err(Rejection::TooLarge)
                }
            }
            EditOp::Ray {
                origin,
                dir,
                action,
            } => {
                check_ray(origin, dir)?;
                match action {
                    RayAction::Sphere { radius, .. } => check_radius(radius, limits),
                    RayAction::Fill { limit, .. } | RayAction::Extrude { limit, .. } => {
                        if limit == 0 {
                            Err(Rejection::malformed("a tool's voxel limit is 0"))
                        } else if limit > limits.max_tool_voxels {
                            Err(Rejection::TooLarge)
                        } else {
                            Ok(())
                        }
                    }
                    RayAction::Remove | RayAction::Place { .. } | RayAction::Paint { .. } => Ok(()),
                }
            }
            EditOp::Span {
                from,
                from_dir,
                to,
                to_dir,
                extent,
                ..
            } => {
                check_ray(from, from_dir)?;
                check_ray(to, to_dir)?;
                if extent == 0 {
                    Err(Rejection::malformed("a span's extent is 0"))
                } else if extent > limits.max_box_extent {
                    Err(Rejection::TooLarge)
                } else {
                    Ok(())
                }
            }
            EditOp::Copy { min, max } => {
                if !per_axis(min, max, |lo, hi| lo <= hi) {
                    return Err(Rejection::malformed("a copy's min is above its max"));
                }
                if !per_axis(max, scene_size, |hi, s| hi < s) {
                    return Err(Rejection::OutOfBounds);
                }
                let extent: [u32; 3] = std::array::from_fn(|i| max[i] - min[i] + 1);
                if per_axis(min, max, |lo, hi| hi - lo < limits.max_box_extent)
                    && fits_an_index(extent)
                {
                    Ok(())
                } else {
                    Err(Rejection::TooLarge)
                }
            }
            EditOp::Paste {
                at, size, turns, ..
            } => {
                if turns > 3 {
                    return Err(Rejection::malformed("a paste turns 0 to 3 quarter turns"));
                }
                if !per_axis(at, scene_size, |a, s| a < s) {
                    return Err(Rejection::OutOfBounds);
                }
                if size.contains(&0) {
                    return Err(Rejection::malformed("a paste's size is 0"));
                }
                if size.iter().all(|&e| e <= limits.max_box_extent) && fits_an_index(size) {
                    Ok(())
                } else {
                    Err(Rejection::TooLarge)
                }
            }
            EditOp::Restore { min, max, .. } => {
                if !per_axis(min, max, |lo, hi| lo <= hi) {
                    return Err(Rejection::malformed("a restore's min is above its max"));
                }
                if !per_axis(max, scene_size, |hi, s| hi < s) {
                    return Err(Rejection::OutOfBounds);
                }
                Ok(())
            }
            EditOp::Swatch { index, .. } => {
                if usize::from(index) < crate::swatches::SWATCHES {
                    Ok(())
                } else {
                    Err(Rejection::malformed(format!(
                        "there is no swatch {index}: a palette has {}",
                        crate::swatches::SWATCHES
                    )))
                }
            }
        }
    }

    /// Whether applying the op reads the map (a ray's target, a fill's region): such ops are
    /// resolved in the turn that applies them, never planned ahead.
    pub fn reads_map(&self) -> bool {
        matches!(
            self,
            EditOp::Ray { .. }
                | EditOp::Span { .. }
                | EditOp::Copy { .. }
                | EditOp::Paste { .. }
                | EditOp::Restore { .. }
        )
    }

    /// Whether the op changes no voxel, so a message of only such ops is no undo step: a
    /// swatch, a copy.
    pub fn keeps_voxels(&self) -> bool {
        matches!(self, EditOp::Swatch { .. } | EditOp::Copy { .. })
    }
}

/// Whether a box of `extent` voxels numbers them in a `u32` (a clipboard's index), whatever
/// box limit a server announces.
fn fits_an_index(extent: [u32; 3]) -> bool {
    extent.iter().map(|&e| u64::from(e)).product::<u64>() <= u64::from(u32::MAX)
}

/// A ray's numbers: finite, and a direction that is not zero.
fn check_ray(origin: [f32; 3], dir: [f32; 3]) -> Result<(), Rejection> {
    if !origin.iter().chain(&dir).all(|v| v.is_finite()) {
        return Err(Rejection::InvalidNumber);
    }
    let len2: f64 = dir.iter().map(|&d| f64::from(d) * f64::from(d)).sum();
    if len2 <= 1e-12 {
        return Err(Rejection::InvalidNumber);
    }
    Ok(())
}

/// What one voxel of a fill's or an extrude's limit is charged, in brush voxels: finding and
/// changing a region costs about 33 times what painting the same voxels with a box brush does
/// (`cargo bench -p brickcast-protocol --bench protocol -- tools/`, BENCHMARKS.md).
pub const TOOL_VOXEL_WORK: u64 = 32;

/// Bricks a box of voxels touches (clipped to the scene).
fn bricks_of(min: [u32; 3], max: [u32; 3], scene_size: [u32; 3]) -> u64 {
    (0..3)
        .map(|i| {
            let hi = max[i].min(scene_size[i].saturating_sub(1)) / 8;
            u64::from(hi.saturating_sub(min[i] / 8)) + 1
        })
        .product()
}

/// Whether `f` holds on every axis.
fn per_axis<A: Copy, B: Copy>(a: [A; 3], b: [B; 3], f: impl Fn(A, B) -> bool) -> bool {
    a.into_iter().zip(b).all(|(a, b)| f(a, b))
}

impl EditOp {
    /// An upper bound on the work applying the op costs the server, in voxels visited, for a
    /// scene of `scene_size`: 1 for a single voxel, the bounding box (clipped to the scene) for
    /// a brush, for a ray the voxels it may cross plus its brush (a fill or extrude:
    /// [`TOOL_VOXEL_WORK`] per voxel of its limit), and for a span two rays plus the box (or
    /// line) of its extent. Brushes rewrite whole
    /// bricks, so the box is what they cost whether or not a voxel changes.
    ///
    /// The server charges edits by this rather than by op count (one sphere of radius 64 costs
    /// two million single-voxel edits), and sizes snapshots by it. Never fails and never
    /// overflows, whatever the op holds; an op that will be rejected still has a cost.
    pub fn work(&self, scene_size: [u32; 3]) -> u64 {
        let sphere = |centre: [f32; 3], radius: f32| -> u64 {
            if !radius.is_finite() || radius <= 0.0 {
                return 1;
            }
            (0..3)
                .map(|i| {
                    let c = if centre[i].is_finite() {
                        centre[i]
                    } else {
                        0.0
                    };
                    let lo = (c - radius).floor().clamp(0.0, scene_size[i] as f32);
                    let hi = (c + radius).ceil().clamp(0.0, scene_size[i] as f32);
                    (hi - lo).max(1.0) as u64
                })
                .product()
        };
        match *self {
            EditOp::Set { .. }
            | EditOp::Clear { .. }
            | EditOp::Paint { .. }
            | EditOp::Swatch { .. } => 1,
            EditOp::Sphere { centre, radius, .. } => sphere(centre, radius),
            EditOp::Box { min, max, .. } => (0..3)
                .map(|i| {
                    let hi = max[i].min(scene_size[i].saturating_sub(1));
                    u64::from(hi.saturating_sub(min[i])) + 1
                })
                .product(),
            // Every brick the box touches is read whole.
            EditOp::Copy { min, max } => bricks_of(min, max, scene_size).saturating_mul(512),
            // The owner looks up each brick of the box's version; the bricks it rewrites (those
            // that differ from then) are bounded by the server apart (`server::scene::rewind`).
            EditOp::Restore { min, max, .. } => bricks_of(min, max, scene_size),
            // Every voxel of the clipboard is placed, even those that land past the scene.
            EditOp::Paste { size, .. } => size.iter().map(|&s| u64::from(s.max(1))).product(),
            EditOp::Ray { action, .. } => {
                // A ray crosses at most the sum of the scene's sides in voxels.
                let walk: u64 = scene_size.iter().map(|&s| u64::from(s)).sum();
                let brush = match action {
                    // Centred on a voxel of the scene: the box of the brush at the scene's middle.
                    RayAction::Sphere { radius, .. } => {
                        sphere(scene_size.map(|s| s as f32 * 0.5), radius)
                    }
                    // The region it may change, and finding it (see `TOOL_VOXEL_WORK`).
                    RayAction::Fill { limit, .. } | RayAction::Extrude { limit, .. } => {
                        TOOL_VOXEL_WORK * u64::from(limit)
                    }
                    _ => 1,
                };
                walk + brush
            }
            EditOp::Span { shape, extent, .. } => {
                let walk: u64 = scene_size.iter().map(|&s| u64::from(s)).sum();
                let side = |i: usize| u64::from(extent.min(scene_size[i]).max(1));
                let drawn = match shape {
                    Shape::Box => side(0) * side(1) * side(2),
                    Shape::Line => side(0) + side(1) + side(2),
                };
                2 * walk + drawn
            }
        }
    }
}

fn check_radius(radius: f32, limits: &Limits) -> Result<(), Rejection> {
    if !radius.is_finite() || radius <= 0.0 {
        Err(Rejection::InvalidNumber)
    } else if radius > limits.max_brush_radius {
        Err(Rejection::TooLarge)
    } else {
        Ok(())
    }
}

/// Why the server did not apply one edit op.
///
/// Rejections are per op and carried in `Ack` rather than being connection errors: a client with
/// a stale picture or a slightly-too-big brush should see its other edits land and learn exactly
/// which one failed. The display text is meant for the user.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Error)]
pub enum Rejection {
    #[error("the edit reaches outside the scene")]
    OutOfBounds,
    #[error("the edit contains a number that is not finite, or a zero-length direction or radius")]
    InvalidNumber,
    #[error("the edit is larger than this server allows")]
    TooLarge,
    #[error("the ray did not hit any voxel")]
    RayMissed,
    #[error("there is no empty cell in front of the hit to place a voxel in")]
    NothingToPlace,
    #[error("this connection may watch but not edit")]
    NotAllowed,
    #[error("too many edits; slow down")]
    RateLimited,
    /// Free text, at most [`MAX_REASON_BYTES`]; build it with [`Rejection::malformed`].
    #[error("malformed edit: {0}")]
    Malformed(#[serde(deserialize_with = "bounded::string::<_, MAX_REASON_BYTES>")] String),
}

impl Rejection {
    /// A `Malformed` rejection whose text is cut to [`MAX_REASON_BYTES`], so that building one
    /// from arbitrary detail can never make the `Ack` unencodable.
    pub fn malformed(reason: impl Into<String>) -> Self {
        Rejection::Malformed(truncate_utf8(reason.into(), MAX_REASON_BYTES))
    }
}
