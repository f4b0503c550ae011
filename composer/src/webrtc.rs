//! The composer's end of each viewer's WebRTC peer connection: an H.264 video track out, one
//! RTCDataChannel for poses and control in.
//!
//! Stack: the `webrtc` crate (webrtc-rs) **0.17**, the mature tokio-based line. 0.20+ is a
//! new API over the sans-IO `rtc` crate; 0.17 was picked because its peer-connection API
//! (the W3C shape, also what Pion has) is the one with years of use behind it, it builds here
//! with the rest of our tokio stack, and it carries the H.264 packetiser (FU-A / STAP-A,
//! packetization-mode 1) and the RTCP readers we need. Its internals log through `log`,
//! which `tracing-subscriber` picks up.
//!
//! Signalling is one HTTP round trip without trickle ICE: [`RtcStack::accept`] takes the
//! browser's offer, waits until its own candidates are gathered and returns a complete
//! answer. ICE: host candidates (loopback included when asked, for one-machine use), plus
//! whatever STUN/TURN servers are configured; `nat_1to1_ips` announces a public address for a
//! composer behind NAT or in a container.
//!
//! Chromium hides its host addresses behind mDNS `.local` names. With mDNS queries off (the
//! default) those candidates are ignored, which is harmless: the answer carries the
//! composer's reachable candidates, the browser's connectivity checks reach them, and the
//! composer learns the browser's address as a peer-reflexive candidate. With
//! [`MdnsMode::Query`] the composer also resolves `.local` names on the local link.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex as StdMutex, Weak};
use std::time::{Duration, Instant};

use bytes::Bytes;
use thiserror::Error;
use tokio::sync::{Mutex, mpsc};
use webrtc::api::interceptor_registry::{configure_rtcp_reports, configure_twcc_receiver_only};
use webrtc::api::media_engine::{MIME_TYPE_H264, MediaEngine};
use webrtc::api::setting_engine::SettingEngine;
use webrtc::api::{API, APIBuilder};
use webrtc::data_channel::RTCDataChannel;
use webrtc::data_channel::data_channel_message::DataChannelMessage;
use webrtc::ice::mdns::MulticastDnsMode;
use webrtc::ice::udp_network::{EphemeralUDP, UDPNetwork};
use webrtc::ice_transport::ice_candidate_type::RTCIceCandidateType;
use webrtc::ice_transport::ice_server::RTCIceServer;
use webrtc::interceptor::registry::Registry;
use webrtc::media::Sample;
use webrtc::peer_connection::RTCPeerConnection;
use webrtc::peer_connection::configuration::RTCConfiguration;
use webrtc::peer_connection::peer_connection_state::RTCPeerConnectionState;
use webrtc::peer_connection::sdp::session_description::RTCSessionDescription;
use webrtc::rtcp::payload_feedbacks::full_intra_request::FullIntraRequest;
use webrtc::rtcp::payload_feedbacks::picture_loss_indication::PictureLossIndication;
use webrtc::rtcp::payload_feedbacks::receiver_estimated_maximum_bitrate::ReceiverEstimatedMaximumBitrate;
use webrtc::rtcp::receiver_report::ReceiverReport;

use crate::congestion::{Feedback, LossWindow};
use webrtc::rtp_transceiver::RTCPFeedback;
use webrtc::rtp_transceiver::rtp_codec::{
    RTCRtpCodecCapability, RTCRtpCodecParameters, RTCRtpHeaderExtensionCapability, RTPCodecType,
};
use webrtc::track::track_local::TrackLocal;
use webrtc::track::track_local::track_local_static_sample::TrackLocalStaticSample;

use crate::encode::EncodedFrame;
use crate::fusion::SessionId;
use crate::pacer::{PACING_FACTOR, Pacing};
use crate::retransmit::{BoundedResponderBuilder, RetransmitCounters};

