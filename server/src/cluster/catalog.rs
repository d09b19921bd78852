//! The cluster's scene list (`brickcast_scenes`), and adding a scene to it.

use brickcast_protocol::BrickMap;
use bytes::Bytes;

use super::jet::{Bucket, Jet, PortError};
use super::{ClusterError, SceneEntry, log, snapshot};

/// The cluster's scenes, sorted.
pub async fn scene_names(jet: &impl Jet) -> Result<Vec<String>, ClusterError> {
    let mut names = jet
        .kv_keys(Bucket::Scenes)
        .await
        .map_err(|e| ClusterError::Nats(format!("listing scenes: {e}")))?;
    // Deleted scenes kept for a while share the bucket under keys no scene name can be.
    names.retain(|n| !super::deleted::is_deleted_key(n));
    names.sort();
    Ok(names)
}

/// What the scene list says of one scene; `None` when the cluster has no such scene.
pub async fn scene_entry(jet: &impl Jet, name: &str) -> Result<Option<SceneEntry>, ClusterError> {
    Ok(scene_entry_at(jet, name).await?.map(|(entry, _)| entry))
}

/// [`scene_entry`] with the entry's revision, for a change that must not undo another
/// node's change made meanwhile (compare-and-set).
pub async fn scene_entry_at(
    jet: &impl Jet,
    name: &str,
) -> Result<Option<(SceneEntry, u64)>, ClusterError> {
    if !crate::store::valid_scene_name(name) {
        return Ok(None);
    }
    let Some(entry) = jet
        .kv_get(Bucket::Scenes, name)
        .await
        .map_err(|e| ClusterError::Nats(format!("reading the scene list: {e}")))?
    else {
        return Ok(None);
    };
    serde_json::from_slice(&entry.value)
        .map(|e| Some((e, entry.revision)))
        .map_err(|e| ClusterError::Nats(format!("the scene list's entry for {name}: {e}")))
}

/// Someone changed the scene list under a change of this node's: nothing of it is left.
pub(super) fn changed_meanwhile(name: &str) -> ClusterError {
    ClusterError::Busy(format!(
        "scene {name} was changed through another node meanwhile; nothing was done: look again and retry"
    ))
}

/// Every log key the scene list uses, live scenes' and kept deleted scenes' alike.
async fn log_keys_in_use(jet: &impl Jet) -> Result<Vec<String>, ClusterError> {
    let mut keys = Vec::new();
    for name in scene_names(jet).await? {
        if let Some(entry) = scene_entry(jet, &name).await? {
            keys.push(entry.log_key(&name).to_string());
        }
    }
    for kept in super::deleted::list(jet).await? {
        keys.push(kept.log_key().to_string());
    }
    Ok(keys)
}

/// Whether a live scene (not a kept deleted one) uses log key `key`.
pub async fn log_key_live(jet: &impl Jet, key: &str) -> Result<bool, ClusterError> {
    for name in scene_names(jet).await? {
        if scene_entry(jet, &name)
            .await?
            .is_some_and(|e| e.log_key(&name) == key)
        {
            return Ok(true);
        }
    }
    Ok(false)
}

