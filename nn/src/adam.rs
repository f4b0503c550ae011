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

    /// Checks the lengths, counts the step and returns its constants.
    fn begin_step(&mut self, params: usize, grads: usize) -> Result<StepConstants, NnError> {
        check_len("Adam parameters", self.m.len(), params)?;
        check_len("Adam gradients", self.m.len(), grads)?;
        self.steps += 1;
        Ok(StepConstants::new(&self.config, self.steps))
    }

    fn update(&mut self, params: &mut [f32], grads: &[f32], sparse: bool) -> Result<(), NnError> {
        let k = self.begin_step(params.len(), grads.len())?;
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks(CHUNK))
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .for_each(|(((p, g), m), v)| {
                for i in 0..p.len() {
                    if sparse && g[i] == 0.0 {
                        continue;
                    }
                    k.apply(&mut p[i], &mut m[i], &mut v[i], g[i]);
                }
            });
        Ok(())
    }
}

/// The constants of one Adam step.
#[derive(Debug, Clone, Copy)]
struct StepConstants {
    beta1: f32,
    beta2: f32,
    weight_decay: f32,
    step_size: f32,
    epsilon: f32,
    shrink: f32,
}

impl StepConstants {
    /// Those of step `t` (from 1).
    fn new(c: &AdamConfig, t: u64) -> StepConstants {
        // Bias corrections folded into the step size (the paper's "efficient version").
        let t = t.min(i32::MAX as u64) as i32;
        let correction1 = 1.0 - c.beta1.powi(t);
        let correction2 = 1.0 - c.beta2.powi(t);
        StepConstants {
            beta1: c.beta1,
            beta2: c.beta2,
            weight_decay: c.weight_decay,
            step_size: c.learning_rate * correction2.sqrt() / correction1,
            epsilon: c.epsilon * correction2.sqrt(),
            shrink: 1.0 - c.learning_rate * c.decoupled_decay,
        }
    }

    /// One entry's update.
    #[inline(always)]
    fn apply(&self, p: &mut f32, m: &mut f32, v: &mut f32, mut grad: f32) {
        if !grad.is_finite() {
            // A non-finite gradient would poison the moments for good.
            return;
        }
        if self.weight_decay != 0.0 {
            grad += self.weight_decay * *p;
        }
        *m = self.beta1 * *m + (1.0 - self.beta1) * grad;
        *v = self.beta2 * *v + (1.0 - self.beta2) * grad * grad;
        *p = self.shrink * *p - self.step_size * *m / (v.sqrt() + self.epsilon);
    }
}

/// Adam over a table whose steps each touch a few of its entries (the i-NOLF heads' hash grid
/// and PSH features), computing what dense [`Adam`] computes while paying only for the
/// touched entries. In dense Adam an entry that no gradient reaches still moves, on its
/// momentum: per step `m <- b1 m`, `v <- b2 v`, `p <- s p - a m / sqrt(v)` (`a` the step
/// size, `s` the decoupled decay's shrink). Over `k` such steps that is, in closed form,
/// `m <- b1^k m`, `v <- b2^k v` and `p <- s^k p - a (m / sqrt(v)) r (s^k - r^k) / (s - r)`
/// with `r = b1 / sqrt(b2)` (the sum of `s^(k-j) r^j` over `j = 1..k`). An entry catches up
/// so when a gradient next reaches it, and every entry at [`LazyAdam::flush`], which
/// [`LazyAdam::set_learning_rate`] calls when the rate changes; call it before reading the
/// parameters. Two approximations, both negligible after the first hundred steps: the
/// catch-up takes the bias-corrected step size of the step after the entry's last update
/// for all of its skipped steps, and drops epsilon. On the i-NOLF heads (11 million table
/// entries, a few percent touched per step) the lazy steps reach dense Adam's training loss
/// and held-out PSNR to the digits printed, and the heads train 2.2x faster (BENCHMARKS.md,
/// 2026-12-07e). Plain sparse steps ([`Adam::step_sparse`]: no momentum for untouched
/// entries) are cheaper still but train differently: on the heads they cost 0.16 dB.
#[derive(Debug, Clone)]
pub struct LazyAdam {
    config: AdamConfig,
    m: Vec<f32>,
    v: Vec<f32>,
    /// The step each entry was last brought up to date at (0: never; its moments are zero).
    last: Vec<u32>,
    steps: u32,
    /// The catch-up's powers and step sizes, tabled: per touched entry they were most of a
    /// lazy step's time.
    tables: CatchUpTables,
}

