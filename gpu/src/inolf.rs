//! The i-NOLF kernel on a GPU: the asset's tables uploaded once, one compute dispatch per
//! batch of pixels (`inolf.wgsl`, one invocation per pixel).

use std::fmt;
use std::sync::Arc;

use crate::context::{GpuContext, GpuError};
use crate::dispatch::{Words, pipeline, render, upload, warm_up};
use nephele_geometry::camera::Camera;
use nephele_kernels::inolf::cubes::{DensityCubes, MAX_BLEND_SAMPLES, MIN_TRANSMITTANCE, SparseCubes};
use nephele_kernels::inolf::encoding::PshEncoding;
use nephele_kernels::inolf::kernel::{DiffuseSource, HIT_OPACITY, HitSource, InolfKernel, RAY_NEAR};
use nephele_kernels::inolf::model::SPECULAR_OUT;
use nephele_kernels::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel};
use nephele_nn::{Mlp, sh_coefficient_count};

/// Floats of the specular MLP that fit workgroup memory (WebGPU's 16 KiB minimum).
pub const MAX_SPECULAR_PARAMS: usize = 4096;

/// An i-NOLF asset resident on a GPU.
pub struct GpuInolfKernel {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    density: wgpu::Buffer,
    diffuse: wgpu::Buffer,
    psh: wgpu::Buffer,
    specular: wgpu::Buffer,
    /// The uniform words after the camera (`Params` in `inolf.wgsl`): ray constants, table
    /// sizes and offsets.
    params: Words,
    bounds: Bounds,
    bytes: u64,
}

impl fmt::Debug for GpuInolfKernel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuInolfKernel").field("device", &self.ctx).field("bytes", &self.bytes).finish()
    }
}

fn density_tables(d: &DensityCubes) -> (Words, [u32; 5]) {
    let c = d.cubes();
    let mut w = Words::default();
    let index = w.u32s(c.index().iter().copied());
    let data = w.bytes(c.data());
    let (words, bits) = d.voxel_bits();
    let voxels = w.bits(bits);
    debug_assert_eq!(bits.len(), words * c.cube_count());
    let proximity = w.bytes(d.proximity());
    let lut = w.f32s(d.decode_table().iter().copied());
    (w, [index, data, voxels, proximity, lut])
}

fn cube_tables(c: &SparseCubes) -> (Words, [u32; 2]) {
    let mut w = Words::default();
    let index = w.u32s(c.index().iter().copied());
    let data = w.bytes(c.data());
    (w, [index, data])
}

fn psh_tables(p: &PshEncoding) -> (Words, [u32; 3]) {
    let mut w = Words::default();
    let offsets =
        w.u32s(p.table.offsets().iter().map(|o| u32::from(o[0]) | (u32::from(o[1]) << 10) | (u32::from(o[2]) << 20)));
    let keys = w.u32s(p.table.keys().iter().copied());
    let features = w.f32s(p.features.iter().copied());
    (w, [offsets, keys, features])
}

/// The shader's size constants for this asset's specular MLP.
fn shader_source(mlp: &Mlp, psh_dim: u32, sh_degree: u32) -> String {
    let c = mlp.config();
    format!(
        "const S_IN: u32 = {}u;\nconst S_HIDDEN: u32 = {}u;\nconst S_LAYERS: u32 = {}u;\nconst S_OUT_ACT: u32 = {}u;\n\
         const S_PARAMS: u32 = {}u;\nconst PSH_DIM: u32 = {}u;\nconst SH_COUNT: u32 = {}u;\nconst MAX_BLEND_SAMPLES: u32 = {}u;\n{}",
        c.input,
        c.hidden.max(1),
        c.hidden_layers,
        c.output_activation.code(),
        mlp.num_params(),
        psh_dim,
        sh_coefficient_count(sh_degree),
        MAX_BLEND_SAMPLES,
        include_str!("inolf.wgsl")
    )
}

