//! Per-user undo and redo: what each edit message changed, and how to take it back without
//! taking back anyone else's work.
//!
//! **Why here, in the owner's order.** An undo is an edit like any other: it must be applied
//! between the edits around it, logged, acknowledged after the commit and broadcast as a delta.
//! So the owner calls this module inside its turn, and the history's changes are written in the
//! same redb transaction as the log entries of that turn: an acknowledged edit's undo record is
//! as durable as the edit. Snapshots never trim history.
//!
//! **A step** is one edit message (one gesture: a click, a brush stroke), an undo or a redo: the
//! voxels it changed in each brick, before and after, from the map's journal (`step.rs`: its
//! columns, frames and stored form).
//! Undoing a step puts back, voxel by voxel, the before-value of every voxel the step changed,
//! *only where the voxel still holds the step's after-value*: a later change by anyone wins and
//! is counted as kept. The undo is itself recorded as a step, on the redo stack; redo undoes that
//! record the same way, and goes back on the undo stack. A new edit clears the redo stack.
//!
//! **Bounds.** Per user at most `Limits::max_undo_steps` steps and `Limits::max_undo_bytes`
//! bytes of stored (compressed) steps, undo and redo together; the oldest go first. Per scene at
//! most `OwnerConfig::max_history_bytes` (`serve --max-history-bytes`), since user ids come from
//! clients: a thousand made-up ids must not fill the disk. Over it, steps go from the users least
//! entitled to keep them first: users whose id a client chose (guests) before users an auth
//! file names, and among those the one idle longest (whose newest step is oldest), its oldest
//! step first. The step just pushed always stays. The bound holds from the next step on: a
//! store written with a larger bound is trimmed as new steps arrive. In memory
//! the owner keeps only each user's list of step ids and sizes: step bodies live in the store
//! (and, until the turn commits, in [`HistoryWrites`]), read back when undone.

use std::collections::{BTreeMap, HashMap, VecDeque};

use brickcast_protocol::wire::UserId;
use serde::{Deserialize, Serialize};

pub use super::step::{
    BrickChange, Image, Revert, Step, VoxelChange, apply_after, plan_revert, write_bricks,
    write_planned,
};

/// A stored step, as a user's stacks name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StepRef {
    pub id: u64,
    pub bytes: u64,
    /// Bricks the step changed: what undoing it costs (512 voxels compared each).
    pub bricks: u32,
}

/// What the store's index keeps per step, under (user, step id): the stack it is on, its
/// stored size and its bricks. Ids grow with every push, so a user's rows in id order *are* the
/// stacks, oldest first: no per-user row is rewritten when a step comes or goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StepMeta {
    pub redo: bool,
    pub bytes: u64,
    pub bricks: u32,
}

/// One user's undo and redo stacks (oldest first).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Stacks {
    pub undo: VecDeque<StepRef>,
    pub redo: Vec<StepRef>,
}

impl Stacks {
    /// Stacks from the index rows of one user, in id order.
    pub fn from_rows(rows: impl IntoIterator<Item = (u64, StepMeta)>) -> Stacks {
        let mut stacks = Stacks::default();
        for (id, meta) in rows {
            let entry = StepRef {
                id,
                bytes: meta.bytes,
                bricks: meta.bricks,
            };
            if meta.redo {
                stacks.redo.push(entry);
            } else {
                stacks.undo.push_back(entry);
            }
        }
        stacks
    }

    fn bytes(&self) -> u64 {
        self.undo.iter().chain(&self.redo).map(|s| s.bytes).sum()
    }

    fn steps(&self) -> usize {
        self.undo.len() + self.redo.len()
    }

    /// The id of the user's newest step (ids grow with every push: its last activity).
    fn newest(&self) -> u64 {
        let undo = self.undo.back().map_or(0, |s| s.id);
        let redo = self.redo.last().map_or(0, |s| s.id);
        undo.max(redo)
    }

    fn holds(&self, id: u64) -> bool {
        self.undo.iter().chain(&self.redo).any(|s| s.id == id)
    }
}

