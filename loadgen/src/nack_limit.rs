//! A receiver that gives up on a lost packet, as browsers do (issue 15): webrtc-rs's NACK
//! generator names every missing packet of its 8,192-packet window every 100 ms until the
//! packet arrives, for ever, so through a narrow link `loadgen` kept asking for packets that
//! the composer had long stopped resending (its responder answers once, within 400 ms:
//! `nephele_composer::retransmit`). libwebrtc's `NackRequester` asks at most 10 times per
//! packet; this filter, placed in the interceptor chain under webrtc-rs's generator, does the
//! same to every NACK the generator writes: a sequence number named [`MAX_NACKS_PER_PACKET`]
//! times is left out of later NACKs, and a NACK left with none is not sent.
//!
//! The bookkeeping is [`NackRequests`] (pure, times given); the interceptor is its thin shell.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use webrtc::interceptor::stream_info::StreamInfo;
use webrtc::interceptor::{Attributes, Interceptor, InterceptorBuilder, RTCPReader, RTCPWriter, RTPReader, RTPWriter};
use webrtc::rtcp::transport_feedbacks::transport_layer_nack::{TransportLayerNack, nack_pairs_from_sequence_numbers};

/// Requests for one lost packet before giving up (libwebrtc's `kMaxNackRetries`).
pub const MAX_NACKS_PER_PACKET: u8 = 10;
/// A packet the generator has not named for this long is forgotten (it arrived, or left the
/// generator's window); its sequence number may then come round again.
const FORGET_AFTER: Duration = Duration::from_secs(2);

/// The interceptor crate's result (its alias is private).
type Result<T> = std::result::Result<T, webrtc::interceptor::Error>;

/// How often each lost packet has been asked for.
#[derive(Debug, Default)]
pub struct NackRequests {
    /// `(media SSRC, sequence number)` -> (requests so far, last time named).
    asked: HashMap<(u32, u16), (u8, Instant)>,
    last_prune: Option<Instant>,
    /// Sequence numbers left out of NACKs since the start.
    pub given_up: u64,
}

impl NackRequests {
    /// The sequence numbers of `nack` still worth asking for at `now` (each counted as asked
    /// once more), in order.
    pub fn still_asked(&mut self, media_ssrc: u32, sequences: impl IntoIterator<Item = u16>, now: Instant) -> Vec<u16> {
        if self.last_prune.is_none_or(|t| now.saturating_duration_since(t) >= FORGET_AFTER) {
            self.asked.retain(|_, (_, last)| now.saturating_duration_since(*last) < FORGET_AFTER);
            self.last_prune = Some(now);
        }
        let mut kept = Vec::new();
        for seq in sequences {
            let (tries, last) = self.asked.entry((media_ssrc, seq)).or_insert((0, now));
            *last = now;
            if *tries < MAX_NACKS_PER_PACKET {
                *tries += 1;
                kept.push(seq);
            } else {
                self.given_up += 1;
            }
        }
        kept
    }

    /// `nack` without the packets given up on; `None` when none is left.
    pub fn filter(&mut self, nack: &TransportLayerNack, now: Instant) -> Option<TransportLayerNack> {
        let sequences = nack.nacks.iter().flat_map(|pair| pair.into_iter());
        let kept = self.still_asked(nack.media_ssrc, sequences, now);
        (!kept.is_empty()).then(|| TransportLayerNack {
            sender_ssrc: nack.sender_ssrc,
            media_ssrc: nack.media_ssrc,
            nacks: nack_pairs_from_sequence_numbers(&kept),
        })
    }
}

/// Builds a [`NackLimit`] per peer connection; register it before webrtc-rs's NACK generator
/// so that the generator writes through it.
#[derive(Debug, Default)]
pub struct NackLimitBuilder;

impl InterceptorBuilder for NackLimitBuilder {
    fn build(&self, _id: &str) -> Result<Arc<dyn Interceptor + Send + Sync>> {
        Ok(Arc::new(NackLimit::default()))
    }
}

/// The interceptor: every RTCP batch written below it passes through [`NackRequests`].
#[derive(Debug, Default)]
pub struct NackLimit {
    requests: Arc<Mutex<NackRequests>>,
}

struct LimitWriter {
    next: Arc<dyn RTCPWriter + Send + Sync>,
    requests: Arc<Mutex<NackRequests>>,
}

