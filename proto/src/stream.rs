//! The async (tokio) side: [`FrameCodec`] for `tokio_util::codec::Framed` and a handshake.
//!
//! ```no_run
//! # async fn demo(stream: tokio::net::TcpStream) -> Result<(), nephele_proto::ProtoError> {
//! use futures_util::{SinkExt, StreamExt};
//! use nephele_proto::{stream::{framed, handshake}, FrameConfig, Message, Role};
//! let mut conn = framed(stream, FrameConfig::default());
//! let peer = handshake(&mut conn, Role::Master, &[Role::Worker], None, std::time::Duration::from_secs(5)).await?;
//! while let Some(item) = conn.next().await {
//!     match item {
//!         Err(fatal) => { tracing_like_log(&fatal); break }      // close the connection
//!         Ok(Err(rejected)) => { /* answer or close */ }
//!         Ok(Ok(message)) => { conn.send(&message).await?; }
//!     }
//! }
//! # Ok(()) }
//! # fn tracing_like_log(_: &nephele_proto::ProtoError) {}
//! ```

use std::time::Duration;

use bytes::{Buf, BytesMut};
use futures_util::{SinkExt, StreamExt};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio_util::codec::{Decoder, Encoder, Framed};

use crate::auth::{self, Challenge, FarmSecret};
use crate::codec::{self, Incoming};
use crate::error::ProtoError;
use crate::frame::{FrameConfig, HEADER_LEN, encode_frame_into};
use crate::messages::{Hello, Message, Role};

/// First read reservation for a body; later ones double with the bytes received.
const RESERVE_STEP: usize = 64 << 10;

/// Length-prefixed frames of [`Message`]s, sent by reference (`conn.send(&message)`: a
/// result is never cloned to be sent). Items are [`Incoming`]: a rejected message does
/// not end the stream; an `Err` does (tokio-util stops a stream after a decoder error).
#[derive(Debug, Clone, Default)]
pub struct FrameCodec {
    config: FrameConfig,
}

impl FrameCodec {
    pub fn new(config: FrameConfig) -> FrameCodec {
        FrameCodec { config }
    }
}

/// A connection speaking the protocol.
pub type Connection<T> = Framed<T, FrameCodec>;

/// Wraps a byte stream (e.g. a `TcpStream`) into a [`Connection`].
pub fn framed<T: AsyncRead + AsyncWrite>(io: T, config: FrameConfig) -> Connection<T> {
    Framed::new(io, FrameCodec::new(config))
}

impl Decoder for FrameCodec {
    type Item = Incoming;
    type Error = ProtoError;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<Incoming>, ProtoError> {
        let Some(header) = src.first_chunk::<HEADER_LEN>() else {
            return Ok(None);
        };
        let len = u32::from_le_bytes(*header) as usize;
        let max = self.config.max_frame.min(u32::MAX as usize);
        if len > max {
            return Err(ProtoError::FrameTooLarge { len: len as u64, max });
        }
        let have = src.len() - HEADER_LEN;
        if have < len {
            // Reserve in steps that grow with what arrived, not what the header claims.
            let missing = len - have;
            src.reserve(missing.min(RESERVE_STEP.max(src.len())));
            return Ok(None);
        }
        src.advance(HEADER_LEN);
        let payload = src.split_to(len);
        codec::decode_payload(&payload).map(Some)
    }

    fn decode_eof(&mut self, src: &mut BytesMut) -> Result<Option<Incoming>, ProtoError> {
        match self.decode(src)? {
            Some(item) => Ok(Some(item)),
            None if src.is_empty() => Ok(None),
            None => {
                let expected = src
                    .first_chunk::<HEADER_LEN>()
                    .map_or(HEADER_LEN as u64, |h| HEADER_LEN as u64 + u64::from(u32::from_le_bytes(*h)));
                Err(ProtoError::Truncated { expected, received: src.len() as u64 })
            }
        }
    }
}

impl Encoder<&Message> for FrameCodec {
    type Error = ProtoError;

    fn encode(&mut self, item: &Message, dst: &mut BytesMut) -> Result<(), ProtoError> {
        encode_frame_into(item, dst, &self.config)
    }
}

/// Receives the next message, treating a rejected one and the end of the stream as errors.
pub async fn recv<T: AsyncRead + AsyncWrite + Unpin>(conn: &mut Connection<T>) -> Result<Message, ProtoError> {
    match conn.next().await {
        None => Err(ProtoError::Closed),
        Some(Err(e)) => Err(e),
        Some(Ok(Err(rejected))) => Err(ProtoError::Invalid(rejected)),
        Some(Ok(Ok(message))) => Ok(message),
    }
}

/// The connection's opening: our [`Hello`] and the peer's (its role must be one of
/// `accept`), then the farm credential ([`crate::auth`]): a [`Challenge`] each way and a
/// [`Proof`] each way, the lower role (a worker before the composer before the master)
/// proving first so that a refused peer reads why instead of a proof. All of it within
/// `timeout`. On failure it tells the peer why (best effort); the caller closes.
pub async fn handshake<T: AsyncRead + AsyncWrite + Unpin>(
    conn: &mut Connection<T>,
    role: Role,
    accept: &[Role],
    secret: Option<&FarmSecret>,
    timeout: Duration,
) -> Result<Hello, ProtoError> {
    let opening = async {
        conn.send(&Message::Hello(Hello::new(role))).await?;
        let hello = match recv(conn).await? {
            Message::Hello(hello) if accept.contains(&hello.role) => hello,
            Message::Hello(hello) => return Err(ProtoError::WrongRole(hello.role)),
            other => return Err(unexpected("Hello", other)),
        };
        let peer = hello.role;
        let ours = auth::nonce()?;
        conn.send(&Message::Challenge(Challenge { nonce: ours })).await?;
        let theirs = match recv(conn).await? {
            Message::Challenge(c) => c.nonce,
            other => return Err(unexpected("Challenge", other)),
        };
        let proof = Message::Proof(auth::prove(secret, role, peer, &theirs, &ours));
        let first = auth::proves_first(role, peer);
        if first {
            conn.send(&proof).await?;
        }
        let theirs_proof = match recv(conn).await? {
            Message::Proof(p) => p,
            other => return Err(unexpected("Proof", other)),
        };
        auth::verify(secret, peer, role, &ours, &theirs, &theirs_proof)?;
        if !first {
            conn.send(&proof).await?;
        }
        Ok(hello)
    };
    let result = match tokio::time::timeout(timeout, opening).await {
        Err(_) => Err(ProtoError::Timeout("the peer's Hello, challenge and proof")),
        Ok(result) => result,
    };
    if let Err(e) = &result
        && !matches!(e, ProtoError::Io(_) | ProtoError::Closed | ProtoError::Refused { .. })
    {
        let _ = tokio::time::timeout(Duration::from_secs(1), conn.send(&crate::error_message(e))).await;
    }
    result
}

/// What an unexpected message during the opening means: the peer's refusal (an `Error`
/// message) or a protocol violation.
pub fn unexpected(expected: &'static str, got: Message) -> ProtoError {
    match got {
        Message::Error(e) => ProtoError::Refused { code: e.code, message: e.message },
        other => ProtoError::Unexpected { expected, got: other.kind() },
    }
}
