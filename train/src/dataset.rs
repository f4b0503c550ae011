//! Datasets in the NeRF-synthetic ("Blender") format.
//!
//! A dataset directory holds one `transforms_{split}.json` per split (`train`, `val`, `test`)
//! and the images it names:
//!
//! ```json
//! {
//!     "camera_angle_x": 0.6911112070083618,
//!     "frames": [
//!         {
//!             "file_path": "./train/r_0",
//!             "rotation": 0.012566370614359171,
//!             "transform_matrix": [[r00, r01, r02, tx], [r10, r11, r12, ty],
//!                                  [r20, r21, r22, tz], [0, 0, 0, 1]]
//!         }
//!     ]
//! }
//! ```
//!
//! `file_path` is relative to the directory and usually lacks the `.png` extension.
//! `transform_matrix` is the camera-to-world matrix written as **rows** (OpenGL camera: looks
//! down -Z, +Y up; world +Z up); glam's [`Mat4`] is column-major, so the translation is
//! `mat.w_axis`. `camera_angle_x` is the horizontal field of view in radians, so the
//! intrinsics follow from the image width and scale with it when images are downscaled.
//! Nephele adds an optional per-frame `"depth_file_path"` naming an OpenEXR depth map
//! (view-space z distance, 0 for misses).
//!
//! The module also samples camera poses on a sphere around a target, for rendering datasets.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use glam::{DVec3, Mat4, Vec3, Vec4};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use nephele_geometry::SplitMix64;
use nephele_geometry::camera::look_at_camera_to_world;
use nephele_imaging::image::{FloatImage, ImageError, RgbaImage};

/// Tolerance on the last row of a `transform_matrix` being `(0, 0, 0, 1)`.
const LAST_ROW_TOLERANCE: f32 = 1e-4;

/// Errors of reading and writing datasets.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A file or directory could not be read or written.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A transforms file is not valid JSON of the expected shape.
    #[error("invalid transforms file {path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parser's error (with line and column).
        source: serde_json::Error,
    },
    /// A transforms file (or the data to be written) breaks a rule of the format.
    #[error("invalid dataset data for {path}: {message}")]
    Invalid {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A file named by a transforms file does not exist.
    #[error("missing file {path} (frame {frame} of {transforms})")]
    MissingFile {
        /// The missing file.
        path: PathBuf,
        /// The frame's `file_path`.
        frame: String,
        /// The transforms file naming it.
        transforms: PathBuf,
    },
    /// A split name that is not a plain word (letters, digits, `_`, `-`).
    #[error("invalid split name {0:?}: use letters, digits, '_' or '-' (e.g. \"train\")")]
    SplitName(String),
    /// A downscale factor of 0.
    #[error("invalid downscale factor {0}: must be at least 1")]
    Downscale(u32),
    /// An image could not be read, written or processed.
    #[error(transparent)]
    Image(#[from] ImageError),
}

/// One frame of a transforms file.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// The image path as written in the JSON, relative to the dataset directory, usually
    /// without extension (e.g. `"./train/r_0"`).
    pub file_path: String,
    /// Camera-to-world matrix (NeRF's `transform_matrix`).
    pub camera_to_world: Mat4,
    /// NeRF-synthetic's per-frame `rotation` (unused by NeRF itself); kept for round trips.
    pub rotation: Option<f32>,
    /// Nephele's optional `depth_file_path`: an OpenEXR depth map, relative to the directory.
    pub depth_path: Option<String>,
}

/// The contents of a `transforms_{split}.json` file.
#[derive(Debug, Clone, PartialEq)]
pub struct Transforms {
    /// Horizontal field of view in radians, in `(0, pi)`.
    pub camera_angle_x: f32,
    /// The frames, in file order.
    pub frames: Vec<Frame>,
}

#[derive(Deserialize)]
struct RawTransforms {
    camera_angle_x: f64,
    frames: Vec<RawFrame>,
}

#[derive(Deserialize)]
struct RawFrame {
    file_path: String,
    #[serde(default)]
    rotation: Option<f64>,
    transform_matrix: Vec<Vec<f64>>,
    #[serde(default)]
    depth_file_path: Option<String>,
}

#[derive(Serialize)]
struct OutTransforms<'a> {
    camera_angle_x: f32,
    frames: Vec<OutFrame<'a>>,
}

#[derive(Serialize)]
struct OutFrame<'a> {
    file_path: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    rotation: Option<f32>,
    transform_matrix: [[f32; 4]; 4],
    #[serde(skip_serializing_if = "Option::is_none")]
    depth_file_path: Option<&'a str>,
}

