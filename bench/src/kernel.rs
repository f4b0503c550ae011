//! `bench kernel`: where the i-NOLF CPU kernel's time goes, in one run, over orbit views of
//! one or more assets: the whole kernel with AVX2+FMA and with scalar code, and the density
//! march alone (the rest is the heads of the rays that hit). Rounds alternate the rows so
//! that a noisy neighbour on a shared machine hits all of them alike.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use nephele_kernels::inolf::cubes::{DensityCubes, MarchHit};
use nephele_kernels::inolf::encoding::CellCache;
use nephele_kernels::inolf::kernel::{HIT_OPACITY, InolfKernel, RAY_NEAR};
use nephele_kernels::kernel::PixelResults;
use nephele_nn::SimdMode;
use rayon::prelude::*;

use crate::Progress;
use crate::device::{orbit, run};

#[derive(Debug, clap::Args)]
pub struct KernelArgs {
    /// i-NOLF assets (`.nolf`), comma-separated; each is timed on its own.
    #[arg(long, value_delimiter = ',', required = true)]
    asset: Vec<PathBuf>,
    /// Frame size.
    #[arg(long, default_value = "640x480", value_parser = nephele_geometry::camera::parse_size, value_name = "WxH")]
    size: (u32, u32),
    /// Views on a circle around each object.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Distance of the cameras from the object's centre, in radii of its box.
    #[arg(long, default_value_t = 2.2)]
    distance: f32,
    /// Rounds; each renders every view once per row, rows alternating.
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// A row for the march sampling every N voxels (`nephele worker --march-stride`), timed
    /// in the same rounds and scored against every-voxel frames; default: the stride each
    /// asset's bake chose (no row for an asset marched every voxel); 1 leaves it out.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=i64::from(nephele_kernels::inolf::cubes::MAX_MARCH_STRIDE)))]
    march_stride: Option<u32>,
}

/// PSNR (dB, peak 1) of colour and opacity together between two lists of frames; 99 when
/// they are equal.
fn psnr_between(a: &[PixelResults], b: &[PixelResults]) -> f64 {
    let (mut sum, mut count) = (0.0f64, 0u64);
    for (a, b) in a.iter().zip(b) {
        for i in 0..a.len() {
            for c in 0..3 {
                sum += f64::from(a.color[i][c] - b.color[i][c]).powi(2);
            }
            sum += f64::from(a.opacity[i] - b.opacity[i]).powi(2);
            count += 4;
        }
    }
    let mse = sum / count.max(1) as f64;
    if mse > 0.0 { (-10.0 * mse.log10()).min(99.0) } else { 99.0 }
}

/// Largest absolute difference of colour, opacity and depth between two lists of frames.
fn largest_difference(a: &[PixelResults], b: &[PixelResults]) -> f32 {
    let mut worst = 0.0f32;
    for (a, b) in a.iter().zip(b) {
        for i in 0..a.len() {
            let d = (0..3).map(|c| (a.color[i][c] - b.color[i][c]).abs()).fold(0.0, f32::max);
            worst = worst.max(d).max((a.opacity[i] - b.opacity[i]).abs()).max((a.depth[i] - b.depth[i]).abs());
        }
    }
    worst
}

/// The march alone over every pixel of every camera: ms per frame and the summed work.
fn march_only(density: &DensityCubes, cameras: &[nephele_geometry::camera::Camera]) -> (f64, MarchWork) {
    let start = Instant::now();
    let mut work = MarchWork::default();
    for camera in cameras {
        let (w, h) = (camera.width(), camera.height());
        let frame = (0..w * h)
            .into_par_iter()
            .map(|p| {
                let ray = camera.pixel_center_ray(p % w, p / w);
                MarchWork::of(&density.march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY))
            })
            .reduce(MarchWork::default, MarchWork::add);
        work = work.add(frame);
    }
    (1e3 * start.elapsed().as_secs_f64() / cameras.len() as f64, work)
}

