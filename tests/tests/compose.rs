//! The container cluster of `deploy/`: images built here from nothing (the base image from
//! the binary's own libraries by `deploy/base/build-base.sh`, then `deploy/Dockerfile`),
//! `deploy/docker-compose.yml` started with a quick bake, two `nephele loadgen` users
//! streaming from the host through WebRTC while one worker container's process is killed
//! (its restart policy brings it back), another worker is cut off the network, and the
//! workers are scaled up; the frames keep coming, none damaged, the master's metrics count
//! the re-issued batches and the new worker renders.
//!
//! Skipped, with a message, where no Docker engine or Compose tool runs.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use nephele_tests::nephele_bin;
use nephele_tests::service::{free_port, get_json};

fn run(command: &mut Command) -> Output {
    command.output().unwrap_or_else(|e| panic!("running {command:?}: {e}"))
}

fn run_ok(command: &mut Command) -> String {
    let out = run(command);
    assert!(
        out.status.success(),
        "{command:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn docker(args: &[&str]) -> Command {
    let mut command = Command::new("docker");
    command.args(args);
    command
}

/// `docker compose` (v2) where it exists, else `docker-compose` (v1); `None` without either or
/// without a running engine.
fn compose_tool() -> Option<Vec<String>> {
    let works = |program: &str, args: &[&str]| {
        Command::new(program).args(args).stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success())
    };
    if !works("docker", &["info"]) {
        return None;
    }
    if works("docker", &["compose", "version"]) {
        return Some(vec!["docker".into(), "compose".into()]);
    }
    works("docker-compose", &["version"]).then(|| vec!["docker-compose".into()])
}

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("the workspace root").to_path_buf()
}

/// A started compose project; taken down (volumes and images too) when dropped.
struct Cluster {
    tool: Vec<String>,
    project: String,
    env: BTreeMap<&'static str, String>,
    images: Vec<String>,
    http: std::net::SocketAddr,
    /// `Authorization` value with the operators' token the cluster wrote (read once it runs).
    operator: String,
}

impl Cluster {
    fn compose(&self, args: &[&str]) -> Command {
        let mut command = Command::new(&self.tool[0]);
        command.args(&self.tool[1..]);
        let file = repo_root().join("deploy/docker-compose.yml");
        command.arg("-p").arg(&self.project).arg("-f").arg(file).args(args);
        command.envs(self.env.iter().map(|(k, v)| (*k, v.as_str())));
        command
    }

    fn container(&self, service: &str, index: u32) -> String {
        // Compose v1 joins with '_', v2 with '-'; ask for the id instead of guessing.
        let ids = run_ok(&mut self.compose(&["ps", "-q", service]));
        let ids: Vec<&str> = ids.lines().filter(|l| !l.is_empty()).collect();
        for id in &ids {
            let labels = run_ok(&mut docker(&[
                "inspect",
                "-f",
                "{{index .Config.Labels \"com.docker.compose.container-number\"}} {{.Name}}",
                id,
            ]));
            let mut parts = labels.split_whitespace();
            if parts.next() == Some(&index.to_string()) {
                return parts.next().unwrap_or(id).trim_start_matches('/').to_string();
            }
        }
        panic!("no container {index} of {service} among {ids:?}");
    }

    fn inspect(&self, container: &str, format: &str) -> String {
        run_ok(&mut docker(&["inspect", "-f", format, container])).trim().to_string()
    }

