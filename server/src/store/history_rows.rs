//! How the store keeps a scene's undo history (store format 3, issue #31).
//!
//! **Why not a row per step.** Every edit message is one undo step, and a full stack drops its
//! oldest step as a new one comes: with a row for each step's body and one for its index entry,
//! a turn of a thousand one-voxel messages wrote and deleted four thousand redb rows, which cost
//! more than applying the edits. Now a turn writes at most three rows, whatever it holds:
//!
//! - `steps/<scene>`: the bodies of the turn's new steps as one **pack**, keyed by its first
//!   step id (ids grow with every push, so a pack is a range of ids); `packs/<scene>`: first id
//!   → last id, the packs' ranges without their bodies. A pack is deleted in the turn that drops
//!   its last live step: the store counts each pack's live steps ([`PackState`], built from the
//!   tables the first time a scene appends, so it is never persisted and cannot disagree).
//! - `undolog/<scene>`: the turn's **index change** (steps added with their user and stack,
//!   steps dropped). The per-step index rows `undo/<scene>` ((user, id) → stack and size, the
//!   layout before format 3) are brought up to date from it once the changes hold
//!   [`FOLD_AT`] entries, or eight times the rows a fold would write ([`fold`], in that turn's
//!   transaction). A fold writes only what is still different, kept in memory as the changes
//!   are written (`PackState::net`): most steps are pushed and dropped between two folds and
//!   never get an index row, and a fold costs the rows it writes, not the changes it ends.
//!   Loading a scene reads the index rows, then the changes after them, in order.
//!
//! Stores before format 3 hold one row per step body in `history/<scene>` (keyed by id); those
//! read as before and are deleted as their steps are dropped, so an old store needs no upgrade
//! pass.

use std::collections::BTreeMap;

use rustc_hash::FxHashMap;

use brickcast_protocol::wire::UserId;
use redb::{ReadTransaction, ReadableTable, TableDefinition, WriteTransaction};
use serde::{Deserialize, Serialize};

use super::{StoreError, UndoIndex, history_table, open_optional, undo_table};
use crate::scene::history::{HistoryWrites, StepMeta};

/// `steps/<scene>`: first step id → a pack of step bodies.
pub(super) fn steps_table(name: &str) -> String {
    format!("steps/{name}")
}
/// `packs/<scene>`: first step id → last step id of each pack.
pub(super) fn packs_table(name: &str) -> String {
    format!("packs/{name}")
}
/// `undolog/<scene>`: change number → an [`IndexChange`].
pub(super) fn journal_table(name: &str) -> String {
    format!("undolog/{name}")
}

type Bodies<'a> = TableDefinition<'a, u64, &'static [u8]>;
type Ranges<'a> = TableDefinition<'a, u64, u64>;

/// What one turn changed in the index.
#[derive(Debug, Default, Serialize, Deserialize)]
struct IndexChange {
    added: Vec<(UserId, u64, StepMeta)>,
    removed: Vec<(UserId, u64)>,
}

/// Entries (steps added or dropped) in the index changes past which an append folds them into
/// the index rows, at the least: what loading a scene may have to replay (about 50 ms).
pub(super) const FOLD_AT: u64 = 1 << 18;

/// A pack's first bytes.
const PACK_MAGIC: [u8; 2] = [b'P', 1];

/// The bodies of a turn's new steps as one row: the magic, the count (u32 LE), then per step
/// its id (u64 LE) and length (u32 LE), then the bodies in that order.
fn encode_pack(steps: &BTreeMap<u64, (UserId, StepMeta, Vec<u8>)>) -> Vec<u8> {
    let bodies: usize = steps.values().map(|(_, _, b)| b.len()).sum();
    let mut out = Vec::with_capacity(6 + 12 * steps.len() + bodies);
    out.extend_from_slice(&PACK_MAGIC);
    out.extend_from_slice(&(steps.len() as u32).to_le_bytes());
    for (id, (_, _, body)) in steps {
        out.extend_from_slice(&id.to_le_bytes());
        out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    }
    for (_, _, body) in steps.values() {
        out.extend_from_slice(body);
    }
    out
}

