//! `nephele bench share`: rays rendered when adjacent views share pixels by reprojection
//! (`nephele-share`), against rendering every view in full, and what it costs in quality, in
//! one run (issue 16).
//!
//! Each scenario is built around an *anchor* view (a held-out dataset view, whose image is the
//! ground truth, or an orbit view without a dataset) so that the anchor itself is one of the
//! shared views: the quality lost to sharing is measured against the ground truth as well as
//! against the view's own full render.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use glam::{Mat4, Vec3};
use nephele_geometry::camera::{Camera, quilt_rig};
use nephele_geometry::{Bounds, PixelResults, all_pixels};
use nephele_imaging::image::RgbaImage;
use nephele_imaging::metrics::psnr;
use nephele_kernels::assets::{LoadOptions, load_by_magic};
use nephele_kernels::kernel::{RayKernel, frame_to_image};
use nephele_share::{Filter, Reprojection, Settings, Source, reproject};
use serde_json::json;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct ShareArgs {
    /// The asset rendered (any format a worker loads: .nolf, .ngp).
    #[arg(long)]
    asset: PathBuf,
    /// Dataset folder whose held-out views anchor the scenarios and are their ground truth
    /// (the lego: `--dataset ../shared/data/lego`). Without it, orbit views of `--size`
    /// anchor them and only the loss against full renders is reported.
    #[arg(long)]
    dataset: Option<PathBuf>,
    #[arg(long, default_value = "train")]
    split: String,
    #[arg(long, default_value_t = 4)]
    downscale: u32,
    /// The views `nephele bake --holdout-every N` left out anchor the scenarios.
    #[arg(long, default_value_t = 8)]
    holdout_every: usize,
    /// Anchor views (every scenario runs around each).
    #[arg(long, default_value_t = 4)]
    views: usize,
    /// Anchor view size without a dataset.
    #[arg(long, default_value = "200x200", value_parser = nephele_geometry::camera::parse_size, value_name = "WxH")]
    size: (u32, u32),
    /// Largest reuse angle at a surface point, degrees (`nephele_share::Settings`).
    #[arg(long, default_value_t = Settings::default().max_angle_deg)]
    max_angle: f32,
    /// Reused pixels next to a hole that are rendered anyway, in pixels.
    #[arg(long, default_value_t = Settings::default().edge_band)]
    edge_band: u32,
    /// Reconstruction between source pixels.
    #[arg(long, value_enum, default_value = "catmull-rom")]
    filter: FilterChoice,
    /// Largest colour difference (linear, per channel) among the source pixels around a point
    /// for it to be reused; `inf`: no limit.
    #[arg(long, default_value_t = Settings::default().max_contrast)]
    max_contrast: f32,
    /// Largest reuse angles tried on the orbiting users (a sweep table); `none` skips it.
    #[arg(long, default_value = "2,4,6,8,12", value_parser = parse_values)]
    sweep_angle: Values,
    /// Largest colour contrasts tried on every scenario (a sweep table; `inf`: no limit);
    /// `none` skips it.
    #[arg(long, default_value = "inf,0.5,0.3,0.2,0.1", value_parser = parse_values)]
    sweep_contrast: Values,
    /// Also write the rows as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Debug, Clone)]
pub struct Values(Vec<f32>);

/// `--filter`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FilterChoice {
    Bilinear,
    CatmullRom,
}

/// Comma-separated non-negative numbers (`inf` allowed); `none` or "" for none.
fn parse_values(text: &str) -> Result<Values, String> {
    if text == "none" || text.is_empty() {
        return Ok(Values(Vec::new()));
    }
    text.split(',')
        .map(|t| match t.trim().parse::<f32>() {
            Ok(a) if a >= 0.0 => Ok(a),
            _ => Err(format!("'{t}' is not a number >= 0")),
        })
        .collect::<Result<Vec<_>, _>>()
        .map(Values)
}

