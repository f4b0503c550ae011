//! What a simulation is made of: objects, users with camera paths, workers, parameters.

use glam::Vec3;
use nephele_geometry::camera::{Camera, CameraError, quilt_rig, stereo_pair};
use nephele_geometry::{Bounds, SplitMix64};

/// Interpupillary distance of simulated headsets, metres.
pub const IPD_M: f32 = 0.064;
/// View cone of simulated quilt displays (Looking Glass: about 40 degrees).
pub use nephele_geometry::camera::QUILT_VIEW_CONE_DEG as QUILT_CONE_DEG;

/// An object instance in the shared world: an axis-aligned cube.
#[derive(Debug, Clone, PartialEq)]
pub struct SimObject {
    pub name: String,
    pub center: Vec3,
    pub half_size: f32,
    /// Relative cost per ray (1 = the kernel worker throughput is measured with; an i-NGP-like
    /// kernel is about 5x an i-NOLF one, NEPHELE table 3).
    pub cost_per_ray: f64,
}

impl SimObject {
    pub fn bounds(&self) -> Bounds {
        Bounds { min: self.center - Vec3::splat(self.half_size), max: self.center + Vec3::splat(self.half_size) }
    }
}

/// Views a user's device asks for per frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViewMode {
    /// A flat screen: one view.
    Mono,
    /// A headset: two eyes 64 mm apart.
    Stereo,
    /// A light-field display: N views over a 40 degree cone (45 for a Looking Glass quilt).
    Quilt(usize),
}

impl ViewMode {
    pub fn parse(text: &str) -> Option<ViewMode> {
        match text {
            "mono" => Some(ViewMode::Mono),
            "stereo" => Some(ViewMode::Stereo),
            "quilt" => Some(ViewMode::Quilt(45)),
            _ => text
                .strip_prefix("quilt")
                .and_then(|n| n.parse().ok())
                .filter(|n| (1..=64).contains(n))
                .map(ViewMode::Quilt),
        }
    }

    pub fn count(self) -> usize {
        match self {
            ViewMode::Mono => 1,
            ViewMode::Stereo => 2,
            ViewMode::Quilt(n) => n,
        }
    }
}

/// A camera orbiting a target: at time `t` after arrival the eye is at
/// `target + (radius cos a, radius sin a, height)` with `a = start + speed t`, looking at the
/// target, +Z up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPath {
    /// `None`: the mean of the user's object centres.
    pub target: Option<Vec3>,
    pub radius_m: f32,
    pub height_m: f32,
    pub speed_deg_s: f32,
    pub start_deg: f32,
}

/// A simulated user session.
#[derive(Debug, Clone, PartialEq)]
pub struct SimUser {
    pub name: String,
    pub arrive_s: f64,
    pub depart_s: f64,
    pub fps: f64,
    pub width: u32,
    pub height: u32,
    /// Vertical field of view.
    pub fov_deg: f32,
    pub views: ViewMode,
    /// Indices into the scenario's objects.
    pub objects: Vec<usize>,
    pub path: CameraPath,
}

impl SimUser {
    /// The user's views `seconds` after arrival.
    pub fn views_at(&self, seconds: f64, objects: &[SimObject]) -> Result<Vec<Camera>, CameraError> {
        let target = self.path.target.unwrap_or_else(|| {
            let sum: Vec3 = self.objects.iter().filter_map(|&i| objects.get(i)).map(|o| o.center).sum();
            sum / self.objects.len().max(1) as f32
        });
        let angle = (self.path.start_deg + self.path.speed_deg_s * seconds as f32).to_radians();
        let eye =
            target + Vec3::new(self.path.radius_m * angle.cos(), self.path.radius_m * angle.sin(), self.path.height_m);
        let centre = Camera::look_at(self.width, self.height, self.fov_deg.to_radians(), eye, target, Vec3::Z)?;
        Ok(match self.views {
            ViewMode::Mono => vec![centre],
            ViewMode::Stereo => stereo_pair(&centre, IPD_M)?.to_vec(),
            ViewMode::Quilt(n) => quilt_rig(&centre, n, QUILT_CONE_DEG.to_radians(), (eye - target).length())?,
        })
    }
}

/// How the master learns that a failed worker is gone.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Detect {
    /// The process died: its TCP connection closes at once.
    Drop,
    /// The machine hangs: only missed heartbeats and deadlines tell.
    Silent,
}

/// A simulated render worker: serves its batches one at a time, first in first out.
#[derive(Debug, Clone, PartialEq)]
pub struct SimWorker {
    pub name: String,
    /// True throughput for cost-1 rays (also what it declares when it registers).
    pub rays_per_s: f64,
    /// Each batch takes `1 + jitter * u` times its nominal time, `u` uniform in [-1, 1].
    pub jitter: f64,
    pub join_s: f64,
    pub fail_s: Option<f64>,
    pub detect: Detect,
    /// `(from_s, to_s, factor)`: batches started in `[from, to)` take `factor` times longer.
    pub slow: Option<(f64, f64, f64)>,
}

