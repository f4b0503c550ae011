//! A synthetic frame source standing in for the render farm: two objects seen from the
//! viewer's pose, rendered as object batches exactly as workers would send them (a solid
//! disc at the world origin and a translucent disc in front of it at `(0.6, 0, 0.4)`), so a
//! composer without workers still exercises fusion, encoding and streaming, and the picture
//! follows the pose.

use nephele_geometry::PixelResults;
use nephele_geometry::camera::Camera;

use crate::fusion::{BatchKey, BatchResult, FrameLayout, PlannedBatch, SessionId};
use crate::wire::PlanBody;

/// Linear background colour of the pattern.
pub const BACKGROUND: [f32; 3] = [0.02, 0.03, 0.05];

struct Blob {
    center: glam::Vec3,
    radius: f32,
    color: [f32; 3],
    opacity: f32,
}

const BLOBS: [Blob; 2] = [
    Blob { center: glam::Vec3::ZERO, radius: 0.5, color: [0.9, 0.45, 0.1], opacity: 1.0 },
    Blob { center: glam::Vec3::new(0.6, 0.0, 0.4), radius: 0.35, color: [0.1, 0.4, 0.9], opacity: 0.5 },
];

/// The plan and batches of one frame: one batch per object per view, covering the pixels
/// inside the object's projected disc. `cameras` gives each view's camera (all of the
/// layout's view size).
pub fn frame(session: SessionId, frame: u64, layout: FrameLayout, cameras: &[Camera]) -> (PlanBody, Vec<BatchResult>) {
    let mut planned = Vec::new();
    let mut results = Vec::new();
    let (w, h) = (layout.view_width(), layout.view_height());
    for (view, camera) in cameras.iter().enumerate().take(usize::from(layout.views())) {
        let view = view as u16;
        for (object, blob) in BLOBS.iter().enumerate() {
            let Some(center) = camera.project(blob.center) else { continue };
            let depth = camera.view_depth(blob.center);
            if depth <= 0.0 {
                continue;
            }
            // Projected radius: focal length in pixels times radius over depth.
            let (fx, _, _, _) = camera.intrinsics();
            let r = fx * blob.radius / depth;
            let (x0, x1) = ((center.x - r).floor().max(0.0) as u32, ((center.x + r).ceil().max(0.0) as u32).min(w));
            let (y0, y1) = ((center.y - r).floor().max(0.0) as u32, ((center.y + r).ceil().max(0.0) as u32).min(h));
            let mut pixels = Vec::new();
            let mut out = PixelResults::default();
            for y in y0..y1 {
                for x in x0..x1 {
                    let d = glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5) - center;
                    let q = d.length_squared() / (r * r);
                    if q < 1.0 {
                        // Shade like a sphere lit from the viewer: brighter in the middle.
                        let shade = (1.0 - q).sqrt() * 0.8 + 0.2;
                        let a = blob.opacity;
                        pixels.push(y * w + x);
                        out.color.push(blob.color.map(|c| c * shade * a));
                        out.opacity.push(a);
                        out.depth.push(depth);
                    }
                }
            }
            if pixels.is_empty() {
                continue;
            }
            let key = BatchKey { object: object as u32, batch: u32::from(view) };
            planned.push(PlannedBatch { key, view, pixels: pixels.clone().into() });
            results.push(BatchResult { session, frame, view, key, pixels, results: out });
        }
    }
    (PlanBody { session, frame, layout, background: BACKGROUND, batches: planned }, results)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn the_pattern_follows_the_camera() {
        let layout = FrameLayout::mono(64, 48).unwrap();
        let front = Camera::look_at(64, 48, 0.8, Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, Vec3::Z).unwrap();
        let side = Camera::look_at(64, 48, 0.8, Vec3::new(4.0, 0.0, 0.0), Vec3::ZERO, Vec3::Z).unwrap();
        let (plan_a, batches_a) = frame(1, 0, layout, &[front]);
        let (_, batches_b) = frame(1, 0, layout, &[side]);
        assert_eq!(plan_a.batches.len(), 2);
        assert_eq!(batches_a.len(), 2);
        for b in &batches_a {
            b.validate(&layout).unwrap();
        }
        assert_ne!(batches_a[1].pixels, batches_b[1].pixels, "the translucent disc moves with the camera");
        let behind =
            Camera::look_at(64, 48, 0.8, Vec3::new(0.0, -4.0, 0.0), Vec3::new(0.0, -8.0, 0.0), Vec3::Z).unwrap();
        assert!(frame(1, 0, layout, &[behind]).1.is_empty());
    }
}
