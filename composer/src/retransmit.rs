//! Answers to the receiver's NACKs with a budget (issue 15): webrtc-rs's stock responder
//! resends every packet a NACK names, as often as it is named, from the last 8,192 packets.
//! A receiver that NACKs every missing packet every 100 ms until it arrives (webrtc-rs's own
//! generator does, so `nephele loadgen` did) turns a link narrower than the stream into a
//! retransmission storm: through the emulated 32 kbit/s link of `tests/tests/lossy_link.rs`
//! the composer sent about 1,900 packets a second, nearly all of them resends, and the
//! viewer's pictures and data channel starved behind them (BENCHMARKS.md, 2026-12-05d).
//!
//! This responder resends a packet
//!
//! * only while it is fresh ([`MAX_AGE`]: a frame older than that is past showing on a
//!   low-latency stream, and a keyframe request repairs the picture instead),
//! * at most once per sequence number,
//! * within a budget: the bytes resent over the last second stay within a quarter of the
//!   bytes first sent over it, plus one packet (so a lone loss on a slow stream is repaired).
//!
//! The bookkeeping is [`Retransmissions`] (pure, times given); the interceptor is its thin
//! shell in webrtc-rs's interceptor chain, in place of the stock responder. Its writer of
//! each outgoing stream also paces the first sending of every packet ([`crate::pacer`]);
//! resends go out at once. Where the viewer negotiated it, every packet, resends included,
//! leaves stamped with its send time (the `abs-send-time` header extension,
//! [`abs_send_time`]), after the pacer's wait: what a browser's delay-based estimate reads.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use webrtc::interceptor::stream_info::StreamInfo;
use webrtc::interceptor::{Attributes, Interceptor, InterceptorBuilder, RTCPReader, RTCPWriter, RTPReader, RTPWriter};
use webrtc::rtcp::transport_feedbacks::transport_layer_nack::TransportLayerNack;
use webrtc::rtp::packet::Packet;

use crate::pacer::{Pacer, Pacing};

/// Packets older than this are not resent.
pub const MAX_AGE: Duration = Duration::from_millis(400);
/// Resent bytes per second, as a share of the bytes first sent.
pub const BUDGET_SHARE: f64 = 0.25;
/// Sent packets remembered (a power of two; at 1,200 bytes, about 1 s of a 10 Mbit/s stream).
const SLOTS: usize = 1024;
const WINDOW: Duration = Duration::from_secs(1);
/// Allowance above the share, bytes per window: one full packet.
const ALLOWANCE: usize = 1500;

/// The interceptor crate's result (its alias is private).
type Result<T> = std::result::Result<T, webrtc::interceptor::Error>;

/// One remembered packet.
#[derive(Debug, Clone)]
struct Sent {
    packet: Packet,
    at: Instant,
    resent: bool,
}

/// The sent packets of one stream and what has been resent of them.
#[derive(Debug)]
pub struct Retransmissions {
    slots: Vec<Option<Sent>>,
    /// Bytes first sent and resent, with their times, over the last [`WINDOW`].
    sent: VecDeque<(Instant, usize)>,
    resent: VecDeque<(Instant, usize)>,
    sent_bytes: usize,
    resent_bytes: usize,
    /// Resends refused: too old, already resent, over the budget, or never seen.
    pub refused: u64,
}

impl Default for Retransmissions {
    fn default() -> Self {
        Retransmissions {
            slots: vec![None; SLOTS],
            sent: VecDeque::new(),
            resent: VecDeque::new(),
            sent_bytes: 0,
            resent_bytes: 0,
            refused: 0,
        }
    }
}

fn size(packet: &Packet) -> usize {
    // Header size without extensions is close enough for a budget.
    12 + 4 * packet.header.csrc.len() + packet.payload.len()
}

impl Retransmissions {
    fn expire(&mut self, now: Instant) {
        let old = |q: &mut VecDeque<(Instant, usize)>, total: &mut usize| {
            while let Some(&(at, bytes)) = q.front() {
                if now.saturating_duration_since(at) <= WINDOW {
                    break;
                }
                q.pop_front();
                *total -= bytes;
            }
        };
        old(&mut self.sent, &mut self.sent_bytes);
        old(&mut self.resent, &mut self.resent_bytes);
    }

