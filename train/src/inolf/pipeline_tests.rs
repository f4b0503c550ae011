//! End to end on an analytic object: density cubes of a sphere, views rendered
//! analytically, training, baking, the asset round trip and the kernel's hard cases.
//!
//! Most tests here put the chain together from its stages on purpose: an analytic density
//! stands in for the radiance field, so that what the heads learn and what the asset renders
//! can be checked against a known answer. The library's whole bake, [`super::pipeline::bake`]
//! (what `nephele bake` and the first start call), has its own test at the end on a small
//! path-traced dataset.

use std::sync::OnceLock;

use glam::Vec3;
use proptest::prelude::*;

use super::bake::{bake_diffuse_cubes, to_asset};
use super::train::{TrainOptions, TrainingView, collect_hit_points, train};
use nephele_geometry::camera::Camera;
use nephele_kernels::inolf::asset::Asset;
use nephele_kernels::inolf::cubes::{CubeOptions, DensityCubes, HitRule, MAX_BLEND_SAMPLES};
use nephele_kernels::inolf::encoding::PshEncoding;
use nephele_kernels::inolf::kernel::{DiffuseSource, HitSource, InolfKernel};
use nephele_kernels::inolf::model::{HeadsShape, InolfModel};
use nephele_kernels::inolf::psh::PshOptions;
use nephele_kernels::kernel::{Bounds, RayKernel, all_pixels};
use nephele_nn::SimdMode;

const RADIUS: f32 = 0.6;

fn bounds() -> Bounds {
    Bounds { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }
}

fn sphere_cubes() -> DensityCubes {
    let options = CubeOptions { resolution: 16, cube_res: 6, probe: 2, dilate: 1 };
    DensityCubes::build(
        bounds(),
        &options,
        |p: &[Vec3], out: &mut [f32]| {
            p.iter().zip(out).for_each(|(p, o)| *o = if p.length() < RADIUS { 300.0 } else { 0.0 })
        },
        &|_| {},
    )
    .expect("cubes")
}

/// Analytic view: a sphere whose linear colour varies with the surface normal.
fn view(eye: Vec3, size: u32) -> TrainingView {
    let camera = Camera::look_at(size, size, 0.7, eye, Vec3::ZERO, Vec3::Z).expect("camera");
    let target = all_pixels(&camera)
        .iter()
        .map(|&p| {
            let ray = camera.pixel_center_ray(p % size, p / size);
            let b = ray.origin.dot(ray.direction);
            // The cubes' sphere is about half a sample step fatter than RADIUS (trilinear
            // interpolation of the density); the images show that sphere.
            let r = RADIUS + 0.012;
            let disc = b * b - (ray.origin.length_squared() - r * r);
            if disc < 0.0 {
                return [0.0; 4];
            }
            let n = ray.at(-b - disc.sqrt()).normalize();
            [0.2 + 0.3 * (n.x * 0.5 + 0.5), 0.1 + 0.5 * (n.z * 0.5 + 0.5), 0.3, 1.0]
        })
        .collect();
    TrainingView { camera, target }
}

fn views() -> Vec<TrainingView> {
    (0..16)
        .map(|i| {
            let a = i as f32 * std::f32::consts::FRAC_PI_8;
            view(Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), if i % 2 == 0 { 1.0 } else { -0.8 }), 24)
        })
        .collect()
}

fn small_shape() -> HeadsShape {
    HeadsShape {
        grid_levels: 4,
        grid_log2_table: 12,
        grid_base: 4,
        grid_scale: 2.0,
        diffuse_hidden: 16,
        diffuse_layers: 1,
        sh_degree: 2,
        specular_hidden: 16,
        specular_layers: 1,
        diffuse_blend: true,
        blend_samples: MAX_BLEND_SAMPLES as u32,
    }
}

struct Trained {
    model: InolfModel,
    cubes: DensityCubes,
    hits: Vec<Vec3>,
    first_loss: f32,
    last_loss: f32,
}

