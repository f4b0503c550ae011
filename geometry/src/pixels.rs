//! Per-pixel results and pixel sets: the unit of work of the render farm.
//!
//! Per-pixel conventions (see the crate documentation for the axes):
//! * `color` is linear RGB **premultiplied** by `opacity`, so that the composer can blend
//!   front to back with `C += (1 - A) * c; A += (1 - A) * a`;
//! * `opacity` is in `[0, 1]`;
//! * `depth` is view-space z distance in world units, finite and `> 0` where `opacity > 0`,
//!   exactly `0` where the pixel saw nothing.

use thiserror::Error;

use crate::camera::Camera;

/// A pixel index (`y * width + x`) outside the camera's image.
#[derive(Debug, Clone, Copy, Error, PartialEq, Eq)]
#[error("pixel index {index} is outside the {width}x{height} image")]
pub struct PixelOutOfImage {
    pub index: u32,
    pub width: u32,
    pub height: u32,
}

/// Per-pixel results of one batch, in the order the pixels were given. Packed arrays (one
/// allocation per channel) because that is how they travel on the wire.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PixelResults {
    pub color: Vec<[f32; 3]>,
    pub opacity: Vec<f32>,
    pub depth: Vec<f32>,
}

impl PixelResults {
    pub fn with_len(len: usize) -> PixelResults {
        PixelResults { color: vec![[0.0; 3]; len], opacity: vec![0.0; len], depth: vec![0.0; len] }
    }

    pub fn len(&self) -> usize {
        self.opacity.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity.is_empty()
    }

    /// Appends `other`'s pixels after these (the parts of a batch rendered in parallel, put
    /// back in order).
    pub fn append(&mut self, other: PixelResults) {
        self.color.extend(other.color);
        self.opacity.extend(other.opacity);
        self.depth.extend(other.depth);
    }
}

/// Checks that every pixel index lies inside `camera`'s image.
pub fn validate_pixels(camera: &Camera, pixels: &[u32]) -> Result<(), PixelOutOfImage> {
    let (width, height) = (camera.width(), camera.height());
    let count = u64::from(width) * u64::from(height);
    match pixels.iter().find(|&&p| u64::from(p) >= count) {
        Some(&index) => Err(PixelOutOfImage { index, width, height }),
        None => Ok(()),
    }
}

/// Every pixel of an image in row-major order: the pixel set of a full frame.
pub fn all_pixels(camera: &Camera) -> Vec<u32> {
    (0..camera.width() * camera.height()).collect()
}
