//! The stream's target bitrate from the receiver's feedback (issue 15, part 4, a first cut):
//! the loss-based controller of Google Congestion Control (draft-ietf-rmcat-gcc-02, section
//! 6) on the loss fraction of RTCP receiver reports, capped by the receiver's REMB estimate
//! (its delay-based estimate, when it sends one), between a floor and a ceiling.
//!
//! * loss above 10 %: `rate *= 1 - loss / 2` (at most once per 300 ms, so one burst of
//!   reports does not cut twice), and at most 1.5 times what got through,
//!   `rate * (1 - loss)` (GCC's cap at 1.5 times the incoming rate, section 5.5, with the
//!   receiver's loss standing in for its rate): a link far narrower than the stream (92 % lost)
//!   cuts a 921-kbit/s stream to 110 kbit/s in one report, where halving alone took five or
//!   six reports, seconds of a flooded queue;
//! * loss below 2 %: `rate *= 1.08` (at most once a second: GCC's 8 % per second), and
//!   faster while the link stays clean ([the climb back](#the-climb-back));
//! * in between: hold;
//! * a REMB caps the rate at the estimate (it expires after 5 s without a new one), until
//!   the receiver's own reports contradict it: once it has gone on getting more than twice
//!   the estimates ([`IMPLAUSIBLE_ESTIMATE_SHARE`] of what it gets, the target less the
//!   latest loss) for [`CONTRADICTED_AFTER_S`] with no report of 2 % loss or more, such low
//!   estimates are ignored and counted, until a higher estimate or a loss comes. GCC's
//!   delay-based decrease goes to 0.85 times the incoming rate, and the floor is where the
//!   stream goes anyway; Chromium sends estimates far below both: behind the lossy-link
//!   test's link its first REMB after a narrowing said 5 kbit/s (its estimator's minimum)
//!   and it climbed to 13 kbit/s in the next 40 s of a clean 20 Mbit/s link, with no loss
//!   reported, which held the stream at its floor for good. A believed estimate also holds
//!   the loss-based rate (GCC's `A_s = min(A_s, A_r)`), which grows from there afterwards;
//! * always within `[floor, ceiling]`;
//! * below the floor the frame rate falls: loss above 10 % while the rate sits at its floor
//!   doubles a frame divisor (the stream sends one frame in 2, 4 or 8; at most once a
//!   second), so that a link narrower than the floor is not flooded (its queue would drop
//!   the data channel's packets too); loss below 2 % halves it again (at most once a
//!   second) before the rate may grow.
//!
//! The divisor comes first on the way up because the picture of a frame at the floor
//! rate is already the coarsest worth sending; fewer such frames keep it.
//!
//! Before the frame rate, the resolution falls ([`RateController::with_resolution_levels`]):
//! a picture coded at too few bits per pixel breaks into blocks, and a quarter of the pixels
//! (half each side) at the same rate is the better picture (libwebrtc's degradation does
//! the same, down to 320x180). Level `L` codes `1 / 2^L` of each side:
//!
//! * down one level when the target gives the current level's picture fewer than
//!   [`SCALE_DOWN_BITS_PER_PIXEL`] bits per pixel (0.025: a quarter of the encoder's
//!   default 0.1; a 640x480 stream at 30 fps below 230 kbit/s);
//! * up one level when it would give the larger picture at least
//!   [`SCALE_UP_BITS_PER_PIXEL`] (twice the threshold down, so the two never alternate);
//! * at most once per [`SCALE_EVERY_S`] (each change re-creates the encoder, with an IDR);
//! * each level down divides the floor by four (the same bits per pixel as the full
//!   picture's floor), so that a link narrower than the full picture's floor gets a smaller
//!   picture before it gets fewer frames.
//!
//! # The climb back
//!
//! At 8 % a second a stream cut to its floor by a narrow link needs half a minute to come
//! back once the link widens (37.5 to 460 kbit/s, where a 640x480 picture returns, is 33 s).
//! So the step doubles with each clean second in a row, 8, 16, 32, 64 and then 100 % (the
//! rate doubles each second, a slow start's probe), and any report with 2 % or more of loss
//! starts it again at 8 %. Near the rate where the link last broke (within
//! [`CAREFUL_BELOW`]..[`CAREFUL_ABOVE`] times the rate before the latest cut, for
//! [`BREAK_MEMORY_S`] after it) the rate grows by 8 % only and a step from below stops at
//! the zone: a link at its capacity keeps GCC's gentle saw-tooth, while a link that has
//! widened, or an old break, gets the fast climb.
//!
//! Pure: the caller feeds [`Feedback`] with times in seconds and reads [`RateController::target_bps`].

