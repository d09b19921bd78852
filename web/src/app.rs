//! The viewer's state and its frame: the shared session and GPU pieces, driven by the browser's
//! animation-frame clock.
//!
//! One frame: copy what the socket applied into the GPU scene (`present::sync_scene`), move the
//! camera, trace at the current resolution scale, blit and blend the overlay onto the canvas.
//! A frame is traced only when the previous one has finished on the GPU, so a slow adapter
//! never builds a queue; the scale adapts so interaction stays smooth (see [`Scale`]).

use std::cell::RefCell;
use std::collections::HashSet;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use brickcast_client_core::camera::{FirstView, FlyCamera, movement};
use brickcast_client_core::follow::Follow;
use brickcast_client_core::gpu::tracer::PendingFrame;
use brickcast_client_core::gpu::{
    BackendChoice, GpuContext, GpuError, GpuFrame, GpuScene, Tracer, new_instance,
};
use brickcast_client_core::overlay::canvas::Canvas;
use brickcast_client_core::overlay::{OverlayInput, draw as draw_overlay};
use brickcast_client_core::paste::Pasting;
use brickcast_client_core::present::{Presenter, acquire, sync_scene};
use brickcast_client_core::session::{ClientSeq, Session, Status};
use brickcast_client_core::shading::{NOTE_SECONDS, SHADING_KEYS, shading_key};
use brickcast_client_core::swatch::{SwatchAction, swatch_action, swatch_key};
use brickcast_client_core::tools::{
    Action, Button, Context as ToolContext, Tool, Tools, selection_note, step_radius,
};
use brickcast_protocol::swatches::Swatches;
use brickcast_protocol::wire::{
    ClientMsg, Cursor, EditOp, ErrorCode, Role, Selection, UserId, View,
};
use brickcast_protocol::{Camera, Colour, Lighting, Projection};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;

use crate::net::{self, Socket};
use crate::page;

/// Everything that exists once the GPU does.
pub struct Gpu {
    pub ctx: Rc<GpuContext>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    tracer: Tracer,
    /// A second tracer for exact-size frames asked for by the test hook, so they never resize
    /// the view's own target.
    probe: Option<Tracer>,
    presenter: Presenter,
    scene: Option<GpuScene>,
}

/// The trace resolution: the canvas divided by `divisor` on each axis. A slow adapter (software
/// WebGPU traces about 0.3 Mrays/s) gets a coarser picture rather than a stuttering one.
pub struct Scale {
    pub divisor: u32,
    /// GPU time of the last finished frame (ms), and how many frames have finished.
    pub last_ms: f64,
    pub frames: u64,
    /// Set by the page (`?scale=N`) or a test: the divisor stays put.
    pinned: bool,
    /// GPU time of recent frames, smoothed (ms).
    pub gpu_ms: f64,
    changed_at: f64,
}

/// Frame time the scale aims for, and the band it keeps to before changing.
const TARGET_MS: f64 = 33.0;
const MAX_DIVISOR: u32 = 8;

/// While a scene streams in (after its first picture), tracing takes at most this share of the
/// time: a frame waits after the last one (1/share − 1) times as long as the GPU took for it.
/// On a GPU a frame takes a millisecond or two and nothing changes; on a software adapter (the
/// test browser's SwiftShader) every frame's rays are traced on the cores that also take the
/// stream in, and on the 16k world the frames took most of one of them while it streamed.
const SYNCING_TRACE_SHARE: f64 = 0.25;
/// ... but the picture still changes a few times a second. (What a frame's GPU time measures
/// includes the uploads queued before it, which grow as frames space out: uncapped, frames came
/// 1, 1.6, 3 and 4.6 s apart on the 16k world.)
const SYNCING_MAX_WAIT_MS: f64 = 250.0;

impl Scale {
    /// Fixes the divisor (1 to 8), or with 0 lets it adapt again.
    pub fn pin(&mut self, divisor: u32) {
        self.pinned = divisor > 0;
        if self.pinned {
            self.divisor = divisor.min(MAX_DIVISOR);
        }
        self.gpu_ms = 0.0;
    }

    fn observe(&mut self, gpu_ms: f64, now: f64) {
        self.last_ms = gpu_ms;
        self.frames += 1;
        self.gpu_ms = if self.gpu_ms == 0.0 {
            gpu_ms
        } else {
            self.gpu_ms * 0.8 + gpu_ms * 0.2
        };
        if self.pinned || now - self.changed_at < 500.0 {
            return;
        }
        if self.gpu_ms > TARGET_MS * 1.5 && self.divisor < MAX_DIVISOR {
            self.divisor += 1;
        } else if self.gpu_ms < TARGET_MS * 0.4 && self.divisor > 1 {
            self.divisor -= 1;
        } else {
            return;
        }
        self.changed_at = now;
        self.gpu_ms = 0.0;
    }
}

