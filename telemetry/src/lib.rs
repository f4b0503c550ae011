//! Operations endpoints shared by every Nephele process: Prometheus metrics through
//! `prometheus-client` (one [`Registry`] per service, no global state, so several services
//! in one test process keep their numbers apart), and the same `/livez`, `/readyz` and
//! `/metrics` on the master, the composer and the workers.
//!
//! * `GET /metrics`: the registry in the OpenMetrics text format (Prometheus scrapes it).
//! * `GET /livez`: 200 while the process serves at all.
//! * `GET /readyz`: 200 `{"ready": true, ...}` when the process can do its job, else 503 with
//!   `"missing": [...]` saying what it waits for.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Instant;

use axum::Router;
use axum::extract::{MatchedPath, Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use tracing::Instrument;

pub use prometheus_client;

/// `Content-Type` of [`render`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Latency buckets in milliseconds shared by every latency histogram: 0.25 ms doubling to
/// about 4 s (15 buckets), wide enough for a 1 ms scheduling round and a 2 s stalled frame.
pub fn latency_buckets_ms() -> impl Iterator<Item = f64> {
    exponential_buckets(0.25, 2.0, 15)
}

/// A histogram over [`latency_buckets_ms`].
pub fn latency_histogram_ms() -> Histogram {
    Histogram::new(latency_buckets_ms())
}

/// Registers `metric` under `name` in `registry` and returns it: the registry holds a clone
/// sharing the same value, the caller keeps the handle it updates.
pub fn register<M>(registry: &mut Registry, name: &str, help: &str, metric: M) -> M
where
    M: prometheus_client::registry::Metric + Clone,
{
    registry.register(name, help, metric.clone());
    metric
}

/// The registry in the OpenMetrics text format.
pub fn render(registry: &Registry) -> String {
    let mut text = String::new();
    if let Err(e) = prometheus_client::encoding::text::encode(&mut text, registry) {
        // Only a collector's own formatting can fail; say so in the scrape rather than
        // answering with half a page.
        tracing::warn!("encoding the metrics failed: {e}");
        text = format!("# encoding the metrics failed: {e}\n# EOF\n");
    }
    text
}

/// `GET /metrics` as a response.
pub fn metrics_response(registry: &Registry) -> Response {
    ([(header::CONTENT_TYPE, CONTENT_TYPE)], render(registry)).into_response()
}

/// `GET /readyz` as a response: 200 when nothing is missing, else 503; `detail` is merged
/// into the JSON body.
pub fn readiness_response(missing: &[String], detail: serde_json::Value) -> Response {
    let ready = missing.is_empty();
    let mut body = serde_json::json!({ "ready": ready, "missing": missing });
    if let (Some(body), serde_json::Value::Object(detail)) = (body.as_object_mut(), detail) {
        body.extend(detail);
    }
    let status = if ready { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE };
    (status, axum::Json(body)).into_response()
}

/// The operators' bearer token (at least 16 bytes), opt-in on every process: with one, the
/// operators' endpoints (`/metrics`; the master's `/v1/farm` and `GET /v1/sessions`, a
/// composer's `GET /v1/sessions`) answer 401 unless the request carries `Authorization:
/// Bearer TOKEN`; the probes (`/livez`, `/readyz`) stay open for orchestrators. Only its
/// SHA-256 is kept, and presented tokens are compared by digest, so the comparison's timing
/// says nothing about the token.
#[derive(Clone, PartialEq, Eq)]
pub struct OperatorToken([u8; 32]);

impl std::fmt::Debug for OperatorToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("OperatorToken(..)")
    }
}

impl OperatorToken {
    /// `None` when shorter than 16 bytes.
    pub fn new(token: &str) -> Option<OperatorToken> {
        use sha2::Digest;
        (token.len() >= 16).then(|| OperatorToken(sha2::Sha256::digest(token.as_bytes()).into()))
    }

    /// Whether `presented` (the bearer token of a request, if any) is this token.
    pub fn admits(&self, presented: Option<&str>) -> bool {
        use sha2::Digest;
        presented.is_some_and(|p| <[u8; 32]>::from(sha2::Sha256::digest(p.as_bytes())) == self.0)
    }
}

/// The token of an `Authorization: Bearer TOKEN` header, if any.
pub fn bearer(headers: &axum::http::HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "))
}

