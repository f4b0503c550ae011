//! The i-NOLF heads (NEPHELE section 4.2, eqs. 5-8).
//!
//! Given the hit point `x` and coarse opacity `a_c` from the density cubes and the view
//! direction `d` of a ray:
//!
//! * **diffuse branch** (eq. 5): multiresolution hash grid of `x` -> MLP -> diffuse colour
//!   `c_d` and specular tint `s` (sigmoids); view-independent, so it can be baked into
//!   diffuse texture cubes after training;
//! * **specular branch** (eq. 6): `[PSH(x), SH(d), a_c]` -> tiny MLP -> specular colour
//!   `c_s` and refined opacity `a` (sigmoids; `a` as a correction of `a_c`, see
//!   [`specular_activation`]);
//! * **colour** (eq. 7): `c = c_d + s * c_s`; the pixel gets `a * c` (premultiplied) and `a`;
//! * **loss** (eq. 8): L2 on the premultiplied colour and on the opacity, the colour compared
//!   either as linear RGB or, by default, sRGB-encoded ([`LossSpace`]).
//!
//! Colours are linear RGB. The gradient of the loss with respect to every head output is
//! written out in [`head_gradients`] and checked against finite differences in the tests.

use glam::Vec3;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::encoding::PshEncoding;
use nephele_geometry::Bounds;
use nephele_nn::{
    Activation, HashGrid, HashGridConfig, Mlp, MlpConfig, MlpWorkspace, NnError, sh_coefficient_count, sh_encode,
};

/// Outputs of the diffuse MLP: diffuse RGB, tint RGB.
pub const DIFFUSE_OUT: usize = 6;
/// Outputs of the specular MLP: specular RGB, refined opacity.
pub const SPECULAR_OUT: usize = 4;

#[derive(Debug, Error)]
pub enum ModelError {
    #[error(transparent)]
    Nn(#[from] NnError),
    #[error("bad model description: {0}")]
    Shape(String),
}

/// Sizes of the heads (stored in the asset's meta section).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeadsShape {
    pub grid_levels: u32,
    pub grid_log2_table: u32,
    pub grid_base: u32,
    pub grid_scale: f32,
    pub diffuse_hidden: usize,
    pub diffuse_layers: usize,
    pub sh_degree: u32,
    pub specular_hidden: usize,
    pub specular_layers: usize,
    /// Where the diffuse branch is read: at the hit point (`false`, assets written before
    /// this field), or at the march's samples of largest weight blended by weight (`true`,
    /// [`super::cubes::MarchHit::blend`]): where a pixel straddles an edge the field's density
    /// splits the ray's weight between the two surfaces, and so does the colour (the lego's
    /// held-out views +0.6 dB, BENCHMARKS.md 2026-12-07f).
    #[serde(default)]
    pub diffuse_blend: bool,
    /// How many of the march's samples of largest weight a blended diffuse colour mixes
    /// (1..=[`super::cubes::MAX_BLEND_SAMPLES`]; read only with `diffuse_blend`). Assets
    /// written before this field blended 4; 8 since 2026-12-08 (the lego's gap to its field
    /// 0.35 -> 0.09 dB, BENCHMARKS.md).
    #[serde(default = "blend_samples_before_they_were_recorded")]
    pub blend_samples: u32,
}

/// `HeadsShape::blend_samples` of assets written before it was recorded.
fn blend_samples_before_they_were_recorded() -> u32 {
    4
}

impl Default for HeadsShape {
    /// Sized for CPU training on 2 cores: 12 levels of 2^17 entries up to 1024^3, a 64-wide
    /// diffuse MLP, a 32-wide two-layer specular MLP.
    fn default() -> Self {
        let grid = HashGridConfig::with_finest_resolution(12, 17, 16, 1024);
        HeadsShape {
            grid_levels: grid.levels,
            grid_log2_table: grid.log2_table_size,
            grid_base: grid.base_resolution,
            grid_scale: grid.per_level_scale,
            diffuse_hidden: 64,
            diffuse_layers: 1,
            sh_degree: 4,
            specular_hidden: 32,
            specular_layers: 2,
            diffuse_blend: true,
            blend_samples: super::cubes::MAX_BLEND_SAMPLES as u32,
        }
    }
}

impl HeadsShape {
    /// The samples the density march keeps for these heads
    /// (`DensityCubes::set_blend_samples`): `blend_samples` where they blend, else none.
    pub fn kept_blend_samples(&self) -> u32 {
        if self.diffuse_blend { self.blend_samples } else { 0 }
    }

    pub fn grid(&self) -> HashGridConfig {
        HashGridConfig {
            levels: self.grid_levels,
            log2_table_size: self.grid_log2_table,
            base_resolution: self.grid_base,
            per_level_scale: self.grid_scale,
        }
    }

