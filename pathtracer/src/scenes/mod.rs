//! Built-in procedural scenes, looked up by name, each with a framing that tells the
//! dataset generator and the CLI where cameras may stand.
//!
//! Object scenes follow NeRF-synthetic: one object (or a small group) floating at the
//! origin with no ground unless it needs one, inside a sphere of radius <= 1.5, lit by a
//! sky and a sun, seen by cameras orbiting at 4 m. The rooms are interiors lit through
//! their windows (day) or by lamps (night). "furnace" is the white-furnace test scene.
//!
//! | name         | content                                                       |
//! |--------------|---------------------------------------------------------------|
//! | `diffuse`    | an orange matte trefoil knot                                  |
//! | `glossy`     | a polished gold torus around a glossy plastic ball            |
//! | `furry`      | a ball covered in 16,000 thin fibres                          |
//! | `shell`      | a thin glass sphere around a cube and a ring                  |
//! | `room-day`   | a furnished room, sun and sky through two windows             |
//! | `room-night` | the same room at night, lit by a ceiling lamp and a table lamp|
//! | `assembly`   | smaller versions of the four objects on a matte ground disc   |
//! | `furnace`    | a white (albedo 1) sphere under uniform light                 |
//!
//! Every scene is deterministic: the same name always builds the same triangles.

mod objects;
mod room;
pub mod shapes;

use glam::{Affine3A, Quat, Vec2, Vec3};
use thiserror::Error;

use crate::{Background, Environment, Material, Scene, SceneBuilder, Sun, scene::SceneError};
use objects::{Parts, add_parts, parts_bounds};
use shapes::{Fur, ShapeError};

/// Where cameras go for a built-in scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Framing {
    /// An object centred at `center`, fits in a sphere of `radius`; dataset cameras orbit at
    /// `orbit_radius`, on the upper hemisphere only if `hemisphere` (an object standing on
    /// a ground).
    Object { center: Vec3, radius: f32, orbit_radius: f32, hemisphere: bool },
    /// An interior: cameras stand inside the box `[min, max]` (kept away from walls)
    /// looking at `look_at` by default.
    Interior { min: Vec3, max: Vec3, eye: Vec3, look_at: Vec3 },
}

/// Vertical field of view of the default interior view, radians (about 66 degrees).
pub const INTERIOR_FOV_Y: f32 = 1.15;

impl Framing {
    /// A good first view: `(eye, target, vertical field of view in radians)`.
    ///
    /// For an object, the eye is on the orbit, 60 degrees clockwise from +X (seen from
    /// above) and 25 degrees above the horizon, looking at the centre, with the field of
    /// view that fits the bounding sphere plus a 5% margin (about 0.69-0.81 rad for the
    /// built-in objects, close to NeRF-synthetic's 0.69). For an interior, the stored eye
    /// and target with [`INTERIOR_FOV_Y`].
    pub fn default_view(&self) -> (Vec3, Vec3, f32) {
        match *self {
            Framing::Object { center, radius, orbit_radius, .. } => {
                let (azimuth, elevation) = ((-60f32).to_radians(), 25f32.to_radians());
                let dir = Vec3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
                let ratio = if orbit_radius > 0.0 { radius / orbit_radius } else { 1.0 };
                let fov = 2.0 * ratio.clamp(0.0, 0.95).asin() * 1.05;
                (center + dir * orbit_radius, center, fov)
            }
            Framing::Interior { eye, look_at, .. } => (eye, look_at, INTERIOR_FOV_Y),
        }
    }
}

/// A built-in scene, ready to render.
#[derive(Debug, Clone)]
pub struct BuiltinScene {
    pub name: &'static str,
    pub description: &'static str,
    pub scene: Scene,
    pub framing: Framing,
}

impl BuiltinScene {
    /// See [`Framing::default_view`].
    pub fn default_view(&self) -> (Vec3, Vec3, f32) {
        self.framing.default_view()
    }

