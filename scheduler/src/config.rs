//! Tunables of the scheduler, and the policies it can run.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use crate::SchedError;

/// Highest target frame rate a session may ask for.
pub const MAX_FPS: f64 = 240.0;

/// Which scheduling policy the core runs. Every policy shares the same event interface, the
/// same TaskAssigner, frame bookkeeping and resiliency (re-issue on worker loss or missed
/// deadline), so the simulator compares placement and ordering alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Policy {
    /// NEPHELE Algorithm 1: starvation-first ordering with admission control, farm filled to
    /// its ray capacity user by user (shared tasks first), HeavyFarm/LightFarm placement,
    /// shared rays and the history table.
    Nephele,
    /// Per-job round robin: every batch, in arrival order, to the next worker in turn, at once,
    /// whatever that worker's load.
    RoundRobin,
    /// One global first-in-first-out queue; a batch goes to the least-loaded worker that has
    /// room (work-conserving, but blind to deadlines, sharing and task size).
    Fifo,
    /// Each object is bound to one worker (the least-bound one when first seen); all its
    /// batches queue there. Best locality, no load balance.
    ObjectPerWorker,
}

impl Policy {
    pub const ALL: [Policy; 4] = [Policy::Nephele, Policy::RoundRobin, Policy::Fifo, Policy::ObjectPerWorker];

    pub fn name(self) -> &'static str {
        match self {
            Policy::Nephele => "nephele",
            Policy::RoundRobin => "round-robin",
            Policy::Fifo => "fifo",
            Policy::ObjectPerWorker => "object-per-worker",
        }
    }
}

impl fmt::Display for Policy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Policy {
    type Err = String;
    fn from_str(s: &str) -> Result<Policy, String> {
        Policy::ALL.into_iter().find(|p| p.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Policy::ALL.iter().map(|p| p.name()).collect();
            format!("unknown policy '{s}' (one of: {})", names.join(", "))
        })
    }
}

/// When two views count as asking for "the same rays" of an object. Cameras are quantised on a
/// grid (see [`crate::CameraKey`]); two views share when they land in the same cell, i.e. they
/// agree within one cell on every coordinate: camera position within `position_m` per axis,
/// each component of the forward and up unit vectors within `angle_rad` (about that many
/// radians of rotation), each intrinsic (`fx, fy, cx, cy`) within `intrinsics_px`, and the
/// image size exactly. Views closer than a cell may still straddle a cell boundary and not
/// share: the rule errs towards rendering twice, never towards a wrong merge beyond the cell.
/// The error a merge does introduce is measured (reprojection of the object's box corners, in
/// pixels) and reported in [`crate::Stats`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ShareTolerance {
    pub position_m: f32,
    pub angle_rad: f32,
    pub intrinsics_px: f32,
}

impl Default for ShareTolerance {
    /// 1 mm, 0.02 degree, a tenth of a pixel: at 2 m in front of a 800x800 camera with a
    /// 40 degree field of view (fx = 1100 px), 1 mm of sideways motion moves a point by
    /// 0.55 px and 0.02 degree of rotation by 0.38 px, so a merge stays below about a pixel;
    /// the reported reprojection error shows what was actually accepted.
    fn default() -> ShareTolerance {
        ShareTolerance { position_m: 0.001, angle_rad: 0.02f32.to_radians(), intrinsics_px: 0.1 }
    }
}

/// Views of one frame derived from an adjacent view of the same frame (issue 16): the eyes of
/// a headset, neighbours in a quilt. The key view's batches carry the derived views' pixels
/// to the worker, which renders the key, reprojects it into the others by depth and renders
/// only what reprojection does not cover (`nephele_worker::derive`, `nephele_share`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DerivedViews {
    /// Largest angle, seen from the object's centre, between a derived view's camera and its
    /// key view's, degrees. 4: reuse is checked per pixel at 6 degrees at the surface point
    /// (`nephele_share::Settings::max_angle_deg`), and a surface point nearer the cameras than
    /// the centre sees a larger angle (by about 4/3 for an object a quarter as deep as it is
    /// far); a 40-degree 45-view quilt then groups up to 9 views around each key (0.91
    /// degrees apart), and a headset's eyes (64 mm apart) pair for objects from 0.92 m away.
    pub max_view_angle_deg: f64,
    /// Work of a derived pixel relative to rendering it, for time and capacity estimates: the
    /// reprojection (0.2-0.35 of a full render of the view, `nephele bench share`) plus the
    /// pixels left to render (12 % of a stereo eye or of a quilt's derived view).
    pub work_fraction: f64,
}

