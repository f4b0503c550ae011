//! Real `nephele worker` processes against a test double of the master and of the composer,
//! over loopback TCP: registration, a frame split over two workers that matches the kernel
//! computed in-process bit for bit, a worker killed mid-frame, graceful SIGTERM, and bad or
//! hostile input from the "master".

use std::collections::{BTreeSet, HashMap};
use std::io::BufReader;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::thread;
use std::time::{Duration, Instant};

use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_kernels::kernel::{PathTracedKernel, PixelResults, RayKernel, all_pixels};
use nephele_pathtracer::Renderer;
use nephele_pathtracer::scenes;
use nephele_proto::{
    BatchIds, BatchResult, Cancel, CancelTarget, DerivedView, ErrorCode, FrameConfig, FrameReader, FrameWriter, Hello,
    Message, RayBatch, Register, Registered, Rejected, ReuseLimits, Role, ViewProjection, encode_frame_unchecked,
};
use nephele_tests::nephele_bin;

const WAIT: Duration = Duration::from_secs(30);

// ---------------------------------------------------------------------------------------
// Worker processes

struct WorkerProcess {
    child: Child,
}

impl WorkerProcess {
    fn start(master: SocketAddr, assets: &Path, name: &str, extra: &[&str]) -> WorkerProcess {
        let logs = std::env::var_os("NEPHELE_TEST_LOGS").is_some();
        let child = Command::new(nephele_bin())
            .args(["--quiet", "--threads", "1", "worker", "--master", &master.to_string(), "--name", name])
            .arg("--assets")
            .arg(assets)
            .args(["--reconnect-secs", "20", "--drain-secs", "20"])
            // These tests compare frames pixel by pixel with the in-process kernel and count
            // every pixel of a batch: exact f32 results. Compact results (the default) are
            // checked end to end in tests/master.rs and in the proto and fusion tests.
            .args(["--results", "f32"])
            .args(extra)
            .env("NEPHELE_LOG", if logs { "debug" } else { "warn" })
            .stdout(Stdio::null())
            .stderr(if logs { Stdio::inherit() } else { Stdio::null() })
            .spawn()
            .expect("starting nephele worker");
        WorkerProcess { child }
    }

    fn signal(&self, signal: &str) {
        let status = Command::new("kill").args([signal, &self.child.id().to_string()]).status().expect("kill");
        assert!(status.success());
    }

    fn wait(&mut self, timeout: Duration) -> ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                return status;
            }
            assert!(start.elapsed() < timeout, "the worker did not exit within {timeout:?}");
            thread::sleep(Duration::from_millis(20));
        }
    }

    fn assert_alive(&mut self) {
        assert!(self.child.try_wait().expect("try_wait").is_none(), "the worker process died");
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

// ---------------------------------------------------------------------------------------
// Test double of the master: accepts workers, one reader thread per connection feeding
// one event channel.

// What the fake master hears, through a channel: size does not matter here.
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
enum Event {
    Message(usize, Message),
    Rejected(usize, Rejected),
    Closed(usize, String),
}

struct Master {
    listener: TcpListener,
    events: Receiver<Event>,
    sender: Sender<Event>,
    writers: Vec<FrameWriter<TcpStream>>,
    registers: Vec<Register>,
    load_reports: usize,
}

impl Master {
    fn new() -> Master {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind master");
        listener.set_nonblocking(true).expect("nonblocking");
        let (sender, events) = channel();
        Master { listener, events, sender, writers: Vec::new(), registers: Vec::new(), load_reports: 0 }
    }

    fn addr(&self) -> SocketAddr {
        self.listener.local_addr().expect("addr")
    }

    fn accept_stream(&self) -> TcpStream {
        let start = Instant::now();
        loop {
            match self.listener.accept() {
                Ok((stream, _)) => {
                    stream.set_nonblocking(false).expect("blocking");
                    stream.set_read_timeout(Some(WAIT)).expect("timeout");
                    stream.set_nodelay(true).expect("nodelay");
                    return stream;
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    assert!(start.elapsed() < WAIT, "no worker connected within {WAIT:?}");
                    thread::sleep(Duration::from_millis(5));
                }
                Err(e) => panic!("accept: {e}"),
            }
        }
    }

    /// Accepts a worker, checks its hello and registration, accepts it; returns its index.
    fn accept_worker(&mut self) -> usize {
        let stream = self.accept_stream();
        let mut reader = FrameReader::new(stream.try_clone().expect("clone"), FrameConfig::default());
        let mut writer = FrameWriter::new(stream, FrameConfig::default());
        let hello = nephele_proto::frame::handshake(&mut reader, &mut writer, Role::Master, &[Role::Worker], None)
            .expect("handshake");
        assert_eq!(hello, Hello::new(Role::Worker));
        let register = match reader.read_message().expect("registration") {
            Ok(Message::Register(r)) => r,
            other => panic!("expected Register, got {other:?}"),
        };
        let index = self.writers.len();
        writer
            .write_message(&Message::Registered(Registered {
                worker_id: 100 + index as u64,
                load_report_interval_ms: 50,
            }))
            .expect("registered");
        writer.flush().expect("flush");
        let events = self.sender.clone();
        thread::spawn(move || {
            loop {
                let event = match reader.read_message() {
                    Ok(Ok(message)) => Event::Message(index, message),
                    Ok(Err(rejected)) => Event::Rejected(index, rejected),
                    Err(e) => {
                        let _ = events.send(Event::Closed(index, e.to_string()));
                        return;
                    }
                };
                if events.send(event).is_err() {
                    return;
                }
            }
        });
        self.writers.push(writer);
        self.registers.push(register);
        index
    }

    fn send(&mut self, worker: usize, message: &Message) {
        let mut frame = Vec::new();
        // Unchecked: the tests send invalid batches on purpose.
        encode_frame_unchecked(message, &mut frame, &FrameConfig::default()).expect("encode");
        self.send_raw(worker, &frame);
    }

    fn send_raw(&mut self, worker: usize, bytes: &[u8]) {
        self.writers[worker].write_raw(bytes).expect("send to worker");
        self.writers[worker].flush().expect("flush");
    }

    /// The next event other than a load report.
    fn next(&mut self) -> Event {
        loop {
            match self.events.recv_timeout(WAIT) {
                Ok(Event::Message(_, Message::LoadReport(_))) => self.load_reports += 1,
                Ok(Event::Rejected(worker, rejected)) => panic!("worker {worker} sent an invalid message: {rejected}"),
                Ok(event) => return event,
                Err(RecvTimeoutError::Timeout) => panic!("no message from the workers within {WAIT:?}"),
                Err(RecvTimeoutError::Disconnected) => panic!("event channel closed"),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Test double of the composer: every result of every connection into one channel.

struct Composer {
    addr: SocketAddr,
    results: Receiver<BatchResult>,
}

impl Composer {
    fn start() -> Composer {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind composer");
        let addr = listener.local_addr().expect("addr");
        let (tx, results) = channel();
        thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { return };
                let tx = tx.clone();
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
                            other => panic!("composer got {other:?}"),
                        }
                    }
                });
            }
        });
        Composer { addr, results }
    }
}

