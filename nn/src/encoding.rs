//! Fixed input encodings: real spherical harmonics for directions (i-NGP's direction
//! encoding) and NeRF's frequency (positional) encoding.

/// Highest supported SH degree in tiny-cuda-nn's convention: degree `d` gives the `d^2`
/// coefficients of bands `0..d` (degree 4: bands 0-3, 16 values, i-NGP's choice; degree 5
/// adds band 4).
pub const SH_MAX_DEGREE: u32 = 5;

/// Number of SH values for `degree` (`degree^2`).
pub fn sh_coefficient_count(degree: u32) -> usize {
    (degree * degree) as usize
}

/// Real spherical harmonics of direction `dir` (normalised here; a zero or non-finite
/// direction is taken as +Z) into `out` (`degree^2` values, `1 <= degree <= 5`; longer
/// `out` is left untouched past that). Orthonormal on the unit sphere.
pub fn sh_encode(dir: [f32; 3], degree: u32, out: &mut [f32]) {
    let degree = degree.clamp(1, SH_MAX_DEGREE);
    debug_assert!(out.len() >= sh_coefficient_count(degree));
    let len = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
    let (x, y, z) =
        if len.is_finite() && len > 1e-20 { (dir[0] / len, dir[1] / len, dir[2] / len) } else { (0.0, 0.0, 1.0) };
    let (x2, y2, z2) = (x * x, y * y, z * z);
    out[0] = 0.282_094_8;
    if degree <= 1 {
        return;
    }
    out[1] = -0.488_602_52 * y;
    out[2] = 0.488_602_52 * z;
    out[3] = -0.488_602_52 * x;
    if degree <= 2 {
        return;
    }
    out[4] = 1.092_548_4 * x * y;
    out[5] = -1.092_548_4 * y * z;
    out[6] = 0.946_174_7 * z2 - 0.315_391_57;
    out[7] = -1.092_548_4 * x * z;
    out[8] = 0.546_274_2 * (x2 - y2);
    if degree <= 3 {
        return;
    }
    out[9] = 0.590_043_6 * y * (-3.0 * x2 + y2);
    out[10] = 2.890_611_4 * x * y * z;
    out[11] = 0.457_045_8 * y * (1.0 - 5.0 * z2);
    out[12] = 0.373_176_33 * z * (5.0 * z2 - 3.0);
    out[13] = 0.457_045_8 * x * (1.0 - 5.0 * z2);
    out[14] = 1.445_305_7 * z * (x2 - y2);
    out[15] = 0.590_043_6 * x * (-x2 + 3.0 * y2);
    if degree <= 4 {
        return;
    }
    out[16] = 2.503_343 * x * y * (x2 - y2);
    out[17] = 1.770_130_8 * y * z * (-3.0 * x2 + y2);
    out[18] = 0.946_174_7 * x * y * (7.0 * z2 - 1.0);
    out[19] = 0.669_046_5 * y * z * (7.0 * z2 - 3.0);
    out[20] = -3.173_566_4 * z2 + 3.702_494 * z2 * z2 + 0.317_356_64;
    out[21] = 0.669_046_5 * x * z * (7.0 * z2 - 3.0);
    out[22] = 0.473_087_34 * (x2 - y2) * (7.0 * z2 - 1.0);
    out[23] = 1.770_130_8 * x * z * (-x2 + 3.0 * y2);
    out[24] = -3.755_014_4 * x2 * y2 + 0.625_835_7 * x2 * x2 + 0.625_835_7 * y2 * y2;
}

/// Length of a frequency encoding of `dims` values with `frequencies` octaves.
pub fn frequency_encoded_len(dims: usize, frequencies: usize, include_input: bool) -> usize {
    dims * (2 * frequencies + usize::from(include_input))
}

/// NeRF's positional encoding (Mildenhall et al. 2020, eq. 4): for each value `x`,
/// optionally `x` itself, then `sin(2^k pi x), cos(2^k pi x)` for `k = 0..frequencies`.
/// Layout per value: `[x], sin_0, cos_0, sin_1, cos_1, ...`. Non-finite inputs encode as 0.
pub fn frequency_encode(values: &[f32], frequencies: usize, include_input: bool, out: &mut [f32]) {
    let per = 2 * frequencies + usize::from(include_input);
    debug_assert!(out.len() >= values.len() * per);
    for (i, &v) in values.iter().enumerate() {
        let v = if v.is_finite() { v } else { 0.0 };
        let o = &mut out[i * per..(i + 1) * per];
        let mut j = 0;
        if include_input {
            o[0] = v;
            j = 1;
        }
        // Reduce the argument in f64 so that high octaves of large inputs stay accurate.
        let mut arg = f64::from(v) * std::f64::consts::PI;
        for _ in 0..frequencies {
            let (s, c) = arg.sin_cos();
            o[j] = s as f32;
            o[j + 1] = c as f32;
            j += 2;
            arg *= 2.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spherical_harmonics_are_orthonormal() {
        // Fibonacci-sphere quadrature: accurate for the low-degree polynomials involved.
        let n = 20_000;
        let count = sh_coefficient_count(SH_MAX_DEGREE);
        let mut gram = vec![0.0f64; count * count];
        let mut y = vec![0.0f32; count];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            sh_encode([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32], SH_MAX_DEGREE, &mut y);
            for a in 0..count {
                for b in 0..count {
                    gram[a * count + b] += f64::from(y[a]) * f64::from(y[b]);
                }
            }
        }
        let area = 4.0 * std::f64::consts::PI / n as f64;
        for a in 0..count {
            for b in 0..count {
                let v = gram[a * count + b] * area;
                let expected = if a == b { 1.0 } else { 0.0 };
                assert!((v - expected).abs() < 2e-3, "<Y{a}, Y{b}> = {v}");
            }
        }
    }

    #[test]
    fn degenerate_directions_are_finite_and_scale_free() {
        let mut a = [0.0f32; 16];
        let mut b = [0.0f32; 16];
        sh_encode([0.0, 0.0, 0.0], 4, &mut a);
        sh_encode([f32::NAN, 1.0, 0.0], 4, &mut b);
        assert!(a.iter().chain(&b).all(|v| v.is_finite()));
        sh_encode([1.0, 2.0, -3.0], 4, &mut a);
        sh_encode([10.0, 20.0, -30.0], 4, &mut b);
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-5);
        }
        // Degree 1 writes only the constant.
        let mut c = [7.0f32; 4];
        sh_encode([1.0, 0.0, 0.0], 1, &mut c);
        assert_eq!(c[1..], [7.0; 3]);
    }

    #[test]
    fn frequency_encoding_layout() {
        let mut out = vec![0.0; frequency_encoded_len(2, 3, true)];
        assert_eq!(out.len(), 14);
        frequency_encode(&[0.5, f32::INFINITY], 3, true, &mut out);
        assert_eq!(out[0], 0.5);
        assert!((out[1] - 1.0).abs() < 1e-6 && out[2].abs() < 1e-6); // sin(pi/2), cos(pi/2)
        assert!(out[3].abs() < 1e-6 && (out[4] + 1.0).abs() < 1e-6); // sin(pi), cos(pi)
        assert_eq!(out[7], 0.0); // non-finite input encodes as 0
        assert!((out[9] - 1.0).abs() < 1e-6); // cos(0)
    }
}
