//! How long a viewer waits before reconnecting: [`brickcast_protocol::backoff`]'s rule from
//! [`START`] to [`MAX`]. The native viewer draws with `rand`, the page with `Math.random`; both
//! share this one schedule, so viewers that lost a server together come back spread out.

use std::time::Duration;

pub use brickcast_protocol::backoff::Backoff;

/// First wait before reconnecting after a lost connection.
pub const START: Duration = Duration::from_millis(250);
/// Longest wait.
pub const MAX: Duration = Duration::from_secs(5);

/// A viewer's reconnect schedule, at its first window.
pub fn reconnect() -> Backoff {
    Backoff::new(START, MAX)
}
