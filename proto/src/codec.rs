//! The payload of a frame: one tag byte ([`MessageKind::tag`]) and the message body.
//!
//! Bodies are [postcard](https://docs.rs/postcard) (compact, varint integers, maintained)
//! except [`Hello`], whose layout is fixed by hand so that it never changes between
//! versions. Bulk pixel arrays are packed blocks of little-endian bytes (see `packed`).
//! Nothing outside this module knows the body format, so it can be swapped by bumping
//! [`crate::PROTOCOL_VERSION`].
//!
//! Decoding never allocates more than the payload it is given: postcard checks every
//! length against the bytes left before it borrows them, strings and packed arrays are
//! copied from the payload, and sequences grow element by element.

use bytes::BufMut;
use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::error::{ProtoError, Rejected};
use crate::messages::{Hello, Message, MessageKind, Role};
use crate::{MAGIC, PROTOCOL_VERSION, validate};

/// A frame that decoded: either a valid message, or a well-formed message whose fields
/// failed validation (the stream is still in sync; see [`ProtoError::Invalid`]).
pub type Incoming = Result<Message, Rejected>;

/// Hello body: magic (4) + version (2, LE) + role (1).
const HELLO_LEN: usize = 7;

/// Validates `message` and appends its payload (tag + body) to `out`.
pub fn encode_payload<B: BufMut>(message: &Message, out: &mut B) -> Result<(), ProtoError> {
    validate::message(message).map_err(|error| Rejected { kind: message.kind(), ids: message.batch_ids(), error })?;
    encode_payload_unchecked(message, out)
}

/// [`encode_payload`] without validation: for tests and tools that play a broken or hostile
/// peer. Never use it to talk to a real one.
pub fn encode_payload_unchecked<B: BufMut>(message: &Message, out: &mut B) -> Result<(), ProtoError> {
    let kind = message.kind();
    if let Message::BatchResult(m) = message
        && m.encoding == crate::messages::ResultEncoding::Compact
    {
        return crate::compact::encode(m, out);
    }
    out.put_u8(kind.tag());
    match message {
        Message::Hello(m) => {
            out.put_slice(&MAGIC);
            out.put_u16_le(m.version);
            out.put_u8(m.role.to_byte());
            Ok(())
        }
        Message::Register(m) => body(kind, m, out),
        Message::Registered(m) => body(kind, m, out),
        Message::LoadReport(m) => body(kind, m, out),
        Message::RayBatch(m) => body(kind, m, out),
        Message::BatchResult(m) => body(kind, m, out),
        Message::BatchDone(m) => body(kind, m, out),
        Message::BatchFailed(m) => body(kind, m, out),
        Message::Cancel(m) => body(kind, m, out),
        Message::Goodbye(m) => body(kind, m, out),
        Message::Error(m) => body(kind, m, out),
        Message::ComposerRegister(m) => body(kind, m, out),
        Message::OpenStream(m) => body(kind, m, out),
        Message::StreamOpened(m) => body(kind, m, out),
        Message::ClientPose(m) => body(kind, m, out),
        Message::FramePlan(m) => body(kind, m, out),
        Message::ReleaseTask(m) => body(kind, m, out),
        Message::CloseStream(m) => body(kind, m, out),
        Message::Challenge(m) => body(kind, m, out),
        Message::Proof(m) => body(kind, m, out),
    }
}

