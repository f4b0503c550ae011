//! NEPHELE Algorithm 1 and its baselines, as one event-driven state machine.
//!
//! # The model
//!
//! * A **session** (user) has a target frame rate `FPS_u`, a list of objects, and its latest
//!   pose (one camera per view: 1 for a screen, 2 for a headset, 45 for a quilt). The core
//!   releases a **frame** every `1/FPS_u` (at most `max_frames_in_flight` at once): the
//!   TaskAssigner turns (views x objects) into **tasks** (one object seen from one camera,
//!   with its `nhit` estimate) and each task into ray **batches**.
//! * `t_u` is the moving average of the user's frame completion time, measured from the first
//!   dispatch of a frame to its last batch (the time a frame needs once it runs); the wait time
//!   is `w_u = 1/FPS_u - t_u` and `target_time = T_last_frame + w_u`, where `T_last_frame` is
//!   the release time of the user's oldest frame still waiting for dispatch (the moment its
//!   previous frame interval ended). So `target_time` is the latest start that still delivers
//!   the frame within `1/FPS_u`. A user whose target time has passed while it still has work
//!   waiting is **starved**.
//! * Each round ([`Scheduler::tick`]), NEPHELE sorts the users: starved ones first (most
//!   overdue first), then the others by loaded tasks (batches in flight, fewest first) and
//!   target time. It then fills the farm up to its ray capacity (every worker holding at most
//!   `horizon` of queued work) user by user; within a user, tasks shared with other users
//!   first (their completion serves every subscriber), then dedicated ones. While anyone is
//!   starved, [`Scheduler::admission`] refuses new sessions.
//! * **HeavyFarm / LightFarm**: a task is Heavy when its estimated time on the median worker
//!   exceeds `heavy_fraction` of its user's frame budget. A Heavy task's batches go to workers
//!   dedicated to it (`heavy:oN:tM` mode: no light batch queues there until they drain),
//!   `ceil(estimate / (heavy_fraction * budget))` of them (idle ones first, then light ones
//!   converted), so that it takes about `heavy_fraction` of the budget. Light tasks are
//!   packed onto the other workers, least backlog first, with a bias (`object_switch_cost`)
//!   towards the worker that last rendered the same object. Workers still idle after that
//!   round are lent to heavy tasks beyond their share (work conservation).
//! * **Shared rays**: views whose quantised cameras ([`crate::CameraKey`]) agree, on the same
//!   object, are one task; every frame that needs it subscribes and the result is fanned out.
//!   Finished tasks stay in a bounded **history table** for `history_max_age`, so a view that
//!   asks again for the same rays (a user standing still, a quilt on a desk) reuses them.
//! * **Resiliency**: a batch whose worker is removed or falls silent, or that misses its
//!   deadline (`straggler_factor` x its expected completion), is put back at the head of the
//!   queue and sent to another worker; the slow copy is cancelled, and whichever copy answers
//!   first counts. Under uniform overload (no other worker idle) a missed deadline of the
//!   batch its holder is rendering is extended instead, `max_deadline_stretches` times: a
//!   copy would only wait behind another worker's backlog. A frame completes only when every
//!   batch of every task it needs is in. A newer frame completing first supersedes older ones
//!   (they are dropped, not shown late).
//!
//! # What the composer is told
//!
//! Workers send their results to the composer tagged with batch and task ids;
//! [`Action::FrameComplete`] lists the tasks that make up a frame (view, object, depth). The
//! composer keeps a task's results until [`Action::ReleaseResult`]; a task in the history
//! table is released when it leaves the table.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::time::Duration;

use nephele_geometry::Bounds;
use nephele_geometry::ViewProjection;
use nephele_geometry::camera::Camera;
use serde::{Deserialize, Serialize};

use crate::assign::{self, CameraKey, OccupancyGrid, PixelSet, TaskClass};
use crate::config::{DerivedViews, MAX_FPS, Policy, SchedulerConfig};
use crate::history::{History, ResultKey};
use crate::snapshot::{FarmSnapshot, QueueSnapshot, SessionSnapshot, Stats, WorkerSnapshot};
use crate::{BatchId, FrameId, IdMap, ObjectId, SchedError, SessionId, TaskId, Time, WorkerId};

/// Frames after which a session's work estimate counts as settled (with the default
/// smoothing 0.2 its first frame then weighs under 11 %).
const ESTIMATE_SETTLING_FRAMES: u64 = 10;
/// `Retry-After` of a capacity refusal while some admitted session's estimate is settling.
const SETTLING_RETRY: Duration = Duration::from_secs(1);

/// An object instance the farm can render.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectInfo {
    /// World-space box holding all its matter (the kernel's `bounds()`).
    pub bounds: Bounds,
    /// Optional tighter proxy inside the box.
    pub occupancy: Option<OccupancyGrid>,
    /// Cost of one ray relative to the unit the workers' throughput is measured in (1.0 = the
    /// kernel the throughput was measured with).
    pub cost_per_ray: f64,
    /// An image-space kernel (the environment's stereo GI U-Net, issue 13): its tasks cover
    /// every pixel of the view (an environment has matter behind every pixel) in bands of
    /// whole rows, one per worker (a convolutional network needs its neighbourhood: the
    /// kernel shades a margin of rows around its band), and a stereo frame's two eyes share
    /// their bands (one pass of the stereo model, the right eye riding as a derived view).
    pub full_frame: bool,
}

/// What a client asks for when it opens a session.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionSpec {
    pub target_fps: f64,
    pub objects: Vec<ObjectId>,
}

/// Whether a new session may start now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admission {
    Admit,
    /// HTTP 503 with `Retry-After: retry_after` (whole seconds).
    Refuse {
        retry_after: Duration,
    },
}

/// A batch to send to a worker.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchSpec {
    pub id: BatchId,
    pub task: TaskId,
    pub object: ObjectId,
    /// The worker generates the rays itself from the camera and the pixel set.
    pub camera: Camera,
    pub pixels: PixelSet,
    pub rays: u64,
    pub class: TaskClass,
    /// 1 for the first dispatch, more for re-issues.
    pub attempt: u32,
    /// The earliest deadline (release + 1/FPS) of the frames waiting for it.
    pub frame_deadline: Time,
    /// When the scheduler will give up on this copy and re-issue it.
    pub timeout: Time,
    /// Frames its results feed (for the composer address of each session).
    pub frames: Vec<(SessionId, FrameId)>,
    /// Views derived from this batch's pixels on the worker (issue 16): each one's result
    /// goes to the composer under its own task; they finish with the batch.
    pub derived: Vec<DerivedSpec>,
    /// Work in pixels' worth: `rays` plus the derived views' pixels at
    /// [`crate::DerivedViews::work_fraction`] (times the object's `cost_per_ray` for rays of
    /// the reference kernel).
    pub work_rays: f64,
    /// It holds every pixel of its task's coverage in the rows it spans (no row is split
    /// with another batch), so the pixels of its bounding box it lacks are empty.
    pub rows_complete: bool,
    /// A render ahead for this session's next frames ([`crate::RenderAhead`]): the worker
    /// keeps it as the session's source and sends no result (`frames` is empty).
    pub ahead_for: Option<SessionId>,
}

/// A view whose pixels in a batch's rows are derived from that batch (see [`BatchSpec`]).
#[derive(Debug, Clone, PartialEq)]
pub struct DerivedSpec {
    pub task: TaskId,
    pub camera: Camera,
    /// Within the rows the batch spans.
    pub pixels: PixelSet,
    pub rays: u64,
    pub frames: Vec<(SessionId, FrameId)>,
}

/// How a view of a frame got its pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PartSource {
    /// A task created for this frame.
    Rendered,
    /// A task another view (or user) created, rendered once for all.
    Shared,
    /// A result from the history table.
    History,
    /// Derived from an adjacent view of the same frame by reprojection on the worker, only
    /// its leftovers rendered ([`crate::DerivedViews`]).
    Derived,
}

/// One object in one view of a frame, and the task whose results fill it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FramePart {
    pub view: u32,
    pub object: ObjectId,
    pub task: TaskId,
    pub rays: u64,
    pub mean_depth: f32,
    pub source: PartSource,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DropReason {
    /// A newer frame of the same session completed first.
    Superseded,
    /// A batch failed `max_attempts` times.
    BatchFailed(BatchId),
}

/// A decision of the scheduler, for the caller to carry out.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    Dispatch {
        worker: WorkerId,
        batch: Box<BatchSpec>,
    },
    /// Stop (or skip) a batch sent earlier: superseded frame, closed session, or re-issued.
    Cancel {
        worker: WorkerId,
        batch: BatchId,
    },
    FrameComplete {
        session: SessionId,
        frame: FrameId,
        released: Time,
        /// Width and height of the frame's views (those of the pose it was released with).
        view_size: (u32, u32),
        latency: Duration,
        /// `latency <= 1/FPS`.
        on_time: bool,
        parts: Vec<FramePart>,
    },
    FrameDropped {
        session: SessionId,
        frame: FrameId,
        reason: DropReason,
    },
    /// A worker missed its heartbeats; its batches were re-issued. The caller should close it.
    WorkerLost {
        worker: WorkerId,
        reissued: u32,
    },
    /// No frame and no history entry needs this task's results any more.
    ReleaseResult {
        task: TaskId,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Idle,
    Light,
    /// Dedicated to one heavy task (of this object) until its queue drains.
    Heavy(TaskId, ObjectId),
}

#[derive(Debug)]
struct Worker {
    declared: f64,
    measured: f64,
    draining: bool,
    mode: Mode,
    in_flight: Vec<BatchId>,
    backlog_s: f64,
    last_object: Option<ObjectId>,
    last_seen: Time,
    /// When the worker finished its previous batch (the start of the current one, FIFO).
    service_mark: Time,
    batches_done: u64,
    rays_done: u64,
}

#[derive(Debug)]
struct Frame {
    id: FrameId,
    released: Time,
    /// Width and height of its views (the pose's; a stream coded smaller asks for smaller).
    view_size: (u32, u32),
    first_dispatch: Option<Time>,
    parts: Vec<FramePart>,
    /// Parts whose task is not finished.
    remaining: u32,
    /// Batches not yet dispatched, over its tasks.
    pending: u64,
    /// Every part before this one has no batch waiting for dispatch (reset by a re-issue).
    cursor: usize,
}

