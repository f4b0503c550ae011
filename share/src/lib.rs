//! `nephele-share`: pixels rendered for one view reused by another, adjacent, view.
//!
//! NEPHELE's multi-user claim rests on rays that several views share (section 5, eqs. 10-12):
//! the two eyes of a headset, the 45 views of a light-field display, users looking at one
//! object from nearby angles, a user's consecutive frames. The scheduler merges identical
//! cameras; this crate goes further: a *target* view takes what it can from frames already
//! rendered for *source* views, by depth-based reprojection, and names the pixels that it
//! could not take and that must be rendered ([`Reprojection::pixels_to_render`]).
//!
//! How ([`reproject`]):
//!
//! 1. Every solid source pixel (opacity at least [`Settings::opaque`]) is lifted to the world
//!    point its depth names and splatted into the target's depth buffer (nearest wins); holes
//!    one pixel wide between splats (magnification) are closed from the pixels on both sides.
//! 2. Each target pixel with a depth is checked *backwards*: its point is projected into each
//!    source, where the bilinear taps must all be solid, agree in depth (no edge between
//!    two surfaces), and agree with the point's own depth (else the point is hidden in that
//!    source: a disocclusion); the angle at the point between the two views' rays must be at
//!    most [`Settings::max_angle_deg`] (view-dependent colour). The source with the smallest
//!    angle gives the colour, bilinearly.
//! 3. A pixel that is not reused is *empty* without rendering when its ray misses the object's
//!    bounds, or when no source point landed in it and every point of its ray inside the
//!    bounds projects into empty pixels of one source (it saw straight through there; the
//!    walk strides across a distance map of the source's empty space); otherwise it is
//!    rendered. Silhouettes
//!    (partly opaque source pixels) are never reused, so they are rendered.
//!
//! Pure: no images, no I/O; rows run on rayon's pool. The composer, the benchmarks and the
//! tests call it. Depends on `nephele-geometry` (and rayon) only.

use glam::{Vec2, Vec3};
use nephele_geometry::{Bounds, Camera, PixelResults, Ray};
use rayon::prelude::*;
use thiserror::Error;

/// How strict reuse is. The defaults come from `nephele bench share` on the lego (BENCHMARKS.md,
/// "Shared rays between adjacent views"); they are per object, so an object with stronger
/// highlights or finer texture can be given its own.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    /// Largest angle, at the surface point, between the source's and the target's rays for a
    /// pixel to be reused (degrees). View-dependent colour (the i-NOLF specular head) is what
    /// limits it. 6 is the knee on the lego: users 5 degrees apart render 4.9 % more rays at 4
    /// to gain 0.05 dB; users 10 degrees apart lose up to 0.32 dB at 8 against 0.21 at 6.
    pub max_angle_deg: f32,
    /// Largest depth mismatch still counted as the same surface, in pixel footprints at that
    /// depth (`depth / focal length in pixels`): 3 accepts surfaces up to about 70 degrees from
    /// facing the camera and tells surfaces apart once they are 3 pixels' width apart in depth.
    pub depth_tolerance_px: f32,
    /// Opacity from which a source pixel is solid enough to be reused.
    pub opaque: f32,
    /// Opacity up to which a source pixel counts as empty space.
    pub empty: f32,
    /// Reused pixels within this many pixels (4-neighbourhood steps) of a pixel to render are
    /// rendered too: a margin around every hole and silhouette.
    pub edge_band: u32,
    /// How a reused colour is read between source pixels.
    pub filter: Filter,
    /// Largest difference between the colours (linear, per channel) of the source pixels
    /// around a point for it to be reused: texture detail finer than a pixel resamples badly,
    /// so such pixels are rendered. `f32::INFINITY` reuses regardless. 0.2 on the lego: 1 to
    /// 2 % more rays than no limit, and the worst anchor's loss against the ground truth falls
    /// from 0.70 to 0.25 dB.
    pub max_contrast: f32,
}

