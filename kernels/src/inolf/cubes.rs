//! Sparse texture cubes (NEPHELE section 4.1): a coarse index grid over the object's box
//! pointing into a table of small dense cubes, stored only where the scene has matter.
//!
//! * [`SparseCubes`] is the container shared by the density cubes and the diffuse cubes:
//!   `dims` coarse cells of side `cell`, each either empty or the index of a cube of
//!   `cube_res^3` samples of `channels` bytes. Samples sit on the cell's *vertices*
//!   (`cube_res` per side, faces shared with the neighbours), so trilinear interpolation
//!   never leaves the cube and is continuous across cubes.
//! * [`DensityCubes`] holds one channel, the opacity of one sample step quantised to 8 bits
//!   (`q = 255 (1 - exp(-sigma * step))`, decoded through a 256-entry table): a quarter of
//!   f32 storage, and densities too thin to show at 8 bits vanish, which is what lets whole
//!   cubes be dropped.
//!
//! [`DensityCubes::march`] walks the coarse grid with a 3D DDA (Amanatides and Woo), so an
//! empty cell costs a few comparisons, samples occupied cells at a fixed step and returns
//! the sample of largest blending weight `w_i = T_i alpha_i` (the hit point, NEPHELE
//! section 4.1) and the accumulated weight `sum w_i = 1 - T` (the coarse opacity, eq. 4).

use std::sync::atomic::{AtomicU64, Ordering};

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use nephele_geometry::Bounds;
use nephele_geometry::camera::marchable_direction;
use nephele_nn::simd::Prefetch;

/// Index-grid entry of a cell without a cube.
pub const EMPTY_CELL: u32 = u32::MAX;
/// Largest coarse grid side.
pub const MAX_GRID_SIDE: u32 = 1024;
/// Largest number of coarse cells.
pub const MAX_CELLS: u64 = 1 << 27;
/// Largest cube side in samples.
pub const MAX_CUBE_RES: u32 = 32;
/// Largest number of bytes per sample.
pub const MAX_CHANNELS: u32 = 16;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum CubeError {
    #[error("bad cube options: {0}")]
    BadOptions(String),
    #[error("bad scene box: {0}")]
    BadBounds(String),
    #[error("inconsistent cube tables: {0}")]
    Inconsistent(String),
}

/// A coarse grid of small dense cubes of 8-bit samples.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseCubes {
    min: Vec3,
    cell: f32,
    dims: [u32; 3],
    cube_res: u32,
    channels: u32,
    /// One entry per coarse cell, `x + dims.x (y + dims.y z)`: a cube index or [`EMPTY_CELL`].
    index: Vec<u32>,
    /// Cubes one after another; inside a cube, samples `x + c (y + c z)`, channels fastest.
    data: Vec<u8>,
}

/// Sizes of a cube table against a dense grid of the same resolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CubeFootprint {
    pub cells: u64,
    pub occupied_cells: u64,
    /// Bytes of the index grid plus the cube table.
    pub bytes: u64,
    /// Bytes of a dense grid of samples at the same resolution and channel count.
    pub dense_bytes: u64,
}

impl SparseCubes {
    /// Checks and assembles stored parts.
    pub fn from_parts(
        min: Vec3,
        cell: f32,
        dims: [u32; 3],
        cube_res: u32,
        channels: u32,
        index: Vec<u32>,
        data: Vec<u8>,
    ) -> Result<SparseCubes, CubeError> {
        let bad = |s: String| Err(CubeError::Inconsistent(s));
        if !(min.is_finite() && cell.is_finite() && cell > 0.0) {
            return bad(format!("origin {min} / cell size {cell} not finite and positive"));
        }
        if dims.iter().any(|&d| d == 0 || d > MAX_GRID_SIDE) {
            return bad(format!("grid {dims:?} outside 1..={MAX_GRID_SIDE}"));
        }
        if !(2..=MAX_CUBE_RES).contains(&cube_res) || !(1..=MAX_CHANNELS).contains(&channels) {
            return bad(format!("cube side {cube_res} or {channels} channels out of range"));
        }
        let cells = dims.iter().map(|&d| d as u64).product::<u64>();
        if cells > MAX_CELLS || index.len() as u64 != cells {
            return bad(format!("{} index entries for {cells} cells", index.len()));
        }
        let cube_bytes = u64::from(cube_res).pow(3) * u64::from(channels);
        if !(data.len() as u64).is_multiple_of(cube_bytes) {
            return bad(format!("{} data bytes is not a whole number of cubes", data.len()));
        }
        let count = data.len() as u64 / cube_bytes;
        let mut used = vec![false; count as usize];
        for &e in &index {
            if e == EMPTY_CELL {
                continue;
            }
            match used.get_mut(e as usize) {
                Some(u) if !*u => *u = true,
                Some(_) => return bad(format!("cube {e} referenced twice")),
                None => return bad(format!("cube {e} out of {count}")),
            }
        }
        if used.iter().any(|&u| !u) {
            return bad("a cube is referenced by no cell".into());
        }
        if !(min + cell * Vec3::new(dims[0] as f32, dims[1] as f32, dims[2] as f32)).is_finite() {
            return bad("grid extent overflows".into());
        }
        Ok(SparseCubes { min, cell, dims, cube_res, channels, index, data })
    }

    pub fn min(&self) -> Vec3 {
        self.min
    }
    pub fn cell(&self) -> f32 {
        self.cell
    }
    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }
    pub fn cube_res(&self) -> u32 {
        self.cube_res
    }
    pub fn channels(&self) -> u32 {
        self.channels
    }
    pub fn index(&self) -> &[u32] {
        &self.index
    }
    pub fn data(&self) -> &[u8] {
        &self.data
    }
    /// Distance between samples, `cell / (cube_res - 1)`.
    pub fn sample_step(&self) -> f32 {
        self.cell / (self.cube_res - 1) as f32
    }
    pub fn max(&self) -> Vec3 {
        self.min + self.cell * Vec3::new(self.dims[0] as f32, self.dims[1] as f32, self.dims[2] as f32)
    }
    pub fn cube_count(&self) -> usize {
        self.data.len() / self.cube_len()
    }
    fn cube_len(&self) -> usize {
        (self.cube_res as usize).pow(3) * self.channels as usize
    }

    pub fn footprint(&self) -> CubeFootprint {
        let cells = self.index.len() as u64;
        let side = |d: u32| u64::from(d) * u64::from(self.cube_res - 1) + 1;
        CubeFootprint {
            cells,
            occupied_cells: self.cube_count() as u64,
            bytes: cells * 4 + self.data.len() as u64,
            dense_bytes: side(self.dims[0]) * side(self.dims[1]) * side(self.dims[2]) * u64::from(self.channels),
        }
    }

    /// Coarse cell holding `p` (points on the far faces belong to the last cell).
    #[inline]
    pub fn cell_of(&self, p: Vec3) -> Option<[u32; 3]> {
        let f = (p - self.min) / self.cell;
        let d = self.dims;
        if !(f.x >= 0.0 && f.y >= 0.0 && f.z >= 0.0) || f.x > d[0] as f32 || f.y > d[1] as f32 || f.z > d[2] as f32 {
            return None;
        }
        Some([(f.x as u32).min(d[0] - 1), (f.y as u32).min(d[1] - 1), (f.z as u32).min(d[2] - 1)])
    }

    #[inline]
    fn cell_index(&self, c: [u32; 3]) -> usize {
        c[0] as usize + self.dims[0] as usize * (c[1] as usize + self.dims[1] as usize * c[2] as usize)
    }

    /// Cube of a cell, if stored.
    #[inline]
    pub fn cube_at(&self, c: [u32; 3]) -> Option<u32> {
        let e = self.index[self.cell_index(c)];
        (e != EMPTY_CELL).then_some(e)
    }

    /// Corner sample offsets and trilinear weights of `p` inside cube `cube` of cell `c`.
    #[inline]
    fn corners(&self, cube: u32, c: [u32; 3], p: Vec3) -> ([usize; 8], [f32; 8]) {
        let res = self.cube_res as usize;
        let top = (self.cube_res - 1) as f32;
        let cell_min = self.min + self.cell * Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32);
        let f = ((p - cell_min) / self.sample_step()).clamp(Vec3::ZERO, Vec3::splat(top));
        // `f` is clamped to >= 0 (NaN clamps to 0 too), so truncation is floor: a cast, not a
        // libm `floorf` call per axis (without SSE4.1 `floor` is not one instruction, and
        // this runs for every marching sample).
        let last = res.saturating_sub(2);
        let (ix, iy, iz) = ((f.x as usize).min(last), (f.y as usize).min(last), (f.z as usize).min(last));
        let w = f - Vec3::new(ix as f32, iy as f32, iz as f32);
        let base = cube as usize * res * res * res;
        let mut offs = [0usize; 8];
        let mut ws = [0f32; 8];
        for k in 0..8 {
            let (dx, dy, dz) = (k & 1, (k >> 1) & 1, k >> 2);
            offs[k] = (base + (ix + dx) + res * ((iy + dy) + res * (iz + dz))) * self.channels as usize;
            ws[k] = (if dx == 1 { w.x } else { 1.0 - w.x })
                * (if dy == 1 { w.y } else { 1.0 - w.y })
                * (if dz == 1 { w.z } else { 1.0 - w.z });
        }
        (offs, ws)
    }

    /// Hints that [`SparseCubes::sample`] at `p` will read its corners soon (the kernel hints
    /// a few hit points ahead: the reads of the diffuse cubes missed the cache, 6-7 % of a live
    /// user's machine under `perf`, most of it waiting).
    #[inline]
    pub fn prefetch_sample(&self, p: Vec3, prefetch: Prefetch) {
        let Some(c) = self.cell_of(p) else { return };
        let Some(cube) = self.cube_at(c) else { return };
        let (offs, _) = self.corners(cube, c, p);
        // Corners dx = 0 and 1 are neighbours in memory: the start and the end of each row.
        for k in [0, 2, 4, 6] {
            prefetch.element(&self.data, offs[k]);
            prefetch.element(&self.data, offs[k + 1] + self.channels as usize - 1);
        }
    }

    /// Trilinear interpolation of the raw samples (`byte / 255`) at `p`, into `out`
    /// (`channels` values). Returns `false` (and zeros) where no cube covers `p`.
    pub fn sample(&self, p: Vec3, out: &mut [f32]) -> bool {
        out.iter_mut().for_each(|v| *v = 0.0);
        let Some(c) = self.cell_of(p) else { return false };
        let Some(cube) = self.cube_at(c) else { return false };
        let (offs, ws) = self.corners(cube, c, p);
        let channels = (self.channels as usize).min(out.len());
        for (&o, w) in offs.iter().zip(ws) {
            let bytes = &self.data[o..o + channels];
            for (v, &b) in out.iter_mut().zip(bytes) {
                *v += w * f32::from(b);
            }
        }
        // One scale at the end instead of a division per corner and channel.
        out.iter_mut().for_each(|v| *v *= 1.0 / 255.0);
        true
    }
}

