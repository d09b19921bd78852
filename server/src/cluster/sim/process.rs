//! One simulated brickcast node process: a tokio runtime of its own with a paused clock, the
//! real name registration, the scene opened with the real `open_scene` (its owner over a real
//! `JetLog`, its real lease and follower tasks), and clients whose edits go through the real
//! `SessionForwarder`. The simulation moves its clock, steps its owner the way the owner
//! thread does, pauses it, kills it, or stops it the way SIGTERM does.

use std::collections::BTreeMap;
use std::sync::atomic::AtomicUsize;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use brickcast_protocol::Colour;
use brickcast_protocol::wire::{EditOp, Limits, ServerMsg, decode_server};
use tokio::sync::mpsc;

use super::jet::{ProcessClock, SimJet, World};
use crate::cluster::forward::SessionForwarder;
use crate::cluster::lease::Opened;
use crate::cluster::log::{self as jetlog, Exec};
use crate::cluster::{ClusterError, NodeName, SceneLink, name, signal};
use crate::metrics::{Metrics, PhaseClock};
use crate::scene::{Command, Outbox, OutboxReceiver, Owner, OwnerConfig, RequestItem, SceneHandle};

/// The scene every process serves.
pub const SCENE: &str = "sim";

/// Edits a client keeps in flight at most.
const IN_FLIGHT: usize = 3;
/// How often an idle owner is stepped anyway (its periodic snapshot).
const IDLE_STEP: Duration = Duration::from_millis(250);

/// What a process is doing.
#[derive(Debug, Clone, PartialEq)]
pub enum Status {
    /// Taking its name.
    Booting,
    Up,
    /// Stopping as SIGTERM makes it (since then, and whether it led the scene at its stop).
    Stopping {
        since: Duration,
    },
    /// Gone: why (a crash, a stop, a name another process took, a failed start).
    Exited(String),
}

/// A client's edit: who made it, its number, and where it goes (unique per user and number).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct EditKey {
    pub user: u64,
    pub k: u32,
}

impl EditKey {
    pub fn pos(&self) -> [u32; 3] {
        [self.k % 32, 8 + (self.user % 8) as u32, (self.k / 32) % 32]
    }

    pub fn colour(&self) -> Colour {
        Colour(((self.user as u16) << 11) | ((self.k as u16) & 0x7ff) | 1)
    }

    pub fn op(&self) -> EditOp {
        EditOp::Set {
            pos: self.pos(),
            colour: self.colour(),
        }
    }

    /// What the client sends: the voxel, and for every fourth edit a swatch of the palette
    /// in its colour too (scene state that takes the same way through log, snapshots and
    /// reloads; replicas' hashes cover it).
    pub fn ops(&self) -> Vec<EditOp> {
        let mut ops = vec![self.op()];
        if self.k.is_multiple_of(4) {
            ops.push(EditOp::Swatch {
                index: (self.k / 4 % 32) as u8,
                colour: self.colour(),
            });
        }
        ops
    }
}

/// A session of a client on a process.
struct Session {
    forwarder: SessionForwarder,
    out: Outbox,
    rx: OutboxReceiver,
    /// Client sequence → the edit it carries.
    pending: BTreeMap<u64, EditKey>,
    next_seq: u64,
}

/// A person editing through one process.
pub struct Client {
    pub user: u64,
    session: Option<Session>,
    pub next_k: u32,
}

impl Client {
    fn new(user: u64) -> Client {
        Client {
            user,
            session: None,
            next_k: 0,
        }
    }
}

/// The scene, as served on this process.
enum SceneSlot {
    Closed {
        retry_at: Duration,
    },
    /// Loading, and the close signal its tasks will follow.
    Opening(
        tokio::task::JoinHandle<anyhow::Result<Opened<SimJet>>>,
        signal::Sender<bool>,
    ),
    Open(Box<OpenScene>),
}

impl SceneSlot {
    fn leading(&self) -> bool {
        match self {
            SceneSlot::Open(s) => s
                .handle
                .info
                .leading
                .load(std::sync::atomic::Ordering::Relaxed),
            _ => false,
        }
    }

