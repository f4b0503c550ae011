//! Scene description for the reference renderer: triangle meshes with one material each,
//! a sun, an environment. Emissive triangles are the area lights.

use glam::{Affine3A, Vec3};
use thiserror::Error;

use super::material::Material;

/// Reasons a scene is refused before any ray is traced.
#[derive(Debug, Error, PartialEq)]
pub enum SceneError {
    #[error("mesh has a triangle index {index} but only {vertices} vertices")]
    IndexOutOfRange { index: u32, vertices: usize },
    #[error("mesh has {normals} normals for {vertices} vertices")]
    NormalCount { normals: usize, vertices: usize },
    #[error("mesh has a non-finite vertex position at index {0}")]
    NonFinitePosition(usize),
    #[error("material {index} is invalid: {reason}")]
    InvalidMaterial { index: usize, reason: String },
    #[error("the scene has no triangles")]
    Empty,
}

/// An indexed triangle mesh. Normals, when present, are per vertex and interpolated
/// (shading normals); the geometric normal always comes from the triangle's winding.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    pub normals: Option<Vec<Vec3>>,
    pub indices: Vec<[u32; 3]>,
}

impl Mesh {
    pub fn new(positions: Vec<Vec3>, indices: Vec<[u32; 3]>) -> Self {
        Self { positions, normals: None, indices }
    }

    pub fn with_normals(mut self, normals: Vec<Vec3>) -> Self {
        self.normals = Some(normals);
        self
    }

    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    /// Checks indices, normal count and finiteness.
    pub fn validate(&self) -> Result<(), SceneError> {
        let vertices = self.positions.len();
        if let Some(n) = &self.normals
            && n.len() != vertices
        {
            return Err(SceneError::NormalCount { normals: n.len(), vertices });
        }
        if let Some(i) = self.positions.iter().position(|p| !p.is_finite()) {
            return Err(SceneError::NonFinitePosition(i));
        }
        for tri in &self.indices {
            for &index in tri {
                if index as usize >= vertices {
                    return Err(SceneError::IndexOutOfRange { index, vertices });
                }
            }
        }
        Ok(())
    }

    /// The mesh moved by `transform`; normals use the inverse transpose.
    pub fn transformed(&self, transform: Affine3A) -> Mesh {
        let normal_matrix = transform.matrix3.inverse().transpose();
        Mesh {
            positions: self.positions.iter().map(|&p| transform.transform_point3(p)).collect(),
            normals: self
                .normals
                .as_ref()
                .map(|ns| ns.iter().map(|&n| (normal_matrix * n).normalize_or_zero()).collect()),
            indices: self.indices.clone(),
        }
    }

    /// Appends `other` to this mesh. Normals are kept only if both meshes have them.
    pub fn append(&mut self, other: &Mesh) {
        let base = self.positions.len() as u32;
        let had_vertices = !self.positions.is_empty();
        self.normals = match (self.normals.take(), &other.normals) {
            (Some(mut a), Some(b)) => {
                a.extend_from_slice(b);
                Some(a)
            }
            (None, Some(b)) if !had_vertices => Some(b.clone()),
            _ => None,
        };
        self.positions.extend_from_slice(&other.positions);
        self.indices.extend(other.indices.iter().map(|t| [t[0] + base, t[1] + base, t[2] + base]));
    }

    /// Axis-aligned bounds `(min, max)`; `None` for a mesh with no vertices.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let first = *self.positions.first()?;
        Some(self.positions.iter().fold((first, first), |(lo, hi), &p| (lo.min(p), hi.max(p))))
    }
}

/// A directional light ("sun") with a small angular radius for soft shadows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sun {
    /// Unit vector from the scene towards the sun.
    pub direction: Vec3,
    /// Irradiance on a surface facing the sun (linear RGB, W/m^2 per channel).
    pub irradiance: Vec3,
    /// Angular radius of the sun's disc, radians (0 = a perfect delta light). Used only to
    /// jitter shadow rays; the sun is never hit by BSDF-sampled rays.
    pub angular_radius: f32,
}

/// Light arriving from infinitely far away in every direction not blocked by geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Environment {
    /// No light from the background.
    Black,
    /// The same radiance from every direction (the furnace test's light).
    Uniform(Vec3),
    /// A smooth sky: `zenith` straight up, `horizon` at the horizon, `ground` below it.
    Sky { zenith: Vec3, horizon: Vec3, ground: Vec3 },
}

impl Environment {
    /// Radiance arriving along a ray travelling in direction `dir` (unit).
    pub fn radiance(&self, dir: Vec3) -> Vec3 {
        match *self {
            Environment::Black => Vec3::ZERO,
            Environment::Uniform(l) => l,
            Environment::Sky { zenith, horizon, ground } => {
                let z = dir.z;
                if z >= 0.0 {
                    // Smooth blend, brighter and whiter towards the horizon.
                    let t = z.clamp(0.0, 1.0).powf(0.6);
                    horizon.lerp(zenith, t)
                } else {
                    let t = (-z).clamp(0.0, 1.0).powf(0.4);
                    horizon.lerp(ground, t)
                }
            }
        }
    }

    pub fn is_black(&self) -> bool {
        match *self {
            Environment::Black => true,
            Environment::Uniform(l) => l == Vec3::ZERO,
            Environment::Sky { zenith, horizon, ground } => {
                zenith == Vec3::ZERO && horizon == Vec3::ZERO && ground == Vec3::ZERO
            }
        }
    }
}

