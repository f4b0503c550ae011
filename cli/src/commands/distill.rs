//! `nephele distill`: a radiance field (`.ngp`) in, a NeLF (`.nelf`, R2L) out: pseudo-data
//! from the field at random poses, the residual MLP trained on it with a hard-example pool,
//! fine-tuned on the dataset's images; progress bars, a pseudo-data cache and checkpoints
//! that a second run resumes from; the held-out PSNR of the NeLF and of its teacher at the
//! end.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nephele_geometry::camera::Camera;
use nephele_kernels::nelf::{MatterGrid, NelfKernel, NelfModel, RaySampling};
use nephele_kernels::ngp::NgpKernel;
use nephele_train::dataset;
use nephele_train::nelf::{
    DistillCheckpoint, DistillOptions, DistillStep, RaySet, distill, geometry_of, pseudo_data, pseudo_key, real_data,
};
use nephele_train::score::mean_score;

use crate::progress::Progress;

/// Distil a NeLF (R2L) from a radiance field. Defaults are the library's
/// (`DistillOptions::default()`), sized for minutes on a 2-core CPU.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The teacher: a radiance field (`nephele train ngp`, or `nephele bake --save-field`).
    #[arg(long)]
    field: PathBuf,
    /// The dataset the field was trained on: its cameras place the pseudo-views, its images
    /// fine-tune the NeLF, its held-out views score it.
    #[arg(long)]
    dataset: PathBuf,
    /// Output asset (.nelf).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value = "train")]
    split: String,
    /// Downscale the images by this integer factor.
    #[arg(long, default_value_t = 2)]
    downscale: u32,
    /// Leave out every Nth view (as `nephele bake --holdout-every N` did for the field):
    /// they are scored at the end, never trained on; 0 = train on all.
    #[arg(long, default_value_t = 8)]
    holdout_every: usize,
    /// Score at most this many held-out views at the end (0 skips the scoring).
    #[arg(long, default_value_t = 4)]
    eval_views: usize,
    /// Points along each ray (R2L: 16).
    #[arg(long, default_value_t = DistillOptions::default().points)]
    points: usize,
    /// Octaves of each point's positional encoding (R2L: 10).
    #[arg(long, default_value_t = DistillOptions::default().frequencies)]
    frequencies: usize,
    /// Width of the residual MLP (R2L: 256).
    #[arg(long, default_value_t = DistillOptions::default().width)]
    width: usize,
    /// Residual blocks of two layers each (R2L: 44, i.e. 88 layers).
    #[arg(long, default_value_t = DistillOptions::default().blocks)]
    blocks: usize,
    /// Random poses the field renders pseudo-data from.
    #[arg(long, default_value_t = DistillOptions::default().pseudo_views)]
    pseudo_views: u32,
    /// Pseudo rays kept per pose (rays that meet the object).
    #[arg(long, default_value_t = DistillOptions::default().rays_per_view)]
    rays_per_view: u32,
    /// Steps on pseudo-data.
    #[arg(long, default_value_t = DistillOptions::default().steps)]
    steps: u32,
    /// Steps of fine-tuning on the real images after them (half of each batch; 0: none).
    #[arg(long, default_value_t = DistillOptions::default().fine_tune_steps)]
    fine_tune_steps: u32,
    /// Rays per step.
    #[arg(long, default_value_t = DistillOptions::default().batch)]
    batch: usize,
    #[arg(long, default_value_t = DistillOptions::default().learning_rate)]
    learning_rate: f32,
    /// Fraction of each batch replayed from the pool of hard examples (0: no pool).
    #[arg(long, default_value_t = DistillOptions::default().hard_fraction)]
    hard_fraction: f32,
    /// Capacity of the hard-example pool, in rays.
    #[arg(long, default_value_t = DistillOptions::default().hard_pool)]
    hard_pool: usize,
    /// Weight of the depth term of the loss.
    #[arg(long, default_value_t = DistillOptions::default().depth_weight)]
    depth_weight: f32,
    #[arg(long, default_value_t = DistillOptions::default().seed)]
    seed: u64,
    /// Pseudo-data cache (default: OUT with `.rays`), reused by a run with the same field,
    /// poses and seed.
    #[arg(long)]
    pseudo_cache: Option<PathBuf>,
    /// Largest pseudo-data cache written, in MiB (44 bytes a ray); larger sets stay in
    /// memory only.
    #[arg(long, default_value_t = 512)]
    max_cache_mib: u64,
    /// Checkpoint file (default: OUT with `.ckpt`), written every --checkpoint-every steps;
    /// a run with the same settings resumes from it.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    #[arg(long, default_value_t = 500)]
    checkpoint_every: u32,
    /// Start afresh even if a checkpoint exists (it is overwritten).
    #[arg(long)]
    restart: bool,
    /// Network sizes to try, smallest first, as WIDTHxBLOCKS (e.g. 32x2,64x4,128x4); with
    /// --target-psnr the first whose held-out PSNR reaches it is kept, else the last.
    /// Overrides --width and --blocks.
    #[arg(long, value_delimiter = ',', value_parser = parse_network_size)]
    sizes: Vec<(usize, usize)>,
    /// Held-out PSNR (dB) a size must reach to be kept (see --sizes).
    #[arg(long)]
    target_psnr: Option<f64>,
}