    fn replica(&self) -> Option<(u64, u64)> {
        match self {
            SceneSlot::Open(s) => Some((s.owner.seq(), s.owner.map().content_hash())),
            _ => None,
        }
    }
}

struct OpenScene {
    owner: Owner,
    commands: mpsc::Receiver<Command>,
    handle: SceneHandle,
    link: SceneLink<SimJet>,
    close: signal::Sender<bool>,
}

/// One copy of the scene on a process, and the people editing through it.
struct Copy {
    /// The scene's name on this copy (both copies follow the log keyed [`SCENE`]).
    name: String,
    slot: SceneSlot,
    clients: Vec<Client>,
    /// A second copy closes at this world time (as a renamed scene's old name does).
    until: Option<Duration>,
    last_step: Duration,
}

/// What a process reports to the simulation after a step.
#[derive(Default)]
pub struct Events {
    /// Acks its clients got: (edit, sequence).
    pub acks: Vec<(EditKey, u64)>,
    /// Edits whose sessions gave up (no node answered): their outcome is unknown.
    pub gave_up: Vec<EditKey>,
    /// Edits acknowledged as not applied (a `Set` inside the scene always applies).
    pub rejected: Vec<EditKey>,
    /// Things to note in the trace.
    pub notes: Vec<String>,
}

pub struct Process {
    pub id: u64,
    pub name: String,
    rt: Arc<tokio::runtime::Runtime>,
    pub jet: SimJet,
    clock: Arc<ProcessClock>,
    pub status: Status,
    boot: Option<tokio::task::JoinHandle<Result<NodeName, ClusterError>>>,
    node_name: Option<NodeName>,
    /// The scene under its name (always wanted), and for a while a second copy of the same
    /// log under another name: what a node serves while a rename reaches it (the old name
    /// still open, the new one opened), each with its own clients.
    copies: Vec<Copy>,
    /// World time until which the process is stopped (SIGSTOP).
    pub paused_until: Option<Duration>,
    metrics: Arc<Metrics>,
    config: OwnerConfig,
    next_session: u64,
    /// Close signals of second copies, kept until their tasks have ended.
    closing: Vec<signal::Sender<bool>>,
    /// The next edit number of the second copy's user (edits are told apart by user and
    /// number, across second copies too).
    second_next_k: u32,
    /// Whether it owned the scene when told to stop, and its sequence once stopped (the stop
    /// must leave a snapshot of it).
    pub stopped_leading: Option<u64>,
    /// While stopping: the closed copies' signals, whose receivers (their tasks) end last.
    stopping_close: Vec<signal::Sender<bool>>,
}

impl Process {
    /// Starts a process named `name` at world time `now`, its clock running at `rate`.
    /// Its clients' users are its own (`10 id`, `10 id + 1`): every edit ever made is told
    /// apart by its user and number.
    pub fn start(
        world: Arc<Mutex<World>>,
        id: u64,
        name: &str,
        now: Duration,
        rate: f64,
        config: OwnerConfig,
    ) -> Process {
        let users = vec![10 * id, 10 * id + 1];
        let rt = Arc::new(
            tokio::runtime::Builder::new_current_thread()
                .enable_time()
                .start_paused(true)
                .build()
                .expect("a runtime"),
        );
        // The process's clock reads `now` (world time) at its start.
        let base = rt.block_on(async { tokio::time::Instant::now() }) - now.mul_f64(rate);
        let clock = Arc::new(ProcessClock { base, rate });
        let jet = SimJet {
            world,
            process: id,
            clock: clock.clone(),
        };
        let instance = format!("{name}#{id}");
        let boot = {
            let jet = jet.clone();
            let name = name.to_string();
            rt.spawn(async move { name::register(&jet, &name, instance, "sim").await })
        };
        Process {
            id,
            name: name.to_string(),
            rt,
            jet,
            clock,
            status: Status::Booting,
            boot: Some(boot),
            node_name: None,
            copies: vec![Copy {
                name: SCENE.to_string(),
                slot: SceneSlot::Closed {
                    retry_at: Duration::ZERO,
                },
                clients: users.into_iter().map(Client::new).collect(),
                until: None,
                last_step: Duration::ZERO,
            }],
            paused_until: None,
            metrics: Arc::new(Metrics::default()),
            config,
            next_session: 1,
            closing: Vec::new(),
            second_next_k: 0,
            stopped_leading: None,
            stopping_close: Vec::new(),
        }
    }

