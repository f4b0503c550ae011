//! The farm's byte streams (issue 15): plain TCP on a trusted network, or TLS (rustls) around
//! it for farms whose processes talk across machines.
//!
//! One certificate serves the whole farm: `farm.crt` (self-signed, for the name
//! [`FARM_SERVER_NAME`]) and its key `farm.key`, in one folder ([`FarmTls::generate`] makes
//! them; `nephele up --farm-tls` does so for its processes). The processes that listen (the
//! master's farm port, the composer's results port) present it; every process that connects
//! trusts that certificate alone: pinned, neither the system's roots nor the host's name, so
//! the folder can be copied to any machine of the farm. A process that only connects (a
//! worker) needs only `farm.crt`. The farm secret's challenge (`nephele_proto::auth`) still
//! runs inside the TLS stream: TLS gives confidentiality and the listener's identity, the
//! secret the connecting process's.

use std::fmt;
use std::io;
use std::path::Path;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use thiserror::Error;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio_rustls::{TlsAcceptor, TlsConnector, client, server};

/// The name in the farm certificate and the one connecting processes ask for.
pub const FARM_SERVER_NAME: &str = "nephele-farm";
/// The certificate's file in a farm TLS folder.
pub const CERT_FILE: &str = "farm.crt";
/// The private key's file (the listening processes only).
pub const KEY_FILE: &str = "farm.key";

#[derive(Debug, Error)]
pub enum TransportError {
    #[error("reading {path}: {reason}")]
    Read { path: String, reason: String },
    #[error("the farm certificate and key do not make a TLS configuration: {0}")]
    Config(String),
    #[error("making the farm certificate: {0}")]
    Generate(String),
    #[error("writing {path}: {source}")]
    Write { path: String, source: io::Error },
}

/// The farm's TLS settings: a connector trusting the farm certificate, and an acceptor
/// presenting it where the key is at hand.
#[derive(Clone)]
pub struct FarmTls {
    connector: TlsConnector,
    acceptor: Option<TlsAcceptor>,
}

impl fmt::Debug for FarmTls {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("FarmTls").field("can_accept", &self.can_accept()).finish_non_exhaustive()
    }
}

impl FarmTls {
    /// Reads `dir/farm.crt` and, when present, `dir/farm.key` (without it the settings can
    /// only connect).
    pub fn load(dir: &Path) -> Result<FarmTls, TransportError> {
        let cert_path = dir.join(CERT_FILE);
        let read = |path: &Path, reason: String| TransportError::Read { path: path.display().to_string(), reason };
        let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(&cert_path)
            .map_err(|e| read(&cert_path, e.to_string()))?
            .collect::<Result<_, _>>()
            .map_err(|e| read(&cert_path, e.to_string()))?;
        let [cert] = <[CertificateDer<'static>; 1]>::try_from(certs)
            .map_err(|c| read(&cert_path, format!("{} certificates; the farm's is one", c.len())))?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let config_error = |e: rustls::Error| TransportError::Config(e.to_string());
        let mut roots = rustls::RootCertStore::empty();
        roots.add(cert.clone()).map_err(config_error)?;
        let client = rustls::ClientConfig::builder_with_provider(Arc::clone(&provider))
            .with_safe_default_protocol_versions()
            .map_err(config_error)?
            .with_root_certificates(roots)
            .with_no_client_auth();
        let key_path = dir.join(KEY_FILE);
        let acceptor = if key_path.exists() {
            let key = PrivateKeyDer::from_pem_file(&key_path).map_err(|e| read(&key_path, e.to_string()))?;
            let server = rustls::ServerConfig::builder_with_provider(provider)
                .with_safe_default_protocol_versions()
                .map_err(config_error)?
                .with_no_client_auth()
                .with_single_cert(vec![cert], key)
                .map_err(config_error)?;
            Some(TlsAcceptor::from(Arc::new(server)))
        } else {
            None
        };
        Ok(FarmTls { connector: TlsConnector::from(Arc::new(client)), acceptor })
    }

    /// Writes a new farm certificate and key into `dir` (made if missing; the key readable
    /// by its owner only), replacing any there.
    pub fn generate(dir: &Path) -> Result<(), TransportError> {
        let generate = |e: rcgen::Error| TransportError::Generate(e.to_string());
        let mut params = rcgen::CertificateParams::new(vec![FARM_SERVER_NAME.to_string()]).map_err(generate)?;
        params.distinguished_name.push(rcgen::DnType::CommonName, "Nephele farm");
        params.extended_key_usages = vec![rcgen::ExtendedKeyUsagePurpose::ServerAuth];
        let key = rcgen::KeyPair::generate().map_err(generate)?;
        let cert = params.self_signed(&key).map_err(generate)?;
        std::fs::create_dir_all(dir)
            .map_err(|source| TransportError::Write { path: dir.display().to_string(), source })?;
        write_file(&dir.join(KEY_FILE), key.serialize_pem().as_bytes(), true)?;
        write_file(&dir.join(CERT_FILE), cert.pem().as_bytes(), false)
    }

    /// Whether these settings hold the key (may serve a listener).
    pub fn can_accept(&self) -> bool {
        self.acceptor.is_some()
    }

    async fn connect_tls(&self, tcp: TcpStream) -> io::Result<FarmStream> {
        let name = ServerName::try_from(FARM_SERVER_NAME).map_err(io::Error::other)?;
        Ok(FarmStream::Client(Box::new(self.connector.connect(name, tcp).await?)))
    }

    async fn accept_tls(&self, tcp: TcpStream) -> io::Result<FarmStream> {
        let acceptor = self.acceptor.as_ref().ok_or_else(|| {
            io::Error::new(io::ErrorKind::InvalidInput, format!("no {KEY_FILE}: these farm TLS settings cannot listen"))
        })?;
        Ok(FarmStream::Server(Box::new(acceptor.accept(tcp).await?)))
    }
}

fn write_file(path: &Path, bytes: &[u8], private: bool) -> Result<(), TransportError> {
    use std::io::Write;
    let failed = |source| TransportError::Write { path: path.display().to_string(), source };
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(if private { 0o600 } else { 0o644 });
    }
    #[cfg(not(unix))]
    let _ = private;
    let mut file = options.open(path).map_err(failed)?;
    file.write_all(bytes).map_err(failed)
}

