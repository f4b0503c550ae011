//! `nephele-composer`: frame assembly, depth fusion, H.264 encoding and WebRTC streaming.
//!
//! Depends on `nephele-proto`, `nephele-geometry` and `nephele-telemetry` only; never on kernels or another
//! service.
//!
//! The composer is the last stage of a frame (DESIGN.md, "What the service does", step 5):
//! workers send per-pixel results of object batches straight here; [`fusion`] gathers and
//! composites them by depth, [`yuv`] converts the fused linear picture to BT.709 YUV 4:2:0,
//! [`encode`] encodes it with OpenH264 in a low-latency IPPP configuration, and [`webrtc`]
//! sends it on the viewer's video track while poses come back over an RTCDataChannel
//! ([`pose`]). [`service`] is the thin network shell around these pure cores, one file per
//! concept: HTTP signalling (`signalling`), viewer sessions (`sessions`), the media path
//! (`media`), the farm link and results listener (`farm`, proto only) and the test pattern
//! ([`testpattern`]), over the state they share (`state`); [`metrics`] is what `GET /metrics`
//! reports; [`congestion`] turns the receiver's feedback into the stream's bitrate.

// Tests may unwrap and spell out their reference tuples.
#![cfg_attr(test, allow(clippy::unwrap_used, clippy::type_complexity, clippy::needless_range_loop))]

mod config;
pub mod congestion;
pub mod encode;
mod farm;
pub mod fusion;
pub mod latency;
mod media;
pub mod metrics;
pub mod pacer;
pub mod pose;
pub mod retransmit;
pub mod scale;
pub mod service;
mod sessions;
mod signalling;
mod state;
pub mod testpattern;
pub mod webrtc;
pub mod yuv;
