//! What a click does: the editing tools of both viewers, as the `EditOp` they send.
//!
//! Edits go to the server as rays (`EditOp::Ray`, `EditOp::Span`), not voxels: the server
//! resolves them on its own copy, so an edit made while the local copy is a few deltas behind
//! lands where the scene is now, two people using tools at once never disagree about what a
//! tool covered, and both shells need only the rays under the pointer.
//!
//! The tools ([`Tool`], keys in [`Tool::from_key`]): the brush (single voxels, or spheres
//! with a radius), box and line (drag from one corner to the other: [`Tools::press`] then
//! [`Tools::release`]), flood fill, face extrude/intrude, and the colour picker (also
//! Alt+click with any tool), which reads the local copy and sends nothing. A fill's and an
//! extrude's voxel limit and a span's extent are sized from the local copy (what the edit
//! should cover, plus a margin for deltas still on their way), so the server charges the
//! work budgets for about what the edit does, and a region too large for the server's limit
//! is refused here, with the reason, before anything is sent.

use brickcast_protocol::apply::span_end;
use brickcast_protocol::map::BrickMap;
use brickcast_protocol::region::{face_region, fill_region};
use brickcast_protocol::wire::{BrushMode, EditOp, Limits, RayAction, Selection, Shape};
use brickcast_protocol::{Colour, Ray, trace};

/// Which button was pressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Button {
    /// Removes (or, with the paint modifier, paints).
    Primary,
    /// Places.
    Secondary,
}

/// The edit for a click of `button` along `ray`: single voxels with `radius` 0, sphere brushes
/// otherwise; `paint` (Ctrl held, or the page's paint tool) recolours instead of removing.
pub fn ray_edit(button: Button, ray: &Ray, radius: f32, paint: bool, colour: Colour) -> EditOp {
    let action = match (button, radius > 0.0, paint) {
        (Button::Primary, false, false) => RayAction::Remove,
        (Button::Primary, false, true) => RayAction::Paint { colour },
        (Button::Secondary, false, _) => RayAction::Place { colour },
        (Button::Primary, true, paint) => RayAction::Sphere {
            mode: if paint {
                BrushMode::Paint
            } else {
                BrushMode::Erase
            },
            radius,
            colour,
        },
        (Button::Secondary, true, _) => RayAction::Sphere {
            mode: BrushMode::Fill,
            radius,
            colour,
        },
    };
    EditOp::Ray {
        origin: ray.origin,
        dir: ray.dir,
        action,
    }
}

/// Brush radius after one `[` (smaller) or `]` (larger) press: one voxel at a time, from 0
/// (single voxels) up to the server's `max`.
pub fn step_radius(radius: f32, larger: bool, max: f32) -> f32 {
    if larger {
        (radius + 1.0).min(max.max(1.0))
    } else {
        (radius - 1.0).max(0.0)
    }
}

/// An editing tool.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Tool {
    /// Single voxels, or sphere brushes of the brush radius.
    #[default]
    Brush,
    /// A box from the press to the release.
    Box,
    /// A line from the press to the release.
    Line,
    /// Recolours the connected region of one colour under the pointer.
    Fill,
    /// Grows (place button) or shrinks (remove button) the face under the pointer (and the
    /// connected faces of its plane and colour) by a layer.
    Extrude,
    /// Takes the colour under the pointer.
    Picker,
    /// Selects the box between the voxels under the press and the release (shown to everyone
    /// in the scene); a click on nothing, or the place button, clears it.
    Select,
}

impl Tool {
    pub const ALL: [Tool; 7] = [
        Tool::Brush,
        Tool::Box,
        Tool::Line,
        Tool::Fill,
        Tool::Extrude,
        Tool::Picker,
        Tool::Select,
    ];

    /// The tool a key (its `KeyboardEvent.code` name) picks: B brush, X box, N line, G fill,
    /// T extrude, I picker, V select. (P types a colour: [`HexEntry`].)
    pub fn from_key(code: &str) -> Option<Tool> {
        Some(match code {
            "KeyB" => Tool::Brush,
            "KeyX" => Tool::Box,
            "KeyN" => Tool::Line,
            "KeyG" => Tool::Fill,
            "KeyT" => Tool::Extrude,
            "KeyI" => Tool::Picker,
            "KeyV" => Tool::Select,
            _ => return None,
        })
    }

