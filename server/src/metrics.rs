//! Server counters, exported at `GET /metrics` in the Prometheus text format.
//!
//! Plain atomics written from the scene owners and sessions (one relaxed add per event); a
//! scrape reads them into a `prometheus-client` collector ([`crate::exposition`]), which
//! writes the text.
//!
//! Besides events, the owners and sessions account for their time per phase (decode, apply,
//! commit, encode, send, ...), so "where does the time go" under load is answered by two scrapes
//! of `/metrics` rather than by a profiler (`brickcast load` prints the breakdown).

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

use brickcast_protocol::wire::ServerMsg;

use crate::exposition::{Exposition, Value};

/// A histogram's bucket bounds, in microseconds.
pub trait Buckets {
    const US: &'static [u64];
}

/// Durable log commits: 100 µs to 1 s.
#[derive(Debug)]
pub struct CommitBuckets;

impl Buckets for CommitBuckets {
    const US: &'static [u64] = &[
        100, 250, 500, 1_000, 2_500, 5_000, 10_000, 25_000, 50_000, 100_000, 250_000, 1_000_000,
    ];
}

/// Owner turns: 1 ms to 10 s.
#[derive(Debug)]
pub struct TurnBuckets;

impl Buckets for TurnBuckets {
    const US: &'static [u64] = &[
        1_000, 2_500, 5_000, 10_000, 25_000, 50_000, 100_000, 250_000, 500_000, 1_000_000,
        2_500_000, 10_000_000,
    ];
}

/// A latency histogram with fixed buckets.
#[derive(Debug)]
pub struct Histogram<B: Buckets> {
    buckets: Vec<AtomicU64>,
    count: AtomicU64,
    sum_us: AtomicU64,
    kind: std::marker::PhantomData<B>,
}

impl<B: Buckets> Default for Histogram<B> {
    fn default() -> Self {
        Histogram {
            buckets: B::US.iter().map(|_| AtomicU64::new(0)).collect(),
            count: AtomicU64::new(0),
            sum_us: AtomicU64::new(0),
            kind: std::marker::PhantomData,
        }
    }
}

impl<B: Buckets> Histogram<B> {
    /// Records one observation.
    pub fn observe(&self, took: Duration) {
        let us = took.as_micros().min(u128::from(u64::MAX)) as u64;
        self.count.fetch_add(1, Relaxed);
        self.sum_us.fetch_add(us, Relaxed);
        if let Some(i) = B::US.iter().position(|&b| us <= b) {
            self.buckets[i].fetch_add(1, Relaxed);
        }
    }

    /// Observations so far.
    pub fn count(&self) -> u64 {
        self.count.load(Relaxed)
    }

    /// The histogram as one scrape's value (seconds).
    pub fn value(&self) -> Value {
        let mut buckets: Vec<(f64, u64)> = B::US
            .iter()
            .zip(&self.buckets)
            .map(|(bound, n)| (*bound as f64 / 1e6, n.load(Relaxed)))
            .collect();
        // Read last: the count includes every bucket read above, and what is over the top bound.
        let count = self.count();
        let counted: u64 = buckets.iter().map(|b| b.1).sum();
        buckets.push((f64::MAX, count.saturating_sub(counted)));
        let sum = self.sum_us.load(Relaxed) as f64 / 1e6;
        Value::Histogram {
            buckets,
            sum,
            count: count.max(counted),
        }
    }
}

/// The phases of a scene owner's turn whose wall time is accounted for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OwnerPhase {
    /// Waiting for commands (idle).
    Wait,
    /// Applying edit ops to the map (including ray tracing and validation).
    Apply,
    /// The durable log commit (redb, fsync).
    Commit,
    /// Encoding acks and queueing them.
    Ack,
    /// Building and compressing the delta frames of a turn.
    Encode,
    /// Queueing delta frames to every subscriber.
    Fanout,
    /// Encoding and queueing sync and resync batches.
    Sync,
    /// Following cameras: working sets retargeted as their eyes move (rules, plans, costs).
    Follow,
    /// Writing snapshots.
    Snapshot,
}

impl OwnerPhase {
    pub const ALL: [OwnerPhase; 9] = [
        OwnerPhase::Wait,
        OwnerPhase::Apply,
        OwnerPhase::Commit,
        OwnerPhase::Ack,
        OwnerPhase::Encode,
        OwnerPhase::Fanout,
        OwnerPhase::Sync,
        OwnerPhase::Follow,
        OwnerPhase::Snapshot,
    ];

