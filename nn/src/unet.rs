//! A small U-Net (Ronneberger et al. 2015) described by data, for the stereo neural global
//! illumination model (Zhang and Simo-Serra): per level two 3x3 convolutions with ReLU, 2x2
//! average pooling down, nearest upsampling and a skip concatenation up, and one 1x1 output
//! head per eye at the end of the decoder.
//!
//! A single-eye network (`eyes = 1`) maps one eye's per-pixel inputs to its output; the
//! stereo network (`eyes = 2`) takes both eyes' inputs stacked per pixel (left then right),
//! shares every layer but the first and has two heads, left then right: one pass for both
//! eyes. [`UNet::stereo_from_single`] builds the stereo student from a trained single-eye
//! teacher: every weight copied except the first layer (it sees twice the channels) and the
//! right-eye head, which start fresh as in the paper or, closer to the teacher, from its
//! first layer over the mean of both eyes and its head ([`StudentStart`]).
//!
//! # Why not burn (or candle)
//!
//! The stereo GI issue asked for a maintained deep-learning crate with CPU and wgpu backends
//! and autodiff, burn being the obvious one. Measured here: burn 0.22.1 with `std, autodiff,
//! ndarray, wgpu, optim` takes 13 min 40 s to compile its dependencies alone (release, 2
//! cores) and makes a 75 MB test binary, against a CI budget of 30 minutes that the suite
//! already uses two thirds of. The network this model needs is five kinds of layer (3x3 and
//! 1x1 convolution, ReLU, average pooling, nearest upsampling, concatenation), a few tens of
//! thousands of multiply-adds per pixel: written out by hand with their backward passes
//! they are a few hundred lines, checked against finite differences below, share the flat
//! parameter vectors and [`crate::Adam`] of the other networks here, and cost no build time.
//! The GPU twin is a WGSL kernel of the same layers in `nephele-gpu`, as for i-NOLF. Should
//! the model grow (attention, training on a GPU), burn is the place to go, behind a feature
//! only the GI trainer enables.
//!
//! Parameters are one flat vector, layer after layer (encoder levels down, decoder levels up,
//! heads), each layer its weights then its biases ([`crate::conv`]'s layout).

use crate::conv::{
    ConvShape, PixelMask, concat, conv_backward, conv_forward, conv_forward_masked, pool_backward, pool_forward, split,
    upsample_backward, upsample_forward,
};
use crate::simd::SimdMode;
use crate::{InitRng, NnError, check_len};

/// How the stereo student's first layer and right-eye head start ([`UNet::stereo_from_single`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StudentStart {
    /// As the paper: fresh (He-initialised) weights.
    #[default]
    Fresh,
    /// From the teacher: the first layer applies the teacher's first layer to the mean of both
    /// eyes' inputs (half its weights on each eye's channels), the right head is a copy of the
    /// teacher's head; so the untrained student already gives the teacher's output for
    /// inputs the two eyes share.
    FromTeacher,
}

/// The network's shape.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct UNetConfig {
    /// Input channels per eye.
    pub inputs: usize,
    /// 1 (single eye) or 2 (stereo: both eyes' inputs, two heads).
    pub eyes: usize,
    /// Output channels per head.
    pub outputs: usize,
    /// Channels of each level, finest first (e.g. `[16, 32, 64]`): images must divide by
    /// `2^(levels - 1)`.
    pub channels: Vec<usize>,
}

impl UNetConfig {
    /// The output pixels each convolution (in [`UNetConfig::layers`] order) must compute for
    /// the network's output at the pixels `needed` selects: walking back from the heads, a
    /// 3x3 convolution needs its input one pixel around what it computes, an upsampling the
    /// coarse pixels under it, a pooling the fine 2x2 blocks, a concatenation both halves.
    pub fn layer_masks(&self, width: usize, height: usize, needed: &PixelMask) -> Result<Vec<PixelMask>, NnError> {
        self.check_size(width, height)?;
        if (needed.width(), needed.height()) != (width, height) {
            return Err(NnError::Config(format!(
                "a {}x{} mask for a {width}x{height} image",
                needed.width(),
                needed.height()
            )));
        }
        let layers = self.layers();
        let levels = self.levels();
        let mut masks: Vec<PixelMask> = (0..layers.len())
            .map(|i| PixelMask::none(width >> level_of(i, levels), height >> level_of(i, levels)))
            .collect();
        // What a layer reads of its input for the pixels it computes.
        let read = |masks: &[PixelMask], i: usize| masks[i].dilated(layers[i].kernel / 2);
        let first_head = layers.len() - self.eyes;
        for head in first_head..layers.len() {
            masks[head] = needed.clone();
            let input = read(&masks, head);
            masks[first_head - 1].union_with(&input);
        }
        // Decoder, finest level first: step `s` works at level `levels - 2 - s`.
        for step in (0..levels - 1).rev() {
            let level = levels - 2 - step;
            let (a, b) = (2 * levels + 2 * step, 2 * levels + 2 * step + 1);
            let input = read(&masks, b);
            masks[a].union_with(&input);
            let joined = read(&masks, a);
            masks[2 * level + 1].union_with(&joined);
            let below = if step == 0 { 2 * levels - 1 } else { b - 2 };
            masks[below].union_with(&joined.coarsened());
        }
        // Encoder, coarsest level first.
        for level in (0..levels).rev() {
            let (a, b) = (2 * level, 2 * level + 1);
            let input = read(&masks, b);
            masks[a].union_with(&input);
            if level > 0 {
                let pooled = read(&masks, a);
                masks[2 * level - 1].union_with(&pooled.refined());
            }
        }
        Ok(masks)
    }

