//! `nephele train ngp`: fit an i-NGP-style radiance field to a NeRF-synthetic dataset on the CPU.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nephele_kernels::kernel::RayKernel;
use nephele_kernels::ngp::{FieldConfig, NgpKernel, save_field};
use nephele_nn::HashGridConfig;
use nephele_train::dataset::{self, Dataset};
use nephele_train::ngp::{TrainConfig, Trainer};

use crate::progress::Progress;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// NeRF-synthetic dataset folder (transforms_train.json, optionally transforms_test.json).
    #[arg(long)]
    dataset: PathBuf,
    /// Where to write the trained field (a `.ngp` file for `nephele render`).
    #[arg(long)]
    out: PathBuf,
    /// Optimisation steps (training also stops at --minutes, whichever comes first).
    #[arg(long, default_value_t = 3000)]
    steps: u32,
    /// Wall-clock budget in minutes; the learning-rate schedule follows whichever of steps
    /// and time runs out first.
    #[arg(long)]
    minutes: Option<f64>,
    /// Downscale the images by this integer factor while loading (4: 800x800 -> 200x200).
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// Without a test split, hold out every Nth training view for the final test figure
    /// (0: score on the training views).
    #[arg(long, default_value_t = 8)]
    holdout_every: usize,
    /// Score at most this many test views (0: all).
    #[arg(long, default_value_t = 0)]
    test_views: usize,
    /// Density samples per step (the number of rays per step adapts to it).
    #[arg(long, default_value_t = 1 << 16)]
    samples_per_step: usize,
    /// log2 of the hash table size per level.
    #[arg(long, default_value_t = 19)]
    table_log2: u32,
    /// Hash-grid levels.
    #[arg(long, default_value_t = 16)]
    levels: u32,
    /// Finest hash-grid resolution.
    #[arg(long, default_value_t = 2048)]
    finest: u32,
    /// Ray-marching steps along the box diagonal (i-NGP: 1024; 512 halves the samples per
    /// ray on a CPU budget and is still finer than a pixel at 400x400).
    #[arg(long, default_value_t = 512)]
    steps_per_diagonal: u32,
    /// Occupancy grid cells per side (multiple of 8, 16..=512).
    #[arg(long, default_value_t = 128)]
    occupancy: u32,
    /// Hidden layers of the colour MLP (i-NGP: 2; 1 is about a third cheaper per sample).
    #[arg(long, default_value_t = 2)]
    color_layers: usize,
    /// Adam learning rate (decays tenfold over the second half).
    #[arg(long, default_value_t = 1e-2)]
    learning_rate: f32,
    /// Do not start from the visual hull of the training views (slower).
    #[arg(long)]
    no_carve: bool,
    /// Seed of the initialisation and the ray sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the test renders (PNG) into this folder.
    #[arg(long)]
    renders: Option<PathBuf>,
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    anyhow::ensure!(args.steps > 0, "--steps must be at least 1");
    if let Some(m) = args.minutes {
        anyhow::ensure!(m.is_finite() && m > 0.0, "--minutes must be positive");
    }
    let loaded = Instant::now();
    let train = dataset::load_split(&args.dataset, "train", args.downscale)
        .with_context(|| format!("loading the train split of {}", args.dataset.display()))?;
    let (train, test, test_label) = if dataset::available_splits(&args.dataset).iter().any(|s| s == "test") {
        let test = dataset::load_split(&args.dataset, "test", args.downscale).context("loading the test split")?;
        (train, test, "test split")
    } else if args.holdout_every > 1 {
        let (kept, held) = dataset::split_holdout(train.views, args.holdout_every);
        let angle = train.camera_angle_x;
        (
            Dataset { camera_angle_x: angle, views: kept },
            Dataset { camera_angle_x: angle, views: held },
            "held-out training views",
        )
    } else {
        let test = train.clone();
        (train, test, "training views (no held-out set)")
    };
    if train.views.is_empty() {
        bail!("no training views");
    }
    let (w, h) = (train.views[0].image.width(), train.views[0].image.height());
    println!(
        "{} training views at {w}x{h}, {} {test_label} (loaded in {:.1} s)",
        train.views.len(),
        test.views.len(),
        loaded.elapsed().as_secs_f64()
    );

    let field_config = FieldConfig {
        grid: HashGridConfig::with_finest_resolution(args.levels, args.table_log2, 16, args.finest),
        steps_per_diagonal: args.steps_per_diagonal,
        occupancy_resolution: args.occupancy,
        color_hidden_layers: args.color_layers,
        ..FieldConfig::default()
    };
    let config = TrainConfig {
        seed: args.seed,
        samples_per_step: args.samples_per_step,
        learning_rate: args.learning_rate,
        carve: !args.no_carve,
        ..TrainConfig::default()
    };
    let setup = Instant::now();
    let mut trainer = Trainer::from_dataset(field_config, config, &train).context("preparing training")?;
    let bounds = trainer.field().bounds();
    println!(
        "box {:.3} .. {:.3} (side {:.3}), {} of {} occupancy cells in the visual hull, {} parameters (setup {:.1} s)",
        bounds.min,
        bounds.max,
        bounds.size().x,
        trainer.candidate_cells(),
        trainer.field().occupancy().cell_count(),
        trainer.field().num_params(),
        setup.elapsed().as_secs_f64()
    );

    let budget = args.minutes.map(|m| m * 60.0);
    let bar = progress.bar(u64::from(args.steps), "training", "steps");
    let start = Instant::now();
    let (mut rays, mut samples) = (0u64, 0u64);
    let mut recent = Vec::new();
    let mut last = nephele_train::ngp::StepStats::default();
    let mut phases = [0.0f64; 4];
    for step in 0..args.steps {
        let elapsed = start.elapsed().as_secs_f64();
        if budget.is_some_and(|b| elapsed >= b) {
            break;
        }
        let by_steps = step as f64 / f64::from(args.steps);
        let by_time = budget.map_or(0.0, |b| elapsed / b);
        let stats = trainer.step(by_steps.max(by_time) as f32).context("training step")?;
        rays += stats.rays as u64;
        samples += stats.samples as u64;
        recent.push(stats.loss);
        if recent.len() > 50 {
            recent.remove(0);
        }
        last = stats;
        for (p, s) in
            phases.iter_mut().zip([stats.seconds_rays, stats.seconds_grid, stats.seconds_adam, stats.seconds_occupancy])
        {
            *p += f64::from(s);
        }
        bar.inc(1);
        if step % 10 == 0 {
            let mse = recent.iter().sum::<f32>() / recent.len() as f32;
            bar.set_message(format!(
                "training: loss {mse:.5} ({:.1} dB), {} rays x {:.0} samples, occupancy {:.1}%",
                -10.0 * mse.max(1e-10).log10(),
                stats.rays,
                stats.samples as f32 / stats.rays.max(1) as f32,
                100.0 * stats.occupied_fraction
            ));
        }
    }
    bar.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    let steps = trainer.steps();
    let mse = recent.iter().sum::<f32>() / recent.len().max(1) as f32;
    println!(
        "trained {steps} steps in {seconds:.1} s on {} threads: {:.2} steps/s, {:.0} rays/s, {:.0} samples/s ({:.1} samples per ray); final loss {mse:.5}, occupancy {:.2}%",
        rayon::current_num_threads(),
        steps as f64 / seconds,
        rays as f64 / seconds,
        samples as f64 / seconds,
        samples as f64 / rays.max(1) as f64,
        100.0 * last.occupied_fraction
    );
    let phase_total = phases.iter().sum::<f64>().max(1e-9);
    println!(
        "time per phase: rays forward+backward {:.0}%, hash-grid scatter {:.0}%, Adam {:.0}%, occupancy {:.0}%",
        100.0 * phases[0] / phase_total,
        100.0 * phases[1] / phase_total,
        100.0 * phases[2] / phase_total,
        100.0 * phases[3] / phase_total
    );
    save_field(trainer.field(), &args.out).with_context(|| format!("writing {}", args.out.display()))?;
    let bytes = std::fs::metadata(&args.out).map(|m| m.len()).unwrap_or(0);
    println!("wrote {} ({:.1} MB)", args.out.display(), bytes as f64 / 1e6);

    // The test figure.
    let kernel = NgpKernel::new(trainer.into_field());
    let count = if args.test_views == 0 { test.views.len() } else { args.test_views.min(test.views.len()) };
    if count == 0 {
        return Ok(());
    }
    if let Some(dir) = &args.renders {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let bar = progress.bar(count as u64, "scoring", "views");
    let (mut psnr_sum, mut ssim_sum) = (0.0, 0.0);
    let (mut render_rays, mut render_samples, mut render_seconds) = (0u64, 0u64, 0.0);
    for v in &test.views[..count] {
        let score = nephele_train::score::score_view(&kernel, v, test.camera_angle_x)?;
        render_seconds += score.seconds;
        render_rays += score.stats.rays;
        render_samples += score.stats.queries;
        psnr_sum += score.psnr;
        ssim_sum += score.ssim;
        if let Some(dir) = &args.renders {
            let path = dir.join(format!("{}.png", v.name));
            score.image.save_png(&path).with_context(|| format!("writing {}", path.display()))?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    println!(
        "test ({count} {test_label}, white background): PSNR {:.2} dB, SSIM {:.4}; rendering {:.0} rays/s, {:.1} samples per ray",
        psnr_sum / count as f64,
        ssim_sum / count as f64,
        render_rays as f64 / render_seconds.max(1e-9),
        render_samples as f64 / render_rays.max(1) as f64
    );
    tracing::debug!(kind = kernel.kind(), "scored");
    Ok(())
}
