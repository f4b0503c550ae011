//! Pacing of the outgoing video (issue 15, part 4): the packets of a frame leave no faster
//! than a pacing rate, `PACING_FACTOR` times the encoder's target bitrate (WebRTC's pacer,
//! libwebrtc `PacingController`, paces at 2.5 times the estimate), after a burst of up to
//! [`BURST`] at that rate.
//!
//! Why: an encoder hands over a frame at once, and a keyframe is ten or more times an
//! ordinary frame. Written to the socket in one go, its packets arrive at the bottleneck of a
//! real network as one burst; a router queue shorter than the burst drops its tail, the
//! receiver asks for the lost packets or a new keyframe, and the next keyframe bursts again.
//! Spread at 2.5 times the target rate, a stream whose target sits below the link's capacity
//! never fills the queue. The burst allowance lets an ordinary frame (a few packets) leave at
//! once, so pacing costs latency only on frames larger than about 40 ms of the pacing rate.
//!
//! On unless turned off (`RtcConfig::pacing`, `nephele composer --no-pacing`).
//!
//! Pure: [`Pacer::reserve`] takes the packet's size, the rate and the time on the caller's
//! clock and answers how long the packet must wait; [`Pacing`] carries the rate from a
//! session's media thread to its stream in the interceptor chain, and counts.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Pacing rate over the encoder's target bitrate (libwebrtc's `kDefaultPaceMultiplier`).
pub const PACING_FACTOR: f64 = 2.5;
/// What may leave at once after a pause, as time at the pacing rate (libwebrtc's send
/// burst interval).
pub const BURST: Duration = Duration::from_millis(40);
/// The longest a packet waits: a frame too large for the pacing rate (a keyframe after the
/// rate fell) leaves at most this late, the rest of it at once, rather than holding every
/// later frame behind it.
pub const MAX_DELAY: Duration = Duration::from_millis(250);

/// A leaky bucket over the outgoing packets of one stream.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pacer {
    /// When the paced link would be free for the next packet, seconds on the caller's clock
    /// (`None` before the first packet).
    next_free: Option<f64>,
}

impl Pacer {
    /// Reserves the paced link for a packet of `bytes` asked to leave at `now` (seconds)
    /// at `rate_bps`, and returns how long it must wait first (seconds, 0: at once). A rate
    /// that is not positive and finite paces nothing; a non-finite `now` waits for nothing.
    pub fn reserve(&mut self, bytes: usize, rate_bps: f64, now: f64) -> f64 {
        if !(rate_bps.is_finite() && rate_bps > 0.0 && now.is_finite()) {
            return 0.0;
        }
        // Unused time at the pacing rate counts only up to the burst.
        let credit_from = now - BURST.as_secs_f64();
        let start = self.next_free.map_or(credit_from, |free| free.max(credit_from));
        let start = start.min(now + MAX_DELAY.as_secs_f64());
        self.next_free = Some(start + bytes as f64 * 8.0 / rate_bps);
        (start - now).max(0.0)
    }
}

/// The pacing rate of each outgoing stream (by SSRC), bits per second, 0 for none: set by
/// the session's media thread from the encoder's target, read by the stream's writer in the
/// interceptor chain (whichever comes first makes the entry); and what pacing did, over
/// every stream.
#[derive(Debug, Default)]
pub struct Pacing {
    by_ssrc: Mutex<HashMap<u32, Arc<AtomicU64>>>,
    /// Packets that waited, and their summed wait in microseconds.
    pub packets_delayed: AtomicU64,
    pub delay_us: AtomicU64,
}

impl Pacing {
    /// Counts a packet that waited `seconds`.
    pub fn count_wait(&self, seconds: f64) {
        self.packets_delayed.fetch_add(1, Ordering::Relaxed);
        self.delay_us.fetch_add((seconds * 1e6) as u64, Ordering::Relaxed);
    }

    /// The rate cell of the stream `ssrc`.
    pub fn handle(&self, ssrc: u32) -> Arc<AtomicU64> {
        Arc::clone(self.by_ssrc.lock().unwrap_or_else(|p| p.into_inner()).entry(ssrc).or_default())
    }

    /// Drops the entry of a stream that ended (its holders keep their cell).
    pub fn forget(&self, ssrc: u32) {
        self.by_ssrc.lock().unwrap_or_else(|p| p.into_inner()).remove(&ssrc);
    }

