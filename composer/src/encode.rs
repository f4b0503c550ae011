//! H.264 encoding with OpenH264 (the `openh264` crate, compiled from its bundled source; its
//! x86 assembly is built when Debian's `nasm` is installed, see README) in a low-latency
//! configuration:
//!
//! * **Constrained baseline**: baseline profile with `constraint_set1_flag` (OpenH264 sets
//!   constraint_set0 and 1 for baseline, so the SPS carries `42 c0 xx`): what every WebRTC
//!   receiver decodes, and what we negotiate as `profile-level-id=42e01f`.
//! * **IPPP**: one IDR, then P frames only. Baseline has no B frames, OpenH264 has no
//!   look-ahead and no frame reordering, so each frame's bits leave as soon as it is encoded.
//!   Scene-change detection is off (it would insert unrequested I frames); periodic intra
//!   frames are off unless asked for. Keyframes come on request ([`H264Encoder::request_keyframe`]:
//!   a new viewer, an RTCP PLI/FIR from the receiver).
//! * **Rate control**: OpenH264's bitrate mode with the maximum bitrate equal to the target
//!   and frame skipping allowed, which is how OpenH264 keeps its (internal, not
//!   configurable) buffer small. OpenH264 exposes no VBV size, so [`Vbv`] models a leaky
//!   bucket of `vbv_ms` at the target rate over the frames actually produced and reports its
//!   peak fullness and overflows: the queueing delay a paced sender would add.
//! * **Resolution limits**: even width and height (4:2:0), at least 16x16, at most 3840x2160
//!   (or 2160x3840), OpenH264's own limit (its level 5.2 tables); anything else is a
//!   [`EncodeError::Resolution`] before any frame is encoded.
//! * **Colour signalling**: the SPS's VUI says BT.709 primaries and matrix, sRGB transfer,
//!   limited range: exactly what [`crate::yuv`] produces.

use openh264::OpenH264API;
use openh264::encoder::{
    BitRate, Complexity, Encoder, EncoderConfig, FrameRate, FrameType, IntraFramePeriod, Profile, RateControlMode,
    SpsPpsStrategy, TransferCharacteristics, UsageType, VuiConfig,
};
use openh264::formats::YUVSource;
use thiserror::Error;

use crate::yuv::Yuv420;

/// Largest encodable picture side (OpenH264 refuses more than 3840x2160 or 2160x3840).
pub const MAX_LONG_SIDE: u32 = 3840;
pub const MAX_SHORT_SIDE: u32 = 2160;
/// Smallest encodable side (one macroblock).
pub const MIN_SIDE: u32 = 16;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum EncodeError {
    #[error("cannot encode {width}x{height}: {reason}")]
    Resolution { width: u32, height: u32, reason: String },
    #[error("bad encoder settings: {0}")]
    Settings(String),
    #[error("frame is {got_w}x{got_h}, the encoder was set up for {width}x{height}")]
    FrameSize { width: u32, height: u32, got_w: u32, got_h: u32 },
    #[error("OpenH264: {0}")]
    OpenH264(String),
}

/// Checks that OpenH264 can encode `width x height` in 4:2:0.
pub fn check_resolution(width: u32, height: u32) -> Result<(), EncodeError> {
    let fail = |reason: String| Err(EncodeError::Resolution { width, height, reason });
    if !width.is_multiple_of(2) || !height.is_multiple_of(2) {
        return fail("width and height must be even for 4:2:0 chroma".into());
    }
    if width < MIN_SIDE || height < MIN_SIDE {
        return fail(format!("each side must be at least {MIN_SIDE} pixels"));
    }
    let (long, short) = (width.max(height), width.min(height));
    if long > MAX_LONG_SIDE || short > MAX_SHORT_SIDE {
        return fail(format!(
            "the encoder's limit is {MAX_LONG_SIDE}x{MAX_SHORT_SIDE} (or {MAX_SHORT_SIDE}x{MAX_LONG_SIDE})"
        ));
    }
    Ok(())
}

/// Speed against quality of OpenH264's mode decision and motion search.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Effort {
    /// Fastest (OpenH264's low complexity): the default for interactive streaming.
    #[default]
    Low,
    Medium,
    High,
}

