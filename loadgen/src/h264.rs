//! Just enough of H.264 over RTP (RFC 6184, packetization mode 1) to count frames and find
//! keyframes without decoding: the NAL unit types inside single-NAL, STAP-A and FU-A payloads.

/// NAL unit types (H.264 Table 7-1) that matter here.
pub mod nal {
    pub const NON_IDR_SLICE: u8 = 1;
    pub const IDR_SLICE: u8 = 5;
    pub const SPS: u8 = 7;
    pub const PPS: u8 = 8;
    pub const STAP_A: u8 = 24;
    pub const FU_A: u8 = 28;
}

/// The NAL unit types that start in one RTP payload (FU-A: only in its first fragment).
pub fn nal_types(payload: &[u8]) -> Vec<u8> {
    let Some(&first) = payload.first() else { return Vec::new() };
    match first & 0x1f {
        nal::STAP_A => {
            let mut out = Vec::new();
            let mut rest = &payload[1..];
            while rest.len() >= 3 {
                let size = usize::from(u16::from_be_bytes([rest[0], rest[1]]));
                if size == 0 || rest.len() < 2 + size {
                    break;
                }
                out.push(rest[2] & 0x1f);
                rest = &rest[2 + size..];
            }
            out
        }
        nal::FU_A => match payload.get(1) {
            Some(&header) if header & 0x80 != 0 => vec![header & 0x1f],
            _ => Vec::new(),
        },
        0 | 30 | 31 => Vec::new(),
        t => vec![t],
    }
}

/// The whole NAL units a payload carries (a single NAL unit, or each of a STAP-A's; an FU-A
/// fragment carries none whole).
fn whole_nal_units(payload: &[u8]) -> Vec<&[u8]> {
    let Some(&first) = payload.first() else { return Vec::new() };
    match first & 0x1f {
        nal::STAP_A => {
            let mut out = Vec::new();
            let mut rest = &payload[1..];
            while rest.len() >= 3 {
                let size = usize::from(u16::from_be_bytes([rest[0], rest[1]]));
                if size == 0 || rest.len() < 2 + size {
                    break;
                }
                out.push(&rest[2..2 + size]);
                rest = &rest[2 + size..];
            }
            out
        }
        nal::FU_A | 0 | 30 | 31 => Vec::new(),
        _ => vec![payload],
    }
}

/// The picture size a sequence parameter set in `payload` announces (H.264 section 7.3.2.1.1,
/// frame cropping applied), if the payload carries one that parses. The stream's resolution
/// may change at any IDR (the composer's falls with its bitrate on a narrow link).
pub fn sps_picture_size(payload: &[u8]) -> Option<(u32, u32)> {
    whole_nal_units(payload).into_iter().find(|n| n.first().is_some_and(|b| b & 0x1f == nal::SPS)).and_then(parse_sps)
}

/// Reads Exp-Golomb and fixed-width fields from a NAL unit's payload, emulation prevention
/// bytes (`00 00 03`) removed.
struct BitReader {
    bytes: Vec<u8>,
    bit: usize,
}

impl BitReader {
    fn new(rbsp_with_prevention: &[u8]) -> BitReader {
        let mut bytes = Vec::with_capacity(rbsp_with_prevention.len());
        let mut zeros = 0;
        for &b in rbsp_with_prevention {
            if zeros >= 2 && b == 3 {
                zeros = 0;
                continue;
            }
            zeros = if b == 0 { zeros + 1 } else { 0 };
            bytes.push(b);
        }
        BitReader { bytes, bit: 0 }
    }

    fn bit(&mut self) -> Option<u32> {
        let byte = *self.bytes.get(self.bit / 8)?;
        let v = (byte >> (7 - self.bit % 8)) & 1;
        self.bit += 1;
        Some(u32::from(v))
    }

    fn bits(&mut self, n: u32) -> Option<u32> {
        (0..n).try_fold(0u32, |acc, _| Some((acc << 1) | self.bit()?))
    }

    /// `ue(v)`, at most 31 leading zeros (a larger value is malformed here).
    fn ue(&mut self) -> Option<u32> {
        let mut zeros = 0;
        while self.bit()? == 0 {
            zeros += 1;
            if zeros > 31 {
                return None;
            }
        }
        let rest = self.bits(zeros)?;
        u32::try_from((1u64 << zeros) - 1 + u64::from(rest)).ok()
    }

    fn se(&mut self) -> Option<i64> {
        let k = i64::from(self.ue()?);
        Some(if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) })
    }
}