/// The H.264 format we send and negotiate: constrained baseline level 3.1, packetization
/// mode 1 (FU-A fragmentation), and the level may differ between directions (we send level
/// 4.0 for 1080p; receivers accept that with `level-asymmetry-allowed`).
pub const H264_FMTP: &str = "level-asymmetry-allowed=1;packetization-mode=1;profile-level-id=42e01f";
/// Payload type we offer for H.264 when we create offers (the test client); as answerer the
/// offerer's number is used.
pub const H264_PAYLOAD_TYPE: u8 = 102;

#[derive(Debug, Error)]
pub enum RtcError {
    #[error("malformed SDP offer: {0}")]
    BadOffer(String),
    #[error("the offer has no video section that can receive H.264 (constrained baseline, packetization-mode 1)")]
    NoH264,
    #[error("bad WebRTC configuration: {0}")]
    Config(String),
    #[error("ICE gathering did not finish within {0:?}")]
    GatheringTimeout(Duration),
    #[error("WebRTC: {0}")]
    Stack(#[from] webrtc::Error),
}

/// Whether the composer resolves the browser's mDNS `.local` host candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MdnsMode {
    /// Ignore them; the browser is found as a peer-reflexive candidate (see module docs).
    #[default]
    Off,
    /// Resolve them by multicast DNS on the local link.
    Query,
}

/// A STUN or TURN server (`stun:host:port`, `turn:host:port?transport=udp`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IceServer {
    pub urls: Vec<String>,
    pub username: String,
    pub credential: String,
}

impl IceServer {
    /// Parses `stun:host:port` or `turn:user:password@host:port[?transport=...]`.
    pub fn parse(text: &str) -> Result<IceServer, RtcError> {
        let bad = || RtcError::Config(format!("'{text}' is not stun:HOST:PORT or turn[s]:USER:PASSWORD@HOST:PORT"));
        let (scheme, rest) = text.split_once(':').ok_or_else(bad)?;
        match scheme {
            "stun" | "stuns" => {
                if rest.is_empty() {
                    return Err(bad());
                }
                Ok(IceServer { urls: vec![text.to_string()], username: String::new(), credential: String::new() })
            }
            "turn" | "turns" => {
                let (auth, host) = rest.rsplit_once('@').ok_or_else(bad)?;
                let (user, password) = auth.split_once(':').ok_or_else(bad)?;
                if host.is_empty() || user.is_empty() {
                    return Err(bad());
                }
                Ok(IceServer {
                    urls: vec![format!("{scheme}:{host}")],
                    username: user.into(),
                    credential: password.into(),
                })
            }
            _ => Err(bad()),
        }
    }
}

/// How the composer's peer connections find and reach viewers.
#[derive(Debug, Clone, PartialEq)]
pub struct RtcConfig {
    pub ice_servers: Vec<IceServer>,
    /// Offer 127.0.0.1 as a host candidate too (one-machine set-ups, tests).
    pub include_loopback: bool,
    /// Public addresses to announce instead of the interfaces' own (1:1 NAT, containers).
    pub nat_1to1_ips: Vec<String>,
    /// Restrict the UDP ports ICE binds (firewalls, containers).
    pub udp_ports: Option<(u16, u16)>,
    pub mdns: MdnsMode,
    /// Longest wait for our own candidates before answering.
    pub gather_timeout: Duration,
    /// A viewer silent this long (no ICE traffic) has failed: its session ends. The
    /// connection counts as "disconnected" after a third of it.
    pub failed_timeout: Duration,
    /// Pace the video's packets at [`crate::pacer::PACING_FACTOR`] times the encoder's
    /// target bitrate ([`crate::pacer`]; the default); off: each frame leaves as one burst.
    pub pacing: bool,
}

impl Default for RtcConfig {
    fn default() -> Self {
        RtcConfig {
            ice_servers: Vec::new(),
            include_loopback: true,
            nat_1to1_ips: Vec::new(),
            udp_ports: None,
            mdns: MdnsMode::Off,
            gather_timeout: Duration::from_secs(5),
            failed_timeout: Duration::from_secs(10),
            pacing: true,
        }
    }
}

