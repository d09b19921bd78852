//! A scene's past (issue #34): what its timeline and a view of an earlier sequence read.
//!
//! **What is kept.** A snapshot used to drop the log it folded in and overwrite the bricks it
//! rewrote. Now, in the same transaction, it first keeps them (unless history is off):
//! - `pastbricks/<scene>`: (P, cell) → the cell's row as it was at the old snapshot P (empty:
//!   no brick), for every cell the new snapshot rewrites;
//! - `pastpalette/<scene>`: P → the palette at P and the bytes kept with P (a row for every
//!   snapshot kept, so its keys are the **points** the past can be rebuilt from);
//! - `pastlog/<scene>`: the log rows the snapshot trims, as they were.
//!
//! and every commit notes its time: `times/<scene>`: the last sequence it made durable → Unix
//! milliseconds (one row per commit, so a turn costs no more rows than a commit already did).
//!
//! **Rebuilding sequence s.** The state at a point P is the snapshot's bricks with, for each
//! cell, the kept row of the *first* point at or after P that kept it (the cell's state just
//! before the next snapshot rewrote it); then the log rows after P (kept ones, then the live
//! log) replay up to s through the same `LogRecord::replay` as recovery. A view starts at the
//! latest point at or before s (the snapshot itself from its sequence on), so it replays at
//! most one snapshot interval of log; it reads every brick row kept after that point.
//!
//! **Retention.** The store keeps at least the last `keep` sequences, unless they take more
//! than `keep_bytes` (each point's row counts the bytes kept with it): at each snapshot, the
//! points older than the latest one at or before `head − keep` (or than the oldest that fits
//! the bytes, counting from the newest), their bricks, and the rows and times at or before
//! that point go. `keep` 0 keeps nothing (as before #34).
//!
//! Single node only: a cluster's snapshots and log live in JetStream, and keep no past yet.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};

use brickcast_protocol::BrickMap;
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::UserId;
use redb::{ReadableDatabase, ReadableTable, TableDefinition, WriteTransaction};
use serde::Serialize;

use super::{
    PALETTE_ROW, RowReader, SCENES, Store, StoreError, bricks_table, log_table, open_optional,
    palette_table, stored_palette,
};
use crate::record::LogRecord;

/// Sequences of history a store keeps unless told otherwise (`serve --keep-history`).
pub const DEFAULT_KEEP: u64 = 1_000_000;
/// Bytes of one scene's past a store keeps at most unless told otherwise (`serve
/// --keep-history-bytes`): the oldest go first beyond them, so a scene rewritten whole at
/// every snapshot cannot fill the disk.
pub const DEFAULT_KEEP_BYTES: u64 = 1 << 30;

type PastBricks<'a> = TableDefinition<'a, (u64, u32), &'static [u8]>;
type Rows<'a> = TableDefinition<'a, u64, &'static [u8]>;
type Times<'a> = TableDefinition<'a, u64, u64>;

pub(super) fn past_bricks_table(name: &str) -> String {
    format!("pastbricks/{name}")
}
pub(super) fn past_palette_table(name: &str) -> String {
    format!("pastpalette/{name}")
}
pub(super) fn past_log_table(name: &str) -> String {
    format!("pastlog/{name}")
}
pub(super) fn times_table(name: &str) -> String {
    format!("times/{name}")
}

/// Deletes every table of a scene's past (the scene is deleted or made anew).
pub(super) fn delete_all(txn: &WriteTransaction, name: &str) -> Result<(), StoreError> {
    txn.delete_table(PastBricks::new(&past_bricks_table(name)))?;
    txn.delete_table(Rows::new(&past_palette_table(name)))?;
    txn.delete_table(Rows::new(&past_log_table(name)))?;
    txn.delete_table(Times::new(&times_table(name)))?;
    Ok(())
}

/// Notes the time of a commit whose last sequence is `last`.
pub(super) fn note_time(txn: &WriteTransaction, name: &str, last: u64) -> Result<(), StoreError> {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64);
    txn.open_table(Times::new(&times_table(name)))?
        .insert(last, now)?;
    Ok(())
}

