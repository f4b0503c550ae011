//! Datasets for the stereo neural global-illumination model (Zhang and Simo-Serra; the design's
//! "Stereo GI" kernel): per view, what a real-time rasteriser would have, and the path-traced
//! global illumination the network learns to produce from it.
//!
//! Per frame (one eye at one moment of the scene's animation), linear float OpenEXR files:
//!
//! | file | channels | what |
//! | --- | --- | --- |
//! | `NAME_position.exr` | 3 | world position of the first hit (0 where none) |
//! | `NAME_normal.exr` | 3 | shading normal of the first hit, towards the camera |
//! | `NAME_albedo.exr` | 3 | diffuse albedo of the first hit |
//! | `NAME_depth.exr` | 1 (stored as RGB) | view-space depth (0 where none) |
//! | `NAME_direct.exr` | 4 | direct light (emission seen + light straight from the lights, the sun or the sky, with shadow rays), premultiplied, alpha |
//! | `NAME_gi.exr` | 4 | full path-traced global illumination, premultiplied, alpha: the target |
//!
//! and `gi.json`, the manifest: the scene, the render settings and every frame's camera,
//! animation time and, for stereo frames, its pair, eye and interpupillary distance.
//!
//! Three sets: `single` frames (`s_N`: one eye, random standpoint and time) train the
//! single-eye model; stereo pairs (left and right eye of one head at one moment, IPD drawn
//! from 55-70 mm, parallel eyes as WebXR gives them) either evaluate (`p_N_left/right`: their
//! path-traced GI is the ground truth of both eyes) or train the stereo student (`t_N_...`:
//! only their G-buffers are read; the student learns from the single-eye teacher's output
//! and the coherence loss, never from stereo ground truth).
//!
//! Resumable: the manifest is written first with every planned frame (deterministic from the
//! seed); each frame's files are written under temporary names and renamed, the G-buffer
//! before the target, so a frame whose `gi` file exists is complete. Running again with the
//! same settings skips complete frames; other settings are refused.

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};
use nephele_geometry::SplitMix64;
use nephele_geometry::camera::{Camera, CameraError};
use nephele_imaging::image::{FloatImage, ImageError};
use nephele_kernels::environment::GiServeSettings;
use nephele_pathtracer::integrator::{Aov, Background};
use nephele_pathtracer::scenes::{self, SceneLookupError};
use nephele_pathtracer::{RenderError, RenderOptions, Renderer};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::synth::view_poses;

/// Smallest and largest interpupillary distance drawn for stereo pairs, metres (the adult
/// range the stereo GI paper trains over).
pub const IPD_RANGE_M: (f32, f32) = (0.055, 0.070);

/// Version of the manifest's layout.
pub const MANIFEST_VERSION: u32 = 1;

/// The G-buffer and target files of a frame, in the order they are written (the target last).
pub const BUFFERS: [&str; 6] = ["position", "normal", "albedo", "depth", "direct", "gi"];

/// What to render.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GiSpec {
    /// `room-day` or `room-night` (or another built-in interior).
    pub scene: String,
    /// Single-eye training frames.
    pub single: usize,
    /// Stereo pairs for evaluation (their path-traced GI is the ground truth of both eyes).
    pub stereo_pairs: usize,
    /// Stereo pairs for training the stereo student: only their G-buffers are used (the
    /// targets come from the single-eye teacher), never their path-traced GI.
    #[serde(default)]
    pub train_pairs: usize,
    pub width: u32,
    pub height: u32,
    /// Vertical field of view, radians.
    pub fov_y: f32,
    /// Samples per pixel of the path-traced target (the G-buffer and direct light come from
    /// the same samples).
    pub spp: u32,
    pub bounces: u32,
    pub seed: u64,
}

