//! A scene's snapshots in the cluster: a whole **base** and a chain of **deltas** after it, in
//! the object store `brickcast_snapshots`, and the scene's **head** in the key-value bucket
//! `brickcast_snapshot_heads`, which names the chain and how far it goes.
//!
//! **Why deltas:** a snapshot lets a node opening the scene skip most of the log, and lets the
//! owner trim the log. A whole scene is big (the 1024³ demo scene: 31 ms to copy on the owner
//! thread, 104 ms to encode, and the upload, kept three times over with `--replicas 3`), while
//! what changed since the last snapshot is usually a few bricks. So the owner writes a base
//! (every brick) and then deltas (the bricks changed since the previous snapshot, the cells
//! emptied, the whole undo index and answered requests, and the step bodies added since),
//! each one trimming the log below it. A new base replaces the chain when the deltas add up
//! to half the base, after [`MAX_DELTAS`], when most bricks changed, or when the owner cannot
//! vouch for what changed since the last snapshot: it just took the scene over, or an upload
//! failed (the changed-brick set it handed over is gone).
//!
//! **Why a head:** an upload can land late: an owner paused (or slow) between deciding to
//! write and its write arriving, while a newer owner snapshotted and trimmed the log below
//! its own snapshot. Objects of one chain are named by its base's random id
//! (`<scene>@<id>`, `<scene>@<id>+1`, …; `@` and `+` cannot occur in a scene name), so no
//! upload replaces another chain's; a snapshot counts only once the head moves to it, by
//! compare-and-set, and only forward (a later log position, and a delta only on the chain and
//! delta the head names). A late upload finds the head past it and is dropped; the log is
//! trimmed only below a snapshot the head names.
//!
//! **Reading:** the head, then its base and exactly its deltas. A chain replaced while it
//! was being read (its objects deleted) fails the read: `log::load` reads again. Scenes
//! written before heads existed (objects `<scene>`, `<scene>+1`, …) are read as they were: the
//! base, then each delta that names that base and follows on.

use std::collections::{BTreeMap, HashMap};
use std::hash::{BuildHasher, Hasher};

use brickcast_protocol::brick::{BrickData, popcount};
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::UserId;
use brickcast_protocol::{BrickMap, Colour, palette};
use serde::{Deserialize, Serialize};

use super::jet::{Bucket, Jet, PortError};
use super::log::{decode_as, encode_as};
use crate::scene::AnsweredEntry;
use crate::scene::LogError;
use crate::scene::history::{History, StepMeta};
use crate::store::{StoreError, decode_brick};

/// First bytes of a base written before deltas existed (no id: no delta follows it; raw rows).
const BASE_V1: [u8; 2] = [b'S', 1];
/// First bytes of a base whose rows are raw (mask, then every voxel's RGB565).
const BASE_V2: [u8; 2] = [b'S', 2];
/// First bytes of a base whose rows are coded (mask, then the brick's colour block).
const BASE_V3: [u8; 2] = [b'S', 3];
/// First bytes of a base with coded rows followed by the scene's palette (`(Base, Swatches)`).
const BASE_MAGIC: [u8; 2] = [b'S', 4];
/// First bytes of a delta whose rows are raw.
const DELTA_V1: [u8; 2] = [b'D', 1];
/// First bytes of a delta whose rows are coded.
const DELTA_V2: [u8; 2] = [b'D', 2];
/// First bytes of a delta with coded rows followed by the scene's palette (`(Delta, Swatches)`).
const DELTA_MAGIC: [u8; 2] = [b'D', 3];

/// How an object's brick rows hold colours; its magic says which.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Rows {
    /// `64 + 2n` bytes: the mask, then each solid voxel's RGB565 (written before issue #29).
    Raw,
    /// The mask, then the brick's exact colour block ([`palette`]): the same words as the
    /// map's colour pool, the redb rows and the wire.
    Coded,
}
/// At most this many deltas follow a base.
pub const MAX_DELTAS: u32 = 32;

/// A whole scene at one sequence.
#[derive(Serialize, Deserialize)]
struct Whole {
    size: [u32; 3],
    /// The scene sequence the bricks reflect.
    seq: u64,
    /// The stream sequence of the last turn the snapshot holds.
    pos: u64,
    undo: Undo,
    bricks: Bricks,
}

/// The undo stacks and answered requests at a snapshot. (bincode writes a nested struct's
/// fields in place: [`Whole`] reads as it did before it was split up.)
#[derive(Serialize, Deserialize)]
struct Undo {
    /// Undo stacks: (user, step id, meta), and step bodies (in a delta, only those newer
    /// than the previous snapshot's).
    history: Vec<(UserId, u64, StepMeta)>,
    steps: Vec<(u64, Vec<u8>)>,
    last_step_id: u64,
    /// The answered forwarded requests (`answered.rs`).
    answered: Vec<AnsweredEntry>,
}

/// Linear cells, and their bricks as rows ([`Rows`]), back to back (a row's length follows
/// from its mask, and for a coded row its block's header).
#[derive(Serialize, Deserialize)]
struct Bricks {
    cells: Vec<u32>,
    rows: Vec<u8>,
}

/// A base: a whole scene and the id its deltas name.
#[derive(Serialize, Deserialize)]
struct Base {
    id: u64,
    whole: Whole,
}

