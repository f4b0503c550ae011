//! Signalling over HTTP (axum): `POST /v1/sessions` takes `{"sdp": OFFER}` (optionally
//! `"session"`, `"width"`, `"height"`, `"views"`) and answers `201 {"session", "token",
//! "type": "answer", "sdp"}`; a malformed offer is `400 {"error"}`. `DELETE
//! /v1/sessions/{id}` with `Authorization: Bearer TOKEN` ends a session; `GET /v1/sessions`
//! reports every session's counters (it and `GET /metrics` ask for the operators' token when
//! the composer has one); `GET /livez` (the process answers) and `GET /readyz`
//! (200 when it can take viewers: standalone, or registered with its master; 503 while the
//! master link is down). With a master, viewers arrive through the master's `OpenStream`
//! instead ([`crate::farm`]).

use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};

use crate::fusion::SessionId;
use crate::sessions::{end_session, layout_for, open_viewer};
use crate::state::{Shared, lock, reports};

/// The HTTP routes over `shared`.
pub(crate) fn router(shared: Arc<Shared>) -> Router {
    let routes = Router::new()
        .route("/livez", get(|| async { "ok" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/sessions", post(create_session).get(list_sessions))
        .route("/v1/sessions/{id}", axum::routing::delete(delete_session));
    shared.metrics.http.layer(routes).with_state(shared)
}

async fn metrics(State(shared): State<Arc<Shared>>, headers: HeaderMap) -> Response {
    if let Some(refusal) = nephele_telemetry::operator_refusal(shared.config.operator_token.as_ref(), &headers) {
        return refusal;
    }
    shared.metrics.peer_connections.set(shared.rtc.peer_connections_alive() as i64);
    // Counted by the responders; brought up to date at each scrape.
    let (resent, refused) = shared.rtc.retransmits();
    let m = &shared.metrics;
    m.nack_resent.inc_by(resent.saturating_sub(m.nack_resent.get()));
    m.nack_refused.inc_by(refused.saturating_sub(m.nack_refused.get()));
    let (paced, wait) = shared.rtc.paced();
    m.packets_paced.inc_by(paced.saturating_sub(m.packets_paced.get()));
    let wait_ms = wait.as_millis() as u64;
    m.pacing_wait_ms.inc_by(wait_ms.saturating_sub(m.pacing_wait_ms.get()));
    nephele_telemetry::metrics_response(&shared.metrics.registry)
}

async fn readyz(State(shared): State<Arc<Shared>>) -> Response {
    let farm_mode = shared.config.master.is_some();
    let linked = lock(&shared.to_master).is_some();
    let ready = !farm_mode || linked;
    let status = if ready { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE };
    let body = serde_json::json!({ "ready": ready, "farm_mode": farm_mode, "master_link": linked });
    (status, Json(body)).into_response()
}

#[derive(Debug, Deserialize)]
struct OfferRequest {
    sdp: String,
    #[serde(rename = "type")]
    kind: Option<String>,
    session: Option<SessionId>,
    width: Option<u32>,
    height: Option<u32>,
    views: Option<u16>,
}

#[derive(Debug, Serialize)]
struct AnswerResponse {
    session: SessionId,
    token: String,
    #[serde(rename = "type")]
    kind: &'static str,
    sdp: String,
}

fn error(status: StatusCode, message: impl std::fmt::Display) -> Response {
    (status, Json(serde_json::json!({ "error": message.to_string() }))).into_response()
}

async fn create_session(State(shared): State<Arc<Shared>>, body: axum::body::Bytes) -> Response {
    let request: OfferRequest = match serde_json::from_slice(&body) {
        Ok(r) => r,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("expected JSON {{\"sdp\": OFFER}}: {e}")),
    };
    if let Some(kind) = &request.kind
        && kind != "offer"
    {
        return error(StatusCode::BAD_REQUEST, format!("expected an SDP offer, got type '{kind}'"));
    }
    let (dw, dh) = shared.config.default_view;
    let layout = match layout_for(request.width.unwrap_or(dw), request.height.unwrap_or(dh), request.views.unwrap_or(1))
    {
        Ok(l) => l,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("bad view size: {e}")),
    };
    let id = request.session.unwrap_or_else(|| shared.next_session.fetch_add(1, Ordering::Relaxed));
    match open_viewer(&shared, id, request.sdp, layout).await {
        Ok((token, sdp)) => {
            (StatusCode::CREATED, Json(AnswerResponse { session: id, token, kind: "answer", sdp })).into_response()
        }
        Err((status, message)) => {
            let mut r = error(status, message);
            if status == StatusCode::SERVICE_UNAVAILABLE {
                r.headers_mut().insert("retry-after", axum::http::HeaderValue::from_static("5"));
            }
            r
        }
    }
}

async fn list_sessions(State(shared): State<Arc<Shared>>, headers: HeaderMap) -> Response {
    if let Some(refusal) = nephele_telemetry::operator_refusal(shared.config.operator_token.as_ref(), &headers) {
        return refusal;
    }
    let body = serde_json::json!({
        "sessions": reports(&shared),
        "wire_errors": shared.metrics.wire_errors.get(),
        "worker_connections": shared.metrics.worker_connections.get(),
        "unknown_session_batches": lock(&shared.compositor).unknown_session_batches(),
        // Pose received to frame sent and its stages, over the last frames of all sessions
        // (farm mode only: standalone frames have no pose of the farm behind them).
        "latency_ms": lock(&shared.latency).report(),
    });
    Json(body).into_response()
}

async fn delete_session(State(shared): State<Arc<Shared>>, Path(id): Path<SessionId>, headers: HeaderMap) -> Response {
    let token = nephele_telemetry::bearer(&headers).map(str::trim);
    let known = lock(&shared.sessions).get(&id).map(|e| e.token.clone());
    match known {
        None => error(StatusCode::NOT_FOUND, format!("no session {id}")),
        Some(t) if Some(t.as_str()) != token => error(StatusCode::UNAUTHORIZED, "missing or wrong session token"),
        Some(_) => {
            end_session(&shared, id).await;
            StatusCode::NO_CONTENT.into_response()
        }
    }
}
