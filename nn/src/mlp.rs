//! Small fully-connected networks with hand-written fused forward and backward passes
//! (see the module documentation of [`crate`] for why).
//!
//! Layout: a batch is row-major (`n x width`). Each layer's weights are stored
//! **input-major** (`W^T`, `in x out`) followed by its bias (`out`), so that the forward pass
//! is, per row, `y = b; for k: y += x_k * W^T[k]` (a contiguous axpy the compiler
//! vectorises, skipped when `x_k` is 0, which ReLU makes true about half of the time), the
//! weight gradient is the same axpy transposed, and the input gradient is a dot product of
//! `W^T[k]` with the output gradient. Those row loops now serve only layers whose outputs do
//! not fill 16-wide register blocks (the small output layers; their weight gradient takes
//! [`crate::conv`]'s plain loop): the others run as 1x1 convolutions through
//! [`crate::conv`]'s tiles (4 rows x 16 outputs in registers, about 4x the row loop, which
//! loads and stores `y` once per input value).

use super::conv::{Image, dense_input_gradient, forward_rows, weight_gradient_rows};
use super::simd::{Simd, SimdMode, WithSimd, axpy, dot};
use super::{InitRng, NnError, check_len};

/// Maximum width of any layer (inputs, hidden or outputs); keeps a row in registers/L1.
pub const MAX_WIDTH: usize = 128;

/// Activation of the output layer (hidden layers are always ReLU).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// Identity.
    None,
    /// `max(x, 0)`.
    Relu,
    /// `1 / (1 + exp(-x))`.
    Sigmoid,
    /// Truncated exponential for densities (i-NGP): `exp(min(x, 15))`; its gradient is taken
    /// as the output itself everywhere, so that a saturated density can still come down.
    Exp,
    /// `ln(1 + exp(x))`.
    Softplus,
}

impl Activation {
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Activation::None => x,
            Activation::Relu => x.max(0.0),
            Activation::Sigmoid => 1.0 / (1.0 + (-x).exp()),
            Activation::Exp => x.min(15.0).exp(),
            Activation::Softplus => {
                if x > 15.0 {
                    x
                } else {
                    x.exp().ln_1p()
                }
            }
        }
    }

    /// Derivative expressed through the output `y = apply(x)`.
    #[inline]
    pub fn derivative_from_output(self, y: f32) -> f32 {
        match self {
            Activation::None => 1.0,
            Activation::Relu => {
                if y > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            Activation::Sigmoid => y * (1.0 - y),
            Activation::Exp => y,
            // d/dx ln(1 + e^x) = sigmoid(x) = 1 - e^{-y}.
            Activation::Softplus => -(-y).exp_m1(),
        }
    }

    /// Stable numeric code for files.
    pub fn code(self) -> u32 {
        match self {
            Activation::None => 0,
            Activation::Relu => 1,
            Activation::Sigmoid => 2,
            Activation::Exp => 3,
            Activation::Softplus => 4,
        }
    }

    pub fn from_code(code: u32) -> Option<Self> {
        Some(match code {
            0 => Activation::None,
            1 => Activation::Relu,
            2 => Activation::Sigmoid,
            3 => Activation::Exp,
            4 => Activation::Softplus,
            _ => return None,
        })
    }
}

/// Shape of a network: `input -> [hidden] x hidden_layers -> output`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MlpConfig {
    pub input: usize,
    pub hidden: usize,
    /// Hidden layers (0 gives a single linear layer).
    pub hidden_layers: usize,
    pub output: usize,
    pub output_activation: Activation,
}

impl MlpConfig {
    pub fn validate(&self) -> Result<(), NnError> {
        for (what, w) in [("input", self.input), ("hidden", self.hidden), ("output", self.output)] {
            if w == 0 || w > MAX_WIDTH {
                return Err(NnError::Config(format!("MLP {what} width {w} not in 1..={MAX_WIDTH}")));
            }
        }
        if self.hidden_layers > 8 {
            return Err(NnError::Config(format!("MLP with {} hidden layers (at most 8)", self.hidden_layers)));
        }
        Ok(())
    }

