//! Deterministic simulation of the cluster: several node processes, each the real scene owner
//! over the real `JetLog`, with the real lease, follower, forwarding and name tasks, on a
//! simulated JetStream (`jet.rs`) that loses, delays and duplicates messages, goes down,
//! loses the answers of appends that landed, and holds garbage on a log subject when told to.
//! In the spirit of TigerBeetle's VOPR and FoundationDB's simulator: one seed drives a random
//! history of faults through the code the nodes run, and checks after every step:
//!
//! * **no acknowledged edit lost**: every edit a client saw acknowledged at sequence `s` is the
//!   log's record `s`;
//! * **none applied twice**: no edit is in the log twice, however often it was retried;
//! * **never two appenders**: every turn that orders edits comes from the node whose claim
//!   (marker) is the last before it, and the log's sequence goes on by one;
//! * **replicas are the log**: every node serving the scene holds exactly the log's scene at
//!   its sequence, a second copy of the same log on one node too (what a node serves while a
//!   rename reaches it: the old name and the new, one lease key, one node name);
//! * **one process per name**: two processes of one node name never both run for long;
//! * **liveness**: once the faults heal (pauses end, the dead restart, an operator repairs a
//!   log with garbage in it), every node has an edit acknowledged within a bound, and every
//!   replica reaches the log's end;
//! * **clean stops**: SIGTERM of the node that owns the scene leaves a snapshot of its last
//!   edit, and no stop panics.
//!
//! Each process runs on a tokio runtime of its own with a paused clock; the simulation moves
//! the world's time in steps of a few tens of milliseconds and runs each process up to it in a
//! fixed order. A paused process (SIGSTOP) is not run: when it wakes, its clock has jumped, as
//! a real one's does. Some processes' clocks run a little fast or slow. Randomness comes from
//! seeded ChaCha generators. A failing seed prints its last actions and replays exactly with
//! `BRICKCAST_CLUSTER_SIM_SEED=N cargo test -p brickcast-server cluster::sim`.

mod jet;
mod process;
mod tests;

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use brickcast_protocol::{BrickMap, BrushMode, Colour};
use bytes::Bytes;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use self::jet::{ProcessClock, SimJet, World};
use self::process::{EditKey, Process, SCENE, Status};
use crate::cluster::log::decode_turn;
use crate::cluster::repair::Repaired;
use crate::cluster::{ClusterError, catalog, repair, snapshot};
use crate::record::LogRecord;
use crate::scene::OwnerConfig;

/// Node names.
const NAMES: [&str; 3] = ["n0", "n1", "n2"];
/// How long faults are injected.
const CHAOS: Duration = Duration::from_secs(30);
/// Once the faults heal, every node must have an edit acknowledged within this.
const LIVENESS: Duration = Duration::from_secs(30);
/// ...and every replica must reach the log's end within this after that.
const CONVERGENCE: Duration = Duration::from_secs(15);
/// Two processes of one name may both run this long (the old one must notice and stop).
const ONE_NAME: Duration = Duration::from_secs(4);
/// A step whose world time moved on by more than this while one process blocked the
/// simulation's thread froze the others meanwhile (see [`Sim::step`]).
const STEP_JUMP: Duration = Duration::from_millis(100);
/// Actions kept for the report of a failing seed.
const TRACE_LEN: usize = 120;

pub type Failure = String;

macro_rules! check {
    ($cond:expr, $($fmt:tt)+) => {
        if !$cond {
            return Err(format!($($fmt)+));
        }
    };
}

/// What one seed did, summed over seeds for the report.
#[derive(Debug, Default, Clone, Copy)]
pub struct SimStats {
    pub steps: u64,
    pub acks: u64,
    pub turns: u64,
    pub claims: u64,
    pub pauses: u64,
    pub lease_window_pauses: u64,
    pub kills: u64,
    pub stops: u64,
    pub name_takeovers: u64,
    pub outages: u64,
    pub network_faults: u64,
    pub garbage: u64,
    pub repairs: u64,
    pub gave_up: u64,
    pub second_names: u64,
}