    pub fn diffuse_mlp(&self) -> MlpConfig {
        MlpConfig {
            input: self.grid().output_dim(),
            hidden: self.diffuse_hidden,
            hidden_layers: self.diffuse_layers,
            output: DIFFUSE_OUT,
            output_activation: Activation::Sigmoid,
        }
    }

    pub fn specular_input(&self, psh_features: u32) -> usize {
        psh_features as usize + sh_coefficient_count(self.sh_degree) + 1
    }

    pub fn specular_mlp(&self, psh_features: u32) -> MlpConfig {
        MlpConfig {
            input: self.specular_input(psh_features),
            hidden: self.specular_hidden,
            hidden_layers: self.specular_layers,
            output: SPECULAR_OUT,
            // Raw outputs; see [`specular_activation`].
            output_activation: Activation::None,
        }
    }
}

/// Turns the specular MLP's raw outputs into specular RGB (sigmoid) and the refined opacity
/// as a correction of the coarse one, `a = sigmoid(logit(a_c) + z_a)`: with no evidence
/// the refined opacity is the coarse opacity, which keeps unseen views and untrained PSH
/// slots close to the density field instead of at an arbitrary value.
#[inline]
pub fn specular_activation(raw: &mut [f32], coarse_opacity: f32) {
    let a = coarse_opacity.clamp(1e-4, 1.0 - 1e-4);
    let logit = (a / (1.0 - a)).ln();
    for v in raw[..3].iter_mut() {
        *v = Activation::Sigmoid.apply(*v);
    }
    raw[3] = Activation::Sigmoid.apply(raw[3] + logit);
}

/// Derivative of an output of [`specular_activation`] with respect to its raw input, from
/// the output.
#[inline]
pub fn specular_activation_derivative(y: f32) -> f32 {
    y * (1.0 - y)
}

/// The trained heads.
#[derive(Debug, Clone)]
pub struct InolfModel {
    pub shape: HeadsShape,
    /// Box the hash grid's unit cube maps to.
    pub bounds: Bounds,
    pub grid: HashGrid,
    pub diffuse: Mlp,
    pub psh: PshEncoding,
    pub specular: Mlp,
}

impl InolfModel {
    pub fn new(shape: HeadsShape, bounds: Bounds, psh: PshEncoding, seed: u64) -> Result<InolfModel, ModelError> {
        if !(bounds.min.is_finite() && bounds.max.is_finite() && bounds.size().min_element() > 0.0) {
            return Err(ModelError::Shape(format!("bad bounds {bounds:?}")));
        }
        if !(1..=5).contains(&shape.sh_degree) {
            return Err(ModelError::Shape(format!("SH degree {}", shape.sh_degree)));
        }
        let grid = HashGrid::new(shape.grid(), seed)?;
        let diffuse = Mlp::new(shape.diffuse_mlp(), seed ^ 1)?;
        let specular = Mlp::new(shape.specular_mlp(psh.feature_dim), seed ^ 2)?;
        Ok(InolfModel { shape, bounds, grid, diffuse, psh, specular })
    }

    /// Hash-grid input: `x` mapped to the unit cube of `bounds` (clamped by the grid).
    #[inline]
    pub fn grid_input(&self, x: Vec3) -> [f32; 3] {
        ((x - self.bounds.min) / self.bounds.size()).to_array()
    }

    /// Writes the specular MLP's input row for one ray; returns the PSH corners used.
    #[inline]
    pub fn specular_row(&self, x: Vec3, dir: Vec3, coarse_opacity: f32, row: &mut [f32]) -> super::encoding::Corners {
        let f = self.psh.dim();
        let corners = self.psh.encode(x, &mut row[..f]);
        let sh = sh_coefficient_count(self.shape.sh_degree);
        sh_encode(dir.to_array(), self.shape.sh_degree, &mut row[f..f + sh]);
        row[f + sh] = coarse_opacity;
        corners
    }

    /// Diffuse colour and tint of a batch of points through the hash grid and MLP
    /// (`out`: `n x 6`).
    pub fn diffuse_batch(
        &self,
        points: &[[f32; 3]],
        out: &mut [f32],
        scratch: &mut (Vec<f32>, MlpWorkspace),
    ) -> Result<(), ModelError> {
        scratch.0.resize(points.len() * self.grid.output_dim(), 0.0);
        self.grid.encode_batch(points, &mut scratch.0)?;
        self.diffuse.infer(&scratch.0, out, &mut scratch.1)?;
        Ok(())
    }
}

