//! Just enough of H.264 over RTP (RFC 6184, packetization mode 1) to count frames and find
//! keyframes without decoding: the NAL unit types inside single-NAL, STAP-A and FU-A payloads.

pub use nephele_proto::h264::nal;

/// The NAL unit types that start in one RTP payload (FU-A: only in its first fragment).
pub fn nal_types(payload: &[u8]) -> Vec<u8> {
    match payload.first().map(|b| b & 0x1f) {
        Some(nal::FU_A) => match payload.get(1) {
            Some(&header) if header & 0x80 != 0 => vec![header & 0x1f],
            _ => Vec::new(),
        },
        _ => whole_nal_units(payload).into_iter().filter_map(nephele_proto::h264::nal_type).collect(),
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

/// The picture size announced by a sequence parameter set that `payload` carries whole, if
/// one parses ([`nephele_proto::h264::sps_picture_size`]).
pub fn picture_size_in_payload(payload: &[u8]) -> Option<(u32, u32)> {
    whole_nal_units(payload).into_iter().find_map(nephele_proto::h264::sps_picture_size)
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
        if let Some(size) = picture_size_in_payload(payload) {
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
        frame.idr |= nal_types(payload).contains(&nal::IDR);
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
        assert_eq!(nal_types(&[0x65, 1, 2]), vec![nal::IDR]);
        assert_eq!(nal_types(&[0x41, 1]), vec![nal::SLICE]);
        // STAP-A with SPS (3 bytes), PPS (2 bytes), IDR (2 bytes).
        let stap = [0x78, 0, 3, 0x67, 1, 2, 0, 2, 0x68, 1, 0, 2, 0x65, 9];
        assert_eq!(nal_types(&stap), vec![nal::SPS, nal::PPS, nal::IDR]);
        // A truncated aggregate stops at the damage.
        assert_eq!(nal_types(&stap[..10]), vec![nal::SPS, nal::PPS]);
        // FU-A: the start fragment names the type, later ones do not.
        assert_eq!(nal_types(&[0x7c, 0x85, 1]), vec![nal::IDR]);
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
        assert_eq!(picture_size_in_payload(&nal), Some((320, 180)));
        assert_eq!(picture_size_in_payload(&sps_nal(40, 30, 0)), Some((640, 480)));
        // Inside a STAP-A with a PPS, as webrtc-rs sends it before an IDR.
        let mut stap = vec![0x78, 0, nal.len() as u8];
        stap.extend_from_slice(&nal);
        stap.extend_from_slice(&[0, 2, 0x68, 0xce]);
        assert_eq!(picture_size_in_payload(&stap), Some((320, 180)));
        // No SPS, truncations, a crop larger than the picture, random bytes: none, no panic.
        assert_eq!(picture_size_in_payload(&[0x65, 1, 2]), None);
        for cut in 1..nal.len() {
            assert_eq!(picture_size_in_payload(&nal[..cut]), None, "cut at {cut}");
        }
        assert_eq!(picture_size_in_payload(&sps_nal(1, 1, 40)), None);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for len in 0..400 {
            let mut junk = vec![0x67];
            junk.extend((0..len % 40).map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            }));
            let _ = picture_size_in_payload(&junk);
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
