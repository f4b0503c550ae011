//! Colour conversion: linear RGB → sRGB-encoded R'G'B' → Y'CbCr 4:2:0 (I420).
//!
//! * **Transfer**: the sRGB curve (IEC 61966-2-1): `12.92 x` below `0.0031308`, else
//!   `1.055 x^(1/2.4) - 0.055`, after clamping linear values to `[0, 1]`. Browsers display
//!   the decoded picture as sRGB, so this is what reproduces the renderer's radiance.
//! * **Matrix**: ITU-R BT.709 (`Kr = 0.2126`, `Kb = 0.0722`, `Kg = 1 - Kr - Kb = 0.7152`):
//!   `Y' = Kr R' + Kg G' + Kb B'`, `Pb = (B' - Y') / (2 (1 - Kb))`, `Pr = (R' - Y') / (2 (1 - Kr))`.
//! * **Range**: limited ("TV", "studio") 8-bit range, as BT.709 specifies for HD and as
//!   decoders assume when the stream says nothing: `Y = 16 + 219 Y'`, `Cb = 128 + 224 Pb`,
//!   `Cr = 128 + 224 Pr`, rounded to nearest (ties to even). Black is (16, 128, 128), white (235, 128, 128).
//!   The encoder signals the same in the SPS's VUI (see `encode`).
//! * **Chroma**: 4:2:0 with each chroma sample the mean of the 2x2 block of R'G'B' it covers
//!   (co-sited between the four luma samples, the MPEG-1/JPEG placement; H.264's default
//!   left-sited placement differs by a quarter pixel, invisible at these sizes). Odd widths
//!   or heights are handled: the chroma planes are `ceil(w/2) x ceil(h/2)` and an edge block
//!   averages the pixels it has. (The encoder itself requires even sizes.)
//!
//! The transfer curve's power is computed through `log2` and `exp2` polynomials (within 1e-5
//! of the exact curve, checked in the tests) rather than looked up: the same code runs eight
//! pixels at a time with AVX2 + FMA ([`pulp::Arch::dispatch`] chooses at run time, no
//! `unsafe`) and one at a time on other CPUs and at the picture's edges. The table with linear
//! interpolation that it replaces (4096 entries, error 1e-4) could not vectorise without
//! gathers, and the conversion was 3.8 % of a live 640x480 user's machine (`perf`,
//! BENCHMARKS.md 2026-12-05i).

use pulp::{Arch, Simd, WithSimd};
use rayon::prelude::*;
use thiserror::Error;

pub const KR: f32 = 0.2126;
pub const KB: f32 = 0.0722;
pub const KG: f32 = 1.0 - KR - KB;

#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum YuvError {
    #[error("image size {width}x{height} must be positive")]
    EmptyImage { width: u32, height: u32 },
    #[error("{got} RGB pixels for a {width}x{height} image")]
    WrongLength { width: u32, height: u32, got: usize },
}

/// Where the sRGB curve turns from its linear toe to its power segment.
const LINEAR_KNEE: f32 = 0.003_130_8;

/// The exact sRGB transfer function, linear → encoded, for `x` clamped to `[0, 1]`.
pub fn linear_to_srgb_exact(x: f32) -> f32 {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    if x <= LINEAR_KNEE { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 }
}

/// The sRGB transfer function as the conversion computes it (see the module docs). NaN maps
/// to 0.
#[inline]
pub fn linear_to_srgb(x: f32) -> f32 {
    srgb_encode(pulp::Scalar::new(), x)
}

/// 1.5 * 2^23: adding it to a float in [-2^22, 2^22) gives a float in [2^23, 2^24), where
/// the spacing is 1: the sum's bit pattern minus MAGIC's is the rounded integer.
const MAGIC: f32 = 12_582_912.0;

/// `2 / (k ln 2)` for k = 1, 3, 5, 7: `log2(m) = sum c_k u^k` with `u = (m - 1) / (m + 1)`
/// (the series of `artanh`); for `m` in `[sqrt(1/2), sqrt(2))`, `|u| < 0.172` and the first
/// omitted term is below 5e-8.
const LOG2_SERIES: [f32; 4] = [2.885_39, 0.961_796_7, 0.577_078, 0.412_198_6];