fn trained() -> &'static Trained {
    static T: OnceLock<Trained> = OnceLock::new();
    T.get_or_init(|| {
        let cubes = sphere_cubes();
        let views = views();
        let hits = collect_hit_points(&cubes, &views, 1);
        let psh =
            PshEncoding::from_points(&hits, bounds().min, 2.0 / 31.0, 32, 4, &PshOptions::coherent()).expect("psh");
        let mut model = InolfModel::new(small_shape(), bounds(), psh, 3).expect("model");
        let mut first_loss = f32::NAN;
        let options = TrainOptions { steps: 1000, batch: 512, ..TrainOptions::default() };
        let report = train(&mut model, &cubes, &views, &options, &mut |step, loss| {
            if step == 5 {
                first_loss = loss;
            }
        })
        .expect("train");
        Trained { model, cubes, hits, first_loss, last_loss: report.smoothed_loss }
    })
}

fn psnr_against(kernel: &InolfKernel, v: &TrainingView) -> f64 {
    let (out, stats) = kernel.render_pixels(&v.camera, &all_pixels(&v.camera)).expect("render");
    assert_eq!(stats.rays, v.target.len() as u64);
    let mut se = 0.0f64;
    for (i, t) in v.target.iter().enumerate() {
        for (c, x) in out.color[i].iter().zip(t) {
            se += f64::from(c - x).powi(2);
        }
        se += f64::from(out.opacity[i] - t[3]).powi(2);
    }
    -10.0 * (se / (v.target.len() * 4) as f64).log10()
}

#[test]
fn training_fits_the_views_and_the_asset_renders_the_same() {
    let t = trained();
    eprintln!("loss {} -> {}", t.first_loss, t.last_loss);
    assert!(t.last_loss < t.first_loss * 0.2, "loss {} -> {}", t.first_loss, t.last_loss);
    let views = views();
    let net = InolfKernel::from_model(&t.model, t.cubes.clone(), None);
    let psnr_net = psnr_against(&net, &views[0]);
    // Bake the diffuse branch and go through the file format.
    let diffuse = bake_diffuse_cubes(&t.model, &t.cubes, &t.hits, 1, 6).expect("bake");
    assert!(diffuse.cube_count() > 0 && diffuse.cube_count() <= t.cubes.cubes().cube_count());
    let asset =
        to_asset(&t.model, t.cubes.clone(), Some(diffuse), true, serde_json::json!({"test": true})).expect("asset");
    let bytes = asset.to_bytes().expect("encode");
    let mut kernel = InolfKernel::from_asset(Asset::from_bytes(&bytes).expect("decode")).expect("kernel");
    assert_eq!(kernel.diffuse_source(), DiffuseSource::Cubes);
    let psnr_cubes = psnr_against(&kernel, &views[0]);
    kernel.set_diffuse_source(DiffuseSource::Network).expect("network kept");
    let psnr_loaded_net = psnr_against(&kernel, &views[0]);
    eprintln!(
        "PSNR (linear, premultiplied + alpha): network {psnr_net:.2} dB, diffuse cubes {psnr_cubes:.2} dB, loaded network {psnr_loaded_net:.2} dB"
    );
    assert!(psnr_net > 35.0, "{psnr_net}");
    assert!((psnr_loaded_net - psnr_net).abs() < 1e-6, "the asset holds the same network");
    assert!(psnr_cubes > psnr_net - 3.0, "baking loses little: {psnr_cubes} vs {psnr_net}");
    // A held-out view.
    let held_out = view(Vec3::new(0.5, -2.9, 0.4), 24);
    let psnr_held = psnr_against(&kernel, &held_out);
    eprintln!("held-out view {psnr_held:.2} dB");
    assert!(psnr_held > 22.0, "{psnr_held}");
}

