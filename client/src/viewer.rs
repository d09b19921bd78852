//! `brickcast view`: a window onto a live scene.
//!
//! Each frame: copy what the network thread applied since the last frame into the GPU buffers,
//! trace the frame in a compute pass, and draw the traced image onto the window with one
//! full-screen triangle (`shaders/blit.wgsl`). Edits are sent as ray ops built from the same
//! per-pixel ray the tracer used, so the server (which resolves them on its own copy) hits the
//! voxel the user pointed at.
//!
//! Controls: WASD to fly, Space/E up, Q/C down, mouse look while the middle button is held (or
//! after Tab, which captures the cursor and aims with a crosshair at the centre); the wheel sets
//! the speed. Left click removes, right click places, Ctrl+left paints; 1–8 pick a colour, `[` and
//! `]` set the brush radius (0 edits single voxels, more carves or fills spheres). B, X, N, G, T
//! and I pick the brush, box, line, fill, extrude and picker tools (box and line: drag from one
//! corner to the other; Alt+click takes a colour with any tool); P then six hex digits types any
//! RGB colour. Ctrl+Z undoes
//! your own latest edit, Ctrl+Shift+Z or Ctrl+Y redoes it. Where you look and point is shared
//! with everyone in the scene (at most 20 times a second).

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow};
use brickcast_client_core::paste::Pasting;
use brickcast_protocol::wire::{Cursor, EditOp, Role, Selection, View};
use brickcast_protocol::{Colour, Lighting, Projection};
use winit::application::ApplicationHandler;
use winit::event::{
    DeviceEvent, DeviceId, ElementState, MouseButton, MouseScrollDelta, WindowEvent,
};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, ModifiersState, PhysicalKey};
use winit::window::{CursorGrabMode, Window, WindowId};

use brickcast_client_core::camera::movement;
pub use brickcast_client_core::camera::{FirstView, FlyCamera};
use brickcast_client_core::shading::{NOTE_SECONDS, shading_key};
use brickcast_client_core::swatch::{SwatchAction, swatch_key};
use brickcast_client_core::tools::{
    Action, Button, Context as ToolContext, HexEntry, HexKey, Tool, Tools, selection_note,
    step_radius,
};
use brickcast_protocol::swatches::Swatches;

use crate::follow::Follow;
use crate::gpu::{BackendChoice, GpuContext, GpuScene, Tracer, new_instance};
use crate::link::websocket_url;
use crate::live::{Live, Status};
use crate::overlay::canvas::Canvas;
use crate::overlay::{OverlayInput, draw as draw_overlay};
use crate::present::{Presenter, acquire, sync_scene};

/// Options of `brickcast view` besides the address.
#[derive(Debug, Clone, clap::Args)]
pub struct ViewArgs {
    /// How exactly the GPU copy keeps colours: `exact`, `bounded` (every voxel within 12 of 255
    /// per channel; about half the colour memory of a textured scene) or `bounded:N`.
    #[arg(long, default_value_t = brickcast_protocol::blocks::Quality::default())]
    pub colours: brickcast_protocol::blocks::Quality,
    /// Trace at 1/SCALE of the window's resolution (faster on slow GPUs).
    #[arg(long, default_value_t = 1)]
    pub scale: u32,
    /// Initial window size, "WIDTHxHEIGHT".
    #[arg(long, default_value = "1280x720")]
    pub size: String,
    /// Only use Vulkan adapters.
    #[arg(long)]
    pub vulkan: bool,
    /// Close after this many frames have been drawn with the scene fully synced (for scripted
    /// runs and smoke tests).
    #[arg(long)]
    pub exit_after: Option<u32>,
    /// With --exit-after: save the last frame, as shown in the window, to this PNG.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// The name others see (default: the OS user name).
    #[arg(long)]
    pub name: Option<String>,
    /// Ride along with this user's camera as soon as they are present (F cycles, moving stops).
    #[arg(long)]
    pub follow: Option<String>,
    /// GPU memory for the scene: `unlimited` (every brick) or a size such as 256MiB. A scene
    /// that fits half of it is held whole; a larger world streams: full resolution near the
    /// camera, coarser levels further away, following the camera.
    #[arg(long, default_value_t = brickcast_client_core::budget::GpuBudget(Some(brickcast_client_core::budget::NATIVE_DEFAULT)))]
    pub gpu_budget: brickcast_client_core::budget::GpuBudget,
    #[command(flatten)]
    pub light: crate::LightArgs,
}