/// `ln(2)^k / k!` for k = 0..=6: `2^f = sum c_k f^k`, for `f` in `[-1/2, 1/2]` within 1.2e-7
/// relative.
const EXP2_SERIES: [f32; 7] =
    [1.0, std::f32::consts::LN_2, 0.240_226_5, 0.055_504_11, 0.009_618_129, 0.001_333_355_8, 0.000_154_035_3];

/// The sRGB transfer function lane by lane, for any [`Simd`] (NaN and values below 0 give 0,
/// above 1 give 1): `12.92 x` below the knee, else `1.055 x^(1/2.4) - 0.055` with the power
/// as `exp2(log2(x) / 2.4)`.
#[inline(always)]
fn srgb_encode<S: Simd>(simd: S, x: S::f32s) -> S::f32s {
    let splat = |v: f32| simd.splat_f32s(v);
    let splat_u = |v: u32| simd.splat_u32s(v);
    // `max` before `min`: `max(NaN, 0)` is 0 both in the vector instruction (second operand
    // on NaN) and in the scalar `f32::max`.
    let x = simd.min_f32s(simd.max_f32s(x, splat(0.0)), splat(1.0));
    let toe = simd.mul_f32s(x, splat(12.92));
    // The power segment, kept finite below the knee (its lanes are not used there).
    let p = simd.max_f32s(x, splat(LINEAR_KNEE));
    let bits = simd.transmute_u32s_f32s(p);
    let mantissa = simd.or_u32s(simd.and_u32s(bits, splat_u(0x007F_FFFF)), splat_u(0x3F80_0000));
    let m = simd.transmute_f32s_u32s(mantissa);
    // The biased exponent (at most 127 for p <= 1) as a float, through MAGIC.
    let biased = simd.wrapping_dyn_shr_u32s(bits, splat_u(23));
    let biased = simd.sub_f32s(simd.transmute_f32s_u32s(simd.add_u32s(biased, splat_u(MAGIC.to_bits()))), splat(MAGIC));
    // m in [1, 2) -> [sqrt(1/2), sqrt(2)): halve it and count one more in the exponent.
    let high = simd.greater_than_f32s(m, splat(std::f32::consts::SQRT_2));
    let m = simd.select_f32s(high, simd.mul_f32s(m, splat(0.5)), m);
    let exponent = simd.add_f32s(biased, simd.select_f32s(high, splat(-126.0), splat(-127.0)));
    let u = simd.div_f32s(simd.sub_f32s(m, splat(1.0)), simd.add_f32s(m, splat(1.0)));
    let u2 = simd.mul_f32s(u, u);
    let [c1, c3, c5, c7] = LOG2_SERIES;
    let series = simd.mul_add_f32s(u2, splat(c7), splat(c5));
    let series = simd.mul_add_f32s(u2, series, splat(c3));
    let series = simd.mul_add_f32s(u2, series, splat(c1));
    let log2 = simd.mul_add_f32s(u, series, exponent);
    // exp2(y) for y = log2(p) / 2.4 in [-3.5, 0]: y = n + f, n = round(y).
    let y = simd.mul_f32s(log2, splat(1.0 / 2.4));
    let shifted = simd.add_f32s(y, splat(MAGIC));
    let n = simd.sub_u32s(simd.transmute_u32s_f32s(shifted), splat_u(MAGIC.to_bits()));
    let f = simd.sub_f32s(y, simd.sub_f32s(shifted, splat(MAGIC)));
    let mut power = splat(EXP2_SERIES[6]);
    for &c in EXP2_SERIES[..6].iter().rev() {
        power = simd.mul_add_f32s(power, f, splat(c));
    }
    // Times 2^n: n added to the exponent field (wrapping: n <= 0 is two's complement).
    let power = simd.add_u32s(simd.transmute_u32s_f32s(power), simd.wrapping_dyn_shl_u32s(n, splat_u(23)));
    let encoded = simd.mul_add_f32s(simd.transmute_f32s_u32s(power), splat(1.055), splat(-0.055));
    simd.select_f32s(simd.less_than_or_equal_f32s(x, splat(LINEAR_KNEE)), toe, encoded)
}

