//! A synthetic frame source standing in for the render farm: two objects seen from the
//! viewer's pose, rendered as object batches exactly as workers would send them (a solid
//! disc at the world origin and a translucent disc in front of it at `(0.6, 0, 0.4)`), so a
//! composer without workers still exercises fusion, encoding and streaming, and the picture
//! follows the pose.

use nephele_geometry::PixelResults;
use nephele_geometry::camera::Camera;

use std::sync::Arc;
use std::time::{Duration, Instant};

use nephele_shutdown::Shutdown;

use crate::fusion::{BatchKey, BatchResult, FrameLayout, FramePlan, PlannedBatch, SessionId};
use crate::pose::Pose;
use crate::state::{Shared, lock};

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

/// The plan (fused at `deadline` at the latest) and batches of one frame: one batch per
/// object per view, covering the pixels inside the object's projected disc. `cameras` gives
/// each view's camera (all of the layout's view size).
pub fn frame(
    session: SessionId,
    frame: u64,
    layout: FrameLayout,
    cameras: &[Camera],
    deadline: Instant,
) -> (FramePlan, Vec<BatchResult>) {
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
            results.push(BatchResult::from_results(session, frame, view, key, pixels, out));
        }
    }
    (FramePlan { session, frame, layout, background: BACKGROUND, deadline, batches: planned }, results)
}

/// Cameras of a session's views: from its latest pose, or a default view of the pattern.
pub(crate) fn cameras_for(layout: FrameLayout, pose: Option<&Pose>) -> Vec<Camera> {
    let (w, h) = (layout.view_width(), layout.view_height());
    let from_pose = pose
        .and_then(|p| p.views.iter().map(|v| Camera::from_view_projection(w, h, v.view, v.projection).ok()).collect());
    from_pose.unwrap_or_else(|| {
        let eye = glam::Vec3::new(0.0, -3.0, 1.0);
        (0..layout.views())
            .filter_map(|i| {
                let offset = glam::Vec3::X * (f32::from(i) - f32::from(layout.views() - 1) / 2.0) * 0.064;
                Camera::look_at(w, h, 0.9, eye + offset, glam::Vec3::ZERO + offset, glam::Vec3::Z).ok()
            })
            .collect()
    })
}

pub(crate) async fn test_pattern_loop(shared: Arc<Shared>, stop: Shutdown) {
    let mut tick = tokio::time::interval(Duration::from_secs_f32(1.0 / shared.config.fps));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.wait() => return,
        }
        let work: Vec<(SessionId, u64, FrameLayout, Option<Arc<Pose>>)> = {
            let mut sessions = lock(&shared.sessions);
            sessions
                .iter_mut()
                .filter(|(_, e)| e.viewer.is_connected())
                .map(|(&id, e)| {
                    e.next_frame += 1;
                    (id, e.next_frame, e.layout, e.last_pose.clone())
                })
                .collect()
        };
        let now = Instant::now();
        for (id, frame, layout, pose) in work {
            let cameras = cameras_for(layout, pose.as_deref());
            let (plan, batches) = self::frame(id, frame, layout, &cameras, now + shared.config.frame_budget);
            let mut compositor = lock(&shared.compositor);
            if compositor.plan_frame(plan).is_ok() {
                for b in batches {
                    let _ = compositor.add_batch(b);
                }
            }
        }
        shared.wake.notify_one();
    }
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
        let now = Instant::now();
        let (plan_a, batches_a) = frame(1, 0, layout, &[front], now);
        let (_, batches_b) = frame(1, 0, layout, &[side], now);
        assert_eq!(plan_a.batches.len(), 2);
        assert_eq!(batches_a.len(), 2);
        for b in &batches_a {
            b.validate(&layout).unwrap();
        }
        assert_ne!(batches_a[1].pixels(), batches_b[1].pixels(), "the translucent disc moves with the camera");
        let behind =
            Camera::look_at(64, 48, 0.8, Vec3::new(0.0, -4.0, 0.0), Vec3::new(0.0, -8.0, 0.0), Vec3::Z).unwrap();
        assert!(frame(1, 0, layout, &[behind], now).1.is_empty());
    }
}
