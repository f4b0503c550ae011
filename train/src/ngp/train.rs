//! Training a radiance field from posed RGBA images on the CPU.
//!
//! One step (i-NGP, section 5.4, adapted to 2 cores):
//! 1. draw random pixels of random training views; the number of rays adapts so that a step
//!    evaluates about `samples_per_step` density samples (i-NGP's fixed sample budget);
//! 2. in parallel over chunks of rays (rayon), each with its own gradient buffers for the two
//!    MLPs: march the occupied cells, evaluate density in chunks of samples until the ray's
//!    transmittance falls below 1e-3, evaluate colour, composite (NEPHELE eq. 4), take the L2
//!    loss on premultiplied RGBA against the pixel, and back-propagate through compositing,
//!    the colour MLP and the density MLP by hand, keeping each sample's position and the
//!    gradient of its hash encoding;
//! 3. reduce the MLP gradients; scatter the encoding gradients into the hash table one level
//!    per task (levels own disjoint parameters, so no locks and no per-thread table copies);
//! 4. Adam on each parameter group (sparse for the table, with L2 decay for the MLPs);
//! 5. every `occupancy_every` steps, refresh the occupancy grid from an exponential moving
//!    maximum of the density at random points of a quarter of the candidate cells (those of
//!    the training views' visual hull).

use glam::Vec3;
use rayon::prelude::*;

use crate::dataset::Dataset;
use crate::targets::{PixelCheck, TargetSpace, is_dropped, premultiplied_targets};
use nephele_geometry::camera::Camera;
use nephele_imaging::image::RgbaImage;
use nephele_nn::{Adam, AdamConfig, MlpWorkspace, sh_coefficient_count, sh_encode};
use nephele_pathtracer::sampling::Rng;

use nephele_kernels::ngp::NgpError;
use nephele_kernels::ngp::field::{
    EARLY_STOP_TRANSMITTANCE, FieldConfig, FieldScratch, RadianceField, density_activation,
};
use nephele_kernels::ngp::march::Marcher;
use nephele_kernels::ngp::occupancy::{CoverageMask, OccupancyGrid, visual_hull};

/// Density samples per network batch along one ray during training.
const TRAIN_CHUNK: usize = 32;
/// Rays per parallel task.
const RAYS_PER_TASK: usize = 128;
/// Decay of the occupancy grid's moving maximum per update (i-NGP).
const OCCUPANCY_DECAY: f32 = 0.95;
/// Opacity a skipped cell may hide at most: a cell is empty when `sigma * cell_size` is
/// below this. 1e-2 rather than i-NGP's much lower threshold: after the few hundred steps a
/// CPU budget allows, free space still holds densities of 0.01-0.05 that would keep the
/// whole visual hull occupied (a faint halo, and samples spent in it); surfaces are orders of
/// magnitude denser.
const OCCUPANCY_OPACITY: f32 = 1e-2;

/// Training hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainConfig {
    pub seed: u64,
    /// Density samples per step (the number of rays adapts to it).
    pub samples_per_step: usize,
    /// Adam learning rate at the start; decays tenfold over the second half of training.
    pub learning_rate: f32,
    /// Steps between occupancy updates.
    pub occupancy_every: u32,
    /// Start from the visual hull of the training views rather than the whole box, and fit
    /// the box to it.
    pub carve: bool,
    /// Half the side of the initial box around the cameras' common focus; `None`: half the
    /// mean camera distance.
    pub initial_half_size: Option<f32>,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            seed: 0,
            samples_per_step: 1 << 16,
            learning_rate: 1e-2,
            occupancy_every: 16,
            carve: true,
            initial_half_size: None,
        }
    }
}

/// One training view: its camera and its pixels as premultiplied RGBA in the image's
/// (sRGB-encoded) space.
#[derive(Debug, Clone)]
struct TrainView {
    camera: Camera,
    pixels: Vec<[f32; 4]>,
}