/// `WIDTHxBLOCKS`.
fn parse_network_size(text: &str) -> Result<(usize, usize), String> {
    let (w, b) = text.split_once('x').ok_or_else(|| format!("'{text}' is not WIDTHxBLOCKS (e.g. 64x4)"))?;
    let w = w.trim().parse().map_err(|_| format!("'{w}' is not a width"))?;
    let b = b.trim().parse().map_err(|_| format!("'{b}' is not a block count"))?;
    Ok((w, b))
}

impl Args {
    fn options(&self) -> DistillOptions {
        DistillOptions {
            points: self.points,
            frequencies: self.frequencies,
            width: self.width,
            blocks: self.blocks,
            pseudo_views: self.pseudo_views,
            rays_per_view: self.rays_per_view,
            steps: self.steps,
            fine_tune_steps: self.fine_tune_steps,
            batch: self.batch,
            learning_rate: self.learning_rate,
            hard_fraction: self.hard_fraction,
            hard_pool: self.hard_pool,
            depth_weight: self.depth_weight,
            seed: self.seed,
        }
    }
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    let start = Instant::now();
    let options = args.options();
    options.validate()?;
    let teacher =
        NgpKernel::load(&args.field).with_context(|| format!("loading the field {}", args.field.display()))?;
    let (sampling, matter) = geometry_of(&teacher, options.points, options.frequencies)?;
    let mut data = dataset::load_split(&args.dataset, &args.split, args.downscale)
        .with_context(|| format!("loading {}", args.dataset.display()))?;
    let (kept, held) = dataset::split_holdout(std::mem::take(&mut data.views), args.holdout_every);
    if kept.is_empty() {
        bail!("no training view left in {}", args.dataset.display());
    }
    let cameras = kept
        .iter()
        .map(|v| Camera::from_fov_x(v.image.width(), v.image.height(), data.camera_angle_x, v.camera_to_world))
        .collect::<Result<Vec<_>, _>>()?;
    println!(
        "distill: NeLF of {} points x {} octaves ({} inputs per ray); {} training and {} held-out views of {}x{}",
        options.points,
        options.frequencies,
        sampling.input_len(),
        kept.len(),
        held.len(),
        kept[0].image.width(),
        kept[0].image.height()
    );

    // Pseudo-data, from the cache when it was made from the same field, poses and seed.
    let teacher_bytes = std::fs::read(&args.field).with_context(|| format!("reading {}", args.field.display()))?;
    let key = pseudo_key(&teacher_bytes, &cameras, &options);
    let cache = args.pseudo_cache.clone().unwrap_or_else(|| args.out.with_extension("rays"));
    let pseudo_start = Instant::now();
    let pseudo = match RaySet::load(&cache, key)? {
        Some(set) => {
            println!("pseudo-data: {} rays from the cache {}", set.len(), cache.display());
            set
        }
        None => {
            let bar = progress.bar(u64::from(options.pseudo_views), "pseudo-data from the field", "views");
            let set =
                pseudo_data(&teacher, &sampling, &matter, &cameras, &options, &mut |done, _| bar.set_position(done))?;
            bar.finish_and_clear();
            let mib = set.file_bytes() as u64 >> 20;
            if mib <= args.max_cache_mib {
                set.save(&cache, key)?;
            } else {
                println!("pseudo-data of {mib} MiB is over --max-cache-mib {}: not cached", args.max_cache_mib);
            }
            println!(
                "pseudo-data: {} rays rendered by the field from {} poses in {:.0} s",
                set.len(),
                options.pseudo_views,
                pseudo_start.elapsed().as_secs_f64()
            );
            set
        }
    };
    let (real, check) = real_data(&kept, data.camera_angle_x, &sampling, &matter)?;
    check.verdict()?;
    if check.repaired_any() {
        println!("training images: {}", check.summary());
    }
    println!("real rays meeting the object: {}", real.len());

