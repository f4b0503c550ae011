//! The radiance field (i-NGP, section 5.4): density from a hash grid and a small MLP, colour
//! from the density network's geometric features and the SH-encoded view direction through
//! a second MLP; an occupancy grid to skip empty space; volume rendering (NEPHELE eq. 4).

use glam::Vec3;

use nephele_geometry::Bounds;
use nephele_nn::{Activation, HashGrid, HashGridConfig, Mlp, MlpConfig, MlpWorkspace, sh_coefficient_count, sh_encode};

use super::NgpError;
use super::march::Marcher;
use super::occupancy::OccupancyGrid;

/// Transmittance below which a ray stops (its remaining contribution is < 1e-3).
pub const EARLY_STOP_TRANSMITTANCE: f32 = 1e-3;
/// Samples evaluated per network batch along one ray while rendering.
const RENDER_CHUNK: usize = 16;
/// Samples whose blending weight is below this skip the colour network when rendering.
const MIN_COLOR_WEIGHT: f32 = 1e-4;

/// Shape of a radiance field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldConfig {
    pub grid: HashGridConfig,
    /// Width of the density network's hidden layer (one hidden layer).
    pub density_hidden: usize,
    /// Geometric features passed to the colour network besides the log-density.
    pub geo_features: usize,
    pub color_hidden: usize,
    pub color_hidden_layers: usize,
    /// SH degree of the direction encoding (tiny-cuda-nn convention: `degree^2` values).
    pub sh_degree: u32,
    /// Ray-marching steps along the box's diagonal (i-NGP: 1024).
    pub steps_per_diagonal: u32,
    /// Occupancy grid cells per side.
    pub occupancy_resolution: u32,
}

impl Default for FieldConfig {
    /// i-NGP's NeRF configuration: 16 levels of 2 features, 2^19 entries, resolutions 16 to
    /// 2048, a 64-wide density MLP giving 16 values and a 64-wide colour MLP with two hidden
    /// layers, SH degree 4, 1024 steps per diagonal, 128^3 occupancy.
    fn default() -> Self {
        FieldConfig {
            grid: HashGridConfig::with_finest_resolution(16, 19, 16, 2048),
            density_hidden: 64,
            geo_features: 15,
            color_hidden: 64,
            color_hidden_layers: 2,
            sh_degree: 4,
            steps_per_diagonal: 1024,
            occupancy_resolution: 128,
        }
    }
}

impl FieldConfig {
    pub fn validate(&self) -> Result<(), NgpError> {
        self.grid.validate()?;
        self.density_config().validate()?;
        self.color_config().validate()?;
        if !(1..=5).contains(&self.sh_degree) {
            return Err(NgpError::Invalid(format!("SH degree {} not in 1..=5", self.sh_degree)));
        }
        if !(16..=8192).contains(&self.steps_per_diagonal) {
            return Err(NgpError::Invalid(format!("steps per diagonal {} not in 16..=8192", self.steps_per_diagonal)));
        }
        if !OccupancyGrid::valid_resolution(self.occupancy_resolution) {
            return Err(NgpError::Invalid(format!(
                "occupancy resolution {} must be a multiple of 8 in 16..=512",
                self.occupancy_resolution
            )));
        }
        Ok(())
    }

    pub fn density_config(&self) -> MlpConfig {
        MlpConfig {
            input: self.grid.output_dim(),
            hidden: self.density_hidden,
            hidden_layers: 1,
            output: 1 + self.geo_features,
            output_activation: Activation::None,
        }
    }

    pub fn color_config(&self) -> MlpConfig {
        MlpConfig {
            input: 1 + self.geo_features + sh_coefficient_count(self.sh_degree),
            hidden: self.color_hidden,
            hidden_layers: self.color_hidden_layers,
            output: 3,
            output_activation: Activation::Sigmoid,
        }
    }
}

/// A trained (or training) radiance field over a cubic box.
#[derive(Debug, Clone)]
pub struct RadianceField {
    pub config: FieldConfig,
    /// Lower corner of the cubic box.
    pub min: Vec3,
    /// Side of the cubic box.
    pub size: f32,
    pub grid: HashGrid,
    pub density: Mlp,
    pub color: Mlp,
    pub occupancy: OccupancyGrid,
}

/// Reusable buffers for queries on one thread.
#[derive(Debug, Default)]
pub struct FieldScratch {
    points: Vec<[f32; 3]>,
    encoded: Vec<f32>,
    density_out: Vec<f32>,
    color_in: Vec<f32>,
    color_out: Vec<f32>,
    ws: MlpWorkspace,
    sh: Vec<f32>,
}