/// In a snapshot's transaction, before it rewrites anything: keeps the rows of `cells` and the
/// palette as they were at the old snapshot `old`, and the log rows up to `new` (see the
/// module doc). Nothing when `keep` is 0 or the snapshot does not move.
pub(super) fn archive(
    txn: &WriteTransaction,
    name: &str,
    old: u64,
    new: u64,
    cells: &[u32],
    keep: Keep,
) -> Result<(), StoreError> {
    if keep.seqs == 0 || new == old {
        return Ok(());
    }
    let mut bytes = 0u64;
    let bricks = txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_table(name)))?;
    let mut past = txn.open_table(PastBricks::new(&past_bricks_table(name)))?;
    for &cell in cells {
        match bricks.get(cell)? {
            Some(row) => {
                bytes += row.value().len() as u64 + 12;
                past.insert((old, cell), row.value())?
            }
            None => {
                bytes += 12;
                past.insert((old, cell), &[][..])?
            }
        };
    }
    drop(bricks);
    let log = txn.open_table(Rows::new(&log_table(name)))?;
    let mut past_log = txn.open_table(Rows::new(&past_log_table(name)))?;
    for row in log.range(..=new)? {
        let (key, row) = row?;
        bytes += row.value().len() as u64 + 8;
        past_log.insert(key.value(), row.value())?;
    }
    let mut point = {
        let table = txn.open_table(TableDefinition::<u32, &[u8]>::new(&palette_table(name)))?;
        let row = table.get(PALETTE_ROW)?;
        row.map_or_else(
            || Swatches::default().to_bytes().to_vec(),
            |r| r.value().to_vec(),
        )
    };
    point.extend_from_slice(&bytes.to_le_bytes());
    txn.open_table(Rows::new(&past_palette_table(name)))?
        .insert(old, point.as_slice())?;
    Ok(())
}

/// A point's row: the palette then, and the bytes kept with the point (its bricks and the log
/// after it up to the next point).
fn split_point(row: &[u8]) -> (&[u8], u64) {
    if row.len() == 2 * brickcast_protocol::swatches::SWATCHES {
        return (row, 0); // a palette alone
    }
    match row.len().checked_sub(8) {
        Some(at) => {
            let (palette, bytes) = row.split_at(at);
            let bytes: [u8; 8] = bytes.try_into().unwrap_or_default();
            (palette, u64::from_le_bytes(bytes))
        }
        None => (row, 0),
    }
}

/// How much of a scene's past a store keeps: at least the last `seqs` sequences, unless they
/// take more than `bytes`, when the oldest go first (0 sequences: nothing).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Keep {
    pub seqs: u64,
    pub bytes: u64,
}

/// After a snapshot at `head`: drops what no sequence `keep` keeps needs.
pub(super) fn trim(
    txn: &WriteTransaction,
    name: &str,
    head: u64,
    keep: Keep,
) -> Result<(), StoreError> {
    let mut points = txn.open_table(Rows::new(&past_palette_table(name)))?;
    let kept: Vec<(u64, u64)> = points
        .iter()?
        .map(|r| r.map(|(k, v)| (k.value(), split_point(v.value()).1)))
        .collect::<Result<_, _>>()?;
    // Every point before `cut` goes, with its bricks, and the log and times up to it.
    let everything = head.saturating_add(1);
    let mut cut = 0;
    if keep.seqs == 0 {
        cut = everything;
    } else {
        // The latest point at or before the horizon: every sequence after it rebuilds from it.
        let horizon = head.saturating_sub(keep.seqs);
        if let Some(&(p, _)) = kept.iter().rev().find(|(p, _)| *p <= horizon) {
            cut = p;
        }
        // Newest first, the points that fit in the bytes; the first that does not goes with
        // every older one.
        let mut total = 0u64;
        for (i, &(_, bytes)) in kept.iter().enumerate().rev() {
            total = total.saturating_add(bytes);
            if total > keep.bytes {
                cut = cut.max(kept.get(i + 1).map_or(everything, |&(p, _)| p));
                break;
            }
        }
    }
    if cut == 0 {
        return Ok(());
    }
    points.retain_in(..cut, |_, _| false)?;
    txn.open_table(PastBricks::new(&past_bricks_table(name)))?
        .retain_in(..(cut, 0), |_, _| false)?;
    txn.open_table(Rows::new(&past_log_table(name)))?
        .retain_in(..=cut.min(head), |_, _| false)?;
    txn.open_table(Times::new(&times_table(name)))?
        .retain_in(..=cut.min(head), |_, _| false)?;
    Ok(())
}

