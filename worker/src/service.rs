//! The worker's life: calibrate, connect, register, serve batches, report load, drain.
//!
//! One event loop per master connection owns the queue and the in-flight table (no locks);
//! each batch runs as its own task: load the asset and render on blocking threads (the
//! render itself on the worker's rayon pool), then send the result to the batch's composer.
//! The loop hears back through a channel and tells the master (`BatchDone` or
//! `BatchFailed`).

use std::collections::{HashMap, VecDeque};
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_kernels::kernel::all_pixels;
use nephele_proto::stream::{Connection, framed, handshake, recv};
use nephele_proto::{
    BatchDone, BatchFailed, BatchIds, BatchResult, Cancel, CancelTarget, ErrorCode, ErrorMessage, FrameConfig, Goodbye,
    KernelStats, LoadReport, Message, ProtoError, RayBatch, Register, Registered, ResultEncoding, Role, clip_text,
    error_message, validate,
};
use nephele_transport::FarmStream;
use thiserror::Error;
use tokio::sync::mpsc;

use crate::assets::AssetLoader;
use crate::composer::ComposerLinks;
use crate::derive::{Absent, Derived, derive_view, derive_view_with};
use crate::metrics::{Phase, WorkerMetrics};
use crate::temporal::{Made, Plan, Previous, PreviousRenders};

/// Pixels of previous renders a worker keeps (24 bytes each: 96 MiB), enough for a dozen
/// 720p users' objects.
const PREVIOUS_RENDER_PIXELS: usize = 4 << 20;

/// How a worker runs.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Master address, `host:port`.
    pub master: String,
    /// Name shown by the master (`[A-Za-z0-9._-]`, 1 to 64 bytes).
    pub name: String,
    /// Render threads.
    pub threads: usize,
    /// Batches rendering at once (each uses the whole pool; two keep it busy between
    /// batches while a result is being sent).
    pub max_concurrent_batches: usize,
    pub frame: FrameConfig,
    /// Limit for connecting, handshakes, registration and each send to a composer.
    pub io_timeout: Duration,
    /// How long to keep trying to reach the master (at start or after losing it) before
    /// giving up with an error.
    pub reconnect_for: Duration,
    /// How long in-flight batches may take to finish after a shutdown request.
    pub drain_timeout: Duration,
    /// Most batches waiting; more are refused with `ErrorCode::Overloaded`.
    pub max_queued_batches: usize,
    /// Asset rendered at start-up to measure throughput.
    pub calibration_asset: String,
    /// Image side of the calibration render.
    pub calibration_size: u32,
    /// What the neural kernels run on, reported at registration (`cpu (AVX2+FMA)`, a GPU
    /// adapter's name).
    pub device: String,
    /// How results travel to the composer: compact (only the pixels the object touched,
    /// half floats) or f32 (every pixel, exact).
    pub result_encoding: ResultEncoding,
    /// Counters and readiness (serve them with `nephele_telemetry::ops_router`).
    pub metrics: Arc<WorkerMetrics>,
    /// The farm credential ([`nephele_proto::auth`]) proved to the master and the composers,
    /// and demanded of them; `None` joins only an open farm.
    pub farm_secret: Option<nephele_proto::auth::FarmSecret>,
    /// TLS to the master and the composers, trusting the farm certificate
    /// ([`nephele_transport`]); `None`: plain TCP.
    pub farm_tls: Option<nephele_transport::FarmTls>,
}

impl WorkerConfig {
    pub fn new(master: impl Into<String>, name: impl Into<String>, threads: usize) -> WorkerConfig {
        WorkerConfig {
            master: master.into(),
            name: name.into(),
            threads,
            max_concurrent_batches: 2,
            frame: FrameConfig::default(),
            io_timeout: Duration::from_secs(10),
            reconnect_for: Duration::from_secs(30),
            drain_timeout: Duration::from_secs(30),
            max_queued_batches: 4096,
            calibration_asset: "diffuse".into(),
            device: "cpu".into(),
            calibration_size: 64,
            result_encoding: ResultEncoding::Compact,
            metrics: Arc::new(WorkerMetrics::new()),
            farm_secret: None,
            farm_tls: None,
        }
    }
}

