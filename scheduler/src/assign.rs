//! The TaskAssigner's geometry: which pixels of a view an object may cover (`nhit`, NEPHELE
//! section 5), how they are cut into ray batches, how heavy a task is, and when two views ask
//! for the same rays.
//!
//! The estimate projects the object's occupancy proxy (its bounding box, or the occupied cells
//! of a coarse occupancy grid inside it) into the view. It is conservative: every pixel whose
//! ray can hit the proxy is in the set (a pixel the set missed would be a hole in the composed
//! frame), at the price of a few pixels around the silhouette that the kernel then returns
//! empty. Pixel sets are lists of rectangles in bands of `band_rows` rows; a worker expands
//! them to index lists (`y * width + x`, the kernel interface's convention) with
//! [`PixelSet::indices`].

use glam::{DVec3, Vec3};
use nephele_geometry::Bounds;
use nephele_geometry::camera::Camera;
use serde::{Deserialize, Serialize};

use crate::config::ShareTolerance;

/// A rectangle of pixels, half-open: columns `x0..x1`, rows `y0..y1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PixelRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl PixelRect {
    pub fn width(&self) -> u32 {
        self.x1.saturating_sub(self.x0)
    }

    pub fn height(&self) -> u32 {
        self.y1.saturating_sub(self.y0)
    }

    pub fn len(&self) -> u64 {
        u64::from(self.width()) * u64::from(self.height())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)
    }
}

/// A set of pixels of one `width x height` view: disjoint rectangles, in row-band order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PixelSet {
    width: u32,
    height: u32,
    rects: Vec<PixelRect>,
}

impl PixelSet {
    /// A set from rectangles; `None` if a rectangle is empty or leaves the image. Disjointness
    /// is the caller's promise (the assigner's sets are disjoint by construction).
    pub fn new(width: u32, height: u32, rects: Vec<PixelRect>) -> Option<PixelSet> {
        let inside = |r: &PixelRect| r.x0 < r.x1 && r.y0 < r.y1 && r.x1 <= width && r.y1 <= height;
        rects.iter().all(inside).then_some(PixelSet { width, height, rects })
    }

    /// Every pixel of the view.
    pub fn full(width: u32, height: u32) -> PixelSet {
        PixelSet { width, height, rects: vec![PixelRect { x0: 0, y0: 0, x1: width, y1: height }] }
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    pub fn rects(&self) -> &[PixelRect] {
        &self.rects
    }

    /// Number of pixels (= primary rays).
    pub fn len(&self) -> u64 {
        self.rects.iter().map(PixelRect::len).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.rects.is_empty()
    }

    pub fn contains(&self, x: u32, y: u32) -> bool {
        self.rects.iter().any(|r| r.contains(x, y))
    }

    /// The pixel indices `y * width + x`, rectangle by rectangle, row-major inside each.
    pub fn indices(&self) -> Vec<u32> {
        let mut out = Vec::with_capacity(usize::try_from(self.len()).unwrap_or(0));
        for r in &self.rects {
            for y in r.y0..r.y1 {
                let row = y * self.width;
                out.extend((r.x0..r.x1).map(|x| row + x));
            }
        }
        out
    }
}

/// A coarse occupancy grid over an object's bounds: `dims[0] x dims[1] x dims[2]` cells,
/// x fastest, `true` where the object has matter. A tighter proxy than the box for objects
/// that fill little of it (a chair, a plant).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OccupancyGrid {
    dims: [u32; 3],
    occupied: Vec<bool>,
}

/// Largest accepted number of cells in an [`OccupancyGrid`] (projection cost is per cell).
pub const MAX_OCCUPANCY_CELLS: usize = 32 * 32 * 32;