/// Encoder settings; see the module docs for what is fixed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncoderSettings {
    pub width: u32,
    pub height: u32,
    /// Target (and maximum) bitrate, bits per second.
    pub bitrate_bps: u32,
    /// Frame rate the rate control plans for.
    pub fps: f32,
    /// Size of the modelled VBV (leaky bucket at the target rate), milliseconds.
    pub vbv_ms: u32,
    /// A keyframe every this many frames; 0: only on request (pure IPPP).
    pub intra_period: u32,
    /// Let the rate control drop a frame rather than overshoot (a dropped frame sends nothing).
    pub allow_skip: bool,
    pub effort: Effort,
    /// OpenH264 threads (1: the encoding runs on the calling thread).
    pub threads: u16,
}

impl EncoderSettings {
    /// Defaults for interactive streaming at `width x height`: 30 fps, a bitrate of about
    /// 0.1 bit per pixel per frame (2.8 Mbit/s at 720p), a 2-frame VBV, no periodic keyframe.
    pub fn low_latency(width: u32, height: u32) -> Self {
        let bitrate = (f64::from(width) * f64::from(height) * 30.0 * 0.1).clamp(300_000.0, 40_000_000.0) as u32;
        EncoderSettings {
            width,
            height,
            bitrate_bps: bitrate,
            fps: 30.0,
            vbv_ms: 67,
            intra_period: 0,
            allow_skip: true,
            effort: Effort::Low,
            threads: 1,
        }
    }

    pub fn validate(&self) -> Result<(), EncodeError> {
        check_resolution(self.width, self.height)?;
        if !(1_000..=200_000_000).contains(&self.bitrate_bps) {
            return Err(EncodeError::Settings(format!(
                "bitrate {} bit/s outside 1 kbit/s..200 Mbit/s",
                self.bitrate_bps
            )));
        }
        if !(self.fps.is_finite() && (1.0..=240.0).contains(&self.fps)) {
            return Err(EncodeError::Settings(format!("frame rate {} outside 1..240", self.fps)));
        }
        if self.vbv_ms == 0 || self.vbv_ms > 10_000 {
            return Err(EncodeError::Settings(format!("VBV of {} ms outside 1..10000", self.vbv_ms)));
        }
        if self.threads == 0 || self.threads > 16 {
            return Err(EncodeError::Settings(format!("{} threads outside 1..16", self.threads)));
        }
        Ok(())
    }
}

/// What kind of picture an encoded frame holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameKind {
    /// Instantaneous decoder refresh, preceded by SPS and PPS: a viewer can start here.
    Idr,
    /// A non-IDR intra frame.
    Intra,
    /// A predicted frame.
    Predicted,
    /// The rate control dropped the frame: nothing to send.
    Skipped,
}

/// One encoded access unit in Annex B byte-stream format (start code before each NAL unit).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EncodedFrame {
    pub kind: FrameKind,
    pub timestamp_ms: u64,
    pub data: Vec<u8>,
}

impl EncodedFrame {
    pub fn is_keyframe(&self) -> bool {
        self.kind == FrameKind::Idr
    }

    /// The NAL units (without start codes).
    pub fn nal_units(&self) -> Vec<&[u8]> {
        split_annex_b(&self.data)
    }
}

/// Running totals of an encoder (`GET /v1/sessions` reports them).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct EncoderStats {
    pub frames: u64,
    pub keyframes: u64,
    pub skipped: u64,
    pub bytes: u64,
    /// Largest modelled VBV fullness, in milliseconds at the target rate.
    pub vbv_peak_ms: f64,
    /// Frames after which the modelled VBV held more than its size.
    pub vbv_overflows: u64,
}

/// A leaky bucket of `size` bits drained at the target rate: after each frame,
/// `fullness = max(0, fullness - rate / fps) + bits`. Its fullness divided by the rate is the
/// time the last bit of a frame waits behind earlier frames on a link of exactly that rate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vbv {
    size_bits: f64,
    drain_per_frame: f64,
    rate_bps: f64,
    fullness: f64,
    peak: f64,
    overflows: u64,
}

impl Vbv {
    pub fn new(rate_bps: u32, fps: f32, size_ms: u32) -> Self {
        let rate = f64::from(rate_bps);
        Vbv {
            size_bits: rate * f64::from(size_ms) / 1000.0,
            drain_per_frame: rate / f64::from(fps),
            rate_bps: rate,
            fullness: 0.0,
            peak: 0.0,
            overflows: 0,
        }
    }

