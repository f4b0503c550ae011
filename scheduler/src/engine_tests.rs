use super::*;
use glam::{Mat4, Vec3};
use nephele_geometry::camera::stereo_pair;

const OBJ: ObjectId = ObjectId(1);

fn ms(ms: u64) -> Time {
    Time::from_micros(ms * 1000)
}

fn config(policy: Policy) -> SchedulerConfig {
    SchedulerConfig { max_batch_rays: 128, ..SchedulerConfig::for_policy(policy) }
}

fn unit_object(center: Vec3, half: f32, cost: f64) -> ObjectInfo {
    ObjectInfo {
        bounds: Bounds { min: center - Vec3::splat(half), max: center + Vec3::splat(half) },
        occupancy: None,
        cost_per_ray: cost,
        full_frame: false,
    }
}

fn scheduler(config: SchedulerConfig) -> Scheduler {
    let mut s = Scheduler::new(config).expect("valid config");
    s.register_object(OBJ, unit_object(Vec3::ZERO, 0.5, 1.0)).expect("object");
    s
}

fn camera_at(angle_deg: f32) -> Camera {
    let a = angle_deg.to_radians();
    Camera::look_at(64, 64, 0.8, Vec3::new(4.0 * a.sin(), -4.0 * a.cos(), 0.0), Vec3::ZERO, Vec3::Z).expect("camera")
}

fn open(s: &mut Scheduler, fps: f64, views: &[Camera], now: Time) -> SessionId {
    let id = s.open_session(SessionSpec { target_fps: fps, objects: vec![OBJ] }, now).expect("admitted");
    s.pose(id, views, now).expect("pose");
    id
}

fn dispatches(actions: &[Action]) -> Vec<(WorkerId, BatchSpec)> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::Dispatch { worker, batch } => Some((*worker, (**batch).clone())),
            _ => None,
        })
        .collect()
}

fn completions(actions: &[Action]) -> Vec<(SessionId, FrameId, Vec<FramePart>)> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::FrameComplete { session, frame, parts, .. } => Some((*session, *frame, parts.clone())),
            _ => None,
        })
        .collect()
}

/// Completes every dispatch of `actions` at `now`, ticks, and repeats until nothing is
/// dispatched; returns every action seen.
fn run_to_quiet(s: &mut Scheduler, mut actions: Vec<Action>, now: Time) -> Vec<Action> {
    let mut all = Vec::new();
    for _ in 0..1000 {
        let sent = dispatches(&actions);
        all.append(&mut actions);
        if sent.is_empty() {
            break;
        }
        for (worker, batch) in sent {
            s.batch_done(worker, batch.id, now).expect("known batch");
        }
        actions = s.tick(now);
    }
    all
}

fn session_of(s: &Scheduler, batch: &BatchSpec) -> SessionId {
    let _ = s;
    batch.frames[0].0
}

#[test]
fn starved_users_are_served_first() {
    let mut cfg = config(Policy::Nephele);
    cfg.horizon = Duration::from_micros(1); // one batch per worker at a time
    cfg.min_batch_timeout = Duration::from_secs(10);
    cfg.heartbeat_timeout = None;
    cfg.sharing = None;
    cfg.history_capacity = 0;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    let a = open(&mut s, 10.0, &[camera_at(0.0)], ms(0));
    let first = dispatches(&s.tick(ms(0)));
    assert_eq!(first.len(), 1);
    assert_eq!(session_of(&s, &first[0].1), a);
    // B arrives, slower frame rate: its deadline is later.
    let b = open(&mut s, 5.0, &[camera_at(30.0)], ms(1));
    assert!(dispatches(&s.tick(ms(1))).is_empty(), "the only worker is full");
    // A second worker: nobody is starved, B has fewer loaded tasks, so B goes first.
    s.add_worker(WorkerId(2), 1e6, ms(2)).expect("worker");
    let second = dispatches(&s.tick(ms(2)));
    assert_eq!(second.len(), 1);
    assert_eq!(session_of(&s, &second[0].1), b);
    // At 150 ms A's target time (release 0 + 1/10 s - t_u) has passed: A is starved, B (target
    // 1 ms + 200 ms) is not. Worker 2 frees up; A still has a batch loaded on worker 1 and B has
    // none, yet A is served.
    s.batch_done(WorkerId(2), second[0].1.id, ms(150)).expect("done");
    let third = dispatches(&s.tick(ms(150)));
    assert_eq!(s.starved_sessions(), 1);
    assert_eq!(third.len(), 1);
    assert_eq!(session_of(&s, &third[0].1), a, "the starved user goes first");
    let snapshot = s.snapshot(ms(150));
    let starved: Vec<SessionId> = snapshot.sessions.iter().filter(|x| x.starved).map(|x| x.id).collect();
    assert_eq!(starved, vec![a]);
}

#[test]
fn no_session_is_admitted_while_anyone_is_starved() {
    let mut cfg = config(Policy::Nephele);
    cfg.min_batch_timeout = Duration::from_secs(10);
    cfg.heartbeat_timeout = None;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e5, ms(0)).expect("worker");
    let a = open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let sent = dispatches(&s.tick(ms(0)));
    assert!(!sent.is_empty());
    assert_eq!(s.admission(ms(10)), Admission::Admit, "not starved yet");
    // 1/30 s later the frame still has undispatched batches (the worker is full): starved.
    assert!(matches!(s.admission(ms(40)), Admission::Refuse { retry_after } if retry_after >= Duration::from_secs(1)));
    let refused = s.open_session(SessionSpec { target_fps: 30.0, objects: vec![OBJ] }, ms(40));
    assert!(matches!(refused, Err(SchedError::Refused { .. })), "{refused:?}");
    assert_eq!(s.stats().sessions_refused, 1);
    let snapshot = s.snapshot(ms(40));
    assert!(!snapshot.admission_open && snapshot.retry_after_s.is_some_and(|r| r >= 1));
    // Serve everything: admission reopens.
    let actions = s.tick(ms(40));
    let mut all = sent.into_iter().map(|(w, b)| Action::Dispatch { worker: w, batch: Box::new(b) }).collect::<Vec<_>>();
    all.extend(actions);
    run_to_quiet(&mut s, all, ms(41));
    // Nobody is starved any more, but admission stays closed for `admission_hold` (1 s)
    // after the round that found A starved, while A stays.
    assert!(!s.snapshot(ms(41)).sessions.iter().any(|x| x.starved));
    assert!(matches!(s.admission(ms(41)), Admission::Refuse { .. }));
    // A leaves: the farm it starved is free, and the next user is admitted at once.
    s.close_session(a, ms(42)).expect("close");
    assert_eq!(s.admission(ms(42)), Admission::Admit);
    assert!(s.open_session(SessionSpec { target_fps: 30.0, objects: vec![OBJ] }, ms(42)).is_ok());
}

#[test]
fn shared_rays_are_rendered_once_and_fanned_out() {
    let mut s = scheduler(config(Policy::Nephele));
    for w in 1..=3 {
        s.add_worker(WorkerId(w), 1e8, ms(0)).expect("worker");
    }
    let view = camera_at(10.0);
    let a = open(&mut s, 30.0, &[view], ms(0));
    let b = open(&mut s, 30.0, &[view], ms(0));
    let actions = s.tick(ms(0));
    let sent = dispatches(&actions);
    let tasks: BTreeSet<TaskId> = sent.iter().map(|(_, b)| b.task).collect();
    assert_eq!(tasks.len(), 1, "one task for both users");
    assert!(sent.iter().all(|(_, batch)| batch.frames.len() == 2), "each batch feeds both frames");
    let stats = s.stats().clone();
    assert_eq!((stats.tasks_created, stats.shared_joins), (1, 1));
    assert_eq!(stats.rays_requested, 2 * stats.rays_created);
    assert_eq!(stats.rays_dispatched, stats.rays_created, "every ray sent once");
    let all = run_to_quiet(&mut s, actions, ms(1));
    let done = completions(&all);
    assert_eq!(done.len(), 2);
    let sessions: BTreeSet<SessionId> = done.iter().map(|d| d.0).collect();
    assert_eq!(sessions, [a, b].into_iter().collect());
    assert!(done.iter().all(|d| d.2.len() == 1 && tasks.contains(&d.2[0].task)));
    assert_eq!(s.stats().share_error_px_max, 0.0, "identical cameras");
}