pub struct App {
    pub scene: String,
    pub token: Option<String>,
    pub name: String,
    pub user: UserId,
    pub session: Session,
    seq: ClientSeq,
    pub socket: Option<Socket>,
    /// Sockets closed from inside one of their own callbacks, dropped at the next connect.
    pub retired: Vec<Socket>,
    pub backoff: brickcast_client_core::backoff::Backoff,
    pub bytes_in: u64,
    canvas: web_sys::HtmlCanvasElement,
    gpu: Option<Gpu>,
    gpu_error: Option<String>,
    camera: Option<FlyCamera>,
    first_view: FirstView,
    /// What the O, L and H keys switch (`shading::SHADING_KEYS`).
    lighting: Lighting,
    /// What the last lighting key switched, and when (page clock, ms): shown for
    /// `NOTE_SECONDS` in the overlay and the status line.
    lighting_note: Option<(String, f64)>,
    keys: HashSet<String>,
    pub ctrl: bool,
    /// Looking around: pointer locked, or a drag in progress.
    pub locked: bool,
    /// Canvas position of the pointer (CSS pixels).
    pub pointer: (f64, f64),
    colour: Colour,
    /// The palette the page's swatches show, and the colour they mark as in use (`None`: not
    /// painted yet).
    shown_swatches: Option<(Swatches, Colour)>,
    /// The tool in use, and a drag in progress (box, line).
    pub tools: Tools,
    /// Alt held at the last press: any tool picks a colour.
    pub alt: bool,
    radius: f32,
    follow: Follow,
    overlay: Canvas,
    /// Projection of the last traced frame, for turning clicks into rays.
    projection: Option<Projection>,
    presence_sent: Option<(Option<View>, Option<Cursor>, Option<Selection>)>,
    /// What the select tool selected (shared with everyone, drawn in white).
    selection: Option<Selection>,
    /// The clipboard as this page knows it, and how the next paste turns.
    pasting: Pasting,
    presence_at: f64,
    my_cursor: Option<Cursor>,
    pub scale: Scale,
    /// When the frame on the GPU was submitted, and when it finished (set by the GPU's callback).
    submitted_at: f64,
    /// No frame before this while a scene streams in ([`SYNCING_TRACE_SHARE`]).
    next_frame_at: f64,
    /// (Atomics only because wgpu asks for `Send` callbacks; a page has one thread.)
    done_at: Arc<AtomicU64>,
    in_flight: Arc<AtomicBool>,
    last_frame: f64,
    frames: u64,
    fps: f64,
    fps_frames: u32,
    fps_at: f64,
    /// When (ms since the page started loading) the GPU finished the first frame with bricks in
    /// it, and the first of the whole synced scene.
    first_picture_ms: Option<f64>,
    synced_ms: Option<f64>,
    /// When (ms since the page started loading) the viewer started, its GPU device was ready,
    /// and the first Welcome arrived: where the time to the first picture goes.
    started_ms: f64,
    gpu_ready_ms: Option<f64>,
    welcome_ms: Option<f64>,
    /// The frame on the GPU shows bricks / the whole synced scene.
    pending_picture: bool,
    pending_synced: bool,
    /// The camera was sent to the server during this connection's sync (nearest bricks first).
    camera_sent: bool,
}

/// A random user id kept in the browser's local storage, so undo history follows this browser
/// across visits (never 0, top bit clear: ids with it set are the server's).
fn browser_user_id() -> UserId {
    let storage = web_sys::window().and_then(|w| w.local_storage().ok().flatten());
    if let Some(s) = &storage
        && let Ok(Some(text)) = s.get_item("brickcast.user")
        && let Ok(id) = text.parse::<u64>()
        && id != 0
        && id >> 63 == 0
    {
        return id;
    }
    let half = || (js_sys::Math::random() * 4_294_967_296.0) as u64;
    let id = (((half() << 32) | half()) >> 1).max(1);
    if let Some(s) = &storage {
        let _ = s.set_item("brickcast.user", &id.to_string());
    }
    id
}

impl App {
    pub fn new(
        scene: String,
        token: Option<String>,
        name: Option<String>,
        colours: brickcast_protocol::blocks::Quality,
    ) -> Result<Rc<RefCell<App>>, JsValue> {
        let canvas: web_sys::HtmlCanvasElement = page::document()
            .and_then(|d| d.get_element_by_id("view"))
            .ok_or("the page has no canvas with id \"view\"")?
            .dyn_into()?;
        let now = page::now_ms();
        Ok(Rc::new(RefCell::new(App {
            scene,
            token: token.filter(|t| !t.is_empty()),
            name: name
                .filter(|n| !n.trim().is_empty())
                .unwrap_or_else(|| "guest".to_string()),
            user: browser_user_id(),
            session: Session {
                colours,
                ..Session::default()
            },
            seq: ClientSeq::default(),
            socket: None,
            retired: Vec::new(),
            backoff: brickcast_client_core::backoff::reconnect(),
            bytes_in: 0,
            canvas,
            gpu: None,
            gpu_error: None,
            camera: None,
            first_view: FirstView::default(),
            lighting: Lighting::default(),
            lighting_note: None,
            keys: HashSet::new(),
            ctrl: false,
            locked: false,
            pointer: (0.0, 0.0),
            colour: Swatches::default().get(0),
            shown_swatches: None,
            tools: Tools::default(),
            alt: false,
            radius: 0.0,
            follow: Follow::default(),
            overlay: Canvas::new(1, 1),
            projection: None,
            presence_sent: None,
            selection: None,
            pasting: Pasting::default(),
            presence_at: 0.0,
            my_cursor: None,
            // Coarse at first, so the first picture comes fast on any adapter; it refines.
            scale: Scale {
                divisor: 4,
                last_ms: 0.0,
                frames: 0,
                pinned: false,
                gpu_ms: 0.0,
                changed_at: now,
            },
            submitted_at: 0.0,
            next_frame_at: 0.0,
            done_at: Arc::new(AtomicU64::new(0)),
            in_flight: Arc::new(AtomicBool::new(false)),
            last_frame: now,
            frames: 0,
            fps: 0.0,
            fps_frames: 0,
            fps_at: now,
            first_picture_ms: None,
            synced_ms: None,
            started_ms: now,
            gpu_ready_ms: None,
            welcome_ms: None,
            pending_picture: false,
            pending_synced: false,
            camera_sent: false,
        })))
    }

