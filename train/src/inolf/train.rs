//! Training the i-NOLF heads from posed RGBA images (NEPHELE section 4.2).
//!
//! Each step draws a batch of pixels through an error map (16x16-pixel tiles of every view,
//! drawn in proportion to a running average of their loss, mixed with uniform draws so that
//! no tile starves), marches their rays through the density cubes to get hit point and
//! coarse opacity, runs both heads forward and backward with the loss of eq. 8, and takes an
//! Adam step on the hash grid, both MLPs and the PSH features. Rays that miss the cubes are
//! not trained: the kernel renders them empty whatever the heads say.

use glam::Vec3;
use rayon::prelude::*;

use crate::dataset::Dataset;
use crate::targets::{PixelCheck, TargetSpace, is_dropped, premultiplied_targets};
use nephele_geometry::SplitMix64;
use nephele_geometry::camera::{Camera, CameraError, Ray};
use nephele_kernels::inolf::cubes::{DensityCubes, HitRule, MAX_BLEND_SAMPLES, MarchHit};
use nephele_kernels::inolf::encoding::Corners;
use nephele_kernels::inolf::kernel::{HIT_OPACITY, RAY_NEAR};
use nephele_kernels::inolf::model::{
    DIFFUSE_OUT, InolfModel, LossSpace, ModelError, SPECULAR_OUT, head_gradients, specular_activation,
    specular_activation_derivative,
};
use nephele_nn::{Adam, AdamConfig, LazyAdam, MlpWorkspace};

/// One training view: its camera and the target per pixel (linear RGB premultiplied by
/// alpha, then alpha), row-major.
#[derive(Debug, Clone)]
pub struct TrainingView {
    pub camera: Camera,
    pub target: Vec<[f32; 4]>,
}

/// The views of a loaded NeRF-synthetic split, as training targets, and what the check of
/// their pixels clamped and dropped (see [`crate::targets`]; refuse the set with
/// [`PixelCheck::verdict`]).
pub fn training_views(dataset: &Dataset) -> Result<(Vec<TrainingView>, PixelCheck), CameraError> {
    let mut check = PixelCheck::default();
    let views = dataset
        .views
        .iter()
        .map(|v| {
            let camera =
                Camera::from_fov_x(v.image.width(), v.image.height(), dataset.camera_angle_x, v.camera_to_world)?;
            let target = premultiplied_targets(&v.image, TargetSpace::Linear, &mut check);
            Ok(TrainingView { camera, target })
        })
        .collect::<Result<Vec<_>, CameraError>>()?;
    Ok((views, check))
}

/// Marches the centre ray of every pixel of every view (in parallel) and returns the hit
/// points of the rays that hit: the occupancy the PSH is built from.
pub fn collect_hit_points(cubes: &DensityCubes, views: &[TrainingView], stride: u32) -> Vec<Vec3> {
    views.par_iter().flat_map_iter(|v| hitting_rays(cubes, v, stride).map(|(ray, hit)| ray.at(hit.t))).collect()
}

/// The centre rays of every `stride`-th pixel of `view` each way that hit the cubes, with
/// their march.
fn hitting_rays<'a>(
    cubes: &'a DensityCubes,
    view: &'a TrainingView,
    stride: u32,
) -> impl Iterator<Item = (Ray, MarchHit)> + 'a {
    let stride = stride.max(1) as usize;
    let (w, h) = (view.camera.width(), view.camera.height());
    (0..h).step_by(stride).flat_map(move |y| (0..w).step_by(stride).map(move |x| (x, y))).filter_map(|(x, y)| {
        let ray = view.camera.pixel_center_ray(x, y);
        let hit = cubes.march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY);
        (hit.opacity >= HIT_OPACITY).then_some((ray, hit))
    })
}

/// Share of hit rays above which a bake takes [`HitRule::SEE_THROUGH`] (see
/// [`choose_hit_rule`]).
pub const LAYERED_SHARE: f64 = 0.5;