/// A frame being assembled from batch results.
struct Assembly {
    image: PixelResults,
    seen: Vec<bool>,
    batches: BTreeSet<u64>,
}

impl Assembly {
    fn new(pixels: usize) -> Assembly {
        Assembly { image: PixelResults::with_len(pixels), seen: vec![false; pixels], batches: BTreeSet::new() }
    }

    fn add(&mut self, r: &BatchResult) {
        for (k, &p) in r.pixels.iter().enumerate() {
            let p = p as usize;
            self.image.color[p] = r.color[k];
            self.image.opacity[p] = r.opacity[k];
            self.image.depth[p] = r.depth[k];
            self.seen[p] = true;
        }
        self.batches.insert(r.ids.batch_id);
    }

    fn complete(&self) -> bool {
        self.seen.iter().all(|&s| s)
    }

    fn collect(&mut self, composer: &Composer) {
        let start = Instant::now();
        while !self.complete() {
            let left = WAIT.checked_sub(start.elapsed()).unwrap_or_default();
            let r = composer.results.recv_timeout(left).expect("the composer waited in vain for pixels");
            self.add(&r);
        }
    }
}

// ---------------------------------------------------------------------------------------
// The frame and its reference

struct Frame {
    wire: ViewProjection,
    expected: PixelResults,
}

/// The `diffuse` scene's default view at `width x height`, and the path tracer's result for
/// every pixel computed here, with the same samples and bounces as the workers.
fn frame(width: u32, height: u32, spp: u32, bounces: u32) -> Frame {
    let scene = scenes::builtin("diffuse").expect("scene");
    let (eye, target, fov_y) = scene.default_view();
    let look = Camera::look_at(width, height, fov_y, eye, target, Vec3::Z).expect("camera");
    let wire = ViewProjection::of_camera(&look, 0.05, 100.0);
    // Exactly the conversion the worker does.
    let camera = wire.camera().expect("camera from view and projection");
    let kernel = PathTracedKernel::new(Renderer::new(scene.scene).expect("renderer"), spp, bounces).expect("kernel");
    let (expected, _) = kernel.render_pixels(&camera, &all_pixels(&camera)).expect("reference render");
    assert!(expected.opacity.iter().any(|&a| a > 0.0) && expected.opacity.contains(&0.0));
    Frame { wire, expected }
}

fn batches(frame: &Frame, count: usize, composer: SocketAddr) -> Vec<RayBatch> {
    let total = (frame.wire.width * frame.wire.height) as usize;
    let all: Vec<u32> = (0..total as u32).collect();
    all.chunks(total.div_ceil(count))
        .enumerate()
        .map(|(i, chunk)| RayBatch {
            ids: BatchIds { batch_id: i as u64 + 1, task_id: 1, session_id: 7, frame_id: 1, view_index: 0 },
            asset_id: "diffuse".into(),
            camera: frame.wire,
            pixels: chunk.to_vec(),
            deadline_in_us: None,
            composer: composer.to_string(),
            derived: Vec::new(),
            reuse: ReuseLimits::default(),
            occluders: Vec::new(),
        })
        .collect()
}

fn assert_matches(frame: &Frame, got: &PixelResults) {
    // Bit for bit: the path tracer seeds every pixel by its index, so the split does not
    // matter.
    for p in 0..frame.expected.len() {
        assert_eq!(got.color[p], frame.expected.color[p], "colour of pixel {p}");
        assert_eq!(got.opacity[p], frame.expected.opacity[p], "opacity of pixel {p}");
        assert_eq!(got.depth[p], frame.expected.depth[p], "depth of pixel {p}");
    }
}