/// The sequences a scene's past can be seen at: `oldest ..= newest`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct Span {
    pub oldest: u64,
    pub newest: u64,
}

/// What one user did to a scene over consecutive sequences (one row of the timeline).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Change {
    pub first: u64,
    pub last: u64,
    /// As a string in JSON: user ids are 64-bit, past what a JavaScript number holds exactly.
    #[serde(serialize_with = "as_string")]
    pub user: UserId,
    /// `edit`, `palette`, `undo`, `redo`, `paste` or `restore`.
    pub kind: &'static str,
    /// The voxels of the bricks it changed lie within `min ..= max` (none for a palette).
    pub min: [u32; 3],
    pub max: [u32; 3],
    /// Bricks changed, summed over its sequences.
    pub bricks: u64,
    /// When its last sequence was made durable (Unix milliseconds), where the store noted it.
    pub at_ms: Option<u64>,
}

fn as_string<S: serde::Serializer>(user: &UserId, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&user.to_string())
}

/// Changes further apart than this in time are two rows of the timeline.
const MERGE_MS: u64 = 10_000;

fn kind(record: &LogRecord) -> &'static str {
    match record {
        LogRecord::Ops { ops, .. }
            if ops
                .iter()
                .all(|op| matches!(op, brickcast_protocol::wire::EditOp::Swatch { .. })) =>
        {
            "palette"
        }
        LogRecord::Ops { .. } => "edit",
        LogRecord::Restore { redo: false, .. } | LogRecord::Revert { redo: false, .. } => "undo",
        LogRecord::Restore { .. } | LogRecord::Revert { .. } => "redo",
        LogRecord::Paste { .. } => "paste",
        LogRecord::Rewind { .. } => "restore",
    }
}

impl Store {
    /// The sequences whose scene the store can rebuild.
    pub fn past_span(&self, name: &str) -> Result<Span, StoreError> {
        let txn = self.db.begin_read()?;
        let meta = self.meta(&txn, name)?;
        span(&txn, name, meta.snapshot_seq)
    }

    /// The scene as it was at sequence `seq` (read-only use: its undo history is not loaded).
    pub fn scene_at(&self, name: &str, seq: u64) -> Result<BrickMap, StoreError> {
        let txn = self.db.begin_read()?;
        self.replay_past(&txn, name, Some(seq), false, |_, _, _| {})
    }

    /// The scene at sequence `seq` and as the store holds it now, read together (what a
    /// restore compares).
    pub fn then_and_now(&self, name: &str, seq: u64) -> Result<(BrickMap, BrickMap), StoreError> {
        let txn = self.db.begin_read()?;
        let then = self.replay_past(&txn, name, Some(seq), false, |_, _, _| {})?;
        let now = self.replay_past(&txn, name, None, false, |_, _, _| {})?;
        Ok((then, now))
    }