    /// Remembers a packet sent for the first time at `now`.
    pub fn on_sent(&mut self, packet: &Packet, now: Instant) {
        self.expire(now);
        let bytes = size(packet);
        self.sent.push_back((now, bytes));
        self.sent_bytes += bytes;
        let slot = usize::from(packet.header.sequence_number) % SLOTS;
        self.slots[slot] = Some(Sent { packet: packet.clone(), at: now, resent: false });
    }

    /// The packet to resend for a NACK of `sequence` at `now`, if the rules allow it (and
    /// counts it as resent).
    pub fn on_nack(&mut self, sequence: u16, now: Instant) -> Option<Packet> {
        self.expire(now);
        let budget = (self.sent_bytes as f64 * BUDGET_SHARE) as usize + ALLOWANCE;
        let slot = &mut self.slots[usize::from(sequence) % SLOTS];
        let fits = |s: &Sent| {
            s.packet.header.sequence_number == sequence
                && !s.resent
                && now.saturating_duration_since(s.at) <= MAX_AGE
                && self.resent_bytes + size(&s.packet) <= budget
        };
        match slot {
            Some(s) if fits(s) => {
                s.resent = true;
                let bytes = size(&s.packet);
                self.resent.push_back((now, bytes));
                self.resent_bytes += bytes;
                Some(s.packet.clone())
            }
            _ => {
                self.refused += 1;
                None
            }
        }
    }
}

/// NACKed packets resent and refused, over every connection of a composer.
#[derive(Debug, Default)]
pub struct RetransmitCounters {
    pub resent: AtomicU64,
    pub refused: AtomicU64,
}

/// Builds a [`BoundedResponder`] per peer connection (registered in place of webrtc-rs's
/// responder), all counting into one [`RetransmitCounters`] and, when pacing is on, pacing
/// at the rates of one [`Pacing`].
#[derive(Debug, Default)]
pub struct BoundedResponderBuilder {
    pub counters: Arc<RetransmitCounters>,
    pub pacing: Option<Arc<Pacing>>,
}

impl InterceptorBuilder for BoundedResponderBuilder {
    fn build(&self, _id: &str) -> Result<Arc<dyn Interceptor + Send + Sync>> {
        Ok(Arc::new(BoundedResponder {
            streams: Arc::default(),
            counters: Arc::clone(&self.counters),
            pacing: self.pacing.clone(),
        }))
    }
}

/// The `abs-send-time` header extension's value for a packet sent `since` after any fixed
/// epoch: seconds in 6.18 fixed point, modulo 64 s, big-endian in 3 bytes
/// (<http://www.webrtc.org/experiments/rtp-hdrext/abs-send-time>; the receiver reads only
/// differences between packets). Not `rtp`'s `AbsSendTimeExtension::new`, which reads the
/// wall clock (`SystemTime`, which can step): this takes the pacer's monotonic clock, the
/// one tokio pauses in tests.
pub fn abs_send_time(since: Duration) -> [u8; 3] {
    let ticks = (since.as_nanos() << 18) / 1_000_000_000;
    let t = (ticks & 0xFF_FFFF) as u32;
    [(t >> 16) as u8, (t >> 8) as u8, t as u8]
}

/// One outgoing stream: its bookkeeping, its pacer and the writer resends go to.
struct Stream {
    ssrc: u32,
    /// The negotiated id of the `abs-send-time` extension, if any.
    abs_send_time: Option<u8>,
    book: Mutex<Retransmissions>,
    /// The pacer, its rate cell (bits per second, 0: none) and the counters; `None`:
    /// pacing is off.
    pacer: Option<(Mutex<Pacer>, Arc<AtomicU64>, Arc<Pacing>)>,
    /// The pacer's clock (tokio's: the same as the system's, and paused in tests).
    epoch: tokio::time::Instant,
    next: Arc<dyn RTPWriter + Send + Sync>,
}

#[async_trait::async_trait]
impl RTPWriter for Stream {
    async fn write(&self, packet: &Packet, attributes: &Attributes) -> Result<usize> {
        if let Some((pacer, rate, pacing)) = &self.pacer {
            let bps = rate.load(Ordering::Relaxed) as f64;
            let now = self.epoch.elapsed().as_secs_f64();
            let wait = pacer.lock().unwrap_or_else(|p| p.into_inner()).reserve(size(packet), bps, now);
            if wait > 0.0 {
                pacing.count_wait(wait);
                tokio::time::sleep(Duration::from_secs_f64(wait)).await;
            }
        }
        self.book.lock().unwrap_or_else(|p| p.into_inner()).on_sent(packet, Instant::now());
        self.send(packet, attributes).await
    }
}

