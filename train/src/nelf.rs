//! Distilling a radiance field into a NeLF (R2L, Wang et al. 2022, section 3.3): pseudo-data
//! rendered by the teacher from random poses around the object, a deep residual MLP trained
//! on it with a pool of hard examples replayed in every batch, then fine-tuned on the real
//! images; checkpoints that a later run resumes bit for bit.
//!
//! * **Teacher**: the i-NGP-style field ([`NgpKernel`]). The NeLF lives in its space: colour
//!   premultiplied by opacity in the dataset's sRGB encoding, the opacity, and the expected
//!   distance along the ray as a fraction of the segment inside the object's box.
//! * **Rays**: only rays that meet the teacher's occupied cells are ever trained on or
//!   queried ([`nephele_kernels::nelf::MatterGrid`]): the rest are empty by construction.
//! * **Pseudo-data**: poses drawn area-uniformly on the sphere the dataset's cameras lie on
//!   (their common focus, mean distance; the upper hemisphere when all cameras are above),
//!   the dataset's intrinsics, random sub-pixel positions; held in memory (44 bytes a ray)
//!   and, by the caller, cached on disk beside the checkpoint ([`RaySet::save`]).
//! * **Hard examples** (R2L's "hard example mining"): after each step the worst
//!   `hard_fraction` of the batch's fresh rays enter a bounded ring; the next batch takes
//!   that fraction from the ring.
//! * **Fine-tuning**: after `steps` steps on pseudo-data, `fine_tune_steps` steps whose
//!   batches are half real pixels (colour and opacity only: the images have no depth) and
//!   half pseudo rays, so that the network does not forget the views between the cameras.
//! * **Loss**: squared error of colour and opacity, plus `depth_weight` times the teacher's
//!   opacity times the squared error of the depth fraction.

use std::path::Path;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use nephele_geometry::SplitMix64;
use nephele_geometry::camera::Camera;
use nephele_kernels::nelf::{MatterGrid, MatterPlacement, NELF_OUTPUTS, RaySampling, network_config};
use nephele_kernels::ngp::{NgpKernel, RayResult};
use nephele_nn::{Adam, AdamConfig, NnError, ResidualMlp, ResidualMlpConfig, ResidualWorkspace};

use crate::checkpoint::{Checkpoint, CheckpointError, CheckpointState};
use crate::dataset::{View, sample_views_on_sphere};
use crate::ngp::train::common_focus;
use crate::targets::{PixelCheck, TargetSpace, is_dropped, premultiplied_targets};

/// Rows per parallel task of a training step (fixed, so that the sum of the gradients, and
/// so a resumed run, does not depend on the number of threads).
const ROWS_PER_TASK: usize = 128;
/// Loss-curve entries every this many steps.
const CURVE_EVERY: u32 = 50;

/// Everything a distillation run is made of.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DistillOptions {
    /// `K`: points along a ray (R2L: 16).
    pub points: usize,
    /// Octaves of the positional encoding of each point (R2L: 10).
    pub frequencies: usize,
    /// Width of the residual MLP.
    pub width: usize,
    /// Residual blocks (two layers each).
    pub blocks: usize,
    /// Poses the teacher renders pseudo-data from.
    pub pseudo_views: u32,
    /// Rays kept per pose (rays that meet the matter).
    pub rays_per_view: u32,
    /// Steps on pseudo-data.
    pub steps: u32,
    /// Steps of fine-tuning on the real images (half of each batch) after them.
    pub fine_tune_steps: u32,
    /// Rays per step.
    pub batch: usize,
    /// Adam's learning rate (a third after half the run, a tenth after three quarters).
    pub learning_rate: f32,
    /// Fraction of each batch replayed from the hard-example pool (0 turns it off).
    pub hard_fraction: f32,
    /// Capacity of the hard-example pool.
    pub hard_pool: usize,
    /// Weight of the depth term.
    pub depth_weight: f32,
    pub seed: u64,
}

impl Default for DistillOptions {
    fn default() -> Self {
        DistillOptions {
            points: 16,
            frequencies: 4,
            width: 64,
            blocks: 4,
            pseudo_views: 300,
            rays_per_view: 2048,
            steps: 6000,
            fine_tune_steps: 1500,
            batch: 2048,
            learning_rate: 1e-3,
            hard_fraction: 0.2,
            hard_pool: 1 << 16,
            depth_weight: 0.5,
            seed: 1,
        }
    }
}

