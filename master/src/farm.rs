//! The live farm: the loop around the pure scheduler core.
//!
//! One task (the *actor*, [`Actor`]) owns the [`Scheduler`] and everything it refers to:
//! the worker links, the composer link and the live sessions. Everything else talks to it
//! through one channel of [`Event`]s: the connection tasks of [`crate::links`] (worker and
//! composer messages, connects and disconnects) and the HTTP layer (through [`Farm`], the
//! [`FarmBackend`]). After each batch of events, and at the scheduler's
//! [`Scheduler::next_wakeup`], the actor runs a round ([`Scheduler::tick`]) and carries out
//! its actions:
//!
//! | action | becomes |
//! | --- | --- |
//! | `Dispatch` | a [`RayBatch`] to that worker (camera moved into the object's frame, results to the composer) |
//! | `Cancel` | a [`Cancel`] of that batch |
//! | `FrameComplete` | a [`FramePlan`] to the composer (which tasks fill which view, for which pose) |
//! | `FrameDropped` | a count (the composer shows the previous frame) |
//! | `WorkerLost` | the link is closed with a `Goodbye` |
//! | `ReleaseResult` | a [`ReleaseTask`] to the composer |
//!
//! Time is the monotonic clock since the farm started, as the scheduler's [`Time`]; deadlines
//! on the wire are time left when sent (the protocol's convention: no two machines' wall
//! clocks need agree, and a step of this one's changes nothing).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use glam::{Mat4, Vec3};
use nephele_geometry::camera::Camera;
use nephele_proto::{
    BatchIds, Cancel, CancelTarget, ClientPose, CloseStream, ComposerRegister, DerivedView, ErrorCode, FramePlan,
    LoadReport, Message, OpenStream, PlanPart, RayBatch, Register, ReleaseTask, ReuseLimits, StreamOpened,
    ViewProjection,
};
use nephele_scheduler::{
    Action, Admission as SchedAdmission, BatchId, BatchSpec, FrameId, FramePart, ObjectId, ObjectInfo, SchedError,
    Scheduler, SchedulerConfig, SessionId, SessionSpec, Time, WorkerId,
};
use serde_json::{Value, json};
use tokio::sync::{mpsc, oneshot};

use crate::http::{Admission, BoxFuture, FarmBackend, OpenError, SceneView};
use crate::metrics::{MasterMetrics, Published};
use crate::scenes::Catalog;
use crate::sessions::SessionRequest;

/// Near and far planes of the projection matrices sent to workers. Workers only read the
/// intrinsics from a projection (`Camera::from_view_projection`), so any finite pair works.
pub const WIRE_NEAR: f32 = 0.01;
pub const WIRE_FAR: f32 = 1000.0;

/// Cost of one pixel of an environment in the unit of the workers' measured throughput (an
/// i-NOLF ray of the default scene). The GI kernel at its defaults (half resolution, the
/// G-buffer at 2 samples, the U-Net's 29,568 multiply-adds per shaded pixel) takes 1.1-1.3
/// us of CPU per view pixel (`nephele bench gi`, BENCHMARKS.md "environment served by the
/// farm"), against 2.2 us per dispatched ray the farm measured on the default scene: about
/// half a ray; 1 keeps it on the safe side of admission (the scene's rays vary 2x).
pub const ENVIRONMENT_COST_PER_PIXEL: f64 = 1.0;

/// Poses remembered per session, to tell which pose a completed frame was rendered for
/// (1.3 s at the client's 50 Hz).
const POSE_MEMORY: usize = 64;
/// Samples kept for the latency and round-cost percentiles in `GET /v1/farm`.
const SAMPLES: usize = 1024;

/// How the live farm runs.
#[derive(Debug, Clone)]
pub struct FarmConfig {
    pub scheduler: SchedulerConfig,
    /// Told to every worker in `Registered`: how often it sends a `LoadReport` (the
    /// heartbeat). The scheduler's heartbeat timeout should be several of these.
    pub load_report_interval_ms: u32,
    /// How long `POST /v1/sessions` waits for the composer's SDP answer.
    pub open_timeout: Duration,
    /// ICE servers for `GET /v1/config` (a JSON array).
    pub ice_servers: Value,
    /// How many of a user's following frames a worker may take from its full render of a
    /// view by reprojection ([`ReuseLimits::previous_frames`]); 0 renders every frame in full.
    pub previous_frames: u32,
}

/// One frame in four rendered in full ([`ReuseLimits::DEFAULT_PREVIOUS_FRAMES`]).
pub const DEFAULT_PREVIOUS_FRAMES: u32 = ReuseLimits::DEFAULT_PREVIOUS_FRAMES;

impl Default for FarmConfig {
    fn default() -> FarmConfig {
        FarmConfig {
            scheduler: live_scheduler_config(),
            load_report_interval_ms: 200,
            open_timeout: Duration::from_secs(10),
            ice_servers: json!([]),
            previous_frames: DEFAULT_PREVIOUS_FRAMES,
        }
    }
}

/// `nephele master`'s admission that looks ahead (`--admit-up-to`): new users are refused
/// while the asked work would pass this share of the farm's measured throughput. The
/// library's live configuration leaves it off, for farms embedded in tests that open users
/// at rates their small farms cannot all carry.
pub const DEFAULT_ADMIT_UP_TO: f64 = 0.9;

/// The scheduler defaults, adjusted for a live farm of CPU workers over TCP: a batch is
/// presumed lost after 50 ms at the least (the core's 8 ms suits GPU kernels; a CPU path
/// tracer on a shared machine misses that by noise alone, and a dead worker is noticed by its
/// connection closing anyway), and a worker after 2 s of silence (10 load reports).
pub fn live_scheduler_config() -> SchedulerConfig {
    SchedulerConfig {
        min_batch_timeout: Duration::from_millis(50),
        heartbeat_timeout: Some(Duration::from_secs(2)),
        // `nephele master` turns it on ([`DEFAULT_ADMIT_UP_TO`]); farms embedded in tests
        // open several users at rates their small farms cannot all carry.
        admit_up_to: None,
        ..SchedulerConfig::default()
    }
}

/// The camera a worker gets for rendering `object` (placed at `translation` in the world)
/// as `camera` sees it: the worker renders the asset in its own coordinates, so the view
/// matrix becomes object-to-camera (`world_to_camera * translate(translation)`). View-space
/// depth is unchanged. The projection carries the camera's intrinsics.
pub fn wire_camera(camera: &Camera, translation: Vec3) -> ViewProjection {
    let world = ViewProjection::of_camera(camera, WIRE_NEAR, WIRE_FAR);
    ViewProjection { view: world.view * Mat4::from_translation(translation), ..world }
}

