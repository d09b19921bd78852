//! The browser side of the server: the scene list at `/`, the viewer page at `/scenes/NAME`,
//! the viewer's wasm bundle and the scene thumbnails.
//!
//! Why embedded: a remote viewer should need a link, nothing else. `build.rs` compiles the
//! viewer (`web/`, the client core for wasm32) and this module serves it from the binary, so the
//! page is exactly as new as the server. Assets are addressed with a hash of their bytes, so a
//! browser may cache them for good and still never run an old viewer against a new server.
//!
//! Thumbnails are traced with the CPU renderer (~30 ms on one core at 320×180 for the demo) on
//! a blocking thread, from a copy of the scene its owner hands out (a memory copy: ~2 ms for
//! the demo), and cached per sequence number; while a scene is being edited a thumbnail is
//! re-rendered at most every [`THUMBNAIL_EVERY`], one render per scene at a time and at most
//! [`RENDERS`] at once, so a flood of thumbnail requests costs the owner next to nothing.

use std::collections::HashMap;
use std::hash::{DefaultHasher, Hasher};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, LazyLock, Mutex};
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use bytes::Bytes;
use tokio::sync::oneshot;

use crate::App;
use crate::metrics::Metrics;
use crate::scene::Command;

const JS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/web/brickcast_web.js"));
const JS_GZ: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/web/brickcast_web.js.gz"));
const WASM: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/web/brickcast_web_bg.wasm"));
const WASM_GZ: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/web/brickcast_web_bg.wasm.gz"));
/// Empty when the bundle was built; otherwise why not (shown on the pages).
const UNBUILT: &str = include_str!(concat!(env!("OUT_DIR"), "/web/status.txt"));
const VIEWER_HTML: &str = include_str!("../../web/page/viewer.html");
const INDEX_HTML: &str = include_str!("../../web/page/index.html");
const STYLE: &str = include_str!("../../web/page/style.css");

/// Thumbnail size: 16:9, small enough to trace in milliseconds on one core.
pub const THUMBNAIL_SIZE: (u32, u32) = (320, 180);
/// A scene that keeps changing gets a new thumbnail at most this often.
pub const THUMBNAIL_EVERY: Duration = Duration::from_secs(2);

/// Hash of everything the page loads: part of every asset address.
static VERSION: LazyLock<String> = LazyLock::new(|| {
    let mut h = DefaultHasher::new();
    for part in [JS, WASM, STYLE.as_bytes(), VIEWER_HTML.as_bytes()] {
        h.write(part);
    }
    format!("{:016x}", h.finish())
});

/// Whether this binary carries the browser viewer.
pub fn viewer_built() -> bool {
    UNBUILT.is_empty()
}

/// Why the viewer is missing, when it is (logged at start).
pub fn unbuilt_reason() -> Option<&'static str> {
    (!viewer_built()).then_some(UNBUILT)
}

/// Cached thumbnails, by scene.
pub struct Thumbnails {
    cache: Mutex<HashMap<String, Thumbnail>>,
    /// One render per scene at a time: a request for a stale picture takes its scene's turn
    /// (scenes share [`FLIGHTS`] turns by the hash of their name, so names from the URL cannot
    /// grow a table), and those waiting behind it take the picture it drew.
    flights: [tokio::sync::Mutex<()>; FLIGHTS],
    renders: tokio::sync::Semaphore,
}

/// How many scenes' thumbnail requests may wait on their own turn at once.
const FLIGHTS: usize = 16;
/// How many thumbnails are drawn at once, across scenes: each holds a copy of its scene.
const RENDERS: usize = 2;

impl Default for Thumbnails {
    fn default() -> Self {
        Thumbnails {
            cache: Mutex::default(),
            flights: std::array::from_fn(|_| tokio::sync::Mutex::new(())),
            renders: tokio::sync::Semaphore::new(RENDERS),
        }
    }
}

impl Thumbnails {
    /// The cached picture of `name`, unless it is stale: the scene has moved on from it (its
    /// sequence `seq`, `None` when this node does not serve it) and it is older than
    /// [`THUMBNAIL_EVERY`]. A scene this node does not serve keeps the picture it had: drawing
    /// it again would open the scene for every visit to the scene list.
    fn fresh(&self, name: &str, seq: Option<u64>) -> Option<Bytes> {
        let cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        let t = cache.get(name)?;
        (Some(t.seq) == seq || seq.is_none() || t.at.elapsed() < THUMBNAIL_EVERY)
            .then(|| t.png.clone())
    }

    /// Drops the picture of a scene that was deleted or renamed: a new scene of that name
    /// must not show it.
    pub fn forget(&self, name: &str) {
        self.cache
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(name);
    }

    fn flight(&self, name: &str) -> &tokio::sync::Mutex<()> {
        let mut h = DefaultHasher::new();
        h.write(name.as_bytes());
        &self.flights[h.finish() as usize % FLIGHTS]
    }
}

