//! The one interface between a scene's owner and where its turns are made durable.
//!
//! **Why a trait:** the owner orders edits, applies them and decides what each turn logs;
//! where a turn goes is another concern, with two answers: the embedded redb file of a single
//! node (`crate::store::StoreLog`) and a JetStream stream that the nodes of a cluster share
//! (the cluster's `JetLog`). The owner knows only this trait, the way ripgrep's searcher
//! knows only its `Matcher`: the cluster depends on the scene and never the reverse, and the
//! simulations run the real owner over a simulated disk (`crate::sim`) or a simulated
//! JetStream (the cluster's simulation).
//!
//! A **shared** log (a cluster) is appended to by one owner at a time and followed by every
//! other replica of the scene: [`SceneLog::may_order`] says whether this owner may order edits
//! now, [`SceneLog::claim`] makes it the one (after catching up with [`SceneLog::tail`]), and
//! the turns other owners append reach it as [`Turn`]s (`replica.rs`). A log with one owner
//! keeps the defaults: it always orders, and nobody else appends.

use brickcast_protocol::BrickMap;
use serde::{Deserialize, Serialize};

use super::answered::{Answered, AnsweredEntry};
use super::durable::Durability;
use super::history::{History, HistoryWrites};
use crate::record::LogRecord;
use crate::store::{Loaded, StoreError};

/// What one turn makes durable, together: its log records, its history changes, and the
/// requests from other origins it answered (so that a retry is answered, not applied again).
pub struct TurnWrite<'a> {
    pub records: &'a [(u64, LogRecord)],
    pub history: &'a HistoryWrites,
    pub answered: &'a [AnsweredEntry],
}

/// One turn as a shared log holds it, for the replicas that apply it: the [`LogRecord`] bytes
/// (replayed with [`LogRecord::replay`], the function recovery uses), the history changes and
/// the answered requests. A turn with none of them is a **marker**: what a new owner appends
/// first, so that an owner that lost the scene finds its next append refused.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Turn {
    /// Who appended it (a node's name).
    pub node: String,
    /// Scene sequence → [`LogRecord`] bytes, in order.
    pub records: Vec<(u64, Vec<u8>)>,
    pub history: HistoryWrites,
    pub requests: Vec<AnsweredEntry>,
}

impl Turn {
    pub fn is_marker(&self) -> bool {
        self.records.is_empty() && self.history.is_empty() && self.requests.is_empty()
    }
}

/// What a snapshot is taken of.
pub struct SnapshotOf<'a> {
    pub map: &'a BrickMap,
    /// Linear cells touched since the last snapshot.
    pub cells: &'a [u32],
    pub seq: u64,
    pub history: &'a History,
    pub answered: &'a Answered,
}

/// Why a log refused or failed.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// This owner may not append: it does not hold the scene (it never did, its lease ran out,
    /// or another owner appended since). Nothing of the turn is in the log.
    #[error("scene {scene}: this node is no longer the scene's owner: {detail}")]
    Deposed { scene: String, detail: String },
    /// The turn may or may not be in the log (an answer was lost, or it was logged in part).
    #[error("scene {scene}: {detail}; the turn's outcome is unknown")]
    Unknown { scene: String, detail: String },
    /// The log cannot be reached now (a NATS server away, a network blip).
    #[error("scene {scene}: {detail}")]
    Unavailable { scene: String, detail: String },
    /// The log cannot do this at all (a single node's log does not reload).
    #[error("scene {scene}: {detail}")]
    Unsupported { scene: String, detail: String },
    /// What is stored is wrong, or storage failed (see [`StoreError`]): a corrupt message or
    /// entry, a log that does not fit its snapshot, a scene that does not exist, a disk error.
    #[error(transparent)]
    Store(#[from] StoreError),
}

