//! `nephele bake`: posed RGBA images in, an i-NOLF asset (`.nolf`) out. The arguments
//! become a [`BakeRecipe`]; the bake itself is the library's [`nephele_train::inolf::pipeline::bake`]
//! (radiance field, density cubes, perfect spatial hash, heads, diffuse cubes).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;
use nephele_kernels::inolf::cubes::HitRule;
use nephele_kernels::inolf::kernel::InolfKernel;
use nephele_kernels::inolf::model::LossSpace;
use nephele_kernels::ngp::{RadianceField, load_field, save_field};
use nephele_train::dataset::{self, Dataset};
use nephele_train::inolf::pipeline::{BakeProgress, BakeRecipe, bake};
use nephele_train::score::{MARCH_STRIDE_BUDGET_DB, choose_march_stride, march_stride_scores};

use crate::progress::Progress;

/// Bake an i-NOLF asset from a NeRF-synthetic dataset. The bake's defaults are the
/// library's (`BakeRecipe::default()`), not a second copy.
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
    #[arg(long, default_value_t = BakeRecipe::default().field_steps)]
    field_steps: u32,
    /// log2 of the radiance field's hash-table entries per level (i-NGP: 19).
    #[arg(long, default_value_t = BakeRecipe::default().field_table_log2)]
    field_table_log2: u32,
    /// Hash-grid levels of the radiance field.
    #[arg(long, default_value_t = BakeRecipe::default().field_levels)]
    field_levels: u32,
    /// Finest hash-grid resolution of the radiance field.
    #[arg(long, default_value_t = BakeRecipe::default().field_finest)]
    field_finest: u32,
    /// Density samples per training step of the radiance field.
    #[arg(long, default_value_t = BakeRecipe::default().field_samples)]
    field_samples: usize,
    /// Training steps of the i-NOLF heads.
    #[arg(long, default_value_t = BakeRecipe::default().head_steps)]
    steps: u32,
    /// Rays per step of the heads.
    #[arg(long, default_value_t = BakeRecipe::default().batch)]
    batch: usize,
    /// Coarse cells of the density cubes along the longest side.
    #[arg(long, default_value_t = BakeRecipe::default().cubes)]
    cubes: u32,
    /// Samples per cube side (density and diffuse cubes).
    #[arg(long, default_value_t = BakeRecipe::default().cube_res)]
    cube_res: u32,
    /// Probes per cell side when finding the cells that hold matter (cube-res - 1 probes
    /// every sample point: no thin matter between probes is missed).
    #[arg(long, default_value_t = BakeRecipe::default().cube_probe)]
    cube_probe: u32,
    /// Side of the PSH lattice over the object's box (NEPHELE: 128, 256 or 512).
    #[arg(long, default_value_t = BakeRecipe::default().psh_res)]
    psh_res: u32,
    /// Learned features per PSH slot.
    #[arg(long, default_value_t = BakeRecipe::default().psh_features)]
    psh_features: u32,
    /// log2 of the hash-table entries per level of the heads' diffuse grid (the colour the
    /// diffuse cubes are baked from); larger tables collide less on detailed objects.
    #[arg(long, default_value_t = BakeRecipe::default().head_table_log2)]
    head_table_log2: u32,
    /// Densities below this (per unit length) are cut to zero before caching: the floor of
    /// what counts as matter.
    #[arg(long, default_value_t = BakeRecipe::default().density_threshold)]
    density_threshold: f32,
    /// Also keep the diffuse network in the asset (for the "+ diffuse MLP" variant).
    #[arg(long)]
    keep_diffuse_network: bool,
    /// Voxels between the density march's samples that the asset is served with (recorded in
    /// it; `nephele worker --march-stride` still overrides): 1 (every voxel) to 4, or auto:
    /// score held-out views (those of `--holdout-every`, else at most 8 of the dataset's test
    /// split) at strides 1 to 4 and keep the coarsest within 0.1 dB of every voxel's PSNR.
    #[arg(long, default_value = "1", value_name = "1-4|auto")]
    march_stride: MarchStrideArg,
    /// Views the radiance field renders at new poses on the sphere of the training cameras,
    /// added to the heads' training views (R2L's pseudo-data: the heads see the object
    /// between the dataset's views; on the lego, 70 gain 0.08 dB on held-out views for about a
    /// minute of rendering, and let 8000 head steps gain 0.16 dB more where without them the
    /// heads over-fit). 0 trains the heads on the dataset alone.
    #[arg(long, default_value_t = BakeRecipe::default().pseudo_views)]
    pseudo_views: u32,
    /// Decoupled weight decay (AdamW) of the heads' PSH features: each step shrinks every
    /// feature by learning rate x this, pulling features that few training rays see towards
    /// zero (a regulariser for views the bake did not train on). 0: off.
    #[arg(long, default_value_t = BakeRecipe::default().psh_decay)]
    psh_decay: f32,
    /// The same for the heads' diffuse hash grid (baked into the diffuse cubes). 0: off.
    #[arg(long, default_value_t = BakeRecipe::default().grid_decay)]
    grid_decay: f32,
    /// Where the heads' colour loss compares a pixel with its target: srgb (the encoding the
    /// views are stored, shown and scored in, so dark pixels weigh as the eye and PSNR weigh
    /// them) or linear (NEPHELE eq. 8 on linear RGB).
    #[arg(long, default_value = "srgb", value_name = "srgb|linear")]
    head_loss: LossSpace,
    /// Which point of the density march stands for a ray's hit point (where the heads'
    /// features are read; recorded in the asset): median-depth (where the ray's opacity
    /// crosses one half, solved inside the sample: the same surface point from every view),
    /// largest-weight (NEPHELE's eq. 4: the centre of the sample of largest weight),
    /// see-through (the layer where the ray's opacity reaches 0.9 when that lies 16 voxels or
    /// more behind the largest weight: what a glass object holds, not the glass that flickers
    /// in front of it), or auto: see-through when most training rays meet such a layer,
    /// median-depth otherwise.
    #[arg(long, default_value = "auto", value_name = "auto|median-depth|largest-weight|see-through")]
    hit_rule: HitRuleArg,
    /// Where a ray's diffuse colour is read: blended over the density march's samples of
    /// largest weight (true, `--blend-samples` of them: where a pixel straddles an edge, the
    /// colour mixes both sides as the radiance field's does; about 1.5x the heads' training
    /// time) or at the hit point alone (false, NEPHELE's eq. 5).
    #[arg(long, default_value_t = BakeRecipe::default().diffuse_blend, action = clap::ArgAction::Set, value_name = "true|false")]
    diffuse_blend: bool,
    /// How many of the march's samples of largest weight the blended diffuse colour mixes, 1
    /// to 8 (recorded in the asset). On the lego 8 put i-NOLF 0.09 dB below its field where 4
    /// left it 0.35 dB below, for the same training time and about 1.25x the kernel's frame
    /// (up to 8 diffuse-cube reads a hit ray instead of 4).
    #[arg(long, default_value_t = BakeRecipe::default().blend_samples, value_parser = clap::value_parser!(u32).range(1..=8))]
    blend_samples: u32,
    #[arg(long, default_value_t = BakeRecipe::default().seed)]
    seed: u64,
}

