//! One websocket connection to a scene: handshake, frames in and out.
//!
//! A `Link` knows the wire protocol but not what to do with the scene; the replica applies what
//! arrives, and the front ends decide when to reconnect.

use std::time::Duration;

use brickcast_protocol::wire::{
    ClientMsg, ErrorCode, Limits, ServerMsg, UserId, WireError, decode_server, encode_client,
};
use futures_util::{SinkExt, StreamExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

use crate::replica::{Replica, ReplicaError};

/// How long the server has to answer the Hello.
const WELCOME_TIMEOUT: Duration = Duration::from_secs(15);

#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("{0:?} is not a scene address: expected ws://HOST:PORT/scenes/NAME")]
    BadUrl(String),
    #[error("could not connect to {url}: {reason}")]
    Connect { url: String, reason: String },
    #[error("could not open {url}: {reason}")]
    NoScene { url: String, reason: String },
    #[error("the server refused the connection ({code:?}): {message}")]
    Refused { code: ErrorCode, message: String },
    #[error("the server closed the connection")]
    Closed,
    #[error("no Welcome from the server within {0:?}")]
    Timeout(Duration),
    #[error("websocket error: {0}")]
    Socket(String),
    #[error("the server sent an invalid frame: {0}")]
    Wire(#[from] WireError),
    #[error("the server sent {0} where a Welcome was expected")]
    Unexpected(&'static str),
    #[error(transparent)]
    Replica(#[from] ReplicaError),
}

impl LinkError {
    /// Whether trying again later can help (a refused token or version cannot).
    pub fn is_retryable(&self) -> bool {
        !matches!(
            self,
            LinkError::BadUrl(_) | LinkError::Refused { .. } | LinkError::NoScene { .. }
        )
    }
}

/// Turns what a user types into the websocket address: `ws://HOST:PORT/scenes/NAME`, with or
/// without the trailing `/ws` the server routes on, or a bare `HOST:PORT/scenes/NAME`.
/// A browser link (`http://HOST:PORT/scenes/NAME#token=T`, the page's `?scale=…`) works too:
/// the query and fragment are not part of the address ([`link_token`] reads the token).
pub fn websocket_url(input: &str) -> Result<String, LinkError> {
    let bad = || LinkError::BadUrl(input.to_string());
    let address = input.split(['#', '?']).next().unwrap_or(input);
    let rest = if let Some(r) = address.strip_prefix("ws://") {
        r
    } else if let Some(r) = address.strip_prefix("http://") {
        r
    } else if address.contains("://") {
        // No TLS support is compiled in; say so rather than fail obscurely.
        return Err(bad());
    } else {
        address
    };
    let (host, path) = rest.split_once('/').ok_or_else(bad)?;
    let path = path.trim_end_matches('/');
    let path = path.strip_suffix("/ws").unwrap_or(path);
    let name = path.strip_prefix("scenes/").ok_or_else(bad)?;
    if host.is_empty() || name.is_empty() || name.contains('/') {
        return Err(bad());
    }
    Ok(format!("ws://{host}/scenes/{name}/ws"))
}

/// The access token a browser link carries in its fragment (`…/scenes/NAME#token=T`), if any:
/// what the page would use, so pasting the page's link into `render` or `view` just works.
pub fn link_token(input: &str) -> Option<String> {
    let (_, fragment) = input.split_once('#')?;
    fragment
        .split('&')
        .find_map(|pair| pair.strip_prefix("token="))
        .filter(|t| !t.is_empty())
        .map(str::to_string)
}

/// A failed websocket handshake as a [`LinkError`]: a 404 (no such scene) is final, so a viewer
/// shows it instead of retrying it forever; anything else may pass.
fn connect_error(url: &str, e: &tokio_tungstenite::tungstenite::Error) -> LinkError {
    let reason = connect_reason(e);
    let url = url.to_string();
    match e {
        tokio_tungstenite::tungstenite::Error::Http(r) if r.status().as_u16() == 404 => {
            LinkError::NoScene { url, reason }
        }
        _ => LinkError::Connect { url, reason },
    }
}

/// The reason to show for a failed websocket handshake: an HTTP answer says what the server
/// meant (no such scene, too many connections) instead of tungstenite's bare status line.
fn connect_reason(e: &tokio_tungstenite::tungstenite::Error) -> String {
    use tokio_tungstenite::tungstenite::Error;
    match e {
        Error::Http(response) => {
            let status = response.status();
            let body = response
                .body()
                .as_deref()
                .map(|b| String::from_utf8_lossy(b).trim().to_string())
                .filter(|b| !b.is_empty() && b.len() < 500 && !b.starts_with('<'));
            let meaning = match status.as_u16() {
                404 => "no such scene on this server (is the name right? `brickcast-server scenes` lists them)".to_string(),
                200 => "the server answered with a page, not a websocket: is this a scene address?".to_string(),
                _ => format!("the server answered HTTP {status}"),
            };
            match body {
                Some(body) => format!("{meaning}: {body}"),
                None => meaning,
            }
        }
        other => other.to_string(),
    }
}

pub use brickcast_client_core::session::Welcome;
use brickcast_client_core::session::{HandshakeError, hello, welcome};

type Socket = WebSocketStream<MaybeTlsStream<TcpStream>>;

/// An open, welcomed connection.
pub struct Link {
    ws: Socket,
    pub welcome: Welcome,
    /// Websocket payload bytes received and sent on this connection (Hello and Welcome
    /// included), for tools that report bandwidth.
    pub bytes_in: u64,
    pub bytes_out: u64,
}

impl Link {
    /// Connects and says hello as `name` (user id `user`, 0 for none), asking to resume from
    /// `resume_from` when the caller holds a complete copy up to that sequence.
    pub async fn connect(
        url: &str,
        name: &str,
        user: UserId,
        token: Option<&str>,
        resume_from: Option<u64>,
    ) -> Result<Link, LinkError> {
        Link::connect_within(url, name, user, token, resume_from, None).await
    }

    /// [`Link::connect`] for a client that gives the scene a GPU budget: the server streams it
    /// a working set within it and follows its camera (`None`: the whole scene).
    pub async fn connect_within(
        url: &str,
        name: &str,
        user: UserId,
        token: Option<&str>,
        resume_from: Option<u64>,
        budget: Option<brickcast_protocol::wire::Budget>,
    ) -> Result<Link, LinkError> {
        // Nagle's algorithm would hold a small edit back until the previous frame is
        // acknowledged, which the server's delayed ACK can put off until our *next* send: an
        // edit would wait for the one after it.
        let (mut ws, _) = tokio_tungstenite::connect_async_with_config(url, None, true)
            .await
            .map_err(|e| connect_error(url, &e))?;
        let hello = hello(name, user, token, resume_from, budget);
        let hello = encode_client(&hello)?;
        let bytes_out = hello.len() as u64;
        ws.send(Message::Binary(hello.into()))
            .await
            .map_err(|e| LinkError::Socket(e.to_string()))?;
        let mut bytes_in = 0;
        let first = tokio::time::timeout(WELCOME_TIMEOUT, read_msg(&mut ws, &mut bytes_in))
            .await
            .map_err(|_| LinkError::Timeout(WELCOME_TIMEOUT))??;
        let welcome = welcome(first.ok_or(LinkError::Closed)?).map_err(|e| match e {
            HandshakeError::Refused { code, message } => LinkError::Refused { code, message },
            HandshakeError::Unexpected(what) => LinkError::Unexpected(what),
        })?;
        Ok(Link {
            ws,
            welcome,
            bytes_in,
            bytes_out,
        })
    }

    /// The next message from the server; `None` once it has closed the connection.
    pub async fn next(&mut self) -> Result<Option<ServerMsg>, LinkError> {
        read_msg(&mut self.ws, &mut self.bytes_in).await
    }

    pub async fn send(&mut self, msg: &ClientMsg) -> Result<(), LinkError> {
        self.feed(msg).await?;
        self.flush().await
    }

    /// Queues a message without flushing the socket, so a burst of messages costs one write;
    /// [`Link::flush`] (or the next [`Link::send`]) puts them on the wire.
    pub async fn feed(&mut self, msg: &ClientMsg) -> Result<(), LinkError> {
        let frame = encode_client(msg)?;
        self.bytes_out += frame.len() as u64;
        self.ws
            .feed(Message::Binary(frame.into()))
            .await
            .map_err(|e| LinkError::Socket(e.to_string()))
    }

    pub async fn flush(&mut self) -> Result<(), LinkError> {
        self.ws
            .flush()
            .await
            .map_err(|e| LinkError::Socket(e.to_string()))
    }

    pub async fn close(mut self) {
        let _ = self.ws.close(None).await;
    }
}

/// The next server message on `ws`, skipping pings and text; `None` once the server has closed.
async fn read_msg(ws: &mut Socket, bytes_in: &mut u64) -> Result<Option<ServerMsg>, LinkError> {
    loop {
        match ws.next().await {
            Some(Ok(Message::Binary(bytes))) => {
                *bytes_in += bytes.len() as u64;
                return Ok(Some(decode_server(&bytes, &Limits::hard_caps())?));
            }
            Some(Ok(Message::Close(_))) | None => return Ok(None),
            Some(Ok(_)) => continue,
            Some(Err(e)) => return Err(LinkError::Socket(e.to_string())),
        }
    }
}

/// Reads until `replica` holds the whole scene, calling `progress` after every sync batch.
/// Errors the server reports during the sync end it.
pub async fn sync(
    link: &mut Link,
    replica: &mut Replica,
    mut progress: impl FnMut(&Replica),
) -> Result<(), LinkError> {
    while !replica.synced {
        match link.next().await? {
            Some(ServerMsg::Error { code, message }) => {
                return Err(LinkError::Refused { code, message });
            }
            Some(msg) => {
                replica.apply(&msg)?;
                progress(replica);
            }
            None => return Err(LinkError::Closed),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_normalise_to_the_websocket_route() {
        let want = "ws://127.0.0.1:7878/scenes/demo/ws";
        for input in [
            "ws://127.0.0.1:7878/scenes/demo",
            "ws://127.0.0.1:7878/scenes/demo/",
            "ws://127.0.0.1:7878/scenes/demo/ws",
            "http://127.0.0.1:7878/scenes/demo",
            "127.0.0.1:7878/scenes/demo",
            // The browser page's link, as copied from the address bar.
            "http://127.0.0.1:7878/scenes/demo#token=secret",
            "http://127.0.0.1:7878/scenes/demo?scale=2#token=secret",
        ] {
            assert_eq!(websocket_url(input).unwrap(), want, "{input}");
        }
        assert_eq!(
            link_token("http://h:1/scenes/demo?scale=2#user=ann&token=secret").as_deref(),
            Some("secret")
        );
        assert_eq!(link_token("http://h:1/scenes/demo#token="), None);
        assert_eq!(link_token("ws://h:1/scenes/demo"), None);
    }

    #[test]
    fn a_missing_scene_is_final_and_said_plainly() {
        use tokio_tungstenite::tungstenite::{Error, http};
        let answer = |status: u16, body: &str| {
            let mut r = http::Response::new(Some(body.as_bytes().to_vec()));
            *r.status_mut() = http::StatusCode::from_u16(status).unwrap();
            Error::Http(Box::new(r))
        };
        let e = connect_error("ws://h:1/scenes/nope/ws", &answer(404, ""));
        assert!(!e.is_retryable(), "{e}");
        assert!(
            e.to_string().contains("no such scene on this server"),
            "{e}"
        );
        let busy = connect_error(
            "ws://h:1/scenes/demo/ws",
            &answer(503, "too many connections from 127.0.0.1 (limit 64)\n"),
        );
        assert!(busy.is_retryable());
        assert!(
            busy.to_string().contains("503") && busy.to_string().contains("limit 64"),
            "{busy}"
        );
        for bad in [
            "wss://host/scenes/demo",
            "ws://host",
            "ws://host/demo",
            "ws:///scenes/demo",
            "ws://host/scenes/",
            "ws://host/scenes/a/b",
        ] {
            assert!(websocket_url(bad).is_err(), "{bad}");
        }
    }
}
