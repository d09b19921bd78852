//! Fair shares of a scene's edit work: what no set of connections may take from the others.
//!
//! Three rules, each where it can be enforced without the owner waiting on anyone:
//!
//! - **Budgets per user and per address, not only per connection.** A session charges an edit's
//!   work (voxels visited, `EditOp::work`) to its connection's bucket *and* to buckets shared by
//!   every connection of the same user and of the same source address ([`Shares`]), each
//!   refilled at `--max-work-per-second`. Eight connections from one address get one budget
//!   between them, not eight.
//! - **Heavy edits are admitted to a scene one budget at a time, in arrival order.** An edit
//!   asking for at least [`HEAVY_WORK`] voxels first takes its work's worth of the scene's
//!   [`HeavyGate`] (a FIFO semaphore holding one `--max-work-per-edit`), and gives it back once
//!   the owner has applied it. So the owner's queue never holds more than one message's worth
//!   of heavy work, heavy senders take turns, and a light edit (a voxel, a small brush) never
//!   waits behind more than the one heavy edit being applied. A heavy sender's session waits for
//!   its turn without reading its socket: backpressure, not a refusal.
//! - **Replies are bounded per connection** (`scene::outbox`): a client that sends without
//!   reading is not read.
//!
//! - **Large undos and heavy edits are planned across turns** (`scene/jobs.rs`) and applied in
//!   one: others wait for at most the last turn of one (writing its bricks, logging them and
//!   broadcasting them). A heavy edit keeps its place at the gate until that last turn.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex, Weak};

use brickcast_protocol::wire::UserId;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::bucket::Bucket;

/// Edits asking for at least this much work (voxels visited) are heavy: a sphere of radius 50.
pub const HEAVY_WORK: u64 = 1 << 20;

/// One unit of the heavy gate, in voxels of work (the semaphore counts in `u32`).
const GATE_UNIT: u64 = 1 << 10;

/// Who a shared budget belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Owner {
    Address(IpAddr),
    User(UserId),
}

/// A budget several sessions share.
pub type SharedBucket = Arc<Mutex<Bucket>>;

/// The server's shared budgets, by address and by user. An entry lives as long as a session
/// holds it; dead ones are swept as the table grows.
#[derive(Default)]
pub struct Shares {
    buckets: Mutex<HashMap<Owner, Weak<Mutex<Bucket>>>>,
}

impl Shares {
    /// The budget `owner` shares, made with `rate` and `burst` when nobody holds it yet.
    pub fn get(&self, owner: Owner, rate: f64, burst: f64) -> SharedBucket {
        let mut map = self.buckets.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(live) = map.get(&owner).and_then(Weak::upgrade) {
            return live;
        }
        // Sweep when the table may be half dead: amortised O(1) per call.
        if map.len() >= 64 && map.len().is_power_of_two() {
            map.retain(|_, w| w.strong_count() > 0);
        }
        let bucket = Arc::new(Mutex::new(Bucket::new(rate, burst)));
        map.insert(owner, Arc::downgrade(&bucket));
        bucket
    }

    /// Entries in the table (live or not yet swept).
    pub fn len(&self) -> usize {
        self.buckets.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Takes `n` from every bucket in `buckets`, or from none of them.
pub fn take_all(buckets: &mut [&mut Bucket], n: f64) -> bool {
    if !buckets.iter_mut().all(|b| b.holds(n)) {
        return false;
    }
    for b in buckets.iter_mut() {
        b.take(n);
    }
    true
}

/// A scene's gate for heavy edits (see the module doc).
#[derive(Clone)]
pub struct HeavyGate {
    permits: Arc<Semaphore>,
    max_units: u32,
}

/// A heavy edit's turn: given back when dropped (by the owner, once the edit is applied).
pub type Admitted = OwnedSemaphorePermit;

impl HeavyGate {
    /// A gate that lets `max_work` voxels of heavy edits into the owner's queue at once.
    pub fn new(max_work: u64) -> HeavyGate {
        let max_units = u32::try_from(max_work.div_ceil(GATE_UNIT))
            .unwrap_or(u32::MAX >> 4)
            .clamp(1, (u32::MAX >> 4).min(Semaphore::MAX_PERMITS as u32));
        HeavyGate {
            permits: Arc::new(Semaphore::new(max_units as usize)),
            max_units,
        }
    }

    /// Waits for `work`'s turn; `None` when the edit is light (it needs none).
    pub async fn admit(&self, work: u64) -> Option<Admitted> {
        if work < HEAVY_WORK {
            return None;
        }
        let units = u32::try_from(work.div_ceil(GATE_UNIT))
            .unwrap_or(u32::MAX)
            .min(self.max_units);
        // The semaphore is never closed.
        self.permits.clone().acquire_many_owned(units).await.ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shared_budgets_are_shared_while_held_and_swept_after() {
        let shares = Shares::default();
        let ip: IpAddr = [10, 0, 0, 1].into();
        let a = shares.get(Owner::Address(ip), 10.0, 10.0);
        let b = shares.get(Owner::Address(ip), 10.0, 10.0);
        assert!(Arc::ptr_eq(&a, &b), "one budget per address");
        assert!(a.lock().unwrap().take(10.0));
        assert!(
            !b.lock().unwrap().take(1.0),
            "spent by the other connection"
        );
        let user = shares.get(Owner::User(7), 10.0, 10.0);
        assert!(!Arc::ptr_eq(&a, &user));
        drop((a, b, user));
        for u in 0..1000 {
            drop(shares.get(Owner::User(u), 1.0, 1.0));
        }
        assert!(
            shares.len() < 200,
            "dead entries are swept: {}",
            shares.len()
        );
    }

    #[test]
    fn take_all_takes_from_every_bucket_or_none() {
        let mut a = Bucket::new(0.0, 5.0);
        let mut b = Bucket::new(0.0, 3.0);
        assert!(!take_all(&mut [&mut a, &mut b], 4.0));
        assert!(
            take_all(&mut [&mut a, &mut b], 3.0),
            "nothing was taken before"
        );
        assert!(take_all(&mut [&mut a], 2.0));
    }

    #[tokio::test]
    async fn heavy_edits_take_turns_and_light_ones_never_wait() {
        let gate = HeavyGate::new(40 << 20);
        assert!(gate.admit(HEAVY_WORK - 1).await.is_none());
        let first = gate.admit(30 << 20).await.unwrap();
        let waiting = tokio::spawn({
            let gate = gate.clone();
            async move { gate.admit(20 << 20).await.map(drop) }
        });
        tokio::task::yield_now().await;
        assert!(
            !waiting.is_finished(),
            "the second heavy edit waits its turn"
        );
        assert!(gate.admit(10).await.is_none(), "a light edit does not");
        drop(first);
        tokio::time::timeout(std::time::Duration::from_secs(5), waiting)
            .await
            .unwrap()
            .unwrap();
        // More than the gate holds is admitted alone.
        drop(gate.admit(1 << 40).await.unwrap());
    }
}
