//! `bench hardcases`: the numerical-stability suite (issue 18). Adversarial rays
//! ([`nephele_geometry::hardcases`]) through every kernel and through the trainers' forward
//! and backward passes, on a tiny (1e-3), a unit and a huge (1e3) scene; counts every output
//! or gradient that is NaN, infinite or out of its range, and every degenerate ray that was
//! not rejected. The goal is zero of both.
//!
//! What runs, per scene scale (each gets a share of `--rays`):
//!
//! * ray level: the density cubes' march, the radiance field's `render_ray` and `density_hit`;
//! * trainers: the radiance field's `batch_gradients` (loss, MLP and hash-table gradients) and
//!   the i-NOLF heads' `heads_forward_backward` (loss, grid, MLP and PSH gradients);
//! * farm kernels (camera and pixels in, as a worker runs them), with cameras built on the hard
//!   rays (odd frames, so the centre pixel is the hard ray itself; fields of view from 0.001
//!   to 2.5 rad): i-NOLF and the i-NGP-style baseline on the CPU and, when an adapter is
//!   there, on the GPU, and the path tracer (unit scene only); a degenerate ray must make
//!   the camera constructor refuse;
//! * the stereo GI model on G-buffers whose values are NaN, infinite, 1e30 or denormal.
//!
//! The scenes are synthetic: a sphere with a soft edge, a thin tilted slab (grazing rays)
//! and a small box in a corner (empty blocks), the same in the density cubes, the field's
//! occupancy and the path tracer's meshes; the networks have random weights with features of
//! order one (untrained networks are what a trainer starts from, and the largest outputs).

use std::fmt;
use std::sync::Arc;

use anyhow::Result;
use glam::Vec3;
use nephele_geometry::Bounds;
use nephele_geometry::camera::Camera;
use nephele_geometry::hardcases::{HardRay, HardRays, RayClass, hard_object_density};
use nephele_gpu::{DeviceChoice, GpuContext, GpuInolfKernel, GpuNgpKernel};
use nephele_kernels::gi::{GBufferPixel, GI_INPUTS, GI_OUTPUTS, GiFeatures, GiModel};
use nephele_kernels::inolf::kernel::{HIT_OPACITY, InolfKernel, RAY_NEAR};
use nephele_kernels::inolf::model::InolfModel;
use nephele_kernels::inolf::model::LossSpace;
use nephele_kernels::inolf::synthetic::{SyntheticObject, spread, synthetic_object};
use nephele_kernels::kernel::{PathTracedKernel, PixelResults, RayKernel, all_pixels};
use nephele_kernels::nelf::{NelfKernel, NelfModel};
use nephele_kernels::ngp::{FieldConfig, FieldScratch, NgpKernel, OccupancyGrid, RadianceField};
use nephele_nn::{HashGridConfig, UNet, UNetConfig, UNetWorkspace};
use nephele_train::inolf::train::{HeadRay, HeadsWorkspace, ParameterGradients, heads_forward_backward};
use nephele_train::ngp::{TrainingRay, batch_gradients};
use rayon::prelude::*;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct HardcaseArgs {
    /// Adversarial rays per kernel (spread over the three scene scales).
    #[arg(long, default_value_t = 1_000_000)]
    rays: u64,
    /// Seed of the ray stream.
    #[arg(long, default_value_t = 18)]
    seed: u64,
    /// The GPU kernels: gpu (a hardware GPU, else a software Vulkan adapter), auto (a hardware
    /// GPU only) or cpu (skip them).
    #[arg(long, default_value = "gpu", value_name = "auto|gpu|cpu")]
    device: DeviceChoice,
}

/// The scales of the scenes: tiny, unit, huge (world units per unit of the synthetic scene).
pub const SCALES: [f32; 3] = [1e-3, 1.0, 1e3];

/// Side of the frames built on hard rays (odd: the centre pixel's ray is the hard ray).
const FRAME: u32 = 7;

/// What one kernel did with its hard rays.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tally {
    /// Rays (or G-buffer pixels) sent.
    pub rays: u64,
    /// Of those, rays that hit matter (a kernel that returns nothing would pass otherwise);
    /// for the radiance field's trainer, batches of 256 rays in which some ray took samples.
    pub hits: u64,
    /// Degenerate rays rejected as they must be (an empty result, or a refused camera).
    pub rejected: u64,
    /// Outputs or gradients that were NaN or infinite.
    pub non_finite: u64,
    /// Finite outputs outside their range (negative colour or depth, opacity outside [0, 1]).
    pub out_of_range: u64,
    /// Degenerate rays that were not rejected.
    pub not_rejected: u64,
    /// The first few failures, for the report.
    pub examples: Vec<String>,
}

