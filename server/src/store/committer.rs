//! A scene's commits on a thread of their own (issue #31): the owner hands a turn over and goes
//! on with the next while this thread makes it durable, several turns to one fsync when they
//! queue up (group commit). The frames the owner queued meanwhile wait for their turn's
//! ticket (`scene::durable`); nothing reaches a client before the commit that holds it.
//!
//! At most [`IN_FLIGHT`] turns wait: past that the owner's hand-over blocks, so a disk slower
//! than the edits slows the edits instead of filling memory. A failed commit stops the thread:
//! the tickets from it on never become durable, and the owner hears the error at its next turn
//! (or hand-over) and stops the scene.

use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use super::{Store, StoreError};
use crate::metrics::Metrics;
use crate::scene::{Durability, OwnedTurn};

/// Turns handed over and not yet committed, at most.
pub const IN_FLIGHT: usize = 4;
/// Turns committed together, at most.
const GROUP: usize = 64;

struct Job {
    turn: OwnedTurn,
    ticket: u64,
    done: Arc<Durability>,
}

#[derive(Default)]
struct State {
    /// The last ticket committed.
    committed: u64,
    /// The failure that stopped the thread: taken by the first to report it.
    error: Option<StoreError>,
    /// What it said, for every later report.
    failure: Option<String>,
}

/// The owner's handle on its commit thread.
pub struct Committer {
    scene: String,
    tx: Option<SyncSender<Job>>,
    shared: Arc<(Mutex<State>, Condvar)>,
    thread: Option<JoinHandle<()>>,
    /// The last ticket handed over.
    handed: u64,
}

impl Committer {
    pub fn start(store: Arc<Store>, scene: String, metrics: Arc<Metrics>) -> std::io::Result<Self> {
        let (tx, rx) = sync_channel(IN_FLIGHT);
        let shared: Arc<(Mutex<State>, Condvar)> = Arc::default();
        let thread = std::thread::Builder::new()
            .name(format!("commit-{scene}"))
            .spawn({
                let (scene, shared) = (scene.clone(), shared.clone());
                move || run(&store, &scene, &metrics, rx, &shared)
            })?;
        Ok(Committer {
            scene,
            tx: Some(tx),
            shared,
            thread: Some(thread),
            handed: 0,
        })
    }

    /// Hands turn `ticket` over (waiting while [`IN_FLIGHT`] turns wait already).
    pub fn submit(
        &mut self,
        turn: OwnedTurn,
        ticket: u64,
        done: &Arc<Durability>,
    ) -> Result<(), StoreError> {
        self.check()?;
        let Some(tx) = &self.tx else {
            return Err(self.stopped());
        };
        let job = Job {
            turn,
            ticket,
            done: done.clone(),
        };
        let sent = match tx.try_send(job) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(job)) => tx.send(job).map_err(|_| ()),
            Err(TrySendError::Disconnected(_)) => Err(()),
        };
        if sent.is_err() {
            // The thread stopped: on a failure, which says why.
            self.check()?;
            return Err(self.stopped());
        }
        self.handed = ticket;
        Ok(())
    }

    /// Waits until every turn handed over is committed.
    pub fn flush(&self) -> Result<(), StoreError> {
        let (lock, cv) = &*self.shared;
        let mut state = lock.lock().unwrap_or_else(|e| e.into_inner());
        while state.committed < self.handed && state.failure.is_none() {
            state = cv.wait(state).unwrap_or_else(|e| e.into_inner());
        }
        drop(state);
        self.check()
    }

    /// The failure of a commit, if one failed.
    pub fn check(&self) -> Result<(), StoreError> {
        let mut state = self.shared.0.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(e) = state.error.take() {
            return Err(e);
        }
        match &state.failure {
            Some(detail) => Err(StoreError::CommitFailed {
                scene: self.scene.clone(),
                detail: detail.clone(),
            }),
            None => Ok(()),
        }
    }

    fn stopped(&self) -> StoreError {
        StoreError::CommitFailed {
            scene: self.scene.clone(),
            detail: "the commit thread stopped".into(),
        }
    }

    /// Commits what was handed over, then stops the thread.
    pub fn close(&mut self) {
        self.tx = None;
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!(scene = %self.scene, "the commit thread panicked");
        }
        if let Err(e) = self.check() {
            tracing::error!(scene = %self.scene, error = %e, "the last commits of the scene failed");
        }
    }
}

impl Drop for Committer {
    /// Closes it unless [`Committer::close`] already did (which reported any failure).
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.close();
        }
    }
}

