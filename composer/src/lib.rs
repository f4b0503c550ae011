//! `nephele-composer`: frame assembly, depth fusion, H.264 encoding and WebRTC streaming.
//!
//! Empty for now: it arrives with the composer and streaming work (issue 5).
