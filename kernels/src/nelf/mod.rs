//! NeLF (R2L, Wang et al. 2022): a neural light field that answers a ray with one query of a
//! deep residual MLP, distilled from a radiance field (`nephele distill`).
//!
//! * The ray is given to the network as `K` points sampled along it ([`RaySampling`], R2L
//!   section 3.1): the midpoints of `K` equal parts of the segment inside the object's box,
//!   each normalised to `[-1, 1]^3` in that box and positionally encoded (NeRF eq. 4, input
//!   included), concatenated in order along the ray.
//! * The network ([`nephele_nn::ResidualMlp`]) outputs [`NELF_OUTPUTS`] values through a
//!   sigmoid: the colour premultiplied by opacity in the teacher's (sRGB-encoded) space, the
//!   opacity, and where along the segment the matter is (a fraction of it: the depth the
//!   composer fuses by).
//! * Rays that cross no occupied cell of the teacher's occupancy grid ([`MatterGrid`]) are
//!   answered empty without the network: the teacher puts nothing there either.
//!
//! The `.nelf` file: magic `NEPHNELF`, a little-endian `u32` format version, the length of a
//! JSON header and the header ([`NelfHeader`]: network shape, sampling, the matter grid's
//! placement, how it was trained), the parameters as `f32`, the occupancy words as `u64`, and
//! a CRC-32 of everything before it. Loading checks every part before allocating for the
//! payload and refuses NaN or infinite parameters.

pub mod kernel;

use std::path::Path;

use glam::Vec3;
use nephele_nn::{Activation, NnError, ResidualMlp, ResidualMlpConfig, frequency_encoded_len};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::ngp::OccupancyGrid;
use crate::ngp::march::{Marcher, ray_box};

pub use kernel::{NelfKernel, NelfRay, NelfScratch};

/// First bytes of a `.nelf` file.
pub const NELF_MAGIC: [u8; 8] = *b"NEPHNELF";
/// Version of the layout after the magic.
pub const NELF_FORMAT_VERSION: u32 = 1;
/// Outputs per ray: premultiplied colour (3), opacity, depth as a fraction of the segment.
pub const NELF_OUTPUTS: usize = 5;
/// Most points along a ray.
pub const MAX_POINTS: usize = 64;
/// Most octaves of the positional encoding.
pub const MAX_FREQUENCIES: usize = 16;
/// Largest file accepted (1 GiB): a hostile header cannot make the loader reserve more.
const MAX_FILE: usize = 1 << 30;

/// How a ray becomes the network's input.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RaySampling {
    /// `K`: points along the ray.
    pub points: usize,
    /// Octaves of the positional encoding of every coordinate.
    pub frequencies: usize,
    /// The box the points are sampled in (the object's matter, world units).
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl RaySampling {
    pub fn validate(&self) -> Result<(), String> {
        if self.points == 0 || self.points > MAX_POINTS {
            return Err(format!("{} points per ray (1..={MAX_POINTS})", self.points));
        }
        if self.frequencies > MAX_FREQUENCIES {
            return Err(format!("{} frequencies (at most {MAX_FREQUENCIES})", self.frequencies));
        }
        let ok = (0..3).all(|a| self.min[a].is_finite() && self.max[a].is_finite() && self.max[a] > self.min[a]);
        if !ok {
            return Err(format!("sampling box {:?} .. {:?} is empty or not finite", self.min, self.max));
        }
        Ok(())
    }

    /// Network inputs per ray.
    pub fn input_len(&self) -> usize {
        frequency_encoded_len(3 * self.points, self.frequencies, true)
    }

    /// Where the ray `origin + t dir` (unit `dir`) is inside the box, from `t >= 0`: `None`
    /// if it misses, the box is behind it, or the segment is empty.
    pub fn segment(&self, origin: Vec3, dir: Vec3) -> Option<(f32, f32)> {
        let (t0, t1) = ray_box(origin, dir, Vec3::from(self.min), Vec3::from(self.max))?;
        let t0 = t0.max(0.0);
        (t1 > t0).then_some((t0, t1))
    }

    /// Distance of point `i` along the segment `[t0, t1]`: the midpoint of its `K`-th part.
    #[inline]
    pub fn point_distance(&self, i: usize, t0: f32, t1: f32) -> f32 {
        t0 + (i as f32 + 0.5) / self.points as f32 * (t1 - t0)
    }

    /// The `K` points of the segment, normalised to `[-1, 1]^3` in the box, into `points`
    /// (`3 K` values), then their encoding into `out` ([`RaySampling::input_len`] values).
    ///
    /// The layout of [`nephele_nn::frequency_encode`] (`x, sin(pi x), cos(pi x), sin(2 pi
    /// x), ...`), computed with one `sin_cos` per value and the double-angle identities for
    /// the higher octaves: a tenth of the cost, within `2^L` float steps of the exact values
    /// for `|x| <= 1` (checked against it in the tests).
    pub fn encode(&self, origin: Vec3, dir: Vec3, t0: f32, t1: f32, points: &mut Vec<f32>, out: &mut [f32]) {
        let (min, max) = (Vec3::from(self.min), Vec3::from(self.max));
        let scale = 2.0 / (max - min);
        points.clear();
        for i in 0..self.points {
            let p = origin + self.point_distance(i, t0, t1) * dir;
            let q = ((p - min) * scale - Vec3::ONE).clamp(Vec3::splat(-1.0), Vec3::ONE);
            points.extend_from_slice(&q.to_array());
        }
        let per = 2 * self.frequencies + 1;
        for (&x, o) in points.iter().zip(out.chunks_exact_mut(per)) {
            let x = if x.is_finite() { x } else { 0.0 };
            o[0] = x;
            let (mut s, mut c) = (std::f32::consts::PI * x).sin_cos();
            for pair in o[1..].chunks_exact_mut(2) {
                pair[0] = s;
                pair[1] = c;
                (s, c) = (2.0 * s * c, (c - s) * (c + s));
            }
        }
    }
}

