//! Multiresolution hash encoding (Müller et al. 2022, "Instant Neural Graphics Primitives
//! with a Multiresolution Hash Encoding", section 3).
//!
//! `L` levels of grids whose resolution grows geometrically by `per_level_scale` from
//! `base_resolution` (their eq. 2-3). Each level stores `FEATURES_PER_LEVEL` learned features
//! per grid vertex in a table of at most `2^log2_table_size` entries: coarse levels whose
//! `(resolution)^3` vertices fit are indexed densely (one-to-one), finer levels through the
//! spatial hash `(x * 1) ^ (y * 2654435761) ^ (z * 805459861) mod T` (their eq. 4). A point's
//! encoding is, per level, the trilinear interpolation of the features at the 8 vertices of
//! its cell, concatenated over levels (`L * F` values, level-major).
//!
//! Inputs are points of the unit cube; anything outside (or NaN) is clamped onto it so that
//! every finite or non-finite input gives a finite encoding.

use rayon::prelude::*;

use super::{InitRng, NnError, check_len};

/// Features per level (`F` in the paper). Fixed at 2, the paper's choice for every task, so
/// that each table entry is one 8-byte load.
pub const FEATURES_PER_LEVEL: usize = 2;

/// Shape of a hash grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HashGridConfig {
    /// Number of levels `L` (1..=32).
    pub levels: u32,
    /// `log2` of the largest table size `T` (10..=26).
    pub log2_table_size: u32,
    /// Resolution of the coarsest level `N_min` (>= 2).
    pub base_resolution: u32,
    /// Growth factor `b` between levels (`1 <= b <= 4`).
    pub per_level_scale: f32,
}

impl HashGridConfig {
    /// A config whose finest level has resolution `finest` (the paper's eq. 3:
    /// `b = exp((ln N_max - ln N_min) / (L - 1))`).
    pub fn with_finest_resolution(levels: u32, log2_table_size: u32, base_resolution: u32, finest: u32) -> Self {
        let per_level_scale = if levels > 1 {
            ((f64::from(finest.max(base_resolution)).ln() - f64::from(base_resolution.max(1)).ln())
                / f64::from(levels - 1))
            .exp() as f32
        } else {
            1.0
        };
        HashGridConfig { levels, log2_table_size, base_resolution, per_level_scale }
    }

    /// Checks the ranges documented on the fields.
    pub fn validate(&self) -> Result<(), NnError> {
        let bad = |m: String| Err(NnError::Config(m));
        if !(1..=32).contains(&self.levels) {
            return bad(format!("hash grid levels {} not in 1..=32", self.levels));
        }
        if !(10..=26).contains(&self.log2_table_size) {
            return bad(format!("hash grid log2 table size {} not in 10..=26", self.log2_table_size));
        }
        if !(2..=1 << 16).contains(&self.base_resolution) {
            return bad(format!("hash grid base resolution {} not in 2..=65536", self.base_resolution));
        }
        if !(self.per_level_scale >= 1.0 && self.per_level_scale <= 4.0) {
            return bad(format!("hash grid per-level scale {} not in [1, 4]", self.per_level_scale));
        }
        let finest = f64::from(self.base_resolution) * f64::from(self.per_level_scale).powi(self.levels as i32 - 1);
        if finest > f64::from(1u32 << 20) {
            return bad(format!("hash grid finest resolution {finest:.0} exceeds 2^20"));
        }
        Ok(())
    }

    /// Length of one point's encoding, `L * F`.
    pub fn output_dim(&self) -> usize {
        self.levels as usize * FEATURES_PER_LEVEL
    }

    /// Learned values of a grid of this shape (computed without allocating, for checking
    /// file headers); meaningful for a valid config.
    pub fn num_params(&self) -> usize {
        level_layout(self).iter().map(|l| l.size).sum::<usize>() * FEATURES_PER_LEVEL
    }
}

