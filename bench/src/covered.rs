//! `nephele bench covered`: what the environment kernel saves by not lighting the room behind
//! the objects' solid matter (issue 13, "pixels the objects cover fully are not shaded"), and
//! what it costs the pixels that stay visible.
//!
//! The room scene as the master serves it (`Catalog::builtin`, its `occluders`), from views
//! orbiting the scene's first view as a scripted user does: per view the kernel with and
//! without the knot's solid cells, alternated, flat and as a stereo pair. Counts: the share
//! of G-buffer samples hidden, against the share of pixels whose centre ray meets the knot's
//! mesh. Error: PSNR of the served room with occluders against without, over the pixels the
//! knot does not cover (their G-buffer samples are the same; only the network's
//! neighbourhood differs, and the knot's shadow darkens the room), and over those of them
//! within 8 pixels of the knot; the share of them the shadow darkens.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, ensure};
use glam::Vec3;
use nephele_geometry::camera::{Camera, stereo_pair};
use nephele_imaging::image::{RgbaImage, linear_to_srgb};
use nephele_kernels::environment::{GiKernel, GiServeSettings};
use nephele_kernels::kernel::{RayKernel, all_pixels};
use nephele_master::scenes::{Catalog, ROOM_VIEW};
use nephele_nn::PixelMask;
use nephele_pathtracer::bvh::{Bvh, TraversalStats};
use nephele_pathtracer::material::luminance;
use nephele_pathtracer::scenes;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct CoveredArgs {
    /// The environment's single-eye model as `nephele up` serves it (its `.stereo.ngi` twin
    /// beside it is used for the stereo rows).
    #[arg(long)]
    model: PathBuf,
    /// The room scene (`room-day` or `room-night`, matching the model).
    #[arg(long, default_value = "room-day")]
    scene: String,
    /// View size.
    #[arg(long, default_value = "640x480", value_parser = nephele_geometry::camera::parse_size)]
    size: (u32, u32),
    /// Views around the orbit.
    #[arg(long, default_value_t = 6)]
    views: usize,
    /// Timed repetitions of each (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Write each view's served room without and with the objects' solid matter (hidden
    /// pixels, shadows) as `view-K-empty.png` and `view-K-objects.png` into this folder.
    #[arg(long)]
    images: Option<PathBuf>,
}

