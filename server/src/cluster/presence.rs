//! Presence across nodes: people connected to different nodes of a cluster see each other.
//!
//! **Why core NATS, not JetStream.** Presence is lossy and never logged (see
//! `crate::presence`): what matters is the latest view and cursor, a fraction of a second old.
//! So each node publishes what changed among its own peers on the scene's subject
//! `brickcast.presence.<scene>` at the hub's rate, and every node subscribes to it. Nothing is
//! stored, acknowledged or replayed.
//!
//! **Repair by repetition.** Core NATS may drop a message (a slow subscriber, a reconnect). So
//! every [`FULL_EVERY`] a node with peers also publishes its whole local roster: a receiver
//! replaces what it holds for that node, which puts back a lost join or state and drops a
//! peer whose leave was lost. A node not heard from for [`SILENT_AFTER`] (it died, or lost its
//! connection to NATS) has its peers removed; a node that restarts under the same name has a
//! new instance number, and its old peers go at once.
//!
//! **Ids.** A peer's id is its session id on its own node, so ids from different nodes
//! collide. [`Remotes`] gives each remote peer an id of this node's own, from
//! `presence::REMOTE_IDS` up, kept while that peer stays; local clients only ever see those.
//!
//! Entries are checked like a client's own message (names, finite numbers, a cursor inside
//! the scene): a node running other code, or a message that is not ours, cannot put garbage on
//! anyone's screen. What cannot be read is counted and dropped.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::signal;
use brickcast_protocol::wire::{Peer, PeerId, PeerState, check_display_name};
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};

use crate::envelope::{EnvelopeError, Format};
use crate::metrics::Metrics;
use crate::presence::{Hub, REMOTE_IDS};
use crate::scene::SceneHandle;

/// How often a node with peers publishes its whole local roster.
pub const FULL_EVERY: Duration = Duration::from_secs(1);
/// A node not heard from this long has its peers removed.
pub const SILENT_AFTER: Duration = Duration::from_secs(4);
/// A presence message between nodes: a tag and the format's version, at most 8 MiB.
const FORMAT: Format<{ 8 << 20 }> = Format::new("presence message", b"P\x01");

pub fn subject(scene: &str) -> String {
    format!("brickcast.presence.{}", super::log::token(scene))
}

/// What one node tells the others about its own peers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Relay {
    pub node: String,
    /// Differs each time a node process starts.
    pub instance: u64,
    /// The whole local roster (anyone not in `joined` has left), not just what changed.
    pub full: bool,
    /// Peers that joined or were renamed (in a full message: every peer).
    pub joined: Vec<Peer>,
    pub left: Vec<PeerId>,
    pub states: Vec<PeerState>,
}

impl Relay {
    pub fn encode(&self) -> Result<Vec<u8>, EnvelopeError> {
        FORMAT.encode(self)
    }

    pub fn decode(bytes: &[u8]) -> Result<Relay, EnvelopeError> {
        FORMAT.decode(bytes)
    }
}

/// This process's instance number (differs between runs of a node with the same name).
fn instance() -> u64 {
    static INSTANCE: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *INSTANCE.get_or_init(|| {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        nanos ^ (u64::from(std::process::id()) << 40)
    })
}

/// One other node's peers as this node knows them.
struct Origin {
    instance: u64,
    heard: Instant,
    /// Its id for a peer → the id this node shows for it.
    ids: HashMap<PeerId, PeerId>,
}

/// The peers of every other node, kept in the hub under ids of this node's own.
pub struct Remotes {
    origins: HashMap<String, Origin>,
    next_id: PeerId,
    size: [u32; 3],
    max_radius: f32,
}

impl Remotes {
    pub fn new(size: [u32; 3], max_radius: f32) -> Remotes {
        Remotes {
            origins: HashMap::new(),
            next_id: REMOTE_IDS,
            size,
            max_radius,
        }
    }

