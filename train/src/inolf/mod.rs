//! Training and baking i-NOLF assets (NEPHELE sections 4.2, 4.3).
//!
//! * [`train`]: training the heads from posed RGBA images with an error map;
//! * [`pipeline`]: the whole bake as one call, [`pipeline::bake`] (what `nephele bake` and the
//!   first start run);
//! * [`bake`]: the density field for the cubes, diffuse texture cubes, the assembly of the
//!   asset.
//!
//! The asset's runtime parts (cubes, PSH, heads, the kernel) live in `nephele_kernels::inolf`.

pub mod bake;
pub mod pipeline;
pub mod train;

#[cfg(test)]
mod pipeline_tests;
#[cfg(test)]
mod scene_tests;
