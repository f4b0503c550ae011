//! A headless viewer on the same WebRTC stack: posts an offer to a composer's
//! `POST /v1/sessions`, receives the H.264 track, depacketises and decodes every access
//! unit, and talks on the data channel. Used by the tests (in-process and cross-process) and
//! meant as the core of a load generator.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use bytes::Bytes;
use openh264::formats::YUVSource;
use thiserror::Error;
use tokio::sync::mpsc;
use webrtc::api::setting_engine::SettingEngine;
use webrtc::data_channel::RTCDataChannel;
use webrtc::data_channel::data_channel_message::DataChannelMessage;
use webrtc::ice::mdns::MulticastDnsMode;
use webrtc::peer_connection::RTCPeerConnection;
use webrtc::peer_connection::sdp::session_description::RTCSessionDescription;
use webrtc::rtp::codecs::h264::H264Packet;
use webrtc::rtp::packetizer::Depacketizer;
use webrtc::rtp_transceiver::RTCRtpTransceiverInit;
use webrtc::rtp_transceiver::rtp_codec::RTPCodecType;
use webrtc::rtp_transceiver::rtp_transceiver_direction::RTCRtpTransceiverDirection;
use webrtc::track::track_remote::TrackRemote;

use nephele_composer::encode::{nal, nal_type, split_annex_b};
use nephele_composer::pose::{Control, Pose};
use nephele_composer::webrtc::{RtcConfig, build_api};

