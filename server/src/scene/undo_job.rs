//! A large undo or redo, planned across turns and applied in one (see `jobs.rs` for the rules
//! every job follows).
//!
//! Undoing a step of two 256³ boxes reads, compares and re-records 65,536 bricks: here the
//! stored step is read a frame (`step::FRAME_BRICKS` bricks) per turn and each frame planned
//! against the map as it is; a frame holding a cell someone changed after it was planned is
//! planned again in the last turn.

use brickcast_protocol::BrickMap;

use super::history::{BrickChange, History, Revert};
use super::jobs::{Job, Planning, Progress};
use super::owner::{Log, Owner, PendingAck, Reverted, UndoAsk};
use super::step::{EncodedFrames, Frames, plan_revert_into};
use crate::metrics::Metrics;

/// One frame of the step, planned against the map as it was in some turn.
struct Planned {
    step: Vec<BrickChange>,
    revert: Revert,
    /// The revert's record, encoded (frames of the stored step the opposite stack gets).
    frames: EncodedFrames,
}

/// An undo or redo waiting for (or in) its planning.
pub(super) struct UndoJob {
    ask: UndoAsk,
    pub(super) user: u64,
    /// The step being planned, once the job started.
    started: Option<Started>,
    planned: Vec<Planned>,
    /// Which frame planned each cell, and the frames changed since.
    pub(super) planning: Planning,
    /// The user's commands that arrived after this one, in order.
    pub(super) waiting: Vec<super::Command>,
}

/// The step a job plans: its id, its stored bytes, and where its next frame starts (`Frames`
/// is made again each turn from there).
struct Started {
    id: u64,
    bytes: Vec<u8>,
    offset: usize,
    left: u32,
    read: bool,
}

impl UndoJob {
    pub(super) fn new(ask: UndoAsk, user: u64) -> UndoJob {
        UndoJob {
            ask,
            user,
            started: None,
            planned: Vec::new(),
            planning: Planning::default(),
            waiting: Vec::new(),
        }
    }
}

impl Owner {
    /// The first job, an undo.
    fn undo_job(&mut self) -> &mut UndoJob {
        match self.jobs.front_mut() {
            Some(Job::Undo(job)) => job,
            _ => unreachable!("the first job is an undo"),
        }
    }

    /// Pops the first job, an undo.
    fn pop_undo_job(&mut self) -> UndoJob {
        match self.jobs.pop_front() {
            Some(Job::Undo(job)) => job,
            _ => unreachable!("the first job is an undo"),
        }
    }

    /// One turn of the first job, an undo: starts it, plans its next frame, or finishes it.
    pub(super) fn undo_turn(&mut self, log: &mut Log, acks: &mut Vec<PendingAck>) -> Progress {
        if self.undo_job().started.is_none() && !self.start_job(acks) {
            return Progress::Skipped(self.pop_undo_job().waiting);
        }
        let job = self.undo_job();
        let started = job.started.as_mut().expect("a job was started");
        if !started.read {
            match next_frame(started) {
                Ok(Some(step)) => {
                    let index = job.planned.len();
                    for change in &step {
                        job.planning.planned(change.cell, index);
                    }
                    let planned = plan(&self.map, step, &mut self.history);
                    self.undo_job().planned.push(planned);
                    return Progress::Planned;
                }
                Ok(None) => started.read = true,
                Err(e) => {
                    let job = self.pop_undo_job();
                    tracing::error!(scene = %self.name, user = job.user, error = %e, "an undo step could not be read; it is dropped");
                    // Dropped from its stack, if it is still on top of it.
                    let id = job.started.as_ref().map(|s| s.id);
                    let direction = job.ask.direction();
                    if self.history.peek(job.user, direction).map(|s| s.id) == id {
                        self.history.take_top(job.user, direction);
                    }
                    acks.push(job.ask.nothing(&self.metrics));
                    return Progress::Finished(job.waiting);
                }
            }
        }
        let limit = job.planned.len();
        let again = job.planning.take_some_dirty(limit);
        if !again.is_empty() {
            let Some(Job::Undo(job)) = self.jobs.front_mut() else {
                unreachable!("the first job is an undo")
            };
            for frame in again {
                let planned = &mut job.planned[frame];
                *planned = plan(
                    &self.map,
                    std::mem::take(&mut planned.step),
                    &mut self.history,
                );
            }
            return Progress::Planned;
        }
        let job = self.pop_undo_job();
        Progress::Finished(self.finish_job(job, log, acks))
    }

