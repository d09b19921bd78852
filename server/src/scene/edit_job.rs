//! A heavy edit, planned across turns and applied in one (see `jobs.rs` for the rules every
//! job follows).
//!
//! An edit message whose ops ask for at least `OwnerConfig::slice_bricks` bricks of work (two
//! 256³ boxes, fifteen radius-64 spheres) is validated when it arrives, then planned a chunk of
//! 8×8×8 cells per turn: each brick of the chunk that an op covers is read from the map and
//! every op of the message is applied to that copy in order ([`Resolved::brushes`] and
//! [`brush_brick`], the same definition the map's own brushes use), which gives the brick the
//! edit writes and the step its user can undo. The last turn plans again the chunks someone
//! changed meanwhile, writes every brick, records the step, logs the message's ops (recovery
//! replays them whole, to the same bricks) and acknowledges it.
//!
//! Only messages whose every op is resolved without the map are planned so: a ray op's target
//! (and a fill's region, a span's ends: `EditOp::reads_map`) depends on the map as the turn
//! that applies it finds it, so a message with one is applied whole, in one turn, as before.

use std::collections::BTreeSet;

use brickcast_protocol::apply::{Resolved, resolve};
use brickcast_protocol::brick::{BRICK_EDGE, BrickData, EMPTY_MASK, Mask};
use brickcast_protocol::journal::diff_bricks;
use brickcast_protocol::map::{VoxelBox, brush_brick};
use brickcast_protocol::wire::{EditOp, OpRejection, Shape};
use brickcast_protocol::{BrickMap, Colour};

use super::history::{BrickChange, History, Image};
use super::jobs::{Job, Planning, Progress};
use super::owner::{AckTo, Log, Owner, PendingAck, ack};
use super::step::EncodedFrames;
use super::{Command, SessionId};
use crate::fair::Admitted;
use crate::metrics::Metrics;
use crate::record::LogRecord;

/// Cells along one edge of a chunk: a chunk is 512 cells, one frame.
const CHUNK_CELLS: u32 = 8;

/// One chunk of the edit, planned against the map as it was in some turn.
struct Planned {
    chunk: u32,
    /// Cells whose brick changes, with the brick they get (`None`: the cell empties).
    writes: Vec<(u32, Option<Image>)>,
    /// The step's bricks of this chunk, encoded (one frame of the stored step).
    frames: EncodedFrames,
    bricks: usize,
    /// Voxels changed, op by op (a voxel two ops change counts twice, as when applied whole).
    voxels: u64,
}

/// A heavy edit waiting for (or in) its planning.
pub(super) struct EditJob {
    pub(super) user: u64,
    session: SessionId,
    /// Whether the user's history outlives the session (not a guest's).
    stable: bool,
    client_seq: u64,
    /// The ops that apply, in order, and what each resolved to.
    ops: Vec<EditOp>,
    resolved: Vec<Resolved>,
    rejected: Vec<OpRejection>,
    work: u64,
    /// Chunks the ops' bounds cover, in order; the next one to plan.
    chunks: Vec<u32>,
    next: usize,
    planned: Vec<Planned>,
    planning: Planning,
    /// The edit's place at the scene's heavy-edit gate, given back once it is applied.
    admitted: Option<Admitted>,
    /// The user's commands that arrived after this one, in order.
    pub(super) waiting: Vec<Command>,
}

impl EditJob {
    /// Notes cells changed since the job planned their chunks.
    pub(super) fn note_touched(&mut self, touched: &[u32], cells: [u32; 3]) {
        for &cell in touched {
            self.planning.touched(chunk_of_index(cell, cells));
        }
    }
}

