//! What `brickcast view` draws over the traced scene: everyone else (a marker at their camera
//! with a stroke where it points, and their name, in their colour), their cursors and brushes
//! on the voxel surface, my own brush and colour, a crosshair while the mouse is captured, and a
//! panel listing who is here.
//!
//! Why on the CPU: it is a few hundred lines and glyphs a frame, it must be exactly where the
//! tests look for it, and it stays sharp at any `--scale` because it is drawn at the window's
//! resolution. `gpu.rs` uploads the image when it changed and blends it over the scene in one
//! full-screen pass (`shaders/overlay.wgsl`).

pub mod canvas;
pub mod gpu;

use brickcast_protocol::roster::Roster;
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::{Cursor, Role, Selection};
use brickcast_protocol::{Colour, Projection};

use canvas::{Canvas, Rgba};

/// Everything the overlay shows in one frame.
pub struct OverlayInput<'a> {
    /// The camera at the window's resolution.
    pub projection: Projection,
    pub roster: &'a Roster,
    /// What my pointer is on, with my brush radius.
    pub cursor: Option<Cursor>,
    /// The colour I paint with.
    pub colour: Colour,
    pub captured: bool,
    /// Lines for the panel under the list of people (state, last undo, ...).
    pub notes: Vec<String>,
    /// The peer I follow.
    pub following: Option<u64>,
    /// The scene's palette, drawn as the strip of swatches keys 1–0 take (`None`: no strip;
    /// the page lists every swatch in its tool bar instead).
    pub swatches: Option<Swatches>,
    /// My selection (the select tool).
    pub selection: Option<Selection>,
}

/// Swatches in the strip: the ones number keys reach.
pub const STRIP_SWATCHES: usize = 10;
/// A swatch's side in the strip, and the step from one to the next, in pixels.
const SWATCH_PX: i32 = 16;
const SWATCH_STEP: i32 = 22;

const WHITE: Rgba = [255, 255, 255, 255];
const PANEL: Rgba = [16, 18, 24, 150];
/// Radius of a camera marker, in pixels.
pub const MARKER_RADIUS: f32 = 7.0;
/// How far (in voxels) the stroke showing where a camera points reaches.
const POINTING_VOXELS: f32 = 12.0;

fn rgba(c: Colour, a: u8) -> Rgba {
    let [r, g, b] = c.to_rgb8();
    [r, g, b, a]
}

/// Where a point lands on the image (continuous pixel coordinates, y down; the centre of pixel
/// `(x, y)` is `(x + 0.5, y + 0.5)`), and its distance along the view direction. `None` behind
/// the camera.
pub fn to_screen(p: &Projection, point: [f32; 3]) -> Option<(f32, f32, f32)> {
    let d = [0, 1, 2].map(|i| point[i] - p.eye[i]);
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let z = dot(d, p.forward);
    if z.is_nan() || z <= 1e-3 {
        return None;
    }
    let u = dot(d, p.right) / (dot(p.right, p.right) * z);
    let v = dot(d, p.up) / (dot(p.up, p.up) * z);
    let x = u + p.width as f32 * 0.5;
    let y = p.height as f32 * 0.5 - v;
    (x.is_finite() && y.is_finite()).then_some((x, y, z))
}

/// A 3D segment on the image, cut where it passes behind the camera.
fn segment(p: &Projection, a: [f32; 3], b: [f32; 3]) -> Option<((f32, f32), (f32, f32))> {
    const NEAR: f32 = 0.05;
    let dot = |v: [f32; 3]| {
        (0..3)
            .map(|i| (v[i] - p.eye[i]) * p.forward[i])
            .sum::<f32>()
    };
    let (za, zb) = (dot(a), dot(b));
    if za < NEAR && zb < NEAR {
        return None;
    }
    let cut = |from: [f32; 3], to: [f32; 3], zf: f32, zt: f32| {
        let t = (NEAR - zf) / (zt - zf);
        [0, 1, 2].map(|i| from[i] + (to[i] - from[i]) * t)
    };
    let a = if za < NEAR { cut(a, b, za, zb) } else { a };
    let b = if zb < NEAR { cut(b, a, zb, za) } else { b };
    let (ax, ay, _) = to_screen(p, a)?;
    let (bx, by, _) = to_screen(p, b)?;
    Some(((ax, ay), (bx, by)))
}

/// The 12 edges of the box a brush of `radius` around `voxel` covers.
fn brush_box(canvas: &mut Canvas, p: &Projection, cursor: &Cursor, c: Rgba) {
    let r = cursor.radius.max(0.0).floor();
    let lo = cursor.voxel.map(|v| v as f32 - r);
    let hi = cursor.voxel.map(|v| v as f32 + 1.0 + r);
    box_edges(canvas, p, lo, hi, 2.0, c);
}

