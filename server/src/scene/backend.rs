//! Where an owner makes its turns durable: one interface, two stores.
//!
//! **Why an enum and not a trait object:** the owner calls the three operations every store
//! has (append a turn, read an undo step, snapshot), and in a cluster it also steers the
//! JetStream log (catch up, take over, step down: `follow.rs`), which only that store has.
//! Matching on two variants keeps both in plain sight.
//!
//! * [`Backend::Redb`]: the embedded redb file of a single node (`crate::store`). The owner is
//!   always the scene's owner; an append is a durable redb commit.
//! * [`Backend::Jet`]: the cluster's JetStream log (`crate::cluster::JetLog`). The owner
//!   appends only while it holds the scene's lease, fenced by the stream's expected last
//!   sequence; otherwise it follows the log.

use std::sync::Arc;

use brickcast_protocol::BrickMap;

use super::history::{History, HistoryWrites};
use crate::cluster::JetLog;
use crate::record::LogRecord;
use crate::store::{Store, StoreError};

/// A scene's durable store, as its owner sees it.
pub enum Backend {
    Redb { store: Arc<Store>, scene: String },
    Jet(Box<JetLog>),
}

impl Backend {
    /// Makes a turn durable: its records (sequence → what it did) and its history changes,
    /// together.
    pub fn append(
        &mut self,
        records: &[(u64, LogRecord)],
        history: &HistoryWrites,
    ) -> Result<(), StoreError> {
        match self {
            Backend::Redb { store, scene } => store.append(scene, records, history),
            Backend::Jet(log) => log.append(records, history),
        }
    }

    /// A stored undo step's bytes.
    pub fn history_step(&self, id: u64) -> Result<Option<Vec<u8>>, StoreError> {
        match self {
            Backend::Redb { store, scene } => store.history_step(scene, id),
            Backend::Jet(log) => Ok(log.history_step(id)),
        }
    }

    /// Snapshots `map` at `seq`, with `cells` the bricks touched since the last one (redb
    /// writes them; the cluster writes them as a delta, or the whole scene as a new base, with
    /// the history). False when nothing was written:
    /// in a cluster only the owner snapshots, one upload at a time.
    pub fn snapshot(
        &mut self,
        map: &BrickMap,
        cells: &[u32],
        seq: u64,
        history: &History,
    ) -> Result<bool, StoreError> {
        match self {
            Backend::Redb { store, scene } => store.snapshot(scene, map, cells, seq).map(|()| true),
            Backend::Jet(log) => log.snapshot(map, cells, seq, history),
        }
    }

    /// Whether this owner may order edits now: always on one node; in a cluster, while it
    /// holds the lease.
    pub fn leading(&self) -> bool {
        match self {
            Backend::Redb { .. } => true,
            Backend::Jet(log) => log.leading(),
        }
    }

    /// Whether the scene lives in a cluster.
    pub fn clustered(&self) -> bool {
        matches!(self, Backend::Jet(_))
    }

    /// The cluster's log, when the scene lives in one (read only).
    pub fn jet_ref(&self) -> Option<&JetLog> {
        match self {
            Backend::Redb { .. } => None,
            Backend::Jet(log) => Some(log),
        }
    }

    /// The cluster's log, when the scene lives in one.
    pub fn jet(&mut self) -> Option<&mut JetLog> {
        match self {
            Backend::Redb { .. } => None,
            Backend::Jet(log) => Some(log),
        }
    }
}