    pub fn name(self) -> &'static str {
        match self {
            OwnerPhase::Wait => "wait",
            OwnerPhase::Apply => "apply",
            OwnerPhase::Commit => "commit",
            OwnerPhase::Ack => "ack",
            OwnerPhase::Encode => "encode",
            OwnerPhase::Fanout => "fanout",
            OwnerPhase::Sync => "sync",
            OwnerPhase::Follow => "follow",
            OwnerPhase::Snapshot => "snapshot",
        }
    }
}

/// The phases of a session whose time is accounted for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SessionPhase {
    /// Decoding client frames (and checking them).
    Decode,
    /// Writing frames to the websocket, flushes included (wall time: a full socket counts).
    Send,
}

impl SessionPhase {
    pub const ALL: [SessionPhase; 2] = [SessionPhase::Decode, SessionPhase::Send];

    pub fn name(self) -> &'static str {
        match self {
            SessionPhase::Decode => "decode",
            SessionPhase::Send => "send",
        }
    }
}

/// Why reading a client's websocket failed, as counted in `brickcast_read_errors_total`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadError {
    /// A frame or message over the size the server accepts.
    TooLarge,
    /// The bytes broke the websocket protocol (bad opcode, masking, control frame, ...).
    Protocol,
    /// A text frame that is not UTF-8.
    Utf8,
    /// The connection failed underneath (reset, timeout).
    Io,
    /// Anything else the websocket layer reports.
    Other,
}

impl ReadError {
    pub const ALL: [ReadError; 5] = [
        ReadError::TooLarge,
        ReadError::Protocol,
        ReadError::Utf8,
        ReadError::Io,
        ReadError::Other,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ReadError::TooLarge => "too_large",
            ReadError::Protocol => "protocol",
            ReadError::Utf8 => "utf8",
            ReadError::Io => "io",
            ReadError::Other => "other",
        }
    }
}

/// Every counter the server exports, shared by the scene owners and the sessions in an `Arc`.
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
    /// Edit messages refused whole for asking more work than one message may.
    pub edits_over_budget: AtomicU64,
    /// Sessions cut off because their client stopped reading.
    pub stalled_disconnects: AtomicU64,
    /// Times a session stopped reading its client until its replies were written.
    pub reads_paused: AtomicU64,
    /// Scene thumbnails drawn (requests that found a fresh one, or waited for one being drawn,
    /// do not count).
    pub thumbnails_rendered: AtomicU64,
    /// Connections refused by the connection limits (total or per address).
    pub refused_connections: AtomicU64,
    /// Clients whose chosen id was over their address's allowance (`crate::ids`): served
    /// under a connection-lived id instead.
    pub ids_over_allowance: AtomicU64,
    /// Camera updates forwarded to scene owners (after the per-session throttle).
    pub camera_updates: AtomicU64,
    /// Presence frames queued, their bytes, and frames skipped for a long queue.
    pub presence_frames: AtomicU64,
    pub presence_bytes: AtomicU64,
    pub presence_skipped: AtomicU64,
    /// Presence messages from clients, and those refused (bad numbers, too fast).
    pub presence_updates: AtomicU64,
    pub presence_refused: AtomicU64,
    /// Cluster: presence messages this node published to the other nodes, and messages (or
    /// entries in them) from other nodes it could not use.
    pub presence_relayed: AtomicU64,
    pub presence_relay_refused: AtomicU64,
    /// Undo and redo requests applied (a step was taken from a stack), refused, and the voxels
    /// they restored or kept.
    pub undos: AtomicU64,
    pub redos: AtomicU64,
    pub history_refused: AtomicU64,
    pub undo_voxels_restored: AtomicU64,
    pub undo_voxels_kept: AtomicU64,
    /// Undos and redos of large steps planned across turns (`scene/undo_job.rs`).
    pub undos_sliced: AtomicU64,
    /// Heavy edits planned across turns (`scene/edit_job.rs`).
    pub edits_sliced: AtomicU64,
    pub commits: AtomicU64,
    pub snapshots: AtomicU64,
    /// Cluster: edits and undos this node's sessions forwarded to scene owners and got an
    /// answer for; turns applied from another owner's log; leases taken and lost.
    pub edits_forwarded: AtomicU64,
    pub turns_replicated: AtomicU64,
    pub takeovers: AtomicU64,
    pub stepdowns: AtomicU64,
    /// Cluster: scenes this node opened because someone asked for them, and closed after
    /// nobody here used them for a while (see `crate::served`).
    pub scene_opens: AtomicU64,
    pub scene_closes: AtomicU64,
    commit: Histogram<CommitBuckets>,
    /// How long each owner turn held the scene (a turn that applied, planned or sent
    /// anything; waiting for commands is not counted): what anyone's edit may wait behind.
    pub turns: Histogram<TurnBuckets>,
    /// Owner turns (one group commit each, when they carried edits).
    pub owner_turns: AtomicU64,
    owner_ns: [AtomicU64; OwnerPhase::ALL.len()],
    session_ns: [AtomicU64; SessionPhase::ALL.len()],
    /// Replies that could not be encoded, per message kind ([`ServerMsg::KINDS`]).
    unencodable: [AtomicU64; ServerMsg::KINDS.len()],
    /// Websocket read failures, per [`ReadError`].
    read_errors: [AtomicU64; ReadError::ALL.len()],
}

