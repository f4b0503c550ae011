//! The master process: the HTTP API and the farm listener around one [`Farm`].
//!
//! ```no_run
//! # async fn demo() -> Result<(), nephele_master::service::MasterError> {
//! use nephele_master::service::{Master, MasterConfig};
//! let master = Master::bind(MasterConfig::default()).await?;
//! println!("http on {}, farm on {}", master.http_addr(), master.farm_addr());
//! master.run(async { let _ = tokio::signal::ctrl_c().await; }).await
//! # }
//! ```

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Instant;

use nephele_proto::FrameConfig;
use nephele_proto::auth::FarmSecret;
use thiserror::Error;
use tokio::net::TcpListener;

use crate::access::{OperatorToken, RateLimiter, ViewerKey};
use crate::farm::{Farm, FarmConfig};
use crate::http::{AccessPolicy, AppState, ClientAddr, router};
use crate::scenes::{Catalog, CatalogError};
use crate::tls::{ServerTls, TlsListener};

/// Session requests one address may make: 30 at once, then 60 a minute (a page that
/// reconnects, a load test's users and their retries from one machine stay well inside).
pub const DEFAULT_SESSION_RATE: (u32, u32) = (30, 60);

#[derive(Debug, Clone)]
pub struct MasterConfig {
    /// Where the HTTP API and the web client listen.
    pub http: String,
    /// Where workers and the composer connect.
    pub farm: String,
    pub farm_config: FarmConfig,
    pub frame: FrameConfig,
    /// The farm credential every worker and composer must prove ([`nephele_proto::auth`]);
    /// `None` is an open farm (anything that reaches `farm` may join).
    pub farm_secret: Option<FarmSecret>,
    /// TLS on the farm port with the farm certificate (needs its key), for farms that cross
    /// machines ([`nephele_transport`]).
    pub farm_tls: Option<nephele_transport::FarmTls>,
    /// HTTPS for the page and the API ([`crate::tls`]); `None`: plain http.
    pub tls: Option<ServerTls>,
    /// Invitations required to open a session, signed with this key ([`crate::access`]).
    pub viewer_key: Option<ViewerKey>,
    /// Session requests per client address: `(burst, per minute)`; a 0 turns the limit off.
    pub session_rate: (u32, u32),
    /// Bearer token the operators' endpoints (`/v1/farm`, `/metrics`, `GET /v1/sessions`)
    /// require; `None` leaves them open.
    pub operator_token: Option<OperatorToken>,
}

impl Default for MasterConfig {
    fn default() -> MasterConfig {
        MasterConfig {
            http: "127.0.0.1:8080".into(),
            farm: "127.0.0.1:7070".into(),
            farm_config: FarmConfig::default(),
            frame: FrameConfig::default(),
            farm_secret: None,
            farm_tls: None,
            tls: None,
            viewer_key: None,
            session_rate: DEFAULT_SESSION_RATE,
            operator_token: None,
        }
    }
}