/// Interpupillary distance of the stereo scenario, world units (metres; the lego's cameras
/// stand about 4 m from it).
const IPD: f32 = 0.064;
/// The quilt: a 45-view Looking Glass rig over a 40-degree cone, every 8th view (and the last)
/// rendered in full, the others shared from their two neighbouring full views.
use nephele_geometry::camera::{QUILT_VIEW_CONE_DEG as QUILT_CONE_DEG, QUILT_VIEWS};
const QUILT_KEY_EVERY: usize = 8;
/// Consecutive frames: a user orbiting at 45 degrees/s seen at 30 frames/s; every
/// `FRAME_KEY_EVERY`th frame is rendered in full and the frames after it take from it
/// (resampling a resampled frame blurs it further each time).
const FRAME_STEP_DEG: f32 = 1.5;
const FRAMES: usize = 8;
const FRAME_KEY_EVERY: usize = 4;

/// One anchor view and, with a dataset, its ground-truth image.
struct Anchor {
    camera: Camera,
    truth: Option<RgbaImage>,
}

/// A set of views and the order in which they are served: each view is rendered in full
/// (no sources) or assembled from the views listed, which come earlier in `order`.
struct Scenario {
    name: String,
    cameras: Vec<Camera>,
    /// `(view, sources)` in serving order.
    order: Vec<(usize, Vec<usize>)>,
    /// The view that is the anchor (scored against the ground truth).
    anchor_view: usize,
}

/// `camera` turned by `degrees` about the world's vertical (+Z) axis through `centre`.
fn orbited(camera: &Camera, centre: Vec3, degrees: f32) -> Result<Camera> {
    let turn =
        Mat4::from_translation(centre) * Mat4::from_rotation_z(degrees.to_radians()) * Mat4::from_translation(-centre);
    moved(camera, turn * camera.camera_to_world())
}

fn moved(camera: &Camera, camera_to_world: Mat4) -> Result<Camera> {
    let (fx, fy, cx, cy) = camera.intrinsics();
    Ok(Camera::from_intrinsics(camera.width(), camera.height(), fx, fy, cx, cy, camera_to_world)?)
}

fn scenarios(anchor: &Camera, centre: Vec3) -> Result<Vec<Scenario>> {
    let mut all = Vec::new();
    // The right eye is the anchor; the left eye is rendered in full.
    let left = moved(anchor, anchor.camera_to_world() * Mat4::from_translation(Vec3::new(-IPD, 0.0, 0.0)))?;
    all.push(Scenario {
        name: "stereo (right eye from left)".into(),
        cameras: vec![left, *anchor],
        order: vec![(0, vec![]), (1, vec![0])],
        anchor_view: 1,
    });
    for spacing in [2.0f32, 5.0, 10.0] {
        // Four users `spacing` apart; the anchor is the second; each takes from those served
        // before it.
        let cameras = (-1..3).map(|k| orbited(anchor, centre, k as f32 * spacing)).collect::<Result<Vec<_>>>()?;
        let order = (0..4).map(|v| (v, (0..v).collect())).collect();
        all.push(Scenario { name: format!("4 users {spacing} deg apart"), cameras, order, anchor_view: 1 });
    }
    let focal_distance = (anchor.position() - centre).length();
    let cameras = quilt_rig(anchor, QUILT_VIEWS, QUILT_CONE_DEG.to_radians(), focal_distance)?;
    let mut keys: Vec<usize> = (0..QUILT_VIEWS).step_by(QUILT_KEY_EVERY).collect();
    if keys.last() != Some(&(QUILT_VIEWS - 1)) {
        keys.push(QUILT_VIEWS - 1);
    }
    let mut order: Vec<(usize, Vec<usize>)> = keys.iter().map(|&k| (k, vec![])).collect();
    for v in (0..QUILT_VIEWS).filter(|v| !keys.contains(v)) {
        let before = keys.iter().rev().find(|&&k| k < v).copied();
        let after = keys.iter().find(|&&k| k > v).copied();
        order.push((v, before.into_iter().chain(after).collect()));
    }
    all.push(Scenario {
        name: format!("{QUILT_VIEWS}-view quilt ({QUILT_CONE_DEG} deg, 1 in {QUILT_KEY_EVERY} full)"),
        cameras,
        order,
        anchor_view: QUILT_VIEWS / 2,
    });
    // Consecutive frames ending at the anchor, each from the last frame rendered in full.
    let cameras = (0..FRAMES)
        .map(|f| orbited(anchor, centre, (f as f32 - (FRAMES - 1) as f32) * FRAME_STEP_DEG))
        .collect::<Result<Vec<_>>>()?;
    let key = |f: usize| f - f % FRAME_KEY_EVERY;
    let order = (0..FRAMES).map(|f| (f, if key(f) == f { vec![] } else { vec![key(f)] })).collect();
    all.push(Scenario {
        name: format!("{FRAMES} frames of one user ({FRAME_STEP_DEG} deg/frame, 1 in {FRAME_KEY_EVERY} full)"),
        cameras,
        order,
        anchor_view: FRAMES - 1,
    });
    Ok(all)
}