impl Metrics {
    pub fn add(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Relaxed);
    }

    /// Adds wall time to an owner phase.
    pub fn owner_time(&self, phase: OwnerPhase, took: Duration) {
        self.owner_ns[phase as usize].fetch_add(nanos(took), Relaxed);
    }

    /// Adds time to a session phase.
    pub fn session_time(&self, phase: SessionPhase, took: Duration) {
        self.session_ns[phase as usize].fetch_add(nanos(took), Relaxed);
    }

    /// Counts a reply of kind `kind` (one of [`ServerMsg::KINDS`]) that could not be encoded.
    pub fn count_unencodable(&self, kind: &str) {
        if let Some(i) = ServerMsg::KINDS.iter().position(|k| *k == kind) {
            self.unencodable[i].fetch_add(1, Relaxed);
        }
    }

    /// Counts one failed websocket read.
    pub fn count_read_error(&self, kind: ReadError) {
        self.read_errors[kind as usize].fetch_add(1, Relaxed);
    }

    /// Records one durable commit of the edit log.
    pub fn observe_commit(&self, took: Duration) {
        self.commits.fetch_add(1, Relaxed);
        self.commit.observe(took);
    }

    /// Every metric of this struct, read once, added to a scrape (see [`crate::exposition`]).
    pub fn expose(&self, x: &mut Exposition) {
        let get = |c: &AtomicU64| c.load(Relaxed);
        x.one(
            "connected_clients",
            "Websocket sessions currently open.",
            Value::gauge(get(&self.connected_clients)),
        );
        x.one(
            "edit_batches",
            "Edit messages that applied at least one op.",
            Value::Counter(get(&self.edit_batches)),
        );
        x.one(
            "edits_applied",
            "Edit ops applied.",
            Value::Counter(get(&self.ops_applied)),
        );
        x.one(
            "edits_rejected",
            "Edit ops rejected (bounds, limits, role, rate).",
            Value::Counter(get(&self.ops_rejected)),
        );
        x.one(
            "voxels_changed",
            "Voxels whose solidity or colour changed.",
            Value::Counter(get(&self.voxels_changed)),
        );
        x.one(
            "deltas_sent",
            "Delta frames queued to clients.",
            Value::Counter(get(&self.deltas_sent)),
        );
        x.one(
            "sync_batches_sent",
            "Sync batch frames queued to clients.",
            Value::Counter(get(&self.sync_batches_sent)),
        );
        x.one(
            "bytes_out",
            "Websocket payload bytes sent.",
            Value::Counter(get(&self.bytes_out)),
        );
        x.one(
            "bytes_in",
            "Websocket payload bytes received.",
            Value::Counter(get(&self.bytes_in)),
        );
        x.one(
            "resyncs",
            "Clients whose queue overflowed and were resynced.",
            Value::Counter(get(&self.resyncs)),
        );
        x.one(
            "rejected_frames",
            "Malformed or oversized frames (the connection is closed).",
            Value::Counter(get(&self.rejected_frames)),
        );
        x.one(
            "ids_over_allowance",
            "Clients whose chosen user id was over their address's allowance (served under a connection-lived id).",
            Value::Counter(get(&self.ids_over_allowance)),
        );
        x.one(
            "edits_over_budget",
            "Edit messages refused whole for asking more work than one message may.",
            Value::Counter(get(&self.edits_over_budget)),
        );
        x.one(
            "stalled_disconnects",
            "Sessions cut off because their client stopped reading.",
            Value::Counter(get(&self.stalled_disconnects)),
        );
        x.one(
            "reads_paused",
            "Times a session stopped reading a client that sent faster than it read its replies.",
            Value::Counter(get(&self.reads_paused)),
        );
        x.one(
            "thumbnails_rendered",
            "Scene thumbnails drawn by scene owners.",
            Value::Counter(get(&self.thumbnails_rendered)),
        );
        x.one(
            "refused_connections",
            "Websocket connections refused by the connection limits.",
            Value::Counter(get(&self.refused_connections)),
        );
        x.one(
            "camera_updates",
            "Camera updates forwarded to scene owners (at most one per session per 50 ms).",
            Value::Counter(get(&self.camera_updates)),
        );
        for (name, help, value) in [
            (
                "cluster_edits_forwarded",
                "Edits and undos forwarded to the scene's owner and answered (cluster).",
                &self.edits_forwarded,
            ),
            (
                "cluster_turns_replicated",
                "Turns applied from another node's log (cluster).",
                &self.turns_replicated,
            ),
            (
                "cluster_takeovers",
                "Scene leases this node took and claimed the log with (cluster).",
                &self.takeovers,
            ),
            (
                "cluster_stepdowns",
                "Times this node stopped ordering a scene's edits: lease lost, another node appended, or an append refused (cluster).",
                &self.stepdowns,
            ),
            (
                "cluster_scene_opens",
                "Scenes this node loaded from the cluster because a client or page asked for them (cluster).",
                &self.scene_opens,
            ),
            (
                "cluster_scene_closes",
                "Scenes this node closed after nobody here used them for --close-idle (cluster).",
                &self.scene_closes,
            ),
            (
                "presence_frames",
                "Presence frames queued to clients.",
                &self.presence_frames,
            ),
            (
                "presence_bytes",
                "Bytes of presence frames queued to clients.",
                &self.presence_bytes,
            ),
            (
                "presence_skipped",
                "Presence frames not queued to a client whose queue was long (it gets a full frame later).",
                &self.presence_skipped,
            ),
            (
                "presence_updates",
                "Presence messages accepted from clients.",
                &self.presence_updates,
            ),
            (
                "presence_refused",
                "Presence and rename messages refused (bad numbers or names, too fast).",
                &self.presence_refused,
            ),
            (
                "cluster_presence_relayed",
                "Presence messages published to the other nodes (cluster).",
                &self.presence_relayed,
            ),
            (
                "cluster_presence_refused",
                "Presence messages or entries from other nodes that could not be read or were out of range (cluster).",
                &self.presence_relay_refused,
            ),
            ("undos", "Undo steps applied.", &self.undos),
            ("redos", "Redo steps applied.", &self.redos),
            (
                "history_refused",
                "Undo and redo requests refused (nothing to undo or redo, viewers, too fast).",
                &self.history_refused,
            ),
            (
                "undo_voxels_restored",
                "Voxels undo and redo put back.",
                &self.undo_voxels_restored,
            ),
            (
                "undo_voxels_kept",
                "Voxels undo and redo left alone because someone changed them since.",
                &self.undo_voxels_kept,
            ),
            (
                "undos_sliced",
                "Undos and redos of large steps planned across turns and applied in one.",
                &self.undos_sliced,
            ),
            (
                "edits_sliced",
                "Heavy edits planned across turns and applied in one.",
                &self.edits_sliced,
            ),
        ] {
            x.one(name, help, Value::Counter(get(value)));
        }
        x.one(
            "snapshots",
            "Scene snapshots written.",
            Value::Counter(get(&self.snapshots)),
        );
        x.one(
            "owner_turns",
            "Scene owner turns (each drains the queued commands and commits once).",
            Value::Counter(get(&self.owner_turns)),
        );
        x.one(
            "log_commit_seconds",
            "Durable edit-log commit latency.",
            self.commit.value(),
        );
        x.one(
            "owner_turn_seconds",
            "How long each scene owner turn held its scene (waiting for commands not counted).",
            self.turns.value(),
        );
        x.labelled(
            "frames_unencodable",
            "Replies that could not be encoded (a server bug; the session is closed with an Internal error).",
            "message",
            ServerMsg::KINDS
                .iter()
                .zip(&self.unencodable)
                .map(|(kind, n)| (kind.to_string(), Value::Counter(get(n)))),
        );
        x.labelled(
            "read_errors",
            "Websocket reads that failed, by cause.",
            "kind",
            ReadError::ALL.iter().map(|k| {
                let n = get(&self.read_errors[*k as usize]);
                (k.name().to_string(), Value::Counter(n))
            }),
        );
        let seconds = |ns: &AtomicU64| Value::Seconds(get(ns) as f64 / 1e9);
        x.labelled(
            "owner_seconds",
            "Wall time scene owners spent per phase.",
            "phase",
            OwnerPhase::ALL
                .iter()
                .map(|p| (p.name().to_string(), seconds(&self.owner_ns[*p as usize]))),
        );
        x.labelled(
            "session_seconds",
            "Time sessions spent decoding frames and writing them.",
            "phase",
            SessionPhase::ALL
                .iter()
                .map(|p| (p.name().to_string(), seconds(&self.session_ns[*p as usize]))),
        );
    }

    /// The text of [`Metrics::expose`] alone (tests; the server adds its gauges).
    pub fn render(&self) -> String {
        let mut x = Exposition::default();
        self.expose(&mut x);
        x.encode()
    }
}

