//! Pinhole cameras, rays and camera rigs (stereo pairs, light-field quilts).
//!
//! Conventions (see the crate docs): world space is right-handed with +Z up; camera space is
//! OpenGL/WebXR (+X right, +Y up, looking down -Z); a camera-to-world matrix is NeRF's
//! `transform_matrix`. Pixel coordinates start at the top-left corner of the image, +x right,
//! +y down, so pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`. Depth is the view-space
//! distance along the camera's -Z axis.
//!
//! A [`Camera`] holds intrinsics in pixels (`fx, fy, cx, cy`, off-axis allowed) and its pose.
//! The camera-space direction through pixel `(x, y)` is `((x - cx) / fx, -(y - cy) / fy, -1)`.
//!
//! # WebXR
//!
//! An `XRView` gives a view matrix (`transform.inverse.matrix`, world to camera) and an OpenGL
//! `projectionMatrix`, usually asymmetric. For a frustum `l, r, b, t, n` that matrix is, in
//! row-major notation,
//! `[[2n/(r-l), 0, (r+l)/(r-l), 0], [0, 2n/(t-b), (t+b)/(t-b), 0], [0, 0, A, B], [0, 0, -1, 0]]`.
//! Mapping normalised device coordinates to pixels of a `w x h` image
//! (`x = (ndc_x + 1) w / 2`, `y = (1 - ndc_y) h / 2`) gives
//! `fx = P00 w / 2`, `cx = (1 - P02) w / 2`, `fy = P11 h / 2`, `cy = (1 + P12) h / 2`;
//! [`Camera::from_view_projection`] applies this and [`Camera::projection_matrix`] inverts it.

use glam::{Affine3A, Mat3, Mat4, Quat, Vec2, Vec3, Vec4};
use std::f32::consts::PI;

/// Largest accepted image side, in pixels.
pub const MAX_IMAGE_SIDE: u32 = 65536;
/// Largest accepted interpupillary distance, in metres.
pub const MAX_IPD: f32 = 1.0;
/// Most views one frame may have (1 flat screen, 2 stereo, 45 for a light-field quilt): the
/// one limit that [`quilt_rig`], the wire, the pose format, the scheduler, the master and the
/// composer all enforce.
pub const MAX_VIEWS: usize = 64;
/// Tolerance on the dot products of the rotation columns of a rigid matrix.
const ORTHONORMAL_TOLERANCE: f32 = 1e-3;
/// Tolerance on the last row of a rigid matrix being `(0, 0, 0, 1)`.
const LAST_ROW_TOLERANCE: f32 = 1e-5;
/// Relative tolerance on the entries that must vanish in a perspective projection.
const PROJECTION_TOLERANCE: f32 = 1e-5;
/// Largest accepted magnitude of `w / fx`, `h / fy`, `cx / fx`, `cy / fy`.
const MAX_NORMALISED_EXTENT: f32 = 1e12;
/// Points with a view-space z at or above this are treated as not in front of the camera.
const NEAR_PLANE_Z: f32 = -1e-6;

/// Parses an image size `WxH` (e.g. `800x800`) as the command line takes it: both sides
/// at least 1 and at most 16384.
pub fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(|| format!("expected WIDTHxHEIGHT, got '{text}'"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("bad width in '{text}'"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("bad height in '{text}'"))?;
    if w == 0 || h == 0 {
        return Err(format!("image size must be positive, got '{text}'"));
    }
    if w > 16384 || h > 16384 {
        return Err(format!("image size '{text}' exceeds 16384 on a side"));
    }
    Ok((w, h))
}

/// A ray `origin + t * direction`, `direction` of unit length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// Start of the ray (the camera centre for camera rays), world space.
    pub origin: Vec3,
    /// Unit-length direction, world space.
    pub direction: Vec3,
}

impl Ray {
    /// The point at distance `t` along the ray.
    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + t * self.direction
    }
}

/// Direction components smaller than this in magnitude are taken as exactly 0 by the
/// marchers: the reciprocal of a denormal component overflows to infinity (1 / 1e-40 in
/// f32), and across such a component the ray moves less than 1e-20 of its length.
pub const TINY_DIRECTION_COMPONENT: f32 = 1e-20;

/// The direction a marcher may step along: `dir` with its tiny components set to 0, or `None`
/// when `dir` is not a unit vector within a factor of two in squared length (zero, denormal,
/// NaN or infinite directions; a march along a tiny direction would take forever, since its
/// samples are spaced in `t`). Every marcher (CPU and GPU twins) applies this rule.
#[inline]
pub fn marchable_direction(dir: Vec3) -> Option<Vec3> {
    let length_squared = dir.length_squared();
    if !(0.5..=2.0).contains(&length_squared) {
        return None;
    }
    Some(Vec3::select(dir.abs().cmplt(Vec3::splat(TINY_DIRECTION_COMPONENT)), Vec3::ZERO, dir))
}