/// What a turn changed in the history, written in the turn's commit (a redb transaction, or
/// the turn's message in the cluster's log, which every node applies with
/// [`History::apply_committed`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HistoryWrites {
    /// New steps: id → (user, index entry, stored bytes).
    pub steps: BTreeMap<u64, (UserId, StepMeta, Vec<u8>)>,
    /// Steps dropped (bounds, a cleared redo stack, undone or redone): id → user.
    pub removed: BTreeMap<u64, UserId>,
}

impl HistoryWrites {
    pub fn is_empty(&self) -> bool {
        self.steps.is_empty() && self.removed.is_empty()
    }
}

/// Which stack an operation takes its step from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    Undo,
    Redo,
}

/// Every user's stacks, and this turn's unwritten changes.
pub struct History {
    users: HashMap<UserId, Stacks>,
    compressor: Option<zstd::bulk::Compressor<'static>>,
    /// Bytes of every stored step, kept as steps come and go.
    bytes: u64,
    next_id: u64,
    max_steps: usize,
    max_bytes: u64,
    /// Bytes of stored steps over every user (see the module doc).
    max_scene_bytes: u64,
    pending: HistoryWrites,
}

impl History {
    /// History as recovered from the store: each user's stacks, and the highest step id in use.
    pub fn new(users: Vec<(UserId, Stacks)>, last_id: u64, max_steps: u32, max_bytes: u64) -> Self {
        let users: HashMap<UserId, Stacks> = users.into_iter().collect();
        History {
            compressor: zstd::bulk::Compressor::new(1).ok(),
            bytes: users.values().map(Stacks::bytes).sum(),
            users,
            next_id: last_id + 1,
            max_steps: max_steps.max(1) as usize,
            max_bytes,
            max_scene_bytes: u64::MAX,
            pending: HistoryWrites::default(),
        }
    }

    /// Bounds the bytes of stored steps over every user (see the module doc).
    pub fn with_scene_cap(mut self, max_scene_bytes: u64) -> Self {
        self.max_scene_bytes = max_scene_bytes;
        self
    }

    /// A user's stacks (for tests and metrics).
    pub fn stacks(&self, user: UserId) -> Option<&Stacks> {
        self.users.get(&user)
    }

