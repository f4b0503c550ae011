//! A real `nephele master` with real `nephele worker` processes over loopback; the test plays
//! the composer (over TCP, as the protocol says) and the browser (over HTTP/1.1).
//!
//! * `a_live_farm_renders_frames_end_to_end_and_survives_a_killed_worker`: two workers, a
//!   session opened through `POST /v1/sessions`, poses in, frame plans out whose tasks'
//!   results cover every pixel the object covers and match the path tracer computed here
//!   bit for bit; `GET /v1/farm`; a worker frozen and SIGKILLed while it holds a batch, frames
//!   still complete; `DELETE`; SIGTERM: the master exits 0 and says goodbye to everyone.
//! * `admission_control_refuses_while_a_user_is_starved_and_bad_requests_are_answered`: no
//!   composer (503), a second composer (refused), bad JSON (400), unknown and wrong tokens
//!   (404, 401), an offer the composer refuses (400), a starved user (503 + Retry-After)
//!   and recovery once it leaves.

use std::collections::{HashMap, HashSet};
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::mpsc::{Receiver, channel};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use glam::{Mat4, Vec3};
use nephele_geometry::camera::Camera;
use nephele_kernels::kernel::{PathTracedKernel, PixelResults, RayKernel, all_pixels};
use nephele_pathtracer::Renderer;
use nephele_pathtracer::scenes;
use nephele_proto::{
    BatchResult, ClientPose, ComposerRegister, ErrorCode, FrameConfig, FramePlan, FrameReader, FrameWriter, Message,
    ResultEncoding, Role, StreamOpened, ViewProjection,
};
use nephele_tests::{metric_value, nephele_bin};
use serde_json::{Value, json};

const WAIT: Duration = Duration::from_secs(30);
const ANSWER: &str = "v=0\r\no=- 1 1 IN IP4 127.0.0.1\r\ns=nephele-test-composer\r\n";
const OFFER: &str = "v=0\r\no=- 1 1 IN IP4 127.0.0.1\r\ns=-\r\nm=video 9 UDP/TLS/RTP/SAVPF 96\r\n";
/// The workers' path tracer settings (the reference uses the same).
const SPP: u32 = 1;
const BOUNCES: u32 = 2;

fn logs() -> bool {
    std::env::var_os("NEPHELE_TEST_LOGS").is_some()
}

// ---------------------------------------------------------------------------------------
// Processes

struct Process {
    child: Child,
    name: String,
}

impl Process {
    fn signal(&self, signal: &str) {
        let status = Command::new("kill").args([signal, &self.child.id().to_string()]).status().expect("kill");
        assert!(status.success(), "kill {signal} {}", self.name);
    }

    fn wait(&mut self, timeout: Duration) -> ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                return status;
            }
            assert!(start.elapsed() < timeout, "{} did not exit within {timeout:?}", self.name);
            thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

struct MasterProcess {
    process: Process,
    http: SocketAddr,
    farm: SocketAddr,
    _stdout: BufReader<ChildStdout>,
}

impl MasterProcess {
    fn start(extra: &[&str]) -> MasterProcess {
        MasterProcess::start_with(extra, &[])
    }

    fn start_with(extra: &[&str], env: &[(&str, &str)]) -> MasterProcess {
        let mut child = Command::new(nephele_bin())
            .args([
                "--quiet",
                "master",
                "--http",
                "127.0.0.1:0",
                "--farm-listen",
                "127.0.0.1:0",
                "--admit-up-to",
                "off",
            ])
            .args(extra)
            .envs(env.iter().copied())
            .env("NEPHELE_LOG", if logs() { "debug" } else { "warn" })
            .stdout(Stdio::piped())
            .stderr(if logs() { Stdio::inherit() } else { Stdio::null() })
            .spawn()
            .expect("starting nephele master");
        let mut stdout = BufReader::new(child.stdout.take().expect("stdout"));
        let mut line = String::new();
        stdout.read_line(&mut line).expect("the master's first line");
        // "listening: http=ADDR farm=ADDR"
        let field = |key: &str| -> SocketAddr {
            let start = line.find(key).unwrap_or_else(|| panic!("{key} missing in {line:?}")) + key.len();
            line[start..].split_whitespace().next().expect("address").parse().expect("socket address")
        };
        let (http, farm) = (field("http="), field("farm="));
        MasterProcess { process: Process { child, name: "master".into() }, http, farm, _stdout: stdout }
    }
}

/// A worker whose log goes to `log` (to check what the master told it). Worker "alpha" sends
/// exact f32 results, every other one compact results (the default), so the end-to-end check
/// sees both encodings.
fn start_worker(farm: SocketAddr, assets: &Path, name: &str, log: &Path) -> Process {
    start_worker_with(farm, assets, name, log, &[])
}

fn start_worker_with(farm: SocketAddr, assets: &Path, name: &str, log: &Path, env: &[(&str, &str)]) -> Process {
    let file = std::fs::File::create(log).expect("worker log");
    let child = Command::new(nephele_bin())
        .envs(env.iter().copied())
        .args(["--quiet", "--threads", "1", "worker", "--master", &farm.to_string(), "--name", name])
        .arg("--assets")
        .arg(assets)
        .args(["--spp", &SPP.to_string(), "--bounces", &BOUNCES.to_string(), "--reconnect-secs", "60"])
        .args(["--results", if name == "alpha" { "f32" } else { "compact" }])
        .env("NEPHELE_LOG", if logs() { "debug" } else { "info" })
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(file)
        .spawn()
        .expect("starting nephele worker");
    Process { child, name: name.into() }
}

// ---------------------------------------------------------------------------------------
// HTTP through the workspace's one client

struct Response {
    status: u16,
    headers: HashMap<String, String>,
    body: Value,
}

fn http(addr: SocketAddr, method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> Response {
    let url = format!("http://{addr}{path}");
    let r = nephele_loadgen::http::request_blocking(&url, method, headers, body, WAIT).expect("an HTTP answer");
    let body = serde_json::from_str(&r.body).unwrap_or(Value::Null);
    Response { status: r.status, headers: r.headers.into_iter().collect(), body }
}

fn farm_state(master: &MasterProcess) -> Value {
    let r = http(master.http, "GET", "/v1/farm", &[], "");
    assert_eq!(r.status, 200);
    r.body
}

/// Polls `GET /v1/farm` until `ready` holds.
fn wait_for_farm(master: &MasterProcess, what: &str, ready: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let state = farm_state(master);
        if ready(&state) {
            return state;
        }
        assert!(start.elapsed() < WAIT, "timed out waiting for {what}: {state:#}");
        thread::sleep(Duration::from_millis(20));
    }
}

fn open_session(master: &MasterProcess, body: Value) -> Response {
    http(master.http, "POST", "/v1/sessions", &[], &body.to_string())
}

