//! The i-NGP-style baseline on a GPU (`ngp.wgsl`): the same field, the same samples, so that
//! GPU ratios between i-NOLF and its baseline compare like with like.

use std::fmt;
use std::sync::Arc;

use crate::context::{GpuContext, GpuError};
use crate::dispatch::{Words, pipeline, render, upload, warm_up};
use nephele_geometry::camera::Camera;
use nephele_kernels::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel};
use nephele_kernels::ngp::field::EARLY_STOP_TRANSMITTANCE;
use nephele_kernels::ngp::{NgpKernel, RadianceField};
use nephele_nn::{Activation, sh_coefficient_count};

/// Samples whose blending weight is below this skip the colour network (as the CPU field).
const MIN_COLOR_WEIGHT: f32 = 1e-4;

/// A radiance field resident on a GPU.
pub struct GpuNgpKernel {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    occupancy: wgpu::Buffer,
    grid: wgpu::Buffer,
    mlp: wgpu::Buffer,
    field_params: Words,
    bounds: Bounds,
    bytes: u64,
}

impl fmt::Debug for GpuNgpKernel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuNgpKernel").field("device", &self.ctx).field("bytes", &self.bytes).finish()
    }
}

fn shader_source(field: &RadianceField) -> Result<String, GpuError> {
    let c = field.config;
    let (d, col) = (field.density.config(), field.color.config());
    if d.hidden_layers != 1 || d.output_activation != Activation::None || col.output_activation != Activation::Sigmoid {
        return Err(GpuError::Unsupported(format!("radiance field networks {d:?} / {col:?}")));
    }
    let sh = sh_coefficient_count(c.sh_degree);
    Ok(format!(
        "const LEVELS: u32 = {}u;\nconst ENC: u32 = {}u;\nconst D_HIDDEN: u32 = {}u;\nconst D_OUT: u32 = {}u;\n\
         const C_IN: u32 = {}u;\nconst C_HIDDEN: u32 = {}u;\nconst C_LAYERS: u32 = {}u;\nconst SH_COUNT: u32 = {}u;\n\
         const C_OFFSET: u32 = {}u;\n{}",
        field.grid.levels().len(),
        field.grid.output_dim(),
        d.hidden,
        d.output,
        col.input,
        col.hidden.max(1),
        col.hidden_layers,
        sh,
        field.density.num_params(),
        include_str!("ngp.wgsl")
    ))
}

impl GpuNgpKernel {
    /// Uploads `kernel`'s field (hash grid, both networks, occupancy bits) and builds the
    /// pipeline.
    pub fn new(ctx: Arc<GpuContext>, kernel: &NgpKernel) -> Result<GpuNgpKernel, GpuError> {
        let field = kernel.field();
        let source = shader_source(field)?;
        let occ = &field.occupancy;
        let mut o = Words::default();
        let fine = o.bits(occ.words());
        let coarse = o.bits(occ.coarse_words());
        let levels = o.offset();
        for l in field.grid.levels() {
            o.f32s([l.scale]);
            o.u32s([l.resolution, l.offset as u32, l.size as u32, u32::from(l.dense)]);
        }
        let params: Vec<u32> = field.density.params().iter().chain(field.color.params()).map(|v| v.to_bits()).collect();
        let grid: Vec<u32> = field.grid.params().iter().map(|v| v.to_bits()).collect();
        let occupancy = upload(&ctx, "occupancy", &o.0)?;
        let grid_buf = upload(&ctx, "hash grid", &grid)?;
        let mlp = upload(&ctx, "field mlps", &params)?;
        let bytes = 4 * (o.0.len() + grid.len() + params.len()) as u64;
        let pipeline = pipeline(&ctx, "ngp.wgsl", source)?;
        let mut w = Words::default();
        w.vec4([field.min.x, field.min.y, field.min.z, field.size]);
        w.f32s([field.step_size()]);
        w.u32s([occ.resolution(), fine, coarse, levels]);
        w.f32s([EARLY_STOP_TRANSMITTANCE, MIN_COLOR_WEIGHT]);
        w.u32s([0]);
        let kernel = GpuNgpKernel {
            bounds: kernel.bounds(),
            ctx,
            pipeline,
            occupancy,
            grid: grid_buf,
            mlp,
            field_params: w,
            bytes,
        };
        warm_up(&kernel)?;
        Ok(kernel)
    }

    /// Bytes of the field resident on the device.
    pub fn device_bytes(&self) -> u64 {
        self.bytes
    }
}

impl RayKernel for GpuNgpKernel {
    fn kind(&self) -> &'static str {
        "ngp"
    }

    fn bounds(&self) -> Bounds {
        self.bounds
    }

    /// `queries` counts density-network evaluations, as the CPU kernel's; the GPU stops
    /// counting at the early-stop sample, the CPU at the end of its 16-sample chunk.
    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        let tables = [&self.occupancy, &self.grid, &self.mlp];
        let (out, samples) = render(&self.ctx, &self.pipeline, camera, pixels, &self.field_params.0, &tables)?;
        let rays_hit = samples.iter().filter(|&&s| s > 0.0).count() as u64;
        let queries = samples.iter().map(|&s| s as u64).sum();
        Ok((out, KernelStats { rays: pixels.len() as u64, rays_hit, queries, hidden: 0 }))
    }
}
