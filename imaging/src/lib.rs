//! `nephele-imaging`: images and image metrics.
//!
//! * [`image`]: RGBA and float images, sRGB <-> linear conversions, PNG and OpenEXR files;
//! * [`metrics`]: PSNR and SSIM as NeRF papers compute them.
//!
//! Depends on nothing of ours. The conventions (sRGB-encoded colour with straight alpha in
//! files, linear premultiplied colour inside the renderers) are stated in `nephele-geometry`.

pub mod image;
pub mod metrics;