    /// What camera rays that miss show by default: nothing (alpha 0, NeRF-synthetic style)
    /// around objects, the environment through the windows of interiors.
    pub fn default_background(&self) -> Background {
        match self.framing {
            Framing::Object { .. } => Background::Transparent,
            Framing::Interior { .. } => Background::Environment,
        }
    }

    /// Horizontal field of view of dataset cameras (NeRF's `camera_angle_x`), radians, for
    /// square images: the default view's field of view, which fits an object's bounding
    /// sphere seen from its orbit (0.69-0.81 rad for the built-in objects).
    pub fn dataset_fov_x(&self) -> f32 {
        self.default_view().2
    }

    /// Wraps a scene from elsewhere (e.g. [`crate::gltf_import::import_gltf`])
    /// as an object: centred on its bounding box, `radius` the farthest vertex from that
    /// centre, orbit at `radius * 8 / 3` (4 m for a 1.5 m object, as the built-ins), full
    /// sphere of views. Interiors cannot be told apart from objects here; frame those by
    /// hand.
    pub fn from_imported(scene: Scene) -> Result<BuiltinScene, SceneLookupError> {
        let unframeable = |reason: &str| SceneLookupError::Unframeable { reason: reason.into() };
        let (lo, hi) = scene.bounds().ok_or_else(|| unframeable("the scene has no vertices"))?;
        let center = (lo + hi) * 0.5;
        let radius = scene.mesh.positions.iter().map(|p| p.distance(center)).fold(0.0f32, f32::max);
        if !(radius.is_finite() && radius > 0.0) {
            return Err(unframeable("the scene has no extent"));
        }
        Ok(BuiltinScene {
            name: "imported",
            description: "A scene imported from a file.",
            scene,
            framing: Framing::Object { center, radius, orbit_radius: radius * 8.0 / 3.0, hemisphere: false },
        })
    }
}

/// Why [`builtin`] gave no scene.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SceneLookupError {
    #[error("unknown built-in scene {name:?}; the built-in scenes are: {}", NAMES.join(", "))]
    Unknown { name: String },
    /// A generator refused its (fixed) arguments: a bug, reported rather than panicking.
    #[error("built-in scene {name:?} could not be built: {reason}")]
    Build { name: &'static str, reason: String },
    /// [`load`] could not import a glTF file.
    #[error("importing {path}: {reason}")]
    Import { path: String, reason: String },
    /// [`BuiltinScene::from_imported`] could not frame the scene.
    #[error("cannot frame the scene: {reason}")]
    Unframeable { reason: String },
}

/// Internal failure while assembling a scene.
#[derive(Debug, Error)]
pub(crate) enum BuildFailure {
    #[error(transparent)]
    Shape(#[from] ShapeError),
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error("scene {0:?} is listed but has no builder")]
    Unlisted(String),
}

/// Name and description of every built-in scene, in listing order.
const CATALOGUE: [(&str, &str); 8] = [
    ("diffuse", "An orange matte (Lambertian) trefoil knot floating in daylight."),
    (
        "glossy",
        "A polished gold torus (roughness 0.18) around a glossy blue plastic ball \
         (roughness 0.12): strong view-dependent highlights.",
    ),
    ("furry", "A brown ball covered in 16,000 thin (0.8-2.5 mm) curved fibres: fine, fuzzy detail."),
    (
        "shell",
        "A thin-walled glass sphere (ior 1.5, faint tint) around a blue cube and a red ring: \
         rays cross the glass twice before reaching the solid content.",
    ),
    ("room-day", "A furnished 5 x 4 x 2.8 m room lit by the sun and the sky through two windows."),
    ("room-night", "The same room at night: a ceiling lamp, a table lamp, a dark blue sky outside."),
    (
        "assembly",
        "Smaller versions of the knot, the glossy pair, the furry ball and the glass shell \
         standing on a matte ground disc.",
    ),
    (
        "furnace",
        "A closed white (albedo 1) sphere under uniform light 0.5: every pixel on it must \
         come out at 0.5.",
    ),
];

