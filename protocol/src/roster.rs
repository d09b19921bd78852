//! A client's picture of who else is in the scene, kept current from `Welcome` and `Presence`
//! frames. Shared by every front end (window, browser, tools) so that they agree on what a
//! frame means.

use std::collections::BTreeMap;

use crate::wire::{Peer, PeerId, PeerState, ServerMsg};

/// Another peer as last heard of.
#[derive(Clone, Debug, PartialEq)]
pub struct Present {
    pub peer: Peer,
    pub state: PeerState,
}

/// Everyone else present, by peer id, and who we are.
#[derive(Clone, Debug, Default)]
pub struct Roster {
    pub you: Option<Peer>,
    pub others: BTreeMap<PeerId, Present>,
}

impl Roster {
    /// Applies a message: `Welcome` starts the roster over, `Presence` updates it; anything
    /// else is ignored. Returns whether the roster changed.
    pub fn apply(&mut self, msg: &ServerMsg) -> bool {
        match msg {
            ServerMsg::Welcome { you, peers, .. } => {
                self.welcome(you.clone(), peers);
                true
            }
            ServerMsg::Presence {
                full,
                joined,
                left,
                states,
            } => {
                if *full {
                    self.others.clear();
                }
                for p in joined {
                    self.add(p);
                }
                for id in left {
                    self.others.remove(id);
                }
                for s in states {
                    if let Some(present) = self.others.get_mut(&s.id) {
                        present.state = *s;
                    }
                }
                true
            }
            _ => false,
        }
    }

    /// Starts over from a `Welcome`: who we are, who else was present.
    pub fn welcome(&mut self, you: Peer, peers: &[Peer]) {
        self.you = Some(you);
        self.others.clear();
        for p in peers {
            self.add(p);
        }
    }

    /// A peer joined or was renamed (its state is kept on a rename).
    fn add(&mut self, peer: &Peer) {
        if self.you.as_ref().is_some_and(|y| y.id == peer.id) {
            self.you = Some(peer.clone());
            return;
        }
        let state = self
            .others
            .get(&peer.id)
            .map(|p| p.state)
            .unwrap_or(PeerState {
                id: peer.id,
                view: None,
                cursor: None,
                selection: None,
            });
        self.others.insert(
            peer.id,
            Present {
                peer: peer.clone(),
                state,
            },
        );
    }

    /// The first other peer with this name (for `--follow NAME`).
    pub fn find(&self, name: &str) -> Option<&Present> {
        self.others.values().find(|p| p.peer.name == name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Colour;
    use crate::wire::{Role, View};

    fn peer(id: PeerId, name: &str) -> Peer {
        Peer {
            id,
            user: id * 10,
            name: name.into(),
            colour: Colour::WHITE,
            role: Role::Editor,
        }
    }

    #[test]
    fn joins_states_renames_and_leaves() {
        let mut r = Roster::default();
        r.apply(&ServerMsg::Presence {
            full: true,
            joined: vec![peer(1, "me"), peer(2, "ann")],
            left: vec![],
            states: vec![],
        });
        r.you = Some(peer(1, "me"));
        r.apply(&ServerMsg::Presence {
            full: true,
            joined: vec![peer(1, "me"), peer(2, "ann")],
            left: vec![],
            states: vec![],
        });
        assert_eq!(r.others.len(), 1);
        let view = View {
            eye: [1.0, 2.0, 3.0],
            forward: [0.0, 0.0, 1.0],
        };
        r.apply(&ServerMsg::Presence {
            full: false,
            joined: vec![peer(2, "anne")],
            left: vec![],
            states: vec![PeerState {
                id: 2,
                view: Some(view),
                cursor: None,
                selection: None,
            }],
        });
        let ann = r.find("anne").unwrap();
        assert_eq!(ann.state.view, Some(view));
        r.apply(&ServerMsg::Presence {
            full: false,
            joined: vec![],
            left: vec![2],
            states: vec![],
        });
        assert!(r.others.is_empty());
    }
}
