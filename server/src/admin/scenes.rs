//! Scene commands of the admin API: list, create, delete (kept for a while), restore,
//! rename, reset. See the module above for the routes.

use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;

use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use brickcast_protocol::BrickMap;
use brickcast_protocol::wire::ErrorCode;
use serde::Deserialize;
use serde_json::{Value, json};

use super::{Admin, AdminError, Body, KEEP, parse_duration};
use crate::App;
use crate::cluster::{ClusterError, catalog, deleted};
use crate::scene::Command;
use crate::served::Closing;
use crate::store::{Loaded, Store, valid_scene_name};

/// Largest demo scene `create` builds: it is made whole in memory first (terrain is not).
const MAX_DEMO_EDGE: u32 = 1024;

/// `GET /admin/scenes`.
pub async fn list(_: Admin, State(app): State<Arc<App>>) -> Result<Json<Value>, AdminError> {
    let scenes: Vec<Value> = app
        .catalog()
        .into_iter()
        .map(|listed| match listed.handle {
            Some(s) => {
                let users: Vec<Value> = s
                    .presence
                    .peers()
                    .into_iter()
                    .map(|(p, here)| {
                        json!({
                            "session": p.id,
                            "user": p.user,
                            "name": p.name,
                            "role": p.role,
                            "on_this_node": here,
                        })
                    })
                    .collect();
                let mut value = crate::open_scene_json(&listed.name, &s);
                value["history_bytes"] = s.info.history_bytes.load(Relaxed).into();
                value["users"] = users.into();
                value
            }
            None => json!({ "name": listed.name, "size": listed.size, "open": false }),
        })
        .collect();
    let deleted: Vec<Value> = match (&app.store, &app.node) {
        (Some(store), _) => {
            let store = store.clone();
            blocking(move || store.deleted().map_err(AdminError::from))
                .await?
                .into_iter()
                .map(|d| {
                    json!({
                        "key": d.key,
                        "name": d.name,
                        "size": d.meta.size,
                        "deleted_at": d.deleted_at,
                        "kept_until": d.kept_until,
                    })
                })
                .collect()
        }
        (None, Some(node)) => deleted::list(&node.cluster)
            .await
            .map_err(from_cluster)?
            .into_iter()
            .map(|d| json!(d))
            .collect(),
        (None, None) => Vec::new(),
    };
    Ok(Json(json!({
        "node": app.node_name(),
        "scenes": scenes,
        "deleted": deleted,
    })))
}

/// What a new scene holds.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// Nothing solid.
    #[default]
    Empty,
    /// A procedural world (`protocol::world`), of any size.
    Terrain,
    /// The demo scene's terrain, at most [`MAX_DEMO_EDGE`] a side.
    Demo,
}

/// The body of `create` and `reset`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Create {
    #[serde(default)]
    kind: Kind,
    /// Voxels along x, y (up), z; default: the demo's size (`create`), the scene's (`reset`).
    size: Option<[u32; 3]>,
    /// Terrain: another seed, another world.
    #[serde(default = "one")]
    seed: u32,
}

fn one() -> u32 {
    1
}

/// `POST /admin/scenes/NAME`.
pub async fn create(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
    Body(spec): Body<Create>,
) -> Result<(StatusCode, Json<Value>), AdminError> {
    check_name(&name)?;
    let _turn = app.scenes.opening.lock().await;
    if app.has_scene(&name).await {
        return Err(AdminError::Conflict(format!(
            "scene {name} already exists: delete or reset it, or pick another name"
        )));
    }
    let size = spec.size.unwrap_or(crate::DEMO_SIZE);
    if let Some(node) = &app.node {
        let map = blocking(move || map_of(spec.kind, size, spec.seed)).await?;
        let described = create_in_cluster(&node.cluster, &name, map).await?;
        tracing::info!(scene = %name, kind = ?spec.kind, ?size, "an administrator created a scene in the cluster");
        return Ok((StatusCode::CREATED, Json(described)));
    }
    let store = single_node(&app, "create")?;
    let loaded = {
        let name = name.clone();
        blocking(move || make_scene(&store, &name, spec.kind, size, spec.seed)).await?
    };
    let described = describe(&name, &loaded);
    app.add_scene(name.clone(), loaded)
        .map_err(|e| AdminError::Failed(format!("{e:#}")))?;
    tracing::info!(scene = %name, kind = ?spec.kind, ?size, "an administrator created a scene");
    Ok((StatusCode::CREATED, Json(described)))
}

