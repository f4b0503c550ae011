//! A deep residual MLP (R2L's network, Wang et al. 2022, section 3.2): an input layer to the
//! width, `blocks` residual blocks of two fully-connected layers, and an output layer, with
//! hand-written fused forward and backward passes in the manner of [`crate::mlp`].
//!
//! ```text
//! h_0     = relu(x W_in + b_in)
//! h_{k+1} = h_k + relu(h_k W1_k + b1_k) W2_k + b2_k        k = 0 .. blocks
//! y       = act(relu(h_blocks) W_out + b_out)
//! ```
//!
//! The skip path carries the stream unchanged, so gradients reach the first layers of a deep
//! network undiminished; the second layer of every block starts scaled by
//! `1 / sqrt(blocks)` so that the stream's variance does not grow with depth at
//! initialisation. Layout as in [`crate::mlp`]: row-major batches, weights input-major
//! followed by the bias, all layers in one parameter vector (input layer, blocks in order
//! with their two layers, output layer).

use super::conv::{Image, dense_input_gradient, forward_rows, weight_gradient_rows};
use super::simd::{Simd, SimdMode, WithSimd, axpy, dot};
use super::{Activation, InitRng, NnError, check_len};

/// Widest input accepted (K points x a positional encoding).
pub const MAX_INPUT: usize = 4096;
/// Widest hidden layer accepted.
pub const MAX_RESIDUAL_WIDTH: usize = 512;
/// Deepest network accepted (R2L's deepest has 44 blocks, 88 layers).
pub const MAX_BLOCKS: usize = 64;

/// Shape of a residual network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ResidualMlpConfig {
    pub input: usize,
    /// Width of the stream and of every hidden layer.
    pub width: usize,
    /// Residual blocks (two layers each); 0 gives input layer -> output layer.
    pub blocks: usize,
    pub output: usize,
    #[serde(with = "activation_code")]
    pub output_activation: Activation,
}

mod activation_code {
    use super::Activation;
    pub fn serialize<S: serde::Serializer>(a: &Activation, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u32(a.code())
    }
    pub fn deserialize<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Activation, D::Error> {
        let code = <u32 as serde::Deserialize>::deserialize(d)?;
        Activation::from_code(code).ok_or_else(|| serde::de::Error::custom(format!("activation code {code}")))
    }
}

impl ResidualMlpConfig {
    pub fn validate(&self) -> Result<(), NnError> {
        let check = |what: &str, v: usize, max: usize| {
            if v == 0 || v > max {
                Err(NnError::Config(format!("residual MLP {what} {v} not in 1..={max}")))
            } else {
                Ok(())
            }
        };
        check("input width", self.input, MAX_INPUT)?;
        check("width", self.width, MAX_RESIDUAL_WIDTH)?;
        check("output width", self.output, MAX_RESIDUAL_WIDTH)?;
        if self.blocks > MAX_BLOCKS {
            return Err(NnError::Config(format!("residual MLP with {} blocks (at most {MAX_BLOCKS})", self.blocks)));
        }
        Ok(())
    }

    /// `(in, out)` of every layer, in parameter order.
    fn layer_dims(&self) -> Vec<(usize, usize)> {
        let mut dims = vec![(self.input, self.width)];
        for _ in 0..2 * self.blocks {
            dims.push((self.width, self.width));
        }
        dims.push((self.width, self.output));
        dims
    }

    /// Fully-connected layers (R2L counts depth in layers: W256D88 has 44 blocks).
    pub fn layers(&self) -> usize {
        2 * self.blocks + 2
    }

    /// Multiply-adds of one row's forward pass (weights only).
    pub fn macs_per_row(&self) -> usize {
        self.layer_dims().iter().map(|(i, o)| i * o).sum()
    }

    /// Floating-point operations of one row's forward pass: a multiply and an add per
    /// weight, an add per bias and per skip connection (activations not counted).
    pub fn flops_per_row(&self) -> usize {
        2 * self.macs_per_row() + self.layer_dims().iter().map(|(_, o)| o).sum::<usize>() + self.blocks * self.width
    }

