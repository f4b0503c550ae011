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
//! The transfer curve goes through a 4096-entry table with linear interpolation (a `powf`
//! per channel would cost more than the rest of the conversion); its error against the exact
//! curve is below 1e-4 (0.03 of an 8-bit code), checked in the tests.

use std::sync::OnceLock;

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

/// The exact sRGB transfer function, linear → encoded, for `x` clamped to `[0, 1]`.
pub fn linear_to_srgb_exact(x: f32) -> f32 {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    if x <= 0.003_130_8 { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 }
}

const TABLE_SIZE: usize = 4096;

/// `[value at i / N, value at (i + 1) / N - value at i / N]` for `i < N`, then the value at 1.
struct SrgbTable {
    knots: [[f32; 2]; TABLE_SIZE],
    one: f32,
}

fn srgb_table() -> &'static SrgbTable {
    static TABLE: OnceLock<Box<SrgbTable>> = OnceLock::new();
    TABLE.get_or_init(|| {
        let at = |i: usize| linear_to_srgb_exact(i as f32 / TABLE_SIZE as f32);
        let mut t = Box::new(SrgbTable { knots: [[0.0; 2]; TABLE_SIZE], one: at(TABLE_SIZE) });
        for (i, k) in t.knots.iter_mut().enumerate() {
            *k = [at(i), at(i + 1) - at(i)];
        }
        t
    })
}

/// The sRGB transfer function through the table (see the module docs). NaN maps to 0.
#[inline]
pub fn linear_to_srgb(x: f32) -> f32 {
    srgb_lookup(srgb_table(), x)
}

#[inline]
#[allow(clippy::manual_clamp)] // `clamp` would keep NaN; this sends it to 0
fn srgb_lookup(table: &SrgbTable, x: f32) -> f32 {
    // `max` then `min` also send NaN to 0 (f32::max returns the non-NaN operand).
    let x = x.max(0.0).min(1.0) * TABLE_SIZE as f32;
    if x >= TABLE_SIZE as f32 {
        return table.one;
    }
    // Integer part without a (saturating, slow) float-to-int cast: adding 2^23 rounds x - 0.5
    // to an integer held in the mantissa. Ties may round down by one; the interpolation
    // weight then is 1 and the result the same.
    let shifted = (x - 0.5) + MAGIC;
    let i = shifted.to_bits().wrapping_sub(MAGIC.to_bits()) as usize;
    let frac = x - (shifted - MAGIC);
    // The mask is a no-op (i < N) that lets the compiler drop the bounds check.
    let [value, step] = table.knots[i & (TABLE_SIZE - 1)];
    value + frac * step
}

/// 1.5 * 2^23: adding it to a float in [-2^22, 2^22) gives a float in [2^23, 2^24), where
/// the spacing is 1: the sum's bit pattern minus MAGIC's is the rounded integer.
const MAGIC: f32 = 12_582_912.0;

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
    /// Rows pairs are converted in parallel (rayon).
    pub fn fill_from_linear_rgb(&mut self, rgb: &[[f32; 3]]) -> Result<(), YuvError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if rgb.len() != w * h {
            return Err(YuvError::WrongLength { width: self.width, height: self.height, got: rgb.len() });
        }
        let cw = w.div_ceil(2);
        let table = srgb_table();
        self.y
            .par_chunks_mut(2 * w)
            .zip(self.u.par_chunks_mut(cw))
            .zip(self.v.par_chunks_mut(cw))
            .zip(rgb.par_chunks(2 * w))
            .for_each(|(((y_rows, u_row), v_row), rgb_rows)| {
                let rows = y_rows.len() / w;
                // Full 2x2 blocks: fixed indices, no edge checks.
                let full = if rows == 2 { w / 2 } else { 0 };
                for cx in 0..full {
                    let x = 2 * cx;
                    let mut sum = [0.0f32; 3];
                    for i in [x, x + 1, w + x, w + x + 1] {
                        let [r, g, b] = rgb_rows[i];
                        let e = [srgb_lookup(table, r), srgb_lookup(table, g), srgb_lookup(table, b)];
                        y_rows[i] = luma_code(KR * e[0] + KG * e[1] + KB * e[2]);
                        sum = [sum[0] + e[0], sum[1] + e[1], sum[2] + e[2]];
                    }
                    let (_, pb, pr) = ypbpr(sum[0] * 0.25, sum[1] * 0.25, sum[2] * 0.25);
                    u_row[cx] = chroma_code(pb);
                    v_row[cx] = chroma_code(pr);
                }
                // Edge blocks (odd width or height) average the pixels they have.
                for cx in full..cw {
                    let (mut sr, mut sg, mut sb) = (0.0f32, 0.0f32, 0.0f32);
                    let mut n = 0.0f32;
                    for dy in 0..rows {
                        for x in 2 * cx..(2 * cx + 2).min(w) {
                            let i = dy * w + x;
                            let [r, g, b] = rgb_rows[i];
                            let (r, g, b) = (srgb_lookup(table, r), srgb_lookup(table, g), srgb_lookup(table, b));
                            y_rows[i] = luma_code(KR * r + KG * g + KB * b);
                            sr += r;
                            sg += g;
                            sb += b;
                            n += 1.0;
                        }
                    }
                    let (_, pb, pr) = ypbpr(sr / n, sg / n, sb / n);
                    u_row[cx] = chroma_code(pb);
                    v_row[cx] = chroma_code(pr);
                }
            });
        Ok(())
    }
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

    #[test]
    fn the_transfer_table_matches_the_exact_curve() {
        let mut worst = 0.0f32;
        for i in 0..=100_000 {
            let x = i as f32 / 100_000.0;
            worst = worst.max((linear_to_srgb(x) - linear_to_srgb_exact(x)).abs());
        }
        assert!(worst < 1e-4, "table error {worst}");
        assert_eq!(linear_to_srgb(0.0), 0.0);
        assert_eq!(linear_to_srgb(1.0), linear_to_srgb_exact(1.0));
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-6);
        assert_eq!(linear_to_srgb(f32::NAN), 0.0);
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
