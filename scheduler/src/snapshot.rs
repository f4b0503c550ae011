//! The scheduler's state as `GET /v1/farm` shows it, and its running counters.

use serde::{Deserialize, Serialize};

use crate::config::Policy;
use crate::{SessionId, WorkerId};

/// Running counters since the scheduler was created.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Calls to `tick`.
    pub rounds: u64,
    /// Rounds in which at least one user was starved.
    pub starved_rounds: u64,
    pub sessions_opened: u64,
    /// `open_session` calls refused by admission control (each retry counts).
    pub sessions_refused: u64,
    /// Of those, refused because the farm's measured throughput would not cover the asked
    /// work ([`crate::SchedulerConfig::admit_up_to`]).
    pub sessions_refused_capacity: u64,
    pub sessions_closed: u64,
    pub frames_released: u64,
    pub frames_completed: u64,
    /// Completed within 1/FPS of their release.
    pub frames_on_time: u64,
    /// Superseded by a newer frame, or given up after repeated batch failures.
    pub frames_dropped: u64,
    pub tasks_created: u64,
    pub tasks_heavy: u64,
    pub tasks_light: u64,
    /// Views that joined a task another view had already created (rendered once, fanned out).
    pub shared_joins: u64,
    /// Views served from the history table.
    pub history_hits: u64,
    /// Rays the frames asked for (every view of every frame, before sharing).
    pub rays_requested: u64,
    /// Rays of the tasks created (what sharing and history left to render).
    pub rays_created: u64,
    /// Rays served by joining a live task.
    pub rays_shared: u64,
    /// Rays served from the history table.
    pub rays_from_history: u64,
    /// Views derived from an adjacent view of their frame (issue 16), and their pixels: the
    /// worker reprojects them and renders only the leftovers (counted in `rays_created`).
    pub views_derived: u64,
    pub rays_derived: u64,
    /// Renders ahead of their frames while the farm was idle ([`crate::RenderAhead`]): tasks
    /// sent, finished, and their rays (not in `tasks_created` / `rays_created`).
    pub ahead_tasks: u64,
    pub ahead_tasks_done: u64,
    pub ahead_rays: u64,
    /// Predicted views left to a render ahead sent for another user's view near them.
    pub ahead_views_covered: u64,
    /// Rays sent to workers, re-issues included.
    pub rays_dispatched: u64,
    /// Rays of batches that came back.
    pub rays_completed: u64,
    pub batches_dispatched: u64,
    pub batches_completed: u64,
    /// Batches sent again after a worker was lost, failed or missed its deadline.
    pub batches_reissued: u64,
    pub batches_timed_out: u64,
    /// Missed deadlines extended instead of re-issued: no other worker was idle.
    pub deadlines_stretched: u64,
    pub batches_failed: u64,
    /// Cancel actions sent (frames superseded or sessions closed while work was in flight).
    pub batches_cancelled: u64,
    pub workers_lost: u64,
    /// Largest reprojection error (pixels) accepted by a shared or history reuse.
    pub share_error_px_max: f32,
    /// Sum of the reprojection errors of all reuses (mean = sum / (shared_joins + history_hits)).
    pub share_error_px_sum: f64,
}

impl Stats {
    /// Mean reprojection error of the reuses, pixels.
    pub fn share_error_px_mean(&self) -> f64 {
        let n = self.shared_joins + self.history_hits;
        if n == 0 { 0.0 } else { self.share_error_px_sum / n as f64 }
    }
}

/// One worker as the scheduler sees it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkerSnapshot {
    pub id: WorkerId,
    pub declared_rays_per_s: f64,
    /// Moving average of the throughput measured from its results.
    pub measured_rays_per_s: f64,
    /// `idle`, `light`, or `heavy:o<ID>` (dedicated to that object's heavy tasks).
    pub mode: String,
    pub draining: bool,
    pub in_flight_batches: usize,
    /// Estimated work queued on it.
    pub backlog_ms: f64,
    pub batches_done: u64,
    pub rays_done: u64,
    pub last_seen_s: f64,
}

/// One user session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionSnapshot {
    pub id: SessionId,
    pub target_fps: f64,
    /// Moving average of the completed-frame rate.
    pub achieved_fps: Option<f64>,
    /// `t_u`: moving average of the frame completion time (first dispatch to last batch).
    pub frame_time_ms: Option<f64>,
    /// `w_u = 1/FPS_u - t_u`.
    pub wait_ms: f64,
    /// `T_last_frame + w_u` of the oldest frame with work not yet dispatched.
    pub target_time_s: Option<f64>,
    pub starved: bool,
    pub objects: usize,
    pub views: usize,
    pub frames_in_flight: usize,
    pub pending_batches: u64,
    pub loaded_batches: u64,
    pub frames_released: u64,
    pub frames_completed: u64,
    pub frames_on_time: u64,
    pub frames_dropped: u64,
    /// Moving average of release-to-completion latency.
    pub latency_ms: Option<f64>,
}

/// Queues and tables.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueueSnapshot {
    pub pending_batches: usize,
    pub in_flight_batches: usize,
    /// Pending rays weighted by their object's cost per ray.
    pub pending_work_rays: f64,
    /// Tasks not finished yet.
    pub live_tasks: usize,
    /// Finished tasks whose results are still held for a frame or the history table.
    pub held_results: usize,
    pub history_entries: usize,
}

/// Everything `GET /v1/farm` returns.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FarmSnapshot {
    pub now_s: f64,
    pub policy: Policy,
    pub admission_open: bool,
    /// Seconds a refused client should wait (`Retry-After`), when admission is closed.
    pub retry_after_s: Option<u64>,
    pub starved_sessions: usize,
    /// Rays per second the farm can render (sum of measured throughputs).
    pub capacity_rays_per_s: f64,
    pub workers: Vec<WorkerSnapshot>,
    pub sessions: Vec<SessionSnapshot>,
    pub queues: QueueSnapshot,
    pub stats: Stats,
}
