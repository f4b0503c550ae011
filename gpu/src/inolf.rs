//! The i-NOLF kernel on a GPU: the asset's tables uploaded once, one compute dispatch per
//! batch of pixels (`inolf.wgsl`, one invocation per pixel).

use std::fmt;
use std::sync::Arc;

use wgpu::util::DeviceExt;

use crate::context::{GpuContext, GpuError};
use nephele_geometry::camera::Camera;
use nephele_kernels::inolf::cubes::{BLOCK, DensityCubes, MIN_TRANSMITTANCE, SparseCubes};
use nephele_kernels::inolf::encoding::PshEncoding;
use nephele_kernels::inolf::kernel::{DiffuseSource, HIT_OPACITY, HitSource, InolfKernel, RAY_NEAR};
use nephele_kernels::inolf::model::SPECULAR_OUT;
use nephele_kernels::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel, validate_pixels};
use nephele_nn::{Mlp, sh_coefficient_count};

/// Invocations per workgroup (the shader's `@workgroup_size`).
const WORKGROUP: u32 = 64;
/// Floats of the specular MLP that fit workgroup memory (WebGPU's 16 KiB minimum).
pub const MAX_SPECULAR_PARAMS: usize = 4096;
/// Floats written per pixel: r, g, b, opacity, depth, hit.
const OUT_FLOATS: usize = 6;

/// An i-NOLF asset resident on a GPU.
pub struct GpuInolfKernel {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    density: wgpu::Buffer,
    diffuse: wgpu::Buffer,
    psh: wgpu::Buffer,
    specular: wgpu::Buffer,
    /// Uniform words that do not depend on the camera (asset tables and their offsets).
    asset_params: AssetParams,
    bounds: Bounds,
    bytes: u64,
}

impl fmt::Debug for GpuInolfKernel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuInolfKernel").field("device", &self.ctx).field("bytes", &self.bytes).finish()
    }
}

/// A growing array of 32-bit words; floats stored as their bits.
#[derive(Default, Clone)]
struct Words(Vec<u32>);

impl Words {
    fn offset(&self) -> u32 {
        self.0.len() as u32
    }
    fn u32s(&mut self, v: impl IntoIterator<Item = u32>) -> u32 {
        let at = self.offset();
        self.0.extend(v);
        at
    }
    fn f32s(&mut self, v: impl IntoIterator<Item = f32>) -> u32 {
        self.u32s(v.into_iter().map(f32::to_bits))
    }
    /// Bytes four to a word, little end first.
    fn bytes(&mut self, v: &[u8]) -> u32 {
        self.u32s(v.chunks(4).map(|c| c.iter().rev().fold(0u32, |w, &b| (w << 8) | u32::from(b))))
    }
    fn vec4(&mut self, v: [f32; 4]) {
        self.f32s(v);
    }
    fn uvec4(&mut self, v: [u32; 4]) {
        self.u32s(v);
    }
}

/// The asset half of the shader's `Params` (layout in `inolf.wgsl`).
#[derive(Clone)]
struct AssetParams(Words);