    /// Accounts one frame of `bytes` (0 for a skipped frame).
    pub fn push(&mut self, bytes: usize) {
        self.fullness = (self.fullness - self.drain_per_frame).max(0.0) + 8.0 * bytes as f64;
        self.peak = self.peak.max(self.fullness);
        if self.fullness > self.size_bits {
            self.overflows += 1;
        }
    }

    pub fn fullness_ms(&self) -> f64 {
        1000.0 * self.fullness / self.rate_bps
    }

    pub fn peak_ms(&self) -> f64 {
        1000.0 * self.peak / self.rate_bps
    }

    pub fn overflows(&self) -> u64 {
        self.overflows
    }
}

/// The low-latency H.264 encoder of one video stream.
pub struct H264Encoder {
    inner: Encoder,
    settings: EncoderSettings,
    keyframe_requested: bool,
    vbv: Vbv,
    stats: EncoderStats,
}

impl std::fmt::Debug for H264Encoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("H264Encoder")
            .field("settings", &self.settings)
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

impl H264Encoder {
    pub fn new(settings: EncoderSettings) -> Result<Self, EncodeError> {
        settings.validate()?;
        let complexity = match settings.effort {
            Effort::Low => Complexity::Low,
            Effort::Medium => Complexity::Medium,
            Effort::High => Complexity::High,
        };
        let config = EncoderConfig::new()
            .usage_type(UsageType::CameraVideoRealTime)
            .profile(Profile::Baseline)
            .rate_control_mode(RateControlMode::Bitrate)
            .bitrate(BitRate::from_bps(settings.bitrate_bps))
            .max_frame_rate(FrameRate::from_hz(settings.fps))
            .skip_frames(settings.allow_skip)
            .complexity(complexity)
            .scene_change_detect(false)
            .long_term_reference(false)
            .intra_frame_period(IntraFramePeriod::from_num_frames(settings.intra_period))
            .sps_pps_strategy(SpsPpsStrategy::ConstantId)
            .num_threads(settings.threads)
            .vui(VuiConfig::bt709().transfer_characteristics(TransferCharacteristics::Srgb).full_range(false));
        let inner = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| EncodeError::OpenH264(e.to_string()))?;
        Ok(H264Encoder {
            inner,
            settings,
            keyframe_requested: false,
            vbv: Vbv::new(settings.bitrate_bps, settings.fps, settings.vbv_ms),
            stats: EncoderStats::default(),
        })
    }

    pub fn settings(&self) -> &EncoderSettings {
        &self.settings
    }

    pub fn stats(&self) -> EncoderStats {
        EncoderStats { vbv_peak_ms: self.vbv.peak_ms(), vbv_overflows: self.vbv.overflows(), ..self.stats }
    }

    /// The next frame will be an IDR (with SPS and PPS).
    pub fn request_keyframe(&mut self) {
        self.keyframe_requested = true;
    }

    /// Encodes one picture of the configured size.
    pub fn encode(&mut self, picture: &Yuv420, timestamp_ms: u64) -> Result<EncodedFrame, EncodeError> {
        let s = self.settings;
        if picture.width() != s.width || picture.height() != s.height {
            return Err(EncodeError::FrameSize {
                width: s.width,
                height: s.height,
                got_w: picture.width(),
                got_h: picture.height(),
            });
        }
        // The first frame is an IDR anyway; forcing it before the encoder is initialised
        // (which happens inside the first encode) is not allowed by OpenH264.
        if self.keyframe_requested && self.stats.frames > 0 {
            self.inner.force_intra_frame();
        }
        self.keyframe_requested = false;
        let stream = self
            .inner
            .encode_at(&Planes(picture), openh264::Timestamp::from_millis(timestamp_ms))
            .map_err(|e| EncodeError::OpenH264(e.to_string()))?;
        let kind = match stream.frame_type() {
            FrameType::IDR => FrameKind::Idr,
            FrameType::I => FrameKind::Intra,
            FrameType::P => FrameKind::Predicted,
            FrameType::Skip => FrameKind::Skipped,
            other => return Err(EncodeError::OpenH264(format!("unexpected frame type {other:?}"))),
        };
        let data = if kind == FrameKind::Skipped { Vec::new() } else { stream.to_vec() };
        self.stats.frames += 1;
        self.stats.bytes += data.len() as u64;
        match kind {
            FrameKind::Idr => self.stats.keyframes += 1,
            FrameKind::Skipped => self.stats.skipped += 1,
            _ => {}
        }
        self.vbv.push(data.len());
        Ok(EncodedFrame { kind, timestamp_ms, data })
    }
}

