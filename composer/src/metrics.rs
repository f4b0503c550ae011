//! The composer's Prometheus metrics (`GET /metrics`, prefix `nephele_composer_`): frames and
//! bytes sent, encoder and send errors, frames dropped because a viewer's media thread was
//! busy, each latency stage of sent frames as a histogram (the stages of
//! [`crate::latency::Stages`]), worker connections and wire errors; viewer sessions and the
//! master link as gauges read at scrape time.

use nephele_telemetry::prometheus_client::metrics::counter::Counter;
use nephele_telemetry::prometheus_client::metrics::family::Family;
use nephele_telemetry::prometheus_client::metrics::gauge::Gauge;
use nephele_telemetry::prometheus_client::metrics::histogram::Histogram;
use nephele_telemetry::prometheus_client::registry::Registry;
use nephele_telemetry::{HttpMetrics, register};

use crate::latency::Stages;

type StageLabels = [(&'static str, &'static str); 1];

#[derive(Debug)]
pub struct ComposerMetrics {
    pub(crate) registry: Registry,
    pub(crate) frames_sent: Counter,
    pub(crate) bytes_sent: Counter,
    pub(crate) frames_dropped_busy: Counter,
    pub(crate) bitrate_changes: Counter,
    pub(crate) encode_errors: Counter,
    pub(crate) send_errors: Counter,
    pub(crate) wire_errors: Counter,
    pub(crate) worker_connections: Counter,
    pub(crate) peers_unauthenticated: Counter,
    pub(crate) sessions: Gauge,
    pub(crate) media_threads: Gauge,
    pub(crate) peer_connections: Gauge,
    pub(crate) nack_resent: Counter,
    pub(crate) nack_refused: Counter,
    pub(crate) packets_paced: Counter,
    pub(crate) frames_skipped_for_rate: Counter,
    pub(crate) resolution_changes: Counter,
    pub(crate) frames_downscaled: Counter,
    pub(crate) pacing_wait_ms: Counter,
    pub(crate) master_linked: Gauge,
    pub(crate) results_after_release: Counter,
    pub(crate) held_tasks: Gauge,
    stage_ms: Family<StageLabels, Histogram, fn() -> Histogram>,
    pub(crate) http: HttpMetrics,
}