/// The rays of a frame by what the march meets: they miss the grid's box, cross it without
/// a hit, or hit.
const RAY_CLASSES: [&str; 3] = ["miss the box", "cross the box, no hit", "hit"];

/// Every camera's pixels sorted into [`RAY_CLASSES`] (untimed; once per asset): per class,
/// per camera, the pixels.
type ClassPixels = [Vec<Vec<u32>>; 3];

fn classify_rays(kernel: &InolfKernel, cameras: &[nephele_geometry::camera::Camera]) -> ClassPixels {
    let bounds = kernel.density().bounds();
    let class_of = |camera: &nephele_geometry::camera::Camera, p: u32| {
        let ray = camera.pixel_center_ray(p % camera.width(), p / camera.width());
        let inv = ray.direction.recip();
        let (ta, tb) = ((bounds.min - ray.origin) * inv, (bounds.max - ray.origin) * inv);
        let enters = ta.min(tb).max_element().max(RAY_NEAR) < ta.max(tb).min_element();
        let hit = kernel.density().march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY).opacity >= HIT_OPACITY;
        if hit { 2 } else { usize::from(enters) }
    };
    let mut lists: [Vec<Vec<u32>>; 3] = Default::default();
    for camera in cameras {
        let mut per_camera: [Vec<u32>; 3] = Default::default();
        for p in 0..camera.width() * camera.height() {
            per_camera[class_of(camera, p)].push(p);
        }
        for (all, one) in lists.iter_mut().zip(per_camera) {
            all.push(one);
        }
    }
    lists
}

/// The march alone per class of ray ([`classify_rays`]), every camera: ms per frame and the
/// summed work of each class.
fn march_by_class(
    kernel: &InolfKernel,
    cameras: &[nephele_geometry::camera::Camera],
    classes: &ClassPixels,
) -> [(f64, MarchWork); 3] {
    std::array::from_fn(|class| {
        let per_camera = &classes[class];
        let start = Instant::now();
        let mut work = MarchWork::default();
        for (camera, pixels) in cameras.iter().zip(per_camera) {
            let w = camera.width();
            let counted = pixels
                .par_iter()
                .map(|&p| {
                    let ray = camera.pixel_center_ray(p % w, p / w);
                    MarchWork::of(&kernel.density().march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY))
                })
                .reduce(MarchWork::default, MarchWork::add);
            work = work.add(counted);
        }
        (1e3 * start.elapsed().as_secs_f64() / cameras.len() as f64, work)
    })
}

/// The share of the heads' PSH look-ups that the kernel's cell cache answers (hit points in
/// the kernel's order: pixel order within its chunks of 1024), over every camera.
fn psh_cell_reuse(kernel: &InolfKernel, cameras: &[nephele_geometry::camera::Camera]) -> f64 {
    let (mut hits, mut queries) = (0u64, 0u64);
    for camera in cameras {
        let w = camera.width();
        let pixels: Vec<u32> = (0..w * camera.height()).collect();
        for chunk in pixels.chunks(1024) {
            let mut cache = CellCache::default();
            for &p in chunk {
                let ray = camera.pixel_center_ray(p % w, p / w);
                let h = kernel.density().march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY);
                if h.opacity >= HIT_OPACITY {
                    kernel.psh().corners_with(ray.at(h.t), &mut cache);
                }
            }
            (hits, queries) = (hits + cache.hits, queries + cache.queries);
        }
    }
    hits as f64 / queries.max(1) as f64
}

#[derive(Debug, Clone, Copy, Default)]
struct MarchWork {
    rays: u64,
    cells: u64,
    samples: u64,
    lookups: u64,
}

impl MarchWork {
    fn of(hit: &MarchHit) -> MarchWork {
        MarchWork { rays: 1, cells: hit.cells.into(), samples: hit.samples.into(), lookups: hit.lookups.into() }
    }