/// How to build density cubes from a density function.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CubeOptions {
    /// Coarse cells along the longest side of the box (NEPHELE uses 128).
    pub resolution: u32,
    /// Samples per cube side (vertex-centred, so `cube_res - 1` sample steps per cell).
    pub cube_res: u32,
    /// Probe samples per cell side when deciding which cells hold matter.
    pub probe: u32,
    /// Cells of margin added around the cells found occupied (catches matter that the
    /// probe lattice stepped over).
    pub dilate: u32,
}

impl Default for CubeOptions {
    fn default() -> Self {
        CubeOptions { resolution: 64, cube_res: 8, probe: 4, dilate: 1 }
    }
}

/// Progress of a build, reported per batch of cells.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BuildProgress {
    pub phase: &'static str,
    pub done: u64,
    pub total: u64,
}

/// Density texture cubes.
#[derive(Debug, Clone, PartialEq)]
pub struct DensityCubes {
    cubes: SparseCubes,
    /// `sigma` of each 8-bit code.
    lut: [f32; 256],
    /// One bit per voxel (the `(cube_res - 1)^3` spaces between samples) of every cube: set
    /// where some corner sample is not zero. Derived from the samples when loading; a sample
    /// in a clear voxel has density exactly 0 and is skipped without decoding its corners.
    occupancy: VoxelOccupancy,
    /// Per coarse cell, the Chebyshev distance in cells to the nearest cell with a cube (0
    /// for those, at most 255): the march jumps over the empty box it guarantees.
    proximity: Vec<u8>,
    /// Voxels between the march's samples ([`DensityCubes::set_march_stride`]), as a float
    /// for the loop; 1 unless asked.
    stride: f32,
    /// Which sample stands for a ray's hit point ([`DensityCubes::set_hit_rule`]).
    hit_rule: HitRule,
    /// How many samples of largest weight the march keeps in [`MarchHit::blend`]
    /// ([`DensityCubes::set_blend_samples`]; 0: none).
    blend_samples: u32,
}

/// The largest [`DensityCubes::set_march_stride`].
pub const MAX_MARCH_STRIDE: u32 = 4;

/// Which sample of a ray's march stands for its hit point: where the PSH features and the
/// diffuse cubes are read (so the bake and the renderer must agree: an asset records its
/// rule, `InolfMeta::hit_rule`) and the depth the composer fuses by.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HitRule {
    /// The sample of largest blending weight (NEPHELE eq. 4): the front of an opaque
    /// surface, however soft the field made it.
    #[default]
    LargestWeight,
    /// The first sample at which the accumulated opacity reaches `opacity`, where that
    /// sample lies more than `gap` voxels behind the sample of largest weight (a second
    /// layer: the content of a glass shell behind the glass), else the sample of largest
    /// weight. Through glass the weights spread over layers far apart and the largest
    /// flips between the glass and what it holds from one ray to the next, so the features
    /// learn speckle; the deeper layer is the same point from every view.
    LayerBehind { opacity: f32, gap: f32 },
    /// Where the ray's accumulated opacity crosses one half (its median depth), solved
    /// inside the crossing sample from that sample's density (constant across the sample,
    /// as eq. 4 assumes); the sample of largest weight where the ray never reaches one half
    /// (a silhouette's fringe). The largest weight's sample centre lies up to half a sample
    /// off the surface, differently from each view, so the features at the hit point learn
    /// that jitter; the crossing is the same point from every view. The lego's held-out
    /// PSNR, same field and heads' steps: 31.12 dB with the largest weight, 31.45 with this
    /// (BENCHMARKS.md, 2026-12-07c).
    MedianDepth,
}

impl HitRule {
    /// The layered rule the bakes use for see-through objects: 0.9 of the ray's opacity, 16
    /// voxels (the built-in glass shell: 88 % of its hit rays cross such a gap, the opaque
    /// objects 2 and 9 %; held-out PSNR in BENCHMARKS.md, 2026-12-05f).
    pub const SEE_THROUGH: HitRule = HitRule::LayerBehind { opacity: 0.9, gap: 16.0 };

    /// Checks the rule's numbers: `opacity` in `[0.5, 0.99]` (reachable before the march
    /// stops at [`MIN_TRANSMITTANCE`]), `gap` in `[1, 4096]` voxels.
    pub fn validate(self) -> Result<(), CubeError> {
        match self {
            HitRule::LargestWeight | HitRule::MedianDepth => Ok(()),
            HitRule::LayerBehind { opacity, gap } => {
                if !(0.5..=0.99).contains(&opacity) || !(1.0..=4096.0).contains(&gap) {
                    return Err(CubeError::BadOptions(format!(
                        "hit rule: layer opacity {opacity} (0.5..=0.99) or gap {gap} voxels (1..=4096)"
                    )));
                }
                Ok(())
            }
        }
    }

    /// The opacity a layer is found at (above 1, never reached, for the largest weight) and
    /// the gap in voxels.
    pub fn layer(self) -> (f32, f32) {
        match self {
            HitRule::LargestWeight | HitRule::MedianDepth => (2.0, 0.0),
            HitRule::LayerBehind { opacity, gap } => (opacity, gap),
        }
    }

    /// The transmittance whose crossing is the hit point ([`HitRule::MedianDepth`]: one
    /// half); -1, never reached, for the other rules.
    pub fn median_transmittance(self) -> f32 {
        match self {
            HitRule::MedianDepth => 0.5,
            HitRule::LargestWeight | HitRule::LayerBehind { .. } => -1.0,
        }
    }
}

/// [`HitRule::MedianDepth`]: where a sample centred at `t`, `span` long, of density `sigma`,
/// entered with transmittance `entering` (above `level`), brings the transmittance down to
/// `level`: `entering exp(-sigma s) = level` at `s = ln(entering / level) / sigma` from the
/// sample's start, clamped to the sample (the march's opacity series and rounding can put the
/// exact crossing a hair outside it).
#[inline(always)]
pub fn crossing_depth(t: f32, span: f32, entering: f32, level: f32, sigma: f32) -> f32 {
    let start = t - 0.5 * span;
    (start + (entering / level).ln() / sigma).clamp(start, start + span)
}

/// Chebyshev distance (in cells, capped at 255) from every cell of `cubes`' grid to the
/// nearest cell holding a cube: a breadth-first search from those cells over the 26
/// neighbours (on the king-move graph the path length is the Chebyshev distance). A grid
/// with no cube at all is 255 everywhere.
fn proximity_of(cubes: &SparseCubes) -> Vec<u8> {
    let [nx, ny, nz] = cubes.dims.map(|d| d as usize);
    let mut distance = vec![u8::MAX; nx * ny * nz];
    let mut frontier: Vec<usize> = Vec::new();
    for (i, &e) in cubes.index.iter().enumerate() {
        if e != EMPTY_CELL {
            distance[i] = 0;
            frontier.push(i);
        }
    }
    let mut level = 0u8;
    while !frontier.is_empty() && level < u8::MAX - 1 {
        level += 1;
        let mut next = Vec::new();
        for &i in &frontier {
            let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
            for dz in z.saturating_sub(1)..=(z + 1).min(nz - 1) {
                for dy in y.saturating_sub(1)..=(y + 1).min(ny - 1) {
                    for dx in x.saturating_sub(1)..=(x + 1).min(nx - 1) {
                        let j = dx + nx * (dy + ny * dz);
                        if distance[j] > level {
                            distance[j] = level;
                            next.push(j);
                        }
                    }
                }
            }
        }
        frontier = next;
    }
    distance
}

/// Per-cube voxel occupancy bits, `words` u64 per cube.
#[derive(Debug, Clone, PartialEq)]
struct VoxelOccupancy {
    words: usize,
    bits: Vec<u64>,
}

impl VoxelOccupancy {
    fn of(cubes: &SparseCubes) -> VoxelOccupancy {
        let res = cubes.cube_res as usize;
        let v = res - 1;
        let words = (v * v * v).div_ceil(64);
        let mut bits = vec![0u64; words * cubes.cube_count()];
        for (samples, out) in cubes.data.chunks_exact(res * res * res).zip(bits.chunks_exact_mut(words)) {
            for z in 0..v {
                for y in 0..v {
                    for x in 0..v {
                        let clear = (0..8).all(|k| {
                            let (dx, dy, dz) = (k & 1, (k >> 1) & 1, k >> 2);
                            samples[(x + dx) + res * ((y + dy) + res * (z + dz))] == 0
                        });
                        if !clear {
                            let i = x + v * (y + v * z);
                            out[i / 64] |= 1 << (i % 64);
                        }
                    }
                }
            }
        }
        VoxelOccupancy { words, bits }
    }

