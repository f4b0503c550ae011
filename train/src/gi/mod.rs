//! The stereo neural global-illumination model's training side (Zhang and Simo-Serra; the
//! design's "Stereo GI"): its datasets ([`data`]), the single-eye teacher's training
//! ([`train`]), the stereo student's training and evaluation ([`stereo`]) and the inter-eye
//! warp of the coherence loss ([`warp`]).

pub mod data;
pub mod stereo;
pub mod train;
pub mod warp;
