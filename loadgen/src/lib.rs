//! `nephele-loadgen`: a headless Nephele client over the same WebRTC stack the service uses
//! (webrtc-rs), for load tests and multi-host checks (`nephele loadgen`).
//!
//! Depends on `nephele-proto` (the pose message's one Rust encoder) and `nephele-geometry`
//! only: it speaks to the service as a browser does (HTTP, WebRTC), never through a
//! service's library.
//!
//! Each simulated user does what the browser client does (`client/PROTOCOL.md`): a peer
//! connection with a receive-only video transceiver and an unordered `control` data channel,
//! ICE gathered before the offer is posted to `POST /v1/sessions` (waiting and retrying on
//! `503` + `Retry-After`), a binary pose every 20 ms from a scripted orbit camera, a ping
//! every second, and `DELETE /v1/sessions/{id}` at the end. A user whose stream is lost (the
//! data channel closes, the peer connection fails or stays disconnected for 3 s, as when the
//! composer restarts) connects again as the browser does (after 1 s, doubling to 10 s) and
//! goes on with its orbit; the report counts the reconnections and adds up every session.
//! It does not decode the video: it parses the RTP/H.264 stream ([`h264`]) to count frames
//! (marker bits), keyframes (IDR slices), losses and bytes. It reports per user the frame
//! rate, the round-trip time of pings, and the pose-to-frame latency when the composer names
//! the pose each frame was rendered for (`{"type": "frame", "seq", "t"}` on the data
//! channel).

pub mod h264;
pub mod http;
pub mod nack_limit;
pub mod pose;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use glam::Vec3;
use serde::Serialize;
use serde_json::json;
use thiserror::Error;
use tokio::sync::Notify;
use webrtc::api::interceptor_registry::{configure_nack, configure_rtcp_reports, configure_twcc_receiver_only};
use webrtc::api::media_engine::{MIME_TYPE_H264, MediaEngine};
use webrtc::api::setting_engine::SettingEngine;
use webrtc::api::{API, APIBuilder};
use webrtc::data_channel::data_channel_init::RTCDataChannelInit;
use webrtc::data_channel::data_channel_message::DataChannelMessage;
use webrtc::ice::mdns::MulticastDnsMode;
use webrtc::ice::network_type::NetworkType;
use webrtc::interceptor::registry::Registry;
use webrtc::peer_connection::RTCPeerConnection;
use webrtc::peer_connection::configuration::RTCConfiguration;
use webrtc::peer_connection::peer_connection_state::RTCPeerConnectionState;
use webrtc::peer_connection::sdp::session_description::RTCSessionDescription;
use webrtc::rtp_transceiver::RTCPFeedback;
use webrtc::rtp_transceiver::RTCRtpTransceiverInit;
use webrtc::rtp_transceiver::rtp_codec::{RTCRtpCodecCapability, RTCRtpCodecParameters, RTPCodecType};
use webrtc::rtp_transceiver::rtp_transceiver_direction::RTCRtpTransceiverDirection;
use webrtc::track::track_remote::TrackRemote;

use crate::h264::FrameCounter;
use crate::http::BaseUrl;
use crate::pose::ScriptedOrbit;