#[derive(Debug, Error)]
pub enum WorkerError {
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error("building the render thread pool: {0}")]
    Pool(#[from] rayon::ThreadPoolBuildError),
    #[error("calibration render failed: {0}")]
    Calibration(String),
    #[error("the master at {addr} and this worker disagree on the farm secret: {reason}")]
    FarmCredential { addr: String, reason: String },
    #[error("gave up on the master at {addr} after {seconds:.0} s: {last_error}")]
    MasterUnreachable { addr: String, seconds: f64, last_error: String },
}

/// What the worker shares with its batch tasks.
#[derive(Debug)]
struct Shared {
    pool: Arc<rayon::ThreadPool>,
    loader: Arc<dyn AssetLoader>,
    composers: ComposerLinks,
    worker_id: AtomicU64,
    result_encoding: ResultEncoding,
    metrics: Arc<WorkerMetrics>,
    /// Full renders later frames of the same views may be taken from.
    previous: PreviousRenders,
}

/// Runs a worker until `shutdown` resolves (then drains and says goodbye: `Ok`) or the
/// master stays unreachable for `config.reconnect_for` (`Err`).
pub async fn run<F: Future<Output = ()>>(
    config: WorkerConfig,
    loader: Arc<dyn AssetLoader>,
    shutdown: F,
) -> Result<(), WorkerError> {
    validate::worker_name(&config.name).map_err(|e| WorkerError::Config(e.to_string()))?;
    validate::address(&config.master).map_err(|e| WorkerError::Config(format!("--master: {e}")))?;
    if config.threads == 0 || config.max_concurrent_batches == 0 {
        return Err(WorkerError::Config("threads and concurrent batches must be at least 1".into()));
    }
    let pool =
        rayon::ThreadPoolBuilder::new().num_threads(config.threads).thread_name(|i| format!("render-{i}")).build()?;
    let shared = Arc::new(Shared {
        previous: PreviousRenders::new(PREVIOUS_RENDER_PIXELS),
        pool: Arc::new(pool),
        loader,
        composers: ComposerLinks::new(
            config.frame,
            config.io_timeout,
            config.farm_secret.clone(),
            config.farm_tls.clone(),
        ),
        worker_id: AtomicU64::new(0),
        result_encoding: config.result_encoding,
        metrics: config.metrics.clone(),
    });
    let metrics = config.metrics.clone();
    metrics.set_phase(Phase::Calibrating);
    let rays_per_second = calibrate(&shared, &config).await?;
    tracing::info!(name = %config.name, threads = config.threads, rays_per_second = format!("{rays_per_second:.0}"), "calibrated");
    let register = Register {
        name: config.name.clone(),
        threads: u32::try_from(config.threads).unwrap_or(u32::MAX),
        kernels: shared.loader.kernel_kinds(),
        rays_per_second,
        device: config.device.clone(),
    };

    metrics.set_phase(Phase::Connecting);
    let mut shutdown = std::pin::pin!(shutdown);
    let mut lost_since = Instant::now();
    let mut backoff = Duration::from_millis(50);
    loop {
        let attempt = tokio::select! {
            attempt = connect_and_register(&config, &register) => attempt,
            () = &mut shutdown => {
                tracing::info!("shutdown requested while not connected to the master; exiting");
                return Ok(());
            }
        };
        match attempt {
            Ok((conn, registered)) => {
                tracing::info!(master = %config.master, worker_id = registered.worker_id, "registered");
                shared.worker_id.store(registered.worker_id, Ordering::Relaxed);
                metrics.set_phase(Phase::Registered);
                metrics.master_connections.inc();
                backoff = Duration::from_millis(50);
                let session = Session::new(&config, &shared, registered);
                match session.run(conn, shutdown.as_mut()).await {
                    SessionEnd::ShutDown => return Ok(()),
                    SessionEnd::MasterLost(reason) => {
                        metrics.set_phase(Phase::Connecting);
                        tracing::warn!(master = %config.master, "lost the master: {reason}; reconnecting");
                        lost_since = Instant::now();
                    }
                }
            }
            Err(
                e @ (ProtoError::Unauthenticated(_) | ProtoError::Refused { code: ErrorCode::Unauthenticated, .. }),
            ) => {
                // Retrying cannot help: the secret is wrong on one side.
                return Err(WorkerError::FarmCredential { addr: config.master.clone(), reason: e.to_string() });
            }
            Err(e) => {
                let waited = lost_since.elapsed();
                if waited >= config.reconnect_for {
                    return Err(WorkerError::MasterUnreachable {
                        addr: config.master.clone(),
                        seconds: waited.as_secs_f64(),
                        last_error: e.to_string(),
                    });
                }
                tracing::debug!(master = %config.master, "master not reachable yet: {e}");
                tokio::select! {
                    () = tokio::time::sleep(backoff) => {}
                    () = &mut shutdown => return Ok(()),
                }
                backoff = (backoff * 2).min(Duration::from_secs(2));
            }
        }
    }
}

