//! `nephele loadgen`: headless users over WebRTC against a running master.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use nephele_loadgen::{Live, LoadConfig};

use crate::progress::Progress;

/// Opens N sessions as the browser client does and streams for a while: each user posts a
/// WebRTC offer to the master (retrying while it answers 503 + Retry-After), sends a pose
/// every 20 ms from a camera orbiting the scene and a ping every second, and parses the
/// H.264 it receives (frames by RTP marker bit, keyframes by IDR slice, losses by sequence
/// number). A user whose stream is lost (a composer restart) connects again after 1 s,
/// doubling to 10 s, as the browser does. Prints per user: frame rate, frames, keyframes,
/// damaged frames, lost packets, reconnections, bitrate, time to connect, ping round trip,
/// and pose-to-frame latency (client time from a pose to the composer's `frame` note naming
/// it; `-` when the composer sends none). Ctrl-C or SIGTERM ends the run early with the same
/// reports.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The master, as a browser opens it.
    #[arg(long, default_value = "http://127.0.0.1:8080/")]
    url: String,
    /// Simulated users.
    #[arg(long, default_value_t = 1)]
    users: usize,
    /// Seconds each user streams once connected.
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Size of each user's view (of each eye's with --stereo).
    #[arg(long, default_value = "640x480", value_parser = super::parse_size)]
    size: (u32, u32),
    /// Stereo users, as a WebXR headset: two views per pose (left and right eye, this many
    /// metres apart, 0.064 when given without a value), streamed side by side.
    #[arg(long, value_name = "IPD_M", num_args = 0..=1, default_missing_value = "0.064")]
    stereo: Option<f32>,
    /// Light-field users, as the page's quilt display: 45 views per pose (Looking Glass's
    /// quilt, 5 columns x 9 rows, a 40-degree view cone focused on the orbit's target), each
    /// of --size (the page's: 180x240), packed into one picture.
    #[arg(long, conflicts_with = "stereo")]
    quilt: bool,
    #[arg(long, default_value = "default")]
    scene: String,
    /// Frame rate each user asks for.
    #[arg(long, default_value_t = 30.0)]
    fps: f32,
    /// Milliseconds between poses.
    #[arg(long, default_value_t = 20)]
    pose_ms: u64,
    /// Orbit speed of the scripted camera, radians per second.
    #[arg(long, default_value_t = 0.5)]
    orbit_speed: f32,
    /// Milliseconds between two users' starts.
    #[arg(long, default_value_t = 100)]
    stagger_ms: u64,
    /// How many times a user retries a session the farm refuses as busy (503 or 429, after
    /// the Retry-After it is given) before it gives up.
    #[arg(long, default_value_t = LoadConfig::default().max_busy_retries)]
    busy_retries: u32,
    /// Write the per-user reports as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// For an https:// master: trust the certificates of this PEM file (and only them), e.g.
    /// the self-signed one of `nephele master --tls-self-signed` (its path is printed at
    /// start). Default: $NEPHELE_TLS_CA, else the public web roots.
    #[arg(long, value_name = "PEM")]
    tls_ca: Option<PathBuf>,
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    if !(args.seconds > 0.0 && args.seconds <= 86_400.0) {
        bail!("--seconds must be in (0, 86400], got {}", args.seconds);
    }
    if let Some(file) = &args.tls_ca {
        nephele_loadgen::http::trust_certificates(file)?;
    }
    let (width, height) = args.size;
    let config = LoadConfig {
        url: args.url,
        users: args.users,
        duration: Duration::from_secs_f64(args.seconds),
        scene: args.scene,
        width: u16::try_from(width).context("--size width")?,
        height: u16::try_from(height).context("--size height")?,
        display: match (args.stereo, args.quilt) {
            (Some(ipd), _) => nephele_loadgen::pose::UserDisplay::Stereo { ipd },
            (None, true) => nephele_loadgen::pose::UserDisplay::Quilt,
            (None, false) => nephele_loadgen::pose::UserDisplay::Flat,
        },
        target_fps: args.fps,
        pose_interval: Duration::from_millis(args.pose_ms),
        orbit_speed: args.orbit_speed,
        stagger: Duration::from_millis(args.stagger_ms),
        max_busy_retries: args.busy_retries,
        ..LoadConfig::default()
    };
    config.validate()?;
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    // Ctrl-C or SIGTERM ends the run early: every user stops and the reports are printed (and
    // written) as usual.
    let stop = nephele_shutdown::Shutdown::on_signals().context("installing the Ctrl-C and SIGTERM handlers")?;
    let live = Arc::new(Live { stop, ..Live::default() });
    let total_ms = (args.seconds * 1e3) as u64 + args.stagger_ms * args.users as u64;
    let bar = progress.bar(total_ms / 1000, "streaming", "s");
    let reports = runtime.block_on(async {
        let work = nephele_loadgen::run(&config, Arc::clone(&live));
        tokio::pin!(work);
        let start = tokio::time::Instant::now();
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        loop {
            tokio::select! {
                reports = &mut work => break reports,
                _ = tick.tick() => {
                    bar.set_position(start.elapsed().as_secs().min(total_ms / 1000));
                    bar.set_message(format!(
                        "{} connected, {} frames, {} poses",
                        live.connected.load(Ordering::Relaxed),
                        live.frames.load(Ordering::Relaxed),
                        live.poses.load(Ordering::Relaxed)
                    ));
                }
            }
        }
    })?;
    bar.finish_and_clear();
    print!("{}", nephele_loadgen::table(&reports));
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&reports)?;
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    let failed = reports.iter().filter(|r| r.error.is_some()).count();
    if failed == reports.len() {
        bail!(
            "no user could stream (first error: {})",
            reports.iter().find_map(|r| r.error.clone()).unwrap_or_default()
        );
    }
    Ok(())
}