#[test]
fn the_two_eyes_of_a_user_are_two_tasks_and_baselines_never_share() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    let eyes = stereo_pair(&camera_at(0.0), 0.064).expect("stereo");
    open(&mut s, 30.0, &eyes, ms(0));
    s.tick(ms(0));
    assert_eq!((s.stats().tasks_created, s.stats().shared_joins), (2, 0));
    let mut fifo = scheduler(config(Policy::Fifo));
    fifo.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    open(&mut fifo, 30.0, &[camera_at(0.0)], ms(0));
    open(&mut fifo, 30.0, &[camera_at(0.0)], ms(0));
    fifo.tick(ms(0));
    assert_eq!((fifo.stats().tasks_created, fifo.stats().shared_joins), (2, 0));
}

#[test]
fn a_frame_reports_the_view_size_of_the_pose_it_was_released_with() {
    // A stream coded smaller asks for half of each side (the composer's smaller poses): the
    // frames released from then on say so, for the composer's plan.
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    let id = open(&mut s, 50.0, &[camera_at(0.0)], ms(0));
    let sizes = |actions: &[Action]| -> Vec<(u32, u32)> {
        actions
            .iter()
            .filter_map(|a| match a {
                Action::FrameComplete { session, view_size, .. } if *session == id => Some(*view_size),
                _ => None,
            })
            .collect()
    };
    let actions = s.tick(ms(0));
    assert_eq!(sizes(&run_to_quiet(&mut s, actions, ms(1))), vec![(64, 64)]);
    let a = 10f32.to_radians();
    let half = Camera::look_at(32, 32, 0.8, Vec3::new(4.0 * a.sin(), -4.0 * a.cos(), 0.0), Vec3::ZERO, Vec3::Z)
        .expect("half-size camera");
    s.pose(id, &[half], ms(20)).expect("pose");
    let actions = s.tick(ms(20));
    assert_eq!(sizes(&run_to_quiet(&mut s, actions, ms(21))), vec![(32, 32)]);
}

#[test]
fn history_reuses_the_results_of_a_still_camera() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    let id = open(&mut s, 50.0, &[camera_at(0.0)], ms(0));
    let actions = s.tick(ms(0));
    let first = run_to_quiet(&mut s, actions, ms(1));
    assert_eq!(completions(&first).len(), 1);
    // 20 ms later the next frame asks for the same rays: served from history, nothing sent.
    let second = s.tick(ms(20));
    assert!(dispatches(&second).is_empty());
    let done = completions(&second);
    assert_eq!(done.len(), 1);
    assert_eq!((done[0].0, done[0].2[0].source), (id, PartSource::History));
    assert_eq!(s.stats().history_hits, 1);
    assert_eq!(s.stats().rays_from_history, s.stats().rays_created);
    // Past the maximum age the result is not reused; the expired one is released.
    s.pose(id, &[camera_at(0.0)], ms(900)).expect("pose");
    let third = s.tick(ms(900));
    assert!(!dispatches(&third).is_empty());
    assert!(third.iter().any(|a| matches!(a, Action::ReleaseResult { .. })));
}

#[test]
fn worker_death_mid_frame_still_completes_every_pixel() {
    let mut cfg = config(Policy::Nephele);
    cfg.heartbeat_timeout = None;
    cfg.min_batch_timeout = Duration::from_secs(10);
    cfg.horizon = Duration::from_micros(300); // about two batches per worker
    cfg.object_switch_cost = Duration::ZERO;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 1e6, ms(0)).expect("worker");
    let id = open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let sent = dispatches(&s.tick(ms(0)));
    let on_one: Vec<BatchId> = sent.iter().filter(|(w, _)| *w == WorkerId(1)).map(|(_, b)| b.id).collect();
    assert!(!on_one.is_empty() && sent.iter().any(|(w, _)| *w == WorkerId(2)));
    let expected_pixels: u64 = s.stats().rays_created;
    let mut rendered: Vec<(BatchId, PixelSet)> = Vec::new();
    // Worker 2 finishes one batch; worker 1 dies.
    let (w2, first) = sent.iter().find(|(w, _)| *w == WorkerId(2)).cloned().expect("a batch on worker 2");
    s.batch_done(w2, first.id, ms(1)).expect("done");
    rendered.push((first.id, first.pixels.clone()));
    s.remove_worker(WorkerId(1), ms(2)).expect("remove");
    assert!(matches!(s.batch_done(WorkerId(1), on_one[0], ms(2)), Err(SchedError::UnknownWorker(_))));
    let mut actions = s.tick(ms(2));
    let mut t = 3;
    let mut complete = Vec::new();
    while complete.is_empty() && t < 500 {
        for (worker, batch) in dispatches(&actions) {
            assert_eq!(worker, WorkerId(2), "only the survivor gets work");
            s.batch_done(worker, batch.id, ms(t)).expect("done");
            rendered.push((batch.id, batch.pixels.clone()));
        }
        for (w, b) in sent.iter().filter(|(w, b)| *w == WorkerId(2) && b.id != first.id) {
            let _ = s.batch_done(*w, b.id, ms(t)); // the rest of worker 2's first load
        }
        actions = s.tick(ms(t));
        complete = completions(&actions);
        t += 1;
    }
    assert_eq!(complete.len(), 1, "the frame completes");
    assert_eq!(complete[0].0, id);
    for b in &on_one {
        assert!(rendered.iter().any(|(id, _)| id == b), "batch {b} of the dead worker re-issued and rendered");
    }
    let first_load: u64 = sent.iter().filter(|(w, _)| *w == WorkerId(2)).map(|(_, b)| b.rays).sum();
    let reissued: u64 = rendered.iter().map(|(_, p)| p.len()).sum();
    assert!(reissued + first_load >= expected_pixels);
    assert!(s.stats().batches_reissued as usize >= on_one.len());
}

#[test]
fn a_missed_deadline_reissues_the_batch_and_the_first_answer_wins() {
    let mut cfg = config(Policy::Nephele);
    cfg.heartbeat_timeout = None;
    cfg.max_batch_rays = 1 << 20; // one batch
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let sent = dispatches(&s.tick(ms(0)));
    assert_eq!(sent.len(), 1);
    let batch = sent[0].1.id;
    s.add_worker(WorkerId(2), 1e8, ms(1)).expect("worker");
    // Worker 1 stalls past the timeout (at least min_batch_timeout = 20 ms).
    let actions = s.tick(ms(25));
    assert!(actions.contains(&Action::Cancel { worker: WorkerId(1), batch }));
    let again = dispatches(&actions);
    assert_eq!(again.len(), 1);
    assert_eq!((again[0].0, again[0].1.id, again[0].1.attempt), (WorkerId(2), batch, 2));
    assert_eq!(s.stats().batches_timed_out, 1);
    // The straggler answers first after all: accepted, the second copy is cancelled.
    s.batch_done(WorkerId(1), batch, ms(26)).expect("late answer counts");
    let actions = s.tick(ms(26));
    assert!(actions.contains(&Action::Cancel { worker: WorkerId(2), batch }));
    assert_eq!(completions(&actions).len(), 1);
    assert!(matches!(s.batch_done(WorkerId(2), batch, ms(27)), Err(SchedError::UnknownBatch(_))));
}

