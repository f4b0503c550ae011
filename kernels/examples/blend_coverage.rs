//! How much of a hitting ray's opacity the samples of largest weight hold, for choosing
//! `HeadsShape::blend_samples` (docs/inolf.md, "The blended diffuse colour"): the plain march
//! of an asset's density cubes (every voxel, as `DensityCubes::march`) from 8 orbit views of
//! 200x200, rays of opacity 0.5 or more; the share the K largest weights hold, over all such
//! rays and over those whose weight spreads over more than 4 voxels of depth (edges).
//!
//! `cargo run --release -p nephele-kernels --example blend_coverage -- lego.nolf`
use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_kernels::inolf::asset::Asset;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let path = std::env::args().nth(1).ok_or("usage: blend_coverage ASSET.nolf")?;
    let asset = Asset::load(std::path::Path::new(&path))?;
    let cubes = asset.density;
    let b = cubes.bounds();
    let step = cubes.cubes().sample_step();
    let ks = [1usize, 2, 4, 6, 8, 12, 16];
    let mut cov = vec![0.0f64; ks.len()];
    let mut cov_edge = vec![0.0f64; ks.len()];
    let (mut hits, mut edges) = (0u64, 0u64);
    let mut nmatter = 0u64;
    let mut n_over = [0u64; 4];
    for v in 0..8 {
        let a = v as f32 * 0.785 + 0.3;
        let eye = Vec3::new(4.0 * a.cos() * 0.8, 4.0 * a.sin() * 0.8, 2.4);
        let cam = Camera::look_at(200, 200, 0.69, eye, Vec3::ZERO, Vec3::Z)?;
        for j in 0..200 {
            for i in 0..200 {
                let r = cam.pixel_center_ray(i, j);
                let (o, d) = (r.origin, r.direction);
                let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
                for ax in 0..3 {
                    if d[ax] != 0.0 {
                        let (ta, tb) = ((b.min[ax] - o[ax]) / d[ax], (b.max[ax] - o[ax]) / d[ax]);
                        t0 = t0.max(ta.min(tb));
                        t1 = t1.min(ta.max(tb));
                    }
                }
                if !(t0 < t1) {
                    continue;
                }
                let mut tr = 1.0f32;
                let mut ws: Vec<(f32, f32)> = Vec::new();
                let mut k = 0;
                loop {
                    let t = t0 + (k as f32 + 0.5) * step;
                    if t >= t1 {
                        break;
                    }
                    k += 1;
                    let s = cubes.density(o + d * t);
                    if s <= 0.0 {
                        continue;
                    }
                    let al = 1.0 - (-s * step).exp();
                    ws.push((t, tr * al));
                    tr *= 1.0 - al;
                    if tr < 1e-3 {
                        break;
                    }
                }
                let op = 1.0 - tr;
                if op < 0.5 {
                    continue;
                }
                hits += 1;
                nmatter += ws.len() as u64;
                // Depth spread: weighted std of t.
                let mean: f32 = ws.iter().map(|w| w.0 * w.1).sum::<f32>() / op;
                let var: f32 = ws.iter().map(|w| w.1 * (w.0 - mean).powi(2)).sum::<f32>() / op;
                let sd = var.sqrt() / step;
                let edge = sd > 4.0;
                if edge {
                    edges += 1;
                }
                for (q, th) in [1.0f32, 2.0, 4.0, 8.0].iter().enumerate() {
                    if sd > *th {
                        n_over[q] += 1;
                    }
                }
                ws.sort_by(|a, b| b.1.total_cmp(&a.1));
                for (q, &kk) in ks.iter().enumerate() {
                    let s: f32 = ws.iter().take(kk).map(|w| w.1).sum();
                    cov[q] += (s / op) as f64;
                    if edge {
                        cov_edge[q] += (s / op) as f64;
                    }
                }
            }
        }
    }
    println!(
        "hits {hits}, samples with matter per hit {:.1}, depth sd >1/2/4/8 voxels: {:?}",
        nmatter as f64 / hits as f64,
        n_over.iter().map(|&n| format!("{:.3}", n as f64 / hits as f64)).collect::<Vec<_>>()
    );
    for (q, &kk) in ks.iter().enumerate() {
        println!(
            "top {kk:2}: coverage {:.4} all, {:.4} on rays with spread > 4 voxels ({edges})",
            cov[q] / hits as f64,
            cov_edge[q] / edges.max(1) as f64
        );
    }
    Ok(())
}
