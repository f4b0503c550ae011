//! `nephele bench assigner`: the TaskAssigner's `nhit` estimate (NEPHELE section 5) against
//! the pixels an object really covers, for each proxy it can project: the bounding box, and
//! coarse occupancy grids made from the object's mesh (the paper's prior mesh) at several
//! resolutions. Per proxy: the mean relative error of the estimated pixel count, the hit
//! pixels it missed (a missed pixel would be a hole in the frame: must be zero), and the
//! estimate's time against the box's, in one run.

use std::time::Instant;

use anyhow::{Context, Result};
use glam::Vec3;
use nephele_geometry::Bounds;
use nephele_geometry::camera::Camera;
use nephele_pathtracer::bvh::{Bvh, TraversalStats};
use nephele_pathtracer::scenes;
use nephele_pathtracer::voxel::cell_occupancy;
use nephele_scheduler::OccupancyGrid;
use nephele_scheduler::assign::estimate_coverage;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct AssignerArgs {
    /// Built-in objects to measure.
    #[arg(long, value_delimiter = ',', default_value = "diffuse,glossy,shell,furry,assembly")]
    objects: Vec<String>,
    /// View size.
    #[arg(long, default_value = "320x240", value_parser = nephele_geometry::camera::parse_size, value_name = "WxH")]
    size: (u32, u32),
    /// Azimuths around each object (each at three distances: 0.6, 1 and 2 times the default
    /// view's).
    #[arg(long, default_value_t = 8)]
    azimuths: usize,
    /// Occupancy grids tried: cells along the longest side of the box.
    #[arg(long, value_delimiter = ',', default_value = "8,16,24,32")]
    cells: Vec<u32>,
    /// Rows per band of the pixel sets (`SchedulerConfig::band_rows`, whose default this is).
    #[arg(long, default_value_t = nephele_scheduler::SchedulerConfig::default().band_rows)]
    band_rows: u32,
    /// Margin of the grids, in cells (`nephele_pathtracer::voxel::cell_occupancy`).
    #[arg(long, default_value_t = 0.5)]
    margin: f32,
}

const DISTANCES: [f32; 3] = [0.6, 1.0, 2.0];

#[derive(Default, Clone)]
struct ProxyTally {
    relative_error: Vec<f64>,
    estimated: u64,
    missed: u64,
    seconds: f64,
    estimates: u64,
    occupied_cells: usize,
}

