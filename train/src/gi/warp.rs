//! The stereo GI paper's spatial coherence (its eq. 1): the right eye's image warped onto the
//! left eye by per-pixel motion from depth and the two cameras, and the mean squared
//! difference to the left image over the pixels both eyes see.
//!
//! For each left pixel with a depth, its centre is lifted to the world point at that depth
//! and projected into the right camera; the right image is sampled there bilinearly. A tap
//! of the bilinear footprint counts only where the right eye's own depth agrees with the
//! point's depth seen from the right (within a relative tolerance): where it does not, the
//! right eye sees something else there (the point is occluded for it: a disocclusion seen
//! from the left). Pixels with no agreeing tap, whose footprint leaves the right image, or
//! without depth are masked out. The surviving taps' weights are renormalised.

use nephele_geometry::camera::Camera;

/// Relative depth difference up to which a right-eye tap is taken as the same surface.
pub const DEPTH_TOLERANCE: f32 = 0.02;

/// Where each left pixel reads the right image.
#[derive(Debug, Clone, PartialEq)]
pub struct Warp {
    pub width: u32,
    pub height: u32,
    /// Per left pixel: up to four (right pixel index, weight) taps summing to 1, or none
    /// (masked).
    pub taps: Vec<Option<Vec<(u32, f32)>>>,
}

impl Warp {
    /// The warp from the right eye onto the left: `left_depth` and `right_depth` are view-space
    /// depths (0 or non-finite where nothing was hit), one per pixel of each camera. Both
    /// cameras must have the same size.
    pub fn right_onto_left(left: &Camera, left_depth: &[f32], right: &Camera, right_depth: &[f32]) -> Warp {
        let (w, h) = (left.width(), left.height());
        let valid_depth = |d: f32| d.is_finite() && d > 0.0;
        let taps = (0..w * h)
            .map(|p| {
                let (x, y) = (p % w, p / w);
                let depth = *left_depth.get(p as usize)?;
                if !valid_depth(depth) || right.width() != w || right.height() != h {
                    return None;
                }
                let ray = left.pixel_center_ray(x, y);
                let point = ray.at(depth / left.depth_per_distance(&ray));
                let seen = right.view_depth(point);
                let at = right.project(point)?;
                // Bilinear footprint around the continuous position (pixel centres at +0.5).
                let (u, v) = (at.x - 0.5, at.y - 0.5);
                if !(u > -1.0 && v > -1.0 && u < w as f32 && v < h as f32) {
                    return None;
                }
                let (u0, v0) = (u.floor(), v.floor());
                let (fu, fv) = (u - u0, v - v0);
                let mut taps = Vec::with_capacity(4);
                for (dx, dy, weight) in
                    [(0, 0, (1.0 - fu) * (1.0 - fv)), (1, 0, fu * (1.0 - fv)), (0, 1, (1.0 - fu) * fv), (1, 1, fu * fv)]
                {
                    let (tx, ty) = (u0 as i64 + dx, v0 as i64 + dy);
                    // Weights that are rounding noise do not count (a point exactly on a
                    // pixel centre reads that pixel alone, even in the last row).
                    if weight <= 1e-4 {
                        continue;
                    }
                    if tx < 0 || ty < 0 || tx >= i64::from(w) || ty >= i64::from(h) {
                        // Part of the footprint lies outside the right image: no source.
                        return None;
                    }
                    let index = (ty as u32) * w + tx as u32;
                    let there = right_depth.get(index as usize).copied().unwrap_or(0.0);
                    if valid_depth(there) && (there - seen).abs() <= DEPTH_TOLERANCE * seen {
                        taps.push((index, weight));
                    }
                }
                let total: f32 = taps.iter().map(|t| t.1).sum();
                if total <= 1e-6 {
                    return None;
                }
                taps.iter_mut().for_each(|t| t.1 /= total);
                Some(taps)
            })
            .collect();
        Warp { width: w, height: h, taps }
    }

    /// Pixels that read the right image.
    pub fn valid(&self) -> usize {
        self.taps.iter().filter(|t| t.is_some()).count()
    }

