//! Image quality metrics, computed as NeRF papers compute them.
//!
//! Both metrics work on RGB values in `[0, 1]` as stored in the files (sRGB-encoded, data
//! range 1). RGBA images are first composited over a background colour (NeRF-synthetic uses
//! white) with `rgb * a + bg * (1 - a)`. All arithmetic is in `f64`.
//!
//! * **PSNR** is `10 log10(1 / MSE)`, the MSE taken over all pixels and channels. Identical
//!   images have MSE 0 and PSNR [`f64::INFINITY`].
//! * **SSIM** reproduces scikit-image's `structural_similarity(a, b, gaussian_weights=True,
//!   sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)`: an 11x11
//!   Gaussian window (sigma 1.5, truncated at 3.5 sigma: radius 5), K1 = 0.01, K2 = 0.03,
//!   population covariances, the SSIM map computed per channel, `(11 - 1) / 2 = 5` pixels
//!   cropped from every border, the mean taken over the rest, then the mean over channels.
//!   Images must be at least 11x11, as scikit-image requires.
//!
//! The reference numbers of the tests come from scikit-image itself, through
//! `imaging/tests/data/metrics_reference.py`.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::Serialize;

use crate::image::{ImageError, RgbaImage};

/// Standard deviation of the SSIM Gaussian window, in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// Radius of the SSIM window: `int(3.5 * sigma + 0.5)` as in `scipy.ndimage`.
pub const SSIM_RADIUS: usize = 5;
/// Side of the SSIM window (11).
pub const SSIM_WINDOW: usize = 2 * SSIM_RADIUS + 1;
const SSIM_K1: f64 = 0.01;
const SSIM_K2: f64 = 0.03;

/// Errors of the metrics.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// The two images differ in size.
    #[error("image sizes differ: {}x{} vs {}x{}", a.0, a.1, b.0, b.1)]
    SizeMismatch {
        /// Width and height of the first image.
        a: (u32, u32),
        /// Width and height of the second image.
        b: (u32, u32),
    },
    /// The images have no pixels.
    #[error("empty image")]
    Empty,
    /// A raw RGB buffer does not hold `width * height * 3` values.
    #[error("a {width}x{height} RGB buffer needs {expected} values, got {actual}")]
    BufferLength {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// `width * height * 3`.
        expected: usize,
        /// The length given.
        actual: usize,
    },
    /// A value is NaN or infinite (after compositing).
    #[error("non-finite value in the {which} image at value index {index}")]
    NonFinite {
        /// `"first"` or `"second"`.
        which: &'static str,
        /// Index into the interleaved RGB values.
        index: usize,
    },
    /// The image is smaller than the SSIM window.
    #[error("SSIM needs images of at least {min}x{min} pixels, got {width}x{height}")]
    TooSmallForSsim {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// The window side.
        min: usize,
    },
    /// An image file could not be read.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// A directory could not be listed.
    #[error("cannot list {path}: {source}")]
    ReadDir {
        /// The directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The prediction directory has no PNG files.
    #[error("no PNG files in {path}")]
    NoImages {
        /// The directory.
        path: PathBuf,
    },
    /// Predictions without a ground-truth image of the same file name.
    #[error("{} prediction(s) have no ground truth in {}: {}", missing.len(), gt.display(), missing.join(", "))]
    MissingGroundTruth {
        /// The ground-truth directory.
        gt: PathBuf,
        /// The file names missing there.
        missing: Vec<String>,
    },
    /// Evaluating one image pair failed.
    #[error("{name}: {source}")]
    InImage {
        /// The file name.
        name: String,
        /// What went wrong.
        source: Box<MetricsError>,
    },
}