#[test]
fn asset_without_diffuse_network_renders_from_cubes_only() {
    let t = trained();
    let diffuse = bake_diffuse_cubes(&t.model, &t.cubes, &t.hits, 1, 4).expect("bake");
    let asset = to_asset(&t.model, t.cubes.clone(), Some(diffuse), false, serde_json::Value::Null).expect("asset");
    assert_eq!(asset.tensors.len(), 1);
    let mut kernel = InolfKernel::from_asset(asset.clone()).expect("kernel");
    assert!(kernel.set_diffuse_source(DiffuseSource::Network).is_err());
    // The bake writes every voxel; a stride recorded in the meta section travels through the
    // file and is what the kernel marches at; one out of range is refused.
    assert_eq!(kernel.density().march_stride(), 1);
    let mut strided = asset.clone();
    nephele_kernels::inolf::heads::set_asset_march_stride(&mut strided, 3).expect("stride 3");
    let strided = Asset::from_bytes(&strided.to_bytes().expect("encode")).expect("decode");
    assert_eq!(InolfKernel::from_asset(strided).expect("kernel").density().march_stride(), 3);
    let mut hostile = asset.clone();
    assert!(hostile.meta.contains("\"march_stride\":1"), "{}", hostile.meta);
    hostile.meta = hostile.meta.replace("\"march_stride\":1", "\"march_stride\":9");
    let err = InolfKernel::from_asset(hostile).expect_err("stride 9");
    assert!(err.to_string().contains("march stride 9"), "{err}");
    // The hit rule the heads were trained with travels the same way; assets older than the
    // field take the largest weight; numbers a march cannot honour are refused.
    assert!(asset.meta.contains("\"hit_rule\":\"largest_weight\""), "{}", asset.meta);
    let mut see_through = asset.clone();
    see_through.meta =
        see_through.meta.replace("\"largest_weight\"", "{\"layer_behind\":{\"opacity\":0.9,\"gap\":16.0}}");
    let see_through = Asset::from_bytes(&see_through.to_bytes().expect("encode")).expect("decode");
    assert_eq!(InolfKernel::from_asset(see_through).expect("kernel").density().hit_rule(), HitRule::SEE_THROUGH);
    let mut median = asset.clone();
    median.meta = median.meta.replace("\"largest_weight\"", "\"median_depth\"");
    let median = Asset::from_bytes(&median.to_bytes().expect("encode")).expect("decode");
    assert_eq!(InolfKernel::from_asset(median).expect("kernel").density().hit_rule(), HitRule::MedianDepth);
    let mut older = asset.clone();
    older.meta = older.meta.replace(",\"hit_rule\":\"largest_weight\"", "");
    assert!(!older.meta.contains("hit_rule"), "{}", older.meta);
    assert_eq!(InolfKernel::from_asset(older).expect("kernel").density().hit_rule(), HitRule::LargestWeight);
    let mut hostile = asset.clone();
    hostile.meta = hostile.meta.replace("\"largest_weight\"", "{\"layer_behind\":{\"opacity\":1.5,\"gap\":16.0}}");
    let err = InolfKernel::from_asset(hostile).expect_err("opacity 1.5");
    assert!(err.to_string().contains("layer opacity 1.5"), "{err}");
    // So does the count of blended samples: assets older than the field blended 4; counts
    // the march cannot keep are refused.
    assert_eq!(kernel.density().blend_samples() as usize, MAX_BLEND_SAMPLES);
    let recorded = format!("\"blend_samples\":{MAX_BLEND_SAMPLES}");
    assert!(asset.meta.contains(&recorded), "{}", asset.meta);
    let mut older = asset.clone();
    older.meta = older.meta.replace(&format!(",{recorded}"), "");
    assert!(!older.meta.contains("blend_samples"), "{}", older.meta);
    assert_eq!(InolfKernel::from_asset(older).expect("kernel").density().blend_samples(), 4);
    for count in [0, MAX_BLEND_SAMPLES + 1] {
        let mut hostile = asset.clone();
        hostile.meta = hostile.meta.replace(&recorded, &format!("\"blend_samples\":{count}"));
        let err = InolfKernel::from_asset(hostile).expect_err("a count out of range");
        assert!(err.to_string().contains(&format!("{count} blend samples")), "{err}");
    }
    // No diffuse part at all is an error, not a broken kernel.
    let mut bare = to_asset(&t.model, t.cubes.clone(), None, false, serde_json::Value::Null).expect("asset");
    bare.tensors.retain(|x| x.name == "specular.mlp");
    assert!(InolfKernel::from_asset(bare).is_err());
}

