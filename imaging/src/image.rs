//! In-memory images and their files.
//!
//! * [`RgbaImage`] holds what a PNG of a NeRF-synthetic dataset holds: sRGB-encoded colour with
//!   straight (not premultiplied) alpha, every value in `[0, 1]` as stored. It is read from and
//!   written to 8-bit (or, when reading, 16-bit) PNG files.
//! * [`FloatImage`] holds arbitrary float channels (depth, normals, positions: "AOVs") and is
//!   written to OpenEXR, or for a quick look to a normalised 16-bit grey PNG.
//! * [`linear_to_srgb`] and [`srgb_to_linear`] convert between the renderer's linear radiance
//!   and the stored encoding.
//!
//! Nothing here panics on the contents of a file: every decoding problem is an [`ImageError`]
//! naming the file.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

/// Errors of image construction, processing and file I/O.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// A file could not be opened, created, read or written.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file was read but its contents could not be decoded.
    #[error("cannot decode {path}: {message}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// What the decoder said.
        message: String,
    },
    /// An image could not be encoded into a file.
    #[error("cannot encode {path}: {message}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// What the encoder said.
        message: String,
    },
    /// A pixel buffer does not have `width * height * channels` entries.
    #[error("a {width}x{height} image with {channels} channel(s) needs {expected} values, got {actual}")]
    BufferSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Channels per pixel.
        channels: usize,
        /// `width * height * channels`.
        expected: usize,
        /// The length that was given.
        actual: usize,
    },
    /// A channel count that the operation does not support.
    #[error("unsupported channel count {channels}: {reason}")]
    Channels {
        /// The channel count.
        channels: usize,
        /// What would have been supported.
        reason: &'static str,
    },
    /// A downscale factor of zero, or one larger than the image.
    #[error("cannot downscale a {width}x{height} image by a factor of {factor}")]
    Downscale {
        /// The factor.
        factor: u32,
        /// Width of the source image.
        width: u32,
        /// Height of the source image.
        height: u32,
    },
    /// A normalisation range that is empty, reversed or not finite.
    #[error("invalid normalisation range [{min}, {max}]: needs finite min < max")]
    Range {
        /// Lower end.
        min: f32,
        /// Upper end.
        max: f32,
    },
}

impl ImageError {
    /// Wraps an error of the `image` crate, keeping I/O errors as [`ImageError::Io`].
    fn from_codec(path: &Path, err: ::image::ImageError, decoding: bool) -> Self {
        match err {
            ::image::ImageError::IoError(source) => Self::Io { path: path.to_path_buf(), source },
            other if decoding => Self::Decode { path: path.to_path_buf(), message: other.to_string() },
            other => Self::Encode { path: path.to_path_buf(), message: other.to_string() },
        }
    }
}

/// Converts a linear value to its sRGB encoding (IEC 61966-2-1, the exact piecewise curve).
/// Values are not clamped: negative inputs stay on the linear segment, NaN stays NaN.
pub fn linear_to_srgb(linear: f32) -> f32 {
    if linear <= 0.003_130_8 { linear * 12.92 } else { 1.055 * linear.powf(1.0 / 2.4) - 0.055 }
}

/// Converts an sRGB-encoded value to linear (IEC 61966-2-1, the exact piecewise curve); the
/// inverse of [`linear_to_srgb`]. Values are not clamped.
pub fn srgb_to_linear(encoded: f32) -> f32 {
    if encoded <= 0.040_45 { encoded / 12.92 } else { ((encoded + 0.055) / 1.055).powf(2.4) }
}

/// Number of pixels of a `width x height` image (cannot overflow on 64-bit targets).
fn pixel_count(width: u32, height: u32) -> usize {
    width as usize * height as usize
}

/// Opens `path` for a decoder of the given format and decodes it.
fn decode_file(path: &Path, format: ::image::ImageFormat) -> Result<::image::DynamicImage, ImageError> {
    let file = File::open(path).map_err(|source| ImageError::Io { path: path.to_path_buf(), source })?;
    ::image::ImageReader::with_format(BufReader::new(file), format)
        .decode()
        .map_err(|e| ImageError::from_codec(path, e, true))
}

/// An RGBA image of `f32` values in `[0, 1]` as stored in PNG files: sRGB-encoded colour,
/// straight alpha. Row-major, top row first.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbaImage {
    width: u32,
    height: u32,
    data: Vec<[f32; 4]>,
}