/// Geometry of every level of `config` (assumed valid).
fn level_layout(config: &HashGridConfig) -> Vec<Level> {
    let table = 1usize << config.log2_table_size.min(26);
    let mut levels = Vec::with_capacity(config.levels as usize);
    let mut offset = 0;
    for l in 0..config.levels {
        let scale = (f64::from(config.base_resolution) * f64::from(config.per_level_scale).powi(l as i32) - 1.0) as f32;
        // Two more vertices than the span of [0.5, scale + 0.5] so that the upper corner of
        // a point on the far face is still inside the dense grid.
        let resolution = scale.ceil() as u32 + 2;
        let dense_entries = u64::from(resolution).pow(3);
        let dense = dense_entries <= table as u64;
        // Round dense tables up to a multiple of 8 entries, as tiny-cuda-nn does.
        let size = if dense { (dense_entries as usize).div_ceil(8) * 8 } else { table };
        levels.push(Level { scale, resolution, offset, size, dense });
        offset += size;
    }
    levels
}

/// Geometry of one level (public for backends that mirror [`HashGrid::encode`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Level {
    /// `N_l - 1`: the unit cube maps to `[0.5, scale + 0.5]` in grid units (as tiny-cuda-nn).
    pub scale: f32,
    /// Vertices per axis when indexed densely.
    pub resolution: u32,
    /// First table entry of this level in the parameter vector (in entries).
    pub offset: usize,
    /// Entries in this level's table (a power of two when hashed).
    pub size: usize,
    /// Dense (one-to-one) indexing instead of hashing.
    pub dense: bool,
}

/// Corner indices and trilinear weights of one point at one level.
#[derive(Debug, Clone, Copy)]
struct Cell {
    index: [usize; 8],
    weight: [f32; 8],
}

/// A multiresolution hash grid: its configuration and its learned table.
#[derive(Debug, Clone, PartialEq)]
pub struct HashGrid {
    config: HashGridConfig,
    levels: Vec<Level>,
    params: Vec<f32>,
}

/// Clamps a coordinate onto `[0, 1]`, mapping NaN to 0.
#[inline]
fn unit(x: f32) -> f32 {
    if x >= 0.0 { x.min(1.0) } else { 0.0 }
}

impl HashGrid {
    /// A grid with features initialised uniformly in `[-1e-4, 1e-4]` (the paper's choice).
    pub fn new(config: HashGridConfig, seed: u64) -> Result<Self, NnError> {
        let mut grid = Self::zeros(config)?;
        let mut rng = InitRng::new(seed);
        for p in &mut grid.params {
            *p = rng.uniform(1e-4);
        }
        Ok(grid)
    }

    /// A grid with all features zero (for loading stored parameters).
    pub fn zeros(config: HashGridConfig) -> Result<Self, NnError> {
        config.validate()?;
        let levels = level_layout(&config);
        let offset = levels.iter().map(|l| l.size).sum::<usize>();
        Ok(HashGrid { config, levels, params: vec![0.0; offset * FEATURES_PER_LEVEL] })
    }

    pub fn config(&self) -> &HashGridConfig {
        &self.config
    }

    /// Length of one point's encoding, `L * F`.
    pub fn output_dim(&self) -> usize {
        self.config.output_dim()
    }

    /// All features, level after level, `F` values per entry.
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    /// Number of learned values.
    pub fn num_params(&self) -> usize {
        self.params.len()
    }

    /// Range of `params()` that level `level` owns (disjoint across levels).
    pub fn level_param_range(&self, level: usize) -> std::ops::Range<usize> {
        let l = &self.levels[level];
        l.offset * FEATURES_PER_LEVEL..(l.offset + l.size) * FEATURES_PER_LEVEL
    }

    /// Whether level `level` is indexed densely (no hash collisions).
    pub fn level_is_dense(&self, level: usize) -> bool {
        self.levels[level].dense
    }