impl crate::sim::seeds::Tally for SimStats {
    fn add(&mut self, o: &SimStats) {
        self.steps += o.steps;
        self.acks += o.acks;
        self.turns += o.turns;
        self.claims += o.claims;
        self.pauses += o.pauses;
        self.lease_window_pauses += o.lease_window_pauses;
        self.kills += o.kills;
        self.stops += o.stops;
        self.name_takeovers += o.name_takeovers;
        self.outages += o.outages;
        self.network_faults += o.network_faults;
        self.garbage += o.garbage;
        self.repairs += o.repairs;
        self.gave_up += o.gave_up;
        self.second_names += o.second_names;
    }
}

/// The log as the checks read it: every append in order, replayed onto a model.
struct Truth {
    scanned: usize,
    model: BrickMap,
    seq: u64,
    /// The model's hash after each sequence.
    hashes: Vec<u64>,
    /// Who appended the last marker (the node that may order).
    claimer: Option<String>,
    /// Where each edit is in the log.
    in_log: BTreeMap<EditKey, u64>,
    /// Messages that are not turns, not yet repaired.
    garbage: usize,
}

impl Truth {
    fn new(map: BrickMap) -> Truth {
        let hash = map.content_hash();
        Truth {
            scanned: 0,
            model: map,
            seq: 0,
            hashes: vec![hash],
            claimer: None,
            in_log: BTreeMap::new(),
            garbage: 0,
        }
    }

    /// Reads the appends made since the last look.
    fn scan(&mut self, world: &World, stats: &mut SimStats) -> Result<(), Failure> {
        let Some(history) = world.history.get(SCENE) else {
            return Ok(());
        };
        let limits = LogRecord::replay_limits();
        for (pos, bytes) in &history.appends[self.scanned..] {
            self.scanned += 1;
            let Ok(turn) = decode_turn(bytes) else {
                self.garbage += 1;
                continue;
            };
            if turn.is_marker() {
                stats.claims += 1;
                self.claimer = Some(turn.node.clone());
                continue;
            }
            stats.turns += 1;
            check!(
                self.claimer.as_deref() == Some(turn.node.as_str()),
                "two appenders: log message {pos} was appended by {} after {:?} claimed the log",
                turn.node,
                self.claimer
            );
            for (s, record) in &turn.records {
                check!(
                    *s == self.seq + 1,
                    "log message {pos} holds sequence {s} after {}: a fork, a gap or a repeat",
                    self.seq
                );
                let record = LogRecord::decode(record)
                    .map_err(|e| format!("log entry {s} does not decode: {e}"))?;
                if let LogRecord::Ops { user, ops } = &record {
                    for op in ops {
                        if let brickcast_protocol::wire::EditOp::Set { pos: p, colour } = op {
                            let k = (p[0] + 32 * p[2]) as u16;
                            let key = EditKey {
                                user: *user,
                                k: u32::from(k),
                            };
                            check!(
                                key.pos() == *p && key.colour() == *colour,
                                "log entry {s} holds an edit no client made: {op:?}"
                            );
                            if let Some(first) = self.in_log.insert(key, *s) {
                                return Err(format!(
                                    "edit {key:?} applied twice: at sequences {first} and {s}"
                                ));
                            }
                        }
                    }
                }
                self.model.set_sequence(*s);
                record
                    .replay(&mut self.model, &limits)
                    .map_err(|e| format!("log entry {s} does not replay: {e}"))?;
                self.seq = *s;
                self.hashes.push(self.model.content_hash());
            }
        }
        Ok(())
    }
}

/// The operator's seat: a runtime of its own to create the scene, repair it and read the
/// snapshots with.
struct Operator {
    rt: tokio::runtime::Runtime,
    jet: SimJet,
    repair: Option<tokio::task::JoinHandle<Result<Repaired, ClusterError>>>,
}

impl Operator {
    /// Brings the operator's clock to world time `now` (it is only run when used).
    fn catch_up(&self, now: Duration) {
        let until = self.jet.clock.local(now);
        self.rt
            .block_on(async move { tokio::time::sleep_until(until).await });
    }
}