#[test]
fn missed_deadlines_wait_longer_while_every_other_worker_is_busy() {
    let mut cfg = config(Policy::Nephele);
    cfg.heartbeat_timeout = None;
    cfg.max_deadline_stretches = 2;
    let mut s = scheduler(cfg);
    // Slow workers: the view's task is heavy and split between both.
    s.add_worker(WorkerId(1), 1e4, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 1e4, ms(0)).expect("worker");
    open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let sent = dispatches(&s.tick(ms(0)));
    let on = |w: WorkerId| sent.iter().filter(|(x, _)| *x == w).count();
    assert!(on(WorkerId(1)) > 0 && on(WorkerId(2)) > 0, "{:?}", (on(WorkerId(1)), on(WorkerId(2))));
    let held: Vec<BatchId> = sent.iter().map(|(_, b)| b.id).collect();
    // Nobody answers. Each miss while the other worker is busy extends the deadline (twice at
    // most): nothing is cancelled or sent again.
    let mut now = ms(0);
    for round in 1..=2u64 {
        let next = s.next_wakeup().expect("deadlines pending");
        now = next + Duration::from_millis(1);
        let actions = s.tick(now);
        assert!(!actions.iter().any(|a| matches!(a, Action::Cancel { .. })), "round {round}: {actions:?}");
        assert!(dispatches(&actions).iter().all(|(_, b)| !held.contains(&b.id)), "round {round}");
        assert_eq!(s.stats().batches_reissued, 0);
    }
    assert!(s.stats().deadlines_stretched >= 2 * held.len() as u64 - 1, "{:?}", s.stats());
    // Past the stretches, a batch that misses again is taken back and sent elsewhere.
    let mut reissued = false;
    for _ in 0..8 {
        now = s.next_wakeup().expect("deadlines pending").max(now) + Duration::from_millis(1);
        let actions = s.tick(now);
        if actions.iter().any(|a| matches!(a, Action::Cancel { batch, .. } if held.contains(batch))) {
            reissued = true;
            break;
        }
    }
    assert!(reissued && s.stats().batches_reissued > 0, "{:?}", s.stats());
    assert_eq!(s.stats().batches_timed_out, s.stats().deadlines_stretched + s.stats().batches_reissued);
}

#[test]
fn silent_workers_are_declared_lost() {
    let mut cfg = config(Policy::Fifo);
    cfg.heartbeat_timeout = Some(Duration::from_millis(100));
    cfg.min_batch_timeout = Duration::from_secs(10);
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 1e6, ms(0)).expect("worker");
    open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    s.tick(ms(0));
    s.heartbeat(WorkerId(2), ms(90)).expect("alive");
    assert!(s.next_wakeup().is_some_and(|t| t <= ms(101)));
    let actions = s.tick(ms(150));
    assert!(actions.iter().any(|a| matches!(a, Action::WorkerLost { worker: WorkerId(1), reissued } if *reissued > 0)));
    assert!(!actions.iter().any(|a| matches!(a, Action::WorkerLost { worker: WorkerId(2), .. })));
    assert!(dispatches(&actions).iter().all(|(w, _)| *w == WorkerId(2)));
    assert_eq!(s.stats().workers_lost, 1);
}

#[test]
fn repeated_failures_drop_the_frame_and_cancel_its_work() {
    let mut cfg = config(Policy::Nephele);
    cfg.max_attempts = 2;
    cfg.sharing = None;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 1e8, ms(0)).expect("worker");
    let id = open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let sent = dispatches(&s.tick(ms(0)));
    let (w, b) = (sent[0].0, sent[0].1.id);
    s.batch_failed(w, b, ms(1)).expect("failure reported");
    let retry = dispatches(&s.tick(ms(1)));
    let (w2, _) = retry.iter().find(|(_, x)| x.id == b).cloned().expect("re-issued");
    assert_ne!(w2, w, "not to the worker that failed");
    s.batch_failed(w2, b, ms(2)).expect("failure reported");
    let actions = s.tick(ms(2));
    assert!(actions.contains(&Action::FrameDropped {
        session: id,
        frame: FrameId(0),
        reason: DropReason::BatchFailed(b)
    }));
    assert!(actions.iter().any(|a| matches!(a, Action::Cancel { .. })), "the frame's other batches are cancelled");
    assert_eq!(s.pending_batches(), 0);
    assert_eq!(s.live_tasks(), 0);
}

#[test]
fn a_newer_frame_supersedes_an_older_one() {
    let mut cfg = config(Policy::Nephele);
    cfg.history_capacity = 0;
    cfg.min_batch_timeout = Duration::from_secs(10);
    cfg.heartbeat_timeout = None;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    let id = open(&mut s, 100.0, &[camera_at(0.0)], ms(0));
    let old = dispatches(&s.tick(ms(0)));
    s.pose(id, &[camera_at(5.0)], ms(10)).expect("pose");
    let new = dispatches(&s.tick(ms(10)));
    // Frame 1 completes first (its batches are answered, frame 0's are not).
    for (w, b) in &new {
        s.batch_done(*w, b.id, ms(11)).expect("done");
    }
    let mut actions = s.tick(ms(11));
    for _ in 0..20 {
        if !completions(&actions).is_empty() {
            break;
        }
        let more = dispatches(&actions);
        for (w, b) in &more {
            if b.frames.iter().any(|f| f.1 == FrameId(1)) {
                s.batch_done(*w, b.id, ms(12)).expect("done");
            }
        }
        actions = s.tick(ms(12));
    }
    assert!(completions(&actions).iter().any(|c| c.1 == FrameId(1)));
    assert!(actions.contains(&Action::FrameDropped { session: id, frame: FrameId(0), reason: DropReason::Superseded }));
    assert!(old.iter().all(|(w, b)| actions.contains(&Action::Cancel { worker: *w, batch: b.id })));
}

#[test]
fn heavy_tasks_get_workers_of_their_own() {
    let mut cfg = config(Policy::Nephele);
    cfg.max_batch_rays = 256;
    let mut s = Scheduler::new(cfg).expect("config");
    // A close object filling the view (heavy) and small far ones (light).
    s.register_object(ObjectId(1), unit_object(Vec3::new(0.0, -2.0, 0.0), 0.8, 1.0)).expect("object");
    for i in 0..6 {
        s.register_object(ObjectId(10 + i), unit_object(Vec3::new(-1.5 + 0.6 * i as f32, 3.0, 0.0), 0.05, 1.0))
            .expect("object");
    }
    for w in 1..=6 {
        s.add_worker(WorkerId(w), 2e5, ms(0)).expect("worker");
    }
    let objects = std::iter::once(ObjectId(1)).chain((0..6).map(|i| ObjectId(10 + i))).collect();
    let id = s.open_session(SessionSpec { target_fps: 30.0, objects }, ms(0)).expect("admitted");
    s.pose(id, &[camera_at(0.0)], ms(0)).expect("pose");
    let sent = dispatches(&s.tick(ms(0)));
    let stats = s.stats();
    assert!(stats.tasks_heavy >= 1 && stats.tasks_light >= 1, "{stats:?}");
    let mut classes: BTreeMap<WorkerId, BTreeSet<(bool, ObjectId)>> = BTreeMap::new();
    for (w, b) in &sent {
        classes.entry(*w).or_default().insert((b.class == TaskClass::Heavy, b.object));
    }
    for (w, set) in &classes {
        let heavy = set.iter().filter(|c| c.0).count();
        assert!(heavy == 0 || set.len() == 1, "worker {w} mixes a heavy task with other work: {set:?}");
    }
    assert!(classes.values().any(|c| c.iter().any(|x| x.0)), "heavy work placed");
    assert!(classes.values().any(|c| c.iter().any(|x| !x.0)), "light work placed beside it");
    let snapshot = s.snapshot(ms(0));
    assert!(snapshot.workers.iter().any(|w| w.mode.starts_with("heavy:o1:t")), "{:?}", snapshot.workers);
}

