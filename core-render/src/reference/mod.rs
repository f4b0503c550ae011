//! The reference renderer: a multi-threaded CPU path tracer over triangle meshes with a BVH.
//! It is the ground truth for every metric and the teacher for every distillation.

pub mod bvh;
pub mod gltf_import;
pub mod integrator;
pub mod material;
pub mod sampling;
pub mod scene;

pub use integrator::{Background, RenderError, RenderOptions, RenderOutput, RenderStats, Renderer};
pub use material::Material;
pub use scene::{Environment, Mesh, Scene, SceneBuilder, Sun};
