//! Random scenes and edit messages for the simulation: every op kind, valid and invalid.

use brickcast_protocol::wire::{EditOp, RayAction};
use brickcast_protocol::{BrickMap, BrushMode, Colour};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

pub(super) fn random_colour(rng: &mut ChaCha8Rng) -> Colour {
    Colour(rng.random_range(1..=u16::MAX))
}

/// Ground, a few hills, a few boxes.
pub(super) fn initial_scene(rng: &mut ChaCha8Rng, size: [u32; 3]) -> BrickMap {
    let mut map = BrickMap::new(size).expect("valid size");
    let ground = rng.random_range(1..size[1] / 3);
    map.fill_box(
        [0, 0, 0],
        [size[0] - 1, ground, size[2] - 1],
        BrushMode::Fill,
        random_colour(rng),
    );
    for _ in 0..rng.random_range(0..6) {
        let centre = std::array::from_fn(|i| rng.random_range(0.0..size[i] as f32));
        let colour = random_colour(rng);
        map.sphere(centre, rng.random_range(1.0..10.0), BrushMode::Fill, colour);
    }
    map
}

/// An edit message: a few ops of every kind, some invalid; sometimes every op is refused.
pub fn random_batch(rng: &mut ChaCha8Rng, size: [u32; 3]) -> Vec<EditOp> {
    let len = rng.random_range(1..=6);
    if rng.random_bool(0.15) {
        (0..len).map(|_| rejected_op(rng, size)).collect()
    } else {
        (0..len).map(|_| random_op(rng, size)).collect()
    }
}

pub(super) fn point(rng: &mut ChaCha8Rng, size: [u32; 3]) -> [u32; 3] {
    std::array::from_fn(|i| rng.random_range(0..size[i]))
}

/// An op the owner must refuse: a ray into the sky, a voxel or box outside the scene, a brush
/// over the size limit or with a non-finite centre.
pub(super) fn rejected_op(rng: &mut ChaCha8Rng, size: [u32; 3]) -> EditOp {
    let colour = random_colour(rng);
    match rng.random_range(0..5) {
        0 | 1 => EditOp::Ray {
            origin: [
                rng.random_range(0.0..size[0] as f32),
                size[1] as f32 + 5.0,
                rng.random_range(0.0..size[2] as f32),
            ],
            dir: [0.1, 1.0, -0.2],
            action: RayAction::Place { colour },
        },
        2 => EditOp::Set {
            pos: [size[0] + rng.random_range(0..3), 0, 0],
            colour,
        },
        3 => EditOp::Sphere {
            centre: [f32::NAN, 1.0, 1.0],
            radius: 2.0,
            mode: BrushMode::Fill,
            colour,
        },
        _ => EditOp::Sphere {
            centre: [1.0, 1.0, 1.0],
            radius: 500.0,
            mode: BrushMode::Erase,
            colour,
        },
    }
}

pub(super) fn random_op(rng: &mut ChaCha8Rng, size: [u32; 3]) -> EditOp {
    let colour = random_colour(rng);
    let mode = [BrushMode::Fill, BrushMode::Erase, BrushMode::Paint][rng.random_range(0..3)];
    match rng.random_range(0..100) {
        0..=24 => EditOp::Set {
            pos: point(rng, size),
            colour,
        },
        25..=34 => EditOp::Clear {
            pos: point(rng, size),
        },
        35..=42 => EditOp::Paint {
            pos: point(rng, size),
            colour,
        },
        43..=57 => EditOp::Sphere {
            centre: std::array::from_fn(|i| rng.random_range(0.0..=size[i] as f32)),
            radius: rng.random_range(0.3..9.0),
            mode,
            colour,
        },
        58..=67 => {
            let min = point(rng, size);
            let max = std::array::from_fn(|i| (min[i] + rng.random_range(0..10)).min(size[i] - 1));
            EditOp::Box {
                min,
                max,
                mode,
                colour,
            }
        }
        68..=69 => rejected_op(rng, size),
        // A swatch of the palette (scene state like the voxels); some past the last one.
        70 => EditOp::Swatch {
            index: rng.random_range(0..40),
            colour,
        },
        _ => {
            // Mostly from above, aimed down at the scene; sometimes from a far-away or extreme
            // origin.
            let origin = if rng.random_bool(0.05) {
                std::array::from_fn(|_| [-3.0e9, 3.0e9, -1.0e30, 2.5e38][rng.random_range(0..4)])
            } else {
                [
                    rng.random_range(-10.0..size[0] as f32 + 10.0),
                    size[1] as f32 + rng.random_range(1.0..20.0),
                    rng.random_range(-10.0..size[2] as f32 + 10.0),
                ]
            };
            let dir = [
                rng.random_range(-0.5..0.5),
                -1.0,
                rng.random_range(-0.5..0.5),
            ];
            let action = match rng.random_range(0..4) {
                0 => RayAction::Remove,
                1 => RayAction::Paint { colour },
                2 => RayAction::Place { colour },
                _ => RayAction::Sphere {
                    mode,
                    radius: rng.random_range(0.5..5.0),
                    colour,
                },
            };
            EditOp::Ray {
                origin,
                dir,
                action,
            }
        }
    }
}
