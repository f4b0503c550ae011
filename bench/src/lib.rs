//! `nephele-bench`: the figures recorded in BENCHMARKS.md (`nephele bench ...`).
//!
//! One module per family: [`encode`] (the composer's stages), [`wire`] (protocol cost and
//! loopback throughput), [`scheduler`] (rounds of the scheduler core), [`inolf`] (PSH,
//! density cubes, cache behaviour, i-NOLF against its baseline), [`hardcases`] (the
//! numerical-stability suite: adversarial rays through every kernel and trainer, with its
//! CI-sized test here), [`share`] (rays saved by reprojection between adjacent views, and
//! the dB it costs), [`assigner`] (the TaskAssigner's pixel estimate against the pixels
//! really hit); the path tracer's throughput is here. Benchmarks print numbers;
//! correctness is the tests' job.
//!
//! Depends on the libraries it measures; nothing depends on it but the CLI. The counting
//! allocator behind `bench inolf`'s runtime-memory column is compiled in only with the
//! `heap-peak` feature ([`heap`]).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_imaging::metrics;
use nephele_pathtracer::integrator::Aov;
use nephele_pathtracer::scenes;
use nephele_pathtracer::{RenderOptions, Renderer};
use serde_json::json;

pub mod assigner;
pub mod covered;
pub mod device;
pub mod encode;
pub mod gi;
pub mod hardcases;
pub mod heap;
pub mod inolf;
pub mod kernel;
pub mod scheduler;
pub mod share;
pub mod wire;

/// Where benchmarks draw their progress bars (the CLI's, hidden by `--quiet`).
pub trait Progress {
    /// A bar of `total` steps labelled `message`, counting `unit`s.
    fn bar(&self, total: u64, message: &str, unit: &str) -> indicatif::ProgressBar;
}

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Path tracer throughput on each built-in scene (samples/s, rays/s), the BVH's work per
    /// ray, and the error reached: PSNR of the timed render against a render with many more
    /// samples of the same view.
    Reference(ReferenceArgs),
    /// The composer's stages per frame at streaming sizes: depth fusion, colour conversion
    /// and H.264 encoding (frames/s, bitrate, PSNR of the decoded stream against its input).
    Encode(crate::encode::Args),
    /// Protocol cost: encode/decode ns per pixel (packed against element-by-element), bytes
    /// on the wire per pixel, and loopback TCP throughput of batch results between two
    /// processes and between two tokio tasks (batches/s, GB/s of pixel results).
    Wire(crate::wire::WireArgs),
    /// The receiving end of `bench wire` (started by it).
    #[command(hide = true)]
    WireSink(crate::wire::SinkArgs),
    /// Scheduler core: microseconds per scheduling round at 10, 100 and 1000 users with
    /// 10,000 pending tasks (NEPHELE against FIFO in the same run).
    Scheduler(crate::scheduler::SchedulerArgs),
    /// Perfect spatial hashing of each scene's surface voxels at 128^3, 256^3, 512^3: table
    /// sizes, build time, neighbour coherence, and a check of zero collisions.
    Psh(crate::inolf::PshArgs),
    /// Density texture cubes over each scene: bytes against a dense grid, and the cost of
    /// marching the default view (cells, samples and nanoseconds per ray, rays that miss).
    Cubes(crate::inolf::CubesArgs),
    /// One stream of encoding queries (hit points from random viewpoints) answered by the PSH
    /// encoding or the multiresolution hash grid; run it under
    /// `valgrind --tool=cachegrind` once per `--encoding` (and once with `none` to subtract).
    PshCache(crate::inolf::PshCacheArgs),
    /// i-NOLF against the i-NGP-style baseline on held-out views of a dataset: quality,
    /// time per frame, rays per second and speed-up, measured in one run.
    Inolf(crate::inolf::InolfArgs),
    /// One i-NOLF asset (and with `--field` its baseline) on the CPU and on a GPU in the same
    /// run (orbit views): ms per frame, the ratio, and the GPU frames' difference from the CPU
    /// frames. A software Vulkan adapter (Mesa's lavapipe) is accepted and labelled as such.
    Device(crate::device::DeviceArgs),
    /// The i-NOLF CPU kernel against its variants in one run (orbit views of one or more
    /// assets): square ray tiles against the batch's row order, AVX2+FMA against scalar code;
    /// ms per frame, the ratios, and the largest difference of the results.
    Kernel(crate::kernel::KernelArgs),
    /// The stereo global-illumination model against its single-eye teacher in one run: one
    /// stereo pass against two single-eye passes (multiply-adds and time), PSNR/SSIM of both
    /// eyes against path tracing, and the inter-eye coherence error with and without the
    /// coherence loss.
    Gi(crate::gi::GiArgs),
    /// The environment kernel with and without the objects' solid matter (the room behind
    /// them is not lit): samples hidden against the pixels the objects cover, time per view
    /// flat and stereo in one run, and the PSNR of the visible pixels against no occluders.
    Covered(crate::covered::CoveredArgs),
    /// The numerical-stability suite: adversarial rays (axis-parallel, grazing, inside the box
    /// and the matter, far away, denormal components, and degenerate ones that must be
    /// rejected) through every kernel (CPU, GPU, path tracer, stereo GI) and both trainers'
    /// forward and backward passes, on tiny, unit and huge scenes. Prints the non-finite and
    /// out-of-range counts per kernel and fails unless they are all zero.
    Hardcases(crate::hardcases::HardcaseArgs),
    /// Shared rays between adjacent views (NEPHELE eqs. 10-12, by depth reprojection): a
    /// stereo pair, four users orbiting 2, 5 and 10 degrees apart, a 45-view quilt and one
    /// user's consecutive frames, each around held-out views of a dataset. Rays rendered
    /// against rendering every view in full, PSNR of every shared view against its own full
    /// render, dB lost against the ground truth, and the reprojection's time against a full
    /// render's, in one run; a sweep of the reuse angle.
    Share(crate::share::ShareArgs),
    /// The TaskAssigner's `nhit` estimate against the pixels each built-in object really
    /// covers (path-traced primary rays), for the bounding box and for occupancy grids made
    /// from the object's mesh: mean relative error, hit pixels missed (must be zero), and the
    /// estimate's time against the box's.
    Assigner(crate::assigner::AssignerArgs),
}