impl RgbaImage {
    /// A `width x height` image of transparent black (all zeros).
    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, data: vec![[0.0; 4]; pixel_count(width, height)] }
    }

    /// An image from row-major pixels, top row first; `pixels.len()` must be `width * height`.
    pub fn from_pixels(width: u32, height: u32, pixels: Vec<[f32; 4]>) -> Result<Self, ImageError> {
        let expected = pixel_count(width, height);
        if pixels.len() != expected {
            return Err(ImageError::BufferSize {
                width,
                height,
                channels: 4,
                expected: expected * 4,
                actual: pixels.len() * 4,
            });
        }
        Ok(Self { width, height, data: pixels })
    }

    /// An image whose pixel `(x, y)` is `f(x, y)`.
    pub fn from_fn(width: u32, height: u32, mut f: impl FnMut(u32, u32) -> [f32; 4]) -> Self {
        let mut data = Vec::with_capacity(pixel_count(width, height));
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self { width, height, data }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Whether the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    fn index(&self, x: u32, y: u32) -> usize {
        y as usize * self.width as usize + x as usize
    }

    /// The pixel at column `x`, row `y` (row 0 is the top).
    ///
    /// # Panics
    /// If `(x, y)` is outside the image; see [`RgbaImage::get`] for a checked version.
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 4] {
        assert!(x < self.width && y < self.height, "pixel ({x}, {y}) outside {}x{}", self.width, self.height);
        self.data[self.index(x, y)]
    }

    /// The pixel at `(x, y)`, or `None` outside the image.
    pub fn get(&self, x: u32, y: u32) -> Option<[f32; 4]> {
        (x < self.width && y < self.height).then(|| self.data[self.index(x, y)])
    }

    /// Sets the pixel at `(x, y)`.
    ///
    /// # Panics
    /// If `(x, y)` is outside the image.
    pub fn set_pixel(&mut self, x: u32, y: u32, value: [f32; 4]) {
        assert!(x < self.width && y < self.height, "pixel ({x}, {y}) outside {}x{}", self.width, self.height);
        let i = self.index(x, y);
        self.data[i] = value;
    }

    /// All pixels, row-major, top row first.
    pub fn pixels(&self) -> &[[f32; 4]] {
        &self.data
    }

    /// All pixels, mutable, row-major, top row first.
    pub fn pixels_mut(&mut self) -> &mut [[f32; 4]] {
        &mut self.data
    }

    /// Consumes the image, returning its pixels.
    pub fn into_pixels(self) -> Vec<[f32; 4]> {
        self.data
    }

    /// Reads a PNG file: 8 or 16 bits per channel, grey, grey+alpha, RGB or RGBA. Values are
    /// scaled to `[0, 1]` (`v / 255` or `v / 65535`), grey is replicated to RGB, and images
    /// without alpha get alpha 1. No colour management is applied: the stored values are kept.
    pub fn load_png(path: impl AsRef<Path>) -> Result<Self, ImageError> {
        use ::image::DynamicImage as D;
        let path = path.as_ref();
        let decoded = decode_file(path, ::image::ImageFormat::Png)?;
        let (width, height) = (decoded.width(), decoded.height());
        let u8f = |v: u8| f32::from(v) / 255.0;
        let u16f = |v: u16| f32::from(v) / 65535.0;
        let data: Vec<[f32; 4]> = match &decoded {
            D::ImageLuma8(img) => img.pixels().map(|p| [u8f(p[0]), u8f(p[0]), u8f(p[0]), 1.0]).collect(),
            D::ImageLumaA8(img) => img.pixels().map(|p| [u8f(p[0]), u8f(p[0]), u8f(p[0]), u8f(p[1])]).collect(),
            D::ImageRgb8(img) => img.pixels().map(|p| [u8f(p[0]), u8f(p[1]), u8f(p[2]), 1.0]).collect(),
            D::ImageRgba8(img) => img.pixels().map(|p| p.0.map(u8f)).collect(),
            D::ImageLuma16(img) => img.pixels().map(|p| [u16f(p[0]), u16f(p[0]), u16f(p[0]), 1.0]).collect(),
            D::ImageLumaA16(img) => img.pixels().map(|p| [u16f(p[0]), u16f(p[0]), u16f(p[0]), u16f(p[1])]).collect(),
            D::ImageRgb16(img) => img.pixels().map(|p| [u16f(p[0]), u16f(p[1]), u16f(p[2]), 1.0]).collect(),
            D::ImageRgba16(img) => img.pixels().map(|p| p.0.map(u16f)).collect(),
            // PNG decodes to one of the above; anything else goes through the crate's conversion.
            other => other.to_rgba32f().pixels().map(|p| p.0).collect(),
        };
        Self::from_pixels(width, height, data)
    }

    /// Writes an 8-bit RGBA PNG. Values are clamped to `[0, 1]` and rounded to the nearest of
    /// the 256 levels; NaN is written as 0.
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<(), ImageError> {
        let path = path.as_ref();
        // `as u8` saturates and maps NaN to 0.
        let to_u8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        let bytes: Vec<u8> = self.data.iter().flat_map(|p| p.map(to_u8)).collect();
        ::image::save_buffer_with_format(
            path,
            &bytes,
            self.width,
            self.height,
            ::image::ExtendedColorType::Rgba8,
            ::image::ImageFormat::Png,
        )
        .map_err(|e| ImageError::from_codec(path, e, false))
    }

    /// Box-filter downscale by an integer `factor`: the result is `floor(w / factor) x
    /// floor(h / factor)` and each output pixel averages a `factor x factor` block; the
    /// right/bottom remainder is ignored. Colour is averaged premultiplied by alpha and then
    /// un-premultiplied, so that compositing commutes with downscaling and transparent pixels
    /// do not bleed their (meaningless) colour into the edges; fully transparent blocks get
    /// colour 0. Errors if `factor` is 0 or the result would be empty.
    pub fn downscale(&self, factor: u32) -> Result<Self, ImageError> {
        if factor == 0 || self.width / factor == 0 || self.height / factor == 0 {
            return Err(ImageError::Downscale { factor, width: self.width, height: self.height });
        }
        if factor == 1 {
            return Ok(self.clone());
        }
        let (w, h) = (self.width / factor, self.height / factor);
        let n = f64::from(factor) * f64::from(factor);
        let mut out = Vec::with_capacity(pixel_count(w, h));
        for oy in 0..h {
            for ox in 0..w {
                // Accumulate in f64: blocks can be large and values are summed, not averaged.
                let mut sum = [0.0f64; 4];
                for y in oy * factor..(oy + 1) * factor {
                    for x in ox * factor..(ox + 1) * factor {
                        let [r, g, b, a] = self.data[self.index(x, y)].map(f64::from);
                        sum[0] += r * a;
                        sum[1] += g * a;
                        sum[2] += b * a;
                        sum[3] += a;
                    }
                }
                let alpha = sum[3] / n;
                let colour = |c: f64| {
                    if sum[3] > 0.0 { (c / sum[3]) as f32 } else { 0.0 }
                };
                out.push([colour(sum[0]), colour(sum[1]), colour(sum[2]), alpha as f32]);
            }
        }
        Ok(Self { width: w, height: h, data: out })
    }

    /// Composites the image over a constant `background` colour (`rgb * a + bg * (1 - a)`,
    /// on the stored sRGB-encoded values, as NeRF does with a white background) and returns an
    /// opaque image (alpha 1).
    pub fn composite_over(&self, background: [f32; 3]) -> Self {
        let data = self
            .data
            .iter()
            .map(|&[r, g, b, a]| {
                let c = |v: f32, bg: f32| v * a + bg * (1.0 - a);
                [c(r, background[0]), c(g, background[1]), c(b, background[2]), 1.0]
            })
            .collect();
        Self { width: self.width, height: self.height, data }
    }
}