/// What changed since the previous snapshot of a chain.
#[derive(Serialize, Deserialize)]
struct Delta {
    /// The id of the base this delta follows.
    base: u64,
    number: u32,
    seq: u64,
    pos: u64,
    undo: Undo,
    /// Changed bricks that hold voxels, and changed cells now empty.
    bricks: Bricks,
    emptied: Vec<u32>,
}

/// What the owner wrote last, so that the next snapshot can be a delta on it.
#[derive(Clone, Debug, PartialEq)]
pub struct Chain {
    pub(super) base: u64,
    base_bytes: u64,
    /// Number of the next delta.
    next: u32,
    delta_bytes: u64,
    /// The newest undo step whose body the chain holds.
    last_step_id: u64,
}

/// A snapshot ready to encode and upload (made on the owner thread: only copies).
pub struct Prepared {
    kind: Kind,
    /// The scene's palette, written after the base or delta (bincode of the pair).
    swatches: Swatches,
    pub seq: u64,
    pub pos: u64,
    last_step_id: u64,
}

enum Kind {
    Base(Base),
    Delta(Delta),
}

/// A snapshot encoded: its object name, description and bytes.
pub struct Encoded {
    pub scene: String,
    pub name: String,
    pub description: String,
    pub bytes: bytes::Bytes,
    pub seq: u64,
    pub pos: u64,
    /// What the chain looks like once it is stored.
    pub chain: Chain,
    pub is_base: bool,
}

impl Encoded {
    /// The head that names this snapshot.
    fn head(&self) -> Head {
        Head {
            version: HEAD_VERSION,
            base: self.chain.base,
            deltas: self.chain.next - 1,
            seq: self.seq,
            pos: self.pos,
        }
    }
}

/// Format of [`Head`]. 2: the chain's objects may hold coded rows (`S3`/`D2`), which a node
/// that reads only 1 would refuse object by object; it refuses the head by name instead.
/// 3: they may hold the scene's palette (`S4`/`D3`).
const HEAD_VERSION: u32 = 3;

/// What `brickcast_snapshot_heads` says of a scene: its newest snapshot is base `base` and its
/// deltas `1..=deltas`, at scene sequence `seq` and log position `pos`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Head {
    pub version: u32,
    pub base: u64,
    pub deltas: u32,
    pub seq: u64,
    pub pos: u64,
}

impl Head {
    /// Whether `next` may follow this head: further on in the log, and (a delta) on this
    /// chain, right after its last delta.
    fn may_move_to(&self, next: &Head) -> bool {
        next.pos > self.pos
            && next.seq >= self.seq
            && (next.deltas == 0 || (next.base == self.base && next.deltas == self.deltas + 1))
    }
}

/// A scene as its snapshots hold it.
pub struct Restored {
    pub map: BrickMap,
    pub size: [u32; 3],
    pub seq: u64,
    pub pos: u64,
    /// Step id → (user, meta).
    pub rows: BTreeMap<u64, (UserId, StepMeta)>,
    pub steps: HashMap<u64, Vec<u8>>,
    pub last_step_id: u64,
    pub answered: Vec<AnsweredEntry>,
    /// Deltas applied after the base.
    pub deltas: u32,
    base: u64,
}

/// The object of a scene's base `base`.
pub fn base_name(scene: &str, base: u64) -> String {
    format!("{scene}@{base:016x}")
}

/// The object of delta `n` on base `base`.
pub fn delta_name(scene: &str, base: u64, n: u32) -> String {
    format!("{scene}@{base:016x}+{n}")
}

/// Delta `n` of a scene written before heads existed (after the base object `<scene>`).
fn legacy_delta_name(scene: &str, n: u32) -> String {
    format!("{scene}+{n}")
}

/// Whether the next snapshot can be a delta on `chain`, with `changed` of `bricks` bricks
/// changed since the last one.
fn delta_fits(chain: &Chain, changed: usize, bricks: u64) -> bool {
    chain.next <= MAX_DELTAS
        && chain.delta_bytes.saturating_mul(2) < chain.base_bytes
        && (changed as u64).saturating_mul(4) <= bricks.max(1)
}

/// Bricks at `cells` (linear indices) as coded rows, back to back; the cells holding none
/// apart. A row's block is copied from the map's colour pool (the owner's map is exact).
fn rows_of(map: &BrickMap, cells: impl Iterator<Item = u32>) -> (Bricks, Vec<u32>) {
    let (mut solid, mut rows, mut empty) = (Vec::new(), Vec::new(), Vec::new());
    let mut scratch = [Colour::BLACK; 512];
    for cell in cells {
        let coords = map.cell_coords(cell);
        let Some(slot) = map.slot_of_cell(coords) else {
            empty.push(cell);
            continue;
        };
        let mask = &map.masks()[slot as usize];
        for word in mask {
            rows.extend_from_slice(&word.to_le_bytes());
        }
        let block = map.block(slot);
        match palette::coding_of_words(block) {
            Ok(palette::Coding::Blocks { .. }) | Err(_) => {
                palette::encode(map.slot_colours(slot, &mut scratch), &mut rows)
            }
            Ok(coding) => {
                let words = &block[..coding.words(popcount(mask) as usize).min(block.len())];
                rows.extend(words.iter().flat_map(|w| w.to_le_bytes()));
            }
        }
        solid.push(cell);
    }
    (Bricks { cells: solid, rows }, empty)
}

