//! `nephele bench scheduler`: the cost of one scheduling round of the core.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, ensure};
use glam::Vec3;
use nephele_render::camera::{Camera, quilt_rig};
use nephele_render::kernel::Bounds;
use nephele_scheduler::{Action, ObjectId, ObjectInfo, Policy, Scheduler, SchedulerConfig, SessionSpec, Time, WorkerId};

use crate::progress::Progress;

#[derive(Debug, clap::Args)]
pub struct SchedulerArgs {
    /// Numbers of users to measure at, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "10,100,1000")]
    users: Vec<usize>,
    /// Pending tasks at the start of the measured rounds (spread evenly over the users).
    #[arg(long, default_value_t = 10_000)]
    pending: usize,
    /// Workers in the farm.
    #[arg(long, default_value_t = 16)]
    workers: u32,
    /// Measured rounds per configuration.
    #[arg(long, default_value_t = 200)]
    rounds: usize,
    /// Policies to measure, comma-separated (the first is the reference of the ratio column).
    #[arg(long, value_delimiter = ',', default_value = "nephele,fifo")]
    policy: Vec<String>,
}

struct Measurement {
    release_ms: f64,
    tasks: u64,
    round_us: Vec<f64>,
    dispatches: usize,
    pending_mean: f64,
}

/// Builds `users` sessions holding `pending` tasks in total (distinct cameras, so nothing is
/// shared), releases them with no worker present, then adds the farm and times rounds. Between
/// rounds (untimed) every batch dispatched in the round completes, so each round refills the
/// farm: sort the users, find the starved ones, place a batch per free worker.
fn measure(policy: Policy, users: usize, pending: usize, workers: u32, rounds: usize) -> Result<Measurement> {
    let per_user = (pending / users).max(1);
    let objects_per_user = per_user.min(25);
    let views = (per_user / objects_per_user).max(1);
    let mut config = SchedulerConfig::for_policy(policy);
    config.max_views = config.max_views.max(views);
    config.heartbeat_timeout = None;
    let mut s = Scheduler::new(config)?;
    for i in 0..objects_per_user {
        let a = i as f32 * 0.9;
        let center = Vec3::new(0.6 * a.cos(), 0.6 * a.sin(), 0.1 * (i % 5) as f32);
        let bounds = Bounds { min: center - Vec3::splat(0.08), max: center + Vec3::splat(0.08) };
        s.register_object(ObjectId(i as u32), ObjectInfo { bounds, occupancy: None, cost_per_ray: 1.0 })?;
    }
    let objects: Vec<ObjectId> = (0..objects_per_user as u32).map(ObjectId).collect();
    for u in 0..users {
        let id = s.open_session(SessionSpec { target_fps: 30.0, objects: objects.clone() }, Time::ZERO)?;
        let a = (u as f32 * 0.37).to_radians();
        let eye = Vec3::new(10.0 * a.cos(), 10.0 * a.sin(), 1.0);
        let centre = Camera::look_at(96, 96, 0.5, eye, Vec3::ZERO, Vec3::Z)?;
        let cameras = if views == 1 { vec![centre] } else { quilt_rig(&centre, views, 0.3, 10.0)? };
        s.pose(id, &cameras, Time::ZERO)?;
    }
    let start = Instant::now();
    s.tick(Time::ZERO);
    let release_ms = start.elapsed().as_secs_f64() * 1e3;
    let tasks = s.stats().tasks_created;
    for w in 0..workers {
        // About one batch per worker per round: a task is ~100-400 rays, the horizon 4 ms.
        s.add_worker(WorkerId(w), 5e4, Time::ZERO)?;
    }
    let mut now = Time::ZERO;
    let mut round_us = Vec::with_capacity(rounds);
    let mut dispatches = 0;
    let mut pending_sum = 0.0;
    let mut in_flight: Vec<(WorkerId, nephele_scheduler::BatchId)> = Vec::new();
    for _ in 0..rounds {
        now = now + Duration::from_micros(500);
        for (w, b) in in_flight.drain(..) {
            s.batch_done(w, b, now).context("completing a batch")?;
        }
        pending_sum += s.live_tasks() as f64;
        let start = Instant::now();
        let actions = s.tick(now);
        round_us.push(start.elapsed().as_secs_f64() * 1e6);
        for a in actions {
            if let Action::Dispatch { worker, batch } = a {
                dispatches += 1;
                in_flight.push((worker, batch.id));
            }
        }
    }
    Ok(Measurement { release_ms, tasks, round_us, dispatches, pending_mean: pending_sum / rounds as f64 })
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len().max(1));
    sorted.get(rank - 1).copied().unwrap_or(0.0)
}

pub fn run(args: SchedulerArgs, progress: &Progress) -> Result<()> {
    ensure!(args.rounds > 0 && args.workers > 0 && args.pending > 0, "--rounds, --workers and --pending must be positive");
    ensure!(args.users.iter().all(|&u| u > 0 && u <= args.pending), "--users must lie in 1..=--pending");
    let policies: Vec<Policy> = args.policy.iter().map(|p| p.parse::<Policy>().map_err(anyhow::Error::msg)).collect::<Result<_>>()?;
    ensure!(!policies.is_empty(), "--policy needs at least one policy");
    println!(
        "scheduler round cost: {} pending tasks spread over the users, {} workers, {} rounds each, one thread",
        args.pending, args.workers, args.rounds
    );
    println!(
        "{:<8} {:>6} {:>7} {:>10} {:>11} {:>10} {:>10} {:>10} {:>11} {:>12} {:>8}",
        "policy", "users", "tasks", "release ms", "pending avg", "round us", "p50 us", "p99 us", "dispatch/rd", "us/dispatch", "ratio"
    );
    let bar = progress.bar((args.users.len() * policies.len()) as u64, "measuring", "runs");
    for &users in &args.users {
        let mut reference: Option<f64> = None;
        for &policy in &policies {
            let m = measure(policy, users, args.pending, args.workers, args.rounds)?;
            bar.inc(1);
            let mut sorted = m.round_us.clone();
            sorted.sort_by(f64::total_cmp);
            let mean = sorted.iter().sum::<f64>() / sorted.len() as f64;
            let per_round = m.dispatches as f64 / args.rounds as f64;
            let ratio = mean / *reference.get_or_insert(mean);
            bar.suspend(|| {
                println!(
                    "{:<8} {:>6} {:>7} {:>10.2} {:>11.0} {:>10.1} {:>10.1} {:>10.1} {:>11.1} {:>12.2} {:>8.2}",
                    policy.name(),
                    users,
                    m.tasks,
                    m.release_ms,
                    m.pending_mean,
                    mean,
                    percentile(&sorted, 0.5),
                    percentile(&sorted, 0.99),
                    per_round,
                    if m.dispatches > 0 { sorted.iter().sum::<f64>() / m.dispatches as f64 } else { 0.0 },
                    ratio
                );
            });
        }
    }
    bar.finish_and_clear();
    Ok(())
}
