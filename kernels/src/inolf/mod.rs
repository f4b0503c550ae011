//! i-NOLF (NEPHELE section 4): the one-query-per-ray neural object kernel and its parts.
//!
//! * [`cubes`]: density (and diffuse) texture cubes and the ray marcher over them.
//! * [`psh`]: Perfect Spatial Hashing of the voxels around the hit surfaces.
//! * [`encoding`]: the PSH feature encoding of hit points (specular branch input).
//! * [`model`]: the diffuse and specular heads and the loss (eqs. 5-8).
//! * [`heads`]: the networks read back from an asset, the diffuse cubes' 8-bit code.
//! * [`asset`]: the versioned `.nolf` asset file and its defensive loader.
//! * [`kernel`]: [`kernel::InolfKernel`], the farm kernel.
//! * [`synthetic`]: a synthetic object with every part of an asset, for tests and benchmarks.
//!
//! Training the heads and baking the asset live in `nephele-train` (`inolf::train`,
//! `inolf::bake`); surface voxelisation of meshes in `nephele-pathtracer` (`voxel`).

pub mod asset;
pub mod cubes;
pub mod encoding;
pub mod heads;
pub mod kernel;
pub mod model;
pub mod psh;
pub mod synthetic;
