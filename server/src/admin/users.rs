//! Disconnecting a user (`POST /admin/kick`), and keeping them out for a while.
//!
//! Clients reconnect by themselves, so a kick that only closed the connections would be
//! undone within a second: a kicked user is also refused for `for` (default [`KICK_FOR`]),
//! by user id and by name (its look-alike key, `crate::identity::name_key`), on the one scene
//! the kick names or on all of them. On a cluster every node is told (`cluster::kick`): each
//! closes the user's connections to it and refuses them. Refusals live in each server's
//! memory: a restart forgets them.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::Json;
use axum::extract::State;
use brickcast_protocol::wire::{ErrorCode, Peer, UserId};
use serde::Deserialize;
use serde_json::{Value, json};

use super::{Admin, AdminError, Body, parse_duration};
use crate::App;
use crate::cluster::kick::{self, Order, Round};
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
    if let Some(name) = &kick.scene
        && !app.has_scene(name).await
    {
        return Err(AdminError::UnknownScene(name.clone()));
    }
    let mut order = Order {
        user: kick.user,
        name: kick.name.clone(),
        scene: kick.scene.clone(),
        refuse_for_ms: u64::try_from(refuse_for.as_millis()).unwrap_or(u64::MAX),
        round: Round::Disconnect,
    };
    let nobody = || {
        AdminError::BadInput(format!(
            "nobody like that is connected to {}: `admin list` (GET /admin/scenes) lists who is",
            kick.scene.as_deref().unwrap_or("any scene of this server")
        ))
    };
    // On a cluster every node is asked (this one too, through NATS), in two rounds.
    let (closed, not_told) = match &app.node {
        None => {
            let closed = disconnect_here(&app, &order);
            if closed.is_empty() {
                return Err(nobody());
            }
            refuse_here(&app, &order);
            (closed, Vec::new())
        }
        Some(node) => {
            let mut closed = Vec::new();
            let mut not_told = Vec::new();
            for (name, answer) in kick::ask_all(&node.cluster, &order).await {
                match answer.and_then(|b| serde_json::from_slice::<Vec<Value>>(&b).ok()) {
                    Some(list) => closed.extend(list),
                    None => not_told.push(name),
                }
            }
            if closed.is_empty() {
                return Err(AdminError::BadInput(format!(
                    "nobody like that is connected to {} on any node that answered{}: `admin list` (GET /admin/scenes) lists who is",
                    kick.scene.as_deref().unwrap_or("any scene"),
                    if not_told.is_empty() {
                        String::new()
                    } else {
                        format!(" (not answering: {})", not_told.join(", "))
                    }
                )));
            }
            if !refuse_for.is_zero() {
                order.round = Round::Refuse;
                for (name, answer) in kick::ask_all(&node.cluster, &order).await {
                    if answer.is_none() {
                        not_told.push(name);
                    }
                }
            }
            not_told.sort();
            not_told.dedup();
            (closed, not_told)
        }
    };
    tracing::info!(name = ?kick.name, user = ?kick.user, scene = ?kick.scene, closed = closed.len(), refused_s = refuse_for.as_secs(), "an administrator disconnected a user");
    let mut answer = json!({
        "disconnected": closed,
        "refused_for_s": refuse_for.as_secs(),
    });
    if !not_told.is_empty() {
        answer["nodes_not_told"] = json!(not_told);
    }
    Ok(Json(answer))
}

/// What this node does with a kick order of the cluster's (`cluster::kick`): the answer's bytes.
pub fn handle_order(app: &App, order: &Order) -> Vec<u8> {
    match order.round {
        Round::Disconnect => serde_json::to_vec(&disconnect_here(app, order)).unwrap_or_default(),
        Round::Refuse => {
            refuse_here(app, order);
            b"[]".to_vec()
        }
    }
}

/// Closes this node's connections of whom `order` names; those closed, as the answer lists them.
fn disconnect_here(app: &App, order: &Order) -> Vec<Value> {
    let scenes = match &order.scene {
        Some(name) => app
            .scene(name)
            .map(|s| vec![(name.clone(), s)])
            .unwrap_or_default(),
        None => app.scene_list(),
    };
    let key = order.name.as_deref().map(name_key);
    let which = |p: &Peer| order.user == Some(p.user) || key.as_deref() == Some(&name_key(&p.name));
    let refuse_for = Duration::from_millis(order.refuse_for_ms);
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
            let mut entry = json!({
                "scene": scene,
                "session": peer.id,
                "user": peer.user,
                "name": peer.name,
            });
            if let Some(node) = app.node_name() {
                entry["node"] = json!(node);
            }
            closed.push(entry);
        }
    }
    closed
}

/// Refuses whom `order` names on this node for the order's time.
fn refuse_here(app: &App, order: &Order) {
    if order.refuse_for_ms == 0 {
        return;
    }
    app.bans.add(Ban {
        user: order.user,
        name: order.name.as_deref().map(name_key),
        scene: order.scene.clone(),
        until: Instant::now() + Duration::from_millis(order.refuse_for_ms),
    });
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
