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

use nephele_kernels::inolf::cubes::MAX_MARCH_STRIDE;
use nephele_kernels::inolf::kernel::InolfKernel;

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
    #[error("march stride: {0}")]
    Stride(String),
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

/// How much held-out PSNR a coarser density march may cost against every voxel's: the first
/// start's objects lose 0.01-0.11 dB at stride 2 and 0.08-0.28 dB at 3 (BENCHMARKS.md,
/// 2026-12-05e).
pub const MARCH_STRIDE_BUDGET_DB: f64 = 0.1;

/// The coarsest march stride whose held-out PSNR, and every finer stride's, stays within
/// `budget_db` of every voxel's (`scores[i]`: the PSNR at stride `i + 1`); 1 when none does.
pub fn choose_march_stride(scores: &[f64], budget_db: f64) -> u32 {
    let Some(&every_voxel) = scores.first() else { return 1 };
    let within = scores.iter().take_while(|&&p| p.is_finite() && p >= every_voxel - budget_db).count();
    within.max(1) as u32
}

/// Mean PSNR of `kernel` over `views` at every march stride from 1 (every voxel) to
/// [`MAX_MARCH_STRIDE`] (empty when there are no views).
pub fn march_stride_scores(kernel: &InolfKernel, views: &[View], camera_angle_x: f32) -> Result<Vec<f64>, ScoreError> {
    let mut strided = kernel.clone();
    let mut scores = Vec::new();
    for stride in 1..=MAX_MARCH_STRIDE {
        strided.set_march_stride(stride).map_err(|e| ScoreError::Stride(e.to_string()))?;
        match mean_score(&strided, views, camera_angle_x)? {
            Some((psnr, _)) => scores.push(psnr),
            None => return Ok(Vec::new()),
        }
    }
    Ok(scores)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_march_stride_is_the_coarsest_within_the_budget() {
        // The first start's objects on 2026-12-05 (held-out dB at strides 1-4).
        assert_eq!(choose_march_stride(&[34.315, 34.203, 34.035, 33.732], 0.1), 1);
        assert_eq!(choose_march_stride(&[26.432, 26.350, 26.181, 26.134], 0.1), 2);
        assert_eq!(choose_march_stride(&[20.024, 20.016, 19.948, 19.845], 0.1), 3);
        // A coarser stride that happens to score well after a finer one that did not is not
        // taken; nothing, a NaN or an empty list give every voxel.
        assert_eq!(choose_march_stride(&[30.0, 29.0, 30.0], 0.1), 1);
        assert_eq!(choose_march_stride(&[30.0, f64::NAN, 30.0], 0.1), 1);
        assert_eq!(choose_march_stride(&[f64::NAN, 30.0], 0.1), 1);
        assert_eq!(choose_march_stride(&[], 0.1), 1);
        assert_eq!(choose_march_stride(&[30.0, 30.5, 29.95, 29.0], 0.1), 3);
    }
}
