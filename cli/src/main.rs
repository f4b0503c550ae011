//! The `nephele` command: one entry point for every tool of the project.

mod commands;
mod progress;

use anyhow::Result;
use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// Nephele: a cloud renderer for neural 3D assets.
///
/// Today this command holds the ground truth of the project: a multi-threaded path tracer
/// over built-in scenes and glTF files, the NeRF-synthetic dataset tools and the image
/// metrics. The render farm (master, workers, composer) and the neural kernels land later;
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
    #[command(subcommand)]
    command: Command,
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
    /// Print performance figures (see BENCHMARKS.md).
    #[command(subcommand)]
    Bench(commands::bench::Command),
    /// Run a composer: depth fusion, H.264 encoding and WebRTC streaming to viewers.
    Composer(commands::composer::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    init_logging(cli.verbose);
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
        Command::Bench(cmd) => commands::bench::run(cmd, &progress),
        Command::Composer(args) => commands::composer::run(args),
    }
}

fn init_logging(verbose: u8) {
    let default = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_env("NEPHELE_LOG").unwrap_or_else(|_| EnvFilter::new(default));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_target(false).init();
}
