//! Working sets (issue #30): a session that states a GPU budget in its `Hello` holds only part
//! of the scene — level 0 near its eye, coarser levels of the pyramid further away — and the
//! owner follows its camera. Part of the owner (these are `impl Owner` methods), like `sync.rs`.
//!
//! A budget that the whole scene fits with room to grow ([`fits_whole`]: half of it) is served
//! the whole scene, as a client without a budget is: a working set is for what does not fit.
//!
//! Both sides run the same rule ([`Rule`], from `protocol::working_set`), so the owner knows
//! exactly what each client holds without a copy of it:
//! - **Join** (once the levels of detail are built): the largest `near` whose working set fits
//!   [`FIT_SHARE`] of the budget at the client's camera, a `Follow` with the rule, then the
//!   plan (`protocol::held::plan`) streamed by the sync pump: coarse bricks and whole level-0
//!   regions (nearest first) in turn, then `SyncDone`. After a move every coarse brick owed
//!   goes first: a region leaving level 0 lets its bricks go when its coarse brick arrives,
//!   so the copy shrinks before the new level 0 grows it.
//! - **Camera**: when the eye enters another region the rule changes: a new `Follow`, and the
//!   plan from the old rule to the new one (only the shells around level boundaries are
//!   visited) added to what is still owed and still wanted.
//! - **Deltas**: each turn a following client gets the level-0 bricks of regions its rule wants
//!   at level 0 and the coarse bricks its rule holds ([`Rule::holds`]) that changed — nothing
//!   about a place it does not hold. Coarse frames go before the turn's `Delta`, so when the
//!   client has the `Delta` it has all of that sequence.
//! - **Resume, resync, a rebuilt pyramid**: the client drops its copy (`Resync { since: 0 }`)
//!   and the working set starts again from its camera.
//!
//! The `near` chosen at the start stays for the session's life; moving the eye changes where
//! the working set is, not how far level 0 reaches.

use std::cmp::Reverse;
use std::collections::HashMap;

use brickcast_protocol::held::plan;
use brickcast_protocol::lod::Changed;
use brickcast_protocol::map::{MIN_STAND_IN_LEVEL, REGION_CELLS};
use brickcast_protocol::wire::{BrickBlob, ErrorCode, ServerMsg, WireError, encode_server};
use brickcast_protocol::working_set::{self, Rule};
use bytes::Bytes;

use super::Subscriber;
use super::owner::Owner;
use crate::metrics::Metrics;

/// The share of a client's budget its working set is fitted in (7/8): the rest leaves room for
/// what the client holds twice while data for a move is in flight (a region keeps showing its
/// old level until the new one arrives) and for an eye that moves where the same `near` costs
/// a little more.
const FIT_SHARE: (u64, u64) = (7, 8);

/// Most regions listed in one `Regions` frame (12 bytes each, uncompressed).
const MAX_REGIONS_PER_FRAME: usize = 4096;

/// Most coarse cells, solid and empty, in one `Coarse` frame's worth of cells (the wire allows
/// 65,536 empty ones a frame).
const MAX_COARSE_CELLS_PER_FRAME: usize = 16384;

/// A following session's side of its working set, in the owner.
pub(crate) struct Follow {
    /// GPU bytes the client gave the scene.
    budget: u64,
    /// The rule last sent (`None` until the first `Follow`).
    rule: Option<Rule>,
    /// What that rule's working set costs (`working_set::cost`), kept current as it moves.
    bytes: u64,
    /// The `near` fitted when the working set started: where the eye finds more than fits, a
    /// smaller `near` is used, and it grows back towards this one when there is room again.
    fitted_near: u32,
    /// Level-0 regions still owed, nearest last (popped first).
    regions: Vec<[u32; 3]>,
    /// Coarse bricks `(level, cell)` still owed, finest and nearest last.
    coarse: Vec<(u32, [u32; 3])>,
    /// Whether the next frame of the stream is coarse (coarse and regions take turns).
    coarse_next: bool,
    /// `near` could not grow back at this cost (the larger rule did not fit): not tried again
    /// until the cost falls a sixteenth of the budget below it, so a working set held small
    /// by a dense part of the world does not cost two whole plans on every move.
    grow_failed_at: Option<u64>,
    /// The working set moved: its coarse bricks go before any region, because a region
    /// leaving level 0 lets its bricks go only once the coarse brick that replaces it arrives;
    /// sent first, the copy shrinks before the new level 0 grows it (its budget holds).
    coarse_first: bool,
}