/// Renders the calibration asset once and returns pixels (primary rays) per second.
async fn calibrate(shared: &Arc<Shared>, config: &WorkerConfig) -> Result<f64, WorkerError> {
    let shared = shared.clone();
    let asset = config.calibration_asset.clone();
    let size = config.calibration_size.max(8);
    let job = tokio::task::spawn_blocking(move || -> Result<f64, String> {
        let kernel = shared.loader.load(&asset).map_err(|e| e.to_string())?;
        let bounds = kernel.bounds();
        let radius = 0.5 * bounds.size().length().max(1e-3);
        let eye = bounds.center() + Vec3::new(1.0, -1.7, 0.9).normalize() * radius * 3.0;
        let camera = Camera::look_at(size, size, 0.8, eye, bounds.center(), Vec3::Z).map_err(|e| e.to_string())?;
        let pixels = all_pixels(&camera);
        // A warm-up render first: a GPU driver compiles the shader at the first dispatch,
        // and caches warm up on any device; the timed render is the steady state.
        shared.pool.install(|| kernel.render_pixels(&camera, &pixels)).map_err(|e| e.to_string())?;
        let start = Instant::now();
        shared.pool.install(|| kernel.render_pixels(&camera, &pixels)).map_err(|e| e.to_string())?;
        Ok(pixels.len() as f64 / start.elapsed().as_secs_f64().max(1e-9))
    });
    job.await.map_err(|e| WorkerError::Calibration(e.to_string()))?.map_err(WorkerError::Calibration)
}

async fn connect_and_register(
    config: &WorkerConfig,
    register: &Register,
) -> Result<(Connection<FarmStream>, Registered), ProtoError> {
    let stream = nephele_transport::connect(&config.master, config.farm_tls.as_ref(), config.io_timeout).await?;
    let mut conn = framed(stream, config.frame);
    handshake(&mut conn, Role::Worker, &[Role::Master], config.farm_secret.as_ref(), config.io_timeout).await?;
    conn.send(&Message::Register(register.clone())).await?;
    match tokio::time::timeout(config.io_timeout, recv(&mut conn)).await {
        Err(_) => Err(ProtoError::Timeout("Registered")),
        Ok(Ok(Message::Registered(registered))) => Ok((conn, registered)),
        Ok(Ok(other)) => Err(nephele_proto::stream::unexpected("Registered", other)),
        Ok(Err(e)) => Err(e),
    }
}

enum SessionEnd {
    ShutDown,
    MasterLost(String),
}

/// A batch that is rendering.
struct InFlight {
    ids: BatchIds,
    cancelled: Arc<AtomicBool>,
}

/// What a batch task reports back.
struct Done {
    slot: u64,
    ids: BatchIds,
    pixels: u64,
    outcome: Result<BatchDone, (ErrorCode, String)>,
}

/// A batch waiting for a render slot, with its deadline on this process's monotonic clock
/// (the wire carries time left, not a wall-clock instant, so that the master's and this
/// machine's clocks need not agree).
struct Queued {
    batch: RayBatch,
    deadline: Option<Instant>,
}

/// One master connection's state.
struct Session<'a> {
    config: &'a WorkerConfig,
    shared: &'a Arc<Shared>,
    registered: Registered,
    queue: VecDeque<Queued>,
    in_flight: HashMap<u64, InFlight>,
    next_slot: u64,
    outbox: Vec<Message>,
    draining: bool,
    returned: Vec<u64>,
}

