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
//!
//! **Peers on other nodes.** In a cluster the hub also holds *remote* peers: people connected
//! to other nodes, fed in by `crate::cluster::presence` under ids of their own (from
//! [`REMOTE_IDS`] up, so they never meet this node's session ids). Local clients see them like
//! anyone else. What changes among the local peers is also kept for the relay
//! ([`Hub::take_local`]), which publishes it to the other nodes.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use brickcast_protocol::Colour;
use brickcast_protocol::wire::{
    Cursor, MAX_DISPLAY_NAME_BYTES, Peer, PeerId, PeerState, Refusal, Selection, ServerMsg, UserId,
    View, encode_server,
};
use bytes::Bytes;

use crate::metrics::Metrics;
use crate::scene::Outbox;

/// A peer whose queue holds more than this is skipped (and gets a full frame later).
pub const MAX_QUEUED: usize = 256 << 10;

/// Ids of peers on other nodes start here: this node's session ids (a counter from 1) never
/// get this far, and every id stays below 2^53, exact in a JavaScript number.
pub const REMOTE_IDS: PeerId = 1 << 52;

/// Most peers from other nodes one hub holds: with the local ones they stay well inside what
/// one presence frame may list (`MAX_PEERS_PER_FRAME`). Beyond it, remote joins are dropped.
pub const MAX_REMOTE: usize = 16_384;

struct Member {
    peer: Peer,
    state: PeerState,
    out: Outbox,
    /// Its Welcome is queued: frames may go to it.
    welcomed: bool,
    /// It missed frames (or never had one): its next frame is a full one.
    stale: bool,
}

/// A peer connected to another node (only in a cluster).
struct Remote {
    peer: Peer,
    state: PeerState,
}

/// What changed among this node's own peers, for the cluster relay.
#[derive(Debug, Default, PartialEq)]
pub struct LocalChanges {
    /// Joined or renamed.
    pub joined: Vec<Peer>,
    pub left: Vec<PeerId>,
    pub states: Vec<PeerState>,
}

impl LocalChanges {
    pub fn is_empty(&self) -> bool {
        self.joined.is_empty() && self.left.is_empty() && self.states.is_empty()
    }
}

#[derive(Default)]
struct Changes {
    joined: BTreeMap<PeerId, Peer>,
    left: Vec<PeerId>,
    changed: BTreeMap<PeerId, PeerState>,
}

impl Changes {
    fn join(&mut self, peer: Peer) {
        self.joined.insert(peer.id, peer);
    }

    fn leave(&mut self, id: PeerId) {
        self.joined.remove(&id);
        self.changed.remove(&id);
        self.left.push(id);
    }
}

#[derive(Default)]
struct Roster {
    members: BTreeMap<PeerId, Member>,
    remote: BTreeMap<PeerId, Remote>,
    /// Since the last tick: peers that joined or were renamed, peers that left, states that
    /// changed (local and remote alike).
    pending: Changes,
    /// Since the relay last took them: the same, local peers only. Kept only in a cluster.
    local: Option<Changes>,
    /// Who shows a name of each look-alike key (`identity::name_key`), and in how many
    /// windows: whether a name is taken is one lookup, not a key of every name present (a
    /// crowd of a thousand same-named clients made each join cost a million skeletons).
    keys: HashMap<String, HashMap<UserId, usize>>,
}

impl Roster {
    fn joined(&mut self, peer: &Peer, local: bool) {
        if local && let Some(l) = &mut self.local {
            l.join(peer.clone());
        }
        self.pending.join(peer.clone());
    }

    /// Two nodes can give one colour to two people who joined at the same moment (each picks
    /// among the peers it knows of). Of a local user and a remote one that look alike, the one
    /// that [`yields`] picks again, on its own node: both nodes apply the same rule, so exactly
    /// one of them changes. The change goes out like a rename, to this node's clients and to
    /// the other nodes. Every window of the user gets the new colour.
    fn recolour_against(&mut self, remote: &Peer) {
        let users: Vec<UserId> = self
            .members
            .values()
            .filter(|m| {
                yields(&m.peer, remote)
                    && crate::identity::looks_alike(m.peer.colour, remote.colour)
            })
            .map(|m| m.peer.user)
            .collect();
        self.recolour(users, None);
    }