/// Composites `img` over `background` into interleaved RGB `f64` values.
fn composite_rgb(img: &RgbaImage, background: [f32; 3]) -> Vec<f64> {
    let bg = background.map(f64::from);
    let mut out = Vec::with_capacity(img.pixels().len() * 3);
    for p in img.pixels() {
        let a = f64::from(p[3]);
        for c in 0..3 {
            out.push(f64::from(p[c]) * a + bg[c] * (1.0 - a));
        }
    }
    out
}

/// Validated pair of interleaved RGB images.
struct RgbPair {
    width: usize,
    height: usize,
    a: Vec<f64>,
    b: Vec<f64>,
}

impl RgbPair {
    fn from_images(a: &RgbaImage, b: &RgbaImage, background: [f32; 3]) -> Result<Self, MetricsError> {
        if (a.width(), a.height()) != (b.width(), b.height()) {
            return Err(MetricsError::SizeMismatch { a: (a.width(), a.height()), b: (b.width(), b.height()) });
        }
        Self::new(a.width(), a.height(), composite_rgb(a, background), composite_rgb(b, background))
    }

    fn from_slices(width: u32, height: u32, a: &[f32], b: &[f32]) -> Result<Self, MetricsError> {
        let expected = width as usize * height as usize * 3;
        for s in [a, b] {
            if s.len() != expected {
                return Err(MetricsError::BufferLength { width, height, expected, actual: s.len() });
            }
        }
        let widen = |s: &[f32]| s.iter().map(|&v| f64::from(v)).collect();
        Self::new(width, height, widen(a), widen(b))
    }

    fn new(width: u32, height: u32, a: Vec<f64>, b: Vec<f64>) -> Result<Self, MetricsError> {
        if a.is_empty() {
            return Err(MetricsError::Empty);
        }
        for (which, values) in [("first", &a), ("second", &b)] {
            if let Some(index) = values.iter().position(|v| !v.is_finite()) {
                return Err(MetricsError::NonFinite { which, index });
            }
        }
        Ok(Self { width: width as usize, height: height as usize, a, b })
    }

    fn psnr(&self) -> f64 {
        let sum: f64 = self.a.iter().zip(&self.b).map(|(x, y)| (x - y) * (x - y)).sum();
        let mse = sum / self.a.len() as f64;
        // As scikit-image: 10 log10(range^2 / mse); mse = 0 gives +infinity.
        10.0 * (1.0 / mse).log10()
    }

    fn ssim(&self) -> Result<f64, MetricsError> {
        let (w, h) = (self.width, self.height);
        if w < SSIM_WINDOW || h < SSIM_WINDOW {
            return Err(MetricsError::TooSmallForSsim { width: w as u32, height: h as u32, min: SSIM_WINDOW });
        }
        let kernel = gaussian_kernel();
        let n = w * h;
        let mut total = 0.0;
        let mut x = vec![0.0; n];
        let mut y = vec![0.0; n];
        for c in 0..3 {
            for i in 0..n {
                x[i] = self.a[i * 3 + c];
                y[i] = self.b[i * 3 + c];
            }
            total += ssim_plane(&x, &y, w, h, &kernel);
        }
        Ok(total / 3.0)
    }
}

/// `scipy.ndimage._gaussian_kernel1d(sigma=1.5, order=0, radius=5)`.
fn gaussian_kernel() -> [f64; SSIM_WINDOW] {
    let sigma2 = SSIM_SIGMA * SSIM_SIGMA;
    let mut k = [0.0; SSIM_WINDOW];
    for (i, v) in k.iter_mut().enumerate() {
        let x = i as f64 - SSIM_RADIUS as f64;
        *v = (-0.5 / sigma2 * x * x).exp();
    }
    let sum: f64 = k.iter().sum();
    k.map(|v| v / sum)
}