/// What a viewer's connection reports to the composer.
#[derive(Debug, Clone, PartialEq)]
pub enum ViewerEvent {
    /// ICE and DTLS are up: a new viewer, who needs a keyframe.
    Connected(SessionId),
    /// The connection failed or closed (a browser that vanished ends here after ICE's timeout).
    Disconnected(SessionId, String),
    /// A binary data-channel message (a pose, still to be validated).
    Binary(SessionId, Bytes, Instant),
    /// A text data-channel message (control, still to be parsed).
    Text(SessionId, String),
    /// RTCP picture loss indication or full intra request from the receiver.
    KeyframeRequest(SessionId),
}

/// The H.264 codec both ends register (video only: the composer sends no audio).
pub fn h264_codec() -> RTCRtpCodecParameters {
    let feedback = |typ: &str, parameter: &str| RTCPFeedback { typ: typ.into(), parameter: parameter.into() };
    RTCRtpCodecParameters {
        capability: RTCRtpCodecCapability {
            mime_type: MIME_TYPE_H264.to_owned(),
            clock_rate: 90_000,
            channels: 0,
            sdp_fmtp_line: H264_FMTP.to_owned(),
            rtcp_feedback: vec![
                feedback("goog-remb", ""),
                feedback("ccm", "fir"),
                feedback("nack", ""),
                feedback("nack", "pli"),
            ],
        },
        payload_type: H264_PAYLOAD_TYPE,
        ..Default::default()
    }
}

/// Builds a webrtc-rs API object for H.264 video and data channels under `config`.
pub fn build_api(config: &RtcConfig) -> Result<API, RtcError> {
    build_api_counting(config, Arc::default(), Arc::default())
}

/// [`build_api`], its NACK responder counting into `retransmits` and pacing at the rates of
/// `pacing` when the configuration asks for pacing.
fn build_api_counting(
    config: &RtcConfig,
    retransmits: Arc<RetransmitCounters>,
    pacing: Arc<Pacing>,
) -> Result<API, RtcError> {
    let mut media = MediaEngine::default();
    media.register_codec(h264_codec(), RTPCodecType::Video)?;
    // The send time of each packet (stamped by `retransmit`'s writer, after pacing), where
    // the viewer offers it: a browser's receive-side estimate (its REMB) reads it instead of
    // the RTP timestamps, which say when a frame was made, not when its packets left.
    media.register_header_extension(
        RTCRtpHeaderExtensionCapability { uri: webrtc::sdp::extmap::ABS_SEND_TIME_URI.to_owned() },
        RTPCodecType::Video,
        None,
    )?;
    // webrtc-rs's default interceptors but for its NACK responder, replaced by one with a
    // budget (`retransmit`); the NACK generator is for received media, which has none here.
    let mut registry = Registry::new();
    registry.add(Box::new(BoundedResponderBuilder { counters: retransmits, pacing: config.pacing.then_some(pacing) }));
    let registry = configure_rtcp_reports(registry);
    let registry = configure_twcc_receiver_only(registry, &mut media)?;
    let mut settings = SettingEngine::default();
    settings.set_include_loopback_candidate(config.include_loopback);
    let failed = config.failed_timeout.max(Duration::from_secs(1));
    // webrtc-rs counts the failed timeout from the moment of "disconnected".
    settings.set_ice_timeouts(Some(failed / 3), Some(failed * 2 / 3), Some(Duration::from_millis(500)));
    settings.set_ice_multicast_dns_mode(match config.mdns {
        MdnsMode::Off => MulticastDnsMode::Disabled,
        MdnsMode::Query => MulticastDnsMode::QueryOnly,
    });
    if !config.nat_1to1_ips.is_empty() {
        settings.set_nat_1to1_ips(config.nat_1to1_ips.clone(), RTCIceCandidateType::Host);
    }
    if let Some((lo, hi)) = config.udp_ports {
        let ports = EphemeralUDP::new(lo, hi).map_err(|e| RtcError::Config(format!("UDP ports {lo}-{hi}: {e}")))?;
        settings.set_udp_network(UDPNetwork::Ephemeral(ports));
    }
    Ok(APIBuilder::new()
        .with_media_engine(media)
        .with_interceptor_registry(registry)
        .with_setting_engine(settings)
        .build())
}

