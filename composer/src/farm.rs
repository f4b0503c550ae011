//! The composer's side of the farm (proto v2): the link to the master and the workers'
//! results.
//!
//! * **Master link**: the composer connects to the master's farm listener, says `Hello`
//!   (role composer) and `ComposerRegister { name, results_address }`. The master sends
//!   `OpenStream` (answered with `StreamOpened`: the SDP answer or why not), `FramePlan`
//!   (which tasks fill which view of a frame), `ReleaseTask` and `CloseStream`; the
//!   composer sends each accepted data-channel pose as `ClientPose` and `CloseStream` when a
//!   viewer vanishes. A lost link is re-established every second until shutdown.
//! * **Results listener**: workers connect, say `Hello` (role worker) and send
//!   `BatchResult`s, filed by `ids.task_id` until the master releases the task. Without a
//!   master, a peer with role tool may send the `FramePlan`s itself; the listener speaks
//!   nothing but proto.
//! * **Frames**: a plan's parts are fused by depth with the existing [`Compositor`]. Results
//!   race the plan (the worker reports `BatchDone` to the master on another connection), so
//!   a plan waits up to [`PLAN_GRACE`] (or its deadline) for tasks with no results yet; a part
//!   still missing then takes the previous frame's pixels of that object in that view.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::SinkExt;
use nephele_proto::stream::{framed, handshake, recv};
use nephele_proto::{CloseStream, ComposerRegister, FrameConfig, FramePlan, Message, Role, StreamOpened};
use nephele_shutdown::Shutdown;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;

use crate::fusion::{self, BatchKey, PlannedBatch};
use crate::latency::FrameTiming;
use crate::sessions::{end_session, layout_for, open_viewer};
use crate::state::{Shared, lock};

/// How long a frame plan waits for results that have not reached the composer yet.
pub const PLAN_GRACE: Duration = Duration::from_millis(100);
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(5);

/// Keeps a link to the master up until `stop`.
pub(crate) async fn run(shared: Arc<Shared>, master: String, results: SocketAddr, stop: Shutdown) {
    loop {
        match link(&shared, &master, results, &stop).await {
            Ok(()) => return,
            Err(e) => tracing::warn!(%master, "master link: {e}; reconnecting"),
        }
        *lock(&shared.to_master) = None;
        shared.metrics.master_linked.set(0);
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
            _ = stop.wait() => return,
        }
    }
}

async fn link(shared: &Arc<Shared>, master: &str, results: SocketAddr, stop: &Shutdown) -> Result<(), String> {
    let stream = nephele_transport::connect(master, shared.config.farm_tls.as_ref(), HANDSHAKE_TIMEOUT)
        .await
        .map_err(|e| format!("connecting: {e}"))?;
    let mut conn = framed(stream, FrameConfig::default());
    handshake(&mut conn, Role::Composer, &[Role::Master], shared.config.farm_secret.as_ref(), HANDSHAKE_TIMEOUT)
        .await
        .map_err(|e| format!("handshake: {e}"))?;
    let results_address = shared.config.advertise_results.clone().unwrap_or_else(|| results.to_string());
    let register = ComposerRegister { name: shared.config.name.clone(), results_address };
    conn.send(&Message::ComposerRegister(register)).await.map_err(|e| format!("registering: {e}"))?;
    match tokio::time::timeout(HANDSHAKE_TIMEOUT, recv(&mut conn)).await {
        Ok(Ok(Message::Registered(r))) => tracing::info!(%master, id = r.worker_id, "registered with the master"),
        Ok(Ok(other)) => return Err(format!("expected Registered, got {}", other.kind().name())),
        Ok(Err(e)) => return Err(format!("registering: {e}")),
        Err(_) => return Err("no answer to the registration".into()),
    }
    let (tx, mut rx) = mpsc::unbounded_channel();
    *lock(&shared.to_master) = Some(tx);
    shared.metrics.master_linked.set(1);
    loop {
        tokio::select! {
            incoming = recv(&mut conn) => match incoming {
                Ok(message) => handle(shared, message),
                Err(e) => return Err(e.to_string()),
            },
            Some(out) = rx.recv() => conn.send(&out).await.map_err(|e| e.to_string())?,
            _ = stop.wait() => return Ok(()),
        }
    }
}