    /// Who changed what region when over the sequences the store keeps: the latest `limit`
    /// changes, oldest first, and the span they were read from.
    pub fn timeline(&self, name: &str, limit: usize) -> Result<(Span, Vec<Change>), StoreError> {
        let txn = self.db.begin_read()?;
        let meta = self.meta(&txn, name)?;
        let span = span(&txn, name, meta.snapshot_seq)?;
        let times: BTreeMap<u64, u64> = match open_optional::<u64, u64>(&txn, &times_table(name))? {
            Some(table) => table
                .iter()?
                .map(|r| r.map(|(k, v)| (k.value(), v.value())))
                .collect::<Result<_, _>>()?,
            None => BTreeMap::new(),
        };
        let mut changes: VecDeque<Change> = VecDeque::new();
        let map = self.replay_past(&txn, name, None, true, |seq, record, cells: &[[u32; 3]]| {
            let kind = kind(record);
            if cells.is_empty() && kind != "palette" {
                return; // a copy, or an edit that changed nothing
            }
            let at_ms = times.range(seq..).next().map(|(_, t)| *t);
            let (mut min, mut max) = ([u32::MAX; 3], [0; 3]);
            for c in cells {
                for i in 0..3 {
                    min[i] = min[i].min(c[i].saturating_mul(8));
                    max[i] = max[i].max(c[i].saturating_mul(8).saturating_add(7));
                }
            }
            if cells.is_empty() {
                (min, max) = ([0; 3], [0; 3]);
            }
            let user = record.user();
            if let Some(last) = changes.back_mut()
                && last.user == user
                && last.kind == kind
                && last.last + 1 == seq
                && match (last.at_ms, at_ms) {
                    // Within the window of the row's latest change.
                    (Some(a), Some(b)) => b.saturating_sub(a) <= MERGE_MS,
                    (None, None) => true,
                    _ => false,
                }
            {
                last.last = seq;
                last.at_ms = at_ms;
                last.bricks += cells.len() as u64;
                if !cells.is_empty() {
                    for i in 0..3 {
                        last.min[i] = last.min[i].min(min[i]);
                        last.max[i] = last.max[i].max(max[i]);
                    }
                }
                return;
            }
            if changes.len() == limit {
                changes.pop_front();
            }
            changes.push_back(Change {
                first: seq,
                last: seq,
                user,
                kind,
                min,
                max,
                bricks: cells.len() as u64,
                at_ms,
            });
        })?;
        let size = map.size();
        for c in &mut changes {
            c.max = std::array::from_fn(|i| c.max[i].min(size[i].saturating_sub(1)));
        }
        Ok((span, changes.into()))
    }

