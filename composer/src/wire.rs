//! The composer's own framing for frame plans and worker results on its TCP listener.
//!
//! Interim: `nephele-proto` will own every message that crosses a process boundary; until
//! its batch-result types land, workers (and tests) speak this. Each message is
//! `u32 length (LE, of what follows) | u8 kind | body`, all little-endian:
//!
//! * kind 1, **frame plan**: `session u64, frame u64, view_width u32, view_height u32,
//!   views u16, columns u16, background f32 x 3, deadline_ms u32` (from receipt), `batches u32`,
//!   then per batch `object u32, batch u32, view u16, n u32, pixels u32 x n`;
//! * kind 2, **batch result**: `session u64, frame u64, view u16, object u32, batch u32, n u32,
//!   pixels u32 x n, colour f32 x 3n, opacity f32 x n, depth f32 x n`.
//!
//! Decoding checks every length against the bytes present, so a short or lying message is an
//! error, never a panic or a huge allocation.

use std::sync::Arc;
use std::time::{Duration, Instant};

use nephele_geometry::PixelResults;
use thiserror::Error;

use crate::fusion::{BatchKey, BatchResult, FrameLayout, FramePlan, PlannedBatch};

/// Largest message accepted (a full 4K frame of results is about 100 MB; batches are smaller).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;
pub const KIND_PLAN: u8 = 1;
pub const KIND_RESULT: u8 = 2;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum WireError {
    #[error("message of {0} bytes exceeds the {MAX_MESSAGE_BYTES}-byte limit")]
    TooLarge(usize),
    #[error("message ends early: {0}")]
    Truncated(&'static str),
    #[error("{0} trailing bytes after the message")]
    Trailing(usize),
    #[error("unknown message kind {0}")]
    UnknownKind(u8),
    #[error("bad layout: {0}")]
    Layout(String),
}

/// A decoded message. The plan's deadline is relative: the receiver adds it to the instant
/// of receipt.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    Plan { plan: PlanBody, deadline: Duration },
    Result(BatchResult),
}

/// A frame plan without its absolute deadline.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanBody {
    pub session: u64,
    pub frame: u64,
    pub layout: FrameLayout,
    pub background: [f32; 3],
    pub batches: Vec<PlannedBatch>,
}

impl PlanBody {
    pub fn with_deadline(self, deadline: Instant) -> FramePlan {
        FramePlan {
            session: self.session,
            frame: self.frame,
            layout: self.layout,
            background: self.background,
            deadline,
            batches: self.batches,
        }
    }
}

/// Encodes a plan message (length prefix included).
pub fn encode_plan(plan: &PlanBody, deadline: Duration) -> Vec<u8> {
    let mut b = Vec::new();
    b.push(KIND_PLAN);
    b.extend_from_slice(&plan.session.to_le_bytes());
    b.extend_from_slice(&plan.frame.to_le_bytes());
    b.extend_from_slice(&plan.layout.view_width().to_le_bytes());
    b.extend_from_slice(&plan.layout.view_height().to_le_bytes());
    b.extend_from_slice(&plan.layout.views().to_le_bytes());
    b.extend_from_slice(&plan.layout.columns().to_le_bytes());
    for c in plan.background {
        b.extend_from_slice(&c.to_le_bytes());
    }
    b.extend_from_slice(&(deadline.as_millis().min(u128::from(u32::MAX)) as u32).to_le_bytes());
    b.extend_from_slice(&(plan.batches.len() as u32).to_le_bytes());
    for batch in &plan.batches {
        b.extend_from_slice(&batch.key.object.to_le_bytes());
        b.extend_from_slice(&batch.key.batch.to_le_bytes());
        b.extend_from_slice(&batch.view.to_le_bytes());
        b.extend_from_slice(&(batch.pixels.len() as u32).to_le_bytes());
        for p in batch.pixels.iter() {
            b.extend_from_slice(&p.to_le_bytes());
        }
    }
    prefix(b)
}

