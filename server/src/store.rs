//! Durable storage of scenes in one embedded redb file.
//!
//! Per scene: a brick snapshot (one row per brick, keyed by linear cell index) taken at some
//! sequence S, and an append-only edit log of every acknowledged batch after S. Recovery loads the
//! snapshot and replays the log through the same `apply_op` the server used, so the recovered
//! scene is the acknowledged one. Snapshots are incremental: only bricks touched since the last
//! snapshot are rewritten, in the same transaction that trims the log, so a crash at any point
//! leaves either the old snapshot + full log or the new snapshot + trimmed log.
//!
//! Each scene also has its undo history (step bodies in one pack per turn, each user's stacks
//! as index rows and the changes since the last snapshot; see `history_rows.rs` and
//! `scene::history`), written in the same transaction as the log entries of the turn that
//! changed it and never trimmed by snapshots. A turn's log records are one row too
//! (`record.rs`): a turn writes a handful of rows whatever number of messages it holds.
//!
//! Every commit uses `Durability::Immediate` (fsync before `commit` returns); the scene owner
//! batches many edits per commit (group commit) because commits, not records, are what cost.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use brickcast_protocol::brick::{BrickData, popcount};
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::UserId;
use brickcast_protocol::{BrickMap, Colour, palette};
use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};

use crate::record::LogRecord;
use crate::scene::history::{HistoryWrites, Stacks, StepMeta};
use crate::scene::{AnsweredEntry, LogError, SceneLog, SnapshotOf, TurnWrite};
use crate::store_rows::{self, decode_row, encode_row};

mod committer;
mod history_rows;
mod past;
mod streamed;
mod trash;
pub use past::{Change, DEFAULT_KEEP, DEFAULT_KEEP_BYTES, Span};
pub use streamed::SceneWriter;
pub use trash::Deleted;

/// `undo/<scene>`: (user, step id) → bincode [`StepMeta`].
type UndoIndex<'a> = TableDefinition<'a, (u64, u64), &'static [u8]>;

/// Scene name → bincode [`SceneMeta`].
const SCENES: TableDefinition<&str, &[u8]> = TableDefinition::new("scenes");
/// `"store"` → the newest layout the file may hold ([`store_rows::FORMAT`]); absent before 2.
const FORMAT: TableDefinition<&str, u32> = TableDefinition::new("format");

/// Why the store failed. Storage errors are fatal for a scene: the owner stops rather than
/// acknowledge edits it could not make durable.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("cannot open the store at {path}: {source}")]
    Open {
        path: PathBuf,
        source: redb::DatabaseError,
    },
    #[error(
        "the store at {path} was written by a newer brickcast-server (store format {found}; this build reads up to {reads}): run that version or a newer one"
    )]
    Newer {
        path: PathBuf,
        found: u32,
        reads: u32,
    },
    #[error("storage error: {0}")]
    Redb(#[from] redb::Error),
    #[error("stored data for scene {scene} is corrupt: {detail}")]
    Corrupt { scene: String, detail: String },
    #[error("scene {0} does not exist")]
    UnknownScene(String),
    /// A sequence of a scene's past that the store does not keep (`store::past`).
    #[error(
        "scene {scene} keeps its history from sequence {oldest} to {newest}; sequence {seq} is not in it"
    )]
    NotKept {
        scene: String,
        seq: u64,
        oldest: u64,
        newest: u64,
    },
    #[error("scene {0} already exists")]
    SceneExists(String),
    /// A brick handed to a [`SceneWriter`] that the scene cannot hold.
    #[error("scene {scene}: brick at cell {cell:?} cannot be stored: {detail}")]
    BadBrick {
        scene: String,
        cell: [u32; 3],
        detail: String,
    },
    #[error(
        "scene name {0:?} is invalid: use 1-64 letters, digits, '-', '_' or '.', starting with a letter or digit"
    )]
    BadName(String),
    /// The log and the snapshot of a scene do not fit together: replaying would lose, repeat or
    /// reorder acknowledged edits, so the scene is not served until someone looks.
    #[error("scene {scene}: the edit log does not fit the snapshot: {detail}")]
    Inconsistent { scene: String, detail: String },
    /// A commit running on the scene's commit thread failed earlier (its error was reported
    /// then); nothing more is written.
    #[error("scene {scene}: an earlier commit failed: {detail}")]
    CommitFailed { scene: String, detail: String },
}

impl StoreError {
    /// The store is held by another process (a running server): redb allows one writer
    /// process per file.
    pub fn is_locked(&self) -> bool {
        matches!(
            self,
            StoreError::Open {
                source: redb::DatabaseError::DatabaseAlreadyOpen,
                ..
            }
        )
    }
}

macro_rules! from_redb {
    ($($t:ty),*) => {$(
        impl From<$t> for StoreError {
            fn from(e: $t) -> Self {
                StoreError::Redb(e.into())
            }
        }
    )*};
}
from_redb!(
    redb::TransactionError,
    redb::TableError,
    redb::StorageError,
    redb::CommitError,
    redb::SetDurabilityError
);