const NAMES: [&str; CATALOGUE.len()] = {
    let mut names = [""; CATALOGUE.len()];
    let mut i = 0;
    while i < names.len() {
        names[i] = CATALOGUE[i].0;
        i += 1;
    }
    names
};

/// The names [`builtin`] accepts.
pub fn names() -> &'static [&'static str] {
    &NAMES
}

/// A built-in scene by name, or a glTF file (a path ending in `.gltf` / `.glb`) framed as
/// one: what every command that takes `--scene` accepts.
pub fn load(name_or_path: &str) -> Result<BuiltinScene, SceneLookupError> {
    let lower = name_or_path.to_ascii_lowercase();
    if lower.ends_with(".gltf") || lower.ends_with(".glb") {
        let path = std::path::Path::new(name_or_path);
        let scene = crate::gltf_import::import_gltf(path)
            .map_err(|e| SceneLookupError::Import { path: path.display().to_string(), reason: e.to_string() })?;
        return BuiltinScene::from_imported(scene);
    }
    builtin(name_or_path)
}

/// Names of the built-in scenes that move ([`builtin_at`] gives them at a time).
pub const ANIMATED: [&str; 2] = ["room-day", "room-night"];

/// The built-in scene `name` at `time` seconds into its animation: in the rooms the floor
/// ball rolls around a loop ([`BALL_PERIOD_S`] seconds); the other scenes are still and
/// ignore `time`. `builtin_at(name, 0.0)` is `builtin(name)`.
pub fn builtin_at(name: &str, time: f32) -> Result<BuiltinScene, SceneLookupError> {
    match CATALOGUE.iter().find(|(n, _)| *n == name) {
        Some(&(name, description)) if time != 0.0 && ANIMATED.contains(&name) => {
            let scene = room::room(name == "room-night", time)
                .map_err(|e| SceneLookupError::Build { name, reason: e.to_string() })?;
            Ok(BuiltinScene { name, description, scene, framing: room::framing() })
        }
        _ => builtin(name),
    }
}

/// Seconds the rooms' floor ball takes to roll once around its loop.
pub const BALL_PERIOD_S: f32 = room::BALL_PERIOD_S;

/// Builds the built-in scene called `name` (see [`names`]).
pub fn builtin(name: &str) -> Result<BuiltinScene, SceneLookupError> {
    let Some(&(name, description)) = CATALOGUE.iter().find(|(n, _)| *n == name) else {
        return Err(SceneLookupError::Unknown { name: name.to_owned() });
    };
    let (scene, framing) = build(name).map_err(|e| SceneLookupError::Build { name, reason: e.to_string() })?;
    Ok(BuiltinScene { name, description, scene, framing })
}

fn build(name: &str) -> Result<(Scene, Framing), BuildFailure> {
    match name {
        "diffuse" => object(objects::knot()?, objects::KNOT_RADIUS + 0.02),
        "glossy" => object(objects::glossy_pair()?, objects::GLOSSY_RADIUS + 0.02),
        "furry" => object(
            objects::fur_ball(objects::FUR_CORE_RADIUS, &objects::FUR)?,
            objects::FUR_CORE_RADIUS + objects::FUR.max_length + 0.03,
        ),
        "shell" => object(objects::glass_shell()?, objects::SHELL_RADIUS + 0.05),
        "room-day" => Ok((room::room(false, 0.0)?, room::framing())),
        "room-night" => Ok((room::room(true, 0.0)?, room::framing())),
        "assembly" => {
            let framing = Framing::Object {
                center: ASSEMBLY_CENTER,
                radius: ASSEMBLY_RADIUS,
                orbit_radius: 4.0,
                hemisphere: true,
            };
            Ok((assembly()?, framing))
        }
        "furnace" => {
            let framing = Framing::Object { center: Vec3::ZERO, radius: 1.0, orbit_radius: 4.0, hemisphere: false };
            Ok((furnace()?, framing))
        }
        other => Err(BuildFailure::Unlisted(other.to_owned())),
    }
}