/// One simulated cluster.
pub struct Sim {
    rng: ChaCha8Rng,
    world: Arc<Mutex<World>>,
    now: Duration,
    procs: Vec<Process>,
    next_id: u64,
    truth: Truth,
    /// Every edit a client saw acknowledged, and its sequence.
    acked: BTreeMap<EditKey, u64>,
    trace: VecDeque<String>,
    pub stats: SimStats,
    operator: Operator,
    config: OwnerConfig,
    /// Names to start again, and when.
    restarts: Vec<(Duration, &'static str)>,
    /// Since when two processes of a name both run.
    doubled: BTreeMap<String, Duration>,
    /// When faults of the network end.
    network_until: Duration,
    /// Since when the world has been down or faulty, for the stop check.
    last_trouble: Duration,
}

fn initial_scene() -> BrickMap {
    let mut map = BrickMap::new([32, 32, 32]).expect("a scene");
    map.fill_box(
        [0, 0, 0],
        [31, 1, 31],
        BrushMode::Fill,
        Colour::from_rgb8(90, 140, 60),
    );
    map
}

impl Sim {
    pub fn new(seed: u64) -> Result<Sim, Failure> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let world = Arc::new(Mutex::new(World::new(ChaCha8Rng::seed_from_u64(
            seed ^ 0x005e_ed0f_0a75,
        ))));
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .start_paused(true)
            .build()
            .map_err(|e| e.to_string())?;
        let base = rt.block_on(async { tokio::time::Instant::now() });
        let jet = SimJet {
            world: world.clone(),
            process: 0,
            clock: Arc::new(ProcessClock { base, rate: 1.0 }),
        };
        let map = initial_scene();
        rt.block_on(catalog::create_scene(&jet, SCENE, &map, false))
            .map_err(|e| format!("the scene could not be created: {e}"))?;
        let config = OwnerConfig {
            snapshot_every: Duration::from_millis(rng.random_range(1500..6000)),
            snapshot_replay_budget: rng.random_range(20..400),
            ..OwnerConfig::default()
        };
        let mut sim = Sim {
            rng,
            world,
            now: Duration::ZERO,
            procs: Vec::new(),
            next_id: 1,
            acked: BTreeMap::new(),
            truth: Truth::new(map),
            trace: VecDeque::new(),
            stats: SimStats::default(),
            operator: Operator {
                rt,
                jet,
                repair: None,
            },
            config,
            restarts: Vec::new(),
            doubled: BTreeMap::new(),
            network_until: Duration::ZERO,
            last_trouble: Duration::ZERO,
        };
        for name in NAMES {
            sim.start(name);
        }
        Ok(sim)
    }

    fn note(&mut self, what: String) {
        if std::env::var_os("BRICKCAST_CLUSTER_SIM_VERBOSE").is_some() {
            eprintln!("[{:>8.3}s] {what}", self.now.as_secs_f64());
        }
        if self.trace.len() == TRACE_LEN {
            self.trace.pop_front();
        }
        self.trace
            .push_back(format!("[{:>8.3}s] {what}", self.now.as_secs_f64()));
    }

    pub fn trace(&self) -> String {
        self.trace.iter().cloned().collect::<Vec<_>>().join("\n")
    }

    fn start(&mut self, name: &'static str) {
        let id = self.next_id;
        self.next_id += 1;
        let rate = if self.rng.random_bool(0.3) {
            self.rng.random_range(0.97..1.03)
        } else {
            1.0
        };
        let p = Process::start(
            self.world.clone(),
            id,
            name,
            self.now,
            rate,
            self.config.clone(),
        );
        self.note(format!("start {name}#{id} (clock x{rate:.3})"));
        self.procs.push(p);
    }

    fn alive(&self) -> Vec<usize> {
        (0..self.procs.len())
            .filter(|&i| self.procs[i].alive() && self.procs[i].status != Status::Booting)
            .collect()
    }

    fn pick_alive(&mut self) -> Option<usize> {
        let alive: Vec<usize> = self
            .alive()
            .into_iter()
            .filter(|&i| !self.procs[i].paused(self.now) && self.procs[i].status == Status::Up)
            .collect();
        if alive.is_empty() {
            return None;
        }
        Some(alive[self.rng.random_range(0..alive.len())])
    }

