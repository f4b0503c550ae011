//! glTF 2.0 import (`.gltf` with embedded or external buffers, or binary `.glb`) into the
//! reference renderer's scene.
//!
//! * **Geometry**: the default scene (or else the first scene, or else every root node) is
//!   walked from its root nodes, composing node transforms; every `TRIANGLES` primitive of
//!   every mesh node is imported with its positions, its normals when present (otherwise
//!   the renderer uses face normals) and its indices (or implicit ones). Other primitive
//!   modes (points, lines, strips, fans) are skipped with a warning. Skins, morph targets,
//!   cameras and lights are ignored. A node whose transform mirrors (negative determinant)
//!   has its triangles' winding reversed, as glTF requires, so faces keep facing out.
//! * **Axes**: glTF is +Y up, this renderer is +Z up (see the crate docs). Everything is
//!   rotated by +90 degrees about X at import: glTF `(x, y, z)` becomes `(x, -z, y)`, so
//!   glTF's up (+Y) becomes +Z and glTF's front (+Z) becomes -Y. Units stay metres.
//! * **Materials**: only the material *factors* are used; textures (base colour,
//!   metallic-roughness, normal, emissive, transmission maps) are not sampled. In order:
//!   1. emissive factor x `KHR_materials_emissive_strength` > 0: [`Material::Emissive`];
//!   2. `KHR_materials_transmission` factor > 0.5: [`Material::glass`] with the ior of
//!      `KHR_materials_ior` (1.5 when absent) and the base colour as tint;
//!   3. metallic > 0.5: [`Material::metal`] with the base colour and the roughness;
//!   4. roughness < 0.6: [`Material::glossy`], diffuse base colour x (1 - metallic),
//!      specular 0.04 blended towards the base colour by metallic;
//!   5. otherwise [`Material::lambertian`] with the base colour.
//!
//!   Factors are clamped to their valid ranges. A primitive without a material gets a
//!   light grey Lambertian (0.8) rather than glTF's default white metal, which almost
//!   never is what an untextured model means.
//!
//! Malformed files give a [`GltfImportError`], never a panic: accessor types, counts and
//! index ranges are checked before use, the node hierarchy must be a forest, and as a last
//! resort a panic inside the `gltf` crate (which has a few on malformed input) is caught
//! and reported. On error the builder is left untouched.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use glam::{Affine3A, Mat4, Vec3};
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use gltf::{Accessor, Semantic};
use thiserror::Error;

use super::material::Material;
use super::scene::{Mesh, Scene, SceneBuilder, SceneError};

/// Why a glTF file could not be imported. Underlying causes (I/O, the `gltf` crate's
/// parse errors, scene validation) are exposed through [`std::error::Error::source`], not
/// repeated in the message.
#[derive(Debug, Error)]
pub enum GltfImportError {
    #[error("glTF file {} not found", path.display())]
    NotFound { path: PathBuf },
    #[error("cannot read glTF file {}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not a valid glTF 2.0 file", path.display())]
    Parse {
        path: PathBuf,
        #[source]
        source: gltf::Error,
    },
    #[error("cannot load the buffers of {}", path.display())]
    Buffers {
        path: PathBuf,
        #[source]
        source: gltf::Error,
    },
    #[error("{}: buffer URI {uri:?} does not decode to a UTF-8 path", path.display())]
    BadUri { path: PathBuf, uri: String },
    #[error("{} contains no meshes", path.display())]
    NoMeshes { path: PathBuf },
    #[error("the scene of {} has no triangles (no mesh nodes, or only non-triangle primitives)", path.display())]
    NoTriangles { path: PathBuf },
    #[error("{}: node {node} is reached twice in the node hierarchy (a cycle or a shared child)", path.display())]
    BadHierarchy { path: PathBuf, node: usize },
    #[error("{}: node {node} has a non-finite transform", path.display())]
    BadTransform { path: PathBuf, node: usize },
    #[error("the transform placing {} is not finite", path.display())]
    BadPlacement { path: PathBuf },
    #[error("{}: mesh {mesh}, primitive {primitive}: {reason}", path.display())]
    BadPrimitive { path: PathBuf, mesh: usize, primitive: usize, reason: String },
    #[error("{}: mesh {mesh}, primitive {primitive} has a non-finite {what}", path.display())]
    NonFinite { path: PathBuf, mesh: usize, primitive: usize, what: &'static str },
    #[error(
        "{}: mesh {mesh}, primitive {primitive} has vertex index {index} but only {vertices} vertices",
        path.display()
    )]
    IndexOutOfRange { path: PathBuf, mesh: usize, primitive: usize, index: u32, vertices: usize },
    #[error("{}: material {material}: {reason}", path.display())]
    BadMaterial { path: PathBuf, material: usize, reason: String },
    #[error("{}: the glTF reader failed on malformed data: {message}", path.display())]
    Malformed { path: PathBuf, message: String },
    #[error("the imported scene is invalid")]
    Scene(#[from] SceneError),
}