impl Tally {
    fn failures(&self) -> u64 {
        self.non_finite + self.out_of_range + self.not_rejected
    }

    fn fail(&mut self, what: &str, ray: Option<&HardRay>) {
        if self.examples.len() < 4 {
            self.examples.push(match ray {
                Some(r) => format!("{what} ({}: origin {}, direction {})", r.class.name(), r.origin, r.direction),
                None => what.to_string(),
            });
        }
    }

    fn merge(&mut self, other: Tally) {
        self.rays += other.rays;
        self.hits += other.hits;
        self.rejected += other.rejected;
        self.non_finite += other.non_finite;
        self.out_of_range += other.out_of_range;
        self.not_rejected += other.not_rejected;
        for e in other.examples {
            if self.examples.len() < 4 {
                self.examples.push(e);
            }
        }
    }

    /// Counts the values of `values` that are not finite.
    fn finite(&mut self, values: impl IntoIterator<Item = f32>, what: &str, ray: Option<&HardRay>) {
        let bad = values.into_iter().filter(|v| !v.is_finite()).count() as u64;
        if bad > 0 {
            self.non_finite += bad;
            self.fail(&format!("{bad} non-finite {what}"), ray);
        }
    }

    /// Checks one pixel of a kernel's results (colour, opacity, depth).
    fn pixel(&mut self, out: &PixelResults, i: usize, ray: Option<&HardRay>) {
        let (c, a, d) = (out.color[i], out.opacity[i], out.depth[i]);
        self.rays += 1;
        if !(c.iter().all(|v| v.is_finite()) && a.is_finite() && d.is_finite()) {
            self.non_finite += 1;
            self.fail(&format!("pixel colour {c:?} opacity {a} depth {d}"), ray);
        } else if c.iter().any(|v| *v < 0.0) || !(0.0..=1.0).contains(&a) || d < 0.0 {
            self.out_of_range += 1;
            self.fail(&format!("pixel colour {c:?} opacity {a} depth {d}"), ray);
        } else if a > 0.0 {
            self.hits += 1;
        }
    }
}

/// The suite's findings, kernel by kernel.
#[derive(Debug, Clone, Default)]
pub struct Report {
    pub kernels: Vec<(String, Tally)>,
    /// Kernels not run, and why (no GPU adapter).
    pub skipped: Vec<String>,
}

impl Report {
    /// Non-finite or out-of-range values and unrejected degenerate rays, in all.
    pub fn failures(&self) -> u64 {
        self.kernels.iter().map(|(_, t)| t.failures()).sum()
    }

    /// Rays sent through all kernels.
    pub fn rays(&self) -> u64 {
        self.kernels.iter().map(|(_, t)| t.rays).sum()
    }

    fn add(&mut self, name: &str, tally: Tally) {
        match self.kernels.iter_mut().find(|(n, _)| n == name) {
            Some((_, t)) => t.merge(tally),
            None => self.kernels.push((name.to_string(), tally)),
        }
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{:<34} {:>10} {:>10} {:>9} {:>11} {:>12} {:>13}",
            "kernel", "rays", "hits", "rejected", "non-finite", "out of range", "not rejected"
        )?;
        for (name, t) in &self.kernels {
            writeln!(
                f,
                "{:<34} {:>10} {:>10} {:>9} {:>11} {:>12} {:>13}",
                name, t.rays, t.hits, t.rejected, t.non_finite, t.out_of_range, t.not_rejected
            )?;
            for e in &t.examples {
                writeln!(f, "    {e}")?;
            }
        }
        for s in &self.skipped {
            writeln!(f, "skipped: {s}")?;
        }
        write!(f, "{} rays in all, {} failures", self.rays(), self.failures())
    }
}

/// One scene scale's kernels and the points inside its matter.
struct Scene {
    scale: f32,
    bounds: Bounds,
    matter: Vec<Vec3>,
    model: InolfModel,
    inolf: InolfKernel,
    ngp: NgpKernel,
    /// A NeLF on the field's matter (random weights: the march, the sampler, the encoding
    /// and the network are what hard rays can break).
    nelf: NelfKernel,
}