/// What the store knows about a scene besides its bricks and log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneMeta {
    pub size: [u32; 3],
    /// Sequence number the brick snapshot reflects; log entries after it are replayed.
    pub snapshot_seq: u64,
}

impl SceneMeta {
    fn bytes(&self, scene: &str) -> Result<Vec<u8>, StoreError> {
        ROW.encode(self).map_err(|e| StoreError::Corrupt {
            scene: scene.into(),
            detail: e.to_string(),
        })
    }
}

/// Scene names become redb table names, URL path segments and spool file names: keep them
/// plain. A name starts with a letter or digit, so `.`, `..` and hidden names are not names.
pub fn valid_scene_name(name: &str) -> bool {
    name.len() <= 64
        && name
            .bytes()
            .next()
            .is_some_and(|b| b.is_ascii_alphanumeric())
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.'))
}

fn bricks_table(name: &str) -> String {
    format!("bricks/{name}")
}
fn log_table(name: &str) -> String {
    format!("log/{name}")
}
fn history_table(name: &str) -> String {
    format!("history/{name}")
}
fn undo_table(name: &str) -> String {
    format!("undo/{name}")
}
/// `palette/<scene>`: row 0 → the scene's palette at its snapshot
/// ([`brickcast_protocol::swatches::Swatches::to_bytes`]); absent: the default palette.
fn palette_table(name: &str) -> String {
    format!("palette/{name}")
}
const PALETTE_ROW: u32 = 0;

/// Puts stored brick rows into a map (a scene's load, a view of its past), reusing its buffers.
#[derive(Default)]
struct RowReader {
    words: Vec<u16>,
}

impl RowReader {
    /// Puts the row of linear cell `cell` into `map`; why not, when the row is damaged.
    fn put(&mut self, map: &mut BrickMap, cell: u32, bytes: &[u8]) -> Result<(), String> {
        let coords = map.cell_coords(cell);
        // A coded row's block goes into the map as it is (decoded once, to check it).
        if let Some(mask) = store_rows::coded_row(bytes, &mut self.words) {
            let n = popcount(&mask) as usize;
            let mut colours = [Colour::BLACK; 512];
            let colours = match palette::decode_words(&self.words, &mut colours[..n]) {
                Ok(used) if used == self.words.len() => &colours[..n],
                _ => return Err(format!("brick row {cell}")),
            };
            return map
                .put_coded(coords, mask, colours, &self.words)
                .map_err(|e| e.to_string());
        }
        let brick = decode_row(coords, bytes).ok_or_else(|| format!("brick row {cell}"))?;
        map.put_brick(&brick).map_err(|e| e.to_string())
    }
}

/// The palette stored with a scene's snapshot (none: the default palette).
fn stored_palette(txn: &redb::ReadTransaction, name: &str) -> Result<Option<Swatches>, StoreError> {
    let Some(table) = open_optional::<u32, &[u8]>(txn, &palette_table(name))? else {
        return Ok(None);
    };
    let Some(row) = table.get(PALETTE_ROW)? else {
        return Ok(None);
    };
    Swatches::from_bytes(row.value())
        .map(Some)
        .ok_or_else(|| StoreError::Corrupt {
            scene: name.into(),
            detail: format!("the palette row is {} bytes", row.value().len()),
        })
}

/// A table that may not exist yet (scenes created before history was stored): reads see an
/// empty table.
fn open_optional<K: redb::Key + 'static, V: redb::Value + 'static>(
    txn: &redb::ReadTransaction,
    name: &str,
) -> Result<Option<redb::ReadOnlyTable<K, V>>, StoreError> {
    match txn.open_table(TableDefinition::<K, V>::new(name)) {
        Ok(table) => Ok(Some(table)),
        Err(redb::TableError::TableDoesNotExist(_)) => Ok(None),
        Err(e) => Err(e.into()),
    }
}

/// A store row's bincode (scene metadata, undo index entries, deleted-scene entries): at
/// most 1 GiB, so a corrupt length prefix cannot ask for more.
pub(crate) const ROW: crate::envelope::Format<{ 1 << 30 }> =
    crate::envelope::Format::new("store row", b"");

/// One raw brick row: 64 mask bytes then the colours as u16 LE (what stores before format 2
/// and cluster snapshots before `S3`/`D2` hold; only tests write it now).
#[cfg(test)]
pub(crate) fn encode_brick(
    mask: &brickcast_protocol::brick::Mask,
    colours: &[Colour],
    out: &mut Vec<u8>,
) {
    out.clear();
    for word in mask {
        out.extend_from_slice(&word.to_le_bytes());
    }
    for c in colours {
        out.extend_from_slice(&c.0.to_le_bytes());
    }
}

