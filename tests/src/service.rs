//! The whole service as a user starts it: `nephele up` (master, composer and workers as
//! child processes on loopback), for the cross-process and browser end-to-end tests.

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use crate::nephele_bin;

/// A running `nephele up`. Dropping it sends SIGINT and reaps it (and kills it if it hangs).
#[derive(Debug)]
pub struct UpService {
    child: Option<Child>,
    /// The master's HTTP address (the client page, `/v1/sessions`, `/v1/farm`).
    pub http: SocketAddr,
    /// The URL line `nephele up` printed once the farm was whole.
    pub url_line: String,
    /// The composer's HTTP address (`GET /v1/sessions`: counters and latency), as printed.
    pub composer_http: Option<SocketAddr>,
    /// Everything `nephele up` printed on stdout up to and including the URL line.
    pub startup: Vec<String>,
    /// The asset folder [`UpService::start`] made (removed when the service is dropped).
    assets: Option<tempfile::TempDir>,
    /// Where the processes' logs go (stderr of `nephele up` and its children, info level);
    /// its tail is printed when a test fails while the service runs.
    log: tempfile::NamedTempFile,
}

/// A loopback port that was free a moment ago.
pub fn free_port() -> SocketAddr {
    TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).expect("a free port")
}

/// Child processes of `pid` (from `pgrep -P`).
pub fn children_of(pid: u32) -> Vec<u32> {
    let out = Command::new("pgrep").args(["-P", &pid.to_string()]).output().expect("pgrep");
    String::from_utf8_lossy(&out.stdout).lines().filter_map(|l| l.trim().parse().ok()).collect()
}

/// The command line of `pid`, arguments separated by spaces (empty once it is gone).
pub fn command_line(pid: u32) -> String {
    std::fs::read(format!("/proc/{pid}/cmdline"))
        .map(|raw| {
            raw.split(|&b| b == 0).map(|a| String::from_utf8_lossy(a).into_owned()).collect::<Vec<_>>().join(" ")
        })
        .unwrap_or_default()
}

/// Live child processes of `pid` whose second argument (the subcommand) is `role`
/// (`worker`, `composer`, `master`).
pub fn children_in_role(pid: u32, role: &str) -> Vec<u32> {
    children_of(pid).into_iter().filter(|&c| alive(c) && command_line(c).split(' ').nth(1) == Some(role)).collect()
}

/// Whether `pid` is a live (not zombie) process.
pub fn alive(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|s| !s.contains(") Z "))
}

impl UpService {
    /// Starts `nephele up --workers N --spp 1 --bake off` (objects path traced, nothing
    /// baked) on a free HTTP port and waits (up to 45 s) for the URL it prints once the
    /// composer and every worker have joined the master.
    pub fn start(workers: usize) -> UpService {
        // An empty asset folder of its own: nothing of the user's cache is read or written.
        let assets = tempfile::tempdir().expect("an asset folder");
        let dir = assets.path().to_str().expect("utf-8 temporary path").to_owned();
        let mut service = UpService::start_with(workers, &["--bake", "off", "--assets", &dir], Duration::from_secs(45));
        service.assets = Some(assets);
        service
    }

    /// Starts `nephele up --workers N --spp 1 EXTRA...` on a free HTTP port and waits up to
    /// `limit` for the URL it prints once the farm is whole (a first start that bakes takes
    /// longer).
    pub fn start_with(workers: usize, extra: &[&str], limit: Duration) -> UpService {
        UpService::start_in(&[], free_port(), workers, extra, limit)
    }