/// The history table renders ahead (issue 16, NEPHELE eq. 12): while the farm has spare
/// capacity (nothing waits, every worker idle), each moving user's next view of each object
/// is predicted from its last two poses and rendered before the frame asks for it, the views
/// that the most users' views lie near first. The worker keeps such a render as the user's
/// source for its next frames (`nephele_worker`'s previous renders), so the frame takes it by
/// reprojection and renders only the leftovers; nothing of it is shown by itself. A busy farm
/// never renders ahead.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderAhead {
    /// Share of the farm's time until the next frame release that ahead work may take (the
    /// rest is margin for the throughput estimate's error: a frame released while ahead work
    /// still runs waits behind it).
    pub budget_fraction: f64,
}

impl Default for RenderAhead {
    fn default() -> RenderAhead {
        RenderAhead { budget_fraction: 0.5 }
    }
}

impl Default for DerivedViews {
    fn default() -> DerivedViews {
        DerivedViews { max_view_angle_deg: 4.0, work_fraction: 0.45 }
    }
}

/// Every tunable of the scheduler core. [`SchedulerConfig::for_policy`] gives the defaults of a
/// policy; the baselines run without sharing, history and admission control, which are part of
/// what NEPHELE adds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SchedulerConfig {
    pub policy: Policy,
    /// How much work (estimated seconds at the worker's measured throughput) may be queued on
    /// one worker ahead of time. Small keeps decisions late (a starved user can still jump the
    /// queue); large hides dispatch latency. A worker with an empty queue always takes one
    /// batch. Ignored by round robin and object-per-worker, which queue everything at once.
    pub horizon: Duration,
    /// Largest ray batch, in pixels (one primary ray per pixel). 65536 rays take about
    /// 0.65 ms on a worker doing 1e8 rays/s (an i-NOLF GPU does about 3e8): long enough to
    /// amortise dispatch and a kernel launch, short enough to spread a frame over the farm.
    pub max_batch_rays: u32,
    /// Height of the pixel bands the coverage estimate is computed in (rows per rectangle).
    pub band_rows: u32,
    /// A task is Heavy when its estimated render time on the median worker (measured rays/s)
    /// exceeds this fraction of its user's frame budget 1/FPS: by the frame-time model
    /// `T_frame = max_i T_i + sum_i D_i / BW + C` (paper eq. 9) such a task is the frame's
    /// critical path, so it gets workers of its own instead of queueing behind light work.
    pub heavy_fraction: f64,
    /// Shared rays across views and users (`None`: every view renders its own).
    pub sharing: Option<ShareTolerance>,
    /// Views derived from an adjacent view of the same frame by reprojection (`None`: every
    /// view renders in full).
    pub derived_views: Option<DerivedViews>,
    /// Entries of the history table of recent results (0 disables it).
    pub history_capacity: usize,
    /// Views rendered ahead of their frames while the farm is idle (`None`: never). Off by
    /// default: it pays only where workers keep previous renders for reuse and the farm's
    /// idle time is not the machine's (BENCHMARKS.md, 2026-12-07: on two cores shared with
    /// the composer it cost latency); `nephele master --render-ahead` turns it on.
    pub render_ahead: Option<RenderAhead>,
    /// How old a history entry may be and still be reused (static objects only; the age bounds
    /// the staleness of anything animated).
    pub history_max_age: Duration,
    /// Refuse new sessions while any user is starved (NEPHELE's admission control)...
    pub admission_control: bool,
    /// ...and for this long after the last round in which someone still open was starved
    /// (a starved user who leaves frees the farm: the hold goes with it). Starvation
    /// flickers on a loaded farm (a user is starved only while its work waits for dispatch),
    /// so an instant check alone lets sessions in between two starved rounds.
    pub admission_hold: Duration,
    /// Admission that looks ahead (with `admission_control`): a new session is refused while
    /// the work its admitted peers ask for (each session's frame rate times the rays its own
    /// frames render, shared work counted once, by the session that rendered it) plus the
    /// newcomer's (the mean of theirs) would pass this fraction of the farm's measured
    /// throughput. `None`: only the starvation refusal. Off in the simulator's baselines.
    pub admit_up_to: Option<f64>,
    /// `Retry-After` of a refusal for capacity (users leave, or nothing changes, on a scale of
    /// seconds); 1 s at most while an admitted session's work estimate is still young (its
    /// first frames, rendered whole before any reuse, overstate it).
    pub capacity_retry: Duration,
    /// Frames of one session that may be in flight at once.
    pub max_frames_in_flight: usize,
    /// Weight of the newest sample in the moving averages (`t_u`, worker throughput).
    pub smoothing: f64,
    /// A batch is re-issued elsewhere when it has not come back after this many times its
    /// expected completion time (queue ahead of it included)...
    pub straggler_factor: f64,
    /// ...and never sooner than this after dispatch.
    pub min_batch_timeout: Duration,
    /// Under uniform overload (no other worker idle) a missed deadline is extended this many
    /// times before the batch is re-issued: a copy would only queue behind another busy
    /// worker's backlog while the first copy keeps running, work wasted on both.
    pub max_deadline_stretches: u32,
    /// A worker silent (no heartbeat, no result) for this long is declared lost; `None` leaves
    /// detection to the caller ([`crate::Scheduler::remove_worker`]).
    pub heartbeat_timeout: Option<Duration>,
    /// Failures (reported or timed out) after which a batch is given up and its frames dropped.
    pub max_attempts: u32,
    /// Expected cost of switching a worker to another object (loading its model into caches):
    /// a placement bias towards workers that last rendered the same object.
    pub object_switch_cost: Duration,
    /// Largest accepted view, in pixels.
    pub max_view_pixels: u64,
    /// Largest number of views in one pose (a 45-view quilt fits).
    pub max_views: usize,
}