#[test]
fn bad_input_is_rejected_with_clear_errors() {
    let mut s = scheduler(config(Policy::Nephele));
    for fps in [0.0, -30.0, f64::NAN, f64::INFINITY, 1000.0] {
        let r = s.open_session(SessionSpec { target_fps: fps, objects: vec![OBJ] }, ms(0));
        assert!(matches!(r, Err(SchedError::InvalidFps(_))), "{fps}: {r:?}");
    }
    assert_eq!(s.open_session(SessionSpec { target_fps: 30.0, objects: vec![] }, ms(0)), Err(SchedError::NoObjects));
    let unknown = s.open_session(SessionSpec { target_fps: 30.0, objects: vec![ObjectId(99)] }, ms(0));
    assert_eq!(unknown, Err(SchedError::UnknownObject(ObjectId(99))));
    assert_eq!(s.pose(SessionId(42), &[camera_at(0.0)], ms(0)), Err(SchedError::UnknownSession(SessionId(42))));
    assert_eq!(s.close_session(SessionId(42), ms(0)), Err(SchedError::UnknownSession(SessionId(42))));
    assert_eq!(s.heartbeat(WorkerId(7), ms(0)), Err(SchedError::UnknownWorker(WorkerId(7))));
    assert_eq!(s.remove_worker(WorkerId(7), ms(0)), Err(SchedError::UnknownWorker(WorkerId(7))));
    for rate in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(matches!(s.add_worker(WorkerId(1), rate, ms(0)), Err(SchedError::InvalidThroughput(_))));
    }
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    assert_eq!(s.add_worker(WorkerId(1), 1e6, ms(0)), Err(SchedError::DuplicateWorker(WorkerId(1))));
    assert_eq!(s.batch_done(WorkerId(1), BatchId(12345), ms(0)), Err(SchedError::UnknownBatch(BatchId(12345))));
    assert_eq!(s.batch_done(WorkerId(9), BatchId(1), ms(0)), Err(SchedError::UnknownWorker(WorkerId(9))));
    let id = open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    // NaN and singular pose matrices, no views, too many views.
    let good = camera_at(0.0);
    let mut nan_view = good.world_to_camera();
    nan_view.w_axis.x = f32::NAN;
    let projection = good.projection_matrix(0.1, 100.0);
    let bad = [ViewProjection { width: 64, height: 64, view: nan_view, projection }];
    assert!(matches!(s.pose_matrices(id, &bad, ms(1)), Err(SchedError::InvalidPose(m)) if m.contains("view 0")));
    let singular = [ViewProjection { width: 64, height: 64, view: good.world_to_camera(), projection: Mat4::ZERO }];
    assert!(matches!(s.pose_matrices(id, &singular, ms(1)), Err(SchedError::InvalidPose(_))));
    let fine = [ViewProjection { width: 64, height: 64, view: good.world_to_camera(), projection }];
    assert!(s.pose_matrices(id, &fine, ms(1)).is_ok());
    assert!(matches!(s.pose(id, &[], ms(1)), Err(SchedError::InvalidPose(_))));
    assert!(matches!(s.pose(id, &vec![good; 65], ms(1)), Err(SchedError::InvalidPose(_))));
    // A batch reported by a worker it was not sent to.
    s.add_worker(WorkerId(2), 1e6, ms(1)).expect("worker");
    let sent = dispatches(&s.tick(ms(1)));
    let (holder, batch) = (sent[0].0, sent[0].1.id);
    let other = if holder == WorkerId(1) { WorkerId(2) } else { WorkerId(1) };
    assert_eq!(s.batch_done(other, batch, ms(2)), Err(SchedError::NotAssigned { batch, worker: other }));
    assert_eq!(s.batch_failed(other, batch, ms(2)), Err(SchedError::NotAssigned { batch, worker: other }));
    // Objects: NaN bounds, inverted box, zero cost, a different object under a used id.
    let nan = ObjectInfo {
        bounds: Bounds { min: Vec3::NAN, max: Vec3::ONE },
        occupancy: None,
        cost_per_ray: 1.0,
        full_frame: false,
    };
    assert!(matches!(s.register_object(ObjectId(5), nan), Err(SchedError::InvalidObject { .. })));
    let inverted = ObjectInfo {
        bounds: Bounds { min: Vec3::ONE, max: Vec3::ZERO },
        occupancy: None,
        cost_per_ray: 1.0,
        full_frame: false,
    };
    assert!(s.register_object(ObjectId(5), inverted).is_err());
    assert!(s.register_object(ObjectId(5), unit_object(Vec3::ZERO, 1.0, 0.0)).is_err());
    assert!(s.register_object(OBJ, unit_object(Vec3::ZERO, 0.5, 1.0)).is_ok(), "same description again");
    assert_eq!(s.register_object(OBJ, unit_object(Vec3::ONE, 0.5, 1.0)), Err(SchedError::DuplicateObject(OBJ)));
    let cfg = SchedulerConfig { max_frames_in_flight: 0, ..Default::default() };
    assert!(matches!(Scheduler::new(cfg), Err(SchedError::InvalidConfig(_))));
    // The state is still consistent: the session renders.
    let all = run_to_quiet(
        &mut s,
        sent.into_iter().map(|(w, b)| Action::Dispatch { worker: w, batch: Box::new(b) }).collect(),
        ms(3),
    );
    assert!(!dispatches(&all).is_empty());
}

#[test]
fn closing_a_session_cancels_only_what_nobody_else_needs() {
    let mut cfg = config(Policy::Nephele);
    cfg.horizon = Duration::from_micros(1);
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    let shared = camera_at(0.0);
    let a = open(&mut s, 30.0, &[shared, camera_at(40.0)], ms(0));
    let b = open(&mut s, 30.0, &[shared], ms(0));
    let sent = dispatches(&s.tick(ms(0)));
    assert_eq!(sent.len(), 1);
    s.close_session(a, ms(1)).expect("close");
    let snapshot = s.snapshot(ms(1));
    assert_eq!(snapshot.sessions.len(), 1);
    assert_eq!(s.live_tasks(), 1, "the shared view lives on for B, A's own view is cancelled");
    let all = run_to_quiet(
        &mut s,
        sent.into_iter().map(|(w, b)| Action::Dispatch { worker: w, batch: Box::new(b) }).collect(),
        ms(2),
    );
    let done = completions(&all);
    assert!(done.iter().all(|c| c.0 == b) && !done.is_empty());
}

#[test]
fn every_policy_completes_frames_and_is_deterministic() {
    for policy in Policy::ALL {
        let run = || {
            let mut s = scheduler(config(policy));
            for w in 1..=3 {
                s.add_worker(WorkerId(w), 1e6 * f64::from(w), ms(0)).expect("worker");
            }
            let ids: Vec<SessionId> =
                (0..4).map(|i| open(&mut s, 30.0, &[camera_at(10.0 * i as f32)], ms(0))).collect();
            let mut log = Vec::new();
            for step in 0..40u64 {
                let now = ms(step * 10);
                for (i, id) in ids.iter().enumerate() {
                    s.pose(*id, &[camera_at(10.0 * i as f32 + step as f32)], now).expect("pose");
                }
                let actions = s.tick(now);
                for (w, b) in dispatches(&actions) {
                    s.batch_done(w, b.id, now + Duration::from_millis(3)).expect("done");
                }
                log.push(format!("{actions:?}"));
            }
            (log, s.stats().clone())
        };
        let (log, stats) = run();
        assert!(stats.frames_completed > 10, "{policy}: {stats:?}");
        assert_eq!(run().0, log, "{policy} is deterministic");
    }
}

