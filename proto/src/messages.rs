//! The messages. Every type here is plain data: the wire layout lives in [`crate::codec`],
//! the limits and checks in [`crate::validate`].
//!
//! Who sends what:
//!
//! | message | from → to | when |
//! | --- | --- | --- |
//! | [`Hello`] | everyone, both ways | first frame on every connection |
//! | [`Register`] | worker → master | after the handshake |
//! | [`Registered`] | master → worker | answer to `Register` |
//! | [`LoadReport`] | worker → master | periodically; doubles as the heartbeat |
//! | [`RayBatch`] | master → worker | work |
//! | [`BatchResult`] | worker → composer | the pixels of one batch (packed arrays) |
//! | [`BatchDone`] | worker → master | a batch's result was handed to the composer |
//! | [`BatchFailed`] | worker → master | a batch could not be rendered (bad asset, bad camera, …) |
//! | [`Cancel`] | master → worker | drop queued batches (of a batch, frame or session) |
//! | [`Goodbye`] | any → peer | orderly close; a worker lists the batches it hands back |
//! | [`ErrorMessage`] | any → peer | a protocol error, sent (best effort) before closing |
//! | [`ComposerRegister`] | composer → master | after the handshake: name and the address workers send results to; answered by [`Registered`] |
//! | [`OpenStream`] | master → composer | a client's SDP offer for a new session |
//! | [`StreamOpened`] | composer → master | the SDP answer (or why there is none) |
//! | [`ClientPose`] | composer → master | one pose from a client's data channel |
//! | [`FramePlan`] | master → composer | a frame is complete: which task results make up each view |
//! | [`ReleaseTask`] | master → composer | a task's results are no longer needed |
//! | [`CloseStream`] | master ⇄ composer | a session ended (closed by its client, or its peer vanished) |
//! | [`Challenge`] | everyone, both ways | after the `Hello`s: a fresh nonce ([`crate::auth`]) |
//! | [`Proof`] | everyone, both ways | after the `Challenge`s: proof of the farm secret, bound to the peer's nonce |

use std::fmt;

/// Cells wholly inside an object's matter (`RayBatch::occluders`).
pub use nephele_geometry::SolidGrid;
/// The one view type, from the browser to the kernels (`nephele_geometry::view`).
pub use nephele_geometry::ViewProjection;
use serde::{Deserialize, Serialize};

use crate::PROTOCOL_VERSION;
pub use crate::auth::{Challenge, Proof};
use crate::packed;

/// What a peer is. Sent in [`Hello`] so that each side can refuse the wrong kind of peer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    Master,
    Worker,
    Composer,
    /// Benchmarks, test doubles, command-line probes.
    Tool,
}

impl Role {
    pub(crate) fn to_byte(self) -> u8 {
        match self {
            Role::Master => 1,
            Role::Worker => 2,
            Role::Composer => 3,
            Role::Tool => 4,
        }
    }

    pub(crate) fn from_byte(byte: u8) -> Option<Role> {
        Some(match byte {
            1 => Role::Master,
            2 => Role::Worker,
            3 => Role::Composer,
            4 => Role::Tool,
            _ => return None,
        })
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Role::Master => "master",
            Role::Worker => "worker",
            Role::Composer => "composer",
            Role::Tool => "tool",
        })
    }
}

/// First frame on every connection, both ways. Its layout is frozen across versions
/// (tag 1, magic `NPHL`, version u16 LE, role u8) so that any two builds can tell each
/// other that they disagree.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Hello {
    pub version: u16,
    pub role: Role,
}

impl Hello {
    /// A hello of this build's [`PROTOCOL_VERSION`].
    pub fn new(role: Role) -> Hello {
        Hello { version: PROTOCOL_VERSION, role }
    }
}

/// A worker introduces itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Register {
    /// Unique-ish, for logs and `GET /v1/farm`: `[A-Za-z0-9._-]`, 1 to 64 bytes.
    pub name: String,
    /// Render threads.
    pub threads: u32,
    /// Kernel kinds it can run (`RayKernel::kind`, e.g. "pathtrace", "inolf").
    pub kernels: Vec<String>,
    /// Throughput measured by a calibration render at start-up, rays per second. The
    /// scheduler's Heavy/Light thresholds come from these figures.
    pub rays_per_second: f64,
    /// What its neural kernels run on, for logs and `GET /v1/farm` (`cpu (AVX2+FMA)`,
    /// `NVIDIA H200 (Vulkan)`, `llvmpipe (Vulkan, software)`); free text, at most
    /// [`crate::validate::MAX_TEXT_LEN`] bytes.
    pub device: String,
}

