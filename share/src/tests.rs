//! Reprojection against an analytic scene whose every view is known exactly: a card floating
//! in front of a wall, both textured smoothly in world space.

use super::*;
use glam::Vec3;
use nephele_geometry::all_pixels;
use proptest::prelude::*;

/// The card (plane y = CARD_Y, |x|, |z| <= CARD_HALF) in front of the wall (plane y = WALL_Y,
/// |x|, |z| <= WALL_HALF); cameras look along +y from y < 0.
const CARD_Y: f32 = -0.5;
const CARD_HALF: f32 = 0.3;
const WALL_Y: f32 = 1.0;
const WALL_HALF: f32 = 1.5;

fn bounds() -> Bounds {
    Bounds {
        min: Vec3::new(-WALL_HALF, CARD_Y - 0.05, -WALL_HALF),
        max: Vec3::new(WALL_HALF, WALL_Y + 0.05, WALL_HALF),
    }
}

/// Where a ray first meets matter and that point's colour; `None` for a miss.
fn trace(ray: &Ray) -> Option<(Vec3, [f32; 3])> {
    let hit = |plane_y: f32, half: f32| {
        let t = (plane_y - ray.origin.y) / ray.direction.y;
        let p = ray.at(t);
        (t > 0.0 && p.x.abs() <= half && p.z.abs() <= half).then_some((t, p))
    };
    if let Some((_, p)) = hit(CARD_Y, CARD_HALF) {
        return Some((p, [0.8, 0.5 + 0.3 * p.x, 0.5 + 0.3 * p.z]));
    }
    hit(WALL_Y, WALL_HALF).map(|(_, p)| (p, [0.5 + 0.2 * p.x, 0.3, 0.5 + 0.2 * p.z]))
}

/// Whether the segment from `eye` to a wall point crosses the card (the point is hidden).
fn hidden_from(eye: Vec3, wall_point: Vec3) -> bool {
    let t = (CARD_Y - eye.y) / (wall_point.y - eye.y);
    let p = eye + t * (wall_point - eye);
    t > 0.0 && t < 1.0 && p.x.abs() <= CARD_HALF && p.z.abs() <= CARD_HALF
}

fn render(camera: &Camera) -> PixelResults {
    let pixels = all_pixels(camera);
    let mut out = PixelResults::with_len(pixels.len());
    for (k, &p) in pixels.iter().enumerate() {
        let ray = camera.pixel_center_ray(p % camera.width(), p / camera.width());
        if let Some((point, color)) = trace(&ray) {
            out.color[k] = color;
            out.opacity[k] = 1.0;
            out.depth[k] = camera.view_depth(point);
        }
    }
    out
}

/// A camera on the circle of radius 4 around the z axis, `degrees` from the -y axis, looking
/// at the origin.
fn orbit(degrees: f32, size: u32) -> Camera {
    let a = degrees.to_radians();
    let eye = Vec3::new(4.0 * a.sin(), -4.0 * a.cos(), 0.0);
    Camera::look_at(size, size, 0.7, eye, Vec3::ZERO, Vec3::Z).expect("valid camera")
}

#[test]
fn a_view_reprojected_onto_itself_is_reused_whole_and_exact() {
    let camera = orbit(0.0, 64);
    let frame = render(&camera);
    let shared = reproject(&camera, &bounds(), &[Source { camera: &camera, frame: &frame }], &Settings::default())
        .expect("reprojects");
    let counts = shared.counts();
    let interior = (0..frame.len()).filter(|&k| shared.fate[k] == Fate::Reused).count();
    assert!(interior > frame.len() / 2, "{counts:?}");
    for k in 0..frame.len() {
        if shared.fate[k] == Fate::Reused {
            for c in 0..3 {
                assert!((shared.frame.color[k][c] - frame.color[k][c]).abs() < 1e-4, "pixel {k}");
            }
            assert!((shared.frame.depth[k] - frame.depth[k]).abs() < 1e-3 * frame.depth[k]);
        }
    }
    // Only the edges between card and wall, and the image border, are left to render: the
    // card's and the wall's outlines (about 60 and 210 pixels) and the border.
    assert!(counts.render < 600, "{counts:?}");
}