/// The share of the views' hitting pixel-centre rays (every `stride`-th pixel each way) whose
/// hit point the cubes' hit rule moves to a layer behind the sample of largest weight.
pub fn layered_share(cubes: &DensityCubes, views: &[TrainingView], stride: u32) -> f64 {
    let (hits, layered) = views
        .par_iter()
        .map(|v| {
            hitting_rays(cubes, v, stride).fold((0u64, 0u64), |(n, l), (_, hit)| (n + 1, l + u64::from(hit.layered)))
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if hits == 0 { 0.0 } else { layered as f64 / hits as f64 }
}

/// The hit rule of a bake whose training rays see a second layer `share` of the time: the
/// layered rule for a see-through object (most rays), the median depth otherwise. Measured on
/// the built-in objects (64 views of 128x128): the glass shell 0.88, the glossy pair 0.09, the
/// diffuse object 0.02; the layered rule took the shell from 20.53 to 23.97 dB on held-out
/// views and cost the opaque objects 0.3-0.4 dB (BENCHMARKS.md, 2026-12-05f). The median
/// depth against the largest weight on opaque objects: BENCHMARKS.md, 2026-12-07c.
pub fn choose_hit_rule(share: f64) -> HitRule {
    if share > LAYERED_SHARE { HitRule::SEE_THROUGH } else { HitRule::MedianDepth }
}

/// Training settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainOptions {
    pub steps: u32,
    /// Rays per step.
    pub batch: usize,
    pub learning_rate: f32,
    /// Weight of the opacity term of the loss.
    pub opacity_weight: f32,
    /// Where the colour term compares a pixel with its target.
    pub loss_space: LossSpace,
    /// Error-map tile side in pixels.
    pub tile: u32,
    /// Share of the batch drawn uniformly instead of through the error map.
    pub uniform_fraction: f32,
    /// Decoupled weight decay (AdamW) of the PSH features: features seen by few training rays
    /// are pulled towards zero, leaving view dependence to the specular MLP (issue 18's
    /// regulariser for held-out views). 0: off.
    pub psh_decay: f32,
    /// The same for the diffuse hash grid (baked into the diffuse cubes).
    pub grid_decay: f32,
    pub seed: u64,
}

impl Default for TrainOptions {
    fn default() -> Self {
        TrainOptions {
            steps: 2000,
            batch: 4096,
            learning_rate: 1e-2,
            opacity_weight: 1.0,
            loss_space: LossSpace::default(),
            tile: 16,
            uniform_fraction: 0.25,
            psh_decay: 0.0,
            grid_decay: 0.0,
            seed: 1,
        }
    }
}

/// What training reached.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TrainReport {
    pub steps: u32,
    /// Mean loss of the last step's hitting rays.
    pub last_loss: f32,
    /// Running average of the loss over the last ~100 steps.
    pub smoothed_loss: f32,
    pub rays: u64,
    pub rays_hit: u64,
}

/// Tiles of all views with a running loss each.
#[derive(Debug)]
struct ErrorMap {
    /// `(view, x0, y0, w, h)` per tile.
    tiles: Vec<(u32, u32, u32, u32, u32)>,
    error: Vec<f32>,
    cdf: Vec<f64>,
}

impl ErrorMap {
    fn new(views: &[TrainingView], tile: u32) -> ErrorMap {
        let tile = tile.max(1);
        let mut tiles = Vec::new();
        for (i, v) in views.iter().enumerate() {
            let (w, h) = (v.camera.width(), v.camera.height());
            for y0 in (0..h).step_by(tile as usize) {
                for x0 in (0..w).step_by(tile as usize) {
                    tiles.push((i as u32, x0, y0, tile.min(w - x0), tile.min(h - y0)));
                }
            }
        }
        let n = tiles.len();
        let mut map = ErrorMap { tiles, error: vec![1.0; n], cdf: Vec::new() };
        map.rebuild();
        map
    }

    fn rebuild(&mut self) {
        let mut acc = 0.0;
        self.cdf = self
            .error
            .iter()
            .map(|&e| {
                acc += f64::from(e.max(1e-6));
                acc
            })
            .collect();
    }

    fn draw(&self, rng: &mut SplitMix64, uniform: bool) -> (usize, u32, u32, u32) {
        let t = if uniform {
            rng.below(self.tiles.len() as u64) as usize
        } else {
            let total = self.cdf.last().copied().unwrap_or(1.0);
            let u = rng.next_f64() * total;
            self.cdf.partition_point(|&c| c <= u).min(self.tiles.len() - 1)
        };
        let (view, x0, y0, w, h) = self.tiles[t];
        (t, view, x0 + rng.below(u64::from(w)) as u32, y0 + rng.below(u64::from(h)) as u32)
    }
}