fn run(
    store: &Store,
    scene: &str,
    metrics: &Metrics,
    rx: Receiver<Job>,
    shared: &(Mutex<State>, Condvar),
) {
    let (lock, cv) = shared;
    while let Ok(first) = rx.recv() {
        let mut jobs = vec![first];
        while jobs.len() < GROUP {
            match rx.try_recv() {
                Ok(job) => jobs.push(job),
                Err(_) => break,
            }
        }
        let started = Instant::now();
        let turns: Vec<_> = jobs
            .iter()
            .map(|j| (&j.turn.records[..], &j.turn.history))
            .collect();
        let result = store.append_turns(scene, &turns);
        let Some(last) = jobs.last() else { continue };
        let mut state = lock.lock().unwrap_or_else(|e| e.into_inner());
        match result {
            Ok(()) => {
                metrics.observe_commit(started.elapsed());
                state.committed = last.ticket;
                last.done.durable_to(last.ticket);
                drop(state);
                cv.notify_all();
            }
            Err(e) => {
                tracing::error!(scene, error = %e, "a commit failed; the scene stops");
                last.done.fail();
                state.failure = Some(e.to_string());
                state.error = Some(e);
                drop(state);
                cv.notify_all();
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::time::Instant;

    use brickcast_protocol::wire::{EditOp, Limits, ServerMsg, decode_server};
    use brickcast_protocol::{BrickMap, Colour};

    use crate::metrics::{Metrics, PhaseClock};
    use crate::record::LogRecord;
    use crate::scene::{Command, Durability, OwnedTurn, Owner, OwnerConfig, SceneLog};
    use crate::sim::disk::SimDisk;
    use crate::store::{Store, StoreLog};

    fn set(x: u32) -> EditOp {
        EditOp::Set {
            pos: [x, 1, 1],
            colour: Colour::WHITE,
        }
    }

    fn turn(seq: u64) -> OwnedTurn {
        OwnedTurn {
            records: vec![(
                seq,
                LogRecord::Ops {
                    user: 1,
                    ops: vec![set(seq as u32)],
                },
            )],
            ..OwnedTurn::default()
        }
    }

    /// Turns handed over become durable in order; once a commit fails, no later ticket ever
    /// does, and the error comes back to the owner (then as `CommitFailed`).
    #[test]
    fn a_pipelined_log_commits_in_order_and_a_failed_commit_releases_nothing() {
        let disk = SimDisk::new();
        let store = Arc::new(Store::with_backend(disk.clone()).unwrap());
        store
            .create_scene("s", &BrickMap::new([32, 32, 32]).unwrap())
            .unwrap();
        let metrics = Arc::new(Metrics::default());
        let mut log = StoreLog::pipelined(store.clone(), "s".into(), metrics).unwrap();
        let done = Arc::new(Durability::default());
        for seq in 1..=3 {
            let ticket = done.next();
            assert!(
                !log.submit(turn(seq), ticket, &done).unwrap(),
                "handed over"
            );
        }
        log.flush().unwrap();
        assert_eq!(done.durable(), 3);
        assert_eq!(store.load_scene("s").unwrap().replayed, 3);
        disk.kill();
        let ticket = done.next();
        // The hand-over itself may succeed; the commit fails.
        let _ = log.submit(turn(4), ticket, &done);
        assert!(log.flush().is_err());
        assert_eq!(done.may_send(ticket), Some(false));
        assert!(log.failed().is_err(), "reported again");
        assert!(log.submit(turn(5), done.next(), &done).is_err());
        assert_eq!(done.durable(), 3);
        log.close();
    }

    /// An owner whose turns are handed over while it goes on: every edit is acknowledged once
    /// its turn is durable, and the store holds every acknowledged edit.
    #[test]
    fn an_owner_with_a_backlog_acks_each_edit_after_its_commit() {
        let dir = tempfile::tempdir().unwrap();
        let store = Arc::new(Store::open(dir.path()).unwrap());
        store
            .create_scene("s", &BrickMap::new([64, 64, 64]).unwrap())
            .unwrap();
        let metrics = Arc::new(Metrics::default());
        let log = StoreLog::pipelined(store.clone(), "s".into(), metrics.clone()).unwrap();
        let mut owner = Owner::with_log(
            "s".into(),
            store.load_scene("s").unwrap(),
            Box::new(log),
            metrics,
            OwnerConfig::default(),
            Arc::new(Instant::now),
        )
        .unwrap();
        let mut rx = crate::scene::testing::join(&mut owner, 1, 7);
        owner.set_backlog(true);
        for n in 1..=40u64 {
            let edit = Command::Edit {
                session: 1,
                client_seq: n,
                ops: vec![set(n as u32)],
                admitted: None,
            };
            owner.step(vec![edit], &mut PhaseClock::start()).unwrap();
        }
        // Acks arrive as their commits land: poll until all forty are in.
        let mut acked = Vec::new();
        let started = Instant::now();
        while acked.len() < 40 {
            assert!(started.elapsed().as_secs() < 60, "acked so far: {acked:?}");
            match rx.try_take() {
                Some(frame) => {
                    if let ServerMsg::Ack {
                        client_seq, seq, ..
                    } = decode_server(&frame, &Limits::hard_caps()).unwrap()
                    {
                        acked.push((client_seq, seq));
                    }
                }
                None => std::thread::yield_now(),
            }
        }
        assert_eq!(
            acked,
            (1..=40).map(|n| (n, Some(n))).collect::<Vec<_>>(),
            "in order, each with its sequence"
        );
        let loaded = store.load_scene("s").unwrap();
        assert_eq!(loaded.seq, 40);
        assert_eq!(loaded.map.content_hash(), owner.map().content_hash());
        owner.stop(Vec::new()).unwrap();
    }
}