    pub fn num_params(&self) -> usize {
        self.layer_dims().iter().map(|(i, o)| i * o + o).sum()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Dense {
    input: usize,
    output: usize,
    weights: usize,
    bias: usize,
}

impl Dense {
    fn weights<'p>(&self, params: &'p [f32]) -> &'p [f32] {
        &params[self.weights..self.weights + self.input * self.output]
    }
    fn bias<'p>(&self, params: &'p [f32]) -> &'p [f32] {
        &params[self.bias..self.bias + self.output]
    }

    /// `y = x W + b` over all rows (`add` keeps `y` and adds to it: the skip connection).
    /// Layers whose outputs fill whole register blocks take [`crate::conv`]'s tiles.
    #[inline(always)]
    fn forward<S: Simd>(&self, simd: S, params: &[f32], x: &[f32], y: &mut [f32], add: bool) {
        let (w, b) = (self.weights(params), self.bias(params));
        let image = Image::dense(self.input, self.output, x.len() / self.input);
        if image.tiles_outputs::<S>() {
            if add {
                let mut sum = vec![0.0f32; y.len()];
                forward_rows(simd, image, w, b, x, 0, &mut sum, false);
                y.iter_mut().zip(&sum).for_each(|(y, s)| *y += s);
            } else {
                forward_rows(simd, image, w, b, x, 0, y, false);
            }
            return;
        }
        for (xr, yr) in x.chunks_exact(self.input).zip(y.chunks_exact_mut(self.output)) {
            if add {
                axpy(simd, yr, 1.0, b);
            } else {
                yr.copy_from_slice(b);
            }
            for (k, &xk) in xr.iter().enumerate() {
                if xk != 0.0 {
                    axpy(simd, yr, xk, &w[k * self.output..(k + 1) * self.output]);
                }
            }
        }
    }

    /// Accumulates the parameter gradients of `y = x W + b` for the output gradient `dy`
    /// and, if asked, writes `dx = dy W^T` (or adds it with `add_dx`).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)] // one layer's buffers; a struct would only rename them
    fn backward<S: Simd>(
        &self,
        simd: S,
        params: &[f32],
        x: &[f32],
        dy: &[f32],
        grad: &mut [f32],
        dx: Option<&mut [f32]>,
        add_dx: bool,
    ) {
        let (gw, gb) = grad[self.weights..self.bias + self.output].split_at_mut(self.input * self.output);
        // Tiles where the outputs fill them, else the plain loop (`crate::conv` chooses).
        weight_gradient_rows(simd, Image::dense(self.input, self.output, x.len() / self.input), x, 0, dy, gw, gb);
        if let Some(dx) = dx {
            let w = self.weights(params);
            if add_dx {
                let mut g = vec![0.0f32; dx.len()];
                if dense_input_gradient(simd, self.input, self.output, w, dy, &mut g) {
                    dx.iter_mut().zip(&g).for_each(|(d, g)| *d += g);
                    return;
                }
            } else if dense_input_gradient(simd, self.input, self.output, w, dy, dx) {
                return;
            }
            for (dxr, dr) in dx.chunks_exact_mut(self.input).zip(dy.chunks_exact(self.output)) {
                for (k, v) in dxr.iter_mut().enumerate() {
                    let g = dot(simd, &w[k * self.output..(k + 1) * self.output], dr);
                    *v = if add_dx { *v + g } else { g };
                }
            }
        }
    }
}

/// A residual network with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct ResidualMlp {
    config: ResidualMlpConfig,
    layers: Vec<Dense>,
    params: Vec<f32>,
    simd: SimdMode,
}

/// Activations of [`ResidualMlp::forward`] kept for [`ResidualMlp::backward`], and scratch;
/// one per thread, so that steady-state training allocates nothing.
#[derive(Debug, Clone, Default)]
pub struct ResidualWorkspace {
    /// The stream after the input layer and after every block (`blocks + 1` of `n x width`).
    stream: Vec<Vec<f32>>,
    /// The hidden activation inside every block.
    inner: Vec<Vec<f32>>,
    /// `relu(h_blocks)`, the output layer's input.
    head_input: Vec<f32>,
    output: Vec<f32>,
    d_stream: Vec<f32>,
    d_inner: Vec<f32>,
    d_head: Vec<f32>,
    rows: usize,
}