fn parse_sps(nal_unit: &[u8]) -> Option<(u32, u32)> {
    let mut r = BitReader::new(nal_unit.get(1..)?);
    let profile = r.bits(8)?;
    r.bits(16)?; // constraint flags, level
    r.ue()?; // seq_parameter_set_id
    let mut chroma_format = 1;
    if matches!(profile, 100 | 110 | 122 | 244 | 44 | 83 | 86 | 118 | 128 | 138 | 139 | 134 | 135) {
        chroma_format = r.ue()?;
        if chroma_format == 3 {
            r.bit()?; // separate_colour_plane_flag
        }
        r.ue()?; // bit depths
        r.ue()?;
        r.bit()?; // qpprime_y_zero_transform_bypass_flag
        if r.bit()? == 1 {
            return None; // scaling matrices: not sent by the composer's encoder; not parsed
        }
    }
    r.ue()?; // log2_max_frame_num_minus4
    match r.ue()? {
        0 => {
            r.ue()?;
        }
        1 => {
            r.bit()?;
            r.se()?;
            r.se()?;
            for _ in 0..r.ue()?.min(255) {
                r.se()?;
            }
        }
        _ => {}
    }
    r.ue()?; // max_num_ref_frames
    r.bit()?; // gaps_in_frame_num_value_allowed_flag
    let width_mbs = u64::from(r.ue()?) + 1;
    let height_units = u64::from(r.ue()?) + 1;
    let frame_mbs_only = u64::from(r.bit()?);
    if frame_mbs_only == 0 {
        r.bit()?; // mb_adaptive_frame_field_flag
    }
    r.bit()?; // direct_8x8_inference_flag
    let (mut width, mut height) = (width_mbs * 16, (2 - frame_mbs_only) * height_units * 16);
    if r.bit()? == 1 {
        let (unit_x, unit_y) = match chroma_format {
            0 => (1, 2 - frame_mbs_only),
            1 => (2, 2 * (2 - frame_mbs_only)),
            2 => (2, 2 - frame_mbs_only),
            _ => (1, 2 - frame_mbs_only),
        };
        let (left, right, top, bottom) = (r.ue()?, r.ue()?, r.ue()?, r.ue()?);
        width = width.checked_sub(unit_x * (u64::from(left) + u64::from(right)))?;
        height = height.checked_sub(unit_y * (u64::from(top) + u64::from(bottom)))?;
    }
    Some((u32::try_from(width).ok()?, u32::try_from(height).ok()?)).filter(|&(w, h)| w > 0 && h > 0)
}

/// A complete access unit as seen on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameInfo {
    pub rtp_timestamp: u32,
    /// It carried an IDR slice.
    pub idr: bool,
    /// Payload bytes over all its packets.
    pub bytes: usize,
    pub packets: u32,
    /// A sequence-number gap fell inside it (it cannot be decoded as is).
    pub damaged: bool,
    /// The picture size of the last sequence parameter set seen (this frame's or an earlier
    /// one's; `None` before any).
    pub size: Option<(u32, u32)>,
}

/// Assembles RTP packets into frames: a frame ends at the packet with the marker bit. A frame
/// whose marker never came (the RTP timestamp moved on) is counted in `unfinished_frames`.
#[derive(Debug, Default)]
pub struct FrameCounter {
    current: Option<FrameInfo>,
    last_sequence: Option<u16>,
    /// Packets missing according to sequence numbers.
    pub lost_packets: u64,
    /// Frames that never saw their marker packet.
    pub unfinished_frames: u64,
    /// The picture size of the last sequence parameter set seen.
    pub size: Option<(u32, u32)>,
}

impl FrameCounter {
    pub fn new() -> Self {
        FrameCounter::default()
    }

