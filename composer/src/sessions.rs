//! Viewer sessions: accepting an offer (peer connection, fusion state, media thread),
//! ending a session, and the viewers' events (connection state, poses and control messages
//! on the data channel). Accepted poses go to the master as `ClientPose`s.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex as StdMutex, mpsc as std_mpsc};
use std::time::Instant;

use axum::http::StatusCode;
use nephele_proto::{ClientPose, Message};
use nephele_shutdown::Shutdown;
use tokio::sync::mpsc;

use crate::encode::{EncoderStats, MAX_LONG_SIDE, MAX_SHORT_SIDE, MIN_SIDE};
use crate::fusion::{FrameLayout, SessionId};
use crate::media::{MediaHandles, spawn_media_thread};
use crate::pose::{Control, Pose, PoseDrop, PoseInbox};
use crate::state::{MediaCounters, SessionEntry, Shared, lock};
use crate::webrtc::{RtcError, ViewerEvent};

/// The packed layout for `views` views of `width x height`: one row for up to two views, a
/// Looking Glass quilt for 45 or 48, a near-square grid otherwise
/// ([`nephele_proto::pose::grid_columns`]); views shrunk (aspect kept) until the picture fits the encoder,
/// and rounded down to even sizes.
pub fn layout_for(width: u32, height: u32, views: u16) -> Result<FrameLayout, String> {
    if width == 0 || height == 0 || views == 0 {
        return Err(format!("{views} views of {width}x{height}"));
    }
    let columns = nephele_proto::pose::grid_columns(views);
    let rows = views.div_ceil(columns);
    let (pw, ph) = (f64::from(width) * f64::from(columns), f64::from(height) * f64::from(rows));
    let (long, short) = if pw >= ph { (MAX_LONG_SIDE, MAX_SHORT_SIDE) } else { (MAX_SHORT_SIDE, MAX_LONG_SIDE) };
    let scale = (f64::from(long) / pw).min(f64::from(short) / ph).min(1.0);
    let even = |v: f64| ((v.floor() as u32) & !1).max(MIN_SIDE);
    let (w, h) = (even(f64::from(width) * scale), even(f64::from(height) * scale));
    FrameLayout::grid(w, h, views, columns).map_err(|e| e.to_string())
}

/// Accepts a viewer's offer for session `id`: the peer connection, the fusion state and the
/// media thread. Answers `(token, answer SDP)`, or the HTTP status and reason of a refusal.
pub(crate) async fn open_viewer(
    shared: &Arc<Shared>,
    id: SessionId,
    offer: String,
    layout: FrameLayout,
) -> Result<(String, String), (StatusCode, String)> {
    if lock(&shared.sessions).len() >= shared.config.max_sessions {
        return Err((StatusCode::SERVICE_UNAVAILABLE, "the composer is full".into()));
    }
    if lock(&shared.compositor).open_session(id).is_err() {
        return Err((StatusCode::CONFLICT, format!("session {id} exists")));
    }
    let (sdp, viewer) = match shared.rtc.accept(id, offer, shared.events.clone()).await {
        Ok(ok) => ok,
        Err(e) => {
            lock(&shared.compositor).close_session(id);
            let status = match e {
                RtcError::BadOffer(_) | RtcError::NoH264 => StatusCode::BAD_REQUEST,
                _ => StatusCode::INTERNAL_SERVER_ERROR,
            };
            tracing::info!(session = id, "offer refused: {e}");
            return Err((status, e.to_string()));
        }
    };
    let token = format!("{:032x}", rand::random::<u128>());
    let viewer = Arc::new(viewer);
    let (frames_tx, frames_rx) = std_mpsc::sync_channel(1);
    let keyframe = Arc::new(AtomicBool::new(true));
    let media = Arc::new(StdMutex::new((MediaCounters::default(), EncoderStats::default())));
    let scale_level = Arc::new(AtomicU32::new(0));
    let handles = MediaHandles {
        keyframe: Arc::clone(&keyframe),
        media: Arc::clone(&media),
        scale_level: Arc::clone(&scale_level),
    };
    let media_thread = spawn_media_thread(shared, Arc::clone(&viewer), frames_rx, handles);
    lock(&shared.sessions).insert(
        id,
        SessionEntry {
            token: token.clone(),
            viewer,
            layout,
            frames: frames_tx,
            keyframe,
            inbox: PoseInbox::default(),
            last_pose: None,
            media,
            scale_level,
            control_malformed: 0,
            created: Instant::now(),
            next_frame: 0,
            media_thread,
        },
    );
    shared.metrics.sessions.inc();
    tracing::info!(session = id, "new viewer session");
    Ok((token, sdp))
}

/// How long an ended session waits for its media thread (a frame being encoded, a packet
/// waiting in the pacer at most 250 ms).
const MEDIA_THREAD_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

pub(crate) async fn end_session(shared: &Shared, id: SessionId) {
    let entry = lock(&shared.sessions).remove(&id);
    lock(&shared.compositor).close_session(id);
    lock(&shared.latency).session_ended(id);
    if let Some(mut e) = entry {
        shared.metrics.sessions.dec();
        let thread = e.media_thread.take();
        let viewer = Arc::clone(&e.viewer);
        // Dropping the entry drops the frame sender: the media thread's loop ends.
        drop(e);
        viewer.close().await;
        // Waited for here, while the runtime it sends through still runs (a thread left
        // sending, or waiting in the pacer, when the runtime stops panics on its timer).
        if let Some(thread) = thread {
            let joined = tokio::time::timeout(MEDIA_THREAD_GRACE, tokio::task::spawn_blocking(move || thread.join()));
            match joined.await {
                Ok(Ok(Ok(()))) => {}
                Ok(Ok(Err(_))) => tracing::error!(session = id, "the media thread panicked"),
                Ok(Err(e)) => tracing::warn!(session = id, "waiting for the media thread: {e}"),
                Err(_) => tracing::warn!(session = id, "the media thread did not end within {MEDIA_THREAD_GRACE:?}"),
            }
        }
        tracing::info!(session = id, "session ended");
    }
}