pub(crate) fn decode_brick(cell: [u32; 3], bytes: &[u8]) -> Option<BrickData> {
    if bytes.len() < 64 || !(bytes.len() - 64).is_multiple_of(2) {
        return None;
    }
    let mut mask = [0u64; 8];
    for (word, chunk) in mask.iter_mut().zip(bytes[..64].chunks_exact(8)) {
        *word = u64::from_le_bytes(chunk.try_into().ok()?);
    }
    let colours = bytes[64..]
        .chunks_exact(2)
        .map(|c| Colour(u16::from_le_bytes([c[0], c[1]])))
        .collect();
    Some(BrickData {
        cell,
        mask,
        colours,
    })
}

/// The redb file holding every scene.
pub struct Store {
    db: Database,
    path: PathBuf,
    /// Per scene, the live steps of each history pack (built from the tables at a scene's
    /// first append, kept only for transactions that commit).
    packs: std::sync::Mutex<std::collections::HashMap<String, history_rows::PackState>>,
    /// Sequences of each scene's past kept for its timeline and views of it (`past.rs`).
    keep_history: std::sync::atomic::AtomicU64,
    /// Bytes of each scene's past kept at most (the oldest go first beyond them).
    keep_history_bytes: std::sync::atomic::AtomicU64,
}

/// A scene as recovered from the store.
pub struct Loaded {
    pub map: BrickMap,
    pub meta: SceneMeta,
    /// The last sequence in the log (or the snapshot's when the log is empty).
    pub seq: u64,
    pub replayed: u64,
    /// Linear cells the replayed log changed (not yet in the snapshot).
    pub replay_touched: Vec<u32>,
    /// Every user's undo and redo stacks.
    pub history: Vec<(UserId, Stacks)>,
    /// The highest history step id in use (0: none).
    pub last_step_id: u64,
    /// Requests from other origins answered so far (a cluster's log; none on one node).
    pub answered: Vec<AnsweredEntry>,
}