/// The body of step `id` in a pack (`None`: the pack does not hold it).
fn pack_step(pack: &[u8], id: u64) -> Result<Option<&[u8]>, String> {
    let short = || "a history pack cut short".to_string();
    let [b'P', 1, a, b, c, d, rest @ ..] = pack else {
        return Err("not a history pack".into());
    };
    let count = u32::from_le_bytes([*a, *b, *c, *d]) as usize;
    let header = count.checked_mul(12).ok_or_else(short)?;
    if rest.len() < header {
        return Err(short());
    }
    let (entries, mut bodies) = rest.split_at(header);
    for entry in entries.chunks_exact(12) {
        let (this, len) = entry.split_at(8);
        let this = u64::from_le_bytes(this.try_into().map_err(|_| short())?);
        let len = u32::from_le_bytes(len.try_into().map_err(|_| short())?) as usize;
        if bodies.len() < len {
            return Err(short());
        }
        let (body, after) = bodies.split_at(len);
        if this == id {
            return Ok(Some(body));
        }
        bodies = after;
    }
    Ok(None)
}

/// Live steps of each pack, and where the next index change goes: what an append needs to
/// know to delete a pack with its last step.
#[derive(Clone, Debug, Default)]
pub(super) struct PackState {
    /// First id → (last id, live steps).
    live: BTreeMap<u64, (u64, u32)>,
    /// The highest id with a body in the pre-format-3 table (0: none).
    legacy_last: u64,
    next_change: u64,
    /// Entries in the index changes not folded yet.
    unfolded: u64,
    /// What folding them would write: per step, `Some` added (and live), `None` dropped.
    net: FxHashMap<(UserId, u64), Option<StepMeta>>,
}

impl PackState {
    /// Notes a change in [`PackState::net`].
    fn note(&mut self, change: &IndexChange) {
        for key in &change.removed {
            if let Some(Some(_)) = self.net.get(key) {
                // Added since the last fold: it never reaches the index.
                self.net.remove(key);
            } else {
                self.net.insert(*key, None);
            }
        }
        for (user, id, meta) in &change.added {
            self.net.insert((*user, *id), Some(*meta));
        }
        self.unfolded += (change.added.len() + change.removed.len()) as u64;
    }

    /// Whether the next append folds: the changes are long, or long against the fold's rows.
    fn fold_due(&self) -> bool {
        self.unfolded >= FOLD_AT.min(8 * self.net.len() as u64).max(FOLD_AT / 4)
    }
}

/// Every live step of a scene: the index rows, then the changes after them.
pub(super) fn live_index(
    txn: &ReadTransaction,
    scene: &str,
) -> Result<BTreeMap<(UserId, u64), StepMeta>, StoreError> {
    live_index_noting(txn, scene, |_| {})
}

/// [`live_index`], showing `each` every change after the index rows, in order.
fn live_index_noting(
    txn: &ReadTransaction,
    scene: &str,
    mut each: impl FnMut(&IndexChange),
) -> Result<BTreeMap<(UserId, u64), StepMeta>, StoreError> {
    let corrupt = |detail: String| StoreError::Corrupt {
        scene: scene.into(),
        detail,
    };
    let mut live = BTreeMap::new();
    if let Some(index) = open_optional::<(u64, u64), &[u8]>(txn, &undo_table(scene))? {
        for row in index.iter()? {
            let (key, bytes) = row?;
            let (user, id) = key.value();
            let (meta, _): (StepMeta, usize) = super::ROW
                .decode_prefix(bytes.value())
                .map_err(|e| corrupt(format!("undo step {id} of user {user}: {e}")))?;
            live.insert((user, id), meta);
        }
    }
    if let Some(journal) = open_optional::<u64, &[u8]>(txn, &journal_table(scene))? {
        for row in journal.iter()? {
            let (n, bytes) = row?;
            let change = decode_change(bytes.value())
                .map_err(|e| corrupt(format!("undo index change {}: {e}", n.value())))?;
            each(&change);
            for key in change.removed {
                live.remove(&key);
            }
            for (user, id, meta) in change.added {
                live.insert((user, id), meta);
            }
        }
    }
    Ok(live)
}

