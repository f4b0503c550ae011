//! The indoor room of "room-day" and "room-night": 5 m x 4 m x 2.8 m, floor at z = 0,
//! centred on the Z axis, two windows in the south wall (y = -2), a table with a few things
//! on it, two crates, a ball, a ceiling lamp and a table lamp.
//!
//! The shell (floor, ceiling, four walls) faces inwards and is one set of grids cut at the
//! same coordinates (the window edges), so walls meet floor and ceiling edge to edge: the
//! only openings are the windows.

use glam::{Affine3A, Quat, Vec3};

use super::objects::{Parts, add_parts};
use super::shapes::{self, ShapeError};
use super::{BuildFailure, Framing, daylight_sky, daylight_sun};
use crate::{Environment, Material, Mesh, Scene, SceneBuilder};

pub(crate) const HALF_X: f32 = 2.5;
pub(crate) const HALF_Y: f32 = 2.0;
pub(crate) const HEIGHT: f32 = 2.8;

/// Cuts of the shell grids: the room's extent plus the window edges.
const XS: [f32; 6] = [-HALF_X, -1.8, -0.6, 0.6, 1.8, HALF_X];
const YS: [f32; 2] = [-HALF_Y, HALF_Y];
const ZS: [f32; 4] = [0.0, 0.9, 2.2, HEIGHT];

/// The two windows of the south wall, `[x0, x1, z0, z1]`.
pub(crate) const WINDOWS: [[f32; 4]; 2] = [[-1.8, -0.6, 0.9, 2.2], [0.6, 1.8, 0.9, 2.2]];

pub(crate) fn framing() -> Framing {
    Framing::Interior {
        min: Vec3::new(-HALF_X + 0.5, -HALF_Y + 0.5, 0.8),
        max: Vec3::new(HALF_X - 0.5, HALF_Y - 0.5, 2.1),
        eye: Vec3::new(1.9, 1.4, 1.6),
        look_at: Vec3::new(-0.4, -0.7, 0.9),
    }
}

/// A flat grid on the plane `axis = value`, spanning the cuts `a_cuts` along axis `a` and
/// `b_cuts` along axis `b`, facing `facing`; cells inside `holes` (`[a0, a1, b0, b1]`) are
/// left out. Coordinates are copied, never computed, so shared edges match bit for bit.
fn panel(
    (axis, value): (usize, f32),
    (a, a_cuts): (usize, &[f32]),
    (b, b_cuts): (usize, &[f32]),
    facing: Vec3,
    holes: &[[f32; 4]],
) -> Result<Mesh, ShapeError> {
    let flat = shapes::grid_panel(a_cuts, b_cuts, holes)?;
    let place = |p: Vec3| {
        let mut q = [0.0; 3];
        q[axis] = value;
        q[a] = p.x;
        q[b] = p.y;
        Vec3::from(q)
    };
    let mut unit_a = [0.0; 3];
    unit_a[a] = 1.0;
    let mut unit_b = [0.0; 3];
    unit_b[b] = 1.0;
    let mesh = Mesh {
        positions: flat.positions.iter().map(|&p| place(p)).collect(),
        normals: Some(vec![facing; flat.positions.len()]),
        indices: flat.indices,
    };
    // The grid faces +a x +b; turn it round if that is the wrong way.
    if Vec3::from(unit_a).cross(Vec3::from(unit_b)).dot(facing) > 0.0 {
        Ok(mesh)
    } else {
        Ok(Mesh { normals: Some(vec![facing; mesh.positions.len()]), ..shapes::flipped(&mesh) })
    }
}

/// The inward-facing shell: floor, ceiling, four walls, windows cut out of the south wall.
/// Returned separately so that tests can check it is closed except for the windows.
pub(crate) fn shell() -> Result<[(Mesh, Material); 3], ShapeError> {
    let (x, y, z) = (0, 1, 2);
    let floor = panel((z, 0.0), (x, &XS), (y, &YS), Vec3::Z, &[])?;
    let ceiling = panel((z, HEIGHT), (x, &XS), (y, &YS), Vec3::NEG_Z, &[])?;
    let mut walls = panel((x, -HALF_X), (y, &YS), (z, &ZS), Vec3::X, &[])?;
    walls.append(&panel((x, HALF_X), (y, &YS), (z, &ZS), Vec3::NEG_X, &[])?);
    walls.append(&panel((y, HALF_Y), (x, &XS), (z, &ZS), Vec3::NEG_Y, &[])?);
    walls.append(&panel((y, -HALF_Y), (x, &XS), (z, &ZS), Vec3::Y, &WINDOWS)?);
    Ok([
        (floor, Material::lambertian(Vec3::new(0.45, 0.31, 0.19))),
        (ceiling, Material::lambertian(Vec3::splat(0.85))),
        (walls, Material::lambertian(Vec3::new(0.78, 0.76, 0.72))),
    ])
}

fn at(x: f32, y: f32, z: f32) -> Affine3A {
    Affine3A::from_translation(Vec3::new(x, y, z))
}

fn turned(angle_z: f32, x: f32, y: f32, z: f32) -> Affine3A {
    Affine3A::from_rotation_translation(Quat::from_rotation_z(angle_z), Vec3::new(x, y, z))
}

/// Height of the table top.
const TABLE_TOP: f32 = 0.76;

/// Seconds the floor ball takes to roll once around its loop.
pub(crate) const BALL_PERIOD_S: f32 = 8.0;

