//! Smaller pictures for narrow links (issue 15, part 4): at resolution level `L` the media
//! thread codes the fused picture at `1 / 2^L` of each side, each coded pixel the mean of a
//! `2^L x 2^L` square of fused ones, in linear light (averaging sRGB codes would darken
//! edges). [`crate::congestion::RateController`] chooses the level; this module says which
//! levels a picture allows and makes the smaller picture.
//!
//! The viewer's browser scales the video back to its element (`client/nephele.js` keeps the
//! element at the session's size) and a headset's layer samples it as a texture, so a
//! smaller stream needs nothing from the client but a decoder that takes a new SPS, which
//! every H.264 decoder does.

use crate::encode::MIN_SIDE;
use crate::fusion::FrameLayout;

/// The deepest level tried at all: a sixteenth of the pixels (the master takes poses down
/// to it).
pub const MAX_LEVEL: u32 = nephele_proto::pose::MAX_SCALE_LEVEL;

/// Fewest pixels a smaller picture may have: 320x180, libwebrtc's default floor for its own
/// resolution scaling (below it a picture says too little to be worth the bits).
pub const MIN_SCALED_PIXELS: u64 = 320 * 180;

/// The deepest level `layout` allows (0: none): every view's sides divisible by `2^level`
/// (so views do not bleed into each other and keep their places in the grid), the smaller
/// picture's sides even (4:2:0) and at least the encoder's least side, and at least
/// [`MIN_SCALED_PIXELS`] pixels.
pub fn deepest_level(layout: &FrameLayout) -> u32 {
    let allowed = |level: u32| {
        let factor = 1u32 << level;
        let (w, h) = (layout.width() / factor, layout.height() / factor);
        layout.view_width().is_multiple_of(factor)
            && layout.view_height().is_multiple_of(factor)
            && w.is_multiple_of(2)
            && h.is_multiple_of(2)
            && w.min(h) >= MIN_SIDE
            && u64::from(w) * u64::from(h) >= MIN_SCALED_PIXELS
    };
    (1..=MAX_LEVEL).take_while(|&level| allowed(level)).last().unwrap_or(0)
}

/// The `width x height` picture `rgb` (row-major) at `level`, written into `out` (resized to
/// fit): each pixel the mean of its `2^level` square. `width` and `height` must be
/// multiples of `2^level` (what [`deepest_level`] checks); level 0 copies.
///
/// # Panics
///
/// When `rgb` does not hold `width * height` pixels (a programming error of the caller).
pub fn downsample_into(width: u32, height: u32, rgb: &[[f32; 3]], level: u32, out: &mut Vec<[f32; 3]>) {
    let (width, height) = (width as usize, height as usize);
    assert_eq!(rgb.len(), width * height, "picture of {width}x{height} with {} pixels", rgb.len());
    let factor = 1usize << level;
    let (w, h) = (width / factor, height / factor);
    out.clear();
    out.resize(w * h, [0.0; 3]);
    let norm = 1.0 / (factor * factor) as f32;
    for (y, row) in out.chunks_exact_mut(w.max(1)).enumerate().take(h) {
        for dy in 0..factor {
            let source = &rgb[(y * factor + dy) * width..][..w * factor];
            for (pixel, square) in row.iter_mut().zip(source.chunks_exact(factor)) {
                for s in square {
                    pixel[0] += s[0];
                    pixel[1] += s[1];
                    pixel[2] += s[2];
                }
            }
        }
        for pixel in row {
            *pixel = pixel.map(|c| c * norm);
        }
    }
}

