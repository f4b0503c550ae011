//! [`NelfKernel`]: a distilled light field behind the farm's kernel interface (kind
//! `"nelf"`): one network query per ray that meets the object's matter, none for the rest.

use std::path::Path;

use glam::Vec3;
use rayon::prelude::*;

use crate::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel, validate_pixels};
use nephele_geometry::camera::Camera;
use nephele_imaging::image::srgb_to_linear;
use nephele_nn::{ResidualWorkspace, SimdMode};

use super::{NELF_OUTPUTS, NelfError, NelfModel};

/// Pixels per parallel task (and rows per network batch).
const PIXELS_PER_TASK: usize = 128;

/// A NeLF as a farm kernel.
#[derive(Debug, Clone)]
pub struct NelfKernel {
    model: NelfModel,
}

/// Per-thread buffers.
#[derive(Debug, Default)]
pub struct NelfScratch {
    points: Vec<f32>,
    inputs: Vec<f32>,
    outputs: Vec<f32>,
    ws: ResidualWorkspace,
}

impl NelfScratch {
    pub fn new() -> Self {
        Self::default()
    }
}

/// One ray's answer, in the teacher's space: premultiplied sRGB-encoded colour, opacity and
/// distance along the ray (0 when nothing).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct NelfRay {
    pub color: [f32; 3],
    pub opacity: f32,
    pub distance: f32,
    /// Whether the network was queried (the ray met the matter).
    pub queried: bool,
}

impl NelfKernel {
    pub fn new(model: NelfModel) -> NelfKernel {
        NelfKernel { model }
    }

    pub fn load(path: &Path) -> Result<NelfKernel, NelfError> {
        Ok(NelfKernel::new(NelfModel::load(path)?))
    }

    pub fn model(&self) -> &NelfModel {
        &self.model
    }

    pub fn set_simd(&mut self, simd: SimdMode) {
        self.model.network.set_simd(simd);
    }

    /// Answers world rays `(origin, unit direction)`; `out` gets one entry per ray. Rays that
    /// meet no occupied cell are answered empty without the network.
    pub fn render_rays_into(&self, rays: &[(Vec3, Vec3)], scratch: &mut NelfScratch, out: &mut Vec<NelfRay>) {
        let sampling = &self.model.header.sampling;
        let input_len = sampling.input_len();
        out.clear();
        out.resize(rays.len(), NelfRay::default());
        let mut queried = Vec::with_capacity(rays.len());
        scratch.inputs.clear();
        for (k, &(origin, dir)) in rays.iter().enumerate() {
            let Some((t0, t1)) = sampling.segment(origin, dir) else { continue };
            if !self.model.matter.hits_within(origin, dir, (t0, t1)) {
                continue;
            }
            let at = scratch.inputs.len();
            scratch.inputs.resize(at + input_len, 0.0);
            sampling.encode(origin, dir, t0, t1, &mut scratch.points, &mut scratch.inputs[at..]);
            queried.push((k, t0, t1));
        }
        if queried.is_empty() {
            return;
        }
        scratch.outputs.resize(queried.len() * NELF_OUTPUTS, 0.0);
        // Sizes agree by construction; a failure would be a bug, answered as empty rays.
        if self.model.network.infer(&scratch.inputs, &mut scratch.outputs, &mut scratch.ws).is_err() {
            return;
        }
        for (&(k, t0, t1), y) in queried.iter().zip(scratch.outputs.chunks_exact(NELF_OUTPUTS)) {
            let opacity = y[3].clamp(0.0, 1.0);
            out[k] = NelfRay {
                color: [y[0], y[1], y[2]].map(|c| c.clamp(0.0, opacity)),
                opacity,
                distance: t0 + y[4].clamp(0.0, 1.0) * (t1 - t0),
                queried: true,
            };
        }
    }
}

impl RayKernel for NelfKernel {
    fn kind(&self) -> &'static str {
        "nelf"
    }

    fn bounds(&self) -> Bounds {
        let s = &self.model.header.sampling;
        Bounds { min: Vec3::from(s.min), max: Vec3::from(s.max) }
    }

    /// `queries` counts network queries: one per ray that meets the matter.
    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        validate_pixels(camera, pixels)?;
        let width = camera.width();
        let per_task: Vec<(PixelResults, KernelStats)> = pixels
            .par_chunks(PIXELS_PER_TASK)
            .map_init(
                || (NelfScratch::new(), Vec::new(), Vec::new()),
                |(scratch, rays, answers), chunk| {
                    rays.clear();
                    let camera_rays: Vec<_> =
                        chunk.iter().map(|&p| camera.pixel_center_ray(p % width, p / width)).collect();
                    rays.extend(camera_rays.iter().map(|r| (r.origin, r.direction)));
                    self.render_rays_into(rays, scratch, answers);
                    let mut out = PixelResults::with_len(chunk.len());
                    let mut stats = KernelStats { rays: chunk.len() as u64, ..KernelStats::default() };
                    for (k, (answer, ray)) in answers.iter().zip(&camera_rays).enumerate() {
                        stats.queries += u64::from(answer.queried);
                        stats.rays_hit += u64::from(answer.queried);
                        let a = answer.opacity;
                        let depth = answer.distance * camera.depth_per_distance(ray);
                        if a > 0.0 && depth.is_finite() && depth > 0.0 {
                            // The teacher's space is sRGB-encoded; the farm wants linear,
                            // premultiplied (as the i-NGP kernel gives).
                            out.color[k] = answer.color.map(|c| a * srgb_to_linear((c / a).clamp(0.0, 1.0)));
                            out.opacity[k] = a;
                            out.depth[k] = depth;
                        }
                    }
                    (out, stats)
                },
            )
            .collect();
        let mut out = PixelResults::default();
        let mut stats = KernelStats::default();
        for (r, s) in per_task {
            out.append(r);
            stats.rays += s.rays;
            stats.rays_hit += s.rays_hit;
            stats.queries += s.queries;
        }
        Ok((out, stats))
    }
}
