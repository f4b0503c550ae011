//! What every GPU kernel does per batch: the camera as uniform words, one dispatch of one
//! invocation per pixel, the results read back.

use crate::context::{GpuContext, GpuError};
use nephele_geometry::camera::Camera;
use nephele_kernels::kernel::{KernelError, PixelResults, RayKernel, validate_pixels};
use wgpu::util::DeviceExt;

/// Invocations per workgroup (`WORKGROUP` in `common.wgsl`).
pub(crate) const WORKGROUP: u32 = 64;

/// The shader prelude every kernel's source starts with.
pub(crate) const COMMON_WGSL: &str = include_str!("common.wgsl");

/// A growing array of 32-bit words (uniforms and tables); floats stored as their bits.
#[derive(Debug, Default, Clone)]
pub(crate) struct Words(pub Vec<u32>);

impl Words {
    pub fn offset(&self) -> u32 {
        self.0.len() as u32
    }
    pub fn u32s(&mut self, v: impl IntoIterator<Item = u32>) -> u32 {
        let at = self.offset();
        self.0.extend(v);
        at
    }
    pub fn f32s(&mut self, v: impl IntoIterator<Item = f32>) -> u32 {
        self.u32s(v.into_iter().map(f32::to_bits))
    }
    /// Bytes four to a word, little end first.
    pub fn bytes(&mut self, v: &[u8]) -> u32 {
        self.u32s(v.chunks(4).map(|c| c.iter().rev().fold(0u32, |w, &b| (w << 8) | u32::from(b))))
    }
    /// u64 words as pairs of u32, low half first: bit `i` lands in u32 `i / 32`.
    pub fn bits(&mut self, v: &[u64]) -> u32 {
        self.u32s(v.iter().flat_map(|&b| [b as u32, (b >> 32) as u32]))
    }
    pub fn vec4(&mut self, v: [f32; 4]) {
        self.f32s(v);
    }
    pub fn uvec4(&mut self, v: [u32; 4]) {
        self.u32s(v);
    }
}

/// The `Camera` struct of `common.wgsl`: 28 words (112 bytes, 16-byte aligned).
fn camera_words(camera: &Camera, pixel_count: u32) -> Words {
    let mut w = Words::default();
    let c2w = camera.camera_to_world();
    w.vec4(c2w.x_axis.to_array());
    w.vec4(c2w.y_axis.to_array());
    w.vec4(c2w.z_axis.to_array());
    w.vec4(c2w.w_axis.to_array());
    w.vec4(camera.world_to_camera().row(2).to_array());
    let (fx, fy, cx, cy) = camera.intrinsics();
    w.vec4([fx, fy, cx, cy]);
    w.u32s([camera.width(), pixel_count, 0, 0]);
    w
}

/// A read-only storage buffer holding `words` (one padding word if empty: bindings cannot
/// be empty), refused if larger than the device binds.
pub(crate) fn upload(ctx: &GpuContext, label: &str, words: &[u32]) -> Result<wgpu::Buffer, GpuError> {
    let bytes: &[u8] = if words.is_empty() { &[0; 4] } else { bytemuck::cast_slice(words) };
    let max = ctx.limits().max_storage_buffer_binding_size;
    if bytes.len() as u64 > max {
        return Err(GpuError::TooLarge(format!("{label}: {} bytes, the device binds at most {max}", bytes.len())));
    }
    Ok(ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytes,
        usage: wgpu::BufferUsages::STORAGE,
    }))
}

/// Compiles a kernel's WGSL (after the prelude) into a compute pipeline with entry `main`;
/// shader errors come back as [`GpuError::Validation`].
pub(crate) fn pipeline(ctx: &GpuContext, label: &str, source: String) -> Result<wgpu::ComputePipeline, GpuError> {
    let device = &ctx.device;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(format!("{COMMON_WGSL}\n{source}").into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });
    match pollster::block_on(scope.pop()) {
        Some(e) => Err(GpuError::Validation(e.to_string())),
        None => Ok(pipeline),
    }
}

