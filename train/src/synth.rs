//! Datasets rendered by the reference path tracer: views of a scene in the NeRF-synthetic
//! format (`DIR/transforms_{train,test}.json`, `DIR/{train,test}/r_N.png`, optionally
//! `r_N_depth.exr`). What `nephele dataset render` and the first start of `nephele up` run,
//! with typed values.

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};
use nephele_geometry::camera::{Camera, CameraError, look_at_camera_to_world};
use nephele_imaging::image::ImageError;
use nephele_pathtracer::integrator::Aov;
use nephele_pathtracer::sampling::Rng;
use nephele_pathtracer::scenes::{BuiltinScene, Framing};
use nephele_pathtracer::{RenderError, RenderOptions, Renderer};
use thiserror::Error;

use crate::dataset::{self, DatasetError, Frame, Transforms};

/// What to render.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DatasetSpec {
    /// Training views (at least 1).
    pub views: usize,
    /// Held-out test views (0 for none).
    pub test_views: usize,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    /// Samples per pixel of the test views; 0: `spp`. The held-out views are the reference
    /// a bake is scored against: more samples there keep the path tracer's noise out of the
    /// score (and out of choices made on it) for few views' cost.
    pub test_spp: u32,
    pub bounces: u32,
    /// Seed of the views and of the path tracer.
    pub seed: u64,
    /// Views on the whole sphere even for objects the scene frames on a hemisphere.
    pub full_sphere: bool,
    /// Also write view-space depth per view (`r_N_depth.exr`, 0 where nothing was hit).
    pub depth: bool,
}

impl DatasetSpec {
    /// At least 1 training view, at most 100000 views in all.
    pub fn validate(&self) -> Result<(), SynthError> {
        if self.views == 0 || self.views + self.test_views > 100_000 {
            return Err(SynthError::ViewCount { views: self.views, test_views: self.test_views });
        }
        Ok(())
    }
}

