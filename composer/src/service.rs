//! The composer process: a thin network shell around [`Compositor`], [`H264Encoder`] and the
//! viewers' peer connections.
//!
//! * **HTTP** (axum): `POST /v1/sessions` takes `{"sdp": OFFER}` (optionally `"session"`,
//!   `"width"`, `"height"`, `"views"`) and answers `201 {"session", "token", "type": "answer",
//!   "sdp"}`; a malformed offer is `400 {"error"}`. `DELETE /v1/sessions/{id}` with
//!   `Authorization: Bearer TOKEN` ends a session; `GET /v1/sessions` reports every session's
//!   counters; `GET /v1/health`. The master will forward its own `POST /v1/sessions` here.
//! * **Worker results** on a TCP listener, in the interim framing of [`crate::wire`] (frame
//!   plans and batch results).
//! * Per session, a **media thread** converts each fused frame to YUV, encodes it and sends
//!   it on the video track; a frame that arrives while the previous one is still being
//!   encoded replaces nothing and is dropped (counted): the stream never queues up latency.
//! * Poses from the data channel are validated ([`PoseInbox`]) and published on a broadcast
//!   channel ([`Composer::poses`]), which the master link will consume; with
//!   [`FrameSource::TestPattern`] the composer renders a synthetic two-object scene from the
//!   latest pose itself, so it streams without a farm.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex as StdMutex, mpsc as std_mpsc};
use std::time::{Duration, Instant};

use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use nephele_geometry::camera::Camera;
use serde::{Deserialize, Serialize};
use thiserror::Error;
use tokio::io::AsyncReadExt;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, broadcast, mpsc, watch};
use tokio::task::JoinHandle;

use crate::encode::{EncoderSettings, EncoderStats, H264Encoder, MAX_LONG_SIDE, MAX_SHORT_SIDE, MIN_SIDE};
use crate::fusion::{Compositor, FrameLayout, FusedFrame, FusionLimits, SessionCounters, SessionId};
use crate::pose::{Control, Pose, PoseCounters, PoseDrop, PoseInbox};
use crate::webrtc::{RtcConfig, RtcError, RtcStack, Viewer, ViewerEvent};
use crate::wire::{self, MAX_MESSAGE_BYTES, Message};
use crate::yuv::Yuv420;

#[derive(Debug, Error)]
pub enum ServiceError {
    #[error("binding {what} on {addr}: {source}")]
    Bind { what: &'static str, addr: SocketAddr, source: std::io::Error },
    #[error(transparent)]
    Rtc(#[from] RtcError),
    #[error("bad configuration: {0}")]
    Config(String),
}

/// Where frames come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FrameSource {
    /// Frame plans and batch results from the TCP listener (the farm).
    #[default]
    Workers,
    /// A synthetic scene rendered in-process from each viewer's latest pose.
    TestPattern,
}

#[derive(Debug, Clone)]
pub struct ComposerConfig {
    pub http_addr: SocketAddr,
    pub results_addr: SocketAddr,
    pub rtc: RtcConfig,
    pub source: FrameSource,
    /// Frame rate of the stream (the encoder's plan and the test pattern's clock).
    pub fps: f32,
    /// Encoder bitrate; `None`: scaled with the picture size ([`EncoderSettings::low_latency`]).
    pub bitrate_bps: Option<u32>,
    /// View size before the first pose arrives.
    pub default_view: (u32, u32),
    /// Deadline after a test-pattern frame is planned.
    pub frame_budget: Duration,
    pub max_sessions: usize,
    /// `host:port` of the master's farm listener: frames come from the farm (proto v2
    /// `FramePlan`s and `BatchResult`s on the results listener) and poses go to the master.
    pub master: Option<String>,
    /// The composer's name in the master's `GET /v1/farm`.
    pub name: String,
}

impl Default for ComposerConfig {
    fn default() -> Self {
        ComposerConfig {
            http_addr: SocketAddr::from(([127, 0, 0, 1], 8090)),
            results_addr: SocketAddr::from(([127, 0, 0, 1], 8091)),
            rtc: RtcConfig::default(),
            source: FrameSource::Workers,
            fps: 30.0,
            bitrate_bps: None,
            default_view: (640, 480),
            frame_budget: Duration::from_millis(40),
            max_sessions: 64,
            master: None,
            name: "composer".into(),
        }
    }
}

/// The packed layout for `views` views of `width x height`: one row for up to two views, a
/// near-square grid beyond; views shrunk (aspect kept) until the picture fits the encoder,
/// and rounded down to even sizes.
pub fn layout_for(width: u32, height: u32, views: u16) -> Result<FrameLayout, String> {
    if width == 0 || height == 0 || views == 0 {
        return Err(format!("{views} views of {width}x{height}"));
    }
    let columns = if views <= 2 { views } else { (f64::from(views).sqrt().ceil()) as u16 };
    let rows = views.div_ceil(columns);
    let (pw, ph) = (f64::from(width) * f64::from(columns), f64::from(height) * f64::from(rows));
    let (long, short) = if pw >= ph { (MAX_LONG_SIDE, MAX_SHORT_SIDE) } else { (MAX_SHORT_SIDE, MAX_LONG_SIDE) };
    let scale = (f64::from(long) / pw).min(f64::from(short) / ph).min(1.0);
    let even = |v: f64| ((v.floor() as u32) & !1).max(MIN_SIDE);
    let (w, h) = (even(f64::from(width) * scale), even(f64::from(height) * scale));
    FrameLayout::grid(w, h, views, columns).map_err(|e| e.to_string())
}

/// Counters of one session's media path.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct MediaCounters {
    pub frames_in: u64,
    pub frames_sent: u64,
    /// Fused frames dropped because the media thread was still busy with the previous one.
    pub frames_dropped_busy: u64,
    pub encode_errors: u64,
    pub send_errors: u64,
    pub keyframes_requested: u64,
    /// Time of the last frame: colour conversion, encoding, sending (ms).
    pub last_yuv_ms: f64,
    pub last_encode_ms: f64,
    pub last_send_ms: f64,
    pub bytes_sent: u64,
}