    /// Feeds one packet; returns the frame its marker bit completed, if any.
    pub fn push(&mut self, sequence: u16, timestamp: u32, marker: bool, payload: &[u8]) -> Option<FrameInfo> {
        let mut gap = false;
        if let Some(last) = self.last_sequence {
            let step = sequence.wrapping_sub(last);
            if step == 0 || step > 0x8000 {
                return None; // a duplicate, or a packet older than one already seen
            }
            if step > 1 {
                self.lost_packets += u64::from(step - 1);
                gap = true;
            }
        }
        self.last_sequence = Some(sequence);
        if self.current.is_some_and(|f| f.rtp_timestamp != timestamp) {
            self.unfinished_frames += 1;
            self.current = None;
        }
        if let Some(size) = sps_picture_size(payload) {
            self.size = Some(size);
        }
        let frame = self.current.get_or_insert(FrameInfo {
            rtp_timestamp: timestamp,
            idr: false,
            bytes: 0,
            packets: 0,
            damaged: false,
            size: None,
        });
        frame.size = self.size;
        // A gap before a frame's first packet may have taken its beginning too.
        frame.damaged |= gap;
        frame.idr |= nal_types(payload).contains(&nal::IDR_SLICE);
        frame.bytes += payload.len();
        frame.packets += 1;
        if marker { self.current.take() } else { None }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nal_types_of_single_stap_a_and_fu_a_payloads() {
        assert_eq!(nal_types(&[0x65, 1, 2]), vec![nal::IDR_SLICE]);
        assert_eq!(nal_types(&[0x41, 1]), vec![nal::NON_IDR_SLICE]);
        // STAP-A with SPS (3 bytes), PPS (2 bytes), IDR (2 bytes).
        let stap = [0x78, 0, 3, 0x67, 1, 2, 0, 2, 0x68, 1, 0, 2, 0x65, 9];
        assert_eq!(nal_types(&stap), vec![nal::SPS, nal::PPS, nal::IDR_SLICE]);
        // A truncated aggregate stops at the damage.
        assert_eq!(nal_types(&stap[..10]), vec![nal::SPS, nal::PPS]);
        // FU-A: the start fragment names the type, later ones do not.
        assert_eq!(nal_types(&[0x7c, 0x85, 1]), vec![nal::IDR_SLICE]);
        assert_eq!(nal_types(&[0x7c, 0x05, 1]), Vec::<u8>::new());
        assert_eq!(nal_types(&[]), Vec::<u8>::new());
    }

    /// An SPS written field by field (baseline profile, cropped 320x180), escaped as a NAL.
    fn sps_nal(width_mbs: u32, height_mbs: u32, crop_bottom: u32) -> Vec<u8> {
        let mut bits: Vec<u8> = Vec::new();
        let mut put = |value: u32, n: u32| (0..n).rev().for_each(|i| bits.push(((value >> i) & 1) as u8));
        let ue = |put: &mut dyn FnMut(u32, u32), v: u32| {
            let n = 32 - (v + 1).leading_zeros();
            put(0, n - 1);
            put(v + 1, n);
        };
        put(66, 8); // profile
        put(0, 16); // constraints, level
        ue(&mut put, 0); // id
        ue(&mut put, 0); // log2_max_frame_num_minus4
        ue(&mut put, 0); // pic_order_cnt_type
        ue(&mut put, 0); // log2_max_pic_order_cnt_lsb_minus4
        ue(&mut put, 1); // max_num_ref_frames
        put(0, 1);
        ue(&mut put, width_mbs - 1);
        ue(&mut put, height_mbs - 1);
        put(1, 1); // frame_mbs_only
        put(1, 1); // direct_8x8
        put(u32::from(crop_bottom > 0), 1);
        if crop_bottom > 0 {
            (0..3).for_each(|_| ue(&mut put, 0));
            ue(&mut put, crop_bottom);
        }
        put(1, 1); // stop bit
        while !bits.len().is_multiple_of(8) {
            bits.push(0);
        }
        let rbsp: Vec<u8> = bits.chunks(8).map(|b| b.iter().fold(0, |a, &x| (a << 1) | x)).collect();
        let mut nal = vec![0x67];
        let mut zeros = 0;
        for b in rbsp {
            if zeros >= 2 && b <= 3 {
                nal.push(3);
                zeros = 0;
            }
            zeros = if b == 0 { zeros + 1 } else { 0 };
            nal.push(b);
        }
        nal
    }

    #[test]
    fn the_sps_gives_the_picture_size_and_garbage_gives_none() {
        let nal = sps_nal(20, 12, 6);
        assert_eq!(sps_picture_size(&nal), Some((320, 180)));
        assert_eq!(sps_picture_size(&sps_nal(40, 30, 0)), Some((640, 480)));
        // Inside a STAP-A with a PPS, as webrtc-rs sends it before an IDR.
        let mut stap = vec![0x78, 0, nal.len() as u8];
        stap.extend_from_slice(&nal);
        stap.extend_from_slice(&[0, 2, 0x68, 0xce]);
        assert_eq!(sps_picture_size(&stap), Some((320, 180)));
        // No SPS, truncations, a crop larger than the picture, random bytes: none, no panic.
        assert_eq!(sps_picture_size(&[0x65, 1, 2]), None);
        for cut in 1..nal.len() {
            assert_eq!(sps_picture_size(&nal[..cut]), None, "cut at {cut}");
        }
        assert_eq!(sps_picture_size(&sps_nal(1, 1, 40)), None);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for len in 0..400 {
            let mut junk = vec![0x67];
            junk.extend((0..len % 40).map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            }));
            let _ = sps_picture_size(&junk);
        }
    }

    #[test]
    fn frames_end_at_the_marker_and_losses_are_counted() {
        let mut c = FrameCounter::new();
        assert_eq!(c.push(10, 1000, false, &[0x7c, 0x85, 0]), None);
        let f = c.push(11, 1000, true, &[0x7c, 0x45, 0]).expect("frame");
        assert_eq!((f.idr, f.packets, f.bytes, f.damaged), (true, 2, 6, false));
        let f = c.push(12, 4000, true, &[0x41, 0]).expect("frame");
        assert!(!f.idr && !f.damaged);
        // Packet 14 lost: frame 7000 never sees its marker; 10000 arrives after the gap.
        assert_eq!(c.push(13, 7000, false, &[0x7c, 0x81]), None);
        let f = c.push(15, 10000, true, &[0x41]).expect("the new frame completes");
        assert_eq!((f.rtp_timestamp, f.damaged), (10000, true));
        assert_eq!((c.lost_packets, c.unfinished_frames), (1, 1));
        // Duplicates are ignored; sequence numbers wrap.
        assert_eq!(c.push(15, 10000, true, &[0x41]), None);
        let mut c = FrameCounter::new();
        c.push(65535, 1, true, &[0x41]);
        assert!(c.push(0, 2, true, &[0x41]).is_some());
        assert_eq!(c.lost_packets, 0);
    }
}