    pub fn validate(&self) -> Result<(), NnError> {
        if self.inputs == 0 || self.outputs == 0 || !(self.eyes == 1 || self.eyes == 2) {
            return Err(NnError::Config(format!(
                "U-Net of {} inputs, {} outputs, {} eyes (inputs and outputs > 0, 1 or 2 eyes)",
                self.inputs, self.outputs, self.eyes
            )));
        }
        if self.channels.is_empty() || self.channels.len() > 6 || self.channels.iter().any(|&c| c == 0 || c > 512) {
            return Err(NnError::Config(format!(
                "U-Net levels {:?} (1 to 6 levels of 1 to 512 channels)",
                self.channels
            )));
        }
        Ok(())
    }

    pub fn levels(&self) -> usize {
        self.channels.len()
    }

    /// Every convolution in parameter order: encoder `(a, b)` per level finest first,
    /// decoder `(a, b)` per level coarsest first, then the heads.
    pub fn layers(&self) -> Vec<ConvShape> {
        let c = &self.channels;
        let conv3 = |inputs, outputs| ConvShape { inputs, outputs, kernel: 3, relu: true };
        let mut layers = Vec::new();
        for (level, &channels) in c.iter().enumerate() {
            let inputs = if level == 0 { self.eyes * self.inputs } else { c[level - 1] };
            layers.push(conv3(inputs, channels));
            layers.push(conv3(channels, channels));
        }
        for level in (0..c.len() - 1).rev() {
            layers.push(conv3(c[level + 1] + c[level], c[level]));
            layers.push(conv3(c[level], c[level]));
        }
        for _ in 0..self.eyes {
            layers.push(ConvShape { inputs: c[0], outputs: self.outputs, kernel: 1, relu: false });
        }
        layers
    }

    pub fn param_count(&self) -> usize {
        self.layers().iter().map(ConvShape::param_count).sum()
    }

    /// Multiply-adds per full-resolution pixel of one forward pass (coarser levels count
    /// a quarter per level down).
    pub fn macs_per_pixel(&self) -> f64 {
        let levels = self.levels();
        self.layers()
            .iter()
            .enumerate()
            .map(|(i, layer)| layer.macs_per_pixel() as f64 / 4f64.powi(level_of(i, levels) as i32))
            .sum()
    }

    /// Whether an image of `width x height` fits the levels.
    pub fn check_size(&self, width: usize, height: usize) -> Result<(), NnError> {
        let step = 1 << (self.levels() - 1);
        if width == 0 || height == 0 || !width.is_multiple_of(step) || !height.is_multiple_of(step) {
            return Err(NnError::Config(format!(
                "image {width}x{height}: a U-Net of {} levels needs sides that divide by {step}",
                self.levels()
            )));
        }
        Ok(())
    }
}

/// The network: shape and parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct UNet {
    config: UNetConfig,
    params: Vec<f32>,
    /// Start of each layer's parameters.
    offsets: Vec<usize>,
    /// Instruction set of the forward convolutions ([`UNet::set_simd`]).
    simd: SimdMode,
}

/// Activations of one forward pass, kept for the backward pass and reused between calls.
#[derive(Debug, Default, Clone)]
pub struct UNetWorkspace {
    size: (usize, usize),
    /// Output of every convolution, in layer order.
    outputs: Vec<Vec<f32>>,
    /// Pooled encoder outputs, input of encoder levels 1.. (index level - 1).
    pooled: Vec<Vec<f32>>,
    /// Concatenated (upsampled, skip) inputs of the decoder levels (decoder order).
    joined: Vec<Vec<f32>>,
    /// Scratch for the upsampled image of each decoder level.
    upsampled: Vec<Vec<f32>>,
    /// Multiply-adds of the last forward pass: (done, a whole pass's).
    macs: (u64, u64),
}

