//! Frame assembly and depth fusion: the pure core of the composer.
//!
//! The master plans every (session, frame) as ray batches of objects; workers send each
//! batch's per-pixel results (premultiplied linear colour, opacity, view depth: exactly
//! [`PixelResults`]) straight to the composer. The [`Compositor`] gathers the batches of a
//! frame from any number of workers, and once the frame is complete, or its deadline has
//! passed, fuses it:
//!
//! * per pixel, the samples of all objects are sorted by view depth (nearest first) and
//!   composited front to back with premultiplied colour, `C += (1 - A) c; A += (1 - A) a`
//!   (NEPHELE section 5: objects rendered separately are merged by depth), then over the
//!   opaque background, `C += (1 - A) bg`;
//! * the views of a frame (one, two for stereo, N for a quilt) are packed into one image, a
//!   grid of `columns` views per row: stereo is left | right side by side;
//! * a batch that misses the deadline is never waited for: the pixels it was planned to cover
//!   take the previous emitted frame's pixels of the same view (or the background when there
//!   is none), and the session's counters record it.
//!
//! No I/O and no clock: every call that depends on time takes `now`, so the same code runs
//! inside the live composer and inside tests and benchmarks.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Instant;

use nephele_geometry::PixelResults;
use rayon::prelude::*;
use thiserror::Error;

/// A viewer's session, as numbered by the composer (or, later, by the master).
pub type SessionId = u64;
/// Frame number inside a session, increasing.
pub type FrameId = u64;

/// Largest view side the compositor accepts, in pixels.
pub const MAX_VIEW_SIDE: u32 = 8192;
/// Largest number of views in one frame (a 45-view quilt fits with room to spare).
pub const MAX_VIEWS: u16 = nephele_geometry::camera::MAX_VIEWS as u16;
/// Largest packed frame, in pixels (a 8K frame).
pub const MAX_FRAME_PIXELS: u64 = 7680 * 4320;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum FusionError {
    #[error("bad frame layout: {0}")]
    Layout(String),
    #[error("unknown session {0}")]
    UnknownSession(SessionId),
    #[error("session {0} is already open")]
    SessionExists(SessionId),
    #[error("frame {frame} of session {session} is already planned")]
    DuplicatePlan { session: SessionId, frame: FrameId },
    #[error("frame {frame} of session {session} is older than the last frame sent ({last})")]
    StalePlan { session: SessionId, frame: FrameId, last: FrameId },
    #[error("bad frame plan: {0}")]
    InvalidPlan(String),
    #[error("batch (object {object}, batch {batch}) of frame {frame} is invalid: {reason}")]
    InvalidBatch { frame: FrameId, object: u32, batch: u32, reason: String },
    #[error("batch (object {object}, batch {batch}) of frame {frame} was not planned")]
    UnplannedBatch { frame: FrameId, object: u32, batch: u32 },
    #[error("batch (object {object}, batch {batch}) of frame {frame} arrived twice")]
    DuplicateBatch { frame: FrameId, object: u32, batch: u32 },
    #[error("too many batches waiting for their frame plan in session {0}")]
    TooManyEarlyBatches(SessionId),
}

/// How the views of a frame are packed into the encoded picture: a grid of `columns` views
/// per row, row-major, each `view_width x view_height`. Mono is 1 view; stereo is 2 views
/// side by side (left eye first).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FrameLayout {
    view_width: u32,
    view_height: u32,
    views: u16,
    columns: u16,
}

impl FrameLayout {
    /// A grid of `views` views, `columns` per row.
    pub fn grid(view_width: u32, view_height: u32, views: u16, columns: u16) -> Result<Self, FusionError> {
        let bad = |m: String| Err(FusionError::Layout(m));
        if view_width == 0 || view_height == 0 || view_width > MAX_VIEW_SIDE || view_height > MAX_VIEW_SIDE {
            return bad(format!(
                "view size {view_width}x{view_height} must be within 1..={MAX_VIEW_SIDE} on each side"
            ));
        }
        if views == 0 || views > MAX_VIEWS {
            return bad(format!("{views} views; must be within 1..={MAX_VIEWS}"));
        }
        if columns == 0 || columns > views {
            return bad(format!("{columns} columns for {views} views"));
        }
        let layout = FrameLayout { view_width, view_height, views, columns };
        if layout.pixel_count() as u64 > MAX_FRAME_PIXELS {
            return bad(format!(
                "packed frame {}x{} exceeds {MAX_FRAME_PIXELS} pixels",
                layout.width(),
                layout.height()
            ));
        }
        Ok(layout)
    }

    /// One view.
    pub fn mono(width: u32, height: u32) -> Result<Self, FusionError> {
        Self::grid(width, height, 1, 1)
    }

    /// Two views side by side, left eye first.
    pub fn stereo(view_width: u32, view_height: u32) -> Result<Self, FusionError> {
        Self::grid(view_width, view_height, 2, 2)
    }

    /// `views` views in one row.
    pub fn side_by_side(view_width: u32, view_height: u32, views: u16) -> Result<Self, FusionError> {
        Self::grid(view_width, view_height, views, views)
    }

    pub fn view_width(&self) -> u32 {
        self.view_width
    }

    pub fn view_height(&self) -> u32 {
        self.view_height
    }

    pub fn views(&self) -> u16 {
        self.views
    }

    pub fn columns(&self) -> u16 {
        self.columns
    }

    pub fn rows(&self) -> u16 {
        self.views.div_ceil(self.columns)
    }

    /// Width of the packed picture.
    pub fn width(&self) -> u32 {
        self.view_width * u32::from(self.columns)
    }

    /// Height of the packed picture.
    pub fn height(&self) -> u32 {
        self.view_height * u32::from(self.rows())
    }

    pub fn pixel_count(&self) -> usize {
        self.width() as usize * self.height() as usize
    }

    pub fn view_pixel_count(&self) -> usize {
        self.view_width as usize * self.view_height as usize
    }

    /// Top-left corner of `view` in the packed picture.
    pub fn view_origin(&self, view: u16) -> (u32, u32) {
        let column = u32::from(view % self.columns);
        let row = u32::from(view / self.columns);
        (column * self.view_width, row * self.view_height)
    }

    /// Index in the packed picture of pixel `y * view_width + x` of `view`.
    pub fn packed_index(&self, view: u16, pixel: u32) -> usize {
        let (x0, y0) = self.view_origin(view);
        let x = pixel % self.view_width;
        let y = pixel / self.view_width;
        (y0 + y) as usize * self.width() as usize + (x0 + x) as usize
    }
}

/// Names one batch of one frame: an object and the batch number the master gave it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BatchKey {
    pub object: u32,
    pub batch: u32,
}

/// One batch the master planned: which view, which pixels (`y * view_width + x`).
#[derive(Debug, Clone, PartialEq)]
pub struct PlannedBatch {
    pub key: BatchKey,
    pub view: u16,
    pub pixels: Arc<[u32]>,
}

/// Everything the compositor needs to know about a frame before its batches arrive.
#[derive(Debug, Clone, PartialEq)]
pub struct FramePlan {
    pub session: SessionId,
    pub frame: FrameId,
    pub layout: FrameLayout,
    /// Opaque background, linear RGB, behind every object.
    pub background: [f32; 3],
    /// After this instant the frame is fused with whatever has arrived.
    pub deadline: Instant,
    pub batches: Vec<PlannedBatch>,
}