impl Store {
    /// Opens (creating if needed) the store in `dir`.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        let path = dir.join("brickcast.redb");
        if let Err(e) = std::fs::create_dir_all(dir) {
            return Err(StoreError::Open {
                path,
                source: redb::DatabaseError::Storage(redb::StorageError::Io(e)),
            });
        }
        let db = Database::create(&path).map_err(|source| StoreError::Open {
            path: path.clone(),
            source,
        })?;
        Store::init(db, path)
    }

    /// Opens (creating if needed) a store on any redb storage backend: the simulation test's
    /// disk, which can lose unsynced writes the way a crash does.
    pub fn with_backend(backend: impl redb::StorageBackend) -> Result<Store, StoreError> {
        let path = PathBuf::from("(custom storage backend)");
        let db = Database::builder()
            .create_with_backend(backend)
            .map_err(|source| StoreError::Open {
                path: path.clone(),
                source,
            })?;
        Store::init(db, path)
    }

    fn init(db: Database, path: PathBuf) -> Result<Store, StoreError> {
        let txn = db.begin_write()?;
        txn.open_table(SCENES)?;
        {
            let mut format = txn.open_table(FORMAT)?;
            let found = format.get("store")?.map(|v| v.value());
            match found {
                Some(found) if found > store_rows::FORMAT => {
                    return Err(StoreError::Newer {
                        path,
                        found,
                        reads: store_rows::FORMAT,
                    });
                }
                Some(found) if found == store_rows::FORMAT => {}
                // Older (or unrecorded): its rows still read; from now on it may hold ours.
                _ => {
                    format.insert("store", store_rows::FORMAT)?;
                }
            }
        }
        txn.commit()?;
        Ok(Store {
            db,
            path,
            packs: Default::default(),
            keep_history: past::DEFAULT_KEEP.into(),
            keep_history_bytes: past::DEFAULT_KEEP_BYTES.into(),
        })
    }

    /// Keeps at least the last `seqs` sequences of each scene's past (0: none), from the next
    /// snapshot on.
    pub fn set_keep_history(&self, seqs: u64) {
        self.keep_history
            .store(seqs, std::sync::atomic::Ordering::Relaxed);
    }

    /// Keeps at most `bytes` of each scene's past (its oldest goes first), from the next
    /// snapshot on.
    pub fn set_keep_history_bytes(&self, bytes: u64) {
        self.keep_history_bytes
            .store(bytes, std::sync::atomic::Ordering::Relaxed);
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Every scene with its metadata, sorted by name.
    pub fn scenes(&self) -> Result<Vec<(String, SceneMeta)>, StoreError> {
        let txn = self.db.begin_read()?;
        let table = txn.open_table(SCENES)?;
        let mut out = Vec::new();
        for row in table.iter()? {
            let (name, bytes) = row?;
            let name = name.value().to_string();
            let meta = self.decode_meta(&name, bytes.value())?;
            out.push((name, meta));
        }
        Ok(out)
    }

    fn decode_meta(&self, scene: &str, bytes: &[u8]) -> Result<SceneMeta, StoreError> {
        ROW.decode_prefix(bytes)
            .map(|(m, _)| m)
            .map_err(|e| StoreError::Corrupt {
                scene: scene.into(),
                detail: format!("metadata: {e}"),
            })
    }

    /// Stores a new scene with all its bricks as the snapshot at the map's sequence.
    pub fn create_scene(&self, name: &str, map: &BrickMap) -> Result<(), StoreError> {
        self.create_scene_with_progress(name, map, &mut |_| {})
    }

    /// [`Store::create_scene`], calling `progress(bricks)` every 4,096 bricks written (an import
    /// of a large scene writes hundreds of thousands of rows).
    pub fn create_scene_with_progress(
        &self,
        name: &str,
        map: &BrickMap,
        progress: &mut dyn FnMut(u64),
    ) -> Result<(), StoreError> {
        if !valid_scene_name(name) {
            return Err(StoreError::BadName(name.into()));
        }
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        {
            let mut scenes = txn.open_table(SCENES)?;
            if scenes.get(name)?.is_some() {
                return Err(StoreError::SceneExists(name.into()));
            }
            let meta = SceneMeta {
                size: map.size(),
                snapshot_seq: map.sequence(),
            };
            scenes.insert(name, meta.bytes(name)?.as_slice())?;
            let bricks_name = bricks_table(name);
            let mut bricks = txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_name))?;
            let mut row = Vec::with_capacity(64 + 1024);
            for (i, (brick, _)) in map.bricks().enumerate() {
                encode_row(&brick.mask, &brick.colours, &mut row);
                bricks.insert(map.cell_index(brick.cell), row.as_slice())?;
                if i % 4096 == 4095 {
                    progress(4096);
                }
            }
            progress(map.brick_count() % 4096);
            let log_name = log_table(name);
            txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_name))?;
            // Also replaces the palette of a scene of this name dropped before.
            let palette_name = palette_table(name);
            let mut palette = txn.open_table(TableDefinition::<u32, &[u8]>::new(&palette_name))?;
            palette.insert(PALETTE_ROW, map.swatches().to_bytes().as_slice())?;
        }
        txn.commit()?;
        Ok(())
    }

    /// Removes a scene, its bricks and its log in one transaction. Returns whether it existed.
    pub fn delete_scene(&self, name: &str) -> Result<bool, StoreError> {
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        let existed = {
            let mut scenes = txn.open_table(SCENES)?;
            scenes.remove(name)?.is_some()
        };
        if existed {
            txn.delete_table(TableDefinition::<u32, &[u8]>::new(&bricks_table(name)))?;
            txn.delete_table(TableDefinition::<u64, &[u8]>::new(&log_table(name)))?;
            txn.delete_table(TableDefinition::<u32, &[u8]>::new(&palette_table(name)))?;
            history_rows::delete_all(&txn, name)?;
            past::delete_all(&txn, name)?;
        }
        self.forget_packs(name);
        txn.commit()?;
        Ok(existed)
    }

    /// Loads a scene: snapshot bricks, then every logged batch replayed in order.
    ///
    /// The log must continue the snapshot exactly: its entries are numbered `snapshot_seq + 1`,
    /// `+ 2`, ... without a gap. Anything else is refused with [`StoreError::Inconsistent`]
    /// rather than replayed around: a gap means acknowledged edits are missing, and an entry
    /// at or below the snapshot's sequence was written after that snapshot (snapshots trim
    /// the log up to their sequence in the same transaction), so skipping it would lose it.
    /// [`Store::load_scene_repairing`] replays such entries instead.
    pub fn load_scene(&self, name: &str) -> Result<Loaded, StoreError> {
        self.load(name, false)
    }

    /// [`Store::load_scene`] for a store whose log holds entries at or below the snapshot's
    /// sequence (written by brickcast-server 0.1, which could record a snapshot one sequence
    /// ahead of the edits it held after a batch whose every op was rejected). Every entry still
    /// in the log was written after the snapshot, so each is replayed, in order; the scene's
    /// sequence becomes the last entry's. `brickcast-server snapshot --repair` then folds them
    /// into a new snapshot. Gaps are still refused.
    pub fn load_scene_repairing(&self, name: &str) -> Result<Loaded, StoreError> {
        self.load(name, true)
    }

    fn load(&self, name: &str, repair: bool) -> Result<Loaded, StoreError> {
        let txn = self.db.begin_read()?;
        let meta = {
            let scenes = txn.open_table(SCENES)?;
            let Some(bytes) = scenes.get(name)? else {
                return Err(StoreError::UnknownScene(name.into()));
            };
            self.decode_meta(name, bytes.value())?
        };
        let corrupt = |detail: String| StoreError::Corrupt {
            scene: name.into(),
            detail,
        };
        let mut map = BrickMap::new(meta.size).map_err(|e| corrupt(e.to_string()))?;
        let bricks_name = bricks_table(name);
        let bricks = txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_name))?;
        map.set_sequence(meta.snapshot_seq);
        // The clearance is built once, after the snapshot's bricks: the log's ray edits are
        // traced again as they replay, and a trace needs it.
        map.begin_bulk_load();
        let mut rows = RowReader::default();
        for row in bricks.iter()? {
            let (cell, bytes) = row?;
            rows.put(&mut map, cell.value(), bytes.value())
                .map_err(corrupt)?;
        }
        map.end_bulk_load();
        if let Some(swatches) = stored_palette(&txn, name)? {
            map.set_swatches(swatches);
        }
        // The snapshot keeps bricks, not the tombstones of bricks removed before it: a client
        // resuming from before the snapshot cannot be told what it must delete, so it gets a
        // full resync (see `BrickMap::changes_since`).
        map.prune_tombstones(meta.snapshot_seq);
        let log_name = log_table(name);
        let log = txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_name))?;
        let unlimited = LogRecord::replay_limits();
        let inconsistent = |detail: String| StoreError::Inconsistent {
            scene: name.into(),
            detail,
        };
        let mut seq = meta.snapshot_seq;
        let mut replayed = 0;
        map.record_touched(true);
        for row in log.iter()? {
            let (key, bytes) = row?;
            let key = key.value();
            let entries = LogRecord::read_row(key, bytes.value())
                .map_err(|e| corrupt(format!("log row {key}: {e}")))?;
            for (s, record) in entries {
                if replayed == 0 && s <= meta.snapshot_seq {
                    if !repair {
                        return Err(inconsistent(format!(
                            "log entry {s} is at or below the snapshot's sequence {} but was written after it \
                             (a store written by brickcast-server 0.1 after a fully rejected edit); serving the scene \
                             would lose that edit. Stop the server and run `brickcast-server snapshot --scene {name} --repair` \
                             to replay every logged entry into a new snapshot",
                            meta.snapshot_seq
                        )));
                    }
                } else if replayed == 0 {
                    if s != meta.snapshot_seq.saturating_add(1) {
                        return Err(inconsistent(format!(
                            "the snapshot is at sequence {} but the log starts at {s}: entries {}..={} are missing",
                            meta.snapshot_seq,
                            meta.snapshot_seq.saturating_add(1),
                            s - 1
                        )));
                    }
                } else if s != seq.saturating_add(1) {
                    return Err(inconsistent(format!(
                        "the log jumps from entry {seq} to {s}: entries {}..={} are missing",
                        seq.saturating_add(1),
                        s - 1
                    )));
                }
                // Only a repair replays entries at or below the snapshot's stamp.
                map.set_sequence(s.max(map.sequence()));
                // An op that applied when logged applies again: the map is in the same state.
                // A failure here means the log does not match the snapshot.
                record
                    .replay(&mut map, &unlimited)
                    .map_err(|e| corrupt(format!("log entry {s} no longer applies: {e}")))?;
                seq = s;
                replayed += 1;
            }
        }
        let seq = seq.max(meta.snapshot_seq);
        if replayed > 0 {
            // Edits only lower it: exact again.
            map.rebuild_clearance();
        }
        let replay_touched = map.take_touched();
        map.record_touched(false);
        let live = history_rows::live_index(&txn, name)?;
        let last_step_id = history_rows::last_id(&txn, name, &live)?;
        let mut rows: BTreeMap<u64, Vec<(u64, StepMeta)>> = BTreeMap::new();
        for ((user, id), meta) in live {
            rows.entry(user).or_default().push((id, meta));
        }
        let history = rows
            .into_iter()
            .map(|(user, rows)| (user, Stacks::from_rows(rows)))
            .collect();
        Ok(Loaded {
            map,
            meta,
            seq,
            replayed,
            replay_touched,
            history,
            last_step_id,
            answered: Vec::new(),
        })
    }

    /// A stored history step's bytes.
    pub fn history_step(&self, scene: &str, id: u64) -> Result<Option<Vec<u8>>, StoreError> {
        let txn = self.db.begin_read()?;
        history_rows::step(&txn, scene, id)
    }

    /// Appends acknowledged records (sequence → what it did) and the turn's history changes in
    /// one durable commit.
    pub fn append(
        &self,
        scene: &str,
        records: &[(u64, LogRecord)],
        history: &HistoryWrites,
    ) -> Result<(), StoreError> {
        self.append_turns(scene, &[(records, history)])
    }

    /// [`Store::append`] of several turns, in order, in one durable commit (group commit: the
    /// turns a pipelined log was handed while the previous commit ran).
    pub fn append_turns(
        &self,
        scene: &str,
        turns: &[(&[(u64, LogRecord)], &HistoryWrites)],
    ) -> Result<(), StoreError> {
        let corrupt = |detail: String| StoreError::Corrupt {
            scene: scene.into(),
            detail,
        };
        let taken = self
            .packs
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(scene);
        let mut packs = match taken {
            Some(packs) => packs,
            None => history_rows::pack_state(&self.db.begin_read()?, scene)?,
        };
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        {
            let log_name = log_table(scene);
            let mut log = txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_name))?;
            let mut buf = Vec::new();
            // Each turn's records in one row when their sequences follow each other (they do:
            // the owner numbers a turn's batches in order); one row each otherwise.
            for (records, history) in turns {
                let rows: Vec<&[(u64, LogRecord)]> =
                    if records.windows(2).all(|w| w[1].0 == w[0].0.wrapping_add(1)) {
                        vec![records]
                    } else {
                        records.chunks(1).collect()
                    };
                for row in rows.into_iter().filter(|r| !r.is_empty()) {
                    LogRecord::encode_batch(row, &mut buf).map_err(corrupt)?;
                    log.insert(row[row.len() - 1].0, buf.as_slice())?;
                }
                history_rows::write(&txn, scene, &mut packs, history)?;
            }
        }
        if let Some(last) = turns
            .iter()
            .filter_map(|(r, _)| r.last())
            .map(|r| r.0)
            .max()
        {
            past::note_time(&txn, scene, last)?;
        }
        txn.commit()?;
        self.packs
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(scene.to_string(), packs);
        Ok(())
    }

    /// Drops what the store remembers of a scene's history packs (its tables are going).
    pub(crate) fn forget_packs(&self, scene: &str) {
        self.packs
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(scene);
    }

    /// [`Store::append`] of plain edit batches with no history (tests).
    #[cfg(test)]
    pub fn append_ops(
        &self,
        scene: &str,
        batches: &[(u64, &[brickcast_protocol::wire::EditOp])],
    ) -> Result<(), StoreError> {
        let records: Vec<(u64, LogRecord)> = batches
            .iter()
            .map(|(seq, ops)| {
                let ops = ops.to_vec();
                (*seq, LogRecord::Ops { user: 0, ops })
            })
            .collect();
        self.append(scene, &records, &HistoryWrites::default())
    }

    /// Writes the bricks at `cells` in their current state (removing rows of empty cells),
    /// moves the snapshot to sequence `seq` (the last sequence whose edits `map` holds) and
    /// drops the log up to it, atomically.
    ///
    /// Refused with [`StoreError::Inconsistent`] when the pieces disagree: a map stamped with
    /// another sequence than `seq`, a `seq` behind the current snapshot, or a log holding
    /// entries after `seq` (they would be replayed on top of a snapshot that already has them).
    pub fn snapshot(
        &self,
        scene: &str,
        map: &BrickMap,
        cells: &[u32],
        seq: u64,
    ) -> Result<(), StoreError> {
        let inconsistent = |detail: String| StoreError::Inconsistent {
            scene: scene.into(),
            detail,
        };
        if map.sequence() != seq {
            return Err(inconsistent(format!(
                "refusing a snapshot at sequence {seq} of a map stamped {}",
                map.sequence()
            )));
        }
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        {
            let old = {
                let scenes = txn.open_table(SCENES)?;
                let Some(bytes) = scenes.get(scene)? else {
                    return Err(StoreError::UnknownScene(scene.into()));
                };
                self.decode_meta(scene, bytes.value())?
            };
            if seq < old.snapshot_seq {
                return Err(inconsistent(format!(
                    "refusing to move the snapshot back from sequence {} to {seq}",
                    old.snapshot_seq
                )));
            }
            let keep = past::Keep {
                seqs: self.keep_history.load(std::sync::atomic::Ordering::Relaxed),
                bytes: self
                    .keep_history_bytes
                    .load(std::sync::atomic::Ordering::Relaxed),
            };
            past::archive(&txn, scene, old.snapshot_seq, seq, cells, keep)?;
            let bricks_name = bricks_table(scene);
            let mut bricks = txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_name))?;
            let mut row = Vec::with_capacity(64 + 1024);
            for &cell in cells {
                match map.brick(map.cell_coords(cell)) {
                    Some(b) => {
                        encode_row(&b.mask, &b.colours, &mut row);
                        bricks.insert(cell, row.as_slice())?;
                    }
                    None => {
                        bricks.remove(cell)?;
                    }
                }
            }
            let log_name = log_table(scene);
            let mut log = txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_name))?;
            if let Some((last, _)) = log.last()? {
                let last = last.value();
                if last > seq {
                    return Err(inconsistent(format!(
                        "refusing a snapshot at sequence {seq}: the log already holds entry {last}"
                    )));
                }
            }
            log.retain_in(..=seq, |_, _| false)?;
            let palette_name = palette_table(scene);
            let mut palette = txn.open_table(TableDefinition::<u32, &[u8]>::new(&palette_name))?;
            palette.insert(PALETTE_ROW, map.swatches().to_bytes().as_slice())?;
            let mut scenes = txn.open_table(SCENES)?;
            let meta = SceneMeta {
                size: map.size(),
                snapshot_seq: seq,
            };
            let bytes = ROW.encode(&meta).map_err(|e| StoreError::Corrupt {
                scene: scene.into(),
                detail: e.to_string(),
            })?;
            scenes.insert(scene, bytes.as_slice())?;
            past::trim(&txn, scene, seq, keep)?;
        }
        txn.commit()?;
        Ok(())
    }

    /// Number of log entries (sequences) after the snapshot.
    pub fn log_len(&self, scene: &str) -> Result<u64, StoreError> {
        let txn = self.db.begin_read()?;
        let log_name = log_table(scene);
        let log = txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_name))?;
        let mut entries = 0;
        for row in log.iter()? {
            entries += LogRecord::row_len(row?.1.value());
        }
        Ok(entries)
    }
}

