//! A large undo or redo, planned across turns and applied in one.
//!
//! **Why.** Undoing a step of two 256³ boxes reads, compares and re-records 65,536 bricks; done
//! in one turn it held every other editor of the scene for seconds. Here the owner plans such
//! a step a frame (`step::FRAME_BRICKS` bricks) per turn, between other people's turns, and
//! only the last turn writes the map, logs the undo, moves the step between the stacks and
//! broadcasts it: nobody ever sees (and no crash ever leaves) half an undo. Nothing of a job is
//! durable before its last turn, so a crash before it loses only an undo nobody was answered.
//!
//! **Others' edits meanwhile** are applied as usual. A brick already planned that someone
//! changes after it was planned is noted (every change reaches `broadcast_delta`'s touched
//! cells), and its frame is planned again in the last turn: the result is exactly what
//! undoing the whole step in that last turn would have done.
//!
//! **The user's own order.** While a job of a user is planned, that user's later edits and
//! undos wait behind it (in arrival order), so they still apply after it, as sent.
//!
//! Jobs are for the scene's own sessions over an unshared log; in a cluster an undo arrives as
//! a forwarded request whose answer is logged with its turn, and is applied in that turn.

use std::collections::{HashMap, HashSet, VecDeque};

use brickcast_protocol::BrickMap;

use super::Command;
use super::history::{BrickChange, History, Revert};
use super::owner::{AckTo, Log, Owner, PendingAck, Reverted, UndoAsk};
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
    user: u64,
    /// The step being planned, once the job started.
    started: Option<Started>,
    planned: Vec<Planned>,
    /// Which frame planned each cell planned so far.
    frame_of: HashMap<u32, usize>,
    /// Frames with a cell someone changed after it was planned.
    dirty: HashSet<usize>,
    /// The user's commands that arrived after this one, in order.
    pub(super) waiting: Vec<Command>,
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
            frame_of: HashMap::new(),
            dirty: HashSet::new(),
            waiting: Vec::new(),
        }
    }
}

impl Owner {
    /// The job of `user` queued or being planned, if any: the user's commands wait behind it.
    pub(super) fn undo_job_of(&mut self, user: u64) -> Option<&mut UndoJob> {
        self.undo_jobs.iter_mut().find(|j| j.user == user)
    }

    /// Whether a job (or what waited behind one) needs turns: the thread must not sleep.
    pub fn has_undo_job(&self) -> bool {
        !self.undo_jobs.is_empty() || !self.released.is_empty()
    }

    /// Whether an undo of a step of `bricks` bricks, answered to `to`, is planned across turns.
    pub(super) fn sliced(&self, to: AckTo, bricks: u32) -> bool {
        matches!(to, AckTo::Session(_))
            && !self.log.shared()
            && bricks >= self.config.undo_slice_bricks
    }

    /// Notes cells changed since the jobs planned them (from every turn's touched cells).
    pub(super) fn note_touched(&mut self, touched: &[u32]) {
        if let Some(job) = self.undo_jobs.front_mut() {
            for cell in touched {
                if let Some(&frame) = job.frame_of.get(cell) {
                    job.dirty.insert(frame);
                }
            }
        }
    }

    /// Advances the first job by one frame, or finishes it; `all`: plans and finishes every
    /// job now (the scene is stopping). Commands that waited behind a finished job are
    /// returned, to be applied next, in order.
    pub(super) fn advance_undo(
        &mut self,
        log: &mut Log,
        acks: &mut Vec<PendingAck>,
        all: bool,
    ) -> Vec<Command> {
        let mut released = Vec::new();
        loop {
            let Some(job) = self.undo_jobs.front() else {
                return released;
            };
            if job.started.is_none() && !self.start_job(acks) {
                let job = self.undo_jobs.pop_front().expect("a job is first");
                released.extend(job.waiting);
                continue;
            }
            let job = self.undo_jobs.front_mut().expect("a job is first");
            let started = job.started.as_mut().expect("a job was started");
            if !started.read {
                match next_frame(started) {
                    Ok(Some(step)) => {
                        let index = job.planned.len();
                        for change in &step {
                            job.frame_of.insert(change.cell, index);
                        }
                        job.planned.push(plan(&self.map, step, &mut self.history));
                        if !all {
                            return released;
                        }
                        continue;
                    }
                    Ok(None) => started.read = true,
                    Err(e) => {
                        tracing::error!(scene = %self.name, user = job.user, error = %e, "an undo step could not be read; it is dropped");
                        let job = self.undo_jobs.pop_front().expect("a job is first");
                        // Dropped from its stack, if it is still on top of it.
                        let id = job.started.as_ref().map(|s| s.id);
                        let direction = job.ask.direction();
                        if self.history.peek(job.user, direction).map(|s| s.id) == id {
                            self.history.take_top(job.user, direction);
                        }
                        acks.push(job.ask.nothing(&self.metrics));
                        released.extend(job.waiting);
                        if !all {
                            return released;
                        }
                        continue;
                    }
                }
            }
            let job = self.undo_jobs.pop_front().expect("a job is first");
            released.extend(self.finish_job(job, log, acks));
            if !all {
                return released;
            }
        }
    }