/// A random base id (never 0: a base written before deltas reads as id 0).
fn new_id() -> u64 {
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0),
    );
    h.finish().max(1)
}

/// Prepares the next snapshot of `map` at (`seq`, `pos`): a delta on `chain` holding the bricks
/// at `changed` when it fits, else a base.
#[allow(clippy::too_many_arguments)]
pub fn prepare(
    chain: Option<&Chain>,
    map: &BrickMap,
    changed: &[u32],
    seq: u64,
    pos: u64,
    history: &History,
    steps: &HashMap<u64, Vec<u8>>,
    answered: Vec<AnsweredEntry>,
) -> Prepared {
    let rows = history.rows();
    let last_step_id = history.last_id();
    let undo = |newer_than: Option<u64>| Undo {
        steps: rows
            .iter()
            .filter(|(_, id, _)| newer_than.is_none_or(|n| *id > n))
            .filter_map(|(_, id, _)| steps.get(id).map(|b| (*id, b.clone())))
            .collect(),
        history: rows.clone(),
        last_step_id,
        answered,
    };
    let kind = match chain.filter(|c| delta_fits(c, changed.len(), map.brick_count())) {
        Some(c) => {
            let (bricks, emptied) = rows_of(map, changed.iter().copied());
            Kind::Delta(Delta {
                base: c.base,
                number: c.next,
                seq,
                pos,
                undo: undo(Some(c.last_step_id)),
                bricks,
                emptied,
            })
        }
        None => {
            let every = map.bricks().map(|(b, _)| map.cell_index(b.cell));
            let (bricks, _) = rows_of(map, every);
            Kind::Base(Base {
                id: new_id(),
                whole: Whole {
                    size: map.size(),
                    seq,
                    pos,
                    undo: undo(None),
                    bricks,
                },
            })
        }
    };
    Prepared {
        kind,
        swatches: *map.swatches(),
        seq,
        pos,
        last_step_id,
    }
}

/// The first snapshot of a new scene: a base with no history.
pub fn first(map: &BrickMap) -> Prepared {
    let history = History::new(Vec::new(), 0, 1, 0);
    prepare(
        None,
        map,
        &[],
        map.sequence(),
        0,
        &history,
        &HashMap::new(),
        Vec::new(),
    )
}

impl Prepared {
    /// Encodes and compresses it (the larger part of the work: off the owner thread).
    pub fn encode(self, scene: &str, chain: Option<Chain>) -> Result<Encoded, String> {
        let (seq, pos) = (self.seq, self.pos);
        match self.kind {
            Kind::Base(base) => {
                let bytes = bytes::Bytes::from(encode_as(BASE_MAGIC, &(&base, &self.swatches))?);
                Ok(Encoded {
                    scene: scene.to_string(),
                    name: base_name(scene, base.id),
                    description: format!("seq={seq} pos={pos} id={}", base.id),
                    chain: Chain {
                        base: base.id,
                        base_bytes: bytes.len() as u64,
                        next: 1,
                        delta_bytes: 0,
                        last_step_id: self.last_step_id,
                    },
                    bytes,
                    seq,
                    pos,
                    is_base: true,
                })
            }
            Kind::Delta(delta) => {
                let bytes = bytes::Bytes::from(encode_as(DELTA_MAGIC, &(&delta, &self.swatches))?);
                let before = chain
                    .filter(|c| c.base == delta.base && c.next == delta.number)
                    .ok_or("the delta does not follow the chain it was encoded with")?;
                Ok(Encoded {
                    scene: scene.to_string(),
                    name: delta_name(scene, delta.base, delta.number),
                    description: format!(
                        "seq={seq} pos={pos} base={} n={}",
                        delta.base, delta.number
                    ),
                    chain: Chain {
                        next: delta.number + 1,
                        delta_bytes: before.delta_bytes + bytes.len() as u64,
                        last_step_id: self.last_step_id,
                        ..before
                    },
                    bytes,
                    seq,
                    pos,
                    is_base: false,
                })
            }
        }
    }
}

/// Step id → (user, meta), from a snapshot's undo index.
fn index(history: &[(UserId, u64, StepMeta)]) -> BTreeMap<u64, (UserId, StepMeta)> {
    history.iter().map(|(u, id, m)| (*id, (*u, *m))).collect()
}

