//! The farm's TCP side: accepts workers and the composer on `--farm-listen`, runs one task
//! per connection that turns frames into [`Event`]s for the farm actor and carries the
//! actor's [`LinkCommand`]s out.
//!
//! A connection starts with the handshake (our role `Master`; the peer must be a worker or a
//! composer), then one registration message: `Register` from a worker, `ComposerRegister`
//! from a composer, each answered with `Registered`. A broken, oversized or undecodable frame
//! ends the connection with a logged reason (and an `Error` to the peer when the stream is
//! still writable); a message that decodes but fails validation is answered with an `Error`
//! and the connection carries on.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use nephele_proto::auth::FarmSecret;
use nephele_proto::stream::{Connection, framed, handshake, recv};
use nephele_proto::{
    ErrorCode, ErrorMessage, FrameConfig, Goodbye, Message, ProtoError, Registered, Role, clip_text, error_message,
};
use nephele_transport::{FarmStream, FarmTls};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, oneshot};

use crate::farm::{Event, Farm, LinkCommand};

/// Time a peer has for its hello and its registration.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Time one write may take before the peer is presumed stuck.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);

type Conn = Connection<FarmStream>;

/// Accepts connections until the task is aborted. With a `secret`, every peer must prove it
/// in the handshake ([`nephele_proto::auth`]); with `tls`, every connection is TLS with the
/// farm certificate ([`nephele_transport`]).
pub async fn serve(
    listener: TcpListener,
    farm: Farm,
    frame: FrameConfig,
    secret: Option<Arc<FarmSecret>>,
    tls: Option<Arc<FarmTls>>,
) {
    loop {
        match listener.accept().await {
            Ok((stream, peer)) => {
                tracing::debug!(%peer, "farm connection accepted");
                tokio::spawn(connection(stream, peer, farm.clone(), frame, secret.clone(), tls.clone()));
            }
            Err(e) => {
                // Out of file descriptors and the like: back off instead of spinning.
                tracing::warn!("accepting a farm connection failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

async fn connection(
    stream: TcpStream,
    peer: SocketAddr,
    farm: Farm,
    frame: FrameConfig,
    secret: Option<Arc<FarmSecret>>,
    tls: Option<Arc<FarmTls>>,
) {
    let stream = match nephele_transport::accept(stream, tls.as_deref(), HANDSHAKE_TIMEOUT).await {
        Ok(stream) => stream,
        Err(e) => {
            farm.metrics().links.handshakes_failed.inc();
            tracing::warn!(%peer, "farm connection refused at the TLS handshake: {e}");
            return;
        }
    };
    let mut conn = framed(stream, frame);
    let accept = [Role::Worker, Role::Composer];
    let hello = match handshake(&mut conn, Role::Master, &accept, secret.as_deref(), HANDSHAKE_TIMEOUT).await {
        Ok(hello) => hello,
        Err(e) => {
            let counters = &farm.metrics().links;
            if matches!(e, ProtoError::Unauthenticated(_)) {
                counters.peers_unauthenticated.inc();
            } else {
                counters.handshakes_failed.inc();
            }
            tracing::warn!(%peer, "farm connection refused at the handshake: {e}");
            return;
        }
    };
    let first = match tokio::time::timeout(HANDSHAKE_TIMEOUT, recv(&mut conn)).await {
        Err(_) => Err(ProtoError::Timeout("the registration")),
        Ok(result) => result,
    };
    let (link_tx, link_rx) = mpsc::unbounded_channel();
    match (hello.role, first) {
        (Role::Worker, Ok(Message::Register(register))) => {
            let name = register.name.clone();
            let (reply, answer) = oneshot::channel();
            if !farm.send(Event::WorkerJoin { register, peer, link: link_tx, reply }) {
                return refuse(conn, peer, ErrorCode::ShuttingDown, "the master is shutting down").await;
            }
            let id = match answer.await {
                Ok(Ok(id)) => id,
                Ok(Err(reason)) => return refuse(conn, peer, ErrorCode::InvalidField, &reason).await,
                Err(_) => return refuse(conn, peer, ErrorCode::ShuttingDown, "the master is shutting down").await,
            };
            let registered =
                Registered { worker_id: u64::from(id), load_report_interval_ms: farm.load_report_interval_ms() };
            if let Err(e) = send(&mut conn, &Message::Registered(registered)).await {
                tracing::warn!(%peer, worker = id, "could not confirm the registration: {e}");
                farm.send(Event::WorkerLeft(id, e.to_string()));
                return;
            }
            let reason = run(conn, link_rx, |m| farm.send(Event::WorkerMessage(id, m))).await;
            tracing::info!(%peer, worker = id, %name, "worker link closed: {reason}");
            farm.send(Event::WorkerLeft(id, reason));
        }
        (Role::Composer, Ok(Message::ComposerRegister(register))) => {
            let name = register.name.clone();
            let (reply, answer) = oneshot::channel();
            if !farm.send(Event::ComposerJoin { register, peer, link: link_tx, reply }) {
                return refuse(conn, peer, ErrorCode::ShuttingDown, "the master is shutting down").await;
            }
            let id = match answer.await {
                Ok(Ok(id)) => id,
                Ok(Err(reason)) => return refuse(conn, peer, ErrorCode::Unexpected, &reason).await,
                Err(_) => return refuse(conn, peer, ErrorCode::ShuttingDown, "the master is shutting down").await,
            };
            let registered = Registered { worker_id: id, load_report_interval_ms: farm.load_report_interval_ms() };
            if let Err(e) = send(&mut conn, &Message::Registered(registered)).await {
                tracing::warn!(%peer, composer = id, "could not confirm the registration: {e}");
                farm.send(Event::ComposerLeft(id, e.to_string()));
                return;
            }
            let reason = run(conn, link_rx, |m| farm.send(Event::ComposerMessage(id, m))).await;
            tracing::info!(%peer, composer = id, %name, "composer link closed: {reason}");
            farm.send(Event::ComposerLeft(id, reason));
        }
        (role, Ok(other)) => {
            let reason = format!("a {role} must register first, got a {} message", other.kind());
            refuse(conn, peer, ErrorCode::Unexpected, &reason).await;
        }
        (role, Err(e)) => {
            tracing::warn!(%peer, %role, "no registration: {e}");
            if !matches!(e, ProtoError::Io(_) | ProtoError::Closed) {
                let _ = tokio::time::timeout(Duration::from_secs(1), conn.send(&error_message(&e))).await;
            }
        }
    }
}

/// Tells the peer why and closes.
async fn refuse(mut conn: Conn, peer: SocketAddr, code: ErrorCode, reason: &str) {
    tracing::warn!(%peer, ?code, "farm connection refused: {reason}");
    let message = Message::Error(ErrorMessage { code, message: clip_text(reason.to_string()) });
    let _ = tokio::time::timeout(Duration::from_secs(1), conn.send(&message)).await;
}

async fn send(conn: &mut Conn, message: &Message) -> Result<(), ProtoError> {
    match tokio::time::timeout(WRITE_TIMEOUT, conn.send(message)).await {
        Ok(result) => result,
        Err(_) => Err(ProtoError::Timeout("the peer to read")),
    }
}

/// Serves a registered link until it ends; returns why. `forward` hands a message to the
/// actor (`false` once the actor is gone).
async fn run(
    mut conn: Conn,
    mut commands: mpsc::UnboundedReceiver<LinkCommand>,
    forward: impl Fn(Message) -> bool,
) -> String {
    loop {
        tokio::select! {
            command = commands.recv() => match command {
                Some(LinkCommand::Send(message)) => {
                    // Batch whatever else is queued into one flush.
                    let mut result = conn.feed(&message).await;
                    let mut close = None;
                    while result.is_ok() {
                        match commands.try_recv() {
                            Ok(LinkCommand::Send(m)) => result = conn.feed(&m).await,
                            Ok(LinkCommand::Close(reason)) => {
                                close = Some(reason);
                                break;
                            }
                            Err(_) => break,
                        }
                    }
                    if result.is_ok() {
                        result = match tokio::time::timeout(WRITE_TIMEOUT, conn.flush()).await {
                            Ok(r) => r,
                            Err(_) => Err(ProtoError::Timeout("the peer to read")),
                        };
                    }
                    if let Err(e) = result {
                        if !e.is_fatal() {
                            // We refused to send an invalid message of our own: a bug, logged;
                            // the stream is still in sync.
                            tracing::error!("not sent: {e}");
                            continue;
                        }
                        return format!("sending failed: {e}");
                    }
                    if let Some(reason) = close {
                        return goodbye(conn, reason).await;
                    }
                }
                Some(LinkCommand::Close(reason)) => return goodbye(conn, reason).await,
                None => return goodbye(conn, "the master is shutting down".into()).await,
            },
            item = conn.next() => match item {
                None => return "the peer closed the connection".into(),
                Some(Err(ProtoError::Io(e))) => return format!("connection lost: {e}"),
                Some(Err(e)) => {
                    if !matches!(e, ProtoError::Closed) {
                        let _ = tokio::time::timeout(Duration::from_secs(1), conn.send(&error_message(&e))).await;
                    }
                    return format!("protocol error: {e}");
                }
                Some(Ok(Err(rejected))) => {
                    tracing::warn!("rejected an invalid message: {rejected}");
                    let message = Message::Error(ErrorMessage { code: ErrorCode::InvalidField, message: clip_text(rejected.to_string()) });
                    if let Err(e) = send(&mut conn, &message).await {
                        return format!("sending failed: {e}");
                    }
                }
                Some(Ok(Ok(message))) => {
                    if !forward(message) {
                        return goodbye(conn, "the master is shutting down".into()).await;
                    }
                }
            },
        }
    }
}

/// Says goodbye (unless `reason` is empty: the peer already said it) and closes.
async fn goodbye(mut conn: Conn, reason: String) -> String {
    if !reason.is_empty() {
        let message = Message::Goodbye(Goodbye { reason: clip_text(reason.clone()), returned_batches: Vec::new() });
        if let Err(e) = send(&mut conn, &message).await {
            tracing::debug!("goodbye not delivered: {e}");
        }
    }
    let _ = tokio::time::timeout(Duration::from_secs(1), conn.close()).await;
    if reason.is_empty() { "the peer said goodbye".into() } else { format!("closed by the master: {reason}") }
}