    /// Rebuilds the scene at `seq` (`None`: the newest sequence) from the oldest point when
    /// `from_oldest`, else from the latest point at or before it (the snapshot itself from its
    /// sequence on), calling `visit` with each record replayed on the way and the cells (brick
    /// coordinates) it changed.
    fn replay_past(
        &self,
        txn: &redb::ReadTransaction,
        name: &str,
        seq: Option<u64>,
        from_oldest: bool,
        mut visit: impl FnMut(u64, &LogRecord, &[[u32; 3]]),
    ) -> Result<BrickMap, StoreError> {
        let meta = self.meta(txn, name)?;
        let span = span(txn, name, meta.snapshot_seq)?;
        let seq = seq.unwrap_or(span.newest);
        if seq < span.oldest || seq > span.newest {
            return Err(StoreError::NotKept {
                scene: name.into(),
                seq,
                oldest: span.oldest,
                newest: span.newest,
            });
        }
        let corrupt = |detail: String| StoreError::Corrupt {
            scene: name.into(),
            detail,
        };
        let points = open_optional::<u64, &[u8]>(txn, &past_palette_table(name))?;
        // The point the rebuild starts from, and the palette then.
        let (start, palette) = {
            let found = match &points {
                Some(_) if !from_oldest && seq >= meta.snapshot_seq => None,
                Some(points) if !from_oldest => points
                    .range(..=seq)?
                    .next_back()
                    .transpose()?
                    .map(|(k, v)| (k.value(), v.value().to_vec())),
                Some(points) => points
                    .first()?
                    .map(|(k, v)| (k.value(), v.value().to_vec())),
                None => None,
            };
            match found {
                Some((point, row)) if point < meta.snapshot_seq => {
                    let swatches = Swatches::from_bytes(split_point(&row).0)
                        .ok_or_else(|| corrupt(format!("the palette kept at sequence {point}")))?;
                    (point, Some(swatches))
                }
                _ => (meta.snapshot_seq, stored_palette(txn, name)?),
            }
        };
        // Each cell's row at `start`: the first point at or after it that kept the cell.
        let mut overlay: HashMap<u32, Vec<u8>> = HashMap::new();
        if start < meta.snapshot_seq
            && let Some(past) = open_optional::<(u64, u32), &[u8]>(txn, &past_bricks_table(name))?
        {
            for row in past.range((start, 0)..)? {
                let (key, bytes) = row?;
                overlay
                    .entry(key.value().1)
                    .or_insert_with(|| bytes.value().to_vec());
            }
        }
        let mut map = BrickMap::new(meta.size).map_err(|e| corrupt(e.to_string()))?;
        map.set_sequence(start);
        map.begin_bulk_load();
        let mut rows = RowReader::default();
        let bricks = txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_table(name)))?;
        for row in bricks.iter()? {
            let (cell, bytes) = row?;
            let cell = cell.value();
            if !overlay.contains_key(&cell) {
                rows.put(&mut map, cell, bytes.value()).map_err(corrupt)?;
            }
        }
        for (cell, bytes) in &overlay {
            if !bytes.is_empty() {
                rows.put(&mut map, *cell, bytes)
                    .map_err(|e| corrupt(format!("kept {e}")))?;
            }
        }
        map.end_bulk_load();
        if let Some(swatches) = palette {
            map.set_swatches(swatches);
        }
        // The records after `start`: the kept rows, then the live log.
        let unlimited = LogRecord::replay_limits();
        let kept = open_optional::<u64, &[u8]>(txn, &past_log_table(name))?;
        let log = txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_table(name)))?;
        let mut at = start;
        map.record_touched(true);
        let mut cells = Vec::new();
        let mut seen = HashSet::new();
        let kept_rows = match &kept {
            Some(kept) => Some(kept.range(start.saturating_add(1)..)?),
            None => None,
        };
        let live_rows = log.range(meta.snapshot_seq.max(start).saturating_add(1)..)?;
        'rows: for row in kept_rows.into_iter().flatten().chain(live_rows) {
            let (key, bytes) = row?;
            let key = key.value();
            let records = LogRecord::read_row(key, bytes.value())
                .map_err(|e| corrupt(format!("log row {key}: {e}")))?;
            for (s, record) in records {
                if s <= at {
                    continue; // a kept row that also held sequences before the start
                }
                if s > seq {
                    break 'rows;
                }
                if s != at + 1 {
                    return Err(StoreError::Inconsistent {
                        scene: name.into(),
                        detail: format!(
                            "the kept history jumps from sequence {at} to {s}: entries {}..={} are missing",
                            at + 1,
                            s - 1
                        ),
                    });
                }
                map.set_sequence(s);
                record
                    .replay(&mut map, &unlimited)
                    .map_err(|e| corrupt(format!("kept log entry {s} no longer applies: {e}")))?;
                cells.clear();
                seen.clear();
                for cell in map.take_touched() {
                    if seen.insert(cell) {
                        cells.push(map.cell_coords(cell));
                    }
                }
                visit(s, &record, &cells);
                at = s;
            }
        }
        map.record_touched(false);
        if at != seq {
            return Err(StoreError::Inconsistent {
                scene: name.into(),
                detail: format!("the kept history ends at sequence {at}, not {seq}"),
            });
        }
        map.rebuild_clearance();
        Ok(map)
    }
}

/// The sequences a scene's past can be rebuilt at (the snapshot at `snapshot_seq`).
fn span(txn: &redb::ReadTransaction, name: &str, snapshot_seq: u64) -> Result<Span, StoreError> {
    let oldest = match open_optional::<u64, &[u8]>(txn, &past_palette_table(name))? {
        Some(points) => points.first()?.map(|(k, _)| k.value()),
        None => None,
    };
    let log = txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_table(name)))?;
    let newest = log.last()?.map_or(snapshot_seq, |(k, _)| k.value());
    Ok(Span {
        oldest: oldest.unwrap_or(snapshot_seq).min(snapshot_seq),
        newest: newest.max(snapshot_seq),
    })
}

impl Store {
    fn meta(
        &self,
        txn: &redb::ReadTransaction,
        name: &str,
    ) -> Result<super::SceneMeta, StoreError> {
        let scenes = txn.open_table(SCENES)?;
        let Some(bytes) = scenes.get(name)? else {
            return Err(StoreError::UnknownScene(name.into()));
        };
        self.decode_meta(name, bytes.value())
    }
}

#[cfg(test)]
mod tests {
    use brickcast_protocol::wire::EditOp;
    use brickcast_protocol::{BrushMode, Colour};