    fn bytes(&self) -> u64 {
        8 * self.bits.len() as u64
    }
}

/// Result of marching one ray.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MarchHit {
    /// Accumulated blending weight `1 - T`, in `[0, 1]` (the coarse opacity).
    pub opacity: f32,
    /// Distance along the (unit) direction of the hit point ([`HitRule`]: the sample of
    /// largest weight, a layer behind it or the median depth); 0 if none.
    pub t: f32,
    /// The largest weight of a sample.
    pub max_weight: f32,
    /// Whether the hit rule moved `t` from the sample of largest weight to a layer behind.
    pub layered: bool,
    /// Distance of the sample of largest weight (equal to `t` unless `layered`): the depth a
    /// kernel reports, the first surface the eye meets. Reprojection between frames needs
    /// it: with the layer's depth the glass shell's reuse of previous frames mostly stopped
    /// paying (a live 640x480 user 24.4 frames/s, 26.1-26.7 with this depth; BENCHMARKS.md
    /// 2026-12-05f).
    pub front_t: f32,
    /// Sample positions visited inside stored cubes.
    pub samples: u32,
    /// Of those, the samples whose voxel holds matter: corners decoded and interpolated
    /// (the others have density exactly 0 and cost a bit test).
    pub lookups: u32,
    /// Coarse cells visited (empty or not).
    pub cells: u32,
    /// The samples of largest blending weight, `(t, weight)`, in no particular order, as many
    /// as the march keeps ([`DensityCubes::set_blend_samples`]) in the first entries
    /// (`(0, 0)` where fewer samples held matter, and after them): where heads with
    /// `HeadsShape::diffuse_blend` read the diffuse colour, blended by weight.
    pub blend: [(f32, f32); MAX_BLEND_SAMPLES],
}

/// The most samples of a march whose diffuse colours a blended hit colour mixes
/// ([`MarchHit::blend`], `HeadsShape::blend_samples`). On the lego a ray that hits has about
/// 16 samples with matter; the 4 largest weights hold 84 % of its opacity on average and 65 %
/// where its weight spreads over more than 4 voxels of depth (the edges), the 8 largest 95 %
/// and 83 %; blending 8 instead of 4 took i-NOLF from 0.35 to 0.09 dB below its field
/// (BENCHMARKS.md, 2026-12-08).
pub const MAX_BLEND_SAMPLES: usize = 8;

impl MarchHit {
    /// Keeps `(t, w)` among the `kept` samples of largest weight (replacing the first of the
    /// smallest, as the GPU twin does).
    #[inline(always)]
    fn keep_for_blend(&mut self, t: f32, w: f32, kept: usize) {
        let mut smallest = 0;
        for j in 1..kept.min(MAX_BLEND_SAMPLES) {
            if self.blend[j].1 < self.blend[smallest].1 {
                smallest = j;
            }
        }
        if w > self.blend[smallest].1 {
            self.blend[smallest] = (t, w);
        }
    }

    /// [`MarchHit::blend`] with its weights scaled to sum to one (all zero where no sample
    /// held matter): the mix of a blended diffuse colour.
    #[inline]
    pub fn normalised_blend(&self) -> [(f32, f32); MAX_BLEND_SAMPLES] {
        let total: f32 = self.blend.iter().map(|b| b.1).sum();
        // A denormal total's reciprocal would overflow.
        let scale = if total >= f32::MIN_POSITIVE { 1.0 / total } else { 0.0 };
        self.blend.map(|(t, w)| (t, w * scale))
    }
}

/// Transmittance below which marching stops.
pub const MIN_TRANSMITTANCE: f32 = 1e-3;

/// A sample's opacity from its optical depth `x = sigma * step` (>= 0): `1 - exp(-x)`.
/// Below 1/8 (the semi-transparent samples that a glass object's march is made of: 8-bit
/// codes up to about 30) the Taylor series to `x^5`, inline (error under `x^6 / 720`, 5e-9);
/// above, libm's `expf`. The call was 15 % of the glass shell's kernel time under `perf`.
#[inline(always)]
fn opacity_of_depth(x: f32) -> f32 {
    if x < 0.125 {
        x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0)))))
    } else {
        1.0 - (-x).exp()
    }
}

fn quantise(sigma: f32, step: f32) -> u8 {
    let alpha = 1.0 - (-sigma.max(0.0) * step).exp();
    if alpha.is_nan() { 0 } else { (alpha * 255.0).round().clamp(0.0, 255.0) as u8 }
}

fn decode_table(step: f32) -> [f32; 256] {
    let mut lut = [0f32; 256];
    for (q, v) in lut.iter_mut().enumerate() {
        // Code 255 stands for "opaque": alpha 1 - 0.5/255 per step.
        let alpha = if q == 255 { 1.0 - 0.5 / 255.0 } else { q as f32 / 255.0 };
        *v = -(1.0 - alpha).ln() / step;
    }
    lut
}

impl DensityCubes {
    /// Wraps a one-channel [`SparseCubes`] holding quantised opacities.
    pub fn from_cubes(cubes: SparseCubes) -> Result<DensityCubes, CubeError> {
        if cubes.channels != 1 {
            return Err(CubeError::Inconsistent(format!("density cubes have {} channels", cubes.channels)));
        }
        let lut = decode_table(cubes.sample_step());
        let occupancy = VoxelOccupancy::of(&cubes);
        let proximity = proximity_of(&cubes);
        Ok(DensityCubes {
            cubes,
            lut,
            occupancy,
            proximity,
            stride: 1.0,
            hit_rule: HitRule::LargestWeight,
            blend_samples: MAX_BLEND_SAMPLES as u32,
        })
    }

    /// Chooses which sample is a ray's hit point ([`HitRule`]; the largest weight unless asked).
    pub fn set_hit_rule(&mut self, rule: HitRule) -> Result<(), CubeError> {
        rule.validate()?;
        self.hit_rule = rule;
        Ok(())
    }

    pub fn hit_rule(&self) -> HitRule {
        self.hit_rule
    }

    /// Samples the march every `stride` voxels instead of every voxel (each sample's opacity
    /// over the longer span, `1 - exp(-sigma stride step)`): the march's speed-for-error knob
    /// (the GPU twin marches at the same stride). The glass shell, whose rays cross thick
    /// semi-transparent matter, marches about half the samples at 2 for 0.08 dB against the
    /// path tracer (`nephele bench kernel --march-stride`, BENCHMARKS.md). The bake itself
    /// always marches every voxel; the stride an asset is served with is recorded in its meta
    /// section (`InolfMeta::march_stride`).
    pub fn set_march_stride(&mut self, stride: u32) -> Result<(), CubeError> {
        if !(1..=MAX_MARCH_STRIDE).contains(&stride) {
            return Err(CubeError::BadOptions(format!("march stride {stride} is not in 1..={MAX_MARCH_STRIDE}")));
        }
        self.stride = stride as f32;
        Ok(())
    }

    /// How many samples of largest weight the march keeps in the first entries of
    /// [`MarchHit::blend`] (the rest left `(0, 0)`): 0 to [`MAX_BLEND_SAMPLES`] (a larger
    /// count keeps that many; `load_heads` refuses such assets), all of them unless set.
    /// Only heads that blend their diffuse colour (`HeadsShape::diffuse_blend`) read them,
    /// as many as they were trained with (`HeadsShape::blend_samples`), and
    /// keeping them costs a few compares per sample with matter, so a kernel serving other
    /// heads keeps none.
    pub fn set_blend_samples(&mut self, samples: u32) {
        self.blend_samples = samples.min(MAX_BLEND_SAMPLES as u32);
    }

    /// The samples the march keeps in [`MarchHit::blend`] ([`Self::set_blend_samples`]).
    pub fn blend_samples(&self) -> u32 {
        self.blend_samples
    }

    /// Voxels between the march's samples (1 unless [`Self::set_march_stride`] said otherwise).
    pub fn march_stride(&self) -> u32 {
        self.stride as u32
    }

    /// Bytes of the voxel occupancy bits derived at load time (not stored in assets).
    pub fn occupancy_bytes(&self) -> u64 {
        self.occupancy.bytes() + self.proximity.len() as u64
    }

    pub fn cubes(&self) -> &SparseCubes {
        &self.cubes
    }

    /// `sigma` of each 8-bit code (for backends that mirror [`DensityCubes::march`]).
    pub fn decode_table(&self) -> &[f32; 256] {
        &self.lut
    }

    /// The voxel occupancy bits: `words` u64 per cube, voxel `x + v (y + v z)` (`v =
    /// cube_res - 1`) at bit `i % 64` of word `i / 64`.
    pub fn voxel_bits(&self) -> (usize, &[u64]) {
        (self.occupancy.words, &self.occupancy.bits)
    }

    /// Per coarse cell (`x + dims.x (y + dims.y z)`), the Chebyshev distance in cells to the
    /// nearest cell holding a cube, at most 255: a ray in a cell at distance `n >= 2` may
    /// jump out of the box of `2n - 1` cells a side around it (for backends that mirror
    /// [`DensityCubes::march`]).
    pub fn proximity(&self) -> &[u8] {
        &self.proximity
    }

    pub fn bounds(&self) -> Bounds {
        Bounds { min: self.cubes.min, max: self.cubes.max() }
    }

