//! Where a frame's time goes, from the pose the composer received to the encoded frame it
//! sent (issue 5's latency split), measured on the composer's clock.
//!
//! In a farm the composer sees every step of a frame: it forwards the viewer's pose to the
//! master, and receives the master's `FramePlan` for it once the farm has rendered it (the
//! master schedules the pose's ray tasks, the workers render them and send their results
//! here, and the master plans the frame when every task reports done: the `farm` stage);
//! then it waits for any results still on their way (`results_wait`), fuses them by depth
//! and hands the picture to the viewer's media thread (`fusion`), converts it to YUV 4:2:0,
//! encodes it and sends it. Inside the farm stage, `render` is the workers' own kernel time
//! on the frame's critical path: per worker, the sum of `render_time_us` of the frame's
//! batches it rendered; the largest of these. The rest of the farm stage is scheduling,
//! queueing and the loopback hops. (A part reused from an earlier frame's task, a still
//! camera, counts the time it took when it was rendered.)

use std::collections::{HashMap, VecDeque};
use std::time::Instant;

use serde::Serialize;

use crate::fusion::{FrameId, SessionId};

/// Frames kept for the percentiles.
pub const WINDOW: usize = 4096;
/// Poses remembered per session while their frames are planned.
const POSES_PER_SESSION: usize = 256;
/// Frames in flight remembered (plans whose frame has not been sent).
const FRAMES_IN_FLIGHT: usize = 4096;

/// The instants of one planned frame, up to its hand-off to the media thread.
#[derive(Debug, Clone, Copy)]
pub struct FrameTiming {
    pub pose_sequence: u32,
    pub client_time_ms: f64,
    pub pose_received: Option<Instant>,
    pub plan_received: Instant,
    pub results_complete: Instant,
    /// The frame's rendering critical path, milliseconds (see the module docs); `None`
    /// when no result of the frame arrived.
    pub render_ms: Option<f64>,
}

/// The stages of one sent frame, milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Stages {
    /// Pose received → frame sent (`None` when the pose was not seen, e.g. a plan for an
    /// older pose whose receipt fell out of the window).
    pub total: Option<f64>,
    /// Pose received → plan received: the master's scheduling, the workers' rendering, their
    /// done reports and the plan (four loopback hops).
    pub farm: Option<f64>,
    /// Part of `farm`: the workers' kernel time on the frame's critical path.
    pub render: Option<f64>,
    /// Plan received → every part's results in at the composer (or the grace over).
    pub results_wait: f64,
    /// Results in → picture at the media thread: depth fusion and the hand-off.
    pub fusion: f64,
    pub yuv: f64,
    pub encode: f64,
    pub send: f64,
}

impl Stages {
    /// Stages of a frame given its timing and the media thread's instants: picked up
    /// (`t0`), converted (`t1`), encoded (`t2`), sent (`t3`).
    pub fn of(timing: &FrameTiming, t0: Instant, t1: Instant, t2: Instant, t3: Instant) -> Stages {
        let ms = |a: Instant, b: Instant| b.saturating_duration_since(a).as_secs_f64() * 1e3;
        Stages {
            total: timing.pose_received.map(|p| ms(p, t3)),
            farm: timing.pose_received.map(|p| ms(p, timing.plan_received)),
            render: timing.render_ms,
            results_wait: ms(timing.plan_received, timing.results_complete),
            fusion: ms(timing.results_complete, t0),
            yuv: ms(t0, t1),
            encode: ms(t1, t2),
            send: ms(t2, t3),
        }
    }
}

/// Median, 99th percentile and count of a stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Percentiles {
    pub p50: Option<f64>,
    pub p99: Option<f64>,
    pub count: usize,
}

impl Percentiles {
    pub fn of(values: impl Iterator<Item = f64>) -> Percentiles {
        let mut v: Vec<f64> = values.filter(|x| x.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        let at = |q: f64| (!v.is_empty()).then(|| v[((v.len() - 1) as f64 * q).round() as usize]);
        Percentiles { p50: at(0.5), p99: at(0.99), count: v.len() }
    }
}

/// What `GET /v1/sessions` reports as `latency_ms`: each stage over the last [`WINDOW`]
/// frames of all sessions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct LatencyReport {
    pub pose_to_sent: Percentiles,
    pub farm: Percentiles,
    pub render: Percentiles,
    pub results_wait: Percentiles,
    pub fusion: Percentiles,
    pub yuv: Percentiles,
    pub encode: Percentiles,
    pub send: Percentiles,
}

/// Poses seen, frames in flight, and the stages of sent frames.
#[derive(Debug, Default)]
pub struct LatencyTracker {
    poses: HashMap<SessionId, VecDeque<(u32, Instant)>>,
    frames: HashMap<(SessionId, FrameId), FrameTiming>,
    sent: VecDeque<Stages>,
}

