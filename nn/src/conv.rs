//! Image layers for convolutional networks (the stereo global-illumination U-Net): a square
//! `k x k` convolution (k = 1 or 3, zero padding, stride 1) with an optional ReLU fused in,
//! 2x2 average pooling, nearest-neighbour 2x upsampling and channel concatenation, each with
//! its backward pass.
//!
//! Images are channels-last (`[(y * width + x) * channels + c]`) so that a pixel's channels
//! are contiguous; weights are stored `[((ky * k + kx) * inputs + i) * outputs + o]`, so the
//! inner loop of the forward pass and of the weight gradient is a contiguous `y[o] += x * w[o]`
//! over the output channels that the compiler vectorises (the same choice as [`crate::Mlp`]).
//! Rows run in parallel on the rayon pool; the weight gradient is accumulated per row chunk
//! and reduced, so the result does not depend on the thread count beyond float summation order.
//!
//! The forward pass, which serving runs (the environment's U-Net on the workers), is
//! register-blocked: a tile of [`TILE_PIXELS`] neighbouring output pixels times
//! [`BLOCK_VECTORS`] vectors of output channels stays in registers over every tap and input
//! channel (8 accumulators, each input value broadcast once per tile and block, each weight
//! vector loaded once per tile), compiled for AVX2 + FMA at run time through `pulp` and for one
//! lane with [`SimdMode::Off`]. The plain loop that loads and stores the output per input value
//! (about 4 multiply-adds per cycle on AVX2 hardware, a quarter of its peak) remains for layers
//! whose output channels are not a multiple of the block (the 1x1 heads) and as the reference
//! the tests compare with.
//!
//! A pass may compute only some output pixels ([`PixelMask`], [`conv_forward_masked`]): each
//! computed pixel gets exactly the value the whole pass gives it (same taps, same summation
//! order, whichever tile it falls in), so a network can skip what nobody will look at.

use rayon::prelude::*;

use crate::simd::{Simd, SimdMode, WithSimd};
use crate::{InitRng, NnError, check_len};

/// Shape of one convolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvShape {
    pub inputs: usize,
    pub outputs: usize,
    /// Kernel side: 1 or 3.
    pub kernel: usize,
    /// ReLU after the convolution.
    pub relu: bool,
}

impl ConvShape {
    pub fn validate(&self) -> Result<(), NnError> {
        if self.inputs == 0 || self.outputs == 0 || !(self.kernel == 1 || self.kernel == 3) {
            return Err(NnError::Config(format!(
                "convolution {} -> {} channels, kernel {} (channels > 0, kernel 1 or 3)",
                self.inputs, self.outputs, self.kernel
            )));
        }
        Ok(())
    }

    pub fn weight_count(&self) -> usize {
        self.kernel * self.kernel * self.inputs * self.outputs
    }

    /// Weights and biases.
    pub fn param_count(&self) -> usize {
        self.weight_count() + self.outputs
    }

    /// Multiply-adds per output pixel.
    pub fn macs_per_pixel(&self) -> usize {
        self.weight_count()
    }

    /// He-uniform weights (ReLU networks), zero biases, appended to `params`.
    pub(crate) fn init(&self, rng: &mut InitRng, params: &mut Vec<f32>) {
        let fan_in = (self.kernel * self.kernel * self.inputs) as f32;
        let bound = (6.0 / fan_in).sqrt();
        params.extend((0..self.weight_count()).map(|_| rng.uniform(bound)));
        params.extend(std::iter::repeat_n(0.0, self.outputs));
    }
}

/// Rows per parallel task (enough work per task for small images).
const ROWS_PER_TASK: usize = 4;

/// The pixels of a `width x height` image that a pass computes (row-major flags).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PixelMask {
    width: usize,
    height: usize,
    selected: Vec<bool>,
}

impl PixelMask {
    /// No pixel selected.
    pub fn none(width: usize, height: usize) -> PixelMask {
        PixelMask { width, height, selected: vec![false; width * height] }
    }

    /// Every pixel selected.
    pub fn all(width: usize, height: usize) -> PixelMask {
        PixelMask { width, height, selected: vec![true; width * height] }
    }