fn handle(shared: &Arc<Shared>, message: Message) {
    match message {
        Message::OpenStream(open) => {
            let shared = Arc::clone(shared);
            tokio::spawn(async move {
                let answer = match layout_for(open.width, open.height, open.views.min(u32::from(u16::MAX)) as u16) {
                    Err(e) => Err(format!("bad view size: {e}")),
                    Ok(layout) => open_viewer(&shared, open.session_id, open.offer_sdp, layout)
                        .await
                        .map(|(_, sdp)| sdp)
                        .map_err(|(_, e)| e),
                };
                if let Err(e) = &answer {
                    tracing::info!(session = open.session_id, "stream refused: {e}");
                }
                shared.to_master(Message::StreamOpened(StreamOpened { session_id: open.session_id, answer }));
            });
        }
        Message::FramePlan(plan) => accept_plan(shared, plan),
        Message::ReleaseTask(release) => {
            let mut results = lock(&shared.task_results);
            results.release(release.task_id);
            shared.metrics.held_tasks.set(results.len() as i64);
        }
        Message::CloseStream(CloseStream { session_id, reason }) => {
            tracing::info!(session = session_id, %reason, "the master closed the stream");
            lock(&shared.last_parts).retain(|k, _| k.0 != session_id);
            let shared = Arc::clone(shared);
            tokio::spawn(async move { end_session(&shared, session_id).await });
        }
        other => tracing::debug!("unexpected message from the master: {}", other.kind().name()),
    }
}

/// Fuses `plan` once its tasks' results are all here, or after [`PLAN_GRACE`] (or its
/// deadline, if sooner) with what has arrived.
fn accept_plan(shared: &Arc<Shared>, plan: FramePlan) {
    let shared = Arc::clone(shared);
    tokio::spawn(async move {
        let start = Instant::now();
        let left = plan.deadline_in_us.map_or(PLAN_GRACE, Duration::from_micros);
        let grace_end = start + PLAN_GRACE.min(left);
        while Instant::now() < grace_end && !all_present(&shared, &plan) {
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        if let Err(e) = fuse_plan(&shared, &plan, start) {
            tracing::debug!(session = plan.session_id, frame = plan.frame_id, "frame plan refused: {e}");
        }
    });
}

fn all_present(shared: &Shared, plan: &FramePlan) -> bool {
    let results = lock(&shared.task_results);
    plan.parts.iter().all(|p| results.get(p.task_id).is_some_and(|r| !r.is_empty()))
}

/// Fuses a frame plan from the stored task results (see the module docs).
fn fuse_plan(shared: &Shared, plan: &FramePlan, plan_received: Instant) -> Result<(), String> {
    let results_complete = Instant::now();
    let views = u16::try_from(plan.views).map_err(|_| format!("{} views", plan.views))?;
    let layout = layout_for(plan.width, plan.height, views)?;
    if (layout.view_width(), layout.view_height()) != (plan.width, plan.height) {
        return Err(format!("views of {}x{} do not fit the encoder", plan.width, plan.height));
    }
    let (session, frame) = (plan.session_id, plan.frame_id);
    let mut planned = Vec::new();
    let mut arrived = Vec::new();
    let mut missing = false;
    // Kernel time per worker on this frame's batches (the latency split's `render`).
    let mut render_us: HashMap<u64, u64> = HashMap::new();
    {
        let results = lock(&shared.task_results);
        let mut last = lock(&shared.last_parts);
        for (i, part) in plan.parts.iter().enumerate() {
            let view = u16::try_from(part.view).map_err(|_| format!("view {}", part.view))?;
            let object = u32::try_from(i).map_err(|_| "too many parts".to_string())?;
            let key = (session, part.view, part.object_id);
            match results.get(part.task_id).filter(|r| !r.is_empty()) {
                Some(batches) => {
                    let mut covered = Vec::new();
                    for (j, r) in batches.iter().enumerate() {
                        if (r.width, r.height) != (plan.width, plan.height) {
                            return Err(format!(
                                "task {} rendered {}x{}, the plan says {}x{}",
                                part.task_id, r.width, r.height, plan.width, plan.height
                            ));
                        }
                        let key =
                            BatchKey { object, batch: u32::try_from(j).map_err(|_| "too many batches".to_string())? };
                        planned.push(PlannedBatch { key, view, pixels: r.pixels.clone().into() });
                        covered.extend_from_slice(&r.pixels);
                        *render_us.entry(r.worker_id).or_default() += r.render_time_us;
                        // The worker's message itself: fusion reads its arrays in place.
                        arrived.push(fusion::BatchResult { session, frame, view, key, data: Arc::clone(r) });
                    }
                    last.insert(key, covered.into());
                }
                None => {
                    // Never arrived: plan the object's pixels of the previous frame without a
                    // result, so the compositor fills them from that frame.
                    if let Some(pixels) = last.get(&key) {
                        planned.push(PlannedBatch {
                            key: BatchKey { object, batch: 0 },
                            view,
                            pixels: Arc::clone(pixels),
                        });
                        missing = true;
                    }
                }
            }
        }
    }
    let deadline = Instant::now() + if missing { Duration::ZERO } else { PLAN_GRACE };
    {
        let mut latency = lock(&shared.latency);
        let pose_received = latency.pose_time(session, plan.pose_sequence);
        let render_ms = render_us.values().max().map(|&us| us as f64 / 1e3);
        let timing = FrameTiming {
            pose_sequence: plan.pose_sequence,
            client_time_ms: plan.client_time_ms,
            pose_received,
            plan_received,
            results_complete,
            render_ms,
        };
        latency.frame_planned(session, frame, timing);
    }
    // Black behind the objects, or the key colour for a viewer in AR mode (its latest pose's).
    let ar = lock(&shared.sessions)
        .get(&session)
        .and_then(|e| e.last_pose.as_ref())
        .is_some_and(|pose| pose.mode == nephele_proto::pose::MODE_AR);
    let background = if ar { nephele_proto::pose::AR_KEY_LINEAR } else { [0.0; 3] };
    let plan = fusion::FramePlan { session, frame, layout, background, deadline, batches: planned };
    {
        let mut compositor = lock(&shared.compositor);
        compositor.plan_frame(plan).map_err(|e| e.to_string())?;
        for batch in arrived {
            if let Err(e) = compositor.add_batch(batch) {
                tracing::debug!(session, frame, "batch refused: {e}");
            }
        }
    }
    shared.wake.notify_one();
    Ok(())
}

/// The results listener: every connection speaks proto (see [`read_results`]).
pub(crate) async fn accept_results(shared: Arc<Shared>, listener: TcpListener, stop: Shutdown) {
    loop {
        let connection_stop = stop.clone();
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    shared.metrics.worker_connections.inc();
                    tokio::spawn(read_results(Arc::clone(&shared), stream, peer, connection_stop));
                }
                Err(e) => tracing::warn!("accepting a worker connection: {e}"),
            },
            _ = stop.wait() => return,
        }
    }
}

