//! Procedural triangle meshes for the built-in scenes (and for tests).
//!
//! Every generator is a pure function returning a [`Mesh`] in its own local frame (+Z up,
//! metres), with per-vertex shading normals: smooth where the surface is smooth, flat on
//! flat faces. Closed meshes are watertight once identical positions are welded, and wound
//! counter-clockwise seen from outside, so their geometric normals face outwards; open
//! surfaces (quads, discs, panels) face +Z. Arguments are validated, never trusted: zero
//! segments, non-finite or non-positive sizes, or a mesh over [`MAX_TRIANGLES`] give a
//! [`ShapeError`] instead of a panic or a degenerate mesh.

use std::collections::HashMap;
use std::f32::consts::{PI, TAU};

use glam::{Quat, Vec2, Vec3};
use thiserror::Error;

use crate::Mesh;
use nephele_geometry::SplitMix64;

/// The largest mesh any generator builds (keeps indices in `u32` and memory bounded).
pub const MAX_TRIANGLES: u64 = 4_000_000;

/// The most subdivisions [`icosphere`] accepts (20 * 4^7 = 327,680 triangles).
pub const MAX_ICOSPHERE_SUBDIVISIONS: u32 = 7;

/// Why a generator refused its arguments.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ShapeError {
    #[error("{what} must be finite and > 0, got {value}")]
    NotPositive { what: &'static str, value: f32 },
    #[error("{what} must be finite")]
    NotFinite { what: &'static str },
    #[error("{what} must be at least {min}, got {value}")]
    TooFew { what: &'static str, value: u32, min: u32 },
    #[error("{what} must be at most {max}, got {value}")]
    TooMany { what: &'static str, value: u32, max: u32 },
    #[error("the mesh would have {triangles} triangles, more than the limit of {MAX_TRIANGLES}")]
    TooLarge { triangles: u64 },
    #[error("{0}")]
    Inconsistent(String),
}

fn positive(what: &'static str, value: f32) -> Result<f32, ShapeError> {
    if value.is_finite() && value > 0.0 { Ok(value) } else { Err(ShapeError::NotPositive { what, value }) }
}

fn finite(what: &'static str, value: Vec3) -> Result<Vec3, ShapeError> {
    if value.is_finite() { Ok(value) } else { Err(ShapeError::NotFinite { what }) }
}

fn at_least(what: &'static str, value: u32, min: u32) -> Result<u32, ShapeError> {
    if value >= min { Ok(value) } else { Err(ShapeError::TooFew { what, value, min }) }
}

fn at_most(what: &'static str, value: u32, max: u32) -> Result<u32, ShapeError> {
    if value <= max { Ok(value) } else { Err(ShapeError::TooMany { what, value, max }) }
}

/// Checks that a mesh of `factors` multiplied together triangles stays within
/// [`MAX_TRIANGLES`] (saturating, so absurd arguments cannot overflow).
fn budget(factors: &[u64]) -> Result<(), ShapeError> {
    let triangles = factors.iter().fold(1u64, |acc, &f| acc.saturating_mul(f));
    if triangles <= MAX_TRIANGLES { Ok(()) } else { Err(ShapeError::TooLarge { triangles }) }
}

/// The same surface seen from the other side: winding reversed and normals negated (turns
/// an outward-facing closed mesh into an inward-facing one, e.g. the inner wall of a shell).
pub fn flipped(mesh: &Mesh) -> Mesh {
    Mesh {
        positions: mesh.positions.clone(),
        normals: mesh.normals.as_ref().map(|ns| ns.iter().map(|&n| -n).collect()),
        indices: mesh.indices.iter().map(|&[a, b, c]| [a, c, b]).collect(),
    }
}

/// A latitude-longitude sphere centred at the origin, poles on the Z axis. `segments`
/// (>= 3) around, `rings` (>= 2) from pole to pole; one vertex per pole, no seam.
pub fn uv_sphere(radius: f32, segments: u32, rings: u32) -> Result<Mesh, ShapeError> {
    positive("sphere radius", radius)?;
    let segments = at_least("sphere segments", segments, 3)?;
    let rings = at_least("sphere rings", rings, 2)?;
    budget(&[2, u64::from(segments), u64::from(rings)])?;
    let profile: Vec<(Vec3, Vec3)> = (1..rings)
        .map(|k| {
            let theta = PI * k as f32 / rings as f32;
            let n = Vec3::new(theta.sin(), 0.0, theta.cos());
            (n * radius, n)
        })
        .collect();
    Ok(lathe(&profile, segments, Vec3::Z * radius, Vec3::NEG_Z * radius))
}

/// A closed surface of revolution about Z. `profile` lists `(position, normal)` at azimuth
/// 0 (in the XZ plane, `x` >= 0) from the north pole down to the south pole, poles
/// excluded: each pole is one vertex, `north` and `south`, on the Z axis.
fn lathe(profile: &[(Vec3, Vec3)], segments: u32, north: Vec3, south: Vec3) -> Mesh {
    let rings = profile.len() as u32;
    let mut positions = Vec::with_capacity((rings * segments + 2) as usize);
    let mut normals = Vec::with_capacity(positions.capacity());
    positions.push(north);
    normals.push(Vec3::Z);
    let azimuths: Vec<(f32, f32)> = (0..segments)
        .map(|j| {
            let phi = TAU * j as f32 / segments as f32;
            (phi.cos(), phi.sin())
        })
        .collect();
    for &(p, n) in profile {
        for &(c, s) in &azimuths {
            positions.push(Vec3::new(p.x * c, p.x * s, p.z));
            normals.push(Vec3::new(n.x * c, n.x * s, n.z));
        }
    }
    positions.push(south);
    normals.push(Vec3::NEG_Z);
    let south_index = positions.len() as u32 - 1;
    let ring = |k: u32, j: u32| 1 + k * segments + j % segments;
    let mut indices = Vec::with_capacity((2 * segments * rings) as usize);
    for j in 0..segments {
        indices.push([0, ring(0, j), ring(0, j + 1)]);
    }
    for k in 0..rings.saturating_sub(1) {
        for j in 0..segments {
            let (a, b, c, d) = (ring(k, j), ring(k + 1, j), ring(k + 1, j + 1), ring(k, j + 1));
            indices.push([a, b, c]);
            indices.push([a, c, d]);
        }
    }
    for j in 0..segments {
        indices.push([ring(rings - 1, j), south_index, ring(rings - 1, j + 1)]);
    }
    Mesh { positions, normals: Some(normals), indices }
}

/// A geodesic sphere centred at the origin: an icosahedron subdivided `subdivisions` times
/// (at most [`MAX_ICOSPHERE_SUBDIVISIONS`]), `20 * 4^subdivisions` triangles, all vertices
/// shared, normals radial.
pub fn icosphere(radius: f32, subdivisions: u32) -> Result<Mesh, ShapeError> {
    positive("icosphere radius", radius)?;
    at_most("icosphere subdivisions", subdivisions, MAX_ICOSPHERE_SUBDIVISIONS)?;
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut unit: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    // Make the base faces outward whatever the table's convention; subdivision keeps it.
    for f in &mut faces {
        let [a, b, c] = f.map(|i| unit[i as usize]);
        if (b - a).cross(c - a).dot(a + b + c) < 0.0 {
            f.swap(1, 2);
        }
    }
    for _ in 0..subdivisions {
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::new();
        let mut next = Vec::with_capacity(faces.len() * 4);
        let mut midpoint = |a: u32, b: u32, unit: &mut Vec<Vec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *midpoints.entry(key).or_insert_with(|| {
                unit.push((unit[a as usize] + unit[b as usize]).normalize());
                unit.len() as u32 - 1
            })
        };
        for &[a, b, c] in &faces {
            let ab = midpoint(a, b, &mut unit);
            let bc = midpoint(b, c, &mut unit);
            let ca = midpoint(c, a, &mut unit);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    Ok(Mesh { positions: unit.iter().map(|&n| n * radius).collect(), normals: Some(unit), indices: faces })
}

/// An axis-aligned box of the given full `size`, centred at the origin: 6 faces of 4
/// unshared vertices each (flat normals), 12 triangles.
pub fn cuboid(size: Vec3) -> Result<Mesh, ShapeError> {
    positive("box width", size.x)?;
    positive("box depth", size.y)?;
    positive("box height", size.z)?;
    let h = size * 0.5;
    let mut positions = Vec::with_capacity(24);
    let mut normals = Vec::with_capacity(24);
    let mut indices = Vec::with_capacity(12);
    // (normal, u, v) with u x v = normal, so corners listed -u-v, +u-v, +u+v, -u+v are CCW.
    let faces = [
        (Vec3::X, Vec3::Y, Vec3::Z),
        (Vec3::NEG_X, Vec3::Z, Vec3::Y),
        (Vec3::Y, Vec3::Z, Vec3::X),
        (Vec3::NEG_Y, Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X, Vec3::Y),
        (Vec3::NEG_Z, Vec3::Y, Vec3::X),
    ];
    for (n, u, v) in faces {
        let base = positions.len() as u32;
        for (su, sv) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            // Component-wise signs (not sums of floats) so corners shared by faces are
            // bit-identical.
            let sign = n + u * su + v * sv;
            positions.push(h * sign);
            normals.push(n);
        }
        indices.push([base, base + 1, base + 2]);
        indices.push([base, base + 2, base + 3]);
    }
    Ok(Mesh { positions, normals: Some(normals), indices })
}

/// Sweeps a circle of `radius` (with `sides` vertices) along a closed polyline `centres`
/// with unit `frames` (a normal perpendicular to the path at each centre). Ring `i` joins
/// ring `i + 1` and the last joins the first: no seam vertices, watertight.
fn sweep_closed(centres: &[Vec3], frames: &[Vec3], radius: f32, sides: u32) -> Mesh {
    let n = centres.len() as u32;
    let mut positions = Vec::with_capacity((n * sides) as usize);
    let mut normals = Vec::with_capacity(positions.capacity());
    let angles: Vec<(f32, f32)> = (0..sides)
        .map(|j| {
            let theta = TAU * j as f32 / sides as f32;
            (theta.cos(), theta.sin())
        })
        .collect();
    for i in 0..n as usize {
        let prev = centres[(i + n as usize - 1) % n as usize];
        let next = centres[(i + 1) % n as usize];
        let tangent = (next - prev).normalize_or_zero();
        let normal = frames[i];
        // (normal, binormal, tangent) is right-handed, so the ring runs counter-clockwise
        // around the tangent.
        let binormal = tangent.cross(normal);
        for &(c, s) in &angles {
            let dir = normal * c + binormal * s;
            positions.push(centres[i] + dir * radius);
            normals.push(dir);
        }
    }
    let index = |i: u32, j: u32| (i % n) * sides + j % sides;
    let mut indices = Vec::with_capacity((2 * n * sides) as usize);
    for i in 0..n {
        for j in 0..sides {
            // d(ring angle) x d(path) points outwards for this frame orientation.
            indices.push([index(i, j), index(i, j + 1), index(i + 1, j)]);
            indices.push([index(i + 1, j), index(i, j + 1), index(i + 1, j + 1)]);
        }
    }
    Mesh { positions, normals: Some(normals), indices }
}

/// A ring torus around the Z axis: tube of `minor_radius` around a circle of
/// `major_radius` in the XY plane; `minor_radius < major_radius` (otherwise the surface
/// intersects itself). `major_segments` >= 3 around Z, `minor_segments` >= 3 around the tube.
pub fn torus(
    major_radius: f32,
    minor_radius: f32,
    major_segments: u32,
    minor_segments: u32,
) -> Result<Mesh, ShapeError> {
    positive("torus major radius", major_radius)?;
    positive("torus minor radius", minor_radius)?;
    if minor_radius >= major_radius {
        return Err(ShapeError::Inconsistent(format!(
            "torus minor radius {minor_radius} must be smaller than its major radius {major_radius}"
        )));
    }
    let major_segments = at_least("torus major segments", major_segments, 3)?;
    let minor_segments = at_least("torus minor segments", minor_segments, 3)?;
    budget(&[2, u64::from(major_segments), u64::from(minor_segments)])?;
    let (centres, frames): (Vec<Vec3>, Vec<Vec3>) = (0..major_segments)
        .map(|i| {
            let phi = TAU * i as f32 / major_segments as f32;
            let radial = Vec3::new(phi.cos(), phi.sin(), 0.0);
            (radial * major_radius, radial)
        })
        .unzip();
    Ok(sweep_closed(&centres, &frames, minor_radius, minor_segments))
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// A tube of `tube_radius` around the `(p, q)` torus knot (it winds `p` times around the Z
/// axis and `q` times through the hole; `p` and `q` coprime, e.g. (2, 3) is the trefoil).
/// The knot lies on a torus of major radius `2 radius / 3` and minor radius `radius / 3`,
/// so its centre line stays within `radius` of the Z axis and `|z| <= radius / 3`; the
/// tube must be thinner than `radius / 3`. `segments` (>= 3) along the knot, `sides` (>= 3)
/// around the tube. The tube follows a parallel-transport frame whose residual twist is
/// spread evenly along the loop, so it closes without a seam.
pub fn torus_knot(
    p: u32,
    q: u32,
    radius: f32,
    tube_radius: f32,
    segments: u32,
    sides: u32,
) -> Result<Mesh, ShapeError> {
    let p = at_least("torus knot p", p, 1)?;
    let q = at_least("torus knot q", q, 1)?;
    if gcd(p, q) != 1 {
        return Err(ShapeError::Inconsistent(format!("torus knot ({p}, {q}) is not a knot: p and q must be coprime")));
    }
    positive("torus knot radius", radius)?;
    positive("torus knot tube radius", tube_radius)?;
    if tube_radius >= radius / 3.0 {
        return Err(ShapeError::Inconsistent(format!(
            "torus knot tube radius {tube_radius} must be smaller than radius / 3 = {}",
            radius / 3.0
        )));
    }
    let segments = at_least("torus knot segments", segments, 3)?;
    let sides = at_least("torus knot sides", sides, 3)?;
    budget(&[2, u64::from(segments), u64::from(sides)])?;
    let (big, small) = (radius * 2.0 / 3.0, radius / 3.0);
    let (pf, qf) = (p as f32, q as f32);
    let curve = |t: f32| {
        let r = big + small * (qf * t).cos();
        Vec3::new(r * (pf * t).cos(), r * (pf * t).sin(), small * (qf * t).sin())
    };
    let n = segments as usize;
    let centres: Vec<Vec3> = (0..n).map(|i| curve(TAU * i as f32 / n as f32)).collect();
    let tangent = |i: usize| (centres[(i + 1) % n] - centres[(i + n - 1) % n]).normalize();
    // Parallel transport by projection, starting from any normal of the first tangent.
    let t0 = tangent(0);
    let mut frames = Vec::with_capacity(n);
    frames.push(t0.any_orthonormal_vector());
    for i in 1..n {
        let t = tangent(i);
        let prev = frames[i - 1];
        frames.push((prev - t * prev.dot(t)).normalize());
    }
    // Carry the last frame back to the start and measure the twist it picked up.
    let last = frames[n - 1];
    let back = (last - t0 * last.dot(t0)).normalize();
    let twist = t0.dot(back.cross(frames[0])).atan2(back.dot(frames[0]));
    for (i, f) in frames.iter_mut().enumerate().skip(1) {
        let t = tangent(i);
        *f = Quat::from_axis_angle(t, twist * i as f32 / n as f32) * *f;
    }
    let mesh = sweep_closed(&centres, &frames, tube_radius, sides);
    if !mesh.positions.iter().all(|p| p.is_finite()) {
        return Err(ShapeError::Inconsistent("torus knot frame degenerated".into()));
    }
    Ok(mesh)
}

/// A closed cylinder along Z, centred at the origin (`z` in `[-height/2, height/2]`):
/// smooth side, flat caps (cap vertices are separate from the side's, at identical
/// positions). `segments` >= 3.
pub fn cylinder(radius: f32, height: f32, segments: u32) -> Result<Mesh, ShapeError> {
    positive("cylinder radius", radius)?;
    positive("cylinder height", height)?;
    let segments = at_least("cylinder segments", segments, 3)?;
    budget(&[4, u64::from(segments)])?;
    let rim: Vec<(f32, f32)> = (0..segments)
        .map(|j| {
            let phi = TAU * j as f32 / segments as f32;
            (phi.cos(), phi.sin())
        })
        .collect();
    let (top, bottom) = (height * 0.5, -height * 0.5);
    let mut positions = Vec::new();
    let mut normals = Vec::new();
    let mut indices = Vec::new();
    // Side: bottom ring then top ring.
    for z in [bottom, top] {
        for &(c, s) in &rim {
            positions.push(Vec3::new(radius * c, radius * s, z));
            normals.push(Vec3::new(c, s, 0.0));
        }
    }
    for j in 0..segments {
        let (a, b) = (j, (j + 1) % segments);
        let (c, d) = (b + segments, a + segments);
        indices.push([a, b, c]);
        indices.push([a, c, d]);
    }
    // Caps: centre plus rim, fans wound to face +Z (top) and -Z (bottom).
    for (z, n) in [(top, Vec3::Z), (bottom, Vec3::NEG_Z)] {
        let centre = positions.len() as u32;
        positions.push(Vec3::new(0.0, 0.0, z));
        normals.push(n);
        for &(c, s) in &rim {
            positions.push(Vec3::new(radius * c, radius * s, z));
            normals.push(n);
        }
        for j in 0..segments {
            let (a, b) = (centre + 1 + j, centre + 1 + (j + 1) % segments);
            indices.push(if n.z > 0.0 { [centre, a, b] } else { [centre, b, a] });
        }
    }
    Ok(Mesh { positions, normals: Some(normals), indices })
}

/// A capsule along Z centred at the origin: a cylinder of `length` (>= 0) capped by two
/// hemispheres of `radius`, total height `length + 2 radius`, smooth everywhere.
/// `segments` >= 3 around, `rings` >= 1 per hemisphere.
pub fn capsule(radius: f32, length: f32, segments: u32, rings: u32) -> Result<Mesh, ShapeError> {
    positive("capsule radius", radius)?;
    if !(length.is_finite() && length >= 0.0) {
        return Err(ShapeError::Inconsistent(format!("capsule length {length} must be finite and >= 0")));
    }
    let segments = at_least("capsule segments", segments, 3)?;
    let rings = at_least("capsule rings", rings, 1)?;
    budget(&[2, u64::from(segments), 2 * u64::from(rings) + 1])?;
    let half = length * 0.5;
    // Upper hemisphere down to its equator (shifted up by half the length), then the lower
    // hemisphere from its equator (shifted down); the cylinder is the band between them.
    let mut profile = Vec::with_capacity(2 * rings as usize);
    for k in 1..=rings {
        let theta = 0.5 * PI * k as f32 / rings as f32;
        let n = Vec3::new(theta.sin(), 0.0, theta.cos());
        profile.push((n * radius + Vec3::Z * half, n));
    }
    // With no cylinder the two equators coincide: emit it once.
    let first = if half > 0.0 { 0 } else { 1 };
    for k in first..rings {
        let theta = 0.5 * PI + 0.5 * PI * k as f32 / rings as f32;
        let n = Vec3::new(theta.sin(), 0.0, theta.cos());
        profile.push((n * radius - Vec3::Z * half, n));
    }
    Ok(lathe(&profile, segments, Vec3::Z * (half + radius), Vec3::NEG_Z * (half + radius)))
}

/// A `width` x `height` rectangle in the XY plane, centred at the origin, facing +Z.
pub fn quad(width: f32, height: f32) -> Result<Mesh, ShapeError> {
    positive("quad width", width)?;
    positive("quad height", height)?;
    let (w, h) = (width * 0.5, height * 0.5);
    Ok(Mesh {
        positions: vec![Vec3::new(-w, -h, 0.0), Vec3::new(w, -h, 0.0), Vec3::new(w, h, 0.0), Vec3::new(-w, h, 0.0)],
        normals: Some(vec![Vec3::Z; 4]),
        indices: vec![[0, 1, 2], [0, 2, 3]],
    })
}

/// A disc of `radius` in the XY plane, centred at the origin, facing +Z; `segments` >= 3.
pub fn disc(radius: f32, segments: u32) -> Result<Mesh, ShapeError> {
    positive("disc radius", radius)?;
    let segments = at_least("disc segments", segments, 3)?;
    budget(&[u64::from(segments)])?;
    let mut positions = vec![Vec3::ZERO];
    positions.extend((0..segments).map(|j| {
        let phi = TAU * j as f32 / segments as f32;
        Vec3::new(radius * phi.cos(), radius * phi.sin(), 0.0)
    }));
    let indices = (0..segments).map(|j| [0, 1 + j, 1 + (j + 1) % segments]).collect();
    Ok(Mesh { normals: Some(vec![Vec3::Z; positions.len()]), positions, indices })
}

/// A rectangular opening in a [`wall_with_openings`], in the wall's local coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Opening {
    pub min: Vec2,
    pub max: Vec2,
}

/// A `width` x `height` wall in the XY plane (`x` in `[0, width]`, `y` in `[0, height]`),
/// facing +Z, with rectangular holes. The wall is a grid cut at every opening edge, so
/// neighbouring cells share whole edges (no T-junctions). Openings must lie strictly inside
/// the wall; overlapping openings simply merge.
pub fn wall_with_openings(width: f32, height: f32, openings: &[Opening]) -> Result<Mesh, ShapeError> {
    positive("wall width", width)?;
    positive("wall height", height)?;
    let mut xs = vec![0.0, width];
    let mut ys = vec![0.0, height];
    for o in openings {
        let inside = o.min.is_finite()
            && o.max.is_finite()
            && o.min.x > 0.0
            && o.min.y > 0.0
            && o.max.x < width
            && o.max.y < height
            && o.min.x < o.max.x
            && o.min.y < o.max.y;
        if !inside {
            return Err(ShapeError::Inconsistent(format!(
                "opening {:?}..{:?} must be a non-empty rectangle strictly inside the {width} x {height} wall",
                o.min, o.max
            )));
        }
        xs.extend([o.min.x, o.max.x]);
        ys.extend([o.min.y, o.max.y]);
    }
    let holes: Vec<[f32; 4]> = openings.iter().map(|o| [o.min.x, o.max.x, o.min.y, o.max.y]).collect();
    grid_panel(&xs, &ys, &holes)
}

/// A flat panel in the XY plane facing +Z, cut into a grid along the (sorted, deduplicated)
/// `xs` and `ys`; cells whose centre lies in one of the `holes` (`[x0, x1, y0, y1]`) are
/// left out. Vertices are the exact cut values, so panels built from the same cut lists
/// meet edge to edge.
pub(crate) fn grid_panel(xs: &[f32], ys: &[f32], holes: &[[f32; 4]]) -> Result<Mesh, ShapeError> {
    let clean = |v: &[f32]| -> Result<Vec<f32>, ShapeError> {
        if v.iter().any(|x| !x.is_finite()) {
            return Err(ShapeError::NotFinite { what: "panel cut" });
        }
        let mut v = v.to_vec();
        v.sort_by(f32::total_cmp);
        v.dedup();
        Ok(v)
    };
    let (xs, ys) = (clean(xs)?, clean(ys)?);
    at_least("panel columns", xs.len().saturating_sub(1) as u32, 1)?;
    at_least("panel rows", ys.len().saturating_sub(1) as u32, 1)?;
    budget(&[2, xs.len() as u64, ys.len() as u64])?;
    let nx = xs.len() as u32;
    let positions: Vec<Vec3> = ys.iter().flat_map(|&y| xs.iter().map(move |&x| Vec3::new(x, y, 0.0))).collect();
    let mut indices = Vec::new();
    for j in 0..ys.len() - 1 {
        for i in 0..xs.len() - 1 {
            let cx = 0.5 * (xs[i] + xs[i + 1]);
            let cy = 0.5 * (ys[j] + ys[j + 1]);
            if holes.iter().any(|h| cx > h[0] && cx < h[1] && cy > h[2] && cy < h[3]) {
                continue;
            }
            let (i, j) = (i as u32, j as u32);
            let (a, b, c, d) = (j * nx + i, j * nx + i + 1, (j + 1) * nx + i + 1, (j + 1) * nx + i);
            indices.push([a, b, c]);
            indices.push([a, c, d]);
        }
    }
    Ok(Mesh { normals: Some(vec![Vec3::Z; positions.len()]), positions, indices })
}

/// Shape of one fibre: a flat ribbon tapering from `root_width` to `tip_width`, following
/// a quadratic Bezier curve, cut into `segments` quads (1 to 3, so 2 to 6 triangles).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fibre {
    pub root: Vec3,
    /// Unit direction the fibre leaves the root in.
    pub direction: Vec3,
    /// Sideways displacement of the tip, as a fraction of the length (the fibre's curl).
    pub bend: Vec3,
    /// The ribbon's width direction at the root (made perpendicular to the path).
    pub side: Vec3,
    pub length: f32,
    pub root_width: f32,
    pub tip_width: f32,
    pub segments: u32,
}

/// The most quads per fibre.
pub const MAX_FIBRE_SEGMENTS: u32 = 3;

/// One fibre as a mesh (see [`Fibre`]).
pub fn fibre(spec: &Fibre) -> Result<Mesh, ShapeError> {
    let mut mesh = Mesh { normals: Some(Vec::new()), ..Mesh::default() };
    push_fibre(&mut mesh, spec)?;
    Ok(mesh)
}

fn push_fibre(mesh: &mut Mesh, spec: &Fibre) -> Result<(), ShapeError> {
    finite("fibre root", spec.root)?;
    finite("fibre bend", spec.bend)?;
    positive("fibre length", spec.length)?;
    positive("fibre root width", spec.root_width)?;
    if !(spec.tip_width.is_finite() && spec.tip_width >= 0.0) {
        return Err(ShapeError::Inconsistent(format!("fibre tip width {} must be finite and >= 0", spec.tip_width)));
    }
    let segments = at_least("fibre segments", spec.segments, 1)?;
    at_most("fibre segments", segments, MAX_FIBRE_SEGMENTS)?;
    let dir = finite("fibre direction", spec.direction)?.normalize_or_zero();
    if dir == Vec3::ZERO {
        return Err(ShapeError::Inconsistent("fibre direction must not be zero".into()));
    }
    let p0 = spec.root;
    let p1 = p0 + dir * (0.5 * spec.length);
    let p2 = p0 + (dir + spec.bend).normalize_or(dir) * spec.length;
    let mut side = finite("fibre side", spec.side)?;
    let normals = mesh.normals.get_or_insert_with(Vec::new);
    let base = mesh.positions.len() as u32;
    for k in 0..=segments {
        let t = k as f32 / segments as f32;
        let point = p0 * (1.0 - t) * (1.0 - t) + p1 * 2.0 * t * (1.0 - t) + p2 * t * t;
        let tangent = ((p1 - p0) * (1.0 - t) + (p2 - p1) * t).normalize_or(dir);
        // Keep the width direction perpendicular to the path as it bends.
        side = (side - tangent * side.dot(tangent)).normalize_or(tangent.any_orthonormal_vector());
        let half = 0.5 * (spec.root_width + (spec.tip_width - spec.root_width) * t);
        mesh.positions.push(point - side * half);
        mesh.positions.push(point + side * half);
        // Matches the winding below: (right - left) x (up the fibre) = side x tangent.
        let n = side.cross(tangent);
        normals.extend([n, n]);
    }
    for k in 0..segments {
        let (l0, r0, l1, r1) = (base + 2 * k, base + 2 * k + 1, base + 2 * k + 2, base + 2 * k + 3);
        mesh.indices.push([l0, r0, r1]);
        mesh.indices.push([l0, r1, l1]);
    }
    Ok(())
}

/// Parameters of [`fur_on_sphere`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fur {
    /// Number of fibres.
    pub count: u32,
    /// Fibre lengths are uniform in `[min_length, max_length]`.
    pub min_length: f32,
    pub max_length: f32,
    pub root_width: f32,
    pub tip_width: f32,
    /// Quads per fibre, 1 to 3.
    pub segments: u32,
    /// Largest angle between a fibre's root direction and the surface normal, radians
    /// (below pi/2).
    pub max_tilt: f32,
    /// Largest sideways bend of a tip, as a fraction of the fibre's length.
    pub curl: f32,
    /// Seed of the deterministic placement.
    pub seed: u64,
}

/// `fur.count` fibres rooted uniformly at random (deterministically, from `fur.seed`) on a
/// sphere of `radius` centred at the origin, growing outwards. Roots sit just below the
/// surface so no gap shows. Only the fibres are returned; add the sphere itself separately.
/// Every vertex lies within `radius + fur.max_length + fur.root_width` of the origin.
pub fn fur_on_sphere(radius: f32, fur: &Fur) -> Result<Mesh, ShapeError> {
    positive("fur sphere radius", radius)?;
    at_least("fibre count", fur.count, 1)?;
    positive("fibre min length", fur.min_length)?;
    positive("fibre max length", fur.max_length)?;
    if fur.min_length > fur.max_length {
        return Err(ShapeError::Inconsistent(format!(
            "fibre min length {} exceeds max length {}",
            fur.min_length, fur.max_length
        )));
    }
    if !(fur.max_tilt.is_finite() && (0.0..PI / 2.0).contains(&fur.max_tilt)) {
        return Err(ShapeError::Inconsistent(format!("fibre tilt {} must lie in [0, pi/2)", fur.max_tilt)));
    }
    if !(fur.curl.is_finite() && fur.curl >= 0.0) {
        return Err(ShapeError::Inconsistent(format!("fibre curl {} must be >= 0", fur.curl)));
    }
    at_most("fibre segments", fur.segments, MAX_FIBRE_SEGMENTS)?;
    budget(&[u64::from(fur.count), 2, u64::from(fur.segments)])?;
    let mut rng = SplitMix64::new(fur.seed);
    let verts = fur.count as usize * 2 * (fur.segments as usize + 1);
    let mut mesh = Mesh {
        positions: Vec::with_capacity(verts),
        normals: Some(Vec::with_capacity(verts)),
        indices: Vec::with_capacity(fur.count as usize * 2 * fur.segments as usize),
    };
    for _ in 0..fur.count {
        let normal = rng.unit_vector();
        let (t1, t2) = normal.any_orthonormal_pair();
        let around = |rng: &mut SplitMix64| {
            let a = TAU * rng.next_f32();
            t1 * a.cos() + t2 * a.sin()
        };
        let tilt = fur.max_tilt * rng.next_f32();
        let direction = normal * tilt.cos() + around(&mut rng) * tilt.sin();
        let bend = around(&mut rng) * (fur.curl * rng.next_f32());
        let side = around(&mut rng);
        let length = fur.min_length + (fur.max_length - fur.min_length) * rng.next_f32();
        push_fibre(
            &mut mesh,
            &Fibre {
                root: normal * (radius * 0.995),
                direction,
                bend,
                side,
                length,
                root_width: fur.root_width,
                tip_width: fur.tip_width,
                segments: fur.segments,
            },
        )?;
    }
    Ok(mesh)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::collections::HashMap;

    /// Welds bit-identical positions (with -0 == +0) and returns each triangle's vertex ids.
    pub(crate) fn welded(mesh: &Mesh) -> Vec<[u32; 3]> {
        let key = |p: Vec3| (p + Vec3::ZERO).to_array().map(f32::to_bits);
        let mut ids: HashMap<[u32; 3], u32> = HashMap::new();
        let remap: Vec<u32> = mesh
            .positions
            .iter()
            .map(|&p| {
                let next = ids.len() as u32;
                *ids.entry(key(p)).or_insert(next)
            })
            .collect();
        mesh.indices.iter().map(|t| t.map(|i| remap[i as usize])).collect()
    }

    /// Directed edges that do not have exactly one opposite partner, after welding. Empty
    /// means closed (every edge shared by exactly two triangles) and consistently wound.
    pub(crate) fn open_edges(mesh: &Mesh) -> Vec<(u32, u32)> {
        let tris = welded(mesh);
        let mut directed: HashMap<(u32, u32), i32> = HashMap::new();
        for t in &tris {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        let mut bad: Vec<(u32, u32)> = directed
            .iter()
            .filter(|&(&(a, b), &count)| count != 1 || directed.get(&(b, a)) != Some(&1))
            .map(|(&e, _)| e)
            .collect();
        bad.sort_unstable();
        bad
    }

    pub(crate) fn signed_volume(mesh: &Mesh) -> f32 {
        mesh.indices
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    /// Shading normals agree with the winding (no triangle's normals point inwards).
    fn normals_agree(mesh: &Mesh) -> bool {
        let normals = mesh.normals.as_ref().expect("normals");
        mesh.indices.iter().all(|t| {
            let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
            let g = (b - a).cross(c - a);
            t.iter().all(|&i| normals[i as usize].dot(g) > 0.0)
        })
    }

    fn assert_closed_outward(name: &str, mesh: &Mesh, volume: f32, tolerance: f32) {
        mesh.validate().expect("valid mesh");
        assert!(open_edges(mesh).is_empty(), "{name}: open or inconsistent edges");
        let v = signed_volume(mesh);
        assert!(v > 0.0, "{name}: signed volume {v} not positive");
        assert!((v - volume).abs() <= tolerance * volume, "{name}: volume {v}, expected {volume}");
        assert!(normals_agree(mesh), "{name}: shading normals disagree with winding");
        let n = mesh.normals.as_ref().expect("normals");
        assert!(n.iter().all(|n| (n.length() - 1.0).abs() < 1e-4), "{name}: unit normals");
    }

    #[test]
    fn closed_meshes_are_watertight_and_outward() {
        let sphere_v = |r: f32| 4.0 / 3.0 * PI * r * r * r;
        assert_closed_outward("uv sphere", &uv_sphere(1.5, 48, 24).expect("ok"), sphere_v(1.5), 0.02);
        assert_closed_outward("icosphere", &icosphere(0.7, 4).expect("ok"), sphere_v(0.7), 0.01);
        assert_closed_outward("icosphere0", &icosphere(1.0, 0).expect("ok"), sphere_v(1.0), 0.5);
        assert_closed_outward("box", &cuboid(Vec3::new(1.0, 2.0, 3.0)).expect("ok"), 6.0, 1e-5);
        let torus_v = |big: f32, small: f32| 2.0 * PI * PI * big * small * small;
        assert_closed_outward("torus", &torus(1.0, 0.3, 96, 32).expect("ok"), torus_v(1.0, 0.3), 0.02);
        let knot = torus_knot(2, 3, 1.2, 0.18, 512, 24).expect("ok");
        // Tube volume ~ pi r^2 times the length of the centre line.
        let ring: Vec<Vec3> = (0..512)
            .map(|i| {
                let k = 24 * i as usize;
                knot.positions[k..k + 24].iter().copied().sum::<Vec3>() / 24.0
            })
            .collect();
        let length: f32 = (0..512).map(|i| ring[i].distance(ring[(i + 1) % 512])).sum();
        assert_closed_outward("knot", &knot, PI * 0.18 * 0.18 * length, 0.03);
        let cyl = cylinder(0.5, 2.0, 40).expect("ok");
        assert_closed_outward("cylinder", &cyl, PI * 0.25 * 2.0, 0.02);
        let cap = capsule(0.5, 1.0, 40, 12).expect("ok");
        assert_closed_outward("capsule", &cap, PI * 0.25 * 1.0 + sphere_v(0.5), 0.02);
        let cap0 = capsule(0.5, 0.0, 16, 1).expect("ok");
        assert!(open_edges(&cap0).is_empty() && signed_volume(&cap0) > 0.0);
    }

    #[test]
    fn flipped_mesh_faces_inwards() {
        let s = icosphere(1.0, 2).expect("ok");
        let f = flipped(&s);
        assert!(open_edges(&f).is_empty());
        assert!(signed_volume(&f) < 0.0);
        assert!(normals_agree(&f));
    }

    #[test]
    fn knot_closes_without_seam_twist() {
        // The frame at the end of the loop must match the start: no long skinny triangles.
        let knot = torus_knot(3, 2, 1.0, 0.1, 300, 12).expect("ok");
        let max_edge = knot
            .indices
            .iter()
            .flat_map(|t| {
                let [a, b, c] = t.map(|i| knot.positions[i as usize]);
                [a.distance(b), b.distance(c), c.distance(a)]
            })
            .fold(0.0f32, f32::max);
        assert!(max_edge < 0.1, "longest edge {max_edge}");
        let r = knot.positions.iter().map(|p| p.truncate().length()).fold(0.0f32, f32::max);
        assert!(r <= 1.1 + 1e-4, "knot within radius + tube, got {r}");
    }

    #[test]
    fn flat_shapes_face_up() {
        for mesh in [
            quad(2.0, 1.0).expect("ok"),
            disc(1.0, 12).expect("ok"),
            wall_with_openings(5.0, 2.8, &[Opening { min: Vec2::new(1.0, 1.0), max: Vec2::new(2.0, 2.0) }])
                .expect("ok"),
        ] {
            mesh.validate().expect("valid");
            assert!(normals_agree(&mesh));
            for t in &mesh.indices {
                let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
                assert!((b - a).cross(c - a).z > 0.0);
            }
        }
        let wall = wall_with_openings(5.0, 2.8, &[Opening { min: Vec2::new(1.0, 1.0), max: Vec2::new(2.0, 2.0) }])
            .expect("ok");
        let area: f32 = wall
            .indices
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| wall.positions[i as usize]);
                0.5 * (b - a).cross(c - a).length()
            })
            .sum();
        assert!((area - (14.0 - 1.0)).abs() < 1e-4, "wall area {area}");
        // The only open edges are the outline of the 3 x 3 cell grid (12 cell edges) and
        // the hole's 4.
        assert_eq!(open_edges(&wall).len(), 16);
    }

    #[test]
    fn fibres_are_thin_deterministic_and_bounded() {
        let spec = Fur {
            count: 500,
            min_length: 0.2,
            max_length: 0.3,
            root_width: 0.002,
            tip_width: 0.0005,
            segments: 3,
            max_tilt: 0.5,
            curl: 0.3,
            seed: 7,
        };
        let a = fur_on_sphere(0.5, &spec).expect("ok");
        let b = fur_on_sphere(0.5, &spec).expect("ok");
        assert_eq!(a, b, "same seed, same fur");
        assert_eq!(a.triangle_count(), 500 * 6);
        a.validate().expect("valid");
        assert!(a.positions.iter().all(|p| p.length() <= 0.5 + 0.3 + 1e-4));
        assert!(normals_agree(&a));
        // Width stays within the ribbon's root width.
        for pair in a.positions.chunks(2) {
            assert!(pair[0].distance(pair[1]) <= 0.002 + 1e-6);
        }
        let other = fur_on_sphere(0.5, &Fur { seed: 8, ..spec }).expect("ok");
        assert_ne!(a, other, "different seed, different fur");
        let single = fibre(&Fibre {
            root: Vec3::ZERO,
            direction: Vec3::Z,
            bend: Vec3::X * 0.2,
            side: Vec3::Y,
            length: 0.1,
            root_width: 0.003,
            tip_width: 0.001,
            segments: 1,
        })
        .expect("ok");
        assert_eq!(single.triangle_count(), 2);
    }

    #[test]
    fn nonsense_arguments_are_errors_not_panics() {
        assert!(matches!(uv_sphere(1.0, 0, 8), Err(ShapeError::TooFew { .. })));
        assert!(matches!(uv_sphere(1.0, 8, 1), Err(ShapeError::TooFew { .. })));
        assert!(matches!(uv_sphere(f32::NAN, 8, 8), Err(ShapeError::NotPositive { .. })));
        assert!(matches!(uv_sphere(1.0, u32::MAX, u32::MAX), Err(ShapeError::TooLarge { .. })));
        assert!(matches!(icosphere(-1.0, 2), Err(ShapeError::NotPositive { .. })));
        assert!(matches!(icosphere(1.0, 99), Err(ShapeError::TooMany { .. })));
        assert!(matches!(cuboid(Vec3::new(1.0, 0.0, 1.0)), Err(ShapeError::NotPositive { .. })));
        assert!(matches!(cuboid(Vec3::INFINITY), Err(ShapeError::NotPositive { .. })));
        assert!(matches!(torus(1.0, 2.0, 8, 8), Err(ShapeError::Inconsistent(_))));
        assert!(matches!(torus(1.0, 0.2, 0, 8), Err(ShapeError::TooFew { .. })));
        assert!(matches!(torus_knot(2, 4, 1.0, 0.1, 64, 8), Err(ShapeError::Inconsistent(_))));
        assert!(matches!(torus_knot(0, 3, 1.0, 0.1, 64, 8), Err(ShapeError::TooFew { .. })));
        assert!(matches!(torus_knot(2, 3, 1.0, 0.5, 64, 8), Err(ShapeError::Inconsistent(_))));
        assert!(matches!(torus_knot(2, 3, 1.0, 0.1, 2, 8), Err(ShapeError::TooFew { .. })));
        assert!(matches!(cylinder(1.0, 1.0, 2), Err(ShapeError::TooFew { .. })));
        assert!(matches!(capsule(1.0, -1.0, 8, 2), Err(ShapeError::Inconsistent(_))));
        assert!(matches!(capsule(1.0, 1.0, 8, 0), Err(ShapeError::TooFew { .. })));
        assert!(matches!(quad(0.0, 1.0), Err(ShapeError::NotPositive { .. })));
        assert!(matches!(disc(1.0, 0), Err(ShapeError::TooFew { .. })));
        let bad = Opening { min: Vec2::new(-1.0, 0.5), max: Vec2::new(1.0, 1.0) };
        assert!(matches!(wall_with_openings(2.0, 2.0, &[bad]), Err(ShapeError::Inconsistent(_))));
        let fur = Fur {
            count: 0,
            min_length: 0.1,
            max_length: 0.2,
            root_width: 0.001,
            tip_width: 0.0,
            segments: 2,
            max_tilt: 0.3,
            curl: 0.1,
            seed: 1,
        };
        assert!(matches!(fur_on_sphere(1.0, &fur), Err(ShapeError::TooFew { .. })));
        let fur = Fur { count: 10, segments: 0, ..fur };
        assert!(matches!(fur_on_sphere(1.0, &fur), Err(ShapeError::TooFew { .. })));
        let fur = Fur { segments: 9, ..fur };
        assert!(matches!(fur_on_sphere(1.0, &fur), Err(ShapeError::TooMany { .. })));
        let fur = Fur { segments: 2, min_length: 0.5, ..fur };
        assert!(matches!(fur_on_sphere(1.0, &fur), Err(ShapeError::Inconsistent(_))));
        let zero_dir = Fibre {
            root: Vec3::ZERO,
            direction: Vec3::ZERO,
            bend: Vec3::ZERO,
            side: Vec3::X,
            length: 1.0,
            root_width: 0.01,
            tip_width: 0.0,
            segments: 2,
        };
        assert!(matches!(fibre(&zero_dir), Err(ShapeError::Inconsistent(_))));
    }
}