fn decode_change(bytes: &[u8]) -> Result<IndexChange, String> {
    super::ROW.decode_body(bytes).map_err(|e| e.to_string())
}

/// The highest step id the scene's tables name (0: none): ids are never given out twice while
/// a body could still be found under them.
pub(super) fn last_id(
    txn: &ReadTransaction,
    scene: &str,
    live: &BTreeMap<(UserId, u64), StepMeta>,
) -> Result<u64, StoreError> {
    let mut last = live.keys().map(|(_, id)| *id).max().unwrap_or(0);
    if let Some(packs) = open_optional::<u64, u64>(txn, &packs_table(scene))? {
        for row in packs.iter()? {
            last = last.max(row?.1.value());
        }
    }
    if let Some(legacy) = open_optional::<u64, &[u8]>(txn, &history_table(scene))?
        && let Some((id, _)) = legacy.last()?
    {
        last = last.max(id.value());
    }
    Ok(last)
}

/// The scene's packs and their live steps, read from its tables.
pub(super) fn pack_state(txn: &ReadTransaction, scene: &str) -> Result<PackState, StoreError> {
    let mut state = PackState::default();
    if let Some(packs) = open_optional::<u64, u64>(txn, &packs_table(scene))? {
        for row in packs.iter()? {
            let (first, last) = row?;
            state.live.insert(first.value(), (last.value(), 0));
        }
    }
    // The changes since the last fold are noted as the index is read: one pass over them.
    let live = live_index_noting(txn, scene, |change| state.note(change))?;
    for (_, id) in live.keys() {
        if let Some((_, (last, live))) = state.live.range_mut(..=*id).next_back()
            && *id <= *last
        {
            *live += 1;
        }
    }
    if let Some(legacy) = open_optional::<u64, &[u8]>(txn, &history_table(scene))?
        && let Some((id, _)) = legacy.last()?
    {
        state.legacy_last = id.value();
    }
    if let Some(journal) = open_optional::<u64, &[u8]>(txn, &journal_table(scene))?
        && let Some((n, _)) = journal.last()?
    {
        state.next_change = n.value() + 1;
    }
    Ok(state)
}

/// Writes a turn's history changes into `txn`, updating `state` (the caller keeps it only if
/// the transaction commits).
pub(super) fn write(
    txn: &WriteTransaction,
    scene: &str,
    state: &mut PackState,
    writes: &HistoryWrites,
) -> Result<(), StoreError> {
    if writes.is_empty() {
        return Ok(());
    }
    let mut steps = txn.open_table(Bodies::new(&steps_table(scene)))?;
    let mut packs = txn.open_table(Ranges::new(&packs_table(scene)))?;
    let mut change = IndexChange::default();
    // Drops first, against the packs of earlier turns only: a step pushed and dropped within
    // this turn was never written, and its id may lie inside this turn's pack.
    for (&id, &user) in &writes.removed {
        change.removed.push((user, id));
        if id <= state.legacy_last {
            let mut legacy = txn.open_table(Bodies::new(&history_table(scene)))?;
            legacy.remove(id)?;
            continue;
        }
        if let Some((&first, (last, live))) = state.live.range_mut(..=id).next_back()
            && id <= *last
        {
            *live = live.saturating_sub(1);
            if *live == 0 {
                state.live.remove(&first);
                steps.remove(first)?;
                packs.remove(first)?;
            }
        }
    }
    if let (Some(&first), Some(&last)) = (writes.steps.keys().next(), writes.steps.keys().last()) {
        steps.insert(first, encode_pack(&writes.steps).as_slice())?;
        packs.insert(first, last)?;
        state.live.insert(first, (last, writes.steps.len() as u32));
    }
    change.added = writes
        .steps
        .iter()
        .map(|(&id, (user, meta, _))| (*user, id, *meta))
        .collect();
    let bytes = super::ROW
        .encode(&change)
        .map_err(|e| StoreError::Corrupt {
            scene: scene.into(),
            detail: format!("undo index change: {e}"),
        })?;
    let mut journal = txn.open_table(Bodies::new(&journal_table(scene)))?;
    journal.insert(state.next_change, bytes.as_slice())?;
    drop(journal);
    state.next_change += 1;
    state.note(&change);
    if state.fold_due() {
        fold(txn, scene, state)?;
    }
    Ok(())
}