impl LogError {
    /// A fault in what the log holds (as opposed to reaching it): waiting does not help, an
    /// operator must look.
    pub fn is_fault(&self) -> bool {
        matches!(
            self,
            LogError::Store(
                StoreError::Corrupt { .. }
                    | StoreError::Inconsistent { .. }
                    | StoreError::UnknownScene(_)
            )
        )
    }
}

/// A turn the owner hands over to be made durable while it goes on ([`SceneLog::submit`]).
#[derive(Debug, Default)]
pub struct OwnedTurn {
    pub records: Vec<(u64, LogRecord)>,
    pub history: HistoryWrites,
    pub answered: Vec<AnsweredEntry>,
}

impl OwnedTurn {
    pub fn as_write(&self) -> TurnWrite<'_> {
        TurnWrite {
            records: &self.records,
            history: &self.history,
            answered: &self.answered,
        }
    }
}

/// Where a scene's owner makes its turns durable (see the module doc).
pub trait SceneLog: Send {
    /// Makes one turn durable, after every turn handed over before it; only then does the
    /// owner acknowledge it. A shared log refuses ([`LogError::Deposed`]) an owner that may
    /// not order.
    fn append(&mut self, turn: TurnWrite<'_>) -> Result<(), LogError>;

    /// Hands over turn `ticket` to be made durable, telling `done` once it is
    /// (`durable.rs`): the owner goes on with the next turn meanwhile, and what it queues for
    /// sessions waits for the ticket. Ok(true): durable already (the default appends now);
    /// Ok(false): being written. An error of an earlier turn's commit may come back here.
    fn submit(
        &mut self,
        turn: OwnedTurn,
        ticket: u64,
        done: &std::sync::Arc<Durability>,
    ) -> Result<bool, LogError> {
        self.append(turn.as_write())?;
        done.durable_to(ticket);
        Ok(true)
    }

    /// Waits until every turn submitted is durable; the error of a commit that failed.
    fn flush(&mut self) -> Result<(), LogError> {
        Ok(())
    }

    /// The error of a commit that failed since, if any, without waiting.
    fn failed(&mut self) -> Result<(), LogError> {
        Ok(())
    }

    /// A stored undo step's bytes.
    fn history_step(&self, id: u64) -> Result<Option<Vec<u8>>, LogError>;

    /// Snapshots the scene so that recovery replays less (and the log can be trimmed). False
    /// when nothing was written (a shared log: not this owner's to write, or one is still
    /// being stored).
    fn snapshot(&mut self, at: SnapshotOf<'_>) -> Result<bool, LogError>;

    /// Whether this owner may order edits now.
    fn may_order(&self) -> bool;

    /// Whether other owners append to this log (and this one follows them).
    fn shared(&self) -> bool {
        false
    }

    /// The position in the log of the last turn this replica holds.
    fn position(&self) -> u64 {
        0
    }

    /// The turns after [`SceneLog::position`], up to the log's end (catching up before a
    /// claim). An error when one cannot be read: the owner reloads.
    fn tail(&mut self) -> Result<Vec<(u64, Turn)>, LogError> {
        Ok(Vec::new())
    }

    /// Makes this owner the one that orders (a shared log: appends a marker, fenced on the
    /// position, so that the previous owner's next append is refused).
    fn claim(&mut self) -> Result<(), LogError> {
        Ok(())
    }

    /// Stops ordering (the lease is gone, or another owner appended).
    fn follow(&mut self) {}

    /// This replica applied the turn at `pos` another owner appended.
    fn applied(&mut self, _pos: u64, _turn: &Turn) {}

    /// The scene as the log holds it now (its snapshot and every turn after it).
    fn reload(&mut self) -> Result<Loaded, LogError>;

    /// Waits a little before the log is tried again (it could not be reached).
    fn pause(&mut self) {
        std::thread::sleep(std::time::Duration::from_millis(500));
    }

    /// Waits for work still running in the background (a snapshot being stored) before the
    /// owner stops.
    fn close(&mut self) {}
}