/// Lends a [`Yuv420`] to OpenH264 (tightly packed planes).
struct Planes<'a>(&'a Yuv420);

impl YUVSource for Planes<'_> {
    fn dimensions(&self) -> (usize, usize) {
        (self.0.width() as usize, self.0.height() as usize)
    }

    fn strides(&self) -> (usize, usize, usize) {
        let c = self.0.chroma_width() as usize;
        (self.0.width() as usize, c, c)
    }

    fn y(&self) -> &[u8] {
        &self.0.y
    }

    fn u(&self) -> &[u8] {
        &self.0.u
    }

    fn v(&self) -> &[u8] {
        &self.0.v
    }
}

// The bitstream's reading (NAL units, slice types, SPS fields) is shared with `loadgen`.
pub use nephele_proto::h264::{SliceType, nal, nal_type, slice_type, split_annex_b, sps_profile};

#[cfg(test)]
mod tests {
    use super::*;
    use openh264::decoder::Decoder;

    /// A moving test picture: smooth gradients and a bright square sliding right.
    fn picture(width: u32, height: u32, t: u32) -> Yuv420 {
        let rgb: Vec<[f32; 3]> = (0..height)
            .flat_map(|y| {
                (0..width).map(move |x| {
                    let inside = (x + 4 * t) % width < width / 4 && y > height / 3 && y < 2 * height / 3;
                    if inside {
                        [0.9, 0.8, 0.2]
                    } else {
                        [x as f32 / width as f32 * 0.5, y as f32 / height as f32 * 0.5, 0.3]
                    }
                })
            })
            .collect();
        Yuv420::from_linear_rgb(width, height, &rgb).unwrap()
    }