/// Connects to `addr` (`host:port`, Nagle off) and, with `tls`, runs the TLS handshake;
/// `timeout` bounds both.
pub async fn connect(addr: &str, tls: Option<&FarmTls>, timeout: Duration) -> io::Result<FarmStream> {
    let timed_out =
        || io::Error::new(io::ErrorKind::TimedOut, format!("connecting to {addr}: no answer within {timeout:?}"));
    tokio::time::timeout(timeout, async {
        let tcp = TcpStream::connect(addr).await?;
        tcp.set_nodelay(true)?;
        match tls {
            Some(tls) => tls.connect_tls(tcp).await,
            None => Ok(FarmStream::Plain(tcp)),
        }
    })
    .await
    .map_err(|_| timed_out())?
}

/// The listening side of an accepted connection (Nagle off): with `tls`, its handshake,
/// within `timeout` (a silent peer holds nothing up beyond it).
pub async fn accept(tcp: TcpStream, tls: Option<&FarmTls>, timeout: Duration) -> io::Result<FarmStream> {
    tcp.set_nodelay(true)?;
    match tls {
        Some(tls) => tokio::time::timeout(timeout, tls.accept_tls(tcp))
            .await
            .map_err(|_| io::Error::new(io::ErrorKind::TimedOut, "no TLS handshake in time"))?,
        None => Ok(FarmStream::Plain(tcp)),
    }
}

/// A farm connection's bytes: plain TCP or TLS over it.
#[derive(Debug)]
pub enum FarmStream {
    Plain(TcpStream),
    Client(Box<client::TlsStream<TcpStream>>),
    Server(Box<server::TlsStream<TcpStream>>),
}

impl FarmStream {
    /// Whether the bytes travel inside TLS.
    pub fn is_tls(&self) -> bool {
        !matches!(self, FarmStream::Plain(_))
    }
}