    /// A mask from row-major flags.
    pub fn from_flags(width: usize, height: usize, selected: Vec<bool>) -> Result<PixelMask, NnError> {
        check_len("pixel mask", width * height, selected.len())?;
        Ok(PixelMask { width, height, selected })
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Whether pixel `(x, y)` is selected.
    pub fn get(&self, x: usize, y: usize) -> bool {
        self.selected[y * self.width + x]
    }

    pub fn select(&mut self, x: usize, y: usize) {
        self.selected[y * self.width + x] = true;
    }

    /// Selected pixels.
    pub fn count(&self) -> usize {
        self.selected.iter().filter(|&&s| s).count()
    }

    /// Adds `other`'s pixels (same size).
    pub fn union_with(&mut self, other: &PixelMask) {
        debug_assert_eq!((self.width, self.height), (other.width, other.height));
        self.selected.iter_mut().zip(&other.selected).for_each(|(a, &b)| *a |= b);
    }

    /// Every pixel within `radius` of a selected one (a square neighbourhood): what a
    /// `(2 radius + 1)`-wide convolution reads to compute the selected pixels.
    pub fn dilated(&self, radius: usize) -> PixelMask {
        if radius == 0 {
            return self.clone();
        }
        let (w, h) = (self.width, self.height);
        let or_into = |to: &mut [bool], from: &[bool]| to.iter_mut().zip(from).for_each(|(a, &b)| *a |= b);
        // Separable: along the rows (each shift one slice-wide OR), then along the columns.
        let mut rows = self.selected.clone();
        for (row, source) in rows.chunks_exact_mut(w).zip(self.selected.chunks_exact(w)) {
            for shift in 1..=radius.min(w.saturating_sub(1)) {
                or_into(&mut row[shift..], &source[..w - shift]);
                or_into(&mut row[..w - shift], &source[shift..]);
            }
        }
        let mut out = rows.clone();
        for shift in 1..=radius.min(h.saturating_sub(1)) {
            or_into(&mut out[shift * w..], &rows[..(h - shift) * w]);
            or_into(&mut out[..(h - shift) * w], &rows[shift * w..]);
        }
        PixelMask { width: w, height: h, selected: out }
    }

    /// The half-size mask whose pixel is selected where any of its 2x2 block is: what a 2x
    /// nearest upsampling reads to give this mask's pixels. Sides must be even.
    pub fn coarsened(&self) -> PixelMask {
        let (w2, h2) = (self.width / 2, self.height / 2);
        let mut out = PixelMask::none(w2, h2);
        for y in 0..2 * h2 {
            for x in 0..2 * w2 {
                if self.get(x, y) {
                    out.selected[(y / 2) * w2 + x / 2] = true;
                }
            }
        }
        out
    }

    /// The double-size mask selecting each selected pixel's 2x2 block: what a 2x2 pooling
    /// reads to give this mask's pixels.
    pub fn refined(&self) -> PixelMask {
        let (w, h) = (2 * self.width, 2 * self.height);
        let mut out = PixelMask::none(w, h);
        for y in 0..h {
            for x in 0..w {
                out.selected[y * w + x] = self.get(x / 2, y / 2);
            }
        }
        out
    }

    /// Runs `[start, end)` of selected pixels in row `y`, left to right.
    pub fn spans(&self, y: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        let row = &self.selected[y * self.width..(y + 1) * self.width];
        let mut x = 0;
        std::iter::from_fn(move || {
            while x < row.len() && !row[x] {
                x += 1;
            }
            if x == row.len() {
                return None;
            }
            let start = x;
            while x < row.len() && row[x] {
                x += 1;
            }
            Some((start, x))
        })
    }
}

/// Output pixels of one register tile of the vector forward pass.
pub const TILE_PIXELS: usize = 4;
/// Vectors of output channels per register block of the vector forward pass (16 channels with
/// AVX2; 2 with the scalar instantiation). Layers whose output channels are not a multiple of
/// it take the plain loop.
pub const BLOCK_VECTORS: usize = 2;

/// `output = act(conv(input))` for an image of `width x height`. `params` holds the weights
/// then the biases ([`ConvShape::param_count`]). `simd` chooses the instruction set of the
/// register-blocked loop (results agree to float rounding: the summation order is the same,
/// the vector path fuses its multiply-adds).
pub fn conv_forward(
    simd: SimdMode,
    shape: &ConvShape,
    params: &[f32],
    width: usize,
    height: usize,
    input: &[f32],
    output: &mut [f32],
) -> Result<(), NnError> {
    conv_forward_in(simd, shape, params, width, height, input, output, None)
}

/// [`conv_forward`] for the output pixels `mask` selects only (a mask of the image's size);
/// the other output pixels keep what they held. Each computed pixel equals the whole pass's.
#[allow(clippy::too_many_arguments)]
pub fn conv_forward_masked(
    simd: SimdMode,
    shape: &ConvShape,
    params: &[f32],
    width: usize,
    height: usize,
    input: &[f32],
    output: &mut [f32],
    mask: &PixelMask,
) -> Result<(), NnError> {
    if (mask.width, mask.height) != (width, height) {
        return Err(NnError::Config(format!("a {}x{} mask for a {width}x{height} image", mask.width, mask.height)));
    }
    conv_forward_in(simd, shape, params, width, height, input, output, Some(mask))
}

/// Both forward passes, after checking the shape and the buffers.
#[allow(clippy::too_many_arguments)]
fn conv_forward_in(
    simd: SimdMode,
    shape: &ConvShape,
    params: &[f32],
    width: usize,
    height: usize,
    input: &[f32],
    output: &mut [f32],
    mask: Option<&PixelMask>,
) -> Result<(), NnError> {
    shape.validate()?;
    check_len("convolution parameters", shape.param_count(), params.len())?;
    check_len("convolution input", width * height * shape.inputs, input.len())?;
    check_len("convolution output", width * height * shape.outputs, output.len())?;
    let (weights, bias) = params.split_at(shape.weight_count());
    let image = Image { inputs: shape.inputs, outputs: shape.outputs, kernel: shape.kernel, width, height };
    output.par_chunks_mut(width * shape.outputs * ROWS_PER_TASK).enumerate().for_each(|(task, rows)| {
        let op =
            ForwardRows { image, weights, bias, input, first_row: task * ROWS_PER_TASK, rows, relu: shape.relu, mask };
        simd.arch().dispatch(op);
    });
    Ok(())
}

/// Sizes of one convolution over one image (a dense layer over `n` rows is a 1x1 convolution
/// over an image of `n x 1`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Image {
    pub inputs: usize,
    pub outputs: usize,
    pub kernel: usize,
    pub width: usize,
    pub height: usize,
}

impl Image {
    /// A dense layer of `inputs -> outputs` over `rows` rows.
    pub fn dense(inputs: usize, outputs: usize, rows: usize) -> Image {
        Image { inputs, outputs, kernel: 1, width: rows, height: 1 }
    }

    /// Whether the register-blocked loops take layers of these output channels with `S`.
    #[inline(always)]
    pub fn tiles_outputs<S: Simd>(&self) -> bool {
        self.outputs.is_multiple_of(BLOCK_VECTORS * S::F32_LANES)
    }
}

/// The output rows `first_row..` of a convolution, for [`pulp::Arch::dispatch`].
struct ForwardRows<'a> {
    image: Image,
    weights: &'a [f32],
    bias: &'a [f32],
    input: &'a [f32],
    first_row: usize,
    rows: &'a mut [f32],
    relu: bool,
    /// Output pixels to compute (all when `None`).
    mask: Option<&'a PixelMask>,
}

impl WithSimd for ForwardRows<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        forward_rows_in(
            simd,
            self.image,
            self.weights,
            self.bias,
            self.input,
            self.first_row,
            self.rows,
            self.relu,
            self.mask,
        )
    }
}

/// Output rows `first_row..` of a convolution (`rows` holds whole rows): the register-blocked
/// loop where the output channels fill whole blocks, else the plain one. Callable from within
/// another kernel's dispatch (the MLP's layers).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn forward_rows<S: Simd>(
    simd: S,
    g: Image,
    weights: &[f32],
    bias: &[f32],
    input: &[f32],
    first_row: usize,
    rows: &mut [f32],
    relu: bool,
) {
    forward_rows_in(simd, g, weights, bias, input, first_row, rows, relu, None)
}

