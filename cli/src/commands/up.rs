//! `nephele up`: the whole service on one machine, as child processes of this executable.

use std::net::{SocketAddr, TcpListener};
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use super::first_start::{BakeQuality, default_asset_dir, ensure_baked, ensure_environment};
use crate::progress::Progress;
use crate::supervise::{Restart, Supervisor, WatchEnd};
use nephele_shutdown::Shutdown;

/// Runs the service locally: one `nephele master`, one `nephele composer --master ...` and
/// `--workers` × `nephele worker --master ...`, on free loopback ports (the master's HTTP
/// address excepted), waits until the master sees the composer and every worker, prints the
/// URL to open, and stops everything on Ctrl-C. A worker or the composer that dies is
/// started again (backoff from 0.5 s, doubling to 10 s) and rejoins the farm, whose master
/// re-issues the lost batches; the master's death, or a process crashing more than 5 times
/// in 2 minutes, stops everything with a message saying which.
///
/// The scene's objects are served as baked i-NOLF assets (one small-network query per
/// ray). None ship with Nephele: the first start bakes the scene's built-in objects (a
/// path-traced dataset of each, then `nephele bake`), with progress bars, into a cache
/// folder that later starts reuse (`--assets`; see `--bake` for the quality, or `--bake off`
/// to have the workers path trace the objects instead). An object's asset is
/// `ASSETS/<object>.nolf`; put your own there to serve it.
///
/// The scenes `room-day` and `room-night` (`--scene room-day`) put the knot inside a
/// furnished room served as an environment: the first start also renders a small GI dataset
/// of the room and trains its single-eye GI model and stereo student
/// (`ASSETS/room-day.ngi`, `ASSETS/room-day.stereo.ngi`, about 3 minutes with the standard
/// recipe); the workers shade every view of the room with it (a headset's two eyes in one
/// stereo pass) and the composer fuses the objects into it by depth.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The master's HTTP address: the viewer page, `POST /v1/sessions`, `GET /v1/farm`.
    #[arg(long, default_value = "127.0.0.1:8080")]
    http: SocketAddr,
    /// Render workers to start.
    #[arg(long, default_value_t = 2)]
    workers: usize,
    /// Scene the printed URL opens (`nephele scenes`; the master's catalog).
    #[arg(long, default_value = "default")]
    scene: String,
    /// How the first start bakes the scene's objects: standard (a few minutes per object on
    /// two cores), quick (seconds per object, blurry), or off (objects without an asset are
    /// path traced by the workers).
    #[arg(long, value_enum, default_value = "standard")]
    bake: BakeQuality,
    /// Path-tracing samples per pixel of the workers, for objects served path traced.
    #[arg(long, default_value_t = 1)]
    spp: u32,
    /// Instruction set of the workers' neural kernels: auto (AVX2+FMA where the CPU has
    /// them) or off (scalar code, for comparison).
    #[arg(long, default_value = "auto", value_name = "auto|off")]
    simd: nephele_nn::SimdMode,
    /// Where the workers run their neural kernels (i-NOLF, the i-NGP baseline): auto (a hardware GPU if there is one, else
    /// the CPU), cpu, or gpu (a hardware GPU, else a software Vulkan adapter).
    #[arg(long, default_value = "auto", value_name = "auto|cpu|gpu")]
    device: nephele_gpu::DeviceChoice,
    /// The workers' voxels between the i-NOLF density march's samples: 1 marches every voxel (the asset's
    /// own accuracy); 2 about halves the samples of objects whose rays cross thick
    /// semi-transparent matter (the glass shell: 0.08 dB against the path tracer,
    /// BENCHMARKS.md). Default: the stride each asset's bake chose within its error budget on
    /// held-out views (the first start's objects, or `nephele bake --march-stride`; every
    /// voxel otherwise). The GPU kernel marches at the same stride.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=i64::from(nephele_kernels::inolf::cubes::MAX_MARCH_STRIDE)))]
    march_stride: Option<u32>,
    /// Asset folder of the workers, where the first start bakes missing objects (default:
    /// `$NEPHELE_CACHE`, `$XDG_CACHE_HOME/nephele` or `~/.cache/nephele`, then
    /// `assets/<quality>`).
    #[arg(long, value_name = "DIR")]
    assets: Option<PathBuf>,
    /// Bake the scene's missing assets into the asset folder and exit without starting the
    /// service (a container cluster's one-shot bake job fills the shared asset volume so).
    #[arg(long)]
    bake_only: bool,
    /// How long to wait for every process to join the farm, seconds.
    #[arg(long, default_value_t = 120)]
    ready_secs: u64,
    /// Admission that looks ahead (the master's `--admit-up-to`): refuse new users while the
    /// asked work would pass this fraction of the farm's measured throughput (default 0.9),
    /// or `off`.
    #[arg(long, value_name = "FRACTION|off")]
    admit_up_to: Option<crate::commands::AdmitUpTo>,
    /// Render every view of a headset or a quilt in full (the master's `--no-derived-views`).
    #[arg(long)]
    no_derived_views: bool,
    /// Send each video frame as one burst instead of pacing it (the composer's
    /// `--no-pacing`).
    #[arg(long)]
    no_pacing: bool,
    /// Frames a worker may take from its previous full render of a view (the master's
    /// `--previous-frames`; 0: every frame in full).
    #[arg(long, value_name = "N")]
    previous_frames: Option<u32>,
    /// Render each moving user's next view ahead while the farm is idle (the master's
    /// `--render-ahead`; off by default: on one shared machine it costs latency).
    #[arg(long)]
    render_ahead: bool,
    #[command(flatten)]
    tls: crate::commands::TlsArgs,
    #[command(flatten)]
    viewer_key: crate::commands::ViewerKeyArgs,
    #[command(flatten)]
    operator_token: crate::commands::OperatorTokenArgs,
    /// The farm secret (see `nephele master --help`); without one `up` makes a fresh secret
    /// for its own processes, so nothing else can join its farm.
    #[command(flatten)]
    farm_secret: crate::commands::FarmSecretArgs,
}

