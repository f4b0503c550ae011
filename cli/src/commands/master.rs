//! `nephele master`: the control plane (HTTP API, signalling, the live scheduler).

use std::io::Write;
use std::time::Duration;

use anyhow::{Context, Result, ensure};

use crate::commands::AdmitUpTo;
use nephele_master::farm::{DEFAULT_ADMIT_UP_TO, DEFAULT_PREVIOUS_FRAMES, FarmConfig, live_scheduler_config};
use nephele_master::service::{Master, MasterConfig};
use nephele_proto::{FrameConfig, ReuseLimits};
use nephele_scheduler::Policy;
use nephele_shutdown::Shutdown;
use serde_json::json;

/// Runs the master: the HTTP API and web client (`--http`), and the farm listener
/// (`--farm-listen`) where `nephele worker` processes and the composer connect.
///
/// The master owns the scheduler (NEPHELE Algorithm 1): it turns each session's poses into
/// ray batches, dispatches them to workers, re-issues the batches of a worker that dies or
/// stalls, and tells the composer which results make up each frame. `GET /v1/farm` shows
/// the workers, their load, the queues and each session's frame rate. Once both sockets
/// listen it prints `listening: http=ADDR farm=ADDR` on stdout. On SIGTERM or Ctrl-C it stops
/// taking requests, says goodbye to the workers and the composer and exits 0 (a second
/// signal exits at once).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// HTTP API and web client address (port 0 picks a free port).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:8080")]
    http: String,
    /// Address workers and the composer connect to (port 0 picks a free port).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:7070")]
    farm_listen: String,
    /// STUN/TURN server URL offered to browsers (repeatable), e.g. `stun:stun.example.org:3478`.
    #[arg(long = "ice-server", value_name = "URL")]
    ice_servers: Vec<String>,
    /// Username for the `turn:` servers among `--ice-server`.
    #[arg(long, value_name = "NAME", requires = "ice_credential")]
    ice_username: Option<String>,
    /// Credential for the `turn:` servers (with `--ice-username`).
    #[arg(long, value_name = "SECRET", requires = "ice_username")]
    ice_credential: Option<String>,
    /// Scheduling policy: nephele (Algorithm 1), or a baseline: round-robin, fifo,
    /// object-per-worker.
    #[arg(long, default_value = "nephele")]
    policy: Policy,
    /// Admission that looks ahead: refuse a new user (503, Retry-After 5 s) while the work
    /// the admitted users ask for (frame rate x the rays their own frames render, shared rays
    /// counted once) plus the newcomer's would pass this fraction of the farm's measured
    /// throughput. Default 0.9 under the nephele policy; `off` leaves only Algorithm 1's
    /// starvation refusal (users are then admitted until someone is starved).
    #[arg(long, value_name = "FRACTION|off")]
    admit_up_to: Option<AdmitUpTo>,
    /// Largest ray batch, pixels.
    #[arg(long, value_name = "N")]
    max_batch_rays: Option<u32>,
    /// Render every view of a headset or a light-field quilt in full, instead of deriving
    /// views from an adjacent view of the same frame by reprojection on the worker (4 degrees
    /// apart at most, seen from the object; only the pixels reprojection cannot vouch for
    /// rendered). For comparisons.
    #[arg(long)]
    no_derived_views: bool,
    /// A user's consecutive frames: a worker renders a view of an object in full, then takes
    /// up to N following frames of it from that render by reprojection (seen within 6
    /// degrees of it, younger than a second), rendering only the pixels reprojection cannot
    /// vouch for. 0 renders every frame in full. Default: 3 (one frame in four in full) for
    /// the nephele policy, 0 for the baselines.
    #[arg(long, value_name = "N")]
    previous_frames: Option<u32>,
    /// Render ahead (nephele policy, previous frames above 0): while the farm is idle (nothing
    /// waiting, every worker free) and there is time before the next frame is due, each
    /// moving user's next view of each object is predicted from its last two poses and
    /// rendered ahead, the views that most users' views lie near first; the worker keeps it
    /// as the user's previous render (lending it to other users' views near it), so the
    /// frame then renders only what reprojection leaves. A busy farm never renders ahead.
    /// Off by default: on two cores shared by workers and composer it made frames later, not
    /// sooner (BENCHMARKS.md, 2026-12-07); meant for farms on hardware of their own.
    #[arg(long)]
    render_ahead: bool,
    /// A batch not back after this long (at the least; more for long queues) is re-issued.
    #[arg(long, value_name = "MS", default_value_t = 50)]
    min_batch_timeout_ms: u64,
    /// A worker silent for this long is declared lost and its batches re-issued.
    #[arg(long, value_name = "MS", default_value_t = 2000)]
    heartbeat_timeout_ms: u64,
    /// How often workers report their load (the heartbeat).
    #[arg(long, value_name = "MS", default_value_t = 200)]
    load_report_ms: u32,
    /// Seconds `POST /v1/sessions` waits for the composer's SDP answer.
    #[arg(long, value_name = "S", default_value_t = 10)]
    open_timeout_secs: u64,
    /// Largest protocol frame accepted or sent, MiB.
    #[arg(long, default_value_t = 64)]
    max_frame_mib: usize,
    #[command(flatten)]
    farm_secret: crate::commands::FarmSecretArgs,
    #[command(flatten)]
    tls: crate::commands::TlsArgs,
    #[command(flatten)]
    viewer_key: crate::commands::ViewerKeyArgs,
    #[command(flatten)]
    operator_token: crate::commands::OperatorTokenArgs,
    /// Session requests one client address may make at once (then
    /// `--sessions-per-minute`); beyond, `POST /v1/sessions` answers 429 with Retry-After.
    /// 0 turns the limit off (behind a reverse proxy every client has the proxy's address).
    #[arg(long, value_name = "N", default_value_t = nephele_master::service::DEFAULT_SESSION_RATE.0)]
    session_burst: u32,
    /// Session requests per minute one client address may make after its burst.
    #[arg(long, value_name = "N", default_value_t = nephele_master::service::DEFAULT_SESSION_RATE.1)]
    sessions_per_minute: u32,
}