impl GiSpec {
    pub fn validate(&self) -> Result<(), GiDataError> {
        let scene = scenes::builtin(&self.scene)?;
        if !matches!(scene.framing, scenes::Framing::Interior { .. }) {
            return Err(GiDataError::Spec(format!(
                "{} is not an interior (the GI model serves environments)",
                self.scene
            )));
        }
        let frames = self.single + 2 * (self.stereo_pairs + self.train_pairs);
        if frames == 0 || frames > 100_000 {
            return Err(GiDataError::Spec("between 1 and 100000 frames".into()));
        }
        if self.width < 8 || self.height < 8 || self.width > 4096 || self.height > 4096 {
            return Err(GiDataError::Spec(format!("image size {}x{} (8 to 4096 per side)", self.width, self.height)));
        }
        if !(self.fov_y > 0.05 && self.fov_y < 3.0) {
            return Err(GiDataError::Spec(format!("vertical field of view {} rad", self.fov_y)));
        }
        RenderOptions { samples_per_pixel: self.spp, max_bounces: self.bounces, ..RenderOptions::default() }
            .validate()?;
        Ok(())
    }

    /// Every frame this spec renders, deterministic from the seed: the single-eye frames,
    /// then the stereo pairs (left, right).
    pub fn plan(&self) -> Result<Vec<GiFrame>, GiDataError> {
        let scene = scenes::builtin(&self.scene)?;
        let pairs = self.train_pairs + self.stereo_pairs;
        let heads = view_poses(&scene, self.single + pairs, true, self.seed);
        let mut rng = SplitMix64::new(self.seed ^ 0x005E_ED0F_71E5);
        let mut frames = Vec::with_capacity(self.single + 2 * pairs);
        for (i, head) in heads[..self.single].iter().enumerate() {
            let time = rng.next_f32() * scenes::BALL_PERIOD_S;
            frames.push(GiFrame { name: format!("s_{i}"), camera_to_world: head.to_cols_array(), time, stereo: None });
        }
        for (index, head) in heads[self.single..].iter().enumerate() {
            let time = rng.next_f32() * scenes::BALL_PERIOD_S;
            let ipd = IPD_RANGE_M.0 + rng.next_f32() * (IPD_RANGE_M.1 - IPD_RANGE_M.0);
            // Evaluation pairs first (their names do not depend on the training pairs).
            let (pair, train) =
                if index < self.stereo_pairs { (index, false) } else { (index - self.stereo_pairs, true) };
            for (eye, side) in [(Eye::Left, -0.5), (Eye::Right, 0.5)] {
                // Parallel eyes: the head's orientation, shifted along its own right axis.
                let camera_to_world = *head * Mat4::from_translation(Vec3::new(side * ipd, 0.0, 0.0));
                frames.push(GiFrame {
                    name: format!("{}_{pair}_{}", if train { "t" } else { "p" }, eye.name()),
                    camera_to_world: camera_to_world.to_cols_array(),
                    time,
                    stereo: Some(StereoEye { pair, eye, ipd, train }),
                });
            }
        }
        Ok(frames)
    }

    /// The camera of `frame`.
    pub fn camera(&self, frame: &GiFrame) -> Result<Camera, CameraError> {
        Camera::from_fov_y(self.width, self.height, self.fov_y, Mat4::from_cols_array(&frame.camera_to_world))
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Eye {
    Left,
    Right,
}

impl Eye {
    pub fn name(self) -> &'static str {
        match self {
            Eye::Left => "left",
            Eye::Right => "right",
        }
    }
}

/// The stereo side of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StereoEye {
    pub pair: usize,
    pub eye: Eye,
    /// Interpupillary distance of the pair, metres.
    pub ipd: f32,
    /// A pair for training the stereo student (its ground truth unused), not for evaluation.
    #[serde(default)]
    pub train: bool,
}

/// One frame of the manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GiFrame {
    /// File stem of the frame's buffers.
    pub name: String,
    /// Camera-to-world, column-major (OpenGL camera).
    pub camera_to_world: [f32; 16],
    /// Seconds into the scene's animation.
    pub time: f32,
    /// `None` for single-eye training frames.
    pub stereo: Option<StereoEye>,
}

/// `gi.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GiManifest {
    pub version: u32,
    pub spec: GiSpec,
    pub frames: Vec<GiFrame>,
}

#[derive(Debug, Error)]
pub enum GiDataError {
    #[error("GI dataset settings: {0}")]
    Spec(String),
    #[error(transparent)]
    Scene(#[from] SceneLookupError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {reason}")]
    Manifest { path: PathBuf, reason: String },
    #[error(
        "{path} holds a GI dataset of other settings ({theirs}); render into another folder or pass the same settings to resume"
    )]
    OtherSettings { path: PathBuf, theirs: String },
}

