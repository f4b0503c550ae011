//! An in-process stand-in for the farm behind the master's HTTP API, for the browser tests
//! (and the load generator's): [`TestFarm`] implements [`FarmBackend`] with a real WebRTC
//! peer (webrtc-rs) per session that answers the client's offer, accepts its `control` data
//! channel, records every pose and control message, answers pings, and streams real H.264
//! (OpenH264) whose picture is a function of the client's latest pose: a flat grey whose
//! level encodes the camera's azimuth around the scene target ([`grey_for_azimuth`]). So a
//! test can check end to end that a scripted pose change changes the picture, and by how much.
//!
//! The full-service test replaces this backend by the real master, composer and workers; the
//! browser side of the tests stays the same.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use bytes::Bytes;
use nephele_master::http::{Admission, AppState, BoxFuture, FarmBackend, OpenError, SceneView};
use nephele_master::sessions::SessionRequest;
use openh264::OpenH264API;
use openh264::encoder::{Encoder, EncoderConfig, FrameRate, IntraFramePeriod, Profile, RateControlMode, UsageType};
use openh264::formats::YUVBuffer;
use serde_json::json;
use webrtc::api::API;
use webrtc::data_channel::RTCDataChannel;
use webrtc::data_channel::data_channel_message::DataChannelMessage;
use webrtc::media::Sample;
use webrtc::peer_connection::RTCPeerConnection;
use webrtc::peer_connection::configuration::RTCConfiguration;
use webrtc::peer_connection::peer_connection_state::RTCPeerConnectionState;
use webrtc::peer_connection::sdp::session_description::RTCSessionDescription;
use webrtc::track::track_local::TrackLocal;
use webrtc::track::track_local::track_local_static_sample::TrackLocalStaticSample;

/// The scene every test session asks for, and its first view (as `POST /v1/sessions` returns).
pub const SCENE: &str = "default";
pub const FIRST_VIEW: SceneView = SceneView { eye: [0.0, -4.0, 2.0], target: [0.0, 0.0, 0.5], fov_y_deg: 40.0 };
/// Frame rate of the test stream.
pub const FPS: u32 = 30;

/// Grey level (0..=255, as the browser shows it) that encodes a camera azimuth (radians,
/// around the scene target, from +X towards +Y): 0.15..0.85 of full scale over one turn, so
/// that neither end clips.
pub fn grey_for_azimuth(azimuth: f64) -> f64 {
    let turn = azimuth.rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU;
    255.0 * (0.15 + 0.7 * turn)
}

/// The browser's pose messages, decoded by the composer's own decoder (`nephele_proto::pose`).
pub use nephele_proto::pose::Pose;

/// Camera position of view `v` in world coordinates: `-R^T t` of the world-to-camera matrix.
pub fn eye(pose: &Pose, v: usize) -> [f64; 3] {
    let m = pose.views[v].view.to_cols_array();
    let t = [m[12], m[13], m[14]].map(f64::from);
    std::array::from_fn(|i| {
        -(f64::from(m[i * 4]) * t[0] + f64::from(m[i * 4 + 1]) * t[1] + f64::from(m[i * 4 + 2]) * t[2])
    })
}

/// Azimuth of view `v`'s camera around `target` (radians, from +X towards +Y).
pub fn azimuth(pose: &Pose, v: usize, target: [f32; 3]) -> f64 {
    let eye = eye(pose, v);
    (eye[1] - f64::from(target[1])).atan2(eye[0] - f64::from(target[0]))
}

/// An offer as the farm received it.
#[derive(Debug, Clone)]
pub struct Offer {
    pub session_id: String,
    pub request: SessionRequest,
    pub sdp: String,
}

/// What one session's peer saw.
#[derive(Debug, Default)]
pub struct PeerLog {
    /// Every binary message with its arrival time.
    pub binary: Vec<(Instant, Bytes)>,
    /// Every text message.
    pub text: Vec<String>,
}

struct Peer {
    pc: Arc<RTCPeerConnection>,
    log: Arc<Mutex<PeerLog>>,
    connected: Arc<AtomicBool>,
    frames_sent: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
}

#[derive(Default)]
struct State {
    offers: Vec<Offer>,
    closed: Vec<String>,
    peers: BTreeMap<String, Peer>,
}

struct Shared {
    api: API,
    state: Mutex<State>,
    refuse_next: AtomicUsize,
    refused: AtomicUsize,
    stream_video: bool,
    /// The master shells serving this farm (for ending sessions as the service does).
    masters: Mutex<Vec<Arc<AppState>>>,
}

