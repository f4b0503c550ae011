//! The objects of the built-in object scenes, each as a list of `(mesh, material)` parts in
//! its own frame (centred at the origin, +Z up), so that a scene can place it alone or
//! several of them together (the "assembly").

use glam::{Affine3A, Quat, Vec3};

use super::shapes::{self, Fur, ShapeError};
use crate::{Material, Mesh, SceneBuilder};

pub(crate) type Parts = Vec<(Mesh, Material)>;

/// Adds every part moved by `transform`.
pub(crate) fn add_parts(builder: &mut SceneBuilder, parts: &Parts, transform: Affine3A) {
    for (mesh, material) in parts {
        builder.add(mesh, transform, *material);
    }
}

/// Axis-aligned bounds of the parts once moved by `transform` (`None` if they are empty).
pub(crate) fn parts_bounds(parts: &Parts, transform: Affine3A) -> Option<(Vec3, Vec3)> {
    parts.iter().flat_map(|(m, _)| m.positions.iter()).map(|&p| transform.transform_point3(p)).fold(None, |acc, p| {
        match acc {
            None => Some((p, p)),
            Some((lo, hi)) => Some((lo.min(p), hi.max(p))),
        }
    })
}

/// Radius of the sphere around the origin that holds the knot (centre line within 1.2,
/// tube 0.18).
pub(crate) const KNOT_RADIUS: f32 = 1.38;

/// An orange matte trefoil knot, about 2.8 m across and 1.2 m tall.
pub(crate) fn knot() -> Result<Parts, ShapeError> {
    let mesh = shapes::torus_knot(2, 3, 1.2, 0.18, 512, 24)?;
    Ok(vec![(mesh, Material::lambertian(Vec3::new(0.8, 0.32, 0.06)))])
}

/// Everything lies within this radius of the origin (the torus: 0.95 + 0.28).
pub(crate) const GLOSSY_RADIUS: f32 = 1.23;

/// A tilted polished-gold torus around a glossy blue plastic ball: sharp, moving
/// highlights from the sun and the sky.
pub(crate) fn glossy_pair() -> Result<Parts, ShapeError> {
    let ring =
        shapes::torus(0.95, 0.28, 160, 48)?.transformed(Affine3A::from_quat(Quat::from_rotation_x(55f32.to_radians())));
    let ball = shapes::icosphere(0.55, 5)?;
    Ok(vec![
        (ring, Material::metal(Vec3::new(0.95, 0.74, 0.36), 0.18)),
        (ball, Material::glossy(Vec3::new(0.04, 0.09, 0.42), Vec3::splat(0.04), 0.12)),
    ])
}

/// The fur of the "furry" scene: ~16k ribbons, 2.5 mm wide at the root, 25-42 cm long.
pub(crate) const FUR: Fur = Fur {
    count: 16_000,
    min_length: 0.25,
    max_length: 0.42,
    root_width: 0.0025,
    tip_width: 0.0008,
    segments: 3,
    max_tilt: 0.6,
    curl: 0.35,
    seed: 0x5EED_F0F0,
};

pub(crate) const FUR_CORE_RADIUS: f32 = 0.7;

/// A brown ball covered in light fibres, grown outwards from a sphere of `core_radius`.
pub(crate) fn fur_ball(core_radius: f32, fur: &Fur) -> Result<Parts, ShapeError> {
    let core = shapes::icosphere(core_radius, 4)?;
    let hair = shapes::fur_on_sphere(core_radius, fur)?;
    Ok(vec![
        (core, Material::lambertian(Vec3::new(0.30, 0.19, 0.10))),
        (hair, Material::lambertian(Vec3::new(0.78, 0.62, 0.42))),
    ])
}

/// Outer radius of the glass shell; the wall is 3 cm thick.
pub(crate) const SHELL_RADIUS: f32 = 1.25;
const SHELL_THICKNESS: f32 = 0.03;

/// The glass of the shells: ior 1.5, a faint green-blue tint.
pub(crate) fn shell_glass() -> Material {
    Material::glass(1.5, Vec3::new(0.95, 0.99, 0.97))
}

/// A thin-walled glass sphere of radius [`SHELL_RADIUS`] (outer surface facing out, inner
/// surface facing the hollow) around a tilted blue cube and a red ring: rays cross two
/// glass interfaces before reaching the solid content.
pub(crate) fn glass_shell() -> Result<Parts, ShapeError> {
    let outer = shapes::icosphere(SHELL_RADIUS, 5)?;
    let inner = shapes::flipped(&shapes::icosphere(SHELL_RADIUS - SHELL_THICKNESS, 5)?);
    // Content: every point of the cube is within 0.65 of the centre, every point of the
    // ring between 0.79 and 0.97, and the inner glass is at 1.22, so nothing touches.
    let cube = shapes::cuboid(Vec3::splat(0.75))?.transformed(Affine3A::from_quat(Quat::from_euler(
        glam::EulerRot::XYZ,
        0.6,
        0.5,
        0.3,
    )));
    let ring = shapes::torus(0.88, 0.09, 96, 16)?
        .transformed(Affine3A::from_quat(Quat::from_rotation_z(0.35) * Quat::from_rotation_x(70f32.to_radians())));
    Ok(vec![
        (outer, shell_glass()),
        (inner, shell_glass()),
        (cube, Material::lambertian(Vec3::new(0.08, 0.38, 0.72))),
        (ring, Material::lambertian(Vec3::new(0.80, 0.12, 0.08))),
    ])
}

/// A closed white (albedo exactly 1) sphere of radius 1 for the furnace test.
pub(crate) fn furnace_sphere() -> Result<Parts, ShapeError> {
    Ok(vec![(shapes::icosphere(1.0, 4)?, Material::lambertian(Vec3::ONE))])
}
