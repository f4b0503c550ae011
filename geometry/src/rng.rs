//! A tiny deterministic random number generator (SplitMix64) for procedural detail such as
//! fibres and for weight initialisation: same seed, same stream, on every platform, with no
//! dependency.

use std::f32::consts::TAU;

use glam::Vec3;

#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The generator's state: `SplitMix64::new(g.state())` continues `g`'s stream (checkpoints).
    pub fn state(&self) -> u64 {
        self.0
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)` (24 random bits, so exactly representable).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `0..n` (`0` when `n` is 0), from [`Self::next_f64`].
    pub fn below(&mut self, n: u64) -> u64 {
        (self.next_f64() * n as f64) as u64 % n.max(1)
    }

    /// A direction uniformly distributed on the unit sphere.
    pub fn unit_vector(&mut self) -> Vec3 {
        let z = 1.0 - 2.0 * self.next_f32();
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = TAU * self.next_f32();
        Vec3::new(r * phi.cos(), r * phi.sin(), z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_in_range() {
        let mut a = SplitMix64::new(42);
        let mut b = SplitMix64::new(42);
        for _ in 0..1000 {
            let x = a.next_f32();
            assert_eq!(x, b.next_f32());
            assert!((0.0..1.0).contains(&x));
            let v = a.unit_vector();
            b.unit_vector();
            assert!((v.length() - 1.0).abs() < 1e-5);
        }
        let mean: f32 = (0..10_000).map(|_| a.next_f32()).sum::<f32>() / 10_000.0;
        assert!((mean - 0.5).abs() < 0.02, "mean {mean}");
    }
}
