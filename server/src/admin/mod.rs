//! The admin API: running a server without stopping it (issue #32), the operator's habits of
//! Minecraft and Luanti servers.
//!
//! Every route is under `/admin/` and needs an admin (`crate::auth`: an `admin` token in
//! `Authorization: Bearer TOKEN`, or, on a server without an auth file, a request from this
//! machine). Answers are JSON; a refusal is `{"error": "..."}` with a status that says what
//! kind (400 bad input, 403 not an admin, 404 unknown scene, 409 name in use, 503 try
//! again). `brickcast-server admin` is the command line over it.
//!
//! * `GET /admin/scenes`: every scene with its size, sequence, bricks, memory and who is
//!   there; the deleted scenes still kept.
//! * `POST /admin/scenes/NAME` `{"kind": "empty"|"terrain"|"demo", "size": [x,y,z], "seed": n}`:
//!   a new scene, served at once.
//! * `DELETE /admin/scenes/NAME?confirm=NAME&keep=24h`: closes the scene (its users are told
//!   why), keeps it for `keep` (default [`KEEP`]) so the delete can be undone.
//! * `POST /admin/deleted/KEY/restore` `{"as": "NAME"}`: a kept scene back, served again.
//! * `DELETE /admin/deleted/KEY?confirm=KEY`: a kept deleted scene dropped now, for good.
//! * `POST /admin/scenes/NAME/rename` `{"to": "NEW"}`; `POST /admin/scenes/NAME/reset`
//!   (a create of the same name, the old scene kept as a delete keeps it).
//! * `GET /admin/scenes/NAME/backup`: the scene as a file (`files.rs`); `PUT
//!   /admin/scenes/NAME[?replace=true]` with a backup or a `.vox` model as the body: a scene.
//! * `POST /admin/kick` `{"user": "NAME or id", "scene": "NAME"?, "for": "10m"?}`: closes the
//!   user's connections and refuses them for a while.
//!
//! **Limits:** scene commands run one at a time per server (they share the lock scenes open
//! under), and a `create` of a large terrain holds it while it generates. On a cluster every
//! command works through any node: scene commands change the cluster's scene list
//! (`crate::cluster::catalog`, `deleted`), whose entries name each scene's log by a key of
//! its own, so a rename moves no data and a reset's old scene keeps its log.

mod files;
mod scenes;
mod users;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::{ConnectInfo, FromRequestParts};
use axum::http::{StatusCode, header, request::Parts};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};

use crate::App;

pub(crate) use scenes::take_out;
pub use users::{Bans, handle_order as handle_kick_order};

/// How long a deleted scene is kept when the delete does not say.
pub const KEEP: Duration = Duration::from_secs(24 * 3600);
/// Longest a deleted scene may be kept (and a user refused after a kick).
pub const MAX_KEEP: Duration = Duration::from_secs(365 * 24 * 3600);

pub fn routes() -> Router<Arc<App>> {
    Router::new()
        .route("/admin/scenes", get(scenes::list))
        .route(
            "/admin/scenes/{name}",
            post(scenes::create)
                .delete(scenes::delete)
                .put(files::upload)
                .layer(axum::extract::DefaultBodyLimit::max(
                    files::MAX_UPLOAD_BYTES,
                )),
        )
        .route("/admin/scenes/{name}/backup", get(files::backup))
        .route("/admin/scenes/{name}/rename", post(scenes::rename))
        .route("/admin/scenes/{name}/reset", post(scenes::reset))
        .route("/admin/deleted/{key}/restore", post(scenes::restore))
        .route("/admin/deleted/{key}", axum::routing::delete(scenes::purge))
        .route("/admin/kick", post(users::kick))
}

/// A refused or failed admin request.
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    #[error("{0}")]
    BadInput(String),
    #[error("{0}")]
    NotAdmin(String),
    #[error("no scene named {0:?}")]
    UnknownScene(String),
    #[error("{0}")]
    Conflict(String),
    #[error("{0}")]
    TryAgain(String),
    #[error("{0}")]
    Failed(String),
}

impl AdminError {
    fn status(&self) -> StatusCode {
        match self {
            AdminError::BadInput(_) => StatusCode::BAD_REQUEST,
            AdminError::NotAdmin(_) => StatusCode::FORBIDDEN,
            AdminError::UnknownScene(_) => StatusCode::NOT_FOUND,
            AdminError::Conflict(_) => StatusCode::CONFLICT,
            AdminError::TryAgain(_) => StatusCode::SERVICE_UNAVAILABLE,
            AdminError::Failed(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

impl IntoResponse for AdminError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({ "error": self.to_string() });
        (self.status(), axum::Json(body)).into_response()
    }
}

impl From<crate::store::StoreError> for AdminError {
    fn from(e: crate::store::StoreError) -> Self {
        use crate::store::StoreError as E;
        match e {
            E::BadName(_) | E::BadBrick { .. } => AdminError::BadInput(e.to_string()),
            E::SceneExists(_) => AdminError::Conflict(e.to_string()),
            E::UnknownScene(name) => AdminError::UnknownScene(name),
            e => AdminError::Failed(e.to_string()),
        }
    }
}

/// Proof that the request is an admin's: handlers take it first.
pub struct Admin;

impl FromRequestParts<Arc<App>> for Admin {
    type Rejection = AdminError;

    async fn from_request_parts(parts: &mut Parts, app: &Arc<App>) -> Result<Admin, AdminError> {
        let from = parts
            .extensions
            .get::<ConnectInfo<SocketAddr>>()
            .map(|c| c.0.ip())
            .ok_or_else(|| AdminError::Failed("no peer address on the request".into()))?;
        let token = parts
            .headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim);
        app.auth
            .check_admin(token, from)
            .map(|()| Admin)
            .map_err(|why| {
                tracing::warn!(%from, why, "refused an admin request");
                AdminError::NotAdmin(why)
            })
    }
}

/// A JSON body, refused with a clear [`AdminError`] when it does not parse.
pub struct Body<T>(pub T);

impl<T: serde::de::DeserializeOwned> axum::extract::FromRequest<Arc<App>> for Body<T> {
    type Rejection = AdminError;

    async fn from_request(
        req: axum::extract::Request,
        app: &Arc<App>,
    ) -> Result<Body<T>, AdminError> {
        let bytes = axum::body::Bytes::from_request(req, app)
            .await
            .map_err(|e| AdminError::BadInput(format!("reading the request: {e}")))?;
        // An empty body is an empty object: every field has a default.
        let bytes: &[u8] = if bytes.iter().all(u8::is_ascii_whitespace) {
            b"{}"
        } else {
            &bytes
        };
        serde_json::from_slice(bytes)
            .map(Body)
            .map_err(|e| AdminError::BadInput(format!("the request's JSON: {e}")))
    }
}

/// `30s`, `10m`, `24h`, `7d` (humantime's forms), at most [`MAX_KEEP`].
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    let d = humantime::parse_duration(text.trim())
        .map_err(|e| format!("{text:?} is not a duration such as 90s, 10m, 24h or 7d: {e}"))?;
    if d > MAX_KEEP {
        return Err(format!("{text:?} is longer than a year"));
    }
    Ok(d)
}