impl OccupancyGrid {
    /// `None` if a dimension is zero, the grid exceeds [`MAX_OCCUPANCY_CELLS`] or the cell
    /// count does not match.
    pub fn new(dims: [u32; 3], occupied: Vec<bool>) -> Option<OccupancyGrid> {
        let cells = dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(usize::try_from(d).ok()?))?;
        (dims.iter().all(|&d| d > 0) && cells <= MAX_OCCUPANCY_CELLS && occupied.len() == cells)
            .then_some(OccupancyGrid { dims, occupied })
    }

    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }

    pub fn occupied_count(&self) -> usize {
        self.occupied.iter().filter(|&&o| o).count()
    }

    /// Boxes of the occupied cells, in world space, for an object with `bounds`.
    pub fn occupied_cells(&self, bounds: &Bounds) -> Vec<Bounds> {
        let [nx, ny, nz] = self.dims;
        let step = bounds.size() / Vec3::new(nx as f32, ny as f32, nz as f32);
        let mut cells = Vec::new();
        for (index, _) in self.occupied.iter().enumerate().filter(|(_, o)| **o) {
            let i = (index % nx as usize) as f32;
            let j = ((index / nx as usize) % ny as usize) as f32;
            let k = (index / (nx as usize * ny as usize)) as f32;
            let min = bounds.min + step * Vec3::new(i, j, k);
            cells.push(Bounds { min, max: min + step });
        }
        cells
    }
}

/// What the assigner estimates for one object in one view: NEPHELE's `nhit`.
#[derive(Debug, Clone, PartialEq)]
pub struct Coverage {
    /// The pixels whose rays may hit the object (conservative).
    pub pixels: PixelSet,
    /// Their number: one primary ray each.
    pub rays: u64,
    /// Mean view-space depth of the proxy (of its occupied cells, or of the box centre).
    pub mean_depth: f32,
}

/// Estimates which pixels of `camera`'s view the object may cover, by projecting its proxy;
/// `None` if it covers none (behind the camera or outside the frustum).
pub fn estimate_coverage(
    camera: &Camera,
    bounds: &Bounds,
    occupancy: Option<&OccupancyGrid>,
    band_rows: u32,
) -> Option<Coverage> {
    let (w, h) = (camera.width(), camera.height());
    let band_rows = band_rows.max(1);
    let boxes = match occupancy {
        Some(grid) => grid.occupied_cells(bounds),
        None => vec![*bounds],
    };
    // (band, x0, x1, r0, r1) spans of each projected box, merged below.
    let mut spans: Vec<(u32, u32, u32, u32, u32)> = Vec::new();
    let mut depth_sum = 0.0f64;
    let mut depth_count = 0u32;
    for cell in &boxes {
        let Some(hull) = project_box(camera, cell) else { continue };
        let depth = camera.view_depth(cell.center());
        if depth.is_finite() && depth > 0.0 {
            depth_sum += f64::from(depth);
            depth_count += 1;
        }
        band_spans(&hull, w, h, band_rows, &mut spans);
    }
    if boxes.len() > 1 {
        spans.sort_unstable();
    }
    let mut rects: Vec<PixelRect> = Vec::with_capacity(spans.len());
    let mut current: Option<(u32, u32, u32, u32, u32)> = None;
    for &(band, x0, x1, r0, r1) in &spans {
        current = match current {
            Some((cb, cx0, cx1, cr0, cr1)) if cb == band && x0 <= cx1 => {
                Some((cb, cx0, cx1.max(x1), cr0.min(r0), cr1.max(r1)))
            }
            Some((_, cx0, cx1, cr0, cr1)) => {
                rects.push(PixelRect { x0: cx0, y0: cr0, x1: cx1, y1: cr1 });
                Some((band, x0, x1, r0, r1))
            }
            None => Some((band, x0, x1, r0, r1)),
        };
    }
    if let Some((_, x0, x1, r0, r1)) = current {
        rects.push(PixelRect { x0, y0: r0, x1, y1: r1 });
    }
    if rects.is_empty() {
        return None;
    }
    let pixels = PixelSet { width: w, height: h, rects };
    let mean_depth = if depth_count > 0 { (depth_sum / f64::from(depth_count)) as f32 } else { 0.0 };
    Some(Coverage { rays: pixels.len(), pixels, mean_depth })
}