    pub fn canvas(&self) -> &web_sys::HtmlCanvasElement {
        &self.canvas
    }

    /// Gives up for good, telling the user why.
    pub fn fail(&mut self, why: String) {
        page::message(Some(&why));
        self.session.status = Status::Failed(why);
        self.retire_socket();
    }

    /// The server refused the Hello.
    pub fn refused(&mut self, code: ErrorCode, message: &str) {
        if matches!(code, ErrorCode::ShuttingDown | ErrorCode::RateLimited) {
            // Trying again later can help: let the close handler schedule it.
            self.drop_connection(format!("refused for now: {message}"));
            return;
        }
        net::show_refusal(code, message, &self.scene);
        let (text, _) = net::refusal_text(code, message, &self.scene);
        self.session.status = Status::Failed(text);
        self.retire_socket();
    }

    /// Closes the socket for good (no reconnect).
    fn retire_socket(&mut self) {
        if let Some(s) = self.socket.take() {
            s.close_quietly();
            self.retired.push(s);
        }
    }

    /// Closes the connection so that the close handler reconnects (and resumes).
    pub fn drop_connection(&mut self, why: String) {
        self.session.status = Status::Reconnecting(why);
        if let Some(s) = &self.socket {
            s.close();
        }
    }

    /// A new connection was welcomed.
    pub fn welcomed(&mut self) {
        if self.gpu_error.is_none() {
            page::message(None);
        }
        page::show("token-form", false);
        self.welcome_ms.get_or_insert_with(page::now_ms);
        self.camera_sent = false;
        if let Some(replica) = &self.session.replica {
            self.first_view
                .place(&mut self.camera, &replica.map, replica.synced);
        }
    }

    fn send(&self, msg: &ClientMsg) -> bool {
        self.socket.as_ref().is_some_and(|s| s.send(msg))
    }

    pub fn key_down(&mut self, code: &str, ctrl: bool, shift: bool) -> bool {
        self.ctrl = ctrl;
        let handled = match code {
            "KeyZ" if ctrl => {
                let msg = self.seq.undo(shift);
                self.send(&msg);
                true
            }
            "KeyY" if ctrl => {
                let msg = self.seq.undo(true);
                self.send(&msg);
                true
            }
            "KeyC" if ctrl => {
                let copied = self.pasting.copy(self.selection);
                self.send_paste_op(copied);
                true
            }
            "KeyX" if ctrl => {
                match self.pasting.cut(self.selection) {
                    Ok((ops, note)) => {
                        let msg = self.seq.edit(ops);
                        self.send(&msg);
                        self.note(note);
                    }
                    Err(why) => self.note(why.to_string()),
                }
                true
            }
            "KeyV" if ctrl => {
                let pasted = match self.projection {
                    Some(p) => {
                        let ray = self.pointer_ray(&p);
                        let map = self.session.replica.as_ref().map(|r| &r.map);
                        self.pasting.paste(map, &ray)
                    }
                    None => Err("the scene is not here yet"),
                };
                self.send_paste_op(pasted);
                true
            }
            "KeyR" if !ctrl => {
                let note = self.pasting.turn();
                self.note(note);
                true
            }
            "KeyM" if !ctrl => {
                let note = self.pasting.mirror();
                self.note(note);
                true
            }
            "KeyF" => {
                self.follow.cycle(&self.session.roster);
                true
            }
            _ if SHADING_KEYS.iter().any(|(key, _)| *key == code) => {
                match shading_key(&mut self.lighting, code) {
                    Some(note) => {
                        self.lighting_note = Some((note, page::now_ms()));
                        page::set_text("status", &self.status_line());
                        true
                    }
                    None => false,
                }
            }
            "BracketLeft" | "BracketRight" => {
                let max = self.session.max_radius;
                self.radius = step_radius(self.radius, code == "BracketRight", max);
                true
            }
            _ => match swatch_key(code, shift, &self.session.swatches(), self.colour) {
                Some(action) => {
                    self.swatch(action);
                    true
                }
                None => match Tool::from_key(code) {
                    Some(tool) if !ctrl => {
                        self.tools.pick_tool(tool);
                        page::set_attr("toolbox", "data-tool", tool.name());
                        self.note(format!("tool: {}", tool.name()));
                        true
                    }
                    _ => false,
                },
            },
        };
        let moves = brickcast_client_core::camera::MOVE_KEYS
            .iter()
            .any(|(p, m)| p.contains(&code) || m.contains(&code));
        if moves && !ctrl {
            self.keys.insert(code.to_string());
        }
        handled || moves
    }