impl<'a> Session<'a> {
    fn new(config: &'a WorkerConfig, shared: &'a Arc<Shared>, registered: Registered) -> Session<'a> {
        Session {
            config,
            shared,
            registered,
            queue: VecDeque::new(),
            in_flight: HashMap::new(),
            next_slot: 0,
            outbox: Vec::new(),
            draining: false,
            returned: Vec::new(),
        }
    }

    async fn run<F: Future<Output = ()>>(
        mut self,
        mut conn: Connection<FarmStream>,
        mut shutdown: Pin<&mut F>,
    ) -> SessionEnd {
        // The load report's totals are the metrics' counters: they survive reconnections.
        let metrics = self.shared.metrics.clone();
        let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Done>();
        let interval = Duration::from_millis(u64::from(self.registered.load_report_interval_ms));
        let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + interval, interval);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut last_report = (Instant::now(), metrics.rays_done.get());
        let mut drain_deadline = tokio::time::Instant::now();
        loop {
            while !self.draining && self.in_flight.len() < self.config.max_concurrent_batches {
                let Some(queued) = self.queue.pop_front() else { break };
                self.start(queued, &done_tx);
            }
            if self.draining && self.in_flight.is_empty() {
                return self.say_goodbye(conn, "shutting down").await;
            }
            self.shared.metrics.queued_batches.set(self.queue.len() as i64);
            self.shared.metrics.in_flight_batches.set(self.in_flight.len() as i64);
            if let Err(e) = flush(&mut conn, &mut self.outbox).await {
                return self.lost(format!("sending to the master: {e}"));
            }
            tokio::select! {
                () = &mut shutdown, if !self.draining => {
                    tracing::info!(
                        in_flight = self.in_flight.len(),
                        queued = self.queue.len(),
                        "shutdown requested: finishing in-flight batches, handing queued ones back"
                    );
                    self.draining = true;
                    self.shared.metrics.set_phase(Phase::Draining);
                    drain_deadline = tokio::time::Instant::now() + self.config.drain_timeout;
                    for queued in std::mem::take(&mut self.queue) {
                        self.hand_back(queued.batch.ids);
                    }
                }
                () = tokio::time::sleep_until(drain_deadline), if self.draining => {
                    tracing::warn!(in_flight = self.in_flight.len(), "drain timeout: handing unfinished batches back");
                    let ids: Vec<BatchIds> = self.in_flight.drain().map(|(_, f)| f.ids).collect();
                    for ids in ids {
                        self.hand_back(ids);
                    }
                    return self.say_goodbye(conn, "shutting down (drain timeout)").await;
                }
                item = conn.next() => match item {
                    None => return self.lost("connection closed".into()),
                    Some(Err(e)) => {
                        tracing::warn!("closing the master connection: {e}");
                        if !matches!(e, ProtoError::Io(_)) {
                            let _ = tokio::time::timeout(Duration::from_secs(1), conn.send(&error_message(&e))).await;
                        }
                        return self.lost(e.to_string());
                    }
                    Some(Ok(Err(rejected))) => {
                        tracing::warn!("rejected a message from the master: {rejected}");
                        let message = clip_text(rejected.to_string());
                        match rejected.ids {
                            Some(ids) => self.outbox.push(Message::BatchFailed(BatchFailed { ids, code: ErrorCode::InvalidField, message })),
                            None => self.outbox.push(Message::Error(ErrorMessage { code: ErrorCode::InvalidField, message })),
                        }
                    }
                    Some(Ok(Ok(message))) => self.handle(message),
                },
                Some(done) = done_rx.recv() => self.finish(done),
                _ = tick.tick() => {
                    let elapsed = last_report.0.elapsed().as_secs_f64().max(1e-6);
                    let rays_done = metrics.rays_done.get();
                    let recent = rays_done.saturating_sub(last_report.1) as f64 / elapsed;
                    last_report = (Instant::now(), rays_done);
                    self.outbox.push(Message::LoadReport(LoadReport {
                        in_flight_batches: self.in_flight.len() as u32,
                        queued_batches: self.queue.len() as u32,
                        queued_rays: self.queue.iter().map(|q| q.batch.pixels.len() as u64).sum(),
                        recent_rays_per_second: recent,
                        batches_done: metrics.batches_done.get(),
                        rays_done,
                    }));
                }
            }
        }
    }

    /// The master connection is gone. While draining there is nobody left to hand work
    /// back to: finish (in-flight results still reach their composers).
    fn lost(&self, reason: String) -> SessionEnd {
        if self.draining {
            tracing::warn!("lost the master while shutting down: {reason}");
            SessionEnd::ShutDown
        } else {
            SessionEnd::MasterLost(reason)
        }
    }

    fn handle(&mut self, message: Message) {
        match message {
            Message::RayBatch(batch) if self.draining => self.hand_back(batch.ids),
            Message::RayBatch(batch) if self.queue.len() >= self.config.max_queued_batches => {
                let message = format!("{} batches already queued", self.queue.len());
                self.fail(batch.ids, ErrorCode::Overloaded, message);
            }
            Message::RayBatch(batch) => {
                tracing::debug!(batch = batch.ids.batch_id, pixels = batch.pixels.len(), asset = %batch.asset_id, "batch queued");
                let deadline = batch.deadline_in_us.map(|us| Instant::now() + Duration::from_micros(us));
                self.queue.push_back(Queued { batch, deadline });
            }
            Message::Cancel(Cancel { target }) => {
                let matches = |ids: &BatchIds| match target {
                    CancelTarget::Batch(id) => ids.batch_id == id,
                    CancelTarget::Frame { session_id, frame_id } => {
                        ids.session_id == session_id && ids.frame_id == frame_id
                    }
                    CancelTarget::Session(session_id) => ids.session_id == session_id,
                };
                let (dropped, kept): (VecDeque<Queued>, VecDeque<Queued>) =
                    std::mem::take(&mut self.queue).into_iter().partition(|q| matches(&q.batch.ids));
                self.queue = kept;
                for Queued { batch, .. } in dropped {
                    self.fail(batch.ids, ErrorCode::Cancelled, "cancelled before it started".into());
                }
                for flight in self.in_flight.values().filter(|f| matches(&f.ids)) {
                    flight.cancelled.store(true, Ordering::Release);
                }
            }
            Message::Error(e) => tracing::warn!(code = ?e.code, "the master reports: {}", e.message),
            Message::Goodbye(g) => tracing::info!("the master says goodbye: {}", g.reason),
            other => {
                tracing::warn!(kind = %other.kind(), "unexpected message from the master");
                self.outbox.push(Message::Error(ErrorMessage {
                    code: ErrorCode::Unexpected,
                    message: format!("a worker does not accept {} messages", other.kind()),
                }));
            }
        }
    }

    fn start(&mut self, Queued { batch, deadline }: Queued, done_tx: &mpsc::UnboundedSender<Done>) {
        if let Some(deadline) = deadline {
            let now = Instant::now();
            if now >= deadline {
                let late_ms = now.duration_since(deadline).as_millis();
                self.fail(
                    batch.ids,
                    ErrorCode::DeadlineExpired,
                    format!("deadline passed {late_ms} ms before the batch could start"),
                );
                return;
            }
        }
        let slot = self.next_slot;
        self.next_slot += 1;
        let cancelled = Arc::new(AtomicBool::new(false));
        self.in_flight.insert(slot, InFlight { ids: batch.ids, cancelled: cancelled.clone() });
        let shared = self.shared.clone();
        let done_tx = done_tx.clone();
        tokio::spawn(async move {
            let (ids, pixels) = (batch.ids, batch.pixels.len() as u64);
            let outcome = render_and_deliver(&shared, batch, &cancelled).await;
            // The session may be gone (master lost); the result went to the composer anyway.
            let _ = done_tx.send(Done { slot, ids, pixels, outcome });
        });
    }

    fn finish(&mut self, done: Done) {
        if self.in_flight.remove(&done.slot).is_none() {
            return;
        }
        match done.outcome {
            Ok(batch_done) => {
                self.shared.metrics.batches_done.inc();
                self.shared.metrics.rays_done.inc_by(done.pixels);
                self.outbox.push(Message::BatchDone(batch_done));
            }
            // Cancelled as the master asked (its session closed, its frame superseded): routine.
            Err((code @ ErrorCode::Cancelled, message)) => {
                tracing::debug!(batch = done.ids.batch_id, ?code, "batch not delivered: {message}");
                self.fail(done.ids, code, message);
            }
            Err((code, message)) => {
                tracing::warn!(batch = done.ids.batch_id, ?code, "batch failed: {message}");
                self.fail(done.ids, code, message);
            }
        }
    }

    fn fail(&mut self, ids: BatchIds, code: ErrorCode, message: String) {
        self.shared.metrics.failed(code);
        self.outbox.push(Message::BatchFailed(BatchFailed { ids, code, message: clip_text(message) }));
    }

    /// Tells the master at once that a batch will not be rendered here, so that it can
    /// re-issue it without waiting for the goodbye.
    fn hand_back(&mut self, ids: BatchIds) {
        self.returned.push(ids.batch_id);
        self.fail(ids, ErrorCode::ShuttingDown, "the worker is shutting down".into());
    }

    async fn say_goodbye(mut self, mut conn: Connection<FarmStream>, reason: &str) -> SessionEnd {
        self.returned.truncate(validate::MAX_RETURNED_BATCHES);
        self.outbox.push(Message::Goodbye(Goodbye {
            reason: reason.into(),
            returned_batches: std::mem::take(&mut self.returned),
        }));
        match tokio::time::timeout(self.config.io_timeout, flush(&mut conn, &mut self.outbox)).await {
            Ok(Ok(())) => tracing::info!("said goodbye to the master"),
            Ok(Err(e)) => tracing::warn!("could not say goodbye: {e}"),
            Err(_) => tracing::warn!("could not say goodbye: timed out"),
        }
        let _ = tokio::time::timeout(Duration::from_secs(1), conn.close()).await;
        SessionEnd::ShutDown
    }
}