/// The sky of the daylight scenes: blue overhead, pale at the horizon, brownish below.
pub fn daylight_sky() -> Environment {
    Environment::Sky {
        zenith: Vec3::new(0.20, 0.33, 0.62),
        horizon: Vec3::new(0.60, 0.64, 0.68),
        ground: Vec3::new(0.26, 0.24, 0.21),
    }
}

/// The sun of the daylight scenes: from the south-south-east (-Y is south), 34 degrees
/// up, slightly warm, with a disc of 1.1 degrees radius for soft-ish shadows.
pub fn daylight_sun() -> Sun {
    Sun {
        direction: Vec3::new(0.35, -0.8, 0.6).normalize(),
        irradiance: Vec3::new(2.6, 2.45, 2.2),
        angular_radius: 0.02,
    }
}

/// A single object at the origin, in daylight, floating (no ground).
fn object(parts: Parts, radius: f32) -> Result<(Scene, Framing), BuildFailure> {
    let mut b = SceneBuilder::new();
    add_parts(&mut b, &parts, Affine3A::IDENTITY);
    b.environment(daylight_sky());
    b.sun(daylight_sun());
    let framing = Framing::Object { center: Vec3::ZERO, radius, orbit_radius: 4.0, hemisphere: false };
    Ok((b.build()?, framing))
}

fn furnace() -> Result<Scene, BuildFailure> {
    let mut b = SceneBuilder::new();
    add_parts(&mut b, &objects::furnace_sphere()?, Affine3A::IDENTITY);
    b.environment(Environment::Uniform(Vec3::splat(0.5)));
    Ok(b.build()?)
}

const ASSEMBLY_GROUND_RADIUS: f32 = 1.45;
const ASSEMBLY_CENTER: Vec3 = Vec3::new(0.0, 0.0, 0.25);
const ASSEMBLY_RADIUS: f32 = 1.5;

/// Adds `parts` scaled, rotated, centred over `xy` and resting on the plane `z = floor`.
fn place(
    b: &mut SceneBuilder,
    parts: &Parts,
    scale: f32,
    rotation: Quat,
    xy: Vec2,
    floor: f32,
) -> Result<(), BuildFailure> {
    let local = Affine3A::from_scale_rotation_translation(Vec3::splat(scale), rotation, Vec3::ZERO);
    let (lo, hi) = parts_bounds(parts, local).ok_or(SceneError::Empty)?;
    let centre = (lo + hi) * 0.5;
    let shift = Vec3::new(xy.x - centre.x, xy.y - centre.y, floor - lo.z);
    add_parts(b, parts, Affine3A::from_translation(shift) * local);
    Ok(())
}

fn assembly() -> Result<Scene, BuildFailure> {
    let mut b = SceneBuilder::new();
    b.add(&shapes::disc(ASSEMBLY_GROUND_RADIUS, 128)?, Affine3A::IDENTITY, Material::lambertian(Vec3::splat(0.5)));
    place(&mut b, &objects::knot()?, 0.4, Quat::from_rotation_z(0.4), Vec2::new(-0.65, 0.55), 0.0)?;
    place(&mut b, &objects::glossy_pair()?, 0.4, Quat::IDENTITY, Vec2::new(0.65, 0.55), 0.0)?;
    // A small ball with shorter, fewer fibres (the fibres keep their real thickness), resting
    // on the tips of its fur.
    let fur = Fur {
        count: 3_000,
        min_length: 0.06,
        max_length: 0.1,
        root_width: 0.002,
        tip_width: 0.0006,
        segments: 2,
        ..objects::FUR
    };
    place(&mut b, &objects::fur_ball(0.2, &fur)?, 1.0, Quat::IDENTITY, Vec2::new(-0.6, -0.6), 0.0)?;
    // The glass shell sits 3 mm above a dark pedestal so that no glass surface crosses
    // another surface.
    let pedestal = 0.06;
    b.add(
        &shapes::cylinder(0.14, pedestal, 48)?,
        Affine3A::from_translation(Vec3::new(0.6, -0.6, pedestal * 0.5)),
        Material::lambertian(Vec3::new(0.2, 0.2, 0.22)),
    );
    place(&mut b, &objects::glass_shell()?, 0.3, Quat::IDENTITY, Vec2::new(0.6, -0.6), pedestal + 0.003)?;
    b.environment(daylight_sky());
    b.sun(daylight_sun());
    Ok(b.build()?)
}