    /// Applies one node's message to `hub`. Returns the entries refused (bad names or
    /// numbers, or the hub full).
    pub fn apply(&mut self, msg: Relay, now: Instant, hub: &Hub) -> u64 {
        let origin = self
            .origins
            .entry(msg.node.clone())
            .or_insert_with(|| Origin {
                instance: msg.instance,
                heard: now,
                ids: HashMap::new(),
            });
        if origin.instance != msg.instance {
            // The node restarted: the peers of its last run are gone.
            for (_, id) in origin.ids.drain() {
                hub.remote_leave(id);
            }
            origin.instance = msg.instance;
        }
        origin.heard = now;
        let mut refused = 0;
        if msg.full {
            let present: std::collections::HashSet<PeerId> =
                msg.joined.iter().map(|p| p.id).collect();
            origin.ids.retain(|theirs, ours| {
                let keep = present.contains(theirs);
                if !keep {
                    hub.remote_leave(*ours);
                }
                keep
            });
        }
        for mut peer in msg.joined {
            if check_display_name(&peer.name).is_err() {
                refused += 1;
                continue;
            }
            let theirs = peer.id;
            let ours = *origin.ids.entry(theirs).or_insert_with(|| {
                let id = self.next_id;
                self.next_id += 1;
                id
            });
            peer.id = ours;
            if !hub.remote_join(peer) {
                origin.ids.remove(&theirs);
                refused += 1;
            }
        }
        for theirs in msg.left {
            if let Some(ours) = origin.ids.remove(&theirs) {
                hub.remote_leave(ours);
            }
        }
        for mut state in msg.states {
            let Some(&ours) = origin.ids.get(&state.id) else {
                continue;
            };
            if crate::presence::check(
                &state.view,
                &state.cursor,
                &state.selection,
                self.size,
                self.max_radius,
            )
            .is_err()
            {
                refused += 1;
                continue;
            }
            state.id = ours;
            hub.remote_update(state);
        }
        refused
    }

    /// Removes the peers of nodes not heard from for [`SILENT_AFTER`].
    pub fn expire(&mut self, now: Instant, hub: &Hub) {
        self.origins.retain(|node, origin| {
            let alive = now.duration_since(origin.heard) < SILENT_AFTER;
            if !alive {
                if !origin.ids.is_empty() {
                    tracing::info!(node = %node, peers = origin.ids.len(), "no presence from a node: its peers are gone");
                }
                for (_, id) in origin.ids.drain() {
                    hub.remote_leave(id);
                }
            }
            alive
        });
    }
}

/// Relays `scene`'s presence to and from the other nodes until the scene stops or the server
/// shuts down.
pub fn start(
    client: async_nats::Client,
    node: String,
    scene: &SceneHandle,
    metrics: Arc<Metrics>,
    shutdown: signal::Receiver<bool>,
) {
    let hub = scene.presence.clone();
    hub.relay_local();
    let remotes = Remotes::new(scene.size, scene.limits.max_brush_radius);
    let subject = subject(&scene.name);
    let name = scene.name.clone();
    tokio::spawn(async move {
        let relay = Relayer {
            client,
            node,
            subject,
            hub,
            metrics,
        };
        if let Err(e) = relay.run(remotes, shutdown).await {
            tracing::warn!(scene = %name, error = %e, "presence relay stopped: people on other nodes are not shown");
        }
    });
}

struct Relayer {
    client: async_nats::Client,
    node: String,
    subject: String,
    hub: Arc<Hub>,
    metrics: Arc<Metrics>,
}

impl Relayer {
    async fn publish(
        &self,
        full: bool,
        joined: Vec<Peer>,
        left: Vec<PeerId>,
        states: Vec<PeerState>,
    ) {
        let msg = Relay {
            node: self.node.clone(),
            instance: instance(),
            full,
            joined,
            left,
            states,
        };
        match msg.encode() {
            Ok(bytes) => match self
                .client
                .publish(self.subject.clone(), bytes.into())
                .await
            {
                Ok(()) => Metrics::add(&self.metrics.presence_relayed, 1),
                Err(e) => tracing::debug!(error = %e, "cannot publish presence"),
            },
            Err(e) => tracing::error!(error = %e, "cannot encode a presence message"),
        }
    }

