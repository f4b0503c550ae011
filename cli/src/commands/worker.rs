//! `nephele worker`: a render worker process.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use nephele_kernels::assets::LoadOptions;
use nephele_proto::FrameConfig;
use nephele_shutdown::Shutdown;
use nephele_worker::{AssetOptions, DirAssetLoader, WorkerConfig};

/// Connects to a master, registers, and renders the ray batches it sends, sending each result
/// to the composer the batch names.
///
/// Asset ids resolve to `<ASSETS>/<id>.glb|.gltf` (path traced) or a built-in scene (see
/// `nephele scenes`), path traced at `--spp` samples per pixel; `.nolf` / `.ngp` files are
/// recognised but need the neural kernels. On SIGTERM or Ctrl-C the worker hands queued
/// batches back to the master, finishes those in flight, says goodbye and exits 0 (a second
/// signal exits at once). If the master goes away it keeps reconnecting for
/// `--reconnect-secs`, then exits with an error.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Master address, `host:port`.
    #[arg(long, value_name = "ADDR")]
    master: String,
    /// Asset directory (asset ids never resolve outside it).
    #[arg(long, value_name = "DIR")]
    assets: PathBuf,
    /// Name shown by the master (`[A-Za-z0-9._-]`, default `worker-<host name>-<pid>`).
    #[arg(long)]
    name: Option<String>,
    /// Samples per pixel of path-traced assets.
    #[arg(long, default_value_t = 4)]
    spp: u32,
    /// Bounces of path-traced assets.
    #[arg(long, default_value_t = 4)]
    bounces: u32,
    /// Instruction set of the neural kernels: auto (AVX2+FMA where the CPU has them) or off
    /// (scalar code, for comparison).
    #[arg(long, default_value = "auto", value_name = "auto|off")]
    simd: nephele_nn::SimdMode,
    /// Where the neural kernels (i-NOLF, the i-NGP baseline) run: auto (a hardware GPU if there
    /// is one, else the CPU), cpu, or gpu (a hardware GPU, else a software Vulkan adapter such
    /// as Mesa's lavapipe; an error if there is none). Path-traced assets run on the CPU.
    #[arg(long, default_value = "auto", value_name = "auto|cpu|gpu")]
    device: nephele_gpu::DeviceChoice,
    /// Voxels between the i-NOLF density march's samples: 1 marches every voxel (the asset's
    /// own accuracy); 2 about halves the samples of objects whose rays cross thick
    /// semi-transparent matter (the glass shell: 0.08 dB against the path tracer,
    /// BENCHMARKS.md). Default: the stride each asset's bake chose within its error budget on
    /// held-out views (the first start's objects, or `nephele bake --march-stride`; every
    /// voxel otherwise). The GPU kernel marches at the same stride.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=i64::from(nephele_kernels::inolf::cubes::MAX_MARCH_STRIDE)))]
    march_stride: Option<u32>,
    /// How results travel to the composer: compact (only the pixels the object touched, half
    /// floats and 16-bit opacity, about 11 bytes per touched pixel) or f32 (every pixel, 24
    /// bytes, exact).
    #[arg(long, value_enum, default_value = "compact")]
    results: ResultsArg,
    /// Batches rendering at once (each on all render threads).
    #[arg(long, default_value_t = 2)]
    concurrent_batches: usize,
    /// Most batches waiting; more are refused as overloaded (the master sends them elsewhere).
    #[arg(long, default_value_t = 4096)]
    max_queued: usize,
    /// Largest frame accepted or sent, MiB.
    #[arg(long, default_value_t = 64)]
    max_frame_mib: usize,
    /// Seconds to keep trying to reach the master, at start and after losing it.
    #[arg(long, default_value_t = 30)]
    reconnect_secs: u64,
    /// Seconds in-flight batches may take to finish after SIGTERM.
    #[arg(long, default_value_t = 30)]
    drain_secs: u64,
    /// Serve `/livez`, `/readyz` (ready once registered with the master) and `/metrics`
    /// (Prometheus; it asks for the operators' token when the worker has one) on this
    /// address, for container health checks and scrapers.
    #[arg(long, value_name = "ADDR")]
    ops: Option<std::net::SocketAddr>,
    /// Asset rendered at start-up to measure this worker's throughput.
    #[arg(long, default_value = "diffuse")]
    calibration_asset: String,
    #[command(flatten)]
    farm_secret: crate::commands::FarmSecretArgs,
    #[command(flatten)]
    operator_token: crate::commands::OperatorTokenArgs,
}