/// The master accepts a worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Registered {
    /// Id the master gives the worker; it appears in [`BatchResult::worker_id`].
    pub worker_id: u64,
    /// How often the worker sends a [`LoadReport`]; the master presumes it dead after a few
    /// missed reports.
    pub load_report_interval_ms: u32,
}

/// A worker's load, sent periodically. It is the heartbeat too.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct LoadReport {
    /// Batches rendering now.
    pub in_flight_batches: u32,
    /// Batches received and waiting.
    pub queued_batches: u32,
    /// Pixels of the waiting batches.
    pub queued_rays: u64,
    /// Rays per second over the last report interval(s).
    pub recent_rays_per_second: f64,
    /// Totals since start.
    pub batches_done: u64,
    pub rays_done: u64,
}

/// Identifies a batch and the frame it belongs to; repeated in every message about it.
///
/// With shared rays one task (one object seen from one camera) feeds the frames of several
/// views and sessions: the composer files results by `task_id` and a [`FramePlan`] names the
/// tasks of each view. `session_id`, `frame_id` and `view_index` then name the first frame
/// the batch feeds (for logs and [`CancelTarget`]s).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub struct BatchIds {
    /// Unique per master; a re-issued batch keeps its id.
    pub batch_id: u64,
    /// The scheduler's task the batch is a part of (unique per master).
    pub task_id: u64,
    /// The user session (one user, one stream).
    pub session_id: u64,
    /// The frame of that session.
    pub frame_id: u64,
    /// Which view of the frame: 0 for a flat screen, 0/1 for the eyes of a headset, 0..45
    /// for a quilt.
    pub view_index: u32,
}

/// Work: render `pixels` of `camera`'s image of asset `asset_id`, send the result to
/// `composer`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RayBatch {
    pub ids: BatchIds,
    /// Object/asset to render: `[A-Za-z0-9._-]`, no `..`, 1 to 128 bytes.
    pub asset_id: String,
    pub camera: ViewProjection,
    /// Pixel indices `y * width + x`, each `< width * height`; packed little-endian u32 on
    /// the wire.
    #[serde(with = "packed")]
    pub pixels: Vec<u32>,
    /// Microseconds from when the master sent the batch by which the result must reach the
    /// composer; `None` for no deadline. Time left, not a wall-clock instant: the worker
    /// counts it from receipt on its own monotonic clock, so the machines' clocks need not
    /// agree (a step of the wall clock, or skew between hosts, once made every batch
    /// "expired"); the transit is not counted. A worker drops a batch whose deadline passed
    /// before it started and reports [`ErrorCode::DeadlineExpired`].
    pub deadline_in_us: Option<u64>,
    /// `host:port` of the composer that gathers this frame.
    pub composer: String,
    /// Views of the same asset this batch's pixels also feed, by reprojection (issue 16;
    /// NEPHELE's shared rays between adjacent views): empty for a plain batch.
    pub derived: Vec<DerivedView>,
    /// How strict that reuse is, and whether the worker may also take this batch's own
    /// pixels from its previous render of the same user's view of the asset.
    pub reuse: ReuseLimits,
    /// For an environment (issue 13): the solid matter of the objects fused in front of it,
    /// in the asset's coordinates; the kernel need not light what they hide. Empty for an
    /// object; at most [`RayBatch::MAX_OCCLUDERS`].
    pub occluders: Vec<SolidGrid>,
}

impl RayBatch {
    /// Most occluders a batch may carry.
    pub const MAX_OCCLUDERS: usize = 16;
}

