//! The discrete-event engine: simulated workers and users driving the scheduler core.
//!
//! Time is explicit ([`Time`], microseconds): events sit in a priority queue and the clock
//! jumps from one to the next, so a minute of farm time costs only the events it holds. After
//! the events of each instant the core's [`Scheduler::tick`] runs once, and its actions are
//! carried out: dispatches start (or queue) on simulated workers, cancels abort them, frame
//! completions are recorded per user. Between events the engine also wakes the core at its
//! [`Scheduler::next_wakeup`] (frame releases, deadlines, heartbeat timeouts).

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::time::Duration;

use nephele_geometry::camera::CameraError;
use nephele_scheduler::{
    Action, BatchId, ObjectId, ObjectInfo, Policy, SchedError, Scheduler, SchedulerConfig, SessionId, SessionSpec,
    Time, WorkerId,
};

use crate::model::{Detect, Rng, Scenario, SimUser, SimWorker};
use crate::report::{Report, Summary, UserMetrics};

/// A scheduling policy under test: a label and the core's configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct Variant {
    pub label: String,
    pub config: SchedulerConfig,
}

impl Variant {
    pub fn of(policy: Policy) -> Variant {
        Variant { label: policy.name().to_string(), config: SchedulerConfig::for_policy(policy) }
    }

    /// NEPHELE with sharing, derived views and the history table off: what ordering,
    /// admission and Heavy/Light placement achieve alone.
    pub fn nephele_without_sharing() -> Variant {
        let mut config = SchedulerConfig::for_policy(Policy::Nephele);
        config.sharing = None;
        config.derived_views = None;
        config.history_capacity = 0;
        Variant { label: "nephele-noshare".to_string(), config }
    }

    pub fn names() -> Vec<&'static str> {
        let mut names: Vec<&'static str> = Policy::ALL.iter().map(|p| p.name()).collect();
        names.push("nephele-noshare");
        names
    }

    pub fn parse(name: &str) -> Result<Variant, String> {
        if name == "nephele-noshare" {
            return Ok(Variant::nephele_without_sharing());
        }
        name.parse::<Policy>().map(Variant::of).map_err(|e| format!("{e}, or nephele-noshare"))
    }

    /// NEPHELE, the three baselines, and the no-sharing ablation.
    pub fn defaults() -> Vec<Variant> {
        let mut all: Vec<Variant> = Policy::ALL.into_iter().map(Variant::of).collect();
        all.push(Variant::nephele_without_sharing());
        all
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("scenario '{scenario}': {message}")]
    Scenario { scenario: String, message: String },
    #[error("the scheduler rejected an event at {at}: {error}")]
    Scheduler { at: Time, error: SchedError },
    #[error("user '{user}': camera: {error}")]
    Camera { user: String, error: CameraError },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Event {
    Join(usize),
    Fail(usize),
    Heartbeat(usize),
    Finish { worker: usize, batch: BatchId, generation: u64 },
    Arrive(usize),
    Pose(usize),
    Depart(usize),
}

#[derive(Debug, Clone, Copy)]
struct Job {
    batch: BatchId,
    object: ObjectId,
    /// Rays rendered: the batch's own and the part of its derived views' pixels that
    /// reprojection leaves.
    rays: f64,
    /// Reference rays of work (reprojection of derived views included), before the object's
    /// cost per ray.
    work: f64,
    /// Pixels sent to the composer (derived views' included).
    pixels: u64,
}

#[derive(Debug)]
struct Running {
    job: Job,
    start: Time,
    end: Time,
}

#[derive(Debug)]
struct WorkerSim {
    spec: SimWorker,
    id: WorkerId,
    rng: Rng,
    connected: bool,
    queue: VecDeque<Job>,
    running: Option<Running>,
    generation: u64,
    last_object: Option<ObjectId>,
    busy_s: f64,
    online_since: Option<Time>,
    online_s: f64,
    rays_rendered: f64,
}

#[derive(Debug)]
struct UserSim {
    spec: SimUser,
    session: Option<SessionId>,
    attempts: u32,
    refusals: u32,
    admitted_at: Option<Time>,
    left_at: Option<Time>,
    completed: u64,
    on_time: u64,
    dropped: u64,
    latencies_ms: Vec<f64>,
}

struct Engine<'a> {
    scenario: &'a Scenario,
    scheduler: Scheduler,
    events: BinaryHeap<Reverse<(Time, u64, Event)>>,
    sequence: u64,
    workers: Vec<WorkerSim>,
    users: Vec<UserSim>,
    by_session: HashMap<SessionId, usize>,
    costs: Vec<f64>,
    end: Time,
}