/// A command for a connection task.
#[derive(Debug)]
// A message is moved once into the channel; boxing it would only add an allocation.
#[allow(clippy::large_enum_variant)]
pub enum LinkCommand {
    Send(Message),
    /// Say goodbye (with this reason) and close.
    Close(String),
}

pub type LinkSender = mpsc::UnboundedSender<LinkCommand>;

/// Everything the actor hears.
#[derive(Debug)]
pub enum Event {
    WorkerJoin {
        register: Register,
        peer: SocketAddr,
        link: LinkSender,
        reply: oneshot::Sender<Result<u32, String>>,
    },
    WorkerMessage(u32, Message),
    WorkerLeft(u32, String),
    ComposerJoin {
        register: ComposerRegister,
        peer: SocketAddr,
        link: LinkSender,
        reply: oneshot::Sender<Result<u64, String>>,
    },
    ComposerMessage(u64, Message),
    ComposerLeft(u64, String),
    Open {
        name: String,
        request: SessionRequest,
        offer: String,
        reply: oneshot::Sender<Result<String, OpenError>>,
    },
    /// The HTTP side gave up waiting for the answer: drop the session.
    Abandon {
        name: String,
    },
    Close {
        name: String,
        reply: oneshot::Sender<()>,
    },
    State {
        reply: oneshot::Sender<Value>,
    },
    Shutdown {
        reply: oneshot::Sender<()>,
    },
}

/// The handle the HTTP layer and the connection tasks hold. Cheap to clone.
#[derive(Debug, Clone)]
pub struct Farm {
    inner: Arc<Inner>,
}

#[derive(Debug)]
struct Inner {
    events: mpsc::UnboundedSender<Event>,
    catalog: Arc<Catalog>,
    admission: Arc<Mutex<Admission>>,
    metrics: Arc<MasterMetrics>,
    ice_servers: Value,
    open_timeout: Duration,
    load_report_interval_ms: u32,
}

impl Farm {
    /// Starts the actor. Returns the handle, the actor's task, and a channel of the HTTP
    /// session ids the farm ended on its own (client vanished, composer gone) for the HTTP
    /// session table to forget.
    pub fn start(
        config: FarmConfig,
        catalog: Catalog,
    ) -> Result<(Farm, tokio::task::JoinHandle<()>, mpsc::UnboundedReceiver<String>), SchedError> {
        let mut scheduler_config = config.scheduler.clone();
        if config.previous_frames == 0 {
            // A render ahead is used as the worker's previous render of the view: nothing to
            // render it for when workers keep none.
            scheduler_config.render_ahead = None;
        }
        let mut scheduler = Scheduler::new(scheduler_config)?;
        for object in catalog.objects() {
            let occupancy = catalog.occupancy(&object.asset).cloned();
            let full_frame = catalog.is_environment(&object.asset);
            let cost_per_ray = if full_frame { ENVIRONMENT_COST_PER_PIXEL } else { 1.0 };
            let info = ObjectInfo { bounds: object.bounds, occupancy, cost_per_ray, full_frame };
            scheduler.register_object(ObjectId(object.id), info)?;
        }
        let catalog = Arc::new(catalog);
        let (events, receiver) = mpsc::unbounded_channel();
        let (ended_tx, ended_rx) = mpsc::unbounded_channel();
        let admission = Arc::new(Mutex::new(Admission::Admit));
        let metrics = Arc::new(MasterMetrics::new());
        let actor = Actor {
            scheduler,
            start: Instant::now(),
            catalog: catalog.clone(),
            workers: BTreeMap::new(),
            composer: None,
            sessions: BTreeMap::new(),
            by_name: HashMap::new(),
            pending_opens: HashMap::new(),
            next_worker: 1,
            next_composer: 1,
            ended: ended_tx,
            admission: admission.clone(),
            metrics: metrics.clone(),
            last_publish: None,
            round_us: Samples::default(),
            pose_to_plan_ms: Samples::default(),
            previous_frames: config.previous_frames.min(ReuseLimits::MAX_PREVIOUS_FRAMES),
        };

        let task = tokio::spawn(actor.run(receiver));
        let inner = Inner {
            events,
            catalog,
            admission,
            metrics,
            ice_servers: config.ice_servers,
            open_timeout: config.open_timeout,
            load_report_interval_ms: config.load_report_interval_ms,
        };
        Ok((Farm { inner: Arc::new(inner) }, task, ended_rx))
    }

    /// Sends an event to the actor; `false` once it has stopped.
    pub fn send(&self, event: Event) -> bool {
        self.inner.events.send(event).is_ok()
    }

    pub fn catalog(&self) -> &Catalog {
        &self.inner.catalog
    }

    /// The master's metrics (`GET /metrics`).
    pub fn metrics(&self) -> &Arc<MasterMetrics> {
        &self.inner.metrics
    }

    pub fn load_report_interval_ms(&self) -> u32 {
        self.inner.load_report_interval_ms
    }

    /// Says goodbye to every worker and the composer and stops the actor (waits up to a few
    /// seconds for the goodbyes to be written).
    pub async fn shutdown(&self) {
        let (reply, done) = oneshot::channel();
        if self.send(Event::Shutdown { reply }) {
            let _ = done.await;
        }
    }
}

impl FarmBackend for Farm {
    fn scenes(&self) -> Vec<(String, SceneView)> {
        self.inner.catalog.scenes().iter().map(|s| (s.name.clone(), s.view.clone())).collect()
    }

    fn ice_servers(&self) -> Value {
        self.inner.ice_servers.clone()
    }

