//! Applying a wire [`EditOp`] to a brick map: the one definition of what an edit means.
//!
//! The server applies ops on the authoritative map; replaying its log at recovery goes through
//! the same function, so a replayed scene is the scene that was acknowledged. Ray ops are
//! resolved here with the CPU tracer against the map being edited (paper 3.3), never against a
//! client's possibly stale copy.

use crate::brick::{BRICK_EDGE, EMPTY_MASK, Mask, mask_set, voxel_bit};
use crate::colour::Colour;
use crate::map::{BrickMap, BrushMode, VoxelBox, box_brushes, sphere_bounds, sphere_brushes};
use crate::region::{face_region, fill_region, line};
use crate::trace::{Hit, Ray, trace};
use crate::wire::{EditOp, Limits, RayAction, Rejection, Shape};

/// An op that passed validation, with a ray op resolved to the voxel or brush it hits: what is
/// left is certain to apply. Splitting the two lets the server stamp the map with a batch's
/// sequence number only once something in the batch applies.
#[derive(Debug, Clone, PartialEq)]
pub enum Resolved {
    Set {
        pos: [u32; 3],
        colour: Colour,
    },
    Clear {
        pos: [u32; 3],
    },
    Paint {
        pos: [u32; 3],
        colour: Colour,
    },
    Sphere {
        centre: [f32; 3],
        radius: f32,
        mode: BrushMode,
        colour: Colour,
    },
    Box {
        min: [u32; 3],
        max: [u32; 3],
        mode: BrushMode,
        colour: Colour,
    },
    /// Voxels a tool found (a fill's region, an extruded face, a line), set, cleared or
    /// painted as `mode` says: a brush mask per brick, in cell order.
    Voxels {
        mode: BrushMode,
        colour: Colour,
        bricks: Vec<([u32; 3], Mask)>,
    },
    /// A swatch of the scene's palette (no voxel).
    Swatch {
        index: u8,
        colour: Colour,
    },
    /// A copy into the user's clipboard (no voxel; the server keeps the clipboard).
    Copy {
        min: [u32; 3],
        max: [u32; 3],
    },
}

/// `voxels` as a brush mask per brick, in cell order (the order they are applied in).
fn brushes_of(voxels: Vec<[u32; 3]>) -> Vec<([u32; 3], Mask)> {
    let mut bricks: std::collections::BTreeMap<[u32; 3], Mask> = std::collections::BTreeMap::new();
    for p in voxels {
        let e = BRICK_EDGE;
        let brush = bricks.entry(p.map(|c| c / e)).or_insert(EMPTY_MASK);
        mask_set(brush, voxel_bit(p[0] % e, p[1] % e, p[2] % e), true);
    }
    bricks.into_iter().collect()
}

/// Where a two-point tool's end lands: filling starts from the empty cell in front of the
/// hit, erasing and painting from the voxel hit. (Viewers size a span with it too.)
pub fn span_end(hit: &Hit, mode: BrushMode) -> Result<[u32; 3], Rejection> {
    match mode {
        BrushMode::Fill => hit.previous.ok_or(Rejection::NothingToPlace),
        BrushMode::Erase | BrushMode::Paint => Ok(hit.voxel),
    }
}