impl Owner {
    /// Whether an edit message from `to`, editing as `editor`, is planned across turns: heavy
    /// enough and free of ops that read the map. If so it is queued as a job (answered when it is applied)
    /// and given back as `None`; otherwise its ops and gate place come back to be applied now.
    pub(super) fn slice_edit(
        &mut self,
        to: AckTo,
        client_seq: u64,
        ops: Vec<EditOp>,
        editor: Option<u64>,
        admitted: Option<Admitted>,
    ) -> Option<(Vec<EditOp>, Option<Admitted>)> {
        let (Some(user), AckTo::Session(session)) = (editor, to) else {
            return Some((ops, admitted));
        };
        // A message of one box between two rays (what the box tool sends) is resolved now, on
        // the map this turn has (the one it would be applied to), and goes on as the box it
        // is: a large one is planned across turns like any box, and the log holds the box,
        // whatever the map is when it is replayed. (In a longer message an earlier op could
        // change what the rays hit: such messages are applied whole, as they came.)
        let ops = match <[EditOp; 1]>::try_from(ops) {
            Ok([op]) => vec![self.boxed_span(op)],
            Err(ops) => ops,
        };
        let size = self.map.size();
        let work: u64 = ops
            .iter()
            .fold(0u64, |sum, op| sum.saturating_add(op.work(size)));
        if !self.may_slice(to)
            || work < u64::from(self.config.slice_bricks).saturating_mul(512)
            || ops.iter().any(EditOp::reads_map)
            // A plan writes bricks; a swatch is set only when its message is applied whole.
            || ops.iter().any(|op| matches!(op, EditOp::Swatch { .. }))
        {
            return Some((ops, admitted));
        }
        // Without rays, resolving reads nothing of the map: the same now as when applied.
        let limits = &self.config.limits;
        let outcomes: Vec<_> = ops
            .iter()
            .map(|op| resolve(&self.map, op, limits))
            .collect();
        if outcomes.iter().all(|o| o.is_err()) {
            // Nothing applies: answered now, like any batch whose every op is rejected.
            return Some((ops, admitted));
        }
        let stable = self.subs.get(&session).is_some_and(|s| s.stable);
        let mut job = EditJob {
            user,
            session,
            stable,
            client_seq,
            ops: Vec::with_capacity(ops.len()),
            resolved: Vec::with_capacity(ops.len()),
            rejected: Vec::new(),
            work: 0,
            chunks: Vec::new(),
            next: 0,
            planned: Vec::new(),
            planning: Planning::default(),
            admitted,
            waiting: Vec::new(),
        };
        for (index, (op, outcome)) in ops.into_iter().zip(outcomes).enumerate() {
            match outcome {
                Ok(resolved) => {
                    job.work = job.work.saturating_add(op.work(size));
                    job.ops.push(op);
                    job.resolved.push(resolved);
                }
                Err(reason) => job.rejected.push(OpRejection {
                    index: index as u32,
                    reason,
                }),
            }
        }
        job.chunks = chunks_of(&job.resolved, &self.map);
        self.jobs.push_back(Job::Edit(job));
        None
    }

    /// `op` as a plain [`EditOp::Box`] when it is a box between two rays that resolves on the
    /// map as it is; any other op (or one that will be refused) as it came.
    fn boxed_span(&self, op: EditOp) -> EditOp {
        if !matches!(
            op,
            EditOp::Span {
                shape: Shape::Box,
                ..
            }
        ) {
            return op;
        }
        match resolve(&self.map, &op, &self.config.limits) {
            Ok(Resolved::Box {
                min,
                max,
                mode,
                colour,
            }) => EditOp::Box {
                min,
                max,
                mode,
                colour,
            },
            _ => op,
        }
    }

    /// The first job, an edit.
    fn edit_job(&mut self) -> &mut EditJob {
        match self.jobs.front_mut() {
            Some(Job::Edit(job)) => job,
            _ => unreachable!("the first job is an edit"),
        }
    }

