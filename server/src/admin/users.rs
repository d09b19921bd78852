//! Disconnecting a user (`POST /admin/kick`), and keeping them out for a while.
//!
//! Clients reconnect by themselves, so a kick that only closed the connections would be
//! undone within a second: a kicked user is also refused for `for` (default [`KICK_FOR`]),
//! by user id and by name (its look-alike key, `crate::identity::name_key`), on the one scene
//! the kick names or on all of them. Refusals live in this server's memory: a restart
//! forgets them, and in a cluster a kick reaches only the connections to the node asked.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::Json;
use axum::extract::State;
use brickcast_protocol::wire::{ErrorCode, Peer, UserId};
use serde::Deserialize;
use serde_json::{Value, json};

use super::{Admin, AdminError, Body, parse_duration};
use crate::App;
use crate::identity::name_key;

/// How long a kicked user is refused when the kick does not say.
pub const KICK_FOR: Duration = Duration::from_secs(600);
/// Most refusals held at once (the oldest go first): a kick is an admin's act, but a script
/// could make many.
const MAX_BANS: usize = 4096;

/// Users refused for now.
#[derive(Default)]
pub struct Bans {
    bans: Mutex<Vec<Ban>>,
}

struct Ban {
    user: Option<UserId>,
    name: Option<String>,
    scene: Option<String>,
    until: Instant,
}

impl Ban {
    fn matches(&self, user: UserId, name: &str, scene: &str) -> bool {
        self.scene.as_deref().is_none_or(|s| s == scene)
            && (self.user == Some(user) || self.name.as_deref() == Some(&name_key(name)))
    }
}

impl Bans {
    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<Ban>> {
        self.bans.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Why a joining user is refused, if they are.
    pub fn refusal(&self, user: UserId, name: &str, scene: &str) -> Option<String> {
        let now = Instant::now();
        let mut bans = self.lock();
        bans.retain(|b| b.until > now);
        let left = bans
            .iter()
            .filter(|b| b.matches(user, name, scene))
            .map(|b| b.until - now)
            .max()?;
        Some(format!(
            "an administrator disconnected you; you may come back in {}",
            minutes(left)
        ))
    }

    fn add(&self, ban: Ban) {
        let mut bans = self.lock();
        if bans.len() >= MAX_BANS {
            bans.sort_by_key(|b| b.until);
            bans.remove(0);
        }
        bans.push(ban);
    }
}

/// `3 min`, `1 h 5 min`: whole minutes, rounded up, for people.
fn minutes(d: Duration) -> String {
    let m = d.as_secs().div_ceil(60).max(1);
    match (m / 60, m % 60) {
        (0, m) => format!("{m} min"),
        (h, 0) => format!("{h} h"),
        (h, m) => format!("{h} h {m} min"),
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Kick {
    /// The user's display name (look-alikes match too).
    name: Option<String>,
    /// Or the user's id (`GET /admin/scenes` lists both).
    user: Option<UserId>,
    /// Only this scene (default: every scene).
    scene: Option<String>,
    /// How long they are refused after (`0s`: not at all).
    #[serde(rename = "for")]
    refuse_for: Option<String>,
}

/// `POST /admin/kick`.
pub async fn kick(
    _: Admin,
    State(app): State<Arc<App>>,
    Body(kick): Body<Kick>,
) -> Result<Json<Value>, AdminError> {
    if kick.name.is_none() && kick.user.is_none() {
        return Err(AdminError::BadInput(
            "say whom to disconnect: \"name\" or \"user\" (an id)".into(),
        ));
    }
    let refuse_for = match &kick.refuse_for {
        Some(text) => parse_duration(text).map_err(AdminError::BadInput)?,
        None => KICK_FOR,
    };
    let scenes = match &kick.scene {
        Some(name) => match app.scene(name) {
            Some(scene) => vec![(name.clone(), scene)],
            None => return Err(AdminError::UnknownScene(name.clone())),
        },
        None => app.scene_list(),
    };
    let key = kick.name.as_deref().map(name_key);
    let which = |p: &Peer| kick.user == Some(p.user) || key.as_deref() == Some(&name_key(&p.name));
    let text = if refuse_for.is_zero() {
        "an administrator disconnected you".to_string()
    } else {
        format!(
            "an administrator disconnected you; you may come back in {}",
            minutes(refuse_for)
        )
    };
    let mut closed = Vec::new();
    for (scene, handle) in &scenes {
        for peer in handle
            .presence
            .disconnect(which, ErrorCode::Unauthorized, &text)
        {
            closed.push(json!({
                "scene": scene,
                "session": peer.id,
                "user": peer.user,
                "name": peer.name,
            }));
        }
    }
    if closed.is_empty() {
        return Err(AdminError::BadInput(format!(
            "nobody like that is connected to {}: `admin list` (GET /admin/scenes) lists who is",
            kick.scene.as_deref().unwrap_or("any scene of this server")
        )));
    }
    if !refuse_for.is_zero() {
        app.bans.add(Ban {
            user: kick.user,
            name: key,
            scene: kick.scene.clone(),
            until: Instant::now() + refuse_for,
        });
    }
    tracing::info!(name = ?kick.name, user = ?kick.user, scene = ?kick.scene, closed = closed.len(), refused_s = refuse_for.as_secs(), "an administrator disconnected a user");
    Ok(Json(json!({
        "disconnected": closed,
        "refused_for_s": refuse_for.as_secs(),
    })))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kicked_user_is_refused_by_id_or_look_alike_name_until_the_time_is_up() {
        let bans = Bans::default();
        let soon = Instant::now() + Duration::from_secs(90);
        bans.add(Ban {
            user: None,
            name: Some(name_key("Mallory")),
            scene: Some("demo".into()),
            until: soon,
        });
        bans.add(Ban {
            user: Some(42),
            name: None,
            scene: None,
            until: soon,
        });
        let why = bans
            .refusal(7, "MaIlory", "demo")
            .expect("look-alike refused");
        assert!(why.contains("come back in 2 min"), "{why}");
        assert!(bans.refusal(7, "Mallory", "other").is_none());
        assert!(bans.refusal(42, "anyone", "other").is_some());
        assert!(bans.refusal(8, "Alice", "demo").is_none());
        bans.add(Ban {
            user: Some(9),
            name: None,
            scene: None,
            until: Instant::now(),
        });
        assert!(bans.refusal(9, "x", "demo").is_none(), "expired");
        assert_eq!(minutes(Duration::from_secs(3 * 3600 + 1)), "3 h 1 min");
        assert_eq!(minutes(Duration::from_secs(7200)), "2 h");
    }
}