/// Everything that exists once the window does.
struct Gpu {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    ctx: GpuContext,
    tracer: Tracer,
    presenter: Presenter,
    scene: Option<GpuScene>,
}

struct App {
    args: ViewArgs,
    live: Live,
    backends: BackendChoice,
    instance: Option<wgpu::Instance>,
    gpu: Option<Gpu>,
    error: Option<anyhow::Error>,
    camera: Option<FlyCamera>,
    first_view: FirstView,
    /// Starts from `--no-ao` and friends; the O, L and H keys switch it (`SHADING_KEYS`).
    lighting: Lighting,
    /// What the last lighting key switched, and when: shown for `NOTE_SECONDS`.
    lighting_note: Option<(String, Instant)>,
    keys: HashSet<KeyCode>,
    modifiers: ModifiersState,
    cursor: (f64, f64),
    looking: bool,
    captured: bool,
    colour: Colour,
    tools: Tools,
    /// A colour being typed (P, then six hex digits).
    hex: HexEntry,
    radius: f32,
    last_frame: Instant,
    frames_since_title: u32,
    title_at: Instant,
    fps: f32,
    synced_frames: u32,
    /// Projection of the last traced frame, for turning clicks into rays.
    projection: Option<Projection>,
    /// The presence last sent, and when the next may go.
    presence_sent: Option<(Option<View>, Option<Cursor>, Option<Selection>)>,
    /// What the select tool selected (shared with everyone, drawn in white).
    selection: Option<Selection>,
    /// The clipboard as this window knows it, and how the next paste turns.
    pasting: Pasting,
    presence_at: Instant,
    /// What my pointer is on (traced on the local copy each frame).
    my_cursor: Option<Cursor>,
    follow: Follow,
    overlay: Canvas,
}