/// The picture `rgb` of `width x height` at level `from`, taken to level `to` (of the same
/// full picture) into `out`: the mean of squares going down ([`downsample_into`]), each pixel
/// repeated over its square going up (only while the farm's frames catch up with a level
/// that rose: a frame or two).
pub fn relevel_into(width: u32, height: u32, rgb: &[[f32; 3]], from: u32, to: u32, out: &mut Vec<[f32; 3]>) {
    if to >= from {
        return downsample_into(width, height, rgb, to - from, out);
    }
    let factor = 1usize << (from - to);
    let (width, height) = (width as usize, height as usize);
    assert_eq!(rgb.len(), width * height, "picture of {width}x{height} with {} pixels", rgb.len());
    let w = width * factor;
    out.clear();
    out.reserve(w * height * factor);
    for row in rgb.chunks_exact(width.max(1)).take(height) {
        let start = out.len();
        out.extend(row.iter().flat_map(|p| std::iter::repeat_n(*p, factor)));
        for _ in 1..factor {
            out.extend_from_within(start..start + w);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_follow_the_grid_the_encoder_and_the_least_picture() {
        let level = |w, h, views, columns| deepest_level(&FrameLayout::grid(w, h, views, columns).unwrap());
        // 640x480: 320x240 (76,800 pixels); 160x120 is below 320x180.
        assert_eq!(level(640, 480, 1, 1), 1);
        // 1280x720 down to 320x180 exactly; 1920x1080 to 480x270 (MAX_LEVEL).
        assert_eq!(level(1280, 720, 1, 1), 2);
        assert_eq!(level(1920, 1080, 1, 1), 2);
        // A stereo pair of 640x480 eyes: 1280x480 packed, 320x120 at level 2 (38,400).
        assert_eq!(level(640, 480, 2, 2), 1);
        // Sides not divisible, or odd once halved: none.
        assert_eq!(level(642, 480, 1, 1), 0);
        assert_eq!(level(644, 482, 1, 1), 0);
        // Small pictures keep their size.
        assert_eq!(level(320, 240, 1, 1), 0);
        assert_eq!(level(64, 48, 1, 1), 0);
    }

    #[test]
    fn each_coded_pixel_is_the_mean_of_its_square_in_linear_light() {
        let (w, h) = (8u32, 4u32);
        let rgb: Vec<[f32; 3]> = (0..w * h).map(|i| [i as f32, (i % w) as f32, 1.0]).collect();
        let mut out = Vec::new();
        downsample_into(w, h, &rgb, 1, &mut out);
        assert_eq!(out.len(), 8);
        for y in 0..2usize {
            for x in 0..4usize {
                let mut sum = [0.0f32; 3];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let s = rgb[(2 * y + dy) * w as usize + 2 * x + dx];
                    (0..3).for_each(|c| sum[c] += s[c] / 4.0);
                }
                assert_eq!(out[y * 4 + x], sum, "pixel {x},{y}");
            }
        }
        // Level 2: one row of two pixels; level 0 copies; a buffer in use is reused.
        downsample_into(w, h, &rgb, 2, &mut out);
        assert_eq!(out.len(), 2);
        let mean: f32 = (0..4).flat_map(|y| (0..4).map(move |x| (y * 8 + x) as f32)).sum::<f32>() / 16.0;
        assert_eq!(out[0], [mean, 1.5, 1.0]);
        downsample_into(w, h, &rgb, 0, &mut out);
        assert_eq!(out, rgb);
    }

    #[test]
    fn a_picture_goes_up_a_level_by_repeating_pixels_and_down_by_means() {
        let rgb: Vec<[f32; 3]> = (0..6).map(|i| [i as f32; 3]).collect();
        let mut up = Vec::new();
        relevel_into(3, 2, &rgb, 1, 0, &mut up);
        let want: Vec<f32> =
            [0., 0., 1., 1., 2., 2., 0., 0., 1., 1., 2., 2., 3., 3., 4., 4., 5., 5., 3., 3., 4., 4., 5., 5.].into();
        assert_eq!(up.iter().map(|p| p[0]).collect::<Vec<_>>(), want);
        // Down again gives the picture back; two levels up is 4x4 squares.
        let mut back = Vec::new();
        relevel_into(6, 4, &up, 0, 1, &mut back);
        assert_eq!(back, rgb);
        relevel_into(3, 2, &rgb, 2, 0, &mut up);
        assert_eq!((up.len(), up[12 * 3 + 3], up[12 * 4 + 4]), (12 * 8, [0.0; 3], [4.0; 3]));
    }

    #[test]
    fn views_of_a_stereo_pair_stay_apart() {
        // Left eye all 0, right eye all 1: after scaling no coded pixel mixes the two.
        let layout = FrameLayout::stereo(4, 2).unwrap();
        let rgb: Vec<[f32; 3]> =
            (0..layout.pixel_count()).map(|i| if i % 8 < 4 { [0.0; 3] } else { [1.0; 3] }).collect();
        let mut out = Vec::new();
        downsample_into(layout.width(), layout.height(), &rgb, 1, &mut out);
        assert_eq!(out, vec![[0.0; 3], [0.0; 3], [1.0; 3], [1.0; 3]]);
    }
}
