//! The master's HTTP API and signalling (axum): the thin shell around the session table and
//! the farm. See `client/PROTOCOL.md` for the wire format.
//!
//! * `GET /` and `GET /client/*`: the browser client (plain files compiled into the binary).
//! * `GET /v1/config`: ICE servers and scenes for the client.
//! * `POST /v1/sessions`: SDP offer + scene in, SDP answer + session token out; 503 with
//!   `Retry-After` while the scheduler's admission control refuses new users.
//! * `DELETE /v1/sessions/{id}` with `Authorization: Bearer TOKEN`.
//! * `GET /v1/sessions/{id}/watch` with the same token: a long poll that answers
//!   `{"state": "ended"}` as soon as the session is not open (the service ended it: its
//!   composer died, its peer vanished; or it is unknown), or `{"state": "open"}` after
//!   [`WATCH_HOLD`] while it lives, so that a client reconnects at once instead of waiting
//!   for ICE to notice a dead peer. Both are `200`: a page's console logs every 4xx as an
//!   error, and an ended session is news, not a failure.
//! * `GET /v1/farm`: the scheduler's state.
//! * `GET /livez`, `GET /readyz`: liveness, and readiness (a composer and a worker joined).
//! * `GET /metrics`: Prometheus metrics ([`crate::metrics`]).

use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::{ConnectInfo, DefaultBodyLimit, Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::access::{Denied, OperatorToken, RateLimiter, ViewerKey};
use crate::client_files;
use crate::metrics::MasterMetrics;
use crate::sessions::{AccessError, SessionRequest, SessionTable};

/// Largest request body accepted (an SDP offer is a few kilobytes).
pub const MAX_BODY_BYTES: usize = 256 * 1024;
/// Largest SDP accepted.
pub const MAX_SDP_BYTES: usize = 64 * 1024;
/// How long `GET /v1/sessions/{id}/watch` holds a request while the session lives (under the
/// 30 s that proxies commonly allow an idle response).
pub const WATCH_HOLD: Duration = Duration::from_secs(25);

pub type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

/// A first camera for a scene, in Nephele world coordinates.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneView {
    pub eye: [f32; 3],
    pub target: [f32; 3],
    pub fov_y_deg: f32,
}

/// Whether a new session may start now (NEPHELE Algorithm 1: no admission while any user is
/// starved).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Admission {
    Admit,
    Refuse { retry_after: Duration },
}

/// Why the farm could not open a session.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OpenError {
    /// The client's offer was rejected (malformed SDP, no video codec we can send).
    #[error("bad offer: {0}")]
    BadOffer(String),
    /// No composer (or no worker) is available.
    #[error("service unavailable: {0}")]
    Unavailable(String),
    /// Admission control refused the session after all (a user became starved between the
    /// [`FarmBackend::admission`] check and the open): 503 with `Retry-After`.
    #[error("the farm is saturated (a user is starved); retry later")]
    Refused { retry_after: Duration },
}

/// What the HTTP layer needs from the farm: the live master implements it over its TCP links
/// to the composer and the workers; tests implement it in memory.
pub trait FarmBackend: Send + Sync + 'static {
    /// Scenes a client may ask for, with a good first view.
    fn scenes(&self) -> Vec<(String, SceneView)>;
    /// ICE servers to offer the client (`{"urls": [...], "username", "credential"}`).
    fn ice_servers(&self) -> serde_json::Value;
    fn admission(&self) -> Admission;
    /// Hands the offer to a composer and returns its SDP answer.
    fn open(
        &self,
        session_id: String,
        request: SessionRequest,
        offer_sdp: String,
    ) -> BoxFuture<Result<String, OpenError>>;
    /// The session ended (closed by its client or dropped by the service).
    fn close(&self, session_id: String) -> BoxFuture<()>;
    /// The scheduler's state for `GET /v1/farm`.
    fn farm_state(&self) -> BoxFuture<serde_json::Value>;
}

/// Shared state of the HTTP handlers.
pub struct AppState {
    pub sessions: Mutex<SessionTable>,
    pub backend: Arc<dyn FarmBackend>,
    pub metrics: Arc<MasterMetrics>,
    clock: Box<dyn Fn() -> f64 + Send + Sync>,
    /// Who may open sessions ([`crate::access`]); the default admits everyone.
    pub access: AccessPolicy,
    /// Bumped whenever sessions leave the table or the server stops: wakes the long polls of
    /// `GET /v1/sessions/{id}/watch`, which then look at the table.
    table_changes: tokio::sync::watch::Sender<TableChange>,
}

/// What the watchers of sessions learn from [`AppState::table_changes`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct TableChange {
    generation: u64,
    stopping: bool,
}

