//! The scene's levels of detail, for sessions that view a coarser level (`/scenes/NAME@K/ws`).
//!
//! A level-K view is an ordinary read-only scene of `⌈size / 2^K⌉` voxels a side, level K of the
//! scene's mip pyramid (`protocol::lod`): its Welcome, sync, deltas, resume and resync are
//! level 0's, made from the level's own `BrickMap`, so every client (native, browser,
//! `render`) can open a world too large for it at a level it can hold.
//!
//! The pyramid is built when a scene larger than a browser viewer's default budget loads
//! ([`EAGER_ABOVE_BYTES`]), or else when a session first asks for a level or a working set,
//! **a part per turn** ([`BUILD_SLOTS_PER_TURN`] brick slots of the level below), level 1
//! from level 0, then level 2 from level 1, and so on, so edits and other clients go on
//! meanwhile: a 16384×512×16384 world takes a few hundred turns. Edits during the build
//! update what is built so far like any other turn (climbing into levels not yet built,
//! which their own pass recomputes), and the parts not yet folded in are read as they are
//! when their turn comes, so the finished pyramid is exactly the map's. Sessions
//! that asked meanwhile are welcomed at once and get their level's sync when it is done. The
//! pyramid is then kept for the scene's life, updated every turn from the cells the turn
//! touched, only where a coarse brick changes, before the turn's deltas go out. Scenes nobody
//! views coarsely pay nothing.

use brickcast_protocol::BrickMap;
use brickcast_protocol::lod::{Changed, Pyramid, level_count};
use brickcast_protocol::map::MapError;

/// Brick slots of level 0 folded into the pyramid per owner turn while it is being built.
pub const BUILD_SLOTS_PER_TURN: u32 = 32_768;

/// Levels a session may ask for in a scene of `size` voxels: 1 ..= this (0 when none).
pub fn levels_of(size: [u32; 3]) -> u32 {
    level_count(size)
}

/// A scene laid out larger than this gets its levels built as soon as it loads, before anyone
/// asks: a 256 MiB browser viewer (the page's default budget) holds only a working set of it,
/// and a working set needs the levels. Smaller scenes pay nothing until a level is asked for.
pub const EAGER_ABOVE_BYTES: u64 = 128 << 20;

/// The pyramid once someone asked for it.
#[derive(Default)]
pub(super) struct Levels {
    pyramid: Option<Pyramid>,
    /// While it is being built: the level being folded in, its next slot of the level below,
    /// and when the build began.
    building: Option<Build>,
    /// Slots folded in per turn ([`BUILD_SLOTS_PER_TURN`]; tests take smaller steps).
    step: Option<u32>,
    /// Level-0 regions' bytes in a working set, remembered for following cameras.
    costs: Option<brickcast_protocol::working_set::RegionCosts>,
}

/// How far a build is: level `level` (1 ..) is being made from the slots of the level below,
/// `next` the first not folded in yet.
#[derive(Clone, Copy)]
struct Build {
    level: u32,
    next: u32,
    started: std::time::Instant,
}

impl Levels {
    /// Starts building the pyramid of `map` unless it is built or being built. Its tombstone
    /// horizon is `seq`, so a client resuming a level from before gets a full resync (the
    /// fresh levels know no earlier removals).
    pub(super) fn start(&mut self, map: &BrickMap, seq: u64) -> Result<(), MapError> {
        if self.pyramid.is_none() {
            self.costs = Some(brickcast_protocol::working_set::RegionCosts::new(
                map.region_dims(),
            ));
            let mut pyramid = Pyramid::empty(map.size())?;
            pyramid.prune_tombstones(seq);
            self.pyramid = Some(pyramid);
            self.building = Some(Build {
                level: 1,
                next: 0,
                started: std::time::Instant::now(),
            });
        }
        Ok(())
    }

    /// Whether the levels are complete and current.
    pub(super) fn ready(&self) -> bool {
        self.pyramid.is_some() && self.building.is_none()
    }

    /// Whether a build is under way (the owner keeps turning until it is done).
    pub(super) fn building(&self) -> bool {
        self.building.is_some()
    }

