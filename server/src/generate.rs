//! A procedural world (`protocol::world`) made tile by tile on several threads and streamed
//! into the store as the tiles come, so a world is never held whole (`Store::begin_scene`).
//! `brickcast-server generate terrain` and the admin API's `create` both use it.

use std::sync::atomic::{AtomicU32, Ordering};

use brickcast_protocol::brick::BrickData;
use brickcast_protocol::map::MapError;
use brickcast_protocol::world::World;

use crate::store::{Store, StoreError};

#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    #[error("generating a tile: {0}")]
    Tile(#[from] MapError),
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// What a generated scene holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Generated {
    pub bricks: u64,
    pub solid_voxels: u64,
}

/// Writes `world` into `store` as the new scene `name`, generating on `threads` threads;
/// `progress(tiles done, bricks written)` after each tile. Until it returns `Ok` the scene
/// does not exist (see `Store::begin_scene`).
pub fn into_store(
    store: &Store,
    name: &str,
    world: &World,
    threads: usize,
    mut progress: impl FnMut(u32, u64),
) -> Result<Generated, GenerateError> {
    let mut writer = store.begin_scene(name, world.size())?;
    let mut tiles = 0;
    let solid_voxels = tiles_of(world, threads.max(1), |bricks| {
        writer.put(&bricks)?;
        tiles += 1;
        progress(tiles, writer.written());
        Ok(())
    })?;
    let bricks = writer.finish()?;
    Ok(Generated {
        bricks,
        solid_voxels,
    })
}

/// Makes every tile of `world` on `threads` threads and hands each tile's bricks to `write`
/// on this thread, in the order they are done. At most two tiles per thread wait to be
/// written, so memory stays a few tiles whatever the world's size. Returns the solid voxels.
fn tiles_of(
    world: &World,
    threads: usize,
    mut write: impl FnMut(Vec<BrickData>) -> Result<(), GenerateError>,
) -> Result<u64, GenerateError> {
    let [nx, nz] = world.tiles();
    let next = AtomicU32::new(0);
    let (tx, rx) = std::sync::mpsc::sync_channel::<Result<Vec<BrickData>, MapError>>(2 * threads);
    std::thread::scope(|scope| {
        for _ in 0..threads {
            let (tx, next) = (tx.clone(), &next);
            scope.spawn(move || {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= nx * nz {
                        return;
                    }
                    // A send fails only once the writer stopped (an error): stop too.
                    if tx.send(world.tile([i % nx, i / nx])).is_err() {
                        return;
                    }
                }
            });
        }
        drop(tx);
        let mut voxels = 0u64;
        for tile in rx {
            let bricks = tile?;
            voxels += bricks.iter().map(|b| b.colours.len() as u64).sum::<u64>();
            write(bricks)?;
        }
        Ok(voxels)
    })
}

/// `world` made whole in memory (a cluster stores a new scene from one map: `catalog`).
pub fn into_map(
    world: &World,
    threads: usize,
) -> Result<brickcast_protocol::BrickMap, GenerateError> {
    let mut map = brickcast_protocol::BrickMap::new(world.size())?;
    tiles_of(world, threads.max(1), |bricks| {
        for brick in &bricks {
            map.put_brick(brick)?;
        }
        Ok(())
    })?;
    map.rebuild_clearance();
    Ok(map)
}