/// What a receiver reported.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Feedback {
    /// Fraction of packets lost since the last report, `fraction_lost / 256` of RFC 3550.
    Loss(f64),
    /// The receiver's estimate of the bitrate it can take (REMB), bits per second.
    Estimate(f64),
}

/// Receiver reports are gathered until they speak for this many packets (libwebrtc's
/// loss-based estimate waits for 20 expected packets too) ...
pub const LOSS_WINDOW_PACKETS: u64 = 20;
/// ... or for this long, seconds (at least one packet).
pub const LOSS_WINDOW_S: f64 = 0.9;

/// The loss of the packets that receiver reports cover, gathered over several reports.
///
/// A report's own loss fraction speaks for the packets since the receiver's previous
/// report. Chromium sends one with every REMB, several a second (every 30-300 ms behind the
/// lossy-link test's link), each about a handful of packets: their fractions swing between
/// 0 and 50 % on a link that loses a steady quarter, and a report of no packets at all read
/// as a clean one (a step of the climb back). So the loss is counted from the reports'
/// cumulative counters (RFC 3550: the extended highest sequence number received and the
/// packets lost so far) and passed on once the reports since the last loss cover
/// [`LOSS_WINDOW_PACKETS`] packets, or [`LOSS_WINDOW_S`] and at least one packet (a slow
/// stream still gets about one loss a second). A receiver that reports once a second
/// (webrtc-rs, and so `nephele loadgen`) is read as before, one loss per report.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LossWindow {
    /// The last report's highest sequence number and cumulative loss.
    last: Option<(u32, u32)>,
    expected: u64,
    lost: u64,
    since: f64,
}

impl LossWindow {
    /// One report's counters, received at `now` (seconds); the loss fraction when the window
    /// is full. The first report only sets the counters' origin; a sequence number that
    /// goes back (a new stream) starts again.
    pub fn on_report(&mut self, highest_sequence: u32, total_lost: u32, now: f64) -> Option<f64> {
        // 24-bit two's complement: a negative count (more duplicates than losses) is none.
        let total_lost = if total_lost & 0x80_0000 != 0 { 0 } else { total_lost & 0xFF_FFFF };
        let Some((last_sequence, last_lost)) = self.last.replace((highest_sequence, total_lost)) else {
            self.since = now;
            return None;
        };
        let expected = highest_sequence.wrapping_sub(last_sequence);
        if expected > 1 << 24 {
            *self = LossWindow { last: self.last, since: now, ..LossWindow::default() };
            return None;
        }
        // The cumulative count is 24 bits and may fall (duplicates): a fall counts as none lost.
        let lost = total_lost.saturating_sub(last_lost).min(expected);
        self.expected += u64::from(expected);
        self.lost += u64::from(lost);
        let long_enough = now - self.since >= LOSS_WINDOW_S && self.expected > 0;
        if self.expected < LOSS_WINDOW_PACKETS && !long_enough {
            return None;
        }
        let fraction = self.lost as f64 / self.expected as f64;
        (self.expected, self.lost, self.since) = (0, 0, now);
        Some(fraction)
    }
}

/// Loss above which the rate is cut.
pub const HIGH_LOSS: f64 = 0.10;
/// Loss below which the rate may grow.
pub const LOW_LOSS: f64 = 0.02;
const INCREASE: f64 = 1.08;
/// The largest step of the climb back: the rate doubles in a clean second.
pub const MAX_INCREASE: f64 = 2.0;
/// The zone around the last break, as fractions of the rate before the cut, where the rate
/// grows by 8 % a second only.
pub const CAREFUL_BELOW: f64 = 0.9;
/// See [`CAREFUL_BELOW`].
pub const CAREFUL_ABOVE: f64 = 1.25;
/// How long a break is remembered, seconds.
pub const BREAK_MEMORY_S: f64 = 10.0;
const INCREASE_EVERY_S: f64 = 1.0;
/// How much earlier than its period a once-a-second step may come: receivers report about
/// every second, some a little under (webrtc-rs's reports arrived 0.9996 s apart now and then,
/// and every such report skipped its step: half the climb's seconds).
const REPORT_JITTER_S: f64 = 0.1;
const DECREASE_EVERY_S: f64 = 0.3;
/// After heavy loss, the rate is at most this many times what got through.
const RECEIVED_RATE_CAP: f64 = 1.5;
const ESTIMATE_LIFETIME_S: f64 = 5.0;
/// A receiver's estimate below this share of what it gets is contradicted by its own clean
/// reports (see the module header) ...
pub const IMPLAUSIBLE_ESTIMATE_SHARE: f64 = 0.5;
/// ... once they have said so for this long, seconds.
pub const CONTRADICTED_AFTER_S: f64 = 5.0;
/// The largest frame divisor: one frame in 8 (a 30-fps stream at about 4 fps).
pub const MAX_FRAME_DIVISOR: u32 = 8;
const DIVISOR_UP_EVERY_S: f64 = 1.0;
const DIVISOR_DOWN_EVERY_S: f64 = 1.0;
/// Bits per pixel and frame below which the picture's resolution falls one level.
pub const SCALE_DOWN_BITS_PER_PIXEL: f64 = 0.025;
/// Bits per pixel and frame the larger picture must get before the resolution rises a level.
pub const SCALE_UP_BITS_PER_PIXEL: f64 = 0.05;
/// Least time between two changes of resolution, seconds.
pub const SCALE_EVERY_S: f64 = 2.0;

