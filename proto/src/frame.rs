//! Framing: `u32` little-endian payload length, then the payload ([`crate::codec`]).
//! Blocking readers and writers for `std::io`; the tokio codec is in [`crate::stream`].
//!
//! A length above [`FrameConfig::max_frame`] is refused before anything is allocated, and a
//! body is read in steps that grow with the bytes that actually arrived, so a peer that
//! announces 4 GiB and sends nothing costs nothing.

use std::io::{ErrorKind, Read, Write};

use bytes::BufMut;

use crate::codec::{self, Incoming};
use crate::error::ProtoError;
use crate::messages::{Hello, Message, Role};

/// Bytes of the length prefix.
pub const HEADER_LEN: usize = 4;
/// Default largest payload: 64 MiB.
pub const DEFAULT_MAX_FRAME: usize = 64 << 20;
/// First read step for a body; later steps double with the bytes received.
const READ_STEP: usize = 64 << 10;

/// Limits of a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameConfig {
    /// Largest payload accepted or sent, bytes (at most `u32::MAX`).
    pub max_frame: usize,
}

impl Default for FrameConfig {
    fn default() -> FrameConfig {
        FrameConfig { max_frame: DEFAULT_MAX_FRAME }
    }
}

impl FrameConfig {
    fn limit(&self) -> usize {
        self.max_frame.min(u32::MAX as usize)
    }
}

/// A buffer a frame can be encoded into and patched.
pub(crate) trait FrameBuf: BufMut + AsMut<[u8]> {
    fn truncate_to(&mut self, len: usize);
}

impl FrameBuf for Vec<u8> {
    fn truncate_to(&mut self, len: usize) {
        self.truncate(len);
    }
}

impl FrameBuf for bytes::BytesMut {
    fn truncate_to(&mut self, len: usize) {
        self.truncate(len);
    }
}

pub(crate) fn encode_frame_into<B: FrameBuf>(
    message: &Message,
    out: &mut B,
    config: &FrameConfig,
) -> Result<(), ProtoError> {
    encode_frame_with(message, out, config, codec::encode_payload)
}

fn encode_frame_with<B: FrameBuf>(
    message: &Message,
    out: &mut B,
    config: &FrameConfig,
    encode: fn(&Message, &mut B) -> Result<(), ProtoError>,
) -> Result<(), ProtoError> {
    let start = out.as_mut().len();
    out.put_u32_le(0);
    let result = encode(message, out);
    let len = out.as_mut().len() - start - HEADER_LEN;
    let result = result.and_then(|()| {
        if len > config.limit() {
            Err(ProtoError::FrameTooLarge { len: len as u64, max: config.limit() })
        } else {
            Ok(())
        }
    });
    match result {
        Ok(()) => {
            // `len <= u32::MAX` by the check above.
            out.as_mut()[start..start + HEADER_LEN].copy_from_slice(&(len as u32).to_le_bytes());
            Ok(())
        }
        Err(e) => {
            out.truncate_to(start);
            Err(e)
        }
    }
}

/// Appends one frame (header + payload) for `message` to `out`. Validates the message and
/// refuses payloads above `config.max_frame`; on error `out` is left as it was.
pub fn encode_frame(message: &Message, out: &mut Vec<u8>, config: &FrameConfig) -> Result<(), ProtoError> {
    encode_frame_into(message, out, config)
}

/// [`encode_frame`] without validating the message: for tests and tools that play a broken
/// or hostile peer (NaN cameras, pixels outside the image, …). Never use it to talk to a
/// real peer.
pub fn encode_frame_unchecked(message: &Message, out: &mut Vec<u8>, config: &FrameConfig) -> Result<(), ProtoError> {
    encode_frame_with(message, out, config, codec::encode_payload_unchecked)
}

/// A frame's payload and the bytes after the frame.
pub type PayloadAndRest<'a> = (&'a [u8], &'a [u8]);

