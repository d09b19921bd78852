//! The brickcast browser viewer: `http://HOST:7878/scenes/NAME` in any WebGPU browser.
//!
//! This crate is only a shell. The wire format, the replica, the GPU copy of the scene, the
//! tracer (`shaders/trace.wgsl`), the overlay, the camera and the editing tools all come from
//! `brickcast-protocol` and `brickcast-client-core`, the same code the native `brickcast view`
//! runs. What is here is what only a browser has: a canvas, a `WebSocket`, DOM events, the
//! animation-frame clock, and a handle the page (and the browser tests) can call.
//!
//! The server's build script compiles this crate for `wasm32-unknown-unknown`, generates the
//! JavaScript bindings and embeds both in the server binary; on other targets it is empty.
#![cfg(target_arch = "wasm32")]

mod app;
mod input;
mod net;
mod page;

use std::cell::RefCell;
use std::rc::Rc;

use wasm_bindgen::prelude::*;

use app::App;

/// The running viewer, as the page holds it (`window.brickcast` in the page, for tests).
#[wasm_bindgen]
pub struct Viewer {
    app: Rc<RefCell<App>>,
}

/// Starts the viewer on the page's canvas for scene `scene`, with `token` (from the URL
/// fragment or the token form), display name `name` and colour quality `colours` (`?colours=`:
/// `exact`, `bounded` or `bounded:N`; bounded when absent) and GPU budget `budget` (`?budget=`:
/// `unlimited` or a size such as `256MiB`; [`BROWSER_DEFAULT`](brickcast_client_core::budget::BROWSER_DEFAULT)
/// when absent: a scene that fits half of it is held whole, a larger world streams a working
/// set around the camera). A `colours` or `budget` it cannot read is an
/// error that says what it takes.
#[wasm_bindgen]
pub fn start(
    scene: String,
    token: Option<String>,
    name: Option<String>,
    colours: Option<String>,
    budget: Option<String>,
) -> Result<Viewer, JsValue> {
    let budget = match budget.filter(|b| !b.is_empty()) {
        Some(b) => {
            brickcast_client_core::budget::parse_budget(&b).map_err(|e| JsValue::from_str(&e))?
        }
        None => Some(brickcast_client_core::budget::BROWSER_DEFAULT),
    };
    let colours = match colours.filter(|c| !c.is_empty()) {
        Some(c) => c.parse().map_err(|e: String| JsValue::from_str(&e))?,
        None => brickcast_protocol::blocks::Quality::default(),
    };
    let app = App::new(scene, token, name, colours)?;
    app.borrow_mut().session.budget = budget;
    input::listen(&app)?;
    net::connect(&app);
    app::start_gpu(&app);
    app::schedule_frame(&app);
    Ok(Viewer { app })
}

#[wasm_bindgen]
impl Viewer {
    /// What the page shows, as JSON: status, sync progress, frame counts, timings, GPU.
    pub fn state(&self) -> String {
        self.app.borrow().state_json()
    }

    /// Presses a key by its `KeyboardEvent.code` name, with Ctrl held or not (the page's
    /// toolbar, for touch screens).
    pub fn press(&self, code: &str, ctrl: bool) {
        let mut app = self.app.borrow_mut();
        app.key_down(code, ctrl, false);
        app.key_up(code);
        app.ctrl = false;
    }

    /// Draws with colour `hex` (`#rrggbb`, the page's colour chooser) from now on.
    pub fn set_colour(&self, hex: &str) -> Result<(), JsValue> {
        let colour = brickcast_protocol::Colour::parse_hex(hex)
            .ok_or_else(|| JsValue::from_str(&format!("{hex:?} is not a colour (#rrggbb)")))?;
        self.app.borrow_mut().set_colour(colour);
        Ok(())
    }

    /// Swatch `index` of the scene's palette clicked: draw with it, or with `set` (Shift
    /// held) make it the colour drawn with now, for everyone in the scene.
    pub fn swatch(&self, index: usize, set: bool) {
        self.app.borrow_mut().click_swatch(index, set);
    }

    /// The tool in use (`brush`, `box`, `line`, `fill`, `extrude`, `picker`).
    pub fn tool(&self) -> String {
        self.app.borrow().tools.tool.name().to_string()
    }

    /// Restores the selection (or the whole scene) to how it was at sequence `to`.
    pub fn restore(&self, to: f64) {
        self.app.borrow_mut().restore(to as u64);
    }

    /// Traces at 1/`divisor` of the canvas's resolution from now on; 0 lets it adapt again.
    pub fn set_scale(&self, divisor: u32) {
        self.app.borrow_mut().scale.pin(divisor);
    }

    /// Puts the camera at `eye` looking at `target` (voxel coordinates).
    pub fn set_camera(&self, eye: Vec<f32>, target: Vec<f32>) -> Result<(), JsValue> {
        self.app.borrow_mut().set_camera(&eye, &target)
    }

    /// Traces the scene as it is now at exactly `width`×`height` from `eye` towards `target`,
    /// and resolves to `{width, height, pixels: Uint8Array (RGBA), hits: Uint32Array (x, y, z
    /// per pixel, 0xFFFFFFFF for a miss)}`: the test hook that compares the GPU frame with the
    /// CPU renderer.
    pub fn trace_exact(
        &self,
        width: u32,
        height: u32,
        eye: Vec<f32>,
        target: Vec<f32>,
        fov_y: f32,
    ) -> js_sys::Promise {
        let app = self.app.clone();
        wasm_bindgen_futures::future_to_promise(async move {
            let pending = app
                .borrow_mut()
                .start_exact_trace(width, height, &eye, &target, fov_y)?;
            let (ctx, pending) = pending;
            let frame = pending
                .finish(&ctx)
                .await
                .map_err(|e| JsValue::from_str(&e.to_string()))?;
            Ok(app::frame_to_js(&frame)?.into())
        })
    }

    /// Bytes of linear memory the wasm module holds (the page's own heap).
    pub fn wasm_memory_bytes(&self) -> f64 {
        let memory: js_sys::WebAssembly::Memory = wasm_bindgen::memory().unchecked_into();
        memory
            .buffer()
            .unchecked_into::<js_sys::ArrayBuffer>()
            .byte_length() as f64
    }
}