    /// Starts the first job: reads its step. False when there is none to undo any more.
    fn start_job(&mut self, acks: &mut Vec<PendingAck>) -> bool {
        let job = self.undo_jobs.front().expect("a job is first");
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
        let job = self.undo_jobs.front_mut().expect("a job is first");
        job.started = Some(Started {
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
        let job = self.undo_jobs.front_mut().expect("a job is first");
        if let Some(e) = error {
            tracing::error!(scene = %self.name, user = job.user, error = %e, "an undo step could not be read; it is dropped");
            self.history.take_top(job.user, job.ask.direction());
        }
        acks.push(job.ask.nothing(&self.metrics));
        false
    }

    /// The job's last turn: plans again the frames someone changed, then applies, logs and
    /// records the whole undo at once.
    fn finish_job(
        &mut self,
        mut job: UndoJob,
        log: &mut Log,
        acks: &mut Vec<PendingAck>,
    ) -> Vec<Command> {
        let id = job.started.take().expect("a finished job started").id;
        let direction = job.ask.direction();
        // The step must still be the user's top: its user may have left (a guest's history is
        // forgotten) or the scene's cap dropped it meanwhile.
        if self.history.peek(job.user, direction).map(|s| s.id) != Some(id) {
            acks.push(job.ask.nothing(&self.metrics));
            return job.waiting;
        }
        for &frame in &job.dirty {
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
            writes.extend(planned.revert.writes);
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

/// Jobs in arrival order (the first one is planned).
pub(super) type UndoJobs = VecDeque<UndoJob>;

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::sync::atomic::AtomicUsize;
    use std::sync::atomic::Ordering::Relaxed;
    use std::time::Instant;

    use brickcast_protocol::apply::apply_op;
    use brickcast_protocol::wire::{BrushMode, EditOp, Limits, Role, ServerMsg, decode_server};
    use brickcast_protocol::{BrickMap, Colour};
    use tokio::sync::oneshot;

    use super::*;
    use crate::metrics::PhaseClock;
    use crate::scene::history::{Step, plan_revert, write_bricks};
    use crate::scene::{Joiner, Outbox, OutboxReceiver, OwnerConfig};
    use crate::store::Store;

    const A: u64 = 1;
    const B: u64 = 2;

    fn open(store: &Arc<Store>, metrics: &Arc<Metrics>, slice: u32) -> Owner {
        let config = OwnerConfig {
            undo_slice_bricks: slice,
            ..OwnerConfig::default()
        };
        let loaded = store.load_scene("s").unwrap();
        Owner::new(
            "s".into(),
            loaded,
            store.clone(),
            metrics.clone(),
            config,
            Arc::new(Instant::now),
        )
        .unwrap()
    }

    fn join(owner: &mut Owner, session: u64, user: u64) -> OutboxReceiver {
        let (out, rx) = Outbox::new(Arc::new(AtomicUsize::new(0)));
        let (joined, _) = oneshot::channel();
        let cmd = Command::Join {
            session,
            out,
            role: Role::Editor,
            resume_from: None,
            who: Joiner::solo(session, user, Role::Editor),
            joined,
        };
        owner.step(vec![cmd], &mut PhaseClock::start()).unwrap();
        rx
    }

    fn edit(session: u64, client_seq: u64, ops: Vec<EditOp>) -> Command {
        Command::Edit {
            session,
            client_seq,
            ops,
            admitted: None,
        }
    }

    /// Every reply (Ack or Undone) waiting in a session's queue: (client_seq, seq, kept).
    fn replies(rx: &mut OutboxReceiver) -> Vec<(u64, Option<u64>, u64)> {
        let mut out = Vec::new();
        while let Some(frame) = rx.try_take() {
            match decode_server(&frame, &Limits::hard_caps()).unwrap() {
                ServerMsg::Ack {
                    client_seq, seq, ..
                } => out.push((client_seq, seq, 0)),
                ServerMsg::Undone {
                    client_seq,
                    seq,
                    kept,
                    refused,
                    ..
                } => {
                    assert_eq!(refused, None);
                    out.push((client_seq, seq, kept));
                }
                _ => {}
            }
        }
        out
    }

    /// A large undo planned across turns while someone paints over bricks it already planned
    /// ends exactly as the same undo done whole in its last turn: the painted voxels are kept,
    /// the user's own later edit applies after it, and recovery replays it to the same map.
    #[test]
    fn a_large_undo_planned_across_turns_ends_as_one_done_whole() {
        let dir = tempfile::tempdir().unwrap();
        let store = Arc::new(Store::open(dir.path()).unwrap());
        let mut reference = BrickMap::new([128, 64, 128]).unwrap();
        store.create_scene("s", &reference).unwrap();
        let metrics = Arc::new(Metrics::default());
        let mut owner = open(&store, &metrics, 64);
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
        assert!(owner.has_undo_job());
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
        while owner.has_undo_job() {
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
        let mut owner = open(&store, &metrics, 64);
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
        while owner.has_undo_job() {
            owner.step(Vec::new(), &mut clock).unwrap();
        }
        assert_eq!(replies(&mut a).len(), 1);
    }
}