/// Figures of one step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepStats {
    /// Mean squared error over the rays' premultiplied RGBA.
    pub loss: f32,
    pub rays: usize,
    /// Density samples evaluated (and back-propagated).
    pub samples: usize,
    /// Fraction of occupancy cells set.
    pub occupied_fraction: f32,
    pub learning_rate: f32,
    /// Wall-clock seconds of the phases: rays through the MLPs forward and backward, the
    /// hash-grid scatter, the Adam updates, the occupancy refresh (0 on most steps).
    pub seconds_rays: f32,
    pub seconds_grid: f32,
    pub seconds_adam: f32,
    pub seconds_occupancy: f32,
}

/// A ray to train on: a pixel's centre ray and its target (sRGB premultiplied by alpha, then
/// alpha).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainingRay {
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
    /// Jitter of the first sample in `[0, 1)` steps.
    pub offset: f32,
    pub target: [f32; 4],
}

/// The loss and the parameters' gradients of a batch of rays (the mean over rays and
/// channels of the squared error).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BatchGradients {
    /// Mean loss per ray.
    pub loss: f32,
    /// Density samples taken.
    pub samples: usize,
    pub density: Vec<f32>,
    pub color: Vec<f32>,
    /// Seconds spent on the rays (forward and backward through the MLPs), and on scattering
    /// the encoding gradients into the hash table.
    pub seconds_rays: f32,
    pub seconds_grid: f32,
}

/// What one parallel task returns.
#[derive(Debug, Default)]
struct TaskOut {
    grad_density: Vec<f32>,
    grad_color: Vec<f32>,
    points: Vec<[f32; 3]>,
    d_encoding: Vec<f32>,
    loss: f64,
    samples: usize,
}

/// Per-task buffers for one ray.
#[derive(Debug, Default)]
struct RayBuffers {
    points: Vec<[f32; 3]>,
    ts: Vec<f32>,
    encoded: Vec<f32>,
    density_out: Vec<f32>,
    sigma: Vec<f32>,
    density_ws: Vec<MlpWorkspace>,
    color_in: Vec<f32>,
    color_ws: MlpWorkspace,
    d_color_out: Vec<f32>,
    d_color_in: Vec<f32>,
    d_density_out: Vec<f32>,
    d_encoding: Vec<f32>,
    d_chunk_out: Vec<f32>,
    d_chunk_in: Vec<f32>,
    chunk_rows: Vec<usize>,
    sh: Vec<f32>,
}

/// The training state.
#[derive(Debug)]
pub struct Trainer {
    field: RadianceField,
    config: TrainConfig,
    views: Vec<TrainView>,
    /// Cells that may ever be occupied (the visual hull, or all).
    candidates: Vec<u32>,
    /// Moving maximum of the density per cell.
    density_ema: Vec<f32>,
    occupancy_threshold: f32,
    adam_grid: Adam,
    adam_density: Adam,
    adam_color: Adam,
    grad_grid: Vec<f32>,
    rng: Rng,
    steps: u64,
    rays_per_step: usize,
    occupancy_updates: u64,
    pixel_check: PixelCheck,
}

/// The point closest (least squares) to all cameras' optical axes: what they look at.
pub fn common_focus(cameras: &[Camera]) -> Vec3 {
    let mut a = glam::Mat3::ZERO;
    let mut b = Vec3::ZERO;
    for c in cameras {
        let d = c.forward().normalize_or_zero();
        let m = glam::Mat3::IDENTITY - glam::Mat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * c.position();
    }
    if a.determinant().abs() < 1e-6 {
        // All axes parallel: no unique focus; fall back to the cameras' centroid.
        return cameras.iter().map(|c| c.position()).sum::<Vec3>() / cameras.len().max(1) as f32;
    }
    a.inverse() * b
}

