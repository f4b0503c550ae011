//! How far two renderings of the same pixels are apart: the CPU/GPU twin check the tests
//! assert on and `nephele bench inolf --device gpu` prints.

use nephele_kernels::kernel::PixelResults;

/// Depth differences above this (relative) count as disagreements.
pub const DEPTH_RELATIVE_TOLERANCE: f32 = 1e-3;

/// Differences between a reference rendering (the CPU kernel) and a twin (the GPU kernel).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Agreement {
    pub pixels: usize,
    /// Pixels one rendering hits and the other does not (grazing rays at silhouettes).
    pub mask_mismatches: usize,
    /// Mean absolute colour difference per channel over all pixels.
    pub color_mean_abs: f64,
    /// Largest colour difference over the pixels both hit.
    pub color_max_abs: f32,
    /// Mean absolute opacity difference over all pixels.
    pub opacity_mean_abs: f64,
    /// Pixels both hit whose depths differ by more than [`DEPTH_RELATIVE_TOLERANCE`]
    /// (relative): where two samples of the march tie for the largest weight.
    pub depth_mismatches: usize,
    /// Non-finite values in the twin.
    pub non_finite: usize,
}

impl Agreement {
    pub fn of(reference: &PixelResults, twin: &PixelResults) -> Agreement {
        let n = reference.len().min(twin.len());
        let mut a = Agreement { pixels: n, ..Agreement::default() };
        let (mut color_sum, mut opacity_sum) = (0.0f64, 0.0f64);
        for i in 0..n {
            let values = twin.color[i].iter().chain([&twin.opacity[i], &twin.depth[i]]);
            a.non_finite += values.filter(|v| !v.is_finite()).count();
            let (hit_r, hit_t) = (reference.opacity[i] > 0.0, twin.opacity[i] > 0.0);
            a.mask_mismatches += usize::from(hit_r != hit_t);
            for k in 0..3 {
                let d = (reference.color[i][k] - twin.color[i][k]).abs();
                color_sum += f64::from(d);
                if hit_r && hit_t && d.is_finite() {
                    a.color_max_abs = a.color_max_abs.max(d);
                }
            }
            opacity_sum += f64::from((reference.opacity[i] - twin.opacity[i]).abs());
            if hit_r && hit_t {
                let (dr, dt) = (reference.depth[i], twin.depth[i]);
                let rel = (dr - dt).abs() / dr.abs().max(1e-6);
                a.depth_mismatches += usize::from(!(rel <= DEPTH_RELATIVE_TOLERANCE));
            }
        }
        a.color_mean_abs = color_sum / (3 * n.max(1)) as f64;
        a.opacity_mean_abs = opacity_sum / n.max(1) as f64;
        a
    }

    /// Adds `other`'s pixels to these (means weighted by pixel counts).
    pub fn merge(&mut self, other: &Agreement) {
        let n = (self.pixels + other.pixels).max(1) as f64;
        let (a, b) = (self.pixels as f64, other.pixels as f64);
        self.color_mean_abs = (self.color_mean_abs * a + other.color_mean_abs * b) / n;
        self.opacity_mean_abs = (self.opacity_mean_abs * a + other.opacity_mean_abs * b) / n;
        self.color_max_abs = self.color_max_abs.max(other.color_max_abs);
        self.pixels += other.pixels;
        self.mask_mismatches += other.mask_mismatches;
        self.depth_mismatches += other.depth_mismatches;
        self.non_finite += other.non_finite;
    }

    /// Fraction of pixels whose hit mask differs.
    pub fn mask_mismatch_fraction(&self) -> f64 {
        self.mask_mismatches as f64 / self.pixels.max(1) as f64
    }

    /// Fraction of pixels whose depth differs beyond the tolerance.
    pub fn depth_mismatch_fraction(&self) -> f64 {
        self.depth_mismatches as f64 / self.pixels.max(1) as f64
    }
}

impl std::fmt::Display for Agreement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} px: hit mask differs on {} ({:.3} %), colour mean |diff| {:.2e} (max {:.2e} on hits), opacity mean |diff| {:.2e}, \
             depth off by > {:.0e} on {} ({:.3} %), non-finite {}",
            self.pixels,
            self.mask_mismatches,
            100.0 * self.mask_mismatch_fraction(),
            self.color_mean_abs,
            self.color_max_abs,
            self.opacity_mean_abs,
            DEPTH_RELATIVE_TOLERANCE,
            self.depth_mismatches,
            100.0 * self.depth_mismatch_fraction(),
            self.non_finite
        )
    }
}