    fn logs(&self) -> String {
        let out = run(&mut self.compose(&["logs", "--no-color", "--tail", "60"]));
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// A GET of the master's API as an operator (with the token).
    fn operator_get(&self, path: &str) -> nephele_loadgen::http::Response {
        let url = format!("http://{}{path}", self.http);
        nephele_loadgen::http::request_blocking(
            &url,
            "GET",
            &[("Authorization", &self.operator)],
            "",
            Duration::from_secs(5),
        )
        .unwrap_or_else(|e| panic!("GET {path}: {e}\n{}", self.logs()))
    }

    fn farm(&self) -> serde_json::Value {
        let response = self.operator_get("/v1/farm");
        serde_json::from_str(&response.body).unwrap_or_else(|e| panic!("GET /v1/farm: {e}: {}", response.body))
    }

    /// The operators' token the one-shot job wrote into the master's secrets volume: the file
    /// belongs to the image's user, so it comes out through `docker cp`'s tar stream (one
    /// 512-byte header, then the bytes).
    fn read_operator_token(&mut self, master: &str) {
        let tar = run(&mut docker(&["cp", &format!("{master}:/var/lib/nephele/secrets/operator"), "-"]));
        assert!(tar.status.success(), "docker cp of the operators' token: {}", String::from_utf8_lossy(&tar.stderr));
        let header = tar.stdout.get(..512).expect("a tar header");
        let size_field = String::from_utf8_lossy(&header[124..136]);
        let size =
            usize::from_str_radix(size_field.trim_matches(|c: char| c == '\0' || c == ' '), 8).expect("tar size");
        let token = String::from_utf8_lossy(&tar.stdout[512..512 + size]).trim().to_string();
        assert!(token.len() >= 16, "the operators' token is {} bytes", token.len());
        self.operator = format!("Bearer {token}");
    }

    /// Names of the workers in the master's farm.
    fn worker_names(&self) -> Vec<String> {
        let farm = self.farm();
        let workers = farm["workers"].as_array().cloned().unwrap_or_default();
        workers.iter().filter_map(|w| w["name"].as_str().map(str::to_string)).collect()
    }

    fn metric(&self, series: &str) -> f64 {
        let text = self.operator_get("/metrics").body;
        nephele_tests::metric_value(&text, series).unwrap_or_else(|| panic!("{series} not in the metrics:\n{text}"))
    }

    fn wait_for(&self, what: &str, limit: Duration, mut ok: impl FnMut() -> bool) {
        let start = Instant::now();
        while !ok() {
            assert!(start.elapsed() < limit, "{what}: not within {limit:?}\n{}", self.logs());
            std::thread::sleep(Duration::from_millis(500));
        }
        println!("{what}: after {:.1} s", start.elapsed().as_secs_f64());
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("cluster logs:\n{}", self.logs());
        }
        let _ = run(&mut self.compose(&["down", "-v", "--remove-orphans", "-t", "5"]));
        for image in &self.images {
            let _ = run(&mut docker(&["rmi", "-f", image]));
        }
    }
}

/// The image's build context: the (stripped) binary, the Dockerfile and the data folder.
fn build_context(binary: &Path) -> tempfile::TempDir {
    let context = tempfile::tempdir().expect("a build context folder");
    let target = context.path().join("nephele");
    // Debug information is most of a test build's binary; the image does not need it.
    let stripped = Command::new("strip").arg("-o").arg(&target).arg(binary).status().is_ok_and(|s| s.success());
    if !stripped {
        std::fs::copy(binary, &target).expect("copying the binary");
    }
    let root = repo_root();
    std::fs::copy(root.join("deploy/Dockerfile"), context.path().join("Dockerfile")).expect("Dockerfile");
    // The data folder's tree (assets/, secrets/), as the Dockerfile copies it.
    let image_data = root.join("deploy/image/var-lib-nephele");
    for folder in std::fs::read_dir(&image_data).expect("deploy/image/var-lib-nephele") {
        let folder = folder.expect("entry").path();
        let name = folder.file_name().expect("a name").to_owned();
        let into = context.path().join("deploy/image/var-lib-nephele").join(name);
        std::fs::create_dir_all(&into).expect("data folder");
        for file in std::fs::read_dir(&folder).expect("data folder") {
            let file = file.expect("entry").path();
            std::fs::copy(&file, into.join(file.file_name().expect("a name"))).expect("data file");
        }
    }
    context
}

/// Users that stream until interrupted (SIGINT), then write their reports to `json`. A user
/// the master's admission control holds back (another user starved on a loaded machine)
/// keeps asking for up to two minutes: the test checks that every user streams, not how soon.
fn loadgen(http: std::net::SocketAddr, users: usize, json: &Path) -> Child {
    Command::new(nephele_bin())
        .args(["--quiet", "loadgen", "--url", &format!("http://{http}/"), "--users", &users.to_string()])
        .args(["--size", "160x120", "--seconds", "900", "--stagger-ms", "500", "--busy-retries", "120", "--json"])
        .arg(json)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starting nephele loadgen")
}