#[cfg(test)]
mod tests {
    use super::shapes::tests::{open_edges, signed_volume};
    use super::*;
    use crate::Mesh;

    fn all() -> Vec<BuiltinScene> {
        names().iter().map(|n| builtin(n).expect("built-in scene builds")).collect()
    }

    #[test]
    fn every_name_resolves_validates_and_stays_small() {
        for s in all() {
            assert!(names().contains(&s.name));
            s.scene.validate().expect("valid scene");
            let n = s.scene.triangle_count();
            assert!((12..200_000).contains(&n), "{}: {n} triangles", s.name);
            assert_eq!(s.scene.material_of_triangle.len(), n);
            assert!(!s.description.is_empty());
            let normals = s.scene.mesh.normals.as_ref().expect("shading normals everywhere");
            assert!(normals.iter().all(|n| n.is_finite() && (n.length() - 1.0).abs() < 1e-3));
            let has_light = s.scene.sun.is_some()
                || !s.scene.environment.is_black()
                || s.scene.materials.iter().any(|m| matches!(m, Material::Emissive { .. }));
            assert!(has_light, "{} has no light", s.name);
            println!("{:<11} {n:>7} triangles", s.name);
        }
    }

    #[test]
    fn imported_scenes_are_framed_around_their_bounds() {
        let mut b = SceneBuilder::new();
        let cube = shapes::cuboid(Vec3::splat(2.0)).expect("ok");
        b.add(&cube, Affine3A::from_translation(Vec3::new(5.0, 0.0, 1.0)), Material::lambertian(Vec3::ONE));
        let framed = BuiltinScene::from_imported(b.build().expect("valid")).expect("framed");
        let Framing::Object { center, radius, orbit_radius, hemisphere } = framed.framing else {
            panic!("object framing expected");
        };
        assert!((center - Vec3::new(5.0, 0.0, 1.0)).length() < 1e-5);
        assert!((radius - 3f32.sqrt()).abs() < 1e-5);
        assert!(orbit_radius > 2.0 * radius && !hemisphere);
        let (eye, target, fov) = framed.default_view();
        assert!((eye.distance(target) - orbit_radius).abs() < 1e-4 && fov > 0.3);
        let mut flat = Scene::clone(&framed.scene);
        flat.mesh.positions.iter_mut().for_each(|p| *p = Vec3::ONE);
        assert!(matches!(BuiltinScene::from_imported(flat), Err(SceneLookupError::Unframeable { .. })));
    }

    #[test]
    fn backgrounds_and_dataset_fov_follow_the_framing() {
        for s in all() {
            let interior = matches!(s.framing, Framing::Interior { .. });
            let expected = if interior { Background::Environment } else { Background::Transparent };
            assert_eq!(s.default_background(), expected, "{}", s.name);
            let fov = s.dataset_fov_x();
            assert!((0.5..1.3).contains(&fov), "{}: {fov}", s.name);
        }
    }