/// One batch of results from a worker: where it goes in the frame, and the worker's
/// message itself, shared and never copied (fusion reads its arrays in place): `pixels`
/// (indices `y * view_width + x` inside the view), `color`, `opacity`, `depth`.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchResult {
    pub session: SessionId,
    pub frame: FrameId,
    pub view: u16,
    pub key: BatchKey,
    pub data: Arc<nephele_proto::BatchResult>,
}

impl BatchResult {
    /// A batch made in this process (the test pattern, tests, benchmarks) from a kernel's
    /// results: the proto message a worker would have sent, with zero ids.
    pub fn from_results(
        session: SessionId,
        frame: FrameId,
        view: u16,
        key: BatchKey,
        pixels: Vec<u32>,
        results: PixelResults,
    ) -> BatchResult {
        let PixelResults { color, opacity, depth } = results;
        let data = nephele_proto::BatchResult {
            ids: nephele_proto::BatchIds::default(),
            worker_id: 0,
            width: 0,
            height: 0,
            pixels,
            color,
            opacity,
            depth,
            render_time_us: 0,
            stats: nephele_proto::KernelStats::default(),
            encoding: nephele_proto::ResultEncoding::F32,
        };
        BatchResult { session, frame, view, key, data: Arc::new(data) }
    }

    /// Pixel indices inside the view, one per result.
    pub fn pixels(&self) -> &[u32] {
        &self.data.pixels
    }

    /// Checks lengths, index ranges and values against `layout`. Colour must be finite and
    /// non-negative (linear radiance may exceed 1), opacity in `[0, 1]`, depth finite,
    /// non-negative, and positive where opacity is positive (the kernel contract).
    pub fn validate(&self, layout: &FrameLayout) -> Result<(), FusionError> {
        let fail = |reason: String| {
            Err(FusionError::InvalidBatch { frame: self.frame, object: self.key.object, batch: self.key.batch, reason })
        };
        let n = self.data.pixels.len();
        let r = &*self.data;
        if r.color.len() != n || r.opacity.len() != n || r.depth.len() != n {
            return fail(format!(
                "{} pixels but {} colours, {} opacities, {} depths",
                n,
                r.color.len(),
                r.opacity.len(),
                r.depth.len()
            ));
        }
        if self.view >= layout.views() {
            return fail(format!("view {} of a {}-view frame", self.view, layout.views()));
        }
        let count = layout.view_pixel_count() as u64;
        // Branch-free passes first (they vectorise); the slow loops below only run to name
        // the offending item of a batch already known to be bad.
        let max_pixel = self.data.pixels.iter().fold(0u32, |m, &p| m.max(p));
        if n > 0 && u64::from(max_pixel) >= count {
            return fail(format!(
                "pixel {max_pixel} outside the {}x{} view",
                layout.view_width(),
                layout.view_height()
            ));
        }
        // On the bit patterns (integer compares vectorise, and NaN needs no special case):
        // finite and >= 0 is +0..+MAX or -0; within [0, 1] is +0..=1.0 or -0.
        const NEG_ZERO: u32 = 0x8000_0000;
        let finite_nonneg = |b: u32| (b < 0x7f80_0000) | (b == NEG_ZERO);
        let colours_ok = r.color.as_flattened().iter().fold(true, |ok, v| ok & finite_nonneg(v.to_bits()));
        let items_ok = r.opacity.iter().zip(&r.depth).fold(true, |ok, (a, z)| {
            let (a, z) = (a.to_bits(), z.to_bits());
            let a_in_unit = (a <= 0x3f80_0000) | (a == NEG_ZERO);
            let a_positive = (a != 0) & (a != NEG_ZERO);
            let z_zero = z & 0x7fff_ffff == 0;
            ok & a_in_unit & finite_nonneg(z) & !(a_positive & z_zero)
        });
        if colours_ok && items_ok {
            return Ok(());
        }
        for i in 0..n {
            let c = r.color[i];
            let (a, z) = (r.opacity[i], r.depth[i]);
            if !c.iter().all(|v| v.is_finite() && *v >= 0.0) {
                return fail(format!("colour {c:?} at item {i} is not finite and non-negative"));
            }
            if !(0.0..=1.0).contains(&a) {
                return fail(format!("opacity {a} at item {i} is outside [0, 1]"));
            }
            if !(z.is_finite() && z >= 0.0) {
                return fail(format!("depth {z} at item {i} is not finite and non-negative"));
            }
            if a > 0.0 && z == 0.0 {
                return fail(format!("depth 0 at item {i} where opacity is {a}"));
            }
        }
        Ok(())
    }
}

/// A fused frame: linear RGB of the packed picture, row-major, `layout.width()` wide.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedFrame {
    pub session: SessionId,
    pub frame: FrameId,
    pub layout: FrameLayout,
    pub rgb: Arc<Vec<[f32; 3]>>,
    pub report: FrameReport,
}

/// What went into one fused frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameReport {
    pub batches_planned: u32,
    pub batches_received: u32,
    /// Planned batches that had not arrived at the deadline.
    pub batches_missing: u32,
    /// Pixels taken from the previous frame (or the background) because of missing batches.
    pub pixels_filled: u64,
    /// Samples composited (one per object per pixel that saw something).
    pub samples: u64,
    /// True when fused at the deadline rather than on completion.
    pub deadline_hit: bool,
}

/// Per-session counters, since the session opened (`GET /v1/sessions` reports them).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SessionCounters {
    pub frames_planned: u64,
    /// Frames fused with every planned batch.
    pub frames_complete: u64,
    /// Frames fused at the deadline with batches missing.
    pub frames_deadline: u64,
    /// Frames dropped because a newer frame was ready first.
    pub frames_superseded: u64,
    pub batches_received: u64,
    /// Planned batches absent from the frame they belonged to.
    pub batches_missing: u64,
    /// Batches that arrived after their frame was sent (or superseded); dropped.
    pub batches_late: u64,
    /// Batches rejected by validation, unplanned or duplicated; dropped.
    pub batches_rejected: u64,
    pub pixels_filled: u64,
}

/// Limits that bound the compositor's memory whatever its inputs, and the size of its
/// parallel work.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FusionLimits {
    /// Frames of one session waiting at once; planning one more supersedes the oldest.
    pub max_pending_frames: usize,
    /// Batches of one session held while their frame plan has not arrived yet.
    pub max_early_batches: usize,
    /// Pixels fused by one parallel task (whole rows of the packed picture, at least one):
    /// a task's counts and samples then stay in the cache.
    pub band_pixels: usize,
}

impl Default for FusionLimits {
    fn default() -> Self {
        FusionLimits { max_pending_frames: 8, max_early_batches: 4096, band_pixels: 32 * 1024 }
    }
}

/// What happened to a batch handed to [`Compositor::add_batch`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchStatus {
    /// Stored; the frame still waits for other batches.
    Accepted,
    /// Stored, and it was the last one the frame waited for.
    FrameComplete,
    /// Stored until the frame's plan arrives.
    Early,
    /// Its frame was already sent or superseded; dropped and counted.
    Late,
}

#[derive(Debug)]
struct PendingFrame {
    plan: FramePlan,
    index: HashMap<BatchKey, usize>,
    received: Vec<Option<BatchResult>>,
    received_count: usize,
}

impl PendingFrame {
    fn is_complete(&self) -> bool {
        self.received_count == self.plan.batches.len()
    }
}

#[derive(Debug)]
struct LastFrame {
    layout: FrameLayout,
    rgb: Arc<Vec<[f32; 3]>>,
}