impl DistillOptions {
    pub fn validate(&self) -> Result<(), DistillError> {
        let bad = |why: String| Err(DistillError::Options(why));
        if self.steps + self.fine_tune_steps == 0 {
            return bad("no steps to take".into());
        }
        if self.batch < 16 || self.batch > 1 << 18 {
            return bad(format!("batch of {} rays (16 ..= 262144)", self.batch));
        }
        if self.pseudo_views == 0 || self.rays_per_view == 0 {
            return bad("pseudo-data needs at least one view and one ray per view".into());
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0 && self.learning_rate < 1.0) {
            return bad(format!("learning rate {}", self.learning_rate));
        }
        if !(0.0..=0.9).contains(&self.hard_fraction) {
            return bad(format!("hard-example fraction {} (0 ..= 0.9)", self.hard_fraction));
        }
        if self.hard_fraction > 0.0 && self.hard_pool < self.batch {
            return bad(format!("a hard-example pool of {} is smaller than a batch", self.hard_pool));
        }
        if !(self.depth_weight.is_finite() && self.depth_weight >= 0.0) {
            return bad(format!("depth weight {}", self.depth_weight));
        }
        Ok(())
    }

    pub fn total_steps(&self) -> u32 {
        self.steps + self.fine_tune_steps
    }

    pub fn learning_rate_at(&self, step: u32) -> f32 {
        let t = step as f32 / self.total_steps() as f32;
        self.learning_rate
            * if t < 0.5 {
                1.0
            } else if t < 0.75 {
                0.3
            } else {
                0.1
            }
    }

    /// Rays per batch drawn from the hard-example pool.
    fn hard_rows(&self) -> usize {
        (self.hard_fraction * self.batch as f32).round() as usize
    }
}

#[derive(Debug, Error)]
pub enum DistillError {
    #[error("distillation options: {0}")]
    Options(String),
    #[error("{0}")]
    Data(String),
    #[error("network: {0}")]
    Network(#[from] NnError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("{path}: {reason}")]
    Cache { path: String, reason: String },
}

/// Where the NeLF samples and where the matter is, from the teacher: the points are sampled
/// in the box of the teacher's occupied cells, and its occupancy grid is the NeLF's.
pub fn geometry_of(
    teacher: &NgpKernel,
    points: usize,
    frequencies: usize,
) -> Result<(RaySampling, MatterGrid), DistillError> {
    use nephele_kernels::kernel::RayKernel;
    let bounds = teacher.bounds();
    let sampling = RaySampling { points, frequencies, min: bounds.min.to_array(), max: bounds.max.to_array() };
    sampling.validate().map_err(DistillError::Options)?;
    let field = teacher.field();
    let placement = MatterPlacement {
        min: field.min.to_array(),
        size: field.size,
        step: field.step_size(),
        resolution: field.occupancy().resolution(),
    };
    let matter = MatterGrid::new(placement, field.occupancy().clone()).map_err(DistillError::Data)?;
    Ok((sampling, matter))
}

/// Training rays and their targets: premultiplied colour (3), opacity, depth fraction.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RaySet {
    pub rays: Vec<(Vec3, Vec3)>,
    pub targets: Vec<[f32; NELF_OUTPUTS]>,
    /// Whether the depth fractions are known (pseudo-data) or not (real images).
    pub depth_known: bool,
}

/// Magic of a pseudo-data cache file.
const RAYS_MAGIC: &[u8; 8] = b"NEPHRAYS";

