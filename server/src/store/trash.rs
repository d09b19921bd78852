//! Renaming scenes, and deleted scenes kept for a while so that a delete can be undone.
//!
//! A scene's rows live in tables named `<kind>/<scene>` (bricks, log, history, undo, ...).
//! Renaming a scene renames each of its tables and moves its `scenes` row, in one
//! transaction: no row is copied, so a world of gigabytes renames as fast as the demo.
//!
//! Deleting a scene through the admin API does not drop its tables: it renames them under a
//! key that no scene name can take (`deleted=<unix ms>=<name>`: scene names have no `=`; the
//! cluster's keys look the same, `crate::cluster::deleted`)
//! and records the scene's metadata and how long it is kept in the `deleted` table. Until
//! then it can be restored under its name or another; afterwards
//! [`Store::purge_deleted`] drops its tables. Stores written before this table existed have
//! none: nothing was deleted this way. An older server ignores the table and the kept
//! tables (it reads only the tables of the scenes it lists).

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use redb::{Durability, ReadableDatabase, ReadableTable, TableDefinition, TableHandle};
use serde::{Deserialize, Serialize};

use super::{SCENES, SceneMeta, Store, StoreError, valid_scene_name};

/// Deleted scene's key → bincode [`Deleted`].
const DELETED: TableDefinition<&str, &[u8]> = TableDefinition::new("deleted");

/// A deleted scene kept for restoring.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Deleted {
    /// What restoring it is called by (`deleted=<unix ms>=<name>`).
    pub key: String,
    /// The scene's name when it was deleted.
    pub name: String,
    pub meta: SceneMeta,
    /// Unix seconds.
    pub deleted_at: u64,
    /// Unix seconds after which [`Store::purge_deleted`] drops it.
    pub kept_until: u64,
}

fn unix_now() -> Duration {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
}

impl Store {
    /// Renames scene `from` to `to` (its rows move with it). The scene must not be served
    /// while this runs: its owner writes to the tables by name.
    pub fn rename_scene(&self, from: &str, to: &str) -> Result<(), StoreError> {
        if !valid_scene_name(to) {
            return Err(StoreError::BadName(to.into()));
        }
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        let meta = {
            let mut scenes = txn.open_table(SCENES)?;
            if scenes.get(to)?.is_some() {
                return Err(StoreError::SceneExists(to.into()));
            }
            let bytes = match scenes.remove(from)? {
                Some(bytes) => bytes.value().to_vec(),
                None => return Err(StoreError::UnknownScene(from.into())),
            };
            scenes.insert(to, bytes.as_slice())?;
            bytes
        };
        self.decode_meta(from, &meta)?;
        rename_tables(&txn, from, to)?;
        self.forget_packs(from);
        self.forget_packs(to);
        txn.commit()?;
        Ok(())
    }

    /// Takes a scene out of the store's scene list and keeps it for `keep` (see the module).
    /// The scene must not be served while this runs.
    pub fn delete_keeping(&self, name: &str, keep: Duration) -> Result<Deleted, StoreError> {
        let now = unix_now();
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        let deleted = {
            let mut scenes = txn.open_table(SCENES)?;
            let meta = match scenes.remove(name)? {
                Some(bytes) => self.decode_meta(name, bytes.value())?,
                None => return Err(StoreError::UnknownScene(name.into())),
            };
            let mut table = txn.open_table(DELETED)?;
            // Two deletes of one name in one millisecond get different keys.
            let mut ms = now.as_millis();
            let mut key = format!("deleted={ms}={name}");
            while table.get(key.as_str())?.is_some() {
                ms += 1;
                key = format!("deleted={ms}={name}");
            }
            let deleted = Deleted {
                key,
                name: name.to_string(),
                meta,
                deleted_at: now.as_secs(),
                kept_until: now.as_secs().saturating_add(keep.as_secs()),
            };
            let bytes = super::ROW
                .encode(&deleted)
                .map_err(|e| corrupt(name, e.to_string()))?;
            table.insert(deleted.key.as_str(), bytes.as_slice())?;
            deleted
        };
        rename_tables(&txn, name, &deleted.key)?;
        self.forget_packs(name);
        txn.commit()?;
        Ok(deleted)
    }

