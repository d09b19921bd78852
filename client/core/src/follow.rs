//! Following another user's camera: `F` cycles through the others (and back to flying), any
//! key or mouse look that moves the camera stops it, `--follow NAME` starts that way as soon as
//! that user is present.

use brickcast_protocol::roster::Roster;
use brickcast_protocol::wire::{PeerId, View};

/// Whom the camera rides with.
#[derive(Debug, Default)]
pub struct Follow {
    pub target: Option<PeerId>,
    /// `--follow NAME` not yet present.
    waiting_for: Option<String>,
}

impl Follow {
    pub fn by_name(name: Option<String>) -> Follow {
        Follow {
            target: None,
            waiting_for: name,
        }
    }

    /// The next other peer after the one followed (by id), or nobody after the last.
    pub fn cycle(&mut self, roster: &Roster) {
        self.waiting_for = None;
        let after = self.target;
        self.target = roster
            .others
            .keys()
            .copied()
            .find(|id| after.is_none_or(|a| *id > a));
    }

    pub fn stop(&mut self) {
        self.target = None;
        self.waiting_for = None;
    }

    /// The view to put the camera at this frame, if following someone who shares one. Picks up
    /// a `--follow` name once it appears; forgets a target that left.
    pub fn view(&mut self, roster: &Roster) -> Option<View> {
        if let Some(name) = &self.waiting_for
            && let Some(p) = roster.find(name)
        {
            self.target = Some(p.peer.id);
            self.waiting_for = None;
        }
        let id = self.target?;
        match roster.others.get(&id) {
            Some(p) => p.state.view,
            None => {
                self.target = None;
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::Colour;
    use brickcast_protocol::roster::Present;
    use brickcast_protocol::wire::{Peer, PeerState, Role};

    fn roster(ids: &[(PeerId, &str)]) -> Roster {
        let mut r = Roster::default();
        for &(id, name) in ids {
            r.others.insert(
                id,
                Present {
                    peer: Peer {
                        id,
                        user: id,
                        name: name.into(),
                        colour: Colour::WHITE,
                        role: Role::Editor,
                    },
                    state: PeerState {
                        id,
                        view: Some(View {
                            eye: [id as f32, 0.0, 0.0],
                            forward: [1.0, 0.0, 0.0],
                        }),
                        cursor: None,
                        selection: None,
                    },
                },
            );
        }
        r
    }

    #[test]
    fn cycles_follows_by_name_and_lets_go_of_leavers() {
        let r = roster(&[(3, "ann"), (8, "bob")]);
        let mut f = Follow::default();
        f.cycle(&r);
        assert_eq!(f.target, Some(3));
        f.cycle(&r);
        assert_eq!(f.target, Some(8));
        f.cycle(&r);
        assert_eq!(f.target, None);
        let mut f = Follow::by_name(Some("bob".into()));
        assert_eq!(f.view(&roster(&[])), None);
        assert_eq!(f.view(&r).unwrap().eye[0], 8.0);
        assert_eq!(f.view(&roster(&[(3, "ann")])), None);
        assert_eq!(f.target, None);
    }
}
