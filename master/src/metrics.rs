//! The master's Prometheus metrics (`GET /metrics`, prefix `nephele_master_`).
//!
//! Two kinds: counters and histograms the farm's actor updates as things happen (links
//! joining and leaving, messages sent, scheduling-round time, pose-to-plan latency), and the
//! scheduler's own state, which the actor publishes a few times a second as a
//! [`FarmSnapshot`] and [`FarmCollector`] encodes at scrape time: its running counts (frames,
//! batches re-issued, sessions refused), the queue depth, each worker's load and each
//! session's frame rate against its target.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use nephele_scheduler::FarmSnapshot;
use nephele_telemetry::prometheus_client::collector::Collector;
use nephele_telemetry::prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use nephele_telemetry::prometheus_client::metrics::counter::{ConstCounter, Counter};
use nephele_telemetry::prometheus_client::metrics::gauge::ConstGauge;
use nephele_telemetry::prometheus_client::metrics::histogram::Histogram;
use nephele_telemetry::prometheus_client::registry::Registry;
use nephele_telemetry::{HttpMetrics, register};

/// Events on the farm's links, counted by the actor.
#[derive(Debug, Default)]
pub(crate) struct LinkCounters {
    pub workers_joined: Counter,
    pub workers_left: Counter,
    pub workers_lost: Counter,
    pub batches_sent: Counter,
    pub batches_unsendable: Counter,
    pub cancels_sent: Counter,
    pub plans_sent: Counter,
    pub releases_sent: Counter,
    pub poses_unknown_session: Counter,
    pub sessions_refused: Counter,
    pub sessions_ended_by_peer: Counter,
    pub stale_reports: Counter,
    pub peers_unauthenticated: Counter,
    pub sessions_denied: Counter,
    pub sessions_rate_limited: Counter,
    pub handshakes_failed: Counter,
    /// From the workers' `BatchDone` reports: rays their kernels traced, and those that hit.
    pub rays_traced: Counter,
    pub rays_hit: Counter,
    /// Of the environment's G-buffer samples, those the objects in front hide (not lit).
    pub samples_hidden: Counter,
}

impl LinkCounters {
    fn register(&self, registry: &mut Registry) {
        let entries: [(&str, &str, &Counter); 19] = [
            ("workers_joined", "Workers that registered", &self.workers_joined),
            ("workers_left", "Worker links that closed", &self.workers_left),
            ("workers_lost", "Workers dropped for missing their heartbeats", &self.workers_lost),
            ("batches_sent", "Ray batches written to worker links (re-issues included)", &self.batches_sent),
            ("batches_unsendable", "Batches whose worker link was already gone", &self.batches_unsendable),
            ("cancels_sent", "Batch cancellations sent to workers", &self.cancels_sent),
            ("plans_sent", "Frame plans sent to the composer", &self.plans_sent),
            ("releases_sent", "Frame releases sent to the composer", &self.releases_sent),
            ("poses_unknown_session", "Poses for sessions the master does not know", &self.poses_unknown_session),
            (
                "admissions_refused",
                "Session offers answered 503 + Retry-After by admission control (each retry counts)",
                &self.sessions_refused,
            ),
            ("sessions_ended_by_peer", "Sessions the composer ended (viewer gone)", &self.sessions_ended_by_peer),
            ("stale_reports", "Worker reports for batches no longer in flight", &self.stale_reports),
            (
                "rays_traced",
                "Rays the workers' kernels traced, from their batch reports (pixels taken by reprojection excluded)",
                &self.rays_traced,
            ),
            (
                "rays_hit",
                "Of those rays, the ones that hit their object (the rest cost a march for nothing)",
                &self.rays_hit,
            ),
            (
                "samples_hidden",
                "Environment G-buffer samples the objects' solid matter hides: traced, not lit (issue 13)",
                &self.samples_hidden,
            ),
            (
                "farm_peers_unauthenticated",
                "Farm connections refused for not proving the farm secret (none, or a wrong one)",
                &self.peers_unauthenticated,
            ),
            (
                "sessions_denied",
                "Session requests refused for lacking a valid invitation (401 or 403)",
                &self.sessions_denied,
            ),
            (
                "sessions_rate_limited",
                "Session requests refused by the per-address rate limit (429)",
                &self.sessions_rate_limited,
            ),
            (
                "farm_handshakes_failed",
                "Farm connections that failed their opening otherwise (wrong role or version, garbage, timeout)",
                &self.handshakes_failed,
            ),
        ];
        for (name, help, counter) in entries {
            registry.register(name, help, counter.clone());
        }
    }
}