/// The teacher's occupancy grid and how it lies in the world: a ray crossing none of its
/// occupied cells carries nothing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MatterPlacement {
    /// Lower corner of the grid's cubic box.
    pub min: [f32; 3],
    /// Side of the box.
    pub size: f32,
    /// The teacher's ray-marching step (world units): the grid is probed at these samples.
    pub step: f32,
    /// Cells per side.
    pub resolution: u32,
}

/// An occupancy grid placed in the world.
#[derive(Debug, Clone, PartialEq)]
pub struct MatterGrid {
    pub placement: MatterPlacement,
    pub grid: OccupancyGrid,
}

impl MatterGrid {
    pub fn new(placement: MatterPlacement, grid: OccupancyGrid) -> Result<MatterGrid, String> {
        let p = &placement;
        if !(p.min.iter().all(|v| v.is_finite()) && p.size.is_finite() && p.size > 0.0) {
            return Err(format!("occupancy box {:?} side {}", p.min, p.size));
        }
        if !(p.step.is_finite() && p.step > 0.0 && p.step <= p.size) {
            return Err(format!("occupancy step {} for a box of side {}", p.step, p.size));
        }
        if grid.resolution() != p.resolution {
            return Err(format!(
                "occupancy grid of {} cells per side, header says {}",
                grid.resolution(),
                p.resolution
            ));
        }
        Ok(MatterGrid { placement, grid })
    }

    /// Whether the ray meets an occupied cell at one of the teacher's samples (the same
    /// march as [`crate::ngp::RadianceField::render_ray`]).
    pub fn hits(&self, origin: Vec3, dir: Vec3) -> bool {
        let p = &self.placement;
        Marcher::new(origin, dir, Vec3::from(p.min), p.size, p.step, 0.0, 0.5, p.resolution)
            .is_some_and(|mut m| m.next(&self.grid).is_some())
    }

    /// [`MatterGrid::hits`] for a ray whose every occupied cell lies within `[t0, t1]` (the
    /// segment inside a box around the occupied cells, such as [`RaySampling::segment`]):
    /// the march starts and ends there, a step of margin each side for rounding, instead of
    /// crossing the grid's whole box. Same samples, same answer, less work.
    pub fn hits_within(&self, origin: Vec3, dir: Vec3, (t0, t1): (f32, f32)) -> bool {
        let p = &self.placement;
        let start = (t0 - p.step).max(0.0);
        Marcher::new(origin, dir, Vec3::from(p.min), p.size, p.step, start, 0.5, p.resolution).is_some_and(|mut m| {
            m.end_by(t1 + p.step);
            m.next(&self.grid).is_some()
        })
    }
}

/// What a `.nelf` header says.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NelfHeader {
    pub network: ResidualMlpConfig,
    pub sampling: RaySampling,
    pub matter: MatterPlacement,
    /// How it was distilled (free-form).
    #[serde(default)]
    pub training: serde_json::Value,
}

#[derive(Debug, Error)]
pub enum NelfError {
    #[error("{0}")]
    Format(String),
    #[error("network: {0}")]
    Network(#[from] NnError),
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
}

/// A distilled light field: the network, how rays are fed to it, where the matter is.
#[derive(Debug, Clone, PartialEq)]
pub struct NelfModel {
    pub header: NelfHeader,
    pub network: ResidualMlp,
    pub matter: MatterGrid,
}

/// The network shape a sampling implies, for `width` and `blocks`.
pub fn network_config(sampling: &RaySampling, width: usize, blocks: usize) -> ResidualMlpConfig {
    ResidualMlpConfig {
        input: sampling.input_len(),
        width,
        blocks,
        output: NELF_OUTPUTS,
        output_activation: Activation::Sigmoid,
    }
}

impl NelfModel {
    pub fn new(
        network: ResidualMlp,
        sampling: RaySampling,
        matter: MatterGrid,
        training: serde_json::Value,
    ) -> Result<NelfModel, NelfError> {
        sampling.validate().map_err(NelfError::Format)?;
        let config = *network.config();
        let expected = network_config(&sampling, config.width, config.blocks);
        if config != expected {
            return Err(NelfError::Format(format!(
                "a NeLF network for {} points at {} frequencies takes {} inputs and gives {NELF_OUTPUTS} sigmoid outputs; this one is {config:?}",
                sampling.points, sampling.frequencies, expected.input
            )));
        }
        let header = NelfHeader { network: config, sampling, matter: matter.placement, training };
        Ok(NelfModel { header, network, matter })
    }