impl Scene {
    fn new(scale: f32) -> Result<Scene> {
        let SyntheticObject { mut model, kernel: mut inolf } =
            synthetic_object(scale).map_err(|e| anyhow::anyhow!("the synthetic object: {e}"))?;
        // As `nephele bake` trains them: the diffuse colour blended over the march's samples of
        // largest weight (their distances and weights are what hard rays can break).
        model.shape.diffuse_blend = true;
        inolf.set_diffuse_blend(true);
        let bounds = Bounds { min: Vec3::splat(-scale), max: Vec3::splat(scale) };
        let matter = vec![Vec3::ZERO, Vec3::new(0.2, 0.1, -0.1) * scale, Vec3::new(-0.8, 0.8, -0.8) * scale];

        let config = FieldConfig {
            grid: HashGridConfig::with_finest_resolution(8, 14, 16, 512),
            steps_per_diagonal: 256,
            occupancy_resolution: 32,
            ..FieldConfig::default()
        };
        let mut field = RadianceField::new(config, bounds.min, 2.0 * scale, 5)?;
        for (i, f) in field.grid.params_mut().iter_mut().enumerate() {
            *f = 2.0 * spread(i);
        }
        let r = config.occupancy_resolution;
        let flags: Vec<bool> = (0..(r as usize).pow(3))
            .map(|i| hard_object_density(field.occupancy.cell_center(i) * 2.0 - Vec3::ONE) > 0.0)
            .collect();
        field.occupancy =
            OccupancyGrid::from_flags(r, &flags).ok_or_else(|| anyhow::anyhow!("occupancy of the field"))?;
        let ngp = NgpKernel::new(field);
        let (sampling, grid) = nephele_train::nelf::geometry_of(&ngp, 8, 4)?;
        let nelf = NelfKernel::new(NelfModel::initial(sampling, grid, 32, 2, 3)?);
        Ok(Scene { scale, bounds, matter, model, inolf, ngp, nelf })
    }

    fn rays(&self, seed: u64, count: u64) -> Vec<HardRay> {
        HardRays::new(self.bounds, &self.matter, seed ^ self.scale.to_bits() as u64).take(count as usize).collect()
    }
}

/// The density cubes' march.
fn march(scene: &Scene, rays: &[HardRay]) -> Tally {
    rays.par_chunks(4096)
        .map(|chunk| {
            let mut t = Tally::default();
            for r in chunk {
                let h = scene.inolf.density().march(r.origin, r.direction, RAY_NEAR * scene.scale, f32::INFINITY);
                t.rays += 1;
                let blend = h.normalised_blend();
                let values = [h.opacity, h.t, h.max_weight].into_iter().chain(blend.iter().flat_map(|b| [b.0, b.1]));
                let blend_total: f32 = blend.iter().map(|b| b.1).sum();
                if !values.clone().all(|v| v.is_finite()) {
                    t.finite(values, "march outputs", Some(r));
                } else if !(0.0..=1.0).contains(&h.opacity)
                    || h.t < 0.0
                    || h.max_weight > h.opacity + 1e-6
                    || (h.opacity > 0.0 && (blend_total - 1.0).abs() > 1e-4)
                {
                    t.out_of_range += 1;
                    t.fail(&format!("march {h:?}"), Some(r));
                } else if r.must_be_rejected() {
                    if h.opacity == 0.0 {
                        t.rejected += 1;
                    } else {
                        t.not_rejected += 1;
                        t.fail(&format!("march {h:?}"), Some(r));
                    }
                } else if h.opacity >= HIT_OPACITY {
                    t.hits += 1;
                }
            }
            t
        })
        .reduce(Tally::default, |mut a, b| {
            a.merge(b);
            a
        })
}

