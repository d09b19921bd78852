//! Runs a simulation's seeds on every core until one fails: the single node's simulation and
//! the cluster's share it.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

/// What a simulation's seeds add up to.
pub trait Tally: Default + Send {
    fn add(&mut self, other: &Self);
}

/// What a seed reports when it fails: what went wrong, and the last actions before it.
pub type Failure = (String, String);

/// What a run of seeds found.
pub struct SeedRun<S> {
    pub ran: u64,
    pub stats: S,
    pub threads: usize,
    pub elapsed: Duration,
    /// The first failing seed a thread came to (the run stops there).
    pub failed: Option<(u64, String, String)>,
}

/// Runs seeds from `first` on one thread per core until `done(seed, elapsed)` says so or one
/// fails; a panic in a seed counts as its failure.
pub fn run_seeds<S: Tally>(
    first: u64,
    done: impl Fn(u64, Duration) -> bool + Sync,
    run: impl Fn(u64) -> Result<S, Failure> + Sync,
) -> SeedRun<S> {
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    let next = AtomicU64::new(first);
    let failed: Mutex<Option<(u64, String, String)>> = Mutex::new(None);
    let total = Mutex::new((0u64, S::default()));
    let started = Instant::now();
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| {
                loop {
                    if failed.lock().unwrap().is_some() {
                        return;
                    }
                    let seed = next.fetch_add(1, Relaxed);
                    if done(seed, started.elapsed()) {
                        return;
                    }
                    let outcome =
                        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(seed)));
                    let result = outcome.unwrap_or_else(|panic| {
                        let text = panic
                            .downcast_ref::<String>()
                            .map(String::as_str)
                            .or_else(|| panic.downcast_ref::<&str>().copied())
                            .unwrap_or("?");
                        Err((format!("panicked: {text}"), String::new()))
                    });
                    match result {
                        Ok(stats) => {
                            let mut t = total.lock().unwrap();
                            t.0 += 1;
                            t.1.add(&stats);
                        }
                        Err((e, trace)) => {
                            failed.lock().unwrap().get_or_insert((seed, e, trace));
                        }
                    }
                }
            });
        }
    });
    let (ran, stats) = total.into_inner().unwrap();
    SeedRun {
        ran,
        stats,
        threads,
        elapsed: started.elapsed(),
        failed: failed.into_inner().unwrap(),
    }
}