/// Puts `bricks`, rows of `format`, into `map` (checked: a corrupt object is an error).
fn put_rows(map: &mut BrickMap, bricks: &Bricks, format: Rows) -> Result<(), String> {
    let (cells, rows) = (&bricks.cells, &bricks.rows);
    let total: u64 = map.cell_dims().iter().map(|&d| u64::from(d)).product();
    let mut colours = Vec::new();
    let mut at = 0usize;
    for &cell in cells {
        if u64::from(cell) >= total {
            return Err(format!("brick {cell} is outside the scene"));
        }
        let mask_end = at + 64;
        let Some(mask_bytes) = rows.get(at..mask_end) else {
            return Err(format!("brick {cell} is cut short"));
        };
        let solid: usize = mask_bytes.iter().map(|b| b.count_ones() as usize).sum();
        let coords = map.cell_coords(cell);
        let end = match format {
            Rows::Raw => {
                let end = mask_end + 2 * solid;
                let row = rows
                    .get(at..end)
                    .ok_or_else(|| format!("brick {cell} is cut short"))?;
                let brick: BrickData = decode_brick(coords, row)
                    .ok_or_else(|| format!("brick {cell} does not decode"))?;
                map.put_brick(&brick).map_err(|e| e.to_string())?;
                end
            }
            Rows::Coded => {
                let bytes = &rows[mask_end.min(rows.len())..];
                let len = palette::decode(bytes, solid, &mut colours)
                    .map_err(|e| format!("brick {cell}'s colours: {e}"))?;
                let mut mask = [0u64; 8];
                for (word, chunk) in mask.iter_mut().zip(mask_bytes.chunks_exact(8)) {
                    let mut le = [0u8; 8];
                    le.copy_from_slice(chunk);
                    *word = u64::from_le_bytes(le);
                }
                let block = palette::words_of(&bytes[..len]);
                map.put_coded(coords, mask, &colours, &block)
                    .map_err(|e| e.to_string())?;
                mask_end + len
            }
        };
        at = end;
    }
    if at != rows.len() {
        return Err(format!("{} bytes after the last brick", rows.len() - at));
    }
    Ok(())
}

impl Restored {
    /// A base's scene.
    pub fn from_base(bytes: &[u8]) -> Result<Restored, String> {
        let old = Swatches::default();
        let (base, format, swatches) = match bytes.get(..2) {
            Some(m) if m == BASE_V1 => {
                let whole = decode_as(BASE_V1, bytes, "snapshot")?;
                (Base { id: 0, whole }, Rows::Raw, old)
            }
            Some(m) if m == BASE_V2 => (decode_as(BASE_V2, bytes, "snapshot")?, Rows::Raw, old),
            Some(m) if m == BASE_V3 => (decode_as(BASE_V3, bytes, "snapshot")?, Rows::Coded, old),
            _ => {
                let (base, swatches) = decode_as(BASE_MAGIC, bytes, "snapshot")?;
                (base, Rows::Coded, swatches)
            }
        };
        let w = base.whole;
        let mut map = BrickMap::new(w.size).map_err(|e| e.to_string())?;
        map.set_sequence(w.seq);
        map.set_swatches(swatches);
        put_rows(&mut map, &w.bricks, format).map_err(|e| format!("snapshot: {e}"))?;
        Ok(Restored {
            map,
            size: w.size,
            seq: w.seq,
            pos: w.pos,
            rows: index(&w.undo.history),
            steps: w.undo.steps.into_iter().collect(),
            last_step_id: w.undo.last_step_id,
            answered: w.undo.answered,
            deltas: 0,
            base: base.id,
        })
    }

    /// Applies delta `number` when it continues this chain: `Ok(false)` when it does not (a
    /// leftover of another chain), an error when it does not decode.
    pub fn apply_delta(&mut self, number: u32, bytes: &[u8]) -> Result<bool, String> {
        let what = format!("snapshot delta {number}");
        let (d, format, swatches): (Delta, Rows, Option<Swatches>) = match bytes.get(..2) {
            Some(m) if m == DELTA_V1 => (decode_as(DELTA_V1, bytes, &what)?, Rows::Raw, None),
            Some(m) if m == DELTA_V2 => (decode_as(DELTA_V2, bytes, &what)?, Rows::Coded, None),
            _ => {
                let (d, swatches) = decode_as(DELTA_MAGIC, bytes, &what)?;
                (d, Rows::Coded, Some(swatches))
            }
        };
        if self.base == 0
            || d.base != self.base
            || d.number != number
            || d.seq < self.seq
            || d.pos < self.pos
        {
            return Ok(false);
        }
        self.map.set_sequence(d.seq);
        if let Some(swatches) = swatches {
            self.map.set_swatches(swatches);
        }
        put_rows(&mut self.map, &d.bricks, format).map_err(|e| format!("{what}: {e}"))?;
        let total: u64 = self.map.cell_dims().iter().map(|&c| u64::from(c)).product();
        for &cell in &d.emptied {
            if u64::from(cell) >= total {
                return Err(format!("{what}: cell {cell} is outside the scene"));
            }
            self.map.remove_brick(self.map.cell_coords(cell));
        }
        self.rows = index(&d.undo.history);
        self.steps.extend(d.undo.steps);
        let rows = &self.rows;
        self.steps.retain(|id, _| rows.contains_key(id));
        self.last_step_id = d.undo.last_step_id;
        self.answered = d.undo.answered;
        self.seq = d.seq;
        self.pos = d.pos;
        self.deltas = number;
        Ok(true)
    }
}

/// A scene's head; `None` for a scene written before heads existed.
pub async fn head(jet: &impl Jet, scene: &str) -> Result<Option<(Head, u64)>, PortError> {
    let Some(entry) = jet.kv_get(Bucket::Heads, scene).await? else {
        return Ok(None);
    };
    match serde_json::from_slice::<Head>(&entry.value) {
        Ok(head) => Ok(Some((head, entry.revision))),
        Err(e) => Err(PortError::Refused(format!(
            "the snapshot head of {scene} does not decode: {e}"
        ))),
    }
}