    /// The 8 corner entries (relative to the level's table) and trilinear weights of `p`.
    #[inline(always)]
    fn cell(level: &Level, p: [f32; 3]) -> Cell {
        let mut base = [0u32; 3];
        let mut frac = [0f32; 3];
        for d in 0..3 {
            let x = unit(p[d]) * level.scale + 0.5;
            // `x` is finite and at least 0.5 (`unit` maps NaN to 0), so the cast is the floor:
            // one instruction, where `f32::floor` is a libm call on baseline x86-64 (3 % of a
            // `train ngp` profile).
            let f = x as u32;
            base[d] = f;
            frac[d] = x - f as f32;
        }
        let mut cell = Cell { index: [0; 8], weight: [0.0; 8] };
        for c in 0..8 {
            let mut w = 1.0;
            let mut v = [0u32; 3];
            for d in 0..3 {
                if c & (1 << d) != 0 {
                    w *= frac[d];
                    v[d] = base[d] + 1;
                } else {
                    w *= 1.0 - frac[d];
                    v[d] = base[d];
                }
            }
            let index = if level.dense {
                let r = level.resolution as usize;
                v[0] as usize + r * (v[1] as usize + r * v[2] as usize)
            } else {
                let h = v[0] ^ v[1].wrapping_mul(2_654_435_761) ^ v[2].wrapping_mul(805_459_861);
                h as usize & (level.size - 1)
            };
            cell.index[c] = index;
            cell.weight[c] = w;
        }
        cell
    }

    /// Every level's geometry.
    pub fn levels(&self) -> &[Level] {
        &self.levels
    }

    /// Encodes one point into `out` (`output_dim()` values).
    pub fn encode(&self, p: [f32; 3], out: &mut [f32]) {
        debug_assert_eq!(out.len(), self.output_dim());
        for (l, level) in self.levels.iter().enumerate() {
            let table =
                &self.params[level.offset * FEATURES_PER_LEVEL..(level.offset + level.size) * FEATURES_PER_LEVEL];
            let cell = Self::cell(level, p);
            let (mut f0, mut f1) = (0.0, 0.0);
            for c in 0..8 {
                let e = cell.index[c] * FEATURES_PER_LEVEL;
                f0 += cell.weight[c] * table[e];
                f1 += cell.weight[c] * table[e + 1];
            }
            out[l * FEATURES_PER_LEVEL] = f0;
            out[l * FEATURES_PER_LEVEL + 1] = f1;
        }
    }