fn camera_strategy() -> impl Strategy<Value = Camera> {
    (
        prop_oneof![
            (-4.0f32..4.0, -4.0f32..4.0, -4.0f32..4.0).prop_map(|(x, y, z)| Vec3::new(x, y, z)),
            (-0.5f32..0.5, -0.5f32..0.5, -0.5f32..0.5).prop_map(|(x, y, z)| Vec3::new(x, y, z) * 0.6),
            (-8i32..=8, -8i32..=8).prop_map(|(x, y)| Vec3::new(x as f32 / 8.0, y as f32 / 8.0, 3.0)),
        ],
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0),
        0.2f32..2.5,
    )
        .prop_filter_map("degenerate", |(eye, (x, y, z), fov)| {
            let dir = Vec3::new(x, y, z);
            (dir.length() > 0.1).then_some(())?;
            let forward = dir.normalize();
            let up = if forward.z.abs() > 0.9 { Vec3::X } else { Vec3::Z };
            Camera::look_at(9, 7, fov, eye, eye + forward, up).ok()
        })
}

/// Every pixel sane: finite non-negative colour, opacity in [0, 1], positive finite depth
/// where opacity > 0 and nothing at all where it is 0.
fn check_frame(out: &nephele_kernels::kernel::PixelResults) -> Result<(), TestCaseError> {
    for i in 0..out.opacity.len() {
        prop_assert!(out.color[i].iter().all(|c| c.is_finite() && *c >= 0.0));
        prop_assert!((0.0..=1.0).contains(&out.opacity[i]));
        prop_assert!(out.depth[i].is_finite());
        if out.opacity[i] > 0.0 {
            prop_assert!(out.depth[i] > 0.0);
        } else {
            prop_assert_eq!(out.depth[i], 0.0);
            prop_assert_eq!(out.color[i], [0.0; 3]);
        }
    }
    Ok(())
}

/// The same frame from the vector kernel and from its scalar twin (`--simd off`): the march
/// has no fused operations, so hit masks, depths and statistics are identical; the heads'
/// MLPs differ by FMA rounding only (colour and opacity within 1e-4 per pixel).
fn check_scalar_twin(
    kernel: &InolfKernel,
    camera: &Camera,
    pixels: &[u32],
    vector: &nephele_kernels::kernel::PixelResults,
) -> Result<(), TestCaseError> {
    let mut scalar = kernel.clone();
    scalar.set_simd(SimdMode::Off);
    let (out, _) = scalar.render_pixels(camera, pixels).expect("render");
    check_frame(&out)?;
    let mut abs_sum = 0.0f64;
    for i in 0..pixels.len() {
        prop_assert_eq!(out.opacity[i] > 0.0, vector.opacity[i] > 0.0, "hit mask differs at pixel {}", i);
        prop_assert_eq!(out.depth[i], vector.depth[i]);
        prop_assert!((out.opacity[i] - vector.opacity[i]).abs() < 1e-4);
        for k in 0..3 {
            let d = (out.color[i][k] - vector.color[i][k]).abs();
            prop_assert!(d < 1e-4, "pixel {} channel {}: {} vs {}", i, k, out.color[i][k], vector.color[i][k]);
            abs_sum += f64::from(d);
        }
    }
    prop_assert!(abs_sum / (3 * pixels.len().max(1)) as f64 <= 1e-5);
    Ok(())
}