/// [`forward_rows`] for the output pixels `mask` selects (all when `None`).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn forward_rows_in<S: Simd>(
    simd: S,
    g: Image,
    weights: &[f32],
    bias: &[f32],
    input: &[f32],
    first_row: usize,
    rows: &mut [f32],
    relu: bool,
    mask: Option<&PixelMask>,
) {
    if !g.tiles_outputs::<S>() {
        return forward_rows_plain(g, weights, bias, input, first_row, rows, relu, mask);
    }
    // Whole vectors: the weights' rows, the biases and the output rows are multiples of
    // the output channels, hence of the lanes.
    let weights = S::as_simd_f32s(weights).0;
    let bias = S::as_simd_f32s(bias).0;
    let pad = g.kernel / 2;
    for (r, row) in rows.chunks_mut(g.width * g.outputs).enumerate() {
        let row = S::as_mut_simd_f32s(row).0;
        let y = first_row + r;
        let spans: &mut dyn Iterator<Item = (usize, usize)> = match mask {
            None => &mut std::iter::once((0, g.width)),
            Some(mask) => &mut mask.spans(y),
        };
        for (start, end) in spans {
            // Pixels whose taps all fall inside the image take whole tiles; the borders and
            // what is left of the span one pixel at a time, with bounds checks. (Direct
            // calls, not closures: a closure may be compiled apart, without the dispatch's
            // AVX2.) A pixel's sum runs in the same order in either.
            let mut x = start;
            while x < end && x < pad {
                forward_tile::<S, 1, true>(simd, g, weights, bias, input, y, x, relu, row);
                x += 1;
            }
            while x + TILE_PIXELS <= end && x + TILE_PIXELS + pad <= g.width {
                forward_tile::<S, TILE_PIXELS, false>(simd, g, weights, bias, input, y, x, relu, row);
                x += TILE_PIXELS;
            }
            while x < end {
                forward_tile::<S, 1, true>(simd, g, weights, bias, input, y, x, relu, row);
                x += 1;
            }
        }
    }
}

/// `dx = dy W^T` for a dense layer of `inputs -> outputs` over the rows of `dy` (`W`
/// input-major, as [`crate::Mlp`] stores it): the forward tiles on the transposed weights.
/// Returns `false`, leaving `dx` as it was, when the inputs do not fill whole register blocks
/// (the caller then takes its plain loop).
#[inline(always)]
pub(crate) fn dense_input_gradient<S: Simd>(
    simd: S,
    inputs: usize,
    outputs: usize,
    weights: &[f32],
    dy: &[f32],
    dx: &mut [f32],
) -> bool {
    let back = Image::dense(outputs, inputs, dy.len() / outputs);
    if !back.tiles_outputs::<S>() {
        return false;
    }
    let mut transposed = vec![0.0f32; weights.len()];
    for (k, row) in weights.chunks_exact(outputs).enumerate() {
        for (o, &v) in row.iter().enumerate() {
            transposed[o * inputs + k] = v;
        }
    }
    let zero_bias = vec![0.0f32; inputs];
    forward_rows(simd, back, &transposed, &zero_bias, dy, 0, dx, false);
    true
}

/// Output pixels `x0..x0 + P` of row `y`, every block of output channels: the accumulators
/// stay in registers over all taps and input channels. With `CHECKED` (only for `P = 1`)
/// taps outside the image are skipped (zero padding); without, the caller guarantees that
/// every tap of the tile is inside the row.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn forward_tile<S: Simd, const P: usize, const CHECKED: bool>(
    simd: S,
    g: Image,
    weights: &[S::f32s],
    bias: &[S::f32s],
    input: &[f32],
    y: usize,
    x0: usize,
    relu: bool,
    row: &mut [S::f32s],
) {
    let vectors = g.outputs / S::F32_LANES;
    let (ci, k, pad) = (g.inputs, g.kernel, g.kernel / 2);
    let zero = simd.splat_f32s(0.0);
    for block in (0..vectors).step_by(BLOCK_VECTORS) {
        let mut acc = [[zero; BLOCK_VECTORS]; P];
        for pixel in acc.iter_mut() {
            pixel.copy_from_slice(&bias[block..block + BLOCK_VECTORS]);
        }
        for ky in 0..k {
            // Rows above the image wrap to huge values and are skipped with those below.
            let sy = (y + ky).wrapping_sub(pad);
            if sy >= g.height {
                continue;
            }
            for kx in 0..k {
                let sx = (x0 + kx).wrapping_sub(pad);
                if CHECKED && sx >= g.width {
                    continue;
                }
                // The tile's P pixels are neighbours: their inputs are one contiguous run.
                let start = (sy * g.width + sx) * ci;
                let source = &input[start..start + P * ci];
                let taps = &weights[(ky * k + kx) * ci * vectors..][..ci * vectors];
                for (i, w) in taps.chunks_exact(vectors).enumerate() {
                    let w = &w[block..block + BLOCK_VECTORS];
                    for (p, pixel) in acc.iter_mut().enumerate() {
                        let v = simd.splat_f32s(source[p * ci + i]);
                        for (a, &w) in pixel.iter_mut().zip(w) {
                            *a = simd.mul_add_e_f32s(v, w, *a);
                        }
                    }
                }
            }
        }
        for (p, pixel) in acc.iter().enumerate() {
            let out = &mut row[(x0 + p) * vectors + block..][..BLOCK_VECTORS];
            for (o, &a) in out.iter_mut().zip(pixel) {
                *o = if relu { simd.max_f32s(a, zero) } else { a };
            }
        }
    }
}

