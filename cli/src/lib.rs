//! The `nephele` command: one entry point for every tool of the project.
//!
//! The CLI parses arguments and calls the libraries; it may depend on every crate.
//!
//! A library with one entry point, [`main`], so that two binaries run the same command:
//! `nephele` (this package's `src/main.rs`) and the copy the cross-process tests build
//! beside themselves (`tests/src/bin/`), which cargo compiles with the tests' own profile
//! and features instead of a second build of the whole stack.

mod commands;
mod progress;
mod supervise;

use anyhow::Result;
use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// Nephele: a cloud renderer for neural 3D assets.
///
/// `nephele up` runs the whole service on this machine (master, composer, render workers;
/// the default scene's objects baked into i-NOLF assets on first start). The other
/// commands run one service each, bake, train and render assets, make datasets with the
/// reference path tracer, score images, simulate the scheduler and print the benchmarks;
/// see README.md.
#[derive(Debug, Parser)]
#[command(name = "nephele", version, about, long_about, propagate_version = true)]
struct Cli {
    /// Log more (-v: debug, -vv: trace). `NEPHELE_LOG` (tracing filter syntax) overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Hide progress bars (they are hidden anyway when stderr is not a terminal).
    #[arg(short, long, global = true)]
    quiet: bool,
    /// Worker threads for rendering and metrics (default: one per core).
    #[arg(long, global = true, value_name = "N")]
    threads: Option<usize>,
    /// Log lines as text (colour only on a terminal, never with `NO_COLOR`) or as JSON, one
    /// object per line with the fields of each event, for log collectors. `nephele up` passes
    /// it on to its processes.
    #[arg(long, global = true, value_enum, default_value = "text")]
    log_format: LogFormat,
    #[command(subcommand)]
    command: Command,
}

/// How log lines are written (on stderr).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    Text,
    Json,
}

impl std::fmt::Display for LogFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            LogFormat::Text => "text",
            LogFormat::Json => "json",
        })
    }
}

#[derive(Debug, Subcommand)]
enum TrainCommand {
    /// Train an i-NGP-style radiance field on a NeRF-synthetic dataset (CPU), save it (`.ngp`),
    /// and print the test PSNR/SSIM.
    Ngp(commands::train::Args),
    /// Train the single-eye global-illumination U-Net (the stereo model's teacher) on a
    /// dataset of `nephele dataset gi`, with checkpoints it resumes from; save it (`.ngi`).
    Gi(commands::train_gi::Args),
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List the built-in scenes.
    Scenes,
    /// Path-trace one view of a built-in scene or a glTF file (the reference renderer).
    Pathtrace(commands::pathtrace::Args),
    /// Render, inspect or load NeRF-synthetic datasets.
    #[command(subcommand)]
    Dataset(commands::dataset::Command),
    /// Compare predicted images against ground truth: per-image and mean PSNR and SSIM.
    Eval(commands::eval::Args),
    /// Train a model: `ngp` (an i-NGP-style radiance field on a NeRF-synthetic dataset) or
    /// `gi` (the global-illumination U-Net on a `nephele dataset gi` dataset).
    #[command(subcommand)]
    Train(TrainCommand),
    /// Render every pose of a transforms file with a trained asset to PNG (for `nephele eval`).
    Render(commands::render::Args),
    /// Print performance figures (see BENCHMARKS.md).
    #[command(subcommand)]
    Bench(nephele_bench::Command),
    /// Run a composer: depth fusion, H.264 encoding and WebRTC streaming to viewers.
    Composer(commands::composer::Args),
    /// Run a render worker: connect to a master and render the ray batches it sends.
    Worker(commands::worker::Args),
    /// Simulate the farm: the scheduler core (NEPHELE Algorithm 1) against baselines on
    /// simulated workers and users; prints a table and writes CSV.
    Simulate(commands::simulate::Args),
    /// Headless users over WebRTC against a running master: poses every 20 ms, frames parsed,
    /// per-user frame rate and pose-to-frame latency.
    Loadgen(commands::loadgen::Args),
    /// Bake an i-NOLF asset (.nolf) from posed RGBA images: radiance field, density cubes,
    /// perfect spatial hash, trained heads, diffuse cubes.
    Bake(commands::bake::Args),
    /// Distil a NeLF asset (.nelf, R2L) from a radiance field: pseudo-data rendered by the
    /// field at random poses, a deep residual MLP with a hard-example pool, fine-tuned on
    /// the dataset's images; resumable. Workers serve .nelf assets like .nolf.
    Distill(commands::distill::Args),
    /// Run the master: HTTP API and signalling, the live scheduler, the farm listener.
    ///
    /// Workers (`nephele worker --master FARM_ADDR`) and the composer connect to
    /// `--farm-listen`; browsers open `http://HTTP_ADDR/`. The master turns each session's
    /// poses into ray batches (NEPHELE Algorithm 1), re-issues the batches of a worker that
    /// dies or stalls, and tells the composer which results make up each frame; `GET /v1/farm`
    /// shows workers, load, queues and per-user FPS. It prints `listening: http=ADDR
    /// farm=ADDR` once both sockets listen. On SIGTERM or Ctrl-C it stops taking requests,
    /// says goodbye to the workers and the composer, and exits 0.
    Master(commands::master::Args),
    /// Ask a process's `/livez` or `/readyz` once: exit 0 on 2xx, 1 otherwise (the
    /// container images' health check).
    Probe(commands::probe::Args),
    /// Write a fresh secret to a file (owner-readable only): a farm secret (the credential
    /// that the master, the composer and the workers prove to each other when they join) or
    /// a viewer key (what `nephele invite` signs invitations with).
    Secret(commands::secret::Args),
    /// Print an invitation link: a session on one scene (or all) until a given time, signed
    /// with the master's viewer key (`nephele master --viewer-key-file`).
    Invite(commands::invite::Args),
    /// Run the whole service locally: master, composer and render workers as child
    /// processes; prints the URL to open; Ctrl-C stops everything.
    ///
    /// A worker or the composer that dies is started again with backoff and rejoins the
    /// farm (the master re-issues its batches; viewers keep streaming through a worker's
    /// death). The master's death, or a crash loop, stops the service with a message.
    ///
    /// The scene's built-in objects are served as i-NOLF assets: the first start bakes them
    /// (about 7 minutes for the default scene on two cores, with progress bars) into a
    /// cache folder that later starts reuse. `--bake quick` bakes in seconds (blurry),
    /// `--bake off` path traces the objects instead.
    Up(commands::up::Args),
}