#[derive(Debug)]
struct Session {
    fps: f64,
    period: Duration,
    objects: Vec<ObjectId>,
    views: Vec<Camera>,
    /// When `views` arrived, and the pose before them with its time: the motion that
    /// render-ahead extrapolates.
    pose_at: Option<Time>,
    earlier_pose: Option<(Time, Vec<Camera>)>,
    /// The release the last renders ahead were made for, and those still running.
    ahead_release: Option<Time>,
    ahead_tasks: Vec<TaskId>,
    next_release: Option<Time>,
    frames: VecDeque<Frame>,
    next_frame: u64,
    /// `t_u`, seconds.
    frame_time: Option<f64>,
    latency: Option<f64>,
    interval: Option<f64>,
    last_complete: Option<Time>,
    /// Batches in flight over the tasks of its frames ("loaded tasks").
    loaded: u64,
    /// The last planning round that found it starved: admission holds for
    /// `admission_hold` after it, while the session stays open.
    last_starved: Option<Time>,
    /// Moving average of the work (rays x cost) its frames asked the farm to render: the
    /// parts it rendered itself, not those it shared or took from the history.
    work_per_frame: Option<f64>,
    released: u64,
    completed: u64,
    on_time: u64,
    dropped: u64,
}

#[derive(Debug)]
struct Task {
    object: ObjectId,
    camera: Camera,
    key: Option<CameraKey>,
    class: TaskClass,
    rays: u64,
    mean_depth: f32,
    cost: f64,
    workers_wanted: usize,
    batches: Vec<BatchId>,
    pending: BTreeSet<BatchId>,
    in_flight: u64,
    remaining: usize,
    subscribers: Vec<(SessionId, FrameId)>,
    /// Frames referencing it, plus one while it is in the history table.
    refs: u32,
    done: bool,
    /// Its pixels ride on another task's batches (it is no key for others).
    derived: bool,
    /// The session whose frame created it (or that it renders ahead for).
    creator: SessionId,
    /// Rendered ahead of any frame for its creator ([`crate::RenderAhead`]): no frame
    /// subscribes, the worker keeps it, it leaves when done.
    ahead: bool,
}