/// Limited-range BT.709 code values of one encoded R'G'B' colour, unrounded chroma offsets
/// `(Y', Pb, Pr)` in `[0,1] x [-0.5,0.5]^2`.
#[inline]
fn ypbpr(r: f32, g: f32, b: f32) -> (f32, f32, f32) {
    let y = KR * r + KG * g + KB * b;
    (y, (b - y) / (2.0 * (1.0 - KB)), (r - y) / (2.0 * (1.0 - KR)))
}

/// Rounds to the nearest 8-bit code (ties to even), clamped to 0..=255.
#[inline]
#[allow(clippy::manual_clamp)] // `clamp` would keep NaN; this sends it to 0
fn code(v: f32) -> u8 {
    (v.max(0.0).min(255.0) + MAGIC).to_bits().wrapping_sub(MAGIC.to_bits()) as u8
}

#[inline]
fn luma_code(y: f32) -> u8 {
    code(16.0 + 219.0 * y)
}

#[inline]
fn chroma_code(c: f32) -> u8 {
    code(128.0 + 224.0 * c)
}

/// BT.709 limited-range code values `(Y, Cb, Cr)` of one linear RGB colour.
pub fn linear_rgb_to_ycbcr(rgb: [f32; 3]) -> (u8, u8, u8) {
    let [r, g, b] = rgb.map(linear_to_srgb_exact);
    let (y, pb, pr) = ypbpr(r, g, b);
    (luma_code(y), chroma_code(pb), chroma_code(pr))
}

/// An 8-bit I420 picture: a full-size luma plane and two chroma planes of
/// `ceil(w/2) x ceil(h/2)`, all tightly packed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Yuv420 {
    width: u32,
    height: u32,
    pub y: Vec<u8>,
    pub u: Vec<u8>,
    pub v: Vec<u8>,
}

impl Yuv420 {
    /// A black picture.
    pub fn new(width: u32, height: u32) -> Result<Self, YuvError> {
        if width == 0 || height == 0 {
            return Err(YuvError::EmptyImage { width, height });
        }
        let (w, h) = (width as usize, height as usize);
        let chroma = w.div_ceil(2) * h.div_ceil(2);
        Ok(Yuv420 { width, height, y: vec![16; w * h], u: vec![128; chroma], v: vec![128; chroma] })
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    pub fn chroma_width(&self) -> u32 {
        self.width.div_ceil(2)
    }

    pub fn chroma_height(&self) -> u32 {
        self.height.div_ceil(2)
    }

    /// Converts a linear RGB picture (row-major, `width * height` pixels).
    pub fn from_linear_rgb(width: u32, height: u32, rgb: &[[f32; 3]]) -> Result<Self, YuvError> {
        let mut out = Yuv420::new(width, height)?;
        out.fill_from_linear_rgb(rgb)?;
        Ok(out)
    }

    /// Converts a linear RGB picture of this picture's size into it, reusing its planes.
    /// Rows pairs are converted in parallel (rayon), with the widest instruction set the CPU
    /// has.
    pub fn fill_from_linear_rgb(&mut self, rgb: &[[f32; 3]]) -> Result<(), YuvError> {
        self.fill_with(Arch::new(), rgb)
    }

    /// [`Self::fill_from_linear_rgb`] through `arch` (`Arch::Scalar` for the scalar twin).
    fn fill_with(&mut self, arch: Arch, rgb: &[[f32; 3]]) -> Result<(), YuvError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if rgb.len() != w * h {
            return Err(YuvError::WrongLength { width: self.width, height: self.height, got: rgb.len() });
        }
        let cw = w.div_ceil(2);
        self.y
            .par_chunks_mut(2 * w)
            .zip(self.u.par_chunks_mut(cw))
            .zip(self.v.par_chunks_mut(cw))
            .zip(rgb.par_chunks(2 * w))
            .for_each(|(((luma, cb), cr), rgb_rows)| {
                let rows = luma.len() / w;
                // Full 2x2 blocks: whole vectors of them, then one at a time.
                let full = if rows == 2 { w / 2 } else { 0 };
                let vectored =
                    arch.dispatch(RowPair { rgb: rgb_rows.as_flattened(), width: w, luma, cb, cr, blocks: full });
                for cx in vectored..full {
                    let x = 2 * cx;
                    let mut sum = [0.0f32; 3];
                    for i in [x, x + 1, w + x, w + x + 1] {
                        let e = rgb_rows[i].map(linear_to_srgb);
                        luma[i] = luma_code(KR * e[0] + KG * e[1] + KB * e[2]);
                        sum = [sum[0] + e[0], sum[1] + e[1], sum[2] + e[2]];
                    }
                    let (_, pb, pr) = ypbpr(sum[0] * 0.25, sum[1] * 0.25, sum[2] * 0.25);
                    cb[cx] = chroma_code(pb);
                    cr[cx] = chroma_code(pr);
                }
                // Edge blocks (odd width or height) average the pixels they have.
                for cx in full..cw {
                    let (mut sr, mut sg, mut sb) = (0.0f32, 0.0f32, 0.0f32);
                    let mut n = 0.0f32;
                    for dy in 0..rows {
                        for x in 2 * cx..(2 * cx + 2).min(w) {
                            let i = dy * w + x;
                            let [r, g, b] = rgb_rows[i].map(linear_to_srgb);
                            luma[i] = luma_code(KR * r + KG * g + KB * b);
                            sr += r;
                            sg += g;
                            sb += b;
                            n += 1.0;
                        }
                    }
                    let (_, pb, pr) = ypbpr(sr / n, sg / n, sb / n);
                    cb[cx] = chroma_code(pb);
                    cr[cx] = chroma_code(pr);
                }
            });
        Ok(())
    }
}