/// `N` distinct free loopback ports. Each listener is held until all are found: released one
/// by one, the kernel could hand the same port out twice (CI saw the master's farm port and
/// the composer's HTTP port collide).
fn free_ports<const N: usize>() -> Result<[SocketAddr; N]> {
    let listeners =
        (0..N).map(|_| TcpListener::bind("127.0.0.1:0").context("finding a free port")).collect::<Result<Vec<_>>>()?;
    let addresses =
        listeners.iter().map(|l| l.local_addr().context("finding a free port")).collect::<Result<Vec<_>>>()?;
    addresses.try_into().map_err(|_| anyhow::anyhow!("finding {N} free ports"))
}

/// A blocking `GET` of one of the master's JSON endpoints (the workspace's one HTTP client).
fn http_get(addr: SocketAddr, path: &str, tls: &Probe, bearer: Option<&str>) -> Result<String> {
    use nephele_loadgen::http::{Verify, request_blocking_with};
    let (scheme, verify) = match tls {
        Probe::Plain => ("http", Verify::Trusted),
        Probe::SelfSigned => ("https", Verify::Trusted),
        Probe::OperatorCertificate => ("https", Verify::Unchecked),
    };
    // The master's own address, or loopback when it listens on every interface.
    let host = if addr.ip().is_unspecified() { SocketAddr::from(([127, 0, 0, 1], addr.port())) } else { addr };
    let url = format!("{scheme}://{host}{path}");
    let authorization = bearer.map(|token| format!("Bearer {token}"));
    let headers: Vec<(&str, &str)> = authorization.iter().map(|a| ("authorization", a.as_str())).collect();
    let response = request_blocking_with(&url, "GET", &headers, "", Duration::from_secs(5), verify)?;
    if response.status != 200 {
        bail!("GET {path}: status {}", response.status);
    }
    Ok(response.body)
}

