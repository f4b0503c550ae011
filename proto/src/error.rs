//! Typed errors: what can go wrong reading or writing a connection.

use std::fmt;

use thiserror::Error;

use crate::messages::{BatchIds, ErrorCode, MessageKind, Role};

/// A connection-level error. All but [`ProtoError::Invalid`] are fatal: the stream can no
/// longer be trusted (or is gone) and the caller closes the connection, logging the reason.
#[derive(Debug, Error)]
pub enum ProtoError {
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
    #[error("the peer closed the connection")]
    Closed,
    #[error("the connection ended inside a frame ({received} of {expected} bytes)")]
    Truncated { expected: u64, received: u64 },
    #[error("frame of {len} bytes exceeds the limit of {max} bytes")]
    FrameTooLarge { len: u64, max: usize },
    #[error("empty frame (no message type)")]
    EmptyFrame,
    #[error("unknown message type {0}")]
    UnknownMessageType(u8),
    #[error("malformed {kind} message: {reason}")]
    Malformed { kind: MessageKind, reason: String },
    #[error("{count} bytes left over after a {kind} message")]
    TrailingBytes { kind: MessageKind, count: usize },
    #[error("bad magic {0:02x?}: the peer does not speak the Nephele protocol")]
    BadMagic([u8; 4]),
    #[error("protocol version mismatch: this side speaks {ours}, the peer {theirs}")]
    VersionMismatch { ours: u16, theirs: u16 },
    #[error("unknown peer role {0}")]
    UnknownRole(u8),
    #[error("a {0} may not connect here")]
    WrongRole(Role),
    #[error("expected {expected}, got a {got} message")]
    Unexpected { expected: &'static str, got: MessageKind },
    #[error("timed out waiting for {0}")]
    Timeout(&'static str),
    /// The peer did not prove the farm secret ([`crate::auth`]).
    #[error("farm credential refused: {0}")]
    Unauthenticated(String),
    /// The peer closed the opening with an error message of its own.
    #[error("the peer refused the connection ({code:?}): {message}")]
    Refused { code: ErrorCode, message: String },
    /// A well-framed message with a field out of range. The stream is still in sync; the
    /// receiver may answer (e.g. [`crate::BatchFailed`]) and carry on, or close.
    #[error(transparent)]
    Invalid(#[from] Rejected),
}

impl ProtoError {
    /// Whether the connection must be closed.
    pub fn is_fatal(&self) -> bool {
        !matches!(self, ProtoError::Invalid(_))
    }

    /// The code to tell the peer (in an [`crate::ErrorMessage`]) before closing.
    pub fn code(&self) -> ErrorCode {
        match self {
            ProtoError::FrameTooLarge { .. } => ErrorCode::FrameTooLarge,
            ProtoError::UnknownMessageType(_) => ErrorCode::UnknownMessageType,
            ProtoError::VersionMismatch { .. } => ErrorCode::VersionMismatch,
            ProtoError::Invalid(_) | ProtoError::WrongRole(_) | ProtoError::UnknownRole(_) => ErrorCode::InvalidField,
            ProtoError::Unexpected { .. } => ErrorCode::Unexpected,
            ProtoError::Unauthenticated(_) => ErrorCode::Unauthenticated,
            ProtoError::Refused { code, .. } => *code,
            ProtoError::Io(_) | ProtoError::Closed | ProtoError::Timeout(_) => ErrorCode::Internal,
            ProtoError::Truncated { .. }
            | ProtoError::EmptyFrame
            | ProtoError::Malformed { .. }
            | ProtoError::TrailingBytes { .. }
            | ProtoError::BadMagic(_) => ErrorCode::Malformed,
        }
    }
}

/// A decoded message that failed validation, with the ids of the batch it was about (if
/// they could be read) so that the receiver can answer for that batch.
#[derive(Debug, Clone, PartialEq, Error)]
pub struct Rejected {
    pub kind: MessageKind,
    pub ids: Option<BatchIds>,
    pub error: ValidationError,
}

impl fmt::Display for Rejected {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "invalid {} message", self.kind)?;
        if let Some(ids) = self.ids {
            write!(f, " (batch {})", ids.batch_id)?;
        }
        write!(f, ": {}", self.error)
    }
}

/// Why a field is out of range.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ValidationError {
    #[error("{field} is not finite")]
    NonFinite { field: &'static str },
    #[error("{field} = {value} is out of range ({range})")]
    OutOfRange { field: &'static str, value: f64, range: &'static str },
    #[error("image size {width}x{height} is outside 1..={max} per side")]
    ImageSize { width: u32, height: u32, max: u32 },
    #[error("pixel index {index} is outside the {width}x{height} image")]
    PixelOutOfImage { index: u32, width: u32, height: u32 },
    #[error("{field} has {len} entries, expected {expected} (one per pixel)")]
    LengthMismatch { field: &'static str, len: usize, expected: usize },
    #[error("{field} has {len} entries, allowed {min}..={max}")]
    Count { field: &'static str, len: usize, min: usize, max: usize },
    #[error("{field} {value:?} is invalid: {reason}")]
    BadString { field: &'static str, value: String, reason: &'static str },
    #[error("occluder: {0}")]
    Occluder(#[from] nephele_geometry::SolidGridError),
}