    /// A freshly initialised NeLF of `width` and `blocks` (what a distillation starts from;
    /// deterministic for `seed`).
    pub fn initial(
        sampling: RaySampling,
        matter: MatterGrid,
        width: usize,
        blocks: usize,
        seed: u64,
    ) -> Result<NelfModel, NelfError> {
        sampling.validate().map_err(NelfError::Format)?;
        let network = ResidualMlp::new(network_config(&sampling, width, blocks), seed)?;
        NelfModel::new(network, sampling, matter, serde_json::Value::Null)
    }

    /// Floating-point operations per ray that reaches the network (encoding not counted).
    pub fn flops_per_ray(&self) -> usize {
        self.header.network.flops_per_row()
    }

    /// Bytes the kernel reads: parameters and occupancy bits.
    pub fn model_bytes(&self) -> usize {
        4 * self.network.params().len() + 8 * self.matter.grid.words().len()
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        let header = serde_json::to_vec(&self.header).unwrap_or_default();
        let mut out = Vec::with_capacity(16 + header.len() + self.model_bytes() + 4);
        out.extend_from_slice(&NELF_MAGIC);
        out.extend_from_slice(&NELF_FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        for p in self.network.params() {
            out.extend_from_slice(&p.to_le_bytes());
        }
        for w in self.matter.grid.words() {
            out.extend_from_slice(&w.to_le_bytes());
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<NelfModel, NelfError> {
        let bad = |why: String| NelfError::Format(why);
        if bytes.len() < 20 || bytes[..8] != NELF_MAGIC {
            return Err(bad("not a NeLF asset (no NEPHNELF header), or truncated".into()));
        }
        if bytes.len() > MAX_FILE {
            return Err(bad(format!("{} bytes: larger than any NeLF this build accepts", bytes.len())));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body).to_le_bytes() != crc {
            return Err(bad("checksum mismatch: the file is damaged or truncated".into()));
        }
        let word = |at: usize| u32::from_le_bytes([body[at], body[at + 1], body[at + 2], body[at + 3]]);
        let version = word(8);
        if version != NELF_FORMAT_VERSION {
            return Err(bad(format!("format version {version}; this build reads {NELF_FORMAT_VERSION}")));
        }
        let header_end = 16usize
            .checked_add(word(12) as usize)
            .filter(|&e| e <= body.len())
            .ok_or_else(|| bad("header length beyond the file".into()))?;
        let header: NelfHeader =
            serde_json::from_slice(&body[16..header_end]).map_err(|e| bad(format!("header: {e}")))?;
        header.network.validate()?;
        header.sampling.validate().map_err(bad)?;
        if !OccupancyGrid::valid_resolution(header.matter.resolution) {
            return Err(bad(format!("occupancy resolution {}", header.matter.resolution)));
        }
        let params = header.network.num_params();
        let words = OccupancyGrid::word_count(header.matter.resolution);
        let rest = &body[header_end..];
        if rest.len() != 4 * params + 8 * words {
            return Err(bad(format!(
                "{} payload bytes; the header implies {} parameters and {} occupancy words ({} bytes)",
                rest.len(),
                params,
                words,
                4 * params + 8 * words
            )));
        }
        let (p, w) = rest.split_at(4 * params);
        let params = p.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let words = w.chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8]))).collect();
        let grid = OccupancyGrid::from_words(header.matter.resolution, words)
            .ok_or_else(|| bad("occupancy words do not fit the resolution".into()))?;
        let matter = MatterGrid::new(header.matter, grid).map_err(bad)?;
        let network = ResidualMlp::from_params(header.network, params)?;
        NelfModel::new(network, header.sampling, matter, header.training)
    }

    /// Writes the asset (via a temporary file renamed into place).
    pub fn save(&self, path: &Path) -> Result<(), NelfError> {
        let io = |source| NelfError::Io { path: path.display().to_string(), source };
        let tmp = path.with_extension("nelf.part");
        std::fs::write(&tmp, self.to_bytes()).map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)
    }

    pub fn load(path: &Path) -> Result<NelfModel, NelfError> {
        let io = |source| NelfError::Io { path: path.display().to_string(), source };
        let len = std::fs::metadata(path).map_err(io)?.len();
        if len > MAX_FILE as u64 {
            return Err(NelfError::Format(format!("{}: {len} bytes, larger than any NeLF", path.display())));
        }
        NelfModel::from_bytes(&std::fs::read(path).map_err(io)?)
    }
}

#[cfg(test)]
mod tests;