impl FieldScratch {
    pub fn new() -> Self {
        Self::default()
    }
}

/// The volume-rendered result of one ray.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RayResult {
    /// `sum_i w_i c_i`: colour premultiplied by opacity, in the dataset's (sRGB-encoded)
    /// space.
    pub color: [f32; 3],
    /// Accumulated opacity `sum_i w_i = 1 - T` over a transparent background.
    pub opacity: f32,
    /// `sum_i w_i t_i / sum_i w_i`: expected distance along the ray (0 when nothing).
    pub distance: f32,
    /// Distance of the sample with the largest blending weight `w_i` (i-NOLF's hit point,
    /// NEPHELE section 4), 0 when nothing.
    pub peak_distance: f32,
    /// Density samples evaluated.
    pub samples: u32,
    /// Colour network evaluations.
    pub color_queries: u32,
}

/// Trunc-exp density activation (i-NGP): `exp(min(raw, 15))`.
#[inline]
pub fn density_activation(raw: f32) -> f32 {
    raw.min(15.0).exp()
}

impl RadianceField {
    /// Chooses the instruction set of both MLPs (default: the best the CPU has).
    pub fn set_simd(&mut self, simd: nephele_nn::SimdMode) {
        self.density.set_simd(simd);
        self.color.set_simd(simd);
    }

    /// A freshly initialised field over the cubic box `[min, min + size]`, with every
    /// occupancy cell set.
    pub fn new(config: FieldConfig, min: Vec3, size: f32, seed: u64) -> Result<Self, NgpError> {
        config.validate()?;
        if !(min.is_finite() && size.is_finite() && size > 0.0) {
            return Err(NgpError::Invalid(format!("field box min {min} size {size} must be finite with size > 0")));
        }
        Ok(RadianceField {
            config,
            min,
            size,
            grid: HashGrid::new(config.grid, seed)?,
            density: Mlp::new(config.density_config(), seed.wrapping_add(1))?,
            color: Mlp::new(config.color_config(), seed.wrapping_add(2))?,
            occupancy: OccupancyGrid::filled(config.occupancy_resolution, true),
        })
    }

    pub fn config(&self) -> &FieldConfig {
        &self.config
    }

    /// The cubic box the field lives in.
    pub fn bounds(&self) -> Bounds {
        Bounds { min: self.min, max: self.min + Vec3::splat(self.size) }
    }

    pub fn occupancy(&self) -> &OccupancyGrid {
        &self.occupancy
    }

    /// Replaces the occupancy grid (its resolution must match the config).
    pub fn set_occupancy(&mut self, grid: OccupancyGrid) -> Result<(), NgpError> {
        if grid.resolution() != self.config.occupancy_resolution {
            return Err(NgpError::Invalid(format!(
                "occupancy grid of resolution {} for a field configured with {}",
                grid.resolution(),
                self.config.occupancy_resolution
            )));
        }
        self.occupancy = grid;
        Ok(())
    }

    /// Ray-marching step in world units: the box diagonal over `steps_per_diagonal`.
    pub fn step_size(&self) -> f32 {
        self.size * 3f32.sqrt() / self.config.steps_per_diagonal as f32
    }

    /// Learned parameters in all (hash grid, density MLP, colour MLP).
    pub fn num_params(&self) -> usize {
        self.grid.num_params() + self.density.num_params() + self.color.num_params()
    }

    /// Bytes the field holds in memory: parameters (f32) and occupancy bits.
    pub fn memory_bytes(&self) -> u64 {
        4 * self.num_params() as u64 + 8 * self.occupancy.words().len() as u64
    }

    /// World point to unit-cube coordinates of the field's box.
    #[inline]
    pub fn to_unit(&self, p: Vec3) -> Vec3 {
        (p - self.min) / self.size
    }

    /// Encodes `scratch.points` and runs the density network: fills `scratch.density_out`
    /// (`n x (1 + geo)`, raw).
    fn density_network(&self, scratch: &mut FieldScratch) -> Result<(), NgpError> {
        let n = scratch.points.len();
        let enc_dim = self.grid.output_dim();
        scratch.encoded.resize(n * enc_dim, 0.0);
        self.grid.encode_batch(&scratch.points, &mut scratch.encoded)?;
        scratch.density_out.resize(n * (1 + self.config.geo_features), 0.0);
        self.density.infer(&scratch.encoded, &mut scratch.density_out, &mut scratch.ws)?;
        Ok(())
    }