/// Colour, opacity and the loss gradient of one ray (eqs. 7-8).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadGradients {
    pub loss: f32,
    /// dL / d(diffuse RGB, tint RGB).
    pub d_diffuse: [f32; DIFFUSE_OUT],
    /// dL / d(specular RGB, opacity).
    pub d_specular: [f32; SPECULAR_OUT],
}

/// Combines the head outputs into the premultiplied colour and opacity of a pixel.
#[inline]
pub fn combine(diffuse: &[f32], specular: &[f32]) -> ([f32; 3], f32) {
    let a = specular[3];
    let mut c = [0.0; 3];
    for k in 0..3 {
        c[k] = a * (diffuse[k] + diffuse[3 + k] * specular[k]);
    }
    (c, a)
}

/// Where the heads' colour loss compares a pixel with its target.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LossSpace {
    /// `|a c - target|^2` on linear RGB, premultiplied (eq. 8 as written).
    Linear,
    /// `|a srgb(c) - a_t srgb(c_t)|^2`: the sRGB encoding the images are stored, viewed and
    /// scored in (PSNR), premultiplied like the radiance field's loss. A linear loss weighs an
    /// error in a dark pixel up to 12.92^2 times less than the score does.
    #[default]
    Srgb,
}

impl std::str::FromStr for LossSpace {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "srgb" => Ok(LossSpace::Srgb),
            "linear" => Ok(LossSpace::Linear),
            _ => Err(format!("'{s}' is not a loss space (srgb or linear)")),
        }
    }
}

/// The sRGB encoding's derivative `d srgb(x) / dx` (IEC 61966-2-1's piecewise curve, as
/// [`nephele_imaging::image::linear_to_srgb`]), for `x >= 0`.
#[inline]
fn srgb_slope(x: f32) -> f32 {
    if x <= 0.003_130_8 { 12.92 } else { (1.055 / 2.4) * x.powf(1.0 / 2.4 - 1.0) }
}

/// Loss `|a c - target_rgb|^2 + w |a - target_a|^2` (target premultiplied, linear; the colour
/// terms encoded first when `space` is [`LossSpace::Srgb`]) and its gradient with respect to
/// the head outputs.
#[inline]
pub fn head_gradients(
    diffuse: &[f32],
    specular: &[f32],
    target: [f32; 4],
    opacity_weight: f32,
    space: LossSpace,
) -> HeadGradients {
    match space {
        LossSpace::Linear => head_gradients_linear(diffuse, specular, target, opacity_weight),
        LossSpace::Srgb => head_gradients_srgb(diffuse, specular, target, opacity_weight),
    }
}

fn head_gradients_srgb(diffuse: &[f32], specular: &[f32], target: [f32; 4], opacity_weight: f32) -> HeadGradients {
    use nephele_imaging::image::linear_to_srgb;
    let a = specular[3];
    let target_alpha = target[3];
    let mut g = HeadGradients { loss: 0.0, d_diffuse: [0.0; DIFFUSE_OUT], d_specular: [0.0; SPECULAR_OUT] };
    let mut d_a = 0.0;
    for k in 0..3 {
        // The target's straight colour, encoded and premultiplied again.
        let t = if target_alpha > 0.0 {
            target_alpha * linear_to_srgb((target[k] / target_alpha).clamp(0.0, 1.0))
        } else {
            0.0
        };
        let c = (diffuse[k] + diffuse[3 + k] * specular[k]).max(0.0);
        let encoded = linear_to_srgb(c);
        let e = a * encoded - t;
        g.loss += e * e;
        let d_c = 2.0 * e * a * srgb_slope(c);
        d_a += 2.0 * e * encoded;
        g.d_diffuse[k] = d_c;
        g.d_diffuse[3 + k] = d_c * specular[k];
        g.d_specular[k] = d_c * diffuse[3 + k];
    }
    let ea = a - target_alpha;
    g.loss += opacity_weight * ea * ea;
    g.d_specular[3] = d_a + 2.0 * opacity_weight * ea;
    g
}

