//! A value that many tasks watch: who owns a scene, whether a scene is closing, why a process
//! must stop. Like `tokio::sync::watch`, but it wakes its watchers in the order they began to
//! wait: tokio's spreads them over shards picked at random, and the cluster's simulation must
//! replay a seed exactly.

use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll, Waker};

struct State<T> {
    value: T,
    version: u64,
    /// The sender is gone: nothing changes any more.
    closed: bool,
    receivers: usize,
    /// Tasks waiting for a change (or for the receivers to go), in the order they came.
    waiting: Vec<Waker>,
}

struct Shared<T> {
    state: Mutex<State<T>>,
}

impl<T> Shared<T> {
    fn lock(&self) -> MutexGuard<'_, State<T>> {
        // One assignment at a time: a poisoned value is still a good value.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn wake(state: &mut State<T>) {
        for w in state.waiting.drain(..) {
            w.wake();
        }
    }
}

/// Sets the value.
pub struct Sender<T> {
    shared: Arc<Shared<T>>,
}

/// Reads the value and waits for it to change.
pub struct Receiver<T> {
    shared: Arc<Shared<T>>,
    seen: u64,
}

/// The sender went away.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the value will not change any more")]
pub struct Closed;

/// A value and its watchers.
pub fn channel<T>(value: T) -> (Sender<T>, Receiver<T>) {
    let shared = Arc::new(Shared {
        state: Mutex::new(State {
            value,
            version: 0,
            closed: false,
            receivers: 1,
            waiting: Vec::new(),
        }),
    });
    (
        Sender {
            shared: shared.clone(),
        },
        Receiver { shared, seen: 0 },
    )
}

impl<T: Clone> Sender<T> {
    /// Sets the value; the old one.
    pub fn send_replace(&self, value: T) -> T {
        let mut state = self.shared.lock();
        let old = std::mem::replace(&mut state.value, value);
        state.version += 1;
        Shared::wake(&mut state);
        old
    }

    /// Changes the value in place; watchers hear of it when `change` says it changed.
    pub fn send_if_modified(&self, change: impl FnOnce(&mut T) -> bool) -> bool {
        let mut state = self.shared.lock();
        let changed = change(&mut state.value);
        if changed {
            state.version += 1;
            Shared::wake(&mut state);
        }
        changed
    }

    pub fn get(&self) -> T {
        self.shared.lock().value.clone()
    }

    /// A new watcher, which has seen the value as it is.
    pub fn subscribe(&self) -> Receiver<T> {
        let mut state = self.shared.lock();
        state.receivers += 1;
        Receiver {
            shared: self.shared.clone(),
            seen: state.version,
        }
    }

    /// Whether every watcher is gone.
    pub fn is_closed(&self) -> bool {
        self.shared.lock().receivers == 0
    }

    /// Resolves once every watcher is gone.
    pub async fn closed(&self) {
        std::future::poll_fn(|cx| {
            let mut state = self.shared.lock();
            if state.receivers == 0 {
                return Poll::Ready(());
            }
            state.waiting.push(cx.waker().clone());
            Poll::Pending
        })
        .await
    }
}

impl<T> Drop for Sender<T> {
    fn drop(&mut self) {
        let mut state = self.shared.lock();
        state.closed = true;
        Shared::wake(&mut state);
    }
}

impl<T: Clone> Receiver<T> {
    /// The value now.
    pub fn get(&self) -> T {
        self.shared.lock().value.clone()
    }

    /// The value now, marked as seen.
    pub fn get_and_update(&mut self) -> T {
        let state = self.shared.lock();
        self.seen = state.version;
        state.value.clone()
    }

    /// Waits for a value this watcher has not seen; an error once the sender is gone.
    pub fn changed(&mut self) -> Changed<'_, T> {
        Changed { receiver: self }
    }

    /// Waits until the value satisfies `holds` (now or later); the value then.
    pub async fn wait_for(&mut self, mut holds: impl FnMut(&T) -> bool) -> Result<T, Closed> {
        loop {
            let value = self.get_and_update();
            if holds(&value) {
                return Ok(value);
            }
            self.changed().await?;
        }
    }
}

impl<T> Clone for Receiver<T> {
    fn clone(&self) -> Self {
        self.shared.lock().receivers += 1;
        Receiver {
            shared: self.shared.clone(),
            seen: self.seen,
        }
    }
}

impl<T> Drop for Receiver<T> {
    fn drop(&mut self) {
        let mut state = self.shared.lock();
        state.receivers -= 1;
        if state.receivers == 0 {
            Shared::wake(&mut state);
        }
    }
}

/// [`Receiver::changed`].
pub struct Changed<'a, T> {
    receiver: &'a mut Receiver<T>,
}

impl<T> Future for Changed<'_, T> {
    type Output = Result<(), Closed>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let shared = self.receiver.shared.clone();
        let mut state = shared.lock();
        if state.version != self.receiver.seen {
            self.receiver.seen = state.version;
            return Poll::Ready(Ok(()));
        }
        if state.closed {
            return Poll::Ready(Err(Closed));
        }
        state.waiting.push(cx.waker().clone());
        Poll::Pending
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn watchers_see_changes_and_the_end() {
        let (tx, mut rx) = channel(1);
        let mut other = rx.clone();
        assert_eq!(rx.get(), 1);
        tx.send_replace(2);
        rx.changed().await.unwrap();
        assert_eq!(rx.get_and_update(), 2);
        assert!(!tx.send_if_modified(|_| false));
        assert!(tx.send_if_modified(|v| {
            *v = 3;
            true
        }));
        assert_eq!(other.wait_for(|v| *v == 3).await, Ok(3));
        drop(tx);
        rx.changed().await.unwrap();
        assert_eq!(rx.changed().await, Err(Closed));
        assert_eq!(other.changed().await, Err(Closed));
    }

    #[tokio::test]
    async fn the_sender_hears_when_every_watcher_is_gone() {
        let (tx, rx) = channel(false);
        let second = tx.subscribe();
        assert!(!tx.is_closed());
        drop(rx);
        assert!(!tx.is_closed());
        let waiting = tokio::spawn(async move {
            tx.closed().await;
            tx.is_closed()
        });
        tokio::task::yield_now().await;
        drop(second);
        assert!(waiting.await.unwrap());
    }
}