#[derive(Debug, Clone, PartialEq)]
pub struct RateController {
    floor: f64,
    ceiling: f64,
    /// The loss-based rate.
    rate: f64,
    estimate: Option<(f64, f64)>,
    /// Estimates ignored as contradicted so far.
    ignored_estimates: u64,
    /// Since when the receiver has taken more than twice its estimates without loss.
    contradicted_since: Option<f64>,
    /// The latest loss fraction reported.
    last_loss: f64,
    last_increase: f64,
    last_decrease: f64,
    /// Increases in a row without a report of 2 % loss or more between them.
    clean_steps: u32,
    /// The rate before the latest cut, and when it was cut.
    broke: Option<(f64, f64)>,
    /// One frame in `divisor` is sent (1: all).
    divisor: u32,
    last_divisor_change: f64,
    /// The floor of the full picture (level 0).
    full_floor: f64,
    /// Pixels per second of the full picture (`None`: the resolution never falls).
    full_pixel_rate: Option<f64>,
    /// Deepest level allowed, and the current one.
    max_level: u32,
    level: u32,
    last_level_change: f64,
}

impl RateController {
    /// Starts at `start`, within `[floor, ceiling]` (`floor` is raised to at most `ceiling`).
    pub fn new(start_bps: f64, floor_bps: f64, ceiling_bps: f64) -> RateController {
        let ceiling = ceiling_bps.max(1.0);
        let floor = floor_bps.clamp(1.0, ceiling);
        RateController {
            floor,
            ceiling,
            rate: start_bps.clamp(floor, ceiling),
            estimate: None,
            ignored_estimates: 0,
            contradicted_since: None,
            last_loss: 0.0,
            last_increase: f64::NEG_INFINITY,
            last_decrease: f64::NEG_INFINITY,
            clean_steps: 0,
            broke: None,
            divisor: 1,
            last_divisor_change: f64::NEG_INFINITY,
            full_floor: floor,
            full_pixel_rate: None,
            max_level: 0,
            level: 0,
            last_level_change: f64::NEG_INFINITY,
        }
    }

    /// Lets the resolution fall down to `max_level` (each level half of each side) for a
    /// picture of `pixels` per frame at `fps` frames per second.
    pub fn with_resolution_levels(mut self, pixels: u64, fps: f64, max_level: u32) -> RateController {
        let rate = pixels as f64 * fps;
        if rate.is_finite() && rate > 0.0 {
            self.full_pixel_rate = Some(rate);
            self.max_level = max_level;
        }
        self
    }

    /// The resolution level to code at: each side `1 / 2^level` of the full picture's.
    pub fn resolution_level(&self) -> u32 {
        self.level
    }

    /// Moves the resolution level by the rules of the module's header at `now`; returns the
    /// previous level when it changed.
    pub fn update_resolution(&mut self, now: f64) -> Option<u32> {
        let full_rate = self.full_pixel_rate?;
        if now - self.last_level_change < SCALE_EVERY_S {
            return None;
        }
        let target = self.target_bps(now);
        let bits_per_pixel = |level: u32| target / (full_rate / 4f64.powi(level as i32));
        let from = self.level;
        if self.level < self.max_level && bits_per_pixel(self.level) < SCALE_DOWN_BITS_PER_PIXEL {
            self.level += 1;
        } else if self.level > 0 && bits_per_pixel(self.level - 1) >= SCALE_UP_BITS_PER_PIXEL {
            self.level -= 1;
        } else {
            return None;
        }
        self.last_level_change = now;
        self.floor = (self.full_floor / 4f64.powi(self.level as i32)).min(self.ceiling);
        self.rate = self.rate.clamp(self.floor, self.ceiling);
        Some(from)
    }