#[test]
fn reprojection_is_exact_where_visible_and_marks_disocclusions() {
    let size = 96;
    let (source_camera, target) = (orbit(0.0, size), orbit(5.0, size));
    let source_frame = render(&source_camera);
    let truth = render(&target);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    let shared = reproject(&target, &bounds(), &sources, &Settings::default()).expect("reprojects");
    // What the target truly sees at each pixel: 0 nothing, 1 the card, 2 the wall visible from
    // the source, 3 the wall hidden from the source (disoccluded).
    let seen: Vec<u8> = (0..truth.len())
        .map(|k| match trace(&target.pixel_center_ray(k as u32 % size, k as u32 / size)) {
            None => 0,
            Some((point, _)) if point.y < 0.0 => 1,
            Some((point, _)) if hidden_from(source_camera.position(), point) => 3,
            Some(_) => 2,
        })
        .collect();
    let (mut disoccluded, mut interior) = (0, 0);
    for k in 0..truth.len() {
        match seen[k] {
            0 => assert_ne!(shared.fate[k], Fate::Reused, "pixel {k} sees nothing but was reused"),
            3 => {
                disoccluded += 1;
                assert_eq!(shared.fate[k], Fate::Render, "disoccluded pixel {k} was not marked");
            }
            _ => {}
        }
        if shared.fate[k] == Fate::Reused {
            // Exact up to bilinear interpolation of a texture linear in world space.
            for c in 0..3 {
                let error = (shared.frame.color[k][c] - truth.color[k][c]).abs();
                assert!(error < 2e-3, "pixel {k} channel {c}: error {error}");
            }
            let depth_error = (shared.frame.depth[k] - truth.depth[k]).abs();
            assert!(depth_error < 1e-3 * truth.depth[k], "pixel {k}: depth error {depth_error}");
        }
        // Two pixels or more from any edge, disocclusion and the image border: must be reused.
        let (i, j) = ((k as u32 % size) as i64, (k as u32 / size) as i64);
        let same_around = (-2..=2).all(|dj| {
            (-2..=2).all(|di| {
                let (x, y) = (i + di, j + dj);
                x >= 2
                    && y >= 2
                    && x < size as i64 - 2
                    && y < size as i64 - 2
                    && seen[(y * size as i64 + x) as usize] == seen[k]
            })
        });
        if matches!(seen[k], 1 | 2) && same_around {
            interior += 1;
            assert_eq!(shared.fate[k], Fate::Reused, "interior pixel {k} ({i}, {j}) was not reused");
        }
    }
    assert!(disoccluded > 50, "the orbit should uncover wall behind the card ({disoccluded} pixels)");
    assert!(interior > truth.len() / 2, "{interior} interior pixels");
}

#[test]
fn empty_space_is_recognised_without_rendering_it() {
    // Zoomed out so that the wall sits inside the frame with empty space around it; the
    // bounds reach beyond the wall, so some empty rays enter them.
    let look = |degrees: f32| {
        let a = degrees.to_radians();
        let eye = Vec3::new(9.0 * a.sin(), -9.0 * a.cos(), 0.0);
        Camera::look_at(64, 64, 0.7, eye, Vec3::ZERO, Vec3::Z).expect("valid camera")
    };
    let (source_camera, target) = (look(0.0), look(3.0));
    let source_frame = render(&source_camera);
    let mut wide = bounds();
    wide.min -= Vec3::splat(0.5);
    wide.max += Vec3::splat(0.5);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    let shared = reproject(&target, &wide, &sources, &Settings::default()).expect("reprojects");
    let counts = shared.counts();
    assert!(counts.outside_bounds > 0 && counts.seen_empty > 0, "{counts:?}");
    for k in 0..shared.fate.len() {
        if matches!(shared.fate[k], Fate::SeenEmpty | Fate::OutsideBounds) {
            let ray = target.pixel_center_ray(k as u32 % 64, k as u32 / 64);
            assert!(trace(&ray).is_none(), "pixel {k} called empty but sees matter");
        }
    }
}

#[test]
fn the_distance_map_counts_pixels_to_the_nearest_matter_or_border() {
    let camera = Camera::look_at(9, 9, 0.7, Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, Vec3::Z).expect("camera");
    let mut frame = PixelResults::with_len(81);
    frame.opacity[2 * 9 + 3] = 1.0; // matter at (3, 2)
    let distances = empty_distances(&Source { camera: &camera, frame: &frame }, &Settings::default());
    for y in 0..9i32 {
        for x in 0..9i32 {
            let to_matter = (x - 3).abs().max((y - 2).abs());
            let to_border = (x + 1).min(y + 1).min(9 - x).min(9 - y);
            assert_eq!(i32::from(distances[(y * 9 + x) as usize]), to_matter.min(to_border), "({x}, {y})");
        }
    }
}

