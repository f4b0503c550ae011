//! `nephele-train`: everything that learns or bakes, and the data it learns from.
//!
//! * [`dataset`]: NeRF-synthetic datasets (read, write, hold out views);
//! * [`synth`]: datasets of a scene rendered by the reference path tracer;
//! * [`ngp`]: training the i-NGP-style radiance field (the baseline, and the density field
//!   i-NOLF caches);
//! * [`inolf`]: training the i-NOLF heads and baking the asset;
//! * [`nelf`]: distilling the radiance field into a NeLF (R2L), with a hard-example pool;
//! * [`score`]: a kernel scored on a dataset's views (PSNR and SSIM over white), one way;
//! * [`checkpoint`]: the one checkpoint format of the trainers that resume;
//! * [`gi`]: G-buffer datasets for the stereo global-illumination model;
//! * [`targets`]: training targets from images, with corrupt pixels clamped or dropped and
//!   counted.
//!
//! Depends on every library below it (geometry, imaging, the path tracer, the neural
//! blocks, the kernels); nothing at run time (worker, master, composer) depends on it.

pub mod checkpoint;
pub mod dataset;
pub mod gi;
pub mod inolf;
pub mod nelf;
pub mod ngp;
pub mod score;
pub mod synth;
pub mod targets;
