//! The compact wire form of a [`BatchResult`] (`encoding: ResultEncoding::Compact`): only the
//! pixels the object touched (opacity > 0, or light added with no opacity: colour not 0,
//! which fusion adds too), in 10 bytes each plus about one byte of index,
//! instead of 24 bytes for every pixel of the batch.
//!
//! Per sent pixel, little-endian:
//!
//! | field | encoding | error after decoding |
//! | --- | --- | --- |
//! | premultiplied linear RGB | 3 x IEEE half float | relative <= 2^-11 (4.9e-4) for values in [6.1e-5, 65504], absolute <= 2^-25 below; beyond 65504 clamped |
//! | opacity | 16-bit unorm | absolute <= 1/131070 (7.6e-6) |
//! | view depth | IEEE half float | relative <= 2^-11; beyond 65504 clamped |
//!
//! Pixel indices travel as zigzag LEB128 varints of the difference to the previous index
//! (the first to 0): one byte per pixel inside a run of hits. A pixel the batch does not
//! send is a miss (opacity 0, no depth), which is what fusion assumes for it.
//!
//! The frame carries its own tag ([`COMPACT_TAG`]) and decodes to a [`BatchResult`] with
//! `encoding: Compact`, so readers of results need not know which form arrived.

use bytes::BufMut;
use half::f16;
use serde::{Deserialize, Serialize};

use crate::ProtoError;
use crate::messages::{BatchIds, BatchResult, KernelStats, MessageKind, ResultEncoding};

/// Wire tag of a compact [`BatchResult`] frame (after every [`MessageKind::tag`]).
pub const COMPACT_TAG: u8 = 64;
/// Bytes of colour, opacity and depth per sent pixel.
pub const VALUE_BYTES: usize = 10;

#[derive(Serialize, Deserialize)]
struct CompactBody {
    ids: BatchIds,
    worker_id: u64,
    width: u32,
    height: u32,
    /// Zigzag varint index deltas.
    #[serde(with = "crate::packed::bytes")]
    indices: Vec<u8>,
    /// [`VALUE_BYTES`] per pixel.
    #[serde(with = "crate::packed::bytes")]
    values: Vec<u8>,
    render_time_us: u64,
    stats: KernelStats,
}

#[inline]
fn half_bits(v: f32, lo: f32) -> [u8; 2] {
    f16::from_f32(v.clamp(lo, f16::MAX.to_f32())).to_bits().to_le_bytes()
}

#[inline]
fn push_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Appends the compact body of `m` (validated by the caller) to `out`.
pub(crate) fn encode<B: BufMut>(m: &BatchResult, out: &mut B) -> Result<(), ProtoError> {
    let touched = |i: usize| m.opacity[i] > 0.0 || m.color[i] != [0.0; 3];
    let hits = (0..m.pixels.len()).filter(|&i| touched(i)).count();
    let mut indices = Vec::with_capacity(hits + 8);
    let mut values = vec![0u8; hits * VALUE_BYTES];
    let mut slots = values.chunks_exact_mut(VALUE_BYTES);
    let mut previous = 0i64;
    for (i, &a) in m.opacity.iter().enumerate() {
        if !touched(i) {
            continue;
        }
        let p = i64::from(m.pixels[i]);
        let delta = p - previous;
        previous = p;
        push_varint(&mut indices, ((delta << 1) ^ (delta >> 63)) as u64);
        let Some(v) = slots.next() else { break };
        let [r, g, b] = m.color[i];
        v[0..2].copy_from_slice(&half_bits(r, -f16::MAX.to_f32()));
        v[2..4].copy_from_slice(&half_bits(g, -f16::MAX.to_f32()));
        v[4..6].copy_from_slice(&half_bits(b, -f16::MAX.to_f32()));
        v[6..8].copy_from_slice(&((a.clamp(0.0, 1.0) * 65535.0).round() as u16).to_le_bytes());
        v[8..10].copy_from_slice(&half_bits(m.depth[i], 0.0));
    }
    let body = CompactBody {
        ids: m.ids,
        worker_id: m.worker_id,
        width: m.width,
        height: m.height,
        indices,
        values,
        render_time_us: m.render_time_us,
        stats: m.stats,
    };
    out.put_u8(COMPACT_TAG);
    postcard::serialize_with_flavor(&body, crate::codec::BufFlavor(out))
        .map_err(|e| ProtoError::Malformed { kind: MessageKind::BatchResult, reason: format!("encoding failed: {e}") })
}

/// Decodes a compact body (after its tag). Field ranges are checked by validation after.
pub(crate) fn decode(body: &[u8]) -> Result<BatchResult, ProtoError> {
    let malformed = |reason: String| ProtoError::Malformed { kind: MessageKind::BatchResult, reason };
    let (b, rest): (CompactBody, _) = postcard::take_from_bytes(body).map_err(|e| malformed(e.to_string()))?;
    if !rest.is_empty() {
        return Err(ProtoError::TrailingBytes { kind: MessageKind::BatchResult, count: rest.len() });
    }
    if !b.values.len().is_multiple_of(VALUE_BYTES) {
        return Err(malformed(format!("{} value bytes is not a whole number of pixels", b.values.len())));
    }
    let n = b.values.len() / VALUE_BYTES;
    let mut pixels = Vec::with_capacity(n);
    let (mut previous, mut bytes) = (0i64, b.indices.iter());
    for _ in 0..n {
        let mut v = 0u64;
        let mut shift = 0;
        loop {
            let byte = *bytes.next().ok_or_else(|| malformed("pixel indices end early".into()))?;
            if shift > 63 {
                return Err(malformed("pixel index varint too long".into()));
            }
            v |= u64::from(byte & 0x7f) << shift;
            shift += 7;
            if byte & 0x80 == 0 {
                break;
            }
        }
        let delta = ((v >> 1) as i64) ^ -((v & 1) as i64);
        previous = previous.checked_add(delta).ok_or_else(|| malformed("pixel index overflows".into()))?;
        // Out-of-image indices are a validation error (reported with the index), so only
        // what does not fit a u32 is malformed here.
        pixels.push(u32::try_from(previous).map_err(|_| malformed(format!("pixel index {previous}")))?);
    }
    if bytes.next().is_some() {
        return Err(malformed("more pixel indices than values".into()));
    }
    let half = |c: &[u8]| f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32();
    let (mut color, mut opacity, mut depth) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
    let mut kept = Vec::with_capacity(n);
    for (v, &pixel) in b.values.chunks_exact(VALUE_BYTES).zip(&pixels) {
        let (rgb, a) =
            ([half(&v[0..2]), half(&v[2..4]), half(&v[4..6])], f32::from(u16::from_le_bytes([v[6], v[7]])) / 65535.0);
        // A pixel sent with no opacity and no colour is a miss, as if it had not been sent
        // (the encoder never sends one): dropped, so that a decoded result re-encodes to
        // the same pixels (found by the `decode` fuzz target).
        if a == 0.0 && rgb == [0.0; 3] {
            continue;
        }
        kept.push(pixel);
        color.push(rgb);
        opacity.push(a);
        depth.push(half(&v[8..10]));
    }
    Ok(BatchResult {
        ids: b.ids,
        worker_id: b.worker_id,
        width: b.width,
        height: b.height,
        pixels: kept,
        color,
        opacity,
        depth,
        render_time_us: b.render_time_us,
        stats: b.stats,
        encoding: ResultEncoding::Compact,
    })
}