/// Encodes a batch-result message (length prefix included).
pub fn encode_result(r: &BatchResult) -> Vec<u8> {
    let n = r.pixels.len();
    let mut b = Vec::with_capacity(31 + 24 * n);
    b.push(KIND_RESULT);
    b.extend_from_slice(&r.session.to_le_bytes());
    b.extend_from_slice(&r.frame.to_le_bytes());
    b.extend_from_slice(&r.view.to_le_bytes());
    b.extend_from_slice(&r.key.object.to_le_bytes());
    b.extend_from_slice(&r.key.batch.to_le_bytes());
    b.extend_from_slice(&(n as u32).to_le_bytes());
    for p in &r.pixels {
        b.extend_from_slice(&p.to_le_bytes());
    }
    for c in &r.results.color {
        for v in c {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    for v in r.results.opacity.iter().chain(&r.results.depth) {
        b.extend_from_slice(&v.to_le_bytes());
    }
    prefix(b)
}

fn prefix(body: Vec<u8>) -> Vec<u8> {
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], WireError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len()).ok_or(WireError::Truncated(what))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u16(&mut self, what: &'static str) -> Result<u16, WireError> {
        let s = self.take(2, what)?;
        Ok(u16::from_le_bytes([s[0], s[1]]))
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, WireError> {
        let s = self.take(4, what)?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }

    fn u64(&mut self, what: &'static str) -> Result<u64, WireError> {
        let s = self.take(8, what)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        Ok(u64::from_le_bytes(a))
    }

    fn f32(&mut self, what: &'static str) -> Result<f32, WireError> {
        Ok(f32::from_bits(self.u32(what)?))
    }

    /// `n` u32 values, with the length checked before allocating.
    fn u32s(&mut self, n: usize, what: &'static str) -> Result<Vec<u32>, WireError> {
        let s = self.take(n.checked_mul(4).ok_or(WireError::Truncated(what))?, what)?;
        Ok(s.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }

    fn f32s(&mut self, n: usize, what: &'static str) -> Result<Vec<f32>, WireError> {
        Ok(self.u32s(n, what)?.into_iter().map(f32::from_bits).collect())
    }
}

/// Decodes one message body (the bytes after the length prefix).
pub fn decode(body: &[u8]) -> Result<Message, WireError> {
    if body.len() > MAX_MESSAGE_BYTES {
        return Err(WireError::TooLarge(body.len()));
    }
    let mut r = Reader { data: body, pos: 0 };
    let kind = r.take(1, "kind")?[0];
    let message = match kind {
        KIND_PLAN => {
            let session = r.u64("session")?;
            let frame = r.u64("frame")?;
            let (vw, vh) = (r.u32("view width")?, r.u32("view height")?);
            let (views, columns) = (r.u16("views")?, r.u16("columns")?);
            let layout = FrameLayout::grid(vw, vh, views, columns).map_err(|e| WireError::Layout(e.to_string()))?;
            let background = [r.f32("background")?, r.f32("background")?, r.f32("background")?];
            let deadline = Duration::from_millis(u64::from(r.u32("deadline")?));
            let count = r.u32("batch count")? as usize;
            let mut batches = Vec::with_capacity(count.min(4096));
            for _ in 0..count {
                let object = r.u32("object")?;
                let batch = r.u32("batch")?;
                let view = r.u16("view")?;
                let n = r.u32("pixel count")? as usize;
                let pixels: Arc<[u32]> = r.u32s(n, "pixels")?.into();
                batches.push(PlannedBatch { key: BatchKey { object, batch }, view, pixels });
            }
            Message::Plan { plan: PlanBody { session, frame, layout, background, batches }, deadline }
        }
        KIND_RESULT => {
            let session = r.u64("session")?;
            let frame = r.u64("frame")?;
            let view = r.u16("view")?;
            let object = r.u32("object")?;
            let batch = r.u32("batch")?;
            let n = r.u32("pixel count")? as usize;
            let pixels = r.u32s(n, "pixels")?;
            let flat = r.f32s(n.checked_mul(3).ok_or(WireError::Truncated("colour"))?, "colour")?;
            let color = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let opacity = r.f32s(n, "opacity")?;
            let depth = r.f32s(n, "depth")?;
            Message::Result(BatchResult {
                session,
                frame,
                view,
                key: BatchKey { object, batch },
                pixels,
                results: PixelResults { color, opacity, depth },
            })
        }
        other => return Err(WireError::UnknownKind(other)),
    };
    if r.pos != body.len() {
        return Err(WireError::Trailing(body.len() - r.pos));
    }
    Ok(message)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_result() -> BatchResult {
        BatchResult {
            session: 3,
            frame: 9,
            view: 1,
            key: BatchKey { object: 2, batch: 5 },
            pixels: vec![0, 7, 11],
            results: PixelResults {
                color: vec![[0.1, 0.2, 0.3], [0.0; 3], [1.5, 0.25, 0.0]],
                opacity: vec![0.5, 0.0, 1.0],
                depth: vec![1.0, 0.0, 2.5],
            },
        }
    }

    #[test]
    fn plans_and_results_round_trip() {
        let r = sample_result();
        let bytes = encode_result(&r);
        assert_eq!(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as usize, bytes.len() - 4);
        assert_eq!(decode(&bytes[4..]), Ok(Message::Result(r)));
        let plan = PlanBody {
            session: 3,
            frame: 9,
            layout: FrameLayout::stereo(4, 3).unwrap(),
            background: [0.1, 0.2, 0.3],
            batches: vec![PlannedBatch {
                key: BatchKey { object: 2, batch: 5 },
                view: 1,
                pixels: vec![0, 7, 11].into(),
            }],
        };
        let bytes = encode_plan(&plan, Duration::from_millis(40));
        assert_eq!(decode(&bytes[4..]), Ok(Message::Plan { plan, deadline: Duration::from_millis(40) }));
    }

    #[test]
    fn short_lying_and_unknown_messages_are_errors() {
        let bytes = encode_result(&sample_result());
        let body = &bytes[4..];
        for cut in [0, 1, 10, 30, body.len() - 1] {
            assert!(matches!(decode(&body[..cut]), Err(WireError::Truncated(_))), "cut at {cut}");
        }
        let mut longer = body.to_vec();
        longer.push(0);
        assert_eq!(decode(&longer), Err(WireError::Trailing(1)));
        // A pixel count of 2^32 - 1 with 3 pixels of data: an error, not a 16 GB allocation.
        let mut lying = body.to_vec();
        lying[27..31].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(decode(&lying), Err(WireError::Truncated(_))));
        assert_eq!(decode(&[42]), Err(WireError::UnknownKind(42)));
        let mut plan = encode_plan(
            &PlanBody {
                session: 1,
                frame: 1,
                layout: FrameLayout::mono(2, 2).unwrap(),
                background: [0.0; 3],
                batches: vec![],
            },
            Duration::ZERO,
        );
        plan[4 + 17..4 + 21].copy_from_slice(&0u32.to_le_bytes()); // view width 0
        assert!(matches!(decode(&plan[4..]), Err(WireError::Layout(_))));
    }
}