impl ResidualWorkspace {
    pub fn new() -> Self {
        Self::default()
    }
}

fn relu_in_place(v: &mut [f32]) {
    for x in v {
        *x = x.max(0.0);
    }
}

impl ResidualMlp {
    /// A network with Glorot-uniform weights (the second layer of every block scaled by
    /// `1 / sqrt(blocks)`) and zero biases, deterministic for `seed`.
    pub fn new(config: ResidualMlpConfig, seed: u64) -> Result<Self, NnError> {
        let mut net = Self::zeros(config)?;
        let mut rng = InitRng::new(seed ^ 0x7232_6c5f_7265_736e);
        let damp = 1.0 / (config.blocks.max(1) as f32).sqrt();
        for (i, layer) in net.layers.clone().into_iter().enumerate() {
            let second_of_block = i > 0 && i + 1 < net.layers.len() && i % 2 == 0;
            let bound = (6.0 / (layer.input + layer.output) as f32).sqrt() * if second_of_block { damp } else { 1.0 };
            for w in &mut net.params[layer.weights..layer.weights + layer.input * layer.output] {
                *w = rng.uniform(bound);
            }
        }
        Ok(net)
    }

    /// A network with all parameters zero (for loading stored parameters).
    pub fn zeros(config: ResidualMlpConfig) -> Result<Self, NnError> {
        config.validate()?;
        let mut layers = Vec::new();
        let mut offset = 0;
        for (input, output) in config.layer_dims() {
            layers.push(Dense { input, output, weights: offset, bias: offset + input * output });
            offset += input * output + output;
        }
        Ok(ResidualMlp { config, layers, params: vec![0.0; offset], simd: SimdMode::Auto })
    }

    /// A network with the given parameters (checked for count and finiteness).
    pub fn from_params(config: ResidualMlpConfig, params: Vec<f32>) -> Result<Self, NnError> {
        let mut net = Self::zeros(config)?;
        check_len("residual MLP parameters", net.params.len(), params.len())?;
        if let Some(i) = params.iter().position(|v| !v.is_finite()) {
            return Err(NnError::Config(format!("residual MLP parameter {i} is not finite")));
        }
        net.params = params;
        Ok(net)
    }

    pub fn config(&self) -> &ResidualMlpConfig {
        &self.config
    }

    pub fn params(&self) -> &[f32] {
        &self.params
    }

    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    pub fn set_simd(&mut self, simd: SimdMode) {
        self.simd = simd;
    }

    fn blocks(&self) -> impl Iterator<Item = (&Dense, &Dense)> {
        let inner = &self.layers[1..self.layers.len() - 1];
        inner.chunks_exact(2).map(|pair| (&pair[0], &pair[1]))
    }

    fn output_layer(&self) -> &Dense {
        &self.layers[self.layers.len() - 1]
    }

    fn rows_of(&self, input: &[f32]) -> Result<usize, NnError> {
        let n = input.len() / self.config.input;
        check_len("residual MLP input", n * self.config.input, input.len())?;
        Ok(n)
    }

