//! `nephele-kernels`: the runtime render kernels behind one interface.
//!
//! * [`kernel`]: [`kernel::RayKernel`] (a camera and a pixel set in, colour, opacity and
//!   depth out), its errors and statistics, and the reference path tracer as a farm kernel;
//! * [`ngp`]: the i-NGP-style radiance field (the baseline): its inference, occupancy
//!   skipping and file format;
//! * [`inolf`]: i-NOLF (NEPHELE section 4): density and diffuse texture cubes, perfect
//!   spatial hashing, the heads, the `.nolf` asset and its kernel;
//! * [`nelf`]: NeLF (R2L): a light field distilled from the radiance field, one query of a
//!   deep residual MLP per ray, and its `.nelf` asset;
//! * [`gi`]: the stereo global-illumination model (a U-Net over G-buffers) and its `.ngi`
//!   file; [`environment`]: a room shaded by it as a farm kernel (G-buffer, one stereo pass
//!   for a pair of eyes, opaque pixels with depth);
//! * [`assets`]: the one registry of asset formats, shared by the worker and `nephele render`.
//!
//! Depends on `nephele-geometry`, `nephele-imaging`, `nephele-nn` and `nephele-pathtracer`
//! (for the path-traced kernel); never on trainers (`nephele-train`) or services. The worker
//! links this crate and nothing that trains.

pub mod assets;
pub mod environment;
pub mod gi;
pub mod inolf;
pub mod kernel;
pub mod nelf;
pub mod ngp;