/// Validates `op` against the map's size and `limits` and resolves what it will do, without
/// changing the map. Ray ops are traced here, on the map they will edit.
pub fn resolve(map: &BrickMap, op: &EditOp, limits: &Limits) -> Result<Resolved, Rejection> {
    op.validate(map.size(), limits)?;
    Ok(match *op {
        EditOp::Set { pos, colour } => Resolved::Set { pos, colour },
        EditOp::Clear { pos } => Resolved::Clear { pos },
        EditOp::Paint { pos, colour } => Resolved::Paint { pos, colour },
        EditOp::Sphere {
            centre,
            radius,
            mode,
            colour,
        } => Resolved::Sphere {
            centre,
            radius,
            mode,
            colour,
        },
        EditOp::Box {
            min,
            max,
            mode,
            colour,
        } => Resolved::Box {
            min,
            max,
            mode,
            colour,
        },
        EditOp::Ray {
            origin,
            dir,
            action,
        } => {
            let hit = trace(map, &Ray { origin, dir }).ok_or(Rejection::RayMissed)?;
            match action {
                RayAction::Remove => Resolved::Clear { pos: hit.voxel },
                RayAction::Paint { colour } => Resolved::Paint {
                    pos: hit.voxel,
                    colour,
                },
                RayAction::Place { colour } => Resolved::Set {
                    pos: hit.previous.ok_or(Rejection::NothingToPlace)?,
                    colour,
                },
                RayAction::Sphere {
                    mode,
                    radius,
                    colour,
                } => {
                    // Filling grows out of the surface, so it centres on the empty cell in front
                    // of the hit; erasing and painting centre on the voxel that was hit.
                    let at = match (mode, hit.previous) {
                        (BrushMode::Fill, Some(front)) => front,
                        _ => hit.voxel,
                    };
                    Resolved::Sphere {
                        centre: at.map(|c| c as f32 + 0.5),
                        radius,
                        mode,
                        colour,
                    }
                }
                RayAction::Fill { colour, limit } => Resolved::Voxels {
                    mode: BrushMode::Paint,
                    colour,
                    bricks: brushes_of(fill_region(map, hit.voxel, limit)?),
                },
                RayAction::Extrude { out, limit } => {
                    let front = hit.previous.ok_or(Rejection::NothingToPlace)?;
                    let normal: [i64; 3] =
                        std::array::from_fn(|i| i64::from(front[i]) - i64::from(hit.voxel[i]));
                    let face = face_region(map, hit.voxel, normal, limit)?;
                    // A face is one colour (`face_region`).
                    let colour = face
                        .first()
                        .and_then(|&p| map.get(p))
                        .unwrap_or(Colour::BLACK);
                    let voxels = if out {
                        // In front of each: inside the map, as `face_region` found it.
                        face.into_iter()
                            .map(|p| std::array::from_fn(|i| (i64::from(p[i]) + normal[i]) as u32))
                            .collect()
                    } else {
                        face
                    };
                    Resolved::Voxels {
                        mode: if out {
                            BrushMode::Fill
                        } else {
                            BrushMode::Erase
                        },
                        colour,
                        bricks: brushes_of(voxels),
                    }
                }
            }
        }
        EditOp::Span {
            from,
            from_dir,
            to,
            to_dir,
            shape,
            mode,
            colour,
            extent,
        } => {
            let end = |origin, dir| {
                let hit = trace(map, &Ray { origin, dir }).ok_or(Rejection::RayMissed)?;
                span_end(&hit, mode)
            };
            let (a, b) = (end(from, from_dir)?, end(to, to_dir)?);
            if (0..3).any(|i| a[i].abs_diff(b[i]) >= extent) {
                return Err(Rejection::TooLarge);
            }
            match shape {
                Shape::Box => Resolved::Box {
                    min: std::array::from_fn(|i| a[i].min(b[i])),
                    max: std::array::from_fn(|i| a[i].max(b[i])),
                    mode,
                    colour,
                },
                Shape::Line => Resolved::Voxels {
                    mode,
                    colour,
                    bricks: brushes_of(line(a, b)),
                },
            }
        }
        EditOp::Swatch { index, colour } => Resolved::Swatch { index, colour },
        EditOp::Copy { min, max } => Resolved::Copy { min, max },
        // Only the server holds clipboards: it applies a message of one paste itself
        // (`server/src/scene/paste.rs`) and logs the voxels it changed.
        EditOp::Paste { .. } => {
            return Err(Rejection::malformed("a paste goes alone in its message"));
        }
        // Only the server holds the past (`server/src/scene/rewind.rs`), and logs the voxels
        // a restore changed.
        EditOp::Restore { .. } => {
            return Err(Rejection::malformed("a restore goes alone in its message"));
        }
    })
}