impl Shared {
    fn state(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|poison| poison.into_inner())
    }
}

/// The in-process farm. Cheap to clone (shared state).
#[derive(Clone)]
pub struct TestFarm {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for TestFarm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TestFarm").field("sessions", &self.shared.state().peers.len()).finish_non_exhaustive()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum FarmError {
    #[error("WebRTC: {0}")]
    Rtc(#[from] webrtc::Error),
    #[error("I/O: {0}")]
    Io(#[from] std::io::Error),
}

pub use nephele_loadgen::{h264_codec, rtc_api};

impl TestFarm {
    /// A farm that answers offers with a real peer; `stream_video` also sends the H.264 stream.
    pub fn new(stream_video: bool) -> Result<TestFarm, FarmError> {
        Ok(TestFarm {
            shared: Arc::new(Shared {
                api: rtc_api()?,
                state: Mutex::default(),
                refuse_next: AtomicUsize::new(0),
                refused: AtomicUsize::new(0),
                stream_video,
                masters: Mutex::default(),
            }),
        })
    }

    /// Serves `nephele_master::http::router` over this farm on a loopback port (on the current
    /// tokio runtime); returns the address.
    pub async fn serve(&self) -> Result<SocketAddr, FarmError> {
        self.serve_configured(None, Default::default()).await
    }

    /// [`TestFarm::serve`] over HTTPS with `tls` (`nephele_master::tls`, as `nephele master
    /// --tls-...` serves).
    pub async fn serve_tls(&self, tls: nephele_master::tls::ServerTls) -> Result<SocketAddr, FarmError> {
        self.serve_configured(Some(tls), Default::default()).await
    }

    /// [`TestFarm::serve`] with HTTPS and a viewer access policy of the caller's.
    pub async fn serve_configured(
        &self,
        tls: Option<nephele_master::tls::ServerTls>,
        access: nephele_master::http::AccessPolicy,
    ) -> Result<SocketAddr, FarmError> {
        self.serve_at(std::net::Ipv4Addr::LOCALHOST.into(), tls, access).await
    }

    /// [`TestFarm::serve_configured`] on an address of the caller's (a LAN address, to see
    /// the page as another machine would).
    pub async fn serve_at(
        &self,
        ip: std::net::IpAddr,
        tls: Option<nephele_master::tls::ServerTls>,
        access: nephele_master::http::AccessPolicy,
    ) -> Result<SocketAddr, FarmError> {
        let start = Instant::now();
        let state = AppState::with_access(
            Arc::new(self.clone()),
            Arc::new(nephele_master::metrics::MasterMetrics::new()),
            Box::new(move || start.elapsed().as_secs_f64()),
            access,
        );
        self.shared.masters.lock().unwrap_or_else(|p| p.into_inner()).push(Arc::clone(&state));
        let listener = tokio::net::TcpListener::bind((ip, 0)).await?;
        let addr = listener.local_addr()?;
        let app = nephele_master::http::router(state);
        match tls {
            None => {
                tokio::spawn(async move {
                    if let Err(e) = axum::serve(listener, app).await {
                        tracing::error!("test master stopped: {e}");
                    }
                });
            }
            Some(tls) => {
                let listener = nephele_master::tls::TlsListener::new(listener, tls.config)?;
                tokio::spawn(async move {
                    if let Err(e) = axum::serve(listener, app).await {
                        tracing::error!("test master stopped: {e}");
                    }
                });
            }
        }
        Ok(addr)
    }

    /// Refuse the next `n` session requests (admission control: 503 + Retry-After: 1).
    pub fn refuse_next(&self, n: usize) {
        self.shared.refuse_next.store(n, Ordering::SeqCst);
    }

    /// Session requests refused so far.
    pub fn refused(&self) -> usize {
        self.shared.refused.load(Ordering::SeqCst)
    }

    pub fn offers(&self) -> Vec<Offer> {
        self.shared.state().offers.clone()
    }

    /// Sessions the master closed (DELETE from the client), in order.
    pub fn closed(&self) -> Vec<String> {
        self.shared.state().closed.clone()
    }

    /// The binary messages a session's peer received since `since`.
    pub fn binary_since(&self, session: &str, since: Instant) -> Vec<(Instant, Bytes)> {
        let state = self.shared.state();
        let Some(peer) = state.peers.get(session) else { return Vec::new() };
        let log = peer.log.lock().unwrap_or_else(|p| p.into_inner());
        log.binary.iter().filter(|(t, _)| *t >= since).cloned().collect()
    }

    /// The text messages a session's peer received.
    pub fn texts(&self, session: &str) -> Vec<String> {
        let state = self.shared.state();
        let Some(peer) = state.peers.get(session) else { return Vec::new() };
        peer.log.lock().unwrap_or_else(|p| p.into_inner()).text.clone()
    }

    /// The latest pose a session sent, parsed.
    pub fn latest_pose(&self, session: &str) -> Option<Pose> {
        let state = self.shared.state();
        let peer = state.peers.get(session)?;
        let log = peer.log.lock().unwrap_or_else(|p| p.into_inner());
        log.binary.iter().rev().find_map(|(_, data)| Pose::decode(data).ok())
    }

    /// Ends every open session from the farm's side, as a composer restart does: each peer
    /// stops its video and closes its connection (the sessions stay listed, as the master
    /// keeps them until the client's `DELETE`). Returns how many were open.
    /// Ends `session` in the master shells as the service does when its composer dies
    /// (`AppState::end_session`), leaving its peer connection up: only the session's watch
    /// can tell the client. Returns whether a master held it.
    pub fn end_session(&self, session: &str) -> bool {
        let masters = self.shared.masters.lock().unwrap_or_else(|p| p.into_inner()).clone();
        let mut ended = false;
        for master in &masters {
            ended |= master.end_session(session);
        }
        ended
    }

    pub async fn drop_sessions(&self) -> usize {
        let pcs: Vec<Arc<RTCPeerConnection>> = {
            let state = self.shared.state();
            state
                .peers
                .iter()
                .filter(|(id, _)| !state.closed.contains(id))
                .map(|(_, peer)| {
                    peer.stop.store(true, Ordering::SeqCst);
                    Arc::clone(&peer.pc)
                })
                .collect()
        };
        for pc in &pcs {
            let _ = pc.close().await;
        }
        pcs.len()
    }

    pub fn is_connected(&self, session: &str) -> bool {
        self.shared.state().peers.get(session).is_some_and(|p| p.connected.load(Ordering::SeqCst))
    }

    pub fn frames_sent(&self, session: &str) -> u64 {
        self.shared.state().peers.get(session).map_or(0, |p| p.frames_sent.load(Ordering::SeqCst))
    }

    async fn answer(shared: Arc<Shared>, session_id: String, offer_sdp: String) -> Result<String, OpenError> {
        let offer = RTCSessionDescription::offer(offer_sdp).map_err(|e| OpenError::BadOffer(e.to_string()))?;
        let unavailable = |e: webrtc::Error| OpenError::Unavailable(e.to_string());
        let pc = Arc::new(shared.api.new_peer_connection(RTCConfiguration::default()).await.map_err(unavailable)?);
        let track = Arc::new(TrackLocalStaticSample::new(
            h264_codec().capability,
            "video".into(),
            format!("nephele-{session_id}"),
        ));
        let sender =
            pc.add_track(Arc::clone(&track) as Arc<dyn TrackLocal + Send + Sync>).await.map_err(unavailable)?;
        // RTCP must be read for the interceptors (NACK, reports) to work.
        tokio::spawn(async move { while sender.read_rtcp().await.is_ok() {} });

        let log: Arc<Mutex<PeerLog>> = Arc::default();
        let channel: Arc<Mutex<Option<Arc<RTCDataChannel>>>> = Arc::default();
        let dc_log = Arc::clone(&log);
        let dc_slot = Arc::clone(&channel);
        pc.on_data_channel(Box::new(move |dc: Arc<RTCDataChannel>| {
            let log = Arc::clone(&dc_log);
            *dc_slot.lock().unwrap_or_else(|p| p.into_inner()) = Some(Arc::clone(&dc));
            let reply = Arc::clone(&dc);
            dc.on_message(Box::new(move |msg: DataChannelMessage| {
                let log = Arc::clone(&log);
                let reply = Arc::clone(&reply);
                Box::pin(async move {
                    if msg.is_string {
                        let text = String::from_utf8_lossy(&msg.data).into_owned();
                        let ping =
                            serde_json::from_str::<serde_json::Value>(&text).ok().filter(|v| v["type"] == "ping");
                        log.lock().unwrap_or_else(|p| p.into_inner()).text.push(text);
                        if let Some(ping) = ping {
                            let pong = json!({ "type": "pong", "id": ping["id"], "t": ping["t"] });
                            let _ = reply.send_text(pong.to_string()).await;
                        }
                    } else {
                        log.lock().unwrap_or_else(|p| p.into_inner()).binary.push((Instant::now(), msg.data));
                    }
                })
            }));
            Box::pin(async {})
        }));

        let connected = Arc::new(AtomicBool::new(false));
        let frames_sent = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let started = Arc::new(AtomicBool::new(false));
        {
            let (connected, frames_sent, stop, log, track, channel) = (
                Arc::clone(&connected),
                Arc::clone(&frames_sent),
                Arc::clone(&stop),
                Arc::clone(&log),
                Arc::clone(&track),
                Arc::clone(&channel),
            );
            let (stream_video, session) = (shared.stream_video, session_id.clone());
            pc.on_peer_connection_state_change(Box::new(move |state: RTCPeerConnectionState| {
                tracing::debug!(session, %state, "test peer");
                connected.store(state == RTCPeerConnectionState::Connected, Ordering::SeqCst);
                if state == RTCPeerConnectionState::Connected && stream_video && !started.swap(true, Ordering::SeqCst) {
                    let video = VideoLoop {
                        track: Arc::clone(&track),
                        log: Arc::clone(&log),
                        channel: Arc::clone(&channel),
                        frames_sent: Arc::clone(&frames_sent),
                        stop: Arc::clone(&stop),
                        runtime: tokio::runtime::Handle::current(),
                    };
                    std::thread::spawn(move || video.run());
                }
                if matches!(state, RTCPeerConnectionState::Failed | RTCPeerConnectionState::Closed) {
                    stop.store(true, Ordering::SeqCst);
                }
                Box::pin(async {})
            }));
        }

        pc.set_remote_description(offer).await.map_err(|e| OpenError::BadOffer(e.to_string()))?;
        let answer = pc.create_answer(None).await.map_err(|e| OpenError::BadOffer(e.to_string()))?;
        let mut gathered = pc.gathering_complete_promise().await;
        pc.set_local_description(answer).await.map_err(unavailable)?;
        if tokio::time::timeout(Duration::from_secs(5), gathered.recv()).await.is_err() {
            return Err(OpenError::Unavailable("ICE gathering did not finish in 5 s".into()));
        }
        let local =
            pc.local_description().await.ok_or_else(|| OpenError::Unavailable("no local description".into()))?;
        shared.state().peers.insert(session_id, Peer { pc, log, connected, frames_sent, stop });
        Ok(local.sdp)
    }
}

/// The per-session video source: one flat frame per 1/FPS s whose grey encodes the latest
/// pose's azimuth, each followed by a `{"type": "frame", "seq", "t"}` note naming that pose;
/// on its own thread (the encoder is synchronous), writing through the runtime.
struct VideoLoop {
    track: Arc<TrackLocalStaticSample>,
    log: Arc<Mutex<PeerLog>>,
    channel: Arc<Mutex<Option<Arc<RTCDataChannel>>>>,
    frames_sent: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    runtime: tokio::runtime::Handle,
}

impl VideoLoop {
    fn run(self) {
        let mut encoder: Option<(Encoder, usize, usize)> = None;
        let period = Duration::from_secs(1) / FPS;
        let mut next = Instant::now();
        while !self.stop.load(Ordering::SeqCst) {
            let pose = {
                let log = self.log.lock().unwrap_or_else(|p| p.into_inner());
                log.binary.iter().rev().find_map(|(_, d)| Pose::decode(d).ok())
            };
            if let Some(pose) = pose {
                let (vw, vh) = pose.view_size();
                // Packed as the composer packs them (two eyes side by side, a quilt's grid).
                let columns = usize::from(nephele_proto::pose::grid_columns(pose.views.len() as u16));
                let (w, h) = (vw as usize * columns, vh as usize * pose.views.len().div_ceil(columns));
                if encoder.as_ref().is_none_or(|(_, ew, eh)| (*ew, *eh) != (w, h)) {
                    encoder = match new_encoder() {
                        Ok(e) => Some((e, w, h)),
                        Err(e) => {
                            tracing::error!("test farm: no encoder: {e}");
                            return;
                        }
                    };
                }
                if let Some((enc, w, h)) = encoder.as_mut() {
                    let grey = grey_for_azimuth(azimuth(&pose, 0, FIRST_VIEW.target));
                    // Limited-range luma (BT.601/709 video levels): what the browser shows as `grey`.
                    let luma = (16.0 + grey * 219.0 / 255.0).round() as u8;
                    let (w, h) = (*w, *h);
                    let mut yuv = vec![luma; w * h];
                    yuv.resize(w * h * 3 / 2, 128);
                    match enc.encode(&YUVBuffer::from_vec(yuv, w, h)) {
                        Ok(stream) => {
                            let data = Bytes::from(stream.to_vec());
                            if !data.is_empty() {
                                let sample = Sample { data, duration: period, ..Default::default() };
                                if self.runtime.block_on(self.track.write_sample(&sample)).is_ok() {
                                    self.frames_sent.fetch_add(1, Ordering::SeqCst);
                                    let dc = self.channel.lock().unwrap_or_else(|p| p.into_inner()).clone();
                                    if let Some(dc) = dc {
                                        let note =
                                            json!({ "type": "frame", "seq": pose.seq, "t": pose.client_time_ms });
                                        let _ = self.runtime.block_on(dc.send_text(note.to_string()));
                                    }
                                }
                            }
                        }
                        Err(e) => tracing::warn!("test farm: encode: {e}"),
                    }
                }
            }
            next += period;
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                next = now;
            }
        }
    }
}

fn new_encoder() -> Result<Encoder, openh264::Error> {
    let config = EncoderConfig::new()
        .usage_type(UsageType::CameraVideoRealTime)
        .profile(Profile::Baseline)
        // Flat test pictures need no rate control (and OpenH264 warns about bitrate control
        // without frame skipping).
        .rate_control_mode(RateControlMode::Off)
        .max_frame_rate(FrameRate::from_hz(FPS as f32))
        .skip_frames(false)
        .intra_frame_period(IntraFramePeriod::from_num_frames(FPS));
    Encoder::with_api_config(OpenH264API::from_source(), config)
}

impl FarmBackend for TestFarm {
    fn scenes(&self) -> Vec<(String, SceneView)> {
        vec![(SCENE.to_string(), FIRST_VIEW)]
    }

