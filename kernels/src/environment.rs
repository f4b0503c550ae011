//! The environment as a farm kernel (issue 13, "served by the farm"): a room's view shaded by
//! the stereo neural global-illumination model ([`crate::gi`]), one eye or both eyes in one
//! pass, returned as opaque pixels with view depth so that the composer fuses the i-NOLF
//! objects into it by depth.
//!
//! Per batch the kernel
//! 1. renders the G-buffer a real-time rasteriser would give (first-hit position, normal,
//!    albedo, view depth) and the direct light (next-event estimation at the first hit plus
//!    the MIS-weighted light its one bounce finds: the path tracer's direct-light-only mode,
//!    which casts no shadow rays at the bounce's hit,
//!    [`GiServeSettings::samples_per_pixel`] samples) for the environment's scene, named in
//!    the model's header, at [`GiServeSettings::scale`] of the view's resolution and sides
//!    rounded up to what the U-Net's levels need (the window reaches past the image: the same
//!    pinhole, real pixels, no padding artefacts);
//! 2. runs the U-Net: the stereo model over both eyes in one pass when the batch is a pair
//!    and a `<asset>.stereo.ngi` sits beside the single-eye model, the single-eye model per
//!    eye otherwise;
//! 3. upsamples to the view (colour bilinear, depth nearest: a depth interpolated across a
//!    silhouette would float between the two surfaces) and returns the requested pixels.
//!
//! The whole window is shaded whatever pixels the batch asks for: a convolutional network
//! needs its neighbourhood, so the scheduler sends an environment's views whole
//! (`ObjectInfo::full_frame`). Pixels that see the sky through a window get
//! [`SKY_DEPTH`], so that every object is fused in front of them.
//!
//! Where objects stand in the room, the master sends their solid matter with the batch
//! ([`RayKernel::render_pixels_behind`]): G-buffer samples whose first hit lies behind it are
//! not lit (no shadow rays, no bounce), since the fused object covers them with full
//! opacity, and the network computes only what the pixels left visible read
//! ([`nephele_nn::UNet::forward_masked`]: a pixel all four of whose shaded taps are covered
//! comes back black, at the room's depth, behind the object; every other pixel gets exactly
//! the value of the whole pass). The same solid matter casts the objects' shadows: shadow
//! rays to the room's lights that it stops bring no direct light, so the network, which
//! turns direct light into global illumination, darkens the room under and behind them.
//!
//! The GPU twin of the network takes the same mask ([`GiDevices`]).
//!
//! Not yet: the G-buffer's camera rays are still traced behind the objects (the network's
//! halo reads them, and a ray's hit decides whether it is covered); the objects' light on
//! the room (they absorb what reaches them; no bounce off them), shadows of the glass shell
//! (no solid grid), the ball's motion (the room is rendered at one moment,
//! [`GiServeSettings::time_s`]).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use nephele_geometry::camera::Camera;
use nephele_nn::{PixelMask, UNetWorkspace};
use nephele_pathtracer::{Background, RenderOptions, RenderOutput, Renderer, scenes};

use crate::gi::{GBufferPixel, GiModel, GiModelError, UNetDevice};
use crate::kernel::{Bounds, KernelError, KernelStats, PixelResults, RayKernel, SolidGrid, validate_pixels};

/// View depth given to pixels that see no geometry (the sky through a window), metres: behind
/// anything an object can be, and inside the compact wire form's half-float range.
pub const SKY_DEPTH: f32 = 1.0e4;

/// Margin of rows shaded around a band of a view, in pooling steps of the U-Net (16 rows of
/// the shaded image for the default three levels): most of the network's neighbourhood, so
/// that bands shaded on different workers meet without a visible seam (`nephele bench gi`
/// measures the difference to the whole view).
pub const HALO_STEPS: u32 = 4;

/// How the environment is served.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GiServeSettings {
    /// Samples per pixel of the G-buffer and direct light. The models were trained on direct
    /// light at the dataset's samples (128 in BENCHMARKS.md): fewer is noisier input.
    pub samples_per_pixel: u32,
    /// Resolution of the shaded image relative to the view, `(0, 1]`: global illumination is
    /// smooth, so half resolution (a quarter of the work) loses little but texture edges.
    pub scale: f32,
    /// Seconds into the scene's animation (the room's rolling ball) the room is rendered at.
    pub time_s: f32,
    /// Run the network over the pixels the objects cover too (every pixel of the window, as
    /// before issue 13's mask): for measuring what the mask saves.
    pub shade_covered: bool,
}

impl GiServeSettings {
    /// How the G-buffer and direct light are path traced: the direct-light-only mode (the
    /// camera ray, shadow rays at its hit, one bounce that finds lights and sky for MIS) at
    /// [`Self::samples_per_pixel`], noise from `seed`. The trainer renders its served-like
    /// inputs with the same options (`nephele train gi --input-spp`).
    pub fn g_buffer_options(&self, seed: u64) -> RenderOptions {
        RenderOptions {
            samples_per_pixel: self.samples_per_pixel,
            max_bounces: 1,
            seed,
            background: Background::Environment,
            direct_only: true,
        }
    }
}