    /// A user the auth file names keeps its own colour: local users a client chose the id of
    /// (so that it lands on that colour, say) and who show it pick again.
    fn give_way_to(&mut self, pinned: UserId) {
        let own = crate::identity::colour_of(pinned);
        let users: Vec<UserId> = self
            .members
            .values()
            .filter(|m| {
                !crate::identity::is_pinned(m.peer.user)
                    && crate::identity::looks_alike(m.peer.colour, own)
            })
            .map(|m| m.peer.user)
            .collect();
        self.recolour(users, Some(own));
    }

    /// `users` pick their colour again among everyone else's (and `also`), every window of
    /// each; the change goes out like a rename.
    fn recolour(&mut self, mut users: Vec<UserId>, also: Option<Colour>) {
        users.sort_unstable();
        users.dedup();
        for user in users {
            let taken: Vec<_> = self
                .peers()
                .filter(|p| p.user != user)
                .map(|p| p.colour)
                .chain(also)
                .collect();
            let colour = crate::identity::colour_among(user, &taken);
            let changed: Vec<Peer> = self
                .members
                .values_mut()
                .filter(|m| m.peer.user == user)
                .map(|m| {
                    m.peer.colour = colour;
                    m.peer.clone()
                })
                .collect();
            for peer in &changed {
                self.joined(peer, true);
            }
        }
    }

    /// Whether another user present (here or on another node) shows a name like `name`.
    fn name_taken(&self, user: UserId, name: &str) -> bool {
        self.keys
            .get(&crate::identity::name_key(name))
            .is_some_and(|users| users.keys().any(|u| *u != user))
    }

    /// `user` shows `name` in one more window.
    fn index(&mut self, name: &str, user: UserId) {
        let users = self
            .keys
            .entry(crate::identity::name_key(name))
            .or_default();
        *users.entry(user).or_insert(0) += 1;
    }

    /// `user` shows `name` in one window fewer.
    fn unindex(&mut self, name: &str, user: UserId) {
        let key = crate::identity::name_key(name);
        let Some(users) = self.keys.get_mut(&key) else {
            return;
        };
        if let Some(n) = users.get_mut(&user) {
            *n -= 1;
            if *n == 0 {
                users.remove(&user);
            }
        }
        if users.is_empty() {
            self.keys.remove(&key);
        }
    }

    fn left(&mut self, id: PeerId, local: bool) {
        if local && let Some(l) = &mut self.local {
            l.leave(id);
        }
        self.pending.leave(id);
    }

    fn changed(&mut self, state: PeerState, local: bool) {
        if local && let Some(l) = &mut self.local {
            l.changed.insert(state.id, state);
        }
        self.pending.changed.insert(state.id, state);
    }

    /// Everyone present, local and remote.
    fn peers(&self) -> impl Iterator<Item = &Peer> {
        self.members
            .values()
            .map(|m| &m.peer)
            .chain(self.remote.values().map(|r| &r.peer))
    }
}

/// Of two users who show one colour, whether `a` picks again rather than `b`: a user the
/// auth file names keeps its colour before one whose id a client chose, and otherwise the
/// larger id picks again. Every node decides the same.
fn yields(a: &Peer, b: &Peer) -> bool {
    use crate::identity::is_pinned;
    match (is_pinned(a.user), is_pinned(b.user)) {
        (false, true) => true,
        (true, false) => false,
        _ => a.user > b.user,
    }
}