/// glTF (+Y up) to world (+Z up): +90 degrees about X, `(x, y, z) -> (x, -z, y)`. Built from
/// exact columns rather than `from_rotation_x` so that no rounding creeps in.
pub const Y_UP_TO_Z_UP: Affine3A = Affine3A {
    matrix3: glam::Mat3A::from_cols(glam::Vec3A::X, glam::Vec3A::Z, glam::Vec3A::NEG_Y),
    translation: glam::Vec3A::ZERO,
};

/// Imports `path` as a whole scene, lit by the daylight sky and sun of the built-in object
/// scenes ([`crate::scenes::daylight_sky`], [`crate::scenes::daylight_sun`]) since glTF
/// lights are not imported. Use [`import_gltf_into`] to choose the lighting or to combine
/// the model with other geometry.
pub fn import_gltf(path: &Path) -> Result<Scene, GltfImportError> {
    let mut builder = SceneBuilder::new();
    import_gltf_into(&mut builder, path, Affine3A::IDENTITY)?;
    builder.environment(crate::scenes::daylight_sky());
    builder.sun(crate::scenes::daylight_sun());
    Ok(builder.build()?)
}

/// Adds the meshes of `path` to `builder`, converted to +Z up and then moved by
/// `transform` (world = `transform` x Y-up-to-Z-up x node transform). Nothing is added if
/// the file cannot be imported.
pub fn import_gltf_into(builder: &mut SceneBuilder, path: &Path, transform: Affine3A) -> Result<(), GltfImportError> {
    if !transform.is_finite() {
        return Err(GltfImportError::BadPlacement { path: path.to_owned() });
    }
    let parts = match catch_unwind(AssertUnwindSafe(|| load(path))) {
        Ok(result) => result?,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "panic with no message".to_owned());
            return Err(GltfImportError::Malformed { path: path.to_owned(), message });
        }
    };
    for part in parts {
        let full = transform * Y_UP_TO_Z_UP * part.node_transform;
        let det = full.matrix3.determinant();
        if det == 0.0 || !det.is_finite() {
            // A zero scale is glTF's way of hiding a node.
            tracing::warn!(path = %path.display(), "skipping a glTF mesh with a degenerate transform");
            continue;
        }
        let mesh = if det < 0.0 {
            Mesh { indices: part.mesh.indices.iter().map(|&[a, b, c]| [a, c, b]).collect(), ..part.mesh }
        } else {
            part.mesh
        };
        builder.add(&mesh, full, part.material);
    }
    Ok(())
}

/// One primitive ready to add: local mesh, its node's glTF-space transform, material.
#[derive(Debug)]
struct Part {
    mesh: Mesh,
    node_transform: Affine3A,
    material: Material,
}