/// One scene of the redb store as its owner's [`SceneLog`]: a single node, where the owner is
/// always the scene's only one and an append is one durable redb commit.
pub struct StoreLog {
    store: std::sync::Arc<Store>,
    scene: String,
    /// The commit thread of a pipelined log (`committer.rs`); none: every append commits
    /// before it returns (the simulation steps the owner turn by turn this way).
    committer: Option<committer::Committer>,
}

impl StoreLog {
    /// A log whose appends commit before they return.
    pub fn new(store: std::sync::Arc<Store>, scene: String) -> StoreLog {
        StoreLog {
            store,
            scene,
            committer: None,
        }
    }

    /// A log that commits on a thread of its own while the owner goes on (the server's).
    pub fn pipelined(
        store: std::sync::Arc<Store>,
        scene: String,
        metrics: std::sync::Arc<crate::metrics::Metrics>,
    ) -> std::io::Result<StoreLog> {
        let committer = committer::Committer::start(store.clone(), scene.clone(), metrics)?;
        Ok(StoreLog {
            store,
            scene,
            committer: Some(committer),
        })
    }

    /// Waits for the turns handed to the commit thread.
    fn settle(&self) -> Result<(), StoreError> {
        match &self.committer {
            Some(c) => c.flush(),
            None => Ok(()),
        }
    }
}