    /// Starts the first job: reads its step. False when there is none to undo any more.
    fn start_job(&mut self, acks: &mut Vec<PendingAck>) -> bool {
        let job = self.undo_job();
        let (user, direction) = (job.user, job.ask.direction());
        let Some(top) = self.history.peek(user, direction) else {
            return self.refuse_first(acks, None);
        };
        let bytes = match self.history.pending_step(top.id) {
            Some(bytes) => Ok(Some(bytes.to_vec())),
            None => self.log.history_step(top.id).map_err(|e| e.to_string()),
        };
        let bytes = match bytes {
            Ok(Some(bytes)) => bytes,
            Ok(None) => {
                let missing = format!("history step {} is missing", top.id);
                return self.refuse_first(acks, Some(missing));
            }
            Err(e) => return self.refuse_first(acks, Some(e)),
        };
        self.undo_job().started = Some(Started {
            id: top.id,
            bytes,
            offset: 0,
            left: 0,
            read: false,
        });
        true
    }

    /// Answers the first job "nothing to undo" (its step is gone, or unreadable: `error`).
    fn refuse_first(&mut self, acks: &mut Vec<PendingAck>, error: Option<String>) -> bool {
        let (user, ask) = {
            let job = self.undo_job();
            (job.user, job.ask)
        };
        if let Some(e) = error {
            tracing::error!(scene = %self.name, user, error = %e, "an undo step could not be read; it is dropped");
            self.history.take_top(user, ask.direction());
        }
        acks.push(ask.nothing(&self.metrics));
        false
    }

    /// The job's last turn: plans again the frames someone changed, then applies, logs and
    /// records the whole undo at once.
    fn finish_job(
        &mut self,
        mut job: UndoJob,
        log: &mut Log,
        acks: &mut Vec<PendingAck>,
    ) -> Vec<super::Command> {
        let id = job.started.take().expect("a finished job started").id;
        let direction = job.ask.direction();
        // The step must still be the user's top: its user may have left (a guest's history is
        // forgotten) or the scene's cap dropped it meanwhile.
        if self.history.peek(job.user, direction).map(|s| s.id) != Some(id) {
            acks.push(job.ask.nothing(&self.metrics));
            return job.waiting;
        }
        for frame in job.planning.take_dirty() {
            let planned = &mut job.planned[frame];
            *planned = plan(
                &self.map,
                std::mem::take(&mut planned.step),
                &mut self.history,
            );
        }
        self.history.take_top(job.user, direction);
        let (mut restored, mut kept, mut bricks) = (0, 0, 0usize);
        let mut writes = Vec::new();
        let mut frames = EncodedFrames::default();
        for planned in job.planned.drain(..) {
            restored += planned.revert.restored;
            kept += planned.revert.kept;
            bricks += planned.revert.record.bricks.len();
            writes.push(planned.revert.writes);
            frames.append(&planned.frames);
        }
        let record = frames.finish();
        self.history
            .push_stored(job.user, direction, record.clone(), bricks);
        let seq = self.apply_revert(
            Reverted {
                user: job.user,
                redo: job.ask.redo,
                writes,
                record,
                bricks,
                restored,
                kept,
            },
            log,
        );
        Metrics::add(&self.metrics.undos_sliced, 1);
        acks.push(job.ask.reply(seq, restored, kept, None));
        std::mem::take(&mut job.waiting)
    }
}

/// Plans undoing one frame of a step against the map as it is, and encodes its record.
fn plan(map: &BrickMap, step: Vec<BrickChange>, history: &mut History) -> Planned {
    let mut revert = Revert::new();
    plan_revert_into(map, &step, &mut revert);
    let mut frames = EncodedFrames::default();
    frames.push(&revert.record.bricks, history.compressor());
    Planned {
        step,
        revert,
        frames,
    }
}

