//! The worker's Prometheus metrics (prefix `nephele_worker_`) and its readiness, served on
//! the operations port (`nephele worker --ops ADDR`: `/livez`, `/readyz`, `/metrics`).

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

use nephele_proto::ErrorCode;
use nephele_telemetry::prometheus_client::metrics::counter::Counter;
use nephele_telemetry::prometheus_client::metrics::family::Family;
use nephele_telemetry::prometheus_client::metrics::gauge::Gauge;
use nephele_telemetry::prometheus_client::metrics::histogram::Histogram;
use nephele_telemetry::prometheus_client::registry::Registry;
use nephele_telemetry::{Probe, register};

/// Where the worker is in its life, for `/readyz`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Phase {
    Calibrating = 0,
    Connecting = 1,
    Registered = 2,
    Draining = 3,
}

#[derive(Debug)]
pub struct WorkerMetrics {
    registry: Arc<Registry>,
    phase: AtomicU8,
    pub(crate) registered: Gauge,
    pub(crate) batches_done: Counter,
    pub(crate) rays_done: Counter,
    pub(crate) batches_failed: Family<[(&'static str, String); 1], Counter>,
    pub(crate) queued_batches: Gauge,
    pub(crate) in_flight_batches: Gauge,
    pub(crate) render_ms: Histogram,
    pub(crate) deliver_ms: Histogram,
    pub(crate) master_connections: Counter,
    pub(crate) derived_pixels: Counter,
    pub(crate) derived_pixels_rendered: Counter,
    pub(crate) previous_frame_pixels: Counter,
    pub(crate) previous_frame_pixels_rendered: Counter,
    pub(crate) ahead_renders: Counter,
    pub(crate) ahead_declined: Counter,
    pub(crate) environment_samples: Counter,
    pub(crate) environment_samples_hidden: Counter,
}

impl WorkerMetrics {
    pub fn new() -> WorkerMetrics {
        let mut registry = Registry::with_prefix("nephele_worker");
        let registered = register(&mut registry, "registered", "1 while registered with the master", Gauge::default());
        let batches_done = register(
            &mut registry,
            "batches_done",
            "Batches rendered and delivered to their composer",
            Counter::default(),
        );
        let rays_done = register(&mut registry, "rays_done", "Rays (pixels) of the batches done", Counter::default());
        let batches_failed = register(
            &mut registry,
            "batches_failed",
            "Batches reported failed to the master, by reason (overloaded = refused, queue full)",
            Family::default(),
        );
        let queued_batches =
            register(&mut registry, "queued_batches", "Batches waiting for a render slot", Gauge::default());
        let in_flight_batches =
            register(&mut registry, "in_flight_batches", "Batches rendering or being delivered", Gauge::default());
        let render_ms = register(
            &mut registry,
            "render_ms",
            "Kernel time of one batch, ms",
            nephele_telemetry::latency_histogram_ms(),
        );
        let deliver_ms = register(
            &mut registry,
            "deliver_ms",
            "Sending one batch's result to its composer, ms",
            nephele_telemetry::latency_histogram_ms(),
        );
        let master_connections = register(
            &mut registry,
            "master_connections",
            "Registrations with the master (reconnections included)",
            Counter::default(),
        );
        let derived_pixels = register(
            &mut registry,
            "derived_pixels",
            "Pixels of derived views (adjacent views taken from a batch by reprojection)",
            Counter::default(),
        );
        let derived_pixels_rendered = register(
            &mut registry,
            "derived_pixels_rendered",
            "Pixels of derived views that reprojection could not vouch for, rendered by the kernel",
            Counter::default(),
        );
        let previous_frame_pixels = register(
            &mut registry,
            "previous_frame_pixels",
            "Pixels of batches taken from the worker's previous full render of the same view by reprojection",
            Counter::default(),
        );
        let previous_frame_pixels_rendered = register(
            &mut registry,
            "previous_frame_pixels_rendered",
            "Pixels of those batches that reprojection could not vouch for, rendered by the kernel",
            Counter::default(),
        );
        let ahead_renders = register(
            &mut registry,
            "ahead_renders",
            "Renders ahead of a session's next frames (the farm was idle), kept as its previous render",
            Counter::default(),
        );
        let ahead_declined = register(
            &mut registry,
            "ahead_declined",
            "Renders ahead not made: reuse of the asset measured dearer than rendering, or a whole-view kernel",
            Counter::default(),
        );
        let environment_samples = register(
            &mut registry,
            "environment_samples",
            "G-buffer samples an environment kernel traced (camera rays)",
            Counter::default(),
        );
        let environment_samples_hidden = register(
            &mut registry,
            "environment_samples_hidden",
            "Of those, samples an object's solid matter hides: traced for the G-buffer, not lit",
            Counter::default(),
        );
        WorkerMetrics {
            registry: Arc::new(registry),
            phase: AtomicU8::new(Phase::Calibrating as u8),
            registered,
            batches_done,
            rays_done,
            batches_failed,
            queued_batches,
            in_flight_batches,
            render_ms,
            deliver_ms,
            master_connections,
            derived_pixels,
            derived_pixels_rendered,
            previous_frame_pixels,
            previous_frame_pixels_rendered,
            ahead_renders,
            ahead_declined,
            environment_samples,
            environment_samples_hidden,
        }
    }

    pub fn registry(&self) -> &Arc<Registry> {
        &self.registry
    }

    pub fn phase(&self) -> Phase {
        match self.phase.load(Ordering::Relaxed) {
            0 => Phase::Calibrating,
            1 => Phase::Connecting,
            2 => Phase::Registered,
            _ => Phase::Draining,
        }
    }

    pub(crate) fn set_phase(&self, phase: Phase) {
        self.phase.store(phase as u8, Ordering::Relaxed);
        self.registered.set(i64::from(phase == Phase::Registered));
    }

    pub(crate) fn failed(&self, code: ErrorCode) {
        let reason = format!("{code:?}").to_lowercase();
        self.batches_failed.get_or_create(&[("reason", reason)]).inc();
    }
}

impl Default for WorkerMetrics {
    fn default() -> WorkerMetrics {
        WorkerMetrics::new()
    }
}

impl Probe for WorkerMetrics {
    fn missing(&self) -> Vec<String> {
        match self.phase() {
            Phase::Registered => Vec::new(),
            Phase::Calibrating => vec!["calibrating (a first render measures this worker's throughput)".into()],
            Phase::Connecting => vec!["not registered with the master".into()],
            Phase::Draining => vec!["draining: shutting down".into()],
        }
    }

    fn detail(&self) -> serde_json::Value {
        serde_json::json!({ "phase": format!("{:?}", self.phase()).to_lowercase() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readiness_follows_the_phase_and_failures_count_by_reason() {
        let metrics = WorkerMetrics::new();
        assert_eq!(metrics.missing().len(), 1);
        metrics.set_phase(Phase::Registered);
        assert!(metrics.missing().is_empty());
        assert_eq!(metrics.registered.get(), 1);
        metrics.set_phase(Phase::Draining);
        assert_eq!(metrics.registered.get(), 0);
        metrics.failed(ErrorCode::Overloaded);
        metrics.failed(ErrorCode::Overloaded);
        let text = nephele_telemetry::render(metrics.registry());
        assert!(text.contains("nephele_worker_batches_failed_total{reason=\"overloaded\"} 2"), "{text}");
    }
}