/// Why a camera or rig could not be built.
#[derive(Debug, Clone, Copy, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("image size {width}x{height} is empty: width and height must be at least 1 pixel")]
    ZeroSizeImage { width: u32, height: u32 },
    #[error("image size {width}x{height} is too large: each side must be at most 65536 pixels")]
    ImageTooLarge { width: u32, height: u32 },
    #[error("{0} is not finite (contains NaN or infinity)")]
    NonFinite(&'static str),
    #[error("field of view {0} rad is not in the open interval (0, pi)")]
    FieldOfView(f32),
    #[error("invalid intrinsics fx={fx}, fy={fy}, cx={cx}, cy={cy}: {reason}")]
    InvalidIntrinsics { fx: f32, fy: f32, cx: f32, cy: f32, reason: &'static str },
    #[error("the {matrix} matrix is not a rigid transform (rotation and translation): {reason}")]
    NotRigid { matrix: &'static str, reason: &'static str },
    #[error("the projection matrix is not an OpenGL perspective projection: {0}")]
    NotPerspective(&'static str),
    #[error("degenerate look-at: {0}")]
    DegenerateLookAt(&'static str),
    #[error("interpupillary distance {0} m is not a finite number in [0, 1] m")]
    InvalidIpd(f32),
    #[error("view count {0} is not in 1..=1024")]
    InvalidViewCount(usize),
    #[error("view cone {0} rad is not a finite angle in [0, pi)")]
    InvalidViewCone(f32),
    #[error("focal distance {0} is not a finite positive number")]
    InvalidFocalDistance(f32),
}

/// A pinhole camera with intrinsics in pixels (fx, fy, cx, cy) — off-axis allowed, as WebXR
/// per-eye projections are asymmetric.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    width: u32,
    height: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    camera_to_world: Mat4,
    world_to_camera: Mat4,
}

fn check_image_size(width: u32, height: u32) -> Result<(), CameraError> {
    if width == 0 || height == 0 {
        return Err(CameraError::ZeroSizeImage { width, height });
    }
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(CameraError::ImageTooLarge { width, height });
    }
    Ok(())
}

/// Checks a field of view and returns `tan(fov / 2)`.
fn check_fov(fov: f32) -> Result<f32, CameraError> {
    if !fov.is_finite() {
        return Err(CameraError::NonFinite("field of view"));
    }
    if fov <= 0.0 || fov >= PI {
        return Err(CameraError::FieldOfView(fov));
    }
    Ok((0.5 * fov).tan())
}

/// Checks that `m` is finite and rigid (orthonormal rotation with determinant +1, last row
/// `(0, 0, 0, 1)`); returns it with the last row set exactly.
fn check_rigid(m: Mat4, matrix: &'static str) -> Result<Mat4, CameraError> {
    if !m.is_finite() {
        return Err(CameraError::NonFinite(matrix));
    }
    let not_rigid = |reason| Err(CameraError::NotRigid { matrix, reason });
    if (m.row(3) - Vec4::W).abs().max_element() > LAST_ROW_TOLERANCE {
        return not_rigid("the last row is not (0, 0, 0, 1)");
    }
    let r = Mat3::from_mat4(m);
    // Column dot products: the identity for an orthonormal basis.
    if !(r.transpose() * r).abs_diff_eq(Mat3::IDENTITY, ORTHONORMAL_TOLERANCE) {
        return not_rigid("the 3x3 part is not orthonormal within 1e-3 (scale, shear, singular)");
    }
    if r.determinant() <= 0.0 {
        return not_rigid("the 3x3 part is a reflection");
    }
    Ok(Affine3A::from_mat3_translation(r, m.w_axis.truncate()).into())
}

/// Camera-to-world matrix of a camera at `eye` looking at `target` (OpenGL axes: the camera
/// looks down its -Z, +Y is up in the image, +X right), with `up` showing as up in the image
/// and no roll. The workspace's one look-at: [`Camera::look_at`], the load generator's orbit
/// (which inverts it into a view matrix) and the dataset cameras all call it. Errors if a
/// value is not finite, `eye == target`, or `up` is zero or parallel to the view.
pub fn look_at_camera_to_world(eye: Vec3, target: Vec3, up: Vec3) -> Result<Mat4, CameraError> {
    if !(eye.is_finite() && target.is_finite() && up.is_finite()) {
        return Err(CameraError::NonFinite("look-at eye, target or up"));
    }
    let forward = (target - eye).try_normalize().ok_or(CameraError::DegenerateLookAt("eye and target coincide"))?;
    let right = forward.cross(up.normalize_or_zero());
    if right.length() <= 1e-6 {
        return Err(CameraError::DegenerateLookAt("up zero or parallel to the view"));
    }
    let right = right.normalize();
    let true_up = right.cross(forward);
    Ok(Mat4::from_cols(right.extend(0.0), true_up.extend(0.0), (-forward).extend(0.0), eye.extend(1.0)))
}

impl Camera {
    /// Validates intrinsics and builds the camera; `world_to_camera` must be the inverse of the
    /// (already validated) `camera_to_world`.
    fn from_parts(
        width: u32,
        height: u32,
        (fx, fy, cx, cy): (f32, f32, f32, f32),
        camera_to_world: Mat4,
        world_to_camera: Mat4,
    ) -> Result<Camera, CameraError> {
        check_image_size(width, height)?;
        let invalid = |reason| CameraError::InvalidIntrinsics { fx, fy, cx, cy, reason };
        if !(fx > 0.0 && fy > 0.0 && Vec4::new(fx, fy, cx, cy).is_finite()) {
            return Err(invalid("focal lengths must be positive, all values finite"));
        }
        let (w, h) = (width as f32, height as f32);
        let extents = [w / fx, h / fy, fx / w, fy / h, cx / fx, cy / fy];
        if !extents.iter().all(|e| e.abs() <= MAX_NORMALISED_EXTENT) {
            return Err(invalid("focal lengths out of range for the image"));
        }
        if !(camera_to_world.is_finite() && world_to_camera.is_finite()) {
            return Err(CameraError::NonFinite("camera pose"));
        }
        Ok(Camera { width, height, fx, fy, cx, cy, camera_to_world, world_to_camera })
    }

    /// Camera with horizontal field of view `fov_x` (radians, NeRF's `camera_angle_x`), square
    /// pixels and the principal point at the image centre.
    pub fn from_fov_x(width: u32, height: u32, fov_x: f32, camera_to_world: Mat4) -> Result<Camera, CameraError> {
        Self::centred(width, height, fov_x, width, camera_to_world)
    }

    /// Camera with vertical field of view `fov_y` (radians), square pixels, centred.
    pub fn from_fov_y(width: u32, height: u32, fov_y: f32, camera_to_world: Mat4) -> Result<Camera, CameraError> {
        Self::centred(width, height, fov_y, height, camera_to_world)
    }

    /// Centred camera with square pixels whose field of view `fov` spans `side` pixels.
    fn centred(w: u32, h: u32, fov: f32, side: u32, pose: Mat4) -> Result<Camera, CameraError> {
        check_image_size(w, h)?;
        let f = 0.5 * side as f32 / check_fov(fov)?;
        Self::from_intrinsics(w, h, f, f, 0.5 * w as f32, 0.5 * h as f32, pose)
    }

    /// Centred camera (vertical fov `fov_y`) at `eye` looking at `target`, with `up` showing
    /// as up in the image. Errors if `eye == target` or `up` is zero or parallel to the view.
    pub fn look_at(
        width: u32,
        height: u32,
        fov_y: f32,
        eye: Vec3,
        target: Vec3,
        up: Vec3,
    ) -> Result<Camera, CameraError> {
        check_image_size(width, height)?;
        check_fov(fov_y)?;
        Self::from_fov_y(width, height, fov_y, look_at_camera_to_world(eye, target, up)?)
    }

    /// Camera from pixel intrinsics: focal lengths `fx, fy` and principal point `cx, cy`.
    pub fn from_intrinsics(
        width: u32,
        height: u32,
        fx: f32,
        fy: f32,
        cx: f32,
        cy: f32,
        camera_to_world: Mat4,
    ) -> Result<Camera, CameraError> {
        check_image_size(width, height)?;
        let camera_to_world = check_rigid(camera_to_world, "camera-to-world")?;
        let world_to_camera = camera_to_world.inverse();
        let intrinsics = (fx, fy, cx, cy);
        Self::from_parts(width, height, intrinsics, camera_to_world, world_to_camera)
    }

    /// WebXR: `view` is the world-to-camera (view) matrix of one eye
    /// (`XRView.transform.inverse.matrix`), `projection` the eye's `projectionMatrix` (OpenGL
    /// clip conventions, column-major as glam). Converts the projection into off-axis
    /// intrinsics for an image of `width x height`.
    pub fn from_view_projection(width: u32, height: u32, view: Mat4, projection: Mat4) -> Result<Camera, CameraError> {
        check_image_size(width, height)?;
        let world_to_camera = check_rigid(view, "view")?;
        if !projection.is_finite() {
            return Err(CameraError::NonFinite("projection matrix"));
        }
        // Row 3 must be s * (0, 0, -1, 0) with s > 0; divide it out.
        let scale = -projection.row(3).z;
        let p = projection * (1.0 / scale);
        let not_perspective = |reason| Err(CameraError::NotPerspective(reason));
        if !(scale > 0.0 && p.is_finite()) {
            return not_perspective("P32 must be negative (w_clip = -z_view)");
        }
        let (p00, p11, tol) = (p.x_axis.x, p.y_axis.y, PROJECTION_TOLERANCE);
        if p.x_axis.w.abs().max(p.y_axis.w.abs()).max(p.w_axis.w.abs()) > tol {
            return not_perspective("the last row is not (0, 0, -1, 0)");
        }
        if !(p00 > 0.0 && p11 > 0.0) {
            return not_perspective("P00 and P11 must be positive");
        }
        if p.y_axis.x.abs().max(p.x_axis.y.abs()) > tol * p00.max(p11) {
            return not_perspective("it has skew (P01, P10)");
        }
        if p.w_axis.x.abs().max(p.w_axis.y.abs()) > tol {
            return not_perspective("it translates x or y (P03, P13)");
        }
        let (w, h) = (width as f32, height as f32);
        let intrinsics = (0.5 * w * p00, 0.5 * h * p11, 0.5 * w * (1.0 - p.z_axis.x), 0.5 * h * (1.0 + p.z_axis.y));
        let camera_to_world = world_to_camera.inverse();
        Self::from_parts(width, height, intrinsics, camera_to_world, world_to_camera)
    }

    /// Image width in pixels.
    #[inline]
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// `(fx, fy, cx, cy)` in pixels.
    pub fn intrinsics(&self) -> (f32, f32, f32, f32) {
        (self.fx, self.fy, self.cx, self.cy)
    }

    /// Camera-to-world matrix (NeRF `transform_matrix`).
    pub fn camera_to_world(&self) -> Mat4 {
        self.camera_to_world
    }

    /// World-to-camera (view) matrix.
    pub fn world_to_camera(&self) -> Mat4 {
        self.world_to_camera
    }

    /// The `width x height` window of this camera's image whose top-left pixel is `(x0, y0)`:
    /// the same rays, pixel `(i, j)` of the crop being `(x0 + i, y0 + j)` of this image (the
    /// window may reach past the image: it is the same pinhole).
    pub fn crop(&self, x0: u32, y0: u32, width: u32, height: u32) -> Result<Camera, CameraError> {
        let (fx, fy, cx, cy) = self.intrinsics();
        Camera::from_intrinsics(width, height, fx, fy, cx - x0 as f32, cy - y0 as f32, self.camera_to_world)
    }

    /// Camera centre in world space.
    #[inline]
    pub fn position(&self) -> Vec3 {
        self.camera_to_world.w_axis.truncate()
    }

    /// Unit viewing direction (camera -Z) in world space.
    pub fn forward(&self) -> Vec3 {
        (-self.camera_to_world.z_axis.truncate()).normalize()
    }

    /// Unit image-right direction (camera +X) in world space.
    pub fn right(&self) -> Vec3 {
        self.camera_to_world.x_axis.truncate().normalize()
    }

    /// Unit image-up direction (camera +Y) in world space.
    pub fn up(&self) -> Vec3 {
        self.camera_to_world.y_axis.truncate().normalize()
    }

    /// Horizontal field of view in radians, `2 atan(w / (2 fx))` (exact for centred cameras).
    pub fn fov_x(&self) -> f32 {
        2.0 * (0.5 * self.width as f32 / self.fx).atan()
    }

    /// Vertical field of view in radians, `2 atan(h / (2 fy))` (exact for centred cameras).
    pub fn fov_y(&self) -> f32 {
        2.0 * (0.5 * self.height as f32 / self.fy).atan()
    }

    /// Ray through continuous pixel coordinates (x right, y down, (0,0) top-left corner of the
    /// image). Direction unit length, origin at the camera centre. Coordinates outside the image
    /// are allowed; non-finite coordinates give a non-finite direction.
    #[inline]
    pub fn ray(&self, x: f32, y: f32) -> Ray {
        let camera_dir = Vec3::new((x - self.cx) / self.fx, -(y - self.cy) / self.fy, -1.0);
        let direction = self.camera_to_world.transform_vector3(camera_dir);
        let origin = self.position();
        Ray { origin, direction: direction.normalize() }
    }

    /// Ray through the centre `(i + 0.5, j + 0.5)` of pixel `(i, j)`.
    #[inline]
    pub fn pixel_center_ray(&self, i: u32, j: u32) -> Ray {
        self.ray(i as f32 + 0.5, j as f32 + 0.5)
    }

    /// Projects a world point to continuous pixel coordinates; `None` if the point is at or
    /// behind the camera plane (view z >= -1e-6) or non-finite.
    #[inline]
    pub fn project(&self, p: Vec3) -> Option<Vec2> {
        let q = self.world_to_camera.transform_point3(p);
        if !q.is_finite() || q.z >= NEAR_PLANE_Z {
            return None;
        }
        let inv_depth = 1.0 / -q.z;
        let pixel = Vec2::new(self.cx + self.fx * q.x * inv_depth, self.cy - self.fy * q.y * inv_depth);
        pixel.is_finite().then_some(pixel)
    }

    /// View-space depth of a world point (positive in front of the camera).
    #[inline]
    pub fn view_depth(&self, p: Vec3) -> f32 {
        -self.world_to_camera.transform_point3(p).z
    }

    /// Factor turning a distance t along `ray(x,y)` into view depth:
    /// `depth = t * depth_per_distance(&ray)` (= -dot(dir_camera_space, z)).
    #[inline]
    pub fn depth_per_distance(&self, ray: &Ray) -> f32 {
        -self.world_to_camera.transform_vector3(ray.direction).z
    }

    /// The projection matrix (OpenGL clip conventions) this camera corresponds to, for given
    /// `near`/`far` (`0 < near < far`; `far` may be `f32::INFINITY`); round-trips with
    /// [`Camera::from_view_projection`]. Degenerate planes give non-finite entries.
    pub fn projection_matrix(&self, near: f32, far: f32) -> Mat4 {
        let (w, h) = (self.width as f32, self.height as f32);
        let (a, b) = match far.is_infinite() {
            true => (-1.0, -2.0 * near),
            false => ((far + near) / (near - far), 2.0 * far * near / (near - far)),
        };
        Mat4::from_cols(
            Vec4::new(2.0 * self.fx / w, 0.0, 0.0, 0.0),
            Vec4::new(0.0, 2.0 * self.fy / h, 0.0, 0.0),
            Vec4::new(1.0 - 2.0 * self.cx / w, 2.0 * self.cy / h - 1.0, a, -1.0),
            Vec4::new(0.0, 0.0, b, 0.0),
        )
    }

    /// This camera moved by `offset` in its own camera space, with principal point `(cx, cy)`.
    fn shifted(&self, offset: Vec3, cx: f32, cy: f32) -> Result<Camera, CameraError> {
        let camera_to_world = self.camera_to_world * Mat4::from_translation(offset);
        let world_to_camera = Mat4::from_translation(-offset) * self.world_to_camera;
        let (w, h, intrinsics) = (self.width, self.height, (self.fx, self.fy, cx, cy));
        Self::from_parts(w, h, intrinsics, camera_to_world, world_to_camera)
    }

    /// Where this camera will be if it goes on moving as it did since `earlier`: `k` times the
    /// motion from `earlier` to `self` added again (position along the line, orientation about
    /// the same axis at the same rate; `k = 1` one more step). Intrinsics and size are this
    /// camera's. `None` when the two differ in image size or the motion is not a number;
    /// `k` is clamped to `[0, 8]` (a prediction farther out is a guess). The scheduler's
    /// render-ahead predicts a user's next pose with it (issue 16).
    pub fn extrapolate(&self, earlier: &Camera, k: f32) -> Option<Camera> {
        if (self.width, self.height) != (earlier.width, earlier.height) || !k.is_finite() {
            return None;
        }
        let k = k.clamp(0.0, 8.0);
        let rotation = |c: &Camera| Quat::from_mat3(&Mat3::from_mat4(c.camera_to_world)).normalize();
        let (from, to) = (rotation(earlier), rotation(self));
        // The step's rotation, taken the short way round, scaled by `k` about its axis.
        let mut step = (to * from.inverse()).normalize();
        if step.w < 0.0 {
            step = -step;
        }
        let (axis, angle) = step.to_axis_angle();
        let turn = if angle.abs() < 1e-7 { Quat::IDENTITY } else { Quat::from_axis_angle(axis, angle * k) };
        let position = self.position() + (self.position() - earlier.position()) * k;
        let pose = Mat4::from_rotation_translation((turn * to).normalize(), position);
        if !pose.is_finite() {
            return None;
        }
        Camera::from_intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy, pose).ok()
    }
}