/// An untrained radiance field over the box: a translucent fog everywhere, the worst case
/// for the "i-NOLF base" hit point (density network marched along every ray).
fn fog_field() -> nephele_kernels::ngp::RadianceField {
    let config = nephele_kernels::ngp::FieldConfig {
        grid: nephele_nn::HashGridConfig::with_finest_resolution(4, 12, 4, 32),
        density_hidden: 16,
        color_hidden: 16,
        color_hidden_layers: 1,
        steps_per_diagonal: 64,
        occupancy_resolution: 16,
        ..nephele_kernels::ngp::FieldConfig::default()
    };
    nephele_kernels::ngp::RadianceField::new(config, bounds().min, 2.0, 11).expect("field")
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Hard cases: cameras outside, inside the box, inside the object, looking anywhere;
    /// hit points from the density cubes and from a density network.
    #[test]
    fn kernel_outputs_are_always_sane(camera in camera_strategy()) {
        let t = trained();
        let kernel = InolfKernel::from_model(&t.model, t.cubes.clone(), None);
        let pixels = all_pixels(&camera);
        let (out, stats) = kernel.render_pixels(&camera, &pixels).expect("render");
        prop_assert_eq!(stats.rays, pixels.len() as u64);
        prop_assert_eq!(stats.queries, stats.rays_hit);
        check_frame(&out)?;
        // Inside the object every ray sees it at once.
        if camera.position().length() < RADIUS - 0.1 {
            prop_assert!(stats.rays_hit == stats.rays);
        }
        check_scalar_twin(&kernel, &camera, &pixels, &out)?;
        // The heads' prefetch hints change nothing.
        let mut unhinted = kernel.clone();
        unhinted.set_prefetch(false);
        let (same, _) = unhinted.render_pixels(&camera, &pixels).expect("render");
        prop_assert_eq!((&same.color, &same.opacity, &same.depth), (&out.color, &out.opacity, &out.depth));

        let mut network = kernel.clone();
        network.use_density_network(fog_field());
        prop_assert_eq!(network.hit_source(), HitSource::DensityNetwork);
        let (out, stats) = network.render_pixels(&camera, &pixels).expect("render");
        prop_assert_eq!(stats.rays, pixels.len() as u64);
        // Each ray that hits costs its density samples plus one heads query.
        prop_assert!(stats.queries >= 2 * stats.rays_hit, "{stats:?}");
        check_frame(&out)?;
        check_scalar_twin(&network, &camera, &pixels, &out)?;
    }
}

/// `bench inolf`'s model bytes: the parts the kernel reads, by hit source and diffuse source.
#[test]
fn memory_counts_the_parts_in_use() {
    let t = trained();
    let mut kernel = InolfKernel::from_model(&t.model, t.cubes.clone(), None);
    let m = kernel.memory();
    assert_eq!(m.in_use, m.density_cubes + m.diffuse_network + m.psh_tables + m.psh_features + m.specular_mlp);
    assert!(
        m.density_cubes > 0
            && m.diffuse_network > 0
            && m.psh_features > 0
            && m.specular_mlp > 0
            && m.density_network == 0
    );
    kernel.use_density_network(fog_field());
    let m = kernel.memory();
    assert!(m.density_network > 0);
    assert_eq!(m.in_use, m.density_network + m.diffuse_network + m.psh_tables + m.psh_features + m.specular_mlp);
}

/// A meta section describing networks that do not match the stored weights (or absurdly
/// large ones) is rejected before any network is allocated.
#[test]
fn meta_that_disagrees_with_the_weights_is_rejected() {
    let t = trained();
    let asset = to_asset(&t.model, t.cubes.clone(), None, true, serde_json::Value::Null).expect("asset");
    for edit in [
        |s: &mut HeadsShape| {
            s.grid_levels = 32;
            s.grid_log2_table = 26;
        },
        |s: &mut HeadsShape| s.specular_hidden = 100_000,
        |s: &mut HeadsShape| s.diffuse_hidden += 1,
        |s: &mut HeadsShape| s.sh_degree = 9,
    ] {
        let mut meta: nephele_kernels::inolf::heads::InolfMeta = serde_json::from_str(&asset.meta).expect("meta");
        edit(&mut meta.shape);
        let mut hostile = asset.clone();
        hostile.meta = serde_json::to_string(&meta).expect("json");
        assert!(InolfKernel::from_asset(hostile).is_err(), "{:?}", meta.shape);
    }
    let mut garbage = asset.clone();
    garbage.meta = "{\"format\": \"something else\"}".into();
    assert!(InolfKernel::from_asset(garbage).is_err());
    assert!(InolfKernel::from_asset(asset).is_ok());
}

/// Stages a bake reported, in order, and whether the trained field was handed over.
#[derive(Debug, Default)]
struct Recorder {
    stages: Vec<String>,
    summaries: Vec<String>,
    field_handed_over: bool,
}

impl super::pipeline::BakeProgress for Recorder {
    fn stage(&mut self, name: &str, _: u64, _: &str) {
        self.stages.push(name.to_string());
    }
    fn advance(&mut self, done: u64, total: u64, _: &str) {
        assert!(done <= total, "progress {done} of {total}");
    }
    fn finished(&mut self, summary: String) {
        self.summaries.push(summary);
    }
    fn field_trained(&mut self, _: &nephele_kernels::ngp::RadianceField) {
        self.field_handed_over = true;
    }
}

