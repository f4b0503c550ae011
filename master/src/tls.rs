//! HTTPS for the page and the API (rustls): browsers expose WebXR only to secure pages, so a
//! headset on the LAN needs the master's page over TLS.
//!
//! * [`ServerTls::from_pem_files`]: a certificate chain and key the operator holds.
//! * [`ServerTls::self_signed`]: a certificate made here for LAN use (ECDSA P-256, valid for
//!   a year, for `localhost`, the loopback addresses, this host's name, its LAN address and
//!   any names asked for), cached in a folder and made again when the names change or it
//!   nears its end. Browsers warn once; its SHA-256 fingerprint is printed so that the user
//!   can check it against what the browser shows, and `nephele loadgen --tls-ca` trusts it.
//! * [`TlsListener`]: an [`axum::serve::Listener`] that accepts TCP and runs each TLS
//!   handshake on its own task with a deadline, so that a slow or silent client holds up
//!   nobody else's connection.

use std::io::Write;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use sha2::{Digest, Sha256};
use thiserror::Error;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::server::TlsStream;

/// How long a client has for its TLS handshake.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Days a self-signed certificate is valid for; a new one is made when fewer than
/// [`RENEW_DAYS`] are left. (Apple platforms refuse server certificates valid for more than
/// 825 days, even ones the user trusts.)
pub const VALID_DAYS: i64 = 365;
pub const RENEW_DAYS: i64 = 30;
/// Handshaken connections waiting for the HTTP server to take them.
const ACCEPT_QUEUE: usize = 64;