/// What `GET /v1/sessions` reports per session.
#[derive(Debug, Clone, Serialize)]
pub struct SessionReport {
    pub session: SessionId,
    pub connected: bool,
    pub width: u32,
    pub height: u32,
    pub views: u16,
    pub age_s: f64,
    pub fusion: SessionCounters,
    pub poses: PoseCounters,
    pub media: MediaCounters,
    pub encoder: EncoderStats,
    pub control_malformed: u64,
}

/// Service-wide counters.
#[derive(Debug, Default)]
pub(crate) struct GlobalCounters {
    pub(crate) wire_errors: AtomicU64,
    pub(crate) worker_connections: AtomicU64,
}

pub(crate) struct SessionEntry {
    token: String,
    viewer: Arc<Viewer>,
    pub(crate) layout: FrameLayout,
    frames: std_mpsc::SyncSender<FusedFrame>,
    keyframe: Arc<AtomicBool>,
    inbox: PoseInbox,
    last_pose: Option<Arc<Pose>>,
    media: Arc<StdMutex<(MediaCounters, EncoderStats)>>,
    control_malformed: u64,
    created: Instant,
    next_frame: u64,
}

pub(crate) struct Shared {
    pub(crate) config: ComposerConfig,
    rtc: RtcStack,
    pub(crate) compositor: StdMutex<Compositor>,
    pub(crate) sessions: StdMutex<HashMap<SessionId, SessionEntry>>,
    next_session: AtomicU64,
    pub(crate) wake: Notify,
    events: mpsc::Sender<ViewerEvent>,
    poses: broadcast::Sender<(SessionId, Arc<Pose>)>,
    pub(crate) counters: GlobalCounters,
    runtime: tokio::runtime::Handle,
    /// Messages for the master, while a master link is up.
    pub(crate) to_master: StdMutex<Option<mpsc::UnboundedSender<nephele_proto::Message>>>,
    /// Worker results of the farm's tasks, by task id, until the master releases the task.
    pub(crate) task_results: StdMutex<HashMap<u64, Vec<Arc<nephele_proto::BatchResult>>>>,
    pub(crate) last_parts: StdMutex<crate::master_link::LastParts>,
    /// Poses received, frames planned and the stages of frames sent (farm mode).
    pub(crate) latency: StdMutex<crate::latency::LatencyTracker>,
}