#[derive(Debug, Error)]
pub enum LoadError {
    #[error("bad URL {0}")]
    Url(String),
    #[error("HTTP: {0}")]
    Http(String),
    #[error("the master refused the session ({status}): {body}")]
    Refused { status: u16, body: String },
    #[error("the farm stayed busy (503 or 429) through {0} retries")]
    Busy(u32),
    #[error("timed out waiting for {0}")]
    Timeout(&'static str),
    #[error("unexpected answer from the master: {0}")]
    Protocol(String),
    #[error("WebRTC: {0}")]
    Rtc(#[from] webrtc::Error),
    #[error("bad settings: {0}")]
    Settings(String),
}

/// What the load generator does.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadConfig {
    /// The master, as the browser opens it (`http://HOST:PORT/`).
    pub url: String,
    pub users: usize,
    /// How long each user streams once connected.
    pub duration: Duration,
    pub scene: String,
    /// Size of each view a user asks for.
    pub width: u16,
    pub height: u16,
    /// What every user looks through: a flat view, a stereo pair (WebXR-like, streamed side
    /// by side) or a light-field quilt, every view `width x height`.
    pub display: pose::UserDisplay,
    pub target_fps: f32,
    /// Pose period (the client's is 20 ms).
    pub pose_interval: Duration,
    pub ping_interval: Duration,
    /// Orbit speed of the scripted camera, radians per second.
    pub orbit_speed: f32,
    /// Delay between two users' starts.
    pub stagger: Duration,
    /// Longest wait for ICE gathering, the answer and the data channel.
    pub connect_timeout: Duration,
    /// How many `503` / `429` + `Retry-After` answers a user waits through before giving up.
    pub max_busy_retries: u32,
}

impl Default for LoadConfig {
    fn default() -> Self {
        LoadConfig {
            url: "http://127.0.0.1:8080/".into(),
            users: 1,
            duration: Duration::from_secs(10),
            scene: "default".into(),
            width: 640,
            height: 480,
            display: pose::UserDisplay::Flat,
            target_fps: 30.0,
            pose_interval: Duration::from_millis(20),
            ping_interval: Duration::from_secs(1),
            orbit_speed: 0.5,
            stagger: Duration::from_millis(100),
            connect_timeout: Duration::from_secs(15),
            max_busy_retries: 10,
        }
    }
}

impl LoadConfig {
    pub fn validate(&self) -> Result<(), LoadError> {
        BaseUrl::parse(&self.url)?;
        let bad = |m: String| Err(LoadError::Settings(m));
        if self.users == 0 || self.users > 1000 {
            return bad(format!("users must be 1 to 1000, got {}", self.users));
        }
        if self.width < 16 || self.height < 16 || !self.width.is_multiple_of(2) || !self.height.is_multiple_of(2) {
            return bad(format!("view size {}x{} must be even and at least 16x16", self.width, self.height));
        }
        if let pose::UserDisplay::Stereo { ipd } = self.display
            && !(ipd.is_finite() && (0.0..=1.0).contains(&ipd))
        {
            return bad(format!("interpupillary distance {ipd} m must be in [0, 1]"));
        }
        if self.pose_interval < Duration::from_millis(1) || self.ping_interval < Duration::from_millis(10) {
            return bad("pose interval must be at least 1 ms and ping interval at least 10 ms".into());
        }
        if !(self.target_fps > 0.0 && self.target_fps <= 240.0 && self.orbit_speed.is_finite()) {
            return bad(format!("target fps {} must be in (0, 240] and the orbit speed finite", self.target_fps));
        }
        Ok(())
    }
}

/// p50 / p99 / max of a sample set, in milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Percentiles {
    pub count: usize,
    pub p50: Option<f64>,
    pub p99: Option<f64>,
    pub max: Option<f64>,
}

