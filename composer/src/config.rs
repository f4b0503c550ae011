//! The composer's configuration.

use std::net::SocketAddr;
use std::time::Duration;

use crate::webrtc::RtcConfig;

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
    /// The results listener's address as workers reach it (`composer:8091` in a container
    /// network); `None`: the bound address.
    pub advertise_results: Option<String>,
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
    /// The farm credential ([`nephele_proto::auth`]): proved to the master and demanded of
    /// every peer of the results listener; `None` is an open farm.
    pub farm_secret: Option<nephele_proto::auth::FarmSecret>,
    /// TLS with the farm certificate on the results listener (needs its key) and to the
    /// master ([`nephele_transport`]); `None`: plain TCP.
    pub farm_tls: Option<nephele_transport::FarmTls>,
    /// Required on the operators' endpoints (`GET /metrics`, `GET /v1/sessions`) when set;
    /// they are open otherwise. Signalling and the probes never ask for it.
    pub operator_token: Option<nephele_telemetry::OperatorToken>,
}

impl Default for ComposerConfig {
    fn default() -> Self {
        ComposerConfig {
            http_addr: SocketAddr::from(([127, 0, 0, 1], 8090)),
            results_addr: SocketAddr::from(([127, 0, 0, 1], 8091)),
            advertise_results: None,
            rtc: RtcConfig::default(),
            source: FrameSource::Workers,
            fps: 30.0,
            bitrate_bps: None,
            default_view: (640, 480),
            frame_budget: Duration::from_millis(40),
            max_sessions: 64,
            master: None,
            name: "composer".into(),
            farm_secret: None,
            farm_tls: None,
            operator_token: None,
        }
    }
}