    pub fn key_up(&mut self, code: &str) {
        self.keys.remove(code);
    }

    pub fn release_keys(&mut self) {
        self.keys.clear();
    }

    pub fn look(&mut self, dx: f64, dy: f64) {
        self.follow.stop();
        if let Some(c) = &mut self.camera {
            c.look(dx as f32, dy as f32);
        }
    }

    /// Wheel: faster or slower flight.
    pub fn wheel(&mut self, delta_y: f64) {
        if let Some(c) = &mut self.camera {
            let factor = if delta_y < 0.0 { 1.25 } else { 0.8 };
            c.speed = (c.speed * factor).clamp(1.0, 4096.0);
        }
    }

    /// Flies along (forward, right, up) for `dt` seconds (touch gestures).
    pub fn fly(&mut self, dir: [f32; 3], dt: f32) {
        self.follow.stop();
        if let Some(c) = &mut self.camera {
            c.fly(dir, dt);
        }
    }

    pub fn set_camera(&mut self, eye: &[f32], target: &[f32]) -> Result<(), JsValue> {
        let (Ok(eye), Ok(target)) = (<[f32; 3]>::try_from(eye), <[f32; 3]>::try_from(target))
        else {
            return Err("eye and target are three numbers each".into());
        };
        let size = self
            .session
            .replica
            .as_ref()
            .map_or([64; 3], |r| r.map.size());
        let fov_y = self.camera.map_or(60.0, |c| c.fov_y);
        self.follow.stop();
        self.camera = Some(FlyCamera {
            speed: self.camera.map_or(8.0, |c| c.speed),
            ..FlyCamera::from_camera(&Camera { eye, target, fov_y }, size)
        });
        Ok(())
    }

    /// The ray under the pointer, or through the centre while the pointer is locked.
    fn pointer_ray(&self, p: &Projection) -> brickcast_protocol::Ray {
        let (cw, ch) = (
            f64::from(self.canvas.client_width().max(1)),
            f64::from(self.canvas.client_height().max(1)),
        );
        let (x, y) = if self.locked {
            (p.width / 2, p.height / 2)
        } else {
            (
                ((self.pointer.0 / cw * f64::from(p.width)) as u32).min(p.width - 1),
                ((self.pointer.1 / ch * f64::from(p.height)) as u32).min(p.height - 1),
            )
        };
        p.ray(x, y)
    }

    /// A press (`pressed`) or release of `button` at the pointer: what the tool in use does
    /// (the native viewer's tools). A click is a press and a release in one place.
    pub fn click(&mut self, button: Button, pressed: bool) {
        // A viewer may take colours and select (pointing a region out to others), not edit.
        let picking = self.alt || matches!(self.tools.tool, Tool::Picker | Tool::Select);
        if self.session.role != Some(Role::Editor) && !picking {
            if pressed {
                page::set_text("note", "this link only lets you watch; edits are ignored");
            }
            return;
        }
        let Some(p) = self.projection else { return };
        let ray = self.pointer_ray(&p);
        let cx = ToolContext {
            radius: self.radius,
            paint: self.ctrl,
            pick: self.alt,
            colour: self.colour,
            limits: &self.session.limits,
            map: self.session.replica.as_ref().map(|r| &r.map),
        };
        let action = if pressed {
            self.tools.press(button, &ray, &cx)
        } else {
            self.tools.release(button, &ray, &cx)
        };
        match action {
            Action::Edit(op) => {
                let msg = self.seq.edit(vec![op]);
                self.send(&msg);
            }
            Action::Picked(colour) => {
                self.set_colour(colour);
                let [r, g, b] = colour.to_rgb8();
                self.note(format!("took colour #{r:02x}{g:02x}{b:02x}"));
            }
            Action::Selected(selection) => {
                self.selection = selection;
                self.note(selection_note(selection));
            }
            Action::Nothing(why) if !why.is_empty() => self.note(why.to_string()),
            Action::Started | Action::Nothing(_) => {}
        }
    }

    /// Sends a copy's or a paste's op and says what it did, or says why there was none.
    fn send_paste_op(&mut self, made: Result<(EditOp, String), &'static str>) {
        match made {
            Ok((op, note)) => {
                let msg = self.seq.edit(vec![op]);
                self.send(&msg);
                self.note(note);
            }
            Err(why) => self.note(why.to_string()),
        }
    }

    /// Swatch `index` of the palette clicked on the page: take it, or with `set` (Shift held)
    /// make it the colour drawn with now, for everyone.
    pub fn click_swatch(&mut self, index: usize, set: bool) {
        if let Some(action) = swatch_action(index, set, &self.session.swatches(), self.colour) {
            self.swatch(action);
        }
    }

