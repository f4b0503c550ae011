//! The scene catalog: what a client may ask for in `POST /v1/sessions`.
//!
//! A scene is a list of objects, each an asset (an id the workers' asset loader resolves:
//! a built-in scene name or a file in their asset directory) placed at a translation in the
//! world. Objects are instances shared by every scene and session that places the same asset
//! at the same spot, so that the scheduler can share their rays across users. World bounds
//! come from the asset's geometry shifted by the translation; a worker renders the asset in
//! its own coordinates, so the master moves the camera instead (see
//! [`crate::farm::wire_camera`]).
//!
//! Each built-in object also gets a coarse occupancy grid made from its mesh (NEPHELE's prior
//! mesh, section 5): the TaskAssigner projects its occupied cells instead of the bounding box
//! to estimate the pixels the object covers (`nephele bench assigner`: 1.41 estimated pixels
//! per hit pixel against the box's 1.60, none missed; BENCHMARKS.md, "The TaskAssigner's
//! estimate").
//!
//! Built in: `default`, three objects side by side (the matte knot on the left, the glossy
//! pair on the right, the glass shell behind them; see [`default_layout`]), and one
//! single-object scene per built-in object scene (`diffuse`, `glossy`, `furry`, `shell`,
//! `assembly`, `furnace`), and two scenes with an environment (issue 13): `room-day` and
//! `room-night`, the furnished room shaded by its stereo GI model (the workers' asset
//! `room-day.ngi`, `room-night.ngi`; without one, the path-traced room) with the matte knot
//! standing in it ([`ROOM_OBJECT`]). An environment is a full-frame object for the scheduler:
//! its views are rendered whole and fused behind the objects by depth.

use glam::Vec3;
use nephele_geometry::Bounds;
use nephele_pathtracer::Material;
use nephele_pathtracer::scenes::{self, Framing};
use nephele_pathtracer::voxel::{cell_occupancy, solid_cells};
use nephele_proto::SolidGrid;
use nephele_scheduler::OccupancyGrid;
use thiserror::Error;

use crate::http::SceneView;

/// The built-in objects (scenes framed as objects, not interiors).
pub const BUILTIN_OBJECTS: [&str; 6] = ["diffuse", "glossy", "furry", "shell", "assembly", "furnace"];

/// The `default` scene's objects: left, right, behind.
pub const DEFAULT_OBJECTS: [&str; 3] = ["diffuse", "glossy", "shell"];

/// The environments: built-in interiors served by a GI model (or path traced).
pub const BUILTIN_ENVIRONMENTS: [&str; 2] = ["room-day", "room-night"];

/// The object standing in the room scenes and where: the knot (2.5 m across) above the
/// middle of the 5 x 4 m floor, clear of the floor and the ceiling.
pub const ROOM_OBJECT: (&str, [f32; 3]) = ("diffuse", [0.0, 0.0, 1.3]);

/// The room scenes' first view: 1.9 m from the knot's axis, so that a camera orbiting the
/// target (the loadgen's scripted user, the page's drag) stays inside the 5 x 4 m room.
pub const ROOM_VIEW: SceneView = SceneView { eye: [1.55, -1.1, 1.75], target: [0.0, 0.0, 1.1], fov_y_deg: 66.0 };

/// Free space between the boxes of the `default` scene's objects, metres.
pub const DEFAULT_GAP: f32 = 0.2;

/// Cells along the longest side of a built-in object's occupancy grid, and the margin (in
/// cells) around its surface. 16 cuts the box's over-estimate of `nhit` from +109 % to +68 %
/// (mean per view) at 66 times the box's projection cost; 32 reaches +48 % at 4.5 times that.
const OCCUPANCY_CELLS: u32 = 16;
const OCCUPANCY_MARGIN: f32 = 0.5;

/// Cells along the longest side of a built-in object's solid grid (what an environment need
/// not light behind it; `nephele_geometry::solid`), and the margin (in cells) kept clear of
/// its surface: half a cell takes in the slivers that sampling misses; the baked field's blur
/// at the surface stays outside the solid cells. 80 cells (3.5 cm for the knot, whose tube is
/// 36 cm thick) make 82 % of the rays that meet the knot blocked (64: 77 %), within the
/// wire's 64^3 cells (fewer along a box too near a cube); `nephele bench covered`.
const SOLID_CELLS: u32 = 80;
const SOLID_MARGIN: f32 = 0.5;

/// Vertical field of view of the composed scenes' first view, degrees.
const SCENE_FOV_Y_DEG: f32 = 40.0;