impl Task {
    /// Nothing of it dispatched, finished or riding elsewhere: it may still become a key or
    /// be derived.
    fn is_fresh(&self) -> bool {
        self.in_flight == 0 && self.pending.len() == self.batches.len() && !self.done && !self.derived
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum BatchState {
    Pending,
    InFlight {
        worker: WorkerId,
        dispatched: Time,
        deadline: Time,
        est_s: f64,
    },
    /// Its result is in; the record goes with its task.
    Done,
}

#[derive(Debug)]
struct Batch {
    task: TaskId,
    pixels: PixelSet,
    rays: u64,
    state: BatchState,
    failures: u32,
    dispatches: u32,
    /// Missed deadlines of its current dispatch that were extended.
    stretches: u32,
    /// Workers that held it before (excluded when re-issuing; their late answer still counts).
    previous: Vec<WorkerId>,
    /// Views derived from its pixels; each finishes with it.
    riders: Vec<Rider>,
}

/// A derived view's pixels in one batch's rows (see [`DerivedSpec`]).
#[derive(Debug, Clone)]
struct Rider {
    task: TaskId,
    pixels: PixelSet,
    rays: u64,
}

/// Work of a batch in reference rays: its own plus its riders' at `fraction`.
fn batch_work(b: &Batch, cost: f64, fraction: f64) -> f64 {
    (b.rays as f64 + fraction * b.riders.iter().map(|r| r.rays as f64).sum::<f64>()) * cost
}

/// The scheduler core. See the module documentation for the model; every method takes the
/// current time and never reads a clock. Time never goes backwards: an event stamped earlier
/// than one already seen is treated as happening at the latest time seen.
#[derive(Debug)]
pub struct Scheduler {
    config: SchedulerConfig,
    now: Time,
    objects: BTreeMap<ObjectId, ObjectInfo>,
    workers: BTreeMap<WorkerId, Worker>,
    sessions: BTreeMap<SessionId, Session>,
    tasks: IdMap<TaskId, Task>,
    batches: IdMap<BatchId, Batch>,
    live: HashMap<ResultKey, TaskId>,
    history: History,
    pending_all: BTreeSet<BatchId>,
    pending_work: f64,
    deadlines: BTreeSet<(Time, BatchId)>,
    outbox: Vec<Action>,
    next_session: u64,
    next_task: u64,
    next_batch: u64,
    rr_cursor: usize,
    bindings: BTreeMap<ObjectId, WorkerId>,
    starved_now: usize,
    stats: Stats,
}

fn secs(d: Duration) -> f64 {
    d.as_secs_f64()
}

fn micros_i(t: Time) -> i128 {
    i128::from(t.as_micros())
}

impl Scheduler {
    pub fn new(config: SchedulerConfig) -> Result<Scheduler, SchedError> {
        config.validate()?;
        Ok(Scheduler {
            history: History::new(config.history_capacity),
            config,
            now: Time::ZERO,
            objects: BTreeMap::new(),
            workers: BTreeMap::new(),
            sessions: BTreeMap::new(),
            tasks: IdMap::default(),
            batches: IdMap::default(),
            live: HashMap::new(),
            pending_all: BTreeSet::new(),
            pending_work: 0.0,
            deadlines: BTreeSet::new(),
            outbox: Vec::new(),
            next_session: 1,
            next_task: 1,
            next_batch: 1,
            rr_cursor: 0,
            bindings: BTreeMap::new(),
            starved_now: 0,
            stats: Stats::default(),
        })
    }

    pub fn config(&self) -> &SchedulerConfig {
        &self.config
    }

    pub fn stats(&self) -> &Stats {
        &self.stats
    }

    /// The latest time the scheduler has seen.
    pub fn now(&self) -> Time {
        self.now
    }

    fn advance(&mut self, now: Time) -> Time {
        self.now = self.now.max(now);
        self.now
    }

    // ----------------------------------------------------------------------------------------
    // Objects, workers, sessions, poses.

    /// Registers an object instance. Registering the same id again with the same description
    /// is a no-op; with a different one, an error.
    pub fn register_object(&mut self, id: ObjectId, info: ObjectInfo) -> Result<(), SchedError> {
        let invalid = |reason: &str| SchedError::InvalidObject { id, reason: reason.to_string() };
        let b = info.bounds;
        if !(b.min.is_finite() && b.max.is_finite()) {
            return Err(invalid("bounds are not finite"));
        }
        if !b.min.cmple(b.max).all() {
            return Err(invalid("bounds min exceeds max"));
        }
        if !(info.cost_per_ray.is_finite() && info.cost_per_ray > 0.0) {
            return Err(invalid("cost per ray must be a finite positive number"));
        }
        match self.objects.get(&id) {
            Some(existing) if *existing == info => Ok(()),
            Some(_) => Err(SchedError::DuplicateObject(id)),
            None => {
                self.objects.insert(id, info);
                Ok(())
            }
        }
    }

    /// A worker joins with its measured throughput (rays/s of a cost-1 kernel).
    pub fn add_worker(&mut self, id: WorkerId, rays_per_s: f64, now: Time) -> Result<(), SchedError> {
        let now = self.advance(now);
        if !(rays_per_s.is_finite() && rays_per_s > 0.0) {
            return Err(SchedError::InvalidThroughput(rays_per_s));
        }
        if self.workers.contains_key(&id) {
            return Err(SchedError::DuplicateWorker(id));
        }
        self.workers.insert(
            id,
            Worker {
                declared: rays_per_s,
                measured: rays_per_s,
                draining: false,
                mode: Mode::Idle,
                in_flight: Vec::new(),
                backlog_s: 0.0,
                last_object: None,
                last_seen: now,
                service_mark: now,
                batches_done: 0,
                rays_done: 0,
            },
        );
        Ok(())
    }

    /// A worker left (connection closed, process died): its batches are re-issued.
    pub fn remove_worker(&mut self, id: WorkerId, now: Time) -> Result<(), SchedError> {
        self.advance(now);
        if !self.workers.contains_key(&id) {
            return Err(SchedError::UnknownWorker(id));
        }
        self.drop_worker(id);
        Ok(())
    }

    /// The worker is shutting down: it gets no new batches, finishes (or returns) its own.
    pub fn drain_worker(&mut self, id: WorkerId, now: Time) -> Result<(), SchedError> {
        let now = self.advance(now);
        let w = self.workers.get_mut(&id).ok_or(SchedError::UnknownWorker(id))?;
        w.draining = true;
        w.last_seen = now;
        Ok(())
    }

    /// The worker is alive.
    pub fn heartbeat(&mut self, id: WorkerId, now: Time) -> Result<(), SchedError> {
        let now = self.advance(now);
        let w = self.workers.get_mut(&id).ok_or(SchedError::UnknownWorker(id))?;
        w.last_seen = now;
        Ok(())
    }

    /// NEPHELE's admission control: refuse while any user is starved (and for
    /// `admission_hold` after a round that found one starved). Only open sessions count: a
    /// starved user who leaves frees the farm, and the next one is admitted at once rather
    /// than after the hold.
    pub fn admission(&self, now: Time) -> Admission {
        let now = self.now.max(now);
        if !self.config.admission_control {
            return Admission::Admit;
        }
        let hold = self.config.admission_hold;
        let recently = |s: &Session| s.last_starved.is_some_and(|t| now.since(t) < hold);
        if self.sessions.values().any(|s| recently(s) || self.is_starved(s, now)) {
            return Admission::Refuse { retry_after: self.retry_after() };
        }
        Admission::Admit
    }

    /// Admission that looks ahead ([`crate::SchedulerConfig::admit_up_to`]): `Some(retry
    /// after)` when a newcomer asking `fps` would take the admitted sessions' asked work past
    /// the allowed share of the farm's measured throughput. Admits while no session has
    /// released a frame yet (nothing is known of the work) or no worker is connected.
    fn over_capacity(&self, fps: f64) -> Option<Duration> {
        let share = self.config.admit_up_to.filter(|_| self.config.admission_control)?;
        let measured: Vec<f64> = self.sessions.values().filter_map(|s| s.work_per_frame).collect();
        if measured.is_empty() {
            return None;
        }
        let mean = measured.iter().sum::<f64>() / measured.len() as f64;
        let asked: f64 = self.sessions.values().map(|s| s.fps * s.work_per_frame.unwrap_or(mean)).sum();
        let capacity: f64 = self.workers.values().filter(|w| !w.draining).map(|w| w.measured).sum();
        if !(capacity > 0.0 && asked + fps * mean > share * capacity) {
            return None;
        }
        // A young estimate is mostly its session's first frames, rendered whole before any
        // previous frame could be reused: it falls within a second or so, so ask again soon.
        // A session that has released nothing has no estimate of its own (and may never get
        // one: a viewer that never sends a pose), so it does not count.
        let settling = self.sessions.values().any(|s| (1..ESTIMATE_SETTLING_FRAMES).contains(&s.released));
        Some(if settling { self.config.capacity_retry.min(SETTLING_RETRY) } else { self.config.capacity_retry })
    }

    /// Time for the farm to work off its queue, whole seconds in 1..=30.
    fn retry_after(&self) -> Duration {
        let capacity: f64 = self.workers.values().filter(|w| !w.draining).map(|w| w.measured).sum();
        let seconds = if capacity > 0.0 { (self.pending_work / capacity).ceil() } else { 5.0 };
        Duration::from_secs(seconds.clamp(1.0, 30.0) as u64)
    }

    /// Opens a session if admission allows it.
    pub fn open_session(&mut self, spec: SessionSpec, now: Time) -> Result<SessionId, SchedError> {
        let now = self.advance(now);
        if !(spec.target_fps.is_finite() && spec.target_fps > 0.0 && spec.target_fps <= MAX_FPS) {
            return Err(SchedError::InvalidFps(spec.target_fps));
        }
        if spec.objects.is_empty() {
            return Err(SchedError::NoObjects);
        }
        let mut objects = Vec::with_capacity(spec.objects.len());
        for id in spec.objects {
            if !self.objects.contains_key(&id) {
                return Err(SchedError::UnknownObject(id));
            }
            if !objects.contains(&id) {
                objects.push(id);
            }
        }
        if let Admission::Refuse { retry_after } = self.admission(now) {
            self.stats.sessions_refused += 1;
            return Err(SchedError::Refused { retry_after });
        }
        if let Some(retry_after) = self.over_capacity(spec.target_fps) {
            self.stats.sessions_refused += 1;
            self.stats.sessions_refused_capacity += 1;
            return Err(SchedError::Refused { retry_after });
        }
        let id = SessionId(self.next_session);
        self.next_session += 1;
        self.sessions.insert(
            id,
            Session {
                fps: spec.target_fps,
                period: Duration::from_secs_f64(1.0 / spec.target_fps),
                objects,
                views: Vec::new(),
                pose_at: None,
                earlier_pose: None,
                ahead_release: None,
                ahead_tasks: Vec::new(),
                next_release: None,
                frames: VecDeque::new(),
                next_frame: 0,
                frame_time: None,
                latency: None,
                interval: None,
                last_complete: None,
                loaded: 0,
                last_starved: None,
                work_per_frame: None,
                released: 0,
                completed: 0,
                on_time: 0,
                dropped: 0,
            },
        );
        self.stats.sessions_opened += 1;
        Ok(id)
    }

    /// Closes a session: its frames are abandoned, work only it needed is cancelled.
    pub fn close_session(&mut self, id: SessionId, now: Time) -> Result<(), SchedError> {
        self.advance(now);
        let frames = match self.sessions.get_mut(&id) {
            Some(s) => std::mem::take(&mut s.frames),
            None => return Err(SchedError::UnknownSession(id)),
        };
        for frame in &frames {
            self.unsubscribe(id, frame);
        }
        let ahead = self.sessions.get(&id).map(|s| s.ahead_tasks.clone()).unwrap_or_default();
        for tid in ahead {
            self.drop_ahead(tid);
        }
        self.sessions.remove(&id);
        self.stats.sessions_closed += 1;
        Ok(())
    }

    /// The user's latest pose: one camera per view. Frames are rendered from the latest pose at
    /// their release.
    pub fn pose(&mut self, id: SessionId, views: &[Camera], now: Time) -> Result<(), SchedError> {
        let now = self.advance(now);
        if !self.sessions.contains_key(&id) {
            return Err(SchedError::UnknownSession(id));
        }
        if views.is_empty() || views.len() > self.config.max_views {
            return Err(SchedError::InvalidPose(format!(
                "{} views (expected 1..={})",
                views.len(),
                self.config.max_views
            )));
        }
        for (i, v) in views.iter().enumerate() {
            let pixels = u64::from(v.width()) * u64::from(v.height());
            if pixels > self.config.max_view_pixels {
                return Err(SchedError::InvalidPose(format!(
                    "view {i} has {pixels} pixels (at most {})",
                    self.config.max_view_pixels
                )));
            }
        }
        let s = self.sessions.get_mut(&id).ok_or(SchedError::UnknownSession(id))?;
        let earlier = std::mem::replace(&mut s.views, views.to_vec());
        s.earlier_pose = s.pose_at.map(|at| (at, earlier));
        s.pose_at = Some(now);
        if s.next_release.is_none() {
            s.next_release = Some(now);
        }
        Ok(())
    }

    /// [`Scheduler::pose`] from the matrices a WebXR client sends; a NaN, singular or
    /// non-perspective matrix is an error naming the view.
    pub fn pose_matrices(&mut self, id: SessionId, views: &[ViewProjection], now: Time) -> Result<(), SchedError> {
        let cameras = views
            .iter()
            .enumerate()
            .map(|(i, v)| v.camera().map_err(|e| SchedError::InvalidPose(format!("view {i}: {e}"))))
            .collect::<Result<Vec<Camera>, SchedError>>()?;
        self.pose(id, &cameras, now)
    }

    // ----------------------------------------------------------------------------------------
    // Results.

    /// A worker returned a batch. A late answer from a worker the batch was taken from still
    /// counts if it is the first; the other copy is cancelled.
    pub fn batch_done(&mut self, worker: WorkerId, batch: BatchId, now: Time) -> Result<(), SchedError> {
        let now = self.advance(now);
        if !self.workers.contains_key(&worker) {
            return Err(SchedError::UnknownWorker(worker));
        }
        let b = self.batches.get(&batch).ok_or(SchedError::UnknownBatch(batch))?;
        let (tid, rays) = (b.task, b.rays);
        let work = self.work_of(batch);
        match b.state {
            // A second copy answering after the first: nothing to do.
            BatchState::Done => return Ok(()),
            BatchState::InFlight { worker: holder, dispatched, est_s, .. } if holder == worker => {
                self.detach(batch, worker, est_s);
                let smoothing = self.config.smoothing;
                if let Some(w) = self.workers.get_mut(&worker) {
                    let start = dispatched.max(w.service_mark);
                    let service = secs(now.since(start)).max(1e-6);
                    let sample = (work / service).clamp(w.declared * 1e-3, w.declared * 1e3);
                    w.measured = (1.0 - smoothing) * w.measured + smoothing * sample;
                    w.service_mark = now;
                    w.batches_done += 1;
                    w.rays_done += rays;
                    w.last_seen = now;
                }
            }
            BatchState::InFlight { worker: holder, est_s, .. } if b.previous.contains(&worker) => {
                self.detach(batch, holder, est_s);
                self.outbox.push(Action::Cancel { worker: holder, batch });
                self.stats.batches_cancelled += 1;
                self.touch(worker, now);
            }
            BatchState::Pending if b.previous.contains(&worker) => {
                self.pending_all.remove(&batch);
                self.pending_work -= self.work_of(batch);
                if let Some(t) = self.tasks.get_mut(&tid) {
                    t.pending.remove(&batch);
                    t.in_flight += 1; // balanced by `finish_batch`
                }
                self.adjust(tid, -1, 1, None);
                self.touch(worker, now);
            }
            _ => return Err(SchedError::NotAssigned { batch, worker }),
        }
        self.finish_batch(batch, tid, rays, now);
        Ok(())
    }

    /// A worker reports that it could not render a batch (kernel error, asset missing): the
    /// batch goes to another worker, or its frames are dropped after `max_attempts` failures.
    pub fn batch_failed(&mut self, worker: WorkerId, batch: BatchId, now: Time) -> Result<(), SchedError> {
        let now = self.advance(now);
        if !self.workers.contains_key(&worker) {
            return Err(SchedError::UnknownWorker(worker));
        }
        let b = self.batches.get(&batch).ok_or(SchedError::UnknownBatch(batch))?;
        match b.state {
            BatchState::InFlight { worker: holder, .. } if holder == worker => {}
            _ => return Err(SchedError::NotAssigned { batch, worker }),
        }
        self.touch(worker, now);
        self.stats.batches_failed += 1;
        self.reissue(batch, true);
        Ok(())
    }

    fn touch(&mut self, worker: WorkerId, now: Time) {
        if let Some(w) = self.workers.get_mut(&worker) {
            w.last_seen = now;
        }
    }

    // ----------------------------------------------------------------------------------------
    // The round.

    /// One scheduling round at `now`: lost workers and missed deadlines are handled, due frames
    /// released, and the policy dispatches. Returns every action decided since the last round.
    pub fn tick(&mut self, now: Time) -> Vec<Action> {
        let now = self.advance(now);
        self.stats.rounds += 1;
        self.check_heartbeats(now);
        self.check_deadlines(now);
        if self.history.enabled() {
            for task in self.history.expire(now, self.config.history_max_age) {
                self.unref(task);
            }
        }
        self.release_frames(now);
        match self.config.policy {
            Policy::Nephele => self.plan_nephele(now),
            Policy::Fifo => self.plan_fifo(now),
            Policy::RoundRobin | Policy::ObjectPerWorker => self.plan_immediate(now),
        }
        std::mem::take(&mut self.outbox)
    }

    /// When the next time-driven decision is due (frame release, batch deadline, heartbeat
    /// timeout); `None` if nothing will happen without a new event.
    pub fn next_wakeup(&self) -> Option<Time> {
        let mut next = self.deadlines.first().map(|&(t, _)| t);
        let mut consider = |t: Time| next = Some(next.map_or(t, |n: Time| n.min(t)));
        for s in self.sessions.values() {
            if let Some(t) = s.next_release.filter(|_| s.frames.len() < self.config.max_frames_in_flight) {
                consider(t);
            }
        }
        if let Some(timeout) = self.config.heartbeat_timeout
            && let Some(t) = self.workers.values().map(|w| w.last_seen + timeout).min()
        {
            consider(t + Duration::from_micros(1));
        }
        next
    }

    fn check_heartbeats(&mut self, now: Time) {
        let Some(timeout) = self.config.heartbeat_timeout else { return };
        let lost: Vec<WorkerId> =
            self.workers.iter().filter(|(_, w)| now.since(w.last_seen) > timeout).map(|(&id, _)| id).collect();
        for id in lost {
            let reissued = self.drop_worker(id);
            self.stats.workers_lost += 1;
            self.outbox.push(Action::WorkerLost { worker: id, reissued });
        }
    }

    fn drop_worker(&mut self, id: WorkerId) -> u32 {
        let in_flight = self.workers.get(&id).map(|w| w.in_flight.clone()).unwrap_or_default();
        for &batch in &in_flight {
            if let Some(b) = self.batches.get_mut(&batch) {
                b.previous.push(id);
            }
            self.reissue(batch, false);
        }
        self.workers.remove(&id);
        self.bindings.retain(|_, w| *w != id);
        in_flight.len() as u32
    }

    fn check_deadlines(&mut self, now: Time) {
        while let Some(&(deadline, batch)) = self.deadlines.first() {
            if deadline > now {
                break;
            }
            self.deadlines.pop_first();
            let Some(b) = self.batches.get(&batch) else { continue };
            let BatchState::InFlight { worker, deadline: d, dispatched, est_s } = b.state else { continue };
            if d != deadline {
                continue;
            }
            self.stats.batches_timed_out += 1;
            // The holder was slower than estimated: trust its throughput less until its
            // results say otherwise.
            if let Some(w) = self.workers.get_mut(&worker) {
                w.measured = (0.5 * w.measured).max(w.declared * 1e-3);
            }
            let rendering = self.workers.get(&worker).is_some_and(|w| w.in_flight.first() == Some(&batch));
            if rendering && b.stretches < self.config.max_deadline_stretches && !self.has_idle_worker_for(batch, worker)
            {
                // The holder is rendering it (its oldest batch; a queued one is better moved)
                // and every other worker is busy: a copy would wait behind another backlog
                // while this one keeps rendering. Wait once more as long as it was given, so a
                // stuck batch still moves after (1 + max_deadline_stretches) times that.
                let first_wait = deadline.since(dispatched) / (b.stretches + 1);
                let deadline = now + first_wait.max(self.config.min_batch_timeout);
                if let Some(b) = self.batches.get_mut(&batch) {
                    b.stretches += 1;
                    b.state = BatchState::InFlight { worker, dispatched, deadline, est_s };
                }
                self.deadlines.insert((deadline, batch));
                self.stats.deadlines_stretched += 1;
                continue;
            }
            self.outbox.push(Action::Cancel { worker, batch });
            self.stats.batches_cancelled += 1;
            if let Some(b) = self.batches.get_mut(&batch) {
                b.previous.push(worker);
            }
            self.reissue(batch, true);
        }
    }

    /// Whether a worker other than `holder` that never held `batch` has nothing in flight
    /// (a re-issued copy would start at once there).
    fn has_idle_worker_for(&self, batch: BatchId, holder: WorkerId) -> bool {
        let previous = self.batches.get(&batch).map_or(&[][..], |b| &b.previous[..]);
        self.workers
            .iter()
            .any(|(id, w)| *id != holder && !w.draining && w.in_flight.is_empty() && !previous.contains(id))
    }

    /// Puts an in-flight batch back in the queue (head: its id is old). `failure` counts
    /// towards `max_attempts`.
    fn reissue(&mut self, batch: BatchId, failure: bool) {
        let Some(b) = self.batches.get_mut(&batch) else { return };
        let BatchState::InFlight { worker, est_s, .. } = b.state else { return };
        let tid = b.task;
        if self.tasks.get(&tid).is_some_and(|t| t.ahead) {
            // A render ahead is not worth a second try (the frame renders what it needs).
            self.detach(batch, worker, est_s);
            if let Some(b) = self.batches.get_mut(&batch) {
                b.state = BatchState::Done;
            }
            self.drop_ahead(tid);
            return;
        }
        if failure {
            b.failures += 1;
            if !b.previous.contains(&worker) {
                b.previous.push(worker);
            }
        }
        let give_up = b.failures >= self.config.max_attempts;
        self.detach(batch, worker, est_s);
        if let Some(b) = self.batches.get_mut(&batch) {
            b.state = BatchState::Pending;
        }
        if let Some(t) = self.tasks.get_mut(&tid) {
            t.in_flight = t.in_flight.saturating_sub(1);
            t.pending.insert(batch);
        }
        self.pending_all.insert(batch);
        self.pending_work += self.work_of(batch);
        self.adjust(tid, 1, -1, None);
        self.stats.batches_reissued += 1;
        if give_up {
            self.fail_task(tid, batch);
        }
    }

    /// Removes an in-flight batch from its worker's books (not from the task's).
    fn detach(&mut self, batch: BatchId, worker: WorkerId, est_s: f64) {
        if let Some(b) = self.batches.get(&batch)
            && let BatchState::InFlight { deadline, .. } = b.state
        {
            self.deadlines.remove(&(deadline, batch));
        }
        if let Some(w) = self.workers.get_mut(&worker) {
            w.in_flight.retain(|&x| x != batch);
            w.backlog_s -= est_s;
            if w.in_flight.is_empty() {
                w.backlog_s = 0.0;
                w.mode = Mode::Idle;
            }
        }
    }

    fn work_of(&self, batch: BatchId) -> f64 {
        let fraction = self.derived_work_fraction();
        self.batches
            .get(&batch)
            .map_or(0.0, |b| batch_work(b, self.tasks.get(&b.task).map_or(1.0, |t| t.cost), fraction))
    }

    /// A batch's result is in (its worker books are already settled).
    fn finish_batch(&mut self, batch: BatchId, tid: TaskId, rays: u64, now: Time) {
        self.stats.batches_completed += 1;
        self.stats.rays_completed += rays;
        let Some(t) = self.tasks.get_mut(&tid) else { return };
        t.in_flight = t.in_flight.saturating_sub(1);
        t.remaining = t.remaining.saturating_sub(1);
        let finished = t.remaining == 0;
        self.adjust(tid, 0, -1, None);
        let riders = match self.batches.get_mut(&batch) {
            Some(b) => {
                b.state = BatchState::Done;
                std::mem::take(&mut b.riders)
            }
            None => Vec::new(),
        };
        // Derived views first: they may complete frames that the key's completion is not
        // part of (another user sharing the derived view's camera).
        self.finish_riders(riders, now);
        if finished {
            self.task_done(tid, now);
        }
    }

    /// Applies changes of a task's pending and in-flight counts to its subscribers' frames and
    /// sessions; marks their first dispatch.
    fn adjust(&mut self, tid: TaskId, d_pending: i64, d_in_flight: i64, dispatched: Option<Time>) {
        let Some(t) = self.tasks.get(&tid) else { return };
        for (sid, fid) in &t.subscribers {
            let Some(s) = self.sessions.get_mut(sid) else { continue };
            s.loaded = s.loaded.saturating_add_signed(d_in_flight);
            if let Some(f) = s.frames.iter_mut().find(|f| f.id == *fid) {
                f.pending = f.pending.saturating_add_signed(d_pending);
                if d_pending > 0 {
                    f.cursor = 0;
                }
                if let Some(at) = dispatched {
                    f.first_dispatch.get_or_insert(at);
                }
            }
        }
    }

    fn task_done(&mut self, tid: TaskId, now: Time) {
        if self.tasks.get(&tid).is_some_and(|t| t.ahead) {
            self.stats.ahead_tasks_done += 1;
            self.drop_ahead(tid);
            return;
        }
        let (key, subscribers, batches) = match self.tasks.get_mut(&tid) {
            Some(t) => {
                t.done = true;
                (t.key.map(|k| (t.object, k)), t.subscribers.clone(), std::mem::take(&mut t.batches))
            }
            None => return,
        };
        for b in batches {
            self.batches.remove(&b);
        }
        if let Some(key) = key {
            if self.live.get(&key) == Some(&tid) {
                self.live.remove(&key);
            }
            if self.history.enabled() {
                if let Some(t) = self.tasks.get_mut(&tid) {
                    t.refs += 1;
                }
                for old in self.history.insert(key, tid, now) {
                    self.unref(old);
                }
            }
        }
        for (sid, fid) in subscribers {
            let complete = match self.sessions.get_mut(&sid).and_then(|s| s.frames.iter_mut().find(|f| f.id == fid)) {
                Some(f) => {
                    f.remaining = f.remaining.saturating_sub(1);
                    f.remaining == 0
                }
                None => false,
            };
            if complete {
                self.complete_frame(sid, fid, now);
            }
        }
    }

    /// All batches of a task failed too often: every frame needing it is dropped.
    fn fail_task(&mut self, tid: TaskId, batch: BatchId) {
        let subscribers = self.tasks.get(&tid).map(|t| t.subscribers.clone()).unwrap_or_default();
        for (sid, fid) in subscribers {
            self.drop_frame(sid, fid, DropReason::BatchFailed(batch));
        }
    }

    fn complete_frame(&mut self, sid: SessionId, fid: FrameId, now: Time) {
        let smoothing = self.config.smoothing;
        let Some(s) = self.sessions.get_mut(&sid) else { return };
        let Some(pos) = s.frames.iter().position(|f| f.id == fid) else { return };
        let Some(frame) = s.frames.remove(pos) else { return };
        let latency = now.since(frame.released);
        let on_time = latency <= s.period;
        let service = secs(now.since(frame.first_dispatch.unwrap_or(now)));
        let ema = |old: Option<f64>, x: f64| Some(old.map_or(x, |o| (1.0 - smoothing) * o + smoothing * x));
        s.frame_time = ema(s.frame_time, service);
        s.latency = ema(s.latency, secs(latency));
        if let Some(last) = s.last_complete {
            s.interval = ema(s.interval, secs(now.since(last)));
        }
        s.last_complete = Some(now);
        s.completed += 1;
        s.on_time += u64::from(on_time);
        let older: Vec<FrameId> = s.frames.iter().filter(|f| f.id < fid).map(|f| f.id).collect();
        self.stats.frames_completed += 1;
        self.stats.frames_on_time += u64::from(on_time);
        self.outbox.push(Action::FrameComplete {
            session: sid,
            frame: fid,
            released: frame.released,
            view_size: frame.view_size,
            latency,
            on_time,
            parts: frame.parts.clone(),
        });
        self.unsubscribe(sid, &frame);
        for old in older {
            self.drop_frame(sid, old, DropReason::Superseded);
        }
    }

    fn drop_frame(&mut self, sid: SessionId, fid: FrameId, reason: DropReason) {
        let Some(s) = self.sessions.get_mut(&sid) else { return };
        let Some(pos) = s.frames.iter().position(|f| f.id == fid) else { return };
        let Some(frame) = s.frames.remove(pos) else { return };
        s.dropped += 1;
        self.stats.frames_dropped += 1;
        self.outbox.push(Action::FrameDropped { session: sid, frame: fid, reason });
        self.unsubscribe(sid, &frame);
    }

    /// Removes a frame (already taken out of its session) from its tasks.
    fn unsubscribe(&mut self, sid: SessionId, frame: &Frame) {
        for part in &frame.parts {
            let Some(t) = self.tasks.get_mut(&part.task) else { continue };
            if let Some(i) = t.subscribers.iter().position(|&(s, f)| s == sid && f == frame.id) {
                t.subscribers.swap_remove(i);
                if !t.done {
                    let in_flight = t.in_flight;
                    if let Some(s) = self.sessions.get_mut(&sid) {
                        s.loaded = s.loaded.saturating_sub(in_flight);
                    }
                }
            }
            self.unref(part.task);
        }
    }

    /// Drops one reference; a task nobody needs is released (finished) or cancelled.
    fn unref(&mut self, tid: TaskId) {
        let Some(t) = self.tasks.get_mut(&tid) else { return };
        t.refs = t.refs.saturating_sub(1);
        if t.refs > 0 {
            return;
        }
        let Some(t) = self.tasks.remove(&tid) else { return };
        if t.done {
            self.outbox.push(Action::ReleaseResult { task: tid });
            return;
        }
        if let Some(k) = t.key
            && self.live.get(&(t.object, k)) == Some(&tid)
        {
            self.live.remove(&(t.object, k));
        }
        let fraction = self.derived_work_fraction();
        let mut orphans = Vec::new();
        for batch in t.batches {
            let Some(b) = self.batches.get_mut(&batch) else { continue };
            let work = batch_work(b, t.cost, fraction);
            let state = b.state;
            if state != BatchState::Done {
                orphans.append(&mut b.riders);
            }
            match state {
                BatchState::Pending => {
                    if self.pending_all.remove(&batch) {
                        self.pending_work -= work;
                    }
                }
                BatchState::InFlight { worker, est_s, .. } => {
                    self.detach(batch, worker, est_s);
                    self.outbox.push(Action::Cancel { worker, batch });
                    self.stats.batches_cancelled += 1;
                }
                BatchState::Done => {}
            }
            self.batches.remove(&batch);
        }
        self.orphan_riders(orphans);
        if self.pending_all.is_empty() {
            self.pending_work = 0.0; // no float drift carried across idle periods
        }
    }

    // ----------------------------------------------------------------------------------------
    // Frames and the TaskAssigner.

    fn release_frames(&mut self, now: Time) {
        let max = self.config.max_frames_in_flight;
        let due: Vec<SessionId> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.frames.len() < max && !s.views.is_empty() && s.next_release.is_some_and(|t| t <= now))
            .map(|(&id, _)| id)
            .collect();
        if due.is_empty() {
            return;
        }
        let reference_rate = self.median_rate();
        for sid in due {
            self.release_frame(sid, now, reference_rate);
            if let Some(s) = self.sessions.get_mut(&sid) {
                let nominal = s.next_release.unwrap_or(now);
                // Stay on the frame grid when on time; re-grid after falling behind.
                s.next_release = Some(if now.since(nominal) < s.period { nominal + s.period } else { now + s.period });
            }
        }
    }

    /// Median measured throughput of the workers taking work: the reference rate for Heavy.
    fn median_rate(&self) -> Option<f64> {
        let mut rates: Vec<f64> = self.workers.values().filter(|w| !w.draining).map(|w| w.measured).collect();
        if rates.is_empty() {
            return None;
        }
        rates.sort_by(f64::total_cmp);
        Some(rates[rates.len() / 2])
    }

    fn release_frame(&mut self, sid: SessionId, now: Time, reference_rate: Option<f64>) {
        let Some(s) = self.sessions.get_mut(&sid) else { return };
        let fid = FrameId(s.next_frame);
        s.next_frame += 1;
        s.released += 1;
        let (views, objects, budget) = (s.views.clone(), s.objects.clone(), secs(s.period));
        self.stats.frames_released += 1;
        let mut parts = Vec::with_capacity(views.len() * objects.len());
        // Tasks this frame creates: its own views are grouped by `plan_derived` afterwards,
        // not derived from each other one by one here.
        let mut created: Vec<TaskId> = Vec::new();
        for (vi, camera) in views.iter().enumerate() {
            for &oid in &objects {
                let Some(bounds) = self.objects.get(&oid).map(|i| i.bounds) else { continue };
                let key = self.config.sharing.map(|tol| (oid, CameraKey::new(camera, &tol)));
                let reuse = key.and_then(|k| match self.live.get(&k) {
                    Some(&tid) => Some((tid, PartSource::Shared)),
                    None => {
                        self.history.get(&k, now, self.config.history_max_age).map(|tid| (tid, PartSource::History))
                    }
                });
                let (tid, source) = match reuse.filter(|(tid, _)| self.tasks.contains_key(tid)) {
                    Some(found) => found,
                    None => match self.create_task(sid, camera, oid, key, budget, reference_rate) {
                        Some(tid) => {
                            self.count_created(tid);
                            match self.adjacent_key(tid, &created) {
                                Some(key_task) if self.derive_from(key_task, tid) => {
                                    self.stats.views_derived += 1;
                                    self.stats.rays_derived += self.tasks.get(&tid).map_or(0, |t| t.rays);
                                    (tid, PartSource::Derived)
                                }
                                _ => {
                                    created.push(tid);
                                    (tid, PartSource::Rendered)
                                }
                            }
                        }
                        None => continue, // not in view
                    },
                };
                let Some(task) = self.tasks.get(&tid) else { continue };
                if source != PartSource::Rendered {
                    let error = assign::reprojection_error_px(&task.camera, camera, &bounds);
                    self.stats.share_error_px_max = self.stats.share_error_px_max.max(error);
                    self.stats.share_error_px_sum += f64::from(error);
                    if source == PartSource::Shared {
                        self.stats.shared_joins += 1;
                        self.stats.rays_shared += task.rays;
                    } else {
                        self.stats.history_hits += 1;
                        self.stats.rays_from_history += task.rays;
                    }
                }
                self.stats.rays_requested += task.rays;
                parts.push(FramePart {
                    view: vi as u32,
                    object: oid,
                    task: tid,
                    rays: task.rays,
                    mean_depth: task.mean_depth,
                    source,
                });
            }
        }
        self.plan_derived(&mut parts);
        let fraction = self.derived_work_fraction();
        let rendered_work: f64 = parts
            .iter()
            .filter_map(|p| {
                let share = match p.source {
                    PartSource::Rendered => 1.0,
                    PartSource::Derived => fraction,
                    PartSource::Shared | PartSource::History => return None,
                };
                self.tasks.get(&p.task).map(|t| share * t.rays as f64 * t.cost)
            })
            .sum();
        let smoothing = self.config.smoothing;
        if let Some(s) = self.sessions.get_mut(&sid) {
            s.work_per_frame = Some(match s.work_per_frame {
                Some(w) => (1.0 - smoothing) * w + smoothing * rendered_work,
                None => rendered_work,
            });
        }
        let view_size = views.first().map_or((0, 0), |c| (c.width(), c.height()));
        let mut frame = Frame {
            id: fid,
            released: now,
            view_size,
            first_dispatch: None,
            parts,
            remaining: 0,
            pending: 0,
            cursor: 0,
        };
        let mut loaded = 0;
        for part in &frame.parts {
            if let Some(t) = self.tasks.get_mut(&part.task) {
                t.subscribers.push((sid, fid));
                t.refs += 1;
                if !t.done {
                    frame.remaining += 1;
                    frame.pending += t.pending.len() as u64;
                    loaded += t.in_flight;
                    if t.in_flight > 0 {
                        frame.first_dispatch = Some(now);
                    }
                }
            }
        }
        let complete = frame.remaining == 0;
        if let Some(s) = self.sessions.get_mut(&sid) {
            s.loaded += loaded;
            s.frames.push_back(frame);
        }
        if complete {
            self.complete_frame(sid, fid, now);
        }
    }

    /// The TaskAssigner: `nhit` estimate, batches, class. `None` if the object is not in view.
    fn create_task(
        &mut self,
        creator: SessionId,
        camera: &Camera,
        oid: ObjectId,
        key: Option<ResultKey>,
        budget: f64,
        reference_rate: Option<f64>,
    ) -> Option<TaskId> {
        let info = self.objects.get(&oid)?;
        let whole = info.full_frame;
        let coverage = if whole {
            let (w, h) = (camera.width(), camera.height());
            let mean_depth = camera.view_depth(info.bounds.center()).max(0.0);
            assign::Coverage { pixels: PixelSet::full(w, h), rays: u64::from(w) * u64::from(h), mean_depth }
        } else {
            assign::estimate_coverage(camera, &info.bounds, info.occupancy.as_ref(), self.config.band_rows)?
        };
        let cost = info.cost_per_ray;
        let estimate = reference_rate.map_or(0.0, |rate| coverage.rays as f64 * cost / rate);
        let class = assign::classify(estimate, budget, self.config.heavy_fraction);
        let workers_wanted = match class {
            TaskClass::Heavy => (estimate / (self.config.heavy_fraction * budget)).ceil().max(1.0) as usize,
            TaskClass::Light => 0,
        };
        let tid = TaskId(self.next_task);
        self.next_task += 1;
        let batches = self.add_batches(tid, &coverage.pixels, cost, whole);
        let task = Task {
            object: oid,
            camera: *camera,
            key: key.map(|(_, k)| k),
            class,
            rays: coverage.rays,
            mean_depth: coverage.mean_depth,
            cost,
            workers_wanted,
            pending: batches.iter().copied().collect(),
            remaining: batches.len(),
            batches,
            in_flight: 0,
            subscribers: Vec::new(),
            refs: 0,
            done: false,
            derived: false,
            creator,
            ahead: false,
        };
        self.tasks.insert(tid, task);
        if let Some(k) = key {
            self.live.insert(k, tid);
        }
        Some(tid)
    }

    /// Counts a task a frame created.
    fn count_created(&mut self, tid: TaskId) {
        let Some(t) = self.tasks.get(&tid) else { return };
        self.stats.tasks_created += 1;
        self.stats.rays_created += t.rays;
        match t.class {
            TaskClass::Heavy => self.stats.tasks_heavy += 1,
            TaskClass::Light => self.stats.tasks_light += 1,
        }
    }

    /// The history table renders ahead (issue 16; NEPHELE eq. 12 ranks rays by the views that
    /// will share them). While the farm has spare capacity (nothing waits for dispatch and
    /// every worker is idle), each moving session's next view of each object is predicted
    /// from its last two poses at its next release ([`Camera::extrapolate`]) and rendered
    /// now, the predictions that the most current views (of every session) lie near first,
    /// within `budget_fraction` of the farm's time until the earliest release; a prediction
    /// within the derived views' angle of one already sent is left to it. The worker keeps
    /// such a render as the session's previous render (and lends it to other sessions' views
    /// near it), so the frame then takes it by reprojection and renders only its leftovers.
    /// Once per release and session; a still session is left to the history table.
    fn render_ahead(&mut self, now: Time) {
        let Some(config) = self.config.render_ahead else { return };
        let active = self.workers.values().filter(|w| !w.draining);
        if !self.pending_all.is_empty() || active.clone().any(|w| !w.in_flight.is_empty()) {
            return;
        }
        let farm_rate: f64 = active.map(|w| w.measured).sum();
        let Some(earliest) = self.sessions.values().filter_map(|s| s.next_release).min() else { return };
        if farm_rate <= 0.0 || earliest <= now {
            return;
        }
        let mut budget = config.budget_fraction * secs(earliest.since(now)) * farm_rate;
        let limit =
            self.config.derived_views.map_or(DerivedViews::default().max_view_angle_deg, |d| d.max_view_angle_deg);
        let limit = limit.to_radians();
        // (views near it, release, session, view index, object, predicted camera, direction
        // from the object's centre)
        type Candidate = (usize, Time, SessionId, usize, ObjectId, Camera, glam::Vec3);
        let mut candidates: Vec<Candidate> = Vec::new();
        for (&sid, s) in &self.sessions {
            let (Some(release), Some(at), Some((earlier_at, earlier))) = (s.next_release, s.pose_at, &s.earlier_pose)
            else {
                continue;
            };
            if s.ahead_release == Some(release) || !s.ahead_tasks.is_empty() || earlier.len() != s.views.len() {
                continue;
            }
            let step = secs(at.since(*earlier_at));
            if step <= 0.0 || release < at {
                continue;
            }
            let k = (secs(release.since(at)) / step) as f32;
            for (vi, (camera, before)) in s.views.iter().zip(earlier).enumerate() {
                if camera == before {
                    continue; // still: the history table serves it
                }
                let Some(predicted) = camera.extrapolate(before, k) else { continue };
                for &oid in &s.objects {
                    let Some(info) = self.objects.get(&oid).filter(|o| !o.full_frame) else { continue };
                    let centre = info.bounds.center();
                    let Some(direction) = (predicted.position() - centre).try_normalize() else { continue };
                    let near = |c: &Camera| {
                        (c.position() - centre)
                            .try_normalize()
                            .is_some_and(|d| f64::from(d.dot(direction).clamp(-1.0, 1.0).acos()) <= limit)
                    };
                    let shares = self
                        .sessions
                        .values()
                        .filter(|other| other.objects.contains(&oid))
                        .map(|other| other.views.iter().filter(|c| near(c)).count())
                        .sum::<usize>();
                    candidates.push((shares, release, sid, vi, oid, predicted, direction));
                }
            }
        }
        candidates.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)).then(a.3.cmp(&b.3)));
        // Renders ahead sent this round: a prediction near one of them (another user looking
        // at the object from nearby) is served by it on the worker, not rendered again.
        let mut sent: Vec<(ObjectId, glam::Vec3)> = Vec::new();
        for (_, release, sid, _, oid, camera, direction) in candidates {
            let covered =
                sent.iter().any(|&(o, d)| o == oid && f64::from(d.dot(direction).clamp(-1.0, 1.0).acos()) <= limit);
            if covered {
                if let Some(s) = self.sessions.get_mut(&sid) {
                    s.ahead_release = Some(release);
                }
                self.stats.ahead_views_covered += 1;
                continue;
            }
            let Some(info) = self.objects.get(&oid) else { continue };
            let Some(coverage) =
                assign::estimate_coverage(&camera, &info.bounds, info.occupancy.as_ref(), self.config.band_rows)
            else {
                continue;
            };
            let work = coverage.rays as f64 * info.cost_per_ray;
            if work > budget {
                continue;
            }
            budget -= work;
            let Some(tid) = self.create_task(sid, &camera, oid, None, f64::INFINITY, None) else { continue };
            let batches = match self.tasks.get_mut(&tid) {
                Some(t) => {
                    t.ahead = true;
                    t.refs = 1;
                    t.batches.clone()
                }
                None => continue,
            };
            if let Some(s) = self.sessions.get_mut(&sid) {
                s.ahead_release = Some(release);
                s.ahead_tasks.push(tid);
            }
            self.stats.ahead_tasks += 1;
            self.stats.ahead_rays += coverage.rays;
            sent.push((oid, direction));
            for batch in batches {
                // The least backlog, biased to the worker that last rendered the object (where
                // the frame's own batches will look first).
                let switch = secs(self.config.object_switch_cost);
                let worker = self
                    .workers
                    .iter()
                    .filter(|(_, w)| !w.draining)
                    .map(|(&id, w)| (w.backlog_s + if w.last_object == Some(oid) { 0.0 } else { switch }, id))
                    .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
                    .map(|(_, id)| id);
                match worker {
                    Some(worker) => self.dispatch(batch, worker, now),
                    None => {
                        self.drop_ahead(tid);
                        break;
                    }
                }
            }
        }
    }

    /// Ends a render ahead: its batches still out are cancelled, it leaves its session.
    fn drop_ahead(&mut self, tid: TaskId) {
        let Some(sid) = self.tasks.get(&tid).filter(|t| t.ahead).map(|t| t.creator) else { return };
        if let Some(s) = self.sessions.get_mut(&sid) {
            s.ahead_tasks.retain(|&t| t != tid);
        }
        if let Some(t) = self.tasks.get_mut(&tid) {
            t.refs = 1;
        }
        self.unref(tid);
    }

    /// Splits `pixels` into pending batches of task `tid` (the task's books are the caller's).
    /// `whole` (a full-frame object's view): bands of whole rows, one per worker but none
    /// under `max_batch_rays` pixels (each band costs its kernel a margin of rows).
    fn add_batches(&mut self, tid: TaskId, pixels: &PixelSet, cost: f64, whole: bool) -> Vec<BatchId> {
        let pieces = if whole && pixels.len() == u64::from(pixels.width()) * u64::from(pixels.height()) {
            let most = (pixels.len() / u64::from(self.config.max_batch_rays)).max(1);
            let bands = (self.workers.len() as u64).clamp(1, most) as u32;
            assign::split_rows(pixels.width(), pixels.height(), bands)
        } else if whole {
            vec![pixels.clone()]
        } else {
            assign::split_batches(pixels, self.config.max_batch_rays)
        };
        let mut batches = Vec::with_capacity(pieces.len());
        for pixels in pieces {
            let id = BatchId(self.next_batch);
            self.next_batch += 1;
            let rays = pixels.len();
            let batch = Batch {
                task: tid,
                pixels,
                rays,
                state: BatchState::Pending,
                failures: 0,
                stretches: 0,
                dispatches: 0,
                previous: Vec::new(),
                riders: Vec::new(),
            };
            self.batches.insert(id, batch);
            self.pending_all.insert(id);
            self.pending_work += rays as f64 * cost;
            batches.push(id);
        }
        batches
    }

    fn is_full_frame(&self, object: ObjectId) -> bool {
        self.objects.get(&object).is_some_and(|o| o.full_frame)
    }

    fn derived_work_fraction(&self) -> f64 {
        self.config.derived_views.map_or(1.0, |d| d.work_fraction)
    }

    /// Views of this frame taken from an adjacent view of it (issue 16). Per object, the
    /// views rendered for this frame are grouped in view order (a rig's views are listed
    /// along it) into runs around a key view, every view of a run within the limit angle of
    /// the key, seen from the object's centre; the others ride on the key's batches (see
    /// [`Self::derive_from`]).
    fn plan_derived(&mut self, parts: &mut [FramePart]) {
        self.pair_full_frame_eyes(parts);
        let Some(config) = self.config.derived_views else { return };
        let limit = config.max_view_angle_deg.to_radians();
        let objects: BTreeSet<ObjectId> = parts.iter().map(|p| p.object).filter(|&o| !self.is_full_frame(o)).collect();
        for oid in objects {
            let Some(centre) = self.objects.get(&oid).map(|o| o.bounds.center()) else { continue };
            let candidates: Vec<(usize, glam::Vec3)> = parts
                .iter()
                .enumerate()
                .filter(|(_, p)| p.object == oid && p.source == PartSource::Rendered)
                .filter_map(|(i, p)| {
                    let t = self.tasks.get(&p.task)?;
                    let direction = (t.camera.position() - centre).try_normalize()?;
                    Some((i, direction))
                })
                .collect();
            let angle = |a: glam::Vec3, b: glam::Vec3| f64::from(a.dot(b).clamp(-1.0, 1.0).acos());
            let within = |a: usize, b: usize| angle(candidates[a].1, candidates[b].1) <= limit;
            let mut start = 0;
            while start < candidates.len() {
                // The key: the farthest view within the limit of the run's first; the run: up
                // to the last view within the limit of the key. A run that ends at its key
                // (its views all within the limit of each other) is keyed in its middle.
                let mut key = start;
                while key + 1 < candidates.len() && within(start, key + 1) {
                    key += 1;
                }
                let mut end = key + 1;
                while end < candidates.len() && within(key, end) {
                    end += 1;
                }
                if end == key + 1 {
                    key = start + (key - start) / 2;
                }
                for d in (start..end).filter(|&d| d != key) {
                    if !within(key, d) {
                        continue;
                    }
                    let (key_part, derived_part) = (candidates[key].0, candidates[d].0);
                    if self.derive_from(parts[key_part].task, parts[derived_part].task) {
                        parts[derived_part].source = PartSource::Derived;
                        self.stats.views_derived += 1;
                        self.stats.rays_derived += parts[derived_part].rays;
                    }
                }
                start = end;
            }
        }
    }

    /// A stereo frame's two eyes of a full-frame object (the environment) in one batch: the
    /// right eye rides on the left eye's batch, whatever the angle between them, so that the
    /// worker shades both in one pass of the stereo GI model (the paper's point: one stereo
    /// pass costs about half of two single-eye passes). On with or without reprojected views
    /// (`derived_views`), which are a different thing; only for two views (a headset), not a
    /// quilt, whose views are farther apart than the eyes the stereo model was trained on.
    fn pair_full_frame_eyes(&mut self, parts: &mut [FramePart]) {
        let objects: BTreeSet<ObjectId> = parts.iter().map(|p| p.object).filter(|&o| self.is_full_frame(o)).collect();
        for oid in objects {
            let eyes: Vec<usize> = parts
                .iter()
                .enumerate()
                .filter(|(_, p)| p.object == oid && p.source == PartSource::Rendered)
                .map(|(i, _)| i)
                .collect();
            let views: BTreeSet<u32> = parts.iter().filter(|p| p.object == oid).map(|p| p.view).collect();
            if eyes.len() != 2 || views.len() != 2 {
                continue;
            }
            let (left, right) = (eyes[0], eyes[1]);
            if self.derive_from(parts[left].task, parts[right].task) {
                parts[right].source = PartSource::Derived;
                self.stats.views_derived += 1;
                self.stats.rays_derived += parts[right].rays;
            }
        }
    }

    /// Moves task `derived`'s pixels onto the batches of task `key` (both just created, nothing
    /// dispatched): the pixels in each key batch's rows ride on that batch; those in rows no
    /// key batch spans stay batches of their own. Only when every key batch holds all of the
    /// key's pixels in the rows it spans (the worker then knows the rest of its box is empty);
    /// false, and nothing changed, otherwise.
    fn derive_from(&mut self, key: TaskId, derived: TaskId) -> bool {
        let (Some(k), Some(d)) = (self.tasks.get(&key), self.tasks.get(&derived)) else { return false };
        if key == derived || k.object != d.object || !k.is_fresh() || !d.is_fresh() {
            return false;
        }
        if (k.camera.width(), k.camera.height()) != (d.camera.width(), d.camera.height()) {
            return false;
        }
        let row_span = |set: &PixelSet| {
            let y0 = set.rects().iter().map(|r| r.y0).min().unwrap_or(0);
            let y1 = set.rects().iter().map(|r| r.y1).max().unwrap_or(0);
            (y0, y1)
        };
        let mut spans: Vec<(u32, u32, BatchId)> = Vec::with_capacity(k.batches.len());
        for id in &k.batches {
            let Some(b) = self.batches.get(id) else { return false };
            let (y0, y1) = row_span(&b.pixels);
            spans.push((y0, y1, *id));
        }
        spans.sort_unstable();
        if spans.windows(2).any(|w| w[0].1 > w[1].0) {
            return false; // a row shared by two batches (rows wider than a batch)
        }
        let derived_rects: Vec<assign::PixelRect> = d
            .batches
            .iter()
            .filter_map(|id| self.batches.get(id))
            .flat_map(|b| b.pixels.rects().iter().copied())
            .collect();
        let (width, height, cost, key_cost) = (d.camera.width(), d.camera.height(), d.cost, k.cost);
        let old: Vec<BatchId> = d.batches.clone();
        let clip = |y0: u32, y1: u32| -> Vec<assign::PixelRect> {
            derived_rects
                .iter()
                .map(|r| assign::PixelRect { y0: r.y0.max(y0), y1: r.y1.min(y1), ..*r })
                .filter(|r| !r.is_empty())
                .collect()
        };
        let mut riders = Vec::new();
        let mut outside = Vec::new();
        let mut row = 0;
        for &(y0, y1, batch) in &spans {
            outside.extend(clip(row, y0));
            if let Some(pixels) = PixelSet::new(width, height, clip(y0, y1)).filter(|s| !s.is_empty()) {
                let rays = pixels.len();
                riders.push((batch, Rider { task: derived, pixels, rays }));
            }
            row = y1;
        }
        outside.extend(clip(row, height));
        // The derived task's own batches are replaced.
        for id in &old {
            if let Some(b) = self.batches.remove(id)
                && self.pending_all.remove(id)
            {
                self.pending_work -= b.rays as f64 * cost;
            }
        }
        let own = match PixelSet::new(width, height, outside) {
            Some(set) if !set.is_empty() => self.add_batches(derived, &set, cost, false),
            _ => Vec::new(),
        };
        let fraction = self.derived_work_fraction();
        let rider_count = riders.len();
        for (batch, rider) in riders {
            self.pending_work += fraction * rider.rays as f64 * key_cost;
            if let Some(b) = self.batches.get_mut(&batch) {
                b.riders.push(rider);
            }
        }
        if let Some(t) = self.tasks.get_mut(&derived) {
            t.pending = own.iter().copied().collect();
            t.remaining = own.len() + rider_count;
            t.batches = own;
            t.derived = true;
        }
        true
    }

    /// A key for a view of another user (issue 16's adjacent users): the nearest task of the
    /// same object, not yet dispatched and not derived itself, created by another session's
    /// frame, whose camera is within the limit angle of `task`'s seen from the object's
    /// centre. Only tasks that can be shared (`live`, with `sharing` on) are looked at. Not
    /// the same session's earlier frame: a frame taken from the one before would complete
    /// with it, and the older would only be superseded (half the frames shown).
    fn adjacent_key(&self, task: TaskId, exclude: &[TaskId]) -> Option<TaskId> {
        let limit = self.config.derived_views?.max_view_angle_deg.to_radians();
        let t = self.tasks.get(&task)?;
        if self.is_full_frame(t.object) {
            return None; // an image-space kernel's views are not reprojected
        }
        let centre = self.objects.get(&t.object)?.bounds.center();
        let direction = (t.camera.position() - centre).try_normalize()?;
        let size = (t.camera.width(), t.camera.height());
        let mut best: Option<(f64, TaskId)> = None;
        for (&(object, _), &candidate) in &self.live {
            if object != t.object || candidate == task || exclude.contains(&candidate) {
                continue;
            }
            let Some(k) = self.tasks.get(&candidate) else { continue };
            if k.creator == t.creator {
                continue;
            }
            if !k.is_fresh() || (k.camera.width(), k.camera.height()) != size {
                continue;
            }
            let Some(other) = (k.camera.position() - centre).try_normalize() else { continue };
            let angle = f64::from(direction.dot(other).clamp(-1.0, 1.0).acos());
            if angle <= limit && best.is_none_or(|(a, id)| (angle, candidate) < (a, id)) {
                best = Some((angle, candidate));
            }
        }
        best.map(|(_, id)| id)
    }

    /// What the worker needs of the views riding on `batch` (those still needed).
    fn derived_specs(&self, batch: BatchId) -> Vec<DerivedSpec> {
        let Some(b) = self.batches.get(&batch) else { return Vec::new() };
        b.riders
            .iter()
            .filter_map(|r| {
                let t = self.tasks.get(&r.task).filter(|t| !t.done)?;
                Some(DerivedSpec {
                    task: r.task,
                    camera: t.camera,
                    pixels: r.pixels.clone(),
                    rays: r.rays,
                    frames: t.subscribers.clone(),
                })
            })
            .collect()
    }

    /// A key batch finished: so did each view derived from it.
    fn finish_riders(&mut self, riders: Vec<Rider>, now: Time) {
        for rider in riders {
            let Some(t) = self.tasks.get_mut(&rider.task) else { continue }; // no longer needed
            if t.done {
                continue;
            }
            t.remaining = t.remaining.saturating_sub(1);
            self.stats.rays_completed += rider.rays;
            if t.remaining == 0 {
                self.task_done(rider.task, now);
            }
        }
    }

    /// A key batch will not be rendered (its task was dropped): the views riding on it get
    /// batches of their own.
    fn orphan_riders(&mut self, riders: Vec<Rider>) {
        for rider in riders {
            let Some(t) = self.tasks.get(&rider.task) else { continue };
            if t.done {
                continue;
            }
            let (cost, whole) = (t.cost, self.is_full_frame(t.object));
            let ids = self.add_batches(rider.task, &rider.pixels, cost, whole);
            let added = ids.len();
            if let Some(t) = self.tasks.get_mut(&rider.task) {
                t.remaining = t.remaining.saturating_sub(1) + added;
                t.pending.extend(ids.iter().copied());
                t.batches.extend(ids);
            }
            self.adjust(rider.task, added as i64, 0, None);
        }
    }

    // ----------------------------------------------------------------------------------------
    // Starvation and ordering.

    /// `target_time = T_last_frame + w_u` of the oldest frame with undispatched work, in
    /// microseconds (may precede the release when `t_u > 1/FPS`).
    fn target_time(&self, s: &Session) -> Option<i128> {
        let frame = s.frames.iter().find(|f| f.pending > 0)?;
        let wait = secs(s.period) - s.frame_time.unwrap_or(0.0);
        Some(micros_i(frame.released) + (wait * 1e6).round() as i128)
    }

    fn is_starved(&self, s: &Session, now: Time) -> bool {
        self.target_time(s).is_some_and(|t| micros_i(now) > t)
    }

    fn has_room(&self, w: &Worker) -> bool {
        !w.draining && (w.in_flight.is_empty() || w.backlog_s < secs(self.config.horizon))
    }

    fn plan_nephele(&mut self, now: Time) {
        let mut order: Vec<(bool, i128, i128, SessionId)> = Vec::new();
        for (&sid, s) in &self.sessions {
            let Some(target) = self.target_time(s) else { continue };
            let starved = micros_i(now) > target;
            let loaded = i128::from(s.loaded);
            order.push(if starved { (false, target, loaded, sid) } else { (true, loaded, target, sid) });
        }
        order.sort_unstable();
        self.starved_now = order.iter().filter(|o| !o.0).count();
        if self.starved_now > 0 {
            self.stats.starved_rounds += 1;
            for o in order.iter().filter(|o| !o.0) {
                if let Some(s) = self.sessions.get_mut(&o.3) {
                    s.last_starved = Some(now);
                }
            }
        }
        let sessions: Vec<SessionId> = order.iter().map(|o| o.3).collect();
        let room = self.workers.values().filter(|w| self.has_room(w)).count();
        // First as Algorithm 1 has it; then, if workers are still idle, heavy tasks may spread
        // over them beyond their share (nothing else could use them this round).
        let room = self.fill(&sessions, false, room, now);
        if room > 0 {
            self.fill(&sessions, true, room, now);
        }
        self.render_ahead(now);
    }

    /// Fills workers with room, user by user in `order`, shared tasks before dedicated ones.
    /// With `spread`, only heavy tasks are placed, on any idle worker. Returns the workers
    /// still with room.
    fn fill(&mut self, order: &[SessionId], spread: bool, mut room: usize, now: Time) -> usize {
        for &sid in order {
            if room == 0 {
                break;
            }
            let tids: Vec<TaskId> = match self.sessions.get(&sid) {
                Some(s) => s
                    .frames
                    .iter()
                    .filter(|f| f.pending > 0)
                    .flat_map(|f| f.parts[f.cursor..].iter().map(|p| p.task))
                    .collect(),
                None => continue,
            };
            for shared_pass in [true, false] {
                for &tid in &tids {
                    if room == 0 {
                        break;
                    }
                    let Some(t) = self.tasks.get(&tid) else { continue };
                    if t.done
                        || t.pending.is_empty()
                        || (t.subscribers.len() > 1) != shared_pass
                        || (spread && t.class == TaskClass::Light)
                    {
                        continue;
                    }
                    let (class, object, wanted) =
                        (t.class, t.object, if spread { usize::MAX } else { t.workers_wanted });
                    while room > 0 {
                        let Some(&batch) = self.tasks.get(&tid).and_then(|t| t.pending.first()) else { break };
                        let exclude = self.batches.get(&batch).map(|b| b.previous.clone()).unwrap_or_default();
                        let choice = match class {
                            TaskClass::Light => self.place_light(object, &exclude),
                            TaskClass::Heavy => self.place_heavy(tid, object, wanted, !spread, &exclude),
                        };
                        let Some((worker, mode)) = choice else { break };
                        if let Some(w) = self.workers.get_mut(&worker) {
                            w.mode = mode;
                        }
                        self.dispatch(batch, worker, now);
                        if self.workers.get(&worker).is_some_and(|w| !self.has_room(w)) {
                            room -= 1;
                        }
                    }
                }
            }
            let tasks = &self.tasks;
            let waiting = |tid: &TaskId| tasks.get(tid).is_some_and(|t| !t.done && !t.pending.is_empty());
            if let Some(s) = self.sessions.get_mut(&sid) {
                for f in s.frames.iter_mut() {
                    while f.cursor < f.parts.len() && !waiting(&f.parts[f.cursor].task) {
                        f.cursor += 1;
                    }
                }
            }
        }
        room
    }

    /// LightFarm: a non-dedicated worker with room, least backlog (plus the switch cost when it
    /// last rendered another object).
    fn place_light(&self, object: ObjectId, exclude: &[WorkerId]) -> Option<(WorkerId, Mode)> {
        let switch = secs(self.config.object_switch_cost);
        let pick = |allow_excluded: bool| {
            self.workers
                .iter()
                .filter(|(id, w)| {
                    !matches!(w.mode, Mode::Heavy(..)) && self.has_room(w) && (allow_excluded || !exclude.contains(id))
                })
                .map(|(&id, w)| (w.backlog_s + if w.last_object == Some(object) { 0.0 } else { switch }, id))
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
                .map(|(_, id)| (id, Mode::Light))
        };
        pick(false).or_else(|| pick(true))
    }

    /// HeavyFarm: the least-loaded worker among those dedicated to this task and, while fewer
    /// than `wanted` are, the idle ones; failing that (still under `wanted`), the least-loaded
    /// light worker is converted (it finishes its light batches, then serves only this task)
    /// if `convert`.
    /// Workers that last rendered the same object are preferred by the switch cost.
    /// `exclude` (the workers a re-issued batch already failed or timed out on) is a
    /// preference, as in [`Self::place_light`]: when every candidate is excluded the batch
    /// goes back to one of them rather than waiting for a worker that may never come.
    fn place_heavy(
        &self,
        task: TaskId,
        object: ObjectId,
        wanted: usize,
        convert: bool,
        exclude: &[WorkerId],
    ) -> Option<(WorkerId, Mode)> {
        let mode = Mode::Heavy(task, object);
        let switch = secs(self.config.object_switch_cost);
        let under_cap = self.workers.values().filter(|w| w.mode == mode).count() < wanted.max(1);
        let least = |filter: &dyn Fn(&Worker) -> bool, allow_excluded: bool| {
            self.workers
                .iter()
                .filter(|(id, w)| filter(w) && self.has_room(w) && (allow_excluded || !exclude.contains(id)))
                .map(|(&id, w)| (w.backlog_s + if w.last_object == Some(object) { 0.0 } else { switch }, id))
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
                .map(|(_, id)| (id, mode))
        };
        let pick = |allow_excluded: bool| {
            least(&|w| w.mode == mode || (under_cap && w.mode == Mode::Idle), allow_excluded)
                .or_else(|| if under_cap && convert { least(&|w| w.mode == Mode::Light, allow_excluded) } else { None })
        };
        pick(false).or_else(|| pick(true))
    }

    fn plan_fifo(&mut self, now: Time) {
        let mut room = self.workers.values().filter(|w| self.has_room(w)).count();
        let mut cursor = BatchId(0);
        while room > 0 {
            let Some(&batch) = self.pending_all.range(cursor..).next() else { break };
            cursor = BatchId(batch.0 + 1);
            let exclude = self.batches.get(&batch).map(|b| b.previous.clone()).unwrap_or_default();
            let pick = |allow_excluded: bool| {
                self.workers
                    .iter()
                    .filter(|(id, w)| self.has_room(w) && (allow_excluded || !exclude.contains(id)))
                    .min_by(|a, b| a.1.backlog_s.total_cmp(&b.1.backlog_s).then(a.0.cmp(b.0)))
                    .map(|(&id, _)| id)
            };
            let Some(worker) = pick(false).or_else(|| pick(true)) else { break };
            if let Some(w) = self.workers.get_mut(&worker) {
                w.mode = Mode::Light;
            }
            self.dispatch(batch, worker, now);
            if self.workers.get(&worker).is_some_and(|w| !self.has_room(w)) {
                room -= 1;
            }
        }
    }

    /// Round robin and object-per-worker: every pending batch is queued at once.
    fn plan_immediate(&mut self, now: Time) {
        let active: Vec<WorkerId> = self.workers.iter().filter(|(_, w)| !w.draining).map(|(&id, _)| id).collect();
        if active.is_empty() {
            return;
        }
        let pending: Vec<BatchId> = self.pending_all.iter().copied().collect();
        for batch in pending {
            let Some(b) = self.batches.get(&batch) else { continue };
            let Some(object) = self.tasks.get(&b.task).map(|t| t.object) else { continue };
            let excluded = |id: &WorkerId| b.previous.contains(id) && b.previous.len() < active.len();
            let worker = if self.config.policy == Policy::RoundRobin {
                let mut pick = active[self.rr_cursor % active.len()];
                self.rr_cursor += 1;
                if excluded(&pick) {
                    pick = active[self.rr_cursor % active.len()];
                    self.rr_cursor += 1;
                }
                pick
            } else {
                match self.bindings.get(&object).copied().filter(|w| active.contains(w) && !excluded(w)) {
                    Some(w) => w,
                    None => {
                        // Bind to the worker holding the fewest objects.
                        let Some(w) = active
                            .iter()
                            .filter(|id| !excluded(id))
                            .min_by_key(|id| (self.bindings.values().filter(|b| b == id).count(), **id))
                            .copied()
                        else {
                            continue;
                        };
                        self.bindings.insert(object, w);
                        w
                    }
                }
            };
            if let Some(w) = self.workers.get_mut(&worker) {
                w.mode = Mode::Light;
            }
            self.dispatch(batch, worker, now);
        }
    }

    /// Whether `batch` holds every pixel of its task's coverage in the rows it spans (no row
    /// is shared with another batch of the task): a pixel of its bounding box that it lacks
    /// is then known empty.
    fn rows_complete(&self, batch: BatchId) -> bool {
        let Some(task) = self.batches.get(&batch).and_then(|b| self.tasks.get(&b.task)) else { return false };
        let mut spans: Vec<(u32, u32)> = Vec::with_capacity(task.batches.len());
        for id in &task.batches {
            let Some(b) = self.batches.get(id) else { return false };
            let y0 = b.pixels.rects().iter().map(|r| r.y0).min().unwrap_or(0);
            let y1 = b.pixels.rects().iter().map(|r| r.y1).max().unwrap_or(0);
            spans.push((y0, y1));
        }
        spans.sort_unstable();
        spans.windows(2).all(|w| w[0].1 <= w[1].0)
    }

    fn dispatch(&mut self, batch: BatchId, worker: WorkerId, now: Time) {
        let (factor, min_timeout) = (self.config.straggler_factor, self.config.min_batch_timeout);
        let work = self.work_of(batch);
        let derived = self.derived_specs(batch);
        let rows_complete = self.rows_complete(batch);
        let Some(b) = self.batches.get_mut(&batch) else { return };
        let Some(t) = self.tasks.get_mut(&b.task) else { return };
        let Some(w) = self.workers.get_mut(&worker) else { return };
        let est_s = work / w.measured;
        if w.in_flight.is_empty() {
            w.service_mark = now;
        }
        w.backlog_s += est_s;
        w.in_flight.push(batch);
        w.last_object = Some(t.object);
        let wait = Duration::from_secs_f64((factor * w.backlog_s).clamp(0.0, 3600.0)).max(min_timeout);
        let deadline = now + wait;
        b.state = BatchState::InFlight { worker, dispatched: now, deadline, est_s };
        b.dispatches += 1;
        b.stretches = 0;
        t.pending.remove(&batch);
        t.in_flight += 1;
        self.pending_all.remove(&batch);
        self.pending_work = (self.pending_work - work).max(0.0);
        self.deadlines.insert((deadline, batch));
        self.stats.batches_dispatched += 1;
        self.stats.rays_dispatched += b.rays;
        let frames = t.subscribers.clone();
        let frame_deadline = frames
            .iter()
            .filter_map(|(sid, fid)| {
                let s = self.sessions.get(sid)?;
                Some(s.frames.iter().find(|f| f.id == *fid)?.released + s.period)
            })
            .min()
            .unwrap_or(deadline);
        let spec = BatchSpec {
            id: batch,
            task: b.task,
            object: t.object,
            camera: t.camera,
            pixels: b.pixels.clone(),
            rays: b.rays,
            class: t.class,
            attempt: b.dispatches,
            frame_deadline,
            timeout: deadline,
            frames,
            derived,
            work_rays: work / t.cost.max(f64::MIN_POSITIVE),
            rows_complete,
            ahead_for: t.ahead.then_some(t.creator),
        };
        let tid = b.task;
        self.outbox.push(Action::Dispatch { worker, batch: Box::new(spec) });
        self.adjust(tid, -1, 1, Some(now));
    }

    // ----------------------------------------------------------------------------------------
    // State for `GET /v1/farm`.

    pub fn snapshot(&self, now: Time) -> FarmSnapshot {
        let now = self.now.max(now);
        let admission = self.admission(now);
        let workers = self
            .workers
            .iter()
            .map(|(&id, w)| WorkerSnapshot {
                id,
                declared_rays_per_s: w.declared,
                measured_rays_per_s: w.measured,
                mode: match w.mode {
                    Mode::Idle => "idle".to_string(),
                    Mode::Light => "light".to_string(),
                    Mode::Heavy(t, o) => format!("heavy:{o}:{t}"),
                },
                draining: w.draining,
                in_flight_batches: w.in_flight.len(),
                backlog_ms: w.backlog_s * 1e3,
                batches_done: w.batches_done,
                rays_done: w.rays_done,
                last_seen_s: w.last_seen.as_secs_f64(),
            })
            .collect();
        let sessions: Vec<SessionSnapshot> = self
            .sessions
            .iter()
            .map(|(&id, s)| SessionSnapshot {
                id,
                target_fps: s.fps,
                achieved_fps: s.interval.filter(|i| *i > 0.0).map(|i| 1.0 / i),
                frame_time_ms: s.frame_time.map(|t| t * 1e3),
                wait_ms: (secs(s.period) - s.frame_time.unwrap_or(0.0)) * 1e3,
                target_time_s: self.target_time(s).map(|t| t as f64 * 1e-6),
                starved: self.is_starved(s, now),
                objects: s.objects.len(),
                views: s.views.len(),
                frames_in_flight: s.frames.len(),
                pending_batches: s.frames.iter().map(|f| f.pending).sum(),
                loaded_batches: s.loaded,
                frames_released: s.released,
                frames_completed: s.completed,
                frames_on_time: s.on_time,
                frames_dropped: s.dropped,
                latency_ms: s.latency.map(|l| l * 1e3),
            })
            .collect();
        let live_tasks = self.tasks.values().filter(|t| !t.done).count();
        FarmSnapshot {
            now_s: now.as_secs_f64(),
            policy: self.config.policy,
            admission_open: admission == Admission::Admit,
            retry_after_s: match admission {
                Admission::Refuse { retry_after } => Some(retry_after.as_secs()),
                Admission::Admit => None,
            },
            starved_sessions: sessions.iter().filter(|s| s.starved).count(),
            capacity_rays_per_s: self.workers.values().filter(|w| !w.draining).map(|w| w.measured).sum(),
            workers,
            sessions,
            queues: QueueSnapshot {
                pending_batches: self.pending_all.len(),
                in_flight_batches: self.deadlines.len(),
                pending_work_rays: self.pending_work.max(0.0),
                live_tasks,
                held_results: self.tasks.len() - live_tasks,
                history_entries: self.history.len(),
            },
            stats: self.stats.clone(),
        }
    }

    /// Number of users starved in the last round.
    pub fn starved_sessions(&self) -> usize {
        self.starved_now
    }

    /// Batches waiting for dispatch.
    pub fn pending_batches(&self) -> usize {
        self.pending_all.len()
    }

    /// Tasks not finished yet.
    pub fn live_tasks(&self) -> usize {
        self.tasks.values().filter(|t| !t.done).count()
    }
}

#[cfg(test)]
#[path = "engine_tests.rs"]
mod tests;