    /// One turn of the first job, an edit: plans its next chunk, or finishes it.
    pub(super) fn edit_turn(&mut self, log: &mut Log, acks: &mut Vec<PendingAck>) -> Progress {
        let job = self.edit_job();
        if let Some(&chunk) = job.chunks.get(job.next) {
            job.next += 1;
            let index = job.planned.len();
            job.planning.planned(chunk, index);
            let Some(Job::Edit(job)) = self.jobs.front_mut() else {
                unreachable!("the first job is an edit")
            };
            let planned = plan(&self.map, &job.resolved, chunk, &mut self.history);
            job.planned.push(planned);
            return Progress::Planned;
        }
        let limit = job.planned.len();
        let again = job.planning.take_some_dirty(limit);
        if !again.is_empty() {
            let Some(Job::Edit(job)) = self.jobs.front_mut() else {
                unreachable!("the first job is an edit")
            };
            for frame in again {
                let chunk = job.planned[frame].chunk;
                job.planned[frame] = plan(&self.map, &job.resolved, chunk, &mut self.history);
            }
            return Progress::Planned;
        }
        let Some(Job::Edit(job)) = self.jobs.pop_front() else {
            unreachable!("the first job is an edit")
        };
        Progress::Finished(self.finish_edit(job, log, acks))
    }

    /// The job's last turn: plans again the chunks someone changed, then writes, records, logs
    /// and acknowledges the whole edit at once.
    fn finish_edit(
        &mut self,
        mut job: EditJob,
        log: &mut Log,
        acks: &mut Vec<PendingAck>,
    ) -> Vec<Command> {
        for frame in job.planning.take_dirty() {
            let chunk = job.planned[frame].chunk;
            job.planned[frame] = plan(&self.map, &job.resolved, chunk, &mut self.history);
        }
        let seq = self.seq + 1;
        self.map.set_sequence(seq);
        let (mut bricks, mut voxels) = (0usize, 0u64);
        let mut frames = EncodedFrames::default();
        let mut writes = Vec::with_capacity(job.planned.len());
        for planned in job.planned.drain(..) {
            bricks += planned.bricks;
            voxels += planned.voxels;
            frames.append(&planned.frames);
            writes.push(planned.writes);
        }
        if let Err(e) = super::step::write_planned(&mut self.map, writes.into_iter().flatten()) {
            // Planned from this map's own bricks: cannot happen.
            tracing::error!(scene = %self.name, error = %e, "an edit wrote a brick the map refused");
        }
        self.seq = seq;
        // A guest's history is forgotten when it leaves: a step finished after that is not kept.
        if job.stable || self.subs.values().any(|s| s.user == job.user) {
            self.history
                .record_encoded(job.user, frames.finish(), bricks);
        }
        let count = job.ops.len() as u32;
        Metrics::add(&self.metrics.ops_rejected, job.rejected.len() as u64);
        Metrics::add(&self.metrics.ops_applied, u64::from(count));
        Metrics::add(&self.metrics.voxels_changed, voxels);
        Metrics::add(&self.metrics.edit_batches, 1);
        Metrics::add(&self.metrics.edits_sliced, 1);
        self.log_ops += u64::from(count);
        self.log_work = self.log_work.saturating_add(job.work);
        let ops = std::mem::take(&mut job.ops);
        log.push((
            seq,
            LogRecord::Ops {
                user: job.user,
                ops,
            },
        ));
        let to = AckTo::Session(job.session);
        let rejected = std::mem::take(&mut job.rejected);
        acks.push(ack(to, job.client_seq, Some(seq), count, rejected));
        // Applied: the next heavy edit may queue.
        drop(job.admitted.take());
        std::mem::take(&mut job.waiting)
    }
}

/// The chunk of a cell, by linear cell index.
fn chunk_of_index(cell: u32, cells: [u32; 3]) -> u32 {
    let (x, rest) = (cell % cells[0], cell / cells[0]);
    let (y, z) = (rest % cells[1], rest / cells[1]);
    chunk_key([x, y, z], cells)
}

/// The linear index of the chunk holding `cell`.
fn chunk_key(cell: [u32; 3], cells: [u32; 3]) -> u32 {
    let dims = cells.map(|c| c.div_ceil(CHUNK_CELLS));
    let c = cell.map(|v| v / CHUNK_CELLS);
    c[0] + dims[0] * (c[1] + dims[1] * c[2])
}