impl Follow {
    pub(super) fn new(budget: u64) -> Follow {
        Follow {
            budget,
            rule: None,
            bytes: 0,
            fitted_near: 0,
            regions: Vec::new(),
            coarse: Vec::new(),
            coarse_next: true,
            coarse_first: false,
            grow_failed_at: None,
        }
    }

    fn owes_nothing(&self) -> bool {
        self.regions.is_empty() && self.coarse.is_empty()
    }
}

/// The share of a budget the whole scene (or level view) may take for a client with that
/// budget to be served all of it, not a working set (1/2: room for edits to grow it).
const WHOLE_SHARE: (u64, u64) = (1, 2);

/// Whether level `level` of `map` (0: the scene itself), as a client lays it out, fits a GPU
/// budget of `budget` bytes with room to grow ([`WHOLE_SHARE`]). A level view is taken as a
/// quarter of the level below (surfaces shrink so, solids by an eighth).
pub(super) fn fits_whole(map: &brickcast_protocol::BrickMap, level: u32, budget: u64) -> bool {
    let bytes = map.memory().total_bytes >> (2 * level.min(30));
    bytes <= budget / WHOLE_SHARE.1 * WHOLE_SHARE.0
}

/// The bytes of a budget a working set is fitted in ([`FIT_SHARE`]).
fn share(budget: u64) -> u64 {
    budget / FIT_SHARE.1 * FIT_SHARE.0
}

/// Chebyshev distance between two regions.
fn chebyshev(a: [u32; 3], b: [u32; 3]) -> u32 {
    (0..3).map(|i| a[i].abs_diff(b[i])).max().unwrap_or(0)
}

/// The region a level-0 cell lies in.
fn region_of(cell: [u32; 3]) -> [u32; 3] {
    cell.map(|c| c / REGION_CELLS)
}

impl Owner {
    /// Starts a following session's working set from nothing: the rule from its budget and
    /// camera, its `Follow`, and the whole plan. `drop_copy`: the client holds a copy it must
    /// drop first (`Resync { since: 0 }`). A session whose budget cannot hold even the
    /// smallest working set is told so and closed.
    pub(super) fn start_follow(&self, sub: &mut Subscriber, drop_copy: bool) {
        let Some(pyramid) = self.levels.pyramid() else {
            // The levels are being built (again): it waits for them.
            sub.awaits_levels = Some(true);
            sub.lagging = false;
            return;
        };
        let Some(follow) = &mut sub.follow else {
            return;
        };
        let max_near = self.map.region_dims().into_iter().max().unwrap_or(0);
        let budget = share(follow.budget);
        let started = std::time::Instant::now();
        let rule = match working_set::fit(&self.map, pyramid, sub.camera, budget, max_near) {
            Ok((rule, cost)) => {
                follow.bytes = cost.bytes;
                follow.fitted_near = rule.near;
                rule
            }
            Err(e) => {
                sub.syncing = false;
                sub.lagging = false;
                sub.out.set_syncing(false);
                sub.out.close(
                    ErrorCode::NotAllowed,
                    format!(
                        "no working set of this scene fits a GPU budget of {} bytes ({} of it is fitted): {e}",
                        follow.budget, budget
                    ),
                );
                return;
            }
        };
        if drop_copy {
            sub.out.send(&ServerMsg::Resync { since: 0 }, &self.metrics);
        }
        follow.rule = None;
        follow.regions.clear();
        follow.coarse.clear();
        sub.lagging = false;
        sub.delivered = self.seq;
        let fitted = started.elapsed();
        self.retarget(sub, rule);
        tracing::debug!(
            scene = %self.name,
            near = rule.near,
            drop_copy,
            fit_ms = fitted.as_secs_f64() * 1e3,
            planned_ms = started.elapsed().as_secs_f64() * 1e3,
            "started a working set"
        );
    }