/// The convex hull, in pixel coordinates, of the part of a box in front of the camera; `None`
/// if the box lies wholly behind the camera plane.
fn project_box(camera: &Camera, bounds: &Bounds) -> Option<Vec<[f64; 2]>> {
    let view = camera.world_to_camera();
    let corners = bounds.corners().map(|c| view.transform_point3(c).as_dvec3());
    if !corners.iter().all(|q| q.is_finite()) {
        return None;
    }
    let extent = corners.iter().map(|q| q.abs().max_element()).fold(1.0f64, f64::max);
    // The clip plane sits just in front of the camera centre; points on it project far outside
    // the image, which is what the conservative estimate wants.
    let near = 1e-6 * extent;
    let in_front = |q: &DVec3| -q.z >= near;
    let (fx, fy, cx, cy) = camera.intrinsics();
    let (fx, fy, cx, cy) = (f64::from(fx), f64::from(fy), f64::from(cx), f64::from(cy));
    let project = |q: DVec3| [cx + fx * q.x / -q.z, cy - fy * q.y / -q.z];
    let mut points: Vec<[f64; 2]> = corners.iter().filter(|q| in_front(q)).map(|&q| project(q)).collect();
    if points.is_empty() {
        return None;
    }
    if points.len() < 8 {
        // Box edges (corners differing in one coordinate bit) that cross the clip plane.
        for i in 0..8usize {
            for bit in [1usize, 2, 4] {
                let j = i | bit;
                if i & bit != 0 || in_front(&corners[i]) == in_front(&corners[j]) {
                    continue;
                }
                let (a, b) = (corners[i], corners[j]);
                let t = (-near - a.z) / (b.z - a.z);
                let mut p = a + t * (b - a);
                p.z = -near;
                points.push(project(p));
            }
        }
    }
    Some(convex_hull(points))
}

