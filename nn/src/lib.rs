//! Neural building blocks for the learned kernels: the multiresolution hash-grid encoding,
//! small fully-connected networks, the deep residual MLP of the NeLF ([`resmlp`]), input encodings, image convolutions and the small U-Net
//! of the global-illumination model ([`conv`], [`unet`]), and the Adam optimiser.
//!
//! `nephele-nn` depends on `nephele-geometry` only (its SplitMix64 seeds the weights); no
//! kernel, asset format or trainer lives here: those compose these blocks.
//!
//! # Why hand-written fused passes
//!
//! The networks here are tiny (width 64 or less, one or two hidden layers) and are evaluated
//! millions of times per training step on a 2-core CPU. An autodiff library (burn, candle,
//! dfdx) builds a graph of generic tensor operations: every layer allocates its activations,
//! launches a separate matrix multiply sized for large matrices and walks the graph backwards
//! through dynamic dispatch. At 64 wide that overhead dominates the arithmetic, and the hash
//! encoding (a gather of 8 corners per level, a scatter-add on the way back) is not a tensor
//! operation those libraries do well at all. So, in the manner of tiny-cuda-nn's
//! "fully fused" MLP, forward and backward are written out by hand: row-major batches,
//! weights stored input-major so that the inner loop is a contiguous `y += x_k * w_k` that
//! the compiler vectorises, zero ReLU activations skipped, parameter gradients accumulated in
//! place into caller-owned buffers (one per thread, reduced by the caller), and no allocation
//! after the first batch. The hash grid is processed level by level over a batch of points
//! so that one level's table is hot in cache at a time, and its backward can run one level
//! per thread without any synchronisation (levels own disjoint parameter ranges).
//!
//! Everything is `f32`; gradient correctness is checked against finite differences in the
//! tests of each module.

pub mod adam;
pub mod conv;
pub mod encoding;
pub mod hashgrid;
pub mod mlp;
pub mod resmlp;
pub mod simd;
pub mod unet;

pub use adam::{Adam, AdamConfig, LazyAdam};
pub use conv::PixelMask;
pub use encoding::{frequency_encode, frequency_encoded_len, sh_coefficient_count, sh_encode};
pub use hashgrid::{FEATURES_PER_LEVEL, HashGrid, HashGridConfig};
pub use mlp::{Activation, Mlp, MlpConfig, MlpWorkspace};
pub use resmlp::{ResidualMlp, ResidualMlpConfig, ResidualWorkspace};
pub use simd::SimdMode;
pub use unet::{StudentStart, UNet, UNetConfig, UNetWorkspace};

/// Invalid network configurations and mismatched buffers.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NnError {
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error("{what}: expected {expected} values, got {actual}")]
    Size { what: &'static str, expected: usize, actual: usize },
}

/// Small deterministic generator for weight initialisation (SplitMix64); weights must not
/// depend on thread scheduling or on another module's random streams.
/// The scenes' SplitMix64 under a seed of its own, so the streams never coincide.
#[derive(Debug, Clone)]
pub(crate) struct InitRng(nephele_geometry::SplitMix64);

impl InitRng {
    pub(crate) fn new(seed: u64) -> Self {
        InitRng(nephele_geometry::SplitMix64::new(seed ^ 0x6E65_7068_656C_6531))
    }

    /// Uniform in `[-bound, bound)`.
    pub(crate) fn uniform(&mut self, bound: f32) -> f32 {
        (2.0 * self.0.next_f32() - 1.0) * bound
    }
}

/// Checks a buffer length.
pub(crate) fn check_len(what: &'static str, expected: usize, actual: usize) -> Result<(), NnError> {
    if expected == actual { Ok(()) } else { Err(NnError::Size { what, expected, actual }) }
}
