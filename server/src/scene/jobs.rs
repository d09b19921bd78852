//! Work planned across turns and applied in one: large undos and redos (`undo_job.rs`) and
//! heavy edits (`edit_job.rs`).
//!
//! **Why.** One turn of the owner holds every other editor of the scene. An undo of two 256³
//! boxes, or an edit of fifteen radius-64 spheres, done whole in one turn held them for a
//! third to half a second (seconds, before undo steps were columns). A job is planned a frame
//! of about `step::FRAME_BRICKS` bricks per turn, between other people's turns, against the
//! map as it is; only its last turn writes the map, logs it, records its history and
//! broadcasts it: nobody ever sees (and no crash ever leaves) half of one. Nothing of a job is
//! durable before its last turn, so a crash before it loses only work nobody was answered.
//!
//! **Others' edits meanwhile** are applied as usual. A frame someone changes after it was
//! planned is noted (every change reaches `broadcast_delta`'s touched cells) and planned again
//! in the last turn: the result is exactly what doing the whole job in its last turn would
//! have done, which is also what recovery replays. When many frames were changed, they are
//! planned again a few per turn before the last ([`REPLAN_PER_TURN`]).
//!
//! **The user's own order.** While a job of a user waits or is planned, that user's later edits
//! and undos wait behind it (in arrival order), so they still apply after it, as sent. Jobs
//! are planned one at a time, in arrival order.
//!
//! Jobs are for the scene's own sessions over an unshared log; in a cluster a request arrives
//! forwarded, its answer is logged with its turn, and it is applied in that turn.

use std::collections::{HashMap, HashSet, VecDeque};

use super::Command;
use super::edit_job::EditJob;
use super::owner::{AckTo, Log, Owner, PendingAck};
use super::undo_job::UndoJob;

/// A job waiting for (or in) its planning.
pub(super) enum Job {
    Undo(UndoJob),
    Edit(EditJob),
}

/// Frames changed since they were planned that a job plans again per turn before its last,
/// when more than this many are waiting: someone touching every planned frame would otherwise
/// make the last turn as long as the whole job. At most as many such turns as the job has
/// frames; the last turn plans again whatever is still changed.
pub(super) const REPLAN_PER_TURN: usize = 4;

/// Jobs in arrival order (the first one is planned).
pub(super) type Jobs = VecDeque<Job>;

/// What one turn did to the first job.
pub(super) enum Progress {
    /// A frame was planned: the job needs more turns.
    Planned,
    /// The job is done (applied, or answered without change) and gone from the queue; the
    /// commands of its user that waited behind it.
    Finished(Vec<Command>),
    /// The job was answered without costing the turn (there was nothing to plan).
    Skipped(Vec<Command>),
}

/// Which planned frame holds each key (a cell, or a chunk of cells), and the frames someone
/// changed since they were planned.
#[derive(Default)]
pub(super) struct Planning {
    frame_of: HashMap<u32, usize>,
    dirty: HashSet<usize>,
    /// Turns spent planning changed frames again before the last.
    replans: usize,
}

impl Planning {
    /// Notes that frame `frame` planned `key`.
    pub(super) fn planned(&mut self, key: u32, frame: usize) {
        self.frame_of.insert(key, frame);
    }

    /// Notes a change to `key`.
    pub(super) fn touched(&mut self, key: u32) {
        if let Some(&frame) = self.frame_of.get(&key) {
            self.dirty.insert(frame);
        }
    }

    /// The frames to plan again, each once.
    pub(super) fn take_dirty(&mut self) -> Vec<usize> {
        let mut dirty: Vec<usize> = self.dirty.drain().collect();
        dirty.sort_unstable();
        dirty
    }

    /// Up to [`REPLAN_PER_TURN`] frames to plan again in a turn before the last, when more are
    /// waiting and the job has had fewer than `limit` such turns; empty otherwise.
    pub(super) fn take_some_dirty(&mut self, limit: usize) -> Vec<usize> {
        if self.dirty.len() <= REPLAN_PER_TURN || self.replans >= limit {
            return Vec::new();
        }
        self.replans += 1;
        let mut dirty: Vec<usize> = self.dirty.iter().copied().collect();
        dirty.sort_unstable();
        dirty.truncate(REPLAN_PER_TURN);
        for frame in &dirty {
            self.dirty.remove(frame);
        }
        dirty
    }
}

impl Job {
    fn user(&self) -> u64 {
        match self {
            Job::Undo(job) => job.user,
            Job::Edit(job) => job.user,
        }
    }

    fn waiting(&mut self) -> &mut Vec<Command> {
        match self {
            Job::Undo(job) => &mut job.waiting,
            Job::Edit(job) => &mut job.waiting,
        }
    }
}