/// A connection to the results listener: `Hello`, then `BatchResult`s. A peer that says it
/// is a tool (no master: tests, benchmarks, a farm of one's own) may also send the
/// `FramePlan`s that the master would.
pub(crate) async fn read_results(shared: Arc<Shared>, stream: TcpStream, peer: SocketAddr, stop: Shutdown) {
    let stream = match nephele_transport::accept(stream, shared.config.farm_tls.as_ref(), HANDSHAKE_TIMEOUT).await {
        Ok(stream) => stream,
        Err(e) => {
            shared.metrics.wire_errors.inc();
            tracing::warn!(%peer, "results connection refused at the TLS handshake: {e}");
            return;
        }
    };
    let mut conn = framed(stream, FrameConfig::default());
    let accept = [Role::Worker, Role::Tool];
    let secret = shared.config.farm_secret.as_ref();
    let peer_role = match handshake(&mut conn, Role::Composer, &accept, secret, HANDSHAKE_TIMEOUT).await {
        Ok(hello) => hello.role,
        Err(e @ nephele_proto::ProtoError::Unauthenticated(_)) => {
            shared.metrics.peers_unauthenticated.inc();
            tracing::warn!(%peer, "results connection refused: {e}");
            return;
        }
        Err(e) => {
            shared.metrics.wire_errors.inc();
            tracing::debug!(%peer, "worker handshake: {e}");
            return;
        }
    };
    loop {
        let message = tokio::select! {
            m = recv(&mut conn) => m,
            _ = stop.wait() => return,
        };
        match message {
            Ok(Message::BatchResult(result)) => {
                let mut results = lock(&shared.task_results);
                if !results.insert(result) {
                    shared.metrics.results_after_release.inc();
                }
                shared.metrics.held_tasks.set(results.len() as i64);
            }
            Ok(Message::FramePlan(plan)) if peer_role == Role::Tool => accept_plan(&shared, plan),
            Ok(Message::Goodbye(_)) => break,
            Ok(other) => tracing::debug!(%peer, "unexpected message from a worker: {}", other.kind().name()),
            Err(nephele_proto::ProtoError::Invalid(rejected)) => {
                // A message that decoded but failed validation: skip it, keep the connection.
                shared.metrics.wire_errors.inc();
                tracing::debug!(%peer, "malformed message from a worker: {rejected}");
            }
            Err(e) => {
                if !matches!(e, nephele_proto::ProtoError::Closed) {
                    shared.metrics.wire_errors.inc();
                    tracing::debug!(%peer, "worker connection: {e}");
                }
                break;
            }
        }
    }
    tracing::debug!(%peer, "worker connection closed");
}