/// Stereo rig: two cameras offset by ±ipd/2 along the centre camera's +X (left eye at -X), same
/// orientation and intrinsics. Returns `[left, right]`.
pub fn stereo_pair(center: &Camera, ipd: f32) -> Result<[Camera; 2], CameraError> {
    if !(0.0..=MAX_IPD).contains(&ipd) {
        return Err(CameraError::InvalidIpd(ipd));
    }
    let half = Vec3::new(0.5 * ipd, 0.0, 0.0);
    let left = center.shifted(-half, center.cx, center.cy)?;
    let right = center.shifted(half, center.cx, center.cy)?;
    Ok([left, right])
}

/// Views of a light-field quilt: Looking Glass's 45 (the page's quilt display, loadgen's
/// `--quilt`, the simulator's and `bench share`'s quilt rows).
pub const QUILT_VIEWS: usize = 45;
/// View cone of a quilt, degrees: the angle its cameras span seen from the focal point
/// (Looking Glass: about 40).
pub const QUILT_VIEW_CONE_DEG: f32 = 40.0;

/// N-view horizontal rig for light-field displays (e.g. a 45-view Looking Glass quilt): cameras
/// spread along the centre camera's X axis over a total angle `view_cone` (radians, seen from
/// the focal point at `focal_distance` in front of the centre camera), all parallel to the
/// centre camera, with the principal point shifted (off-axis) so the focal plane projects to
/// the same pixels in every view. View 0 is the leftmost. Error for views == 0 or > 1024,
/// non-finite or non-positive focal distance, view_cone not in [0, pi).
pub fn quilt_rig(
    center: &Camera,
    views: usize,
    view_cone: f32,
    focal_distance: f32,
) -> Result<Vec<Camera>, CameraError> {
    if views == 0 || views > MAX_VIEWS {
        return Err(CameraError::InvalidViewCount(views));
    }
    if !(0.0..PI).contains(&view_cone) {
        return Err(CameraError::InvalidViewCone(view_cone));
    }
    if !(focal_distance.is_finite() && focal_distance > 0.0) {
        return Err(CameraError::InvalidFocalDistance(focal_distance));
    }
    // Offsets over the baseline, as a fraction of the focal distance: [-tan, +tan].
    let half_extent = (0.5 * view_cone).tan();
    let step = if views > 1 { 2.0 * half_extent / (views - 1) as f32 } else { 0.0 };
    (0..views)
        .map(|k| {
            let relative_offset = (k as f32 - 0.5 * (views - 1) as f32) * step;
            // A focal-plane point at camera x = X projects to cx + fx X / D in the centre view
            // and to cx_k + fx (X - offset) / D in view k: shift cx by fx * offset / D.
            let cx = center.cx + center.fx * relative_offset;
            let offset = Vec3::new(relative_offset * focal_distance, 0.0, 0.0);
            center.shifted(offset, cx, center.cy)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{EulerRot, Quat};
    use proptest::prelude::*;
    use std::f32::consts::FRAC_PI_2;

    /// Asserts two vectors agree component-wise within a tolerance.
    macro_rules! assert_near {
        ($a:expr, $b:expr, $tol:expr) => {{
            let (a, b, tol) = ($a, $b, $tol);
            assert!((a - b).abs().max_element() <= tol, "{a} != {b} (tol {tol})");
        }};
    }

    #[test]
    fn extrapolation_goes_on_along_an_orbit_and_a_turn() {
        let orbit = |degrees: f32| {
            let a = degrees.to_radians();
            Camera::look_at(64, 48, 0.9, Vec3::new(3.0 * a.sin(), -3.0 * a.cos(), 0.7), Vec3::ZERO, Vec3::Z)
                .expect("camera")
        };
        // 2 degrees a frame about the object: one and two frames ahead.
        for (k, degrees) in [(1.0, 4.0), (2.0, 6.0), (0.5, 3.0)] {
            let predicted = orbit(2.0).extrapolate(&orbit(0.0), k).expect("prediction");
            let truth = orbit(degrees);
            // The position goes on along the chord: off the circle by about r * angle^2.
            let chord_error = 3.0 * (degrees - 2.0f32).to_radians().powi(2) * 2.0;
            assert_near!(predicted.position(), truth.position(), chord_error);
            assert_near!(predicted.forward(), (Vec3::ZERO - predicted.position()).normalize(), 2e-2);
            assert_near!(predicted.up(), truth.up(), 1e-4);
            assert_eq!(predicted.intrinsics(), truth.intrinsics());
        }
        // A head turning in place: the position stays, the turn goes on exactly.
        let turn = |degrees: f32| {
            let pose = Mat4::from_rotation_translation(Quat::from_rotation_y(degrees.to_radians()), Vec3::ONE);
            Camera::from_fov_x(32, 32, 1.0, pose).expect("camera")
        };
        let predicted = turn(10.0).extrapolate(&turn(7.0), 2.0).expect("prediction");
        assert_near!(predicted.position(), Vec3::ONE, 1e-6);
        assert_near!(predicted.forward(), turn(16.0).forward(), 1e-5);
        // Standing still, k = 0, another image size, a non-finite k.
        let still = turn(5.0).extrapolate(&turn(5.0), 3.0).expect("prediction");
        assert_near!(still.forward(), turn(5.0).forward(), 1e-6);
        assert_near!(orbit(2.0).extrapolate(&orbit(0.0), 0.0).expect("k = 0").position(), orbit(2.0).position(), 1e-6);
        assert!(turn(5.0).extrapolate(&orbit(0.0), 1.0).is_none());
        assert!(orbit(2.0).extrapolate(&orbit(0.0), f32::NAN).is_none());
        // Far out is clamped: k = 100 goes 8 steps.
        let far = turn(1.0).extrapolate(&turn(0.0), 100.0).expect("prediction");
        assert_near!(far.forward(), turn(9.0).forward(), 1e-5);
    }

    #[test]
    fn a_crop_keeps_every_ray_and_projection() {
        let full = Camera::look_at(64, 48, 0.9, Vec3::new(1.0, -3.0, 0.7), Vec3::ZERO, Vec3::Z).expect("camera");
        let crop = full.crop(10, 7, 20, 9).expect("crop");
        assert_eq!((crop.width(), crop.height()), (20, 9));
        for (i, j) in [(0, 0), (19, 8), (5, 3)] {
            let (a, b) = (crop.pixel_center_ray(i, j), full.pixel_center_ray(10 + i, 7 + j));
            assert_near!(a.origin, b.origin, 1e-6);
            assert_near!(a.direction, b.direction, 1e-6);
        }
        let p = Vec3::new(0.1, 0.2, 0.05);
        let (a, b) = (crop.project(p).expect("in front"), full.project(p).expect("in front"));
        assert!((a - (b - Vec2::new(10.0, 7.0))).abs().max_element() < 1e-4);
        assert!(full.crop(0, 0, 0, 4).is_err());
    }

    /// Asserts a result is an error matching a pattern.
    macro_rules! assert_rejects {
        ($result:expr, $pattern:pat) => {{
            let result = $result;
            assert!(matches!(result, Err($pattern)), "got {result:?}");
        }};
    }

    fn pixel(camera: &Camera, p: Vec3) -> Vec2 {
        camera.project(p).expect("in front of the camera")
    }

    /// glFrustum, written out by hand (OpenGL clip conventions).
    fn frustum_gl(l: f32, r: f32, b: f32, t: f32, n: f32, f: f32) -> Mat4 {
        let mut m = Mat4::ZERO;
        (m.x_axis.x, m.y_axis.y) = (2.0 * n / (r - l), 2.0 * n / (t - b));
        (m.z_axis.x, m.z_axis.y) = ((r + l) / (r - l), (t + b) / (t - b));
        (m.z_axis.z, m.z_axis.w, m.w_axis.z) = ((f + n) / (n - f), -1.0, 2.0 * f * n / (n - f));
        m
    }

    /// Pixel of a world point through a view and an OpenGL projection matrix, the GPU way.
    fn gpu_pixel(view: Mat4, projection: Mat4, (w, h): (u32, u32), p: Vec3) -> Vec2 {
        let clip = projection * view * p.extend(1.0);
        let ndc = clip.truncate() / clip.w;
        (Vec2::new(ndc.x, -ndc.y) + 1.0) * 0.5 * Vec2::new(w as f32, h as f32)
    }

    fn centred_90(size: u32) -> Camera {
        Camera::from_fov_x(size, size, FRAC_PI_2, Mat4::IDENTITY).expect("valid")
    }

    #[test]
    fn each_camera_kind_projects_known_points() {
        let shifted = Mat4::from_translation(Vec3::new(1.0, 2.0, 3.0));
        let fov_x = Camera::from_fov_x(200, 100, FRAC_PI_2, Mat4::IDENTITY).expect("valid");
        let fov_y = Camera::from_fov_y(300, 100, FRAC_PI_2, shifted).expect("valid");
        let intrinsics = Camera::from_intrinsics(640, 480, 500.0, 400.0, 320.0, 200.0, shifted);
        let intrinsics = intrinsics.expect("valid");
        // Looking down -X from (5, 0, 0) with +Z up: world +Y is right, +Z is up.
        let eye = Vec3::new(5.0, 0.0, 0.0);
        let look = Camera::look_at(100, 100, FRAC_PI_2, eye, Vec3::ZERO, Vec3::Z).expect("valid");
        // Camera-space points: (1, .5, -2) for fov_x, (.2, -.4, -2) for fov_y, (.2, -.1, -2)
        // for intrinsics.
        let cases = [
            (&fov_x, [1.0, 0.5, -2.0], [150.0, 25.0]),
            (&fov_y, [1.2, 1.6, 1.0], [155.0, 60.0]),
            (&intrinsics, [1.2, 1.9, 1.0], [370.0, 220.0]),
            (&look, [0.0, 0.0, 0.0], [50.0, 50.0]),
            (&look, [0.0, 1.0, 0.0], [60.0, 50.0]),
            (&look, [0.0, 0.0, 1.0], [50.0, 40.0]),
        ];
        for (camera, point, expected) in cases {
            assert_near!(pixel(camera, point.into()), Vec2::from(expected), 1e-3);
        }
        let expected = Vec4::new(100.0, 100.0, 100.0, 50.0);
        assert_near!(Vec4::from(fov_x.intrinsics()), expected, 1e-3);
        assert_eq!(intrinsics.intrinsics(), (500.0, 400.0, 320.0, 200.0));
        assert_eq!((intrinsics.width(), intrinsics.height()), (640, 480));
        assert!((fov_x.fov_x() - FRAC_PI_2).abs() < 1e-6);
        assert!((fov_y.fov_y() - FRAC_PI_2).abs() < 1e-6);
        assert_eq!(fov_x.forward(), Vec3::NEG_Z);
        assert_eq!(fov_x.position(), Vec3::ZERO);
        assert_near!(look.forward(), Vec3::NEG_X, 1e-6);
        assert!((fov_y.view_depth(Vec3::new(1.2, 1.6, 1.0)) - 2.0).abs() < 1e-5);
    }

    #[test]
    fn nerf_synthetic_convention() {
        // Camera at (0, -4, 0) looking at the origin (+Y), +Z up: right +X, up +Z, back -Y.
        let transform_matrix = Mat4::from_cols(
            Vec4::new(1.0, 0.0, 0.0, 0.0),
            Vec4::new(0.0, 0.0, 1.0, 0.0),
            Vec4::new(0.0, -1.0, 0.0, 0.0),
            Vec4::new(0.0, -4.0, 0.0, 1.0),
        );
        let camera = Camera::from_fov_x(800, 800, 0.691_111_2, transform_matrix).expect("valid");
        assert_near!(camera.forward(), Vec3::Y, 1e-6);
        assert_near!(pixel(&camera, Vec3::ZERO), Vec2::new(400.0, 400.0), 1e-3);
        let (up, right) = (pixel(&camera, Vec3::Z), pixel(&camera, Vec3::X));
        assert!(up.y < 400.0 && (up.x - 400.0).abs() < 1e-3, "{up}");
        assert!(right.x > 400.0 && (right.y - 400.0).abs() < 1e-3, "{right}");
        assert!((camera.view_depth(Vec3::ZERO) - 4.0).abs() < 1e-5);
    }

    #[test]
    fn corner_rays_of_90_degree_camera() {
        let camera = centred_90(100);
        let cases = [
            (0.0, 0.0, Vec3::new(-1.0, 1.0, -1.0)),
            (100.0, 0.0, Vec3::new(1.0, 1.0, -1.0)),
            (0.0, 100.0, Vec3::new(-1.0, -1.0, -1.0)),
            (100.0, 100.0, Vec3::new(1.0, -1.0, -1.0)),
            (50.0, 50.0, Vec3::NEG_Z),
        ];
        for (x, y, expected) in cases {
            let ray = camera.ray(x, y);
            assert_eq!(ray.origin, Vec3::ZERO);
            assert_near!(ray.direction, expected.normalize(), 1e-6);
        }
        let ray = centred_90(2).pixel_center_ray(0, 0);
        assert_near!(ray.direction, Vec3::new(-0.5, 0.5, -1.0).normalize(), 1e-6);
    }

    #[test]
    fn ray_project_round_trip_and_depth() {
        let rotation = Quat::from_euler(EulerRot::ZXY, 0.7, 1.1, -0.3);
        let pose = Mat4::from_rotation_translation(rotation, Vec3::new(0.5, -3.0, 1.5));
        let camera = Camera::from_intrinsics(320, 240, 300.0, 280.0, 150.0, 130.0, pose);
        let camera = camera.expect("valid");
        for (x, y) in [(0.0, 0.0), (320.0, 240.0), (17.25, 200.5), (160.0, 120.0)] {
            let ray = camera.ray(x, y);
            assert!((ray.direction.length() - 1.0).abs() < 1e-6);
            for t in [0.5, 2.0, 10.0] {
                assert_near!(pixel(&camera, ray.at(t)), Vec2::new(x, y), 2e-3);
                let depth = t * camera.depth_per_distance(&ray);
                assert!((camera.view_depth(ray.at(t)) - depth).abs() < 1e-4);
            }
        }
        assert_eq!(camera.project(camera.position() - camera.forward()), None);
        assert_eq!(camera.project(camera.position()), None);
        assert_eq!(camera.project(Vec3::NAN), None);
    }

    #[test]
    fn view_projection_matches_gpu_and_round_trips() {
        // WebXR-like eye: rotated, translated, asymmetric frustum (tangents l -1, r 0.8,
        // b -1.1, t 0.9).
        let rotation = Quat::from_rotation_y(0.3);
        let pose = Mat4::from_rotation_translation(rotation, Vec3::new(0.1, 0.2, 1.6));
        let (view, size) = (pose.inverse(), (1000, 1100));
        let projection = frustum_gl(-0.1, 0.08, -0.11, 0.09, 0.1, 100.0);
        let camera = Camera::from_view_projection(1000, 1100, view, projection).expect("valid");
        let expected = Vec4::new(1000.0 / 1.8, 550.0, 1000.0 / 1.8, 495.0);
        assert_near!(Vec4::from(camera.intrinsics()), expected, 1e-2);
        let points = [[0.3, -0.2, -2.0], [-1.5, 1.2, -3.0], [0.0, 0.0, -1.0]];
        for p in points.map(|local| pose.transform_point3(local.into())) {
            let gpu = gpu_pixel(view, projection, size, p);
            assert_near!(pixel(&camera, p), gpu, 1e-2);
        }
        // Back to a projection matrix (finite and infinite far) and to the same camera.
        let rebuilt = camera.projection_matrix(0.1, 100.0);
        assert!(rebuilt.abs_diff_eq(projection, 1e-4), "{rebuilt}");
        let again = Camera::from_view_projection(1000, 1100, view, rebuilt).expect("valid");
        let intrinsics = Vec4::from(camera.intrinsics());
        assert_near!(intrinsics, Vec4::from(again.intrinsics()), 1e-2);
        let infinite = camera.projection_matrix(0.1, f32::INFINITY);
        let p = Vec3::new(0.2, 0.3, 1.0);
        assert_near!(pixel(&camera, p), gpu_pixel(view, infinite, size, p), 1e-2);
        // A symmetric projection, also scaled by 2 (same clip-space point), gives the centre.
        let symmetric = frustum_gl(-0.1, 0.1, -0.075, 0.075, 0.1, 50.0);
        let p = pose.transform_point3(Vec3::new(0.4, 0.1, -2.5));
        for matrix in [symmetric, symmetric * 2.0] {
            let camera = Camera::from_view_projection(640, 480, view, matrix).expect("valid");
            let gpu = gpu_pixel(view, symmetric, (640, 480), p);
            assert_near!(pixel(&camera, p), gpu, 1e-2);
            let (_, _, cx, cy) = camera.intrinsics();
            assert_eq!((cx, cy), (320.0, 240.0));
        }
    }

    #[test]
    fn stereo_eyes_project_known_points() {
        let center = centred_90(100);
        let [left, right] = stereo_pair(&center, 0.064).expect("valid ipd");
        assert_near!(left.position(), Vec3::new(-0.032, 0.0, 0.0), 1e-7);
        assert_near!(right.position(), Vec3::new(0.032, 0.0, 0.0), 1e-7);
        assert_eq!(left.forward(), center.forward());
        assert_eq!(left.intrinsics(), center.intrinsics());
        assert_near!(pixel(&left, Vec3::NEG_Z), Vec2::new(51.6, 50.0), 1e-3);
        assert_near!(pixel(&right, Vec3::NEG_Z), Vec2::new(48.4, 50.0), 1e-3);
        let p = left.ray(10.0, 20.0).at(3.0);
        assert_near!(pixel(&left, p), Vec2::new(10.0, 20.0), 1e-3);
    }

    #[test]
    fn quilt_focal_plane_is_shared_and_parallax_has_right_sign() {
        let (eye, target) = (Vec3::new(1.0, -5.0, 2.0), Vec3::new(0.0, 0.0, 0.5));
        let center = Camera::look_at(420, 560, 0.8, eye, target, Vec3::Z).expect("valid");
        let (distance, cone) = ((eye - target).length(), 40f32.to_radians());
        let views = quilt_rig(&center, 45, cone, distance).expect("valid rig");
        assert_eq!(views.len(), 45);
        let along_view = |d: f32| center.position() + d * distance * center.forward();
        let (focal, near, far) = (along_view(1.0), along_view(0.5), along_view(2.0));
        let centre = pixel(&center, focal);
        let mut previous_near_x = f32::INFINITY;
        for view in &views {
            assert_near!(pixel(view, focal), centre, 1e-2);
            assert_near!(view.forward(), center.forward(), 1e-6);
            let near_x = pixel(view, near).x;
            assert!(near_x < previous_near_x, "parallax order");
            previous_near_x = near_x;
        }
        // Leftmost view (at -X): near points appear right of the focal point, far points left.
        let x_in = |k: usize, p: Vec3| pixel(&views[k], p).x;
        assert!(x_in(0, near) > centre.x + 1.0 && x_in(0, far) < centre.x - 1.0);
        assert!(x_in(44, near) < centre.x - 1.0 && x_in(44, far) > centre.x + 1.0);
        let along_right = |c: &Camera| (c.position() - center.position()).dot(center.right());
        assert!(along_right(&views[0]) < 0.0 && along_right(&views[44]) > 0.0);
        // The baseline subtends the view cone from the focal point.
        let half_baseline = 0.5 * (views[44].position() - views[0].position()).length();
        assert!((2.0 * (half_baseline / distance).atan() - cone).abs() < 1e-4);
        assert_eq!(quilt_rig(&center, 1, 0.5, 2.0), Ok(vec![center]));
    }

    #[test]
    fn rejects_invalid_inputs() {
        use CameraError as E;
        let (id, fov) = (Mat4::IDENTITY, 1.0);
        assert_rejects!(Camera::from_fov_x(0, 10, fov, id), E::ZeroSizeImage { .. });
        assert_rejects!(Camera::from_fov_y(10, 0, fov, id), E::ZeroSizeImage { .. });
        let result = Camera::from_fov_x(65537, 9, fov, id);
        assert_rejects!(result, E::ImageTooLarge { .. });
        assert!(Camera::from_fov_x(65536, 65536, fov, id).is_ok());
        let mut nan_matrix = id;
        nan_matrix.w_axis.y = f32::NAN;
        assert_rejects!(Camera::from_fov_x(10, 10, fov, nan_matrix), E::NonFinite(_));
        assert_rejects!(Camera::from_fov_x(10, 10, f32::NAN, id), E::NonFinite(_));
        for bad_fov in [0.0, -0.5, PI, 3.5] {
            assert_rejects!(Camera::from_fov_x(10, 10, bad_fov, id), E::FieldOfView(_));
            assert_rejects!(Camera::from_fov_y(10, 10, bad_fov, id), E::FieldOfView(_));
        }
        let bad_poses = [
            Mat4::from_scale(Vec3::splat(2.0)),
            Mat4::from_cols(Vec4::X, Vec4::X, Vec4::Z, Vec4::W), // singular
            Mat4::ZERO,
            Mat4::from_scale(Vec3::new(1.0, 1.0, -1.0)), // reflection
            Mat4::from_cols(Vec4::X, Vec4::Y, Vec4::Z, Vec4::new(0.0, 0.0, 0.0, 2.0)),
        ];
        for pose in bad_poses {
            assert_rejects!(Camera::from_fov_x(10, 10, fov, pose), E::NotRigid { .. });
        }
        for focal in [0.0, -1.0, f32::NAN, 1e-30, f32::MAX] {
            let result = Camera::from_intrinsics(10, 10, focal, 1.0, 5.0, 5.0, id);
            assert_rejects!(result, E::InvalidIntrinsics { .. });
            let result = Camera::from_intrinsics(10, 10, 1.0, focal, 5.0, 5.0, id);
            assert_rejects!(result, E::InvalidIntrinsics { .. });
        }
        let (eye, up) = (Vec3::new(1.0, 2.0, 3.0), Vec3::Z);
        // Target at the eye, zero up, up parallel to the view direction.
        let degenerate = [(eye, up), (Vec3::X, Vec3::ZERO), (Vec3::X, eye - Vec3::X)];
        for (target, up) in degenerate {
            let result = Camera::look_at(10, 10, fov, eye, target, up);
            assert_rejects!(result, E::DegenerateLookAt(_));
        }
        let result = Camera::look_at(9, 9, fov, Vec3::NAN, eye, up);
        assert_rejects!(result, E::NonFinite(_));

        let perspective = frustum_gl(-0.1, 0.1, -0.1, 0.1, 0.1, 10.0);
        let mut orthographic = Mat4::from_scale(Vec3::new(1.0, 1.0, -0.2));
        orthographic.w_axis.z = -1.0;
        let (mut skewed, mut translated, mut flipped) = (perspective, perspective, perspective);
        skewed.y_axis.x = 0.3;
        translated.w_axis.x = 0.5;
        flipped.y_axis.y *= -1.0; // Vulkan-style y-down clip space
        let bad_projections = [orthographic, skewed, translated, flipped, -perspective];
        for bad in bad_projections {
            let result = Camera::from_view_projection(9, 9, id, bad);
            assert_rejects!(result, E::NotPerspective(_));
        }
        let mut nan_projection = perspective;
        nan_projection.z_axis.x = f32::NAN;
        let result = Camera::from_view_projection(10, 10, id, nan_projection);
        assert_rejects!(result, E::NonFinite(_));
        let scaled_view = Mat4::from_scale(Vec3::splat(2.0));
        let result = Camera::from_view_projection(10, 10, scaled_view, perspective);
        assert_rejects!(result, E::NotRigid { matrix: "view", .. });
        let result = Camera::from_view_projection(0, 10, id, perspective);
        assert_rejects!(result, E::ZeroSizeImage { .. });

        let center = centred_90(10);
        for ipd in [-0.01, f32::NAN, f32::INFINITY, 1.5] {
            assert_rejects!(stereo_pair(&center, ipd), E::InvalidIpd(_));
        }
        assert!(stereo_pair(&center, 0.0).is_ok());
        assert_rejects!(quilt_rig(&center, 0, 0.5, 2.0), E::InvalidViewCount(0));
        assert_rejects!(quilt_rig(&center, MAX_VIEWS + 1, 0.5, 2.0), E::InvalidViewCount(_));
        for cone in [-0.1, PI, f32::NAN] {
            assert_rejects!(quilt_rig(&center, 45, cone, 2.0), E::InvalidViewCone(_));
        }
        for distance in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let result = quilt_rig(&center, 45, 0.5, distance);
            assert_rejects!(result, E::InvalidFocalDistance(_));
        }
    }

    #[test]
    fn error_messages_are_descriptive() {
        let zero = Camera::from_fov_x(0, 7, 1.0, Mat4::IDENTITY).expect_err("zero size");
        assert!(zero.to_string().contains("0x7"), "{zero}");
        let fov = CameraError::FieldOfView(4.0).to_string();
        assert!(fov.contains('4') && fov.contains("(0, pi)"), "{fov}");
        let scaled = Mat4::from_scale(Vec3::splat(2.0));
        let rigid = Camera::from_fov_x(10, 10, 1.0, scaled).expect_err("not rigid");
        let rigid = rigid.to_string();
        assert!(rigid.contains("camera-to-world"), "{rigid}");
        assert!(rigid.contains("orthonormal"), "{rigid}");
    }

    proptest! {
        #[test]
        fn random_cameras_round_trip(
            (width, height) in (1u32..2048, 1u32..2048),
            fov in 0.2f32..2.8,
            euler in prop::array::uniform3(-PI..PI),
            position in prop::array::uniform3(-10.0f32..10.0),
            principal in prop::array::uniform2(-0.5f32..1.5),
            aspect in 0.5f32..2.0,
            pixel in prop::array::uniform2(0.0f32..=1.0),
            t in 0.5f32..50.0,
        ) {
            let rotation = Quat::from_euler(EulerRot::ZXY, euler[0], euler[1], euler[2]);
            let pose = Mat4::from_rotation_translation(rotation, Vec3::from(position));
            let centred = Camera::from_fov_x(width, height, fov, pose).expect("valid");
            let (f, (w, h)) = (centred.intrinsics().0, (width as f32, height as f32));
            let (cx, cy) = (principal[0] * w, principal[1] * h);
            let off_axis = Camera::from_intrinsics(width, height, f, f * aspect, cx, cy, pose);
            for camera in [centred, off_axis.expect("valid")] {
                let (x, y) = (pixel[0] * w, pixel[1] * h);
                let ray = camera.ray(x, y);
                prop_assert!(ray.direction.is_finite() && ray.origin.is_finite());
                prop_assert!((ray.direction.length() - 1.0).abs() < 1e-5);
                let (p, scale) = (ray.at(t), Vec3::from(position).length() + t);
                let depth = camera.view_depth(p);
                let expected_depth = t * camera.depth_per_distance(&ray);
                prop_assert!(depth > 0.0 && (depth - expected_depth).abs() <= 1e-5 * scale);
                // Rounding error of a point at distance `scale` seen at `depth`, in pixels:
                // d(X/Z) <= (1 + |X/Z|) dZ / Z, so a pixel error of about (f + |x - cx|) dZ / Z.
                let (fx, fy, cx, cy) = camera.intrinsics();
                let spread = fx.max(fy) + (x - cx).abs() + (y - cy).abs();
                let tol = 1e-3 + 32.0 * f32::EPSILON * spread * scale / depth;
                let back = camera.project(p).unwrap_or(Vec2::NAN);
                prop_assert!((back - Vec2::new(x, y)).abs().max_element() <= tol, "{back} {x},{y}");
            }
        }
    }
}