/// `name`, or (when another user present shows a name that looks like it) `name (2)`,
/// `name (3)`, ..., whichever is free, cut to fit the name bound.
fn free_name(roster: &Roster, user: UserId, name: &str) -> String {
    if !roster.name_taken(user, name) {
        return name.to_string();
    }
    for n in 2..1000 {
        let suffix = format!(" ({n})");
        let mut base = name.to_string();
        while base.len() + suffix.len() > MAX_DISPLAY_NAME_BYTES {
            base.pop();
        }
        let candidate = format!("{}{suffix}", base.trim_end());
        if !roster.name_taken(user, &candidate) {
            return candidate;
        }
    }
    format!("guest-{user:x}")
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
        let here = roster.peers().find(|p| p.user == peer.user).cloned();
        match here {
            // The same user in another window keeps the colour it shows there.
            Some(same) => peer.colour = same.colour,
            None => {
                if crate::identity::is_pinned(peer.user) {
                    roster.give_way_to(peer.user);
                }
                let taken: Vec<_> = roster.peers().map(|p| p.colour).collect();
                peer.colour = crate::identity::colour_among(peer.user, &taken);
                peer.name = free_name(&roster, peer.user, &peer.name);
            }
        }
        let others: Vec<Peer> = roster.peers().cloned().collect();
        let id = peer.id;
        roster.joined(&peer, true);
        roster.index(&peer.name, peer.user);
        roster.members.insert(
            id,
            Member {
                state: PeerState {
                    id,
                    view: None,
                    cursor: None,
                    selection: None,
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

    /// The peer's latest view, cursor and selection (checked by the session).
    pub fn update(
        &self,
        id: PeerId,
        view: Option<View>,
        cursor: Option<Cursor>,
        selection: Option<Selection>,
    ) {
        let mut roster = self.roster();
        let Some(m) = roster.members.get_mut(&id) else {
            return;
        };
        if m.state.view == view && m.state.cursor == cursor && m.state.selection == selection {
            return;
        }
        m.state.view = view;
        m.state.cursor = cursor;
        m.state.selection = selection;
        let state = m.state;
        roster.changed(state, true);
    }

    /// The peer's new display name (checked by the session), unless another user present
    /// shows one like it.
    pub fn rename(&self, id: PeerId, name: String) -> Result<(), Refusal> {
        let mut roster = self.roster();
        let Some(user) = roster.members.get(&id).map(|m| m.peer.user) else {
            return Ok(());
        };
        if roster.name_taken(user, &name) {
            return Err(Refusal::NameTaken);
        }
        let Some(m) = roster.members.get_mut(&id) else {
            return Ok(());
        };
        let old = std::mem::replace(&mut m.peer.name, name);
        let peer = m.peer.clone();
        roster.unindex(&old, user);
        roster.index(&peer.name, user);
        roster.joined(&peer, true);
        Ok(())
    }

    /// The peer left.
    pub fn leave(&self, id: PeerId) {
        let mut roster = self.roster();
        if let Some(m) = roster.members.remove(&id) {
            roster.unindex(&m.peer.name, m.peer.user);
            roster.left(id, true);
        }
    }

    /// Keeps what changes among the local peers for [`Hub::take_local`] from now on (a node in
    /// a cluster relays it to the others).
    pub fn relay_local(&self) {
        let mut roster = self.roster();
        if roster.local.is_none() {
            roster.local = Some(Changes::default());
        }
    }

    /// What changed among the local peers since the last call (empty unless
    /// [`Hub::relay_local`] was called).
    pub fn take_local(&self) -> LocalChanges {
        let mut roster = self.roster();
        let Some(l) = roster.local.as_mut().map(std::mem::take) else {
            return LocalChanges::default();
        };
        LocalChanges {
            joined: l.joined.into_values().collect(),
            left: l.left,
            states: l.changed.into_values().collect(),
        }
    }

    /// Every local peer and its latest state (the relay's periodic full message).
    pub fn local_full(&self) -> (Vec<Peer>, Vec<PeerState>) {
        let roster = self.roster();
        roster
            .members
            .values()
            .map(|m| (m.peer.clone(), m.state))
            .unzip()
    }

    /// A peer on another node joined or was renamed (`peer.id` is its id here, at or above
    /// [`REMOTE_IDS`]). False when the hub holds [`MAX_REMOTE`] remote peers already.
    pub fn remote_join(&self, peer: Peer) -> bool {
        let mut roster = self.roster();
        let id = peer.id;
        if id < REMOTE_IDS {
            return false;
        }
        let full = roster.remote.len() >= MAX_REMOTE;
        match roster.remote.get_mut(&id) {
            Some(r) if r.peer == peer => return true,
            Some(r) => {
                let old = std::mem::replace(&mut r.peer, peer.clone());
                roster.unindex(&old.name, old.user);
                roster.index(&peer.name, peer.user);
            }
            None if full => return false,
            None => {
                roster.index(&peer.name, peer.user);
                let state = PeerState {
                    id,
                    view: None,
                    cursor: None,
                    selection: None,
                };
                roster.remote.insert(
                    id,
                    Remote {
                        peer: peer.clone(),
                        state,
                    },
                );
            }
        }
        roster.joined(&peer, false);
        roster.recolour_against(&peer);
        true
    }

    /// A remote peer's latest view and cursor (ignored for an id the hub does not hold).
    pub fn remote_update(&self, state: PeerState) {
        let mut roster = self.roster();
        let Some(r) = roster.remote.get_mut(&state.id) else {
            return;
        };
        if r.state == state {
            return;
        }
        r.state = state;
        roster.changed(state, false);
    }

    /// A remote peer left (or its node went silent).
    pub fn remote_leave(&self, id: PeerId) {
        let mut roster = self.roster();
        if let Some(r) = roster.remote.remove(&id) {
            roster.unindex(&r.peer.name, r.peer.user);
            roster.left(id, false);
        }
    }

    /// Names of the peers present, here and on other nodes, in joining order (the scene list
    /// shows them).
    pub fn names(&self) -> Vec<String> {
        self.roster().peers().map(|p| p.name.clone()).collect()
    }

    /// Everyone present: each peer and whether it is connected to this node.
    pub fn peers(&self) -> Vec<(Peer, bool)> {
        let roster = self.roster();
        let here = roster.members.values().map(|m| (m.peer.clone(), true));
        let away = roster.remote.values().map(|r| (r.peer.clone(), false));
        here.chain(away).collect()
    }

    /// Closes the connections to this node of the peers `which` picks, telling them why
    /// (`crate::admin`'s kick). Returns those closed.
    pub fn disconnect(
        &self,
        which: impl Fn(&Peer) -> bool,
        code: brickcast_protocol::wire::ErrorCode,
        text: &str,
    ) -> Vec<Peer> {
        let roster = self.roster();
        roster
            .members
            .values()
            .filter(|m| which(&m.peer))
            .map(|m| {
                m.out.close(code, text);
                m.peer.clone()
            })
            .collect()
    }

    /// Peers connected to this node.
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

    pub fn is_closed(&self) -> bool {
        self.closed.load(Relaxed)
    }

    /// How often the hub sends frames.
    pub fn interval(&self) -> Duration {
        self.interval
    }

    /// One tick: sends what changed to every peer that keeps up, a full frame to each stale
    /// peer whose queue has drained. Returns the bytes queued.
    pub fn tick(&self, metrics: &Metrics) -> usize {
        let mut roster = self.roster();
        let pending = std::mem::take(&mut roster.pending);
        let joined: Vec<Peer> = pending.joined.into_values().collect();
        let left = pending.left;
        let states: Vec<PeerState> = pending.changed.into_values().collect();
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
        let Roster {
            members, remote, ..
        } = &mut *roster;
        let needs_full = members
            .values()
            .any(|m| m.welcomed && m.stale && m.out.queued() <= MAX_QUEUED);
        let full = if needs_full {
            encode(
                ServerMsg::Presence {
                    full: true,
                    joined: members
                        .values()
                        .map(|m| m.peer.clone())
                        .chain(remote.values().map(|r| r.peer.clone()))
                        .collect(),
                    left: Vec::new(),
                    states: members
                        .values()
                        .map(|m| m.state)
                        .chain(remote.values().map(|r| r.state))
                        .collect(),
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

/// Checks a view, cursor and selection: finite numbers, a direction with length, a cursor inside
/// a scene of `size` with a radius up to `max_radius`, a selection inside the scene with its
/// corners in order. For clients' messages and for peers relayed from other nodes alike.
pub fn check(
    view: &Option<View>,
    cursor: &Option<Cursor>,
    selection: &Option<Selection>,
    size: [u32; 3],
    max_radius: f32,
) -> Result<(), Refusal> {
    if selection.as_ref().is_some_and(|s| !s.is_within(size)) {
        return Err(Refusal::OutOfRange);
    }
    if view.as_ref().is_some_and(|v| !v.is_valid()) {
        return Err(Refusal::NotFinite);
    }
    if let Some(c) = cursor {
        if !c.radius.is_finite() {
            return Err(Refusal::NotFinite);
        }
        let inside = (0..3).all(|i| c.voxel[i] < size[i]);
        if !inside || c.radius < 0.0 || c.radius > max_radius {
            return Err(Refusal::OutOfRange);
        }
    }
    Ok(())
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
    fn a_colour_two_nodes_gave_at_once_is_picked_again_by_one_of_them() {
        let total = Arc::new(AtomicUsize::new(0));
        let hub = Hub::new(20);
        hub.relay_local();
        let (out, _rx) = Outbox::new(total.clone());
        let (me, _) = hub.join(peer(9), out.clone());
        // The same user in a second window of this node: the same colour.
        let mut second = peer(10);
        second.user = 9;
        let (window, _) = hub.join(second, out);
        assert_eq!(window.colour, me.colour);
        // Another node gave a user with a smaller id the same colour: this node's user yields,
        // in both windows, and the new colour is relayed.
        let mut them = peer(REMOTE_IDS + 1);
        them.user = 5;
        them.colour = me.colour;
        assert!(hub.remote_join(them.clone()));
        let changed = hub.take_local();
        let mine: Vec<_> = changed.joined.iter().filter(|p| p.user == 9).collect();
        assert_eq!(mine.len(), 2, "{changed:?}");
        assert!(mine.iter().all(|p| p.colour == mine[0].colour));
        assert!(!crate::identity::looks_alike(mine[0].colour, them.colour));
        // A user with a larger id on another node: that node yields, not this one.
        let mut other = peer(REMOTE_IDS + 2);
        other.user = 50;
        other.colour = mine[0].colour;
        assert!(hub.remote_join(other));
        assert!(hub.take_local().joined.is_empty());
    }

    #[test]
    fn a_name_like_another_users_is_numbered_or_refused() {
        let total = Arc::new(AtomicUsize::new(0));
        let hub = Hub::new(20);
        let (out, _rx) = Outbox::new(total.clone());
        let mut alice = peer(1);
        alice.name = "Alice".into();
        assert_eq!(hub.join(alice, out.clone()).0.name, "Alice");
        // Another user asking for a name that looks the same is shown with a number.
        for (id, asked, shown) in [
            (2, "AIice", "AIice (2)"),
            (3, "\u{410}lice", "\u{410}lice (3)"),
        ] {
            let mut p = peer(id);
            p.name = asked.into();
            assert_eq!(hub.join(p, out.clone()).0.name, shown);
        }
        // The same user in a second window keeps the name.
        let mut window = peer(4);
        window.user = 1;
        window.name = "Alice".into();
        assert_eq!(hub.join(window, out.clone()).0.name, "Alice");
        // A rename to a name like another user's is refused; one's own is fine.
        assert_eq!(hub.rename(2, "ALICE".into()), Err(Refusal::NameTaken));
        assert_eq!(hub.rename(4, "ALICE".into()), Ok(()));
        assert_eq!(hub.rename(2, "Bob".into()), Ok(()));
        // Alice's name is hers while one of her windows shows it, and free once none does.
        assert_eq!(hub.rename(3, "Alice".into()), Err(Refusal::NameTaken));
        hub.leave(1);
        assert_eq!(
            hub.rename(3, "Alice".into()),
            Err(Refusal::NameTaken),
            "window 4 is ALICE"
        );
        hub.leave(4);
        assert_eq!(hub.rename(3, "Alice".into()), Ok(()));
        // "AIice (2)" went with its rename to Bob: the next look-alike takes that number again.
        let mut next = peer(5);
        next.name = "alice".into();
        assert_eq!(hub.join(next, out.clone()).0.name, "alice (2)");
        // A name another node's user shows is taken too, until that user leaves or renames.
        let mut far = peer(REMOTE_IDS + 1);
        far.user = 77;
        far.name = "Carol".into();
        assert!(hub.remote_join(far.clone()));
        assert_eq!(hub.rename(2, "CAROL".into()), Err(Refusal::NameTaken));
        far.name = "Dave".into();
        assert!(hub.remote_join(far));
        assert_eq!(hub.rename(2, "CAROL".into()), Ok(()));
        assert_eq!(hub.rename(5, "dave".into()), Err(Refusal::NameTaken));
        hub.remote_leave(REMOTE_IDS + 1);
        assert_eq!(hub.rename(5, "dave".into()), Ok(()));
    }

    #[test]
    fn a_user_the_auth_file_names_keeps_its_colour() {
        let total = Arc::new(AtomicUsize::new(0));
        let hub = Hub::new(20);
        let (out, _rx) = Outbox::new(total.clone());
        let alice = crate::identity::identify(false, Some("Alice"), 0, "", 1, |_| false);
        let own = crate::identity::colour_of(alice.user);
        // A stranger chose an id that lands on Alice's colour, and came first.
        let stranger_id = (1..10_000u64)
            .find(|&u| crate::identity::colour_of(u) == own)
            .unwrap();
        let mut stranger = peer(2);
        stranger.user = stranger_id;
        assert_eq!(hub.join(stranger, out.clone()).0.colour, own);
        let mut pinned = peer(3);
        pinned.user = alice.user;
        let (joined, roster) = hub.join(pinned, out);
        assert_eq!(joined.colour, own, "Alice shows her own colour");
        let squatter = roster.iter().find(|p| p.id == 2).unwrap();
        assert!(!crate::identity::looks_alike(squatter.colour, own));
        // Across nodes the same: a pinned user does not yield to a stranger with a smaller id.
        let mut remote = peer(REMOTE_IDS + 1);
        remote.user = 1;
        remote.colour = own;
        assert!(yields(&remote, &joined) && !yields(&joined, &remote));
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
            hub.update(1, Some(view(i as f32)), None, None);
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