fn load(path: &Path) -> Result<Vec<Part>, GltfImportError> {
    let owned = || path.to_owned();
    let gltf = gltf::Gltf::open(path).map_err(|e| match e {
        gltf::Error::Io(io) if io.kind() == std::io::ErrorKind::NotFound => GltfImportError::NotFound { path: owned() },
        gltf::Error::Io(io) => GltfImportError::Io { path: owned(), source: io },
        other => GltfImportError::Parse { path: owned(), source: other },
    })?;
    let gltf::Gltf { document, blob } = gltf;
    if document.meshes().len() == 0 {
        return Err(GltfImportError::NoMeshes { path: owned() });
    }
    // The `gltf` crate unwraps the percent-decoding of relative URIs: check them first.
    for buffer in document.buffers() {
        match buffer.source() {
            gltf::buffer::Source::Uri(uri) if !uri.contains(':') && percent_decode(uri).is_none() => {
                return Err(GltfImportError::BadUri { path: owned(), uri: uri.to_owned() });
            }
            _ => {}
        }
    }
    let buffers = gltf::import_buffers(&document, path.parent(), blob)
        .map_err(|source| GltfImportError::Buffers { path: owned(), source })?;
    let buffer_data = |b: gltf::Buffer<'_>| buffers.get(b.index()).map(|d| d.0.as_slice());

    let node_count = document.nodes().len();
    let roots: Vec<gltf::Node<'_>> = match document.default_scene().or_else(|| document.scenes().next()) {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut is_child = vec![false; node_count];
            for node in document.nodes() {
                for child in node.children() {
                    if let Some(flag) = is_child.get_mut(child.index()) {
                        *flag = true;
                    }
                }
            }
            document.nodes().filter(|n| !is_child.get(n.index()).copied().unwrap_or(true)).collect()
        }
    };

    // Depth-first over the forest; a node met twice means a cycle or a shared child, both
    // invalid glTF, and would otherwise loop forever.
    let mut visited = vec![false; node_count];
    let mut stack: Vec<(gltf::Node<'_>, Affine3A)> = roots.into_iter().rev().map(|n| (n, Affine3A::IDENTITY)).collect();
    let mut parts = Vec::new();
    while let Some((node, parent)) = stack.pop() {
        let seen =
            visited.get_mut(node.index()).ok_or(GltfImportError::BadHierarchy { path: owned(), node: node.index() })?;
        if std::mem::replace(seen, true) {
            return Err(GltfImportError::BadHierarchy { path: owned(), node: node.index() });
        }
        let local = Affine3A::from_mat4(Mat4::from_cols_array_2d(&node.transform().matrix()));
        let world = parent * local;
        if !world.is_finite() {
            return Err(GltfImportError::BadTransform { path: owned(), node: node.index() });
        }
        if let Some(mesh) = node.mesh() {
            for primitive in mesh.primitives() {
                if primitive.mode() != Mode::Triangles {
                    tracing::warn!(
                        path = %path.display(),
                        mesh = mesh.index(),
                        primitive = primitive.index(),
                        mode = ?primitive.mode(),
                        "skipping a glTF primitive that is not a triangle list"
                    );
                    continue;
                }
                let ctx = Ctx { path, mesh: mesh.index(), primitive: primitive.index() };
                if let Some(triangles) = read_primitive(&ctx, &primitive, &buffer_data)? {
                    let material = material_of(path, &primitive.material())?;
                    parts.push(Part { mesh: triangles, node_transform: world, material });
                }
            }
        }
        let children: Vec<_> = node.children().collect();
        stack.extend(children.into_iter().rev().map(|c| (c, world)));
    }
    if parts.is_empty() {
        return Err(GltfImportError::NoTriangles { path: owned() });
    }
    Ok(parts)
}

/// Percent-decodes a relative URI; `None` when the result is not UTF-8.
fn percent_decode(uri: &str) -> Option<String> {
    let bytes = uri.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |k: usize| bytes.get(k).and_then(|&b| (b as char).to_digit(16));
        match (bytes[i], hex(i + 1), hex(i + 2)) {
            (b'%', Some(hi), Some(lo)) => {
                out.push((hi * 16 + lo) as u8);
                i += 3;
            }
            (b, _, _) => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8(out).ok()
}

/// Where a primitive comes from, for error messages.
struct Ctx<'p> {
    path: &'p Path,
    mesh: usize,
    primitive: usize,
}

impl Ctx<'_> {
    fn bad(&self, reason: impl Into<String>) -> GltfImportError {
        GltfImportError::BadPrimitive {
            path: self.path.to_owned(),
            mesh: self.mesh,
            primitive: self.primitive,
            reason: reason.into(),
        }
    }

    fn non_finite(&self, what: &'static str) -> GltfImportError {
        GltfImportError::NonFinite { path: self.path.to_owned(), mesh: self.mesh, primitive: self.primitive, what }
    }
}