    fn psnr(a: &[u8], b: &[u8]) -> f64 {
        let mse = a.iter().zip(b).map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2)).sum::<f64>() / a.len() as f64;
        10.0 * (255.0f64 * 255.0 / mse.max(1e-9)).log10()
    }

    fn types(frame: &EncodedFrame) -> Vec<u8> {
        frame.nal_units().iter().filter_map(|u| nal_type(u)).collect()
    }

    #[test]
    fn resolution_limits_are_enforced_with_a_clear_error() {
        assert!(check_resolution(640, 480).is_ok());
        assert!(check_resolution(3840, 2160).is_ok());
        assert!(check_resolution(2160, 3840).is_ok());
        assert!(check_resolution(1920, 1080).is_ok());
        for (w, h, words) in [
            (641, 480, "even"),
            (640, 481, "even"),
            (8, 8, "at least 16"),
            (3842, 2160, "3840x2160"),
            (4096, 2160, "3840x2160"),
            (2400, 2400, "3840x2160"),
        ] {
            let e = check_resolution(w, h).unwrap_err();
            assert!(e.to_string().contains(words), "{w}x{h}: {e}");
            assert!(H264Encoder::new(EncoderSettings::low_latency(w, h)).is_err());
        }
        let mut bad = EncoderSettings::low_latency(64, 64);
        bad.fps = f32::NAN;
        assert!(matches!(H264Encoder::new(bad), Err(EncodeError::Settings(_))));
        let mut enc = H264Encoder::new(EncoderSettings::low_latency(64, 64)).unwrap();
        let e = enc.encode(&Yuv420::new(32, 32).unwrap(), 0).unwrap_err();
        assert!(matches!(e, EncodeError::FrameSize { got_w: 32, .. }), "{e}");
    }

    /// IDR with SPS/PPS first, then P slices only, an IDR again on request; a decoder gets
    /// back pictures close to the input.
    #[test]
    fn ippp_with_keyframes_on_request_decodes_back() {
        let (w, h) = (160, 96);
        let mut settings = EncoderSettings::low_latency(w, h);
        settings.bitrate_bps = 2_000_000;
        settings.allow_skip = false;
        let mut enc = H264Encoder::new(settings).unwrap();
        let mut dec = Decoder::new().unwrap();
        let mut psnrs = Vec::new();
        for t in 0..8u32 {
            if t == 5 {
                enc.request_keyframe();
            }
            let pic = picture(w, h, t);
            let frame = enc.encode(&pic, u64::from(t) * 33).unwrap();
            let units = frame.nal_units();
            let kinds = types(&frame);
            if t == 0 || t == 5 {
                assert_eq!(frame.kind, FrameKind::Idr, "frame {t}");
                assert!(
                    kinds.contains(&nal::SPS) && kinds.contains(&nal::PPS) && kinds.contains(&nal::IDR),
                    "frame {t}: {kinds:?}"
                );
                let sps = units.iter().find(|u| nal_type(u) == Some(nal::SPS)).unwrap();
                let (profile, constraints, _level) = sps_profile(sps).unwrap();
                assert_eq!(profile, 66, "baseline profile_idc");
                assert_ne!(constraints & 0x40, 0, "constraint_set1_flag: constrained baseline");
                for u in units.iter().filter(|u| nal_type(u) == Some(nal::IDR)) {
                    assert_eq!(slice_type(u), Some(SliceType::I));
                }
            } else {
                assert_eq!(frame.kind, FrameKind::Predicted, "frame {t}");
                assert!(kinds.iter().all(|&k| k == nal::SLICE || k == nal::SEI), "frame {t}: {kinds:?}");
                for u in units.iter().filter(|u| nal_type(u) == Some(nal::SLICE)) {
                    assert_eq!(slice_type(u), Some(SliceType::P), "frame {t}");
                }
            }
            let decoded = dec.decode(&frame.data).unwrap().expect("a picture per access unit (no reordering)");
            assert_eq!(decoded.dimensions(), (w as usize, h as usize));
            let (ys, us, _) = decoded.strides();
            let y: Vec<u8> = (0..h as usize).flat_map(|r| decoded.y()[r * ys..r * ys + w as usize].to_vec()).collect();
            let cw = (w / 2) as usize;
            let u: Vec<u8> = (0..(h / 2) as usize).flat_map(|r| decoded.u()[r * us..r * us + cw].to_vec()).collect();
            psnrs.push((psnr(&y, &pic.y), psnr(&u, &pic.u)));
        }
        for (t, (py, pu)) in psnrs.iter().enumerate() {
            assert!(*py > 32.0 && *pu > 32.0, "frame {t}: PSNR Y {py:.1} dB, U {pu:.1} dB");
        }
        let stats = enc.stats();
        assert_eq!((stats.frames, stats.keyframes, stats.skipped), (8, 2, 0));
        assert!(stats.bytes > 0 && stats.vbv_peak_ms > 0.0);
    }

    #[test]
    fn vbv_model_drains_at_the_target_rate() {
        // 1 Mbit/s at 10 fps drains 100 kbit per frame; a 200 ms bucket holds 200 kbit.
        let mut v = Vbv::new(1_000_000, 10.0, 200);
        v.push(25_000); // 200 kbit: full, not over.
        assert_eq!((v.fullness_ms(), v.overflows()), (200.0, 0));
        v.push(12_500); // 200 - 100 + 100 = 200 kbit.
        assert_eq!(v.fullness_ms(), 200.0);
        v.push(25_000); // 100 + 200 = 300 kbit: over.
        assert_eq!((v.fullness_ms(), v.overflows(), v.peak_ms()), (300.0, 1, 300.0));
        v.push(0);
        v.push(0);
        v.push(0);
        assert_eq!(v.fullness_ms(), 0.0);
    }

    #[test]
    fn annex_b_splitting_and_header_parsing() {
        let data = [0, 0, 0, 1, 0x67, 66, 0xc0, 31, 0, 0, 1, 0x68, 1, 0, 0, 0, 1, 0x41, 0x9a, 0];
        let units = split_annex_b(&data);
        assert_eq!(units, vec![&[0x67, 66, 0xc0, 31][..], &[0x68, 1][..], &[0x41, 0x9a, 0][..]]);
        assert_eq!(sps_profile(units[0]), Some((66, 0xc0, 31)));
        // 0x9a = 1 0 0 1 1...: first_mb = 0 ("1"), slice_type = ue("00110") = 5 → P.
        assert_eq!(slice_type(units[2]), Some(SliceType::P));
        // 0x88 = 1 0001000: first_mb = 0, slice_type = ue("0001000") = 7 → I.
        assert_eq!(slice_type(&[0x65, 0x88]), Some(SliceType::I));
        assert_eq!(slice_type(units[1]), None);
    }
}