/// The 12 edges of a selection's box (its voxels' outer faces), drawn thicker than a brush.
fn selection_box(canvas: &mut Canvas, p: &Projection, s: &Selection, c: Rgba) {
    let lo = s.min.map(|v| v as f32);
    let hi = s.max.map(|v| v as f32 + 1.0);
    box_edges(canvas, p, lo, hi, 3.0, c);
}

/// The 12 edges of the box `lo..hi` (voxel coordinates), `width` pixels wide on a shadow.
fn box_edges(canvas: &mut Canvas, p: &Projection, lo: [f32; 3], hi: [f32; 3], width: f32, c: Rgba) {
    let corner = |i: usize| {
        [
            if i & 1 == 0 { lo[0] } else { hi[0] },
            if i & 2 == 0 { lo[1] } else { hi[1] },
            if i & 4 == 0 { lo[2] } else { hi[2] },
        ]
    };
    for i in 0..8 {
        for bit in [1, 2, 4] {
            if i & bit == 0
                && let Some((a, b)) = segment(p, corner(i), corner(i | bit))
            {
                canvas.line(a, b, width + 2.0, canvas::SHADOW);
                canvas.line(a, b, width, c);
            }
        }
    }
}

/// A name on a dark tag with a stripe of the person's colour: readable on any scene.
fn name_tag(canvas: &mut Canvas, x: i32, y: i32, name: &str, colour: Rgba) {
    let width = 8 * name.chars().count() as i32;
    canvas.rect(x, y, width + 10, 12, PANEL);
    canvas.rect(x, y, 3, 12, colour);
    canvas.label(x + 6, y + 2, name, WHITE);
}

