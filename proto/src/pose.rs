//! The pose message of the viewer's RTCDataChannel (browser -> composer): its one encoder
//! and decoder in Rust. The composer decodes every pose with [`Pose::decode`]; loadgen and the
//! tests encode with [`Pose::encode`]; the browser client's JavaScript is the other language's
//! encoder (`client/PROTOCOL.md`).
//!
//! # Pose (binary message), version 1, little-endian
//!
//! The browser client's format (`client/PROTOCOL.md`):
//!
//! | offset | type | field |
//! | --- | --- | --- |
//! | 0 | u8 | magic `0x50` (`'P'`) |
//! | 1 | u8 | version, 1 |
//! | 2 | u8 | view count `N`, 1..=[`MAX_POSE_VIEWS`] (1 flat screen, 2 WebXR stereo, N a quilt) |
//! | 3 | u8 | display mode: 0 flat, 1 immersive VR, 2 quilt, 3 AR (key-colour background) |
//! | 4 | u32 | sequence number, increasing |
//! | 8 | f64 | client timestamp, ms (`performance.now()`), echoed for latency measurements |
//! | 16 | u16, u16 | frame width, height of one view in pixels |
//! | 20 + 128 i | f32 x 16 | view i: view matrix (world to camera), column-major as WebGL/WebXR give it |
//! | 84 + 128 i | f32 x 16 | view i: OpenGL projection matrix, column-major |
//!
//! A message is exactly `20 + 128 N` bytes. The matrices follow the project's conventions
//! (world +Z up, camera looking down -Z); a WebXR client converts its y-up reference space
//! into that frame before sending. Every view has the same frame size (they are packed
//! into one picture), at most [`MAX_POSE_SIDE`] on a side.
//!
//!
//! [`Pose::decode`] refuses a message that is malformed: wrong size, magic or version, NaN
//! or infinity, a view matrix that is not rigid, a projection that is not a perspective, a
//! bad frame size.

use glam::Mat4;
use nephele_geometry::ViewProjection;
use nephele_geometry::camera::Camera;
use thiserror::Error;

pub const POSE_MAGIC: u8 = 0x50;
pub const POSE_VERSION: u8 = 1;
pub const POSE_HEADER_BYTES: usize = 20;
pub const POSE_VIEW_BYTES: usize = 64 + 64;
/// Display mode: a flat screen, one view.
pub const MODE_FLAT: u8 = 0;
/// Display mode: immersive VR, one view per eye, as a WebXR headset sends them.
pub const MODE_XR: u8 = 1;
/// Display mode: a light-field quilt.
pub const MODE_QUILT: u8 = 2;
/// Display mode: augmented reality. Where no object covers a pixel the frame shows
/// [`AR_KEY_SRGB`] instead of black (partly covered pixels are blended over it), so that a
/// headset's passthrough, or the page's own keying in `immersive-ar`, replaces it by the
/// real world. One view (a flat page or a passthrough app keying the colour) or one per eye.
pub const MODE_AR: u8 = 3;
/// Display modes: 0 flat, 1 immersive VR, 2 quilt, 3 AR.
pub const MAX_POSE_MODE: u8 = MODE_AR;
/// The AR mode's key colour, sRGB 8-bit: pure green, the usual chroma key (no object of the
/// built-in scenes comes near it). `client/nephele.js` keys the same colour.
pub const AR_KEY_SRGB: [u8; 3] = [0, 255, 0];
/// [`AR_KEY_SRGB`] in linear RGB (the compositor's background).
pub const AR_KEY_LINEAR: [f32; 3] = [0.0, 1.0, 0.0];

/// Columns of the grid that packs `views` views into one picture (rows follow), filled row by
/// row from the top: up to two views side by side; Looking Glass's quilts as that display
/// expects them (45 views in 5 columns and 9 rows, 48 in 8 and 6); otherwise the squarest
/// grid. The client orders a quilt's views so that the picture is the display's quilt (its
/// view 0, the leftmost camera, in the bottom-left corner); `client/nephele.js` holds the
/// same table.
pub fn grid_columns(views: u16) -> u16 {
    match views {
        0..=2 => views.max(1),
        45 => 5,
        48 => 8,
        _ => f64::from(views).sqrt().ceil() as u16,
    }
}

