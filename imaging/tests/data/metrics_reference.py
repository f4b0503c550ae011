#!/usr/bin/env python3
"""Reference PSNR/SSIM numbers for the tests of `nephele-imaging`'s `metrics` module.

Run with scikit-image and numpy installed (`pip install scikit-image numpy`):

    python3 imaging/tests/data/metrics_reference.py

It prints the constants pasted into `imaging/src/metrics.rs` (`mod tests`). The Rust test
regenerates exactly the same input images from the same integer formulas (see `test_level` and
`reference_case` there): every pixel value is an 8-bit level `k / 255` computed with integer
arithmetic only, then rounded to float32 as the Rust `RgbaImage` stores it, so both sides see
bit-identical inputs. Keep this file and the Rust generator in step.
"""

import numpy as np
import skimage
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

MASK = 0xFFFFFFFF


def hash32(x):
    """'lowbias32' integer hash (Chris Wellons), on u32 with wrapping multiplication."""
    x &= MASK
    x ^= x >> 16
    x = (x * 0x7FEB352D) & MASK
    x ^= x >> 15
    x = (x * 0x846CA68B) & MASK
    x ^= x >> 16
    return x


def h(i, j, c, seed):
    return hash32((seed << 24) ^ (j << 12) ^ (i << 2) ^ c)


def clamp255(v):
    return max(0, min(255, v))


def level_a(i, j, c):
    """The 'ground truth' image: a structured pattern plus hash noise."""
    base = (i * i * (c + 2) + j * 7 * (3 - c) + 31 * c) % 256
    noise = h(i, j, c, 1) % 41 - 20
    return clamp255(base + noise)


def level_b(i, j, c, w, hgt):
    """The 'prediction': a 3x3 box blur of A (clamp-to-edge), plus noise and a small offset."""
    s = 0
    for dj in (-1, 0, 1):
        for di in (-1, 0, 1):
            ii = min(max(i + di, 0), w - 1)
            jj = min(max(j + dj, 0), hgt - 1)
            s += level_a(ii, jj, c)
    return clamp255(s // 9 + h(i, j, c, 2) % 21 - 10 + 3 * c)


def level_c(i, j, c):
    """A mildly degraded A: small hash noise only (a high-SSIM case)."""
    return clamp255(level_a(i, j, c) + h(i, j, c, 5) % 7 - 3)


def alpha_a(i, j, w):
    return 255 if i < w // 2 else h(i, j, 3, 3) % 256


def alpha_b(i, j, w):
    return 255 if i < w // 2 else clamp255(alpha_a(i, j, w) + h(i, j, 3, 4) % 31 - 15)


def to_f32_levels(k):
    # The Rust side stores k / 255 as f32 (what a PNG load gives), then widens to f64.
    return (np.asarray(k, dtype=np.float32) / np.float32(255.0)).astype(np.float64)


def rgba_pair(w, hgt, mild=False):
    a = np.zeros((hgt, w, 4), dtype=np.int64)
    b = np.zeros((hgt, w, 4), dtype=np.int64)
    for j in range(hgt):
        for i in range(w):
            for c in range(3):
                a[j, i, c] = level_a(i, j, c)
                b[j, i, c] = level_c(i, j, c) if mild else level_b(i, j, c, w, hgt)
            a[j, i, 3] = alpha_a(i, j, w)
            b[j, i, 3] = alpha_b(i, j, w)
    return to_f32_levels(a), to_f32_levels(b)


def composite(img, bg):
    rgb, alpha = img[..., :3], img[..., 3:4]
    return rgb * alpha + np.asarray(bg, dtype=np.float64) * (1.0 - alpha)


def metrics(gt, pred):
    psnr = peak_signal_noise_ratio(gt, pred, data_range=1.0)
    ssim = structural_similarity(
        gt,
        pred,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )
    return psnr, ssim


def main():
    print(f"# scikit-image {skimage.__version__}, numpy {np.__version__}")
    # (name, width, height, mild, use_alpha, background); must match `REFERENCE_CASES` in Rust.
    cases = [
        ("OPAQUE_24X20", 24, 20, False, False, None),
        ("OPAQUE_32X32", 32, 32, False, False, None),
        ("MILD_32X32", 32, 32, True, False, None),
        ("ALPHA_17X23_WHITE", 17, 23, False, True, (1.0, 1.0, 1.0)),
        ("ALPHA_17X23_BLACK", 17, 23, False, True, (0.0, 0.0, 0.0)),
    ]
    for name, w, hgt, mild, use_alpha, bg in cases:
        a, b = rgba_pair(w, hgt, mild)
        if use_alpha:
            ga, gb = composite(a, bg), composite(b, bg)
        else:
            ga, gb = a[..., :3], b[..., :3]
        psnr, ssim = metrics(ga, gb)
        print(f"const {name}: (f64, f64) = ({float(psnr)!r}, {float(ssim)!r});")
    # Sanity values: identical images.
    a, _ = rgba_pair(24, 20)
    with np.errstate(divide="ignore"):
        print("# identical images:", [float(v) for v in metrics(a[..., :3], a[..., :3].copy())])


if __name__ == "__main__":
    main()