/// The peer-connection factory of a composer.
pub struct RtcStack {
    api: API,
    config: RtcConfig,
    /// Every peer connection made, weakly: how many are still alive (not freed) is the
    /// `peer_connections` gauge, the check that ended sessions release theirs.
    made: StdMutex<Vec<Weak<RTCPeerConnection>>>,
    /// NACKed packets resent and refused by every connection's responder.
    retransmits: Arc<RetransmitCounters>,
    /// The pacing rates of the streams, and what pacing did.
    pacing: Arc<Pacing>,
}

impl std::fmt::Debug for RtcStack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RtcStack").field("config", &self.config).finish_non_exhaustive()
    }
}

impl RtcStack {
    pub fn new(config: RtcConfig) -> Result<Self, RtcError> {
        let retransmits = Arc::<RetransmitCounters>::default();
        let pacing = Arc::<Pacing>::default();
        Ok(RtcStack {
            api: build_api_counting(&config, Arc::clone(&retransmits), Arc::clone(&pacing))?,
            config,
            made: StdMutex::default(),
            retransmits,
            pacing,
        })
    }

    /// Packets the pacer held back so far, over every connection, and their summed wait.
    pub fn paced(&self) -> (u64, Duration) {
        (
            self.pacing.packets_delayed.load(Ordering::Relaxed),
            Duration::from_micros(self.pacing.delay_us.load(Ordering::Relaxed)),
        )
    }

    /// NACKed packets resent and refused so far, over every connection.
    pub fn retransmits(&self) -> (u64, u64) {
        (self.retransmits.resent.load(Ordering::Relaxed), self.retransmits.refused.load(Ordering::Relaxed))
    }

    /// Peer connections made and not yet freed (closed ones included until their last
    /// reference is dropped).
    pub fn peer_connections_alive(&self) -> usize {
        self.alive().len()
    }

