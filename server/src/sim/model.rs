//! The simulation's model: what the owner must be doing, worked out with the same ops applied to
//! a map of its own, and the acks it must send.

use std::collections::BTreeMap;

use brickcast_protocol::BrickMap;
use brickcast_protocol::apply::apply_op;
use brickcast_protocol::wire::{EditOp, Limits, OpRejection, Rejection, Role};

use crate::scene::{Command, SessionId};

/// The ack the model expects for one edit message.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Expected {
    pub(super) seq: Option<u64>,
    pub(super) applied: u32,
    pub(super) rejected: Vec<OpRejection>,
}

/// What the owner should be doing: the same ops applied to a map of its own.
pub(super) struct Model {
    pub(super) map: BrickMap,
    pub(super) seq: u64,
    /// Content hash of the scene after each sequence (`hashes[0]`: as created).
    pub(super) hashes: Vec<u64>,
    /// The scene at sequence `base.0` (as created, or as last recovered) and the ops each
    /// later batch applied: enough to rebuild the scene at any sequence for a failure report.
    pub(super) base: (u64, BrickMap),
    pub(super) batches: Vec<Vec<EditOp>>,
    /// Highest sequence acknowledged to any client.
    pub(super) acked: u64,
    /// Sessions the owner has subscribed, with their roles, as the commands of a turn go by.
    pub(super) subscribed: BTreeMap<SessionId, Role>,
    pub(super) expected: BTreeMap<(SessionId, u64), Expected>,
    pub(super) limits: Limits,
}

impl Model {
    /// The scene at sequence `seq` (from the last recovery on), rebuilt from the batches.
    pub(super) fn state_at(&self, seq: u64) -> Option<BrickMap> {
        let (base_seq, base) = &self.base;
        let mut map = base.clone();
        let from = usize::try_from(seq.checked_sub(*base_seq)?).ok()?;
        for ops in self.batches.get(..from)? {
            for op in ops {
                apply_op(&mut map, op, &self.limits).ok()?;
            }
        }
        Some(map)
    }

    /// Applies a turn's commands the way the owner must, recording the acks it must send.
    pub(super) fn turn(&mut self, commands: &[Command]) {
        for cmd in commands {
            match cmd {
                Command::Join { session, role, .. } => {
                    self.subscribed.insert(*session, *role);
                }
                Command::Leave { session } => {
                    self.subscribed.remove(session);
                }
                Command::Edit {
                    session,
                    client_seq,
                    ops,
                } => {
                    let editor = self.subscribed.get(session) == Some(&Role::Editor);
                    let mut applied = 0;
                    let mut rejected = Vec::new();
                    let mut batch = Vec::new();
                    for (index, op) in ops.iter().enumerate() {
                        let outcome = if editor {
                            apply_op(&mut self.map, op, &self.limits).map(|_| ())
                        } else {
                            Err(Rejection::NotAllowed)
                        };
                        match outcome {
                            Ok(()) => {
                                applied += 1;
                                batch.push(*op);
                            }
                            Err(reason) => rejected.push(OpRejection {
                                index: index as u32,
                                reason,
                            }),
                        }
                    }
                    let seq = (applied > 0).then(|| {
                        self.seq += 1;
                        self.hashes.push(self.map.content_hash());
                        self.batches.push(batch);
                        self.seq
                    });
                    self.expected.insert(
                        (*session, *client_seq),
                        Expected {
                            seq,
                            applied,
                            rejected,
                        },
                    );
                }
                // The simulation sends no undo (yet): `server/tests/collab.rs` tests it.
                Command::Camera { .. }
                | Command::Undo { .. }
                | Command::Resume { .. }
                | Command::Snapshot { .. }
                | Command::Shutdown => {}
            }
        }
    }
}
