//! `nephele-master`: the control plane. HTTP API and signalling (axum), sessions, the scene
//! catalog, and the live loop that drives the pure scheduler core (`nephele-scheduler`) over
//! the workers' and the composer's TCP links.
//!
//! Depends on `nephele-proto`, `nephele-scheduler`, `nephele-geometry` and `nephele-pathtracer`
//! (the scene catalog's object bounds); never on kernels, trainers or another service.
//!
//! * [`access`]: who may open viewer sessions (signed invitations, a rate limit).
//! * [`http`]: the HTTP API and the [`http::FarmBackend`] trait the farm implements.
//! * [`sessions`]: the HTTP session table (ids, tokens, validated requests).
//! * [`scenes`]: the scene catalog (objects placed in the world, first views).
//! * [`farm`]: the actor that owns the scheduler, and [`farm::Farm`], its handle.
//! * [`links`]: the farm listener and one task per worker or composer connection.
//! * [`metrics`]: the Prometheus metrics (`GET /metrics`).
//! * [`service`]: both listeners and graceful shutdown: `nephele master`.
//! * [`tls`]: HTTPS for the page and the API (certificates, a self-signed one for LAN use).

pub mod access;
pub mod client_files;
pub mod farm;
pub mod http;
pub mod links;
pub mod metrics;
pub mod scenes;
pub mod service;
pub mod sessions;
pub mod tls;