    /// One turn's part of the build (the scene at sequence `seq`); true when this part finished
    /// it. Levels are made one after another, each from the finished level below (edits
    /// meanwhile keep what is built current through [`Levels::update`]), so each coarse brick
    /// is computed about once. A finished pyramid's tombstone horizon is `seq`: a coarse brick
    /// emptied during the build before it was folded in left no tombstone, so a client
    /// resuming a level from before the build finished must get a full resync.
    pub(super) fn advance(
        &mut self,
        map: &BrickMap,
        seq: u64,
        scene: &str,
    ) -> Result<bool, MapError> {
        let (Some(pyramid), Some(build)) = (&mut self.pyramid, self.building) else {
            return Ok(false);
        };
        let Build {
            mut level,
            mut next,
            started,
        } = build;
        let mut left = self.step.unwrap_or(BUILD_SLOTS_PER_TURN);
        // Small upper levels share a turn with the end of the one below.
        while left > 0 && level <= pyramid.level_count() {
            let below = if level == 1 {
                map
            } else {
                pyramid.level(level - 1).unwrap_or(map)
            };
            let slots = below.slot_count();
            let end = next.saturating_add(left).min(slots);
            let cells: Vec<u32> = below.slot_cells(next..end).collect();
            left -= end - next;
            pyramid.fold(map, level, &cells)?;
            if end < slots {
                next = end;
                break;
            }
            (level, next) = (level + 1, 0);
        }
        if level <= pyramid.level_count() {
            self.building = Some(Build {
                level,
                next,
                started,
            });
            return Ok(false);
        }
        self.building = None;
        pyramid.prune_tombstones(seq);
        tracing::info!(scene, levels = pyramid.level_count(), bricks = pyramid.brick_count(), took = ?started.elapsed(), "built the levels of detail");
        Ok(true)
    }

    /// After the map was replaced whole (a reload from the log): built again from the start if
    /// it was built or being built.
    pub(super) fn reset(&mut self, map: &BrickMap, seq: u64) -> Result<(), MapError> {
        if self.pyramid.take().is_some() {
            self.start(map, seq)?;
        }
        Ok(())
    }

    /// Level-0 regions' bytes, remembered (`None` before the levels were asked for).
    pub(super) fn costs(&self) -> Option<&brickcast_protocol::working_set::RegionCosts> {
        self.costs.as_ref()
    }

    /// The pyramid, once it is complete and current.
    pub(super) fn pyramid(&self) -> Option<&Pyramid> {
        self.pyramid.as_ref().filter(|_| self.ready())
    }

    /// Level `level` of the scene: `map` itself for 0; `None` for a level that is not complete.
    pub(super) fn map_at<'a>(&'a self, map: &'a BrickMap, level: u32) -> Option<&'a BrickMap> {
        match level {
            0 => Some(map),
            k if self.ready() => self.pyramid.as_ref()?.level(k),
            _ => None,
        }
    }

    /// Brings the levels (as far as they are built) up to date with the level-0 cells a turn
    /// touched; what changed per level (empty when there are no levels).
    pub(super) fn update(&mut self, map: &BrickMap, touched: &[u32]) -> Result<Changed, MapError> {
        if let Some(costs) = &self.costs {
            costs.forget_cells(map, touched);
        }
        match &mut self.pyramid {
            Some(pyramid) if !touched.is_empty() => pyramid.update(map, touched),
            _ => Ok(Changed::new()),
        }
    }

