//! The whole bake (NEPHELE section 4) as one library call: posed RGBA images in, an i-NOLF
//! [`Asset`] out. `nephele bake` and the first start of `nephele up` call [`bake`] with typed
//! values; progress and the stage summaries go to a [`BakeProgress`] of the caller's.
//!
//! 1. the i-NGP-style radiance field of the scene (trained here, or given);
//! 2. its density cached as density texture cubes;
//! 3. the hit points of every training ray -> the perfect spatial hash;
//! 4. the i-NOLF heads trained on the same images (error-map ray sampling);
//! 5. the diffuse branch baked into diffuse texture cubes; everything in one asset.

use std::time::Instant;

use nephele_geometry::Bounds;
use nephele_geometry::camera::{Camera, CameraError};
use nephele_kernels::inolf::asset::Asset;
use nephele_kernels::inolf::cubes::{CubeError, CubeOptions, DensityCubes, HitRule, MAX_BLEND_SAMPLES};
use nephele_kernels::inolf::encoding::PshEncoding;
use nephele_kernels::inolf::model::{HeadsShape, InolfModel, LossSpace, ModelError};
use nephele_kernels::inolf::psh::{PshError, PshOptions};
use nephele_kernels::kernel::{RayKernel, all_pixels};
use nephele_kernels::ngp::{FieldConfig, NgpError, NgpKernel, RadianceField};
use nephele_nn::HashGridConfig;
use serde_json::json;
use thiserror::Error;

use super::bake::{bake_diffuse_cubes, field_density_for_cubes, to_asset};
use super::train::{
    TrainOptions, TrainingView, choose_hit_rule, collect_hit_points, layered_share, train, training_views,
};
use crate::dataset::Dataset;
use crate::dataset::sample_views_on_sphere;
use crate::ngp::train::common_focus;
use crate::ngp::{TrainConfig, Trainer};
use crate::targets::CorruptPixels;

/// Everything a bake is asked to do. `Default` is `nephele bake`'s defaults.
#[derive(Debug, Clone, PartialEq)]
pub struct BakeRecipe {
    /// Training steps of the radiance field (when none is given).
    pub field_steps: u32,
    /// log2 of the radiance field's hash-table entries per level (i-NGP: 19).
    pub field_table_log2: u32,
    /// Hash-grid levels of the radiance field.
    pub field_levels: u32,
    /// Finest hash-grid resolution of the radiance field.
    pub field_finest: u32,
    /// Density samples per training step of the radiance field.
    pub field_samples: usize,
    /// Training steps of the i-NOLF heads.
    pub head_steps: u32,
    /// Rays per step of the heads.
    pub batch: usize,
    /// log2 of the hash-table entries per level of the heads' diffuse grid.
    pub head_table_log2: u32,
    /// Coarse cells of the density cubes along the longest side.
    pub cubes: u32,
    /// Samples per cube side (density and diffuse cubes).
    pub cube_res: u32,
    /// Probes per cell side when finding the cells with matter (`cube_res - 1`: every
    /// sample point).
    pub cube_probe: u32,
    /// Side of the PSH lattice over the object's box (NEPHELE: 128, 256 or 512).
    pub psh_res: u32,
    /// Learned features per PSH slot.
    pub psh_features: u32,
    /// Densities below this (per unit length) are cut to zero before caching.
    pub density_threshold: f32,
    /// Also keep the diffuse network in the asset (the "+ diffuse MLP" variant).
    pub keep_diffuse_network: bool,
    /// Views the radiance field renders at poses the dataset lacks, added to the heads'
    /// training views (R2L's pseudo-data; issue 18): 0 trains on the dataset alone.
    pub pseudo_views: u32,
    /// Decoupled weight decay of the heads' PSH features and diffuse grid
    /// ([`TrainOptions::psh_decay`], [`TrainOptions::grid_decay`]); 0: off.
    pub psh_decay: f32,
    pub grid_decay: f32,
    /// Where the heads' colour loss compares pixels ([`LossSpace`]).
    pub head_loss: LossSpace,
    /// Blend the diffuse colour over the march's samples of largest weight instead of reading
    /// it at the hit point ([`HeadsShape::diffuse_blend`]).
    pub diffuse_blend: bool,
    /// How many of the march's samples of largest weight the blend mixes
    /// ([`HeadsShape::blend_samples`], 1..=[`MAX_BLEND_SAMPLES`]).
    pub blend_samples: u32,
    /// Which sample of the march is a ray's hit point; `None`: chosen from the share of
    /// training rays that see a second layer ([`choose_hit_rule`]).
    pub hit_rule: Option<HitRule>,
    pub seed: u64,
}

