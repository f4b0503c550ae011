//! `nephele bench gi`: the stereo global-illumination model against its single-eye teacher,
//! in one run. Cost: one stereo pass for both eyes against two single-eye passes at a given
//! size per eye (the networks' multiply-adds per pixel, and the measured ratio). Quality on
//! the dataset's evaluation pairs: PSNR and SSIM of both eyes against path tracing, and the
//! inter-eye coherence error, for the teacher run twice, the stereo student, and a student
//! trained without the coherence loss when given.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail, ensure};
use nephele_geometry::camera::Camera;
use nephele_kernels::environment::{GiKernel, GiServeSettings};
use nephele_kernels::gi::{GI_INPUTS, GiModel};
use nephele_kernels::kernel::{RayKernel, all_pixels};
use nephele_nn::{SimdMode, UNetWorkspace};
use nephele_train::gi::data::read_manifest;
use nephele_train::gi::stereo::{StereoEvaluation, StereoSample, evaluate_pairs, load_pairs, shade_pairs};

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct GiArgs {
    /// A dataset of one lighting from `nephele dataset gi` (with evaluation pairs).
    #[arg(long)]
    data: PathBuf,
    /// The single-eye model (`nephele train gi`).
    #[arg(long)]
    teacher: PathBuf,
    /// Its stereo student (`nephele train gi --teacher`).
    #[arg(long)]
    stereo: PathBuf,
    /// A student trained with `--coherence-weight 0`, for the coherence loss's effect.
    #[arg(long)]
    stereo_no_coherence: Option<PathBuf>,
    /// Image size per eye of the timed passes (the paper: 512x512).
    #[arg(long, default_value = "512x512", value_parser = nephele_geometry::camera::parse_size)]
    size: (u32, u32),
    /// Timed repetitions of each (the median is reported).
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    /// Samples per pixel of the served G-buffer and direct light (the farm kernel's default).
    #[arg(long, default_value_t = 2)]
    served_spp: u32,
    /// Skip the GPU backend's row (the WGSL U-Net). Where the only Vulkan adapter is a
    /// software one (llvmpipe), that row takes minutes at 512x512 and is not a GPU figure.
    #[arg(long)]
    no_gpu: bool,
}

