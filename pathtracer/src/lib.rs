//! The reference renderer: a multi-threaded CPU path tracer over triangle meshes with a BVH.
//! It is the ground truth for every metric and the teacher for every distillation.
//!
//! `nephele-pathtracer` owns the renderer ([`integrator`], [`bvh`], [`material`],
//! [`sampling`]), the scene description ([`scene`]), the built-in procedural scenes
//! ([`scenes`]), glTF import ([`gltf_import`]) and surface voxelisation of meshes
//! ([`voxel`]). It depends on `nephele-geometry` (cameras) and `nephele-imaging` (output
//! images) only; nothing neural and nothing of the services belongs here.

pub mod bvh;
pub mod gltf_import;
pub mod integrator;
pub mod material;
pub mod sampling;
pub mod scene;
pub mod scenes;
pub mod voxel;

pub use integrator::{Background, RenderError, RenderOptions, RenderOutput, RenderStats, Renderer};
pub use material::Material;
pub use scene::{Environment, Mesh, Scene, SceneBuilder, Sun};