impl Percentiles {
    /// Nearest-rank percentiles.
    pub fn of(samples: &[f64]) -> Percentiles {
        let mut sorted: Vec<f64> = samples.iter().copied().filter(|x| x.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        let rank = |p: f64| -> Option<f64> {
            if sorted.is_empty() {
                return None;
            }
            let i = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
            Some(sorted[i])
        };
        Percentiles { count: sorted.len(), p50: rank(0.5), p99: rank(0.99), max: sorted.last().copied() }
    }
}

/// One simulated user's results.
#[derive(Debug, Clone, Default, Serialize)]
pub struct UserReport {
    pub user: usize,
    pub session_id: Option<String>,
    /// Why the user did not (fully) run.
    pub error: Option<String>,
    pub busy_retries: u32,
    /// Sessions opened again after the stream was lost (as the browser client does, for
    /// example when the composer restarts; failed attempts are not counted); the counts
    /// below add up every session.
    pub reconnects: u32,
    /// Why each lost session was lost ("the service ended the session": the master said so
    /// through the session's watch; otherwise what the peer connection showed).
    pub lost: Vec<String>,
    /// From posting the offer to the data channel opening.
    pub connect_ms: Option<f64>,
    /// From the data channel opening to the first complete frame.
    pub first_frame_ms: Option<f64>,
    pub poses_sent: u64,
    pub frames: u64,
    pub idr_frames: u64,
    /// Frames with a sequence gap inside, and frames whose marker packet never came.
    pub damaged_frames: u64,
    pub unfinished_frames: u64,
    pub lost_packets: u64,
    pub video_bytes: u64,
    /// Frames per picture size ("640x480"), from the stream's sequence parameter sets: the
    /// composer codes a smaller picture when the link is narrow.
    pub frames_by_size: std::collections::BTreeMap<String, u64>,
    /// Frames per second between the first and the last frame.
    pub fps: f64,
    pub kbit_per_s: f64,
    pub rtt_ms: Percentiles,
    /// Client time from sending a pose to receiving the composer's note of the frame made
    /// from it (needs the composer's `frame` messages).
    pub pose_to_frame_ms: Percentiles,
}

/// Live totals over all users, for a progress display.
#[derive(Debug, Default)]
pub struct Live {
    pub connected: AtomicU64,
    pub frames: AtomicU64,
    pub poses: AtomicU64,
    /// Triggered (Ctrl-C): every user stops streaming now and reports what it has.
    pub stop: nephele_shutdown::Shutdown,
}

#[derive(Debug, Default)]
struct VideoStats {
    frames: u64,
    idr: u64,
    damaged: u64,
    unfinished: u64,
    lost: u64,
    bytes: u64,
    sizes: std::collections::BTreeMap<(u32, u32), u64>,
    first: Option<Instant>,
    last: Option<Instant>,
}

#[derive(Debug, Default)]
struct ControlStats {
    rtt_ms: Vec<f64>,
    pose_to_frame_ms: Vec<f64>,
}

/// H.264 as Chromium offers it (constrained baseline, packetization mode 1), video only.
pub fn h264_codec() -> RTCRtpCodecParameters {
    let feedback = |typ: &str, parameter: &str| RTCPFeedback { typ: typ.into(), parameter: parameter.into() };
    RTCRtpCodecParameters {
        capability: RTCRtpCodecCapability {
            mime_type: MIME_TYPE_H264.to_owned(),
            clock_rate: 90_000,
            channels: 0,
            sdp_fmtp_line: "level-asymmetry-allowed=1;packetization-mode=1;profile-level-id=42e01f".to_owned(),
            rtcp_feedback: vec![feedback("ccm", "fir"), feedback("nack", ""), feedback("nack", "pli")],
        },
        payload_type: 102,
        ..Default::default()
    }
}

/// The client's WebRTC API: H.264 video (as Chromium offers it) and data channels over IPv4
/// UDP host candidates, loopback included, no multicast DNS.
pub fn client_api() -> Result<API, LoadError> {
    Ok(rtc_api()?)
}

/// [`client_api`] with webrtc-rs's own error (also the in-process test farm's API).
pub fn rtc_api() -> Result<API, webrtc::Error> {
    let mut media = MediaEngine::default();
    media.register_codec(h264_codec(), RTPCodecType::Video)?;
    // webrtc-rs's default interceptors, with a limit on NACKs per lost packet under its NACK
    // generator (`nack_limit`: a browser gives up on a packet, webrtc-rs's generator never).
    let mut registry = Registry::new();
    registry.add(Box::new(nack_limit::NackLimitBuilder));
    let registry = configure_nack(registry, &mut media);
    let registry = configure_rtcp_reports(registry);
    let registry = configure_twcc_receiver_only(registry, &mut media)?;
    let mut settings = SettingEngine::default();
    settings.set_include_loopback_candidate(true);
    settings.set_network_types(vec![NetworkType::Udp4]);
    settings.set_ice_multicast_dns_mode(MulticastDnsMode::Disabled);
    Ok(APIBuilder::new()
        .with_media_engine(media)
        .with_interceptor_registry(registry)
        .with_setting_engine(settings)
        .build())
}

/// Runs every user to the end and returns their reports (failed users carry their error).
pub async fn run(config: &LoadConfig, live: Arc<Live>) -> Result<Vec<UserReport>, LoadError> {
    config.validate()?;
    let base = BaseUrl::parse(&config.url)?;
    let api = Arc::new(client_api()?);
    let clock = Instant::now();
    let mut tasks = Vec::with_capacity(config.users);
    for user in 0..config.users {
        let (config, base, api, live) = (config.clone(), base.clone(), Arc::clone(&api), Arc::clone(&live));
        tasks.push(tokio::spawn(async move {
            tokio::time::sleep(config.stagger * user as u32).await;
            let mut report = UserReport { user, ..Default::default() };
            if let Err(e) = run_user(&config, &base, &api, clock, &live, &mut report).await {
                tracing::warn!(user, "load user failed: {e}");
                report.error = Some(e.to_string());
            }
            report
        }));
    }
    let mut reports = Vec::with_capacity(tasks.len());
    for (user, task) in tasks.into_iter().enumerate() {
        reports.push(task.await.unwrap_or_else(|e| UserReport {
            user,
            error: Some(format!("task failed: {e}")),
            ..Default::default()
        }));
    }
    Ok(reports)
}

fn ms_since(clock: Instant) -> f64 {
    clock.elapsed().as_secs_f64() * 1e3
}

async fn run_user(
    config: &LoadConfig,
    base: &BaseUrl,
    api: &API,
    clock: Instant,
    live: &Live,
    report: &mut UserReport,
) -> Result<(), LoadError> {
    let mut run = UserRun::default();
    let mut backoff = RECONNECT_FIRST_BACKOFF;
    let result = loop {
        let pc = Arc::new(api.new_peer_connection(RTCConfiguration::default()).await?);
        let outcome = stream_session(config, base, &pc, clock, live, report, &mut run).await;
        if tokio::time::timeout(Duration::from_secs(5), pc.close()).await.is_err() {
            tracing::debug!("the peer connection did not close within 5 s; dropped");
        }
        let reason = match outcome {
            Ok(SessionEnd::RunOver) => break Ok(()),
            Ok(SessionEnd::Lost(reason)) => reason,
            // A failed attempt to connect again (the master still has no composer, say)
            // is retried like a lost session while the run lasts; a first connection that
            // fails is the user's error.
            Err(e) if run.end.is_some() => e.to_string(),
            Err(e) => break Err(e),
        };
        // As the browser does: connect again with a doubling backoff while the run lasts.
        let Some(end) = run.end else { break Err(LoadError::Protocol(reason)) };
        if tokio::time::Instant::now() + backoff >= end {
            break Ok(());
        }
        tracing::info!(user = report.user, "session lost ({reason}); connecting again in {backoff:?}");
        report.lost.push(reason);
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = live.stop.wait() => break Ok(()),
        }
        backoff = (backoff * 2).min(RECONNECT_MAX_BACKOFF);
    };
    run.fill(report);
    result
}

