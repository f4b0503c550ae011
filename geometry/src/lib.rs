//! `nephele-geometry`: cameras, rays, bounds, camera rigs and per-pixel results, and the
//! conventions every other crate follows. It owns the one camera type of the whole system:
//! the wire, the scheduler, the kernels and the composer all speak [`camera::Camera`].
//!
//! Depends on nothing of ours and on no image, mesh or thread-pool crate (glam, serde and
//! thiserror only), so that the protocol, the pure scheduler, the composer and loadgen can use
//! it cheaply.
//!
//! # Conventions (stated once, converted at the edges)
//!
//! * **World space** is right-handed with **+Z up**, as in Blender and the NeRF-synthetic
//!   datasets. Units are metres.
//! * **Camera space** follows OpenGL and WebXR: +X right, +Y up, the camera looks down **-Z**.
//!   A camera-to-world matrix (NeRF's `transform_matrix`, WebXR's inverse view matrix) maps
//!   camera space to world space.
//! * **Pixels**: origin at the top-left corner of the image, +x right, +y down; pixel `(i, j)`
//!   covers `[i, i+1) x [j, j+1)` and its centre is `(i + 0.5, j + 0.5)`.
//! * **Depth** is view-space z distance (along the camera's -Z axis), in world units; a pixel
//!   whose rays hit nothing has depth 0 and alpha 0.
//! * **Colour** inside the renderer is linear radiance; PNG files hold sRGB-encoded 8-bit
//!   values with straight (not premultiplied) alpha, as NeRF-synthetic does. Image metrics
//!   work on the values stored in the files, in `[0, 1]`.

pub mod bounds;
pub mod camera;
pub mod hardcases;
pub mod pixels;
pub mod rng;
pub mod solid;
pub mod view;

pub use bounds::Bounds;
pub use camera::{Camera, CameraError, Ray};
pub use pixels::{PixelOutOfImage, PixelResults, all_pixels, validate_pixels};
pub use rng::SplitMix64;
pub use solid::{SolidGrid, SolidGridError};
pub use view::ViewProjection;