/// A running composer. Dropping it does not stop it; call [`Composer::shutdown`].
pub struct Composer {
    shared: Arc<Shared>,
    http_addr: SocketAddr,
    results_addr: SocketAddr,
    stop: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for Composer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Composer")
            .field("http", &self.http_addr)
            .field("results", &self.results_addr)
            .finish_non_exhaustive()
    }
}

pub(crate) fn lock<T>(m: &StdMutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic while holding one of these locks leaves plain data behind; keep serving.
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Composer {
    /// Binds the HTTP and results listeners and starts serving (inside a tokio runtime).
    pub async fn start(config: ComposerConfig) -> Result<Composer, ServiceError> {
        if !(config.fps.is_finite() && (1.0..=240.0).contains(&config.fps)) {
            return Err(ServiceError::Config(format!("frame rate {} outside 1..240", config.fps)));
        }
        layout_for(config.default_view.0, config.default_view.1, 1).map_err(ServiceError::Config)?;
        let rtc = RtcStack::new(config.rtc.clone())?;
        let http = TcpListener::bind(config.http_addr).await.map_err(|source| ServiceError::Bind {
            what: "HTTP",
            addr: config.http_addr,
            source,
        })?;
        let results = TcpListener::bind(config.results_addr).await.map_err(|source| ServiceError::Bind {
            what: "worker results",
            addr: config.results_addr,
            source,
        })?;
        let http_addr =
            http.local_addr().map_err(|source| ServiceError::Bind { what: "HTTP", addr: config.http_addr, source })?;
        let results_addr = results.local_addr().map_err(|source| ServiceError::Bind {
            what: "worker results",
            addr: config.results_addr,
            source,
        })?;
        let (events_tx, events_rx) = mpsc::channel(4096);
        let (poses, _) = broadcast::channel(256);
        let shared = Arc::new(Shared {
            config,
            rtc,
            compositor: StdMutex::new(Compositor::new(FusionLimits::default())),
            sessions: StdMutex::new(HashMap::new()),
            next_session: AtomicU64::new(1),
            wake: Notify::new(),
            events: events_tx,
            poses,
            counters: GlobalCounters::default(),
            runtime: tokio::runtime::Handle::current(),
            to_master: StdMutex::new(None),
            task_results: StdMutex::new(HashMap::new()),
            last_parts: StdMutex::new(HashMap::new()),
            latency: StdMutex::new(crate::latency::LatencyTracker::default()),
        });
        let (stop, stop_rx) = watch::channel(false);
        let mut tasks = Vec::new();
        let router = Router::new()
            .route("/v1/health", get(|| async { "ok" }))
            .route("/v1/sessions", post(create_session).get(list_sessions))
            .route("/v1/sessions/{id}", axum::routing::delete(delete_session))
            .with_state(Arc::clone(&shared));
        let mut http_stop = stop_rx.clone();
        tasks.push(tokio::spawn(async move {
            let shutdown = async move {
                let _ = http_stop.wait_for(|s| *s).await;
            };
            if let Err(e) = axum::serve(http, router).with_graceful_shutdown(shutdown).await {
                tracing::error!("HTTP server: {e}");
            }
        }));
        tasks.push(tokio::spawn(accept_results(Arc::clone(&shared), results, stop_rx.clone())));
        tasks.push(tokio::spawn(fusion_loop(Arc::clone(&shared), stop_rx.clone())));
        tasks.push(tokio::spawn(event_loop(Arc::clone(&shared), events_rx, stop_rx.clone())));
        if let Some(master) = shared.config.master.clone() {
            tasks.push(tokio::spawn(crate::master_link::run(
                Arc::clone(&shared),
                master,
                results_addr,
                stop_rx.clone(),
            )));
        }
        if shared.config.source == FrameSource::TestPattern {
            tasks.push(tokio::spawn(test_pattern_loop(Arc::clone(&shared), stop_rx)));
        }
        tracing::info!(%http_addr, %results_addr, source = ?shared.config.source, "composer listening");
        Ok(Composer { shared, http_addr, results_addr, stop, tasks })
    }

    pub fn http_addr(&self) -> SocketAddr {
        self.http_addr
    }

    pub fn results_addr(&self) -> SocketAddr {
        self.results_addr
    }

    /// Every accepted pose, as it arrives.
    pub fn poses(&self) -> broadcast::Receiver<(SessionId, Arc<Pose>)> {
        self.shared.poses.subscribe()
    }

    pub fn sessions(&self) -> Vec<SessionReport> {
        reports(&self.shared)
    }

    /// Malformed worker messages seen so far.
    pub fn wire_errors(&self) -> u64 {
        self.shared.counters.wire_errors.load(Ordering::Relaxed)
    }

    /// Stops listening, closes every peer connection and waits for the tasks.
    pub async fn shutdown(self) {
        let _ = self.stop.send(true);
        let ids: Vec<SessionId> = lock(&self.shared.sessions).keys().copied().collect();
        for id in ids {
            end_session(&self.shared, id).await;
        }
        for t in self.tasks {
            let _ = t.await;
        }
    }
}

fn reports(shared: &Shared) -> Vec<SessionReport> {
    let compositor = lock(&shared.compositor);
    let sessions = lock(&shared.sessions);
    let mut out: Vec<SessionReport> = sessions
        .iter()
        .map(|(&id, e)| {
            let (media, encoder) = *lock(&e.media);
            SessionReport {
                session: id,
                connected: e.viewer.is_connected(),
                width: e.layout.width(),
                height: e.layout.height(),
                views: e.layout.views(),
                age_s: e.created.elapsed().as_secs_f64(),
                fusion: compositor.counters(id).unwrap_or_default(),
                poses: e.inbox.counters(),
                media,
                encoder,
                control_malformed: e.control_malformed,
            }
        })
        .collect();
    out.sort_by_key(|r| r.session);
    out
}

#[derive(Debug, Deserialize)]
struct OfferRequest {
    sdp: String,
    #[serde(rename = "type")]
    kind: Option<String>,
    session: Option<SessionId>,
    width: Option<u32>,
    height: Option<u32>,
    views: Option<u16>,
}

#[derive(Debug, Serialize)]
struct AnswerResponse {
    session: SessionId,
    token: String,
    #[serde(rename = "type")]
    kind: &'static str,
    sdp: String,
}

fn error(status: StatusCode, message: impl std::fmt::Display) -> Response {
    (status, Json(serde_json::json!({ "error": message.to_string() }))).into_response()
}

async fn create_session(State(shared): State<Arc<Shared>>, body: axum::body::Bytes) -> Response {
    let request: OfferRequest = match serde_json::from_slice(&body) {
        Ok(r) => r,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("expected JSON {{\"sdp\": OFFER}}: {e}")),
    };
    if let Some(kind) = &request.kind
        && kind != "offer"
    {
        return error(StatusCode::BAD_REQUEST, format!("expected an SDP offer, got type '{kind}'"));
    }
    let (dw, dh) = shared.config.default_view;
    let layout = match layout_for(request.width.unwrap_or(dw), request.height.unwrap_or(dh), request.views.unwrap_or(1))
    {
        Ok(l) => l,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("bad view size: {e}")),
    };
    let id = request.session.unwrap_or_else(|| shared.next_session.fetch_add(1, Ordering::Relaxed));
    match open_viewer(&shared, id, request.sdp, layout).await {
        Ok((token, sdp)) => {
            (StatusCode::CREATED, Json(AnswerResponse { session: id, token, kind: "answer", sdp })).into_response()
        }
        Err((status, message)) => {
            let mut r = error(status, message);
            if status == StatusCode::SERVICE_UNAVAILABLE {
                r.headers_mut().insert("retry-after", axum::http::HeaderValue::from_static("5"));
            }
            r
        }
    }
}