#[derive(Debug, Error)]
pub enum SynthError {
    #[error("at least 1 training view and at most 100000 views in all (asked {views} + {test_views})")]
    ViewCount { views: usize, test_views: usize },
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("view camera: {0}")]
    Camera(#[from] CameraError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("creating {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

/// Renders `spec` of `scene` into `out` (created if absent; files of the same names are
/// replaced). `on_rows` is called with the rows of each image as they finish, out of
/// `(views + test_views) * height` in all.
pub fn render_dataset(
    scene: BuiltinScene,
    spec: &DatasetSpec,
    out: &Path,
    on_rows: &(dyn Fn(u32) + Sync),
) -> Result<(), SynthError> {
    spec.validate()?;
    let poses = view_poses(&scene, spec.views + spec.test_views, !spec.full_sphere, spec.seed);
    let fov_x = scene.dataset_fov_x();
    let options = RenderOptions {
        samples_per_pixel: spec.spp,
        max_bounces: spec.bounces,
        seed: spec.seed,
        background: scene.default_background(),
        direct_only: false,
    };
    options.validate()?;
    let renderer = Renderer::new(scene.scene)?;
    let splits = [("train", &poses[..spec.views]), ("test", &poses[spec.views..])];
    for (split, split_poses) in splits {
        if split_poses.is_empty() {
            continue;
        }
        let dir = out.join(split);
        std::fs::create_dir_all(&dir).map_err(|source| SynthError::Io { path: dir.clone(), source })?;
        let mut frames = Vec::with_capacity(split_poses.len());
        for (i, &camera_to_world) in split_poses.iter().enumerate() {
            let camera = Camera::from_fov_x(spec.width, spec.height, fov_x, camera_to_world)?;
            // Every view gets its own noise: the seed mixes in the view's global index.
            let view_seed = spec
                .seed
                .wrapping_mul(0x9E37_79B9)
                .wrapping_add(frames.len() as u64 + if split == "test" { 1 << 32 } else { 0 });
            let samples_per_pixel = if split == "test" && spec.test_spp > 0 { spec.test_spp } else { spec.spp };
            let image =
                renderer.render(&camera, &RenderOptions { seed: view_seed, samples_per_pixel, ..options }, on_rows)?;
            let name = format!("r_{i}");
            image.to_rgba(Aov::Color).save_png(dir.join(format!("{name}.png")))?;
            let depth_path = if spec.depth {
                image.to_float(Aov::Depth).save_exr(dir.join(format!("{name}_depth.exr")))?;
                Some(format!("./{split}/{name}_depth.exr"))
            } else {
                None
            };
            frames.push(Frame { file_path: format!("./{split}/{name}"), camera_to_world, rotation: None, depth_path });
        }
        let transforms = Transforms { camera_angle_x: fov_x, frames };
        dataset::write_transforms(out.join(format!("transforms_{split}.json")), &transforms)?;
    }
    Ok(())
}

/// Camera-to-world matrices for `count` views of a scene, deterministic by seed: on a sphere
/// (or upper hemisphere) around an object, or from standpoints inside an interior.
pub fn view_poses(scene: &BuiltinScene, count: usize, allow_hemisphere: bool, seed: u64) -> Vec<Mat4> {
    match scene.framing {
        Framing::Object { center, orbit_radius, hemisphere, .. } => {
            dataset::sample_views_on_sphere(count, orbit_radius, center, hemisphere && allow_hemisphere, seed)
        }
        Framing::Interior { min, max, look_at, .. } => {
            // Standpoints anywhere in the scene's camera box (already away from the walls),
            // looking roughly at the room's point of interest with some spread so that
            // every wall is seen.
            let mut rng = Rng::new(seed, 0x1_0000);
            (0..count)
                .map(|_| {
                    let r = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
                    let eye = min + (max - min) * r;
                    let spread = Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, 0.3 * (rng.next_f32() - 0.5))
                        * (max - min);
                    let target = look_at + spread;
                    let target = if (target - eye).length() < 0.1 { look_at } else { target };
                    // A view straight up or down (a spread that lines up with +Z) keeps
                    // +Y as its up; eye == target cannot happen (checked just above).
                    look_at_camera_to_world(eye, target, Vec3::Z)
                        .or_else(|_| look_at_camera_to_world(eye, target, Vec3::Y))
                        .unwrap_or(Mat4::from_translation(eye))
                })
                .collect()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_small_dataset_renders_and_loads_back() {
        let dir = tempfile::tempdir().expect("tempdir");
        let scene = nephele_pathtracer::scenes::builtin("diffuse").expect("scene");
        let spec = DatasetSpec {
            views: 2,
            test_views: 1,
            width: 8,
            height: 6,
            spp: 1,
            test_spp: 16,
            bounces: 1,
            seed: 3,
            full_sphere: false,
            depth: true,
        };
        let rows = std::sync::atomic::AtomicU32::new(0);
        render_dataset(scene, &spec, dir.path(), &|r| {
            rows.fetch_add(r, std::sync::atomic::Ordering::Relaxed);
        })
        .expect("renders");
        assert_eq!(rows.into_inner(), 3 * 6);
        let train = dataset::load_split(dir.path(), "train", 1).expect("train split");
        let test = dataset::load_split(dir.path(), "test", 1).expect("test split");
        assert_eq!((train.views.len(), test.views.len()), (2, 1));
        assert_eq!((train.views[0].image.width(), train.views[0].image.height()), (8, 6));
        assert!(dir.path().join("train/r_1_depth.exr").is_file());
        let scene = nephele_pathtracer::scenes::builtin("diffuse").expect("scene");
        let none = DatasetSpec { views: 0, ..spec };
        assert!(matches!(render_dataset(scene, &none, dir.path(), &|_| {}), Err(SynthError::ViewCount { .. })));
    }
}