impl Trainer {
    /// Prepares training on the views of `dataset` (images as loaded: sRGB, straight alpha).
    pub fn from_dataset(field_config: FieldConfig, config: TrainConfig, dataset: &Dataset) -> Result<Self, NgpError> {
        let mut views = Vec::with_capacity(dataset.views.len());
        for v in &dataset.views {
            let camera =
                Camera::from_fov_x(v.image.width(), v.image.height(), dataset.camera_angle_x, v.camera_to_world)
                    .map_err(|e| NgpError::Invalid(format!("view {}: {e}", v.name)))?;
            views.push((camera, &v.image));
        }
        Self::new(field_config, config, &views)
    }

    /// Prepares training on posed images: fits the box (and, with `carve`, the visual hull)
    /// and initialises the field.
    pub fn new(
        field_config: FieldConfig,
        config: TrainConfig,
        views: &[(Camera, &RgbaImage)],
    ) -> Result<Self, NgpError> {
        field_config.validate()?;
        if views.is_empty() {
            return Err(NgpError::Invalid("no training views".into()));
        }
        if config.samples_per_step < 256 || config.samples_per_step > 1 << 24 {
            return Err(NgpError::Invalid(format!("samples per step {} not in 256..=2^24", config.samples_per_step)));
        }
        for (camera, image) in views {
            if (camera.width(), camera.height()) != (image.width(), image.height()) {
                return Err(NgpError::Invalid("a view's camera and image differ in size".into()));
            }
        }
        let cameras: Vec<Camera> = views.iter().map(|(c, _)| *c).collect();
        let focus = common_focus(&cameras);
        let mean_distance = cameras.iter().map(|c| c.position().distance(focus)).sum::<f32>() / cameras.len() as f32;
        let half = config.initial_half_size.unwrap_or(0.5 * mean_distance);
        if !(half.is_finite() && half > 0.0 && focus.is_finite()) {
            return Err(NgpError::Invalid(format!("cannot place the scene box (focus {focus}, half size {half})")));
        }
        let res = field_config.occupancy_resolution;
        let (mut min, mut size) = (focus - Vec3::splat(half), 2.0 * half);
        let mut hull = OccupancyGrid::filled(res, true);
        if config.carve {
            let masks: Vec<CoverageMask> = views.par_iter().map(|(c, img)| CoverageMask::new(*c, img, 0.0)).collect();
            let first = visual_hull(min, Vec3::splat(size), res, &masks)
                .ok_or_else(|| NgpError::Invalid("bad occupancy resolution".into()))?;
            let (lo, hi) = first
                .occupied_bounds()
                .ok_or_else(|| NgpError::Invalid("the training images show no matter (visual hull empty)".into()))?;
            // Fit a cube around the hull with a margin of two cells, then carve again in it.
            let (lo, hi) = (min + lo * size, min + hi * size);
            let side = (hi - lo).max_element() + 4.0 * size / res as f32;
            min = 0.5 * (lo + hi) - Vec3::splat(0.5 * side);
            size = side;
            hull = visual_hull(min, Vec3::splat(size), res, &masks)
                .ok_or_else(|| NgpError::Invalid("bad occupancy resolution".into()))?;
            if hull.occupied_count() == 0 {
                return Err(NgpError::Invalid("the training images show no matter (visual hull empty)".into()));
            }
        }
        let mut field = RadianceField::new(field_config, min, size, config.seed)?;
        field.set_occupancy(hull.clone())?;
        let candidates: Vec<u32> = (0..hull.cell_count()).filter(|&i| hull.get(i)).map(|i| i as u32).collect();
        let cell_size = size / res as f32;
        let occupancy_threshold = OCCUPANCY_OPACITY / cell_size;
        let mut density_ema = vec![0.0f32; hull.cell_count()];
        for &c in &candidates {
            // Start occupied: two thresholds decay below one in about 14 updates unless the
            // density confirms the cell.
            density_ema[c as usize] = 2.0 * occupancy_threshold;
        }
        let mut pixel_check = PixelCheck::default();
        let train_views: Vec<TrainView> = views
            .iter()
            .map(|(camera, image)| TrainView {
                camera: *camera,
                pixels: premultiplied_targets(image, TargetSpace::Srgb, &mut pixel_check),
            })
            .collect();
        pixel_check.verdict().map_err(|e| NgpError::Invalid(e.to_string()))?;
        if pixel_check.repaired_any() {
            tracing::warn!("{}", pixel_check.summary());
        }
        let mlp_adam = AdamConfig { learning_rate: config.learning_rate, weight_decay: 1e-6, ..AdamConfig::default() };
        Ok(Trainer {
            adam_grid: Adam::new(
                AdamConfig { learning_rate: config.learning_rate, ..AdamConfig::default() },
                field.grid.num_params(),
            ),
            adam_density: Adam::new(mlp_adam, field.density.num_params()),
            adam_color: Adam::new(mlp_adam, field.color.num_params()),
            grad_grid: vec![0.0; field.grid.num_params()],
            field,
            config,
            views: train_views,
            candidates,
            density_ema,
            occupancy_threshold,
            rng: Rng::new(config.seed, 0x0074_7261_696e),
            steps: 0,
            rays_per_step: (config.samples_per_step / 64).max(64),
            occupancy_updates: 0,
            pixel_check,
        })
    }