    /// Builds the cubes of `bounds` from a batched density function (`sigma` per point, per
    /// unit length): probes every cell on a `probe^3` lattice, keeps the cells where some
    /// probe is visible at 8 bits (plus `dilate` cells of margin), samples their cubes and
    /// drops cubes that quantise to all zeros.
    pub fn build<F>(
        bounds: Bounds,
        options: &CubeOptions,
        density: F,
        progress: &(dyn Fn(BuildProgress) + Sync),
    ) -> Result<DensityCubes, CubeError>
    where
        F: Fn(&[Vec3], &mut [f32]) + Sync,
    {
        let o = options;
        if !(1..=MAX_GRID_SIDE).contains(&o.resolution)
            || !(2..=MAX_CUBE_RES).contains(&o.cube_res)
            || !(1..=16).contains(&o.probe)
            || o.dilate > 8
        {
            return Err(CubeError::BadOptions(format!("{o:?}")));
        }
        let size = bounds.size();
        if !(bounds.min.is_finite() && size.is_finite() && size.min_element() >= 0.0 && size.max_element() > 0.0) {
            return Err(CubeError::BadBounds(format!("{bounds:?}")));
        }
        let cell = size.max_element() / o.resolution as f32;
        let dims = [0, 1, 2].map(|a| ((size[a] / cell).ceil() as u32).clamp(1, o.resolution));
        let (nx, ny, nz) = (dims[0] as usize, dims[1] as usize, dims[2] as usize);
        let cells = nx * ny * nz;
        let step = cell / (o.cube_res - 1) as f32;
        let cell_min =
            |c: usize| bounds.min + cell * Vec3::new((c % nx) as f32, ((c / nx) % ny) as f32, (c / (nx * ny)) as f32);

        // Phase 1: which cells hold matter visible at 8 bits.
        let done = AtomicU64::new(0);
        let total = cells as u64;
        let probe = o.probe as usize;
        let occupied: Vec<bool> = (0..cells)
            .into_par_iter()
            .map_init(
                || (Vec::new(), Vec::new()),
                |(points, values): &mut (Vec<Vec3>, Vec<f32>), c| {
                    let base = cell_min(c);
                    points.clear();
                    for k in 0..=probe {
                        for j in 0..=probe {
                            for i in 0..=probe {
                                points.push(base + cell / probe as f32 * Vec3::new(i as f32, j as f32, k as f32));
                            }
                        }
                    }
                    values.resize(points.len(), 0.0);
                    density(points, values);
                    let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                    if n.is_multiple_of(4096) || n == total {
                        progress(BuildProgress { phase: "probe", done: n, total });
                    }
                    values.iter().any(|&s| quantise(s, step) > 0)
                },
            )
            .collect();
        let occupied = dilate(&occupied, dims, o.dilate);

        // Phase 2: sample the cubes of the occupied cells.
        let todo: Vec<usize> = (0..cells).filter(|&c| occupied[c]).collect();
        let res = o.cube_res as usize;
        let done = AtomicU64::new(0);
        let total = todo.len() as u64;
        let cubes: Vec<Option<Vec<u8>>> = todo
            .par_iter()
            .map_init(
                || (Vec::new(), Vec::new()),
                |(points, values): &mut (Vec<Vec3>, Vec<f32>), &c| {
                    // Global vertex coordinates, so shared faces get bit-identical positions.
                    let g = [(c % nx) * (res - 1), ((c / nx) % ny) * (res - 1), (c / (nx * ny)) * (res - 1)];
                    points.clear();
                    for k in 0..res {
                        for j in 0..res {
                            for i in 0..res {
                                let v = Vec3::new((g[0] + i) as f32, (g[1] + j) as f32, (g[2] + k) as f32);
                                points.push(bounds.min + v * step);
                            }
                        }
                    }
                    values.resize(points.len(), 0.0);
                    density(points, values);
                    let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                    if n.is_multiple_of(1024) || n == total {
                        progress(BuildProgress { phase: "cubes", done: n, total });
                    }
                    let q: Vec<u8> = values.iter().map(|&s| quantise(s, step)).collect();
                    q.iter().any(|&b| b > 0).then_some(q)
                },
            )
            .collect();
        let mut index = vec![EMPTY_CELL; cells];
        let mut data = Vec::new();
        let mut count = 0u32;
        for (&c, cube) in todo.iter().zip(cubes) {
            if let Some(q) = cube {
                index[c] = count;
                count += 1;
                data.extend_from_slice(&q);
            }
        }
        // One channel, the same decode table (`step` is the cubes' sample step).
        DensityCubes::from_cubes(SparseCubes {
            min: bounds.min,
            cell,
            dims,
            cube_res: o.cube_res,
            channels: 1,
            index,
            data,
        })
    }

