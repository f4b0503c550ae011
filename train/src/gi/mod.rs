//! The stereo neural global-illumination model's training side (Zhang and Simo-Serra; the
//! design's "Stereo GI"): its datasets ([`data`]) and the inter-eye warp of the coherence
//! loss ([`warp`]).

pub mod data;
pub mod warp;