/// The plain forward of output rows `first_row..`: per output pixel, the output channels are
/// loaded and stored once per input value (zero inputs skipped). For layers the tiles do not
/// fit, and the reference of the tests. Only the pixels `mask` selects, where given.
#[allow(clippy::too_many_arguments)]
fn forward_rows_plain(
    g: Image,
    weights: &[f32],
    bias: &[f32],
    input: &[f32],
    first_row: usize,
    rows: &mut [f32],
    relu: bool,
    mask: Option<&PixelMask>,
) {
    let (ci, co, k) = (g.inputs, g.outputs, g.kernel);
    let pad = (k / 2) as isize;
    for (r, row) in rows.chunks_mut(g.width * co).enumerate() {
        let y = (first_row + r) as isize;
        for (x, out) in row.chunks_exact_mut(co).enumerate() {
            if mask.is_some_and(|m| !m.get(x, y as usize)) {
                continue;
            }
            out.copy_from_slice(bias);
            for ky in 0..k {
                let sy = y + ky as isize - pad;
                if sy < 0 || sy >= g.height as isize {
                    continue;
                }
                for kx in 0..k {
                    let sx = x as isize + kx as isize - pad;
                    if sx < 0 || sx >= g.width as isize {
                        continue;
                    }
                    let src = &input[(sy as usize * g.width + sx as usize) * ci..][..ci];
                    let w = &weights[(ky * k + kx) * ci * co..][..ci * co];
                    for (&v, wrow) in src.iter().zip(w.chunks_exact(co)) {
                        if v != 0.0 {
                            out.iter_mut().zip(wrow).for_each(|(o, &w)| *o += v * w);
                        }
                    }
                }
            }
            if relu {
                out.iter_mut().for_each(|o| *o = o.max(0.0));
            }
        }
    }
}

/// Backward pass of [`conv_forward`]. `output` is the forward's output (for the ReLU's
/// derivative); `d_output` its gradient, overwritten with the gradient before the ReLU.
/// Adds the parameter gradient into `d_params`; writes the input gradient into `d_input`
/// when given (the first layer of a network needs none).
///
/// The input gradient is itself a convolution, of the output gradient with the taps mirrored
/// and inputs and outputs swapped, so it runs [`conv_forward`]'s register-blocked loop; the
/// weight gradient keeps [`TILE_INPUTS`] input channels times [`BLOCK_VECTORS`] vectors of
/// output channels in registers along each row of pixels. `simd` chooses the instruction set
/// of both, as for the forward pass.
#[allow(clippy::too_many_arguments)]
pub fn conv_backward(
    simd: SimdMode,
    shape: &ConvShape,
    params: &[f32],
    width: usize,
    height: usize,
    input: &[f32],
    output: &[f32],
    d_output: &mut [f32],
    d_params: &mut [f32],
    d_input: Option<&mut [f32]>,
) -> Result<(), NnError> {
    shape.validate()?;
    let pixels = width * height;
    check_len("convolution parameters", shape.param_count(), params.len())?;
    check_len("convolution parameter gradient", shape.param_count(), d_params.len())?;
    check_len("convolution input", pixels * shape.inputs, input.len())?;
    check_len("convolution output", pixels * shape.outputs, output.len())?;
    check_len("convolution output gradient", pixels * shape.outputs, d_output.len())?;
    let (ci, co, k) = (shape.inputs, shape.outputs, shape.kernel);
    if shape.relu {
        d_output.par_iter_mut().zip(output.par_iter()).for_each(|(d, &o)| {
            if o <= 0.0 {
                *d = 0.0;
            }
        });
    }
    let d_output: &[f32] = d_output;
    let weights = &params[..shape.weight_count()];
    let image = Image { inputs: ci, outputs: co, kernel: k, width, height };

    // Parameter gradient: per task of rows, then summed.
    let partial = d_output
        .par_chunks(width * co * ROWS_PER_TASK)
        .enumerate()
        .fold(
            || vec![0.0f32; shape.param_count()],
            |mut acc, (task, rows)| {
                let (d_weights, d_bias) = acc.split_at_mut(shape.weight_count());
                let first_row = task * ROWS_PER_TASK;
                simd.arch().dispatch(WeightGradientRows { image, input, first_row, rows, d_weights, d_bias });
                acc
            },
        )
        .reduce(
            || vec![0.0f32; shape.param_count()],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                a
            },
        );
    d_params.iter_mut().zip(&partial).for_each(|(d, p)| *d += p);

    // Input gradient: d_in[y, x, i] = sum over taps and outputs of d_out[y', x', o] * w, the
    // forward convolution of d_out with w'[ky, kx, o, i] = w[k-1-ky, k-1-kx, i, o] (the same
    // zero padding: the mirrored tap of an output outside the image reads outside it too).
    if let Some(d_input) = d_input {
        check_len("convolution input gradient", pixels * ci, d_input.len())?;
        let mut mirrored = vec![0.0f32; weights.len()];
        for tap in 0..k * k {
            let source = &weights[(k * k - 1 - tap) * ci * co..][..ci * co];
            let target = &mut mirrored[tap * co * ci..][..co * ci];
            for i in 0..ci {
                for o in 0..co {
                    target[o * ci + i] = source[i * co + o];
                }
            }
        }
        let zero_bias = vec![0.0f32; ci];
        let back = Image { inputs: co, outputs: ci, kernel: k, width, height };
        d_input.par_chunks_mut(width * ci * ROWS_PER_TASK).enumerate().for_each(|(task, rows)| {
            let op = ForwardRows {
                image: back,
                weights: &mirrored,
                bias: &zero_bias,
                input: d_output,
                first_row: task * ROWS_PER_TASK,
                rows,
                relu: false,
                mask: None,
            };
            simd.arch().dispatch(op);
        });
    }
    Ok(())
}

/// Input channels per register tile of the weight gradient.
pub const TILE_INPUTS: usize = 4;

/// The weight and bias gradient of output rows `first_row..` (`rows` of the output gradient),
/// added into `d_weights` and `d_bias`, for [`pulp::Arch::dispatch`].
struct WeightGradientRows<'a> {
    image: Image,
    input: &'a [f32],
    first_row: usize,
    rows: &'a [f32],
    d_weights: &'a mut [f32],
    d_bias: &'a mut [f32],
}

impl WithSimd for WeightGradientRows<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        weight_gradient_rows(simd, self.image, self.input, self.first_row, self.rows, self.d_weights, self.d_bias)
    }
}