    pub fn field(&self) -> &RadianceField {
        &self.field
    }

    pub fn into_field(self) -> RadianceField {
        self.field
    }

    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// What the check of the training pixels clamped and dropped.
    pub fn pixel_check(&self) -> PixelCheck {
        self.pixel_check
    }

    /// Number of cells the occupancy may ever set (the visual hull).
    pub fn candidate_cells(&self) -> usize {
        self.candidates.len()
    }

    /// One optimisation step; `progress` in `[0, 1]` (fraction of the training budget spent)
    /// drives the learning-rate schedule.
    pub fn step(&mut self, progress: f32) -> Result<StepStats, NgpError> {
        let progress = progress.clamp(0.0, 1.0);
        let lr = self.config.learning_rate * 0.1f32.powf(((progress - 0.5) / 0.5).max(0.0));
        self.adam_grid.set_learning_rate(lr);
        self.adam_density.set_learning_rate(lr);
        self.adam_color.set_learning_rate(lr);

        let tasks = self.draw_rays(self.rays_per_step);
        let n_rays = tasks.len();
        let batch = batch_gradients(&self.field, &tasks, &mut self.grad_grid)?;
        let (grad_density, grad_color, samples) = (batch.density, batch.color, batch.samples);
        let clock = std::time::Instant::now();
        self.adam_grid.step_sparse(self.field.grid.params_mut(), &self.grad_grid)?;
        self.adam_density.step(self.field.density.params_mut(), &grad_density)?;
        self.adam_color.step(self.field.color.params_mut(), &grad_color)?;
        let seconds_adam = clock.elapsed().as_secs_f32();
        let clock = std::time::Instant::now();

        self.steps += 1;
        // Adapt the ray count to the sample budget (i-NGP), smoothing the estimate.
        let per_ray = (samples as f32 / n_rays.max(1) as f32).max(1.0);
        let wanted = (self.config.samples_per_step as f32 / per_ray) as usize;
        self.rays_per_step = ((self.rays_per_step + wanted.clamp(64, 1 << 18)) / 2).max(64);
        if self.steps.is_multiple_of(u64::from(self.config.occupancy_every.max(1))) {
            self.update_occupancy()?;
        }
        let seconds_occupancy = clock.elapsed().as_secs_f32();
        let occupancy = self.field.occupancy();
        Ok(StepStats {
            loss: batch.loss,
            rays: n_rays,
            samples,
            occupied_fraction: occupancy.occupied_count() as f32 / occupancy.cell_count() as f32,
            learning_rate: lr,
            seconds_rays: batch.seconds_rays,
            seconds_grid: batch.seconds_grid,
            seconds_adam,
            seconds_occupancy,
        })
    }