impl LazyAdam {
    /// Refuses an L2 weight decay (`AdamConfig::weight_decay`): it gives every entry a
    /// gradient at every step. Decoupled decay is fine.
    pub fn new(config: AdamConfig, len: usize) -> Result<Self, NnError> {
        if config.weight_decay != 0.0 {
            return Err(NnError::Config(
                "an L2 weight decay reaches every entry at every step: lazy Adam cannot skip any".into(),
            ));
        }
        let tables = CatchUpTables::new(&config);
        Ok(LazyAdam { config, m: vec![0.0; len], v: vec![0.0; len], last: vec![0; len], steps: 0, tables })
    }

    /// Changes the learning rate of the steps to come; when it differs, first brings every
    /// entry of `params` up to date at the old rate.
    pub fn set_learning_rate(&mut self, params: &mut [f32], learning_rate: f32) -> Result<(), NnError> {
        if learning_rate != self.config.learning_rate {
            self.flush(params)?;
            self.config.learning_rate = learning_rate;
            self.tables = CatchUpTables::new(&self.config);
        }
        Ok(())
    }

    /// One step: every entry whose gradient is non-zero catches up on the steps it missed and
    /// takes this one; the gradients are set back to zero on the way (only the touched ones
    /// are written). A non-finite gradient is dropped.
    pub fn step(&mut self, params: &mut [f32], grads: &mut [f32]) -> Result<(), NnError> {
        check_len("Adam parameters", self.m.len(), params.len())?;
        check_len("Adam gradients", self.m.len(), grads.len())?;
        self.steps = self.steps.checked_add(1).ok_or_else(|| NnError::Config("too many steps".into()))?;
        let t = self.steps;
        let now = StepConstants::new(&self.config, u64::from(t));
        let tables = &self.tables;
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks_mut(CHUNK))
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .zip(self.last.par_chunks_mut(CHUNK))
            .for_each(|((((p, g), m), v), last)| {
                for i in 0..p.len() {
                    if g[i] == 0.0 {
                        continue;
                    }
                    let grad = std::mem::replace(&mut g[i], 0.0);
                    if !grad.is_finite() {
                        continue;
                    }
                    tables.catch_up(&mut p[i], &mut m[i], &mut v[i], last[i], t - 1);
                    now.apply(&mut p[i], &mut m[i], &mut v[i], grad);
                    last[i] = t;
                }
            });
        Ok(())
    }

    /// Brings every entry up to date with the steps taken: afterwards `params` is what dense
    /// Adam would hold.
    pub fn flush(&mut self, params: &mut [f32]) -> Result<(), NnError> {
        check_len("Adam parameters", self.m.len(), params.len())?;
        let t = self.steps;
        let tables = &self.tables;
        params
            .par_chunks_mut(CHUNK)
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .zip(self.last.par_chunks_mut(CHUNK))
            .for_each(|(((p, m), v), last)| {
                for i in 0..p.len() {
                    tables.catch_up(&mut p[i], &mut m[i], &mut v[i], last[i], t);
                    last[i] = t;
                }
            });
        Ok(())
    }
}

/// Gaps (in steps) whose powers are tabled; a longer one computes them.
const POWER_TABLE: usize = 1024;
/// Steps whose bias-corrected step size is tabled.
const STEP_SIZE_TABLE: usize = 4096;

/// What [`LazyAdam`]'s catch-up needs at one learning rate.
#[derive(Debug, Clone)]
struct CatchUpTables {
    config: AdamConfig,
    /// `r = beta1 / sqrt(beta2)`.
    r: f32,
    /// The decoupled decay's factor per step.
    shrink: f32,
    /// `[r^k, beta1^k, beta2^k, shrink^k]` for gaps `k < POWER_TABLE`.
    powers: Vec<[f32; 4]>,
    /// The bias-corrected step size of steps `u < STEP_SIZE_TABLE`.
    step_sizes: Vec<f32>,
}

impl CatchUpTables {
    fn new(c: &AdamConfig) -> CatchUpTables {
        let r = c.beta1 / c.beta2.sqrt();
        let shrink = 1.0 - c.learning_rate * c.decoupled_decay;
        let power = |k: usize| {
            let k = k as i32;
            [r.powi(k), c.beta1.powi(k), c.beta2.powi(k), shrink.powi(k)]
        };
        let powers = (0..POWER_TABLE).map(power).collect();
        let step_sizes = (0..STEP_SIZE_TABLE).map(|u| StepConstants::new(c, u.max(1) as u64).step_size).collect();
        CatchUpTables { config: *c, r, shrink, powers, step_sizes }
    }

