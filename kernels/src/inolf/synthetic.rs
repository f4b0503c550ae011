//! A synthetic i-NOLF object with every part a baked asset has, built in milliseconds for the
//! tests and benchmarks that need one without a bake: sparse density cubes of
//! [`hard_object_density`] (a soft-edged sphere, a thin tilted slab for grazing rays, a box
//! alone in a corner for empty blocks), a PSH over the hit points of a ring of views with
//! features spread over [-1, 1] (so that the encoding shapes the specular output), diffuse
//! cubes of varied bytes and small random heads. The GPU agreement tests and
//! `bench hardcases` (at three scales) render it.

use glam::Vec3;
use nephele_geometry::Bounds;
use nephele_geometry::camera::Camera;
use nephele_geometry::hardcases::hard_object_density;

use super::asset::{Asset, Tensor};
use super::cubes::{CubeOptions, DensityCubes, SparseCubes};
use super::encoding::PshEncoding;
use super::heads::InolfMeta;
use super::kernel::{InolfKernel, RAY_NEAR};
use super::model::{HeadsShape, InolfModel, ModelError};
use super::psh::PshOptions;
use crate::kernel::all_pixels;

/// The object's model (for training and assets) and its kernel (diffuse from the cubes).
#[derive(Debug, Clone)]
pub struct SyntheticObject {
    pub model: InolfModel,
    pub kernel: InolfKernel,
}

impl SyntheticObject {
    /// The object as the contents of an asset file (the specular MLP and both cube sets,
    /// marched every voxel).
    pub fn asset(&self) -> Result<Asset, ModelError> {
        let meta = InolfMeta {
            format: "inolf".into(),
            shape: self.model.shape,
            grid_bounds: [self.model.bounds.min.to_array(), self.model.bounds.max.to_array()],
            bake: serde_json::Value::Null,
            march_stride: 1,
            hit_rule: self.kernel.density().hit_rule(),
        };
        let specular = self.model.specular.params();
        Ok(Asset {
            meta: serde_json::to_string(&meta).map_err(|e| ModelError::Shape(e.to_string()))?,
            density: self.kernel.density().clone(),
            diffuse: self.kernel.diffuse_cubes().cloned(),
            psh: Some(self.model.psh.clone()),
            tensors: vec![Tensor {
                name: "specular.mlp".into(),
                shape: vec![specular.len() as u32],
                data: specular.to_vec(),
            }],
        })
    }
}

/// A value in `[-1, 1)` spread by the golden-ratio hash of `i`.
pub fn spread(i: usize) -> f32 {
    ((i as u32).wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0
}

/// The object over `[-scale, scale]^3` (densities divided by `scale`: the same optical depths
/// at every scale).
pub fn synthetic_object(scale: f32) -> Result<SyntheticObject, Box<dyn std::error::Error + Send + Sync>> {
    let bounds = Bounds { min: Vec3::splat(-scale), max: Vec3::splat(scale) };
    let options = CubeOptions { resolution: 24, cube_res: 6, probe: 2, dilate: 1 };
    let cubes = DensityCubes::build(
        bounds,
        &options,
        |p: &[Vec3], out: &mut [f32]| p.iter().zip(out).for_each(|(p, o)| *o = hard_object_density(*p / scale) / scale),
        &|_| {},
    )?;
    let mut points = Vec::new();
    for i in 0..12 {
        let a = i as f32 * std::f32::consts::TAU / 12.0;
        let eye = Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), if i % 2 == 0 { 1.2 } else { -0.9 }) * scale;
        let camera = Camera::look_at(24, 24, 0.8, eye, Vec3::ZERO, Vec3::Z)?;
        for p in all_pixels(&camera) {
            let ray = camera.pixel_center_ray(p % 24, p / 24);
            let h = cubes.march(ray.origin, ray.direction, RAY_NEAR * scale, f32::INFINITY);
            if h.opacity > 1e-3 {
                points.push(ray.at(h.t));
            }
        }
    }
    let u = 64;
    let mut psh = PshEncoding::from_points(&points, bounds.min, 2.0 * scale / u as f32, u, 4, &PshOptions::default())?;
    for (i, f) in psh.features.iter_mut().enumerate() {
        *f = spread(i);
    }
    let shape = HeadsShape {
        grid_levels: 2,
        grid_log2_table: 10,
        grid_base: 4,
        grid_scale: 2.0,
        diffuse_hidden: 8,
        diffuse_layers: 1,
        sh_degree: 3,
        specular_hidden: 16,
        specular_layers: 2,
        diffuse_blend: false,
        blend_samples: super::cubes::MAX_BLEND_SAMPLES as u32,
    };
    let mut model = InolfModel::new(shape, bounds, psh, 7)?;
    // Grid features of order one, so that the diffuse network's output varies in space.
    for (i, f) in model.grid.params_mut().iter_mut().enumerate() {
        *f = spread(i);
    }
    let c = cubes.cubes();
    let diffuse_bytes = (0..c.cube_count() * 4 * 4 * 4 * 6).map(|i| (i * 37 % 251) as u8).collect();
    let diffuse = SparseCubes::from_parts(c.min(), c.cell(), c.dims(), 4, 6, c.index().to_vec(), diffuse_bytes)?;
    let kernel = InolfKernel::from_model(&model, cubes, Some(diffuse));
    Ok(SyntheticObject { model, kernel })
}
