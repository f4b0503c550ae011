//! Scoring a kernel on a dataset's views, one way for every command that reports quality
//! (`nephele train ngp`, `nephele distill`, the first start's bake): the view's camera
//! rendered in full, the image assembled as datasets store it, PSNR and SSIM against the
//! view's image over white (NeRF conventions).

use std::time::Instant;

use thiserror::Error;

use nephele_geometry::camera::{Camera, CameraError};
use nephele_imaging::image::RgbaImage;
use nephele_imaging::metrics::{MetricsError, psnr_and_ssim};
use nephele_kernels::kernel::{KernelError, KernelStats, RayKernel, all_pixels, frame_to_image};

use crate::dataset::View;

/// What one view scored.
#[derive(Debug, Clone)]
pub struct ViewScore {
    /// The rendered view (sRGB, straight alpha).
    pub image: RgbaImage,
    pub psnr: f64,
    pub ssim: f64,
    /// The kernel's work on the view.
    pub stats: KernelStats,
    /// Seconds the kernel took (rendering only).
    pub seconds: f64,
}

#[derive(Debug, Error)]
pub enum ScoreError {
    #[error("camera of view {view}: {source}")]
    Camera { view: String, source: CameraError },
    #[error("rendering view {view}: {source}")]
    Kernel { view: String, source: KernelError },
    #[error("scoring view {view}: {source}")]
    Metrics { view: String, source: MetricsError },
    #[error("view {0}: the kernel returned a frame of the wrong size")]
    Frame(String),
}

/// Renders `view` (horizontal field of view `camera_angle_x`) with `kernel` and scores it.
pub fn score_view(kernel: &dyn RayKernel, view: &View, camera_angle_x: f32) -> Result<ViewScore, ScoreError> {
    let name = || view.name.clone();
    let (w, h) = (view.image.width(), view.image.height());
    let camera = Camera::from_fov_x(w, h, camera_angle_x, view.camera_to_world)
        .map_err(|source| ScoreError::Camera { view: name(), source })?;
    let start = Instant::now();
    let (frame, stats) = kernel
        .render_pixels(&camera, &all_pixels(&camera))
        .map_err(|source| ScoreError::Kernel { view: name(), source })?;
    let seconds = start.elapsed().as_secs_f64();
    let image = frame_to_image(w, h, &frame).ok_or_else(|| ScoreError::Frame(name()))?;
    let (psnr, ssim) =
        psnr_and_ssim(&image, &view.image, [1.0; 3]).map_err(|source| ScoreError::Metrics { view: name(), source })?;
    Ok(ViewScore { image, psnr, ssim, stats, seconds })
}

/// Mean PSNR and SSIM of `kernel` over `views` (`None` when there are none).
pub fn mean_score(
    kernel: &dyn RayKernel,
    views: &[View],
    camera_angle_x: f32,
) -> Result<Option<(f64, f64)>, ScoreError> {
    if views.is_empty() {
        return Ok(None);
    }
    let (mut psnr, mut ssim) = (0.0, 0.0);
    for v in views {
        let s = score_view(kernel, v, camera_angle_x)?;
        psnr += s.psnr;
        ssim += s.ssim;
    }
    let n = views.len() as f64;
    Ok(Some((psnr / n, ssim / n)))
}