impl SimWorker {
    pub fn new(name: &str, rays_per_s: f64) -> SimWorker {
        SimWorker {
            name: name.to_string(),
            rays_per_s,
            jitter: 0.1,
            join_s: 0.0,
            fail_s: None,
            detect: Detect::Drop,
            slow: None,
        }
    }
}

/// Costs outside the scheduler that the simulation models (paper eq. 9:
/// `T_frame = max_i T_i + sum_i D_i / BW + C`).
#[derive(Debug, Clone, PartialEq)]
pub struct SimParams {
    pub seed: u64,
    pub duration_s: f64,
    /// Pose updates from each client (NEPHELE section 5.2: every 20 ms).
    pub pose_interval_s: f64,
    pub heartbeat_s: f64,
    /// Fixed cost per batch on a worker (receive, ray generation setup, send).
    pub batch_overhead_s: f64,
    /// Extra time when a worker switches to another object (model weights into caches).
    pub switch_cost_s: f64,
    /// Worker-to-composer bandwidth (`BW`), bytes/s.
    pub link_bytes_per_s: f64,
    /// Result bytes per pixel (`D_i`): colour 3 x f32, opacity f32, depth f32.
    pub bytes_per_pixel: f64,
    /// Composition and encoding of a frame (`C`).
    pub composite_s: f64,
    /// How often a refused user tries again (after the Retry-After it was given).
    pub retries: u32,
    /// Share of a derived view's pixels (issue 16) that reprojection leaves to render: 12 %
    /// for a stereo eye and for a quilt's derived views (`nephele bench share`, BENCHMARKS.md).
    /// Counted as rays rendered; the time a worker spends on a derived view comes from the
    /// scheduler's `work_rays` (reprojection included).
    pub derived_render_fraction: f64,
}

impl Default for SimParams {
    fn default() -> SimParams {
        SimParams {
            seed: 1,
            duration_s: 10.0,
            pose_interval_s: 0.02,
            heartbeat_s: 0.1,
            batch_overhead_s: 50e-6,
            switch_cost_s: 0.5e-3,
            link_bytes_per_s: 3.125e9,
            bytes_per_pixel: 20.0,
            derived_render_fraction: 0.12,
            composite_s: 1e-3,
            retries: 3,
        }
    }
}

/// A complete simulation input.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    pub name: String,
    pub description: String,
    pub objects: Vec<SimObject>,
    pub users: Vec<SimUser>,
    pub workers: Vec<SimWorker>,
    pub params: SimParams,
}

/// The project's SplitMix64 under a seed of the simulator's own (its only randomness).
#[derive(Debug, Clone)]
pub struct Rng(SplitMix64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(SplitMix64::new(seed ^ 0x9E37_79B9_7F4A_7C15))
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        self.0.next_f64()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_follow_the_path_and_modes() {
        let objects =
            vec![SimObject { name: "a".into(), center: Vec3::new(1.0, 0.0, 0.0), half_size: 0.5, cost_per_ray: 1.0 }];
        let path = CameraPath { target: None, radius_m: 3.0, height_m: 0.0, speed_deg_s: 90.0, start_deg: 0.0 };
        let mut user = SimUser {
            name: "u".into(),
            arrive_s: 0.0,
            depart_s: 1.0,
            fps: 30.0,
            width: 64,
            height: 48,
            fov_deg: 50.0,
            views: ViewMode::Mono,
            objects: vec![0],
            path,
        };
        let at0 = user.views_at(0.0, &objects).expect("views");
        assert!((at0[0].position() - Vec3::new(4.0, 0.0, 0.0)).length() < 1e-5);
        let at1 = user.views_at(1.0, &objects).expect("views");
        assert!((at1[0].position() - Vec3::new(1.0, 3.0, 0.0)).length() < 1e-4);
        user.views = ViewMode::Stereo;
        assert_eq!(user.views_at(0.0, &objects).expect("views").len(), 2);
        user.views = ViewMode::parse("quilt").expect("mode");
        assert_eq!(user.views_at(0.0, &objects).expect("views").len(), 45);
        assert_eq!(ViewMode::parse("quilt8"), Some(ViewMode::Quilt(8)));
        assert_eq!(ViewMode::parse("quilt0"), None);
        assert_eq!(ViewMode::parse("cube"), None);
        let mut rng = Rng::new(7);
        let draws: Vec<f64> = (0..1000).map(|_| rng.unit()).collect();
        assert!(draws.iter().all(|u| (0.0..1.0).contains(u)));
        let mean = draws.iter().sum::<f64>() / 1000.0;
        assert!((mean - 0.5).abs() < 0.05);
        assert_eq!(Rng::new(7).next_u64(), Rng::new(7).next_u64());
    }
}