    fn add(self, o: MarchWork) -> MarchWork {
        MarchWork {
            rays: self.rays + o.rays,
            cells: self.cells + o.cells,
            samples: self.samples + o.samples,
            lookups: self.lookups + o.lookups,
        }
    }
}

pub fn run_kernel(args: KernelArgs, progress: &dyn Progress) -> Result<()> {
    anyhow::ensure!(args.rounds > 0 && args.views > 0, "--rounds and --views must be positive");
    let (w, h) = args.size;
    let rays = f64::from(w) * f64::from(h);
    println!(
        "i-NOLF CPU kernel, {} orbit views of {w}x{h} per asset, {} rounds, {} threads",
        args.views,
        args.rounds,
        rayon::current_num_threads()
    );
    for path in &args.asset {
        let mut fast = InolfKernel::load(path).with_context(|| format!("loading {}", path.display()))?;
        // Every row but the strided one marches every voxel, whatever stride the bake chose.
        let asset_stride = fast.density().march_stride();
        fast.set_march_stride(1)?;
        let mut scalar = fast.clone();
        scalar.set_simd(SimdMode::Off);
        let mut unhinted = fast.clone();
        unhinted.set_prefetch(false);
        let stride = args.march_stride.unwrap_or(asset_stride);
        let strided = match stride {
            1 => None,
            n => {
                let mut kernel = fast.clone();
                kernel.set_march_stride(n)?;
                Some(kernel)
            }
        };
        // The march with the blend samples kept (for heads that blend their diffuse colour)
        // if the asset's heads do not, and without them if they do: what keeping them costs.
        let mut toggled = fast.density().clone();
        let kept = fast.density().blend_samples();
        toggled.set_blend_samples(if kept > 0 { 0 } else { fast.shape().blend_samples.max(1) });
        let cameras = orbit(&fast, args.size, args.views, args.distance)?;
        let classes = classify_rays(&fast, &cameras);
        let kernels = 3 + usize::from(strided.is_some());
        let bar = progress.bar((args.rounds * kernels * cameras.len()) as u64, "rendering", "frames");
        let (mut fast_ms, mut scalar_ms, mut march_ms, mut strided_ms, mut unhinted_ms) = (0.0, 0.0, 0.0, 0.0, 0.0);
        let mut toggled_ms = 0.0;
        let (mut hits, mut work) = (0.0, MarchWork::default());
        let mut by_class = [(0.0, MarchWork::default()); 3];
        let (mut fast_frames, mut scalar_frames, mut strided_frames, mut unhinted_frames) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let share = 1.0 / args.rounds as f64;
        for _ in 0..args.rounds {
            let (t, hit, out) = run(&fast, &cameras, &bar)?;
            (fast_ms, hits, fast_frames) = (fast_ms + share * t, hit, out);
            let (t, _, out) = run(&scalar, &cameras, &bar)?;
            (scalar_ms, scalar_frames) = (scalar_ms + share * t, out);
            let (t, _, out) = run(&unhinted, &cameras, &bar)?;
            (unhinted_ms, unhinted_frames) = (unhinted_ms + share * t, out);
            let (t, counted) = march_only(fast.density(), &cameras);
            (march_ms, work) = (march_ms + share * t, counted);
            toggled_ms += share * march_only(&toggled, &cameras).0;
            for (sum, (t, counted)) in by_class.iter_mut().zip(march_by_class(&fast, &cameras, &classes)) {
                *sum = (sum.0 + share * t, counted);
            }
            if let Some(kernel) = &strided {
                let (t, _, out) = run(kernel, &cameras, &bar)?;
                (strided_ms, strided_frames) = (strided_ms + share * t, out);
            }
        }
        bar.finish_and_clear();
        let per_ray = |v: u64| v as f64 / work.rays.max(1) as f64;
        println!(
            "{} (its bake chose march stride {asset_stride}; rows below march every voxel unless named): {hits:.0} rays hit per frame ({:.1} %); per ray {:.2} cells, {:.2} samples, {:.2} corner decodes",
            path.display(),
            100.0 * hits / rays,
            per_ray(work.cells),
            per_ray(work.samples),
            per_ray(work.lookups)
        );
        println!(
            "heads: {:.1} % of the hit rays' PSH look-ups answered by the previous hit ray's lattice cell",
            100.0 * psh_cell_reuse(&fast, &cameras)
        );
        let class_ms: f64 = by_class.iter().map(|c| c.0).sum();
        let threads = rayon::current_num_threads() as f64;
        for (name, (ms, w)) in RAY_CLASSES.iter().zip(&by_class) {
            let rays = w.rays.max(1) as f64;
            println!(
                "  march, rays that {name}: {:.0} per frame, {:.1} % of the march's time, {:.0} ns of a thread per ray; per ray {:.2} cells, {:.2} samples, {:.2} corner decodes",
                w.rays as f64 / cameras.len() as f64,
                100.0 * ms / class_ms.max(1e-12),
                ms * 1e6 * threads * cameras.len() as f64 / rays,
                w.cells as f64 / rays,
                w.samples as f64 / rays,
                w.lookups as f64 / rays
            );
        }
        println!("{:<40} {:>10} {:>14} {:>10}", "row", "ms/frame", "rays/s", "share");
        let strided_label = format!("whole kernel, march stride {stride}");
        let toggled_label = if toggled.blend_samples() > 0 {
            "density march keeping blend samples"
        } else {
            "density march without blend samples"
        };
        let mut rows = vec![
            ("whole kernel, AVX2+FMA where present", fast_ms),
            ("whole kernel, scalar (--simd off)", scalar_ms),
            ("whole kernel, no prefetch hints", unhinted_ms),
            ("density march alone", march_ms),
            (toggled_label, toggled_ms),
            ("heads of the hit rays (the difference)", fast_ms - march_ms),
        ];
        if strided.is_some() {
            rows.push((strided_label.as_str(), strided_ms));
        }
        for (label, ms) in rows {
            println!("{label:<40} {ms:>10.2} {:>14.0} {:>9.1}%", rays / (ms / 1e3).max(1e-12), 100.0 * ms / fast_ms);
        }
        if let Some(kernel) = &strided {
            // Counted once: the work is the same every round (its time is not used).
            let strided_work = march_only(kernel.density(), &cameras).1;
            let per_ray = |v: u64| v as f64 / strided_work.rays.max(1) as f64;
            println!(
                "march stride {}: {:.2} samples and {:.2} corner decodes per ray; {:.2}x the speed of every voxel in this run; colour and opacity {:.2} dB PSNR against every voxel's",
                stride,
                per_ray(strided_work.samples),
                per_ray(strided_work.lookups),
                fast_ms / strided_ms.max(1e-12),
                psnr_between(&strided_frames, &fast_frames)
            );
        }
        let (with_blend, without_blend) =
            if toggled.blend_samples() > 0 { (toggled_ms, march_ms) } else { (march_ms, toggled_ms) };
        println!(
            "keeping the {} blend samples (heads that blend their diffuse colour; this asset's heads {}): the march {:.3}x its time without them in this run",
            kept.max(toggled.blend_samples()),
            if fast.shape().diffuse_blend { "do" } else { "do not" },
            with_blend / without_blend.max(1e-12)
        );
        println!(
            "scalar over AVX2+FMA in this run: {:.2}x; largest difference of their results {:.2e}",
            scalar_ms / fast_ms.max(1e-12),
            largest_difference(&fast_frames, &scalar_frames)
        );
        println!(
            "without the heads' prefetch hints in this run: {:.2}x; largest difference of their results {:.2e} (none expected)",
            unhinted_ms / fast_ms.max(1e-12),
            largest_difference(&fast_frames, &unhinted_frames)
        );
    }
    Ok(())
}