    /// Deleted scenes still kept, oldest first.
    pub fn deleted(&self) -> Result<Vec<Deleted>, StoreError> {
        let txn = self.db.begin_read()?;
        let table = match txn.open_table(DELETED) {
            Ok(table) => table,
            Err(redb::TableError::TableDoesNotExist(_)) => return Ok(Vec::new()),
            Err(e) => return Err(e.into()),
        };
        let mut out = Vec::new();
        for row in table.iter()? {
            let (key, bytes) = row?;
            out.push(decode_deleted(key.value(), bytes.value())?);
        }
        out.sort_by_key(|d| (d.deleted_at, d.key.clone()));
        Ok(out)
    }

    /// Puts a deleted scene back under `name`. Returns its metadata.
    pub fn restore_deleted(&self, key: &str, name: &str) -> Result<SceneMeta, StoreError> {
        if !valid_scene_name(name) {
            return Err(StoreError::BadName(name.into()));
        }
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        let meta = {
            let mut table = txn.open_table(DELETED)?;
            let deleted = match table.remove(key)? {
                Some(bytes) => decode_deleted(key, bytes.value())?,
                None => return Err(StoreError::UnknownScene(key.into())),
            };
            let mut scenes = txn.open_table(SCENES)?;
            if scenes.get(name)?.is_some() {
                return Err(StoreError::SceneExists(name.into()));
            }
            scenes.insert(name, deleted.meta.bytes(name)?.as_slice())?;
            deleted.meta
        };
        rename_tables(&txn, key, name)?;
        self.forget_packs(name);
        txn.commit()?;
        Ok(meta)
    }

    /// Drops the deleted scenes kept until before `now` (unix seconds; `u64::MAX`: all of
    /// them). Returns what was dropped.
    pub fn purge_deleted(&self, now: u64) -> Result<Vec<Deleted>, StoreError> {
        self.drop_deleted(|d| d.kept_until < now)
    }

    /// Drops the deleted scene kept as `key` now, for good.
    pub fn drop_kept(&self, key: &str) -> Result<Deleted, StoreError> {
        self.drop_deleted(|d| d.key == key)?
            .pop()
            .ok_or_else(|| StoreError::UnknownScene(key.into()))
    }

    /// Drops the deleted scenes `which` picks: their entries and every table they had.
    fn drop_deleted(&self, which: impl Fn(&Deleted) -> bool) -> Result<Vec<Deleted>, StoreError> {
        let expired: Vec<Deleted> = self.deleted()?.into_iter().filter(which).collect();
        if expired.is_empty() {
            return Ok(expired);
        }
        let mut txn = self.db.begin_write()?;
        txn.set_durability(Durability::Immediate)?;
        {
            let mut table = txn.open_table(DELETED)?;
            for d in &expired {
                table.remove(d.key.as_str())?;
            }
        }
        for name in scene_tables(
            &txn,
            &expired.iter().map(|d| d.key.as_str()).collect::<Vec<_>>(),
        )? {
            txn.delete_table(TableDefinition::<u64, u64>::new(&name))?;
        }
        txn.commit()?;
        Ok(expired)
    }

    /// Unix seconds now, as [`Deleted`] counts them.
    pub fn unix_seconds() -> u64 {
        unix_now().as_secs()
    }
}

fn corrupt(scene: &str, detail: String) -> StoreError {
    StoreError::Corrupt {
        scene: scene.into(),
        detail,
    }
}

fn decode_deleted(key: &str, bytes: &[u8]) -> Result<Deleted, StoreError> {
    super::ROW
        .decode_prefix(bytes)
        .map(|(d, _)| d)
        .map_err(|e| corrupt(key, format!("deleted scene entry: {e}")))
}

/// The names of the tables holding the rows of any of `scenes` (`<kind>/<scene>`).
fn scene_tables(txn: &redb::WriteTransaction, scenes: &[&str]) -> Result<Vec<String>, StoreError> {
    Ok(txn
        .list_tables()?
        .map(|t| t.name().to_string())
        .filter(|name| {
            name.split_once('/')
                .is_some_and(|(_, scene)| scenes.contains(&scene))
        })
        .collect())
}