    // Each size in turn (one unless --sizes): the first to reach --target-psnr is kept.
    let sizes = if args.sizes.is_empty() { vec![(options.width, options.blocks)] } else { args.sizes.clone() };
    if args.target_psnr.is_some() && (args.eval_views == 0 || held.is_empty()) {
        bail!("--target-psnr needs held-out views to score (--holdout-every and --eval-views above 0)");
    }
    let eval_views = &held[..held.len().min(args.eval_views)];
    let teacher_score = mean_score(&teacher, eval_views, data.camera_angle_x)?;
    for (i, &(width, blocks)) in sizes.iter().enumerate() {
        let options = DistillOptions { width, blocks, ..options.clone() };
        options.validate()?;
        let several = sizes.len() > 1;
        let checkpoint_path = match (&args.checkpoint, several) {
            (Some(path), false) => path.clone(),
            (Some(path), true) => path.with_extension(format!("w{width}b{blocks}.ckpt")),
            (None, false) => args.out.with_extension("ckpt"),
            (None, true) => args.out.with_extension(format!("w{width}b{blocks}.ckpt")),
        };
        let model = distill_one(&args, &options, [&pseudo, &real], sampling, &matter, &checkpoint_path, progress)?;
        let last = i + 1 == sizes.len();
        let nelf = NelfKernel::new(model);
        let Some((teacher_psnr, teacher_ssim)) = teacher_score else {
            nelf.model().save(&args.out).with_context(|| format!("writing {}", args.out.display()))?;
            println!("wrote {} after {:.0} s", args.out.display(), start.elapsed().as_secs_f64());
            return Ok(());
        };
        let (psnr, ssim) = mean_score(&nelf, eval_views, data.camera_angle_x)?.unwrap_or_default();
        println!(
            "held-out views ({}): NeLF W{width} B{blocks} {psnr:.2} dB PSNR, SSIM {ssim:.4} ({} FLOPs per ray); its teacher {teacher_psnr:.2} dB, SSIM {teacher_ssim:.4}",
            eval_views.len(),
            nelf.model().flops_per_ray()
        );
        let met = args.target_psnr.is_none_or(|t| psnr >= t);
        if met || last {
            if !met {
                println!(
                    "no size reached --target-psnr {:.2} dB; keeping the last (W{width} B{blocks})",
                    args.target_psnr.unwrap_or_default()
                );
            }
            nelf.model().save(&args.out).with_context(|| format!("writing {}", args.out.display()))?;
            println!(
                "wrote {} ({:.2} MiB, W{width} B{blocks}) after {:.0} s",
                args.out.display(),
                nelf.model().model_bytes() as f64 / 1048576.0,
                start.elapsed().as_secs_f64()
            );
            return Ok(());
        }
    }
    Ok(())
}

/// Distils one network size (resuming its checkpoint when there is one).
fn distill_one(
    args: &Args,
    options: &DistillOptions,
    [pseudo, real]: [&RaySet; 2],
    sampling: RaySampling,
    matter: &MatterGrid,
    checkpoint_path: &Path,
    progress: &Progress,
) -> Result<NelfModel> {
    let resume = resume_from(checkpoint_path, args.restart, options)?;
    let total = options.total_steps();
    let name = format!("distilling W{} B{}", options.width, options.blocks);
    let bar = progress.bar(u64::from(total), &name, "steps");
    if let Some(c) = &resume {
        bar.set_position(u64::from(c.state.step));
    }
    let train_start = Instant::now();
    let mut smoothed = None::<f32>;
    let (network, state) = distill(
        [pseudo, real],
        &sampling,
        options,
        resume,
        args.checkpoint_every,
        &mut |s: DistillStep| {
            let loss = smoothed.map_or(s.loss, |l| 0.95 * l + 0.05 * s.loss);
            smoothed = Some(loss);
            bar.set_position(u64::from(s.step));
            let phase = if s.fine_tuning { "fine-tuning" } else { "pseudo-data" };
            bar.set_message(format!("{name} ({phase}), loss {loss:.5}"));
        },
        &mut |c| c.save(checkpoint_path).map_err(Into::into),
    )?;
    bar.finish_and_clear();
    let seconds = train_start.elapsed().as_secs_f64();
    let config = nephele_kernels::nelf::network_config(&sampling, options.width, options.blocks);
    println!(
        "W{} B{} ({} layers, {} parameters, {} FLOPs per ray): {} steps, {:.0} s, {:.0} rays/s",
        options.width,
        options.blocks,
        config.layers(),
        config.num_params(),
        config.flops_per_row(),
        state.step,
        seconds,
        // Rays of this run's steps (all of them when it did not resume).
        f64::from(state.step) * options.batch as f64 / seconds.max(1e-9)
    );
    println!(
        "loss curve (step, mean loss): {:?}",
        state.curve.iter().map(|(s, l)| (*s, (l * 1e5).round() / 1e5)).collect::<Vec<_>>()
    );
    let training = serde_json::json!({
        "teacher": args.field.file_name().map(|n| n.to_string_lossy().into_owned()),
        "options": options,
        "pseudo_rays": pseudo.len(),
        "real_rays": real.len(),
        "seconds": seconds,
        "curve": state.curve,
    });
    Ok(NelfModel::new(network, sampling, matter.clone(), training)?)
}

/// The checkpoint to resume, or `None` (absent, or `--restart`).
fn resume_from(path: &Path, restart: bool, options: &DistillOptions) -> Result<Option<DistillCheckpoint>> {
    if !path.exists() || restart {
        return Ok(None);
    }
    let c = DistillCheckpoint::load(path)?;
    if c.state.options != *options {
        bail!("{} was made with other settings; pass the same settings to resume, or --restart", path.display());
    }
    println!("resuming from {} at step {}", path.display(), c.state.step);
    Ok(Some(c))
}
