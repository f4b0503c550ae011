//! i-NOLF (NEPHELE section 4): the one-query-per-ray neural object kernel and its parts.
//!
//! * [`asset`]: the versioned `.nolf` asset file and its defensive loader.
//! * [`cubes`]: density (and diffuse) texture cubes and the ray marcher over them.
//! * [`encoding`]: the PSH feature encoding of hit points (specular branch input).
//! * [`psh`]: Perfect Spatial Hashing of the voxels around the hit surfaces (the specular
//!   branch's single-resolution encoding).
//! * [`voxel`]: surface voxelisation of meshes (occupancies for tests and benchmarks).

pub mod asset;
pub mod cubes;
pub mod encoding;
pub mod psh;
pub mod voxel;

#[cfg(test)]
mod scene_tests;