/// The browser client's reconnection backoff (`client/nephele.js`): 1 s, doubling to 10 s.
const RECONNECT_FIRST_BACKOFF: Duration = Duration::from_secs(1);
const RECONNECT_MAX_BACKOFF: Duration = Duration::from_secs(10);
/// A peer connection "disconnected" this long counts as lost (the browser client's wait).
const DISCONNECTED_GRACE: Duration = Duration::from_secs(3);

/// How a session ended.
#[derive(Debug)]
enum SessionEnd {
    /// The run's time is up or it was stopped.
    RunOver,
    /// The stream went away before (the composer died, the master ended the session).
    Lost(String),
}

/// What a user's sessions add up to over the run (a user whose session is lost connects
/// again and goes on counting).
#[derive(Default)]
struct UserRun {
    /// When the first session's data channel opened, the orbit it started, and the run's end.
    open: Option<Instant>,
    orbit: Option<ScriptedOrbit>,
    end: Option<tokio::time::Instant>,
    control: Arc<Mutex<ControlStats>>,
    video: VideoStats,
    sequence: u32,
    ping_id: u64,
}

impl UserRun {
    /// Adds one session's video counts.
    fn add_video(&mut self, v: &VideoStats) {
        let t = &mut self.video;
        t.frames += v.frames;
        t.idr += v.idr;
        t.damaged += v.damaged;
        t.unfinished += v.unfinished;
        t.lost += v.lost;
        t.bytes += v.bytes;
        for (size, n) in &v.sizes {
            *t.sizes.entry(*size).or_default() += n;
        }
        t.first = match (t.first, v.first) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        t.last = t.last.max(v.last);
    }

    /// The report's counts over every session: the frame rate over the whole run, gaps
    /// while reconnecting included.
    fn fill(&self, report: &mut UserReport) {
        let v = &self.video;
        report.frames = v.frames;
        report.idr_frames = v.idr;
        report.damaged_frames = v.damaged;
        report.unfinished_frames = v.unfinished;
        report.lost_packets = v.lost;
        report.video_bytes = v.bytes;
        report.frames_by_size = v.sizes.iter().map(|((w, h), n)| (format!("{w}x{h}"), *n)).collect();
        if let (Some(first), Some(last)) = (v.first, v.last) {
            let span = last.saturating_duration_since(first).as_secs_f64();
            if v.frames >= 2 && span > 0.0 {
                report.fps = (v.frames - 1) as f64 / span;
                report.kbit_per_s = v.bytes as f64 * 8.0 / span / 1e3;
            }
        }
        if let (Some(open), Some(first)) = (self.open, v.first) {
            report.first_frame_ms = Some(first.saturating_duration_since(open).as_secs_f64() * 1e3);
        }
        let c = self.control.lock().unwrap_or_else(|p| p.into_inner());
        report.rtt_ms = Percentiles::of(&c.rtt_ms);
        report.pose_to_frame_ms = Percentiles::of(&c.pose_to_frame_ms);
    }
}