async fn flush(conn: &mut Connection<FarmStream>, outbox: &mut Vec<Message>) -> Result<(), ProtoError> {
    if outbox.is_empty() {
        return Ok(());
    }
    for message in outbox.drain(..) {
        conn.feed(&message).await?;
    }
    conn.flush().await
}

/// A kernel's work as the protocol carries it.
fn wire_stats(stats: nephele_kernels::kernel::KernelStats) -> KernelStats {
    KernelStats { rays: stats.rays, rays_hit: stats.rays_hit, queries: stats.queries, hidden: stats.hidden }
}

/// Renders a batch's own pixels, or takes them from this worker's previous render of the same
/// session's view of the asset where the batch allows it and that pays ([`crate::temporal`]).
/// Runs on the caller's rayon pool. `occluders`: see [`RayBatch::occluders`].
#[allow(clippy::too_many_arguments)]
fn render_or_reuse(
    worker: &Shared,
    kernel: &dyn nephele_kernels::kernel::RayKernel,
    slot: (u64, &str),
    camera: &Camera,
    pixels: &[u32],
    reuse: &nephele_proto::ReuseLimits,
    settings: &nephele_share::Settings,
    occluders: &[nephele_proto::SolidGrid],
) -> Result<(nephele_kernels::kernel::PixelResults, nephele_kernels::kernel::KernelStats), String> {
    let previous_frames = if kernel.shades_whole_views() { 0 } else { reuse.previous_frames };
    let centre = kernel.bounds().center();
    let angle = settings.max_angle_deg;
    let begun = Instant::now();
    match worker.previous.plan(slot, camera, centre, angle, previous_frames) {
        Plan::Reuse(source) => {
            let from = (&source.camera, source.pixels.as_slice(), &source.results);
            let made =
                derive_view_with(kernel, from, source.absent, camera, pixels, settings).map_err(|e| e.to_string())?;
            worker.previous.record(slot.1, Made::Reused, pixels.len(), begun.elapsed());
            worker.metrics.previous_frame_pixels.inc_by(pixels.len() as u64);
            worker.metrics.previous_frame_pixels_rendered.inc_by(made.rendered as u64);
            Ok((made.results, made.stats))
        }
        Plan::Render(why) => {
            tracing::trace!(asset = %slot.1, ?why, "rendered in full");
            let (results, stats) = kernel.render_pixels_behind(camera, pixels, occluders).map_err(|e| e.to_string())?;
            if previous_frames > 0 {
                worker.previous.record(slot.1, Made::Full, pixels.len(), begun.elapsed());
                let absent = if reuse.rows_complete { Absent::Empty } else { Absent::Unknown };
                let kept = Previous { camera: *camera, pixels: pixels.to_vec(), results: results.clone(), absent };
                worker.previous.remember(slot, kept, centre, angle, previous_frames);
            }
            Ok((results, stats))
        }
    }
}

