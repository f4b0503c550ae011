//! `nephele-master`: HTTP API and signalling, sessions, the TaskAssigner and the ray-level
//! scheduler (NEPHELE Algorithm 1).
//!
//! Empty for now: it arrives with the ray-level scheduling work (issue 4).