fn delete_session(master: &MasterProcess, id: &str, token: &str) -> u16 {
    http(master.http, "DELETE", &format!("/v1/sessions/{id}"), &[("Authorization", &format!("Bearer {token}"))], "")
        .status
}

// ---------------------------------------------------------------------------------------
// The composer double: one link to the master (answers offers by itself), one listener
// for the workers' results.

struct TestComposer {
    writer: Arc<Mutex<FrameWriter<TcpStream>>>,
    messages: Receiver<Message>,
    results: Receiver<BatchResult>,
    /// Results by task.
    store: HashMap<u64, Vec<BatchResult>>,
    released: HashSet<u64>,
}

/// Connects to the master as a composer; `Err` with what the master said if it refused.
fn connect_composer(farm: SocketAddr, name: &str) -> Result<TestComposer, Box<Message>> {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind results");
    let results_address = listener.local_addr().expect("addr").to_string();
    let (results_tx, results) = channel();
    thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(stream) = stream else { return };
            let tx = results_tx.clone();
            thread::spawn(move || {
                let mut reader =
                    FrameReader::new(BufReader::new(stream.try_clone().expect("clone")), FrameConfig::default());
                let mut writer = FrameWriter::new(stream, FrameConfig::default());
                if nephele_proto::frame::handshake(&mut reader, &mut writer, Role::Composer, &[Role::Worker], None)
                    .is_err()
                {
                    return;
                }
                while let Ok(incoming) = reader.read_message() {
                    match incoming {
                        Ok(Message::BatchResult(result)) => {
                            if tx.send(result).is_err() {
                                return;
                            }
                        }
                        other => panic!("a worker sent the composer {other:?}"),
                    }
                }
            });
        }
    });

    let stream = TcpStream::connect(farm).expect("connect to the farm port");
    stream.set_nodelay(true).expect("nodelay");
    let mut reader = FrameReader::new(BufReader::new(stream.try_clone().expect("clone")), FrameConfig::default());
    let mut writer = FrameWriter::new(stream, FrameConfig::default());
    nephele_proto::frame::handshake(&mut reader, &mut writer, Role::Composer, &[Role::Master], None)
        .expect("handshake with the master");
    writer
        .write_message(&Message::ComposerRegister(ComposerRegister { name: name.into(), results_address }))
        .expect("register");
    writer.flush().expect("flush");
    match reader.read_message() {
        Ok(Ok(Message::Registered(_))) => {}
        Ok(Ok(other)) => return Err(Box::new(other)),
        other => panic!("no answer to the registration: {other:?}"),
    }
    let writer = Arc::new(Mutex::new(writer));
    let (tx, messages) = channel();
    let answer_with = writer.clone();
    thread::spawn(move || {
        while let Ok(Ok(message)) = reader.read_message() {
            if let Message::OpenStream(open) = &message {
                let answer = if open.offer_sdp.contains("refuse-me") {
                    Err("no H.264 in the offer".to_string())
                } else {
                    Ok(ANSWER.to_string())
                };
                let mut w = answer_with.lock().expect("writer");
                w.write_message(&Message::StreamOpened(StreamOpened { session_id: open.session_id, answer }))
                    .expect("answer");
                w.flush().expect("flush");
            }
            if tx.send(message).is_err() {
                return;
            }
        }
    });
    Ok(TestComposer { writer, messages, results, store: HashMap::new(), released: HashSet::new() })
}

impl TestComposer {
    fn send(&self, message: &Message) {
        let mut w = self.writer.lock().expect("writer");
        w.write_message(message).expect("send to the master");
        w.flush().expect("flush");
    }

    /// The next message from the master other than a `ReleaseTask` (those are recorded).
    fn next(&mut self) -> Message {
        loop {
            match self.messages.recv_timeout(WAIT).expect("a message from the master") {
                Message::ReleaseTask(r) => {
                    self.released.insert(r.task_id);
                }
                other => return other,
            }
        }
    }

    fn next_plan(&mut self) -> FramePlan {
        loop {
            match self.next() {
                Message::FramePlan(plan) => return plan,
                Message::OpenStream(_) => {}
                other => panic!("expected a frame plan, got {other:?}"),
            }
        }
    }

    fn collect_results(&mut self) {
        while let Ok(r) = self.results.try_recv() {
            self.store.entry(r.ids.task_id).or_default().push(r);
        }
    }

    /// Waits until the results of the plan's tasks cover every pixel the reference covers,
    /// then checks every delivered pixel against the reference bit for bit. Returns the
    /// number of result pixels checked.
    fn verify(&mut self, plan: &FramePlan, expected: &PixelResults) -> usize {
        assert_eq!(plan.views, 1);
        assert!(!plan.parts.is_empty(), "the object is in view: {plan:?}");
        let tasks: Vec<u64> = plan.parts.iter().map(|p| p.task_id).collect();
        let start = Instant::now();
        let missing = loop {
            self.collect_results();
            let mut seen = vec![false; expected.len()];
            for r in tasks.iter().filter_map(|t| self.store.get(t)).flatten() {
                assert_eq!((r.width, r.height), (plan.width, plan.height));
                for &p in &r.pixels {
                    seen[p as usize] = true;
                }
            }
            let missing: Vec<usize> = (0..expected.len()).filter(|&p| expected.opacity[p] > 0.0 && !seen[p]).collect();
            if missing.is_empty() || start.elapsed() > Duration::from_secs(5) {
                break missing;
            }
            thread::sleep(Duration::from_millis(5));
        };
        assert!(
            missing.is_empty(),
            "frame {}: {} covered pixels without a result, e.g. {:?}",
            plan.frame_id,
            missing.len(),
            &missing[..missing.len().min(5)]
        );
        let mut checked = 0;
        for r in tasks.iter().filter_map(|t| self.store.get(t)).flatten() {
            for (k, &p) in r.pixels.iter().enumerate() {
                let p = p as usize;
                match r.encoding {
                    ResultEncoding::F32 => {
                        assert_eq!(r.color[k], expected.color[p], "frame {} pixel {p} colour", plan.frame_id);
                        assert_eq!(r.opacity[k], expected.opacity[p], "frame {} pixel {p} opacity", plan.frame_id);
                        assert_eq!(r.depth[k], expected.depth[p], "frame {} pixel {p} depth", plan.frame_id);
                    }
                    // Half floats and 16-bit opacity: the error `nephele_proto::compact` states.
                    ResultEncoding::Compact => {
                        let half = |want: f32, got: f32| (want - got).abs() <= want.abs() * 2f32.powi(-11) + 1e-7;
                        for c in 0..3 {
                            assert!(
                                half(expected.color[p][c], r.color[k][c]),
                                "frame {} pixel {p} colour",
                                plan.frame_id
                            );
                        }
                        assert!((expected.opacity[p] - r.opacity[k]).abs() <= 1.0 / 131070.0 + 1e-7);
                        assert!(half(expected.depth[p], r.depth[k]), "frame {} pixel {p} depth", plan.frame_id);
                    }
                }
                checked += 1;
            }
        }
        checked
    }
}

