//! Headless Chromium over W3C WebDriver, for the browser end-to-end tests.
//!
//! [`Browser::start`] runs `chromedriver --port=P` as a child process (killed on drop), opens a
//! WebDriver session with headless Chromium, and offers the few commands the tests need:
//! navigate, run (async) scripts, tabs, the browser console, screenshots. The WebDriver
//! calls are JSON over HTTP on loopback, through the workspace's one HTTP client
//! (`nephele_loadgen::http`, on `ureq`).
//!
//! When a test panics while a [`Browser`] is alive, its drop saves a screenshot of every tab,
//! the console log and chromedriver's log into the test's artifact folder and keeps that
//! folder (the path is printed).
//!
//! Chromium and chromedriver are Debian's `chromium` and `chromium-driver`; `scripts/test`
//! (the README's test command) installs them. `NEPHELE_CHROMIUM` and `NEPHELE_CHROMEDRIVER`
//! override the binaries. A missing one is an error that says so, never a skipped test.

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use thiserror::Error;

/// What to do when Chromium or its driver is missing.
pub const INSTALL_HINT: &str = "run `scripts/test` (the README's test command), which installs Debian's `chromium` and \
     `chromium-driver`, or set NEPHELE_CHROMIUM / NEPHELE_CHROMEDRIVER to their paths";

/// Chromium switches for the tests: headless, no sandbox (containers, root), fake media
/// permission prompts, autoplay, plain IP host candidates instead of mDNS `.local` names
/// (so that a WebRTC peer in the test process can reach the browser without multicast DNS),
/// and no throttling of background tabs (a second tab must not slow the first one's 20 ms
/// pose timer to once a second).
pub const CHROMIUM_ARGS: &[&str] = &[
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--use-fake-ui-for-media-stream",
    "--autoplay-policy=no-user-gesture-required",
    "--disable-features=WebRtcHideLocalIpsWithMdns",
    "--disable-background-timer-throttling",
    "--disable-renderer-backgrounding",
    "--disable-backgrounding-occluded-windows",
    "--no-first-run",
    "--mute-audio",
    "--window-size=1024,768",
];