#[derive(Debug, Default, Deserialize)]
pub struct DeleteQuery {
    confirm: Option<String>,
    keep: Option<String>,
}

/// `DELETE /admin/scenes/NAME?confirm=NAME&keep=24h`.
pub async fn delete(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
    Query(query): Query<DeleteQuery>,
) -> Result<Json<Value>, AdminError> {
    if query.confirm.as_deref() != Some(name.as_str()) {
        return Err(AdminError::BadInput(format!(
            "deleting scene {name} closes it for everyone on it: confirm with ?confirm={name} (`--yes` on the command line)"
        )));
    }
    let keep = match &query.keep {
        Some(text) => parse_duration(text).map_err(AdminError::BadInput)?,
        None => KEEP,
    };
    let _turn = app.scenes.opening.lock().await;
    let why = format!("scene {name} was deleted by an administrator");
    if let Some(node) = &app.node {
        // Out of the list first, so no node opens it again; the others close it when they see.
        let deleted = deleted::delete_keeping(&node.cluster, &name, unix_ms(), keep.as_secs())
            .await
            .map_err(from_cluster)?;
        match take_out(&app, &name, why).await {
            Ok(()) | Err(AdminError::UnknownScene(_)) => {}
            Err(e) => return Err(e),
        }
        tracing::info!(scene = %name, key = %deleted.key, kept_until = deleted.kept_until, "an administrator deleted a scene of the cluster");
        return Ok(Json(json!({
            "deleted": name,
            "key": deleted.key,
            "kept_until": deleted.kept_until,
        })));
    }
    let store = single_node(&app, "delete")?;
    take_out(&app, &name, why).await?;
    let deleted = {
        let (store, name) = (store.clone(), name.clone());
        blocking(move || store.delete_keeping(&name, keep).map_err(AdminError::from)).await
    };
    let deleted = match deleted {
        Ok(deleted) => deleted,
        Err(e) => {
            put_back(&app, &store, &name).await;
            return Err(e);
        }
    };
    tracing::info!(scene = %name, key = %deleted.key, kept_until = deleted.kept_until, "an administrator deleted a scene");
    Ok(Json(json!({
        "deleted": name,
        "key": deleted.key,
        "kept_until": deleted.kept_until,
    })))
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Restore {
    /// The name to serve it under (default: its name when deleted).
    #[serde(rename = "as")]
    name: Option<String>,
}

/// `POST /admin/deleted/KEY/restore`.
pub async fn restore(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(key): Path<String>,
    Body(body): Body<Restore>,
) -> Result<Json<Value>, AdminError> {
    if let Some(node) = &app.node {
        if let Some(name) = &body.name {
            check_name(name)?;
        }
        let _turn = app.scenes.opening.lock().await;
        let (_, name) = deleted::restore(&node.cluster, &key, body.name.as_deref())
            .await
            .map_err(|e| match e {
                ClusterError::SceneExists(name) => AdminError::Conflict(format!(
                    "scene {name} exists: restore under another name ({{\"as\": \"NAME\"}}, `--as` on the command line)"
                )),
                ClusterError::UnknownScene(_) => not_kept(&key),
                e => from_cluster(e),
            })?;
        tracing::info!(scene = %name, key = %key, "an administrator restored a deleted scene of the cluster");
        return Ok(Json(described_in_cluster(node, &name).await?));
    }
    let store = single_node(&app, "restore")?;
    let kept = {
        let store = store.clone();
        blocking(move || store.deleted().map_err(AdminError::from)).await?
    };
    let Some(kept) = kept.into_iter().find(|d| d.key == key) else {
        return Err(not_kept(&key));
    };
    let name = body.name.unwrap_or(kept.name);
    check_name(&name)?;
    let _turn = app.scenes.opening.lock().await;
    if app.has_scene(&name).await {
        return Err(AdminError::Conflict(format!(
            "scene {name} exists: restore under another name ({{\"as\": \"NAME\"}}, `--as` on the command line)"
        )));
    }
    let loaded = {
        let (store, name) = (store.clone(), name.clone());
        blocking(move || {
            store.restore_deleted(&key, &name)?;
            store.load_scene(&name).map_err(AdminError::from)
        })
        .await?
    };
    let described = describe(&name, &loaded);
    app.add_scene(name.clone(), loaded)
        .map_err(|e| AdminError::Failed(format!("{e:#}")))?;
    tracing::info!(scene = %name, "an administrator restored a deleted scene");
    Ok(Json(described))
}

/// `DELETE /admin/deleted/KEY?confirm=KEY`: a kept deleted scene dropped for good (its disk
/// back; on a cluster its name free again).
pub async fn purge(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(key): Path<String>,
    Query(query): Query<DeleteQuery>,
) -> Result<Json<Value>, AdminError> {
    if query.confirm.as_deref() != Some(key.as_str()) {
        return Err(AdminError::BadInput(format!(
            "purging {key} drops it for good: confirm with ?confirm={key} (`--yes` on the command line)"
        )));
    }
    let _turn = app.scenes.opening.lock().await;
    let dropped = match (&app.store, &app.node) {
        (Some(store), _) => {
            let (store, key) = (store.clone(), key.clone());
            blocking(move || store.drop_kept(&key).map_err(AdminError::from))
                .await
                .map(|d| d.name)
        }
        (None, Some(node)) => deleted::purge_key(&node.cluster, &key)
            .await
            .map(|d| d.name)
            .map_err(from_cluster),
        (None, None) => Err(AdminError::Failed("no store and no cluster".into())),
    };
    let name = dropped.map_err(|e| match e {
        AdminError::UnknownScene(_) => not_kept(&key),
        e => e,
    })?;
    tracing::info!(scene = %name, key = %key, "an administrator dropped a deleted scene for good");
    Ok(Json(json!({ "purged": key, "name": name })))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rename {
    to: String,
}

/// `POST /admin/scenes/NAME/rename`.
pub async fn rename(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
    Body(body): Body<Rename>,
) -> Result<Json<Value>, AdminError> {
    let to = body.to;
    check_name(&to)?;
    let _turn = app.scenes.opening.lock().await;
    if app.has_scene(&to).await {
        return Err(AdminError::Conflict(format!(
            "scene {to} already exists: pick another name"
        )));
    }
    let why = format!("scene {name} was renamed to {to} by an administrator: open /scenes/{to}");
    if let Some(node) = &app.node {
        // The entry moves first; this node's copy closes now, the others' when they see it.
        catalog::rename_scene(&node.cluster, &name, &to)
            .await
            .map_err(|e| match e {
                ClusterError::SceneExists(to) => {
                    AdminError::Conflict(format!("scene {to} already exists: pick another name"))
                }
                e => from_cluster(e),
            })?;
        match take_out(&app, &name, why).await {
            Ok(()) | Err(AdminError::UnknownScene(_)) => {}
            Err(e) => return Err(e),
        }
        tracing::info!(scene = %name, to = %to, "an administrator renamed a scene of the cluster");
        return Ok(Json(described_in_cluster(node, &to).await?));
    }
    let store = single_node(&app, "rename")?;
    take_out(&app, &name, why).await?;
    let loaded = {
        let (store, name, to) = (store.clone(), name.clone(), to.clone());
        blocking(move || {
            store.rename_scene(&name, &to)?;
            store.load_scene(&to).map_err(AdminError::from)
        })
        .await
    };
    let loaded = match loaded {
        Ok(loaded) => loaded,
        Err(e) => {
            put_back(&app, &store, &name).await;
            return Err(e);
        }
    };
    let described = describe(&to, &loaded);
    app.add_scene(to.clone(), loaded)
        .map_err(|e| AdminError::Failed(format!("{e:#}")))?;
    tracing::info!(scene = %name, to = %to, "an administrator renamed a scene");
    Ok(Json(described))
}

/// `POST /admin/scenes/NAME/reset`: the scene made anew (empty by default, its size by
/// default); the old one is kept for [`KEEP`] like a deleted scene.
pub async fn reset(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
    Body(spec): Body<Create>,
) -> Result<Json<Value>, AdminError> {
    let why = format!("scene {name} was reset by an administrator: reconnect to see it");
    if let Some(node) = &app.node {
        let Some(entry) = catalog::scene_entry(&node.cluster, &name)
            .await
            .map_err(from_cluster)?
        else {
            return Err(AdminError::UnknownScene(name));
        };
        let size = spec.size.unwrap_or(entry.size);
        let map = blocking(move || map_of(spec.kind, size, spec.seed)).await?;
        let _turn = app.scenes.opening.lock().await;
        let described = replace_in_cluster(&app, node, &name, why, map).await?;
        tracing::info!(scene = %name, "an administrator reset a scene of the cluster");
        return Ok(Json(described));
    }
    let store = single_node(&app, "reset")?;
    let _turn = app.scenes.opening.lock().await;
    let Some(size) = app.scene(&name).map(|s| s.size) else {
        return Err(AdminError::UnknownScene(name));
    };
    let size = spec.size.unwrap_or(size);
    let make = move |store: &Store, name: &str| make_scene(store, name, spec.kind, size, spec.seed);
    let described = replace(&app, &store, &name, why, make).await?;
    tracing::info!(scene = %name, "an administrator reset a scene");
    Ok(Json(described))
}

/// Replaces served scene `name` by what `make` writes under that name, keeping the one before
/// for [`KEEP`] like a deleted scene (its key in the answer's `previous`). A `make` that fails
/// puts the one before back: nothing is lost. The caller holds `served.opening`.
pub(super) async fn replace(
    app: &App,
    store: &Arc<Store>,
    name: &str,
    why: String,
    make: impl FnOnce(&Store, &str) -> Result<Loaded, AdminError> + Send + 'static,
) -> Result<Value, AdminError> {
    take_out(app, name, why).await?;
    let made = {
        let (store, name) = (store.clone(), name.to_string());
        blocking(move || {
            let kept = store.delete_keeping(&name, KEEP)?;
            match make(&store, &name) {
                Ok(loaded) => Ok((kept, loaded)),
                Err(e) => {
                    if let Err(back) = store.restore_deleted(&kept.key, &name) {
                        tracing::error!(scene = %name, key = %kept.key, error = %back, "a failed replacement could not put the old scene back; it is kept as deleted");
                    }
                    Err(e)
                }
            }
        })
        .await
    };
    let (kept, loaded) = match made {
        Ok(made) => made,
        Err(e) => {
            put_back(app, store, name).await;
            return Err(e);
        }
    };
    let mut described = describe(name, &loaded);
    described["previous"] = json!({ "key": kept.key, "kept_until": kept.kept_until });
    app.add_scene(name.to_string(), loaded)
        .map_err(|e| AdminError::Failed(format!("{e:#}")))?;
    Ok(described)
}

/// On a cluster: replaces scene `name` by `map` under a log of its own, keeping the one
/// before for [`KEEP`] like a deleted scene (its key in the answer's `previous`). A create
/// that fails puts the one before back. The caller holds `served.opening`.
pub(super) async fn replace_in_cluster(
    app: &App,
    node: &crate::Node,
    name: &str,
    why: String,
    map: BrickMap,
) -> Result<Value, AdminError> {
    let cluster = &node.cluster;
    let kept = deleted::delete_keeping(cluster, name, unix_ms(), KEEP.as_secs())
        .await
        .map_err(from_cluster)?;
    match take_out(app, name, why).await {
        Ok(()) | Err(AdminError::UnknownScene(_)) => {}
        Err(e) => {
            tracing::warn!(scene = %name, error = %e, "could not close the scene being replaced here")
        }
    }
    if let Err(e) = catalog::create_scene(cluster, name, &map, false).await {
        if let Err(back) = deleted::restore(cluster, &kept.key, None).await {
            tracing::error!(scene = %name, key = %kept.key, error = %back, "a failed replacement could not put the old scene back; it is kept as deleted");
        }
        return Err(from_cluster(e));
    }
    let mut described = json!({
        "name": name,
        "size": map.size(),
        "seq": map.sequence(),
        "bricks": map.brick_count(),
        "voxels": map.solid_voxels(),
    });
    described["previous"] = json!({ "key": kept.key, "kept_until": kept.kept_until });
    Ok(described)
}

/// What the admin API answers about cluster scene `name`: its name and size (the list's
/// entry; its contents are read only by a node that opens it).
async fn described_in_cluster(node: &crate::Node, name: &str) -> Result<Value, AdminError> {
    let Some(entry) = catalog::scene_entry(&node.cluster, name)
        .await
        .map_err(from_cluster)?
    else {
        return Err(AdminError::UnknownScene(name.into()));
    };
    Ok(json!({ "name": name, "size": entry.size }))
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default()
        .as_millis() as u64
}

fn not_kept(key: &str) -> AdminError {
    AdminError::BadInput(format!(
        "no deleted scene is kept as {key:?} (GET /admin/scenes lists them; they are dropped when their time is up)"
    ))
}

pub(super) fn from_cluster(e: ClusterError) -> AdminError {
    match e {
        ClusterError::SceneExists(name) => {
            AdminError::Conflict(format!("scene {name} already exists in the cluster"))
        }
        ClusterError::UnknownScene(name) => AdminError::UnknownScene(name),
        ClusterError::Busy(why) => AdminError::Conflict(why),
        e => AdminError::TryAgain(e.to_string()),
    }
}

/// Largest horizontal edge of a terrain made on a cluster node (made whole in memory first).
const MAX_CLUSTER_TERRAIN_EDGE: u32 = 4096;

/// A new scene's map, whole (for a cluster).
fn map_of(kind: Kind, size: [u32; 3], seed: u32) -> Result<BrickMap, AdminError> {
    let bad = |e: brickcast_protocol::map::MapError| {
        AdminError::BadInput(format!(
            "a scene of {}x{}x{} voxels: {e}",
            size[0], size[1], size[2]
        ))
    };
    match kind {
        Kind::Empty => BrickMap::new(size).map_err(bad),
        Kind::Demo => {
            check_demo(size)?;
            brickcast_protocol::demo::demo_scene(size).map_err(bad)
        }
        Kind::Terrain => {
            if size[0].max(size[2]) > MAX_CLUSTER_TERRAIN_EDGE {
                return Err(AdminError::BadInput(format!(
                    "a cluster node makes a terrain whole in memory first: at most {MAX_CLUSTER_TERRAIN_EDGE} voxels along x and z"
                )));
            }
            let world = brickcast_protocol::world::World::new(size, seed).map_err(bad)?;
            crate::generate::into_map(&world, threads()).map_err(|e| match e {
                crate::generate::GenerateError::Tile(e) => bad(e),
                e => AdminError::Failed(e.to_string()),
            })
        }
    }
}

fn check_demo(size: [u32; 3]) -> Result<(), AdminError> {
    if size.iter().any(|&e| e > MAX_DEMO_EDGE) {
        return Err(AdminError::BadInput(format!(
            "a demo scene is at most {MAX_DEMO_EDGE} voxels a side (it is built whole in memory); use \"kind\": \"terrain\" for larger worlds"
        )));
    }
    Ok(())
}

/// Generating threads on a serving node: half the cores, the scenes being served keep the rest.
fn threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).max(1))
}