    fn swatch(&mut self, action: SwatchAction) {
        match action {
            SwatchAction::Take { colour, .. } => self.set_colour(colour),
            SwatchAction::Set { op, .. } => {
                let msg = self.seq.edit(vec![op]);
                self.send(&msg);
            }
        }
        self.note(action.note());
    }

    /// Restores the selection (the whole scene when nothing is selected) to sequence `to`
    /// (the history panel's "restore": `client_core::history`).
    pub fn restore(&mut self, to: u64) {
        let Some(size) = self.session.replica.as_ref().map(|r| r.map.size()) else {
            self.note("the scene is not here yet".into());
            return;
        };
        let (op, note) = brickcast_client_core::history::restore(self.selection, size, to);
        let msg = self.seq.edit(vec![op]);
        self.send(&msg);
        self.note(note);
    }

    /// Paints the page's swatches when the scene's palette is not what they show.
    fn show_swatches(&mut self) {
        let swatches = self.session.swatches();
        if self.shown_swatches == Some((swatches, self.colour)) {
            return;
        }
        self.shown_swatches = Some((swatches, self.colour));
        let colours: Vec<String> = swatches.0.iter().map(|c| c.to_hex()).collect();
        let titles: Vec<String> = colours
            .iter()
            .enumerate()
            .map(|(i, hex)| {
                let key = if i < 10 {
                    format!(" (key {})", (i + 1) % 10)
                } else {
                    String::new()
                };
                format!(
                    "swatch {}{key}: {hex} · Shift+click sets it to your colour for everyone",
                    i + 1
                )
            })
            .collect();
        page::set_swatches("swatches", &colours, &titles, &self.colour.to_hex());
    }

    /// Draws with `colour` from now on (the page's colour chooser shows it).
    pub fn set_colour(&mut self, colour: Colour) {
        self.colour = colour;
        page::set_value("colour", &colour.to_hex());
        self.show_swatches();
    }

    /// A note on the status line for a few seconds.
    fn note(&mut self, text: String) {
        self.lighting_note = Some((text, page::now_ms()));
        page::set_text("status", &self.status_line());
    }

    /// Shares view and cursor at the server's presence rate, when they changed.
    fn share_presence(&mut self, now: f64) {
        let Some(camera) = self.camera else { return };
        let view = Some(View {
            eye: camera.eye,
            forward: camera.forward(),
        });
        let cursor = match (&self.session.replica, &self.projection) {
            (Some(replica), Some(p)) => {
                brickcast_protocol::trace(&replica.map, &self.pointer_ray(p)).map(|hit| Cursor {
                    voxel: hit.voxel,
                    radius: self.radius,
                })
            }
            _ => None,
        };
        self.my_cursor = cursor;
        let syncing = self.session.replica.as_ref().is_some_and(|r| !r.synced);
        if syncing && !self.camera_sent {
            // Nearest bricks first: the server orders the rest of the sync by this camera.
            self.camera_sent = self.send(&ClientMsg::Camera {
                eye: camera.eye,
                forward: camera.forward(),
            });
        }
        if now < self.presence_at || self.session.status != Status::Live {
            return;
        }
        let sharing = (view, cursor, self.selection);
        if let Some(v) = &view {
            self.session.eye = Some(v.eye);
        }
        let presence = ClientMsg::Presence {
            view,
            cursor,
            selection: self.selection,
        };
        if self.presence_sent != Some(sharing) && self.send(&presence) {
            self.presence_sent = Some(sharing);
            self.presence_at = now + 1000.0 / f64::from(self.session.presence_hz.max(1));
        }
    }

    /// One animation frame.
    fn frame(&mut self) {
        let now = page::now_ms();
        let dt = ((now - self.last_frame) / 1000.0).min(0.25) as f32;
        self.last_frame = now;
        let held = |k: &str| self.keys.contains(k);
        let dir = movement(held);
        if dir != [0.0; 3] {
            self.follow.stop();
        }
        if let Some(view) = self.follow.view(&self.session.roster)
            && let Some(c) = &mut self.camera
        {
            c.look_along(view);
        } else if let Some(c) = &mut self.camera {
            c.fly(dir, dt);
        }
        if let Err(e) = self.draw(now) {
            self.gpu_error = Some(e.clone());
            page::message(Some(&format!("The GPU failed: {e}")));
            self.gpu = None;
        }
        self.share_presence(now);
        self.fps_frames += 1;
        if now - self.fps_at >= 500.0 {
            self.fps = f64::from(self.fps_frames) * 1000.0 / (now - self.fps_at);
            self.fps_frames = 0;
            self.fps_at = now;
            page::set_text("status", &self.status_line());
            // Editing tools only for an editor, and not over a message that must be read.
            let tools = self.session.role == Some(Role::Editor)
                && self.gpu_error.is_none()
                && !page::shown("message");
            page::show("tools", tools);
            page::show("toolbox", tools);
            self.show_swatches();
        }
    }