/// For a quilt of `views` views, the camera (0 = the leftmost of the rig) each slot of the
/// packed grid shows, slots in packing order (rows from the top, left to right): Looking
/// Glass reads view 0 from the bottom-left corner, so the bottom row holds views
/// `0..columns`. A grid with a partly filled row keeps slot = view.
pub fn quilt_slot_views(views: u16) -> Vec<usize> {
    let (n, columns) = (usize::from(views), usize::from(grid_columns(views)));
    if !n.is_multiple_of(columns) {
        return (0..n).collect();
    }
    let rows = n / columns;
    (0..n).map(|slot| (rows - 1 - slot / columns) * columns + slot % columns).collect()
}
/// Most views in one pose.
pub const MAX_POSE_VIEWS: u16 = nephele_geometry::camera::MAX_VIEWS as u16;
/// Largest frame side a pose may ask for.
pub const MAX_POSE_SIDE: u32 = 3840;
/// Deepest level of a stream coded smaller on a narrow link (issue 15): the composer may
/// forward a viewer's pose to the master with each side of its views divided by `2^level`,
/// `level <= MAX_SCALE_LEVEL`, so that the farm renders only the pixels it will code.
pub const MAX_SCALE_LEVEL: u32 = 2;

/// The size of a view `width x height` at scale `level` (each side `1 / 2^level`), if both
/// sides divide; level 0 is the view itself.
pub fn scaled_view_size(width: u32, height: u32, level: u32) -> Option<(u32, u32)> {
    let factor = 1u32.checked_shl(level)?;
    (level <= MAX_SCALE_LEVEL && width.is_multiple_of(factor) && height.is_multiple_of(factor))
        .then(|| (width / factor, height / factor))
}

/// The level at which a view `width x height` becomes `size` (the inverse of
/// [`scaled_view_size`]), if it is one of the levels the stream may take.
pub fn scale_level_of(width: u32, height: u32, size: (u32, u32)) -> Option<u32> {
    (0..=MAX_SCALE_LEVEL).find(|&level| scaled_view_size(width, height, level) == Some(size))
}

#[derive(Debug, Error, Clone, PartialEq)]
pub enum PoseError {
    #[error("pose message of {got} bytes is too short")]
    TooShort { got: usize },
    #[error("not a pose message (magic {0:#04x})")]
    BadMagic(u8),
    #[error("pose version {0} is not supported (expected {POSE_VERSION})")]
    BadVersion(u8),
    #[error("{0} views; a pose carries 1..={MAX_POSE_VIEWS}")]
    ViewCount(u16),
    #[error("unknown display mode {0}")]
    BadMode(u8),
    #[error("pose message of {got} bytes; {views} views need exactly {expected}")]
    WrongSize { views: u16, expected: usize, got: usize },
    #[error("pose timestamp is not finite")]
    BadTimestamp,
    #[error("view {view}: {reason}")]
    BadView { view: u16, reason: String },
}

/// A decoded, validated pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Pose {
    pub seq: u32,
    /// 0 flat screen, 1 immersive VR, 2 quilt, 3 AR (the client's display mode).
    pub mode: u8,
    pub client_time_ms: f64,
    /// One per eye (or view of a quilt).
    pub views: Vec<ViewProjection>,
}

impl Pose {
    /// Frame size of every view.
    pub fn view_size(&self) -> (u32, u32) {
        self.views.first().map_or((0, 0), |v| (v.width, v.height))
    }