/// Brings the index rows up to date with the changes since the last fold (`state.net`) and
/// deletes those changes.
pub(super) fn fold(
    txn: &WriteTransaction,
    scene: &str,
    state: &mut PackState,
) -> Result<(), StoreError> {
    let mut index = txn.open_table(UndoIndex::new(&undo_table(scene)))?;
    let mut net: Vec<_> = state.net.drain().collect();
    net.sort_unstable_by_key(|(key, _)| *key);
    let mut buf = Vec::new();
    for (key, meta) in net {
        match meta {
            Some(meta) => {
                buf.clear();
                super::ROW
                    .encode_into(&meta, &mut buf)
                    .map_err(|e| StoreError::Corrupt {
                        scene: scene.into(),
                        detail: e.to_string(),
                    })?;
                index.insert(key, buf.as_slice())?;
            }
            None => {
                index.remove(key)?;
            }
        }
    }
    let mut journal = txn.open_table(Bodies::new(&journal_table(scene)))?;
    journal.retain(|_, _| false)?;
    state.unfolded = 0;
    Ok(())
}

/// The stored body of step `id`, from its pack or (stores before format 3) its own row.
pub(super) fn step(
    txn: &ReadTransaction,
    scene: &str,
    id: u64,
) -> Result<Option<Vec<u8>>, StoreError> {
    if let Some(steps) = open_optional::<u64, &[u8]>(txn, &steps_table(scene))?
        && let Some(row) = steps.range(..=id)?.next_back()
    {
        let (first, pack) = row?;
        let found = pack_step(pack.value(), id).map_err(|e| StoreError::Corrupt {
            scene: scene.into(),
            detail: format!("history pack {}: {e}", first.value()),
        })?;
        if let Some(body) = found {
            return Ok(Some(body.to_vec()));
        }
    }
    let Some(legacy) = open_optional::<u64, &[u8]>(txn, &history_table(scene))? else {
        return Ok(None);
    };
    Ok(legacy.get(id)?.map(|v| v.value().to_vec()))
}

