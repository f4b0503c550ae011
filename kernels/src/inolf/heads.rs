//! Reading an i-NOLF asset's networks back: the meta section, the specular MLP (and the
//! diffuse network when the asset kept it), checked against each other before anything is
//! allocated; and the 8-bit code of the diffuse texture cubes.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::asset::Asset;
use super::model::{DIFFUSE_OUT, HeadsShape, ModelError};
use nephele_geometry::Bounds;
use nephele_nn::{HashGrid, Mlp};

/// The asset's meta section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InolfMeta {
    /// Always "inolf".
    pub format: String,
    pub shape: HeadsShape,
    /// Box the diffuse hash grid's unit cube maps to.
    pub grid_bounds: [[f32; 3]; 2],
    /// Free-form description of the bake (source, steps, losses).
    #[serde(default)]
    pub bake: serde_json::Value,
    /// Voxels between the density march's samples that the asset is rendered with unless a
    /// renderer asks otherwise ([`super::cubes::DensityCubes::set_march_stride`]): 1 (every
    /// voxel) unless the bake measured a coarser march within its error budget on held-out
    /// views. Assets written before this field march every voxel.
    #[serde(default = "every_voxel")]
    pub march_stride: u32,
    /// Which sample of the march is a ray's hit point: the rule the heads were trained with
    /// ([`super::cubes::HitRule`]). Assets written before this field took the sample of
    /// largest weight.
    #[serde(default)]
    pub hit_rule: super::cubes::HitRule,
}

fn every_voxel() -> u32 {
    1
}

/// Records in `asset`'s meta section the march stride it is to be rendered with (the bake's
/// choice, [`InolfMeta::march_stride`]).
pub fn set_asset_march_stride(asset: &mut Asset, stride: u32) -> Result<(), ModelError> {
    if !(1..=super::cubes::MAX_MARCH_STRIDE).contains(&stride) {
        return Err(ModelError::Shape(format!("march stride {stride} (1..={})", super::cubes::MAX_MARCH_STRIDE)));
    }
    let mut meta: InolfMeta = serde_json::from_str(&asset.meta).map_err(|e| ModelError::Shape(format!("meta: {e}")))?;
    meta.march_stride = stride;
    asset.meta = serde_json::to_string(&meta).map_err(|e| ModelError::Shape(e.to_string()))?;
    Ok(())
}

/// Diffuse colour and tint are stored as `sqrt(value)` in 8 bits: finer steps in the darks,
/// where sRGB is most sensitive.
#[inline]
pub fn encode_diffuse(v: f32) -> u8 {
    (v.clamp(0.0, 1.0).sqrt() * 255.0).round() as u8
}

/// Inverse of [`encode_diffuse`] for an interpolated code in `[0, 1]`.
#[inline]
pub fn decode_diffuse(code: f32) -> f32 {
    code * code
}

/// The networks read back from an asset.
#[derive(Debug, Clone)]
pub struct LoadedHeads {
    pub meta: InolfMeta,
    pub grid_bounds: Bounds,
    pub specular: Mlp,
    /// Present when the asset kept the diffuse network.
    pub diffuse: Option<(HashGrid, Mlp)>,
}

/// Checks the meta section and the tensors against each other and rebuilds the networks.
pub fn load_heads(asset: &Asset) -> Result<LoadedHeads, ModelError> {
    let bad = |m: String| ModelError::Shape(m);
    let meta: InolfMeta = serde_json::from_str(&asset.meta).map_err(|e| bad(format!("meta: {e}")))?;
    if meta.format != "inolf" {
        return Err(bad(format!("asset format {:?} is not inolf", meta.format)));
    }
    let psh = asset.psh.as_ref().ok_or_else(|| bad("no PSH section".into()))?;
    if !(1..=5).contains(&meta.shape.sh_degree) {
        return Err(bad(format!("SH degree {}", meta.shape.sh_degree)));
    }
    if !(1..=super::cubes::MAX_MARCH_STRIDE).contains(&meta.march_stride) {
        return Err(bad(format!("march stride {} (1..={})", meta.march_stride, super::cubes::MAX_MARCH_STRIDE)));
    }
    meta.hit_rule.validate().map_err(|e| bad(e.to_string()))?;
    let blend_samples = meta.shape.blend_samples as usize;
    if meta.shape.diffuse_blend && !(1..=super::cubes::MAX_BLEND_SAMPLES).contains(&blend_samples) {
        return Err(bad(format!("{blend_samples} blend samples (1..={})", super::cubes::MAX_BLEND_SAMPLES)));
    }
    let [lo, hi] = meta.grid_bounds.map(Vec3::from);
    if !(lo.is_finite() && hi.is_finite() && (hi - lo).min_element() > 0.0) {
        return Err(bad("grid bounds".into()));
    }
    let tensor = |name: &str| asset.tensors.iter().find(|t| t.name == name);
    // Sizes are checked against the tensors present in the file before any network is
    // allocated, so a hostile meta section cannot ask for a huge grid.
    let data = |name: &str, expected: usize| -> Result<&[f32], ModelError> {
        let t = tensor(name).ok_or_else(|| bad(format!("tensor {name} missing")))?;
        if t.data.len() != expected {
            return Err(bad(format!("tensor {name} has {} values, the shape needs {expected}", t.data.len())));
        }
        Ok(&t.data)
    };
    let specular_config = meta.shape.specular_mlp(psh.feature_dim);
    specular_config.validate()?;
    let weights = data("specular.mlp", specular_config.num_params())?;
    let mut specular = Mlp::zeros(specular_config)?;
    specular.params_mut().copy_from_slice(weights);
    let diffuse = if tensor("diffuse.mlp").is_some() {
        let grid_config = meta.shape.grid();
        grid_config.validate()?;
        let mlp_config = meta.shape.diffuse_mlp();
        mlp_config.validate()?;
        let grid_weights = data("diffuse.grid", grid_config.num_params())?;
        let mlp_weights = data("diffuse.mlp", mlp_config.num_params())?;
        let mut grid = HashGrid::zeros(grid_config)?;
        grid.params_mut().copy_from_slice(grid_weights);
        let mut mlp = Mlp::zeros(mlp_config)?;
        mlp.params_mut().copy_from_slice(mlp_weights);
        Some((grid, mlp))
    } else {
        None
    };
    if diffuse.is_none() && asset.diffuse.is_none() {
        return Err(bad("neither diffuse cubes nor a diffuse network".into()));
    }
    if let Some(d) = &asset.diffuse {
        let c = asset.density.cubes();
        if d.channels() != DIFFUSE_OUT as u32 || d.dims() != c.dims() || d.cell() != c.cell() || d.min() != c.min() {
            return Err(bad("diffuse cubes do not match the density grid".into()));
        }
    }
    Ok(LoadedHeads { grid_bounds: Bounds { min: lo, max: hi }, meta, specular, diffuse })
}