    fn draw_rays(&mut self, count: usize) -> Vec<TrainingRay> {
        let mut tasks = Vec::with_capacity(count);
        for _ in 0..count {
            let v = &self.views[(self.rng.next_u32() as usize) % self.views.len()];
            let (w, h) = (v.camera.width(), v.camera.height());
            let x = self.rng.next_u32() % w;
            let y = self.rng.next_u32() % h;
            let ray = v.camera.pixel_center_ray(x, y);
            let offset = self.rng.next_f32();
            let target = v.pixels[(y * w + x) as usize];
            if is_dropped(&target) {
                // A pixel the check dropped (NaN or infinite): never trained.
                continue;
            }
            tasks.push(TrainingRay { origin: ray.origin, dir: ray.direction, offset, target });
        }
        tasks
    }

    /// Refreshes the occupancy grid: decay every moving maximum, evaluate the density at a
    /// random point of a quarter of the candidate cells, set the bits above the threshold.
    fn update_occupancy(&mut self) -> Result<(), NgpError> {
        let update = self.occupancy_updates;
        self.occupancy_updates += 1;
        let res = self.field.occupancy().resolution();
        for &c in &self.candidates {
            self.density_ema[c as usize] *= OCCUPANCY_DECAY;
        }
        let selected: Vec<u32> = self
            .candidates
            .iter()
            .copied()
            .filter(|&c| nephele_pathtracer::sampling::splitmix64(u64::from(c)).wrapping_add(update).is_multiple_of(4))
            .collect();
        let seed = self.config.seed ^ update.wrapping_mul(0x9E37_79B9);
        let field = &self.field;
        let densities: Vec<(u32, f32)> = selected
            .par_chunks(1024)
            .enumerate()
            .map(|(k, cells)| {
                let mut rng = Rng::new(seed, k as u64);
                let mut scratch = FieldScratch::new();
                let points: Vec<Vec3> = cells
                    .iter()
                    .map(|&c| {
                        let center = field.occupancy().cell_center(c as usize);
                        let jitter = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5;
                        field.min + (center + jitter / res as f32) * field.size
                    })
                    .collect();
                let mut sigma = vec![0.0f32; points.len()];
                let ok = field.density_batch(&points, &mut sigma, &mut scratch).is_ok();
                cells.iter().zip(sigma).map(|(&c, s)| (c, if ok { s } else { f32::MAX })).collect::<Vec<_>>()
            })
            .flatten()
            .collect();
        for (c, s) in densities {
            let e = &mut self.density_ema[c as usize];
            *e = e.max(s);
        }
        let mut grid = self.field.occupancy().clone();
        for &c in &self.candidates {
            grid.set(c as usize, self.density_ema[c as usize] > self.occupancy_threshold);
        }
        grid.rebuild_coarse();
        self.field.set_occupancy(grid)
    }
}