impl SceneLog for StoreLog {
    fn append(&mut self, turn: TurnWrite<'_>) -> Result<(), LogError> {
        self.settle()?;
        Ok(self.store.append(&self.scene, turn.records, turn.history)?)
    }

    fn submit(
        &mut self,
        turn: crate::scene::OwnedTurn,
        ticket: u64,
        done: &std::sync::Arc<crate::scene::Durability>,
    ) -> Result<bool, LogError> {
        match &mut self.committer {
            Some(c) => {
                c.submit(turn, ticket, done)?;
                Ok(false)
            }
            None => {
                self.store
                    .append(&self.scene, &turn.records, &turn.history)?;
                done.durable_to(ticket);
                Ok(true)
            }
        }
    }

    fn flush(&mut self) -> Result<(), LogError> {
        Ok(self.settle()?)
    }

    fn failed(&mut self) -> Result<(), LogError> {
        match &self.committer {
            Some(c) => Ok(c.check()?),
            None => Ok(()),
        }
    }

    fn history_step(&self, id: u64) -> Result<Option<Vec<u8>>, LogError> {
        // A step of a turn still being committed is not in the store yet.
        self.settle()?;
        Ok(self.store.history_step(&self.scene, id)?)
    }

    fn snapshot(&mut self, at: SnapshotOf<'_>) -> Result<bool, LogError> {
        // The log must hold every entry up to the snapshot's sequence before it is trimmed.
        self.settle()?;
        self.store.snapshot(&self.scene, at.map, at.cells, at.seq)?;
        Ok(true)
    }