/// How reading `scene`'s snapshot fails: NATS does not answer, or what it holds is corrupt.
fn read_errors(
    scene: &str,
) -> (
    impl Fn(PortError) -> LogError + Copy + '_,
    impl Fn(String) -> StoreError + Copy + '_,
) {
    let unavailable = move |e: PortError| LogError::Unavailable {
        scene: scene.into(),
        detail: format!("reading its snapshot: {e}"),
    };
    let corrupt = move |detail: String| StoreError::Corrupt {
        scene: scene.into(),
        detail,
    };
    (unavailable, corrupt)
}

/// The scene as its newest snapshot holds it.
pub async fn read(jet: &impl Jet, scene: &str) -> Result<Restored, LogError> {
    let (unavailable, corrupt) = read_errors(scene);
    let head = head(jet, scene).await.map_err(unavailable)?;
    let Some((head, _)) = head else {
        return read_legacy(jet, scene).await;
    };
    if !(1..=HEAD_VERSION).contains(&head.version) {
        return Err(corrupt(format!(
            "its snapshot head has format {} (this brickcast reads {HEAD_VERSION}): upgrade every node",
            head.version
        ))
        .into());
    }
    // A chain replaced (and deleted) while it is read: the load reads again.
    let gone = |name: &str| LogError::Unavailable {
        scene: scene.into(),
        detail: format!("snapshot object {name} is gone (a newer snapshot replaced it)"),
    };
    let name = base_name(scene, head.base);
    let bytes = jet
        .object_get(&name)
        .await
        .map_err(unavailable)?
        .ok_or_else(|| gone(&name))?;
    let mut restored = Restored::from_base(&bytes).map_err(corrupt)?;
    drop(bytes);
    for n in 1..=head.deltas {
        let name = delta_name(scene, head.base, n);
        let bytes = jet
            .object_get(&name)
            .await
            .map_err(unavailable)?
            .ok_or_else(|| gone(&name))?;
        if !restored.apply_delta(n, &bytes).map_err(corrupt)? {
            return Err(corrupt(format!("snapshot delta {name} does not follow its base")).into());
        }
    }
    if (restored.seq, restored.pos) != (head.seq, head.pos) {
        return Err(corrupt(format!(
            "its snapshot is at sequence {} (log message {}) but its head says {} ({})",
            restored.seq, restored.pos, head.seq, head.pos
        ))
        .into());
    }
    restored.map.prune_tombstones(restored.seq);
    Ok(restored)
}

/// A scene written before heads existed: the base `<scene>`, then each delta `<scene>+N`
/// that names that base and follows on.
async fn read_legacy(jet: &impl Jet, scene: &str) -> Result<Restored, LogError> {
    let (unavailable, corrupt) = read_errors(scene);
    let Some(bytes) = jet.object_get(scene).await.map_err(unavailable)? else {
        return Err(StoreError::UnknownScene(scene.into()).into());
    };
    let mut restored = Restored::from_base(&bytes).map_err(corrupt)?;
    drop(bytes);
    for n in 1..=MAX_DELTAS {
        let Some(bytes) = jet
            .object_get(&legacy_delta_name(scene, n))
            .await
            .map_err(unavailable)?
        else {
            break;
        };
        if !restored.apply_delta(n, &bytes).map_err(corrupt)? {
            break;
        }
    }
    restored.map.prune_tombstones(restored.seq);
    Ok(restored)
}

/// What storing a snapshot came to.
#[derive(Debug, PartialEq)]
pub enum Stored {
    /// The head names it now (it named `before`).
    Moved { before: Option<Head> },
    /// The head had moved past it (a newer snapshot, another chain): it counts for nothing,
    /// and its object is gone again.
    Stale { head: Head },
}

/// Stores an encoded snapshot: its object, then the head moved to it (compare-and-set, only
/// forward). Only a snapshot the head names may trim the log.
pub async fn store(jet: &impl Jet, encoded: &Encoded) -> Result<Stored, PortError> {
    jet.object_put(&encoded.name, &encoded.description, encoded.bytes.clone())
        .await?;
    let next = encoded.head();
    let value = bytes::Bytes::from(
        serde_json::to_vec(&next).map_err(|e| PortError::Refused(e.to_string()))?,
    );
    for _ in 0..8 {
        let moved = match head(jet, &encoded.scene).await? {
            Some((head, _)) if !head.may_move_to(&next) => {
                let _ = jet.object_delete(&encoded.name).await;
                return Ok(Stored::Stale { head });
            }
            Some((head, revision)) => jet
                .kv_update(Bucket::Heads, &encoded.scene, value.clone(), revision)
                .await
                .map(|_| Some(head)),
            None => jet
                .kv_create(Bucket::Heads, &encoded.scene, value.clone())
                .await
                .map(|_| None),
        };
        match moved {
            Ok(before) => return Ok(Stored::Moved { before }),
            // Another snapshot moved the head meanwhile: look again.
            Err(PortError::Conflict(_)) => continue,
            Err(e) => return Err(e),
        }
    }
    Err(PortError::Unavailable(
        "the snapshot head kept moving".into(),
    ))
}

/// Deletes a chain's objects: its base and deltas `1..=deltas` (after a new base, or with the
/// scene). Best effort: leftovers are never read.
pub async fn delete_chain(jet: &impl Jet, scene: &str, base: u64, deltas: u32) {
    for n in (1..=deltas).rev() {
        let _ = jet.object_delete(&delta_name(scene, base, n)).await;
    }
    let _ = jet.object_delete(&base_name(scene, base)).await;
}

