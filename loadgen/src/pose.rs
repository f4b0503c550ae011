//! Pose messages as the browser client sends them (`client/PROTOCOL.md`), and the scripted
//! camera the load generator flies.

use glam::{Mat4, Vec3};
use nephele_geometry::ViewProjection;
use nephele_proto::pose::Pose;
pub use nephele_proto::pose::{
    MODE_FLAT, MODE_QUILT, MODE_XR, POSE_HEADER_BYTES as HEADER_BYTES, POSE_VIEW_BYTES as VIEW_BYTES,
};

/// What a simulated user looks through.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum UserDisplay {
    /// A flat screen: one view.
    #[default]
    Flat,
    /// A WebXR headset: two eyes this many metres apart.
    Stereo { ipd: f32 },
    /// A light-field display: Looking Glass's quilt of
    /// [`nephele_geometry::camera::QUILT_VIEWS`] views.
    Quilt,
}

impl UserDisplay {
    /// Views per pose.
    pub fn views(self) -> u16 {
        match self {
            UserDisplay::Flat => 1,
            UserDisplay::Stereo { .. } => 2,
            UserDisplay::Quilt => nephele_geometry::camera::QUILT_VIEWS as u16,
        }
    }

    /// The pose's display mode.
    pub fn mode(self) -> u8 {
        match self {
            UserDisplay::Flat => MODE_FLAT,
            UserDisplay::Stereo { .. } => MODE_XR,
            UserDisplay::Quilt => MODE_QUILT,
        }
    }
}

/// One pose message through the one Rust encoder (`nephele_proto::pose`): `views` are
/// (world-to-camera, projection) pairs, each of `width x height`.
pub fn encode(
    sequence: u32,
    client_time_ms: f64,
    width: u16,
    height: u16,
    mode: u8,
    views: &[(Mat4, Mat4)],
) -> Vec<u8> {
    let (width, height) = (u32::from(width), u32::from(height));
    let views = views.iter().map(|&(view, projection)| ViewProjection { width, height, view, projection }).collect();
    Pose { seq: sequence, mode, client_time_ms, views }.encode()
}

/// Near and far planes of the scripted cameras (the browser client's).
const NEAR: f32 = 0.05;
const FAR: f32 = 1000.0;

/// A camera orbiting the scene target at a constant angular speed, as a user dragging would:
/// the first view the master suggests, turned by `speed` radians per second around +Z.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScriptedOrbit {
    pub eye: Vec3,
    pub target: Vec3,
    pub fov_y_deg: f32,
    /// Radians per second.
    pub speed: f32,
}

impl ScriptedOrbit {
    /// The camera `t` seconds in, for one view of aspect `aspect` (world +Z up, OpenGL camera).
    pub fn view_at(&self, t: f32, aspect: f32) -> (Mat4, Mat4) {
        let offset = self.eye - self.target;
        let turned = glam::Quat::from_rotation_z(self.speed * t) * offset;
        (
            world_to_camera(self.target + turned, self.target),
            perspective(self.fov_y_deg.to_radians(), aspect, NEAR, FAR),
        )
    }

    /// The two eyes of a head at the orbit's camera `t` seconds in, `ipd` metres apart
    /// (left, then right, as WebXR lists them): the head's world-to-camera matrix with the
    /// eye's offset along the head's right axis, and the same projection for both.
    pub fn stereo_views_at(&self, t: f32, aspect: f32, ipd: f32) -> [(Mat4, Mat4); 2] {
        let (head, projection) = self.view_at(t, aspect);
        // An eye at +x (head space) sees the world shifted by -x.
        let eye = |x: f32| (Mat4::from_translation(Vec3::new(-x, 0.0, 0.0)) * head, projection);
        [eye(-0.5 * ipd), eye(0.5 * ipd)]
    }

