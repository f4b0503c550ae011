//! `nephele bench psh | cubes | psh-cache`: figures of the i-NOLF building blocks
//! (perfect spatial hashing, density texture cubes, cache behaviour of the PSH encoding
//! against the multiresolution hash grid).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_kernels::inolf::cubes::{CubeOptions, DensityCubes};
use nephele_kernels::inolf::encoding::PshEncoding;
use nephele_kernels::inolf::psh::{PshOptions, PshTable};
use nephele_kernels::kernel::{Bounds, all_pixels};
use nephele_nn::{HashGrid, HashGridConfig, SimdMode};
use nephele_pathtracer::scenes;
use nephele_pathtracer::voxel::{VoxelBits, VoxelGrid, surface_bits};
use serde_json::json;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct PshArgs {
    /// Voxel grid sides to hash (surface voxels of each scene at that resolution).
    #[arg(long, value_delimiter = ',', default_value = "128,256,512")]
    resolutions: Vec<u32>,
    /// Scenes to run (default: all built-in scenes).
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct CubesArgs {
    /// Coarse cells along the longest side of the scene box.
    #[arg(long, default_value_t = 64)]
    resolution: u32,
    /// Samples per cube side.
    #[arg(long, default_value_t = 8)]
    cube_res: u32,
    /// Image size of the marched view (the scene's default view).
    #[arg(long, default_value = "400x400", value_parser = nephele_geometry::camera::parse_size)]
    size: (u32, u32),
    /// Scenes to run (default: all built-in scenes).
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CacheEncoding {
    /// Single-resolution perfect spatial hash, trilinear over stored corners.
    Psh,
    /// Multiresolution hash grid (i-NGP: 16 levels, 2^19 entries, 2 features each).
    Hashgrid,
    /// Build the query stream only (subtract its cost from the other two).
    None,
}

#[derive(Debug, clap::Args)]
pub struct PshCacheArgs {
    /// Which encoding answers the query stream.
    #[arg(long, value_enum)]
    encoding: CacheEncoding,
    /// Scene whose surface the queries lie on.
    #[arg(long, default_value = "glossy")]
    scene: String,
    /// Number of queries (hit points from random viewpoints).
    #[arg(long, default_value_t = 200_000)]
    queries: usize,
    /// PSH lattice side (the occupied lattice points are the corners around the hit points).
    #[arg(long, default_value_t = 256)]
    lattice: u32,
    /// Features per PSH slot.
    #[arg(long, default_value_t = 16)]
    features: u32,
    /// Passes over the query stream: run with 1 and 3 and divide the difference of the
    /// counts by 2 x queries to get the cost of a query alone, without the set-up.
    #[arg(long, default_value_t = 1)]
    passes: u32,
}

#[derive(Debug, clap::Args)]
pub struct InolfArgs {
    /// Baked i-NOLF assets (`nephele bake`), all baked from the radiance field `--field`.
    /// The first gives the ablation rows of NEPHELE table 5 (hit point from the density
    /// network, then from the density cubes; diffuse MLP, then diffuse cubes); each further
    /// one (another `--psh-res`, say) adds one row. Repeat the flag or separate with commas.
    #[arg(long, required = true, value_delimiter = ',')]
    asset: Vec<PathBuf>,
    /// The radiance field the assets were baked from (`nephele bake --save-field`): the
    /// i-NGP-style baseline, rendered in the same run, and the density network of the
    /// "i-NOLF base" row.
    #[arg(long)]
    field: PathBuf,
    /// Dataset folder whose held-out split is rendered and scored.
    #[arg(long)]
    dataset: PathBuf,
    #[arg(long, default_value = "test")]
    split: String,
    #[arg(long, default_value_t = 2)]
    downscale: u32,
    /// Score at most this many views.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Score only every Nth view of the split: the views `nephele bake --holdout-every N`
    /// left out (for datasets with no test split, such as the shared lego); 0 = all.
    #[arg(long, default_value_t = 0)]
    holdout_every: usize,
    /// The distance curve (NEPHELE fig. 14): the first view's camera moved along its line to
    /// the object's centre, at these multiples of its distance; frame time of the baseline
    /// and of i-NOLF at each, comma-separated. `none` (or an empty string) skips it.
    #[arg(long, value_parser = parse_factors, default_value = "3,2,1.5,1,0.75,0.5")]
    distances: Factors,
    /// Also time one large frame (3840x2160 is 4K) of the first view's camera moved to
    /// `--large-distance` (the object filling the screen), baseline against i-NOLF: the ray
    /// count of NEPHELE's 4K figure. The baseline takes minutes on a CPU.
    #[arg(long, value_parser = nephele_geometry::camera::parse_size, value_name = "WxH")]
    large_frame: Option<(u32, u32)>,
    /// Multiple of the first view's distance for `--large-frame`.
    #[arg(long, default_value = "0.5", value_parser = parse_factor)]
    large_distance: f32,
    /// Instruction set of the kernels: auto (AVX2+FMA where the CPU has them), off (scalar),
    /// or both (every row as auto, plus the baseline and the main i-NOLF row again in scalar
    /// code, so the SIMD speed-up is measured in this run).
    #[arg(long, value_enum, default_value = "both")]
    simd: SimdChoice,
    /// Also run the main i-NOLF row on a GPU: gpu (a hardware GPU, else a software Vulkan
    /// adapter, labelled as such), auto (a hardware GPU if there is one) or cpu (no GPU row).
    #[arg(long, default_value = "cpu", value_name = "cpu|auto|gpu")]
    device: nephele_gpu::DeviceChoice,
    /// NeLF assets distilled from `--field` (`nephele distill`): one row each, with the
    /// FLOPs per ray of its network. Repeat the flag or separate with commas.
    #[arg(long, value_delimiter = ',')]
    nelf: Vec<PathBuf>,
}

/// `bench inolf --simd`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimdChoice {
    Auto,
    Off,
    Both,
}

/// Positive distance factors (`--distances`); empty for `none` or "".
#[derive(Debug, Clone)]
pub struct Factors(Vec<f32>);

fn parse_factors(text: &str) -> Result<Factors, String> {
    let text = text.trim();
    if text.is_empty() || text.eq_ignore_ascii_case("none") {
        return Ok(Factors(Vec::new()));
    }
    text.split(',').map(parse_factor).collect::<Result<Vec<_>, _>>().map(Factors)
}

/// One positive, finite distance factor.
fn parse_factor(text: &str) -> Result<f32, String> {
    match text.trim().parse::<f32>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("'{}' is not a positive distance factor", text.trim())),
    }
}