/// Applies a resolved op. Returns the number of voxels whose solidity or colour changed (0 is a
/// valid outcome: clearing air changes nothing).
pub fn apply_resolved(map: &mut BrickMap, op: Resolved) -> u64 {
    match op {
        Resolved::Set { pos, colour } => u64::from(map.set(pos, colour)),
        Resolved::Clear { pos } => u64::from(map.clear(pos)),
        Resolved::Paint { pos, colour } => u64::from(map.paint(pos, colour)),
        Resolved::Sphere {
            centre,
            radius,
            mode,
            colour,
        } => map.sphere(centre, radius, mode, colour),
        Resolved::Box {
            min,
            max,
            mode,
            colour,
        } => map.fill_box(min, max, mode, colour),
        Resolved::Voxels {
            mode,
            colour,
            bricks,
        } => bricks
            .iter()
            .map(|(cell, brush)| map.apply_brush(*cell, brush, mode, colour))
            .sum(),
        Resolved::Swatch { index, colour } => {
            // `resolve` checked the index (validation): a bad one changes nothing here.
            map.set_swatch(usize::from(index), colour);
            0
        }
        Resolved::Copy { .. } => 0,
    }
}

impl Resolved {
    /// The voxels the op may change (not clipped to a scene); `None` when it changes none.
    pub fn bounds(&self) -> Option<VoxelBox> {
        match *self {
            Resolved::Set { pos, .. } | Resolved::Clear { pos } | Resolved::Paint { pos, .. } => {
                Some(VoxelBox { lo: pos, hi: pos })
            }
            Resolved::Sphere { centre, radius, .. } => sphere_bounds(centre, radius),
            Resolved::Box { min, max, .. } => (0..3)
                .all(|i| min[i] <= max[i])
                .then_some(VoxelBox { lo: min, hi: max }),
            Resolved::Voxels { ref bricks, .. } => {
                let e = BRICK_EDGE;
                let mut cells = bricks.iter().map(|(c, _)| *c);
                let first = cells.next()?;
                let (lo, hi) = cells.fold((first, first), |(lo, hi), c| {
                    (
                        std::array::from_fn(|i| lo[i].min(c[i])),
                        std::array::from_fn(|i| hi[i].max(c[i])),
                    )
                });
                // The bricks' box (the voxels' box, rounded out to whole bricks).
                Some(VoxelBox {
                    lo: lo.map(|c| c * e),
                    hi: hi.map(|c| c * e + e - 1),
                })
            }
            Resolved::Swatch { .. } | Resolved::Copy { .. } => None,
        }
    }

    /// Calls `each(cell, brush, mode, colour)` for every brick the op covers inside `within`
    /// (the scene, or a brick-aligned part of it): what [`apply_resolved`] does, brick by
    /// brick, without changing anything. A plan made from these with
    /// [`crate::map::brush_brick`] ends where applying the op would.
    pub fn brushes(
        &self,
        within: VoxelBox,
        mut each: impl FnMut([u32; 3], &Mask, BrushMode, Colour),
    ) {
        let mut voxel = |pos: [u32; 3], mode: BrushMode, colour: Colour| {
            if (0..3).any(|i| pos[i] < within.lo[i] || pos[i] > within.hi[i]) {
                return;
            }
            let mut brush = EMPTY_MASK;
            mask_set(&mut brush, voxel_bit(pos[0], pos[1], pos[2]), true);
            each(pos.map(|p| p / BRICK_EDGE), &brush, mode, colour);
        };
        match *self {
            Resolved::Set { pos, colour } => voxel(pos, BrushMode::Fill, colour),
            Resolved::Clear { pos } => voxel(pos, BrushMode::Erase, Colour::BLACK),
            Resolved::Paint { pos, colour } => voxel(pos, BrushMode::Paint, colour),
            Resolved::Sphere {
                centre,
                radius,
                mode,
                colour,
            } => sphere_brushes(centre, radius, within, |cell, brush| {
                each(cell, brush, mode, colour)
            }),
            Resolved::Box {
                min,
                max,
                mode,
                colour,
            } => box_brushes(min, max, within, |cell, brush| {
                each(cell, brush, mode, colour)
            }),
            Resolved::Voxels {
                mode,
                colour,
                ref bricks,
            } => {
                for (cell, brush) in bricks {
                    let lo = cell.map(|c| c * BRICK_EDGE);
                    let hi = lo.map(|c| c + BRICK_EDGE - 1);
                    let inside = (0..3).all(|i| lo[i] <= within.hi[i] && hi[i] >= within.lo[i]);
                    if inside {
                        each(*cell, brush, mode, colour);
                    }
                }
            }
            Resolved::Swatch { .. } | Resolved::Copy { .. } => {}
        }
    }
}