/// What the actor publishes for [`FarmCollector`]: the scheduler's snapshot and the names
/// behind its ids.
#[derive(Debug, Default)]
pub(crate) struct Published {
    pub snapshot: Option<FarmSnapshot>,
    pub worker_names: BTreeMap<u32, String>,
    pub session_names: BTreeMap<u64, String>,
    pub composer_linked: bool,
}

/// Encodes the latest [`Published`] state on each scrape.
#[derive(Debug, Clone, Default)]
pub(crate) struct FarmCollector {
    pub published: Arc<Mutex<Published>>,
}

fn counter(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: u64) -> Result<(), std::fmt::Error> {
    let metric = ConstCounter::new(value);
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

fn gauge(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: f64) -> Result<(), std::fmt::Error> {
    let metric = ConstGauge::new(value);
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

/// One gauge family, one labelled value per row.
fn gauge_family(
    encoder: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    label: &'static str,
    rows: &[(String, f64)],
) -> Result<(), std::fmt::Error> {
    if rows.is_empty() {
        return Ok(());
    }
    let mut family = encoder.encode_descriptor(name, help, None, ConstGauge::new(0.0).metric_type())?;
    for (value_label, value) in rows {
        let labels = [(label, value_label.as_str())];
        ConstGauge::new(*value).encode(family.encode_family(&labels)?)?;
    }
    Ok(())
}

impl Collector for FarmCollector {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let published = self.published.lock().unwrap_or_else(|p| p.into_inner());
        let e = &mut encoder;
        gauge(
            e,
            "composer_linked",
            "1 while a composer is in the farm",
            f64::from(u8::from(published.composer_linked)),
        )?;
        gauge(e, "workers", "Workers in the farm", published.worker_names.len() as f64)?;
        let Some(snapshot) = &published.snapshot else { return Ok(()) };
        let s = &snapshot.stats;
        let counts = [
            ("scheduler_rounds", "Scheduling rounds", s.rounds),
            ("scheduler_starved_rounds", "Rounds in which at least one user was starved", s.starved_rounds),
            ("sessions_opened", "Sessions the scheduler admitted", s.sessions_opened),
            (
                "scheduler_sessions_refused",
                "Session opens the scheduler itself refused (a user became starved after the HTTP check, or the farm's capacity)",
                s.sessions_refused,
            ),
            (
                "scheduler_sessions_refused_capacity",
                "Of those, refused because the asked work would pass the share of the measured throughput set by --admit-up-to",
                s.sessions_refused_capacity,
            ),
            ("sessions_closed", "Sessions closed", s.sessions_closed),
            ("frames_released", "Frames released to the composer", s.frames_released),
            ("frames_completed", "Frames whose every batch came back", s.frames_completed),
            ("frames_on_time", "Frames completed within 1/FPS of their release", s.frames_on_time),
            ("frames_dropped", "Frames superseded or given up", s.frames_dropped),
            ("tasks_created", "Ray tasks created", s.tasks_created),
            ("shared_joins", "Views that joined a live task (rendered once, fanned out)", s.shared_joins),
            ("history_hits", "Views served from the history table", s.history_hits),
            ("ahead_tasks", "Views rendered ahead of their frames while the farm was idle", s.ahead_tasks),
            ("ahead_rays", "Rays of the views rendered ahead", s.ahead_rays),
            (
                "ahead_views_covered",
                "Predicted views left to a render ahead of another user's view near them",
                s.ahead_views_covered,
            ),
            ("rays_requested", "Rays the frames asked for", s.rays_requested),
            ("rays_dispatched", "Rays sent to workers, re-issues included", s.rays_dispatched),
            ("rays_completed", "Rays of batches that came back", s.rays_completed),
            ("batches_dispatched", "Batches dispatched, re-issues included", s.batches_dispatched),
            ("batches_completed", "Batches that came back", s.batches_completed),
            (
                "batches_reissued",
                "Batches sent again after a worker was lost, failed or missed its deadline",
                s.batches_reissued,
            ),
            ("batches_timed_out", "Batches that missed their deadline", s.batches_timed_out),
            (
                "deadlines_stretched",
                "Missed deadlines extended instead of re-issued (no other worker idle)",
                s.deadlines_stretched,
            ),
            ("batches_failed", "Batches a worker reported as failed", s.batches_failed),
        ];
        for (name, help, value) in counts {
            counter(e, name, help, value)?;
        }
        counter(e, "scheduler_workers_lost", "Workers the scheduler lost (link gone or silent)", s.workers_lost)?;
        gauge(e, "admission_open", "1 while new sessions are admitted", f64::from(u8::from(snapshot.admission_open)))?;
        gauge(e, "sessions", "Sessions the scheduler serves", snapshot.sessions.len() as f64)?;
        gauge(
            e,
            "starved_sessions",
            "Sessions below their frame rate (NEPHELE Algorithm 1)",
            snapshot.starved_sessions as f64,
        )?;
        gauge(e, "capacity_rays_per_second", "Sum of the workers' measured throughputs", snapshot.capacity_rays_per_s)?;
        let q = &snapshot.queues;
        gauge(e, "queue_pending_batches", "Batches waiting for a worker (queue depth)", q.pending_batches as f64)?;
        gauge(e, "queue_in_flight_batches", "Batches on workers", q.in_flight_batches as f64)?;
        gauge(e, "queue_pending_work_rays", "Pending rays weighted by cost per ray", q.pending_work_rays)?;
        gauge(e, "live_tasks", "Tasks not finished yet", q.live_tasks as f64)?;

        let worker_name = |id: u32| published.worker_names.get(&id).cloned().unwrap_or_else(|| format!("worker-{id}"));
        let rows = |f: &dyn Fn(&nephele_scheduler::snapshot::WorkerSnapshot) -> f64| -> Vec<(String, f64)> {
            snapshot.workers.iter().map(|w| (worker_name(w.id.0), f(w))).collect()
        };
        gauge_family(
            e,
            "worker_backlog_ms",
            "Estimated work queued on each worker, ms",
            "worker",
            &rows(&|w| w.backlog_ms),
        )?;
        gauge_family(
            e,
            "worker_in_flight_batches",
            "Batches on each worker",
            "worker",
            &rows(&|w| w.in_flight_batches as f64),
        )?;
        gauge_family(
            e,
            "worker_rays_per_second",
            "Each worker's measured throughput",
            "worker",
            &rows(&|w| w.measured_rays_per_s),
        )?;

        let session_name = |id: u64| published.session_names.get(&id).cloned().unwrap_or_else(|| format!("s{id}"));
        let sessions = |f: &dyn Fn(&nephele_scheduler::snapshot::SessionSnapshot) -> f64| -> Vec<(String, f64)> {
            snapshot.sessions.iter().map(|s| (session_name(s.id.0), f(s))).collect()
        };
        gauge_family(
            e,
            "session_target_fps",
            "Each session's target frame rate",
            "session",
            &sessions(&|s| s.target_fps),
        )?;
        gauge_family(
            e,
            "session_fps",
            "Each session's completed-frame rate (moving average)",
            "session",
            &sessions(&|s| s.achieved_fps.unwrap_or(0.0)),
        )?;
        gauge_family(
            e,
            "session_fps_attainment",
            "Completed-frame rate over target frame rate, per session (1 = on target)",
            "session",
            &sessions(&|s| if s.target_fps > 0.0 { s.achieved_fps.unwrap_or(0.0) / s.target_fps } else { 0.0 }),
        )?;
        Ok(())
    }
}

/// Everything the master measures; `registry` is what `GET /metrics` renders.
#[derive(Debug)]
pub struct MasterMetrics {
    pub(crate) registry: Arc<Registry>,
    pub(crate) links: Arc<LinkCounters>,
    pub(crate) round_ms: Histogram,
    pub(crate) pose_to_plan_ms: Histogram,
    pub(crate) farm: FarmCollector,
    pub(crate) http: HttpMetrics,
}

impl MasterMetrics {
    pub fn new() -> MasterMetrics {
        let mut registry = Registry::with_prefix("nephele_master");
        let links = Arc::new(LinkCounters::default());
        links.register(&mut registry);
        let round_ms = register(
            &mut registry,
            "round_ms",
            "Time of one scheduling round (tick and its actions), ms",
            nephele_telemetry::latency_histogram_ms(),
        );
        let pose_to_plan_ms = register(
            &mut registry,
            "pose_to_plan_ms",
            "From a viewer's pose reaching the master to its frame plan leaving, ms",
            nephele_telemetry::latency_histogram_ms(),
        );
        let farm = FarmCollector::default();
        registry.register_collector(Box::new(farm.clone()));
        let http = HttpMetrics::register(&mut registry);
        MasterMetrics { registry: Arc::new(registry), links, round_ms, pose_to_plan_ms, farm, http }
    }

    /// The text `GET /metrics` answers.
    pub fn render(&self) -> String {
        nephele_telemetry::render(&self.registry)
    }
}

impl Default for MasterMetrics {
    fn default() -> MasterMetrics {
        MasterMetrics::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nephele_scheduler::{Scheduler, SchedulerConfig, WorkerId};
    use nephele_telemetry::prometheus_client::encoding::text::encode;

    fn value_of(text: &str, series: &str) -> Option<f64> {
        text.lines().find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
    }

    #[test]
    fn the_published_scheduler_state_is_scraped_with_names_for_ids() {
        let metrics = MasterMetrics::new();
        let before = metrics.render();
        assert_eq!(value_of(&before, "nephele_master_workers"), Some(0.0), "{before}");
        assert!(!before.contains("batches_reissued"), "nothing published yet: {before}");

        let mut scheduler = Scheduler::new(SchedulerConfig::default()).expect("scheduler");
        let now = nephele_scheduler::Time::ZERO;
        scheduler.add_worker(WorkerId(7), 2e6, now).expect("worker");
        metrics.links.workers_joined.inc();
        metrics.round_ms.observe(0.3);
        *metrics.farm.published.lock().expect("lock") = Published {
            snapshot: Some(scheduler.snapshot(now)),
            worker_names: BTreeMap::from([(7, "gpu-box".to_string())]),
            session_names: BTreeMap::new(),
            composer_linked: true,
        };
        let mut text = String::new();
        encode(&mut text, &metrics.registry).expect("encode");
        assert_eq!(value_of(&text, "nephele_master_workers"), Some(1.0), "{text}");
        assert_eq!(value_of(&text, "nephele_master_composer_linked"), Some(1.0), "{text}");
        assert_eq!(value_of(&text, "nephele_master_batches_reissued_total"), Some(0.0), "{text}");
        assert_eq!(value_of(&text, "nephele_master_workers_joined_total"), Some(1.0), "{text}");
        assert_eq!(value_of(&text, "nephele_master_admission_open"), Some(1.0), "{text}");
        assert_eq!(value_of(&text, "nephele_master_worker_rays_per_second{worker=\"gpu-box\"}"), Some(2e6), "{text}");
        assert_eq!(value_of(&text, "nephele_master_round_ms_count"), Some(1.0), "{text}");
        // Every family is declared once (a collector that repeated a name would break scrapes).
        let mut names: Vec<&str> = text.lines().filter_map(|l| l.strip_prefix("# TYPE ")?.split(' ').next()).collect();
        let declared = names.len();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), declared, "{text}");
    }
}