    /// Takes one report received at `now` (seconds). Non-finite or out-of-range values are
    /// ignored.
    pub fn on_feedback(&mut self, feedback: Feedback, now: f64) {
        match feedback {
            Feedback::Loss(loss) if (0.0..=1.0).contains(&loss) => {
                self.last_loss = loss;
                if loss >= LOW_LOSS {
                    self.clean_steps = 0;
                    self.contradicted_since = None;
                }
                let since_divisor = now - self.last_divisor_change;
                if loss > HIGH_LOSS && self.rate <= self.floor {
                    if since_divisor >= DIVISOR_UP_EVERY_S - REPORT_JITTER_S && self.divisor < MAX_FRAME_DIVISOR {
                        self.divisor *= 2;
                        self.last_divisor_change = now;
                    }
                } else if loss < LOW_LOSS && self.divisor > 1 {
                    if since_divisor >= DIVISOR_DOWN_EVERY_S - REPORT_JITTER_S {
                        self.divisor /= 2;
                        self.last_divisor_change = now;
                    }
                    // The rate grows only once every frame is sent again.
                    return;
                }
                if loss > HIGH_LOSS {
                    if now - self.last_decrease >= DECREASE_EVERY_S {
                        if self.rate > self.floor {
                            self.broke = Some((self.rate, now));
                        }
                        self.rate = (self.rate * (1.0 - loss / 2.0)).min(RECEIVED_RATE_CAP * self.rate * (1.0 - loss));
                        self.last_decrease = now;
                    }
                } else if loss < LOW_LOSS && now - self.last_increase >= INCREASE_EVERY_S - REPORT_JITTER_S {
                    self.grow(now);
                    self.last_increase = now;
                }
                self.rate = self.rate.clamp(self.floor, self.ceiling);
            }
            Feedback::Estimate(bps) if bps.is_finite() && bps > 0.0 => {
                let received = self.target_bps(now) * (1.0 - self.last_loss);
                if bps >= IMPLAUSIBLE_ESTIMATE_SHARE * received {
                    self.contradicted_since = None;
                } else if now - *self.contradicted_since.get_or_insert(now) >= CONTRADICTED_AFTER_S {
                    self.ignored_estimates += 1;
                    self.estimate = None;
                    return;
                }
                self.estimate = Some((bps, now));
                // GCC's loss-based rate is itself held at the receiver's estimate, so that it
                // grows from there once the estimate goes stale or is no longer believed.
                self.rate = self.rate.min(bps).clamp(self.floor, self.ceiling);
            }
            _ => {}
        }
    }

    /// One clean second's increase (the module header's climb back).
    fn grow(&mut self, now: f64) {
        let broke_at = self.broke.filter(|&(_, at)| now - at <= BREAK_MEMORY_S).map(|(rate, _)| rate);
        if broke_at.is_some_and(|b| (CAREFUL_BELOW * b..CAREFUL_ABOVE * b).contains(&self.rate)) {
            self.rate *= INCREASE;
            self.clean_steps = 0;
            return;
        }
        let step = (INCREASE - 1.0) * 2f64.powi(self.clean_steps.min(8) as i32);
        let mut next = self.rate * (1.0 + step).min(MAX_INCREASE);
        if let Some(b) = broke_at.filter(|&b| self.rate < CAREFUL_BELOW * b) {
            next = next.min(CAREFUL_BELOW * b).max(self.rate * INCREASE);
        }
        self.rate = next;
        self.clean_steps += 1;
    }

    /// Receiver estimates ignored so far as contradicted by the receiver's reports (below
    /// [`IMPLAUSIBLE_ESTIMATE_SHARE`] of what it gets, for [`CONTRADICTED_AFTER_S`]).
    pub fn ignored_estimates(&self) -> u64 {
        self.ignored_estimates
    }

    /// The stream sends one frame in this many (1: every frame).
    pub fn frame_divisor(&self) -> u32 {
        self.divisor
    }

