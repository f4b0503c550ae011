//! Pose and control messages on the viewer's RTCDataChannel.
//!
//! The binary pose message and its decoder live in `nephele_proto::pose`; here is what a
//! viewer's poses go through after decoding: a pose older than the last accepted one is
//! dropped and counted, and so is a pose that arrives while the sender is far above the
//! nominal rate of one pose per 20 ms (NEPHELE section 5.2): a token bucket lets bursts of
//! [`PoseGate::BURST`] through and refills one pose per [`PoseGate::MIN_INTERVAL`].
//!
//! # Control (text message): JSON
//!
//! `{"type":"keyframe"}` asks for an IDR; `{"type":"ping","t":<ms>}` is answered on the same
//! channel with `{"type":"pong","t":<ms>}` for round-trip measurements.

use std::time::{Duration, Instant};

pub use nephele_proto::pose::{Pose, PoseError, look_at_pose};
use serde::{Deserialize, Serialize};

/// Control messages (text frames, JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum Control {
    /// Ask for a keyframe (e.g. after a decoder error).
    Keyframe,
    /// Round-trip probe; answered with `Pong` carrying the same `t`.
    Ping {
        t: f64,
    },
    Pong {
        t: f64,
    },
}

/// Per-viewer pose counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct PoseCounters {
    pub received: u64,
    pub accepted: u64,
    pub malformed: u64,
    pub rate_limited: u64,
    pub stale: u64,
}

/// Why a pose was dropped.
#[derive(Debug, Clone, PartialEq)]
pub enum PoseDrop {
    Malformed(PoseError),
    RateLimited,
    /// Older than (or the same as) the last accepted sequence number.
    Stale {
        seq: u32,
        last: u32,
    },
}

/// Token bucket against pose floods, time passed in.
#[derive(Debug, Clone, Copy)]
pub struct PoseGate {
    tokens: f64,
    last: Option<Instant>,
}

impl Default for PoseGate {
    fn default() -> Self {
        PoseGate { tokens: Self::BURST, last: None }
    }
}

impl PoseGate {
    /// Poses let through back to back (a client catching up after a hiccup).
    pub const BURST: f64 = 5.0;
    /// Sustained rate: one pose per 10 ms, twice the nominal rate of one per 20 ms.
    pub const MIN_INTERVAL: Duration = Duration::from_millis(10);

    pub fn admit(&mut self, now: Instant) -> bool {
        if let Some(last) = self.last {
            let elapsed = now.saturating_duration_since(last).as_secs_f64();
            self.tokens = (self.tokens + elapsed / Self::MIN_INTERVAL.as_secs_f64()).min(Self::BURST);
        }
        self.last = Some(now);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

/// Everything a viewer's pose messages go through: decoding, validation, ordering, rate.
#[derive(Debug, Default, Clone)]
pub struct PoseInbox {
    gate: PoseGate,
    last_seq: Option<u32>,
    counters: PoseCounters,
}

impl PoseInbox {
    pub fn counters(&self) -> PoseCounters {
        self.counters
    }

    /// Takes one binary message received at `now`.
    pub fn offer(&mut self, bytes: &[u8], now: Instant) -> Result<Pose, PoseDrop> {
        self.counters.received += 1;
        // The rate limit applies before decoding: a flood costs no parsing.
        if !self.gate.admit(now) {
            self.counters.rate_limited += 1;
            return Err(PoseDrop::RateLimited);
        }
        let pose = match Pose::decode(bytes) {
            Ok(p) => p,
            Err(e) => {
                self.counters.malformed += 1;
                return Err(PoseDrop::Malformed(e));
            }
        };
        if let Some(last) = self.last_seq
            && pose.seq <= last
        {
            self.counters.stale += 1;
            return Err(PoseDrop::Stale { seq: pose.seq, last });
        }
        self.last_seq = Some(pose.seq);
        self.counters.accepted += 1;
        Ok(pose)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn pose(seq: u32) -> Pose {
        look_at_pose(seq, 640, 480, 0.8, Vec3::new(3.0, -4.0, 2.0), Vec3::ZERO).unwrap()
    }

    #[test]
    fn floods_stale_and_malformed_poses_are_dropped_and_counted() {
        let t0 = Instant::now();
        let mut inbox = PoseInbox::default();
        // At the nominal 20 ms every pose passes.
        for i in 0..50u32 {
            assert!(inbox.offer(&pose(i + 1).encode(), t0 + Duration::from_millis(20 * u64::from(i))).is_ok());
        }
        // 200 poses within 20 ms (0.1 ms apart): only the burst allowance passes.
        let t1 = t0 + Duration::from_secs(2);
        let mut passed = 0;
        for i in 0..200u32 {
            if inbox.offer(&pose(100 + i).encode(), t1 + Duration::from_micros(100 * u64::from(i))).is_ok() {
                passed += 1;
            }
        }
        assert!((5..=7).contains(&passed), "{passed} passed");
        // After a quiet moment, a stale and a malformed pose.
        let t2 = t1 + Duration::from_secs(1);
        assert!(matches!(inbox.offer(&pose(3).encode(), t2), Err(PoseDrop::Stale { seq: 3, .. })));
        assert!(matches!(inbox.offer(b"{\"hello\":1}", t2 + Duration::from_millis(20)), Err(PoseDrop::Malformed(_))));
        let c = inbox.counters();
        assert_eq!(c.received, 252);
        assert_eq!(c.accepted, 50 + passed);
        assert_eq!(c.rate_limited, 200 - passed);
        assert_eq!((c.stale, c.malformed), (1, 1));
    }

    #[test]
    fn control_messages_are_tagged_json() {
        assert_eq!(serde_json::from_str::<Control>(r#"{"type":"keyframe"}"#).unwrap(), Control::Keyframe);
        assert_eq!(serde_json::from_str::<Control>(r#"{"type":"ping","t":12.5}"#).unwrap(), Control::Ping { t: 12.5 });
        assert_eq!(serde_json::to_string(&Control::Pong { t: 1.0 }).unwrap(), r#"{"type":"pong","t":1.0}"#);
        assert!(serde_json::from_str::<Control>(r#"{"type":"reboot"}"#).is_err());
    }
}