/// `worker-<host>-<pid>`: unique across containers too (every container's worker is pid 1;
/// its host name is the container's id).
fn default_name() -> String {
    let host = std::fs::read_to_string("/etc/hostname").unwrap_or_default();
    let host: String =
        host.trim().chars().filter(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '.').take(40).collect();
    if host.is_empty() {
        format!("worker-{}", std::process::id())
    } else {
        format!("worker-{host}-{}", std::process::id())
    }
}

/// `nephele worker --results`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ResultsArg {
    Compact,
    F32,
}

pub fn run(args: Args, threads: Option<usize>) -> Result<()> {
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let name = args.name.unwrap_or_else(default_name);
    let (accelerator, device) = crate::commands::open_device(args.device, args.simd)?;
    let load = LoadOptions {
        pathtrace_spp: args.spp,
        pathtrace_bounces: args.bounces,
        simd: args.simd,
        accelerator,
        march_stride: args.march_stride,
    };
    let options = AssetOptions { load, ..AssetOptions::default() };
    let loader = DirAssetLoader::new(&args.assets, options)
        .with_context(|| format!("opening the asset directory {}", args.assets.display()))?;
    let mut config = WorkerConfig::new(args.master, name, threads);
    config.max_concurrent_batches = args.concurrent_batches;
    config.result_encoding = match args.results {
        ResultsArg::Compact => nephele_proto::ResultEncoding::Compact,
        ResultsArg::F32 => nephele_proto::ResultEncoding::F32,
    };
    config.max_queued_batches = args.max_queued;
    config.frame = FrameConfig { max_frame: args.max_frame_mib.saturating_mul(1 << 20) };
    config.reconnect_for = Duration::from_secs(args.reconnect_secs);
    config.drain_timeout = Duration::from_secs(args.drain_secs);
    config.calibration_asset = args.calibration_asset;
    config.device = device;
    config.farm_secret = args.farm_secret.resolve()?;
    config.farm_tls = args.farm_secret.resolve_tls(false)?;
    // Read before the runtime starts, so that a bad file stops the worker at once.
    let operator_token = args.operator_token.resolve()?.map(|(_, kept)| kept);

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("worker-io")
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let shutdown = Shutdown::on_signals().context("installing the Ctrl-C and SIGTERM handlers")?;
    let metrics = config.metrics.clone();
    let result = runtime.block_on(async move {
        let ops = match args.ops {
            Some(addr) => {
                let router = nephele_telemetry::ops_router(metrics.registry().clone(), metrics.clone(), operator_token);
                let stop = shutdown.clone();
                let (bound, task) = nephele_telemetry::serve(addr, router, async move { stop.wait().await })
                    .await
                    .with_context(|| format!("--ops: cannot listen on {addr}"))?;
                tracing::info!(%bound, "operations endpoint: /livez /readyz /metrics");
                Some(task)
            }
            None => None,
        };
        let shutdown = async move { shutdown.wait().await };
        let result = nephele_worker::run(config, Arc::new(loader), shutdown).await.map_err(anyhow::Error::from);
        if let Some(task) = ops {
            task.abort();
        }
        result
    });
    // Renders that outlived the drain timeout must not hold the exit.
    runtime.shutdown_timeout(Duration::from_secs(1));
    result
}
