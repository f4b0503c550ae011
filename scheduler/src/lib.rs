//! The master's scheduler core: NEPHELE Algorithm 1 as a pure, deterministic state machine.
//!
//! `nephele-scheduler` depends on `nephele-geometry` only (cameras, bounds): no image, mesh,
//! network or thread-pool crate, as `cargo tree -p nephele-scheduler` shows.
//!
//! Nothing in this crate does I/O, reads a clock, spawns a thread or draws a random number:
//! time is an explicit [`Time`] passed with every event, so the same code runs inside the live
//! master (which feeds it wall-clock time) and inside the discrete-event simulator
//! (`nephele-sim`, which feeds it simulated time).
//!
//! # Driving it
//!
//! Events go in through methods of [`Scheduler`] ([`Scheduler::add_worker`],
//! [`Scheduler::open_session`], [`Scheduler::pose`], [`Scheduler::batch_done`], ...). Decisions
//! come out of [`Scheduler::tick`] as a list of [`Action`]s: dispatch this ray batch to that
//! worker, cancel that one, this frame is complete, that worker is lost, the composer may
//! forget these results. [`Scheduler::next_wakeup`] says when the next time-driven decision is
//! due (a frame release, a batch deadline, a heartbeat timeout), so a live loop knows how long
//! it may sleep and a simulator knows when to schedule its next tick.
//! [`Scheduler::snapshot`] returns the serde-serialisable state behind `GET /v1/farm`.
//!
//! ```
//! use std::time::Duration;
//! use glam::Vec3;
//! use nephele_geometry::{Bounds, Camera};
//! use nephele_scheduler::*;
//!
//! let mut s = Scheduler::new(SchedulerConfig::default())?;
//! let bounds = Bounds { min: Vec3::splat(-0.5), max: Vec3::splat(0.5) };
//! s.register_object(ObjectId(1), ObjectInfo { bounds, occupancy: None, cost_per_ray: 1.0, full_frame: false })?;
//! let t0 = Time::ZERO;
//! s.add_worker(WorkerId(1), 1e8, t0)?; // registration: measured rays/s
//! let user = match s.admission(t0) {
//!     Admission::Admit => s.open_session(SessionSpec { target_fps: 60.0, objects: vec![ObjectId(1)] }, t0)?,
//!     Admission::Refuse { retry_after } => panic!("HTTP 503, Retry-After: {}", retry_after.as_secs()),
//! };
//! let eye = Camera::look_at(640, 480, 0.8, Vec3::new(0.0, -3.0, 0.5), Vec3::ZERO, Vec3::Z)?;
//! s.pose(user, &[eye], t0)?; // every 20 ms from the client
//! let mut now = t0;
//! let mut shown = 0;
//! while shown == 0 {
//!     for action in s.tick(now) {
//!         match action {
//!             // Send the batch to the worker; here it answers 1 ms later.
//!             Action::Dispatch { worker, batch } => s.batch_done(worker, batch.id, now + Duration::from_millis(1))?,
//!             Action::FrameComplete { session, latency, .. } => {
//!                 assert_eq!(session, user);
//!                 assert!(latency <= Duration::from_millis(2));
//!                 shown += 1;
//!             }
//!             _ => {}
//!         }
//!     }
//!     now = now + Duration::from_millis(1);
//! }
//! let farm = s.snapshot(now); // GET /v1/farm
//! assert_eq!(farm.sessions[0].frames_completed, 1);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! # Modules
//!
//! * [`assign`]: the TaskAssigner: occupancy-proxy projection (`nhit`: covered pixels, mean
//!   depth), ray batches as pixel rectangles, Heavy/Light classification, camera quantisation
//!   for shared rays.
//! * [`engine`]: Algorithm 1 itself, the HeavyFarm/LightFarm placement, shared tasks, the
//!   history table, resiliency, and the baseline policies behind the same interface.
//! * [`config`]: every tunable, with the reasoning for its default.

pub mod assign;
pub mod config;
pub mod engine;
mod history;
pub mod snapshot;

pub use assign::{CameraKey, Coverage, OccupancyGrid, PixelRect, PixelSet, TaskClass};
pub use config::{DerivedViews, Policy, RenderAhead, SchedulerConfig, ShareTolerance};
pub use engine::{
    Action, Admission, BatchSpec, DerivedSpec, DropReason, FramePart, ObjectInfo, PartSource, Scheduler, SessionSpec,
};
pub use snapshot::{FarmSnapshot, Stats};

use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::fmt;
use std::hash::{BuildHasherDefault, Hasher};
use std::ops::{Add, Sub};
use std::time::Duration;

/// FxHash (rustc's hasher): fast and deterministic, for maps keyed by ids the scheduler assigns
/// itself. Not collision-resistant, so maps keyed by anything a client controls (quantised
/// cameras) keep the standard SipHash.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct IdHasher(u64);

impl IdHasher {
    fn add(&mut self, word: u64) {
        self.0 = (self.0.rotate_left(5) ^ word).wrapping_mul(0x517c_c1b7_2722_0a95);
    }
}

impl Hasher for IdHasher {
    fn write(&mut self, bytes: &[u8]) {
        for chunk in bytes.chunks(8) {
            let mut word = [0u8; 8];
            word[..chunk.len()].copy_from_slice(chunk);
            self.add(u64::from_le_bytes(word));
        }
    }

    fn write_u32(&mut self, v: u32) {
        self.add(u64::from(v));
    }