    fn admission(&self) -> Admission {
        *self.inner.admission.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn open(
        &self,
        session_id: String,
        request: SessionRequest,
        offer_sdp: String,
    ) -> BoxFuture<Result<String, OpenError>> {
        let farm = self.clone();
        Box::pin(async move {
            let (reply, answer) = oneshot::channel();
            let name = session_id.clone();
            if !farm.send(Event::Open { name: session_id, request, offer: offer_sdp, reply }) {
                return Err(OpenError::Unavailable("the farm is shutting down".into()));
            }
            match tokio::time::timeout(farm.inner.open_timeout, answer).await {
                Ok(Ok(result)) => result,
                Ok(Err(_)) => Err(OpenError::Unavailable("the farm stopped".into())),
                Err(_) => {
                    farm.send(Event::Abandon { name });
                    let seconds = farm.inner.open_timeout.as_secs_f64();
                    Err(OpenError::Unavailable(format!("the composer did not answer the offer within {seconds:.0} s")))
                }
            }
        })
    }

    fn close(&self, session_id: String) -> BoxFuture<()> {
        let farm = self.clone();
        Box::pin(async move {
            let (reply, done) = oneshot::channel();
            if farm.send(Event::Close { name: session_id, reply }) {
                let _ = done.await;
            }
        })
    }

    fn farm_state(&self) -> BoxFuture<Value> {
        let farm = self.clone();
        Box::pin(async move {
            let (reply, state) = oneshot::channel();
            if !farm.send(Event::State { reply }) {
                return json!({ "error": "the farm is shutting down" });
            }
            state.await.unwrap_or_else(|_| json!({ "error": "the farm stopped" }))
        })
    }
}

// ---------------------------------------------------------------------------------------
// The actor

#[derive(Debug)]
struct WorkerLink {
    name: String,
    peer: SocketAddr,
    threads: u32,
    kernels: Vec<String>,
    rays_per_second: f64,
    device: String,
    link: LinkSender,
    joined: Time,
    load: Option<LoadReport>,
    draining: bool,
}

#[derive(Debug)]
struct ComposerLink {
    id: u64,
    name: String,
    peer: SocketAddr,
    results_address: String,
    link: LinkSender,
    joined: Time,
}

#[derive(Debug, Clone, Copy)]
struct PoseMark {
    at: Time,
    received: Instant,
    sequence: u32,
    client_time_ms: f64,
}

#[derive(Debug)]
struct LiveSession {
    name: String,
    request: SessionRequest,
    /// The composer answered the offer.
    streaming: bool,
    poses: VecDeque<PoseMark>,
    poses_received: u64,
    poses_rejected: u64,
    plans_sent: u64,
    frames_dropped: u64,
}

/// A bounded window of samples for percentiles.
#[derive(Debug, Default)]
struct Samples {
    values: VecDeque<f64>,
    total: u64,
}

impl Samples {
    fn push(&mut self, value: f64) {
        if self.values.len() == SAMPLES {
            self.values.pop_front();
        }
        self.values.push_back(value);
        self.total += 1;
    }

    fn summary(&self) -> Value {
        let mut sorted: Vec<f64> = self.values.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let pick = |q: f64| sorted.get(((sorted.len() as f64 - 1.0) * q).round() as usize).copied();
        json!({ "samples": self.total, "window": sorted.len(), "p50": pick(0.5), "p99": pick(0.99), "max": sorted.last() })
    }
}

#[derive(Debug)]
struct Actor {
    scheduler: Scheduler,
    start: Instant,
    catalog: Arc<Catalog>,
    workers: BTreeMap<u32, WorkerLink>,
    composer: Option<ComposerLink>,
    sessions: BTreeMap<SessionId, LiveSession>,
    by_name: HashMap<String, SessionId>,
    pending_opens: HashMap<SessionId, oneshot::Sender<Result<String, OpenError>>>,
    next_worker: u32,
    next_composer: u64,
    ended: mpsc::UnboundedSender<String>,
    admission: Arc<Mutex<Admission>>,
    metrics: Arc<MasterMetrics>,
    /// When the scheduler's state was last published for `/metrics`.
    last_publish: Option<Instant>,
    round_us: Samples,
    pose_to_plan_ms: Samples,
    /// [`FarmConfig::previous_frames`], sent with every batch.
    previous_frames: u32,
}

/// Events handled per round at most (the rest wait for the next round, so a flood of
/// results cannot starve the rounds).
const EVENTS_PER_ROUND: usize = 256;

/// How often the scheduler's state is published for `/metrics` (a scrape sees state at most
/// this old).
const PUBLISH_EVERY: Duration = Duration::from_millis(250);

impl Actor {
    fn now(&self) -> Time {
        Time::from_micros(self.start.elapsed().as_micros() as u64)
    }

    async fn run(mut self, mut events: mpsc::UnboundedReceiver<Event>) {
        tracing::debug!("farm loop started");
        loop {
            let wake = self.scheduler.next_wakeup().map(|t| {
                let at = self.start + Duration::from_micros(t.as_micros());
                // Never spin: a wakeup already due runs after the next round at the latest.
                tokio::time::Instant::from_std(at.max(Instant::now() + Duration::from_micros(200)))
            });
            let first = tokio::select! {
                event = events.recv() => match event {
                    Some(event) => Some(event),
                    None => break,
                },
                () = sleep_until(wake) => None,
            };
            if let Some(event) = first {
                if let Some(reply) = self.handle(event) {
                    self.shutdown(reply).await;
                    return;
                }
                for _ in 1..EVENTS_PER_ROUND {
                    let Ok(event) = events.try_recv() else { break };
                    if let Some(reply) = self.handle(event) {
                        self.shutdown(reply).await;
                        return;
                    }
                }
            }
            self.round();
        }
        tracing::debug!("farm loop stopped: every handle dropped");
    }

    /// One scheduling round and its actions.
    fn round(&mut self) {
        let now = self.now();
        let start = Instant::now();
        let actions = self.scheduler.tick(now);
        let round_s = start.elapsed().as_secs_f64();
        self.round_us.push(round_s * 1e6);
        self.metrics.round_ms.observe(round_s * 1e3);
        for action in actions {
            self.carry_out(action);
        }
        let admission = match self.scheduler.admission(now) {
            SchedAdmission::Admit => Admission::Admit,
            SchedAdmission::Refuse { retry_after } => Admission::Refuse { retry_after },
        };
        *self.admission.lock().unwrap_or_else(|p| p.into_inner()) = admission;
        if self.last_publish.is_none_or(|at| at.elapsed() >= PUBLISH_EVERY) {
            self.publish(now);
        }
    }

    /// Hands the scheduler's state to the `/metrics` collector.
    fn publish(&mut self, now: Time) {
        self.last_publish = Some(Instant::now());
        let published = Published {
            snapshot: Some(self.scheduler.snapshot(now)),
            worker_names: self.workers.iter().map(|(&id, w)| (id, w.name.clone())).collect(),
            session_names: self.sessions.iter().map(|(sid, s)| (sid.0, s.name.clone())).collect(),
            composer_linked: self.composer.is_some(),
        };
        *self.metrics.farm.published.lock().unwrap_or_else(|p| p.into_inner()) = published;
    }