/// Draws the overlay for one frame into `canvas` (cleared to the projection's size first).
pub fn draw(canvas: &mut Canvas, input: &OverlayInput) {
    let p = &input.projection;
    canvas.clear(p.width, p.height);
    let (w, h) = (p.width as f32, p.height as f32);

    // Other people's selections, cursors and brushes, then their cameras on top.
    for other in input.roster.others.values() {
        if let Some(selection) = &other.state.selection {
            selection_box(canvas, p, selection, rgba(other.peer.colour, 255));
        }
        if let Some(cursor) = &other.state.cursor {
            brush_box(canvas, p, cursor, rgba(other.peer.colour, 255));
        }
    }
    // My selection, in white.
    if let Some(selection) = &input.selection {
        selection_box(canvas, p, selection, WHITE);
    }
    for other in input.roster.others.values() {
        let Some(view) = &other.state.view else {
            continue;
        };
        if input.following == Some(other.peer.id) {
            continue; // We are looking from there.
        }
        let colour = rgba(other.peer.colour, 255);
        match to_screen(p, view.eye) {
            Some((x, y, _)) if (0.0..w).contains(&x) && (0.0..h).contains(&y) => {
                let len = view.forward.iter().map(|v| v * v).sum::<f32>().sqrt();
                if len > 0.0 {
                    let tip =
                        [0, 1, 2].map(|i| view.eye[i] + view.forward[i] / len * POINTING_VOXELS);
                    if let Some((a, b)) = segment(p, view.eye, tip) {
                        canvas.line(a, b, 4.0, canvas::SHADOW);
                        canvas.line(a, b, 2.0, colour);
                    }
                }
                canvas.disc(x, y, MARKER_RADIUS + 3.0, [0, 0, 0, 200]);
                canvas.disc(x, y, MARKER_RADIUS + 1.5, WHITE);
                canvas.disc(x, y, MARKER_RADIUS, colour);
                name_tag(
                    canvas,
                    (x + MARKER_RADIUS + 6.0) as i32,
                    (y - 6.0) as i32,
                    &other.peer.name,
                    colour,
                );
            }
            seen => {
                // Off-screen or behind: a small marker at the edge, towards them.
                let (dx, dy) = match seen {
                    Some((x, y, _)) => (x - w * 0.5, y - h * 0.5),
                    None => {
                        let d = [0, 1, 2].map(|i| view.eye[i] - p.eye[i]);
                        let dot = |a: [f32; 3]| d[0] * a[0] + d[1] * a[1] + d[2] * a[2];
                        (dot(p.right), -dot(p.up))
                    }
                };
                let scale = ((w * 0.5 - 12.0) / dx.abs().max(1e-6))
                    .min((h * 0.5 - 12.0) / dy.abs().max(1e-6));
                if scale.is_finite() {
                    let (x, y) = (w * 0.5 + dx * scale, h * 0.5 + dy * scale);
                    canvas.disc(x, y, 5.0, [0, 0, 0, 200]);
                    canvas.disc(x, y, 4.0, colour);
                    let name_x = if x > w * 0.5 {
                        x as i32 - 20 - 8 * other.peer.name.chars().count() as i32
                    } else {
                        x as i32 + 10
                    };
                    name_tag(canvas, name_x, (y - 6.0) as i32, &other.peer.name, colour);
                }
            }
        }
    }

    // My brush, in my paint colour.
    if let Some(cursor) = &input.cursor {
        brush_box(canvas, p, cursor, rgba(input.colour, 255));
    }
    if input.captured {
        let (cx, cy) = (w * 0.5, h * 0.5);
        for (a, b) in [
            ((cx - 9.0, cy), (cx - 3.0, cy)),
            ((cx + 3.0, cy), (cx + 9.0, cy)),
            ((cx, cy - 9.0), (cx, cy - 3.0)),
            ((cx, cy + 3.0), (cx, cy + 9.0)),
        ] {
            canvas.line(a, b, 3.0, canvas::SHADOW);
            canvas.line(a, b, 1.0, WHITE);
        }
    }

    // The panel: me, everyone else, then the notes.
    let mut lines: Vec<(String, Rgba)> = Vec::new();
    if let Some(me) = &input.roster.you {
        let role = if me.role == Role::Viewer {
            " (viewer)"
        } else {
            ""
        };
        lines.push((format!("{} (you){role}", me.name), rgba(me.colour, 255)));
    }
    for other in input.roster.others.values() {
        let mut line = other.peer.name.clone();
        if other.peer.role == Role::Viewer {
            line.push_str(" (viewer)");
        }
        if input.following == Some(other.peer.id) {
            line.push_str(" - following");
        }
        lines.push((line, rgba(other.peer.colour, 255)));
    }
    let notes: Vec<(String, Rgba)> = input.notes.iter().map(|n| (n.clone(), WHITE)).collect();
    let rows = lines.len() + notes.len() + 1;
    let width = lines
        .iter()
        .chain(&notes)
        .map(|(t, _)| t.chars().count())
        .max()
        .unwrap_or(0)
        .max(14) as i32
        * 8
        + 30;
    canvas.rect(6, 6, width, rows as i32 * 12 + 10, PANEL);
    let mut y = 12;
    for (text, colour) in &lines {
        canvas.rect(12, y, 8, 8, *colour);
        canvas.label(26, y, text, WHITE);
        y += 12;
    }
    // My paint colour.
    canvas.rect(12, y, 8, 8, rgba(input.colour, 255));
    let brush = input.cursor.map_or(0.0, |c| c.radius);
    canvas.label(26, y, &format!("colour, brush {brush}"), WHITE);
    y += 12;
    for (text, colour) in &notes {
        canvas.label(12, y, text, *colour);
        y += 12;
    }
    if let Some(swatches) = &input.swatches {
        swatch_strip(canvas, swatches, input.colour);
    }
}

/// Where swatch `i` of the strip is drawn (its top-left corner) on an image `height` high.
pub fn strip_swatch_at(i: usize, height: u32) -> (i32, i32) {
    (12 + i as i32 * SWATCH_STEP, height as i32 - 36)
}

