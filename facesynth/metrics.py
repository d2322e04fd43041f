"""Image and parameter metrics shared by every evaluation in facesynth."""

from __future__ import annotations

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


def ncc(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per-column normalised cross-correlation (Pearson r) of two (N, K) arrays -> (K,)."""
    p = np.asarray(pred, np.float64)
    t = np.asarray(true, np.float64)
    p = p - p.mean(0)
    t = t - t.mean(0)
    den = np.sqrt((p**2).sum(0) * (t**2).sum(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (p * t).sum(0) / den, 0.0)