/// An object instance: an asset at a place.
#[derive(Debug, Clone, PartialEq)]
pub struct PlacedObject {
    /// Catalog-wide id (the scheduler's `ObjectId`).
    pub id: u32,
    pub asset: String,
    pub translation: Vec3,
    /// World-space box around the object's matter.
    pub bounds: Bounds,
}

/// A named scene: object ids into the catalog and a good first view.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneDef {
    pub name: String,
    pub objects: Vec<u32>,
    pub view: SceneView,
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum CatalogError {
    #[error("asset {asset:?}: {reason}")]
    Asset { asset: String, reason: String },
    #[error("scene {0:?} is defined twice")]
    Duplicate(String),
    #[error("scene {0:?} has no objects")]
    Empty(String),
}

/// Every scene and object the master knows.
#[derive(Debug, Clone, Default)]
pub struct Catalog {
    objects: Vec<PlacedObject>,
    scenes: Vec<SceneDef>,
    /// Occupancy grids by asset, over the asset's own bounds (so every placement shares one).
    occupancy: Vec<(String, OccupancyGrid)>,
    /// Solid grids by asset, in the asset's own coordinates: built-in objects whose every
    /// material is opaque.
    solid: Vec<(String, SolidGrid)>,
    /// Assets that are environments (rendered as whole views behind everything).
    environments: Vec<String>,
}

impl Catalog {
    /// An empty catalog; add scenes with [`Catalog::add_scene`].
    pub fn new() -> Catalog {
        Catalog::default()
    }

    /// The built-in scenes (builds each built-in object once to measure its bounds).
    pub fn builtin() -> Result<Catalog, CatalogError> {
        let mut catalog = Catalog::new();
        let mut framed = Vec::new();
        for name in BUILTIN_OBJECTS {
            let scene =
                scenes::builtin(name).map_err(|e| CatalogError::Asset { asset: name.into(), reason: e.to_string() })?;
            let bounds = mesh_bounds(name, &scene.scene)?;
            let (dims, occupied) =
                cell_occupancy(&scene.scene.mesh, bounds.min, bounds.max, OCCUPANCY_CELLS, OCCUPANCY_MARGIN);
            if let Some(grid) = OccupancyGrid::new(dims, occupied) {
                catalog.occupancy.push((name.to_string(), grid));
            }
            // Glass lets the room through: only opaque objects hide it.
            let opaque = !scene.scene.materials.iter().any(|m| matches!(m, Material::Dielectric { .. }));
            if opaque {
                let cells = solid_cells_along(bounds.size(), SOLID_CELLS);
                let (dims, solid) = solid_cells(&scene.scene.mesh, bounds.min, bounds.max, cells, SOLID_MARGIN);
                match SolidGrid::new(bounds.min, bounds.max, dims, &solid) {
                    Ok(grid) if grid.solid_count() > 0 => catalog.solid.push((name.to_string(), grid)),
                    Ok(_) => {}
                    Err(e) => tracing::warn!(object = name, "no solid grid: {e}"),
                }
            }
            framed.push((name, bounds, scene.framing, scene.default_view()));
        }
        let bounds_of = |asset: &str| {
            framed
                .iter()
                .find(|f| f.0 == asset)
                .map(|f| f.1)
                .ok_or_else(|| CatalogError::Asset { asset: asset.into(), reason: "not built in".into() })
        };
        let boxes = [bounds_of(DEFAULT_OBJECTS[0])?, bounds_of(DEFAULT_OBJECTS[1])?, bounds_of(DEFAULT_OBJECTS[2])?];
        let placed = DEFAULT_OBJECTS
            .iter()
            .zip(default_layout(&boxes, DEFAULT_GAP))
            .zip(boxes)
            .map(|((a, t), b)| (a.to_string(), t, b))
            .collect();
        catalog.add_scene("default", placed, None)?;
        for (name, bounds, framing, (eye, target, fov_y)) in &framed {
            // Object scenes come with their own first view; keep it.
            let view = matches!(framing, Framing::Object { .. }).then(|| SceneView {
                eye: eye.to_array(),
                target: target.to_array(),
                fov_y_deg: fov_y.to_degrees(),
            });
            catalog.add_scene(name, vec![(name.to_string(), Vec3::ZERO, *bounds)], view)?;
        }
        let (object, at) = ROOM_OBJECT;
        let object_bounds = bounds_of(object)?;
        for name in BUILTIN_ENVIRONMENTS {
            let room =
                scenes::builtin(name).map_err(|e| CatalogError::Asset { asset: name.into(), reason: e.to_string() })?;
            let room_bounds = mesh_bounds(name, &room.scene)?;
            catalog.environments.push(name.to_string());
            catalog.add_scene(
                name,
                vec![(name.to_string(), Vec3::ZERO, room_bounds), (object.to_string(), Vec3::from(at), object_bounds)],
                Some(ROOM_VIEW),
            )?;
        }
        Ok(catalog)
    }

