//! `nephele-composer`: frame assembly, depth fusion, H.264 encoding and WebRTC streaming.
//!
//! Depends on `nephele-proto` and `nephele-geometry` only; never on kernels or another
//! service.
//!
//! The composer is the last stage of a frame (DESIGN.md, "What the service does", step 5):
//! workers send per-pixel results of object batches straight here; [`fusion`] gathers and
//! composites them by depth, [`yuv`] converts the fused linear picture to BT.709 YUV 4:2:0,
//! [`encode`] encodes it with OpenH264 in a low-latency IPPP configuration, and [`webrtc`]
//! sends it on the viewer's video track while poses come back over an RTCDataChannel
//! ([`pose`]). [`service`] is the thin network shell (HTTP signalling, the worker-results
//! listener of [`wire`]) around these pure cores.

// Tests may unwrap and spell out their reference tuples.
#![cfg_attr(test, allow(clippy::unwrap_used, clippy::type_complexity, clippy::needless_range_loop))]

pub mod client;
pub mod encode;
pub mod fusion;
pub mod latency;
mod master_link;
pub mod pose;
pub mod service;
pub mod testpattern;
pub mod webrtc;
pub mod wire;
pub mod yuv;