fn at(seconds: f64) -> Time {
    Time::from_secs_f64(seconds)
}

/// Runs `scenario` under `variant`. Deterministic: the same scenario (seed included) and
/// variant give the same report.
pub fn run(scenario: &Scenario, variant: &Variant) -> Result<Report, SimError> {
    let invalid = |message: String| SimError::Scenario { scenario: scenario.name.clone(), message };
    if scenario.workers.is_empty() || scenario.users.is_empty() {
        return Err(invalid("needs at least one worker and one user".to_string()));
    }
    let p = &scenario.params;
    if !(p.duration_s.is_finite()
        && p.duration_s > 0.0
        && p.pose_interval_s > 0.0
        && p.heartbeat_s > 0.0
        && p.link_bytes_per_s > 0.0)
    {
        return Err(invalid("duration, pose interval, heartbeat and link bandwidth must be positive".to_string()));
    }
    let mut scheduler =
        Scheduler::new(variant.config.clone()).map_err(|error| SimError::Scheduler { at: Time::ZERO, error })?;
    for (i, object) in scenario.objects.iter().enumerate() {
        let info = ObjectInfo {
            bounds: object.bounds(),
            occupancy: None,
            cost_per_ray: object.cost_per_ray,
            full_frame: false,
        };
        scheduler
            .register_object(ObjectId(i as u32 + 1), info)
            .map_err(|e| invalid(format!("object '{}': {e}", object.name)))?;
    }
    for user in &scenario.users {
        if let Some(&bad) = user.objects.iter().find(|&&i| i >= scenario.objects.len()) {
            return Err(invalid(format!("user '{}' names object {bad}, which does not exist", user.name)));
        }
    }
    let mut engine = Engine {
        scenario,
        scheduler,
        events: BinaryHeap::new(),
        sequence: 0,
        workers: scenario
            .workers
            .iter()
            .enumerate()
            .map(|(i, spec)| WorkerSim {
                spec: spec.clone(),
                id: WorkerId(i as u32 + 1),
                rng: Rng::new(p.seed.wrapping_mul(0x1000_0001).wrapping_add(i as u64)),
                connected: false,
                queue: VecDeque::new(),
                running: None,
                generation: 0,
                last_object: None,
                busy_s: 0.0,
                online_since: None,
                online_s: 0.0,
                rays_rendered: 0.0,
            })
            .collect(),
        users: scenario
            .users
            .iter()
            .map(|spec| UserSim {
                spec: spec.clone(),
                session: None,
                attempts: 0,
                refusals: 0,
                admitted_at: None,
                left_at: None,
                completed: 0,
                on_time: 0,
                dropped: 0,
                latencies_ms: Vec::new(),
            })
            .collect(),
        by_session: HashMap::new(),
        costs: scenario.objects.iter().map(|o| o.cost_per_ray).collect(),
        end: at(p.duration_s),
    };
    for (i, w) in scenario.workers.iter().enumerate() {
        engine.push(at(w.join_s), Event::Join(i));
        if let Some(fail) = w.fail_s {
            engine.push(at(fail), Event::Fail(i));
        }
    }
    for (i, u) in scenario.users.iter().enumerate() {
        engine.push(at(u.arrive_s), Event::Arrive(i));
    }
    engine.run()?;
    Ok(engine.report(&variant.label))
}