/// The sums over every anchor of one scenario at one setting.
#[derive(Default)]
struct Tally {
    views: usize,
    full_rays: usize,
    in_bounds_rays: usize,
    rendered_rays: usize,
    /// PSNR of each shared view against its own full render.
    shared_psnr: Vec<f64>,
    /// dB lost on the anchor against the ground truth (full minus shared).
    truth_loss: Vec<f64>,
    reprojection_s: f64,
    full_render_s: f64,
    shared_views: usize,
}

/// A view rendered in full, once per scenario: the frame, the seconds it took, and how many of
/// its pixels' rays enter the asset's box.
struct FullRender {
    frame: PixelResults,
    seconds: f64,
    in_bounds: usize,
}

/// Runs one scenario at `settings`: the served frames, counted against `full`.
fn serve(
    kernel: &dyn RayKernel,
    bounds: &Bounds,
    scenario: &Scenario,
    full: &[FullRender],
    truth: Option<&RgbaImage>,
    settings: &Settings,
    tally: &mut Tally,
) -> Result<()> {
    let mut served: Vec<Option<PixelResults>> = vec![None; scenario.cameras.len()];
    for (view, sources) in &scenario.order {
        let camera = &scenario.cameras[*view];
        let (w, h) = (camera.width(), camera.height());
        let pixels = (w * h) as usize;
        tally.views += 1;
        tally.full_rays += pixels;
        tally.in_bounds_rays += full[*view].in_bounds;
        if sources.is_empty() {
            tally.rendered_rays += pixels;
            served[*view] = Some(full[*view].frame.clone());
            continue;
        }
        let source_list: Vec<Source<'_>> = sources
            .iter()
            .map(|&s| Source { camera: &scenario.cameras[s], frame: served[s].as_ref().expect("served earlier") })
            .collect();
        let start = Instant::now();
        let mut shared: Reprojection = reproject(camera, bounds, &source_list, settings)?;
        tally.reprojection_s += start.elapsed().as_secs_f64();
        tally.full_render_s += full[*view].seconds;
        tally.shared_views += 1;
        let holes = shared.pixels_to_render();
        tally.rendered_rays += holes.len();
        if !holes.is_empty() {
            let (rendered, _) = kernel.render_pixels(camera, &holes)?;
            shared.fill(&holes, &rendered)?;
        }
        let image = frame_to_image(w, h, &shared.frame).context("shared frame")?;
        let reference = frame_to_image(w, h, &full[*view].frame).context("full frame")?;
        tally.shared_psnr.push(psnr(&image, &reference, [1.0; 3])?.min(99.0));
        if let (true, Some(truth)) = (*view == scenario.anchor_view, truth) {
            tally.truth_loss.push(psnr(&reference, truth, [1.0; 3])? - psnr(&image, truth, [1.0; 3])?);
        }
        served[*view] = Some(shared.frame);
    }
    Ok(())
}

