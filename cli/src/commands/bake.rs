//! `nephele bake`: posed RGBA images in, an i-NOLF asset (`.nolf`) out.
//!
//! 1. the i-NGP-style radiance field of the scene (trained here, or loaded with `--field`);
//! 2. its density cached as density texture cubes;
//! 3. the hit points of every training ray -> the perfect spatial hash;
//! 4. the i-NOLF heads trained on the same images (error-map ray sampling);
//! 5. the diffuse branch baked into diffuse texture cubes; everything written to one file.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nephele_geometry::Bounds;
use nephele_kernels::inolf::cubes::{CubeOptions, DensityCubes};
use nephele_kernels::inolf::encoding::PshEncoding;
use nephele_kernels::inolf::model::{HeadsShape, InolfModel};
use nephele_kernels::inolf::psh::PshOptions;
use nephele_kernels::ngp::{FieldConfig, RadianceField, load_field, save_field};
use nephele_nn::HashGridConfig;
use nephele_train::dataset;
use nephele_train::inolf::bake::{bake_diffuse_cubes, field_density_for_cubes, to_asset};
use nephele_train::inolf::train::{TrainOptions, collect_hit_points, train, training_views};
use nephele_train::ngp::{TrainConfig, Trainer};
use serde_json::json;

use crate::progress::Progress;

/// Bake an i-NOLF asset from a NeRF-synthetic dataset.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Dataset folder (NeRF-synthetic layout: transforms_train.json and images).
    #[arg(long)]
    dataset: PathBuf,
    /// Output asset file (.nolf).
    #[arg(long)]
    out: PathBuf,
    /// Split to train on.
    #[arg(long, default_value = "train")]
    split: String,
    /// Downscale the images by this integer factor (2 turns 800x800 into 400x400).
    #[arg(long, default_value_t = 2)]
    downscale: u32,
    /// Use at most this many views (evenly spaced); 0 = all.
    #[arg(long, default_value_t = 0)]
    max_views: usize,
    /// Leave out every Nth view of the split (score them with `nephele bench inolf
    /// --holdout-every N`); 0 = train on all.
    #[arg(long, default_value_t = 0)]
    holdout_every: usize,
    /// Use a trained radiance field instead of training one.
    #[arg(long)]
    field: Option<PathBuf>,
    /// Save the radiance field trained here (reuse it with --field).
    #[arg(long)]
    save_field: Option<PathBuf>,
    /// Training steps of the radiance field.
    #[arg(long, default_value_t = 2000)]
    field_steps: u32,
    /// log2 of the radiance field's hash-table entries per level (i-NGP: 19).
    #[arg(long, default_value_t = 19)]
    field_table_log2: u32,
    /// Hash-grid levels of the radiance field.
    #[arg(long, default_value_t = 16)]
    field_levels: u32,
    /// Finest hash-grid resolution of the radiance field.
    #[arg(long, default_value_t = 2048)]
    field_finest: u32,
    /// Density samples per training step of the radiance field.
    #[arg(long, default_value_t = 1 << 16)]
    field_samples: usize,
    /// Training steps of the i-NOLF heads.
    #[arg(long, default_value_t = 3000)]
    pub(crate) steps: u32,
    /// Rays per step of the heads.
    #[arg(long, default_value_t = 4096)]
    batch: usize,
    /// Coarse cells of the density cubes along the longest side.
    #[arg(long, default_value_t = 64)]
    cubes: u32,
    /// Samples per cube side (density and diffuse cubes).
    #[arg(long, default_value_t = 8)]
    cube_res: u32,
    /// Side of the PSH lattice over the object's box (NEPHELE: 128, 256 or 512).
    #[arg(long, default_value_t = 256)]
    pub(crate) psh_res: u32,
    /// Learned features per PSH slot.
    #[arg(long, default_value_t = 8)]
    psh_features: u32,
    /// Densities below this (per unit length) are cut to zero before caching: the floor of
    /// what counts as matter.
    #[arg(long, default_value_t = 1.0)]
    density_threshold: f32,
    /// Also keep the diffuse network in the asset (for the "+ diffuse MLP" variant).
    #[arg(long)]
    keep_diffuse_network: bool,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