/// Opens the window and runs until it is closed.
/// Opens the window on the scene at `urls` (several: a cluster's nodes, tried in turn when a
/// connection is lost).
pub fn run(urls: &[String], token: Option<String>, args: ViewArgs) -> Result<()> {
    if args.scale == 0 || args.scale > 16 {
        return Err(anyhow!("--scale must be 1..=16"));
    }
    let (w, h) = parse_size(&args.size)?;
    let urls = urls
        .iter()
        .map(|u| websocket_url(u))
        .collect::<Result<Vec<_>, _>>()?;
    if urls.is_empty() {
        return Err(anyhow!("no scene address given"));
    }
    let event_loop =
        EventLoop::new().context("opening a window system connection (is DISPLAY set?)")?;
    let backends = if args.vulkan {
        BackendChoice::Vulkan
    } else {
        BackendChoice::Primary
    };
    let instance = new_instance(backends, Some(Box::new(event_loop.owned_display_handle())));
    let name = args
        .name
        .clone()
        .unwrap_or_else(crate::identity::default_name);
    brickcast_protocol::wire::check_display_name(&name).map_err(|e| anyhow!("--name: {e}"))?;
    let live = Live::start_any(
        urls,
        name,
        crate::identity::user_id(),
        token,
        args.colours,
        args.gpu_budget.0,
    )
    .context("starting the network thread")?;
    let follow = Follow::by_name(args.follow.clone());
    let lighting = args.light.lighting()?;
    let mut app = App {
        args: ViewArgs {
            size: format!("{w}x{h}"),
            ..args
        },
        live,
        backends,
        instance: Some(instance),
        gpu: None,
        error: None,
        camera: None,
        first_view: FirstView::default(),
        lighting,
        lighting_note: None,
        keys: HashSet::new(),
        modifiers: ModifiersState::empty(),
        cursor: (0.0, 0.0),
        looking: false,
        captured: false,
        colour: Swatches::default().get(0),
        tools: Tools::default(),
        hex: HexEntry::default(),
        radius: 0.0,
        last_frame: Instant::now(),
        frames_since_title: 0,
        title_at: Instant::now(),
        fps: 0.0,
        synced_frames: 0,
        projection: None,
        presence_sent: None,
        selection: None,
        pasting: Pasting::default(),
        presence_at: Instant::now(),
        my_cursor: None,
        follow,
        overlay: Canvas::new(1, 1),
    };
    event_loop
        .run_app(&mut app)
        .context("running the event loop")?;
    match app.error.take() {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// A window or image size, `WIDTHxHEIGHT` (1 to 16384 a side).
pub fn parse_size(text: &str) -> Result<(u32, u32)> {
    let (w, h) = text
        .split_once('x')
        .ok_or_else(|| anyhow!("--size must look like 1280x720, not {text:?}"))?;
    let w: u32 = w.trim().parse().context("window width")?;
    let h: u32 = h.trim().parse().context("window height")?;
    if !(1..=16384).contains(&w) || !(1..=16384).contains(&h) {
        return Err(anyhow!("window size {w}x{h} is out of range"));
    }
    Ok((w, h))
}

impl App {
    /// What the last lighting key switched, while it is recent.
    fn lighting_note(&self) -> Option<String> {
        self.lighting_note
            .as_ref()
            .filter(|(_, at)| at.elapsed().as_secs_f64() < NOTE_SECONDS)
            .map(|(note, _)| note.clone())
    }

    fn fail(&mut self, event_loop: &ActiveEventLoop, error: anyhow::Error) {
        tracing::error!("{error:#}");
        self.error = Some(error);
        event_loop.exit();
    }

    fn create(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let (w, h) = parse_size(&self.args.size)?;
        let window = Arc::new(
            event_loop
                .create_window(
                    Window::default_attributes()
                        .with_title("brickcast")
                        .with_inner_size(winit::dpi::PhysicalSize::new(w, h)),
                )
                .context("creating the window")?,
        );
        let instance = match self.instance.take() {
            Some(i) => i,
            None => new_instance(
                self.backends,
                Some(Box::new(event_loop.owned_display_handle())),
            ),
        };
        let surface = instance
            .create_surface(window.clone())
            .context("creating a surface for the window")?;
        let ctx = pollster::block_on(GpuContext::with_instance(instance, Some(&surface)))?;
        let size = window.inner_size();
        let mut config = surface
            .get_default_config(&ctx.adapter, size.width.max(1), size.height.max(1))
            .ok_or_else(|| anyhow!("{} cannot present to this window", ctx.adapter_name))?;
        let caps = surface.get_capabilities(&ctx.adapter);
        // The traced bytes are already display values: present them untouched, not through an
        // sRGB conversion.
        if let Some(format) = caps.formats.iter().find(|f| !f.is_srgb()) {
            config.format = *format;
        }
        if caps.usages.contains(wgpu::TextureUsages::COPY_SRC) {
            config.usage |= wgpu::TextureUsages::COPY_SRC;
        }
        surface.configure(&ctx.device, &config);
        let tracer = Tracer::new(&ctx)?;
        tracing::info!("tracing on {}", ctx.adapter_name);
        let presenter = Presenter::new(&ctx.device, config.format);
        self.gpu = Some(Gpu {
            window,
            surface,
            config,
            ctx,
            tracer,
            presenter,
            scene: None,
        });
        Ok(())
    }

    /// Movement keys held now, as (forward, right, up); none while Ctrl is held (Ctrl+C
    /// copies, it does not fly down).
    fn movement(&self) -> [f32; 3] {
        if self.modifiers.control_key() {
            return [0.0; 3];
        }
        movement(|name| self.keys.iter().any(|k| format!("{k:?}") == name))
    }

    fn frame(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let now = Instant::now();
        let dt = now.duration_since(self.last_frame).as_secs_f32().min(0.25);
        self.last_frame = now;
        let movement = self.movement();
        let lighting_note = self.lighting_note();
        let Some(gpu) = &mut self.gpu else {
            return Ok(());
        };
        // Bring the GPU copy up to date with what the network thread applied.
        let (status, status_line, role, synced, rejected, others, undo) = {
            let mut live = self.live.lock();
            let status_line = live.status_text();
            let status = live.status.clone();
            let role = live.role;
            let rejected = live.last_rejection.clone();
            let others = live.roster.others.len();
            let undo = live.last_undo.clone();
            let synced = match &mut live.replica {
                Some(replica) => {
                    self.first_view
                        .place(&mut self.camera, &replica.map, replica.synced);
                    sync_scene(&gpu.ctx, &mut gpu.scene, replica)?;
                    replica.synced
                }
                None => false,
            };
            (status, status_line, role, synced, rejected, others, undo)
        };
        if let Status::Failed(reason) = &status {
            return Err(anyhow!("{reason}"));
        }
        if movement != [0.0; 3] {
            self.follow.stop();
        }
        let followed = {
            let live = self.live.lock();
            self.follow.view(&live.roster)
        };
        if let Some(camera) = &mut self.camera {
            match followed {
                Some(view) => camera.look_along(view),
                None => camera.fly(movement, dt),
            }
        }
        self.share_presence();
        let Some(gpu) = &mut self.gpu else {
            return Ok(());
        };
        let Some(frame) = acquire(&gpu.ctx, &gpu.surface, &gpu.config) else {
            return Ok(());
        };
        let target = frame
            .texture
            .create_view(&wgpu::TextureViewDescriptor::default());
        let mut encoder = gpu
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame"),
            });
        let scale = self.args.scale;
        let (tw, th) = (
            gpu.config.width.div_ceil(scale).max(1),
            gpu.config.height.div_ceil(scale).max(1),
        );
        let traced = match (&gpu.scene, &self.camera) {
            (Some(scene), Some(camera)) => match camera.camera().project(tw, th) {
                Some(projection) => {
                    gpu.tracer.encode(
                        &gpu.ctx,
                        &mut encoder,
                        scene,
                        &projection,
                        &self.lighting,
                    )?;
                    self.projection = Some(projection);
                    true
                }
                None => false,
            },
            _ => false,
        };
        // The overlay, drawn at the window's resolution, also before there is a scene: then
        // its notes say what the viewer waits for (connecting, retrying, and why).
        if let Some(projection) =
            overlay_projection(self.camera.as_ref(), gpu.config.width, gpu.config.height)
        {
            let live = self.live.lock();
            let mut notes = vec![status_line.clone()];
            if let Some(why) = &rejected {
                notes.push(format!("last edit rejected: {why}"));
            }
            if let Some(undo) = &undo {
                notes.push(undo.clone());
            }
            if let Some(note) = &lighting_note {
                notes.push(note.clone());
            }
            notes.push("Ctrl+Z undo, Ctrl+Y redo, F follow".into());
            draw_overlay(
                &mut self.overlay,
                &OverlayInput {
                    projection,
                    roster: &live.roster,
                    cursor: self.my_cursor.map(|c| Cursor {
                        radius: self.radius,
                        ..c
                    }),
                    colour: self.colour,
                    captured: self.captured,
                    notes,
                    following: self.follow.target,
                    swatches: Some(live.swatches()),
                    selection: self.selection,
                },
            );
            drop(live);
            gpu.presenter.upload_overlay(&gpu.ctx, &self.overlay);
        }
        let image = if traced {
            gpu.tracer.image_view()
        } else {
            None
        };
        gpu.presenter.draw(&gpu.ctx, &mut encoder, &target, image);
        if synced && traced {
            self.synced_frames += 1;
        }
        let last = self
            .args
            .exit_after
            .is_some_and(|n| self.synced_frames >= n);
        let shot = match (&self.args.screenshot, last) {
            (Some(path), true) => Some((
                path.clone(),
                screenshot_buffer(&gpu.ctx, &mut encoder, &frame.texture, &gpu.config),
            )),
            _ => None,
        };
        gpu.ctx.queue.submit([encoder.finish()]);
        gpu.window.pre_present_notify();
        gpu.ctx.queue.present(frame);
        if let Some((path, readback)) = shot {
            save_screenshot(&gpu.ctx, &readback, &gpu.config, &path)?;
        }
        if last {
            event_loop.exit();
        }

        self.frames_since_title += 1;
        let since = now.duration_since(self.title_at);
        if since >= Duration::from_millis(500) {
            self.fps = self.frames_since_title as f32 / since.as_secs_f32();
            self.frames_since_title = 0;
            self.title_at = now;
            let state = status_line;
            let role = match role {
                Some(Role::Editor) => "editor",
                Some(Role::Viewer) => "viewer (read-only)",
                None => "",
            };
            let [r, g, b] = self.colour.to_rgb8();
            let colour = match self.hex.shown() {
                Some(typed) => format!("colour {typed} (typing; Esc gives up)"),
                None => format!(
                    "colour #{r:02x}{g:02x}{b:02x} (1-0 swatch, Shift sets it; P #hex, Alt+click)"
                ),
            };
            let mut title = format!(
                "brickcast — {state} — {:.1} fps — {role} — {} (B X N G T I V) — {colour} — brush {} ([ ])",
                self.fps,
                self.tools.tool.name(),
                self.radius
            );
            if others > 0 {
                title.push_str(&format!(" — {others} others here"));
            }
            if let Some(why) = rejected {
                title.push_str(&format!(" — last edit rejected: {why}"));
            }
            if let Some(undo) = undo {
                title.push_str(&format!(" — {undo}"));
            }
            if let Some(note) = &lighting_note {
                title.push_str(&format!(" — {note}"));
            }
            gpu.window.set_title(&title);
        }
        Ok(())
    }

    /// Sends a copy's or a paste's op and says what it did, or says why there was none.
    fn send_paste_op(&mut self, made: Result<(EditOp, String), &'static str>) {
        let note = match made {
            Ok((op, note)) => {
                self.live.edit(vec![op]);
                note
            }
            Err(why) => why.to_string(),
        };
        self.lighting_note = Some((note, Instant::now()));
    }

    /// A press (`pressed`) or release of `button` at the pointer: what the tool in use does.
    fn click(&mut self, button: MouseButton, pressed: bool) {
        let Some(projection) = self.projection else {
            return;
        };
        let button = match button {
            MouseButton::Left => Button::Primary,
            MouseButton::Right => Button::Secondary,
            _ => return,
        };
        let pick = self.modifiers.alt_key();
        let live = self.live.lock();
        // A viewer may take colours and select (pointing a region out to others), not edit.
        let reads = pick || matches!(self.tools.tool, Tool::Picker | Tool::Select);
        if live.role != Some(Role::Editor) && !reads {
            drop(live);
            if pressed {
                tracing::info!("this connection may only watch; edits are ignored");
            }
            return;
        }
        let ray = self.pointer_ray(&projection);
        let cx = ToolContext {
            radius: self.radius,
            paint: self.modifiers.control_key(),
            pick,
            colour: self.colour,
            limits: &live.limits,
            map: live.replica.as_ref().map(|r| &r.map),
        };
        let action = if pressed {
            self.tools.press(button, &ray, &cx)
        } else {
            self.tools.release(button, &ray, &cx)
        };
        drop(live);
        match action {
            Action::Edit(op) => self.live.edit(vec![op]),
            Action::Picked(colour) => {
                self.colour = colour;
                let [r, g, b] = colour.to_rgb8();
                self.lighting_note = Some((
                    format!("took colour #{r:02x}{g:02x}{b:02x}"),
                    Instant::now(),
                ));
            }
            Action::Selected(selection) => {
                self.selection = selection;
                self.lighting_note = Some((selection_note(selection), Instant::now()));
            }
            Action::Nothing(why) if !why.is_empty() => {
                self.lighting_note = Some((why.to_string(), Instant::now()));
            }
            Action::Started | Action::Nothing(_) => {}
        }
    }

    /// The ray under the pointer (the crosshair at the centre while the cursor is captured).
    fn pointer_ray(&self, projection: &Projection) -> brickcast_protocol::Ray {
        let scale = f64::from(self.args.scale);
        let (x, y) = if self.captured {
            (projection.width / 2, projection.height / 2)
        } else {
            (
                ((self.cursor.0 / scale) as u32).min(projection.width - 1),
                ((self.cursor.1 / scale) as u32).min(projection.height - 1),
            )
        };
        projection.ray(x, y)
    }

    /// Shares where we look and what the pointer is on, when it changed and the server's rate
    /// allows. The cursor voxel is traced on the local copy, which is what the user sees.
    fn share_presence(&mut self) {
        let now = Instant::now();
        let Some(camera) = self.camera else { return };
        let view = Some(View {
            eye: camera.eye,
            forward: camera.forward(),
        });
        let (hz, cursor) = {
            let live = self.live.lock();
            let hz = live.presence_hz.max(1);
            let cursor = match (&live.replica, &self.projection) {
                (Some(replica), Some(projection)) => {
                    brickcast_protocol::trace(&replica.map, &self.pointer_ray(projection)).map(
                        |hit| Cursor {
                            voxel: hit.voxel,
                            radius: self.radius,
                        },
                    )
                }
                _ => None,
            };
            (hz, cursor)
        };
        self.my_cursor = cursor;
        if now < self.presence_at {
            return;
        }
        let now_sharing = (view, cursor, self.selection);
        if self.presence_sent != Some(now_sharing) {
            self.live.presence(view, cursor, self.selection);
            self.presence_sent = Some(now_sharing);
            self.presence_at = now + Duration::from_secs_f64(1.0 / f64::from(hz));
        }
    }

    fn set_captured(&mut self, on: bool) {
        let Some(gpu) = &self.gpu else { return };
        self.captured = on;
        if on {
            let grabbed = gpu
                .window
                .set_cursor_grab(CursorGrabMode::Locked)
                .or_else(|_| gpu.window.set_cursor_grab(CursorGrabMode::Confined));
            if grabbed.is_err() {
                tracing::warn!("this window system cannot capture the cursor");
            }
        } else {
            let _ = gpu.window.set_cursor_grab(CursorGrabMode::None);
        }
        gpu.window.set_cursor_visible(!on);
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gpu.is_none()
            && let Err(e) = self.create(event_loop)
        {
            self.fail(event_loop, e);
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let Some(gpu) = &mut self.gpu
                    && size.width > 0
                    && size.height > 0
                {
                    gpu.config.width = size.width;
                    gpu.config.height = size.height;
                    gpu.surface.configure(&gpu.ctx.device, &gpu.config);
                }
            }
            WindowEvent::ModifiersChanged(m) => self.modifiers = m.state(),
            // A drag whose release goes to another window is forgotten.
            WindowEvent::Focused(false) => self.tools.cancel(),
            WindowEvent::KeyboardInput { event, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else {
                    return;
                };
                if event.state == ElementState::Released {
                    self.keys.remove(&code);
                    return;
                }
                // P, then six hex digits: a colour (the digits are not flying keys meanwhile).
                if !event.repeat {
                    match self.hex.key(&format!("{code:?}")) {
                        HexKey::Ignored => {}
                        HexKey::Typing => return,
                        HexKey::Done(colour) => {
                            self.colour = colour;
                            let [r, g, b] = colour.to_rgb8();
                            self.lighting_note =
                                Some((format!("colour #{r:02x}{g:02x}{b:02x}"), Instant::now()));
                            return;
                        }
                        HexKey::Cancelled => {
                            self.lighting_note = Some(("colour unchanged".into(), Instant::now()));
                            return;
                        }
                    }
                } else if self.hex.typing() {
                    return;
                }
                self.keys.insert(code);
                if event.repeat {
                    return;
                }
                let ctrl = self.modifiers.control_key();
                let shift = self.modifiers.shift_key();
                let name = format!("{code:?}");
                if let Some(note) = shading_key(&mut self.lighting, &name) {
                    self.lighting_note = Some((note, Instant::now()));
                    return;
                }
                if !ctrl && let Some(tool) = Tool::from_key(&name) {
                    self.tools.pick_tool(tool);
                    self.lighting_note = Some((format!("tool: {}", tool.name()), Instant::now()));
                    return;
                }
                match code {
                    KeyCode::KeyC if ctrl => {
                        let copied = self.pasting.copy(self.selection);
                        self.send_paste_op(copied);
                    }
                    KeyCode::KeyX if ctrl => {
                        let note = match self.pasting.cut(self.selection) {
                            Ok((ops, note)) => {
                                self.live.edit(ops);
                                note
                            }
                            Err(why) => why.to_string(),
                        };
                        self.lighting_note = Some((note, Instant::now()));
                    }
                    KeyCode::KeyV if ctrl => {
                        let pasted = match self.projection {
                            Some(p) => {
                                let ray = self.pointer_ray(&p);
                                let live = self.live.lock();
                                let map = live.replica.as_ref().map(|r| &r.map);
                                self.pasting.paste(map, &ray)
                            }
                            None => Err("the scene is not here yet"),
                        };
                        self.send_paste_op(pasted);
                    }
                    KeyCode::KeyR => {
                        self.lighting_note = Some((self.pasting.turn(), Instant::now()));
                    }
                    KeyCode::KeyM => {
                        self.lighting_note = Some((self.pasting.mirror(), Instant::now()));
                    }
                    KeyCode::KeyZ if ctrl => self.live.undo(shift),
                    KeyCode::KeyY if ctrl => self.live.undo(true),
                    KeyCode::KeyF => {
                        let roster = self.live.lock().roster.clone();
                        self.follow.cycle(&roster);
                    }
                    KeyCode::Escape if self.captured => self.set_captured(false),
                    KeyCode::Escape => event_loop.exit(),
                    KeyCode::Tab => self.set_captured(!self.captured),
                    KeyCode::BracketLeft | KeyCode::BracketRight => {
                        let max = self.live.lock().max_radius;
                        self.radius = step_radius(self.radius, code == KeyCode::BracketRight, max);
                    }
                    _ => {
                        let swatches = self.live.lock().swatches();
                        if let Some(action) = swatch_key(&name, shift, &swatches, self.colour) {
                            match action {
                                SwatchAction::Take { colour, .. } => self.colour = colour,
                                SwatchAction::Set { op, .. } => self.live.edit(vec![op]),
                            }
                            self.lighting_note = Some((action.note(), Instant::now()));
                        }
                    }
                }
            }
            WindowEvent::CursorMoved { position, .. } => self.cursor = (position.x, position.y),
            WindowEvent::MouseInput { state, button, .. } => match (button, state) {
                (MouseButton::Middle, s) => self.looking = s == ElementState::Pressed,
                (b, s) => self.click(b, s == ElementState::Pressed),
            },
            WindowEvent::MouseWheel { delta, .. } => {
                let steps = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y,
                    MouseScrollDelta::PixelDelta(p) => (p.y / 40.0) as f32,
                };
                if let Some(camera) = &mut self.camera {
                    camera.speed = (camera.speed * 1.25f32.powf(steps)).clamp(1.0, 20_000.0);
                }
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.frame(event_loop) {
                    self.fail(event_loop, e);
                }
            }
            _ => {}
        }
    }

    fn device_event(&mut self, _event_loop: &ActiveEventLoop, _id: DeviceId, event: DeviceEvent) {
        if let DeviceEvent::MouseMotion { delta } = event
            && (self.looking || self.captured)
            && let Some(camera) = &mut self.camera
        {
            self.follow.stop();
            camera.look(delta.0 as f32, delta.1 as f32);
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        // Render continuously: the scene changes under us and the camera flies. A minimised
        // (or zero-sized) window draws nothing; it looks again ten times a second, and catches
        // up on the scene's changes in one upload when it is back.
        if let Some(gpu) = &self.gpu {
            let size = gpu.window.inner_size();
            let hidden =
                size.width == 0 || size.height == 0 || gpu.window.is_minimized() == Some(true);
            if hidden {
                event_loop.set_control_flow(ControlFlow::WaitUntil(
                    Instant::now() + Duration::from_millis(100),
                ));
            } else if self.camera.is_none() {
                // Nothing to trace yet (connecting, or retrying a server that is not there):
                // the notes change a few times a second at most, so 20 frames a second do.
                let next = self.last_frame + IDLE_FRAME;
                if Instant::now() >= next {
                    gpu.window.request_redraw();
                }
                event_loop.set_control_flow(ControlFlow::WaitUntil(next.max(Instant::now())));
            } else {
                event_loop.set_control_flow(ControlFlow::Wait);
                gpu.window.request_redraw();
            }
        }
    }
}