pub fn run(args: AssignerArgs, progress: &dyn Progress) -> Result<()> {
    let (w, h) = args.size;
    let proxies = 1 + args.cells.len();
    let mut names = vec!["box".to_string()];
    names.extend(args.cells.iter().map(|c| format!("grid {c} (margin {})", args.margin)));
    let mut totals = vec![ProxyTally::default(); proxies];
    let views = args.objects.len() * args.azimuths * DISTANCES.len();
    let bar = progress.bar(views as u64, "views", "views");
    let (mut hit_pixels, mut view_count) = (0u64, 0usize);
    println!(
        "| object | triangles | proxy | occupied cells | estimated / hit pixels | mean relative error | missed hit pixels |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for name in &args.objects {
        let object = scenes::builtin(name).with_context(|| format!("building '{name}'"))?;
        let mesh = &object.scene.mesh;
        let (min, max) = mesh.bounds().with_context(|| format!("'{name}' has no geometry"))?;
        let bounds = Bounds { min, max };
        let grids: Vec<OccupancyGrid> = args
            .cells
            .iter()
            .map(|&cells| {
                let (dims, occupied) = cell_occupancy(mesh, min, max, cells, args.margin);
                OccupancyGrid::new(dims, occupied).with_context(|| format!("a {cells}-cell grid is too large"))
            })
            .collect::<Result<_>>()?;
        let bvh = Bvh::build(mesh);
        let (eye, target, fov_y) = object.default_view();
        let mut tallies = vec![ProxyTally::default(); proxies];
        let mut object_hits = 0u64;
        for k in 0..args.azimuths {
            let turn = glam::Mat3::from_rotation_z(k as f32 * std::f32::consts::TAU / args.azimuths as f32);
            for factor in DISTANCES {
                let eye = target + turn * (eye - target) * factor;
                let camera = Camera::look_at(w, h, fov_y, eye, target, Vec3::Z)?;
                let mut hit = vec![false; (w * h) as usize];
                let mut stats = TraversalStats::default();
                for (index, slot) in hit.iter_mut().enumerate() {
                    let ray = camera.pixel_center_ray(index as u32 % w, index as u32 / w);
                    *slot = bvh.intersect(&ray, 1e-4, f32::INFINITY, &mut stats).is_some();
                }
                let hits = hit.iter().filter(|&&x| x).count() as u64;
                object_hits += hits;
                for (p, tally) in tallies.iter_mut().enumerate() {
                    let grid = if p == 0 { None } else { Some(&grids[p - 1]) };
                    let start = Instant::now();
                    let coverage = estimate_coverage(&camera, &bounds, grid, args.band_rows);
                    tally.seconds += start.elapsed().as_secs_f64();
                    tally.estimates += 1;
                    let (estimated, covered) = match &coverage {
                        Some(c) => {
                            let mut mask = vec![false; hit.len()];
                            for i in c.pixels.indices() {
                                mask[i as usize] = true;
                            }
                            (c.rays, mask)
                        }
                        None => (0, vec![false; hit.len()]),
                    };
                    tally.estimated += estimated;
                    tally.missed += hit.iter().zip(&covered).filter(|(h, c)| **h && !**c).count() as u64;
                    if hits > 0 {
                        tally.relative_error.push((estimated as f64 - hits as f64) / hits as f64);
                    }
                }
                view_count += 1;
                bar.inc(1);
            }
        }
        hit_pixels += object_hits;
        for (p, tally) in tallies.iter_mut().enumerate() {
            tally.occupied_cells = if p == 0 { 1 } else { grids[p - 1].occupied_count() };
            println!(
                "| {name} | {} | {} | {} | {:.2} | {:+.1} % | {} |",
                mesh.triangle_count(),
                names[p],
                tally.occupied_cells,
                tally.estimated as f64 / object_hits.max(1) as f64,
                100.0 * mean(&tally.relative_error),
                tally.missed
            );
            let total = &mut totals[p];
            total.relative_error.extend(&tally.relative_error);
            total.estimated += tally.estimated;
            total.missed += tally.missed;
            total.seconds += tally.seconds;
            total.estimates += tally.estimates;
            total.occupied_cells += tally.occupied_cells;
        }
    }
    bar.finish_and_clear();
    println!(
        "\n{} objects x {} views of {w}x{h} (azimuths x distances 0.6 / 1 / 2 of the default view's), {} hit pixels in all (path-traced primary rays)",
        args.objects.len(),
        view_count / args.objects.len().max(1),
        hit_pixels
    );
    println!("| proxy | estimated / hit pixels | mean relative error | missed hit pixels | estimate time / box's |");
    println!("| --- | --- | --- | --- | --- |");
    let box_time = totals[0].seconds / totals[0].estimates.max(1) as f64;
    for (p, total) in totals.iter().enumerate() {
        let time = total.seconds / total.estimates.max(1) as f64;
        println!(
            "| {} | {:.2} | {:+.1} % | {} | {:.1} |",
            names[p],
            total.estimated as f64 / hit_pixels.max(1) as f64,
            100.0 * mean(&total.relative_error),
            total.missed,
            time / box_time.max(1e-12)
        );
    }
    Ok(())
}

fn mean(values: &[f64]) -> f64 {
    if values.is_empty() { 0.0 } else { values.iter().sum::<f64>() / values.len() as f64 }
}
