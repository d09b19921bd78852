//! The scratch scene a load run edits instead of a real one.
//!
//! A run's edits stay in the scene it edits. So unless told `--in-place`, a run on a scene that
//! holds voxels makes a scratch scene of the same size through the server's admin API (the
//! demo's terrain, or a generated world above its size limit), runs there, and deletes it
//! after (kept for no time). On a cluster it is made and deleted through the first node, and the
//! run's clients edit it through every node they were given, as they would the scene. That needs
//! an admin: any client on the server's own machine when the server has no auth file, or an
//! `admin` `--token`. Whatever refuses it is named with the ways around it.

use std::time::Duration;

use brickcast_client_core::session::Welcome;

use super::LoadError;

/// Largest edge the admin API builds a demo scene for (beyond it: terrain).
const DEMO_EDGE: u32 = 1024;

/// A scratch scene that exists until [`Scratch::delete`].
pub struct Scratch {
    base: String,
    pub name: String,
    token: Option<String>,
}

impl Scratch {
    /// Creates the scratch scene for a run on `welcome`'s scene at `ws_url`.
    pub async fn create(
        ws_url: &str,
        token: Option<&str>,
        welcome: &Welcome,
    ) -> Result<Scratch, LoadError> {
        let refused = |why: String| LoadError::Scratch {
            scene: welcome.scene.clone(),
            bricks: welcome.total_bricks,
            why,
        };
        let base = http_base(ws_url).ok_or_else(|| refused(format!("{ws_url} names no host")))?;
        // Unique enough: one run per process at a time, and the time tells runs apart.
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default()
            .as_millis()
            % 1_000_000;
        let prefix: String = welcome.scene.chars().take(40).collect();
        let name = format!("{prefix}.load-{}-{stamp}", std::process::id());
        let size = welcome.size;
        let kind = if size.iter().all(|&e| e <= DEMO_EDGE) {
            "demo"
        } else {
            "terrain"
        };
        let scratch = Scratch {
            base,
            name,
            token: token.map(String::from),
        };
        let body = serde_json::json!({ "kind": kind, "size": size });
        scratch
            .call(
                "POST",
                &format!("/admin/scenes/{}", scratch.name),
                Some(body),
            )
            .await
            .map_err(refused)?;
        tracing::info!(
            scene = %welcome.scene,
            scratch = %scratch.name,
            "the run edits a scratch scene of the same size (--in-place edits the scene itself); it is deleted afterwards"
        );
        Ok(scratch)
    }

    /// The scratch scene's websocket address at each server of `ws_urls` (the scene's
    /// addresses, as `crate::link::websocket_url` makes them), in their order.
    pub fn urls(&self, ws_urls: &[String]) -> Vec<String> {
        ws_urls
            .iter()
            .map(|u| http_base(u).unwrap_or_else(|| self.base.clone()))
            .map(|base| {
                let host = base.trim_start_matches("http://");
                format!("ws://{host}/scenes/{}/ws", self.name)
            })
            .collect()
    }

    /// Deletes the scratch scene (at once: it is kept for no time).
    pub async fn delete(self) {
        let path = format!("/admin/scenes/{0}?confirm={0}&keep=0s", self.name);
        if let Err(e) = self.call("DELETE", &path, None).await {
            tracing::warn!(scratch = %self.name, error = %e, "could not delete the scratch scene: `brickcast-server admin delete` it");
        }
    }

    /// One admin request, off the async threads; the server's `{"error"}` on failure.
    async fn call(
        &self,
        method: &'static str,
        path: &str,
        body: Option<serde_json::Value>,
    ) -> Result<(), String> {
        let url = format!("{}{path}", self.base);
        let auth = self.token.as_ref().map(|t| format!("Bearer {t}"));
        let request = move || -> Result<(), String> {
            let agent: ureq::Agent = ureq::Agent::config_builder()
                .http_status_as_error(false)
                .timeout_global(Some(Duration::from_secs(600)))
                .build()
                .into();
            let response = match method {
                "DELETE" => {
                    let mut r = agent.delete(&url);
                    if let Some(auth) = &auth {
                        r = r.header("authorization", auth);
                    }
                    r.call()
                }
                _ => {
                    let mut r = agent.post(&url).header("content-type", "application/json");
                    if let Some(auth) = &auth {
                        r = r.header("authorization", auth);
                    }
                    r.send(body.unwrap_or_default().to_string())
                }
            };
            let mut response = response.map_err(|e| format!("{method} {url}: {e}"))?;
            if response.status().is_success() {
                return Ok(());
            }
            let status = response.status();
            let text = response.body_mut().read_to_string().unwrap_or_default();
            let error = serde_json::from_str::<serde_json::Value>(&text)
                .ok()
                .and_then(|v| v["error"].as_str().map(String::from));
            Err(error.unwrap_or_else(|| format!("{method} {url}: {status}")))
        };
        tokio::task::spawn_blocking(request)
            .await
            .map_err(|e| format!("the request failed: {e}"))?
    }
}

/// `http://HOST:PORT` of a `ws://HOST:PORT/…` address.
fn http_base(ws_url: &str) -> Option<String> {
    let host = ws_url.strip_prefix("ws://")?.split('/').next()?;
    (!host.is_empty()).then(|| format!("http://{host}"))
}
