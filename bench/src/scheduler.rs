//! `nephele bench scheduler`: the cost of one scheduling round of the core.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, ensure};
use glam::Vec3;
use nephele_geometry::Bounds;
use nephele_geometry::camera::{Camera, quilt_rig};
use nephele_scheduler::{
    Action, ObjectId, ObjectInfo, Policy, Scheduler, SchedulerConfig, SessionSpec, Time, WorkerId,
};

use crate::Progress;

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
/// shared), releases them with no worker present (the "release" column: the TaskAssigner for
/// every task), then adds the farm and times rounds in a saturated steady state, as the live
/// loop runs them: before each round (untimed) two workers report their batches done, and the
/// round refills them: sort the users, find the starved ones, place about one batch per freed
/// worker. Time advances 100 us per round, so users pass their target times and starve
/// during the run; no new frame is released (one frame in flight per user).
fn measure(policy: Policy, users: usize, pending: usize, workers: u32, rounds: usize) -> Result<Measurement> {
    let per_user = (pending / users).max(1);
    let objects_per_user = per_user.min(25);
    let views = (per_user / objects_per_user).max(1);
    let mut config = SchedulerConfig::for_policy(policy);
    config.max_views = config.max_views.max(views);
    config.heartbeat_timeout = None;
    config.max_frames_in_flight = 1;
    config.min_batch_timeout = Duration::from_secs(3600);
    // Each worker is freed every `workers / 2` rounds of 100 us; with a matching horizon and
    // throughput a freed worker takes about one batch, so the queue stays near `pending`.
    let refill = Duration::from_micros(100 * u64::from(workers.max(2) / 2));
    config.horizon = refill;
    // Completions here are bunched (a worker's batches all return at once), which would teach
    // the throughput estimate nonsense; keep it at the declared rate.
    config.smoothing = 1e-9;
    let mut s = Scheduler::new(config)?;
    for i in 0..objects_per_user {
        let a = i as f32 * 0.9;
        let center = Vec3::new(0.6 * a.cos(), 0.6 * a.sin(), 0.1 * (i % 5) as f32);
        let bounds = Bounds { min: center - Vec3::splat(0.08), max: center + Vec3::splat(0.08) };
        s.register_object(
            ObjectId(i as u32),
            ObjectInfo { bounds, occupancy: None, cost_per_ray: 1.0, full_frame: false },
        )?;
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
    let rays_per_task = s.stats().rays_created as f64 / tasks.max(1) as f64;
    for w in 0..workers {
        s.add_worker(WorkerId(w), rays_per_task / refill.as_secs_f64(), Time::ZERO)?;
    }
    let mut held: Vec<Vec<nephele_scheduler::BatchId>> = vec![Vec::new(); workers as usize];
    let record = |actions: Vec<Action>, held: &mut Vec<Vec<nephele_scheduler::BatchId>>| {
        let mut n = 0;
        for a in actions {
            if let Action::Dispatch { worker, batch } = a {
                n += 1;
                held[worker.0 as usize].push(batch.id);
            }
        }
        n
    };
    let mut now = Time::ZERO + Duration::from_micros(100);
    record(s.tick(now), &mut held); // fill the farm
    let mut round_us = Vec::with_capacity(rounds);
    let mut dispatches = 0;
    let mut pending_sum = 0.0;
    for r in 0..rounds {
        now = now + Duration::from_micros(100);
        for w in [r % workers as usize, (r + 1) % workers as usize] {
            for b in std::mem::take(&mut held[w]) {
                s.batch_done(WorkerId(w as u32), b, now).context("completing a batch")?;
            }
        }
        pending_sum += s.live_tasks() as f64;
        let start = Instant::now();
        let actions = s.tick(now);
        round_us.push(start.elapsed().as_secs_f64() * 1e6);
        dispatches += record(actions, &mut held);
    }
    Ok(Measurement { release_ms, tasks, round_us, dispatches, pending_mean: pending_sum / rounds as f64 })
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len().max(1));
    sorted.get(rank - 1).copied().unwrap_or(0.0)
}

pub fn run(args: SchedulerArgs, progress: &dyn Progress) -> Result<()> {
    ensure!(
        args.rounds > 0 && args.workers > 0 && args.pending > 0,
        "--rounds, --workers and --pending must be positive"
    );
    ensure!(args.users.iter().all(|&u| u > 0 && u <= args.pending), "--users must lie in 1..=--pending");
    let policies: Vec<Policy> =
        args.policy.iter().map(|p| p.parse::<Policy>().map_err(anyhow::Error::msg)).collect::<Result<_>>()?;
    ensure!(!policies.is_empty(), "--policy needs at least one policy");
    println!(
        "scheduler round cost: {} pending tasks spread over the users, {} workers, {} rounds each, one thread",
        args.pending, args.workers, args.rounds
    );
    println!(
        "(release: one tick running the TaskAssigner for every task; p50 is the robust figure, mean and p99 include preemption)"
    );
    println!(
        "{:<8} {:>6} {:>7} {:>10} {:>11} {:>10} {:>10} {:>10} {:>11} {:>8}",
        "policy",
        "users",
        "tasks",
        "release ms",
        "pending avg",
        "p50 us",
        "mean us",
        "p99 us",
        "dispatch/rd",
        "p50 ratio"
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
            let p50 = percentile(&sorted, 0.5);
            let ratio = p50 / *reference.get_or_insert(p50);
            bar.suspend(|| {
                println!(
                    "{:<8} {:>6} {:>7} {:>10.2} {:>11.0} {:>10.1} {:>10.1} {:>10.1} {:>11.1} {:>8.2}",
                    policy.name(),
                    users,
                    m.tasks,
                    m.release_ms,
                    m.pending_mean,
                    p50,
                    mean,
                    percentile(&sorted, 0.99),
                    per_round,
                    ratio
                );
            });
        }
    }
    bar.finish_and_clear();
    Ok(())
}