impl Owner {
    /// Where the commands of `user` wait while a job of theirs is queued or planned.
    pub(super) fn waiting_behind(&mut self, user: u64) -> Option<&mut Vec<Command>> {
        self.jobs
            .iter_mut()
            .find(|j| j.user() == user)
            .map(Job::waiting)
    }

    /// Whether a job (or what waited behind one) needs turns: the thread must not sleep.
    pub fn has_jobs(&self) -> bool {
        !self.jobs.is_empty() || !self.released.is_empty()
    }

    /// Whether work answered to `to` may be planned across turns: the scene's own sessions
    /// over an unshared log.
    pub(super) fn may_slice(&self, to: AckTo) -> bool {
        matches!(to, AckTo::Session(_)) && !self.log.shared()
    }

    /// Notes cells changed since the first job planned them (from every turn's touched cells).
    pub(super) fn note_touched(&mut self, touched: &[u32]) {
        let cells = self.map.cell_dims();
        match self.jobs.front_mut() {
            Some(Job::Undo(job)) => touched.iter().for_each(|&c| job.planning.touched(c)),
            Some(Job::Edit(job)) => job.note_touched(touched, cells),
            None => {}
        }
    }

    /// Advances the first job by one frame, or finishes it; `all`: plans and finishes every
    /// job now (the scene is stopping). Commands that waited behind a finished job are
    /// returned, to be applied next, in order.
    pub(super) fn advance_jobs(
        &mut self,
        log: &mut Log,
        acks: &mut Vec<PendingAck>,
        all: bool,
    ) -> Vec<Command> {
        let mut released = Vec::new();
        loop {
            let progress = match self.jobs.front() {
                None => return released,
                Some(Job::Undo(_)) => self.undo_turn(log, acks),
                Some(Job::Edit(_)) => self.edit_turn(log, acks),
            };
            match progress {
                Progress::Planned => {}
                Progress::Finished(waiting) => released.extend(waiting),
                Progress::Skipped(waiting) => {
                    released.extend(waiting);
                    continue;
                }
            }
            if !all {
                return released;
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod testing {
    use std::sync::Arc;
    use std::sync::atomic::AtomicUsize;
    use std::time::Instant;

    use brickcast_protocol::wire::{EditOp, Limits, Role, ServerMsg, decode_server};
    use tokio::sync::oneshot;

    use crate::metrics::{Metrics, PhaseClock};
    use crate::scene::{Command, Joiner, Outbox, OutboxReceiver, Owner, OwnerConfig};
    use crate::store::Store;

    /// A store holding one scene, "s", and the metrics its owners count into.
    pub struct Scene {
        _dir: tempfile::TempDir,
        pub store: Arc<Store>,
        pub metrics: Arc<Metrics>,
    }

    impl Scene {
        pub fn new(map: &brickcast_protocol::BrickMap) -> Scene {
            let dir = tempfile::tempdir().unwrap();
            let store = Arc::new(Store::open(dir.path()).unwrap());
            store.create_scene("s", map).unwrap();
            Scene {
                _dir: dir,
                store,
                metrics: Arc::new(Metrics::default()),
            }
        }

        /// An owner of the scene as stored, planning jobs of `slice` bricks and up.
        pub fn owner(&self, slice: u32) -> Owner {
            open(&self.store, &self.metrics, slice)
        }
    }

    pub const A: u64 = 1;
    pub const B: u64 = 2;

    pub fn open(store: &Arc<Store>, metrics: &Arc<Metrics>, slice: u32) -> Owner {
        let config = OwnerConfig {
            slice_bricks: slice,
            ..OwnerConfig::default()
        };
        open_with(store, metrics, config)
    }

    /// An owner of scene "s" with `config`.
    pub fn open_with(store: &Arc<Store>, metrics: &Arc<Metrics>, config: OwnerConfig) -> Owner {
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

    pub fn join(owner: &mut Owner, session: u64, user: u64) -> OutboxReceiver {
        let (out, rx) = Outbox::new(Arc::new(AtomicUsize::new(0)));
        let (joined, _) = oneshot::channel();
        let cmd = Command::Join {
            session,
            out,
            role: Role::Editor,
            resume_from: None,
            level: 0,
            budget: None,
            who: Joiner::solo(session, user, Role::Editor),
            joined,
        };
        owner.step(vec![cmd], &mut PhaseClock::start()).unwrap();
        rx
    }

    pub fn edit(session: u64, client_seq: u64, ops: Vec<EditOp>) -> Command {
        Command::Edit {
            session,
            client_seq,
            ops,
            admitted: None,
        }
    }

    /// Every reply (Ack or Undone) waiting in a session's queue: (client_seq, seq, kept).
    pub fn replies(rx: &mut OutboxReceiver) -> Vec<(u64, Option<u64>, u64)> {
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
}
