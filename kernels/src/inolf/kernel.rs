//! The i-NOLF CPU kernel: one small-network query per ray that hits.
//!
//! Per batch of pixels (rayon, 1024 pixels per task): generate the rays, march them through
//! the density cubes (a ray that misses every occupied cell costs a slab test and a few DDA
//! steps, and nothing else), compact the hitting rays, look their diffuse colour and tint up
//! in the diffuse cubes (or run the diffuse network), build the specular MLP's input rows
//! (PSH features, SH of the direction, coarse opacity) in one contiguous batch and run the
//! specular MLP once over it, then combine (eq. 7).
//!
//! For the ablation of NEPHELE table 5 the hit point can instead come from marching the
//! radiance field's density network ([`InolfKernel::use_density_network`], "i-NOLF base"):
//! same heads, many network queries per ray.

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;

use super::asset::Asset;
use super::cubes::{DensityCubes, MAX_BLEND_SAMPLES, SparseCubes};
use super::encoding::{CellCache, PshEncoding};
use super::heads::{decode_diffuse, load_heads};
use super::model::{DIFFUSE_OUT, HeadsShape, InolfModel, ModelError, SPECULAR_OUT, combine, specular_activation};
use crate::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel, validate_pixels};
use crate::ngp::{FieldScratch, RadianceField};
use nephele_geometry::camera::Camera;
use nephele_nn::simd::{Prefetch, Simd, WithSimd};
use nephele_nn::{HashGrid, Mlp, MlpWorkspace, SimdMode, sh_coefficient_count, sh_encode};

/// Rays whose coarse opacity is below this are treated as misses (kernel and training).
pub const HIT_OPACITY: f32 = 1e-3;
/// Near distance of camera rays.
pub const RAY_NEAR: f32 = 1e-3;

/// Where the diffuse colour and tint come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DiffuseSource {
    /// Baked diffuse texture cubes (the default when present).
    Cubes,
    /// The hash grid and diffuse MLP (one more network query per ray).
    Network,
}

/// Where the hit point and the coarse opacity come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HitSource {
    /// Marching the baked density texture cubes (the kernel the farm runs).
    DensityCubes,
    /// Marching the radiance field's density network ("i-NOLF base" in table 5).
    DensityNetwork,
}

/// Bytes of each part an i-NOLF kernel holds in memory (0 for a part it does not have).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct KernelMemory {
    pub density_cubes: u64,
    pub diffuse_cubes: u64,
    /// Hash grid and diffuse MLP.
    pub diffuse_network: u64,
    /// PSH offset and key tables.
    pub psh_tables: u64,
    pub psh_features: u64,
    pub specular_mlp: u64,
    /// Radiance field (hash grid, both MLPs, occupancy bits) when it gives the hit point.
    pub density_network: u64,
    /// What the current configuration reads while rendering.
    pub in_use: u64,
}

/// An i-NOLF object ready to render.
#[derive(Debug, Clone)]
pub struct InolfKernel {
    density: DensityCubes,
    hit_field: Option<Arc<RadianceField>>,
    diffuse_cubes: Option<SparseCubes>,
    diffuse_net: Option<(HashGrid, Mlp)>,
    grid_bounds: Bounds,
    psh: PshEncoding,
    specular: Mlp,
    shape: HeadsShape,
    source: DiffuseSource,
    /// Hints that fetch the PSH tables' and diffuse cubes' lines ahead of their reads.
    prefetch: Prefetch,
}

