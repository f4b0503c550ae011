//! Adversarial rays for the numerical-stability suite (issue 18): the rays a kernel or a
//! trainer sees least often and breaks on first.
//!
//! [`HardRays`] draws, for an object's box and a few points inside its matter, rays of the
//! classes of [`RayClass`]: exactly axis-parallel rays from cell-aligned origins, rays lying
//! in a face of the box or along an edge or through a corner, rays starting inside the box
//! and inside matter, cameras far beyond the scene (at the far plane, where a float's step is
//! coarse), directions with denormal or tiny components, and the degenerate rays every entry
//! point must reject (zero, denormal-length, NaN or infinite direction or origin). The
//! stream is deterministic for a seed, and classes are drawn in turn so that any count
//! covers all of them.
//!
//! Pure: no kernel here. The suite that drives every kernel and trainer with these rays is
//! `nephele bench hardcases` (`nephele-bench`'s `hardcases` module) and its tests.

use glam::Vec3;

use crate::{Bounds, SplitMix64};

/// Density (per unit length) of a synthetic object made for hard cases, in `[-1, 1]^3`: a
/// sphere of radius 0.5 with a soft edge (fractional opacities), a thin tilted slab (grazing
/// rays) and a small box alone in a corner (empty blocks around it). The GPU agreement tests
/// and `bench hardcases` build their kernels on it.
pub fn hard_object_density(p: Vec3) -> f32 {
    let sphere = (0.5 - p.length()) * 400.0;
    let slab = if (p.x + 0.3 * p.y - 0.6).abs() < 0.02 && p.y.abs() < 0.6 && p.z.abs() < 0.6 { 80.0 } else { 0.0 };
    let corner = if (p - Vec3::new(-0.8, 0.8, -0.8)).abs().max_element() < 0.08 { 200.0 } else { 0.0 };
    sphere.clamp(0.0, 300.0) + slab + corner
}

/// A kind of adversarial ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RayClass {
    /// From outside the box towards a random point inside it: the ordinary case, as control.
    Ordinary,
    /// Exactly along +-x, +-y or +-z, from an origin on the box's 16^3 cell lattice (slab tests
    /// divide by zero, DDA steps land on cell faces).
    AxisParallel,
    /// Lying in a face plane of the box (or one float step inside or outside it).
    GrazingFace,
    /// Along an edge of the box, or through one of its corners.
    EdgeOrCorner,
    /// Starting inside the box, in any direction.
    InsideBox,
    /// Starting inside matter (at or next to one of the given matter points).
    InsideMatter,
    /// From 10^4 to 10^7 box sizes away, towards the box: a camera at the far plane.
    FarAway,
    /// A unit direction with one or two components tiny or denormal (1e-30 .. 1e-44).
    TinyComponents,
    /// Must be rejected (a miss, never NaN): zero or denormal-length direction, NaN or
    /// infinite origin or direction.
    Degenerate,
}

impl RayClass {
    /// Every class, in the order [`HardRays`] draws them.
    pub const ALL: [RayClass; 9] = [
        RayClass::Ordinary,
        RayClass::AxisParallel,
        RayClass::GrazingFace,
        RayClass::EdgeOrCorner,
        RayClass::InsideBox,
        RayClass::InsideMatter,
        RayClass::FarAway,
        RayClass::TinyComponents,
        RayClass::Degenerate,
    ];

    pub fn name(self) -> &'static str {
        match self {
            RayClass::Ordinary => "ordinary",
            RayClass::AxisParallel => "axis-parallel",
            RayClass::GrazingFace => "grazing a face",
            RayClass::EdgeOrCorner => "edge or corner",
            RayClass::InsideBox => "inside the box",
            RayClass::InsideMatter => "inside matter",
            RayClass::FarAway => "far away",
            RayClass::TinyComponents => "tiny components",
            RayClass::Degenerate => "degenerate",
        }
    }
}

/// One adversarial ray. `direction` is unit length except for [`RayClass::Degenerate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HardRay {
    pub class: RayClass,
    pub origin: Vec3,
    pub direction: Vec3,
}

impl HardRay {
    /// Whether a kernel must treat the ray as invalid (render nothing, return no gradient).
    pub fn must_be_rejected(&self) -> bool {
        self.class == RayClass::Degenerate
    }
}

/// An endless, deterministic stream of hard rays for one object.
#[derive(Debug, Clone)]
pub struct HardRays {
    bounds: Bounds,
    matter: Vec<Vec3>,
    rng: SplitMix64,
    next_class: usize,
}