#[derive(Debug, Error)]
pub enum TlsError {
    #[error("reading {what} {path}: {reason}")]
    Read { what: &'static str, path: String, reason: String },
    #[error("{path} holds no {what}")]
    Empty { what: &'static str, path: String },
    #[error("the certificate and key do not make a TLS configuration: {0}")]
    Config(String),
    #[error("making a self-signed certificate: {0}")]
    Generate(String),
    #[error("writing {path}: {source}")]
    Write { path: String, source: std::io::Error },
}

/// A server TLS configuration and what to tell users about it.
#[derive(Debug, Clone)]
pub struct ServerTls {
    pub config: Arc<rustls::ServerConfig>,
    /// SHA-256 of the leaf certificate, `AB:CD:...` as browsers show it.
    pub fingerprint: String,
    /// The PEM file of the certificate (what clients may trust with `--tls-ca`).
    pub cert_path: PathBuf,
}

impl ServerTls {
    /// A certificate chain (leaf first) and its private key, both PEM.
    pub fn from_pem_files(cert: &Path, key: &Path) -> Result<ServerTls, TlsError> {
        let read = |what: &'static str, path: &Path, reason: String| TlsError::Read {
            what,
            path: path.display().to_string(),
            reason,
        };
        let chain: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(cert)
            .map_err(|e| read("certificate", cert, e.to_string()))?
            .collect::<Result<_, _>>()
            .map_err(|e| read("certificate", cert, e.to_string()))?;
        if chain.is_empty() {
            return Err(TlsError::Empty { what: "certificate", path: cert.display().to_string() });
        }
        let key = PrivateKeyDer::from_pem_file(key).map_err(|e| read("private key", key, e.to_string()))?;
        let fingerprint = fingerprint(&chain[0]);
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut config = rustls::ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .map_err(|e| TlsError::Config(e.to_string()))?
            .with_no_client_auth()
            .with_single_cert(chain, key)
            .map_err(|e| TlsError::Config(e.to_string()))?;
        // HTTP/1.1 only: what the server speaks (axum without its http2 feature); offering h2
        // here made Chromium open HTTP/2 and the connection reset.
        config.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(ServerTls { config: Arc::new(config), fingerprint, cert_path: cert.to_path_buf() })
    }

    /// The self-signed certificate cached in `dir` (`cert.pem`, `key.pem` readable by the
    /// owner only, `names.txt`), made anew when missing, unreadable, for other names, or
    /// within [`RENEW_DAYS`] of its end. Returns whether it was made now.
    pub fn self_signed(dir: &Path, names: &[String]) -> Result<(ServerTls, bool), TlsError> {
        let (cert, key, list) = (dir.join("cert.pem"), dir.join("key.pem"), dir.join("names.txt"));
        let wanted = names.join("\n");
        let today = days_since_epoch(SystemTime::now());
        let cached = std::fs::read_to_string(&list).ok().and_then(|text| {
            let (expires, listed) = text.split_once('\n')?;
            let expires: i64 = expires.strip_prefix("expires-day ")?.parse().ok()?;
            (listed == wanted && expires - today > RENEW_DAYS).then_some(())
        });
        if cached.is_some()
            && let Ok(tls) = ServerTls::from_pem_files(&cert, &key)
        {
            return Ok((tls, false));
        }
        std::fs::create_dir_all(dir).map_err(|source| TlsError::Write { path: dir.display().to_string(), source })?;
        let mut params =
            rcgen::CertificateParams::new(names.to_vec()).map_err(|e| TlsError::Generate(e.to_string()))?;
        params.distinguished_name.push(rcgen::DnType::CommonName, "Nephele (self-signed)");
        let ymd = |(y, m, d): (i32, u8, u8)| rcgen::date_time_ymd(y, m, d);
        params.not_before = ymd(day_to_date(today - 1));
        params.not_after = ymd(day_to_date(today + VALID_DAYS));
        let key_pair = rcgen::KeyPair::generate().map_err(|e| TlsError::Generate(e.to_string()))?;
        let made = params.self_signed(&key_pair).map_err(|e| TlsError::Generate(e.to_string()))?;
        write_private(&key, key_pair.serialize_pem().as_bytes(), 0o600)?;
        write_private(&cert, made.pem().as_bytes(), 0o644)?;
        write_private(&list, format!("expires-day {}\n{wanted}", today + VALID_DAYS).as_bytes(), 0o644)?;
        Ok((ServerTls::from_pem_files(&cert, &key)?, true))
    }
}

/// The names a self-signed certificate for this machine covers: `localhost`, 127.0.0.1, ::1,
/// the host name, the address of the interface that routes to the outside (found without
/// sending a packet), then `extra`.
pub fn default_names(extra: &[String]) -> Vec<String> {
    let mut names = vec!["localhost".to_string(), "127.0.0.1".to_string(), "::1".to_string()];
    if let Ok(host) = std::fs::read_to_string("/proc/sys/kernel/hostname") {
        let host = host.trim();
        if !host.is_empty() {
            names.push(host.to_string());
        }
    }
    if let Some(ip) = lan_address() {
        names.push(ip.to_string());
    }
    names.extend(extra.iter().cloned());
    let mut seen = std::collections::HashSet::new();
    names.retain(|n| seen.insert(n.clone()));
    names
}

/// The address of the interface that routes to the outside, if any: a UDP socket
/// "connected" to a documentation address (RFC 5737) picks it; nothing is sent.
pub fn lan_address() -> Option<std::net::IpAddr> {
    let socket = std::net::UdpSocket::bind("0.0.0.0:0").ok()?;
    socket.connect("192.0.2.1:9").ok()?;
    let ip = socket.local_addr().ok()?.ip();
    (!ip.is_unspecified()).then_some(ip)
}

/// SHA-256 of a certificate's DER bytes, upper-case hex pairs joined by colons.
pub fn fingerprint(cert: &[u8]) -> String {
    Sha256::digest(cert).iter().map(|b| format!("{b:02X}")).collect::<Vec<_>>().join(":")
}

fn write_private(path: &Path, bytes: &[u8], mode: u32) -> Result<(), TlsError> {
    use std::os::unix::fs::OpenOptionsExt;
    let err = |source| TlsError::Write { path: path.display().to_string(), source };
    // Into a fresh temporary file with its final mode, then renamed over the old one: a
    // reader sees the old file or the new one, never half of it.
    let tmp = path.with_extension("tmp");
    let _ = std::fs::remove_file(&tmp);
    let mut file = std::fs::OpenOptions::new().write(true).create_new(true).mode(mode).open(&tmp).map_err(err)?;
    file.write_all(bytes).and_then(|()| file.sync_all()).map_err(err)?;
    std::fs::rename(&tmp, path).map_err(err)
}

fn days_since_epoch(t: SystemTime) -> i64 {
    t.duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| (d.as_secs() / 86_400) as i64)
}

/// The civil date of a day number (days since 1970-01-01), by Howard Hinnant's
/// `civil_from_days`.
fn day_to_date(days: i64) -> (i32, u8, u8) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = (doy - (153 * mp + 2) / 5 + 1) as u8;
    let month = if mp < 10 { mp + 3 } else { mp - 9 } as u8;
    let year = (yoe + era * 400 + i64::from(month <= 2)) as i32;
    (year, month, day)
}