/// A render ahead of the session's next frames (`ReuseLimits::ahead`, the scheduler's
/// render-ahead while the farm is idle): rendered in full and kept as the session's previous
/// render of this view, so that its next batches take it by reprojection; no result is sent,
/// since no frame shows it. Not made (and answered at once) for an asset whose reuse measured
/// dearer than rendering, or a kernel that shades whole views.
async fn render_ahead(shared: &Arc<Shared>, batch: RayBatch) -> Result<BatchDone, (ErrorCode, String)> {
    let RayBatch { ids, asset_id, camera: wire, pixels, reuse, .. } = batch;
    let camera = wire.camera().map_err(|e| (ErrorCode::InvalidField, format!("camera: {e}")))?;
    let worker = shared.clone();
    let (stats, render_time, made) = tokio::task::spawn_blocking(move || {
        let kernel = worker.loader.load(&asset_id).map_err(|e| (e.code(), e.to_string()))?;
        if kernel.shades_whole_views() || worker.previous.reuse_measured_dearer(&asset_id) {
            return Ok((nephele_kernels::kernel::KernelStats::default(), Duration::ZERO, false));
        }
        let start = Instant::now();
        let (results, stats) = worker
            .pool
            .install(|| kernel.render_pixels(&camera, &pixels))
            .map_err(|e| (ErrorCode::RenderFailed, e.to_string()))?;
        let elapsed = start.elapsed();
        // Not recorded as the cost of a full render: made on an idle farm, it would make
        // frames' full renders look cheaper than they are against reuse.
        let absent = if reuse.rows_complete { Absent::Empty } else { Absent::Unknown };
        let centre = kernel.bounds().center();
        let kept = Previous { camera, pixels, results, absent };
        let slot = (ids.session_id, asset_id.as_str());
        worker.previous.remember_ahead(slot, kept, centre, reuse.max_angle_deg, reuse.previous_frames);
        worker.metrics.render_ms.observe(elapsed.as_secs_f64() * 1e3);
        Ok((stats, elapsed, true))
    })
    .await
    .map_err(|e| (ErrorCode::Internal, format!("render task: {e}")))??;
    if made {
        shared.metrics.ahead_renders.inc();
    } else {
        shared.metrics.ahead_declined.inc();
    }
    let render_time_us = render_time.as_micros() as u64;
    tracing::debug!(batch = ids.batch_id, made, rays = stats.rays, render_us = render_time_us, "render ahead kept");
    let pixels = if made { stats.rays as u32 } else { 0 };
    Ok(BatchDone { ids, pixels, render_time_us, stats: wire_stats(stats) })
}