/// One training ray of the heads: where it starts, its direction, where it hit the density
/// cubes, and the pixel it should show (linear RGB premultiplied by alpha, then alpha).
#[derive(Debug, Clone, Copy)]
pub struct HeadRay {
    pub origin: Vec3,
    pub dir: Vec3,
    pub hit: MarchHit,
    pub target: [f32; 4],
}

/// Gradients of the heads' parameters, one buffer per parameter group.
#[derive(Debug, Clone, PartialEq)]
pub struct ParameterGradients {
    pub grid: Vec<f32>,
    pub diffuse: Vec<f32>,
    pub psh: Vec<f32>,
    pub specular: Vec<f32>,
}

impl ParameterGradients {
    /// Zero gradients shaped like `model`'s parameters.
    pub fn zeros(model: &InolfModel) -> ParameterGradients {
        ParameterGradients {
            grid: vec![0.0; model.grid.num_params()],
            diffuse: vec![0.0; model.diffuse.num_params()],
            psh: vec![0.0; model.psh.features.len()],
            specular: vec![0.0; model.specular.num_params()],
        }
    }

    /// Sets every gradient back to zero.
    pub fn clear(&mut self) {
        for g in [&mut self.grid, &mut self.diffuse, &mut self.psh, &mut self.specular] {
            g.iter_mut().for_each(|x| *x = 0.0);
        }
    }

    /// Every value, group after group.
    pub fn values(&self) -> impl Iterator<Item = f32> + '_ {
        self.grid.iter().chain(&self.diffuse).chain(&self.psh).chain(&self.specular).copied()
    }
}

/// The two heads' network workspaces, kept between batches.
#[derive(Debug, Default)]
pub struct HeadsWorkspace {
    diffuse: MlpWorkspace,
    specular: MlpWorkspace,
}