/// The live path of a scenario's views (issue 16): the scheduler (live defaults, derived views
/// on) plans one frame of a session with these views; each batch is rendered and its derived
/// views made exactly as a worker does (`nephele_worker::derive::derive_view`), and each view
/// is assembled from its task's results and compared with its full render.
fn serve_live(
    kernel: &dyn RayKernel,
    bounds: &Bounds,
    cameras: &[Camera],
    full: &[FullRender],
    settings: &Settings,
    tally: &mut Tally,
) -> Result<()> {
    use nephele_scheduler::{Action, ObjectId, ObjectInfo, PartSource, Scheduler, SchedulerConfig, SessionSpec, Time};
    use std::collections::HashMap;
    let mut scheduler = Scheduler::new(SchedulerConfig::default())?;
    let object = ObjectId(1);
    scheduler.register_object(
        object,
        ObjectInfo { bounds: *bounds, occupancy: None, cost_per_ray: 1.0, full_frame: false },
    )?;
    scheduler.add_worker(nephele_scheduler::WorkerId(1), 1e9, Time::ZERO)?;
    let session = scheduler.open_session(SessionSpec { target_fps: 1.0, objects: vec![object] }, Time::ZERO)?;
    scheduler.pose(session, cameras, Time::ZERO)?;
    let mut results: HashMap<nephele_scheduler::TaskId, Vec<(Vec<u32>, PixelResults)>> = HashMap::new();
    let mut derive_s = 0.0;
    let mut parts = None;
    let mut now = Time::ZERO;
    for _ in 0..10_000 {
        for action in scheduler.tick(now) {
            match action {
                Action::Dispatch { worker, batch } => {
                    let pixels = batch.pixels.indices();
                    let (rendered, _) = kernel.render_pixels(&batch.camera, &pixels)?;
                    tally.rendered_rays += pixels.len();
                    for derived in &batch.derived {
                        let asked = derived.pixels.indices();
                        let start = Instant::now();
                        let made = nephele_worker::derive::derive_view(
                            kernel,
                            &batch.camera,
                            &pixels,
                            &rendered,
                            &derived.camera,
                            &asked,
                            settings,
                        )?;
                        derive_s += start.elapsed().as_secs_f64();
                        tally.rendered_rays += made.rendered;
                        results.entry(derived.task).or_default().push((asked, made.results));
                    }
                    results.entry(batch.task).or_default().push((pixels, rendered));
                    scheduler.batch_done(worker, batch.id, now)?;
                }
                Action::FrameComplete { parts: done, .. } => parts = Some(done),
                _ => {}
            }
        }
        if parts.is_some() {
            break;
        }
        now = now + std::time::Duration::from_millis(1);
    }
    let parts = parts.context("the scheduler never completed the frame")?;
    for (view, camera) in cameras.iter().enumerate() {
        let (w, h) = (camera.width(), camera.height());
        tally.views += 1;
        tally.full_rays += (w * h) as usize;
        let Some(part) = parts.iter().find(|p| p.view as usize == view) else { continue };
        // The live service without derived views renders each view's covered pixels (the
        // TaskAssigner's estimate): the second ratio of a live row is against that.
        tally.in_bounds_rays += part.rays as usize;
        if part.source != PartSource::Derived {
            continue;
        }
        let mut frame = PixelResults::with_len((w * h) as usize);
        for (pixels, values) in results.get(&part.task).map(Vec::as_slice).unwrap_or_default() {
            scatter_into(&mut frame, pixels, values);
        }
        tally.shared_views += 1;
        tally.full_render_s += full[view].seconds;
        let image = frame_to_image(w, h, &frame).context("derived frame")?;
        let reference = frame_to_image(w, h, &full[view].frame).context("full frame")?;
        tally.shared_psnr.push(psnr(&image, &reference, [1.0; 3])?.min(99.0));
    }
    tally.reprojection_s += derive_s;
    Ok(())
}

/// Writes `values` (one per index of `pixels`) into the whole-image `frame`.
fn scatter_into(frame: &mut PixelResults, pixels: &[u32], values: &PixelResults) {
    for (k, &p) in pixels.iter().enumerate() {
        let p = p as usize;
        (frame.color[p], frame.opacity[p], frame.depth[p]) = (values.color[k], values.opacity[k], values.depth[k]);
    }
}

