//! Admission of websocket connections: at most so many in all, and so many from one address.
//!
//! Why: every session costs a task pair, buffers and (while it syncs) owner time, and without
//! `--auth` anyone may connect; a single host opening thousands of sockets must not take the
//! server from everybody else. Refused upgrades get HTTP 503 with a reason, before any
//! websocket work is done.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};

/// How many connections the server takes.
#[derive(Clone, Debug)]
pub struct ConnectionLimits {
    /// Websocket sessions open at once, from everywhere.
    pub max_total: usize,
    /// Websocket sessions open at once from one IP address.
    pub max_per_ip: usize,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        ConnectionLimits {
            max_total: 4096,
            max_per_ip: 64,
        }
    }
}

/// A crowd of at least this many connections that shrinks to half of its peak hands the
/// memory it used back to the system (see [`Connections`]).
const CROWD: usize = 64;

/// The open connections, counted per address.
///
/// Also the moment to give memory back: glibc's allocator keeps what a thousand connections
/// freed (their buffers, the start of their syncs) for reuse, so the server's resident memory
/// stayed at its peak after a crowd left (BENCHMARKS.md, "Fair share"). When the connections
/// fall to half of their peak (of at least [`CROWD`]), the freed pages are returned
/// (`malloc_trim`, on a blocking thread).
#[derive(Default)]
pub struct Connections {
    open: Mutex<Open>,
    /// Times memory was given back.
    trims: std::sync::atomic::AtomicU64,
}

#[derive(Default)]
struct Open {
    total: usize,
    per_ip: HashMap<IpAddr, usize>,
    /// The most open at once since memory was last given back.
    peak: usize,
}

/// Why a connection was refused.
#[derive(Debug, thiserror::Error)]
pub enum Refusal {
    #[error("the server is at its limit of {0} connections; try again later")]
    Total(usize),
    #[error("too many connections from {0} (the limit is {1} per address)")]
    PerIp(IpAddr, usize),
}

/// Holds one admitted connection's place; dropping it frees the place.
pub struct Admitted {
    conns: Arc<Connections>,
    ip: IpAddr,
}

impl Connections {
    /// Admits a connection from `ip` if the limits allow.
    pub fn admit(
        self: &Arc<Self>,
        ip: IpAddr,
        limits: &ConnectionLimits,
    ) -> Result<Admitted, Refusal> {
        let mut open = self.open.lock().unwrap_or_else(|e| e.into_inner());
        if open.total >= limits.max_total {
            return Err(Refusal::Total(limits.max_total));
        }
        let from_ip = open.per_ip.entry(ip).or_insert(0);
        if *from_ip >= limits.max_per_ip {
            return Err(Refusal::PerIp(ip, limits.max_per_ip));
        }
        *from_ip += 1;
        open.total += 1;
        open.peak = open.peak.max(open.total);
        Ok(Admitted {
            conns: self.clone(),
            ip,
        })
    }

    /// Connections open now.
    pub fn open(&self) -> usize {
        self.open.lock().unwrap_or_else(|e| e.into_inner()).total
    }

    /// Times memory was given back after a crowd left.
    pub fn trims(&self) -> u64 {
        self.trims.load(std::sync::atomic::Ordering::Relaxed)
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        let trim = {
            let mut open = self.conns.open.lock().unwrap_or_else(|e| e.into_inner());
            open.total -= 1;
            if let Some(n) = open.per_ip.get_mut(&self.ip) {
                *n -= 1;
                if *n == 0 {
                    open.per_ip.remove(&self.ip);
                }
            }
            let trim = open.peak >= CROWD && open.total <= open.peak / 2;
            if trim {
                open.peak = open.total;
            }
            trim
        };
        if trim {
            self.conns
                .trims
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            // Off the async threads: trimming a large heap takes milliseconds.
            if let Ok(runtime) = tokio::runtime::Handle::try_current() {
                runtime.spawn_blocking(crate::served::give_back_memory);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_hold_and_places_come_back() {
        let conns = Arc::new(Connections::default());
        let limits = ConnectionLimits {
            max_total: 3,
            max_per_ip: 2,
        };
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let a1 = conns.admit(a, &limits).unwrap();
        let _a2 = conns.admit(a, &limits).unwrap();
        assert!(matches!(conns.admit(a, &limits), Err(Refusal::PerIp(..))));
        let _b1 = conns.admit(b, &limits).unwrap();
        assert!(matches!(conns.admit(b, &limits), Err(Refusal::Total(3))));
        drop(a1);
        assert_eq!(conns.open(), 2);
        let _b2 = conns.admit(b, &limits).unwrap();
        assert_eq!(conns.open(), 3);
        assert_eq!(conns.trims(), 0, "three connections are no crowd");
    }

    #[test]
    fn memory_is_given_back_once_a_crowd_has_halved() {
        let conns = Arc::new(Connections::default());
        let limits = ConnectionLimits::default();
        let ip: IpAddr = "10.0.0.3".parse().unwrap();
        let mut crowd: Vec<Admitted> = (0..CROWD)
            .map(|_| conns.admit(ip, &limits).unwrap())
            .collect();
        crowd.truncate(CROWD / 2 + 1);
        assert_eq!(conns.trims(), 0);
        crowd.pop();
        assert_eq!(conns.trims(), 1, "half of the peak left");
        crowd.clear();
        assert_eq!(conns.trims(), 1, "32 is no crowd");
    }
}
