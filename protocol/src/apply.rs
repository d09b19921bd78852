//! Applying a wire [`EditOp`] to a brick map: the one definition of what an edit means.
//!
//! The server applies ops on the authoritative map; replaying its log at recovery goes through
//! the same function, so a replayed scene is the scene that was acknowledged. Ray ops are
//! resolved here with the CPU tracer against the map being edited (paper 3.3), never against a
//! client's possibly stale copy.

use crate::colour::Colour;
use crate::map::{BrickMap, BrushMode};
use crate::trace::{Ray, trace};
use crate::wire::{EditOp, Limits, RayAction, Rejection};

/// An op that passed validation, with a ray op resolved to the voxel or brush it hits: what is
/// left is certain to apply. Splitting the two lets the server stamp the map with a batch's
/// sequence number only once something in the batch applies.
#[derive(Debug, Clone, Copy, PartialEq)]
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
            }
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
}