impl Stream {
    /// Writes a packet on, stamped with its send time where the viewer asked for it.
    async fn send(&self, packet: &Packet, attributes: &Attributes) -> Result<usize> {
        let Some(id) = self.abs_send_time else { return self.next.write(packet, attributes).await };
        let mut stamped = packet.clone();
        let time = abs_send_time(self.epoch.elapsed());
        // Only an id outside RFC 8285's range fails; the packet then leaves unstamped.
        if stamped.header.set_extension(id, bytes::Bytes::copy_from_slice(&time)).is_err() {
            return self.next.write(packet, attributes).await;
        }
        self.next.write(&stamped, attributes).await
    }
}

/// The interceptor: NACKs read from the receiver's RTCP are answered from [`Retransmissions`].
pub struct BoundedResponder {
    streams: Arc<Mutex<Vec<Arc<Stream>>>>,
    counters: Arc<RetransmitCounters>,
    pacing: Option<Arc<Pacing>>,
}

impl std::fmt::Debug for BoundedResponder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let streams = self.streams.lock().unwrap_or_else(|p| p.into_inner()).len();
        f.debug_struct("BoundedResponder").field("streams", &streams).finish()
    }
}

struct NackReader {
    parent: Arc<dyn RTCPReader + Send + Sync>,
    streams: Arc<Mutex<Vec<Arc<Stream>>>>,
    counters: Arc<RetransmitCounters>,
}

#[async_trait::async_trait]
impl RTCPReader for NackReader {
    async fn read(
        &self,
        buf: &mut [u8],
        attributes: &Attributes,
    ) -> Result<(Vec<Box<dyn webrtc::rtcp::packet::Packet + Send + Sync>>, Attributes)> {
        let (packets, attributes) = self.parent.read(buf, attributes).await?;
        for p in &packets {
            let Some(nack) = p.as_any().downcast_ref::<TransportLayerNack>() else { continue };
            let stream = self
                .streams
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .iter()
                .find(|s| s.ssrc == nack.media_ssrc)
                .cloned();
            let Some(stream) = stream else { continue };
            let now = Instant::now();
            let resend: Vec<Packet> = {
                let mut book = stream.book.lock().unwrap_or_else(|p| p.into_inner());
                let refused = book.refused;
                let resend: Vec<Packet> = nack
                    .nacks
                    .iter()
                    .flat_map(|pair| pair.into_iter())
                    .filter_map(|seq| book.on_nack(seq, now))
                    .collect();
                self.counters.refused.fetch_add(book.refused - refused, Ordering::Relaxed);
                resend
            };
            self.counters.resent.fetch_add(resend.len() as u64, Ordering::Relaxed);
            if !resend.is_empty() {
                tokio::spawn(async move {
                    for packet in resend {
                        if let Err(e) = stream.send(&packet, &Attributes::new()).await {
                            tracing::debug!("resending a NACKed packet: {e}");
                        }
                    }
                });
            }
        }
        Ok((packets, attributes))
    }
}

#[async_trait::async_trait]
impl Interceptor for BoundedResponder {
    async fn bind_rtcp_reader(&self, reader: Arc<dyn RTCPReader + Send + Sync>) -> Arc<dyn RTCPReader + Send + Sync> {
        Arc::new(NackReader {
            parent: reader,
            streams: Arc::clone(&self.streams),
            counters: Arc::clone(&self.counters),
        })
    }

    async fn bind_rtcp_writer(&self, writer: Arc<dyn RTCPWriter + Send + Sync>) -> Arc<dyn RTCPWriter + Send + Sync> {
        writer
    }