/// What [`render_gi_dataset`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GiRenderReport {
    pub rendered: usize,
    /// Complete frames found from an earlier run.
    pub skipped: usize,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> GiDataError + '_ {
    move |source| GiDataError::Io { path: path.to_path_buf(), source }
}

/// Reads `DIR/gi.json`.
pub fn read_manifest(dir: &Path) -> Result<GiManifest, GiDataError> {
    let path = dir.join("gi.json");
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    let manifest: GiManifest =
        serde_json::from_str(&text).map_err(|e| GiDataError::Manifest { path: path.clone(), reason: e.to_string() })?;
    if manifest.version != MANIFEST_VERSION {
        return Err(GiDataError::Manifest {
            path,
            reason: format!("version {} (this build reads {MANIFEST_VERSION})", manifest.version),
        });
    }
    Ok(manifest)
}

/// Whether every buffer of `frame` is in `dir` (the target is written last).
pub fn frame_complete(dir: &Path, frame: &GiFrame) -> bool {
    BUFFERS.iter().all(|b| dir.join(format!("{}_{b}.exr", frame.name)).is_file())
}

/// Renders `spec` into `out` (created if absent), resuming an earlier run of the same
/// settings. `on_rows` is called with rows as they finish, out of `frames * height`
/// (skipped frames count at once).
pub fn render_gi_dataset(
    spec: &GiSpec,
    out: &Path,
    on_rows: &(dyn Fn(u32) + Sync),
) -> Result<GiRenderReport, GiDataError> {
    spec.validate()?;
    std::fs::create_dir_all(out).map_err(io(out))?;
    let manifest = GiManifest { version: MANIFEST_VERSION, spec: spec.clone(), frames: spec.plan()? };
    let manifest_path = out.join("gi.json");
    if manifest_path.exists() {
        let earlier = read_manifest(out)?;
        if earlier != manifest {
            let theirs = serde_json::to_string(&earlier.spec).unwrap_or_default();
            return Err(GiDataError::OtherSettings { path: manifest_path, theirs });
        }
    } else {
        let text = serde_json::to_string_pretty(&manifest)
            .map_err(|e| GiDataError::Manifest { path: manifest_path.clone(), reason: e.to_string() })?;
        write_atomically(&manifest_path, |tmp| std::fs::write(tmp, &text).map_err(io(tmp)))?;
    }

    let mut report = GiRenderReport::default();
    for (index, frame) in manifest.frames.iter().enumerate() {
        if frame_complete(out, frame) {
            report.skipped += 1;
            on_rows(spec.height);
            continue;
        }
        let scene = scenes::builtin_at(&spec.scene, frame.time)?;
        let options = RenderOptions {
            samples_per_pixel: spec.spp,
            max_bounces: spec.bounces,
            // Every frame its own noise.
            seed: spec.seed.wrapping_mul(0x9E37_79B9).wrapping_add(index as u64),
            background: Background::Environment,
            direct_only: false,
        };
        let renderer = Renderer::new(scene.scene)?;
        let image = renderer.render(&spec.camera(frame)?, &options, on_rows)?;
        for (buffer, aov) in
            BUFFERS.iter().zip([Aov::Position, Aov::Normal, Aov::Albedo, Aov::Depth, Aov::Direct, Aov::Color])
        {
            let path = out.join(format!("{}_{buffer}.exr", frame.name));
            let data = image.to_float(aov);
            write_atomically(&path, |tmp| data.save_exr(tmp).map_err(GiDataError::from))?;
        }
        report.rendered += 1;
    }
    Ok(report)
}

/// Writes through `write` to a temporary sibling (same extension, so format detection by
/// name still works), then renames it over `path`.
fn write_atomically(path: &Path, write: impl FnOnce(&Path) -> Result<(), GiDataError>) -> Result<(), GiDataError> {
    let file_name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let tmp = path.with_file_name(format!(".part-{}-{file_name}", std::process::id()));
    write(&tmp)?;
    std::fs::rename(&tmp, path).map_err(io(path))
}