// ---------------------------------------------------------------------------------------
// Poses and references

struct View {
    width: u32,
    height: u32,
    eye: Vec3,
    target: Vec3,
    fov_y: f32,
}

impl View {
    /// The default view of a built-in object scene, orbited about the vertical axis by
    /// `sequence` half degrees (a pose per sequence number, never the same twice).
    fn pose(&self, sequence: u32) -> ViewProjection {
        let angle = (sequence as f32 * 0.5).to_radians();
        let eye = self.target + Mat4::from_rotation_z(angle).transform_vector3(self.eye - self.target);
        let camera = Camera::look_at(self.width, self.height, self.fov_y, eye, self.target, Vec3::Z).expect("camera");
        ViewProjection::of_camera(&camera, 0.05, 100.0)
    }
}

fn client_pose(session_id: u64, sequence: u32, camera: ViewProjection) -> Message {
    Message::ClientPose(ClientPose {
        session_id,
        sequence,
        client_time_ms: f64::from(sequence) * 20.0,
        views: vec![camera],
    })
}

/// What the workers must deliver for a pose: the same conversions as the master (pose
/// matrices to the scheduler's camera, `wire_camera` into the object's frame) and the
/// worker (wire camera to camera), then the path tracer on every pixel.
struct Reference {
    kernel: PathTracedKernel,
    cache: HashMap<u32, PixelResults>,
}

impl Reference {
    fn new(scene: &str) -> Reference {
        let scene = scenes::builtin(scene).expect("scene");
        let kernel =
            PathTracedKernel::new(Renderer::new(scene.scene).expect("renderer"), SPP, BOUNCES).expect("kernel");
        Reference { kernel, cache: HashMap::new() }
    }

    fn for_pose(&mut self, sequence: u32, pose: &ViewProjection) -> &PixelResults {
        let kernel = &self.kernel;
        self.cache.entry(sequence).or_insert_with(|| {
            let to_camera = |w: &ViewProjection| w.camera().expect("camera");
            let scheduled = to_camera(pose);
            let worker = to_camera(&nephele_master::farm::wire_camera(&scheduled, Vec3::ZERO));
            kernel.render_pixels(&worker, &all_pixels(&worker)).expect("reference render").0
        })
    }
}

type SendTimes = Arc<Mutex<HashMap<u32, Instant>>>;

/// Sends a pose every 20 ms from a thread until stopped, noting when each left.
struct PoseSender {
    stop: Arc<AtomicBool>,
    handle: Option<thread::JoinHandle<()>>,
    sent: SendTimes,
}

impl PoseSender {
    fn start(
        writer: Arc<Mutex<FrameWriter<TcpStream>>>,
        session_id: u64,
        view: View,
        next: Arc<AtomicU32>,
    ) -> PoseSender {
        let stop = Arc::new(AtomicBool::new(false));
        let sent = SendTimes::default();
        let (flag, times) = (stop.clone(), sent.clone());
        let handle = thread::spawn(move || {
            while !flag.load(Ordering::Relaxed) {
                let sequence = next.fetch_add(1, Ordering::Relaxed);
                let message = client_pose(session_id, sequence, view.pose(sequence));
                {
                    let mut w = writer.lock().expect("writer");
                    if w.write_message(&message).and_then(|()| w.flush()).is_err() {
                        return;
                    }
                }
                times.lock().expect("times").insert(sequence, Instant::now());
                thread::sleep(Duration::from_millis(20));
            }
        });
        PoseSender { stop, handle: Some(handle), sent }
    }
}