    /// One random fault, now and then.
    fn chaos(&mut self) {
        if !self.rng.random_bool(0.03) {
            return;
        }
        match self.rng.random_range(0..100) {
            0..30 => {
                let Some(i) = self.pick_alive() else { return };
                // A third of the pauses end just under the lease's life: the owner's own
                // deadline has passed, its key has not expired.
                let pause = match self.rng.random_range(0..3) {
                    0 => {
                        self.stats.lease_window_pauses += 1;
                        Duration::from_millis(self.rng.random_range(2500..3000))
                    }
                    1 => Duration::from_millis(self.rng.random_range(100..2500)),
                    _ => Duration::from_millis(self.rng.random_range(3000..9000)),
                };
                self.stats.pauses += 1;
                let p = &mut self.procs[i];
                p.paused_until = Some(self.now + pause);
                let what = format!(
                    "pause {}#{} for {:.3}s{}",
                    p.name,
                    p.id,
                    pause.as_secs_f64(),
                    if p.leading() {
                        " (it owns the scene)"
                    } else {
                        ""
                    }
                );
                self.note(what);
            }
            30..42 => {
                let Some(i) = self.pick_alive() else { return };
                self.stats.kills += 1;
                self.procs[i].kill();
                let what = format!("SIGKILL {}#{}", self.procs[i].name, self.procs[i].id);
                self.note(what);
                self.restart_later(i);
            }
            42..52 => {
                let Some(i) = self.pick_alive() else { return };
                self.stats.stops += 1;
                self.sigterm(i);
                self.restart_later(i);
            }
            52..60 => {
                // Paused until its name expires, while a new process takes the name.
                let Some(i) = self.pick_alive() else { return };
                let pause = Duration::from_millis(self.rng.random_range(6500..9000));
                self.stats.name_takeovers += 1;
                self.procs[i].paused_until = Some(self.now + pause);
                let name = NAMES
                    .iter()
                    .find(|n| **n == self.procs[i].name)
                    .copied()
                    .expect("a name");
                let what = format!(
                    "pause {name}#{} for {:.3}s and start another {name} meanwhile",
                    self.procs[i].id,
                    pause.as_secs_f64()
                );
                self.note(what);
                self.restarts
                    .push((self.now + Duration::from_millis(500), name));
            }
            60..72 => {
                let down = Duration::from_millis(self.rng.random_range(300..5000));
                self.stats.outages += 1;
                let until = self.now + down;
                self.world
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .faults
                    .down_until = until;
                self.last_trouble = self.last_trouble.max(until);
                self.note(format!("NATS down for {:.3}s", down.as_secs_f64()));
            }
            72..92 => {
                let faults = jet::Faults {
                    down_until: Duration::ZERO,
                    loss: self.rng.random_range(0.0..0.3),
                    duplicate: self.rng.random_range(0.0..0.3),
                    delay: Duration::from_millis(self.rng.random_range(0..400)),
                    lost_acks: self.rng.random_range(0.0..0.3),
                };
                let lasting = Duration::from_millis(self.rng.random_range(500..6000));
                self.stats.network_faults += 1;
                self.note(format!(
                    "network faults for {:.3}s: {faults:?}",
                    lasting.as_secs_f64()
                ));
                let mut world = self.world.lock().unwrap_or_else(|e| e.into_inner());
                world.faults = jet::Faults {
                    down_until: world.faults.down_until,
                    ..faults
                };
                self.network_until = self.now + lasting;
                self.last_trouble = self.last_trouble.max(self.network_until);
            }
            92..95 => {
                self.stats.garbage += 1;
                let len = self.rng.random_range(1..40);
                let bytes: Vec<u8> = (0..len).map(|_| self.rng.random()).collect();
                let pos = self
                    .world
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .publish_unfenced(SCENE, Bytes::from(bytes));
                self.note(format!("garbage published on the log: message {pos}"));
            }
            95..99 => {
                // A rename reaching this node: the scene's log served under a second name
                // beside the first for a while, people editing through both.
                let Some(i) = self.pick_alive() else { return };
                if self.procs[i].has_second() {
                    return;
                }
                let lasting = Duration::from_millis(self.rng.random_range(1000..10000));
                self.stats.second_names += 1;
                self.procs[i].open_second(self.now + lasting);
                let what = format!(
                    "{}#{} serves the scene under a second name for {:.3}s",
                    self.procs[i].name,
                    self.procs[i].id,
                    lasting.as_secs_f64()
                );
                self.note(what);
            }
            _ => {}
        }
    }