impl HardRays {
    /// Rays for an object in `bounds` with matter at (some of) `matter` (may be empty: the
    /// inside-matter class then starts at the box centre).
    pub fn new(bounds: Bounds, matter: &[Vec3], seed: u64) -> HardRays {
        HardRays { bounds, matter: matter.to_vec(), rng: SplitMix64::new(seed), next_class: 0 }
    }

    fn point_in_box(&mut self) -> Vec3 {
        let u = Vec3::new(self.rng.next_f32(), self.rng.next_f32(), self.rng.next_f32());
        self.bounds.min + u * self.bounds.size()
    }

    fn axis(&mut self) -> (usize, f32) {
        let a = self.rng.below(6) as usize;
        (a % 3, if a < 3 { 1.0 } else { -1.0 })
    }

    /// A float step (or none) up or down from `v`.
    fn nudge(&mut self, v: f32) -> f32 {
        match self.rng.below(3) {
            0 => v,
            1 => v.next_up(),
            _ => v.next_down(),
        }
    }

    fn draw(&mut self, class: RayClass) -> HardRay {
        let b = self.bounds;
        let size = b.size();
        let scale = size.max_element();
        let (origin, direction) = match class {
            RayClass::Ordinary => {
                let target = self.point_in_box();
                let origin = b.center() + self.rng.unit_vector() * scale * (1.0 + 3.0 * self.rng.next_f32());
                (origin, (target - origin).normalize())
            }
            RayClass::AxisParallel => {
                let (axis, sign) = self.axis();
                let cell = size / 16.0;
                let lattice = |k: u64, lo: f32, step: f32| lo + k as f32 * step;
                let mut origin = Vec3::new(
                    lattice(self.rng.below(17), b.min.x, cell.x),
                    lattice(self.rng.below(17), b.min.y, cell.y),
                    lattice(self.rng.below(17), b.min.z, cell.z),
                );
                // Start outside the box on the axis half the time.
                if self.rng.below(2) == 0 {
                    origin[axis] =
                        if sign > 0.0 { b.min[axis] - 0.5 * size[axis] } else { b.max[axis] + 0.5 * size[axis] };
                }
                let mut dir = Vec3::ZERO;
                dir[axis] = sign;
                (origin, dir)
            }
            RayClass::GrazingFace => {
                let (axis, _) = self.axis();
                let face = if self.rng.below(2) == 0 { b.min[axis] } else { b.max[axis] };
                let mut origin = b.center() + self.rng.unit_vector() * scale * 2.0;
                let mut target = self.point_in_box();
                origin[axis] = self.nudge(face);
                target[axis] = origin[axis];
                let d = target - origin;
                (origin, if d.length() > 0.0 { d.normalize() } else { Vec3::X })
            }
            RayClass::EdgeOrCorner => {
                let corner = |k: u64| {
                    Vec3::new(
                        if k & 1 == 0 { b.min.x } else { b.max.x },
                        if k & 2 == 0 { b.min.y } else { b.max.y },
                        if k & 4 == 0 { b.min.z } else { b.max.z },
                    )
                };
                let a = corner(self.rng.below(8));
                if self.rng.below(2) == 0 {
                    // Along an edge: from beyond one corner through its neighbour on one axis.
                    let (axis, _) = self.axis();
                    let mut other = a;
                    other[axis] = if a[axis] == b.min[axis] { b.max[axis] } else { b.min[axis] };
                    let dir = (other - a).normalize();
                    (a - dir * 0.5 * scale, dir)
                } else {
                    // Through a corner from outside, at any angle.
                    let origin = a + self.rng.unit_vector() * scale;
                    (origin, (a - origin).normalize())
                }
            }
            RayClass::InsideBox => (self.point_in_box(), self.rng.unit_vector()),
            RayClass::InsideMatter => {
                let base = if self.matter.is_empty() {
                    b.center()
                } else {
                    self.matter[self.rng.below(self.matter.len() as u64) as usize]
                };
                let jitter = self.rng.unit_vector() * scale * 1e-3 * self.rng.next_f32();
                (base + jitter, self.rng.unit_vector())
            }
            RayClass::FarAway => {
                let distance = scale * 10f32.powf(4.0 + 3.0 * self.rng.next_f32());
                let origin = b.center() + self.rng.unit_vector() * distance;
                let target = self.point_in_box();
                (origin, (target - origin).normalize())
            }
            RayClass::TinyComponents => {
                const TINY: [f32; 4] = [1e-30, 1e-38, 1e-40, 1e-44];
                let (axis, sign) = self.axis();
                let mut dir = Vec3::ZERO;
                dir[axis] = sign;
                for k in 1..=(1 + self.rng.below(2) as usize) {
                    let t = TINY[self.rng.below(4) as usize];
                    dir[(axis + k) % 3] = if self.rng.below(2) == 0 { t } else { -t };
                }
                let origin = b.center() - dir * scale + (self.point_in_box() - b.center()) * 0.5;
                (origin, dir)
            }
            RayClass::Degenerate => {
                let origin = self.point_in_box();
                match self.rng.below(6) {
                    0 => (origin, Vec3::ZERO),
                    1 => (origin, Vec3::new(1e-40, -1e-41, 1e-42)),
                    2 => (origin, Vec3::new(f32::NAN, 0.0, 1.0)),
                    3 => (origin, Vec3::new(0.0, f32::INFINITY, 0.0)),
                    4 => (Vec3::new(f32::NAN, origin.y, origin.z), Vec3::Z),
                    _ => (Vec3::new(origin.x, f32::NEG_INFINITY, origin.z), Vec3::Z),
                }
            }
        };
        HardRay { class, origin, direction }
    }
}

