//! End-to-end tests of the radiance field: training on a tiny analytic dataset, and the
//! kernel's hard cases.

use glam::Vec3;
use proptest::prelude::*;

use super::*;
use nephele_geometry::camera::Camera;
use nephele_imaging::image::RgbaImage;
use nephele_imaging::metrics;
use nephele_kernels::kernel::{RayKernel, all_pixels, frame_to_image};
use nephele_kernels::ngp::{FieldConfig, FieldScratch, NgpKernel, OccupancyGrid, RadianceField, RayResult, save_field};
use nephele_nn::HashGridConfig;

const RADIUS: f32 = 0.5;
const ORBIT: f32 = 3.0;

/// A small field configuration for tests.
fn tiny_config() -> FieldConfig {
    FieldConfig {
        grid: HashGridConfig::with_finest_resolution(8, 14, 8, 128),
        density_hidden: 32,
        geo_features: 15,
        color_hidden: 32,
        color_hidden_layers: 1,
        sh_degree: 3,
        steps_per_diagonal: 256,
        occupancy_resolution: 32,
    }
}

/// Exact image of a sphere of radius 0.5 at the origin, coloured by its normal, over a
/// transparent background.
fn sphere_image(camera: &Camera) -> RgbaImage {
    RgbaImage::from_fn(camera.width(), camera.height(), |x, y| {
        let ray = camera.pixel_center_ray(x, y);
        let b = ray.origin.dot(ray.direction);
        let c = ray.origin.length_squared() - RADIUS * RADIUS;
        let disc = b * b - c;
        if disc < 0.0 {
            return [0.0; 4];
        }
        let t = -b - disc.sqrt();
        let n = ray.at(t).normalize();
        [0.5 + 0.4 * n.x, 0.5 + 0.4 * n.y, 0.5 + 0.4 * n.z, 1.0]
    })
}

fn view(i: usize, count: usize, size: u32) -> Camera {
    // Fibonacci sphere, avoiding the poles.
    let z = 0.9 * (1.0 - 2.0 * (i as f32 + 0.5) / count as f32);
    let phi = i as f32 * std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let r = (1.0 - z * z).sqrt();
    let eye = ORBIT * Vec3::new(r * phi.cos(), r * phi.sin(), z);
    Camera::look_at(size, size, 0.6, eye, Vec3::ZERO, Vec3::Z).expect("camera")
}

fn render(kernel: &NgpKernel, camera: &Camera) -> RgbaImage {
    let (out, _) = kernel.render_pixels(camera, &all_pixels(camera)).expect("render");
    frame_to_image(camera.width(), camera.height(), &out).expect("image")
}

