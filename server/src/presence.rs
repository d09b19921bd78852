//! Presence: who is in a scene and where each of them looks and points, shared at a fixed rate.
//!
//! **Why not on the scene owner.** The owner stalls on every fsync and snapshot; presence must
//! keep flowing meanwhile and must never delay an edit. So each scene has a [`Hub`] beside its
//! owner: sessions write their latest view and cursor into it (latest wins, under a mutex held
//! for a few field writes), and one task per scene ticks at `Limits::presence_hz`, encodes what
//! changed since the last tick *once*, and queues the same bytes to every peer.
//!
//! **Lossy by design.** Presence is never logged. A peer whose outgoing queue is longer than
//! [`MAX_QUEUED`] is skipped and marked stale; when its queue has drained it gets one full frame
//! (the whole roster and every state) instead of the frames it missed, so a slow or stalled
//! client holds at most one presence frame and never a backlog.
//!
//! Joins, renames and leaves ride in the same frames. A joining session registers before its
//! `Welcome` is built (the Welcome lists the roster it saw) and is sent nothing until the
//! Welcome is queued; then its first frame is a full one.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use brickcast_protocol::wire::{Cursor, Peer, PeerId, PeerState, ServerMsg, View, encode_server};
use bytes::Bytes;

use crate::metrics::Metrics;
use crate::scene::Outbox;

/// A peer whose queue holds more than this is skipped (and gets a full frame later).
pub const MAX_QUEUED: usize = 256 << 10;

struct Member {
    peer: Peer,
    state: PeerState,
    out: Outbox,
    /// Its Welcome is queued: frames may go to it.
    welcomed: bool,
    /// It missed frames (or never had one): its next frame is a full one.
    stale: bool,
}

#[derive(Default)]
struct Roster {
    members: BTreeMap<PeerId, Member>,
    /// Since the last tick: peers that joined or were renamed, peers that left, states that
    /// changed.
    joined: BTreeMap<PeerId, Peer>,
    left: Vec<PeerId>,
    changed: BTreeMap<PeerId, PeerState>,
}

/// One scene's presence: the roster and latest states, and what changed since the last tick.
pub struct Hub {
    roster: Mutex<Roster>,
    interval: Duration,
    closed: AtomicBool,
}

impl Hub {
    /// A hub sending at most `hz` frames a second.
    pub fn new(hz: u32) -> Hub {
        Hub {
            roster: Mutex::new(Roster::default()),
            interval: Duration::from_secs_f64(1.0 / f64::from(hz.max(1))),
            closed: AtomicBool::new(false),
        }
    }