/// Adds `map` to the cluster as scene `name` (nodes open it when someone asks).
pub(super) async fn create_in_cluster(
    cluster: &crate::cluster::Cluster,
    name: &str,
    map: BrickMap,
) -> Result<Value, AdminError> {
    catalog::create_scene(cluster, name, &map, false)
        .await
        .map_err(from_cluster)?;
    Ok(json!({
        "name": name,
        "size": map.size(),
        "seq": map.sequence(),
        "bricks": map.brick_count(),
        "voxels": map.solid_voxels(),
    }))
}

/// The redb store (every command handles a cluster node before it asks for this).
pub(super) fn single_node(app: &App, what: &str) -> Result<Arc<Store>, AdminError> {
    app.store
        .clone()
        .ok_or_else(|| AdminError::Failed(format!("`{what}`: this server has no store")))
}

pub(super) fn check_name(name: &str) -> Result<(), AdminError> {
    if valid_scene_name(name) {
        Ok(())
    } else {
        Err(crate::store::StoreError::BadName(name.into()).into())
    }
}

/// Runs store work off the async threads.
pub(super) async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, AdminError> + Send + 'static,
) -> Result<T, AdminError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| AdminError::Failed(format!("the task failed: {e}")))?
}

/// Makes scene `name` in the store and loads it.
fn make_scene(
    store: &Store,
    name: &str,
    kind: Kind,
    size: [u32; 3],
    seed: u32,
) -> Result<Loaded, AdminError> {
    let bad = |e: brickcast_protocol::map::MapError| {
        AdminError::BadInput(format!(
            "a scene of {}x{}x{} voxels: {e}",
            size[0], size[1], size[2]
        ))
    };
    match kind {
        Kind::Empty => store.create_scene(name, &BrickMap::new(size).map_err(bad)?)?,
        Kind::Demo => {
            check_demo(size)?;
            let map = brickcast_protocol::demo::demo_scene(size).map_err(bad)?;
            store.create_scene(name, &map)?;
        }
        Kind::Terrain => {
            let world = brickcast_protocol::world::World::new(size, seed).map_err(bad)?;
            crate::generate::into_store(store, name, &world, threads(), |_, _| {}).map_err(
                |e| match e {
                    crate::generate::GenerateError::Store(e) => e.into(),
                    e => AdminError::Failed(e.to_string()),
                },
            )?;
        }
    }
    Ok(store.load_scene(name)?)
}

