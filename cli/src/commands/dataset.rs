//! `nephele dataset`: render NeRF-synthetic datasets from built-in scenes, and inspect them.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use nephele_pathtracer::scenes::BuiltinScene;
use nephele_train::dataset;
use nephele_train::gi::data::{GiSpec, render_gi_dataset};
use nephele_train::synth::{DatasetSpec, render_dataset};

use crate::progress::Progress;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Render a train/test dataset of a scene from random views (sphere or upper hemisphere
    /// around an object, random standpoints inside an interior), in the NeRF-synthetic
    /// format: DIR/transforms_{train,test}.json and DIR/{train,test}/r_N.png.
    Render(RenderArgs),
    /// Load a dataset (as training would) and summarise it.
    Info(InfoArgs),
    /// Render a dataset for the stereo global-illumination model of the room: per frame the
    /// G-buffer a rasteriser would have (position, normal, albedo, depth), the direct light
    /// (shadow rays) and the path-traced global illumination as the target, as float EXRs
    /// with a gi.json manifest. Single-eye frames train the model; stereo pairs (IPD drawn
    /// from 55-70 mm) are for evaluation only. The floor ball rolls: each frame is a moment
    /// of the animation. Resumes an interrupted run of the same settings.
    Gi(GiArgs),
}

#[derive(Debug, clap::Args)]
pub struct GiArgs {
    /// Lighting: `day` (room-day), `night` (room-night) or `both` (one subfolder each).
    #[arg(long, default_value = "both", value_parser = ["day", "night", "both"])]
    lighting: String,
    /// Single-eye training frames per lighting.
    #[arg(long, default_value_t = 160)]
    single: usize,
    /// Stereo pairs per lighting for evaluation (their path-traced GI is the ground truth).
    #[arg(long, default_value_t = 16)]
    stereo_pairs: usize,
    /// Stereo pairs per lighting for training the stereo student (only their G-buffers are
    /// used: the targets come from the single-eye teacher).
    #[arg(long, default_value_t = 48)]
    train_pairs: usize,
    /// Image size per eye.
    #[arg(long, default_value = "128x128", value_parser = super::parse_size)]
    size: (u32, u32),
    /// Vertical field of view, degrees.
    #[arg(long, default_value_t = 70.0)]
    fov_deg: f32,
    /// Samples per pixel of the path-traced target.
    #[arg(long, default_value_t = 256)]
    spp: u32,
    /// Longest path in bounces.
    #[arg(long, default_value_t = 6)]
    bounces: u32,
    /// Seed of the views, the animation times, the IPDs and the path tracer.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output folder (created; `day/` and `night/` inside it).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// A built-in scene (see `nephele scenes`) or a .gltf/.glb file.
    #[arg(long)]
    scene: String,
    /// Training views.
    #[arg(long, default_value_t = 100)]
    pub(crate) views: usize,
    /// Held-out test views (0 for none).
    #[arg(long, default_value_t = 20)]
    test_views: usize,
    /// Image size.
    #[arg(long, default_value = "400x400", value_parser = super::parse_size)]
    size: (u32, u32),
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    spp: u32,
    /// Samples per pixel of the test views (the reference a bake is scored against); default:
    /// `--spp`.
    #[arg(long)]
    test_spp: Option<u32>,
    /// Longest path in bounces.
    #[arg(long, default_value_t = 8)]
    bounces: u32,
    /// Seed for the views and the path tracer.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Views on the whole sphere even for objects the scene frames on a hemisphere.
    #[arg(long)]
    full_sphere: bool,
    /// Also write view-space depth per view (r_N_depth.exr, 0 where nothing was hit).
    #[arg(long)]
    depth: bool,
    /// Output folder (created; must be empty or absent unless --force).
    #[arg(long)]
    out: PathBuf,
    /// Write into a non-empty output folder, replacing files of the same names.
    #[arg(long)]
    force: bool,
}

#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// Dataset folder (with transforms_*.json).
    dir: PathBuf,
    /// Downscale factor applied while loading (as training would).
    #[arg(long, default_value_t = 1)]
    downscale: u32,
}

pub fn run(command: Command, progress: &Progress) -> Result<()> {
    match command {
        Command::Render(args) => render(args, progress),
        Command::Info(args) => info(args),
        Command::Gi(args) => gi(args, progress),
    }
}

impl RenderArgs {
    pub(crate) fn spec(&self) -> DatasetSpec {
        DatasetSpec {
            views: self.views,
            test_views: self.test_views,
            width: self.size.0,
            height: self.size.1,
            spp: self.spp,
            test_spp: self.test_spp.unwrap_or(0),
            bounces: self.bounces,
            seed: self.seed,
            full_sphere: self.full_sphere,
            depth: self.depth,
        }
    }
}