    /// Interpolated density (`sigma`) at `p`; 0 outside the cubes.
    pub fn density(&self, p: Vec3) -> f32 {
        let Some(c) = self.cubes.cell_of(p) else { return 0.0 };
        let Some(cube) = self.cubes.cube_at(c) else { return 0.0 };
        let cell_min = self.cubes.min + self.cubes.cell * Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32);
        self.density_at(cube, (p - cell_min) / self.cubes.sample_step()).0
    }

    /// Density at cube-local sample coordinates `g` (`(p - cell_min) / sample_step`) of
    /// `cube`: 0 at once when the voxel is clear, else the trilinear interpolation of the
    /// decoded corners (seven lerps). Returns whether the corners were decoded.
    #[inline(always)]
    fn density_at(&self, cube: u32, g: Vec3) -> (f32, bool) {
        let res = self.cubes.cube_res as usize;
        let v = res - 1;
        let top = v as f32;
        let f = g.clamp(Vec3::ZERO, Vec3::splat(top));
        // `f` >= 0 (NaN clamps to 0), so the cast is floor; through i32, one instruction
        // (a float to usize cast is a dozen on x86-64 without AVX-512).
        let last = (res - 2) as i32;
        let (ix, iy, iz) = ((f.x as i32).min(last), (f.y as i32).min(last), (f.z as i32).min(last));
        let w = f - Vec3::new(ix as f32, iy as f32, iz as f32);
        let (ix, iy, iz) = (ix as usize, iy as usize, iz as usize);
        let voxel = ix + v * (iy + v * iz);
        let word = self.occupancy.bits[cube as usize * self.occupancy.words + voxel / 64];
        if word & (1 << (voxel % 64)) == 0 {
            return (0.0, false);
        }
        let base = cube as usize * res * res * res + ix + res * (iy + res * iz);
        let d = &self.cubes.data;
        let s = |o: usize| self.lut[d[base + o] as usize];
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let (r, rr) = (res, res * res);
        let x00 = lerp(s(0), s(1), w.x);
        let x10 = lerp(s(r), s(r + 1), w.x);
        let x01 = lerp(s(rr), s(rr + 1), w.x);
        let x11 = lerp(s(rr + r), s(rr + r + 1), w.x);
        (lerp(lerp(x00, x10, w.y), lerp(x01, x11, w.y), w.z), true)
    }

    /// Marches the ray `origin + t dir` (`dir` of unit length) over `[t_near, t_far]`
    /// through the occupied cells. Non-finite input gives an empty hit.
    ///
    /// Cost per ray: a slab test, one DDA step per coarse cell crossed, and per sample
    /// position inside a stored cube a voxel bit test; only samples in voxels with matter
    /// decode eight corners (counted in [`MarchHit::lookups`]).
    #[inline(always)]
    pub fn march(&self, origin: Vec3, dir: Vec3, t_near: f32, t_far: f32) -> MarchHit {
        let mut hit = MarchHit::default();
        // Zero, denormal-length and non-finite directions are refused; tiny components are
        // flushed to 0 (their reciprocals would be infinite).
        let Some(dir) = marchable_direction(dir) else {
            return hit;
        };
        if !(origin.is_finite() && t_near.is_finite() && !t_far.is_nan()) {
            return hit;
        }
        let cubes = &self.cubes;
        let (lo, hi) = (cubes.min, cubes.max());
        // Slab test; a zero direction component restricts nothing if the origin is inside
        // that slab and misses otherwise (no 0 * inf).
        let (mut t0, mut t1) = (t_near.max(0.0), t_far);
        for a in 0..3 {
            if dir[a] == 0.0 {
                if origin[a] < lo[a] || origin[a] > hi[a] {
                    return hit;
                }
            } else {
                let inv = 1.0 / dir[a];
                let (ta, tb) = ((lo[a] - origin[a]) * inv, (hi[a] - origin[a]) * inv);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        // Also a miss when either bound is NaN.
        if t0.partial_cmp(&t1) != Some(std::cmp::Ordering::Less) {
            return hit;
        }
        let step = cubes.sample_step();
        let inv_step = 1.0 / step;
        // Samples `span` apart along the ray: `stride` voxels (1 unless asked).
        let span = step * self.stride;
        let inv_span = 1.0 / span;
        let g_step = dir * self.stride;
        let inv_cell = 1.0 / cubes.cell;
        // Reciprocals once per ray: the loop below only multiplies (a division costs as much
        // as a dozen multiplications in latency, and the DDA's steps depend on each other).
        let inv_dir = Vec3::ONE / dir;
        let d = cubes.dims;
        // DDA set-up from the entry point.
        let entry = origin + dir * t0;
        let f = (entry - lo) * inv_cell;
        let mut c = [0i64; 3];
        let mut t_next = [f32::INFINITY; 3];
        let mut t_delta = [f32::INFINITY; 3];
        let mut stepdir = [0i64; 3];
        for a in 0..3 {
            c[a] = floor_i64(f[a]).clamp(0, i64::from(d[a]) - 1);
            if dir[a] > 0.0 {
                stepdir[a] = 1;
                t_next[a] = (lo[a] + (c[a] + 1) as f32 * cubes.cell - origin[a]) * inv_dir[a];
                t_delta[a] = cubes.cell * inv_dir[a];
            } else if dir[a] < 0.0 {
                stepdir[a] = -1;
                t_next[a] = (lo[a] + c[a] as f32 * cubes.cell - origin[a]) * inv_dir[a];
                t_delta[a] = -cubes.cell * inv_dir[a];
            }
        }
        let mut transmittance = 1.0f32;
        // The layer of `HitRule::LayerBehind`: where the accumulated opacity first reaches
        // `layer_opacity` (never, above 1, for the largest weight).
        let (layer_opacity, layer_gap) = self.hit_rule.layer();
        let mut layer_t = f32::INFINITY;
        // `HitRule::MedianDepth`: the transmittance whose crossing is the hit (-1: never)
        // and where it was crossed.
        let median_level = self.hit_rule.median_transmittance();
        let mut median_t = f32::INFINITY;
        let blend_samples = self.blend_samples as usize;
        let mut t_cur = t0;
        // Samples sit at t0 + (k + 1/2) step, whatever cell they fall in.
        let mut k = 0u64;
        let max_cells = (d[0] + d[1] + d[2]) as usize + 3;
        for _ in 0..max_cells {
            // A cell at Chebyshev distance `n >= 2` from every cube sits in an empty box of
            // `2 n - 1` cells a side: the ray leaves that box in one step, and the DDA
            // restarts there. Sample positions depend on t only, so nothing else changes.
            // Inside the grid every c is in 0..dims.
            let here = c[0] as usize + d[0] as usize * (c[1] as usize + d[1] as usize * c[2] as usize);
            let n = i64::from(self.proximity[here]);
            if n >= 2 {
                hit.cells += 1;
                let reach = n - 1;
                let (mut t_leave, mut exit_axis) = (f32::INFINITY, 0);
                for a in 0..3 {
                    if stepdir[a] != 0 {
                        let face_cell = if stepdir[a] > 0 { c[a] + reach + 1 } else { c[a] - reach };
                        let t = (lo[a] + face_cell as f32 * cubes.cell - origin[a]) * inv_dir[a];
                        if t < t_leave {
                            (t_leave, exit_axis) = (t, a);
                        }
                    }
                }
                if t_leave >= t1 {
                    break;
                }
                t_cur = t_cur.max(t_leave);
                let p = origin + dir * t_cur;
                for a in 0..3 {
                    if stepdir[a] == 0 {
                        continue;
                    }
                    c[a] = if a == exit_axis {
                        c[a] + stepdir[a] * (reach + 1)
                    } else {
                        // The ray's cell index only moves along `stepdir`: a point on a face
                        // rounds to either side, and going back could ping-pong between two
                        // empty boxes at an edge.
                        let at = floor_i64((p[a] - lo[a]) * inv_cell).clamp(0, i64::from(d[a]) - 1);
                        if stepdir[a] > 0 { c[a].max(at) } else { c[a].min(at) }
                    };
                    if a != exit_axis || (0..i64::from(d[a])).contains(&c[a]) {
                        t_next[a] =
                            (lo[a] + (c[a] + i64::from(stepdir[a] > 0)) as f32 * cubes.cell - origin[a]) * inv_dir[a];
                    }
                }
                if c[exit_axis] < 0 || c[exit_axis] >= i64::from(d[exit_axis]) {
                    break;
                }
                continue;
            }
            let axis = if t_next[0] <= t_next[1] && t_next[0] <= t_next[2] {
                0
            } else if t_next[1] <= t_next[2] {
                1
            } else {
                2
            };
            let t_exit = t_next[axis].min(t1);
            hit.cells += 1;
            let cell = [c[0] as u32, c[1] as u32, c[2] as u32];
            if let Some(cube) = cubes.cube_at(cell) {
                // First sample index at or after t_cur.
                let first = ceil_non_negative(((t_cur - t0) * inv_span - 0.5).max(0.0));
                k = k.max(first);
                let cell_min = lo + cubes.cell * Vec3::new(cell[0] as f32, cell[1] as f32, cell[2] as f32);
                // Cube-local sample coordinates of sample k; one sample step along the ray
                // moves them by `dir` times the stride exactly, so they advance by addition (recomputed at
                // every cell, so rounding cannot build up over more than a cube).
                let mut g = (origin + dir * (t0 + (k as f32 + 0.5) * span) - cell_min) * inv_step;
                loop {
                    let t = t0 + (k as f32 + 0.5) * span;
                    if t >= t_exit {
                        break;
                    }
                    k += 1;
                    let (sigma, decoded) = self.density_at(cube, g);
                    g += g_step;
                    hit.samples += 1;
                    hit.lookups += u32::from(decoded);
                    if sigma <= 0.0 {
                        continue;
                    }
                    let alpha = opacity_of_depth(sigma * span);
                    let w = transmittance * alpha;
                    if blend_samples > 0 {
                        hit.keep_for_blend(t, w, blend_samples);
                    }
                    if w > hit.max_weight {
                        hit.max_weight = w;
                        hit.t = t;
                    }
                    let entering = transmittance;
                    transmittance *= 1.0 - alpha;
                    if layer_t == f32::INFINITY && 1.0 - transmittance >= layer_opacity {
                        layer_t = t;
                    }
                    if transmittance <= median_level && entering > median_level {
                        median_t = crossing_depth(t, span, entering, median_level, sigma);
                    }
                    if transmittance < MIN_TRANSMITTANCE {
                        hit.opacity = (1.0 - transmittance).clamp(0.0, 1.0);
                        hit.take_hit_point(layer_t, layer_gap * step, median_t);
                        return hit;
                    }
                }
            }
            if t_exit >= t1 {
                break;
            }
            t_cur = t_exit;
            c[axis] += stepdir[axis];
            if c[axis] < 0 || c[axis] >= i64::from(d[axis]) {
                break;
            }
            t_next[axis] += t_delta[axis];
        }
        hit.opacity = (1.0 - transmittance).clamp(0.0, 1.0);
        hit.take_hit_point(layer_t, layer_gap * step, median_t);
        hit
    }
}

impl MarchHit {
    /// Applies the hit rule to a march's end: [`HitRule::MedianDepth`] takes `median_t` when
    /// the ray crossed it; [`HitRule::LayerBehind`] moves the hit point to the layer at
    /// `layer_t` when that lies more than `gap` (a distance) behind the sample of largest
    /// weight. `front_t` keeps the sample of largest weight either way.
    #[inline(always)]
    fn take_hit_point(&mut self, layer_t: f32, gap: f32, median_t: f32) {
        self.front_t = self.t;
        if median_t < f32::INFINITY {
            self.t = median_t;
        } else if layer_t < f32::INFINITY && layer_t - self.t > gap {
            self.t = layer_t;
            self.layered = true;
        }
    }
}

/// `floor(x)` as an integer without a libm call (baseline x86-64 has no `roundss`);
/// saturating for huge or NaN input like `as`.
#[inline(always)]
fn floor_i64(x: f32) -> i64 {
    let t = x as i64;
    t - i64::from((t as f32) > x)
}

/// `ceil(x)` for `x >= 0` (NaN gives 0) without a libm call.
#[inline(always)]
fn ceil_non_negative(x: f32) -> u64 {
    let t = x as u64;
    t + u64::from((t as f32) < x)
}

/// Marks every cell within `r` cells (Chebyshev distance) of a marked cell.
pub fn dilate(marks: &[bool], dims: [u32; 3], r: u32) -> Vec<bool> {
    let mut cur = marks.to_vec();
    let (nx, ny, nz) = (dims[0] as usize, dims[1] as usize, dims[2] as usize);
    let r = r as usize;
    if r == 0 {
        return cur;
    }
    // Separable max filter, one axis at a time.
    for (axis, n, stride) in [(0, nx, 1), (1, ny, nx), (2, nz, nx * ny)] {
        let _ = axis;
        let src = cur.clone();
        for (i, v) in cur.iter_mut().enumerate() {
            if *v {
                continue;
            }
            let pos = (i / stride) % n;
            let lo = pos.saturating_sub(r);
            let hi = (pos + r).min(n - 1);
            *v = (lo..=hi).any(|p| src[i - pos * stride + p * stride]);
        }
    }
    cur
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const CENTER: Vec3 = Vec3::new(0.1, -0.05, 0.02);
    const RADIUS: f32 = 0.5;

    fn sphere_density(points: &[Vec3], out: &mut [f32]) {
        for (p, o) in points.iter().zip(out) {
            *o = if p.distance(CENTER) < RADIUS { 400.0 } else { 0.0 };
        }
    }

    fn box_density(points: &[Vec3], out: &mut [f32]) {
        for (p, o) in points.iter().zip(out) {
            *o = if p.abs().cmplt(Vec3::splat(0.5)).all() { 400.0 } else { 0.0 };
        }
    }

    fn unit_box() -> Bounds {
        Bounds { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }
    }

    fn build(density: fn(&[Vec3], &mut [f32])) -> DensityCubes {
        let options = CubeOptions { resolution: 16, cube_res: 8, probe: 2, dilate: 1 };
        DensityCubes::build(unit_box(), &options, density, &|_| {}).expect("build")
    }

    /// A dense thin sheet (optical depth 2: opacity 0.86) across the box at x in
    /// [-0.7, -0.65] and an opaque box [0, 0.5]^3 behind it: glass in front of content.
    fn sheet_and_box_density(points: &[Vec3], out: &mut [f32]) {
        for (p, o) in points.iter().zip(out) {
            *o = if (-0.7..=-0.65).contains(&p.x) {
                40.0
            } else if p.cmpge(Vec3::ZERO).all() && p.cmple(Vec3::splat(0.5)).all() {
                400.0
            } else {
                0.0
            };
        }
    }

    fn sheet_and_box_cubes() -> &'static DensityCubes {
        static CUBES: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
        CUBES.get_or_init(|| build(sheet_and_box_density))
    }

    #[test]
    fn the_see_through_rule_takes_the_layer_behind_the_glass() {
        let largest = sheet_and_box_cubes().clone();
        let mut layered = largest.clone();
        layered.set_hit_rule(HitRule::SEE_THROUGH).expect("rule");
        // Through the sheet into the box (sheet at t 1.3-1.35, box front at t 2).
        let o = Vec3::new(-2.0, 0.25, 0.25);
        let (a, b) = (largest.march(o, Vec3::X, 0.0, f32::INFINITY), layered.march(o, Vec3::X, 0.0, f32::INFINITY));
        assert!((a.t - 1.325).abs() < 0.06 && !a.layered, "{a:?}");
        assert!((b.t - 2.0).abs() < 0.04 && b.layered, "{b:?}");
        assert_eq!((a.front_t, b.front_t), (a.t, a.t));
        assert_eq!((a.opacity, a.max_weight, a.samples), (b.opacity, b.max_weight, b.samples));
        // Through the sheet alone: the opacity never reaches 0.9, the largest weight stays.
        let o = Vec3::new(-2.0, -0.5, 0.25);
        let (a, b) = (largest.march(o, Vec3::X, 0.0, f32::INFINITY), layered.march(o, Vec3::X, 0.0, f32::INFINITY));
        assert!(a.opacity > 0.7 && a.opacity < 0.9, "{a:?}");
        assert_eq!(a, b);
        // Into the box alone: one opaque surface, no layer behind it.
        let o = Vec3::new(0.25, 0.25, 2.0);
        let (a, b) = (largest.march(o, -Vec3::Z, 0.0, f32::INFINITY), layered.march(o, -Vec3::Z, 0.0, f32::INFINITY));
        assert!(a.opacity > 0.99 && (a.t - 1.5).abs() < 0.04, "{a:?}");
        assert_eq!(a, b);
        // Numbers a march cannot honour are refused.
        for bad in [
            HitRule::LayerBehind { opacity: 0.999, gap: 16.0 },
            HitRule::LayerBehind { opacity: f32::NAN, gap: 16.0 },
            HitRule::LayerBehind { opacity: 0.9, gap: 0.5 },
            HitRule::LayerBehind { opacity: 0.9, gap: f32::INFINITY },
        ] {
            assert!(layered.clone().set_hit_rule(bad).is_err(), "{bad:?}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]

        /// On any ray, the see-through rule changes nothing but the hit point, and moves that
        /// only backwards, by more than the gap, to where the opacity reached the layer's.
        #[test]
        fn the_see_through_rule_only_moves_hits_back_past_the_gap(o in origin(), d in direction(), near in 0.0f32..0.2) {
            let largest = sheet_and_box_cubes();
            let mut layered = largest.clone();
            layered.set_hit_rule(HitRule::SEE_THROUGH).expect("rule");
            let (a, b) = (largest.march(o, d, near, f32::INFINITY), layered.march(o, d, near, f32::INFINITY));
            check_sane(&b);
            prop_assert_eq!((a.opacity, a.max_weight, a.samples, a.lookups), (b.opacity, b.max_weight, b.samples, b.lookups));
            let gap = 16.0 * largest.cubes().sample_step();
            if b.layered {
                prop_assert!(b.t > a.t + gap && b.opacity >= 0.9, "{:?} vs {:?}", a, b);
                prop_assert_eq!(b.front_t, a.t);
                let before = reference_march(largest, o, d, near, b.t - 1e-3);
                prop_assert!(before.opacity < 0.9 + 1e-3, "{:?} then {:?}", before, b);
            } else {
                prop_assert_eq!(a, b);
            }
        }
    }

    /// The ray's transmittance at distance `x` by the march's definition written plainly (as
    /// [`reference_march`]: every sample of constant density over its span, partly crossed
    /// at `x`), with the true exponential.
    fn reference_transmittance_at(cubes: &DensityCubes, o: Vec3, d: Vec3, t_near: f32, x: f32) -> f32 {
        let b = cubes.bounds();
        let (mut t0, mut t1) = (t_near.max(0.0), f32::INFINITY);
        for a in 0..3 {
            if d[a] != 0.0 {
                let (ta, tb) = ((b.min[a] - o[a]) / d[a], (b.max[a] - o[a]) / d[a]);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        let span = cubes.cubes().sample_step() * cubes.march_stride() as f32;
        let mut transmittance = 1.0f32;
        for k in 0.. {
            let t = t0 + (k as f32 + 0.5) * span;
            let start = t - 0.5 * span;
            if t >= t1 || start >= x {
                break;
            }
            let sigma = cubes.density(o + d * t);
            transmittance *= (-sigma * (x - start).min(span)).exp();
        }
        transmittance
    }

    /// Rays through the sheet (semi-transparent: the crossing falls inside the sheet), into
    /// the box and into a ball marched every third voxel: the median-depth rule changes
    /// nothing but the hit point, which lies where the plain transmittance crosses one half
    /// (within 2e-4 either side), and stays the largest weight's where the ray never gets
    /// there.
    fn check_median_depth(largest: &DensityCubes, o: Vec3, d: Vec3, near: f32) -> Result<(), TestCaseError> {
        let mut median = largest.clone();
        median.set_hit_rule(HitRule::MedianDepth).expect("rule");
        let (a, m) = (largest.march(o, d, near, f32::INFINITY), median.march(o, d, near, f32::INFINITY));
        check_sane(&m);
        prop_assert_eq!(
            (a.opacity, a.max_weight, a.samples, a.lookups),
            (m.opacity, m.max_weight, m.samples, m.lookups)
        );
        prop_assert_eq!((m.front_t, m.layered), (a.t, false));
        if m.opacity > 0.5 + 1e-3 {
            let (before, after) = (
                reference_transmittance_at(largest, o, d, near, m.t - 2e-4),
                reference_transmittance_at(largest, o, d, near, m.t + 2e-4),
            );
            prop_assert!(before >= 0.5 - 1e-3 && after <= 0.5 + 1e-3, "T {} then {}: {:?}", before, after, m);
        } else if m.opacity < 0.5 - 1e-3 {
            prop_assert_eq!(a, m);
        }
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(700))]

        #[test]
        fn the_median_depth_is_where_the_transmittance_crosses_one_half(
            o in origin(),
            d in direction(),
            near in 0.0f32..0.2,
        ) {
            check_median_depth(sheet_and_box_cubes(), o, d, near)?;
            check_median_depth(strided_sphere_cubes(), o, d, near)?;
        }
    }

    /// The point of the median depth: rays from every side onto one point of a flat face
    /// find it at one depth below the face, where the largest weight's sample centre lands
    /// anywhere within a sample of it (each ray's samples start where it enters the box).
    #[test]
    fn the_median_depth_is_the_same_point_from_every_view() {
        let mut median = box_cubes().clone();
        median.set_hit_rule(HitRule::MedianDepth).expect("rule");
        let step = median.cubes().sample_step();
        let target = Vec3::new(0.1, 0.07, 0.5);
        let (mut spread_largest, mut spread_median) = ((f32::MAX, f32::MIN), (f32::MAX, f32::MIN));
        for i in 0..60 {
            // Elevation 15 to 90 degrees above the face, any azimuth, any distance.
            let elevation = (15.0 + 75.0 * (i as f32 * 0.618_034).fract()).to_radians();
            let azimuth = i as f32 * 2.399_963;
            let from = Vec3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
            let o = target + from * (1.5 + 0.37 * (i as f32 * 0.414_213_5).fract());
            let d = (target - o).normalize();
            let (a, m) = (box_cubes().march(o, d, 0.0, f32::INFINITY), median.march(o, d, 0.0, f32::INFINITY));
            assert!(a.opacity > 0.99 && m.opacity > 0.99, "{a:?} {m:?}");
            for (spread, t) in [(&mut spread_largest, a.t), (&mut spread_median, m.t)] {
                let z = (o + d * t).z;
                *spread = (spread.0.min(z), spread.1.max(z));
            }
        }
        let (largest, median) = (spread_largest.1 - spread_largest.0, spread_median.1 - spread_median.0);
        eprintln!("depth spread below the face: largest weight {} samples, median {}", largest / step, median / step);
        assert!(
            median < 0.5 * step && median < 0.6 * largest,
            "largest weight {largest}, median {median}, step {step}"
        );
    }

    fn sphere_cubes() -> &'static DensityCubes {
        static CUBES: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
        CUBES.get_or_init(|| build(sphere_density))
    }

    /// [`sphere_cubes`] marched every third voxel.
    fn strided_sphere_cubes() -> &'static DensityCubes {
        static CUBES: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
        CUBES.get_or_init(|| {
            let mut cubes = build(sphere_density);
            cubes.set_march_stride(3).expect("a valid stride");
            cubes
        })
    }

    /// Two small balls in opposite corners of a 32^3 grid: most cells between them are far
    /// from any cube, so rays cross them in a few jumps.
    fn sparse_cubes() -> &'static DensityCubes {
        static CUBES: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
        CUBES.get_or_init(|| {
            let balls = |points: &[Vec3], out: &mut [f32]| {
                for (p, o) in points.iter().zip(out) {
                    let near = p.distance(Vec3::splat(-0.6)) < 0.25 || p.distance(Vec3::new(0.6, 0.55, 0.5)) < 0.2;
                    *o = if near { 300.0 } else { 0.0 };
                }
            };
            let options = CubeOptions { resolution: 32, cube_res: 5, probe: 2, dilate: 1 };
            DensityCubes::build(unit_box(), &options, balls, &|_| {}).expect("build")
        })
    }

    fn box_cubes() -> &'static DensityCubes {
        static CUBES: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
        CUBES.get_or_init(|| build(box_density))
    }

    /// Entry distance of a ray into the analytic sphere (0 if starting inside), the length
    /// of its path inside, and the ray's closest approach to the centre.
    /// The inline series and libm meet at the threshold; both stay within 1e-7 of the exact
    /// `1 - exp(-x)`, from denormals through the 8-bit codes' range to infinity.
    #[test]
    fn a_march_stride_samples_the_same_matter_less_often() {
        let mut strided = build(sphere_density);
        assert!(strided.set_march_stride(0).is_err());
        assert!(strided.set_march_stride(MAX_MARCH_STRIDE + 1).is_err());
        assert_eq!(strided.march_stride(), 1);
        strided.set_march_stride(2).expect("stride 2");
        assert_eq!(strided.march_stride(), 2);
        let step = strided.cubes().sample_step();
        let o = CENTER - Vec3::new(2.0, 0.013, -0.021);
        let every = sphere_cubes().march(o, Vec3::X, 0.0, f32::INFINITY);
        let half = strided.march(o, Vec3::X, 0.0, f32::INFINITY);
        assert!(every.opacity > 0.99 && half.opacity > 0.99, "{every:?} {half:?}");
        assert!(half.samples < every.samples, "{every:?} {half:?}");
        // The solid sphere's surface, found within the longer span.
        assert!((half.t - every.t).abs() <= 2.0 * step, "{every:?} {half:?}");
    }

    #[test]
    fn opacity_of_depth_is_one_minus_exp_minus_x() {
        let mut xs: Vec<f32> = vec![0.0, 1e-40, 1e-20, 1e-7, 0.124_999_99, 0.125, 0.125_000_01, 50.0, f32::INFINITY];
        xs.extend((0..4000).map(|i| i as f32 * 1e-4));
        xs.extend((0..256).map(|q| -(1.0 - f64::from(q.min(254)) / 255.0).ln() as f32));
        for x in xs {
            let exact = 1.0 - (-f64::from(x)).exp();
            let got = opacity_of_depth(x);
            assert!((f64::from(got) - exact).abs() < 1e-7, "x {x}: {got} against {exact}");
            assert!((0.0..=1.0).contains(&got), "x {x}: {got}");
        }
    }

    /// Issue 18: a denormal-length direction used to march until a counter overflowed; a
    /// denormal component is exactly a zero one.
    #[test]
    fn degenerate_directions_are_refused_and_tiny_components_are_zero() {
        let cubes = sphere_cubes();
        for dir in [Vec3::new(1e-40, -1e-41, 1e-42), Vec3::ZERO, Vec3::splat(f32::NAN), Vec3::splat(0.1)] {
            assert_eq!(cubes.march(CENTER, dir, 0.0, f32::INFINITY), MarchHit::default(), "{dir}");
        }
        let o = Vec3::new(-2.0, CENTER.y, CENTER.z);
        let exact = cubes.march(o, Vec3::X, 0.0, f32::INFINITY);
        assert!(exact.opacity > 0.9);
        assert_eq!(cubes.march(o, Vec3::new(1.0, 1e-40, -1e-44), 0.0, f32::INFINITY), exact);
    }

    fn sphere_hit(o: Vec3, d: Vec3) -> (Option<(f32, f32)>, f32) {
        let oc = o - CENTER;
        let b = oc.dot(d);
        let closest = (oc - d * b).length();
        let disc = b * b - (oc.length_squared() - RADIUS * RADIUS);
        if disc < 0.0 {
            return (None, closest);
        }
        let (enter, exit) = (-b - disc.sqrt(), -b + disc.sqrt());
        if exit <= 0.0 {
            return (None, closest);
        }
        (Some((enter.max(0.0), exit - enter.max(0.0))), closest)
    }

    fn check_sane(h: &MarchHit) {
        assert!(h.opacity.is_finite() && (0.0..=1.0).contains(&h.opacity), "{h:?}");
        assert!(h.t.is_finite() && h.t >= 0.0, "{h:?}");
        assert!(h.max_weight.is_finite() && h.max_weight <= h.opacity + 1e-6, "{h:?}");
        if h.opacity > 0.0 {
            assert!(h.t > 0.0, "{h:?}");
        }
    }

    #[test]
    fn only_matter_is_stored() {
        let cubes = sphere_cubes();
        let fp = cubes.cubes().footprint();
        assert_eq!(fp.cells, 16 * 16 * 16);
        // The sphere (radius 4 cells) touches about (4/3) pi 5^3 ~ 520 cells.
        assert!(fp.occupied_cells > 200 && fp.occupied_cells < 800, "{fp:?}");
        assert!(fp.bytes < fp.dense_bytes, "{fp:?}");
        assert!(cubes.density(CENTER) > 100.0);
        assert_eq!(cubes.density(Vec3::new(0.9, 0.9, 0.9)), 0.0);
        // Corner cells are empty.
        assert_eq!(cubes.cubes().cube_at([0, 0, 0]), None);
    }

    #[test]
    fn proximity_is_the_chebyshev_distance_to_the_nearest_cube() {
        let cubes = sparse_cubes();
        let grid = cubes.cubes();
        let [nx, ny, nz] = grid.dims().map(|d| d as i64);
        let stored: Vec<[i64; 3]> = (0..nx * ny * nz)
            .filter(|&i| grid.index()[i as usize] != EMPTY_CELL)
            .map(|i| [i % nx, (i / nx) % ny, i / (nx * ny)])
            .collect();
        assert!(!stored.is_empty());
        for i in 0..nx * ny * nz {
            let c = [i % nx, (i / nx) % ny, i / (nx * ny)];
            let nearest = stored.iter().map(|s| (0..3).map(|a| (s[a] - c[a]).abs()).max().unwrap_or(0)).min();
            assert_eq!(i64::from(cubes.proximity[i as usize]), nearest.unwrap_or(255).min(255), "cell {c:?}");
        }
    }

    #[test]
    fn empty_space_is_crossed_in_few_steps() {
        let cubes = sparse_cubes();
        // Along the diagonal between the balls: fewer DDA steps than cells crossed.
        let d = Vec3::ONE.normalize();
        let h = cubes.march(Vec3::splat(-0.3), d, 0.0, f32::INFINITY);
        check_sane(&h);
        assert!(h.opacity > 0.9, "{h:?}");
        let cells_crossed = (0.9f32 * 3f32.sqrt() / cubes.cubes().cell()) as u32;
        assert!(h.cells < cells_crossed * 3 / 4, "{h:?}: {cells_crossed} cells on the way");
        // A ray through empty space only costs a few steps and no samples.
        let h = cubes.march(Vec3::new(-2.0, 0.9, -0.9), Vec3::X, 0.0, f32::INFINITY);
        assert_eq!((h.opacity, h.samples), (0.0, 0));
        assert!(h.cells <= 8 + 2, "{h:?}");
    }

    #[test]
    fn axis_rays_hit_the_sphere_where_expected() {
        let cubes = sphere_cubes();
        for a in 0..3 {
            for sign in [-1.0f32, 1.0] {
                let mut d = Vec3::ZERO;
                d[a] = sign;
                let o = CENTER - d * 3.0;
                let h = cubes.march(o, d, 0.0, f32::INFINITY);
                check_sane(&h);
                assert!(h.opacity > 0.99, "{h:?}");
                assert!((h.t - (3.0 - RADIUS)).abs() < cubes.cubes().sample_step() * 1.5, "{h:?}");
                // Marching skipped most samples: only cells with matter are sampled.
                assert!(h.samples < 40, "{h:?}");
            }
        }
    }

    #[test]
    fn missing_rays_cost_nothing_and_see_nothing() {
        let cubes = sphere_cubes();
        // Misses the box entirely.
        let h = cubes.march(Vec3::new(5.0, 5.0, 5.0), Vec3::X, 0.0, f32::INFINITY);
        assert_eq!((h.opacity, h.samples, h.cells), (0.0, 0, 0));
        // Crosses the box through empty cells only.
        let h = cubes.march(Vec3::new(-3.0, 0.9, 0.9), Vec3::X, 0.0, f32::INFINITY);
        assert_eq!((h.opacity, h.samples), (0.0, 0));
        assert!(h.cells > 0);
        // Degenerate input.
        assert_eq!(cubes.march(Vec3::NAN, Vec3::X, 0.0, 1.0), MarchHit::default());
        assert_eq!(cubes.march(Vec3::ZERO, Vec3::ZERO, 0.0, 1.0), MarchHit::default());
    }

    #[test]
    fn camera_inside_the_object_sees_it_at_once() {
        let cubes = sphere_cubes();
        let h = cubes.march(CENTER, Vec3::new(0.3, -0.5, 0.8).normalize(), 0.01, f32::INFINITY);
        check_sane(&h);
        assert!(h.opacity > 0.99 && h.t < 0.05, "{h:?}");
    }

    #[test]
    fn bad_options_are_errors() {
        let bad = CubeOptions { cube_res: 1, ..CubeOptions::default() };
        assert!(DensityCubes::build(unit_box(), &bad, sphere_density, &|_| {}).is_err());
        let flat = Bounds { min: Vec3::ZERO, max: Vec3::ZERO };
        assert!(DensityCubes::build(flat, &CubeOptions::default(), sphere_density, &|_| {}).is_err());
        let nan = Bounds { min: Vec3::NAN, max: Vec3::ONE };
        assert!(DensityCubes::build(nan, &CubeOptions::default(), sphere_density, &|_| {}).is_err());
    }

    #[test]
    fn from_parts_round_trips_and_rejects_garbage() {
        let c = sphere_cubes().cubes();
        let again = SparseCubes::from_parts(
            c.min(),
            c.cell(),
            c.dims(),
            c.cube_res(),
            1,
            c.index().to_vec(),
            c.data().to_vec(),
        );
        assert_eq!(again.as_ref(), Ok(c));
        let mut index = c.index().to_vec();
        let first = index.iter().position(|&e| e != EMPTY_CELL).expect("a cube");
        index[first] = c.cube_count() as u32;
        assert!(
            SparseCubes::from_parts(c.min(), c.cell(), c.dims(), c.cube_res(), 1, index, c.data().to_vec()).is_err()
        );
        let mut data = c.data().to_vec();
        data.pop();
        assert!(
            SparseCubes::from_parts(c.min(), c.cell(), c.dims(), c.cube_res(), 1, c.index().to_vec(), data).is_err()
        );
    }

    /// A ray origin: anywhere (often inside the box or the sphere), or on a cell boundary
    /// (grazing faces, edges and corners).
    fn origin() -> impl Strategy<Value = Vec3> {
        prop_oneof![
            (-3.0f32..3.0, -3.0f32..3.0, -3.0f32..3.0).prop_map(|(x, y, z)| Vec3::new(x, y, z)),
            (-8i32..=8, -8i32..=8, -8i32..=8).prop_map(|(x, y, z)| Vec3::new(x as f32, y as f32, z as f32) / 8.0),
            (-8i32..=8, -8i32..=8, -3.0f32..3.0).prop_map(|(x, y, z)| Vec3::new(x as f32 / 8.0, y as f32 / 8.0, z)),
        ]
    }

    /// A unit direction, often with zero components (axis-parallel rays).
    fn direction() -> impl Strategy<Value = Vec3> {
        ((-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0), 0u8..8, any::<bool>()).prop_filter_map(
            "zero",
            |((x, y, z), mask, keep)| {
                let mut d = Vec3::new(x, y, z);
                if !keep {
                    for a in 0..3 {
                        if mask & (1 << a) != 0 {
                            d[a] = 0.0;
                        }
                    }
                }
                (d.length() > 1e-3).then(|| d.normalize())
            },
        )
    }

    /// The march's definition, written plainly: density at every sample position
    /// `t0 + (k + 1/2) step` from the box entry to the exit, no cells, no skipping.
    fn reference_march(cubes: &DensityCubes, o: Vec3, d: Vec3, t_near: f32, t_far: f32) -> MarchHit {
        let mut hit = MarchHit::default();
        let b = cubes.bounds();
        let (mut t0, mut t1) = (t_near.max(0.0), t_far);
        for a in 0..3 {
            if d[a] == 0.0 {
                if o[a] < b.min[a] || o[a] > b.max[a] {
                    return hit;
                }
            } else {
                let (ta, tb) = ((b.min[a] - o[a]) / d[a], (b.max[a] - o[a]) / d[a]);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        if !(t0 < t1) {
            return hit;
        }
        let step = cubes.cubes().sample_step() * cubes.march_stride() as f32;
        let mut transmittance = 1.0f32;
        let mut k = 0u32;
        loop {
            let t = t0 + (k as f32 + 0.5) * step;
            if t >= t1 {
                break;
            }
            k += 1;
            let sigma = cubes.density(o + d * t);
            if sigma <= 0.0 {
                continue;
            }
            let alpha = 1.0 - (-sigma * step).exp();
            let w = transmittance * alpha;
            if w > hit.max_weight {
                hit.max_weight = w;
                hit.t = t;
            }
            // The largest weights, sorted afresh (the fast march keeps them on the way).
            let mut all: Vec<(f32, f32)> = hit.blend.iter().copied().chain([(t, w)]).collect();
            all.sort_by(|a, b| b.1.total_cmp(&a.1));
            let kept = cubes.blend_samples() as usize;
            hit.blend[..kept].copy_from_slice(&all[..kept]);
            transmittance *= 1.0 - alpha;
            if transmittance < MIN_TRANSMITTANCE {
                break;
            }
        }
        hit.opacity = (1.0 - transmittance).clamp(0.0, 1.0);
        hit
    }

    /// The blending weight the plain march gives the sample at distance `t`.
    fn reference_weight_at(cubes: &DensityCubes, o: Vec3, d: Vec3, near: f32, t: f32) -> f32 {
        let before = reference_march(cubes, o, d, near, t - 1e-4);
        let through = reference_march(cubes, o, d, near, t + 1e-4);
        (1.0 - before.opacity) - (1.0 - through.opacity)
    }

    /// The fast march and the plain one agree: the same coarse opacity to 1e-4 plus 1e-3 of
    /// it and the same hit distance, unless two samples' weights tie to within rounding (then
    /// within the ray's extent through the box, and with equal maximum weights). The relative
    /// part is for rays lying in a plane between two cubes (`o.x = 0`, `d.x = 0`): each cube
    /// quantises its own corners, so density is not continuous across that plane, and the
    /// two marches may read a sample from either side (found at opacity 0.2472 against
    /// 0.2471 over 25 samples).
    fn check_against_reference(cubes: &DensityCubes, o: Vec3, d: Vec3, near: f32) -> Result<(), TestCaseError> {
        let fast = cubes.march(o, d, near, f32::INFINITY);
        let slow = reference_march(cubes, o, d, near, f32::INFINITY);
        let close = |a: f32, b: f32| (a - b).abs() < 1e-4 + 1e-3 * a.abs().max(b.abs());
        prop_assert!(close(fast.opacity, slow.opacity), "{:?} vs {:?}", fast, slow);
        prop_assert!(close(fast.max_weight, slow.max_weight), "{:?} vs {:?}", fast, slow);
        if (fast.t - slow.t).abs() > 1e-4 {
            // Another sample won: only where the two largest weights tie to rounding.
            prop_assert!(close(fast.max_weight, slow.max_weight), "{:?} vs {:?}", fast, slow);
            prop_assert!(close(reference_weight_at(cubes, o, d, near, fast.t), slow.max_weight));
        }
        prop_assert!(fast.lookups <= fast.samples);
        // The blend keeps the largest weights (their distances may differ where weights tie).
        let sorted = |h: &MarchHit| {
            let mut w: Vec<f32> = h.blend.iter().map(|b| b.1).collect();
            w.sort_by(|a, b| b.total_cmp(a));
            w
        };
        for (a, b) in sorted(&fast).iter().zip(sorted(&slow)) {
            prop_assert!(close(*a, b), "blend {:?} vs {:?}", fast.blend, slow.blend);
        }
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        #[test]
        fn march_agrees_with_its_plain_definition(o in origin(), d in direction(), near in 0.0f32..0.2) {
            check_against_reference(sphere_cubes(), o, d, near)?;
            check_against_reference(box_cubes(), o, d, near)?;
            check_against_reference(sparse_cubes(), o, d, near)?;
            check_against_reference(strided_sphere_cubes(), o, d, near)?;
        }

        /// Without the blend the march is the same but for it.
        #[test]
        fn a_march_without_the_blend_differs_only_by_it(o in origin(), d in direction(), near in 0.0f32..0.2) {
            static UNBLENDED: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
            static FOUR: std::sync::OnceLock<DensityCubes> = std::sync::OnceLock::new();
            let with = |slot: &'static std::sync::OnceLock<DensityCubes>, samples: u32| {
                slot.get_or_init(|| {
                    let mut c = sphere_cubes().clone();
                    c.set_blend_samples(samples);
                    c
                })
            };
            let (unblended, four) = (with(&UNBLENDED, 0), with(&FOUR, 4));
            prop_assert_eq!(sphere_cubes().blend_samples() as usize, MAX_BLEND_SAMPLES);
            let full = sphere_cubes().march(o, d, near, f32::INFINITY);
            let plain = unblended.march(o, d, near, f32::INFINITY);
            prop_assert_eq!(plain, MarchHit { blend: [(0.0, 0.0); MAX_BLEND_SAMPLES], ..full });
            // Four kept: the same march but for the blend, whose four weights the reference
            // check holds to the four largest and whose other entries stay empty.
            let fewer = four.march(o, d, near, f32::INFINITY);
            prop_assert_eq!(MarchHit { blend: full.blend, ..fewer }, full);
            prop_assert!(fewer.blend[4..].iter().all(|b| *b == (0.0, 0.0)));
            check_against_reference(four, o, d, near)?;
        }

        #[test]
        fn sphere_rays_are_sane_and_hit_where_the_sphere_is(o in origin(), d in direction(), near in 0.0f32..0.2) {
            let cubes = sphere_cubes();
            let h = cubes.march(o, d, near, f32::INFINITY);
            check_sane(&h);
            let cell = cubes.cubes().cell();
            let step = cubes.cubes().sample_step();
            let start = o + d * near;
            let (analytic, closest) = sphere_hit(start, d);
            if closest > RADIUS + 2.0 * step {
                prop_assert_eq!(h.opacity, 0.0);
            }
            if let Some((t, inside)) = analytic && inside > 2.0 * cell {
                prop_assert!(h.opacity > 0.9, "{:?} analytic {}", h, t);
                // Within one cube cell of the analytic hit.
                prop_assert!((h.t - near - t).abs() <= cell, "{:?} analytic {}", h, t + near);
            }
        }

        #[test]
        fn box_rays_are_sane_and_hit_where_the_box_is(o in origin(), d in direction()) {
            let cubes = box_cubes();
            let h = cubes.march(o, d, 0.0, f32::INFINITY);
            check_sane(&h);
            // Analytic slab test against the box [-0.5, 0.5]^3.
            let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
            let mut inside_slabs = true;
            for a in 0..3 {
                if d[a] == 0.0 {
                    inside_slabs &= o[a].abs() < 0.5 - 0.2;
                } else {
                    let (ta, tb) = ((-0.5 - o[a]) / d[a], (0.5 - o[a]) / d[a]);
                    t0 = t0.max(ta.min(tb));
                    t1 = t1.min(ta.max(tb));
                }
            }
            let cell = cubes.cubes().cell();
            // Rays that graze a face (a cell into the box they are still within half a cell
            // of it) see the interpolated edge of the cubes, not the box: not checked here
            // (the march still equals its definition there, see the agreement test).
            let deep = (o + d * (t0 + cell)).abs().max_element() < 0.5 - 0.5 * cell;
            if inside_slabs && deep && t1 - t0 > 2.0 * cell {
                prop_assert!(h.opacity > 0.9, "{:?} analytic {}", h, t0);
                prop_assert!((h.t - t0).abs() <= cell, "{:?} analytic {}", h, t0);
            }
        }

        #[test]
        fn bounded_interval_is_respected(o in origin(), d in direction(), far in 0.0f32..4.0) {
            let h = sphere_cubes().march(o, d, 0.0, far);
            check_sane(&h);
            if h.opacity > 0.0 {
                prop_assert!(h.t <= far);
            }
        }
    }
}