    use super::*;
    use crate::scene::history::HistoryWrites;

    /// The op of sequence `seq` in the test's scene (a voxel, a hole, a swatch, a box).
    fn op(seq: u64) -> EditOp {
        let x = (seq * 5 % 30) as u32;
        match seq % 4 {
            0 => EditOp::Set {
                pos: [x, 6, 31 - x],
                colour: Colour(seq as u16 * 97),
            },
            1 => EditOp::Sphere {
                centre: [x as f32, 2.0, 10.0],
                radius: 3.0,
                mode: BrushMode::Erase,
                colour: Colour::WHITE,
            },
            2 => EditOp::Swatch {
                index: (seq % 32) as u8,
                colour: Colour(seq as u16),
            },
            _ => EditOp::Box {
                min: [x, 2, 20],
                max: [x + 1, 4 + (seq % 5) as u32, 22],
                mode: BrushMode::Fill,
                colour: Colour(seq as u16 * 31),
            },
        }
    }

    /// Edits a scene sequence by sequence (turns of one to three), snapshotting every seventh
    /// sequence, and keeps the scene after each sequence to compare with.
    struct Scene {
        store: Store,
        map: BrickMap,
        states: Vec<BrickMap>,
        snapshot_at: u64,
    }

    impl Scene {
        fn new(dir: &std::path::Path) -> Scene {
            let store = Store::open(dir).unwrap();
            let mut map = BrickMap::new([32, 16, 32]).unwrap();
            map.fill_box([0, 0, 0], [31, 1, 31], BrushMode::Fill, Colour(500));
            store.create_scene("s", &map).unwrap();
            map.record_touched(true);
            Scene {
                store,
                states: vec![map.clone()],
                map,
                snapshot_at: 0,
            }
        }

        fn edit_to(&mut self, last: u64) {
            let mut turn = Vec::new();
            for seq in self.states.len() as u64..=last {
                self.map.set_sequence(seq);
                let op = op(seq);
                brickcast_protocol::apply::apply_op(&mut self.map, &op, &Default::default())
                    .unwrap();
                self.states.push(self.map.clone());
                turn.push((
                    seq,
                    LogRecord::Ops {
                        user: seq % 2 + 1,
                        ops: vec![op],
                    },
                ));
                if turn.len() == (seq % 3 + 1) as usize || seq == last || seq % 7 == 0 {
                    self.store
                        .append("s", &turn, &HistoryWrites::default())
                        .unwrap();
                    turn.clear();
                }
                if seq % 7 == 0 {
                    self.snapshot();
                }
            }
        }

        fn snapshot(&mut self) {
            let cells = self.map.take_touched();
            let seq = self.map.sequence();
            self.store.snapshot("s", &self.map, &cells, seq).unwrap();
            self.snapshot_at = seq;
        }

        /// Every sequence in `span` rebuilds as it was.
        fn check(&self, seqs: std::ops::RangeInclusive<u64>) {
            for seq in seqs {
                let then = self.store.scene_at("s", seq).unwrap();
                assert_eq!(
                    then.content_hash(),
                    self.states[seq as usize].content_hash(),
                    "sequence {seq}"
                );
                assert_eq!(then.sequence(), seq);
            }
        }
    }

    #[test]
    fn every_kept_sequence_rebuilds_and_retention_trims_at_snapshots() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Scene::new(dir.path());
        s.edit_to(40);
        // Snapshots at 7, 14, ..., 35 kept their past: every sequence from 0 rebuilds, those
        // before the snapshot and those in the live log after it.
        assert_eq!(s.snapshot_at, 35);
        assert_eq!(
            s.store.past_span("s").unwrap(),
            Span {
                oldest: 0,
                newest: 40
            }
        );
        s.check(0..=40);
        assert!(matches!(
            s.store.scene_at("s", 41),
            Err(StoreError::NotKept {
                seq: 41,
                oldest: 0,
                newest: 40,
                ..
            })
        ));
        // The scene itself loads as before.
        let loaded = s.store.load_scene("s").unwrap();
        assert_eq!(loaded.map.content_hash(), s.map.content_hash());

