//! `nephele loadgen` (library and command) against the in-process test farm: real WebRTC
//! peers, real H.264, the real master HTTP shell.

use std::sync::Arc;
use std::time::Duration;

use nephele_loadgen::{Live, LoadConfig};
use nephele_tests::farm::{FPS, TestFarm};

fn farm(runtime: &tokio::runtime::Runtime) -> (TestFarm, String) {
    let farm = TestFarm::new(true).expect("test farm");
    let addr = runtime.block_on(farm.serve()).expect("serving the master");
    (farm, format!("http://{addr}/"))
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().expect("tokio runtime")
}

#[test]
fn two_users_stream_and_report_frame_rate_and_pose_to_frame_latency() {
    let rt = runtime();
    let (farm, url) = farm(&rt);
    farm.refuse_next(1);
    let config = LoadConfig {
        url,
        users: 2,
        duration: Duration::from_secs(2),
        width: 160,
        height: 120,
        ..LoadConfig::default()
    };
    let live = Arc::new(Live::default());
    let reports = rt.block_on(nephele_loadgen::run(&config, Arc::clone(&live))).expect("loadgen runs");
    let table = nephele_loadgen::table(&reports);
    println!("{table}");
    assert_eq!(reports.len(), 2);
    let offers = farm.offers();
    assert_eq!(offers.len(), 2, "{table}");
    for r in &reports {
        assert_eq!(r.error, None, "{table}");
        let id = r.session_id.as_deref().expect("a session");
        assert!(offers.iter().any(|o| o.session_id == id));
        // 2 s of poses every 20 ms; the farm saw them all as well-formed poses.
        assert!((70..=110).contains(&r.poses_sent), "{table}");
        assert!(r.frames >= 20 && r.idr_frames >= 1, "{table}");
        assert!(r.fps > 0.6 * f64::from(FPS) && r.fps < 1.5 * f64::from(FPS), "{table}");
        assert_eq!((r.lost_packets, r.damaged_frames), (0, 0), "{table}");
        // Every frame at the asked size (loopback: the resolution never falls).
        assert_eq!(r.frames_by_size, [("160x120".to_string(), r.frames)].into(), "{table}");
        assert!(r.rtt_ms.count >= 1 && r.pose_to_frame_ms.count >= 20, "{table}");
        let p50 = r.pose_to_frame_ms.p50.expect("latency");
        assert!(p50 > 0.0 && p50 < 500.0, "{table}");
    }
    // One user met the busy farm first and retried.
    assert_eq!(farm.refused(), 1);
    assert_eq!(reports.iter().map(|r| r.busy_retries).sum::<u32>(), 1, "{table}");
    // Every session was closed with DELETE.
    let closed = farm.closed();
    assert!(reports.iter().all(|r| r.session_id.as_ref().is_some_and(|id| closed.contains(id))), "{closed:?}");
    assert!(live.frames.load(std::sync::atomic::Ordering::Relaxed) >= 40);
}

/// A user whose session the farm ends mid-run (as a composer restart does) connects again,
/// as the browser client does, and streams on: two sessions, one reconnection, frames from
/// both, both closed with `DELETE`.
#[test]
fn a_user_whose_session_is_lost_connects_again_and_streams_on() {
    let rt = runtime();
    let (farm, url) = farm(&rt);
    let config = LoadConfig {
        url,
        users: 1,
        duration: Duration::from_secs(4),
        width: 160,
        height: 120,
        ..LoadConfig::default()
    };
    let live = Arc::new(Live::default());
    let run = rt.spawn({
        let live = Arc::clone(&live);
        async move { nephele_loadgen::run(&config, live).await }
    });
    // Once the first session streams, the farm drops it.
    let started = std::time::Instant::now();
    while live.frames.load(std::sync::atomic::Ordering::Relaxed) < 10 {
        assert!(started.elapsed() < Duration::from_secs(20), "no frames from the first session");
        std::thread::sleep(Duration::from_millis(20));
    }
    let frames_before = live.frames.load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(rt.block_on(farm.drop_sessions()), 1);
    let reports = rt.block_on(run).expect("the loadgen task").expect("loadgen runs");
    let table = nephele_loadgen::table(&reports);
    println!("{table}");
    let r = &reports[0];
    assert_eq!(r.error, None, "{table}");
    assert_eq!(r.reconnects, 1, "{table}");
    let offers = farm.offers();
    assert_eq!(offers.len(), 2, "{table}");
    // The second session is the one reported, it streamed too, and both were closed.
    assert_eq!(r.session_id.as_deref(), Some(offers[1].session_id.as_str()), "{table}");
    assert!(farm.frames_sent(&offers[1].session_id) > 0, "{table}");
    assert!(r.frames > frames_before + 5, "{frames_before} frames before the drop; {table}");
    let closed = farm.closed();
    assert!(offers.iter().all(|o| closed.contains(&o.session_id)), "{closed:?}");
}

