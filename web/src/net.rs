//! The connection: a browser `WebSocket` carrying the same binary frames as the native client's,
//! decoded by the protocol crate and applied by the shared [`Session`](brickcast_client_core::session::Session).
//!
//! Reconnects with the native client's backoff (`client_core::backoff`: 250 ms doubling to
//! 5 s, each wait drawn in the window's second half) and resumes from the last sequence the
//! replica holds completely; a refusal that retrying cannot fix (bad token,
//! unknown scene, other protocol version) ends it with a message for the user.

use std::cell::RefCell;
use std::rc::Rc;

use brickcast_client_core::session::{HandshakeError, Status, hello, welcome};
use brickcast_protocol::wire::{ClientMsg, ErrorCode, Limits, decode_server, encode_client};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::{BinaryType, CloseEvent, MessageEvent, WebSocket};

use crate::app::App;
use crate::page;

/// One open (or opening) socket and the callbacks that must live as long as it.
pub struct Socket {
    ws: WebSocket,
    /// The Welcome has arrived: messages after it are the scene's.
    welcomed: bool,
    _on_open: Closure<dyn FnMut()>,
    _on_message: Closure<dyn FnMut(MessageEvent)>,
    _on_close: Closure<dyn FnMut(CloseEvent)>,
}

impl Socket {
    /// Sends `msg` when the connection is welcomed; otherwise it is dropped (as the native
    /// client drops edits made while disconnected: the page shows the state).
    pub fn send(&self, msg: &ClientMsg) -> bool {
        if !self.welcomed || self.ws.ready_state() != WebSocket::OPEN {
            return false;
        }
        match encode_client(msg) {
            Ok(bytes) => self.ws.send_with_u8_array(&bytes).is_ok(),
            Err(_) => false,
        }
    }

    /// Closes the socket; the close handler will reconnect.
    pub fn close(&self) {
        let _ = self.ws.close();
    }

    /// Closes the socket without reconnecting: its handlers are detached first.
    pub fn close_quietly(&self) {
        self.ws.set_onopen(None);
        self.ws.set_onmessage(None);
        self.ws.set_onclose(None);
        let _ = self.ws.close();
    }
}

/// The websocket address of `scene` on the server that served this page.
fn socket_url(scene: &str) -> Option<String> {
    let location = web_sys::window()?.location();
    let scheme = if location.protocol().ok()? == "https:" {
        "wss"
    } else {
        "ws"
    };
    Some(format!(
        "{scheme}://{}/scenes/{scene}/ws",
        location.host().ok()?
    ))
}

/// Opens a connection for `app` (replacing any old one).
pub fn connect(app: &Rc<RefCell<App>>) {
    let Some(url) = socket_url(&app.borrow().scene) else {
        app.borrow_mut()
            .fail("this page has no location to connect to".into());
        return;
    };
    let ws = match WebSocket::new(&url) {
        Ok(ws) => ws,
        Err(e) => {
            app.borrow_mut()
                .fail(format!("cannot open a websocket to {url}: {e:?}"));
            return;
        }
    };
    ws.set_binary_type(BinaryType::Arraybuffer);

    let on_open = {
        let app = app.clone();
        let ws = ws.clone();
        Closure::<dyn FnMut()>::new(move || {
            let a = app.borrow();
            let msg = hello(
                &a.name,
                a.user,
                a.token.as_deref(),
                a.session.resume_point(),
                a.session.hello_budget(),
            );
            if let Ok(bytes) = encode_client(&msg) {
                let _ = ws.send_with_u8_array(&bytes);
            }
        })
    };
    let on_message = {
        let app = app.clone();
        Closure::<dyn FnMut(MessageEvent)>::new(move |event: MessageEvent| {
            let Ok(buffer) = event.data().dyn_into::<js_sys::ArrayBuffer>() else {
                return;
            };
            let bytes = js_sys::Uint8Array::new(&buffer).to_vec();
            received(&app, &bytes);
        })
    };
    let on_close = {
        let app = app.clone();
        Closure::<dyn FnMut(CloseEvent)>::new(move |event: CloseEvent| {
            closed(&app, &event);
        })
    };
    ws.set_onopen(Some(on_open.as_ref().unchecked_ref()));
    ws.set_onmessage(Some(on_message.as_ref().unchecked_ref()));
    ws.set_onclose(Some(on_close.as_ref().unchecked_ref()));
    let mut a = app.borrow_mut();
    // Sockets are never dropped inside their own callbacks (wasm-bindgen forbids freeing a
    // running closure): they are retired there and dropped here, from a timer or at start.
    a.retired.clear();
    if let Some(old) = a.socket.take() {
        old.close_quietly();
    }
    a.socket = Some(Socket {
        ws,
        welcomed: false,
        _on_open: on_open,
        _on_message: on_message,
        _on_close: on_close,
    });
}

