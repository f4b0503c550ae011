//! The specular branch's position encoding (NEPHELE section 4.2): a single-resolution
//! lattice of learned feature vectors stored through a perfect spatial hash.
//!
//! Lattice points sit at `origin + voxel * (i, j, k)`, `0 <= i, j, k < u`. Only the points
//! around the hit surfaces are stored (the PSH's occupied voxels). A hit point's encoding is
//! the trilinear interpolation of the features at the 8 lattice points of its cell, taken
//! over the corners that are stored and renormalised by their weights, so points near the
//! edge of the stored band still get a full-strength feature; a point with no stored corner
//! encodes to zeros. A query is 8 key checks and 8 contiguous feature rows from one table,
//! against `L` levels of scattered rows for a multiresolution hash grid (NEPHELE table 1).

use glam::Vec3;

use nephele_nn::simd::Prefetch;

use super::psh::{CellProbe, PshError, PshOptions, PshTable};

/// The encoding: PSH table, lattice placement and the feature table (`feature_dim` values
/// per slot, slot-major).
#[derive(Debug, Clone, PartialEq)]
pub struct PshEncoding {
    pub table: PshTable,
    pub origin: Vec3,
    pub voxel: f32,
    pub feature_dim: u32,
    pub features: Vec<f32>,
}

/// Where one point reads the table: up to 8 slots and their renormalised weights.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Corners {
    pub slots: [u32; 8],
    pub weights: [f32; 8],
    pub count: u8,
}

/// The stored corners of one lattice cell: the slot of each corner `c = dx + 2 dy + 4 dz`
/// and a bit per corner that is stored.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CellSlots {
    cell: [i64; 3],
    slots: [u32; 8],
    stored: u8,
}

/// The last cell [`PshEncoding::corners_with`] looked up. Neighbouring pixels' hit points
/// often fall in one lattice cell (a 640x480 view of a first-start object: about two pixels
/// per lattice voxel across), and a batch's hit rays come in pixel order, so the next point's
/// 8 hash look-ups (16 reads of two tables of about a MiB each) are often the last point's.
#[derive(Debug, Clone, Default)]
pub struct CellCache {
    last: Option<CellSlots>,
    /// Look-ups answered from the cache, and in all.
    pub hits: u64,
    pub queries: u64,
}