impl GpuInolfKernel {
    /// Uploads `kernel`'s tables and networks to `ctx`'s device and builds the pipeline.
    /// The GPU kernel marches the density cubes and reads the diffuse cubes; an asset set
    /// to other sources is an [`GpuError::Unsupported`].
    pub fn new(ctx: Arc<GpuContext>, kernel: &InolfKernel) -> Result<GpuInolfKernel, GpuError> {
        if kernel.hit_source() != HitSource::DensityCubes {
            return Err(GpuError::Unsupported("hit points from the density network (only the density cubes)".into()));
        }
        let Some(diffuse) = kernel.diffuse_cubes().filter(|_| kernel.diffuse_source() == DiffuseSource::Cubes) else {
            return Err(GpuError::Unsupported("diffuse colour from the network (only the diffuse cubes)".into()));
        };
        let mlp = kernel.specular();
        let cfg = mlp.config();
        let psh = kernel.psh();
        let sh_degree = kernel.shape().sh_degree;
        if cfg.output != SPECULAR_OUT || cfg.input != psh.dim() + sh_coefficient_count(sh_degree) + 1 {
            return Err(GpuError::Unsupported(format!("specular MLP {cfg:?} does not match the PSH and SH sizes")));
        }
        if mlp.num_params() > MAX_SPECULAR_PARAMS {
            return Err(GpuError::TooLarge(format!(
                "the specular MLP has {} parameters; the GPU kernel keeps at most {MAX_SPECULAR_PARAMS} in workgroup memory",
                mlp.num_params()
            )));
        }
        if diffuse.channels() > 6 {
            return Err(GpuError::Unsupported(format!("{} diffuse channels (at most 6)", diffuse.channels())));
        }
        let density = kernel.density();
        let (d_words, [d_index, d_data, d_voxels, d_proximity, d_lut]) = density_tables(density);
        let (c_words, [c_index, c_data]) = cube_tables(diffuse);
        let (p_words, [p_offsets, p_keys, p_features]) = psh_tables(psh);

        let density_buf = upload(&ctx, "density cubes", &d_words.0)?;
        let diffuse_buf = upload(&ctx, "diffuse cubes", &c_words.0)?;
        let psh_buf = upload(&ctx, "psh", &p_words.0)?;
        let specular_buf = upload(&ctx, "specular mlp", &mlp.params().iter().map(|v| v.to_bits()).collect::<Vec<_>>())?;
        let bytes = 4 * (d_words.0.len() + c_words.0.len() + p_words.0.len() + mlp.num_params()) as u64;
        let pipeline = pipeline(&ctx, "inolf.wgsl", shader_source(mlp, psh.dim() as u32, sh_degree))?;

        let c = density.cubes();
        let mut a = Words::default();
        // The hit rule (`DensityCubes::march`): the layer's opacity (2: never, for the other
        // rules), its gap as a distance and the median depth's transmittance (-1: never).
        let (layer_opacity, layer_gap_voxels) = density.hit_rule().layer();
        let layer_gap = layer_gap_voxels * density.cubes().sample_step();
        a.f32s([RAY_NEAR, HIT_OPACITY, density.march_stride() as f32, layer_opacity]);
        a.vec4([c.min().x, c.min().y, c.min().z, c.cell()]);
        let (voxel_words, _) = density.voxel_bits();
        a.uvec4([c.dims()[0], c.dims()[1], c.dims()[2], c.cube_res()]);
        a.f32s([c.sample_step(), MIN_TRANSMITTANCE]);
        a.u32s([2 * voxel_words as u32, d_index, d_data, d_voxels, d_proximity, d_lut]);
        a.vec4([diffuse.min().x, diffuse.min().y, diffuse.min().z, diffuse.cell()]);
        a.uvec4([diffuse.dims()[0], diffuse.dims()[1], diffuse.dims()[2], diffuse.cube_res()]);
        a.u32s([diffuse.channels(), c_index, c_data, density.blend_samples()]);
        a.vec4([psh.origin.x, psh.origin.y, psh.origin.z, psh.voxel]);
        a.u32s([
            psh.table.domain(),
            psh.table.table_side(),
            psh.table.offset_side(),
            p_offsets,
            p_keys,
            p_features,
            layer_gap.to_bits(),
            density.hit_rule().median_transmittance().to_bits(),
        ]);

        let kernel = GpuInolfKernel {
            bounds: density.bounds(),
            ctx,
            pipeline,
            density: density_buf,
            diffuse: diffuse_buf,
            psh: psh_buf,
            specular: specular_buf,
            params: a,
            bytes,
        };
        warm_up(&kernel)?;
        Ok(kernel)
    }

    /// Bytes of the asset resident on the device.
    pub fn device_bytes(&self) -> u64 {
        self.bytes
    }
}

impl RayKernel for GpuInolfKernel {
    fn kind(&self) -> &'static str {
        "inolf"
    }

    fn bounds(&self) -> Bounds {
        self.bounds
    }

    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        let tables = [&self.density, &self.diffuse, &self.psh, &self.specular];
        let (out, hit) = render(&self.ctx, &self.pipeline, camera, pixels, &self.params.0, &tables)?;
        let rays_hit = hit.iter().filter(|&&h| h > 0.5).count() as u64;
        Ok((out, KernelStats { rays: pixels.len() as u64, rays_hit, queries: rays_hit, hidden: 0 }))
    }
}
