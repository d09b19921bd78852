//! How many lasting user ids one address may bring: the per-address allowance of ids.
//!
//! **Why.** Without `--auth` a client chooses its user id, and every id's undo history outlives
//! its connection (`scene/history.rs`). A script that makes up a thousand ids a minute would
//! fill the scene-wide history cap with its own steps and push out everyone else's. So the ids
//! clients of one address choose are counted: the first [`Ids::per_address`] distinct ids an
//! address brings keep their history as usual (an id counts again each time it comes back, and
//! is forgotten after [`FORGET_AFTER`] unseen); any further id from that address is served like
//! a client that sent none: a connection-lived id whose history goes when it leaves. The id it
//! asked for is not used, so nothing of that id's history is touched.
//!
//! Ids an auth file's token pins are never counted. IPv6 addresses count by their /64 prefix
//! (what one host is usually given). The table is in memory: a restart forgets it, while the
//! scene cap (`--max-history-bytes`) still bounds what is stored.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use brickcast_protocol::wire::UserId;

/// Default of [`Ids::per_address`] (`serve --ids-per-address`).
pub const PER_ADDRESS: usize = 64;

/// An id not seen from its address for this long no longer counts against it.
pub const FORGET_AFTER: Duration = Duration::from_secs(24 * 3600);

/// Addresses the table keeps at most; beyond it those seen least recently are forgotten.
const MAX_ADDRESSES: usize = 1 << 16;

/// The ids each address has brought (see the module doc).
pub struct Ids {
    per_address: usize,
    table: Mutex<HashMap<IpAddr, Seen>>,
}

/// One address's ids and when each was last brought.
#[derive(Default)]
struct Seen {
    ids: HashMap<UserId, Instant>,
    last: Option<Instant>,
}

impl Ids {
    /// A table allowing `per_address` lasting ids per address (0: none).
    pub fn new(per_address: usize) -> Ids {
        Ids {
            per_address,
            table: Mutex::new(HashMap::new()),
        }
    }

    pub fn per_address(&self) -> usize {
        self.per_address
    }

    /// Whether a client from `from` may keep a lasting history under the id `user` it chose;
    /// counts the id against the address when it may.
    pub fn admit(&self, from: IpAddr, user: UserId) -> bool {
        self.admit_at(from, user, Instant::now())
    }

    fn admit_at(&self, from: IpAddr, user: UserId, now: Instant) -> bool {
        let mut table = self.table.lock().unwrap_or_else(|e| e.into_inner());
        let key = address_key(from);
        if !table.contains_key(&key) && table.len() >= MAX_ADDRESSES {
            forget_oldest(&mut table);
        }
        let seen = table.entry(key).or_default();
        seen.last = Some(now);
        if let Some(at) = seen.ids.get_mut(&user) {
            *at = now;
            return true;
        }
        if seen.ids.len() >= self.per_address {
            seen.ids
                .retain(|_, at| now.saturating_duration_since(*at) < FORGET_AFTER);
        }
        if seen.ids.len() >= self.per_address {
            return false;
        }
        seen.ids.insert(user, now);
        true
    }

    /// Addresses in the table.
    pub fn addresses(&self) -> usize {
        self.table.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}

/// What an address counts as: IPv4 as is (an IPv4-mapped IPv6 address too), IPv6 by its /64.
fn address_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(_) => ip,
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let mut octets = v6.octets();
                octets[8..].fill(0);
                IpAddr::from(octets)
            }
        },
    }
}

/// Forgets the quarter of the addresses seen least recently: amortised O(1) per new address.
fn forget_oldest(table: &mut HashMap<IpAddr, Seen>) {
    let mut lasts: Vec<Option<Instant>> = table.values().map(|s| s.last).collect();
    let cut = lasts.len() / 4;
    let (_, &mut threshold, _) = lasts.select_nth_unstable(cut);
    table.retain(|_, s| s.last > threshold);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_address_keeps_its_first_ids_and_those_it_brings_back() {
        let ids = Ids::new(3);
        let a: IpAddr = [10, 0, 0, 1].into();
        let b: IpAddr = [10, 0, 0, 2].into();
        let t0 = Instant::now();
        for user in 1..=3 {
            assert!(ids.admit_at(a, user, t0));
        }
        assert!(!ids.admit_at(a, 4, t0), "a fourth id from one address");
        assert!(ids.admit_at(a, 2, t0), "an id it brought before");
        assert!(
            ids.admit_at(b, 4, t0),
            "another address has its own allowance"
        );
        // A day later the ids not brought back are forgotten and make room.
        let later = t0 + FORGET_AFTER + Duration::from_secs(1);
        assert!(ids.admit_at(a, 1, later - Duration::from_secs(2)));
        assert!(ids.admit_at(a, 4, later));
        assert!(ids.admit_at(a, 5, later));
        assert!(!ids.admit_at(a, 6, later), "1, 4 and 5 are in use");
        assert!(!Ids::new(0).admit_at(a, 1, t0), "an allowance of none");
    }

    #[test]
    fn ipv6_counts_by_prefix_and_mapped_ipv4_as_ipv4() {
        let ids = Ids::new(1);
        let one: IpAddr = "2001:db8::1".parse().unwrap();
        let same_net: IpAddr = "2001:db8::ffff:2".parse().unwrap();
        let other_net: IpAddr = "2001:db8:0:1::1".parse().unwrap();
        assert!(ids.admit(one, 1));
        assert!(!ids.admit(same_net, 2), "one /64 is one address");
        assert!(ids.admit(other_net, 2));
        let v4: IpAddr = [192, 0, 2, 7].into();
        let mapped: IpAddr = "::ffff:192.0.2.7".parse().unwrap();
        assert!(ids.admit(v4, 1));
        assert!(!ids.admit(mapped, 2));
    }

    #[test]
    fn the_table_forgets_the_addresses_seen_least_recently() {
        let ids = Ids::new(1);
        let t0 = Instant::now();
        let addr = |i: usize| IpAddr::from((i as u32 + 1).to_be_bytes());
        for i in 0..MAX_ADDRESSES {
            assert!(ids.admit_at(addr(i), 1, t0 + Duration::from_millis(i as u64)));
        }
        assert!(ids.admit_at(addr(MAX_ADDRESSES), 1, t0 + Duration::from_secs(3600)));
        let left = ids.addresses();
        assert!(left <= MAX_ADDRESSES - MAX_ADDRESSES / 4 + 1, "{left}");
        // The newest addresses are still counted; the oldest start afresh.
        assert!(!ids.admit_at(addr(MAX_ADDRESSES - 1), 2, t0 + Duration::from_secs(3601)));
        assert!(ids.admit_at(addr(0), 2, t0 + Duration::from_secs(3601)));
    }
}