/// Accepts TCP connections and hands the HTTP server those whose TLS handshake finished.
#[derive(Debug)]
pub struct TlsListener {
    ready: mpsc::Receiver<(TlsStream<TcpStream>, SocketAddr)>,
    local: SocketAddr,
    acceptor: tokio::task::JoinHandle<()>,
}

impl TlsListener {
    /// Starts accepting on `listener` (on the current tokio runtime).
    pub fn new(listener: TcpListener, config: Arc<rustls::ServerConfig>) -> std::io::Result<TlsListener> {
        let local = listener.local_addr()?;
        let (tx, ready) = mpsc::channel(ACCEPT_QUEUE);
        let tls = TlsAcceptor::from(config);
        let acceptor = tokio::spawn(async move {
            loop {
                let (stream, peer) = match listener.accept().await {
                    Ok(accepted) => accepted,
                    Err(e) => {
                        // Out of file descriptors and the like: back off instead of spinning.
                        tracing::warn!("accepting an HTTPS connection failed: {e}");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                };
                let (tls, tx) = (tls.clone(), tx.clone());
                tokio::spawn(async move {
                    match tokio::time::timeout(HANDSHAKE_TIMEOUT, tls.accept(stream)).await {
                        Ok(Ok(stream)) => {
                            let _ = tx.send((stream, peer)).await;
                        }
                        // Browsers that have not accepted a self-signed certificate yet
                        // close the handshake with an alert: routine, not a warning.
                        Ok(Err(e)) => tracing::debug!(%peer, "TLS handshake failed: {e}"),
                        Err(_) => tracing::debug!(%peer, "TLS handshake timed out"),
                    }
                });
            }
        });
        Ok(TlsListener { ready, local, acceptor })
    }
}

impl Drop for TlsListener {
    fn drop(&mut self) {
        self.acceptor.abort();
    }
}

impl axum::serve::Listener for TlsListener {
    type Io = TlsStream<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.ready.recv().await {
            Some(accepted) => accepted,
            // The acceptor task never ends while the listener lives.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        Ok(self.local)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn civil_dates_from_day_numbers() {
        assert_eq!(day_to_date(0), (1970, 1, 1));
        assert_eq!(day_to_date(11_016), (2000, 2, 29));
        assert_eq!(day_to_date(20_790), (2026, 12, 3));
        assert_eq!(day_to_date(-1), (1969, 12, 31));
    }

    #[test]
    fn a_self_signed_certificate_is_cached_and_made_again_for_other_names() {
        let dir = tempfile::tempdir().expect("tempdir");
        let names = vec!["localhost".to_string(), "127.0.0.1".to_string()];
        let (first, made) = ServerTls::self_signed(dir.path(), &names).expect("made");
        assert!(made);
        assert_eq!(first.fingerprint.len(), 32 * 3 - 1);
        let (again, made) = ServerTls::self_signed(dir.path(), &names).expect("cached");
        assert!(!made);
        assert_eq!(again.fingerprint, first.fingerprint);
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(dir.path().join("key.pem")).expect("key").permissions().mode();
        assert_eq!(mode & 0o077, 0, "the key is the owner's alone: {mode:o}");
        let more = vec!["localhost".to_string(), "nephele.lan".to_string()];
        let (other, made) = ServerTls::self_signed(dir.path(), &more).expect("remade");
        assert!(made);
        assert_ne!(other.fingerprint, first.fingerprint);
        // A damaged cache is made again, not an error.
        std::fs::write(dir.path().join("cert.pem"), "garbage").expect("write");
        assert!(ServerTls::self_signed(dir.path(), &more).expect("remade").1);
    }

    #[test]
    fn missing_or_empty_files_are_clear_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cert = dir.path().join("cert.pem");
        let err = ServerTls::from_pem_files(&cert, &dir.path().join("key.pem")).expect_err("missing");
        assert!(err.to_string().contains("cert.pem"), "{err}");
        std::fs::write(&cert, "").expect("write");
        let err = ServerTls::from_pem_files(&cert, &dir.path().join("key.pem")).expect_err("empty");
        assert!(err.to_string().contains("no certificate"), "{err}");
    }
}