impl LatencyTracker {
    pub fn pose_received(&mut self, session: SessionId, sequence: u32, at: Instant) {
        let poses = self.poses.entry(session).or_default();
        if poses.len() == POSES_PER_SESSION {
            poses.pop_front();
        }
        poses.push_back((sequence, at));
    }

    /// When the pose `sequence` of `session` was received, if still remembered.
    pub fn pose_time(&self, session: SessionId, sequence: u32) -> Option<Instant> {
        self.poses.get(&session)?.iter().rev().find(|(s, _)| *s == sequence).map(|(_, t)| *t)
    }

    pub fn frame_planned(&mut self, session: SessionId, frame: FrameId, timing: FrameTiming) {
        if self.frames.len() >= FRAMES_IN_FLIGHT {
            // Frames never sent (superseded, dropped): forget the oldest half.
            let mut planned: Vec<Instant> = self.frames.values().map(|t| t.plan_received).collect();
            planned.sort();
            let cut = planned[planned.len() / 2];
            self.frames.retain(|_, t| t.plan_received > cut);
        }
        self.frames.insert((session, frame), timing);
    }

    /// The timing of a frame about to be sent, forgetting it.
    pub fn take_frame(&mut self, session: SessionId, frame: FrameId) -> Option<FrameTiming> {
        self.frames.remove(&(session, frame))
    }

    pub fn frame_sent(&mut self, stages: Stages) {
        if self.sent.len() == WINDOW {
            self.sent.pop_front();
        }
        self.sent.push_back(stages);
    }

    pub fn session_ended(&mut self, session: SessionId) {
        self.poses.remove(&session);
        self.frames.retain(|(s, _), _| *s != session);
    }

    pub fn report(&self) -> LatencyReport {
        let s = &self.sent;
        LatencyReport {
            pose_to_sent: Percentiles::of(s.iter().filter_map(|x| x.total)),
            farm: Percentiles::of(s.iter().filter_map(|x| x.farm)),
            render: Percentiles::of(s.iter().filter_map(|x| x.render)),
            results_wait: Percentiles::of(s.iter().map(|x| x.results_wait)),
            fusion: Percentiles::of(s.iter().map(|x| x.fusion)),
            yuv: Percentiles::of(s.iter().map(|x| x.yuv)),
            encode: Percentiles::of(s.iter().map(|x| x.encode)),
            send: Percentiles::of(s.iter().map(|x| x.send)),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[test]
    fn stages_split_the_frame_time_and_percentiles_rank() {
        let base = Instant::now();
        let at = |ms: u64| base + Duration::from_millis(ms);
        let mut tracker = LatencyTracker::default();
        tracker.pose_received(1, 7, at(0));
        assert_eq!(tracker.pose_time(1, 7), Some(at(0)));
        assert_eq!(tracker.pose_time(1, 8), None);
        let timing = FrameTiming {
            pose_sequence: 7,
            client_time_ms: 140.0,
            pose_received: tracker.pose_time(1, 7),
            plan_received: at(2),
            results_complete: at(30),
            render_ms: Some(1.5),
        };
        tracker.frame_planned(1, 3, timing);
        let timing = tracker.take_frame(1, 3).expect("planned");
        assert!(tracker.take_frame(1, 3).is_none());
        let stages = Stages::of(&timing, at(31), at(33), at(40), at(41));
        assert_eq!(
            stages,
            Stages {
                total: Some(41.0),
                farm: Some(2.0),
                render: Some(1.5),
                results_wait: 28.0,
                fusion: 1.0,
                yuv: 2.0,
                encode: 7.0,
                send: 1.0
            }
        );
        for _ in 0..98 {
            tracker.frame_sent(stages);
        }
        for _ in 0..2 {
            tracker.frame_sent(Stages { total: None, results_wait: 100.0, ..stages });
        }
        let r = tracker.report();
        assert_eq!((r.pose_to_sent.count, r.results_wait.count), (98, 100));
        assert_eq!((r.results_wait.p50, r.results_wait.p99), (Some(28.0), Some(100.0)));
        assert_eq!((r.encode.p50, r.render.p50), (Some(7.0), Some(1.5)));
        tracker.session_ended(1);
        assert_eq!(tracker.pose_time(1, 7), None);
    }

    #[test]
    fn memory_stays_bounded() {
        let mut tracker = LatencyTracker::default();
        let now = Instant::now();
        for i in 0..10_000u32 {
            tracker.pose_received(1, i, now);
            let timing = FrameTiming {
                pose_sequence: i,
                client_time_ms: 0.0,
                pose_received: None,
                plan_received: now + Duration::from_micros(u64::from(i)),
                results_complete: now,
                render_ms: None,
            };
            tracker.frame_planned(1, u64::from(i), timing);
            tracker.frame_sent(Stages::default());
        }
        assert!(tracker.poses[&1].len() <= POSES_PER_SESSION);
        assert!(tracker.frames.len() <= FRAMES_IN_FLIGHT);
        assert!(tracker.sent.len() <= WINDOW);
        assert!(tracker.take_frame(1, 9_999).is_some(), "the newest frames are kept");
    }
}