    fn may_order(&self) -> bool {
        true
    }

    fn reload(&mut self) -> Result<Loaded, LogError> {
        self.settle()?;
        Ok(self.store.load_scene(&self.scene)?)
    }

    fn close(&mut self) {
        if let Some(mut c) = self.committer.take() {
            c.close();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::BrushMode;
    use brickcast_protocol::wire::EditOp;

    /// A scene's palette goes with it: a new scene keeps the palette its map has, and a
    /// scene made again under a deleted one's name (created, or written in batches) starts
    /// from its own, not the old one's.
    #[test]
    fn a_palette_goes_with_its_scene() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        map.set_swatch(5, Colour(0x1234));
        store.create_scene("p", &map).unwrap();
        assert_eq!(
            store.load_scene("p").unwrap().map.swatches(),
            map.swatches()
        );
        assert!(store.delete_scene("p").unwrap());
        let fresh = BrickMap::new([32, 32, 32]).unwrap();
        store.create_scene("p", &fresh).unwrap();
        assert_eq!(
            store.load_scene("p").unwrap().map.swatches(),
            fresh.swatches()
        );
        // Replaced with a palette of its own, deleted, then written in batches.
        assert!(store.delete_scene("p").unwrap());
        store.create_scene("p", &map).unwrap();
        assert!(store.delete_scene("p").unwrap());
        store
            .begin_scene("p", [32, 32, 32])
            .unwrap()
            .finish()
            .unwrap();
        assert_eq!(
            store.load_scene("p").unwrap().map.swatches(),
            fresh.swatches()
        );
    }

    #[test]
    fn create_append_snapshot_and_recover() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 3, 63], BrushMode::Fill, Colour::WHITE);
        store.create_scene("s", &map).unwrap();
        assert!(matches!(
            store.create_scene("s", &map),
            Err(StoreError::SceneExists(_))
        ));
        assert!(matches!(
            store.create_scene("bad/name", &map),
            Err(StoreError::BadName(_))
        ));

        let red = Colour::from_rgb8(255, 0, 0);
        let ops1 = [EditOp::Set {
            pos: [5, 10, 5],
            colour: red,
        }];
        // The palette is scene state too: replayed from the log, then kept by the snapshot.
        let ops2 = [
            EditOp::Sphere {
                centre: [30.0, 4.0, 30.0],
                radius: 6.0,
                mode: BrushMode::Erase,
                colour: red,
            },
            EditOp::Swatch {
                index: 9,
                colour: red,
            },
        ];
        map.record_touched(true);
        for (seq, ops) in [(1u64, &ops1[..]), (2, &ops2[..])] {
            map.set_sequence(seq);
            for op in ops {
                brickcast_protocol::apply::apply_op(&mut map, op, &Default::default()).unwrap();
            }
        }
        let record = |ops: &[EditOp]| LogRecord::Ops {
            user: 1,
            ops: ops.to_vec(),
        };
        store
            .append(
                "s",
                &[(1, record(&ops1)), (2, record(&ops2))],
                &HistoryWrites::default(),
            )
            .unwrap();
        // The turn is one row (keyed by its last sequence) holding two entries.
        assert_eq!(store.log_len("s").unwrap(), 2);
        {
            let txn = store.db.begin_read().unwrap();
            let log = txn
                .open_table(TableDefinition::<u64, &[u8]>::new(&log_table("s")))
                .unwrap();
            let keys: Vec<u64> = log.iter().unwrap().map(|r| r.unwrap().0.value()).collect();
            assert_eq!(keys, vec![2]);
        }
        let loaded = store.load_scene("s").unwrap();
        assert_eq!((loaded.seq, loaded.replayed), (2, 2));
        assert_eq!(loaded.map.content_hash(), map.content_hash());
        assert_eq!(loaded.map.swatches().get(9), red);
        assert_eq!(loaded.map.swatches(), map.swatches());

        let touched = map.take_touched();
        store.snapshot("s", &map, &touched, 2).unwrap();
        assert_eq!(store.log_len("s").unwrap(), 0);
        let loaded = store.load_scene("s").unwrap();
        assert_eq!((loaded.meta.snapshot_seq, loaded.replayed), (2, 0));
        assert_eq!(loaded.map.content_hash(), map.content_hash());
        assert_eq!(
            loaded.map.swatches(),
            map.swatches(),
            "kept by the snapshot"
        );
        drop(store);
        let reopened = Store::open(dir.path()).unwrap();
        assert_eq!(reopened.scenes().unwrap().len(), 1);
        assert!(matches!(
            reopened.load_scene("nope"),
            Err(StoreError::UnknownScene(_))
        ));
    }

    #[test]
    fn a_store_of_raw_rows_without_a_format_loads_and_a_newer_one_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut map = BrickMap::new([64, 64, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 9, 63], BrushMode::Fill, Colour::WHITE);
        map.fill_box([3, 3, 3], [20, 20, 20], BrushMode::Fill, Colour(0x1234));
        Store::open(dir.path())
            .unwrap()
            .create_scene("s", &map)
            .unwrap();
        // As a store written before the format record: raw rows, no `format` table.
        {
            let db = Database::create(dir.path().join("brickcast.redb")).unwrap();
            let txn = db.begin_write().unwrap();
            assert!(txn.delete_table(FORMAT).unwrap());
            {
                let name = bricks_table("s");
                let mut bricks = txn
                    .open_table(TableDefinition::<u32, &[u8]>::new(&name))
                    .unwrap();
                let mut row = Vec::new();
                for (b, _) in map.bricks() {
                    encode_brick(&b.mask, &b.colours, &mut row);
                    bricks
                        .insert(map.cell_index(b.cell), row.as_slice())
                        .unwrap();
                }
            }
            txn.commit().unwrap();
        }
        let store = Store::open(dir.path()).unwrap();
        assert_eq!(
            store.load_scene("s").unwrap().map.content_hash(),
            map.content_hash()
        );
        drop(store);
        // A newer build's store is refused by name, not read as corrupt rows.
        {
            let db = Database::create(dir.path().join("brickcast.redb")).unwrap();
            let txn = db.begin_write().unwrap();
            txn.open_table(FORMAT)
                .unwrap()
                .insert("store", store_rows::FORMAT + 1)
                .unwrap();
            txn.commit().unwrap();
        }
        let err = Store::open(dir.path())
            .err()
            .expect("a newer store is refused");
        assert!(matches!(err, StoreError::Newer { found, .. } if found == store_rows::FORMAT + 1));
        assert!(err.to_string().contains("newer brickcast-server"), "{err}");
    }
}
