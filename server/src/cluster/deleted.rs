//! Deleted scenes of a cluster, kept for a while so that a delete can be undone (the admin
//! API, `crate::admin`).
//!
//! Deleting takes the scene's entry out of the scene list (`brickcast_scenes`), so no node
//! opens it again and the nodes serving it close it (`served.rs`), and writes it back under
//! a key no scene name can be, `deleted=<unix ms>=<name>` (scene names have no `=`), with
//! when it is kept until. Its log stream and snapshots stay under its name: restoring puts the
//! entry back (under the same name: the stream is named after the scene), and a new scene of
//! that name is refused while the old one is kept. When the time is up any node drops the
//! stream, the snapshots and the entry ([`purge`], every minute; doing it twice is harmless).

use bytes::Bytes;
use serde::{Deserialize, Serialize};

use super::jet::{Bucket, Jet, PortError};
use super::{ClusterError, SceneEntry, catalog, snapshot};

const PREFIX: &str = "deleted=";

/// A deleted scene as the scene list keeps it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Deleted {
    /// What restoring it is called by.
    pub key: String,
    pub name: String,
    pub size: [u32; 3],
    /// Unix seconds.
    pub deleted_at: u64,
    pub kept_until: u64,
}

/// Whether a scene list key is a deleted scene's.
pub fn is_deleted_key(key: &str) -> bool {
    key.starts_with(PREFIX)
}

fn nats(what: &str) -> impl FnOnce(PortError) -> ClusterError + '_ {
    move |e| ClusterError::Nats(format!("{what}: {e}"))
}

/// Takes scene `name` out of the scene list, keeping it until `now + keep` (unix seconds).
pub async fn delete_keeping(
    jet: &impl Jet,
    name: &str,
    now_ms: u64,
    keep_s: u64,
) -> Result<Deleted, ClusterError> {
    let Some(entry) = catalog::scene_entry(jet, name).await? else {
        return Err(ClusterError::UnknownScene(name.into()));
    };
    let deleted = Deleted {
        key: format!("{PREFIX}{now_ms}={name}"),
        name: name.to_string(),
        size: entry.size,
        deleted_at: now_ms / 1000,
        kept_until: (now_ms / 1000).saturating_add(keep_s),
    };
    let value = serde_json::to_vec(&deleted)
        .map_err(|e| ClusterError::Nats(format!("deleted scene entry: {e}")))?;
    jet.kv_create(Bucket::Scenes, &deleted.key, Bytes::from(value))
        .await
        .map_err(nats("keeping the deleted scene"))?;
    jet.kv_delete(Bucket::Scenes, name, None)
        .await
        .map_err(nats("taking the scene out of the list"))?;
    Ok(deleted)
}

/// The deleted scenes still kept, oldest first.
pub async fn list(jet: &impl Jet) -> Result<Vec<Deleted>, ClusterError> {
    let keys = jet
        .kv_keys(Bucket::Scenes)
        .await
        .map_err(nats("listing scenes"))?;
    let mut out = Vec::new();
    for key in keys.into_iter().filter(|k| is_deleted_key(k)) {
        let Some(entry) = jet
            .kv_get(Bucket::Scenes, &key)
            .await
            .map_err(nats("reading a deleted scene"))?
        else {
            continue;
        };
        match serde_json::from_slice::<Deleted>(&entry.value) {
            Ok(d) if d.key == key => out.push(d),
            _ => tracing::warn!(key, "skipping an unreadable deleted scene entry"),
        }
    }
    out.sort_by_key(|d| (d.deleted_at, d.key.clone()));
    Ok(out)
}

/// The kept deleted scene named `name`, if any.
pub async fn kept_as(jet: &impl Jet, name: &str) -> Result<Option<Deleted>, ClusterError> {
    Ok(list(jet).await?.into_iter().find(|d| d.name == name))
}

/// Puts a deleted scene back in the scene list under its name.
pub async fn restore(jet: &impl Jet, key: &str) -> Result<Deleted, ClusterError> {
    let Some(deleted) = list(jet).await?.into_iter().find(|d| d.key == key) else {
        return Err(ClusterError::UnknownScene(key.into()));
    };
    let entry = SceneEntry { size: deleted.size };
    let value =
        serde_json::to_vec(&entry).map_err(|e| ClusterError::Nats(format!("scene entry: {e}")))?;
    match jet
        .kv_create(Bucket::Scenes, &deleted.name, Bytes::from(value))
        .await
    {
        Ok(_) => {}
        Err(PortError::Conflict(_)) => return Err(ClusterError::SceneExists(deleted.name)),
        Err(e) => return Err(nats("putting the scene back in the list")(e)),
    }
    jet.kv_delete(Bucket::Scenes, key, None)
        .await
        .map_err(nats("removing the deleted scene's entry"))?;
    Ok(deleted)
}

/// Drops the deleted scenes kept until before `now` (unix seconds): their logs, snapshots and
/// entries. Returns those dropped.
pub async fn purge(jet: &impl Jet, now: u64) -> Result<Vec<Deleted>, ClusterError> {
    let mut dropped = Vec::new();
    for d in list(jet).await? {
        if d.kept_until < now {
            drop_one(jet, &d).await?;
            dropped.push(d);
        }
    }
    Ok(dropped)
}

/// Drops the deleted scene kept as `key` now, for good.
pub async fn purge_key(jet: &impl Jet, key: &str) -> Result<Deleted, ClusterError> {
    let Some(d) = list(jet).await?.into_iter().find(|d| d.key == key) else {
        return Err(ClusterError::UnknownScene(key.into()));
    };
    drop_one(jet, &d).await?;
    Ok(d)
}

async fn drop_one(jet: &impl Jet, d: &Deleted) -> Result<(), ClusterError> {
    // The entry last: a purge cut short is done again by the next one.
    let _ = jet.delete_stream(&d.name).await;
    snapshot::delete_all(jet, &d.name).await;
    jet.kv_delete(Bucket::Scenes, &d.key, None)
        .await
        .map_err(nats("dropping a deleted scene's entry"))
}