#[derive(Debug, clap::Args)]
pub struct ReferenceArgs {
    /// Image size of the timed render.
    #[arg(long, default_value = "128x128", value_parser = nephele_geometry::camera::parse_size)]
    size: (u32, u32),
    /// Samples per pixel of the timed render.
    #[arg(long, default_value_t = 16)]
    spp: u32,
    /// Samples per pixel of the converged image the error is measured against.
    #[arg(long, default_value_t = 256)]
    reference_spp: u32,
    /// Scenes to run (default: all built-in scenes).
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

pub fn run(command: Command, progress: &dyn Progress) -> Result<()> {
    match command {
        Command::Reference(args) => reference(args, progress),
        Command::Encode(args) => crate::encode::run(args, progress),
        Command::Wire(args) => crate::wire::run(args, progress),
        Command::WireSink(args) => crate::wire::sink(args),
        Command::Scheduler(args) => crate::scheduler::run(args, progress),
        Command::Psh(args) => crate::inolf::psh(args, progress),
        Command::Cubes(args) => crate::inolf::cubes(args, progress),
        Command::PshCache(args) => crate::inolf::psh_cache(args, progress),
        Command::Inolf(args) => crate::inolf::inolf(args, progress),
        Command::Device(args) => crate::device::device(args, progress),
        Command::Kernel(args) => crate::kernel::run_kernel(args, progress),
        Command::Gi(args) => crate::gi::run(args, progress),
        Command::Covered(args) => crate::covered::run(args, progress),
        Command::Hardcases(args) => crate::hardcases::hardcases(args, progress),
        Command::Share(args) => crate::share::run(args, progress),
        Command::Assigner(args) => crate::assigner::run(args, progress),
    }
}

fn reference(args: ReferenceArgs, progress: &dyn Progress) -> Result<()> {
    let names: Vec<String> = if args.scenes.is_empty() {
        scenes::names().iter().map(|s| s.to_string()).collect()
    } else {
        args.scenes.clone()
    };
    let (width, height) = args.size;
    println!(
        "reference path tracer, {width}x{height}, {} spp timed, error against {} spp, {} threads",
        args.spp,
        args.reference_spp,
        rayon::current_num_threads()
    );
    println!(
        "{:<11} {:>9} {:>9} {:>11} {:>11} {:>10} {:>10} {:>9}",
        "scene", "triangles", "build ms", "samples/s", "rays/s", "tri/ray", "nodes/ray", "PSNR dB"
    );
    println!("(nodes of the 4-wide BVH, four box tests each)");
    let mut rows = Vec::new();
    for name in &names {
        let builtin = nephele_pathtracer::scenes::load(name)?;
        let (eye, target, fov_y) = builtin.default_view();
        let background = builtin.default_background();
        let triangles = builtin.scene.triangle_count();
        let camera = Camera::look_at(width, height, fov_y, eye, target, Vec3::Z)?;
        let build_start = Instant::now();
        let renderer = Renderer::new(builtin.scene)?;
        let build_ms = build_start.elapsed().as_secs_f64() * 1e3;
        let timed_options = RenderOptions { samples_per_pixel: args.spp, background, seed: 1, ..Default::default() };
        let bar = progress.bar(u64::from(height), name, "rows");
        let start = Instant::now();
        let timed = renderer.render(&camera, &timed_options, &|r| bar.inc(u64::from(r)))?;
        let seconds = start.elapsed().as_secs_f64();
        bar.finish_and_clear();
        let bar = progress.bar(u64::from(height), &format!("{name} reference"), "rows");
        let converged = renderer.render(
            &camera,
            &RenderOptions { samples_per_pixel: args.reference_spp, seed: 2, ..timed_options },
            &|r| bar.inc(u64::from(r)),
        )?;
        bar.finish_and_clear();
        let psnr = metrics::psnr(&timed.to_rgba(Aov::Color), &converged.to_rgba(Aov::Color), [1.0; 3])
            .context("measuring the error")?;
        let stats = timed.stats;
        let rays = stats.traversal.rays.max(1) as f64;
        let row = json!({
            "scene": name,
            "triangles": triangles,
            "bvh_build_ms": build_ms,
            "samples_per_second": stats.samples as f64 / seconds,
            "rays_per_second": rays / seconds,
            "triangle_tests_per_ray": stats.traversal.triangle_tests as f64 / rays,
            "node_visits_per_ray": stats.traversal.node_visits as f64 / rays,
            "rays_per_sample": rays / stats.samples.max(1) as f64,
            "psnr_vs_reference_db": psnr,
        });
        println!(
            "{:<11} {:>9} {:>9.1} {:>11.0} {:>11.0} {:>10.1} {:>10.1} {:>9.2}",
            name,
            triangles,
            build_ms,
            stats.samples as f64 / seconds,
            rays / seconds,
            stats.traversal.triangle_tests as f64 / rays,
            stats.traversal.node_visits as f64 / rays,
            psnr
        );
        rows.push(row);
    }
    if let Some(path) = args.json {
        std::fs::write(&path, serde_json::to_string_pretty(&rows)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