#[derive(Debug, Error)]
pub enum BrowserError {
    #[error("{what} not found ({detail}): {INSTALL_HINT}")]
    Missing { what: &'static str, detail: String },
    #[error("chromedriver did not start: {0}")]
    DriverStart(String),
    #[error("WebDriver I/O with chromedriver: {0}")]
    Io(#[from] std::io::Error),
    #[error("WebDriver HTTP: {0}")]
    Http(#[from] nephele_loadgen::LoadError),
    #[error("malformed WebDriver response: {0}")]
    Protocol(String),
    #[error("WebDriver {command}: {error}: {message}")]
    Command { command: String, error: String, message: String },
    #[error("timed out after {0:?} waiting for {1}")]
    Timeout(Duration, String),
}

pub type Result<T> = std::result::Result<T, BrowserError>;

/// Finds `name` on `PATH` (or takes `env` as an explicit path).
pub fn find_program(env: &str, name: &'static str) -> Result<PathBuf> {
    if let Some(path) = std::env::var_os(env) {
        let path = PathBuf::from(path);
        return if path.is_file() {
            Ok(path)
        } else {
            Err(BrowserError::Missing { what: name, detail: format!("{env}={} is not a file", path.display()) })
        };
    }
    let paths = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&paths)
        .map(|dir| dir.join(name))
        .find(|candidate| candidate.is_file())
        .ok_or_else(|| BrowserError::Missing { what: name, detail: "not on PATH".into() })
}

/// A console message of the page (Chromium's "browser" log).
#[derive(Debug, Clone, PartialEq)]
pub struct LogEntry {
    /// `SEVERE` for errors (uncaught exceptions, failed loads), `WARNING`, `INFO`, ...
    pub level: String,
    pub message: String,
}

/// How to start the browser.
#[derive(Debug, Clone)]
pub struct BrowserOptions {
    pub chromium: Option<PathBuf>,
    pub chromedriver: Option<PathBuf>,
    /// Extra Chromium switches after [`CHROMIUM_ARGS`].
    pub extra_args: Vec<String>,
    /// Longest wait for one WebDriver command (a script's own timeout is set separately).
    pub command_timeout: Duration,
}

impl Default for BrowserOptions {
    fn default() -> Self {
        BrowserOptions {
            chromium: None,
            chromedriver: None,
            extra_args: Vec::new(),
            command_timeout: Duration::from_secs(60),
        }
    }
}

/// A headless Chromium driven over WebDriver. Dropping it ends the session and kills
/// chromedriver (which takes Chromium with it).
#[derive(Debug)]
pub struct Browser {
    driver: Child,
    addr: SocketAddr,
    session: String,
    timeout: Duration,
    artifacts: Option<tempfile::TempDir>,
    artifacts_path: PathBuf,
}

impl Browser {
    /// Starts chromedriver and a headless Chromium session with the default options.
    pub fn start() -> Result<Browser> {
        Browser::start_with(BrowserOptions::default())
    }

    pub fn start_with(options: BrowserOptions) -> Result<Browser> {
        let chromedriver = match options.chromedriver {
            Some(path) if path.is_file() => path,
            Some(path) => {
                return Err(BrowserError::Missing {
                    what: "chromedriver",
                    detail: format!("{} is not a file", path.display()),
                });
            }
            None => find_program("NEPHELE_CHROMEDRIVER", "chromedriver")?,
        };
        let chromium = match options.chromium {
            Some(path) if path.is_file() => path,
            Some(path) => {
                return Err(BrowserError::Missing {
                    what: "chromium",
                    detail: format!("{} is not a file", path.display()),
                });
            }
            None => find_program("NEPHELE_CHROMIUM", "chromium")?,
        };
        let artifacts = tempfile::Builder::new().prefix("nephele-browser-").tempdir()?;
        let artifacts_path = artifacts.path().to_path_buf();
        let driver_log = std::fs::File::create(artifacts_path.join("chromedriver.log"))?;

        // A free port: bind, read it, release it. Another process could take it in between;
        // chromedriver then exits at once and we say so.
        let port = TcpListener::bind(("127.0.0.1", 0))?.local_addr()?.port();
        let driver = Command::new(&chromedriver)
            .arg(format!("--port={port}"))
            .stdin(Stdio::null())
            .stdout(driver_log.try_clone()?)
            .stderr(driver_log)
            .spawn()
            .map_err(|e| BrowserError::Missing {
                what: "chromedriver",
                detail: format!("{}: {e}", chromedriver.display()),
            })?;
        let mut browser = Browser {
            driver,
            addr: SocketAddr::from(([127, 0, 0, 1], port)),
            session: String::new(),
            timeout: options.command_timeout,
            artifacts: Some(artifacts),
            artifacts_path,
        };
        browser.wait_for_driver(Duration::from_secs(20))?;

        let mut args: Vec<String> = CHROMIUM_ARGS.iter().map(|s| s.to_string()).collect();
        args.extend(options.extra_args);
        let capabilities = json!({
            "capabilities": {
                "alwaysMatch": {
                    "browserName": "chrome",
                    "goog:chromeOptions": { "binary": chromium, "args": args },
                    "goog:loggingPrefs": { "browser": "ALL" },
                    "timeouts": { "script": 30_000, "pageLoad": 30_000 },
                }
            }
        });
        let created = browser.request("POST", "/session", Some(&capabilities))?;
        browser.session = created["sessionId"]
            .as_str()
            .ok_or_else(|| BrowserError::Protocol(format!("no sessionId in {created}")))?
            .to_string();
        Ok(browser)
    }

    fn wait_for_driver(&mut self, limit: Duration) -> Result<()> {
        let start = Instant::now();
        loop {
            if let Some(status) = self.driver.try_wait()? {
                return Err(BrowserError::DriverStart(format!(
                    "chromedriver exited with {status}: {}",
                    self.driver_log()
                )));
            }
            if let Ok(value) = self.request("GET", "/status", None)
                && value["ready"].as_bool() == Some(true)
            {
                return Ok(());
            }
            if start.elapsed() > limit {
                return Err(BrowserError::DriverStart(format!("not ready after {limit:?}: {}", self.driver_log())));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn driver_log(&self) -> String {
        std::fs::read_to_string(self.artifacts_path.join("chromedriver.log")).unwrap_or_default()
    }

    /// The folder where failure artifacts go (kept only when a test fails).
    pub fn artifacts(&self) -> &Path {
        &self.artifacts_path
    }

    fn session_path(&self, tail: &str) -> String {
        format!("/session/{}{tail}", self.session)
    }

    /// One WebDriver command; returns its `value`.
    fn request(&self, method: &str, path: &str, body: Option<&Value>) -> Result<Value> {
        let body = body.map(|b| b.to_string()).unwrap_or_default();
        let url = format!("http://{}{path}", self.addr);
        let answer = nephele_loadgen::http::request_blocking(&url, method, &[], &body, self.timeout)?;
        let (status, response) = (answer.status, answer.body.into_bytes());
        let value: Value = serde_json::from_slice(&response).map_err(|e| {
            BrowserError::Protocol(format!("{method} {path}: {e}: {}", String::from_utf8_lossy(&response)))
        })?;
        let value = value.get("value").cloned().unwrap_or(Value::Null);
        if status != 200 {
            return Err(BrowserError::Command {
                command: format!("{method} {path}"),
                error: value["error"].as_str().unwrap_or("unknown error").to_string(),
                message: value["message"].as_str().unwrap_or("").to_string(),
            });
        }
        Ok(value)
    }

    /// Navigates the current tab and waits for the page to load.
    pub fn goto(&self, url: &str) -> Result<()> {
        self.request("POST", &self.session_path("/url"), Some(&json!({ "url": url })))?;
        Ok(())
    }

    /// Runs `script` (a function body: `return ...;`, `arguments[i]`) in the current tab.
    pub fn execute(&self, script: &str, args: Vec<Value>) -> Result<Value> {
        self.request("POST", &self.session_path("/execute/sync"), Some(&json!({ "script": script, "args": args })))
    }

    /// Runs an asynchronous script: it ends by calling `arguments[arguments.length - 1](result)`.
    pub fn execute_async(&self, script: &str, args: Vec<Value>) -> Result<Value> {
        self.request("POST", &self.session_path("/execute/async"), Some(&json!({ "script": script, "args": args })))
    }

    /// Awaits a JavaScript expression that yields a promise (or a value) and returns its result;
    /// a rejection is an error with its message.
    pub fn eval_promise(&self, expression: &str) -> Result<Value> {
        let script = format!(
            "const done = arguments[arguments.length - 1];\n\
             Promise.resolve().then(async () => ({expression}))\n\
               .then((value) => done({{ ok: value === undefined ? null : value }}), (e) => done({{ err: String(e && e.stack || e) }}));"
        );
        let value = self.execute_async(&script, Vec::new())?;
        if let Some(err) = value.get("err") {
            return Err(BrowserError::Command {
                command: "script".into(),
                error: "javascript error".into(),
                message: err.to_string(),
            });
        }
        Ok(value.get("ok").cloned().unwrap_or(Value::Null))
    }

    /// Polls `expression` every 50 ms until it is truthy; returns its value.
    pub fn wait_until(&self, expression: &str, limit: Duration) -> Result<Value> {
        let start = Instant::now();
        loop {
            let value = self.execute(&format!("return ({expression});"), Vec::new())?;
            let truthy = match &value {
                Value::Null => false,
                Value::Bool(b) => *b,
                Value::Number(n) => n.as_f64().is_some_and(|x| x != 0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return Ok(value);
            }
            if start.elapsed() > limit {
                return Err(BrowserError::Timeout(limit, format!("`{expression}` (last value {value})")));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Runs `source` in every document this tab opens from now on, before the page's own
    /// scripts (Chromium's `Page.addScriptToEvaluateOnNewDocument`, through chromedriver): how
    /// tests inject doubles such as a scripted `navigator.xr`.
    pub fn add_script_on_new_document(&self, source: &str) -> Result<()> {
        let command = json!({ "cmd": "Page.addScriptToEvaluateOnNewDocument", "params": { "source": source } });
        self.request("POST", &self.session_path("/goog/cdp/execute"), Some(&command))?;
        Ok(())
    }

    /// Resizes the browser window (WebDriver's Set Window Rect); the page sees `resize`.
    pub fn set_window_size(&self, width: u32, height: u32) -> Result<()> {
        let rect = json!({ "width": width, "height": height });
        self.request("POST", &self.session_path("/window/rect"), Some(&rect))?;
        Ok(())
    }

    /// The current tab's handle.
    pub fn window(&self) -> Result<String> {
        let value = self.request("GET", &self.session_path("/window"), None)?;
        value.as_str().map(str::to_string).ok_or_else(|| BrowserError::Protocol(format!("window handle {value}")))
    }

    pub fn windows(&self) -> Result<Vec<String>> {
        let value = self.request("GET", &self.session_path("/window/handles"), None)?;
        handles(&value)
    }

    /// Opens a new tab, switches to it and returns its handle.
    pub fn new_tab(&self) -> Result<String> {
        let value = self.request("POST", &self.session_path("/window/new"), Some(&json!({ "type": "tab" })))?;
        let handle =
            value["handle"].as_str().ok_or_else(|| BrowserError::Protocol(format!("new window {value}")))?.to_string();
        self.switch_to(&handle)?;
        Ok(handle)
    }

    pub fn switch_to(&self, handle: &str) -> Result<()> {
        self.request("POST", &self.session_path("/window"), Some(&json!({ "handle": handle })))?;
        Ok(())
    }

    /// Closes the current tab (its page sees `pagehide`); returns the remaining handles. Switch
    /// to one of them before the next command.
    pub fn close_tab(&self) -> Result<Vec<String>> {
        let value = self.request("DELETE", &self.session_path("/window"), None)?;
        handles(&value)
    }

    /// Console messages since the last call (Chromium's "browser" log; chromedriver only).
    pub fn console_log(&self) -> Result<Vec<LogEntry>> {
        let value = self.request("POST", &self.session_path("/se/log"), Some(&json!({ "type": "browser" })))?;
        let entries = value.as_array().ok_or_else(|| BrowserError::Protocol(format!("log {value}")))?;
        Ok(entries
            .iter()
            .map(|e| LogEntry {
                level: e["level"].as_str().unwrap_or("").to_string(),
                message: e["message"].as_str().unwrap_or("").to_string(),
            })
            .collect())
    }

    /// A PNG of the current tab's viewport.
    pub fn screenshot(&self) -> Result<Vec<u8>> {
        let value = self.request("GET", &self.session_path("/screenshot"), None)?;
        let text = value.as_str().ok_or_else(|| BrowserError::Protocol("screenshot is not a string".into()))?;
        use base64::Engine as _;
        base64::engine::general_purpose::STANDARD
            .decode(text)
            .map_err(|e| BrowserError::Protocol(format!("screenshot is not base64: {e}")))
    }

    /// Saves screenshots of every tab and the console log into the artifact folder, keeps the
    /// folder, and returns its path.
    pub fn save_artifacts(&mut self) -> PathBuf {
        let dir = self.artifacts_path.clone();
        if let Ok(tabs) = self.windows() {
            for (i, tab) in tabs.iter().enumerate() {
                if self.switch_to(tab).is_ok()
                    && let Ok(png) = self.screenshot()
                {
                    let _ = std::fs::write(dir.join(format!("tab{i}.png")), png);
                }
            }
        }
        if let Ok(log) = self.console_log() {
            let text: String = log.iter().map(|e| format!("{} {}\n", e.level, e.message)).collect();
            let _ = std::fs::write(dir.join("console.log"), text);
        }
        if let Some(tmp) = self.artifacts.take() {
            let _ = tmp.keep();
        }
        dir
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if std::thread::panicking() && !self.session.is_empty() {
            let dir = self.save_artifacts();
            eprintln!("browser test failed: screenshots, console and chromedriver logs in {}", dir.display());
        }
        if !self.session.is_empty() {
            let _ = self.request("DELETE", &self.session_path(""), None);
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

fn handles(value: &Value) -> Result<Vec<String>> {
    value
        .as_array()
        .map(|a| a.iter().filter_map(|h| h.as_str().map(str::to_string)).collect())
        .ok_or_else(|| BrowserError::Protocol(format!("window handles {value}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_driver_is_a_clear_error_that_names_the_fix() {
        let options =
            BrowserOptions { chromedriver: Some(PathBuf::from("/nonexistent/chromedriver")), ..Default::default() };
        let err = Browser::start_with(options).expect_err("no driver there");
        let text = err.to_string();
        assert!(matches!(err, BrowserError::Missing { what: "chromedriver", .. }), "{text}");
        assert!(text.contains("scripts/test") && text.contains("chromium-driver"), "{text}");
    }
}
