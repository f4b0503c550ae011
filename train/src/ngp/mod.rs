//! Training the i-NGP-style radiance field from posed RGBA images (random rays, L2 on
//! premultiplied RGBA, Adam, rayon over rays with per-task gradient buffers). The field, its
//! marcher and its file live in `nephele_kernels::ngp`.

pub mod train;

pub use train::{BatchGradients, StepStats, TrainConfig, Trainer, TrainingRay, batch_gradients};

#[cfg(test)]
mod tests;