    /// Forward pass over `input` (`n x config.input`, row-major), keeping the activations in
    /// `ws` for [`ResidualMlp::backward`]; returns the outputs (`n x config.output`).
    pub fn forward<'w>(&self, input: &[f32], ws: &'w mut ResidualWorkspace) -> Result<&'w [f32], NnError> {
        let n = self.rows_of(input)?;
        struct Op<'a> {
            net: &'a ResidualMlp,
            input: &'a [f32],
            ws: &'a mut ResidualWorkspace,
            n: usize,
        }
        impl WithSimd for Op<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: Simd>(self, simd: S) {
                self.net.forward_in(simd, self.input, self.ws, self.n)
            }
        }
        self.simd.arch().dispatch(Op { net: self, input, ws, n });
        Ok(&ws.output)
    }

    #[inline(always)]
    fn forward_in<S: Simd>(&self, simd: S, input: &[f32], ws: &mut ResidualWorkspace, n: usize) {
        let (width, blocks) = (self.config.width, self.config.blocks);
        ws.rows = n;
        ws.stream.resize_with(blocks + 1, Vec::new);
        ws.inner.resize_with(blocks, Vec::new);
        let h0 = &mut ws.stream[0];
        h0.resize(n * width, 0.0);
        self.layers[0].forward(simd, &self.params, input, h0, false);
        relu_in_place(h0);
        for (k, (first, second)) in self.blocks().enumerate() {
            let (before, after) = ws.stream.split_at_mut(k + 1);
            let (h, next) = (&before[k], &mut after[0]);
            let a = &mut ws.inner[k];
            a.resize(n * width, 0.0);
            first.forward(simd, &self.params, h, a, false);
            relu_in_place(a);
            next.clear();
            next.extend_from_slice(h);
            second.forward(simd, &self.params, a, next, true);
        }
        ws.head_input.clear();
        ws.head_input.extend(ws.stream[blocks].iter().map(|v| v.max(0.0)));
        ws.output.resize(n * self.config.output, 0.0);
        self.output_layer().forward(simd, &self.params, &ws.head_input, &mut ws.output, false);
        let act = self.config.output_activation;
        if act != Activation::None {
            for v in &mut ws.output {
                *v = act.apply(*v);
            }
        }
    }

    /// Forward pass without gradients: `output` gets `n x config.output` values.
    pub fn infer(&self, input: &[f32], output: &mut [f32], ws: &mut ResidualWorkspace) -> Result<(), NnError> {
        let n = self.rows_of(input)?;
        check_len("residual MLP output", n * self.config.output, output.len())?;
        let out = self.forward(input, ws)?;
        output.copy_from_slice(out);
        Ok(())
    }

    /// Backward pass after [`ResidualMlp::forward`] on the same `input`: `d_output` is the
    /// loss's gradient with respect to the (post-activation) outputs. Accumulates (`+=`)
    /// the parameter gradients into `grad` (`params().len()` values).
    pub fn backward(
        &self,
        input: &[f32],
        ws: &mut ResidualWorkspace,
        d_output: &[f32],
        grad: &mut [f32],
    ) -> Result<(), NnError> {
        let n = ws.rows;
        check_len("residual MLP input (backward)", n * self.config.input, input.len())?;
        check_len("residual MLP output gradient", n * self.config.output, d_output.len())?;
        check_len("residual MLP parameter gradient", self.params.len(), grad.len())?;
        if ws.stream.len() != self.config.blocks + 1 || ws.output.len() != n * self.config.output {
            return Err(NnError::Config("residual MLP backward without a matching forward pass".into()));
        }
        struct Op<'a> {
            net: &'a ResidualMlp,
            input: &'a [f32],
            ws: &'a mut ResidualWorkspace,
            d_output: &'a [f32],
            grad: &'a mut [f32],
        }
        impl WithSimd for Op<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: Simd>(self, simd: S) {
                self.net.backward_in(simd, self.input, self.ws, self.d_output, self.grad)
            }
        }
        self.simd.arch().dispatch(Op { net: self, input, ws, d_output, grad });
        Ok(())
    }

    #[inline(always)]
    fn backward_in<S: Simd>(
        &self,
        simd: S,
        input: &[f32],
        ws: &mut ResidualWorkspace,
        d_output: &[f32],
        grad: &mut [f32],
    ) {
        let (n, width, blocks) = (ws.rows, self.config.width, self.config.blocks);
        let act = self.config.output_activation;
        // dL/dz of the output layer.
        let mut d_head = std::mem::take(&mut ws.d_head);
        d_head.clear();
        d_head.extend(d_output.iter().zip(&ws.output).map(|(&g, &y)| g * act.derivative_from_output(y)));
        // dL/d(relu(h_blocks)), then through the ReLU: dL/dh_blocks.
        let mut d_stream = std::mem::take(&mut ws.d_stream);
        d_stream.resize(n * width, 0.0);
        self.output_layer().backward(simd, &self.params, &ws.head_input, &d_head, grad, Some(&mut d_stream), false);
        for (d, &h) in d_stream.iter_mut().zip(&ws.stream[blocks]) {
            if h <= 0.0 {
                *d = 0.0;
            }
        }
        let mut d_inner = std::mem::take(&mut ws.d_inner);
        d_inner.resize(n * width, 0.0);
        let pairs: Vec<(&Dense, &Dense)> = self.blocks().collect();
        for k in (0..blocks).rev() {
            let (first, second) = pairs[k];
            // h_{k+1} = h_k + relu(h_k W1 + b1) W2 + b2: the skip passes d_stream through.
            second.backward(simd, &self.params, &ws.inner[k], &d_stream, grad, Some(&mut d_inner), false);
            for (d, &a) in d_inner.iter_mut().zip(&ws.inner[k]) {
                if a <= 0.0 {
                    *d = 0.0;
                }
            }
            first.backward(simd, &self.params, &ws.stream[k], &d_inner, grad, Some(&mut d_stream), true);
        }
        // h_0 = relu(x W_in + b_in).
        for (d, &h) in d_stream.iter_mut().zip(&ws.stream[0]) {
            if h <= 0.0 {
                *d = 0.0;
            }
        }
        self.layers[0].backward(simd, &self.params, input, &d_stream, grad, None, false);
        ws.d_head = d_head;
        ws.d_stream = d_stream;
        ws.d_inner = d_inner;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(blocks: usize, act: Activation) -> ResidualMlpConfig {
        ResidualMlpConfig { input: 7, width: 12, blocks, output: 4, output_activation: act }
    }

    fn inputs(n: usize, width: usize, seed: u64) -> Vec<f32> {
        let mut rng = InitRng::new(seed);
        (0..n * width).map(|_| rng.uniform(1.5)).collect()
    }

    /// Loss `sum_j c_j y_j` with fixed random `c`, so that every output matters.
    fn loss(net: &ResidualMlp, x: &[f32], c: &[f32]) -> f64 {
        let mut ws = ResidualWorkspace::new();
        let y = net.forward(x, &mut ws).expect("forward");
        y.iter().zip(c).map(|(&a, &b)| f64::from(a) * f64::from(b)).sum()
    }

    fn check_gradients(blocks: usize, act: Activation, simd: SimdMode) {
        check_gradients_of(config(blocks, act), simd);
    }

    fn check_gradients_of(config: ResidualMlpConfig, simd: SimdMode) {
        let (blocks, act) = (config.blocks, config.output_activation);
        let mut net = ResidualMlp::new(config, 3).expect("net");
        net.set_simd(simd);
        // Biases away from zero so that the ReLUs are not all at their kink.
        for (i, p) in net.params_mut().iter_mut().enumerate() {
            if *p == 0.0 {
                *p = 0.05 * ((i % 7) as f32 - 3.0);
            }
        }
        let n = 5;
        let x = inputs(n, 7, 9);
        let c = inputs(n, 4, 11);
        let mut ws = ResidualWorkspace::new();
        net.forward(&x, &mut ws).expect("forward");
        let mut grad = vec![0.0; net.params().len()];
        net.backward(&x, &mut ws, &c, &mut grad).expect("backward");
        let (mut worst, mut checked) = (0.0f64, 0);
        for i in (0..net.params().len()).step_by(3) {
            let h = 1e-2f32;
            let keep = net.params()[i];
            net.params_mut()[i] = keep + h;
            let up = loss(&net, &x, &c);
            net.params_mut()[i] = keep - h;
            let down = loss(&net, &x, &c);
            net.params_mut()[i] = keep;
            let numeric = (up - down) / (2.0 * f64::from(h));
            let analytic = f64::from(grad[i]);
            let error = (numeric - analytic).abs() / (1e-2 + numeric.abs().max(analytic.abs()));
            // The network is piecewise linear in any one weight between ReLU kinks (and smooth
            // through the sigmoid): a kink inside the +-h window makes the difference quotient
            // wrong there, and shows as two one-sided quotients that differ; those are skipped.
            let centre = loss(&net, &x, &c);
            let one_sided = ((up - centre) / f64::from(h) - (centre - down) / f64::from(h)).abs();
            if one_sided > 5e-3 * (1.0 + numeric.abs()) {
                continue;
            }
            worst = worst.max(error);
            checked += 1;
        }
        assert!(checked > net.params().len() / 6, "only {checked} parameters checked");
        assert!(worst < 2e-2, "blocks {blocks} {act:?} {simd}: worst relative gradient error {worst}");
    }

    #[test]
    fn gradients_match_finite_differences() {
        for blocks in [0, 1, 3] {
            for act in [Activation::None, Activation::Sigmoid] {
                check_gradients(blocks, act, SimdMode::Auto);
            }
        }
        check_gradients(2, Activation::Sigmoid, SimdMode::Off);
        // A width of 16 fills the AVX2 tiles of the hidden layers (and their input gradient).
        for simd in [SimdMode::Auto, SimdMode::Off] {
            check_gradients_of(ResidualMlpConfig { width: 16, ..config(2, Activation::Sigmoid) }, simd);
        }
    }

    #[test]
    fn simd_and_scalar_agree_and_infer_matches_forward() {
        let mut net = ResidualMlp::new(config(4, Activation::Sigmoid), 5).expect("net");
        let x = inputs(9, 7, 1);
        let mut ws = ResidualWorkspace::new();
        let simd = net.forward(&x, &mut ws).expect("forward").to_vec();
        net.set_simd(SimdMode::Off);
        let mut out = vec![0.0; 9 * 4];
        net.infer(&x, &mut out, &mut ws).expect("infer");
        for (a, b) in simd.iter().zip(&out) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
        assert!(net.infer(&x[..8], &mut out, &mut ws).is_err());
        assert!(net.infer(&x, &mut out[..4], &mut ws).is_err());
    }

    #[test]
    fn shapes_counts_and_bad_configurations() {
        let c = ResidualMlpConfig { input: 10, width: 8, blocks: 2, output: 3, output_activation: Activation::None };
        assert_eq!(c.num_params(), 10 * 8 + 8 + 4 * (8 * 8 + 8) + 8 * 3 + 3);
        assert_eq!(c.macs_per_row(), 80 + 4 * 64 + 24);
        assert_eq!(c.layers(), 6);
        assert_eq!(c.flops_per_row(), 2 * c.macs_per_row() + 8 + 4 * 8 + 3 + 2 * 8);
        for bad in [
            ResidualMlpConfig { input: 0, ..c },
            ResidualMlpConfig { width: MAX_RESIDUAL_WIDTH + 1, ..c },
            ResidualMlpConfig { blocks: MAX_BLOCKS + 1, ..c },
        ] {
            assert!(ResidualMlp::new(bad, 1).is_err());
        }
        let net = ResidualMlp::new(c, 1).expect("net");
        let params = net.params().to_vec();
        assert_eq!(ResidualMlp::from_params(c, params.clone()).expect("same"), net);
        assert!(ResidualMlp::from_params(c, params[1..].to_vec()).is_err());
        let mut nan = params;
        nan[3] = f32::NAN;
        assert!(ResidualMlp::from_params(c, nan).is_err());
        let mut ws = ResidualWorkspace::new();
        assert!(net.backward(&[0.0; 10], &mut ws, &[0.0; 3], &mut vec![0.0; c.num_params()]).is_err());
    }

    #[test]
    fn a_deep_network_keeps_its_output_bounded_at_initialisation() {
        let c = ResidualMlpConfig { input: 32, width: 64, blocks: 32, output: 4, output_activation: Activation::None };
        let net = ResidualMlp::new(c, 2).expect("net");
        let x = inputs(16, 32, 4);
        let mut ws = ResidualWorkspace::new();
        let y = net.forward(&x, &mut ws).expect("forward");
        assert!(y.iter().all(|v| v.is_finite() && v.abs() < 50.0), "{y:?}");
    }
}