/// Checks that `p` is a relative path that stays inside the dataset directory.
fn check_relative_path(p: &str) -> Result<(), String> {
    if p.is_empty() {
        return Err("empty path".into());
    }
    if p.starts_with('/') || p.starts_with('\\') || Path::new(p).is_absolute() {
        return Err(format!("path {p:?} must be relative to the dataset directory"));
    }
    let mut parts = p.split(['/', '\\']);
    if parts.next().is_some_and(|first| first.contains(':')) {
        return Err(format!("path {p:?} must be relative (no drive or scheme prefix)"));
    }
    if p.split(['/', '\\']).any(|c| c == "..") {
        return Err(format!("path {p:?} must not contain '..' components"));
    }
    if p.contains('\0') {
        return Err(format!("path {p:?} contains a NUL character"));
    }
    Ok(())
}

/// Checks that a matrix is finite with last row `(0, 0, 0, 1)`.
fn check_matrix(m: &Mat4) -> Result<(), String> {
    if !m.is_finite() {
        return Err("transform_matrix has non-finite entries".into());
    }
    let last = m.row(3);
    if (last - Vec4::W).abs().max_element() > LAST_ROW_TOLERANCE {
        return Err(format!("transform_matrix last row must be (0, 0, 0, 1), got {last}"));
    }
    Ok(())
}

fn check_angle(camera_angle_x: f32) -> Result<(), String> {
    if !(camera_angle_x > 0.0 && camera_angle_x < std::f32::consts::PI) {
        return Err(format!("camera_angle_x must be in (0, pi) radians, got {camera_angle_x}"));
    }
    Ok(())
}

impl Transforms {
    /// Checks the rules of the format: `camera_angle_x` in `(0, pi)`, every matrix finite with
    /// last row `(0, 0, 0, 1)` (within 1e-4), every path relative without `..`, rotations
    /// finite. The message names the offending frame.
    pub fn validate(&self) -> Result<(), String> {
        check_angle(self.camera_angle_x)?;
        for (i, f) in self.frames.iter().enumerate() {
            let at = |e: String| format!("frame {i} ({:?}): {e}", f.file_path);
            check_relative_path(&f.file_path).map_err(at)?;
            check_matrix(&f.camera_to_world).map_err(at)?;
            if let Some(d) = &f.depth_path {
                check_relative_path(d).map_err(at)?;
            }
            if f.rotation.is_some_and(|r| !r.is_finite()) {
                return Err(at("rotation is not finite".into()));
            }
        }
        Ok(())
    }
}

/// Converts the JSON rows of a `transform_matrix` into a column-major [`Mat4`].
fn matrix_from_rows(rows: &[Vec<f64>]) -> Result<Mat4, String> {
    if rows.len() != 4 || rows.iter().any(|r| r.len() != 4) {
        let shape: Vec<usize> = rows.iter().map(Vec::len).collect();
        return Err(format!("transform_matrix must be 4 rows of 4 numbers, got rows of lengths {shape:?}"));
    }
    let mut cols = [[0.0f32; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        for (c, &v) in row.iter().enumerate() {
            cols[c][r] = v as f32;
        }
    }
    Ok(Mat4::from_cols_array_2d(&cols))
}

/// Reads and validates a `transforms_*.json` file. Unknown keys (e.g. `fl_x`) are ignored.
pub fn read_transforms(path: impl AsRef<Path>) -> Result<Transforms, DatasetError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })?;
    let raw: RawTransforms =
        serde_json::from_str(&text).map_err(|source| DatasetError::Json { path: path.to_path_buf(), source })?;
    let invalid = |message: String| DatasetError::Invalid { path: path.to_path_buf(), message };
    let mut frames = Vec::with_capacity(raw.frames.len());
    for (i, f) in raw.frames.into_iter().enumerate() {
        let camera_to_world = matrix_from_rows(&f.transform_matrix)
            .map_err(|e| invalid(format!("frame {i} ({:?}): {e}", f.file_path)))?;
        frames.push(Frame {
            file_path: f.file_path,
            camera_to_world,
            rotation: f.rotation.map(|r| r as f32),
            depth_path: f.depth_file_path,
        });
    }
    let transforms = Transforms { camera_angle_x: raw.camera_angle_x as f32, frames };
    transforms.validate().map_err(invalid)?;
    Ok(transforms)
}