fn scene_names(requested: &[String]) -> Vec<String> {
    if requested.is_empty() { scenes::names().iter().map(|s| s.to_string()).collect() } else { requested.to_vec() }
}

pub fn psh(args: PshArgs, progress: &dyn Progress) -> Result<()> {
    println!(
        "perfect spatial hashing of surface voxels: paper settings (table factor 1.05, sigma 1/6) and i-NOLF's coherent settings (1.5, 1)"
    );
    println!(
        "{:<11} {:>5} {:>9} {:<8} {:>4} {:>4} {:>10} {:>8} {:>9} {:>8} {:>9} {:>10}",
        "scene",
        "res",
        "voxels",
        "settings",
        "m",
        "r",
        "table KiB",
        "B/voxel",
        "build ms",
        "attempts",
        "coherence",
        "collisions"
    );
    let names = scene_names(&args.scenes);
    let bar = progress.bar((names.len() * args.resolutions.len()) as u64, "psh", "builds");
    let mut rows = Vec::new();
    for name in &names {
        let builtin = nephele_pathtracer::scenes::load(name)?;
        let (lo, hi) = builtin.scene.bounds().context("scene has no geometry")?;
        for &res in &args.resolutions {
            let grid = VoxelGrid::around(lo, hi, res);
            let points = surface_bits(&builtin.scene.mesh, &grid).points();
            for (label, options) in [("paper", PshOptions::default()), ("coherent", PshOptions::coherent())] {
                let start = Instant::now();
                let (table, stats) = PshTable::build(res, &points, &options)?;
                let build_ms = start.elapsed().as_secs_f64() * 1e3;
                let collisions = count_collisions(&table, &points);
                let (coherent, pairs) = table.coherence();
                let coherence = coherent as f64 / pairs.max(1) as f64;
                let bytes = table.table_bytes();
                println!(
                    "{:<11} {:>5} {:>9} {:<8} {:>4} {:>4} {:>10.1} {:>8.2} {:>9.1} {:>8} {:>9.3} {:>10}",
                    name,
                    res,
                    points.len(),
                    label,
                    table.table_side(),
                    table.offset_side(),
                    bytes as f64 / 1024.0,
                    bytes as f64 / points.len().max(1) as f64,
                    build_ms,
                    stats.attempts,
                    coherence,
                    collisions
                );
                if collisions != 0 {
                    bail!("{name} at {res}^3: {collisions} collisions");
                }
                rows.push(json!({"scene": name, "resolution": res, "voxels": points.len(), "settings": label,
                    "m": table.table_side(), "r": table.offset_side(), "table_bytes": bytes, "build_ms": build_ms,
                    "attempts": stats.attempts, "coherence": coherence, "collisions": collisions}));
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    write_json(args.json, rows)
}

/// Occupied voxels that are not found or share a slot (0 for a perfect hash).
fn count_collisions(table: &PshTable, points: &[[u32; 3]]) -> usize {
    let mut seen = vec![false; table.slot_count()];
    let mut bad = 0;
    for &p in points {
        match table.slot(p) {
            Some(s) if !seen[s as usize] => seen[s as usize] = true,
            _ => bad += 1,
        }
    }
    bad
}

/// A density field standing in for a trained one: opaque inside the surface voxels of the
/// mesh at the cubes' sample resolution.
fn surface_density(bits: &VoxelBits) -> impl Fn(&[Vec3], &mut [f32]) + Sync + '_ {
    move |points: &[Vec3], out: &mut [f32]| {
        for (p, o) in points.iter().zip(out) {
            *o = if bits.contains(*p) { 1000.0 } else { 0.0 };
        }
    }
}

fn scene_cubes(name: &str, resolution: u32, cube_res: u32) -> Result<(DensityCubes, scenes::BuiltinScene, f64)> {
    let builtin = nephele_pathtracer::scenes::load(name)?;
    let (lo, hi) = builtin.scene.bounds().context("scene has no geometry")?;
    let margin = Vec3::splat((hi - lo).max_element() * 0.01);
    let bounds = Bounds { min: lo - margin, max: hi + margin };
    let fine = resolution * (cube_res - 1);
    let bits = surface_bits(&builtin.scene.mesh, &VoxelGrid::around(bounds.min, bounds.max, fine));
    let start = Instant::now();
    let options = CubeOptions { resolution, cube_res, ..CubeOptions::default() };
    let cubes = DensityCubes::build(bounds, &options, surface_density(&bits), &|_| {})?;
    Ok((cubes, builtin, start.elapsed().as_secs_f64()))
}

pub fn cubes(args: CubesArgs, progress: &dyn Progress) -> Result<()> {
    let (width, height) = args.size;
    println!(
        "density cubes {}^3 coarse x {}^3 samples (u8) over each scene's surface voxels; marching the default view at {width}x{height}, one thread",
        args.resolution, args.cube_res
    );
    println!(
        "{:<11} {:>8} {:>8} {:>10} {:>11} {:>7} {:>8} {:>6} {:>9} {:>11} {:>11} {:>9} {:>9} {:>9}",
        "scene",
        "cells",
        "cubes",
        "cubes MiB",
        "dense MiB",
        "ratio",
        "build s",
        "hit %",
        "cells/ray",
        "samples/ray",
        "lookups/ray",
        "dense/ray",
        "ns/ray",
        "ns/miss"
    );
    let names = scene_names(&args.scenes);
    let bar = progress.bar(names.len() as u64, "cubes", "scenes");
    let mut rows = Vec::new();
    for name in &names {
        let (cubes, builtin, build_s) = scene_cubes(name, args.resolution, args.cube_res)?;
        let fp = cubes.cubes().footprint();
        let (eye, target, fov_y) = builtin.default_view();
        let camera = Camera::look_at(width, height, fov_y, eye, target, Vec3::Z)?;
        let rays: Vec<_> = all_pixels(&camera).iter().map(|&p| camera.pixel_center_ray(p % width, p / width)).collect();
        let start = Instant::now();
        let hits: Vec<_> = rays.iter().map(|r| cubes.march(r.origin, r.direction, 1e-3, f32::INFINITY)).collect();
        let total_ns = start.elapsed().as_secs_f64() * 1e9;
        let missing: Vec<_> = rays.iter().zip(&hits).filter(|(_, h)| h.samples == 0).map(|(r, _)| *r).collect();
        let start = Instant::now();
        for r in &missing {
            std::hint::black_box(cubes.march(r.origin, r.direction, 1e-3, f32::INFINITY));
        }
        let miss_ns = start.elapsed().as_secs_f64() * 1e9 / missing.len().max(1) as f64;
        let n = rays.len() as f64;
        let hit_pct = 100.0 * hits.iter().filter(|h| h.opacity > 0.5).count() as f64 / n;
        let cells = hits.iter().map(|h| f64::from(h.cells)).sum::<f64>() / n;
        let samples = hits.iter().map(|h| f64::from(h.samples)).sum::<f64>() / n;
        let lookups = hits.iter().map(|h| f64::from(h.lookups)).sum::<f64>() / n;
        let dense = rays.iter().map(|r| dense_samples(&cubes, r.origin, r.direction)).sum::<f64>() / n;
        let mib = |b: u64| b as f64 / (1 << 20) as f64;
        println!(
            "{:<11} {:>8} {:>8} {:>10.2} {:>11.2} {:>7.1} {:>8.2} {:>6.1} {:>9.1} {:>11.1} {:>11.1} {:>9.1} {:>9.0} {:>9.0}",
            name,
            fp.cells,
            fp.occupied_cells,
            mib(fp.bytes),
            mib(fp.dense_bytes),
            fp.dense_bytes as f64 / fp.bytes.max(1) as f64,
            build_s,
            hit_pct,
            cells,
            samples,
            lookups,
            dense,
            total_ns / n,
            miss_ns
        );
        rows.push(json!({"scene": name, "cells": fp.cells, "cubes": fp.occupied_cells, "bytes": fp.bytes, "dense_bytes": fp.dense_bytes,
            "build_s": build_s, "hit_fraction": hit_pct / 100.0, "cells_per_ray": cells, "samples_per_ray": samples, "lookups_per_ray": lookups,
            "dense_samples_per_ray": dense, "ns_per_ray": total_ns / n, "ns_per_miss": miss_ns}));
        bar.inc(1);
    }
    bar.finish_and_clear();
    write_json(args.json, rows)
}

/// Samples a uniform marcher at the cubes' step would take through the whole box.
fn dense_samples(cubes: &DensityCubes, o: Vec3, d: Vec3) -> f64 {
    let b = cubes.bounds();
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for a in 0..3 {
        if d[a] == 0.0 {
            if o[a] < b.min[a] || o[a] > b.max[a] {
                return 0.0;
            }
        } else {
            let (ta, tb) = ((b.min[a] - o[a]) / d[a], (b.max[a] - o[a]) / d[a]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    f64::from((t1 - t0).max(0.0) / cubes.cubes().sample_step())
}

pub fn psh_cache(args: PshCacheArgs, progress: &dyn Progress) -> Result<()> {
    let bar = progress.bar(3, "query stream", "steps");
    let (cubes, builtin, _) = scene_cubes(&args.scene, 48, 8)?;
    bar.inc(1);
    // Hit points of rays from random viewpoints around the object (deterministic).
    let bounds = cubes.bounds();
    let (center, radius) = (bounds.center(), 0.5 * bounds.size().length());
    let mut state = 0x1234_5678_9abc_def0u64;
    let mut next = move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut stream = Vec::with_capacity(args.queries);
    let per_view = 4096;
    let mut views = 0;
    while stream.len() < args.queries && views < 100_000 {
        views += 1;
        let (zc, phi) = (2.0 * next() - 1.0, std::f32::consts::TAU * next());
        let dir = Vec3::new((1.0 - zc * zc).sqrt() * phi.cos(), (1.0 - zc * zc).sqrt() * phi.sin(), zc);
        let eye = center + dir * radius * 2.5;
        let up = if dir.z.abs() > 0.99 { Vec3::X } else { Vec3::Z };
        let camera = Camera::look_at(64, 64, 0.8, eye, center, up)?;
        for _ in 0..per_view {
            let ray = camera.ray(64.0 * next(), 64.0 * next());
            let h = cubes.march(ray.origin, ray.direction, 1e-3, f32::INFINITY);
            if h.opacity > 0.5 && stream.len() < args.queries {
                stream.push(ray.at(h.t));
            }
        }
    }
    bar.inc(1);
    let _ = builtin;
    let voxel = bounds.size().max_element() / (args.lattice - 1) as f32;
    let mut checksum = 0.0f64;
    let (name, bytes) = match args.encoding {
        CacheEncoding::None => ("none", 0usize),
        CacheEncoding::Psh => {
            let enc = PshEncoding::from_points(
                &stream,
                bounds.min,
                voxel,
                args.lattice,
                args.features,
                &PshOptions::coherent(),
            )?;
            bar.inc(1);
            let mut out = vec![0.0; enc.dim()];
            for _ in 0..args.passes {
                for p in &stream {
                    enc.encode(*p, &mut out);
                    checksum += f64::from(out[0]);
                }
            }
            ("psh", enc.features.len() * 4 + enc.table.table_bytes())
        }
        CacheEncoding::Hashgrid => {
            let config = HashGridConfig::with_finest_resolution(16, 19, 16, 2048);
            let grid = HashGrid::new(config, 7)?;
            bar.inc(1);
            let mut out = vec![0.0; grid.output_dim()];
            let inv = 1.0 / bounds.size().max_element();
            for _ in 0..args.passes {
                for p in &stream {
                    let u = (*p - bounds.min) * inv;
                    grid.encode([u.x, u.y, u.z], &mut out);
                    checksum += f64::from(out[0]);
                }
            }
            ("hashgrid", grid.num_params() * 4)
        }
    };
    bar.finish_and_clear();
    println!(
        "encoding {name}: {} queries on {} ({views} views), table {:.2} MiB, checksum {checksum:.6}",
        stream.len(),
        args.scene,
        bytes as f64 / (1 << 20) as f64
    );
    Ok(())
}

fn write_json(path: Option<PathBuf>, rows: Vec<serde_json::Value>) -> Result<()> {
    if let Some(path) = path {
        std::fs::write(&path, serde_json::to_string_pretty(&rows)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// One row of the table: a kernel and the bytes of the parts it reads.
struct Variant {
    name: String,
    kernel: Box<dyn nephele_kernels::kernel::RayKernel>,
    model_bytes: u64,
}

/// The first view's camera moved along its line to the object's centre by `factor`, at
/// `width x height` with the same horizontal field of view.
fn moved_camera(
    data: &nephele_train::dataset::Dataset,
    view: usize,
    centre: Vec3,
    factor: f32,
    width: u32,
    height: u32,
) -> Result<(Camera, f32)> {
    anyhow::ensure!(factor.is_finite() && factor > 0.0, "{factor} is not a positive distance factor");
    let mut c2w = data.views[view].camera_to_world;
    let eye = c2w.w_axis.truncate();
    let moved = centre + (eye - centre) * factor;
    c2w.w_axis = moved.extend(1.0);
    Ok((Camera::from_fov_x(width, height, data.camera_angle_x, c2w)?, (moved - centre).length()))
}

/// i-NOLF against the i-NGP-style baseline on held-out views: PSNR/SSIM against the images
/// (over white, as NeRF papers), time per frame, rays per second and memory, measured in
/// one run; the ablation rows of NEPHELE table 5.
pub fn inolf(args: InolfArgs, progress: &dyn Progress) -> Result<()> {
    use nephele_imaging::metrics::psnr_and_ssim;
    use nephele_kernels::inolf::kernel::{DiffuseSource, InolfKernel};
    use nephele_kernels::kernel::frame_to_image;
    use nephele_kernels::ngp::NgpKernel;

    let mut data = nephele_train::dataset::load_split(&args.dataset, &args.split, args.downscale)?;
    if args.holdout_every > 1 {
        data.views = nephele_train::dataset::split_holdout(std::mem::take(&mut data.views), args.holdout_every).1;
        anyhow::ensure!(!data.views.is_empty(), "no view left out by --holdout-every {}", args.holdout_every);
    }
    data.views.truncate(args.views.max(1));
    let simd = if args.simd == SimdChoice::Off { SimdMode::Off } else { SimdMode::Auto };
    let mut ngp = NgpKernel::load(&args.field).with_context(|| format!("loading {}", args.field.display()))?;
    ngp.set_simd(simd);
    let bounds = ngp.field().bounds();
    let centre = 0.5 * (bounds.min + bounds.max);
    let field_bytes = ngp.field().memory_bytes();
    // The "i-NOLF base" row's density network (the first asset's); the baseline keeps `ngp`.
    let mut base_field = Some(ngp.field().clone());
    let gpu_context = nephele_gpu::GpuContext::open(args.device)?;
    let gpu_baseline = match &gpu_context {
        Some(ctx) => Some(nephele_gpu::GpuNgpKernel::new(ctx.clone(), &ngp)?),
        None => None,
    };
    let mut gpu_base_row = None;
    let mut variants = vec![Variant { name: "i-NGP baseline".into(), kernel: Box::new(ngp), model_bytes: field_bytes }];
    let mut main_inolf = 0;
    let mut main_work = None;
    let mut gpu_row = None;
    // Rows run in scalar code for `--simd both`, and the rows they repeat.
    let mut scalar_rows = Vec::new();
    if let Some(gpu) = gpu_baseline {
        gpu_base_row = Some(variants.len());
        let model_bytes = gpu.device_bytes();
        variants.push(Variant { name: "i-NGP baseline, GPU".into(), kernel: Box::new(gpu), model_bytes });
    }
    if args.simd == SimdChoice::Both {
        let mut scalar = NgpKernel::load(&args.field).with_context(|| format!("loading {}", args.field.display()))?;
        scalar.set_simd(SimdMode::Off);
        scalar_rows.push(variants.len());
        variants.push(Variant {
            name: "i-NGP baseline, scalar".into(),
            kernel: Box::new(scalar),
            model_bytes: field_bytes,
        });
    }
    for (i, path) in args.asset.iter().enumerate() {
        let mut cubes = InolfKernel::load(path).with_context(|| format!("loading {}", path.display()))?;
        cubes.set_simd(simd);
        let psh = cubes.psh().table.domain();
        let mut network = cubes.clone();
        let has_network = network.set_diffuse_source(DiffuseSource::Network).is_ok();
        cubes
            .set_diffuse_source(DiffuseSource::Cubes)
            .with_context(|| format!("{}: no diffuse cubes", path.display()))?;
        let variant = |name: String, kernel: InolfKernel| {
            let model_bytes = kernel.memory().in_use;
            Variant { name, kernel: Box::new(kernel), model_bytes }
        };
        if i == 0 {
            let mut base = if has_network { network.clone() } else { cubes.clone() };
            if let Some(field) = base_field.take() {
                base.use_density_network(field);
            }
            let diffuse = if has_network { "diffuse MLP" } else { "diffuse cubes" };
            variants.push(variant(format!("i-NOLF base (density network, {diffuse}, PSH {psh}^3)"), base));
            if has_network {
                variants.push(variant(format!("+ density cubes (diffuse MLP, PSH {psh}^3)"), network));
            }
            main_inolf = variants.len();
            let cameras = data
                .views
                .iter()
                .map(|v| Camera::from_fov_x(v.image.width(), v.image.height(), data.camera_angle_x, v.camera_to_world))
                .collect::<Result<Vec<_>, _>>()?;
            main_work = Some(FrameWork::count(&cubes, &cameras));
            let scalar = (args.simd == SimdChoice::Both).then(|| {
                let mut scalar = cubes.clone();
                scalar.set_simd(SimdMode::Off);
                scalar
            });
            let gpu = match &gpu_context {
                Some(ctx) => Some(nephele_gpu::GpuInolfKernel::new(ctx.clone(), &cubes)?),
                None => None,
            };
            variants.push(variant(format!("+ diffuse cubes (PSH {psh}^3)"), cubes));
            if let Some(scalar) = scalar {
                scalar_rows.push(variants.len());
                variants.push(variant(format!("+ diffuse cubes (PSH {psh}^3), scalar"), scalar));
            }
            if let Some(gpu) = gpu {
                gpu_row = Some(variants.len());
                let model_bytes = gpu.device_bytes();
                let name = format!("+ diffuse cubes (PSH {psh}^3), GPU");
                variants.push(Variant { name, kernel: Box::new(gpu), model_bytes });
            }
        } else {
            let file = path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
            variants.push(variant(format!("+ diffuse cubes (PSH {psh}^3, {file})"), cubes));
        }
    }
    // NeLF rows: (row, FLOPs per network query).
    let mut nelf_rows = Vec::new();
    for path in &args.nelf {
        let mut kernel =
            nephele_kernels::nelf::NelfKernel::load(path).with_context(|| format!("loading {}", path.display()))?;
        kernel.set_simd(simd);
        let model = kernel.model();
        let (net, sampling) = (model.header.network, model.header.sampling);
        let file = path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let name = format!(
            "NeLF W{} D{} (K={}, L={}, {file})",
            net.width,
            net.layers(),
            sampling.points,
            sampling.frequencies
        );
        nelf_rows.push((variants.len(), model.flops_per_ray()));
        let model_bytes = model.model_bytes() as u64;
        variants.push(Variant { name, kernel: Box::new(kernel), model_bytes });
    }
    let views = &data.views;
    let bar = progress.bar((views.len() * variants.len()) as u64, "rendering", "frames");
    struct Row {
        psnr: f64,
        ssim: f64,
        ms: f64,
        rays_per_s: f64,
        queries_per_ray: f64,
        runtime_bytes: Option<usize>,
    }
    let mut rows = Vec::new();
    for variant in &variants {
        let (mut seconds, mut rays, mut queries, mut psnr, mut ssim, mut runtime_bytes) =
            (0.0f64, 0u64, 0u64, 0.0f64, 0.0f64, None::<usize>);
        for v in views {
            let (w, h) = (v.image.width(), v.image.height());
            let camera = Camera::from_fov_x(w, h, data.camera_angle_x, v.camera_to_world)?;
            let pixels = all_pixels(&camera);
            crate::heap::reset_peak();
            let start = Instant::now();
            let (out, stats) = variant.kernel.render_pixels(&camera, &pixels)?;
            seconds += start.elapsed().as_secs_f64();
            runtime_bytes = runtime_bytes.max(crate::heap::peak());
            rays += stats.rays;
            queries += stats.queries;
            let image = frame_to_image(w, h, &out).context("frame")?;
            let (p, s) = psnr_and_ssim(&image, &v.image, [1.0; 3])?;
            psnr += p;
            ssim += s;
            bar.inc(1);
        }
        let n = views.len() as f64;
        rows.push(Row {
            psnr: psnr / n,
            ssim: ssim / n,
            ms: 1e3 * seconds / n,
            rays_per_s: rays as f64 / seconds.max(1e-9),
            queries_per_ray: queries as f64 / rays.max(1) as f64,
            runtime_bytes,
        });
    }
    bar.finish_and_clear();
    let base_ms = rows[0].ms;
    let (w, h) = (views[0].image.width(), views[0].image.height());
    let mib = |b: f64| b / 1048576.0;
    println!(
        "{} held-out views of {w}x{h}, {} threads, SIMD: {} (rows marked scalar: the same code one lane wide)",
        views.len(),
        rayon::current_num_threads(),
        simd.describe()
    );
    println!(
        "model MiB: the parts the kernel reads; runtime MiB: most extra heap in use at once during a frame (outputs included{})",
        if crate::heap::peak().is_some() { "" } else { "; '-': measured only by a build with --features heap-peak" }
    );
    println!(
        "{:<58} {:>8} {:>7} {:>10} {:>12} {:>10} {:>12} {:>11} {:>9}",
        "kernel", "PSNR dB", "SSIM", "model MiB", "runtime MiB", "ms/frame", "rays/s", "queries/ray", "speed-up"
    );
    for (variant, r) in variants.iter().zip(&rows) {
        println!(
            "{:<58} {:>8.2} {:>7.4} {:>10.2} {:>12} {:>10.1} {:>12.0} {:>11.2} {:>8.1}x",
            variant.name,
            r.psnr,
            r.ssim,
            mib(variant.model_bytes as f64),
            r.runtime_bytes.map_or("-".to_string(), |b| format!("{:.2}", mib(b as f64))),
            r.ms,
            r.rays_per_s,
            r.queries_per_ray,
            base_ms / r.ms.max(1e-9)
        );
    }
    if let [base_scalar, inolf_scalar] = scalar_rows[..] {
        println!(
            "SIMD speed-up in this run ({} over scalar): i-NGP baseline {:.2}x, i-NOLF {:.2}x",
            simd.describe(),
            rows[base_scalar].ms / rows[0].ms.max(1e-9),
            rows[inolf_scalar].ms / rows[main_inolf].ms.max(1e-9)
        );
    }
    if let (Some(row), Some(ctx)) = (gpu_row, &gpu_context) {
        let software =
            if ctx.is_software() { ": a software adapter on this machine's CPU cores, not a GPU figure" } else { "" };
        println!("GPU row on {}{software}", ctx.label());
        println!("GPU over CPU (SIMD) i-NOLF in this run: {:.2}x", rows[main_inolf].ms / rows[row].ms.max(1e-9));
        if let Some(base) = gpu_base_row {
            println!(
                "GPU over CPU (SIMD) i-NGP baseline in this run: {:.2}x; on the GPU, i-NOLF over the baseline: {:.1}x",
                rows[0].ms / rows[base].ms.max(1e-9),
                rows[base].ms / rows[row].ms.max(1e-9)
            );
        }
        let pairs = [(main_inolf, Some(row), "i-NOLF"), (0, gpu_base_row, "i-NGP baseline")];
        for (cpu_row, gpu_row, name) in pairs {
            let Some(gpu_row) = gpu_row else { continue };
            let mut agreement = nephele_gpu::Agreement::default();
            for v in views {
                let (w, h) = (v.image.width(), v.image.height());
                let camera = Camera::from_fov_x(w, h, data.camera_angle_x, v.camera_to_world)?;
                let pixels = all_pixels(&camera);
                let (cpu, _) = variants[cpu_row].kernel.render_pixels(&camera, &pixels)?;
                let (gpu, _) = variants[gpu_row].kernel.render_pixels(&camera, &pixels)?;
                agreement.merge(&nephele_gpu::Agreement::of(&cpu, &gpu));
            }
            println!("GPU against CPU {name}: {agreement}");
        }
    }
    for &(row, flops) in &nelf_rows {
        println!(
            "{}: {flops} FLOPs per network query (weights and biases; the encoding not counted), {:.0} per ray of these frames",
            variants[row].name,
            flops as f64 * rows[row].queries_per_ray
        );
    }
    for path in args.asset.iter().chain(&args.nelf) {
        let file = std::fs::metadata(path)?.len();
        println!("asset {}: {:.2} MiB on disk", path.display(), mib(file as f64));
    }

    let inolf = &variants[main_inolf];
    if let Some(work) = &main_work {
        work.print(rows[main_inolf].ms);
    }
    // Distance curve: one camera, moved towards the object's centre.
    if !args.distances.0.is_empty() {
        println!();
        println!("distance curve: the first view's camera moved towards the object's centre, {w}x{h}, {}", inolf.name);
        println!(
            "{:>8} {:>9} {:>9} {:>14} {:>14} {:>9}",
            "factor", "distance", "covered", "baseline ms", "i-NOLF ms", "speed-up"
        );
        for &factor in &args.distances.0 {
            let (camera, distance) = moved_camera(&data, 0, centre, factor, w, h).context("--distances")?;
            let (base_ms, _) = time_frame(variants[0].kernel.as_ref(), &camera)?;
            let (inolf_ms, covered) = time_frame(inolf.kernel.as_ref(), &camera)?;
            println!(
                "{factor:>8.2} {distance:>9.3} {:>8.1}% {base_ms:>14.1} {inolf_ms:>14.1} {:>8.1}x",
                100.0 * covered,
                base_ms / inolf_ms.max(1e-9)
            );
        }
    }
    if let Some((lw, lh)) = args.large_frame {
        let (camera, distance) =
            moved_camera(&data, 0, centre, args.large_distance, lw, lh).context("--large-distance")?;
        println!();
        println!(
            "large frame: {lw}x{lh} ({:.2} M rays), the first view's camera at {}x its distance ({distance:.3}), {}",
            f64::from(lw) * f64::from(lh) / 1e6,
            args.large_distance,
            inolf.name
        );
        let bar = progress.bar(2, "large frame", "frames");
        let (base_ms, _) = time_frame(variants[0].kernel.as_ref(), &camera)?;
        bar.inc(1);
        let (inolf_ms, covered) = time_frame(inolf.kernel.as_ref(), &camera)?;
        bar.finish_and_clear();
        let rays = f64::from(lw) * f64::from(lh);
        println!(
            "{:>9} {:>14} {:>14} {:>16} {:>16} {:>9}",
            "covered", "baseline ms", "i-NOLF ms", "baseline rays/s", "i-NOLF rays/s", "speed-up"
        );
        println!(
            "{:>8.1}% {base_ms:>14.1} {inolf_ms:>14.1} {:>16.0} {:>16.0} {:>8.1}x",
            100.0 * covered,
            rays / (base_ms / 1e3).max(1e-9),
            rays / (inolf_ms / 1e3).max(1e-9),
            base_ms / inolf_ms.max(1e-9)
        );
    }
    Ok(())
}

/// The i-NOLF kernel's work on a set of frames, counted, and the floor it implies on this
/// machine: the least cycles each unit of work needs (loads at two per cycle, eight-wide
/// FMA at two per cycle), summed, over the core clock and the threads.
struct FrameWork {
    cells: u64,
    samples: u64,
    lookups: u64,
    hits: u64,
    rays: u64,
    frames: usize,
    macs: f64,
    psh_dim: f64,
}

impl FrameWork {
    fn count(kernel: &nephele_kernels::inolf::kernel::InolfKernel, cameras: &[Camera]) -> FrameWork {
        use nephele_kernels::inolf::kernel::{HIT_OPACITY, RAY_NEAR};
        let mut w = FrameWork {
            cells: 0,
            samples: 0,
            lookups: 0,
            hits: 0,
            rays: 0,
            frames: cameras.len(),
            macs: kernel.specular_macs() as f64,
            psh_dim: kernel.psh().dim() as f64,
        };
        for camera in cameras {
            for p in all_pixels(camera) {
                let ray = camera.pixel_center_ray(p % camera.width(), p / camera.width());
                let m = kernel.density().march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY);
                w.cells += u64::from(m.cells);
                w.samples += u64::from(m.samples);
                w.lookups += u64::from(m.lookups);
                w.hits += u64::from(m.opacity >= HIT_OPACITY);
                w.rays += 1;
            }
        }
        w
    }

    fn print(&self, measured_ms: f64) {
        let n = self.rays.max(1) as f64;
        let frames = self.frames.max(1) as f64;
        let (macs, psh_dim) = (self.macs, self.psh_dim);
        // Least cycles per unit of work (see BENCHMARKS.md): a coarse cell is an index load
        // and a compare (1); an empty sample a bit test (1); a lookup 16 loads (8 corner
        // bytes, 8 table entries) at two per cycle (8); a hit ray 8 PSH corners (two table
        // loads and `psh_dim` features each), 8 diffuse corners of 6 bytes, and the MLP at
        // 16 MACs/cycle.
        let hit_cycles = 8.0 * (2.0 + psh_dim) / 2.0 + 8.0 * 6.0 / 2.0 + macs / 16.0;
        let cycles = self.cells as f64
            + (self.samples - self.lookups) as f64
            + 8.0 * self.lookups as f64
            + hit_cycles * self.hits as f64;
        let ghz = cpu_ghz().unwrap_or(2.5);
        let threads = rayon::current_num_threads() as f64;
        let floor_ms = cycles / frames / (ghz * 1e9 * threads) * 1e3;
        println!();
        println!("work per ray of the main i-NOLF row, averaged over the {} views:", self.frames);
        println!(
            "  cells {:.2}, samples {:.2}, lookups {:.2} (samples in voxels with matter), hit rays {:.1} %",
            self.cells as f64 / n,
            self.samples as f64 / n,
            self.lookups as f64 / n,
            100.0 * self.hits as f64 / n
        );
        println!(
            "  per hit ray: specular MLP {macs:.0} MACs, 8 PSH corners of {psh_dim:.0} features, 8 diffuse corners of 6 bytes"
        );
        println!(
            "  floor at {ghz:.2} GHz x {threads:.0} threads: {:.0} cycles per frame = {floor_ms:.2} ms; measured {measured_ms:.2} ms ({:.1}x the floor)",
            cycles / frames,
            measured_ms / floor_ms.max(1e-9)
        );
    }
}

/// The core clock from `/proc/cpuinfo` (Linux), GHz.
fn cpu_ghz() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("cpu MHz"))?;
    let mhz: f64 = line.split(':').nth(1)?.trim().parse().ok()?;
    (mhz > 0.0).then_some(mhz / 1e3)
}

/// Milliseconds to render every pixel of `camera`, and the fraction with opacity > 0.5.
fn time_frame(kernel: &dyn nephele_kernels::kernel::RayKernel, camera: &Camera) -> Result<(f64, f64)> {
    let pixels = all_pixels(camera);
    let start = Instant::now();
    let (out, _) = kernel.render_pixels(camera, &pixels)?;
    let ms = 1e3 * start.elapsed().as_secs_f64();
    let covered = out.opacity.iter().filter(|&&a| a > 0.5).count() as f64 / out.opacity.len().max(1) as f64;
    Ok((ms, covered))
}
