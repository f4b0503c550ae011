//! The stream's target bitrate from the receiver's feedback (issue 15, part 4, a first cut):
//! the loss-based controller of Google Congestion Control (draft-ietf-rmcat-gcc-02, section
//! 6) on the loss fraction of RTCP receiver reports, capped by the receiver's REMB estimate
//! (its delay-based estimate, when it sends one), between a floor and a ceiling.
//!
//! * loss above 10 %: `rate *= 1 - loss / 2` (at most once per 300 ms, so one burst of
//!   reports does not cut twice);
//! * loss below 2 %: `rate *= 1.08` (at most once a second: GCC's 8 % per second);
//! * in between: hold;
//! * a REMB caps the rate at the estimate (it expires after 5 s without a new one);
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
//! Pure: the caller feeds [`Feedback`] with times in seconds and reads [`RateController::target_bps`].

/// What a receiver reported.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Feedback {
    /// Fraction of packets lost since the last report, `fraction_lost / 256` of RFC 3550.
    Loss(f64),
    /// The receiver's estimate of the bitrate it can take (REMB), bits per second.
    Estimate(f64),
}

/// Loss above which the rate is cut.
pub const HIGH_LOSS: f64 = 0.10;
/// Loss below which the rate may grow.
pub const LOW_LOSS: f64 = 0.02;
const INCREASE: f64 = 1.08;
const INCREASE_EVERY_S: f64 = 1.0;
const DECREASE_EVERY_S: f64 = 0.3;
const ESTIMATE_LIFETIME_S: f64 = 5.0;
/// The largest frame divisor: one frame in 8 (a 30-fps stream at about 4 fps).
pub const MAX_FRAME_DIVISOR: u32 = 8;
const DIVISOR_UP_EVERY_S: f64 = 1.0;
const DIVISOR_DOWN_EVERY_S: f64 = 1.0;

#[derive(Debug, Clone, PartialEq)]
pub struct RateController {
    floor: f64,
    ceiling: f64,
    /// The loss-based rate.
    rate: f64,
    estimate: Option<(f64, f64)>,
    last_increase: f64,
    last_decrease: f64,
    /// One frame in `divisor` is sent (1: all).
    divisor: u32,
    last_divisor_change: f64,
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
            last_increase: f64::NEG_INFINITY,
            last_decrease: f64::NEG_INFINITY,
            divisor: 1,
            last_divisor_change: f64::NEG_INFINITY,
        }
    }

    /// Takes one report received at `now` (seconds). Non-finite or out-of-range values are
    /// ignored.
    pub fn on_feedback(&mut self, feedback: Feedback, now: f64) {
        match feedback {
            Feedback::Loss(loss) if (0.0..=1.0).contains(&loss) => {
                let since_divisor = now - self.last_divisor_change;
                if loss > HIGH_LOSS && self.rate <= self.floor {
                    if since_divisor >= DIVISOR_UP_EVERY_S && self.divisor < MAX_FRAME_DIVISOR {
                        self.divisor *= 2;
                        self.last_divisor_change = now;
                    }
                } else if loss < LOW_LOSS && self.divisor > 1 {
                    if since_divisor >= DIVISOR_DOWN_EVERY_S {
                        self.divisor /= 2;
                        self.last_divisor_change = now;
                    }
                    // The rate grows only once every frame is sent again.
                    return;
                }
                if loss > HIGH_LOSS {
                    if now - self.last_decrease >= DECREASE_EVERY_S {
                        self.rate *= 1.0 - loss / 2.0;
                        self.last_decrease = now;
                    }
                } else if loss < LOW_LOSS && now - self.last_increase >= INCREASE_EVERY_S {
                    self.rate *= INCREASE;
                    self.last_increase = now;
                }
                self.rate = self.rate.clamp(self.floor, self.ceiling);
            }
            Feedback::Estimate(bps) if bps.is_finite() && bps > 0.0 => self.estimate = Some((bps, now)),
            _ => {}
        }
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
    fn an_estimate_caps_the_rate_until_it_goes_stale() {
        let mut c = RateController::new(4e6, 0.3e6, 4e6);
        c.on_feedback(Feedback::Estimate(1.5e6), 0.0);
        assert_eq!(c.target_bps(1.0), 1.5e6);
        c.on_feedback(Feedback::Estimate(0.1e6), 2.0);
        assert_eq!(c.target_bps(2.0), 0.3e6, "never below the floor");
        assert_eq!(c.target_bps(7.5), 4e6, "a stale estimate caps nothing");
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
