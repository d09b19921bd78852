//! Deleted scenes of a cluster, kept for a while so that a delete can be undone (the admin
//! API, `crate::admin`).
//!
//! Deleting takes the scene's entry out of the scene list (`brickcast_scenes`), so no node
//! opens it again and the nodes serving it close it (`served.rs`), and writes it back under
//! a key no scene name can be, `deleted=<unix ms>=<name>` (scene names have no `=`), with
//! when it is kept until. Its log stream and snapshots stay under its log key
//! ([`SceneEntry`]): restoring puts the entry back, under its name or another, and a new
//! scene may take the name meanwhile (it gets a log key of its own). When the time is up any
//! node drops the entry, then the stream and snapshots ([`purge`], every minute; doing it
//! twice is harmless). Every step that takes an entry away does so only at the revision it
//! read (compare-and-set), so two nodes acting on one scene at once never both succeed: the
//! loser undoes what it wrote and says so.

use bytes::Bytes;
use serde::{Deserialize, Serialize};

use super::entry::Size;
use super::jet::{Bucket, Jet, PortError};
use super::{ClusterError, SceneEntry, catalog};

const PREFIX: &str = "deleted=";

/// A deleted scene as the scene list keeps it (its size and log key in the shape of
/// [`SceneEntry`]'s: a node from before log keys cannot read one whose key is not its name,
/// so it never purges the log named after it — someone else's).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "Raw", into = "Raw")]
pub struct Deleted {
    /// What restoring it is called by.
    pub key: String,
    pub name: String,
    pub size: [u32; 3],
    /// Unix seconds.
    pub deleted_at: u64,
    pub kept_until: u64,
    /// Its log key (`None`: its name).
    pub log: Option<String>,
}

/// A deleted scene's entry as JSON holds it.
#[derive(Serialize, Deserialize)]
struct Raw {
    key: String,
    name: String,
    size: Size,
    deleted_at: u64,
    kept_until: u64,
}

impl From<Raw> for Deleted {
    fn from(raw: Raw) -> Deleted {
        let (size, log) = raw.size.parts();
        Deleted {
            key: raw.key,
            name: raw.name,
            size,
            deleted_at: raw.deleted_at,
            kept_until: raw.kept_until,
            log,
        }
    }
}

impl From<Deleted> for Raw {
    fn from(d: Deleted) -> Raw {
        Raw {
            size: Size::of(d.size, d.log.as_deref(), &d.name),
            key: d.key,
            name: d.name,
            deleted_at: d.deleted_at,
            kept_until: d.kept_until,
        }
    }
}

impl Deleted {
    /// The key its log, snapshots and lease go by.
    pub fn log_key(&self) -> &str {
        self.log.as_deref().unwrap_or(&self.name)
    }
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
    let Some((entry, revision)) = catalog::scene_entry_at(jet, name).await? else {
        return Err(ClusterError::UnknownScene(name.into()));
    };
    let deleted = Deleted {
        key: format!("{PREFIX}{now_ms}={name}"),
        name: name.to_string(),
        size: entry.size,
        deleted_at: now_ms / 1000,
        kept_until: (now_ms / 1000).saturating_add(keep_s),
        log: entry.log.clone(),
    };
    let value = serde_json::to_vec(&deleted)
        .map_err(|e| ClusterError::Nats(format!("deleted scene entry: {e}")))?;
    let kept = jet
        .kv_create(Bucket::Scenes, &deleted.key, Bytes::from(value))
        .await
        .map_err(nats("keeping the deleted scene"))?;
    match jet.kv_delete(Bucket::Scenes, name, Some(revision)).await {
        Ok(()) => Ok(deleted),
        Err(e) => {
            // Changed through another node since it was read: keep nothing twice.
            let _ = jet
                .kv_delete(Bucket::Scenes, &deleted.key, Some(kept))
                .await;
            Err(match e {
                PortError::Conflict(_) | PortError::NotFound(_) => catalog::changed_meanwhile(name),
                e => nats("taking the scene out of the list")(e),
            })
        }
    }
}

/// The deleted scenes still kept, oldest first.
pub async fn list(jet: &impl Jet) -> Result<Vec<Deleted>, ClusterError> {
    Ok(list_at(jet).await?.into_iter().map(|(d, _)| d).collect())
}

/// [`list`] with each entry's revision.
async fn list_at(jet: &impl Jet) -> Result<Vec<(Deleted, u64)>, ClusterError> {
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
            Ok(d) if d.key == key => out.push((d, entry.revision)),
            _ => tracing::warn!(key, "skipping an unreadable deleted scene entry"),
        }
    }
    out.sort_by_key(|(d, _)| (d.deleted_at, d.key.clone()));
    Ok(out)
}