/// One session: offer, answer, stream until the run's end or until the stream is lost, then
/// `DELETE` the session as the browser does on leaving.
async fn stream_session(
    config: &LoadConfig,
    base: &BaseUrl,
    pc: &Arc<RTCPeerConnection>,
    clock: Instant,
    live: &Live,
    report: &mut UserReport,
    run: &mut UserRun,
) -> Result<SessionEnd, LoadError> {
    let init = RTCRtpTransceiverInit { direction: RTCRtpTransceiverDirection::Recvonly, send_encodings: vec![] };
    pc.add_transceiver_from_kind(RTPCodecType::Video, Some(init)).await?;
    let video: Arc<Mutex<VideoStats>> = Arc::default();
    let frames_live = Arc::new(AtomicU64::new(0));
    {
        let video = Arc::clone(&video);
        let frames_live = Arc::clone(&frames_live);
        pc.on_track(Box::new(move |track, _, _| {
            tokio::spawn(receive_video(track, Arc::clone(&video), Arc::clone(&frames_live)));
            Box::pin(async {})
        }));
    }
    let (state_tx, mut state_rx) = tokio::sync::watch::channel(RTCPeerConnectionState::New);
    pc.on_peer_connection_state_change(Box::new(move |state| {
        let _ = state_tx.send(state);
        Box::pin(async {})
    }));
    let channel_init = RTCDataChannelInit { ordered: Some(false), max_retransmits: Some(0), ..Default::default() };
    let dc = pc.create_data_channel("control", Some(channel_init)).await?;
    {
        let control = Arc::clone(&run.control);
        dc.on_message(Box::new(move |message: DataChannelMessage| {
            if message.is_string {
                on_control(&message.data, clock, &control);
            }
            Box::pin(async {})
        }));
    }
    let opened = Arc::new(Notify::new());
    {
        let opened = Arc::clone(&opened);
        dc.on_open(Box::new(move || {
            opened.notify_one();
            Box::pin(async {})
        }));
    }
    let closed = Arc::new(Notify::new());
    {
        let closed = Arc::clone(&closed);
        dc.on_close(Box::new(move || {
            closed.notify_one();
            Box::pin(async {})
        }));
    }

    let offer = pc.create_offer(None).await?;
    let mut gathered = pc.gathering_complete_promise().await;
    pc.set_local_description(offer).await?;
    tokio::time::timeout(config.connect_timeout, gathered.recv())
        .await
        .map_err(|_| LoadError::Timeout("ICE gathering"))?;
    let offer_sdp = pc.local_description().await.ok_or(LoadError::Timeout("the local description"))?.sdp;
    let body = json!({
        "sdp": offer_sdp, "scene": config.scene, "views": config.display.views(),
        "width": config.width, "height": config.height, "target_fps": config.target_fps,
    })
    .to_string();

    let posted = Instant::now();
    let answer = loop {
        let bearer = base.invite.as_ref().map(|token| format!("Bearer {token}"));
        let headers: Vec<(&str, &str)> = bearer.iter().map(|b| ("Authorization", b.as_str())).collect();
        let response = http::request(base, "POST", "/v1/sessions", &headers, &body, config.connect_timeout).await?;
        match response.status {
            201 => break response,
            // 503: the farm is full (or has no composer while one restarts); 429: this
            // address asked too often. Both say when to come back.
            503 | 429 if report.busy_retries < config.max_busy_retries => {
                report.busy_retries += 1;
                let wait = response.header("retry-after").and_then(|v| v.parse::<u64>().ok()).unwrap_or(2).clamp(1, 60);
                tokio::time::sleep(Duration::from_secs(wait)).await;
            }
            503 | 429 => return Err(LoadError::Busy(report.busy_retries)),
            status => return Err(LoadError::Refused { status, body: response.body.chars().take(500).collect() }),
        }
    };
    let answer: serde_json::Value =
        serde_json::from_str(&answer.body).map_err(|e| LoadError::Protocol(format!("answer is not JSON: {e}")))?;
    let field = |k: &str| {
        answer[k].as_str().map(str::to_string).ok_or_else(|| LoadError::Protocol(format!("no {k:?} in the answer")))
    };
    let (session, token, sdp) = (field("session_id")?, field("token")?, field("sdp")?);
    report.session_id = Some(session.clone());
    // A session after a reconnection goes on with the first one's orbit where it is.
    let orbit = *run.orbit.get_or_insert_with(|| first_view(&answer["view"], config.orbit_speed));
    let service_ended = Arc::new(Notify::new());
    let watcher = tokio::spawn(watch_session(base.clone(), session.clone(), token.clone(), Arc::clone(&service_ended)));

    let result = async {
        pc.set_remote_description(RTCSessionDescription::answer(sdp)?).await?;
        tokio::time::timeout(config.connect_timeout, opened.notified()).await.map_err(|_| LoadError::Timeout("the data channel to open"))?;
        if run.open.is_some() {
            report.reconnects += 1;
        } else {
            live.connected.fetch_add(1, Ordering::Relaxed);
        }
        let open = *run.open.get_or_insert_with(Instant::now);
        let end = *run.end.get_or_insert_with(|| tokio::time::Instant::now() + config.duration);
        report.connect_ms.get_or_insert(posted.elapsed().as_secs_f64() * 1e3);

        let mut poses = tokio::time::interval(config.pose_interval);
        poses.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut pings = tokio::time::interval(config.ping_interval);
        pings.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut counted_frames = 0u64;
        let mut disconnected_since: Option<Instant> = None;
        let ended = loop {
            tokio::select! {
                _ = tokio::time::sleep_until(end) => break SessionEnd::RunOver,
                _ = live.stop.wait() => break SessionEnd::RunOver,
                _ = closed.notified() => break SessionEnd::Lost("the data channel closed".into()),
                _ = service_ended.notified() => break SessionEnd::Lost("the service ended the session".into()),
                changed = state_rx.changed() => {
                    let state = *state_rx.borrow_and_update();
                    match state {
                        _ if changed.is_err() => break SessionEnd::Lost("the peer connection went away".into()),
                        RTCPeerConnectionState::Failed | RTCPeerConnectionState::Closed => {
                            break SessionEnd::Lost(format!("the peer connection is {state}"));
                        }
                        RTCPeerConnectionState::Disconnected => { disconnected_since.get_or_insert_with(Instant::now); }
                        _ => disconnected_since = None,
                    }
                }
                _ = poses.tick() => {
                    if disconnected_since.is_some_and(|since| since.elapsed() >= DISCONNECTED_GRACE) {
                        break SessionEnd::Lost(format!("the peer connection stayed disconnected for {DISCONNECTED_GRACE:?}"));
                    }
                    let t = open.elapsed().as_secs_f32();
                    let views = orbit.views_at(t, config.width, config.height, config.display);
                    let message =
                        pose::encode(run.sequence, ms_since(clock), config.width, config.height, config.display.mode(), &views);
                    // A full send buffer drops this pose, like the browser's unreliable channel.
                    // A send that never returns (a broken association) must not outlive the
                    // run: select! polls nothing else while an arm's body waits.
                    if let Ok(Ok(_)) = tokio::time::timeout_at(end, dc.send(&Bytes::from(message))).await {
                        run.sequence = run.sequence.wrapping_add(1);
                        report.poses_sent += 1;
                        live.poses.fetch_add(1, Ordering::Relaxed);
                    }
                }
                _ = pings.tick() => {
                    run.ping_id += 1;
                    let ping = json!({ "type": "ping", "id": run.ping_id, "t": ms_since(clock) }).to_string();
                    let _ = tokio::time::timeout_at(end, dc.send_text(ping)).await;
                }
            }
            let frames = frames_live.load(Ordering::Relaxed);
            live.frames.fetch_add(frames - counted_frames, Ordering::Relaxed);
            counted_frames = frames;
        };
        Ok::<_, LoadError>(ended)
    }
    .await;
    watcher.abort();

    // Close like the browser does on leaving, even after a failure.
    let auth = format!("Bearer {token}");
    if let Err(e) = http::request(
        base,
        "DELETE",
        &format!("/v1/sessions/{session}"),
        &[("Authorization", &auth)],
        "",
        Duration::from_secs(5),
    )
    .await
    {
        tracing::debug!(session, "closing the session: {e}");
    }
    run.add_video(&video.lock().unwrap_or_else(|p| p.into_inner()));
    result
}