pub fn run(args: Args) -> Result<()> {
    ensure!((10..=60_000).contains(&args.load_report_ms), "--load-report-ms must be between 10 and 60000");
    ensure!(
        args.heartbeat_timeout_ms > u64::from(args.load_report_ms),
        "--heartbeat-timeout-ms must exceed --load-report-ms"
    );
    let ice_servers: Vec<serde_json::Value> = args
        .ice_servers
        .iter()
        .map(|url| {
            let mut server = json!({ "urls": [url] });
            if url.starts_with("turn")
                && let (Some(user), Some(secret)) = (&args.ice_username, &args.ice_credential)
            {
                server["username"] = json!(user);
                server["credential"] = json!(secret);
            }
            server
        })
        .collect();
    let mut scheduler = nephele_scheduler::SchedulerConfig { policy: args.policy, ..live_scheduler_config() };
    if args.policy != Policy::Nephele {
        let baseline = nephele_scheduler::SchedulerConfig::for_policy(args.policy);
        scheduler.sharing = baseline.sharing;
        scheduler.history_capacity = baseline.history_capacity;
        scheduler.admission_control = baseline.admission_control;
        scheduler.derived_views = baseline.derived_views;
    }
    if args.no_derived_views {
        scheduler.derived_views = None;
    }
    if args.render_ahead {
        ensure!(args.policy == Policy::Nephele, "--render-ahead needs the nephele policy");
        scheduler.render_ahead = Some(nephele_scheduler::RenderAhead::default());
    }
    scheduler.admit_up_to = match args.admit_up_to {
        None => scheduler.admission_control.then_some(DEFAULT_ADMIT_UP_TO),
        Some(AdmitUpTo(None)) => None,
        Some(AdmitUpTo(Some(fraction))) => {
            ensure!(scheduler.admission_control, "--admit-up-to needs the nephele policy's admission control");
            Some(fraction)
        }
    };
    if let Some(n) = args.max_batch_rays {
        scheduler.max_batch_rays = n;
    }
    scheduler.min_batch_timeout = Duration::from_millis(args.min_batch_timeout_ms);
    scheduler.heartbeat_timeout = Some(Duration::from_millis(args.heartbeat_timeout_ms));
    scheduler.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    let default_previous = if args.policy == Policy::Nephele { DEFAULT_PREVIOUS_FRAMES } else { 0 };
    let previous_frames = args.previous_frames.unwrap_or(default_previous);
    ensure!(
        previous_frames <= ReuseLimits::MAX_PREVIOUS_FRAMES,
        "--previous-frames must be at most {}",
        ReuseLimits::MAX_PREVIOUS_FRAMES
    );
    let config = MasterConfig {
        http: args.http,
        farm: args.farm_listen,
        farm_config: FarmConfig {
            scheduler,
            load_report_interval_ms: args.load_report_ms,
            open_timeout: Duration::from_secs(args.open_timeout_secs.max(1)),
            ice_servers: json!(ice_servers),
            previous_frames,
        },
        frame: FrameConfig { max_frame: args.max_frame_mib.saturating_mul(1 << 20) },
        farm_secret: args.farm_secret.resolve()?,
        farm_tls: args.farm_secret.resolve_tls(true)?,
        tls: args.tls.resolve()?,
        viewer_key: args.viewer_key.resolve()?,
        session_rate: (args.session_burst, args.sessions_per_minute),
        operator_token: args.operator_token.resolve()?.map(|(_, kept)| kept),
    };
    let tls = config.tls.as_ref().map(|t| (t.fingerprint.clone(), t.cert_path.clone()));

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("master")
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let shutdown = Shutdown::on_signals().context("installing the Ctrl-C and SIGTERM handlers")?;
    let result = runtime.block_on(async move {
        let master = Master::bind(config).await?;
        let mut out = std::io::stdout().lock();
        writeln!(out, "listening: http={} farm={}", master.http_addr(), master.farm_addr())?;
        if let Some((fingerprint, cert)) = &tls {
            writeln!(out, "tls: sha256={fingerprint} certificate={}", cert.display())?;
        }
        out.flush()?;
        drop(out);
        let scheme = if tls.is_some() { "https" } else { "http" };
        tracing::info!("web client at {scheme}://{}/", master.http_addr());
        master.run(async move { shutdown.wait().await }).await.map_err(anyhow::Error::from)
    });
    runtime.shutdown_timeout(Duration::from_secs(1));
    result
}