/// The host and port to put in the page's URL: the listening address, or this machine's
/// LAN address when it listens on every interface.
fn page_host(http: SocketAddr) -> String {
    match nephele_master::tls::lan_address() {
        Some(ip) if http.ip().is_unspecified() => SocketAddr::new(ip, http.port()).to_string(),
        _ => http.to_string(),
    }
}

/// How `up` reaches its own master.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Probe {
    Plain,
    /// Its self-signed certificate, trusted for this process (it names 127.0.0.1).
    SelfSigned,
    /// The operator's certificate names the public host, not the address probed: the probe
    /// of our own child goes without the check.
    OperatorCertificate,
}

/// `(composer registered, workers registered)` from the master's `GET /v1/farm`.
fn farm_members(http: SocketAddr, tls: &Probe, operator_token: Option<&str>) -> Option<(bool, usize)> {
    let farm: serde_json::Value = serde_json::from_str(&http_get(http, "/v1/farm", tls, operator_token).ok()?).ok()?;
    let workers = farm.get("workers").and_then(|w| w.as_array()).map_or(0, Vec::len);
    Some((farm.get("composer").is_some_and(|c| !c.is_null()), workers))
}

/// The built-in objects of `scene` in the master's catalog (the ones a first start can bake).
fn builtin_objects_of(scene: &str) -> Result<Vec<String>> {
    use nephele_master::scenes::{BUILTIN_OBJECTS, Catalog};
    let catalog = Catalog::builtin().map_err(|e| anyhow::anyhow!("building the scene catalog: {e}"))?;
    let Some(def) = catalog.scene(scene) else {
        let names: Vec<&str> = catalog.scenes().iter().map(|s| s.name.as_str()).collect();
        bail!("--scene {scene:?} is not in the catalog; known scenes: {}", names.join(", "));
    };
    Ok(def
        .objects
        .iter()
        .filter_map(|id| catalog.object(*id))
        .map(|o| o.asset.clone())
        .filter(|asset| BUILTIN_OBJECTS.contains(&asset.as_str()))
        .collect())
}

/// The environments of `scene` (built-in rooms served by a GI model).
fn environments_of(scene: &str) -> Result<Vec<String>> {
    use nephele_master::scenes::Catalog;
    let catalog = Catalog::builtin().map_err(|e| anyhow::anyhow!("building the scene catalog: {e}"))?;
    let Some(def) = catalog.scene(scene) else { return Ok(Vec::new()) };
    Ok(def
        .objects
        .iter()
        .filter_map(|id| catalog.object(*id))
        .filter(|o| catalog.is_environment(&o.asset))
        .map(|o| o.asset.clone())
        .collect())
}