/// Splits one frame off the front of `bytes`: `Ok(Some((payload, rest)))`, `Ok(None)` if
/// more bytes are needed, `Err` if the length exceeds the limit.
pub fn split_frame<'a>(bytes: &'a [u8], config: &FrameConfig) -> Result<Option<PayloadAndRest<'a>>, ProtoError> {
    let Some(header) = bytes.first_chunk::<HEADER_LEN>() else {
        return Ok(None);
    };
    let len = u32::from_le_bytes(*header) as usize;
    if len > config.limit() {
        return Err(ProtoError::FrameTooLarge { len: len as u64, max: config.limit() });
    }
    let rest = &bytes[HEADER_LEN..];
    Ok((rest.len() >= len).then(|| rest.split_at(len)))
}

/// Decodes the frame at the front of `bytes` and returns it with the bytes after it.
/// [`ProtoError::Truncated`] if the frame is incomplete.
pub fn decode_frame<'a>(bytes: &'a [u8], config: &FrameConfig) -> Result<(Incoming, &'a [u8]), ProtoError> {
    match split_frame(bytes, config)? {
        Some((payload, rest)) => Ok((codec::decode_payload(payload)?, rest)),
        None => {
            let expected = bytes
                .first_chunk::<HEADER_LEN>()
                .map_or(HEADER_LEN as u64, |h| HEADER_LEN as u64 + u64::from(u32::from_le_bytes(*h)));
            Err(ProtoError::Truncated { expected, received: bytes.len() as u64 })
        }
    }
}

/// Reads frames from a blocking stream. Wrap a socket in a `BufReader` to save a system
/// call per frame header.
#[derive(Debug)]
pub struct FrameReader<R> {
    inner: R,
    config: FrameConfig,
    buf: Vec<u8>,
}

impl<R: Read> FrameReader<R> {
    pub fn new(inner: R, config: FrameConfig) -> FrameReader<R> {
        FrameReader { inner, config, buf: Vec::new() }
    }

    /// Reads one frame's payload. [`ProtoError::Closed`] if the peer closed between frames.
    pub fn read_payload(&mut self) -> Result<&[u8], ProtoError> {
        let mut header = [0u8; HEADER_LEN];
        let got = read_full(&mut self.inner, &mut header)?;
        if got == 0 {
            return Err(ProtoError::Closed);
        }
        if got < HEADER_LEN {
            return Err(ProtoError::Truncated { expected: HEADER_LEN as u64, received: got as u64 });
        }
        let len = u32::from_le_bytes(header) as usize;
        if len > self.config.limit() {
            return Err(ProtoError::FrameTooLarge { len: len as u64, max: self.config.limit() });
        }
        // Grow with what arrives, never to what the header claims up front. The buffer keeps
        // its initialised length between frames so that it is not zeroed again.
        let mut filled = 0;
        while filled < len {
            let step = (len - filled).min(READ_STEP.max(filled));
            if self.buf.len() < filled + step {
                self.buf.resize(filled + step, 0);
            }
            let got = read_full(&mut self.inner, &mut self.buf[filled..filled + step])?;
            if got < step {
                return Err(ProtoError::Truncated {
                    expected: (HEADER_LEN + len) as u64,
                    received: (HEADER_LEN + filled + got) as u64,
                });
            }
            filled += step;
        }
        // Keep a big buffer only while frames are big.
        if self.buf.len() > 4 * len.max(READ_STEP) {
            self.buf.truncate(len.max(READ_STEP));
            self.buf.shrink_to_fit();
        }
        Ok(&self.buf[..len])
    }

    /// Reads and decodes one message. `Ok(Err(rejected))`: a valid frame with bad fields.
    pub fn read_message(&mut self) -> Result<Incoming, ProtoError> {
        let payload = self.read_payload()?;
        codec::decode_payload(payload)
    }

    pub fn get_ref(&self) -> &R {
        &self.inner
    }

