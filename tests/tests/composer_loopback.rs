//! A WebRTC client built on the same stack negotiates with a running composer on loopback,
//! receives H.264 over RTP and decodes it, sends poses and control over the data channel;
//! worker results sent over TCP come out as the picture; bad signalling gets clear errors.

#![allow(clippy::unwrap_used)] // a test may unwrap

use std::time::Duration;

use futures_util::SinkExt;
use glam::Vec3;
use nephele_composer::pose::{Control, Pose, look_at_pose};
use nephele_composer::service::{Composer, ComposerConfig, FrameSource};
use nephele_proto::stream::{framed, handshake};
use nephele_proto::{BatchIds, BatchResult, FrameConfig, FramePlan, KernelStats, Message, PlanPart, Role};
use nephele_tests::viewer::{Client, ClientOptions, http_request};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

const WAIT: Duration = Duration::from_secs(15);

async fn http(
    addr: std::net::SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> (u16, String) {
    http_request(addr, method, path, headers, body).await.unwrap()
}

async fn connect(composer: &Composer, extra: &str) -> Client {
    let client =
        Client::connect(composer.http_addr(), ClientOptions { extra_json: extra.into(), ..Default::default() })
            .await
            .unwrap();
    let sdp = &client.answer_sdp;
    assert!(sdp.contains("H264/90000") && sdp.contains("packetization-mode=1"), "{sdp}");
    assert!(sdp.contains("profile-level-id=42e01f"), "{sdp}");
    assert!(sdp.contains("a=candidate:"), "the answer carries its candidates (no trickle)");
    client
}

fn config(source: FrameSource) -> ComposerConfig {
    ComposerConfig {
        http_addr: "127.0.0.1:0".parse().unwrap(),
        results_addr: "127.0.0.1:0".parse().unwrap(),
        source,
        fps: 30.0,
        default_view: (160, 120),
        ..ComposerConfig::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_negotiates_receives_h264_and_sends_poses() {
    let composer = Composer::start(config(FrameSource::TestPattern)).await.unwrap();
    let mut poses = composer.poses();
    let mut client = connect(&composer, "").await;

    // The first decodable picture is an IDR of the default view size.
    let first = client.next_picture(WAIT, |_| true).await.unwrap();
    assert!(first.idr, "the stream starts with an IDR");
    assert_eq!((first.width, first.height), (160, 120));

    // A stereo pose of 96x64 per eye: the composer receives it, and the picture becomes
    // 192x64 side by side (a new encoder, so a new IDR).
    let mut pose = look_at_pose(1, 96, 64, 0.9, Vec3::new(0.0, -3.0, 1.0), Vec3::ZERO).unwrap();
    let mut right = pose.views[0];
    right.view = glam::Mat4::from_translation(Vec3::new(-0.064, 0.0, 0.0)) * right.view;
    pose.views.push(right);
    client.send_pose(&pose).await.unwrap();
    let (session, received) = tokio::time::timeout(WAIT, poses.recv()).await.unwrap().unwrap();
    assert_eq!((session, received.seq, received.views.len()), (client.session, 1, 2));
    let stereo = client.next_picture(WAIT, |p| p.width == 192).await.unwrap();
    assert_eq!((stereo.width, stereo.height, stereo.idr), (192, 64, true));

    // Malformed poses are dropped and counted; ping gets a pong; a keyframe request works.
    client.send_binary(vec![0x50, 1, 1, 0]).await.unwrap();
    let mut nan = Pose::decode(&pose.encode()).unwrap().encode();
    nan[20..24].copy_from_slice(&f32::NAN.to_le_bytes());
    tokio::time::sleep(Duration::from_millis(30)).await;
    client.send_binary(nan).await.unwrap();
    client.send_control(&Control::Ping { t: 42.5 }).await.unwrap();
    let pong = client.next_text(WAIT).await.unwrap();
    assert_eq!(pong, r#"{"type":"pong","t":42.5}"#);
    client.send_text(r#"{"type":"keyframe"}"#).await.unwrap();
    client.next_picture(WAIT, |p| p.idr && p.width == 192).await.unwrap();
    // The media thread counts a frame after sending it: the client can see the keyframe
    // before the report does.
    let deadline = tokio::time::Instant::now() + WAIT;
    let report = loop {
        let report = composer.sessions().into_iter().find(|r| r.session == client.session).unwrap();
        if report.encoder.keyframes >= 2 || tokio::time::Instant::now() >= deadline {
            break report;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    assert_eq!((report.poses.accepted, report.poses.malformed), (1, 2), "{report:?}");
    assert!(report.connected && report.media.frames_sent >= 3, "{report:?}");
    assert!(report.encoder.keyframes >= 2, "{report:?}");

    // The session list over HTTP; deleting needs the token.
    let (status, list) = http(composer.http_addr(), "GET", "/v1/sessions", &[], "").await;
    assert_eq!(status, 200);
    let (_, metrics) = http(composer.http_addr(), "GET", "/metrics", &[], "").await;
    assert!(metrics.contains("nephele_composer_media_threads 1\n"), "{metrics}");
    assert!(list.contains(&format!("\"session\":{}", client.session)), "{list}");
    let path = format!("/v1/sessions/{}", client.session);
    let (status, _) = http(composer.http_addr(), "DELETE", &path, &[("Authorization", "Bearer nope")], "").await;
    assert_eq!(status, 401);
    let bearer = format!("Bearer {}", client.token);
    let (status, _) = http(composer.http_addr(), "DELETE", &path, &[("Authorization", &bearer)], "").await;
    assert_eq!(status, 204);
    // The session's media thread ended before the answer: none is left sending through the
    // runtime (shutdown ends sessions the same way).
    let (_, metrics) = http(composer.http_addr(), "GET", "/metrics", &[], "").await;
    assert!(metrics.contains("nephele_composer_media_threads 0\n"), "{metrics}");
    let (status, _) = http(composer.http_addr(), "DELETE", &path, &[("Authorization", &bearer)], "").await;
    assert_eq!(status, 404);
    assert!(composer.sessions().is_empty());
    client.close().await;
    composer.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_offers_get_a_clear_error() {
    let composer = Composer::start(config(FrameSource::Workers)).await.unwrap();
    let addr = composer.http_addr();
    let cases = [
        (r#"{"type":"offer","sdp":"hello"}"#, "malformed SDP"),
        (
            r#"{"type":"offer","sdp":"v=0\r\no=- 1 1 IN IP4 0.0.0.0\r\ns=-\r\nt=0 0\r\nm=audio 9 UDP/TLS/RTP/SAVPF 111\r\n"}"#,
            "H.264",
        ),
        (r#"{"type":"offer","sdp":"v=0\r\nm=video 9 garbage\r\n"}"#, "malformed SDP"),
        (r#"{"type":"answer","sdp":"v=0"}"#, "expected an SDP offer"),
        (r#"not json"#, "expected JSON"),
    ];
    for (body, words) in cases {
        let (status, reply) = http(addr, "POST", "/v1/sessions", &[], body).await;
        assert_eq!(status, 400, "{body} → {reply}");
        assert!(reply.contains(words), "{body} → {reply}");
    }
    assert!(composer.sessions().is_empty());
    composer.shutdown().await;
}

/// A farm of one's own on the results listener: a peer with role tool sends the frame plans
/// a master would, and batch results as workers do, all in proto.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worker_results_over_tcp_become_the_streamed_picture() {
    let composer = Composer::start(config(FrameSource::Workers)).await.unwrap();
    let mut client = connect(&composer, r#""width":64,"height":32"#).await;
    let results = || async {
        let stream = TcpStream::connect(composer.results_addr()).await.unwrap();
        let mut conn = framed(stream, FrameConfig::default());
        handshake(&mut conn, Role::Tool, &[Role::Composer], None, WAIT).await.unwrap();
        conn
    };
    let mut farm = results().await;
    let all: Vec<u32> = (0..64 * 32).collect();
    // Two workers' batches per frame: left half white, right half black, on the farm's
    // black background; then the halves swap. Mean luma tells which frame arrived.
    let left: Vec<u32> = all.iter().copied().filter(|p| p % 64 < 32).collect();
    let right: Vec<u32> = all.iter().copied().filter(|p| p % 64 >= 32).collect();
    let session = client.session;
    let batch = |frame: u64, task_id: u64, pixels: &[u32], value: f32, depth: f32| BatchResult {
        ids: BatchIds { batch_id: task_id, task_id, session_id: session, frame_id: frame, view_index: 0 },
        worker_id: 1,
        width: 64,
        height: 32,
        pixels: pixels.to_vec(),
        color: vec![[value; 3]; pixels.len()],
        opacity: vec![1.0; pixels.len()],
        depth: vec![depth; pixels.len()],
        render_time_us: 10,
        stats: KernelStats::default(),
        encoding: nephele_proto::ResultEncoding::F32,
    };
    let plan = |frame: u64, parts: Vec<PlanPart>| FramePlan {
        session_id: session,
        frame_id: frame,
        pose_sequence: 0,
        client_time_ms: 0.0,
        width: 64,
        height: 32,
        views: 1,
        parts,
        deadline_in_us: None,
    };
    let mut means = Vec::new();
    for frame in 0..6u64 {
        let bright_left = frame < 3;
        let (l, r) = if bright_left { (1.0, 0.0) } else { (0.0, 1.0) };
        let (left_task, right_task) = (2 * frame, 2 * frame + 1);
        farm.send(&Message::BatchResult(batch(frame, right_task, &right, r, 2.0))).await.unwrap();
        farm.send(&Message::BatchResult(batch(frame, left_task, &left, l, 1.0))).await.unwrap();
        let parts = vec![
            PlanPart { view: 0, task_id: left_task, object_id: 0 },
            PlanPart { view: 0, task_id: right_task, object_id: 1 },
        ];
        farm.send(&Message::FramePlan(plan(frame, parts))).await.unwrap();
        let p = client.next_picture(WAIT, |_| true).await.unwrap();
        assert_eq!((p.width, p.height), (64, 32));
        means.push(p.mean_y);
    }
    // Half white (235) and half black (16): mean about 125.5 either way, and the decoded
    // pictures are complete frames, not the background (16).
    for m in &means {
        assert!((*m - 125.5).abs() < 6.0, "{means:?}");
    }
    // Bytes that are no message (an unknown message type) end that connection, counted; the
    // composer goes on serving: a new connection's plan still becomes a picture.
    farm.get_mut().write_all(&[3, 0, 0, 0, 99, 1, 2]).await.unwrap();
    let start = std::time::Instant::now();
    while composer.wire_errors() == 0 && start.elapsed() < WAIT {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let mut farm = results().await;
    farm.send(&Message::BatchResult(batch(10, 100, &all, 1.0, 1.0))).await.unwrap();
    farm.send(&Message::FramePlan(plan(10, vec![PlanPart { view: 0, task_id: 100, object_id: 0 }]))).await.unwrap();
    let white = client.next_picture(WAIT, |p| p.mean_y > 200.0).await.unwrap();
    assert!(white.mean_y > 230.0, "{white:?}");
    assert_eq!(composer.wire_errors(), 1);
    let report = composer.sessions().remove(0);
    assert_eq!(report.fusion.frames_complete, 7, "{report:?}");
    // Only a tool may plan frames: a worker's plan is ignored.
    let stream = TcpStream::connect(composer.results_addr()).await.unwrap();
    let mut worker = framed(stream, FrameConfig::default());
    handshake(&mut worker, Role::Worker, &[Role::Composer], None, WAIT).await.unwrap();
    worker.send(&Message::FramePlan(plan(11, vec![PlanPart { view: 0, task_id: 100, object_id: 0 }]))).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let report = composer.sessions().remove(0);
    assert_eq!(report.fusion.frames_complete, 7, "a worker's plan was fused: {report:?}");
    client.close().await;
    composer.shutdown().await;
}

/// Chromium hides its host addresses behind mDNS `.local` names. The composer (mDNS off)
/// ignores those candidates and still connects: the client reaches the composer's own
/// candidates and shows up as peer-reflexive.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_with_mdns_candidates_still_connects() {
    let composer = Composer::start(config(FrameSource::TestPattern)).await.unwrap();
    let options = ClientOptions { mdns_candidates: true, ..Default::default() };
    let mut client = Client::connect(composer.http_addr(), options).await.unwrap();
    let candidates: Vec<&str> = client.offer_sdp.lines().filter(|l| l.starts_with("a=candidate:")).collect();
    assert!(!candidates.is_empty() && candidates.iter().all(|c| c.contains(".local")), "{candidates:?}");
    let first = client.next_picture(WAIT, |_| true).await.unwrap();
    assert!(first.idr && first.width == 160);
    client.close().await;
    composer.shutdown().await;
}

/// Bad clients do not disturb good ones: poses sent far faster than every 20 ms are dropped
/// and counted (a token bucket), and a client that vanishes without `DELETE` loses its
/// session, while another viewer's stream goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flooding_client_is_rate_limited_and_a_vanished_one_dropped_without_disturbing_others() {
    let composer = Composer::start(config(FrameSource::TestPattern)).await.unwrap();
    let mut calm = connect(&composer, "").await;
    let flood = connect(&composer, "").await;
    calm.next_picture(WAIT, |_| true).await.unwrap();
    let report_of = |session: u64| composer.sessions().into_iter().find(|r| r.session == session);

    let sent = 200u32;
    for seq in 1..=sent {
        let pose = look_at_pose(seq, 160, 120, 0.9, Vec3::new(0.0, -3.0, 1.0), Vec3::ZERO).unwrap();
        flood.send_pose(&pose).await.unwrap();
    }
    for _ in 0..5 {
        calm.next_picture(WAIT, |_| true).await.unwrap();
    }
    let start = std::time::Instant::now();
    let flooded = loop {
        let r = report_of(flood.session).expect("the flooding session still exists");
        if r.poses.received == u64::from(sent) || start.elapsed() > WAIT {
            break r;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let p = flooded.poses;
    assert_eq!(p.received, u64::from(sent), "{p:?}");
    assert!(p.rate_limited >= 100 && p.accepted >= 1, "{p:?}");
    assert_eq!(p.accepted + p.rate_limited + p.stale + p.malformed, p.received, "{p:?}");

    // Vanish: the peer connection goes away, no DELETE.
    flood.close().await;
    let start = std::time::Instant::now();
    while report_of(flood.session).is_some() {
        assert!(start.elapsed() < Duration::from_secs(20), "the vanished client's session is still there");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    for _ in 0..5 {
        calm.next_picture(WAIT, |_| true).await.unwrap();
    }
    let calm_report = report_of(calm.session).expect("the calm session");
    assert!(calm_report.connected && calm_report.poses.rate_limited == 0, "{calm_report:?}");
    calm.close().await;
    composer.shutdown().await;
}

/// Congestion control (issue 15, part 4, first cut): a receiver's REMB estimate below the
/// stream's rate brings the encoder down to it (re-created at the new rate, counted), and the
/// stream goes on from a keyframe.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_receivers_estimate_brings_the_stream_bitrate_down() {
    let composer = Composer::start(config(FrameSource::TestPattern)).await.unwrap();
    let mut client = connect(&composer, "").await;
    client.next_picture(WAIT, |_| true).await.unwrap();
    let changes = || composer.sessions().first().map_or(0, |r| r.media.bitrate_changes);
    assert_eq!(changes(), 0, "a clean loopback link changes nothing");
    // 160x120 streams at 300 kbit/s (the picture-size default's minimum); the receiver says
    // it can take 100: the rate goes to the floor, 150 kbit/s, within the 2-s hold.
    let start = std::time::Instant::now();
    while changes() == 0 {
        assert!(start.elapsed() < Duration::from_secs(15), "the estimate never moved the bitrate");
        client.send_remb(100_000.0).await.unwrap();
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(changes(), 1);
    // The new encoder starts with a keyframe; pictures keep coming.
    let idr = client.next_picture(WAIT, |p| p.idr).await.unwrap();
    assert_eq!((idr.width, idr.height), (160, 120));
    client.next_picture(WAIT, |p| !p.idr).await.unwrap();
    client.close().await;
    composer.shutdown().await;
}

/// The composer's counter `name` from its `/metrics`.
async fn composer_counter(composer: &Composer, name: &str) -> u64 {
    let (status, text) = http(composer.http_addr(), "GET", "/metrics", &[], "").await;
    assert_eq!(status, 200);
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|rest| rest.trim().parse().ok()))
        .unwrap_or_else(|| panic!("no {name} in {text}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_keyframe_leaves_paced_unless_pacing_is_off() {
    use nephele_composer::pacer::{BURST, PACING_FACTOR};
    for pacing in [true, false] {
        // 640x480 at 30 kbit/s: paced at 75 kbit/s with a burst of 375 bytes; the first
        // keyframe, at the encoder's coarsest quantiser, is several times that (at ordinary
        // rates OpenH264's keyframes stay within the burst: BENCHMARKS.md 2026-12-05g).
        let bitrate = 30_000;
        let mut cfg = config(FrameSource::TestPattern);
        cfg.default_view = (640, 480);
        cfg.bitrate_bps = Some(bitrate);
        cfg.rtc.pacing = pacing;
        let composer = Composer::start(cfg).await.unwrap();
        let mut client = connect(&composer, "").await;
        let idr = client.next_picture(WAIT, |p| p.idr).await.unwrap();
        let rate = PACING_FACTOR * f64::from(bitrate);
        let burst = BURST.as_secs_f64() * rate / 8.0;
        assert!(idr.bytes as f64 > 3.0 * burst, "the keyframe ({} bytes) must need pacing", idr.bytes);
        assert!(idr.packets >= 2, "{} packets", idr.packets);
        // The media thread counts after the frame left; the counters are read at a scrape.
        tokio::time::sleep(Duration::from_millis(200)).await;
        let paced = composer_counter(&composer, "nephele_composer_packets_paced_total").await;
        let wait_ms = composer_counter(&composer, "nephele_composer_pacing_wait_ms_total").await;
        if pacing {
            // The packets past the burst were held back (their spacing on a given clock is
            // checked in `retransmit`'s paused-clock test; arrival times on loopback would
            // depend on this machine's scheduling).
            assert!(paced > 0 && wait_ms > 0, "paced {paced}, waited {wait_ms} ms");
        } else {
            assert_eq!((paced, wait_ms), (0, 0));
        }
        client.next_picture(WAIT, |p| !p.idr).await.unwrap();
        client.close().await;
        composer.shutdown().await;
    }
}