    /// Its name for people (status lines, the page's toolbar).
    pub fn name(self) -> &'static str {
        match self {
            Tool::Brush => "brush",
            Tool::Box => "box",
            Tool::Line => "line",
            Tool::Fill => "fill",
            Tool::Extrude => "extrude",
            Tool::Picker => "picker",
            Tool::Select => "select",
        }
    }

    /// Its key, as [`Tool::from_key`] reads it.
    pub fn key(self) -> &'static str {
        match self {
            Tool::Brush => "KeyB",
            Tool::Box => "KeyX",
            Tool::Line => "KeyN",
            Tool::Fill => "KeyG",
            Tool::Extrude => "KeyT",
            Tool::Picker => "KeyI",
            Tool::Select => "KeyV",
        }
    }

    /// Whether it acts on a drag (press, then release elsewhere) rather than a click.
    pub fn drags(self) -> bool {
        matches!(self, Tool::Box | Tool::Line | Tool::Select)
    }
}

/// What a press or release comes to.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Send this edit.
    Edit(EditOp),
    /// The colour under the pointer, to draw with from now on.
    Picked(Colour),
    /// The selection from now on (`None`: nothing selected), shared in presence.
    Selected(Option<Selection>),
    /// A drag started: wait for the release.
    Started,
    /// Nothing to send, and why (for the status line).
    Nothing(&'static str),
}

/// What the tools need to know at a press or release.
pub struct Context<'a> {
    /// The brush radius (0: single voxels).
    pub radius: f32,
    /// The paint modifier (Ctrl): the remove button paints instead.
    pub paint: bool,
    /// The picker modifier (Alt): any tool takes the colour under the pointer.
    pub pick: bool,
    pub colour: Colour,
    /// The server's limits (a fill's most voxels, a box's largest edge).
    pub limits: &'a Limits,
    /// The local copy, when there is one: what the picker reads and what sizes the edits.
    pub map: Option<&'a BrickMap>,
}

/// Room left for deltas still on their way when an edit is sized from the local copy.
const MARGIN_VOXELS: u32 = 8;

/// Most voxels a viewer searches its own copy for when it sizes a fill or an extrude, whatever
/// the server allows: a server announcing a huge limit does not make a click freeze the
/// viewer (a larger region is then not sent).
pub const MAX_LOCAL_TOOL_VOXELS: u32 = 1 << 22;

/// The tool in use and a drag in progress.
#[derive(Debug, Default)]
pub struct Tools {
    pub tool: Tool,
    /// Where a drag started (the button and the ray under the pointer then).
    start: Option<(Button, Ray)>,
}

impl Tools {
    /// Whether a drag is in progress (the shell then draws no camera look for it).
    pub fn dragging(&self) -> bool {
        self.start.is_some()
    }

    /// Forgets a drag in progress (the pointer left, a key changed the tool).
    pub fn cancel(&mut self) {
        self.start = None;
    }

    /// Picks `tool` (a drag in progress is forgotten).
    pub fn pick_tool(&mut self, tool: Tool) {
        self.tool = tool;
        self.start = None;
    }

    /// A press of `button` along `ray`. A drag still in progress (its release never came:
    /// the pointer left the window, another button) is forgotten.
    pub fn press(&mut self, button: Button, ray: &Ray, cx: &Context) -> Action {
        self.start = None;
        if cx.pick || self.tool == Tool::Picker {
            return pick(ray, cx);
        }
        match self.tool {
            Tool::Brush => Action::Edit(ray_edit(button, ray, cx.radius, cx.paint, cx.colour)),
            Tool::Box | Tool::Line | Tool::Select => {
                self.start = Some((button, *ray));
                Action::Started
            }
            Tool::Fill => fill(ray, cx),
            Tool::Extrude => extrude(button, ray, cx),
            Tool::Picker => pick(ray, cx),
        }
    }