    async fn bind_local_stream(
        &self,
        info: &StreamInfo,
        writer: Arc<dyn RTPWriter + Send + Sync>,
    ) -> Arc<dyn RTPWriter + Send + Sync> {
        // NACKs are answered only for streams that negotiated plain NACK feedback.
        let nack = info.rtcp_feedback.iter().any(|fb| fb.typ == "nack" && fb.parameter.is_empty());
        let abs_send_time = info
            .rtp_header_extensions
            .iter()
            .find(|e| e.uri == webrtc::sdp::extmap::ABS_SEND_TIME_URI)
            .and_then(|e| u8::try_from(e.id).ok());
        tracing::debug!(
            ssrc = info.ssrc,
            nack,
            pacing = self.pacing.is_some(),
            ?abs_send_time,
            "outgoing stream bound"
        );
        if !nack && self.pacing.is_none() && abs_send_time.is_none() {
            return writer;
        }
        let pacer = self.pacing.as_ref().map(|p| (Mutex::default(), p.handle(info.ssrc), Arc::clone(p)));
        let stream = Arc::new(Stream {
            ssrc: info.ssrc,
            abs_send_time,
            book: Mutex::default(),
            pacer,
            epoch: tokio::time::Instant::now(),
            next: writer,
        });
        if nack {
            self.streams.lock().unwrap_or_else(|p| p.into_inner()).push(Arc::clone(&stream));
        }
        stream
    }

    async fn unbind_local_stream(&self, info: &StreamInfo) {
        self.streams.lock().unwrap_or_else(|p| p.into_inner()).retain(|s| s.ssrc != info.ssrc);
        if let Some(pacing) = &self.pacing {
            pacing.forget(info.ssrc);
        }
    }

    async fn bind_remote_stream(
        &self,
        _info: &StreamInfo,
        reader: Arc<dyn RTPReader + Send + Sync>,
    ) -> Arc<dyn RTPReader + Send + Sync> {
        reader
    }

    async fn unbind_remote_stream(&self, _info: &StreamInfo) {}

