//! Keyboard, mouse, pointer lock, wheel and touch, turned into the shared camera and tools.
//!
//! The native viewer's keys (named by `KeyboardEvent.code`, see `camera::MOVE_KEYS`). The mouse
//! differs where a page must: a drag looks around (a click that did not move edits: left
//! removes, right places, Ctrl+left paints; with the box and line tools a drag draws from one
//! corner to the other instead; Alt+click takes a colour), a double click locks the pointer for mouse-look with
//! a crosshair (Escape releases it, as browsers require). Touch: one finger drags to look and
//! taps to edit, two fingers drag to fly forward and back.

use std::cell::RefCell;
use std::rc::Rc;

use brickcast_client_core::tools::Button;
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{EventTarget, KeyboardEvent, MouseEvent, TouchEvent, WheelEvent};

use crate::app::App;
use crate::page;

/// Pixels a pointer may move between press and release and still count as a click.
const CLICK_SLOP: f64 = 4.0;

/// Mouse or touch state between events.
#[derive(Default)]
struct Drag {
    /// Where the press happened, and which button.
    down: Option<(f64, f64, i16)>,
    moved: bool,
    last: (f64, f64),
    /// Two-finger gesture: the fingers' mean y last time.
    pinch_y: Option<f64>,
}

fn on<E: wasm_bindgen::convert::FromWasmAbi + 'static>(
    target: &EventTarget,
    kind: &str,
    f: impl FnMut(E) + 'static,
) -> Result<(), JsValue> {
    let cb = Closure::<dyn FnMut(E)>::new(f);
    target.add_event_listener_with_callback(kind, cb.as_ref().unchecked_ref())?;
    // Listeners live as long as the page.
    cb.forget();
    Ok(())
}

pub fn listen(app: &Rc<RefCell<App>>) -> Result<(), JsValue> {
    let window: EventTarget = web_sys::window().ok_or("no window")?.into();
    let canvas: EventTarget = app.borrow().canvas().clone().into();
    let drag = Rc::new(RefCell::new(Drag::default()));

    {
        let app = app.clone();
        on(&window, "keydown", move |e: KeyboardEvent| {
            // Typing into the token form is not flying.
            if e.target()
                .and_then(|t| t.dyn_into::<web_sys::HtmlInputElement>().ok())
                .is_some()
            {
                return;
            }
            if app
                .borrow_mut()
                .key_down(&e.code(), e.ctrl_key() || e.meta_key(), e.shift_key())
            {
                e.prevent_default();
            }
        })?;
    }
    {
        let app = app.clone();
        on(&window, "keyup", move |e: KeyboardEvent| {
            app.borrow_mut().key_up(&e.code());
        })?;
    }
    {
        let app = app.clone();
        on(&window, "blur", move |_: web_sys::Event| {
            let mut a = app.borrow_mut();
            a.release_keys();
            a.tools.cancel();
        })?;
    }
    {
        let app = app.clone();
        let drag = drag.clone();
        on(&canvas, "mousedown", move |e: MouseEvent| {
            let (x, y) = (f64::from(e.offset_x()), f64::from(e.offset_y()));
            let mut a = app.borrow_mut();
            a.pointer = (x, y);
            a.ctrl = e.ctrl_key() || e.meta_key();
            a.alt = e.alt_key();
            *drag.borrow_mut() = Drag {
                down: Some((x, y, e.button())),
                last: (x, y),
                ..Drag::default()
            };
            // Box and line: the press is a corner, the drag draws rather than looks.
            if a.tools.tool.drags()
                && !a.alt
                && let Some(button) = button_of(e.button())
            {
                a.click(button, true);
            }
            e.prevent_default();
        })?;
    }
    {
        let app = app.clone();
        let drag = drag.clone();
        on(&canvas, "mousemove", move |e: MouseEvent| {
            let mut a = app.borrow_mut();
            let (x, y) = (f64::from(e.offset_x()), f64::from(e.offset_y()));
            a.pointer = (x, y);
            if a.locked {
                a.look(f64::from(e.movement_x()), f64::from(e.movement_y()));
                return;
            }
            let mut d = drag.borrow_mut();
            if let Some((x0, y0, _)) = d.down {
                if (x - x0).hypot(y - y0) > CLICK_SLOP {
                    d.moved = true;
                }
                if d.moved && !a.tools.dragging() {
                    a.look(x - d.last.0, y - d.last.1);
                }
            }
            d.last = (x, y);
        })?;
    }
    {
        let app = app.clone();
        let drag = drag.clone();
        on(&canvas, "mouseup", move |e: MouseEvent| {
            let mut a = app.borrow_mut();
            a.ctrl = e.ctrl_key() || e.meta_key();
            a.alt = e.alt_key();
            let d = std::mem::take(&mut *drag.borrow_mut());
            let locked = a.locked;
            let Some(button) = d.down.and_then(|(_, _, b)| button_of(b)) else {
                return;
            };
            if a.tools.dragging() {
                // The other corner of a box or line.
                a.click(button, false);
            } else if !d.moved || locked {
                a.click(button, true);
                a.click(button, false);
            }
        })?;
    }
    {
        // A drag that leaves the canvas ends there: its release would not be heard.
        let app = app.clone();
        let drag = drag.clone();
        on(&canvas, "mouseleave", move |_: MouseEvent| {
            app.borrow_mut().tools.cancel();
            *drag.borrow_mut() = Drag::default();
        })?;
    }
    on(&canvas, "contextmenu", move |e: MouseEvent| {
        e.prevent_default()
    })?;
    {
        let canvas_el = app.borrow().canvas().clone();
        on(&canvas, "dblclick", move |_: MouseEvent| {
            canvas_el.request_pointer_lock();
        })?;
    }
    {
        let app = app.clone();
        let document: EventTarget = page::document().ok_or("no document")?.into();
        on(&document, "pointerlockchange", move |_: web_sys::Event| {
            let locked = page::document()
                .and_then(|d| d.pointer_lock_element())
                .is_some();
            app.borrow_mut().locked = locked;
        })?;
    }
    {
        let app = app.clone();
        on(&canvas, "wheel", move |e: WheelEvent| {
            app.borrow_mut().wheel(e.delta_y());
            e.prevent_default();
        })?;
    }
    touch(app, &canvas, drag)
}