/// Deletes a scene's snapshots: its head's chain and a chain written before heads existed.
pub async fn delete_all(jet: &impl Jet, scene: &str) {
    if let Ok(Some((head, _))) = head(jet, scene).await {
        delete_chain(jet, scene, head.base, head.deltas).await;
    }
    let _ = jet.kv_delete(Bucket::Heads, scene, None).await;
    let _ = jet.object_delete(scene).await;
    for n in 1..=MAX_DELTAS + 1 {
        if jet
            .object_delete(&legacy_delta_name(scene, n))
            .await
            .is_err()
        {
            break;
        }
    }
}

/// The newest snapshot's scene sequence, stream position and deltas (`cluster status`, and
/// a load telling whether the snapshot moved while it read).
pub async fn newest(jet: &impl Jet, scene: &str) -> Option<(u64, u64, u32)> {
    match head(jet, scene).await {
        Ok(Some((head, _))) => return Some((head.seq, head.pos, head.deltas)),
        Ok(None) => {}
        Err(_) => return None,
    }
    let base = jet.object_description(scene).await.ok()??;
    let described = |d: &str, key: &str| {
        d.split_whitespace()
            .find_map(|p| p.strip_prefix(key))
            .and_then(|v| v.parse::<u64>().ok())
    };
    let (mut seq, mut pos) = (described(&base, "seq=")?, described(&base, "pos=")?);
    let id = described(&base, "id=");
    let mut deltas = 0;
    for n in 1..=MAX_DELTAS {
        let Ok(Some(d)) = jet.object_description(&legacy_delta_name(scene, n)).await else {
            break;
        };
        let follows = id.is_some() && described(&d, "base=") == id;
        match (follows, described(&d, "seq="), described(&d, "pos=")) {
            (true, Some(s), Some(p)) if s >= seq && p >= pos => {
                (seq, pos, deltas) = (s, p, n);
            }
            _ => break,
        }
    }
    Some((seq, pos, deltas))
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::{BrushMode, Colour};

    fn scene() -> BrickMap {
        let mut map = BrickMap::new([64, 32, 64]).unwrap();
        map.fill_box(
            [0, 0, 0],
            [63, 3, 63],
            BrushMode::Fill,
            Colour::from_rgb8(90, 120, 60),
        );
        map.set_sequence(5);
        map
    }

    fn chain_of(p: Prepared, scene: &str, chain: Option<Chain>) -> (Encoded, Chain) {
        let e = p.encode(scene, chain).unwrap();
        let c = e.chain.clone();
        (e, c)
    }

    #[test]
    fn a_base_and_its_deltas_give_the_scene_back() {
        let history = History::new(Vec::new(), 0, 1, 0);
        let mut map = scene();
        map.set_swatch(3, Colour(0x1234));
        let cells: Vec<u32> = Vec::new();
        let base = prepare(
            None,
            &map,
            &cells,
            5,
            10,
            &history,
            &HashMap::new(),
            Vec::new(),
        );
        let (base, chain) = chain_of(base, "s", None);
        assert!(base.is_base);
        assert!(base.name.starts_with("s@"), "{}", base.name);

        // Change some bricks: a new one, an emptied one, a changed one.
        map.record_touched(true);
        map.set_sequence(6);
        map.sphere(
            [40.0, 20.0, 40.0],
            5.0,
            BrushMode::Fill,
            Colour::from_rgb8(200, 10, 10),
        );
        map.set_sequence(7);
        map.fill_box([0, 0, 0], [7, 3, 7], BrushMode::Erase, Colour::WHITE);
        map.set_swatch(31, Colour(0x4321));
        let changed = map.take_touched();
        map.record_touched(false);
        assert!(!changed.is_empty());
        let delta = prepare(
            Some(&chain),
            &map,
            &changed,
            7,
            12,
            &history,
            &HashMap::new(),
            Vec::new(),
        );
        let (delta, chain2) = chain_of(delta, "s", Some(chain.clone()));
        assert!(!delta.is_base);
        assert_eq!(delta.name, format!("{}+1", base.name));
        // Only the changed bricks (the base's one-colour rows are as small as a delta's now).
        let (d, _): (Delta, Swatches) = decode_as(DELTA_MAGIC, &delta.bytes, "delta").unwrap();
        assert_eq!(d.bricks.cells.len() + d.emptied.len(), changed.len());
        assert!((d.bricks.cells.len() as u64) < map.brick_count());
        assert_eq!(chain2.next, 2);

        let mut restored = Restored::from_base(&base.bytes).unwrap();
        assert_ne!(restored.map.content_hash(), map.content_hash());
        // The palette goes with each snapshot: the base's, then the delta's.
        assert_eq!(restored.map.swatches().get(3), Colour(0x1234));
        assert_ne!(restored.map.swatches(), map.swatches());
        assert!(restored.apply_delta(1, &delta.bytes).unwrap());
        assert_eq!(restored.map.content_hash(), map.content_hash());
        assert_eq!(restored.map.swatches(), map.swatches());
        assert_eq!((restored.seq, restored.pos, restored.deltas), (7, 12, 1));

        // A delta of another chain, or out of place, is not applied.
        let other = Restored::from_base(&base.bytes).unwrap();
        let mut again = other;
        assert!(!again.apply_delta(2, &delta.bytes).unwrap());
        let foreign = prepare(
            None,
            &map,
            &[],
            7,
            12,
            &history,
            &HashMap::new(),
            Vec::new(),
        );
        let (foreign, _) = chain_of(foreign, "s", None);
        let mut from_foreign = Restored::from_base(&foreign.bytes).unwrap();
        assert!(!from_foreign.apply_delta(1, &delta.bytes).unwrap());
        // Garbage is an error, not a silent stop.
        assert!(again.apply_delta(1, b"Dx not a delta").is_err());
        assert!(Restored::from_base(b"nothing").is_err());
    }

    /// A base written before deltas existed: the flat layout of that release, magic `S1`.
    #[test]
    fn bases_from_before_deltas_still_load() {
        #[derive(Serialize)]
        struct OldSnapshotBody {
            size: [u32; 3],
            seq: u64,
            pos: u64,
            history: Vec<(UserId, u64, StepMeta)>,
            steps: Vec<(u64, Vec<u8>)>,
            last_step_id: u64,
            answered: Vec<AnsweredEntry>,
            cells: Vec<u32>,
            rows: Vec<u8>,
        }
        let map = scene();
        let bricks = raw_rows(&map);
        let old = OldSnapshotBody {
            size: map.size(),
            seq: 5,
            pos: 7,
            history: Vec::new(),
            steps: vec![(3, vec![1, 2, 3])],
            last_step_id: 3,
            answered: Vec::new(),
            cells: bricks.cells,
            rows: bricks.rows,
        };
        let bytes = encode_as(BASE_V1, &old).unwrap();
        let restored = Restored::from_base(&bytes).unwrap();
        assert_eq!(restored.map.content_hash(), map.content_hash());
        assert_eq!(
            (restored.seq, restored.pos, restored.last_step_id),
            (5, 7, 3)
        );
        assert_eq!(restored.steps.get(&3), Some(&vec![1, 2, 3]));
        assert_eq!(restored.base, 0, "no delta follows an old base");
    }

    /// Every brick of `map` as raw rows, as snapshots before coded rows held them.
    fn raw_rows(map: &BrickMap) -> Bricks {
        let (mut cells, mut rows, mut row) = (Vec::new(), Vec::new(), Vec::new());
        for (b, _) in map.bricks() {
            crate::store::encode_brick(&b.mask, &b.colours, &mut row);
            rows.extend_from_slice(&row);
            cells.push(map.cell_index(b.cell));
        }
        Bricks { cells, rows }
    }

    /// A chain written before coded rows (`S2` base, `D1` delta) still loads, and a new
    /// delta (coded) can follow it.
    #[test]
    fn chains_of_raw_rows_still_load() {
        let history = History::new(Vec::new(), 0, 1, 0);
        let mut map = scene();
        // Many colours in one brick, so the coded rows are not all one colour.
        for x in 0..8 {
            map.set([x, 10, 0], Colour::from_rgb8(10 * x as u8, 7, 99));
        }
        let old_base = Base {
            id: 77,
            whole: Whole {
                size: map.size(),
                seq: 5,
                pos: 9,
                undo: Undo {
                    history: Vec::new(),
                    steps: Vec::new(),
                    last_step_id: 0,
                    answered: Vec::new(),
                },
                bricks: raw_rows(&map),
            },
        };
        let before = map.content_hash();
        map.sphere(
            [20.0, 20.0, 20.0],
            4.0,
            BrushMode::Fill,
            Colour::from_rgb8(1, 2, 3),
        );
        let mut changed_map = BrickMap::new(map.size()).unwrap();
        for (b, _) in map.bricks().filter(|(b, _)| b.cell[1] >= 2) {
            changed_map.put_brick(&b).unwrap();
        }
        let old_delta = Delta {
            base: 77,
            number: 1,
            seq: 6,
            pos: 11,
            undo: Undo {
                history: Vec::new(),
                steps: Vec::new(),
                last_step_id: 0,
                answered: Vec::new(),
            },
            bricks: raw_rows(&changed_map),
            emptied: Vec::new(),
        };
        let mut restored = Restored::from_base(&encode_as(BASE_V2, &old_base).unwrap()).unwrap();
        assert_eq!(restored.map.content_hash(), before);
        assert!(
            restored
                .apply_delta(1, &encode_as(DELTA_V1, &old_delta).unwrap())
                .unwrap()
        );
        assert_eq!(restored.map.content_hash(), map.content_hash());
        // The next snapshot on that chain is a coded delta.
        let chain = Chain {
            base: 77,
            base_bytes: 1 << 20,
            next: 2,
            delta_bytes: 0,
            last_step_id: 0,
        };
        map.set([1, 20, 1], Colour::from_rgb8(50, 60, 70));
        let cell = map.cell_index([0, 2, 0]);
        let delta = prepare(
            Some(&chain),
            &map,
            &[cell],
            7,
            12,
            &history,
            &HashMap::new(),
            Vec::new(),
        );
        let (delta, _) = chain_of(delta, "s", Some(chain));
        assert_eq!(delta.bytes.get(..2), Some(&DELTA_MAGIC[..]));
        assert!(restored.apply_delta(2, &delta.bytes).unwrap());
        assert_eq!(restored.map.content_hash(), map.content_hash());
    }

    /// A chain written before palettes (`S3` base, `D2` delta: coded rows) still loads, with
    /// the default palette.
    #[test]
    fn chains_from_before_palettes_still_load() {
        let mut map = scene();
        let undo = || Undo {
            history: Vec::new(),
            steps: Vec::new(),
            last_step_id: 0,
            answered: Vec::new(),
        };
        let every = map.bricks().map(|(b, _)| map.cell_index(b.cell));
        let (bricks, _) = rows_of(&map, every);
        let old_base = Base {
            id: 78,
            whole: Whole {
                size: map.size(),
                seq: 5,
                pos: 9,
                undo: undo(),
                bricks,
            },
        };
        map.set([1, 20, 1], Colour::from_rgb8(50, 60, 70));
        let cell = map.cell_index([0, 2, 0]);
        let (bricks, emptied) = rows_of(&map, [cell].into_iter());
        let old_delta = Delta {
            base: 78,
            number: 1,
            seq: 6,
            pos: 11,
            undo: undo(),
            bricks,
            emptied,
        };
        let mut restored = Restored::from_base(&encode_as(BASE_V3, &old_base).unwrap()).unwrap();
        assert!(
            restored
                .apply_delta(1, &encode_as(DELTA_V2, &old_delta).unwrap())
                .unwrap()
        );
        assert_eq!(restored.map.content_hash(), map.content_hash());
        assert_eq!(restored.map.swatches(), &Swatches::default());
    }

    /// A coded row whose block does not decode is an error naming the brick, not a panic.
    #[test]
    fn a_coded_row_that_does_not_decode_is_an_error() {
        let map = scene();
        let every = map.bricks().map(|(b, _)| map.cell_index(b.cell));
        let (bricks, _) = rows_of(&map, every);
        // Turn the first row's block header (one colour) into a palette of 2 entries whose
        // indices then run into the next row; or cut the rows short; or name no coding.
        for bad in [0x11u16, 0x7] {
            let mut rows = bricks.rows.clone();
            rows[64..66].copy_from_slice(&bad.to_le_bytes());
            let broken = Bricks {
                cells: bricks.cells.clone(),
                rows,
            };
            let mut fresh = BrickMap::new(map.size()).unwrap();
            assert!(put_rows(&mut fresh, &broken, Rows::Coded).is_err());
        }
        let cut = Bricks {
            cells: bricks.cells.clone(),
            rows: bricks.rows[..bricks.rows.len() - 1].to_vec(),
        };
        let mut fresh = BrickMap::new(map.size()).unwrap();
        assert!(put_rows(&mut fresh, &cut, Rows::Coded).is_err());
        let mut fresh = BrickMap::new(map.size()).unwrap();
        put_rows(&mut fresh, &bricks, Rows::Coded).unwrap();
        assert_eq!(fresh.content_hash(), map.content_hash());
    }

    #[test]
    fn the_head_moves_only_forward_and_deltas_only_on_its_chain() {
        let head = Head {
            version: HEAD_VERSION,
            base: 7,
            deltas: 2,
            seq: 50,
            pos: 40,
        };
        let next = |base, deltas, seq, pos| Head {
            version: HEAD_VERSION,
            base,
            deltas,
            seq,
            pos,
        };
        assert!(head.may_move_to(&next(7, 3, 55, 45)), "the next delta");
        assert!(head.may_move_to(&next(9, 0, 55, 45)), "a new base");
        assert!(!head.may_move_to(&next(7, 3, 50, 40)), "not further on");
        assert!(
            !head.may_move_to(&next(7, 2, 60, 41)),
            "a delta the chain has"
        );
        assert!(
            !head.may_move_to(&next(8, 3, 60, 41)),
            "a delta of another chain"
        );
        assert!(!head.may_move_to(&next(9, 0, 45, 39)), "a late base");
    }

    #[test]
    fn a_new_base_when_deltas_grow_or_most_bricks_changed() {
        let chain = Chain {
            base: 9,
            base_bytes: 1000,
            next: 3,
            delta_bytes: 100,
            last_step_id: 0,
        };
        assert!(delta_fits(&chain, 10, 100));
        assert!(!delta_fits(&chain, 30, 100), "most bricks changed");
        let big = Chain {
            delta_bytes: 500,
            ..chain.clone()
        };
        assert!(
            !delta_fits(&big, 1, 100),
            "the deltas add up to half the base"
        );
        let long = Chain {
            next: MAX_DELTAS + 1,
            ..chain
        };
        assert!(!delta_fits(&long, 1, 100), "too many deltas");
    }

    #[test]
    fn a_delta_is_refused_on_a_chain_that_moved() {
        let history = History::new(Vec::new(), 0, 1, 0);
        let map = scene();
        let chain = Chain {
            base: 9,
            base_bytes: 1 << 20,
            next: 2,
            delta_bytes: 0,
            last_step_id: 0,
        };
        let p = prepare(
            Some(&chain),
            &map,
            &[0],
            5,
            10,
            &history,
            &HashMap::new(),
            Vec::new(),
        );
        let moved = Chain {
            next: 3,
            ..chain.clone()
        };
        assert!(p.encode("s", Some(moved)).is_err());
    }
}