/// PSNR of `a` against `b` (linear, clamped to [0, 1]) over the pixels `keep` selects.
fn psnr(a: &[[f32; 3]], b: &[[f32; 3]], keep: impl Fn(usize) -> bool) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (_, (x, y)) in a.iter().zip(b).enumerate().filter(|(i, _)| keep(*i)) {
        for c in 0..3 {
            let d = f64::from(x[c].clamp(0.0, 1.0) - y[c].clamp(0.0, 1.0));
            sum += d * d;
        }
        n += 3;
    }
    10.0 * (1.0 / (sum / n.max(1) as f64).max(1e-12)).log10()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn run(args: CoveredArgs, progress: &dyn Progress) -> Result<()> {
    let catalog = Catalog::builtin().context("the scene catalog")?;
    let scene = catalog.scene(&args.scene).with_context(|| format!("no scene {:?}", args.scene))?;
    let environment = scene
        .objects
        .iter()
        .filter_map(|id| catalog.object(*id))
        .find(|o| catalog.is_environment(&o.asset))
        .with_context(|| format!("{} has no environment", args.scene))?;
    let occluders = catalog.occluders(environment, &[args.scene.as_str()]);
    ensure!(!occluders.is_empty(), "nothing in {} hides the room", args.scene);
    let objects: Vec<_> = scene
        .objects
        .iter()
        .filter_map(|id| catalog.object(*id))
        .filter(|o| !catalog.is_environment(&o.asset))
        .map(|o| {
            let mesh = scenes::builtin(&o.asset).map(|s| s.scene.mesh).context("a built-in object")?;
            Ok((Bvh::build(&mesh), o.translation - environment.translation))
        })
        .collect::<Result<_>>()?;
    let kernel = GiKernel::load(&args.model, GiServeSettings::default())
        .with_context(|| format!("loading {}", args.model.display()))?;
    // The same models running the network over the covered pixels too, as before the mask.
    let whole_network = GiKernel::load(&args.model, GiServeSettings { shade_covered: true, ..Default::default() })
        .with_context(|| format!("loading {}", args.model.display()))?;
    let solid: u64 = occluders.iter().map(|g| g.solid_count()).sum();
    println!(
        "{}: {} occluder(s), {solid} solid cells; served at {:?}, network on {}; stereo model: {}",
        args.scene,
        occluders.len(),
        GiServeSettings::default(),
        kernel.network_device(),
        kernel.has_stereo()
    );
    let (w, h) = args.size;
    let view = ROOM_VIEW;
    let (target, eye) = (Vec3::from(view.target), Vec3::from(view.eye));
    let radius = (eye - target).truncate().length();
    let start = (eye - target).y.atan2((eye - target).x);
    if let Some(dir) = &args.images {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    // ms: plain and behind, flat then stereo, then behind with the network over every pixel
    // (flat, stereo).
    let mut totals = [0.0f64; 6];
    let bar = progress.bar(args.views.max(1) as u64, "views", "views");
    for k in 0..args.views.max(1) {
        let a = start + k as f32 * std::f32::consts::TAU / args.views.max(1) as f32;
        let at = Vec3::new(target.x + radius * a.cos(), target.y + radius * a.sin(), eye.z);
        let camera = Camera::look_at(w, h, view.fov_y_deg.to_radians(), at, target, Vec3::Z)?;
        let all = all_pixels(&camera);
        // Pixels whose centre ray meets an object's mesh (what the fused objects cover).
        let mut stats = TraversalStats::default();
        let covered: Vec<bool> = all
            .iter()
            .map(|&p| {
                let ray = camera.pixel_center_ray(p % w, p / w);
                objects.iter().any(|(bvh, offset)| {
                    let mut local = ray;
                    local.origin -= *offset;
                    bvh.intersect(&local, 1e-4, f32::INFINITY, &mut stats).is_some()
                })
            })
            .collect();
        let near = PixelMask::from_flags(w as usize, h as usize, covered.clone())?.dilated(8);
        let [left, right] = stereo_pair(&camera, 0.063)?;
        let (mut g_plain, mut g_behind) = (Vec::new(), Vec::new());
        let (mut rays, mut shaded, mut light_blocked) = ((0, 0), (0, 0), 0);
        for _ in 0..args.repeats.max(1) {
            let t = Instant::now();
            let out = kernel.trace_g_buffer(&camera, &[])?;
            g_plain.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let hid = kernel.trace_g_buffer(&camera, &occluders)?;
            g_behind.push(t.elapsed().as_secs_f64() * 1e3);
            rays = (out.stats.traversal.rays, hid.stats.traversal.rays);
            light_blocked = hid.stats.light_blocked;
            shaded = (out.width, out.height);
        }
        let (g_plain, g_behind) = (median(g_plain), median(g_behind));
        // A warm-up round, then rounds that rotate the order of the renders (so that none
        // always follows the same one).
        let mut times = [(); 6].map(|_| Vec::new());
        // Multiply-adds the network ran and what whole passes would, per job.
        let mut macs = [(0u64, 0u64); 6];
        let (mut plain, mut behind, mut behind_whole) = (None, None, None);
        let jobs: Vec<usize> = if kernel.has_stereo() { (0..6).collect() } else { vec![0, 1, 4] };
        for round in 0..=args.repeats.max(1) {
            for job in (0..jobs.len()).map(|j| jobs[(j + round) % jobs.len()]) {
                let before = kernel.network_macs();
                let t = Instant::now();
                match job {
                    0 => plain = Some(kernel.render_pixels(&camera, &all)?),
                    1 => behind = Some(kernel.render_pixels_behind(&camera, &all, &occluders)?),
                    2 => {
                        kernel.render_pair((&left, &all), (&right, &all)).context("a stereo pass")??;
                    }
                    3 => {
                        kernel
                            .render_pair_behind((&left, &all), (&right, &all), &occluders)
                            .context("a stereo pass")??;
                    }
                    4 => behind_whole = Some(whole_network.render_pixels_behind(&camera, &all, &occluders)?.0),
                    _ => {
                        whole_network
                            .render_pair_behind((&left, &all), (&right, &all), &occluders)
                            .context("a stereo pass")??;
                    }
                }
                if round > 0 {
                    times[job].push(t.elapsed().as_secs_f64() * 1e3);
                    let after = kernel.network_macs();
                    macs[job].0 += after.0 - before.0;
                    macs[job].1 += after.1 - before.1;
                }
            }
        }
        let last = plain.zip(behind).zip(behind_whole);
        let (((plain, plain_stats), (behind, behind_stats)), behind_whole) = last.context("one repetition")?;
        let ms = times.map(|t| if t.is_empty() { 0.0 } else { median(t) });
        for (total, m) in totals.iter_mut().zip(ms) {
            *total += m;
        }
        let knot_share = covered.iter().filter(|&&c| c).count() as f64 / all.len() as f64;
        let share = |(done, whole): (u64, u64)| 100.0 * done as f64 / whole.max(1) as f64;
        // The mask changes no pixel the objects leave visible.
        let changed = (0..all.len()).filter(|&i| !covered[i] && behind.color[i] != behind_whole.color[i]).count();
        println!(
            "view {k}: network over the pixels left visible only: {:.1} % of a whole pass's multiply-adds (flat){}; behind the objects {:.1} -> {:.1} ms flat ({:.3}){}; visible pixels changed by the mask: {changed}",
            share(macs[1]),
            if kernel.has_stereo() { format!(", {:.1} % (stereo pair)", share(macs[3])) } else { String::new() },
            ms[4],
            ms[1],
            ms[1] / ms[4],
            if kernel.has_stereo() {
                format!(", stereo pair {:.1} -> {:.1} ms ({:.3})", ms[5], ms[3], ms[3] / ms[5])
            } else {
                String::new()
            },
        );
        println!(
            "view {k}: G-buffer alone ({}x{}): {g_plain:.1} -> {g_behind:.1} ms ({:.3}), rays traced {} -> {} ({:.3}), {light_blocked} shadow rays stopped by the objects",
            shaded.0,
            shaded.1,
            g_behind / g_plain,
            rays.0,
            rays.1,
            rays.1 as f64 / rays.0 as f64
        );
        let visible = covered.iter().filter(|&&c| !c).count().max(1);
        let darker = (0..all.len())
            .filter(|&i| !covered[i] && luminance(behind.color[i].into()) < 0.9 * luminance(plain.color[i].into()))
            .count();
        if let Some(dir) = &args.images {
            for (name, image) in [("empty", &plain.color), ("objects", &behind.color)] {
                let path = dir.join(format!("view-{k}-{name}.png"));
                RgbaImage::from_fn(w, h, |x, y| {
                    let c = image[(y * w + x) as usize];
                    [linear_to_srgb(c[0]), linear_to_srgb(c[1]), linear_to_srgb(c[2]), 1.0]
                })
                .save_png(&path)
                .with_context(|| format!("writing {}", path.display()))?;
            }
        }
        println!(
            "view {k}: objects cover {:.1} % of the pixels; samples hidden {:.1} % ({} of {}); flat {:.1} -> {:.1} ms ({:.3}){}; visible pixels: PSNR {:.2} dB against no occluders, {:.2} dB within 8 px of an object, {:.1} % at least 10 % darker (shadows)",
            100.0 * knot_share,
            100.0 * behind_stats.hidden as f64 / behind_stats.rays.max(1) as f64,
            behind_stats.hidden,
            behind_stats.rays,
            ms[0],
            ms[1],
            ms[1] / ms[0],
            if kernel.has_stereo() {
                format!("; stereo pair {:.1} -> {:.1} ms ({:.3})", ms[2], ms[3], ms[3] / ms[2])
            } else {
                String::new()
            },
            psnr(&behind.color, &plain.color, |i| !covered[i]),
            psnr(&behind.color, &plain.color, |i| !covered[i] && near.get(i % w as usize, i / w as usize)),
            100.0 * darker as f64 / visible as f64,
        );
        ensure!(plain_stats.hidden == 0, "a render without occluders hid samples");
        bar.inc(1);
    }
    bar.finish_and_clear();
    let per_view = |t: f64| t / args.views as f64;
    println!(
        "all views: flat {:.1} -> {:.1} ms per view ({:.3}; {:.1} ms, {:.3}, with the network over the covered pixels too){}",
        per_view(totals[0]),
        per_view(totals[1]),
        totals[1] / totals[0],
        per_view(totals[4]),
        totals[4] / totals[0],
        if kernel.has_stereo() {
            format!(
                "; stereo pair {:.1} -> {:.1} ms ({:.3}; {:.1} ms, {:.3}, the network over every pixel)",
                per_view(totals[2]),
                per_view(totals[3]),
                totals[3] / totals[2],
                per_view(totals[5]),
                totals[5] / totals[2]
            )
        } else {
            String::new()
        }
    );
    Ok(())
}