/// The index of `table`'s row called `name`, added empty if missing.
fn row(table: &mut Vec<(String, Tally)>, name: String) -> usize {
    match table.iter().position(|(n, _)| *n == name) {
        Some(i) => i,
        None => {
            table.push((name, Tally::default()));
            table.len() - 1
        }
    }
}

/// The live path of a user's consecutive frames (`ReuseLimits::previous_frames`): each
/// frame's batch planned, taken from the previous full render or rendered in full and kept,
/// exactly as a worker does (`nephele_worker::temporal`, the master's default count), and
/// each frame taken from a previous render compared with its own full render.
fn serve_previous_frames(
    kernel: &dyn RayKernel,
    bounds: &Bounds,
    cameras: &[Camera],
    full: &[FullRender],
    settings: &Settings,
    tally: &mut Tally,
) -> Result<()> {
    use nephele_worker::derive::{Absent, derive_view_with};
    use nephele_worker::temporal::{Plan, Previous, PreviousRenders};
    let renders = PreviousRenders::new(usize::MAX);
    let count = nephele_proto::ReuseLimits::DEFAULT_PREVIOUS_FRAMES;
    let centre = bounds.center();
    let slot = (1, "bench");
    let band_rows = nephele_scheduler::SchedulerConfig::default().band_rows;
    for (view, camera) in cameras.iter().enumerate() {
        let (w, h) = (camera.width(), camera.height());
        tally.views += 1;
        tally.full_rays += (w * h) as usize;
        // The batch the live service sends: the TaskAssigner's covered pixels, as one batch
        // (whole rows of its task).
        let Some(coverage) = nephele_scheduler::assign::estimate_coverage(camera, bounds, None, band_rows) else {
            continue;
        };
        let pixels = coverage.pixels.indices();
        tally.in_bounds_rays += pixels.len();
        match renders.plan(slot, camera, centre, settings.max_angle_deg, count) {
            Plan::Reuse(source) => {
                let start = Instant::now();
                let from = (&source.camera, source.pixels.as_slice(), &source.results);
                let made = derive_view_with(kernel, from, source.absent, camera, &pixels, settings)?;
                tally.reprojection_s += start.elapsed().as_secs_f64();
                tally.full_render_s += full[view].seconds;
                tally.rendered_rays += made.rendered;
                tally.shared_views += 1;
                let mut frame = PixelResults::with_len((w * h) as usize);
                scatter_into(&mut frame, &pixels, &made.results);
                let image = frame_to_image(w, h, &frame).context("reused frame")?;
                let reference = frame_to_image(w, h, &full[view].frame).context("full frame")?;
                tally.shared_psnr.push(psnr(&image, &reference, [1.0; 3])?.min(99.0));
            }
            Plan::Render(_) => {
                tally.rendered_rays += pixels.len();
                let source = &full[view].frame;
                let mut results = PixelResults::with_len(pixels.len());
                for (k, &p) in pixels.iter().enumerate() {
                    let p = p as usize;
                    (results.color[k], results.opacity[k], results.depth[k]) =
                        (source.color[p], source.opacity[p], source.depth[p]);
                }
                let kept = Previous { camera: *camera, pixels, results, absent: Absent::Empty };
                renders.remember(slot, kept, centre, settings.max_angle_deg, count);
            }
        }
    }
    Ok(())
}