/// A view taken from a batch's rendered pixels (the eyes of a headset, the neighbours in a
/// quilt): the worker renders the batch, lifts its solid pixels by their depth into
/// `camera`'s image, renders only those of `pixels` that the reprojection does not cover
/// (disocclusions, silhouettes, pixels seen at too large an angle), and sends all of
/// `pixels` to the composer as one [`BatchResult`] under `ids`, before the batch's own.
///
/// The master promises that the batch holds *every* pixel of its camera's covered set in the
/// rows it spans (whole rows of the task's coverage), so that a pixel of the batch's bounding
/// box that the batch does not hold is known to be empty.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DerivedView {
    pub ids: BatchIds,
    pub camera: ViewProjection,
    /// Pixel indices `y * width + x` of `camera`'s image; packed like [`RayBatch::pixels`].
    #[serde(with = "packed")]
    pub pixels: Vec<u32>,
}

/// The limits of `nephele_share::Settings` that the master sets per object.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReuseLimits {
    /// Largest angle at the surface point between the rendered and the derived view's rays,
    /// degrees, in `[0, 90]`.
    pub max_angle_deg: f32,
    /// Largest colour difference (linear, per channel) among the source pixels read for one
    /// reused pixel; `>= 0`, infinity for no limit.
    pub max_contrast: f32,
    /// A user's consecutive frames (issue 16, NEPHELE section 5: "consecutive frames of one
    /// user"): for how many batches after rendering a view of this asset for this session in
    /// full the worker may take a later view from that render by reprojection, rendering
    /// only what it cannot vouch for; then it renders in full again, so that no pixel is
    /// older than this many frames and none is resampled twice. 0: never (every batch in
    /// full); at most [`ReuseLimits::MAX_PREVIOUS_FRAMES`].
    pub previous_frames: u32,
    /// The batch holds every covered pixel of the rows it spans (the promise a batch with
    /// derived views always makes), so that, kept as a previous render, the pixels of its
    /// bounding box it lacks are empty space; otherwise they are unknown, and whatever a
    /// later view reads there is rendered.
    pub rows_complete: bool,
    /// A render ahead of the session's next frames (issue 16, the scheduler's render-ahead
    /// while the farm is idle): render it in full, keep it as the session's previous render
    /// of this view of the asset (to serve its next `previous_frames` batches), and send no
    /// result, since no frame shows it. Needs `previous_frames >= 1` and no derived views.
    pub ahead: bool,
}

impl ReuseLimits {
    /// The most frames a full render may serve after its own.
    pub const MAX_PREVIOUS_FRAMES: u32 = 15;
    /// What the master asks by default: one frame in four rendered in full (the "frames of
    /// one user" rows of `nephele bench share`, BENCHMARKS.md: 38.6-41.9 % of the rays at
    /// 0.03-0.07 dB on the lego).
    pub const DEFAULT_PREVIOUS_FRAMES: u32 = 3;
}

impl Default for ReuseLimits {
    /// The defaults of `nephele_share::Settings` (BENCHMARKS.md, "Shared rays between adjacent
    /// views"): 6 degrees, contrast 0.2; no reuse of previous frames.
    fn default() -> ReuseLimits {
        ReuseLimits { max_angle_deg: 6.0, max_contrast: 0.2, previous_frames: 0, rows_complete: false, ahead: false }
    }
}

/// Work a kernel did for a batch (mirrors `nephele_kernels::kernel::KernelStats`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct KernelStats {
    pub rays: u64,
    pub rays_hit: u64,
    pub queries: u64,
    /// Samples an environment kernel traced but did not light: the objects' solid matter
    /// ([`RayBatch::occluders`]) hides them.
    pub hidden: u64,
}

/// The pixels of one batch, worker → composer. Arrays are parallel to `pixels`; each travels
/// as one packed little-endian block (20 bytes per pixel for the results + 4 for the index).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BatchResult {
    pub ids: BatchIds,
    pub worker_id: u64,
    /// Image size the pixel indices refer to.
    pub width: u32,
    pub height: u32,
    #[serde(with = "packed")]
    pub pixels: Vec<u32>,
    /// Linear RGB premultiplied by opacity.
    #[serde(with = "packed")]
    pub color: Vec<[f32; 3]>,
    /// In `[0, 1]`.
    #[serde(with = "packed")]
    pub opacity: Vec<f32>,
    /// View-space depth, `0` where the pixel saw nothing.
    #[serde(with = "packed")]
    pub depth: Vec<f32>,
    pub render_time_us: u64,
    pub stats: KernelStats,
    /// How the result travels (not a field on the wire: the frame's tag says it). A result
    /// decoded from a compact frame says `Compact`: its values are quantised and it holds
    /// only the pixels the object touched.
    #[serde(skip)]
    pub encoding: ResultEncoding,
}