#[test]
fn nothing_is_reused_beyond_the_angle_or_from_no_source() {
    let (source_camera, target) = (orbit(0.0, 48), orbit(8.0, 48));
    let source_frame = render(&source_camera);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    let strict = Settings { max_angle_deg: 4.0, ..Settings::default() };
    let shared = reproject(&target, &bounds(), &sources, &strict).expect("reprojects");
    assert_eq!(shared.counts().reused, 0);
    let lenient = Settings { max_angle_deg: 12.0, ..Settings::default() };
    assert!(reproject(&target, &bounds(), &sources, &lenient).expect("reprojects").counts().reused > 0);
    let alone = reproject(&target, &bounds(), &[], &Settings::default()).expect("reprojects");
    assert_eq!(alone.counts().reused + alone.counts().seen_empty, 0);
}

#[test]
fn the_rendered_pixels_complete_the_frame() {
    let (source_camera, target) = (orbit(-3.0, 48), orbit(3.0, 48));
    let source_frame = render(&source_camera);
    let truth = render(&target);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    let mut shared = reproject(&target, &bounds(), &sources, &Settings::default()).expect("reprojects");
    let pixels = shared.pixels_to_render();
    let mut rendered = PixelResults::with_len(pixels.len());
    for (k, &p) in pixels.iter().enumerate() {
        rendered.color[k] = truth.color[p as usize];
        rendered.opacity[k] = truth.opacity[p as usize];
        rendered.depth[k] = truth.depth[p as usize];
    }
    shared.fill(&pixels, &rendered).expect("fills");
    let worst = (0..truth.len())
        .flat_map(|k| (0..3).map(move |c| (k, c)))
        .map(|(k, c)| (shared.frame.color[k][c] - truth.color[k][c]).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 2e-3, "largest colour error {worst}");
    let short = PixelResults::with_len(pixels.len().saturating_sub(1));
    assert!(matches!(shared.fill(&pixels, &short), Err(ShareError::RenderedSize { .. })));
    assert!(matches!(shared.fill(&[48 * 48], &PixelResults::with_len(1)), Err(ShareError::PixelOutside { .. })));
}

/// The wall textured, right of x = 0, with vertical stripes about one pixel wide (sharp detail
/// across the direction the views move in); left of it, smooth.
fn striped(camera: &Camera) -> PixelResults {
    let mut frame = render(camera);
    for k in 0..frame.len() {
        let ray = camera.pixel_center_ray(k as u32 % camera.width(), k as u32 / camera.width());
        if let Some((point, _)) = trace(&ray).filter(|(p, _)| p.y > 0.0 && p.x > 0.0) {
            let stripe = ((point.x * 18.0).floor() as i64).rem_euclid(2) as f32;
            frame.color[k] = [stripe, stripe, stripe];
        }
    }
    frame
}

#[test]
fn sharp_detail_is_rendered_under_a_contrast_limit() {
    let (source_camera, target) = (orbit(0.0, 64), orbit(2.0, 64));
    let source_frame = striped(&source_camera);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    let fates = |max_contrast| {
        let settings = Settings { max_contrast, ..Settings::default() };
        reproject(&target, &bounds(), &sources, &settings).expect("reprojects").fate
    };
    let (limited, unlimited) = (fates(0.2), fates(f32::INFINITY));
    let (mut striped_kept, mut striped_seen, mut smooth_lost) = (0, 0, 0);
    for k in 0..limited.len() {
        let ray = target.pixel_center_ray(k as u32 % 64, k as u32 / 64);
        let Some((point, _)) = trace(&ray) else { continue };
        let on_stripes = point.y > 0.0 && point.x > 0.05;
        let smooth = point.y > 0.0 && point.x < -0.05 && unlimited[k] == Fate::Reused;
        if on_stripes && unlimited[k] == Fate::Reused {
            striped_seen += 1;
            striped_kept += usize::from(limited[k] == Fate::Reused);
        }
        smooth_lost += usize::from(smooth && limited[k] != Fate::Reused);
    }
    assert!(striped_seen > 100, "{striped_seen}");
    // Pixels between two source pixels of one stripe may still be reused; most are not.
    assert!(striped_kept * 4 < striped_seen, "{striped_kept} of {striped_seen} striped pixels reused");
    assert_eq!(smooth_lost, 0, "smooth pixels lost to the contrast limit");
}