/// An image of `channels` `f32` values per pixel (depth: 1, normals or positions: 3), row-major,
/// top row first, channels interleaved. Values are unrestricted.
#[derive(Debug, Clone, PartialEq)]
pub struct FloatImage {
    width: u32,
    height: u32,
    channels: usize,
    data: Vec<f32>,
}

impl FloatImage {
    /// A `width x height` image of zeros; `channels` must be at least 1.
    pub fn new(width: u32, height: u32, channels: usize) -> Result<Self, ImageError> {
        if channels == 0 {
            return Err(ImageError::Channels { channels, reason: "an image needs at least one channel" });
        }
        Ok(Self { width, height, channels, data: vec![0.0; pixel_count(width, height) * channels] })
    }

    /// An image from interleaved row-major data of length `width * height * channels`.
    pub fn from_data(width: u32, height: u32, channels: usize, data: Vec<f32>) -> Result<Self, ImageError> {
        if channels == 0 {
            return Err(ImageError::Channels { channels, reason: "an image needs at least one channel" });
        }
        let expected = pixel_count(width, height) * channels;
        if data.len() != expected {
            return Err(ImageError::BufferSize { width, height, channels, expected, actual: data.len() });
        }
        Ok(Self { width, height, channels, data })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Values per pixel.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// All values, interleaved, row-major, top row first.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// All values, mutable.
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }

    fn offset(&self, x: u32, y: u32) -> usize {
        (y as usize * self.width as usize + x as usize) * self.channels
    }

    /// The values of pixel `(x, y)`, or `None` outside the image.
    pub fn pixel(&self, x: u32, y: u32) -> Option<&[f32]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let o = self.offset(x, y);
        Some(&self.data[o..o + self.channels])
    }

    /// Channel `c` of pixel `(x, y)`, or `None` outside the image.
    pub fn get(&self, x: u32, y: u32, c: usize) -> Option<f32> {
        self.pixel(x, y).and_then(|p| p.get(c).copied())
    }

    /// Sets channel `c` of pixel `(x, y)`.
    ///
    /// # Panics
    /// If `(x, y, c)` is outside the image.
    pub fn set(&mut self, x: u32, y: u32, c: usize, value: f32) {
        assert!(
            x < self.width && y < self.height && c < self.channels,
            "({x}, {y}, channel {c}) outside {}x{}x{}",
            self.width,
            self.height,
            self.channels
        );
        let o = self.offset(x, y);
        self.data[o + c] = value;
    }

    /// A one-channel image holding channel `c` of this one.
    pub fn channel(&self, c: usize) -> Result<Self, ImageError> {
        if c >= self.channels {
            return Err(ImageError::Channels { channels: self.channels, reason: "channel index out of range" });
        }
        let data = self.data.chunks_exact(self.channels).map(|p| p[c]).collect();
        Ok(Self { width: self.width, height: self.height, channels: 1, data })
    }

    /// Box-filter downscale by an integer `factor` (see [`RgbaImage::downscale`] for the size
    /// rule), every channel averaged.
    pub fn downscale(&self, factor: u32) -> Result<Self, ImageError> {
        self.downscale_impl(factor, false)
    }

    /// Like [`FloatImage::downscale`] but averaging only non-zero values, each channel on its
    /// own; a block of zeros stays 0. Meant for depth, where 0 means "no hit": averaging the
    /// misses in would pull silhouette depths towards the camera.
    pub fn downscale_ignoring_zeros(&self, factor: u32) -> Result<Self, ImageError> {
        self.downscale_impl(factor, true)
    }

    fn downscale_impl(&self, factor: u32, skip_zeros: bool) -> Result<Self, ImageError> {
        if factor == 0 || self.width / factor == 0 || self.height / factor == 0 {
            return Err(ImageError::Downscale { factor, width: self.width, height: self.height });
        }
        let (w, h, ch) = (self.width / factor, self.height / factor, self.channels);
        let mut out = Vec::with_capacity(pixel_count(w, h) * ch);
        let mut sum = vec![0.0f64; ch];
        let mut count = vec![0u64; ch];
        for oy in 0..h {
            for ox in 0..w {
                sum.iter_mut().for_each(|s| *s = 0.0);
                count.iter_mut().for_each(|n| *n = 0);
                for y in oy * factor..(oy + 1) * factor {
                    for x in ox * factor..(ox + 1) * factor {
                        let o = self.offset(x, y);
                        for c in 0..ch {
                            let v = self.data[o + c];
                            if !skip_zeros || v != 0.0 {
                                sum[c] += f64::from(v);
                                count[c] += 1;
                            }
                        }
                    }
                }
                out.extend(sum.iter().zip(&count).map(|(&s, &n)| if n > 0 { (s / n as f64) as f32 } else { 0.0 }));
            }
        }
        Ok(Self { width: w, height: h, channels: ch, data: out })
    }

    /// Writes a 32-bit float OpenEXR file. The `image` crate writes only RGB and RGBA, so a
    /// one-channel image is written as RGB with the value replicated, and a two-channel one as
    /// RGB with B = 0; three and four channels are written as RGB and RGBA. Reading such a file
    /// back with [`FloatImage::load_exr`] gives 3 channels; take [`FloatImage::channel`] 0.
    pub fn save_exr(&self, path: impl AsRef<Path>) -> Result<(), ImageError> {
        let path = path.as_ref();
        let (colour, data): (_, std::borrow::Cow<'_, [f32]>) = match self.channels {
            1 => (::image::ExtendedColorType::Rgb32F, self.data.iter().flat_map(|&v| [v, v, v]).collect()),
            2 => (
                ::image::ExtendedColorType::Rgb32F,
                self.data.chunks_exact(2).flat_map(|p| [p[0], p[1], 0.0]).collect(),
            ),
            3 => (::image::ExtendedColorType::Rgb32F, self.data.as_slice().into()),
            4 => (::image::ExtendedColorType::Rgba32F, self.data.as_slice().into()),
            channels => {
                return Err(ImageError::Channels { channels, reason: "OpenEXR output supports 1 to 4" });
            }
        };
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_ne_bytes()).collect();
        ::image::save_buffer_with_format(path, &bytes, self.width, self.height, colour, ::image::ImageFormat::OpenExr)
            .map_err(|e| ImageError::from_codec(path, e, false))
    }

    /// Reads an RGB or RGBA OpenEXR file (the `image` crate's decoder reads only those) as a
    /// 3- or 4-channel image of 32-bit floats.
    pub fn load_exr(path: impl AsRef<Path>) -> Result<Self, ImageError> {
        let path = path.as_ref();
        let decoded = decode_file(path, ::image::ImageFormat::OpenExr)?;
        let (width, height) = (decoded.width(), decoded.height());
        match decoded {
            ::image::DynamicImage::ImageRgb32F(img) => Self::from_data(width, height, 3, img.into_raw()),
            other => Self::from_data(width, height, 4, other.into_rgba32f().into_raw()),
        }
    }

    /// Writes a one-channel image as a 16-bit grey PNG, mapping `[min, max]` linearly to
    /// `[0, 65535]` (values outside are clamped, NaN becomes 0). For viewing depth maps.
    pub fn save_png_normalised(&self, path: impl AsRef<Path>, min: f32, max: f32) -> Result<(), ImageError> {
        let path = path.as_ref();
        if self.channels != 1 {
            return Err(ImageError::Channels {
                channels: self.channels,
                reason: "normalised PNG output needs exactly one channel",
            });
        }
        if !(min.is_finite() && max.is_finite() && min < max) {
            return Err(ImageError::Range { min, max });
        }
        let scale = 1.0 / (f64::from(max) - f64::from(min));
        let bytes: Vec<u8> = self
            .data
            .iter()
            .flat_map(|&v| {
                let t = ((f64::from(v) - f64::from(min)) * scale).clamp(0.0, 1.0);
                // `as u16` maps NaN to 0.
                ((t * 65535.0).round() as u16).to_ne_bytes()
            })
            .collect();
        ::image::save_buffer_with_format(
            path,
            &bytes,
            self.width,
            self.height,
            ::image::ExtendedColorType::L16,
            ::image::ImageFormat::Png,
        )
        .map_err(|e| ImageError::from_codec(path, e, false))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp() -> tempfile::TempDir {
        tempfile::tempdir().expect("temporary directory")
    }

    /// A test image whose values are exact 8-bit levels.
    fn levels_image(width: u32, height: u32) -> RgbaImage {
        RgbaImage::from_fn(width, height, |x, y| {
            let l = |k: u32| (k % 256) as f32 / 255.0;
            [l(x * 37 + y * 11), l(x * 5 + y * 91 + 7), l(x * y * 13 + 100), l(x * 17 + y * 29 + 3)]
        })
    }

    #[test]
    fn png_round_trip_is_exact_for_8_bit_levels() {
        let dir = tmp();
        let path = dir.path().join("a.png");
        let img = levels_image(13, 7);
        img.save_png(&path).expect("save");
        let back = RgbaImage::load_png(&path).expect("load");
        assert_eq!(back, img);
    }

    #[test]
    fn png_save_clamps_and_rounds() {
        let dir = tmp();
        let path = dir.path().join("c.png");
        let img =
            RgbaImage::from_pixels(2, 1, vec![[-0.5, 1.5, 0.5, f32::NAN], [0.1, 0.2, 0.999, 1.0]]).expect("pixels");
        img.save_png(&path).expect("save");
        let back = RgbaImage::load_png(&path).expect("load");
        assert_eq!(back.pixel(0, 0), [0.0, 1.0, 128.0 / 255.0, 0.0]);
        assert_eq!(back.pixel(1, 0), [26.0 / 255.0, 51.0 / 255.0, 1.0, 1.0]);
    }

    #[test]
    fn load_png_handles_16_bit_grey_and_rgb() {
        let dir = tmp();
        let grey = dir.path().join("g16.png");
        let buf = ::image::ImageBuffer::<::image::Luma<u16>, Vec<u16>>::from_raw(2, 1, vec![0, 65535]).expect("buf");
        buf.save(&grey).expect("save");
        let img = RgbaImage::load_png(&grey).expect("load");
        assert_eq!(img.pixels(), &[[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 1.0, 1.0]]);

        let rgb = dir.path().join("rgb8.png");
        let buf = ::image::RgbImage::from_raw(1, 1, vec![255, 0, 51]).expect("buf");
        buf.save(&rgb).expect("save");
        let img = RgbaImage::load_png(&rgb).expect("load");
        assert_eq!(img.pixels(), &[[1.0, 0.0, 0.2, 1.0]]);
    }

    #[test]
    fn load_errors_name_the_file_and_do_not_panic() {
        let dir = tmp();
        let missing = dir.path().join("missing.png");
        let err = RgbaImage::load_png(&missing).expect_err("missing file");
        assert!(matches!(err, ImageError::Io { .. }));
        assert!(err.to_string().contains("missing.png"), "{err}");

        let garbage = dir.path().join("garbage.png");
        std::fs::write(&garbage, b"\x89PNG\r\n\x1a\nthis is not a png").expect("write");
        let err = RgbaImage::load_png(&garbage).expect_err("garbage");
        assert!(err.to_string().contains("garbage.png"), "{err}");

        // A valid PNG cut short.
        let img = levels_image(16, 16);
        let full = dir.path().join("full.png");
        img.save_png(&full).expect("save");
        let bytes = std::fs::read(&full).expect("read");
        let cut = dir.path().join("cut.png");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write");
        assert!(RgbaImage::load_png(&cut).is_err());
    }

    #[test]
    fn from_pixels_checks_length() {
        assert!(RgbaImage::from_pixels(2, 2, vec![[0.0; 4]; 3]).is_err());
        assert!(RgbaImage::from_pixels(2, 2, vec![[0.0; 4]; 4]).is_ok());
        assert!(FloatImage::from_data(2, 2, 3, vec![0.0; 11]).is_err());
        assert!(FloatImage::from_data(2, 2, 0, vec![]).is_err());
    }

    #[test]
    fn downscale_averages_premultiplied_colour() {
        // 5x3 image, factor 2: output 2x1, the last column and row are ignored.
        let mut img = RgbaImage::new(5, 3);
        // Block (0,0): one opaque red pixel, one half-transparent blue, two transparent.
        img.set_pixel(0, 0, [1.0, 0.0, 0.0, 1.0]);
        img.set_pixel(1, 0, [0.0, 0.0, 1.0, 0.5]);
        img.set_pixel(0, 1, [0.0, 1.0, 0.0, 0.0]); // colour of a transparent pixel must not count
        // Block (1,0): uniform opaque grey.
        for (x, y) in [(2, 0), (3, 0), (2, 1), (3, 1)] {
            img.set_pixel(x, y, [0.25, 0.5, 0.75, 1.0]);
        }
        // Ignored remainder.
        img.set_pixel(4, 0, [1.0; 4]);
        img.set_pixel(0, 2, [1.0; 4]);
        let small = img.downscale(2).expect("downscale");
        assert_eq!((small.width(), small.height()), (2, 1));
        let [r, g, b, a] = small.pixel(0, 0);
        assert!((a - 1.5 / 4.0).abs() < 1e-6);
        assert!((r - 1.0 / 1.5).abs() < 1e-6);
        assert!(g.abs() < 1e-6);
        assert!((b - 0.5 / 1.5).abs() < 1e-6);
        assert_eq!(small.pixel(1, 0), [0.25, 0.5, 0.75, 1.0]);
    }

    #[test]
    fn downscale_commutes_with_compositing() {
        let img = levels_image(12, 8);
        let bg = [1.0, 1.0, 1.0];
        let a = img.downscale(4).expect("downscale").composite_over(bg);
        let b = img.composite_over(bg).downscale(4).expect("downscale");
        for (p, q) in a.pixels().iter().zip(b.pixels()) {
            for c in 0..4 {
                assert!((p[c] - q[c]).abs() < 1e-5, "{p:?} vs {q:?}");
            }
        }
    }

    #[test]
    fn downscale_rejects_zero_and_too_large_factors() {
        let img = RgbaImage::new(4, 3);
        assert!(img.downscale(0).is_err());
        assert!(img.downscale(4).is_err());
        assert_eq!(img.downscale(3).expect("ok").width(), 1);
        assert_eq!(img.downscale(1).expect("ok"), img);
    }

    #[test]
    fn composite_over_white() {
        let img = RgbaImage::from_pixels(1, 1, vec![[0.2, 0.4, 0.6, 0.5]]).expect("pixels");
        let c = img.composite_over([1.0, 1.0, 1.0]).pixel(0, 0);
        let expected = [0.6, 0.7, 0.8, 1.0];
        for i in 0..4 {
            assert!((c[i] - expected[i]).abs() < 1e-6);
        }
    }

    #[test]
    fn srgb_functions_invert_each_other() {
        for i in 0..=1000 {
            let v = i as f32 / 1000.0;
            assert!((srgb_to_linear(linear_to_srgb(v)) - v).abs() < 1e-6, "{v}");
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-6, "{v}");
        }
        // Known points of the curve.
        assert_eq!(linear_to_srgb(0.0), 0.0);
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-6);
        assert!((linear_to_srgb(0.18) - 0.461_356).abs() < 1e-5);
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
        // The two pieces meet.
        assert!((linear_to_srgb(0.003_130_8) - 0.040_45).abs() < 1e-5);
    }

    #[test]
    fn exr_round_trip() {
        let dir = tmp();
        let path = dir.path().join("n.exr");
        let data: Vec<f32> = (0..5 * 4 * 3).map(|i| i as f32 * 0.37 - 3.0).collect();
        let img = FloatImage::from_data(5, 4, 3, data).expect("data");
        img.save_exr(&path).expect("save");
        assert_eq!(FloatImage::load_exr(&path).expect("load"), img);

        let depth = FloatImage::from_data(3, 2, 1, vec![0.0, 1.5, 2.25, 1e6, 0.125, 7.0]).expect("data");
        let path = dir.path().join("d.exr");
        depth.save_exr(&path).expect("save");
        let back = FloatImage::load_exr(&path).expect("load");
        assert_eq!(back.channels(), 3);
        assert_eq!(back.channel(0).expect("channel"), depth);

        let rgba = FloatImage::from_data(1, 1, 4, vec![0.5, -1.0, 2.0, 0.25]).expect("data");
        let path = dir.path().join("rgba.exr");
        rgba.save_exr(&path).expect("save");
        assert_eq!(FloatImage::load_exr(&path).expect("load"), rgba);
    }

    #[test]
    fn normalised_png_maps_range_to_16_bit() {
        let dir = tmp();
        let path = dir.path().join("depth.png");
        let depth = FloatImage::from_data(4, 1, 1, vec![1.0, 2.0, 3.0, -5.0]).expect("data");
        depth.save_png_normalised(&path, 1.0, 3.0).expect("save");
        let raw = ::image::open(&path).expect("open").into_luma16();
        assert_eq!(raw.into_raw(), vec![0, 32768, 65535, 0]);
        assert!(depth.save_png_normalised(&path, 3.0, 3.0).is_err());
        let rgb = FloatImage::new(1, 1, 3).expect("new");
        assert!(rgb.save_png_normalised(&path, 0.0, 1.0).is_err());
    }

    #[test]
    fn depth_downscale_ignores_misses() {
        let depth = FloatImage::from_data(2, 2, 1, vec![0.0, 2.0, 4.0, 0.0]).expect("data");
        assert_eq!(depth.downscale_ignoring_zeros(2).expect("ds").data(), &[3.0]);
        assert_eq!(depth.downscale(2).expect("ds").data(), &[1.5]);
    }
}
