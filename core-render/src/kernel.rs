//! The kernel interface: the unit of work the render farm ships.
//!
//! A worker receives a camera and a set of pixels of one object and returns, per pixel,
//! colour, opacity and depth. Every kernel (the reference path tracer, the i-NGP-style
//! baseline, i-NOLF, later GPU backends) sits behind [`RayKernel`] so that workers, the
//! benchmarks and the tests drive them the same way.
//!
//! Per-pixel conventions (see the crate documentation for the axes):
//! * `color` is linear RGB **premultiplied** by `opacity`, so that the composer can blend
//!   front to back with `C += (1 - A) * c; A += (1 - A) * a`;
//! * `opacity` is in `[0, 1]`;
//! * `depth` is view-space z distance in world units, finite and `> 0` where `opacity > 0`,
//!   exactly `0` where the pixel saw nothing.

use std::fmt::Debug;

use glam::Vec3;
use thiserror::Error;

use crate::camera::Camera;
use crate::reference::{Background, RenderOptions, Renderer};

/// Axis-aligned box holding all of an object's matter, in world space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    pub min: Vec3,
    pub max: Vec3,
}

impl Bounds {
    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }

    /// The eight corners, for projecting the box as an occupancy proxy.
    pub fn corners(&self) -> [Vec3; 8] {
        let (a, b) = (self.min, self.max);
        [
            Vec3::new(a.x, a.y, a.z),
            Vec3::new(b.x, a.y, a.z),
            Vec3::new(a.x, b.y, a.z),
            Vec3::new(b.x, b.y, a.z),
            Vec3::new(a.x, a.y, b.z),
            Vec3::new(b.x, a.y, b.z),
            Vec3::new(a.x, b.y, b.z),
            Vec3::new(b.x, b.y, b.z),
        ]
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum KernelError {
    #[error("pixel index {index} is outside the {width}x{height} image")]
    PixelOutOfImage { index: u32, width: u32, height: u32 },
    #[error("kernel failed: {0}")]
    Failed(String),
}

/// Per-pixel results of one batch, in the order the pixels were given. Packed arrays (one
/// allocation per channel) because that is how they travel on the wire.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PixelResults {
    pub color: Vec<[f32; 3]>,
    pub opacity: Vec<f32>,
    pub depth: Vec<f32>,
}

impl PixelResults {
    pub fn with_len(len: usize) -> PixelResults {
        PixelResults { color: vec![[0.0; 3]; len], opacity: vec![0.0; len], depth: vec![0.0; len] }
    }

    pub fn len(&self) -> usize {
        self.opacity.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity.is_empty()
    }
}

/// Work a kernel did for one batch, for load reports and benchmarks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct KernelStats {
    /// Rays generated (one per pixel for one-query kernels, more with supersampling).
    pub rays: u64,
    /// Rays that reached the object's matter (the rest cost next to nothing).
    pub rays_hit: u64,
    /// Network evaluations (or samples for the path tracer).
    pub queries: u64,
}

/// One renderable object: a camera and a pixel set in, colour, opacity and depth out.
pub trait RayKernel: Send + Sync + Debug {
    /// Short name of the kernel kind, for logs and reports ("pathtrace", "ngp", "inolf").
    fn kind(&self) -> &'static str;

    /// World-space box of the object's matter: the TaskAssigner projects it to estimate the
    /// pixels an object covers.
    fn bounds(&self) -> Bounds;

    /// Renders `pixels` (indices `y * width + x` of `camera`'s image). Implementations must
    /// call [`validate_pixels`] (or check the same) before touching memory.
    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError>;
}

/// Checks that every pixel index lies inside `camera`'s image.
pub fn validate_pixels(camera: &Camera, pixels: &[u32]) -> Result<(), KernelError> {
    let (width, height) = (camera.width(), camera.height());
    let count = u64::from(width) * u64::from(height);
    match pixels.iter().find(|&&p| u64::from(p) >= count) {
        Some(&index) => Err(KernelError::PixelOutOfImage { index, width, height }),
        None => Ok(()),
    }
}

/// Every pixel of an image in row-major order: the pixel set of a full frame.
pub fn all_pixels(camera: &Camera) -> Vec<u32> {
    (0..camera.width() * camera.height()).collect()
}