    /// Densities (world units, per unit length) at world points `points` into `out`. Points
    /// outside the box are evaluated at their clamped position; the occupancy grid is not
    /// consulted (this is the network itself, as the i-NOLF bake needs it).
    pub fn density_batch(&self, points: &[Vec3], out: &mut [f32], scratch: &mut FieldScratch) -> Result<(), NgpError> {
        super::check_len("density output", points.len(), out.len())?;
        scratch.points.clear();
        scratch.points.extend(points.iter().map(|&p| self.to_unit(p).to_array()));
        self.density_network(scratch)?;
        let stride = 1 + self.config.geo_features;
        for (o, row) in out.iter_mut().zip(scratch.density_out.chunks_exact(stride)) {
            *o = density_activation(row[0]);
        }
        Ok(())
    }

    /// Colours (in `[0, 1]`, the dataset's sRGB-encoded space, not premultiplied) seen at
    /// world points `points` along unit directions `dirs` (the direction of travel of the
    /// camera ray).
    pub fn color_batch(
        &self,
        points: &[Vec3],
        dirs: &[Vec3],
        out: &mut [[f32; 3]],
        scratch: &mut FieldScratch,
    ) -> Result<(), NgpError> {
        super::check_len("directions", points.len(), dirs.len())?;
        super::check_len("colour output", points.len(), out.len())?;
        scratch.points.clear();
        scratch.points.extend(points.iter().map(|&p| self.to_unit(p).to_array()));
        self.density_network(scratch)?;
        let geo = 1 + self.config.geo_features;
        let sh_len = sh_coefficient_count(self.config.sh_degree);
        let width = geo + sh_len;
        scratch.color_in.resize(points.len() * width, 0.0);
        for (i, row) in scratch.color_in.chunks_exact_mut(width).enumerate() {
            row[..geo].copy_from_slice(&scratch.density_out[i * geo..(i + 1) * geo]);
            sh_encode(dirs[i].to_array(), self.config.sh_degree, &mut row[geo..]);
        }
        scratch.color_out.resize(points.len() * 3, 0.0);
        self.color.infer(&scratch.color_in, &mut scratch.color_out, &mut scratch.ws)?;
        for (o, c) in out.iter_mut().zip(scratch.color_out.chunks_exact(3)) {
            *o = [c[0], c[1], c[2]];
        }
        Ok(())
    }

    /// View-independent ("diffuse") colour at world points: the mean of
    /// [`RadianceField::color_batch`] over the 12 directions of an icosahedron's vertices.
    pub fn diffuse_batch(
        &self,
        points: &[Vec3],
        out: &mut [[f32; 3]],
        scratch: &mut FieldScratch,
    ) -> Result<(), NgpError> {
        super::check_len("diffuse output", points.len(), out.len())?;
        let phi = (1.0 + 5f32.sqrt()) / 2.0;
        let mut dirs = Vec::with_capacity(12);
        for (a, b) in [(1.0, phi), (-1.0, phi), (1.0, -phi), (-1.0, -phi)] {
            dirs.push(Vec3::new(0.0, a, b).normalize());
            dirs.push(Vec3::new(a, b, 0.0).normalize());
            dirs.push(Vec3::new(b, 0.0, a).normalize());
        }
        out.fill([0.0; 3]);
        let mut tmp = vec![[0.0f32; 3]; points.len()];
        let mut dir_buf = vec![Vec3::ZERO; points.len()];
        for d in &dirs {
            dir_buf.fill(*d);
            self.color_batch(points, &dir_buf, &mut tmp, scratch)?;
            for (o, c) in out.iter_mut().zip(&tmp) {
                for k in 0..3 {
                    o[k] += c[k] / dirs.len() as f32;
                }
            }
        }
        Ok(())
    }

    /// Volume-renders one world ray (`dir` unit length) starting at distance `t_min`
    /// (NEPHELE eq. 4): `C = sum_i T_i (1 - exp(-sigma_i delta_i)) c_i`, `T_i = exp(-sum_{j<i}
    /// sigma_j delta_j)`, marching the occupied cells only and stopping once `T` falls below
    /// [`EARLY_STOP_TRANSMITTANCE`].
    pub fn render_ray(&self, origin: Vec3, dir: Vec3, t_min: f32, scratch: &mut FieldScratch) -> RayResult {
        self.march_ray(origin, dir, t_min, scratch, true)
    }