impl PshEncoding {
    /// Builds the encoding over a lattice of side `u` at `origin`/`voxel` whose stored points
    /// are the 8 corners of the cells of `points` (the hit points seen in training); features
    /// start at small deterministic values.
    pub fn from_points(
        points: &[Vec3],
        origin: Vec3,
        voxel: f32,
        u: u32,
        feature_dim: u32,
        options: &PshOptions,
    ) -> Result<PshEncoding, PshError> {
        if !(voxel.is_finite() && voxel > 0.0 && origin.is_finite()) || feature_dim == 0 || feature_dim > 64 {
            return Err(PshError::BadOption("lattice origin/voxel or feature size"));
        }
        let mut keys = Vec::with_capacity(points.len() * 8);
        for p in points {
            let f = (*p - origin) / voxel;
            if !f.is_finite() {
                continue;
            }
            let b = f.floor();
            for c in 0..8u32 {
                let v = b + Vec3::new((c & 1) as f32, ((c >> 1) & 1) as f32, (c >> 2) as f32);
                if v.cmpge(Vec3::ZERO).all() && v.cmplt(Vec3::splat(u as f32)).all() {
                    keys.push([v.x as u32, v.y as u32, v.z as u32]);
                }
            }
        }
        let (table, _) = PshTable::build(u, &keys, options)?;
        let n = table.slot_count() * feature_dim as usize;
        // Small hashed values break the symmetry between slots (as i-NGP's U(-1e-4, 1e-4)).
        let features = (0..n)
            .map(|i| ((i as u32).wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32 * 2e-4 - 1e-4)
            .collect();
        Ok(PshEncoding { table, origin, voxel, feature_dim, features })
    }

    pub fn dim(&self) -> usize {
        self.feature_dim as usize
    }

    /// The stored corners of `p`'s cell and their renormalised trilinear weights.
    #[inline]
    pub fn corners(&self, p: Vec3) -> Corners {
        self.corners_with(p, &mut CellCache::default())
    }

    /// The 8 corners' slots of the lattice cell with lowest corner `b`.
    #[inline]
    fn cell_slots(&self, b: [i64; 3]) -> CellSlots {
        let (slots, stored) = self.table.cell_slots(b);
        CellSlots { cell: b, slots, stored }
    }

    /// [`Self::corners`], reusing the slots of the cell `cache` last saw when `p` falls in
    /// it (the same result, bit for bit).
    #[inline]
    pub fn corners_with(&self, p: Vec3, cache: &mut CellCache) -> Corners {
        let f = (p - self.origin) / self.voxel;
        if !f.is_finite() {
            return Corners::default();
        }
        let b = f.floor();
        let w = f - b;
        let (bx, by, bz) = (b.x as i64, b.y as i64, b.z as i64);
        let u = i64::from(self.table.domain());
        if bx < -1 || by < -1 || bz < -1 || bx >= u || by >= u || bz >= u {
            return Corners::default();
        }
        cache.queries += 1;
        let cell = match cache.last {
            Some(last) if last.cell == [bx, by, bz] => {
                cache.hits += 1;
                last
            }
            _ => {
                let looked_up = self.cell_slots([bx, by, bz]);
                cache.last = Some(looked_up);
                looked_up
            }
        };
        weigh(&cell, w)
    }

    /// [`Self::corners_with`] of every point in turn (the same results, bit for bit, and the
    /// same cache), with the tables' reads started ahead: the cells' look-ups run as a
    /// pipeline that fetches the lines of `Φ` for the cell [`LOOKAHEAD`] x 2 ahead and of the
    /// keys and features for the cell [`LOOKAHEAD`] ahead, so the misses of many cells
    /// overlap (under `perf`, the reads waiting one after the other were a fifth of a live
    /// user's machine).
    pub fn corners_batch(&self, points: &[Vec3], cache: &mut CellCache, prefetch: Prefetch) -> Vec<Corners> {
        const NONE: u32 = u32::MAX;
        let u = i64::from(self.table.domain());
        // Each point's cell (an index into `cells`, NONE without one) and position in it.
        let mut cells: Vec<CellSlots> = Vec::new();
        let mut of_point: Vec<(u32, Vec3)> = Vec::with_capacity(points.len());
        let mut todo: Vec<usize> = Vec::new();
        let mut last = cache.last.map(|c| {
            cells.push(c);
            0u32
        });
        for &p in points {
            let f = (p - self.origin) / self.voxel;
            if !f.is_finite() {
                of_point.push((NONE, Vec3::ZERO));
                continue;
            }
            let b = f.floor();
            let w = f - b;
            let cell = [b.x as i64, b.y as i64, b.z as i64];
            if cell.iter().any(|&c| c < -1 || c >= u) {
                of_point.push((NONE, Vec3::ZERO));
                continue;
            }
            cache.queries += 1;
            let index = match last {
                Some(i) if cells[i as usize].cell == cell => {
                    cache.hits += 1;
                    i
                }
                _ => {
                    todo.push(cells.len());
                    cells.push(CellSlots { cell, slots: [0; 8], stored: 0 });
                    (cells.len() - 1) as u32
                }
            };
            last = Some(index);
            of_point.push((index, w));
        }
        let table = &self.table;
        let d = self.dim();
        let n = todo.len();
        let mut probes: Vec<CellProbe> = Vec::with_capacity(n);
        for j in 0..n + 2 * LOOKAHEAD {
            if j < n {
                for q in table.offset_indices(cells[todo[j]].cell) {
                    prefetch.element(table.offsets(), q);
                }
            }
            if let Some(k) = j.checked_sub(LOOKAHEAD).filter(|&k| k < n) {
                let probe = table.probe_cell(cells[todo[k]].cell);
                for &s in &probe.slots {
                    prefetch.element(table.keys(), s as usize);
                    prefetch.element(&self.features, s as usize * d);
                }
                probes.push(probe);
            }
            if let Some(k) = j.checked_sub(2 * LOOKAHEAD).filter(|&k| k < n) {
                let cell = &mut cells[todo[k]];
                cell.slots = probes[k].slots;
                cell.stored = table.occupied(&probes[k]);
            }
        }
        if let Some(&i) = last.as_ref() {
            cache.last = Some(cells[i as usize]);
        }
        of_point
            .iter()
            .map(|&(i, w)| if i == NONE { Corners::default() } else { weigh(&cells[i as usize], w) })
            .collect()
    }

    /// Encodes `p` into `out` (`dim()` values); returns the corners used.
    #[inline]
    pub fn encode(&self, p: Vec3, out: &mut [f32]) -> Corners {
        let corners = self.corners(p);
        self.encode_corners(&corners, out);
        corners
    }

    #[inline]
    pub fn encode_corners(&self, corners: &Corners, out: &mut [f32]) {
        let d = self.dim();
        out[..d].iter_mut().for_each(|x| *x = 0.0);
        for k in 0..corners.count as usize {
            let row = &self.features[corners.slots[k] as usize * d..][..d];
            let w = corners.weights[k];
            for (o, f) in out.iter_mut().zip(row) {
                *o += w * f;
            }
        }
    }

    /// Scatter-adds `d_out` (gradient w.r.t. the encoding) into `grad` (same layout as
    /// `features`).
    #[inline]
    pub fn backward(&self, corners: &Corners, d_out: &[f32], grad: &mut [f32]) {
        let d = self.dim();
        for k in 0..corners.count as usize {
            let row = &mut grad[corners.slots[k] as usize * d..][..d];
            let w = corners.weights[k];
            for (g, x) in row.iter_mut().zip(d_out) {
                *g += w * x;
            }
        }
    }
}

/// Cells between the stages of [`PshEncoding::corners_batch`]'s pipeline.
const LOOKAHEAD: usize = 8;

/// The stored corners of `cell` and their trilinear weights at `w` (the position in the cell,
/// each coordinate in `[0, 1)`), renormalised over the stored ones.
#[inline(always)]
fn weigh(cell: &CellSlots, w: Vec3) -> Corners {
    let mut out = Corners::default();
    let mut total = 0.0;
    for c in 0..8 {
        let (dx, dy, dz) = (c & 1, (c >> 1) & 1, c >> 2);
        if cell.stored & (1 << c) != 0 {
            let wc = (if dx == 1 { w.x } else { 1.0 - w.x })
                * (if dy == 1 { w.y } else { 1.0 - w.y })
                * (if dz == 1 { w.z } else { 1.0 - w.z });
            out.slots[out.count as usize] = cell.slots[c as usize];
            out.weights[out.count as usize] = wc;
            out.count += 1;
            total += wc;
        }
    }
    if total > 1e-12 {
        out.weights.iter_mut().for_each(|x| *x /= total);
    } else {
        out.count = 0;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stored_corners_interpolate_and_others_are_zero() {
        let pts = [Vec3::new(0.55, 0.55, 0.55)];
        let mut enc = PshEncoding::from_points(&pts, Vec3::ZERO, 0.1, 16, 2, &PshOptions::default()).expect("build");
        assert_eq!(enc.table.len(), 8);
        // Feature = lattice x coordinate in channel 0, so interpolation gives back x / voxel.
        for p in enc.table.points().collect::<Vec<_>>() {
            let s = enc.table.slot(p).expect("slot") as usize;
            enc.features[s * 2] = p[0] as f32;
            enc.features[s * 2 + 1] = 1.0;
        }
        let mut out = [0.0; 2];
        let c = enc.encode(Vec3::new(0.57, 0.52, 0.59), &mut out);
        assert_eq!(c.count, 8);
        assert!((out[0] - 5.7).abs() < 1e-4 && (out[1] - 1.0).abs() < 1e-5, "{out:?}");
        // Far away: nothing stored.
        let c = enc.encode(Vec3::new(1.2, 0.2, 0.3), &mut out);
        assert_eq!((c.count, out), (0, [0.0, 0.0]));
        // Outside the lattice and NaN.
        assert_eq!(enc.encode(Vec3::splat(-5.0), &mut out).count, 0);
        assert_eq!(enc.encode(Vec3::NAN, &mut out).count, 0);
        // A neighbouring cell sharing 4 stored corners renormalises onto them.
        let c = enc.encode(Vec3::new(0.65, 0.55, 0.55), &mut out);
        assert_eq!(c.count, 4);
        assert!((out[1] - 1.0).abs() < 1e-5);
    }

    /// A small encoding stored around a strip of points, for the look-up tests' random walks.
    fn strip_encoding() -> PshEncoding {
        let pts: Vec<Vec3> = (0..400).map(|i| Vec3::new(0.1 + 0.002 * i as f32, 0.4, 0.2 + 0.001 * i as f32)).collect();
        PshEncoding::from_points(&pts, Vec3::ZERO, 0.05, 32, 3, &PshOptions::default()).expect("build")
    }

    /// The cell cache changes nothing: along random walks (consecutive points often in one
    /// cell, sometimes in cells with no stored corner, outside the lattice or NaN) the cached
    /// corners equal fresh look-ups bit for bit, and the cache is used.
    #[test]
    fn cached_corners_are_the_looked_up_ones() {
        let enc = strip_encoding();
        let mut cache = CellCache::default();
        let mut p = Vec3::new(0.1, 0.4, 0.2);
        for i in 0..5000usize {
            let jump = crate::inolf::synthetic::spread(i);
            p += Vec3::new(0.004 * jump, 0.003 * crate::inolf::synthetic::spread(i + 7), 0.002);
            if i % 97 == 0 {
                p = Vec3::new(0.1 + 0.7 * jump.abs(), 0.4, 0.2 + 0.3 * jump.abs());
            }
            let q = match i % 500 {
                13 => Vec3::NAN,
                14 => Vec3::splat(-3.0),
                _ => p,
            };
            assert_eq!(enc.corners_with(q, &mut cache), enc.corners(q), "point {i}: {q}");
        }
        assert!(cache.hits > cache.queries / 2 && cache.queries > 4000, "{cache:?}");
    }

    /// The batched look-up is the one-by-one look-up: the same corners bit for bit, the same
    /// cache counts and the same cell left in the cache, in batches of every size (the
    /// pipeline's fill and drain included), with hints and without.
    #[test]
    fn batched_corners_are_the_one_by_one_corners() {
        let enc = strip_encoding();
        let mut walk = Vec::new();
        let mut p = Vec3::new(0.1, 0.4, 0.2);
        for i in 0..3000usize {
            p += Vec3::new(
                0.006 * crate::inolf::synthetic::spread(i),
                0.003 * crate::inolf::synthetic::spread(i + 7),
                0.002,
            );
            if i % 89 == 0 {
                p = Vec3::new(0.1 + 0.7 * crate::inolf::synthetic::spread(i).abs(), 0.4, 0.3);
            }
            walk.push(match i % 400 {
                13 => Vec3::NAN,
                14 => Vec3::splat(-3.0),
                15 => Vec3::splat(1e30),
                _ => p,
            });
        }
        for prefetch in [Prefetch::new(), Prefetch::off()] {
            let (mut one, mut batched) = (CellCache::default(), CellCache::default());
            let mut start = 0;
            for size in (0..).map(|k| [0usize, 1, 2, 7, 17, 33, 300][k % 7]) {
                if start >= walk.len() {
                    break;
                }
                let batch = &walk[start..(start + size).min(walk.len())];
                let expected: Vec<Corners> = batch.iter().map(|&q| enc.corners_with(q, &mut one)).collect();
                assert_eq!(enc.corners_batch(batch, &mut batched, prefetch), expected, "batch at {start}");
                assert_eq!((batched.hits, batched.queries), (one.hits, one.queries));
                assert_eq!(batched.last, one.last);
                start += size;
            }
            assert!(one.hits > 0 && one.hits < one.queries, "{one:?}");
        }
    }

    #[test]
    fn backward_is_the_transpose_of_encode() {
        let pts: Vec<Vec3> = (0..20).map(|i| Vec3::new(0.1 + 0.03 * i as f32, 0.4, 0.2 + 0.01 * i as f32)).collect();
        let enc = PshEncoding::from_points(&pts, Vec3::ZERO, 0.05, 32, 3, &PshOptions::default()).expect("build");
        let p = Vec3::new(0.31, 0.41, 0.27);
        let d_out = [0.3, -1.0, 2.0];
        let mut grad = vec![0.0; enc.features.len()];
        let mut out = [0.0; 3];
        let corners = enc.encode(p, &mut out);
        assert!(corners.count > 0);
        enc.backward(&corners, &d_out, &mut grad);
        // <d_out, encode(features)> is linear in features with gradient `grad`.
        let mut bumped = enc.clone();
        for (f, g) in bumped.features.iter_mut().zip(&grad) {
            *f += 0.5 * g;
        }
        let mut out2 = [0.0; 3];
        bumped.encode(p, &mut out2);
        let change: f32 = out2.iter().zip(&out).zip(&d_out).map(|((a, b), d)| (a - b) * d).sum();
        let expect: f32 = 0.5 * grad.iter().map(|g| g * g).sum::<f32>();
        assert!((change - expect).abs() < 1e-4 * expect.max(1.0), "{change} vs {expect}");
    }
}