    /// `(in, out)` of every layer.
    fn layer_dims(&self) -> Vec<(usize, usize)> {
        let mut dims = Vec::with_capacity(self.hidden_layers + 1);
        let mut prev = self.input;
        for _ in 0..self.hidden_layers {
            dims.push((prev, self.hidden));
            prev = self.hidden;
        }
        dims.push((prev, self.output));
        dims
    }

    /// Multiply-adds of one row's forward pass (weights only; biases are additions).
    pub fn macs_per_row(&self) -> usize {
        self.layer_dims().iter().map(|(i, o)| i * o).sum()
    }

    /// Number of weights and biases.
    pub fn num_params(&self) -> usize {
        self.layer_dims().iter().map(|(i, o)| i * o + o).sum()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Layer {
    input: usize,
    output: usize,
    weights: usize,
    bias: usize,
}

/// A fully-connected network with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    config: MlpConfig,
    layers: Vec<Layer>,
    params: Vec<f32>,
    /// Instruction set of the passes (not a property of the function: not saved).
    simd: SimdMode,
}

/// Activations kept by [`Mlp::forward`] for [`Mlp::backward`], plus scratch; reuse one per
/// thread so that steady-state training allocates nothing.
#[derive(Debug, Clone, Default)]
pub struct MlpWorkspace {
    /// Post-activation outputs of every layer (`n x out`).
    outputs: Vec<Vec<f32>>,
    delta: Vec<f32>,
    delta_prev: Vec<f32>,
    rows: usize,
}

impl MlpWorkspace {
    pub fn new() -> Self {
        Self::default()
    }
}

impl Mlp {
    /// A network with weights drawn uniformly in `±sqrt(6 / (in + out))` (Glorot) and zero
    /// biases.
    pub fn new(config: MlpConfig, seed: u64) -> Result<Self, NnError> {
        let mut mlp = Self::zeros(config)?;
        let mut rng = InitRng::new(seed);
        for layer in mlp.layers.clone() {
            let bound = (6.0 / (layer.input + layer.output) as f32).sqrt();
            for w in &mut mlp.params[layer.weights..layer.weights + layer.input * layer.output] {
                *w = rng.uniform(bound);
            }
        }
        Ok(mlp)
    }

    /// A network with all parameters zero (for loading stored parameters).
    pub fn zeros(config: MlpConfig) -> Result<Self, NnError> {
        config.validate()?;
        let mut layers = Vec::new();
        let mut offset = 0;
        for (input, output) in config.layer_dims() {
            layers.push(Layer { input, output, weights: offset, bias: offset + input * output });
            offset += input * output + output;
        }
        Ok(Mlp { config, layers, params: vec![0.0; offset], simd: SimdMode::Auto })
    }

    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// Weights and biases, layer after layer (weights input-major, then bias).
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    pub fn num_params(&self) -> usize {
        self.params.len()
    }

    /// Chooses the instruction set of the forward and backward passes (default: the best
    /// the CPU has).
    pub fn set_simd(&mut self, simd: SimdMode) {
        self.simd = simd;
    }

    pub fn simd(&self) -> SimdMode {
        self.simd
    }

    /// One layer over `n` rows: `y = act(x W + b)`. A layer whose outputs fill whole
    /// register blocks is the 1x1 convolution of [`crate::conv`] over an image of `n x 1`
    /// (tiles of 4 rows x 16 outputs in registers, each weight vector loaded once per tile);
    /// others (the small output layers) take one row at a time.
    #[inline(always)]
    fn layer_forward<S: Simd>(&self, simd: S, layer: &Layer, act: Activation, x: &[f32], y: &mut [f32]) {
        let w = &self.params[layer.weights..layer.weights + layer.input * layer.output];
        let b = &self.params[layer.bias..layer.bias + layer.output];
        let image = Image::dense(layer.input, layer.output, x.len() / layer.input);
        if image.tiles_outputs::<S>() {
            forward_rows(simd, image, w, b, x, 0, y, act == Activation::Relu);
            if !matches!(act, Activation::None | Activation::Relu) {
                y.iter_mut().for_each(|v| *v = act.apply(*v));
            }
            return;
        }
        for (xr, yr) in x.chunks_exact(layer.input).zip(y.chunks_exact_mut(layer.output)) {
            yr.copy_from_slice(b);
            for (k, &xk) in xr.iter().enumerate() {
                if xk != 0.0 {
                    axpy(simd, yr, xk, &w[k * layer.output..(k + 1) * layer.output]);
                }
            }
            if act != Activation::None {
                for v in yr.iter_mut() {
                    *v = act.apply(*v);
                }
            }
        }
    }