/// Forward and backward of a batch of training rays through `field`: the mean loss and the
/// MLPs' gradients, and the hash table's gradient written into `grad_grid` (zeroed here;
/// `field.grid.num_params()` long). A ray that finds no occupied cell is trained towards
/// transparency by its loss alone (no parameter takes its gradient).
pub fn batch_gradients(
    field: &RadianceField,
    rays: &[TrainingRay],
    grad_grid: &mut [f32],
) -> Result<BatchGradients, NgpError> {
    if grad_grid.len() != field.grid.num_params() {
        return Err(NgpError::Invalid(format!(
            "grid gradient of {} values for a table of {}",
            grad_grid.len(),
            field.grid.num_params()
        )));
    }
    let clock = std::time::Instant::now();
    let n_rays = rays.len();
    let outs: Vec<TaskOut> = rays
        .par_chunks(RAYS_PER_TASK)
        .map(|chunk| {
            let mut out = TaskOut {
                grad_density: vec![0.0; field.density.num_params()],
                grad_color: vec![0.0; field.color.num_params()],
                ..TaskOut::default()
            };
            let mut buffers = RayBuffers::default();
            for ray in chunk {
                train_ray(field, ray, n_rays, &mut buffers, &mut out);
            }
            out
        })
        .collect();

    // Reduce.
    let mut density = vec![0.0f32; field.density.num_params()];
    let mut color = vec![0.0f32; field.color.num_params()];
    let (mut loss, mut samples, mut points_total) = (0.0f64, 0usize, 0usize);
    for o in &outs {
        for (g, v) in density.iter_mut().zip(&o.grad_density) {
            *g += v;
        }
        for (g, v) in color.iter_mut().zip(&o.grad_color) {
            *g += v;
        }
        loss += o.loss;
        samples += o.samples;
        points_total += o.points.len();
    }
    let enc_dim = field.grid.output_dim();
    let mut points = Vec::with_capacity(points_total);
    let mut d_encoding = Vec::with_capacity(points_total * enc_dim);
    for o in outs {
        points.extend_from_slice(&o.points);
        d_encoding.extend_from_slice(&o.d_encoding);
    }
    let seconds_rays = clock.elapsed().as_secs_f32();
    let clock = std::time::Instant::now();
    grad_grid.par_chunks_mut(1 << 16).for_each(|c| c.fill(0.0));
    field.grid.backward_batch_parallel(&points, &d_encoding, grad_grid)?;
    Ok(BatchGradients {
        loss: (loss / n_rays.max(1) as f64) as f32,
        samples,
        density,
        color,
        seconds_rays,
        seconds_grid: clock.elapsed().as_secs_f32(),
    })
}