impl UNet {
    /// A network with He-initialised weights, deterministic by `seed`.
    pub fn new(config: UNetConfig, seed: u64) -> Result<UNet, NnError> {
        config.validate()?;
        let mut rng = InitRng::new(seed);
        let mut params = Vec::with_capacity(config.param_count());
        let mut offsets = Vec::new();
        for layer in config.layers() {
            offsets.push(params.len());
            layer.init(&mut rng, &mut params);
        }
        Ok(UNet { config, params, offsets, simd: SimdMode::Auto })
    }

    /// A network of `config` with the given parameters (a loaded model).
    pub fn from_params(config: UNetConfig, params: Vec<f32>) -> Result<UNet, NnError> {
        config.validate()?;
        check_len("U-Net parameters", config.param_count(), params.len())?;
        if params.iter().any(|p| !p.is_finite()) {
            return Err(NnError::Config("U-Net parameters hold NaN or infinity".into()));
        }
        let mut offsets = Vec::new();
        let mut at = 0;
        for layer in config.layers() {
            offsets.push(at);
            at += layer.param_count();
        }
        Ok(UNet { config, params, offsets, simd: SimdMode::Auto })
    }

    /// The stereo student of a single-eye teacher: every layer copied but the first (it sees
    /// both eyes) and the right-eye head, which start as `start` says.
    pub fn stereo_from_single(single: &UNet, start: StudentStart, seed: u64) -> Result<UNet, NnError> {
        if single.config.eyes != 1 {
            return Err(NnError::Config("the teacher must be a single-eye network".into()));
        }
        let mut stereo = UNet::new(UNetConfig { eyes: 2, ..single.config.clone() }, seed)?;
        let layers = single.config.layers();
        // Layer 0 differs in shape; the teacher's last layer is its only head, which becomes
        // the left head (index `layers.len() - 1` in both); the right head follows it.
        for index in 1..layers.len() {
            let source = single.layer_params(index);
            let start = stereo.offsets[index];
            stereo.params[start..start + source.len()].copy_from_slice(source);
        }
        if start == StudentStart::FromTeacher {
            // The first layer sees the mean of both eyes' inputs through the teacher's
            // weights: half of them on each eye's channels, the teacher's biases.
            let (inputs, outputs, taps) = (single.config.inputs, layers[0].outputs, layers[0].kernel.pow(2));
            let teacher = single.layer_params(0);
            let first = &mut stereo.params[..stereo.offsets[1]];
            for tap in 0..taps {
                for eye in 0..2 {
                    for i in 0..inputs {
                        let from = &teacher[(tap * inputs + i) * outputs..][..outputs];
                        let to = &mut first[(tap * 2 * inputs + eye * inputs + i) * outputs..][..outputs];
                        for (t, f) in to.iter_mut().zip(from) {
                            *t = 0.5 * f;
                        }
                    }
                }
            }
            let (weights, biases) = (taps * 2 * inputs * outputs, taps * inputs * outputs);
            first[weights..].copy_from_slice(&teacher[biases..]);
            // The right head starts as the teacher's (the left head's) copy.
            let n = layers.len();
            let head = single.layer_params(n - 1);
            let at = stereo.offsets[n];
            stereo.params[at..at + head.len()].copy_from_slice(head);
        }
        Ok(stereo)
    }

    pub fn config(&self) -> &UNetConfig {
        &self.config
    }

    /// Chooses the instruction set of the forward pass (default: the best the CPU has;
    /// [`SimdMode::Off`] runs the same register-blocked loops one lane wide, for the ratio).
    pub fn set_simd(&mut self, simd: SimdMode) {
        self.simd = simd;
    }

    pub fn simd(&self) -> SimdMode {
        self.simd
    }

    pub fn params(&self) -> &[f32] {
        &self.params
    }

    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    /// Number of convolutions.
    pub fn layer_count(&self) -> usize {
        self.offsets.len()
    }

    /// The parameters of layer `index` (see [`UNetConfig::layers`]).
    pub fn layer_params(&self, index: usize) -> &[f32] {
        let end = self.offsets.get(index + 1).copied().unwrap_or(self.params.len());
        &self.params[self.offsets[index]..end]
    }