#[derive(Debug, Error)]
pub enum MasterError {
    #[error("cannot listen on {addr} ({what}): {source}")]
    Bind { what: &'static str, addr: String, source: std::io::Error },
    #[error("scene catalog: {0}")]
    Catalog(#[from] CatalogError),
    #[error("scheduler: {0}")]
    Scheduler(#[from] nephele_scheduler::SchedError),
    #[error("the HTTP server failed: {0}")]
    Http(std::io::Error),
}

/// A master with its sockets bound, not yet serving.
#[derive(Debug)]
pub struct Master {
    http: TcpListener,
    farm_listener: TcpListener,
    config: MasterConfig,
    catalog: Catalog,
}

impl Master {
    /// Builds the scene catalog and binds both sockets (port 0 picks a free port; see
    /// [`Master::http_addr`]).
    pub async fn bind(config: MasterConfig) -> Result<Master, MasterError> {
        let started = Instant::now();
        let catalog = tokio::task::spawn_blocking(Catalog::builtin)
            .await
            .map_err(|e| CatalogError::Asset { asset: "builtin".into(), reason: e.to_string() })??;
        tracing::debug!(
            ms = started.elapsed().as_millis() as u64,
            scenes = catalog.scenes().len(),
            "scene catalog built"
        );
        Master::bind_with(config, catalog).await
    }

    /// [`Master::bind`] with a catalog of the caller's.
    pub async fn bind_with(config: MasterConfig, catalog: Catalog) -> Result<Master, MasterError> {
        let bind = |what: &'static str, addr: String| async move {
            TcpListener::bind(&addr).await.map_err(|source| MasterError::Bind { what, addr, source })
        };
        let http = bind("http", config.http.clone()).await?;
        let farm_listener = bind("farm", config.farm.clone()).await?;
        Ok(Master { http, farm_listener, config, catalog })
    }

    pub fn http_addr(&self) -> SocketAddr {
        self.http.local_addr().unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)))
    }

    pub fn farm_addr(&self) -> SocketAddr {
        self.farm_listener.local_addr().unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)))
    }

    /// Serves until `shutdown` resolves, then stops taking HTTP requests (those in flight
    /// finish), says goodbye to the workers and the composer, and returns.
    pub async fn run<F: Future<Output = ()> + Send + 'static>(self, shutdown: F) -> Result<(), MasterError> {
        let (http_addr, farm_addr) = (self.http_addr(), self.farm_addr());
        let Master { http, farm_listener, config, catalog } = self;
        let (farm, farm_task, mut ended) = Farm::start(config.farm_config, catalog)?;
        let start = Instant::now();
        let access = AccessPolicy {
            viewer_key: config.viewer_key,
            rate_limit: RateLimiter::new(config.session_rate.0, config.session_rate.1),
            operator_token: config.operator_token,
        };
        let state = AppState::with_access(
            Arc::new(farm.clone()),
            farm.metrics().clone(),
            Box::new(move || start.elapsed().as_secs_f64()),
            access,
        );
        // Sessions the farm ended on its own (client vanished, composer gone) leave the
        // HTTP table too, so that their ids answer 404.
        let table = state.clone();
        let forget = tokio::spawn(async move {
            while let Some(name) = ended.recv().await {
                if table.end_session(&name) {
                    tracing::info!(session = %name, "session dropped by the service");
                }
            }
        });
        if config.farm_secret.is_none() {
            tracing::warn!(
                farm = %farm_addr,
                "the farm is open: any process that reaches the farm port may join as a worker or composer \
                 (give a secret with NEPHELE_FARM_SECRET_FILE; `nephele up` does)"
            );
        }
        let secret = config.farm_secret.map(Arc::new);
        let farm_tls = config.farm_tls.map(Arc::new);
        let listener = tokio::spawn(crate::links::serve(farm_listener, farm.clone(), config.frame, secret, farm_tls));
        tracing::info!(http = %http_addr, farm = %farm_addr, "master serving");
        // Long polls on sessions answer at once when the server stops, rather than hold the
        // graceful shutdown.
        let watched = state.clone();
        let shutdown = async move {
            shutdown.await;
            watched.stop_watches();
        };
        // With each connection's address, for the per-address rate limit.
        let app = router(state).into_make_service_with_connect_info::<ClientAddr>();
        let served = match config.tls {
            Some(tls) => match TlsListener::new(http, tls.config) {
                Ok(listener) => axum::serve(listener, app).with_graceful_shutdown(shutdown).await,
                Err(e) => Err(e),
            },
            None => axum::serve(http, app).with_graceful_shutdown(shutdown).await,
        };
        tracing::info!("HTTP server stopped; closing the farm");
        listener.abort();
        farm.shutdown().await;
        forget.abort();
        drop(farm);
        let _ = farm_task.await;
        served.map_err(MasterError::Http)
    }
}