    #[test]
    fn scenes_are_deterministic() {
        let a = builtin("furry").expect("ok");
        let b = builtin("furry").expect("ok");
        assert_eq!(a.scene.mesh, b.scene.mesh);
    }

    #[test]
    fn every_listed_name_has_a_builder() {
        for name in names() {
            assert!(build(name).is_ok(), "{name}");
        }
        assert!(matches!(build("nope"), Err(BuildFailure::Unlisted(_))));
    }

    #[test]
    fn unknown_name_lists_the_valid_ones() {
        let err = builtin("teapot").expect_err("no teapot");
        assert_eq!(err, SceneLookupError::Unknown { name: "teapot".into() });
        let message = err.to_string();
        for n in names() {
            assert!(message.contains(n), "{message}");
        }
        assert!(builtin("").is_err());
        assert!(builtin("Diffuse").is_err(), "names are case sensitive");
    }

    #[test]
    fn object_scenes_fit_their_framing() {
        for s in all() {
            let (eye, target, fov) = s.default_view();
            assert!(eye.is_finite() && target.is_finite() && fov > 0.3 && fov < 1.6);
            match s.framing {
                Framing::Object { center, radius, orbit_radius, hemisphere } => {
                    let far = s.scene.mesh.positions.iter().map(|p| p.distance(center)).fold(0.0f32, f32::max);
                    assert!(far <= radius * (1.0 + 1e-5), "{}: vertex {far} from centre, radius {radius}", s.name);
                    assert!(radius <= 1.55 && orbit_radius > 2.0 * radius);
                    assert!((eye.distance(center) - orbit_radius).abs() < 1e-4);
                    assert!(eye.z > center.z);
                    // The bounding sphere fits in the default field of view.
                    assert!((radius / orbit_radius).asin() < fov / 2.0);
                    let (lo, _) = s.scene.bounds().expect("bounds");
                    if hemisphere {
                        assert!(lo.z >= -1e-4, "{}: nothing below the ground", s.name);
                    }
                }
                Framing::Interior { min, max, eye, look_at } => {
                    let (lo, hi) = s.scene.bounds().expect("bounds");
                    assert!(min.cmpgt(lo).all() && max.cmplt(hi).all(), "{}: box inside", s.name);
                    assert!(eye.cmpge(min).all() && eye.cmple(max).all());
                    assert!(look_at.cmpgt(lo).all() && look_at.cmplt(hi).all());
                    assert!((lo - Vec3::new(-2.5, -2.0, 0.0)).length() < 1e-5);
                    assert!((hi - Vec3::new(2.5, 2.0, 2.8)).length() < 1e-5);
                }
            }
        }
    }

    /// The triangles of `scene` using a material that satisfies `pick`, as a mesh.
    fn triangles_where(s: &BuiltinScene, pick: impl Fn(&Material) -> bool) -> Mesh {
        let scene = &s.scene;
        let indices = scene
            .mesh
            .indices
            .iter()
            .zip(&scene.material_of_triangle)
            .filter(|&(_, &m)| pick(&scene.materials[m as usize]))
            .map(|(t, _)| *t)
            .collect();
        Mesh { positions: scene.mesh.positions.clone(), normals: None, indices }
    }

    #[test]
    fn furnace_sphere_is_white_closed_and_alone() {
        let s = builtin("furnace").expect("ok");
        assert_eq!(s.scene.materials, vec![Material::Lambertian { albedo: Vec3::ONE }]);
        assert_eq!(s.scene.environment, Environment::Uniform(Vec3::splat(0.5)));
        assert!(s.scene.sun.is_none());
        assert!(open_edges(&s.scene.mesh).is_empty());
        assert!(signed_volume(&s.scene.mesh) > 0.0);
        assert!(s.scene.mesh.positions.iter().all(|p| (p.length() - 1.0).abs() < 1e-5));
    }

