//! The HTTP accept loop: HTTP/1.1 with websocket upgrades, serving the router on every
//! connection.
//!
//! Why not `axum::serve`: it sets no timer on hyper, so hyper's header read timeout never takes
//! effect, and a client that opens connections and sends half a request line holds each one
//! forever (300 such connections were all still open after 40 s). Here every connection must
//! deliver its request headers within [`HttpConfig::header_timeout`] (idle keep-alive
//! connections included: the clock runs while waiting for the next request), accepted sockets
//! get TCP_NODELAY (acks and deltas are small writes a client waits on: without it Nagle holds
//! a segment until the peer's delayed ACK), and the peer's address reaches handlers as
//! `ConnectInfo` (the connection limits need it). Shutdown stops accepting, lets requests in
//! flight finish (upgraded websockets end through the server's own shutdown signal), and gives
//! up on connections still open after [`DRAIN`].

use std::future::Future;
use std::net::SocketAddr;
use std::pin::pin;
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use axum::extract::ConnectInfo;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tower::ServiceExt;

/// How long shutdown waits for HTTP requests in flight.
const DRAIN: Duration = Duration::from_secs(5);

/// Knobs of the HTTP layer.
#[derive(Clone, Debug)]
pub struct HttpConfig {
    /// A connection that has not sent a whole request head this long after it was opened (or
    /// after its previous request) is closed.
    pub header_timeout: Duration,
}

impl Default for HttpConfig {
    fn default() -> Self {
        HttpConfig {
            header_timeout: Duration::from_secs(10),
        }
    }
}

/// Serves `router` on `listener` until `shutdown` resolves.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    config: HttpConfig,
    shutdown: impl Future<Output = ()>,
) {
    let mut shutdown = pin!(shutdown);
    // Cancelled when accepting stops; every connection task watches it and is tracked, so the
    // drain waits for exactly the connections still open.
    let stop = CancellationToken::new();
    let connections = TaskTracker::new();
    loop {
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of file descriptors and the like: wait instead of spinning.
                    tracing::warn!(error = %e, "cannot accept a connection");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        if let Err(e) = stream.set_nodelay(true) {
            tracing::warn!(error = %e, "cannot set TCP_NODELAY on an accepted socket");
        }
        let router = router.clone();
        let service = hyper::service::service_fn(move |mut request: hyper::Request<Incoming>| {
            request
                .extensions_mut()
                .insert(ConnectInfo::<SocketAddr>(peer));
            router.clone().oneshot(request.map(Body::new))
        });
        let stopped = stop.clone();
        let header_timeout = config.header_timeout;
        connections.spawn(async move {
            let mut builder = http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(header_timeout);
            let mut conn = pin!(
                builder
                    .serve_connection(TokioIo::new(stream), service)
                    .with_upgrades()
            );
            let result = tokio::select! {
                result = conn.as_mut() => result,
                () = stopped.cancelled() => {
                    conn.as_mut().graceful_shutdown();
                    conn.await
                }
            };
            if let Err(e) = result {
                tracing::debug!(%peer, error = %e, "HTTP connection ended with an error");
            }
        });
    }
    stop.cancel();
    connections.close();
    let _ = tokio::time::timeout(DRAIN, connections.wait()).await;
}