struct Thumbnail {
    seq: u64,
    png: Bytes,
    at: Instant,
}

pub fn routes() -> Router<Arc<App>> {
    Router::new()
        .route("/", get(index))
        .route("/scenes/{name}", get(viewer))
        .route("/scenes/{name}/thumb.png", get(thumbnail))
        .route("/assets/{file}", get(asset))
        // Browsers ask for it on every page; a 404 would fill their consoles.
        .route("/favicon.ico", get(|| async { StatusCode::NO_CONTENT }))
}

/// `&`, `<`, `>`, `"` and `'` as HTML entities.
fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// `text` as a JavaScript string literal (JSON is one), safe inside a `<script>`.
fn js_string(text: &str) -> String {
    serde_json::to_string(text)
        .unwrap_or_else(|_| "\"\"".into())
        .replace('<', "\\u003c")
}

fn html(status: StatusCode, body: String) -> Response {
    (
        status,
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
        .into_response()
}

fn unbuilt_text() -> String {
    format!(
        "This server was built without its browser viewer: {}. Until then, use the native viewer (brickcast view).",
        UNBUILT.trim()
    )
}

async fn index(State(app): State<Arc<App>>, headers: HeaderMap) -> Response {
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .unwrap_or("HOST:7878")
        .to_string();
    let scenes = app.catalog();
    let rows: Vec<String> = scenes
        .iter()
        .map(|listed| {
            let [x, y, z] = listed.size;
            // A cluster node knows who is in a scene only while it serves the scene.
            let (figures, here) = match &listed.handle {
                Some(s) => {
                    let who = s.presence.names();
                    let here = match who.len() {
                        0 => "nobody here".to_string(),
                        n => format!("{n} here: {}", who.join(", ")),
                    };
                    let figures = format!(
                        " · {} voxels · {} bricks",
                        s.info.voxels.load(Relaxed),
                        s.info.bricks.load(Relaxed)
                    );
                    (figures, here)
                }
                None => (String::new(), "not open on this server yet: it opens when you join".to_string()),
            };
            let name_html = escape(&listed.name);
            format!(
                "<li><a href=\"/scenes/{name_html}\"><img src=\"/scenes/{name_html}/thumb.png\" alt=\"{name_html}\" loading=\"lazy\"></a>\
                 <div class=\"meta\"><a class=\"name\" href=\"/scenes/{name_html}\">{name_html}</a><br>\
                 {x}×{y}×{z}{figures}<br>{}</div></li>",
                escape(&here)
            )
        })
        .collect();
    let count = match scenes.len() {
        1 => "One scene".to_string(),
        n => format!("{n} scenes"),
    };
    let note = if viewer_built() {
        String::new()
    } else {
        format!("<p class=\"warn\">{}</p>", escape(&unbuilt_text()))
    };
    let page = INDEX_HTML
        .replace("{{VERSION}}", &VERSION)
        .replace("{{SERVER}}", &escape(&host))
        .replace("{{HOST}}", &escape(&host))
        .replace("{{COUNT}}", &count)
        .replace("{{UNBUILT_NOTE}}", &note)
        .replace("{{ROWS}}", &rows.join("\n"));
    html(StatusCode::OK, page)
}

async fn viewer(State(app): State<Arc<App>>, Path(name): Path<String>) -> Response {
    // `NAME@K` is level K of the scene (the websocket checks K against the scene's size);
    // `NAME~S` the scene at sequence S (the websocket checks S against what is kept).
    let scene = match crate::past_views::split_past(&name) {
        Some(past) => past.map_or(name.as_str(), |(scene, _)| scene),
        None => crate::split_level(&name).map_or(name.as_str(), |(scene, _)| scene),
    };
    if !app.has_scene(scene).await {
        let page = format!(
            "<!doctype html><meta charset=\"utf-8\"><title>No such scene · brickcast</title>\
             <link rel=\"stylesheet\" href=\"/assets/style.css?v={}\"><body class=\"list\">\
             <h1>brickcast</h1><p id=\"message\" class=\"warn\">There is no scene called \u{201c}{}\u{201d} on this server.</p>\
             <p><a href=\"/\">All scenes</a></p>",
            *VERSION,
            escape(&name)
        );
        return html(StatusCode::NOT_FOUND, page);
    }
    let page = VIEWER_HTML
        .replace("{{VERSION}}", &VERSION)
        .replace("{{NAME}}", &escape(&name))
        .replace("{{UNBUILT}}", if viewer_built() { "false" } else { "true" })
        .replace("{{UNBUILT_TEXT}}", &js_string(&unbuilt_text()));
    html(StatusCode::OK, page)
}

async fn asset(Path(file): Path<String>, headers: HeaderMap) -> Response {
    let (plain, gzipped, kind): (&[u8], Option<&[u8]>, &str) = match file.as_str() {
        "brickcast_web.js" => (JS, Some(JS_GZ), "text/javascript"),
        "brickcast_web_bg.wasm" => (WASM, Some(WASM_GZ), "application/wasm"),
        "style.css" => (STYLE.as_bytes(), None, "text/css"),
        _ => return (StatusCode::NOT_FOUND, "no such file\n").into_response(),
    };
    if plain.is_empty() {
        return (StatusCode::NOT_FOUND, unbuilt_text()).into_response();
    }
    let gzip_ok = headers
        .get(header::ACCEPT_ENCODING)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|e| e.trim().starts_with("gzip")));
    // Addresses carry the version, so what is behind one never changes.
    let cache = (header::CACHE_CONTROL, "public, max-age=31536000, immutable");
    match gzipped {
        Some(gz) if gzip_ok => (
            [
                (header::CONTENT_TYPE, kind),
                (header::CONTENT_ENCODING, "gzip"),
                (header::VARY, "accept-encoding"),
                cache,
            ],
            gz,
        )
            .into_response(),
        _ => (
            [
                (header::CONTENT_TYPE, kind),
                (header::VARY, "accept-encoding"),
                cache,
            ],
            plain,
        )
            .into_response(),
    }
}

