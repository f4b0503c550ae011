//! `nephele-worker`: the render worker process (`nephele worker`).
//!
//! Depends on `nephele-proto`, `nephele-geometry`, `nephele-kernels`, `nephele-pathtracer`
//! (built-in scenes), `nephele-share` (derived views) and `nephele-telemetry` (metrics); never on a trainer (`nephele-train`) or another service.
//!
//! A worker connects to the master, says hello, registers (name, threads, kernel kinds and
//! the throughput a short calibration render measured), then serves [`nephele_proto::RayBatch`]es:
//! it loads the batch's asset on demand ([`assets`]), renders the pixel set with the asset's
//! [`nephele_kernels::kernel::RayKernel`] on its own rayon pool (never on the async runtime's
//! threads), sends the [`nephele_proto::BatchResult`] straight to the composer the batch names
//! (one cached connection per composer) and tells the master `BatchDone` or `BatchFailed`.
//! It reports its load periodically (the heartbeat), honours cancellations, reconnects if it
//! loses the master, and on shutdown hands back queued batches, finishes in-flight ones and
//! says goodbye. A batch may carry derived views ([`derive`]): adjacent views of the same
//! asset taken from its pixels by reprojection, only their leftovers rendered; and it may be
//! taken from the worker's previous full render of the same user's view ([`temporal`]).

pub mod assets;
mod composer;
pub mod derive;
pub mod metrics;
mod service;
pub mod temporal;

pub use assets::{AssetError, AssetLoader, AssetOptions, DirAssetLoader};
pub use metrics::WorkerMetrics;
pub use service::{WorkerConfig, WorkerError, run};