    /// Starts the names whose restart is due (if no process of the name lives).
    fn restart_due(&mut self) {
        let due: Vec<&'static str> = self
            .restarts
            .iter()
            .filter(|(at, _)| *at <= self.now)
            .map(|(_, n)| *n)
            .collect();
        self.restarts.retain(|(at, _)| *at > self.now);
        for name in due {
            let running = self
                .procs
                .iter()
                .any(|p| p.name == name && p.alive() && !p.paused(self.now));
            if !running {
                self.start(name);
            }
        }
    }

    /// One step of the world: time moves, every process runs, everything is checked.
    pub fn step(&mut self, edit_chance: f64) -> Result<(), Failure> {
        self.stats.steps += 1;
        self.now += Duration::from_millis(self.rng.random_range(10..50));
        {
            let mut world = self.world.lock().unwrap_or_else(|e| e.into_inner());
            world.advance(self.now);
            if self.now >= self.network_until {
                let down_until = world.faults.down_until;
                world.faults = jet::Faults {
                    down_until,
                    ..Default::default()
                };
            }
            self.now = self.now.max(world.now);
        }
        self.restart_due();
        for i in 0..self.procs.len() {
            let was_paused =
                self.procs[i].paused_until.is_some() && !self.procs[i].paused(self.now);
            if was_paused {
                let what = format!("{}#{} wakes", self.procs[i].name, self.procs[i].id);
                self.note(what);
            }
            let events = self.procs[i].tick(self.now, edit_chance, &mut self.rng);
            for n in events.notes {
                self.note(n);
            }
            {
                let world = self.world.lock().unwrap_or_else(|e| e.into_inner());
                self.truth.scan(&world, &mut self.stats)?;
            }
            for (key, seq) in events.acks {
                self.stats.acks += 1;
                if std::env::var_os("BRICKCAST_CLUSTER_SIM_VERBOSE").is_some() {
                    let what = format!(
                        "ack {key:?} at {seq} on {}#{}",
                        self.procs[i].name, self.procs[i].id
                    );
                    self.note(what);
                }
                let logged = self.truth.in_log.get(&key).copied();
                check!(
                    logged == Some(seq),
                    "edit {key:?} was acknowledged at sequence {seq} but the log holds it at {logged:?}"
                );
                self.acked.insert(key, seq);
            }
            check!(
                events.rejected.is_empty(),
                "edits {:?} were acknowledged as not applied",
                events.rejected
            );
            self.stats.gave_up += events.gave_up.len() as u64;
            self.check_stop(i)?;
        }
        // Time in the world may have moved on while a process blocked.
        let world_now = self.world.lock().unwrap_or_else(|e| e.into_inner()).now;
        if world_now > self.now + STEP_JUMP {
            // One process blocked this thread (a boot waiting for NATS, an open) while the
            // world's time went on: the others were frozen meanwhile, as if paused, and had no
            // chance to notice anything. Two of one name are timed from here.
            for since in self.doubled.values_mut() {
                *since = world_now;
            }
        }
        self.now = self.now.max(world_now);
        self.check_replicas()?;
        self.check_names()?;
        Ok(())
    }

    /// Every serving replica holds the log's scene at its sequence.
    fn check_replicas(&self) -> Result<(), Failure> {
        for p in &self.procs {
            if !p.alive() {
                continue;
            }
            for (seq, hash) in p.replicas() {
                check!(
                    seq <= self.truth.seq,
                    "{}#{} is at sequence {seq}, past the log's {}",
                    p.name,
                    p.id,
                    self.truth.seq
                );
                check!(
                    self.truth.hashes[seq as usize] == hash,
                    "{}#{} at sequence {seq} differs from the log's scene there",
                    p.name,
                    p.id
                );
            }
        }
        Ok(())
    }