/// Forward and backward of one training ray; accumulates into `out`.
fn train_ray(field: &RadianceField, ray: &TrainingRay, n_rays: usize, b: &mut RayBuffers, out: &mut TaskOut) {
    let dt = field.step_size();
    let geo = 1 + field.config.geo_features;
    let enc_dim = field.grid.output_dim();
    let sh_len = sh_coefficient_count(field.config.sh_degree);
    let max_samples = 2 * field.config.steps_per_diagonal as usize;
    b.points.clear();
    b.ts.clear();
    b.encoded.clear();
    b.density_out.clear();
    b.sigma.clear();
    b.chunk_rows.clear();
    if let Some(mut marcher) =
        Marcher::new(ray.origin, ray.dir, field.min, field.size, dt, 0.0, ray.offset, field.occupancy.resolution())
    {
        let mut transmittance = 1.0f32;
        'march: while b.points.len() < max_samples {
            let start = b.points.len();
            while b.points.len() - start < TRAIN_CHUNK {
                match marcher.next(&field.occupancy) {
                    Some((t, p)) => {
                        b.ts.push(t);
                        b.points.push(p.to_array());
                    }
                    None => break,
                }
            }
            let n = b.points.len() - start;
            if n == 0 {
                break;
            }
            b.encoded.resize((start + n) * enc_dim, 0.0);
            if field.grid.encode_batch(&b.points[start..], &mut b.encoded[start * enc_dim..]).is_err() {
                break;
            }
            let c = b.chunk_rows.len();
            if b.density_ws.len() <= c {
                b.density_ws.push(MlpWorkspace::new());
            }
            let Ok(y) = field.density.forward(&b.encoded[start * enc_dim..], &mut b.density_ws[c]) else {
                break;
            };
            b.density_out.extend_from_slice(y);
            b.chunk_rows.push(n);
            for i in start..start + n {
                let sigma = density_activation(b.density_out[i * geo]);
                b.sigma.push(sigma);
                transmittance *= (-sigma * dt).exp();
                if transmittance < EARLY_STOP_TRANSMITTANCE {
                    // Keep the samples up to here; later ones of the chunk are dropped.
                    let keep = i + 1;
                    b.points.truncate(keep);
                    b.ts.truncate(keep);
                    break 'march;
                }
            }
        }
    }
    let k = b.points.len();
    let target = ray.target;
    if k == 0 {
        out.loss += target.iter().map(|v| f64::from(v * v)).sum::<f64>() / 4.0;
        return;
    }
    out.samples += k;

    // Colour network over the kept samples.
    b.sh.resize(sh_len, 0.0);
    sh_encode(ray.dir.to_array(), field.config.sh_degree, &mut b.sh);
    let width = geo + sh_len;
    b.color_in.clear();
    for i in 0..k {
        b.color_in.extend_from_slice(&b.density_out[i * geo..(i + 1) * geo]);
        b.color_in.extend_from_slice(&b.sh);
    }
    let Ok(rgb) = field.color.forward(&b.color_in, &mut b.color_ws) else {
        return;
    };
    let rgb = rgb.to_vec();

    // Composite (NEPHELE eq. 4).
    let mut transmittance = 1.0f32;
    let mut pred = [0.0f32; 4];
    let mut weights = Vec::with_capacity(k);
    let mut t_after = Vec::with_capacity(k);
    for i in 0..k {
        let alpha = 1.0 - (-b.sigma[i] * dt).exp();
        let w = transmittance * alpha;
        transmittance *= 1.0 - alpha;
        weights.push(w);
        t_after.push(transmittance);
        for c in 0..3 {
            pred[c] += w * rgb[i * 3 + c];
        }
        pred[3] += w;
    }
    // L = mean over rays and channels of (pred - target)^2.
    let scale = 2.0 / (4.0 * n_rays as f32);
    let mut d_pred = [0.0f32; 4];
    let mut ray_loss = 0.0f64;
    for c in 0..4 {
        let e = pred[c] - target[c];
        ray_loss += f64::from(e * e);
        d_pred[c] = scale * e;
    }
    out.loss += ray_loss / 4.0;

    // dL/dc_i = w_i dL/dC; dL/dsigma_i = dt (T_{i+1} s_i - sum_{j>i} w_j s_j) with
    // s_i = c_i . dL/dC + dL/dA.
    b.d_color_out.clear();
    b.d_color_out.resize(k * 3, 0.0);
    let s: Vec<f32> = (0..k).map(|i| (0..3).map(|c| rgb[i * 3 + c] * d_pred[c]).sum::<f32>() + d_pred[3]).collect();
    let mut d_sigma = vec![0.0f32; k];
    let mut suffix = 0.0f32;
    for i in (0..k).rev() {
        d_sigma[i] = dt * (t_after[i] * s[i] - suffix);
        suffix += weights[i] * s[i];
        for (d, g) in b.d_color_out[i * 3..i * 3 + 3].iter_mut().zip(&d_pred) {
            *d = weights[i] * g;
        }
    }
    b.d_color_in.resize(k * width, 0.0);
    if field
        .color
        .backward(&b.color_in, &mut b.color_ws, &b.d_color_out, &mut out.grad_color, Some(&mut b.d_color_in))
        .is_err()
    {
        return;
    }
    // Gradient at the density network's outputs: the colour network's input gradient on the
    // geometric part, plus the compositing gradient through sigma = exp(raw) on channel 0.
    b.d_density_out.clear();
    for (i, (ds, sigma)) in d_sigma.iter().zip(&b.sigma).enumerate() {
        b.d_density_out.extend_from_slice(&b.d_color_in[i * width..i * width + geo]);
        b.d_density_out[i * geo] += ds * sigma;
    }
    b.d_encoding.resize(k * enc_dim, 0.0);
    // Backward chunk by chunk through the workspaces of the forward pass; rows past `k`
    // (evaluated, then dropped by early termination) get zero gradient.
    let mut start = 0;
    for c in 0..b.chunk_rows.len() {
        if start >= k {
            break;
        }
        let rows = b.chunk_rows[c];
        let used = rows.min(k - start);
        b.d_chunk_out.clear();
        b.d_chunk_out.extend_from_slice(&b.d_density_out[start * geo..(start + used) * geo]);
        b.d_chunk_out.resize(rows * geo, 0.0);
        b.d_chunk_in.resize(rows * enc_dim, 0.0);
        let input = &b.encoded[start * enc_dim..(start + rows) * enc_dim];
        if field
            .density
            .backward(input, &mut b.density_ws[c], &b.d_chunk_out, &mut out.grad_density, Some(&mut b.d_chunk_in))
            .is_err()
        {
            return;
        }
        b.d_encoding[start * enc_dim..(start + used) * enc_dim].copy_from_slice(&b.d_chunk_in[..used * enc_dim]);
        start += rows;
    }
    out.points.extend_from_slice(&b.points[..k]);
    out.d_encoding.extend_from_slice(&b.d_encoding[..k * enc_dim]);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Loss and gradients of one ray through an untrained (foggy, never terminating) field.
    fn ray_loss(field: &RadianceField, ray: &TrainingRay) -> (f64, TaskOut) {
        let mut out = TaskOut {
            grad_density: vec![0.0; field.density.num_params()],
            grad_color: vec![0.0; field.color.num_params()],
            ..TaskOut::default()
        };
        train_ray(field, ray, 1, &mut RayBuffers::default(), &mut out);
        (out.loss, out)
    }

    #[test]
    fn ray_gradients_match_finite_differences() {
        let config = FieldConfig::small_test();
        let mut field = RadianceField::new(config, Vec3::splat(-1.0), 2.0, 8).expect("field");
        // Larger hash features than the default 1e-4 so that their gradients matter.
        let mut rng = Rng::new(1, 2);
        for p in field.grid.params_mut() {
            *p = 0.5 * (rng.next_f32() - 0.5);
        }
        let ray = TrainingRay {
            origin: Vec3::new(-3.0, 0.1, 0.2),
            dir: Vec3::new(1.0, 0.1, -0.05).normalize(),
            offset: 0.3,
            target: [0.3, 0.1, 0.2, 0.8],
        };
        let (loss, out) = ray_loss(&field, &ray);
        assert!(loss > 0.0 && out.samples > 20, "{loss} {}", out.samples);
        let mut grad_grid = vec![0.0; field.grid.num_params()];
        field.grid.backward_batch(&out.points, &out.d_encoding, &mut grad_grid).expect("grid backward");

        let h = 1e-3f32;
        let check = |analytic: f32, up: f64, down: f64, what: String| {
            let fd = (up - down) / (2.0 * f64::from(h));
            assert!((fd - f64::from(analytic)).abs() < 0.05 * fd.abs() + 2e-5, "{what}: fd {fd} analytic {analytic}");
        };
        // The largest gradients of each parameter group.
        let top = |g: &[f32]| {
            let mut idx: Vec<usize> = (0..g.len()).collect();
            idx.sort_by(|&a, &b| g[b].abs().total_cmp(&g[a].abs()));
            idx.truncate(6);
            idx
        };
        for i in top(&out.grad_density) {
            let mut f = field.clone();
            f.density.params_mut()[i] += h;
            let up = ray_loss(&f, &ray).0;
            f.density.params_mut()[i] -= 2.0 * h;
            let down = ray_loss(&f, &ray).0;
            check(out.grad_density[i], up, down, format!("density param {i}"));
        }
        for i in top(&out.grad_color) {
            let mut f = field.clone();
            f.color.params_mut()[i] += h;
            let up = ray_loss(&f, &ray).0;
            f.color.params_mut()[i] -= 2.0 * h;
            let down = ray_loss(&f, &ray).0;
            check(out.grad_color[i], up, down, format!("colour param {i}"));
        }
        for i in top(&grad_grid) {
            let mut f = field.clone();
            f.grid.params_mut()[i] += h;
            let up = ray_loss(&f, &ray).0;
            f.grid.params_mut()[i] -= 2.0 * h;
            let down = ray_loss(&f, &ray).0;
            check(grad_grid[i], up, down, format!("grid param {i}"));
        }
    }
}