    /// Dense Adam's steps `last + 1 ..= until` of an entry without gradient, in closed form
    /// (see [`LazyAdam`]).
    #[inline(always)]
    fn catch_up(&self, p: &mut f32, m: &mut f32, v: &mut f32, last: u32, until: u32) {
        if until <= last {
            return;
        }
        let k = until - last;
        let [r_k, beta1_k, beta2_k, shrink_k] = match self.powers.get(k as usize) {
            Some(p) => *p,
            None => {
                let k = k.min(i32::MAX as u32) as i32;
                let c = &self.config;
                [self.r.powi(k), c.beta1.powi(k), c.beta2.powi(k), self.shrink.powi(k)]
            }
        };
        if *v > 0.0 {
            let next = last as usize + 1;
            let step_size = match self.step_sizes.get(next) {
                Some(s) => *s,
                None => StepConstants::new(&self.config, next as u64).step_size,
            };
            let (r, shrink) = (self.r, self.shrink);
            // The sum of shrink^(k - j) r^j over j = 1..k (k r^k when the two are equal).
            let sum = if (shrink - r).abs() > 1e-6 { r * (shrink_k - r_k) / (shrink - r) } else { k as f32 * r_k };
            *p = shrink_k * *p - step_size * (*m / v.sqrt()) * sum;
        } else {
            *p *= shrink_k;
        }
        *m *= beta1_k;
        *v *= beta2_k;
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

    /// Random sparse gradients: a tenth of the entries touched per step, one NaN.
    fn sparse_gradients(n: usize, steps: usize) -> Vec<Vec<f32>> {
        let mut rng = nephele_geometry::SplitMix64::new(7);
        (0..steps)
            .map(|s| {
                let mut g: Vec<f32> =
                    (0..n).map(|_| if rng.next_f32() < 0.1 { rng.next_f32() - 0.4 } else { 0.0 }).collect();
                if s == 50 {
                    g[3] = f32::NAN;
                }
                g
            })
            .collect()
    }

    #[test]
    fn lazy_adam_computes_what_dense_adam_computes() {
        let n = CHUNK + 33;
        let config = AdamConfig { learning_rate: 0.01, decoupled_decay: 0.1, ..AdamConfig::default() };
        let init: Vec<f32> = (0..n).map(|i| ((i * 37) % 101) as f32 / 101.0 - 0.5).collect();
        let (mut dense, mut lazy) = (init.clone(), init.clone());
        let mut adam_dense = Adam::new(config, n);
        let mut adam_lazy = LazyAdam::new(config, n).expect("no L2 decay");
        // Past the bias correction's first thousand steps (where the catch-up's single step
        // size is an approximation), with every entry touched: the two agree to rounding.
        let mut rng = nephele_geometry::SplitMix64::new(3);
        for _ in 0..1500 {
            let g: Vec<f32> = (0..n).map(|_| rng.next_f32() - 0.5).collect();
            adam_dense.step(&mut dense, &g).expect("step");
            adam_lazy.step(&mut lazy, &mut g.clone()).expect("step");
        }
        let init = dense.clone();
        let (mut lazy, mut sparse) = (dense.clone(), dense.clone());
        let mut adam_sparse = adam_dense.clone();
        let grads = sparse_gradients(n, 400);
        for (s, g) in grads.iter().enumerate() {
            // A schedule: the rate drops after half the steps.
            let lr = if s < 200 { 0.01 } else { 0.003 };
            adam_dense.set_learning_rate(lr);
            adam_sparse.set_learning_rate(lr);
            adam_lazy.set_learning_rate(&mut lazy, lr).expect("flush");
            adam_dense.step(&mut dense, g).expect("step");
            adam_sparse.step_sparse(&mut sparse, g).expect("step");
            let mut g = g.clone();
            adam_lazy.step(&mut lazy, &mut g).expect("step");
            assert!(g.iter().all(|&x| x == 0.0), "gradients left after step {s}");
        }
        adam_lazy.flush(&mut lazy).expect("flush");
        // The NaN's entry (3) differs by one step of momentum (dense Adam skips that entry's
        // step entirely); every other within rounding and the bias-correction approximation.
        let max_diff = |a: &[f32]| {
            a.iter()
                .zip(&dense)
                .enumerate()
                .filter(|(i, _)| *i != 3)
                .map(|(_, (x, y))| (x - y).abs())
                .fold(0.0f32, f32::max)
        };
        let travel = init.iter().zip(&dense).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        let lazy_diff = max_diff(&lazy);
        assert!(lazy_diff < 2e-3 * travel, "lazy differs by {lazy_diff} (entries moved up to {travel})");
        // Plain sparse steps train differently: the comparison can tell.
        assert!(max_diff(&sparse) > 20.0 * lazy_diff, "sparse {} lazy {lazy_diff}", max_diff(&sparse));
        assert!(LazyAdam::new(AdamConfig { weight_decay: 1e-3, ..config }, 4).is_err());
        assert!(adam_lazy.step(&mut lazy, &mut [0.0; 2]).is_err());
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