/// `nephele bake --hit-rule`: `None` is auto.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HitRuleArg(Option<HitRule>);

impl std::str::FromStr for HitRuleArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "auto" => Ok(HitRuleArg(None)),
            "largest-weight" => Ok(HitRuleArg(Some(HitRule::LargestWeight))),
            "see-through" => Ok(HitRuleArg(Some(HitRule::SEE_THROUGH))),
            "median-depth" => Ok(HitRuleArg(Some(HitRule::MedianDepth))),
            _ => Err(format!("'{s}' is not a hit rule (auto, median-depth, largest-weight or see-through)")),
        }
    }
}

impl Args {
    fn recipe(&self) -> BakeRecipe {
        BakeRecipe {
            field_steps: self.field_steps,
            field_table_log2: self.field_table_log2,
            field_levels: self.field_levels,
            field_finest: self.field_finest,
            field_samples: self.field_samples,
            head_steps: self.steps,
            batch: self.batch,
            cubes: self.cubes,
            cube_res: self.cube_res,
            cube_probe: self.cube_probe,
            psh_res: self.psh_res,
            psh_features: self.psh_features,
            head_table_log2: self.head_table_log2,
            density_threshold: self.density_threshold,
            keep_diffuse_network: self.keep_diffuse_network,
            pseudo_views: self.pseudo_views,
            psh_decay: self.psh_decay,
            grid_decay: self.grid_decay,
            head_loss: self.head_loss,
            diffuse_blend: self.diffuse_blend,
            blend_samples: self.blend_samples,
            hit_rule: self.hit_rule.0,
            seed: self.seed,
        }
    }
}