/// Deletes every history table of a scene (the scene is deleted or written anew).
pub(super) fn delete_all(txn: &WriteTransaction, scene: &str) -> Result<(), StoreError> {
    txn.delete_table(Bodies::new(&history_table(scene)))?;
    txn.delete_table(UndoIndex::new(&undo_table(scene)))?;
    txn.delete_table(Bodies::new(&steps_table(scene)))?;
    txn.delete_table(Ranges::new(&packs_table(scene)))?;
    txn.delete_table(Bodies::new(&journal_table(scene)))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pack_finds_each_of_its_steps_and_refuses_a_cut_one() {
        let meta = StepMeta {
            redo: false,
            bytes: 3,
            bricks: 1,
        };
        let steps: BTreeMap<u64, (UserId, StepMeta, Vec<u8>)> = [
            (7, (1, meta, vec![1, 2, 3])),
            (9, (2, meta, vec![])),
            (10, (1, meta, vec![4; 300])),
        ]
        .into_iter()
        .collect();
        let pack = encode_pack(&steps);
        for (id, (_, _, body)) in &steps {
            assert_eq!(pack_step(&pack, *id).unwrap(), Some(&body[..]));
        }
        assert_eq!(pack_step(&pack, 8).unwrap(), None);
        assert!(pack_step(&pack[..pack.len() - 1], 10).is_err());
        assert!(pack_step(&pack[..20], 7).is_err());
        assert!(pack_step(b"xx", 7).is_err());
    }

    use crate::store::Store;
    use brickcast_protocol::BrickMap;
    use redb::ReadableDatabase;

    fn meta(bytes: u64) -> StepMeta {
        StepMeta {
            redo: false,
            bytes,
            bricks: 1,
        }
    }

    /// A turn's writes: steps `ids` of `user` pushed (bodies `[id; 3]`), `dropped` removed.
    fn turn(user: UserId, ids: &[u64], dropped: &[u64]) -> HistoryWrites {
        HistoryWrites {
            steps: ids
                .iter()
                .map(|&id| (id, (user, meta(3), vec![id as u8; 3])))
                .collect(),
            removed: dropped.iter().map(|&id| (id, user)).collect(),
        }
    }

    fn rows(store: &Store, table: &str) -> u64 {
        let txn = store.db.begin_read().unwrap();
        match open_optional::<u64, &[u8]>(&txn, table).unwrap() {
            Some(t) => t.iter().unwrap().count() as u64,
            None => 0,
        }
    }

    fn fold_now(store: &Store) {
        let mut state = pack_state(&store.db.begin_read().unwrap(), "s").unwrap();
        let txn = store.db.begin_write().unwrap();
        fold(&txn, "s", &mut state).unwrap();
        txn.commit().unwrap();
        store.forget_packs("s");
    }

    fn stacks(store: &Store) -> Vec<(UserId, Vec<u64>)> {
        let loaded = store.load_scene("s").unwrap();
        let mut out: Vec<(UserId, Vec<u64>)> = loaded
            .history
            .iter()
            .map(|(u, s)| (*u, s.undo.iter().map(|r| r.id).collect()))
            .collect();
        out.sort();
        out
    }

    #[test]
    fn a_turn_writes_one_pack_and_a_pack_goes_with_its_last_step() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let map = BrickMap::new([64, 64, 64]).unwrap();
        store.create_scene("s", &map).unwrap();
        // Two turns of three steps each; in the second, a step pushed and dropped in the same
        // turn (5: never written) lies inside the turn's own pack.
        store.append("s", &[], &turn(1, &[1, 2, 3], &[])).unwrap();
        store.append("s", &[], &turn(2, &[4, 6], &[5])).unwrap();
        assert_eq!(rows(&store, &steps_table("s")), 2);
        assert_eq!(rows(&store, &journal_table("s")), 2);
        assert_eq!(stacks(&store), vec![(1, vec![1, 2, 3]), (2, vec![4, 6])]);
        for id in [1, 2, 3, 4, 6] {
            assert_eq!(
                store.history_step("s", id).unwrap(),
                Some(vec![id as u8; 3])
            );
        }
        assert_eq!(store.history_step("s", 5).unwrap(), None);
        // Dropping two of the first pack's steps keeps it; the third deletes it.
        store.append("s", &[], &turn(1, &[], &[1, 3])).unwrap();
        assert_eq!(rows(&store, &steps_table("s")), 2);
        assert_eq!(store.history_step("s", 2).unwrap(), Some(vec![2; 3]));
        // The count of live steps is rebuilt from the tables by a store opened afresh.
        drop(store);
        let store = Store::open(dir.path()).unwrap();
        store.append("s", &[], &turn(1, &[7], &[2])).unwrap();
        assert_eq!(rows(&store, &steps_table("s")), 2);
        let txn = store.db.begin_read().unwrap();
        let ranges = txn.open_table(Ranges::new(&packs_table("s"))).unwrap();
        assert_eq!(ranges.iter().unwrap().count(), 2);
        drop((ranges, txn));
        assert_eq!(store.history_step("s", 2).unwrap(), None);
        assert_eq!(stacks(&store), vec![(1, vec![7]), (2, vec![4, 6])]);
        assert_eq!(store.load_scene("s").unwrap().last_step_id, 7);
        // A fold turns the changes into index rows: only the live steps get one.
        fold_now(&store);
        assert_eq!(rows(&store, &journal_table("s")), 0);
        let txn = store.db.begin_read().unwrap();
        let index = txn.open_table(UndoIndex::new(&undo_table("s"))).unwrap();
        let keys: Vec<(u64, u64)> = index
            .iter()
            .unwrap()
            .map(|r| r.unwrap().0.value())
            .collect();
        assert_eq!(keys, vec![(1, 7), (2, 4), (2, 6)]);
        drop((index, txn));
        assert_eq!(stacks(&store), vec![(1, vec![7]), (2, vec![4, 6])]);
        // Dropping a folded step after the fold: the change removes its index row next time.
        store.append("s", &[], &turn(2, &[8], &[4])).unwrap();
        assert_eq!(stacks(&store), vec![(1, vec![7]), (2, vec![6, 8])]);
        fold_now(&store);
        assert_eq!(stacks(&store), vec![(1, vec![7]), (2, vec![6, 8])]);
        // Appends fold by themselves once the changes are long enough.
        let (mut id, mut turns, mut before) = (9, 0, vec![]);
        while turns * 127 < FOLD_AT / 4 + 127 {
            let ids: Vec<u64> = (id..id + 64).collect();
            store
                .append("s", &[], &turn(3, &ids, &before[..before.len().min(63)]))
                .unwrap();
            before = ids;
            id += 64;
            turns += 1;
        }
        assert!(rows(&store, &journal_table("s")) < turns - 1);
        assert_eq!(stacks(&store)[..2], [(1, vec![7]), (2, vec![6, 8])]);
        assert_eq!(stacks(&store)[2].1.len() as u64, turns + 63);
        // Each of those turns' packs keeps one live step (the packs of 4 and 6, of 7, of 8
        // stay too); no live step lost its body.
        assert_eq!(rows(&store, &steps_table("s")), 3 + turns);
        for (_, ids) in stacks(&store) {
            for id in ids {
                assert!(store.history_step("s", id).unwrap().is_some(), "step {id}");
            }
        }
        assert!(store.delete_scene("s").unwrap());
        assert_eq!(rows(&store, &steps_table("s")), 0);
    }

    #[test]
    fn a_store_with_a_row_per_step_still_reads_and_drops_its_steps() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        store
            .create_scene("s", &BrickMap::new([64, 64, 64]).unwrap())
            .unwrap();
        // As format 2 wrote them: a body row and an index row per step.
        {
            let txn = store.db.begin_write().unwrap();
            {
                let mut bodies = txn.open_table(Bodies::new(&history_table("s"))).unwrap();
                let mut index = txn.open_table(UndoIndex::new(&undo_table("s"))).unwrap();
                for id in [3u64, 4] {
                    bodies.insert(id, [id as u8; 5].as_slice()).unwrap();
                    let m = super::super::ROW.encode(&meta(5)).unwrap();
                    index.insert((9, id), m.as_slice()).unwrap();
                }
            }
            txn.commit().unwrap();
        }
        assert_eq!(stacks(&store), vec![(9, vec![3, 4])]);
        assert_eq!(store.load_scene("s").unwrap().last_step_id, 4);
        assert_eq!(store.history_step("s", 3).unwrap(), Some(vec![3; 5]));
        // New steps go to packs beside them; dropping an old step deletes its own row.
        store.append("s", &[], &turn(9, &[5], &[3])).unwrap();
        assert_eq!(rows(&store, &history_table("s")), 1);
        assert_eq!(store.history_step("s", 3).unwrap(), None);
        assert_eq!(store.history_step("s", 4).unwrap(), Some(vec![4; 5]));
        assert_eq!(store.history_step("s", 5).unwrap(), Some(vec![5; 3]));
        assert_eq!(stacks(&store), vec![(9, vec![4, 5])]);
    }
}