impl Engine<'_> {
    fn push(&mut self, time: Time, event: Event) {
        self.sequence += 1;
        self.events.push(Reverse((time, self.sequence, event)));
    }

    fn sched<T>(result: Result<T, SchedError>, now: Time) -> Result<T, SimError> {
        result.map_err(|error| SimError::Scheduler { at: now, error })
    }

    fn run(&mut self) -> Result<(), SimError> {
        let mut now = Time::ZERO;
        loop {
            let next_event = self.events.peek().map(|Reverse((t, _, _))| *t);
            let wake = self.scheduler.next_wakeup().map(|t| t.max(now));
            let mut t = match (next_event, wake) {
                (Some(a), Some(b)) => a.min(b),
                (Some(a), None) => a,
                (None, Some(b)) => b,
                (None, None) => break,
            };
            if t <= now && next_event.is_none_or(|e| e > now) {
                // Nothing new at this instant: the core was already ticked at `now`.
                t = now + Duration::from_micros(1);
            }
            if t > self.end {
                break;
            }
            now = t;
            while let Some(Reverse((time, _, event))) = self.events.peek().copied() {
                if time != now {
                    break;
                }
                self.events.pop();
                self.handle(event, now)?;
            }
            let actions = self.scheduler.tick(now);
            self.apply(actions, now)?;
        }
        Ok(())
    }

    fn handle(&mut self, event: Event, now: Time) -> Result<(), SimError> {
        match event {
            Event::Join(i) => {
                let (id, rate) = (self.workers[i].id, self.workers[i].spec.rays_per_s);
                Self::sched(self.scheduler.add_worker(id, rate, now), now)?;
                let w = &mut self.workers[i];
                w.connected = true;
                w.online_since = Some(now);
                let beat = now + Duration::from_secs_f64(self.scenario.params.heartbeat_s);
                self.push(beat, Event::Heartbeat(i));
            }
            Event::Heartbeat(i) => {
                if self.workers[i].connected {
                    if self.scheduler.heartbeat(self.workers[i].id, now).is_err() {
                        self.disconnect(i, now); // declared lost: the master closed it
                    } else {
                        let beat = now + Duration::from_secs_f64(self.scenario.params.heartbeat_s);
                        self.push(beat, Event::Heartbeat(i));
                    }
                }
            }
            Event::Fail(i) => {
                if self.workers[i].connected {
                    self.disconnect(i, now);
                    if self.workers[i].spec.detect == Detect::Drop {
                        // The process died: its connection closes and the master notices.
                        let _ = self.scheduler.remove_worker(self.workers[i].id, now);
                    }
                }
            }
            Event::Finish { worker, batch, generation } => {
                let w = &mut self.workers[worker];
                let current = w.running.as_ref().is_some_and(|r| r.job.batch == batch);
                if w.generation != generation || !current {
                    return Ok(());
                }
                if let Some(r) = w.running.take() {
                    w.busy_s += now.since(r.start).as_secs_f64();
                    w.rays_rendered += r.job.rays;
                }
                let id = w.id;
                // A copy that lost the race, or whose task finished meanwhile, is refused:
                // harmless, as in the live master.
                let _ = self.scheduler.batch_done(id, batch, now);
                self.start_next(worker, now);
            }
            Event::Arrive(u) => self.arrive(u, now)?,
            Event::Pose(u) => {
                if let Some(session) = self.users[u].session {
                    let user = &self.users[u].spec;
                    let views = user
                        .views_at(now.as_secs_f64() - user.arrive_s, &self.scenario.objects)
                        .map_err(|error| SimError::Camera { user: user.name.clone(), error })?;
                    Self::sched(self.scheduler.pose(session, &views, now), now)?;
                    let next = now + Duration::from_secs_f64(self.scenario.params.pose_interval_s);
                    if next.as_secs_f64() < user.depart_s {
                        self.push(next, Event::Pose(u));
                    }
                }
            }
            Event::Depart(u) => {
                if let Some(session) = self.users[u].session.take() {
                    Self::sched(self.scheduler.close_session(session, now), now)?;
                    self.users[u].left_at = Some(now);
                }
            }
        }
        Ok(())
    }

    fn arrive(&mut self, u: usize, now: Time) -> Result<(), SimError> {
        let user = &self.users[u].spec;
        let spec = SessionSpec {
            target_fps: user.fps,
            objects: user.objects.iter().map(|&i| ObjectId(i as u32 + 1)).collect(),
        };
        let depart = user.depart_s;
        match self.scheduler.open_session(spec, now) {
            Ok(session) => {
                let state = &mut self.users[u];
                state.session = Some(session);
                state.admitted_at = Some(now);
                self.by_session.insert(session, u);
                self.handle(Event::Pose(u), now)?;
                self.push(at(depart), Event::Depart(u));
            }
            Err(SchedError::Refused { retry_after }) => {
                let state = &mut self.users[u];
                state.refusals += 1;
                state.attempts += 1;
                let retry = now + retry_after;
                if state.attempts <= self.scenario.params.retries && retry.as_secs_f64() < depart {
                    self.push(retry, Event::Arrive(u));
                }
            }
            Err(error) => return Err(SimError::Scheduler { at: now, error }),
        }
        Ok(())
    }

    fn disconnect(&mut self, i: usize, now: Time) {
        let w = &mut self.workers[i];
        if let Some(r) = w.running.take() {
            let spent = now.since(r.start).as_secs_f64();
            w.busy_s += spent;
            w.rays_rendered += r.job.rays * spent / r.end.since(r.start).as_secs_f64().max(1e-12);
        }
        w.queue.clear();
        w.generation += 1;
        w.connected = false;
        if let Some(since) = w.online_since.take() {
            w.online_s += now.since(since).as_secs_f64();
        }
    }

    fn apply(&mut self, actions: Vec<Action>, now: Time) -> Result<(), SimError> {
        for action in actions {
            match action {
                Action::Dispatch { worker, batch } => {
                    let i = worker.0 as usize - 1;
                    if self.workers.get(i).is_some_and(|w| w.connected) {
                        let derived: u64 = batch.derived.iter().map(|d| d.rays).sum();
                        self.workers[i].queue.push_back(Job {
                            batch: batch.id,
                            object: batch.object,
                            rays: batch.rays as f64 + self.scenario.params.derived_render_fraction * derived as f64,
                            work: batch.work_rays,
                            pixels: batch.rays + derived,
                        });
                        if self.workers[i].running.is_none() {
                            self.start_next(i, now);
                        }
                    }
                }
                Action::Cancel { worker, batch } => {
                    let i = worker.0 as usize - 1;
                    let Some(w) = self.workers.get_mut(i) else { continue };
                    if w.running.as_ref().is_some_and(|r| r.job.batch == batch) {
                        if let Some(r) = w.running.take() {
                            let spent = now.since(r.start).as_secs_f64();
                            w.busy_s += spent;
                            w.rays_rendered += r.job.rays * spent / r.end.since(r.start).as_secs_f64().max(1e-12);
                        }
                        w.generation += 1;
                        self.start_next(i, now);
                    } else {
                        w.queue.retain(|j| j.batch != batch);
                    }
                }
                Action::FrameComplete { session, latency, .. } => {
                    let Some(&u) = self.by_session.get(&session) else { continue };
                    let user = &mut self.users[u];
                    let total = latency.as_secs_f64() + self.scenario.params.composite_s;
                    user.completed += 1;
                    user.on_time += u64::from(total <= 1.0 / user.spec.fps + 1e-9);
                    user.latencies_ms.push(total * 1e3);
                }
                Action::FrameDropped { session, .. } => {
                    if let Some(&u) = self.by_session.get(&session) {
                        self.users[u].dropped += 1;
                    }
                }
                Action::WorkerLost { worker, .. } => {
                    let i = worker.0 as usize - 1;
                    if self.workers.get(i).is_some_and(|w| w.connected) {
                        self.disconnect(i, now);
                    }
                }
                Action::ReleaseResult { .. } => {}
            }
        }
        Ok(())
    }

    /// Starts the next queued batch on an idle worker.
    fn start_next(&mut self, i: usize, now: Time) {
        let p = &self.scenario.params;
        let w = &mut self.workers[i];
        if w.running.is_some() || !w.connected {
            return;
        }
        let Some(job) = w.queue.pop_front() else { return };
        let cost = self.costs.get(job.object.0 as usize - 1).copied().unwrap_or(1.0);
        let mut render = job.work * cost / w.spec.rays_per_s;
        if let Some((from, to, factor)) = w.spec.slow {
            let t = now.as_secs_f64();
            if t >= from && t < to {
                render *= factor;
            }
        }
        render *= 1.0 + w.spec.jitter * (2.0 * w.rng.unit() - 1.0);
        let switch = if w.last_object == Some(job.object) { 0.0 } else { p.switch_cost_s };
        let transfer = job.pixels as f64 * p.bytes_per_pixel / p.link_bytes_per_s;
        let duration = p.batch_overhead_s + switch + render + transfer;
        let end = now + Duration::from_secs_f64(duration.max(1e-6));
        w.last_object = Some(job.object);
        w.running = Some(Running { job, start: now, end });
        let event = Event::Finish { worker: i, batch: job.batch, generation: w.generation };
        self.push(end, event);
    }

    fn report(&mut self, label: &str) -> Report {
        let end = self.end;
        for i in 0..self.workers.len() {
            if self.workers[i].connected {
                let w = &mut self.workers[i];
                if let Some(r) = &w.running {
                    w.busy_s += end.since(r.start).as_secs_f64();
                }
                if let Some(since) = w.online_since.take() {
                    w.online_s += end.since(since).as_secs_f64();
                }
            }
        }
        let users: Vec<UserMetrics> = self
            .users
            .iter()
            .map(|u| {
                let active_s = match u.admitted_at {
                    Some(start) => u.left_at.unwrap_or(end).min(end).since(start).as_secs_f64(),
                    None => 0.0,
                };
                let expected = active_s * u.spec.fps;
                UserMetrics {
                    user: u.spec.name.clone(),
                    admitted: u.admitted_at.is_some(),
                    refusals: u.refusals,
                    target_fps: u.spec.fps,
                    active_s,
                    frames_completed: u.completed,
                    frames_on_time: u.on_time,
                    frames_dropped: u.dropped,
                    achieved_fps: if active_s > 0.0 { u.completed as f64 / active_s } else { 0.0 },
                    attainment: if expected >= 1.0 { (u.on_time as f64 / expected).min(1.0) } else { 0.0 },
                    latency_p50_ms: percentile(&u.latencies_ms, 0.5),
                }
            })
            .collect();
        let stats = self.scheduler.stats();
        let mut latencies: Vec<f64> = self.users.iter().flat_map(|u| u.latencies_ms.iter().copied()).collect();
        latencies.sort_by(f64::total_cmp);
        let admitted: Vec<&UserMetrics> =
            users.iter().filter(|u| u.admitted && u.active_s * u.target_fps >= 1.0).collect();
        let attainment: Vec<f64> = admitted.iter().map(|u| u.attainment).collect();
        let normalised: Vec<f64> = admitted.iter().map(|u| u.achieved_fps / u.target_fps).collect();
        let busy: f64 = self.workers.iter().map(|w| w.busy_s).sum();
        let online: f64 = self.workers.iter().map(|w| w.online_s).sum();
        let rendered: f64 = self.workers.iter().map(|w| w.rays_rendered).sum();
        let summary = Summary {
            scenario: self.scenario.name.clone(),
            policy: label.to_string(),
            users: users.len(),
            admitted: users.iter().filter(|u| u.admitted).count(),
            refusals: stats.sessions_refused,
            attainment_mean: mean(&attainment),
            attainment_min: if attainment.is_empty() { 0.0 } else { attainment.iter().copied().fold(1.0, f64::min) },
            latency_p50_ms: percentile_sorted(&latencies, 0.5),
            latency_p99_ms: percentile_sorted(&latencies, 0.99),
            utilisation: if online > 0.0 { busy / online } else { 0.0 },
            rays_requested: stats.rays_requested,
            rays_rendered: rendered.round() as u64,
            pixels_displayed: self
                .users
                .iter()
                .map(|u| u.completed * u64::from(u.spec.width) * u64::from(u.spec.height) * u.spec.views.count() as u64)
                .sum(),
            frames_released: stats.frames_released,
            frames_completed: users.iter().map(|u| u.frames_completed).sum(),
            frames_dropped: users.iter().map(|u| u.frames_dropped).sum(),
            batches_reissued: stats.batches_reissued,
            shared_joins: stats.shared_joins,
            history_hits: stats.history_hits,
            share_error_px_max: f64::from(stats.share_error_px_max),
            jain: jain(&normalised),
        };
        Report { summary, users }
    }
}