/// The bake's stages as progress bars, their summaries printed; a trained field saved as
/// soon as it exists when asked.
pub(crate) struct Bars<'a> {
    progress: &'a Progress,
    bar: Option<ProgressBar>,
    stage: String,
    save_field: Option<PathBuf>,
    save_error: Option<anyhow::Error>,
}

impl<'a> Bars<'a> {
    pub(crate) fn new(progress: &'a Progress) -> Self {
        Bars { progress, bar: None, stage: String::new(), save_field: None, save_error: None }
    }
}

impl BakeProgress for Bars<'_> {
    fn stage(&mut self, name: &str, total: u64, unit: &str) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
        self.stage = name.to_string();
        self.bar = Some(self.progress.bar(total, name, unit));
    }

    fn advance(&mut self, done: u64, total: u64, status: &str) {
        if let Some(bar) = &self.bar {
            bar.set_length(total);
            bar.set_position(done);
            bar.set_message(format!("{} ({status})", self.stage));
        }
    }

    fn finished(&mut self, summary: String) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
        println!("{summary}");
    }

    fn field_trained(&mut self, field: &RadianceField) {
        if let Some(path) = &self.save_field {
            let saved = save_field(field, path).with_context(|| format!("saving {}", path.display()));
            self.save_error = saved.err();
        }
    }
}

fn evenly(n: usize, keep: usize) -> Vec<usize> {
    if keep == 0 || keep >= n { (0..n).collect() } else { (0..keep).map(|i| i * n / keep).collect() }
}

/// Loads `split` of the dataset at `dir` as the bake trains on it: downscaled, every
/// `holdout_every`th view held out, at most `max_views` evenly spaced views.
pub(crate) fn training_data(
    dir: &Path,
    split: &str,
    downscale: u32,
    holdout_every: usize,
    max_views: usize,
) -> Result<Dataset> {
    let mut data = dataset::load_split(dir, split, downscale)
        .with_context(|| format!("loading the {split} split of {}", dir.display()))?;
    let (kept, held) = dataset::split_holdout(std::mem::take(&mut data.views), holdout_every);
    if !held.is_empty() {
        println!("bake: {} views held out (every {}th)", held.len(), holdout_every);
    }
    data.views = kept;
    let keep = evenly(data.views.len(), max_views);
    data.views = keep.iter().map(|&i| data.views[i].clone()).collect();
    if data.views.is_empty() {
        bail!("the dataset has no views");
    }
    Ok(data)
}

/// `nephele bake --march-stride`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MarchStrideArg {
    Fixed(u32),
    Auto,
}

impl std::str::FromStr for MarchStrideArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let max = nephele_kernels::inolf::cubes::MAX_MARCH_STRIDE;
        match s.trim() {
            "auto" => Ok(MarchStrideArg::Auto),
            n => match n.parse::<u32>() {
                Ok(n) if (1..=max).contains(&n) => Ok(MarchStrideArg::Fixed(n)),
                _ => Err(format!("'{s}' is not a march stride (1 to {max}, or auto)")),
            },
        }
    }
}