/// Andrew's monotone chain; counter-clockwise in a y-up frame, duplicates removed.
fn convex_hull(mut points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    points.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    points.dedup();
    if points.len() < 3 {
        return points;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(points.len() * 2);
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &[f64; 2]>> =
            if pass == 0 { Box::new(points.iter()) } else { Box::new(points.iter().rev()) };
        for &p in iter {
            while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    if hull.is_empty() {
        // All points collinear and equal after dedup cannot happen (len >= 3); keep the extremes.
        hull = vec![points[0], points[points.len() - 1]];
    }
    hull
}

/// Adds, per band of `band_rows` rows, the pixel span the convex polygon `hull` touches.
fn band_spans(hull: &[[f64; 2]], w: u32, h: u32, band_rows: u32, spans: &mut Vec<(u32, u32, u32, u32, u32)>) {
    let (mut ymin, mut ymax, mut xmin, mut xmax) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for p in hull {
        xmin = xmin.min(p[0]);
        xmax = xmax.max(p[0]);
        ymin = ymin.min(p[1]);
        ymax = ymax.max(p[1]);
    }
    let (wf, hf) = (f64::from(w), f64::from(h));
    if !(ymax >= 0.0 && ymin < hf && xmax >= 0.0 && xmin < wf) {
        return;
    }
    // Pixel rows whose [y, y + 1) interval meets [ymin, ymax].
    let ystart = ymin.max(0.0).floor() as u32;
    let yend = (ymax.min(hf - 1.0).floor() as u32 + 1).min(h);
    if ystart >= yend {
        return;
    }
    for band in ystart / band_rows..=(yend - 1) / band_rows {
        let r0 = (band * band_rows).max(ystart);
        let r1 = ((band + 1) * band_rows).min(yend);
        let Some((lo, hi)) = slab_x_range(hull, f64::from(r0), f64::from(r1)) else { continue };
        if hi < 0.0 || lo >= wf {
            continue;
        }
        let x0 = lo.max(0.0).floor() as u32;
        let x1 = (hi.min(wf - 1.0).floor() as u32 + 1).min(w);
        if x1 > x0 {
            spans.push((band, x0, x1, r0, r1));
        }
    }
}

/// The x extent of a convex polygon (or segment, or point) within the slab `ya <= y <= yb`.
fn slab_x_range(hull: &[[f64; 2]], ya: f64, yb: f64) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut take = |x: f64| {
        lo = lo.min(x);
        hi = hi.max(x);
    };
    let n = hull.len();
    for (i, p) in hull.iter().enumerate() {
        if p[1] >= ya && p[1] <= yb {
            take(p[0]);
        }
        let q = hull[(i + 1) % n];
        for y in [ya, yb] {
            if (p[1] - y) * (q[1] - y) < 0.0 {
                take(p[0] + (y - p[1]) / (q[1] - p[1]) * (q[0] - p[0]));
            }
        }
    }
    (lo <= hi).then_some((lo, hi))
}

/// Cuts a pixel set into batches of at most `max_rays` pixels, each again a list of
/// rectangles: whole rectangles where they fit, rows of a rectangle otherwise, pieces of a row
/// only for rows wider than `max_rays`. The batches partition the set exactly.
/// `bands` horizontal bands of whole rows of the image (an environment's view split over
/// workers; the kernel shades each band with a margin of rows around it).
pub fn split_rows(width: u32, height: u32, bands: u32) -> Vec<PixelSet> {
    let bands = bands.clamp(1, height.max(1));
    (0..bands)
        .filter_map(|k| {
            let (y0, y1) = (k * height / bands, (k + 1) * height / bands);
            PixelSet::new(width, height, vec![PixelRect { x0: 0, y0, x1: width, y1 }])
        })
        .collect()
}

pub fn split_batches(set: &PixelSet, max_rays: u32) -> Vec<PixelSet> {
    let max = u64::from(max_rays.max(1));
    let mut batches = Vec::new();
    let mut current: Vec<PixelRect> = Vec::new();
    let mut filled = 0u64;
    let mut flush = |current: &mut Vec<PixelRect>, filled: &mut u64| {
        if !current.is_empty() {
            batches.push(PixelSet { width: set.width, height: set.height, rects: std::mem::take(current) });
        }
        *filled = 0;
    };
    for rect in &set.rects {
        let mut r = *rect;
        // Rows wider than a batch: cut into single-row pieces first.
        let pieces: Vec<PixelRect> = if u64::from(r.width()) > max {
            let step = max_rays.max(1);
            (r.y0..r.y1)
                .flat_map(|y| {
                    (r.x0..r.x1).step_by(step as usize).map(move |x| PixelRect {
                        x0: x,
                        y0: y,
                        x1: (x + step).min(r.x1),
                        y1: y + 1,
                    })
                })
                .collect()
        } else {
            Vec::new()
        };
        if !pieces.is_empty() {
            for piece in pieces {
                if filled + piece.len() > max {
                    flush(&mut current, &mut filled);
                }
                filled += piece.len();
                current.push(piece);
            }
            continue;
        }
        while !r.is_empty() {
            let room = max - filled;
            if r.len() <= room {
                filled += r.len();
                current.push(r);
                break;
            }
            let rows = (room / u64::from(r.width())) as u32;
            if rows > 0 {
                current.push(PixelRect { y1: r.y0 + rows, ..r });
                r.y0 += rows;
            }
            flush(&mut current, &mut filled);
        }
        if filled == max {
            flush(&mut current, &mut filled);
        }
    }
    flush(&mut current, &mut filled);
    batches
}

/// NEPHELE's task classes: Heavy tasks get workers of their own (HeavyFarm), Light ones are
/// packed onto shared workers (LightFarm).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TaskClass {
    Heavy,
    Light,
}

/// Heavy when the task's estimated time on the median worker exceeds `heavy_fraction` of the
/// frame budget (see [`crate::SchedulerConfig::heavy_fraction`]).
pub fn classify(estimated_seconds: f64, frame_budget_seconds: f64, heavy_fraction: f64) -> TaskClass {
    if estimated_seconds > heavy_fraction * frame_budget_seconds { TaskClass::Heavy } else { TaskClass::Light }
}