    /// Whether `asset` is an environment (a full-frame object).
    pub fn is_environment(&self, asset: &str) -> bool {
        self.environments.iter().any(|e| e == asset)
    }

    /// Adds a scene of `(asset, translation, bounds in the asset's own coordinates)`. Objects
    /// already placed identically by another scene are reused. Without `view`, a first view
    /// is framed around the scene's bounds.
    pub fn add_scene(
        &mut self,
        name: &str,
        objects: Vec<(String, Vec3, Bounds)>,
        view: Option<SceneView>,
    ) -> Result<(), CatalogError> {
        if self.scenes.iter().any(|s| s.name == name) {
            return Err(CatalogError::Duplicate(name.into()));
        }
        if objects.is_empty() {
            return Err(CatalogError::Empty(name.into()));
        }
        let mut ids = Vec::with_capacity(objects.len());
        for (asset, translation, local) in objects {
            nephele_proto::validate::asset_id(&asset)
                .map_err(|e| CatalogError::Asset { asset: asset.clone(), reason: e.to_string() })?;
            let bounds = Bounds { min: local.min + translation, max: local.max + translation };
            let existing =
                self.objects.iter().find(|o| o.asset == asset && o.translation == translation && o.bounds == bounds);
            let id = match existing {
                Some(o) => o.id,
                None => {
                    let id = self.objects.len() as u32 + 1;
                    self.objects.push(PlacedObject { id, asset, translation, bounds });
                    id
                }
            };
            if !ids.contains(&id) {
                ids.push(id);
            }
        }
        let view = view.unwrap_or_else(|| {
            let boxes: Vec<Bounds> = ids.iter().filter_map(|id| self.object(*id)).map(|o| o.bounds).collect();
            frame_view(&boxes)
        });
        self.scenes.push(SceneDef { name: name.into(), objects: ids, view });
        Ok(())
    }

    pub fn scenes(&self) -> &[SceneDef] {
        &self.scenes
    }

    pub fn scene(&self, name: &str) -> Option<&SceneDef> {
        self.scenes.iter().find(|s| s.name == name)
    }

    pub fn objects(&self) -> &[PlacedObject] {
        &self.objects
    }

    pub fn object(&self, id: u32) -> Option<&PlacedObject> {
        self.objects.iter().find(|o| o.id == id)
    }

    /// What hides an environment's view in every one of `scenes`: the solid grids of the
    /// objects all of them place (a batch that feeds several sessions may skip only what
    /// every one of them has in front), moved into `environment`'s coordinates.
    pub fn occluders(&self, environment: &PlacedObject, scenes: &[&str]) -> Vec<SolidGrid> {
        let defs: Vec<&SceneDef> = scenes.iter().filter_map(|name| self.scene(name)).collect();
        if defs.len() != scenes.len() || defs.is_empty() {
            return Vec::new();
        }
        defs[0]
            .objects
            .iter()
            .filter(|id| defs.iter().all(|d| d.objects.contains(id)))
            .filter_map(|&id| self.object(id))
            .filter(|o| o.id != environment.id && !self.is_environment(&o.asset))
            .filter_map(|o| {
                let (_, grid) = self.solid.iter().find(|(asset, _)| *asset == o.asset)?;
                Some(grid.translated(o.translation - environment.translation))
            })
            .collect()
    }

    /// The solid grid of an asset (in its own coordinates), where the catalog made one.
    pub fn solid(&self, asset: &str) -> Option<&SolidGrid> {
        self.solid.iter().find(|(a, _)| a == asset).map(|(_, grid)| grid)
    }

    /// The occupancy grid of an asset (over its bounds), where the catalog made one.
    pub fn occupancy(&self, asset: &str) -> Option<&OccupancyGrid> {
        self.occupancy.iter().find(|(a, _)| a == asset).map(|(_, grid)| grid)
    }
}

