//! `nephele probe`: one health check over HTTP, for container health checks (the images
//! carry no curl): exit 0 on a 2xx answer, 1 otherwise.

use std::time::Duration;

use anyhow::{Result, bail};

/// Asks `URL` once (GET) and exits 0 if it answers 2xx, 1 on any other status or no answer
/// within `--timeout-secs`; prints the status and body (first line) either way. Used as the
/// images' `HEALTHCHECK`, e.g. `nephele probe http://127.0.0.1:8080/readyz`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The URL to ask: a process's `/livez` or `/readyz` (default: `$NEPHELE_PROBE_URL`, else
    /// `http://127.0.0.1:8080/readyz`, the master's readiness).
    url: Option<String>,
    /// Seconds to wait for the answer.
    #[arg(long, default_value_t = 3)]
    timeout_secs: u64,
    /// File holding the operators' bearer token, sent as `Authorization: Bearer TOKEN`: what
    /// `/metrics` and `/v1/farm` of a master started with `--operator-token-file` ask for
    /// (`/livez` and `/readyz` need none). Default: the file named by
    /// $NEPHELE_OPERATOR_TOKEN_FILE, so a probe inside the master's container finds it.
    #[arg(long, value_name = "FILE")]
    operator_token_file: Option<std::path::PathBuf>,
}

const DEFAULT_URL: &str = "http://127.0.0.1:8080/readyz";

pub fn run(args: Args) -> Result<()> {
    let url = args
        .url
        .or_else(|| std::env::var("NEPHELE_PROBE_URL").ok().filter(|u| !u.is_empty()))
        .unwrap_or_else(|| DEFAULT_URL.to_string());
    let timeout = Duration::from_secs(args.timeout_secs.max(1));
    // Read by the same rules as the master's (size, trimming, at least 16 bytes).
    let token = super::OperatorTokenArgs { operator_token_file: args.operator_token_file }.resolve()?;
    let authorization = token.map(|(token, _)| format!("Bearer {token}"));
    let headers: Vec<(&str, &str)> = authorization.iter().map(|a| ("Authorization", a.as_str())).collect();
    let response = nephele_loadgen::http::request_blocking(&url, "GET", &headers, "", timeout)?;
    let first_line = response.body.lines().next().unwrap_or("");
    println!("{} {url}: {first_line}", response.status);
    if !(200..300).contains(&response.status) {
        bail!("{url} answered {}", response.status);
    }
    Ok(())
}