    /// The bitrate to encode at, at `now`.
    pub fn target_bps(&self, now: f64) -> f64 {
        let cap = match self.estimate {
            Some((bps, at)) if now - at <= ESTIMATE_LIFETIME_S => bps,
            _ => f64::INFINITY,
        };
        self.rate.min(cap).clamp(self.floor, self.ceiling)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heavy_loss_cuts_light_loss_grows_and_the_bounds_hold() {
        let mut c = RateController::new(4e6, 0.5e6, 4e6);
        // No loss at the ceiling: stays there.
        c.on_feedback(Feedback::Loss(0.0), 0.0);
        assert_eq!(c.target_bps(0.0), 4e6);
        // 20 % loss: cut by 10 %, but not twice within 300 ms.
        c.on_feedback(Feedback::Loss(0.2), 1.0);
        assert!((c.target_bps(1.0) - 3.6e6).abs() < 1.0);
        c.on_feedback(Feedback::Loss(0.2), 1.1);
        assert!((c.target_bps(1.1) - 3.6e6).abs() < 1.0);
        c.on_feedback(Feedback::Loss(0.2), 1.4);
        assert!((c.target_bps(1.4) - 3.24e6).abs() < 1.0);
        // Above 50 % the cut goes to 1.5 times what got through: 92 % lost at 921.6 kbit/s
        // leaves 110.6 kbit/s, not 497.
        let mut flooded = RateController::new(921_600.0, 1e4, 921_600.0);
        flooded.on_feedback(Feedback::Loss(0.92), 0.0);
        assert!((flooded.target_bps(0.0) - 1.5 * 0.08 * 921_600.0).abs() < 1.0, "{}", flooded.target_bps(0.0));
        // 5 %: hold.
        c.on_feedback(Feedback::Loss(0.05), 3.0);
        assert!((c.target_bps(3.0) - 3.24e6).abs() < 1.0);
        // Clean: 8 % a second at most.
        c.on_feedback(Feedback::Loss(0.0), 3.5);
        c.on_feedback(Feedback::Loss(0.0), 3.9);
        assert!((c.target_bps(3.9) - 3.24e6 * 1.08).abs() < 1.0);
        // A collapse stops at the floor; recovery stops at the ceiling.
        for i in 0..100 {
            c.on_feedback(Feedback::Loss(0.9), 10.0 + f64::from(i));
        }
        assert_eq!(c.target_bps(200.0), 0.5e6);
        for i in 0..100 {
            c.on_feedback(Feedback::Loss(0.0), 300.0 + f64::from(i));
        }
        assert_eq!(c.target_bps(500.0), 4e6);
    }

    #[test]
    fn below_the_floor_the_frame_rate_falls_and_comes_back_first() {
        let mut c = RateController::new(1e6, 0.5e6, 1e6);
        // Heavy loss: the rate falls to the floor first; the divisor stays 1 meanwhile.
        let mut t = 0.0;
        while c.target_bps(t) > 0.5e6 {
            c.on_feedback(Feedback::Loss(0.5), t);
            assert_eq!(c.frame_divisor(), 1);
            t += 0.5;
        }
        // At the floor, still losing: 2, 4, 8, at most once a second, never beyond 8.
        c.on_feedback(Feedback::Loss(0.5), t + 0.5);
        assert_eq!(c.frame_divisor(), 2);
        c.on_feedback(Feedback::Loss(0.5), t + 1.0);
        assert_eq!(c.frame_divisor(), 2, "not twice within a second");
        for k in 2..10 {
            c.on_feedback(Feedback::Loss(0.5), t + f64::from(k));
        }
        assert_eq!(c.frame_divisor(), MAX_FRAME_DIVISOR);
        // Moderate loss holds; clean reports halve it once a second at most, and the rate
        // stays at the floor until every frame is sent again.
        t += 20.0;
        c.on_feedback(Feedback::Loss(0.05), t);
        assert_eq!(c.frame_divisor(), 8);
        for (k, want) in [(0.0, 4), (0.5, 4), (1.0, 2), (2.0, 1)] {
            c.on_feedback(Feedback::Loss(0.0), t + k);
            assert_eq!(c.frame_divisor(), want, "at +{k} s");
            assert_eq!(c.target_bps(t + k), 0.5e6);
        }
        c.on_feedback(Feedback::Loss(0.0), t + 3.0);
        assert!(c.target_bps(t + 3.0) > 0.5e6, "then the rate grows");
    }

    #[test]
    fn the_resolution_falls_before_the_frame_rate_and_rises_last() {
        // A 640x480 stream at 30 fps: the encoder's default ceiling (0.1 bit per pixel) and
        // the media thread's floor; one level (320x240) allowed.
        let (pixels, fps) = (640u32 * 480, 30.0);
        let full_rate = f64::from(pixels) * fps;
        let mut c = RateController::new(921_600.0, 150_000.0, 921_600.0).with_resolution_levels(pixels.into(), fps, 1);
        assert_eq!((c.resolution_level(), c.update_resolution(0.0)), (0, None), "the ceiling needs no fall");
        // Heavy loss: the rate falls; the level drops as soon as the picture gets fewer than
        // 0.025 bits per pixel, while every frame is still sent.
        let mut t = 0.0;
        let mut fell_at = None;
        while t < 60.0 && c.frame_divisor() == 1 {
            c.on_feedback(Feedback::Loss(0.3), t);
            if let Some(from) = c.update_resolution(t) {
                assert_eq!((from, c.resolution_level()), (0, 1));
                assert!(fell_at.is_none(), "one level allowed, one fall");
                assert!(c.target_bps(t) < SCALE_DOWN_BITS_PER_PIXEL * full_rate);
                fell_at = Some(t);
            }
            t += 0.1;
        }
        let fell_at = fell_at.expect("the resolution fell");
        assert_eq!(c.resolution_level(), 1);
        // The frame rate fell only at the lowered floor: a quarter of the full picture's.
        assert_eq!(c.frame_divisor(), 2);
        assert!((c.target_bps(t) - 150_000.0 / 4.0).abs() < 1.0, "floor {}", c.target_bps(t));
        assert!(t > fell_at);
        // Clean reports: the divisor comes back first, then the rate grows, and the level
        // rises only once the full picture would get 0.05 bits per pixel; no flapping.
        let mut rose_at = None;
        let mut changes = 0;
        for _ in 0..1200 {
            t += 0.1;
            c.on_feedback(Feedback::Loss(0.0), t);
            if c.update_resolution(t).is_some() {
                changes += 1;
                assert_eq!(c.frame_divisor(), 1);
                assert!(c.target_bps(t) >= SCALE_UP_BITS_PER_PIXEL * full_rate);
                rose_at.get_or_insert(t);
            }
        }
        assert_eq!((c.resolution_level(), changes), (0, 1));
        assert!(rose_at.is_some());
        // A rate held below the threshold down falls once, and then stays: the full picture
        // would get under 0.05 bits per pixel.
        let mut held =
            RateController::new(200_000.0, 150_000.0, 200_000.0).with_resolution_levels(pixels.into(), fps, 1);
        for k in 0..50 {
            assert_eq!(held.update_resolution(f64::from(k)), if k == 0 { Some(0) } else { None });
        }
        // Without levels, or with level 0 the deepest, it never moves.
        let mut plain = RateController::new(150_000.0, 150_000.0, 921_600.0);
        let mut zero = plain.clone().with_resolution_levels(pixels.into(), fps, 0);
        assert_eq!((plain.update_resolution(10.0), zero.update_resolution(10.0)), (None, None));
        // A degenerate picture leaves it off.
        let mut empty = plain.clone().with_resolution_levels(0, fps, 2);
        assert_eq!(empty.update_resolution(10.0), None);
    }

    /// The rate after each of `n` clean reports from `t`, as ratios to the one before; the
    /// reports come a little under a second apart, as a receiver's do now and then.
    fn clean_steps(c: &mut RateController, t: &mut f64, n: usize) -> Vec<f64> {
        (0..n)
            .map(|_| {
                let before = c.target_bps(*t);
                *t += 0.9996;
                c.on_feedback(Feedback::Loss(0.0), *t);
                c.target_bps(*t) / before
            })
            .collect()
    }

    #[test]
    fn the_rate_climbs_back_fast_on_a_clean_link_and_gently_where_it_broke() {
        let close = |got: &[f64], want: &[f64]| {
            got.len() == want.len() && got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-9)
        };
        // A clean link far from any break: 8, 16, 32, 64 %, then the rate doubles each second.
        let mut c = RateController::new(1e4, 1e4, 1e9);
        let mut t = 0.0;
        let steps = clean_steps(&mut c, &mut t, 7);
        assert!(close(&steps, &[1.08, 1.16, 1.32, 1.64, 2.0, 2.0, 2.0]), "{steps:?}");
        // One report of 2 % loss or more starts the climb again at 8 %; a clean report within
        // the second adds nothing.
        c.on_feedback(Feedback::Loss(0.05), t + 0.5);
        c.on_feedback(Feedback::Loss(0.0), t + 0.7);
        let steps = clean_steps(&mut c, &mut t, 3);
        assert!(close(&steps, &[1.08, 1.16, 1.32]), "{steps:?}");

        // A link at its capacity: 40 % loss at 1 Mbit/s cuts to 0.8 Mbit/s. Below the zone the
        // climb stops at its edge (0.9 Mbit/s) or takes one 8 % step; inside the zone (0.9 to
        // 1.25 Mbit/s) 8 % a second; past it, the fast climb again.
        let mut c = RateController::new(1e6, 1e5, 1e8);
        c.on_feedback(Feedback::Loss(0.4), 0.0);
        assert!((c.target_bps(0.0) - 0.8e6).abs() < 1e-3);
        let mut t = 0.0;
        let steps = clean_steps(&mut c, &mut t, 8);
        assert!(close(&steps, &[1.08, 1.08, 1.08, 1.08, 1.08, 1.08, 1.08, 1.16]), "{steps:?}");
        // Seven steps of 8 % (0.8 * 1.08^6 = 1.269 Mbit/s is past the zone), then 16 %.
        assert!(c.target_bps(t) > CAREFUL_ABOVE * 1e6);
        // The same cut, remembered no longer than BREAK_MEMORY_S: a hold of 11 s (5 % loss)
        // and then the fast climb through the old zone.
        let mut c = RateController::new(1e6, 1e5, 1e8);
        c.on_feedback(Feedback::Loss(0.4), 0.0);
        let mut t = 0.0;
        while t < BREAK_MEMORY_S + 1.0 {
            t += 0.5;
            c.on_feedback(Feedback::Loss(0.05), t);
        }
        let steps = clean_steps(&mut c, &mut t, 3);
        assert!(close(&steps, &[1.08, 1.16, 1.32]), "{steps:?}");
    }

