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
        let frame = self.current.get_or_insert(FrameInfo {
            rtp_timestamp: timestamp,
            idr: false,
            bytes: 0,
            packets: 0,
            damaged: false,
        });
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
