//! The whole service across processes: `nephele up --workers 2` (master, composer, two
//! workers) on a first start, which bakes the default scene's objects into i-NOLF assets
//! (`--bake quick`: small, blurry, seconds each); a WebRTC client that opens its session
//! through the MASTER's `POST /v1/sessions`, sends poses in the browser client's format and
//! receives H.264 rendered by the farm from those assets; a worker killed with SIGKILL
//! mid-stream is started again while the frames keep coming; a composer killed while
//! `nephele loadgen` streams is started again and the user goes on in a new session; then
//! SIGINT stops everything with no child left behind.

use std::time::{Duration, Instant};

use nephele_composer::pose::look_at_pose;
use nephele_tests::service::{UpService, alive, children_in_role, children_of};
use nephele_tests::viewer::{Client, ClientOptions, http_request};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nephele_up_bakes_the_default_scene_streams_frames_rendered_by_the_farm_and_stops_on_ctrl_c() {
    let assets = tempfile::tempdir().expect("an empty asset folder: a first start");
    let assets_arg = assets.path().to_str().expect("utf-8 path");
    let mut up = UpService::start_with(
        2,
        &["--bake", "quick", "--assets", assets_arg, "--log-format", "json"],
        Duration::from_secs(600),
    );
    let http = up.http;
    // Each of the default scene's objects was baked, scored and put where the workers look.
    for object in ["diffuse", "glossy", "shell"] {
        let baked = up.startup.iter().find(|l| l.starts_with(&format!("baked '{object}'")));
        assert!(baked.is_some_and(|l| l.contains(" dB on held-out views")), "{object}: {:#?}", up.startup);
        assert!(assets.path().join(format!("{object}.nolf")).is_file(), "{object}.nolf");
    }
    let names: Vec<String> = std::fs::read_dir(assets.path())
        .expect("the asset folder")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        !names.iter().any(|n| n.contains(".part") || n.starts_with(".bake-")),
        "scratch files left behind: {names:?}"
    );
    assert!(up.startup.iter().any(|l| l.contains("served by the i-NOLF kernel")), "{:#?}", up.startup);
    assert!(up.url_line.contains(&http.to_string()), "{}", up.url_line);
    let children = children_of(up.pid());
    assert_eq!(children.len(), 4, "master, composer, two workers: {children:?}");

    let (w, h) = (64, 48);
    let options =
        ClientOptions { extra_json: format!(r#""scene":"default","width":{w},"height":{h}"#), ..Default::default() };
    let mut client = Client::connect(http, options).await.expect("a session through the master");
    let name = client.session_name.clone().expect("the master's session_id");

    // Poses in the browser client's format; frames must follow: an IDR, then more.
    let (eye, target) = (glam::Vec3::new(0.0, -6.0, 2.0), glam::Vec3::ZERO);
    let started = Instant::now();
    let (mut seq, mut idr, mut after) = (0u32, false, 0u32);
    while started.elapsed() < Duration::from_secs(30) && after < 5 {
        seq += 1;
        let pose = look_at_pose(seq, w, h, 0.8, eye, target).expect("a valid pose");
        client.send_pose(&pose).await.expect("sending a pose");
        if let Ok(picture) = client.next_picture(Duration::from_millis(50), |_| true).await {
            assert_eq!((picture.width, picture.height), (w as usize, h as usize));
            if idr {
                after += 1;
            } else {
                assert!(picture.idr, "the first picture is an IDR");
                idr = true;
            }
        }
    }
    assert!(idr && after >= 5, "an IDR then 5 more frames within 30 s: idr {idr}, after {after}");
    // The workers rendered them from the baked assets, not by path tracing the built-ins.
    let log = up.log_text();
    assert!(log.contains("loading asset file") && log.contains(".nolf"), "no worker loaded a baked asset");
    assert!(!log.contains("path traced"), "a worker path traced a built-in object");

    let (status, farm) = http_request(http, "GET", "/v1/farm", &[], "").await.expect("GET /v1/farm");
    assert_eq!(status, 200, "{farm}");
    let farm: serde_json::Value = serde_json::from_str(&farm).expect("JSON");
    assert_eq!(farm["workers"].as_array().map(Vec::len), Some(2), "{farm}");
    assert!(!farm["composer"].is_null(), "{farm}");
    let sessions = farm["sessions"].as_array().expect("sessions");
    assert!(sessions.iter().any(|s| s["id"].as_str() == Some(name.as_str())), "{farm}");

    // The composer timed every frame from the pose it received to the frame it sent.
    let composer = up.composer_http.expect("nephele up prints the composer's address");
    let (status, body) =
        http_request(composer, "GET", "/v1/sessions", &[], "").await.expect("composer GET /v1/sessions");
    assert_eq!(status, 200, "{body}");
    let report: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    let latency = &report["latency_ms"];
    assert!(latency["pose_to_sent"]["count"].as_u64().is_some_and(|n| n >= 3), "{latency}");
    for stage in ["pose_to_sent", "farm", "results_wait", "fusion", "yuv", "encode", "send"] {
        let p50 = latency[stage]["p50"].as_f64().unwrap_or(-1.0);
        assert!((0.0..10_000.0).contains(&p50), "{stage}: {latency}");
    }
    let total = latency["pose_to_sent"]["p50"].as_f64().unwrap_or(0.0);
    assert!(total >= latency["encode"]["p50"].as_f64().unwrap_or(0.0), "{latency}");

    // A worker killed mid-stream: the frames keep coming (the master re-issues its batches
    // to the other worker), and `nephele up` starts it again; it rejoins the farm.
    let workers = children_in_role(up.pid(), "worker");
    assert_eq!(workers.len(), 2, "{workers:?}");
    let victim = workers[0];
    let killed = std::process::Command::new("kill").args(["-KILL", &victim.to_string()]).status().expect("kill");
    assert!(killed.success());
    let started = Instant::now();
    let (mut while_down, mut after_back, mut back_after) = (0u32, 0u32, None);
    while started.elapsed() < Duration::from_secs(90) && (back_after.is_none() || after_back < 3) {
        seq += 1;
        let pose = look_at_pose(seq, w, h, 0.8, eye, target).expect("a valid pose");
        client.send_pose(&pose).await.expect("sending a pose");
        if client.next_picture(Duration::from_millis(50), |_| true).await.is_ok() {
            if back_after.is_some() { after_back += 1 } else { while_down += 1 }
        }
        if back_after.is_none() && seq % 10 == 0 {
            let now = children_in_role(up.pid(), "worker");
            let (_, farm) = http_request(http, "GET", "/v1/farm", &[], "").await.expect("GET /v1/farm");
            let farm: serde_json::Value = serde_json::from_str(&farm).expect("JSON");
            if now.len() == 2 && !now.contains(&victim) && farm["workers"].as_array().map(Vec::len) == Some(2) {
                back_after = Some(started.elapsed());
            }
        }
    }
    let log = up.log_text();
    assert!(back_after.is_some(), "the killed worker did not rejoin within 90 s");
    assert!(log.contains("restarted"), "no restart in the log");
    // The same session streams on after the restart (how many frames arrive during the
    // outage depends on this machine's speed: printed, not checked).
    assert!(after_back >= 3, "frames while the worker was down {while_down}, after it was back {after_back}");
    println!("worker {victim} killed: back in the farm after {back_after:?}; {while_down} frames meanwhile");
    // `--log-format json` reached every process, the restarted one included: each of our
    // log events is one JSON object per line (other lines come from C libraries writing to
    // stderr themselves, such as Mesa's Vulkan loader when a worker looks for a GPU, and
    // none of them is a text-format event: those begin with a timestamp), no colour codes.
    let lines: Vec<&str> = log.lines().filter(|l| !l.trim().is_empty()).collect();
    let is_event = |l: &&&str| {
        serde_json::from_str::<serde_json::Value>(l).is_ok_and(|v| v["level"].is_string() && v["message"].is_string())
    };
    let json_lines = lines.iter().filter(is_event).count();
    let text_events: Vec<&&str> =
        lines.iter().filter(|l| !is_event(l) && l.starts_with("20") && l.contains('Z')).collect();
    assert!(json_lines > 20, "{json_lines} of {} log lines are JSON events", lines.len());
    assert!(text_events.is_empty(), "text-format events with --log-format json: {text_events:#?}");
    assert!(!log.contains('\u{1b}'), "colour codes in the log");
    assert!(log.contains(r#""message":"restarted""#) && log.contains(r#""process":"worker-"#), "no JSON restart event");
    let children: Vec<u32> = children.into_iter().chain(children_of(up.pid())).collect();

    let auth = format!("Bearer {}", client.token);
    let (status, body) = http_request(http, "DELETE", &format!("/v1/sessions/{name}"), &[("authorization", &auth)], "")
        .await
        .expect("DELETE");
    assert_eq!(status, 204, "{body}");
    client.close().await;
    // The ended session's peer connection is freed, not only closed (webrtc-rs handlers that
    // hold their connection would keep it, and its buffers, for the composer's life).
    let started = std::time::Instant::now();
    let peer_connections = loop {
        let (_, text) = http_request(composer, "GET", "/metrics", &[], "").await.expect("composer GET /metrics");
        let count = nephele_tests::metric_value(&text, "nephele_composer_peer_connections");
        if count == Some(0.0) || started.elapsed() > Duration::from_secs(20) {
            break count;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    assert_eq!(peer_connections, Some(0.0), "peer connections still alive 20 s after the only session ended");

    // A composer killed mid-stream: the master ends its sessions and `nephele up` starts it
    // again; a viewer (`nephele loadgen`, which connects again as the browser client does)
    // streams on in a new session.
    let report_file = assets.path().join("loadgen.json");
    let loadgen = std::process::Command::new(nephele_tests::nephele_bin())
        .args(["-q", "loadgen", "--url", &format!("http://{http}/"), "--users", "1", "--size", "64x48"])
        .args(["--seconds", "25", "--json", report_file.to_str().expect("utf-8 path")])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("nephele loadgen");
    let started = Instant::now();
    let first_session = loop {
        let (_, body) = http_request(http, "GET", "/v1/sessions", &[], "").await.expect("GET /v1/sessions");
        let listed: serde_json::Value = serde_json::from_str(&body).expect("JSON");
        if let Some(id) = listed["sessions"][0]["id"].as_str() {
            break id.to_string();
        }
        assert!(started.elapsed() < Duration::from_secs(60), "loadgen opened no session: {body}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    tokio::time::sleep(Duration::from_secs(2)).await;
    let composers = children_in_role(up.pid(), "composer");
    assert_eq!(composers.len(), 1, "{composers:?}");
    let killed = std::process::Command::new("kill").args(["-KILL", &composers[0].to_string()]).status().expect("kill");
    assert!(killed.success());
    let output = loadgen.wait_with_output().expect("loadgen's output");
    let table = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{table}\n{}", String::from_utf8_lossy(&output.stderr));
    let reports: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report_file).expect("the JSON report")).expect("JSON");
    let user = &reports[0];
    assert!(user["error"].is_null() && user["reconnects"] == 1, "{table}");
    // Told by the master's watch the moment the composer's link closed, not by ICE seconds later.
    assert_eq!(user["lost"], serde_json::json!(["the service ended the session"]), "{reports}");
    assert!(user["session_id"].as_str().is_some_and(|id| id != first_session), "{table}");
    assert!(user["frames"].as_u64().is_some_and(|n| n >= 10), "{table}");
    let restarted = children_in_role(up.pid(), "composer");
    assert!(restarted.len() == 1 && restarted[0] != composers[0], "{restarted:?}");
    println!("composer {} killed; loadgen went on in a new session:\n{table}", composers[0]);
    let children: Vec<u32> = children.into_iter().chain(children_of(up.pid())).collect();

    let status = up.interrupt(Duration::from_secs(15)).expect("nephele up stops within 15 s of SIGINT");
    assert!(status.success(), "nephele up exited with {status}");
    let left: Vec<u32> = children.into_iter().filter(|&c| alive(c)).collect();
    assert!(left.is_empty(), "children still running: {left:?}");
}
