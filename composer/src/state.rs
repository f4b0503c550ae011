//! What every part of the composer shares: the configuration, the compositor, the viewer
//! sessions, the farm's results and the counters, behind short-held locks.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::{Arc, Mutex as StdMutex, mpsc as std_mpsc};
use std::time::Instant;

use serde::Serialize;
use tokio::sync::{Notify, broadcast, mpsc};

use crate::config::ComposerConfig;
use crate::encode::EncoderStats;
use crate::fusion::{Compositor, FrameLayout, FusedFrame, SessionCounters, SessionId};
use crate::pose::{Pose, PoseCounters, PoseInbox};
use crate::webrtc::{RtcStack, Viewer, ViewerEvent};

/// Counters of one session's media path.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct MediaCounters {
    pub frames_in: u64,
    pub frames_sent: u64,
    /// Fused frames dropped because the media thread was still busy with the previous one.
    pub frames_dropped_busy: u64,
    /// Times the receiver's feedback moved the stream's bitrate (the encoder re-created).
    pub bitrate_changes: u64,
    /// Fused frames left out because the stream sends one frame in several at its floor
    /// bitrate ([`crate::congestion::RateController::frame_divisor`]).
    pub frames_skipped_for_rate: u64,
    /// Times the stream's resolution moved with its bitrate (`crate::scale`), and frames
    /// sent smaller than fused; the level of the last frame (each side `1 / 2^level`).
    pub resolution_changes: u64,
    pub frames_downscaled: u64,
    pub resolution_level: u32,
    pub encode_errors: u64,
    pub send_errors: u64,
    pub keyframes_requested: u64,
    /// The receiver's bitrate estimates read (REMB; a browser sends them about once a
    /// second) and the latest, in bits per second (0 before the first).
    pub receiver_estimates: u64,
    pub receiver_estimate_bps: u64,
    /// Of those, estimates the controller ignored as implausible
    /// ([`crate::congestion::IMPLAUSIBLE_ESTIMATE_SHARE`]).
    pub receiver_estimates_ignored: u64,
    /// The encoder's bitrate now (the controller's target at the last encoder built).
    pub bitrate_bps: u64,
    /// Time of the last frame: colour conversion, encoding, sending (ms).
    pub last_yuv_ms: f64,
    pub last_encode_ms: f64,
    pub last_send_ms: f64,
    pub bytes_sent: u64,
}

/// What `GET /v1/sessions` reports per session.
#[derive(Debug, Clone, Serialize)]
pub struct SessionReport {
    pub session: SessionId,
    pub connected: bool,
    pub width: u32,
    pub height: u32,
    pub views: u16,
    pub age_s: f64,
    pub fusion: SessionCounters,
    pub poses: PoseCounters,
    pub media: MediaCounters,
    pub encoder: EncoderStats,
    pub control_malformed: u64,
}

pub(crate) struct SessionEntry {
    pub(crate) token: String,
    pub(crate) viewer: Arc<Viewer>,
    pub(crate) layout: FrameLayout,
    pub(crate) frames: std_mpsc::SyncSender<FusedFrame>,
    pub(crate) keyframe: Arc<AtomicBool>,
    pub(crate) inbox: PoseInbox,
    pub(crate) last_pose: Option<Arc<Pose>>,
    pub(crate) media: Arc<StdMutex<(MediaCounters, EncoderStats)>>,
    /// The stream's resolution level (`crate::scale`), set by the media thread; poses go to
    /// the master with their views that much smaller.
    pub(crate) scale_level: Arc<std::sync::atomic::AtomicU32>,
    pub(crate) control_malformed: u64,
    pub(crate) created: Instant,
    pub(crate) next_frame: u64,
    /// The media thread, joined when the session ends (it sends through the runtime, which
    /// must outlive it).
    pub(crate) media_thread: Option<std::thread::JoinHandle<()>>,
}

pub(crate) struct Shared {
    pub(crate) config: ComposerConfig,
    pub(crate) rtc: RtcStack,
    pub(crate) compositor: StdMutex<Compositor>,
    pub(crate) sessions: StdMutex<HashMap<SessionId, SessionEntry>>,
    pub(crate) next_session: AtomicU64,
    pub(crate) wake: Notify,
    pub(crate) events: mpsc::Sender<ViewerEvent>,
    pub(crate) poses: broadcast::Sender<(SessionId, Arc<Pose>)>,
    pub(crate) metrics: crate::metrics::ComposerMetrics,
    pub(crate) runtime: tokio::runtime::Handle,
    /// Messages for the master, while a master link is up.
    pub(crate) to_master: StdMutex<Option<mpsc::UnboundedSender<nephele_proto::Message>>>,
    /// Worker results of the farm's tasks, by task id, until the master releases the task.
    pub(crate) task_results: StdMutex<TaskResults>,
    pub(crate) last_parts: StdMutex<LastParts>,
    /// Poses received, frames planned and the stages of frames sent (farm mode).
    pub(crate) latency: StdMutex<crate::latency::LatencyTracker>,
}

