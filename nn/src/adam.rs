//! Adam (Kingma and Ba 2015) with bias correction, optional L2 weight decay and optional
//! decoupled weight decay (AdamW, Loshchilov and Hutter 2019).
//!
//! i-NGP trains with `beta1 = 0.9, beta2 = 0.99, epsilon = 1e-15`, weight decay on the MLP
//! weights only (never on the hash-grid features: most table entries see no gradient in a
//! step and would decay to nothing). One [`Adam`] per parameter group gives that choice.

use rayon::prelude::*;

use super::{NnError, check_len};

/// Hyper-parameters of one parameter group.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    pub learning_rate: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    /// L2 penalty added to the gradient (`g += weight_decay * w`); 0 turns it off. Adam's
    /// normalisation rescales it with the gradient, so its pull depends on how often and how
    /// strongly an entry is trained.
    pub weight_decay: f32,
    /// Decoupled decay (AdamW): every updated entry also shrinks by `learning_rate *
    /// decoupled_decay * w`, whatever its gradient's scale; 0 turns it off.
    pub decoupled_decay: f32,
}

impl Default for AdamConfig {
    /// i-NGP's settings.
    fn default() -> Self {
        AdamConfig {
            learning_rate: 1e-2,
            beta1: 0.9,
            beta2: 0.99,
            epsilon: 1e-15,
            weight_decay: 0.0,
            decoupled_decay: 0.0,
        }
    }
}

/// Optimiser state for one parameter vector.
#[derive(Debug, Clone)]
pub struct Adam {
    config: AdamConfig,
    m: Vec<f32>,
    v: Vec<f32>,
    steps: u64,
}

/// Parameters per parallel chunk of the update.
const CHUNK: usize = 1 << 14;

impl Adam {
    pub fn new(config: AdamConfig, len: usize) -> Self {
        Adam { config, m: vec![0.0; len], v: vec![0.0; len], steps: 0 }
    }

    pub fn config(&self) -> &AdamConfig {
        &self.config
    }