    /// The release of `released` along `ray`: ends the drag that button started.
    pub fn release(&mut self, released: Button, ray: &Ray, cx: &Context) -> Action {
        let Some((button, from)) = self.start else {
            return Action::Nothing("");
        };
        if button != released {
            return Action::Nothing("");
        }
        self.start = None;
        if self.tool == Tool::Select {
            return select(button, &from, ray, cx);
        }
        let mode = match (button, cx.paint) {
            (Button::Secondary, _) => BrushMode::Fill,
            (Button::Primary, true) => BrushMode::Paint,
            (Button::Primary, false) => BrushMode::Erase,
        };
        let shape = if self.tool == Tool::Line {
            Shape::Line
        } else {
            Shape::Box
        };
        let extent = match span_locally(cx.map, &from, ray, mode) {
            Some(span) if span > cx.limits.max_box_extent => {
                return Action::Nothing("that is larger than this server's largest box");
            }
            Some(span) => (span + MARGIN_VOXELS).min(cx.limits.max_box_extent),
            None => cx.limits.max_box_extent,
        };
        Action::Edit(EditOp::Span {
            from: from.origin,
            from_dir: from.dir,
            to: ray.origin,
            to_dir: ray.dir,
            shape,
            mode,
            colour: cx.colour,
            extent,
        })
    }
}

/// A line for the status bar about the selection now.
pub fn selection_note(selection: Option<Selection>) -> String {
    match selection {
        Some(s) => {
            let [x, y, z] = s.extent();
            format!("selected {x}×{y}×{z} voxels (everyone here sees the box)")
        }
        None => "nothing selected".into(),
    }
}

/// The box between the voxels the two rays hit on the local copy (what the user sees): the
/// selection; the place button, or a ray that hits nothing, clears it.
fn select(button: Button, from: &Ray, to: &Ray, cx: &Context) -> Action {
    if button == Button::Secondary {
        return Action::Selected(None);
    }
    let Some(map) = cx.map else {
        return Action::Nothing("the scene is not here yet");
    };
    match (trace(map, from), trace(map, to)) {
        (Some(a), Some(b)) => Action::Selected(Some(Selection::between(a.voxel, b.voxel))),
        _ => Action::Selected(None),
    }
}

/// The colour of the voxel under the pointer, on the local copy.
fn pick(ray: &Ray, cx: &Context) -> Action {
    match cx.map.and_then(|map| trace(map, ray)) {
        Some(hit) => Action::Picked(hit.colour),
        None => Action::Nothing("nothing under the pointer to take a colour from"),
    }
}

/// A voxel limit for a region the local copy finds `found` voxels in: the region and a
/// margin, within the server's limit.
fn limit_for(
    found: Result<Vec<[u32; 3]>, brickcast_protocol::wire::Rejection>,
    max: u32,
) -> Result<u32, &'static str> {
    match found {
        Ok(region) => {
            let n = region.len() as u32;
            Ok(n.saturating_add(n / 8 + MARGIN_VOXELS).min(max))
        }
        Err(_) => Err("that region is larger than this server lets one tool change"),
    }
}

fn fill(ray: &Ray, cx: &Context) -> Action {
    let max = cx.limits.max_tool_voxels.min(MAX_LOCAL_TOOL_VOXELS);
    let limit = match cx.map {
        Some(map) => match trace(map, ray) {
            Some(hit) => match limit_for(fill_region(map, hit.voxel, max), max) {
                Ok(limit) => limit,
                Err(why) => return Action::Nothing(why),
            },
            None => return Action::Nothing("nothing under the pointer to fill"),
        },
        None => max,
    };
    Action::Edit(EditOp::Ray {
        origin: ray.origin,
        dir: ray.dir,
        action: RayAction::Fill {
            colour: cx.colour,
            limit,
        },
    })
}