fn mean(values: &[f64]) -> f64 {
    if values.is_empty() { 0.0 } else { values.iter().sum::<f64>() / values.len() as f64 }
}

fn percentile(values: &[f64], q: f64) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    percentile_sorted(&sorted, q)
}

/// Nearest-rank percentile; 0 for no data.
fn percentile_sorted(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

/// Jain's fairness index `(sum x)^2 / (n sum x^2)`: 1 when all are equal, 1/n when one user
/// gets everything.
pub fn jain(values: &[f64]) -> f64 {
    let sum: f64 = values.iter().sum();
    let squares: f64 = values.iter().map(|x| x * x).sum();
    if values.is_empty() || squares == 0.0 { 0.0 } else { sum * sum / (values.len() as f64 * squares) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fairness_and_percentiles() {
        assert!((jain(&[1.0, 1.0, 1.0]) - 1.0).abs() < 1e-12);
        assert!((jain(&[1.0, 0.0, 0.0, 0.0]) - 0.25).abs() < 1e-12);
        assert_eq!(jain(&[]), 0.0);
        let values: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile_sorted(&values, 0.5), 50.0);
        assert_eq!(percentile_sorted(&values, 0.99), 99.0);
        assert_eq!(percentile(&[3.0, 1.0, 2.0], 1.0), 3.0);
        assert_eq!(percentile_sorted(&[], 0.5), 0.0);
        assert!(
            Variant::parse("nephele-noshare")
                .is_ok_and(|v| v.config.sharing.is_none() && v.config.derived_views.is_none())
        );
        assert!(Variant::parse("lottery").is_err());
        assert_eq!(Variant::defaults().len(), 5);
    }
}