    /// Handles one event; `Some` to stop (shutdown requested).
    fn handle(&mut self, event: Event) -> Option<oneshot::Sender<()>> {
        let now = self.now();
        match event {
            Event::WorkerJoin { register, peer, link, reply } => self.worker_join(register, peer, link, reply, now),
            Event::WorkerMessage(id, message) => self.worker_message(id, message, now),
            Event::WorkerLeft(id, reason) => {
                if self.workers.remove(&id).is_some() {
                    self.metrics.links.workers_left.inc();
                    match self.scheduler.remove_worker(WorkerId(id), now) {
                        Ok(()) => {
                            tracing::info!(worker = id, %reason, "worker disconnected; its batches are re-issued")
                        }
                        Err(e) => tracing::warn!(worker = id, %reason, "worker disconnected: {e}"),
                    }
                }
            }
            Event::ComposerJoin { register, peer, link, reply } => self.composer_join(register, peer, link, reply, now),
            Event::ComposerMessage(id, message) => self.composer_message(id, message, now),
            Event::ComposerLeft(id, reason) => {
                if self.composer.as_ref().is_some_and(|c| c.id == id) {
                    tracing::warn!(composer = id, %reason, "composer disconnected; its sessions end");
                    self.composer = None;
                    self.end_all_sessions("the composer left", now);
                }
            }
            Event::Open { name, request, offer, reply } => self.open(name, request, offer, reply, now),
            Event::Abandon { name } => {
                if let Some(&sid) = self.by_name.get(&name) {
                    tracing::warn!(session = %name, "the HTTP request gave up on the composer's answer; dropping the session");
                    self.end_session(sid, "the offer was not answered in time", true, now);
                }
            }
            Event::Close { name, reply } => {
                if let Some(&sid) = self.by_name.get(&name) {
                    self.end_session(sid, "closed by the client", true, now);
                }
                let _ = reply.send(());
            }
            Event::State { reply } => {
                let _ = reply.send(self.state(now));
            }
            Event::Shutdown { reply } => return Some(reply),
        }
        None
    }

    fn worker_join(
        &mut self,
        register: Register,
        peer: SocketAddr,
        link: LinkSender,
        reply: oneshot::Sender<Result<u32, String>>,
        now: Time,
    ) {
        let id = self.next_worker;
        self.next_worker += 1;
        // The scheduler works in rays of a cost-1 kernel; a worker measures primary rays
        // (pixels) per second of its own kernel, which is that unit for path-traced assets.
        if let Err(e) = self.scheduler.add_worker(WorkerId(id), register.rays_per_second, now) {
            tracing::warn!(name = %register.name, %peer, "worker refused: {e}");
            let _ = reply.send(Err(e.to_string()));
            return;
        }
        if reply.send(Ok(id)).is_err() {
            // The connection died while we were registering it.
            let _ = self.scheduler.remove_worker(WorkerId(id), now);
            return;
        }
        tracing::info!(
            worker = id,
            name = %register.name,
            %peer,
            threads = register.threads,
            rays_per_second = format!("{:.0}", register.rays_per_second),
            device = %register.device,
            "worker registered"
        );
        self.metrics.links.workers_joined.inc();
        self.workers.insert(
            id,
            WorkerLink {
                name: register.name,
                peer,
                threads: register.threads,
                kernels: register.kernels,
                rays_per_second: register.rays_per_second,
                device: register.device,
                link,
                joined: now,
                load: None,
                draining: false,
            },
        );
    }

    fn worker_message(&mut self, id: u32, message: Message, now: Time) {
        if !self.workers.contains_key(&id) {
            self.metrics.links.stale_reports.inc();
            return;
        }
        let worker = WorkerId(id);
        match message {
            Message::LoadReport(report) => {
                if let Some(w) = self.workers.get_mut(&id) {
                    w.load = Some(report);
                }
                if let Err(e) = self.scheduler.heartbeat(worker, now) {
                    tracing::debug!(worker = id, "heartbeat: {e}");
                }
            }
            Message::BatchDone(done) => {
                self.metrics.links.rays_traced.inc_by(done.stats.rays);
                self.metrics.links.rays_hit.inc_by(done.stats.rays_hit.min(done.stats.rays));
                self.metrics.links.samples_hidden.inc_by(done.stats.hidden.min(done.stats.rays));
                if let Err(e) = self.scheduler.batch_done(worker, BatchId(done.ids.batch_id), now) {
                    // A batch cancelled, superseded or re-issued meanwhile: nothing to do.
                    tracing::debug!(worker = id, batch = done.ids.batch_id, "late result: {e}");
                }
            }
            Message::BatchFailed(failed) => {
                let batch = failed.ids.batch_id;
                match failed.code {
                    ErrorCode::Cancelled => {
                        tracing::debug!(worker = id, batch, "batch cancelled as asked");
                        return;
                    }
                    ErrorCode::ShuttingDown => {
                        if let Some(w) = self.workers.get_mut(&id)
                            && !w.draining
                        {
                            w.draining = true;
                            tracing::info!(worker = id, "worker is shutting down: no new batches for it");
                            let _ = self.scheduler.drain_worker(worker, now);
                        }
                    }
                    _ => {}
                }
                let known = self.scheduler.batch_failed(worker, BatchId(batch), now);
                let code = failed.code;
                match known {
                    // Shed by a loaded worker after the scheduler had dropped it (its session
                    // closed, its frame superseded): nothing was lost.
                    Err(e)
                        if matches!(
                            code,
                            ErrorCode::DeadlineExpired | ErrorCode::Overloaded | ErrorCode::ShuttingDown
                        ) =>
                    {
                        tracing::debug!(worker = id, batch, ?code, "failure report for a batch no longer there: {e}")
                    }
                    Err(e) => tracing::warn!(worker = id, batch, ?code, "batch failed ({e}): {}", failed.message),
                    Ok(()) if code == ErrorCode::ShuttingDown => {}
                    Ok(()) => tracing::warn!(worker = id, batch, ?code, "batch failed: {}", failed.message),
                }
            }
            Message::Goodbye(goodbye) => {
                tracing::info!(
                    worker = id,
                    returned = goodbye.returned_batches.len(),
                    "worker said goodbye: {}",
                    goodbye.reason
                );
                if let Some(w) = self.workers.remove(&id) {
                    self.metrics.links.workers_left.inc();
                    let _ = w.link.send(LinkCommand::Close(String::new()));
                }
                if let Err(e) = self.scheduler.remove_worker(worker, now) {
                    tracing::warn!(worker = id, "removing worker: {e}");
                }
            }
            Message::Error(e) => tracing::warn!(worker = id, code = ?e.code, "worker reports: {}", e.message),
            other => tracing::warn!(worker = id, kind = %other.kind(), "unexpected message from a worker; ignored"),
        }
    }

    fn composer_join(
        &mut self,
        register: ComposerRegister,
        peer: SocketAddr,
        link: LinkSender,
        reply: oneshot::Sender<Result<u64, String>>,
        now: Time,
    ) {
        if let Some(existing) = &self.composer {
            let reason = format!(
                "composer {:?} ({}) is already registered; this master drives one composer",
                existing.name, existing.peer
            );
            tracing::warn!(name = %register.name, %peer, "composer refused: {reason}");
            let _ = reply.send(Err(reason));
            return;
        }
        let id = self.next_composer;
        self.next_composer += 1;
        if reply.send(Ok(id)).is_err() {
            return;
        }
        tracing::info!(composer = id, name = %register.name, %peer, results = %register.results_address, "composer registered");
        self.composer = Some(ComposerLink {
            id,
            name: register.name,
            peer,
            results_address: register.results_address,
            link,
            joined: now,
        });
    }