/// The next frame of a started job's step.
fn next_frame(started: &mut Started) -> Result<Option<Vec<BrickChange>>, String> {
    let mut frames = Frames::resume(&started.bytes, started.offset, started.left)?;
    let frame = frames.next_frame()?;
    (started.offset, started.left) = frames.position(&started.bytes);
    Ok(frame)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::Ordering::Relaxed;

    use brickcast_protocol::apply::apply_op;
    use brickcast_protocol::wire::{BrushMode, EditOp, Limits};
    use brickcast_protocol::{BrickMap, Colour};

    use crate::metrics::PhaseClock;
    use crate::scene::Command;
    use crate::scene::history::{Step, plan_revert, write_bricks};
    use crate::scene::jobs::testing::{A, B, Scene, edit, join, replies};

    /// A large undo planned across turns while someone paints over bricks it already planned
    /// ends exactly as the same undo done whole in its last turn: the painted voxels are kept,
    /// the user's own later edit applies after it, and recovery replays it to the same map.
    #[test]
    fn a_large_undo_planned_across_turns_ends_as_one_done_whole() {
        let mut reference = BrickMap::new([128, 64, 128]).unwrap();
        let scene = Scene::new(&reference);
        let metrics = scene.metrics.clone();
        let mut owner = scene.owner(64);
        let mut a = join(&mut owner, 1, A);
        let mut b = join(&mut owner, 2, B);
        let mut clock = PhaseClock::start();
        let red = Colour::from_rgb8(200, 0, 0);
        // 12 × 6 × 12 = 864 bricks: two frames.
        let fill = EditOp::Box {
            min: [0, 0, 0],
            max: [95, 47, 95],
            mode: BrushMode::Fill,
            colour: red,
        };
        owner
            .step(vec![edit(1, 1, vec![fill])], &mut clock)
            .unwrap();
        // A heavy edit itself: planned across turns too.
        while owner.has_jobs() {
            owner.step(Vec::new(), &mut clock).unwrap();
        }
        reference.begin_journal();
        apply_op(&mut reference, &fill, &Limits::default()).unwrap();
        let step = Step::from_journal(&mut reference);

        // The undo starts planning in its own turn (the first frame: the lowest cells).
        let undo = Command::Undo {
            session: 1,
            client_seq: 2,
            redo: false,
        };
        owner.step(vec![undo], &mut clock).unwrap();
        assert!(owner.has_jobs());
        // Bob paints a voxel of the first frame, already planned; Alice's next edit waits.
        let paint = EditOp::Set {
            pos: [0, 0, 0],
            colour: Colour::from_rgb8(0, 0, 200),
        };
        let mine = EditOp::Set {
            pos: [1, 0, 0],
            colour: Colour::from_rgb8(0, 200, 0),
        };
        owner
            .step(
                vec![edit(2, 1, vec![paint]), edit(1, 3, vec![mine])],
                &mut clock,
            )
            .unwrap();
        let bob = replies(&mut b);
        assert_eq!(bob.len(), 1, "bob's edit applied while the undo is planned");
        let mut turns = 0;
        while owner.has_jobs() {
            owner.step(Vec::new(), &mut clock).unwrap();
            turns += 1;
            assert!(turns < 10, "the undo never finished");
        }
        let alice = replies(&mut a);
        let (fill_seq, undo_seq, edit_seq) = (
            alice[0].1.unwrap(),
            alice[1].1.unwrap(),
            alice[2].1.unwrap(),
        );
        assert!(
            fill_seq < bob[0].1.unwrap() && bob[0].1.unwrap() < undo_seq && undo_seq < edit_seq,
            "{alice:?} {bob:?}"
        );
        assert_eq!(alice[1].2, 1, "bob's voxel is kept");
        assert_eq!(metrics.undos_sliced.load(Relaxed), 1);

        // The same, whole, on a plain map: fill, bob's paint, the undo, alice's edit.
        apply_op(&mut reference, &paint, &Limits::default()).unwrap();
        let revert = plan_revert(&reference, &step);
        assert_eq!(revert.kept, 1);
        write_bricks(&mut reference, &revert.writes).unwrap();
        apply_op(&mut reference, &mine, &Limits::default()).unwrap();
        assert_eq!(owner.map().content_hash(), reference.content_hash());

        // Recovery replays the logged undo to the same map, and redo is there.
        let hash = owner.map().content_hash();
        drop(owner);
        let mut owner = scene.owner(64);
        assert_eq!(owner.map().content_hash(), hash);
        assert_eq!(
            owner.history().stacks(A).unwrap().redo.len(),
            0,
            "alice's edit cleared redo"
        );
        let mut a = join(&mut owner, 3, A);
        owner
            .step(
                vec![Command::Undo {
                    session: 3,
                    client_seq: 1,
                    redo: false,
                }],
                &mut clock,
            )
            .unwrap();
        while owner.has_jobs() {
            owner.step(Vec::new(), &mut clock).unwrap();
        }
        assert_eq!(replies(&mut a).len(), 1);
    }
}