impl Default for SchedulerConfig {
    fn default() -> SchedulerConfig {
        SchedulerConfig::for_policy(Policy::Nephele)
    }
}

impl SchedulerConfig {
    /// The defaults of `policy`.
    pub fn for_policy(policy: Policy) -> SchedulerConfig {
        let nephele = policy == Policy::Nephele;
        SchedulerConfig {
            policy,
            horizon: Duration::from_millis(4),
            max_batch_rays: 65_536,
            band_rows: 16,
            heavy_fraction: 0.25,
            sharing: nephele.then(ShareTolerance::default),
            derived_views: nephele.then(DerivedViews::default),
            history_capacity: if nephele { 4096 } else { 0 },
            render_ahead: None,
            history_max_age: Duration::from_millis(500),
            admission_control: nephele,
            admission_hold: Duration::from_secs(1),
            admit_up_to: nephele.then_some(0.9),
            capacity_retry: Duration::from_secs(5),
            max_frames_in_flight: 2,
            smoothing: 0.2,
            straggler_factor: 3.0,
            min_batch_timeout: Duration::from_millis(8),
            max_deadline_stretches: 2,
            heartbeat_timeout: Some(Duration::from_secs(1)),
            max_attempts: 4,
            object_switch_cost: Duration::from_micros(500),
            max_view_pixels: 8192 * 8192,
            max_views: nephele_geometry::camera::MAX_VIEWS,
        }
    }

    pub fn validate(&self) -> Result<(), SchedError> {
        let bad = |what: &str| Err(SchedError::InvalidConfig(what.to_string()));
        if self.horizon.is_zero() {
            return bad("horizon must be positive");
        }
        if self.max_batch_rays == 0 || self.band_rows == 0 {
            return bad("max_batch_rays and band_rows must be at least 1");
        }
        if !(self.heavy_fraction.is_finite() && self.heavy_fraction > 0.0) {
            return bad("heavy_fraction must be a positive number");
        }
        if self.admit_up_to.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
            return bad("admit_up_to must be a positive number");
        }
        if !(self.smoothing > 0.0 && self.smoothing <= 1.0) {
            return bad("smoothing must lie in (0, 1]");
        }
        if !(self.straggler_factor.is_finite() && self.straggler_factor >= 1.0) {
            return bad("straggler_factor must be at least 1");
        }
        if self.max_frames_in_flight == 0 || self.max_attempts == 0 || self.max_views == 0 {
            return bad("max_frames_in_flight, max_attempts and max_views must be at least 1");
        }
        if let Some(t) = self.sharing {
            let steps = [t.position_m, t.angle_rad, t.intrinsics_px];
            if !steps.iter().all(|s| s.is_finite() && *s > 0.0) {
                return bad("sharing tolerances must be finite and positive");
            }
        }
        if let Some(r) = self.render_ahead
            && !(r.budget_fraction.is_finite() && r.budget_fraction > 0.0 && r.budget_fraction <= 1.0)
        {
            return bad("render_ahead's budget_fraction must lie in (0, 1]");
        }
        if let Some(d) = self.derived_views {
            if !(d.max_view_angle_deg.is_finite() && (0.0..=90.0).contains(&d.max_view_angle_deg)) {
                return bad("derived views' max_view_angle_deg must lie in [0, 90]");
            }
            if !(d.work_fraction.is_finite() && d.work_fraction > 0.0 && d.work_fraction <= 2.0) {
                return bad("derived views' work_fraction must lie in (0, 2]");
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn policies_parse_and_defaults_validate() {
        for p in Policy::ALL {
            assert_eq!(p.name().parse::<Policy>(), Ok(p));
            assert!(SchedulerConfig::for_policy(p).validate().is_ok());
        }
        assert!("lottery".parse::<Policy>().expect_err("unknown").contains("round-robin"));
        let baseline = SchedulerConfig::for_policy(Policy::Fifo);
        assert!(baseline.sharing.is_none() && !baseline.admission_control && baseline.history_capacity == 0);
        let bad = SchedulerConfig { smoothing: 0.0, ..Default::default() };
        assert!(bad.validate().is_err());
        let bad = SchedulerConfig {
            sharing: Some(ShareTolerance { position_m: f32::NAN, ..Default::default() }),
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }
}