#[test]
fn snapshot_serialises_for_the_farm_endpoint() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    s.tick(ms(0));
    let snapshot = s.snapshot(ms(5));
    let json = serde_json::to_string(&snapshot).expect("serialise");
    assert!(json.contains("\"policy\":\"nephele\"") && json.contains("target_fps"), "{json}");
    let back: FarmSnapshot = serde_json::from_str(&json).expect("deserialise");
    assert_eq!(back, snapshot);
    assert_eq!(snapshot.workers[0].mode, "light");
    assert!(snapshot.queues.in_flight_batches > 0);
}

#[test]
fn views_within_the_tolerance_share_and_the_error_is_measured() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
    let at = |x: f32| Camera::look_at(64, 64, 0.8, Vec3::new(x, -4.0, 0.0), Vec3::ZERO, Vec3::Z).expect("camera");
    // 0.2 mm apart, inside one 1 mm cell: one task, and a tiny but non-zero error.
    open(&mut s, 30.0, &[at(0.0001)], ms(0));
    open(&mut s, 30.0, &[at(0.0003)], ms(0));
    // 5 cm away: other rays.
    open(&mut s, 30.0, &[at(0.05)], ms(0));
    s.tick(ms(0));
    let stats = s.stats();
    assert_eq!((stats.tasks_created, stats.shared_joins), (2, 1));
    assert!(stats.share_error_px_max > 0.0 && stats.share_error_px_max < 0.05, "{}", stats.share_error_px_max);
    assert!(stats.share_error_px_mean() > 0.0);
}

#[test]
fn a_heavy_batch_that_timed_out_on_every_worker_is_still_reissued() {
    // Two workers, heavy tasks in one batch each; nobody answers. Once a batch has timed out
    // on every worker that may take it, it must go back to one of them, not wait forever for
    // another: the live farm froze a user's stream this way when a loaded machine made both
    // path tracers miss their deadlines. (Each worker renders its own batch, so the deadlines
    // are first stretched, `max_deadline_stretches` times, and each miss halves the holder's
    // trusted throughput: the second dispatch comes after tens of seconds, the third later.)
    let mut cfg = config(Policy::Nephele);
    cfg.heartbeat_timeout = None;
    cfg.max_batch_rays = 1 << 20;
    cfg.sharing = None;
    cfg.history_capacity = 0;
    let mut s = Scheduler::new(cfg).expect("config");
    s.register_object(OBJ, unit_object(Vec3::new(0.0, -2.0, 0.0), 0.8, 1.0)).expect("object");
    s.add_worker(WorkerId(1), 2e3, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 2e3, ms(0)).expect("worker");
    let id = s.open_session(SessionSpec { target_fps: 1.0, objects: vec![OBJ] }, ms(0)).expect("admitted");
    s.pose(id, &[camera_at(0.0)], ms(0)).expect("pose");
    let first = dispatches(&s.tick(ms(0)));
    assert_eq!(first.len(), 1);
    let (batch, class) = (first[0].1.id, first[0].1.class);
    assert_eq!(class, TaskClass::Heavy);
    let mut workers = vec![first[0].0];
    for t in (100..600_000).step_by(100) {
        for (w, b) in dispatches(&s.tick(ms(t))) {
            if b.id == batch {
                workers.push(w);
            }
        }
    }
    assert!(workers.len() >= 3, "the batch went to {workers:?} and then waited forever");
}

#[test]
fn admission_looks_ahead_at_the_farms_capacity() {
    let run = |admit_up_to: Option<f64>| {
        let mut cfg = config(Policy::Nephele);
        cfg.heartbeat_timeout = None;
        cfg.admit_up_to = admit_up_to;
        let mut s = scheduler(cfg);
        s.add_worker(WorkerId(1), 1e5, ms(0)).expect("worker");
        // Before any frame nothing is known of the work: the first user is admitted.
        let a = open(&mut s, 1.0, &[camera_at(0.0)], ms(0));
        s.tick(ms(0));
        let work = s.sessions.get(&a).and_then(|x| x.work_per_frame).expect("work of the released frame");
        assert!(work > 100.0, "{work}");
        // A rate at which two users at different angles fill 80 % of 0.9 x 1e5 rays/s.
        let fps = 0.9e5 / (2.5 * work);
        s.close_session(a, ms(1)).expect("close");
        let a = open(&mut s, fps, &[camera_at(0.0)], ms(2));
        s.tick(ms(2));
        let b = s.open_session(SessionSpec { target_fps: fps, objects: vec![OBJ] }, ms(3));
        let c = s.open_session(SessionSpec { target_fps: fps, objects: vec![OBJ] }, ms(4));
        let d = s.open_session(SessionSpec { target_fps: 0.1 * fps, objects: vec![OBJ] }, ms(5));
        (a, b, c, d, s)
    };
    let (_, b, c, d, mut s) = run(Some(0.9));
    assert!(b.is_ok(), "two users fit: {b:?}");
    assert!(
        matches!(c, Err(SchedError::Refused { retry_after }) if retry_after == Duration::from_secs(1)),
        "a third would pass 90 % of the capacity; the estimates are young, so ask again in 1 s: {c:?}"
    );
    assert!(d.is_ok(), "a slower one still fits: {d:?}");
    assert_eq!((s.stats().sessions_refused, s.stats().sessions_refused_capacity), (1, 1));
    // Once every admitted session's estimate has settled, the refusal says 5 s; a session
    // that has released no frame (no estimate of its own, perhaps never) does not hold it at 1 s.
    s.sessions.values_mut().for_each(|x| x.released = ESTIMATE_SETTLING_FRAMES);
    if let Some(x) = s.sessions.values_mut().next() {
        x.released = 0;
    }
    let fps = s.sessions.values().map(|x| x.fps).fold(0.0, f64::max);
    let c = s.open_session(SessionSpec { target_fps: fps, objects: vec![OBJ] }, ms(6));
    assert!(matches!(c, Err(SchedError::Refused { retry_after }) if retry_after == Duration::from_secs(5)), "{c:?}");
    // Off: only starvation refuses.
    let (_, b, c, d, s) = run(None);
    assert!(b.is_ok() && c.is_ok() && d.is_ok());
    assert_eq!(s.stats().sessions_refused, 0);
}

#[test]
fn a_user_sharing_every_ray_asks_nothing_of_the_farm() {
    let mut cfg = config(Policy::Nephele);
    cfg.heartbeat_timeout = None;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e5, ms(0)).expect("worker");
    let view = [camera_at(0.0)];
    let a = open(&mut s, 10.0, &view, ms(0));
    let b = open(&mut s, 10.0, &view, ms(0));
    s.tick(ms(0));
    let work = |id| s.sessions.get(&id).and_then(|x| x.work_per_frame);
    assert!(work(a).is_some_and(|w| w > 0.0));
    assert_eq!(work(b), Some(0.0), "b joined a's tasks");
}

/// Every pixel index of a set.
fn indices(set: &PixelSet) -> BTreeSet<u32> {
    set.indices().into_iter().collect()
}