    /// Two processes of one name do not both run for long while NATS answers (a process can
    /// only learn that another took its name from NATS).
    fn check_names(&mut self) -> Result<(), Failure> {
        let down = self.world.lock().unwrap_or_else(|e| e.into_inner()).down();
        for name in NAMES {
            let running = self
                .procs
                .iter()
                .filter(|p| p.name == name && p.status == Status::Up && !p.paused(self.now))
                .count();
            if running < 2 || down {
                self.doubled.remove(name);
                continue;
            }
            let since = *self.doubled.entry(name.to_string()).or_insert(self.now);
            check!(
                self.now.saturating_sub(since) < ONE_NAME,
                "two processes named {name} have run side by side for {:?}",
                self.now.saturating_sub(since)
            );
        }
        Ok(())
    }

    /// A process stopped by SIGTERM while it owned the scene left a snapshot of its last
    /// edit (when NATS was well meanwhile).
    fn check_stop(&mut self, i: usize) -> Result<(), Failure> {
        let p = &mut self.procs[i];
        if p.status != Status::Exited("stopped".into()) {
            return Ok(());
        }
        let Some(seq) = p.stopped_leading.take() else {
            return Ok(());
        };
        let since = self.now.saturating_sub(Duration::from_secs(31));
        if self.last_trouble >= since {
            return Ok(());
        }
        self.operator.catch_up(self.now);
        let jet = self.operator.jet.clone();
        let newest = self
            .operator
            .rt
            .block_on(async move { snapshot::newest(&jet, SCENE).await });
        let what = format!("{}#{}", p.name, p.id);
        check!(
            newest.is_some_and(|(s, _, _)| s >= seq),
            "{what} stopped while it owned the scene at sequence {seq}, but the newest snapshot is {newest:?}"
        );
        Ok(())
    }

    /// The faults end: pauses end, network and server are well, the dead start again, and an
    /// operator repairs a log holding garbage.
    fn heal(&mut self) -> Result<(), Failure> {
        self.note("heal".into());
        {
            let mut world = self.world.lock().unwrap_or_else(|e| e.into_inner());
            world.faults = jet::Faults::default();
        }
        self.network_until = self.now;
        self.last_trouble = self.now;
        for p in &mut self.procs {
            if p.paused(self.now) {
                p.paused_until = Some(self.now);
            }
        }
        self.restarts.clear();
        for name in NAMES {
            if !self.procs.iter().any(|p| p.name == name && p.alive()) {
                self.start(name);
            }
        }
        if self.truth.garbage > 0 {
            self.stats.repairs += 1;
            self.operator.catch_up(self.now);
            let jet = self.operator.jet.clone();
            let task = self
                .operator
                .rt
                .spawn(async move { repair::repair(&jet, SCENE).await });
            self.operator.repair = Some(task);
            // The repair runs on the operator's clock while the nodes run on theirs.
            let deadline = self.now + Duration::from_secs(60);
            while self
                .operator
                .repair
                .as_ref()
                .is_some_and(|t| !t.is_finished())
            {
                check!(self.now < deadline, "the repair did not finish");
                self.operator.catch_up(self.now);
                self.step(0.0)?;
            }
            let task = self.operator.repair.take().expect("checked");
            let repaired = self
                .operator
                .rt
                .block_on(task)
                .map_err(|e| format!("the repair panicked: {e}"))?
                .map_err(|e| format!("the repair failed: {e}"))?;
            check!(
                repaired.dropped.len() >= self.truth.garbage.min(1),
                "the repair dropped nothing: {repaired:?}"
            );
            self.note(repaired.render().trim_end().to_string());
            self.truth.garbage = 0;
        }
        Ok(())
    }