    pub fn alive(&self) -> bool {
        !matches!(self.status, Status::Exited(_))
    }

    pub fn paused(&self, now: Duration) -> bool {
        self.paused_until.is_some_and(|t| now < t)
    }

    /// Whether a copy of the scene here has its owner ordering edits.
    pub fn leading(&self) -> bool {
        self.copies.iter().any(|c| c.slot.leading())
    }

    /// Its owner's sequence and map hash, while it serves the scene under its name.
    pub fn replica(&self) -> Option<(u64, u64)> {
        self.copies[0].slot.replica()
    }

    /// Every copy's sequence and map hash (a second copy's too).
    pub fn replicas(&self) -> Vec<(u64, u64)> {
        self.copies
            .iter()
            .filter_map(|c| c.slot.replica())
            .collect()
    }

    /// The clients of the scene under its name.
    pub fn clients(&self) -> impl Iterator<Item = &Client> {
        self.copies[0].clients.iter()
    }

    /// Whether a second copy is open or opening.
    pub fn has_second(&self) -> bool {
        self.copies.len() > 1
    }

    /// Opens a second copy of the scene's log under another name, closed at world time
    /// `until`, with one client of its own (user `10 id + 2`).
    pub fn open_second(&mut self, until: Duration) {
        if self.has_second() || self.status != Status::Up {
            return;
        }
        let name = format!("{SCENE}-renamed");
        let slot = self.open(&name);
        let user = 10 * self.id + 2;
        // The second copy's client starts where an earlier one of its user stopped.
        let next_k = self.second_next_k;
        self.copies.push(Copy {
            name,
            slot,
            clients: vec![Client {
                user,
                session: None,
                next_k,
            }],
            until: Some(until),
            last_step: Duration::ZERO,
        });
    }

    /// Where its replica stands, for a report: sequence, log position, whether it leads.
    pub fn describe(&self) -> String {
        let mut out = Vec::new();
        for copy in &self.copies {
            let state = match &copy.slot {
                SceneSlot::Open(s) => format!(
                    "seq {} pos {} leading {} lease owner {:?}",
                    s.owner.seq(),
                    s.owner.position(),
                    copy.slot.leading(),
                    s.link.owner.get()
                ),
                SceneSlot::Opening(..) => "opening".into(),
                SceneSlot::Closed { .. } => "closed".into(),
            };
            out.push(format!("{}: {state}", copy.name));
        }
        out.join("; ")
    }

    /// Runs the process's tasks up to world time `now`. A process waking from a pause finds
    /// its clock already there, before anything runs (a stopped process's clock goes on).
    fn drive(&self, now: Duration, waking: bool) {
        let until = self.clock.local(now);
        self.rt.block_on(async move {
            if waking {
                let behind = until.saturating_duration_since(tokio::time::Instant::now());
                tokio::time::advance(behind).await;
            }
            tokio::time::sleep_until(until).await;
            tokio::task::yield_now().await;
        });
    }

    /// One step of the process at world time `now`: its tasks run, its owner takes what was
    /// sent to it, its clients read and edit.
    pub fn tick(&mut self, now: Duration, edit_chance: f64, rng: &mut impl rand::Rng) -> Events {
        let mut events = Events::default();
        if !self.alive() || self.paused(now) {
            return events;
        }
        let waking = self.paused_until.take().is_some();
        self.drive(now, waking);
        if self.status == Status::Booting {
            self.boot_done(&mut events);
        }
        if !self.alive() {
            return events;
        }
        let lost = self.node_name.as_ref().and_then(|n| n.lost.get());
        if let Some(why) = lost
            && !matches!(self.status, Status::Stopping { .. })
        {
            events
                .notes
                .push(format!("{}#{} stops: {why}", self.name, self.id));
            self.terminate(now);
        }
        for i in 0..self.copies.len() {
            self.tend_scene(i, now, &mut events);
        }
        self.close_second(now, &mut events);
        if let Status::Stopping { since } = self.status {
            self.finish_stop(now, since, &mut events);
            return events;
        }
        if self.status == Status::Up {
            for i in 0..self.copies.len() {
                self.tend_clients(i, edit_chance, rng, &mut events);
            }
        }
        events
    }

