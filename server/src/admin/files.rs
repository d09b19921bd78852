//! Scenes as files through the admin API: a backup of a scene (`GET
//! /admin/scenes/NAME/backup`) and an upload of a backup or a MagicaVoxel model as a scene
//! (`PUT /admin/scenes/NAME[?replace=true]`).
//!
//! A backup is a scene file (`crate::incoming`'s format, the spool's: magic, version, the
//! bricks as zstd blobs, about 100 bytes a brick) of the scene as committed when asked: its
//! voxels, not its undo history or log. An upload is checked whole before anything changes: a
//! body cut short, a damaged file or a model over the importer's limits is refused with the
//! reason, and the scene of that name, if any, is untouched.

use std::sync::Arc;

use axum::Json;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::Value;

use super::scenes::{blocking, check_name, create_in_cluster, describe, replace, single_node};
use super::{Admin, AdminError};
use crate::App;
use crate::incoming;
use crate::scene::Command;
use crate::store::Store;

/// Largest upload taken (the spool's limit).
pub const MAX_UPLOAD_BYTES: usize = incoming::MAX_SPOOL_BYTES as usize;

/// `GET /admin/scenes/NAME/backup`.
pub async fn backup(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
) -> Result<Response, AdminError> {
    let (scene, _using) = match app.open_scene(&name).await {
        Ok(Some(found)) => found,
        Ok(None) => return Err(AdminError::UnknownScene(name)),
        Err(e) => return Err(AdminError::TryAgain(e.to_string())),
    };
    let (done, copy) = tokio::sync::oneshot::channel();
    let closing = || AdminError::TryAgain(format!("scene {name} is closing; try again"));
    scene
        .send(Command::Thumbnail { done })
        .await
        .map_err(|_| closing())?;
    let (seq, map) = copy.await.map_err(|_| closing())?;
    let bytes = {
        let name = name.clone();
        blocking(move || incoming::encode(&name, &map).map_err(AdminError::Failed)).await?
    };
    tracing::info!(scene = %name, seq, bytes = bytes.len(), "an administrator took a backup");
    let headers = [
        (header::CONTENT_TYPE, "application/octet-stream".to_string()),
        (
            header::CONTENT_DISPOSITION,
            format!("attachment; filename=\"{name}.scene\""),
        ),
        (
            header::HeaderName::from_static("x-brickcast-seq"),
            seq.to_string(),
        ),
    ];
    Ok((headers, bytes).into_response())
}

#[derive(Debug, Default, Deserialize)]
pub struct UploadQuery {
    /// Replace a scene of that name (kept like a deleted one) instead of refusing.
    #[serde(default)]
    replace: bool,
}

/// `PUT /admin/scenes/NAME`: a scene file or a `.vox` model as scene NAME.
pub async fn upload(
    _: Admin,
    State(app): State<Arc<App>>,
    Path(name): Path<String>,
    Query(query): Query<UploadQuery>,
    body: Result<Bytes, BytesRejection>,
) -> Result<(StatusCode, Json<Value>), AdminError> {
    check_name(&name)?;
    let body = body.map_err(|e| {
        AdminError::BadInput(format!(
            "the upload did not arrive whole ({e}); nothing changed"
        ))
    })?;
    // Checked and built before any scene is touched.
    let map = {
        let name = name.clone();
        blocking(move || read_upload(&name, &body)).await?
    };
    let _turn = app.scenes.opening.lock().await;
    let exists = match &app.node {
        // The cluster's list as it is now, not as this node last looked at it.
        Some(node) => crate::cluster::catalog::scene_entry(&node.cluster, &name)
            .await
            .map_err(super::scenes::from_cluster)?
            .is_some(),
        None => app.has_scene(&name).await,
    };
    if let Some(node) = &app.node {
        if exists && query.replace {
            let why = format!("scene {name} was replaced by an administrator: reconnect to see it");
            let described = super::scenes::replace_in_cluster(&app, node, &name, why, map).await?;
            tracing::info!(scene = %name, "an administrator replaced a scene of the cluster by an upload");
            return Ok((StatusCode::OK, Json(described)));
        }
        if exists {
            return Err(AdminError::Conflict(format!(
                "scene {name} already exists in the cluster: upload under another name, or replace it (?replace=true, `--replace`; the scene before is kept like a deleted one)"
            )));
        }
        let described = create_in_cluster(&node.cluster, &name, map).await?;
        tracing::info!(scene = %name, "an administrator uploaded a scene into the cluster");
        return Ok((StatusCode::CREATED, Json(described)));
    }
    let store = single_node(&app, "upload")?;
    if exists && !query.replace {
        return Err(AdminError::Conflict(format!(
            "scene {name} already exists: upload under another name, or replace it (?replace=true, `--replace`; the scene before is kept like a deleted one)"
        )));
    }
    let make = move |store: &Store, name: &str| {
        store.create_scene(name, &map)?;
        store.load_scene(name).map_err(AdminError::from)
    };
    let described = if exists {
        let why = format!("scene {name} was replaced by an administrator: reconnect to see it");
        replace(&app, &store, &name, why, make).await?
    } else {
        let (store, named) = (store.clone(), name.clone());
        let loaded = blocking(move || make(&store, &named)).await?;
        let described = describe(&name, &loaded);
        app.add_scene(name.clone(), loaded)
            .map_err(|e| AdminError::Failed(format!("{e:#}")))?;
        described
    };
    tracing::info!(scene = %name, replaced = exists, "an administrator uploaded a scene");
    let status = if exists {
        StatusCode::OK
    } else {
        StatusCode::CREATED
    };
    Ok((status, Json(described)))
}

/// The scene an upload holds.
fn read_upload(name: &str, bytes: &[u8]) -> Result<brickcast_protocol::BrickMap, AdminError> {
    if incoming::is_scene_file(bytes) {
        let (_, map) = incoming::decode(bytes)
            .map_err(|e| AdminError::BadInput(format!("the scene file: {e}; nothing changed")))?;
        return Ok(map);
    }
    if bytes.starts_with(b"VOX ") {
        let path = std::path::PathBuf::from(format!("{name}.vox"));
        return crate::import::vox::import_vox(bytes, &path)
            .map_err(|e| AdminError::BadInput(format!("the .vox model: {e}; nothing changed")));
    }
    Err(AdminError::BadInput(
        "the upload is neither a brickcast scene file (`admin backup` makes them) nor a MagicaVoxel .vox model; import OBJ models with `brickcast-server import` on the server's machine".into(),
    ))
}
