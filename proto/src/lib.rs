//! `nephele-proto`: every message that crosses a Nephele process boundary (master, workers,
//! composer), with its framing, versioning and validation. Depends on `nephele-geometry` only
//! (the limits every process shares, such as `MAX_VIEWS`).
//!
//! * [`messages`]: the message types ([`Message`] and one struct per kind).
//! * [`codec`]: a frame's payload, a tag byte and a postcard body with packed pixel arrays
//!   (hidden here so that the format can change with [`PROTOCOL_VERSION`]).
//! * [`frame`]: `u32` LE length prefix, a maximum frame size, blocking reader/writer.
//! * [`stream`]: the same for tokio (`Framed` codec) and the handshake.
//! * [`validate`]: limits and the field checks run on every message decoded or sent.
//!
//! A connection starts with a [`Hello`] each way (magic, version, role). After that any
//! frame that cannot be decoded (truncated, oversized, unknown type, wrong version, bad
//! body) is a fatal [`ProtoError`]: the receiver logs it, sends an [`ErrorMessage`] if it
//! can, and closes. A frame that decodes but whose fields are out of range is a
//! [`Rejected`] message: the stream is still in sync, so a worker answers a bad
//! [`RayBatch`] with [`BatchFailed`] and keeps serving everybody else's batches.

pub mod auth;
pub mod codec;
pub mod compact;
mod error;
pub mod frame;
pub mod h264;
pub mod messages;
mod packed;
pub mod pose;
pub mod stream;
pub mod validate;

pub use codec::{Incoming, decode_payload, encode_payload};
pub use error::{ProtoError, Rejected, ValidationError};
pub use frame::{
    DEFAULT_MAX_FRAME, FrameConfig, FrameReader, FrameWriter, decode_frame, encode_frame, encode_frame_unchecked,
};
pub use messages::*;

/// Magic of the [`Hello`] frame.
pub const MAGIC: [u8; 4] = *b"NPHL";
/// Version of everything after the `Hello`. Peers of different versions refuse each other.
/// 2: `BatchIds::task_id` and the composer ⇄ master messages.
/// 3: compact batch results ([`compact`]).
/// 5: the farm credential ([`auth`]: `Challenge` and `Proof` after the `Hello`s).
/// 6: deadlines travel as time left (`deadline_in_us`), not as Unix instants.
/// 7: derived views ride on ray batches (`RayBatch::derived`, `RayBatch::reuse`).
/// 8: a worker may take a batch from its previous render of the user's view
///    (`ReuseLimits::previous_frames`).
/// 9: an environment's batch carries the solid matter of the objects standing in it
///    (`RayBatch::occluders`).
/// 10: renders ahead of a session's next frames (`ReuseLimits::ahead`).
pub const PROTOCOL_VERSION: u16 = 10;

/// The [`ErrorMessage`] that tells a peer why its connection is being closed.
pub fn error_message(error: &ProtoError) -> Message {
    Message::Error(ErrorMessage { code: error.code(), message: clip_text(error.to_string()) })
}

/// Cuts free text to [`validate::MAX_TEXT_LEN`] bytes (at a character boundary) so that it
/// passes validation.
pub fn clip_text(mut text: String) -> String {
    if text.len() > validate::MAX_TEXT_LEN {
        let mut end = validate::MAX_TEXT_LEN;
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        text.truncate(end);
    }
    text
}

#[cfg(test)]
mod tests;