/// Renames every table of scene `from` to the same kind of table of `to`.
fn rename_tables(txn: &redb::WriteTransaction, from: &str, to: &str) -> Result<(), StoreError> {
    for name in scene_tables(txn, &[from])? {
        let kind = name.split_once('/').map_or("", |(kind, _)| kind);
        let new = format!("{kind}/{to}");
        // Untyped: renaming reads no rows.
        txn.rename_table(
            TableDefinition::<u64, u64>::new(&name),
            TableDefinition::<u64, u64>::new(&new),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use brickcast_protocol::wire::EditOp;
    use brickcast_protocol::{BrushMode, Colour};

    use super::*;
    use crate::record::LogRecord;
    use crate::scene::history::HistoryWrites;

    /// A scene with a snapshot and a log entry after it.
    fn scene(store: &Store, name: &str) -> u64 {
        let mut map = brickcast_protocol::BrickMap::new([64, 32, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 3, 63], BrushMode::Fill, Colour::WHITE);
        store.create_scene(name, &map).unwrap();
        let op = EditOp::Set {
            pos: [5, 10, 5],
            colour: Colour::from_rgb8(255, 0, 0),
        };
        let record = LogRecord::Ops {
            user: 1,
            ops: vec![op],
        };
        store
            .append(name, &[(1, record)], &HistoryWrites::default())
            .unwrap();
        store.load_scene(name).unwrap().map.content_hash()
    }

    fn tables(store: &Store) -> Vec<String> {
        let txn = store.db.begin_write().unwrap();
        let names = txn
            .list_tables()
            .unwrap()
            .map(|t| t.name().to_string())
            .collect();
        txn.abort().unwrap();
        names
    }

    #[test]
    fn a_scene_renames_and_a_deleted_one_is_kept_restored_or_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let hash = scene(&store, "a");
        scene(&store, "b");

        assert!(matches!(
            store.rename_scene("a", "b"),
            Err(StoreError::SceneExists(_))
        ));
        assert!(matches!(
            store.rename_scene("nope", "c"),
            Err(StoreError::UnknownScene(_))
        ));
        assert!(matches!(
            store.rename_scene("a", "~x"),
            Err(StoreError::BadName(_))
        ));
        store.rename_scene("a", "c").unwrap();
        let loaded = store.load_scene("c").unwrap();
        assert_eq!(
            (loaded.seq, loaded.map.content_hash()),
            (1, hash),
            "log and bricks moved"
        );
        assert!(matches!(
            store.load_scene("a"),
            Err(StoreError::UnknownScene(_))
        ));
        assert!(
            !tables(&store).iter().any(|t| t.ends_with("/a")),
            "{:?}",
            tables(&store)
        );

        let kept = store
            .delete_keeping("c", Duration::from_secs(3600))
            .unwrap();
        assert_eq!(kept.name, "c");
        assert!(kept.key.starts_with("deleted=") && kept.kept_until >= kept.deleted_at + 3600);
        let names: Vec<String> = store
            .scenes()
            .unwrap()
            .into_iter()
            .map(|(n, _)| n)
            .collect();
        assert_eq!(names, ["b"]);
        assert_eq!(store.deleted().unwrap(), std::slice::from_ref(&kept));
        // Kept scenes survive a reopen, and a restore under a taken name is refused.
        drop(store);
        let store = Store::open(dir.path()).unwrap();
        assert!(matches!(
            store.restore_deleted(&kept.key, "b"),
            Err(StoreError::SceneExists(_))
        ));
        assert!(matches!(
            store.restore_deleted("deleted=1=zz", "d"),
            Err(StoreError::UnknownScene(_))
        ));
        store.restore_deleted(&kept.key, "d").unwrap();
        let loaded = store.load_scene("d").unwrap();
        assert_eq!((loaded.seq, loaded.map.content_hash()), (1, hash));
        assert!(store.deleted().unwrap().is_empty());

        // Only what is past its time is dropped, with every table it had.
        let soon = store.delete_keeping("d", Duration::ZERO).unwrap();
        let later = store
            .delete_keeping("b", Duration::from_secs(3600))
            .unwrap();
        assert!(store.purge_deleted(soon.kept_until).unwrap().is_empty());
        let dropped = store.purge_deleted(soon.kept_until + 1).unwrap();
        assert_eq!(dropped, std::slice::from_ref(&soon));
        assert_eq!(store.deleted().unwrap(), std::slice::from_ref(&later));
        let left = tables(&store);
        assert!(!left.iter().any(|t| t.contains(&soon.key)), "{left:?}");
        assert!(left.iter().any(|t| t.contains(&later.key)), "{left:?}");
        // A new scene of a deleted scene's name starts empty of the old one's rows.
        scene(&store, "b");
        assert_eq!(store.load_scene("b").unwrap().seq, 1);
        // One kept scene dropped at once, by its key.
        assert_eq!(store.drop_kept(&later.key).unwrap(), later);
        assert!(store.deleted().unwrap().is_empty());
        assert!(matches!(
            store.drop_kept(&later.key),
            Err(StoreError::UnknownScene(_))
        ));
        assert!(!tables(&store).iter().any(|t| t.contains(&later.key)));
    }
}