/// Checks an attribute accessor holds `count` float 3-vectors (the `gltf` reader would
/// otherwise reinterpret the bytes, or panic on a zero count).
fn check_vec3(ctx: &Ctx<'_>, accessor: &Accessor<'_>, name: &str) -> Result<(), GltfImportError> {
    if accessor.data_type() != DataType::F32 || accessor.dimensions() != Dimensions::Vec3 {
        return Err(ctx.bad(format!(
            "{name} must be float VEC3, found {:?} {:?}",
            accessor.data_type(),
            accessor.dimensions()
        )));
    }
    Ok(())
}

/// Reads one triangle-list primitive; `None` for an empty one.
fn read_primitive<'a, 's, F>(
    ctx: &Ctx<'_>,
    primitive: &'a gltf::Primitive<'a>,
    buffer_data: &F,
) -> Result<Option<Mesh>, GltfImportError>
where
    F: Clone + Fn(gltf::Buffer<'a>) -> Option<&'s [u8]>,
{
    let position_accessor = primitive.get(&Semantic::Positions).ok_or_else(|| ctx.bad("no POSITION attribute"))?;
    check_vec3(ctx, &position_accessor, "POSITION")?;
    if position_accessor.count() == 0 {
        return Ok(None);
    }
    let reader = primitive.reader(buffer_data.clone());
    let positions: Vec<Vec3> = reader
        .read_positions()
        .ok_or_else(|| ctx.bad("POSITION data is missing or outside its buffer"))?
        .map(Vec3::from)
        .collect();
    if positions.len() != position_accessor.count() {
        return Err(ctx.bad("POSITION data is shorter than its accessor"));
    }
    if !positions.iter().all(|p| p.is_finite()) {
        return Err(ctx.non_finite("position"));
    }

    let normals = match primitive.get(&Semantic::Normals) {
        None => None,
        Some(accessor) => {
            check_vec3(ctx, &accessor, "NORMAL")?;
            if accessor.count() != positions.len() {
                return Err(ctx.bad(format!("{} normals for {} positions", accessor.count(), positions.len())));
            }
            let normals: Vec<Vec3> = reader
                .read_normals()
                .ok_or_else(|| ctx.bad("NORMAL data is missing or outside its buffer"))?
                .map(Vec3::from)
                .collect();
            if normals.len() != positions.len() {
                return Err(ctx.bad("NORMAL data is shorter than its accessor"));
            }
            if !normals.iter().all(|n| n.is_finite()) {
                return Err(ctx.non_finite("normal"));
            }
            let unit: Option<Vec<Vec3>> = normals.iter().map(|n| n.try_normalize()).collect();
            if unit.is_none() {
                tracing::warn!(
                    path = %ctx.path.display(),
                    mesh = ctx.mesh,
                    primitive = ctx.primitive,
                    "zero-length normals: using face normals for this primitive"
                );
            }
            unit
        }
    };

    let flat: Vec<u32> = match primitive.indices() {
        None => (0..positions.len() as u32).collect(),
        Some(accessor) => {
            let integer = matches!(accessor.data_type(), DataType::U8 | DataType::U16 | DataType::U32);
            if !integer || accessor.dimensions() != Dimensions::Scalar {
                return Err(ctx.bad(format!(
                    "indices must be unsigned integer scalars, found {:?} {:?}",
                    accessor.data_type(),
                    accessor.dimensions()
                )));
            }
            if accessor.count() == 0 {
                return Ok(None);
            }
            let indices: Vec<u32> = reader
                .read_indices()
                .ok_or_else(|| ctx.bad("index data is missing or outside its buffer"))?
                .into_u32()
                .collect();
            if indices.len() != accessor.count() {
                return Err(ctx.bad("index data is shorter than its accessor"));
            }
            indices
        }
    };
    if !flat.chunks_exact(3).remainder().is_empty() {
        return Err(ctx.bad(format!("{} indices do not make whole triangles", flat.len())));
    }
    if let Some(&index) = flat.iter().find(|&&i| i as usize >= positions.len()) {
        return Err(GltfImportError::IndexOutOfRange {
            path: ctx.path.to_owned(),
            mesh: ctx.mesh,
            primitive: ctx.primitive,
            index,
            vertices: positions.len(),
        });
    }
    let indices: Vec<[u32; 3]> = flat.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
    if indices.is_empty() {
        return Ok(None);
    }
    Ok(Some(Mesh { positions, normals, indices }))
}

/// The material factors this importer looks at (all linear, as glTF stores them).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaterialFactors {
    pub base_color: Vec3,
    pub metallic: f32,
    pub roughness: f32,
    /// Emissive factor times `KHR_materials_emissive_strength`.
    pub emission: Vec3,
    pub transmission: f32,
    pub ior: Option<f32>,
}