/// Validates and writes a transforms file in the NeRF-synthetic layout (4-space indent,
/// `transform_matrix` as rows). Numbers are written as the shortest decimal that reads back
/// as the same `f32`, so a write/read round trip is exact.
pub fn write_transforms(path: impl AsRef<Path>, transforms: &Transforms) -> Result<(), DatasetError> {
    let path = path.as_ref();
    transforms.validate().map_err(|message| DatasetError::Invalid { path: path.to_path_buf(), message })?;
    let out = OutTransforms {
        camera_angle_x: transforms.camera_angle_x,
        frames: transforms
            .frames
            .iter()
            .map(|f| OutFrame {
                file_path: &f.file_path,
                rotation: f.rotation,
                // Transposing the column-major matrix yields its rows.
                transform_matrix: f.camera_to_world.transpose().to_cols_array_2d(),
                depth_file_path: f.depth_path.as_deref(),
            })
            .collect(),
    };
    let mut bytes = Vec::new();
    let formatter = serde_json::ser::PrettyFormatter::with_indent(b"    ");
    let mut ser = serde_json::Serializer::with_formatter(&mut bytes, formatter);
    out.serialize(&mut ser).map_err(|source| DatasetError::Json { path: path.to_path_buf(), source })?;
    bytes.push(b'\n');
    std::fs::write(path, bytes).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })
}

/// One view of a dataset: a posed image, with an optional depth map.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// The image's file stem (e.g. `"r_0"`).
    pub name: String,
    /// Camera-to-world matrix.
    pub camera_to_world: Mat4,
    /// The image as stored (sRGB, straight alpha).
    pub image: RgbaImage,
    /// One-channel depth (view-space z distance, 0 for misses), the size of `image`.
    pub depth: Option<FloatImage>,
}

/// Splits `views` into the kept ones and a held-out set of every `every`-th view (views
/// `every - 1`, `2 every - 1`, ...), for datasets without a test split (`every` <= 1 holds
/// nothing out). `nephele train ngp`, `bake` and `bench inolf` share this rule, so a bake with
/// `--holdout-every N` never sees the views `bench inolf --holdout-every N` scores.
pub fn split_holdout(views: Vec<View>, every: usize) -> (Vec<View>, Vec<View>) {
    if every <= 1 {
        return (views, Vec::new());
    }
    let (mut kept, mut held) = (Vec::new(), Vec::new());
    for (i, v) in views.into_iter().enumerate() {
        if i % every == every - 1 { held.push(v) } else { kept.push(v) }
    }
    (kept, held)
}

/// One split of a dataset, loaded.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// Horizontal field of view in radians; the focal length in pixels is
    /// `0.5 * width / tan(0.5 * camera_angle_x)` for the (downscaled) image width.
    pub camera_angle_x: f32,
    /// The views, in the order of the transforms file.
    pub views: Vec<View>,
}

fn check_split(split: &str) -> Result<(), DatasetError> {
    let ok = !split.is_empty() && split.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if ok { Ok(()) } else { Err(DatasetError::SplitName(split.to_string())) }
}

/// Joins a validated relative `file_path` to `dir`, dropping `.` components.
fn join_relative(dir: &Path, rel: &str) -> PathBuf {
    let mut p = dir.to_path_buf();
    for part in rel.split(['/', '\\']).filter(|c| !c.is_empty() && *c != ".") {
        p.push(part);
    }
    p
}

fn has_extension(p: &str, ext: &str) -> bool {
    Path::new(p).extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case(ext))
}

/// The image file of a frame: `file_path`, with `.png` appended unless already there.
fn image_path(dir: &Path, file_path: &str) -> PathBuf {
    let p = join_relative(dir, file_path);
    if has_extension(file_path, "png") {
        p
    } else {
        let mut s = p.into_os_string();
        s.push(".png");
        PathBuf::from(s)
    }
}

/// The view name of a frame: the last component of `file_path` without a `.png` extension.
fn view_name(file_path: &str) -> String {
    let last = file_path.rsplit(['/', '\\']).next().unwrap_or(file_path);
    if has_extension(last, "png") { last[..last.len() - 4].to_string() } else { last.to_string() }
}

/// Path of the transforms file of `split` in `dir`.
pub fn transforms_path(dir: &Path, split: &str) -> PathBuf {
    dir.join(format!("transforms_{split}.json"))
}

/// Loads split `split` of the dataset in `dir`: `dir/transforms_{split}.json` and the PNG
/// images (and depth maps) it names, in parallel, each downscaled by `downscale` (1 keeps the
/// full size; see [`RgbaImage::downscale`]: sizes are floored). Depth maps are downscaled
/// averaging only the pixels that hit something. A missing file is reported by name.
pub fn load_split(dir: &Path, split: &str, downscale: u32) -> Result<Dataset, DatasetError> {
    check_split(split)?;
    if downscale == 0 {
        return Err(DatasetError::Downscale(downscale));
    }
    let json = transforms_path(dir, split);
    let transforms = read_transforms(&json)?;
    let views = transforms
        .frames
        .par_iter()
        .map(|frame| load_view(dir, &json, frame, downscale))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Dataset { camera_angle_x: transforms.camera_angle_x, views })
}

