//! The media path: fused frames go to their sessions' media threads, which convert to YUV,
//! encode H.264 and send on the video track. A frame that arrives while the previous one is
//! still being encoded is dropped (counted): the stream never queues up latency.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex as StdMutex, mpsc as std_mpsc};
use std::time::{Duration, Instant};

use nephele_shutdown::Shutdown;

use crate::congestion::{Feedback, RateController};
use crate::encode::{EncoderSettings, EncoderStats, H264Encoder};
use crate::fusion::FusedFrame;
use crate::scale;
use crate::state::{MediaCounters, Shared, lock};
use crate::webrtc::Viewer;
use crate::yuv::Yuv420;

/// Lowest bitrate the receiver's feedback may bring a stream to.
const MIN_BITRATE_BPS: f64 = 150_000.0;

/// What a session's media thread shares with the rest of the session.
pub(crate) struct MediaHandles {
    /// Set to ask for an IDR.
    pub(crate) keyframe: Arc<AtomicBool>,
    pub(crate) media: Arc<StdMutex<(MediaCounters, EncoderStats)>>,
    /// The stream's resolution level, written here, read by the pose path.
    pub(crate) scale_level: Arc<AtomicU32>,
}

/// One running media thread in the composer's gauge, for as long as it lives.
struct Running(nephele_telemetry::prometheus_client::metrics::gauge::Gauge);

impl Running {
    fn new(gauge: &nephele_telemetry::prometheus_client::metrics::gauge::Gauge) -> Running {
        gauge.inc();
        Running(gauge.clone())
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.0.dec();
    }
}

