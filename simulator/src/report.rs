//! What a run measured, as a table for people and CSV for tools.

use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// Per-user results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UserMetrics {
    pub user: String,
    pub admitted: bool,
    pub refusals: u32,
    pub target_fps: f64,
    /// Seconds between admission and departure (or the end of the run).
    pub active_s: f64,
    pub frames_completed: u64,
    /// Completed within 1/FPS of release, composition included.
    pub frames_on_time: u64,
    pub frames_dropped: u64,
    pub achieved_fps: f64,
    /// FPS attainment: on-time frames over the frames the user wanted (`active_s x fps`),
    /// at most 1. Frames never released because the farm was behind count as missed.
    pub attainment: f64,
    pub latency_p50_ms: f64,
}

/// One (scenario, policy) row.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub scenario: String,
    pub policy: String,
    pub users: usize,
    pub admitted: usize,
    /// Refused session requests (retries included).
    pub refusals: u64,
    /// Mean and minimum FPS attainment over admitted users.
    pub attainment_mean: f64,
    pub attainment_min: f64,
    /// Frame latency, release to composed (all completed frames of all users).
    pub latency_p50_ms: f64,
    pub latency_p99_ms: f64,
    /// Busy time over connected time, all workers.
    pub utilisation: f64,
    /// Rays the frames asked for (every view, before sharing).
    pub rays_requested: u64,
    /// Rays the workers rendered (re-issued and aborted work included).
    pub rays_rendered: u64,
    /// Pixels of the frames the users were shown (completed frames x views x width x height).
    pub pixels_displayed: u64,
    /// Frames the scheduler released (all users, frames in flight at the end included).
    pub frames_released: u64,
    pub frames_completed: u64,
    pub frames_dropped: u64,
    pub batches_reissued: u64,
    pub shared_joins: u64,
    pub history_hits: u64,
    /// Largest reprojection error accepted by sharing, pixels.
    pub share_error_px_max: f64,
    /// Jain's fairness index over admitted users' achieved/target FPS.
    pub jain: f64,
}

impl Summary {
    /// Share of requested rays not rendered thanks to sharing and history (negative when
    /// re-issues cost more than sharing saved).
    pub fn rays_saved(&self) -> f64 {
        if self.rays_requested == 0 { 0.0 } else { 1.0 - self.rays_rendered as f64 / self.rays_requested as f64 }
    }

    /// Rays rendered per pixel shown: below 1 where pixels need no ray (the object does not
    /// cover them) or come from another user's rays; above 1 where work was thrown away.
    pub fn rays_per_displayed_pixel(&self) -> f64 {
        if self.pixels_displayed == 0 { 0.0 } else { self.rays_rendered as f64 / self.pixels_displayed as f64 }
    }
}

/// A run's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub summary: Summary,
    pub users: Vec<UserMetrics>,
}

/// Column header of [`table`].
pub fn table_header() -> String {
    format!(
        "{:<13} {:<17} {:>7} {:>7} {:>7} {:>6} {:>7} {:>7} {:>5} {:>9} {:>9} {:>6} {:>6} {:>6} {:>6} {:>5}",
        "scenario",
        "policy",
        "users",
        "refused",
        "attain%",
        "min%",
        "p50 ms",
        "p99 ms",
        "util%",
        "req Mray",
        "rend Mray",
        "saved%",
        "ray/px",
        "err px",
        "reiss",
        "jain"
    )
}

/// One table line.
pub fn table_row(s: &Summary) -> String {
    format!(
        "{:<13} {:<17} {:>7} {:>7} {:>7.1} {:>6.1} {:>7.1} {:>7.1} {:>5.1} {:>9.1} {:>9.1} {:>6.1} {:>6.3} {:>6.2} {:>6} {:>5.3}",
        s.scenario,
        s.policy,
        format!("{}/{}", s.admitted, s.users),
        s.refusals,
        100.0 * s.attainment_mean,
        100.0 * s.attainment_min,
        s.latency_p50_ms,
        s.latency_p99_ms,
        100.0 * s.utilisation,
        s.rays_requested as f64 * 1e-6,
        s.rays_rendered as f64 * 1e-6,
        100.0 * s.rays_saved(),
        s.rays_per_displayed_pixel(),
        s.share_error_px_max,
        s.batches_reissued,
        s.jain
    )
}

/// The table, with a blank line between scenarios.
pub fn table(rows: &[Summary]) -> String {
    let mut out = table_header();
    out.push('\n');
    let mut previous: Option<&str> = None;
    for row in rows {
        if previous.is_some_and(|p| p != row.scenario) {
            out.push('\n');
        }
        previous = Some(&row.scenario);
        out.push_str(&table_row(row));
        out.push('\n');
    }
    out
}

pub const CSV_HEADER: &str = "scenario,policy,users,admitted,refusals,attainment_mean,attainment_min,latency_p50_ms,latency_p99_ms,utilisation,rays_requested,rays_rendered,rays_saved,pixels_displayed,rays_per_displayed_pixel,frames_released,frames_completed,frames_dropped,batches_reissued,shared_joins,history_hits,share_error_px_max,jain";

/// The rows as CSV (header included).
pub fn csv(rows: &[Summary]) -> String {
    let mut out = String::from(CSV_HEADER);
    out.push('\n');
    for s in rows {
        let _ = writeln!(
            out,
            "{},{},{},{},{},{:.6},{:.6},{:.3},{:.3},{:.6},{},{},{:.6},{},{:.6},{},{},{},{},{},{},{:.3},{:.6}",
            s.scenario,
            s.policy,
            s.users,
            s.admitted,
            s.refusals,
            s.attainment_mean,
            s.attainment_min,
            s.latency_p50_ms,
            s.latency_p99_ms,
            s.utilisation,
            s.rays_requested,
            s.rays_rendered,
            s.rays_saved(),
            s.pixels_displayed,
            s.rays_per_displayed_pixel(),
            s.frames_released,
            s.frames_completed,
            s.frames_dropped,
            s.batches_reissued,
            s.shared_joins,
            s.history_hits,
            s.share_error_px_max,
            s.jain
        );
    }
    out
}
