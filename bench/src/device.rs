//! `bench device`: one i-NOLF asset on the CPU and on a GPU in the same run: time per frame,
//! the ratio, and how far the GPU frames are from the CPU frames.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_gpu::{Agreement, DeviceChoice, GpuContext, GpuInolfKernel};
use nephele_kernels::inolf::kernel::InolfKernel;
use nephele_kernels::kernel::{PixelResults, RayKernel, all_pixels};
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
    /// Instruction set of the CPU kernel.
    #[arg(long, default_value = "auto", value_name = "auto|off")]
    simd: SimdMode,
}

fn orbit(kernel: &dyn RayKernel, (width, height): (u32, u32), views: usize, distance: f32) -> Result<Vec<Camera>> {
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
fn run(
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
    let cameras = orbit(&cpu, args.size, args.views, args.distance)?;
    let bar = progress.bar(2 * cameras.len() as u64, "rendering", "frames");
    let (cpu_ms, hits, cpu_frames) = run(&cpu, &cameras, &bar)?;
    let (gpu_ms, gpu_hits, gpu_frames) = run(&gpu, &cameras, &bar)?;
    bar.finish_and_clear();

    let (w, h) = args.size;
    println!(
        "i-NOLF {} on the CPU and on a GPU, {} orbit views of {w}x{h}, {hits:.0} rays hit per frame",
        args.asset.display(),
        cameras.len()
    );
    let label = ctx.label();
    if ctx.is_software() {
        println!("GPU: {label} -- a software adapter running on this machine's CPU cores: not a GPU figure");
    } else {
        println!("GPU: {label}");
    }
    println!("{:<52} {:>10} {:>14} {:>12}", "kernel", "ms/frame", "rays/s", "hit rays");
    let rays = f64::from(w) * f64::from(h);
    let cpu_label = format!("cpu ({}, {} threads)", args.simd.describe(), rayon::current_num_threads());
    for (name, ms, hit) in [(cpu_label.as_str(), cpu_ms, hits), (label.as_str(), gpu_ms, gpu_hits)] {
        println!("{:<52} {:>10.2} {:>14.0} {:>12.0}", name, ms, rays / (ms / 1e3).max(1e-12), hit);
    }
    println!("GPU over CPU in this run: {:.2}x", cpu_ms / gpu_ms.max(1e-9));
    println!("GPU asset resident: {:.2} MiB", gpu.device_bytes() as f64 / 1048576.0);
    let mut total = Agreement::default();
    for (c, g) in cpu_frames.iter().zip(&gpu_frames) {
        total.merge(&Agreement::of(c, g));
    }
    println!("GPU against CPU: {total}");
    Ok(())
}