#[test]
fn a_headsets_right_eye_rides_on_the_left_eyes_batches_and_completes_with_them() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
    let eyes = stereo_pair(&camera_at(0.0), 0.064).expect("eyes");
    let user = open(&mut s, 30.0, &eyes, ms(0));
    let actions = s.tick(ms(0));
    let sent = dispatches(&actions);
    assert!(!sent.is_empty());
    // Every batch is the left eye's (or the right eye's rows beyond them), and the right
    // eye's pixels in a batch's rows ride on it: whole rows, nothing twice.
    let key = sent[0].1.task;
    let mut right = BTreeSet::new();
    for (_, batch) in &sent {
        let rows: BTreeSet<u32> = batch.pixels.indices().iter().map(|p| p / 64).collect();
        for d in &batch.derived {
            assert_ne!(d.task, key);
            assert_eq!(d.camera, eyes[1]);
            assert!(d.pixels.indices().iter().all(|p| rows.contains(&(p / 64))), "rider outside its batch's rows");
            assert!(indices(&d.pixels).is_disjoint(&right));
            right.extend(indices(&d.pixels));
            assert_eq!(d.frames, vec![(user, FrameId(0))]);
        }
        let expected = batch.rays as f64 + 0.45 * batch.derived.iter().map(|d| d.rays as f64).sum::<f64>();
        assert!((batch.work_rays - expected).abs() < 1e-9);
    }
    assert!(!right.is_empty());
    let all = run_to_quiet(&mut s, actions, ms(1));
    let done = completions(&all);
    assert_eq!(done.len(), 1, "one frame");
    let parts = &done[0].2;
    assert_eq!(parts.len(), 2);
    assert_eq!(parts[0].source, PartSource::Rendered);
    assert_eq!(parts[1].source, PartSource::Derived);
    // The rider pixels plus the right eye's own batches are its whole coverage, once.
    let own: Vec<BatchSpec> =
        dispatches(&all).into_iter().map(|(_, b)| b).filter(|b| b.task == parts[1].task).collect();
    let mut covered = right.clone();
    for b in &own {
        assert!(indices(&b.pixels).is_disjoint(&covered));
        covered.extend(indices(&b.pixels));
    }
    assert_eq!(covered.len() as u64, parts[1].rays);
    let stats = s.stats();
    assert_eq!(stats.views_derived, 1);
    assert_eq!(stats.rays_derived, parts[1].rays);
}

#[test]
fn a_quilt_renders_a_few_keys_and_derives_the_rest_within_the_angle() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
    let centre = camera_at(0.0);
    let rig = nephele_geometry::camera::quilt_rig(&centre, 45, 40f32.to_radians(), 4.0).expect("rig");
    open(&mut s, 10.0, &rig, ms(0));
    let first = s.tick(ms(0));
    let all = run_to_quiet(&mut s, first, ms(1));
    let done = completions(&all);
    assert_eq!(done.len(), 1);
    let parts = &done[0].2;
    assert_eq!(parts.len(), 45);
    let keys: Vec<u32> = parts.iter().filter(|p| p.source == PartSource::Rendered).map(|p| p.view).collect();
    // 0.91 degrees between views: runs of up to 9 views within 8 degrees, keyed in the middle.
    assert_eq!(keys, vec![4, 13, 22, 31, 40]);
    assert!(parts.iter().all(|p| p.source != PartSource::Shared));
    // Each derived view is within 4 views (3.6 degrees) of a key.
    for p in parts.iter().filter(|p| p.source == PartSource::Derived) {
        assert!(keys.iter().any(|&k| k.abs_diff(p.view) <= 4), "view {}", p.view);
    }
    assert_eq!(s.stats().views_derived, 40);
}

#[test]
fn views_too_far_apart_or_derivation_switched_off_render_in_full() {
    let views = [camera_at(0.0), camera_at(10.0)];
    for derived in [true, false] {
        let mut cfg = config(Policy::Nephele);
        if !derived {
            cfg.derived_views = None;
        }
        let mut s = scheduler(cfg);
        s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
        // The headset stands far from the first user's views: its eyes pair with each other.
        let eyes = stereo_pair(&camera_at(60.0), 0.064).expect("eyes");
        open(&mut s, 30.0, &views, ms(0));
        open(&mut s, 30.0, &eyes, ms(0));
        let first = s.tick(ms(0));
        let all = run_to_quiet(&mut s, first, ms(1));
        assert!(dispatches(&all).iter().all(|(_, b)| derived || b.derived.is_empty()));
        let sources: Vec<Vec<PartSource>> =
            completions(&all).iter().map(|(_, _, parts)| parts.iter().map(|p| p.source).collect()).collect();
        assert_eq!(sources.len(), 2);
        // 10 degrees apart: both rendered whatever the setting.
        assert_eq!(sources[0], vec![PartSource::Rendered, PartSource::Rendered]);
        let right = if derived { PartSource::Derived } else { PartSource::Rendered };
        assert_eq!(sources[1], vec![PartSource::Rendered, right]);
    }
}

#[test]
fn a_user_two_degrees_from_another_rides_on_its_view_and_one_ten_degrees_away_does_not() {
    let mut s = scheduler(config(Policy::Nephele));
    s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
    let first = open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let near = open(&mut s, 30.0, &[camera_at(2.0)], ms(0));
    let far = open(&mut s, 30.0, &[camera_at(10.0)], ms(0));
    let actions = s.tick(ms(0));
    let sent = dispatches(&actions);
    // The near user's view rides on the first user's batches; the far one renders its own.
    let riders: Vec<(SessionId, SessionId)> =
        sent.iter().flat_map(|(_, b)| b.derived.iter().map(|d| (b.frames[0].0, d.frames[0].0))).collect();
    assert!(!riders.is_empty() && riders.iter().all(|&r| r == (first, near)), "{riders:?}");
    assert!(sent.iter().any(|(_, b)| b.frames[0].0 == far && b.derived.is_empty()));
    let all = run_to_quiet(&mut s, actions, ms(1));
    let done = completions(&all);
    let source = |user: SessionId| done.iter().find(|c| c.0 == user).map(|c| c.2[0].source);
    assert_eq!(source(first), Some(PartSource::Rendered));
    assert_eq!(source(near), Some(PartSource::Derived));
    assert_eq!(source(far), Some(PartSource::Rendered));
    assert_eq!(s.stats().views_derived, 1);
}

#[test]
fn a_derived_view_another_user_shares_survives_its_key_being_dropped() {
    let mut cfg = config(Policy::Nephele);
    cfg.history_capacity = 0;
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
    let eyes = stereo_pair(&camera_at(0.0), 0.064).expect("eyes");
    let headset = open(&mut s, 30.0, &eyes, ms(0));
    // A second user whose only view is the headset's right eye: it shares that task.
    let screen = open(&mut s, 30.0, &eyes[1..], ms(0));
    let first = s.tick(ms(0));
    let sent = dispatches(&first);
    assert!(sent.iter().any(|(_, b)| !b.derived.is_empty()));
    // The headset leaves before anything is rendered: its left eye (the key) is cancelled,
    // and the right eye, still needed by the screen, gets batches of its own.
    s.close_session(headset, ms(0)).expect("close");
    let after = s.tick(ms(0));
    let own: Vec<BatchSpec> = dispatches(&after).into_iter().map(|(_, b)| b).collect();
    assert!(!own.is_empty() && own.iter().all(|b| b.derived.is_empty() && b.frames[0].0 == screen));
    for (worker, batch) in &sent {
        let _ = s.batch_done(*worker, batch.id, ms(1)); // cancelled: unknown now, or ignored
    }
    let all = run_to_quiet(&mut s, after, ms(1));
    let done = completions(&all);
    assert_eq!(done.len(), 1);
    assert_eq!(done[0].0, screen);
    assert_eq!(done[0].2[0].source, PartSource::Shared);
}