/// Translations that put three objects (boxes in their own coordinates) side by side on the
/// ground plane z = 0 (each box's centre at z = its own): the first left of the origin, the
/// second right of it, the third behind both (+Y), centred, `gap` metres between boxes. The
/// built-in objects are about 2.5 m across, so this is roughly x = -1.4, x = +1.4, y = +2.7.
pub fn default_layout(boxes: &[Bounds; 3], gap: f32) -> [Vec3; 3] {
    let [left, right, back] = boxes;
    let t_left = Vec3::new(-0.5 * gap - left.max.x, -left.center().y, 0.0);
    let t_right = Vec3::new(0.5 * gap - right.min.x, -right.center().y, 0.0);
    let front_back = (left.max.y + t_left.y).max(right.max.y + t_right.y);
    let t_back = Vec3::new(-back.center().x, front_back + gap - back.min.y, 0.0);
    [t_left, t_right, t_back]
}

/// Cells along the longest side of a box: `wanted`, or fewer where the grid would exceed
/// `MAX_SOLID_CELLS` (a box near a cube: the glossy pair's 80 x 54 x 69 would).
fn solid_cells_along(size: Vec3, wanted: u32) -> u32 {
    let size = size.max(Vec3::splat(1e-6));
    (1..=wanted.max(1))
        .rev()
        .find(|&n| {
            let cell = size.max_element() / n as f32;
            let dims = (size / cell).ceil().max(Vec3::ONE);
            (dims.x as u64) * (dims.y as u64) * (dims.z as u64) <= nephele_geometry::solid::MAX_SOLID_CELLS
        })
        .unwrap_or(1)
}

fn mesh_bounds(name: &str, scene: &nephele_pathtracer::Scene) -> Result<Bounds, CatalogError> {
    let (min, max) = scene
        .bounds()
        .ok_or_else(|| CatalogError::Asset { asset: name.into(), reason: "the scene has no geometry".into() })?;
    if !(min.is_finite() && max.is_finite()) {
        return Err(CatalogError::Asset { asset: name.into(), reason: "non-finite bounds".into() });
    }
    Ok(Bounds { min, max })
}