#[derive(Debug, Default)]
struct SessionState {
    pending: BTreeMap<FrameId, PendingFrame>,
    early: Vec<BatchResult>,
    /// Newest frame sent or superseded; batches and plans at or below it are late.
    done_upto: Option<FrameId>,
    last: Option<LastFrame>,
    counters: SessionCounters,
}

impl SessionState {
    fn is_done(&self, frame: FrameId) -> bool {
        self.done_upto.is_some_and(|d| frame <= d)
    }
}

/// Gathers the batches of every session's frames and fuses them. See the module docs.
#[derive(Debug, Default)]
pub struct Compositor {
    sessions: HashMap<SessionId, SessionState>,
    limits: FusionLimits,
    /// Batches for sessions that are not open.
    unknown_session_batches: u64,
}

impl Compositor {
    pub fn new(limits: FusionLimits) -> Self {
        Compositor { sessions: HashMap::new(), limits, unknown_session_batches: 0 }
    }

    pub fn open_session(&mut self, session: SessionId) -> Result<(), FusionError> {
        if self.sessions.contains_key(&session) {
            return Err(FusionError::SessionExists(session));
        }
        self.sessions.insert(session, SessionState::default());
        Ok(())
    }

    /// Forgets a session and everything pending for it; returns its final counters.
    pub fn close_session(&mut self, session: SessionId) -> Option<SessionCounters> {
        self.sessions.remove(&session).map(|s| s.counters)
    }

    pub fn sessions(&self) -> impl Iterator<Item = SessionId> + '_ {
        self.sessions.keys().copied()
    }

    pub fn counters(&self, session: SessionId) -> Option<SessionCounters> {
        self.sessions.get(&session).map(|s| s.counters)
    }

    /// Batches dropped because their session was not open.
    pub fn unknown_session_batches(&self) -> u64 {
        self.unknown_session_batches
    }

    /// Registers a frame's plan. Batches that arrived before it are moved in.
    pub fn plan_frame(&mut self, plan: FramePlan) -> Result<(), FusionError> {
        let limits = self.limits;
        let state = self.sessions.get_mut(&plan.session).ok_or(FusionError::UnknownSession(plan.session))?;
        if let Some(last) = state.done_upto
            && plan.frame <= last
        {
            return Err(FusionError::StalePlan { session: plan.session, frame: plan.frame, last });
        }
        if state.pending.contains_key(&plan.frame) {
            return Err(FusionError::DuplicatePlan { session: plan.session, frame: plan.frame });
        }
        let mut index = HashMap::with_capacity(plan.batches.len());
        let count = plan.layout.view_pixel_count() as u64;
        for (i, b) in plan.batches.iter().enumerate() {
            if b.view >= plan.layout.views() {
                return Err(FusionError::InvalidPlan(format!(
                    "batch {:?} in view {} of {}",
                    b.key,
                    b.view,
                    plan.layout.views()
                )));
            }
            if let Some(p) = b.pixels.iter().find(|&&p| u64::from(p) >= count) {
                return Err(FusionError::InvalidPlan(format!("batch {:?} plans pixel {p} outside its view", b.key)));
            }
            if index.insert(b.key, i).is_some() {
                return Err(FusionError::InvalidPlan(format!("batch {:?} planned twice", b.key)));
            }
        }
        if !plan.background.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(FusionError::InvalidPlan(format!("background {:?}", plan.background)));
        }
        let frame = plan.frame;
        let received = vec![None; plan.batches.len()];
        state.pending.insert(frame, PendingFrame { plan, index, received, received_count: 0 });
        state.counters.frames_planned += 1;
        // Bound memory: too many frames in flight means the oldest will never be shown.
        while state.pending.len() > limits.max_pending_frames {
            if let Some((old, _)) = state.pending.pop_first() {
                state.counters.frames_superseded += 1;
                state.done_upto = Some(state.done_upto.map_or(old, |d| d.max(old)));
            }
        }
        let early = std::mem::take(&mut state.early);
        let mut first_error = None;
        for batch in early {
            if batch.frame == frame {
                if let Err(e) = insert_batch(state, batch)
                    && first_error.is_none()
                {
                    first_error = Some(e);
                }
            } else if !state.is_done(batch.frame) {
                state.early.push(batch);
            } else {
                state.counters.batches_late += 1;
            }
        }
        // An early batch that fails validation is counted and dropped; the plan itself stands.
        if let Some(e) = first_error {
            tracing::debug!("dropped an early batch of frame {frame}: {e}");
        }
        Ok(())
    }

    /// Hands in one batch. Invalid, unplanned and duplicate batches are rejected (and
    /// counted); batches of frames already sent are dropped as late.
    pub fn add_batch(&mut self, batch: BatchResult) -> Result<BatchStatus, FusionError> {
        let Some(state) = self.sessions.get_mut(&batch.session) else {
            self.unknown_session_batches += 1;
            return Err(FusionError::UnknownSession(batch.session));
        };
        if state.is_done(batch.frame) {
            state.counters.batches_late += 1;
            return Ok(BatchStatus::Late);
        }
        if !state.pending.contains_key(&batch.frame) {
            if state.early.len() >= self.limits.max_early_batches {
                state.counters.batches_rejected += 1;
                return Err(FusionError::TooManyEarlyBatches(batch.session));
            }
            state.early.push(batch);
            return Ok(BatchStatus::Early);
        }
        insert_batch(state, batch)
    }

    /// The earliest deadline among pending frames: when [`Compositor::poll`] should run next.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.sessions.values().flat_map(|s| s.pending.values().map(|p| p.plan.deadline)).min()
    }

    /// Fuses every frame that is ready at `now`: complete, or past its deadline. Per session
    /// only the newest ready frame is fused; older pending frames are superseded (a newer
    /// picture is already there, showing an older one would only add latency).
    pub fn poll(&mut self, now: Instant) -> Vec<FusedFrame> {
        let mut out = Vec::new();
        let mut ids: Vec<SessionId> = self.sessions.keys().copied().collect();
        ids.sort_unstable();
        for id in ids {
            let Some(state) = self.sessions.get_mut(&id) else { continue };
            let ready =
                state.pending.iter().rev().find(|(_, p)| p.is_complete() || now >= p.plan.deadline).map(|(&f, _)| f);
            let Some(frame) = ready else { continue };
            let older: Vec<FrameId> = state.pending.range(..frame).map(|(&f, _)| f).collect();
            for f in older {
                state.pending.remove(&f);
                state.counters.frames_superseded += 1;
            }
            let Some(pending) = state.pending.remove(&frame) else { continue };
            state.done_upto = Some(frame);
            let last = state.last.as_ref().filter(|l| l.layout == pending.plan.layout);
            let fused = fuse(&pending, last.map(|l| l.rgb.as_slice()), self.limits.band_pixels);
            let c = &mut state.counters;
            if fused.report.batches_missing == 0 {
                c.frames_complete += 1;
            } else {
                c.frames_deadline += 1;
            }
            c.batches_missing += u64::from(fused.report.batches_missing);
            c.pixels_filled += fused.report.pixels_filled;
            state.last = Some(LastFrame { layout: fused.layout, rgb: fused.rgb.clone() });
            // Early batches of frames now superseded can never be used.
            let before = state.early.len();
            state.early.retain(|b| b.frame > frame);
            state.counters.batches_late += (before - state.early.len()) as u64;
            out.push(fused);
        }
        out
    }
}