/// `bake(dataset, recipe)` as the CLI calls it, on a small path-traced dataset of a built-in
/// object: every stage reports, the asset renders the views it was baked from much better
/// than an empty frame does, and a second bake from the returned field trains no field.
#[test]
fn the_library_bake_turns_posed_images_into_an_asset() {
    use super::pipeline::{BakeError, BakeRecipe, bake};
    use crate::synth::{DatasetSpec, render_dataset};
    use nephele_imaging::metrics::psnr;
    use nephele_kernels::kernel::frame_to_image;

    let dir = tempfile::tempdir().expect("tempdir");
    let scene = nephele_pathtracer::scenes::builtin("diffuse").expect("scene");
    let spec = DatasetSpec {
        views: 16,
        test_views: 0,
        width: 32,
        height: 32,
        spp: 2,
        test_spp: 0,
        bounces: 2,
        seed: 0,
        full_sphere: false,
        depth: false,
    };
    render_dataset(scene, &spec, dir.path(), &|_| {}).expect("dataset");
    let data = crate::dataset::load_split(dir.path(), "train", 1).expect("load");
    let recipe = BakeRecipe {
        field_steps: 60,
        field_table_log2: 12,
        field_levels: 6,
        field_finest: 64,
        field_samples: 1 << 12,
        head_steps: 80,
        batch: 512,
        cubes: 16,
        cube_res: 4,
        psh_res: 48,
        pseudo_views: 0,
        ..BakeRecipe::default()
    };
    let mut progress = Recorder::default();
    let baked = bake(&data, "tiny diffuse", &recipe, None, &mut progress).expect("bake");
    assert_eq!(progress.stages, ["radiance field", "density cubes", "i-NOLF heads"]);
    assert_eq!(progress.summaries.len(), 6, "{:?}", progress.summaries);
    // A diffuse scene is opaque: the bake takes the median depth and says why.
    assert!(
        progress.summaries[2].starts_with("hit points: the median depth (where the ray's opacity crosses one half) ("),
        "{:?}",
        progress.summaries
    );
    assert!(progress.field_handed_over);

    let meta: serde_json::Value = serde_json::from_str(&baked.asset.meta).expect("meta is JSON");
    assert_eq!(meta["bake"]["field_steps"], 60, "{meta}");
    assert!(meta["bake"]["layered_share"].as_f64().is_some_and(|s| s < 0.5), "{meta}");
    assert_eq!(meta["hit_rule"], "median_depth", "{meta}");
    let kernel = InolfKernel::from_asset(baked.asset).expect("kernel");
    let (mut baked_db, mut empty_db) = (0.0, 0.0);
    for view in &data.views {
        let camera = Camera::from_fov_x(32, 32, data.camera_angle_x, view.camera_to_world).expect("camera");
        let (out, _) = kernel.render_pixels(&camera, &all_pixels(&camera)).expect("render");
        let image = frame_to_image(32, 32, &out).expect("image");
        let empty = frame_to_image(32, 32, &nephele_kernels::kernel::PixelResults::with_len(32 * 32)).expect("empty");
        baked_db += psnr(&image, &view.image, [1.0; 3]).expect("psnr");
        empty_db += psnr(&empty, &view.image, [1.0; 3]).expect("psnr");
    }
    let n = data.views.len() as f64;
    eprintln!("bake of 16 views: {:.2} dB against {:.2} dB for an empty frame", baked_db / n, empty_db / n);
    assert!(baked_db / n > empty_db / n + 5.0, "{} vs {}", baked_db / n, empty_db / n);

    // Again from the returned field, with pseudo-views of it for the heads and decoupled decay
    // of their features (recorded in the asset); a decay out of range is refused first.
    let mut again = Recorder::default();
    let bad = BakeRecipe { psh_decay: f32::NAN, ..recipe.clone() };
    assert!(matches!(bake(&data, "x", &bad, None, &mut again), Err(BakeError::Decay { name: "psh_decay", .. })));
    let bad = BakeRecipe { head_table_log2: 40, ..recipe.clone() };
    assert!(matches!(bake(&data, "x", &bad, None, &mut again), Err(BakeError::Model(_))));
    assert!(again.stages.is_empty(), "refused before any stage: {:?}", again.stages);
    let recipe = BakeRecipe { pseudo_views: 4, psh_decay: 0.5, grid_decay: 0.5, ..recipe };
    let rebaked = bake(&data, "tiny diffuse", &recipe, Some(baked.field), &mut again).expect("bake from the field");
    assert_eq!(again.stages, ["density cubes", "pseudo-views", "i-NOLF heads"]);
    assert!(!again.field_handed_over);
    assert!(again.summaries.iter().any(|s| s.starts_with("pseudo-views: 4 rendered")), "{:?}", again.summaries);
    let meta: serde_json::Value = serde_json::from_str(&rebaked.asset.meta).expect("meta is JSON");
    assert_eq!((&meta["bake"]["field_steps"], &meta["bake"]["pseudo_views"]), (&0.into(), &4.into()), "{meta}");
    assert_eq!(meta["bake"]["psh_decay"], 0.5, "{meta}");
}