/// The separable Gaussian filter of `plane` (`w x h`), evaluated only where the SSIM mean is
/// taken: rows and columns `[r, n - r)` with `r` the window radius. scikit-image filters the
/// whole image with `mode='reflect'` and then crops exactly that border, and no output inside
/// it reads beyond the image, so the border mode never affects the result and need not be
/// reproduced. Output is `(w - 2r) x (h - 2r)`, row-major.
fn filter_valid(plane: &[f64], w: usize, h: usize, kernel: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let r = SSIM_RADIUS;
    let (vw, vh) = (w - 2 * r, h - 2 * r);
    // Axis 0 (vertical) first, as scipy does, for the valid rows and every column.
    let mut vertical = vec![0.0; vh * w];
    for oy in 0..vh {
        let row = &mut vertical[oy * w..(oy + 1) * w];
        for (k, &wk) in kernel.iter().enumerate() {
            let src = &plane[(oy + k) * w..(oy + k + 1) * w];
            for (o, &s) in row.iter_mut().zip(src) {
                *o += wk * s;
            }
        }
    }
    // Then axis 1 (horizontal) for the valid columns.
    let mut out = vec![0.0; vh * vw];
    for oy in 0..vh {
        let src = &vertical[oy * w..(oy + 1) * w];
        for ox in 0..vw {
            out[oy * vw + ox] = kernel.iter().zip(&src[ox..ox + SSIM_WINDOW]).map(|(k, s)| k * s).sum();
        }
    }
    out
}

/// Mean SSIM of one channel (see the module documentation).
fn ssim_plane(x: &[f64], y: &[f64], w: usize, h: usize, kernel: &[f64; SSIM_WINDOW]) -> f64 {
    let product = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(a, b)| a * b).collect::<Vec<f64>>();
    let ux = filter_valid(x, w, h, kernel);
    let uy = filter_valid(y, w, h, kernel);
    let uxx = filter_valid(&product(x, x), w, h, kernel);
    let uyy = filter_valid(&product(y, y), w, h, kernel);
    let uxy = filter_valid(&product(x, y), w, h, kernel);
    let c1 = SSIM_K1 * SSIM_K1;
    let c2 = SSIM_K2 * SSIM_K2;
    let mut sum = 0.0;
    for i in 0..ux.len() {
        let (mx, my) = (ux[i], uy[i]);
        // Population (co)variances: use_sample_covariance=False.
        let vx = uxx[i] - mx * mx;
        let vy = uyy[i] - my * my;
        let vxy = uxy[i] - mx * my;
        let a1 = 2.0 * mx * my + c1;
        let a2 = 2.0 * vxy + c2;
        let b1 = mx * mx + my * my + c1;
        let b2 = vx + vy + c2;
        sum += (a1 * a2) / (b1 * b2);
    }
    sum / ux.len() as f64
}

/// PSNR in dB of two RGBA images composited over `background`. Identical images give
/// [`f64::INFINITY`].
pub fn psnr(a: &RgbaImage, b: &RgbaImage, background: [f32; 3]) -> Result<f64, MetricsError> {
    Ok(RgbPair::from_images(a, b, background)?.psnr())
}

/// SSIM of two RGBA images composited over `background` (at least 11x11); 1 for identical
/// images.
pub fn ssim(a: &RgbaImage, b: &RgbaImage, background: [f32; 3]) -> Result<f64, MetricsError> {
    RgbPair::from_images(a, b, background)?.ssim()
}

/// `(psnr, ssim)` of two RGBA images composited over `background`, compositing once.
pub fn psnr_and_ssim(a: &RgbaImage, b: &RgbaImage, background: [f32; 3]) -> Result<(f64, f64), MetricsError> {
    let pair = RgbPair::from_images(a, b, background)?;
    Ok((pair.psnr(), pair.ssim()?))
}

/// PSNR in dB of two `width x height` images given as interleaved RGB values in `[0, 1]`
/// (row-major, top row first). Identical images give [`f64::INFINITY`].
pub fn psnr_rgb(width: u32, height: u32, a: &[f32], b: &[f32]) -> Result<f64, MetricsError> {
    Ok(RgbPair::from_slices(width, height, a, b)?.psnr())
}

