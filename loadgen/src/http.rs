//! The master's signalling API (`POST /v1/sessions`, `DELETE /v1/sessions/{id}`) through the
//! workspace's one HTTP client, `ureq` (http:// and, with rustls, https:// masters). `ureq`
//! blocks, so each request runs on tokio's blocking pool; it is one request per session
//! start and end, not a hot path.

use std::path::Path;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use crate::LoadError;

/// The environment variable naming a PEM file of certificates that https:// requests trust
/// instead of the public roots (a master's self-signed certificate, a private CA).
pub const TLS_CA_ENV: &str = "NEPHELE_TLS_CA";

/// Certificates trusted instead of the public roots, for the whole process: set once at
/// start-up ([`trust_certificates`], `nephele loadgen --tls-ca`), else read from
/// `$NEPHELE_TLS_CA` on first use; empty: the public web roots.
static TRUSTED: OnceLock<Arc<Vec<ureq::tls::Certificate<'static>>>> = OnceLock::new();

/// Reads the PEM certificates of `file` (one or more).
pub fn read_certificates(file: &Path) -> Result<Vec<ureq::tls::Certificate<'static>>, LoadError> {
    let shown = file.display();
    let pem = std::fs::read(file).map_err(|e| LoadError::Http(format!("reading the certificate file {shown}: {e}")))?;
    let mut certs = Vec::new();
    for item in ureq::tls::parse_pem(&pem) {
        if let ureq::tls::PemItem::Certificate(cert) = item.map_err(|e| LoadError::Http(format!("{shown}: {e}")))? {
            certs.push(cert);
        }
    }
    if certs.is_empty() {
        return Err(LoadError::Http(format!("{shown} holds no PEM certificate")));
    }
    Ok(certs)
}

/// Makes every https:// request of this process trust the certificates of `file` (and only
/// them). Call it once, before the first request; a second call with a different file
/// is an error.
pub fn trust_certificates(file: &Path) -> Result<(), LoadError> {
    let certs = Arc::new(read_certificates(file)?);
    let set = TRUSTED.get_or_init(|| certs.clone());
    if set.iter().map(|c| c.der()).ne(certs.iter().map(|c| c.der())) {
        return Err(LoadError::Http("another set of trusted certificates is already in use".into()));
    }
    Ok(())
}

fn trusted() -> Result<Arc<Vec<ureq::tls::Certificate<'static>>>, LoadError> {
    if let Some(set) = TRUSTED.get() {
        return Ok(set.clone());
    }
    let from_env = match std::env::var_os(TLS_CA_ENV).filter(|v| !v.is_empty()) {
        Some(file) => read_certificates(Path::new(&file))?,
        None => Vec::new(),
    };
    Ok(TRUSTED.get_or_init(|| Arc::new(from_env)).clone())
}

/// The master's URL, `http[s]://HOST[:PORT][/PREFIX]`, without query or trailing slash.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BaseUrl {
    /// `scheme://authority[/prefix]`: the API paths are appended to it.
    pub root: String,
    /// The invitation of an invitation link (`?invite=...`), sent with session requests.
    pub invite: Option<String>,
}

impl BaseUrl {
    pub fn parse(url: &str) -> Result<BaseUrl, LoadError> {
        let bad = |why: &str| LoadError::Url(format!("{url}: {why}"));
        let (scheme, rest) = url.split_once("://").ok_or_else(|| bad("not a URL (expected http://HOST:PORT)"))?;
        if scheme != "http" && scheme != "https" {
            return Err(bad("only http:// and https:// URLs are supported"));
        }
        // The page URL may carry a query (`?width=...`): signalling ignores it but for an
        // invitation.
        let invite = rest
            .split_once('?')
            .map(|(_, query)| query.split('#').next().unwrap_or(""))
            .and_then(|query| query.split('&').find_map(|pair| pair.strip_prefix("invite=")))
            .filter(|token| !token.is_empty())
            .map(str::to_string);
        let rest = rest.split(['?', '#']).next().unwrap_or("");
        let (authority, path) = rest.split_once('/').unwrap_or((rest, ""));
        if authority.is_empty() || authority.starts_with(':') {
            return Err(bad("no host"));
        }
        let prefix = path.trim_end_matches('/');
        let root = if prefix.is_empty() {
            format!("{scheme}://{authority}")
        } else {
            format!("{scheme}://{authority}/{prefix}")
        };
        Ok(BaseUrl { root, invite })
    }
}

/// A response: status, headers (lower-case names), body.
#[derive(Debug, Clone)]
pub struct Response {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: String,
}

impl Response {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// One JSON request to `url` with an overall timeout, blocking (for threads that are not on
/// a runtime: `nephele up`'s readiness probe, tests). Every status is an answer (the caller
/// decides what a 503 means); only transport failures are errors.
pub fn request_blocking(
    url: &str,
    method: &str,
    headers: &[(&str, &str)],
    body: &str,
    timeout: Duration,
) -> Result<Response, LoadError> {
    request_blocking_with(url, method, headers, body, timeout, Verify::Trusted)
}

/// How an https:// request checks the server's certificate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verify {
    /// Against the trusted certificates ([`trust_certificates`]), else the public roots.
    Trusted,
    /// Not at all: only for a process probing a child of its own that it just started,
    /// whose certificate names the public host rather than the address probed (`nephele up
    /// --tls-cert`). Never for anything a user typed.
    Unchecked,
}