/// Reconstruction of a source frame between its pixel centres.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Filter {
    /// The four nearest pixels, bilinearly.
    Bilinear,
    /// The sixteen nearest, Catmull-Rom cubic (sharper), clamped to the four nearest's range
    /// so that it cannot ring; bilinear where the sixteen are not all one solid surface.
    CatmullRom,
}

impl Default for Settings {
    fn default() -> Settings {
        Settings {
            max_angle_deg: 6.0,
            depth_tolerance_px: 3.0,
            opaque: 0.99,
            empty: 1e-3,
            edge_band: 0,
            filter: Filter::CatmullRom,
            max_contrast: 0.2,
        }
    }
}

impl Settings {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<(), ShareError> {
        let check = |name: &'static str, value: f32, ok: bool, why: &'static str| match ok {
            true => Ok(()),
            false => Err(ShareError::Setting { name, value, why }),
        };
        check("max_angle_deg", self.max_angle_deg, (0.0..=90.0).contains(&self.max_angle_deg), "must be in [0, 90]")?;
        let tolerance = self.depth_tolerance_px;
        check("depth_tolerance_px", tolerance, tolerance.is_finite() && tolerance >= 0.0, "must be finite and >= 0")?;
        check("opaque", self.opaque, self.opaque > 0.0 && self.opaque <= 1.0, "must be in (0, 1]")?;
        check("empty", self.empty, (0.0..self.opaque).contains(&self.empty), "must be in [0, opaque)")?;
        check("edge_band", self.edge_band as f32, self.edge_band <= 16, "must be at most 16")?;
        check("max_contrast", self.max_contrast, self.max_contrast >= 0.0, "must be >= 0 (infinity: no limit)")
    }
}

#[derive(Debug, Clone, Error, PartialEq)]
pub enum ShareError {
    #[error("source {index} holds {len} pixels; its {width}x{height} camera needs {expected}")]
    SourceSize { index: usize, len: usize, width: u32, height: u32, expected: usize },
    #[error("{len} rendered pixels for {pixels} pixel indices")]
    RenderedSize { len: usize, pixels: usize },
    #[error("pixel {index} is outside the {width}x{height} target")]
    PixelOutside { index: u32, width: u32, height: u32 },
    #[error("setting {name} = {value} {why}")]
    Setting { name: &'static str, value: f32, why: &'static str },
}

/// A frame rendered in full for `camera` (pixels in `all_pixels` order).
#[derive(Debug, Clone, Copy)]
pub struct Source<'a> {
    pub camera: &'a Camera,
    pub frame: &'a PixelResults,
}

/// What became of one target pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fate {
    /// Taken from a source.
    Reused,
    /// Its ray misses the object's bounds: empty, nothing to render.
    OutsideBounds,
    /// Its ray crosses the bounds only where a source saw empty space: empty.
    SeenEmpty,
    /// No source could vouch for it: to be rendered.
    Render,
}

/// How many target pixels met each fate.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FateCounts {
    pub reused: usize,
    pub outside_bounds: usize,
    pub seen_empty: usize,
    pub render: usize,
}

impl FateCounts {
    pub fn total(&self) -> usize {
        self.reused + self.outside_bounds + self.seen_empty + self.render
    }

    /// Pixels whose ray enters the object's bounds: what a full render marches.
    pub fn in_bounds(&self) -> usize {
        self.total() - self.outside_bounds
    }
}

/// A target frame assembled from sources, with the pixels still to render.
#[derive(Debug, Clone, PartialEq)]
pub struct Reprojection {
    pub width: u32,
    pub height: u32,
    /// Reused pixels filled in; empty and still-to-render pixels zero (until [`Self::fill`]).
    pub frame: PixelResults,
    pub fate: Vec<Fate>,
}

impl Reprojection {
    /// The pixels (`y * width + x`) that no source covered: the rays the farm renders.
    pub fn pixels_to_render(&self) -> Vec<u32> {
        (0..self.fate.len() as u32).filter(|&i| self.fate[i as usize] == Fate::Render).collect()
    }

