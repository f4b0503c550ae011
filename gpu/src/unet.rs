//! The GI U-Net on the GPU (issue 13): the twin of [`nephele_nn::UNet::forward`], layer by
//! layer in WGSL (`unet_conv.wgsl`, `unet_pool.wgsl`): the network's parameters uploaded
//! once, one dispatch per convolution or pooling, every dispatch of a pass in one submission,
//! the decoder's upsampling and skip concatenation read in place by the convolution that
//! consumes them (no buffer for either). Checked against the CPU forward in `unet_tests.rs`.
//!
//! A pass may compute only the output pixels a mask selects ([`GpuUNet::forward_masked`], the
//! twin of [`nephele_nn::UNet::forward_masked`]): each layer's mask
//! ([`nephele_nn::UNetConfig::layer_masks`], made on the CPU) travels bit-packed in one buffer,
//! and an invocation whose pixel it leaves out writes 0 and returns.

use std::sync::Arc;

use nephele_nn::conv::{ConvShape, PixelMask};
use nephele_nn::{UNet, UNetConfig};
use wgpu::util::DeviceExt;

use crate::context::{GpuContext, GpuError};
use crate::dispatch::{pipeline, read_back, upload, workgroup_grid};

/// A U-Net resident on the GPU.
#[derive(Debug)]
pub struct GpuUNet {
    ctx: Arc<GpuContext>,
    config: UNetConfig,
    layers: Vec<ConvShape>,
    /// Start of each layer's parameters in `params` (floats).
    offsets: Vec<u32>,
    params: wgpu::Buffer,
    conv: wgpu::ComputePipeline,
    pool: wgpu::ComputePipeline,
}

impl GpuUNet {
    /// Uploads `net`'s parameters and compiles the two kernels.
    pub fn new(ctx: Arc<GpuContext>, net: &UNet) -> Result<GpuUNet, GpuError> {
        let config = net.config().clone();
        let layers = config.layers();
        let mut offsets = Vec::with_capacity(layers.len());
        let mut at = 0u32;
        for layer in &layers {
            offsets.push(at);
            at += layer.param_count() as u32;
        }
        let words: Vec<u32> = net.params().iter().map(|v| v.to_bits()).collect();
        let params = upload(&ctx, "U-Net parameters", &words)?;
        let conv = pipeline(&ctx, "U-Net convolution", include_str!("unet_conv.wgsl").into())?;
        let pool = pipeline(&ctx, "U-Net pooling", include_str!("unet_pool.wgsl").into())?;
        Ok(GpuUNet { ctx, config, layers, offsets, params, conv, pool })
    }

    pub fn config(&self) -> &UNetConfig {
        &self.config
    }

    /// One forward pass over an image of `width x height` (inputs as
    /// [`nephele_nn::UNet::forward`] takes them); returns each head's output, left first.
    pub fn forward(&self, width: usize, height: usize, input: &[f32]) -> Result<Vec<Vec<f32>>, GpuError> {
        self.forward_masked(width, height, input, None)
    }