/// `None` when `headers` may read an operators' endpoint guarded by `token` (always, without
/// one), else the 401 (`WWW-Authenticate: Bearer`, a JSON error naming the token) to answer.
pub fn operator_refusal(token: Option<&OperatorToken>, headers: &axum::http::HeaderMap) -> Option<Response> {
    let token = token?;
    let presented = bearer(headers).map(str::trim);
    if token.admits(presented) {
        return None;
    }
    tracing::debug!(present = presented.is_some(), "operators' endpoint refused: no or a wrong operator token");
    let body = serde_json::json!({
        "error": "this endpoint is for the service's operators: send Authorization: Bearer with the operator token"
    });
    let mut response = (StatusCode::UNAUTHORIZED, axum::Json(body)).into_response();
    response.headers_mut().insert(header::WWW_AUTHENTICATE, axum::http::HeaderValue::from_static("Bearer"));
    Some(response)
}

/// What a process without an HTTP API of its own (a worker) serves on its operations port.
pub trait Probe: Send + Sync + 'static {
    /// What the process still waits for before it can do its job; empty when ready.
    fn missing(&self) -> Vec<String>;
    /// Extra fields for the `/readyz` body.
    fn detail(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}

struct OpsState {
    registry: Arc<Registry>,
    probe: Arc<dyn Probe>,
    token: Option<OperatorToken>,
}

/// `/livez`, `/readyz` and `/metrics` for a process whose readiness `probe` tells; with a
/// `token`, `/metrics` asks for it ([`operator_refusal`]).
pub fn ops_router(registry: Arc<Registry>, probe: Arc<dyn Probe>, token: Option<OperatorToken>) -> Router {
    Router::new()
        .route("/livez", get(|| async { "ok" }))
        .route("/readyz", get(ops_readyz))
        .route("/metrics", get(ops_metrics))
        .with_state(Arc::new(OpsState { registry, probe, token }))
}

async fn ops_readyz(State(state): State<Arc<OpsState>>) -> Response {
    readiness_response(&state.probe.missing(), state.probe.detail())
}

async fn ops_metrics(State(state): State<Arc<OpsState>>, headers: axum::http::HeaderMap) -> Response {
    if let Some(refusal) = operator_refusal(state.token.as_ref(), &headers) {
        return refusal;
    }
    metrics_response(&state.registry)
}

type HttpLabels = Vec<(&'static str, String)>;

/// Request tracing and metrics for an HTTP API: a `http` span per request (method, route),
/// a debug event with its status and duration, and `http_requests` / `http_request_ms`
/// by method, route and status. Add it with [`HttpMetrics::layer`].
#[derive(Debug, Clone)]
pub struct HttpMetrics {
    requests: Family<HttpLabels, Counter>,
    duration_ms: Family<HttpLabels, Histogram, fn() -> Histogram>,
}

impl HttpMetrics {
    /// Registers the two families in `registry`.
    pub fn register(registry: &mut Registry) -> HttpMetrics {
        HttpMetrics {
            requests: register(
                registry,
                "http_requests",
                "HTTP requests answered, by method, route and status",
                Family::default(),
            ),
            duration_ms: register(
                registry,
                "http_request_ms",
                "HTTP request duration, ms, by method and route",
                Family::new_with_constructor(latency_histogram_ms as fn() -> Histogram),
            ),
        }
    }

    /// Wraps every route of `router` (routes added later are not tracked).
    pub fn layer<S: Clone + Send + Sync + 'static>(&self, router: Router<S>) -> Router<S> {
        router.route_layer(axum::middleware::from_fn_with_state(self.clone(), track_request))
    }
}

async fn track_request(State(metrics): State<HttpMetrics>, request: Request, next: Next) -> Response {
    let method = request.method().as_str().to_owned();
    let route =
        request.extensions().get::<MatchedPath>().map_or_else(|| "unmatched".to_owned(), |p| p.as_str().to_owned());
    let span = tracing::info_span!("http", method = %method, route = %route);
    let started = Instant::now();
    let response = next.run(request).instrument(span.clone()).await;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let status = response.status().as_u16();
    span.in_scope(|| tracing::debug!(status, ms, "request answered"));
    metrics.duration_ms.get_or_create(&vec![("method", method.clone()), ("route", route.clone())]).observe(ms);
    metrics.requests.get_or_create(&vec![("method", method), ("route", route), ("status", status.to_string())]).inc();
    response
}