/// SSIM of two `width x height` images given as interleaved RGB values in `[0, 1]`.
pub fn ssim_rgb(width: u32, height: u32, a: &[f32], b: &[f32]) -> Result<f64, MetricsError> {
    RgbPair::from_slices(width, height, a, b)?.ssim()
}

/// The scores of one image.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImageScore {
    /// File name (e.g. `r_0.png`).
    pub name: String,
    /// PSNR in dB; infinite for a perfect match (written as `null` in JSON).
    pub psnr: f64,
    /// SSIM.
    pub ssim: f64,
}

/// Per-image and mean scores of a set of predictions.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvalReport {
    /// One entry per image, sorted by name.
    pub per_image: Vec<ImageScore>,
    /// Mean of the per-image PSNRs (as NeRF reports it, not the PSNR of the mean MSE), over
    /// the images with a finite PSNR: a perfect match would otherwise make the mean infinite
    /// and hide every other image. [`EvalReport::perfect_matches`] counts the excluded ones;
    /// if every image matches perfectly the mean is infinite (`null` in JSON).
    pub mean_psnr: f64,
    /// Mean of the per-image SSIMs, over all images.
    pub mean_ssim: f64,
    /// Number of images whose prediction is identical to the ground truth (infinite PSNR).
    pub perfect_matches: usize,
}

impl EvalReport {
    /// Builds the report (means and the count of perfect matches) from per-image scores; both
    /// means are NaN for an empty list.
    pub fn from_scores(mut per_image: Vec<ImageScore>) -> Self {
        per_image.sort_by(|a, b| a.name.cmp(&b.name));
        let finite: Vec<f64> = per_image.iter().map(|s| s.psnr).filter(|p| p.is_finite()).collect();
        let perfect_matches = per_image.len() - finite.len();
        let mean_psnr = if finite.is_empty() {
            if per_image.is_empty() { f64::NAN } else { f64::INFINITY }
        } else {
            finite.iter().sum::<f64>() / finite.len() as f64
        };
        let mean_ssim = per_image.iter().map(|s| s.ssim).sum::<f64>() / per_image.len() as f64;
        Self { per_image, mean_psnr, mean_ssim, perfect_matches }
    }
}