    /// Every running process gets an edit acknowledged within [`LIVENESS`], then every replica
    /// reaches the log's end within [`CONVERGENCE`].
    fn settle(&mut self) -> Result<(), Failure> {
        let healed = self.now;
        // Edits made from now on count.
        let firsts: BTreeMap<u64, u32> = self
            .procs
            .iter()
            .flat_map(|p| p.clients().map(|c| (c.user, c.next_k)))
            .collect();
        // Every process running (now or later): whether one of its edits made since landed.
        let mut acked_after: BTreeMap<u64, bool> = BTreeMap::new();
        loop {
            self.step(0.3)?;
            for p in &self.procs {
                if p.status != Status::Up {
                    acked_after.remove(&p.id);
                    continue;
                }
                let acked = p.clients().any(|c| {
                    let first = firsts.get(&c.user).copied().unwrap_or(0);
                    let from = EditKey {
                        user: c.user,
                        k: first,
                    };
                    let to = EditKey {
                        user: c.user,
                        k: u32::MAX,
                    };
                    self.acked.range(from..to).next().is_some()
                });
                let seen = acked_after.entry(p.id).or_insert(false);
                *seen |= acked;
            }
            if !acked_after.is_empty() && acked_after.values().all(|a| *a) {
                break;
            }
            if self.now.saturating_sub(healed) > LIVENESS {
                let waiting: Vec<String> = acked_after
                    .iter()
                    .filter(|(_, a)| !**a)
                    .map(|(id, _)| {
                        let p = self.procs.iter().find(|p| p.id == *id).expect("a process");
                        format!("{}#{}", p.name, p.id)
                    })
                    .collect();
                let all: Vec<String> = self
                    .procs
                    .iter()
                    .map(|p| format!("{}#{} {:?} ({})", p.name, p.id, p.status, p.describe()))
                    .collect();
                return Err(format!(
                    "liveness: {waiting:?} had no edit acknowledged within {LIVENESS:?} after the faults healed; processes: {all:?}"
                ));
            }
        }
        self.note("every node had an edit acknowledged".into());
        let deadline = self.now + CONVERGENCE;
        loop {
            // Clients stop editing; what is in flight lands or not.
            self.step(0.0)?;
            let behind: Vec<String> = self
                .procs
                .iter()
                .filter(|p| p.status == Status::Up)
                .filter(|p| {
                    p.replica().is_none_or(|(seq, _)| seq < self.truth.seq)
                        || !p.pending().is_empty()
                })
                .map(|p| {
                    format!(
                        "{}#{} ({}), {} pending",
                        p.name,
                        p.id,
                        p.describe(),
                        p.pending().len()
                    )
                })
                .collect();
            if behind.is_empty() {
                return Ok(());
            }
            check!(
                self.now < deadline,
                "replicas did not reach the log's end (sequence {}): {behind:?}",
                self.truth.seq
            );
        }
    }

    /// SIGTERM to process `i`, noted in the trace.
    fn sigterm(&mut self, i: usize) {
        let p = &self.procs[i];
        let owns = if p.leading() {
            " (it owns the scene)"
        } else {
            ""
        };
        let what = format!("SIGTERM {}#{}{owns}", p.name, p.id);
        self.note(what);
        self.procs[i].terminate(self.now);
    }

    /// Starts a process of `i`'s name again 0.5–6 s from now.
    fn restart_later(&mut self, i: usize) {
        let name = NAMES
            .iter()
            .find(|n| **n == self.procs[i].name)
            .copied()
            .expect("a name");
        let at = self.now + Duration::from_millis(self.rng.random_range(500..6000));
        self.restarts.push((at, name));
    }

    /// Stops every process as SIGTERM does, the scene's owner last.
    fn stop_all(&mut self) -> Result<(), Failure> {
        let mut order: Vec<usize> = self.alive();
        order.sort_by_key(|&i| self.procs[i].leading());
        for i in order {
            self.sigterm(i);
            let deadline = self.now + Duration::from_secs(40);
            while self.procs[i].alive() {
                check!(
                    self.now < deadline,
                    "{}#{} did not stop",
                    self.procs[i].name,
                    self.procs[i].id
                );
                self.step(0.0)?;
            }
        }
        Ok(())
    }

    /// The whole history of one seed.
    pub fn run(&mut self) -> Result<(), Failure> {
        while self.now < CHAOS {
            self.chaos();
            self.step(0.25)?;
        }
        self.heal()?;
        self.settle()?;
        self.stop_all()
    }
}

/// Runs one seed: its statistics, or why it failed and its last actions.
pub fn run_seed(seed: u64) -> Result<SimStats, (Failure, String)> {
    let mut sim = Sim::new(seed).map_err(|e| (e, String::new()))?;
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| sim.run()));
    match outcome {
        Ok(Ok(())) => Ok(sim.stats),
        Ok(Err(failure)) => Err((failure, sim.trace())),
        Err(panic) => {
            let why = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "a panic".into());
            Err((format!("panicked: {why}"), sim.trace()))
        }
    }
}