/// Validates `op` against the map's size and `limits`, then applies it: [`resolve`] then
/// [`apply_resolved`]. Returns the number of voxels changed. A rejected op leaves the map
/// untouched.
pub fn apply_op(map: &mut BrickMap, op: &EditOp, limits: &Limits) -> Result<u64, Rejection> {
    let resolved = resolve(map, op, limits)?;
    Ok(apply_resolved(map, resolved))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_swatch_sets_the_palette_and_changes_no_voxel() {
        let mut map = ground();
        let (hash, red) = (map.content_hash(), Colour::from_rgb8(255, 0, 0));
        let limits = Limits::default();
        let set = EditOp::Swatch {
            index: 31,
            colour: red,
        };
        assert_eq!(apply_op(&mut map, &set, &limits), Ok(0));
        assert_eq!(map.swatches().get(31), red);
        assert_ne!(map.content_hash(), hash, "the palette is part of the scene");
        assert_eq!(resolve(&map, &set, &limits).unwrap().bounds(), None);
        let before = *map.swatches();
        let past = EditOp::Swatch {
            index: 32,
            colour: Colour::WHITE,
        };
        assert!(matches!(
            apply_op(&mut map, &past, &limits),
            Err(Rejection::Malformed(_))
        ));
        assert_eq!(map.swatches(), &before);
        // The hash sees where each swatch is: two groups of four swapped hash otherwise.
        let mut swapped = before;
        swapped.0[..8].rotate_left(4);
        assert_ne!(swapped, before);
        let hash = map.content_hash();
        map.set_swatches(swapped);
        assert_ne!(map.content_hash(), hash);
    }

    fn ground() -> BrickMap {
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 9, 63], BrushMode::Fill, Colour::WHITE);
        map
    }

    fn down_at(x: f32, z: f32) -> ([f32; 3], [f32; 3]) {
        ([x, 60.0, z], [0.0, -1.0, 0.0])
    }

    #[test]
    fn ray_edits_resolve_on_the_map() {
        let mut map = ground();
        let limits = Limits::default();
        let red = Colour::from_rgb8(255, 0, 0);
        let (origin, dir) = down_at(5.5, 7.5);
        let place = EditOp::Ray {
            origin,
            dir,
            action: RayAction::Place { colour: red },
        };
        assert_eq!(apply_op(&mut map, &place, &limits), Ok(1));
        assert_eq!(
            map.get([5, 10, 7]),
            Some(red),
            "placed on top of the ground"
        );
        // The same click again stacks on the voxel just placed.
        assert_eq!(apply_op(&mut map, &place, &limits), Ok(1));
        assert_eq!(map.get([5, 11, 7]), Some(red));
        let remove = EditOp::Ray {
            origin,
            dir,
            action: RayAction::Remove,
        };
        assert_eq!(apply_op(&mut map, &remove, &limits), Ok(1));
        assert_eq!(map.get([5, 11, 7]), None);
        let paint = EditOp::Ray {
            origin,
            dir,
            action: RayAction::Paint {
                colour: Colour::BLACK,
            },
        };
        assert_eq!(apply_op(&mut map, &paint, &limits), Ok(1));
        assert_eq!(map.get([5, 10, 7]), Some(Colour::BLACK));
        let dig = EditOp::Ray {
            origin,
            dir,
            action: RayAction::Sphere {
                mode: BrushMode::Erase,
                radius: 3.0,
                colour: red,
            },
        };
        // Roughly the lower half of a radius-3 ball (about 46 voxels) plus the painted voxel.
        assert!(apply_op(&mut map, &dig, &limits).is_ok_and(|n| (30..80).contains(&n)));
        assert_eq!(map.get([5, 10, 7]), None);
        map.check_invariants().unwrap();
    }

    #[test]
    fn bad_ops_are_rejected_and_change_nothing() {
        let mut map = ground();
        let before = map.content_hash();
        let limits = Limits::default();
        let miss = EditOp::Ray {
            origin: [5.0, 60.0, 5.0],
            dir: [0.0, 1.0, 0.0],
            action: RayAction::Remove,
        };
        assert_eq!(
            apply_op(&mut map, &miss, &limits),
            Err(Rejection::RayMissed)
        );
        let inside = EditOp::Ray {
            origin: [5.5, 5.5, 5.5],
            dir: [0.0, 1.0, 0.0],
            action: RayAction::Place {
                colour: Colour::WHITE,
            },
        };
        assert_eq!(
            apply_op(&mut map, &inside, &limits),
            Err(Rejection::NothingToPlace)
        );
        let out = EditOp::Set {
            pos: [64, 0, 0],
            colour: Colour::WHITE,
        };
        assert_eq!(
            apply_op(&mut map, &out, &limits),
            Err(Rejection::OutOfBounds)
        );
        let nan = EditOp::Sphere {
            centre: [f32::NAN, 1.0, 1.0],
            radius: 2.0,
            mode: BrushMode::Fill,
            colour: Colour::WHITE,
        };
        assert_eq!(
            apply_op(&mut map, &nan, &limits),
            Err(Rejection::InvalidNumber)
        );
        let huge = EditOp::Sphere {
            centre: [1.0; 3],
            radius: 1e6,
            mode: BrushMode::Fill,
            colour: Colour::WHITE,
        };
        assert_eq!(apply_op(&mut map, &huge, &limits), Err(Rejection::TooLarge));
        assert_eq!(map.content_hash(), before);
    }

    fn ray(origin: [f32; 3], action: RayAction) -> EditOp {
        EditOp::Ray {
            origin,
            dir: [0.0, -1.0, 0.0],
            action,
        }
    }

    #[test]
    fn a_fill_recolours_one_connected_colour_and_refuses_a_runaway() {
        let mut map = ground();
        let red = Colour::from_rgb8(255, 0, 0);
        let blue = Colour::from_rgb8(0, 0, 255);
        map.fill_box([10, 9, 10], [19, 9, 19], BrushMode::Paint, red);
        map.set([30, 9, 30], red);
        let limits = Limits::default();
        let fill = |limit| {
            ray(
                [12.5, 60.0, 12.5],
                RayAction::Fill {
                    colour: blue,
                    limit,
                },
            )
        };
        let before = map.content_hash();
        assert_eq!(
            apply_op(&mut map, &fill(99), &limits),
            Err(Rejection::TooLarge)
        );
        assert_eq!(map.content_hash(), before, "a refused fill changes nothing");
        assert_eq!(apply_op(&mut map, &fill(100), &limits), Ok(100));
        assert_eq!(map.get([19, 9, 19]), Some(blue));
        assert_eq!(map.get([30, 9, 30]), Some(red), "not connected");
        assert_eq!(map.get([20, 9, 19]), Some(Colour::WHITE), "another colour");
        assert_eq!(
            apply_op(&mut map, &fill(0), &limits),
            Err(Rejection::malformed("a tool's voxel limit is 0"))
        );
        assert_eq!(
            apply_op(&mut map, &fill(limits.max_tool_voxels + 1), &limits),
            Err(Rejection::TooLarge)
        );
        map.check_invariants().unwrap();
    }

    #[test]
    fn a_face_extrudes_and_intrudes_with_its_colours() {
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        let red = Colour::from_rgb8(255, 0, 0);
        map.fill_box([4, 0, 4], [9, 3, 9], BrushMode::Fill, Colour::WHITE);
        map.set([5, 3, 5], red);
        let limits = Limits::default();
        let out = ray(
            [6.5, 30.0, 6.5],
            RayAction::Extrude {
                out: true,
                limit: 1000,
            },
        );
        assert_eq!(apply_op(&mut map, &out, &limits), Ok(35));
        assert_eq!(map.get([9, 4, 9]), Some(Colour::WHITE));
        assert_eq!(map.get([5, 4, 5]), None, "another colour is another face");
        assert_eq!(map.get([10, 4, 9]), None, "one layer, on the face only");
        let side = EditOp::Ray {
            origin: [30.5, 2.5, 6.5],
            dir: [-1.0, 0.0, 0.0],
            action: RayAction::Extrude {
                out: false,
                limit: 1000,
            },
        };
        // The +x side is now five high (the extruded layer joined it) and six deep.
        assert_eq!(apply_op(&mut map, &side, &limits), Ok(30));
        assert_eq!(map.get([9, 2, 6]), None);
        assert_eq!(map.get([8, 2, 6]), Some(Colour::WHITE));
        let small = ray(
            [6.5, 30.0, 6.5],
            RayAction::Extrude {
                out: true,
                limit: 10,
            },
        );
        assert_eq!(
            apply_op(&mut map, &small, &limits),
            Err(Rejection::TooLarge)
        );
        map.check_invariants().unwrap();
    }

    #[test]
    fn spans_draw_boxes_and_lines_between_two_hits() {
        let mut map = ground();
        let red = Colour::from_rgb8(255, 0, 0);
        let limits = Limits::default();
        let span = |shape, mode, extent| EditOp::Span {
            from: [2.5, 60.0, 3.5],
            from_dir: [0.0, -1.0, 0.0],
            to: [12.5, 60.0, 8.5],
            to_dir: [0.0, -1.0, 0.0],
            shape,
            mode,
            colour: red,
            extent,
        };
        // Filling starts in front of the hits: a box one voxel high on the ground.
        assert_eq!(
            apply_op(&mut map, &span(Shape::Box, BrushMode::Fill, 64), &limits),
            Ok(11 * 6)
        );
        assert_eq!(map.get([12, 10, 8]), Some(red));
        assert_eq!(map.get([2, 10, 3]), Some(red));
        // Erasing takes the voxels hit: now the red layer, as a line.
        assert_eq!(
            apply_op(&mut map, &span(Shape::Line, BrushMode::Erase, 64), &limits),
            Ok(11)
        );
        assert_eq!(map.get([2, 10, 3]), None);
        assert_eq!(map.get([12, 10, 8]), None);
        assert_eq!(map.get([3, 10, 3]), Some(red), "beside the line");
        let before = map.content_hash();
        assert_eq!(
            apply_op(&mut map, &span(Shape::Box, BrushMode::Paint, 10), &limits),
            Err(Rejection::TooLarge),
            "11 voxels along x is more than the extent allows"
        );
        assert_eq!(
            apply_op(
                &mut map,
                &span(Shape::Box, BrushMode::Paint, limits.max_box_extent + 1),
                &limits
            ),
            Err(Rejection::TooLarge)
        );
        let mut up = span(Shape::Box, BrushMode::Fill, 64);
        if let EditOp::Span { to_dir, .. } = &mut up {
            *to_dir = [0.0, 1.0, 0.0];
        }
        assert_eq!(apply_op(&mut map, &up, &limits), Err(Rejection::RayMissed));
        assert_eq!(map.content_hash(), before);
        map.check_invariants().unwrap();
    }

    /// Planning an op brick by brick, over brick-aligned parts of the scene (what the server
    /// does for a heavy edit), ends exactly where applying it to the map does.
    #[test]
    fn brushes_brick_by_brick_end_where_applying_does() {
        use std::collections::HashMap;

        use crate::brick::BrickData;
        use crate::map::brush_brick;

        let mut map = BrickMap::new([64, 40, 48]).unwrap();
        map.fill_box([0, 0, 0], [63, 9, 47], BrushMode::Fill, Colour::WHITE);
        map.sphere(
            [20.5, 10.0, 20.0],
            9.0,
            BrushMode::Fill,
            Colour::from_rgb8(0, 90, 0),
        );
        let red = Colour::from_rgb8(255, 0, 0);
        let ops = [
            EditOp::Set {
                pos: [3, 30, 4],
                colour: red,
            },
            EditOp::Set {
                pos: [0, 0, 0],
                colour: red,
            },
            EditOp::Clear { pos: [1, 1, 1] },
            EditOp::Paint {
                pos: [2, 2, 2],
                colour: Colour::BLACK,
            },
            EditOp::Sphere {
                centre: [30.2, 8.0, 17.9],
                radius: 13.5,
                mode: BrushMode::Fill,
                colour: red,
            },
            EditOp::Sphere {
                centre: [60.0, 5.0, 44.0],
                radius: 10.0,
                mode: BrushMode::Erase,
                colour: red,
            },
            EditOp::Sphere {
                centre: [20.0, 12.0, 20.0],
                radius: 7.0,
                mode: BrushMode::Paint,
                colour: Colour::BLACK,
            },
            EditOp::Box {
                min: [5, 3, 9],
                max: [41, 22, 30],
                mode: BrushMode::Fill,
                colour: Colour::from_rgb8(0, 0, 255),
            },
            EditOp::Box {
                min: [10, 0, 0],
                max: [63, 6, 13],
                mode: BrushMode::Erase,
                colour: red,
            },
            EditOp::Box {
                min: [0, 5, 40],
                max: [63, 39, 47],
                mode: BrushMode::Paint,
                colour: red,
            },
            EditOp::Ray {
                origin: [40.5, 39.0, 20.5],
                dir: [0.0, -1.0, 0.0],
                action: RayAction::Fill {
                    colour: Colour::from_rgb8(9, 9, 9),
                    limit: 100_000,
                },
            },
            EditOp::Ray {
                origin: [50.5, 39.0, 22.5],
                dir: [0.0, -1.0, 0.0],
                action: RayAction::Extrude {
                    out: true,
                    limit: 100_000,
                },
            },
            EditOp::Span {
                from: [3.5, 39.0, 3.5],
                from_dir: [0.0, -1.0, 0.0],
                to: [60.5, 39.0, 30.5],
                to_dir: [0.02, -1.0, 0.01],
                shape: Shape::Line,
                mode: BrushMode::Fill,
                colour: red,
                extent: 256,
            },
        ];
        let limits = Limits::default();
        for op in ops {
            let resolved = resolve(&map, &op, &limits).unwrap_or_else(|e| panic!("{op:?}: {e}"));
            let mut bricks: HashMap<[u32; 3], (crate::brick::Mask, Vec<Colour>)> = HashMap::new();
            let mut scratch = [Colour::BLACK; 512];
            for z in (0..48).step_by(16) {
                for y in (0..40).step_by(16) {
                    for x in (0..64).step_by(16) {
                        let part = VoxelBox {
                            lo: [x, y, z],
                            hi: [x + 15, y + 15, z + 15],
                        };
                        let within = part.clip(&map.whole()).unwrap();
                        resolved.brushes(within, |cell, brush, mode, colour| {
                            let brick =
                                bricks.entry(cell).or_insert_with(|| match map.brick(cell) {
                                    Some(b) => (b.mask, b.colours),
                                    None => (EMPTY_MASK, Vec::new()),
                                });
                            let (mask, n, _) = brush_brick(
                                (&brick.0, &brick.1),
                                brush,
                                mode,
                                colour,
                                &mut scratch,
                            );
                            *brick = (mask, scratch[..n].to_vec());
                        });
                    }
                }
            }
            let mut planned = map.clone();
            for (cell, (mask, colours)) in bricks {
                if colours.is_empty() {
                    planned.remove_brick(cell);
                } else {
                    planned
                        .put_brick(&BrickData {
                            cell,
                            mask,
                            colours,
                        })
                        .unwrap();
                }
            }
            apply_resolved(&mut map, resolved);
            assert_eq!(planned.content_hash(), map.content_hash(), "{op:?}");
        }
    }
}
