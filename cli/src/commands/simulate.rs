//! `nephele simulate`: the scheduler core against simulated workers and users.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nephele_sim::csv::{TRACE_FORMAT, WORKERS_FORMAT};
use nephele_sim::{Scenario, SimParams, Summary, Variant, report, scenarios};

use crate::progress::Progress;

/// The two CSV formats, shown under `--help`.
pub fn formats_help() -> String {
    format!(
        "Scenarios: {}.\n\nTRACE FORMAT (--trace FILE), one user session per line:\n{TRACE_FORMAT}\n\nFARM FORMAT (--workers FILE), one worker per line:\n{WORKERS_FORMAT}\n\nMETRICS: attain% = on-time frames (release to composed within 1/FPS) over the frames the user wanted (time admitted x FPS), mean and min over admitted users; p50/p99 frame latency; util% = worker busy time over connected time; req/rend Mray = rays the frames asked for / rays workers rendered (saved% = sharing and history savings, minus re-issued work); ray/px = rays rendered per pixel shown to the users (below 1 where the object leaves pixels empty or users share rays); err px = largest reprojection error a shared or reused result was accepted with; reiss = batches re-issued after a loss, failure or missed deadline; jain = Jain's fairness index over achieved/target FPS.",
        scenarios::names().join(", ")
    )
}

#[derive(Debug, clap::Args)]
#[command(after_long_help = formats_help())]
pub struct Args {
    /// Built-in scenarios to run, comma-separated, or `all` (see --list).
    #[arg(long, value_delimiter = ',', default_value = "all")]
    scenario: Vec<String>,
    /// Replay user sessions from a CSV file (format under --help) instead of a built-in scenario.
    #[arg(long, value_name = "FILE")]
    trace: Option<PathBuf>,
    /// The farm from a CSV file (format under --help); replaces the scenario's workers
    /// (default with --trace: 8 workers of 1e8 rays/s).
    #[arg(long, value_name = "FILE")]
    workers: Option<PathBuf>,
    /// Policies to compare, comma-separated: nephele, round-robin, fifo, object-per-worker,
    /// nephele-noshare (NEPHELE with sharing, derived views and history off). Default: all five.
    #[arg(long, value_delimiter = ',')]
    policy: Vec<String>,
    /// Seed of the simulated randomness (worker jitter).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Simulated seconds (default: the scenario's own; with --trace, the last departure).
    #[arg(long)]
    duration: Option<f64>,
    /// Write the table as CSV.
    #[arg(long, value_name = "FILE")]
    csv: Option<PathBuf>,
    /// Write per-user results as CSV.
    #[arg(long, value_name = "FILE")]
    users_csv: Option<PathBuf>,
    /// List the built-in scenarios and exit.
    #[arg(long)]
    list: bool,
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    if args.list {
        for (name, description) in scenarios::SCENARIOS {
            println!("{name:<13} {description}");
        }
        return Ok(());
    }
    if let Some(d) = args.duration.filter(|d| !(d.is_finite() && *d > 0.0 && *d <= 3600.0)) {
        bail!("--duration must be a number of seconds in (0, 3600], got {d}");
    }
    let variants: Vec<Variant> = if args.policy.is_empty() {
        Variant::defaults()
    } else {
        args.policy.iter().map(|p| Variant::parse(p).map_err(anyhow::Error::msg)).collect::<Result<_>>()?
    };
    let farm = match &args.workers {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            Some(nephele_sim::csv::parse_workers(&text, &path.display().to_string())?)
        }
        None => None,
    };
    let mut list: Vec<Scenario> = Vec::new();
    if let Some(path) = &args.trace {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let file = path.display().to_string();
        let (objects, users) = nephele_sim::csv::parse_trace(&text, &file)?;
        let last = users.iter().map(|u| u.depart_s).fold(0.0, f64::max);
        let params = SimParams { seed: args.seed, duration_s: args.duration.unwrap_or(last), ..SimParams::default() };
        let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("trace").to_string();
        let workers = farm
            .clone()
            .unwrap_or_else(|| (1..=8).map(|i| nephele_sim::SimWorker::new(&format!("w{i}"), 1e8)).collect());
        list.push(Scenario { name, description: format!("replay of {file}"), objects, users, workers, params });
    } else {
        let names: Vec<String> = if args.scenario.iter().any(|s| s == "all") {
            scenarios::names().into_iter().map(str::to_string).collect()
        } else {
            args.scenario.clone()
        };
        for name in &names {
            let mut scenario = scenarios::builtin(name, args.seed).with_context(|| {
                format!("unknown scenario '{name}' (one of: {}, all)", scenarios::names().join(", "))
            })?;
            if let Some(d) = args.duration {
                scenario.params.duration_s = d;
                for u in &mut scenario.users {
                    u.depart_s = u.depart_s.max(d);
                }
            }
            if let Some(workers) = &farm {
                scenario.workers = workers.clone();
            }
            list.push(scenario);
        }
    }
    let bar = progress.bar((list.len() * variants.len()) as u64, "simulating", "runs");
    let mut rows: Vec<Summary> = Vec::new();
    let mut user_rows = String::from(
        "scenario,policy,user,admitted,refusals,target_fps,active_s,frames_completed,frames_on_time,frames_dropped,achieved_fps,attainment,latency_p50_ms\n",
    );
    let mut timings = Vec::new();
    for scenario in &list {
        for variant in &variants {
            let start = Instant::now();
            let result = nephele_sim::run(scenario, variant)
                .with_context(|| format!("simulating {} under {}", scenario.name, variant.label))?;
            timings.push((
                scenario.name.clone(),
                variant.label.clone(),
                scenario.params.duration_s,
                start.elapsed().as_secs_f64(),
            ));
            for u in &result.users {
                user_rows.push_str(&format!(
                    "{},{},{},{},{},{},{:.3},{},{},{},{:.3},{:.4},{:.3}\n",
                    scenario.name,
                    variant.label,
                    u.user,
                    u.admitted,
                    u.refusals,
                    u.target_fps,
                    u.active_s,
                    u.frames_completed,
                    u.frames_on_time,
                    u.frames_dropped,
                    u.achieved_fps,
                    u.attainment,
                    u.latency_p50_ms
                ));
            }
            rows.push(result.summary);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    println!("seed {}", args.seed);
    for s in &list {
        println!(
            "{}: {} ({} s, {} users, {} workers)",
            s.name,
            s.description,
            s.params.duration_s,
            s.users.len(),
            s.workers.len()
        );
    }
    println!();
    print!("{}", report::table(&rows));
    let total: f64 = timings.iter().map(|t| t.3).sum();
    let slowest = timings.iter().max_by(|a, b| (a.3 / a.2).total_cmp(&(b.3 / b.2)));
    if let Some((scenario, policy, simulated, wall)) = slowest {
        println!(
            "\n{} runs in {:.2} s of wall time; slowest per simulated second: {scenario} under {policy}, {:.0} ms for {simulated} s",
            timings.len(),
            total,
            wall * 1e3
        );
    }
    if let Some(path) = &args.csv {
        std::fs::write(path, report::csv(&rows)).with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.users_csv {
        std::fs::write(path, user_rows).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