fn extrude(button: Button, ray: &Ray, cx: &Context) -> Action {
    let max = cx.limits.max_tool_voxels.min(MAX_LOCAL_TOOL_VOXELS);
    let limit = match cx.map {
        Some(map) => match trace(map, ray) {
            Some(hit) => {
                let Some(front) = hit.previous else {
                    return Action::Nothing("no face under the pointer");
                };
                let normal = std::array::from_fn(|i| i64::from(front[i]) - i64::from(hit.voxel[i]));
                match limit_for(face_region(map, hit.voxel, normal, max), max) {
                    Ok(limit) => limit,
                    Err(why) => return Action::Nothing(why),
                }
            }
            None => return Action::Nothing("nothing under the pointer to extrude"),
        },
        None => max,
    };
    Action::Edit(EditOp::Ray {
        origin: ray.origin,
        dir: ray.dir,
        action: RayAction::Extrude {
            out: button == Button::Secondary,
            limit,
        },
    })
}

/// The longest edge (in voxels) of the span between two rays' ends on the local copy, as the
/// server resolves them (`brickcast_protocol::apply`); `None` when the local copy cannot tell.
fn span_locally(map: Option<&BrickMap>, a: &Ray, b: &Ray, mode: BrushMode) -> Option<u32> {
    let map = map?;
    let end = |ray: &Ray| span_end(&trace(map, ray)?, mode).ok();
    let (a, b) = (end(a)?, end(b)?);
    (0..3).map(|i| a[i].abs_diff(b[i]) + 1).max()
}

/// Typing a colour as six hex digits (the native viewer's RGB chooser: P, then the digits;
/// Backspace takes one back, Escape gives up). Keys by their `KeyboardEvent.code` name.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct HexEntry {
    /// The digits typed so far, while typing.
    digits: Option<String>,
}

/// What a key did to a [`HexEntry`].
#[derive(Debug, Clone, PartialEq)]
pub enum HexKey {
    /// Not typing, and the key does not start it: the key is the viewer's as usual.
    Ignored,
    /// Typing (the key was taken).
    Typing,
    /// Six digits: draw with this colour.
    Done(Colour),
    /// Escape: typing ended, nothing chosen.
    Cancelled,
}

impl HexEntry {
    /// The key that starts typing.
    pub const START: &'static str = "KeyP";

    /// Whether digits are being typed (the viewer's other keys wait).
    pub fn typing(&self) -> bool {
        self.digits.is_some()
    }

    /// What is typed so far, for the title or status line (`#3b8e__`).
    pub fn shown(&self) -> Option<String> {
        let digits = self.digits.as_ref()?;
        Some(format!("#{digits:_<6}"))
    }