fn evenly(n: usize, keep: usize) -> Vec<usize> {
    if keep == 0 || keep >= n { (0..n).collect() } else { (0..keep).map(|i| i * n / keep).collect() }
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    let start = Instant::now();
    let mut data = dataset::load_split(&args.dataset, &args.split, args.downscale)
        .with_context(|| format!("loading the {} split of {}", args.split, args.dataset.display()))?;
    let (kept, held) = dataset::split_holdout(std::mem::take(&mut data.views), args.holdout_every);
    if !held.is_empty() {
        println!("bake: {} views held out (every {}th)", held.len(), args.holdout_every);
    }
    data.views = kept;
    let keep = evenly(data.views.len(), args.max_views);
    data.views = keep.iter().map(|&i| data.views[i].clone()).collect();
    if data.views.is_empty() {
        bail!("the dataset has no views");
    }
    let (w, h) = (data.views[0].image.width(), data.views[0].image.height());
    println!("bake: {} views of {w}x{h} from {}", data.views.len(), args.dataset.display());

    // 1. Radiance field.
    let t = Instant::now();
    let field: RadianceField = match &args.field {
        Some(path) => load_field(path).with_context(|| format!("loading {}", path.display()))?,
        None => {
            let config =
                TrainConfig { seed: args.seed, samples_per_step: args.field_samples, ..TrainConfig::default() };
            let field_config = FieldConfig {
                grid: HashGridConfig::with_finest_resolution(
                    args.field_levels,
                    args.field_table_log2,
                    16,
                    args.field_finest,
                ),
                ..FieldConfig::default()
            };
            let mut trainer = Trainer::from_dataset(field_config, config, &data)?;
            let bar = progress.bar(u64::from(args.field_steps), "radiance field", "steps");
            let mut last = 0.0;
            for step in 0..args.field_steps {
                let stats = trainer.step(step as f32 / args.field_steps.max(1) as f32)?;
                last = stats.loss;
                bar.inc(1);
                if step % 50 == 0 {
                    bar.set_message(format!("radiance field (loss {:.5})", stats.loss));
                }
            }
            bar.finish_and_clear();
            println!(
                "radiance field: {} steps, last loss {last:.5}, {:.0} s",
                args.field_steps,
                t.elapsed().as_secs_f64()
            );
            let field = trainer.into_field();
            if let Some(path) = &args.save_field {
                save_field(&field, path).with_context(|| format!("saving {}", path.display()))?;
            }
            field
        }
    };
    let fb = field.bounds();
    let bounds = match field.occupancy().occupied_bounds() {
        Some((lo, hi)) => {
            let size = fb.size();
            let margin = size * (2.0 / field.occupancy().resolution() as f32);
            Bounds { min: (fb.min + lo * size - margin).max(fb.min), max: (fb.min + hi * size + margin).min(fb.max) }
        }
        None => fb,
    };

    // 2. Density cubes.
    let t = Instant::now();
    let cube_options = CubeOptions { resolution: args.cubes, cube_res: args.cube_res, ..CubeOptions::default() };
    let bar = progress.bar(1, "density cubes", "cells");
    let density = field_density_for_cubes(&field, args.density_threshold);
    let cubes = DensityCubes::build(bounds, &cube_options, density, &|p| {
        bar.set_length(p.total);
        bar.set_position(p.done);
        bar.set_message(format!("density cubes ({})", p.phase));
    })?;
    bar.finish_and_clear();
    let fp = cubes.cubes().footprint();
    println!(
        "density cubes: {} of {} cells occupied ({:.2} %), {:.2} MiB against {:.2} MiB for a dense grid of the same resolution, {:.0} s",
        fp.occupied_cells,
        fp.cells,
        100.0 * fp.occupied_cells as f64 / fp.cells as f64,
        fp.bytes as f64 / 1048576.0,
        fp.dense_bytes as f64 / 1048576.0,
        t.elapsed().as_secs_f64()
    );

    // 3. Hit points and the perfect spatial hash.
    let t = Instant::now();
    let views = training_views(&data)?;
    let hits = collect_hit_points(&cubes, &views, 1);
    let cb = cubes.bounds();
    let voxel = cb.size().max_element() / (args.psh_res - 1).max(1) as f32;
    let psh = PshEncoding::from_points(&hits, cb.min, voxel, args.psh_res, args.psh_features, &PshOptions::coherent())?;
    let (coherent, pairs) = psh.table.coherence();
    println!(
        "perfect spatial hash: {} hit points -> {} lattice points at {}^3, table {}^3 slots, offsets {}^3, coherence {:.3}, {:.1} s",
        hits.len(),
        psh.table.len(),
        args.psh_res,
        psh.table.table_side(),
        psh.table.offset_side(),
        coherent as f64 / pairs.max(1) as f64,
        t.elapsed().as_secs_f64()
    );

    // 4. Heads.
    let t = Instant::now();
    let mut model = InolfModel::new(HeadsShape::default(), cb, psh, args.seed)?;
    let options = TrainOptions { steps: args.steps, batch: args.batch, seed: args.seed, ..TrainOptions::default() };
    let bar = progress.bar(u64::from(args.steps), "i-NOLF heads", "steps");
    let report = train(&mut model, &cubes, &views, &options, &mut |step, loss| {
        bar.set_position(u64::from(step));
        if step % 50 == 0 {
            bar.set_message(format!("i-NOLF heads (loss {loss:.5})"));
        }
    })?;
    bar.finish_and_clear();
    let psnr_train = -10.0 * (f64::from(report.smoothed_loss) / 4.0).log10();
    println!(
        "heads: {} steps, loss {:.6} (~{psnr_train:.1} dB on linear premultiplied RGBA of training rays), {:.0} % of drawn rays hit, {:.0} s",
        report.steps,
        report.smoothed_loss,
        100.0 * report.rays_hit as f64 / report.rays.max(1) as f64,
        t.elapsed().as_secs_f64()
    );

    // 5. Diffuse cubes and the asset.
    let t = Instant::now();
    let diffuse = bake_diffuse_cubes(&model, &cubes, &hits, 1, args.cube_res)?;
    let dfp = diffuse.footprint();
    println!(
        "diffuse cubes: {} cells around the hit surfaces, {:.2} MiB against {:.2} MiB dense, {:.1} s",
        dfp.occupied_cells,
        dfp.bytes as f64 / 1048576.0,
        dfp.dense_bytes as f64 / 1048576.0,
        t.elapsed().as_secs_f64()
    );
    let bake = json!({
        "dataset": args.dataset.display().to_string(), "views": data.views.len(), "size": [w, h],
        "field_steps": if args.field.is_some() { 0 } else { args.field_steps }, "steps": args.steps,
        "loss": report.smoothed_loss, "cubes": args.cubes, "cube_res": args.cube_res, "psh_res": args.psh_res,
    });
    let asset = to_asset(&model, cubes, Some(diffuse), args.keep_diffuse_network, bake)?;
    asset.save(&args.out).with_context(|| format!("writing {}", args.out.display()))?;
    let sizes = asset.sizes();
    println!("asset {}:", args.out.display());
    for (part, bytes) in &sizes.parts {
        println!("  {part:<14} {:>10.3} MiB", *bytes as f64 / 1048576.0);
    }
    println!(
        "  {:<14} {:>10.3} MiB (file {} bytes); total bake time {:.0} s",
        "total",
        sizes.total as f64 / 1048576.0,
        std::fs::metadata(&args.out)?.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