/// Accepts a viewer's offer for session `id`: the peer connection, the fusion state and the
/// media thread. Answers `(token, answer SDP)`, or the HTTP status and reason of a refusal.
pub(crate) async fn open_viewer(
    shared: &Arc<Shared>,
    id: SessionId,
    offer: String,
    layout: FrameLayout,
) -> Result<(String, String), (StatusCode, String)> {
    if lock(&shared.sessions).len() >= shared.config.max_sessions {
        return Err((StatusCode::SERVICE_UNAVAILABLE, "the composer is full".into()));
    }
    if lock(&shared.compositor).open_session(id).is_err() {
        return Err((StatusCode::CONFLICT, format!("session {id} exists")));
    }
    let (sdp, viewer) = match shared.rtc.accept(id, offer, shared.events.clone()).await {
        Ok(ok) => ok,
        Err(e) => {
            lock(&shared.compositor).close_session(id);
            let status = match e {
                RtcError::BadOffer(_) | RtcError::NoH264 => StatusCode::BAD_REQUEST,
                _ => StatusCode::INTERNAL_SERVER_ERROR,
            };
            tracing::info!(session = id, "offer refused: {e}");
            return Err((status, e.to_string()));
        }
    };
    let token = format!("{:032x}", rand::random::<u128>());
    let viewer = Arc::new(viewer);
    let (frames_tx, frames_rx) = std_mpsc::sync_channel(1);
    let keyframe = Arc::new(AtomicBool::new(true));
    let media = Arc::new(StdMutex::new((MediaCounters::default(), EncoderStats::default())));
    spawn_media_thread(shared, Arc::clone(&viewer), frames_rx, Arc::clone(&keyframe), Arc::clone(&media));
    lock(&shared.sessions).insert(
        id,
        SessionEntry {
            token: token.clone(),
            viewer,
            layout,
            frames: frames_tx,
            keyframe,
            inbox: PoseInbox::default(),
            last_pose: None,
            media,
            control_malformed: 0,
            created: Instant::now(),
            next_frame: 0,
        },
    );
    tracing::info!(session = id, "new viewer session");
    Ok((token, sdp))
}

