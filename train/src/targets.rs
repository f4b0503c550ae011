//! Training targets from posed images, checked once before any step (issue 18: a training
//! run fed corrupt pixels refuses or clamps them, with a count).
//!
//! PNG files hold values in `[0, 1]`, but images made in the process (path-traced views,
//! denoised or converted ones, anything built with `RgbaImage::from_pixels`) can hold
//! anything. A finite value outside `[0, 1]` is clamped onto it and counted; a pixel with a
//! NaN or infinite channel is dropped (its target becomes [`DROPPED`], which the trainers
//! never draw) and counted. More than [`MAX_DROPPED_FRACTION`] dropped pixels is not noise
//! but a broken dataset: [`PixelCheck::verdict`] refuses it.

use nephele_imaging::image::{RgbaImage, srgb_to_linear};
use thiserror::Error;

/// At most this fraction of all training pixels may be dropped as non-finite (a few NaN
/// fireflies of a path tracer) before a training run refuses the data.
pub const MAX_DROPPED_FRACTION: f64 = 0.01;

/// The target of a dropped pixel: never drawn (see [`is_dropped`]).
pub const DROPPED: [f32; 4] = [f32::NAN; 4];

/// Whether a target is [`DROPPED`].
pub fn is_dropped(target: &[f32; 4]) -> bool {
    target[3].is_nan()
}

/// The colour space the trainer learns in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TargetSpace {
    /// The stored sRGB encoding, premultiplied by alpha (the radiance field's loss).
    Srgb,
    /// Linear radiance, premultiplied by alpha (the i-NOLF heads' loss).
    Linear,
}

/// What the check found in the pixels of a training set.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PixelCheck {
    /// Pixels checked.
    pub pixels: u64,
    /// Pixels with a finite channel outside `[0, 1]`, clamped onto it.
    pub clamped: u64,
    /// Pixels with a NaN or infinite channel, dropped from training.
    pub dropped: u64,
}

/// Too many training pixels are not numbers.
#[derive(Debug, Error, Clone, Copy, PartialEq, Eq)]
#[error(
    "{dropped} of {pixels} training pixels hold NaN or infinite values (more than {} %): the images are corrupt",
    MAX_DROPPED_FRACTION * 100.0
)]
pub struct CorruptPixels {
    pub pixels: u64,
    pub dropped: u64,
}

impl PixelCheck {
    /// Adds another image's counts.
    pub fn merge(&mut self, other: PixelCheck) {
        self.pixels += other.pixels;
        self.clamped += other.clamped;
        self.dropped += other.dropped;
    }

    /// Accepts the set unless more than [`MAX_DROPPED_FRACTION`] of its pixels were dropped.
    pub fn verdict(&self) -> Result<(), CorruptPixels> {
        if self.dropped as f64 > MAX_DROPPED_FRACTION * self.pixels as f64 {
            return Err(CorruptPixels { pixels: self.pixels, dropped: self.dropped });
        }
        Ok(())
    }

    /// Whether anything was clamped or dropped.
    pub fn repaired_any(&self) -> bool {
        self.clamped + self.dropped > 0
    }

    /// One line for logs and bake reports.
    pub fn summary(&self) -> String {
        format!(
            "{} training pixels: {} clamped into [0, 1], {} dropped as NaN or infinite",
            self.pixels, self.clamped, self.dropped
        )
    }
}

/// The premultiplied targets of `image` (row-major) in `space`, with its pixels' check added
/// to `check`.
pub fn premultiplied_targets(image: &RgbaImage, space: TargetSpace, check: &mut PixelCheck) -> Vec<[f32; 4]> {
    let mut local = PixelCheck { pixels: image.pixels().len() as u64, ..PixelCheck::default() };
    let targets = image
        .pixels()
        .iter()
        .map(|p| {
            if !p.iter().all(|v| v.is_finite()) {
                local.dropped += 1;
                return DROPPED;
            }
            if p.iter().any(|v| !(0.0..=1.0).contains(v)) {
                local.clamped += 1;
            }
            let [r, g, b, a] = p.map(|v| v.clamp(0.0, 1.0));
            let rgb = match space {
                TargetSpace::Srgb => [r, g, b],
                TargetSpace::Linear => [r, g, b].map(srgb_to_linear),
            };
            [rgb[0] * a, rgb[1] * a, rgb[2] * a, a]
        })
        .collect();
    check.merge(local);
    targets
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corrupt_values_are_clamped_or_dropped_and_counted() {
        let image = RgbaImage::from_pixels(
            3,
            2,
            vec![
                [0.5, 0.25, 1.0, 0.5],
                [1.5, -0.2, 0.5, 1.0],
                [f32::NAN, 0.0, 0.0, 1.0],
                [0.0, 0.0, 0.0, f32::INFINITY],
                [0.2, 0.2, 0.2, 2.0],
                [1e-45, 0.0, 0.0, 1.0],
            ],
        )
        .expect("image");
        let mut check = PixelCheck::default();
        let srgb = premultiplied_targets(&image, TargetSpace::Srgb, &mut check);
        assert_eq!(check, PixelCheck { pixels: 6, clamped: 2, dropped: 2 });
        assert_eq!(srgb[0], [0.25, 0.125, 0.5, 0.5]);
        assert_eq!(srgb[1], [1.0, 0.0, 0.5, 1.0]);
        assert!(is_dropped(&srgb[2]) && is_dropped(&srgb[3]));
        assert_eq!(srgb[4], [0.2, 0.2, 0.2, 1.0]);
        assert!(srgb.iter().filter(|t| !is_dropped(t)).flatten().all(|v| (0.0..=1.0).contains(v)));
        let linear = premultiplied_targets(&image, TargetSpace::Linear, &mut check);
        assert_eq!(check.pixels, 12);
        assert!((linear[0][1] - srgb_to_linear(0.25) * 0.5).abs() < 1e-7);
        // Two of six dropped is far beyond 1 %.
        let err = check.verdict().expect_err("corrupt");
        assert_eq!(err, CorruptPixels { pixels: 12, dropped: 4 });
        assert!(err.to_string().contains("4 of 12"), "{err}");
    }

    #[test]
    fn a_few_dropped_pixels_are_accepted() {
        let check = PixelCheck { pixels: 1000, clamped: 50, dropped: 10 };
        assert!(check.verdict().is_ok() && check.repaired_any());
        assert!(PixelCheck { pixels: 1000, clamped: 0, dropped: 11 }.verdict().is_err());
        assert!(!PixelCheck { pixels: 10, ..PixelCheck::default() }.repaired_any());
    }
}