impl Iterator for HardRays {
    type Item = HardRay;

    fn next(&mut self) -> Option<HardRay> {
        let class = RayClass::ALL[self.next_class];
        self.next_class = (self.next_class + 1) % RayClass::ALL.len();
        Some(self.draw(class))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> Bounds {
        Bounds { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }
    }

    #[test]
    fn every_class_in_turn_and_deterministic() {
        let a: Vec<HardRay> = HardRays::new(unit_box(), &[Vec3::ZERO], 3).take(90).collect();
        let b: Vec<HardRay> = HardRays::new(unit_box(), &[Vec3::ZERO], 3).take(90).collect();
        // NaN components compare unequal: compare the bits.
        let bits = |r: &HardRay| (r.origin.to_array().map(f32::to_bits), r.direction.to_array().map(f32::to_bits));
        assert!(a.iter().zip(&b).all(|(x, y)| bits(x) == bits(y)));
        for class in RayClass::ALL {
            assert_eq!(a.iter().filter(|r| r.class == class).count(), 10, "{}", class.name());
        }
    }

    #[test]
    fn classes_are_what_they_say() {
        let bounds = Bounds { min: Vec3::new(-2.0, 0.5, 10.0), max: Vec3::new(3.0, 1.5, 12.0) };
        let matter = [Vec3::new(0.0, 1.0, 11.0)];
        for r in HardRays::new(bounds, &matter, 9).take(9000) {
            if r.must_be_rejected() {
                let len = r.direction.length();
                assert!(!(r.origin.is_finite() && r.direction.is_finite() && len > 1e-20), "{r:?}");
                continue;
            }
            assert!(r.origin.is_finite() && r.direction.is_finite(), "{r:?}");
            assert!((r.direction.length() - 1.0).abs() < 1e-5, "{r:?}");
            match r.class {
                RayClass::AxisParallel => {
                    assert_eq!(r.direction.abs().to_array().iter().filter(|&&c| c == 1.0).count(), 1, "{r:?}");
                    assert_eq!(r.direction.abs().element_sum(), 1.0, "{r:?}");
                }
                RayClass::TinyComponents => {
                    let tiny = r.direction.to_array().iter().filter(|c| c.abs() > 0.0 && c.abs() < 1e-29).count();
                    assert!(tiny >= 1, "{r:?}");
                }
                RayClass::InsideBox => {
                    assert!(r.origin.cmpge(bounds.min).all() && r.origin.cmple(bounds.max).all(), "{r:?}")
                }
                RayClass::InsideMatter => assert!(r.origin.distance(matter[0]) < 0.01, "{r:?}"),
                RayClass::FarAway => assert!(r.origin.distance(bounds.center()) > 4e4, "{r:?}"),
                RayClass::GrazingFace => {
                    // The origin lies on (or a float step off) a face plane and the ray stays in it.
                    let on_face = (0..3).any(|a| {
                        let near = |f: f32| (r.origin[a] - f).abs() <= f.abs() * 2.0 * f32::EPSILON;
                        (near(bounds.min[a]) || near(bounds.max[a])) && r.direction[a] == 0.0
                    });
                    assert!(on_face, "{r:?}");
                }
                _ => {}
            }
        }
    }
}