    /// [`Self::start_with`] on a given HTTP address, the command run through `prefix`
    /// (`ip netns exec NAME`: a service in a network namespace of its own).
    pub fn start_in(prefix: &[&str], http: SocketAddr, workers: usize, extra: &[&str], limit: Duration) -> UpService {
        let log = tempfile::Builder::new().prefix("nephele-up-").suffix(".log").tempfile().expect("a log file");
        let ready_secs = (limit.as_secs() + 5).to_string();
        let bin = nephele_bin();
        let mut command = match prefix.split_first() {
            Some((program, args)) => {
                let mut c = Command::new(program);
                c.args(args).arg(&bin);
                c
            }
            None => Command::new(&bin),
        };
        let mut child = command
            .args([
                "--quiet",
                "up",
                "--http",
                &http.to_string(),
                "--workers",
                &workers.to_string(),
                "--spp",
                "1",
                "--ready-secs",
                &ready_secs,
                // The tests open users at rates their path-traced test farms cannot all carry;
                // admission by starvation alone, as before the look-ahead became the default.
                "--admit-up-to",
                "off",
            ])
            .args(extra)
            .env("NEPHELE_LOG", std::env::var("NEPHELE_LOG").unwrap_or_else(|_| "info".into()))
            .env("NO_COLOR", "1")
            .stdout(Stdio::piped())
            .stderr(log.reopen().expect("reopening the log file"))
            .spawn()
            .expect("starting nephele up");
        let stdout = child.stdout.take().expect("piped stdout");
        let (line_tx, line_rx) = std::sync::mpsc::channel();
        // Drain every line (the children share the pipe), passing on those up to the URL.
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = line_tx.send(line);
            }
        });
        let mut service = UpService {
            child: Some(child),
            http,
            url_line: String::new(),
            composer_http: None,
            startup: Vec::new(),
            assets: None,
            log,
        };
        let deadline = Instant::now() + limit;
        while service.url_line.is_empty() {
            let left = deadline.saturating_duration_since(Instant::now());
            let line = match line_rx.recv_timeout(left) {
                Ok(line) => line,
                Err(e) => {
                    service.print_log_tail(40);
                    panic!(
                        "nephele up did not print the URL once the farm was whole: {e}; it printed {:#?}",
                        service.startup
                    )
                }
            };
            if line.contains("open http://") {
                service.url_line = line.clone();
            } else if line.starts_with("composer counters") {
                // "composer counters and latency: http://ADDR/v1/sessions"
                service.composer_http =
                    line.split("http://").nth(1).and_then(|rest| rest.split('/').next()).and_then(|a| a.parse().ok());
            }
            service.startup.push(line);
        }
        service
    }

    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// Sends SIGINT (Ctrl-C) and waits up to `limit` for the exit status.
    pub fn interrupt(&mut self, limit: Duration) -> Option<ExitStatus> {
        let mut child = self.child.take()?;
        let _ = Command::new("kill").args(["-INT", &child.id().to_string()]).status();
        let deadline = Instant::now() + limit;
        loop {
            if let Ok(Some(status)) = child.try_wait() {
                return Some(status);
            }
            if Instant::now() >= deadline {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for UpService {
    fn drop(&mut self) {
        if std::thread::panicking() {
            // What the composer and the master saw, while they still run.
            match self.composer_sessions() {
                Ok(v) => eprintln!("composer sessions: {v}"),
                Err(e) => eprintln!("composer sessions: {e}"),
            }
            match get_json(self.http, "/v1/farm") {
                Ok(v) => eprintln!("master farm state: {v}"),
                Err(e) => eprintln!("master farm state: {e}"),
            }
        }
        self.interrupt(Duration::from_secs(15));
        if std::thread::panicking() {
            self.print_log_tail(80);
        }
    }
}

/// A blocking `GET` of a JSON endpoint on loopback.
pub fn get_json(addr: SocketAddr, path: &str) -> Result<serde_json::Value, String> {
    let url = format!("http://{addr}{path}");
    let r = nephele_loadgen::http::request_blocking(&url, "GET", &[], "", Duration::from_secs(5))
        .map_err(|e| e.to_string())?;
    if r.status != 200 {
        return Err(format!("{path}: status {}", r.status));
    }
    serde_json::from_str(&r.body).map_err(|e| format!("{path}: {e}"))
}

impl UpService {
    /// The composer's per-session counters, encoder statistics and latency
    /// (`GET /v1/sessions` on the composer).
    pub fn composer_sessions(&self) -> Result<serde_json::Value, String> {
        let addr = self.composer_http.ok_or("nephele up did not print the composer's address")?;
        get_json(addr, "/v1/sessions")
    }

    /// Prints the last `lines` lines of the service's log to stderr (the test's output).
    /// The service's log so far (stderr of `nephele up` and its children).
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(self.log.path()).unwrap_or_default()
    }

    pub fn print_log_tail(&self, lines: usize) {
        let text = std::fs::read_to_string(self.log.path()).unwrap_or_default();
        let all: Vec<&str> = text.lines().collect();
        eprintln!("--- last {} of {} lines of the nephele up log ---", lines.min(all.len()), all.len());
        for line in &all[all.len().saturating_sub(lines)..] {
            eprintln!("{line}");
        }
        eprintln!("--- end of the nephele up log ---");
    }
}