/// Parses the command line and runs the command; the whole of a `nephele` binary.
pub fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    init_logging(cli.verbose, cli.log_format);
    match run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    if let Some(threads) = cli.threads {
        anyhow::ensure!(threads > 0, "--threads must be at least 1");
        rayon::ThreadPoolBuilder::new().num_threads(threads).build_global()?;
    }
    let progress = progress::Progress::new(cli.quiet);
    match cli.command {
        Command::Scenes => commands::scenes::list(),
        Command::Pathtrace(args) => commands::pathtrace::run(args, &progress),
        Command::Dataset(cmd) => commands::dataset::run(cmd, &progress),
        Command::Eval(args) => commands::eval::run(args),
        Command::Bench(cmd) => nephele_bench::run(cmd, &progress),
        Command::Composer(args) => commands::composer::run(args),
        Command::Worker(args) => commands::worker::run(args, cli.threads),
        Command::Simulate(args) => commands::simulate::run(args, &progress),
        Command::Loadgen(args) => commands::loadgen::run(args, &progress),
        Command::Bake(args) => commands::bake::run(args, &progress),
        Command::Distill(args) => commands::distill::run(args, &progress),
        Command::Train(TrainCommand::Ngp(args)) => commands::train::run(args, &progress),
        Command::Train(TrainCommand::Gi(args)) => commands::train_gi::run(args, &progress),
        Command::Render(args) => commands::render::run(args, &progress),
        Command::Master(args) => commands::master::run(args),
        Command::Probe(args) => commands::probe::run(args),
        Command::Secret(args) => commands::secret::run(args),
        Command::Invite(args) => commands::invite::run(args),
        Command::Up(args) => commands::up::run(args, &progress, cli.log_format),
    }
}

fn init_logging(verbose: u8, format: LogFormat) {
    let default = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_env("NEPHELE_LOG").unwrap_or_else(|_| EnvFilter::new(default));
    let logs = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    match format {
        // One JSON object per line: timestamp, level, message and the event's fields
        // (flattened), and the spans it happened in.
        LogFormat::Json => logs.json().flatten_event(true).with_current_span(true).init(),
        LogFormat::Text => {
            // Colour only on a terminal, and never with NO_COLOR set (logs piped to files stay plain).
            let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr()) && std::env::var_os("NO_COLOR").is_none();
            logs.with_target(false).with_ansi(ansi).init()
        }
    }
}