impl Default for BakeRecipe {
    fn default() -> Self {
        // The steps: the best held-out lego measured from a bake under 30 minutes on a 2-core
        // host (2026-12-07d: 7000 field steps, 70 pseudo-views and 8000 head steps in about 19
        // minutes, field 32.69 dB, i-NOLF 31.69 dB; 5000 head steps 31.53 dB, no pseudo-views
        // 31.45; 10000 field steps cost 7.4 minutes for +0.22 dB of the field; 2000 / 3000
        // took 10 minutes for 30.27 / 29.91 dB). The pseudo-views (as many as the lego's
        // training views; 35 and 200 score lower) are what lets more head steps gain instead of
        // over-fitting (BENCHMARKS.md).
        BakeRecipe {
            field_steps: 7000,
            field_table_log2: 19,
            field_levels: 16,
            field_finest: 2048,
            field_samples: 1 << 16,
            head_steps: 8000,
            batch: 4096,
            head_table_log2: HeadsShape::default().grid_log2_table,
            cubes: 64,
            cube_res: 8,
            cube_probe: CubeOptions::default().probe,
            psh_res: 256,
            psh_features: 8,
            density_threshold: 1.0,
            keep_diffuse_network: false,
            pseudo_views: 70,
            psh_decay: 0.0,
            grid_decay: 0.0,
            head_loss: LossSpace::default(),
            diffuse_blend: true,
            blend_samples: HeadsShape::default().blend_samples,
            hit_rule: None,
            seed: 1,
        }
    }
}

/// Where a bake reports: one stage at a time, with its steps, then a summary line (`Send`:
/// the density cubes report from the thread pool).
pub trait BakeProgress: Send {
    /// A stage of `total` steps of `unit` begins.
    fn stage(&mut self, name: &str, total: u64, unit: &str);
    /// `done` of `total` steps of the current stage, with a short status.
    fn advance(&mut self, done: u64, total: u64, status: &str);
    /// The stage ended; `summary` is one line for the user.
    fn finished(&mut self, summary: String);
    /// The radiance field was trained (not given): the place to keep it before the rest of
    /// the bake runs, so that a later failure does not lose it.
    fn field_trained(&mut self, _field: &RadianceField) {}
}

/// A [`BakeProgress`] that reports nothing (tests, batch jobs).
#[derive(Debug, Clone, Copy, Default)]
pub struct Quiet;

impl BakeProgress for Quiet {
    fn stage(&mut self, _: &str, _: u64, _: &str) {}
    fn advance(&mut self, _: u64, _: u64, _: &str) {}
    fn finished(&mut self, _: String) {}
}