    fn status_line(&self) -> String {
        let mut line = self.session.status_text();
        // Frames and resolution only where something is drawn.
        if self.gpu.is_some() {
            line.push_str(&format!(
                " · {:.0} fps · 1/{} resolution",
                self.fps, self.scale.divisor
            ));
        }
        match self.session.role {
            Some(Role::Editor) => {
                let [r, g, b] = self.colour.to_rgb8();
                line.push_str(&format!(
                    " · editor · {} · colour #{r:02x}{g:02x}{b:02x} · brush {}",
                    self.tools.tool.name(),
                    self.radius
                ));
            }
            Some(Role::Viewer) => line.push_str(" · watching"),
            None => {}
        }
        match self.session.roster.others.len() {
            0 => {}
            1 => line.push_str(" · 1 other here"),
            n => line.push_str(&format!(" · {n} others here")),
        }
        if let Some(note) = self.lighting_note() {
            line.push_str(&format!(" · {note}"));
        }
        line
    }

    /// What the last lighting key switched, while it is recent.
    fn lighting_note(&self) -> Option<String> {
        self.lighting_note
            .as_ref()
            .filter(|(_, at)| page::now_ms() - at < NOTE_SECONDS * 1000.0)
            .map(|(note, _)| note.clone())
    }

    fn draw(&mut self, now: f64) -> Result<(), String> {
        // The GPU finished the last frame: learn from its time.
        if self.in_flight.load(Ordering::Relaxed) {
            return Ok(());
        }
        if self.submitted_at > 0.0 {
            let done = f64::from_bits(self.done_at.load(Ordering::Relaxed));
            self.scale.observe(done - self.submitted_at, now);
            let wait = (done - self.submitted_at) * (1.0 / SYNCING_TRACE_SHARE - 1.0);
            self.next_frame_at = done + wait.min(SYNCING_MAX_WAIT_MS);
            self.submitted_at = 0.0;
            // The picture is there once the GPU has finished it.
            if self.pending_picture && self.first_picture_ms.is_none() {
                self.first_picture_ms = Some(done);
            }
            if self.pending_synced && self.synced_ms.is_none() {
                self.synced_ms = Some(done);
            }
        }
        let streaming = self
            .session
            .replica
            .as_ref()
            .is_some_and(|r| !r.synced && self.first_picture_ms.is_some());
        if streaming && now < self.next_frame_at {
            return Ok(());
        }
        let lighting_note = self.lighting_note();
        let Some(gpu) = &mut self.gpu else {
            return Ok(());
        };
        let ctx = gpu.ctx.clone();
        let synced = match &mut self.session.replica {
            Some(replica) => {
                self.first_view
                    .place(&mut self.camera, &replica.map, replica.synced);
                sync_scene(&ctx, &mut gpu.scene, replica).map_err(|e| e.to_string())?;
                replica.synced
            }
            None => false,
        };
        // Follow the canvas's size on the page.
        let (w, h) = (
            self.canvas.client_width().max(1) as u32,
            self.canvas.client_height().max(1) as u32,
        );
        if (w, h) != (gpu.config.width, gpu.config.height) {
            self.canvas.set_width(w);
            self.canvas.set_height(h);
            gpu.config.width = w;
            gpu.config.height = h;
            gpu.surface.configure(&ctx.device, &gpu.config);
        }
        let Some(frame) = acquire(&ctx, &gpu.surface, &gpu.config) else {
            return Ok(());
        };
        let target = frame
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        let d = self.scale.divisor;
        let (tw, th) = (w.div_ceil(d).max(1), h.div_ceil(d).max(1));
        let mut traced = false;
        if let (Some(scene), Some(camera)) = (&gpu.scene, &self.camera)
            && let Some(p) = camera.camera().project(tw, th)
        {
            gpu.tracer
                .encode(&ctx, &mut encoder, scene, &p, &self.lighting)
                .map_err(|e| e.to_string())?;
            self.projection = Some(p);
            traced = true;
        }
        if let Some(camera) = &self.camera
            && let Some(p) = camera.camera().project(w, h)
        {
            let mut notes = Vec::new();
            if let Some(why) = &self.session.last_rejection {
                notes.push(format!("last edit rejected: {why}"));
            }
            if let Some(undo) = &self.session.last_undo {
                notes.push(undo.clone());
            }
            notes.extend(lighting_note);
            draw_overlay(
                &mut self.overlay,
                &OverlayInput {
                    projection: p,
                    roster: &self.session.roster,
                    cursor: self.my_cursor.map(|c| Cursor {
                        radius: self.radius,
                        ..c
                    }),
                    colour: self.colour,
                    captured: self.locked,
                    notes,
                    following: self.follow.target,
                    // The page lists the palette in its tool bar.
                    swatches: None,
                    selection: self.selection,
                },
            );
            gpu.presenter.upload_overlay(&ctx, &self.overlay);
        }
        let image = if traced {
            gpu.tracer.image_view()
        } else {
            None
        };
        gpu.presenter.draw(&ctx, &mut encoder, &target, image);
        ctx.queue.submit([encoder.finish()]);
        ctx.queue.present(frame);
        self.submitted_at = now;
        self.in_flight.store(true, Ordering::Relaxed);
        let (in_flight, done_at) = (self.in_flight.clone(), self.done_at.clone());
        ctx.queue.on_submitted_work_done(move || {
            done_at.store(page::now_ms().to_bits(), Ordering::Relaxed);
            in_flight.store(false, Ordering::Relaxed);
        });
        self.frames += 1;
        // Coarse stand-ins are a picture too: a working set shows its far levels first (as
        // `brickcast fly` counts its first picture at the first coarse or level-0 bricks).
        let has_bricks = self
            .session
            .replica
            .as_ref()
            .is_some_and(|r| r.map.brick_count() > 0 || r.map.stand_in_count() > 0);
        self.pending_picture = traced && has_bricks;
        self.pending_synced = traced && synced;
        Ok(())
    }