/// Task ids released remembered, so that late results for them are dropped (at 30 fps with a
/// few tasks per frame, minutes of releases).
const RELEASED_REMEMBERED: usize = 1 << 16;

/// Worker results by task id until the master releases the task. A result that arrives
/// after its task's release (the late first copy of a batch the master re-issued after its
/// deadline) is dropped instead of being held forever: nothing would release it again.
#[derive(Debug, Default)]
pub(crate) struct TaskResults {
    held: HashMap<u64, Vec<Arc<nephele_proto::BatchResult>>>,
    released: HashSet<u64>,
    released_order: VecDeque<u64>,
}

impl TaskResults {
    /// Holds `result` for its task; `false` (dropped) when the task was already released.
    pub(crate) fn insert(&mut self, result: nephele_proto::BatchResult) -> bool {
        let task = result.ids.task_id;
        if self.released.contains(&task) {
            return false;
        }
        self.held.entry(task).or_default().push(Arc::new(result));
        true
    }

    /// The master will not name `task` again: forget its results, and drop any that come later.
    pub(crate) fn release(&mut self, task: u64) {
        self.held.remove(&task);
        if self.released.insert(task) {
            self.released_order.push_back(task);
            if self.released_order.len() > RELEASED_REMEMBERED
                && let Some(oldest) = self.released_order.pop_front()
            {
                self.released.remove(&oldest);
            }
        }
    }

    pub(crate) fn get(&self, task: u64) -> Option<&Vec<Arc<nephele_proto::BatchResult>>> {
        self.held.get(&task)
    }

    /// Tasks whose results are held.
    pub(crate) fn len(&self) -> usize {
        self.held.len()
    }
}

/// Pixel sets of each (session, view, object) in the last frame that had them.
pub(crate) type LastParts = HashMap<(SessionId, u32, u64), Arc<[u32]>>;

impl Shared {
    /// Sends `message` to the master if a link is up (dropped otherwise).
    pub(crate) fn to_master(&self, message: nephele_proto::Message) {
        if let Some(tx) = lock(&self.to_master).as_ref() {
            let _ = tx.send(message);
        }
    }
}

pub(crate) fn lock<T>(m: &StdMutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic while holding one of these locks leaves plain data behind; keep serving.
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

pub(crate) fn reports(shared: &Shared) -> Vec<SessionReport> {
    let compositor = lock(&shared.compositor);
    let sessions = lock(&shared.sessions);
    let mut out: Vec<SessionReport> = sessions
        .iter()
        .map(|(&id, e)| {
            let (media, encoder) = *lock(&e.media);
            SessionReport {
                session: id,
                connected: e.viewer.is_connected(),
                width: e.layout.width(),
                height: e.layout.height(),
                views: e.layout.views(),
                age_s: e.created.elapsed().as_secs_f64(),
                fusion: compositor.counters(id).unwrap_or_default(),
                poses: e.inbox.counters(),
                media,
                encoder,
                control_malformed: e.control_malformed,
            }
        })
        .collect();
    out.sort_by_key(|r| r.session);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nephele_proto::{BatchIds, BatchResult, KernelStats, ResultEncoding};

    fn result(task: u64) -> BatchResult {
        BatchResult {
            ids: BatchIds { session_id: 1, frame_id: 1, task_id: task, batch_id: task, view_index: 0 },
            worker_id: 1,
            width: 4,
            height: 4,
            pixels: vec![0],
            color: vec![[0.0; 3]],
            opacity: vec![1.0],
            depth: vec![1.0],
            render_time_us: 1,
            stats: KernelStats::default(),
            encoding: ResultEncoding::F32,
        }
    }

    #[test]
    fn results_after_their_release_are_dropped_not_held_forever() {
        let mut results = TaskResults::default();
        assert!(results.insert(result(7)));
        assert!(results.insert(result(7)), "a re-issued batch's second copy before the release is held");
        assert_eq!(results.get(7).map(Vec::len), Some(2));
        results.release(7);
        assert_eq!((results.len(), results.get(7).is_none()), (0, true));
        assert!(!results.insert(result(7)), "a late copy after the release is dropped");
        assert_eq!(results.len(), 0);
        // Only the last RELEASED_REMEMBERED releases are remembered.
        for task in 100..100 + RELEASED_REMEMBERED as u64 {
            results.release(task);
        }
        assert!(results.insert(result(7)), "forgotten after 2^16 later releases");
        assert!(!results.insert(result(100)));
    }
}
