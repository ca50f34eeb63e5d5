"""Image quality of renders against captured frames: PSNR and SSIM.

Both take colour images as uint8 ``[H, W, 3]`` (or floats in [0, 1]) and compare them in
[0, 1], the convention of the neural-SLAM papers (NICE-SLAM, CP-SLAM):

- PSNR = ``10 log10(1 / MSE)`` over all pixels and channels;
- SSIM (Wang et al. 2004) with an 11-tap Gaussian window of sigma 1.5, ``K1 = 0.01``,
  ``K2 = 0.03``, population (not sample) variances, averaged over the pixels whose window
  lies inside the image and over the channels; the same numbers as scikit-image's
  ``structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1, channel_axis=-1)``.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import correlate1d

__all__ = ["psnr", "ssim"]

SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # 11 taps: int(3.5 * sigma + 0.5), as scikit-image truncates the window
SSIM_K1, SSIM_K2 = 0.01, 0.03


def psnr(rendered: np.ndarray, reference: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB (inf for identical images)."""
    a, b = _pair(rendered, reference, "psnr")
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def ssim(rendered: np.ndarray, reference: np.ndarray) -> float:
    """Mean structural similarity in [-1, 1] (1 for identical images)."""
    a, b = _pair(rendered, reference, "ssim")
    if min(a.shape[:2]) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"ssim: images of {a.shape[1]}x{a.shape[0]} are smaller than the "
                         f"{2 * SSIM_RADIUS + 1}-pixel window")
    taps = np.exp(-0.5 * (np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1) / SSIM_SIGMA) ** 2)
    taps /= taps.sum()

    def blur(x: np.ndarray) -> np.ndarray:
        return correlate1d(correlate1d(x, taps, axis=0, mode="reflect"), taps, axis=1,
                           mode="reflect")

    c1, c2 = SSIM_K1**2, SSIM_K2**2
    means = []
    for ch in range(a.shape[2]):
        x, y = a[..., ch], b[..., ch]
        mx, my = blur(x), blur(y)
        vx = blur(x * x) - mx * mx
        vy = blur(y * y) - my * my
        cxy = blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        # Pixels whose window reaches past the border use reflected values: left out.
        r = SSIM_RADIUS
        means.append(s[r:-r, r:-r].mean())
    return float(np.mean(means))


def _pair(a: np.ndarray, b: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    a, b = _unit(np.asarray(a)), _unit(np.asarray(b))
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"{name}: images must both be [H, W, C], got {a.shape} and {b.shape}")
    return a, b


def _unit(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    return img.astype(np.float64)