/// Two samples at half resolution: `nephele bench gi` (BENCHMARKS.md, "environment served by
/// the farm") measured 0.54 us per view pixel for a stereo pair at 256x256 per eye on this
/// 2-core VM, -0.2 dB against 4 samples and 1.5x faster; 1 sample loses another 0.3 dB.
impl Default for GiServeSettings {
    fn default() -> GiServeSettings {
        GiServeSettings { samples_per_pixel: 2, scale: 0.5, time_s: 0.0, shade_covered: false }
    }
}

/// A room shaded by a GI model, behind [`RayKernel`].
#[derive(Debug)]
pub struct GiKernel {
    single: GiModel,
    stereo: Option<GiModel>,
    renderer: Renderer,
    settings: GiServeSettings,
    bounds: Bounds,
    /// Workspaces of finished passes, reused (their buffers are the size of a view).
    workspaces: Mutex<Vec<UNetWorkspace>>,
    /// The networks' twins on a GPU (`--device`), `None`: the CPU runs them.
    devices: Option<GiDevices>,
    /// Multiply-adds the CPU networks ran, and what whole passes would have run.
    network_macs: [AtomicU64; 2],
}

/// The single-eye and (where there is a stereo model) stereo networks resident on a device.
#[derive(Debug, Clone)]
pub struct GiDevices {
    pub single: Arc<dyn UNetDevice>,
    pub stereo: Option<Arc<dyn UNetDevice>>,
}

/// Where a `.ngi` asset's stereo twin lives: `room-day.ngi` -> `room-day.stereo.ngi`.
pub fn stereo_path(single: &Path) -> std::path::PathBuf {
    single.with_extension("stereo.ngi")
}

impl GiKernel {
    /// A kernel from a single-eye model and, optionally, its stereo student. The scene is the
    /// built-in one the models' header names.
    pub fn new(single: GiModel, stereo: Option<GiModel>, settings: GiServeSettings) -> Result<GiKernel, KernelError> {
        let failed = |why: String| KernelError::Failed(why);
        if single.eyes() != 1 {
            return Err(failed(format!("the environment's model must be single-eye, not {}-eye", single.eyes())));
        }
        if !(settings.scale > 0.0 && settings.scale <= 1.0) || settings.samples_per_pixel == 0 {
            return Err(failed(format!("environment settings {settings:?}: scale in (0, 1], at least one sample")));
        }
        let scene_name = single.header.scene.clone().ok_or_else(|| {
            failed("the GI model names no scene (train it with this build's `nephele train gi`)".into())
        })?;
        if let Some(s) = &stereo {
            if s.eyes() != 2 {
                return Err(failed(format!("the stereo model has {} eyes", s.eyes())));
            }
            if s.header.scene.as_deref() != Some(scene_name.as_str()) || s.header.features != single.header.features {
                return Err(failed("the stereo model was trained for another scene than the single-eye model".into()));
            }
        }
        let scene = scenes::builtin_at(&scene_name, settings.time_s)
            .map_err(|e| failed(format!("scene {scene_name:?}: {e}")))?;
        let renderer = Renderer::new(scene.scene).map_err(|e| failed(e.to_string()))?;
        let (min, max) = renderer.scene().bounds().ok_or_else(|| failed("the environment has no geometry".into()))?;
        Ok(GiKernel {
            single,
            stereo,
            renderer,
            settings,
            bounds: Bounds { min, max },
            workspaces: Mutex::new(Vec::new()),
            devices: None,
            network_macs: [AtomicU64::new(0), AtomicU64::new(0)],
        })
    }

    /// The models this kernel shades with (the stereo one where there is one), for a device
    /// to take copies of.
    pub fn models(&self) -> (&GiModel, Option<&GiModel>) {
        (&self.single, self.stereo.as_ref())
    }

    /// The same kernel with its networks run on a device (built from [`Self::models`]); the
    /// G-buffer stays on the CPU.
    pub fn with_devices(mut self, devices: GiDevices) -> Result<GiKernel, KernelError> {
        if devices.stereo.is_some() != self.stereo.is_some() {
            return Err(KernelError::Failed("a stereo device network without a stereo model, or the reverse".into()));
        }
        self.devices = Some(devices);
        Ok(self)
    }

    /// Where the networks run: a device's label, or "cpu".
    pub fn network_device(&self) -> String {
        self.devices.as_ref().map_or_else(|| "cpu".into(), |d| d.single.label())
    }