/// The wire form of a [`BatchResult`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum ResultEncoding {
    /// Every pixel of the batch, 32-bit floats: 24 bytes per pixel (the reference).
    #[default]
    F32,
    /// Only the pixels with opacity > 0, half floats and 16-bit opacity: 10 bytes per sent
    /// pixel plus its index delta (see [`crate::compact`] for the error of each field).
    Compact,
}

/// A batch's result was sent to its composer (worker → master): the master's completion
/// time model (`t_u`) and resiliency bookkeeping run on these.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct BatchDone {
    pub ids: BatchIds,
    pub pixels: u32,
    pub render_time_us: u64,
    pub stats: KernelStats,
}

/// A batch could not be rendered (worker → master). The worker carries on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BatchFailed {
    pub ids: BatchIds,
    pub code: ErrorCode,
    pub message: String,
}

/// Which queued work to drop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum CancelTarget {
    Batch(u64),
    Frame { session_id: u64, frame_id: u64 },
    Session(u64),
}

/// Master → worker: drop matching batches that have not started; results of matching
/// batches that are rendering are discarded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Cancel {
    pub target: CancelTarget,
}

/// Orderly close. A worker shutting down lists the batches it did not start, so that the
/// master re-issues them at once instead of waiting for a deadline.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Goodbye {
    pub reason: String,
    pub returned_batches: Vec<u64>,
}

/// What went wrong, in [`BatchFailed`] and [`ErrorMessage`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ErrorCode {
    /// The frame could not be decoded.
    Malformed,
    FrameTooLarge,
    UnknownMessageType,
    VersionMismatch,
    /// A field is out of range (NaN camera, pixel outside the image, bad name, …).
    InvalidField,
    /// A message that makes no sense in this state (e.g. a batch before registration).
    Unexpected,
    UnknownAsset,
    AssetLoadFailed,
    RenderFailed,
    DeadlineExpired,
    Cancelled,
    ComposerUnreachable,
    /// The worker's queue is full: send the batch elsewhere.
    Overloaded,
    ShuttingDown,
    Internal,
    /// The peer did not prove the farm secret ([`crate::auth`]).
    Unauthenticated,
}

/// A protocol error, sent before closing (or, for a rejected message, instead of acting on
/// it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorMessage {
    pub code: ErrorCode,
    pub message: String,
}

/// A composer introduces itself to the master (after the handshake). The master answers
/// with [`Registered`] (its `worker_id` is the composer's id) and names `results_address`
/// in every [`RayBatch`] it sends, so that workers deliver their results there.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ComposerRegister {
    /// For logs and `GET /v1/farm`: `[A-Za-z0-9._-]`, 1 to 64 bytes.
    pub name: String,
    /// `host:port` where the composer accepts worker connections.
    pub results_address: String,
}

/// Master → composer: a client asks for a stream. The composer answers with
/// [`StreamOpened`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OpenStream {
    /// The scheduler's session id; every later message about the session carries it.
    pub session_id: u64,
    /// The public session id of the HTTP API (`[A-Za-z0-9._-]`, 1 to 64 bytes), for logs.
    pub session_name: String,
    /// The client's SDP offer (at most [`crate::validate::MAX_SDP_LEN`] bytes).
    pub offer_sdp: String,
    /// Views side by side in the video (1 screen, 2 headset, N quilt; 1 to 64).
    pub views: u32,
    /// Size of one view, pixels.
    pub width: u32,
    pub height: u32,
    pub target_fps: f32,
}

/// Composer → master: the answer to an [`OpenStream`]: the SDP answer, or why the offer was
/// refused (malformed SDP, no codec in common).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StreamOpened {
    pub session_id: u64,
    pub answer: Result<String, String>,
}

/// Composer → master: one pose a client sent over its data channel (already checked by the
/// composer: size, magic, rate), one camera per view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClientPose {
    pub session_id: u64,
    /// The client's sequence number (wraps).
    pub sequence: u32,
    /// The client's clock (`performance.now()`, ms), echoed back for pose-to-frame latency.
    pub client_time_ms: f64,
    /// 1 to [`crate::validate::MAX_VIEWS`] views.
    pub views: Vec<ViewProjection>,
}