#[test]
fn training_on_a_sphere_lowers_the_loss_and_beats_a_constant() {
    let size = 32;
    let cameras: Vec<Camera> = (0..24).map(|i| view(i, 24, size)).collect();
    let images: Vec<RgbaImage> = cameras.iter().map(sphere_image).collect();
    let views: Vec<(Camera, &RgbaImage)> = cameras.iter().copied().zip(images.iter()).collect();
    let config = TrainConfig { samples_per_step: 1 << 12, learning_rate: 2e-2, ..TrainConfig::default() };
    let mut trainer = Trainer::new(tiny_config(), config, &views).expect("trainer");
    // The visual hull is a small part of the initial box and the box was fitted to it.
    let bounds = trainer.field().bounds();
    assert!(bounds.size().x < 2.0 && bounds.min.x < -RADIUS && bounds.max.x > RADIUS, "{bounds:?}");
    let steps = 250;
    let mut losses = Vec::new();
    for s in 0..steps {
        let stats = trainer.step(s as f32 / steps as f32).expect("step");
        assert!(stats.loss.is_finite() && stats.rays > 0);
        losses.push(stats.loss);
    }
    let early: f32 = losses[..10].iter().sum::<f32>() / 10.0;
    let late: f32 = losses[steps - 20..].iter().sum::<f32>() / 20.0;
    assert!(late < 0.2 * early, "loss {early} -> {late}");

    // A held-out view between the training ones.
    let kernel = NgpKernel::new(trainer.into_field());
    let test = Camera::look_at(size, size, 0.6, Vec3::new(2.1, -2.0, 0.7), Vec3::ZERO, Vec3::Z).expect("camera");
    let truth = sphere_image(&test);
    let pred = render(&kernel, &test);
    let white = [1.0; 3];
    let psnr = metrics::psnr(&pred, &truth, white).expect("psnr");
    // The best constant colour (the mean of the truth over white).
    let over = truth.composite_over(white);
    let n = over.pixels().len() as f32;
    let mean =
        over.pixels().iter().fold([0.0f32; 3], |acc, p| [acc[0] + p[0] / n, acc[1] + p[1] / n, acc[2] + p[2] / n]);
    let constant = RgbaImage::from_fn(size, size, |_, _| [mean[0], mean[1], mean[2], 1.0]);
    let baseline = metrics::psnr(&constant, &truth, white).expect("psnr");
    eprintln!("sphere: loss {early} -> {late}, held-out PSNR {psnr:.2} dB vs best constant {baseline:.2} dB");
    assert!(psnr > baseline + 8.0, "psnr {psnr} vs constant {baseline}");

    // Depth of the centre pixel: the sphere's front at orbit - radius (view depth), within a
    // couple of marching steps plus the pixel's footprint.
    let centre = (size / 2) * size + size / 2;
    let (out, stats) = kernel.render_pixels(&test, &[centre, 0]).expect("render");
    let expected = test.position().length() - RADIUS;
    assert!(out.opacity[0] > 0.9 && (out.depth[0] - expected).abs() < 0.08, "{:?} vs {expected}", out);
    // The peak-weight sample (i-NOLF's hit point) lies on the surface too.
    let ray = test.pixel_center_ray(size / 2, size / 2);
    let (hit, _) = kernel.render_rays(&[(ray.origin, ray.direction)]);
    let surface = ray.origin.length() - RADIUS;
    assert!((hit[0].peak_distance - surface).abs() < 0.08, "{:?} vs {surface}", hit[0]);
    assert_eq!((out.opacity[1], out.depth[1]), (0.0, 0.0));
    assert_eq!(stats.rays, 2);
    assert!(stats.queries > 0 && stats.rays_hit >= 1);

    hit_points_agree_with_density_cubes(&kernel, &test);
    density_hit_matches_the_full_render(&kernel, &test);

    // Round trip through the file gives the same image.
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("sphere.ngp");
    save_field(kernel.field(), &path).expect("save");
    let loaded = NgpKernel::load(&path).expect("load");
    assert_eq!(render(&loaded, &test), pred);
    assert_eq!(loaded.kind(), "ngp");
}

/// An untrained field made dense everywhere (large density bias): the worst case for
/// marching, compositing and early termination.
fn dense_field() -> NgpKernel {
    let mut field = RadianceField::new(tiny_config(), Vec3::splat(-1.0), 2.0, 5).expect("field");
    let n = field.density.num_params();
    let out = field.density.config().output;
    // The density MLP's last bias block: raise the log-density output.
    field.density.params_mut()[n - out] = 3.0;
    NgpKernel::new(field)
}

fn check(r: &RayResult) -> Result<(), TestCaseError> {
    prop_assert!(r.color.iter().all(|c| c.is_finite() && *c >= 0.0 && *c <= 1.0 + 1e-5), "{r:?}");
    prop_assert!((0.0..=1.0).contains(&r.opacity), "{r:?}");
    prop_assert!(r.distance.is_finite());
    if r.opacity > 0.0 {
        prop_assert!(r.distance > 0.0, "{r:?}");
    }
    Ok(())
}

#[test]
fn hard_rays_stay_finite_and_bounded() {
    let kernel = dense_field();
    let axes = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];
    let mut rays = Vec::new();
    // Missing the box entirely, and pointing away from it.
    rays.push((Vec3::new(5.0, 5.0, 5.0), Vec3::X));
    rays.push((Vec3::new(-5.0, 0.0, 0.0), Vec3::NEG_X));
    // Axis-parallel from outside, through the centre, along faces and edges (grazing).
    for a in axes {
        rays.push((-3.0 * a, a));
        rays.push((-3.0 * a + Vec3::ONE - a.abs(), a));
        rays.push((-3.0 * a - (Vec3::ONE - a.abs()), a));
    }
    // Starting inside the box (the camera inside the object), in every axis direction.
    for a in axes {
        rays.push((Vec3::ZERO, a));
        rays.push((Vec3::splat(0.999), a));
    }
    // Through a corner exactly.
    rays.push((Vec3::splat(-2.0), Vec3::ONE.normalize()));
    let (results, stats) = kernel.render_rays(&rays);
    for r in &results {
        check(r).expect("bounded");
    }
    // Misses cost nothing: no samples, no colour queries.
    assert_eq!((results[0].samples, results[1].samples), (0, 0));
    assert_eq!(results[0].opacity, 0.0);
    // Dense field: rays through it become opaque and stop early.
    let through = &results[2];
    assert!(through.opacity > 0.99 && through.samples < 256, "{through:?}");
    assert!(stats.rays_hit > 10);

    // The camera inside the dense object sees it everywhere at a small positive depth.
    let camera = Camera::look_at(8, 8, 1.0, Vec3::ZERO, Vec3::X, Vec3::Z).expect("camera");
    let (out, _) = kernel.render_pixels(&camera, &all_pixels(&camera)).expect("render");
    for i in 0..out.len() {
        assert!(
            out.opacity[i] > 0.9 && out.depth[i] > 0.0 && out.depth[i] < 0.5,
            "{i}: {} {}",
            out.opacity[i],
            out.depth[i]
        );
        assert!(out.color[i].iter().all(|c| c.is_finite() && *c >= 0.0 && *c <= out.opacity[i] + 1e-5));
    }
    assert!(kernel.render_pixels(&camera, &[64]).is_err());
}