/// Loads, renders, checks and sends one batch; returns what to tell the master.
async fn render_and_deliver(
    shared: &Arc<Shared>,
    batch: RayBatch,
    cancelled: &AtomicBool,
) -> Result<BatchDone, (ErrorCode, String)> {
    if batch.reuse.ahead {
        return render_ahead(shared, batch).await;
    }
    let RayBatch { ids, asset_id, camera: wire, pixels, composer, derived, reuse, occluders, .. } = batch;
    let camera = wire.camera().map_err(|e| (ErrorCode::InvalidField, format!("camera: {e}")))?;
    let derived_cameras = derived
        .iter()
        .map(|view| view.camera.camera())
        .collect::<Result<Vec<Camera>, _>>()
        .map_err(|e| (ErrorCode::InvalidField, format!("derived view camera: {e}")))?;
    let settings = nephele_share::Settings {
        max_angle_deg: reuse.max_angle_deg,
        max_contrast: reuse.max_contrast,
        ..nephele_share::Settings::default()
    };
    let worker = shared.clone();
    let asset = asset_id.clone();
    let (pixels, derived, rendered, render_time, whole_views) = tokio::task::spawn_blocking(move || {
        let kernel = match worker.loader.load(&asset_id) {
            Ok(kernel) => kernel,
            Err(e) => return (pixels, derived, Err((e.code(), e.to_string())), Duration::ZERO, false),
        };
        let start = Instant::now();
        let rendered = worker.pool.install(|| {
            // A headset's other eye in the same pass, where the kernel has one (stereo GI).
            if let ([view], [target]) = (derived.as_slice(), derived_cameras.as_slice())
                && let Some(pair) = kernel.render_pair_behind((&camera, &pixels), (target, &view.pixels), &occluders)
            {
                let ([results, other], stats) = pair.map_err(|e| e.to_string())?;
                let rendered = view.pixels.len();
                let none = nephele_kernels::kernel::KernelStats::default();
                let other = Derived { results: other, stats: none, reused: 0, empty: 0, rendered };
                return Ok::<_, String>((results, stats, vec![other]));
            }
            let slot = (ids.session_id, asset_id.as_str());
            let (results, stats) =
                render_or_reuse(&worker, kernel.as_ref(), slot, &camera, &pixels, &reuse, &settings, &occluders)?;
            let mut views = Vec::with_capacity(derived.len());
            for (view, target) in derived.iter().zip(&derived_cameras) {
                let view = if kernel.shades_whole_views() {
                    // Reprojection would save nothing: what it leaves costs a whole pass.
                    let (results, stats) =
                        kernel.render_pixels_behind(target, &view.pixels, &occluders).map_err(|e| e.to_string())?;
                    Derived { results, stats, reused: 0, empty: 0, rendered: view.pixels.len() }
                } else {
                    derive_view(kernel.as_ref(), &camera, &pixels, &results, target, &view.pixels, &settings)
                        .map_err(|e| e.to_string())?
                };
                views.push(view);
            }
            Ok::<_, String>((results, stats, views))
        });
        let rendered = rendered.map_err(|e| (ErrorCode::RenderFailed, e));
        let elapsed = start.elapsed();
        worker.metrics.render_ms.observe(elapsed.as_secs_f64() * 1e3);
        (pixels, derived, rendered, elapsed, kernel.shades_whole_views())
    })
    .await
    .map_err(|e| (ErrorCode::Internal, format!("render task: {e}")))?;
    let (results, stats, views) = rendered?;
    let hidden = stats.hidden + views.iter().map(|v| v.stats.hidden).sum::<u64>();
    if whole_views {
        let samples = stats.rays + views.iter().map(|v| v.stats.rays).sum::<u64>();
        shared.metrics.environment_samples.inc_by(samples);
        shared.metrics.environment_samples_hidden.inc_by(hidden);
    }
    if cancelled.load(Ordering::Acquire) {
        return Err((ErrorCode::Cancelled, "cancelled while rendering".into()));
    }
    let mut stats = wire_stats(stats);
    let render_time_us = render_time.as_micros() as u64;
    let mut count = pixels.len() as u32;
    // The derived views first: the master hears `BatchDone` after the batch's own result, so
    // every result of the batch is at the composer by then.
    for (view, made) in derived.into_iter().zip(views) {
        stats.rays += made.stats.rays;
        stats.rays_hit += made.stats.rays_hit;
        stats.queries += made.stats.queries;
        stats.hidden += made.stats.hidden;
        count = count.saturating_add(view.pixels.len() as u32);
        shared.metrics.derived_pixels.inc_by(view.pixels.len() as u64);
        shared.metrics.derived_pixels_rendered.inc_by(made.rendered as u64);
        let result = Message::BatchResult(BatchResult {
            ids: view.ids,
            worker_id: shared.worker_id.load(Ordering::Relaxed),
            width: view.camera.width,
            height: view.camera.height,
            pixels: view.pixels,
            color: made.results.color,
            opacity: made.results.opacity,
            depth: made.results.depth,
            render_time_us,
            stats: wire_stats(made.stats),
            encoding: shared.result_encoding,
        });
        validate::message(&result)
            .map_err(|e| (ErrorCode::RenderFailed, format!("a derived view's result is invalid: {e}")))?;
        shared
            .composers
            .send(&composer, &result)
            .await
            .map_err(|e| (ErrorCode::ComposerUnreachable, format!("composer {composer}: {e}")))?;
    }
    let result = Message::BatchResult(BatchResult {
        ids,
        worker_id: shared.worker_id.load(Ordering::Relaxed),
        width: wire.width,
        height: wire.height,
        pixels,
        color: results.color,
        opacity: results.opacity,
        depth: results.depth,
        render_time_us,
        stats,
        encoding: shared.result_encoding,
    });
    validate::message(&result)
        .map_err(|e| (ErrorCode::RenderFailed, format!("the kernel produced an invalid result: {e}")))?;
    let delivering = Instant::now();
    shared
        .composers
        .send(&composer, &result)
        .await
        .map_err(|e| (ErrorCode::ComposerUnreachable, format!("composer {composer}: {e}")))?;
    shared.metrics.deliver_ms.observe(delivering.elapsed().as_secs_f64() * 1e3);
    tracing::debug!(batch = ids.batch_id, %asset, pixels = count, rays = stats.rays, hidden, render_us = render_time_us, "batch delivered");
    Ok(BatchDone { ids, pixels: count, render_time_us, stats })
}