fn load_view(dir: &Path, json: &Path, frame: &Frame, downscale: u32) -> Result<View, DatasetError> {
    let missing = |path: PathBuf| DatasetError::MissingFile {
        path,
        frame: frame.file_path.clone(),
        transforms: json.to_path_buf(),
    };
    let path = image_path(dir, &frame.file_path);
    if !path.is_file() {
        return Err(missing(path));
    }
    let mut image = RgbaImage::load_png(&path)?;
    if downscale > 1 {
        image = image
            .downscale(downscale)
            .map_err(|e| DatasetError::Invalid { path: path.clone(), message: e.to_string() })?;
    }
    let depth = match &frame.depth_path {
        None => None,
        Some(rel) => {
            let depth_path = join_relative(dir, rel);
            if !has_extension(rel, "exr") {
                return Err(DatasetError::Invalid {
                    path: depth_path,
                    message: "depth maps must be OpenEXR (.exr) files".into(),
                });
            }
            if !depth_path.is_file() {
                return Err(missing(depth_path));
            }
            let invalid = |message: String| DatasetError::Invalid { path: depth_path.clone(), message };
            // Written as RGB with the depth replicated (see `FloatImage::save_exr`): keep R.
            let mut depth = FloatImage::load_exr(&depth_path)?.channel(0)?;
            if downscale > 1 {
                depth = depth.downscale_ignoring_zeros(downscale).map_err(|e| invalid(e.to_string()))?;
            }
            if (depth.width(), depth.height()) != (image.width(), image.height()) {
                return Err(invalid(format!(
                    "depth map is {}x{} but the image is {}x{}",
                    depth.width(),
                    depth.height(),
                    image.width(),
                    image.height()
                )));
            }
            Some(depth)
        }
    };
    Ok(View { name: view_name(&frame.file_path), camera_to_world: frame.camera_to_world, image, depth })
}

/// The splits present in `dir` (those with a `transforms_{split}.json`): `train`, `val`,
/// `test` first in that order, then any others alphabetically. Empty if `dir` cannot be read.
pub fn available_splits(dir: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut splits: Vec<String> = entries
        .filter_map(Result::ok)
        .filter(|e| e.path().is_file())
        .filter_map(|e| e.file_name().into_string().ok())
        .filter_map(|n| Some(n.strip_prefix("transforms_")?.strip_suffix(".json")?.to_string()))
        .filter(|s| check_split(s).is_ok())
        .collect();
    let rank = |s: &str| ["train", "val", "test"].iter().position(|&k| k == s).unwrap_or(3);
    splits.sort_by(|a, b| rank(a).cmp(&rank(b)).then_with(|| a.cmp(b)));
    splits
}

fn check_view_name(name: &str) -> Result<(), String> {
    if name.is_empty() || name == "." || name == ".." || name.contains(['/', '\\', '\0', ':']) {
        return Err(format!("view name {name:?} must be a plain file name"));
    }
    Ok(())
}

/// Writes split `split` of a dataset into `dir`: `dir/{split}/{name}.png` for every view,
/// `dir/{split}/{name}_depth.exr` for views with depth, and `dir/transforms_{split}.json`
/// (frames in the order of `views`, `file_path` `"./{split}/{name}"` as NeRF-synthetic
/// writes it). Everything is validated before anything is written. Images are written in
/// parallel.
pub fn write_split(dir: &Path, split: &str, camera_angle_x: f32, views: &[View]) -> Result<(), DatasetError> {
    check_split(split)?;
    let json = transforms_path(dir, split);
    let invalid = |message: String| DatasetError::Invalid { path: json.clone(), message };
    let mut seen = HashSet::new();
    for v in views {
        check_view_name(&v.name).map_err(invalid)?;
        if !seen.insert(v.name.as_str()) {
            return Err(invalid(format!("two views are named {:?}", v.name)));
        }
        let image_size = (v.image.width(), v.image.height());
        let bad_depth = v.depth.as_ref().filter(|d| d.channels() != 1 || (d.width(), d.height()) != image_size);
        if let Some(d) = bad_depth {
            return Err(invalid(format!(
                "view {:?}: depth must be one channel of {}x{}, got {} channel(s) of {}x{}",
                v.name,
                image_size.0,
                image_size.1,
                d.channels(),
                d.width(),
                d.height()
            )));
        }
    }
    let transforms = Transforms {
        camera_angle_x,
        frames: views
            .iter()
            .map(|v| Frame {
                file_path: format!("./{split}/{}", v.name),
                camera_to_world: v.camera_to_world,
                rotation: None,
                depth_path: v.depth.as_ref().map(|_| format!("./{split}/{}_depth.exr", v.name)),
            })
            .collect(),
    };
    transforms.validate().map_err(invalid)?;

    let image_dir = dir.join(split);
    std::fs::create_dir_all(&image_dir).map_err(|source| DatasetError::Io { path: image_dir.clone(), source })?;
    views.par_iter().try_for_each(|v| -> Result<(), DatasetError> {
        v.image.save_png(image_dir.join(format!("{}.png", v.name)))?;
        if let Some(d) = &v.depth {
            d.save_exr(image_dir.join(format!("{}_depth.exr", v.name)))?;
        }
        Ok(())
    })?;
    write_transforms(&json, &transforms)
}