/// One object in one view of a frame, and the task whose results fill it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PlanPart {
    pub view: u32,
    pub task_id: u64,
    pub object_id: u64,
}

/// Master → composer: a frame of a session is complete (every batch of every task it needs
/// has been rendered and delivered). The composer fuses the parts of each view by depth,
/// front to back; a part whose results are missing at `deadline_in_us` is filled from the
/// previous frame. A view with no part shows nothing (no object in view).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FramePlan {
    pub session_id: u64,
    pub frame_id: u64,
    /// The [`ClientPose::sequence`] and client time of the pose the frame was rendered for.
    pub pose_sequence: u32,
    pub client_time_ms: f64,
    /// Size of one view, pixels.
    pub width: u32,
    pub height: u32,
    /// Views in the frame (1 to [`crate::validate::MAX_VIEWS`]).
    pub views: u32,
    pub parts: Vec<PlanPart>,
    /// Microseconds from when the master sent the plan (time left, counted by the composer
    /// from receipt on its own monotonic clock, as [`RayBatch::deadline_in_us`]); `None` for
    /// no deadline.
    pub deadline_in_us: Option<u64>,
}

/// Master → composer: no frame needs this task's results any more.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReleaseTask {
    pub task_id: u64,
}

/// Either way: a session ended (master: its client closed it or the service dropped it;
/// composer: the peer connection failed or the client vanished).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CloseStream {
    pub session_id: u64,
    pub reason: String,
}

/// Every message. The frame's first payload byte is [`MessageKind::tag`].
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    Hello(Hello),
    Register(Register),
    Registered(Registered),
    LoadReport(LoadReport),
    RayBatch(RayBatch),
    BatchResult(BatchResult),
    BatchDone(BatchDone),
    BatchFailed(BatchFailed),
    Cancel(Cancel),
    Goodbye(Goodbye),
    Error(ErrorMessage),
    ComposerRegister(ComposerRegister),
    OpenStream(OpenStream),
    StreamOpened(StreamOpened),
    ClientPose(ClientPose),
    FramePlan(FramePlan),
    ReleaseTask(ReleaseTask),
    CloseStream(CloseStream),
    Challenge(Challenge),
    Proof(Proof),
}

/// The type of a message, as its one-byte tag on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MessageKind {
    Hello,
    Register,
    Registered,
    LoadReport,
    RayBatch,
    BatchResult,
    BatchDone,
    BatchFailed,
    Cancel,
    Goodbye,
    Error,
    ComposerRegister,
    OpenStream,
    StreamOpened,
    ClientPose,
    FramePlan,
    ReleaseTask,
    CloseStream,
    Challenge,
    Proof,
}

impl MessageKind {
    pub const ALL: [MessageKind; 20] = [
        MessageKind::Hello,
        MessageKind::Register,
        MessageKind::Registered,
        MessageKind::LoadReport,
        MessageKind::RayBatch,
        MessageKind::BatchResult,
        MessageKind::BatchDone,
        MessageKind::BatchFailed,
        MessageKind::Cancel,
        MessageKind::Goodbye,
        MessageKind::Error,
        MessageKind::ComposerRegister,
        MessageKind::OpenStream,
        MessageKind::StreamOpened,
        MessageKind::ClientPose,
        MessageKind::FramePlan,
        MessageKind::ReleaseTask,
        MessageKind::CloseStream,
        MessageKind::Challenge,
        MessageKind::Proof,
    ];

    /// Wire tag (0 is never used, so a zeroed buffer is not a message).
    pub fn tag(self) -> u8 {
        match self {
            MessageKind::Hello => 1,
            MessageKind::Register => 2,
            MessageKind::Registered => 3,
            MessageKind::LoadReport => 4,
            MessageKind::RayBatch => 5,
            MessageKind::BatchResult => 6,
            MessageKind::BatchDone => 7,
            MessageKind::BatchFailed => 8,
            MessageKind::Cancel => 9,
            MessageKind::Goodbye => 10,
            MessageKind::Error => 11,
            MessageKind::ComposerRegister => 12,
            MessageKind::OpenStream => 13,
            MessageKind::StreamOpened => 14,
            MessageKind::ClientPose => 15,
            MessageKind::FramePlan => 16,
            MessageKind::ReleaseTask => 17,
            MessageKind::CloseStream => 18,
            MessageKind::Challenge => 19,
            MessageKind::Proof => 20,
        }
    }