    fn roster(&self) -> std::sync::MutexGuard<'_, Roster> {
        // Every change under the lock is a few field writes: a poisoned roster is still whole.
        self.roster.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Registers a joining peer and returns it (its colour changed if another user present
    /// shows the same one, see `identity::colour_among`) with everyone else present, for its
    /// Welcome. It is sent nothing until [`Hub::welcomed`].
    pub fn join(&self, mut peer: Peer, out: Outbox) -> (Peer, Vec<Peer>) {
        let mut roster = self.roster();
        let others: Vec<Peer> = roster.members.values().map(|m| m.peer.clone()).collect();
        match others.iter().find(|p| p.user == peer.user) {
            // The same user in another window keeps the colour it shows there.
            Some(same) => peer.colour = same.colour,
            None => {
                let taken: Vec<_> = others.iter().map(|p| p.colour).collect();
                peer.colour = crate::identity::colour_among(peer.user, &taken);
            }
        }
        let id = peer.id;
        roster.joined.insert(id, peer.clone());
        roster.members.insert(
            id,
            Member {
                state: PeerState {
                    id,
                    view: None,
                    cursor: None,
                },
                peer: peer.clone(),
                out,
                welcomed: false,
                stale: true,
            },
        );
        (peer, others)
    }

    /// The peer's Welcome is queued: frames may follow it.
    pub fn welcomed(&self, id: PeerId) {
        if let Some(m) = self.roster().members.get_mut(&id) {
            m.welcomed = true;
        }
    }

    /// The peer's latest view and cursor (checked by the session).
    pub fn update(&self, id: PeerId, view: Option<View>, cursor: Option<Cursor>) {
        let mut roster = self.roster();
        let Some(m) = roster.members.get_mut(&id) else {
            return;
        };
        if m.state.view == view && m.state.cursor == cursor {
            return;
        }
        m.state.view = view;
        m.state.cursor = cursor;
        let state = m.state;
        roster.changed.insert(id, state);
    }

    /// The peer's new display name (checked by the session).
    pub fn rename(&self, id: PeerId, name: String) {
        let mut roster = self.roster();
        let Some(m) = roster.members.get_mut(&id) else {
            return;
        };
        m.peer.name = name;
        let peer = m.peer.clone();
        roster.joined.insert(id, peer);
    }

    /// The peer left.
    pub fn leave(&self, id: PeerId) {
        let mut roster = self.roster();
        if roster.members.remove(&id).is_some() {
            roster.joined.remove(&id);
            roster.changed.remove(&id);
            roster.left.push(id);
        }
    }

    /// Names of the peers present, in joining order (the scene list shows them).
    pub fn names(&self) -> Vec<String> {
        self.roster()
            .members
            .values()
            .map(|m| m.peer.name.clone())
            .collect()
    }

    /// Peers present.
    pub fn len(&self) -> usize {
        self.roster().members.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Stops the hub's task (the scene stopped).
    pub fn close(&self) {
        self.closed.store(true, Relaxed);
    }

    /// One tick: sends what changed to every peer that keeps up, a full frame to each stale
    /// peer whose queue has drained. Returns the bytes queued.
    pub fn tick(&self, metrics: &Metrics) -> usize {
        let mut roster = self.roster();
        let joined: Vec<Peer> = std::mem::take(&mut roster.joined).into_values().collect();
        let left = std::mem::take(&mut roster.left);
        let states: Vec<PeerState> = std::mem::take(&mut roster.changed).into_values().collect();
        let delta = if joined.is_empty() && left.is_empty() && states.is_empty() {
            None
        } else {
            encode(
                ServerMsg::Presence {
                    full: false,
                    joined,
                    left,
                    states,
                },
                metrics,
            )
        };
        let mut sent = 0;
        let Roster { members, .. } = &mut *roster;
        let needs_full = members
            .values()
            .any(|m| m.welcomed && m.stale && m.out.queued() <= MAX_QUEUED);
        let full = if needs_full {
            encode(
                ServerMsg::Presence {
                    full: true,
                    joined: members.values().map(|m| m.peer.clone()).collect(),
                    left: Vec::new(),
                    states: members.values().map(|m| m.state).collect(),
                },
                metrics,
            )
        } else {
            None
        };
        for m in members.values_mut() {
            if !m.welcomed {
                continue;
            }
            if m.out.queued() > MAX_QUEUED {
                if delta.is_some() {
                    m.stale = true;
                    Metrics::add(&metrics.presence_skipped, 1);
                }
                continue;
            }
            let frame = if m.stale { &full } else { &delta };
            if let Some(frame) = frame
                && m.out.push(frame.clone())
            {
                sent += frame.len();
                m.stale = false;
                Metrics::add(&metrics.presence_frames, 1);
            }
        }
        Metrics::add(&metrics.presence_bytes, sent as u64);
        sent
    }
}

fn encode(msg: ServerMsg, metrics: &Metrics) -> Option<Bytes> {
    match encode_server(&msg) {
        Ok(frame) => Some(Bytes::from(frame)),
        Err(e) => {
            tracing::error!(error = %e, "cannot encode a presence frame");
            metrics.count_unencodable("Presence");
            None
        }
    }
}

/// Ticks `hub` until it is closed.
pub async fn run(hub: Arc<Hub>, metrics: Arc<Metrics>) {
    let mut ticks = tokio::time::interval(hub.interval);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    while !hub.closed.load(Relaxed) {
        ticks.tick().await;
        hub.tick(&metrics);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::Colour;
    use brickcast_protocol::wire::{Role, decode_server};
    use std::sync::atomic::AtomicUsize;

    fn peer(id: PeerId) -> Peer {
        Peer {
            id,
            user: id,
            name: format!("p{id}"),
            colour: Colour::WHITE,
            role: Role::Editor,
        }
    }

    fn frames(rx: &mut crate::scene::OutboxReceiver) -> Vec<ServerMsg> {
        std::iter::from_fn(|| rx.try_take())
            .filter_map(|f| decode_server(&f, &brickcast_protocol::wire::Limits::hard_caps()).ok())
            .collect()
    }

    #[test]
    fn a_long_queue_skips_frames_and_then_gets_one_full_frame() {
        let metrics = Metrics::default();
        let total = Arc::new(AtomicUsize::new(0));
        let hub = Hub::new(20);
        let (out1, mut rx1) = Outbox::new(total.clone());
        let (out2, mut rx2) = Outbox::new(total.clone());
        assert!(hub.join(peer(1), out1.clone()).1.is_empty());
        let (second, others) = hub.join(peer(2), out2.clone());
        assert_eq!(others.len(), 1);
        assert_ne!(second.colour, others[0].colour, "two people, two colours");
        // Nothing before the Welcome.
        hub.tick(&metrics);
        assert!(frames(&mut rx1).is_empty());
        hub.welcomed(1);
        hub.welcomed(2);
        hub.tick(&metrics);
        for rx in [&mut rx1, &mut rx2] {
            match frames(rx).as_slice() {
                [
                    ServerMsg::Presence {
                        full: true, joined, ..
                    },
                ] => assert_eq!(joined.len(), 2),
                other => panic!("{other:?}"),
            }
        }
        // Peer 2 stops reading: its queue is long. Peer 1 moves many times.
        out2.push(Bytes::from(vec![0u8; MAX_QUEUED + 1]));
        let view = |x: f32| View {
            eye: [x, 0.0, 0.0],
            forward: [0.0, 0.0, 1.0],
        };
        for i in 0..50 {
            hub.update(1, Some(view(i as f32)), None);
            hub.tick(&metrics);
        }
        assert_eq!(frames(&mut rx1).len(), 50);
        assert_eq!(metrics.presence_skipped.load(Relaxed), 50);
        // Peer 2 drains: one full frame with the latest state, not fifty.
        let backlog = frames(&mut rx2);
        assert!(backlog.is_empty(), "{backlog:?}");
        hub.tick(&metrics);
        match frames(&mut rx2).as_slice() {
            [
                ServerMsg::Presence {
                    full: true, states, ..
                },
            ] => {
                let s = states.iter().find(|s| s.id == 1).unwrap();
                assert_eq!(s.view, Some(view(49.0)));
            }
            other => panic!("{other:?}"),
        }
        hub.leave(1);
        hub.tick(&metrics);
        match frames(&mut rx2).as_slice() {
            [
                ServerMsg::Presence {
                    full: false, left, ..
                },
            ] => assert_eq!(left, &[1]),
            other => panic!("{other:?}"),
        }
    }
}