/// Largest `|cos|` of the angle between a sampled view direction and the world Z axis:
/// directions are kept about 0.8 degrees away from the poles so that the world up vector is
/// never parallel to the view direction and the camera's horizontal axis stays defined.
const MAX_ABS_Z: f64 = 0.9999;

/// `count` camera-to-world matrices of cameras at distance `radius` (positive) from `target`,
/// looking at it with no roll (OpenGL camera, world +Z up), their directions independently
/// and uniformly distributed over the area of the sphere, or of the upper hemisphere
/// (`z >= target.z`, horizon included) if `upper_hemisphere_only`. Deterministic for a given
/// `seed`. Directions within about 0.8 degrees of the poles are moved to that limit.
pub fn sample_views_on_sphere(
    count: usize,
    radius: f32,
    target: Vec3,
    upper_hemisphere_only: bool,
    seed: u64,
) -> Vec<Mat4> {
    let mut rng = SplitMix64::new(seed);
    let target = target.as_dvec3();
    let radius = f64::from(radius);
    (0..count)
        .map(|_| {
            // Archimedes: z uniform in [-1, 1] (or [0, 1]) is area-uniform on the sphere.
            let u = rng.next_f64();
            let z = if upper_hemisphere_only { u } else { 2.0 * u - 1.0 }.clamp(-MAX_ABS_Z, MAX_ABS_Z);
            let phi = std::f64::consts::TAU * rng.next_f64();
            let s = (1.0 - z * z).max(0.0).sqrt();
            let dir = DVec3::new(s * phi.cos(), s * phi.sin(), z);
            let eye = (target + radius * dir).as_vec3();
            // Not parallel to +Z (clamped above); a zero radius (eye == target) keeps the
            // world axes.
            look_at_camera_to_world(eye, target.as_vec3(), Vec3::Z).unwrap_or(Mat4::from_translation(eye))
        })
        .collect()
}

#[cfg(test)]
mod tests {

    #[test]
    fn holdout_takes_every_nth_view() {
        let view = |i: usize| View {
            name: format!("r_{i}"),
            camera_to_world: Mat4::IDENTITY,
            image: RgbaImage::new(1, 1),
            depth: None,
        };
        let names = |v: &[View]| v.iter().map(|v| v.name.clone()).collect::<Vec<_>>();
        let (kept, held) = split_holdout((0..7).map(view).collect(), 3);
        assert_eq!(names(&held), ["r_2", "r_5"]);
        assert_eq!(names(&kept), ["r_0", "r_1", "r_3", "r_4", "r_6"]);
        let (kept, held) = split_holdout((0..3).map(view).collect(), 0);
        assert_eq!((kept.len(), held.len()), (3, 0));
    }

    use super::*;

    /// The lego scene shipped with the repository (required: the test fails without it).
    const LEGO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/lego");