/// [`request_blocking`] with a choice of certificate check.
pub fn request_blocking_with(
    url: &str,
    method: &str,
    headers: &[(&str, &str)],
    body: &str,
    timeout: Duration,
    verify: Verify,
) -> Result<Response, LoadError> {
    let what = format!("{method} {url}");
    let mut builder = ureq::http::Request::builder().method(method).uri(url).header("Content-Type", "application/json");
    for (k, v) in headers {
        builder = builder.header(*k, *v);
    }
    let request = builder.body(body.to_owned()).map_err(|e| LoadError::Http(format!("{what}: {e}")))?;
    // Only an https request settles the process's trusted set: a plain-http one before
    // `trust_certificates` must not freeze it empty.
    let trusted = if url.starts_with("https://") { trusted()? } else { Arc::default() };
    let mut tls = ureq::tls::TlsConfig::builder();
    if !trusted.is_empty() {
        tls = tls.root_certs(ureq::tls::RootCerts::Specific(trusted));
    }
    if verify == Verify::Unchecked {
        tls = tls.disable_verification(true);
    }
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(timeout))
        .tls_config(tls.build())
        .build()
        .into();
    let send = || -> Result<Response, ureq::Error> {
        let mut response = agent.run(request)?;
        let status = response.status().as_u16();
        let headers = response
            .headers()
            .iter()
            .map(|(k, v)| (k.as_str().to_ascii_lowercase(), String::from_utf8_lossy(v.as_bytes()).into_owned()))
            .collect();
        let body = response.body_mut().read_to_string()?;
        Ok(Response { status, headers, body })
    };
    send().map_err(|e| match e {
        ureq::Error::Timeout(_) => LoadError::Http(format!("{what}: no answer within {timeout:?}")),
        e => LoadError::Http(format!("{what}: {e}")),
    })
}

/// [`request_blocking`] of `path` under `base`, on tokio's blocking pool.
pub async fn request(
    base: &BaseUrl,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
    timeout: Duration,
) -> Result<Response, LoadError> {
    let url = format!("{}{path}", base.root);
    let (method, body) = (method.to_owned(), body.to_owned());
    let headers: Vec<(String, String)> = headers.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned())).collect();
    let what = format!("{method} {url}");
    tokio::task::spawn_blocking(move || {
        let headers: Vec<(&str, &str)> = headers.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
        request_blocking(&url, &method, &headers, &body, timeout)
    })
    .await
    .map_err(|e| LoadError::Http(format!("{what}: the request task failed: {e}")))?
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[test]
    fn urls_parse_or_fail_clearly() {
        let u = BaseUrl::parse("http://127.0.0.1:8080/").expect("url");
        assert_eq!(u.root, "http://127.0.0.1:8080");
        let u = BaseUrl::parse("https://farm.example/nephele/?width=64").expect("url");
        assert_eq!(u.root, "https://farm.example/nephele");
        assert_eq!(u.invite, None);
        let u = BaseUrl::parse("https://farm.example/?scene=default&invite=v1.default.9.ab#x").expect("url");
        assert_eq!((u.root.as_str(), u.invite.as_deref()), ("https://farm.example", Some("v1.default.9.ab")));
        assert!(BaseUrl::parse("ftp://x:1").is_err());
        assert!(BaseUrl::parse("http:///x").is_err());
        assert!(BaseUrl::parse("localhost:8080").is_err());
    }

    /// A one-shot server on loopback answering `answer` to the first request it reads.
    async fn serve_once(answer: &'static [u8]) -> (BaseUrl, tokio::task::JoinHandle<String>) {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let base = BaseUrl::parse(&format!("http://{}/api", listener.local_addr().expect("addr"))).expect("url");
        let server = tokio::spawn(async move {
            let (mut socket, _) = listener.accept().await.expect("accept");
            let mut seen = Vec::new();
            let mut buf = [0u8; 4096];
            while !seen.windows(4).any(|w| w == b"\r\n\r\n") {
                let n = socket.read(&mut buf).await.expect("read");
                if n == 0 {
                    break;
                }
                seen.extend_from_slice(&buf[..n]);
            }
            socket.write_all(answer).await.expect("write");
            socket.shutdown().await.ok();
            String::from_utf8_lossy(&seen).into_owned()
        });
        (base, server)
    }

    #[tokio::test]
    async fn error_statuses_are_answers_with_headers_and_chunked_bodies() {
        let (base, server) =
            serve_once(b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 2\r\nTransfer-Encoding: chunked\r\n\r\n2\r\n{}\r\n0\r\n\r\n")
                .await;
        let r =
            request(&base, "DELETE", "/v1/sessions/7", &[("Authorization", "Bearer t")], "", Duration::from_secs(5))
                .await
                .expect("an answer");
        assert_eq!((r.status, r.header("retry-after"), r.body.as_str()), (503, Some("2"), "{}"));
        let seen = server.await.expect("server");
        assert!(seen.starts_with("DELETE /api/v1/sessions/7 HTTP/1.1"), "{seen}");
        assert!(seen.to_ascii_lowercase().contains("authorization: bearer t"), "{seen}");
    }

    #[tokio::test]
    async fn a_silent_server_times_out_and_a_closed_port_fails() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let base = BaseUrl::parse(&format!("http://{}", listener.local_addr().expect("addr"))).expect("url");
        let e =
            request(&base, "POST", "/v1/sessions", &[], "{}", Duration::from_millis(300)).await.expect_err("timeout");
        assert!(e.to_string().contains("no answer within"), "{e}");
        drop(listener);
        assert!(request(&base, "POST", "/v1/sessions", &[], "{}", Duration::from_secs(2)).await.is_err());
    }
}