impl Drop for PoseSender {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

fn object_view(scene: &str, width: u32, height: u32) -> View {
    let (eye, target, fov_y) = scenes::builtin(scene).expect("scene").default_view();
    View { width, height, eye, target, fov_y }
}

fn worker_id(state: &Value, name: &str) -> u64 {
    state["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .find(|w| w["name"] == name)
        .and_then(|w| w["id"].as_u64())
        .expect("worker id")
}

fn in_flight(state: &Value, id: u64) -> u64 {
    state["scheduler"]["workers"]
        .as_array()
        .expect("scheduler workers")
        .iter()
        .find(|w| w["id"].as_u64() == Some(id))
        .and_then(|w| w["in_flight_batches"].as_u64())
        .unwrap_or(0)
}

// ---------------------------------------------------------------------------------------
// Tests

#[test]
fn a_live_farm_renders_frames_end_to_end_and_survives_a_killed_worker() {
    let dir = tempfile::tempdir().expect("temp dir");
    let assets = dir.path().join("assets");
    std::fs::create_dir(&assets).expect("assets");
    // Small batches, so that a frame spreads over both workers.
    let mut master = MasterProcess::start(&["--max-batch-rays", "256"]);
    let logs: Vec<PathBuf> = ["alpha", "beta"].iter().map(|n| dir.path().join(format!("{n}.log"))).collect();
    let mut workers: Vec<Process> =
        ["alpha", "beta"].iter().zip(&logs).map(|(n, log)| start_worker(master.farm, &assets, n, log)).collect();
    let mut composer = connect_composer(master.farm, "composer-test").expect("composer registered");
    let state = wait_for_farm(&master, "two workers", |s| s["workers"].as_array().is_some_and(|w| w.len() == 2));
    assert_eq!(state["composer"]["name"], "composer-test");

    // Open a session as a browser would.
    let (width, height) = (64, 48);
    let r = open_session(
        &master,
        json!({ "sdp": OFFER, "scene": "diffuse", "views": 1, "width": width, "height": height, "target_fps": 30 }),
    );
    assert_eq!(r.status, 201, "{}", r.body);
    assert_eq!(r.body["sdp"], ANSWER);
    let (name, token) =
        (r.body["session_id"].as_str().expect("id").to_string(), r.body["token"].as_str().expect("token").to_string());
    let open = match composer.next() {
        Message::OpenStream(open) => open,
        other => panic!("expected the offer, got {other:?}"),
    };
    assert_eq!(
        (open.session_name.as_str(), open.offer_sdp.as_str(), open.views, open.width, open.height),
        (name.as_str(), OFFER, 1, width, height)
    );
    assert_eq!(open.target_fps, 30.0);
    let sid = open.session_id;

    // One pose: the first frame plan is for it, and its results are the path tracer's.
    let view = object_view("diffuse", width, height);
    let mut reference = Reference::new("diffuse");
    let pose = view.pose(1);
    let sent = Instant::now();
    composer.send(&client_pose(sid, 1, pose));
    let plan = composer.next_plan();
    let first_plan_ms = sent.elapsed().as_secs_f64() * 1e3;
    assert_eq!((plan.session_id, plan.pose_sequence, plan.client_time_ms), (sid, 1, 20.0));
    assert_eq!((plan.width, plan.height, plan.views), (width, height, 1));
    assert!(plan.parts.iter().all(|p| p.view == 0) && plan.parts.len() == 1, "{plan:?}");
    assert!(plan.deadline_in_us.is_some());
    let checked = composer.verify(&plan, reference.for_pose(1, &pose));
    let covered = reference.for_pose(1, &pose).opacity.iter().filter(|&&a| a > 0.0).count();
    assert!(checked >= covered && covered > 100, "checked {checked} pixels, the object covers {covered}");
    eprintln!("pose to first frame plan over loopback: {first_plan_ms:.1} ms ({covered} pixels covered)");

    // The farm state shows both workers and the session.
    let state = farm_state(&master);
    assert_eq!(state["workers"].as_array().map(Vec::len), Some(2), "{state:#}");
    assert_eq!(state["scheduler"]["workers"].as_array().map(Vec::len), Some(2));
    assert_eq!(state["sessions"][0]["id"], name.as_str());
    assert_eq!(state["sessions"][0]["scheduler_id"], sid);
    assert_eq!(state["sessions_open"], 1);
    assert_eq!(state["scheduler"]["sessions"].as_array().map(Vec::len), Some(1));
    assert!(state["sessions"][0]["frames_planned"].as_u64() >= Some(1));
    let batches_before = state["live"]["batches_sent"].as_u64().expect("batches sent");
    assert!(batches_before >= 2, "a frame of {covered} pixels in batches of 256: {state:#}");

    // Moving poses keep the workers busy; freeze one worker until it holds a batch, then
    // SIGKILL it: every later frame is still complete.
    let next = Arc::new(AtomicU32::new(2));
    let poses = PoseSender::start(composer.writer.clone(), sid, object_view("diffuse", width, height), next.clone());
    let victim_id = worker_id(&state, "beta");
    workers[1].signal("-STOP");
    wait_for_farm(&master, "a batch on the frozen worker", |s| in_flight(s, victim_id) > 0);
    workers[1].child.kill().expect("SIGKILL");
    let killed_at = next.load(Ordering::Relaxed);
    assert!(!workers[1].wait(Duration::from_secs(5)).success());
    let mut verified = 0;
    let start = Instant::now();
    while verified < 5 {
        let plan = composer.next_plan();
        if plan.pose_sequence <= killed_at {
            continue;
        }
        let pose = view.pose(plan.pose_sequence);
        composer.verify(&plan, reference.for_pose(plan.pose_sequence, &pose));
        verified += 1;
        assert!(start.elapsed() < WAIT, "frames stopped after the kill");
    }
    drop(poses);
    let state = wait_for_farm(&master, "one worker left", |s| s["workers"].as_array().is_some_and(|w| w.len() == 1));
    let stats = &state["scheduler"]["stats"];
    assert!(stats["batches_reissued"].as_u64() >= Some(1), "the frozen worker's batch was re-issued: {stats:#}");
    assert!(state["live"]["workers_left"].as_u64() >= Some(1));
    assert_eq!(state["workers"][0]["name"], "alpha");
    eprintln!(
        "live rounds: {} (p50 {} us, p99 {} us); pose to plan: p50 {} ms, p99 {} ms over {} plans",
        state["live"]["round_us"]["samples"],
        state["live"]["round_us"]["p50"],
        state["live"]["round_us"]["p99"],
        state["live"]["pose_to_plan_ms"]["p50"],
        state["live"]["pose_to_plan_ms"]["p99"],
        state["live"]["pose_to_plan_ms"]["samples"],
    );

    // Close the session: the composer is told; the token is checked.
    assert_eq!(delete_session(&master, &name, &"0".repeat(32)), 401);
    assert_eq!(delete_session(&master, &name, &token), 204);
    let closed = loop {
        match composer.next() {
            Message::CloseStream(close) => break close,
            Message::FramePlan(_) => {}
            other => panic!("expected the close, got {other:?}"),
        }
    };
    assert_eq!(closed.session_id, sid);
    assert_eq!(delete_session(&master, &name, &token), 404);
    let state = wait_for_farm(&master, "no session", |s| s["sessions"].as_array().is_some_and(Vec::is_empty));
    assert_eq!(state["sessions_open"], 0);
    // Finished tasks stay in the history table for 500 ms, then the composer may forget them.
    wait_for_farm(&master, "results released", |s| s["live"]["releases_sent"].as_u64() >= Some(1));

    // SIGTERM: exit 0; the composer and the surviving worker hear goodbye.
    master.process.signal("-TERM");
    let status = master.process.wait(Duration::from_secs(15));
    assert!(status.success(), "master exit status {status:?}");
    let goodbye = loop {
        match composer.messages.recv_timeout(WAIT).expect("the master's goodbye") {
            Message::Goodbye(g) => break g,
            _ => continue,
        }
    };
    assert!(goodbye.reason.contains("shutting down"), "{goodbye:?}");
    let start = Instant::now();
    loop {
        let log = std::fs::read_to_string(&logs[0]).unwrap_or_default();
        if log.contains("the master says goodbye") {
            break;
        }
        assert!(start.elapsed() < WAIT, "the worker never heard goodbye:\n{log}");
        thread::sleep(Duration::from_millis(20));
    }
    workers[0].signal("-TERM");
    assert!(workers[0].wait(Duration::from_secs(15)).success());
}

/// `--render-ahead`: a farm idle between the frames of a slow user renders its predicted next
/// view ahead; the worker keeps it and sends the composer nothing for it; frames go on
/// arriving with every covered pixel.
#[test]
fn an_idle_farm_renders_a_moving_users_next_view_ahead_unseen() {
    let dir = tempfile::tempdir().expect("temp dir");
    let assets = dir.path().join("assets");
    std::fs::create_dir(&assets).expect("assets");
    let master = MasterProcess::start(&["--render-ahead"]);
    let _worker = start_worker(master.farm, &assets, "alpha", &dir.path().join("alpha.log"));
    let mut composer = connect_composer(master.farm, "composer-test").expect("composer registered");
    wait_for_farm(&master, "a worker", |s| s["workers"].as_array().is_some_and(|w| w.len() == 1));
    let (width, height) = (64, 48);
    let r = open_session(
        &master,
        json!({ "sdp": OFFER, "scene": "diffuse", "views": 1, "width": width, "height": height, "target_fps": 5 }),
    );
    assert_eq!(r.status, 201, "{}", r.body);
    let sid = match composer.next() {
        Message::OpenStream(open) => open.session_id,
        other => panic!("expected the offer, got {other:?}"),
    };
    let view = object_view("diffuse", width, height);
    let mut reference = Reference::new("diffuse");
    let next = Arc::new(AtomicU32::new(1));
    let poses = PoseSender::start(composer.writer.clone(), sid, object_view("diffuse", width, height), next);
    let mut plans = 0;
    let start = Instant::now();
    let state = loop {
        let plan = composer.next_plan();
        plans += 1;
        // Every pixel the object covers arrives (values: a reused pixel is resampled).
        let expected = reference.for_pose(plan.pose_sequence, &view.pose(plan.pose_sequence));
        let tasks: Vec<u64> = plan.parts.iter().map(|p| p.task_id).collect();
        let covered = (0..expected.len()).filter(|&p| expected.opacity[p] > 0.0).count();
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            composer.collect_results();
            let seen: HashSet<u32> =
                tasks.iter().filter_map(|t| composer.store.get(t)).flatten().flat_map(|r| r.pixels.clone()).collect();
            if (0..expected.len()).all(|p| expected.opacity[p] == 0.0 || seen.contains(&(p as u32))) {
                break;
            }
            assert!(Instant::now() < deadline, "frame {}: {covered} covered pixels not all delivered", plan.frame_id);
            thread::sleep(Duration::from_millis(5));
        }
        let state = farm_state(&master);
        if plans >= 6 && state["scheduler"]["stats"]["ahead_tasks_done"].as_u64() >= Some(2) {
            break state;
        }
        assert!(start.elapsed() < WAIT, "no render ahead in {plans} frames: {:#}", state["scheduler"]["stats"]);
    };
    drop(poses);
    let stats = &state["scheduler"]["stats"];
    assert!(stats["ahead_rays"].as_u64() > Some(0), "{stats:#}");
    assert_eq!(stats["batches_reissued"], 0, "{stats:#}");
    composer.collect_results();
    let unseen = composer.store.values().flatten().filter(|r| r.ids.frame_id == u64::MAX).count();
    assert_eq!(unseen, 0, "a render ahead reached the composer");
    let metrics = scrape_metrics(master.http);
    assert!(
        metrics.lines().any(|l| l.starts_with("nephele_master_ahead_tasks_total") && !l.ends_with(" 0")),
        "{metrics}"
    );
}

#[test]
fn admission_control_refuses_while_a_user_is_starved_and_bad_requests_are_answered() {
    let dir = tempfile::tempdir().expect("temp dir");
    let assets = dir.path().join("assets");
    std::fs::create_dir(&assets).expect("assets");
    let master = MasterProcess::start(&[]);
    let _worker = start_worker(master.farm, &assets, "solo", &dir.path().join("solo.log"));
    wait_for_farm(&master, "the worker", |s| s["workers"].as_array().is_some_and(|w| w.len() == 1));
    let request = |scene: &str, size: (u32, u32), fps: f64, sdp: &str| json!({ "sdp": sdp, "scene": scene, "views": 1, "width": size.0, "height": size.1, "target_fps": fps });

    // Bad command lines are clear errors.
    let taken = master.http.to_string();
    let err = nephele_tests::nephele_err(&["master", "--http", &taken, "--farm-listen", "127.0.0.1:0"]);
    assert!(err.contains("cannot listen on") && err.contains("http"), "{err}");
    let err = nephele_tests::nephele_err(&["master", "--http", "127.0.0.1:0", "--load-report-ms", "1"]);
    assert!(err.contains("--load-report-ms"), "{err}");

    // Alive, but not ready without a composer.
    assert_eq!(http(master.http, "GET", "/livez", &[], "").status, 200);
    let r = http(master.http, "GET", "/readyz", &[], "");
    assert_eq!(r.status, 503, "{}", r.body);
    assert_eq!(r.body["missing"], json!(["no composer has joined the farm"]), "{}", r.body);

    // No composer yet: 503 without Retry-After (nothing to wait for).
    let r = open_session(&master, request("diffuse", (64, 48), 30.0, OFFER));
    assert_eq!(r.status, 503, "{}", r.body);
    assert!(r.body["error"].as_str().is_some_and(|e| e.contains("composer")), "{}", r.body);
    assert!(!r.headers.contains_key("retry-after"));

    // Bad requests.
    let r = http(master.http, "POST", "/v1/sessions", &[], "{\"sdp\": ");
    assert_eq!(r.status, 400);
    assert!(r.body["error"].as_str().is_some_and(|e| e.contains("malformed")), "{}", r.body);
    assert_eq!(open_session(&master, request("nowhere", (64, 48), 30.0, OFFER)).status, 400);
    assert_eq!(delete_session(&master, "s99-abcdef", &"0".repeat(32)), 404);

    let mut composer = connect_composer(master.farm, "composer-a").expect("first composer");
    let r = http(master.http, "GET", "/readyz", &[], "");
    assert_eq!((r.status, &r.body["ready"]), (200, &json!(true)), "{}", r.body);
    match connect_composer(master.farm, "composer-b").map_err(|m| *m) {
        Err(Message::Error(e)) => assert_eq!(e.code, ErrorCode::Unexpected, "{e:?}"),
        Err(other) => panic!("expected an error, got {other:?}"),
        Ok(_) => panic!("a second composer must be refused"),
    }

    // An offer the composer refuses: 400, and no session is left behind.
    let r = open_session(&master, request("diffuse", (64, 48), 30.0, "v=0\r\ns=refuse-me\r\n"));
    assert_eq!(r.status, 400, "{}", r.body);
    assert!(r.body["error"].as_str().is_some_and(|e| e.contains("H.264")), "{}", r.body);
    assert!(matches!(composer.next(), Message::OpenStream(_)));
    let r = http(master.http, "GET", "/v1/sessions", &[], "");
    assert_eq!(r.body["sessions"].as_array().map(Vec::len), Some(0), "{}", r.body);

    // A user asking for far more than one worker can render (three objects, 240 FPS,
    // moving): its frames wait, its target time passes, it is starved.
    let (width, height) = (160, 120);
    let r = open_session(&master, request("default", (width, height), 240.0, OFFER));
    assert_eq!(r.status, 201, "{}", r.body);
    let (name, token) =
        (r.body["session_id"].as_str().expect("id").to_string(), r.body["token"].as_str().expect("token").to_string());
    let sid = match composer.next() {
        Message::OpenStream(open) => open.session_id,
        other => panic!("expected the offer, got {other:?}"),
    };
    let view = {
        let v = r.body["view"].clone();
        let vec3 = |v: &Value| {
            Vec3::new(
                v[0].as_f64().expect("x") as f32,
                v[1].as_f64().expect("y") as f32,
                v[2].as_f64().expect("z") as f32,
            )
        };
        View {
            width,
            height,
            eye: vec3(&v["eye"]),
            target: vec3(&v["target"]),
            fov_y: (v["fov_y_deg"].as_f64().expect("fov") as f32).to_radians(),
        }
    };
    let poses = PoseSender::start(composer.writer.clone(), sid, view, Arc::new(AtomicU32::new(1)));
    let start = Instant::now();
    let refused = loop {
        let r = open_session(&master, request("diffuse", (64, 48), 30.0, OFFER));
        if r.status == 503 {
            break r;
        }
        assert_eq!(r.status, 201, "{}", r.body);
        // Admitted before the starvation showed: close it again and retry.
        let id = r.body["session_id"].as_str().expect("id");
        assert_eq!(delete_session(&master, id, r.body["token"].as_str().expect("token")), 204);
        assert!(start.elapsed() < WAIT, "never refused");
        thread::sleep(Duration::from_millis(50));
    };
    let retry_after: u64 = refused.headers.get("retry-after").expect("Retry-After").parse().expect("seconds");
    assert!((1..=30).contains(&retry_after), "{retry_after}");
    assert!(refused.body["error"].as_str().is_some_and(|e| e.contains("starved")), "{}", refused.body);
    let state = farm_state(&master);
    assert_eq!(state["scheduler"]["admission_open"], false, "{state:#}");
    assert!(state["scheduler"]["stats"]["starved_rounds"].as_u64() >= Some(1), "{state:#}");

    // The starved user leaves: once the hold passes, sessions are admitted again.
    drop(poses);
    assert_eq!(delete_session(&master, &name, &token), 204);
    let start = Instant::now();
    loop {
        let r = open_session(&master, request("diffuse", (64, 48), 30.0, OFFER));
        if r.status == 201 {
            break;
        }
        assert_eq!(r.status, 503, "{}", r.body);
        assert!(start.elapsed() < WAIT, "admission never reopened");
        thread::sleep(Duration::from_millis(100));
    }
}

/// Percentile of unsorted samples.
fn percentile(samples: &mut [f64], q: f64) -> f64 {
    if samples.is_empty() {
        return f64::NAN;
    }
    samples.sort_by(f64::total_cmp);
    samples[((samples.len() as f64 - 1.0) * q).round() as usize]
}

/// The live loop's figures: sessions x target FPS on two one-thread workers, moving poses
/// every 20 ms, for a few seconds each. Prints a table (see /work/notes/svc-BENCH.md).
#[test]
#[ignore = "a benchmark: cargo test -p nephele-tests --test master bench_live_loop -- --ignored --nocapture"]
fn bench_live_loop() {
    let seconds: f64 = std::env::var("BENCH_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(5.0);
    let (width, height) = (160u32, 120u32);
    println!(
        "live loop: diffuse {width}x{height}, 2 workers x 1 thread, spp {SPP}, poses every 20 ms, {seconds} s per row"
    );
    println!(
        "{:>8} {:>5} {:>10} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "admitted",
        "fps",
        "plans/s/u",
        "e2e p50",
        "e2e p99",
        "in p50",
        "in p99",
        "round50",
        "round99",
        "rounds",
        "reissue",
        "dropped"
    );
    for (sessions, fps) in [(1usize, 30.0), (1, 120.0), (4, 30.0), (4, 120.0)] {
        let dir = tempfile::tempdir().expect("temp dir");
        let assets = dir.path().join("assets");
        std::fs::create_dir(&assets).expect("assets");
        let master = MasterProcess::start(&["--max-batch-rays", "2048"]);
        let _workers: Vec<Process> = ["alpha", "beta"]
            .iter()
            .map(|n| start_worker(master.farm, &assets, n, &dir.path().join(format!("{n}.log"))))
            .collect();
        let mut composer = connect_composer(master.farm, "composer-bench").expect("composer");
        wait_for_farm(&master, "two workers", |s| s["workers"].as_array().is_some_and(|w| w.len() == 2));
        let mut senders = Vec::new();
        for k in 0..sessions {
            let body = json!({ "sdp": OFFER, "scene": "diffuse", "views": 1, "width": width, "height": height, "target_fps": fps });
            let r = open_session(&master, body);
            if r.status == 503 {
                // Admission control: the users already in are starved.
                continue;
            }
            assert_eq!(r.status, 201, "{}", r.body);
            let sid = loop {
                if let Message::OpenStream(open) = composer.next() {
                    break open.session_id;
                }
            };
            // Sessions orbit from different angles: no two ask for the same rays.
            let first = 1 + 1000 * k as u32;
            senders.push((
                sid,
                PoseSender::start(
                    composer.writer.clone(),
                    sid,
                    object_view("diffuse", width, height),
                    Arc::new(AtomicU32::new(first)),
                ),
            ));
        }
        let start = Instant::now();
        let mut e2e = Vec::new();
        let mut seen = HashSet::new();
        let mut plans = 0usize;
        while start.elapsed().as_secs_f64() < seconds {
            let Ok(message) = composer.messages.recv_timeout(Duration::from_millis(100)) else { continue };
            let Message::FramePlan(plan) = message else { continue };
            plans += 1;
            let arrived = Instant::now();
            if seen.insert((plan.session_id, plan.pose_sequence))
                && let Some((_, sender)) = senders.iter().find(|(sid, _)| *sid == plan.session_id)
                && let Some(sent) = sender.sent.lock().expect("times").get(&plan.pose_sequence)
            {
                e2e.push(arrived.duration_since(*sent).as_secs_f64() * 1e3);
            }
        }
        let state = farm_state(&master);
        let admitted = senders.len();
        drop(senders);
        let live = &state["live"];
        let stats = &state["scheduler"]["stats"];
        let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
        let n = |v: &Value| v.as_u64().unwrap_or(0);
        println!(
            "{:>8} {:>5} {:>10.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>8.1} {:>8.1} {:>8} {:>8} {:>8}",
            format!("{admitted}/{sessions}"),
            fps,
            plans as f64 / seconds / admitted.max(1) as f64,
            percentile(&mut e2e.clone(), 0.5),
            percentile(&mut e2e, 0.99),
            f(&live["pose_to_plan_ms"]["p50"]),
            f(&live["pose_to_plan_ms"]["p99"]),
            f(&live["round_us"]["p50"]),
            f(&live["round_us"]["p99"]),
            n(&live["round_us"]["samples"]),
            n(&stats["batches_reissued"]),
            n(&stats["frames_dropped"]),
        );
    }
    println!(
        "e2e: pose sent by the test composer -> first frame plan for it received (ms); in: the master's pose received -> plan sent (ms); round: scheduler tick (us)"
    );
}

/// A composer process joined to `master`, with `env` (and no operators' token from the
/// test's own environment) and the `extra` arguments; its signalling address (from its
/// banner) and its results address.
fn start_composer(
    master: &MasterProcess,
    env: &[(&str, &str)],
    extra: &[&std::ffi::OsStr],
) -> (Process, SocketAddr, SocketAddr) {
    let results = TcpListener::bind("127.0.0.1:0").expect("a free port").local_addr().expect("addr");
    let mut composer = Command::new(nephele_bin())
        .env_remove("NEPHELE_OPERATOR_TOKEN_FILE")
        .envs(env.iter().copied())
        .args(["--quiet", "composer", "--master", &master.farm.to_string(), "--http", "127.0.0.1:0"])
        .args(["--results", &results.to_string()])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(if logs() { Stdio::inherit() } else { Stdio::null() })
        .spawn()
        .expect("starting nephele composer");
    let mut banner = String::new();
    BufReader::new(composer.stdout.take().expect("stdout")).read_line(&mut banner).expect("the composer's banner");
    let http: SocketAddr = banner
        .split("http://")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|a| a.parse().ok())
        .unwrap_or_else(|| panic!("no address in {banner:?}"));
    (Process { child: composer, name: "composer".into() }, http, results)
}

/// A process's Prometheus text (`GET /metrics`, no token).
fn scrape_metrics(addr: SocketAddr) -> String {
    let url = format!("http://{addr}/metrics");
    nephele_loadgen::http::request_blocking(&url, "GET", &[], "", WAIT).expect("metrics").body
}

/// The farm credential (issue 15): a master and a composer holding a secret admit the
/// processes that prove it, refuse (and count) every peer that does not, and a result sent
/// to the composer by a peer without the secret never gets in.
#[test]
fn the_farm_admits_only_peers_that_prove_its_secret() {
    use nephele_proto::ProtoError;
    use nephele_proto::auth::FarmSecret;
    const SECRET: &str = "the test farm's secret, long enough";
    let env = [("NEPHELE_FARM_SECRET", SECRET)];
    let dir = tempfile::tempdir().expect("temp dir");
    let assets = dir.path().join("assets");
    std::fs::create_dir(&assets).expect("assets");
    let master = MasterProcess::start_with(&[], &env);

    // Strangers at the farm port: no secret, a wrong one, as a worker or as a composer.
    let try_join = |addr: SocketAddr, role: Role, accept: Role, secret: Option<&str>| -> Result<(), ProtoError> {
        let stream = TcpStream::connect(addr).expect("connect");
        let mut reader = FrameReader::new(stream.try_clone().expect("clone"), FrameConfig::default());
        let mut writer = FrameWriter::new(stream, FrameConfig::default());
        let secret = secret.map(|t| FarmSecret::from_text(t, "test").expect("secret"));
        nephele_proto::frame::handshake(&mut reader, &mut writer, role, &[accept], secret.as_ref()).map(|_| ())
    };
    for (role, secret) in [
        (Role::Worker, None),
        (Role::Worker, Some("a wrong farm secret, guessed")),
        (Role::Composer, Some("another wrong one, guessed")),
    ] {
        let err = try_join(master.farm, role, Role::Master, secret).expect_err("a stranger is refused");
        assert!(matches!(err, ProtoError::Refused { code: ErrorCode::Unauthenticated, .. }), "{err}");
    }
    // A worker process given the wrong secret file stops at once, saying why.
    let wrong = dir.path().join("wrong-secret");
    std::fs::write(&wrong, "not the secret of this farm\n").expect("write");
    let out = Command::new(nephele_bin())
        .args(["--quiet", "worker", "--master", &master.farm.to_string(), "--reconnect-secs", "60"])
        .arg("--assets")
        .arg(&assets)
        .arg("--farm-secret-file")
        .arg(&wrong)
        .output()
        .expect("running a worker");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("farm secret"), "{stderr}");

