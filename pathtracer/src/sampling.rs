//! Random numbers and the sampling routines of the path tracer.
//!
//! Every pixel sample draws from its own generator seeded by (render seed, pixel, sample), so
//! an image is identical whatever the thread count or scheduling.

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// PCG32 (O'Neill 2014, XSH-RR output): small, fast, and good enough for Monte Carlo.
#[derive(Debug, Clone)]
pub struct Rng {
    state: u64,
    increment: u64,
}

const PCG_MULTIPLIER: u64 = 6364136223846793005;

impl Rng {
    /// A generator for stream `stream` of `seed`; distinct streams are independent.
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut rng = Rng { state: 0, increment: (splitmix64(stream) << 1) | 1 };
        rng.next_u32();
        rng.state = rng.state.wrapping_add(splitmix64(seed));
        rng.next_u32();
        rng
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(PCG_MULTIPLIER).wrapping_add(self.increment);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in `[0, 1)`: the top 24 bits, so the value is exactly representable.
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    pub fn next_vec2(&mut self) -> Vec2 {
        Vec2::new(self.next_f32(), self.next_f32())
    }
}

/// SplitMix64 finaliser: spreads nearby integers (pixel indices) over the whole 64-bit range.
pub fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E3779B97F4A7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D049BB133111EB);
    x ^ (x >> 31)
}

/// An orthonormal basis with `normal` as its z axis (Duff et al. 2017, branchless).
#[derive(Debug, Clone, Copy)]
pub struct Frame {
    pub tangent: Vec3,
    pub bitangent: Vec3,
    pub normal: Vec3,
}

impl Frame {
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let tangent = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let bitangent = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { tangent, bitangent, normal: n }
    }

    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.tangent), v.dot(self.bitangent), v.dot(self.normal))
    }

    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.tangent * v.x + self.bitangent * v.y + self.normal * v.z
    }
}

/// Cosine-weighted direction on the +z hemisphere; pdf = cos(theta) / pi.
pub fn cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = concentric_disk(u);
    let z = (1.0 - d.length_squared()).max(0.0).sqrt();
    Vec3::new(d.x, d.y, z)
}

/// Shirley-Chiu concentric mapping of the unit square onto the unit disc.
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let o = 2.0 * u - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, (PI / 4.0) * (o.y / o.x))
    } else {
        (o.y, PI / 2.0 - (PI / 4.0) * (o.x / o.y))
    };
    r * Vec2::new(theta.cos(), theta.sin())
}

/// Uniform direction on the unit sphere; pdf = 1 / (4 pi).
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

pub const UNIFORM_SPHERE_PDF: f32 = 1.0 / (4.0 * PI);

/// Uniform direction inside a cone of half-angle `cos_max` around +z.
pub fn uniform_cone(u: Vec2, cos_max: f32) -> Vec3 {
    let cos_theta = 1.0 - u.x * (1.0 - cos_max);
    let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(sin_theta * phi.cos(), sin_theta * phi.sin(), cos_theta)
}

/// Uniform barycentric coordinates `(b1, b2)` on a triangle (Heitz 2019, low distortion).
pub fn uniform_triangle(u: Vec2) -> Vec2 {
    if u.y > u.x {
        let b0 = u.x / 2.0;
        let b1 = u.y - b0;
        Vec2::new(b1, 1.0 - b0 - b1)
    } else {
        let b1 = u.y / 2.0;
        let b0 = u.x - b1;
        Vec2::new(b1, 1.0 - b0 - b1)
    }
}

/// Veach's power heuristic (beta = 2) for two strategies.
pub fn power_heuristic(pdf_a: f32, pdf_b: f32) -> f32 {
    let a = pdf_a * pdf_a;
    let b = pdf_b * pdf_b;
    if a + b == 0.0 || !(a + b).is_finite() {
        // A delta or infinite pdf wins outright.
        return if pdf_a >= pdf_b { 1.0 } else { 0.0 };
    }
    a / (a + b)
}

/// Picks an index from a discrete distribution given by its cumulative sums.
#[derive(Debug, Clone, Default)]
pub struct Distribution1D {
    cdf: Vec<f32>,
    total: f32,
}

impl Distribution1D {
    /// `None` when no weight is positive.
    pub fn new(weights: &[f32]) -> Option<Self> {
        let mut cdf = Vec::with_capacity(weights.len());
        let mut total = 0.0f64;
        for &w in weights {
            total += f64::from(w.max(0.0));
            cdf.push(total as f32);
        }
        if !(total > 0.0) {
            return None;
        }
        Some(Distribution1D { cdf, total: total as f32 })
    }

    /// Returns `(index, probability of that index)`.
    pub fn sample(&self, u: f32) -> (usize, f32) {
        let target = u * self.total;
        let index = self.cdf.partition_point(|&c| c <= target).min(self.cdf.len() - 1);
        (index, self.probability(index))
    }

    pub fn probability(&self, index: usize) -> f32 {
        let hi = self.cdf[index];
        let lo = if index == 0 { 0.0 } else { self.cdf[index - 1] };
        (hi - lo) / self.total
    }

    pub fn len(&self) -> usize {
        self.cdf.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cdf.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rng_is_deterministic_and_uniform() {
        let mut a = Rng::new(7, 3);
        let mut b = Rng::new(7, 3);
        let mut c = Rng::new(7, 4);
        let xs: Vec<f32> = (0..10_000).map(|_| a.next_f32()).collect();
        let ys: Vec<f32> = (0..10_000).map(|_| b.next_f32()).collect();
        assert_eq!(xs, ys);
        assert_ne!(xs[..8], (0..8).map(|_| c.next_f32()).collect::<Vec<_>>()[..]);
        let mean = xs.iter().sum::<f32>() / xs.len() as f32;
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        assert!(xs.iter().all(|&x| (0.0..1.0).contains(&x)));
    }

    #[test]
    fn frame_is_orthonormal_for_awkward_normals() {
        for n in [Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(0.0, -1.0, 1e-8).normalize()] {
            let f = Frame::from_normal(n);
            assert!((f.tangent.length() - 1.0).abs() < 1e-5);
            assert!((f.bitangent.length() - 1.0).abs() < 1e-5);
            assert!(f.tangent.dot(f.bitangent).abs() < 1e-5);
            assert!(f.tangent.dot(n).abs() < 1e-5);
            let v = Vec3::new(0.3, -0.2, 0.9);
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-5);
        }
    }

    #[test]
    fn cosine_hemisphere_has_the_expected_mean_cosine() {
        // E[cos] under pdf cos/pi is 2/3.
        let mut rng = Rng::new(1, 1);
        let n = 200_000;
        let mean: f32 = (0..n).map(|_| cosine_hemisphere(rng.next_vec2()).z).sum::<f32>() / n as f32;
        assert!((mean - 2.0 / 3.0).abs() < 0.005, "{mean}");
    }

    #[test]
    fn distribution_matches_weights() {
        let d = Distribution1D::new(&[1.0, 0.0, 3.0]).expect("positive");
        assert_eq!(d.probability(1), 0.0);
        assert!((d.probability(2) - 0.75).abs() < 1e-6);
        assert_eq!(d.sample(0.1).0, 0);
        assert_eq!(d.sample(0.9).0, 2);
        assert_eq!(d.sample(0.999_999).0, 2);
        assert!(Distribution1D::new(&[0.0, -1.0]).is_none());
    }
}