    /// The first frame of lego's transforms_train.json.
    const LEGO_FRAME_0: &str = r#"{
        "camera_angle_x": 0.6911112070083618,
        "frames": [
            {
                "file_path": "./train/r_0",
                "rotation": 0.012566370614359171,
                "transform_matrix": [
                    [-0.9999021887779236, 0.004192245192825794, -0.013345719315111637, -0.05379832163453102],
                    [-0.013988681137561798, -0.2996590733528137, 0.95394366979599, 3.845470428466797],
                    [-4.656612873077393e-10, 0.9540371894836426, 0.29968830943107605, 1.2080823183059692],
                    [0.0, 0.0, 0.0, 1.0]
                ]
            }
        ]
    }"#;

    fn write_json(dir: &Path, text: &str) -> PathBuf {
        let path = dir.join("transforms_test.json");
        std::fs::write(&path, text).expect("write json");
        path
    }

    fn close(a: Vec3, b: Vec3, tol: f32) -> bool {
        (a - b).abs().max_element() <= tol
    }

    fn assert_lego_frame_0(m: &Mat4) {
        // The translation is the last column of the JSON rows: glam's w_axis.
        assert!(close(m.w_axis.truncate(), Vec3::new(-0.0538, 3.8455, 1.2081), 1e-4), "{m}");
        assert_eq!(m.w_axis.w, 1.0);
        // First column = first entries of the rows.
        assert!(close(m.x_axis.truncate(), Vec3::new(-0.999_902_2, -0.013_988_68, 0.0), 1e-6), "{m}");
        assert_eq!(m.row(3), Vec4::W);
        // The camera looks down -Z, towards the origin where the model is.
        let forward = -m.z_axis.truncate();
        assert!(forward.dot(-m.w_axis.truncate().normalize()) > 0.99);
    }

    #[test]
    fn transform_matrix_rows_become_glam_columns() {
        let dir = tempfile::tempdir().expect("tempdir");
        let t = read_transforms(write_json(dir.path(), LEGO_FRAME_0)).expect("read");
        assert_eq!(t.camera_angle_x, 0.691_111_2_f32);
        assert_eq!(t.frames.len(), 1);
        assert_eq!(t.frames[0].file_path, "./train/r_0");
        assert_eq!(t.frames[0].rotation, Some(0.012_566_371));
        assert_eq!(t.frames[0].depth_path, None);
        assert_lego_frame_0(&t.frames[0].camera_to_world);
    }

    #[test]
    fn transforms_round_trip_exactly() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mats = sample_views_on_sphere(5, 4.031_129, Vec3::new(0.1, -0.2, 0.3), true, 7);
        let t = Transforms {
            camera_angle_x: 0.691_111_2,
            frames: mats
                .iter()
                .enumerate()
                .map(|(i, m)| Frame {
                    file_path: format!("./train/r_{i}"),
                    camera_to_world: *m,
                    rotation: (i % 2 == 0).then_some(0.012_566_371),
                    depth_path: (i == 3).then(|| "./train/r_3_depth.exr".to_string()),
                })
                .collect(),
        };
        let path = dir.path().join("transforms_train.json");
        write_transforms(&path, &t).expect("write");
        let back = read_transforms(&path).expect("read");
        assert_eq!(back, t);
        // The file has NeRF's shape: rows of the matrix, optional keys only when present.
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).expect("read text")).expect("json");
        let f0 = &json["frames"][0];
        assert_eq!(f0["transform_matrix"].as_array().map(Vec::len), Some(4));
        assert_eq!(f0["transform_matrix"][3], serde_json::json!([0.0, 0.0, 0.0, 1.0]));
        assert_eq!(f0["transform_matrix"][0][3].as_f64().map(|v| v as f32), Some(mats[0].w_axis.x));
        assert!(json["frames"][1].get("rotation").is_none());
        assert!(f0.get("depth_file_path").is_none());
        assert_eq!(json["frames"][3]["depth_file_path"], "./train/r_3_depth.exr");
    }

    #[test]
    fn rejects_bad_transforms() {
        let dir = tempfile::tempdir().expect("tempdir");
        let frame = |file_path: &str, matrix: &str| {
            format!(
                r#"{{"camera_angle_x": 0.69, "frames": [{{"file_path": "{file_path}", "transform_matrix": {matrix}}}]}}"#
            )
        };
        let identity = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
        let cases = [
            // (json, expected fragment of the message)
            (r#"{"frames": []}"#.to_string(), "camera_angle_x"),
            (r#"{"camera_angle_x": 0.69}"#.to_string(), "frames"),
            (r#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./a"}]}"#.to_string(), "transform_matrix"),
            (frame("./a", "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,null]]"), "null"),
            (frame("./a", "[[1,0,0,NaN],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"), "line"),
            (frame("./a", "[[1,0,0,0],[0,1,0,0],[0,0,1,0]]"), "4 rows of 4"),
            (frame("./a", "[[1,0,0],[0,1,0],[0,0,1],[0,0,0]]"), "4 rows of 4"),
            (frame("./a", "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0.5,1]]"), "last row"),
            (frame("./a", "[[1,0,0,1e39],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"), "non-finite"),
            (frame("../a", identity), ".."),
            (frame("./train/../../a", identity), ".."),
            (frame("/etc/a", identity), "relative"),
            (frame("C:\\\\a", identity), "relative"),
            (frame("", identity), "empty"),
            (r#"{"camera_angle_x": 0, "frames": []}"#.to_string(), "camera_angle_x"),
            (r#"{"camera_angle_x": 3.5, "frames": []}"#.to_string(), "camera_angle_x"),
            ("not json".to_string(), "line"),
        ];
        for (json, fragment) in cases {
            let err = read_transforms(write_json(dir.path(), &json)).expect_err(&json);
            let msg = err.to_string();
            assert!(msg.contains(fragment), "{json}\n  -> {msg}\n  (expected {fragment:?})");
            assert!(msg.contains("transforms_test.json"), "{msg}");
        }
        // Depth paths are checked too.
        let json = r#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./a", "depth_file_path": "../d.exr",
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#;
        assert!(read_transforms(write_json(dir.path(), json)).is_err());
        // A missing file is an I/O error naming it.
        let err = read_transforms(dir.path().join("nope.json")).expect_err("missing");
        assert!(err.to_string().contains("nope.json"));
        // And write_transforms refuses invalid data.
        let bad = Transforms {
            camera_angle_x: 0.5,
            frames: vec![Frame {
                file_path: "../x".into(),
                camera_to_world: Mat4::IDENTITY,
                rotation: None,
                depth_path: None,
            }],
        };
        assert!(write_transforms(dir.path().join("t.json"), &bad).is_err());
    }

    /// A small image of exact 8-bit levels.
    fn test_image(seed: u32, w: u32, h: u32) -> RgbaImage {
        RgbaImage::from_fn(w, h, |x, y| {
            let l = |k: u32| (k % 256) as f32 / 255.0;
            [l(x * 31 + seed), l(y * 17 + seed * 3), l(x * y + 5), l(x * 7 + y * 13 + seed)]
        })
    }

    #[test]
    fn dataset_write_load_round_trip() {
        let dir = tempfile::tempdir().expect("tempdir");
        let poses = sample_views_on_sphere(3, 4.0, Vec3::ZERO, false, 1);
        let views: Vec<View> = poses
            .iter()
            .enumerate()
            .map(|(i, m)| View {
                name: format!("r_{i}"),
                camera_to_world: *m,
                image: test_image(i as u32, 8, 6),
                depth: (i != 1).then(|| {
                    let data = (0..48).map(|k| if k % 5 == 0 { 0.0 } else { 2.0 + k as f32 * 0.25 }).collect();
                    FloatImage::from_data(8, 6, 1, data).expect("depth")
                }),
            })
            .collect();
        write_split(dir.path(), "val", 0.75, &views).expect("write");
        assert!(dir.path().join("val/r_0.png").is_file());
        assert!(dir.path().join("val/r_0_depth.exr").is_file());
        assert!(!dir.path().join("val/r_1_depth.exr").exists());
        assert_eq!(available_splits(dir.path()), ["val"]);

        let loaded = load_split(dir.path(), "val", 1).expect("load");
        assert_eq!(loaded.camera_angle_x, 0.75);
        assert_eq!(loaded.views, views);

        // Downscaled: images and depth shrink, poses and angle do not change.
        let half = load_split(dir.path(), "val", 2).expect("load");
        assert_eq!(half.views.len(), 3);
        for (v, orig) in half.views.iter().zip(&views) {
            assert_eq!((v.image.width(), v.image.height()), (4, 3));
            assert_eq!(v.image, orig.image.downscale(2).expect("downscale"));
            assert_eq!(v.camera_to_world, orig.camera_to_world);
            assert_eq!(v.depth.as_ref().map(|d| (d.width(), d.height())), orig.depth.as_ref().map(|_| (4, 3)));
        }

        // A missing image is named.
        std::fs::remove_file(dir.path().join("val/r_2.png")).expect("remove");
        let err = load_split(dir.path(), "val", 1).expect_err("missing image");
        assert!(matches!(err, DatasetError::MissingFile { .. }), "{err}");
        assert!(err.to_string().contains("r_2.png"), "{err}");
    }

    #[test]
    fn file_paths_with_extension_and_splits() {
        let dir = tempfile::tempdir().expect("tempdir");
        let img = test_image(0, 4, 4);
        std::fs::create_dir_all(dir.path().join("test")).expect("mkdir");
        img.save_png(dir.path().join("test/a.png")).expect("save");
        let t = Transforms {
            camera_angle_x: 0.5,
            frames: vec![Frame {
                file_path: "test/a.png".into(),
                camera_to_world: Mat4::IDENTITY,
                rotation: None,
                depth_path: None,
            }],
        };
        write_transforms(transforms_path(dir.path(), "test"), &t).expect("write");
        write_transforms(transforms_path(dir.path(), "train"), &t).expect("write");
        write_transforms(transforms_path(dir.path(), "extra"), &t).expect("write");
        std::fs::write(dir.path().join("transforms_bad name.json"), "{}").expect("write");
        assert_eq!(available_splits(dir.path()), ["train", "test", "extra"]);
        let d = load_split(dir.path(), "test", 1).expect("load");
        assert_eq!(d.views[0].name, "a");
        assert_eq!(d.views[0].image, img);
        assert!(matches!(load_split(dir.path(), "test", 0), Err(DatasetError::Downscale(0))));
        assert!(matches!(load_split(dir.path(), "../x", 1), Err(DatasetError::SplitName(_))));
        assert!(load_split(dir.path(), "test", 8).is_err(), "4x4 image cannot be downscaled by 8");
        assert!(available_splits(&dir.path().join("does-not-exist")).is_empty());
    }

    #[test]
    fn write_split_rejects_bad_views() {
        let dir = tempfile::tempdir().expect("tempdir");
        let view = |name: &str| View {
            name: name.into(),
            camera_to_world: Mat4::IDENTITY,
            image: test_image(0, 2, 2),
            depth: None,
        };
        assert!(write_split(dir.path(), "train", 0.5, &[view("a"), view("a")]).is_err());
        assert!(write_split(dir.path(), "train", 0.5, &[view("../a")]).is_err());
        assert!(write_split(dir.path(), "train", 0.0, &[view("a")]).is_err());
        assert!(write_split(dir.path(), "tr/ain", 0.5, &[view("a")]).is_err());
        let mut v = view("a");
        v.depth = Some(FloatImage::new(3, 2, 1).expect("depth"));
        assert!(write_split(dir.path(), "train", 0.5, &[v]).is_err());
        let mut v = view("a");
        v.camera_to_world.x_axis.x = f32::NAN;
        assert!(write_split(dir.path(), "train", 0.5, &[v]).is_err());
        // Nothing was written by the failed calls.
        assert!(!dir.path().join("train").exists());
    }

    #[test]
    fn lego_loads_downscaled() {
        let dir = Path::new(LEGO);
        assert!(
            dir.join("transforms_train.json").is_file(),
            "the lego dataset is required for this test but {} has no transforms_train.json \
             (expected at <repository>/../shared/data/lego)",
            dir.display()
        );
        let d = load_split(dir, "train", 8).expect("load lego");
        assert_eq!(d.views.len(), 80);
        assert!((d.camera_angle_x - 0.6911).abs() < 1e-4, "{}", d.camera_angle_x);
        for v in &d.views {
            assert_eq!((v.image.width(), v.image.height()), (100, 100), "{}", v.name);
            assert!(v.depth.is_none());
        }
        assert_eq!(d.views[0].name, "r_0");
        assert_lego_frame_0(&d.views[0].camera_to_world);
        // Transparent background, opaque object in the middle.
        assert_eq!(d.views[0].image.pixel(0, 0)[3], 0.0);
        assert!(d.views.iter().any(|v| v.image.pixel(50, 50)[3] > 0.99));
        assert_eq!(available_splits(dir), ["train"]);
    }

    #[test]
    fn sampled_views_look_at_the_target_from_the_sphere() {
        let target = Vec3::new(0.5, -1.0, 0.25);
        let radius = 4.0;
        for hemisphere in [false, true] {
            let views = sample_views_on_sphere(500, radius, target, hemisphere, 42);
            assert_eq!(views.len(), 500);
            let mut mean_z = 0.0;
            for m in &views {
                let eye = m.w_axis.truncate();
                assert!(((eye - target).length() - radius).abs() < 1e-4 * radius, "{m}");
                // Looking at the target: -Z points from the eye to the target.
                let to_target = (target - eye).normalize();
                assert!((-m.z_axis.truncate()).dot(to_target) > 1.0 - 1e-5, "{m}");
                // Rigid, right-handed, no roll: +X horizontal, +Y upwards.
                let (x, y, z) = (m.x_axis.truncate(), m.y_axis.truncate(), m.z_axis.truncate());
                assert!((x.length() - 1.0).abs() < 1e-5 && (y.length() - 1.0).abs() < 1e-5);
                assert!(x.dot(y).abs() < 1e-5 && x.cross(y).dot(z) > 0.9999);
                assert!(x.z.abs() < 1e-6, "roll: {m}");
                assert!(y.z > 0.0, "upside down: {m}");
                assert_eq!(m.row(3), Vec4::W);
                assert!(m.is_finite());
                if hemisphere {
                    assert!(eye.z >= target.z, "{m}");
                }
                mean_z += (eye.z - target.z) / radius;
            }
            // Area-uniform: E[z] is 0 on the sphere, 1/2 on the hemisphere.
            mean_z /= views.len() as f32;
            let expected = if hemisphere { 0.5 } else { 0.0 };
            assert!((mean_z - expected).abs() < 0.06, "mean z {mean_z}");
        }
        // Deterministic by seed.
        assert_eq!(sample_views_on_sphere(10, 2.0, target, true, 3), sample_views_on_sphere(10, 2.0, target, true, 3));
        assert_ne!(sample_views_on_sphere(10, 2.0, target, true, 3), sample_views_on_sphere(10, 2.0, target, true, 4));
        assert!(sample_views_on_sphere(0, 2.0, target, true, 3).is_empty());
    }

    #[test]
    fn poles_are_avoided() {
        // Directions right at the pole would leave +X undefined; they are clamped instead.
        let eye = DVec3::new(0.0, 0.0, 1.0) * MAX_ABS_Z + DVec3::X * (1.0 - MAX_ABS_Z * MAX_ABS_Z).sqrt();
        let m = look_at_camera_to_world(eye.as_vec3(), Vec3::ZERO, Vec3::Z).expect("defined at the clamp");
        assert!(m.is_finite());
        let mut rng = SplitMix64::new(0);
        assert!((0..1000).all(|_| (0.0..1.0).contains(&rng.next_f64())));
    }
}
