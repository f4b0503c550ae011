//! `bench device`: one i-NOLF asset (and optionally its radiance field, the baseline) on the
//! CPU and on a GPU in the same run: time per frame, the ratio, and how far the GPU frames
//! are from the CPU frames.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_gpu::{Agreement, DeviceChoice, GpuContext, GpuInolfKernel, GpuNgpKernel};
use nephele_kernels::inolf::kernel::InolfKernel;
use nephele_kernels::kernel::{PixelResults, RayKernel, all_pixels};
use nephele_kernels::ngp::NgpKernel;
use nephele_nn::SimdMode;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct DeviceArgs {
    /// The i-NOLF asset (`.nolf`).
    #[arg(long)]
    asset: PathBuf,
    /// Frame size.
    #[arg(long, default_value = "400x400", value_parser = nephele_geometry::camera::parse_size, value_name = "WxH")]
    size: (u32, u32),
    /// Views on a circle around the object (each rendered once per device after a warm-up).
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Distance of the cameras from the object's centre, in radii of its box.
    #[arg(long, default_value_t = 2.2)]
    distance: f32,
    /// The GPU: gpu (a hardware GPU, else a software Vulkan adapter) or auto (a hardware GPU
    /// only).
    #[arg(long, default_value = "gpu", value_name = "auto|gpu")]
    device: DeviceChoice,
    /// Also the i-NGP-style baseline from this radiance field (`nephele bake --save-field`),
    /// on both devices, over the same cameras.
    #[arg(long)]
    field: Option<PathBuf>,
    /// Instruction set of the CPU kernel.
    #[arg(long, default_value = "auto", value_name = "auto|off")]
    simd: SimdMode,
}

pub(crate) fn orbit(
    kernel: &dyn RayKernel,
    (width, height): (u32, u32),
    views: usize,
    distance: f32,
) -> Result<Vec<Camera>> {
    let b = kernel.bounds();
    let (centre, radius) = (b.center(), 0.5 * b.size().length().max(1e-3));
    (0..views.max(1))
        .map(|i| {
            let a = i as f32 * std::f32::consts::TAU / views.max(1) as f32;
            let eye = centre + radius * distance * Vec3::new(a.cos(), a.sin(), 0.45 + 0.3 * (i % 2) as f32).normalize();
            Camera::look_at(width, height, 0.7, eye, centre, Vec3::Z).context("orbit camera")
        })
        .collect()
}

/// Renders every camera once; returns ms per frame, rays hit per frame and the frames.
pub(crate) fn run(
    kernel: &dyn RayKernel,
    cameras: &[Camera],
    bar: &indicatif::ProgressBar,
) -> Result<(f64, f64, Vec<PixelResults>)> {
    // Warm-up: caches, lazily built pipelines and buffers.
    kernel.render_pixels(&cameras[0], &all_pixels(&cameras[0]))?;
    let (mut seconds, mut hits, mut frames) = (0.0, 0u64, Vec::new());
    for camera in cameras {
        let pixels = all_pixels(camera);
        let start = Instant::now();
        let (out, stats) = kernel.render_pixels(camera, &pixels)?;
        seconds += start.elapsed().as_secs_f64();
        hits += stats.rays_hit;
        frames.push(out);
        bar.inc(1);
    }
    let n = cameras.len() as f64;
    Ok((1e3 * seconds / n, hits as f64 / n, frames))
}

/// Times `cpu` and `gpu` over `cameras` and prints their rows, the ratio and the agreement.
fn compare(
    name: &str,
    cpu: &dyn RayKernel,
    gpu: &dyn RayKernel,
    cameras: &[Camera],
    args: &DeviceArgs,
    gpu_label: &str,
    bar: &indicatif::ProgressBar,
) -> Result<()> {
    let (cpu_ms, hits, cpu_frames) = run(cpu, cameras, bar)?;
    let (gpu_ms, gpu_hits, gpu_frames) = run(gpu, cameras, bar)?;
    let (w, h) = args.size;
    println!("{name}: {} orbit views of {w}x{h}, {hits:.0} rays hit per frame", cameras.len());
    println!("{:<52} {:>10} {:>14} {:>12}", "kernel", "ms/frame", "rays/s", "hit rays");
    let rays = f64::from(w) * f64::from(h);
    let cpu_label = format!("cpu ({}, {} threads)", args.simd.describe(), rayon::current_num_threads());
    for (label, ms, hit) in [(cpu_label.as_str(), cpu_ms, hits), (gpu_label, gpu_ms, gpu_hits)] {
        println!("{:<52} {:>10.2} {:>14.0} {:>12.0}", label, ms, rays / (ms / 1e3).max(1e-12), hit);
    }
    println!("GPU over CPU in this run: {:.2}x", cpu_ms / gpu_ms.max(1e-9));
    let mut total = Agreement::default();
    for (c, g) in cpu_frames.iter().zip(&gpu_frames) {
        total.merge(&Agreement::of(c, g));
    }
    println!("GPU against CPU: {total}");
    Ok(())
}

pub fn device(args: DeviceArgs, progress: &dyn Progress) -> Result<()> {
    anyhow::ensure!(
        args.device != DeviceChoice::Cpu,
        "--device must name a GPU (gpu or auto); the CPU row is always run"
    );
    let mut cpu = InolfKernel::load(&args.asset).with_context(|| format!("loading {}", args.asset.display()))?;
    cpu.set_simd(args.simd);
    let ctx = GpuContext::open(args.device)?
        .context("--device auto found no hardware GPU (use --device gpu to accept a software adapter)")?;
    let gpu = GpuInolfKernel::new(ctx.clone(), &cpu)?;
    let baseline = match &args.field {
        Some(path) => {
            let mut ngp = NgpKernel::load(path).with_context(|| format!("loading {}", path.display()))?;
            ngp.set_simd(args.simd);
            let gpu = GpuNgpKernel::new(ctx.clone(), &ngp)?;
            Some((ngp, gpu))
        }
        None => None,
    };
    let cameras = orbit(&cpu, args.size, args.views, args.distance)?;
    let label = ctx.label();
    if ctx.is_software() {
        println!("GPU: {label} -- a software adapter running on this machine's CPU cores: not a GPU figure");
    } else {
        println!("GPU: {label}");
    }
    let rows = if baseline.is_some() { 4 } else { 2 };
    let bar = progress.bar((rows * cameras.len()) as u64, "rendering", "frames");
    compare(&format!("i-NOLF {}", args.asset.display()), &cpu, &gpu, &cameras, &args, &label, &bar)?;
    println!("GPU asset resident: {:.2} MiB", gpu.device_bytes() as f64 / 1048576.0);
    if let (Some((ngp, gpu)), Some(path)) = (&baseline, &args.field) {
        compare(&format!("i-NGP baseline {}", path.display()), ngp, gpu, &cameras, &args, &label, &bar)?;
        println!("GPU field resident: {:.2} MiB", gpu.device_bytes() as f64 / 1048576.0);
    }
    bar.finish_and_clear();
    Ok(())
}
