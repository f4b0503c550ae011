//! `nephele-sim`: a deterministic discrete-event simulator of the render farm.
//!
//! Depends on `nephele-scheduler` and `nephele-geometry`; never on a service or a kernel.
//!
//! Simulated workers (throughput, jitter, failures, stragglers) and users (arrival,
//! departure, target FPS, objects, a camera path) drive the very scheduler core the live
//! master runs ([`nephele_scheduler::Scheduler`]), under NEPHELE's policy or a baseline behind
//! the same interface, and the run is measured: FPS attainment, frame latency, worker
//! utilisation, rays rendered against requested (sharing), refusals, Jain's fairness index.
//! Same scenario and seed, same numbers. CSV input and output live here, not in the core.

pub mod csv;
pub mod model;
pub mod report;
pub mod scenarios;
pub mod sim;

pub use model::{CameraPath, Detect, Scenario, SimObject, SimParams, SimUser, SimWorker, ViewMode};
pub use report::{Report, Summary, UserMetrics};
pub use sim::{SimError, Variant, run};

/// A scenario from CSV files: `trace` (user sessions, see [`csv::TRACE_FORMAT`]) and
/// optionally `workers` (the farm, [`csv::WORKERS_FORMAT`]; default: 8 workers of 1e8 rays/s).
pub fn scenario_from_csv(
    name: &str,
    trace: (&str, &str),
    workers: Option<(&str, &str)>,
    params: SimParams,
) -> Result<Scenario, csv::CsvError> {
    let (objects, users) = csv::parse_trace(trace.0, trace.1)?;
    let workers = match workers {
        Some((text, file)) => csv::parse_workers(text, file)?,
        None => (1..=8).map(|i| SimWorker::new(&format!("w{i}"), 1e8)).collect(),
    };
    Ok(Scenario { name: name.to_string(), description: format!("trace {}", trace.1), objects, users, workers, params })
}
