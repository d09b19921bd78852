//! What a click does: the editing tools of both viewers, as the `EditOp` they send.
//!
//! Edits go to the server as rays (`EditOp::Ray`), not voxels: the server resolves them on its
//! own copy, so an edit made while the local copy is a few deltas behind lands where the scene
//! is now, and both shells need only the ray under the pointer.

use brickcast_protocol::wire::{BrushMode, EditOp, RayAction};
use brickcast_protocol::{Colour, Ray};

/// Which button was pressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Button {
    /// Removes (or, with the paint modifier, paints).
    Primary,
    /// Places.
    Secondary,
}

/// The edit for a click of `button` along `ray`: single voxels with `radius` 0, sphere brushes
/// otherwise; `paint` (Ctrl held, or the page's paint tool) recolours instead of removing.
pub fn ray_edit(button: Button, ray: &Ray, radius: f32, paint: bool, colour: Colour) -> EditOp {
    let action = match (button, radius > 0.0, paint) {
        (Button::Primary, false, false) => RayAction::Remove,
        (Button::Primary, false, true) => RayAction::Paint { colour },
        (Button::Secondary, false, _) => RayAction::Place { colour },
        (Button::Primary, true, paint) => RayAction::Sphere {
            mode: if paint {
                BrushMode::Paint
            } else {
                BrushMode::Erase
            },
            radius,
            colour,
        },
        (Button::Secondary, true, _) => RayAction::Sphere {
            mode: BrushMode::Fill,
            radius,
            colour,
        },
    };
    EditOp::Ray {
        origin: ray.origin,
        dir: ray.dir,
        action,
    }
}

/// Brush radius after one `[` (smaller) or `]` (larger) press: one voxel at a time, from 0
/// (single voxels) up to the server's `max`.
pub fn step_radius(radius: f32, larger: bool, max: f32) -> f32 {
    if larger {
        (radius + 1.0).min(max.max(1.0))
    } else {
        (radius - 1.0).max(0.0)
    }
}