fn insert_batch(state: &mut SessionState, batch: BatchResult) -> Result<BatchStatus, FusionError> {
    let outcome = try_insert(state.pending.get_mut(&batch.frame), batch);
    match outcome {
        Ok(_) => state.counters.batches_received += 1,
        Err(_) => state.counters.batches_rejected += 1,
    }
    outcome
}

fn try_insert(pending: Option<&mut PendingFrame>, batch: BatchResult) -> Result<BatchStatus, FusionError> {
    let (frame, object, number) = (batch.frame, batch.key.object, batch.key.batch);
    let Some(pending) = pending else {
        return Err(FusionError::UnplannedBatch { frame, object, batch: number });
    };
    let Some(&slot) = pending.index.get(&batch.key) else {
        return Err(FusionError::UnplannedBatch { frame, object, batch: number });
    };
    batch.validate(&pending.plan.layout)?;
    let planned = &pending.plan.batches[slot];
    // A compact result sends only the pixels its object touched (the others are misses), so
    // a batch may hold fewer pixels than planned, never more.
    if planned.view != batch.view || planned.pixels.len() < batch.data.pixels.len() {
        let reason = format!(
            "planned {} pixels of view {}, got {} pixels of view {}",
            planned.pixels.len(),
            planned.view,
            batch.data.pixels.len(),
            batch.view
        );
        return Err(FusionError::InvalidBatch { frame, object, batch: number, reason });
    }
    if pending.received[slot].is_some() {
        return Err(FusionError::DuplicateBatch { frame, object, batch: number });
    }
    pending.received[slot] = Some(batch);
    pending.received_count += 1;
    Ok(if pending.is_complete() { BatchStatus::FrameComplete } else { BatchStatus::Accepted })
}

/// One object's contribution to one pixel, copied out of its batch so that compositing
/// reads contiguous memory.
#[derive(Debug, Clone, Copy, Default)]
struct Sample {
    depth: f32,
    /// Planned batch order, for a deterministic order among equal depths.
    slot: u32,
    color: [f32; 3],
    alpha: f32,
}

/// One received batch, as a fusion task reads it: its pixels in ascending order (through
/// `order` when the batch did not send them sorted) and its range.
struct BatchView<'a> {
    slot: u32,
    batch: &'a BatchResult,
    /// A permutation sorting `batch.pixels`; `None` when they are sorted already.
    order: Option<Vec<u32>>,
    min_pixel: u32,
    max_pixel: u32,
}

impl BatchView<'_> {
    fn pixel_at(&self, i: usize) -> (u32, usize) {
        let item = self.order.as_ref().map_or(i, |o| o[i] as usize);
        (self.batch.data.pixels[item], item)
    }

    /// The items with a pixel in `[from, to)`, in ascending pixel order.
    fn items_in(&self, from: u32, to: u32) -> impl Iterator<Item = (u32, usize)> + '_ {
        let n = self.batch.data.pixels.len();
        let first = match &self.order {
            None => self.batch.data.pixels.partition_point(|&p| p < from),
            Some(o) => o.partition_point(|&i| self.batch.data.pixels[i as usize] < from),
        };
        (first..n).map(|i| self.pixel_at(i)).take_while(move |&(p, _)| p < to)
    }
}

/// Per-thread scratch of [`fuse`]'s tasks, reused from one task to the next.
#[derive(Default)]
struct FuseScratch {
    ends: Vec<u32>,
    samples: Vec<Sample>,
    sorted: Vec<Sample>,
}

/// Fuses a frame: composites every view's samples by depth and fills missing batches.
///
/// The packed picture is cut into bands of rows fused in parallel. A band gathers, for each
/// view it shows, the samples of the batches that reach its rows (batches' pixels are
/// searched in ascending order, so a band reads only its own part of each batch), buckets
/// them by pixel with a counting sort, then blends each pixel's bucket front to back in
/// depth order (ties in planned batch order, so the result never depends on threads).
fn fuse(pending: &PendingFrame, last: Option<&[[f32; 3]]>, band_pixels: usize) -> FusedFrame {
    let plan = &pending.plan;
    let layout = plan.layout;
    let mut report = FrameReport {
        batches_planned: plan.batches.len() as u32,
        batches_received: pending.received_count as u32,
        batches_missing: (plan.batches.len() - pending.received_count) as u32,
        deadline_hit: !pending.is_complete(),
        ..FrameReport::default()
    };
    let view_pixels = layout.view_pixel_count();
    let keys = view_pixels * usize::from(layout.views());
    let batches: Vec<BatchView> = pending
        .received
        .par_iter()
        .enumerate()
        .filter_map(|(slot, b)| b.as_ref().map(|b| (slot, b)))
        .map(|(slot, batch)| {
            let pixels = &batch.data.pixels;
            let sorted = pixels.windows(2).all(|w| w[0] <= w[1]);
            let order = (!sorted).then(|| {
                let mut order: Vec<u32> = (0..pixels.len() as u32).collect();
                order.sort_by_key(|&i| pixels[i as usize]);
                order
            });
            let (min_pixel, max_pixel) = pixels.iter().fold((u32::MAX, 0), |(lo, hi), &p| (lo.min(p), hi.max(p)));
            BatchView { slot: slot as u32, batch, order, min_pixel, max_pixel }
        })
        .collect();

    let width = layout.width() as usize;
    let (vw, vh) = (layout.view_width() as usize, layout.view_height() as usize);
    let columns = usize::from(layout.columns());
    let views = usize::from(layout.views());
    let background = plan.background;
    let mut rgb = vec![background; layout.pixel_count()];
    let rows_per_task = (band_pixels / width.max(1)).max(1);
    let batches = &batches;
    report.samples = rgb
        .par_chunks_mut(width * rows_per_task)
        .enumerate()
        .map_init(FuseScratch::default, |scratch, (task, out)| {
            let mut samples_fused = 0u64;
            let first_row = task * rows_per_task;
            let rows = out.len() / width;
            // A band may straddle two grid rows of views: fuse it one grid row at a time.
            let mut row = first_row;
            while row < first_row + rows {
                let grid_row = row / vh;
                let segment_end = ((grid_row + 1) * vh).min(first_row + rows);
                let (y0, y1) = (row % vh, row % vh + (segment_end - row));
                for column in 0..columns {
                    let view = grid_row * columns + column;
                    if view >= views {
                        break;
                    }
                    let target = OutRows { rows: &mut *out, width, x0: column * vw, first_row: row - first_row, vw };
                    samples_fused += fuse_view_rows(
                        batches,
                        scratch,
                        view as u16,
                        (y0 * vw) as u32,
                        (y1 * vw) as u32,
                        background,
                        target,
                    );
                }
                row = segment_end;
            }
            samples_fused
        })
        .sum();

    // Missing batches: their pixels show the last frame's picture of the same view.
    if report.batches_missing > 0 {
        let mut filled = vec![false; keys];
        for (slot, planned) in plan.batches.iter().enumerate() {
            if pending.received[slot].is_some() {
                continue;
            }
            let base = usize::from(planned.view) * view_pixels;
            for &p in planned.pixels.iter() {
                if !std::mem::replace(&mut filled[base + p as usize], true) {
                    let index = layout.packed_index(planned.view, p);
                    rgb[index] = last.map_or(background, |l| l[index]);
                    report.pixels_filled += 1;
                }
            }
        }
    }
    FusedFrame { session: plan.session, frame: plan.frame, layout, rgb: Arc::new(rgb), report }
}

