//! The simulation's model: what the owner must be doing, worked out with the same ops applied to
//! a map of its own, and the acks it must send.

use std::collections::BTreeMap;

use brickcast_protocol::apply::apply_op;
use brickcast_protocol::wire::{EditOp, Limits, OpRejection, Refusal, Rejection, Role};
use brickcast_protocol::{BrickMap, Colour};

use super::undo::{ModelHistory, diff, push, revert};
use crate::scene::{Command, SessionId};

/// What one sequence did, for rebuilding the scene at any sequence.
#[derive(Clone, Debug)]
pub(super) enum Entry {
    Ops(Vec<EditOp>),
    /// An undo or redo: voxels written (`None`: cleared).
    Voxels(Vec<([u32; 3], Option<Colour>)>),
}

/// The reply the model expects to an undo or redo.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct ExpectedUndone {
    pub(super) seq: Option<u64>,
    pub(super) restored: u64,
    pub(super) kept: u64,
    pub(super) refused: Option<Refusal>,
}

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
    pub(super) batches: Vec<Entry>,
    /// Highest sequence acknowledged to any client.
    pub(super) acked: u64,
    /// Sessions the owner has subscribed, with their roles, as the commands of a turn go by.
    pub(super) subscribed: BTreeMap<SessionId, Role>,
    pub(super) expected: BTreeMap<(SessionId, u64), Expected>,
    pub(super) expected_undone: BTreeMap<(SessionId, u64), ExpectedUndone>,
    pub(super) limits: Limits,
    /// Session → user, as the owner's subscribers know them.
    pub(super) users: BTreeMap<SessionId, u64>,
    pub(super) history: ModelHistory,
    /// The history at every point where the owner may have committed, with the sequence then:
    /// after a crash the recovered history must be one of those at the recovered sequence.
    pub(super) committed: Vec<(u64, ModelHistory)>,
}

impl Model {
    /// The scene at sequence `seq` (from the last recovery on), rebuilt from the batches.
    pub(super) fn state_at(&self, seq: u64) -> Option<BrickMap> {
        let (base_seq, base) = &self.base;
        let mut map = base.clone();
        let from = usize::try_from(seq.checked_sub(*base_seq)?).ok()?;
        for entry in self.batches.get(..from)? {
            match entry {
                Entry::Ops(ops) => {
                    for op in ops {
                        apply_op(&mut map, op, &self.limits).ok()?;
                    }
                }
                Entry::Voxels(writes) => write_voxels(&mut map, writes),
            }
        }
        Some(map)
    }

    /// A point where the owner commits what came before (a join, a resume, the end of a turn).
    fn commit_point(&mut self) {
        if self.committed.last() != Some(&(self.seq, self.history.clone())) {
            self.committed.push((self.seq, self.history.clone()));
        }
    }

    /// Applies a turn's commands the way the owner must, recording the acks it must send.
    pub(super) fn turn(&mut self, commands: &[Command]) {
        for cmd in commands {
            match cmd {
                Command::Join {
                    session, role, who, ..
                } => {
                    self.commit_point();
                    self.subscribed.insert(*session, *role);
                    self.users.insert(*session, who.peer.user);
                }
                Command::Leave { session } => {
                    self.subscribed.remove(session);
                    self.users.remove(session);
                }
                // Both publish what is queued before they are served.
                Command::Resume { .. }
                | Command::Thumbnail { .. }
                | Command::Describe { .. }
                | Command::Farewell { .. } => self.commit_point(),
                // Commands of a shared log: this simulation runs one owner on redb.
                Command::Request { .. }
                | Command::Apply { .. }
                | Command::Lead { .. }
                | Command::Follow { .. }
                | Command::Behind { .. }
                | Command::Fault { .. } => {}
                Command::Undo {
                    session,
                    client_seq,
                    redo,
                } => {
                    if let Some(reply) = self.undo(*session, *redo) {
                        self.expected_undone.insert((*session, *client_seq), reply);
                    }
                }
                Command::Edit {
                    session,
                    client_seq,
                    ops,
                    ..
                } => {
                    let editor = self.subscribed.get(session) == Some(&Role::Editor);
                    let mut applied = 0;
                    let mut rejected = Vec::new();
                    let mut batch = Vec::new();
                    let before = editor.then(|| self.map.clone());
                    self.map.record_touched(true);
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
                    let touched = self.map.take_touched();
                    self.map.record_touched(false);
                    // A message that only set swatches is no undo step (`Owner::apply_batch`).
                    let step = batch.iter().any(|op| !op.keeps_voxels());
                    if let (Some(before), true) = (&before, step) {
                        let step = diff(before, &self.map, &touched);
                        let user = self.users.get(session).copied().unwrap_or(0);
                        let max = self.limits.max_undo_steps as usize;
                        let steps = self.history.entry(user).or_default();
                        steps.redo.clear();
                        push(steps, true, step, max);
                    }
                    let seq = (applied > 0).then(|| {
                        self.seq += 1;
                        self.hashes.push(self.map.content_hash());
                        self.batches.push(Entry::Ops(batch));
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
                Command::Camera { .. } | Command::Snapshot { .. } | Command::Shutdown => {}
            }
        }
        self.commit_point();
    }

    /// Undo (or redo) of the session's user's latest step, as the owner must do it.
    fn undo(&mut self, session: SessionId, redo: bool) -> Option<ExpectedUndone> {
        let role = *self.subscribed.get(&session)?;
        let refused = |reason| ExpectedUndone {
            seq: None,
            restored: 0,
            kept: 0,
            refused: Some(reason),
        };
        if role != Role::Editor {
            return Some(refused(Refusal::NotAllowed));
        }
        let user = self.users.get(&session).copied().unwrap_or(0);
        let steps = self.history.entry(user).or_default();
        let step = if redo {
            steps.redo.pop()
        } else {
            steps.undo.pop_back()
        };
        let Some(step) = step else {
            return Some(refused(if redo {
                Refusal::NothingToRedo
            } else {
                Refusal::NothingToUndo
            }));
        };
        let (record, restored, kept) = revert(&mut self.map, &step);
        let max = self.limits.max_undo_steps as usize;
        let steps = self.history.entry(user).or_default();
        push(steps, redo, record.clone(), max);
        let seq = (restored > 0).then(|| {
            self.seq += 1;
            self.hashes.push(self.map.content_hash());
            let writes = record.iter().map(|&(pos, _, now)| (pos, now)).collect();
            self.batches.push(Entry::Voxels(writes));
            self.seq
        });
        Some(ExpectedUndone {
            seq,
            restored,
            kept,
            refused: None,
        })
    }
}

fn write_voxels(map: &mut BrickMap, writes: &[([u32; 3], Option<Colour>)]) {
    for &(pos, value) in writes {
        match value {
            Some(c) => map.set(pos, c),
            None => map.clear(pos),
        };
    }
}