/// Forward and backward of both heads over a batch of rays that hit (the loss of eq. 8 in
/// `space`, averaged over the batch): adds the parameters' gradients into `grads` and returns
/// each ray's loss.
pub fn heads_forward_backward(
    model: &InolfModel,
    rays: &[HeadRay],
    opacity_weight: f32,
    space: LossSpace,
    grads: &mut ParameterGradients,
    workspace: &mut HeadsWorkspace,
) -> Result<Vec<f32>, ModelError> {
    let n = rays.len();
    if n == 0 {
        return Ok(Vec::new());
    }
    let f_dim = model.psh.dim();
    let s_in = model.specular.config().input;
    let e_dim = model.grid.output_dim();
    // The diffuse branch's rows: one per ray at its hit point, or with
    // `HeadsShape::diffuse_blend` one per sample the ray's colour blends, weighted as the
    // kernel weighs them (`MarchHit::normalised_blend`). Each row: its ray and weight.
    let blend = model.shape.diffuse_blend;
    let mut points: Vec<[f32; 3]> = Vec::with_capacity(n * if blend { MAX_BLEND_SAMPLES } else { 1 });
    let mut row_of: Vec<(usize, f32)> = Vec::with_capacity(points.capacity());
    for (k, r) in rays.iter().enumerate() {
        let start = points.len();
        if blend {
            for (t, w) in r.hit.normalised_blend().into_iter().filter(|b| b.1 > 0.0) {
                points.push(model.grid_input(r.origin + r.dir * t));
                row_of.push((k, w));
            }
        }
        if points.len() == start {
            points.push(model.grid_input(r.origin + r.dir * r.hit.t));
            row_of.push((k, 1.0));
        }
    }
    let mut enc = vec![0.0; points.len() * e_dim];
    model.grid.encode_batch(&points, &mut enc)?;
    let out_rows = model.diffuse.forward(&enc, &mut workspace.diffuse)?.to_vec();
    let mut out_d = vec![0.0f32; n * DIFFUSE_OUT];
    for (&(k, w), row) in row_of.iter().zip(out_rows.chunks_exact(DIFFUSE_OUT)) {
        for (v, &r) in out_d[k * DIFFUSE_OUT..(k + 1) * DIFFUSE_OUT].iter_mut().zip(row) {
            *v += w * r;
        }
    }
    let mut s_input = vec![0.0; n * s_in];
    let mut corners: Vec<Corners> = Vec::with_capacity(n);
    for (k, r) in rays.iter().enumerate() {
        corners.push(model.specular_row(
            r.origin + r.dir * r.hit.t,
            r.dir,
            r.hit.opacity,
            &mut s_input[k * s_in..(k + 1) * s_in],
        ));
    }
    let mut out_s = model.specular.forward(&s_input, &mut workspace.specular)?.to_vec();
    for (k, r) in rays.iter().enumerate() {
        specular_activation(&mut out_s[k * SPECULAR_OUT..(k + 1) * SPECULAR_OUT], r.hit.opacity);
    }
    let mut d_out_d = vec![0.0; n * DIFFUSE_OUT];
    let mut d_out_s = vec![0.0; n * SPECULAR_OUT];
    let scale = 1.0 / n as f32;
    let mut losses = Vec::with_capacity(n);
    for (k, r) in rays.iter().enumerate() {
        let g = head_gradients(
            &out_d[k * DIFFUSE_OUT..(k + 1) * DIFFUSE_OUT],
            &out_s[k * SPECULAR_OUT..(k + 1) * SPECULAR_OUT],
            r.target,
            opacity_weight,
            space,
        );
        losses.push(g.loss);
        for j in 0..DIFFUSE_OUT {
            d_out_d[k * DIFFUSE_OUT + j] = g.d_diffuse[j] * scale;
        }
        for j in 0..SPECULAR_OUT {
            d_out_s[k * SPECULAR_OUT + j] =
                g.d_specular[j] * scale * specular_activation_derivative(out_s[k * SPECULAR_OUT + j]);
        }
    }
    let mut d_s_input = vec![0.0; n * s_in];
    model.specular.backward(&s_input, &mut workspace.specular, &d_out_s, &mut grads.specular, Some(&mut d_s_input))?;
    for (k, c) in corners.iter().enumerate() {
        model.psh.backward(c, &d_s_input[k * s_in..k * s_in + f_dim], &mut grads.psh);
    }
    let d_rows: Vec<f32> = row_of
        .iter()
        .flat_map(|&(k, w)| d_out_d[k * DIFFUSE_OUT..(k + 1) * DIFFUSE_OUT].iter().map(move |&d| w * d))
        .collect();
    let mut d_enc = vec![0.0; points.len() * e_dim];
    model.diffuse.backward(&enc, &mut workspace.diffuse, &d_rows, &mut grads.diffuse, Some(&mut d_enc))?;
    model.grid.backward_batch_parallel(&points, &d_enc, &mut grads.grid)?;
    Ok(losses)
}