/// One frame's buffers, loaded: planar per-pixel values in row-major order.
#[derive(Debug, Clone)]
pub struct GiBuffers {
    pub width: u32,
    pub height: u32,
    pub position: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
    pub albedo: Vec<[f32; 3]>,
    pub depth: Vec<f32>,
    /// Direct light, premultiplied RGB (alpha is 1 in an interior).
    pub direct: Vec<[f32; 3]>,
    /// The target.
    pub gi: Vec<[f32; 3]>,
    /// Values that were NaN or infinite in the files and were set to 0.
    pub non_finite: usize,
}

/// Loads the buffers of `frame` from `dir`; NaN and infinite values become 0 and are counted.
pub fn load_frame(dir: &Path, frame: &GiFrame) -> Result<GiBuffers, GiDataError> {
    let mut non_finite = 0usize;
    let mut load = |buffer: &str, channels: usize| -> Result<(u32, u32, Vec<f32>), GiDataError> {
        let image = FloatImage::load_exr(dir.join(format!("{}_{buffer}.exr", frame.name)))?;
        let (w, h, c) = (image.width(), image.height(), image.channels());
        let mut out = Vec::with_capacity(w as usize * h as usize * channels);
        for px in image.data().chunks_exact(c) {
            for &v in &px[..channels.min(c)] {
                out.push(if v.is_finite() {
                    v
                } else {
                    non_finite += 1;
                    0.0
                });
            }
        }
        Ok((w, h, out))
    };
    let triples = |v: Vec<f32>| v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect::<Vec<_>>();
    let (width, height, position) = load("position", 3)?;
    let mut rest = Vec::new();
    for (buffer, channels) in [("normal", 3), ("albedo", 3), ("depth", 1), ("direct", 3), ("gi", 3)] {
        let (w, h, data) = load(buffer, channels)?;
        if (w, h) != (width, height) {
            return Err(GiDataError::Manifest {
                path: dir.join(format!("{}_{buffer}.exr", frame.name)),
                reason: format!("{w}x{h}, but the position buffer is {width}x{height}"),
            });
        }
        rest.push(data);
    }
    let [normal, albedo, depth, direct, gi] = <[Vec<f32>; 5]>::try_from(rest)
        .map_err(|_| GiDataError::Manifest { path: dir.to_path_buf(), reason: "buffer count".into() })?;
    Ok(GiBuffers {
        width,
        height,
        position: triples(position),
        normal: triples(normal),
        albedo: triples(albedo),
        depth,
        direct: triples(direct),
        gi: triples(gi),
        non_finite,
    })
}