/// The session's media path on its own thread: YUV conversion and encoding are CPU work
/// that must not stall the async runtime.
pub(crate) fn spawn_media_thread(
    shared: &Arc<Shared>,
    viewer: Arc<Viewer>,
    frames: std_mpsc::Receiver<FusedFrame>,
    handles: MediaHandles,
) -> Option<std::thread::JoinHandle<()>> {
    let MediaHandles { keyframe, media, scale_level } = handles;
    let runtime = shared.runtime.clone();
    let shared = Arc::clone(shared);
    let fps = shared.config.fps;
    let bitrate = shared.config.bitrate_bps;
    let session = viewer.session();
    // Counted out however the thread ends, or with the closure if it never starts.
    let running = Running::new(&shared.metrics.media_threads);
    let spawned = std::thread::Builder::new().name(format!("media-{session}")).spawn(move || {
        let _running = running;
        let frame_time = Duration::from_secs_f32(1.0 / fps);
        let mut previous_send: Option<Instant> = None;
        let mut encoder: Option<H264Encoder> = None;
        let mut yuv: Option<Yuv420> = None;
        let started = Instant::now();
        // The bitrate follows the receiver's feedback between a floor and the configured (or
        // picture-size) rate; a new target re-creates the encoder (OpenH264 takes its rate at
        // creation; the new one starts with an IDR), so only a change of a fifth or more,
        // at most every two seconds. Below a rate too low for the picture the picture gets
        // smaller (`crate::scale`): also a new encoder. The level goes to the session's pose
        // path (`scale_level`), which asks the farm for pictures that small; frames rendered
        // before that arrive larger and are brought to the level here. The controller
        // belongs to the full picture's size: a frame of a size that is no level of it
        // (another session shape) starts a new one.
        let mut rate: Option<(RateController, (u32, u32))> = None;
        let mut last_rebuild = Instant::now();
        let mut frame_index = 0u64;
        let mut scaled: Vec<[f32; 3]> = Vec::new();
        while let Ok(frame) = frames.recv() {
            // Below the floor bitrate the frame rate falls: one frame in `divisor`.
            frame_index += 1;
            let divisor = rate.as_ref().map_or(1, |(c, _)| c.frame_divisor());
            if divisor > 1 && !frame_index.is_multiple_of(u64::from(divisor)) {
                lock(&media).0.frames_skipped_for_rate += 1;
                shared.metrics.frames_skipped_for_rate.inc();
                continue;
            }
            let frame_size = (frame.layout.width(), frame.layout.height());
            let level_of_frame =
                rate.as_ref().and_then(|(_, (w, h))| nephele_proto::pose::scale_level_of(*w, *h, frame_size));
            let frame_level = match level_of_frame {
                Some(level) => level,
                None => {
                    let (w, h) = frame_size;
                    let mut settings = EncoderSettings::low_latency(w, h);
                    if let Some(b) = bitrate {
                        settings.bitrate_bps = b;
                    }
                    let ceiling = f64::from(settings.bitrate_bps);
                    let controller = RateController::new(ceiling, (ceiling / 8.0).max(MIN_BITRATE_BPS), ceiling)
                        .with_resolution_levels(
                            u64::from(w) * u64::from(h),
                            f64::from(fps),
                            scale::deepest_level(&frame.layout),
                        );
                    rate = Some((controller, frame_size));
                    scale_level.store(0, Ordering::Relaxed);
                    encoder = None;
                    0
                }
            };
            let Some((controller, (full_w, full_h))) = rate.as_mut() else { continue };
            let (full_w, full_h) = (*full_w, *full_h);
            let mut settings = EncoderSettings::low_latency(full_w, full_h);
            settings.fps = fps;
            let now = started.elapsed().as_secs_f64();
            let feedback = viewer.take_feedback();
            let mut retarget = None;
            if let Some(enc) = encoder.as_ref() {
                let divisor = controller.frame_divisor();
                for (report, at) in feedback {
                    let at = at.saturating_duration_since(started).as_secs_f64();
                    if let Feedback::Estimate(bps) = report {
                        let mut counters = lock(&media);
                        counters.0.receiver_estimates += 1;
                        counters.0.receiver_estimate_bps = bps.max(0.0) as u64;
                    }
                    controller.on_feedback(report, at);
                    tracing::debug!(
                        session,
                        ?report,
                        at,
                        target = controller.target_bps(at) as u64,
                        "receiver feedback"
                    );
                }
                lock(&media).0.receiver_estimates_ignored = controller.ignored_estimates();
                if controller.frame_divisor() != divisor {
                    tracing::info!(
                        session,
                        from = divisor,
                        to = controller.frame_divisor(),
                        "the stream sends one frame in this many (below its floor bitrate)"
                    );
                }
                if let Some(from) = controller.update_resolution(now) {
                    let to = controller.resolution_level();
                    tracing::info!(
                        session,
                        from = %format!("{}x{}", full_w >> from, full_h >> from),
                        to = %format!("{}x{}", full_w >> to, full_h >> to),
                        bitrate = controller.target_bps(now) as u64,
                        "the stream's resolution follows its bitrate"
                    );
                    lock(&media).0.resolution_changes += 1;
                    shared.metrics.resolution_changes.inc();
                    scale_level.store(to, Ordering::Relaxed);
                }
                let target = controller.target_bps(now);
                let current = f64::from(enc.settings().bitrate_bps);
                if (target - current).abs() >= 0.2 * current && last_rebuild.elapsed() >= Duration::from_secs(2) {
                    retarget = Some((current as u32, target as u32));
                }
            }
            let level = controller.resolution_level();
            let (w, h) = (full_w >> level, full_h >> level);
            let t0 = Instant::now();
            let rgb: &[[f32; 3]] = if level == frame_level {
                &frame.rgb
            } else {
                scale::relevel_into(frame_size.0, frame_size.1, &frame.rgb, frame_level, level, &mut scaled);
                &scaled
            };
            let picture = match yuv.take() {
                Some(mut p) if p.width() == w && p.height() == h => p.fill_from_linear_rgb(rgb).map(|_| p),
                _ => Yuv420::from_linear_rgb(w, h, rgb),
            };
            let picture = match picture {
                Ok(p) => p,
                Err(e) => {
                    tracing::warn!(session, "colour conversion: {e}");
                    lock(&media).0.encode_errors += 1;
                    shared.metrics.encode_errors.inc();
                    continue;
                }
            };
            let t1 = Instant::now();
            let resized = encoder.as_ref().is_none_or(|e| e.settings().width != w || e.settings().height != h);
            (settings.width, settings.height) = (w, h);
            // A new encoder (first, or at a new resolution) starts at the controller's rate.
            settings.bitrate_bps = controller.target_bps(now) as u32;
            if resized || retarget.is_some() {
                if let Some((current, target)) = retarget {
                    tracing::info!(
                        session,
                        from = current,
                        to = target,
                        "the stream's bitrate follows the receiver's feedback"
                    );
                    settings.bitrate_bps = target;
                    shared.metrics.bitrate_changes.inc();
                    lock(&media).0.bitrate_changes += 1;
                }
                last_rebuild = Instant::now();
                let target = settings.bitrate_bps;
                match H264Encoder::new(settings) {
                    Ok(e) => {
                        encoder = Some(e);
                        viewer.set_pacing_target(target);
                        lock(&media).0.bitrate_bps = u64::from(target);
                    }
                    Err(e) => {
                        tracing::warn!(session, "encoder for {w}x{h}: {e}");
                        lock(&media).0.encode_errors += 1;
                        shared.metrics.encode_errors.inc();
                        yuv = Some(picture);
                        continue;
                    }
                }
            }
            let Some(enc) = encoder.as_mut() else { continue };
            if keyframe.swap(false, Ordering::SeqCst) {
                enc.request_keyframe();
                lock(&media).0.keyframes_requested += 1;
            }
            let encoded = enc.encode(&picture, started.elapsed().as_millis() as u64);
            let t2 = Instant::now();
            yuv = Some(picture);
            let encoded = match encoded {
                Ok(f) => f,
                Err(e) => {
                    tracing::warn!(session, "encoding: {e}");
                    lock(&media).0.encode_errors += 1;
                    shared.metrics.encode_errors.inc();
                    continue;
                }
            };
            let now = Instant::now();
            let step = timestamp_step(previous_send, now, frame_time);
            previous_send = Some(now);
            let sent = runtime.block_on(viewer.send_frame(&encoded, step));
            let t3 = Instant::now();
            let timing = {
                let mut latency = lock(&shared.latency);
                let timing = latency.take_frame(session, frame.frame).filter(|_| sent.is_ok());
                if let Some(t) = &timing {
                    let stages = crate::latency::Stages::of(t, t0, t1, t2, t3);
                    shared.metrics.frame_sent(&stages);
                    latency.frame_sent(stages);
                }
                timing
            };
            if let Some(timing) = timing {
                // Tells the viewer which of its poses this frame shows (the client's and
                // `nephele loadgen`'s pose-to-frame latency).
                let note =
                    serde_json::json!({ "type": "frame", "t": timing.client_time_ms, "seq": timing.pose_sequence });
                let _ = runtime.block_on(viewer.send_text(note.to_string()));
            }
            let mut m = lock(&media);
            m.1 = enc.stats();
            let c = &mut m.0;
            c.resolution_level = level;
            if level > 0 {
                c.frames_downscaled += 1;
                shared.metrics.frames_downscaled.inc();
            }
            c.last_yuv_ms = (t1 - t0).as_secs_f64() * 1e3;
            c.last_encode_ms = (t2 - t1).as_secs_f64() * 1e3;
            c.last_send_ms = (t3 - t2).as_secs_f64() * 1e3;
            match sent {
                Ok(()) => {
                    c.frames_sent += 1;
                    c.bytes_sent += encoded.data.len() as u64;
                    shared.metrics.frames_sent.inc();
                    shared.metrics.bytes_sent.inc_by(encoded.data.len() as u64);
                }
                Err(e) => {
                    c.send_errors += 1;
                    shared.metrics.send_errors.inc();
                    tracing::debug!(session, "sending a frame: {e}");
                }
            }
        }
        tracing::debug!(session, "media thread ends");
    });
    match spawned {
        Ok(thread) => Some(thread),
        Err(e) => {
            tracing::error!(session, "cannot start the media thread: {e}");
            None
        }
    }
}