/// Decodes and validates one payload. `Err` is fatal (close the connection); `Ok(Err(_))`
/// is a rejected message.
pub fn decode_payload(payload: &[u8]) -> Result<Incoming, ProtoError> {
    let (&tag, rest) = payload.split_first().ok_or(ProtoError::EmptyFrame)?;
    if tag == crate::compact::COMPACT_TAG {
        let message = Message::BatchResult(crate::compact::decode(rest)?);
        return Ok(match validate::message(&message) {
            Ok(()) => Ok(message),
            Err(error) => Err(Rejected { kind: MessageKind::BatchResult, ids: message.batch_ids(), error }),
        });
    }
    let kind = MessageKind::from_tag(tag).ok_or(ProtoError::UnknownMessageType(tag))?;
    let message = match kind {
        MessageKind::Hello => Message::Hello(decode_hello(rest)?),
        MessageKind::Register => Message::Register(from_body(kind, rest)?),
        MessageKind::Registered => Message::Registered(from_body(kind, rest)?),
        MessageKind::LoadReport => Message::LoadReport(from_body(kind, rest)?),
        MessageKind::RayBatch => Message::RayBatch(from_body(kind, rest)?),
        MessageKind::BatchResult => Message::BatchResult(from_body(kind, rest)?),
        MessageKind::BatchDone => Message::BatchDone(from_body(kind, rest)?),
        MessageKind::BatchFailed => Message::BatchFailed(from_body(kind, rest)?),
        MessageKind::Cancel => Message::Cancel(from_body(kind, rest)?),
        MessageKind::Goodbye => Message::Goodbye(from_body(kind, rest)?),
        MessageKind::Error => Message::Error(from_body(kind, rest)?),
        MessageKind::ComposerRegister => Message::ComposerRegister(from_body(kind, rest)?),
        MessageKind::OpenStream => Message::OpenStream(from_body(kind, rest)?),
        MessageKind::StreamOpened => Message::StreamOpened(from_body(kind, rest)?),
        MessageKind::ClientPose => Message::ClientPose(from_body(kind, rest)?),
        MessageKind::FramePlan => Message::FramePlan(from_body(kind, rest)?),
        MessageKind::ReleaseTask => Message::ReleaseTask(from_body(kind, rest)?),
        MessageKind::CloseStream => Message::CloseStream(from_body(kind, rest)?),
        MessageKind::Challenge => Message::Challenge(from_body(kind, rest)?),
        MessageKind::Proof => Message::Proof(from_body(kind, rest)?),
    };
    Ok(match validate::message(&message) {
        Ok(()) => Ok(message),
        Err(error) => Err(Rejected { kind, ids: message.batch_ids(), error }),
    })
}

fn decode_hello(body: &[u8]) -> Result<Hello, ProtoError> {
    let malformed = |reason: &str| ProtoError::Malformed { kind: MessageKind::Hello, reason: reason.into() };
    if body.len() < 4 {
        return Err(malformed("shorter than the magic"));
    }
    let magic = [body[0], body[1], body[2], body[3]];
    if magic != MAGIC {
        return Err(ProtoError::BadMagic(magic));
    }
    if body.len() < HELLO_LEN {
        return Err(malformed("shorter than 7 bytes"));
    }
    let version = u16::from_le_bytes([body[4], body[5]]);
    if version != PROTOCOL_VERSION {
        return Err(ProtoError::VersionMismatch { ours: PROTOCOL_VERSION, theirs: version });
    }
    let role = Role::from_byte(body[6]).ok_or(ProtoError::UnknownRole(body[6]))?;
    if body.len() > HELLO_LEN {
        return Err(ProtoError::TrailingBytes { kind: MessageKind::Hello, count: body.len() - HELLO_LEN });
    }
    Ok(Hello { version, role })
}

fn body<T: Serialize, B: BufMut>(kind: MessageKind, value: &T, out: &mut B) -> Result<(), ProtoError> {
    postcard::serialize_with_flavor(value, BufFlavor(out))
        .map_err(|e| ProtoError::Malformed { kind, reason: format!("encoding failed: {e}") })
}

fn from_body<T: DeserializeOwned>(kind: MessageKind, body: &[u8]) -> Result<T, ProtoError> {
    let (value, rest) =
        postcard::take_from_bytes(body).map_err(|e| ProtoError::Malformed { kind, reason: e.to_string() })?;
    if !rest.is_empty() {
        return Err(ProtoError::TrailingBytes { kind, count: rest.len() });
    }
    Ok(value)
}

/// Postcard output straight into the frame buffer (a `memcpy` per packed array).
pub(crate) struct BufFlavor<'a, B: BufMut>(pub(crate) &'a mut B);

impl<B: BufMut> postcard::ser_flavors::Flavor for BufFlavor<'_, B> {
    type Output = ();

    fn try_push(&mut self, data: u8) -> postcard::Result<()> {
        self.0.put_u8(data);
        Ok(())
    }

    fn try_extend(&mut self, data: &[u8]) -> postcard::Result<()> {
        self.0.put_slice(data);
        Ok(())
    }

    fn finalize(self) -> postcard::Result<()> {
        Ok(())
    }
}