impl AsyncRead for FarmStream {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            FarmStream::Plain(s) => Pin::new(s).poll_read(cx, buf),
            FarmStream::Client(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
            FarmStream::Server(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for FarmStream {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            FarmStream::Plain(s) => Pin::new(s).poll_write(cx, buf),
            FarmStream::Client(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
            FarmStream::Server(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            FarmStream::Plain(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            FarmStream::Client(s) => Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
            FarmStream::Server(s) => Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            FarmStream::Plain(s) => s.is_write_vectored(),
            FarmStream::Client(s) => s.is_write_vectored(),
            FarmStream::Server(s) => s.is_write_vectored(),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            FarmStream::Plain(s) => Pin::new(s).poll_flush(cx),
            FarmStream::Client(s) => Pin::new(s.as_mut()).poll_flush(cx),
            FarmStream::Server(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            FarmStream::Plain(s) => Pin::new(s).poll_shutdown(cx),
            FarmStream::Client(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
            FarmStream::Server(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}

#[cfg(test)]
mod tests {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio::net::TcpListener;

    use super::*;

    const T: Duration = Duration::from_secs(10);

    /// A listener with `server` settings that echoes one message; returns what the client
    /// read back, or the error of either side.
    async fn exchange(server: Option<FarmTls>, client: Option<FarmTls>, message: &[u8]) -> Result<Vec<u8>, String> {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("address").to_string();
        let echo = tokio::spawn(async move {
            let (tcp, _) = listener.accept().await.map_err(|e| e.to_string())?;
            let mut stream = accept(tcp, server.as_ref(), T).await.map_err(|e| format!("server: {e}"))?;
            let mut buf = vec![0u8; 1 << 16];
            let n = stream.read(&mut buf).await.map_err(|e| format!("server read: {e}"))?;
            stream.write_all(&buf[..n]).await.map_err(|e| format!("server write: {e}"))?;
            stream.flush().await.map_err(|e| e.to_string())?;
            Ok::<bool, String>(stream.is_tls())
        });
        let run = async {
            let mut stream = connect(&addr, client.as_ref(), T).await.map_err(|e| format!("client: {e}"))?;
            stream.write_all(message).await.map_err(|e| format!("client write: {e}"))?;
            stream.flush().await.map_err(|e| e.to_string())?;
            let mut back = vec![0u8; message.len()];
            stream.read_exact(&mut back).await.map_err(|e| format!("client read: {e}"))?;
            Ok::<Vec<u8>, String>(back)
        };
        let back = run.await;
        let served = echo.await.map_err(|e| e.to_string())?;
        // The listener's error first: it says why (the client sees only a reset).
        match (back, served) {
            (Ok(back), Ok(_)) => Ok(back),
            (_, Err(e)) | (Err(e), Ok(_)) => Err(e),
        }
    }

    fn farm(dir: &Path) -> FarmTls {
        FarmTls::generate(dir).expect("generate");
        FarmTls::load(dir).expect("load")
    }

    #[tokio::test]
    async fn a_farm_certificate_carries_bytes_and_a_stranger_is_refused() {
        let (a, b) = (tempfile::tempdir().expect("dir"), tempfile::tempdir().expect("dir"));
        let (ours, theirs) = (farm(a.path()), farm(b.path()));
        assert!(ours.can_accept());
        let message = b"a RayBatch's bytes".repeat(100);
        assert_eq!(exchange(Some(ours.clone()), Some(ours.clone()), &message).await, Ok(message.clone()));
        assert_eq!(exchange(None, None, &message).await, Ok(message.clone()));
        // A client that trusts another farm's certificate, a plain client against a TLS
        // listener, and a TLS client against a plain one all fail.
        assert!(exchange(Some(ours.clone()), Some(theirs), &message).await.is_err());
        assert!(exchange(Some(ours.clone()), None, &message).await.is_err());
        assert!(exchange(None, Some(ours), &message).await.is_err());
    }

    #[tokio::test]
    async fn the_certificate_alone_connects_but_cannot_listen() {
        let dir = tempfile::tempdir().expect("dir");
        let full = farm(dir.path());
        let worker_dir = tempfile::tempdir().expect("dir");
        std::fs::copy(dir.path().join(CERT_FILE), worker_dir.path().join(CERT_FILE)).expect("copy");
        let worker = FarmTls::load(worker_dir.path()).expect("load");
        assert!(!worker.can_accept());
        let message = b"hello".to_vec();
        assert_eq!(exchange(Some(full), Some(worker.clone()), &message).await, Ok(message.clone()));
        let refused = exchange(Some(worker), None, &message).await;
        assert!(refused.as_ref().is_err_and(|e| e.contains(KEY_FILE)), "{refused:?}");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(dir.path().join(KEY_FILE)).expect("key").permissions().mode();
            assert_eq!(mode & 0o077, 0, "the key is readable by its owner only: {mode:o}");
        }
    }

    #[test]
    fn bad_folders_are_clear_errors() {
        let empty = tempfile::tempdir().expect("dir");
        let missing = FarmTls::load(empty.path()).expect_err("no certificate");
        assert!(missing.to_string().contains(CERT_FILE), "{missing}");
        std::fs::write(empty.path().join(CERT_FILE), "not a certificate").expect("write");
        let garbage = FarmTls::load(empty.path()).expect_err("garbage");
        assert!(garbage.to_string().contains(CERT_FILE), "{garbage}");
        let dir = tempfile::tempdir().expect("dir");
        FarmTls::generate(dir.path()).expect("generate");
        std::fs::write(dir.path().join(KEY_FILE), "not a key").expect("write");
        let bad_key = FarmTls::load(dir.path()).expect_err("bad key");
        assert!(bad_key.to_string().contains(KEY_FILE), "{bad_key}");
    }
}
