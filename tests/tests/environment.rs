//! The environment served by the farm (issue 13): `nephele up --scene room-day` on a first
//! start bakes the knot (i-NOLF) and trains the room's single-eye GI model and its stereo
//! student (`--bake quick`: seconds, barely trained); the workers shade every view of the
//! room with them and the composer fuses the knot into it by depth. A flat WebRTC client gets
//! frames the room fills (no black background left); a stereo `loadgen` user streams, the
//! room's two eyes in one batch (the scheduler's `views_derived`), shaded in one stereo pass;
//! the G-buffer samples behind the knot's solid matter are not lit (the master's
//! `samples_hidden`).

use std::sync::Arc;
use std::time::{Duration, Instant};

use nephele_composer::pose::look_at_pose;
use nephele_loadgen::{Live, LoadConfig, pose::UserDisplay};
use nephele_tests::service::UpService;
use nephele_tests::viewer::{Client, ClientOptions, http_request};

/// Share of pixels darker than video black plus a margin (luma 16 is black in H.264's
/// limited range).
fn black_share(luma: &[u8]) -> f64 {
    luma.iter().filter(|&&y| y <= 20).count() as f64 / luma.len().max(1) as f64
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_room_is_shaded_by_its_gi_model_on_the_farm_and_fused_with_the_knot_for_flat_and_stereo_users() {
    let assets = tempfile::tempdir().expect("an empty asset folder: a first start");
    let assets_arg = assets.path().to_str().expect("utf-8 path");
    let mut up = UpService::start_with(
        2,
        &["--bake", "quick", "--scene", "room-day", "--assets", assets_arg],
        Duration::from_secs(600),
    );
    let http = up.http;
    let startup = up.startup.join("\n");
    assert!(startup.contains("baked 'diffuse'") && startup.contains("baked 'room-day'"), "{startup}");
    assert!(startup.contains("the environment 'room-day' shaded by its GI model"), "{startup}");
    for file in ["diffuse.nolf", "room-day.ngi", "room-day.stereo.ngi"] {
        assert!(assets.path().join(file).is_file(), "{file}: {startup}");
    }

    // A flat client: the room behind the knot fills the frame.
    let (w, h) = (64, 48);
    let options =
        ClientOptions { extra_json: format!(r#""scene":"room-day","width":{w},"height":{h}"#), ..Default::default() };
    let mut client = Client::connect(http, options).await.expect("a session through the master");
    let (eye, target) = (glam::Vec3::new(1.55, -1.1, 1.75), glam::Vec3::new(0.0, 0.0, 1.1));
    let started = Instant::now();
    let (mut seq, mut pictures, mut darkest) = (0u32, 0u32, 0.0f64);
    while started.elapsed() < Duration::from_secs(60) && pictures < 5 {
        seq += 1;
        let pose = look_at_pose(seq, w, h, 66f32.to_radians(), eye, target).expect("a valid pose");
        client.send_pose(&pose).await.expect("sending a pose");
        if let Ok(picture) = client.next_picture(Duration::from_millis(50), |_| true).await {
            assert_eq!((picture.width, picture.height), (w as usize, h as usize));
            pictures += 1;
            // The first pictures may predate the first composed frame.
            if pictures >= 3 {
                darkest = darkest.max(black_share(&picture.luma));
            }
        }
    }
    assert!(pictures >= 5, "5 pictures within 60 s, got {pictures}");
    println!("black pixels: {:.1} %", 100.0 * darkest);
    // Without the environment most of this view is black background (the knot covers about
    // a third); with it, next to nothing is.
    assert!(darkest < 0.05, "{:.1} % of the pixels are black", 100.0 * darkest);
    client.close().await;

    // A stereo user through `loadgen`.
    let config = LoadConfig {
        url: format!("http://{http}/"),
        scene: "room-day".into(),
        width: 64,
        height: 48,
        display: UserDisplay::Stereo { ipd: 0.064 },
        duration: Duration::from_secs(4),
        target_fps: 10.0,
        max_busy_retries: 60,
        ..LoadConfig::default()
    };
    let reports = nephele_loadgen::run(&config, Arc::new(Live::default())).await.expect("loadgen runs");
    let table = nephele_loadgen::table(&reports);
    assert!(reports[0].error.is_none() && reports[0].frames > 0, "{table}");

    // The room's right eye rode on its left eye's batch; a worker loaded the GI model.
    let (status, farm) = http_request(http, "GET", "/v1/farm", &[], "").await.expect("GET /v1/farm");
    assert_eq!(status, 200, "{farm}");
    let farm: serde_json::Value = serde_json::from_str(&farm).expect("JSON");
    let derived = farm["scheduler"]["stats"]["views_derived"].as_u64().unwrap_or(0);
    assert!(derived >= 1, "no view of the room was paired: {}", farm["scheduler"]["stats"]);
    // The knot's solid matter rode on the room's batches: samples behind it were not lit.
    let (traced, hidden) = (farm["live"]["rays_traced"].as_u64(), farm["live"]["samples_hidden"].as_u64());
    assert!(hidden.is_some_and(|h| h > 0 && Some(h) < traced), "hidden {hidden:?} of {traced:?}: {}", farm["live"]);
    let log = up.log_text();
    assert!(log.contains("room-day.ngi"), "no worker loaded the GI model");
    // A loaded machine sheds batches that waited past their deadline or found a full queue,
    // and a closed session's batches are cancelled (the farm at work, not a defect); any
    // other failure is the GI kernel's.
    let shed = |line: &str| ["DeadlineExpired", "Overloaded", "Cancelled"].iter().any(|code| line.contains(code));
    let failures: Vec<&str> = log
        .lines()
        .filter(|line| (line.contains("BatchFailed") || line.contains("batch failed")) && !shed(line))
        .collect();
    assert!(failures.is_empty(), "a batch failed:\n{}", failures.join("\n"));
    up.interrupt(Duration::from_secs(20));
}