#[derive(Debug, Error)]
pub enum ClientError {
    #[error("HTTP: {0}")]
    Http(String),
    #[error("the composer refused the offer ({status}): {body}")]
    Refused { status: u16, body: String },
    #[error("timed out waiting for {0}")]
    Timeout(&'static str),
    #[error("WebRTC: {0}")]
    Rtc(#[from] webrtc::Error),
    #[error(transparent)]
    Config(#[from] nephele_composer::webrtc::RtcError),
}

/// A decoded picture as the client saw it.
#[derive(Debug, Clone, PartialEq)]
pub struct Picture {
    pub width: usize,
    pub height: usize,
    /// The access unit held an IDR slice.
    pub idr: bool,
    /// Bytes of the access unit (Annex B).
    pub bytes: usize,
    /// Mean of the luma plane.
    pub mean_y: f64,
    /// The luma plane, row-major, `width * height`.
    pub luma: Vec<u8>,
    /// RTP packets of the access unit.
    pub packets: usize,
}

/// How the client connects.
#[derive(Debug, Clone, Default)]
pub struct ClientOptions {
    /// Extra JSON fields of the offer request (e.g. `"width": 64`), without braces.
    pub extra_json: String,
    /// Hide the client's host addresses behind mDNS `.local` names, as Chromium does.
    pub mdns_candidates: bool,
}

/// One request to the service's HTTP API through the workspace's one client; returns
/// (status, body).
pub async fn http_request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> Result<(u16, String), ClientError> {
    let base = nephele_loadgen::http::BaseUrl::parse(&format!("http://{addr}"))
        .map_err(|e| ClientError::Http(e.to_string()))?;
    let r = nephele_loadgen::http::request(&base, method, path, headers, body, Duration::from_secs(30))
        .await
        .map_err(|e| ClientError::Http(e.to_string()))?;
    Ok((r.status, r.body))
}

/// A connected headless viewer.
pub struct Client {
    pc: Arc<RTCPeerConnection>,
    /// The SSRC of the video the composer sends (0 until the track arrives).
    media_ssrc: Arc<AtomicU32>,
    dc: Arc<RTCDataChannel>,
    pictures: mpsc::UnboundedReceiver<Picture>,
    texts: mpsc::UnboundedReceiver<String>,
    pub session: u64,
    /// The session's id in the master's HTTP API (`session_id`), where a master answered.
    pub session_name: Option<String>,
    pub token: String,
    pub offer_sdp: String,
    pub answer_sdp: String,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client").field("session", &self.session).finish_non_exhaustive()
    }
}

/// Reads RTP, depacketises H.264 (FU-A / STAP-A), decodes each access unit (marker bit).
async fn receive_video(track: Arc<TrackRemote>, pictures: mpsc::UnboundedSender<Picture>) {
    let mut depacketizer = H264Packet::default();
    let mut unit: Vec<u8> = Vec::new();
    let Ok(mut decoder) = openh264::decoder::Decoder::new() else {
        tracing::error!("cannot create an H.264 decoder");
        return;
    };
    let mut packets = 0;
    while let Ok((packet, _)) = track.read_rtp().await {
        packets += 1;
        if let Ok(chunk) = depacketizer.depacketize(&packet.payload) {
            unit.extend_from_slice(&chunk);
        }
        if !packet.header.marker {
            continue;
        }
        let idr = split_annex_b(&unit).iter().any(|u| nal_type(u) == Some(nal::IDR));
        if let Ok(Some(yuv)) = decoder.decode(&unit) {
            let (width, height) = yuv.dimensions();
            let stride = yuv.strides().0;
            let luma: Vec<u8> =
                (0..height).flat_map(|r| yuv.y()[r * stride..r * stride + width].iter().copied()).collect();
            let mean_y = luma.iter().map(|&v| f64::from(v)).sum::<f64>() / luma.len().max(1) as f64;
            let picture = Picture { width, height, idr, bytes: unit.len(), mean_y, luma, packets };
            if pictures.send(picture).is_err() {
                return;
            }
        }
        unit.clear();
        packets = 0;
    }
}

impl Client {
    /// Negotiates with the composer at `http` and waits until the data channel is open.
    pub async fn connect(http: SocketAddr, options: ClientOptions) -> Result<Client, ClientError> {
        let api = if options.mdns_candidates {
            let mut media = webrtc::api::media_engine::MediaEngine::default();
            media.register_codec(nephele_composer::webrtc::h264_codec(), RTPCodecType::Video)?;
            let mut settings = SettingEngine::default();
            settings.set_ice_multicast_dns_mode(MulticastDnsMode::QueryAndGather);
            webrtc::api::APIBuilder::new().with_media_engine(media).with_setting_engine(settings).build()
        } else {
            build_api(&RtcConfig::default())?
        };
        let pc = Arc::new(api.new_peer_connection(Default::default()).await?);
        match Self::negotiate(http, options, &pc).await {
            Ok(c) => Ok(c),
            Err(e) => {
                let _ = pc.close().await;
                Err(e)
            }
        }
    }

    async fn negotiate(
        http: SocketAddr,
        options: ClientOptions,
        pc: &Arc<RTCPeerConnection>,
    ) -> Result<Client, ClientError> {
        let init = RTCRtpTransceiverInit { direction: RTCRtpTransceiverDirection::Recvonly, send_encodings: vec![] };
        pc.add_transceiver_from_kind(RTPCodecType::Video, Some(init)).await?;
        let (pictures_tx, pictures) = mpsc::unbounded_channel();
        let media_ssrc = Arc::new(AtomicU32::new(0));
        let track_ssrc = Arc::clone(&media_ssrc);
        pc.on_track(Box::new(move |track, _, _| {
            track_ssrc.store(track.ssrc(), Ordering::SeqCst);
            tokio::spawn(receive_video(track, pictures_tx.clone()));
            Box::pin(async {})
        }));
        let dc = pc.create_data_channel("control", None).await?;
        let (texts_tx, texts) = mpsc::unbounded_channel();
        dc.on_message(Box::new(move |m: DataChannelMessage| {
            let _ = texts_tx.send(String::from_utf8_lossy(&m.data).into_owned());
            Box::pin(async {})
        }));
        let (open_tx, mut open_rx) = mpsc::channel::<()>(1);
        dc.on_open(Box::new(move || {
            Box::pin(async move {
                let _ = open_tx.send(()).await;
            })
        }));
        let offer = pc.create_offer(None).await?;
        let mut gathered = pc.gathering_complete_promise().await;
        pc.set_local_description(offer).await?;
        tokio::time::timeout(Duration::from_secs(10), gathered.recv())
            .await
            .map_err(|_| ClientError::Timeout("ICE gathering"))?;
        let offer = pc.local_description().await.ok_or(ClientError::Timeout("local description"))?;
        let offer_sdp = offer.sdp;
        let mut body = serde_json::json!({ "type": "offer", "sdp": offer_sdp }).to_string();
        if !options.extra_json.is_empty() {
            body.pop();
            body.push(',');
            body.push_str(&options.extra_json);
            body.push('}');
        }
        let (status, reply) = http_request(http, "POST", "/v1/sessions", &[], &body).await?;
        if status != 201 {
            return Err(ClientError::Refused { status, body: reply });
        }
        let answer: serde_json::Value =
            serde_json::from_str(&reply).map_err(|e| ClientError::Http(format!("answer is not JSON: {e}")))?;
        let field =
            |k: &str| answer.get(k).cloned().ok_or_else(|| ClientError::Http(format!("answer lacks '{k}': {reply}")));
        let sdp = field("sdp")?.as_str().unwrap_or_default().to_string();
        // The composer answers `session` (a number), the master `session_id` (a name).
        let session_name = answer.get("session_id").and_then(|v| v.as_str()).map(str::to_owned);
        let session = match &session_name {
            Some(_) => answer.get("session").and_then(serde_json::Value::as_u64).unwrap_or_default(),
            None => field("session")?.as_u64().unwrap_or_default(),
        };
        let token = field("token")?.as_str().unwrap_or_default().to_string();
        pc.set_remote_description(RTCSessionDescription::answer(sdp.clone())?).await?;
        tokio::time::timeout(Duration::from_secs(15), open_rx.recv())
            .await
            .map_err(|_| ClientError::Timeout("the data channel to open"))?;
        Ok(Client {
            pc: Arc::clone(pc),
            media_ssrc,
            dc,
            pictures,
            texts,
            session,
            session_name,
            token,
            offer_sdp,
            answer_sdp: sdp,
        })
    }

    /// The next decoded picture that satisfies `accept`, within `timeout`.
    pub async fn next_picture(
        &mut self,
        timeout: Duration,
        accept: impl Fn(&Picture) -> bool,
    ) -> Result<Picture, ClientError> {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            match tokio::time::timeout_at(deadline, self.pictures.recv()).await {
                Ok(Some(p)) if accept(&p) => return Ok(p),
                Ok(Some(_)) => continue,
                Ok(None) | Err(_) => return Err(ClientError::Timeout("a picture")),
            }
        }
    }

    /// The next text message from the composer.
    pub async fn next_text(&mut self, timeout: Duration) -> Result<String, ClientError> {
        match tokio::time::timeout(timeout, self.texts.recv()).await {
            Ok(Some(t)) => Ok(t),
            _ => Err(ClientError::Timeout("a data-channel message")),
        }
    }

    /// Sends the composer an RTCP REMB: this receiver's estimate of the bitrate it can take.
    pub async fn send_remb(&self, bitrate_bps: f32) -> Result<(), ClientError> {
        use webrtc::rtcp::payload_feedbacks::receiver_estimated_maximum_bitrate::ReceiverEstimatedMaximumBitrate;
        let ssrc = self.media_ssrc.load(Ordering::SeqCst);
        let remb = ReceiverEstimatedMaximumBitrate { sender_ssrc: 1, bitrate: bitrate_bps, ssrcs: vec![ssrc] };
        self.pc.write_rtcp(&[Box::new(remb)]).await?;
        Ok(())
    }

    pub async fn send_pose(&self, pose: &Pose) -> Result<(), ClientError> {
        self.send_binary(pose.encode()).await
    }

    /// Any binary message (tests send malformed ones).
    pub async fn send_binary(&self, bytes: Vec<u8>) -> Result<(), ClientError> {
        self.dc.send(&Bytes::from(bytes)).await?;
        Ok(())
    }

    pub async fn send_control(&self, control: &Control) -> Result<(), ClientError> {
        let text = serde_json::to_string(control).map_err(|e| ClientError::Http(e.to_string()))?;
        self.send_text(&text).await
    }

    pub async fn send_text(&self, text: &str) -> Result<(), ClientError> {
        self.dc.send_text(text.to_string()).await?;
        Ok(())
    }

    pub async fn close(&self) {
        let _ = self.pc.close().await;
    }
}
