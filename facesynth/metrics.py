"""Image and parameter metrics shared by every evaluation in facesynth."""

from __future__ import annotations

import cv2
import numpy as np

from facesynth.errors import FacesynthError


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, peak: float = 255.0) -> float:
    """Peak signal-to-noise ratio in dB over a mask, pooled over all images.

    Parameters
    ----------
    a, b : np.ndarray
        Same shape, (..., H, W, C) or (..., H, W); any numeric dtype (compared as float64).
    mask : np.ndarray, optional
        Boolean, broadcastable to ``a`` over its leading and channel axes: (H, W),
        (..., H, W) or (..., H, W, 1). Only True pixels count.
    peak : float
        Peak value (255 for 8-bit images, 65535 for 16-bit geometry images).

    Returns
    -------
    float
        ``10 log10(peak^2 / MSE)``; ``inf`` when the images are equal on the mask.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise FacesynthError(f"psnr: shapes differ {a.shape} vs {b.shape}")
    err = (a - b) ** 2
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.ndim < err.ndim and m.shape == err.shape[-m.ndim - 1 : -1]:
            m = m[..., None]  # (H, W) mask for (..., H, W, C) images
        m = np.broadcast_to(m, err.shape)
        err = err[m]
    mse = float(err.mean()) if err.size else float("nan")
    return float("inf") if mse == 0 else 10.0 * np.log10(peak**2 / mse)


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, peak: float = 255.0) -> float:
    """Structural similarity (Wang, Bovik, Sheikh, Simoncelli, IEEE TIP 2004): 11 x 11
    Gaussian window, sigma 1.5, K1 = 0.01, K2 = 0.03; the SSIM map of each channel, averaged
    over the channels and the True pixels of ``mask``.

    a, b : (H, W) or (H, W, C), any numeric dtype; mask : bool (H, W), optional.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim not in (2, 3):
        raise FacesynthError(f"ssim: expected two (H, W) or (H, W, C) images of one shape, got {a.shape} and {b.shape}")
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2

    def blur(x):
        return cv2.GaussianBlur(x, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    smap = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    if smap.ndim == 3:
        smap = smap.mean(-1)
    if mask is not None:
        smap = smap[np.asarray(mask, bool)]
    return float(smap.mean()) if smap.size else float("nan")


def ncc(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per-column normalised cross-correlation (Pearson r) of two (N, K) arrays -> (K,)."""
    p = np.asarray(pred, np.float64)
    t = np.asarray(true, np.float64)
    p = p - p.mean(0)
    t = t - t.mean(0)
    den = np.sqrt((p**2).sum(0) * (t**2).sum(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (p * t).sum(0) / den, 0.0)