    /// One forward pass over an image of `width x height` whose pixels hold `eyes * inputs`
    /// channels (left eye's then right eye's). Returns each head's output image
    /// (`outputs` channels per pixel), left head first; the activations stay in `ws` for
    /// [`UNet::backward`].
    pub fn forward<'w>(
        &self,
        width: usize,
        height: usize,
        input: &[f32],
        ws: &'w mut UNetWorkspace,
    ) -> Result<Vec<&'w [f32]>, NnError> {
        self.forward_masked(width, height, input, None, ws)
    }

    /// [`UNet::forward`] for the output pixels `needed` selects (all when `None`): each
    /// layer computes only what those pixels read through the layers after it
    /// ([`UNet::layer_masks`]); the heads' other pixels are 0. The needed pixels get exactly
    /// the whole pass's values. Not for training: the backward pass needs every activation.
    pub fn forward_masked<'w>(
        &self,
        width: usize,
        height: usize,
        input: &[f32],
        needed: Option<&PixelMask>,
        ws: &'w mut UNetWorkspace,
    ) -> Result<Vec<&'w [f32]>, NnError> {
        let c = &self.config;
        c.check_size(width, height)?;
        check_len("U-Net input", width * height * c.eyes * c.inputs, input.len())?;
        let layers = c.layers();
        let levels = c.levels();
        ws.allocate(c, &layers, width, height);
        let size = |level: usize| (width >> level, height >> level);
        let masks = needed.map(|n| self.layer_masks(width, height, n)).transpose()?;
        let full: u64 = (0..layers.len())
            .map(|i| {
                (layers[i].macs_per_pixel() * (width >> level_of(i, levels)) * (height >> level_of(i, levels))) as u64
            })
            .sum();
        ws.macs = match &masks {
            None => (full, full),
            Some(masks) => {
                (masks.iter().zip(&layers).map(|(m, l)| (m.count() * l.macs_per_pixel()) as u64).sum(), full)
            }
        };
        let conv = |index: usize, w: usize, h: usize, source: &[f32], output: &mut [f32]| match &masks {
            None => conv_forward(self.simd, &layers[index], self.layer_params(index), w, h, source, output),
            Some(masks) => conv_forward_masked(
                self.simd,
                &layers[index],
                self.layer_params(index),
                w,
                h,
                source,
                output,
                &masks[index],
            ),
        };

        // Encoder.
        for level in 0..levels {
            let (w, h) = size(level);
            let (a, b) = (2 * level, 2 * level + 1);
            let source: &[f32] = if level == 0 { input } else { &ws.pooled[level - 1] };
            conv(a, w, h, source, &mut ws.outputs[a])?;
            let (before, after) = ws.outputs.split_at_mut(b);
            conv(b, w, h, &before[a], &mut after[0])?;
            if level + 1 < levels {
                pool_forward(w, h, c.channels[level], &ws.outputs[b], &mut ws.pooled[level]);
            }
        }
        // Decoder, coarsest first.
        let mut below = 2 * levels - 1;
        for (step, level) in (0..levels - 1).rev().enumerate() {
            let (w, h) = size(level);
            let (a, b) = (2 * levels + 2 * step, 2 * levels + 2 * step + 1);
            upsample_forward(w / 2, h / 2, c.channels[level + 1], &ws.outputs[below], &mut ws.upsampled[step]);
            let skip = &ws.outputs[2 * level + 1];
            concat(w * h, &ws.upsampled[step], c.channels[level + 1], skip, c.channels[level], &mut ws.joined[step]);
            conv(a, w, h, &ws.joined[step], &mut ws.outputs[a])?;
            let (before, after) = ws.outputs.split_at_mut(b);
            conv(b, w, h, &before[a], &mut after[0])?;
            below = b;
        }
        // Heads.
        let first_head = layers.len() - c.eyes;
        for head in first_head..layers.len() {
            let (before, after) = ws.outputs.split_at_mut(head);
            conv(head, width, height, &before[below], &mut after[0])?;
            if let Some(needed) = needed {
                for (p, out) in after[0].chunks_exact_mut(c.outputs).enumerate() {
                    if !needed.get(p % width, p / width) {
                        out.fill(0.0);
                    }
                }
            }
        }
        Ok(ws.outputs[first_head..].iter().map(Vec::as_slice).collect())
    }

    /// The output pixels each convolution must compute for the output at the pixels `needed`
    /// selects ([`UNetConfig::layer_masks`]).
    pub fn layer_masks(&self, width: usize, height: usize, needed: &PixelMask) -> Result<Vec<PixelMask>, NnError> {
        self.config.layer_masks(width, height, needed)
    }

    /// Backward pass of the last [`UNet::forward`] with `ws`: `d_heads` holds the loss
    /// gradient of each head's output (left first; overwritten). Adds the parameter gradient
    /// into `d_params`.
    pub fn backward(
        &self,
        input: &[f32],
        ws: &mut UNetWorkspace,
        d_heads: &mut [Vec<f32>],
        d_params: &mut [f32],
    ) -> Result<(), NnError> {
        let c = &self.config;
        let (width, height) = ws.size;
        check_len("U-Net parameter gradient", self.params.len(), d_params.len())?;
        check_len("U-Net head gradients", c.eyes, d_heads.len())?;
        let layers = c.layers();
        let levels = c.levels();
        let size = |level: usize| (width >> level, height >> level);
        let d_layer = |index: usize| self.offsets[index]..self.offsets[index] + layers[index].param_count();
        // Gradient of every encoder level's output (skip + the level below).
        let mut d_encoder: Vec<Vec<f32>> =
            (0..levels).map(|l| vec![0.0; size(l).0 * size(l).1 * c.channels[l]]).collect();

        // Heads: both read the last decoder output (or the bottom level when there is one level).
        let last = if levels == 1 { 1 } else { 2 * levels + 2 * (levels - 1) - 1 };
        let mut d_top = vec![0.0; width * height * c.channels[0]];
        let first_head = layers.len() - c.eyes;
        for (eye, d_head) in d_heads.iter_mut().enumerate() {
            let head = first_head + eye;
            check_len("U-Net head gradient", width * height * c.outputs, d_head.len())?;
            let mut d_in = vec![0.0; d_top.len()];
            let range = d_layer(head);
            conv_backward(
                self.simd,
                &layers[head],
                self.layer_params(head),
                width,
                height,
                &ws.outputs[last],
                &ws.outputs[head],
                d_head,
                &mut d_params[range],
                Some(&mut d_in),
            )?;
            d_top.iter_mut().zip(&d_in).for_each(|(a, b)| *a += b);
        }

        // Decoder, finest first (the reverse of the forward order). The level indexes the
        // encoder gradients, the channel list and (through `step`) the decoder's buffers.
        let mut d_above = d_top;
        #[allow(clippy::needless_range_loop)]
        for level in 0..levels - 1 {
            let step = levels - 2 - level;
            let (w, h) = size(level);
            let (a, b) = (2 * levels + 2 * step, 2 * levels + 2 * step + 1);
            let mut d_a = vec![0.0; w * h * c.channels[level]];
            let range = d_layer(b);
            conv_backward(
                self.simd,
                &layers[b],
                self.layer_params(b),
                w,
                h,
                &ws.outputs[a],
                &ws.outputs[b],
                &mut d_above,
                &mut d_params[range],
                Some(&mut d_a),
            )?;
            let mut d_joined = vec![0.0; ws.joined[step].len()];
            let range = d_layer(a);
            conv_backward(
                self.simd,
                &layers[a],
                self.layer_params(a),
                w,
                h,
                &ws.joined[step],
                &ws.outputs[a],
                &mut d_a,
                &mut d_params[range],
                Some(&mut d_joined),
            )?;
            let (cu, cs) = (c.channels[level + 1], c.channels[level]);
            let mut d_up = vec![0.0; w * h * cu];
            let mut d_skip = vec![0.0; w * h * cs];
            split(w * h, &d_joined, cu, cs, &mut d_up, &mut d_skip);
            d_encoder[level].iter_mut().zip(&d_skip).for_each(|(a, b)| *a += b);
            let mut d_below = vec![0.0; (w / 2) * (h / 2) * cu];
            upsample_backward(w / 2, h / 2, cu, &d_up, &mut d_below);
            d_above = d_below;
        }
        // The bottom level's output feeds the decoder (or the heads directly).
        d_encoder[levels - 1].iter_mut().zip(&d_above).for_each(|(a, b)| *a += b);

        // Encoder, coarsest first.
        for level in (0..levels).rev() {
            let (w, h) = size(level);
            let (a, b) = (2 * level, 2 * level + 1);
            let mut d_out = std::mem::take(&mut d_encoder[level]);
            let mut d_a = vec![0.0; w * h * c.channels[level]];
            let range = d_layer(b);
            conv_backward(
                self.simd,
                &layers[b],
                self.layer_params(b),
                w,
                h,
                &ws.outputs[a],
                &ws.outputs[b],
                &mut d_out,
                &mut d_params[range],
                Some(&mut d_a),
            )?;
            let source: &[f32] = if level == 0 { input } else { &ws.pooled[level - 1] };
            let range = d_layer(a);
            if level == 0 {
                conv_backward(
                    self.simd,
                    &layers[a],
                    self.layer_params(a),
                    w,
                    h,
                    source,
                    &ws.outputs[a],
                    &mut d_a,
                    &mut d_params[range],
                    None,
                )?;
            } else {
                let mut d_pooled = vec![0.0; source.len()];
                conv_backward(
                    self.simd,
                    &layers[a],
                    self.layer_params(a),
                    w,
                    h,
                    source,
                    &ws.outputs[a],
                    &mut d_a,
                    &mut d_params[range],
                    Some(&mut d_pooled),
                )?;
                let mut d_finer = vec![0.0; (2 * w) * (2 * h) * c.channels[level - 1]];
                pool_backward(2 * w, 2 * h, c.channels[level - 1], &d_pooled, &mut d_finer);
                d_encoder[level - 1].iter_mut().zip(&d_finer).for_each(|(a, b)| *a += b);
            }
        }
        Ok(())
    }
}