    async fn close(&self) -> Result<()> {
        self.streams.lock().unwrap_or_else(|p| p.into_inner()).clear();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;

    fn packet(sequence: u16, bytes: usize) -> Packet {
        let mut p = Packet { payload: Bytes::from(vec![0u8; bytes - 12]), ..Default::default() };
        p.header.sequence_number = sequence;
        p
    }

    #[test]
    fn send_times_are_6_18_fixed_point_seconds_modulo_64() {
        assert_eq!(abs_send_time(Duration::ZERO), [0, 0, 0]);
        assert_eq!(abs_send_time(Duration::from_secs(1)), [0x04, 0, 0], "1 s is 2^18");
        assert_eq!(abs_send_time(Duration::from_millis(250)), [0x01, 0, 0]);
        // One tick is 1 / 2^18 s, about 3.8 us; 63.999... s is the largest value, 64 s wraps.
        assert_eq!(abs_send_time(Duration::from_nanos(3_815)), [0, 0, 1]);
        assert_eq!(abs_send_time(Duration::from_secs(64)), [0, 0, 0]);
        assert_eq!(abs_send_time(Duration::from_secs(64) - Duration::from_nanos(1)), [0xFF, 0xFF, 0xFF]);
        assert_eq!(abs_send_time(Duration::from_secs(65)), abs_send_time(Duration::from_secs(1)));
        // A stamped header carries it as a one-byte extension that reads back.
        let mut p = packet(7, 100);
        p.header.set_extension(3, Bytes::copy_from_slice(&abs_send_time(Duration::from_secs(2)))).expect("stamp");
        assert_eq!(p.header.get_extension(3).as_deref(), Some(&[0x08u8, 0, 0][..]));
    }

    #[test]
    fn fresh_packets_are_resent_once_and_old_or_unknown_ones_never() {
        let mut r = Retransmissions::default();
        let t0 = Instant::now();
        for s in 0..10u16 {
            r.on_sent(&packet(s, 1000), t0);
        }
        let ms = |m: u64| t0 + Duration::from_millis(m);
        assert_eq!(r.on_nack(3, ms(50)).map(|p| p.header.sequence_number), Some(3));
        assert!(r.on_nack(3, ms(60)).is_none(), "a second NACK of the same packet");
        assert!(r.on_nack(42, ms(60)).is_none(), "never sent");
        assert!(r.on_nack(4, ms(500)).is_none(), "older than MAX_AGE");
        assert_eq!(r.refused, 3);
        // A slot reused by a later packet answers only for that one.
        r.on_sent(&packet(3 + SLOTS as u16, 1000), ms(600));
        assert!(r.on_nack(3, ms(610)).is_none());
        assert!(r.on_nack(3 + SLOTS as u16, ms(610)).is_some());
    }

    #[test]
    fn a_storm_of_nacks_is_held_to_a_quarter_of_the_stream() {
        let mut r = Retransmissions::default();
        let t0 = Instant::now();
        // A 1 Mbit/s stream of 1,000-byte packets (125 a second) for 3 s; the receiver NACKs
        // every packet every 10 ms: at most a quarter of the bytes (plus a packet) per second
        // come back.
        let (mut resent_bytes, mut sent_bytes) = (0usize, 0usize);
        for i in 0..375u16 {
            let now = t0 + Duration::from_millis(8 * u64::from(i));
            r.on_sent(&packet(i, 1000), now);
            sent_bytes += 1000;
            for seq in i.saturating_sub(40)..=i {
                resent_bytes += r.on_nack(seq, now).map_or(0, |p| size(&p));
            }
        }
        let seconds = 3.0;
        let limit = sent_bytes as f64 * BUDGET_SHARE + seconds * ALLOWANCE as f64;
        assert!(resent_bytes as f64 <= limit + 1000.0, "{resent_bytes} bytes resent against {sent_bytes} sent");
        assert!(resent_bytes > 0);
    }

    /// Records when each packet reached the next writer (tokio's clock).
    #[derive(Default)]
    struct Recorder {
        sent: Mutex<Vec<(u16, tokio::time::Instant)>>,
    }

    #[async_trait::async_trait]
    impl RTPWriter for Recorder {
        async fn write(&self, packet: &Packet, _attributes: &Attributes) -> Result<usize> {
            self.sent
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .push((packet.header.sequence_number, tokio::time::Instant::now()));
            Ok(size(packet))
        }
    }

    #[tokio::test(start_paused = true)]
    async fn the_writer_paces_at_the_rate_its_session_sets() {
        let pacing = Arc::new(Pacing::default());
        let builder = BoundedResponderBuilder { counters: Arc::default(), pacing: Some(Arc::clone(&pacing)) };
        let responder = builder.build("").expect("build");
        let recorder = Arc::new(Recorder::default());
        let nack = webrtc::interceptor::stream_info::RTCPFeedback { typ: "nack".into(), parameter: String::new() };
        let info = StreamInfo { ssrc: 42, rtcp_feedback: vec![nack], ..Default::default() };
        let writer =
            responder.bind_local_stream(&info, Arc::clone(&recorder) as Arc<dyn RTPWriter + Send + Sync>).await;
        let attributes = Attributes::new();
        // No rate set yet: nothing waits.
        let start = tokio::time::Instant::now();
        for seq in 0..30 {
            writer.write(&packet(seq, 1200), &attributes).await.expect("write");
        }
        assert_eq!(start.elapsed(), Duration::ZERO);
        // The session sets 1 Mbit/s; after a pause the 40-ms burst (5,000 bytes) leaves at
        // once, then one 1,200-byte packet every 9.6 ms.
        pacing.handle(42).store(1_000_000, Ordering::Relaxed);
        tokio::time::advance(Duration::from_secs(1)).await;
        let start = tokio::time::Instant::now();
        for seq in 100..120 {
            writer.write(&packet(seq, 1200), &attributes).await.expect("write");
        }
        let sent = recorder.sent.lock().unwrap_or_else(|p| p.into_inner()).clone();
        let paced: Vec<f64> = sent[30..].iter().map(|(_, at)| (*at - start).as_secs_f64()).collect();
        assert_eq!(sent.len(), 50);
        assert!(paced[..5].iter().all(|&t| t == 0.0), "{paced:?}");
        for (k, &t) in paced.iter().enumerate().skip(5) {
            // Tokio's timer has millisecond steps: within one of the schedule.
            let due = k as f64 * 0.0096 - 0.04;
            assert!(t >= due - 1e-9 && t <= due + 0.0011, "packet {k} at {t} s, due {due}");
        }
        assert_eq!(pacing.packets_delayed.load(Ordering::Relaxed), 15);
        // The stream's end drops its rate.
        responder.unbind_local_stream(&info).await;
        assert!(pacing.is_empty());
    }
}