    /// The density network's answer alone, no colour: accumulated opacity `sum_i w_i`,
    /// expected and peak-weight distances, samples evaluated (`color` stays zero). The hit
    /// point of the "i-NOLF base" variant of NEPHELE table 5, which queries the density
    /// network along the ray instead of the baked density cubes.
    pub fn density_hit(&self, origin: Vec3, dir: Vec3, t_min: f32, scratch: &mut FieldScratch) -> RayResult {
        self.march_ray(origin, dir, t_min, scratch, false)
    }

    fn march_ray(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_min: f32,
        scratch: &mut FieldScratch,
        with_color: bool,
    ) -> RayResult {
        let mut result = RayResult::default();
        let dt = self.step_size();
        let Some(mut marcher) =
            Marcher::new(origin, dir, self.min, self.size, dt, t_min, 0.5, self.occupancy.resolution())
        else {
            return result;
        };
        let geo = 1 + self.config.geo_features;
        let sh_len = sh_coefficient_count(self.config.sh_degree);
        scratch.sh.resize(sh_len, 0.0);
        let mut sh_done = false;
        let mut transmittance = 1.0f32;
        let mut weighted_t = 0.0f32;
        let mut peak_weight = 0.0f32;
        let mut ts = [0.0f32; RENDER_CHUNK];
        let mut weights = [0.0f32; RENDER_CHUNK];
        loop {
            scratch.points.clear();
            let mut n = 0;
            while n < RENDER_CHUNK {
                match marcher.next(&self.occupancy) {
                    Some((t, p)) => {
                        ts[n] = t;
                        scratch.points.push(p.to_array());
                        n += 1;
                    }
                    None => break,
                }
            }
            if n == 0 {
                break;
            }
            result.samples += n as u32;
            if self.density_network(scratch).is_err() {
                break;
            }
            // Composite densities; colour only where the weight matters.
            let mut colored = 0;
            let mut stop = false;
            for i in 0..n {
                let sigma = density_activation(scratch.density_out[i * geo]);
                let alpha = 1.0 - (-sigma * dt).exp();
                let w = transmittance * alpha;
                weights[i] = w;
                if w > peak_weight {
                    peak_weight = w;
                    result.peak_distance = ts[i];
                }
                transmittance *= 1.0 - alpha;
                if with_color && w >= MIN_COLOR_WEIGHT {
                    colored += 1;
                }
                if transmittance < EARLY_STOP_TRANSMITTANCE {
                    // Samples past this one are never composited.
                    for w in &mut weights[i + 1..n] {
                        *w = 0.0;
                    }
                    stop = true;
                    break;
                }
            }
            if colored > 0 {
                if !sh_done {
                    sh_encode(dir.to_array(), self.config.sh_degree, &mut scratch.sh);
                    sh_done = true;
                }
                let width = geo + sh_len;
                scratch.color_in.clear();
                for i in (0..n).filter(|&i| weights[i] >= MIN_COLOR_WEIGHT) {
                    scratch.color_in.extend_from_slice(&scratch.density_out[i * geo..(i + 1) * geo]);
                    scratch.color_in.extend_from_slice(&scratch.sh);
                }
                debug_assert_eq!(scratch.color_in.len(), colored * width);
                scratch.color_out.resize(colored * 3, 0.0);
                if self.color.infer(&scratch.color_in, &mut scratch.color_out, &mut scratch.ws).is_err() {
                    break;
                }
                result.color_queries += colored as u32;
                for (k, i) in (0..n).filter(|&i| weights[i] >= MIN_COLOR_WEIGHT).enumerate() {
                    let w = weights[i];
                    for c in 0..3 {
                        result.color[c] += w * scratch.color_out[k * 3 + c];
                    }
                    result.opacity += w;
                    weighted_t += w * ts[i];
                }
            }
            // Low-weight samples (all of them without colour) still count towards opacity
            // and depth.
            for i in (0..n).filter(|&i| !with_color || weights[i] < MIN_COLOR_WEIGHT) {
                result.opacity += weights[i];
                weighted_t += weights[i] * ts[i];
            }
            if stop {
                break;
            }
        }
        result.opacity = result.opacity.clamp(0.0, 1.0);
        if result.opacity > 0.0 {
            result.distance = weighted_t / result.opacity;
        }
        if result.opacity <= 0.0 {
            result.peak_distance = 0.0;
        }
        if !(result.color.iter().all(|c| c.is_finite())
            && result.distance.is_finite()
            && result.peak_distance.is_finite())
        {
            return RayResult { samples: result.samples, color_queries: result.color_queries, ..RayResult::default() };
        }
        result
    }
}
