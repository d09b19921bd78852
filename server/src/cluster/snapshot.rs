//! A scene's snapshots in the cluster: a whole **base** and a chain of **deltas** after it, in
//! the object store `brickcast_snapshots`.
//!
//! **Why deltas:** a snapshot lets a node opening the scene skip most of the log, and lets the
//! owner trim the log. A whole scene is big (the 1024³ demo scene: 31 ms to copy on the owner
//! thread, 104 ms to encode, and the upload, kept three times over with `--replicas 3`), while
//! what changed since the last snapshot is usually a few bricks. So the owner writes a base
//! (object `<scene>`: every brick) and then deltas (`<scene>+1`, `+2`, …: the bricks changed
//! since the previous snapshot, the cells emptied, the whole undo index and answered requests,
//! and the step bodies added since), each one trimming the log below it. A new base replaces
//! the chain when the deltas add up to half the base, after [`MAX_DELTAS`], when most bricks
//! changed, or when the owner cannot vouch for what changed since the last snapshot: it just
//! took the scene over, or an upload failed (the changed-brick set it handed over is gone).
//! `+` cannot occur in a scene name, so one scene's objects never collide with another's.
//!
//! **Reading:** the base, then `+1`, `+2`, … while each names that base (its random id) and
//! follows on (sequence and stream position never go back); the first that does not ends the
//! chain, so leftovers of an older chain are ignored. A chain replaced while it was being read
//! shows up as a gap between the snapshot and the log: `log::load` then reads again.

use std::collections::{BTreeMap, HashMap};
use std::hash::{BuildHasher, Hasher};

use brickcast_protocol::BrickMap;
use brickcast_protocol::brick::BrickData;
use brickcast_protocol::wire::UserId;
use serde::{Deserialize, Serialize};

use super::jet::{Jet, PortError};
use super::log::{decode_as, encode_as};
use crate::scene::AnsweredEntry;
use crate::scene::LogError;
use crate::scene::history::{History, StepMeta};
use crate::store::{StoreError, decode_brick, encode_brick};

/// First bytes of a base written before deltas existed (no id: no delta follows it).
const BASE_V1: [u8; 2] = [b'S', 1];
/// First bytes of a base.
const BASE_MAGIC: [u8; 2] = [b'S', 2];
/// First bytes of a delta.
const DELTA_MAGIC: [u8; 2] = [b'D', 1];
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

/// Linear cells, and their bricks as the redb store's rows, back to back (a row's length
/// follows from its mask).
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
    base: u64,
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
    pub name: String,
    pub description: String,
    pub bytes: bytes::Bytes,
    pub seq: u64,
    pub pos: u64,
    /// What the chain looks like once it is stored.
    pub chain: Chain,
    pub is_base: bool,
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

/// The name of a scene's delta `n`.
pub fn delta_name(scene: &str, n: u32) -> String {
    format!("{scene}+{n}")
}

/// Whether the next snapshot can be a delta on `chain`, with `changed` of `bricks` bricks
/// changed since the last one.
fn delta_fits(chain: &Chain, changed: usize, bricks: u64) -> bool {
    chain.next <= MAX_DELTAS
        && chain.delta_bytes.saturating_mul(2) < chain.base_bytes
        && (changed as u64).saturating_mul(4) <= bricks.max(1)
}