    #[test]
    fn after_a_narrow_link_the_full_picture_returns_within_seconds() {
        // The lossy-link test's stream (640x480 at 30 fps, floor 150 kbit/s, one level): a
        // narrow link brings it to 320x240 at 37.5 kbit/s and one frame in 8.
        let (pixels, fps) = (640u64 * 480, 30.0);
        let mut c = RateController::new(921_600.0, 150_000.0, 921_600.0).with_resolution_levels(pixels, fps, 1);
        let mut t = 0.0;
        while t < 15.0 {
            c.on_feedback(Feedback::Loss(0.3), t);
            c.update_resolution(t);
            t += 0.25;
        }
        assert_eq!((c.resolution_level(), c.frame_divisor()), (1, MAX_FRAME_DIVISOR));
        // A wide, clean link with a report about every second: every frame again after 3 s,
        // then the climb; 640x480 back once the full picture gets 0.05 bits per pixel
        // (461 kbit/s).
        let wide = t;
        let mut back = None;
        while t < wide + 60.0 && back.is_none() {
            t += 0.9996;
            c.on_feedback(Feedback::Loss(0.0), t);
            if c.update_resolution(t) == Some(1) {
                back = Some(t - wide);
            }
        }
        let back = back.expect("the full picture came back");
        // With 8 % a second the climb alone from 37.5 to 461 kbit/s takes
        // ln(12.3) / ln(1.08) = 33 s.
        assert!(back < 12.0, "640x480 came back after {back} s");
        let mut later = t;
        clean_steps(&mut c, &mut later, 3);
        assert_eq!(c.target_bps(later), 921_600.0, "and the rate reaches its ceiling");
    }