/// Where a view's rows go in a band of the packed picture: `rows` is the band (`width`
/// pixels per row), the view's first row lands on band row `first_row`, at column `x0`.
struct OutRows<'a> {
    rows: &'a mut [[f32; 3]],
    width: usize,
    x0: usize,
    first_row: usize,
    vw: usize,
}

/// Fuses the pixels `[from, to)` (whole rows) of one view into `out`; returns the samples
/// composited.
fn fuse_view_rows(
    batches: &[BatchView],
    scratch: &mut FuseScratch,
    view: u16,
    from: u32,
    to: u32,
    background: [f32; 3],
    out: OutRows,
) -> u64 {
    let reaching = || batches.iter().filter(move |b| b.batch.view == view && b.max_pixel >= from && b.min_pixel < to);
    let span = (to - from) as usize;
    // ends[k + 1] counts the samples of pixel from + k; after the prefix sum, ends[k] is where
    // pixel from + k starts.
    let ends = &mut scratch.ends;
    ends.clear();
    ends.resize(span + 1, 0);
    let mut total = 0usize;
    for b in reaching() {
        let r = &*b.batch.data;
        for (p, item) in b.items_in(from, to) {
            if contributes(r.opacity[item], &r.color[item]) {
                ends[(p - from) as usize + 1] += 1;
                total += 1;
            }
        }
    }
    if total == 0 {
        return 0;
    }
    for k in 1..ends.len() {
        ends[k] += ends[k - 1];
    }
    let samples = &mut scratch.samples;
    samples.clear();
    samples.resize(total, Sample::default());
    for b in reaching() {
        let r = &*b.batch.data;
        for (p, item) in b.items_in(from, to) {
            let (alpha, color) = (r.opacity[item], r.color[item]);
            if contributes(alpha, &color) {
                let cursor = &mut ends[(p - from) as usize];
                samples[*cursor as usize] = Sample { depth: r.depth[item], slot: b.slot, color, alpha };
                *cursor += 1;
            }
        }
    }
    // After the scatter, ends[k] is the end of pixel from + k and ends[k - 1] its start.
    let sorted = &mut scratch.sorted;
    let mut start = 0usize;
    for (k, &end) in ends[..span].iter().enumerate() {
        let end = end as usize;
        let bucket = &samples[start..end];
        start = end;
        let (color, alpha) = match bucket {
            [] => continue,
            [one] => (one.color, one.alpha),
            many => {
                sorted.clear();
                sorted.extend_from_slice(many);
                sorted.sort_unstable_by(|a, b| a.depth.total_cmp(&b.depth).then(a.slot.cmp(&b.slot)));
                composite(sorted)
            }
        };
        let t = 1.0 - alpha;
        let (y, x) = (k / out.vw, k % out.vw);
        out.rows[(out.first_row + y) * out.width + out.x0 + x] =
            [color[0] + t * background[0], color[1] + t * background[1], color[2] + t * background[2]];
    }
    total as u64
}

/// Front-to-back blending of depth-sorted samples (premultiplied colour):
/// `C += (1 - A) c; A += (1 - A) a`.
fn composite(sorted: &[Sample]) -> ([f32; 3], f32) {
    let mut color = [0.0f32; 3];
    let mut alpha = 0.0f32;
    for s in sorted {
        let t = 1.0 - alpha;
        color[0] += t * s.color[0];
        color[1] += t * s.color[1];
        color[2] += t * s.color[2];
        alpha += t * s.alpha;
    }
    (color, alpha)
}