/// The views `--march-stride auto` judges by: the split's held-out views, else the dataset's
/// test split (at most 8, evenly spaced).
fn stride_views(args: &Args) -> Result<Dataset> {
    let mut data = if args.holdout_every > 1 {
        let mut all = dataset::load_split(&args.dataset, &args.split, args.downscale)?;
        all.views = dataset::split_holdout(std::mem::take(&mut all.views), args.holdout_every).1;
        all
    } else {
        dataset::load_split(&args.dataset, "test", args.downscale).with_context(|| {
            format!(
                "--march-stride auto needs held-out views: --holdout-every N, or a test split in {}",
                args.dataset.display()
            )
        })?
    };
    let keep = evenly(data.views.len(), 8);
    data.views = keep.iter().map(|&i| data.views[i].clone()).collect();
    anyhow::ensure!(!data.views.is_empty(), "--march-stride auto found no held-out views");
    Ok(data)
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    let start = Instant::now();
    let data = training_data(&args.dataset, &args.split, args.downscale, args.holdout_every, args.max_views)?;
    // Before the bake's minutes: `auto` without held-out views is an error at once.
    let stride_choice = match args.march_stride {
        MarchStrideArg::Auto => Err(stride_views(&args)?),
        MarchStrideArg::Fixed(n) => Ok(n),
    };
    let (w, h) = (data.views[0].image.width(), data.views[0].image.height());
    println!("bake: {} views of {w}x{h} from {}", data.views.len(), args.dataset.display());
    let field = match &args.field {
        Some(path) => Some(load_field(path).with_context(|| format!("loading {}", path.display()))?),
        None => None,
    };
    let mut bars = Bars { save_field: args.save_field.clone(), ..Bars::new(progress) };
    let baked = bake(&data, &args.dataset.display().to_string(), &args.recipe(), field, &mut bars);
    if let Some(e) = &bars.save_error {
        // The bake goes on without the saved field; the failure is reported at the end.
        tracing::warn!("{e:#}");
    }
    let mut asset = baked?.asset;
    // `Ok`: the stride asked; `Err`: the held-out views that judge the strides.
    let stride = match stride_choice {
        Ok(n) => n,
        Err(held) => {
            let kernel = InolfKernel::from_asset(asset.clone())?;
            let scores = march_stride_scores(&kernel, &held.views, held.camera_angle_x)?;
            let stride = choose_march_stride(&scores, MARCH_STRIDE_BUDGET_DB);
            println!(
                "march stride {stride}: PSNR on {} held-out views at strides 1-{}: {} dB",
                held.views.len(),
                scores.len(),
                scores.iter().map(|p| format!("{p:.3}")).collect::<Vec<_>>().join(" / ")
            );
            stride
        }
    };
    nephele_kernels::inolf::heads::set_asset_march_stride(&mut asset, stride)?;
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
    match bars.save_error {
        Some(e) => Err(e.context("the asset was written, but not the radiance field")),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn march_strides_parse_or_fail_clearly() {
        assert_eq!("auto".parse(), Ok(MarchStrideArg::Auto));
        assert_eq!("see-through".parse(), Ok(HitRuleArg(Some(HitRule::SEE_THROUGH))));
        assert_eq!(" largest-weight".parse(), Ok(HitRuleArg(Some(HitRule::LargestWeight))));
        assert_eq!("auto".parse(), Ok(HitRuleArg(None)));
        assert_eq!("median-depth ".parse(), Ok(HitRuleArg(Some(HitRule::MedianDepth))));
        assert_eq!("srgb".parse(), Ok(LossSpace::Srgb));
        assert_eq!(" linear".parse(), Ok(LossSpace::Linear));
        assert!("rgb".parse::<LossSpace>().is_err());
        assert!("max".parse::<HitRuleArg>().expect_err("max").contains("not a hit rule"));
        assert_eq!(" 3".parse(), Ok(MarchStrideArg::Fixed(3)));
        for bad in ["0", "5", "-1", "two", ""] {
            let err = bad.parse::<MarchStrideArg>().expect_err(bad);
            assert!(err.contains("1 to 4, or auto"), "{err}");
        }
    }
}