fn mean(values: &[f64]) -> Option<f64> {
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

pub fn run(args: ShareArgs, progress: &dyn Progress) -> Result<()> {
    let kernel = load_by_magic(&args.asset, &LoadOptions::default())
        .with_context(|| format!("loading {}", args.asset.display()))?;
    let bounds = kernel.bounds();
    let centre = bounds.center();
    let anchors = anchors(&args, &bounds)?;
    let filter = match args.filter {
        FilterChoice::Bilinear => Filter::Bilinear,
        FilterChoice::CatmullRom => Filter::CatmullRom,
    };
    let base = Settings {
        max_angle_deg: args.max_angle,
        edge_band: args.edge_band,
        filter,
        max_contrast: args.max_contrast,
        ..Settings::default()
    };
    base.validate()?;
    let mut table: Vec<(String, Tally)> = Vec::new();
    let mut sweep: Vec<((String, String), Tally)> = Vec::new();
    let first = scenarios(&anchors[0].camera, centre)?;
    let frames: usize = first.iter().map(|s| s.cameras.len()).sum::<usize>() * anchors.len();
    let bar = progress.bar(frames as u64, "full renders", "frames");
    for anchor in &anchors {
        for scenario in scenarios(&anchor.camera, centre)? {
            let mut full = Vec::with_capacity(scenario.cameras.len());
            for camera in &scenario.cameras {
                let start = Instant::now();
                let (frame, _) = kernel.render_pixels(camera, &all_pixels(camera))?;
                let seconds = start.elapsed().as_secs_f64();
                let in_bounds = reproject(camera, &bounds, &[], &base)?.counts().in_bounds();
                full.push(FullRender { frame, seconds, in_bounds });
                bar.inc(1);
            }
            let k = row(&mut table, scenario.name.clone());
            serve(kernel.as_ref(), &bounds, &scenario, &full, anchor.truth.as_ref(), &base, &mut table[k].1)?;
            if scenario.name.starts_with("stereo") || scenario.name.contains("quilt") {
                let name = format!("live path: {}", scenario.name.split(" (").next().unwrap_or(&scenario.name));
                let k = row(&mut table, name);
                serve_live(kernel.as_ref(), &bounds, &scenario.cameras, &full, &base, &mut table[k].1)?;
            }
            if scenario.name.contains("frames of one user") {
                let k = row(&mut table, "live path: frames of one user".to_string());
                serve_previous_frames(kernel.as_ref(), &bounds, &scenario.cameras, &full, &base, &mut table[k].1)?;
            }
            let mut variants: Vec<(String, Settings)> = Vec::new();
            if scenario.name.starts_with("4 users") {
                let angles = args.sweep_angle.0.iter();
                variants.extend(angles.map(|&a| (format!("max angle {a} deg"), Settings { max_angle_deg: a, ..base })));
            }
            let contrasts = args.sweep_contrast.0.iter();
            variants.extend(contrasts.map(|&c| (format!("max contrast {c}"), Settings { max_contrast: c, ..base })));
            for (label, settings) in variants {
                let key = (scenario.name.clone(), label);
                let row = match sweep.iter().position(|(k, _)| *k == key) {
                    Some(i) => i,
                    None => {
                        sweep.push((key, Tally::default()));
                        sweep.len() - 1
                    }
                };
                let truth = anchor.truth.as_ref();
                serve(kernel.as_ref(), &bounds, &scenario, &full, truth, &settings, &mut sweep[row].1)?;
            }
        }
    }
    bar.finish_and_clear();
    let camera = &anchors[0].camera;
    println!(
        "asset {} ({}), {} anchor views of {}x{}{}; settings: max angle {} deg, depth tolerance {} px, opaque >= {}, edge band {}, {:?}, max contrast {}",
        args.asset.display(),
        kernel.kind(),
        anchors.len(),
        camera.width(),
        camera.height(),
        if anchors[0].truth.is_some() { " with ground truth" } else { "" },
        base.max_angle_deg,
        base.depth_tolerance_px,
        base.opaque,
        base.edge_band,
        base.filter,
        base.max_contrast
    );
    println!(
        "rays rendered: shared against every view in full (all pixels; in-bounds: pixels whose ray enters the asset's box; \
         for the live-path rows: each view's covered pixels, what the service renders without derived views); \
         time: reprojection (live rows: the worker's whole derived view, leftovers included) against full renders"
    );
    println!(
        "| scenario | views | rays rendered / full | / full in-bounds | shared views: PSNR vs own full render, mean (min) | anchor: dB lost vs ground truth | reprojection / full render time |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    let mut json_rows = Vec::new();
    for (name, tally) in &table {
        print_row(name, tally);
        json_rows.push(row_json(name, None, tally));
    }
    if !sweep.is_empty() {
        println!("\nsweeps: one setting changed at a time (same full renders)");
        println!(
            "| scenario | setting | rays rendered / full | shared views: PSNR vs own full render, mean (min) | anchor: dB lost vs ground truth |"
        );
        println!("| --- | --- | --- | --- | --- |");
        let mut rows: Vec<_> = sweep.iter().collect();
        rows.sort_by_key(|((_, label), _)| label.starts_with("max contrast"));
        for ((name, label), tally) in rows {
            println!(
                "| {name} | {label} | {:.1} % | {} | {} |",
                100.0 * tally.rendered_rays as f64 / tally.full_rays as f64,
                psnr_cell(tally),
                loss_cell(tally)
            );
            json_rows.push(row_json(name, Some(label), tally));
        }
    }
    if let Some(path) = args.json {
        std::fs::write(&path, serde_json::to_string_pretty(&json_rows)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

fn psnr_cell(tally: &Tally) -> String {
    match mean(&tally.shared_psnr) {
        Some(m) => format!("{m:.2} dB ({:.2})", tally.shared_psnr.iter().copied().fold(f64::INFINITY, f64::min)),
        None => "-".into(),
    }
}

fn loss_cell(tally: &Tally) -> String {
    match mean(&tally.truth_loss) {
        Some(m) => {
            let worst = tally.truth_loss.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            format!("{m:.3} dB (worst {worst:.3})")
        }
        None => "-".into(),
    }
}

fn print_row(name: &str, tally: &Tally) {
    let ratio = if tally.full_render_s > 0.0 { tally.reprojection_s / tally.full_render_s } else { 0.0 };
    println!(
        "| {name} | {} | {:.1} % | {:.1} % | {} | {} | {:.2} |",
        tally.views,
        100.0 * tally.rendered_rays as f64 / tally.full_rays as f64,
        100.0 * tally.rendered_rays as f64 / tally.in_bounds_rays.max(1) as f64,
        psnr_cell(tally),
        loss_cell(tally),
        ratio
    );
}

fn row_json(name: &str, setting: Option<&str>, tally: &Tally) -> serde_json::Value {
    json!({
        "scenario": name,
        "setting": setting,
        "views": tally.views,
        "full_rays": tally.full_rays,
        "in_bounds_rays": tally.in_bounds_rays,
        "rendered_rays": tally.rendered_rays,
        "shared_psnr_db": tally.shared_psnr,
        "truth_loss_db": tally.truth_loss,
        "reprojection_to_full_render_time": if tally.full_render_s > 0.0 { tally.reprojection_s / tally.full_render_s } else { 0.0 },
    })
}

/// The anchor views: held-out dataset views with their images, or orbit views of the box.
fn anchors(args: &ShareArgs, bounds: &Bounds) -> Result<Vec<Anchor>> {
    let count = args.views.max(1);
    if let Some(dir) = &args.dataset {
        let mut data = nephele_train::dataset::load_split(dir, &args.split, args.downscale)?;
        if args.holdout_every > 1 {
            data.views = nephele_train::dataset::split_holdout(std::mem::take(&mut data.views), args.holdout_every).1;
        }
        anyhow::ensure!(!data.views.is_empty(), "no view of {} to anchor the scenarios", dir.display());
        data.views.truncate(count);
        return data
            .views
            .into_iter()
            .map(|v| {
                let camera =
                    Camera::from_fov_x(v.image.width(), v.image.height(), data.camera_angle_x, v.camera_to_world)?;
                Ok(Anchor { camera, truth: Some(v.image) })
            })
            .collect();
    }
    let (w, h) = args.size;
    let fov_y = 0.7f32;
    let radius = 0.5 * bounds.size().length();
    let distance = 1.3 * radius / (0.5 * fov_y).tan();
    (0..count)
        .map(|k| {
            let azimuth = (k as f32 * 360.0 / count as f32 + 20.0).to_radians();
            let elevation = 25.0f32.to_radians();
            let direction =
                Vec3::new(azimuth.cos() * elevation.cos(), azimuth.sin() * elevation.cos(), elevation.sin());
            let camera =
                Camera::look_at(w, h, fov_y, bounds.center() + distance * direction, bounds.center(), Vec3::Z)?;
            Ok(Anchor { camera, truth: None })
        })
        .collect()
}