/// Adds the weight and bias gradient of output rows `first_row..` (`rows` of the output
/// gradient, whole rows) into `d_weights` and `d_bias`: the register-blocked loop where the
/// output channels fill whole blocks, else the plain one. Callable from within another
/// kernel's dispatch (the MLP's layers).
#[inline(always)]
pub(crate) fn weight_gradient_rows<S: Simd>(
    simd: S,
    g: Image,
    input: &[f32],
    first_row: usize,
    rows: &[f32],
    d_weights: &mut [f32],
    d_bias: &mut [f32],
) {
    if !g.tiles_outputs::<S>() {
        return weight_gradient_rows_plain(g, input, first_row, rows, d_weights, d_bias);
    }
    let (ci, co, k, pad) = (g.inputs, g.outputs, g.kernel, g.kernel / 2);
    let vectors = co / S::F32_LANES;
    let d_weights = S::as_mut_simd_f32s(d_weights).0;
    for (r, row) in rows.chunks(g.width * co).enumerate() {
        for d in row.chunks_exact(co) {
            d_bias.iter_mut().zip(d).for_each(|(b, &v)| *b += v);
        }
        let row = S::as_simd_f32s(row).0;
        let y = first_row + r;
        for ky in 0..k {
            let sy = (y + ky).wrapping_sub(pad);
            if sy >= g.height {
                continue;
            }
            for kx in 0..k {
                // Output pixels x whose tap (ky, kx) reads inside the row: sx = x + kx - pad.
                let x_start = pad.saturating_sub(kx);
                let x_end = (g.width + pad).saturating_sub(kx).min(g.width);
                if x_start >= x_end {
                    continue;
                }
                let taps = &mut d_weights[(ky * k + kx) * ci * vectors..][..ci * vectors];
                let source_row = &input[(sy * g.width) * ci..][..g.width * ci];
                let sx_start = x_start + kx - pad;
                let mut i = 0;
                while i + TILE_INPUTS <= ci {
                    weight_gradient_tile::<S, TILE_INPUTS>(
                        simd, ci, vectors, source_row, sx_start, row, x_start, x_end, i, taps,
                    );
                    i += TILE_INPUTS;
                }
                while i < ci {
                    weight_gradient_tile::<S, 1>(simd, ci, vectors, source_row, sx_start, row, x_start, x_end, i, taps);
                    i += 1;
                }
            }
        }
    }
}

/// `d_w[tap, i0 + ii, o] += sum over x of in[sy, x + kx - pad, i0 + ii] * d_out[y, x, o]` for
/// `I` input channels and every block of output channels, the sums in registers.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn weight_gradient_tile<S: Simd, const I: usize>(
    simd: S,
    ci: usize,
    vectors: usize,
    source_row: &[f32],
    sx_start: usize,
    d_row: &[S::f32s],
    x_start: usize,
    x_end: usize,
    i0: usize,
    taps: &mut [S::f32s],
) {
    let zero = simd.splat_f32s(0.0);
    let n = x_end - x_start;
    let source = &source_row[sx_start * ci..][..n * ci];
    let d_row = &d_row[x_start * vectors..][..n * vectors];
    for block in (0..vectors).step_by(BLOCK_VECTORS) {
        let mut acc = [[zero; BLOCK_VECTORS]; I];
        for (src, d) in source.chunks_exact(ci).zip(d_row.chunks_exact(vectors)) {
            let d = &d[block..block + BLOCK_VECTORS];
            for (ii, a) in acc.iter_mut().enumerate() {
                let v = simd.splat_f32s(src[i0 + ii]);
                for (a, &d) in a.iter_mut().zip(d) {
                    *a = simd.mul_add_e_f32s(v, d, *a);
                }
            }
        }
        for (ii, a) in acc.iter().enumerate() {
            let out = &mut taps[(i0 + ii) * vectors + block..][..BLOCK_VECTORS];
            for (o, &a) in out.iter_mut().zip(a) {
                *o = simd.add_f32s(*o, a);
            }
        }
    }
}

/// The plain weight and bias gradient of output rows `first_row..`: per pixel with a non-zero
/// gradient, per tap and input channel, the output channels loaded and stored. For layers the
/// tiles do not fit, and the reference of the tests.
fn weight_gradient_rows_plain(
    g: Image,
    input: &[f32],
    first_row: usize,
    rows: &[f32],
    d_weights: &mut [f32],
    d_bias: &mut [f32],
) {
    let (ci, co, k) = (g.inputs, g.outputs, g.kernel);
    let pad = (k / 2) as isize;
    for (r, row) in rows.chunks(g.width * co).enumerate() {
        let y = (first_row + r) as isize;
        for (x, d) in row.chunks_exact(co).enumerate() {
            if d.iter().all(|&v| v == 0.0) {
                continue;
            }
            d_bias.iter_mut().zip(d).for_each(|(b, &v)| *b += v);
            for ky in 0..k {
                let sy = y + ky as isize - pad;
                if sy < 0 || sy >= g.height as isize {
                    continue;
                }
                for kx in 0..k {
                    let sx = x as isize + kx as isize - pad;
                    if sx < 0 || sx >= g.width as isize {
                        continue;
                    }
                    let src = &input[(sy as usize * g.width + sx as usize) * ci..][..ci];
                    let w = &mut d_weights[(ky * k + kx) * ci * co..][..ci * co];
                    for (&v, wrow) in src.iter().zip(w.chunks_exact_mut(co)) {
                        if v != 0.0 {
                            wrow.iter_mut().zip(d).for_each(|(w, &g)| *w += v * g);
                        }
                    }
                }
            }
        }
    }
}

/// 2x2 average pooling of a `width x height` image (both even) of `channels`.
pub fn pool_forward(width: usize, height: usize, channels: usize, input: &[f32], output: &mut [f32]) {
    let (w2, h2) = (width / 2, height / 2);
    debug_assert!(input.len() == width * height * channels && output.len() == w2 * h2 * channels);
    output.par_chunks_mut(w2 * channels).enumerate().for_each(|(y, row)| {
        for (x, out) in row.chunks_exact_mut(channels).enumerate() {
            let at = |dy: usize, dx: usize| &input[((2 * y + dy) * width + 2 * x + dx) * channels..][..channels];
            let (a, b, c, d) = (at(0, 0), at(0, 1), at(1, 0), at(1, 1));
            for i in 0..channels {
                out[i] = 0.25 * (a[i] + b[i] + c[i] + d[i]);
            }
        }
    });
}

/// Backward of [`pool_forward`]: each input pixel gets a quarter of its block's gradient.
pub fn pool_backward(width: usize, height: usize, channels: usize, d_output: &[f32], d_input: &mut [f32]) {
    let w2 = width / 2;
    debug_assert!(d_input.len() == width * height * channels);
    d_input.par_chunks_mut(width * channels).enumerate().for_each(|(y, row)| {
        for (x, din) in row.chunks_exact_mut(channels).enumerate() {
            let d = &d_output[((y / 2) * w2 + x / 2) * channels..][..channels];
            din.iter_mut().zip(d).for_each(|(a, &g)| *a = 0.25 * g);
        }
    });
}