    /// Opens `path` (a single-eye `.ngi`) and its stereo twin when there is one.
    pub fn load(path: &Path, settings: GiServeSettings) -> Result<GiKernel, KernelError> {
        let failed = |e: GiModelError| KernelError::Failed(e.to_string());
        let single = GiModel::load(path).map_err(failed)?;
        let twin = stereo_path(path);
        let stereo = if twin.is_file() { Some(GiModel::load(&twin).map_err(failed)?) } else { None };
        GiKernel::new(single, stereo, settings)
    }

    /// Multiply-adds the networks ran on the CPU so far, and what whole passes over the same
    /// windows would have run (the difference: pixels the objects cover, not shaded).
    pub fn network_macs(&self) -> (u64, u64) {
        (self.network_macs[0].load(Ordering::Relaxed), self.network_macs[1].load(Ordering::Relaxed))
    }

    /// Chooses the instruction set of the networks' CPU convolutions (`--simd`).
    pub fn set_simd(&mut self, simd: nephele_nn::SimdMode) {
        self.single.network.set_simd(simd);
        if let Some(stereo) = &mut self.stereo {
            stereo.network.set_simd(simd);
        }
    }

    /// Whether a pair of views is shaded in one stereo pass.
    pub fn has_stereo(&self) -> bool {
        self.stereo.is_some()
    }

    /// The camera of the shaded image: the view at the scale, sides rounded up to the U-Net's
    /// step (the same pinhole, reaching past the view's bottom-right edge).
    fn shading_camera(&self, view: &Camera) -> Result<Camera, KernelError> {
        let step = 1u32 << (self.single.network.config().levels() - 1);
        let s = self.settings.scale;
        let side = |n: u32| (((n as f32 * s).ceil() as u32).max(1)).div_ceil(step) * step;
        let (w, h) = (side(view.width()), side(view.height()));
        let (fx, fy, cx, cy) = view.intrinsics();
        Camera::from_intrinsics(w, h, fx * s, fy * s, cx * s, cy * s, view.camera_to_world())
            .map_err(|e| KernelError::Failed(e.to_string()))
    }

    /// The G-buffer and direct light the kernel traces for the whole of `view` (at the shading
    /// scale), behind `occluders`: what a pass costs before the network (`nephele bench
    /// covered`).
    pub fn trace_g_buffer(&self, view: &Camera, occluders: &[SolidGrid]) -> Result<RenderOutput, KernelError> {
        let camera = self.shading_camera(view)?;
        Ok(self.g_buffer(&camera, occluders)?.0)
    }

    /// The G-buffer and direct light of `camera`'s image; samples behind `occluders` keep
    /// their G-buffer and get no light ([`Renderer::render_behind`]).
    fn g_buffer(
        &self,
        camera: &Camera,
        occluders: &[SolidGrid],
    ) -> Result<(RenderOutput, Vec<GBufferPixel>), KernelError> {
        let options = self.settings.g_buffer_options(0);
        let out = self
            .renderer
            .render_behind(camera, &options, occluders, &|_| {})
            .map_err(|e| KernelError::Failed(e.to_string()))?;
        if !occluders.is_empty() {
            tracing::trace!(
                hidden = out.stats.hidden_samples,
                light_blocked = out.stats.light_blocked,
                "G-buffer behind and in the shadow of the objects"
            );
        }
        let pixels = g_buffer_pixels(&out);
        Ok((out, pixels))
    }

    /// The rows of the shaded image to shade for view rows `[y0, y1)`: a margin of
    /// [`HALO_STEPS`] pooling steps of rows on each side (the network's neighbourhood), the
    /// start aligned to a pooling step (so that the band's pooled grids are the whole view's),
    /// the height a multiple of it. Returns `(first row, rows)`.
    fn window(&self, shaded: &Camera, y0: u32, y1: u32) -> (u32, u32) {
        let step = 1u32 << (self.single.network.config().levels() - 1);
        let halo = HALO_STEPS * step;
        let s = self.settings.scale;
        let first = ((y0 as f32 * s).floor() as u32).saturating_sub(halo) / step * step;
        let last = (((y1 as f32 * s).ceil() as u32) + halo).min(shaded.height());
        let rows = (last.saturating_sub(first)).div_ceil(step) * step;
        (first, rows.clamp(step, shaded.height() - first))
    }