/// Time between frames while there is no scene to trace.
const IDLE_FRAME: Duration = Duration::from_millis(50);

/// The projection the overlay places markers with: the camera's, or before there is one (no
/// scene yet) a fixed one, so the notes are drawn all the same.
fn overlay_projection(camera: Option<&FlyCamera>, width: u32, height: u32) -> Option<Projection> {
    let camera = camera.map_or(
        brickcast_protocol::render::Camera {
            eye: [0.0; 3],
            target: [0.0, 0.0, 1.0],
            fov_y: 60.0,
        },
        FlyCamera::camera,
    );
    camera.project(width, height)
}

/// Where a screenshot is copied before presenting, and its row pitch.
struct ScreenshotReadback {
    buffer: wgpu::Buffer,
    row: u32,
}

/// Copies the window's image (before it is presented) into a buffer, so the smoke test checks
/// what reached the window and not just what the tracer produced.
fn screenshot_buffer(
    ctx: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    config: &wgpu::SurfaceConfiguration,
) -> Option<ScreenshotReadback> {
    if !config.usage.contains(wgpu::TextureUsages::COPY_SRC) {
        tracing::warn!("this surface cannot be read back; no screenshot");
        return None;
    }
    let (buffer, row) = crate::gpu::tracer::copy_out(ctx, encoder, texture, 4);
    Some(ScreenshotReadback { buffer, row })
}