/// Nearest-neighbour 2x upsampling of a `width x height` image to `2 width x 2 height`.
pub fn upsample_forward(width: usize, height: usize, channels: usize, input: &[f32], output: &mut [f32]) {
    debug_assert!(input.len() == width * height * channels && output.len() == 4 * width * height * channels);
    output.par_chunks_mut(2 * width * channels).enumerate().for_each(|(y, row)| {
        for (x, out) in row.chunks_exact_mut(channels).enumerate() {
            out.copy_from_slice(&input[((y / 2) * width + x / 2) * channels..][..channels]);
        }
    });
}

/// Backward of [`upsample_forward`]: each small pixel sums its 2x2 block's gradient.
pub fn upsample_backward(width: usize, height: usize, channels: usize, d_output: &[f32], d_input: &mut [f32]) {
    debug_assert!(d_input.len() == width * height * channels);
    d_input.par_chunks_mut(width * channels).enumerate().for_each(|(y, row)| {
        for (x, din) in row.chunks_exact_mut(channels).enumerate() {
            let at = |dy: usize, dx: usize| &d_output[((2 * y + dy) * 2 * width + 2 * x + dx) * channels..][..channels];
            let (a, b, c, d) = (at(0, 0), at(0, 1), at(1, 0), at(1, 1));
            for i in 0..channels {
                din[i] = a[i] + b[i] + c[i] + d[i];
            }
        }
    });
}

/// Per pixel, `a`'s `ca` channels then `b`'s `cb`.
pub fn concat(pixels: usize, a: &[f32], ca: usize, b: &[f32], cb: usize, out: &mut [f32]) {
    debug_assert!(a.len() == pixels * ca && b.len() == pixels * cb && out.len() == pixels * (ca + cb));
    out.par_chunks_mut(ca + cb).zip(a.par_chunks(ca)).zip(b.par_chunks(cb)).for_each(|((o, a), b)| {
        o[..ca].copy_from_slice(a);
        o[ca..].copy_from_slice(b);
    });
}