/// A sample that adds nothing (no opacity, no colour: the ray saw nothing) is skipped.
#[inline]
fn contributes(opacity: f32, color: &[f32; 3]) -> bool {
    opacity > 0.0 || *color != [0.0; 3]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn results(items: &[([f32; 3], f32, f32)]) -> PixelResults {
        PixelResults {
            color: items.iter().map(|i| i.0).collect(),
            opacity: items.iter().map(|i| i.1).collect(),
            depth: items.iter().map(|i| i.2).collect(),
        }
    }

    fn planned(object: u32, batch: u32, view: u16, pixels: &[u32]) -> PlannedBatch {
        PlannedBatch { key: BatchKey { object, batch }, view, pixels: pixels.into() }
    }

    fn result(
        frame: FrameId,
        object: u32,
        batch: u32,
        view: u16,
        pixels: &[u32],
        items: &[([f32; 3], f32, f32)],
    ) -> BatchResult {
        BatchResult::from_results(1, frame, view, BatchKey { object, batch }, pixels.to_vec(), results(items))
    }

    fn plan(
        frame: FrameId,
        layout: FrameLayout,
        background: [f32; 3],
        deadline: Instant,
        batches: Vec<PlannedBatch>,
    ) -> FramePlan {
        FramePlan { session: 1, frame, layout, background, deadline, batches }
    }

    /// Two objects, one a translucent shell, over a grey background, on a 2x2 view.
    /// Every expected value is computed by hand from `C += (1-A) c; A += (1-A) a`.
    #[test]
    fn translucent_and_solid_objects_fuse_front_to_back_exactly() {
        let t0 = Instant::now();
        let layout = FrameLayout::mono(2, 2).unwrap();
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        // Object 0: translucent shell (opacity 0.5, premultiplied red 0.25) on pixels 0, 1, 2.
        // Object 1: solid green (premultiplied 0.5) on pixels 0, 1 (two workers: two batches).
        let p = plan(
            7,
            layout,
            [0.5, 0.5, 0.5],
            t0 + Duration::from_millis(50),
            vec![planned(0, 0, 0, &[0, 1, 2]), planned(1, 0, 0, &[0]), planned(1, 1, 0, &[1])],
        );
        c.plan_frame(p).unwrap();
        // Solid object arrives first; at pixel 1 it is in front of the shell.
        assert_eq!(c.add_batch(result(7, 1, 0, 0, &[0], &[([0.0, 0.5, 0.0], 1.0, 2.0)])), Ok(BatchStatus::Accepted));
        assert_eq!(c.add_batch(result(7, 1, 1, 0, &[1], &[([0.0, 0.5, 0.0], 1.0, 0.5)])), Ok(BatchStatus::Accepted));
        assert!(c.poll(t0).is_empty(), "incomplete before the deadline");
        let shell = [([0.25, 0.0, 0.0], 0.5, 1.0); 3];
        assert_eq!(c.add_batch(result(7, 0, 0, 0, &[0, 1, 2], &shell)), Ok(BatchStatus::FrameComplete));
        let frames = c.poll(t0);
        assert_eq!(frames.len(), 1);
        let f = &frames[0];
        // Pixel 0: shell (z=1) then solid (z=2): C = 0.25 red + 0.5 * 0.5 green, A = 1.
        assert_eq!(f.rgb[0], [0.25, 0.25, 0.0]);
        // Pixel 1: solid (z=0.5) in front hides the shell entirely.
        assert_eq!(f.rgb[1], [0.0, 0.5, 0.0]);
        // Pixel 2: shell over the background: 0.25 + 0.5 * 0.5 = 0.5 red, 0.25 green/blue.
        assert_eq!(f.rgb[2], [0.5, 0.25, 0.25]);
        // Pixel 3: nothing: background.
        assert_eq!(f.rgb[3], [0.5, 0.5, 0.5]);
        assert_eq!(f.report.samples, 5);
        assert!(!f.report.deadline_hit);
        let counters = c.counters(1).unwrap();
        assert_eq!((counters.frames_complete, counters.batches_received, counters.batches_missing), (1, 3, 0));
    }

    /// Compact results send only the pixels their object touched: a batch with fewer pixels
    /// than planned (or none) completes the frame, and the pixels it left out are misses.
    #[test]
    fn compact_batches_with_only_touched_pixels_complete_the_frame() {
        let t0 = Instant::now();
        let layout = FrameLayout::mono(2, 2).unwrap();
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        let p = plan(
            3,
            layout,
            [0.5, 0.5, 0.5],
            t0 + Duration::from_secs(5),
            vec![planned(0, 0, 0, &[0, 1, 2, 3]), planned(1, 0, 0, &[0, 1])],
        );
        c.plan_frame(p).unwrap();
        // Object 0 touched pixels 1 and 3 only; object 1 touched nothing.
        let touched = [([0.2, 0.0, 0.0], 1.0, 1.0), ([0.0, 0.0, 0.4], 1.0, 1.0)];
        assert_eq!(c.add_batch(result(3, 0, 0, 0, &[1, 3], &touched)), Ok(BatchStatus::Accepted));
        assert_eq!(c.add_batch(result(3, 1, 0, 0, &[], &[])), Ok(BatchStatus::FrameComplete));
        let f = c.poll(t0).remove(0);
        assert_eq!(*f.rgb, vec![[0.5, 0.5, 0.5], [0.2, 0.0, 0.0], [0.5, 0.5, 0.5], [0.0, 0.0, 0.4]]);
        assert!(!f.report.deadline_hit);
        // More pixels than planned is still an invalid batch.
        c.plan_frame(plan(4, layout, [0.0; 3], t0, vec![planned(0, 0, 0, &[0])])).unwrap();
        let two = [([0.0; 3], 1.0, 1.0); 2];
        assert!(matches!(c.add_batch(result(4, 0, 0, 0, &[0, 1], &two)), Err(FusionError::InvalidBatch { .. })));
    }

    #[test]
    fn three_translucent_layers_in_any_arrival_order() {
        // Layers at depths 3, 1, 2 with opacities 0.5, 0.25, 0.5, premultiplied unit colours.
        // Sorted: z=1 (a .25, c .25 r), z=2 (a .5, c .5 g), z=3 (a .5, c .5 b).
        // C_r = .25; A = .25; C_g = .75 * .5 = .375; A = .25 + .375 = .625;
        // C_b = .375 * .5 = .1875; A = .8125; black background adds nothing.
        let layers = [
            (0u32, ([0.0, 0.0, 0.5], 0.5f32, 3.0f32)),
            (1, ([0.25, 0.0, 0.0], 0.25, 1.0)),
            (2, ([0.0, 0.5, 0.0], 0.5, 2.0)),
        ];
        for order in [[0usize, 1, 2], [2, 1, 0], [1, 0, 2]] {
            let t0 = Instant::now();
            let mut c = Compositor::default();
            c.open_session(1).unwrap();
            let layout = FrameLayout::mono(1, 1).unwrap();
            let batches = layers.iter().map(|(o, _)| planned(*o, 0, 0, &[0])).collect();
            c.plan_frame(plan(1, layout, [0.0; 3], t0, batches)).unwrap();
            for i in order {
                let (o, item) = layers[i];
                c.add_batch(result(1, o, 0, 0, &[0], &[item])).unwrap();
            }
            let f = c.poll(t0).remove(0);
            assert_eq!(f.rgb[0], [0.25, 0.375, 0.1875], "order {order:?}");
        }
    }

    #[test]
    fn stereo_views_are_packed_side_by_side() {
        let t0 = Instant::now();
        let layout = FrameLayout::stereo(2, 1).unwrap();
        assert_eq!((layout.width(), layout.height()), (4, 1));
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        c.plan_frame(plan(0, layout, [0.0; 3], t0, vec![planned(0, 0, 0, &[1]), planned(0, 1, 1, &[0])])).unwrap();
        c.add_batch(result(0, 0, 0, 0, &[1], &[([1.0, 0.0, 0.0], 1.0, 1.0)])).unwrap();
        c.add_batch(result(0, 0, 1, 1, &[0], &[([0.0, 0.0, 1.0], 1.0, 1.0)])).unwrap();
        let f = c.poll(t0).remove(0);
        assert_eq!(&f.rgb[..], &[[0.0; 3], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0; 3]]);
        // A 3-view grid with 2 columns: view 2 starts on the second row.
        let grid = FrameLayout::grid(2, 2, 3, 2).unwrap();
        assert_eq!((grid.width(), grid.height()), (4, 4));
        assert_eq!(grid.packed_index(2, 3), 3 * 4 + 1);
        assert_eq!(grid.packed_index(1, 2), 4 + 2);
    }

    #[test]
    fn deadline_fills_missing_batches_from_the_last_frame_and_counts_them() {
        let t0 = Instant::now();
        let layout = FrameLayout::stereo(2, 1).unwrap();
        let deadline = |f: u64| t0 + Duration::from_millis(20 * (f + 1));
        let red = ([1.0, 0.0, 0.0], 1.0, 1.0);
        let green = ([0.0, 1.0, 0.0], 1.0, 1.0);
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        let batches = || vec![planned(0, 0, 0, &[0, 1]), planned(0, 1, 1, &[0, 1])];
        // Frame 0: everything red, but the right view's batch never comes: no previous frame,
        // so the right view shows the background.
        c.plan_frame(plan(0, layout, [0.0, 0.0, 0.25], deadline(0), batches())).unwrap();
        c.add_batch(result(0, 0, 0, 0, &[0, 1], &[red, red])).unwrap();
        assert!(c.poll(deadline(0) - Duration::from_millis(1)).is_empty());
        let f0 = c.poll(deadline(0)).remove(0);
        assert_eq!(&f0.rgb[..], &[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.25], [0.0, 0.0, 0.25]]);
        assert_eq!((f0.report.batches_missing, f0.report.pixels_filled, f0.report.deadline_hit), (1, 2, true));
        // The late batch is dropped and counted.
        assert_eq!(c.add_batch(result(0, 0, 1, 1, &[0, 1], &[red, red])), Ok(BatchStatus::Late));
        // Frame 1: complete, all green.
        c.plan_frame(plan(1, layout, [0.0, 0.0, 0.25], deadline(1), batches())).unwrap();
        c.add_batch(result(1, 0, 0, 0, &[0, 1], &[green, green])).unwrap();
        c.add_batch(result(1, 0, 1, 1, &[0, 1], &[green, green])).unwrap();
        let f1 = c.poll(t0).remove(0);
        assert!(f1.rgb.iter().all(|p| *p == [0.0, 1.0, 0.0]));
        // Frame 2: the left view's batch is missing: it shows frame 1's left pixels (green);
        // the right view is red.
        c.plan_frame(plan(2, layout, [0.0, 0.0, 0.25], deadline(2), batches())).unwrap();
        c.add_batch(result(2, 0, 1, 1, &[0, 1], &[red, red])).unwrap();
        let f2 = c.poll(deadline(2)).remove(0);
        assert_eq!(&f2.rgb[..], &[[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]);
        let k = c.counters(1).unwrap();
        assert_eq!(
            (k.frames_complete, k.frames_deadline, k.batches_missing, k.pixels_filled, k.batches_late),
            (1, 2, 2, 4, 1)
        );
    }

    #[test]
    fn a_newer_ready_frame_supersedes_older_pending_ones() {
        let t0 = Instant::now();
        let layout = FrameLayout::mono(1, 1).unwrap();
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        let far = t0 + Duration::from_secs(1);
        c.plan_frame(plan(1, layout, [0.0; 3], far, vec![planned(0, 0, 0, &[0])])).unwrap();
        c.plan_frame(plan(2, layout, [0.0; 3], far, vec![planned(0, 0, 0, &[0])])).unwrap();
        assert_eq!(c.next_deadline(), Some(far));
        c.add_batch(result(2, 0, 0, 0, &[0], &[([0.5; 3], 1.0, 1.0)])).unwrap();
        let frames = c.poll(t0);
        assert_eq!(frames.iter().map(|f| f.frame).collect::<Vec<_>>(), vec![2]);
        assert_eq!(c.counters(1).unwrap().frames_superseded, 1);
        assert_eq!(c.add_batch(result(1, 0, 0, 0, &[0], &[([0.5; 3], 1.0, 1.0)])), Ok(BatchStatus::Late));
        assert!(matches!(
            c.plan_frame(plan(2, layout, [0.0; 3], far, vec![])),
            Err(FusionError::StalePlan { frame: 2, last: 2, .. })
        ));
        assert_eq!(c.next_deadline(), None);
    }

    #[test]
    fn batches_before_their_plan_are_kept_until_it_arrives() {
        let t0 = Instant::now();
        let layout = FrameLayout::mono(1, 1).unwrap();
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        assert_eq!(c.add_batch(result(3, 0, 0, 0, &[0], &[([0.5; 3], 1.0, 1.0)])), Ok(BatchStatus::Early));
        c.plan_frame(plan(3, layout, [0.0; 3], t0 + Duration::from_secs(1), vec![planned(0, 0, 0, &[0])])).unwrap();
        let f = c.poll(t0).remove(0);
        assert_eq!(f.rgb[0], [0.5; 3]);
        assert_eq!(c.counters(1).unwrap().frames_complete, 1);
    }

    #[test]
    fn nan_and_out_of_range_inputs_are_rejected_and_counted() {
        let t0 = Instant::now();
        let layout = FrameLayout::mono(2, 1).unwrap();
        let mut c = Compositor::default();
        c.open_session(1).unwrap();
        c.plan_frame(plan(0, layout, [0.0; 3], t0, vec![planned(0, 0, 0, &[0, 1])])).unwrap();
        let ok = ([0.1, 0.1, 0.1], 0.5, 1.0);
        let bad: Vec<(Vec<u32>, Vec<([f32; 3], f32, f32)>, &str)> = vec![
            (vec![0, 1], vec![ok, ([f32::NAN, 0.0, 0.0], 0.5, 1.0)], "colour"),
            (vec![0, 1], vec![ok, ([0.0, -0.1, 0.0], 0.5, 1.0)], "colour"),
            (vec![0, 1], vec![ok, ([0.0; 3], 1.5, 1.0)], "opacity"),
            (vec![0, 1], vec![ok, ([0.0; 3], f32::NAN, 1.0)], "opacity"),
            (vec![0, 1], vec![ok, ([0.0; 3], 0.5, f32::INFINITY)], "depth"),
            (vec![0, 1], vec![ok, ([0.0; 3], 0.5, -1.0)], "depth"),
            (vec![0, 1], vec![ok, ([0.0; 3], 0.5, 0.0)], "depth 0"),
            (vec![0, 2], vec![ok, ok], "outside"),
            (vec![0], vec![ok, ok], "pixels but"),
        ];
        for (i, (pixels, items, what)) in bad.iter().enumerate() {
            let e = c.add_batch(result(0, 0, 0, 0, pixels, items)).unwrap_err();
            assert!(e.to_string().contains(what), "case {i}: {e}");
        }
        // Wrong view, unplanned batch, unknown session.
        assert!(c.add_batch(result(0, 0, 0, 1, &[0, 1], &[ok, ok])).is_err());
        assert!(matches!(c.add_batch(result(0, 9, 0, 0, &[0, 1], &[ok, ok])), Err(FusionError::UnplannedBatch { .. })));
        let mut stranger = result(0, 0, 0, 0, &[0, 1], &[ok, ok]);
        stranger.session = 99;
        assert_eq!(c.add_batch(stranger), Err(FusionError::UnknownSession(99)));
        assert_eq!(c.unknown_session_batches(), 1);
        assert_eq!(c.counters(1).unwrap().batches_rejected, bad.len() as u64 + 2);
        // A valid batch still goes through, once.
        assert_eq!(c.add_batch(result(0, 0, 0, 0, &[0, 1], &[ok, ok])), Ok(BatchStatus::FrameComplete));
        assert!(matches!(c.add_batch(result(0, 0, 0, 0, &[0, 1], &[ok, ok])), Err(FusionError::DuplicateBatch { .. })));
        // Bad plans and layouts.
        assert!(FrameLayout::mono(0, 4).is_err());
        assert!(FrameLayout::grid(4, 4, 2, 3).is_err());
        assert!(FrameLayout::mono(9000, 4).is_err());
        let e = c.plan_frame(plan(5, layout, [0.0; 3], t0, vec![planned(0, 0, 0, &[7])])).unwrap_err();
        assert!(matches!(e, FusionError::InvalidPlan(_)), "{e}");
        let e = c.plan_frame(plan(5, layout, [f32::NAN; 3], t0, vec![])).unwrap_err();
        assert!(matches!(e, FusionError::InvalidPlan(_)), "{e}");
    }

    #[test]
    fn edge_values_pass_validation() {
        let layout = FrameLayout::mono(4, 1).unwrap();
        let ok = result(
            0,
            0,
            0,
            0,
            &[0, 1, 2, 3],
            &[
                ([-0.0, 0.0, f32::MAX], -0.0, 0.0),
                ([0.0; 3], 0.0, 0.0),
                ([1e-30, 2.0, 3.0], 1.0, f32::MAX),
                ([0.5; 3], f32::MIN_POSITIVE, 1e-30),
            ],
        );
        assert_eq!(ok.validate(&layout), Ok(()));
        let bad = result(0, 0, 0, 0, &[0], &[([0.0; 3], 1.0 + f32::EPSILON, 1.0)]);
        assert!(bad.validate(&layout).is_err());
        let bad = result(0, 0, 0, 0, &[0], &[([0.0; 3], f32::MIN_POSITIVE, -0.0)]);
        assert!(bad.validate(&layout).unwrap_err().to_string().contains("depth 0"));
    }

    #[test]
    fn pending_frames_and_early_batches_are_bounded() {
        let t0 = Instant::now();
        let layout = FrameLayout::mono(1, 1).unwrap();
        let mut c =
            Compositor::new(FusionLimits { max_pending_frames: 2, max_early_batches: 1, ..FusionLimits::default() });
        c.open_session(1).unwrap();
        for f in 0..4 {
            c.plan_frame(plan(f, layout, [0.0; 3], t0 + Duration::from_secs(1), vec![planned(0, 0, 0, &[0])])).unwrap();
        }
        assert_eq!(c.counters(1).unwrap().frames_superseded, 2);
        assert_eq!(c.add_batch(result(1, 0, 0, 0, &[0], &[([0.0; 3], 0.0, 0.0)])), Ok(BatchStatus::Late));
        assert_eq!(c.add_batch(result(10, 0, 0, 0, &[0], &[([0.0; 3], 0.0, 0.0)])), Ok(BatchStatus::Early));
        assert!(matches!(
            c.add_batch(result(11, 0, 0, 0, &[0], &[([0.0; 3], 0.0, 0.0)])),
            Err(FusionError::TooManyEarlyBatches(1))
        ));
        assert!(c.close_session(1).is_some());
        assert!(c.poll(t0).is_empty());
    }

    #[test]
    fn a_batch_reaching_a_band_by_its_first_pixel_only_is_fused() {
        // One-row bands of a 4x3 view: the batch's last pixel (4) is the first of band 1, and
        // its first pixel (3) the last of band 0.
        let t0 = Instant::now();
        let layout = FrameLayout::mono(4, 3).unwrap();
        let mut c = Compositor::new(FusionLimits { band_pixels: 4, ..FusionLimits::default() });
        c.open_session(1).unwrap();
        c.plan_frame(plan(0, layout, [0.0; 3], t0, vec![planned(0, 0, 0, &[4, 3])])).unwrap();
        c.add_batch(result(0, 0, 0, 0, &[4, 3], &[([0.5; 3], 1.0, 2.0), ([0.25; 3], 1.0, 2.0)])).unwrap();
        let f = c.poll(t0).remove(0);
        assert_eq!((f.rgb[3], f.rgb[4], f.rgb[5]), ([0.25; 3], [0.5; 3], [0.0; 3]));
        assert_eq!(f.report.samples, 2);
    }

    proptest::proptest! {
        /// Whatever the arrival order of the object batches, the fused pixel is the same and
        /// equals a direct front-to-back composite; the result stays within [0, max colour].
        #[test]
        fn fusion_is_independent_of_arrival_order(
            layers in proptest::collection::vec((0.0f32..1.0, 0.0f32..=1.0, 0.1f32..10.0), 1..6),
            seed in 0u64..1000,
        ) {
            let t0 = Instant::now();
            let layout = FrameLayout::mono(1, 1).unwrap();
            let mut order: Vec<usize> = (0..layers.len()).collect();
            // A cheap deterministic shuffle.
            let mut s = seed;
            for i in (1..order.len()).rev() {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                order.swap(i, (s >> 33) as usize % (i + 1));
            }
            let mut c = Compositor::default();
            c.open_session(1).unwrap();
            let batches = (0..layers.len()).map(|o| planned(o as u32, 0, 0, &[0])).collect();
            c.plan_frame(plan(0, layout, [0.2; 3], t0, batches)).unwrap();
            for &o in &order {
                let (v, a, z) = layers[o];
                c.add_batch(result(0, o as u32, 0, 0, &[0], &[([v * a; 3], a, z)])).unwrap();
            }
            let f = c.poll(t0).remove(0);
            let mut sorted: Vec<(usize, (f32, f32, f32))> = layers.iter().copied().enumerate().collect();
            sorted.sort_by(|x, y| x.1.2.total_cmp(&y.1.2).then(x.0.cmp(&y.0)));
            let (mut col, mut alpha) = (0.0f32, 0.0f32);
            for (_, (v, a, _)) in sorted {
                col += (1.0 - alpha) * (v * a);
                alpha += (1.0 - alpha) * a;
            }
            col += (1.0 - alpha) * 0.2;
            proptest::prop_assert_eq!(f.rgb[0], [col; 3]);
            proptest::prop_assert!((0.0..=1.0 + 1e-6).contains(&col));
        }

        /// Any layout (views in a grid), any bands (one row up to the whole picture, bands
        /// straddling grid rows), batches with pixels in any order and any overlap: every
        /// pixel equals a direct per-pixel composite of its samples sorted by (depth, batch).
        #[test]
        fn banded_fusion_equals_a_per_pixel_reference(
            (vw, vh, views) in (1u32..24, 1u32..24, 1u16..6),
            band_rows in 1usize..8,
            objects in proptest::collection::vec((0.0f32..1.0, 1usize..4, proptest::bool::ANY), 1..5),
            seed in 0u64..u64::MAX,
        ) {
            let t0 = Instant::now();
            let layout = FrameLayout::grid(vw, vh, views, views.div_ceil(2)).unwrap();
            let mut rng = seed;
            let mut next = move || {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (rng >> 33) as u32
            };
            let view_pixels = vw * vh;
            // Object o covers a random subset of each view (density `fill`), split into
            // `split` batches, each optionally shuffled; random colours, opacities (some 0),
            // depths (some tied).
            let mut planned_batches = Vec::new();
            let mut results = Vec::new();
            for (o, &(fill, split, shuffle)) in objects.iter().enumerate() {
                for view in 0..views {
                    let mut pixels: Vec<u32> = (0..view_pixels).filter(|_| (next() % 1000) as f32 / 1000.0 < fill).collect();
                    if shuffle {
                        for i in (1..pixels.len()).rev() {
                            pixels.swap(i, next() as usize % (i + 1));
                        }
                    }
                    let chunk = pixels.len().div_ceil(split).max(1);
                    for (b, part) in pixels.chunks(chunk).enumerate() {
                        let items: Vec<([f32; 3], f32, f32)> = part
                            .iter()
                            .map(|_| {
                                let a = [0.0, 0.3, 0.7, 1.0][next() as usize % 4];
                                let c = (next() % 100) as f32 / 100.0 * a;
                                let z = 1.0 + (next() % 5) as f32;
                                ([c, 0.5 * c, 0.25 * c], a, z)
                            })
                            .collect();
                        let batch = u32::from(view) * 100 + b as u32;
                        planned_batches.push(planned(o as u32, batch, view, part));
                        results.push(result(0, o as u32, batch, view, part, &items));
                    }
                }
            }
            let background = [0.1, 0.2, 0.3];
            let limits = FusionLimits { band_pixels: band_rows * layout.width() as usize, ..FusionLimits::default() };
            let mut c = Compositor::new(limits);
            c.open_session(1).unwrap();
            c.plan_frame(plan(0, layout, background, t0, planned_batches.clone())).unwrap();
            for r in results.iter().rev() {
                c.add_batch(r.clone()).unwrap();
            }
            let f = c.poll(t0).remove(0);
            // The reference: every sample of every pixel, in planned order, sorted, blended.
            let slot_of = |r: &BatchResult| planned_batches.iter().position(|p| p.key == r.key).unwrap();
            let mut per_pixel: Vec<Vec<(f32, usize, [f32; 3], f32)>> = vec![Vec::new(); layout.pixel_count()];
            for r in &results {
                for (i, &p) in r.data.pixels.iter().enumerate() {
                    let (color, alpha) = (r.data.color[i], r.data.opacity[i]);
                    if contributes(alpha, &color) {
                        per_pixel[layout.packed_index(r.view, p)].push((r.data.depth[i], slot_of(r), color, alpha));
                    }
                }
            }
            for (index, samples) in per_pixel.iter_mut().enumerate() {
                samples.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let (mut color, mut alpha) = ([0.0f32; 3], 0.0f32);
                for s in samples.iter() {
                    let t = 1.0 - alpha;
                    for k in 0..3 {
                        color[k] += t * s.2[k];
                    }
                    alpha += t * s.3;
                }
                let t = 1.0 - alpha;
                let expected = [color[0] + t * background[0], color[1] + t * background[1], color[2] + t * background[2]];
                proptest::prop_assert_eq!(f.rgb[index], expected, "pixel {}", index);
            }
            proptest::prop_assert_eq!(f.report.samples, per_pixel.iter().map(|s| s.len() as u64).sum::<u64>());
        }
    }
}