    fn boot_done(&mut self, events: &mut Events) {
        let Some(boot) = &self.boot else { return };
        if !boot.is_finished() {
            return;
        }
        let boot = self.boot.take().expect("checked");
        match self.rt.block_on(boot) {
            Ok(Ok(name)) => {
                self.node_name = Some(name);
                self.status = Status::Up;
                events.notes.push(format!("{}#{} up", self.name, self.id));
            }
            Ok(Err(e)) => self.status = Status::Exited(format!("did not start: {e}")),
            Err(e) => self.status = Status::Exited(format!("did not start: {e}")),
        }
    }

    /// Opens a copy of the scene's log (keyed [`SCENE`]) under `scene_name`.
    fn open(&self, scene_name: &str) -> SceneSlot {
        let jet = self.jet.clone();
        let scene_name = scene_name.to_string();
        let exec = Exec::Own(self.rt.clone());
        let name = self.name.clone();
        let instance = format!("{}#{}", self.name, self.id);
        let metrics = self.metrics.clone();
        let config = self.config.clone();
        let clock = {
            let rt = self.rt.clone();
            Arc::new(move || {
                let _inside = rt.enter();
                tokio::time::Instant::now().into_std()
            })
        };
        let (close, closed) = signal::channel(false);
        let task = self.rt.spawn(async move {
            let loaded = jetlog::load(&jet, SCENE).await?;
            crate::cluster::open_scene(
                &jet, exec, &name, &instance, scene_name, SCENE, loaded, metrics, config, clock,
                closed,
            )
            .await
        });
        SceneSlot::Opening(task, close)
    }

    /// Copy `i`: opens it when closed (again after a failed open), takes it in when loaded, and steps its owner as the owner thread does.
    fn tend_scene(&mut self, i: usize, now: Duration, events: &mut Events) {
        let label = format!("{}#{} ({})", self.name, self.id, self.copies[i].name);
        let mut slot = std::mem::replace(
            &mut self.copies[i].slot,
            SceneSlot::Closed {
                retry_at: Duration::MAX,
            },
        );
        match &mut slot {
            SceneSlot::Closed { retry_at } => {
                if self.status == Status::Up && now >= *retry_at {
                    slot = self.open(&self.copies[i].name);
                }
            }
            SceneSlot::Opening(task, _) => {
                if task.is_finished() {
                    let SceneSlot::Opening(task, close) = std::mem::replace(
                        &mut slot,
                        SceneSlot::Closed {
                            retry_at: now + Duration::from_secs(1),
                        },
                    ) else {
                        unreachable!()
                    };
                    match self.rt.block_on(task) {
                        Ok(Ok(opened)) => {
                            let Opened {
                                owner,
                                handle,
                                commands,
                                link,
                            } = opened;
                            events
                                .notes
                                .push(format!("{label} opened the scene at {}", owner.seq()));
                            slot = SceneSlot::Open(Box::new(OpenScene {
                                owner,
                                commands,
                                handle,
                                link,
                                close,
                            }));
                        }
                        Ok(Err(e)) => events
                            .notes
                            .push(format!("{label} cannot open the scene: {e:#}")),
                        Err(e) => events.notes.push(format!("{label} open failed: {e}")),
                    }
                }
            }
            SceneSlot::Open(scene) => {
                let mut commands = Vec::new();
                while let Ok(cmd) = scene.commands.try_recv() {
                    commands.push(cmd);
                }
                let idle = now.saturating_sub(self.copies[i].last_step) < IDLE_STEP;
                if !(commands.is_empty() && idle) {
                    self.copies[i].last_step = now;
                    // As the owner thread does (`scene::run`).
                    let stop = match scene.owner.step(commands, &mut PhaseClock::start()) {
                        Ok(stop) => stop,
                        Err(e) => {
                            events.notes.push(format!("{label} owner error: {e}"));
                            scene.owner.fail_all(&e.to_string());
                            true
                        }
                    };
                    if stop {
                        let mut rest = Vec::new();
                        while let Ok(cmd) = scene.commands.try_recv() {
                            rest.push(cmd);
                        }
                        if let Err(e) = scene.owner.stop(rest) {
                            events.notes.push(format!("{label} stop error: {e}"));
                        }
                        events.notes.push(format!(
                            "{label} took the scene out of service at {}",
                            scene.owner.seq()
                        ));
                        scene.close.send_replace(true);
                        slot = SceneSlot::Closed {
                            retry_at: now + Duration::from_secs(2),
                        };
                    }
                }
            }
        }
        self.copies[i].slot = slot;
    }