    /// The camera of a following session moved: its rule follows. The working set's cost is
    /// kept current through the plans between rules (`working_set::plan_bytes`); where the
    /// same `near` would cost more than the budget allows, `near` shrinks until it fits, and
    /// it grows back towards the fitted one where there is room (a quarter of the budget
    /// spare) again.
    pub(super) fn follow_camera(&self, sub: &mut Subscriber) {
        let (Some(pyramid), Some(follow)) = (self.levels.pyramid(), &mut sub.follow) else {
            return;
        };
        let Some(old) = follow.rule else {
            return;
        };
        let dims = self.map.region_dims();
        // The cost after moving: what `to` brings, less what it lets go of; and the plan.
        let Some(costs) = self.levels.costs() else {
            return;
        };
        let moved = |from: &Rule, to: &Rule, bytes: u64| {
            let wanted = plan(dims, Some(from), to);
            let cost = |p| working_set::plan_bytes_with(&self.map, pyramid, p, costs);
            let gained = cost(&wanted);
            let lost = cost(&plan(dims, Some(to), from));
            ((bytes + gained).saturating_sub(lost), wanted)
        };
        let limit = share(follow.budget);
        let mut rule = Rule::new(&self.map, pyramid, sub.camera, old.near);
        if rule == old {
            return;
        }
        let (mut bytes, mut wanted) = moved(&old, &rule, follow.bytes);
        let mut changed_near = false;
        while bytes > limit && rule.near > 0 {
            let smaller = Rule {
                near: rule.near - 1,
                ..rule
            };
            bytes = moved(&rule, &smaller, bytes).0;
            rule = smaller;
            changed_near = true;
        }
        let may_grow = follow
            .grow_failed_at
            .is_none_or(|failed| bytes + limit / 16 < failed);
        while may_grow && rule.near < follow.fitted_near && bytes < limit / 4 * 3 {
            let larger = Rule {
                near: rule.near + 1,
                ..rule
            };
            let grown = moved(&rule, &larger, bytes).0;
            if grown > limit {
                follow.grow_failed_at = Some(bytes);
                break;
            }
            (rule, bytes) = (larger, grown);
            follow.grow_failed_at = None;
            changed_near = true;
        }
        follow.bytes = bytes;
        // The plan from the old rule is the one computed first unless `near` changed.
        if changed_near {
            wanted = plan(dims, Some(&old), &rule);
        }
        self.retarget_with(sub, rule, wanted);
    }

    /// Moves a following session to `rule`: a `Follow`, and what it now lacks added to what is
    /// still owed and still wanted (the two never overlap: the plan lists only what the old
    /// rule did not want at that level).
    fn retarget(&self, sub: &mut Subscriber, rule: Rule) {
        let old = sub.follow.as_ref().and_then(|f| f.rule);
        let wanted = plan(self.map.region_dims(), old.as_ref(), &rule);
        self.retarget_with(sub, rule, wanted);
    }

    /// [`Owner::retarget`] with the plan from the session's rule to `rule` already made.
    fn retarget_with(
        &self,
        sub: &mut Subscriber,
        rule: Rule,
        wanted: brickcast_protocol::held::Plan,
    ) {
        let Some(follow) = &mut sub.follow else {
            return;
        };
        if follow.rule == Some(rule) {
            return;
        }
        let dims = self.map.region_dims();
        let old = follow.rule.replace(rule);
        follow.coarse_first = old.is_some();
        follow.regions.retain(|&r| rule.level_of(r) == 0);
        follow.coarse.retain(|&(k, c)| rule.holds(dims, k, c));
        follow.regions.extend(wanted.regions);
        follow.coarse.extend(wanted.coarse);
        follow
            .regions
            .sort_unstable_by_key(|&r| Reverse(chebyshev(r, rule.eye)));
        // About a million entries for a first rule on a 16k world: each key computed once.
        follow.coarse.sort_by_cached_key(|&(k, c)| {
            let span = 1u32 << (k - MIN_STAND_IN_LEVEL);
            let middle = c.map(|v| v.saturating_mul(span).saturating_add(span / 2));
            Reverse((k, chebyshev(middle, rule.eye)))
        });
        let msg = ServerMsg::Follow {
            eye: rule.eye,
            near: rule.near,
            top: rule.top,
        };
        sub.out.send(&msg, &self.metrics);
        sub.sync_total = (follow.regions.len() + follow.coarse.len()) as u32;
        sub.sync_sent = 0;
        sub.syncing = true;
        sub.out.set_syncing(true);
    }