/// A log key for a new scene `name`: its name when no scene (live or kept deleted) uses that
/// key, else `name=<unix ms>` (no scene name holds `=`, so it is nobody's name either).
pub async fn fresh_log_key(
    jet: &impl Jet,
    name: &str,
    now_ms: u64,
) -> Result<String, ClusterError> {
    let used = log_keys_in_use(jet).await?;
    if !used.iter().any(|k| k == name) {
        return Ok(name.to_string());
    }
    let mut at = now_ms;
    loop {
        let key = format!("{name}={at}");
        if !used.contains(&key) {
            return Ok(key);
        }
        at += 1;
    }
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Adds a scene to the cluster: its stream, a first snapshot, then its entry in the scene
/// list (last, so no node opens a scene that is not complete). A deleted scene kept under the
/// same name keeps its own log: the new scene gets a log key of its own ([`fresh_log_key`]).
/// `replace` replaces a scene of that name for good (`import --replace`): the new log is
/// made first under a key of its own, the entry is switched to it in one compare-and-set
/// (nodes serving the old scene close it when they see the entry name another log), then
/// the old log and snapshots are dropped.
pub async fn create_scene(
    jet: &impl Jet,
    name: &str,
    map: &BrickMap,
    replace: bool,
) -> Result<(), ClusterError> {
    if !crate::store::valid_scene_name(name) {
        return Err(ClusterError::Nats(format!(
            "scene name {name:?} is invalid"
        )));
    }
    let old = scene_entry_at(jet, name).await?;
    if old.is_some() && !replace {
        return Err(ClusterError::SceneExists(name.into()));
    }
    // Chosen while the old entry still holds its key: never the old scene's key again.
    let key = fresh_log_key(jet, name, unix_ms()).await?;
    log::create(jet, &key, map)
        .await
        .map_err(|e| ClusterError::Nats(e.to_string()))?;
    let entry = SceneEntry::new(name, map.size(), &key);
    let written = match &old {
        None => put_new(jet, name, &entry).await,
        Some((_, revision)) => {
            let value = serde_json::to_vec(&entry)
                .map_err(|e| ClusterError::Nats(format!("scene entry: {e}")))?;
            match jet
                .kv_update(Bucket::Scenes, name, Bytes::from(value), *revision)
                .await
            {
                Ok(_) => Ok(()),
                Err(PortError::Conflict(_)) => Err(changed_meanwhile(name)),
                Err(e) => Err(ClusterError::Nats(format!("replacing the scene: {e}"))),
            }
        }
    };
    if let Err(e) = written {
        // The new log belongs to no entry: drop it rather than leave it behind.
        drop_log(jet, &key).await;
        return Err(e);
    }
    if let Some((old, _)) = &old
        && !log_key_live(jet, old.log_key(name)).await?
    {
        drop_log(jet, old.log_key(name)).await;
    }
    Ok(())
}

/// Drops a log's stream and snapshots (whatever is there; doing it twice is harmless).
pub(super) async fn drop_log(jet: &impl Jet, key: &str) {
    let _ = jet.delete_stream(key).await;
    snapshot::delete_all(jet, key).await;
}

/// Writes a new scene list entry; a name taken meanwhile is [`ClusterError::SceneExists`].
pub(super) async fn put_new(
    jet: &impl Jet,
    name: &str,
    entry: &SceneEntry,
) -> Result<(), ClusterError> {
    let value =
        serde_json::to_vec(entry).map_err(|e| ClusterError::Nats(format!("scene entry: {e}")))?;
    match jet
        .kv_create(Bucket::Scenes, name, Bytes::from(value))
        .await
    {
        Ok(_) => Ok(()),
        Err(PortError::Conflict(_)) => Err(ClusterError::SceneExists(name.into())),
        Err(e) => Err(ClusterError::Nats(format!(
            "adding the scene to the list: {e}"
        ))),
    }
}

/// Renames scene `from` to `to`: the entry moves (written under `to` first, then taken from
/// `from` if nobody changed it meanwhile, else the move is undone), the log, snapshots and
/// lease stay under their key, so nothing is copied and no edit is lost. Nodes serving
/// `from` close it when they see it gone; one serving both for a moment runs two replicas of
/// one log, which the log's fence keeps to one writer.
pub async fn rename_scene(
    jet: &impl Jet,
    from: &str,
    to: &str,
) -> Result<SceneEntry, ClusterError> {
    if !crate::store::valid_scene_name(to) {
        return Err(ClusterError::Nats(format!("scene name {to:?} is invalid")));
    }
    let Some((entry, revision)) = scene_entry_at(jet, from).await? else {
        return Err(ClusterError::UnknownScene(from.into()));
    };
    let moved = SceneEntry::new(to, entry.size, entry.log_key(from));
    put_new(jet, to, &moved).await?;
    match jet.kv_delete(Bucket::Scenes, from, Some(revision)).await {
        Ok(()) => Ok(moved),
        Err(e) => {
            // Reset, deleted or renamed through another node meanwhile: undo the move.
            if let Ok(Some((_, new))) = scene_entry_at(jet, to).await {
                let _ = jet.kv_delete(Bucket::Scenes, to, Some(new)).await;
            }
            Err(match e {
                PortError::Conflict(_) | PortError::NotFound(_) => changed_meanwhile(from),
                e => ClusterError::Nats(format!("taking the old name out of the list: {e}")),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_from_before_log_keys_use_the_name() {
        let old: SceneEntry = serde_json::from_str(r#"{"size":[64,32,64]}"#).unwrap();
        assert_eq!(old.log, None);
        assert_eq!(old.log_key("demo"), "demo");
        // A new entry whose key is its name is written as before (older nodes read it).
        let same = SceneEntry::new("demo", [1, 2, 3], "demo");
        assert_eq!(serde_json::to_string(&same).unwrap(), r#"{"size":[1,2,3]}"#);
        let moved = SceneEntry::new("other", [1, 2, 3], "demo=17");
        let text = serde_json::to_string(&moved).unwrap();
        let back: SceneEntry = serde_json::from_str(&text).unwrap();
        assert_eq!(back.log_key("other"), "demo=17");
        // A node from before log keys reads `size` as three numbers: it cannot read this
        // entry, so it never uses the log named after the scene (someone else's).
        #[derive(serde::Deserialize)]
        #[allow(dead_code)]
        struct Before {
            size: [u32; 3],
        }
        assert!(serde_json::from_str::<Before>(&text).is_err(), "{text}");
        assert!(serde_json::from_str::<Before>(r#"{"size":[1,2,3]}"#).is_ok());
    }
}