    #[test]
    fn shell_is_a_closed_two_sided_glass_wall_around_solid_content() {
        for name in ["shell", "assembly"] {
            let s = builtin(name).expect("ok");
            let glass = triangles_where(&s, |m| matches!(m, Material::Dielectric { ior, .. } if *ior == 1.5));
            assert!(!glass.indices.is_empty(), "{name}: glass present");
            // Outer sphere outward plus inner sphere inward: closed, and the enclosed volume
            // is the wall's (outer minus inner), positive and small.
            assert!(open_edges(&glass).is_empty(), "{name}: glass watertight");
            let wall = signed_volume(&glass);
            let outer = 4.0 / 3.0 * std::f32::consts::PI * objects::SHELL_RADIUS.powi(3);
            let scale = if name == "shell" { 1.0 } else { 0.3f32.powi(3) };
            assert!(wall > 0.0 && wall < 0.1 * outer * scale, "{name}: wall volume {wall}");
            let solid = triangles_where(&s, |m| matches!(m, Material::Lambertian { .. }));
            assert!(!solid.indices.is_empty());
        }
        // In "shell" the solid content lies strictly inside the inner glass surface.
        let s = builtin("shell").expect("ok");
        let solid = triangles_where(&s, |m| matches!(m, Material::Lambertian { .. }));
        let used: Vec<Vec3> = solid.indices.iter().flatten().map(|&i| solid.positions[i as usize]).collect();
        assert!(used.iter().all(|p| p.length() < objects::SHELL_RADIUS - 0.2));
    }

    #[test]
    fn object_meshes_are_closed_and_outward() {
        for name in ["diffuse", "glossy"] {
            let s = builtin(name).expect("ok");
            assert!(open_edges(&s.scene.mesh).is_empty(), "{name}: watertight");
            assert!(signed_volume(&s.scene.mesh) > 0.0, "{name}: outward");
            assert!(s.scene.sun.is_some() && matches!(s.scene.environment, Environment::Sky { .. }));
        }
        let glossy = builtin("glossy").expect("ok");
        assert!(glossy.scene.materials.iter().all(|m| matches!(
            m,
            Material::Glossy { roughness, .. } if (0.1..=0.25).contains(roughness)
        )));
    }

    #[test]
    fn furry_has_thousands_of_thin_fibres() {
        let s = builtin("furry").expect("ok");
        let fibres = s.scene.triangle_count() - 5120;
        assert_eq!(fibres, objects::FUR.count as usize * 6);
        assert!(s.scene.triangle_count() < 150_000);
        assert!((1000..=objects::FUR.count).contains(&(fibres as u32 / 6)));
    }

    #[test]
    fn rooms_are_closed_but_for_the_windows_and_lit() {
        let [floor, ceiling, walls] = room::shell().expect("ok");
        let mut shell = floor.0;
        shell.append(&ceiling.0);
        shell.append(&walls.0);
        // Each window is one missing grid cell: 4 open edges each.
        assert_eq!(open_edges(&shell).len(), 4 * room::WINDOWS.len());
        let inside = Vec3::new(0.0, 0.0, 1.4);
        for t in &shell.indices {
            let [a, b, c] = t.map(|i| shell.positions[i as usize]);
            assert!((b - a).cross(c - a).dot(inside - (a + b + c) / 3.0) > 0.0, "faces inward");
        }
        let day = builtin("room-day").expect("ok");
        let night = builtin("room-night").expect("ok");
        assert_eq!(day.scene.mesh.positions, night.scene.mesh.positions, "same room");
        let sun = day.scene.sun.expect("sun by day");
        assert!(sun.direction.z > 0.0 && sun.direction.y < 0.0, "shines in through the south wall");
        assert!(!day.scene.materials.iter().any(|m| matches!(m, Material::Emissive { .. })));
        assert!(night.scene.sun.is_none());
        let lamps = triangles_where(&night, |m| matches!(m, Material::Emissive { .. }));
        assert!(lamps.indices.len() >= 2);
        // The ceiling lamp faces down.
        assert!(lamps.indices.iter().any(|t| {
            let [a, b, c] = t.map(|i| lamps.positions[i as usize]);
            (b - a).cross(c - a).z < 0.0 && a.z > 2.7
        }));
        let night_sky = night.scene.environment.radiance(Vec3::Z);
        assert!(night_sky.max_element() < 0.05 && night_sky.z > night_sky.x);
        // The sun reaches the floor through a window: a ray from a point of the sunny floor
        // patch towards the sun leaves through the window opening.
        let start = Vec3::new(0.3, -0.5, 0.0);
        let t = (-2.0 - start.y) / sun.direction.y;
        let exit = start + sun.direction * t;
        assert!(room::WINDOWS.iter().any(|w| exit.x > w[0] && exit.x < w[1] && exit.z > w[2] && exit.z < w[3]));
    }