    #[test]
    fn an_estimate_caps_the_rate_until_it_goes_stale() {
        let mut c = RateController::new(4e6, 0.3e6, 4e6);
        c.on_feedback(Feedback::Estimate(1.5e6), 0.0);
        assert_eq!(c.target_bps(1.0), 1.5e6);
        c.on_feedback(Feedback::Estimate(0.1e6), 2.0);
        assert_eq!(c.target_bps(2.0), 0.3e6, "never below the floor");
        assert_eq!(c.target_bps(7.5), 0.3e6, "a stale estimate leaves the rate where it held it");
        c.on_feedback(Feedback::Loss(0.0), 8.0);
        assert!(c.target_bps(8.0) > 0.3e6, "which grows from there on clean reports");
        assert_eq!(c.ignored_estimates(), 0);
    }

    #[test]
    fn an_estimate_the_receivers_clean_reports_contradict_is_ignored_after_a_while() {
        let mut c = RateController::new(921_600.0, 150_000.0, 921_600.0);
        // Chromium's REMB after the link narrowed, its estimator's 5 kbit/s minimum: believed
        // at first (the rate goes to its floor).
        let mut t = 0.0;
        c.on_feedback(Feedback::Loss(0.0), t);
        c.on_feedback(Feedback::Estimate(5_000.0), t);
        assert_eq!((c.target_bps(t), c.ignored_estimates()), (150_000.0, 0));
        // It goes on at 5-13 kbit/s while the receiver takes the 150-kbit/s floor without
        // loss: after 5 s of that it is ignored, and the rate is what the loss reports allow.
        while t < 4.5 {
            t += 0.5;
            c.on_feedback(Feedback::Loss(0.0), t);
            c.on_feedback(Feedback::Estimate(13_000.0), t);
            assert_eq!((c.target_bps(t), c.ignored_estimates()), (150_000.0, 0), "at {t} s");
        }
        t = 5.0;
        c.on_feedback(Feedback::Loss(0.0), t);
        c.on_feedback(Feedback::Estimate(13_000.0), t);
        assert_eq!(c.ignored_estimates(), 1);
        for _ in 0..8 {
            t += 1.0;
            c.on_feedback(Feedback::Loss(0.0), t);
            c.on_feedback(Feedback::Estimate(13_000.0), t);
        }
        assert_eq!((c.target_bps(t), c.ignored_estimates()), (921_600.0, 9), "the climb back, from the floor");
        // A report of loss makes the next low estimate believed again, for another 5 s.
        c.on_feedback(Feedback::Loss(0.05), t);
        c.on_feedback(Feedback::Estimate(13_000.0), t);
        assert_eq!((c.target_bps(t), c.ignored_estimates()), (150_000.0, 9));
        c.on_feedback(Feedback::Estimate(13_000.0), t + 4.9);
        assert_eq!((c.target_bps(t + 4.9), c.ignored_estimates()), (150_000.0, 9));
        c.on_feedback(Feedback::Estimate(13_000.0), t + 5.0);
        assert_eq!(c.ignored_estimates(), 10);
        // An estimate within half of what the receiver gets is believed and restarts the clock
        // (84 % lost: 0.85 times the 16 % that arrives is GCC's own decrease).
        let mut d = RateController::new(921_600.0, 150_000.0, 921_600.0);
        d.on_feedback(Feedback::Loss(0.84), 0.0);
        d.on_feedback(Feedback::Estimate(0.85 * 0.16 * 921_600.0), 0.0);
        assert_eq!((d.target_bps(0.0), d.ignored_estimates()), (150_000.0, 0), "held at the floor");
        d.on_feedback(Feedback::Estimate(100_000.0), 20.0);
        assert_eq!(d.ignored_estimates(), 0);
    }