    fn composer_message(&mut self, id: u64, message: Message, now: Time) {
        if self.composer.as_ref().is_none_or(|c| c.id != id) {
            return;
        }
        match message {
            Message::StreamOpened(StreamOpened { session_id, answer }) => {
                let sid = SessionId(session_id);
                let Some(reply) = self.pending_opens.remove(&sid) else {
                    tracing::warn!(session_id, "an answer for no pending session; ignored");
                    return;
                };
                match answer {
                    Ok(sdp) => {
                        if let Some(s) = self.sessions.get_mut(&sid) {
                            s.streaming = true;
                        }
                        if reply.send(Ok(sdp)).is_err() {
                            self.end_session(sid, "the client's request went away", true, now);
                        }
                    }
                    Err(reason) => {
                        tracing::info!(session_id, "the composer refused the offer: {reason}");
                        self.end_session(sid, "offer refused", false, now);
                        let _ = reply.send(Err(OpenError::BadOffer(reason)));
                    }
                }
            }
            Message::ClientPose(pose) => self.pose(pose, now),
            Message::CloseStream(CloseStream { session_id, reason }) => {
                let sid = SessionId(session_id);
                if let Some(s) = self.sessions.get(&sid) {
                    tracing::info!(session = %s.name, %reason, "the composer ended the session");
                    self.metrics.links.sessions_ended_by_peer.inc();
                    let name = s.name.clone();
                    self.end_session(sid, &reason, false, now);
                    let _ = self.ended.send(name);
                }
            }
            Message::Goodbye(goodbye) => {
                tracing::info!(composer = id, "composer said goodbye: {}", goodbye.reason);
                if let Some(c) = self.composer.take() {
                    let _ = c.link.send(LinkCommand::Close(String::new()));
                }
                self.end_all_sessions("the composer left", now);
            }
            Message::Error(e) => tracing::warn!(composer = id, code = ?e.code, "composer reports: {}", e.message),
            other => {
                tracing::warn!(composer = id, kind = %other.kind(), "unexpected message from the composer; ignored")
            }
        }
    }

    fn pose(&mut self, pose: ClientPose, now: Time) {
        let sid = SessionId(pose.session_id);
        let Some(s) = self.sessions.get_mut(&sid) else {
            self.metrics.links.poses_unknown_session.inc();
            tracing::debug!(session_id = pose.session_id, "pose for an unknown session; dropped");
            return;
        };
        let r = &s.request;
        // The session's view size, or the same divided by 2^level where the composer codes the
        // stream smaller on a narrow link (`nephele_proto::pose::MAX_SCALE_LEVEL`).
        let size_ok = |w: u32, h: u32| nephele_proto::pose::scale_level_of(r.width, r.height, (w, h)).is_some();
        if pose.views.len() != r.views as usize || pose.views.iter().any(|v| !size_ok(v.width, v.height)) {
            s.poses_rejected += 1;
            tracing::debug!(session = %s.name, views = pose.views.len(), "pose of the wrong view count or size; dropped");
            return;
        }
        match self.scheduler.pose_matrices(sid, &pose.views, now) {
            Ok(()) => {
                s.poses_received += 1;
                if s.poses.len() == POSE_MEMORY {
                    s.poses.pop_front();
                }
                s.poses.push_back(PoseMark {
                    at: now,
                    received: Instant::now(),
                    sequence: pose.sequence,
                    client_time_ms: pose.client_time_ms,
                });
            }
            Err(e) => {
                s.poses_rejected += 1;
                tracing::debug!(session = %s.name, "pose rejected: {e}");
            }
        }
    }

    fn open(
        &mut self,
        name: String,
        request: SessionRequest,
        offer: String,
        reply: oneshot::Sender<Result<String, OpenError>>,
        now: Time,
    ) {
        let Some(scene) = self.catalog.scene(&request.scene) else {
            let _ = reply.send(Err(OpenError::BadOffer(format!("unknown scene {:?}", request.scene))));
            return;
        };
        let Some(composer) = &self.composer else {
            let _ = reply.send(Err(OpenError::Unavailable("no composer is connected".into())));
            return;
        };
        if self.workers.values().all(|w| w.draining) {
            let _ = reply.send(Err(OpenError::Unavailable("no render worker is connected".into())));
            return;
        }
        let spec = SessionSpec {
            target_fps: f64::from(request.target_fps),
            objects: scene.objects.iter().map(|&id| ObjectId(id)).collect(),
        };
        let sid = match self.scheduler.open_session(spec, now) {
            Ok(sid) => sid,
            Err(SchedError::Refused { retry_after }) => {
                tracing::info!(session = %name, retry_after_s = retry_after.as_secs(), "session refused: a user is starved or the farm is full");
                let _ = reply.send(Err(OpenError::Refused { retry_after }));
                return;
            }
            Err(e) => {
                let _ = reply.send(Err(OpenError::BadOffer(e.to_string())));
                return;
            }
        };
        let open = OpenStream {
            session_id: sid.0,
            session_name: name.clone(),
            offer_sdp: offer,
            views: request.views,
            width: request.width,
            height: request.height,
            target_fps: request.target_fps,
        };
        if composer.link.send(LinkCommand::Send(Message::OpenStream(open))).is_err() {
            let _ = self.scheduler.close_session(sid, now);
            let _ = reply.send(Err(OpenError::Unavailable("the composer link is closing".into())));
            return;
        }
        tracing::info!(session = %name, scheduler_id = sid.0, scene = %request.scene, views = request.views, width = request.width, height = request.height, fps = request.target_fps, "session opening: offer sent to the composer");
        self.by_name.insert(name.clone(), sid);
        self.sessions.insert(
            sid,
            LiveSession {
                name,
                request,
                streaming: false,
                poses: VecDeque::new(),
                poses_received: 0,
                poses_rejected: 0,
                plans_sent: 0,
                frames_dropped: 0,
            },
        );
        self.pending_opens.insert(sid, reply);
    }

    /// Ends a session in the scheduler and our tables; tells the composer if `notify`.
    fn end_session(&mut self, sid: SessionId, reason: &str, notify: bool, now: Time) {
        let Some(s) = self.sessions.remove(&sid) else { return };
        self.by_name.remove(&s.name);
        if let Some(reply) = self.pending_opens.remove(&sid) {
            let _ = reply.send(Err(OpenError::Unavailable(reason.to_string())));
        }
        if let Err(e) = self.scheduler.close_session(sid, now) {
            tracing::warn!(session = %s.name, "closing in the scheduler: {e}");
        }
        if notify && let Some(c) = &self.composer {
            let close = CloseStream { session_id: sid.0, reason: nephele_proto::clip_text(reason.to_string()) };
            let _ = c.link.send(LinkCommand::Send(Message::CloseStream(close)));
        }
        tracing::info!(session = %s.name, %reason, poses = s.poses_received, plans = s.plans_sent, "session ended");
    }

