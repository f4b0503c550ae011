//! Ray marching through the occupancy grid: samples at a fixed step `dt` along the ray
//! (aligned on a grid of `t` so that skipping does not shift them), skipping empty cells
//! and empty coarse blocks by jumping to their exit (i-NGP's `advance_to_next_voxel`).
//!
//! Work happens in the unit cube of the field's box; `t` stays a world-space distance along
//! the (unit-length) world direction, so `dt` and the densities keep world units.

use glam::Vec3;
use nephele_geometry::camera::marchable_direction;

use super::occupancy::{BLOCK, OccupancyGrid};

/// Entry and exit distances of a ray through the box `[min, max]`, `None` if it misses or
/// the box lies behind the origin or the input is not finite or the direction not
/// marchable ([`marchable_direction`]: tiny components count as 0). Rays parallel to a slab
/// are handled without dividing by zero;
/// `t_enter` may be negative when the origin is inside.
pub fn ray_box(origin: Vec3, dir: Vec3, min: Vec3, max: Vec3) -> Option<(f32, f32)> {
    let dir = marchable_direction(dir)?;
    if !origin.is_finite() {
        return None;
    }
    let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
    for a in 0..3 {
        let (o, d) = (origin[a], dir[a]);
        if d == 0.0 {
            if o < min[a] || o > max[a] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d;
        let (mut ta, mut tb) = ((min[a] - o) * inv, (max[a] - o) * inv);
        if ta > tb {
            std::mem::swap(&mut ta, &mut tb);
        }
        t0 = t0.max(ta);
        t1 = t1.min(tb);
    }
    (t0 <= t1 && t1 >= 0.0 && t1.is_finite()).then_some((t0, t1))
}

/// `t + by` for `t >= 0`, but always past `t`: far from the box (a camera 10^7 box sizes
/// away) a step is below half a float step of `t` and `t + by` would not move, so the march
/// would never end; it then moves one float step (the GPU twin does the same).
#[inline]
fn advance(t: f32, by: f32) -> f32 {
    let next = t + by;
    if next > t { next } else { t.next_up() }
}

/// Iterator-like marcher over the occupied samples of one ray.
#[derive(Debug, Clone)]
pub struct Marcher {
    /// Origin and direction in unit-cube coordinates (direction not normalised).
    origin: Vec3,
    dir: Vec3,
    t: f32,
    t_end: f32,
    dt: f32,
    resolution: f32,
    /// Cells visited (including skipped ones), for statistics.
    pub steps: u32,
}

impl Marcher {
    /// A marcher for the world ray `origin + t dir` (`dir` unit length) through the box
    /// `[min, min + size]`, starting no earlier than `t_min`. `offset` in `[0, 1)` shifts the
    /// sample grid by that fraction of a step (training jitter; 0.5 for rendering). `None`
    /// if the ray misses the box.
    #[allow(clippy::too_many_arguments)] // all plain numbers of one ray; a struct would only rename them
    pub fn new(
        origin: Vec3,
        dir: Vec3,
        min: Vec3,
        size: f32,
        dt: f32,
        t_min: f32,
        offset: f32,
        resolution: u32,
    ) -> Option<Self> {
        let dir = marchable_direction(dir)?;
        let (t0, t1) = ray_box(origin, dir, min, min + Vec3::splat(size))?;
        let start = t0.max(t_min);
        if start >= t1 {
            return None;
        }
        // Samples at t = k * dt + offset * dt for integer k: aligned along the ray.
        let k = ((start / dt) - offset).ceil();
        let t = (k + offset) * dt;
        Some(Marcher {
            origin: (origin - min) / size,
            dir: dir / size,
            t,
            t_end: t1,
            dt,
            resolution: resolution as f32,
            steps: 0,
        })
    }

    /// Ends the march at `t_max` (or where it ended before, if sooner).
    pub fn end_by(&mut self, t_max: f32) {
        self.t_end = self.t_end.min(t_max);
    }

    /// `t` at which the ray leaves the axis-aligned cell of side `1 / cells` holding `p`.
    #[inline]
    fn exit(&self, p: Vec3, cells: f32) -> f32 {
        let mut t_exit = f32::INFINITY;
        for a in 0..3 {
            let d = self.dir[a];
            if d == 0.0 {
                continue;
            }
            let c = (p[a] * cells).floor();
            let boundary = if d > 0.0 { (c + 1.0) / cells } else { c / cells };
            t_exit = t_exit.min((boundary - self.origin[a]) / d);
        }
        t_exit
    }

    /// Moves `t` past `t_exit` on the sample grid (at least one step).
    #[inline]
    fn skip_to(&mut self, t_exit: f32) {
        let steps = ((t_exit - self.t) / self.dt).ceil().max(1.0);
        self.t = advance(self.t, steps * self.dt);
    }

    /// The next occupied sample `(t, unit-cube position)`, or `None` at the end of the box.
    #[inline]
    pub fn next(&mut self, grid: &OccupancyGrid) -> Option<(f32, Vec3)> {
        let r = self.resolution;
        let max_cell = grid.resolution() - 1;
        while self.t < self.t_end {
            self.steps += 1;
            let p = self.origin + self.t * self.dir;
            let c = (p * r).floor();
            let cell = |v: f32| (v.max(0.0) as u32).min(max_cell);
            let (x, y, z) = (cell(c.x), cell(c.y), cell(c.z));
            if !grid.block_occupied(x, y, z) {
                let t_exit = self.exit(p.clamp(Vec3::ZERO, Vec3::ONE), r / BLOCK as f32);
                self.skip_to(t_exit);
                continue;
            }
            if !grid.get(grid.index(x, y, z)) {
                let t_exit = self.exit(p.clamp(Vec3::ZERO, Vec3::ONE), r);
                self.skip_to(t_exit);
                continue;
            }
            let t = self.t;
            self.t = advance(self.t, self.dt);
            return Some((t, p.clamp(Vec3::ZERO, Vec3::ONE)));
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 18: a camera 10^6 box sizes away (a sample step below half a float step of `t`)
    /// used to leave `t` where it was, for ever; denormal and tiny directions.
    #[test]
    fn far_rays_end_and_degenerate_directions_are_refused() {
        let grid = OccupancyGrid::filled(16, true);
        let origin = Vec3::new(-1e6, 0.31, 0.42);
        let mut marcher = Marcher::new(origin, Vec3::X, Vec3::ZERO, 1.0, 1.0 / 256.0, 0.0, 0.5, 16).expect("hits");
        let mut samples = 0;
        while marcher.next(&grid).is_some() {
            samples += 1;
            assert!(samples < 10_000, "the march does not move");
        }
        assert!(samples > 0);
        for dir in [Vec3::ZERO, Vec3::new(1e-40, 1e-41, 0.0), Vec3::new(f32::NAN, 0.0, 1.0), Vec3::splat(0.01)] {
            assert!(Marcher::new(Vec3::splat(0.5), dir, Vec3::ZERO, 1.0, 0.01, 0.0, 0.5, 16).is_none(), "{dir}");
            assert_eq!(ray_box(Vec3::splat(0.5), dir, Vec3::ZERO, Vec3::ONE), None, "{dir}");
        }
        // A denormal component is exactly a zero one.
        let o = Vec3::new(-1.0, 0.5, 0.5);
        assert_eq!(
            ray_box(o, Vec3::new(1.0, 1e-40, 0.0), Vec3::ZERO, Vec3::ONE),
            ray_box(o, Vec3::X, Vec3::ZERO, Vec3::ONE)
        );
    }

    #[test]
    fn ray_box_handles_parallel_and_inside_rays() {
        let (min, max) = (Vec3::ZERO, Vec3::ONE);
        assert_eq!(ray_box(Vec3::new(-1.0, 0.5, 0.5), Vec3::X, min, max), Some((1.0, 2.0)));
        assert_eq!(ray_box(Vec3::new(-1.0, 2.0, 0.5), Vec3::X, min, max), None);
        let (t0, t1) = ray_box(Vec3::splat(0.5), Vec3::Z, min, max).expect("inside");
        assert!(t0 < 0.0 && (t1 - 0.5).abs() < 1e-6);
        // On a face, parallel to it: still inside the closed box.
        assert!(ray_box(Vec3::new(-1.0, 0.0, 1.0), Vec3::X, min, max).is_some());
        assert_eq!(ray_box(Vec3::new(f32::NAN, 0.0, 0.0), Vec3::X, min, max), None);
        assert_eq!(ray_box(Vec3::new(2.0, 0.5, 0.5), Vec3::X, min, max), None);
    }

    #[test]
    fn skips_empty_cells_and_visits_occupied_ones() {
        let mut grid = OccupancyGrid::filled(16, false);
        // One occupied cell on the ray's path, in the middle of the cube.
        let i = grid.index(8, 8, 8);
        grid.set(i, true);
        grid.rebuild_coarse();
        let dt = 1.0 / 256.0;
        let origin = Vec3::new(-1.0, 8.5 / 16.0, 8.5 / 16.0);
        let mut m = Marcher::new(origin, Vec3::X, Vec3::ZERO, 1.0, dt, 0.0, 0.5, 16).expect("hit");
        let mut samples = Vec::new();
        while let Some((t, p)) = m.next(&grid) {
            samples.push((t, p));
        }
        // The cell spans x in [0.5, 0.5625): 16 steps of 1/256.
        assert_eq!(samples.len(), 16, "{samples:?}");
        assert!(samples.iter().all(|(_, p)| (p.x * 16.0).floor() == 8.0));
        // Aligned: t - 0.5 dt is a multiple of dt.
        for (t, _) in &samples {
            let k = (t / dt) - 0.5;
            assert!((k - k.round()).abs() < 1e-3);
        }
        // Far fewer steps than samples along the whole box would be.
        assert!(m.steps < 64, "{}", m.steps);
        // Empty grid: no samples, few steps, even along a diagonal.
        let empty = OccupancyGrid::filled(16, false);
        let mut m =
            Marcher::new(Vec3::splat(-1.0), Vec3::ONE.normalize(), Vec3::ZERO, 1.0, dt, 0.0, 0.5, 16).expect("hit");
        assert!(m.next(&empty).is_none());
        assert!(m.steps <= 8, "{}", m.steps);
    }
}