fn render(args: RenderArgs, progress: &Progress) -> Result<()> {
    let spec = args.spec();
    spec.validate()?;
    if args.out.exists() && !args.force && std::fs::read_dir(&args.out).map(|mut d| d.next().is_some()).unwrap_or(false)
    {
        bail!("{} is not empty; pass --force to write into it", args.out.display());
    }
    let scene = nephele_pathtracer::scenes::load(&args.scene)?;
    render_into(scene, &args.scene, &spec, &args.out, progress)
}

/// Renders `spec` of `scene` into `out` with a progress bar, then says what it wrote.
pub(crate) fn render_into(
    scene: BuiltinScene,
    name: &str,
    spec: &DatasetSpec,
    out: &Path,
    progress: &Progress,
) -> Result<()> {
    let total_rows = (spec.views + spec.test_views) as u64 * u64::from(spec.height);
    let bar = progress.bar(total_rows, &format!("{name} dataset"), "rows");
    render_dataset(scene, spec, out, &|rows| bar.inc(u64::from(rows)))
        .with_context(|| format!("rendering the dataset of '{name}' into {}", out.display()))?;
    bar.finish_and_clear();
    println!(
        "wrote {} train and {} test views of '{name}' at {}x{}, {} spp ({} for the test views), to {}",
        spec.views,
        spec.test_views,
        spec.width,
        spec.height,
        spec.spp,
        if spec.test_spp > 0 { spec.test_spp } else { spec.spp },
        out.display()
    );
    Ok(())
}

fn gi(args: GiArgs, progress: &Progress) -> Result<()> {
    let lightings: &[&str] = match args.lighting.as_str() {
        "day" => &["day"],
        "night" => &["night"],
        _ => &["day", "night"],
    };
    for lighting in lightings {
        let spec = GiSpec {
            scene: format!("room-{lighting}"),
            single: args.single,
            stereo_pairs: args.stereo_pairs,
            train_pairs: args.train_pairs,
            width: args.size.0,
            height: args.size.1,
            fov_y: args.fov_deg.to_radians(),
            spp: args.spp,
            bounces: args.bounces,
            seed: args.seed,
        };
        spec.validate()?;
        let out = args.out.join(lighting);
        let frames = (spec.single + 2 * (spec.stereo_pairs + spec.train_pairs)) as u64;
        let bar = progress.bar(frames * u64::from(spec.height), &format!("GI dataset, {lighting}"), "rows");
        let report = render_gi_dataset(&spec, &out, &|rows| bar.inc(u64::from(rows)))
            .with_context(|| format!("rendering the {lighting} GI dataset into {}", out.display()))?;
        bar.finish_and_clear();
        println!(
            "{lighting}: {} frames rendered, {} already there: {} single-eye frames, {} evaluation and {} training stereo pairs at {}x{}, {} spp, in {}",
            report.rendered,
            report.skipped,
            spec.single,
            spec.stereo_pairs,
            spec.train_pairs,
            spec.width,
            spec.height,
            spec.spp,
            out.display()
        );
    }
    Ok(())
}

fn info(args: InfoArgs) -> Result<()> {
    let splits = dataset::available_splits(&args.dir);
    if splits.is_empty() {
        bail!("{} holds no transforms_*.json", args.dir.display());
    }
    for split in splits {
        let data = dataset::load_split(&args.dir, &split, args.downscale)
            .with_context(|| format!("loading split '{split}' of {}", args.dir.display()))?;
        let (w, h) = data.views.first().map(|v| (v.image.width(), v.image.height())).unwrap_or((0, 0));
        let coverage: f64 = data
            .views
            .iter()
            .map(|v| {
                v.image.pixels().iter().map(|p| f64::from(p[3])).sum::<f64>() / v.image.pixels().len().max(1) as f64
            })
            .sum::<f64>()
            / data.views.len().max(1) as f64;
        let distances: Vec<f32> = data.views.iter().map(|v| v.camera_to_world.w_axis.truncate().length()).collect();
        let (dmin, dmax) = distances.iter().fold((f32::INFINITY, 0.0f32), |(lo, hi), &d| (lo.min(d), hi.max(d)));
        println!(
            "{split:<6} {:>4} views {w}x{h}, camera_angle_x {:.4} rad, mean alpha coverage {:.3}, camera distance {:.2}..{:.2}",
            data.views.len(),
            data.camera_angle_x,
            coverage,
            dmin,
            dmax
        );
    }
    Ok(())
}