fn received(app: &Rc<RefCell<App>>, bytes: &[u8]) {
    let mut a = app.borrow_mut();
    a.bytes_in += bytes.len() as u64;
    let msg = match decode_server(bytes, &Limits::hard_caps()) {
        Ok(msg) => msg,
        Err(e) => {
            a.drop_connection(format!("the server sent an invalid frame: {e}"));
            return;
        }
    };
    let welcomed = a.socket.as_ref().is_some_and(|s| s.welcomed);
    if !welcomed {
        match welcome(msg) {
            Ok(w) => {
                if let Some(s) = &mut a.socket {
                    s.welcomed = true;
                }
                a.backoff.reset();
                if a.session.welcomed(&w).is_ok() {
                    a.welcomed();
                } else {
                    let why = a.session.status_text();
                    a.fail(why);
                }
            }
            Err(HandshakeError::Refused { code, message }) => a.refused(code, &message),
            Err(e) => a.drop_connection(e.to_string()),
        }
        return;
    }
    if let Err(e) = a.session.apply(&msg) {
        a.drop_connection(format!(
            "our copy of the scene went wrong ({e}); syncing again"
        ));
    }
}

fn closed(app: &Rc<RefCell<App>>, event: &CloseEvent) {
    let delay = {
        let mut a = app.borrow_mut();
        if let Some(s) = a.socket.take() {
            a.retired.push(s);
        }
        if matches!(a.session.status, Status::Failed(_)) {
            return;
        }
        let why = match event.reason() {
            r if !r.is_empty() => format!("closed: {r}"),
            _ if event.code() == 1006 => "the server cannot be reached".to_string(),
            _ => format!("closed (code {})", event.code()),
        };
        a.session.status = Status::Reconnecting(why);
        a.backoff.next_wait(js_sys::Math::random()).as_millis() as i32
    };
    let again = app.clone();
    let retry = Closure::once_into_js(move || connect(&again));
    if let Some(window) = web_sys::window() {
        let _ = window
            .set_timeout_with_callback_and_timeout_and_arguments_0(retry.unchecked_ref(), delay);
    }
}

/// Words for a refusal, and whether the token form should be offered.
pub fn refusal_text(code: ErrorCode, message: &str, scene: &str) -> (String, bool) {
    match code {
        ErrorCode::Unauthorized => (
            format!("This scene needs an access token ({message}). Enter it below."),
            true,
        ),
        ErrorCode::UnknownScene => (
            format!("There is no scene called \u{201c}{scene}\u{201d} on this server."),
            false,
        ),
        ErrorCode::VersionMismatch => (
            format!(
                "This page and the server speak different protocol versions ({message}). Reload the page."
            ),
            false,
        ),
        _ => (
            format!("The server refused the connection: {message}"),
            false,
        ),
    }
}

pub fn show_refusal(code: ErrorCode, message: &str, scene: &str) {
    let (text, token_form) = refusal_text(code, message, scene);
    page::message(Some(&text));
    page::show("token-form", token_form);
}