    // The real composer and worker, holding the secret, join.
    let (_composer, composer_http, results) = start_composer(&master, &env, &[]);
    let _worker = start_worker_with(master.farm, &assets, "trusted", &dir.path().join("trusted.log"), &env);
    wait_for_farm(&master, "the composer and the worker", |s| {
        !s["composer"].is_null() && s["workers"].as_array().is_some_and(|w| w.len() == 1)
    });

    // A forged result: a peer without the secret at the composer's results port is refused
    // before it can send one (a tool may even send frame plans there once admitted).
    let err = try_join(results, Role::Tool, Role::Composer, None).expect_err("refused");
    assert!(matches!(err, ProtoError::Refused { code: ErrorCode::Unauthenticated, .. }), "{err}");
    let err = try_join(results, Role::Worker, Role::Composer, Some("a forger's guess at it")).expect_err("refused");
    assert!(matches!(err, ProtoError::Refused { code: ErrorCode::Unauthenticated, .. }), "{err}");
    // ... while a peer holding it gets in.
    try_join(results, Role::Tool, Role::Composer, Some(SECRET)).expect("a tool with the secret is admitted");

    // Counted: three strangers and the misconfigured worker at the master, two at the composer.
    let master_metrics = scrape_metrics(master.http);
    assert_eq!(
        metric_value(&master_metrics, "nephele_master_farm_peers_unauthenticated_total"),
        Some(4.0),
        "{master_metrics}"
    );
    let composer_metrics = scrape_metrics(composer_http);
    assert_eq!(
        metric_value(&composer_metrics, "nephele_composer_peers_unauthenticated_total"),
        Some(2.0),
        "{composer_metrics}"
    );
}