/// Longest wait for an answer to a watch (the master holds one for 25 s).
const WATCH_TIMEOUT: Duration = Duration::from_secs(40);

/// Long poll on the session as the browser client does (`GET /v1/sessions/{id}/watch`):
/// returns, waking `ended`, once the master says it is not open (`{"state": "ended"}`), so
/// that the user connects again without waiting for ICE to notice a dead peer.
async fn watch_session(base: BaseUrl, session: String, token: String, ended: Arc<Notify>) {
    let auth = format!("Bearer {token}");
    let path = format!("/v1/sessions/{session}/watch");
    loop {
        match http::request(&base, "GET", &path, &[("Authorization", &auth)], "", WATCH_TIMEOUT).await {
            Ok(r) if r.status == 200 => {
                let state = serde_json::from_str::<serde_json::Value>(&r.body).ok();
                match state.as_ref().and_then(|s| s["state"].as_str()) {
                    Some("ended") => {
                        ended.notify_one();
                        return;
                    }
                    Some("open") => {}
                    _ => tokio::time::sleep(Duration::from_secs(2)).await,
                }
            }
            // The master stopping (503) or unreachable: the peer connection's checks decide.
            Ok(_) | Err(_) => tokio::time::sleep(Duration::from_secs(2)).await,
        }
    }
}