/// A client's address, as the HTTP server records it for each connection (plain or TLS):
/// what the per-address rate limit counts by.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClientAddr(pub std::net::SocketAddr);

impl axum::extract::connect_info::Connected<axum::serve::IncomingStream<'_, tokio::net::TcpListener>> for ClientAddr {
    fn connect_info(stream: axum::serve::IncomingStream<'_, tokio::net::TcpListener>) -> ClientAddr {
        ClientAddr(*stream.remote_addr())
    }
}

impl axum::extract::connect_info::Connected<axum::serve::IncomingStream<'_, crate::tls::TlsListener>> for ClientAddr {
    fn connect_info(stream: axum::serve::IncomingStream<'_, crate::tls::TlsListener>) -> ClientAddr {
        ClientAddr(*stream.remote_addr())
    }
}

/// The viewer access policy of `POST /v1/sessions`.
#[derive(Debug, Default)]
pub struct AccessPolicy {
    /// Invitations are required (signed with this key) when set.
    pub viewer_key: Option<ViewerKey>,
    /// Per-address limit on session requests.
    pub rate_limit: Option<RateLimiter>,
    /// Required on the operators' endpoints (`/v1/farm`, `/metrics`, `GET /v1/sessions`)
    /// when set; they are open otherwise.
    pub operator_token: Option<OperatorToken>,
}

impl AccessPolicy {
    /// `None` when `headers` may read an operators' endpoint, else the 401 to answer.
    fn operator_refusal(&self, headers: &HeaderMap) -> Option<Response> {
        nephele_telemetry::operator_refusal(self.operator_token.as_ref(), headers)
    }
}

impl std::fmt::Debug for AppState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AppState").finish_non_exhaustive()
    }
}

impl AppState {
    pub fn new(
        backend: Arc<dyn FarmBackend>,
        metrics: Arc<MasterMetrics>,
        clock: Box<dyn Fn() -> f64 + Send + Sync>,
    ) -> Arc<AppState> {
        AppState::with_access(backend, metrics, clock, AccessPolicy::default())
    }

    /// [`AppState::new`] with a viewer access policy.
    pub fn with_access(
        backend: Arc<dyn FarmBackend>,
        metrics: Arc<MasterMetrics>,
        clock: Box<dyn Fn() -> f64 + Send + Sync>,
        access: AccessPolicy,
    ) -> Arc<AppState> {
        let (table_changes, _) = tokio::sync::watch::channel(TableChange::default());
        Arc::new(AppState { sessions: Mutex::new(SessionTable::new()), backend, metrics, clock, access, table_changes })
    }

    /// The service ended session `id` on its own (its composer or peer is gone): it leaves
    /// the table, and its watchers hear at once. Returns whether it was there.
    pub fn end_session(&self, id: &str) -> bool {
        let removed = self.sessions().drop_session(id).is_some();
        self.sessions_left();
        removed
    }

    /// Wakes the watches: some session left the table.
    fn sessions_left(&self) {
        self.table_changes.send_modify(|c| c.generation += 1);
    }

    /// The server is stopping: pending watches answer now rather than hold its graceful
    /// shutdown for up to [`WATCH_HOLD`].
    pub fn stop_watches(&self) {
        self.table_changes.send_modify(|c| c.stopping = true);
    }

    fn sessions(&self) -> std::sync::MutexGuard<'_, SessionTable> {
        // A panic while holding the lock cannot leave the table half-updated (every update is
        // a single insert or remove), so a poisoned lock is still usable.
        self.sessions.lock().unwrap_or_else(|poison| poison.into_inner())
    }
}