pub fn run(args: Args, progress: &Progress, log_format: crate::LogFormat) -> Result<()> {
    if args.workers == 0 {
        bail!("--workers must be at least 1");
    }
    let objects = builtin_objects_of(&args.scene)?;
    let assets = args.assets.clone().unwrap_or_else(|| default_asset_dir(args.bake));
    std::fs::create_dir_all(&assets).with_context(|| format!("creating the asset folder {}", assets.display()))?;
    // Before the Ctrl-C handler: a Ctrl-C while baking simply ends the process, and what is
    // baked by then stays (each asset is renamed into place only once complete).
    let mut baked = ensure_baked(&assets, &objects, args.bake, progress)?;
    let environments = environments_of(&args.scene)?;
    for environment in &environments {
        baked.extend(
            ensure_environment(&assets, environment, args.bake, progress)
                .with_context(|| format!("training the environment '{environment}'"))?,
        );
    }
    for object in &baked {
        match object.psnr_db {
            Some(db) => println!(
                "baked '{}' in {:.0} s ({db:.2} dB on held-out views{}): {}",
                object.name,
                object.seconds,
                object.march_stride.map(|s| format!(", march stride {s}")).unwrap_or_default(),
                object.path.display()
            ),
            None => println!("using the baked '{}': {}", object.name, object.path.display()),
        }
    }
    if args.bake_only {
        println!("assets ready in {} ({} objects)", assets.display(), baked.len());
        return Ok(());
    }
    // The certificate first (made and cached here, so the master finds it), and how to
    // probe the master with it.
    let tls = args.tls.resolve()?;
    let probe = match (&tls, args.tls.tls_self_signed) {
        (None, _) => Probe::Plain,
        (Some(tls), true) => {
            nephele_loadgen::http::trust_certificates(&tls.cert_path)?;
            Probe::SelfSigned
        }
        (Some(_), false) => Probe::OperatorCertificate,
    };
    let stop = Shutdown::on_signals().context("installing the Ctrl-C and SIGTERM handlers")?;
    let exe = std::env::current_exe().context("locating the nephele executable")?;
    let [farm, composer_http, composer_results] = free_ports()?;
    let mut supervisor = Supervisor::new();
    // The farm credential: the one given (so that workers on other machines holding the
    // same file can join this farm), else a fresh one for this run. The children get it in
    // their environment, which `ps` does not show to other users.
    let secret = match args.farm_secret.resolve()? {
        Some(secret) => secret,
        None => nephele_proto::auth::FarmSecret::generate()?,
    };
    // TLS between the processes when asked: the folder's certificate, made there when it has
    // none (workers on other machines joining this farm need a copy of its `farm.crt`).
    let farm_tls = match args.farm_secret.tls_dir() {
        Some(dir) => {
            if !dir.join(nephele_transport::CERT_FILE).exists() {
                nephele_transport::FarmTls::generate(&dir)
                    .with_context(|| format!("making the farm certificate in {}", dir.display()))?;
                tracing::info!(dir = %dir.display(), "made a farm certificate for TLS between the farm's processes");
            }
            args.farm_secret.resolve_tls(true)?;
            Some(std::path::absolute(&dir).with_context(|| format!("the farm TLS folder {}", dir.display()))?)
        }
        None => None,
    };
    // `nephele ROLE --log-format F ...`: every process logs in the format asked of `nephele up`.
    let nephele = |role: &str| {
        let mut command = Command::new(&exe);
        command.args([role, "--log-format", &log_format.to_string()]);
        command.env_remove(nephele_proto::auth::SECRET_FILE_ENV).env(nephele_proto::auth::SECRET_ENV, secret.expose());
        match &farm_tls {
            Some(dir) => command.env(super::FARM_TLS_ENV, dir),
            None => command.env_remove(super::FARM_TLS_ENV),
        };
        command
    };
    let mut master = nephele("master");
    master.args(["--http", &args.http.to_string(), "--farm-listen", &farm.to_string()]);
    master.args(args.tls.to_args());
    let viewer_key = args.viewer_key.resolve()?;
    if let Some(file) = args.viewer_key.file() {
        master.arg("--viewer-key-file").arg(file);
    }
    if let Some(admit) = args.admit_up_to {
        master.args(["--admit-up-to", &admit.to_string()]);
    }
    if args.no_derived_views {
        master.arg("--no-derived-views");
    }
    if let Some(n) = args.previous_frames {
        master.args(["--previous-frames", &n.to_string()]);
    }
    if args.render_ahead {
        master.arg("--render-ahead");
    }
    // Read here too: `up` asks its master's `/v1/farm` whether the farm is whole.
    let operator_token = args.operator_token.resolve()?.map(|(token, _)| token);
    if let Some(file) = args.operator_token.file() {
        master.arg("--operator-token-file").arg(file);
    }
    supervisor.spawn("master", master, Restart::Never)?;
    let mut composer = nephele("composer");
    composer.args([
        "--master",
        &farm.to_string(),
        "--http",
        &composer_http.to_string(),
        "--results",
        &composer_results.to_string(),
    ]);
    if let Some(file) = args.operator_token.file() {
        composer.arg("--operator-token-file").arg(file);
    }
    if args.no_pacing {
        composer.arg("--no-pacing");
    }
    supervisor.spawn("composer", composer, Restart::OnExit)?;
    for i in 0..args.workers {
        let mut worker = nephele("worker");
        worker.args([
            "--master",
            &farm.to_string(),
            "--name",
            &format!("worker-{i}"),
            "--spp",
            &args.spp.to_string(),
            "--simd",
            &args.simd.to_string(),
            "--device",
            &args.device.to_string(),
        ]);
        if let Some(stride) = args.march_stride {
            worker.arg("--march-stride").arg(stride.to_string());
        }
        worker.arg("--assets").arg(&assets);
        // Calibrate on an object the workers will serve (its kernel, on its device), not on
        // the path-traced default: the scheduler's estimates come from this figure.
        if let Some(object) = baked.first() {
            worker.args(["--calibration-asset", &object.name]);
        }
        supervisor.spawn(&format!("worker-{i}"), worker, Restart::OnExit)?;
    }
    // Wait until the farm is whole (workers calibrate before they register).
    let started = Instant::now();
    loop {
        if stop.is_triggered() {
            supervisor.shutdown(Duration::from_secs(10));
            return Ok(());
        }
        if let Some((name, status)) = supervisor.exited()? {
            supervisor.shutdown(Duration::from_secs(10));
            bail!("{name} exited while starting ({status}); everything stopped");
        }
        if let Some((true, n)) = farm_members(args.http, &probe, operator_token.as_deref())
            && n >= args.workers
        {
            break;
        }
        if started.elapsed() > Duration::from_secs(args.ready_secs) {
            supervisor.shutdown(Duration::from_secs(10));
            bail!("the farm did not assemble within {} s; everything stopped", args.ready_secs);
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    println!("nephele up: master, composer and {} workers ready", args.workers);
    let (neural, traced): (Vec<&String>, Vec<&String>) =
        objects.iter().partition(|o| assets.join(format!("{o}.nolf")).is_file());
    let list = |v: &[&String]| v.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ");
    if !neural.is_empty() {
        println!(
            "scene '{}': {} served by the i-NOLF kernel (assets in {})",
            args.scene,
            list(&neural),
            assets.display()
        );
    }
    if !traced.is_empty() {
        println!("scene '{}': {} path traced at {} spp (no baked asset)", args.scene, list(&traced), args.spp);
    }
    for environment in &environments {
        let model = assets.join(format!("{environment}.ngi"));
        if model.is_file() {
            println!(
                "scene '{}': the environment '{environment}' shaded by its GI model, both eyes of a headset in one stereo pass ({})",
                args.scene,
                model.display()
            );
        } else {
            println!("scene '{}': the environment '{environment}' path traced (no GI model)", args.scene);
        }
    }
    println!("composer counters and latency: http://{composer_http}/v1/sessions");
    // With a viewer key, the link to open is an invitation (for a day).
    let invite = viewer_key.map(|key| {
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        format!("&invite={}", key.invite(&args.scene, now + 24 * 3600))
    });
    let invite = invite.unwrap_or_default();
    match &tls {
        Some(tls) => {
            println!("open https://{}/?scene={}{invite}", page_host(args.http), args.scene);
            println!("TLS certificate SHA-256 {} ({})", tls.fingerprint, tls.cert_path.display());
        }
        None => println!("open http://{}/?scene={}{invite}", args.http, args.scene),
    }
    let end = supervisor.watch(&stop)?;
    for (name, restarts) in supervisor.restart_counts() {
        println!("nephele up: {name} was restarted {restarts} time(s)");
    }
    let killed = supervisor.shutdown(Duration::from_secs(10));
    match end {
        WatchEnd::Stopped => {}
        WatchEnd::Exited { name, status } => {
            bail!("{name} exited ({status}); the service cannot go on without it, stopped the others")
        }
        WatchEnd::CrashLoop { name, status, restarts, window } => bail!(
            "{name} keeps crashing (last exit: {status}; restarted {restarts} times within {} s); stopped the service",
            window.as_secs()
        ),
    }
    if !killed.is_empty() {
        bail!("had to kill {} after the grace period", killed.join(", "));
    }
    println!("nephele up: stopped");
    Ok(())
}