    #[test]
    fn loss_is_counted_over_reports_that_cover_enough_packets() {
        let mut w = LossWindow::default();
        assert_eq!(w.on_report(1000, 0, 0.0), None, "the first report sets the origin");
        // Chromium's reports, a few packets each: nothing until 20 packets are covered.
        assert_eq!(w.on_report(1005, 2, 0.1), None);
        assert_eq!(w.on_report(1005, 2, 0.2), None, "a report of no packets is no clean report");
        assert_eq!(w.on_report(1012, 3, 0.3), None);
        assert_eq!(w.on_report(1020, 5, 0.4), Some(5.0 / 20.0));
        // A slow stream: 3 packets in 0.95 s still give a loss.
        assert_eq!(w.on_report(1021, 5, 0.6), None);
        assert_eq!(w.on_report(1023, 6, 1.35), Some(1.0 / 3.0));
        // But time alone, without packets, gives none.
        assert_eq!(w.on_report(1023, 6, 5.0), None);
        // A report a second at 30 fps (webrtc-rs): one loss per report, as its own fraction.
        assert_eq!(w.on_report(1063, 6, 6.0), Some(0.0));
        assert_eq!(w.on_report(1103, 10, 7.0), Some(0.1));
        // Sequence numbers across the 16-bit wrap (extended numbers go on counting).
        let mut w = LossWindow::default();
        w.on_report(65_530, 0, 0.0);
        assert_eq!(w.on_report(65_560, 3, 0.5), Some(0.1));
        // A cumulative loss that falls (duplicates) counts as none; more lost than expected
        // is capped; a sequence number that goes back restarts the window.
        assert_eq!(w.on_report(65_600, 1, 1.0), Some(0.0));
        assert_eq!(w.on_report(65_620, 500, 1.5), Some(1.0));
        assert_eq!(w.on_report(10, 500, 2.0), None);
        assert_eq!(w.on_report(40, 503, 2.5), Some(0.1));
        // A negative cumulative count (24-bit two's complement) is none lost.
        assert_eq!(w.on_report(80, 0xFF_FFFE, 3.0), Some(0.0));
    }

    #[test]
    fn garbage_feedback_changes_nothing() {
        let mut c = RateController::new(2e6, 1e5, 4e6);
        for f in [Feedback::Loss(f64::NAN), Feedback::Loss(-0.1), Feedback::Loss(1.5), Feedback::Estimate(f64::NAN)] {
            c.on_feedback(f, 0.0);
        }
        c.on_feedback(Feedback::Estimate(-5.0), 0.0);
        c.on_feedback(Feedback::Estimate(f64::INFINITY), 0.0);
        assert_eq!(c.target_bps(0.0), 2e6);
        // Bounds given upside down still make a usable controller.
        assert_eq!(RateController::new(5e6, 9e6, 1e6).target_bps(0.0), 1e6);
    }
}