async fn list_sessions(State(shared): State<Arc<Shared>>) -> Response {
    let body = serde_json::json!({
        "sessions": reports(&shared),
        "wire_errors": shared.counters.wire_errors.load(Ordering::Relaxed),
        "worker_connections": shared.counters.worker_connections.load(Ordering::Relaxed),
        "unknown_session_batches": lock(&shared.compositor).unknown_session_batches(),
        // Pose received to frame sent and its stages, over the last frames of all sessions
        // (farm mode only: standalone frames have no pose of the farm behind them).
        "latency_ms": lock(&shared.latency).report(),
    });
    Json(body).into_response()
}

async fn delete_session(State(shared): State<Arc<Shared>>, Path(id): Path<SessionId>, headers: HeaderMap) -> Response {
    let token = headers
        .get("authorization")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .map(str::trim);
    let known = lock(&shared.sessions).get(&id).map(|e| e.token.clone());
    match known {
        None => error(StatusCode::NOT_FOUND, format!("no session {id}")),
        Some(t) if Some(t.as_str()) != token => error(StatusCode::UNAUTHORIZED, "missing or wrong session token"),
        Some(_) => {
            end_session(&shared, id).await;
            StatusCode::NO_CONTENT.into_response()
        }
    }
}

pub(crate) async fn end_session(shared: &Shared, id: SessionId) {
    let entry = lock(&shared.sessions).remove(&id);
    lock(&shared.compositor).close_session(id);
    lock(&shared.latency).session_ended(id);
    if let Some(e) = entry {
        // Dropping the entry drops the frame sender: the media thread ends.
        e.viewer.close().await;
        tracing::info!(session = id, "session ended");
    }
}