/// The cells of a chunk, as an inclusive box of voxels clipped to the scene.
fn chunk_box(chunk: u32, map: &BrickMap) -> VoxelBox {
    let cells = map.cell_dims();
    let dims = cells.map(|c| c.div_ceil(CHUNK_CELLS));
    let c = [
        chunk % dims[0],
        (chunk / dims[0]) % dims[1],
        chunk / dims[0] / dims[1],
    ];
    let edge = CHUNK_CELLS * BRICK_EDGE;
    let chunk = VoxelBox {
        lo: c.map(|v| v * edge),
        hi: c.map(|v| v * edge + edge - 1),
    };
    chunk.clip(&map.whole()).unwrap_or(chunk)
}

/// Every chunk the ops' bounds reach inside the scene, in order.
fn chunks_of(resolved: &[Resolved], map: &BrickMap) -> Vec<u32> {
    let cells = map.cell_dims();
    let mut chunks = BTreeSet::new();
    for op in resolved {
        let Some(bounds) = op.bounds().and_then(|b| b.clip(&map.whole())) else {
            continue;
        };
        let edge = CHUNK_CELLS * BRICK_EDGE;
        let (lo, hi) = (bounds.lo.map(|v| v / edge), bounds.hi.map(|v| v / edge));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let cell = [x, y, z].map(|v| v * CHUNK_CELLS);
                    chunks.insert(chunk_key(cell, cells));
                }
            }
        }
    }
    chunks.into_iter().collect()
}

/// A brick of a chunk being planned: as the map holds it, and after the ops so far.
struct Working {
    cell: [u32; 3],
    before: (Mask, Vec<Colour>),
    after: (Mask, Vec<Colour>),
}