    /// Shades the rows asked of one view, or of two for the stereo model (a band of rows with
    /// a margin, [`Self::window`]), and returns each view's `requested` pixels. The lighting
    /// of what `occluders` hide is skipped (the network still sees those pixels' G-buffer).
    fn shade(
        &self,
        views: &[(&Camera, &[u32])],
        occluders: &[SolidGrid],
    ) -> Result<(Vec<PixelResults>, KernelStats), KernelError> {
        for (camera, pixels) in views {
            validate_pixels(camera, pixels)?;
        }
        let rows = views.iter().flat_map(|(c, pixels)| pixels.iter().map(move |p| p / c.width()));
        let Some((y0, y1)) = rows
            .fold(None, |span: Option<(u32, u32)>, y| Some(span.map_or((y, y + 1), |(a, b)| (a.min(y), b.max(y + 1)))))
        else {
            return Ok((views.iter().map(|_| PixelResults::with_len(0)).collect(), KernelStats::default()));
        };
        let whole: Vec<Camera> = views.iter().map(|(c, _)| self.shading_camera(c)).collect::<Result<_, _>>()?;
        let (first, count) = self.window(&whole[0], y0, y1);
        let cameras: Vec<Camera> = whole
            .iter()
            .map(|c| c.crop(0, first, c.width(), count).map_err(|e| KernelError::Failed(e.to_string())))
            .collect::<Result<_, _>>()?;
        let buffers: Vec<(RenderOutput, Vec<GBufferPixel>)> =
            cameras.iter().map(|c| self.g_buffer(c, occluders)).collect::<Result<_, _>>()?;
        let mut ws = self.workspaces.lock().ok().and_then(|mut pool| pool.pop()).unwrap_or_default();
        let (w, h) = (cameras[0].width() as usize, cameras[0].height() as usize);
        let failed = |e: GiModelError| KernelError::Failed(e.to_string());
        let mut images: Vec<Vec<[f32; 3]>> = Vec::with_capacity(views.len());
        let mut non_finite = 0;
        let mut passes = 0u64;
        let stereo_device = self.devices.as_ref().and_then(|d| d.stereo.as_deref());
        let single_device = self.devices.as_ref().map(|d| d.single.as_ref());
        let covered: Vec<&[bool]> = buffers.iter().map(|(out, _)| out.covered.as_slice()).collect();
        let needed =
            if self.settings.shade_covered { None } else { needed_pixels(views, &cameras[0], first, &covered) };
        let needed = needed.as_ref();
        let count = |ws: &UNetWorkspace| {
            let (done, whole) = ws.last_macs();
            self.network_macs[0].fetch_add(done, Ordering::Relaxed);
            self.network_macs[1].fetch_add(whole, Ordering::Relaxed);
        };
        match (&self.stereo, buffers.as_slice()) {
            (Some(stereo), [left, right]) => {
                let eyes = [left.1.as_slice(), right.1.as_slice()];
                let shaded = match stereo_device {
                    Some(device) => stereo.shade_on(device, w, h, &eyes, needed),
                    None => stereo.shade_where(w, h, &eyes, needed, &mut ws).inspect(|_| count(&ws)),
                }
                .map_err(failed)?;
                non_finite += shaded.non_finite_inputs;
                images.extend(shaded.eyes);
                passes += 1;
            }
            _ => {
                for (_, pixels) in &buffers {
                    let shaded = match single_device {
                        Some(device) => self.single.shade_on(device, w, h, &[pixels], needed),
                        None => self.single.shade_where(w, h, &[pixels], needed, &mut ws).inspect(|_| count(&ws)),
                    }
                    .map_err(failed)?;
                    non_finite += shaded.non_finite_inputs;
                    images.extend(shaded.eyes);
                    passes += 1;
                }
            }
        }
        if let Ok(mut pool) = self.workspaces.lock() {
            pool.push(ws);
        }
        if non_finite > 0 {
            tracing::warn!(non_finite, "non-finite G-buffer values were zeroed before shading");
        }
        let mut results = Vec::with_capacity(views.len());
        let mut rays = 0;
        for (((view, pixels), camera), (image, (out, _))) in views.iter().zip(&cameras).zip(images.iter().zip(&buffers))
        {
            results.push(upsample(view, pixels, camera, first, image, &out.depth));
            rays += u64::from(camera.width()) * u64::from(camera.height());
        }
        let stats = KernelStats {
            rays: rays * u64::from(self.settings.samples_per_pixel),
            rays_hit: rays,
            queries: passes,
            hidden: buffers.iter().map(|(out, _)| out.stats.hidden_samples).sum(),
        };
        Ok((results, stats))
    }
}

/// The G-buffer pixels of a render (the same fields the training data stores, so that served
/// and trained inputs agree).
pub fn g_buffer_pixels(out: &RenderOutput) -> Vec<GBufferPixel> {
    (0..out.depth.len())
        .map(|i| GBufferPixel {
            position: out.position[i].to_array(),
            normal: out.normal[i].to_array(),
            albedo: out.albedo[i].to_array(),
            depth: out.depth[i],
            direct: out.direct[i].to_array(),
        })
        .collect()
}

/// Where a view's pixel reads the image shaded for it: the four bilinear taps (indices into
/// the shaded image: top left, top right, bottom left, bottom right), the fractions between
/// them, and the nearest shaded pixel (one of the four).
struct Taps {
    corners: [usize; 4],
    fx: f32,
    fy: f32,
    nearest: usize,
}