    /// The weak references of the connections still alive (the freed ones forgotten).
    fn alive(&self) -> std::sync::MutexGuard<'_, Vec<Weak<RTCPeerConnection>>> {
        let mut made = self.made.lock().unwrap_or_else(|p| p.into_inner());
        made.retain(|pc| pc.strong_count() > 0);
        made
    }

    pub fn rtc_configuration(&self) -> RTCConfiguration {
        RTCConfiguration {
            ice_servers: self
                .config
                .ice_servers
                .iter()
                .map(|s| RTCIceServer {
                    urls: s.urls.clone(),
                    username: s.username.clone(),
                    credential: s.credential.clone(),
                })
                .collect(),
            ..Default::default()
        }
    }

    /// Answers a viewer's offer: a peer connection with our H.264 track, handlers that turn
    /// everything the viewer does into [`ViewerEvent`]s on `events`, and the complete answer
    /// SDP (candidates included).
    pub async fn accept(
        &self,
        session: SessionId,
        offer_sdp: String,
        events: mpsc::Sender<ViewerEvent>,
    ) -> Result<(String, Viewer), RtcError> {
        check_offer(&offer_sdp)?;
        let offer = RTCSessionDescription::offer(offer_sdp).map_err(|e| RtcError::BadOffer(e.to_string()))?;
        let pc = Arc::new(self.api.new_peer_connection(self.rtc_configuration()).await?);
        self.alive().push(Arc::downgrade(&pc));
        match self.wire_up(session, &pc, offer, events).await {
            Ok(ok) => Ok(ok),
            Err(e) => {
                let _ = pc.close().await;
                Err(e)
            }
        }
    }

    async fn wire_up(
        &self,
        session: SessionId,
        pc: &Arc<RTCPeerConnection>,
        offer: RTCSessionDescription,
        events: mpsc::Sender<ViewerEvent>,
    ) -> Result<(String, Viewer), RtcError> {
        let track = Arc::new(TrackLocalStaticSample::new(
            h264_codec().capability,
            "video".into(),
            format!("nephele-{session}"),
        ));
        let sender = pc.add_track(Arc::clone(&track) as Arc<dyn TrackLocal + Send + Sync>).await?;
        // The stream's pacing rate, shared with its writer in the interceptor chain by SSRC
        // (the sender has chosen it already; the writer binds once negotiation ends).
        let pacing = match (self.config.pacing, sender.get_parameters().await.encodings.first()) {
            (true, Some(encoding)) => Some(PacingHandle {
                ssrc: encoding.ssrc,
                rate: self.pacing.handle(encoding.ssrc),
                pacing: Arc::clone(&self.pacing),
            }),
            _ => None,
        };

        // RTCP from the viewer: picture loss / full intra request → keyframe; receiver
        // reports' loss and REMB estimates → the media thread's rate controller.
        let rtcp_events = events.clone();
        let feedback: Arc<StdMutex<Vec<(Feedback, Instant)>>> = Arc::default();
        let rtcp_feedback = Arc::clone(&feedback);
        tokio::spawn(async move {
            let mut loss = LossWindow::default();
            let epoch = Instant::now();
            while let Ok((packets, _)) = sender.read_rtcp().await {
                let now = Instant::now();
                for p in packets {
                    let any = p.as_any();
                    if any.is::<PictureLossIndication>() || any.is::<FullIntraRequest>() {
                        let _ = rtcp_events.try_send(ViewerEvent::KeyframeRequest(session));
                    }
                    let mut reports = Vec::new();
                    if let Some(remb) = any.downcast_ref::<ReceiverEstimatedMaximumBitrate>() {
                        reports.push(Feedback::Estimate(f64::from(remb.bitrate)));
                    }
                    if let Some(rr) = any.downcast_ref::<ReceiverReport>() {
                        let at = now.saturating_duration_since(epoch).as_secs_f64();
                        reports.extend(
                            rr.reports
                                .iter()
                                .filter_map(|r| loss.on_report(r.last_sequence_number, r.total_lost, at))
                                .map(Feedback::Loss),
                        );
                    }
                    if !reports.is_empty() {
                        let mut queue = rtcp_feedback.lock().unwrap_or_else(|p| p.into_inner());
                        // Read every frame; a stalled media thread must not grow it.
                        if queue.len() < MAX_QUEUED_FEEDBACK {
                            queue.extend(reports.into_iter().map(|f| (f, now)));
                        }
                    }
                }
            }
        });

        let channel: Arc<Mutex<Option<Arc<RTCDataChannel>>>> = Arc::default();
        let dc_slot = Arc::clone(&channel);
        let dc_events = events.clone();
        pc.on_data_channel(Box::new(move |dc: Arc<RTCDataChannel>| {
            let slot = Arc::clone(&dc_slot);
            let events = dc_events.clone();
            Box::pin(async move {
                tracing::debug!(session, label = dc.label(), "data channel opened by the viewer");
                dc.on_message(Box::new(move |msg: DataChannelMessage| {
                    let events = events.clone();
                    Box::pin(async move {
                        let event = if msg.is_string {
                            ViewerEvent::Text(session, String::from_utf8_lossy(&msg.data).into_owned())
                        } else {
                            ViewerEvent::Binary(session, msg.data, Instant::now())
                        };
                        // A full queue means the composer is behind: dropping a pose is right.
                        let _ = events.try_send(event);
                    })
                }));
                *slot.lock().await = Some(dc);
            })
        }));

        let connected = Arc::new(AtomicBool::new(false));
        let state_flag = Arc::clone(&connected);
        let state_events = events;
        pc.on_peer_connection_state_change(Box::new(move |state: RTCPeerConnectionState| {
            let events = state_events.clone();
            let flag = Arc::clone(&state_flag);
            Box::pin(async move {
                tracing::debug!(session, %state, "peer connection state");
                match state {
                    RTCPeerConnectionState::Connected => {
                        flag.store(true, Ordering::SeqCst);
                        let _ = events.send(ViewerEvent::Connected(session)).await;
                    }
                    // "disconnected" can heal (a network hiccup); ICE declares "failed" once the
                    // viewer has been silent for its failure timeout: a vanished client ends there.
                    RTCPeerConnectionState::Disconnected => flag.store(false, Ordering::SeqCst),
                    RTCPeerConnectionState::Failed | RTCPeerConnectionState::Closed => {
                        flag.store(false, Ordering::SeqCst);
                        let _ = events.send(ViewerEvent::Disconnected(session, state.to_string())).await;
                    }
                    _ => {}
                }
            })
        }));

        pc.set_remote_description(offer).await.map_err(|e| RtcError::BadOffer(e.to_string()))?;
        let answer = pc.create_answer(None).await?;
        let mut gathered = pc.gathering_complete_promise().await;
        pc.set_local_description(answer).await?;
        let timeout = self.config.gather_timeout;
        if tokio::time::timeout(timeout, gathered.recv()).await.is_err() {
            return Err(RtcError::GatheringTimeout(timeout));
        }
        let local = pc
            .local_description()
            .await
            .ok_or_else(|| RtcError::Config("no local description after answering".into()))?;
        if !answer_sends_h264(&local.sdp) {
            return Err(RtcError::NoH264);
        }
        Ok((local.sdp, Viewer { session, pc: Arc::clone(pc), track, channel, connected, feedback, pacing }))
    }
}