/// The level (0 finest) at which layer `index` of a U-Net of `levels` works.
fn level_of(index: usize, levels: usize) -> usize {
    if index < 2 * levels {
        index / 2
    } else if index < 2 * levels + 2 * (levels - 1) {
        levels - 2 - (index - 2 * levels) / 2
    } else {
        0
    }
}

impl UNetWorkspace {
    pub fn new() -> Self {
        Self::default()
    }

    /// Multiply-adds of the last forward pass with this workspace, and of a whole pass over
    /// the same image: what a mask saved.
    pub fn last_macs(&self) -> (u64, u64) {
        self.macs
    }

    fn allocate(&mut self, c: &UNetConfig, layers: &[ConvShape], width: usize, height: usize) {
        let levels = c.levels();
        let pixels = |level: usize| (width >> level) * (height >> level);
        let level_of = |index: usize| level_of(index, levels);
        let resize = |v: &mut Vec<Vec<f32>>, sizes: Vec<usize>| {
            v.resize_with(sizes.len(), Vec::new);
            for (buffer, n) in v.iter_mut().zip(sizes) {
                buffer.resize(n, 0.0);
            }
        };
        resize(&mut self.outputs, layers.iter().enumerate().map(|(i, l)| pixels(level_of(i)) * l.outputs).collect());
        resize(&mut self.pooled, (1..levels).map(|l| pixels(l) * c.channels[l - 1]).collect());
        let decoder: Vec<usize> = (0..levels - 1).rev().collect();
        resize(&mut self.joined, decoder.iter().map(|&l| pixels(l) * (c.channels[l] + c.channels[l + 1])).collect());
        resize(&mut self.upsampled, decoder.iter().map(|&l| pixels(l) * c.channels[l + 1]).collect());
        self.size = (width, height);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(eyes: usize) -> UNetConfig {
        UNetConfig { inputs: 3, eyes, outputs: 2, channels: vec![4, 6, 8] }
    }

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = InitRng::new(seed);
        (0..n).map(|_| rng.uniform(1.0)).collect()
    }

