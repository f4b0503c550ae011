//! The composer process: a thin network shell around [`crate::fusion::Compositor`],
//! [`crate::encode::H264Encoder`] and the viewers' peer connections. [`Composer::start`]
//! binds the listeners and starts the parts, each in a file of its own:
//!
//! * [`crate::signalling`]: HTTP signalling (`/v1/sessions`, `/livez`, `/readyz`);
//! * [`crate::sessions`]: viewer sessions, their poses and control messages;
//! * [`crate::media`]: per session, YUV conversion, H.264 encoding and sending;
//! * [`crate::farm`]: the link to the master and the workers' results (proto), fused by
//!   frame plan;
//! * [`crate::testpattern`]: with [`FrameSource::TestPattern`], a synthetic two-object scene
//!   rendered from each viewer's latest pose, so the composer streams without a farm.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex as StdMutex};

use nephele_shutdown::Shutdown;
use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::{Notify, broadcast, mpsc};
use tokio::task::JoinHandle;

pub use crate::config::{ComposerConfig, FrameSource};
use crate::fusion::{Compositor, FusionLimits, SessionId};
use crate::pose::Pose;
use crate::sessions::{end_session, event_loop, layout_for};
use crate::state::{SessionReport, Shared, lock, reports};
use crate::webrtc::{RtcError, RtcStack};

#[derive(Debug, Error)]
pub enum ServiceError {
    #[error("binding {what} on {addr}: {source}")]
    Bind { what: &'static str, addr: SocketAddr, source: std::io::Error },
    #[error(transparent)]
    Rtc(#[from] RtcError),
    #[error("bad configuration: {0}")]
    Config(String),
}

/// A running composer. Dropping it does not stop it; call [`Composer::shutdown`].
pub struct Composer {
    shared: Arc<Shared>,
    http_addr: SocketAddr,
    results_addr: SocketAddr,
    stop: Shutdown,
    tasks: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for Composer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Composer")
            .field("http", &self.http_addr)
            .field("results", &self.results_addr)
            .finish_non_exhaustive()
    }
}

impl Composer {
    /// Binds the HTTP and results listeners and starts serving (inside a tokio runtime).
    pub async fn start(config: ComposerConfig) -> Result<Composer, ServiceError> {
        if !(config.fps.is_finite() && (1.0..=240.0).contains(&config.fps)) {
            return Err(ServiceError::Config(format!("frame rate {} outside 1..240", config.fps)));
        }
        layout_for(config.default_view.0, config.default_view.1, 1).map_err(ServiceError::Config)?;
        let rtc = RtcStack::new(config.rtc.clone())?;
        let http = TcpListener::bind(config.http_addr).await.map_err(|source| ServiceError::Bind {
            what: "HTTP",
            addr: config.http_addr,
            source,
        })?;
        let results = TcpListener::bind(config.results_addr).await.map_err(|source| ServiceError::Bind {
            what: "worker results",
            addr: config.results_addr,
            source,
        })?;
        let http_addr =
            http.local_addr().map_err(|source| ServiceError::Bind { what: "HTTP", addr: config.http_addr, source })?;
        let results_addr = results.local_addr().map_err(|source| ServiceError::Bind {
            what: "worker results",
            addr: config.results_addr,
            source,
        })?;
        let (events_tx, events_rx) = mpsc::channel(4096);
        let (poses, _) = broadcast::channel(256);
        let shared = Arc::new(Shared {
            config,
            rtc,
            compositor: StdMutex::new(Compositor::new(FusionLimits::default())),
            sessions: StdMutex::new(HashMap::new()),
            next_session: AtomicU64::new(1),
            wake: Notify::new(),
            events: events_tx,
            poses,
            metrics: crate::metrics::ComposerMetrics::new(),
            runtime: tokio::runtime::Handle::current(),
            to_master: StdMutex::new(None),
            task_results: StdMutex::new(crate::state::TaskResults::default()),
            last_parts: StdMutex::new(HashMap::new()),
            latency: StdMutex::new(crate::latency::LatencyTracker::default()),
        });
        let stop = Shutdown::new();
        let mut tasks = Vec::new();
        let router = crate::signalling::router(Arc::clone(&shared));
        let http_stop = stop.clone();
        tasks.push(tokio::spawn(async move {
            let shutdown = async move {
                let _ = http_stop.wait().await;
            };
            if let Err(e) = axum::serve(http, router).with_graceful_shutdown(shutdown).await {
                tracing::error!("HTTP server: {e}");
            }
        }));
        tasks.push(tokio::spawn(crate::farm::accept_results(Arc::clone(&shared), results, stop.clone())));
        tasks.push(tokio::spawn(crate::media::fusion_loop(Arc::clone(&shared), stop.clone())));
        tasks.push(tokio::spawn(event_loop(Arc::clone(&shared), events_rx, stop.clone())));
        if let Some(master) = shared.config.master.clone() {
            tasks.push(tokio::spawn(crate::farm::run(Arc::clone(&shared), master, results_addr, stop.clone())));
        }
        if shared.config.source == FrameSource::TestPattern {
            tasks.push(tokio::spawn(crate::testpattern::test_pattern_loop(Arc::clone(&shared), stop.clone())));
        }
        tracing::info!(%http_addr, %results_addr, source = ?shared.config.source, "composer listening");
        Ok(Composer { shared, http_addr, results_addr, stop, tasks })
    }

    pub fn http_addr(&self) -> SocketAddr {
        self.http_addr
    }

    pub fn results_addr(&self) -> SocketAddr {
        self.results_addr
    }

    /// Every accepted pose, as it arrives.
    pub fn poses(&self) -> broadcast::Receiver<(SessionId, Arc<Pose>)> {
        self.shared.poses.subscribe()
    }

    pub fn sessions(&self) -> Vec<SessionReport> {
        reports(&self.shared)
    }

    /// Malformed worker messages seen so far.
    pub fn wire_errors(&self) -> u64 {
        self.shared.metrics.wire_errors.get()
    }

    /// Stops listening, closes every peer connection and waits for the tasks.
    pub async fn shutdown(self) {
        self.stop.trigger();
        let ids: Vec<SessionId> = lock(&self.shared.sessions).keys().copied().collect();
        for id in ids {
            end_session(&self.shared, id).await;
        }
        for t in self.tasks {
            let _ = t.await;
        }
    }
}
