//! The master's signalling API over plain HTTP/1.1 (one request per connection): enough for
//! `POST /v1/sessions` and `DELETE /v1/sessions/{id}` without an HTTP stack.

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::LoadError;

/// `http://HOST:PORT[/PREFIX]`, split.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BaseUrl {
    /// `host:port`, as for `TcpStream::connect`.
    pub authority: String,
    /// Path prefix without a trailing slash (`""` at the root).
    pub prefix: String,
}

impl BaseUrl {
    pub fn parse(url: &str) -> Result<BaseUrl, LoadError> {
        let bad = |why: &str| LoadError::Url(format!("{url}: {why}"));
        let rest = url.strip_prefix("http://").ok_or_else(|| bad("only http:// URLs are supported"))?;
        // The page URL may carry a query (`?width=...`): signalling ignores it.
        let rest = rest.split(['?', '#']).next().unwrap_or("");
        let (authority, path) = rest.split_once('/').map_or((rest, ""), |(a, p)| (a, p));
        if authority.is_empty() {
            return Err(bad("no host"));
        }
        let authority =
            if authority.rsplit_once(':').is_some_and(|(_, p)| p.parse::<u16>().is_ok()) && !authority.ends_with(']') {
                authority.to_string()
            } else {
                format!("{authority}:80")
            };
        let prefix = path.trim_end_matches('/');
        let prefix = if prefix.is_empty() { String::new() } else { format!("/{prefix}") };
        Ok(BaseUrl { authority, prefix })
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

/// One request on a fresh connection (`Connection: close`), with an overall timeout.
pub async fn request(
    base: &BaseUrl,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
    timeout: Duration,
) -> Result<Response, LoadError> {
    let work = async {
        let mut stream = TcpStream::connect(&base.authority).await?;
        let mut head = format!(
            "{method} {}{path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\nContent-Type: application/json\r\nContent-Length: {}\r\n",
            base.prefix,
            base.authority,
            body.len()
        );
        for (k, v) in headers {
            head.push_str(&format!("{k}: {v}\r\n"));
        }
        head.push_str("\r\n");
        stream.write_all(head.as_bytes()).await?;
        stream.write_all(body.as_bytes()).await?;
        let mut raw = Vec::new();
        stream.read_to_end(&mut raw).await?;
        Ok::<_, std::io::Error>(raw)
    };
    let raw = tokio::time::timeout(timeout, work)
        .await
        .map_err(|_| LoadError::Http(format!("{method} {path}: no answer within {timeout:?}")))?
        .map_err(|e| LoadError::Http(format!("{method} {path} to {}: {e}", base.authority)))?;
    parse_response(&raw).ok_or_else(|| LoadError::Http(format!("{method} {path}: malformed HTTP response")))
}

fn parse_response(raw: &[u8]) -> Option<Response> {
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = std::str::from_utf8(&raw[..split]).ok()?;
    let mut lines = head.split("\r\n");
    let status = lines.next()?.split_whitespace().nth(1)?.parse().ok()?;
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let mut body = raw[split + 4..].to_vec();
    if headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked")) {
        body = dechunk(&body)?;
    }
    Some(Response { status, headers, body: String::from_utf8_lossy(&body).into_owned() })
}

fn dechunk(mut rest: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let end = rest.windows(2).position(|w| w == b"\r\n")?;
        let size = usize::from_str_radix(std::str::from_utf8(&rest[..end]).ok()?.split(';').next()?.trim(), 16).ok()?;
        rest = &rest[end + 2..];
        if size == 0 {
            return Some(out);
        }
        out.extend_from_slice(rest.get(..size)?);
        rest = rest.get(size + 2..)?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_parse_or_fail_clearly() {
        let u = BaseUrl::parse("http://127.0.0.1:8080/").expect("url");
        assert_eq!((u.authority.as_str(), u.prefix.as_str()), ("127.0.0.1:8080", ""));
        let u = BaseUrl::parse("http://farm.example/nephele/?width=64").expect("url");
        assert_eq!((u.authority.as_str(), u.prefix.as_str()), ("farm.example:80", "/nephele"));
        assert!(BaseUrl::parse("https://x:1").is_err());
        assert!(BaseUrl::parse("http:///x").is_err());
        assert!(BaseUrl::parse("localhost:8080").is_err());
    }

    #[test]
    fn responses_parse_with_and_without_chunks() {
        let r = parse_response(b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 2\r\ncontent-length: 2\r\n\r\n{}")
            .expect("response");
        assert_eq!((r.status, r.header("retry-after"), r.body.as_str()), (503, Some("2"), "{}"));
        let r = parse_response(b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\n\r\n2\r\n{}\r\n0\r\n\r\n")
            .expect("response");
        assert_eq!((r.status, r.body.as_str()), (201, "{}"));
        assert!(parse_response(b"nonsense").is_none());
    }
}