    pub fn key(&mut self, code: &str) -> HexKey {
        let Some(digits) = &mut self.digits else {
            if code == Self::START {
                self.digits = Some(String::new());
                return HexKey::Typing;
            }
            return HexKey::Ignored;
        };
        let digit = code
            .strip_prefix("Digit")
            .or_else(|| code.strip_prefix("Numpad"))
            .or_else(|| {
                code.strip_prefix("Key")
                    .filter(|k| matches!(*k, "A" | "B" | "C" | "D" | "E" | "F"))
            });
        match (code, digit) {
            ("Escape", _) => {
                self.digits = None;
                HexKey::Cancelled
            }
            ("Backspace", _) => {
                digits.pop();
                HexKey::Typing
            }
            (_, Some(d)) if d.len() == 1 && d.chars().all(|c| c.is_ascii_hexdigit()) => {
                digits.push_str(&d.to_ascii_lowercase());
                if digits.len() < 6 {
                    return HexKey::Typing;
                }
                let colour = Colour::parse_hex(digits);
                self.digits = None;
                colour.map_or(HexKey::Cancelled, HexKey::Done)
            }
            _ => HexKey::Typing,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::apply::apply_op;

    fn ground() -> BrickMap {
        let mut map = BrickMap::new([64, 32, 64]).unwrap();
        map.fill_box([0, 0, 0], [63, 3, 63], BrushMode::Fill, Colour::WHITE);
        map
    }

    fn down(x: f32, z: f32) -> Ray {
        Ray {
            origin: [x, 30.0, z],
            dir: [0.0, -1.0, 0.0],
        }
    }

    fn cx<'a>(map: &'a BrickMap, limits: &'a Limits) -> Context<'a> {
        Context {
            radius: 0.0,
            paint: false,
            pick: false,
            colour: Colour::from_rgb8(255, 0, 0),
            limits,
            map: Some(map),
        }
    }

    /// V selects the box between the voxels under the press and the release, on the local
    /// copy; the place button, or a drag onto nothing, clears it. Nothing is sent.
    #[test]
    fn the_select_tool_selects_the_box_between_two_hits() {
        let map = ground();
        let limits = Limits::default();
        let cx = cx(&map, &limits);
        let mut tools = Tools::default();
        tools.pick_tool(Tool::from_key("KeyV").unwrap());
        assert!(tools.tool.drags());
        assert_eq!(
            tools.press(Button::Primary, &down(20.5, 9.5), &cx),
            Action::Started
        );
        assert_eq!(
            tools.release(Button::Primary, &down(12.5, 14.5), &cx),
            Action::Selected(Some(Selection {
                min: [12, 3, 9],
                max: [20, 3, 14]
            }))
        );
        tools.press(Button::Secondary, &down(20.5, 9.5), &cx);
        assert_eq!(
            tools.release(Button::Secondary, &down(12.5, 14.5), &cx),
            Action::Selected(None)
        );
        let sky = Ray {
            origin: [10.0, 30.0, 10.0],
            dir: [0.0, 1.0, 0.0],
        };
        tools.press(Button::Primary, &down(20.5, 9.5), &cx);
        assert_eq!(
            tools.release(Button::Primary, &sky, &cx),
            Action::Selected(None)
        );
    }

    #[test]
    fn a_colour_is_typed_as_six_hex_digits() {
        let mut hex = HexEntry::default();
        assert_eq!(
            hex.key("KeyW"),
            HexKey::Ignored,
            "not typing: flying keys fly"
        );
        assert_eq!(hex.key("KeyP"), HexKey::Typing);
        for code in ["Digit3", "KeyB", "Digit8", "KeyE", "KeyX", "Digit9"] {
            assert_eq!(hex.key(code), HexKey::Typing, "{code}");
        }
        assert_eq!(
            hex.shown().as_deref(),
            Some("#3b8e9_"),
            "X is not a hex digit"
        );
        assert_eq!(hex.key("Backspace"), HexKey::Typing);
        assert_eq!(hex.key("KeyD"), HexKey::Typing);
        assert_eq!(
            hex.key("Numpad9"),
            HexKey::Done(Colour::from_rgb8(0x3b, 0x8e, 0xd9))
        );
        assert!(!hex.typing());
        assert_eq!(hex.key("KeyP"), HexKey::Typing);
        assert_eq!(hex.key("Escape"), HexKey::Cancelled);
        assert_eq!(hex.shown(), None);
    }

    #[test]
    fn keys_pick_tools_and_every_tool_has_one() {
        for tool in Tool::ALL {
            assert_eq!(Tool::from_key(tool.key()), Some(tool), "{}", tool.name());
        }
        assert_eq!(Tool::from_key("KeyW"), None, "flying keys stay flying keys");
    }

    #[test]
    fn a_drag_draws_a_box_sized_from_the_local_copy() {
        let mut map = ground();
        let limits = Limits::default();
        let mut tools = Tools {
            tool: Tool::Box,
            ..Tools::default()
        };
        let c = cx(&map, &limits);
        assert_eq!(
            tools.press(Button::Secondary, &down(2.5, 2.5), &c),
            Action::Started
        );
        assert!(tools.dragging());
        // Another button's release does not end it.
        assert_eq!(
            tools.release(Button::Primary, &down(12.5, 6.5), &c),
            Action::Nothing("")
        );
        let Action::Edit(op) = tools.release(Button::Secondary, &down(12.5, 6.5), &c) else {
            panic!("no edit")
        };
        assert!(!tools.dragging());
        let EditOp::Span { extent, mode, .. } = op else {
            panic!("{op:?}")
        };
        assert_eq!((extent, mode), (11 + MARGIN_VOXELS, BrushMode::Fill));
        // The server's reading of it: a box one voxel high on the ground.
        assert_eq!(apply_op(&mut map, &op, &limits), Ok(11 * 5));
        assert_eq!(map.get([12, 4, 6]), Some(Colour::from_rgb8(255, 0, 0)));
        // A drag whose release never came is forgotten by the next press: an Alt+click then
        // picks a colour, and its release draws nothing.
        let c = cx(&map, &limits);
        tools.press(Button::Primary, &down(2.5, 2.5), &c);
        let mut alt = cx(&map, &limits);
        alt.pick = true;
        assert!(matches!(
            tools.press(Button::Primary, &down(20.5, 20.5), &alt),
            Action::Picked(_)
        ));
        assert!(!tools.dragging());
        assert_eq!(
            tools.release(Button::Primary, &down(20.5, 20.5), &alt),
            Action::Nothing("")
        );
    }

    #[test]
    fn a_fill_is_sized_from_the_local_copy_and_a_runaway_is_not_sent() {
        let mut map = ground();
        let limits = Limits {
            max_tool_voxels: 5000,
            ..Limits::default()
        };
        map.fill_box([0, 3, 0], [9, 3, 9], BrushMode::Paint, Colour::BLACK);
        let mut tools = Tools {
            tool: Tool::Fill,
            ..Tools::default()
        };
        let Action::Edit(op) = tools.press(Button::Primary, &down(4.5, 4.5), &cx(&map, &limits))
        else {
            panic!("no edit")
        };
        let EditOp::Ray {
            action: RayAction::Fill { limit, .. },
            ..
        } = op
        else {
            panic!("{op:?}")
        };
        assert_eq!(limit, 100 + 100 / 8 + MARGIN_VOXELS);
        assert_eq!(apply_op(&mut map, &op, &limits), Ok(100));
        // The white ground is 64·64·4 − 100 voxels: more than this server's 5,000.
        assert!(matches!(
            tools.press(Button::Primary, &down(40.5, 40.5), &cx(&map, &limits)),
            Action::Nothing(_)
        ));
    }

    #[test]
    fn the_picker_and_alt_take_the_colour_under_the_pointer() {
        let mut map = ground();
        let limits = Limits::default();
        let teal = Colour::from_rgb8(0, 128, 128);
        map.set([8, 3, 8], teal);
        let mut tools = Tools::default();
        let mut c = cx(&map, &limits);
        c.pick = true;
        assert_eq!(
            tools.press(Button::Primary, &down(8.5, 8.5), &c),
            Action::Picked(teal)
        );
        tools.pick_tool(Tool::Picker);
        c.pick = false;
        assert_eq!(
            tools.press(Button::Secondary, &down(1.5, 1.5), &c),
            Action::Picked(Colour::WHITE)
        );
        let up = Ray {
            origin: [1.5, 30.0, 1.5],
            dir: [0.0, 1.0, 0.0],
        };
        assert!(matches!(
            tools.press(Button::Primary, &up, &c),
            Action::Nothing(_)
        ));
    }

    #[test]
    fn extrude_grows_with_place_and_shrinks_with_remove() {
        let mut map = ground();
        let limits = Limits::default();
        map.fill_box([10, 4, 10], [12, 6, 12], BrushMode::Fill, Colour::BLACK);
        let mut tools = Tools {
            tool: Tool::Extrude,
            ..Tools::default()
        };
        let Action::Edit(op) =
            tools.press(Button::Secondary, &down(11.5, 11.5), &cx(&map, &limits))
        else {
            panic!("no edit")
        };
        assert_eq!(apply_op(&mut map, &op, &limits), Ok(9));
        assert_eq!(map.get([10, 7, 10]), Some(Colour::BLACK));
        let Action::Edit(op) = tools.press(Button::Primary, &down(11.5, 11.5), &cx(&map, &limits))
        else {
            panic!("no edit")
        };
        assert_eq!(apply_op(&mut map, &op, &limits), Ok(9));
        assert_eq!(map.get([10, 7, 10]), None);
    }
}
