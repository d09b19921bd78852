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
                json!({
                    "name": listed.name,
                    "size": s.size,
                    "open": true,
                    "seq": s.info.seq.load(Relaxed),
                    "bricks": s.info.bricks.load(Relaxed),
                    "voxels": s.info.voxels.load(Relaxed),
                    "gpu_bytes": s.info.gpu_bytes.load(Relaxed),
                    "history_bytes": s.info.history_bytes.load(Relaxed),
                    "clients": s.info.clients.load(Relaxed),
                    "users": users,
                })
            }
            None => json!({ "name": listed.name, "size": listed.size, "open": false }),
        })
        .collect();
    let deleted = match &app.store {
        Some(store) => {
            let store = store.clone();
            blocking(move || store.deleted().map_err(AdminError::from)).await?
        }
        None => Vec::new(),
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
    let store = single_node(&app, "create")?;
    check_name(&name)?;
    let _turn = app.scenes.opening.lock().await;
    if app.has_scene(&name).await {
        return Err(AdminError::Conflict(format!(
            "scene {name} already exists: delete or reset it, or pick another name"
        )));
    }
    let size = spec.size.unwrap_or(crate::DEMO_SIZE);
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
    let store = single_node(&app, "delete")?;
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
    take_out(
        &app,
        &name,
        format!("scene {name} was deleted by an administrator"),
    )
    .await?;
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
    let store = single_node(&app, "restore")?;
    let kept = {
        let store = store.clone();
        blocking(move || store.deleted().map_err(AdminError::from)).await?
    };
    let Some(kept) = kept.into_iter().find(|d| d.key == key) else {
        return Err(AdminError::BadInput(format!(
            "no deleted scene is kept as {key:?} (GET /admin/scenes lists them; they are dropped when their time is up)"
        )));
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
    let store = single_node(&app, "rename")?;
    let to = body.to;
    check_name(&to)?;
    let _turn = app.scenes.opening.lock().await;
    if app.has_scene(&to).await {
        return Err(AdminError::Conflict(format!(
            "scene {to} already exists: pick another name"
        )));
    }
    take_out(
        &app,
        &name,
        format!("scene {name} was renamed to {to} by an administrator: open /scenes/{to}"),
    )
    .await?;
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
    let store = single_node(&app, "reset")?;
    let _turn = app.scenes.opening.lock().await;
    let Some(size) = app.scene(&name).map(|s| s.size) else {
        return Err(AdminError::UnknownScene(name));
    };
    let size = spec.size.unwrap_or(size);
    let why = format!("scene {name} was reset by an administrator: reconnect to see it");
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

/// The redb store, or the refusal of a command not built for cluster nodes yet.
pub(super) fn single_node(app: &App, what: &str) -> Result<Arc<Store>, AdminError> {
    app.store.clone().ok_or_else(|| {
        AdminError::NotOnCluster(format!(
            "`{what}` is not available on a cluster node yet; scenes of a cluster are made with `brickcast-server import --nats`"
        ))
    })
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
            if size.iter().any(|&e| e > MAX_DEMO_EDGE) {
                return Err(AdminError::BadInput(format!(
                    "a demo scene is at most {MAX_DEMO_EDGE} voxels a side (it is built whole in memory); use \"kind\": \"terrain\" for larger worlds"
                )));
            }
            let map = brickcast_protocol::demo::demo_scene(size).map_err(bad)?;
            store.create_scene(name, &map)?;
        }
        Kind::Terrain => {
            let world = brickcast_protocol::world::World::new(size, seed).map_err(bad)?;
            // Half the cores: the scenes being served keep the rest.
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get() / 2);
            crate::generate::into_store(store, name, &world, threads.max(1), |_, _| {}).map_err(
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
async fn take_out(app: &App, name: &str, why: String) -> Result<(), AdminError> {
    let Some(entry) = app.scenes.remove(name) else {
        return Err(AdminError::UnknownScene(name.to_string()));
    };
    let handle = entry.handle().clone();
    let farewell = Command::Farewell {
        code: ErrorCode::UnknownScene,
        text: why,
    };
    let _ = handle.send(farewell).await;
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