fn assets() -> tempfile::TempDir {
    tempfile::tempdir().expect("asset dir")
}

// ---------------------------------------------------------------------------------------
// Tests

#[test]
fn two_workers_register_and_render_a_frame_exactly() {
    let (spp, bounces) = (2, 2);
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let args = ["--spp", "2", "--bounces", "2"];
    let _a = WorkerProcess::start(master.addr(), assets.path(), "alpha", &args);
    let _b = WorkerProcess::start(master.addr(), assets.path(), "beta", &args);
    let frame = frame(64, 48, spp, bounces);
    let (w0, w1) = (master.accept_worker(), master.accept_worker());
    let mut names: Vec<&str> = master.registers.iter().map(|r| r.name.as_str()).collect();
    names.sort();
    assert_eq!(names, ["alpha", "beta"]);
    for r in &master.registers {
        assert_eq!(r.threads, 1);
        assert!(r.kernels.iter().any(|k| k == "pathtrace"), "{r:?}");
        assert!(r.rays_per_second > 0.0 && r.rays_per_second.is_finite(), "{r:?}");
    }

    let batches = batches(&frame, 8, composer.addr);
    let mut assigned = HashMap::new();
    for (i, batch) in batches.iter().enumerate() {
        let worker = if i % 2 == 0 { w0 } else { w1 };
        assigned.insert(batch.ids.batch_id, worker);
        master.send(worker, &Message::RayBatch(batch.clone()));
    }
    let mut done = BTreeSet::new();
    while done.len() < batches.len() {
        match master.next() {
            Event::Message(worker, Message::BatchDone(d)) => {
                assert_eq!(assigned[&d.ids.batch_id], worker, "done by the worker it was sent to");
                let batch = &batches[d.ids.batch_id as usize - 1];
                assert_eq!((d.ids, d.pixels as usize), (batch.ids, batch.pixels.len()));
                assert_eq!(d.stats.rays, u64::from(spp) * d.pixels as u64);
                done.insert(d.ids.batch_id);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    let mut assembly = Assembly::new(frame.expected.len());
    assembly.collect(&composer);
    assert_eq!(assembly.batches.len(), batches.len());
    assert_matches(&frame, &assembly.image);
    // Load reports (every 50 ms) keep coming while the workers idle.
    thread::sleep(Duration::from_millis(200));
    while let Ok(event) = master.events.try_recv() {
        if let Event::Message(_, Message::LoadReport(report)) = event {
            assert!(report.recent_rays_per_second.is_finite());
            master.load_reports += 1;
        }
    }
    assert!(master.load_reports >= 2, "{} load reports", master.load_reports);
}

#[test]
fn a_worker_killed_mid_frame_loses_no_pixel() {
    // Enough work per batch (32 spp, one batch at a time) that the victim still has batches
    // queued when it dies.
    let (spp, bounces) = (32, 2);
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let args = ["--spp", "32", "--bounces", "2", "--concurrent-batches", "1"];
    let mut survivor_process = WorkerProcess::start(master.addr(), assets.path(), "survivor", &args);
    let mut victim_process = WorkerProcess::start(master.addr(), assets.path(), "victim", &args);
    let frame = frame(96, 72, spp, bounces);
    let (w0, w1) = (master.accept_worker(), master.accept_worker());
    let (survivor, victim) = if master.registers[w0].name == "survivor" { (w0, w1) } else { (w1, w0) };

    let batches = batches(&frame, 16, composer.addr);
    let mut owner: HashMap<u64, usize> = HashMap::new();
    for (i, batch) in batches.iter().enumerate() {
        let worker = if i % 2 == 0 { survivor } else { victim };
        owner.insert(batch.ids.batch_id, worker);
        master.send(worker, &Message::RayBatch(batch.clone()));
    }
    let mut done = BTreeSet::new();
    let mut killed = false;
    let mut reissued = 0;
    while done.len() < batches.len() {
        match master.next() {
            Event::Message(worker, Message::BatchDone(d)) => {
                assert_eq!(owner[&d.ids.batch_id], worker);
                done.insert(d.ids.batch_id);
                if worker == victim && !killed {
                    victim_process.child.kill().expect("SIGKILL");
                    killed = true;
                }
            }
            Event::Closed(worker, _) if worker == victim => {
                assert!(killed, "the victim closed before it was killed");
                // What the master does: re-issue every batch of the dead worker that it did
                // not confirm.
                for batch in &batches {
                    if owner[&batch.ids.batch_id] == victim && !done.contains(&batch.ids.batch_id) {
                        owner.insert(batch.ids.batch_id, survivor);
                        master.send(survivor, &Message::RayBatch(batch.clone()));
                        reissued += 1;
                    }
                }
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert!(killed && reissued > 0, "the victim must die mid-frame (re-issued {reissued})");
    assert!(!victim_process.wait(Duration::from_secs(5)).success());
    let mut assembly = Assembly::new(frame.expected.len());
    assembly.collect(&composer);
    assert_matches(&frame, &assembly.image);
    survivor_process.assert_alive();
}

#[test]
fn sigterm_finishes_in_flight_batches_hands_back_the_rest_and_exits_0() {
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    // Heavy batches (64 spp) so that most are still queued when the signal lands; those are
    // handed back, not rendered, so the test stays quick.
    let args = ["--spp", "64", "--bounces", "2", "--concurrent-batches", "1"];
    let mut process = WorkerProcess::start(master.addr(), assets.path(), "leaving", &args);
    let frame = Frame { wire: frame_camera(96, 72), expected: PixelResults::default() };
    let w = master.accept_worker();
    let batches = batches(&frame, 24, composer.addr);
    for batch in &batches {
        master.send(w, &Message::RayBatch(batch.clone()));
    }
    let mut done = BTreeSet::new();
    let mut handed_back = BTreeSet::new();
    let mut signalled = false;
    let mut done_after_signal = 0;
    let goodbye = loop {
        match master.next() {
            Event::Message(_, Message::BatchDone(d)) => {
                done.insert(d.ids.batch_id);
                if signalled {
                    done_after_signal += 1;
                } else {
                    process.signal("-TERM");
                    signalled = true;
                }
            }
            Event::Message(_, Message::BatchFailed(f)) => {
                assert_eq!(f.code, ErrorCode::ShuttingDown, "{f:?}");
                handed_back.insert(f.ids.batch_id);
            }
            Event::Message(_, Message::Goodbye(g)) => break g,
            other => panic!("unexpected {other:?}"),
        }
    };
    assert!(matches!(master.next(), Event::Closed(..)), "the worker closes after its goodbye");
    let status = process.wait(Duration::from_secs(20));
    assert!(status.success(), "exit status {status:?}");
    // Every batch is either done or handed back, never both, and the goodbye lists the
    // handed-back ones.
    assert_eq!(done.len() + handed_back.len(), batches.len(), "done {done:?}, handed back {handed_back:?}");
    assert!(done.is_disjoint(&handed_back));
    assert_eq!(goodbye.returned_batches.iter().copied().collect::<BTreeSet<_>>(), handed_back);
    assert!(!handed_back.is_empty(), "queued batches are handed back, not rendered");
    assert!(done_after_signal >= 1, "the batch in flight at SIGTERM is finished");
    // Every batch reported done reached the composer.
    let mut delivered = BTreeSet::new();
    while let Ok(r) = composer.results.recv_timeout(Duration::from_millis(500)) {
        delivered.insert(r.ids.batch_id);
    }
    assert!(done.is_subset(&delivered), "done {done:?}, delivered {delivered:?}");
}

fn frame_camera(width: u32, height: u32) -> ViewProjection {
    let scene = scenes::builtin("diffuse").expect("scene");
    let (eye, target, fov_y) = scene.default_view();
    let look = Camera::look_at(width, height, fov_y, eye, target, Vec3::Z).expect("camera");
    ViewProjection::of_camera(&look, 0.05, 100.0)
}

/// Issue 16: a batch carrying a derived view (a headset's right eye taken from the left
/// eye's rows). The worker sends the derived view's pixels under its own task before the
/// batch's, renders only what reprojection leaves (bit for bit the kernel's pixels: the rows
/// beyond the batch's), and reports the rays it really rendered.
#[test]
fn a_derived_view_rides_on_a_batch_and_only_its_leftovers_are_rendered() {
    let (spp, bounces) = (4, 1);
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let _worker = WorkerProcess::start(master.addr(), assets.path(), "eyes", &["--spp", "4", "--bounces", "1"]);
    let w = master.accept_worker();
    let scene = scenes::builtin("diffuse").expect("scene");
    let (eye, target, fov_y) = scene.default_view();
    let centre = Camera::look_at(64, 48, fov_y, eye, target, Vec3::Z).expect("camera");
    let eyes = nephele_geometry::camera::stereo_pair(&centre, 0.064).expect("eyes");
    let [left, right] = eyes.map(|c| ViewProjection::of_camera(&c, 0.05, 100.0));
    let kernel = PathTracedKernel::new(Renderer::new(scene.scene).expect("renderer"), spp, bounces).expect("kernel");
    let right_camera = right.camera().expect("camera");
    let (truth, _) = kernel.render_pixels(&right_camera, &all_pixels(&right_camera)).expect("reference");
    // The key batch: rows 8..40 of the left eye; the derived view asks every row of the right.
    let asked: Vec<u32> = (0..64 * 48).collect();
    let derived_ids = BatchIds { batch_id: 1, task_id: 2, session_id: 1, frame_id: 1, view_index: 1 };
    let batch = RayBatch {
        ids: BatchIds { batch_id: 1, task_id: 1, session_id: 1, frame_id: 1, view_index: 0 },
        asset_id: "diffuse".into(),
        camera: left,
        pixels: (8 * 64..40 * 64).collect(),
        deadline_in_us: None,
        composer: composer.addr.to_string(),
        derived: vec![DerivedView { ids: derived_ids, camera: right, pixels: asked.clone() }],
        reuse: ReuseLimits::default(),
        occluders: Vec::new(),
    };
    master.send(w, &Message::RayBatch(batch.clone()));
    let done = match master.next() {
        Event::Message(_, Message::BatchDone(done)) => done,
        other => panic!("unexpected {other:?}"),
    };
    let first = composer.results.recv_timeout(WAIT).expect("derived result");
    let second = composer.results.recv_timeout(WAIT).expect("key result");
    assert_eq!((first.ids, second.ids), (derived_ids, batch.ids), "the derived view first, under its own task");
    assert_eq!(first.pixels, asked);
    assert_eq!(done.pixels as usize, batch.pixels.len() + asked.len());
    // Rendered: every key pixel, and some of the derived view's, not all (pixels whose ray
    // misses the object's box are empty without rendering, in any row).
    let leftover = done.stats.rays / u64::from(spp) - batch.pixels.len() as u64;
    assert!((1..asked.len() as u64 / 2).contains(&leftover), "{leftover} derived pixels rendered");
    assert_eq!(first.stats.rays, leftover * u64::from(spp));
    let (reused, mean, silhouettes) = compare_with_truth(&first, &truth, 8..40);
    // Reused pixels are the left eye's samples, not the right's: the same surface, other
    // noise (4 samples a pixel), hence a small mean difference rather than none.
    assert!(reused > 0);
    assert!(mean < 0.08, "reused pixels differ by {mean} on average");
    let covered = truth.opacity.iter().filter(|&&a| a > 0.0).count();
    assert!(silhouettes * 20 < covered, "{silhouettes} silhouette pixels lost of {covered} covered");
}

/// A user's consecutive frames (`ReuseLimits::previous_frames`): after a full render of a
/// view, the next frames of that view are taken from it by reprojection, only the leftovers
/// rendered; then the view is rendered in full again. The source batch held part of its
/// rows, so what lies beyond them is rendered, never taken for empty space.
#[test]
fn a_users_next_frames_come_from_the_previous_render_until_it_is_renewed() {
    let spp = 4;
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let _worker = WorkerProcess::start(master.addr(), assets.path(), "frames", &["--spp", "4", "--bounces", "1"]);
    let w = master.accept_worker();
    let scene = scenes::builtin("diffuse").expect("scene");
    let (eye, target, fov_y) = scene.default_view();
    let kernel = PathTracedKernel::new(Renderer::new(scene.scene).expect("renderer"), spp, 1).expect("kernel");
    // The user orbits the target by half a degree a frame.
    let view = |frame: u32| {
        let turn = glam::Quat::from_rotation_z((0.5 * frame as f32).to_radians());
        let camera = Camera::look_at(64, 48, fov_y, target + turn * (eye - target), target, Vec3::Z).expect("camera");
        (camera, ViewProjection::of_camera(&camera, 0.05, 100.0))
    };
    // A count with room for two reused frames after the staggered start of a new slot.
    let previous_frames = (2..=ReuseLimits::MAX_PREVIOUS_FRAMES)
        .find(|&n| n - nephele_worker::temporal::staggered_start("diffuse", n) >= 2)
        .expect("a count");
    let serves = previous_frames - nephele_worker::temporal::staggered_start("diffuse", previous_frames);
    let all: Vec<u32> = (0..64 * 48).collect();
    let mut frame_batch = |frame: u32, pixels: Vec<u32>| {
        let batch = RayBatch {
            ids: BatchIds {
                batch_id: u64::from(frame),
                task_id: u64::from(frame),
                session_id: 9,
                frame_id: u64::from(frame),
                view_index: 0,
            },
            asset_id: "diffuse".into(),
            camera: view(frame).1,
            pixels,
            deadline_in_us: None,
            composer: composer.addr.to_string(),
            derived: Vec::new(),
            reuse: ReuseLimits { previous_frames, ..ReuseLimits::default() },
            occluders: Vec::new(),
        };
        master.send(w, &Message::RayBatch(batch.clone()));
        let done = match master.next() {
            Event::Message(_, Message::BatchDone(done)) => done,
            other => panic!("unexpected {other:?}"),
        };
        let result = composer.results.recv_timeout(WAIT).expect("result");
        assert_eq!((result.ids, &result.pixels), (batch.ids, &batch.pixels));
        (done.stats.rays / u64::from(spp), result)
    };
    // Frame 0: rows 8..40 only, in full.
    let (rendered, _) = frame_batch(0, (8 * 64..40 * 64).collect());
    assert_eq!(rendered, 32 * 64);
    for frame in 1..=serves + 1 {
        let (rendered, result) = frame_batch(frame, all.clone());
        if frame > serves {
            assert_eq!(rendered, all.len() as u64, "frame {frame}: the render has served its count: in full");
            break;
        }
        // Rows 0..8 and 40..48 had no source (a third of the image): at most those and the
        // edges are rendered. Only the first reuse is certain: later ones depend on the
        // worker measuring reuse cheaper than rendering (it is, by far, for a path tracer,
        // but a test must not rest on timing), and a frame rendered in full is as good.
        // One rendered in full renews the slot (new source, new count): nothing more to check.
        if frame > 1 && rendered == all.len() as u64 {
            break;
        }
        assert!(rendered < all.len() as u64 * 2 / 3, "frame {frame}: {rendered} pixels rendered");
        let (camera, _) = view(frame);
        let (truth, _) = kernel.render_pixels(&camera, &all).expect("reference");
        let (reused, mean, _) = compare_with_truth(&result, &truth, 4..44);
        assert!(reused > 0, "frame {frame}");
        assert!(mean < 0.08, "frame {frame}: reused pixels differ by {mean} on average");
    }
}

/// A render ahead (`ReuseLimits::ahead`, the scheduler's render-ahead while the farm is idle):
/// the worker renders it in full, sends nothing to the composer, and keeps it, so that the
/// user's next frame near it is taken from it with only the leftovers rendered, as is another
/// user's view near it; a view far from it is rendered in full.
#[test]
fn a_render_ahead_is_kept_unseen_and_serves_the_users_next_frame() {
    let spp = 4;
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let _worker = WorkerProcess::start(master.addr(), assets.path(), "ahead", &["--spp", "4", "--bounces", "1"]);
    let w = master.accept_worker();
    let scene = scenes::builtin("diffuse").expect("scene");
    let (eye, target, fov_y) = scene.default_view();
    let kernel = PathTracedKernel::new(Renderer::new(scene.scene).expect("renderer"), spp, 1).expect("kernel");
    let view = |degrees: f32| {
        let turn = glam::Quat::from_rotation_z(degrees.to_radians());
        let camera = Camera::look_at(64, 48, fov_y, target + turn * (eye - target), target, Vec3::Z).expect("camera");
        (camera, ViewProjection::of_camera(&camera, 0.05, 100.0))
    };
    let previous_frames = ReuseLimits::DEFAULT_PREVIOUS_FRAMES;
    let all: Vec<u32> = (0..64 * 48).collect();
    let batch = |id: u64, degrees: f32, ahead: bool| RayBatch {
        ids: BatchIds { batch_id: id, task_id: id, session_id: 11, frame_id: id, view_index: 0 },
        asset_id: "diffuse".into(),
        camera: view(degrees).1,
        pixels: all.clone(),
        deadline_in_us: None,
        composer: composer.addr.to_string(),
        derived: Vec::new(),
        reuse: ReuseLimits { previous_frames, rows_complete: true, ahead, ..ReuseLimits::default() },
        occluders: Vec::new(),
    };
    let done = |master: &mut Master| match master.next() {
        Event::Message(_, Message::BatchDone(done)) => done,
        other => panic!("unexpected {other:?}"),
    };
    master.send(w, &Message::RayBatch(batch(1, 1.0, true)));
    let ahead = done(&mut master);
    assert_eq!(ahead.stats.rays / u64::from(spp), all.len() as u64, "rendered in full");
    assert!(composer.results.recv_timeout(Duration::from_millis(300)).is_err(), "no frame shows a render ahead");
    // The frame half a degree on: taken from the render ahead.
    let frame = batch(2, 1.5, false);
    master.send(w, &Message::RayBatch(frame.clone()));
    let done_frame = done(&mut master);
    let result = composer.results.recv_timeout(WAIT).expect("result");
    assert_eq!((result.ids, &result.pixels), (frame.ids, &frame.pixels));
    let rendered = done_frame.stats.rays / u64::from(spp);
    assert!(rendered < all.len() as u64 / 2, "{rendered} of {} pixels rendered", all.len());
    let (truth, _) = kernel.render_pixels(&view(1.5).0, &all).expect("reference");
    let (reused, mean, _) = compare_with_truth(&result, &truth, 0..48);
    assert!(reused > 0);
    assert!(mean < 0.08, "reused pixels differ by {mean} on average");
    // Another user looking from nearby, with no render of its own here, takes from it too;
    // one looking from far round the object renders in full.
    let mut near = batch(3, 2.0, false);
    near.ids.session_id = 12;
    master.send(w, &Message::RayBatch(near));
    let rendered = done(&mut master).stats.rays / u64::from(spp);
    assert!(rendered < all.len() as u64 / 2, "lent: {rendered} pixels rendered");
    let _ = composer.results.recv_timeout(WAIT).expect("result");
    let mut far = batch(4, 40.0, false);
    far.ids.session_id = 13;
    master.send(w, &Message::RayBatch(far));
    assert_eq!(done(&mut master).stats.rays / u64::from(spp), all.len() as u64, "no source near: in full");
    let _ = composer.results.recv_timeout(WAIT).expect("result");
}

/// A result with reused pixels against the kernel's own render `truth` of the whole 64-pixel
/// wide view: pixels outside the rows `sourced` had no source, so they are the kernel's own,
/// exactly; a pixel that differs (reused) never loses full coverage nor invents solid
/// coverage (a silhouette pixel that some samples hit may change). Returns the reused
/// pixels, their mean colour difference, and the silhouette pixels whose coverage changed.
fn compare_with_truth(
    result: &BatchResult,
    truth: &PixelResults,
    sourced: std::ops::Range<u32>,
) -> (usize, f64, usize) {
    let (mut reused, mut off, mut silhouettes) = (0usize, 0.0f64, 0usize);
    for (k, &p) in result.pixels.iter().enumerate() {
        let row = p / 64;
        let p = p as usize;
        let exact = result.color[k] == truth.color[p] && result.opacity[k] == truth.opacity[p];
        if !sourced.contains(&row) {
            assert!(exact, "pixel {p} (row {row}) has no source: the kernel's own");
        }
        if !exact {
            reused += 1;
            off += (0..3).map(|c| f64::from((result.color[k][c] - truth.color[p][c]).abs())).sum::<f64>() / 3.0;
            let (got, want) = (result.opacity[k], truth.opacity[p]);
            let (lost, invented) = (want == 1.0 && got == 0.0, want == 0.0 && got >= 0.99);
            assert!(!lost && !invented, "pixel {p}: {got} vs {want}");
            silhouettes += usize::from((got > 0.0) != (want > 0.0));
        }
    }
    (reused, off / reused.max(1) as f64, silhouettes)
}

#[test]
fn bad_batches_are_answered_and_the_worker_carries_on() {
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let mut process = WorkerProcess::start(
        master.addr(),
        assets.path(),
        "sturdy",
        &["--spp", "1", "--bounces", "1", "--concurrent-batches", "1"],
    );
    let w = master.accept_worker();
    let camera = frame_camera(64, 48);
    let good = RayBatch {
        ids: BatchIds { batch_id: 0, task_id: 1, session_id: 1, frame_id: 1, view_index: 0 },
        asset_id: "diffuse".into(),
        camera,
        pixels: (0..64 * 48).collect(),
        deadline_in_us: None,
        composer: composer.addr.to_string(),
        derived: Vec::new(),
        reuse: ReuseLimits::default(),
        occluders: Vec::new(),
    };
    let with = |id: u64, change: &dyn Fn(&mut RayBatch)| {
        let mut b = good.clone();
        b.ids.batch_id = id;
        change(&mut b);
        b
    };
    let mut scaled = camera;
    scaled.view.as_mut()[0] = 2.0; // finite, but not a rigid view: the camera conversion refuses it
    let cases: Vec<(RayBatch, ErrorCode)> = vec![
        (with(1, &|b| b.asset_id = "../diffuse".into()), ErrorCode::InvalidField),
        (with(2, &|b| b.asset_id = "scenes/diffuse".into()), ErrorCode::InvalidField),
        (with(3, &|b| b.asset_id = "..".into()), ErrorCode::InvalidField),
        (with(4, &|b| b.asset_id = "no-such-asset".into()), ErrorCode::UnknownAsset),
        (with(5, &|b| b.camera.view.as_mut()[5] = f32::NAN), ErrorCode::InvalidField),
        (with(6, &|b| b.camera.projection.as_mut()[0] = f32::INFINITY), ErrorCode::InvalidField),
        (with(7, &|b| b.pixels = vec![0, 64 * 48]), ErrorCode::InvalidField),
        (with(8, &|b| b.pixels = vec![]), ErrorCode::InvalidField),
        (with(9, &|b| b.camera = scaled), ErrorCode::InvalidField),
        (with(10, &|b| b.deadline_in_us = Some(0)), ErrorCode::DeadlineExpired),
        (with(11, &|b| b.composer = "nowhere".into()), ErrorCode::InvalidField),
    ];
    for (batch, _) in &cases {
        master.send(w, &Message::RayBatch(batch.clone()));
    }
    let mut answered = HashMap::new();
    while answered.len() < cases.len() {
        match master.next() {
            Event::Message(_, Message::BatchFailed(f)) => {
                assert!(!f.message.is_empty());
                assert!(answered.insert(f.ids.batch_id, f.code).is_none(), "batch {} answered twice", f.ids.batch_id);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    for (batch, code) in &cases {
        assert_eq!(answered[&batch.ids.batch_id], *code, "batch {}", batch.ids.batch_id);
    }
    process.assert_alive();

    // Cancellation: the second of two batches is dropped while the first renders.
    master.send(w, &Message::RayBatch(with(20, &|_| {})));
    master.send(w, &Message::RayBatch(with(21, &|_| {})));
    master.send(w, &Message::Cancel(Cancel { target: CancelTarget::Batch(21) }));
    // And then a good batch still renders and reaches the composer; its deadline is time
    // left (ten minutes), whatever the wall clocks say.
    master.send(
        w,
        &Message::RayBatch(with(22, &|b| {
            b.pixels = vec![0, 5, 64 * 24 + 32];
            b.deadline_in_us = Some(600_000_000);
        })),
    );
    let mut outcome = HashMap::new();
    while outcome.len() < 3 {
        match master.next() {
            Event::Message(_, Message::BatchDone(d)) => outcome.insert(d.ids.batch_id, None),
            Event::Message(_, Message::BatchFailed(f)) => outcome.insert(f.ids.batch_id, Some(f.code)),
            other => panic!("unexpected {other:?}"),
        };
    }
    assert_eq!(outcome[&20], None);
    assert_eq!(outcome[&21], Some(ErrorCode::Cancelled));
    assert_eq!(outcome[&22], None);
    let mut delivered = BTreeSet::new();
    while delivered.len() < 2 {
        let r = composer.results.recv_timeout(WAIT).expect("results at the composer");
        assert_eq!(r.worker_id, 100);
        delivered.insert(r.ids.batch_id);
    }
    assert_eq!(delivered, BTreeSet::from([20, 22]));
    process.assert_alive();
}

#[test]
fn garbage_oversized_frames_and_wrong_versions_close_the_connection_without_a_crash() {
    let assets = assets();
    let composer = Composer::start();
    let mut master = Master::new();
    let mut process = WorkerProcess::start(
        master.addr(),
        assets.path(),
        "target",
        &["--spp", "1", "--bounces", "1", "--concurrent-batches", "1", "--max-queued", "2"],
    );

    let expect_closed = |master: &mut Master, worker: usize, code: ErrorCode| {
        let mut told = false;
        loop {
            match master.next() {
                Event::Message(w, Message::Error(e)) if w == worker => {
                    assert_eq!(e.code, code, "{e:?}");
                    told = true;
                }
                Event::Closed(w, reason) if w == worker => {
                    assert!(!reason.is_empty());
                    break;
                }
                other => panic!("unexpected {other:?}"),
            }
        }
        assert!(told, "the worker says why before closing");
    };

    // An unknown message type.
    let w = master.accept_worker();
    master.send_raw(w, &[5, 0, 0, 0, 200, 1, 2, 3, 4]);
    expect_closed(&mut master, w, ErrorCode::UnknownMessageType);
    // The worker reconnects; now a 4 GiB length prefix.
    let w = master.accept_worker();
    master.send_raw(w, &u32::MAX.to_le_bytes());
    expect_closed(&mut master, w, ErrorCode::FrameTooLarge);
    // An HTTP request ("GET " read as a length is 542 MB).
    let w = master.accept_worker();
    master.send_raw(w, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n");
    expect_closed(&mut master, w, ErrorCode::FrameTooLarge);
    // A body that is not a RayBatch.
    let w = master.accept_worker();
    master.send_raw(w, &[6, 0, 0, 0, 5, 0xff, 0xff, 0xff, 0xff, 0xff]);
    expect_closed(&mut master, w, ErrorCode::Malformed);
    process.assert_alive();

    // A master of another protocol version: refused at the handshake.
    let stream = master.accept_stream();
    let mut reader = FrameReader::new(stream.try_clone().expect("clone"), FrameConfig::default());
    let mut writer = FrameWriter::new(stream, FrameConfig::default());
    writer.write_raw(&[8, 0, 0, 0, 1, b'N', b'P', b'H', b'L', 99, 0, 1]).expect("hello v99");
    assert!(matches!(reader.read_message(), Ok(Ok(Message::Hello(_)))));
    match reader.read_message() {
        Ok(Ok(Message::Error(e))) => assert_eq!(e.code, ErrorCode::VersionMismatch),
        other => panic!("expected a version error, got {other:?}"),
    }
    assert!(matches!(reader.read_message(), Err(nephele_proto::ProtoError::Closed)));

    // Through all that the process lived on and still renders.
    process.assert_alive();
    let w = master.accept_worker();
    let batch = RayBatch {
        ids: BatchIds { batch_id: 1, task_id: 1, session_id: 1, frame_id: 1, view_index: 0 },
        asset_id: "diffuse".into(),
        camera: frame_camera(32, 24),
        pixels: (0..32 * 24).collect(),
        deadline_in_us: None,
        composer: composer.addr.to_string(),
        derived: Vec::new(),
        reuse: ReuseLimits::default(),
        occluders: Vec::new(),
    };
    master.send(w, &Message::RayBatch(batch.clone()));
    assert!(matches!(master.next(), Event::Message(_, Message::BatchDone(_))));
    assert_eq!(composer.results.recv_timeout(WAIT).expect("result").pixels.len(), 32 * 24);

    // A flood: one batch rendering, two queued (--max-queued 2), the fourth refused.
    let big = RayBatch { camera: frame_camera(192, 144), pixels: (0..192 * 144).collect(), ..batch.clone() };
    for id in 10..14 {
        let b = if id == 10 { big.clone() } else { batch.clone() };
        master.send(w, &Message::RayBatch(RayBatch { ids: BatchIds { batch_id: id, ..b.ids }, ..b }));
    }
    let mut outcome = HashMap::new();
    while outcome.len() < 4 {
        match master.next() {
            Event::Message(_, Message::BatchDone(d)) => outcome.insert(d.ids.batch_id, None),
            Event::Message(_, Message::BatchFailed(f)) => outcome.insert(f.ids.batch_id, Some(f.code)),
            other => panic!("unexpected {other:?}"),
        };
    }
    assert_eq!(outcome, HashMap::from([(10, None), (11, None), (12, None), (13, Some(ErrorCode::Overloaded))]));
    process.assert_alive();
}

#[test]
fn an_unreachable_master_is_a_clear_error_and_bad_arguments_are_refused() {
    let assets = assets();
    let dir = assets.path().to_str().expect("utf-8 path");
    // A port nobody listens on.
    let port = TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr").port();
    let master = format!("127.0.0.1:{port}");
    let err = nephele_tests::nephele_err(&[
        "worker",
        "--master",
        &master,
        "--assets",
        dir,
        "--reconnect-secs",
        "0",
        "--spp",
        "1",
    ]);
    assert!(err.contains("gave up on the master"), "{err}");
    let err = nephele_tests::nephele_err(&["worker", "--master", "no-port", "--assets", dir]);
    assert!(err.contains("--master"), "{err}");
    let err = nephele_tests::nephele_err(&["worker", "--master", &master, "--assets", "/no/such/dir"]);
    assert!(err.contains("asset directory"), "{err}");
    let err = nephele_tests::nephele_err(&["worker", "--master", &master, "--assets", dir, "--name", "bad/name"]);
    assert!(err.contains("worker name"), "{err}");
}

#[test]
fn the_wire_benchmark_runs_between_two_processes() {
    let help = nephele_tests::nephele_ok(&["worker", "--help"]);
    assert!(help.contains("--master") && help.contains("SIGTERM"), "{help}");
    let out = nephele_tests::nephele_ok(&["bench", "wire", "--pixels", "256", "--batches", "20", "--repeats", "3"]);
    for row in ["packed arrays", "element by element", "two processes", "two tokio tasks", "bytes/px"] {
        assert!(out.contains(row), "{row} missing from:\n{out}");
    }
}
