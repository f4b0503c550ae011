//! The kernel interface: the unit of work the render farm ships.
//!
//! A worker receives a camera and a set of pixels of one object and returns, per pixel,
//! colour, opacity and depth. Every kernel (the reference path tracer, the i-NGP-style
//! baseline, i-NOLF, later GPU backends) sits behind [`RayKernel`] so that workers, the
//! benchmarks and the tests drive them the same way.
//!
//! The per-pixel results and their conventions live in `nephele-geometry`
//! ([`PixelResults`]), shared with the protocol and the composer.

use std::fmt::Debug;

use thiserror::Error;

use nephele_geometry::camera::Camera;
pub use nephele_geometry::{Bounds, PixelOutOfImage, PixelResults, SolidGrid, all_pixels, validate_pixels};
use nephele_pathtracer::{Background, RenderOptions, Renderer};

#[derive(Debug, Error, PartialEq)]
pub enum KernelError {
    #[error("pixel index {index} is outside the {width}x{height} image")]
    PixelOutOfImage { index: u32, width: u32, height: u32 },
    #[error("kernel failed: {0}")]
    Failed(String),
}

impl From<PixelOutOfImage> for KernelError {
    fn from(e: PixelOutOfImage) -> KernelError {
        KernelError::PixelOutOfImage { index: e.index, width: e.width, height: e.height }
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
    /// Samples an environment kernel traced but did not light because an object's solid
    /// matter hides them ([`RayKernel::render_pixels_behind`]).
    pub hidden: u64,
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

    /// Renders two views (a headset's eyes) in one pass, where the kernel has such a pass (the
    /// stereo GI model: one pass costs about half of two); `None`: render them one by one.
    fn render_pair(
        &self,
        left: (&Camera, &[u32]),
        right: (&Camera, &[u32]),
    ) -> Option<Result<([PixelResults; 2], KernelStats), KernelError>> {
        let _ = (left, right);
        None
    }

    /// [`Self::render_pixels`] for a kernel behind objects whose solid matter (`occluders`, in
    /// this kernel's coordinates) hides part of the view: an environment kernel may skip the
    /// lighting of what they hide (issue 13); the default renders as if they were not there.
    fn render_pixels_behind(
        &self,
        camera: &Camera,
        pixels: &[u32],
        occluders: &[SolidGrid],
    ) -> Result<(PixelResults, KernelStats), KernelError> {
        let _ = occluders;
        self.render_pixels(camera, pixels)
    }

    /// [`Self::render_pair`] behind `occluders` (see [`Self::render_pixels_behind`]).
    fn render_pair_behind(
        &self,
        left: (&Camera, &[u32]),
        right: (&Camera, &[u32]),
        occluders: &[SolidGrid],
    ) -> Option<Result<([PixelResults; 2], KernelStats), KernelError>> {
        let _ = occluders;
        self.render_pair(left, right)
    }

    /// Whether the kernel's cost is a whole view whatever pixels are asked (an image-space
    /// network such as the GI U-Net): then a derived view is rendered, not reprojected.
    fn shades_whole_views(&self) -> bool {
        false
    }
}

/// A full frame's results (pixels in [`all_pixels`] order) as an image the way datasets store
/// them: sRGB-encoded colour with straight alpha (`linear_to_srgb(color / opacity)`). `None`
/// if `results` does not hold `width * height` pixels.
pub fn frame_to_image(width: u32, height: u32, results: &PixelResults) -> Option<nephele_imaging::image::RgbaImage> {
    let pixels = (0..results.len())
        .map(|i| {
            let a = results.opacity[i].clamp(0.0, 1.0);
            if a > 0.0 {
                let c = results.color[i].map(|v| nephele_imaging::image::linear_to_srgb((v / a).clamp(0.0, 1.0)));
                [c[0], c[1], c[2], a]
            } else {
                [0.0; 4]
            }
        })
        .collect();
    nephele_imaging::image::RgbaImage::from_pixels(width, height, pixels).ok()
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
        let options = RenderOptions {
            samples_per_pixel,
            max_bounces,
            background: Background::Transparent,
            ..RenderOptions::default()
        };
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
        let (values, stats) = self
            .renderer
            .render_pixel_list(camera, &self.options, pixels)
            .map_err(|e| KernelError::Failed(e.to_string()))?;
        let mut out = PixelResults::with_len(pixels.len());
        let mut rays_hit = 0;
        for (i, (color, alpha, depth)) in values.into_iter().enumerate() {
            out.color[i] = color.to_array();
            out.opacity[i] = alpha.clamp(0.0, 1.0);
            out.depth[i] = if alpha > 0.0 { depth } else { 0.0 };
            rays_hit += u64::from(alpha > 0.0);
        }
        let kernel_stats = KernelStats { rays: stats.samples, rays_hit, queries: stats.traversal.rays, hidden: 0 };
        Ok((out, kernel_stats))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use nephele_pathtracer::scenes;

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