impl Taps {
    /// Pixel `p` of `view` in the image shaded through `camera` (the view scaled, same
    /// pinhole, its rows from `first_row` of the scaled view on).
    fn of(view: &Camera, camera: &Camera, first_row: u32, p: u32) -> Taps {
        let (sw, sh) = (camera.width() as usize, camera.height() as usize);
        let sx = camera.intrinsics().0 / view.intrinsics().0;
        let sy = camera.intrinsics().1 / view.intrinsics().1;
        let (x, y) = ((p % view.width()) as f32, (p / view.width()) as f32);
        // Centre of the view's pixel in the shaded image's pixel coordinates.
        let (u, v) = ((x + 0.5) * sx - 0.5, (y + 0.5) * sy - 0.5 - first_row as f32);
        let (x0, y0) = (u.floor().clamp(0.0, (sw - 1) as f32) as usize, v.floor().clamp(0.0, (sh - 1) as f32) as usize);
        let (x1, y1) = ((x0 + 1).min(sw - 1), (y0 + 1).min(sh - 1));
        let (fx, fy) = ((u - x0 as f32).clamp(0.0, 1.0), (v - y0 as f32).clamp(0.0, 1.0));
        let nx = (u.round().clamp(0.0, (sw - 1) as f32)) as usize;
        let ny = (v.round().clamp(0.0, (sh - 1) as f32)) as usize;
        Taps { corners: [y0 * sw + x0, y0 * sw + x1, y1 * sw + x0, y1 * sw + x1], fx, fy, nearest: ny * sw + nx }
    }
}

/// The shaded pixels the network must give for `views`' requested pixels, where some shaded
/// pixels are `covered` (per view, every G-buffer sample hidden behind the objects): the taps
/// of each requested pixel not all of whose taps are covered. `None` (shade everything) when
/// nothing is covered.
fn needed_pixels(
    views: &[(&Camera, &[u32])],
    camera: &Camera,
    first_row: u32,
    covered: &[&[bool]],
) -> Option<PixelMask> {
    if !covered.iter().any(|c| c.contains(&true)) {
        return None;
    }
    let (sw, sh) = (camera.width() as usize, camera.height() as usize);
    // A view pixel's taps are the 2x2 block (clamped at the borders) from its top-left tap,
    // which depends on its column and its row alone: tables, no division per pixel.
    let block = |q: usize| {
        let (x, y) = (q % sw, q / sw);
        let (x1, y1) = ((x + 1).min(sw - 1), (y + 1).min(sh - 1));
        [q, y * sw + x1, y1 * sw + x, y1 * sw + x1]
    };
    let mut seen_from = vec![false; sw * sh];
    for ((view, pixels), covered) in views.iter().zip(covered) {
        let open: Vec<bool> = (0..sw * sh).map(|q| block(q).iter().any(|&i| !covered[i])).collect();
        let width = view.width();
        let columns: Vec<usize> = (0..width).map(|x| Taps::of(view, camera, first_row, x).corners[0]).collect();
        let rows: Vec<usize> =
            (0..view.height()).map(|y| Taps::of(view, camera, first_row, y * width).corners[0] - columns[0]).collect();
        let (mut row, mut row_start) = (0, 0);
        for &p in pixels.iter() {
            if p < row_start || p - row_start >= width {
                row = p / width;
                row_start = row * width;
            }
            let q = rows[row as usize] + columns[(p - row_start) as usize];
            seen_from[q] |= open[q];
        }
    }
    let mut needed = vec![false; sw * sh];
    for q in (0..sw * sh).filter(|&q| seen_from[q]) {
        for i in block(q) {
            needed[i] = true;
        }
    }
    PixelMask::from_flags(sw, sh, needed).ok()
}

/// `pixels` of `view` from an image shaded through `camera` (the view scaled, same pinhole,
/// its rows from `first_row` of the scaled view on): colour bilinear, depth of the nearest
/// shaded pixel ([`SKY_DEPTH`] where it saw no geometry), opacity 1.
fn upsample(
    view: &Camera,
    pixels: &[u32],
    camera: &Camera,
    first_row: u32,
    image: &[[f32; 3]],
    depth: &[f32],
) -> PixelResults {
    let mut out = PixelResults::with_len(pixels.len());
    for (k, &p) in pixels.iter().enumerate() {
        let Taps { corners, fx, fy, nearest } = Taps::of(view, camera, first_row, p);
        let [a, b, c, d] = corners.map(|i| image[i]);
        for ch in 0..3 {
            let top = a[ch] + (b[ch] - a[ch]) * fx;
            let bottom = c[ch] + (d[ch] - c[ch]) * fx;
            out.color[k][ch] = top + (bottom - top) * fy;
        }
        let z = depth[nearest];
        // The shaded camera's depth is the view's (same pose, z along the same axis).
        out.depth[k] = if z.is_finite() && z > 0.0 { z } else { SKY_DEPTH };
        out.opacity[k] = 1.0;
    }
    out
}

