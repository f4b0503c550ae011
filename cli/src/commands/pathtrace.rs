//! `nephele pathtrace`: one view of a scene through the reference path tracer.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_pathtracer::integrator::Aov;
use nephele_pathtracer::{Background, RenderOptions, RenderOutput, Renderer};

use crate::progress::Progress;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// A built-in scene (see `nephele scenes`) or a .gltf/.glb file.
    #[arg(long, default_value = "assembly")]
    scene: String,
    /// Image size.
    #[arg(long, default_value = "640x480", value_parser = super::parse_size)]
    size: (u32, u32),
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    spp: u32,
    /// Longest path in bounces.
    #[arg(long, default_value_t = 8)]
    bounces: u32,
    /// Random seed; the same seed gives the same image.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Camera position x,y,z (world space, +Z up). Default: the scene's own view.
    #[arg(long, value_parser = super::parse_vec3, allow_hyphen_values = true)]
    eye: Option<Vec3>,
    /// Point the camera looks at.
    #[arg(long, value_parser = super::parse_vec3, allow_hyphen_values = true)]
    target: Option<Vec3>,
    /// Vertical field of view in degrees.
    #[arg(long)]
    fov_y: Option<f32>,
    /// What misses show: 'transparent' (alpha 0) or 'environment'. Default: transparent for
    /// objects, environment for interiors.
    #[arg(long)]
    background: Option<BackgroundArg>,
    /// Outputs to write, comma separated: color, direct, alpha, depth, position, normal, albedo.
    #[arg(long, default_value = "color", value_delimiter = ',')]
    aov: Vec<String>,
    /// Also write linear, premultiplied OpenEXR files of the colour outputs.
    #[arg(long)]
    exr: bool,
    /// Output folder (created if needed).
    #[arg(long, default_value = "out/pathtrace")]
    out: PathBuf,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum BackgroundArg {
    Transparent,
    Environment,
}

impl From<BackgroundArg> for Background {
    fn from(b: BackgroundArg) -> Self {
        match b {
            BackgroundArg::Transparent => Background::Transparent,
            BackgroundArg::Environment => Background::Environment,
        }
    }
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    let aovs = parse_aovs(&args.aov)?;
    let builtin = nephele_pathtracer::scenes::load(&args.scene)?;
    let (default_eye, default_target, default_fov) = builtin.default_view();
    let fov_y = match args.fov_y {
        Some(deg) if deg.is_finite() && deg > 0.0 && deg < 180.0 => deg.to_radians(),
        Some(deg) => bail!("--fov-y must lie in (0, 180) degrees, got {deg}"),
        None => default_fov,
    };
    let (width, height) = args.size;
    let camera = Camera::look_at(
        width,
        height,
        fov_y,
        args.eye.unwrap_or(default_eye),
        args.target.unwrap_or(default_target),
        Vec3::Z,
    )
    .context("building the camera")?;
    let background = args.background.map(Background::from).unwrap_or_else(|| builtin.default_background());
    let options = RenderOptions {
        samples_per_pixel: args.spp,
        max_bounces: args.bounces,
        seed: args.seed,
        background,
        direct_only: false,
    };
    options.validate()?;
    let renderer = Renderer::new(builtin.scene).context("preparing the scene")?;
    tracing::info!(scene = %args.scene, width, height, spp = args.spp, "path tracing");
    let bar = progress.bar(u64::from(height), &format!("{} {width}x{height} @ {} spp", args.scene, args.spp), "rows");
    let started = std::time::Instant::now();
    let output = renderer.render(&camera, &options, &|rows| bar.inc(u64::from(rows)))?;
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let written = write_outputs(&output, &aovs, args.exr, &args.out, "")?;
    let stats = output.stats;
    println!(
        "{} samples in {:.2} s ({:.0} samples/s, {:.1} triangle tests per ray); wrote {}",
        stats.samples,
        seconds,
        stats.samples as f64 / seconds,
        stats.traversal.triangle_tests as f64 / stats.traversal.rays.max(1) as f64,
        written.join(", ")
    );
    if stats.dropped_non_finite > 0 {
        tracing::warn!(dropped = stats.dropped_non_finite, "samples with a non-finite value were dropped");
    }
    Ok(())
}

pub fn parse_aovs(names: &[String]) -> Result<Vec<Aov>> {
    names
        .iter()
        .map(|n| {
            Aov::from_name(n.trim()).with_context(|| {
                let valid: Vec<&str> = Aov::ALL.iter().map(|a| a.name()).collect();
                format!("unknown output '{n}'; choose from {}", valid.join(", "))
            })
        })
        .collect()
}

/// Writes each requested output as `{prefix}{name}.png` (colours, albedo) or `.exr`
/// (geometry); returns the file names written.
pub fn write_outputs(output: &RenderOutput, aovs: &[Aov], exr: bool, dir: &Path, prefix: &str) -> Result<Vec<String>> {
    let mut written = Vec::new();
    for &aov in aovs {
        match aov {
            Aov::Color | Aov::Direct => {
                let name = format!("{prefix}{}.png", aov.name());
                output.to_rgba(aov).save_png(dir.join(&name))?;
                written.push(name);
                if exr {
                    let name = format!("{prefix}{}.exr", aov.name());
                    output.to_float(aov).save_exr(dir.join(&name))?;
                    written.push(name);
                }
            }
            Aov::Alpha | Aov::Depth | Aov::Position | Aov::Normal | Aov::Albedo => {
                let name = format!("{prefix}{}.exr", aov.name());
                output.to_float(aov).save_exr(dir.join(&name))?;
                written.push(name);
            }
        }
    }
    Ok(written)
}
