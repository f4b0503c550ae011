//! The session table: who is connected, with which token, asking for what.
//!
//! Pure bookkeeping (no I/O); the HTTP layer validates requests into [`SessionRequest`]s and
//! the farm driver reads the table. Tokens are 128-bit random values compared in constant
//! time.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Most views one session may ask for (a 45-view quilt fits).
pub const MAX_VIEWS: u32 = nephele_geometry::camera::MAX_VIEWS as u32;
/// Smallest and largest size of one view, in pixels (H.264 needs even sizes; the encoder's
/// level limits cap the total).
pub const MIN_VIEW_SIDE: u32 = 16;
pub const MAX_VIEW_SIDE: u32 = 4096;
/// Largest video frame (all views side by side), in pixels: 4K UHD.
pub const MAX_FRAME_PIXELS: u64 = 3840 * 2160;
pub const MAX_TARGET_FPS: f32 = 240.0;

/// What a client asks for when it opens a session (validated).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionRequest {
    pub scene: String,
    pub views: u32,
    pub width: u32,
    pub height: u32,
    pub target_fps: f32,
}

#[derive(Debug, Error, PartialEq)]
pub enum RequestError {
    #[error("views must be between 1 and {MAX_VIEWS}, got {0}")]
    Views(u32),
    #[error("view size {0}x{1} is invalid: each side must be even and between {MIN_VIEW_SIDE} and {MAX_VIEW_SIDE}")]
    Size(u32, u32),
    #[error("the video frame ({views} views of {width}x{height}) exceeds {MAX_FRAME_PIXELS} pixels")]
    FrameTooLarge { views: u32, width: u32, height: u32 },
    #[error("target_fps must be a number in (0, {MAX_TARGET_FPS}], got {0}")]
    TargetFps(f32),
    #[error("scene name must be 1 to 64 characters of [A-Za-z0-9._-], got {0:?}")]
    SceneName(String),
}

impl SessionRequest {
    pub fn validate(&self) -> Result<(), RequestError> {
        let name_ok = !self.scene.is_empty()
            && self.scene.len() <= 64
            && self.scene.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'.' || b == b'_' || b == b'-')
            && !self.scene.contains("..");
        if !name_ok {
            return Err(RequestError::SceneName(self.scene.chars().take(80).collect()));
        }
        if !(1..=MAX_VIEWS).contains(&self.views) {
            return Err(RequestError::Views(self.views));
        }
        let side_ok = |s: u32| (MIN_VIEW_SIDE..=MAX_VIEW_SIDE).contains(&s) && s.is_multiple_of(2);
        if !(side_ok(self.width) && side_ok(self.height)) {
            return Err(RequestError::Size(self.width, self.height));
        }
        if u64::from(self.views) * u64::from(self.width) * u64::from(self.height) > MAX_FRAME_PIXELS {
            return Err(RequestError::FrameTooLarge { views: self.views, width: self.width, height: self.height });
        }
        if !(self.target_fps > 0.0 && self.target_fps <= MAX_TARGET_FPS) {
            return Err(RequestError::TargetFps(self.target_fps));
        }
        Ok(())
    }
}

/// An open session.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Session {
    pub id: String,
    #[serde(skip)]
    token: [u8; 16],
    pub request: SessionRequest,
    /// Master clock (seconds) when the session opened.
    pub opened_at: f64,
}

#[derive(Debug, Error, PartialEq, Eq)]
pub enum AccessError {
    #[error("no session {0:?}")]
    Unknown(String),
    #[error("wrong or missing token for session {0:?}")]
    BadToken(String),
}

/// All open sessions, by id (ordered, so listings are deterministic).
#[derive(Debug, Default)]
pub struct SessionTable {
    sessions: BTreeMap<String, Session>,
    next_serial: u64,
}

impl SessionTable {
    pub fn new() -> SessionTable {
        SessionTable::default()
    }

    /// Adds a session; `secret` is 16 random bytes from the caller (the table stays pure).
    /// Returns the id and the token (hex) to hand to the client.
    pub fn open(&mut self, request: SessionRequest, secret: [u8; 16], now: f64) -> (String, String) {
        self.next_serial += 1;
        // The id is public (it shows in /v1/farm); the token is the capability.
        let id = format!("s{}-{}", self.next_serial, hex(&secret[..3]));
        let session = Session { id: id.clone(), token: secret, request, opened_at: now };
        self.sessions.insert(id.clone(), session);
        (id, hex(&secret))
    }

