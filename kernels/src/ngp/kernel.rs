//! [`NgpKernel`]: volume rendering of a trained radiance field behind the farm's kernel
//! interface (kind `"ngp"`), the i-NGP-style baseline of every i-NOLF speed figure.

use std::path::Path;

use glam::Vec3;
use rayon::prelude::*;

use crate::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel, validate_pixels};
use nephele_geometry::camera::Camera;
use nephele_imaging::image::srgb_to_linear;

use super::NgpError;
use super::field::{FieldScratch, RadianceField, RayResult};

/// Pixels per parallel task.
const PIXELS_PER_TASK: usize = 64;

/// A radiance field as a farm kernel.
#[derive(Debug, Clone)]
pub struct NgpKernel {
    field: RadianceField,
    bounds: Bounds,
}

/// Totals over a batch of rays.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MarchStats {
    pub rays: u64,
    /// Rays with at least one occupied sample.
    pub rays_hit: u64,
    /// Density-network evaluations.
    pub samples: u64,
    /// Colour-network evaluations (samples with a blending weight that matters).
    pub color_queries: u64,
}

impl NgpKernel {
    pub fn new(field: RadianceField) -> Self {
        // The matter's box: the occupied cells, or the whole box if none is (a blank field).
        let b = field.bounds();
        let bounds = match field.occupancy().occupied_bounds() {
            Some((lo, hi)) => Bounds { min: b.min + lo * field.size, max: b.min + hi * field.size },
            None => b,
        };
        NgpKernel { field, bounds }
    }

    /// Loads a field file (see [`super::file`]).
    pub fn load(path: &Path) -> Result<Self, NgpError> {
        Ok(Self::new(super::file::load_field(path)?))
    }

    pub fn field(&self) -> &RadianceField {
        &self.field
    }

    /// Chooses the instruction set of the field's MLPs.
    pub fn set_simd(&mut self, simd: nephele_nn::SimdMode) {
        self.field.set_simd(simd);
    }

    /// Volume-renders world rays `(origin, unit direction)` in parallel.
    pub fn render_rays(&self, rays: &[(Vec3, Vec3)]) -> (Vec<RayResult>, MarchStats) {
        let results: Vec<RayResult> = rays
            .par_chunks(PIXELS_PER_TASK)
            .map_init(FieldScratch::new, |scratch, chunk| {
                chunk.iter().map(|&(o, d)| self.field.render_ray(o, d, 0.0, scratch)).collect::<Vec<_>>()
            })
            .flatten()
            .collect();
        let mut stats = MarchStats { rays: rays.len() as u64, ..MarchStats::default() };
        for r in &results {
            stats.rays_hit += u64::from(r.samples > 0);
            stats.samples += u64::from(r.samples);
            stats.color_queries += u64::from(r.color_queries);
        }
        (results, stats)
    }

    /// [`RayKernel::render_pixels`] with the marching totals.
    pub fn render_pixels_with_stats(
        &self,
        camera: &Camera,
        pixels: &[u32],
    ) -> Result<(PixelResults, MarchStats), KernelError> {
        validate_pixels(camera, pixels)?;
        let width = camera.width();
        let per_task: Vec<(PixelResults, MarchStats)> = pixels
            .par_chunks(PIXELS_PER_TASK)
            .map_init(FieldScratch::new, |scratch, chunk| {
                let mut out = PixelResults::with_len(chunk.len());
                let mut stats = MarchStats { rays: chunk.len() as u64, ..MarchStats::default() };
                for (k, &p) in chunk.iter().enumerate() {
                    let ray = camera.pixel_center_ray(p % width, p / width);
                    let r = self.field.render_ray(ray.origin, ray.direction, 0.0, scratch);
                    stats.rays_hit += u64::from(r.samples > 0);
                    stats.samples += u64::from(r.samples);
                    stats.color_queries += u64::from(r.color_queries);
                    if r.opacity > 0.0 {
                        // The field composites sRGB-encoded colour; the farm wants linear,
                        // premultiplied.
                        let a = r.opacity;
                        out.color[k] = r.color.map(|c| a * srgb_to_linear((c / a).clamp(0.0, 1.0)));
                        out.opacity[k] = a;
                        let depth = r.distance * camera.depth_per_distance(&ray);
                        out.depth[k] = if depth.is_finite() && depth > 0.0 { depth } else { 0.0 };
                        if out.depth[k] == 0.0 {
                            // No usable depth means nothing to fuse: report nothing.
                            out.color[k] = [0.0; 3];
                            out.opacity[k] = 0.0;
                        }
                    }
                }
                (out, stats)
            })
            .collect();
        let mut out = PixelResults::default();
        let mut stats = MarchStats::default();
        for (r, s) in per_task {
            out.append(r);
            stats.rays += s.rays;
            stats.rays_hit += s.rays_hit;
            stats.samples += s.samples;
            stats.color_queries += s.color_queries;
        }
        Ok((out, stats))
    }
}

impl RayKernel for NgpKernel {
    fn kind(&self) -> &'static str {
        "ngp"
    }

    fn bounds(&self) -> Bounds {
        self.bounds
    }

    /// `queries` counts density-network evaluations (samples); the colour network runs on
    /// the subset of samples whose blending weight matters.
    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        let (out, s) = self.render_pixels_with_stats(camera, pixels)?;
        Ok((out, KernelStats { rays: s.rays, rays_hit: s.rays_hit, queries: s.samples, hidden: 0 }))
    }
}