    /// [`Self::forward`] for the output pixels `needed` selects (all when `None`): each layer
    /// computes only what those pixels read through the layers after it; the heads' other
    /// pixels are 0, as [`nephele_nn::UNet::forward_masked`] gives them.
    pub fn forward_masked(
        &self,
        width: usize,
        height: usize,
        input: &[f32],
        needed: Option<&PixelMask>,
    ) -> Result<Vec<Vec<f32>>, GpuError> {
        let c = &self.config;
        c.check_size(width, height).map_err(|e| GpuError::Unsupported(e.to_string()))?;
        let expected = width * height * c.eyes * c.inputs;
        if input.len() != expected {
            return Err(GpuError::Unsupported(format!("{} input values for {expected}", input.len())));
        }
        let masks = needed
            .map(|n| c.layer_masks(width, height, n))
            .transpose()
            .map_err(|e| GpuError::Unsupported(e.to_string()))?;
        let (mask_words, mask_offsets) = pack_masks(masks.as_deref());
        let device = &self.ctx.device;
        let levels = c.levels();
        let size = |level: usize| ((width >> level) as u32, (height >> level) as u32);
        let words: Vec<u32> = input.iter().map(|v| v.to_bits()).collect();
        let input_buf = upload(&self.ctx, "U-Net input", &words)?;
        let empty = upload(&self.ctx, "nothing", &[])?;
        let mask_buf = upload(&self.ctx, "U-Net layer masks", &mask_words)?;
        let mask = |index: usize| (&mask_buf, mask_offsets.as_ref().map(|o| o[index]));
        let max = self.ctx.limits().max_storage_buffer_binding_size;
        let buffer = |label: &str, floats: u64| -> Result<wgpu::Buffer, GpuError> {
            if 4 * floats > max {
                return Err(GpuError::TooLarge(format!(
                    "{label}: {} bytes, the device binds at most {max}",
                    4 * floats
                )));
            }
            Ok(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: 4 * floats.max(1),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }))
        };
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("U-Net") });
        // Every layer's output, in layer order (as the CPU workspace).
        let mut outputs: Vec<wgpu::Buffer> = Vec::with_capacity(self.layers.len());
        let mut pooled: Vec<wgpu::Buffer> = Vec::with_capacity(levels);
        let pixels = |(w, h): (u32, u32)| u64::from(w) * u64::from(h);
        // Encoder.
        for level in 0..levels {
            let (w, h) = size(level);
            for (n, index) in [2 * level, 2 * level + 1].into_iter().enumerate() {
                let layer = self.layers[index];
                let out = buffer("U-Net activations", pixels((w, h)) * layer.outputs as u64)?;
                let source = match (n, level) {
                    (0, 0) => &input_buf,
                    (0, _) => &pooled[level - 1],
                    _ => &outputs[index - 1],
                };
                let source = (source, layer.inputs as u32, false);
                self.conv(&mut encoder, index, (w, h), source, (&empty, 0), mask(index), &out);
                outputs.push(out);
            }
            if level + 1 < levels {
                let channels = c.channels[level] as u32;
                let out = buffer("U-Net pooled", pixels((w / 2, h / 2)) * u64::from(channels))?;
                self.pool_into(&mut encoder, (w, h), channels, &outputs[2 * level + 1], &out);
                pooled.push(out);
            }
        }
        // Decoder, coarsest first: the first convolution of a level reads the level below
        // (upsampled) and the skip in place.
        let mut below = 2 * levels - 1;
        for (step, level) in (0..levels - 1).rev().enumerate() {
            let (w, h) = size(level);
            let (a, b) = (2 * levels + 2 * step, 2 * levels + 2 * step + 1);
            let out_a = buffer("U-Net activations", pixels((w, h)) * self.layers[a].outputs as u64)?;
            let below_channels = c.channels[level + 1] as u32;
            let skip = (&outputs[2 * level + 1], c.channels[level] as u32);
            self.conv(&mut encoder, a, (w, h), (&outputs[below], below_channels, true), skip, mask(a), &out_a);
            outputs.push(out_a);
            let out_b = buffer("U-Net activations", pixels((w, h)) * self.layers[b].outputs as u64)?;
            let source = (&outputs[a], self.layers[b].inputs as u32, false);
            self.conv(&mut encoder, b, (w, h), source, (&empty, 0), mask(b), &out_b);
            outputs.push(out_b);
            below = b;
        }
        // Heads.
        let first_head = self.layers.len() - c.eyes;
        let full = size(0);
        let head_floats = pixels(full) * c.outputs as u64;
        let mut readbacks = Vec::with_capacity(c.eyes);
        for head in first_head..self.layers.len() {
            let out = buffer("U-Net head", head_floats)?;
            let source = (&outputs[below], self.layers[head].inputs as u32, false);
            self.conv(&mut encoder, head, full, source, (&empty, 0), mask(head), &out);
            let readback = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("U-Net readback"),
                size: 4 * head_floats,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            encoder.copy_buffer_to_buffer(&out, 0, &readback, 0, 4 * head_floats);
            outputs.push(out);
            readbacks.push(readback);
        }
        let submission = self.ctx.queue.submit([encoder.finish()]);
        let readbacks: Vec<&wgpu::Buffer> = readbacks.iter().collect();
        read_back(&self.ctx, submission, &readbacks)
    }

    /// Records layer `index` over a `w x h` image: input `a` (`ca` channels, at half
    /// resolution when `a_half`) then `b` (`cb` channels) per pixel, into `out`; only the
    /// pixels of the layer's mask (bit-packed at a word offset of `masks`) when it has one.
    #[allow(clippy::too_many_arguments)]
    fn conv(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        index: usize,
        (w, h): (u32, u32),
        (a, ca, a_half): (&wgpu::Buffer, u32, bool),
        (b, cb): (&wgpu::Buffer, u32),
        (masks, mask_offset): (&wgpu::Buffer, Option<u32>),
        out: &wgpu::Buffer,
    ) {
        let layer = self.layers[index];
        let words = [
            w,
            h,
            ca,
            cb,
            layer.outputs as u32,
            layer.kernel as u32,
            u32::from(layer.relu),
            u32::from(a_half),
            self.offsets[index],
            u32::from(mask_offset.is_some()),
            mask_offset.unwrap_or(0),
            0,
        ];
        let values = u64::from(w) * u64::from(h) * layer.outputs as u64;
        self.dispatch(encoder, &self.conv, &words, &[&self.params, a, b, out, masks], values);
    }

    fn pool_into(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        (w, h): (u32, u32),
        channels: u32,
        src: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) {
        let values = u64::from(w / 2) * u64::from(h / 2) * u64::from(channels);
        self.dispatch(encoder, &self.pool, &[w, h, channels, 0], &[src, out], values);
    }

    /// One dispatch of `values` invocations: binding 0 the uniform `words`, then `buffers`.
    fn dispatch(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        words: &[u32],
        buffers: &[&wgpu::Buffer],
        values: u64,
    ) {
        let device = &self.ctx.device;
        let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("U-Net layer"),
            contents: bytemuck::cast_slice(words),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let mut entries = vec![wgpu::BindGroupEntry { binding: 0, resource: uniform.as_entire_binding() }];
        for (i, b) in buffers.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry { binding: 1 + i as u32, resource: b.as_entire_binding() });
        }
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        });
        let (gx, gy) = workgroup_grid(&self.ctx, values);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: None, timestamp_writes: None });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
    }
}