/// Most lanes of any instruction set the dispatch may choose (AVX-512: 16).
const MAX_LANES: usize = 16;

/// The first full 2x2 blocks of a pair of rows, as many as fill whole vectors (one block per
/// lane: each step reads `2 * lanes` pixels of both rows). Returns the blocks done.
struct RowPair<'a> {
    /// Both rows' linear RGB, flattened (`6 * width` floats).
    rgb: &'a [f32],
    width: usize,
    luma: &'a mut [u8],
    cb: &'a mut [u8],
    cr: &'a mut [u8],
    /// Full blocks in the row pair (`width / 2`, or 0 for a last single row).
    blocks: usize,
}

impl WithSimd for RowPair<'_> {
    type Output = usize;

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) -> usize {
        let lanes = S::F32_LANES;
        if lanes > MAX_LANES {
            return 0;
        }
        let w = self.width;
        let splat = |v: f32| simd.splat_f32s(v);
        let blocks = self.blocks / lanes * lanes;
        // Through memory: pulp's shuffles for two vectors are not the record transposes its
        // fallback performs, and these copies cost little beside the curve.
        let mut soa = [[0.0f32; MAX_LANES]; 6];
        let mut codes = [[0u32; MAX_LANES]; 2];
        for first in (0..blocks).step_by(lanes) {
            let x = 2 * first;
            let mut sum = [splat(0.0); 3];
            for row in 0..2 {
                let start = 3 * (row * w + x);
                // Pixel pairs as records of six: r, g, b of the even pixel, then of the odd.
                for (j, record) in self.rgb[start..start + 6 * lanes].chunks_exact(6).enumerate() {
                    for (channel, &v) in soa.iter_mut().zip(record) {
                        channel[j] = v;
                    }
                }
                let e: [S::f32s; 6] =
                    std::array::from_fn(|k| srgb_encode(simd, simd.partial_load_f32s(&soa[k][..lanes])));
                let luma_of = |r, g, b| simd.mul_add_f32s(splat(219.0), luma_lanes(simd, r, g, b), splat(16.0));
                let even = luma_of(e[0], e[1], e[2]);
                let odd = luma_of(e[3], e[4], e[5]);
                simd.partial_store_u32s(&mut codes[0][..lanes], code_bits(simd, even));
                simd.partial_store_u32s(&mut codes[1][..lanes], code_bits(simd, odd));
                let out = &mut self.luma[row * w + x..row * w + x + 2 * lanes];
                for (j, pair) in out.chunks_exact_mut(2).enumerate() {
                    pair[0] = codes[0][j] as u8;
                    pair[1] = codes[1][j] as u8;
                }
                for c in 0..3 {
                    sum[c] = simd.add_f32s(sum[c], simd.add_f32s(e[c], e[c + 3]));
                }
            }
            let [r, g, b] = sum.map(|v| simd.mul_f32s(v, splat(0.25)));
            let y = luma_lanes(simd, r, g, b);
            let pb = simd.mul_f32s(simd.sub_f32s(b, y), splat(1.0 / (2.0 * (1.0 - KB))));
            let pr = simd.mul_f32s(simd.sub_f32s(r, y), splat(1.0 / (2.0 * (1.0 - KR))));
            for (plane, p) in [(&mut *self.cb, pb), (&mut *self.cr, pr)] {
                simd.partial_store_u32s(
                    &mut codes[0][..lanes],
                    code_bits(simd, simd.mul_add_f32s(splat(224.0), p, splat(128.0))),
                );
                for (o, &c) in plane[first..first + lanes].iter_mut().zip(&codes[0]) {
                    *o = c as u8;
                }
            }
        }
        blocks
    }
}