/// Cheap structural checks that give a clearer error than the SDP parser's.
fn check_offer(sdp: &str) -> Result<(), RtcError> {
    let sdp = sdp.trim_start();
    if sdp.is_empty() {
        return Err(RtcError::BadOffer("empty".into()));
    }
    if !sdp.starts_with("v=0") {
        return Err(RtcError::BadOffer("an SDP starts with 'v=0'".into()));
    }
    if sdp.len() > 256 * 1024 {
        return Err(RtcError::BadOffer(format!("{} bytes is more than any offer needs", sdp.len())));
    }
    if !sdp.lines().any(|l| l.starts_with("m=video")) {
        return Err(RtcError::NoH264);
    }
    Ok(())
}

/// Whether a local answer has an active video section with an H.264 payload.
fn answer_sends_h264(sdp: &str) -> bool {
    let mut in_video = false;
    let mut active = false;
    let mut h264 = false;
    for line in sdp.lines() {
        if let Some(m) = line.strip_prefix("m=") {
            if in_video && active && h264 {
                return true;
            }
            in_video = m.starts_with("video");
            // A rejected section has port 0.
            active = in_video && m.split_whitespace().nth(1).is_some_and(|port| port != "0");
            h264 = false;
        } else if in_video && line.starts_with("a=rtpmap:") && line.contains("H264/90000") {
            h264 = true;
        } else if in_video && (line == "a=inactive" || line == "a=recvonly") {
            active = false;
        }
    }
    in_video && active && h264
}

/// One viewer's live connection.
pub struct Viewer {
    session: SessionId,
    pc: Arc<RTCPeerConnection>,
    track: Arc<TrackLocalStaticSample>,
    channel: Arc<Mutex<Option<Arc<RTCDataChannel>>>>,
    connected: Arc<AtomicBool>,
    /// The receiver's rate feedback since the media thread last took it.
    feedback: Arc<StdMutex<Vec<(Feedback, Instant)>>>,
    /// The video stream's pacing rate; `None`: not paced.
    pacing: Option<PacingHandle>,
}

/// A viewer's end of its stream's pacing rate.
struct PacingHandle {
    ssrc: u32,
    rate: Arc<AtomicU64>,
    pacing: Arc<Pacing>,
}