/// TLS between the farm's processes (issue 15): a master, a composer and a worker given the
/// farm TLS folder (the worker only its certificate) join over TLS; a peer speaking plain
/// TCP at the farm port or the results port gets no handshake and is counted, and a TLS peer
/// that trusts another farm's certificate gets nowhere.
#[test]
fn the_farm_speaks_tls_with_its_certificate_only() {
    use nephele_transport::{CERT_FILE, FarmTls};
    let dir = tempfile::tempdir().expect("temp dir");
    let (farm_dir, worker_dir, stranger_dir) =
        (dir.path().join("tls"), dir.path().join("cert"), dir.path().join("other"));
    // The farm's folder as an operator makes it: `nephele secret --farm-tls`, which refuses to
    // replace it and keeps it with `--if-missing`.
    let make = |extra: &[&str]| {
        Command::new(nephele_bin())
            .args(["secret", "--farm-tls", "--out"])
            .arg(&farm_dir)
            .args(extra)
            .output()
            .expect("nephele secret --farm-tls")
    };
    assert!(make(&[]).status.success());
    let again = make(&[]);
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(!again.status.success() && stderr.contains(CERT_FILE), "{stderr}");
    assert!(make(&["--if-missing"]).status.success());
    FarmTls::generate(&stranger_dir).expect("another farm's certificate");
    std::fs::create_dir(&worker_dir).expect("dir");
    std::fs::copy(farm_dir.join(CERT_FILE), worker_dir.join(CERT_FILE)).expect("copy");
    let assets = dir.path().join("assets");
    std::fs::create_dir(&assets).expect("assets");
    let farm_env = [("NEPHELE_FARM_TLS_DIR", farm_dir.to_str().expect("utf-8"))];
    let master = MasterProcess::start_with(&[], &farm_env);
    let (_composer, composer_http, results) = start_composer(&master, &farm_env, &[]);
    let worker_env = [("NEPHELE_FARM_TLS_DIR", worker_dir.to_str().expect("utf-8"))];
    let _worker = start_worker_with(master.farm, &assets, "tls", &dir.path().join("tls.log"), &worker_env);
    wait_for_farm(&master, "the composer and the worker over TLS", |s| {
        !s["composer"].is_null() && s["workers"].as_array().is_some_and(|w| w.len() == 1)
    });

    // Plain TCP speaking the protocol at either port: no answer the protocol understands.
    let plain = |addr: SocketAddr, accept: Role| {
        let stream = TcpStream::connect(addr).expect("connect");
        stream.set_read_timeout(Some(Duration::from_secs(20))).expect("timeout");
        let mut reader = FrameReader::new(stream.try_clone().expect("clone"), FrameConfig::default());
        let mut writer = FrameWriter::new(stream, FrameConfig::default());
        nephele_proto::frame::handshake(&mut reader, &mut writer, Role::Tool, &[accept], None)
    };
    assert!(plain(master.farm, Role::Master).is_err(), "the master's farm port spoke plain TCP");
    assert!(plain(results, Role::Composer).is_err(), "the composer's results port spoke plain TCP");
    // TLS: the farm's certificate is trusted, another farm's is not.
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
    let tls_handshake = |folder: &Path| {
        let tls = FarmTls::load(folder).expect("tls settings");
        rt.block_on(async {
            let stream = nephele_transport::connect(&results.to_string(), Some(&tls), WAIT).await?;
            let mut conn = nephele_proto::stream::framed(stream, FrameConfig::default());
            nephele_proto::stream::handshake(&mut conn, Role::Tool, &[Role::Composer], None, WAIT).await?;
            Ok::<(), Box<dyn std::error::Error>>(())
        })
    };
    tls_handshake(&worker_dir).expect("a tool holding the farm certificate is admitted");
    assert!(tls_handshake(&stranger_dir).is_err(), "a client trusting another farm's certificate got in");

    let master_metrics = scrape_metrics(master.http);
    assert_eq!(
        metric_value(&master_metrics, "nephele_master_farm_handshakes_failed_total"),
        Some(1.0),
        "{master_metrics}"
    );
    let composer_metrics = scrape_metrics(composer_http);
    assert!(
        metric_value(&composer_metrics, "nephele_composer_wire_errors_total").is_some_and(|n| n >= 1.0),
        "{composer_metrics}"
    );
}