    /// Queues the next frames of a following session's stream (coarse bricks and regions in
    /// turn); `SyncDone` once nothing is owed. Returns how many frames were queued.
    pub(super) fn follow_frames(&mut self, sub: &mut Subscriber) -> usize {
        let most = self.config.limits.max_bricks_per_frame as usize;
        let take = (super::sync::SYNC_BATCH_BYTES / self.sync_brick_bytes.max(1))
            .clamp(super::sync::SYNC_BATCH_MIN_BRICKS.min(most), most);
        let Some(follow) = &mut sub.follow else {
            return 0;
        };
        let coarse = !follow.coarse.is_empty()
            && (follow.regions.is_empty() || follow.coarse_first || follow.coarse_next);
        follow.coarse_next = !follow.coarse_next;
        let (encoded, count) = if coarse {
            let level = follow.coarse.last().map_or(0, |&(k, _)| k);
            let Some(map) = self.levels.map_at(&self.map, level) else {
                sub.awaits_levels = Some(true);
                return 0;
            };
            // A frame takes `take` solid bricks, with the empty cells between them: most of a
            // first working set's coarse cells are empty (air around the 16k world's
            // terrain) and cost a few bytes each, so frames of `take` cells were a fraction of
            // a region frame, and the coarse bricks finished seconds after level 0.
            let (mut cells, mut solid) = (Vec::new(), 0);
            while solid < take
                && cells.len() < MAX_COARSE_CELLS_PER_FRAME
                && let Some(&(k, c)) = follow.coarse.last()
                && k == level
            {
                follow.coarse.pop();
                solid += usize::from(map.slot_of_cell(c).is_some());
                cells.push(map.cell_index(c));
            }
            let count = cells.len();
            let make = |bricks, empty| ServerMsg::Coarse {
                level,
                bricks,
                empty,
            };
            (self.encode_cells(level, &cells, make), count)
        } else {
            let mut regions = Vec::new();
            let mut bricks = 0;
            while bricks < take
                && regions.len() < MAX_REGIONS_PER_FRAME
                && let Some(r) = follow.regions.pop()
            {
                bricks += self
                    .map
                    .region_cells(r)
                    .filter(|&c| self.map.slot_of_cell(c).is_some())
                    .count();
                regions.push(r);
            }
            let count = regions.len();
            (self.encode_regions(&regions), count)
        };
        let frames = match encoded {
            Ok(frames) => frames,
            Err(e) => {
                tracing::error!(scene = %self.name, error = %e, "could not encode a working set's data; closing the session");
                self.metrics.count_unencodable("Regions");
                sub.syncing = false;
                sub.out.close(
                    ErrorCode::Internal,
                    format!("the server could not encode this client's working set: {e}"),
                );
                return 0;
            }
        };
        let n = frames.len();
        for f in frames {
            Metrics::add(&self.metrics.sync_batches_sent, 1);
            sub.out.push(f);
        }
        sub.sync_sent = sub.sync_sent.saturating_add(count as u32);
        if sub.follow.as_ref().is_none_or(Follow::owes_nothing) {
            sub.syncing = false;
            sub.out.set_syncing(false);
            sub.delivered = self.seq;
            sub.out
                .send(&ServerMsg::SyncDone { seq: self.seq }, &self.metrics);
        }
        n.max(1)
    }

    /// `Regions` frames for whole regions, each listed region's bricks in the frame that lists
    /// it: a batch that does not fit one frame is halved until it does.
    fn encode_regions(&mut self, regions: &[[u32; 3]]) -> Result<Vec<Bytes>, WireError> {
        let cells: Vec<u32> = regions
            .iter()
            .flat_map(|&r| self.map.region_cells(r))
            .filter(|&c| self.map.slot_of_cell(c).is_some())
            .map(|c| self.map.cell_index(c))
            .collect();
        let make = |bricks, _| ServerMsg::Regions {
            regions: regions.to_vec(),
            bricks,
        };
        if cells.is_empty() {
            return Ok(vec![Bytes::from(encode_server(&make(
                BrickBlob::empty(),
                Vec::new(),
            ))?)]);
        }
        let frames = self.encode_cells(0, &cells, make)?;
        if frames.len() <= 1 {
            return Ok(frames);
        }
        if regions.len() == 1 {
            return Err(WireError::TooLong {
                what: "one region's bricks in a frame",
                len: frames.iter().map(|f| f.len()).sum(),
                max: self.config.limits.max_frame_bytes as usize,
            });
        }
        let (a, b) = regions.split_at(regions.len() / 2);
        let mut frames = self.encode_regions(a)?;
        frames.extend(self.encode_regions(b)?);
        Ok(frames)
    }