fn head_gradients_linear(diffuse: &[f32], specular: &[f32], target: [f32; 4], opacity_weight: f32) -> HeadGradients {
    let a = specular[3];
    let mut g = HeadGradients { loss: 0.0, d_diffuse: [0.0; DIFFUSE_OUT], d_specular: [0.0; SPECULAR_OUT] };
    let mut d_a = 0.0;
    for k in 0..3 {
        let c = diffuse[k] + diffuse[3 + k] * specular[k];
        let e = a * c - target[k];
        g.loss += e * e;
        // d/d(a c) = 2 e; chain to c and a.
        let d_c = 2.0 * e * a;
        d_a += 2.0 * e * c;
        g.d_diffuse[k] = d_c;
        g.d_diffuse[3 + k] = d_c * specular[k];
        g.d_specular[k] = d_c * diffuse[3 + k];
    }
    let ea = a - target[3];
    g.loss += opacity_weight * ea * ea;
    g.d_specular[3] = d_a + 2.0 * opacity_weight * ea;
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn head_gradients_match_finite_differences() {
        // Bright and dark colours (the sRGB curve is steepest near black; no colour within a
        // step of the curve's kink at 0.0031), and targets with partial alpha; f64
        // differences of the f32 loss.
        let cases: [([f32; 6], [f32; 4], [f32; 4]); 3] = [
            ([0.3, 0.6, 0.2, 0.5, 0.4, 0.9], [0.7, 0.1, 0.35, 0.8], [0.2, 0.5, 0.1, 1.0]),
            ([0.01, 0.03, 0.02, 0.2, 0.1, 0.05], [0.05, 0.4, 0.02, 0.95], [0.004, 0.02, 0.0, 0.9]),
            ([0.8, 0.9, 0.7, 0.9, 0.9, 0.9], [0.9, 0.8, 0.95, 0.3], [0.3, 0.2, 0.25, 0.4]),
        ];
        for space in [LossSpace::Linear, LossSpace::Srgb] {
            for (diffuse, specular, target) in cases {
                // Both heads' outputs as one vector: diffuse (6) then specular (4).
                let outputs: Vec<f32> = diffuse.iter().chain(&specular).copied().collect();
                let loss = |o: &[f32]| {
                    f64::from(head_gradients(&o[..DIFFUSE_OUT], &o[DIFFUSE_OUT..], target, 0.5, space).loss)
                };
                let g = head_gradients(&diffuse, &specular, target, 0.5, space);
                let analytic: Vec<f32> = g.d_diffuse.iter().chain(&g.d_specular).copied().collect();
                let h = 1e-3;
                for (i, &analytic) in analytic.iter().enumerate() {
                    let (mut p, mut m) = (outputs.clone(), outputs.clone());
                    p[i] += h;
                    m[i] -= h;
                    let num = (loss(&p) - loss(&m)) / (2.0 * f64::from(h));
                    let tolerance = 2e-3 * (1.0 + f64::from(analytic.abs()));
                    assert!((num - f64::from(analytic)).abs() < tolerance, "{space:?} output {i}: {num} vs {analytic}");
                }
            }
        }
        let (c, a) = combine(&[0.3, 0.6, 0.2, 0.5, 0.4, 0.9], &[0.7, 0.1, 0.35, 0.8]);
        assert!((c[0] - 0.8 * (0.3 + 0.5 * 0.7)).abs() < 1e-6 && a == 0.8);
    }

    #[test]
    fn the_srgb_loss_weighs_dark_errors_as_the_score_does() {
        // The same linear error of 0.01 costs a near-black pixel far more than a bright one in
        // sRGB, and the same in linear.
        let loss = |c: f32, space| {
            let diffuse = [c + 0.01, c + 0.01, c + 0.01, 0.0, 0.0, 0.0];
            head_gradients(&diffuse, &[0.0, 0.0, 0.0, 1.0], [c, c, c, 1.0], 0.0, space).loss
        };
        assert!((loss(0.02, LossSpace::Linear) - loss(0.8, LossSpace::Linear)).abs() < 1e-6);
        assert!(loss(0.02, LossSpace::Srgb) > 20.0 * loss(0.8, LossSpace::Srgb));
        // A perfect prediction costs nothing in either space.
        let perfect = head_gradients(
            &[0.1, 0.2, 0.3, 0.0, 0.0, 0.0],
            &[0.0; 4].map(|_| 0.5),
            [0.05, 0.1, 0.15, 0.5],
            0.0,
            LossSpace::Srgb,
        );
        assert!(perfect.loss < 1e-10, "{perfect:?}");
    }

    /// Assets from before `blend_samples` was recorded blended 4 samples (and read as such);
    /// new shapes record theirs, and the march keeps none for heads that do not blend.
    #[test]
    fn the_blend_count_of_older_assets_is_four() {
        let mut json = serde_json::to_value(HeadsShape::default()).expect("serialises");
        let new: HeadsShape = serde_json::from_value(json.clone()).expect("reads back");
        assert_eq!(new.blend_samples as usize, super::super::cubes::MAX_BLEND_SAMPLES);
        assert_eq!(new.kept_blend_samples(), new.blend_samples);
        json.as_object_mut().expect("an object").remove("blend_samples");
        let old: HeadsShape = serde_json::from_value(json).expect("reads without the count");
        assert_eq!(old.blend_samples, 4);
        assert_eq!(HeadsShape { diffuse_blend: false, ..old }.kept_blend_samples(), 0);
    }
}