#[test]
fn the_command_prints_a_table_and_writes_json() {
    let rt = runtime();
    let (_farm, url) = farm(&rt);
    let dir = tempfile::tempdir().expect("temp dir");
    let json = dir.path().join("loadgen.json");
    let json_arg = json.to_str().expect("utf-8 path");
    let out = nephele_tests::nephele_ok(&[
        "loadgen",
        "--url",
        &url,
        "--users",
        "1",
        "--seconds",
        "1",
        "--size",
        "160x120",
        "--json",
        json_arg,
    ]);
    assert!(out.contains("1 of 1 users streamed"), "{out}");
    let reports: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json written")).expect("valid JSON");
    assert!(reports[0]["frames"].as_u64().is_some_and(|n| n > 5), "{reports}");
    // A master that is not there is a clear failure.
    let err = nephele_tests::nephele_err(&["loadgen", "--url", "http://127.0.0.1:9/", "--seconds", "1"]);
    assert!(err.contains("no user could stream"), "{err}");
    let err = nephele_tests::nephele_err(&["loadgen", "--url", "ftp://x", "--seconds", "1"]);
    assert!(err.contains("only http://"), "{err}");
}

/// HTTPS (issue 15): the master's router behind the TLS listener with a self-signed
/// certificate; `nephele loadgen` refuses it until told to trust that certificate, then
/// streams through it.
#[test]
fn loadgen_streams_from_an_https_master_that_it_trusts() {
    let rt = runtime();
    let farm = TestFarm::new(true).expect("test farm");
    let dir = tempfile::tempdir().expect("temp dir");
    let names = ["localhost".to_string(), "127.0.0.1".to_string()];
    let (tls, made) = nephele_master::tls::ServerTls::self_signed(dir.path(), &names).expect("certificate");
    assert!(made);
    let cert = tls.cert_path.to_str().expect("utf-8 path").to_string();
    let addr = rt.block_on(farm.serve_tls(tls)).expect("serving the master over https");
    let url = format!("https://127.0.0.1:{}/", addr.port());

    // The certificate file holds the one certificate clients are told to trust.
    let certs = nephele_loadgen::http::read_certificates(std::path::Path::new(&cert)).expect("pem");
    assert_eq!(certs.len(), 1);

    // Not trusted: no user can stream, and the reason names the certificate.
    let err = nephele_tests::nephele_err(&["loadgen", "--url", &url, "--seconds", "1", "--size", "160x120"]);
    assert!(err.contains("no user could stream"), "{err}");
    assert!(err.to_lowercase().contains("certificate") || err.contains("UnknownIssuer"), "{err}");

    // Trusted: streams.
    one_user_streams(&url, &["--tls-ca", &cert]);
}

/// `nephele loadgen` with one small user for a second against `url` streams.
fn one_user_streams(url: &str, extra: &[&str]) {
    let mut args = vec!["loadgen", "--url", url, "--users", "1", "--seconds", "1", "--size", "160x120"];
    args.extend_from_slice(extra);
    let out = nephele_tests::nephele_ok(&args);
    assert!(out.contains("1 of 1 users streamed"), "{out}");
}