/// The session's media path on its own thread: YUV conversion and encoding are CPU work
/// that must not stall the async runtime.
fn spawn_media_thread(
    shared: &Arc<Shared>,
    viewer: Arc<Viewer>,
    frames: std_mpsc::Receiver<FusedFrame>,
    keyframe: Arc<AtomicBool>,
    media: Arc<StdMutex<(MediaCounters, EncoderStats)>>,
) {
    let runtime = shared.runtime.clone();
    let shared = Arc::clone(shared);
    let fps = shared.config.fps;
    let bitrate = shared.config.bitrate_bps;
    let session = viewer.session();
    let spawned = std::thread::Builder::new().name(format!("media-{session}")).spawn(move || {
        let frame_time = Duration::from_secs_f32(1.0 / fps);
        let mut encoder: Option<H264Encoder> = None;
        let mut yuv: Option<Yuv420> = None;
        let started = Instant::now();
        while let Ok(frame) = frames.recv() {
            let (w, h) = (frame.layout.width(), frame.layout.height());
            let t0 = Instant::now();
            let picture = match yuv.take() {
                Some(mut p) if p.width() == w && p.height() == h => p.fill_from_linear_rgb(&frame.rgb).map(|_| p),
                _ => Yuv420::from_linear_rgb(w, h, &frame.rgb),
            };
            let picture = match picture {
                Ok(p) => p,
                Err(e) => {
                    tracing::warn!(session, "colour conversion: {e}");
                    lock(&media).0.encode_errors += 1;
                    continue;
                }
            };
            let t1 = Instant::now();
            if encoder.as_ref().is_none_or(|e| e.settings().width != w || e.settings().height != h) {
                let mut settings = EncoderSettings::low_latency(w, h);
                settings.fps = fps;
                if let Some(b) = bitrate {
                    settings.bitrate_bps = b;
                }
                match H264Encoder::new(settings) {
                    Ok(e) => encoder = Some(e),
                    Err(e) => {
                        tracing::warn!(session, "encoder for {w}x{h}: {e}");
                        lock(&media).0.encode_errors += 1;
                        yuv = Some(picture);
                        continue;
                    }
                }
            }
            let Some(enc) = encoder.as_mut() else { continue };
            if keyframe.swap(false, Ordering::SeqCst) {
                enc.request_keyframe();
                lock(&media).0.keyframes_requested += 1;
            }
            let encoded = enc.encode(&picture, started.elapsed().as_millis() as u64);
            let t2 = Instant::now();
            yuv = Some(picture);
            let encoded = match encoded {
                Ok(f) => f,
                Err(e) => {
                    tracing::warn!(session, "encoding: {e}");
                    lock(&media).0.encode_errors += 1;
                    continue;
                }
            };
            let sent = runtime.block_on(viewer.send_frame(&encoded, frame_time));
            let t3 = Instant::now();
            let timing = {
                let mut latency = lock(&shared.latency);
                let timing = latency.take_frame(session, frame.frame).filter(|_| sent.is_ok());
                if let Some(t) = &timing {
                    latency.frame_sent(crate::latency::Stages::of(t, t0, t1, t2, t3));
                }
                timing
            };
            if let Some(timing) = timing {
                // Tells the viewer which of its poses this frame shows (the client's and
                // `nephele loadgen`'s pose-to-frame latency).
                let note =
                    serde_json::json!({ "type": "frame", "t": timing.client_time_ms, "seq": timing.pose_sequence });
                let _ = runtime.block_on(viewer.send_text(note.to_string()));
            }
            let mut m = lock(&media);
            m.1 = enc.stats();
            let c = &mut m.0;
            c.last_yuv_ms = (t1 - t0).as_secs_f64() * 1e3;
            c.last_encode_ms = (t2 - t1).as_secs_f64() * 1e3;
            c.last_send_ms = (t3 - t2).as_secs_f64() * 1e3;
            match sent {
                Ok(()) => {
                    c.frames_sent += 1;
                    c.bytes_sent += encoded.data.len() as u64;
                }
                Err(e) => {
                    c.send_errors += 1;
                    tracing::debug!(session, "sending a frame: {e}");
                }
            }
        }
        tracing::debug!(session, "media thread ends");
    });
    if let Err(e) = spawned {
        tracing::error!(session, "cannot start the media thread: {e}");
    }
}

/// Hands fused frames to their sessions' media threads, never blocking.
fn dispatch(shared: &Shared, frames: Vec<FusedFrame>) {
    if frames.is_empty() {
        return;
    }
    let sessions = lock(&shared.sessions);
    for frame in frames {
        let Some(entry) = sessions.get(&frame.session) else { continue };
        let mut m = lock(&entry.media);
        m.0.frames_in += 1;
        match entry.frames.try_send(frame) {
            Ok(()) => {}
            Err(std_mpsc::TrySendError::Full(_)) => m.0.frames_dropped_busy += 1,
            Err(std_mpsc::TrySendError::Disconnected(_)) => {}
        }
    }
}