/// The tool button a mouse button is (left, right).
fn button_of(button: i16) -> Option<Button> {
    match button {
        0 => Some(Button::Primary),
        2 => Some(Button::Secondary),
        _ => None,
    }
}

fn touch(
    app: &Rc<RefCell<App>>,
    canvas: &EventTarget,
    drag: Rc<RefCell<Drag>>,
) -> Result<(), JsValue> {
    let point = |e: &TouchEvent, i: u32| -> Option<(f64, f64)> {
        let t = e.touches().get(i)?;
        let rect = e
            .target()?
            .dyn_into::<web_sys::Element>()
            .ok()?
            .get_bounding_client_rect();
        Some((
            f64::from(t.client_x()) - rect.left(),
            f64::from(t.client_y()) - rect.top(),
        ))
    };
    {
        let app = app.clone();
        let drag = drag.clone();
        on(canvas, "touchstart", move |e: TouchEvent| {
            e.prevent_default();
            let mut d = drag.borrow_mut();
            match e.touches().length() {
                1 => {
                    if let Some(p) = point(&e, 0) {
                        app.borrow_mut().pointer = p;
                        *d = Drag {
                            down: Some((p.0, p.1, 0)),
                            last: p,
                            ..Drag::default()
                        };
                    }
                }
                _ => {
                    d.down = None;
                    d.pinch_y = match (point(&e, 0), point(&e, 1)) {
                        (Some(a), Some(b)) => Some((a.1 + b.1) / 2.0),
                        _ => None,
                    };
                }
            }
        })?;
    }
    {
        let app = app.clone();
        let drag = drag.clone();
        on(canvas, "touchmove", move |e: TouchEvent| {
            e.prevent_default();
            let mut d = drag.borrow_mut();
            let mut a = app.borrow_mut();
            if e.touches().length() >= 2 {
                if let (Some(y0), Some(p), Some(q)) = (d.pinch_y, point(&e, 0), point(&e, 1)) {
                    let y = (p.1 + q.1) / 2.0;
                    // Dragging two fingers up flies forward, about a speed-second per 200 px.
                    a.fly([((y0 - y) / 200.0) as f32, 0.0, 0.0], 1.0);
                    d.pinch_y = Some(y);
                }
                return;
            }
            let Some(p) = point(&e, 0) else { return };
            if let Some((x0, y0, _)) = d.down
                && (p.0 - x0).hypot(p.1 - y0) > CLICK_SLOP * 2.0
            {
                d.moved = true;
            }
            if d.moved {
                a.look(p.0 - d.last.0, p.1 - d.last.1);
            }
            d.last = p;
            a.pointer = p;
        })?;
    }
    {
        let app = app.clone();
        on(canvas, "touchend", move |e: TouchEvent| {
            e.prevent_default();
            let d = std::mem::take(&mut *drag.borrow_mut());
            if d.down.is_some() && !d.moved && e.touches().length() == 0 {
                let mut a = app.borrow_mut();
                a.click(Button::Primary, true);
                a.click(Button::Primary, false);
            }
        })?;
    }
    Ok(())
}