/// A camera quantised on the sharing grid of a [`ShareTolerance`]: views with equal keys ask
/// for the same rays (within the tolerance) and are rendered once.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraKey {
    size: [u32; 2],
    position: [i64; 3],
    forward: [i32; 3],
    up: [i32; 3],
    intrinsics: [i64; 4],
}

impl std::hash::Hash for CameraKey {
    /// One write of the packed fields: hashing field by field costs several times more.
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        let mut bytes = [0u8; 88];
        let mut at = 0;
        let mut put = |b: &[u8]| {
            bytes[at..at + b.len()].copy_from_slice(b);
            at += b.len();
        };
        self.size.iter().for_each(|v| put(&v.to_le_bytes()));
        self.position.iter().for_each(|v| put(&v.to_le_bytes()));
        self.forward.iter().chain(&self.up).for_each(|v| put(&v.to_le_bytes()));
        self.intrinsics.iter().for_each(|v| put(&v.to_le_bytes()));
        state.write(&bytes);
    }
}

impl CameraKey {
    pub fn new(camera: &Camera, tolerance: &ShareTolerance) -> CameraKey {
        let q64 = |v: f32, step: f32| ((f64::from(v) / f64::from(step)).round().clamp(-9e18, 9e18)) as i64;
        let q32 = |v: f32, step: f32| ((v / step).round().clamp(-2e9, 2e9)) as i32;
        let p = camera.position();
        let (f, u) = (camera.forward(), camera.up());
        let (fx, fy, cx, cy) = camera.intrinsics();
        let (ps, a, i) = (tolerance.position_m, tolerance.angle_rad, tolerance.intrinsics_px);
        CameraKey {
            size: [camera.width(), camera.height()],
            position: [q64(p.x, ps), q64(p.y, ps), q64(p.z, ps)],
            forward: [q32(f.x, a), q32(f.y, a), q32(f.z, a)],
            up: [q32(u.x, a), q32(u.y, a), q32(u.z, a)],
            intrinsics: [q64(fx, i), q64(fy, i), q64(cx, i), q64(cy, i)],
        }
    }
}