    pub fn from_tag(tag: u8) -> Option<MessageKind> {
        MessageKind::ALL.into_iter().find(|k| k.tag() == tag)
    }

    pub fn name(self) -> &'static str {
        match self {
            MessageKind::Hello => "Hello",
            MessageKind::Register => "Register",
            MessageKind::Registered => "Registered",
            MessageKind::LoadReport => "LoadReport",
            MessageKind::RayBatch => "RayBatch",
            MessageKind::BatchResult => "BatchResult",
            MessageKind::BatchDone => "BatchDone",
            MessageKind::BatchFailed => "BatchFailed",
            MessageKind::Cancel => "Cancel",
            MessageKind::Goodbye => "Goodbye",
            MessageKind::Error => "Error",
            MessageKind::ComposerRegister => "ComposerRegister",
            MessageKind::OpenStream => "OpenStream",
            MessageKind::StreamOpened => "StreamOpened",
            MessageKind::ClientPose => "ClientPose",
            MessageKind::FramePlan => "FramePlan",
            MessageKind::ReleaseTask => "ReleaseTask",
            MessageKind::CloseStream => "CloseStream",
            MessageKind::Challenge => "Challenge",
            MessageKind::Proof => "Proof",
        }
    }
}

impl fmt::Display for MessageKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl Message {
    pub fn kind(&self) -> MessageKind {
        match self {
            Message::Hello(_) => MessageKind::Hello,
            Message::Register(_) => MessageKind::Register,
            Message::Registered(_) => MessageKind::Registered,
            Message::LoadReport(_) => MessageKind::LoadReport,
            Message::RayBatch(_) => MessageKind::RayBatch,
            Message::BatchResult(_) => MessageKind::BatchResult,
            Message::BatchDone(_) => MessageKind::BatchDone,
            Message::BatchFailed(_) => MessageKind::BatchFailed,
            Message::Cancel(_) => MessageKind::Cancel,
            Message::Goodbye(_) => MessageKind::Goodbye,
            Message::Error(_) => MessageKind::Error,
            Message::ComposerRegister(_) => MessageKind::ComposerRegister,
            Message::OpenStream(_) => MessageKind::OpenStream,
            Message::StreamOpened(_) => MessageKind::StreamOpened,
            Message::ClientPose(_) => MessageKind::ClientPose,
            Message::FramePlan(_) => MessageKind::FramePlan,
            Message::ReleaseTask(_) => MessageKind::ReleaseTask,
            Message::CloseStream(_) => MessageKind::CloseStream,
            Message::Challenge(_) => MessageKind::Challenge,
            Message::Proof(_) => MessageKind::Proof,
        }
    }

    /// The batch a message is about, if any.
    pub fn batch_ids(&self) -> Option<BatchIds> {
        match self {
            Message::RayBatch(m) => Some(m.ids),
            Message::BatchResult(m) => Some(m.ids),
            Message::BatchDone(m) => Some(m.ids),
            Message::BatchFailed(m) => Some(m.ids),
            _ => None,
        }
    }
}

macro_rules! from_variant {
    ($($t:ident => $v:ident),* $(,)?) => {
        $(impl From<$t> for Message {
            fn from(m: $t) -> Message {
                Message::$v(m)
            }
        })*
    };
}

from_variant!(
    Hello => Hello,
    Register => Register,
    Registered => Registered,
    LoadReport => LoadReport,
    RayBatch => RayBatch,
    BatchResult => BatchResult,
    BatchDone => BatchDone,
    BatchFailed => BatchFailed,
    Cancel => Cancel,
    Goodbye => Goodbye,
    ErrorMessage => Error,
    ComposerRegister => ComposerRegister,
    OpenStream => OpenStream,
    StreamOpened => StreamOpened,
    ClientPose => ClientPose,
    FramePlan => FramePlan,
    ReleaseTask => ReleaseTask,
    CloseStream => CloseStream,
    Challenge => Challenge,
    Proof => Proof,
);