    /// Traces one exact-size frame for the test hook and starts reading it back.
    pub fn start_exact_trace(
        &mut self,
        width: u32,
        height: u32,
        eye: &[f32],
        target: &[f32],
        fov_y: f32,
    ) -> Result<(Rc<GpuContext>, PendingFrame), JsValue> {
        let (Ok(eye), Ok(target)) = (<[f32; 3]>::try_from(eye), <[f32; 3]>::try_from(target))
        else {
            return Err("eye and target are three numbers each".into());
        };
        let gpu = self.gpu.as_mut().ok_or("the GPU is not ready")?;
        let ctx = gpu.ctx.clone();
        if let Some(replica) = &mut self.session.replica {
            sync_scene(&ctx, &mut gpu.scene, replica).map_err(|e| e.to_string())?;
        }
        let scene = gpu.scene.as_ref().ok_or("no scene yet")?;
        let p = Camera { eye, target, fov_y }
            .project(width, height)
            .ok_or("that camera cannot be projected")?;
        if gpu.probe.is_none() {
            gpu.probe = Some(Tracer::new(&ctx).map_err(|e| e.to_string())?);
        }
        let probe = gpu.probe.as_mut().ok_or("no tracer")?;
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("exact"),
            });
        probe
            .encode(&ctx, &mut encoder, scene, &p, &self.lighting)
            .map_err(|e| e.to_string())?;
        ctx.queue.submit([encoder.finish()]);
        let pending = probe.start_read_back(&ctx).map_err(|e| e.to_string())?;
        Ok((ctx, pending))
    }

    pub fn state_json(&self) -> String {
        let replica = self.session.replica.as_ref();
        let value = serde_json::json!({
            "status": match &self.session.status {
                Status::Connecting => "connecting",
                Status::Syncing => "syncing",
                Status::Live => "live",
                Status::Reconnecting(_) => "reconnecting",
                Status::Failed(_) => "failed",
            },
            "status_text": self.session.status_text(),
            "synced": replica.is_some_and(|r| r.synced),
            "seq": replica.map(|r| r.seq),
            "bricks": replica.map_or(0, |r| r.map.brick_count()),
            "scene_bytes": replica.map_or(0, |r| r.map.memory().total_bytes),
            "size": replica.map(|r| r.map.size()),
            "connects": self.session.connects,
            "frames": self.frames,
            "fps": self.fps,
            "divisor": self.scale.divisor,
            "gpu_ms": self.scale.gpu_ms,
            "gpu_last_ms": self.scale.last_ms,
            "gpu_frames": self.scale.frames,
            "adapter": self.gpu.as_ref().map(|g| g.ctx.adapter_name.clone()),
            "gpu_error": self.gpu_error,
            "started_ms": self.started_ms,
            "gpu_ready_ms": self.gpu_ready_ms,
            "welcome_ms": self.welcome_ms,
            "first_picture_ms": self.first_picture_ms,
            "synced_ms": self.synced_ms,
            "role": self.session.role.map(|r| format!("{r:?}")),
            "rejected": self.session.rejected,
            "last_undo": self.session.last_undo,
            "others": self.session.roster.others.values().map(|o| o.peer.name.clone()).collect::<Vec<_>>(),
            // User id (a string: ids are 64-bit) → name, for whoever is here (the history panel).
            "names": self.session.roster.you.iter().chain(self.session.roster.others.values().map(|o| &o.peer))
                .map(|p| (p.user.to_string(), p.name.clone()))
                .collect::<std::collections::BTreeMap<_, _>>(),
            "bytes_in": self.bytes_in,
            "camera": self.camera.map(|c| c.eye),
            "budget": self.session.budget,
            "gpu_bytes": self.gpu.as_ref().and_then(|g| g.scene.as_ref()).map(|s| s.gpu_bytes()),
            // What crossed to the GPU since the scene's buffers were made (bytes, writes,
            // pools reallocated).
            "uploaded": self.gpu.as_ref().and_then(|g| g.scene.as_ref()).map(|s| {
                let u = s.uploaded;
                serde_json::json!({ "bytes": u.bytes, "writes": u.writes, "reallocations": u.reallocations })
            }),
            // The working set the server streams within the budget (`null`: the whole scene).
            "working_set": replica.and_then(|r| r.held()).and_then(|h| h.rule()).map(|rule| {
                serde_json::json!({ "eye": rule.eye, "near": rule.near, "top": rule.top })
            }),
            "stand_ins": replica.map_or(0, |r| r.map.stand_in_count()),
            "selection": self.selection.map(|s| [s.min, s.max]),
            "colour": self.colour.to_hex(),
            // The scene's shared palette as this copy holds it.
            "swatches": self.session.swatches().0.iter().map(|c| c.to_hex()).collect::<Vec<_>>(),
        });
        value.to_string()
    }
}