/// A first view of boxes: from the front-right and above (azimuth -60 degrees, 25 degrees
/// up, as the built-in scenes' default views), far enough for their bounding sphere to fit
/// the vertical field of view with a 10 % margin.
pub fn frame_view(boxes: &[Bounds]) -> SceneView {
    let (min, max) = boxes.iter().fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), b| {
        (lo.min(b.min), hi.max(b.max))
    });
    let (center, radius) = if min.is_finite() && max.is_finite() {
        (0.5 * (min + max), 0.5 * (max - min).length())
    } else {
        (Vec3::ZERO, 1.0)
    };
    let half = (0.5 * SCENE_FOV_Y_DEG).to_radians();
    let distance = 1.1 * radius.max(1e-3) / half.sin();
    let (azimuth, elevation) = ((-60f32).to_radians(), 25f32.to_radians());
    let dir = Vec3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
    SceneView { eye: (center + dir * distance).to_array(), target: center.to_array(), fov_y_deg: SCENE_FOV_Y_DEG }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit() -> Bounds {
        Bounds { min: Vec3::splat(-0.5), max: Vec3::splat(0.5) }
    }

    #[test]
    fn objects_are_shifted_and_shared_between_scenes() {
        let mut catalog = Catalog::new();
        catalog
            .add_scene(
                "a",
                vec![("x".into(), Vec3::new(2.0, 0.0, 0.0), unit()), ("y".into(), Vec3::ZERO, unit())],
                None,
            )
            .expect("a");
        catalog.add_scene("b", vec![("x".into(), Vec3::new(2.0, 0.0, 0.0), unit())], None).expect("b");
        catalog.add_scene("c", vec![("x".into(), Vec3::ZERO, unit())], None).expect("c");
        assert_eq!(catalog.objects().len(), 3, "x at 2 is one instance, x at 0 another");
        let a = catalog.scene("a").expect("a");
        let b = catalog.scene("b").expect("b");
        assert_eq!(a.objects[0], b.objects[0]);
        let x = catalog.object(a.objects[0]).expect("x");
        assert_eq!(x.bounds.min, Vec3::new(1.5, -0.5, -0.5));
        assert_eq!(x.translation, Vec3::new(2.0, 0.0, 0.0));
        assert!(catalog.add_scene("a", vec![("x".into(), Vec3::ZERO, unit())], None).is_err());
        assert!(catalog.add_scene("d", vec![], None).is_err());
        assert!(catalog.add_scene("e", vec![("../x".into(), Vec3::ZERO, unit())], None).is_err());
    }

    #[test]
    fn the_framed_view_sees_every_box() {
        let boxes = [
            Bounds { min: Vec3::new(-2.0, -0.5, -0.5), max: Vec3::new(-1.0, 0.5, 0.5) },
            Bounds { min: Vec3::new(1.0, 1.0, -0.5), max: Vec3::new(2.0, 2.0, 0.5) },
        ];
        let view = frame_view(&boxes);
        let camera = nephele_geometry::camera::Camera::look_at(
            200,
            200,
            view.fov_y_deg.to_radians(),
            Vec3::from(view.eye),
            Vec3::from(view.target),
            Vec3::Z,
        )
        .expect("camera");
        for b in &boxes {
            for corner in b.corners() {
                let p = camera.project(corner).expect("in front");
                assert!((0.0..200.0).contains(&p.x) && (0.0..200.0).contains(&p.y), "{corner} -> {p}");
            }
        }
    }

    #[test]
    fn the_builtin_catalog_has_the_default_scene_and_one_per_object() {
        let catalog = Catalog::builtin().expect("catalog");
        let names: Vec<&str> = catalog.scenes().iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names[0], "default");
        for object in BUILTIN_OBJECTS {
            assert!(names.contains(&object), "{object}");
            assert!(!catalog.is_environment(object));
        }
        // The rooms: the environment (its bounds the room's, at the origin) and the knot
        // inside it, clear of the floor and the ceiling; the first view inside the room.
        for room in BUILTIN_ENVIRONMENTS {
            assert!(catalog.is_environment(room));
            let scene = catalog.scene(room).expect("room scene");
            let [env, knot] = [0, 1].map(|i| catalog.object(scene.objects[i]).expect("object"));
            assert_eq!(env.asset, room);
            assert_eq!(knot.asset, ROOM_OBJECT.0);
            assert!(env.bounds.min.cmple(knot.bounds.min).all() && knot.bounds.max.cmple(env.bounds.max).all());
            assert!(knot.bounds.min.z > 0.1 && knot.bounds.max.z < env.bounds.max.z - 0.1, "{:?}", knot.bounds);
            // The first view, and the circle a camera orbiting its target draws, inside.
            let (eye, target) = (Vec3::from(scene.view.eye), Vec3::from(scene.view.target));
            let radius = (eye - target).truncate().length();
            let inner = Bounds { min: env.bounds.min + 0.05, max: env.bounds.max - 0.05 };
            for k in 0..32 {
                let a = k as f32 * std::f32::consts::TAU / 32.0;
                let p = Vec3::new(target.x + radius * a.cos(), target.y + radius * a.sin(), eye.z);
                assert!(inner.min.cmplt(p).all() && p.cmplt(inner.max).all(), "{p} leaves the room");
            }
        }
        let default = catalog.scene("default").expect("default");
        assert_eq!(default.objects.len(), 3);
        let diffuse_in_default = catalog.object(default.objects[0]).expect("object");
        let diffuse = catalog.object(catalog.scene("diffuse").expect("diffuse").objects[0]).expect("object");
        assert_eq!(diffuse_in_default.asset, "diffuse");
        assert_ne!(diffuse_in_default.id, diffuse.id, "placed elsewhere: another instance");
        assert!(
            diffuse_in_default.bounds.max.x < 0.0 && diffuse_in_default.translation.x < -0.5,
            "{diffuse_in_default:?}"
        );
        // Side by side: the three boxes of the default scene do not overlap.
        let boxes: Vec<Bounds> = default.objects.iter().map(|id| catalog.object(*id).expect("o").bounds).collect();
        for i in 0..3 {
            for j in i + 1..3 {
                let (a, b) = (boxes[i], boxes[j]);
                let overlap = a.min.cmplt(b.max).all() && b.min.cmplt(a.max).all();
                assert!(!overlap, "{a:?} and {b:?} overlap");
            }
        }
    }

    /// The room's knot hides the room behind its solid cells: every camera ray they block
    /// meets the knot's own mesh first, and they block most of the rays that meet it.
    #[test]
    fn the_knots_solid_cells_lie_inside_it_and_cover_most_of_it() {
        use nephele_geometry::camera::Camera;
        use nephele_pathtracer::bvh::{Bvh, TraversalStats};

        let catalog = Catalog::builtin().expect("catalog");
        assert!(catalog.solid("diffuse").is_some() && catalog.solid("glossy").is_some());
        assert!(catalog.solid("shell").is_none(), "glass hides nothing");
        let room = catalog.scene("room-day").expect("room");
        let env = catalog.object(room.objects[0]).expect("environment");
        let knot = catalog.object(room.objects[1]).expect("knot");
        let occluders = catalog.occluders(env, &["room-day", "room-day"]);
        assert_eq!(occluders.len(), 1);
        assert!(catalog.occluders(env, &["room-day", "default"]).is_empty(), "not in front for every session");
        assert!(catalog.occluders(env, &["room-day", "no-such-scene"]).is_empty());
        let mesh = scenes::builtin(&knot.asset).expect("built in").scene.mesh;
        let bvh = Bvh::build(&mesh);
        let mut stats = TraversalStats::default();
        let (target, eye) = (Vec3::from(ROOM_VIEW.target), Vec3::from(ROOM_VIEW.eye));
        let radius = (eye - target).truncate().length();
        let (w, h) = (96, 72);
        let (mut hits, mut blocked) = (0, 0);
        for k in 0..6 {
            let a = k as f32 * std::f32::consts::TAU / 6.0 + 0.3;
            let at = Vec3::new(target.x + radius * a.cos(), target.y + radius * a.sin(), eye.z);
            let camera = Camera::look_at(w, h, ROOM_VIEW.fov_y_deg.to_radians(), at, target, Vec3::Z).expect("camera");
            for p in 0..w * h {
                let ray = camera.pixel_center_ray(p % w, p / w);
                let block = occluders[0].first_solid(ray.origin, ray.direction, f32::INFINITY);
                let mut local = ray;
                local.origin -= knot.translation;
                let hit = bvh.intersect(&local, 1e-4, f32::INFINITY, &mut stats);
                if let Some((t, _)) = block {
                    let t_mesh = hit.as_ref().map(|h| h.t);
                    assert!(t_mesh.is_some_and(|m| m <= t), "pixel {p}: blocked at {t}, the knot at {t_mesh:?}");
                    blocked += 1;
                }
                hits += u32::from(hit.is_some());
            }
        }
        let share = f64::from(blocked) / f64::from(hits);
        eprintln!("solid cells block {blocked} of {hits} rays that meet the knot ({:.1} %)", 100.0 * share);
        assert!(share > 0.75, "{share}");
    }

    /// The default scene's first view as a client opens it: each object's occupancy grid,
    /// placed, covers every pixel where the object's own mesh is hit, with fewer pixels than
    /// its box.
    #[test]
    fn occupancy_grids_cover_every_hit_pixel_with_fewer_than_the_box() {
        use nephele_geometry::camera::Camera;
        use nephele_pathtracer::bvh::{Bvh, TraversalStats};
        use nephele_scheduler::assign::estimate_coverage;

        let catalog = Catalog::builtin().expect("catalog");
        let default = catalog.scene("default").expect("default");
        let view = &default.view;
        let (w, h) = (160, 120);
        let camera =
            Camera::look_at(w, h, view.fov_y_deg.to_radians(), Vec3::from(view.eye), Vec3::from(view.target), Vec3::Z)
                .expect("camera");
        for id in &default.objects {
            let object = catalog.object(*id).expect("object");
            let grid = catalog.occupancy(&object.asset).expect("a grid for every built-in object");
            let mesh = scenes::builtin(&object.asset).expect("built in").scene.mesh;
            let bvh = Bvh::build(&mesh);
            let mut stats = TraversalStats::default();
            let hits: Vec<u32> = (0..w * h)
                .filter(|&p| {
                    let mut ray = camera.pixel_center_ray(p % w, p / w);
                    ray.origin -= object.translation; // the asset in its own coordinates
                    bvh.intersect(&ray, 1e-4, f32::INFINITY, &mut stats).is_some()
                })
                .collect();
            assert!(hits.len() > 100, "{}: {} hit pixels", object.asset, hits.len());
            let with_grid = estimate_coverage(&camera, &object.bounds, Some(grid), 16).expect("in view");
            let with_box = estimate_coverage(&camera, &object.bounds, None, 16).expect("in view");
            let mut covered = with_grid.pixels.indices();
            covered.sort_unstable();
            let missed = hits.iter().filter(|p| covered.binary_search(p).is_err()).count();
            assert_eq!(missed, 0, "{}: hit pixels outside the grid's estimate", object.asset);
            assert!(with_grid.rays < with_box.rays, "{}: {} >= {}", object.asset, with_grid.rays, with_box.rays);
        }
    }
}