impl RayKernel for GiKernel {
    fn kind(&self) -> &'static str {
        "gi"
    }

    fn bounds(&self) -> Bounds {
        self.bounds
    }

    fn render_pixels(&self, camera: &Camera, pixels: &[u32]) -> Result<(PixelResults, KernelStats), KernelError> {
        self.render_pixels_behind(camera, pixels, &[])
    }

    fn render_pixels_behind(
        &self,
        camera: &Camera,
        pixels: &[u32],
        occluders: &[SolidGrid],
    ) -> Result<(PixelResults, KernelStats), KernelError> {
        let (mut results, stats) = self.shade(&[(camera, pixels)], occluders)?;
        Ok((results.remove(0), stats))
    }

    fn shades_whole_views(&self) -> bool {
        true
    }

    fn render_pair(
        &self,
        left: (&Camera, &[u32]),
        right: (&Camera, &[u32]),
    ) -> Option<Result<([PixelResults; 2], KernelStats), KernelError>> {
        self.render_pair_behind(left, right, &[])
    }

    fn render_pair_behind(
        &self,
        left: (&Camera, &[u32]),
        right: (&Camera, &[u32]),
        occluders: &[SolidGrid],
    ) -> Option<Result<([PixelResults; 2], KernelStats), KernelError>> {
        if !self.has_stereo() || (left.0.width(), left.0.height()) != (right.0.width(), right.0.height()) {
            return None;
        }
        Some(self.shade(&[left, right], occluders).map(|(mut results, stats)| {
            let right = results.remove(1);
            ([results.remove(0), right], stats)
        }))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use nephele_geometry::camera::stereo_pair;
    use nephele_nn::{UNet, UNetConfig};

    use super::*;
    use crate::gi::{GI_INPUTS, GI_OUTPUTS, GiFeatures};

    fn model(eyes: usize, scene: &str) -> GiModel {
        let config = UNetConfig { inputs: GI_INPUTS, eyes, outputs: GI_OUTPUTS, channels: vec![4, 8] };
        let features = GiFeatures { centre: [0.0, 0.0, 1.4], scale: 2.5 };
        let mut m = GiModel::new(UNet::new(config, 7).expect("net"), features, serde_json::Value::Null).expect("model");
        m.header.scene = Some(scene.into());
        m
    }

    fn view(width: u32, height: u32) -> Camera {
        Camera::look_at(width, height, 1.2, Vec3::new(0.0, -1.2, 1.5), Vec3::new(0.5, 1.0, 1.0), Vec3::Z)
            .expect("camera")
    }

    #[test]
    fn a_view_is_opaque_with_depth_and_a_subset_matches_the_whole() {
        let settings = GiServeSettings { samples_per_pixel: 2, scale: 1.0, time_s: 0.0, shade_covered: false };
        let kernel = GiKernel::new(model(1, "room-day"), None, settings).expect("kernel");
        let camera = view(16, 12);
        let all: Vec<u32> = (0..16 * 12).collect();
        let (full, stats) = kernel.render_pixels(&camera, &all).expect("render");
        assert_eq!(stats.queries, 1, "one network pass");
        assert!(full.opacity.iter().all(|&a| a == 1.0));
        assert!(full.depth.iter().all(|&d| d > 0.0 && d.is_finite()));
        assert!(full.color.iter().flatten().all(|c| c.is_finite() && *c >= 0.0));
        // Inside the room: the nearest wall is within its 5 x 4 x 2.8 m.
        assert!(full.depth.iter().any(|&d| d < 6.0));
        let subset = [0u32, 17, 100, 191];
        let (part, _) = kernel.render_pixels(&camera, &subset).expect("subset");
        for (k, &p) in subset.iter().enumerate() {
            assert_eq!(part.color[k], full.color[p as usize]);
            assert_eq!(part.depth[k], full.depth[p as usize]);
        }
        assert!(kernel.render_pixels(&camera, &[16 * 12]).is_err(), "outside the view");
    }

    #[test]
    fn what_an_object_hides_is_not_lit_and_the_rest_is_untouched() {
        let settings = GiServeSettings { samples_per_pixel: 2, scale: 1.0, time_s: 0.0, shade_covered: false };
        let kernel = GiKernel::new(model(1, "room-day"), None, settings).expect("kernel");
        let camera = view(16, 12);
        let all: Vec<u32> = (0..16 * 12).collect();
        let (plain, plain_stats) = kernel.render_pixels(&camera, &all).expect("render");
        assert_eq!(plain_stats.hidden, 0);
        // A solid block behind the camera hides nothing: the same image.
        let eye = camera.camera_to_world().transform_point3(Vec3::ZERO);
        let forward = camera.camera_to_world().transform_vector3(-Vec3::Z);
        let block = |at: Vec3| SolidGrid::new(at - Vec3::splat(0.1), at + Vec3::splat(0.1), [1, 1, 1], &[true]);
        let behind = block(eye - forward).expect("grid");
        let (same, stats) = kernel.render_pixels_behind(&camera, &all, &[behind]).expect("render");
        assert_eq!((same, stats.hidden), (plain.clone(), 0));
        // One in front: some samples are hidden, the view stays opaque, and only pixels with a
        // hidden sample may change depth (a hidden sample draws fewer random numbers, so the
        // pixel's next sample takes another path).
        let front = block(eye + forward * 0.5).expect("grid");
        let (hid, stats) = kernel.render_pixels_behind(&camera, &all, &[front]).expect("render");
        assert!(stats.hidden > 0 && stats.hidden < stats.rays, "{stats:?}");
        assert_eq!(hid.opacity, plain.opacity);
        let moved = hid.depth.iter().zip(&plain.depth).filter(|(a, b)| a != b).count() as u64;
        assert!(moved <= stats.hidden, "{moved} pixels changed depth, {} samples hidden", stats.hidden);
        assert_ne!(hid.color, plain.color);
    }

    #[test]
    fn pixels_the_objects_cover_are_not_shaded_and_the_others_are_exact() {
        // At scale 1 a pixel's taps are itself and its right and lower neighbours, at zero
        // weight: its colour is its shaded pixel's.
        let settings = GiServeSettings { samples_per_pixel: 2, scale: 1.0, time_s: 0.0, shade_covered: false };
        let kernel = GiKernel::new(model(1, "room-day"), None, settings).expect("kernel");
        let camera = view(16, 12);
        let all: Vec<u32> = (0..16 * 12).collect();
        let eye = camera.camera_to_world().transform_point3(Vec3::ZERO);
        let forward = camera.camera_to_world().transform_vector3(-Vec3::Z);
        let at = eye + forward * 0.5;
        let front = SolidGrid::new(at - Vec3::splat(0.1), at + Vec3::splat(0.1), [1, 1, 1], &[true]).expect("grid");
        assert_eq!(kernel.network_macs(), (0, 0));
        let (hid, _) = kernel.render_pixels_behind(&camera, &all, std::slice::from_ref(&front)).expect("render");
        let (done, whole) = kernel.network_macs();
        // The network over the same G-buffer, every pixel.
        let g = kernel.trace_g_buffer(&camera, std::slice::from_ref(&front)).expect("g-buffer");
        let reference = kernel
            .single
            .shade(16, 12, &[&g_buffer_pixels(&g)], &mut UNetWorkspace::new())
            .expect("shade")
            .eyes
            .remove(0);
        let mut black = 0;
        for (p, want) in reference.iter().enumerate() {
            let (x, y) = (p % 16, p / 16);
            let taps = [(x, y), ((x + 1).min(15), y), (x, (y + 1).min(11)), ((x + 1).min(15), (y + 1).min(11))];
            if taps.iter().all(|&(x, y)| g.covered[y * 16 + x]) {
                // Covered: black, or exact where a seen neighbour needed its shaded pixel.
                if hid.color[p] == [0.0; 3] {
                    // Not shaded (the whole pass gives it light).
                    black += usize::from(*want != [0.0; 3]);
                } else {
                    assert_eq!(hid.color[p], *want, "pixel {p} is covered");
                }
            } else {
                assert_eq!(hid.color[p], *want, "pixel {p} is seen");
            }
            assert_eq!(hid.depth[p], if g.depth[p] > 0.0 { g.depth[p] } else { SKY_DEPTH });
        }
        assert!(black > 0, "no covered pixel was left unshaded");
        assert!(done < whole && whole > 0, "the network skipped nothing: {done} of {whole}");
        // Nothing covered: the whole pass.
        kernel.render_pixels(&camera, &all).expect("render");
        let (after, after_whole) = kernel.network_macs();
        assert_eq!(after - done, after_whole - whole);
    }

    #[test]
    fn views_of_any_size_are_shaded_at_the_scale() {
        let kernel = GiKernel::new(
            model(1, "room-night"),
            None,
            GiServeSettings { samples_per_pixel: 1, scale: 0.5, time_s: 0.0, shade_covered: false },
        )
        .expect("kernel");
        // 22 x 10 at half scale: 11 x 5, rounded up to even sides for the two-level U-Net.
        let camera = view(22, 10);
        let shaded = kernel.shading_camera(&camera).expect("camera");
        assert_eq!((shaded.width(), shaded.height()), (12, 6));
        let all: Vec<u32> = (0..22 * 10).collect();
        let (out, stats) = kernel.render_pixels(&camera, &all).expect("render");
        assert_eq!(out.len(), 220);
        assert_eq!(stats.rays_hit, 12 * 6);
        assert!(out.opacity.iter().all(|&a| a == 1.0) && out.depth.iter().all(|&d| d > 0.0));
    }

    /// A band of a view is shaded over its rows plus the margin, aligned to the pooling step,
    /// inside the scaled view; the band's pixels come back valid.
    #[test]
    fn a_band_of_rows_is_shaded_with_an_aligned_margin() {
        let settings = GiServeSettings { samples_per_pixel: 1, scale: 0.5, time_s: 0.0, shade_covered: false };
        let kernel = GiKernel::new(model(1, "room-day"), None, settings).expect("kernel");
        let view = view(64, 96);
        let shaded = kernel.shading_camera(&view).expect("camera");
        assert_eq!((shaded.width(), shaded.height()), (32, 48));
        // Two levels: step 2, margin 8 shaded rows.
        for (y0, y1) in [(0, 48), (48, 96), (30, 31), (0, 96)] {
            let (first, rows) = kernel.window(&shaded, y0, y1);
            assert_eq!(first % 2, 0);
            assert_eq!(rows % 2, 0);
            assert!(first + rows <= 48);
            let (need0, need1) = (y0 / 2, y1.div_ceil(2));
            assert!(
                first <= need0.saturating_sub(8) && first + rows >= (need1 + 8).min(48),
                "{y0}..{y1}: {first}+{rows}"
            );
        }
        let band: Vec<u32> = (48 * 64..96 * 64).collect();
        let (out, stats) = kernel.render_pixels(&view, &band).expect("band");
        assert_eq!(out.len(), band.len());
        assert_eq!(stats.rays_hit, 32 * (24 + 8), "the band's 24 shaded rows and the 8 above it");
        assert!(out.opacity.iter().all(|&a| a == 1.0) && out.depth.iter().all(|&d| d > 0.0));
        let (none, _) = kernel.render_pixels(&view, &[]).expect("nothing asked");
        assert!(none.is_empty());
    }

    #[test]
    fn upsampling_interpolates_colour_and_gives_the_sky_the_far_depth() {
        let fine = view(8, 8);
        let kernel = GiKernel::new(
            model(1, "room-day"),
            None,
            GiServeSettings { samples_per_pixel: 1, scale: 0.5, time_s: 0.0, shade_covered: false },
        )
        .expect("k");
        let coarse = kernel.shading_camera(&fine).expect("coarse");
        assert_eq!((coarse.width(), coarse.height()), (4, 4));
        // A horizontal ramp 0, 1, 2, 3 per coarse column; the sky (depth 0) in the top row.
        let image: Vec<[f32; 3]> = (0..16).map(|i| [(i % 4) as f32; 3]).collect();
        let depth: Vec<f32> = (0..16).map(|i| if i < 4 { 0.0 } else { 2.0 }).collect();
        let all: Vec<u32> = (0..64).collect();
        let out = upsample(&fine, &all, &coarse, 0, &image, &depth);
        // Fine pixel x sits at coarse (x + 0.5) / 2 - 0.5: x = 1 -> 0.25, x = 2 -> 0.75.
        assert!((out.color[8 + 1][0] - 0.25).abs() < 1e-5 && (out.color[8 + 2][0] - 0.75).abs() < 1e-5);
        assert_eq!(out.color[8][0], 0.0, "clamped at the edge");
        assert_eq!(out.depth[0], SKY_DEPTH);
        assert_eq!(out.depth[7 * 8], 2.0);
    }

    #[test]
    fn a_pair_is_one_stereo_pass_only_with_a_stereo_model_of_the_same_scene() {
        let settings = GiServeSettings { samples_per_pixel: 1, scale: 1.0, time_s: 0.0, shade_covered: false };
        let eyes = stereo_pair(&view(16, 12), 0.064).expect("eyes");
        let all: Vec<u32> = (0..16 * 12).collect();
        let mono = GiKernel::new(model(1, "room-day"), None, settings).expect("mono");
        assert!(mono.render_pair((&eyes[0], &all), (&eyes[1], &all)).is_none());
        let stereo = GiKernel::new(model(1, "room-day"), Some(model(2, "room-day")), settings).expect("stereo");
        let ([left, right], stats) =
            stereo.render_pair((&eyes[0], &all), (&eyes[1], &all[..10])).expect("a pair pass").expect("rendered");
        assert_eq!(stats.queries, 1, "both eyes in one network pass");
        assert_eq!((left.len(), right.len()), (192, 10));
        assert!(right.opacity.iter().all(|&a| a == 1.0));
        // The left head is not the single-eye model's output: a different network.
        let (single_left, _) = stereo.render_pixels(&eyes[0], &all).expect("single");
        assert_ne!(single_left.color, left.color);
        assert!(GiKernel::new(model(1, "room-day"), Some(model(2, "room-night")), settings).is_err());
        assert!(GiKernel::new(model(2, "room-day"), None, settings).is_err());
        assert!(GiKernel::new(model(1, "no-such-scene"), None, settings).is_err());
        let mut unnamed = model(1, "room-day");
        unnamed.header.scene = None;
        assert!(GiKernel::new(unnamed, None, settings).expect_err("no scene").to_string().contains("names no scene"));
    }

    #[test]
    fn the_scene_name_survives_the_file() {
        let m = model(1, "room-night");
        assert_eq!(GiModel::from_bytes(&m.to_bytes()).expect("decode").header.scene.as_deref(), Some("room-night"));
    }
}
