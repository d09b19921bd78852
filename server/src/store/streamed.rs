//! A new scene written brick batch by brick batch (`brickcast-server generate`), for scenes too
//! large to build as one map first.
//!
//! [`Store::create_scene`] writes a map it holds in one transaction. A generated world of
//! millions of bricks is never held whole: its tiles arrive one by one and go to the store as
//! they come. The rows are written in transactions of [`ROWS_PER_COMMIT`] that are not made
//! durable on their own (`Durability::None`), and the scene's metadata row, which is what makes
//! a scene exist, goes in last, in a durable commit that also makes every earlier one durable.
//! So a crash or an error midway leaves no scene at all, only rows under a name no scene has,
//! which the next writer of that name clears first.

use brickcast_protocol::BrickMap;
use brickcast_protocol::brick::BrickData;
use redb::{Durability, ReadableTable, TableDefinition, WriteTransaction};

use super::{
    SCENES, SceneMeta, Store, StoreError, bricks_table, encode_row, log_table, valid_scene_name,
};

/// Rows per intermediate commit: bounds what one transaction holds in memory.
pub const ROWS_PER_COMMIT: usize = 1 << 16;

/// A scene being written: [`SceneWriter::put`] batches of bricks, then
/// [`SceneWriter::finish`]. Dropped unfinished, the scene does not exist.
pub struct SceneWriter<'a> {
    store: &'a Store,
    name: String,
    /// An empty map of the scene's size: it checks bricks and numbers cells as the scene will
    /// (its region array is all it holds: 16 MiB for a 16384×512×16384 world).
    shape: BrickMap,
    txn: Option<WriteTransaction>,
    uncommitted: usize,
    written: u64,
    row: Vec<u8>,
}

impl Store {
    /// Starts a new scene `name` of `size` voxels, to be written in batches. Fails at once if
    /// the name is invalid or taken, or the size is not a scene's; clears rows a writer of the
    /// same name left behind unfinished.
    pub fn begin_scene(&self, name: &str, size: [u32; 3]) -> Result<SceneWriter<'_>, StoreError> {
        if !valid_scene_name(name) {
            return Err(StoreError::BadName(name.into()));
        }
        let shape = BrickMap::new(size).map_err(|e| StoreError::BadBrick {
            scene: name.into(),
            cell: [0; 3],
            detail: e.to_string(),
        })?;
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        let exists = txn.open_table(SCENES)?.get(name)?.is_some();
        if exists {
            return Err(StoreError::SceneExists(name.into()));
        }
        txn.delete_table(TableDefinition::<u32, &[u8]>::new(&bricks_table(name)))?;
        txn.delete_table(TableDefinition::<u64, &[u8]>::new(&log_table(name)))?;
        txn.delete_table(TableDefinition::<u32, &[u8]>::new(&super::palette_table(
            name,
        )))?;
        super::history_rows::delete_all(&txn, name)?;
        super::past::delete_all(&txn, name)?;
        self.forget_packs(name);
        txn.commit()?;
        Ok(SceneWriter {
            store: self,
            name: name.into(),
            shape,
            txn: None,
            uncommitted: 0,
            written: 0,
            row: Vec::with_capacity(64 + 1024),
        })
    }
}

impl SceneWriter<'_> {
    /// Writes `bricks` (cells in scene coordinates). Each is checked as a scene would hold it:
    /// inside the scene, voxels and colours agreeing; a cell written twice keeps the later one.
    pub fn put(&mut self, bricks: &[BrickData]) -> Result<(), StoreError> {
        for brick in bricks {
            self.check(brick)?;
        }
        let txn = match &mut self.txn {
            Some(txn) => txn,
            txn @ None => {
                let mut t = self.store.db.begin_write()?;
                t.set_durability(Durability::None)?;
                txn.insert(t)
            }
        };
        {
            let mut table = txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_table(
                &self.name,
            )))?;
            for brick in bricks {
                let index = self.shape.cell_index(brick.cell);
                encode_row(&brick.mask, &brick.colours, &mut self.row);
                table.insert(index, self.row.as_slice())?;
            }
        }
        self.uncommitted += bricks.len();
        self.written += bricks.len() as u64;
        if self.uncommitted >= ROWS_PER_COMMIT
            && let Some(txn) = self.txn.take()
        {
            txn.commit()?;
            self.uncommitted = 0;
        }
        Ok(())
    }

    /// Bricks written so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Makes the scene exist, durably, with everything written as its snapshot at sequence 0.
    /// Returns the bricks written.
    pub fn finish(mut self) -> Result<u64, StoreError> {
        let mut txn = match self.txn.take() {
            Some(txn) => txn,
            None => self.store.db.begin_write()?,
        };
        txn.set_durability(Durability::Immediate)?;
        {
            let mut scenes = txn.open_table(SCENES)?;
            if scenes.get(self.name.as_str())?.is_some() {
                return Err(StoreError::SceneExists(self.name.clone()));
            }
            let meta = SceneMeta {
                size: self.shape.size(),
                snapshot_seq: 0,
            };
            scenes.insert(self.name.as_str(), meta.bytes(&self.name)?.as_slice())?;
            txn.open_table(TableDefinition::<u32, &[u8]>::new(&bricks_table(
                &self.name,
            )))?;
            txn.open_table(TableDefinition::<u64, &[u8]>::new(&log_table(&self.name)))?;
        }
        txn.commit()?;
        Ok(self.written)
    }

    fn check(&self, brick: &BrickData) -> Result<(), StoreError> {
        self.shape
            .check_brick(brick)
            .map_err(|e| StoreError::BadBrick {
                scene: self.name.clone(),
                cell: brick.cell,
                detail: e.to_string(),
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::brick::EMPTY_MASK;
    use brickcast_protocol::world::World;

    #[test]
    fn a_streamed_world_loads_as_built_whole_and_an_unfinished_one_does_not_exist() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let world = World::new([300, 64, 260], 3).unwrap();
        // A writer dropped midway: no scene, and its rows do not leak into the next one.
        let mut w = store.begin_scene("w", world.size()).unwrap();
        w.put(&world.tile([0, 0]).unwrap()).unwrap();
        drop(w);
        assert!(store.scenes().unwrap().is_empty());
        let mut w = store.begin_scene("w", world.size()).unwrap();
        for tile in [[1, 1], [0, 1], [1, 0]] {
            w.put(&world.tile(tile).unwrap()).unwrap();
        }
        let bad = BrickData {
            cell: [999, 0, 0],
            mask: EMPTY_MASK,
            colours: Vec::new(),
        };
        assert!(matches!(w.put(&[bad]), Err(StoreError::BadBrick { .. })));
        w.finish().unwrap();
        let loaded = store.load_scene("w").unwrap();
        let whole = world.map().unwrap();
        assert_ne!(
            loaded.map.content_hash(),
            whole.content_hash(),
            "tile (0, 0) was only in the dropped writer"
        );
        assert!(matches!(
            store.begin_scene("w", world.size()),
            Err(StoreError::SceneExists(_))
        ));
        store.delete_scene("w").unwrap();
        let mut w = store.begin_scene("w", world.size()).unwrap();
        for tile in [[1, 1], [0, 1], [1, 0], [0, 0]] {
            w.put(&world.tile(tile).unwrap()).unwrap();
        }
        w.finish().unwrap();
        let loaded = store.load_scene("w").unwrap();
        assert_eq!(loaded.map.content_hash(), whole.content_hash());
        assert_eq!(loaded.map.brick_count(), whole.brick_count());
    }
}
