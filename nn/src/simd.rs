//! Run-time choice of the instruction set for the numeric kernels.
//!
//! `pulp::Arch::dispatch` checks the CPU once and runs a generic kernel compiled for AVX2 and
//! FMA (x86-64-v3) where the CPU has them, through a safe API: no `unsafe` here, and the
//! binary still runs on a CPU without AVX2 (it takes the scalar instantiation). The same
//! generic code is instantiated for [`pulp::Scalar`], one `f32` per "vector", with `a * b + c`
//! unfused: [`SimdMode::Off`] runs that, so the speed-up of the vector code is measured in
//! one run of one binary (`--simd off`).

use std::fmt;
use std::str::FromStr;

pub use pulp::{Arch, Simd, WithSimd};

/// Hints to the CPU that an element will be read soon: `prefetcht0` on x86-64 through pulp's
/// safe wrapper of the instruction, nothing elsewhere or when made with [`Prefetch::off`].
/// For loops whose reads miss the cache and whose addresses are known some iterations ahead
/// (the i-NOLF heads' perfect-hash tables). A hint never changes a result.
#[derive(Debug, Clone, Copy)]
pub struct Prefetch {
    #[cfg(target_arch = "x86_64")]
    sse: Option<pulp::core_arch::x86::Sse>,
}

impl Prefetch {
    /// Hints where the CPU takes them.
    pub fn new() -> Prefetch {
        Prefetch {
            #[cfg(target_arch = "x86_64")]
            sse: pulp::core_arch::x86::Sse::try_new(),
        }
    }

    /// No hints (for comparisons).
    pub fn off() -> Prefetch {
        Prefetch {
            #[cfg(target_arch = "x86_64")]
            sse: None,
        }
    }

    /// Hints that `data[index]` will be read soon; an index past the end hints nothing.
    #[inline(always)]
    pub fn element<T>(&self, data: &[T], index: usize) {
        #[cfg(target_arch = "x86_64")]
        if let (Some(sse), Some(item)) = (self.sse, data.get(index)) {
            sse._mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>((item as *const T).cast());
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (data, index);
    }
}

impl Default for Prefetch {
    fn default() -> Self {
        Prefetch::new()
    }
}

/// Which instruction set the kernels use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SimdMode {
    /// The widest set the CPU has (AVX2 + FMA on x86-64 where present), else scalar.
    #[default]
    Auto,
    /// Scalar code (the same generic kernels, one lane wide, no fused multiply-add).
    Off,
}

impl SimdMode {
    /// The dispatcher for this mode on this CPU.
    #[inline]
    pub fn arch(self) -> Arch {
        match self {
            SimdMode::Auto => Arch::new(),
            SimdMode::Off => Arch::Scalar,
        }
    }

    /// Runs `f` under this mode's dispatch. Beware: a closure is a function of its own, and
    /// LLVM may compile it apart, for the baseline, instead of inlining it into pulp's
    /// `#[target_feature]` function (a large one it does: the i-NOLF render chunk's closure
    /// had not one VEX instruction). For a hot kernel implement [`WithSimd`] with an
    /// `#[inline(always)]` `with_simd` and call `self.arch().dispatch(op)`, as
    /// `nephele_kernels::inolf::kernel::Chunk` does.
    #[inline(always)]
    pub fn run<R>(self, f: impl FnOnce() -> R) -> R {
        self.arch().dispatch(f)
    }

    /// What this mode runs on this CPU, for reports: "scalar" or "AVX2+FMA" (x86-64) or
    /// "SIMD" (another architecture's vector set).
    pub fn describe(self) -> &'static str {
        match self.arch() {
            Arch::Scalar => "scalar",
            #[allow(unreachable_patterns)]
            _ => {
                if cfg!(any(target_arch = "x86_64", target_arch = "x86")) {
                    "AVX2+FMA"
                } else {
                    "SIMD"
                }
            }
        }
    }
}

impl fmt::Display for SimdMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            SimdMode::Auto => "auto",
            SimdMode::Off => "off",
        })
    }
}

/// Not `auto` or `off`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("'{0}' is not a SIMD mode (auto or off)")]
pub struct BadSimdMode(String);