    #[test]
    fn the_rooms_ball_rolls_and_the_rest_stays() {
        let still = builtin("room-day").expect("ok");
        let at_zero = builtin_at("room-day", 0.0).expect("ok");
        assert_eq!(still.scene.mesh.positions, at_zero.scene.mesh.positions);
        let later = builtin_at("room-day", 1.5).expect("ok");
        let (a, b) = (&still.scene.mesh.positions, &later.scene.mesh.positions);
        assert_eq!(a.len(), b.len(), "same triangles, moved");
        let moved = a.iter().zip(b).filter(|(p, q)| p != q).count();
        let ball_vertices = shapes::icosphere(0.25, 4).expect("ball").positions.len();
        assert_eq!(moved, ball_vertices, "only the ball moves ({} vertices in all)", a.len());
        // Every moved vertex lies on the ball at its new centre; all along the loop the ball
        // stays on the floor, inside the walls and clear of the table legs (6 cm square
        // posts at (0.3 +- 0.62, 0.3 +- 0.32)).
        let centre = room::ball_centre(1.5);
        assert!(b.iter().zip(a).filter(|(q, p)| p != q).all(|(q, _)| ((*q - centre).length() - 0.25).abs() < 0.01));
        for i in 0..64 {
            let c = room::ball_centre(i as f32 * BALL_PERIOD_S / 64.0);
            assert!(c.z - 0.25 >= 0.0 && c.y - 0.25 > -room::HALF_Y && c.x.abs() + 0.25 < room::HALF_X);
            for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let leg = glam::Vec2::new(0.3 + sx * 0.62, 0.3 + sy * 0.32);
                assert!((c.truncate() - leg).length() > 0.25 + 0.045, "touches a leg at {c}");
            }
        }
        // Periodic, and the still scenes do not move.
        assert!((room::ball_centre(BALL_PERIOD_S + 0.3) - room::ball_centre(0.3)).length() < 1e-4);
        let knot = builtin_at("diffuse", 2.0).expect("ok");
        assert_eq!(knot.scene.mesh.positions, builtin("diffuse").expect("ok").scene.mesh.positions);
    }

    #[test]
    fn assembly_stands_on_its_ground() {
        let s = builtin("assembly").expect("ok");
        assert!(matches!(s.framing, Framing::Object { hemisphere: true, .. }));
        let (lo, hi) = s.scene.bounds().expect("bounds");
        assert!(lo.z.abs() < 1e-4 && hi.z > 0.5);
        assert!(s.scene.materials.len() >= 8, "all four objects' materials are there");
    }

    #[test]
    fn scenes_build_quickly() {
        // Generous: the target is < 0.5 s in release; tests run at opt-level 2.
        for name in names() {
            let start = std::time::Instant::now();
            builtin(name).expect("ok");
            let elapsed = start.elapsed();
            println!("{name:<11} built in {elapsed:?}");
            assert!(elapsed.as_secs_f32() < 2.0, "{name} took {elapsed:?}");
        }
    }
}