    /// The binary message of this pose (the browser client's format, `client/PROTOCOL.md`);
    /// every view takes view 0's frame size.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(POSE_HEADER_BYTES + POSE_VIEW_BYTES * self.views.len());
        let (w, h) = self.view_size();
        out.push(POSE_MAGIC);
        out.push(POSE_VERSION);
        out.push(self.views.len() as u8);
        out.push(self.mode);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.client_time_ms.to_le_bytes());
        out.extend_from_slice(&(w as u16).to_le_bytes());
        out.extend_from_slice(&(h as u16).to_le_bytes());
        for v in &self.views {
            for m in [v.view, v.projection] {
                for x in m.to_cols_array() {
                    out.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
        out
    }

    /// Decodes and validates a binary pose message (see the module docs).
    pub fn decode(bytes: &[u8]) -> Result<Pose, PoseError> {
        if bytes.len() < POSE_HEADER_BYTES {
            return Err(PoseError::TooShort { got: bytes.len() });
        }
        if bytes[0] != POSE_MAGIC {
            return Err(PoseError::BadMagic(bytes[0]));
        }
        if bytes[1] != POSE_VERSION {
            return Err(PoseError::BadVersion(bytes[1]));
        }
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let f32_at = |o: usize| f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        let count = u16::from(bytes[2]);
        if count == 0 || count > MAX_POSE_VIEWS {
            return Err(PoseError::ViewCount(count));
        }
        let mode = bytes[3];
        if mode > MAX_POSE_MODE {
            return Err(PoseError::BadMode(mode));
        }
        let expected = POSE_HEADER_BYTES + POSE_VIEW_BYTES * usize::from(count);
        if bytes.len() != expected {
            return Err(PoseError::WrongSize { views: count, expected, got: bytes.len() });
        }
        let seq = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
        let mut t = [0u8; 8];
        t.copy_from_slice(&bytes[8..16]);
        let client_time_ms = f64::from_le_bytes(t);
        if !client_time_ms.is_finite() {
            return Err(PoseError::BadTimestamp);
        }
        let (width, height) = (u32::from(u16_at(16)), u32::from(u16_at(18)));
        let mut views = Vec::with_capacity(usize::from(count));
        for i in 0..count {
            let base = POSE_HEADER_BYTES + POSE_VIEW_BYTES * usize::from(i);
            let bad = |reason: String| PoseError::BadView { view: i, reason };
            if width == 0 || height == 0 || width > MAX_POSE_SIDE || height > MAX_POSE_SIDE {
                return Err(bad(format!("frame size {width}x{height} outside 1..={MAX_POSE_SIDE}")));
            }
            let matrix = |o: usize| Mat4::from_cols_array(&std::array::from_fn(|k| f32_at(o + 4 * k)));
            let view = matrix(base);
            let projection = matrix(base + 64);
            if !view.is_finite() || !projection.is_finite() {
                return Err(bad("matrix with NaN or infinity".into()));
            }
            let pose = ViewProjection { width, height, view, projection };
            pose.camera().map_err(|e| bad(e.to_string()))?;
            views.push(pose);
        }
        Ok(Pose { seq, mode, client_time_ms, views })
    }
}

/// A one-view pose looking at `target` from `eye` (world +Z up) with a symmetric frustum of
/// vertical field of view `fov_y` (radians), for tests, benchmarks and headless clients.
pub fn look_at_pose(
    seq: u32,
    width: u32,
    height: u32,
    fov_y: f32,
    eye: glam::Vec3,
    target: glam::Vec3,
) -> Result<Pose, PoseError> {
    let camera = Camera::look_at(width, height, fov_y, eye, target, glam::Vec3::Z)
        .map_err(|e| PoseError::BadView { view: 0, reason: e.to_string() })?;
    let view = ViewProjection::of_camera(&camera, 0.05, 100.0);
    Ok(Pose { seq, mode: 0, client_time_ms: f64::from(seq) * 20.0, views: vec![view] })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn pose(seq: u32) -> Pose {
        look_at_pose(seq, 640, 480, 0.8, Vec3::new(3.0, -4.0, 2.0), Vec3::ZERO).expect("pose")
    }

    #[test]
    fn scaled_views_halve_each_side_down_to_the_deepest_level() {
        assert_eq!(scaled_view_size(640, 480, 0), Some((640, 480)));
        assert_eq!(scaled_view_size(640, 480, 1), Some((320, 240)));
        assert_eq!(scaled_view_size(640, 480, 2), Some((160, 120)));
        assert_eq!(scaled_view_size(640, 480, 3), None, "deeper than MAX_SCALE_LEVEL");
        assert_eq!(scaled_view_size(640, 480, 40), None);
        assert_eq!(scaled_view_size(642, 480, 2), None, "642 is not a multiple of 4");
        assert_eq!(scale_level_of(640, 480, (640, 480)), Some(0));
        assert_eq!(scale_level_of(640, 480, (160, 120)), Some(2));
        assert_eq!(scale_level_of(640, 480, (80, 60)), None, "deeper than MAX_SCALE_LEVEL");
        assert_eq!(scale_level_of(640, 480, (320, 480)), None, "one side only");
    }

    #[test]
    fn poses_round_trip_and_describe_a_camera() {
        let mut p = pose(7);
        let mut right = p.views[0];
        right.view = Mat4::from_translation(Vec3::new(-0.064, 0.0, 0.0)) * right.view;
        p.views.push(right);
        let bytes = p.encode();
        assert_eq!(bytes.len(), 20 + 2 * 128);
        let q = Pose::decode(&bytes).expect("decodes");
        assert_eq!(q, p);
        let camera = q.views[0].camera().expect("camera");
        assert!((camera.position() - Vec3::new(3.0, -4.0, 2.0)).length() < 1e-4);
        assert_eq!((camera.width(), camera.height()), (640, 480));
    }

    #[test]
    fn malformed_poses_are_rejected_with_a_reason() {
        let good = pose(1).encode();
        assert!(matches!(Pose::decode(&good[..10]), Err(PoseError::TooShort { got: 10 })));
        assert!(matches!(Pose::decode(&good[..good.len() - 1]), Err(PoseError::WrongSize { .. })));
        let mut longer = good.clone();
        longer.push(0);
        assert!(matches!(Pose::decode(&longer), Err(PoseError::WrongSize { .. })));
        let mut b = good.clone();
        b[0] = b'{';
        assert_eq!(Pose::decode(&b), Err(PoseError::BadMagic(b'{')));
        let mut b = good.clone();
        b[1] = 9;
        assert_eq!(Pose::decode(&b), Err(PoseError::BadVersion(9)));
        let mut b = good.clone();
        b[2] = 0;
        assert_eq!(Pose::decode(&b), Err(PoseError::ViewCount(0)));
        // NaN in the view matrix, infinity in the projection.
        for offset in [20 + 4 * 5, 84 + 4 * 10] {
            let mut b = good.clone();
            b[offset..offset + 4].copy_from_slice(&f32::NAN.to_le_bytes());
            assert!(matches!(Pose::decode(&b), Err(PoseError::BadView { view: 0, .. })), "offset {offset}");
        }
        let mut b = good.clone();
        b[8..16].copy_from_slice(&f64::INFINITY.to_le_bytes());
        assert_eq!(Pose::decode(&b), Err(PoseError::BadTimestamp));
        // A scaled (non-rigid) view matrix, a zero frame size, an orthographic projection.
        let mut p = pose(1);
        p.views[0].view *= 2.0;
        assert!(matches!(Pose::decode(&p.encode()), Err(PoseError::BadView { .. })));
        let mut p = pose(1);
        p.views[0].width = 0;
        assert!(matches!(Pose::decode(&p.encode()), Err(PoseError::BadView { .. })));
        let mut p = pose(1);
        p.views[0].projection = Mat4::from_diagonal(glam::Vec4::new(1.0, 1.0, -0.2, 1.0)); // orthographic: w = 1
        assert!(matches!(Pose::decode(&p.encode()), Err(PoseError::BadView { .. })));
        // The AR mode decodes; an unknown display mode does not.
        assert_eq!([1, 2, 3, 4, 9, 45, 48, 64].map(grid_columns), [1, 2, 2, 2, 3, 5, 8, 8]);
        let slots = quilt_slot_views(45);
        assert_eq!((slots[0], slots[4], slots[40], slots[44], slots[22]), (40, 44, 0, 4, 22));
        let mut seen = slots.clone();
        seen.sort_unstable();
        assert_eq!(seen, (0..45).collect::<Vec<_>>());
        assert_eq!(quilt_slot_views(10), (0..10).collect::<Vec<_>>());
        let mut b = good.clone();
        b[3] = MODE_AR;
        assert_eq!(Pose::decode(&b).map(|p| p.mode), Ok(MODE_AR));
        b[3] = 4;
        assert_eq!(Pose::decode(&b), Err(PoseError::BadMode(4)));
    }
}