/// Corrupt training pixels (issue 18): the heads never train on a dropped pixel (a target of
/// NaN), so a few of them leave every loss and parameter finite; `training_views` counts what
/// it clamped and dropped.
#[test]
fn dropped_pixels_are_never_trained() {
    let cubes = sphere_cubes();
    let mut views = views();
    for v in &mut views {
        for (i, t) in v.target.iter_mut().enumerate() {
            if i % 97 == 0 {
                *t = crate::targets::DROPPED;
            }
        }
    }
    let hits = collect_hit_points(&cubes, &views, 1);
    let psh = PshEncoding::from_points(&hits, bounds().min, 2.0 / 31.0, 32, 4, &PshOptions::coherent()).expect("psh");
    let mut model = InolfModel::new(small_shape(), bounds(), psh, 3).expect("model");
    let options = TrainOptions { steps: 60, batch: 512, ..TrainOptions::default() };
    let mut losses = Vec::new();
    let report = train(&mut model, &cubes, &views, &options, &mut |_, loss| losses.push(loss)).expect("train");
    assert!(report.smoothed_loss.is_finite() && losses.iter().all(|l| l.is_finite()), "{report:?}");
    assert!(model.specular.params().iter().chain(model.diffuse.params()).all(|p| p.is_finite()));
    assert!(model.psh.features.iter().chain(model.grid.params()).all(|p| p.is_finite()));

    // The dataset path: clamped and dropped pixels counted, targets in range.
    let image = nephele_imaging::image::RgbaImage::from_fn(8, 8, |x, y| match (x, y) {
        (0, 0) => [f32::NAN, 0.0, 0.0, 1.0],
        (1, 0) => [2.0, 0.5, 0.5, 1.0],
        _ => [0.5, 0.5, 0.5, 1.0],
    });
    let dataset = crate::dataset::Dataset {
        camera_angle_x: 0.7,
        views: vec![crate::dataset::View {
            name: "r_0".into(),
            camera_to_world: glam::Mat4::from_translation(Vec3::new(0.0, 0.0, 3.0)),
            image,
            depth: None,
        }],
    };
    let (views, check) = super::train::training_views(&dataset).expect("views");
    assert_eq!((check.pixels, check.clamped, check.dropped), (64, 1, 1));
    assert!(crate::targets::is_dropped(&views[0].target[0]));
    assert!(views[0].target[1..].iter().flatten().all(|v| (0.0..=1.0).contains(v)));
    assert!(check.verdict().is_err(), "1 in 64 is more than 1 %");
}

/// The bake's choice of hit rule on the shares measured on the built-in objects (64 views of
/// 128x128 each): only the glass shell is see-through.
#[test]
fn only_mostly_layered_objects_are_baked_see_through() {
    use super::train::choose_hit_rule;
    assert_eq!(choose_hit_rule(0.879), HitRule::SEE_THROUGH);
    for opaque in [0.093, 0.018, 0.0, 0.5, f64::NAN] {
        assert_eq!(choose_hit_rule(opaque), HitRule::MedianDepth, "{opaque}");
    }
}
