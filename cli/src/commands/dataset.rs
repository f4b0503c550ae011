//! `nephele dataset`: render NeRF-synthetic datasets from built-in scenes, and inspect them.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use glam::{Mat4, Vec3};
use nephele_geometry::camera::Camera;
use nephele_pathtracer::integrator::Aov;
use nephele_pathtracer::sampling::Rng;
use nephele_pathtracer::scenes::{BuiltinScene, Framing};
use nephele_pathtracer::{RenderOptions, Renderer};
use nephele_train::dataset::{self, Frame, Transforms};

use crate::progress::Progress;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Render a train/test dataset of a scene from random views (sphere or upper hemisphere
    /// around an object, random standpoints inside an interior), in the NeRF-synthetic
    /// format: DIR/transforms_{train,test}.json and DIR/{train,test}/r_N.png.
    Render(RenderArgs),
    /// Load a dataset (as training would) and summarise it.
    Info(InfoArgs),
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
    }
}

fn render(args: RenderArgs, progress: &Progress) -> Result<()> {
    anyhow::ensure!(args.views > 0, "--views must be at least 1");
    anyhow::ensure!(args.views + args.test_views <= 100_000, "at most 100000 views in all");
    if args.out.exists() && !args.force && std::fs::read_dir(&args.out).map(|mut d| d.next().is_some()).unwrap_or(false)
    {
        bail!("{} is not empty; pass --force to write into it", args.out.display());
    }
    let builtin = super::load_scene(&args.scene)?;
    let (width, height) = args.size;
    let poses = view_poses(&builtin, args.views + args.test_views, !args.full_sphere, args.seed);
    let fov_x = builtin.dataset_fov_x();
    let options = RenderOptions {
        samples_per_pixel: args.spp,
        max_bounces: args.bounces,
        seed: args.seed,
        background: builtin.default_background(),
    };
    options.validate()?;
    let renderer = Renderer::new(builtin.scene).context("preparing the scene")?;
    let total_rows = (poses.len() as u64) * u64::from(height);
    let bar = progress.bar(total_rows, &format!("{} dataset", args.scene), "rows");
    let splits = [("train", &poses[..args.views]), ("test", &poses[args.views..])];
    for (split, split_poses) in splits {
        if split_poses.is_empty() {
            continue;
        }
        let dir = args.out.join(split);
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let mut frames = Vec::with_capacity(split_poses.len());
        for (i, &camera_to_world) in split_poses.iter().enumerate() {
            let camera = Camera::from_fov_x(width, height, fov_x, camera_to_world).context("view camera")?;
            // Every view gets its own noise: the seed mixes in the view's global index.
            let view_seed = args
                .seed
                .wrapping_mul(0x9E37_79B9)
                .wrapping_add(frames.len() as u64 + if split == "test" { 1 << 32 } else { 0 });
            let out = renderer
                .render(&camera, &RenderOptions { seed: view_seed, ..options }, &|rows| bar.inc(u64::from(rows)))?;
            let name = format!("r_{i}");
            let mut aovs = vec![Aov::Color];
            if args.depth {
                aovs.push(Aov::Depth);
            }
            super::pathtrace::write_outputs(&out, &aovs, false, &dir, "")?;
            // write_outputs names files by output; rename to the dataset's names.
            std::fs::rename(dir.join("color.png"), dir.join(format!("{name}.png")))?;
            let depth_path = if args.depth {
                std::fs::rename(dir.join("depth.exr"), dir.join(format!("{name}_depth.exr")))?;
                Some(format!("./{split}/{name}_depth.exr"))
            } else {
                None
            };
            frames.push(Frame { file_path: format!("./{split}/{name}"), camera_to_world, rotation: None, depth_path });
        }
        let transforms = Transforms { camera_angle_x: fov_x, frames };
        let path = args.out.join(format!("transforms_{split}.json"));
        dataset::write_transforms(&path, &transforms).with_context(|| format!("writing {}", path.display()))?;
    }
    bar.finish_and_clear();
    println!(
        "wrote {} train and {} test views of '{}' at {width}x{height}, {} spp, to {}",
        args.views,
        args.test_views,
        args.scene,
        args.spp,
        args.out.display()
    );
    Ok(())
}

/// Camera-to-world matrices for `count` views of a scene, deterministic by seed.
fn view_poses(builtin: &BuiltinScene, count: usize, allow_hemisphere: bool, seed: u64) -> Vec<Mat4> {
    match builtin.framing {
        Framing::Object { center, orbit_radius, hemisphere, .. } => {
            dataset::sample_views_on_sphere(count, orbit_radius, center, hemisphere && allow_hemisphere, seed)
        }
        Framing::Interior { min, max, look_at, .. } => {
            // Standpoints anywhere in the scene's camera box (already away from the walls),
            // looking roughly at the room's point of interest with some spread so that
            // every wall is seen.
            let mut rng = Rng::new(seed, 0x1_0000);
            (0..count)
                .map(|_| {
                    let r = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
                    let eye = min + (max - min) * r;
                    let spread = Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, 0.3 * (rng.next_f32() - 0.5))
                        * (max - min);
                    let target = look_at + spread;
                    look_at_matrix(eye, if (target - eye).length() < 0.1 { look_at } else { target })
                })
                .collect()
        }
    }
}

/// Camera-to-world for a camera at `eye` looking at `target` with +Z up (OpenGL camera axes).
fn look_at_matrix(eye: Vec3, target: Vec3) -> Mat4 {
    let forward = (target - eye).normalize_or(Vec3::Y);
    let right = forward.cross(Vec3::Z).normalize_or(Vec3::X);
    let up = right.cross(forward);
    Mat4::from_cols(right.extend(0.0), up.extend(0.0), (-forward).extend(0.0), eye.extend(1.0))
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