    /// Sends each following session what changed this turn of what it holds: coarse bricks its
    /// rule holds, then the level-0 bricks of regions it holds at level 0, as a `Delta` (empty
    /// when none: it still learns the sequence). Sessions whose data is the same share frames.
    pub(super) fn broadcast_follow(
        &mut self,
        touched: &[u32],
        changed: &Changed,
        from: u64,
        to: u64,
    ) {
        let ids: Vec<_> = self
            .subs
            .iter()
            .filter(|(_, s)| {
                s.follow.as_ref().is_some_and(|f| f.rule.is_some())
                    && !s.lagging
                    && s.awaits_levels.is_none()
            })
            .map(|(&id, _)| id)
            .collect();
        if ids.is_empty() {
            return;
        }
        let dims = self.map.region_dims();
        let mut cache: HashMap<(u32, Vec<u32>), Vec<Bytes>> = HashMap::new();
        for id in ids {
            let Some(rule) = self
                .subs
                .get(&id)
                .and_then(|s| s.follow.as_ref())
                .and_then(|f| f.rule)
            else {
                continue;
            };
            let mut wanted: Vec<(u32, Vec<u32>)> = Vec::new();
            for (k0, cells) in changed.iter().enumerate() {
                let k = k0 as u32 + 1;
                let Some(level) = self.levels.map_at(&self.map, k).filter(|_| k >= 2) else {
                    continue;
                };
                let mine: Vec<u32> = cells
                    .iter()
                    .copied()
                    .filter(|&i| rule.holds(dims, k, level.cell_coords(i)))
                    .collect();
                if !mine.is_empty() {
                    wanted.push((k, mine));
                }
            }
            let mine: Vec<u32> = touched
                .iter()
                .copied()
                .filter(|&i| rule.level_of(region_of(self.map.cell_coords(i))) == 0)
                .collect();
            wanted.push((0, mine));
            let mut frames = Vec::new();
            for key in wanted {
                if let Some(f) = cache.get(&key) {
                    frames.extend(f.iter().cloned());
                    continue;
                }
                let (level, cells) = (key.0, &key.1);
                let encoded = if level == 0 && cells.is_empty() {
                    let empty = ServerMsg::Delta {
                        from_seq: from,
                        to_seq: to,
                        bricks: BrickBlob::empty(),
                        removed: Vec::new(),
                    };
                    encode_server(&empty).map(|f| vec![Bytes::from(f)])
                } else if level == 0 {
                    let make = |bricks, removed| ServerMsg::Delta {
                        from_seq: from,
                        to_seq: to,
                        bricks,
                        removed,
                    };
                    self.encode_cells(0, cells, make)
                } else {
                    let make = |bricks, empty| ServerMsg::Coarse {
                        level,
                        bricks,
                        empty,
                    };
                    self.encode_cells(level, cells, make)
                };
                match encoded {
                    Ok(f) => {
                        frames.extend(f.iter().cloned());
                        cache.insert(key, f);
                    }
                    Err(e) => {
                        tracing::error!(scene = %self.name, error = %e, level, "could not encode a working set's delta; it starts again");
                        self.metrics.count_unencodable("Delta");
                        frames.clear();
                        if let Some(sub) = self.subs.get_mut(&id) {
                            sub.lagging = true;
                        }
                        break;
                    }
                }
            }
            let Some(sub) = self.subs.get_mut(&id) else {
                continue;
            };
            if sub.lagging {
                Metrics::add(&self.metrics.resyncs, 1);
                continue;
            }
            let bytes: usize = frames.iter().map(|f| f.len()).sum();
            let queued = sub.out.queued();
            if queued + bytes > self.config.max_queue_bytes
                || (queued > super::owner::SHORT_QUEUE
                    && sub.out.total_queued() + bytes > self.config.max_queued_total)
            {
                sub.lagging = true;
                Metrics::add(&self.metrics.resyncs, 1);
                continue;
            }
            Metrics::add(&self.metrics.deltas_sent, frames.len() as u64);
            for f in frames {
                sub.out.push(f);
            }
            sub.delivered = to;
        }
    }
}
