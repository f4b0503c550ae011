//! Derived views (issue 16; NEPHELE's shared rays between adjacent views, section 5): a view
//! of the same asset taken from a batch's freshly rendered pixels by depth-based
//! reprojection ([`nephele_share::reproject`]), with only the pixels that reprojection
//! cannot vouch for rendered by the kernel.
//!
//! Why on the worker and not in the composer: the worker holds the source pixels the moment
//! they are rendered and the kernel that renders the leftovers, so a derived view costs no
//! second round trip (composer → master → worker) and no extra frame of latency, and the
//! reprojection (0.4-0.8 of a full render of the view, leftovers included, on the first
//! start's objects: `nephele bench share`, BENCHMARKS.md 2026-12-05i) spreads over the farm
//! instead of loading the one composer that also encodes every stream.
//!
//! The source is the batch's bounding box of pixels: the master sends only batches that hold
//! every covered pixel of the rows they span, so a pixel of that box the batch lacks is
//! empty. Target pixels whose sources fall outside the box are simply rendered.

use nephele_geometry::camera::{Camera, CameraError};
use nephele_geometry::pixels::PixelResults;
use nephele_kernels::kernel::{KernelError, KernelStats, RayKernel};
use nephele_share::{Fate, ShareError, Source};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum DeriveError {
    #[error("reprojection: {0}")]
    Share(#[from] ShareError),
    #[error("cropping a camera: {0}")]
    Camera(#[from] CameraError),
    #[error("rendering the pixels reprojection left: {0}")]
    Kernel(#[from] KernelError),
    #[error("{results} results for {pixels} pixels")]
    Mismatch { results: usize, pixels: usize },
}

/// A derived view's pixels, in the order asked, and what it took.
#[derive(Debug, Clone, PartialEq)]
pub struct Derived {
    pub results: PixelResults,
    /// The kernel's work on the pixels left to render.
    pub stats: KernelStats,
    pub reused: usize,
    /// Pixels found empty without rendering (their ray misses the bounds, or crosses them
    /// only where the source saw empty space).
    pub empty: usize,
    pub rendered: usize,
}

/// The smallest `(x0, y0, x1, y1)` (exclusive ends) holding every index of `pixels` in a
/// `width`-wide image; `None` for no pixels.
fn pixel_box(pixels: &[u32], width: u32) -> Option<(u32, u32, u32, u32)> {
    let width = width.max(1);
    let mut bounds: Option<(u32, u32, u32, u32)> = None;
    for &p in pixels {
        let (x, y) = (p % width, p / width);
        bounds = Some(match bounds {
            None => (x, y, x + 1, y + 1),
            Some((x0, y0, x1, y1)) => (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1)),
        });
    }
    bounds
}

/// What a pixel of the source's bounding box that the source does not hold stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Absent {
    /// Empty space: the master promises that a batch holds every covered pixel of the rows
    /// it spans ([`nephele_proto::DerivedView`]).
    Empty,
    /// Not known (a previous render, whose batch may have held part of its rows): such a
    /// pixel is neither reused nor taken for empty space, so whatever lands on it is
    /// rendered.
    Unknown,
}

/// Renders `target_pixels` of `target` from `source_results` (the kernel's results for
/// `source_pixels` of `source`, which must hold every non-empty pixel of their bounding box)
/// plus what the kernel renders of the pixels reprojection leaves. Runs on the caller's rayon
/// pool.
pub fn derive_view(
    kernel: &dyn RayKernel,
    source: &Camera,
    source_pixels: &[u32],
    source_results: &PixelResults,
    target: &Camera,
    target_pixels: &[u32],
    settings: &nephele_share::Settings,
) -> Result<Derived, DeriveError> {
    derive_view_with(kernel, (source, source_pixels, source_results), Absent::Empty, target, target_pixels, settings)
}

/// [`derive_view`] with the source's missing pixels standing for `absent`.
pub fn derive_view_with(
    kernel: &dyn RayKernel,
    (source, source_pixels, source_results): (&Camera, &[u32], &PixelResults),
    absent: Absent,
    target: &Camera,
    target_pixels: &[u32],
    settings: &nephele_share::Settings,
) -> Result<Derived, DeriveError> {
    if source_results.len() != source_pixels.len() {
        return Err(DeriveError::Mismatch { results: source_results.len(), pixels: source_pixels.len() });
    }
    let (Some(source_box), Some(target_box)) =
        (pixel_box(source_pixels, source.width()), pixel_box(target_pixels, target.width()))
    else {
        // Nothing rendered to reuse, or nothing asked: render what is asked.
        let (results, stats) = kernel.render_pixels(target, target_pixels)?;
        let rendered = target_pixels.len();
        return Ok(Derived { results, stats, reused: 0, empty: 0, rendered });
    };
    // The source: its box of pixels, empty where the batch holds none.
    let (sx0, sy0, sx1, sy1) = source_box;
    let source_crop = source.crop(sx0, sy0, sx1 - sx0, sy1 - sy0)?;
    let box_width = (sx1 - sx0) as usize;
    let mut frame = PixelResults::with_len(box_width * (sy1 - sy0) as usize);
    if absent == Absent::Unknown {
        // Between "empty" and "solid": treated like a silhouette pixel (never reused, never
        // empty space), so a target pixel that reads it is rendered.
        frame.opacity.fill(0.5 * (settings.empty + settings.opaque));
    }
    for (k, &p) in source_pixels.iter().enumerate() {
        let (x, y) = (p % source.width(), p / source.width());
        let local = (y - sy0) as usize * box_width + (x - sx0) as usize;
        frame.color[local] = source_results.color[k];
        frame.opacity[local] = source_results.opacity[k];
        frame.depth[local] = source_results.depth[k];
    }
    let (tx0, ty0, tx1, ty1) = target_box;
    let target_crop = target.crop(tx0, ty0, tx1 - tx0, ty1 - ty0)?;
    let sources = [Source { camera: &source_crop, frame: &frame }];
    let reprojection = nephele_share::reproject(&target_crop, &kernel.bounds(), &sources, settings)?;
    let target_width = (tx1 - tx0) as usize;
    let local = |p: u32| (p / target.width() - ty0) as usize * target_width + (p % target.width() - tx0) as usize;
    let to_render: Vec<u32> =
        target_pixels.iter().copied().filter(|&p| reprojection.fate[local(p)] == Fate::Render).collect();
    let (rendered, stats) = match to_render.is_empty() {
        true => (PixelResults::with_len(0), KernelStats::default()),
        false => kernel.render_pixels(target, &to_render)?,
    };
    if rendered.len() != to_render.len() {
        return Err(DeriveError::Mismatch { results: rendered.len(), pixels: to_render.len() });
    }
    let mut results = PixelResults::with_len(target_pixels.len());
    let (mut next, mut reused, mut empty) = (0, 0, 0);
    for (k, &p) in target_pixels.iter().enumerate() {
        let l = local(p);
        match reprojection.fate[l] {
            Fate::Reused => {
                results.color[k] = reprojection.frame.color[l];
                results.opacity[k] = reprojection.frame.opacity[l];
                results.depth[k] = reprojection.frame.depth[l];
                reused += 1;
            }
            Fate::OutsideBounds | Fate::SeenEmpty => empty += 1,
            Fate::Render => {
                results.color[k] = rendered.color[next];
                results.opacity[k] = rendered.opacity[next];
                results.depth[k] = rendered.depth[next];
                next += 1;
            }
        }
    }
    Ok(Derived { results, stats, reused, empty, rendered: to_render.len() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use nephele_geometry::camera::{Ray, stereo_pair};
    use nephele_geometry::{Bounds, all_pixels, validate_pixels};

    /// A sphere of radius 0.5 at the origin, coloured by its normal (smooth, view
    /// independent): depth and colour known exactly, so reuse can be checked against it.
    #[derive(Debug)]
    struct Sphere;

    fn hit(ray: &Ray) -> Option<f32> {
        let b = ray.origin.dot(ray.direction);
        let c = ray.origin.length_squared() - 0.25;
        let disc = b * b - c;
        (disc >= 0.0).then(|| -b - disc.sqrt()).filter(|&t| t > 0.0)
    }

    impl RayKernel for Sphere {
        fn kind(&self) -> &'static str {
            "sphere"
        }

        fn bounds(&self) -> Bounds {
            Bounds { min: Vec3::splat(-0.5), max: Vec3::splat(0.5) }
        }

        fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
            validate_pixels(camera, pixels)?;
            let mut out = PixelResults::with_len(pixels.len());
            for (k, &p) in pixels.iter().enumerate() {
                let ray = camera.pixel_center_ray(p % camera.width(), p / camera.width());
                if let Some(t) = hit(&ray) {
                    let n = ray.at(t).normalize();
                    out.color[k] = (0.5 * (n + Vec3::ONE)).to_array();
                    out.opacity[k] = 1.0;
                    out.depth[k] = t * camera.depth_per_distance(&ray);
                }
            }
            let stats = KernelStats { rays: pixels.len() as u64, ..KernelStats::default() };
            Ok((out, stats))
        }
    }

    fn eyes() -> [Camera; 2] {
        let centre = Camera::look_at(96, 72, 0.7, Vec3::new(0.3, -2.5, 0.4), Vec3::ZERO, Vec3::Z).expect("camera");
        stereo_pair(&centre, 0.064).expect("eyes")
    }

    /// Rows `y0..y1` of a `width`-wide image.
    fn rows(width: u32, y0: u32, y1: u32) -> Vec<u32> {
        (y0 * width..y1 * width).collect()
    }

    #[test]
    fn the_right_eye_from_the_left_eye_matches_its_own_render() {
        let [left, right] = eyes();
        let all = all_pixels(&right);
        let (source, _) = Sphere.render_pixels(&left, &all).expect("left");
        let (truth, _) = Sphere.render_pixels(&right, &all).expect("right");
        let derived = derive_view(&Sphere, &left, &all, &source, &right, &all, &nephele_share::Settings::default())
            .expect("derived");
        assert_eq!(derived.reused + derived.empty + derived.rendered, all.len());
        assert_eq!(derived.stats.rays, derived.rendered as u64);
        // Most of the eye comes from the other: only a sliver of disocclusion and the
        // silhouette (partly covered source pixels are never reused) is rendered.
        let covered = truth.opacity.iter().filter(|&&a| a > 0.0).count();
        assert!(derived.reused > covered * 3 / 4, "{derived:?}");
        for k in 0..all.len() {
            let (a, b) = (derived.results.opacity[k], truth.opacity[k]);
            assert_eq!(a, b, "pixel {k}: coverage");
            if b > 0.0 {
                let error = (0..3).map(|c| (derived.results.color[k][c] - truth.color[k][c]).abs()).fold(0.0, f32::max);
                assert!(error < 0.02, "pixel {k}: colour off by {error}");
                // Depth read between source pixels: within a pixel's footprint at that depth.
                let footprint = truth.depth[k] / right.intrinsics().0;
                let off = (derived.results.depth[k] - truth.depth[k]).abs();
                assert!(off < footprint, "pixel {k}: depth off by {off}, footprint {footprint}");
            }
        }
    }

    #[test]
    fn a_band_of_rows_reuses_within_it_and_renders_what_lies_beyond() {
        let [left, right] = eyes();
        let width = left.width();
        // The batch: rows 20..40 of the left eye. The derived view asks rows 10..50 of the
        // right: rows outside the band have no source and must be rendered, exactly.
        let band = rows(width, 20, 40);
        let asked = rows(width, 10, 50);
        let (source, _) = Sphere.render_pixels(&left, &band).expect("band");
        let (truth, _) = Sphere.render_pixels(&right, &asked).expect("truth");
        let derived = derive_view(&Sphere, &left, &band, &source, &right, &asked, &nephele_share::Settings::default())
            .expect("derived");
        assert!(derived.reused > 0);
        for (k, &p) in asked.iter().enumerate() {
            let y = p / width;
            assert_eq!(derived.results.opacity[k], truth.opacity[k], "pixel {p}");
            if !(20..40).contains(&y) {
                assert_eq!(derived.results.color[k], truth.color[k], "row {y} has no source: rendered");
            }
        }
    }

    #[test]
    fn pixels_a_source_lacks_are_rendered_when_unknown_and_lost_when_taken_for_empty() {
        let [left, right] = eyes();
        let width = left.width();
        // The source holds rows 20..40 of the left eye but not columns 30..60 of them: the
        // sphere's middle is missing (a batch holding part of its rows).
        let partial: Vec<u32> = rows(width, 20, 40).into_iter().filter(|p| !(30..60).contains(&(p % width))).collect();
        let asked = rows(width, 20, 40);
        let (source, _) = Sphere.render_pixels(&left, &partial).expect("source");
        let (truth, _) = Sphere.render_pixels(&right, &asked).expect("truth");
        let settings = nephele_share::Settings::default();
        let derive = |absent| {
            derive_view_with(&Sphere, (&left, &partial, &source), absent, &right, &asked, &settings).expect("derived")
        };
        let unknown = derive(Absent::Unknown);
        assert!(unknown.reused > 0);
        for (k, p) in asked.iter().enumerate() {
            assert_eq!(unknown.results.opacity[k], truth.opacity[k], "pixel {p}: coverage");
        }
        // Taken for empty space (the promise a derived view's source makes), the gap would
        // punch a hole into the sphere: why a previous render's gaps are unknown.
        let empty = derive(Absent::Empty);
        let lost = (0..asked.len()).filter(|&k| truth.opacity[k] > 0.0 && empty.results.opacity[k] == 0.0).count();
        assert!(lost > 0, "the gap is not in view: the test proves nothing");
    }

    #[test]
    fn no_source_pixels_or_a_mismatch_are_handled() {
        let [left, right] = eyes();
        let asked = rows(right.width(), 30, 31);
        let settings = nephele_share::Settings::default();
        let empty = PixelResults::with_len(0);
        let derived = derive_view(&Sphere, &left, &[], &empty, &right, &asked, &settings).expect("renders");
        assert_eq!(derived.rendered, asked.len());
        assert_eq!(derived.results, Sphere.render_pixels(&right, &asked).expect("truth").0);
        let err = derive_view(&Sphere, &left, &asked, &empty, &right, &asked, &settings).expect_err("mismatch");
        assert!(matches!(err, DeriveError::Mismatch { .. }));
        assert_eq!(pixel_box(&[5, 96 + 2, 3 * 96 + 90], 96), Some((2, 0, 91, 4)));
    }
}