    fn write_u64(&mut self, v: u64) {
        self.add(v);
    }

    fn finish(&self) -> u64 {
        self.0
    }
}

pub(crate) type IdMap<K, V> = HashMap<K, V, BuildHasherDefault<IdHasher>>;

/// A point in time, in whole microseconds since an origin the caller chooses (the live master:
/// its start; the simulator: the start of the run). Integer so that event ordering is exact
/// and the state machine is bit-for-bit deterministic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default, Serialize, Deserialize)]
pub struct Time(u64);

impl Time {
    pub const ZERO: Time = Time(0);
    pub const MAX: Time = Time(u64::MAX);

    pub const fn from_micros(micros: u64) -> Time {
        Time(micros)
    }

    /// Seconds to a time, rounded to the microsecond; negative or non-finite input gives zero.
    pub fn from_secs_f64(seconds: f64) -> Time {
        if seconds.is_finite() && seconds > 0.0 {
            Time((seconds * 1e6).round().min(u64::MAX as f64) as u64)
        } else {
            Time::ZERO
        }
    }

    pub const fn as_micros(self) -> u64 {
        self.0
    }

    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-6
    }

    /// `self - earlier`, or zero if `earlier` is later.
    pub fn since(self, earlier: Time) -> Duration {
        Duration::from_micros(self.0.saturating_sub(earlier.0))
    }
}

impl Add<Duration> for Time {
    type Output = Time;
    fn add(self, d: Duration) -> Time {
        Time(self.0.saturating_add(u64::try_from(d.as_micros()).unwrap_or(u64::MAX)))
    }
}

impl Sub<Duration> for Time {
    type Output = Time;
    fn sub(self, d: Duration) -> Time {
        Time(self.0.saturating_sub(u64::try_from(d.as_micros()).unwrap_or(u64::MAX)))
    }
}

impl fmt::Display for Time {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:.6}s", self.as_secs_f64())
    }
}

macro_rules! id_type {
    ($(#[$doc:meta])* $name:ident($inner:ty), $prefix:literal) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
        #[serde(transparent)]
        pub struct $name(pub $inner);

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, concat!($prefix, "{}"), self.0)
            }
        }
    };
}

id_type!(
    /// A render worker, numbered by the caller (the master assigns it at registration).
    WorkerId(u32), "w"
);
id_type!(
    /// A user session, numbered by the scheduler ([`Scheduler::open_session`]).
    SessionId(u64), "s"
);
id_type!(
    /// An object instance placed in the world (an asset at a pose), registered with
    /// [`Scheduler::register_object`]. Sessions that name the same id see the same object, so
    /// their rays on it can be shared.
    ObjectId(u32), "o"
);
id_type!(
    /// A task: one object seen from one (quantised) camera; its results may feed several frames.
    TaskId(u64), "t"
);
id_type!(
    /// A ray batch: a set of pixels of one task, the unit of dispatch and of re-issue.
    BatchId(u64), "b"
);
id_type!(
    /// A frame of one session, numbered from 0 per session.
    FrameId(u64), "f"
);

/// Why an event was rejected. Every variant is the caller's input being wrong or refused; the
/// scheduler's own state stays consistent whatever it is fed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SchedError {
    #[error("unknown session {0}")]
    UnknownSession(SessionId),
    #[error("unknown worker {0}")]
    UnknownWorker(WorkerId),
    #[error("unknown object {0}")]
    UnknownObject(ObjectId),
    #[error("unknown batch {0} (never issued, or its task already finished)")]
    UnknownBatch(BatchId),
    #[error("batch {batch} is not assigned to worker {worker}")]
    NotAssigned { batch: BatchId, worker: WorkerId },
    #[error("worker {0} is already registered")]
    DuplicateWorker(WorkerId),
    #[error("object {0} is already registered with different geometry")]
    DuplicateObject(ObjectId),
    #[error("target FPS {0} is not a finite number in (0, {max}]", max = config::MAX_FPS)]
    InvalidFps(f64),
    #[error("worker throughput {0} rays/s is not a finite positive number")]
    InvalidThroughput(f64),
    #[error("invalid object {id}: {reason}")]
    InvalidObject { id: ObjectId, reason: String },
    #[error("a session needs at least one object")]
    NoObjects,
    #[error("invalid pose: {0}")]
    InvalidPose(String),
    #[error("invalid scheduler configuration: {0}")]
    InvalidConfig(String),
    #[error("admission refused while a user is starved; retry after {} s", retry_after.as_secs())]
    Refused { retry_after: Duration },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_arithmetic_saturates_and_rounds() {
        let t = Time::from_secs_f64(1.5);
        assert_eq!(t.as_micros(), 1_500_000);
        assert_eq!(Time::from_secs_f64(f64::NAN), Time::ZERO);
        assert_eq!(Time::from_secs_f64(-3.0), Time::ZERO);
        assert_eq!(t + Duration::from_millis(2), Time::from_micros(1_502_000));
        assert_eq!(Time::ZERO - Duration::from_secs(1), Time::ZERO);
        assert_eq!(Time::MAX + Duration::from_secs(1), Time::MAX);
        assert_eq!(t.since(Time::from_secs_f64(2.0)), Duration::ZERO);
        assert_eq!(Time::from_secs_f64(2.0).since(t), Duration::from_millis(500));
        assert_eq!(WorkerId(3).to_string(), "w3");
    }
}