impl Drop for PacingHandle {
    fn drop(&mut self) {
        self.pacing.forget(self.ssrc);
    }
}

/// Most rate reports held for the media thread.
const MAX_QUEUED_FEEDBACK: usize = 256;

impl std::fmt::Debug for Viewer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Viewer")
            .field("session", &self.session)
            .field("connected", &self.is_connected())
            .finish_non_exhaustive()
    }
}

impl Viewer {
    pub fn session(&self) -> SessionId {
        self.session
    }

    pub fn is_connected(&self) -> bool {
        self.connected.load(Ordering::SeqCst)
    }

    /// Paces the video at [`PACING_FACTOR`] times `target_bps`, the encoder's target bitrate
    /// (nothing when pacing is off).
    pub fn set_pacing_target(&self, target_bps: u32) {
        if let Some(p) = &self.pacing {
            p.rate.store((PACING_FACTOR * f64::from(target_bps)) as u64, Ordering::Relaxed);
        }
    }

    /// The receiver's rate feedback (receiver reports' loss, REMB) since the last call.
    pub fn take_feedback(&self) -> Vec<(Feedback, Instant)> {
        std::mem::take(&mut *self.feedback.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// Sends one encoded frame on the video track (packetised as H.264 RTP, FU-A for NAL
    /// units larger than the MTU). Skipped frames send nothing.
    pub async fn send_frame(&self, frame: &EncodedFrame, duration: Duration) -> Result<(), RtcError> {
        if frame.data.is_empty() {
            return Ok(());
        }
        let sample = Sample { data: Bytes::copy_from_slice(&frame.data), duration, ..Default::default() };
        self.track.write_sample(&sample).await?;
        Ok(())
    }

    /// Sends a text message on the viewer's data channel, if it is open.
    pub async fn send_text(&self, text: String) -> Result<bool, RtcError> {
        let dc = self.channel.lock().await.clone();
        match dc {
            Some(dc) => {
                dc.send_text(text).await?;
                Ok(true)
            }
            None => Ok(false),
        }
    }

    pub async fn close(&self) {
        if let Err(e) = self.pc.close().await {
            tracing::debug!(session = self.session, "closing peer connection: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ice_servers_parse_or_fail_clearly() {
        assert_eq!(IceServer::parse("stun:stun.example.org:3478").unwrap().urls, vec!["stun:stun.example.org:3478"]);
        let t = IceServer::parse("turn:alice:s3cret@turn.example.org:3478?transport=udp").unwrap();
        assert_eq!(
            (t.urls[0].as_str(), t.username.as_str(), t.credential.as_str()),
            ("turn:turn.example.org:3478?transport=udp", "alice", "s3cret")
        );
        for bad in ["stun:", "turn:host:3478", "http://x", "turn:@host", "nothing"] {
            assert!(IceServer::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn offers_are_checked_before_parsing() {
        assert!(matches!(check_offer(""), Err(RtcError::BadOffer(_))));
        assert!(matches!(check_offer("hello"), Err(RtcError::BadOffer(_))));
        assert!(matches!(check_offer("v=0\r\nm=audio 9 UDP/TLS/RTP/SAVPF 111\r\n"), Err(RtcError::NoH264)));
        assert!(check_offer("v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 102\r\n").is_ok());
    }

    #[test]
    fn answers_are_checked_for_an_active_h264_section() {
        let ok =
            "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 102\r\na=rtpmap:102 H264/90000\r\na=sendonly\r\nm=application 9 x\r\n";
        assert!(answer_sends_h264(ok));
        assert!(!answer_sends_h264("v=0\r\nm=video 0 UDP/TLS/RTP/SAVPF 0\r\n"));
        assert!(!answer_sends_h264("v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 96\r\na=rtpmap:96 VP8/90000\r\n"));
        assert!(!answer_sends_h264(
            "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 102\r\na=rtpmap:102 H264/90000\r\na=inactive\r\n"
        ));
    }
}