pub fn router(state: Arc<AppState>) -> Router {
    let routes = Router::new()
        .route("/", get(index))
        .route("/client/{file}", get(client_file))
        .route("/v1/config", get(config))
        .route("/v1/sessions", post(open_session).get(list_sessions))
        .route("/v1/sessions/{id}", delete(close_session))
        .route("/v1/sessions/{id}/watch", get(watch_session))
        .route("/v1/farm", get(farm))
        .route("/livez", get(|| async { "ok" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics));
    state.metrics.http.layer(routes).layer(DefaultBodyLimit::max(MAX_BODY_BYTES)).with_state(state)
}

/// A JSON error body with a status.
fn error(status: StatusCode, message: impl std::fmt::Display) -> Response {
    (status, Json(json!({ "error": message.to_string() }))).into_response()
}

async fn index() -> Response {
    client_files::serve("index.html")
}

async fn client_file(Path(file): Path<String>) -> Response {
    client_files::serve(&file)
}

async fn config(State(state): State<Arc<AppState>>) -> Response {
    let scenes: Vec<String> = state.backend.scenes().into_iter().map(|(name, _)| name).collect();
    Json(json!({ "ice_servers": state.backend.ice_servers(), "scenes": scenes })).into_response()
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct OpenBody {
    sdp: String,
    /// `"offer"` where given (WebRTC's `RTCSessionDescription` JSON carries it).
    #[serde(rename = "type", default)]
    kind: Option<String>,
    #[serde(default = "default_scene")]
    scene: String,
    #[serde(default = "one")]
    views: u32,
    #[serde(default = "default_width")]
    width: u32,
    #[serde(default = "default_height")]
    height: u32,
    #[serde(default = "default_fps")]
    target_fps: f32,
}

fn default_scene() -> String {
    "default".into()
}
fn one() -> u32 {
    1
}
fn default_width() -> u32 {
    640
}
fn default_height() -> u32 {
    480
}
fn default_fps() -> f32 {
    30.0
}

async fn open_session(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    extensions: axum::http::Extensions,
    body: axum::body::Bytes,
) -> Response {
    // The rate limit before anything else is looked at (served with connect info; a router
    // served without it, as in tests, has no client address and no limit).
    if let (Some(limiter), Some(ConnectInfo(ClientAddr(peer)))) =
        (&state.access.rate_limit, extensions.get::<ConnectInfo<ClientAddr>>())
        && let Err(wait) = limiter.take(peer.ip(), (state.clock)())
    {
        state.metrics.links.sessions_rate_limited.inc();
        tracing::info!(%peer, "session request over the rate limit");
        let mut response =
            error(StatusCode::TOO_MANY_REQUESTS, "too many session requests from this address; retry later");
        let seconds = wait.as_secs_f64().ceil().max(1.0) as u64;
        response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(seconds));
        return response;
    }
    // Parse by hand so that every malformed body gets our JSON error, not axum's text.
    let body: OpenBody = match serde_json::from_slice(&body) {
        Ok(body) => body,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("malformed session request: {e}")),
    };
    if body.kind.as_deref().is_some_and(|k| k != "offer") {
        return error(StatusCode::BAD_REQUEST, "expected an SDP offer (\"type\": \"offer\")");
    }
    if body.sdp.len() > MAX_SDP_BYTES {
        return error(StatusCode::BAD_REQUEST, format!("SDP offer larger than {MAX_SDP_BYTES} bytes"));
    }
    if !body.sdp.starts_with("v=0") {
        return error(StatusCode::BAD_REQUEST, "malformed SDP offer: it must start with \"v=0\"");
    }
    let request = SessionRequest {
        scene: body.scene,
        views: body.views,
        width: body.width,
        height: body.height,
        target_fps: body.target_fps,
    };
    if let Err(e) = request.validate() {
        return error(StatusCode::BAD_REQUEST, e);
    }
    let scenes = state.backend.scenes();
    let Some((_, view)) = scenes.iter().find(|(name, _)| *name == request.scene) else {
        let names: Vec<&str> = scenes.iter().map(|(n, _)| n.as_str()).collect();
        return error(
            StatusCode::BAD_REQUEST,
            format!("unknown scene {:?}; known: {}", request.scene, names.join(", ")),
        );
    };
    let view = view.clone();
    if let Some(key) = &state.access.viewer_key {
        let presented = nephele_telemetry::bearer(&headers).map(str::trim);
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        let checked = match presented {
            None => Err(Denied::Missing),
            Some(token) => key.check(token, &request.scene, now),
        };
        if let Err(denied) = checked {
            state.metrics.links.sessions_denied.inc();
            tracing::info!(scene = %request.scene, "session request denied: {denied}");
            if denied.is_missing() {
                let mut response = error(StatusCode::UNAUTHORIZED, denied);
                response.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
                return response;
            }
            return error(StatusCode::FORBIDDEN, denied);
        }
    }
    if let Admission::Refuse { retry_after } = state.backend.admission() {
        tracing::info!(retry_after_s = retry_after.as_secs_f64(), "session refused by admission control");
        state.metrics.links.sessions_refused.inc();
        return refused(retry_after);
    }
    let mut secret = [0u8; 16];
    if let Err(e) = getrandom::fill(&mut secret) {
        return error(StatusCode::INTERNAL_SERVER_ERROR, format!("no randomness for a token: {e}"));
    }
    let now = (state.clock)();
    let (id, token) = state.sessions().open(request.clone(), secret, now);
    match state.backend.open(id.clone(), request, body.sdp).await {
        Ok(answer) => {
            tracing::info!(session = %id, "session opened");
            let body = json!({ "session_id": id, "token": token, "type": "answer", "sdp": answer, "view": view });
            (StatusCode::CREATED, Json(body)).into_response()
        }
        Err(e) => {
            state.sessions().drop_session(&id);
            tracing::warn!(session = %id, error = %e, "session not opened");
            match e {
                OpenError::BadOffer(_) => error(StatusCode::BAD_REQUEST, e),
                OpenError::Unavailable(_) => error(StatusCode::SERVICE_UNAVAILABLE, e),
                OpenError::Refused { retry_after } => {
                    state.metrics.links.sessions_refused.inc();
                    refused(retry_after)
                }
            }
        }
    }
}