/// Plans the edit's ops over one chunk against the map as it is: the bricks it writes, and
/// its undo step's frame, encoded.
fn plan(map: &BrickMap, ops: &[Resolved], chunk: u32, history: &mut History) -> Planned {
    let within = chunk_box(chunk, map);
    let lo = within.lo.map(|v| v / BRICK_EDGE);
    let edge = CHUNK_CELLS as usize;
    // Indexed by the cell's place in the chunk.
    let mut working: Vec<Option<Working>> = (0..edge * edge * edge).map(|_| None).collect();
    let mut scratch = [Colour::BLACK; 512];
    let mut voxels = 0u64;
    for op in ops {
        op.brushes(within, |cell, brush, mode, colour| {
            let local: [usize; 3] = std::array::from_fn(|i| (cell[i] - lo[i]) as usize);
            let at = local[0] + edge * (local[1] + edge * local[2]);
            let brick = working[at].get_or_insert_with(|| {
                let before = match map.brick(cell) {
                    Some(BrickData { mask, colours, .. }) => (mask, colours),
                    None => (EMPTY_MASK, Vec::new()),
                };
                Working {
                    cell,
                    after: before.clone(),
                    before,
                }
            });
            let after = (&brick.after.0, &brick.after.1[..]);
            let (mask, n, changed) = brush_brick(after, brush, mode, colour, &mut scratch);
            if changed > 0 {
                voxels += changed;
                brick.after = (mask, scratch[..n].to_vec());
            }
        });
    }
    let mut writes = Vec::new();
    let mut changes = Vec::new();
    for brick in working.into_iter().flatten() {
        let index = map.cell_index(brick.cell);
        let mut change = BrickChange::empty(index);
        diff_bricks(
            (&brick.before.0, &brick.before.1),
            (&brick.after.0, &brick.after.1),
            |bit, b, a| change.push(bit, b, a),
        );
        if change.is_empty() {
            continue;
        }
        let (mask, colours) = brick.after;
        let image = (!colours.is_empty()).then_some(Image { mask, colours });
        writes.push((index, image));
        changes.push(change);
    }
    changes.sort_unstable_by_key(|c| c.cell);
    writes.sort_unstable_by_key(|w| w.0);
    let mut frames = EncodedFrames::default();
    frames.push(&changes, history.compressor());
    Planned {
        chunk,
        writes,
        bricks: changes.len(),
        frames,
        voxels,
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::Ordering::Relaxed;

    use brickcast_protocol::apply::apply_op;
    use brickcast_protocol::wire::{BrushMode, EditOp, Limits};
    use brickcast_protocol::{BrickMap, Colour};

    use crate::metrics::PhaseClock;
    use crate::scene::Command;
    use crate::scene::jobs::Job;
    use crate::scene::jobs::testing::{A, B, Scene, edit, join, replies};

    /// A heavy edit planned across turns while someone else changes a brick it already
    /// planned ends exactly as the same edit applied whole in its last turn: the other voxel
    /// is kept, the user's own later edit applies after it, recovery replays it to the same
    /// map, and undoing it takes back exactly what it did.
    #[test]
    fn a_heavy_edit_planned_across_turns_ends_as_one_applied_whole() {
        let mut reference = BrickMap::new([128, 64, 128]).unwrap();
        let scene = Scene::new(&reference);
        let metrics = scene.metrics.clone();
        // 64 bricks' work (32,768 voxels) and up is planned across turns.
        let mut owner = scene.owner(64);
        let mut a = join(&mut owner, 1, A);
        let mut b = join(&mut owner, 2, B);
        let mut clock = PhaseClock::start();
        let limits = Limits::default();
        // Four chunks of 8×8×8 cells; the top row of bricks (y 40..47) is covered up to 46.
        let fill = EditOp::Box {
            min: [0, 0, 0],
            max: [94, 46, 94],
            mode: BrushMode::Fill,
            colour: Colour::from_rgb8(200, 0, 0),
        };
        let erase = EditOp::Sphere {
            centre: [60.0, 20.0, 60.0],
            radius: 12.0,
            mode: BrushMode::Erase,
            colour: Colour::BLACK,
        };
        let bad = EditOp::Set {
            pos: [0, 64, 0],
            colour: Colour::WHITE,
        };
        owner
            .step(vec![edit(1, 1, vec![fill, bad, erase])], &mut clock)
            .unwrap();
        assert!(owner.has_jobs(), "the edit is being planned");
        assert!(replies(&mut a).is_empty(), "not answered before it applies");
        // Bob sets a voxel in a brick of the first chunk, already planned; Alice's next edit
        // waits behind her first.
        let theirs = EditOp::Set {
            pos: [0, 47, 0],
            colour: Colour::from_rgb8(0, 0, 200),
        };
        let mine = EditOp::Set {
            pos: [1, 0, 0],
            colour: Colour::from_rgb8(0, 200, 0),
        };
        owner
            .step(
                vec![edit(2, 1, vec![theirs]), edit(1, 2, vec![mine])],
                &mut clock,
            )
            .unwrap();
        let bob = replies(&mut b);
        assert_eq!(bob.len(), 1, "bob's edit applied while the edit is planned");
        let mut turns = 0;
        while owner.has_jobs() {
            owner.step(Vec::new(), &mut clock).unwrap();
            turns += 1;
            assert!(turns < 10, "the edit never finished");
        }
        let alice = replies(&mut a);
        assert_eq!(alice.len(), 2, "{alice:?}");
        let (fill_seq, mine_seq) = (alice[0].1.unwrap(), alice[1].1.unwrap());
        assert!(
            bob[0].1.unwrap() < fill_seq && fill_seq < mine_seq,
            "{alice:?} {bob:?}"
        );
        assert_eq!(metrics.edits_sliced.load(Relaxed), 1);
        assert_eq!(
            metrics.ops_rejected.load(Relaxed),
            1,
            "the bad op is rejected"
        );

        // The same, whole, on a plain map: bob's voxel, the edit, alice's voxel.
        let empty = reference.content_hash();
        apply_op(&mut reference, &theirs, &limits).unwrap();
        let bobs = reference.content_hash();
        apply_op(&mut reference, &fill, &limits).unwrap();
        apply_op(&mut reference, &erase, &limits).unwrap();
        apply_op(&mut reference, &mine, &limits).unwrap();
        assert_eq!(owner.map().content_hash(), reference.content_hash());
        assert_eq!(
            owner.map().get([0, 47, 0]),
            Some(Colour::from_rgb8(0, 0, 200)),
            "bob's voxel, changed after its brick was planned, is kept"
        );

        // Recovery replays the logged ops to the same map.
        let hash = owner.map().content_hash();
        drop(owner);
        let mut owner = scene.owner(64);
        assert_eq!(owner.map().content_hash(), hash);
        // Alice undoes her voxel, then the heavy edit: only bob's voxel is left.
        let mut a = join(&mut owner, 3, A);
        for client_seq in 1..=2 {
            let undo = Command::Undo {
                session: 3,
                client_seq,
                redo: false,
            };
            owner.step(vec![undo], &mut clock).unwrap();
            while owner.has_jobs() {
                owner.step(Vec::new(), &mut clock).unwrap();
            }
        }
        assert_eq!(replies(&mut a).len(), 2);
        assert_eq!(owner.map().content_hash(), bobs);
        assert_ne!(bobs, empty);
    }

    /// A large box drawn between two rays (the box tool) is planned across turns like any
    /// box: resolved when it is ordered, logged as the box it is, so recovery replays it to
    /// the same map even though later edits change what its rays would hit.
    #[test]
    fn a_large_box_between_two_rays_is_planned_across_turns() {
        let mut reference = BrickMap::new([128, 64, 128]).unwrap();
        reference.fill_box([0, 0, 0], [127, 3, 127], BrushMode::Fill, Colour::WHITE);
        // A post whose top the second ray hits.
        reference.fill_box([100, 4, 90], [100, 39, 90], BrushMode::Fill, Colour::BLACK);
        let scene = Scene::new(&reference);
        let metrics = scene.metrics.clone();
        let mut owner = scene.owner(64);
        let mut a = join(&mut owner, 1, A);
        let mut clock = PhaseClock::start();
        let red = Colour::from_rgb8(200, 0, 0);
        let span = EditOp::Span {
            from: [2.5, 60.0, 2.5],
            from_dir: [0.0, -1.0, 0.0],
            to: [100.5, 60.0, 90.5],
            to_dir: [0.0, -1.0, 0.0],
            shape: brickcast_protocol::wire::Shape::Box,
            mode: BrushMode::Fill,
            colour: red,
            extent: 128,
        };
        owner
            .step(vec![edit(1, 1, vec![span])], &mut clock)
            .unwrap();
        assert!(owner.has_jobs(), "the box is being planned");
        while owner.has_jobs() {
            owner.step(Vec::new(), &mut clock).unwrap();
        }
        assert_eq!(metrics.edits_sliced.load(Relaxed), 1);
        assert_eq!(replies(&mut a).len(), 1);
        // From the cell in front of one hit (on the ground) to the other's (on the post).
        let limits = Limits::default();
        let boxed = EditOp::Box {
            min: [2, 4, 2],
            max: [100, 40, 90],
            mode: BrushMode::Fill,
            colour: red,
        };
        apply_op(&mut reference, &boxed, &limits).unwrap();
        assert_eq!(owner.map().content_hash(), reference.content_hash());
        // Another box on top would move the rays' hits: the log holds the box, not the rays.
        let hash = owner.map().content_hash();
        drop(owner);
        let owner = scene.owner(64);
        assert_eq!(owner.map().content_hash(), hash);
    }

    /// A scene stopping right after a heavy edit finished still applies its user's commands
    /// in the order sent: the ones that waited behind the edit before the ones still queued.
    #[test]
    fn commands_that_waited_behind_a_job_go_first_when_the_scene_stops() {
        let scene = Scene::new(&BrickMap::new([128, 64, 128]).unwrap());
        let mut owner = scene.owner(64);
        let mut a = join(&mut owner, 1, A);
        let mut clock = PhaseClock::start();
        let fill = EditOp::Box {
            min: [0, 0, 0],
            max: [94, 46, 94],
            mode: BrushMode::Fill,
            colour: Colour::WHITE,
        };
        let voxel = |colour| EditOp::Set {
            pos: [3, 50, 3],
            colour,
        };
        let (first, second) = (Colour::from_rgb8(9, 0, 0), Colour::from_rgb8(0, 9, 0));
        owner
            .step(
                vec![edit(1, 1, vec![fill]), edit(1, 2, vec![voxel(first)])],
                &mut clock,
            )
            .unwrap();
        // The edit finishes; what waited behind it is applied at the start of the next turn.
        while !owner.jobs.is_empty() {
            owner.step(Vec::new(), &mut clock).unwrap();
        }
        // That turn is the stopping one, with the user's next edit still queued.
        owner.stop(vec![edit(1, 3, vec![voxel(second)])]).unwrap();
        let mut answered = replies(&mut a);
        answered.sort_by_key(|r| r.0);
        let seqs: Vec<_> = answered.iter().map(|r| r.1.unwrap()).collect();
        assert!(
            seqs.windows(2).all(|w| w[0] < w[1]),
            "in the order sent: {answered:?}"
        );
        assert_eq!(
            owner.map().get([3, 50, 3]),
            Some(second),
            "the later edit wins"
        );
    }

    /// Someone changing every chunk a heavy edit already planned does not make its last turn
    /// the whole edit again: the changed chunks are planned again a few per turn first, and
    /// the edit still ends as if applied whole at the end.
    #[test]
    fn chunks_changed_after_planning_are_planned_again_a_few_per_turn() {
        let mut reference = BrickMap::new([256, 64, 256]).unwrap();
        let scene = Scene::new(&reference);
        let mut owner = scene.owner(64);
        let _a = join(&mut owner, 1, A);
        let mut b = join(&mut owner, 2, B);
        let mut clock = PhaseClock::start();
        let limits = Limits::default();
        // 4 × 1 × 4 chunks; bricks of the top row (y 40..47) are covered up to 46.
        let fill = EditOp::Box {
            min: [0, 0, 0],
            max: [255, 46, 255],
            mode: BrushMode::Fill,
            colour: Colour::WHITE,
        };
        owner
            .step(vec![edit(1, 1, vec![fill])], &mut clock)
            .unwrap();
        let planned = |owner: &crate::scene::Owner| match owner.jobs.front() {
            Some(Job::Edit(job)) => job.next,
            _ => panic!("the edit is not being planned"),
        };
        while planned(&owner) < 16 {
            owner.step(Vec::new(), &mut clock).unwrap();
        }
        // Bob sets a voxel above the box in every chunk, each already planned.
        let theirs: Vec<EditOp> = (0..16)
            .map(|c| EditOp::Set {
                pos: [(c % 4) * 64 + 5, 47, (c / 4) * 64 + 5],
                colour: Colour::from_rgb8(0, 0, 200),
            })
            .collect();
        owner
            .step(vec![edit(2, 1, theirs.clone())], &mut clock)
            .unwrap();
        assert_eq!(replies(&mut b).len(), 1);
        let mut turns = 0;
        while owner.has_jobs() {
            owner.step(Vec::new(), &mut clock).unwrap();
            turns += 1;
        }
        // 16 changed chunks: 4 planned again in Bob's turn and in each of the next two, the
        // last 4 in the last turn (without spreading, Bob's turn would have finished it).
        assert_eq!(turns, 3);
        for op in theirs.iter().chain([&fill]) {
            apply_op(&mut reference, op, &limits).unwrap();
        }
        assert_eq!(owner.map().content_hash(), reference.content_hash());
    }
}