#[test]
fn the_compose_cluster_streams_through_a_killed_worker_a_cut_off_worker_and_a_scale_up() {
    let Some(tool) = compose_tool() else {
        eprintln!("SKIPPED: no Docker engine with Compose here (docker info / docker compose version failed)");
        return;
    };
    let tag = std::process::id().to_string();
    let (base, image) = (format!("nephele-test-base:{tag}"), format!("nephele-test:{tag}"));
    let context = build_context(&nephele_bin());
    let script = repo_root().join("deploy/base/build-base.sh");
    run_ok(Command::new("bash").arg(&script).arg(context.path().join("nephele")).arg(&base));
    let mut build = docker(&["build", "-q", "--build-arg"]);
    build.arg(format!("BASE={base}")).args(["--build-arg", "NEPHELE_BINARY=nephele", "-t", &image]);
    run_ok(build.arg(context.path()));

    let http = free_port();
    // UDP ports outside Linux's ephemeral range (32768-60999), apart for concurrent runs.
    let udp = 20000 + (std::process::id() % 500) * 20;
    let env = BTreeMap::from([
        ("NEPHELE_IMAGE", image.clone()),
        ("NEPHELE_HTTP_PORT", http.port().to_string()),
        ("NEPHELE_BAKE", "quick".to_string()),
        ("NEPHELE_UDP_PORTS", format!("{udp}-{}", udp + 19)),
    ]);
    let mut cluster = Cluster {
        tool,
        project: format!("nephele-test-{tag}").replace(':', "-"),
        env,
        images: vec![image, base],
        http,
        operator: String::new(),
    };
    run_ok(&mut cluster.compose(&["up", "-d"]));
    // The operators' endpoints are closed to requests without the cluster's token.
    let master = cluster.container("master", 1);
    cluster.read_operator_token(&master);
    let url = format!("http://{http}/metrics");
    cluster.wait_for("the master answers /metrics without the token with 401", Duration::from_secs(120), || {
        nephele_loadgen::http::request_blocking(&url, "GET", &[], "", Duration::from_secs(5))
            .is_ok_and(|r| r.status == 401)
    });
    cluster.wait_for("the master is ready (a composer and a worker joined)", Duration::from_secs(900), || {
        get_json(http, "/readyz").is_ok_and(|r| r["ready"] == true)
    });
    cluster.wait_for("three workers joined", Duration::from_secs(120), || cluster.worker_names().len() == 3);
    // The images' health checks pass: each role's /readyz through `nephele probe`.
    cluster.wait_for("the master container is healthy", Duration::from_secs(60), || {
        cluster.inspect(&master, "{{.State.Health.Status}}") == "healthy"
    });
    assert_eq!(cluster.inspect(&master, "{{.Config.User}}"), "10001:10001", "the image runs unprivileged");

    let report = tempfile::NamedTempFile::new().expect("report file");
    let mut users = loadgen(http, 2, report.path());
    let frames_completed = || cluster.metric("nephele_master_frames_completed_total");
    cluster.wait_for("frames flow", Duration::from_secs(60), || frames_completed() > 20.0);

    // 1. A worker's process dies (SIGKILL from outside, as a crash): Docker's restart policy
    // starts it again and it rejoins; its batches were re-issued.
    let worker1 = cluster.container("worker", 1);
    let worker1_name = format!("worker-{}-1", cluster.inspect(&worker1, "{{.Config.Hostname}}"));
    assert!(cluster.worker_names().contains(&worker1_name), "{worker1_name} is not in the farm");
    let pid = cluster.inspect(&worker1, "{{.State.Pid}}");
    let killed_at = Instant::now();
    let killed = Command::new("kill").args(["-KILL", &pid]).status().is_ok_and(|s| s.success());
    if !killed {
        // Not allowed to signal the container's process (not root): kill it through Docker,
        // which counts as a manual stop, and start it again by hand.
        run_ok(&mut docker(&["kill", &worker1]));
        run_ok(&mut docker(&["start", &worker1]));
    }
    let before = frames_completed();
    cluster.wait_for("the killed worker is back in the farm", Duration::from_secs(120), || {
        let restarts: u32 = cluster.inspect(&worker1, "{{.RestartCount}}").parse().unwrap_or(0);
        // The same name (same host name, pid 1) on a link younger than the kill.
        let rejoined = cluster.farm()["workers"].as_array().is_some_and(|workers| {
            workers.iter().any(|w| {
                w["name"] == worker1_name.as_str()
                    && w["connected_s"].as_f64().is_some_and(|s| s < killed_at.elapsed().as_secs_f64())
            })
        });
        (restarts >= 1 || !killed) && rejoined
    });
    cluster.wait_for("frames flow after the kill", Duration::from_secs(60), || frames_completed() > before + 20.0);

    // 2. Another worker is cut off the network: its link goes silent, the master drops it
    // when its heartbeats stop and re-issues its batches.
    let worker2 = cluster.container("worker", 2);
    let network = cluster.inspect(&worker2, "{{range $name, $_ := .NetworkSettings.Networks}}{{$name}}{{end}}");
    let lost_before = cluster.metric("nephele_master_workers_lost_total");
    run_ok(&mut docker(&["network", "disconnect", &network, &worker2]));
    cluster.wait_for("the master drops the silent worker", Duration::from_secs(60), || {
        cluster.metric("nephele_master_workers_lost_total") > lost_before
    });
    let before = frames_completed();
    cluster.wait_for("frames flow with two workers", Duration::from_secs(60), || frames_completed() > before + 20.0);
    let reissued = cluster.metric("nephele_master_batches_reissued_total");
    assert!(reissued > 0.0, "no batch re-issued after a killed and a cut-off worker");

    // 3. Scale up: a fourth worker joins and the master gives it work.
    let names_before = cluster.worker_names();
    run_ok(&mut cluster.compose(&["up", "-d", "--no-recreate", "--scale", "worker=4"]));
    let worker4 = cluster.container("worker", 4);
    let host = cluster.inspect(&worker4, "{{.Config.Hostname}}");
    let new_name = format!("worker-{host}-1");
    cluster.wait_for("the new worker renders", Duration::from_secs(120), || {
        let farm = cluster.farm();
        let ids: Vec<(u64, String)> = farm["workers"]
            .as_array()
            .map(|w| w.iter().filter_map(|w| Some((w["id"].as_u64()?, w["name"].as_str()?.to_string()))).collect())
            .unwrap_or_default();
        let Some((id, _)) = ids.iter().find(|(_, name)| *name == new_name) else { return false };
        let scheduled = farm["scheduler"]["workers"].as_array().cloned().unwrap_or_default();
        scheduled.iter().any(|w| w["id"].as_u64() == Some(*id) && w["batches_done"].as_u64().is_some_and(|n| n > 0))
    });
    assert!(!names_before.contains(&new_name), "{new_name} was there before the scale-up: {names_before:?}");

    // Both users stream before the end: admission control may hold one back while the other
    // is starved on a loaded machine (loadgen keeps asking for up to two minutes), and the
    // steps above can all pass within seconds, before it got in.
    cluster.wait_for("both users stream", Duration::from_secs(180), || {
        let sessions = cluster.farm()["scheduler"]["sessions"].as_array().cloned().unwrap_or_default();
        sessions.len() == 2 && sessions.iter().all(|s| s["frames_completed"].as_u64().is_some_and(|n| n > 200))
    });

    // The users streamed to the end; every frame arrived whole.
    let interrupted = Command::new("kill").args(["-INT", &users.id().to_string()]).status();
    assert!(interrupted.is_ok_and(|s| s.success()), "interrupting loadgen");
    let status = users.wait().expect("loadgen");
    let mut stderr = String::new();
    if let Some(mut pipe) = users.stderr.take() {
        let _ = std::io::Read::read_to_string(&mut pipe, &mut stderr);
    }
    assert!(status.success(), "loadgen failed: {stderr}");
    let reports: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.path()).expect("report")).expect("JSON report");
    let reports = reports.as_array().expect("one report per user");
    assert_eq!(reports.len(), 2);
    for r in reports {
        println!(
            "user {}: {} frames, {:.1} fps, damaged {}, unfinished {}",
            r["user"],
            r["frames"],
            r["fps"].as_f64().unwrap_or(0.0),
            r["damaged_frames"],
            r["unfinished_frames"]
        );
        assert!(r["error"].is_null(), "{r}");
        assert!(r["frames"].as_u64().is_some_and(|n| n > 100), "{r}");
        assert_eq!((r["damaged_frames"].as_u64(), r["unfinished_frames"].as_u64()), (Some(0), Some(0)), "{r}");
    }
    println!("batches re-issued: {reissued}");
}