pub(super) fn describe(name: &str, loaded: &Loaded) -> Value {
    json!({
        "name": name,
        "size": loaded.map.size(),
        "seq": loaded.seq,
        "bricks": loaded.map.brick_count(),
        "voxels": loaded.map.solid_voxels(),
    })
}

/// Takes a served scene out of service: its sessions are told `why` and closed, its owner
/// commits what it has, writes a snapshot and stops. Waits until it has stopped, so the
/// store's rows of the scene are nobody's when this returns.
pub(crate) async fn take_out(app: &App, name: &str, why: String) -> Result<(), AdminError> {
    let Some(entry) = app.scenes.remove(name) else {
        return Err(AdminError::UnknownScene(name.to_string()));
    };
    let handle = entry.handle().clone();
    let farewell = Command::Farewell {
        code: ErrorCode::UnknownScene,
        text: why,
    };
    let _ = handle.send(farewell).await;
    app.past
        .close_scene(
            name,
            &format!("scene {name} was changed by an administrator: its past is gone"),
        )
        .await;
    crate::served::close(name, entry, Closing::Admin, &app.scenes.still_closing).await;
    // A large scene's last snapshot may take longer than a close's patience: wait for it.
    handle.closed().await;
    app.thumbnails.forget(name);
    Ok(())
}

/// Serves `name` again after a command that took it out failed.
async fn put_back(app: &App, store: &Arc<Store>, name: &str) {
    let loaded = {
        let (store, name) = (store.clone(), name.to_string());
        tokio::task::spawn_blocking(move || store.load_scene(&name)).await
    };
    match loaded {
        Ok(Ok(loaded)) => {
            if let Err(e) = app.add_scene(name.to_string(), loaded) {
                tracing::error!(scene = %name, error = %format!("{e:#}"), "cannot serve a scene again after a failed admin command");
            }
        }
        Ok(Err(e)) => {
            tracing::error!(scene = %name, error = %e, "cannot load a scene again after a failed admin command")
        }
        Err(e) => tracing::error!(scene = %name, error = %e, "loading a scene again failed"),
    }
}