/// Creates the GPU context on the canvas (asynchronously: adapters are promises in a browser).
pub fn start_gpu(app: &Rc<RefCell<App>>) {
    let app = app.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let canvas = app.borrow().canvas.clone();
        let instance = new_instance(BackendChoice::Primary, None);
        let surface = match instance.create_surface(wgpu::SurfaceTarget::Canvas(canvas.clone())) {
            Ok(s) => s,
            Err(e) => return no_gpu(&app, &format!("cannot draw on the canvas: {e}")),
        };
        let ctx = match GpuContext::with_instance(instance, Some(&surface)).await {
            Ok(ctx) => ctx,
            Err(GpuError::NoAdapter(_)) => {
                return no_gpu(
                    &app,
                    "the browser offers WebGPU but no adapter: it may be switched off, or the GPU blocklisted",
                );
            }
            Err(e) => return no_gpu(&app, &e.to_string()),
        };
        let (w, h) = (
            canvas.client_width().max(1) as u32,
            canvas.client_height().max(1) as u32,
        );
        let Some(mut config) = surface.get_default_config(&ctx.adapter, w, h) else {
            return no_gpu(
                &app,
                &format!("{} cannot draw on this canvas", ctx.adapter_name),
            );
        };
        // The traced bytes are already display values: no sRGB conversion on the way out.
        let caps = surface.get_capabilities(&ctx.adapter);
        if let Some(f) = caps.formats.iter().find(|f| !f.is_srgb()) {
            config.format = *f;
        }
        canvas.set_width(w);
        canvas.set_height(h);
        surface.configure(&ctx.device, &config);
        let tracer = match Tracer::new(&ctx) {
            Ok(t) => t,
            Err(e) => return no_gpu(&app, &e.to_string()),
        };
        let presenter = Presenter::new(&ctx.device, config.format);
        let mut a = app.borrow_mut();
        a.gpu_ready_ms = Some(page::now_ms());
        a.gpu = Some(Gpu {
            ctx: Rc::new(ctx),
            surface,
            config,
            tracer,
            probe: None,
            presenter,
            scene: None,
        });
    });
}

fn no_gpu(app: &Rc<RefCell<App>>, why: &str) {
    let text = format!(
        "This browser cannot show the scene: no WebGPU ({why}). Try a current Chrome, Edge or Safari, or Firefox with WebGPU enabled."
    );
    if let Some(window) = web_sys::window() {
        let _ = js_sys::Reflect::set(&window, &"brickcastFailed".into(), &"no-webgpu".into());
    }
    // Nothing can be shown: stop syncing a scene nobody will see (the message stays).
    let mut a = app.borrow_mut();
    a.gpu_error = Some(why.to_string());
    a.fail(text);
}

/// Runs [`App::frame`] on every animation frame from now on.
pub fn schedule_frame(app: &Rc<RefCell<App>>) {
    // The callback re-arms itself, so it holds a handle to its own slot.
    type Slot = Rc<RefCell<Option<Closure<dyn FnMut()>>>>;
    let slot: Slot = Rc::new(RefCell::new(None));
    let again = slot.clone();
    let app = app.clone();
    *slot.borrow_mut() = Some(Closure::new(move || {
        app.borrow_mut().frame();
        if let (Some(window), Some(cb)) = (web_sys::window(), again.borrow().as_ref()) {
            let _ = window.request_animation_frame(cb.as_ref().unchecked_ref());
        }
    }));
    if let (Some(window), Some(cb)) = (web_sys::window(), slot.borrow().as_ref()) {
        let _ = window.request_animation_frame(cb.as_ref().unchecked_ref());
    }
}

/// A traced frame as the test hook returns it.
pub fn frame_to_js(frame: &GpuFrame) -> Result<js_sys::Object, JsValue> {
    let out = js_sys::Object::new();
    let pixels: Vec<u8> = frame.pixels.iter().flatten().copied().collect();
    let hits: Vec<u32> = frame
        .hits
        .iter()
        .flat_map(|h| h.unwrap_or([u32::MAX; 3]))
        .collect();
    js_sys::Reflect::set(&out, &"width".into(), &frame.width.into())?;
    js_sys::Reflect::set(&out, &"height".into(), &frame.height.into())?;
    js_sys::Reflect::set(
        &out,
        &"pixels".into(),
        &js_sys::Uint8Array::from(pixels.as_slice()),
    )?;
    js_sys::Reflect::set(
        &out,
        &"hits".into(),
        &js_sys::Uint32Array::from(hits.as_slice()),
    )?;
    Ok(out)
}