    /// A quilt's views around the orbit's camera `t` seconds in, in the slots' packing order
    /// (`nephele_proto::pose::quilt_slot_views`): the light-field rig of
    /// `nephele_geometry::camera::quilt_rig`, focused on the orbit's target, as the browser
    /// client's quilt display sends it.
    pub fn quilt_views_at(&self, t: f32, width: u16, height: u16) -> Vec<(Mat4, Mat4)> {
        use nephele_geometry::camera::{Camera, QUILT_VIEW_CONE_DEG, QUILT_VIEWS, quilt_rig};
        use nephele_proto::pose::quilt_slot_views;
        let (width, height) = (u32::from(width), u32::from(height));
        let (view, projection) = self.view_at(t, width as f32 / height as f32);
        let focal = self.eye.distance(self.target);
        let rig = Camera::from_view_projection(width, height, view, projection)
            .and_then(|centre| quilt_rig(&centre, QUILT_VIEWS, QUILT_VIEW_CONE_DEG.to_radians(), focal));
        match rig {
            Ok(rig) => quilt_slot_views(QUILT_VIEWS as u16)
                .into_iter()
                .map(|k| (rig[k].world_to_camera(), rig[k].projection_matrix(NEAR, FAR)))
                .collect(),
            // Only for a degenerate orbit (eye on the target): the centre view everywhere.
            Err(_) => vec![(view, projection); QUILT_VIEWS],
        }
    }

    /// The views of one pose message for `display`, each `width x height`.
    pub fn views_at(&self, t: f32, width: u16, height: u16, display: UserDisplay) -> Vec<(Mat4, Mat4)> {
        let aspect = f32::from(width) / f32::from(height);
        match display {
            UserDisplay::Flat => vec![self.view_at(t, aspect)],
            UserDisplay::Stereo { ipd } => self.stereo_views_at(t, aspect, ipd).to_vec(),
            UserDisplay::Quilt => self.quilt_views_at(t, width, height),
        }
    }
}

/// World-to-camera (view) matrix of an OpenGL camera at `eye` looking at `target` with
/// world +Z up, as the browser client's `mat4.lookAt` gives: the inverse of the workspace's
/// one look-at. A camera looking straight down or up takes +Y as its up instead; `eye ==
/// target` (no direction at all) keeps the world axes.
pub fn world_to_camera(eye: Vec3, target: Vec3) -> Mat4 {
    use nephele_geometry::camera::look_at_camera_to_world;
    look_at_camera_to_world(eye, target, Vec3::Z)
        .or_else(|_| look_at_camera_to_world(eye, target, Vec3::Y))
        .map_or(Mat4::from_translation(-eye), |camera_to_world| camera_to_world.inverse())
}