    /// A second copy whose time is up closes the way a renamed scene's old name closes on a
    /// node (`served::close`): its clients are cut off, its owner commits what it has and
    /// stops, its lease (if it held it) is handed over.
    fn close_second(&mut self, now: Duration, events: &mut Events) {
        let due = self.copies.len() > 1
            && self.copies[1]
                .until
                .is_some_and(|t| now >= t || self.status != Status::Up);
        self.closing.retain(|c| !c.is_closed());
        if !due {
            return;
        }
        let mut copy = self.copies.pop().expect("checked");
        for client in &mut copy.clients {
            self.second_next_k = self.second_next_k.max(client.next_k);
            if let Some(mut session) = client.session.take() {
                read_acks(&mut session, &Limits::default(), events);
                events.gave_up.extend(session.pending.values().copied());
            }
        }
        let (_, close) = close_slot(copy.slot);
        self.closing.extend(close);
        events.notes.push(format!(
            "{}#{} closed its second copy ({})",
            self.name, self.id, copy.name
        ));
    }

    fn tend_clients(
        &mut self,
        i: usize,
        edit_chance: f64,
        rng: &mut impl rand::Rng,
        events: &mut Events,
    ) {
        let copy = &mut self.copies[i];
        let SceneSlot::Open(scene) = &copy.slot else {
            return;
        };
        let limits = Limits::default();
        for client in &mut copy.clients {
            if client.session.as_ref().is_some_and(|s| s.out.is_closed()) {
                let session = client.session.take().expect("checked");
                // Read what came before the close, then give up on the rest.
                let mut session = session;
                read_acks(&mut session, &limits, events);
                events.gave_up.extend(session.pending.values().copied());
                events.notes.push(format!(
                    "{}#{}: user {} reconnects ({} edits unknown)",
                    self.name,
                    self.id,
                    client.user,
                    session.pending.len()
                ));
            }
            let session = client.session.get_or_insert_with(|| {
                let id = self.next_session;
                self.next_session += 1;
                let (out, rx) = Outbox::new(Arc::new(AtomicUsize::new(0)));
                let _inside = self.rt.enter();
                let forwarder = SessionForwarder::start(
                    scene.link.clone(),
                    id,
                    client.user,
                    true,
                    out.clone(),
                    self.metrics.clone(),
                );
                Session {
                    forwarder,
                    out,
                    rx,
                    pending: BTreeMap::new(),
                    next_seq: 1,
                }
            });
            read_acks(session, &limits, events);
            if session.pending.len() < IN_FLIGHT
                && client.next_k < 1024
                && rng.random_bool(edit_chance)
            {
                let key = EditKey {
                    user: client.user,
                    k: client.next_k,
                };
                client.next_k += 1;
                let client_seq = session.next_seq;
                session.next_seq += 1;
                session.pending.insert(client_seq, key);
                let forwarder = &session.forwarder;
                let sent = self
                    .rt
                    .block_on(forwarder.send(client_seq, RequestItem::Edit(key.ops())));
                if !sent {
                    session.pending.remove(&client_seq);
                }
            }
        }
    }

    /// Edits this process's clients are still waiting for.
    pub fn pending(&self) -> Vec<EditKey> {
        self.copies
            .iter()
            .flat_map(|c| &c.clients)
            .filter_map(|c| c.session.as_ref())
            .flat_map(|s| s.pending.values().copied())
            .collect()
    }

