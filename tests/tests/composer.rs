//! The `nephele composer` process: a WebRTC client in this process negotiates with it over
//! HTTP on loopback, receives decodable H.264, gets clear errors for bad offers, and the
//! process stops cleanly on Ctrl-C (SIGINT).

#![allow(clippy::unwrap_used)] // a test may unwrap

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use nephele_tests::nephele_bin;
use nephele_tests::viewer::{Client, ClientOptions, http_request};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn composer_process_streams_to_a_client_and_stops_on_ctrl_c() {
    let mut child = Command::new(nephele_bin())
        .args([
            "--quiet",
            "composer",
            "--source",
            "test-pattern",
            "--http",
            "127.0.0.1:0",
            "--results",
            "127.0.0.1:0",
            "--view",
            "128x96",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting nephele composer");
    let stdout = child.stdout.take().expect("piped stdout");
    let mut lines = BufReader::new(stdout).lines();
    let banner = lines.next().expect("a banner line").expect("readable stdout");
    // "composer: signalling on http://ADDR/v1/sessions, worker results on ADDR"
    let http: std::net::SocketAddr = banner
        .split("http://")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|a| a.parse().ok())
        .unwrap_or_else(|| panic!("no address in '{banner}'"));

    // Standalone (no master): alive and ready.
    assert_eq!(http_request(http, "GET", "/livez", &[], "").await.unwrap().0, 200);
    let (status, body) = http_request(http, "GET", "/readyz", &[], "").await.unwrap();
    assert_eq!(status, 200, "{body}");
    assert!(body.contains("\"ready\":true"), "{body}");

    let (status, body) = http_request(http, "POST", "/v1/sessions", &[], r#"{"sdp":"v=1 nonsense"}"#).await.unwrap();
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("malformed SDP offer"), "{body}");

    let mut client = Client::connect(http, ClientOptions::default()).await.unwrap();
    let picture = client.next_picture(Duration::from_secs(15), |_| true).await.unwrap();
    assert!(
        picture.idr && (picture.width, picture.height) == (128, 96),
        "{:?}",
        (picture.idr, picture.width, picture.height)
    );
    let (status, list) = http_request(http, "GET", "/v1/sessions", &[], "").await.unwrap();
    assert_eq!(status, 200);
    assert!(list.contains(&format!("\"session\":{}", client.session)), "{list}");

    let pid = child.id().to_string();
    assert!(Command::new("kill").args(["-INT", &pid]).status().unwrap().success());
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(10), "composer did not stop on SIGINT");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{status:?}");
    client.close().await;
}