/// OpenGL perspective projection (clip z in [-1, 1]), as WebXR and the browser client give.
pub fn perspective(fov_y: f32, aspect: f32, near: f32, far: f32) -> Mat4 {
    let f = 1.0 / (fov_y / 2.0).tan();
    Mat4::from_cols_array(&[
        f / aspect,
        0.0,
        0.0,
        0.0,
        0.0,
        f,
        0.0,
        0.0,
        0.0,
        0.0,
        (far + near) / (near - far),
        -1.0,
        0.0,
        0.0,
        2.0 * far * near / (near - far),
        0.0,
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quilt_user_sends_the_light_field_rig_in_slot_order_focused_on_the_target() {
        use nephele_geometry::camera::Camera;
        let orbit = ScriptedOrbit { eye: Vec3::new(0.0, -4.0, 2.0), target: Vec3::ZERO, fov_y_deg: 40.0, speed: 0.5 };
        let views = orbit.views_at(1.0, 180, 240, UserDisplay::Quilt);
        assert_eq!(views.len(), 45);
        let cameras: Vec<Camera> =
            views.iter().map(|&(v, p)| Camera::from_view_projection(180, 240, v, p).expect("camera")).collect();
        // The middle slot is the orbit's own camera; the target lands on the same pixel in
        // every view; the bottom-left slot (40) is the leftmost camera, the top-left (0) view 40.
        let (centre, _) = orbit.view_at(1.0, 0.75);
        assert!(cameras[22].world_to_camera().abs_diff_eq(centre, 1e-5));
        let at = cameras[22].project(orbit.target).expect("in view");
        for c in &cameras {
            assert!(c.project(orbit.target).expect("in view").distance(at) < 1e-2);
        }
        let x = |slot: usize| cameras[22].right().dot(cameras[slot].position() - cameras[22].position());
        let step = x(41) - x(40);
        assert!(step > 0.0 && (x(0) - x(40) - 40.0 * step).abs() < 1e-3, "{} {}", x(0), step);
        // 44 steps span 2 tan(cone / 2) focal distances.
        let half_cone = nephele_geometry::camera::QUILT_VIEW_CONE_DEG.to_radians() / 2.0;
        let span = 2.0 * half_cone.tan() * orbit.eye.distance(orbit.target);
        assert!((44.0 * step - span).abs() < 1e-3, "{} vs {span}", 44.0 * step);
    }

    #[test]
    fn encodes_the_documented_layout() {
        let orbit = ScriptedOrbit { eye: Vec3::new(0.0, -4.0, 2.0), target: Vec3::ZERO, fov_y_deg: 40.0, speed: 0.5 };
        let v = orbit.view_at(0.0, 4.0 / 3.0);
        let data = encode(9, 1234.5, 640, 480, MODE_FLAT, &[v, v]);
        assert_eq!(data.len(), 20 + 2 * 128);
        assert_eq!(&data[..4], &[0x50, 1, 2, 0]);
        assert_eq!(u32::from_le_bytes([data[4], data[5], data[6], data[7]]), 9);
        assert_eq!(f64::from_le_bytes(data[8..16].try_into().expect("8 bytes")), 1234.5);
        assert_eq!((u16::from_le_bytes([data[16], data[17]]), u16::from_le_bytes([data[18], data[19]])), (640, 480));
        // The view matrix maps the eye to the camera origin and the target down -Z.
        let eye = v.0.transform_point3(Vec3::new(0.0, -4.0, 2.0));
        assert!(eye.length() < 1e-5);
        let target = v.0.transform_point3(Vec3::ZERO);
        assert!(target.x.abs() < 1e-5 && target.y.abs() < 1e-5 && target.z < 0.0);
        let m0 = f32::from_le_bytes(data[20..24].try_into().expect("4 bytes"));
        assert_eq!(m0, v.0.to_cols_array()[0]);
    }

    #[test]
    fn the_orbit_turns_at_its_speed_and_keeps_its_radius() {
        let orbit = ScriptedOrbit { eye: Vec3::new(4.0, 0.0, 1.0), target: Vec3::ZERO, fov_y_deg: 40.0, speed: 0.5 };
        let (view, _) = orbit.view_at(std::f32::consts::PI, 1.0); // a quarter turn
        let eye = view.inverse().transform_point3(Vec3::ZERO);
        assert!((eye - Vec3::new(0.0, 4.0, 1.0)).length() < 1e-4, "{eye}");
    }

    #[test]
    fn stereo_eyes_are_ipd_apart_across_the_gaze_around_the_head() {
        let orbit = ScriptedOrbit { eye: Vec3::new(0.0, -4.0, 0.0), target: Vec3::ZERO, fov_y_deg: 40.0, speed: 0.5 };
        let (head, projection) = orbit.view_at(0.0, 1.0);
        let [left, right] = orbit.stereo_views_at(0.0, 1.0, 0.064);
        let position = |m: Mat4| m.inverse().transform_point3(Vec3::ZERO);
        let (l, r, h) = (position(left.0), position(right.0), position(head));
        // Looking along +y with +z up, the right eye is at +x.
        assert!((l - Vec3::new(-0.032, -4.0, 0.0)).length() < 1e-5, "{l}");
        assert!((r - Vec3::new(0.032, -4.0, 0.0)).length() < 1e-5, "{r}");
        assert!(((l + r) * 0.5 - h).length() < 1e-5);
        assert_eq!((left.1, right.1), (projection, projection));
        // Both eyes look the same way (parallel axes, as WebXR's views are).
        let gaze = |m: Mat4| m.inverse().transform_vector3(-Vec3::Z);
        assert!((gaze(left.0) - gaze(right.0)).length() < 1e-6);
        let pose = encode(1, 0.0, 64, 64, MODE_XR, &orbit.views_at(0.0, 64, 64, UserDisplay::Stereo { ipd: 0.064 }));
        assert_eq!((pose.len(), pose[2], pose[3]), (HEADER_BYTES + 2 * VIEW_BYTES, 2, MODE_XR));
    }
}
