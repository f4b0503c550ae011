//! Baking (NEPHELE section 4.3): the diffuse branch is view-independent, so after training
//! it is sampled once into diffuse texture cubes around the hit surfaces, and the asset
//! keeps the density cubes, the diffuse cubes, the PSH tables and features and the specular
//! MLP (plus the diffuse network, for the "+ diffuse MLP" variant and for re-baking).

use glam::Vec3;
use rayon::prelude::*;

use nephele_kernels::inolf::asset::{Asset, Tensor};
use nephele_kernels::inolf::cubes::{CubeError, DensityCubes, EMPTY_CELL, SparseCubes, dilate};
use nephele_kernels::inolf::heads::{InolfMeta, encode_diffuse};
use nephele_kernels::inolf::model::{DIFFUSE_OUT, InolfModel, ModelError};
use nephele_kernels::ngp::{FieldScratch, RadianceField};
use nephele_nn::MlpWorkspace;

/// The density the cubes are built from (NEPHELE section 4: density texture cubes baked
/// from the radiance field): the field's density network, cut to zero outside its own
/// occupancy grid (the calibrated notion of "empty" the baseline marches with) and below
/// `threshold` (per unit length). Batched, for [`DensityCubes::build`].
pub fn field_density_for_cubes(field: &RadianceField, threshold: f32) -> impl Fn(&[Vec3], &mut [f32]) + Sync + '_ {
    move |points: &[Vec3], out: &mut [f32]| {
        let occupancy = field.occupancy();
        let res = occupancy.resolution();
        let mut scratch = FieldScratch::new();
        if field.density_batch(points, out, &mut scratch).is_err() {
            out.iter_mut().for_each(|v| *v = 0.0);
        }
        for (p, o) in points.iter().zip(out.iter_mut()) {
            let u = field.to_unit(*p) * res as f32;
            let cell = [u.x, u.y, u.z].map(|c| (c.max(0.0) as u32).min(res - 1));
            if *o < threshold || !occupancy.get(occupancy.index(cell[0], cell[1], cell[2])) {
                *o = 0.0;
            }
        }
    }
}

/// Per-thread buffers of the bake: grid inputs, outputs, encoder scratch.
type BakeScratch = (Vec<[f32; 3]>, Vec<f32>, (Vec<f32>, MlpWorkspace));

/// Samples the diffuse branch into cubes of `cube_res^3` on the density cubes' coarse grid,
/// in the cells that hold density and lie within `margin` cells of a hit point.
pub fn bake_diffuse_cubes(
    model: &InolfModel,
    cubes: &DensityCubes,
    hits: &[Vec3],
    margin: u32,
    cube_res: u32,
) -> Result<SparseCubes, ModelError> {
    let grid = cubes.cubes();
    let dims = grid.dims();
    let (nx, ny) = (dims[0] as usize, dims[1] as usize);
    let cells = grid.index().len();
    let mut marks = vec![false; cells];
    for p in hits {
        if let Some(c) = grid.cell_of(*p) {
            marks[c[0] as usize + nx * (c[1] as usize + ny * c[2] as usize)] = true;
        }
    }
    let marks = dilate(&marks, dims, margin);
    let todo: Vec<usize> = (0..cells).filter(|&c| marks[c] && grid.index()[c] != EMPTY_CELL).collect();
    let res = cube_res as usize;
    let step = grid.cell() / (cube_res - 1).max(1) as f32;
    let min = grid.min();
    let baked: Vec<Result<Vec<u8>, ModelError>> = todo
        .par_iter()
        .map_init(
            || (Vec::new(), Vec::new(), (Vec::new(), MlpWorkspace::new())),
            |(points, out, scratch): &mut BakeScratch, &c| {
                let g = [(c % nx) * (res - 1), ((c / nx) % ny) * (res - 1), (c / (nx * ny)) * (res - 1)];
                points.clear();
                for k in 0..res {
                    for j in 0..res {
                        for i in 0..res {
                            let p = min + Vec3::new((g[0] + i) as f32, (g[1] + j) as f32, (g[2] + k) as f32) * step;
                            points.push(model.grid_input(p));
                        }
                    }
                }
                out.resize(points.len() * DIFFUSE_OUT, 0.0);
                model.diffuse_batch(points, out, scratch)?;
                Ok(out.iter().map(|&v| encode_diffuse(v)).collect())
            },
        )
        .collect();
    let mut index = vec![EMPTY_CELL; cells];
    let mut data = Vec::new();
    for (n, (&c, cube)) in todo.iter().zip(baked).enumerate() {
        index[c] = n as u32;
        data.extend_from_slice(&cube?);
    }
    SparseCubes::from_parts(min, grid.cell(), dims, cube_res, DIFFUSE_OUT as u32, index, data)
        .map_err(|e: CubeError| ModelError::Shape(e.to_string()))
}

/// Assembles the asset. `keep_diffuse_network` also stores the hash grid and diffuse MLP.
pub fn to_asset(
    model: &InolfModel,
    cubes: DensityCubes,
    diffuse: Option<SparseCubes>,
    keep_diffuse_network: bool,
    bake: serde_json::Value,
) -> Result<Asset, ModelError> {
    let meta = InolfMeta {
        format: "inolf".into(),
        shape: model.shape,
        grid_bounds: [model.bounds.min.to_array(), model.bounds.max.to_array()],
        bake,
        march_stride: 1,
        hit_rule: cubes.hit_rule(),
    };
    let flat =
        |name: &str, data: &[f32]| Tensor { name: name.into(), shape: vec![data.len() as u32], data: data.to_vec() };
    let mut tensors = vec![flat("specular.mlp", model.specular.params())];
    if keep_diffuse_network || diffuse.is_none() {
        tensors.push(flat("diffuse.grid", model.grid.params()));
        tensors.push(flat("diffuse.mlp", model.diffuse.params()));
    }
    Ok(Asset {
        meta: serde_json::to_string(&meta).map_err(|e| ModelError::Shape(e.to_string()))?,
        density: cubes,
        diffuse,
        psh: Some(model.psh.clone()),
        tensors,
    })
}
