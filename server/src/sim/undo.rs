//! The simulation's own undo history: per user, steps as lists of voxels (position, before,
//! after), worked out voxel by voxel on the model's map, with none of `scene::history`'s code
//! (bricks, images, journals, encodings). The server's history is turned into the same form and
//! must be equal after every turn, and after a crash equal to what the model had at one of the
//! points where the owner commits.

use std::collections::{BTreeMap, VecDeque};

use brickcast_protocol::brick::{BRICK_EDGE, bit_voxel};
use brickcast_protocol::{BrickMap, Colour};

use crate::scene::history::{Stacks, Step};
use crate::store::Store;

/// What one message changed: every voxel whose value differs, sorted by position.
pub(super) type VoxelStep = Vec<([u32; 3], Option<Colour>, Option<Colour>)>;

/// One user's stacks, oldest first.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct UserSteps {
    pub(super) undo: VecDeque<VoxelStep>,
    pub(super) redo: Vec<VoxelStep>,
}

/// Every user's history.
pub(super) type ModelHistory = BTreeMap<u64, UserSteps>;

/// The voxels that differ between `before` and `after` in the given linear cells.
pub(super) fn diff(before: &BrickMap, after: &BrickMap, cells: &[u32]) -> VoxelStep {
    let size = after.size();
    let mut out = Vec::new();
    for &cell in cells {
        let c = after.cell_coords(cell);
        for bit in 0..512 {
            let l = bit_voxel(bit);
            let pos = [0, 1, 2].map(|i| c[i] * BRICK_EDGE + l[i]);
            if (0..3).any(|i| pos[i] >= size[i]) {
                continue;
            }
            let (b, a) = (before.get(pos), after.get(pos));
            if b != a {
                out.push((pos, b, a));
            }
        }
    }
    out.sort_by_key(|(p, _, _)| *p);
    out
}

/// Undoes `step` on `map`: each voxel back to its before-value where it still holds the
/// after-value. Returns (the record of what changed, restored, kept).
pub(super) fn revert(map: &mut BrickMap, step: &VoxelStep) -> (VoxelStep, u64, u64) {
    let mut record = Vec::new();
    let mut kept = 0;
    for &(pos, before, after) in step {
        if map.get(pos) == after {
            match before {
                Some(c) => map.set(pos, c),
                None => map.clear(pos),
            };
            record.push((pos, after, before));
        } else {
            kept += 1;
        }
    }
    let restored = record.len() as u64;
    (record, restored, kept)
}

/// Pushes a step onto a user's undo (`onto_undo`) or redo stack and drops the oldest steps over
/// `max` (undo stack first, then redo; never the step just pushed).
pub(super) fn push(steps: &mut UserSteps, onto_undo: bool, step: VoxelStep, max: usize) {
    if onto_undo {
        steps.undo.push_back(step);
    } else {
        steps.redo.push(step);
    }
    while steps.undo.len() + steps.redo.len() > max.max(1) {
        if steps.undo.len() > usize::from(onto_undo) {
            steps.undo.pop_front();
        } else if steps.redo.len() > usize::from(!onto_undo) {
            steps.redo.remove(0);
        } else {
            break;
        }
    }
}

/// The server's stored history in the model's form, reading each step from the store.
pub(super) fn server_history(
    store: &Store,
    scene: &str,
    map: &BrickMap,
    users: impl Iterator<Item = (u64, Stacks)>,
) -> Result<ModelHistory, String> {
    let load = |id: u64| -> Result<VoxelStep, String> {
        let bytes = store
            .history_step(scene, id)
            .map_err(|e| e.to_string())?
            .ok_or_else(|| format!("history step {id} is not in the store"))?;
        Ok(voxel_step(map, &Step::decode(&bytes)?))
    };
    let mut out = ModelHistory::new();
    for (user, stacks) in users {
        let steps = UserSteps {
            undo: stacks
                .undo
                .iter()
                .map(|s| load(s.id))
                .collect::<Result<_, _>>()?,
            redo: stacks
                .redo
                .iter()
                .map(|s| load(s.id))
                .collect::<Result<_, _>>()?,
        };
        if !(steps.undo.is_empty() && steps.redo.is_empty()) {
            out.insert(user, steps);
        }
    }
    Ok(out)
}

fn voxel_step(map: &BrickMap, step: &Step) -> VoxelStep {
    let mut out = Vec::new();
    for change in &step.bricks {
        let c = map.cell_coords(change.cell);
        for v in change.voxels() {
            let l = bit_voxel(u32::from(v.bit));
            out.push((
                [0, 1, 2].map(|i| c[i] * BRICK_EDGE + l[i]),
                v.before,
                v.after,
            ));
        }
    }
    out.sort_by_key(|(p, _, _)| *p);
    out
}

/// A short description of how two histories differ, for a failure report.
pub(super) fn describe(server: &ModelHistory, model: &ModelHistory) -> String {
    let summary = |h: &ModelHistory| -> Vec<String> {
        h.iter()
            .map(|(u, s)| {
                format!(
                    "user {u}: undo {:?} redo {:?}",
                    s.undo.iter().map(Vec::len).collect::<Vec<_>>(),
                    s.redo.iter().map(Vec::len).collect::<Vec<_>>()
                )
            })
            .collect()
    };
    format!(
        "server [{}], model [{}]",
        summary(server).join("; "),
        summary(model).join("; ")
    )
}

/// The history without users whose stacks are both empty (the server may keep those).
pub(super) fn normal(h: &ModelHistory) -> ModelHistory {
    h.iter()
        .filter(|(_, s)| !(s.undo.is_empty() && s.redo.is_empty()))
        .map(|(u, s)| (*u, s.clone()))
        .collect()
}