/// The operators' token (issue 15) across processes: a master, a composer and a worker
/// started with it (flag or `$NEPHELE_OPERATOR_TOKEN_FILE`) answer `nephele probe` of their
/// operators' endpoints with 401 unless the probe holds the token (flag or variable); the
/// probes' own endpoints need none.
#[test]
fn probe_reaches_the_operators_endpoints_only_with_the_token() {
    let dir = tempfile::tempdir().expect("temp dir");
    let token = dir.path().join("operator-token");
    std::fs::write(&token, "the operators' token of this test\n").expect("write");
    let wrong = dir.path().join("wrong-token");
    std::fs::write(&wrong, "a token that is not the master's\n").expect("write");
    let master = MasterProcess::start(&["--operator-token-file", token.to_str().expect("utf-8 path")]);
    let probe_at = |addr: SocketAddr, path: &str, args: &[&std::ffi::OsStr], env: Option<&Path>| {
        let mut command = Command::new(nephele_bin());
        command.args(["--quiet", "probe"]).arg(format!("http://{addr}{path}")).args(args);
        command.env_remove("NEPHELE_OPERATOR_TOKEN_FILE");
        if let Some(file) = env {
            command.env("NEPHELE_OPERATOR_TOKEN_FILE", file);
        }
        command.output().expect("running nephele probe")
    };
    let probe = |path: &str, args: &[&std::ffi::OsStr], env: Option<&Path>| probe_at(master.http, path, args, env);
    let flag = std::ffi::OsStr::new("--operator-token-file");
    let denied = probe("/metrics", &[], None);
    assert!(!denied.status.success(), "no token: {denied:?}");
    assert!(String::from_utf8_lossy(&denied.stdout).starts_with("401"), "{denied:?}");
    let wrong_token = probe("/metrics", &[flag, wrong.as_os_str()], None);
    assert!(!wrong_token.status.success(), "a wrong token: {wrong_token:?}");
    let allowed = probe("/metrics", &[flag, token.as_os_str()], None);
    assert!(allowed.status.success(), "with the token: {allowed:?}");
    assert!(String::from_utf8_lossy(&allowed.stdout).starts_with("200"), "{allowed:?}");
    let from_env = probe("/v1/farm", &[], Some(&token));
    assert!(from_env.status.success(), "with the token from the environment: {from_env:?}");
    let live = probe("/livez", &[], None);
    assert!(live.status.success(), "/livez needs no token: {live:?}");

    // A composer given the token by flag, a worker by the variable: their /metrics (and the
    // composer's session list) ask for it too; /livez does not.
    let (_composer, composer_http, _) = start_composer(&master, &[], &[flag, token.as_os_str()]);
    let ops = TcpListener::bind("127.0.0.1:0").expect("a free port").local_addr().expect("addr");
    let assets = dir.path().join("assets");
    std::fs::create_dir(&assets).expect("assets");
    let worker = Command::new(nephele_bin())
        .args(["--quiet", "--threads", "1", "worker", "--master", &master.farm.to_string(), "--name", "scraped"])
        .arg("--assets")
        .arg(&assets)
        .args(["--ops", &ops.to_string(), "--spp", "1", "--bounces", "1"])
        .env("NEPHELE_OPERATOR_TOKEN_FILE", &token)
        .stdout(Stdio::null())
        .stderr(if logs() { Stdio::inherit() } else { Stdio::null() })
        .spawn()
        .expect("starting nephele worker");
    let _worker = Process { child: worker, name: "worker".into() };
    let deadline = Instant::now() + Duration::from_secs(60);
    while !probe_at(ops, "/livez", &[], None).status.success() {
        assert!(Instant::now() < deadline, "the worker's operations port did not answer");
        thread::sleep(Duration::from_millis(100));
    }
    for (addr, path) in [(composer_http, "/metrics"), (composer_http, "/v1/sessions"), (ops, "/metrics")] {
        let denied = probe_at(addr, path, &[], None);
        assert!(String::from_utf8_lossy(&denied.stdout).starts_with("401"), "{addr}{path} without a token: {denied:?}");
        let wrong_token = probe_at(addr, path, &[flag, wrong.as_os_str()], None);
        assert!(!wrong_token.status.success(), "{addr}{path} with a wrong token: {wrong_token:?}");
        let allowed = probe_at(addr, path, &[], Some(&token));
        assert!(allowed.status.success(), "{addr}{path} with the token: {allowed:?}");
    }
    assert!(probe_at(composer_http, "/livez", &[], None).status.success());
}