/// One dispatch over `pixels`: binding 0 the uniform `params`, 1 the pixel list, then
/// `tables` in order, then the output of `floats_per_pixel` floats per pixel, which is read
/// back and returned.
fn run(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    params: &[u32],
    pixels: &[u32],
    tables: &[&wgpu::Buffer],
    floats_per_pixel: usize,
) -> Result<Vec<f32>, GpuError> {
    let n = pixels.len();
    let out_bytes = (n * floats_per_pixel * 4) as u64;
    let limits = ctx.limits();
    if out_bytes > limits.max_storage_buffer_binding_size || out_bytes == 0 {
        return Err(GpuError::TooLarge(format!("{n} pixels in one batch")));
    }
    let device = &ctx.device;
    let params_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("params"),
        contents: bytemuck::cast_slice(params),
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
    let mut entries = vec![
        wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
        wgpu::BindGroupEntry { binding: 1, resource: pixel_buf.as_entire_binding() },
    ];
    for (i, t) in tables.iter().enumerate() {
        entries.push(wgpu::BindGroupEntry { binding: 2 + i as u32, resource: t.as_entire_binding() });
    }
    entries.push(wgpu::BindGroupEntry { binding: 2 + tables.len() as u32, resource: out_buf.as_entire_binding() });
    let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    });
    let (gx, gy) = workgroup_grid(ctx, n as u64);
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
    {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: None, timestamp_writes: None });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
    }
    encoder.copy_buffer_to_buffer(&out_buf, 0, &readback, 0, out_bytes);
    let submission = ctx.queue.submit([encoder.finish()]);
    let mut values = read_back(ctx, submission, &[&readback])?;
    Ok(values.pop().unwrap_or_default())
}

/// Workgroups for `invocations` of `WORKGROUP` each, as an `x, y` grid within the device's
/// per-dimension limit (shaders take `id.x + id.y * x * WORKGROUP`).
pub(crate) fn workgroup_grid(ctx: &GpuContext, invocations: u64) -> (u32, u32) {
    let groups = invocations.div_ceil(u64::from(WORKGROUP)) as u32;
    let max_x = ctx.limits().max_compute_workgroups_per_dimension.max(1);
    (groups.min(max_x), groups.div_ceil(max_x))
}

/// Waits for `submission` and returns the floats of each mapped-readable buffer, in order.
pub(crate) fn read_back(
    ctx: &GpuContext,
    submission: wgpu::SubmissionIndex,
    readbacks: &[&wgpu::Buffer],
) -> Result<Vec<Vec<f32>>, GpuError> {
    let failed = |e: &dyn std::fmt::Display| GpuError::Readback(e.to_string());
    let (tx, rx) = std::sync::mpsc::channel();
    for readback in readbacks {
        let tx = tx.clone();
        readback.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
    }
    ctx.device
        .poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: None })
        .map_err(|e| failed(&e))?;
    for _ in readbacks {
        rx.recv().map_err(|e| failed(&e))?.map_err(|e| failed(&e))?;
    }
    let mut all = Vec::with_capacity(readbacks.len());
    for readback in readbacks {
        let values = {
            let view = readback.get_mapped_range(..).map_err(|e| failed(&e))?;
            bytemuck::cast_slice::<u8, f32>(&view).to_vec()
        };
        readback.unmap();
        all.push(values);
    }
    Ok(all)
}

/// Renders one pixel so that the driver compiles the pipeline now (most compile at the
/// first dispatch) and not inside the first batch's deadline.
pub(crate) fn warm_up(kernel: &dyn RayKernel) -> Result<(), GpuError> {
    let b = kernel.bounds();
    let camera = Camera::look_at(
        1,
        1,
        1.0,
        b.center() + glam::Vec3::new(0.3, -1.0, 0.6) * b.size().length().max(1e-3),
        b.center(),
        glam::Vec3::Z,
    )
    .map_err(|e| GpuError::Validation(format!("warm-up camera: {e}")))?;
    kernel.render_pixels(&camera, &[0]).map(|_| ()).map_err(|e| GpuError::Validation(format!("warm-up dispatch: {e}")))
}

/// Floats each kernel writes per pixel: r, g, b, opacity, depth, then one kernel-specific
/// value (a hit flag, a sample count).
const OUT_FLOATS: usize = 6;

/// One batch of any kernel: checks the pixels, runs the dispatch with the camera followed by
/// the kernel's constant uniform words (`kernel_params`), and splits the read-back floats
/// into per-pixel results and the kernel-specific column.
pub(crate) fn render(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    camera: &Camera,
    pixels: &[u32],
    kernel_params: &[u32],
    tables: &[&wgpu::Buffer],
) -> Result<(PixelResults, Vec<f32>), KernelError> {
    validate_pixels(camera, pixels)?;
    if pixels.is_empty() {
        return Ok((PixelResults::with_len(0), Vec::new()));
    }
    let mut params = camera_words(camera, pixels.len() as u32);
    params.0.extend_from_slice(kernel_params);
    let values =
        run(ctx, pipeline, &params.0, pixels, tables, OUT_FLOATS).map_err(|e| KernelError::Failed(e.to_string()))?;
    let mut out = PixelResults::with_len(pixels.len());
    let mut extra = Vec::with_capacity(pixels.len());
    for (i, v) in values.chunks_exact(OUT_FLOATS).enumerate() {
        out.color[i] = [v[0], v[1], v[2]];
        out.opacity[i] = v[3];
        out.depth[i] = v[4];
        extra.push(v[5]);
    }
    Ok((out, extra))
}