#[derive(Debug, Error)]
pub enum BakeError {
    #[error("the dataset has no views")]
    NoViews,
    #[error("radiance field: {0}")]
    Field(#[from] NgpError),
    #[error("density cubes: {0}")]
    Cubes(#[from] CubeError),
    #[error("training view: {0}")]
    Camera(#[from] CameraError),
    #[error("perfect spatial hash: {0}")]
    Psh(#[from] PshError),
    #[error("heads: {0}")]
    Model(#[from] ModelError),
    #[error(transparent)]
    Pixels(#[from] CorruptPixels),
    #[error("{name} = {value}: must be finite, at least 0 and below 10")]
    Decay { name: &'static str, value: f32 },
    #[error("{0} blend samples: the march keeps 1 to {MAX_BLEND_SAMPLES}")]
    BlendSamples(u32),
}

/// What a bake made.
#[derive(Debug)]
pub struct Baked {
    pub asset: Asset,
    /// The radiance field it cached (trained here, or the one given): save it to bake
    /// again from the same field.
    pub field: RadianceField,
}

/// Bakes an i-NOLF asset of `data`'s views (all of them: hold views out before), from
/// `field` when given, else from a radiance field trained here. `source` names the data in
/// the asset's description of its bake.
pub fn bake(
    data: &Dataset,
    source: &str,
    recipe: &BakeRecipe,
    field: Option<RadianceField>,
    progress: &mut dyn BakeProgress,
) -> Result<Baked, BakeError> {
    let first = data.views.first().ok_or(BakeError::NoViews)?;
    let (w, h) = (first.image.width(), first.image.height());
    // With the default learning rate (1e-2) a decay of 10 shrinks features by 10 % a step:
    // beyond that the features cannot hold anything.
    for (name, value) in [("psh_decay", recipe.psh_decay), ("grid_decay", recipe.grid_decay)] {
        if !(0.0..10.0).contains(&value) {
            return Err(BakeError::Decay { name, value });
        }
    }
    // The heads' shape is checked before the minutes of the radiance field, not after.
    if !(1..=MAX_BLEND_SAMPLES as u32).contains(&recipe.blend_samples) {
        return Err(BakeError::BlendSamples(recipe.blend_samples));
    }
    let shape = HeadsShape {
        grid_log2_table: recipe.head_table_log2,
        diffuse_blend: recipe.diffuse_blend,
        blend_samples: recipe.blend_samples,
        ..HeadsShape::default()
    };
    shape.grid().validate().map_err(ModelError::from)?;

    // 1. Radiance field.
    let t = Instant::now();
    let field_trained = field.is_none();
    let field = match field {
        Some(field) => field,
        None => {
            let config =
                TrainConfig { seed: recipe.seed, samples_per_step: recipe.field_samples, ..TrainConfig::default() };
            let field_config = FieldConfig {
                grid: HashGridConfig::with_finest_resolution(
                    recipe.field_levels,
                    recipe.field_table_log2,
                    16,
                    recipe.field_finest,
                ),
                ..FieldConfig::default()
            };
            let mut trainer = Trainer::from_dataset(field_config, config, data)?;
            let steps = u64::from(recipe.field_steps);
            progress.stage("radiance field", steps, "steps");
            let mut last = 0.0;
            for step in 0..recipe.field_steps {
                let stats = trainer.step(step as f32 / recipe.field_steps.max(1) as f32)?;
                last = stats.loss;
                if step % 50 == 0 {
                    progress.advance(u64::from(step), steps, &format!("loss {:.5}", stats.loss));
                }
            }
            progress.finished(format!(
                "radiance field: {} steps, last loss {last:.5}, {:.0} s",
                recipe.field_steps,
                t.elapsed().as_secs_f64()
            ));
            let field = trainer.into_field();
            progress.field_trained(&field);
            field
        }
    };
    let fb = field.bounds();
    let bounds = match field.occupancy().occupied_bounds() {
        Some((lo, hi)) => {
            let size = fb.size();
            let margin = size * (2.0 / field.occupancy().resolution() as f32);
            Bounds { min: (fb.min + lo * size - margin).max(fb.min), max: (fb.min + hi * size + margin).min(fb.max) }
        }
        None => fb,
    };

    // 2. Density cubes.
    let t = Instant::now();
    let cube_options = CubeOptions {
        resolution: recipe.cubes,
        cube_res: recipe.cube_res,
        probe: recipe.cube_probe,
        ..CubeOptions::default()
    };
    progress.stage("density cubes", 1, "cells");
    let density = field_density_for_cubes(&field, recipe.density_threshold);
    let mut cubes = {
        let progress = std::sync::Mutex::new(&mut *progress);
        DensityCubes::build(bounds, &cube_options, density, &|p| {
            if let Ok(mut progress) = progress.lock() {
                progress.advance(p.done, p.total, p.phase);
            }
        })?
    };
    let fp = cubes.cubes().footprint();
    progress.finished(format!(
        "density cubes: {} of {} cells occupied ({:.2} %), {:.2} MiB against {:.2} MiB for a dense grid of the same resolution, {:.0} s",
        fp.occupied_cells,
        fp.cells,
        100.0 * fp.occupied_cells as f64 / fp.cells as f64,
        fp.bytes as f64 / 1048576.0,
        fp.dense_bytes as f64 / 1048576.0,
        t.elapsed().as_secs_f64()
    ));

    // 3. Hit points and the perfect spatial hash.
    let (mut views, pixel_check) = training_views(data)?;
    pixel_check.verdict()?;
    if pixel_check.repaired_any() {
        progress.finished(pixel_check.summary());
    }
    if recipe.pseudo_views > 0 {
        let t = Instant::now();
        let pseudo = pseudo_views(&field, &views, recipe.pseudo_views, recipe.seed, progress)?;
        progress.finished(format!(
            "pseudo-views: {} rendered by the radiance field at new poses for the heads, {:.0} s",
            pseudo.len(),
            t.elapsed().as_secs_f64()
        ));
        views.extend(pseudo);
    }
    let t = Instant::now();
    // The share is measured with the layered rule itself, then the chosen rule replaces it.
    cubes.set_hit_rule(HitRule::SEE_THROUGH)?;
    let share = layered_share(&cubes, &views, 2);
    let rule = recipe.hit_rule.unwrap_or_else(|| choose_hit_rule(share));
    cubes.set_hit_rule(rule)?;
    progress.finished(format!(
        "hit points: {} ({:.1} % of hit rays see a layer behind the largest weight{}), {:.1} s",
        match rule {
            HitRule::LargestWeight => "the sample of largest weight".to_string(),
            HitRule::MedianDepth => "the median depth (where the ray's opacity crosses one half)".to_string(),
            HitRule::LayerBehind { opacity, gap } => {
                format!("see-through, where the opacity reaches {opacity} when that lies {gap} voxels or more behind the largest weight")
            }
        },
        100.0 * share,
        if recipe.hit_rule.is_some() { ", as asked" } else { "" },
        t.elapsed().as_secs_f64()
    ));
    let t = Instant::now();
    let hits = collect_hit_points(&cubes, &views, 1);
    let cb = cubes.bounds();
    let voxel = cb.size().max_element() / (recipe.psh_res - 1).max(1) as f32;
    let psh =
        PshEncoding::from_points(&hits, cb.min, voxel, recipe.psh_res, recipe.psh_features, &PshOptions::coherent())?;
    let (coherent, pairs) = psh.table.coherence();
    progress.finished(format!(
        "perfect spatial hash: {} hit points -> {} lattice points at {}^3, table {}^3 slots, offsets {}^3, coherence {:.3}, {:.1} s",
        hits.len(),
        psh.table.len(),
        recipe.psh_res,
        psh.table.table_side(),
        psh.table.offset_side(),
        coherent as f64 / pairs.max(1) as f64,
        t.elapsed().as_secs_f64()
    ));

    // 4. Heads.
    let t = Instant::now();
    let mut model = InolfModel::new(shape, cb, psh, recipe.seed)?;
    let options = TrainOptions {
        steps: recipe.head_steps,
        batch: recipe.batch,
        psh_decay: recipe.psh_decay,
        grid_decay: recipe.grid_decay,
        loss_space: recipe.head_loss,
        seed: recipe.seed,
        ..TrainOptions::default()
    };
    let steps = u64::from(recipe.head_steps);
    progress.stage("i-NOLF heads", steps, "steps");
    let report = train(&mut model, &cubes, &views, &options, &mut |step, loss| {
        if step % 50 == 0 {
            progress.advance(u64::from(step), steps, &format!("loss {loss:.5}"));
        }
    })?;
    let psnr_train = -10.0 * (f64::from(report.smoothed_loss) / 4.0).log10();
    progress.finished(format!(
        "heads: {} steps, loss {:.6} (~{psnr_train:.1} dB on {} premultiplied RGBA of training rays), {:.0} % of drawn rays hit, {:.0} s",
        report.steps,
        report.smoothed_loss,
        match recipe.head_loss {
            LossSpace::Linear => "linear",
            LossSpace::Srgb => "sRGB",
        },
        100.0 * report.rays_hit as f64 / report.rays.max(1) as f64,
        t.elapsed().as_secs_f64()
    ));

    // 5. Diffuse cubes and the asset.
    let t = Instant::now();
    let diffuse = bake_diffuse_cubes(&model, &cubes, &hits, 1, recipe.cube_res)?;
    let dfp = diffuse.footprint();
    progress.finished(format!(
        "diffuse cubes: {} cells around the hit surfaces, {:.2} MiB against {:.2} MiB dense, {:.1} s",
        dfp.occupied_cells,
        dfp.bytes as f64 / 1048576.0,
        dfp.dense_bytes as f64 / 1048576.0,
        t.elapsed().as_secs_f64()
    ));
    let description = json!({
        "dataset": source, "views": data.views.len(), "size": [w, h],
        "field_steps": if field_trained { recipe.field_steps } else { 0 }, "steps": recipe.head_steps,
        "loss": report.smoothed_loss, "pseudo_views": recipe.pseudo_views, "psh_decay": recipe.psh_decay, "grid_decay": recipe.grid_decay, "head_loss": recipe.head_loss, "cubes": recipe.cubes, "cube_res": recipe.cube_res, "cube_probe": recipe.cube_probe, "psh_res": recipe.psh_res, "layered_share": share,
    });
    let asset = to_asset(&model, cubes, Some(diffuse), recipe.keep_diffuse_network, description)?;
    Ok(Baked { asset, field })
}

/// `count` views rendered by `field` (linear, premultiplied: the heads' targets) from poses on
/// the sphere the training cameras lie on (around their common focus, at their mean distance;
/// the upper hemisphere only if every camera is above the focus), with the first view's
/// intrinsics. R2L trains its light field on such pseudo-data of its teacher; here it shows
/// the heads the object between the dataset's views, where they otherwise overfit.
fn pseudo_views(
    field: &RadianceField,
    views: &[TrainingView],
    count: u32,
    seed: u64,
    progress: &mut dyn BakeProgress,
) -> Result<Vec<TrainingView>, BakeError> {
    let first = views.first().ok_or(BakeError::NoViews)?.camera;
    let cameras: Vec<Camera> = views.iter().map(|v| v.camera).collect();
    let focus = common_focus(&cameras);
    let radius = cameras.iter().map(|c| c.position().distance(focus)).sum::<f32>() / cameras.len() as f32;
    let upper = cameras.iter().all(|c| c.position().z >= focus.z);
    let fov_x = first.fov_x();
    let kernel = NgpKernel::new(field.clone());
    progress.stage("pseudo-views", u64::from(count), "views");
    let mut out = Vec::with_capacity(count as usize);
    // A seed of its own, so that the poses do not repeat the field's ray draws.
    for (i, pose) in
        sample_views_on_sphere(count as usize, radius, focus, upper, seed ^ 0x7073_6575_646f).into_iter().enumerate()
    {
        let camera = Camera::from_fov_x(first.width(), first.height(), fov_x, pose)?;
        let (frame, _) = kernel
            .render_pixels(&camera, &all_pixels(&camera))
            .map_err(|e| NgpError::Invalid(format!("rendering a pseudo-view: {e}")))?;
        let target = (0..frame.len())
            .map(|k| {
                let a = frame.opacity[k].clamp(0.0, 1.0);
                let [r, g, b] = frame.color[k].map(|c| c.clamp(0.0, a));
                [r, g, b, a]
            })
            .collect();
        out.push(TrainingView { camera, target });
        progress.advance(i as u64 + 1, u64::from(count), "");
    }
    Ok(out)
}