    /// Checks `token` (hex) against the session's.
    pub fn authorize(&self, id: &str, token: &str) -> Result<&Session, AccessError> {
        let session = self.sessions.get(id).ok_or_else(|| AccessError::Unknown(truncate(id)))?;
        let given = parse_hex16(token).unwrap_or([0; 16]);
        // Constant-time comparison: no early exit on the first differing byte.
        let diff = given.iter().zip(session.token.iter()).fold(0u8, |acc, (a, b)| acc | (a ^ b));
        if diff != 0 || token.len() != 32 {
            return Err(AccessError::BadToken(truncate(id)));
        }
        Ok(session)
    }

    pub fn close(&mut self, id: &str, token: &str) -> Result<Session, AccessError> {
        self.authorize(id, token)?;
        self.sessions.remove(id).ok_or_else(|| AccessError::Unknown(truncate(id)))
    }

    /// Removes a session without a token (the service itself ends it: the peer vanished).
    pub fn drop_session(&mut self, id: &str) -> Option<Session> {
        self.sessions.remove(id)
    }

    pub fn get(&self, id: &str) -> Option<&Session> {
        self.sessions.get(id)
    }

    pub fn len(&self) -> usize {
        self.sessions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sessions.is_empty()
    }

    pub fn iter(&self) -> impl Iterator<Item = &Session> {
        self.sessions.values()
    }
}

fn truncate(id: &str) -> String {
    id.chars().take(64).collect()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn parse_hex16(text: &str) -> Option<[u8; 16]> {
    if text.len() != 32 || !text.is_ascii() {
        return None;
    }
    let mut out = [0u8; 16];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&text[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request() -> SessionRequest {
        SessionRequest { scene: "default".into(), views: 1, width: 640, height: 480, target_fps: 30.0 }
    }

    #[test]
    fn open_authorize_close() {
        let mut table = SessionTable::new();
        let (id, token) = table.open(request(), [7; 16], 0.0);
        assert_eq!(token.len(), 32);
        assert!(table.authorize(&id, &token).is_ok());
        assert_eq!(table.authorize(&id, &"00".repeat(16)), Err(AccessError::BadToken(id.clone())));
        assert_eq!(table.authorize(&id, "short"), Err(AccessError::BadToken(id.clone())));
        assert_eq!(table.authorize("nope", &token), Err(AccessError::Unknown("nope".into())));
        assert!(table.close(&id, "zz").is_err());
        assert_eq!(table.close(&id, &token).map(|s| s.id), Ok(id.clone()));
        assert!(table.is_empty());
        assert_eq!(table.close(&id, &token), Err(AccessError::Unknown(id)));
    }

    #[test]
    fn ids_are_unique_even_with_equal_secrets() {
        let mut table = SessionTable::new();
        let (a, _) = table.open(request(), [1; 16], 0.0);
        let (b, _) = table.open(request(), [1; 16], 0.0);
        assert_ne!(a, b);
        assert_eq!(table.len(), 2);
    }

    #[test]
    fn bad_requests_are_rejected() {
        let ok = request();
        assert_eq!(ok.validate(), Ok(()));
        let cases = [
            SessionRequest { views: 0, ..ok.clone() },
            SessionRequest { views: MAX_VIEWS + 1, ..ok.clone() },
            SessionRequest { width: 641, ..ok.clone() },
            SessionRequest { height: 0, ..ok.clone() },
            SessionRequest { width: 8192, ..ok.clone() },
            SessionRequest { views: 45, width: 1920, height: 1080, ..ok.clone() },
            SessionRequest { target_fps: f32::NAN, ..ok.clone() },
            SessionRequest { target_fps: 0.0, ..ok.clone() },
            SessionRequest { target_fps: -1.0, ..ok.clone() },
            SessionRequest { scene: "../etc".into(), ..ok.clone() },
            SessionRequest { scene: "a/b".into(), ..ok.clone() },
            SessionRequest { scene: String::new(), ..ok.clone() },
        ];
        for case in cases {
            assert!(case.validate().is_err(), "{case:?} should be rejected");
        }
    }
}
