//! The scene's history in a viewer (issue #34): restoring to an earlier sequence, the same
//! for every viewer. The server keeps the past and rebuilds it (`store::past`); a viewer
//! names the sequence and the box, and the server writes the box as it was, as one undo step.

use brickcast_protocol::wire::{EditOp, Selection};

/// The op that restores the selection (the whole scene when nothing is selected) of a scene
/// of `size` voxels to how it was at sequence `to`, and what the viewer says of it.
pub fn restore(selection: Option<Selection>, size: [u32; 3], to: u64) -> (EditOp, String) {
    let (min, max, what) = match selection {
        Some(s) => (s.min, s.max, "the selection"),
        None => ([0; 3], size.map(|s| s.saturating_sub(1)), "the whole scene"),
    };
    let op = EditOp::Restore { to, min, max };
    (
        op,
        format!("restoring {what} to sequence {to} (Ctrl+Z takes it back)"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_restore_covers_the_selection_or_else_the_scene() {
        let s = Selection {
            min: [1, 2, 3],
            max: [4, 5, 6],
        };
        let (op, note) = restore(Some(s), [64, 32, 64], 9);
        assert_eq!(
            op,
            EditOp::Restore {
                to: 9,
                min: [1, 2, 3],
                max: [4, 5, 6]
            }
        );
        assert!(note.contains("the selection") && note.contains('9'));
        let (op, note) = restore(None, [64, 32, 64], 0);
        assert_eq!(
            op,
            EditOp::Restore {
                to: 0,
                min: [0; 3],
                max: [63, 31, 63]
            }
        );
        assert!(note.contains("whole scene"));
        // Every restore a viewer makes passes the server's check.
        assert!(op.validate([64, 32, 64], &Default::default()).is_ok());
    }
}