/// The process's resident memory, from `/proc/self/statm` (Linux; `None` elsewhere).
pub fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    // Every Linux platform brickcast runs on has 4 KiB pages.
    Some(pages * 4096)
}

/// CPU time (user + system) the server process has used, in seconds, from `/proc/self/stat`.
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    // SAFETY: sysconf only reads a configuration value.
    let per_second = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (per_second > 0).then(|| ticks as f64 / per_second as f64)
}

fn nanos(d: Duration) -> u64 {
    d.as_nanos().min(u128::from(u64::MAX)) as u64
}

/// Times consecutive phases with one clock read per phase boundary.
pub struct PhaseClock {
    at: std::time::Instant,
}

impl PhaseClock {
    pub fn start() -> PhaseClock {
        PhaseClock {
            at: std::time::Instant::now(),
        }
    }

    /// Charges the time since the last mark to `phase`.
    pub fn mark(&mut self, metrics: &Metrics, phase: OwnerPhase) {
        let now = std::time::Instant::now();
        metrics.owner_time(phase, now.duration_since(self.at));
        self.at = now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The value of each sample line (`name{labels} value`) of a scrape.
    fn samples(text: &str) -> std::collections::HashMap<String, f64> {
        text.lines()
            .filter(|l| !l.starts_with('#'))
            .filter_map(|l| {
                let (name, value) = l.rsplit_once(' ')?;
                Some((name.to_string(), value.parse().ok()?))
            })
            .collect()
    }

    #[test]
    fn histogram_is_cumulative() {
        let m = Metrics::default();
        m.observe_commit(Duration::from_micros(90));
        m.observe_commit(Duration::from_micros(3_000));
        m.observe_commit(Duration::from_secs(5));
        let text = m.render();
        let got = samples(&text);
        for (series, want) in [
            ("brickcast_log_commit_seconds_bucket{le=\"0.0001\"}", 1.0),
            ("brickcast_log_commit_seconds_bucket{le=\"0.005\"}", 2.0),
            ("brickcast_log_commit_seconds_bucket{le=\"1.0\"}", 2.0),
            ("brickcast_log_commit_seconds_bucket{le=\"+Inf\"}", 3.0),
            ("brickcast_log_commit_seconds_count", 3.0),
            ("brickcast_log_commit_seconds_sum", 5.00309),
        ] {
            assert_eq!(got.get(series), Some(&want), "{series}:\n{text}");
        }
        assert!(text.contains("# TYPE brickcast_log_commit_seconds histogram\n"));
        assert!(text.ends_with("# EOF\n"), "{text}");
    }

    #[test]
    fn phase_times_are_exported_per_phase() {
        let m = Metrics::default();
        m.owner_time(OwnerPhase::Apply, Duration::from_millis(1500));
        m.owner_time(OwnerPhase::Apply, Duration::from_millis(250));
        m.owner_time(OwnerPhase::Fanout, Duration::from_micros(5));
        m.session_time(SessionPhase::Decode, Duration::from_millis(20));
        let text = m.render();
        let got = samples(&text);
        for (series, want) in [
            ("brickcast_owner_seconds_total{phase=\"apply\"}", 1.75),
            ("brickcast_owner_seconds_total{phase=\"fanout\"}", 0.000005),
            ("brickcast_owner_seconds_total{phase=\"commit\"}", 0.0),
            ("brickcast_session_seconds_total{phase=\"decode\"}", 0.02),
            ("brickcast_session_seconds_total{phase=\"send\"}", 0.0),
        ] {
            assert_eq!(got.get(series), Some(&want), "{series}:\n{text}");
        }
        assert!(text.contains("# TYPE brickcast_owner_seconds counter\n"));
        let mut clock = PhaseClock::start();
        std::thread::sleep(Duration::from_millis(2));
        clock.mark(&m, OwnerPhase::Wait);
        assert!(m.owner_ns[OwnerPhase::Wait as usize].load(Relaxed) >= 2_000_000);
    }
}