    fn end_all_sessions(&mut self, reason: &str, now: Time) {
        let ids: Vec<SessionId> = self.sessions.keys().copied().collect();
        for sid in ids {
            let name = self.sessions.get(&sid).map(|s| s.name.clone());
            self.end_session(sid, reason, false, now);
            if let Some(name) = name {
                let _ = self.ended.send(name);
            }
        }
    }

    fn carry_out(&mut self, action: Action) {
        match action {
            Action::Dispatch { worker, batch } => self.dispatch(worker, &batch),
            Action::Cancel { worker, batch } => {
                if let Some(w) = self.workers.get(&worker.0) {
                    self.metrics.links.cancels_sent.inc();
                    let _ = w
                        .link
                        .send(LinkCommand::Send(Message::Cancel(Cancel { target: CancelTarget::Batch(batch.0) })));
                }
            }
            Action::FrameComplete { session, frame, released, view_size, parts, .. } => {
                self.plan(session, frame, (released, view_size), &parts)
            }
            Action::FrameDropped { session, frame, reason } => {
                if let Some(s) = self.sessions.get_mut(&session) {
                    s.frames_dropped += 1;
                }
                tracing::debug!(session = session.0, frame = frame.0, ?reason, "frame dropped");
            }
            Action::WorkerLost { worker, reissued } => {
                self.metrics.links.workers_lost.inc();
                if let Some(w) = self.workers.remove(&worker.0) {
                    tracing::warn!(worker = worker.0, name = %w.name, reissued, "worker missed its heartbeats: closing its link, batches re-issued");
                    let _ = w.link.send(LinkCommand::Close("missed heartbeats".into()));
                }
            }
            Action::ReleaseResult { task } => {
                if let Some(c) = &self.composer {
                    self.metrics.links.releases_sent.inc();
                    let _ = c.link.send(LinkCommand::Send(Message::ReleaseTask(ReleaseTask { task_id: task.0 })));
                }
            }
        }
    }

    fn dispatch(&mut self, worker: WorkerId, batch: &BatchSpec) {
        let (Some(w), Some(composer)) = (self.workers.get(&worker.0), &self.composer) else {
            // The worker's departure (or the composer's) is queued; the scheduler re-issues
            // the batch when it hears of it, or at its deadline.
            self.metrics.links.batches_unsendable.inc();
            tracing::debug!(worker = worker.0, batch = batch.id.0, "batch not sent: worker or composer gone");
            return;
        };
        let Some(object) = self.catalog.object(batch.object.0) else {
            self.metrics.links.batches_unsendable.inc();
            tracing::error!(object = batch.object.0, "batch for an object not in the catalog");
            return;
        };
        // A render ahead feeds no frame: it names its session (whose previous render it
        // becomes on the worker) and no frame.
        let (session, frame) = match batch.ahead_for {
            Some(session) => (session, FrameId(u64::MAX)),
            None => batch.frames.first().copied().unwrap_or((SessionId(0), FrameId(0))),
        };
        // An environment need not light what the objects in front of it hide, in every
        // session the batch feeds (issue 13).
        let occluders = if self.catalog.is_environment(&object.asset) {
            let scenes: Option<Vec<&str>> =
                batch.frames.iter().map(|(s, _)| self.sessions.get(s).map(|s| s.request.scene.as_str())).collect();
            scenes.map_or_else(Vec::new, |scenes| self.catalog.occluders(object, &scenes))
        } else {
            Vec::new()
        };
        let message = RayBatch {
            ids: BatchIds {
                batch_id: batch.id.0,
                task_id: batch.task.0,
                session_id: session.0,
                frame_id: frame.0,
                view_index: 0,
            },
            asset_id: object.asset.clone(),
            camera: wire_camera(&batch.camera, object.translation),
            pixels: batch.pixels.indices(),
            // The scheduler re-issues the batch elsewhere at its timeout: a copy that has not
            // started by then is not worth starting.
            deadline_in_us: Some(batch.timeout.since(self.now()).as_micros() as u64),
            composer: composer.results_address.clone(),
            derived: batch
                .derived
                .iter()
                .map(|d| {
                    let (session, frame) = d.frames.first().copied().unwrap_or((session, frame));
                    DerivedView {
                        ids: BatchIds {
                            batch_id: batch.id.0,
                            task_id: d.task.0,
                            session_id: session.0,
                            frame_id: frame.0,
                            view_index: 0,
                        },
                        camera: wire_camera(&d.camera, object.translation),
                        pixels: d.pixels.indices(),
                    }
                })
                .collect(),
            reuse: ReuseLimits {
                previous_frames: self.previous_frames,
                rows_complete: batch.rows_complete,
                ahead: batch.ahead_for.is_some(),
                ..ReuseLimits::default()
            },
            occluders,
        };
        self.metrics.links.batches_sent.inc();
        let _ = w.link.send(LinkCommand::Send(Message::RayBatch(message)));
    }

    /// The composer's plan of a completed frame, `released` at that time with views of
    /// `view_size` (the session's, or smaller while the stream is coded smaller).
    fn plan(
        &mut self,
        session: SessionId,
        frame: FrameId,
        (released, view_size): (Time, (u32, u32)),
        parts: &[FramePart],
    ) {
        let Some(s) = self.sessions.get_mut(&session) else { return };
        let Some(composer) = &self.composer else { return };
        // The pose the frame was released with: the newest received at or before its release.
        let pose = s.poses.iter().rev().find(|p| p.at <= released).or(s.poses.front()).copied();
        let period_us = (1e6 / f64::from(s.request.target_fps.max(1e-3))) as u64;
        let plan = FramePlan {
            session_id: session.0,
            frame_id: frame.0,
            pose_sequence: pose.map_or(0, |p| p.sequence),
            client_time_ms: pose.map_or(0.0, |p| p.client_time_ms),
            width: view_size.0,
            height: view_size.1,
            views: s.request.views,
            parts: parts
                .iter()
                .map(|p| PlanPart { view: p.view, task_id: p.task.0, object_id: u64::from(p.object.0) })
                .collect(),
            // Every batch is in (BatchDone follows delivery); one more frame interval covers
            // results still in flight on other connections.
            deadline_in_us: Some(period_us),
        };
        if composer.link.send(LinkCommand::Send(Message::FramePlan(plan))).is_ok() {
            s.plans_sent += 1;
            self.metrics.links.plans_sent.inc();
            if let Some(p) = pose {
                let ms = p.received.elapsed().as_secs_f64() * 1e3;
                self.pose_to_plan_ms.push(ms);
                self.metrics.pose_to_plan_ms.observe(ms);
            }
        }
    }