impl ComposerMetrics {
    pub fn new() -> ComposerMetrics {
        let mut registry = Registry::with_prefix("nephele_composer");
        let counter =
            |registry: &mut Registry, name: &str, help: &str| register(registry, name, help, Counter::default());
        let frames_sent = counter(&mut registry, "frames_sent", "Encoded frames sent to viewers");
        let bytes_sent = counter(&mut registry, "bytes_sent", "H.264 bytes sent to viewers");
        let frames_dropped_busy =
            counter(&mut registry, "frames_dropped_busy", "Fused frames dropped: the viewer's media thread was busy");
        let bitrate_changes = counter(
            &mut registry,
            "bitrate_changes",
            "Times a receiver's feedback (RTCP loss, REMB) moved a stream's bitrate",
        );
        let encode_errors = counter(&mut registry, "encode_errors", "Frames the encoder failed on");
        let send_errors = counter(&mut registry, "send_errors", "Frames that could not be sent");
        let wire_errors = counter(&mut registry, "wire_errors", "Malformed messages on the results listener");
        let worker_connections = counter(&mut registry, "worker_connections", "Worker connections accepted");
        let peers_unauthenticated = counter(
            &mut registry,
            "peers_unauthenticated",
            "Results connections refused for not proving the farm secret (their results never reach a frame)",
        );
        let sessions = register(&mut registry, "sessions", "Viewer sessions", Gauge::default());
        let media_threads = register(
            &mut registry,
            "media_threads",
            "Sessions' media threads (encoding and sending) still running; an ended session's is waited for",
            Gauge::default(),
        );
        let peer_connections = register(
            &mut registry,
            "peer_connections",
            "WebRTC peer connections not yet freed (above `sessions` for long after viewers leave: a leak)",
            Gauge::default(),
        );
        let nack_resent = counter(&mut registry, "nack_resent", "Packets resent on a viewer's NACK");
        let nack_refused = counter(
            &mut registry,
            "nack_refused",
            "NACKed packets not resent: older than 400 ms, resent already, unknown, or past the budget (a quarter of the stream)",
        );
        let frames_skipped_for_rate = counter(
            &mut registry,
            "frames_skipped_for_rate",
            "Frames left out because the stream sends one in several below its floor bitrate (a link narrower than the floor)",
        );
        let resolution_changes = counter(
            &mut registry,
            "resolution_changes",
            "Times a stream's resolution moved with its bitrate (half of each side per level, below 0.025 bits per pixel)",
        );
        let frames_downscaled = counter(
            &mut registry,
            "frames_downscaled",
            "Frames sent at a smaller resolution than fused (a narrow link)",
        );
        let packets_paced = counter(
            &mut registry,
            "packets_paced",
            "Video packets the pacer held back (a frame larger than 40 ms at 2.5 times the target bitrate)",
        );
        let pacing_wait_ms = counter(&mut registry, "pacing_wait_ms", "Summed wait of the paced packets, milliseconds");
        let master_linked = register(
            &mut registry,
            "master_linked",
            "1 while the link to the master is up (farm mode)",
            Gauge::default(),
        );
        let results_after_release = counter(
            &mut registry,
            "results_after_release",
            "Worker results dropped: their task was already released (late copies of re-issued batches)",
        );
        let held_tasks = register(
            &mut registry,
            "held_tasks",
            "Tasks whose results are held until the master releases them",
            Gauge::default(),
        );
        let stage_ms = register(
            &mut registry,
            "frame_stage_ms",
            "Latency of each stage of sent frames, ms (pose_to_sent, farm, render, results_wait, fusion, yuv, encode, send)",
            Family::new_with_constructor(nephele_telemetry::latency_histogram_ms as fn() -> Histogram),
        );
        let http = HttpMetrics::register(&mut registry);
        ComposerMetrics {
            registry,
            frames_sent,
            bytes_sent,
            frames_dropped_busy,
            bitrate_changes,
            encode_errors,
            send_errors,
            wire_errors,
            worker_connections,
            peers_unauthenticated,
            sessions,
            media_threads,
            peer_connections,
            nack_resent,
            nack_refused,
            packets_paced,
            frames_skipped_for_rate,
            resolution_changes,
            frames_downscaled,
            pacing_wait_ms,
            master_linked,
            results_after_release,
            held_tasks,
            stage_ms,
            http,
        }
    }

    /// Records the stages of one sent frame.
    pub(crate) fn frame_sent(&self, stages: &Stages) {
        let optional = [("pose_to_sent", stages.total), ("farm", stages.farm), ("render", stages.render)];
        for (stage, ms) in optional {
            if let Some(ms) = ms {
                self.stage_ms.get_or_create(&[("stage", stage)]).observe(ms);
            }
        }
        let always = [
            ("results_wait", stages.results_wait),
            ("fusion", stages.fusion),
            ("yuv", stages.yuv),
            ("encode", stages.encode),
            ("send", stages.send),
        ];
        for (stage, ms) in always {
            self.stage_ms.get_or_create(&[("stage", stage)]).observe(ms);
        }
    }

    /// The text `GET /metrics` answers.
    pub fn render(&self) -> String {
        nephele_telemetry::render(&self.registry)
    }
}

impl Default for ComposerMetrics {
    fn default() -> ComposerMetrics {
        ComposerMetrics::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_of_a_sent_frame_land_in_their_histograms() {
        let metrics = ComposerMetrics::new();
        metrics.frames_sent.inc();
        metrics.bytes_sent.inc_by(1500);
        let stages = Stages { total: Some(40.0), farm: None, render: Some(6.0), encode: 3.0, ..Stages::default() };
        metrics.frame_sent(&stages);
        let text = metrics.render();
        assert!(text.contains("nephele_composer_frames_sent_total 1"), "{text}");
        assert!(text.contains("nephele_composer_bytes_sent_total 1500"), "{text}");
        assert!(text.contains("nephele_composer_frame_stage_ms_count{stage=\"pose_to_sent\"} 1"), "{text}");
        assert!(text.contains("nephele_composer_frame_stage_ms_sum{stage=\"encode\"} 3.0"), "{text}");
        assert!(!text.contains("stage=\"farm\""), "a stage not measured is not observed: {text}");
    }
}