    async fn run(
        &self,
        mut remotes: Remotes,
        mut shutdown: signal::Receiver<bool>,
    ) -> Result<(), async_nats::SubscribeError> {
        let mut incoming = self.client.subscribe(self.subject.clone()).await?;
        let mut ticks = tokio::time::interval(self.hub.interval());
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut last_full = Instant::now() - FULL_EVERY;
        // Whether the last full message listed anyone: an empty roster is sent once, then
        // not again until someone joins.
        let mut had_peers = false;
        loop {
            if shutdown.get() || self.hub.is_closed() {
                break;
            }
            tokio::select! {
                _ = ticks.tick() => {
                    let now = Instant::now();
                    if now.duration_since(last_full) >= FULL_EVERY {
                        self.hub.take_local();
                        let (joined, states) = self.hub.local_full();
                        if !joined.is_empty() || had_peers {
                            had_peers = !joined.is_empty();
                            self.publish(true, joined, Vec::new(), states).await;
                        }
                        last_full = now;
                    } else {
                        let changes = self.hub.take_local();
                        if !changes.is_empty() {
                            self.publish(false, changes.joined, changes.left, changes.states).await;
                        }
                    }
                    remotes.expire(now, &self.hub);
                }
                msg = incoming.next() => {
                    let Some(msg) = msg else { break };
                    match Relay::decode(&msg.payload) {
                        Ok(relay) if relay.node == self.node && relay.instance == instance() => {}
                        Ok(relay) => {
                            let refused = remotes.apply(relay, Instant::now(), &self.hub);
                            Metrics::add(&self.metrics.presence_relay_refused, refused);
                        }
                        Err(e) => {
                            tracing::debug!(error = %e, "a presence message that cannot be read");
                            Metrics::add(&self.metrics.presence_relay_refused, 1);
                        }
                    }
                }
                _ = shutdown.changed() => {}
            }
        }
        // Leaving: the others drop this node's peers now rather than after SILENT_AFTER.
        self.publish(true, Vec::new(), Vec::new(), Vec::new()).await;
        let _ = self.client.flush().await;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Outbox;
    use brickcast_protocol::Colour;
    use brickcast_protocol::wire::{Cursor, Role, View};
    use std::sync::atomic::AtomicUsize;

    fn peer(id: PeerId, name: &str) -> Peer {
        Peer {
            id,
            user: 100 + id,
            name: name.into(),
            colour: Colour::WHITE,
            role: Role::Editor,
        }
    }

    fn relay(node: &str, instance: u64, full: bool) -> Relay {
        Relay {
            node: node.into(),
            instance,
            full,
            joined: Vec::new(),
            left: Vec::new(),
            states: Vec::new(),
        }
    }

    /// Names of the remote peers a new local client would be told about.
    fn others(hub: &Hub) -> Vec<(PeerId, String)> {
        let total = Arc::new(AtomicUsize::new(0));
        let (out, _rx) = Outbox::new(total);
        let (me, others) = hub.join(peer(999, "me"), out);
        hub.leave(me.id);
        let mut v: Vec<_> = others.into_iter().map(|p| (p.id, p.name)).collect();
        v.sort();
        v
    }

    #[test]
    fn messages_round_trip_and_garbage_is_refused() {
        let mut m = relay("a", 7, false);
        m.joined.push(peer(1, "alice"));
        m.left.push(3);
        m.states.push(PeerState {
            id: 1,
            view: Some(View {
                eye: [1.0, 2.0, 3.0],
                forward: [0.0, 0.0, 1.0],
            }),
            cursor: None,
            selection: None,
        });
        let bytes = m.encode().unwrap();
        assert_eq!(Relay::decode(&bytes).unwrap(), m);
        assert!(Relay::decode(&bytes[..bytes.len() - 1]).is_err());
        assert!(Relay::decode(b"T\x01whatever").is_err());
        assert!(Relay::decode(&[]).is_err());
        let mut long = bytes.clone();
        long.push(0);
        assert!(Relay::decode(&long).is_err());
    }

    #[test]
    fn remote_peers_get_ids_of_their_own_and_leave_with_their_node() {
        let hub = Hub::new(20);
        let mut r = Remotes::new([64, 64, 64], 8.0);
        let t0 = Instant::now();
        // Two nodes whose sessions both have id 1.
        let mut a = relay("a", 1, false);
        a.joined.push(peer(1, "alice"));
        let mut b = relay("b", 1, false);
        b.joined.push(peer(1, "bob"));
        assert_eq!(r.apply(a, t0, &hub), 0);
        assert_eq!(r.apply(b, t0, &hub), 0);
        let seen = others(&hub);
        assert_eq!(seen.len(), 2);
        assert!(seen.iter().all(|(id, _)| *id >= REMOTE_IDS));
        assert_ne!(seen[0].0, seen[1].0);
        let alice = seen.iter().find(|(_, n)| n == "alice").unwrap().0;

        // A state for alice, one out of range (refused), one for someone unknown (ignored).
        let mut s = relay("a", 1, false);
        let cursor = |x| Cursor {
            voxel: [x, 0, 0],
            radius: 1.0,
        };
        s.states.push(PeerState {
            id: 1,
            view: None,
            cursor: Some(cursor(5)),
            selection: None,
        });
        s.states.push(PeerState {
            id: 1,
            view: None,
            cursor: Some(cursor(64)),
            selection: None,
        });
        s.states.push(PeerState {
            id: 2,
            view: None,
            cursor: Some(cursor(5)),
            selection: None,
        });
        assert_eq!(r.apply(s, t0, &hub), 1);

        // A bad name is refused; a rename keeps the id.
        let mut n = relay("a", 1, false);
        n.joined.push(peer(4, "bad\tname"));
        n.joined.push(peer(1, "Alice"));
        assert_eq!(r.apply(n, t0, &hub), 1);
        let seen = others(&hub);
        assert!(seen.contains(&(alice, "Alice".into())), "{seen:?}");
        assert_eq!(seen.len(), 2);

        // A full message from b without bob: bob left (his leave was lost).
        let mut full = relay("b", 1, true);
        full.joined.push(peer(2, "carol"));
        r.apply(full, t0, &hub);
        let names: Vec<_> = others(&hub).into_iter().map(|(_, n)| n).collect();
        assert_eq!(names, ["Alice", "carol"]);

        // b restarts (a new instance): carol of the last run is gone.
        let mut again = relay("b", 2, false);
        again.joined.push(peer(1, "dave"));
        r.apply(again, t0 + Duration::from_secs(1), &hub);
        let names: Vec<_> = others(&hub).into_iter().map(|(_, n)| n).collect();
        assert_eq!(names, ["Alice", "dave"]);

        // a goes silent: alice goes; b was heard from later and stays.
        r.expire(t0 + SILENT_AFTER, &hub);
        let names: Vec<_> = others(&hub).into_iter().map(|(_, n)| n).collect();
        assert_eq!(names, ["dave"]);
    }

    #[test]
    fn local_changes_are_kept_for_the_relay_only_once_asked() {
        let hub = Hub::new(20);
        let total = Arc::new(AtomicUsize::new(0));
        let (out, _rx) = Outbox::new(total);
        hub.join(peer(1, "early"), out.clone());
        assert!(hub.take_local().is_empty(), "not relayed yet");
        hub.relay_local();
        hub.join(peer(2, "x"), out.clone());
        hub.update(
            2,
            None,
            Some(Cursor {
                voxel: [1, 1, 1],
                radius: 0.0,
            }),
            Some(brickcast_protocol::wire::Selection::between(
                [1, 1, 1],
                [2, 3, 4],
            )),
        );
        hub.join(peer(3, "gone"), out);
        hub.leave(3);
        // A remote peer is not relayed back.
        hub.remote_join(peer(REMOTE_IDS, "far"));
        let c = hub.take_local();
        assert_eq!(
            c.joined.iter().map(|p| p.id).collect::<Vec<_>>(),
            [2],
            "{c:?}"
        );
        assert_eq!(c.left, [3]);
        assert_eq!(c.states.len(), 1);
        assert_eq!(
            c.states[0].selection.map(|s| s.extent()),
            Some([2, 3, 4]),
            "the selection is relayed"
        );
        assert!(hub.take_local().is_empty());
        let (peers, states) = hub.local_full();
        assert_eq!(peers.len(), 2);
        assert_eq!(states.len(), 2);
    }
}