fn save_screenshot(
    ctx: &GpuContext,
    readback: &Option<ScreenshotReadback>,
    config: &wgpu::SurfaceConfiguration,
    path: &std::path::Path,
) -> Result<()> {
    let Some(readback) = readback else {
        return Err(anyhow!(
            "the surface of {} cannot be read back for --screenshot",
            ctx.adapter_name
        ));
    };
    let bytes = pollster::block_on(crate::gpu::tracer::map_read(ctx, &readback.buffer))?;
    let bgra = matches!(
        config.format,
        wgpu::TextureFormat::Bgra8Unorm | wgpu::TextureFormat::Bgra8UnormSrgb
    );
    let mut pixels = Vec::with_capacity((config.width * config.height) as usize);
    for y in 0..config.height as usize {
        let line = &bytes[y * readback.row as usize..][..config.width as usize * 4];
        pixels.extend(line.chunks_exact(4).map(|p| {
            if bgra {
                [p[2], p[1], p[0], 255]
            } else {
                [p[0], p[1], p[2], 255]
            }
        }));
    }
    crate::headless::write_png(path, config.width, config.height, &pixels)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Before there is a scene (connecting, or retrying a server that is not there) the window
    /// still shows the notes that say so; it was one flat colour.
    #[test]
    fn the_overlay_says_what_the_viewer_waits_for_before_there_is_a_scene() {
        let (w, h) = (320, 200);
        let projection = overlay_projection(None, w, h).expect("a projection without a camera");
        let mut canvas = Canvas::new(w, h);
        let roster = Default::default();
        draw_overlay(
            &mut canvas,
            &OverlayInput {
                projection,
                roster: &roster,
                cursor: None,
                colour: Colour::WHITE,
                captured: false,
                notes: vec!["cannot reach the server; retrying in 2 s".into()],
                following: None,
                swatches: None,
                selection: None,
            },
        );
        let drawn = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .filter(|&(x, y)| canvas.get(x, y)[3] > 0)
            .count();
        assert!(drawn > 100, "{drawn} pixels of notes drawn");
    }
}