/// `Y' = Kr R' + Kg G' + Kb B'` lane by lane.
#[inline(always)]
fn luma_lanes<S: Simd>(simd: S, r: S::f32s, g: S::f32s, b: S::f32s) -> S::f32s {
    let splat = |v: f32| simd.splat_f32s(v);
    simd.mul_add_f32s(splat(KR), r, simd.mul_add_f32s(splat(KG), g, simd.mul_f32s(splat(KB), b)))
}

/// [`code`] lane by lane: the low byte of each lane is the rounded, clamped 8-bit code.
#[inline(always)]
fn code_bits<S: Simd>(simd: S, v: S::f32s) -> S::u32s {
    let clamped = simd.min_f32s(simd.max_f32s(v, simd.splat_f32s(0.0)), simd.splat_f32s(255.0));
    simd.transmute_u32s_f32s(simd.add_f32s(clamped, simd.splat_f32s(MAGIC)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The standard 8-bit BT.709 limited-range code values of the primaries, black and white
    /// (e.g. ITU-R BT.709 colour bars; Y = 16 + 219 Y', Cb/Cr = 128 + 224 P).
    #[test]
    fn primaries_black_and_white_give_the_standard_code_values() {
        let cases = [
            ([0.0, 0.0, 0.0], (16, 128, 128)),
            ([1.0, 1.0, 1.0], (235, 128, 128)),
            ([1.0, 0.0, 0.0], (63, 102, 240)),
            ([0.0, 1.0, 0.0], (173, 42, 26)),
            ([0.0, 0.0, 1.0], (32, 240, 118)),
            ([1.0, 1.0, 0.0], (219, 16, 138)),
            ([0.0, 1.0, 1.0], (188, 154, 16)),
            ([1.0, 0.0, 1.0], (78, 214, 230)),
        ];
        for (rgb, expected) in cases {
            assert_eq!(linear_rgb_to_ycbcr(rgb), expected, "{rgb:?}");
            // The fast path over a uniform 4x2 picture gives the same codes everywhere.
            let img = Yuv420::from_linear_rgb(4, 2, &[rgb; 8]).unwrap();
            assert!(img.y.iter().all(|&y| y == expected.0), "{rgb:?}: {:?}", img.y);
            assert!(img.u.iter().all(|&u| u == expected.1), "{rgb:?}: {:?}", img.u);
            assert!(img.v.iter().all(|&v| v == expected.2), "{rgb:?}: {:?}", img.v);
        }
        // Linear mid-grey 0.2140 is sRGB 0.5 (to 4 digits): Y = 16 + 219 * 0.5 = 125.5 → 125 or 126.
        let (y, u, v) = linear_rgb_to_ycbcr([0.214_041; 3]);
        assert!((125..=126).contains(&y) && u == 128 && v == 128, "{y} {u} {v}");
        // Out-of-range and NaN input clamp rather than wrap.
        assert_eq!(linear_rgb_to_ycbcr([7.0, 7.0, 7.0]), (235, 128, 128));
        assert_eq!(Yuv420::from_linear_rgb(2, 2, &[[f32::NAN, -1.0, 0.0]; 4]).unwrap().y, vec![16; 4]);
    }

    #[test]
    fn chroma_is_the_mean_of_each_2x2_block() {
        // Left block: two red and two blue pixels; right block: all white.
        let (r, b, w) = ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]);
        let img = Yuv420::from_linear_rgb(4, 2, &[r, b, w, w, b, r, w, w]).unwrap();
        assert_eq!(img.y, vec![63, 32, 235, 235, 32, 63, 235, 235]);
        // Mean R'G'B' = (0.5, 0, 0.5): Y' = 0.1424, Pb = 0.1927..., Pr = 0.2271...
        let (_, pb, pr) = ypbpr(0.5, 0.0, 0.5);
        assert_eq!((img.u[0], img.v[0]), (chroma_code(pb), chroma_code(pr)));
        assert_eq!((img.u[0], img.v[0]), (171, 179));
        assert_eq!((img.u[1], img.v[1]), (128, 128));
    }

    #[test]
    fn odd_sizes_are_handled_and_bad_sizes_rejected() {
        let img = Yuv420::from_linear_rgb(3, 3, &[[1.0, 0.0, 0.0]; 9]).unwrap();
        assert_eq!((img.chroma_width(), img.chroma_height()), (2, 2));
        assert_eq!((img.y.len(), img.u.len(), img.v.len()), (9, 4, 4));
        assert!(img.u.iter().all(|&u| u == 102) && img.v.iter().all(|&v| v == 240));
        // The edge block of a 3x1 picture averages only what it has.
        let img = Yuv420::from_linear_rgb(3, 1, &[[0.0; 3], [0.0; 3], [0.0, 0.0, 1.0]]).unwrap();
        assert_eq!((img.u.clone(), img.v.clone()), (vec![128, 240], vec![128, 118]));
        assert_eq!(Yuv420::new(0, 4), Err(YuvError::EmptyImage { width: 0, height: 4 }));
        assert!(matches!(Yuv420::from_linear_rgb(2, 2, &[[0.0; 3]; 3]), Err(YuvError::WrongLength { got: 3, .. })));
    }

    /// The curve through each instruction set the CPU offers, one vector of inputs at a time.
    fn encode_with(arch: Arch, xs: &[f32]) -> Vec<f32> {
        struct Encode<'a>(&'a [f32]);
        impl WithSimd for Encode<'_> {
            type Output = Vec<f32>;
            fn with_simd<S: Simd>(self, simd: S) -> Vec<f32> {
                let mut out = vec![0.0; self.0.len()];
                for (o, x) in out.chunks_mut(S::F32_LANES).zip(self.0.chunks(S::F32_LANES)) {
                    simd.partial_store_f32s(o, srgb_encode(simd, simd.partial_load_f32s(x)));
                }
                out
            }
        }
        arch.dispatch(Encode(xs))
    }

    #[test]
    fn the_transfer_polynomials_match_the_exact_curve() {
        let xs: Vec<f32> = (0..=200_000).map(|i| i as f32 / 200_000.0).collect();
        for arch in [Arch::Scalar, Arch::new()] {
            let encoded = encode_with(arch, &xs);
            let worst = xs.iter().zip(&encoded).map(|(&x, &e)| (e - linear_to_srgb_exact(x)).abs()).fold(0.0, f32::max);
            // A tenth of the old table's 1e-4 bound; 8-bit codes are 1/255 apart.
            assert!(worst < 1e-5, "{arch:?}: error {worst}");
            // Around the knee, the two segments meet.
            let knee = encode_with(arch, &[LINEAR_KNEE, LINEAR_KNEE * 1.0001, 0.5, 1.0]);
            assert!((knee[0] - 0.040_45).abs() < 1e-5 && (knee[1] - knee[0]).abs() < 1e-5, "{knee:?}");
            assert!((knee[3] - 1.0).abs() < 1e-6, "{knee:?}");
            // Out of range and NaN clamp; never NaN.
            let odd = encode_with(arch, &[f32::NAN, -1.0, -0.0, 2.0, f32::INFINITY, f32::NEG_INFINITY, 1e-30, 5e-39]);
            assert_eq!(&odd[..3], &[0.0, 0.0, 0.0]);
            assert!((odd[3] - 1.0).abs() < 1e-6 && (odd[4] - 1.0).abs() < 1e-6 && odd[5] == 0.0, "{odd:?}");
            assert!(odd[6] >= 0.0 && odd[6] < 1e-28 && odd[7] >= 0.0 && odd[7] < 1e-37, "{odd:?}");
        }
        assert_eq!(linear_to_srgb(0.0), 0.0);
        assert_eq!(linear_to_srgb(f32::NAN), 0.0);
    }

    /// A linear RGB picture with values in and out of range, and NaN now and then.
    fn nasty_picture(n: usize, seed: u32) -> Vec<[f32; 3]> {
        (0..n)
            .map(|i| {
                let k = (i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed.wrapping_mul(40_503));
                let v = |s: u32| match (k >> s) % 41 {
                    0 => f32::NAN,
                    1 => -0.3,
                    2 => 1.7,
                    3 => 0.002,
                    q => (q * 37 % 1000) as f32 / 999.0,
                };
                [v(0), v(7), v(14)]
            })
            .collect()
    }

    #[test]
    fn the_vector_conversion_agrees_with_its_scalar_twin() {
        // Widths around the vector step (16 pixels with AVX2), odd sizes, a single row.
        for (w, h) in [(640, 8), (33, 5), (16, 2), (15, 2), (31, 1), (2, 2), (48, 3)] {
            let rgb = nasty_picture((w * h) as usize, w * 7 + h);
            let mut fast = Yuv420::new(w, h).unwrap();
            fast.fill_with(Arch::new(), &rgb).unwrap();
            let mut twin = Yuv420::new(w, h).unwrap();
            twin.fill_with(Arch::Scalar, &rgb).unwrap();
            // Fused multiply-adds round differently: a code may move by one at a tie.
            for (plane, a, b) in [("Y", &fast.y, &twin.y), ("Cb", &fast.u, &twin.u), ("Cr", &fast.v, &twin.v)] {
                let off = a.iter().zip(b.iter()).map(|(&p, &q)| (i32::from(p) - i32::from(q)).abs()).max();
                assert!(off <= Some(1), "{w}x{h} {plane}: off by {off:?}");
                let same = a.iter().zip(b.iter()).filter(|(p, q)| p == q).count();
                assert!(same * 100 >= a.len() * 99, "{w}x{h} {plane}: {same} of {} equal", a.len());
            }
            // And both against the per-pixel reference.
            for (i, &c) in rgb.iter().enumerate() {
                let (y, _, _) = linear_rgb_to_ycbcr(c);
                assert!((i32::from(fast.y[i]) - i32::from(y)).abs() <= 1, "{w}x{h} pixel {i}");
            }
        }
    }

    proptest::proptest! {
        /// The parallel plane conversion agrees with the per-pixel reference within one code.
        #[test]
        fn planes_agree_with_the_per_pixel_reference(
            w in 1u32..9, h in 1u32..9, seed in 0u32..10_000,
        ) {
            let n = (w * h) as usize;
            let rgb: Vec<[f32; 3]> = (0..n)
                .map(|i| {
                    let k = (i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed);
                    [(k % 1000) as f32 / 999.0, (k / 1000 % 1000) as f32 / 999.0, (k / 7 % 1000) as f32 / 999.0]
                })
                .collect();
            let img = Yuv420::from_linear_rgb(w, h, &rgb).unwrap();
            for (i, &c) in rgb.iter().enumerate() {
                let (y, _, _) = linear_rgb_to_ycbcr(c);
                proptest::prop_assert!((i32::from(img.y[i]) - i32::from(y)).abs() <= 1);
            }
        }
    }
}