/// The radiance field's `render_ray` and `density_hit`.
fn field_rays(scene: &Scene, rays: &[HardRay]) -> Tally {
    let field = scene.ngp.field();
    rays.par_chunks(512)
        .map(|chunk| {
            let mut t = Tally::default();
            let mut scratch = FieldScratch::new();
            for r in chunk {
                let a = field.render_ray(r.origin, r.direction, 0.0, &mut scratch);
                let b = field.density_hit(r.origin, r.direction, 0.0, &mut scratch);
                t.rays += 1;
                let mut ok = true;
                for res in [&a, &b] {
                    let values =
                        [res.color[0], res.color[1], res.color[2], res.opacity, res.distance, res.peak_distance];
                    if !values.iter().all(|v| v.is_finite()) {
                        t.finite(values, "field outputs", Some(r));
                        ok = false;
                    } else if res.color.iter().any(|c| *c < 0.0)
                        || !(0.0..=1.0).contains(&res.opacity)
                        || res.distance < 0.0
                        || res.peak_distance < 0.0
                    {
                        t.out_of_range += 1;
                        t.fail(&format!("field {res:?}"), Some(r));
                        ok = false;
                    }
                }
                if !ok {
                    continue;
                }
                if r.must_be_rejected() {
                    if a.opacity == 0.0 && b.opacity == 0.0 {
                        t.rejected += 1;
                    } else {
                        t.not_rejected += 1;
                        t.fail("field rendered a degenerate ray", Some(r));
                    }
                } else if a.opacity > 0.0 {
                    t.hits += 1;
                }
            }
            t
        })
        .reduce(Tally::default, |mut a, b| {
            a.merge(b);
            a
        })
}

/// Targets of training rays: ordinary pixels, the extremes of the range, transparent.
fn target(i: usize) -> [f32; 4] {
    match i % 4 {
        0 => [0.0; 4],
        1 => [1.0; 4],
        2 => [0.25, 0.5, 0.125, 0.5],
        _ => [1e-30, 0.0, 1.0, 1.0],
    }
}

/// The radiance field trainer's forward and backward, in batches of 256 rays.
fn field_training(scene: &Scene, rays: &[HardRay]) -> Result<Tally> {
    let field = scene.ngp.field();
    let mut tally = Tally::default();
    let mut grad_grid = vec![0.0; field.grid.num_params()];
    for (k, chunk) in rays.chunks(256).enumerate() {
        let batch: Vec<TrainingRay> = chunk
            .iter()
            .enumerate()
            .map(|(i, r)| TrainingRay {
                origin: r.origin,
                dir: r.direction,
                offset: ((k + i) % 7) as f32 / 7.0,
                target: target(i),
            })
            .collect();
        let g = batch_gradients(field, &batch, &mut grad_grid)?;
        tally.rays += chunk.len() as u64;
        tally.hits += u64::from(g.samples > 0);
        let before = tally.non_finite;
        tally.finite([g.loss], "losses", None);
        tally.finite(g.density.iter().chain(&g.color).copied(), "MLP gradients", None);
        tally.finite(grad_grid.iter().copied(), "hash-table gradients", None);
        if tally.non_finite > before {
            // Name the rays of the failing batch's classes.
            let classes: std::collections::BTreeSet<&str> = chunk.iter().map(|r| r.class.name()).collect();
            tally.fail(&format!("batch {k} of classes {classes:?}"), None);
        }
        tally.rejected += chunk.iter().filter(|r| r.must_be_rejected()).count() as u64;
    }
    Ok(tally)
}

/// The i-NOLF heads' forward and backward on the rays that hit the density cubes, in batches
/// of 256.
fn heads_training(scene: &Scene, rays: &[HardRay]) -> Result<Tally> {
    let mut tally = Tally { rays: rays.len() as u64, ..Tally::default() };
    let hits: Vec<HeadRay> = rays
        .iter()
        .enumerate()
        .filter_map(|(i, r)| {
            let hit = scene.inolf.density().march(r.origin, r.direction, RAY_NEAR * scene.scale, f32::INFINITY);
            (hit.opacity >= HIT_OPACITY).then_some(HeadRay {
                origin: r.origin,
                dir: r.direction,
                hit,
                target: target(i),
            })
        })
        .collect();
    tally.hits = hits.len() as u64;
    tally.rejected = rays.iter().filter(|r| r.must_be_rejected()).count() as u64;
    let mut grads = ParameterGradients::zeros(&scene.model);
    let mut workspace = HeadsWorkspace::default();
    for chunk in hits.chunks(256) {
        let losses = heads_forward_backward(&scene.model, chunk, 0.5, LossSpace::Srgb, &mut grads, &mut workspace)?;
        tally.finite(losses, "losses", None);
        tally.finite(grads.values(), "gradients", None);
        grads.clear();
    }
    Ok(tally)
}