    /// SIGTERM: the scene closes the one way it does on a node (`served::close`): its tasks
    /// are told, its owner commits what it has, snapshots and stops (waiting for the upload),
    /// the lease is handed over once it has; then the name is given back.
    pub fn terminate(&mut self, now: Duration) {
        if matches!(self.status, Status::Stopping { .. } | Status::Exited(_)) {
            return;
        }
        let mut closing = std::mem::take(&mut self.closing);
        for mut copy in std::mem::take(&mut self.copies) {
            for client in &mut copy.clients {
                client.session = None;
            }
            let slot = std::mem::replace(
                &mut copy.slot,
                SceneSlot::Closed {
                    retry_at: Duration::MAX,
                },
            );
            let (led, close) = close_slot(slot);
            if let Some(seq) = led {
                self.stopped_leading = Some(self.stopped_leading.unwrap_or(0).max(seq));
            }
            closing.extend(close);
            // The first copy stays, closed for good; a second one goes.
            if self.copies.is_empty() {
                self.copies.push(copy);
            }
        }
        // The close signals live until the stop is finished (`finish_stop`).
        self.stopping_close = closing;
        self.status = Status::Stopping { since: now };
    }

    fn finish_stop(&mut self, now: Duration, since: Duration, events: &mut Events) {
        let tasks_done = self.stopping_close.iter().all(|c| c.is_closed());
        if !tasks_done && now.saturating_sub(since) < Duration::from_secs(30) {
            return;
        }
        self.stopping_close.clear();
        if let Some(name) = self.node_name.take() {
            self.rt.block_on(name.release());
        }
        events
            .notes
            .push(format!("{}#{} stopped", self.name, self.id));
        self.status = Status::Exited("stopped".into());
    }

    /// SIGKILL: everything goes at once; nothing runs any more, nothing is written.
    pub fn kill(&mut self) {
        self.jet
            .world
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .bury(self.id);
        // Dropped inside the process's runtime, the owner's log does not wait for (or finish)
        // an upload: a crash runs nothing more. The runtime is never driven again.
        let _inside = self.rt.enter();
        self.copies.truncate(1);
        for client in &mut self.copies[0].clients {
            client.session = None;
        }
        self.copies[0].slot = SceneSlot::Closed {
            retry_at: Duration::MAX,
        };
        self.closing.clear();
        self.node_name = None;
        self.stopping_close.clear();
        self.boot = None;
        self.status = Status::Exited("killed".into());
    }
}

/// Closes a copy the one way a node does (`served::close`): its tasks are told, its owner
/// commits what it has, snapshots and stops (waiting for the upload); dropping the owner, the
/// lease task hands a held lease over. The owner's sequence if it led, and the close signal
/// (to keep until its tasks have ended).
fn close_slot(slot: SceneSlot) -> (Option<u64>, Option<signal::Sender<bool>>) {
    match slot {
        SceneSlot::Closed { .. } => (None, None),
        SceneSlot::Opening(task, _) => {
            task.abort();
            (None, None)
        }
        SceneSlot::Open(scene) => {
            let mut scene = *scene;
            let led = scene
                .handle
                .info
                .leading
                .load(std::sync::atomic::Ordering::Relaxed);
            scene.close.send_replace(true);
            let _ = scene.handle.try_send(Command::Shutdown);
            let mut commands = Vec::new();
            while let Ok(cmd) = scene.commands.try_recv() {
                commands.push(cmd);
            }
            // As the owner thread does: the turn that holds the Shutdown, then the rest.
            let _ = scene.owner.step(commands, &mut PhaseClock::start());
            let mut rest = Vec::new();
            while let Ok(cmd) = scene.commands.try_recv() {
                rest.push(cmd);
            }
            let _ = scene.owner.stop(rest);
            let seq = scene.owner.seq();
            drop(scene.owner);
            drop(scene.commands);
            (led.then_some(seq), Some(scene.close))
        }
    }
}

fn read_acks(session: &mut Session, limits: &Limits, events: &mut Events) {
    while let Some(frame) = session.rx.try_take() {
        let Ok(msg) = decode_server(&frame, limits) else {
            events.notes.push("a frame that does not decode".into());
            continue;
        };
        if let ServerMsg::Ack {
            client_seq, seq, ..
        } = msg
            && let Some(key) = session.pending.remove(&client_seq)
        {
            match seq {
                Some(seq) => events.acks.push((key, seq)),
                None => events.rejected.push(key),
            }
        }
    }
}