/// The scripted camera from the master's suggested first view (or a default one).
fn first_view(view: &serde_json::Value, speed: f32) -> ScriptedOrbit {
    let vec3 = |v: &serde_json::Value| -> Option<Vec3> {
        let a = v.as_array()?;
        let x: Vec<f32> = a.iter().filter_map(|x| x.as_f64().map(|x| x as f32)).collect();
        (x.len() == 3 && x.iter().all(|v| v.is_finite())).then(|| Vec3::new(x[0], x[1], x[2]))
    };
    let eye = vec3(&view["eye"]).unwrap_or(Vec3::new(0.0, -4.0, 2.0));
    let target = vec3(&view["target"]).unwrap_or(Vec3::ZERO);
    let fov = view["fov_y_deg"].as_f64().map(|f| f as f32).filter(|f| *f > 1.0 && *f < 179.0).unwrap_or(40.0);
    let eye = if (eye - target).length() > 1e-3 { eye } else { target + Vec3::new(0.0, -4.0, 2.0) };
    ScriptedOrbit { eye, target, fov_y_deg: fov, speed }
}

fn on_control(data: &[u8], clock: Instant, control: &Mutex<ControlStats>) {
    let Ok(message) = serde_json::from_slice::<serde_json::Value>(data) else { return };
    let Some(sent) = message["t"].as_f64() else { return };
    let age = ms_since(clock) - sent;
    if !(0.0..600_000.0).contains(&age) {
        return;
    }
    let mut c = control.lock().unwrap_or_else(|p| p.into_inner());
    match message["type"].as_str() {
        Some("pong") => c.rtt_ms.push(age),
        Some("frame") => c.pose_to_frame_ms.push(age),
        _ => {}
    }
}