    fn loss(net: &UNet, w: usize, h: usize, input: &[f32], probes: &[Vec<f32>]) -> f64 {
        let mut ws = UNetWorkspace::new();
        let heads = net.forward(w, h, input, &mut ws).expect("forward");
        heads.iter().zip(probes).map(|(o, p)| o.iter().zip(p).map(|(o, p)| f64::from(o * p)).sum::<f64>()).sum()
    }

    #[test]
    fn gradients_match_finite_differences_in_every_layer() {
        for eyes in [1, 2] {
            let mut net = UNet::new(config(eyes), 3).expect("net");
            // Small positive biases keep most ReLUs away from their kink.
            let layers = net.config().layers();
            for (i, layer) in layers.iter().enumerate() {
                let start = net.offsets[i] + layer.weight_count();
                net.params_mut()[start..start + layer.outputs].iter_mut().for_each(|b| *b = 0.1);
            }
            let (w, h) = (8, 4);
            let input = random(w * h * 3 * eyes, 4);
            let probes: Vec<Vec<f32>> = (0..eyes).map(|e| random(w * h * 2, 10 + e as u64)).collect();
            let mut ws = UNetWorkspace::new();
            net.forward(w, h, &input, &mut ws).expect("forward");
            let mut d_heads = probes.clone();
            let mut grads = vec![0.0; net.params().len()];
            net.backward(&input, &mut ws, &mut d_heads, &mut grads).expect("backward");
            // Three parameters of every layer. A finite step can push a ReLU across its kink
            // (the difference quotient then jumps); the analytic gradient must agree at one
            // of two step sizes.
            for (i, layer) in layers.iter().enumerate() {
                for pick in [0, layer.param_count() / 2, layer.param_count() - 1] {
                    let p = net.offsets[i] + pick;
                    let analytic = f64::from(grads[p]);
                    let numeric = |eps: f32| {
                        let mut plus = net.clone();
                        plus.params_mut()[p] += eps;
                        let mut minus = net.clone();
                        minus.params_mut()[p] -= eps;
                        (loss(&plus, w, h, &input, &probes) - loss(&minus, w, h, &input, &probes))
                            / (2.0 * f64::from(eps))
                    };
                    let tries = [numeric(1e-3), numeric(3e-4)];
                    assert!(
                        tries.iter().any(|n| (n - analytic).abs() < 3e-3 * (1.0 + analytic.abs())),
                        "eyes {eyes} layer {i} param {pick}: {tries:?} vs {analytic}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_stereo_student_copies_all_but_the_first_layer_and_the_right_head() {
        let single = UNet::new(config(1), 1).expect("single");
        let stereo = UNet::stereo_from_single(&single, StudentStart::Fresh, 2).expect("stereo");
        let fresh = UNet::new(config(2), 2).expect("fresh");
        let n = stereo.layer_count();
        assert_eq!(n, single.layer_count() + 1);
        assert_eq!(stereo.layer_params(0), fresh.layer_params(0), "first layer: fresh");
        assert_eq!(stereo.layer_params(0).len(), 2 * 9 * 3 * 4 + 4);
        for i in 1..n - 1 {
            assert_eq!(stereo.layer_params(i), single.layer_params(i), "layer {i} copied");
        }
        assert_eq!(stereo.layer_params(n - 2), single.layer_params(n - 2), "left head = the teacher's head");
        assert_eq!(stereo.layer_params(n - 1), fresh.layer_params(n - 1), "right head: fresh");
        assert_ne!(stereo.layer_params(n - 1), single.layer_params(n - 2));
        assert!(UNet::stereo_from_single(&stereo, StudentStart::Fresh, 3).is_err());
    }

    #[test]
    fn a_student_started_from_the_teacher_gives_its_output_when_the_eyes_agree() {
        let single = UNet::new(config(1), 1).expect("single");
        let stereo = UNet::stereo_from_single(&single, StudentStart::FromTeacher, 2).expect("stereo");
        let n = stereo.layer_count();
        for i in 1..n - 1 {
            assert_eq!(stereo.layer_params(i), single.layer_params(i), "layer {i} copied");
        }
        assert_eq!(stereo.layer_params(n - 1), single.layer_params(n - 2), "right head = the teacher's head");
        // Both eyes given the same image: both heads give the teacher's output for it (up to
        // the rounding of the halved weights' sums).
        let (width, height) = (8, 8);
        let mut rng = InitRng::new(9);
        let one: Vec<f32> = (0..width * height * 3).map(|_| rng.uniform(1.0)).collect();
        let both: Vec<f32> = one.chunks(3).flat_map(|p| p.iter().chain(p).copied().collect::<Vec<_>>()).collect();
        let (mut ws1, mut ws2) = (UNetWorkspace::new(), UNetWorkspace::new());
        let teacher = single.forward(width, height, &one, &mut ws1).expect("teacher")[0].to_vec();
        let heads = stereo.forward(width, height, &both, &mut ws2).expect("student");
        for head in heads {
            for (s, t) in head.iter().zip(&teacher) {
                assert!((s - t).abs() < 1e-4 * (1.0 + t.abs()), "{s} vs {t}");
            }
        }
    }

    #[test]
    fn both_heads_of_one_stereo_pass_equal_their_separate_evaluation() {
        // The stereo pass computes the shared trunk once; each head alone on that trunk
        // (a single-eye network holding the trunk and that head) gives the same image.
        let stereo = UNet::new(config(2), 5).expect("stereo");
        let (w, h) = (8, 8);
        let input = random(w * h * 6, 6);
        let mut ws = UNetWorkspace::new();
        let both: Vec<Vec<f32>> =
            stereo.forward(w, h, &input, &mut ws).expect("forward").iter().map(|s| s.to_vec()).collect();
        let n = stereo.layer_count();
        for (eye, expected) in both.iter().enumerate() {
            // A single-eye network whose first layer sees six channels has the stereo
            // network's trunk layer for layer; give it the trunk and this eye's head.
            let mut params: Vec<f32> = stereo.params()[..stereo.offsets[n - 2]].to_vec();
            params.extend_from_slice(stereo.layer_params(n - 2 + eye));
            let one_head = UNet::from_params(UNetConfig { inputs: 6, eyes: 1, ..config(1) }, params).expect("net");
            let mut ws1 = UNetWorkspace::new();
            let alone = one_head.forward(w, h, &input, &mut ws1).expect("forward")[0].to_vec();
            assert_eq!(&alone, expected, "eye {eye}");
        }
    }

    #[test]
    fn a_masked_pass_gives_the_needed_pixels_exactly_for_less_work() {
        // Blobs, single pixels at borders and corners, an empty and a full mask; one to
        // three levels, one and two eyes, both instruction sets.
        let (w, h) = (16, 12);
        let mut blob = PixelMask::none(w, h);
        for y in 3..9 {
            for x in 6..13 {
                blob.select(x, y);
            }
        }
        let mut corners = PixelMask::none(w, h);
        for (x, y) in [(0, 0), (15, 0), (0, 11), (15, 11), (7, 5)] {
            corners.select(x, y);
        }
        let mut rng = InitRng::new(77);
        let scattered =
            PixelMask::from_flags(w, h, (0..w * h).map(|_| rng.uniform(1.0) > 0.8).collect()).expect("mask");
        let masks = [blob, corners, scattered, PixelMask::none(w, h), PixelMask::all(w, h)];
        for channels in [vec![4], vec![4, 6], vec![4, 6, 8]] {
            for eyes in [1, 2] {
                let mut net = UNet::new(UNetConfig { channels: channels.clone(), ..config(eyes) }, 9).expect("net");
                let input = random(w * h * 3 * eyes, 11);
                for simd in [SimdMode::Auto, SimdMode::Off] {
                    net.set_simd(simd);
                    let mut ws = UNetWorkspace::new();
                    let whole: Vec<Vec<f32>> =
                        net.forward(w, h, &input, &mut ws).expect("forward").iter().map(|s| s.to_vec()).collect();
                    let (_, full) = ws.last_macs();
                    assert_eq!(ws.last_macs(), (full, full));
                    for (m, needed) in masks.iter().enumerate() {
                        // The same workspace: what the whole pass left in it must not matter.
                        let heads: Vec<Vec<f32>> = net
                            .forward_masked(w, h, &input, Some(needed), &mut ws)
                            .expect("masked")
                            .iter()
                            .map(|s| s.to_vec())
                            .collect();
                        let (done, total) = ws.last_macs();
                        assert_eq!(total, full);
                        assert!(done <= full, "mask {m}: {done} of {full}");
                        if needed.count() == 0 {
                            assert_eq!(done, 0);
                        }
                        if m < 2 {
                            assert!(done < full, "{channels:?} mask {m}: {done} of {full}: nothing saved");
                        }
                        for (head, want) in heads.iter().zip(&whole) {
                            for p in 0..w * h {
                                let got = &head[p * 2..][..2];
                                if needed.get(p % w, p / w) {
                                    assert_eq!(
                                        got,
                                        &want[p * 2..][..2],
                                        "{channels:?} eyes {eyes} {simd} mask {m} pixel {p}"
                                    );
                                } else {
                                    assert_eq!(got, &[0.0, 0.0], "mask {m} pixel {p} not needed");
                                }
                            }
                        }
                    }
                }
            }
        }
        let net = UNet::new(config(1), 1).expect("net");
        assert!(net.layer_masks(16, 12, &PixelMask::all(8, 12)).is_err());
    }

    #[test]
    fn sizes_and_counts_are_checked_and_stated() {
        let c = config(1);
        assert!(c.check_size(8, 12).is_ok() && c.check_size(6, 8).is_err() && c.check_size(0, 8).is_err());
        assert!(UNetConfig { channels: vec![], ..c.clone() }.validate().is_err());
        assert!(UNetConfig { eyes: 3, ..c.clone() }.validate().is_err());
        let net = UNet::new(c.clone(), 0).expect("net");
        assert_eq!(net.params().len(), c.param_count());
        // Level 0: 3->4, 4->4 and the decoder's 10->4, 4->4 and the head 4->2.
        let level0 = 9 * (3 * 4 + 4 * 4 + 10 * 4 + 4 * 4) + 4 * 2;
        let level1 = 9 * (4 * 6 + 6 * 6 + 14 * 6 + 6 * 6);
        let level2 = 9 * (6 * 8 + 8 * 8);
        let expected = level0 as f64 + level1 as f64 / 4.0 + level2 as f64 / 16.0;
        assert!((c.macs_per_pixel() - expected).abs() < 1e-9, "{} vs {expected}", c.macs_per_pixel());
        let mut bad = net.params().to_vec();
        bad[0] = f32::NAN;
        assert!(UNet::from_params(c.clone(), bad).is_err());
        let mut ws = UNetWorkspace::new();
        assert!(net.forward(8, 8, &[0.0; 10], &mut ws).is_err());
    }
}