/// Centre of the floor ball `time` seconds into the animation: an ellipse on the sunny part
/// of the floor (0.6 m by 0.5 m half-axes, clear of the table legs), passing through the
/// still scene's ball position at `time = 0`.
pub(crate) fn ball_centre(time: f32) -> Vec3 {
    let phase = std::f32::consts::TAU * (time / BALL_PERIOD_S).fract();
    Vec3::new(0.3 + 0.6 * phase.cos(), -0.7 + 0.5 * phase.sin(), 0.25)
}

/// Furniture that is the same by day and by night; the floor ball where it is at `time`.
fn furniture(time: f32) -> Result<Vec<(Mesh, Affine3A, Material)>, ShapeError> {
    let wood = Material::lambertian(Vec3::new(0.42, 0.25, 0.12));
    let (tx, ty) = (0.3, 0.3);
    let mut items = vec![(shapes::cuboid(Vec3::new(1.4, 0.8, 0.05))?, at(tx, ty, TABLE_TOP - 0.025), wood)];
    // Legs reach 1 cm into the top so that no crack shows.
    let leg = shapes::cuboid(Vec3::new(0.06, 0.06, TABLE_TOP - 0.04))?;
    for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        items.push((leg.clone(), at(tx + sx * 0.62, ty + sy * 0.32, (TABLE_TOP - 0.04) / 2.0), wood));
    }
    // On the table: a glossy red ball and a brushed-metal capsule "vase".
    items.push((
        shapes::icosphere(0.12, 4)?,
        at(tx - 0.25, ty + 0.05, TABLE_TOP + 0.121),
        Material::glossy(Vec3::new(0.55, 0.04, 0.03), Vec3::splat(0.04), 0.15),
    ));
    items.push((
        shapes::capsule(0.06, 0.14, 32, 8)?,
        at(tx + 0.25, ty - 0.1, TABLE_TOP + 0.131),
        Material::metal(Vec3::new(0.9, 0.9, 0.92), 0.22),
    ));
    // Two stacked crates in the north-west corner and a ball in the sunny part of the floor.
    items.push((
        shapes::cuboid(Vec3::splat(0.6))?,
        turned(0.26, -1.85, 1.3, 0.3),
        Material::lambertian(Vec3::new(0.55, 0.40, 0.24)),
    ));
    items.push((
        shapes::cuboid(Vec3::splat(0.4))?,
        turned(-0.35, -1.8, 1.28, 0.8),
        Material::lambertian(Vec3::new(0.25, 0.42, 0.6)),
    ));
    let ball = ball_centre(time);
    items.push((
        shapes::icosphere(0.25, 4)?,
        at(ball.x, ball.y, ball.z),
        Material::lambertian(Vec3::new(0.85, 0.65, 0.15)),
    ));
    // The ceiling lamp's housing and the table lamp's base and stem.
    items.push((
        shapes::cuboid(Vec3::new(0.7, 0.5, 0.06))?,
        at(0.0, 0.0, HEIGHT - 0.03),
        Material::lambertian(Vec3::splat(0.7)),
    ));
    let dark_metal = Material::metal(Vec3::splat(0.3), 0.4);
    items.push((shapes::cylinder(0.07, 0.02, 32)?, at(0.85, 0.55, TABLE_TOP + 0.01), dark_metal));
    items.push((shapes::cylinder(0.012, 0.3, 16)?, at(0.85, 0.55, TABLE_TOP + 0.17), dark_metal));
    Ok(items)
}

/// Radiance of the ceiling lamp's diffuser by night.
pub(crate) const CEILING_LAMP: Vec3 = Vec3::new(20.0, 18.0, 14.0);
/// Radiance of the table lamp's bulb by night.
pub(crate) const TABLE_LAMP: Vec3 = Vec3::new(12.0, 9.0, 5.0);

/// The room by day or by night, `time` seconds into its animation (the floor ball rolls; the
/// still scenes are `time = 0`).
pub(crate) fn room(night: bool, time: f32) -> Result<Scene, BuildFailure> {
    let mut b = SceneBuilder::new();
    let shell: Parts = shell()?.into();
    add_parts(&mut b, &shell, Affine3A::IDENTITY);
    for (mesh, transform, material) in furniture(time)? {
        b.add(&mesh, transform, material);
    }
    // The lamps are diffusers by day and area lights (front faces only) by night: the
    // ceiling one is a quad 1 mm below its housing, facing down.
    let (ceiling_lamp, table_lamp) = if night {
        (Material::emissive(CEILING_LAMP), Material::emissive(TABLE_LAMP))
    } else {
        (Material::lambertian(Vec3::splat(0.9)), Material::lambertian(Vec3::new(0.9, 0.9, 0.85)))
    };
    b.add(&shapes::flipped(&shapes::quad(0.6, 0.4)?), at(0.0, 0.0, HEIGHT - 0.061), ceiling_lamp);
    b.add(&shapes::icosphere(0.05, 3)?, at(0.85, 0.55, TABLE_TOP + 0.365), table_lamp);
    if night {
        b.environment(Environment::Sky {
            zenith: Vec3::new(0.004, 0.006, 0.02),
            horizon: Vec3::new(0.01, 0.015, 0.035),
            ground: Vec3::new(0.003, 0.003, 0.004),
        });
    } else {
        // The sun stands in the south-south-east, 34 degrees up: it shines through both
        // windows onto the floor and the table.
        b.environment(daylight_sky());
        b.sun(daylight_sun());
    }
    Ok(b.build()?)
}