    /// Encodes a batch: `out[i * output_dim() ..]` is the encoding of `points[i]`. Processes
    /// one level at a time over all points so that the level's table stays in cache.
    pub fn encode_batch(&self, points: &[[f32; 3]], out: &mut [f32]) -> Result<(), NnError> {
        let dim = self.output_dim();
        check_len("hash grid batch output", points.len() * dim, out.len())?;
        // Compiled for AVX2 where present, so that the eight corners' hashes and weights
        // vectorise (the gathers stay scalar).
        struct Op<'a>(&'a HashGrid, &'a [[f32; 3]], &'a mut [f32]);
        impl crate::simd::WithSimd for Op<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: crate::simd::Simd>(self, _simd: S) {
                self.0.encode_batch_in(self.1, self.2)
            }
        }
        crate::simd::Arch::new().dispatch(Op(self, points, out));
        Ok(())
    }

    #[inline(always)]
    fn encode_batch_in(&self, points: &[[f32; 3]], out: &mut [f32]) {
        let dim = self.output_dim();
        for (l, level) in self.levels.iter().enumerate() {
            let table =
                &self.params[level.offset * FEATURES_PER_LEVEL..(level.offset + level.size) * FEATURES_PER_LEVEL];
            for (p, row) in points.iter().zip(out.chunks_exact_mut(dim)) {
                let cell = Self::cell(level, *p);
                let (mut f0, mut f1) = (0.0, 0.0);
                for c in 0..8 {
                    let e = cell.index[c] * FEATURES_PER_LEVEL;
                    f0 += cell.weight[c] * table[e];
                    f1 += cell.weight[c] * table[e + 1];
                }
                row[l * FEATURES_PER_LEVEL] = f0;
                row[l * FEATURES_PER_LEVEL + 1] = f1;
            }
        }
    }

    /// Accumulates into `grad` (`num_params()` values) the gradient of a loss with respect to
    /// the features, given `d_out[i * output_dim() ..]`, the loss's gradient with respect to
    /// the encoding of `points[i]`. The encoding is linear in the features, so this is the
    /// transpose of [`HashGrid::encode_batch`]: a scatter-add of `weight * d_out`.
    pub fn backward_batch(&self, points: &[[f32; 3]], d_out: &[f32], grad: &mut [f32]) -> Result<(), NnError> {
        let dim = self.output_dim();
        check_len("hash grid output gradient", points.len() * dim, d_out.len())?;
        check_len("hash grid parameter gradient", self.params.len(), grad.len())?;
        for l in 0..self.levels.len() {
            let range = self.level_param_range(l);
            self.backward_level(l, points, d_out, &mut grad[range]);
        }
        Ok(())
    }

    /// [`HashGrid::backward_batch`] with one task per level on the rayon pool: levels own
    /// disjoint parameter ranges, so no thread ever writes another's gradient.
    pub fn backward_batch_parallel(&self, points: &[[f32; 3]], d_out: &[f32], grad: &mut [f32]) -> Result<(), NnError> {
        let dim = self.output_dim();
        check_len("hash grid output gradient", points.len() * dim, d_out.len())?;
        check_len("hash grid parameter gradient", self.params.len(), grad.len())?;
        let mut slices = Vec::with_capacity(self.levels.len());
        let mut rest = grad;
        for l in 0..self.levels.len() {
            let (head, tail) = rest.split_at_mut(self.levels[l].size * FEATURES_PER_LEVEL);
            slices.push((l, head));
            rest = tail;
        }
        // Finest levels first: they are the slow ones (cache misses), so start them early.
        slices.reverse();
        slices.into_par_iter().with_max_len(1).for_each(|(l, g)| self.backward_level(l, points, d_out, g));
        Ok(())
    }

    /// Scatter-add of one level into that level's gradient slice.
    fn backward_level(&self, l: usize, points: &[[f32; 3]], d_out: &[f32], grad: &mut [f32]) {
        let dim = self.output_dim();
        let level = &self.levels[l];
        for (p, d) in points.iter().zip(d_out.chunks_exact(dim)) {
            let (g0, g1) = (d[l * FEATURES_PER_LEVEL], d[l * FEATURES_PER_LEVEL + 1]);
            if g0 == 0.0 && g1 == 0.0 {
                continue;
            }
            let cell = Self::cell(level, *p);
            for c in 0..8 {
                let e = cell.index[c] * FEATURES_PER_LEVEL;
                grad[e] += cell.weight[c] * g0;
                grad[e + 1] += cell.weight[c] * g1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn small() -> HashGridConfig {
        // Levels 0-1 dense, the rest hashed into 2^10 entries.
        HashGridConfig { levels: 5, log2_table_size: 10, base_resolution: 4, per_level_scale: 2.0 }
    }

    #[test]
    fn coarse_levels_are_dense_fine_levels_hashed() {
        let grid = HashGrid::new(small(), 1).expect("grid");
        assert!(grid.level_is_dense(0) && grid.level_is_dense(1));
        assert!(!grid.level_is_dense(4));
        // Disjoint, contiguous ranges covering the parameters.
        let mut end = 0;
        for l in 0..5 {
            let r = grid.level_param_range(l);
            assert_eq!(r.start, end);
            end = r.end;
        }
        assert_eq!(end, grid.num_params());
        assert_eq!(small().num_params(), grid.num_params());
        let c = HashGridConfig::with_finest_resolution(16, 19, 16, 2048);
        assert!((c.per_level_scale - 1.3819).abs() < 1e-3, "{}", c.per_level_scale);
    }

    #[test]
    fn interpolation_is_exact_on_a_linear_field() {
        // A dense level whose features are a linear function of the vertex position must
        // reproduce that function anywhere inside the cube (trilinear interpolation).
        let config = HashGridConfig { levels: 1, log2_table_size: 12, base_resolution: 9, per_level_scale: 1.0 };
        let mut grid = HashGrid::zeros(config).expect("grid");
        let level = grid.levels[0];
        let r = level.resolution as usize;
        for z in 0..r {
            for y in 0..r {
                for x in 0..r {
                    let e = (x + r * (y + r * z)) * FEATURES_PER_LEVEL;
                    grid.params[e] = x as f32 + 2.0 * y as f32;
                    grid.params[e + 1] = z as f32;
                }
            }
        }
        let mut out = [0.0; 2];
        for p in [[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.77, 0.01, 0.5]] {
            grid.encode(p, &mut out);
            let g = |v: f32| v * level.scale + 0.5;
            assert!((out[0] - (g(p[0]) + 2.0 * g(p[1]))).abs() < 1e-4, "{p:?} {out:?}");
            assert!((out[1] - g(p[2])).abs() < 1e-4);
        }
    }

    #[test]
    fn batch_matches_single_point_encoding() {
        let grid = HashGrid::new(small(), 7).expect("grid");
        let points = [[0.1, 0.5, 0.9], [0.0, 1.0, 0.5], [0.33, 0.66, 0.99]];
        let dim = grid.output_dim();
        let mut batch = vec![0.0; points.len() * dim];
        grid.encode_batch(&points, &mut batch).expect("batch");
        for (i, p) in points.iter().enumerate() {
            let mut one = vec![0.0; dim];
            grid.encode(*p, &mut one);
            assert_eq!(&batch[i * dim..(i + 1) * dim], &one[..]);
        }
        assert!(grid.encode_batch(&points, &mut batch[1..]).is_err());
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut grid = HashGrid::new(small(), 3).expect("grid");
        let points: Vec<[f32; 3]> = (0..20)
            .map(|i| {
                let t = i as f32 / 19.0;
                [t, (t * 7.3).fract(), (t * 3.1 + 0.2).fract()]
            })
            .collect();
        let dim = grid.output_dim();
        // Loss = sum_i <r_i, enc(p_i)> with fixed random r.
        let mut rng = InitRng::new(9);
        let r: Vec<f32> = (0..points.len() * dim).map(|_| rng.uniform(1.0)).collect();
        let loss = |g: &HashGrid| {
            let mut out = vec![0.0; points.len() * dim];
            g.encode_batch(&points, &mut out).expect("encode");
            out.iter().zip(&r).map(|(a, b)| f64::from(*a) * f64::from(*b)).sum::<f64>()
        };
        let mut grad = vec![0.0; grid.num_params()];
        grid.backward_batch(&points, &r, &mut grad).expect("backward");
        let mut grad_par = vec![0.0; grid.num_params()];
        grid.backward_batch_parallel(&points, &r, &mut grad_par).expect("backward");
        assert_eq!(grad, grad_par);
        // Check every parameter with a non-zero gradient and a sample of the others.
        let mut checked = 0;
        for i in (0..grid.num_params()).filter(|&i| grad[i] != 0.0 || i % 97 == 0) {
            let old = grid.params[i];
            let h = 1e-2;
            grid.params[i] = old + h;
            let up = loss(&grid);
            grid.params[i] = old - h;
            let down = loss(&grid);
            grid.params[i] = old;
            let fd = (up - down) / (2.0 * f64::from(h));
            assert!(
                (fd - f64::from(grad[i])).abs() < 2e-3 * (1.0 + fd.abs()),
                "param {i}: fd {fd} analytic {}",
                grad[i]
            );
            checked += 1;
        }
        assert!(checked > 100, "{checked}");
    }

    proptest! {
        #[test]
        fn encoding_is_finite_for_any_input(x in prop::num::f32::ANY, y in -1e30f32..1e30, z in -2.0f32..3.0) {
            let grid = HashGrid::new(small(), 5).expect("grid");
            let mut out = vec![0.0; grid.output_dim()];
            grid.encode([x, y, z], &mut out);
            prop_assert!(out.iter().all(|v| v.is_finite()));
            // Outside points encode as their clamped image on the cube.
            let mut clamped = vec![0.0; grid.output_dim()];
            grid.encode([unit(x), unit(y), unit(z)], &mut clamped);
            prop_assert_eq!(out, clamped);
        }

        #[test]
        fn boundary_points_are_finite_and_continuous(a in 0.0f32..=1.0, face in 0usize..3, side in 0u32..2) {
            let grid = HashGrid::new(small(), 6).expect("grid");
            let mut p = [a, 1.0 - a, 0.5];
            p[face] = side as f32;
            let mut on = vec![0.0; grid.output_dim()];
            grid.encode(p, &mut on);
            let mut q = p;
            q[face] = if side == 0 { 1e-6 } else { 1.0 - 1e-6 };
            let mut near = vec![0.0; grid.output_dim()];
            grid.encode(q, &mut near);
            for (u, v) in on.iter().zip(&near) {
                prop_assert!(u.is_finite() && (u - v).abs() < 1e-5);
            }
        }
    }
}