async fn fusion_loop(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    loop {
        let next = lock(&shared.compositor).next_deadline();
        let sleep = async {
            match next {
                Some(deadline) => tokio::time::sleep_until(tokio::time::Instant::from_std(deadline)).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = shared.wake.notified() => {}
            _ = sleep => {}
            _ = stop.wait_for(|s| *s) => return,
        }
        let frames = lock(&shared.compositor).poll(Instant::now());
        dispatch(&shared, frames);
    }
}

async fn accept_results(shared: Arc<Shared>, listener: TcpListener, mut stop: watch::Receiver<bool>) {
    loop {
        let connection_stop = stop.clone();
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    shared.counters.worker_connections.fetch_add(1, Ordering::Relaxed);
                    if shared.config.master.is_some() {
                        tokio::spawn(crate::master_link::read_results(Arc::clone(&shared), stream, peer, connection_stop));
                    } else {
                        tokio::spawn(read_results(Arc::clone(&shared), stream, peer, connection_stop));
                    }
                }
                Err(e) => tracing::warn!("accepting a worker connection: {e}"),
            },
            _ = stop.wait_for(|s| *s) => return,
        }
    }
}

async fn read_results(shared: Arc<Shared>, mut stream: TcpStream, peer: SocketAddr, mut stop: watch::Receiver<bool>) {
    let _ = stream.set_nodelay(true);
    let mut body = Vec::new();
    loop {
        let mut len = [0u8; 4];
        tokio::select! {
            r = stream.read_exact(&mut len) => if r.is_err() { break },
            _ = stop.wait_for(|s| *s) => break,
        }
        let n = u32::from_le_bytes(len) as usize;
        if n > MAX_MESSAGE_BYTES {
            shared.counters.wire_errors.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(%peer, "worker message of {n} bytes exceeds the limit; closing the connection");
            break;
        }
        body.resize(n, 0);
        if stream.read_exact(&mut body).await.is_err() {
            break;
        }
        let now = Instant::now();
        match wire::decode(&body) {
            Ok(Message::Plan { plan, deadline }) => {
                if let Err(e) = lock(&shared.compositor).plan_frame(plan.with_deadline(now + deadline)) {
                    tracing::debug!(%peer, "frame plan refused: {e}");
                }
            }
            Ok(Message::Result(batch)) => {
                if let Err(e) = lock(&shared.compositor).add_batch(batch) {
                    tracing::debug!(%peer, "batch refused: {e}");
                }
            }
            Err(e) => {
                // The length prefix keeps the framing: skip the message, keep the connection.
                shared.counters.wire_errors.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(%peer, "malformed worker message: {e}");
            }
        }
        shared.wake.notify_one();
    }
    tracing::debug!(%peer, "worker connection closed");
}

async fn event_loop(shared: Arc<Shared>, mut events: mpsc::Receiver<ViewerEvent>, mut stop: watch::Receiver<bool>) {
    loop {
        let event = tokio::select! {
            e = events.recv() => match e { Some(e) => e, None => return },
            _ = stop.wait_for(|s| *s) => return,
        };
        match event {
            ViewerEvent::Connected(id) | ViewerEvent::KeyframeRequest(id) => {
                // A new viewer, or a receiver that lost a picture: the next frame is an IDR.
                if let Some(e) = lock(&shared.sessions).get(&id) {
                    e.keyframe.store(true, Ordering::SeqCst);
                }
            }
            ViewerEvent::Disconnected(id, state) => {
                tracing::info!(session = id, %state, "viewer gone");
                if lock(&shared.sessions).contains_key(&id) {
                    crate::master_link::to_master(
                        &shared,
                        nephele_proto::Message::CloseStream(nephele_proto::CloseStream {
                            session_id: id,
                            reason: format!("viewer gone ({state})"),
                        }),
                    );
                }
                end_session(&shared, id).await;
            }
            ViewerEvent::Binary(id, bytes, at) => {
                let mut sessions = lock(&shared.sessions);
                let Some(e) = sessions.get_mut(&id) else { continue };
                match e.inbox.offer(&bytes, at) {
                    Ok(pose) => {
                        let (w, h) = pose.view_size();
                        if let Ok(layout) = layout_for(w, h, pose.views.len() as u16) {
                            e.layout = layout;
                        }
                        let pose = Arc::new(pose);
                        e.last_pose = Some(Arc::clone(&pose));
                        crate::master_link::forward_pose(&shared, id, &pose);
                        let _ = shared.poses.send((id, pose));
                    }
                    Err(PoseDrop::Malformed(err)) => tracing::debug!(session = id, "pose dropped: {err}"),
                    Err(other) => tracing::trace!(session = id, "pose dropped: {other:?}"),
                }
            }
            ViewerEvent::Text(id, text) => {
                let control = serde_json::from_str::<Control>(&text);
                let viewer = {
                    let mut sessions = lock(&shared.sessions);
                    let Some(e) = sessions.get_mut(&id) else { continue };
                    match &control {
                        Ok(Control::Keyframe) => e.keyframe.store(true, Ordering::SeqCst),
                        Ok(Control::Ping { .. }) => {}
                        Ok(Control::Pong { .. }) | Err(_) => e.control_malformed += 1,
                    }
                    Arc::clone(&e.viewer)
                };
                if let Ok(Control::Ping { t }) = control
                    && let Ok(reply) = serde_json::to_string(&Control::Pong { t })
                {
                    let _ = viewer.send_text(reply).await;
                }
            }
        }
    }
}