#[async_trait::async_trait]
impl RTCPWriter for LimitWriter {
    async fn write(
        &self,
        packets: &[Box<dyn webrtc::rtcp::packet::Packet + Send + Sync>],
        attributes: &Attributes,
    ) -> Result<usize> {
        let now = Instant::now();
        let mut out: Vec<Box<dyn webrtc::rtcp::packet::Packet + Send + Sync>> = Vec::with_capacity(packets.len());
        let mut changed = false;
        for packet in packets {
            match packet.as_any().downcast_ref::<TransportLayerNack>() {
                Some(nack) => {
                    changed = true;
                    let kept = self.requests.lock().unwrap_or_else(|p| p.into_inner()).filter(nack, now);
                    if let Some(kept) = kept {
                        out.push(Box::new(kept));
                    }
                }
                None => out.push(packet.cloned()),
            }
        }
        if !changed {
            return self.next.write(packets, attributes).await;
        }
        if out.is_empty() {
            return Ok(0);
        }
        self.next.write(&out, attributes).await
    }
}

#[async_trait::async_trait]
impl Interceptor for NackLimit {
    async fn bind_rtcp_reader(&self, reader: Arc<dyn RTCPReader + Send + Sync>) -> Arc<dyn RTCPReader + Send + Sync> {
        reader
    }

    async fn bind_rtcp_writer(&self, writer: Arc<dyn RTCPWriter + Send + Sync>) -> Arc<dyn RTCPWriter + Send + Sync> {
        Arc::new(LimitWriter { next: writer, requests: Arc::clone(&self.requests) })
    }

    async fn bind_local_stream(
        &self,
        _info: &StreamInfo,
        writer: Arc<dyn RTPWriter + Send + Sync>,
    ) -> Arc<dyn RTPWriter + Send + Sync> {
        writer
    }

    async fn unbind_local_stream(&self, _info: &StreamInfo) {}

    async fn bind_remote_stream(
        &self,
        _info: &StreamInfo,
        reader: Arc<dyn RTPReader + Send + Sync>,
    ) -> Arc<dyn RTPReader + Send + Sync> {
        reader
    }

    async fn unbind_remote_stream(&self, _info: &StreamInfo) {}

    async fn close(&self) -> Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn nack(sequences: &[u16]) -> TransportLayerNack {
        TransportLayerNack { sender_ssrc: 1, media_ssrc: 7, nacks: nack_pairs_from_sequence_numbers(sequences) }
    }

    fn sequences(nack: &TransportLayerNack) -> Vec<u16> {
        nack.nacks.iter().flat_map(|pair| pair.into_iter()).collect()
    }

    #[test]
    fn a_lost_packet_is_asked_for_ten_times_then_never() {
        let mut requests = NackRequests::default();
        let t0 = Instant::now();
        let every_100ms = |i: u32| t0 + Duration::from_millis(100 * u64::from(i));
        for i in 0..u32::from(MAX_NACKS_PER_PACKET) {
            // The generator names 5 and 6 every 100 ms; 9 joins later.
            let asked = if i < 3 { nack(&[5, 6]) } else { nack(&[5, 6, 9]) };
            let kept = requests.filter(&asked, every_100ms(i)).expect("still asked");
            assert_eq!(sequences(&kept), if i < 3 { vec![5, 6] } else { vec![5, 6, 9] });
        }
        // 5 and 6 have had their ten requests; 9 has had seven.
        let kept = requests.filter(&nack(&[5, 6, 9]), every_100ms(10)).expect("9 is still asked");
        assert_eq!(sequences(&kept), vec![9]);
        assert_eq!((kept.media_ssrc, kept.sender_ssrc), (7, 1));
        for i in 11..14 {
            requests.filter(&nack(&[5, 6, 9]), every_100ms(i));
        }
        assert!(requests.filter(&nack(&[5, 6, 9]), every_100ms(14)).is_none(), "all given up");
        // 5 and 6 from the eleventh request on (2 + 2 x 3), 9 at its eleventh, then all three.
        assert_eq!(requests.given_up, 2 + 2 * 3 + 1 + 3);
        // Another stream's packet 5 is its own.
        let other = TransportLayerNack { media_ssrc: 8, ..nack(&[5]) };
        assert!(requests.filter(&other, every_100ms(15)).is_some());
    }

    #[test]
    fn a_sequence_number_not_named_for_a_while_starts_afresh() {
        let mut requests = NackRequests::default();
        let t0 = Instant::now();
        for i in 0..u64::from(MAX_NACKS_PER_PACKET) {
            requests.filter(&nack(&[40_000]), t0 + Duration::from_millis(10 * i));
        }
        assert!(requests.filter(&nack(&[40_000]), t0 + Duration::from_millis(200)).is_none());
        // Two seconds without it (it arrived, or left the window): the number may be reused
        // after the 16-bit sequence wraps, and is asked for again.
        let later = t0 + Duration::from_millis(200) + FORGET_AFTER + Duration::from_millis(1);
        assert!(requests.filter(&nack(&[40_000]), later).is_some());
        // Large batches keep their order and ranges (pairs of a base and 16 following bits).
        let many: Vec<u16> = (100..160).chain([65_530, 65_535, 0, 3]).collect();
        let kept = requests.filter(&nack(&many), later).expect("fresh");
        assert_eq!(sequences(&kept), many);
    }
}