/// Why an asset file could not be opened as a kernel.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error(transparent)]
    Asset(#[from] super::asset::AssetError),
    #[error(transparent)]
    Model(#[from] ModelError),
}

/// Pixels per rayon task.
const CHUNK: usize = 1024;

/// Hit points between a diffuse-cube read and its hint ([`SparseCubes::prefetch_sample`]).
const DIFFUSE_LOOKAHEAD: usize = 8;

impl InolfKernel {
    /// From a loaded asset (meta, tensors and sections checked against each other), marching
    /// at the asset's own stride and with its hit rule ([`super::heads::InolfMeta`]).
    pub fn from_asset(asset: Asset) -> Result<InolfKernel, ModelError> {
        let heads = load_heads(&asset)?;
        let psh = asset.psh.ok_or_else(|| ModelError::Shape("no PSH section".into()))?;
        let source = if asset.diffuse.is_some() { DiffuseSource::Cubes } else { DiffuseSource::Network };
        let mut density = asset.density;
        density.set_march_stride(heads.meta.march_stride).map_err(|e| ModelError::Shape(e.to_string()))?;
        density.set_hit_rule(heads.meta.hit_rule).map_err(|e| ModelError::Shape(e.to_string()))?;
        density.set_blend_samples(heads.meta.shape.kept_blend_samples());
        Ok(InolfKernel {
            density,
            hit_field: None,
            diffuse_cubes: asset.diffuse,
            diffuse_net: heads.diffuse,
            grid_bounds: heads.grid_bounds,
            psh,
            specular: heads.specular,
            shape: heads.meta.shape,
            source,
            prefetch: Prefetch::new(),
        })
    }

    /// Loads and validates a `.nolf` file (first bytes [`super::asset::MAGIC`]).
    pub fn load(path: &std::path::Path) -> Result<InolfKernel, LoadError> {
        Ok(InolfKernel::from_asset(Asset::load(path)?)?)
    }

    /// From a model in memory (tests, and rendering right after training).
    pub fn from_model(
        model: &InolfModel,
        mut density: DensityCubes,
        diffuse_cubes: Option<SparseCubes>,
    ) -> InolfKernel {
        density.set_blend_samples(model.shape.kept_blend_samples());
        let source = if diffuse_cubes.is_some() { DiffuseSource::Cubes } else { DiffuseSource::Network };
        InolfKernel {
            density,
            hit_field: None,
            diffuse_cubes,
            diffuse_net: Some((model.grid.clone(), model.diffuse.clone())),
            grid_bounds: model.bounds,
            psh: model.psh.clone(),
            specular: model.specular.clone(),
            shape: model.shape,
            source,
            prefetch: Prefetch::new(),
        }
    }

    /// Whether the heads hint the CPU to fetch their table reads ahead (on by default; off
    /// only to measure what the hints save: the results are the same either way).
    pub fn set_prefetch(&mut self, on: bool) {
        self.prefetch = if on { Prefetch::new() } else { Prefetch::off() };
    }

    /// Chooses the instruction set of the march and the heads (default: the best the CPU
    /// has; [`SimdMode::Off`] for the scalar comparison).
    pub fn set_simd(&mut self, simd: SimdMode) {
        self.specular.set_simd(simd);
        if let Some((_, mlp)) = &mut self.diffuse_net {
            mlp.set_simd(simd);
        }
        if let Some(field) = &mut self.hit_field {
            Arc::make_mut(field).set_simd(simd);
        }
    }

    /// Which sample is a ray's hit point ([`DensityCubes::set_hit_rule`]); an asset's heads
    /// are only right with the rule they were trained with (`from_asset` applies it).
    pub fn set_hit_rule(&mut self, rule: super::cubes::HitRule) -> Result<(), ModelError> {
        self.density.set_hit_rule(rule).map_err(|e| ModelError::Shape(e.to_string()))
    }

    /// Samples the density march every `stride` voxels ([`DensityCubes::set_march_stride`]).
    pub fn set_march_stride(&mut self, stride: u32) -> Result<(), ModelError> {
        self.density.set_march_stride(stride).map_err(|e| ModelError::Shape(e.to_string()))
    }

    /// The instruction set in use (every network of the kernel holds the same).
    pub fn simd(&self) -> SimdMode {
        self.specular.simd()
    }

    /// Chooses the diffuse source; fails if that part is not in the asset.
    pub fn set_diffuse_source(&mut self, source: DiffuseSource) -> Result<(), ModelError> {
        let ok = match source {
            DiffuseSource::Cubes => self.diffuse_cubes.is_some(),
            DiffuseSource::Network => self.diffuse_net.is_some(),
        };
        if !ok {
            return Err(ModelError::Shape(format!("the asset has no {source:?} diffuse part")));
        }
        self.source = source;
        Ok(())
    }

    pub fn diffuse_source(&self) -> DiffuseSource {
        self.source
    }

    /// Takes hit points and coarse opacities from `field`'s density network instead of the
    /// density cubes (the field the asset was baked from; the cubes cache its density).
    pub fn use_density_network(&mut self, mut field: RadianceField) {
        field.set_simd(self.simd());
        self.hit_field = Some(Arc::new(field));
    }

    pub fn hit_source(&self) -> HitSource {
        if self.hit_field.is_some() { HitSource::DensityNetwork } else { HitSource::DensityCubes }
    }

    /// Bytes of every part, and of those the current configuration reads.
    pub fn memory(&self) -> KernelMemory {
        let mlp = |m: &Mlp| 4 * m.num_params() as u64;
        let mut m = KernelMemory {
            density_cubes: self.density.cubes().footprint().bytes + self.density.occupancy_bytes(),
            diffuse_cubes: self.diffuse_cubes.as_ref().map_or(0, |c| c.footprint().bytes),
            diffuse_network: self.diffuse_net.as_ref().map_or(0, |(g, d)| 4 * g.num_params() as u64 + mlp(d)),
            psh_tables: self.psh.table.table_bytes() as u64,
            psh_features: 4 * self.psh.features.len() as u64,
            specular_mlp: mlp(&self.specular),
            density_network: self.hit_field.as_ref().map_or(0, |f| f.memory_bytes()),
            in_use: 0,
        };
        let hit = if self.hit_field.is_some() { m.density_network } else { m.density_cubes };
        let diffuse = match self.source {
            DiffuseSource::Cubes => m.diffuse_cubes,
            DiffuseSource::Network => m.diffuse_network,
        };
        m.in_use = hit + diffuse + m.psh_tables + m.psh_features + m.specular_mlp;
        m
    }

    pub fn density(&self) -> &DensityCubes {
        &self.density
    }

    /// The diffuse texture cubes, if the asset has them.
    pub fn diffuse_cubes(&self) -> Option<&SparseCubes> {
        self.diffuse_cubes.as_ref()
    }

    /// The specular MLP.
    pub fn specular(&self) -> &Mlp {
        &self.specular
    }

    /// Sizes of the heads.
    pub fn shape(&self) -> HeadsShape {
        self.shape
    }

    /// Reads the diffuse colour blended over the march's samples of largest weight, or at
    /// the hit point (`HeadsShape::diffuse_blend`: what the heads were trained with; the
    /// other reading is for comparisons).
    pub fn set_diffuse_blend(&mut self, blend: bool) {
        self.shape.diffuse_blend = blend;
        self.density.set_blend_samples(self.shape.kept_blend_samples());
    }

    /// How many samples a blended diffuse colour mixes (`HeadsShape::blend_samples`: what the
    /// heads were trained with; others are for comparisons; at most
    /// [`MAX_BLEND_SAMPLES`]).
    pub fn set_blend_samples(&mut self, samples: u32) {
        self.shape.blend_samples = samples.min(MAX_BLEND_SAMPLES as u32);
        self.density.set_blend_samples(self.shape.kept_blend_samples());
    }

    /// Multiply-adds of the specular MLP per hitting ray.
    pub fn specular_macs(&self) -> usize {
        self.specular.config().macs_per_row()
    }

    /// The specular branch's PSH encoding (its lattice side is `psh().table.domain()`).
    pub fn psh(&self) -> &PshEncoding {
        &self.psh
    }

    /// Renders one chunk of pixels into the given output slices; returns the rays that hit
    /// and the density-network samples taken (0 with the density cubes). Inlined into the
    /// SIMD dispatch of `render_pixels`, so the march is compiled for the chosen instruction
    /// set.
    #[inline(always)]
    fn render_chunk(
        &self,
        camera: &Camera,
        pixels: &[u32],
        color: &mut [[f32; 3]],
        opacity: &mut [f32],
        depth: &mut [f32],
    ) -> Result<(u64, u64), ModelError> {
        let width = camera.width();
        let mut hits: Vec<(usize, Vec3, Vec3, f32)> = Vec::with_capacity(pixels.len());
        // Per hit, the points and weights its diffuse colour blends (`HeadsShape::diffuse_blend`).
        let blend = self.shape.diffuse_blend;
        let mut blends: Vec<[(Vec3, f32); MAX_BLEND_SAMPLES]> =
            Vec::with_capacity(if blend { pixels.len() } else { 0 });
        // Per hit, the view depth reported: of the sample of largest weight, which a hit
        // rule may have left for a layer behind (`MarchHit::front_t`).
        let mut front_depths: Vec<f32> = Vec::with_capacity(pixels.len());
        let mut field_scratch = self.hit_field.as_ref().map(|_| FieldScratch::new());
        let mut network_samples = 0u64;
        for (k, &p) in pixels.iter().enumerate() {
            let ray = camera.pixel_center_ray(p % width, p / width);
            let mut blend_points = [(Vec3::ZERO, 0.0f32); MAX_BLEND_SAMPLES];
            let (opacity, t, front_t) = match (&self.hit_field, &mut field_scratch) {
                (Some(field), Some(scratch)) => {
                    let r = field.density_hit(ray.origin, ray.direction, RAY_NEAR, scratch);
                    network_samples += u64::from(r.samples);
                    (r.opacity, r.peak_distance, r.peak_distance)
                }
                _ => {
                    let h = self.density.march(ray.origin, ray.direction, RAY_NEAR, f32::INFINITY);
                    if blend {
                        blend_points = h.normalised_blend().map(|(bt, w)| (ray.at(bt), w));
                    }
                    (h.opacity, h.t, h.front_t)
                }
            };
            if opacity >= HIT_OPACITY {
                hits.push((k, ray.at(t), ray.direction, opacity));
                if blend {
                    // The density network's hit has no samples kept: its hit point alone.
                    if blend_points[0].1 == 0.0 {
                        blend_points[0] = (ray.at(t), 1.0);
                    }
                    blends.push(blend_points);
                }
                front_depths.push(camera.view_depth(ray.at(front_t)));
            }
        }
        if hits.is_empty() {
            return Ok((0, network_samples));
        }
        let n = hits.len();
        // Diffuse colour and tint.
        let mut diffuse = vec![0.0f32; n * DIFFUSE_OUT];
        match (self.source, &self.diffuse_cubes, &self.diffuse_net) {
            (DiffuseSource::Cubes, Some(cubes), _) => {
                for (i, (row, h)) in diffuse.chunks_exact_mut(DIFFUSE_OUT).zip(&hits).enumerate() {
                    if let Some(ahead) = hits.get(i + DIFFUSE_LOOKAHEAD) {
                        cubes.prefetch_sample(ahead.1, self.prefetch);
                    }
                    if blend {
                        let mut read = [0.0f32; DIFFUSE_OUT];
                        row.fill(0.0);
                        for &(p, w) in blends[i].iter().filter(|b| b.1 > 0.0) {
                            cubes.sample(p, &mut read);
                            for (v, &r) in row.iter_mut().zip(&read) {
                                *v += w * decode_diffuse(r);
                            }
                        }
                    } else {
                        cubes.sample(h.1, row);
                        row.iter_mut().for_each(|v| *v = decode_diffuse(*v));
                    }
                }
            }
            (_, _, Some((grid, mlp))) => {
                let size = self.grid_bounds.size();
                let to_grid = |p: Vec3| ((p - self.grid_bounds.min) / size).to_array();
                if blend {
                    // Every blended point through the network (each row: its hit and weight),
                    // then each hit's weighted sum.
                    let (row_of, points): (Vec<(usize, f32)>, Vec<[f32; 3]>) = blends
                        .iter()
                        .enumerate()
                        .flat_map(|(i, b)| b.iter().filter(|b| b.1 > 0.0).map(move |&(p, w)| ((i, w), to_grid(p))))
                        .unzip();
                    let mut enc = vec![0.0; points.len() * grid.output_dim()];
                    grid.encode_batch(&points, &mut enc)?;
                    let mut rows = vec![0.0; points.len() * DIFFUSE_OUT];
                    mlp.infer(&enc, &mut rows, &mut MlpWorkspace::new())?;
                    for (&(i, w), read) in row_of.iter().zip(rows.chunks_exact(DIFFUSE_OUT)) {
                        for (v, &r) in diffuse[i * DIFFUSE_OUT..(i + 1) * DIFFUSE_OUT].iter_mut().zip(read) {
                            *v += w * r;
                        }
                    }
                } else {
                    let points: Vec<[f32; 3]> = hits.iter().map(|h| to_grid(h.1)).collect();
                    let mut enc = vec![0.0; n * grid.output_dim()];
                    grid.encode_batch(&points, &mut enc)?;
                    mlp.infer(&enc, &mut diffuse, &mut MlpWorkspace::new())?;
                }
            }
            _ => return Err(ModelError::Shape("no diffuse part".into())),
        }
        // Specular branch: one MLP query per hitting ray, as one batch.
        let f = self.psh.dim();
        let sh = sh_coefficient_count(self.shape.sh_degree);
        let s_in = f + sh + 1;
        let mut input = vec![0.0f32; n * s_in];
        // The look-ups of all hits first, then the feature rows: neither loop branches on
        // what it reads, so the table reads of many hits are in flight together.
        let mut cells = CellCache::default();
        let points: Vec<Vec3> = hits.iter().map(|h| h.1).collect();
        let corners = self.psh.corners_batch(&points, &mut cells, self.prefetch);
        for ((row, h), corners) in input.chunks_exact_mut(s_in).zip(&hits).zip(&corners) {
            self.psh.encode_corners(corners, &mut row[..f]);
            sh_encode(h.2.to_array(), self.shape.sh_degree, &mut row[f..f + sh]);
            row[f + sh] = h.3;
        }
        let mut specular = vec![0.0f32; n * SPECULAR_OUT];
        self.specular.infer(&input, &mut specular, &mut MlpWorkspace::new())?;
        for (raw, h) in specular.chunks_exact_mut(SPECULAR_OUT).zip(&hits) {
            specular_activation(raw, h.3);
        }
        for (i, h) in hits.iter().enumerate() {
            let (c, a) = combine(
                &diffuse[i * DIFFUSE_OUT..(i + 1) * DIFFUSE_OUT],
                &specular[i * SPECULAR_OUT..(i + 1) * SPECULAR_OUT],
            );
            let k = h.0;
            let d = front_depths[i];
            if a > 0.0 && a.is_finite() && d.is_finite() && d > 0.0 && c.iter().all(|v| v.is_finite()) {
                color[k] = c.map(|v| v.max(0.0));
                opacity[k] = a.clamp(0.0, 1.0);
                depth[k] = d;
            }
        }
        Ok((n as u64, network_samples))
    }
}

/// One chunk of [`InolfKernel::render_pixels`] as a `pulp` operation. Its `with_simd` is
/// inlined into the dispatcher's `#[target_feature]` function, and `render_chunk` (with the
/// march, the PSH lookups and the diffuse cubes) into it, so all of them are compiled for
/// AVX2+FMA where the CPU has them. Through a closure they were not: LLVM compiled the
/// closure apart, for the baseline, and the "AVX2+FMA" path's march ran SSE2 code (not one
/// VEX instruction in it under `perf annotate`); only the MLP had its own dispatch.
struct Chunk<'a> {
    kernel: &'a InolfKernel,
    camera: &'a Camera,
    pixels: &'a [u32],
    color: &'a mut [[f32; 3]],
    opacity: &'a mut [f32],
    depth: &'a mut [f32],
}