    /// Streams with an entry.
    pub fn len(&self) -> usize {
        self.by_ssrc.lock().unwrap_or_else(|p| p.into_inner()).len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const MBIT: f64 = 1e6;

    /// Departure times of packets of `sizes` all asked to leave at `now`.
    fn departures(pacer: &mut Pacer, sizes: &[usize], rate: f64, now: f64) -> Vec<f64> {
        sizes.iter().map(|&s| now + pacer.reserve(s, rate, now)).collect()
    }

    #[test]
    fn an_ordinary_frame_leaves_at_once_and_a_keyframe_is_spread_at_the_rate() {
        let mut pacer = Pacer::default();
        // 2.5 Mbit/s: 40 ms of burst is 12,500 bytes; a 4-packet frame of 4,800 bytes fits.
        let rate = 2.5 * MBIT;
        assert!(departures(&mut pacer, &[1200; 4], rate, 10.0).iter().all(|&t| t == 10.0));
        // A second later the burst is back; a 60,000-byte keyframe (50 packets): the first
        // 12,500 bytes (the burst, plus the packet that starts inside it) at once, the rest
        // at 2.5 Mbit/s, so the last leaves 60,000 * 8 / 2.5e6 - 0.04 = 152 ms later.
        let t = departures(&mut pacer, &[1200; 50], rate, 11.0);
        assert!(t[..11].iter().all(|&d| d == 11.0), "{t:?}");
        assert!(t[11] > 11.0);
        let last = t[49] - 11.0;
        assert!((last - (49.0 * 1200.0 * 8.0 / rate - 0.04)).abs() < 1e-9, "{last}");
        for pair in t[11..].windows(2) {
            assert!((pair[1] - pair[0] - 1200.0 * 8.0 / rate).abs() < 1e-9, "{pair:?}");
        }
    }

    #[test]
    fn no_rate_paces_nothing_and_a_huge_frame_waits_at_most_the_cap() {
        let mut pacer = Pacer::default();
        for rate in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(pacer.reserve(1_000_000, rate, 1.0), 0.0);
        }
        assert_eq!(pacer.reserve(1200, MBIT, f64::NAN), 0.0);
        // 1 MB at 1 Mbit/s would take 8 s: no packet waits more than MAX_DELAY.
        let t = departures(&mut pacer, &[1200; 834], MBIT, 5.0);
        let cap = MAX_DELAY.as_secs_f64();
        assert!(t.iter().all(|&d| d - 5.0 <= cap + 1e-12));
        assert!((t[833] - 5.0 - cap).abs() < 1e-12);
    }

    proptest! {
        /// Packets asked at random times leave in order, never before they are asked, and
        /// in any window no more than the burst, one packet and the rate times the window's
        /// length (while no packet meets the cap).
        #[test]
        fn departures_keep_order_and_the_rate(
            gaps in proptest::collection::vec((0.0f64..0.05, 60usize..1300), 1..200),
            rate in 0.2e6f64..20e6,
        ) {
            let mut pacer = Pacer::default();
            let mut now = 100.0;
            let mut sent: Vec<(f64, usize)> = Vec::new();
            for (gap, size) in gaps {
                now += gap;
                let wait = pacer.reserve(size, rate, now);
                prop_assert!(wait >= 0.0);
                if wait >= MAX_DELAY.as_secs_f64() - 1e-9 {
                    return Ok(());
                }
                let at = now + wait;
                if let Some(&(last, _)) = sent.last() {
                    prop_assert!(at >= last - 1e-12);
                }
                sent.push((at, size));
            }
            let burst = BURST.as_secs_f64() * rate / 8.0;
            for i in 0..sent.len() {
                let mut bytes = 0.0;
                for j in i..sent.len() {
                    bytes += sent[j].1 as f64;
                    let window = sent[j].0 - sent[i].0;
                    prop_assert!(bytes <= burst + 1300.0 + window * rate / 8.0 + 1e-6, "{bytes} bytes in {window} s");
                }
            }
        }
    }

    #[test]
    fn rates_are_shared_by_ssrc_and_forgotten() {
        let rates = Pacing::default();
        let a = rates.handle(7);
        a.store(2_000_000, Ordering::Relaxed);
        assert_eq!(rates.handle(7).load(Ordering::Relaxed), 2_000_000);
        assert_eq!(rates.handle(8).load(Ordering::Relaxed), 0);
        assert_eq!(rates.len(), 2);
        rates.forget(7);
        rates.forget(8);
        assert!(rates.is_empty());
        assert_eq!(a.load(Ordering::Relaxed), 2_000_000);
    }
}