/// The strip of swatches at the bottom left, each with its key under it; the one drawn with
/// now is framed in white.
fn swatch_strip(canvas: &mut Canvas, swatches: &Swatches, current: Colour) {
    let height = canvas.height;
    let (x0, y0) = strip_swatch_at(0, height);
    canvas.rect(
        x0 - 6,
        y0 - 6,
        STRIP_SWATCHES as i32 * SWATCH_STEP + 6,
        SWATCH_PX + 24,
        PANEL,
    );
    for i in 0..STRIP_SWATCHES {
        let (x, y) = strip_swatch_at(i, height);
        let colour = swatches.get(i);
        if colour == current {
            canvas.rect(x - 2, y - 2, SWATCH_PX + 4, SWATCH_PX + 4, WHITE);
        }
        canvas.rect(x, y, SWATCH_PX, SWATCH_PX, rgba(colour, 255));
        canvas.label(x + 4, y + SWATCH_PX + 4, &((i + 1) % 10).to_string(), WHITE);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickcast_protocol::Camera;
    use brickcast_protocol::roster::Present;
    use brickcast_protocol::wire::{Peer, PeerState, View};

    #[test]
    fn to_screen_inverts_the_primary_rays() {
        let camera = Camera {
            eye: [10.0, 20.0, -30.0],
            target: [64.0, 0.0, 64.0],
            fov_y: 60.0,
        };
        let p = camera.project(320, 200).unwrap();
        for (x, y) in [(0, 0), (160, 100), (319, 199), (17, 150)] {
            let ray = p.ray(x, y);
            let at = [0, 1, 2].map(|i| ray.origin[i] + ray.dir[i] * 37.0);
            let (sx, sy, _) = to_screen(&p, at).unwrap();
            assert!((sx - (x as f32 + 0.5)).abs() < 1e-2, "{sx} vs {x}");
            assert!((sy - (y as f32 + 0.5)).abs() < 1e-2, "{sy} vs {y}");
        }
        let behind = [0, 1, 2].map(|i| p.eye[i] - p.forward[i]);
        assert!(to_screen(&p, behind).is_none());
    }

    #[test]
    fn a_peer_is_drawn_where_its_camera_projects() {
        let camera = Camera {
            eye: [0.0, 0.0, 0.0],
            target: [0.0, 0.0, 100.0],
            fov_y: 60.0,
        };
        let p = camera.project(320, 200).unwrap();
        let colour = Colour::from_rgb8(230, 57, 70);
        let mut roster = Roster::default();
        roster.others.insert(
            9,
            Present {
                peer: Peer {
                    id: 9,
                    user: 1,
                    name: "bob".into(),
                    colour,
                    role: Role::Editor,
                },
                state: PeerState {
                    id: 9,
                    view: Some(View {
                        eye: [10.0, 5.0, 50.0],
                        forward: [0.0, 0.0, 1.0],
                    }),
                    cursor: None,
                    selection: Some(Selection {
                        min: [2, 2, 60],
                        max: [6, 6, 64],
                    }),
                },
            },
        );
        let mut canvas = Canvas::new(1, 1);
        draw(
            &mut canvas,
            &OverlayInput {
                projection: p,
                roster: &roster,
                cursor: None,
                colour: Colour::WHITE,
                captured: true,
                notes: vec!["live".into()],
                following: None,
                swatches: None,
                selection: None,
            },
        );
        let (x, y, _) = to_screen(&p, [10.0, 5.0, 50.0]).unwrap();
        assert_eq!(canvas.get(x as u32, y as u32), rgba(colour, 255));
        // The crosshair's arms are white.
        assert_eq!(canvas.get(160 - 6, 100), WHITE);
        // Bob's selection: its box's edges in his colour (the middle of its near bottom edge).
        let (x, y, _) = to_screen(&p, [4.5, 2.0, 60.0]).unwrap();
        assert_eq!(canvas.get(x as u32, y as u32), rgba(colour, 255));
    }

    /// The strip shows the swatches keys 1–0 take, the scene's (not the default) ones, and
    /// frames the colour drawn with.
    #[test]
    fn the_swatch_strip_shows_the_scenes_palette() {
        let camera = Camera {
            eye: [0.0, 0.0, 0.0],
            target: [0.0, 0.0, 100.0],
            fov_y: 60.0,
        };
        let p = camera.project(320, 200).unwrap();
        let mut swatches = Swatches::default();
        let teal = Colour::from_rgb8(0, 128, 128);
        swatches.set(9, teal);
        let mut canvas = Canvas::new(1, 1);
        let roster = Roster::default();
        let input = |swatches| OverlayInput {
            projection: p,
            roster: &roster,
            cursor: None,
            colour: teal,
            captured: false,
            notes: Vec::new(),
            following: None,
            swatches,
            selection: None,
        };
        draw(&mut canvas, &input(Some(swatches)));
        let centre = |i| {
            let (x, y) = strip_swatch_at(i, 200);
            ((x + SWATCH_PX / 2) as u32, (y + SWATCH_PX / 2) as u32)
        };
        for i in 0..STRIP_SWATCHES {
            let (x, y) = centre(i);
            assert_eq!(canvas.get(x, y), rgba(swatches.get(i), 255), "swatch {i}");
        }
        let (x, y) = strip_swatch_at(9, 200);
        assert_eq!(canvas.get((x - 1) as u32, y as u32), WHITE, "framed");
        let (x, y) = strip_swatch_at(0, 200);
        assert_ne!(canvas.get((x - 1) as u32, y as u32), WHITE);
        draw(&mut canvas, &input(None));
        let (x, y) = centre(0);
        assert_eq!(canvas.get(x, y)[3], 0, "no strip without a palette");
    }
}