/// Viewer access (issue 15): a master with a viewer key refuses a user without an
/// invitation (401, saying so); `nephele invite` makes a link from the same key file, and
/// loadgen given that link streams.
#[test]
fn loadgen_follows_an_invitation_link_and_is_refused_without_one() {
    let rt = runtime();
    let farm = TestFarm::new(true).expect("test farm");
    let dir = tempfile::tempdir().expect("temp dir");
    let key_file = dir.path().join("viewer.key");
    let out = nephele_tests::nephele_ok(&["secret", "--out", key_file.to_str().expect("utf-8 path")]);
    assert!(out.contains("secret written"), "{out}");
    let text = std::fs::read_to_string(&key_file).expect("key file");
    let key = nephele_master::access::ViewerKey::new(text.trim().as_bytes()).expect("viewer key");
    let access = nephele_master::http::AccessPolicy { viewer_key: Some(key), ..Default::default() };
    let addr = rt.block_on(farm.serve_configured(None, access)).expect("serving the master");
    let base = format!("http://{addr}/");

    let link = nephele_tests::nephele_ok(&[
        "invite",
        "--scene",
        "default",
        "--hours",
        "1",
        "--url",
        &base,
        "--viewer-key-file",
        key_file.to_str().expect("utf-8 path"),
    ]);
    let link = link.trim();
    assert!(link.starts_with(&format!("{base}?scene=default&invite=v1.default.")), "{link}");

    let err = nephele_tests::nephele_err(&["loadgen", "--url", &base, "--seconds", "1", "--size", "160x120"]);
    assert!(err.contains("401") && err.contains("invitation"), "{err}");
    one_user_streams(link, &[]);
}

/// The HTTPS listener (issue 15) keeps serving while one client connects and says nothing
/// (each handshake runs on its own task with a deadline) and another sends garbage.
#[test]
fn the_https_listener_serves_others_while_a_client_stalls_or_sends_garbage() {
    use std::io::Write;
    let rt = runtime();
    let farm = TestFarm::new(false).expect("test farm");
    let dir = tempfile::tempdir().expect("temp dir");
    let (tls, _) = nephele_master::tls::ServerTls::self_signed(dir.path(), &["127.0.0.1".to_string()]).expect("cert");
    nephele_loadgen::http::trust_certificates(&tls.cert_path).expect("trusted in this process");
    let addr = rt.block_on(farm.serve_tls(tls)).expect("serving the master over https");
    let _silent = std::net::TcpStream::connect(addr).expect("a silent client");
    let mut garbage = std::net::TcpStream::connect(addr).expect("a garbage client");
    let mut rng = 0x2545_f491_4f6c_dd1d_u64;
    let noise: Vec<u8> = (0..8192)
        .map(|_| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng as u8
        })
        .collect();
    // A TLS record header claiming a huge handshake, then noise.
    let _ = garbage.write_all(&[0x16, 0x03, 0x01, 0xff, 0xff]);
    let _ = garbage.write_all(&noise);
    for _ in 0..3 {
        let url = format!("https://127.0.0.1:{}/livez", addr.port());
        let r = nephele_loadgen::http::request_blocking(&url, "GET", &[], "", std::time::Duration::from_secs(5))
            .expect("an answer while the others hang");
        assert_eq!((r.status, r.body.as_str()), (200, "ok"));
    }
}

/// loadgen reads the picture size from the sequence parameter sets of the composer's own
/// encoder (OpenH264), at the sizes the composer codes when its resolution falls (cropped
/// ones included: 180 rows are 12 macroblocks less 12 rows).
#[test]
fn loadgen_reads_the_picture_size_of_the_composers_stream() {
    use nephele_composer::encode::{EncoderSettings, H264Encoder};
    use nephele_composer::yuv::Yuv420;
    for (w, h) in [(640, 480), (320, 240), (1280, 720), (640, 360), (320, 180), (480, 270), (176, 144)] {
        let mut encoder = H264Encoder::new(EncoderSettings::low_latency(w, h)).expect("encoder");
        let grey = vec![[0.5f32; 3]; (w * h) as usize];
        let picture = Yuv420::from_linear_rgb(w, h, &grey).expect("picture");
        let frame = encoder.encode(&picture, 0).expect("encoded");
        // Annex B: NAL units after 00 00 01 start codes, each sent as its own RTP payload.
        let mut sizes = Vec::new();
        let data = &frame.data;
        let starts: Vec<usize> = (0..data.len().saturating_sub(3))
            .filter(|&i| data[i] == 0 && data[i + 1] == 0 && data[i + 2] == 1)
            .map(|i| i + 3)
            .collect();
        for (k, &start) in starts.iter().enumerate() {
            let end = starts.get(k + 1).map_or(data.len(), |&next| next - 3);
            let nal = &data[start..end];
            let nal = nal.strip_suffix(&[0]).unwrap_or(nal); // a 4-byte start code's leading zero
            if let Some(size) = nephele_loadgen::h264::picture_size_in_payload(nal) {
                sizes.push(size);
            }
        }
        assert_eq!(sizes, vec![(w, h)], "{w}x{h}");
    }
}