/// The models as the farm serves them ([`GiKernel`]: the G-buffer and direct light rendered
/// at `--served-spp` at 1 and 0.5 of the view's resolution, then the U-Net, upsampled), on
/// the evaluation pairs' cameras against path tracing, and the whole kernel's cost at the
/// timed size: one stereo pair against two single-eye views.
fn served(
    args: &GiArgs,
    teacher: &GiModel,
    stereo: &GiModel,
    pairs: &[StereoSample],
    row: impl Fn(&str, &StereoEvaluation),
) -> Result<()> {
    if teacher.header.scene.is_none() {
        println!("served: the model names no scene (trained before serving existed); skipped");
        return Ok(());
    }
    let manifest = read_manifest(&args.data)?;
    let camera = |name: String| -> Result<Camera> {
        let frame = manifest.frames.iter().find(|f| f.name == name).with_context(|| format!("no frame {name}"))?;
        Ok(manifest.spec.camera(frame)?)
    };
    // Each pair's cameras and moment of the animation (the ball rolls).
    let cameras: Vec<([Camera; 2], f32)> = pairs
        .iter()
        .map(|p| {
            let name = format!("{}_left", p.name);
            let time = manifest.frames.iter().find(|f| f.name == name).map_or(0.0, |f| f.time);
            Ok(([camera(name)?, camera(format!("{}_right", p.name))?], time))
        })
        .collect::<Result<_>>()?;
    for scale in [1.0, 0.5] {
        let (mut single, mut paired) = (Vec::new(), Vec::new());
        for ([l, r], time_s) in &cameras {
            let settings =
                GiServeSettings { samples_per_pixel: args.served_spp, scale, time_s: *time_s, shade_covered: false };
            let kernel = GiKernel::new(teacher.clone(), Some(stereo.clone()), settings)?;
            let all = all_pixels(l);
            let eye = |c: &Camera| kernel.render_pixels(c, &all).map(|(p, _)| p.color);
            single.push([eye(l)?, eye(r)?]);
            let ([a, b], _) = kernel.render_pair((l, &all), (r, &all)).context("a stereo pass")??;
            paired.push([a.color, b.color]);
        }
        let tag = format!("served at {scale}x, {} spp", args.served_spp);
        row(&format!("{tag}, single-eye twice"), &evaluate_pairs(pairs, &single));
        row(&format!("{tag}, stereo pass"), &evaluate_pairs(pairs, &paired));
    }
    // Cost of the whole kernel (G-buffer + network + upsampling) at the timed size.
    let (w, h) = args.size;
    let ([l, r], _) = &cameras[0];
    let sized = |c: &Camera| Camera::from_fov_y(w, h, c.fov_y(), c.camera_to_world());
    let (l, r) = (sized(l)?, sized(r)?);
    let all = all_pixels(&l);
    for scale in [1.0, 0.5] {
        let settings = GiServeSettings { samples_per_pixel: args.served_spp, scale, time_s: 0.0, shade_covered: false };
        let kernel = GiKernel::new(teacher.clone(), Some(stereo.clone()), settings)?;
        let (mut two, mut one) = (Vec::new(), Vec::new());
        for _ in 0..args.repeats.max(1) + 1 {
            let t = Instant::now();
            kernel.render_pixels(&l, &all)?;
            kernel.render_pixels(&r, &all)?;
            two.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            kernel.render_pair((&l, &all), (&r, &all)).context("a stereo pass")??;
            one.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let (two, one) = (median(&mut two), median(&mut one));
        println!(
            "served kernel, CPU, {w}x{h} per eye at {scale}x, {} spp: two single-eye views {two:.1} ms, one stereo pair {one:.1} ms: ratio {:.3}; {:.3} us per view pixel (pair)",
            args.served_spp,
            one / two,
            1e3 * one / (2.0 * f64::from(w) * f64::from(h))
        );
        // Two bands of rows (two workers) against the whole view: the seam's cost.
        let half = all.len() / 2;
        let (whole, _) = kernel.render_pixels(&l, &all)?;
        let (top, _) = kernel.render_pixels(&l, &all[..half])?;
        let (bottom, _) = kernel.render_pixels(&l, &all[half..])?;
        let banded: Vec<[f32; 3]> = top.color.iter().chain(&bottom.color).copied().collect();
        let mse = whole
            .color
            .iter()
            .zip(&banded)
            .flat_map(|(a, b)| {
                (0..3).map(move |c| {
                    let d = a[c].clamp(0.0, 1.0) - b[c].clamp(0.0, 1.0);
                    f64::from(d * d)
                })
            })
            .sum::<f64>()
            / (3 * all.len()) as f64;
        println!(
            "  two bands of rows against the whole view at {scale}x: PSNR {:.2} dB (linear, clamped; the G-buffer's noise differs per band)",
            10.0 * (1.0 / mse.max(1e-12)).log10()
        );
    }
    Ok(())
}

/// The same passes through the WGSL U-Net ([`nephele_gpu::GpuUNet`]) on the Vulkan adapter
/// there is (a software one says so: its times are not a GPU's), with the largest difference
/// to the CPU's outputs.
fn gpu_ratio(
    teacher: &GiModel,
    stereo: &GiModel,
    (w, h): (usize, usize),
    (left, right, both): (&[f32], &[f32], &[f32]),
    repeats: usize,
) -> Result<()> {
    use nephele_gpu::{DeviceChoice, GpuContext, GpuUNet};
    let ctx = match GpuContext::open(DeviceChoice::Gpu) {
        Ok(Some(ctx)) => ctx,
        Ok(None) | Err(_) => {
            println!("GPU backend: no Vulkan adapter here; no GPU ratio");
            return Ok(());
        }
    };
    let single = GpuUNet::new(ctx.clone(), &teacher.network)?;
    let pair = GpuUNet::new(ctx.clone(), &stereo.network)?;
    let (mut two_single, mut one_stereo) = (Vec::new(), Vec::new());
    let mut outputs = Vec::new();
    for _ in 0..repeats.max(1) + 1 {
        let t = Instant::now();
        let l = single.forward(w, h, left)?;
        single.forward(w, h, right)?;
        two_single.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        outputs = pair.forward(w, h, both)?;
        one_stereo.push(t.elapsed().as_secs_f64() * 1e3);
        outputs.extend(l);
    }
    let (single_ms, stereo_ms) = (median(&mut two_single), median(&mut one_stereo));
    // Agreement with the CPU forward (stereo heads, then the single-eye left).
    let mut ws = UNetWorkspace::new();
    let mut cpu: Vec<Vec<f32>> = stereo.network.forward(w, h, both, &mut ws)?.iter().map(|s| s.to_vec()).collect();
    cpu.push(teacher.network.forward(w, h, left, &mut ws)?[0].to_vec());
    let worst = cpu
        .iter()
        .zip(&outputs)
        .flat_map(|(c, g)| c.iter().zip(g).map(|(a, b)| (a - b).abs() / a.abs().max(1.0)))
        .fold(0.0f32, f32::max);
    let kind = if ctx.is_software() { "software Vulkan: not a GPU figure" } else { "a GPU figure" };
    println!(
        "GPU backend ({}; {kind}), {w}x{h} per eye: two single-eye passes {single_ms:.1} ms, one stereo pass {stereo_ms:.1} ms: ratio {:.3}; largest difference to the CPU {worst:.2e}",
        ctx.label(),
        stereo_ms / single_ms
    );
    Ok(())
}

fn median(v: &mut Vec<f64>) -> f64 {
    v.remove(0);
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn load(path: &std::path::Path) -> Result<GiModel> {
    GiModel::load(path).with_context(|| format!("loading {}", path.display()))
}

pub fn run(args: GiArgs, _progress: &dyn Progress) -> Result<()> {
    let teacher = load(&args.teacher)?;
    let stereo = load(&args.stereo)?;
    ensure!(teacher.eyes() == 1, "{} is not a single-eye model", args.teacher.display());
    ensure!(stereo.eyes() == 2, "{} is not a stereo model", args.stereo.display());
    let features = teacher.header.features;
    let pairs =
        load_pairs(&args.data, &features, false, None).with_context(|| format!("loading {}", args.data.display()))?;
    if pairs.is_empty() {
        bail!("{} has no evaluation pairs (nephele dataset gi --stereo-pairs)", args.data.display());
    }

    // Cost: the networks' arithmetic, then one stereo pass against two single-eye passes.
    let (w, h) = (args.size.0 as usize, args.size.1 as usize);
    stereo.header.network.check_size(w, h)?;
    let (single_macs, stereo_macs) = (teacher.header.network.macs_per_pixel(), stereo.header.network.macs_per_pixel());
    println!(
        "networks: single-eye {} parameters, {single_macs:.0} multiply-adds per pixel; stereo {} parameters, {stereo_macs:.0} per pixel of both eyes ({:.3} of two single-eye passes)",
        teacher.network.params().len(),
        stereo.network.params().len(),
        stereo_macs / (2.0 * single_macs)
    );
    // Inputs: an evaluation pair scaled to the timed size (nearest), so the activations (and
    // the zero-skipping of the convolutions) are those of real frames.
    let p = &pairs[0];
    let resize = |src: &[f32], channels: usize| -> Vec<f32> {
        let mut out = Vec::with_capacity(w * h * channels);
        for y in 0..h {
            for x in 0..w {
                let (sx, sy) = (x * p.width / w, y * p.height / h);
                out.extend_from_slice(&src[(sy * p.width + sx) * channels..][..channels]);
            }
        }
        out
    };
    let (left, right, both) =
        (resize(&p.eyes[0], GI_INPUTS), resize(&p.eyes[1], GI_INPUTS), resize(&p.stacked, 2 * GI_INPUTS));
    let mut ws = UNetWorkspace::new();
    // The same networks run by the scalar twin of the convolutions, for the SIMD speed-up.
    let (mut teacher_scalar, mut stereo_scalar) = (teacher.network.clone(), stereo.network.clone());
    teacher_scalar.set_simd(SimdMode::Off);
    stereo_scalar.set_simd(SimdMode::Off);
    let mut times = [(); 4].map(|_| Vec::new());
    for _ in 0..args.repeats.max(1) + 1 {
        // Alternated, so all see the same machine load; the first round warms up.
        for (k, (single, pair)) in
            [(&teacher.network, &stereo.network), (&teacher_scalar, &stereo_scalar)].into_iter().enumerate()
        {
            let t = Instant::now();
            single.forward(w, h, &left, &mut ws)?;
            single.forward(w, h, &right, &mut ws)?;
            times[2 * k].push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            pair.forward(w, h, &both, &mut ws)?;
            times[2 * k + 1].push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    let [single_ms, stereo_ms, single_scalar_ms, stereo_scalar_ms] = times.map(|mut t| median(&mut t));
    let threads = rayon::current_num_threads();
    println!(
        "CPU ({}), {w}x{h} per eye, {threads} threads: two single-eye passes {single_ms:.1} ms, one stereo pass {stereo_ms:.1} ms: ratio {:.3} (paper 0.53 on a GPU)",
        SimdMode::Auto.describe(),
        stereo_ms / single_ms
    );
    let gmacs = |macs: f64, ms: f64| macs * (w * h) as f64 / (ms * 1e6);
    println!(
        "CPU scalar twin (--simd off): two single-eye passes {single_scalar_ms:.1} ms, one stereo pass {stereo_scalar_ms:.1} ms: SIMD speed-up {:.2}x / {:.2}x; {:.1} / {:.1} G multiply-adds per second with SIMD, {:.1} / {:.1} scalar",
        single_scalar_ms / single_ms,
        stereo_scalar_ms / stereo_ms,
        gmacs(2.0 * single_macs, single_ms),
        gmacs(stereo_macs, stereo_ms),
        gmacs(2.0 * single_macs, single_scalar_ms),
        gmacs(stereo_macs, stereo_scalar_ms),
    );
    if args.no_gpu {
        println!("GPU backend: skipped (--no-gpu)");
    } else {
        gpu_ratio(&teacher, &stereo, (w, h), (&left, &right, &both), args.repeats)?;
    }

    // Quality on the evaluation pairs.
    let row = |name: &str, e: &StereoEvaluation| {
        println!(
            "{name:<34} PSNR {:.2} / {:.2} dB  SSIM {:.4} / {:.4}  coherence error {:.6}",
            e.psnr[0], e.psnr[1], e.ssim[0], e.ssim[1], e.coherence
        );
    };
    println!("{} evaluation pairs of {}x{} (left / right eye, displayed images):", pairs.len(), p.width, p.height);
    // What the rasteriser has without the model: its direct light (input channels 10..13
    // hold ln(1 + direct)).
    let direct: Vec<[Vec<[f32; 3]>; 2]> = pairs
        .iter()
        .map(|p| {
            p.eyes.clone().map(|inputs| {
                inputs.chunks_exact(GI_INPUTS).map(|c| [c[10].exp_m1(), c[11].exp_m1(), c[12].exp_m1()]).collect()
            })
        })
        .collect();
    row("direct light only (no GI model)", &evaluate_pairs(&pairs, &direct));
    let twice = evaluate_pairs(&pairs, &shade_pairs(&teacher, &pairs)?);
    row("single-eye model, run twice", &twice);
    let student = evaluate_pairs(&pairs, &shade_pairs(&stereo, &pairs)?);
    row("stereo model, one pass", &student);
    println!(
        "stereo against single-eye: {:+.2} / {:+.2} dB",
        student.psnr[0] - twice.psnr[0],
        student.psnr[1] - twice.psnr[1]
    );
    served(&args, &teacher, &stereo, &pairs, row)?;
    if let Some(path) = &args.stereo_no_coherence {
        let plain = load(path)?;
        ensure!(plain.eyes() == 2, "{} is not a stereo model", path.display());
        let without = evaluate_pairs(&pairs, &shade_pairs(&plain, &pairs)?);
        row("stereo model, no coherence loss", &without);
        println!(
            "coherence error with the loss / without: {:.6} / {:.6} = {:.3} (paper 0.00538 / 0.00804 = 0.669)",
            student.coherence,
            without.coherence,
            student.coherence / without.coherence
        );
    }
    Ok(())
}
