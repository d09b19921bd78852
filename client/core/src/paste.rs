//! Copy and paste in both viewers (issue #34; the server keeps the clipboard,
//! `brickcast_protocol::clipboard`): Ctrl+C copies the selection (the select tool's box),
//! Ctrl+X cuts it (copies, then erases the box, in one message: one undo step; a move is a
//! cut and a paste),
//! Ctrl+V pastes it with its lowest corner at the empty cell in front of the face under the
//! pointer (on a face that looks down or towards −x or −z, the box grows that way), R turns
//! the next pastes a quarter turn, M mirrors them. The clipboard is the user's on the server,
//! so it pastes into any scene of the server; a window knows the size of what it copied.

use brickcast_protocol::clipboard::turned;
use brickcast_protocol::wire::{EditOp, Selection};
use brickcast_protocol::{BrickMap, BrushMode, Colour, Ray, trace};

/// What this viewer knows of the user's clipboard and how the next paste is turned.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Pasting {
    /// The size of the box last copied from this viewer (`None`: nothing yet).
    copied: Option<[u32; 3]>,
    /// Quarter turns about the vertical axis, 0–3.
    turns: u8,
    mirror: bool,
}

impl Pasting {
    /// Ctrl+C: the op that copies `selection` into the clipboard.
    pub fn copy(&mut self, selection: Option<Selection>) -> Result<(EditOp, String), &'static str> {
        let s = selection.ok_or("select a box first (V, then drag)")?;
        self.copied = Some(s.extent());
        let [x, y, z] = s.extent();
        Ok((
            EditOp::Copy {
                min: s.min,
                max: s.max,
            },
            format!("copied {x}×{y}×{z} voxels (Ctrl+V pastes; R turns, M mirrors)"),
        ))
    }

    /// Ctrl+X: the ops that copy `selection` and then erase it, in one message (so one undo
    /// step brings the voxels back).
    pub fn cut(
        &mut self,
        selection: Option<Selection>,
    ) -> Result<(Vec<EditOp>, String), &'static str> {
        let (copy, _) = self.copy(selection)?;
        let EditOp::Copy { min, max } = copy else {
            return Err("nothing to cut");
        };
        let [x, y, z] = self.copied.unwrap_or_default();
        Ok((
            vec![
                copy,
                EditOp::Box {
                    min,
                    max,
                    mode: BrushMode::Erase,
                    colour: Colour::BLACK,
                },
            ],
            format!("cut {x}×{y}×{z} voxels (Ctrl+V pastes; Ctrl+Z puts them back)"),
        ))
    }

    /// The size the next paste fills (the copied box, turned).
    pub fn size(&self) -> Option<[u32; 3]> {
        Some(turned(self.copied?, self.turns))
    }

    /// Ctrl+V along `ray`: the op that pastes at the empty cell in front of the face hit on the
    /// local copy (what the user sees).
    pub fn paste(
        &self,
        map: Option<&BrickMap>,
        ray: &Ray,
    ) -> Result<(EditOp, String), &'static str> {
        let size = self
            .size()
            .ok_or("nothing copied yet (Ctrl+C copies the selection)")?;
        let map = map.ok_or("the scene is not here yet")?;
        let hit = trace(map, ray).ok_or("point at a face to paste onto")?;
        let front = hit.previous.unwrap_or(hit.voxel);
        // The box lies in front of the face: against a face looking towards −axis it ends at
        // the cell in front rather than starting there.
        let at: [u32; 3] = std::array::from_fn(|i| {
            if front[i] < hit.voxel[i] {
                front[i].saturating_sub(size[i] - 1)
            } else {
                front[i]
            }
        });
        Ok((
            EditOp::Paste {
                at,
                size,
                turns: self.turns,
                mirror: self.mirror,
            },
            format!("pasted at {at:?}"),
        ))
    }

    /// R: the next pastes turn a quarter more.
    pub fn turn(&mut self) -> String {
        self.turns = (self.turns + 1) % 4;
        format!("pastes turn {}°", u32::from(self.turns) * 90)
    }

    /// M: the next pastes are mirrored (or no longer).
    pub fn mirror(&mut self) -> String {
        self.mirror = !self.mirror;
        if self.mirror {
            "pastes are mirrored".into()
        } else {
            "pastes are not mirrored".into()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn copy_then_paste_on_the_face_under_the_pointer_turned_and_mirrored() {
        let mut map = BrickMap::new([64, 32, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 3, 63], BrushMode::Fill, Colour::WHITE);
        let down = Ray {
            origin: [20.5, 30.0, 9.5],
            dir: [0.0, -1.0, 0.0],
        };
        let mut p = Pasting::default();
        assert!(p.paste(Some(&map), &down).is_err(), "nothing copied");
        assert!(p.copy(None).is_err(), "nothing selected");
        assert!(p.cut(None).is_err(), "nothing selected");
        let (cut, _) = p
            .cut(Some(Selection::between([4, 0, 4], [5, 1, 5])))
            .unwrap();
        assert_eq!(
            cut,
            vec![
                EditOp::Copy {
                    min: [4, 0, 4],
                    max: [5, 1, 5]
                },
                EditOp::Box {
                    min: [4, 0, 4],
                    max: [5, 1, 5],
                    mode: BrushMode::Erase,
                    colour: Colour::BLACK
                }
            ]
        );
        assert_eq!(p.size(), Some([2, 2, 2]));
        let (copy, _) = p
            .copy(Some(Selection::between([1, 0, 1], [3, 1, 6])))
            .unwrap();
        assert_eq!(
            copy,
            EditOp::Copy {
                min: [1, 0, 1],
                max: [3, 1, 6]
            }
        );
        let (paste, _) = p.paste(Some(&map), &down).unwrap();
        assert_eq!(
            paste,
            EditOp::Paste {
                at: [20, 4, 9],
                size: [3, 2, 6],
                turns: 0,
                mirror: false
            },
            "on top of the ground under the pointer"
        );
        assert_eq!(p.turn(), "pastes turn 90°");
        p.mirror();
        let (paste, _) = p.paste(Some(&map), &down).unwrap();
        assert_eq!(
            paste,
            EditOp::Paste {
                at: [20, 4, 9],
                size: [6, 2, 3],
                turns: 1,
                mirror: true
            }
        );
        for _ in 0..3 {
            p.turn();
        }
        assert_eq!(p.size(), Some([3, 2, 6]), "four turns are none");
        let sky = Ray {
            origin: [20.5, 30.0, 9.5],
            dir: [0.0, 1.0, 0.0],
        };
        assert!(p.paste(Some(&map), &sky).is_err());
        // Under a ceiling (a face looking down) the box hangs from it.
        let mut roofed = map.clone();
        roofed.fill_box([0, 20, 0], [63, 20, 63], BrushMode::Fill, Colour::WHITE);
        let up = Ray {
            origin: [20.5, 10.5, 9.5],
            dir: [0.0, 1.0, 0.0],
        };
        let (paste, _) = p.paste(Some(&roofed), &up).unwrap();
        let EditOp::Paste { at, size, .. } = paste else {
            unreachable!()
        };
        assert_eq!(
            at[1] + size[1] - 1,
            19,
            "it ends under the ceiling: {at:?} {size:?}"
        );
    }
}