    /// The right image (`channels` per pixel) warped onto the left: `None` where masked.
    pub fn apply(&self, right: &[f32], channels: usize) -> Vec<Option<Vec<f32>>> {
        self.taps
            .iter()
            .map(|taps| {
                taps.as_ref().map(|taps| {
                    let mut out = vec![0.0; channels];
                    for &(index, weight) in taps {
                        let src = &right[index as usize * channels..][..channels];
                        out.iter_mut().zip(src).for_each(|(o, s)| *o += weight * s);
                    }
                    out
                })
            })
            .collect()
    }

    /// The coherence error: mean over unmasked pixels and channels of
    /// `(left - warped right)^2`, and the number of unmasked pixels (0: error 0).
    pub fn coherence(&self, left: &[f32], right: &[f32], channels: usize) -> (f64, usize) {
        let warped = self.apply(right, channels);
        let (mut sum, mut count) = (0.0f64, 0usize);
        for (p, w) in warped.iter().enumerate() {
            if let Some(w) = w {
                let l = &left[p * channels..][..channels];
                sum += l.iter().zip(w).map(|(a, b)| f64::from(a - b).powi(2)).sum::<f64>();
                count += 1;
            }
        }
        if count == 0 { (0.0, 0) } else { (sum / (count * channels) as f64, count) }
    }

