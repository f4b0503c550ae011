//! Reading an H.264 byte stream without decoding it (ITU-T H.264): the composer's tests check
//! what its encoder writes, `loadgen` and the test viewers what arrives. NAL units, the slice
//! type of a slice header, the SPS's profile and picture size. Pure and total: malformed input
//! gives `None`, never a panic.

/// NAL unit types looked at (H.264 table 7-1), and RTP's aggregation and fragmentation units
/// (RFC 6184).
pub mod nal {
    pub const SLICE: u8 = 1;
    pub const IDR: u8 = 5;
    pub const SEI: u8 = 6;
    pub const SPS: u8 = 7;
    pub const PPS: u8 = 8;
    pub const STAP_A: u8 = 24;
    pub const FU_A: u8 = 28;
}

/// Splits an Annex B byte stream at its start codes (`00 00 01` or `00 00 00 01`).
pub fn split_annex_b(data: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut i = 0;
    while i + 3 <= data.len() {
        if data[i] == 0 && data[i + 1] == 0 && data[i + 2] == 1 {
            starts.push((i, i + 3));
            i += 3;
        } else {
            i += 1;
        }
    }
    let mut out = Vec::with_capacity(starts.len());
    for (k, &(_, begin)) in starts.iter().enumerate() {
        let mut end = starts.get(k + 1).map_or(data.len(), |&(next, _)| next);
        // A 4-byte start code leaves one zero byte at the end of the previous unit.
        while end > begin && data[end - 1] == 0 && k + 1 < starts.len() {
            end -= 1;
        }
        if end > begin {
            out.push(&data[begin..end]);
        }
    }
    out
}

/// `nal_unit_type` of a NAL unit (without start code).
pub fn nal_type(unit: &[u8]) -> Option<u8> {
    unit.first().map(|b| b & 0x1f)
}

/// Slice types (H.264 table 7-6, modulo 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SliceType {
    P,
    B,
    I,
    Sp,
    Si,
}

/// The `slice_type` of a coded slice NAL unit (types 1 and 5), read from its header.
pub fn slice_type(unit: &[u8]) -> Option<SliceType> {
    if !matches!(nal_type(unit)?, nal::SLICE | nal::IDR) {
        return None;
    }
    let mut bits = BitReader::new(unit.get(1..)?.get(..32).unwrap_or(&unit[1..]));
    let _first_mb = bits.ue()?;
    Some(match bits.ue()? % 5 {
        0 => SliceType::P,
        1 => SliceType::B,
        2 => SliceType::I,
        3 => SliceType::Sp,
        _ => SliceType::Si,
    })
}

/// `(profile_idc, constraint flags byte, level_idc)` of an SPS NAL unit.
pub fn sps_profile(unit: &[u8]) -> Option<(u8, u8, u8)> {
    if nal_type(unit)? != nal::SPS || unit.len() < 4 {
        return None;
    }
    Some((unit[1], unit[2], unit[3]))
}

/// The picture size an SPS NAL unit announces (section 7.3.2.1.1, frame cropping applied).
/// A stream's size may change at any IDR (the composer's falls with its bitrate on a narrow
/// link). An SPS with scaling matrices (which the composer's encoder never writes) gives
/// `None`.
pub fn sps_picture_size(unit: &[u8]) -> Option<(u32, u32)> {
    if nal_type(unit)? != nal::SPS {
        return None;
    }
    let mut r = BitReader::new(unit.get(1..)?);
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
            return None; // seq_scaling_matrix_present_flag
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

/// Reads fixed-width and Exp-Golomb fields of a NAL unit's payload, emulation prevention
/// bytes (`00 00 03`) removed.
struct BitReader {
    bytes: Vec<u8>,
    bit: usize,
}

impl BitReader {
    fn new(escaped: &[u8]) -> BitReader {
        let mut bytes = Vec::with_capacity(escaped.len());
        let mut zeros = 0;
        for &b in escaped {
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

    /// `se(v)`.
    fn se(&mut self) -> Option<i64> {
        let k = i64::from(self.ue()?);
        Some(if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) })
    }
}
