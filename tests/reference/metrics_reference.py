#!/usr/bin/env python3
"""Reference PSNR and SSIM figures for the unit tests in src/metrics/.

Not run by CI. Run it by hand after changing the test images:

    pip install scikit-image numpy
    python3 tests/reference/metrics_reference.py

It builds small deterministic RGB images from closed-form formulas (no random
number generator, so that the Rust tests can rebuild them bit for bit), scores
pairs of them with scikit-image, and cross-checks scikit-image's SSIM against
a direct numpy implementation of the definition zrak uses (11x11 Gaussian
window, sigma 1.5, 'valid' filtering, population variances).

Every pixel value is computed in float64 with Python's `math` functions (the
same C library functions Rust's f64::sin/cos call), then rounded to float32,
because zrak's RgbImage stores f32. The float32 values are then widened back to
float64 before scoring, since scikit-image computes in float32 when handed
float32 arrays, whereas zrak always computes in f64.
"""

import math

import numpy as np
import skimage
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

MASK32 = 0xFFFFFFFF


def hash32(x, y, c, seed):
    """An integer hash on wrapping u32 arithmetic, mirrored in the Rust tests."""
    h = (x * 0x9E3779B1) & MASK32
    h ^= (y * 0x85EBCA77) & MASK32
    h ^= (c * 0xC2B2AE3D) & MASK32
    h ^= (seed * 0x27D4EB2F) & MASK32
    h ^= h >> 16
    h = (h * 0x7FEB352D) & MASK32
    h ^= h >> 15
    h = (h * 0x846CA68B) & MASK32
    h ^= h >> 16
    return h


def noise(x, y, c, seed):
    """A value in [0, 1) from the top 24 bits of the hash (exact in f64)."""
    return (hash32(x, y, c, seed) >> 8) / 16777216.0


def clamp01(v):
    return min(max(v, 0.0), 1.0)


def gradient(x, y, c, w, h):
    return (x + 0.5) / w * 0.6 + (y + 0.5) / h * 0.3 + 0.05 * c


def texture(x, y, c, w, h):
    return (
        0.5
        + 0.3 * math.sin(0.7 * x + 0.9 * c) * math.cos(0.45 * y)
        + 0.15 * math.sin(0.11 * (x + y) + c)
    )


def checker(x, y, c, w, h):
    return 0.85 if (x // 4 + y // 4 + c) % 2 == 0 else 0.15


# Each pair: name, width, height, formula for image a, formula for image b.
# The b formulas perturb a in the ways a rendered view differs from its
# ground truth: additive noise, contrast and brightness change, blending with
# something unrelated, or being something else entirely.
PAIRS = [
    (
        "gradient_noisy",
        16,
        16,
        gradient,
        lambda x, y, c, w, h: clamp01(gradient(x, y, c, w, h) + 0.1 * (noise(x, y, c, 7) - 0.5)),
    ),
    (
        "texture_contrast",
        23,
        19,
        texture,
        lambda x, y, c, w, h: 0.8 * texture(x, y, c, w, h) + 0.1 + 0.05 * (noise(x, y, c, 3) - 0.5),
    ),
    (
        "checker_blend",
        32,
        32,
        checker,
        lambda x, y, c, w, h: 0.7 * checker(x, y, c, w, h) + 0.3 * noise(x, y, c, 11),
    ),
    (
        "noise_vs_noise",
        32,
        32,
        lambda x, y, c, w, h: noise(x, y, c, 1),
        lambda x, y, c, w, h: noise(x, y, c, 2),
    ),
    ("texture_vs_gradient", 19, 23, texture, gradient),
    (
        "minimum_size",
        11,
        11,
        texture,
        lambda x, y, c, w, h: noise(x, y, c, 5),
    ),
]


def build(formula, w, h):
    """An (h, w, 3) image: values computed in f64, stored as f32, scored as f64."""
    img = np.empty((h, w, 3), dtype=np.float32)
    for y in range(h):
        for x in range(w):
            for c in range(3):
                img[y, x, c] = np.float32(formula(x, y, c, w, h))
    return img.astype(np.float64)


def gaussian_taps(sigma=1.5, radius=5):
    t = np.exp(-0.5 * (np.arange(-radius, radius + 1, dtype=np.float64) / sigma) ** 2)
    return t / t.sum()


def valid_filter(plane, taps):
    """Separable correlation without padding: (H, W) -> (H-10, W-10)."""
    n = len(taps)
    h, w = plane.shape
    rows = sum(taps[k] * plane[:, k : w - n + 1 + k] for k in range(n))
    return sum(taps[k] * rows[k : h - n + 1 + k, :] for k in range(n))


def ssim_valid(a, b):
    """SSIM written straight from the definition, independent of scikit-image."""
    taps = gaussian_taps()
    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for c in range(a.shape[2]):
        x, y = a[:, :, c], b[:, :, c]
        mx, my = valid_filter(x, taps), valid_filter(y, taps)
        vx = valid_filter(x * x, taps) - mx * mx
        vy = valid_filter(y * y, taps) - my * my
        cxy = valid_filter(x * y, taps) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        per_channel.append(s.mean())
    return float(np.mean(per_channel))


def main():
    print(f"scikit-image {skimage.__version__}, numpy {np.__version__}")
    worst = 0.0
    for name, w, h, fa, fb in PAIRS:
        a, b = build(fa, w, h), build(fb, w, h)
        psnr = peak_signal_noise_ratio(a, b, data_range=1.0)
        ssim = structural_similarity(
            a,
            b,
            channel_axis=-1,
            data_range=1.0,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
        mine = ssim_valid(a, b)
        worst = max(worst, abs(ssim - mine))
        # repr gives the shortest decimal that round-trips to the same f64
        # (16-17 significant digits), so the Rust literals are exact.
        print(
            f"{name:20s} {w}x{h}  psnr {float(psnr)!r}  ssim {float(ssim)!r}"
            f"  (numpy valid-filter ssim {mine!r}, diff {abs(ssim - mine):.1e})"
        )
    print(f"largest |skimage - valid-filter| SSIM difference: {worst:.1e}")


if __name__ == "__main__":
    main()