/// A full frame's results (pixels in [`all_pixels`] order) as an image the way datasets store
/// them: sRGB-encoded colour with straight alpha (`linear_to_srgb(color / opacity)`). `None`
/// if `results` does not hold `width * height` pixels.
pub fn frame_to_image(width: u32, height: u32, results: &PixelResults) -> Option<crate::image::RgbaImage> {
    let pixels = (0..results.len())
        .map(|i| {
            let a = results.opacity[i].clamp(0.0, 1.0);
            if a > 0.0 {
                let c = results.color[i].map(|v| crate::image::linear_to_srgb((v / a).clamp(0.0, 1.0)));
                [c[0], c[1], c[2], a]
            } else {
                [0.0; 4]
            }
        })
        .collect();
    crate::image::RgbaImage::from_pixels(width, height, pixels).ok()
}

/// The reference path tracer as a farm kernel: ground truth, slow, and available before any
/// neural asset is baked. Background is transparent so that objects can be fused by depth.
#[derive(Debug)]
pub struct PathTracedKernel {
    renderer: Renderer,
    options: RenderOptions,
    bounds: Bounds,
}

impl PathTracedKernel {
    pub fn new(renderer: Renderer, samples_per_pixel: u32, max_bounces: u32) -> Result<PathTracedKernel, KernelError> {
        let options = RenderOptions { samples_per_pixel, max_bounces, seed: 0, background: Background::Transparent };
        options.validate().map_err(|e| KernelError::Failed(e.to_string()))?;
        let (min, max) = renderer.scene().bounds().ok_or_else(|| KernelError::Failed("empty scene".into()))?;
        Ok(PathTracedKernel { renderer, options, bounds: Bounds { min, max } })
    }
}

impl RayKernel for PathTracedKernel {
    fn kind(&self) -> &'static str {
        "pathtrace"
    }

    fn bounds(&self) -> Bounds {
        self.bounds
    }

    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        validate_pixels(camera, pixels)?;
        let (values, stats) =
            self.renderer.render_pixel_list(camera, &self.options, pixels).map_err(|e| KernelError::Failed(e.to_string()))?;
        let mut out = PixelResults::with_len(pixels.len());
        let mut rays_hit = 0;
        for (i, (color, alpha, depth)) in values.into_iter().enumerate() {
            out.color[i] = color.to_array();
            out.opacity[i] = alpha.clamp(0.0, 1.0);
            out.depth[i] = if alpha > 0.0 { depth } else { 0.0 };
            rays_hit += u64::from(alpha > 0.0);
        }
        let kernel_stats = KernelStats { rays: stats.samples, rays_hit, queries: stats.traversal.rays };
        Ok((out, kernel_stats))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenes;

    fn kernel_and_camera() -> (PathTracedKernel, Camera) {
        let scene = scenes::builtin("diffuse").expect("builtin scene");
        let (eye, target, fov_y) = scene.default_view();
        let camera = Camera::look_at(32, 24, fov_y, eye, target, Vec3::Z).expect("camera");
        let renderer = Renderer::new(scene.scene).expect("renderer");
        (PathTracedKernel::new(renderer, 4, 2).expect("kernel"), camera)
    }

    #[test]
    fn pixel_subset_matches_full_frame() {
        let (kernel, camera) = kernel_and_camera();
        let all = all_pixels(&camera);
        let (full, _) = kernel.render_pixels(&camera, &all).expect("full frame");
        let subset = vec![0u32, 5, 31, 12 * 32 + 16, 32 * 24 - 1, 12 * 32 + 16];
        let (part, stats) = kernel.render_pixels(&camera, &subset).expect("subset");
        assert_eq!(stats.rays, subset.len() as u64 * 4);
        for (k, &p) in subset.iter().enumerate() {
            assert_eq!(part.color[k], full.color[p as usize]);
            assert_eq!(part.opacity[k], full.opacity[p as usize]);
            assert_eq!(part.depth[k], full.depth[p as usize]);
        }
        // The object sits in the middle of the default view; the corner sees nothing.
        assert!(full.opacity[12 * 32 + 16] > 0.0 && full.depth[12 * 32 + 16] > 0.0);
        assert_eq!((full.opacity[0], full.depth[0]), (0.0, 0.0));
    }

    #[test]
    fn out_of_image_pixels_are_rejected() {
        let (kernel, camera) = kernel_and_camera();
        let err = kernel.render_pixels(&camera, &[0, 32 * 24]).expect_err("out of image");
        assert_eq!(err, KernelError::PixelOutOfImage { index: 32 * 24, width: 32, height: 24 });
        assert!(kernel.render_pixels(&camera, &[u32::MAX]).is_err());
    }
}