#[test]
fn both_filters_reproduce_a_smooth_texture() {
    let (source_camera, target) = (orbit(0.0, 64), orbit(3.0, 64));
    let source_frame = render(&source_camera);
    let truth = render(&target);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    for filter in [Filter::Bilinear, Filter::CatmullRom] {
        let settings = Settings { filter, ..Settings::default() };
        let shared = reproject(&target, &bounds(), &sources, &settings).expect("reprojects");
        let mut reused = 0;
        for k in 0..truth.len() {
            if shared.fate[k] == Fate::Reused {
                reused += 1;
                for c in 0..3 {
                    let error = (shared.frame.color[k][c] - truth.color[k][c]).abs();
                    assert!(error < 2e-3, "{filter:?}: pixel {k} channel {c}: error {error}");
                }
            }
        }
        assert!(reused > truth.len() / 2, "{filter:?}: {reused}");
    }
}

#[test]
fn edge_bands_grow_the_holes() {
    let (source_camera, target) = (orbit(0.0, 64), orbit(5.0, 64));
    let source_frame = render(&source_camera);
    let sources = [Source { camera: &source_camera, frame: &source_frame }];
    let render_count = |band| {
        let settings = Settings { edge_band: band, ..Settings::default() };
        reproject(&target, &bounds(), &sources, &settings).expect("reprojects").counts().render
    };
    assert!(render_count(1) > render_count(0));
    assert!(render_count(2) > render_count(1));
}

#[test]
fn bad_sources_and_settings_are_refused() {
    let camera = orbit(0.0, 16);
    let short = PixelResults::with_len(10);
    let error = reproject(&camera, &bounds(), &[Source { camera: &camera, frame: &short }], &Settings::default());
    assert!(matches!(error, Err(ShareError::SourceSize { index: 0, len: 10, expected: 256, .. })));
    for settings in [
        Settings { max_angle_deg: f32::NAN, ..Settings::default() },
        Settings { max_angle_deg: 91.0, ..Settings::default() },
        Settings { depth_tolerance_px: -1.0, ..Settings::default() },
        Settings { opaque: 0.0, ..Settings::default() },
        Settings { empty: 0.995, ..Settings::default() },
        Settings { edge_band: 17, ..Settings::default() },
        Settings { max_contrast: f32::NAN, ..Settings::default() },
        Settings { max_contrast: -0.1, ..Settings::default() },
    ] {
        assert!(
            matches!(reproject(&camera, &bounds(), &[], &settings), Err(ShareError::Setting { .. })),
            "{settings:?}"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Garbage in a source (NaN and infinite depths and colours, negative opacity) and cameras
    /// anywhere never give non-finite reused pixels.
    #[test]
    fn garbage_sources_never_leak_into_the_target(
        seed in any::<u64>(),
        degrees in -180.0f32..180.0,
        distance in 0.01f32..1e4,
    ) {
        let source_camera = orbit(0.0, 16);
        let mut frame = render(&source_camera);
        let mut rng = nephele_geometry::SplitMix64::new(seed);
        let nasty = [f32::NAN, f32::INFINITY, -f32::INFINITY, 0.0, -1.0, 1e30, f32::MIN_POSITIVE];
        for k in 0..frame.len() {
            if rng.next_u64().is_multiple_of(3) {
                let pick = |rng: &mut nephele_geometry::SplitMix64| nasty[(rng.next_u64() % nasty.len() as u64) as usize];
                frame.depth[k] = pick(&mut rng);
                frame.color[k] = [pick(&mut rng), 0.5, pick(&mut rng)];
                frame.opacity[k] = if rng.next_u64().is_multiple_of(2) { pick(&mut rng) } else { 1.0 };
            }
        }
        let a = degrees.to_radians();
        let eye = Vec3::new(distance * a.sin(), -distance * a.cos(), 0.3);
        let target = Camera::look_at(16, 16, 0.7, eye, Vec3::ZERO, Vec3::Z).expect("valid camera");
        let sources = [Source { camera: &source_camera, frame: &frame }];
        let shared = reproject(&target, &bounds(), &sources, &Settings::default()).expect("reprojects");
        for k in 0..shared.fate.len() {
            if shared.fate[k] == Fate::Reused {
                prop_assert!(shared.frame.color[k].iter().all(|c| c.is_finite()));
                prop_assert!(shared.frame.opacity[k].is_finite() && shared.frame.depth[k].is_finite());
                // A result's validation refuses opacity outside [0, 1] (1 + rounding once
                // came out of four solid taps).
                prop_assert!((0.0..=1.0).contains(&shared.frame.opacity[k]), "opacity {}", shared.frame.opacity[k]);
            }
        }
    }
}