        // Keep 10: the snapshot at 49 drops what sequences before 39 needed, keeping the
        // latest point at or before 39 (the snapshot at 35).
        s.store.set_keep_history(10);
        s.edit_to(49);
        assert_eq!(s.store.past_span("s").unwrap().oldest, 35);
        s.check(35..=49);
        assert!(matches!(
            s.store.scene_at("s", 34),
            Err(StoreError::NotKept { oldest: 35, .. })
        ));
        // A restart reads the same past.
        let path = s.store.path().parent().unwrap().to_path_buf();
        let s = {
            let Scene {
                store,
                map,
                states,
                snapshot_at,
            } = s;
            drop(store);
            Scene {
                store: Store::open(&path).unwrap(),
                map,
                states,
                snapshot_at,
            }
        };
        s.check(35..=49);

        // Bytes bound it too: with room for less than the newest point's, the next snapshot
        // keeps none of the past, whatever the sequences.
        let mut s = s;
        s.store.set_keep_history(1_000_000);
        s.store.set_keep_history_bytes(1);
        s.edit_to(56);
        assert_eq!(s.store.past_span("s").unwrap().oldest, 56);
        s.store.set_keep_history_bytes(u64::MAX);
        s.edit_to(63);
        assert_eq!(s.store.past_span("s").unwrap().oldest, 56);
        s.check(56..=63);
        // Keep nothing: the next snapshot drops it all.
        s.store.set_keep_history(0);
        s.edit_to(70);
        assert_eq!(
            s.store.past_span("s").unwrap(),
            Span {
                oldest: 70,
                newest: 70
            }
        );
        s.check(70..=70);
        // Deleting the scene deletes its past: a scene made again under the name has none.
        assert!(s.store.delete_scene("s").unwrap());
        s.store.create_scene("s", &s.states[0]).unwrap();
        assert_eq!(
            s.store.past_span("s").unwrap(),
            Span {
                oldest: 0,
                newest: 0
            }
        );
        assert!(s.store.timeline("s", 10).unwrap().1.is_empty());
    }

    #[test]
    fn the_timeline_says_who_changed_what_region_when() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Scene::new(dir.path());
        let before = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_millis() as u64;
        s.edit_to(20);
        let (span, changes) = s.store.timeline("s", 1000).unwrap();
        assert_eq!(
            span,
            Span {
                oldest: 0,
                newest: 20
            }
        );
        // Users alternate every sequence: one change per sequence that changed something.
        for c in &changes {
            assert_eq!(c.first, c.last, "{c:?}");
            let seq = c.first;
            assert_eq!(c.user, seq % 2 + 1);
            let at = c.at_ms.expect("every commit noted its time");
            assert!(at >= before, "{c:?}");
            match op(seq) {
                EditOp::Swatch { .. } => assert_eq!(c.kind, "palette"),
                EditOp::Set { pos, .. } => {
                    assert_eq!(c.kind, "edit");
                    assert!(
                        (0..3).all(|i| c.min[i] <= pos[i] && pos[i] <= c.max[i]),
                        "{c:?}"
                    );
                    assert_eq!(c.bricks, 1);
                }
                EditOp::Box { min, max, .. } => {
                    assert!(
                        (0..3).all(|i| c.min[i] <= min[i] && max[i] <= c.max[i]),
                        "{c:?}"
                    );
                }
                _ => assert_eq!(c.kind, "edit"),
            }
            assert!((0..3).all(|i| c.max[i] < [32, 16, 32][i]), "{c:?}");
        }
        // Every sequence that changed something is there, from before and after snapshots.
        let listed: Vec<u64> = changes.iter().map(|c| c.first).collect();
        let changed: Vec<u64> = (1..=20u64)
            .filter(|&q| {
                let (a, b) = (&s.states[q as usize - 1], &s.states[q as usize]);
                a.content_hash() != b.content_hash()
            })
            .collect();
        assert_eq!(listed, changed);
        // The latest `limit` only.
        let last3 = s.store.timeline("s", 3).unwrap().1;
        assert_eq!(last3, changes[changes.len() - 3..].to_vec());
    }
}