    /// Changes the learning rate (schedules).
    pub fn set_learning_rate(&mut self, learning_rate: f32) {
        self.config.learning_rate = learning_rate;
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The first and second moment estimates (for checkpoints).
    pub fn moments(&self) -> (&[f32], &[f32]) {
        (&self.m, &self.v)
    }

    /// An optimiser resumed from a checkpoint's moments and step count.
    pub fn from_moments(config: AdamConfig, m: Vec<f32>, v: Vec<f32>, steps: u64) -> Result<Self, NnError> {
        check_len("Adam second moments", m.len(), v.len())?;
        Ok(Adam { config, m, v, steps })
    }

    /// One update of `params` from `grads` (same length as at construction). Runs on the
    /// rayon pool in chunks.
    pub fn step(&mut self, params: &mut [f32], grads: &[f32]) -> Result<(), NnError> {
        self.update(params, grads, false)
    }

    /// Like [`Adam::step`], but entries whose gradient is exactly zero are left alone, moments
    /// included (PyTorch's `SparseAdam` semantics). For hash-grid tables, where a step touches
    /// a small fraction of the entries: it saves the memory traffic of the untouched ones and
    /// keeps their features from drifting on stale momentum.
    pub fn step_sparse(&mut self, params: &mut [f32], grads: &[f32]) -> Result<(), NnError> {
        self.update(params, grads, true)
    }

    fn update(&mut self, params: &mut [f32], grads: &[f32], sparse: bool) -> Result<(), NnError> {
        check_len("Adam parameters", self.m.len(), params.len())?;
        check_len("Adam gradients", self.m.len(), grads.len())?;
        self.steps += 1;
        let c = self.config;
        let t = self.steps as i32;
        // Bias corrections folded into the step size (the paper's "efficient version").
        let correction1 = 1.0 - c.beta1.powi(t);
        let correction2 = 1.0 - c.beta2.powi(t);
        let step_size = c.learning_rate * correction2.sqrt() / correction1;
        let epsilon = c.epsilon * correction2.sqrt();
        let shrink = 1.0 - c.learning_rate * c.decoupled_decay;
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks(CHUNK))
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .for_each(|(((p, g), m), v)| {
                for i in 0..p.len() {
                    let mut grad = g[i];
                    if sparse && grad == 0.0 {
                        continue;
                    }
                    if !grad.is_finite() {
                        // A non-finite gradient would poison the moments for good.
                        continue;
                    }
                    if c.weight_decay != 0.0 {
                        grad += c.weight_decay * p[i];
                    }
                    m[i] = c.beta1 * m[i] + (1.0 - c.beta1) * grad;
                    v[i] = c.beta2 * v[i] + (1.0 - c.beta2) * grad * grad;
                    p[i] = shrink * p[i] - step_size * m[i] / (v[i].sqrt() + epsilon);
                }
            });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minimises_a_quadratic() {
        // f(w) = sum (w - target)^2, ill-conditioned scales.
        let target = [3.0f32, -1.0, 0.5, 100.0];
        let scale = [1.0f32, 10.0, 0.1, 1.0];
        let mut w = vec![0.0f32; 4];
        let mut adam = Adam::new(AdamConfig { learning_rate: 0.5, ..AdamConfig::default() }, 4);
        for _ in 0..2000 {
            let g: Vec<f32> = (0..4).map(|i| 2.0 * scale[i] * (w[i] - target[i])).collect();
            adam.step(&mut w, &g).expect("step");
        }
        for i in 0..4 {
            assert!((w[i] - target[i]).abs() < 0.05, "{i}: {} vs {}", w[i], target[i]);
        }
        assert_eq!(adam.steps(), 2000);
    }

    #[test]
    fn first_step_moves_each_parameter_by_the_learning_rate() {
        // With bias correction the first step is lr * sign(g), whatever the gradient's scale.
        let mut w = vec![0.0f32; 3];
        let mut adam = Adam::new(AdamConfig { learning_rate: 0.1, epsilon: 1e-15, ..AdamConfig::default() }, 3);
        adam.step(&mut w, &[1e-6, -5.0, 0.0]).expect("step");
        assert!((w[0] + 0.1).abs() < 1e-5 && (w[1] - 0.1).abs() < 1e-5 && w[2] == 0.0, "{w:?}");
        assert!(adam.step(&mut w, &[0.0; 2]).is_err());
        // Non-finite gradients are skipped rather than poisoning the state.
        adam.step(&mut w, &[f32::NAN, f32::INFINITY, 0.0]).expect("step");
        assert!(w.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn sparse_step_leaves_zero_gradient_entries_alone() {
        let mut w = vec![1.0f32, 1.0];
        let mut adam = Adam::new(AdamConfig { learning_rate: 0.1, ..AdamConfig::default() }, 2);
        adam.step_sparse(&mut w, &[1.0, 1.0]).expect("step");
        adam.step_sparse(&mut w, &[1.0, 0.0]).expect("step");
        // The second entry kept its value after the first step despite its momentum.
        assert!((w[1] - 0.9).abs() < 1e-5 && w[0] < 0.85, "{w:?}");
        let mut dense = vec![1.0f32, 1.0];
        let mut adam = Adam::new(AdamConfig { learning_rate: 0.1, ..AdamConfig::default() }, 2);
        adam.step(&mut dense, &[1.0, 1.0]).expect("step");
        adam.step(&mut dense, &[1.0, 0.0]).expect("step");
        assert!(dense[1] < 0.85, "{dense:?}");
    }

    #[test]
    fn decoupled_decay_shrinks_by_the_learning_rate_whatever_the_gradient() {
        // A zero gradient (dense step): only the decay moves the entry, by lr * decay per
        // step; the L2 penalty instead would move it by a full lr-sized Adam step.
        let config = AdamConfig { learning_rate: 0.1, decoupled_decay: 0.5, ..AdamConfig::default() };
        let mut w = vec![2.0f32, -4.0];
        let mut adam = Adam::new(config, 2);
        for _ in 0..10 {
            adam.step(&mut w, &[0.0, 0.0]).expect("step");
        }
        let expected = 0.95f32.powi(10);
        assert!((w[0] - 2.0 * expected).abs() < 1e-5 && (w[1] + 4.0 * expected).abs() < 1e-5, "{w:?}");
        // Sparse steps leave untouched entries alone, decay included.
        let mut w = vec![2.0f32, 2.0];
        let mut adam = Adam::new(config, 2);
        adam.step_sparse(&mut w, &[0.0, 1e-3]).expect("step");
        assert_eq!(w[0], 2.0);
        assert!((w[1] - (2.0 * 0.95 - 0.1)).abs() < 1e-5, "{w:?}");
    }

    #[test]
    fn weight_decay_pulls_towards_zero() {
        let mut w = vec![1.0f32; 2];
        let mut adam = Adam::new(AdamConfig { learning_rate: 0.01, weight_decay: 1.0, ..AdamConfig::default() }, 2);
        for _ in 0..300 {
            adam.step(&mut w, &[0.0, 0.0]).expect("step");
        }
        assert!(w[0] < 0.1, "{w:?}");
    }
}