/// Trains `model` on `views`; `progress(step, smoothed loss)` is called after every step.
pub fn train(
    model: &mut InolfModel,
    cubes: &DensityCubes,
    views: &[TrainingView],
    options: &TrainOptions,
    progress: &mut dyn FnMut(u32, f32),
) -> Result<TrainReport, ModelError> {
    if views.is_empty() || options.batch == 0 {
        return Err(ModelError::Shape("no views or an empty batch".into()));
    }
    // The march keeps as many blend samples as these heads mix (as the kernel's will).
    let kept = model.shape.kept_blend_samples();
    let matched;
    let cubes = if cubes.blend_samples() == kept {
        cubes
    } else {
        let mut c = cubes.clone();
        c.set_blend_samples(kept);
        matched = c;
        &matched
    };
    let mut rng = SplitMix64::new(options.seed);
    let mut map = ErrorMap::new(views, options.tile);
    let adam = |lr: f32, weight_decay: f32, decoupled_decay: f32, len: usize| {
        Adam::new(AdamConfig { learning_rate: lr, weight_decay, decoupled_decay, ..AdamConfig::default() }, len)
    };
    let lr = options.learning_rate;
    // The tables (diffuse hash grid, PSH features) take lazy steps: the same updates as dense
    // Adam, paid only for the entries a step's rays touch (a few percent). Dense steps over
    // their 11 million entries were 80 % of the heads' training time (the heads 2.2x faster
    // now), and plain sparse steps cost 0.16 dB held out (BENCHMARKS.md, 2026-12-07e).
    let lazy = |decay: f32, len: usize| {
        LazyAdam::new(AdamConfig { learning_rate: lr, decoupled_decay: decay, ..AdamConfig::default() }, len)
    };
    let mut opt_grid = lazy(options.grid_decay, model.grid.num_params())?;
    let mut opt_diffuse = adam(lr, 1e-6, 0.0, model.diffuse.num_params());
    let mut opt_psh = lazy(options.psh_decay, model.psh.features.len())?;
    let mut opt_specular = adam(lr, 1e-6, 0.0, model.specular.num_params());
    let mut grads = ParameterGradients::zeros(model);
    let mut workspace = HeadsWorkspace::default();
    let mut report = TrainReport::default();
    let mut smoothed = f32::NAN;

    for step in 0..options.steps {
        // Learning-rate schedule: full rate, then x0.3 after half, x0.1 after 80 %.
        let frac = step as f32 / options.steps.max(1) as f32;
        let rate = lr
            * if frac < 0.5 {
                1.0
            } else if frac < 0.8 {
                0.3
            } else {
                0.1
            };
        for o in [&mut opt_diffuse, &mut opt_specular] {
            o.set_learning_rate(rate);
        }
        opt_grid.set_learning_rate(model.grid.params_mut(), rate)?;
        opt_psh.set_learning_rate(&mut model.psh.features, rate)?;
        if step % 16 == 0 {
            map.rebuild();
        }
        let draws: Vec<(usize, u32, u32, u32)> = (0..options.batch)
            .map(|_| {
                let uniform = rng.next_f64() < f64::from(options.uniform_fraction);
                map.draw(&mut rng, uniform)
            })
            .collect();
        let marched: Vec<(MarchHit, Vec3, Vec3)> = draws
            .par_iter()
            .map(|&(_, view, x, y)| {
                let ray = views[view as usize].camera.pixel_center_ray(x, y);
                (cubes.march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY), ray.origin, ray.direction)
            })
            .collect();
        let target_of = |i: usize| {
            let (_, view, x, y) = draws[i];
            let v = &views[view as usize];
            v.target[(y * v.camera.width() + x) as usize]
        };
        // Pixels the check dropped (NaN or infinite) are not trained either.
        let kept: Vec<usize> =
            (0..draws.len()).filter(|&i| marched[i].0.opacity >= HIT_OPACITY && !is_dropped(&target_of(i))).collect();
        // A ray that misses cannot be improved: its tile's error decays so that tiles of
        // empty background stop being drawn.
        for (i, m) in marched.iter().enumerate() {
            if m.0.opacity < HIT_OPACITY {
                let tile = draws[i].0;
                map.error[tile] *= 0.9;
            }
        }
        report.rays += draws.len() as u64;
        report.rays_hit += kept.len() as u64;
        if kept.is_empty() {
            progress(step + 1, smoothed);
            continue;
        }
        let rays: Vec<HeadRay> = kept
            .iter()
            .map(|&i| {
                let (hit, origin, dir) = marched[i];
                HeadRay { origin, dir, hit, target: target_of(i) }
            })
            .collect();
        let losses = heads_forward_backward(
            model,
            &rays,
            options.opacity_weight,
            options.loss_space,
            &mut grads,
            &mut workspace,
        )?;
        let mut loss_sum = 0.0f64;
        for (&i, &loss) in kept.iter().zip(&losses) {
            loss_sum += f64::from(loss);
            let tile = draws[i].0;
            map.error[tile] = 0.9 * map.error[tile] + 0.1 * loss;
        }
        let n = kept.len();

        opt_grid.step(model.grid.params_mut(), &mut grads.grid)?;
        opt_psh.step(&mut model.psh.features, &mut grads.psh)?;
        opt_diffuse.step(model.diffuse.params_mut(), &grads.diffuse)?;
        opt_specular.step(model.specular.params_mut(), &grads.specular)?;
        grads.diffuse.fill(0.0);
        grads.specular.fill(0.0);
        let loss = (loss_sum / n as f64) as f32;
        smoothed = if smoothed.is_nan() { loss } else { 0.98 * smoothed + 0.02 * loss };
        report.last_loss = loss;
        report.smoothed_loss = smoothed;
        report.steps = step + 1;
        progress(step + 1, smoothed);
    }
    opt_grid.flush(model.grid.params_mut())?;
    opt_psh.flush(&mut model.psh.features)?;
    Ok(report)
}