/// Binds `addr` and serves `router` until `shutdown` resolves. Returns the bound address
/// (port 0 picks one) and the server's task.
pub async fn serve<F>(
    addr: SocketAddr,
    router: Router,
    shutdown: F,
) -> std::io::Result<(SocketAddr, tokio::task::JoinHandle<()>)>
where
    F: Future<Output = ()> + Send + 'static,
{
    let listener = tokio::net::TcpListener::bind(addr).await?;
    let bound = listener.local_addr()?;
    let task = tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, router).with_graceful_shutdown(shutdown).await {
            tracing::warn!(%bound, "the operations endpoint failed: {e}");
        }
    });
    Ok((bound, task))
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::http::Request;
    use http_body_util::BodyExt;
    use std::sync::atomic::{AtomicBool, Ordering};
    use tower::ServiceExt;

    struct Flag(AtomicBool);

    impl Probe for Flag {
        fn missing(&self) -> Vec<String> {
            if self.0.load(Ordering::Relaxed) { Vec::new() } else { vec!["not registered with the master".into()] }
        }
    }

    async fn get_text(router: &Router, path: &str) -> (StatusCode, String) {
        let response =
            router.clone().oneshot(Request::get(path).body(Body::empty()).expect("request")).await.expect("response");
        let status = response.status();
        let body = response.into_body().collect().await.expect("body").to_bytes();
        (status, String::from_utf8_lossy(&body).into_owned())
    }

    #[tokio::test]
    async fn ops_endpoints_answer_what_the_probe_and_registry_say() {
        let mut registry = Registry::with_prefix("nephele_worker");
        let batches = Counter::<u64>::default();
        registry.register("batches", "Batches rendered", batches.clone());
        let histogram = latency_histogram_ms();
        registry.register("render_ms", "Render time", histogram.clone());
        batches.inc_by(3);
        histogram.observe(1.0);
        let probe = Arc::new(Flag(AtomicBool::new(false)));
        let registry = Arc::new(registry);
        let router = ops_router(registry.clone(), probe.clone(), None);

        let (status, body) = get_text(&router, "/readyz").await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        assert!(body.contains("not registered with the master"), "{body}");
        probe.0.store(true, Ordering::Relaxed);
        let (status, body) = get_text(&router, "/readyz").await;
        assert_eq!((status, body.contains("\"ready\":true")), (StatusCode::OK, true), "{body}");
        assert_eq!(get_text(&router, "/livez").await.0, StatusCode::OK);

        let (status, body) = get_text(&router, "/metrics").await;
        assert_eq!(status, StatusCode::OK);
        assert!(body.contains("nephele_worker_batches_total 3"), "{body}");
        assert!(body.contains("nephele_worker_render_ms_bucket{le=\"1.0\"} 1"), "{body}");
        assert!(body.trim_end().ends_with("# EOF"), "{body}");

        // With an operators' token, /metrics asks for it; the probes stay open.
        let token = "the operators' token, long enough";
        assert!(OperatorToken::new("too short").is_none());
        let guarded = ops_router(registry, probe, OperatorToken::new(token));
        let get_with = |authorization: Option<String>| {
            let guarded = guarded.clone();
            async move {
                let mut request = Request::get("/metrics");
                if let Some(value) = authorization {
                    request = request.header(header::AUTHORIZATION, value);
                }
                guarded.oneshot(request.body(Body::empty()).expect("request")).await.expect("response")
            }
        };
        let refused = get_with(None).await;
        assert_eq!(refused.status(), StatusCode::UNAUTHORIZED);
        assert_eq!(refused.headers()[header::WWW_AUTHENTICATE], "Bearer");
        for wrong in ["Bearer not the operators' token", "Bearer ", "Basic abc", token] {
            assert_eq!(get_with(Some(wrong.into())).await.status(), StatusCode::UNAUTHORIZED, "{wrong}");
        }
        assert_eq!(get_with(Some(format!("Bearer {token}"))).await.status(), StatusCode::OK);
        assert_eq!(get_text(&guarded, "/readyz").await.0, StatusCode::OK);
        assert_eq!(get_text(&guarded, "/livez").await.0, StatusCode::OK);
    }

    #[tokio::test]
    async fn http_requests_are_counted_by_route_and_status() {
        let mut registry = Registry::default();
        let http = HttpMetrics::register(&mut registry);
        let router = http.layer(
            Router::new()
                .route("/v1/sessions/{id}", get(|| async { (StatusCode::NOT_FOUND, "no such session") }))
                .route("/livez", get(|| async { "ok" })),
        );
        get_text(&router, "/v1/sessions/abc").await;
        get_text(&router, "/v1/sessions/def").await;
        get_text(&router, "/livez").await;
        let text = render(&registry);
        assert!(
            text.contains("http_requests_total{method=\"GET\",route=\"/v1/sessions/{id}\",status=\"404\"} 2"),
            "{text}"
        );
        assert!(text.contains("http_requests_total{method=\"GET\",route=\"/livez\",status=\"200\"} 1"), "{text}");
        assert!(text.contains("http_request_ms_count{method=\"GET\",route=\"/livez\"} 1"), "{text}");
    }

    #[test]
    fn latency_buckets_span_a_round_to_a_stalled_frame() {
        let buckets: Vec<f64> = latency_buckets_ms().collect();
        assert_eq!(buckets.first(), Some(&0.25));
        assert!(buckets.last().is_some_and(|&b| b >= 2000.0), "{buckets:?}");
    }
}