    /// Adds `scale` times the gradient of [`Warp::coherence`]'s error with respect to both
    /// images into `d_left` and `d_right`.
    pub fn coherence_backward(
        &self,
        left: &[f32],
        right: &[f32],
        channels: usize,
        scale: f32,
        d_left: &mut [f32],
        d_right: &mut [f32],
    ) {
        let count = self.valid();
        if count == 0 {
            return;
        }
        let k = scale * 2.0 / (count * channels) as f32;
        let warped = self.apply(right, channels);
        for (p, (taps, w)) in self.taps.iter().zip(&warped).enumerate() {
            let (Some(taps), Some(w)) = (taps, w) else { continue };
            for c in 0..channels {
                let diff = left[p * channels + c] - w[c];
                d_left[p * channels + c] += k * diff;
                for &(index, weight) in taps {
                    d_right[index as usize * channels + c] -= k * diff * weight;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Mat4, Vec3};

    /// A wall at y = 3 (facing the cameras, which look along +y) with a texture, and
    /// optionally a small box in front of it; returns (depth, colour) per pixel of `camera`.
    fn render(camera: &Camera, with_box: bool) -> (Vec<f32>, Vec<f32>) {
        let (w, h) = (camera.width(), camera.height());
        let mut depth = Vec::new();
        let mut colour = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let ray = camera.pixel_center_ray(x, y);
                let mut t = (3.0 - ray.origin.y) / ray.direction.y;
                if with_box {
                    // The box's front face: y = 2, |x| < 0.3, |z| < 0.3.
                    let tb = (2.0 - ray.origin.y) / ray.direction.y;
                    let p = ray.at(tb);
                    if p.x.abs() < 0.3 && p.z.abs() < 0.3 {
                        t = tb;
                    }
                }
                let p = ray.at(t);
                depth.push(t * camera.depth_per_distance(&ray));
                // A texture linear in world x and z: bilinear sampling reproduces it exactly.
                colour.extend([0.5 + 0.1 * p.x, 0.3 - 0.05 * p.z, if p.y < 2.5 { 1.0 } else { 0.0 }]);
            }
        }
        (depth, colour)
    }

    fn cameras(ipd: f32) -> (Camera, Camera) {
        // Looking along +y from the origin, +z up; the right eye ipd metres along +x.
        let head =
            Mat4::from_cols(Vec3::X.extend(0.0), Vec3::Z.extend(0.0), (-Vec3::Y).extend(0.0), Vec3::ZERO.extend(1.0));
        let eye = |dx: f32| Camera::from_fov_y(32, 24, 0.9, head * Mat4::from_translation(Vec3::new(dx, 0.0, 0.0)));
        (eye(-ipd / 2.0).expect("left"), eye(ipd / 2.0).expect("right"))
    }

    #[test]
    fn a_pair_with_known_motion_warps_exactly_and_the_border_is_masked() {
        let (left, right) = cameras(0.064);
        let (ld, lc) = render(&left, false);
        let (rd, rc) = render(&right, false);
        let warp = Warp::right_onto_left(&left, &ld, &right, &rd);
        let warped = warp.apply(&rc, 3);
        // Disparity in pixels: f * ipd / depth. The right camera sees the wall shifted left,
        // so the left image's leftmost columns have no source.
        let f = left.intrinsics().0;
        let disparity = f * 0.064 / 3.0;
        let masked_columns = (0..32).filter(|&x| warped[x].is_none()).count();
        assert_eq!(masked_columns as f32, disparity.ceil(), "disparity {disparity}");
        for (p, w) in warped.iter().enumerate() {
            if let Some(w) = w {
                for c in 0..3 {
                    assert!((w[c] - lc[p * 3 + c]).abs() < 1e-4, "pixel {p}: {w:?} vs {:?}", &lc[p * 3..p * 3 + 3]);
                }
            }
        }
        let (error, count) = warp.coherence(&lc, &rc, 3);
        assert!(error < 1e-8 && count == warp.valid() && count > 32 * 24 * 3 / 4, "{error} over {count}");
    }

    #[test]
    fn disocclusions_are_masked() {
        let (left, right) = cameras(0.3);
        let (ld, lc) = render(&left, true);
        let (rd, rc) = render(&right, true);
        let warp = Warp::right_onto_left(&left, &ld, &right, &rd);
        let warped = warp.apply(&rc, 3);
        // Wall pixels just beside the box that the box hides from the right eye are masked;
        // everything warped is the surface the left eye sees (flag channel, wall 0 / box 1).
        let hidden = (0..32 * 24)
            .filter(|&p| {
                lc[p * 3 + 2] == 0.0 && {
                    let ray = left.pixel_center_ray(p as u32 % 32, p as u32 / 32);
                    let point = ray.at(ld[p] / left.depth_per_distance(&ray));
                    // Behind the box from the right eye: the segment to the right eye crosses
                    // the box's front face.
                    let to_eye = right.position() - point;
                    let s = (2.0 - point.y) / to_eye.y;
                    let q = point + to_eye * s;
                    q.x.abs() < 0.3 && q.z.abs() < 0.3
                }
            })
            .collect::<Vec<_>>();
        assert!(!hidden.is_empty(), "the setup has disoccluded pixels");
        assert!(hidden.iter().all(|&p| warped[p].is_none()), "hidden wall pixels are masked");
        for (p, w) in warped.iter().enumerate() {
            if let Some(w) = w {
                assert!((w[2] - lc[p * 3 + 2]).abs() < 1e-6, "pixel {p} reads the other surface");
            }
        }
        // Pixels without depth are masked too.
        let mut holes = ld.clone();
        holes[5] = 0.0;
        holes[6] = f32::NAN;
        let warp = Warp::right_onto_left(&left, &holes, &right, &rd);
        assert!(warp.taps[5].is_none() && warp.taps[6].is_none());
    }

    #[test]
    fn the_coherence_gradient_matches_finite_differences() {
        let (left, right) = cameras(0.07);
        let (ld, _) = render(&left, true);
        let (rd, _) = render(&right, true);
        let warp = Warp::right_onto_left(&left, &ld, &right, &rd);
        let mut rng = nephele_geometry::SplitMix64::new(3);
        let l: Vec<f32> = (0..32 * 24 * 3).map(|_| rng.next_f32()).collect();
        let r: Vec<f32> = (0..32 * 24 * 3).map(|_| rng.next_f32()).collect();
        let (mut dl, mut dr) = (vec![0.0; l.len()], vec![0.0; r.len()]);
        warp.coherence_backward(&l, &r, 3, 1.0, &mut dl, &mut dr);
        let eps = 1e-2;
        for i in (0..l.len()).step_by(97) {
            for (image, grad, is_left) in [(&l, &dl, true), (&r, &dr, false)] {
                let (mut plus, mut minus) = (image.clone(), image.clone());
                plus[i] += eps;
                minus[i] -= eps;
                let e = |x: &Vec<f32>| if is_left { warp.coherence(x, &r, 3).0 } else { warp.coherence(&l, x, 3).0 };
                let numeric = (e(&plus) - e(&minus)) / (2.0 * f64::from(eps));
                assert!(
                    (numeric - f64::from(grad[i])).abs() < 1e-6 + 1e-3 * numeric.abs(),
                    "{i}: {numeric} vs {}",
                    grad[i]
                );
            }
        }
    }
}