    /// Every user's stacks (copies).
    pub fn users(&self) -> impl Iterator<Item = (UserId, Stacks)> + '_ {
        self.users.iter().map(|(u, s)| (*u, s.clone()))
    }

    /// Users with any history.
    pub fn user_count(&self) -> usize {
        self.users.len()
    }

    /// Bytes of stored steps over every user.
    pub fn total_bytes(&self) -> u64 {
        self.bytes
    }

    /// Records an edit message's step: onto the undo stack, clearing the redo stack.
    pub fn record_edit(&mut self, user: UserId, step: &Step) {
        let bytes = step.encode_with(self.compressor.as_mut());
        self.record_encoded(user, bytes, step.bricks.len());
    }

    /// [`History::record_edit`] of a step already in its stored form (of `bricks` bricks).
    pub fn record_encoded(&mut self, user: UserId, bytes: Vec<u8>, bricks: usize) {
        let stacks = self.users.entry(user).or_default();
        for dropped in stacks.redo.drain(..) {
            self.bytes -= dropped.bytes;
            self.pending.removed.insert(dropped.id, user);
            self.pending.steps.remove(&dropped.id);
        }
        self.push(user, Direction::Undo, bytes, bricks);
    }

    /// The top of a user's undo (or redo) stack, left there.
    pub fn peek(&self, user: UserId, direction: Direction) -> Option<StepRef> {
        let stacks = self.users.get(&user)?;
        match direction {
            Direction::Undo => stacks.undo.back().copied(),
            Direction::Redo => stacks.redo.last().copied(),
        }
    }

    /// The top of a user's undo (or redo) stack, removed from it. `load` reads a stored step.
    pub fn pop(
        &mut self,
        user: UserId,
        direction: Direction,
        load: impl FnOnce(u64) -> Result<Option<Vec<u8>>, String>,
    ) -> Result<Option<Step>, String> {
        let Some(top) = self.peek(user, direction) else {
            return Ok(None);
        };
        let pending = self.pending.steps.get(&top.id).map(|(_, _, b)| b.clone());
        self.take_top(user, direction);
        let bytes = match pending {
            Some(bytes) => bytes,
            None => load(top.id)?.ok_or_else(|| format!("history step {} is missing", top.id))?,
        };
        Step::decode(&bytes).map(Some)
    }

    /// Removes the top of a user's undo (or redo) stack without reading it.
    pub fn take_top(&mut self, user: UserId, direction: Direction) -> Option<StepRef> {
        let stacks = self.users.get_mut(&user)?;
        let top = match direction {
            Direction::Undo => stacks.undo.pop_back(),
            Direction::Redo => stacks.redo.pop(),
        }?;
        self.bytes -= top.bytes;
        self.pending.removed.insert(top.id, user);
        self.pending.steps.remove(&top.id);
        Some(top)
    }

    /// A step's stored form while its turn has not committed yet (the store does not hold it).
    pub fn pending_step(&self, id: u64) -> Option<&[u8]> {
        self.pending.steps.get(&id).map(|(_, _, b)| &b[..])
    }

    /// The compressor steps are stored with.
    pub fn compressor(&mut self) -> Option<&mut zstd::bulk::Compressor<'static>> {
        self.compressor.as_mut()
    }

    /// Pushes the stored form of an undo's (redo's) record of `bricks` bricks onto the
    /// opposite stack. Returns its size.
    pub fn push_stored(
        &mut self,
        user: UserId,
        popped_from: Direction,
        bytes: Vec<u8>,
        bricks: usize,
    ) -> u64 {
        let onto = match popped_from {
            Direction::Undo => Direction::Redo,
            Direction::Redo => Direction::Undo,
        };
        let size = bytes.len() as u64;
        self.push(user, onto, bytes, bricks);
        size
    }

    /// Pushes the record of an undo (onto the redo stack) or a redo (onto the undo stack).
    /// Returns its stored form, which the log's record of the undo carries too.
    pub fn push_record(&mut self, user: UserId, popped_from: Direction, record: &Step) -> Vec<u8> {
        let onto = match popped_from {
            Direction::Undo => Direction::Redo,
            Direction::Redo => Direction::Undo,
        };
        let bytes = record.encode_with(self.compressor.as_mut());
        self.push(user, onto, bytes.clone(), record.bricks.len());
        bytes
    }

    /// Forgets a user (a connection without a stable id, once it leaves).
    pub fn forget(&mut self, user: UserId) {
        if let Some(stacks) = self.users.remove(&user) {
            self.bytes -= stacks.bytes();
            for s in stacks.undo.iter().chain(&stacks.redo) {
                self.pending.removed.insert(s.id, user);
                self.pending.steps.remove(&s.id);
            }
        }
    }

    /// Pushes a stored step of `bricks` bricks onto a stack, then applies the bounds.
    fn push(&mut self, user: UserId, onto: Direction, bytes: Vec<u8>, bricks: usize) {
        let id = self.next_id;
        self.next_id += 1;
        let entry = StepRef {
            id,
            bytes: bytes.len() as u64,
            bricks: bricks.min(u32::MAX as usize) as u32,
        };
        let meta = StepMeta {
            redo: onto == Direction::Redo,
            bytes: entry.bytes,
            bricks: entry.bricks,
        };
        self.pending.steps.insert(id, (user, meta, bytes));
        self.bytes += entry.bytes;
        let stacks = self.users.entry(user).or_default();
        match onto {
            Direction::Undo => stacks.undo.push_back(entry),
            Direction::Redo => stacks.redo.push(entry),
        }
        // Oldest first: the bottom of the undo stack, then of the redo stack; the step just
        // pushed always stays.
        while stacks.steps() > 1
            && (stacks.steps() > self.max_steps || stacks.bytes() > self.max_bytes)
        {
            let dropped = if stacks.undo.len() > usize::from(onto == Direction::Undo) {
                stacks.undo.pop_front()
            } else if !stacks.redo.is_empty()
                && stacks.redo.len() > usize::from(onto == Direction::Redo)
            {
                Some(stacks.redo.remove(0))
            } else {
                None
            };
            let Some(dropped) = dropped else { break };
            self.bytes -= dropped.bytes;
            self.pending.removed.insert(dropped.id, user);
            self.pending.steps.remove(&dropped.id);
        }
        while self.bytes > self.max_scene_bytes {
            let Some(victim) = self.least_entitled(id) else {
                break;
            };
            let Some(stacks) = self.users.get_mut(&victim) else {
                break;
            };
            // Its oldest step that is not the one just pushed.
            // (The one just pushed is the oldest of its stack only when it is alone there.)
            let dropped = if stacks.undo.front().is_some_and(|s| s.id != id) {
                stacks.undo.pop_front()
            } else if stacks.redo.first().is_some_and(|s| s.id != id) {
                Some(stacks.redo.remove(0))
            } else {
                None
            };
            let Some(dropped) = dropped else { break };
            if stacks.steps() == 0 {
                self.users.remove(&victim);
            }
            self.bytes -= dropped.bytes;
            self.pending.removed.insert(dropped.id, victim);
            self.pending.steps.remove(&dropped.id);
        }
    }

    /// The user whose steps go first when the scene is over its cap: guests before users an
    /// auth file names, then the one idle longest. `keep` (the step just pushed) is not
    /// counted as a step that may go.
    fn least_entitled(&self, keep: u64) -> Option<UserId> {
        self.users
            .iter()
            .filter(|(_, s)| s.steps() > usize::from(s.holds(keep)))
            .min_by_key(|(user, s)| (crate::identity::is_pinned(**user), s.newest(), **user))
            .map(|(user, _)| *user)
    }

    /// Applies a turn's changes committed by another node (the scene's owner in a cluster):
    /// steps dropped leave their stacks, new steps go on top of theirs (ids grow with every
    /// push, so appending keeps each stack in id order, as [`Stacks::from_rows`] builds it).
    /// Writes nothing of its own.
    pub fn apply_committed(&mut self, writes: &HistoryWrites) {
        for (id, user) in &writes.removed {
            if let Some(stacks) = self.users.get_mut(user) {
                let before = stacks.bytes();
                stacks.undo.retain(|s| s.id != *id);
                stacks.redo.retain(|s| s.id != *id);
                self.bytes -= before - stacks.bytes();
                if stacks.steps() == 0 {
                    self.users.remove(user);
                }
            }
        }
        for (id, (user, meta, _)) in &writes.steps {
            let entry = StepRef {
                id: *id,
                bytes: meta.bytes,
                bricks: meta.bricks,
            };
            let stacks = self.users.entry(*user).or_default();
            if meta.redo {
                stacks.redo.push(entry);
            } else {
                stacks.undo.push_back(entry);
            }
            self.bytes += meta.bytes;
            self.next_id = self.next_id.max(id + 1);
        }
    }

    /// Every stored step as the store's index names it: (user, step id, meta).
    pub fn rows(&self) -> Vec<(UserId, u64, StepMeta)> {
        let mut rows = Vec::new();
        for (user, stacks) in &self.users {
            for (s, redo) in stacks
                .undo
                .iter()
                .map(|s| (s, false))
                .chain(stacks.redo.iter().map(|s| (s, true)))
            {
                let meta = StepMeta {
                    redo,
                    bytes: s.bytes,
                    bricks: s.bricks,
                };
                rows.push((*user, s.id, meta));
            }
        }
        rows.sort_unstable_by_key(|r| (r.0, r.1));
        rows
    }

    /// The highest step id given out (0: none).
    pub fn last_id(&self) -> u64 {
        self.next_id - 1
    }

    /// This turn's changes, for the commit; the history starts the next turn with none.
    pub fn take_writes(&mut self) -> HistoryWrites {
        std::mem::take(&mut self.pending)
    }

    /// Whether the turn changed the history.
    pub fn has_writes(&self) -> bool {
        !self.pending.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::{BrickMap, Colour};

    fn red() -> Colour {
        Colour::from_rgb8(255, 0, 0)
    }
    fn blue() -> Colour {
        Colour::from_rgb8(0, 0, 255)
    }

    /// Applies an edit with the journal on and returns its step.
    fn edit(map: &mut BrickMap, f: impl FnOnce(&mut BrickMap)) -> Step {
        map.begin_journal();
        f(map);
        Step::from_journal(map)
    }

    /// Undoes `step` as the owner does, and checks that replaying the undo's record (as
    /// recovery does from the log) on the map as it was gives the same map.
    fn undo(map: &mut BrickMap, step: &Step) -> Revert {
        let mut replayed = map.clone();
        let revert = plan_revert(map, step);
        write_bricks(map, &revert.writes).unwrap();
        apply_after(
            &mut replayed,
            &Step::decode(&revert.record.encode()).unwrap(),
        )
        .unwrap();
        assert_eq!(replayed.content_hash(), map.content_hash());
        revert
    }

    #[test]
    fn undo_restores_only_voxels_nobody_changed_since() {
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        map.set([1, 1, 1], blue());
        let before = map.content_hash();
        let mine = edit(&mut map, |m| {
            m.set([1, 1, 1], red());
            m.set([2, 1, 1], red());
            m.set([20, 20, 20], red());
        });
        // Someone else paints one of my voxels and removes another.
        map.set([2, 1, 1], blue());
        map.clear([20, 20, 20]);
        let r = undo(&mut map, &mine);
        assert_eq!((r.restored, r.kept), (1, 2));
        assert_eq!(map.get([1, 1, 1]), Some(blue()));
        assert_eq!(map.get([2, 1, 1]), Some(blue()));
        assert_eq!(map.get([20, 20, 20]), None);
        assert_ne!(map.content_hash(), before);
        map.check_invariants().unwrap();

        // Redo (undoing the undo's record) puts back what the undo restored.
        let redo = undo(&mut map, &r.record);
        assert_eq!((redo.restored, redo.kept), (1, 0));
        assert_eq!(map.get([1, 1, 1]), Some(red()));
    }

    #[test]
    fn undo_of_a_sphere_returns_the_map_exactly() {
        let mut map = BrickMap::new([96, 96, 96]).unwrap();
        map.sphere(
            [40.0, 40.0, 40.0],
            10.0,
            brickcast_protocol::BrushMode::Fill,
            blue(),
        );
        let before = map.content_hash();
        let step = edit(&mut map, |m| {
            m.sphere(
                [48.0, 48.0, 48.0],
                32.0,
                brickcast_protocol::BrushMode::Fill,
                red(),
            );
        });
        let changed = map.content_hash();
        let r = undo(&mut map, &step);
        assert_eq!(r.kept, 0);
        assert_eq!(map.content_hash(), before);
        undo(&mut map, &r.record);
        assert_eq!(map.content_hash(), changed);
        map.check_invariants().unwrap();
        let bytes = step.encode();
        assert!(
            bytes.len() < 128 << 10,
            "a compressed sphere step is {} bytes",
            bytes.len()
        );
        assert_eq!(Step::decode(&bytes).unwrap(), step);
    }

    #[test]
    fn bounds_drop_the_oldest_step_and_a_new_edit_clears_redo() {
        let mut history = History::new(Vec::new(), 0, 3, u64::MAX);
        let step = Step::default();
        for _ in 0..5 {
            history.record_edit(7, &step);
        }
        let ids: Vec<u64> = history
            .stacks(7)
            .unwrap()
            .undo
            .iter()
            .map(|s| s.id)
            .collect();
        assert_eq!(ids, [3, 4, 5]);
        let popped = history.pop(7, Direction::Undo, |_| Ok(None)).unwrap();
        assert!(popped.is_some());
        history.push_record(7, Direction::Undo, &step);
        assert_eq!(history.stacks(7).unwrap().redo.len(), 1);
        history.record_edit(7, &step);
        assert!(history.stacks(7).unwrap().redo.is_empty());
        let writes = history.take_writes();
        assert!(writes.removed.contains_key(&1) && writes.removed.contains_key(&5));
        let stored: u64 = writes.steps.values().map(|(_, _, b)| b.len() as u64).sum();
        assert_eq!(history.total_bytes(), stored);
        assert!(
            history
                .pop(8, Direction::Undo, |_| Ok(None))
                .unwrap()
                .is_none()
        );
    }

    /// A scene's history stays under its cap however many ids clients make up: guests' steps
    /// go before those of a user the auth file names, the longest idle first, and a replica
    /// applying the committed writes ends where the owner does.
    #[test]
    fn the_scene_cap_trims_idle_guests_first() {
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        let step = edit(&mut map, |m| {
            for x in 0..8 {
                m.set([x, 1, 1], red());
            }
        });
        let size = step.encode().len() as u64;
        let cap = 10 * size;
        let mut owner = History::new(Vec::new(), 0, 256, u64::MAX).with_scene_cap(cap);
        let mut replica = History::new(Vec::new(), 0, 256, u64::MAX);
        let pinned: UserId = crate::identity::PINNED | 5;
        for _ in 0..3 {
            owner.record_edit(pinned, &step);
        }
        for guest in 1..=100 {
            owner.record_edit(guest, &step);
            assert!(
                owner.total_bytes() <= cap,
                "{} > {cap}",
                owner.total_bytes()
            );
            if guest % 7 == 0 {
                replica.apply_committed(&owner.take_writes());
            }
        }
        // Guest 1 comes back: its new step stays, and the idlest guest's goes.
        owner.record_edit(1, &step);
        replica.apply_committed(&owner.take_writes());
        assert!(owner.total_bytes() <= cap);
        assert_eq!(owner.stacks(pinned).map(|s| s.undo.len()), Some(3));
        let guests: Vec<UserId> = (1..=100).filter(|g| owner.stacks(*g).is_some()).collect();
        assert_eq!(guests, [1, 95, 96, 97, 98, 99, 100]);
        assert_eq!(owner.rows(), replica.rows());
        assert_eq!(owner.total_bytes(), replica.total_bytes());
        // With no guest left to trim, the named user's own oldest steps go, never the newest.
        let mut alone = History::new(Vec::new(), 0, 256, u64::MAX).with_scene_cap(2 * size);
        for _ in 0..5 {
            alone.record_edit(pinned, &step);
        }
        let ids: Vec<u64> = alone
            .stacks(pinned)
            .unwrap()
            .undo
            .iter()
            .map(|s| s.id)
            .collect();
        assert_eq!(ids, [4, 5]);
        // A single step larger than the cap is kept: it is the one just pushed.
        let mut tiny = History::new(Vec::new(), 0, 256, u64::MAX).with_scene_cap(1);
        tiny.record_edit(3, &step);
        tiny.record_edit(4, &step);
        assert!(tiny.stacks(3).is_none());
        assert_eq!(tiny.stacks(4).map(|s| s.undo.len()), Some(1));
    }

    /// A replica that applies the owner's committed writes, turn by turn, holds the same
    /// stacks, byte count and next id as the owner: a new owner undoes where the old left off.
    #[test]
    fn a_replica_applying_committed_writes_matches_the_owner() {
        let mut owner = History::new(Vec::new(), 0, 3, u64::MAX);
        let mut replica = History::new(Vec::new(), 0, 3, u64::MAX);
        let mut bodies: HashMap<u64, Vec<u8>> = HashMap::new();
        let mut map = BrickMap::new([32, 32, 32]).unwrap();
        // Ends a turn: the owner's writes are "committed" and the replica applies them.
        let mut commit = |owner: &mut History, bodies: &mut HashMap<u64, Vec<u8>>| {
            let writes = owner.take_writes();
            for (id, (_, _, body)) in &writes.steps {
                bodies.insert(*id, body.clone());
            }
            replica.apply_committed(&writes);
            for user in [1, 2] {
                assert_eq!(owner.stacks(user), replica.stacks(user), "user {user}");
            }
            assert_eq!(owner.total_bytes(), replica.total_bytes());
            assert_eq!(owner.last_id(), replica.last_id());
            assert_eq!(owner.rows(), replica.rows());
            assert!(!replica.has_writes(), "a replica writes nothing of its own");
            replica.user_count()
        };
        owner.record_edit(
            1,
            &edit(&mut map, |m| {
                m.set([1, 1, 1], red());
            }),
        );
        commit(&mut owner, &mut bodies);
        owner.record_edit(
            2,
            &edit(&mut map, |m| {
                m.set([2, 2, 2], blue());
            }),
        );
        commit(&mut owner, &mut bodies);
        let step = owner
            .pop(1, Direction::Undo, |id| Ok(bodies.get(&id).cloned()))
            .unwrap()
            .unwrap();
        owner.push_record(1, Direction::Undo, &step);
        commit(&mut owner, &mut bodies);
        // Past the bound of 3 steps: user 2's oldest goes.
        for i in 0..3 {
            owner.record_edit(
                2,
                &edit(&mut map, |m| {
                    m.set([3, 3, i], red());
                }),
            );
        }
        commit(&mut owner, &mut bodies);
        owner.forget(1);
        assert_eq!(commit(&mut owner, &mut bodies), 1);
    }
}
