//! A view as WebXR and the wire give it: image size, view matrix and OpenGL projection.
//!
//! The browser sends views this way, the composer forwards them, the scheduler plans with
//! them and the master hands them to workers inside ray batches: one type from the browser
//! to the kernels, and the one conversion each way to a [`Camera`]
//! ([`ViewProjection::camera`], [`ViewProjection::of_camera`]). On the wire (postcard, JSON)
//! each matrix is 16 column-major `f32`s.

use glam::Mat4;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, CameraError};

/// One view: `view` is world-to-camera (`XRView.transform.inverse.matrix`), `projection`
/// follows OpenGL clip conventions, `width x height` is the image to render.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ViewProjection {
    pub width: u32,
    pub height: u32,
    pub view: Mat4,
    pub projection: Mat4,
}

impl ViewProjection {
    /// The camera this view describes (checks that the view is rigid and the projection a
    /// perspective one; see [`Camera::from_view_projection`]).
    pub fn camera(&self) -> Result<Camera, CameraError> {
        Camera::from_view_projection(self.width, self.height, self.view, self.projection)
    }

    /// `camera` as a view, its projection with clip planes `near` and `far` (they do not
    /// change the rays; they only make the matrix a complete OpenGL projection).
    pub fn of_camera(camera: &Camera, near: f32, far: f32) -> ViewProjection {
        ViewProjection {
            width: camera.width(),
            height: camera.height(),
            view: camera.world_to_camera(),
            projection: camera.projection_matrix(near, far),
        }
    }

    /// Both matrices finite.
    pub fn is_finite(&self) -> bool {
        self.view.is_finite() && self.projection.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    #[test]
    fn a_camera_survives_the_round_trip_and_the_wire_form_is_sixteen_floats_per_matrix() {
        let camera = Camera::look_at(64, 48, 0.9, Vec3::new(1.0, -3.0, 1.5), Vec3::ZERO, Vec3::Z).expect("camera");
        let view = ViewProjection::of_camera(&camera, 0.01, 100.0);
        let back = view.camera().expect("camera again");
        for (x, y) in [(0.5, 0.5), (63.5, 47.5), (32.0, 24.0)] {
            let (a, b) = (camera.ray(x, y), back.ray(x, y));
            assert!((a.origin - b.origin).length() < 1e-5 && (a.direction - b.direction).length() < 1e-5);
        }
        let json = serde_json::to_value(view).expect("json");
        assert_eq!(json["view"].as_array().map(Vec::len), Some(16));
        assert_eq!(json["view"][12].as_f64(), Some(f64::from(view.view.to_cols_array()[12])));
        assert!(view.is_finite());
        assert!(!ViewProjection { view: Mat4::NAN, ..view }.is_finite());
    }
}