/// How far apart (pixels, largest over the box corners in front of both cameras) an object's
/// box appears in two views: the error of showing `a`'s rendering to a viewer at `b`.
pub fn reprojection_error_px(a: &Camera, b: &Camera, bounds: &Bounds) -> f32 {
    bounds.corners().iter().filter_map(|&c| Some((a.project(c)? - b.project(c)?).length())).fold(0.0f32, f32::max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;
    use nephele_geometry::camera::{quilt_rig, stereo_pair};
    use proptest::prelude::*;

    fn camera(eye: Vec3, target: Vec3, w: u32, h: u32) -> Camera {
        Camera::look_at(w, h, 0.8, eye, target, Vec3::Z).expect("valid camera")
    }

    fn unit_box() -> Bounds {
        Bounds { min: Vec3::splat(-0.5), max: Vec3::splat(0.5) }
    }

    fn assert_partition(set: &PixelSet) {
        let mut seen = vec![false; (set.width() * set.height()) as usize];
        for i in set.indices() {
            assert!(!seen[i as usize], "pixel {i} twice");
            seen[i as usize] = true;
        }
        assert_eq!(seen.iter().filter(|&&s| s).count() as u64, set.len());
    }

    #[test]
    fn box_in_front_covers_its_projection_and_no_far_pixels() {
        let cam = camera(Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, 200, 100);
        let cov = estimate_coverage(&cam, &unit_box(), None, 16).expect("visible");
        assert_partition(&cov.pixels);
        assert!((cov.mean_depth - 4.0).abs() < 1e-4, "{}", cov.mean_depth);
        // Every corner projects into a covered pixel; the image corners are not covered.
        for c in unit_box().corners() {
            let p = cam.project(c).expect("in front");
            assert!(cov.pixels.contains(p.x as u32, p.y as u32), "{p}");
        }
        assert!(!cov.pixels.contains(0, 0) && !cov.pixels.contains(199, 99));
        // A box seen head-on from 4 m at fy = 50 / tan(0.4): about (fy * 1.1 / 3.5)^2 pixels
        // (the near face is 3.5 m away); bands add at most a few rows and columns.
        let fy = 50.0 / 0.4f64.tan();
        let side = fy * 1.0 / 3.5;
        assert!((cov.rays as f64) >= side * side && (cov.rays as f64) < (side + 18.0) * (side + 18.0), "{}", cov.rays);
    }

    #[test]
    fn invisible_objects_cover_nothing_and_enclosing_ones_cover_everything() {
        let cam = camera(Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, 64, 48);
        let behind = Bounds { min: Vec3::new(-0.5, -9.0, -0.5), max: Vec3::new(0.5, -8.0, 0.5) };
        assert_eq!(estimate_coverage(&cam, &behind, None, 8), None);
        let beside = Bounds { min: Vec3::new(50.0, -1.0, -0.5), max: Vec3::new(51.0, 0.0, 0.5) };
        assert_eq!(estimate_coverage(&cam, &beside, None, 8), None);
        // The camera inside the box: every pixel.
        let around = Bounds { min: Vec3::splat(-10.0), max: Vec3::splat(10.0) };
        let cov = estimate_coverage(&cam, &around, None, 8).expect("visible");
        assert_eq!(cov.rays, 64 * 48);
        // Straddling the camera plane (part behind): still conservative and inside the image.
        let straddle = Bounds { min: Vec3::new(-0.2, -5.0, -0.2), max: Vec3::new(0.2, -3.0, 0.2) };
        let cov = estimate_coverage(&cam, &straddle, None, 8).expect("visible");
        assert!(cov.pixels.contains(32, 24));
        assert_partition(&cov.pixels);
    }

    #[test]
    fn occupancy_grid_tightens_the_estimate() {
        let cam = camera(Vec3::new(0.3, -3.0, 0.5), Vec3::ZERO, 160, 120);
        // An L-shaped object: 3 of 8 cells.
        let mut occupied = vec![false; 8];
        for i in [0, 1, 4] {
            occupied[i] = true;
        }
        let grid = OccupancyGrid::new([2, 2, 2], occupied).expect("grid");
        let full = estimate_coverage(&cam, &unit_box(), None, 8).expect("visible");
        let tight = estimate_coverage(&cam, &unit_box(), Some(&grid), 8).expect("visible");
        assert!(tight.rays < full.rays, "{} vs {}", tight.rays, full.rays);
        for cell in grid.occupied_cells(&unit_box()) {
            for c in cell.corners() {
                let p = cam.project(c).expect("in front");
                assert!(tight.pixels.contains(p.x as u32, p.y as u32));
            }
        }
        assert_partition(&tight.pixels);
        assert!(OccupancyGrid::new([0, 1, 1], vec![]).is_none());
        assert!(OccupancyGrid::new([2, 2, 2], vec![true; 7]).is_none());
        assert!(OccupancyGrid::new([64, 64, 64], vec![true; 64 * 64 * 64]).is_none());
    }

    #[test]
    fn batches_partition_the_set_within_the_limit() {
        let set = PixelSet::full(100, 37);
        for max in [1, 7, 100, 150, 1000, 5000] {
            let batches = split_batches(&set, max);
            let mut all: Vec<u32> = batches.iter().flat_map(PixelSet::indices).collect();
            assert!(batches.iter().all(|b| b.len() <= u64::from(max) && !b.is_empty()));
            all.sort_unstable();
            assert_eq!(all, (0..3700).collect::<Vec<u32>>(), "max {max}");
            assert!(batches.len() as u64 >= 3700u64.div_ceil(u64::from(max)));
        }
        // Whole rows are kept together where they fit: 150 -> one row of 100 per batch.
        assert_eq!(split_batches(&set, 150).len(), 37);
        assert_eq!(split_batches(&set, 1000).len(), 4);
        assert!(PixelSet::new(10, 10, vec![PixelRect { x0: 5, y0: 0, x1: 11, y1: 1 }]).is_none());
        assert!(PixelSet::new(10, 10, vec![PixelRect { x0: 5, y0: 0, x1: 5, y1: 1 }]).is_none());
    }

    #[test]
    fn camera_keys_share_identical_views_not_eyes_or_quilt_neighbours() {
        let tol = ShareTolerance::default();
        let centre = camera(Vec3::new(0.0, -4.0, 1.0), Vec3::ZERO, 320, 240);
        let same = Camera::from_intrinsics(
            320,
            240,
            centre.intrinsics().0,
            centre.intrinsics().1,
            160.0,
            120.0,
            centre.camera_to_world(),
        );
        assert_eq!(CameraKey::new(&centre, &tol), CameraKey::new(&same.expect("valid"), &tol));
        let [left, right] = stereo_pair(&centre, 0.064).expect("stereo");
        assert_ne!(CameraKey::new(&left, &tol), CameraKey::new(&right, &tol));
        let quilt = quilt_rig(&centre, 45, 0.7, 4.0).expect("quilt");
        let keys: std::collections::HashSet<CameraKey> = quilt.iter().map(|c| CameraKey::new(c, &tol)).collect();
        assert_eq!(keys.len(), 45, "adjacent quilt views are different rays");
        let again = quilt_rig(&centre, 45, 0.7, 4.0).expect("quilt");
        assert!(quilt.iter().zip(&again).all(|(a, b)| CameraKey::new(a, &tol) == CameraKey::new(b, &tol)));
        // Moved by 0.1 mm, or a different image size.
        let nudged = Camera::from_fov_y(
            320,
            240,
            centre.fov_y(),
            Mat4::from_translation(Vec3::new(1e-4, 0.0, 0.0)) * centre.camera_to_world(),
        );
        let nudged = nudged.expect("valid");
        let err = reprojection_error_px(&centre, &nudged, &unit_box());
        assert!(err > 0.0 && err < 0.1, "{err}");
        let other_size = camera(Vec3::new(0.0, -4.0, 1.0), Vec3::ZERO, 321, 240);
        assert_ne!(CameraKey::new(&centre, &tol), CameraKey::new(&other_size, &tol));
        assert_eq!(classify(0.01, 1.0 / 30.0, 0.25), TaskClass::Heavy);
        assert_eq!(classify(0.008, 1.0 / 30.0, 0.25), TaskClass::Light);
    }

    proptest! {
        /// Any point inside the box that projects into the image lands in a covered pixel, and
        /// the batches partition the set.
        #[test]
        fn coverage_is_conservative(
            eye in prop::array::uniform3(-6.0f32..6.0),
            lo in prop::array::uniform3(-1.0f32..1.0),
            size in prop::array::uniform3(0.01f32..2.0),
            samples in prop::collection::vec(prop::array::uniform3(0.0f32..=1.0), 16),
            band in 1u32..40,
            max_rays in 1u32..5000,
        ) {
            let eye = Vec3::from(eye);
            prop_assume!(eye.length() > 0.5 && (eye.x.abs() + eye.y.abs()) > 0.1);
            let cam = Camera::look_at(97, 61, 1.1, eye, Vec3::ZERO, Vec3::Z).expect("valid");
            let bounds = Bounds { min: Vec3::from(lo), max: Vec3::from(lo) + Vec3::from(size) };
            let cov = estimate_coverage(&cam, &bounds, None, band);
            for s in samples {
                let p = bounds.min + Vec3::from(s) * bounds.size();
                if let Some(px) = cam.project(p)
                    && px.x >= 0.0 && px.y >= 0.0 && px.x < 97.0 && px.y < 61.0 {
                        let cov = cov.as_ref().expect("a visible point means coverage");
                        prop_assert!(cov.pixels.contains(px.x as u32, px.y as u32), "{px} not covered");
                    }
            }
            if let Some(cov) = cov {
                assert_partition(&cov.pixels);
                let batches = split_batches(&cov.pixels, max_rays);
                prop_assert_eq!(batches.iter().map(PixelSet::len).sum::<u64>(), cov.rays);
                prop_assert!(batches.iter().all(|b| b.len() <= u64::from(max_rays)));
            }
        }
    }
}