#[test]
fn empty_occupancy_costs_nothing() {
    let kernel = dense_field();
    let mut field = kernel.field().clone();
    field.set_occupancy(OccupancyGrid::filled(32, false)).expect("occupancy");
    let kernel = NgpKernel::new(field);
    let rays: Vec<(Vec3, Vec3)> = (0..64).map(|i| (Vec3::new(-3.0, 0.01 * i as f32, 0.3), Vec3::X)).collect();
    let (results, stats) = kernel.render_rays(&rays);
    assert_eq!((stats.samples, stats.rays_hit, stats.color_queries), (0, 0, 0));
    assert!(results.iter().all(|r| r.opacity == 0.0));
}

#[test]
fn point_queries_for_the_bake() {
    let kernel = dense_field();
    let field = kernel.field();
    let mut scratch = FieldScratch::new();
    let points = [Vec3::ZERO, Vec3::splat(0.9), Vec3::splat(7.0)];
    let mut sigma = [0.0; 3];
    field.density_batch(&points, &mut sigma, &mut scratch).expect("density");
    assert!(sigma.iter().all(|s| s.is_finite() && *s > 1.0), "{sigma:?}");
    let mut rgb = [[0.0; 3]; 3];
    field.color_batch(&points, &[Vec3::X, Vec3::Y, Vec3::ZERO], &mut rgb, &mut scratch).expect("colour");
    let mut diffuse = [[0.0; 3]; 3];
    field.diffuse_batch(&points, &mut diffuse, &mut scratch).expect("diffuse");
    for c in rgb.iter().chain(&diffuse) {
        assert!(c.iter().all(|v| (0.0..=1.0).contains(v)));
    }
    assert!(field.density_batch(&points, &mut sigma[..2], &mut scratch).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
    #[test]
    fn random_rays_stay_finite_and_bounded(
        o in prop::array::uniform3(-3.0f32..3.0),
        d in prop::array::uniform3(-1.0f32..1.0),
        zero in 0usize..4,
    ) {
        let kernel = dense_field();
        let mut d = Vec3::from(d);
        if zero < 3 {
            d[zero] = 0.0;
        }
        let Some(d) = d.try_normalize() else { return Ok(()); };
        let (results, _) = kernel.render_rays(&[(Vec3::from(o), d)]);
        check(&results[0])?;
    }
}

/// i-NOLF's hit point against the baseline's (issue 3, hard cases): density cubes baked from
/// the trained field as `nephele bake` bakes them; on every pixel of `camera` where both see
/// the solid sphere, the cube march's sample of largest weight lies within one cube cell of
/// the baseline's expected depth on at least 95 % of them and within two everywhere; and
/// within two cells of the baseline's own peak-weight sample (noisier: a trained field's
/// density ramps up over a few marching steps) everywhere.
fn hit_points_agree_with_density_cubes(kernel: &NgpKernel, camera: &Camera) {
    use crate::inolf::bake::field_density_for_cubes;
    use nephele_kernels::inolf::cubes::{CubeOptions, DensityCubes};
    let field = kernel.field();
    let options = CubeOptions { resolution: 16, cube_res: 6, ..CubeOptions::default() };
    let cubes =
        DensityCubes::build(field.bounds(), &options, field_density_for_cubes(field, 1.0), &|_| {}).expect("cubes");
    let cell = cubes.cubes().cell();
    let rays: Vec<(Vec3, Vec3)> = all_pixels(camera)
        .iter()
        .map(|&p| {
            let r = camera.pixel_center_ray(p % camera.width(), p / camera.width());
            (r.origin, r.direction)
        })
        .collect();
    let (baseline, _) = kernel.render_rays(&rays);
    let (mut compared, mut within_cell, mut worst_peak, mut worst_mean) = (0, 0, 0.0f32, 0.0f32);
    for ((origin, dir), b) in rays.iter().zip(&baseline) {
        let hit = cubes.march(*origin, *dir, 0.0, f32::INFINITY);
        assert!(hit.opacity.is_finite() && (0.0..=1.0).contains(&hit.opacity) && hit.t.is_finite());
        if b.opacity > 0.9 && hit.opacity > 0.9 {
            compared += 1;
            worst_peak = worst_peak.max((hit.t - b.peak_distance).abs());
            worst_mean = worst_mean.max((hit.t - b.distance).abs());
            within_cell += usize::from((hit.t - b.distance).abs() <= cell);
        }
    }
    let fraction = within_cell as f64 / compared.max(1) as f64;
    eprintln!(
        "hit agreement on {compared} pixels: {:.1} % within one cube cell ({cell:.4}) of the baseline's depth; worst {worst_mean:.4} (depth), {worst_peak:.4} (peak sample)",
        100.0 * fraction
    );
    assert!(compared > 50, "only {compared} pixels where both see the sphere");
    assert!(fraction >= 0.95, "{:.1} % of hit points within one cube cell", 100.0 * fraction);
    assert!(
        worst_peak <= 2.0 * cell && worst_mean <= 2.0 * cell,
        "worst {worst_peak} / {worst_mean} against a cube cell of {cell}"
    );
}

/// The density network alone ("i-NOLF base"'s hit point) gives the full render's opacity,
/// depth and peak-weight sample with the same samples and no colour query.
fn density_hit_matches_the_full_render(kernel: &NgpKernel, camera: &Camera) {
    let field = kernel.field();
    let mut scratch = FieldScratch::new();
    let mut hits = 0;
    for &p in &all_pixels(camera) {
        let ray = camera.pixel_center_ray(p % camera.width(), p / camera.width());
        let full = field.render_ray(ray.origin, ray.direction, 0.0, &mut scratch);
        let density = field.density_hit(ray.origin, ray.direction, 0.0, &mut scratch);
        assert_eq!((density.samples, density.color_queries, density.color), (full.samples, 0, [0.0; 3]));
        assert_eq!(density.peak_distance, full.peak_distance);
        assert!((density.opacity - full.opacity).abs() < 1e-5, "{density:?} vs {full:?}");
        assert!((density.distance - full.distance).abs() < 1e-4, "{density:?} vs {full:?}");
        hits += usize::from(full.opacity > 0.5);
    }
    assert!(hits > 50, "{hits} pixels see the sphere");
}

/// Corrupt training pixels (issue 18): a few NaN, infinite or out-of-range values are dropped
/// or clamped and counted, and training stays finite; a set with more than 1 % of them is
/// refused.
#[test]
fn corrupt_pixels_are_clamped_or_dropped_with_a_count() {
    let size = 24;
    let cameras: Vec<Camera> = (0..12).map(|i| view(i, 12, size)).collect();
    let corrupt = |every: u32| -> Vec<RgbaImage> {
        cameras
            .iter()
            .map(|c| {
                let clean = sphere_image(c);
                RgbaImage::from_fn(size, size, |x, y| {
                    let p = clean.pixel(x, y);
                    match (y * size + x) % every {
                        0 => [f32::NAN, p[1], p[2], p[3]],
                        1 => [p[0], p[1], p[2], f32::INFINITY],
                        2 => [4.0, -1.0, p[2], 1.5],
                        _ => p,
                    }
                })
            })
            .collect()
    };
    let config = TrainConfig { samples_per_step: 1 << 12, ..TrainConfig::default() };
    // Four pixels in 576 per view are not numbers (0.7 %): dropped; two are out of range.
    let images = corrupt(288);
    let views: Vec<(Camera, &RgbaImage)> = cameras.iter().copied().zip(images.iter()).collect();
    let mut trainer = Trainer::new(tiny_config(), config, &views).expect("a few corrupt pixels are accepted");
    let check = trainer.pixel_check();
    assert_eq!(check.pixels, 12 * 576);
    assert_eq!((check.dropped, check.clamped), (12 * 4, 12 * 2), "{check:?}");
    for s in 0..20 {
        let stats = trainer.step(s as f32 / 20.0).expect("step");
        assert!(stats.loss.is_finite(), "{stats:?}");
    }
    assert!(trainer.field().density.params().iter().all(|p| p.is_finite()));
    // One pixel in ten is not a number: refused, with the count.
    let images = corrupt(20);
    let views: Vec<(Camera, &RgbaImage)> = cameras.iter().copied().zip(images.iter()).collect();
    let err = Trainer::new(tiny_config(), config, &views).expect_err("corrupt images are refused");
    assert!(err.to_string().contains("NaN or infinite"), "{err}");
}