impl FromStr for SimdMode {
    type Err = BadSimdMode;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" | "on" => Ok(SimdMode::Auto),
            "off" | "scalar" => Ok(SimdMode::Off),
            other => Err(BadSimdMode(other.to_string())),
        }
    }
}

/// `y[j] += a * x[j]` (fused where the instruction set has FMA).
#[inline(always)]
pub fn axpy<S: Simd>(simd: S, y: &mut [f32], a: f32, x: &[f32]) {
    let n = y.len().min(x.len());
    let (yh, yt) = S::as_mut_simd_f32s(&mut y[..n]);
    let (xh, xt) = S::as_simd_f32s(&x[..n]);
    let av = simd.splat_f32s(a);
    for (y, x) in yh.iter_mut().zip(xh) {
        *y = simd.mul_add_e_f32s(av, *x, *y);
    }
    for (y, x) in yt.iter_mut().zip(xt) {
        *y += a * x;
    }
}

/// Dot product with four independent vector accumulators (four scalar ones when scalar).
#[inline(always)]
pub fn dot<S: Simd>(simd: S, a: &[f32], b: &[f32]) -> f32 {
    let n = a.len().min(b.len());
    let (ah, at) = S::as_simd_f32s(&a[..n]);
    let (bh, bt) = S::as_simd_f32s(&b[..n]);
    let zero = simd.splat_f32s(0.0);
    let mut acc = [zero; 4];
    let (a4, ar) = (ah.chunks_exact(4), ah.chunks_exact(4).remainder());
    let (b4, br) = (bh.chunks_exact(4), bh.chunks_exact(4).remainder());
    for (x, y) in a4.zip(b4) {
        for k in 0..4 {
            acc[k] = simd.mul_add_e_f32s(x[k], y[k], acc[k]);
        }
    }
    for (k, (x, y)) in ar.iter().zip(br).enumerate() {
        acc[k] = simd.mul_add_e_f32s(*x, *y, acc[k]);
    }
    let sum = simd.add_f32s(simd.add_f32s(acc[0], acc[1]), simd.add_f32s(acc[2], acc[3]));
    let mut s = simd.reduce_sum_f32s(sum);
    for (x, y) in at.iter().zip(bt) {
        s += x * y;
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Both<'a>(&'a [f32], &'a [f32]);
    impl WithSimd for Both<'_> {
        type Output = (f32, Vec<f32>);
        #[inline(always)]
        fn with_simd<S: Simd>(self, simd: S) -> Self::Output {
            let mut y = self.1.to_vec();
            axpy(simd, &mut y, 0.5, self.0);
            (dot(simd, self.0, self.1), y)
        }
    }

    #[test]
    fn vector_and_scalar_agree_on_every_length() {
        for n in 0..70 {
            let a: Vec<f32> = (0..n).map(|i| ((i * 37 % 11) as f32 - 5.0) / 3.0).collect();
            let b: Vec<f32> = (0..n).map(|i| ((i * 13 % 7) as f32 - 3.0) / 2.0).collect();
            let exact: f64 = a.iter().zip(&b).map(|(x, y)| f64::from(*x) * f64::from(*y)).sum();
            let (d_auto, y_auto) = SimdMode::Auto.arch().dispatch(Both(&a, &b));
            let (d_off, y_off) = SimdMode::Off.arch().dispatch(Both(&a, &b));
            assert!((f64::from(d_auto) - exact).abs() < 1e-4, "{n}: {d_auto} vs {exact}");
            assert!((f64::from(d_off) - exact).abs() < 1e-4, "{n}: {d_off} vs {exact}");
            for i in 0..n {
                let want = b[i] + 0.5 * a[i];
                assert!((y_auto[i] - want).abs() < 1e-6 && (y_off[i] - want).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn modes_parse_and_describe() {
        assert_eq!("auto".parse(), Ok(SimdMode::Auto));
        assert_eq!("OFF".parse(), Ok(SimdMode::Off));
        assert!("avx9".parse::<SimdMode>().is_err());
        assert_eq!(SimdMode::Off.describe(), "scalar");
        assert_eq!(SimdMode::Auto.to_string(), "auto");
    }
}