/// A farm kernel on frames built around the hard rays.
fn farm_kernel(kernel: &dyn RayKernel, rays: &[HardRay]) -> Result<Tally> {
    const FOVS: [f32; 4] = [1e-3, 0.3, 1.2, 2.5];
    let mut tally = Tally::default();
    let per_frame = u64::from(FRAME * FRAME);
    let frames = rays.len().div_ceil(per_frame as usize);
    for (k, r) in rays.iter().take(frames).enumerate() {
        let forward = r.direction;
        let up = if forward.normalize_or_zero().z.abs() > 0.9 { Vec3::X } else { Vec3::Z };
        // The target as far out as the eye is from the origin, so that far-away eyes keep
        // their direction in float.
        let reach = r.origin.length().max(1.0);
        let camera = Camera::look_at(FRAME, FRAME, FOVS[k % 4], r.origin, r.origin + forward * reach, up);
        let camera = match (camera, r.must_be_rejected()) {
            (Err(_), true) => {
                tally.rays += per_frame;
                tally.rejected += per_frame;
                continue;
            }
            (Err(e), false) => {
                // A valid ray whose camera cannot be built: far away, the target is the eye
                // within rounding. Not a kernel failure; the ray is not sent.
                let _ = e;
                continue;
            }
            (Ok(c), true) => {
                tally.rays += per_frame;
                tally.not_rejected += per_frame;
                tally.fail(&format!("camera built on a degenerate ray: {c:?}"), Some(r));
                continue;
            }
            (Ok(c), false) => c,
        };
        let pixels = all_pixels(&camera);
        let (out, _) = kernel.render_pixels(&camera, &pixels)?;
        for i in 0..out.len() {
            tally.pixel(&out, i, Some(r));
        }
    }
    Ok(tally)
}

/// G-buffer values a renderer should never give and a GI kernel must survive.
fn nasty(i: usize) -> f32 {
    const VALUES: [f32; 10] = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30, -1e30, 1e-40, -1e-45, 0.0, 0.5, -0.7];
    VALUES[(i.wrapping_mul(2_654_435_761) >> 7) % VALUES.len()]
}

/// The stereo GI model on G-buffers of nasty values (16x16, both eyes).
fn gi(pixels: u64) -> Result<Tally> {
    let config = UNetConfig { inputs: GI_INPUTS, eyes: 2, outputs: GI_OUTPUTS, channels: vec![4, 8] };
    let features = GiFeatures { centre: [0.0, 0.0, 1.4], scale: 2.5 };
    let model = GiModel::new(UNet::new(config, 3)?, features, serde_json::json!({}))?;
    let (w, h) = (16usize, 16usize);
    let mut ws = UNetWorkspace::new();
    let mut tally = Tally::default();
    let images = pixels.div_ceil((2 * w * h) as u64);
    for k in 0..images as usize {
        let eye = |e: usize| -> Vec<GBufferPixel> {
            (0..w * h)
                .map(|p| {
                    let s = (k * 7919 + e * 104_729 + p) * 13;
                    let v = |j: usize| if (s + j).is_multiple_of(3) { nasty(s + j) } else { spread(s + j) };
                    GBufferPixel {
                        position: [v(0), v(1), v(2)],
                        normal: [v(3), v(4), v(5)],
                        albedo: [v(6), v(7), v(8)],
                        depth: v(9),
                        direct: [v(10), v(11), v(12)],
                    }
                })
                .collect()
        };
        let (left, right) = (eye(0), eye(1));
        let shaded = model.shade(w, h, &[&left, &right], &mut ws)?;
        for image in &shaded.eyes {
            for c in image {
                tally.rays += 1;
                if !c.iter().all(|v| v.is_finite()) {
                    tally.non_finite += 1;
                    tally.fail(&format!("GI output {c:?}"), None);
                } else if c.iter().any(|v| *v < 0.0) {
                    tally.out_of_range += 1;
                    tally.fail(&format!("GI output {c:?}"), None);
                } else if c.iter().any(|v| *v > 0.0) {
                    tally.hits += 1;
                }
            }
        }
    }
    Ok(tally)
}

