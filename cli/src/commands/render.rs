//! `nephele render`: render every pose of a NeRF-synthetic transforms file with a trained
//! asset, to RGBA PNG files named like the dataset's, so that `nephele eval` can score them.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use nephele_geometry::camera::Camera;
use nephele_imaging::image::RgbaImage;
use nephele_kernels::kernel::{RayKernel, all_pixels, frame_to_image};
use nephele_train::dataset;

use crate::progress::Progress;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// A trained asset: a radiance field from `nephele train ngp` or an i-NOLF asset from
    /// `nephele bake` (the format is recognised by the file's first bytes).
    #[arg(long)]
    asset: PathBuf,
    /// A NeRF-synthetic transforms file (e.g. DATASET/transforms_test.json).
    #[arg(long)]
    transforms: PathBuf,
    /// Output folder (created); one PNG per pose, named after the pose's image.
    #[arg(long)]
    out: PathBuf,
    /// Image size; default: the size of the first pose's image next to the transforms file
    /// (divided by --downscale), or 800x800 if it cannot be read.
    #[arg(long, value_parser = super::parse_size)]
    size: Option<(u32, u32)>,
    /// Divide the default size by this factor (as `nephele train ngp --downscale`).
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// Render only the first N poses.
    #[arg(long)]
    limit: Option<usize>,
    /// Instruction set of the neural kernels: auto (AVX2+FMA where the CPU has them) or off
    /// (scalar code, for comparison).
    #[arg(long, default_value = "auto", value_name = "auto|off")]
    simd: nephele_nn::SimdMode,
    /// Where the neural kernel runs: auto (a hardware GPU if there is one, else the CPU),
    /// cpu, or gpu (a hardware GPU, else a software Vulkan adapter).
    #[arg(long, default_value = "auto", value_name = "auto|cpu|gpu")]
    device: nephele_gpu::DeviceChoice,
    /// Voxels between the i-NOLF density march's samples: 1 marches every voxel (the asset's
    /// own accuracy); 2 about halves the samples of objects whose rays cross thick
    /// semi-transparent matter (the glass shell: 0.08 dB against the path tracer,
    /// BENCHMARKS.md). Default: the stride each asset's bake chose within its error budget on
    /// held-out views (the first start's objects, or `nephele bake --march-stride`; every
    /// voxel otherwise). The GPU kernel marches at the same stride.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=i64::from(nephele_kernels::inolf::cubes::MAX_MARCH_STRIDE)))]
    march_stride: Option<u32>,
}

/// Opens an asset, choosing the kernel by the file's magic bytes (the kernels' registry),
/// on the device `device` asks for.
pub fn load_kernel(
    path: &Path,
    simd: nephele_nn::SimdMode,
    device: nephele_gpu::DeviceChoice,
    march_stride: Option<u32>,
) -> Result<std::sync::Arc<dyn RayKernel>> {
    let (accelerator, _) = super::open_device(device, simd)?;
    let options = nephele_kernels::assets::LoadOptions { simd, accelerator, march_stride, ..Default::default() };
    Ok(nephele_kernels::assets::load_by_magic(path, &options)?)
}

/// The image file a frame names, relative to the transforms file's folder.
fn frame_image(dir: &Path, file_path: &str) -> PathBuf {
    let p = dir.join(file_path);
    if p.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")) { p } else { p.with_extension("png") }
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    anyhow::ensure!(args.downscale > 0, "--downscale must be at least 1");
    let kernel = load_kernel(&args.asset, args.simd, args.device, args.march_stride)?;
    let transforms =
        dataset::read_transforms(&args.transforms).with_context(|| format!("reading {}", args.transforms.display()))?;
    let dir = args.transforms.parent().unwrap_or(Path::new("."));
    let (width, height) = match args.size {
        Some(s) => s,
        None => {
            let first = transforms.frames.first().map(|f| frame_image(dir, &f.file_path));
            let native = first
                .and_then(|p| RgbaImage::load_png(p).ok())
                .map(|img| (img.width(), img.height()))
                .unwrap_or((800, 800));
            ((native.0 / args.downscale).max(1), (native.1 / args.downscale).max(1))
        }
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let frames = &transforms.frames[..args.limit.unwrap_or(usize::MAX).min(transforms.frames.len())];
    let bar = progress.bar(frames.len() as u64, &format!("rendering ({})", kernel.kind()), "frames");
    let (mut seconds, mut rays, mut hits, mut queries) = (0.0f64, 0u64, 0u64, 0u64);
    for frame in frames {
        let camera = Camera::from_fov_x(width, height, transforms.camera_angle_x, frame.camera_to_world)
            .with_context(|| format!("camera of {}", frame.file_path))?;
        let start = Instant::now();
        let (out, stats) = kernel.render_pixels(&camera, &all_pixels(&camera))?;
        seconds += start.elapsed().as_secs_f64();
        rays += stats.rays;
        hits += stats.rays_hit;
        queries += stats.queries;
        let image = frame_to_image(width, height, &out).context("assembling the image")?;
        let name = frame.file_path.rsplit(['/', '\\']).next().unwrap_or("frame").trim_end_matches(".png");
        let path = args.out.join(format!("{name}.png"));
        image.save_png(&path).with_context(|| format!("writing {}", path.display()))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = frames.len().max(1) as f64;
    println!(
        "rendered {} frames at {width}x{height} with '{}' on {} threads: {:.1} ms per frame, {:.0} rays/s, {:.1}% rays hit, {:.2} queries per ray ({:.1} per hit ray)",
        frames.len(),
        kernel.kind(),
        rayon::current_num_threads(),
        1e3 * seconds / n,
        rays as f64 / seconds.max(1e-9),
        100.0 * hits as f64 / rays.max(1) as f64,
        queries as f64 / rays.max(1) as f64,
        queries as f64 / hits.max(1) as f64
    );
    println!("wrote {}", args.out.display());
    Ok(())
}
