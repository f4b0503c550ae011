//! Helpers for the cross-process tests in `tests/tests/` (they run the real `nephele` binary)
//! and the browser end-to-end tests: [`browser`] (headless Chromium over WebDriver),
//! [`client`] (the client page's state), [`farm`] (an in-process farm with a real WebRTC peer),
//! [`service`] (the whole service under `nephele up`), [`viewer`] (a headless WebRTC viewer
//! that decodes the stream, on the composer's own stack).

pub mod browser;
pub mod client;
pub mod farm;
pub mod service;
pub mod viewer;

use std::path::PathBuf;
use std::process::{Command, Output};
use std::sync::OnceLock;

/// Path of the `nephele` command under test: this package's `nephele-under-test` binary
/// (the same command, see `src/bin/`), which cargo builds beside the integration tests with
/// their profile; built here with `cargo build` if it is missing. `NEPHELE_BIN` overrides,
/// e.g. to test an installed `nephele`.
pub fn nephele_bin() -> PathBuf {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
        if let Some(path) = std::env::var_os("NEPHELE_BIN") {
            return PathBuf::from(path);
        }
        // The test executable lives in target/<profile>/deps/; the binary in target/<profile>/.
        let exe = std::env::current_exe().expect("test executable path");
        let profile_dir = exe.parent().and_then(|deps| deps.parent()).expect("target/<profile>").to_path_buf();
        let bin = profile_dir.join(format!("nephele-under-test{}", std::env::consts::EXE_SUFFIX));
        if bin.is_file() {
            return bin;
        }
        let profile = profile_dir.file_name().and_then(|n| n.to_str()).unwrap_or("debug").to_string();
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut build = Command::new(cargo);
        build.args(["build", "--quiet", "-p", "nephele-tests", "--bin", "nephele-under-test"]);
        if profile != "debug" {
            build.args(["--profile", if profile == "release" { "release" } else { &profile }]);
        }
        build.current_dir(env!("CARGO_MANIFEST_DIR"));
        // `cargo test` runs this executable with the package's `CARGO_PKG_*` (and similar)
        // variables set; build scripts that watch them (ring's does) would otherwise see a
        // change and rebuild half the TLS stack.
        for (name, _) in std::env::vars_os() {
            let name = name.to_string_lossy();
            if [
                "CARGO_PKG_",
                "CARGO_MANIFEST_",
                "CARGO_CRATE_",
                "CARGO_BIN_",
                "CARGO_PRIMARY_PACKAGE",
                "CARGO_TARGET_TMPDIR",
                "OUT_DIR",
            ]
            .iter()
            .any(|prefix| name.starts_with(prefix))
            {
                build.env_remove(name.as_ref());
            }
        }
        let status = build.status().expect("running cargo build");
        assert!(status.success(), "cargo build of the nephele-under-test binary failed");
        bin
    })
    .clone()
}

/// Runs `nephele ARGS` with progress bars off and returns its output.
pub fn nephele(args: &[&str]) -> Output {
    Command::new(nephele_bin()).arg("--quiet").args(args).output().expect("running nephele")
}

/// Like [`nephele`], but panics with the command's stderr unless it succeeded.
pub fn nephele_ok(args: &[&str]) -> String {
    let out = nephele(args);
    assert!(out.status.success(), "nephele {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs a command that must fail, and returns its stderr for checking the message.
pub fn nephele_err(args: &[&str]) -> String {
    let out = nephele(args);
    assert!(!out.status.success(), "nephele {args:?} should have failed");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The value of an unlabelled series (`name` or `name_total`, written out) in a process's
/// Prometheus text (`GET /metrics`).
pub fn metric_value(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.trim().parse().ok())
}

/// The shared data folder beside the checkout (`../shared/data`).
pub fn shared_data() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"))
}