/// Evaluates every PNG file of `pred` (not recursive) against the file of the same name in
/// `gt`, both composited over `background`, in parallel. Every prediction needs a ground
/// truth of the same size; the error for missing ones lists them all. Files of `gt` without a
/// prediction are ignored.
pub fn evaluate_dirs(pred: &Path, gt: &Path, background: [f32; 3]) -> Result<EvalReport, MetricsError> {
    let entries =
        std::fs::read_dir(pred).map_err(|source| MetricsError::ReadDir { path: pred.to_path_buf(), source })?;
    let mut names = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|source| MetricsError::ReadDir { path: pred.to_path_buf(), source })?;
        let path = entry.path();
        let is_png = path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if !is_png || !path.is_file() {
            continue;
        }
        match entry.file_name().into_string() {
            Ok(name) => names.push(name),
            Err(name) => {
                tracing::warn!(?name, "skipping a prediction whose file name is not UTF-8")
            }
        }
    }
    if names.is_empty() {
        return Err(MetricsError::NoImages { path: pred.to_path_buf() });
    }
    names.sort();
    let missing: Vec<String> = names.iter().filter(|n| !gt.join(n).is_file()).cloned().collect();
    if !missing.is_empty() {
        return Err(MetricsError::MissingGroundTruth { gt: gt.to_path_buf(), missing });
    }
    let scores = names
        .par_iter()
        .map(|name| {
            let score = || -> Result<ImageScore, MetricsError> {
                let p = RgbaImage::load_png(pred.join(name))?;
                let g = RgbaImage::load_png(gt.join(name))?;
                let (psnr, ssim) = psnr_and_ssim(&p, &g, background)?;
                Ok(ImageScore { name: name.clone(), psnr, ssim })
            };
            score().map_err(|e| MetricsError::InImage { name: name.clone(), source: Box::new(e) })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(EvalReport::from_scores(scores))
}

#[cfg(test)]
mod tests {
    use super::*;

    // Reference values from scikit-image 0.26.0 / numpy 2.4.6, printed by
    // `imaging/tests/data/metrics_reference.py`: (PSNR, SSIM) of `level_b` (or `level_c`
    // for MILD) against `level_a`, computed with `peak_signal_noise_ratio(data_range=1)` and
    // `structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    // data_range=1.0, channel_axis=-1)`.
    const OPAQUE_24X20: (f64, f64) = (12.374066280003378, 0.33675697416808886);
    const OPAQUE_32X32: (f64, f64) = (12.034892492625994, 0.2268598284511755);
    const MILD_32X32: (f64, f64) = (42.23351774198049, 0.9996365619986767);
    const ALPHA_17X23_WHITE: (f64, f64) = (16.645281942361233, 0.7422667567997362);
    const ALPHA_17X23_BLACK: (f64, f64) = (16.74613828251133, 0.7362976453977518);

    // The same integer formulas as the Python script, so that both sides see identical
    // inputs (8-bit levels k / 255 rounded to f32).
    fn hash32(mut x: u32) -> u32 {
        x ^= x >> 16;
        x = x.wrapping_mul(0x7feb_352d);
        x ^= x >> 15;
        x = x.wrapping_mul(0x846c_a68b);
        x ^= x >> 16;
        x
    }

    fn h(i: u32, j: u32, c: u32, seed: u32) -> i64 {
        i64::from(hash32((seed << 24) ^ (j << 12) ^ (i << 2) ^ c))
    }

    fn clamp255(v: i64) -> i64 {
        v.clamp(0, 255)
    }

    fn level_a(i: u32, j: u32, c: u32) -> i64 {
        let (i64_, j64, c64) = (i64::from(i), i64::from(j), i64::from(c));
        let base = (i64_ * i64_ * (c64 + 2) + j64 * 7 * (3 - c64) + 31 * c64) % 256;
        clamp255(base + h(i, j, c, 1) % 41 - 20)
    }

    fn level_b(i: u32, j: u32, c: u32, w: u32, hgt: u32) -> i64 {
        let mut s = 0;
        for dj in -1i64..=1 {
            for di in -1i64..=1 {
                let ii = (i64::from(i) + di).clamp(0, i64::from(w) - 1) as u32;
                let jj = (i64::from(j) + dj).clamp(0, i64::from(hgt) - 1) as u32;
                s += level_a(ii, jj, c);
            }
        }
        clamp255(s / 9 + h(i, j, c, 2) % 21 - 10 + 3 * i64::from(c))
    }

    fn level_c(i: u32, j: u32, c: u32) -> i64 {
        clamp255(level_a(i, j, c) + h(i, j, c, 5) % 7 - 3)
    }

    fn alpha_a(i: u32, j: u32, w: u32) -> i64 {
        if i < w / 2 { 255 } else { h(i, j, 3, 3) % 256 }
    }

    fn alpha_b(i: u32, j: u32, w: u32) -> i64 {
        if i < w / 2 { 255 } else { clamp255(alpha_a(i, j, w) + h(i, j, 3, 4) % 31 - 15) }
    }

    fn f(k: i64) -> f32 {
        k as f32 / 255.0
    }

    /// The RGBA pair (A, B) of the Python script; `mild` uses `level_c` for B.
    fn reference_pair(w: u32, hgt: u32, mild: bool) -> (RgbaImage, RgbaImage) {
        let a = RgbaImage::from_fn(w, hgt, |i, j| {
            [f(level_a(i, j, 0)), f(level_a(i, j, 1)), f(level_a(i, j, 2)), f(alpha_a(i, j, w))]
        });
        let b = RgbaImage::from_fn(w, hgt, |i, j| {
            let l = |c| {
                if mild { level_c(i, j, c) } else { level_b(i, j, c, w, hgt) }
            };
            [f(l(0)), f(l(1)), f(l(2)), f(alpha_b(i, j, w))]
        });
        (a, b)
    }

    fn rgb_of(img: &RgbaImage) -> Vec<f32> {
        img.pixels().iter().flat_map(|p| [p[0], p[1], p[2]]).collect()
    }

    fn assert_rel(actual: f64, expected: f64, what: &str) {
        let rel = ((actual - expected) / expected).abs();
        assert!(rel < 1e-6, "{what}: got {actual}, scikit-image {expected} (relative error {rel:e})");
    }

    #[test]
    fn opaque_cases_match_scikit_image() {
        for (w, hgt, mild, (p, s), name) in [
            (24, 20, false, OPAQUE_24X20, "24x20"),
            (32, 32, false, OPAQUE_32X32, "32x32"),
            (32, 32, true, MILD_32X32, "mild 32x32"),
        ] {
            // The opaque cases ignore alpha: use the raw RGB API.
            let (a, b) = reference_pair(w, hgt, mild);
            let (a, b) = (rgb_of(&a), rgb_of(&b));
            assert_rel(psnr_rgb(w, hgt, &a, &b).expect("psnr"), p, &format!("PSNR {name}"));
            assert_rel(ssim_rgb(w, hgt, &a, &b).expect("ssim"), s, &format!("SSIM {name}"));
            // Symmetric in its arguments.
            assert_rel(ssim_rgb(w, hgt, &b, &a).expect("ssim"), s, &format!("SSIM {name} swapped"));
        }
    }

    #[test]
    fn alpha_cases_match_scikit_image() {
        let (a, b) = reference_pair(17, 23, false);
        for (bg, (p, s), name) in [([1.0; 3], ALPHA_17X23_WHITE, "white"), ([0.0; 3], ALPHA_17X23_BLACK, "black")] {
            assert_rel(psnr(&a, &b, bg).expect("psnr"), p, &format!("PSNR over {name}"));
            assert_rel(ssim(&a, &b, bg).expect("ssim"), s, &format!("SSIM over {name}"));
            let (p2, s2) = psnr_and_ssim(&a, &b, bg).expect("both");
            assert_eq!(
                (p2.to_bits(), s2.to_bits()),
                (psnr(&a, &b, bg).expect("psnr").to_bits(), ssim(&a, &b, bg).expect("ssim").to_bits())
            );
        }
    }

    #[test]
    fn identical_images_give_infinite_psnr_and_unit_ssim() {
        let (a, _) = reference_pair(24, 20, false);
        let p = psnr(&a, &a.clone(), [1.0; 3]).expect("psnr");
        assert_eq!(p, f64::INFINITY);
        let s = ssim(&a, &a.clone(), [1.0; 3]).expect("ssim");
        assert!((s - 1.0).abs() < 1e-12, "{s}");
    }

    #[test]
    fn psnr_of_a_known_mse() {
        // Every value differs by 0.1: MSE 0.01, PSNR 20 dB.
        let a = vec![0.5f32; 4 * 3];
        let b = vec![0.6f32; 4 * 3];
        let p = psnr_rgb(2, 2, &a, &b).expect("psnr");
        assert!((p - 20.0).abs() < 1e-5, "{p}");
    }

    #[test]
    fn errors_on_bad_input() {
        let a = RgbaImage::new(12, 12);
        let b = RgbaImage::new(12, 13);
        assert!(matches!(psnr(&a, &b, [1.0; 3]), Err(MetricsError::SizeMismatch { .. })));
        assert!(matches!(ssim(&a, &b, [1.0; 3]), Err(MetricsError::SizeMismatch { .. })));
        let e = RgbaImage::new(0, 0);
        assert!(matches!(psnr(&e, &e, [1.0; 3]), Err(MetricsError::Empty)));
        let small = RgbaImage::new(10, 12);
        assert!(matches!(ssim(&small, &small, [1.0; 3]), Err(MetricsError::TooSmallForSsim { .. })));
        assert!(psnr(&small, &small, [1.0; 3]).is_ok());
        let mut nan = RgbaImage::new(12, 12);
        nan.set_pixel(3, 4, [f32::NAN, 0.0, 0.0, 1.0]);
        assert!(matches!(psnr(&a, &nan, [1.0; 3]), Err(MetricsError::NonFinite { which: "second", .. })));
        assert!(matches!(ssim(&nan, &a, [1.0; 3]), Err(MetricsError::NonFinite { which: "first", .. })));
        assert!(matches!(psnr_rgb(2, 2, &[0.0; 12], &[0.0; 11]), Err(MetricsError::BufferLength { .. })));
    }

    #[test]
    fn evaluate_dirs_scores_matching_files() {
        let pred = tempfile::tempdir().expect("tempdir");
        let gt = tempfile::tempdir().expect("tempdir");
        let (a, b) = reference_pair(24, 20, false);
        a.save_png(gt.path().join("x.png")).expect("save");
        b.save_png(pred.path().join("x.png")).expect("save");
        a.save_png(gt.path().join("y.png")).expect("save");
        a.save_png(pred.path().join("y.png")).expect("save");
        a.save_png(gt.path().join("only_gt.png")).expect("save");
        std::fs::write(pred.path().join("notes.txt"), "ignored").expect("write");

        let report = evaluate_dirs(pred.path(), gt.path(), [1.0; 3]).expect("evaluate");
        let names: Vec<&str> = report.per_image.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["x.png", "y.png"]);
        let (px, sx) = psnr_and_ssim(&b, &a, [1.0; 3]).expect("metrics");
        assert_eq!(report.per_image[0].psnr, px);
        assert_eq!(report.per_image[0].ssim, sx);
        assert_eq!(report.per_image[1].psnr, f64::INFINITY);
        // The perfect match is left out of the PSNR mean but counted.
        assert_eq!(report.perfect_matches, 1);
        assert_eq!(report.mean_psnr, px);
        assert!((report.mean_ssim - (sx + 1.0) / 2.0).abs() < 1e-12);
        let json = serde_json::to_value(&report).expect("json");
        assert_eq!(json["per_image"][1]["psnr"], serde_json::Value::Null);
        assert_eq!(json["perfect_matches"], 1);
    }

    #[test]
    fn evaluate_dirs_lists_missing_ground_truth() {
        let pred = tempfile::tempdir().expect("tempdir");
        let gt = tempfile::tempdir().expect("tempdir");
        let img = RgbaImage::new(12, 12);
        for n in ["a.png", "b.png", "c.png"] {
            img.save_png(pred.path().join(n)).expect("save");
        }
        img.save_png(gt.path().join("b.png")).expect("save");
        match evaluate_dirs(pred.path(), gt.path(), [1.0; 3]) {
            Err(MetricsError::MissingGroundTruth { missing, .. }) => {
                assert_eq!(missing, ["a.png", "c.png"])
            }
            other => panic!("expected MissingGroundTruth, got {other:?}"),
        }
        // Size mismatch names the image.
        RgbaImage::new(13, 12).save_png(gt.path().join("a.png")).expect("save");
        img.save_png(gt.path().join("c.png")).expect("save");
        let err = evaluate_dirs(pred.path(), gt.path(), [1.0; 3]).expect_err("size mismatch");
        assert!(err.to_string().contains("a.png"), "{err}");
        // An empty prediction directory is an error.
        let empty = tempfile::tempdir().expect("tempdir");
        assert!(matches!(evaluate_dirs(empty.path(), gt.path(), [1.0; 3]), Err(MetricsError::NoImages { .. })));
    }
}