    fn ice_servers(&self) -> serde_json::Value {
        json!([])
    }

    fn admission(&self) -> Admission {
        let refuse =
            self.shared.refuse_next.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1)).is_ok();
        if refuse {
            self.shared.refused.fetch_add(1, Ordering::SeqCst);
            Admission::Refuse { retry_after: Duration::from_secs(1) }
        } else {
            Admission::Admit
        }
    }

    fn open(
        &self,
        session_id: String,
        request: SessionRequest,
        offer_sdp: String,
    ) -> BoxFuture<Result<String, OpenError>> {
        self.shared.state().offers.push(Offer { session_id: session_id.clone(), request, sdp: offer_sdp.clone() });
        let shared = Arc::clone(&self.shared);
        Box::pin(TestFarm::answer(shared, session_id, offer_sdp))
    }

    fn close(&self, session_id: String) -> BoxFuture<()> {
        let pc = {
            let mut state = self.shared.state();
            state.closed.push(session_id.clone());
            state.peers.get(&session_id).map(|peer| {
                peer.stop.store(true, Ordering::SeqCst);
                Arc::clone(&peer.pc)
            })
        };
        Box::pin(async move {
            if let Some(pc) = pc {
                let _ = pc.close().await;
            }
        })
    }

    fn farm_state(&self) -> nephele_master::http::BoxFuture<serde_json::Value> {
        let state = self.shared.state();
        let sessions: Vec<serde_json::Value> = state
            .peers
            .iter()
            .map(|(id, p)| {
                let poses = p.log.lock().unwrap_or_else(|e| e.into_inner()).binary.len();
                json!({ "id": id, "connected": p.connected.load(Ordering::SeqCst), "poses": poses, "frames_sent": p.frames_sent.load(Ordering::SeqCst) })
            })
            .collect();
        let value = json!({ "workers": [], "test_farm": sessions });
        Box::pin(async move { value })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_give_the_camera_position_and_azimuth() {
        let pose =
            nephele_proto::pose::look_at_pose(7, 640, 480, 0.8, glam::Vec3::new(1.0, 2.0, 3.0), glam::Vec3::ZERO)
                .expect("a pose");
        let decoded = Pose::decode(&pose.encode()).expect("decodes");
        let e = eye(&decoded, 0);
        assert!((e[0] - 1.0).abs() < 1e-5 && (e[1] - 2.0).abs() < 1e-5 && (e[2] - 3.0).abs() < 1e-5, "{e:?}");
        assert!((azimuth(&decoded, 0, [0.0; 3]) - 2f64.atan2(1.0)).abs() < 1e-5);
    }

    #[test]
    fn grey_levels_span_one_turn_without_clipping() {
        assert!((grey_for_azimuth(0.0) - 38.25).abs() < 1e-9);
        assert!((grey_for_azimuth(-0.5) - grey_for_azimuth(std::f64::consts::TAU - 0.5)).abs() < 1e-9);
        assert!(grey_for_azimuth(std::f64::consts::TAU - 1e-9) < 255.0 * 0.85 + 1e-6);
    }
}