/// Bricks at `cells` (linear indices) as rows, back to back; the cells holding none apart.
fn rows_of(map: &BrickMap, cells: impl Iterator<Item = u32>) -> (Bricks, Vec<u32>) {
    let (mut solid, mut rows, mut empty, mut row) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for cell in cells {
        match map.brick(map.cell_coords(cell)) {
            Some(b) => {
                encode_brick(&b.mask, &b.colours, &mut row);
                rows.extend_from_slice(&row);
                solid.push(cell);
            }
            None => empty.push(cell),
        }
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
                let bytes = bytes::Bytes::from(encode_as(BASE_MAGIC, &base)?);
                Ok(Encoded {
                    name: scene.to_string(),
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
                let bytes = bytes::Bytes::from(encode_as(DELTA_MAGIC, &delta)?);
                let before = chain
                    .filter(|c| c.base == delta.base && c.next == delta.number)
                    .ok_or("the delta does not follow the chain it was encoded with")?;
                Ok(Encoded {
                    name: delta_name(scene, delta.number),
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

/// Puts `bricks` into `map` (checked: a corrupt object is an error).
fn put_rows(map: &mut BrickMap, bricks: &Bricks) -> Result<(), String> {
    let (cells, rows) = (&bricks.cells, &bricks.rows);
    let total: u64 = map.cell_dims().iter().map(|&d| u64::from(d)).product();
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
        let end = mask_end + 2 * solid;
        let row = rows
            .get(at..end)
            .ok_or_else(|| format!("brick {cell} is cut short"))?;
        let brick: BrickData = decode_brick(map.cell_coords(cell), row)
            .ok_or_else(|| format!("brick {cell} does not decode"))?;
        map.put_brick(&brick).map_err(|e| e.to_string())?;
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
        let base = if bytes.get(..2) == Some(&BASE_V1[..]) {
            Base {
                id: 0,
                whole: decode_as(BASE_V1, bytes, "snapshot")?,
            }
        } else {
            decode_as::<Base>(BASE_MAGIC, bytes, "snapshot")?
        };
        let w = base.whole;
        let mut map = BrickMap::new(w.size).map_err(|e| e.to_string())?;
        map.set_sequence(w.seq);
        put_rows(&mut map, &w.bricks).map_err(|e| format!("snapshot: {e}"))?;
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
        let d: Delta = decode_as(DELTA_MAGIC, bytes, &what)?;
        if self.base == 0
            || d.base != self.base
            || d.number != number
            || d.seq < self.seq
            || d.pos < self.pos
        {
            return Ok(false);
        }
        self.map.set_sequence(d.seq);
        put_rows(&mut self.map, &d.bricks).map_err(|e| format!("{what}: {e}"))?;
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

/// The scene as its base and deltas hold it.
pub async fn read(jet: &impl Jet, scene: &str) -> Result<Restored, LogError> {
    let unavailable = |e: PortError| LogError::Unavailable {
        scene: scene.into(),
        detail: format!("reading its snapshot: {e}"),
    };
    let corrupt = |detail: String| StoreError::Corrupt {
        scene: scene.into(),
        detail,
    };
    let Some(bytes) = jet.object_get(scene).await.map_err(unavailable)? else {
        return Err(StoreError::UnknownScene(scene.into()).into());
    };
    let mut restored = Restored::from_base(&bytes).map_err(corrupt)?;
    drop(bytes);
    for n in 1..=MAX_DELTAS {
        let Some(bytes) = jet
            .object_get(&delta_name(scene, n))
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

/// Stores an encoded snapshot.
pub async fn put(jet: &impl Jet, encoded: &Encoded) -> Result<(), PortError> {
    jet.object_put(&encoded.name, &encoded.description, encoded.bytes.clone())
        .await
}

/// Deletes a scene's deltas (after a new base, or with the scene), up to the first missing.
pub async fn delete_deltas(jet: &impl Jet, scene: &str) {
    for n in 1..=MAX_DELTAS + 1 {
        if jet.object_delete(&delta_name(scene, n)).await.is_err() {
            return;
        }
    }
}

/// The newest snapshot's scene sequence, stream position and deltas, from object
/// descriptions alone (`cluster status`).
pub async fn newest(jet: &impl Jet, scene: &str) -> Option<(u64, u64, u32)> {
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
        let Ok(Some(d)) = jet.object_description(&delta_name(scene, n)).await else {
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
        assert_eq!(base.name, "s");

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
        assert_eq!(delta.name, "s+1");
        assert!(delta.bytes.len() < base.bytes.len());
        assert_eq!(chain2.next, 2);

        let mut restored = Restored::from_base(&base.bytes).unwrap();
        assert_ne!(restored.map.content_hash(), map.content_hash());
        assert!(restored.apply_delta(1, &delta.bytes).unwrap());
        assert_eq!(restored.map.content_hash(), map.content_hash());
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
        let every = map.bricks().map(|(b, _)| map.cell_index(b.cell));
        let (bricks, _) = rows_of(&map, every);
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