/// The kept deleted scene named `name`, if any.
pub async fn kept_as(jet: &impl Jet, name: &str) -> Result<Option<Deleted>, ClusterError> {
    Ok(list(jet).await?.into_iter().find(|d| d.name == name))
}

/// Puts a deleted scene back in the scene list, under `name` (its own name when `None`).
/// Returns it as it was kept, and the name it is served under now.
pub async fn restore(
    jet: &impl Jet,
    key: &str,
    name: Option<&str>,
) -> Result<(Deleted, String), ClusterError> {
    let Some((deleted, revision)) = list_at(jet).await?.into_iter().find(|(d, _)| d.key == key)
    else {
        return Err(ClusterError::UnknownScene(key.into()));
    };
    let name = name.unwrap_or(&deleted.name).to_string();
    if !crate::store::valid_scene_name(&name) {
        return Err(ClusterError::Nats(format!(
            "scene name {name:?} is invalid"
        )));
    }
    let entry = SceneEntry::new(&name, deleted.size, deleted.log_key());
    catalog::put_new(jet, &name, &entry).await?;
    match jet.kv_delete(Bucket::Scenes, key, Some(revision)).await {
        Ok(()) => Ok((deleted, name)),
        Err(e) => {
            // Purged or restored through another node meanwhile: the scene is not put back.
            if let Ok(Some((_, new))) = catalog::scene_entry_at(jet, &name).await {
                let _ = jet.kv_delete(Bucket::Scenes, &name, Some(new)).await;
            }
            Err(match e {
                PortError::Conflict(_) | PortError::NotFound(_) => ClusterError::Busy(format!(
                    "the deleted scene {key} was purged or restored through another node meanwhile"
                )),
                e => nats("removing the deleted scene's entry")(e),
            })
        }
    }
}

/// Drops the deleted scenes kept until before `now` (unix seconds): their logs, snapshots and
/// entries. Returns those dropped.
pub async fn purge(jet: &impl Jet, now: u64) -> Result<Vec<Deleted>, ClusterError> {
    let mut dropped = Vec::new();
    for (d, revision) in list_at(jet).await? {
        if d.kept_until < now && drop_one(jet, &d, revision).await? {
            dropped.push(d);
        }
    }
    Ok(dropped)
}

/// Drops the deleted scene kept as `key` now, for good.
pub async fn purge_key(jet: &impl Jet, key: &str) -> Result<Deleted, ClusterError> {
    let Some((d, revision)) = list_at(jet).await?.into_iter().find(|(d, _)| d.key == key) else {
        return Err(ClusterError::UnknownScene(key.into()));
    };
    if !drop_one(jet, &d, revision).await? {
        return Err(ClusterError::Busy(format!(
            "the deleted scene {key} was purged or restored through another node meanwhile"
        )));
    }
    Ok(d)
}

/// Drops a kept scene: its entry first, at the revision read (so a restore through another
/// node meanwhile wins, and this one does nothing: false), then its log and snapshots unless
/// a live scene or another kept one uses its key. A purge cut short after its entry leaves
/// the log behind (disk, never a scene without its log).
async fn drop_one(jet: &impl Jet, d: &Deleted, revision: u64) -> Result<bool, ClusterError> {
    match jet.kv_delete(Bucket::Scenes, &d.key, Some(revision)).await {
        Ok(()) => {}
        Err(PortError::Conflict(_) | PortError::NotFound(_)) => return Ok(false),
        Err(e) => return Err(nats("dropping a deleted scene's entry")(e)),
    }
    let key = d.log_key();
    let kept_elsewhere = list(jet).await?.iter().any(|o| o.log_key() == key);
    if !kept_elsewhere && !catalog::log_key_live(jet, key).await? {
        catalog::drop_log(jet, key).await;
    }
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kept_entries_from_before_log_keys_load_and_new_ones_round_trip() {
        let old = r#"{"key":"deleted=5=isle","name":"isle","size":[8,8,8],"deleted_at":5,"kept_until":9}"#;
        let d: Deleted = serde_json::from_str(old).unwrap();
        assert_eq!((d.log_key(), d.size), ("isle", [8, 8, 8]));
        let keyed = Deleted {
            log: Some("isle=3".into()),
            ..d
        };
        let text = serde_json::to_string(&keyed).unwrap();
        assert_eq!(serde_json::from_str::<Deleted>(&text).unwrap(), keyed);
        assert!(text.contains(r#""log":"isle=3""#), "{text}");
    }
}