/// Runs the suite: `rays` per kernel (split over the scales), GPU kernels on `gpu` if given.
pub fn run(rays: u64, seed: u64, gpu: Option<Arc<GpuContext>>, progress: &dyn Progress) -> Result<Report> {
    let mut report = Report::default();
    let per_scale = rays.div_ceil(SCALES.len() as u64);
    let bar = progress.bar(SCALES.len() as u64 + 1, "hard cases", "scenes");
    for &scale in &SCALES {
        let scene = Scene::new(scale)?;
        let rays = scene.rays(seed, per_scale);
        report.add("density cubes: march", march(&scene, &rays));
        report.add("radiance field: render, hit", field_rays(&scene, &rays));
        report.add("radiance field: train fwd+bwd", field_training(&scene, &rays)?);
        report.add("i-NOLF heads: train fwd+bwd", heads_training(&scene, &rays)?);
        report.add("i-NOLF kernel (CPU)", farm_kernel(&scene.inolf, &rays)?);
        report.add("i-NGP baseline kernel (CPU)", farm_kernel(&scene.ngp, &rays)?);
        report.add("NeLF kernel (CPU)", farm_kernel(&scene.nelf, &rays)?);
        if let Some(ctx) = &gpu {
            let kernel = GpuInolfKernel::new(ctx.clone(), &scene.inolf)?;
            report.add("i-NOLF kernel (GPU)", farm_kernel(&kernel, &rays)?);
            let kernel = GpuNgpKernel::new(ctx.clone(), &scene.ngp)?;
            report.add("i-NGP baseline kernel (GPU)", farm_kernel(&kernel, &rays)?);
        }
        if scale == 1.0 {
            let builtin = nephele_pathtracer::scenes::builtin("diffuse")?;
            let renderer = nephele_pathtracer::Renderer::new(builtin.scene)?;
            let kernel = PathTracedKernel::new(renderer, 1, 3)?;
            let bounds = kernel.bounds();
            let rays: Vec<HardRay> =
                HardRays::new(bounds, &[bounds.center()], seed).take(rays.len() * SCALES.len()).collect();
            report.add("path tracer", farm_kernel(&kernel, &rays)?);
        }
        bar.inc(1);
    }
    if gpu.is_none() {
        report.skipped.push("the GPU kernels: no GPU adapter (or --device cpu)".into());
    }
    report.add("stereo GI (nasty G-buffers)", gi(rays)?);
    bar.finish_and_clear();
    Ok(report)
}

pub fn hardcases(args: HardcaseArgs, progress: &dyn Progress) -> Result<()> {
    let gpu = match args.device {
        DeviceChoice::Cpu => None,
        choice => GpuContext::open(choice)?,
    };
    println!(
        "hard cases: {} adversarial rays per kernel over scenes of scale {:?} ({} classes: {}), seed {}{}",
        args.rays,
        SCALES,
        RayClass::ALL.len(),
        RayClass::ALL.map(RayClass::name).join(", "),
        args.seed,
        gpu.as_ref().map(|c| format!(", GPU: {}", c.label())).unwrap_or_default()
    );
    let report = run(args.rays, args.seed, gpu, progress)?;
    println!("{report}");
    if report.failures() > 0 {
        anyhow::bail!("{} non-finite or out-of-range values or unrejected degenerate rays", report.failures());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    struct NoBars;

    impl Progress for NoBars {
        fn bar(&self, _: u64, _: &str, _: &str) -> indicatif::ProgressBar {
            indicatif::ProgressBar::hidden()
        }
    }

    fn gpu() -> Option<Arc<GpuContext>> {
        // CI has Mesa's software Vulkan (scripts/test installs it); elsewhere the GPU rows are
        // skipped and the report says so.
        GpuContext::open(DeviceChoice::Gpu).ok().flatten()
    }

    fn check(report: &Report, rays: u64) {
        eprintln!("{report}");
        assert_eq!(report.failures(), 0, "\n{report}");
        for (name, t) in &report.kernels {
            // Every kernel saw its rays (the farm kernels lose a few far-away cameras that
            // cannot be built), hit matter and rejected degenerate rays.
            assert!(t.rays >= rays * 9 / 10, "{name}: {t:?}");
            assert!(t.hits > 0, "{name}: {t:?}");
            if !name.starts_with("stereo GI") {
                assert!(t.rejected > 0, "{name}: {t:?}");
            }
        }
    }

    /// The CI draw: 20,000 rays per kernel.
    #[test]
    fn hard_rays_give_no_nan_anywhere() {
        let report = run(20_000, 18, gpu(), &NoBars).expect("suite");
        assert!(report.kernels.len() >= 8, "\n{report}");
        check(&report, 20_000);
    }

    /// The full million per kernel (`nephele bench hardcases` prints the same table).
    #[test]
    #[ignore = "a million rays per kernel: minutes; run with --ignored or `nephele bench hardcases`"]
    fn a_million_hard_rays_give_no_nan_anywhere() {
        let report = run(1_000_000, 18, gpu(), &NoBars).expect("suite");
        check(&report, 1_000_000);
    }
}