impl MaterialFactors {
    /// Maps glTF PBR factors to a reference-renderer material (see the module docs for the
    /// rules). Factors are clamped into range; a non-finite emission gives `None`.
    pub fn to_material(&self) -> Option<Material> {
        let base = self.base_color.clamp(Vec3::ZERO, Vec3::ONE);
        let base = if base.is_finite() { base } else { Vec3::splat(0.8) };
        let unit = |x: f32| {
            if x.is_finite() { x.clamp(0.0, 1.0) } else { 0.0 }
        };
        let (metallic, roughness) = (unit(self.metallic), unit(self.roughness));
        let emission = self.emission.max(Vec3::ZERO);
        if !emission.is_finite() {
            return None;
        }
        Some(if emission.max_element() > 0.0 {
            Material::emissive(emission)
        } else if unit(self.transmission) > 0.5 {
            let ior = self.ior.filter(|i| i.is_finite() && *i >= 1.0).unwrap_or(1.5);
            Material::glass(ior, base)
        } else if metallic > 0.5 {
            Material::metal(base, roughness)
        } else if roughness < 0.6 {
            Material::glossy(base * (1.0 - metallic), Vec3::splat(0.04).lerp(base, metallic), roughness)
        } else {
            Material::lambertian(base)
        })
    }
}