#[test]
fn a_users_next_frame_never_rides_on_its_own_earlier_frame() {
    let mut s = scheduler(config(Policy::Nephele));
    // No worker yet: the first frame's task waits undispatched when the second is released.
    let user = open(&mut s, 30.0, &[camera_at(0.0)], ms(0));
    let _ = s.tick(ms(0));
    s.pose(user, &[camera_at(1.0)], ms(34)).expect("pose");
    let _ = s.tick(ms(34));
    s.add_worker(WorkerId(1), 1e7, ms(35)).expect("worker");
    let first = s.tick(ms(35));
    assert!(dispatches(&first).iter().all(|(_, b)| b.derived.is_empty()), "a frame rode on its predecessor");
    let all = run_to_quiet(&mut s, first, ms(36));
    assert!(completions(&all).iter().all(|(_, _, parts)| parts.iter().all(|p| p.source == PartSource::Rendered)));
    assert_eq!(s.stats().views_derived, 0);
}

/// The environment (a full-frame object, issue 13): one batch per view covering every pixel,
/// whatever the batch-size limit; a headset's two eyes in one batch (the right eye riding on
/// the left's, so the worker shades both in one stereo pass) even with reprojected views
/// switched off; a flat user's single view alone; objects inside it batched as before.
#[test]
fn an_environment_renders_whole_views_and_a_headsets_eyes_in_one_batch() {
    const ROOM: ObjectId = ObjectId(2);
    for derived_views in [true, false] {
        let mut cfg = config(Policy::Nephele);
        if !derived_views {
            cfg.derived_views = None;
        }
        let mut s = scheduler(cfg);
        let room = ObjectInfo { full_frame: true, ..unit_object(Vec3::ZERO, 6.0, 8.0) };
        s.register_object(ROOM, room).expect("room");
        s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
        let eyes = stereo_pair(&camera_at(0.0), 0.064).expect("eyes");
        let user = s.open_session(SessionSpec { target_fps: 30.0, objects: vec![OBJ, ROOM] }, ms(0)).expect("user");
        s.pose(user, &eyes, ms(0)).expect("pose");
        let first = s.tick(ms(0));
        let all = run_to_quiet(&mut s, first, ms(1));
        let room_batches: Vec<BatchSpec> =
            dispatches(&all).into_iter().map(|(_, b)| b).filter(|b| b.object == ROOM).collect();
        assert_eq!(room_batches.len(), 1, "both eyes in one batch");
        let batch = &room_batches[0];
        assert_eq!(batch.rays, 64 * 64, "every pixel of the left eye, beyond max_batch_rays = 128");
        assert_eq!(batch.camera, eyes[0]);
        assert_eq!(batch.derived.len(), 1);
        assert_eq!((batch.derived[0].camera, batch.derived[0].rays), (eyes[1], 64 * 64));
        // The object inside is split into batches as always.
        assert!(dispatches(&all).iter().filter(|(_, b)| b.object == OBJ).count() > 1);
        let done = completions(&all);
        assert_eq!(done.len(), 1);
        let room_parts: Vec<&FramePart> = done[0].2.iter().filter(|p| p.object == ROOM).collect();
        assert_eq!(room_parts.len(), 2);
        assert_eq!((room_parts[0].source, room_parts[1].source), (PartSource::Rendered, PartSource::Derived));

        // A flat user: one view, one whole batch, nothing derived.
        let flat = s.open_session(SessionSpec { target_fps: 30.0, objects: vec![ROOM] }, ms(100)).expect("flat");
        s.pose(flat, &[camera_at(30.0)], ms(100)).expect("pose");
        let first = s.tick(ms(100));
        let all = run_to_quiet(&mut s, first, ms(101));
        let sent: Vec<BatchSpec> = dispatches(&all).into_iter().map(|(_, b)| b).filter(|b| b.object == ROOM).collect();
        assert_eq!(sent.len(), 1);
        assert!(sent[0].derived.is_empty() && sent[0].rays == 64 * 64);
    }
}

/// With two workers an environment's view is two bands of whole rows (as many as workers,
/// none under `max_batch_rays`, so that they can spread); the right eye's rows ride on the
/// left eye's band of the same rows.
#[test]
fn an_environments_view_is_split_into_row_bands_one_per_worker() {
    const ROOM: ObjectId = ObjectId(2);
    let mut cfg = config(Policy::Nephele);
    cfg.max_batch_rays = 1024;
    let mut s = scheduler(cfg);
    s.register_object(ROOM, ObjectInfo { full_frame: true, ..unit_object(Vec3::ZERO, 6.0, 1.0) }).expect("room");
    s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 1e7, ms(0)).expect("worker");
    let eyes = stereo_pair(&camera_at(0.0), 0.064).expect("eyes");
    let user = s.open_session(SessionSpec { target_fps: 30.0, objects: vec![ROOM] }, ms(0)).expect("user");
    s.pose(user, &eyes, ms(0)).expect("pose");
    let first = s.tick(ms(0));
    let all = run_to_quiet(&mut s, first, ms(1));
    let sent: Vec<(WorkerId, BatchSpec)> = dispatches(&all);
    assert_eq!(sent.len(), 2, "two bands");
    let mut rows_seen = BTreeSet::new();
    for (_, b) in &sent {
        let rows: BTreeSet<u32> = b.pixels.indices().iter().map(|p| p / 64).collect();
        assert_eq!(b.rays, 64 * rows.len() as u64, "whole rows");
        assert!(rows.iter().all(|r| rows_seen.insert(*r)), "bands are disjoint");
        assert_eq!(b.derived.len(), 1);
        let right: BTreeSet<u32> = b.derived[0].pixels.indices().iter().map(|p| p / 64).collect();
        assert_eq!(right, rows, "the right eye's same rows ride on the band");
    }
    assert_eq!(rows_seen.len(), 64);
    assert_eq!(completions(&all).len(), 1);
}

/// `BatchSpec::rows_complete` is true exactly when no other batch of the task shares a row
/// with it (a worker then takes the rest of the batch's box for empty space).
#[test]
fn a_batch_says_whether_it_holds_whole_rows_of_its_task() {
    for (max_batch_rays, whole) in [(1 << 20, Some(true)), (8, None)] {
        let mut s = scheduler(SchedulerConfig { max_batch_rays, ..config(Policy::Nephele) });
        s.add_worker(WorkerId(1), 1e8, ms(0)).expect("worker");
        open(&mut s, 30.0, &[camera_at(10.0)], ms(0));
        let first = s.tick(ms(0));
        let sent = dispatches(&run_to_quiet(&mut s, first, ms(1)));
        assert!(!sent.is_empty());
        let rows = |b: &BatchSpec| -> BTreeSet<u32> { indices(&b.pixels).iter().map(|p| p / 64).collect() };
        let mut split = false;
        for (_, batch) in &sent {
            let shares_a_row = sent
                .iter()
                .filter(|(_, other)| other.task == batch.task && other.id != batch.id)
                .any(|(_, other)| !rows(other).is_disjoint(&rows(batch)));
            assert_eq!(batch.rows_complete, !shares_a_row, "batch {:?}", batch.id);
            split |= shares_a_row;
        }
        match whole {
            Some(true) => assert!(sent.iter().all(|(_, b)| b.rows_complete), "one batch per task"),
            _ => assert!(split, "batches of 8 rays must cut rows wider than 8 pixels"),
        }
    }
}

/// NEPHELE with render-ahead on, no heartbeats, no timeouts.
fn ahead_config() -> SchedulerConfig {
    let mut cfg = config(Policy::Nephele);
    cfg.render_ahead = Some(crate::RenderAhead::default());
    cfg.heartbeat_timeout = None;
    cfg.min_batch_timeout = Duration::from_secs(10);
    cfg
}