    fn state(&self, now: Time) -> Value {
        let snapshot =
            serde_json::to_value(self.scheduler.snapshot(now)).unwrap_or_else(|e| json!({ "error": e.to_string() }));
        let workers: Vec<Value> = self
            .workers
            .iter()
            .map(|(id, w)| {
                json!({
                    "id": id,
                    "name": w.name,
                    "address": w.peer.to_string(),
                    "threads": w.threads,
                    "kernels": w.kernels,
                    "calibrated_rays_per_s": w.rays_per_second,
                    "device": w.device,
                    "draining": w.draining,
                    "connected_s": now.since(w.joined).as_secs_f64(),
                    "load": w.load,
                })
            })
            .collect();
        let composer = self.composer.as_ref().map(|c| {
            json!({
                "id": c.id,
                "name": c.name,
                "address": c.peer.to_string(),
                "results_address": c.results_address,
                "connected_s": now.since(c.joined).as_secs_f64(),
            })
        });
        let sessions: Vec<Value> = self
            .sessions
            .iter()
            .map(|(sid, s)| {
                json!({
                    "id": s.name,
                    "scheduler_id": sid.0,
                    "scene": s.request.scene,
                    "views": s.request.views,
                    "width": s.request.width,
                    "height": s.request.height,
                    "target_fps": s.request.target_fps,
                    "streaming": s.streaming,
                    "poses": s.poses_received,
                    "poses_rejected": s.poses_rejected,
                    "frames_planned": s.plans_sent,
                    "frames_dropped": s.frames_dropped,
                })
            })
            .collect();
        let c = &self.metrics.links;
        json!({
            "uptime_s": now.as_secs_f64(),
            "workers": workers,
            "composer": composer,
            "sessions": sessions,
            "scheduler": snapshot,
            "live": {
                "round_us": self.round_us.summary(),
                "pose_to_plan_ms": self.pose_to_plan_ms.summary(),
                "workers_joined": c.workers_joined.get(),
                "workers_left": c.workers_left.get(),
                "workers_lost": c.workers_lost.get(),
                "batches_sent": c.batches_sent.get(),
                "batches_unsendable": c.batches_unsendable.get(),
                "cancels_sent": c.cancels_sent.get(),
                "plans_sent": c.plans_sent.get(),
                "releases_sent": c.releases_sent.get(),
                "poses_unknown_session": c.poses_unknown_session.get(),
                "sessions_refused": c.sessions_refused.get(),
                "sessions_ended_by_peer": c.sessions_ended_by_peer.get(),
                "stale_reports": c.stale_reports.get(),
                "rays_traced": c.rays_traced.get(),
                "rays_hit": c.rays_hit.get(),
                "samples_hidden": c.samples_hidden.get(),
            },
        })
    }