/// Every layer's mask bit-packed (pixel `p` of layer `i` is bit `p % 32` of word
/// `offsets[i] + p / 32`), and those offsets; one unused word and `None` without masks.
fn pack_masks(masks: Option<&[PixelMask]>) -> (Vec<u32>, Option<Vec<u32>>) {
    let Some(masks) = masks else { return (vec![0], None) };
    let mut words = Vec::new();
    let mut offsets = Vec::with_capacity(masks.len());
    for mask in masks {
        offsets.push(words.len() as u32);
        let (w, h) = (mask.width(), mask.height());
        let start = words.len();
        words.resize(start + (w * h).div_ceil(32), 0);
        for p in (0..w * h).filter(|&p| mask.get(p % w, p / w)) {
            words[start + p / 32] |= 1 << (p % 32);
        }
    }
    words.push(0);
    (words, Some(offsets))
}

/// The farm's GI kernel runs its networks through this ([`nephele_kernels::gi::UNetDevice`]).
impl nephele_kernels::gi::UNetDevice for GpuUNet {
    fn forward(
        &self,
        width: usize,
        height: usize,
        input: &[f32],
        needed: Option<&PixelMask>,
    ) -> Result<Vec<Vec<f32>>, String> {
        GpuUNet::forward_masked(self, width, height, input, needed).map_err(|e| e.to_string())
    }

    fn label(&self) -> String {
        self.ctx.label()
    }
}