fn density_tables(d: &DensityCubes) -> (Words, [u32; 5]) {
    let c = d.cubes();
    let mut w = Words::default();
    let index = w.u32s(c.index().iter().copied());
    let data = w.bytes(c.data());
    let (words, bits) = d.voxel_bits();
    // u64 words as pairs of u32, low half first: bit i of a cube lands in u32 i / 32.
    let voxels = w.u32s(bits.iter().flat_map(|&b| [b as u32, (b >> 32) as u32]));
    debug_assert_eq!(bits.len(), words * c.cube_count());
    let (_, flags) = d.block_flags();
    let blocks = w.u32s(flags.iter().map(|&f| u32::from(f)));
    let lut = w.f32s(d.decode_table().iter().copied());
    (w, [index, data, voxels, blocks, lut])
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
         const S_PARAMS: u32 = {}u;\nconst PSH_DIM: u32 = {}u;\nconst SH_DEGREE: u32 = {}u;\nconst SH_COUNT: u32 = {}u;\n{}",
        c.input,
        c.hidden.max(1),
        c.hidden_layers,
        c.output_activation.code(),
        mlp.num_params(),
        psh_dim,
        sh_degree,
        sh_coefficient_count(sh_degree),
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
        let (d_words, [d_index, d_data, d_voxels, d_blocks, d_lut]) = density_tables(density);
        let (c_words, [c_index, c_data]) = cube_tables(diffuse);
        let (p_words, [p_offsets, p_keys, p_features]) = psh_tables(psh);

        let device = &ctx.device;
        let max_binding = ctx.limits().max_storage_buffer_binding_size;
        let upload = |label: &str, words: &[u32]| -> Result<wgpu::Buffer, GpuError> {
            // A zero-sized binding is not allowed: pad empty tables with one word.
            let bytes: &[u8] = if words.is_empty() { &[0; 4] } else { bytemuck::cast_slice(words) };
            if bytes.len() as u64 > max_binding {
                return Err(GpuError::TooLarge(format!(
                    "{label}: {} bytes, the device binds at most {max_binding}",
                    bytes.len()
                )));
            }
            Ok(device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage: wgpu::BufferUsages::STORAGE,
            }))
        };
        let density_buf = upload("density cubes", &d_words.0)?;
        let diffuse_buf = upload("diffuse cubes", &c_words.0)?;
        let psh_buf = upload("psh", &p_words.0)?;
        let specular_buf = upload("specular mlp", &mlp.params().iter().map(|v| v.to_bits()).collect::<Vec<_>>())?;
        let bytes = 4 * (d_words.0.len() + c_words.0.len() + p_words.0.len() + mlp.num_params()) as u64;

        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("inolf.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shader_source(mlp, psh.dim() as u32, sh_degree).into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("inolf"),
            layout: None,
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()));
        }

        let c = density.cubes();
        let mut a = Words::default();
        a.vec4([c.min().x, c.min().y, c.min().z, c.cell()]);
        let (block_dims, _) = density.block_flags();
        let (voxel_words, _) = density.voxel_bits();
        a.uvec4([c.dims()[0], c.dims()[1], c.dims()[2], c.cube_res()]);
        a.uvec4([block_dims[0], block_dims[1], block_dims[2], 2 * voxel_words as u32]);
        a.f32s([c.sample_step(), MIN_TRANSMITTANCE]);
        a.u32s([BLOCK, d_index, d_data, d_voxels, d_blocks, d_lut]);
        a.vec4([diffuse.min().x, diffuse.min().y, diffuse.min().z, diffuse.cell()]);
        a.uvec4([diffuse.dims()[0], diffuse.dims()[1], diffuse.dims()[2], diffuse.cube_res()]);
        a.u32s([diffuse.channels(), c_index, c_data, 0]);
        a.vec4([psh.origin.x, psh.origin.y, psh.origin.z, psh.voxel]);
        a.u32s([
            psh.table.domain(),
            psh.table.table_side(),
            psh.table.offset_side(),
            p_offsets,
            p_keys,
            p_features,
            0,
            0,
        ]);

        Ok(GpuInolfKernel {
            bounds: density.bounds(),
            ctx,
            pipeline,
            density: density_buf,
            diffuse: diffuse_buf,
            psh: psh_buf,
            specular: specular_buf,
            asset_params: AssetParams(a),
            bytes,
        })
    }

    /// Bytes of the asset resident on the device.
    pub fn device_bytes(&self) -> u64 {
        self.bytes
    }

    /// The device it runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    fn params(&self, camera: &Camera, pixel_count: u32) -> Vec<u32> {
        let mut w = Words::default();
        let c2w = camera.camera_to_world();
        w.vec4(c2w.x_axis.to_array());
        w.vec4(c2w.y_axis.to_array());
        w.vec4(c2w.z_axis.to_array());
        w.vec4(c2w.w_axis.to_array());
        w.vec4(camera.world_to_camera().row(2).to_array());
        let (fx, fy, cx, cy) = camera.intrinsics();
        w.vec4([fx, fy, cx, cy]);
        w.u32s([camera.width(), pixel_count]);
        w.f32s([RAY_NEAR, HIT_OPACITY]);
        w.0.extend_from_slice(&self.asset_params.0.0);
        w.0
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
        validate_pixels(camera, pixels)?;
        let n = pixels.len();
        if n == 0 {
            return Ok((PixelResults::with_len(0), KernelStats::default()));
        }
        let failed = |e: GpuError| KernelError::Failed(e.to_string());
        let out_bytes = (n * OUT_FLOATS * 4) as u64;
        let limits = self.ctx.limits();
        if out_bytes > limits.max_storage_buffer_binding_size {
            return Err(failed(GpuError::TooLarge(format!("{n} pixels in one batch"))));
        }
        let device = &self.ctx.device;
        let params = self.params(camera, n as u32);
        let params_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("params"),
            contents: bytemuck::cast_slice(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let pixel_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("pixels"),
            contents: bytemuck::cast_slice(pixels),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let out_buf = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("results"),
            size: out_bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: out_bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("inolf"),
            layout: &self.pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: pixel_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: self.density.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: self.diffuse.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: self.psh.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: self.specular.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: out_buf.as_entire_binding() },
            ],
        });
        let groups = (n as u32).div_ceil(WORKGROUP);
        let max_x = limits.max_compute_workgroups_per_dimension.max(1);
        let (gx, gy) = (groups.min(max_x), groups.div_ceil(max_x));
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("inolf") });
        {
            let mut pass = encoder
                .begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("inolf"), timestamp_writes: None });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        encoder.copy_buffer_to_buffer(&out_buf, 0, &readback, 0, out_bytes);
        let submission = self.ctx.queue.submit([encoder.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        readback.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        device
            .poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: None })
            .map_err(|e| failed(GpuError::Readback(e.to_string())))?;
        rx.recv()
            .map_err(|e| failed(GpuError::Readback(e.to_string())))?
            .map_err(|e| failed(GpuError::Readback(e.to_string())))?;
        let view = readback.get_mapped_range(..).map_err(|e| failed(GpuError::Readback(e.to_string())))?;
        let values: &[f32] = bytemuck::cast_slice(&view);
        let mut out = PixelResults::with_len(n);
        let mut rays_hit = 0u64;
        for (i, v) in values.chunks_exact(OUT_FLOATS).enumerate() {
            out.color[i] = [v[0], v[1], v[2]];
            out.opacity[i] = v[3];
            out.depth[i] = v[4];
            rays_hit += u64::from(v[5] > 0.5);
        }
        drop(view);
        readback.unmap();
        Ok((out, KernelStats { rays: n as u64, rays_hit, queries: rays_hit }))
    }
}