impl WithSimd for Chunk<'_> {
    type Output = Result<(u64, u64), ModelError>;

    #[inline(always)]
    fn with_simd<S: Simd>(self, _simd: S) -> Self::Output {
        self.kernel.render_chunk(self.camera, self.pixels, self.color, self.opacity, self.depth)
    }
}

impl RayKernel for InolfKernel {
    fn kind(&self) -> &'static str {
        "inolf"
    }

    fn bounds(&self) -> Bounds {
        self.density.bounds()
    }

    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        validate_pixels(camera, pixels)?;
        let mut out = PixelResults::with_len(pixels.len());
        let simd = self.simd();
        let hit_counts: Vec<Result<(u64, u64), ModelError>> = pixels
            .par_chunks(CHUNK)
            .zip(out.color.par_chunks_mut(CHUNK))
            .zip(out.opacity.par_chunks_mut(CHUNK))
            .zip(out.depth.par_chunks_mut(CHUNK))
            .map(|(((pixels, color), opacity), depth)| {
                simd.arch().dispatch(Chunk { kernel: self, camera, pixels, color, opacity, depth })
            })
            .collect();
        let (mut rays_hit, mut network_samples) = (0, 0);
        for h in hit_counts {
            let (hit, samples) = h.map_err(|e| KernelError::Failed(e.to_string()))?;
            rays_hit += hit;
            network_samples += samples;
        }
        // One heads query per hitting ray, plus the density network's samples if it gives
        // the hit point.
        Ok((out, KernelStats { rays: pixels.len() as u64, rays_hit, queries: rays_hit + network_samples, hidden: 0 }))
    }
}
