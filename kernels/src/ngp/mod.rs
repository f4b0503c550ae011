//! The i-NGP-style radiance field (Müller et al. 2022, section 5.4) trained on the CPU, and
//! its volume renderer behind [`crate::kernel::RayKernel`]: the baseline every i-NOLF speed
//! figure is compared against, and the source of the density field the i-NOLF bake caches.
//!
//! * [`field`]: hash grid + density MLP + colour MLP, batched queries of density and colour
//!   at points (what the bake needs), and volume rendering of one ray (NEPHELE eq. 4);
//! * [`occupancy`]: the occupancy bit grid that lets marching skip empty space, and the
//!   visual hull of the training images that initialises it;
//! * [`march`]: ray/box intersection and the occupancy-skipping marcher;
//! * [`file`]: the versioned, checksummed file of a trained field;
//! * [`kernel`]: [`NgpKernel`], the farm kernel.

pub mod field;
pub mod file;
pub mod kernel;
pub mod march;
pub mod occupancy;

pub use field::{FieldConfig, FieldScratch, RadianceField, RayResult};
pub use file::{MAGIC as FILE_MAGIC, load_field, save_field};
pub use kernel::NgpKernel;
pub use occupancy::OccupancyGrid;

use std::path::PathBuf;

use nephele_nn::NnError;

/// Errors of training, loading and querying radiance fields.
#[derive(Debug, thiserror::Error)]
pub enum NgpError {
    #[error(transparent)]
    Nn(#[from] NnError),
    #[error("invalid radiance field: {0}")]
    Invalid(String),
    #[error("I/O error on {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path} is not a valid radiance field file: {reason}")]
    Format { path: PathBuf, reason: String },
}

pub(crate) fn check_len(what: &'static str, expected: usize, actual: usize) -> Result<(), NgpError> {
    if expected == actual { Ok(()) } else { Err(NgpError::Nn(NnError::Size { what, expected, actual })) }
}

impl FieldConfig {
    /// The smallest useful field: what unit tests train and round-trip in a fraction of a
    /// second.
    pub fn small_test() -> FieldConfig {
        FieldConfig {
            grid: nephele_nn::HashGridConfig {
                levels: 4,
                log2_table_size: 10,
                base_resolution: 4,
                per_level_scale: 2.0,
            },
            density_hidden: 16,
            geo_features: 7,
            color_hidden: 16,
            color_hidden_layers: 1,
            sh_degree: 2,
            steps_per_diagonal: 64,
            occupancy_resolution: 16,
        }
    }
}