async fn receive_video(track: Arc<TrackRemote>, stats: Arc<Mutex<VideoStats>>, frames_live: Arc<AtomicU64>) {
    let mut counter = FrameCounter::new();
    while let Ok((packet, _)) = track.read_rtp().await {
        let frame =
            counter.push(packet.header.sequence_number, packet.header.timestamp, packet.header.marker, &packet.payload);
        let now = Instant::now();
        let mut s = stats.lock().unwrap_or_else(|p| p.into_inner());
        s.lost = counter.lost_packets;
        s.unfinished = counter.unfinished_frames;
        if let Some(frame) = frame {
            s.frames += 1;
            s.idr += u64::from(frame.idr);
            s.damaged += u64::from(frame.damaged);
            s.bytes += frame.bytes as u64;
            if let Some(size) = frame.size {
                *s.sizes.entry(size).or_default() += 1;
            }
            s.first.get_or_insert(now);
            s.last = Some(now);
            frames_live.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// A fixed-width table of the reports, one line per user, then the totals.
pub fn table(reports: &[UserReport]) -> String {
    let fmt = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.1}"));
    let mut out = String::from(
        "user  session        fps  frames   idr  damaged  lost  reconn  kbit/s  connect_ms  rtt_p50  p2f_p50  p2f_p99  error\n",
    );
    for r in reports {
        out.push_str(&format!(
            "{:>4}  {:<12} {:>5.1}  {:>6}  {:>4}  {:>7}  {:>4}  {:>6}  {:>6.0}  {:>10}  {:>7}  {:>7}  {:>7}  {}\n",
            r.user,
            r.session_id.as_deref().unwrap_or("-"),
            r.fps,
            r.frames,
            r.idr_frames,
            r.damaged_frames + r.unfinished_frames,
            r.lost_packets,
            r.reconnects,
            r.kbit_per_s,
            fmt(r.connect_ms),
            fmt(r.rtt_ms.p50),
            fmt(r.pose_to_frame_ms.p50),
            fmt(r.pose_to_frame_ms.p99),
            r.error.as_deref().unwrap_or(""),
        ));
    }
    let ok: Vec<&UserReport> = reports.iter().filter(|r| r.error.is_none()).collect();
    let fps: Vec<f64> = ok.iter().map(|r| r.fps).collect();
    let min = fps.iter().copied().fold(f64::INFINITY, f64::min);
    let mean = fps.iter().sum::<f64>() / fps.len().max(1) as f64;
    out.push_str(&format!(
        "{} of {} users streamed; fps mean {:.1}, min {}\n",
        ok.len(),
        reports.len(),
        mean,
        if fps.is_empty() { "-".into() } else { format!("{min:.1}") }
    ));
    // A stream whose resolution moved (a narrow link): how many frames at each size.
    for r in reports.iter().filter(|r| r.frames_by_size.len() > 1) {
        let sizes: Vec<String> = r.frames_by_size.iter().map(|(size, n)| format!("{n} at {size}")).collect();
        out.push_str(&format!("user {}: frames {}\n", r.user, sizes.join(", ")));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_nearest_rank() {
        let p = Percentiles::of(&[5.0, 1.0, 3.0, 2.0, 4.0, f64::NAN]);
        assert_eq!((p.count, p.p50, p.p99, p.max), (5, Some(3.0), Some(5.0), Some(5.0)));
        assert_eq!(Percentiles::of(&[]).p50, None);
        let many: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!((Percentiles::of(&many).p50, Percentiles::of(&many).p99), (Some(50.0), Some(99.0)));
    }

    #[test]
    fn settings_are_checked() {
        assert!(LoadConfig::default().validate().is_ok());
        let stereo = |ipd| LoadConfig { display: pose::UserDisplay::Stereo { ipd }, ..Default::default() };
        assert!(stereo(0.064).validate().is_ok());
        assert!(LoadConfig { display: pose::UserDisplay::Quilt, ..Default::default() }.validate().is_ok());
        for bad in [
            stereo(f32::NAN),
            stereo(-0.01),
            stereo(2.0),
            LoadConfig { users: 0, ..Default::default() },
            LoadConfig { width: 15, ..Default::default() },
            LoadConfig { url: "ftp://x".into(), ..Default::default() },
            LoadConfig { target_fps: f32::NAN, ..Default::default() },
            LoadConfig { pose_interval: Duration::ZERO, ..Default::default() },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn control_messages_give_rtt_and_pose_to_frame_latency() {
        let clock = Instant::now() - Duration::from_millis(100);
        let control = Mutex::new(ControlStats::default());
        on_control(br#"{"type":"pong","id":1,"t":90}"#, clock, &control);
        on_control(br#"{"type":"frame","seq":3,"t":60}"#, clock, &control);
        on_control(br#"{"type":"frame","seq":3}"#, clock, &control);
        on_control(b"not json", clock, &control);
        let c = control.lock().expect("lock");
        assert_eq!((c.rtt_ms.len(), c.pose_to_frame_ms.len()), (1, 1));
        assert!((c.rtt_ms[0] - 10.0).abs() < 5.0 && (c.pose_to_frame_ms[0] - 40.0).abs() < 5.0);
    }

    #[test]
    fn the_first_view_comes_from_the_answer_or_a_default() {
        let o = first_view(&json!({"eye": [1, 2, 3], "target": [0, 0, 1], "fov_y_deg": 50}), 0.5);
        assert_eq!((o.eye, o.target, o.fov_y_deg), (Vec3::new(1.0, 2.0, 3.0), Vec3::Z, 50.0));
        let o = first_view(&json!(null), 0.5);
        assert_eq!(o.target, Vec3::ZERO);
        let o = first_view(&json!({"eye": [0, 0, 0], "target": [0, 0, 0]}), 0.5);
        assert!((o.eye - o.target).length() > 1.0);
    }
}
