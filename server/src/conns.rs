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

/// The open connections, counted per address.
#[derive(Default)]
pub struct Connections {
    open: Mutex<(usize, HashMap<IpAddr, usize>)>,
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
        let (total, per_ip) = &mut *open;
        if *total >= limits.max_total {
            return Err(Refusal::Total(limits.max_total));
        }
        let from_ip = per_ip.entry(ip).or_insert(0);
        if *from_ip >= limits.max_per_ip {
            return Err(Refusal::PerIp(ip, limits.max_per_ip));
        }
        *from_ip += 1;
        *total += 1;
        Ok(Admitted {
            conns: self.clone(),
            ip,
        })
    }

    /// Connections open now.
    pub fn open(&self) -> usize {
        self.open.lock().unwrap_or_else(|e| e.into_inner()).0
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        let mut open = self.conns.open.lock().unwrap_or_else(|e| e.into_inner());
        let (total, per_ip) = &mut *open;
        *total -= 1;
        if let Some(n) = per_ip.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                per_ip.remove(&self.ip);
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
    }
}
