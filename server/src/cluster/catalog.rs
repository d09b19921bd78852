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
        .map(Some)
        .map_err(|e| ClusterError::Nats(format!("the scene list's entry for {name}: {e}")))
}

/// Adds a scene to the cluster: its stream, a first snapshot, then its entry in the scene
/// list (last, so no node opens a scene that is not complete). `replace` first deletes a
/// scene of that name: its log and snapshot (nodes serving it must be restarted).
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
    // A deleted scene kept under this name still has its log and snapshots here.
    if let Some(kept) = super::deleted::kept_as(jet, name).await? {
        return Err(ClusterError::Nats(format!(
            "a deleted scene named {name} is kept until unix time {} (key {}): restore it, or use another name until then",
            kept.kept_until, kept.key
        )));
    }
    let exists = scene_entry(jet, name).await?.is_some();
    if exists && !replace {
        return Err(ClusterError::SceneExists(name.into()));
    }
    if exists {
        jet.kv_delete(Bucket::Scenes, name, None)
            .await
            .map_err(|e| ClusterError::Nats(format!("removing the old scene: {e}")))?;
        let _ = jet.delete_stream(name).await;
        snapshot::delete_all(jet, name).await;
    }
    log::create(jet, name, map)
        .await
        .map_err(|e| ClusterError::Nats(e.to_string()))?;
    let entry = SceneEntry { size: map.size() };
    let value =
        serde_json::to_vec(&entry).map_err(|e| ClusterError::Nats(format!("scene entry: {e}")))?;
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
