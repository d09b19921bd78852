//! Server counters, exported at `GET /metrics` in the Prometheus text format.
//!
//! Plain atomics written from the scene owners and sessions; rendering is a string build on
//! request. No metrics crate: the set is small and fixed, and this keeps the hot path to one
//! relaxed add per event.

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

/// Upper bounds of the commit latency buckets, in microseconds.
const COMMIT_BUCKETS_US: [u64; 12] = [
    100, 250, 500, 1_000, 2_500, 5_000, 10_000, 25_000, 50_000, 100_000, 250_000, 1_000_000,
];

#[derive(Default)]
pub struct Metrics {
    pub connected_clients: AtomicU64,
    pub edit_batches: AtomicU64,
    pub ops_applied: AtomicU64,
    pub ops_rejected: AtomicU64,
    pub voxels_changed: AtomicU64,
    pub deltas_sent: AtomicU64,
    pub sync_batches_sent: AtomicU64,
    pub bytes_out: AtomicU64,
    pub bytes_in: AtomicU64,
    pub resyncs: AtomicU64,
    pub rejected_frames: AtomicU64,
    pub commits: AtomicU64,
    pub snapshots: AtomicU64,
    commit_buckets: [AtomicU64; COMMIT_BUCKETS_US.len()],
    commit_sum_us: AtomicU64,
}

impl Metrics {
    pub fn add(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Relaxed);
    }

    /// Records one durable commit of the edit log.
    pub fn observe_commit(&self, took: Duration) {
        let us = took.as_micros().min(u128::from(u64::MAX)) as u64;
        self.commits.fetch_add(1, Relaxed);
        self.commit_sum_us.fetch_add(us, Relaxed);
        if let Some(i) = COMMIT_BUCKETS_US.iter().position(|&b| us <= b) {
            self.commit_buckets[i].fetch_add(1, Relaxed);
        }
    }

    /// The Prometheus text exposition of every metric.
    pub fn render(&self) -> String {
        let mut out = String::new();
        let mut metric = |name: &str, kind: &str, help: &str, value: u64| {
            let _ = writeln!(
                out,
                "# HELP brickcast_{name} {help}\n# TYPE brickcast_{name} {kind}\nbrickcast_{name} {value}"
            );
        };
        let get = |c: &AtomicU64| c.load(Relaxed);
        metric(
            "connected_clients",
            "gauge",
            "Websocket sessions currently open.",
            get(&self.connected_clients),
        );
        metric(
            "edit_batches_total",
            "counter",
            "Edit messages that applied at least one op.",
            get(&self.edit_batches),
        );
        metric(
            "edits_applied_total",
            "counter",
            "Edit ops applied.",
            get(&self.ops_applied),
        );
        metric(
            "edits_rejected_total",
            "counter",
            "Edit ops rejected (bounds, limits, role, rate).",
            get(&self.ops_rejected),
        );
        metric(
            "voxels_changed_total",
            "counter",
            "Voxels whose solidity or colour changed.",
            get(&self.voxels_changed),
        );
        metric(
            "deltas_sent_total",
            "counter",
            "Delta frames queued to clients.",
            get(&self.deltas_sent),
        );
        metric(
            "sync_batches_sent_total",
            "counter",
            "Sync batch frames queued to clients.",
            get(&self.sync_batches_sent),
        );
        metric(
            "bytes_out_total",
            "counter",
            "Websocket payload bytes sent.",
            get(&self.bytes_out),
        );
        metric(
            "bytes_in_total",
            "counter",
            "Websocket payload bytes received.",
            get(&self.bytes_in),
        );
        metric(
            "resyncs_total",
            "counter",
            "Clients whose queue overflowed and were resynced.",
            get(&self.resyncs),
        );
        metric(
            "rejected_frames_total",
            "counter",
            "Malformed or oversized frames (the connection is closed).",
            get(&self.rejected_frames),
        );
        metric(
            "snapshots_total",
            "counter",
            "Scene snapshots written.",
            get(&self.snapshots),
        );
        let _ = writeln!(
            out,
            "# HELP brickcast_log_commit_seconds Durable edit-log commit latency."
        );
        let _ = writeln!(out, "# TYPE brickcast_log_commit_seconds histogram");
        let mut cumulative = 0;
        for (bound, bucket) in COMMIT_BUCKETS_US.iter().zip(&self.commit_buckets) {
            cumulative += get(bucket);
            let _ = writeln!(
                out,
                "brickcast_log_commit_seconds_bucket{{le=\"{}\"}} {cumulative}",
                *bound as f64 / 1e6
            );
        }
        let count = get(&self.commits);
        let _ = writeln!(
            out,
            "brickcast_log_commit_seconds_bucket{{le=\"+Inf\"}} {count}"
        );
        let _ = writeln!(
            out,
            "brickcast_log_commit_seconds_sum {}",
            get(&self.commit_sum_us) as f64 / 1e6
        );
        let _ = writeln!(out, "brickcast_log_commit_seconds_count {count}");
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_is_cumulative() {
        let m = Metrics::default();
        m.observe_commit(Duration::from_micros(90));
        m.observe_commit(Duration::from_micros(3_000));
        m.observe_commit(Duration::from_secs(5));
        let text = m.render();
        assert!(
            text.contains("brickcast_log_commit_seconds_bucket{le=\"0.0001\"} 1"),
            "{text}"
        );
        assert!(text.contains("brickcast_log_commit_seconds_bucket{le=\"0.005\"} 2"));
        assert!(text.contains("brickcast_log_commit_seconds_bucket{le=\"+Inf\"} 3"));
        assert!(text.contains("brickcast_log_commit_seconds_count 3"));
    }
}
