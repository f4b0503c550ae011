//! i-NOLF (NEPHELE section 4): the one-query-per-ray neural object kernel and its parts.
//!
//! * [`cubes`]: density (and diffuse) texture cubes and the ray marcher over them.
//! * [`psh`]: Perfect Spatial Hashing of the voxels around the hit surfaces.
//! * [`encoding`]: the PSH feature encoding of hit points (specular branch input).
//! * [`model`]: the diffuse and specular heads and the loss (eqs. 5-8).
//! * [`train`]: training the heads from posed RGBA images with an error map.
//! * [`bake`]: diffuse texture cubes and the assembly of the asset.
//! * [`asset`]: the versioned `.nolf` asset file and its defensive loader.
//! * [`kernel`]: [`kernel::InolfKernel`], the farm kernel.
//! * [`voxel`]: surface voxelisation of meshes (occupancies for tests and benchmarks).

pub mod asset;
pub mod bake;
pub mod cubes;
pub mod encoding;
pub mod kernel;
pub mod model;
pub mod psh;
pub mod train;
pub mod voxel;

#[cfg(test)]
mod pipeline_tests;
#[cfg(test)]
mod scene_tests;