/// Backward of [`concat`]: splits the gradient.
pub fn split(pixels: usize, d: &[f32], ca: usize, cb: usize, da: &mut [f32], db: &mut [f32]) {
    debug_assert!(d.len() == pixels * (ca + cb));
    da.par_chunks_mut(ca).zip(db.par_chunks_mut(cb)).zip(d.par_chunks(ca + cb)).for_each(|((a, b), d)| {
        a.copy_from_slice(&d[..ca]);
        b.copy_from_slice(&d[ca..]);
    });
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = InitRng::new(seed);
        (0..n).map(|_| rng.uniform(1.0)).collect()
    }

    /// The plain loop over the whole image: the reference.
    fn plain(shape: &ConvShape, params: &[f32], w: usize, h: usize, input: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0; w * h * shape.outputs];
        let (weights, bias) = params.split_at(shape.weight_count());
        let image = Image { inputs: shape.inputs, outputs: shape.outputs, kernel: shape.kernel, width: w, height: h };
        forward_rows_plain(image, weights, bias, input, 0, &mut out, shape.relu, None);
        out
    }

    /// Largest difference to the reference relative to the magnitude of the terms summed.
    fn check_agreement(shape: &ConvShape, params: &[f32], w: usize, h: usize, input: &[f32]) {
        let want = plain(shape, params, w, h, input);
        let scale = 1.0
            + input.iter().fold(0f32, |m, v| m.max(v.abs()))
                * params.iter().fold(0f32, |m, v| m.max(v.abs()))
                * (shape.weight_count() / shape.outputs) as f32;
        for simd in [SimdMode::Auto, SimdMode::Off] {
            let mut got = vec![f32::NAN; want.len()];
            conv_forward(simd, shape, params, w, h, input, &mut got).expect("forward");
            for (i, (g, e)) in got.iter().zip(&want).enumerate() {
                assert!(g.is_finite(), "{simd} {shape:?} {w}x{h}: output {i} is {g}");
                assert!((g - e).abs() <= 1e-5 * scale, "{simd} {shape:?} {w}x{h}: output {i} {g} vs {e}");
            }
        }
    }

    #[test]
    fn the_register_blocked_loop_agrees_with_the_plain_one() {
        // Output channels that fill whole blocks (16, 32, 48 with AVX2) and that do not (3, 8,
        // 20: the plain loop with AVX2, tiles with the scalar twin's 2-channel blocks); images
        // narrower than a tile and with a ragged last tile.
        let mut seed = 0;
        for (inputs, outputs) in [(1, 16), (13, 16), (16, 32), (48, 16), (32, 48), (16, 3), (5, 8), (7, 20)] {
            for kernel in [1, 3] {
                for (w, h) in [(1, 1), (2, 3), (3, 1), (5, 4), (6, 2), (9, 3), (13, 5)] {
                    seed += 1;
                    let shape = ConvShape { inputs, outputs, kernel, relu: seed % 2 == 0 };
                    let params = random(shape.param_count(), seed);
                    let mut input = random(w * h * inputs, seed + 1000);
                    // ReLU outputs feed most layers: many exact zeros.
                    input.iter_mut().step_by(3).for_each(|v| *v = 0.0);
                    check_agreement(&shape, &params, w, h, &input);
                }
            }
        }
    }

    #[test]
    fn a_masked_pass_computes_exactly_the_selected_pixels() {
        // Masks that start and end spans at every offset against the tiles and the borders;
        // both loops (channels that fill blocks and that do not), both instruction sets.
        let mut seed = 500;
        for (inputs, outputs) in [(13, 16), (16, 32), (16, 3)] {
            for kernel in [1, 3] {
                for (w, h) in [(1, 1), (7, 3), (13, 5), (16, 4)] {
                    seed += 1;
                    let shape = ConvShape { inputs, outputs, kernel, relu: seed % 2 == 0 };
                    let params = random(shape.param_count(), seed);
                    let input = random(w * h * inputs, seed + 1000);
                    let mut rng = InitRng::new(seed + 2000);
                    let flags: Vec<bool> = (0..w * h).map(|_| rng.uniform(1.0) > 0.0).collect();
                    let mask = PixelMask::from_flags(w, h, flags).expect("mask");
                    for simd in [SimdMode::Auto, SimdMode::Off] {
                        let mut whole = vec![0.0; w * h * outputs];
                        conv_forward(simd, &shape, &params, w, h, &input, &mut whole).expect("forward");
                        let mut masked = vec![f32::NAN; w * h * outputs];
                        conv_forward_masked(simd, &shape, &params, w, h, &input, &mut masked, &mask).expect("masked");
                        for p in 0..w * h {
                            let (got, want) = (&masked[p * outputs..][..outputs], &whole[p * outputs..][..outputs]);
                            if mask.get(p % w, p / w) {
                                assert_eq!(got, want, "{simd} {shape:?} {w}x{h} pixel {p}");
                            } else {
                                assert!(got.iter().all(|v| v.is_nan()), "{simd} {shape:?} pixel {p} was written");
                            }
                        }
                    }
                }
            }
        }
        let shape = ConvShape { inputs: 1, outputs: 16, kernel: 3, relu: false };
        let params = random(shape.param_count(), 1);
        let mut out = vec![0.0; 16 * 4];
        let wrong = PixelMask::all(2, 3);
        assert!(conv_forward_masked(SimdMode::Auto, &shape, &params, 2, 2, &[0.0; 4], &mut out, &wrong).is_err());
    }

    #[test]
    fn masks_grow_shrink_and_split_into_spans() {
        let mut m = PixelMask::none(8, 6);
        m.select(0, 0);
        m.select(5, 3);
        assert_eq!(m.spans(3).collect::<Vec<_>>(), vec![(5, 6)]);
        let d = m.dilated(1);
        assert_eq!(d.count(), 4 + 9);
        assert_eq!(d.spans(3).collect::<Vec<_>>(), vec![(4, 7)]);
        assert_eq!(d.spans(0).collect::<Vec<_>>(), vec![(0, 2)]);
        assert_eq!(d.spans(5).count(), 0);
        let c = m.coarsened();
        assert_eq!((c.width(), c.height(), c.count()), (4, 3, 2));
        assert!(c.get(0, 0) && c.get(2, 1));
        let r = c.refined();
        assert_eq!((r.width(), r.height(), r.count()), (8, 6, 8));
        assert!(r.get(4, 2) && r.get(5, 3) && r.get(1, 1) && !r.get(2, 2));
        let mut u = PixelMask::none(8, 6);
        u.union_with(&r);
        assert_eq!(u, r);
        assert_eq!(PixelMask::all(3, 2).spans(1).collect::<Vec<_>>(), vec![(0, 3)]);
    }

    /// The backward pass, vector and scalar, against its definition: the weight gradient by
    /// the plain loop, the input gradient summed tap by tap.
    fn check_backward(shape: &ConvShape, params: &[f32], w: usize, h: usize, input: &[f32], seed: u64) {
        let (ci, co, k) = (shape.inputs, shape.outputs, shape.kernel);
        let pad = (k / 2) as isize;
        let output = plain(shape, params, w, h, input);
        let mut d_output = random(output.len(), seed);
        if shape.relu {
            d_output.iter_mut().zip(&output).for_each(|(d, &o)| *d = if o <= 0.0 { 0.0 } else { *d });
        }
        let image = Image { inputs: ci, outputs: co, kernel: k, width: w, height: h };
        let mut want_params = vec![0.0; shape.param_count()];
        let (dw, db) = want_params.split_at_mut(shape.weight_count());
        weight_gradient_rows_plain(image, input, 0, &d_output, dw, db);
        let mut want_input = vec![0.0f32; input.len()];
        for y in 0..h as isize {
            for x in 0..w as isize {
                for ky in 0..k as isize {
                    for kx in 0..k as isize {
                        let (sy, sx) = (y + ky - pad, x + kx - pad);
                        if sy < 0 || sx < 0 || sy >= h as isize || sx >= w as isize {
                            continue;
                        }
                        for i in 0..ci {
                            for o in 0..co {
                                want_input[(sy as usize * w + sx as usize) * ci + i] += d_output
                                    [(y as usize * w + x as usize) * co + o]
                                    * params[((ky as usize * k + kx as usize) * ci + i) * co + o];
                            }
                        }
                    }
                }
            }
        }
        let scale =
            1.0 + (w * h * k * k * ci.max(co)) as f32 * input.iter().chain(params).fold(0f32, |m, v| m.max(v.abs()));
        for simd in [SimdMode::Auto, SimdMode::Off] {
            // Start from a non-zero parameter gradient: the pass adds into it.
            let mut d_params = vec![0.5; shape.param_count()];
            let mut d_input = vec![f32::NAN; input.len()];
            let mut d_out = d_output.clone();
            conv_backward(simd, shape, params, w, h, input, &output, &mut d_out, &mut d_params, Some(&mut d_input))
                .expect("backward");
            for (i, (g, e)) in d_params.iter().zip(&want_params).enumerate() {
                assert!(
                    (g - 0.5 - e).abs() <= 1e-5 * scale,
                    "{simd} {shape:?} {w}x{h}: parameter {i} {g} vs {e} + 0.5"
                );
            }
            for (i, (g, e)) in d_input.iter().zip(&want_input).enumerate() {
                assert!((g - e).abs() <= 1e-5 * scale, "{simd} {shape:?} {w}x{h}: input {i} {g} vs {e}");
            }
        }
    }

    #[test]
    fn the_register_blocked_backward_agrees_with_its_definition() {
        let mut seed = 0;
        for (inputs, outputs) in [(1, 16), (13, 16), (16, 32), (48, 16), (6, 32), (16, 3), (5, 8)] {
            for kernel in [1, 3] {
                for (w, h) in [(1, 1), (2, 3), (5, 4), (9, 3)] {
                    seed += 1;
                    let shape = ConvShape { inputs, outputs, kernel, relu: seed % 2 == 0 };
                    let params = random(shape.param_count(), seed);
                    let mut input = random(w * h * inputs, seed + 1000);
                    input.iter_mut().step_by(3).for_each(|v| *v = 0.0);
                    check_backward(&shape, &params, w, h, &input, seed + 2000);
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn register_blocked_and_plain_agree_on_random_layers(
            inputs in 1usize..20,
            blocks in 1usize..4,
            kernel in prop::sample::select(vec![1usize, 3]),
            relu in any::<bool>(),
            w in 1usize..12,
            h in 1usize..6,
            magnitude in prop::sample::select(vec![1e-30f32, 1.0, 1e3, 1e15]),
            seed in any::<u64>(),
        ) {
            let shape = ConvShape { inputs, outputs: 16 * blocks, kernel, relu };
            let params = random(shape.param_count(), seed);
            let input: Vec<f32> = random(w * h * inputs, seed ^ 0x5eed).iter().map(|v| v * magnitude).collect();
            check_agreement(&shape, &params, w, h, &input);
        }
    }

    /// Loss = sum(output * probe); its gradient with respect to the output is `probe`.
    fn loss(shape: &ConvShape, params: &[f32], w: usize, h: usize, input: &[f32], probe: &[f32]) -> f64 {
        let mut out = vec![0.0; w * h * shape.outputs];
        conv_forward(SimdMode::Auto, shape, params, w, h, input, &mut out).expect("forward");
        out.iter().zip(probe).map(|(o, p)| f64::from(o * p)).sum()
    }

    #[test]
    fn gradients_match_finite_differences() {
        for (kernel, relu) in [(3, false), (3, true), (1, false)] {
            let shape = ConvShape { inputs: 3, outputs: 4, kernel, relu };
            let (w, h) = (5, 4);
            let mut params = Vec::new();
            shape.init(&mut InitRng::new(1), &mut params);
            params.iter_mut().skip(shape.weight_count()).for_each(|b| *b = 0.05);
            let input = random(w * h * 3, 2);
            let probe = random(w * h * 4, 3);
            let mut out = vec![0.0; w * h * 4];
            conv_forward(SimdMode::Auto, &shape, &params, w, h, &input, &mut out).expect("forward");
            let mut d_out = probe.clone();
            let mut d_params = vec![0.0; shape.param_count()];
            let mut d_input = vec![0.0; input.len()];
            conv_backward(
                SimdMode::Auto,
                &shape,
                &params,
                w,
                h,
                &input,
                &out,
                &mut d_out,
                &mut d_params,
                Some(&mut d_input),
            )
            .expect("backward");
            let eps = 1e-3;
            for i in (0..params.len()).step_by(5) {
                let (mut plus, mut minus) = (params.clone(), params.clone());
                plus[i] += eps;
                minus[i] -= eps;
                let numeric = (loss(&shape, &plus, w, h, &input, &probe) - loss(&shape, &minus, w, h, &input, &probe))
                    / (2.0 * f64::from(eps));
                assert!(
                    (numeric - f64::from(d_params[i])).abs() < 3e-3,
                    "k{kernel} relu {relu} param {i}: {numeric} vs {}",
                    d_params[i]
                );
            }
            for i in (0..input.len()).step_by(3) {
                let (mut plus, mut minus) = (input.clone(), input.clone());
                plus[i] += eps;
                minus[i] -= eps;
                let numeric = (loss(&shape, &params, w, h, &plus, &probe)
                    - loss(&shape, &params, w, h, &minus, &probe))
                    / (2.0 * f64::from(eps));
                assert!(
                    (numeric - f64::from(d_input[i])).abs() < 3e-3,
                    "k{kernel} relu {relu} input {i}: {numeric} vs {}",
                    d_input[i]
                );
            }
        }
    }

    #[test]
    fn a_centred_identity_kernel_copies_and_borders_are_zero_padded() {
        let shape = ConvShape { inputs: 2, outputs: 2, kernel: 3, relu: false };
        let mut params = vec![0.0; shape.param_count()];
        // Tap (1, 1) is the centre: identity there.
        for c in 0..2 {
            params[(4 * 2 + c) * 2 + c] = 1.0;
        }
        let (w, h) = (4, 3);
        let input = random(w * h * 2, 9);
        let mut out = vec![0.0; input.len()];
        conv_forward(SimdMode::Auto, &shape, &params, w, h, &input, &mut out).expect("forward");
        assert_eq!(out, input);
        // A kernel reading the left neighbour: column 0 reads the zero padding.
        params.fill(0.0);
        for c in 0..2 {
            params[(3 * 2 + c) * 2 + c] = 1.0;
        }
        conv_forward(SimdMode::Auto, &shape, &params, w, h, &input, &mut out).expect("forward");
        for y in 0..h {
            assert_eq!(&out[(y * w) * 2..][..2], &[0.0, 0.0]);
            assert_eq!(&out[(y * w + 1) * 2..][..2], &input[(y * w) * 2..][..2]);
        }
        assert!(conv_forward(SimdMode::Auto, &shape, &params, w, h, &input[1..], &mut out).is_err());
        assert!(ConvShape { kernel: 2, ..shape }.validate().is_err());
    }

    #[test]
    fn pooling_upsampling_and_concatenation_are_adjoint_to_their_backward() {
        // <forward(x), y> == <x, backward(y)> for the linear layers.
        let (w, h, c) = (6, 4, 3);
        let x = random(w * h * c, 4);
        let y = random(w * h * c / 4, 5);
        let mut fx = vec![0.0; y.len()];
        pool_forward(w, h, c, &x, &mut fx);
        let mut by = vec![0.0; x.len()];
        pool_backward(w, h, c, &y, &mut by);
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(a, b)| f64::from(a * b)).sum::<f64>();
        assert!((dot(&fx, &y) - dot(&x, &by)).abs() < 1e-4);

        let small = random(3 * 2 * c, 6);
        let big = random(6 * 4 * c, 7);
        let mut up = vec![0.0; big.len()];
        upsample_forward(3, 2, c, &small, &mut up);
        let mut down = vec![0.0; small.len()];
        upsample_backward(3, 2, c, &big, &mut down);
        assert!((dot(&up, &big) - dot(&small, &down)).abs() < 1e-4);

        let (a, b) = (random(10 * 2, 8), random(10 * 3, 9));
        let mut ab = vec![0.0; 50];
        concat(10, &a, 2, &b, 3, &mut ab);
        let (mut da, mut db) = (vec![0.0; 20], vec![0.0; 30]);
        split(10, &ab, 2, 3, &mut da, &mut db);
        assert_eq!((da, db), (a, b));
    }
}