    /// Goodbye to every link, end every session, and wait (briefly) for the goodbyes to go
    /// out.
    async fn shutdown(mut self, reply: oneshot::Sender<()>) {
        let now = self.now();
        tracing::info!(
            workers = self.workers.len(),
            sessions = self.sessions.len(),
            "farm shutting down: saying goodbye"
        );
        for (_, reply) in self.pending_opens.drain() {
            let _ = reply.send(Err(OpenError::Unavailable("the master is shutting down".into())));
        }
        let mut links = Vec::new();
        for (_, w) in std::mem::take(&mut self.workers) {
            let _ = w.link.send(LinkCommand::Close("the master is shutting down".into()));
            links.push(w.link);
        }
        self.end_all_sessions("the master is shutting down", now);
        if let Some(c) = self.composer.take() {
            let _ = c.link.send(LinkCommand::Close("the master is shutting down".into()));
            links.push(c.link);
        }
        let all_closed = futures_util::future::join_all(links.iter().map(|l| l.closed()));
        if tokio::time::timeout(Duration::from_secs(3), all_closed).await.is_err() {
            tracing::warn!("some links did not close within 3 s");
        }
        let _ = reply.send(());
    }
}

async fn sleep_until(at: Option<tokio::time::Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nephele_proto::{BatchDone, KernelStats};

    fn peer() -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], 1))
    }

    async fn next(rx: &mut mpsc::UnboundedReceiver<LinkCommand>) -> LinkCommand {
        tokio::time::timeout(Duration::from_secs(10), rx.recv()).await.expect("a command in time").expect("link open")
    }

    #[test]
    fn the_wire_camera_sees_the_object_where_the_world_camera_sees_its_placement() {
        let camera =
            Camera::look_at(64, 48, 0.8, Vec3::new(1.0, -6.0, 2.0), Vec3::new(0.5, 0.5, 0.0), Vec3::Z).expect("camera");
        let translation = Vec3::new(-1.4, 2.7, 0.3);
        let wire = wire_camera(&camera, translation);
        let object_camera = wire.camera().expect("a valid camera");
        for local in [Vec3::ZERO, Vec3::new(0.3, -0.2, 0.5), Vec3::new(-0.6, 0.4, -0.1)] {
            let world = local + translation;
            let (a, b) = (camera.project(world).expect("in view"), object_camera.project(local).expect("in view"));
            assert!((a - b).length() < 1e-3, "{a} vs {b}");
            assert!((camera.view_depth(world) - object_camera.view_depth(local)).abs() < 1e-4);
        }
        // At the origin the view matrix passes through unchanged.
        assert_eq!(wire_camera(&camera, Vec3::ZERO).view, camera.world_to_camera());
    }

    /// The actor end to end over in-memory links: a worker and a composer join, a session
    /// opens, a pose becomes ray batches (each object of the `default` scene, moved into its
    /// own frame), the completed frame becomes a plan, the session closes, the farm shuts
    /// down with goodbyes.
    #[tokio::test]
    async fn poses_become_batches_and_completed_frames_become_plans() {
        let catalog = Catalog::builtin().expect("catalog");
        let (farm, task, _ended) = Farm::start(FarmConfig::default(), catalog).expect("farm");

        let (wtx, mut wrx) = mpsc::unbounded_channel();
        let (reply, answer) = oneshot::channel();
        let register = Register {
            name: "w".into(),
            threads: 1,
            kernels: vec!["pathtrace".into()],
            rays_per_second: 1e6,
            device: "cpu".into(),
        };
        assert!(farm.send(Event::WorkerJoin { register, peer: peer(), link: wtx, reply }));
        let wid = answer.await.expect("reply").expect("worker accepted");
        let (ctx, mut crx) = mpsc::unbounded_channel();
        let (reply, answer) = oneshot::channel();
        let register = ComposerRegister { name: "c".into(), results_address: "127.0.0.1:9".into() };
        assert!(farm.send(Event::ComposerJoin { register, peer: peer(), link: ctx, reply }));
        let cid = answer.await.expect("reply").expect("composer accepted");
        // A second composer is refused.
        let (other, _other_rx) = mpsc::unbounded_channel();
        let (reply, answer) = oneshot::channel();
        let register = ComposerRegister { name: "c2".into(), results_address: "127.0.0.1:10".into() };
        assert!(farm.send(Event::ComposerJoin { register, peer: peer(), link: other, reply }));
        assert!(answer.await.expect("reply").is_err());

        let request = SessionRequest { scene: "default".into(), views: 1, width: 64, height: 48, target_fps: 30.0 };
        let opening = tokio::spawn(farm.open("s1-abc".into(), request, "v=0 offer".into()));
        let LinkCommand::Send(Message::OpenStream(open)) = next(&mut crx).await else { panic!("expected the offer") };
        assert_eq!((open.session_name.as_str(), open.offer_sdp.as_str(), open.width), ("s1-abc", "v=0 offer", 64));
        let answer = StreamOpened { session_id: open.session_id, answer: Ok("v=0 answer".into()) };
        assert!(farm.send(Event::ComposerMessage(cid, Message::StreamOpened(answer))));
        assert_eq!(opening.await.expect("task").expect("opened"), "v=0 answer");

        let scene = farm.catalog().scene("default").expect("scene").clone();
        let v = &scene.view;
        let camera =
            Camera::look_at(64, 48, v.fov_y_deg.to_radians(), Vec3::from(v.eye), Vec3::from(v.target), Vec3::Z)
                .expect("camera");
        let pose = ViewProjection::of_camera(&camera, 0.05, 100.0);
        let client_pose =
            ClientPose { session_id: open.session_id, sequence: 7, client_time_ms: 140.0, views: vec![pose] };
        assert!(farm.send(Event::ComposerMessage(cid, Message::ClientPose(client_pose))));

        // Serve batches until the plan comes.
        let mut tasks = std::collections::BTreeSet::new();
        let mut assets = std::collections::BTreeSet::new();
        let (mut traced, mut hit) = (0u64, 0u64);
        let plan = loop {
            tokio::select! {
                command = next(&mut wrx) => {
                    let LinkCommand::Send(Message::RayBatch(batch)) = command else { panic!("expected a batch") };
                    assert_eq!(batch.composer, "127.0.0.1:9");
                    assert_eq!(batch.ids.session_id, open.session_id);
                    assert!(batch.pixels.iter().all(|&p| p < 64 * 48) && !batch.pixels.is_empty());
                    let object = farm.catalog().objects().iter().find(|o| o.asset == batch.asset_id && scene.objects.contains(&o.id)).expect("object");
                    // The batch's camera sees the object (in its own frame) where the pose sees
                    // its placement.
                    let wire = batch.camera;
                    let local = wire.camera().expect("camera");
                    let center = object.bounds.center();
                    if let (Some(a), Some(b)) = (camera.project(center), local.project(center - object.translation)) {
                        assert!((a - b).length() < 1e-2, "{} {a} {b}", object.asset);
                    }
                    tasks.insert(batch.ids.task_id);
                    assets.insert(batch.asset_id.clone());
                    let rays = batch.pixels.len() as u64;
                    let stats = KernelStats { rays, rays_hit: rays / 2, queries: rays / 2, hidden: 0 };
                    let done = BatchDone { ids: batch.ids, pixels: batch.pixels.len() as u32, render_time_us: 10, stats };
                    assert!(farm.send(Event::WorkerMessage(wid, Message::BatchDone(done))));
                    (traced, hit) = (traced + rays, hit + rays / 2);
                }
                command = next(&mut crx) => match command {
                    LinkCommand::Send(Message::FramePlan(plan)) => break plan,
                    other => panic!("unexpected {other:?}"),
                },
            }
        };
        assert_eq!(assets.len(), 3, "every object of the default scene is in its first view: {assets:?}");
        assert_eq!((plan.session_id, plan.pose_sequence, plan.client_time_ms), (open.session_id, 7, 140.0));
        let planned: std::collections::BTreeSet<u64> = plan.parts.iter().map(|p| p.task_id).collect();
        assert_eq!(planned, tasks);
        assert!(plan.parts.iter().all(|p| p.view == 0));

        // Poses the composer sends smaller while it codes the stream smaller (half or a
        // quarter of each side) are taken; any other size is not.
        for (sequence, (w, h)) in (8..).zip([(32, 24), (16, 12), (48, 36), (8, 6)]) {
            let camera =
                Camera::look_at(w, h, v.fov_y_deg.to_radians(), Vec3::from(v.eye), Vec3::from(v.target), Vec3::Z)
                    .expect("camera");
            let views = vec![ViewProjection::of_camera(&camera, 0.05, 100.0)];
            let pose = ClientPose { session_id: open.session_id, sequence, client_time_ms: 150.0, views };
            assert!(farm.send(Event::ComposerMessage(cid, Message::ClientPose(pose))));
        }
        let state = farm.farm_state().await;
        assert_eq!(
            (state["sessions"][0]["poses"].as_u64(), state["sessions"][0]["poses_rejected"].as_u64()),
            (Some(3), Some(2)),
            "{state:#}"
        );

        let state = farm.farm_state().await;
        assert_eq!(state["workers"][0]["name"], "w");
        assert_eq!(state["composer"]["name"], "c");
        assert_eq!(state["sessions"][0]["id"], "s1-abc");
        assert!(state["live"]["plans_sent"].as_u64() >= Some(1), "{state:#}");
        // The reports' ray counts are summed (every report is in: the plan came after them).
        assert_eq!(state["live"]["rays_traced"].as_u64(), Some(traced), "{state:#}");
        assert_eq!(state["live"]["rays_hit"].as_u64(), Some(hit), "{state:#}");

        farm.close("s1-abc".into()).await;
        let close = loop {
            match next(&mut crx).await {
                LinkCommand::Send(Message::CloseStream(close)) => break close,
                LinkCommand::Send(Message::FramePlan(_) | Message::ReleaseTask(_)) => {}
                other => panic!("unexpected {other:?}"),
            }
        };
        assert_eq!(close.session_id, open.session_id);

        let shutdown = tokio::spawn({
            let farm = farm.clone();
            async move { farm.shutdown().await }
        });
        let goodbye = loop {
            match next(&mut wrx).await {
                LinkCommand::Close(reason) => break reason,
                LinkCommand::Send(_) => {}
            }
        };
        assert!(goodbye.contains("shutting down"));
        drop((wrx, crx));
        shutdown.await.expect("shutdown");
        drop(farm);
        task.await.expect("actor");
    }
}