/// Cameras of a session's views: from its latest pose, or a default view of the pattern.
fn cameras_for(layout: FrameLayout, pose: Option<&Pose>) -> Vec<Camera> {
    let (w, h) = (layout.view_width(), layout.view_height());
    let from_pose = pose
        .and_then(|p| p.views.iter().map(|v| Camera::from_view_projection(w, h, v.view, v.projection).ok()).collect());
    from_pose.unwrap_or_else(|| {
        let eye = glam::Vec3::new(0.0, -3.0, 1.0);
        (0..layout.views())
            .filter_map(|i| {
                let offset = glam::Vec3::X * (f32::from(i) - f32::from(layout.views() - 1) / 2.0) * 0.064;
                Camera::look_at(w, h, 0.9, eye + offset, glam::Vec3::ZERO + offset, glam::Vec3::Z).ok()
            })
            .collect()
    })
}

async fn test_pattern_loop(shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    let mut tick = tokio::time::interval(Duration::from_secs_f32(1.0 / shared.config.fps));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.wait_for(|s| *s) => return,
        }
        let work: Vec<(SessionId, u64, FrameLayout, Option<Arc<Pose>>)> = {
            let mut sessions = lock(&shared.sessions);
            sessions
                .iter_mut()
                .filter(|(_, e)| e.viewer.is_connected())
                .map(|(&id, e)| {
                    e.next_frame += 1;
                    (id, e.next_frame, e.layout, e.last_pose.clone())
                })
                .collect()
        };
        let now = Instant::now();
        for (id, frame, layout, pose) in work {
            let cameras = cameras_for(layout, pose.as_deref());
            let (plan, batches) = crate::testpattern::frame(id, frame, layout, &cameras);
            let mut compositor = lock(&shared.compositor);
            if compositor.plan_frame(plan.with_deadline(now + shared.config.frame_budget)).is_ok() {
                for b in batches {
                    let _ = compositor.add_batch(b);
                }
            }
        }
        shared.wake.notify_one();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_fit_the_encoder() {
        let l = layout_for(1280, 720, 1).unwrap();
        assert_eq!((l.width(), l.height(), l.columns()), (1280, 720, 1));
        let l = layout_for(1920, 1080, 2).unwrap();
        assert_eq!((l.width(), l.height()), (3840, 1080));
        // Two 2000x2000 eyes: shrunk to fit 3840 wide, even sizes.
        let l = layout_for(2000, 2000, 2).unwrap();
        assert_eq!((l.view_width(), l.view_height()), (1920, 1920));
        assert!(l.height() <= 2160);
        // Odd sizes round down to even.
        let l = layout_for(641, 479, 1).unwrap();
        assert_eq!((l.width(), l.height()), (640, 478));
        // A 45-view quilt: a 7x7 grid within 3840x2160.
        let l = layout_for(420, 560, 45).unwrap();
        assert_eq!((l.columns(), l.rows()), (7, 7));
        assert!(crate::encode::check_resolution(l.width(), l.height()).is_ok() && l.view_width().is_multiple_of(2));
        assert!(layout_for(0, 10, 1).is_err());
    }
}