impl RaySet {
    pub fn len(&self) -> usize {
        self.rays.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    /// Bytes a cache file of this set takes.
    pub fn file_bytes(&self) -> usize {
        8 + 8 + 8 + 1 + self.len() * 4 * (6 + NELF_OUTPUTS) + 4
    }

    /// Writes the set with `key` (what it was made from) and a CRC-32.
    pub fn save(&self, path: &Path, key: u64) -> Result<(), DistillError> {
        let mut out = Vec::with_capacity(self.file_bytes());
        out.extend_from_slice(RAYS_MAGIC);
        out.extend_from_slice(&key.to_le_bytes());
        out.extend_from_slice(&(self.len() as u64).to_le_bytes());
        out.push(u8::from(self.depth_known));
        for ((o, d), t) in self.rays.iter().zip(&self.targets) {
            for v in o.to_array().iter().chain(&d.to_array()).chain(t) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        let err = |e: std::io::Error| DistillError::Cache { path: path.display().to_string(), reason: e.to_string() };
        let tmp = path.with_extension("part");
        std::fs::write(&tmp, &out).map_err(err)?;
        std::fs::rename(&tmp, path).map_err(err)
    }

    /// Reads a set written by [`RaySet::save`] with the same `key`; `Ok(None)` when the file
    /// is missing or was made from something else.
    pub fn load(path: &Path, key: u64) -> Result<Option<RaySet>, DistillError> {
        let err = |reason: String| DistillError::Cache { path: path.display().to_string(), reason };
        let bytes = match std::fs::read(path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(err(e.to_string())),
        };
        if bytes.len() < 29 || &bytes[..8] != RAYS_MAGIC {
            return Err(err("not a ray cache".into()));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body).to_le_bytes() != crc {
            return Err(err("checksum mismatch: damaged or truncated".into()));
        }
        let u64_at = |at: usize| u64::from_le_bytes(body[at..at + 8].try_into().unwrap_or([0; 8]));
        if u64_at(8) != key {
            return Ok(None);
        }
        let count = usize::try_from(u64_at(16)).map_err(|e| err(e.to_string()))?;
        let per = 4 * (6 + NELF_OUTPUTS);
        if Some(body.len()) != count.checked_mul(per).and_then(|n| n.checked_add(25)) {
            return Err(err("length does not match the count".into()));
        }
        let mut set = RaySet { depth_known: body[24] != 0, ..RaySet::default() };
        for record in body[25..].chunks_exact(per) {
            let f: Vec<f32> = record.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            set.rays.push((Vec3::new(f[0], f[1], f[2]), Vec3::new(f[3], f[4], f[5])));
            let mut t = [0.0; NELF_OUTPUTS];
            t.copy_from_slice(&f[6..]);
            set.targets.push(t);
        }
        Ok(Some(set))
    }
}

/// What pseudo-data is made from: the teacher's file, the cameras that place the poses and
/// the options that draw them. A cache with another key is not reused.
pub fn pseudo_key(teacher_file: &[u8], cameras: &[Camera], options: &DistillOptions) -> u64 {
    let mut what = crc32fast::Hasher::new();
    let first = cameras.first().map(|c| (c.width(), c.height(), c.fov_x().to_bits()));
    let positions: Vec<[u32; 3]> = cameras.iter().map(|c| c.position().to_array().map(f32::to_bits)).collect();
    what.update(
        format!("{first:?} {positions:?} {} {} {}", options.pseudo_views, options.rays_per_view, options.seed)
            .as_bytes(),
    );
    (u64::from(crc32fast::hash(teacher_file)) << 32) | u64::from(what.finalize())
}

/// A teacher's answer as a NeLF target: its premultiplied colour and opacity, and its
/// expected distance as a fraction of the segment `[t0, t1]`.
fn target_of(result: &RayResult, t0: f32, t1: f32) -> [f32; NELF_OUTPUTS] {
    let a = result.opacity.clamp(0.0, 1.0);
    let [r, g, b] = result.color.map(|c| c.clamp(0.0, a));
    let depth = if a > 0.0 { ((result.distance - t0) / (t1 - t0)).clamp(0.0, 1.0) } else { 0.5 };
    [r, g, b, a, if depth.is_finite() { depth } else { 0.5 }]
}

/// Pseudo-data: `options.rays_per_view` rays meeting the matter from each of
/// `options.pseudo_views` random poses around the dataset's cameras, answered by `teacher`.
/// `progress(done, total)` after each pose.
pub fn pseudo_data(
    teacher: &NgpKernel,
    sampling: &RaySampling,
    matter: &MatterGrid,
    cameras: &[Camera],
    options: &DistillOptions,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<RaySet, DistillError> {
    let first = cameras.first().ok_or_else(|| DistillError::Data("no cameras to place the pseudo-views".into()))?;
    let focus = common_focus(cameras);
    let radius = cameras.iter().map(|c| c.position().distance(focus)).sum::<f32>() / cameras.len() as f32;
    let upper = cameras.iter().all(|c| c.position().z >= focus.z);
    let poses = sample_views_on_sphere(options.pseudo_views as usize, radius, focus, upper, options.seed ^ 0x6e65_6c66);
    let (w, h) = (first.width(), first.height());
    let mut set = RaySet { depth_known: true, ..RaySet::default() };
    let total = poses.len() as u64;
    for (i, pose) in poses.into_iter().enumerate() {
        let camera = Camera::from_fov_x(w, h, first.fov_x(), pose).map_err(|e| DistillError::Data(e.to_string()))?;
        let mut rng = SplitMix64::new(options.seed ^ (i as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let mut rays = Vec::with_capacity(options.rays_per_view as usize);
        let mut segments = Vec::with_capacity(options.rays_per_view as usize);
        // Most rays of a view miss a small object: try up to 64 per ray wanted.
        for _ in 0..64 * options.rays_per_view {
            if rays.len() == options.rays_per_view as usize {
                break;
            }
            let ray = camera.ray(rng.next_f32() * w as f32, rng.next_f32() * h as f32);
            if let Some(segment) = sampling.segment(ray.origin, ray.direction)
                && matter.hits_within(ray.origin, ray.direction, segment)
            {
                rays.push((ray.origin, ray.direction));
                segments.push(segment);
            }
        }
        let (answers, _) = teacher.render_rays(&rays);
        set.targets.extend(answers.iter().zip(&segments).map(|(r, &(t0, t1))| target_of(r, t0, t1)));
        set.rays.extend(rays);
        progress(i as u64 + 1, total);
    }
    if set.is_empty() {
        return Err(DistillError::Data("no pseudo-view ray meets the teacher's occupied cells".into()));
    }
    Ok(set)
}

/// The real images' pixels whose centre rays meet the matter, with their premultiplied
/// sRGB colour and opacity (depth unknown), and what the pixel check found.
pub fn real_data(
    views: &[View],
    camera_angle_x: f32,
    sampling: &RaySampling,
    matter: &MatterGrid,
) -> Result<(RaySet, PixelCheck), DistillError> {
    let mut check = PixelCheck::default();
    let mut per_view = Vec::with_capacity(views.len());
    for v in views {
        let camera = Camera::from_fov_x(v.image.width(), v.image.height(), camera_angle_x, v.camera_to_world)
            .map_err(|e| DistillError::Data(format!("view {}: {e}", v.name)))?;
        per_view.push((camera, premultiplied_targets(&v.image, TargetSpace::Srgb, &mut check)));
    }
    let parts: Vec<RaySet> = per_view
        .par_iter()
        .map(|(camera, targets)| {
            let mut set = RaySet::default();
            let width = camera.width();
            for (p, t) in targets.iter().enumerate() {
                if is_dropped(t) {
                    continue;
                }
                let ray = camera.pixel_center_ray(p as u32 % width, p as u32 / width);
                if let Some(segment) = sampling.segment(ray.origin, ray.direction)
                    && matter.hits_within(ray.origin, ray.direction, segment)
                {
                    set.rays.push((ray.origin, ray.direction));
                    set.targets.push([t[0], t[1], t[2], t[3], 0.5]);
                }
            }
            set
        })
        .collect();
    let mut set = RaySet::default();
    for part in parts {
        set.rays.extend(part.rays);
        set.targets.extend(part.targets);
    }
    Ok((set, check))
}

/// Where a run stands (what a checkpoint holds besides the weights).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DistillState {
    pub options: DistillOptions,
    pub network: ResidualMlpConfig,
    pub step: u32,
    /// `(step, mean loss of the steps since the previous entry)`.
    pub curve: Vec<(u32, f32)>,
    pub adam_steps: u64,
    pub rng: u64,
    /// The hard-example pool: `(set << 32) | index` (set 0 pseudo, 1 real), and where the
    /// next entry goes once it is full.
    pub pool: Vec<u64>,
    pub pool_next: usize,
}

impl CheckpointState for DistillState {
    const MAGIC: &'static [u8; 4] = b"NLFC";
    const VERSION: u32 = 1;
    const WHAT: &'static str = "NeLF distillation checkpoint";
}

pub type DistillCheckpoint = Checkpoint<DistillState>;

/// Progress of a run, every step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DistillStep {
    pub step: u32,
    pub steps: u32,
    pub loss: f32,
    /// Whether the step was one of fine-tuning on the real images.
    pub fine_tuning: bool,
}

/// One ray's loss and its gradient with respect to the network's outputs.
#[inline]
fn ray_loss(y: &[f32], t: &[f32; NELF_OUTPUTS], depth_weight: f32, scale: f32, d: &mut [f32]) -> f32 {
    let mut loss = 0.0;
    for c in 0..4 {
        let e = y[c] - t[c];
        loss += e * e;
        d[c] = 2.0 * e * scale;
    }
    let wd = depth_weight * t[3];
    let e = y[4] - t[4];
    loss += wd * e * e;
    d[4] = 2.0 * wd * e * scale;
    loss
}

/// Forward, loss and backward over the rays `refs` names: the summed gradient (for the mean
/// loss over `batch` rays) and every ray's loss.
fn batch_gradient(
    network: &ResidualMlp,
    sampling: &RaySampling,
    sets: [&RaySet; 2],
    refs: &[u64],
    depth_weight: f32,
) -> (Vec<f32>, Vec<f32>) {
    let input_len = sampling.input_len();
    let scale = 1.0 / refs.len() as f32;
    let parts: Vec<(Vec<f32>, Vec<f32>)> = refs
        .par_chunks(ROWS_PER_TASK)
        .map(|chunk| {
            let mut inputs = vec![0.0; chunk.len() * input_len];
            let mut points = Vec::new();
            let mut targets = Vec::with_capacity(chunk.len());
            for (r, row) in chunk.iter().zip(inputs.chunks_exact_mut(input_len)) {
                let set = sets[(r >> 32) as usize];
                let i = (r & 0xffff_ffff) as usize;
                let (o, d) = set.rays[i];
                let (t0, t1) = sampling.segment(o, d).unwrap_or((0.0, 1.0));
                sampling.encode(o, d, t0, t1, &mut points, row);
                let wd = if set.depth_known { depth_weight } else { 0.0 };
                targets.push((set.targets[i], wd));
            }
            let mut ws = ResidualWorkspace::new();
            let mut grad = vec![0.0; network.params().len()];
            let mut d_out = vec![0.0; chunk.len() * NELF_OUTPUTS];
            let mut losses = Vec::with_capacity(chunk.len());
            if let Ok(y) = network.forward(&inputs, &mut ws) {
                for ((y, d), (t, wd)) in
                    y.chunks_exact(NELF_OUTPUTS).zip(d_out.chunks_exact_mut(NELF_OUTPUTS)).zip(&targets)
                {
                    losses.push(ray_loss(y, t, *wd, scale, d));
                }
                // Sizes agree by construction.
                let _ = network.backward(&inputs, &mut ws, &d_out, &mut grad);
            }
            (grad, losses)
        })
        .collect();
    let mut grad = vec![0.0; network.params().len()];
    let mut losses = Vec::with_capacity(refs.len());
    for (g, l) in parts {
        for (a, b) in grad.iter_mut().zip(&g) {
            *a += b;
        }
        losses.extend(l);
    }
    (grad, losses)
}

/// Distils a NeLF from `[pseudo, real]`: pseudo-data first, then fine-tuning with the real
/// images' rays (or more pseudo-data when there are none), from `resume` when given (same
/// options, else an error). `checkpoint` is called every `checkpoint_every` steps and at the
/// end.
pub fn distill(
    [pseudo, real]: [&RaySet; 2],
    sampling: &RaySampling,
    options: &DistillOptions,
    resume: Option<DistillCheckpoint>,
    checkpoint_every: u32,
    on_step: &mut dyn FnMut(DistillStep),
    checkpoint: &mut dyn FnMut(&DistillCheckpoint) -> Result<(), DistillError>,
) -> Result<(ResidualMlp, DistillState), DistillError> {
    options.validate()?;
    if pseudo.is_empty() || pseudo.len() > u32::MAX as usize || real.len() > u32::MAX as usize {
        return Err(DistillError::Data(format!("{} pseudo rays, {} real rays", pseudo.len(), real.len())));
    }
    let config = network_config(sampling, options.width, options.blocks);
    let adam_config = AdamConfig { learning_rate: options.learning_rate, epsilon: 1e-8, ..AdamConfig::default() };
    let (mut network, mut adam, mut state) = match resume {
        Some(c) => {
            if c.state.options != *options || c.state.network != config {
                return Err(DistillError::Options(
                    "the checkpoint was made with other options; start afresh or pass the same settings".into(),
                ));
            }
            let network = ResidualMlp::from_params(config, c.params)?;
            let adam = Adam::from_moments(adam_config, c.m, c.v, c.state.adam_steps)?;
            (network, adam, c.state)
        }
        None => {
            let network = ResidualMlp::new(config, options.seed)?;
            let adam = Adam::new(adam_config, network.params().len());
            let state = DistillState {
                options: options.clone(),
                network: config,
                step: 0,
                curve: Vec::new(),
                adam_steps: 0,
                rng: options.seed ^ 0x6469_7374,
                pool: Vec::new(),
                pool_next: 0,
            };
            (network, adam, state)
        }
    };
    let total = options.total_steps();
    let hard_rows = options.hard_rows();
    let mut rng = SplitMix64::new(state.rng);
    let mut window = (0.0f64, 0u32);
    let draw = |rng: &mut SplitMix64, set: u64, len: usize| (set << 32) | (rng.next_u64() % len as u64);
    while state.step < total {
        let fine_tuning = state.step >= options.steps;
        let hard = if state.pool.is_empty() { 0 } else { hard_rows };
        let fresh = options.batch - hard;
        let mut refs = Vec::with_capacity(options.batch);
        for k in 0..fresh {
            let from_real = fine_tuning && !real.is_empty() && k % 2 == 0;
            refs.push(if from_real { draw(&mut rng, 1, real.len()) } else { draw(&mut rng, 0, pseudo.len()) });
        }
        for _ in 0..hard {
            refs.push(state.pool[(rng.next_u64() % state.pool.len() as u64) as usize]);
        }
        let (grad, losses) = batch_gradient(&network, sampling, [pseudo, real], &refs, options.depth_weight);
        let loss = losses.iter().map(|&l| f64::from(l)).sum::<f64>() / losses.len() as f64;
        if !loss.is_finite() {
            return Err(DistillError::Data(format!("the loss became {loss} at step {}", state.step)));
        }
        // The worst fresh rays enter the pool (a ring once full).
        if hard_rows > 0 {
            let mut order: Vec<usize> = (0..fresh).collect();
            order.sort_by(|&a, &b| losses[b].total_cmp(&losses[a]));
            for &k in order.iter().take(hard_rows) {
                if state.pool.len() < options.hard_pool {
                    state.pool.push(refs[k]);
                } else {
                    state.pool[state.pool_next] = refs[k];
                    state.pool_next = (state.pool_next + 1) % options.hard_pool;
                }
            }
        }
        adam.set_learning_rate(options.learning_rate_at(state.step));
        adam.step(network.params_mut(), &grad)?;
        state.step += 1;
        window.0 += loss;
        window.1 += 1;
        if state.step.is_multiple_of(CURVE_EVERY) || state.step == total {
            state.curve.push((state.step, (window.0 / f64::from(window.1)) as f32));
            window = (0.0, 0);
        }
        on_step(DistillStep { step: state.step, steps: total, loss: loss as f32, fine_tuning });
        if (checkpoint_every > 0 && state.step.is_multiple_of(checkpoint_every)) || state.step == total {
            state.adam_steps = adam.steps();
            state.rng = rng.state();
            let (m, v) = adam.moments();
            checkpoint(&Checkpoint {
                state: state.clone(),
                params: network.params().to_vec(),
                m: m.to_vec(),
                v: v.to_vec(),
            })?;
        }
    }
    Ok((network, state))
}

/// Mean loss of `network` over every ray of `set` (no gradient).
pub fn mean_loss(network: &ResidualMlp, sampling: &RaySampling, set: &RaySet, depth_weight: f32) -> f64 {
    if set.is_empty() {
        return 0.0;
    }
    let refs: Vec<u64> = (0..set.len() as u64).collect();
    let (_, losses) = batch_gradient(network, sampling, [set, set], &refs, depth_weight);
    losses.iter().map(|&l| f64::from(l)).sum::<f64>() / losses.len() as f64
}

#[cfg(test)]
mod tests;