/// 503 with `Retry-After` in whole seconds (at least 1).
fn refused(retry_after: Duration) -> Response {
    let seconds = retry_after.as_secs_f64().ceil().max(1.0) as u64;
    let mut response = error(StatusCode::SERVICE_UNAVAILABLE, "the farm is saturated (a user is starved); retry later");
    response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(seconds));
    response
}

async fn list_sessions(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Some(refusal) = state.access.operator_refusal(&headers) {
        return refusal;
    }
    let sessions: Vec<serde_json::Value> = state
        .sessions()
        .iter()
        .map(|s| json!({ "id": s.id, "scene": s.request.scene, "views": s.request.views, "width": s.request.width, "height": s.request.height, "target_fps": s.request.target_fps }))
        .collect();
    Json(json!({ "sessions": sessions })).into_response()
}

async fn close_session(State(state): State<Arc<AppState>>, Path(id): Path<String>, headers: HeaderMap) -> Response {
    let token = nephele_telemetry::bearer(&headers).unwrap_or("");
    let closed = state.sessions().close(&id, token);
    match closed {
        Ok(session) => {
            state.sessions_left();
            state.backend.close(session.id.clone()).await;
            tracing::info!(session = %session.id, "session closed by its client");
            StatusCode::NO_CONTENT.into_response()
        }
        Err(e @ AccessError::Unknown(_)) => error(StatusCode::NOT_FOUND, e),
        Err(e @ AccessError::BadToken(_)) => error(StatusCode::UNAUTHORIZED, e),
    }
}

/// Long poll on a session (see the module documentation): `{"state":"ended"}` once it is not
/// open, `{"state":"open"}` after [`WATCH_HOLD`] while it lives (both 200), 401 for a wrong
/// token, 503 when the server stops.
async fn watch_session(State(state): State<Arc<AppState>>, Path(id): Path<String>, headers: HeaderMap) -> Response {
    let token = nephele_telemetry::bearer(&headers).unwrap_or("");
    // Subscribed before the first look, so that an end in between is not missed.
    let mut changes = state.table_changes.subscribe();
    let ended = || {
        let body = json!({
            "state": "ended",
            "error": "this session is not open (the service ended it: its composer or peer connection was lost); open a new one",
        });
        Json(body).into_response()
    };
    let known = state.sessions().authorize(&id, token).map(|_| ());
    match known {
        Ok(()) => {}
        Err(AccessError::Unknown(_)) => return ended(),
        Err(e @ AccessError::BadToken(_)) => return error(StatusCode::UNAUTHORIZED, e),
    }
    if changes.borrow_and_update().stopping {
        return error(StatusCode::SERVICE_UNAVAILABLE, "the master is stopping");
    }
    let hold = tokio::time::sleep(WATCH_HOLD);
    tokio::pin!(hold);
    loop {
        tokio::select! {
            _ = &mut hold => return Json(json!({ "state": "open" })).into_response(),
            changed = changes.changed() => {
                if changed.is_err() || changes.borrow_and_update().stopping {
                    return error(StatusCode::SERVICE_UNAVAILABLE, "the master is stopping");
                }
                if state.sessions().get(&id).is_none() {
                    return ended();
                }
            }
        }
    }
}

async fn farm(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Some(refusal) = state.access.operator_refusal(&headers) {
        return refusal;
    }
    let sessions = state.sessions().len();
    let mut body = state.backend.farm_state().await;
    if let Some(object) = body.as_object_mut() {
        object.insert("sessions_open".into(), json!(sessions));
    }
    Json(body).into_response()
}

async fn metrics(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Some(refusal) = state.access.operator_refusal(&headers) {
        return refusal;
    }
    nephele_telemetry::metrics_response(&state.metrics.registry)
}