fn material_of(path: &Path, material: &gltf::Material<'_>) -> Result<Material, GltfImportError> {
    let Some(index) = material.index() else {
        return Ok(Material::lambertian(Vec3::splat(0.8)));
    };
    let pbr = material.pbr_metallic_roughness();
    let [r, g, b, _alpha] = pbr.base_color_factor();
    let factors = MaterialFactors {
        base_color: Vec3::new(r, g, b),
        metallic: pbr.metallic_factor(),
        roughness: pbr.roughness_factor(),
        emission: Vec3::from(material.emissive_factor()) * material.emissive_strength().unwrap_or(1.0),
        transmission: material.transmission().map_or(0.0, |t| t.transmission_factor()),
        ior: material.ior(),
    };
    factors.to_material().ok_or_else(|| GltfImportError::BadMaterial {
        path: path.to_owned(),
        material: index,
        reason: "emission is not finite".to_owned(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn base64(bytes: &[u8]) -> String {
        const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
        let mut out = String::new();
        for chunk in bytes.chunks(3) {
            let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
            let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
            for k in 0..4 {
                if k <= chunk.len() {
                    out.push(ALPHABET[(n >> (18 - 6 * k) & 63) as usize] as char);
                } else {
                    out.push('=');
                }
            }
        }
        out
    }

    /// One triangle (0,0,0), (1,0,0), (0,1,0) with +Z normals and u16 `indices`.
    fn buffer(indices: [u16; 3]) -> Vec<u8> {
        let mut bytes = Vec::new();
        for p in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
            p.iter().for_each(|x| bytes.extend(x.to_le_bytes()));
        }
        for _ in 0..3 {
            [0.0f32, 0.0, 1.0].iter().for_each(|x| bytes.extend(x.to_le_bytes()));
        }
        indices.iter().for_each(|i| bytes.extend(i.to_le_bytes()));
        bytes.extend([0, 0]);
        bytes
    }

    /// A glTF with 5 material variants of the triangle, a parent/child pair, a mirrored
    /// node, a points primitive, an implicit-index primitive and a node outside the scene.
    fn sample(indices: [u16; 3]) -> String {
        let data = buffer(indices);
        let tri = |material: &str| {
            format!(r#"{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1}},"indices":2{material}}}]}}"#)
        };
        let meshes = [
            tri(r#","material":0"#),
            tri(r#","material":1"#),
            tri(r#","material":2"#),
            tri(r#","material":3"#),
            tri(r#","material":4"#),
            r#"{"primitives":[{"attributes":{"POSITION":0},"mode":0},{"attributes":{"POSITION":0}}]}"#.to_owned(),
        ]
        .join(",");
        format!(
            r#"{{
  "asset": {{"version": "2.0"}},
  "extensionsUsed": ["KHR_materials_transmission", "KHR_materials_ior", "KHR_materials_emissive_strength"],
  "scene": 0,
  "scenes": [{{"nodes": [0, 1, 3, 4, 5, 6, 7]}}],
  "nodes": [
    {{"mesh": 0, "translation": [1, 2, 3]}},
    {{"scale": [2, 2, 2], "children": [2]}},
    {{"mesh": 1, "translation": [0, 0, 1]}},
    {{"mesh": 2}},
    {{"mesh": 3}},
    {{"mesh": 4}},
    {{"mesh": 5}},
    {{"mesh": 0, "scale": [-1, 1, 1]}},
    {{"mesh": 0, "translation": [100, 0, 0]}}
  ],
  "meshes": [{meshes}],
  "materials": [
    {{"pbrMetallicRoughness": {{"baseColorFactor": [0.8, 0.2, 0.1, 1], "metallicFactor": 0, "roughnessFactor": 0.9}}}},
    {{"pbrMetallicRoughness": {{"baseColorFactor": [0.9, 0.8, 0.5, 1], "metallicFactor": 1, "roughnessFactor": 0.3}}}},
    {{"pbrMetallicRoughness": {{"baseColorFactor": [0.1, 0.2, 0.7, 1], "metallicFactor": 0, "roughnessFactor": 0.2}}}},
    {{"pbrMetallicRoughness": {{"baseColorFactor": [0.9, 1, 0.95, 1], "metallicFactor": 0, "roughnessFactor": 0}},
      "extensions": {{"KHR_materials_transmission": {{"transmissionFactor": 1}}, "KHR_materials_ior": {{"ior": 1.45}}}}}},
    {{"emissiveFactor": [1, 0.5, 0.25], "extensions": {{"KHR_materials_emissive_strength": {{"emissiveStrength": 4}}}}}}
  ],
  "buffers": [{{"byteLength": {len}, "uri": "data:application/octet-stream;base64,{b64}"}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 36}},
    {{"buffer": 0, "byteOffset": 36, "byteLength": 36}},
    {{"buffer": 0, "byteOffset": 72, "byteLength": 6}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]}},
    {{"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"}},
    {{"bufferView": 2, "componentType": 5123, "count": 3, "type": "SCALAR"}}
  ]
}}"#,
            len = data.len(),
            b64 = base64(&data),
        )
    }

    fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
        let path = dir.path().join(name);
        std::fs::write(&path, text).expect("write test file");
        path
    }

    fn path_of(dir: &tempfile::TempDir) -> PathBuf {
        write(dir, "good.gltf", &sample([0, 1, 2]))
    }

    fn triangle(scene: &Scene, t: usize) -> [Vec3; 3] {
        scene.mesh.indices[t].map(|i| scene.mesh.positions[i as usize])
    }

    fn close(a: Vec3, b: Vec3) -> bool {
        a.distance(b) < 1e-5
    }

    #[test]
    fn base64_encoder_matches_known_values() {
        assert_eq!(base64(b"Man"), "TWFu");
        assert_eq!(base64(b"Ma"), "TWE=");
        assert_eq!(base64(b"M"), "TQ==");
    }

    #[test]
    fn imports_triangles_transforms_and_materials() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = write(&dir, "sample.gltf", &sample([0, 1, 2]));
        let scene = import_gltf(&path).expect("imports");
        // Nodes 0, 2 (child of 1), 3, 4, 5, 6 (its points primitive skipped), 7; node 8 is
        // not in the scene.
        assert_eq!(scene.triangle_count(), 7);
        // Node 0: glTF (x, y, z) + (1, 2, 3), then Y-up to Z-up (x, y, z) -> (x, -z, y).
        let [a, b, c] = triangle(&scene, 0);
        assert!(close(a, Vec3::new(1.0, -3.0, 2.0)), "{a}");
        assert!(close(b, Vec3::new(2.0, -3.0, 2.0)), "{b}");
        assert!(close(c, Vec3::new(1.0, -3.0, 3.0)), "{c}");
        // glTF +Z normal becomes -Y, and agrees with the winding.
        let normals = scene.mesh.normals.as_ref().expect("normals");
        let n0 = normals[scene.mesh.indices[0][0] as usize];
        assert!(close(n0, Vec3::NEG_Y), "{n0}");
        // Node 2 under node 1: scale 2 after translation (0, 0, 1): (1, 0, 0) -> (2, 0, 2)
        // in glTF -> (2, -2, 0).
        let [a, b, _] = triangle(&scene, 1);
        assert!(close(a, Vec3::new(0.0, -2.0, 0.0)), "{a}");
        assert!(close(b, Vec3::new(2.0, -2.0, 0.0)), "{b}");
        // Every triangle's shading normals agree with its winding, the mirrored one too.
        for t in 0..scene.triangle_count() {
            let [a, b, c] = triangle(&scene, t);
            let g = (b - a).cross(c - a);
            for &i in &scene.mesh.indices[t] {
                assert!(normals[i as usize].dot(g) > 0.0, "triangle {t}");
            }
        }
        // The mirrored node 7: glTF (1, 0, 0) -> (-1, 0, 0), unchanged by the axis swap.
        let mirrored = triangle(&scene, 6);
        assert!(mirrored.iter().any(|&p| close(p, Vec3::new(-1.0, 0.0, 0.0))), "{mirrored:?}");
        let material = |t: usize| scene.materials[scene.material_of_triangle[t] as usize];
        assert_eq!(material(0), Material::lambertian(Vec3::new(0.8, 0.2, 0.1)));
        assert_eq!(material(1), Material::metal(Vec3::new(0.9, 0.8, 0.5), 0.3));
        assert_eq!(material(2), Material::glossy(Vec3::new(0.1, 0.2, 0.7), Vec3::splat(0.04), 0.2));
        assert_eq!(material(3), Material::glass(1.45, Vec3::new(0.9, 1.0, 0.95)));
        assert_eq!(material(4), Material::emissive(Vec3::new(4.0, 2.0, 1.0)));
        assert_eq!(material(5), Material::lambertian(Vec3::splat(0.8)), "no material");
        assert_eq!(material(6), material(0));
        assert!(scene.sun.is_some(), "default daylight");
    }

    #[test]
    fn import_into_applies_the_callers_transform_after_the_axis_change() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = write(&dir, "sample.gltf", &sample([0, 1, 2]));
        let mut builder = SceneBuilder::new();
        let shift = Affine3A::from_translation(Vec3::new(10.0, 0.0, 0.0));
        import_gltf_into(&mut builder, &path, shift).expect("imports");
        let scene = builder.build().expect("valid");
        let [a, _, _] = triangle(&scene, 0);
        assert!(close(a, Vec3::new(11.0, -3.0, 2.0)), "{a}");
        assert!(scene.sun.is_none(), "lighting is the caller's");
    }

    #[test]
    fn malformed_files_are_errors_not_panics() {
        let dir = tempfile::tempdir().expect("tempdir");
        let missing = dir.path().join("missing.gltf");
        assert!(matches!(import_gltf(&missing), Err(GltfImportError::NotFound { .. })));

        let junk = write(&dir, "junk.gltf", "this is not glTF");
        assert!(matches!(import_gltf(&junk), Err(GltfImportError::Parse { .. })));

        let empty = write(&dir, "empty.gltf", r#"{"asset": {"version": "2.0"}}"#);
        let err = import_gltf(&empty).expect_err("no meshes");
        assert!(matches!(err, GltfImportError::NoMeshes { .. }), "{err}");

        let out_of_range = write(&dir, "range.gltf", &sample([0, 1, 7]));
        let err = import_gltf(&out_of_range).expect_err("bad index");
        assert!(matches!(err, GltfImportError::IndexOutOfRange { index: 7, vertices: 3, .. }), "{err}");

        // An accessor claiming more data than its buffer view holds.
        let long =
            sample([0, 1, 2]).replace(r#""count": 3, "type": "VEC3", "min""#, r#""count": 300, "type": "VEC3", "min""#);
        assert!(import_gltf(&write(&dir, "long.gltf", &long)).is_err());

        // Indices stored as floats.
        let float_indices = sample([0, 1, 2]).replace(
            r#""componentType": 5123, "count": 3, "type": "SCALAR""#,
            r#""componentType": 5126, "count": 1, "type": "SCALAR""#,
        );
        let err = import_gltf(&write(&dir, "float.gltf", &float_indices)).expect_err("float");
        assert!(matches!(err, GltfImportError::BadPrimitive { .. }), "{err}");

        // A node hierarchy with a cycle.
        let cycle =
            sample([0, 1, 2]).replace(r#"{"mesh": 0, "translation": [100, 0, 0]}"#, r#"{"mesh": 0, "children": [8]}"#);
        let cycle = cycle.replace(r#""nodes": [0, 1, 3, 4, 5, 6, 7]"#, r#""nodes": [8]"#);
        assert!(import_gltf(&write(&dir, "cycle.gltf", &cycle)).is_err());

        // A buffer URI the `gltf` crate cannot decode (it panics inside; we must not).
        let good = sample([0, 1, 2]);
        let start = good.find("data:application").expect("data URI");
        let end = start + good[start..].find('"').expect("end of URI");
        let bad_uri = format!("{}%FF%FE{}", &good[..start], &good[end..]);
        let err = import_gltf(&write(&dir, "uri.gltf", &bad_uri)).expect_err("bad URI");
        assert!(matches!(err, GltfImportError::BadUri { .. }), "{err}");
        // A relative buffer file that does not exist.
        let absent = format!("{}absent.bin{}", &good[..start], &good[end..]);
        let err = import_gltf(&write(&dir, "absent.gltf", &absent)).expect_err("no buffer");
        assert!(matches!(err, GltfImportError::Buffers { .. }), "{err}");

        // A scene with only a points primitive.
        let points = sample([0, 1, 2]).replace(r#""nodes": [0, 1, 3, 4, 5, 6, 7]"#, r#""nodes": []"#);
        let err = import_gltf(&write(&dir, "points.gltf", &points)).expect_err("no triangles");
        assert!(matches!(err, GltfImportError::NoTriangles { .. }), "{err}");

        let nan = Affine3A::from_translation(Vec3::NAN);
        let err = import_gltf_into(&mut SceneBuilder::new(), &path_of(&dir), nan).expect_err("NaN");
        assert!(matches!(err, GltfImportError::BadPlacement { .. }), "{err}");

        // A failed import leaves the builder as it was.
        let mut builder = SceneBuilder::new();
        assert!(import_gltf_into(&mut builder, &out_of_range, Affine3A::IDENTITY).is_err());
        assert!(builder.build().is_err(), "still empty");
    }

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%20b.bin").as_deref(), Some("a b.bin"));
        assert_eq!(percent_decode("100%").as_deref(), Some("100%"));
        assert_eq!(percent_decode("%C3%A9").as_deref(), Some("\u{e9}"));
        assert_eq!(percent_decode("%FF"), None);
    }

    #[test]
    fn material_mapping_rules() {
        let plain = MaterialFactors {
            base_color: Vec3::new(0.5, 0.4, 0.3),
            metallic: 0.0,
            roughness: 1.0,
            emission: Vec3::ZERO,
            transmission: 0.0,
            ior: None,
        };
        assert_eq!(plain.to_material(), Some(Material::lambertian(plain.base_color)));
        let emissive = MaterialFactors { emission: Vec3::splat(3.0), metallic: 1.0, ..plain };
        assert_eq!(emissive.to_material(), Some(Material::emissive(Vec3::splat(3.0))));
        let glass = MaterialFactors { transmission: 0.9, ..plain };
        assert_eq!(glass.to_material(), Some(Material::glass(1.5, plain.base_color)));
        let half_metal = MaterialFactors { metallic: 0.5, roughness: 0.4, ..plain };
        let Some(Material::Glossy { albedo, specular, roughness }) = half_metal.to_material() else {
            panic!("glossy expected");
        };
        assert!(close(albedo, plain.base_color * 0.5));
        assert!(close(specular, (Vec3::splat(0.04) + plain.base_color) * 0.5));
        assert_eq!(roughness, 0.4);
        let wild = MaterialFactors { base_color: Vec3::splat(7.0), roughness: -3.0, ..plain };
        let material = wild.to_material().expect("clamped");
        assert!(material.validate().is_ok(), "{material:?}");
        let bad = MaterialFactors { emission: Vec3::INFINITY, ..plain };
        assert_eq!(bad.to_material(), None);
    }
}