/// Hands fused frames to their sessions' media threads, never blocking.
pub(crate) fn dispatch(shared: &Shared, frames: Vec<FusedFrame>) {
    if frames.is_empty() {
        return;
    }
    let sessions = lock(&shared.sessions);
    for frame in frames {
        let Some(entry) = sessions.get(&frame.session) else { continue };
        let mut m = lock(&entry.media);
        m.0.frames_in += 1;
        match entry.frames.try_send(frame) {
            Ok(()) => {}
            Err(std_mpsc::TrySendError::Full(_)) => {
                m.0.frames_dropped_busy += 1;
                shared.metrics.frames_dropped_busy.inc();
            }
            Err(std_mpsc::TrySendError::Disconnected(_)) => {}
        }
    }
}

pub(crate) async fn fusion_loop(shared: Arc<Shared>, stop: Shutdown) {
    loop {
        let next = lock(&shared.compositor).next_deadline();
        let sleep = async {
            match next {
                Some(deadline) => tokio::time::sleep_until(tokio::time::Instant::from_std(deadline)).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = shared.wake.notified() => {}
            _ = sleep => {}
            _ = stop.wait() => return,
        }
        let frames = lock(&shared.compositor).poll(Instant::now());
        dispatch(&shared, frames);
    }
}

/// The step from a frame's RTP timestamp to the next frame's (webrtc-rs stamps each frame
/// with the previous frame's timestamp plus the previous frame's duration).
///
/// The timestamps follow the clock rather than the nominal frame rate: the receiver's jitter
/// buffer maps them onto its own clock, and a browser's delay-based estimate (REMB) reads the
/// growth of arrival time against them. A stream that sends fewer frames than its nominal
/// rate (one frame in 8 below its floor bitrate, or a farm that renders 25 frames a second
/// of 30) with timestamps `1 / fps` apart looks to the receiver like a queue that grows
/// without end: Chromium's estimate then sits at its 5 kbit/s minimum for good
/// (`tests/tests/lossy_link.rs`, the Chromium test). The next frame's time is not known when
/// this one leaves, so the step is the interval just ended: timestamps one frame behind the
/// clock, without drift. Clamped to [1 ms, 10 s] (a stalled session does not jump far).
fn timestamp_step(previous_send: Option<Instant>, now: Instant, nominal: Duration) -> Duration {
    previous_send.map_or(nominal, |previous| {
        now.saturating_duration_since(previous).clamp(Duration::from_millis(1), Duration::from_secs(10))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rtp_timestamps_follow_the_clock_one_frame_behind() {
        let nominal = Duration::from_millis(33);
        let t0 = Instant::now();
        let ms = |m: u64| Duration::from_millis(m);
        assert_eq!(timestamp_step(None, t0, nominal), nominal, "the first frame's step is nominal");
        // Frames sent 125 ms apart (one in 4 of 30 fps, say): the steps follow, not 33 ms.
        let sends: Vec<Instant> = (0..6).map(|i| t0 + ms(125 * i)).collect();
        let mut timestamp = Duration::ZERO;
        let mut previous = None;
        let mut stamps = Vec::new();
        for &now in &sends {
            stamps.push(timestamp);
            timestamp += timestamp_step(previous, now, nominal);
            previous = Some(now);
        }
        // Frame k is stamped with the send time of frame k - 1 (frame 0 at 0, frame 1 one
        // nominal step after it): no drift however long the stream.
        for k in 1..sends.len() {
            assert_eq!(stamps[k], nominal + (sends[k - 1] - sends[0]), "frame {k}");
        }
        // Out of order clocks and stalls stay within bounds.
        assert_eq!(timestamp_step(Some(t0 + ms(5)), t0, nominal), ms(1));
        assert_eq!(timestamp_step(Some(t0), t0 + Duration::from_secs(60), nominal), Duration::from_secs(10));
    }
}