/// Ready to serve viewers: the farm's event loop answers, a composer is registered and at
/// least one render worker is. 503 with what is missing otherwise (load balancers and
/// Kubernetes' readiness probe take a viewer elsewhere meanwhile).
async fn readyz(State(state): State<Arc<AppState>>) -> Response {
    let farm = state.backend.farm_state().await;
    let workers = farm.get("workers").and_then(|w| w.as_array()).map_or(0, Vec::len);
    let composer = farm.get("composer").is_some_and(|c| !c.is_null());
    let mut missing = Vec::new();
    if !composer {
        missing.push("no composer has joined the farm");
    }
    if workers == 0 {
        missing.push("no render worker has joined the farm");
    }
    let status = if missing.is_empty() { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE };
    (status, Json(json!({ "ready": missing.is_empty(), "workers": workers, "composer": composer, "missing": missing })))
        .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::http::Request;
    use http_body_util::BodyExt;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    use tower::ServiceExt;

    #[derive(Default)]
    struct FakeFarm {
        refuse: AtomicBool,
        /// Workers and composer that `farm_state` reports.
        members: AtomicUsize,
        opened: AtomicUsize,
        closed: AtomicUsize,
    }

    impl FarmBackend for FakeFarm {
        fn scenes(&self) -> Vec<(String, SceneView)> {
            vec![("default".into(), SceneView { eye: [0.0, -4.0, 2.0], target: [0.0; 3], fov_y_deg: 40.0 })]
        }
        fn ice_servers(&self) -> serde_json::Value {
            json!([])
        }
        fn admission(&self) -> Admission {
            if self.refuse.load(Ordering::SeqCst) {
                Admission::Refuse { retry_after: Duration::from_millis(1500) }
            } else {
                Admission::Admit
            }
        }
        fn open(&self, _id: String, _request: SessionRequest, offer: String) -> BoxFuture<Result<String, OpenError>> {
            self.opened.fetch_add(1, Ordering::SeqCst);
            Box::pin(async move {
                if offer.contains("starve") {
                    Err(OpenError::Refused { retry_after: Duration::from_millis(2500) })
                } else if offer.contains("m=video") {
                    Ok("v=0 answer".to_string())
                } else {
                    Err(OpenError::BadOffer("no video section".into()))
                }
            })
        }
        fn close(&self, _id: String) -> BoxFuture<()> {
            self.closed.fetch_add(1, Ordering::SeqCst);
            Box::pin(async {})
        }
        fn farm_state(&self) -> BoxFuture<serde_json::Value> {
            // 0: empty farm; 1: a worker only; 2: a worker and a composer.
            let members = self.members.load(Ordering::SeqCst);
            let workers: Vec<serde_json::Value> = (0..members.min(1)).map(|i| json!({ "id": i })).collect();
            let composer = if members >= 2 { json!({ "id": 1 }) } else { serde_json::Value::Null };
            Box::pin(async move { json!({ "workers": workers, "composer": composer }) })
        }
    }

    fn app() -> (Router, Arc<FakeFarm>, Arc<AppState>) {
        let farm = Arc::new(FakeFarm::default());
        let state = AppState::new(farm.clone(), Arc::new(MasterMetrics::new()), Box::new(|| 0.0));
        (router(state.clone()), farm, state)
    }

    async fn call(app: &Router, request: Request<Body>) -> (StatusCode, HeaderMap, serde_json::Value) {
        let response = app.clone().oneshot(request).await.expect("infallible");
        let (parts, body) = response.into_parts();
        let bytes = body.collect().await.expect("body").to_bytes();
        let value = serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null);
        (parts.status, parts.headers, value)
    }

    fn post(body: &str) -> Request<Body> {
        Request::post("/v1/sessions")
            .header("content-type", "application/json")
            .body(Body::from(body.to_owned()))
            .expect("request")
    }

    const OFFER: &str = r#"{"sdp": "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 96\r\n", "scene": "default"}"#;

    /// Invitations (issue 15): none presented 401 (with `WWW-Authenticate`), a wrong,
    /// altered, expired or other-scene one 403, a valid one opens the session; the farm
    /// never sees the refused ones.
    #[tokio::test]
    async fn a_master_with_a_viewer_key_opens_sessions_only_for_valid_invitations() {
        use crate::access::{ANY_SCENE, ViewerKey};
        let farm = Arc::new(FakeFarm::default());
        let key = ViewerKey::new(b"the viewer key of the http test").expect("key");
        let policy = AccessPolicy { viewer_key: Some(key.clone()), ..AccessPolicy::default() };
        let state = AppState::with_access(farm.clone(), Arc::new(MasterMetrics::new()), Box::new(|| 0.0), policy);
        let app = router(state.clone());
        let with = |token: &str| {
            let mut request = post(OFFER);
            request
                .headers_mut()
                .insert(header::AUTHORIZATION, HeaderValue::from_str(&format!("Bearer {token}")).expect("header"));
            request
        };
        let (status, headers, body) = call(&app, post(OFFER)).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{body}");
        assert_eq!(headers.get(header::WWW_AUTHENTICATE).and_then(|v| v.to_str().ok()), Some("Bearer"));
        assert!(body["error"].as_str().is_some_and(|e| e.contains("invitation")), "{body}");
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).expect("clock").as_secs();
        let valid = key.invite("default", now + 3600);
        let other_key = ViewerKey::new(b"not the key of this master").expect("key");
        let refused = [
            ("garbage".to_string(), "malformed"),
            (other_key.invite("default", now + 3600), "signature"),
            (valid.replacen(&format!(".{}.", now + 3600), &format!(".{}.", now + 999_999), 1), "signature"),
            (key.invite("default", now - 5), "expired"),
            (key.invite("room-day", now + 3600), "scene"),
        ];
        for (token, why) in &refused {
            let (status, _, body) = call(&app, with(token)).await;
            assert_eq!(status, StatusCode::FORBIDDEN, "{token}: {body}");
            assert!(body["error"].as_str().is_some_and(|e| e.contains(why)), "{why}: {body}");
        }
        assert_eq!(farm.opened.load(Ordering::SeqCst), 0, "refused requests never reach the farm");
        let (status, _, body) = call(&app, with(&valid)).await;
        assert_eq!(status, StatusCode::CREATED, "{body}");
        let (status, _, body) = call(&app, with(&key.invite(ANY_SCENE, now + 60))).await;
        assert_eq!(status, StatusCode::CREATED, "{body}");
        let metrics = state.metrics.render();
        assert!(metrics.contains("nephele_master_sessions_denied_total 6"), "{metrics}");
    }

    /// The per-address rate limit (issue 15): a burst, then 429 with `Retry-After`; another
    /// address is not affected.
    #[tokio::test]
    async fn session_requests_over_the_rate_limit_get_429() {
        use axum::extract::ConnectInfo;
        let farm = Arc::new(FakeFarm::default());
        let policy = AccessPolicy { rate_limit: crate::access::RateLimiter::new(2, 6), ..AccessPolicy::default() };
        let state = AppState::with_access(farm.clone(), Arc::new(MasterMetrics::new()), Box::new(|| 0.0), policy);
        let app = router(state.clone());
        let from = |addr: &str| {
            let mut request = post(OFFER);
            request.extensions_mut().insert(ConnectInfo(ClientAddr(addr.parse().expect("addr"))));
            request
        };
        for _ in 0..2 {
            assert_eq!(call(&app, from("10.1.1.1:5000")).await.0, StatusCode::CREATED);
        }
        let (status, headers, body) = call(&app, from("10.1.1.1:5001")).await;
        assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{body}");
        assert_eq!(headers.get(header::RETRY_AFTER).and_then(|v| v.to_str().ok()), Some("10"));
        assert_eq!(call(&app, from("10.2.2.2:5000")).await.0, StatusCode::CREATED);
        assert_eq!(farm.opened.load(Ordering::SeqCst), 3);
        assert!(state.metrics.render().contains("nephele_master_sessions_rate_limited_total 1"));
    }

    /// The operator token (issue 15): the operators' endpoints answer 401 without it or with a
    /// wrong one, 200 with it; viewers' requests and the probes need none.
    #[tokio::test]
    async fn operators_endpoints_need_the_operator_token_when_one_is_set() {
        assert!(OperatorToken::new("too short").is_none());
        let token = "the operator token of the http test";
        let policy = AccessPolicy { operator_token: OperatorToken::new(token), ..AccessPolicy::default() };
        let farm = Arc::new(FakeFarm::default());
        farm.members.store(2, Ordering::SeqCst);
        let state = AppState::with_access(farm.clone(), Arc::new(MasterMetrics::new()), Box::new(|| 0.0), policy);
        let guarded = router(state);
        let get = |path: &str, bearer: Option<&str>| {
            let mut request = Request::get(path);
            if let Some(b) = bearer {
                request = request.header(header::AUTHORIZATION, format!("Bearer {b}"));
            }
            request.body(Body::empty()).expect("request")
        };
        for path in ["/v1/farm", "/metrics", "/v1/sessions"] {
            for bearer in [None, Some("the operator token of the http tesT"), Some("")] {
                let (status, headers, body) = call(&guarded, get(path, bearer)).await;
                assert_eq!(status, StatusCode::UNAUTHORIZED, "{path} {bearer:?}: {body}");
                assert_eq!(headers.get(header::WWW_AUTHENTICATE).and_then(|v| v.to_str().ok()), Some("Bearer"));
                assert!(body["error"].as_str().is_some_and(|e| e.contains("operator token")), "{body}");
            }
            let (status, _, _) = call(&guarded, get(path, Some(token))).await;
            assert_eq!(status, StatusCode::OK, "{path}");
        }
        for path in ["/livez", "/readyz", "/v1/config", "/"] {
            assert_eq!(call(&guarded, get(path, None)).await.0, StatusCode::OK, "{path}");
        }
        assert_eq!(call(&guarded, post(OFFER)).await.0, StatusCode::CREATED);
        // Without a token the endpoints are open, as before.
        let (open, _, _) = app();
        assert_eq!(call(&open, get("/v1/farm", None)).await.0, StatusCode::OK);
    }

    #[tokio::test]
    async fn ready_only_with_a_composer_and_a_worker() {
        let (app, farm, _) = app();
        let get = |path: &str| Request::get(path).body(Body::empty()).expect("request");
        let (status, _, _) = call(&app, get("/livez")).await;
        assert_eq!(status, StatusCode::OK);
        let (status, _, body) = call(&app, get("/readyz")).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
        assert_eq!(body["missing"].as_array().map(Vec::len), Some(2), "{body}");
        farm.members.store(1, Ordering::SeqCst);
        let (status, _, body) = call(&app, get("/readyz")).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
        assert_eq!(body["missing"][0], "no composer has joined the farm", "{body}");
        farm.members.store(2, Ordering::SeqCst);
        let (status, _, body) = call(&app, get("/readyz")).await;
        assert_eq!(status, StatusCode::OK, "{body}");
        assert_eq!((body["ready"].as_bool(), body["workers"].as_u64()), (Some(true), Some(1)), "{body}");
    }

    #[tokio::test]
    async fn session_lifecycle() {
        let (app, farm, state) = app();
        let (status, _, body) = call(&app, post(OFFER)).await;
        assert_eq!(status, StatusCode::CREATED, "{body}");
        assert_eq!(body["sdp"], "v=0 answer");
        assert_eq!(body["view"]["fov_y_deg"], 40.0);
        let id = body["session_id"].as_str().expect("id").to_owned();
        let token = body["token"].as_str().expect("token").to_owned();
        assert_eq!(state.sessions().len(), 1);
        let (status, _, farm_body) = call(&app, Request::get("/v1/farm").body(Body::empty()).expect("request")).await;
        assert_eq!((status, farm_body["sessions_open"].as_u64()), (StatusCode::OK, Some(1)));

        let del = |token: &str| {
            Request::delete(format!("/v1/sessions/{id}"))
                .header("authorization", format!("Bearer {token}"))
                .body(Body::empty())
                .expect("request")
        };
        assert_eq!(call(&app, del("wrong")).await.0, StatusCode::UNAUTHORIZED);
        assert_eq!(call(&app, del(&token)).await.0, StatusCode::NO_CONTENT);
        assert_eq!(call(&app, del(&token)).await.0, StatusCode::NOT_FOUND);
        assert_eq!((farm.opened.load(Ordering::SeqCst), farm.closed.load(Ordering::SeqCst)), (1, 1));
    }

    /// A watch answers "ended" as soon as the service ends its session (and for an unknown
    /// one), 401 without the token, 503 when the server stops, and holds otherwise.
    #[tokio::test]
    async fn a_watch_hears_at_once_that_the_service_ended_its_session() {
        let (app, _, state) = app();
        let open = |app: Router| async move {
            let (status, _, body) = call(&app, post(OFFER)).await;
            assert_eq!(status, StatusCode::CREATED, "{body}");
            (body["session_id"].as_str().expect("id").to_owned(), body["token"].as_str().expect("token").to_owned())
        };
        let watch = |id: &str, token: &str| {
            Request::get(format!("/v1/sessions/{id}/watch"))
                .header("authorization", format!("Bearer {token}"))
                .body(Body::empty())
                .expect("request")
        };
        let (id, token) = open(app.clone()).await;
        assert_eq!(call(&app, watch(&id, "wrong")).await.0, StatusCode::UNAUTHORIZED);
        let (status, _, body) = call(&app, watch("s99-000000", &token)).await;
        assert_eq!((status, body["state"].as_str()), (StatusCode::OK, Some("ended")), "{body}");
        let (other, other_token) = open(app.clone()).await;
        let pending = tokio::spawn({
            let app = app.clone();
            let request = watch(&id, &token);
            async move { call(&app, request).await }
        });
        let unaffected = tokio::spawn({
            let app = app.clone();
            let request = watch(&other, &other_token);
            async move { call(&app, request).await }
        });
        // Both hold while their sessions live (the hold is 25 s; nothing answers in 200 ms).
        tokio::time::sleep(Duration::from_millis(200)).await;
        assert!(!pending.is_finished() && !unaffected.is_finished());
        assert!(state.end_session(&id));
        let (status, _, body) =
            tokio::time::timeout(Duration::from_secs(10), pending).await.expect("answered").expect("task");
        assert_eq!((status, body["state"].as_str()), (StatusCode::OK, Some("ended")), "{body}");
        // The other session's watch is still holding; the server stopping releases it.
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert!(!unaffected.is_finished());
        state.stop_watches();
        let (status, _, _) =
            tokio::time::timeout(Duration::from_secs(10), unaffected).await.expect("answered").expect("task");
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        // A watch asked while the server stops is answered at once.
        let (status, _, _) = call(&app, watch(&other, &other_token)).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        // After its end the session is unknown: ended at once.
        let (status, _, body) = call(&app, watch(&id, &token)).await;
        assert_eq!((status, body["state"].as_str()), (StatusCode::OK, Some("ended")), "{body}");
    }

    #[tokio::test]
    async fn bad_requests_get_clear_errors() {
        let (app, farm, state) = app();
        let cases = [
            "not json",
            r#"{"scene": "default"}"#,
            r#"{"sdp": "hello", "scene": "default"}"#,
            r#"{"sdp": "v=0", "scene": "nowhere"}"#,
            r#"{"sdp": "v=0", "scene": "../../etc/passwd"}"#,
            r#"{"sdp": "v=0", "views": 0}"#,
            r#"{"sdp": "v=0", "width": 641}"#,
            r#"{"sdp": "v=0", "target_fps": -3}"#,
            r#"{"sdp": "v=0", "bogus": 1}"#,
        ];
        for case in cases {
            let (status, _, body) = call(&app, post(case)).await;
            assert_eq!(status, StatusCode::BAD_REQUEST, "{case}: {body}");
            assert!(body["error"].as_str().is_some_and(|e| !e.is_empty()), "{case}: {body}");
        }
        // An offer the composer rejects: 400, and the session is not left behind.
        let (status, _, body) = call(&app, post(r#"{"sdp": "v=0\r\n"}"#)).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
        assert!(state.sessions().is_empty());
        assert_eq!(farm.opened.load(Ordering::SeqCst), 1);
        let huge = format!(r#"{{"sdp": "v=0{}"}}"#, "a".repeat(MAX_SDP_BYTES));
        assert_eq!(call(&app, post(&huge)).await.0, StatusCode::BAD_REQUEST);
        let too_big = "x".repeat(MAX_BODY_BYTES + 1);
        assert_eq!(call(&app, post(&too_big)).await.0, StatusCode::PAYLOAD_TOO_LARGE);
    }

    #[tokio::test]
    async fn starved_farm_refuses_with_retry_after() {
        let (app, farm, state) = app();
        farm.refuse.store(true, Ordering::SeqCst);
        let (status, headers, body) = call(&app, post(OFFER)).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
        assert_eq!(headers.get(header::RETRY_AFTER).and_then(|v| v.to_str().ok()), Some("2"));
        assert!(state.sessions().is_empty());
        assert_eq!(farm.opened.load(Ordering::SeqCst), 0);
        // Refused by the scheduler itself (starvation began after the check): the same answer.
        farm.refuse.store(false, Ordering::SeqCst);
        let (status, headers, body) = call(&app, post(r#"{"sdp": "v=0\r\nm=video starve\r\n"}"#)).await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
        assert_eq!(headers.get(header::RETRY_AFTER).and_then(|v| v.to_str().ok()), Some("3"));
        assert!(state.sessions().is_empty());
        // Both refusals are counted for /metrics.
        let response = app
            .clone()
            .oneshot(Request::get("/metrics").body(Body::empty()).expect("request"))
            .await
            .expect("infallible");
        let text =
            String::from_utf8_lossy(&response.into_body().collect().await.expect("body").to_bytes()).into_owned();
        assert!(text.contains("nephele_master_admissions_refused_total 2"), "{text}");
        assert!(text.contains("route=\"/v1/sessions\",status=\"503\"} 2"), "{text}");
    }

    #[tokio::test]
    async fn serves_the_client() {
        let (app, _, _) = app();
        let response =
            app.clone().oneshot(Request::get("/").body(Body::empty()).expect("request")).await.expect("infallible");
        assert_eq!(response.status(), StatusCode::OK);
        assert_eq!(
            response.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()),
            Some("text/html; charset=utf-8")
        );
        let js = app
            .clone()
            .oneshot(Request::get("/client/nephele.js").body(Body::empty()).expect("request"))
            .await
            .expect("infallible");
        assert_eq!(js.status(), StatusCode::OK);
        let missing = app
            .clone()
            .oneshot(Request::get("/client/..%2FCargo.toml").body(Body::empty()).expect("request"))
            .await
            .expect("infallible");
        assert_eq!(missing.status(), StatusCode::NOT_FOUND);
        let (status, _, config) = call(&app, Request::get("/v1/config").body(Body::empty()).expect("request")).await;
        assert_eq!((status, config["scenes"][0].as_str()), (StatusCode::OK, Some("default")));
    }
}