    /// Forgets removals at or before `seq` in every level, as level 0 does.
    pub(super) fn prune_tombstones(&mut self, seq: u64) {
        if let Some(pyramid) = &mut self.pyramid {
            pyramid.prune_tombstones(seq);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::map::BrushMode;
    use brickcast_protocol::{BrickMap, Colour};

    /// Edits that land between the parts of a build (touching parts built and parts not yet
    /// built) leave the finished levels equal to a pyramid built at once from the final map.
    #[test]
    fn a_build_spread_over_turns_with_edits_between_equals_one_built_at_once() {
        let mut map = BrickMap::new([96, 48, 96]).unwrap();
        map.record_touched(true);
        for i in 0..40u32 {
            let c = [(i * 37) % 96, (i * 11) % 40, (i * 53) % 96].map(|v| v as f32);
            map.sphere(
                c,
                3.0 + (i % 4) as f32,
                BrushMode::Fill,
                Colour(0x1111 * (i % 9) as u16),
            );
        }
        map.take_touched();
        let mut levels = Levels {
            step: Some(7),
            ..Levels::default()
        };
        levels.start(&map, 0).unwrap();
        assert!(levels.building() && !levels.ready());
        assert!(
            levels.map_at(&map, 1).is_none(),
            "no level before it is built"
        );
        let mut turn = 0u32;
        loop {
            turn += 1;
            map.set_sequence(u64::from(turn));
            let at = [(turn * 29) % 96, (turn * 7) % 48, (turn * 61) % 96].map(|v| v as f32);
            let mode = [BrushMode::Erase, BrushMode::Fill, BrushMode::Paint][turn as usize % 3];
            map.sphere(at, 4.0, mode, Colour(0xF800));
            let touched = map.take_touched();
            levels.update(&map, &touched).unwrap();
            if levels.advance(&map, u64::from(turn), "test").unwrap() {
                break;
            }
            assert!(turn < 10_000);
        }
        assert!(turn > 3, "the build took several turns ({turn})");
        assert!(levels.ready());
        let fresh = Pyramid::build(&map).unwrap();
        for k in 1..=fresh.level_count() {
            let want = fresh.level(k).unwrap();
            let got = levels.map_at(&map, k).unwrap();
            assert_eq!(got.content_hash(), want.content_hash(), "level {k}");
            assert_eq!(got.brick_count(), want.brick_count(), "level {k}");
        }
    }

    /// A scene larger than `eager_levels_bytes` starts its levels when it loads and builds
    /// them over turns nobody asked for, exactly as a build at once would; a smaller scene
    /// builds nothing until asked.
    #[test]
    fn a_large_scene_builds_its_levels_at_load() {
        use crate::scene::OwnerConfig;
        use crate::scene::jobs::testing::{Scene, open_with};
        let mut map = BrickMap::new([256, 32, 256]).unwrap();
        map.fill_box([0, 0, 0], [255, 9, 255], BrushMode::Fill, Colour(0x07E0));
        let scene = Scene::new(&map);
        let bytes = map.memory().total_bytes;
        let small = open_with(
            &scene.store,
            &scene.metrics,
            OwnerConfig {
                eager_levels_bytes: bytes,
                ..OwnerConfig::default()
            },
        );
        assert!(!small.levels.building() && !small.levels.ready());
        assert!(!small.has_ready_work(), "no build, no turns");
        drop(small);
        let mut owner = open_with(
            &scene.store,
            &scene.metrics,
            OwnerConfig {
                eager_levels_bytes: bytes - 1,
                ..OwnerConfig::default()
            },
        );
        owner.levels.step = Some(64);
        assert!(owner.levels.building() && owner.has_ready_work());
        let mut turns = 0;
        while owner.has_ready_work() {
            owner
                .step(Vec::new(), &mut crate::metrics::PhaseClock::start())
                .unwrap();
            turns += 1;
            assert!(turns < 1000, "the build ends");
        }
        assert!(
            owner.levels.ready() && turns > 2,
            "built over {turns} turns"
        );
        let fresh = Pyramid::build(&map).unwrap();
        for k in 1..=fresh.level_count() {
            let got = owner.levels.map_at(&owner.map, k).unwrap();
            assert_eq!(got.content_hash(), fresh.level(k).unwrap().content_hash());
        }
    }

    /// A coarse brick that an edit empties before the build folds it in leaves no tombstone, so
    /// a client holding the level from before the build (a restart, a reload) must not be
    /// patched from it: resumes from before the build finished get a full resync.
    #[test]
    fn resumes_from_before_a_build_finished_are_full_resyncs() {
        let mut map = BrickMap::new([64, 16, 64]).unwrap();
        map.record_touched(true);
        map.set_sequence(5);
        map.fill_box([0, 0, 0], [63, 3, 63], BrushMode::Fill, Colour(0x07E0));
        map.take_touched();
        let mut levels = Levels {
            step: Some(4),
            ..Levels::default()
        };
        levels.start(&map, 5).unwrap();
        assert!(!levels.advance(&map, 5, "test").unwrap());
        // Erase the far half, which the build has not reached yet.
        map.set_sequence(6);
        map.fill_box([0, 0, 32], [63, 3, 63], BrushMode::Erase, Colour(0));
        let touched = map.take_touched();
        levels.update(&map, &touched).unwrap();
        while !levels.advance(&map, 6, "test").unwrap() {}
        let one = levels.map_at(&map, 1).unwrap();
        assert!(
            one.changes_since(5).is_none(),
            "a copy from 5 would keep erased bricks"
        );
        assert!(one.changes_since(6).is_some());
    }
}