pub(crate) async fn event_loop(shared: Arc<Shared>, mut events: mpsc::Receiver<ViewerEvent>, stop: Shutdown) {
    loop {
        let event = tokio::select! {
            e = events.recv() => match e { Some(e) => e, None => return },
            _ = stop.wait() => return,
        };
        match event {
            ViewerEvent::Connected(id) | ViewerEvent::KeyframeRequest(id) => {
                // A new viewer, or a receiver that lost a picture: the next frame is an IDR.
                if let Some(e) = lock(&shared.sessions).get(&id) {
                    e.keyframe.store(true, Ordering::SeqCst);
                }
            }
            ViewerEvent::Disconnected(id, state) => {
                tracing::info!(session = id, %state, "viewer gone");
                if lock(&shared.sessions).contains_key(&id) {
                    shared.to_master(nephele_proto::Message::CloseStream(nephele_proto::CloseStream {
                        session_id: id,
                        reason: format!("viewer gone ({state})"),
                    }));
                }
                end_session(&shared, id).await;
            }
            ViewerEvent::Binary(id, bytes, at) => {
                let mut sessions = lock(&shared.sessions);
                let Some(e) = sessions.get_mut(&id) else { continue };
                match e.inbox.offer(&bytes, at) {
                    Ok(pose) => {
                        let (w, h) = pose.view_size();
                        if let Ok(layout) = layout_for(w, h, pose.views.len() as u16) {
                            e.layout = layout;
                        }
                        let pose = Arc::new(pose);
                        e.last_pose = Some(Arc::clone(&pose));
                        forward_pose(&shared, id, &pose, e.scale_level.load(Ordering::Relaxed));
                        let _ = shared.poses.send((id, pose));
                    }
                    Err(PoseDrop::Malformed(err)) => tracing::debug!(session = id, "pose dropped: {err}"),
                    Err(other) => tracing::trace!(session = id, "pose dropped: {other:?}"),
                }
            }
            ViewerEvent::Text(id, text) => {
                let control = serde_json::from_str::<Control>(&text);
                let viewer = {
                    let mut sessions = lock(&shared.sessions);
                    let Some(e) = sessions.get_mut(&id) else { continue };
                    match &control {
                        Ok(Control::Keyframe) => e.keyframe.store(true, Ordering::SeqCst),
                        Ok(Control::Ping { .. }) => {}
                        Ok(Control::Pong { .. }) | Err(_) => e.control_malformed += 1,
                    }
                    Arc::clone(&e.viewer)
                };
                if let Ok(Control::Ping { t }) = control
                    && let Ok(reply) = serde_json::to_string(&Control::Pong { t })
                {
                    // Sent apart: on a congested association the send waits, and this loop
                    // also forwards every viewer's poses.
                    tokio::spawn(async move {
                        let _ = viewer.send_text(reply).await;
                    });
                }
            }
        }
    }
}

/// An accepted data-channel pose, as the master's `ClientPose`, its views `1 / 2^level` of
/// each side while the stream is coded that much smaller (the projection matrices hold for
/// any size: the same rays, fewer of them).
pub(crate) fn forward_pose(shared: &Shared, session: SessionId, pose: &Pose, level: u32) {
    if shared.config.master.is_none() {
        return;
    }
    let mut views = pose.views.clone();
    let (w, h) = pose.view_size();
    if let Some((w, h)) = nephele_proto::pose::scaled_view_size(w, h, level) {
        for v in &mut views {
            (v.width, v.height) = (w, h);
        }
    }
    lock(&shared.latency).pose_received(session, pose.seq, Instant::now());
    shared.to_master(Message::ClientPose(ClientPose {
        session_id: session,
        sequence: pose.seq,
        client_time_ms: pose.client_time_ms,
        views,
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_fit_the_encoder() {
        let l = layout_for(1280, 720, 1).unwrap();
        assert_eq!((l.width(), l.height(), l.columns()), (1280, 720, 1));
        let l = layout_for(1920, 1080, 2).unwrap();
        assert_eq!((l.width(), l.height()), (3840, 1080));
        // Two 2000x2000 eyes: shrunk to fit 3840 wide, even sizes.
        let l = layout_for(2000, 2000, 2).unwrap();
        assert_eq!((l.view_width(), l.view_height()), (1920, 1920));
        assert!(l.height() <= 2160);
        // Odd sizes round down to even.
        let l = layout_for(641, 479, 1).unwrap();
        assert_eq!((l.width(), l.height()), (640, 478));
        // A 45-view quilt: Looking Glass's 5 columns and 9 rows, within 3840x2160.
        let l = layout_for(420, 560, 45).unwrap();
        assert_eq!((l.columns(), l.rows()), (5, 9));
        assert!(l.width() <= 2160 && l.height() <= 3840, "{}x{}", l.width(), l.height());
        let l = layout_for(180, 240, 45).unwrap();
        assert_eq!((l.width(), l.height()), (900, 2160));
        assert!(crate::encode::check_resolution(l.width(), l.height()).is_ok() && l.view_width().is_multiple_of(2));
        assert!(layout_for(0, 10, 1).is_err());
    }
}