/// One worker of 1e6 rays/s and a 10-fps user that turned from 0 to `to_deg` degrees between
/// its poses at 0 and 20 ms.
fn one_user_turning(cfg: SchedulerConfig, to_deg: f32) -> (Scheduler, SessionId) {
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    let a = open(&mut s, 10.0, &[camera_at(0.0)], ms(0));
    s.pose(a, &[camera_at(to_deg)], ms(20)).expect("pose");
    (s, a)
}

/// Ticks at 20 ms and completes everything at 25 ms.
fn first_frame_done(s: &mut Scheduler) -> Vec<Action> {
    let first = s.tick(ms(20));
    run_to_quiet(s, first, ms(25))
}

fn aheads(actions: &[Action]) -> Vec<(WorkerId, BatchSpec)> {
    dispatches(actions).into_iter().filter(|(_, b)| b.ahead_for.is_some()).collect()
}

#[test]
fn an_idle_farm_renders_a_moving_users_next_view_ahead() {
    let mut s = scheduler(ahead_config());
    s.add_worker(WorkerId(1), 1e6, ms(0)).expect("worker");
    s.add_worker(WorkerId(2), 1e6, ms(0)).expect("worker");
    // 10 fps, turning 2 degrees every 20 ms (a pose per 20 ms, as the client sends them).
    let a = open(&mut s, 10.0, &[camera_at(0.0)], ms(0));
    s.pose(a, &[camera_at(2.0)], ms(20)).expect("pose");
    // Frame 0 released at 0 renders; nothing ahead while it runs.
    let actions = s.tick(ms(20));
    assert!(!dispatches(&actions).is_empty());
    assert!(aheads(&actions).is_empty(), "a busy farm renders nothing ahead");
    let all = run_to_quiet(&mut s, actions, ms(25));
    assert_eq!(completions(&all).len(), 1);
    // Once the farm is idle, the next release (100 ms) is predicted: 2 degrees per 20 ms from
    // the pose of 20 ms, 80 ms on, is 10 degrees.
    let ahead = aheads(&all);
    assert!(!ahead.is_empty(), "the idle farm renders ahead");
    for (_, b) in &ahead {
        assert_eq!(b.ahead_for, Some(a));
        assert!(b.frames.is_empty(), "no frame waits for a render ahead");
        let expected = camera_at(10.0).position();
        assert!(b.camera.position().distance(expected) < 0.05, "{} vs {expected}", b.camera.position());
    }
    let stats = s.stats().clone();
    assert_eq!(stats.ahead_tasks, 1);
    assert_eq!(stats.ahead_tasks_done, 1, "run_to_quiet completed it");
    assert_eq!(stats.tasks_created, 1, "a render ahead is not a frame's task");
    assert!(!all.iter().any(|x| matches!(x, Action::ReleaseResult { .. })), "no result went to the composer");
    // Once per release: the idle farm does not render the same prediction again.
    assert!(aheads(&s.tick(ms(30))).is_empty());
    // The frame of 100 ms renders as usual; after it, the next release is predicted again.
    s.pose(a, &[camera_at(20.0)], ms(100)).expect("pose");
    let all = {
        let first = s.tick(ms(100));
        run_to_quiet(&mut s, first, ms(105))
    };
    assert_eq!(completions(&all).len(), 1);
    assert!(!aheads(&all).is_empty());
    assert_eq!(s.stats().ahead_tasks, 2);
    assert!(s.live_tasks() <= 1, "done renders ahead leave the scheduler");
}

#[test]
fn render_ahead_waits_for_spare_capacity_motion_and_being_asked() {
    // Off by default.
    let (mut off, _) = one_user_turning(SchedulerConfig { heartbeat_timeout: None, ..config(Policy::Nephele) }, 2.0);
    let all = first_frame_done(&mut off);
    assert!(aheads(&all).is_empty());
    assert_eq!(off.stats().ahead_tasks, 0);
    // A user standing still: the history table serves the same pose, nothing is predicted.
    let (mut s, _) = one_user_turning(ahead_config(), 0.0);
    let all = first_frame_done(&mut s);
    assert!(aheads(&all).is_empty());
    // Ahead work must fit the farm's spare time before the next release: a budget of a
    // billionth of it fits nothing.
    let mut cfg = ahead_config();
    cfg.render_ahead = Some(crate::RenderAhead { budget_fraction: 1e-9 });
    let (mut tight, _) = one_user_turning(cfg, 2.0);
    let all = first_frame_done(&mut tight);
    assert!(aheads(&all).is_empty(), "ahead work must end before the next release");
}

#[test]
fn renders_ahead_go_first_where_most_views_share_them_and_are_never_retried() {
    let mut cfg = ahead_config();
    cfg.render_ahead = Some(crate::RenderAhead { budget_fraction: 1.0 });
    let mut s = scheduler(cfg);
    s.add_worker(WorkerId(1), 1e7, ms(0)).expect("worker");
    // Two users a degree apart, one far round the object.
    let near_a = open(&mut s, 10.0, &[camera_at(0.0)], ms(0));
    let near_b = open(&mut s, 10.0, &[camera_at(1.0)], ms(0));
    let far = open(&mut s, 10.0, &[camera_at(120.0)], ms(0));
    s.pose(far, &[camera_at(121.0)], ms(20)).expect("pose");
    s.pose(near_a, &[camera_at(0.5)], ms(20)).expect("pose");
    s.pose(near_b, &[camera_at(1.5)], ms(20)).expect("pose");
    let all = {
        let first = s.tick(ms(20));
        run_to_quiet(&mut s, first, ms(25))
    };
    let mut order: Vec<SessionId> = aheads(&all).iter().filter_map(|(_, b)| b.ahead_for).collect();
    order.dedup();
    // The pair's predictions (a degree apart) share one render, sent first; the far user's
    // comes after it.
    assert_eq!(order.len(), 2, "{order:?}");
    assert!(order[0] == near_a || order[0] == near_b, "shared first: {order:?}");
    assert_eq!(order[1], far);
    assert_eq!(s.stats().ahead_tasks, 2);
    assert_eq!(s.stats().ahead_views_covered, 1);
    // A render ahead whose worker is lost is dropped, not re-issued; closing a session ends
    // its renders ahead.
    let (mut s, _) = one_user_turning(ahead_config(), 2.0);
    let first = s.tick(ms(20));
    for (w, b) in dispatches(&first) {
        s.batch_done(w, b.id, ms(25)).expect("done");
    }
    let ahead = aheads(&s.tick(ms(25)));
    assert!(!ahead.is_empty());
    let reissued = s.stats().batches_reissued;
    s.add_worker(WorkerId(2), 1e6, ms(26)).expect("worker");
    s.remove_worker(WorkerId(1), ms(26)).expect("removed");
    assert_eq!(s.stats().batches_reissued, reissued, "not re-issued");
    assert!(aheads(&s.tick(ms(27))).is_empty(), "not sent again for the same release");
    assert_eq!(s.pending_batches(), 0);
    assert!(s.batch_done(WorkerId(2), ahead[0].1.id, ms(28)).is_err(), "it is gone");
    // A session closed while its render ahead runs: the batches are cancelled.
    let (mut s, a) = one_user_turning(ahead_config(), 2.0);
    for (w, b) in dispatches(&s.tick(ms(20))) {
        s.batch_done(w, b.id, ms(25)).expect("done");
    }
    let ahead = aheads(&s.tick(ms(25)));
    assert!(!ahead.is_empty());
    s.close_session(a, ms(26)).expect("closed");
    let cancels = s.tick(ms(26)).iter().filter(|x| matches!(x, Action::Cancel { .. })).count();
    assert_eq!(cancels, ahead.len());
    assert_eq!(s.live_tasks(), 0);
}