/// `frame`'s buffers with the network's inputs (position, normal, albedo, depth, direct
/// light) replaced by what the farm's environment kernel gives at `spp` samples: the path
/// tracer's direct-light-only mode, one bounce for MIS, as `GiKernel` renders its G-buffer.
/// The target (`gi`) stays the dataset's converged one, so a model trained on these learns to
/// take the served, noisy inputs to it (the dataset's direct light shares the target's
/// hundreds of samples; the farm's has two).
pub fn with_served_inputs(spec: &GiSpec, frame: &GiFrame, spp: u32, b: &GiBuffers) -> Result<GiBuffers, GiDataError> {
    let scene = scenes::builtin_at(&spec.scene, frame.time)?;
    // Noise of its own per frame, unlike the dataset's (its name picks the stream).
    let seed = frame.name.bytes().fold(spec.seed ^ 0x5E_4E_ED, |h, c| h.wrapping_mul(0x100_0000_01B3) ^ u64::from(c));
    let served = GiServeSettings { samples_per_pixel: spp, ..GiServeSettings::default() };
    let out = Renderer::new(scene.scene)?.render(&spec.camera(frame)?, &served.g_buffer_options(seed), &|_| {})?;
    if (out.width, out.height) != (b.width, b.height) {
        return Err(GiDataError::Manifest {
            path: PathBuf::from(&frame.name),
            reason: format!("served inputs {}x{} against the frame's {}x{}", out.width, out.height, b.width, b.height),
        });
    }
    let finite = |v: Vec3| if v.is_finite() { v.to_array() } else { [0.0; 3] };
    Ok(GiBuffers {
        width: b.width,
        height: b.height,
        position: out.position.iter().map(|&v| finite(v)).collect(),
        normal: out.normal.iter().map(|&v| finite(v)).collect(),
        albedo: out.albedo.iter().map(|&v| finite(v)).collect(),
        depth: out.depth.iter().map(|&d| if d.is_finite() { d } else { 0.0 }).collect(),
        direct: out.direct.iter().map(|&v| finite(v)).collect(),
        gi: b.gi.clone(),
        non_finite: b.non_finite,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny(scene: &str) -> GiSpec {
        GiSpec {
            scene: scene.into(),
            single: 2,
            stereo_pairs: 1,
            train_pairs: 0,
            width: 12,
            height: 10,
            fov_y: 1.0,
            spp: 2,
            bounces: 3,
            seed: 5,
        }
    }

    #[test]
    fn the_plan_is_deterministic_and_pairs_are_parallel_eyes_apart_by_the_ipd() {
        let spec = GiSpec { single: 5, stereo_pairs: 20, train_pairs: 3, ..tiny("room-day") };
        let plan = spec.plan().expect("plan");
        assert_eq!(plan, spec.plan().expect("plan"));
        assert_ne!(plan, GiSpec { seed: 6, ..spec.clone() }.plan().expect("plan"));
        assert_eq!(plan.len(), 51);
        assert_eq!(plan.iter().filter(|f| f.stereo.is_some_and(|s| s.train)).count(), 6);
        assert!(
            plan[45..].iter().all(|f| f.name.starts_with("t_")) && plan[5..45].iter().all(|f| f.name.starts_with("p_"))
        );
        assert!(plan[..5].iter().all(|f| f.stereo.is_none() && f.name.starts_with("s_")));
        for pair in plan[5..].chunks(2) {
            let (l, r) = (&pair[0], &pair[1]);
            let (sl, sr) = (l.stereo.expect("stereo"), r.stereo.expect("stereo"));
            assert_eq!((sl.eye, sr.eye, sl.pair, sl.ipd, l.time), (Eye::Left, Eye::Right, sr.pair, sr.ipd, r.time));
            assert!((IPD_RANGE_M.0..=IPD_RANGE_M.1).contains(&sl.ipd));
            let (ml, mr) = (Mat4::from_cols_array(&l.camera_to_world), Mat4::from_cols_array(&r.camera_to_world));
            // Same orientation; the right eye sits ipd metres along the left eye's +X.
            assert!((ml.x_axis - mr.x_axis).length() < 1e-6 && (ml.z_axis - mr.z_axis).length() < 1e-6);
            let offset = (mr.w_axis - ml.w_axis).truncate();
            assert!((offset - ml.x_axis.truncate() * sl.ipd).length() < 1e-5, "{offset}");
        }
        let times: Vec<f32> = plan.iter().map(|f| f.time).collect();
        assert!(times.iter().all(|t| (0.0..scenes::BALL_PERIOD_S).contains(t)));
        assert!(times.windows(2).any(|w| w[0] != w[1]), "the scene moves between frames");
    }

    #[test]
    fn served_inputs_replace_the_inputs_and_keep_the_target() {
        let dir = tempfile::tempdir().expect("tempdir");
        let spec = GiSpec { spp: 16, ..tiny("room-day") };
        render_gi_dataset(&spec, dir.path(), &|_| {}).expect("render");
        let frame = &read_manifest(dir.path()).expect("manifest").frames[0];
        let b = load_frame(dir.path(), frame).expect("load");
        let served = with_served_inputs(&spec, frame, 2, &b).expect("served");
        assert_eq!(served.gi, b.gi, "the target stays");
        assert_eq!((served.width, served.height, served.direct.len()), (b.width, b.height, b.direct.len()));
        // Other samples of the same view (pixels of these 12x10 views span edges): most depths
        // within the pixel's spread, the mean depth alike; other, noisier direct light. The
        // same call gives the same inputs.
        assert_ne!(served.direct, b.direct);
        let agree = served.depth.iter().zip(&b.depth).filter(|(a, b)| (*a - *b).abs() < 0.05 * b.max(0.1)).count();
        assert!(agree * 2 > served.depth.len(), "{agree} of {} depths agree", served.depth.len());
        let mean = |d: &[f32]| d.iter().sum::<f32>() / d.len() as f32;
        assert!((mean(&served.depth) - mean(&b.depth)).abs() < 0.1 * mean(&b.depth));
        assert!(served.direct.iter().flatten().chain(&served.depth).all(|v| v.is_finite() && *v >= 0.0));
        let again = with_served_inputs(&spec, frame, 2, &b).expect("served");
        assert_eq!((again.direct, again.depth), (served.direct, served.depth));
    }

    #[test]
    fn bad_settings_are_refused_clearly() {
        let e = tiny("diffuse").validate().expect_err("an object, not an interior");
        assert!(e.to_string().contains("not an interior"), "{e}");
        assert!(GiSpec { single: 0, stereo_pairs: 0, ..tiny("room-day") }.validate().is_err());
        assert!(GiSpec { width: 2, ..tiny("room-day") }.validate().is_err());
        assert!(GiSpec { fov_y: f32::NAN, ..tiny("room-day") }.validate().is_err());
        assert!(GiSpec { spp: 0, ..tiny("room-day") }.validate().is_err());
        assert!(tiny("nowhere").validate().is_err());
    }

    #[test]
    fn a_dataset_renders_resumes_and_loads_back() {
        let dir = tempfile::tempdir().expect("tempdir");
        let spec = tiny("room-night");
        let rows = std::sync::atomic::AtomicU32::new(0);
        let count = |r: u32| {
            rows.fetch_add(r, std::sync::atomic::Ordering::Relaxed);
        };
        let report = render_gi_dataset(&spec, dir.path(), &count).expect("render");
        assert_eq!(report, GiRenderReport { rendered: 4, skipped: 0 });
        assert_eq!(rows.load(std::sync::atomic::Ordering::Relaxed), 4 * spec.height);
        let manifest = read_manifest(dir.path()).expect("manifest");
        assert_eq!((manifest.spec.clone(), manifest.frames.len()), (spec.clone(), 4));

        // An interrupted run: one frame lost its target; only that one renders again.
        std::fs::remove_file(dir.path().join("p_0_right_gi.exr")).expect("remove");
        let again = render_gi_dataset(&spec, dir.path(), &|_| {}).expect("resume");
        assert_eq!(again, GiRenderReport { rendered: 1, skipped: 3 });
        let other = GiSpec { spp: 3, ..spec.clone() };
        let e = render_gi_dataset(&other, dir.path(), &|_| {}).expect_err("other settings");
        assert!(matches!(e, GiDataError::OtherSettings { .. }), "{e}");

        for frame in &manifest.frames {
            let b = load_frame(dir.path(), frame).expect("load");
            assert_eq!((b.width, b.height, b.non_finite), (12, 10, 0));
            let n = 120;
            assert!(b.position.len() == n && b.normal.len() == n && b.depth.len() == n && b.gi.len() == n);
            // Inside the room most pixels hit something (the rest look out of a
            // window at the sky): unit normals where the depth is positive, zeros elsewhere.
            assert!(b.depth.iter().filter(|&&d| d > 0.0).count() * 4 > n * 3, "{}", frame.name);
            for (d, n) in b.depth.iter().zip(&b.normal) {
                let length = Vec3::from(*n).length();
                assert!(if *d > 0.0 { (length - 1.0).abs() < 1e-3 } else { length == 0.0 }, "{d} {length}");
            }
            // Global illumination holds at least the direct light (same samples), and the
            // lamps light the room.
            let sum = |v: &[[f32; 3]]| v.iter().map(|c| c.iter().sum::<f32>()).sum::<f32>();
            assert!(sum(&b.gi) >= sum(&b.direct) - 1e-3 && sum(&b.gi) > 0.0);
        }
    }

    #[test]
    fn non_finite_values_in_the_files_are_zeroed_and_counted() {
        let dir = tempfile::tempdir().expect("tempdir");
        let spec = GiSpec { single: 1, stereo_pairs: 0, ..tiny("room-day") };
        render_gi_dataset(&spec, dir.path(), &|_| {}).expect("render");
        let frame = &read_manifest(dir.path()).expect("manifest").frames[0];
        let path = dir.path().join(format!("{}_albedo.exr", frame.name));
        let mut albedo = FloatImage::load_exr(&path).expect("load");
        albedo.data_mut()[0] = f32::NAN;
        albedo.data_mut()[4] = f32::INFINITY;
        albedo.save_exr(&path).expect("save");
        let b = load_frame(dir.path(), frame).expect("load");
        assert_eq!(b.non_finite, 2);
        assert!(b.albedo.iter().flatten().all(|v| v.is_finite()));
    }
}