    /// Writes the farm's results for `pixels` into the frame.
    pub fn fill(&mut self, pixels: &[u32], rendered: &PixelResults) -> Result<(), ShareError> {
        if rendered.len() != pixels.len() {
            return Err(ShareError::RenderedSize { len: rendered.len(), pixels: pixels.len() });
        }
        for (k, &index) in pixels.iter().enumerate() {
            let i = index as usize;
            if i >= self.fate.len() {
                return Err(ShareError::PixelOutside { index, width: self.width, height: self.height });
            }
            self.frame.color[i] = rendered.color[k];
            self.frame.opacity[i] = rendered.opacity[k];
            self.frame.depth[i] = rendered.depth[k];
        }
        Ok(())
    }

    pub fn counts(&self) -> FateCounts {
        let mut counts = FateCounts::default();
        for fate in &self.fate {
            match fate {
                Fate::Reused => counts.reused += 1,
                Fate::OutsideBounds => counts.outside_bounds += 1,
                Fate::SeenEmpty => counts.seen_empty += 1,
                Fate::Render => counts.render += 1,
            }
        }
        counts
    }
}

/// Assembles `target`'s frame from `sources` (see the crate documentation); `bounds` holds all
/// of the object's matter. Errors for a source frame of the wrong size or invalid settings;
/// non-finite depths or colours in a source are skipped, never reused.
pub fn reproject(
    target: &Camera,
    bounds: &Bounds,
    sources: &[Source<'_>],
    settings: &Settings,
) -> Result<Reprojection, ShareError> {
    settings.validate()?;
    for (index, source) in sources.iter().enumerate() {
        let (width, height) = (source.camera.width(), source.camera.height());
        let expected = width as usize * height as usize;
        let len = source.frame.len();
        let consistent = source.frame.color.len() == len && source.frame.depth.len() == len;
        if len != expected || !consistent {
            return Err(ShareError::SourceSize { index, len, width, height, expected });
        }
    }
    let (width, height) = (target.width(), target.height());
    let (w, h) = (width as usize, height as usize);
    let candidates = close_cracks(&splat_depths(target, sources, settings), w, h);
    let cos_max = settings.max_angle_deg.to_radians().cos();
    let distances: Vec<Vec<u16>> = sources.par_iter().map(|source| empty_distances(source, settings)).collect();
    // Rows in parallel, written in place: each pixel's fate depends on the sources and its
    // own depth only.
    let mut frame = PixelResults::with_len(w * h);
    let mut fate = vec![Fate::Render; w * h];
    let row_len = w.max(1);
    frame
        .color
        .par_chunks_mut(row_len)
        .zip(frame.opacity.par_chunks_mut(row_len))
        .zip(frame.depth.par_chunks_mut(row_len))
        .zip(fate.par_chunks_mut(row_len))
        .enumerate()
        .for_each(|(y, (((colors, opacities), depths), fates))| {
            for x in 0..fates.len() {
                let t = y * w + x;
                let ray = target.pixel_center_ray(x as u32, y as u32);
                let Some((t0, t1)) = ray_box(&ray, bounds) else {
                    fates[x] = Fate::OutsideBounds;
                    continue;
                };
                if candidates[t].is_finite() {
                    let point = ray.at(candidates[t] / target.depth_per_distance(&ray));
                    // Without a reusable sample, a solid source point that lands in this
                    // pixel says its ray passes matter: not empty (and the walk below, the
                    // costliest check, would only find that out), so it is rendered.
                    if let Some(sample) = best_sample(target, point, sources, settings, cos_max) {
                        fates[x] = Fate::Reused;
                        (colors[x], opacities[x], depths[x]) =
                            (sample.color, sample.opacity, target.view_depth(sample.point));
                    }
                } else if seen_empty(&ray, t0, t1, sources, &distances, settings) {
                    fates[x] = Fate::SeenEmpty;
                }
            }
        });
    widen_holes(&mut fate, &mut frame, w, h, settings.edge_band);
    Ok(Reprojection { width, height, frame, fate })
}

/// The world point a pixel's depth names: along the ray through continuous pixel coordinates
/// `(x, y)`, at view depth `depth`.
fn point_at_depth(camera: &Camera, x: f32, y: f32, depth: f32) -> Vec3 {
    let ray = camera.ray(x, y);
    ray.at(depth / camera.depth_per_distance(&ray))
}

fn is_solid(frame: &PixelResults, k: usize, settings: &Settings) -> bool {
    frame.opacity[k] >= settings.opaque && frame.depth[k] > 0.0 && frame.depth[k].is_finite()
}

/// Step 1: each solid source pixel's point splatted into the target's pixel grid (view depth,
/// the nearest wins); infinity where nothing landed.
fn splat_depths(target: &Camera, sources: &[Source<'_>], settings: &Settings) -> Vec<f32> {
    let (w, h) = (target.width() as usize, target.height() as usize);
    let mut depth = vec![f32::INFINITY; w * h];
    for source in sources {
        let sw = source.camera.width() as usize;
        for k in 0..source.frame.len() {
            if !is_solid(source.frame, k, settings) {
                continue;
            }
            let (x, y) = ((k % sw) as f32 + 0.5, (k / sw) as f32 + 0.5);
            let point = point_at_depth(source.camera, x, y, source.frame.depth[k]);
            let Some(pixel) = target.project(point) else { continue };
            if !(pixel.x >= 0.0 && pixel.y >= 0.0 && pixel.x < w as f32 && pixel.y < h as f32) {
                continue;
            }
            let t = pixel.y as usize * w + pixel.x as usize;
            depth[t] = depth[t].min(target.view_depth(point));
        }
    }
    depth
}

/// Closes holes one pixel wide (splats spread apart by magnification): an empty pixel with
/// splats on both sides along a row, a column or a diagonal takes the nearer such pair's mean.
/// Whether the guess holds is checked afterwards, like every other depth.
fn close_cracks(depth: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut closed = depth.to_vec();
    let pairs: [((isize, isize), (isize, isize)); 4] =
        [((-1, 0), (1, 0)), ((0, -1), (0, 1)), ((-1, -1), (1, 1)), ((1, -1), (-1, 1))];
    let at = |i: usize, j: usize, (di, dj): (isize, isize)| {
        let (x, y) = (i as isize + di, j as isize + dj);
        match x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
            true => depth[y as usize * w + x as usize],
            false => f32::INFINITY,
        }
    };
    for j in 0..h {
        for i in 0..w {
            let k = j * w + i;
            if depth[k].is_finite() {
                continue;
            }
            if i >= 1 && j >= 1 && i + 1 < w && j + 1 < h {
                // Inside: the four pairs' neighbours indexed directly.
                let (up, down) = (k - w, k + w);
                for (a, b) in [(k - 1, k + 1), (up, down), (up - 1, down + 1), (up + 1, down - 1)] {
                    let (da, db) = (depth[a], depth[b]);
                    if da.is_finite() && db.is_finite() {
                        closed[k] = closed[k].min(0.5 * (da + db));
                    }
                }
                continue;
            }
            for &(a, b) in &pairs {
                let (da, db) = (at(i, j, a), at(i, j, b));
                if da.is_finite() && db.is_finite() {
                    closed[k] = closed[k].min(0.5 * (da + db));
                }
            }
        }
    }
    closed
}

/// A reusable colour for a target point, and the (refined) point it was read at.
struct Sample {
    color: [f32; 3],
    opacity: f32,
    point: Vec3,
    cos_angle: f32,
}

/// Bilinear weights below this are taps the point does not reach (it sits on their row or
/// column): they are left out, so that a point exactly on a pixel centre needs only that pixel.
const NEGLIGIBLE_WEIGHT: f32 = 1e-3;

/// The pixels around continuous coordinates `pixel` that bilinear interpolation reads, with
/// their weights (at most four; those under [`NEGLIGIBLE_WEIGHT`] left out, the rest summing
/// to one). `None` when one of them is outside the `w` x `h` image.
fn bilinear_taps(pixel: Vec2, w: usize, h: usize) -> Option<Taps> {
    let (fx, fy) = (pixel.x - 0.5, pixel.y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    if !(x0 >= -1.0 && y0 >= -1.0 && x0 < w as f32 && y0 < h as f32) {
        return None;
    }
    let (ax, ay) = (fx - x0, fy - y0);
    let mut taps = Taps { items: [(0, 0.0); 4], len: 0 };
    let mut total = 0.0;
    for (dx, dy, weight) in
        [(0, 0, (1.0 - ax) * (1.0 - ay)), (1, 0, ax * (1.0 - ay)), (0, 1, (1.0 - ax) * ay), (1, 1, ax * ay)]
    {
        if weight < NEGLIGIBLE_WEIGHT {
            continue;
        }
        let (x, y) = (x0 as isize + dx, y0 as isize + dy);
        if x < 0 || y < 0 || x as usize >= w || y as usize >= h {
            return None;
        }
        taps.items[taps.len] = (y as usize * w + x as usize, weight);
        taps.len += 1;
        total += weight;
    }
    for tap in &mut taps.items[..taps.len] {
        tap.1 /= total;
    }
    Some(taps)
}

/// Up to four bilinear taps: pixel index and weight.
struct Taps {
    items: [(usize, f32); 4],
    len: usize,
}

impl Taps {
    fn iter(&self) -> std::slice::Iter<'_, (usize, f32)> {
        self.items[..self.len].iter()
    }
}

/// Step 2: the best source's colour for `point` (seen by the target), or `None` when no source
/// shows that same surface, solid, without an edge, within the angle.
fn best_sample(
    target: &Camera,
    point: Vec3,
    sources: &[Source<'_>],
    settings: &Settings,
    cos_max: f32,
) -> Option<Sample> {
    let to_target = (point - target.position()).normalize();
    let mut best: Option<Sample> = None;
    for source in sources {
        let camera = source.camera;
        let Some(pixel) = camera.project(point) else { continue };
        let (sw, sh) = (camera.width() as usize, camera.height() as usize);
        let Some(taps) = bilinear_taps(pixel, sw, sh) else { continue };
        if !taps.iter().all(|&(k, _)| is_solid(source.frame, k, settings)) {
            continue;
        }
        let expected = camera.view_depth(point);
        // Depth tolerance in world units: pixel footprints at this depth.
        let tolerance = settings.depth_tolerance_px * expected / camera.intrinsics().0;
        let (low_depth, high_depth) = taps.iter().fold((f32::INFINITY, 0.0f32), |(l, hi), &(k, _)| {
            (l.min(source.frame.depth[k]), hi.max(source.frame.depth[k]))
        });
        if high_depth - low_depth > tolerance {
            continue;
        }
        let seen: f32 = taps.iter().map(|&(k, w)| w * source.frame.depth[k]).sum();
        if !((seen - expected).abs() <= tolerance) {
            continue;
        }
        let refined = point_at_depth(camera, pixel.x, pixel.y, seen);
        let to_source = (refined - camera.position()).normalize();
        let cos_angle = to_source.dot(to_target);
        if !(cos_angle >= cos_max) || best.as_ref().is_some_and(|b| b.cos_angle >= cos_angle) {
            continue;
        }
        let mut color = [0.0f32; 3];
        let mut opacity = 0.0;
        let (mut low, mut high) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for &(k, w) in taps.iter() {
            let c = source.frame.color[k];
            for channel in 0..3 {
                color[channel] += w * c[channel];
                low[channel] = low[channel].min(c[channel]);
                high[channel] = high[channel].max(c[channel]);
            }
            opacity += w * source.frame.opacity[k];
        }
        if (0..3).any(|c| !(high[c] - low[c] <= settings.max_contrast)) {
            continue;
        }
        if settings.filter == Filter::CatmullRom
            && let Some(sharper) = catmull_rom(source, pixel, (low_depth, high_depth), tolerance, settings)
        {
            color = sharper;
        }
        // Within the taps' range (weights summing to 1 + rounding once gave opacity
        // 1.0000001, which a result's validation refuses).
        color = std::array::from_fn(|c| color[c].max(low[c]).min(high[c]));
        let opacity = opacity.clamp(0.0, 1.0);
        if color.iter().all(|c| c.is_finite()) && opacity.is_finite() {
            best = Some(Sample { color, opacity, point: refined, cos_angle });
        }
    }
    best
}

/// Catmull-Rom weights of the four taps around a fractional offset `a` in `[0, 1)`.
fn catmull_rom_weights(a: f32) -> [f32; 4] {
    let (a2, a3) = (a * a, a * a * a);
    [0.5 * (-a + 2.0 * a2 - a3), 0.5 * (2.0 - 5.0 * a2 + 3.0 * a3), 0.5 * (a + 4.0 * a2 - 3.0 * a3), 0.5 * (a3 - a2)]
}

/// The Catmull-Rom colour of a source at continuous pixel coordinates, when the sixteen pixels
/// around are all inside the image, solid, and within `tolerance` of the central four's depth
/// range `(low, high)` (one surface); else `None`.
fn catmull_rom(
    source: &Source<'_>,
    pixel: Vec2,
    (low, high): (f32, f32),
    tolerance: f32,
    settings: &Settings,
) -> Option<[f32; 3]> {
    let (w, h) = (source.camera.width() as isize, source.camera.height() as isize);
    let (fx, fy) = (pixel.x - 0.5, pixel.y - 0.5);
    let (x0, y0) = (fx.floor() as isize, fy.floor() as isize);
    if x0 < 1 || y0 < 1 || x0 + 2 >= w || y0 + 2 >= h {
        return None;
    }
    let (wx, wy) = (catmull_rom_weights(fx - fx.floor()), catmull_rom_weights(fy - fy.floor()));
    let mut color = [0.0f32; 3];
    for (dy, weight_y) in wy.iter().enumerate() {
        for (dx, weight_x) in wx.iter().enumerate() {
            let k = ((y0 + dy as isize - 1) * w + x0 + dx as isize - 1) as usize;
            let depth = source.frame.depth[k];
            if !is_solid(source.frame, k, settings) || depth < low - tolerance || depth > high + tolerance {
                return None;
            }
            for (sum, v) in color.iter_mut().zip(source.frame.color[k]) {
                *sum += weight_x * weight_y * v;
            }
        }
    }
    Some(color)
}

/// Whether a source pixel shows empty space (at most `settings.empty` opaque; NaN is not).
fn is_empty(frame: &PixelResults, k: usize, settings: &Settings) -> bool {
    frame.opacity[k] <= settings.empty
}

/// Per source pixel, the chessboard distance (in pixels) to the nearest pixel that is not
/// empty, counting the outside of the image as not empty: 0 on matter, 1 next to it or on the
/// border. Two passes (Rosenfeld and Pfaltz).
fn empty_distances(source: &Source<'_>, settings: &Settings) -> Vec<u16> {
    let (w, h) = (source.camera.width() as usize, source.camera.height() as usize);
    let mut distance = vec![0u16; w * h];
    let at = |d: &[u16], x: isize, y: isize| match x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
        true => d[y as usize * w + x as usize],
        false => 0,
    };
    // Interior pixels (all eight neighbours inside) index directly; the border through `at`.
    let inner = |x: usize, y: usize| x >= 1 && y >= 1 && x + 1 < w && y + 1 < h;
    for y in 0..h {
        for x in 0..w {
            let k = y * w + x;
            if is_empty(source.frame, k, settings) {
                let near = if inner(x, y) {
                    let above = k - w;
                    distance[k - 1].min(distance[above - 1]).min(distance[above]).min(distance[above + 1])
                } else {
                    let (x, y) = (x as isize, y as isize);
                    let near = at(&distance, x - 1, y).min(at(&distance, x - 1, y - 1));
                    near.min(at(&distance, x, y - 1)).min(at(&distance, x + 1, y - 1))
                };
                distance[k] = near.saturating_add(1);
            }
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let k = y * w + x;
            if distance[k] == 0 {
                continue;
            }
            let near = if inner(x, y) {
                let below = k + w;
                distance[k + 1].min(distance[below + 1]).min(distance[below]).min(distance[below - 1])
            } else {
                let (x, y) = (x as isize, y as isize);
                let near = at(&distance, x + 1, y).min(at(&distance, x + 1, y + 1));
                near.min(at(&distance, x, y + 1)).min(at(&distance, x - 1, y + 1))
            };
            distance[k] = distance[k].min(near.saturating_add(1));
        }
    }
    distance
}

/// Whether every bilinear tap around continuous pixel coordinates is empty.
fn taps_empty(source: &Source<'_>, pixel: Vec2, settings: &Settings) -> bool {
    let (sw, sh) = (source.camera.width() as usize, source.camera.height() as usize);
    bilinear_taps(pixel, sw, sh).is_some_and(|taps| taps.iter().all(|&(k, _)| is_empty(source.frame, k, settings)))
}

/// Step 3: whether one source saw empty space all along `ray` between `t0` and `t1`. The
/// stretch projects onto the segment between its ends' projections (both in front of the
/// source: the stretch is then wholly in front), which is walked in the source's image at
/// half-pixel steps, or in one stride across pixels that `distances` shows to be far from any
/// matter (points within `d - 3` pixels of a pixel at distance `d` have only empty taps).
fn seen_empty(
    ray: &Ray,
    t0: f32,
    t1: f32,
    sources: &[Source<'_>],
    distances: &[Vec<u16>],
    settings: &Settings,
) -> bool {
    let (a, b) = (ray.at(t0), ray.at(t1));
    sources.iter().zip(distances).any(|(source, distance)| {
        let (Some(start), Some(end)) = (source.camera.project(a), source.camera.project(b)) else { return false };
        let length = (end - start).length();
        if !length.is_finite() {
            return false;
        }
        let (w, h) = (source.camera.width() as f32, source.camera.height() as f32);
        let mut travelled = 0.0f32;
        loop {
            let along = travelled.min(length);
            let pixel = if length > 0.0 { start + (end - start) * (along / length) } else { start };
            if !(pixel.x >= 0.0 && pixel.y >= 0.0 && pixel.x < w && pixel.y < h) {
                return false;
            }
            let d = distance[pixel.y as usize * w as usize + pixel.x as usize];
            if d >= 4 {
                travelled += f32::from(d - 3);
            } else if taps_empty(source, pixel, settings) {
                travelled += 0.5;
            } else {
                return false;
            }
            if along >= length {
                return true;
            }
        }
    })
}

/// The stretch `(t0, t1)` of `ray` inside `bounds` (slab test), `None` if it misses or the
/// box is behind the origin.
fn ray_box(ray: &Ray, bounds: &Bounds) -> Option<(f32, f32)> {
    let inverse = ray.direction.recip();
    let ta = (bounds.min - ray.origin) * inverse;
    let tb = (bounds.max - ray.origin) * inverse;
    // NaN (0 * inf on a slab's plane) must not decide: min/max ignore it.
    let t0 = ta.min(tb).max_element().max(0.0);
    let t1 = ta.max(tb).min_element();
    (t0 <= t1 && t1.is_finite()).then_some((t0, t1))
}

/// Marks reused pixels within `band` steps of a pixel to render as to render (and clears them).
fn widen_holes(fate: &mut [Fate], frame: &mut PixelResults, w: usize, h: usize, band: u32) {
    for _ in 0..band {
        let before = fate.to_vec();
        for j in 0..h {
            for i in 0..w {
                let t = j * w + i;
                if before[t] != Fate::Reused {
                    continue;
                }
                let near_hole = [(0isize, -1isize), (0, 1), (-1, 0), (1, 0)].iter().any(|&(di, dj)| {
                    let (x, y) = (i as isize + di, j as isize + dj);
                    x >= 0
                        && y >= 0
                        && (x as usize) < w
                        && (y as usize) < h
                        && before[y as usize * w + x as usize] == Fate::Render
                });
                if near_hole {
                    fate[t] = Fate::Render;
                    frame.color[t] = [0.0; 3];
                    frame.opacity[t] = 0.0;
                    frame.depth[t] = 0.0;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