async fn thumbnail(State(app): State<Arc<App>>, Path(name): Path<String>) -> Response {
    // A cluster node draws a scene it does not serve (and has no picture of) by opening it;
    // it closes again when nobody uses it.
    let seq = app.scene(&name).map(|s| s.info.seq.load(Relaxed));
    let png = |png: Bytes| {
        (
            [
                (header::CONTENT_TYPE, "image/png"),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            png,
        )
            .into_response()
    };
    if let Some(cached) = app.thumbnails.fresh(&name, seq) {
        return png(cached);
    }
    // Whoever had the turn before us may have drawn it.
    let _turn = app.thumbnails.flight(&name).lock().await;
    let seq = app.scene(&name).map(|s| s.info.seq.load(Relaxed));
    if let Some(cached) = app.thumbnails.fresh(&name, seq) {
        return png(cached);
    }
    let (scene, _using) = match app.open_scene(&name).await {
        Ok(Some(found)) => found,
        Ok(None) => {
            return (StatusCode::NOT_FOUND, format!("no scene named {name:?}\n")).into_response();
        }
        Err(e) => return (StatusCode::SERVICE_UNAVAILABLE, format!("{e}\n")).into_response(),
    };
    let Ok(_render) = app.thumbnails.renders.acquire().await else {
        return (StatusCode::SERVICE_UNAVAILABLE, "the server is stopping\n").into_response();
    };
    let (done, copied) = oneshot::channel();
    if scene.send(Command::Thumbnail { done }).await.is_err() {
        return (StatusCode::SERVICE_UNAVAILABLE, "the scene has stopped\n").into_response();
    }
    let Ok((seq, map)) = copied.await else {
        return (StatusCode::SERVICE_UNAVAILABLE, "the scene has stopped\n").into_response();
    };
    Metrics::add(&app.metrics.thumbnails_rendered, 1);
    let encoded = tokio::task::spawn_blocking(move || encode_png(&draw(&map))).await;
    let Ok(Ok(bytes)) = encoded else {
        return (
            StatusCode::INTERNAL_SERVER_ERROR,
            "could not encode the thumbnail\n",
        )
            .into_response();
    };
    let bytes = Bytes::from(bytes);
    app.thumbnails
        .cache
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .insert(
            name,
            Thumbnail {
                seq,
                png: bytes.clone(),
                at: Instant::now(),
            },
        );
    png(bytes)
}

/// The scene from its first camera, at [`THUMBNAIL_SIZE`], on one core.
fn draw(map: &brickcast_protocol::BrickMap) -> brickcast_protocol::Frame {
    let (width, height) = THUMBNAIL_SIZE;
    let camera = brickcast_protocol::viewpoint::find(map, 55.0).camera;
    match camera.project(width, height) {
        Some(p) => {
            brickcast_protocol::render::render(map, &p, &brickcast_protocol::Lighting::default(), 1)
        }
        None => brickcast_protocol::Frame {
            width: 0,
            height: 0,
            pixels: Vec::new(),
            hits: Vec::new(),
        },
    }
}

fn encode_png(frame: &brickcast_protocol::Frame) -> Result<Vec<u8>, image::ImageError> {
    use image::ImageEncoder;
    let raw: Vec<u8> = frame.pixels.iter().flatten().copied().collect();
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out).write_image(
        &raw,
        frame.width,
        frame.height,
        image::ExtendedColorType::Rgba8,
    )?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_cannot_break_out_of_the_page() {
        assert_eq!(
            escape("<a href=\"x\">&'"),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;"
        );
        assert_eq!(js_string("</script>\"x"), "\"\\u003c/script>\\\"x\"");
    }
}