    #[cfg(test)]
    pub(crate) fn buf_capacity(&self) -> usize {
        self.buf.capacity()
    }

    pub fn into_inner(self) -> R {
        self.inner
    }
}

/// Writes frames to a blocking stream.
#[derive(Debug)]
pub struct FrameWriter<W> {
    inner: W,
    config: FrameConfig,
    buf: Vec<u8>,
}

impl<W: Write> FrameWriter<W> {
    pub fn new(inner: W, config: FrameConfig) -> FrameWriter<W> {
        FrameWriter { inner, config, buf: Vec::new() }
    }

    /// Encodes, validates and writes one message (not flushed).
    pub fn write_message(&mut self, message: &Message) -> Result<(), ProtoError> {
        self.buf.clear();
        encode_frame(message, &mut self.buf, &self.config)?;
        self.inner.write_all(&self.buf)?;
        if self.buf.capacity() > 4 * self.buf.len().max(READ_STEP) {
            self.buf = Vec::new();
        }
        Ok(())
    }

    /// Writes raw bytes (tests and fuzzing of peers).
    pub fn write_raw(&mut self, bytes: &[u8]) -> Result<(), ProtoError> {
        self.inner.write_all(bytes)?;
        Ok(())
    }

    pub fn flush(&mut self) -> Result<(), ProtoError> {
        self.inner.flush()?;
        Ok(())
    }

    pub fn get_ref(&self) -> &W {
        &self.inner
    }

    pub fn into_inner(self) -> W {
        self.inner
    }
}

/// Blocking twin of [`crate::stream::handshake`]: the `Hello`s, then the farm credential
/// ([`crate::auth`]). On a fatal error it tells the peer why (best effort) before returning.
pub fn handshake<R: Read, W: Write>(
    reader: &mut FrameReader<R>,
    writer: &mut FrameWriter<W>,
    role: Role,
    accept: &[Role],
    secret: Option<&crate::auth::FarmSecret>,
) -> Result<Hello, ProtoError> {
    use crate::auth::{self, Challenge};
    use crate::stream::unexpected;
    let mut send = |m: &Message| -> Result<(), ProtoError> {
        writer.write_message(m)?;
        writer.flush()
    };
    let mut recv = || -> Result<Message, ProtoError> { reader.read_message()?.map_err(ProtoError::Invalid) };
    let result = (|| {
        send(&Message::Hello(Hello::new(role)))?;
        let hello = match recv()? {
            Message::Hello(hello) if accept.contains(&hello.role) => hello,
            Message::Hello(hello) => return Err(ProtoError::WrongRole(hello.role)),
            other => return Err(unexpected("Hello", other)),
        };
        let ours = auth::nonce()?;
        send(&Message::Challenge(Challenge { nonce: ours }))?;
        let theirs = match recv()? {
            Message::Challenge(c) => c.nonce,
            other => return Err(unexpected("Challenge", other)),
        };
        let proof = Message::Proof(auth::prove(secret, role, hello.role, &theirs, &ours));
        let first = auth::proves_first(role, hello.role);
        if first {
            send(&proof)?;
        }
        let their_proof = match recv()? {
            Message::Proof(p) => p,
            other => return Err(unexpected("Proof", other)),
        };
        auth::verify(secret, hello.role, role, &ours, &theirs, &their_proof)?;
        if !first {
            send(&proof)?;
        }
        Ok(hello)
    })();
    if let Err(e) = &result
        && !matches!(e, ProtoError::Io(_) | ProtoError::Closed | ProtoError::Refused { .. })
    {
        let _ = send(&crate::error_message(e));
    }
    result
}

/// Like `read_exact`, but returns how many bytes arrived before end of stream.
fn read_full<R: Read>(reader: &mut R, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut filled = 0;
    while filled < buf.len() {
        match reader.read(&mut buf[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(filled)
}
