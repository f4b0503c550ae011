//! `nephele-master`: the control plane. HTTP API and signalling (axum), sessions, and (with
//! the scheduler work of issue 4) the live loop that drives the pure scheduler core over the
//! workers' TCP links.

pub mod client_files;
pub mod http;
pub mod sessions;