/// A scene ready to be rendered: one flat triangle soup with a material per triangle.
#[derive(Debug, Clone)]
pub struct Scene {
    pub mesh: Mesh,
    /// One entry per triangle of `mesh`, indexing `materials`.
    pub material_of_triangle: Vec<u32>,
    pub materials: Vec<Material>,
    pub sun: Option<Sun>,
    pub environment: Environment,
}

impl Scene {
    pub fn triangle_count(&self) -> usize {
        self.mesh.indices.len()
    }

    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        self.mesh.bounds()
    }

    pub fn validate(&self) -> Result<(), SceneError> {
        if self.mesh.indices.is_empty() {
            return Err(SceneError::Empty);
        }
        self.mesh.validate()?;
        for (index, m) in self.materials.iter().enumerate() {
            m.validate().map_err(|reason| SceneError::InvalidMaterial { index, reason })?;
        }
        Ok(())
    }
}

/// Assembles a [`Scene`] from meshes, each placed with a transform and given a material.
#[derive(Debug, Clone)]
pub struct SceneBuilder {
    mesh: Mesh,
    material_of_triangle: Vec<u32>,
    materials: Vec<Material>,
    sun: Option<Sun>,
    environment: Environment,
}

impl Default for SceneBuilder {
    fn default() -> Self {
        Self::new()
    }
}

impl SceneBuilder {
    pub fn new() -> Self {
        Self {
            mesh: Mesh::default(),
            material_of_triangle: Vec::new(),
            materials: Vec::new(),
            sun: None,
            environment: Environment::Black,
        }
    }

    /// Registers a material and returns its id, reusing an identical one.
    pub fn material(&mut self, material: Material) -> u32 {
        if let Some(i) = self.materials.iter().position(|m| *m == material) {
            return i as u32;
        }
        self.materials.push(material);
        (self.materials.len() - 1) as u32
    }

    /// Adds `mesh` moved by `transform` with `material`.
    pub fn add(&mut self, mesh: &Mesh, transform: Affine3A, material: Material) -> &mut Self {
        let id = self.material(material);
        let placed = mesh.transformed(transform);
        // Keep shading normals only when every mesh so far has them; mixed scenes fall back
        // to geometric normals for meshes without, by giving them their face normals.
        let placed = if placed.normals.is_none() && self.mesh.normals.is_some() {
            flat_normals_per_vertex(&placed)
        } else if placed.normals.is_some() && self.mesh.normals.is_none() && !self.mesh.positions.is_empty() {
            let fixed = flat_normals_per_vertex(&self.mesh);
            self.mesh = fixed;
            placed
        } else {
            placed
        };
        self.mesh.append(&placed);
        self.material_of_triangle.extend(std::iter::repeat_n(id, mesh.indices.len()));
        self
    }

    pub fn sun(&mut self, sun: Sun) -> &mut Self {
        self.sun = Some(sun);
        self
    }

    pub fn environment(&mut self, environment: Environment) -> &mut Self {
        self.environment = environment;
        self
    }

    pub fn build(self) -> Result<Scene, SceneError> {
        let scene = Scene {
            mesh: self.mesh,
            material_of_triangle: self.material_of_triangle,
            materials: self.materials,
            sun: self.sun,
            environment: self.environment,
        };
        scene.validate()?;
        Ok(scene)
    }
}

/// Unshares vertices so that every triangle gets its own face normal as vertex normals.
fn flat_normals_per_vertex(mesh: &Mesh) -> Mesh {
    let mut positions = Vec::with_capacity(mesh.indices.len() * 3);
    let mut normals = Vec::with_capacity(mesh.indices.len() * 3);
    let mut indices = Vec::with_capacity(mesh.indices.len());
    for tri in &mesh.indices {
        let [a, b, c] = tri.map(|i| mesh.positions[i as usize]);
        let n = (b - a).cross(c - a).normalize_or_zero();
        let base = positions.len() as u32;
        positions.extend([a, b, c]);
        normals.extend([n, n, n]);
        indices.push([base, base + 1, base + 2]);
    }
    Mesh { positions, normals: Some(normals), indices }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn triangle() -> Mesh {
        Mesh::new(vec![Vec3::ZERO, Vec3::X, Vec3::Y], vec![[0, 1, 2]])
    }

    #[test]
    fn rejects_out_of_range_index() {
        let mesh = Mesh::new(vec![Vec3::ZERO, Vec3::X], vec![[0, 1, 2]]);
        assert_eq!(mesh.validate(), Err(SceneError::IndexOutOfRange { index: 2, vertices: 2 }));
    }

    #[test]
    fn rejects_nan_vertex_and_empty_scene() {
        let mesh = Mesh::new(vec![Vec3::ZERO, Vec3::NAN, Vec3::Y], vec![[0, 1, 2]]);
        assert_eq!(mesh.validate(), Err(SceneError::NonFinitePosition(1)));
        assert_eq!(SceneBuilder::new().build().err(), Some(SceneError::Empty));
    }

    #[test]
    fn builder_mixes_meshes_with_and_without_normals() {
        let mut b = SceneBuilder::new();
        let with_normals = triangle().with_normals(vec![Vec3::Z; 3]);
        b.add(&triangle(), Affine3A::IDENTITY, Material::lambertian(Vec3::ONE));
        b.add(&with_normals, Affine3A::from_translation(Vec3::Z), Material::lambertian(Vec3::ONE));
        let scene = b.build().expect("valid");
        assert_eq!(scene.triangle_count(), 2);
        assert_eq!(scene.materials.len(), 1, "identical materials are shared");
        let normals = scene.mesh.normals.as_ref().expect("normals kept");
        assert_eq!(normals.len(), scene.mesh.positions.len());
    }
}