    fn activation(&self, layer_index: usize) -> Activation {
        if layer_index + 1 == self.layers.len() { self.config.output_activation } else { Activation::Relu }
    }

    /// Forward pass over `input` (`n x config.input`, row-major) keeping the activations in
    /// `ws` for [`Mlp::backward`]; returns the outputs (`n x config.output`).
    pub fn forward<'w>(&self, input: &[f32], ws: &'w mut MlpWorkspace) -> Result<&'w [f32], NnError> {
        if !input.len().is_multiple_of(self.config.input) {
            return Err(NnError::Size {
                what: "MLP input",
                expected: input.len().div_ceil(self.config.input) * self.config.input,
                actual: input.len(),
            });
        }
        struct Op<'a> {
            mlp: &'a Mlp,
            input: &'a [f32],
            ws: &'a mut MlpWorkspace,
        }
        impl WithSimd for Op<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: Simd>(self, simd: S) {
                self.mlp.forward_in(simd, self.input, self.ws)
            }
        }
        self.simd.arch().dispatch(Op { mlp: self, input, ws });
        Ok(&ws.outputs[self.layers.len() - 1][..])
    }

    #[inline(always)]
    fn forward_in<S: Simd>(&self, simd: S, input: &[f32], ws: &mut MlpWorkspace) {
        let n = input.len() / self.config.input;
        ws.rows = n;
        ws.outputs.resize_with(self.layers.len(), Vec::new);
        for (i, layer) in self.layers.iter().enumerate() {
            let (before, rest) = ws.outputs.split_at_mut(i);
            let y = &mut rest[0];
            y.resize(n * layer.output, 0.0);
            let x = if i == 0 { input } else { &before[i - 1][..] };
            self.layer_forward(simd, layer, self.activation(i), x, y);
        }
    }

    /// Forward pass without keeping activations: `output` gets `n x config.output` values.
    /// `scratch` holds two hidden buffers between calls.
    pub fn infer(&self, input: &[f32], output: &mut [f32], scratch: &mut MlpWorkspace) -> Result<(), NnError> {
        let n = input.len() / self.config.input;
        check_len("MLP input", n * self.config.input, input.len())?;
        check_len("MLP output", n * self.config.output, output.len())?;
        struct Op<'a> {
            mlp: &'a Mlp,
            input: &'a [f32],
            output: &'a mut [f32],
            scratch: &'a mut MlpWorkspace,
        }
        impl WithSimd for Op<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: Simd>(self, simd: S) {
                self.mlp.infer_in(simd, self.input, self.output, self.scratch)
            }
        }
        self.simd.arch().dispatch(Op { mlp: self, input, output, scratch });
        Ok(())
    }

    #[inline(always)]
    fn infer_in<S: Simd>(&self, simd: S, input: &[f32], output: &mut [f32], scratch: &mut MlpWorkspace) {
        let n = input.len() / self.config.input;
        let last = self.layers.len() - 1;
        if last == 0 {
            self.layer_forward(simd, &self.layers[0], self.config.output_activation, input, output);
            return;
        }
        let (mut a, mut b) = (std::mem::take(&mut scratch.delta), std::mem::take(&mut scratch.delta_prev));
        a.resize(n * self.config.hidden, 0.0);
        b.resize(n * self.config.hidden, 0.0);
        self.layer_forward(simd, &self.layers[0], Activation::Relu, input, &mut a);
        for i in 1..last {
            self.layer_forward(simd, &self.layers[i], Activation::Relu, &a, &mut b);
            std::mem::swap(&mut a, &mut b);
        }
        self.layer_forward(simd, &self.layers[last], self.config.output_activation, &a, output);
        scratch.delta = a;
        scratch.delta_prev = b;
    }

    /// Backward pass after [`Mlp::forward`] on the same `input`: `d_output` is the loss's
    /// gradient with respect to the (post-activation) outputs. Accumulates (`+=`) parameter
    /// gradients into `grad` (`num_params()` values) and, if given, writes the gradient with
    /// respect to the input into `d_input` (`n x config.input`).
    pub fn backward(
        &self,
        input: &[f32],
        ws: &mut MlpWorkspace,
        d_output: &[f32],
        grad: &mut [f32],
        d_input: Option<&mut [f32]>,
    ) -> Result<(), NnError> {
        let n = ws.rows;
        check_len("MLP input (backward)", n * self.config.input, input.len())?;
        check_len("MLP output gradient", n * self.config.output, d_output.len())?;
        check_len("MLP parameter gradient", self.params.len(), grad.len())?;
        if let Some(d) = &d_input {
            check_len("MLP input gradient", n * self.config.input, d.len())?;
        }
        if ws.outputs.len() != self.layers.len() {
            return Err(NnError::Config("MLP backward without a forward pass".into()));
        }
        struct Op<'a> {
            mlp: &'a Mlp,
            input: &'a [f32],
            ws: &'a mut MlpWorkspace,
            d_output: &'a [f32],
            grad: &'a mut [f32],
            d_input: Option<&'a mut [f32]>,
        }
        impl WithSimd for Op<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: Simd>(self, simd: S) {
                self.mlp.backward_in(simd, self.input, self.ws, self.d_output, self.grad, self.d_input)
            }
        }
        self.simd.arch().dispatch(Op { mlp: self, input, ws, d_output, grad, d_input });
        Ok(())
    }

    #[inline(always)]
    fn backward_in<S: Simd>(
        &self,
        simd: S,
        input: &[f32],
        ws: &mut MlpWorkspace,
        d_output: &[f32],
        grad: &mut [f32],
        d_input: Option<&mut [f32]>,
    ) {
        let n = ws.rows;
        let last = self.layers.len() - 1;
        // delta = dL/dz of the last layer.
        let mut delta = std::mem::take(&mut ws.delta);
        let mut delta_prev = std::mem::take(&mut ws.delta_prev);
        delta.clear();
        let act = self.config.output_activation;
        delta.extend(d_output.iter().zip(&ws.outputs[last]).map(|(&g, &y)| g * act.derivative_from_output(y)));
        let mut d_input = d_input;
        for i in (0..=last).rev() {
            let layer = &self.layers[i];
            let x: &[f32] = if i == 0 { input } else { &ws.outputs[i - 1] };
            let (gw, gb) = grad[layer.weights..layer.bias + layer.output].split_at_mut(layer.input * layer.output);
            // Tiles where the outputs fill them, else the plain loop (`crate::conv` chooses).
            weight_gradient_rows(simd, Image::dense(layer.input, layer.output, n), x, 0, &delta, gw, gb);
            // Propagate to the layer's input unless it is the network input and nobody asked.
            let want_input = i > 0 || d_input.is_some();
            if !want_input {
                break;
            }
            let w = &self.params[layer.weights..layer.weights + layer.input * layer.output];
            delta_prev.clear();
            delta_prev.resize(n * layer.input, 0.0);
            if dense_input_gradient(simd, layer.input, layer.output, w, &delta, &mut delta_prev) {
                // Then ReLU's derivative: zero where the activation was not positive.
                if i > 0 {
                    delta_prev.iter_mut().zip(x).for_each(|(d, &xv)| {
                        if !(xv > 0.0) {
                            *d = 0.0;
                        }
                    });
                }
            } else {
                for (r, (dp, dr)) in
                    delta_prev.chunks_exact_mut(layer.input).zip(delta.chunks_exact(layer.output)).enumerate()
                {
                    if i > 0 {
                        // ReLU hidden: zero where the activation was zero.
                        let xr = &x[r * layer.input..(r + 1) * layer.input];
                        for (k, v) in dp.iter_mut().enumerate() {
                            if xr[k] > 0.0 {
                                *v = dot(simd, &w[k * layer.output..(k + 1) * layer.output], dr);
                            }
                        }
                    } else {
                        for (k, v) in dp.iter_mut().enumerate() {
                            *v = dot(simd, &w[k * layer.output..(k + 1) * layer.output], dr);
                        }
                    }
                }
            }
            if i == 0
                && let Some(d) = d_input.take()
            {
                d.copy_from_slice(&delta_prev);
            }
            std::mem::swap(&mut delta, &mut delta_prev);
        }
        ws.delta = delta;
        ws.delta_prev = delta_prev;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn config(act: Activation) -> MlpConfig {
        MlpConfig { input: 5, hidden: 16, hidden_layers: 2, output: 3, output_activation: act }
    }

    fn inputs(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = InitRng::new(seed);
        (0..n * 5).map(|_| rng.uniform(1.0)).collect()
    }

    #[test]
    fn infer_matches_forward_and_sizes_are_checked() {
        let mlp = Mlp::new(config(Activation::Sigmoid), 1).expect("mlp");
        let x = inputs(7, 2);
        let mut ws = MlpWorkspace::new();
        let y = mlp.forward(&x, &mut ws).expect("forward").to_vec();
        let mut out = vec![0.0; 21];
        mlp.infer(&x, &mut out, &mut MlpWorkspace::new()).expect("infer");
        assert_eq!(y, out);
        assert!(y.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(mlp.forward(&x[1..], &mut ws).is_err());
        assert!(mlp.infer(&x, &mut out[1..], &mut ws).is_err());
        assert_eq!(mlp.num_params(), 5 * 16 + 16 + 16 * 16 + 16 + 16 * 3 + 3);
        assert!(Mlp::new(MlpConfig { input: 0, ..config(Activation::None) }, 0).is_err());
        assert!(Mlp::new(MlpConfig { hidden: 1000, ..config(Activation::None) }, 0).is_err());
    }

    /// Checks parameter and input gradients of `L = sum r * f(x)` against central differences.
    fn check_gradients(act: Activation, hidden_layers: usize) {
        let cfg = MlpConfig { hidden_layers, ..config(act) };
        let mut mlp = Mlp::new(cfg, 11).expect("mlp");
        // Non-zero biases so that the bias gradients are exercised away from zero too.
        let mut rng = InitRng::new(4);
        for p in mlp.params_mut() {
            *p += rng.uniform(0.1);
        }
        let n = 6;
        let x = inputs(n, 3);
        let r: Vec<f32> = (0..n * 3).map(|_| rng.uniform(1.0)).collect();
        let loss = |m: &Mlp, x: &[f32]| {
            let mut out = vec![0.0; n * 3];
            m.infer(x, &mut out, &mut MlpWorkspace::new()).expect("infer");
            out.iter().zip(&r).map(|(a, b)| f64::from(*a) * f64::from(*b)).sum::<f64>()
        };
        let mut ws = MlpWorkspace::new();
        mlp.forward(&x, &mut ws).expect("forward");
        let mut grad = vec![0.0; mlp.num_params()];
        let mut d_input = vec![0.0; x.len()];
        mlp.backward(&x, &mut ws, &r, &mut grad, Some(&mut d_input)).expect("backward");
        let h = 5e-4f32;
        let close = |fd: f64, an: f32, what: &str| {
            assert!((fd - f64::from(an)).abs() < 2e-2 * (fd.abs() + 1e-1), "{act:?} {what}: fd {fd} analytic {an}");
        };
        for (i, &g) in grad.iter().enumerate() {
            let old = mlp.params[i];
            mlp.params[i] = old + h;
            let up = loss(&mlp, &x);
            mlp.params[i] = old - h;
            let down = loss(&mlp, &x);
            mlp.params[i] = old;
            close((up - down) / (2.0 * f64::from(h)), g, &format!("param {i}"));
        }
        for i in 0..x.len() {
            let mut xp = x.clone();
            xp[i] += h;
            let up = loss(&mlp, &xp);
            xp[i] -= 2.0 * h;
            let down = loss(&mlp, &xp);
            close((up - down) / (2.0 * f64::from(h)), d_input[i], &format!("input {i}"));
        }
        // Gradients accumulate.
        let mut again = grad.clone();
        mlp.forward(&x, &mut ws).expect("forward");
        mlp.backward(&x, &mut ws, &r, &mut again, None).expect("backward");
        for (a, g) in again.iter().zip(&grad) {
            assert!((a - 2.0 * g).abs() <= 1e-5 * (1.0 + g.abs()));
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        for act in [Activation::None, Activation::Sigmoid, Activation::Exp, Activation::Softplus, Activation::Relu] {
            check_gradients(act, 2);
        }
        check_gradients(Activation::Sigmoid, 0);
        check_gradients(Activation::None, 1);
    }

    /// A layer-by-layer reference in f64.
    fn naive_forward(mlp: &Mlp, x: &[f32]) -> Vec<f64> {
        let mut a: Vec<f64> = x.iter().map(|&v| f64::from(v)).collect();
        for (i, layer) in mlp.layers.iter().enumerate() {
            let act = mlp.activation(i);
            let rows = a.len() / layer.input;
            let mut y = vec![0.0f64; rows * layer.output];
            for r in 0..rows {
                for o in 0..layer.output {
                    let mut s = f64::from(mlp.params[layer.bias + o]);
                    for k in 0..layer.input {
                        s += a[r * layer.input + k] * f64::from(mlp.params[layer.weights + k * layer.output + o]);
                    }
                    y[r * layer.output + o] = f64::from(act.apply(s as f32));
                }
            }
            a = y;
        }
        a
    }

    #[test]
    fn wide_layers_agree_with_the_reference_and_between_vector_and_scalar_code() {
        // Layers of 64 and 16 outputs take the register-blocked tiles (with AVX2, and with the
        // scalar twin's 2-wide blocks); 13 rows leave a ragged last tile.
        let cfg =
            MlpConfig { input: 32, hidden: 64, hidden_layers: 2, output: 16, output_activation: Activation::Sigmoid };
        let mut mlp = Mlp::new(cfg, 5).expect("mlp");
        let n = 13;
        let mut rng = InitRng::new(7);
        let mut x: Vec<f32> = (0..n * 32).map(|_| rng.uniform(1.0)).collect();
        x.iter_mut().step_by(4).for_each(|v| *v = 0.0);
        let want = naive_forward(&mlp, &x);
        let r: Vec<f32> = (0..n * 16).map(|i| ((i * 37 % 19) as f32 - 9.0) / 9.0).collect();
        let mut results = Vec::new();
        for simd in [SimdMode::Auto, SimdMode::Off] {
            mlp.set_simd(simd);
            let mut ws = MlpWorkspace::new();
            let out = mlp.forward(&x, &mut ws).expect("forward").to_vec();
            for (i, (o, w)) in out.iter().zip(&want).enumerate() {
                assert!((f64::from(*o) - w).abs() < 1e-5, "{simd}: output {i} {o} vs {w}");
            }
            let mut inferred = vec![0.0; out.len()];
            mlp.infer(&x, &mut inferred, &mut MlpWorkspace::new()).expect("infer");
            assert_eq!(inferred, out, "{simd}: infer and forward");
            let mut grad = vec![0.0; mlp.num_params()];
            let mut d_input = vec![0.0; x.len()];
            mlp.backward(&x, &mut ws, &r, &mut grad, Some(&mut d_input)).expect("backward");
            results.push((grad, d_input));
        }
        let (auto, off) = (&results[0], &results[1]);
        for (a, b) in auto.0.iter().zip(&off.0).chain(auto.1.iter().zip(&off.1)) {
            assert!(a.is_finite() && (a - b).abs() <= 1e-4 * (1.0 + b.abs()), "gradients: {a} vs {b}");
        }
    }

    #[test]
    fn activation_codes_round_trip() {
        for act in [Activation::None, Activation::Relu, Activation::Sigmoid, Activation::Exp, Activation::Softplus] {
            assert_eq!(Activation::from_code(act.code()), Some(act));
        }
        assert_eq!(Activation::from_code(99), None);
        assert!(Activation::Exp.apply(1e30).is_finite());
        assert!(Activation::Softplus.apply(1e30).is_finite());
        assert_eq!(Activation::Sigmoid.apply(-1e30), 0.0);
    }

    proptest! {
        #[test]
        fn outputs_are_finite_for_bounded_inputs(v in prop::collection::vec(-1e4f32..1e4, 10), act in 0u32..5) {
            let act = Activation::from_code(act).expect("code");
            let mlp = Mlp::new(config(act), 21).expect("mlp");
            let mut out = vec![0.0; 6];
            mlp.infer(&v, &mut out, &mut MlpWorkspace::new()).expect("infer");
            prop_assert!(out.iter().all(|y| y.is_finite()));
        }
    }
}
